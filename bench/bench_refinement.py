"""Refinement benchmark (stage 5): bias on exact data and speed. Not part of the test suite.

    python bench/bench_refinement.py

Prints, for starts perturbed from the truth, the mean delta_p and pose errors of the paper's one-shot
bottom-edge refinement, the iterated bottom-edge refinement and the whole-box refinement on exact boxes,
then the whole-box covariance of a single straight road vs a junction, then timings on ~1000 boxes.
The synthetic scenes are the ones of tests/pipeline/test_refinement.py.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "pipeline"))

import test_refinement as scene

from pipeline.refinement import Refinement, RefinementParams, refine_bottom_edge, refine_whole_box

SEEDS = 20


def bias_table() -> None:
    for fx, k1 in ((1000.0, 0.0), (800.0, -0.05)):
        camera = scene.make_camera(fx, k1)
        truth = scene.camera_pose(*scene.STANDARD)
        tracks = scene.exact_tracks(scene.junction_paths(), truth, camera)
        ground = scene.track_ground(tracks)
        for shift_m, angle_deg in ((0.5, 2.0), (0.2, 0.5)):
            rows: dict[str, list[tuple[float, float, float]]] = {}
            starts = []
            for seed in range(SEEDS):
                start = scene.perturbed(truth, np.random.default_rng(seed), shift_m, angle_deg)
                starts.append(scene.start_delta_p(tracks, start, camera, ground))
                R0, t0 = start
                runs = {
                    "paper one-shot": refine_bottom_edge(
                        R0,
                        t0,
                        tracks,
                        camera,
                        scene.VEHICLE,
                        ground,
                        RefinementParams(iterate_correspondences=False),
                    ),
                    "paper 10 rounds": refine_bottom_edge(
                        R0,
                        t0,
                        tracks,
                        camera,
                        scene.VEHICLE,
                        ground,
                        RefinementParams(iterate_correspondences=False, paper_rounds=10),
                    ),
                    "iterated bottom": refine_bottom_edge(
                        R0, t0, tracks, camera, scene.VEHICLE, ground, RefinementParams()
                    ),
                    "whole box": refine_whole_box(
                        R0, t0, tracks, camera, scene.VEHICLE, RefinementParams(), ground=ground
                    ),
                }
                for name, result in runs.items():
                    position_m, rotation_deg = scene.pose_errors(result, truth)
                    rows.setdefault(name, []).append(
                        (float(np.nanmean(result.delta_p_m)), position_m, rotation_deg)
                    )
            print(
                f"fx {fx:.0f} k1 {k1}: start {shift_m} m / {angle_deg} deg, "
                f"start delta_p mean {np.mean(starts):.3f} m"
            )
            for name, values in rows.items():
                a = np.array(values)
                print(
                    f"  {name:16s} delta_p mean {a[:, 0].mean():.4f} m   "
                    f"centre error mean {a[:, 1].mean():.4f} m   rotation error mean {a[:, 2].mean():.4f} deg"
                )


def covariance_table() -> None:
    camera = scene.make_camera(fx=3000.0)
    truth = scene.camera_pose((0.0, 0.0, 10.0), 0.0, math.degrees(math.atan2(10.0, 110.0)))
    road = np.array([1.0, 0.0, 0.0])
    scenes = {
        "one straight road": [
            scene.straight((60.0, 3.0), (200.0, 3.0)),
            scene.straight((200.0, 3.0), (60.0, 3.0)),
            scene.straight((65.0, 3.0), (190.0, 3.0), 1.3),
        ],
        "junction": [
            scene.straight((60.0, 3.0), (200.0, 3.0)),
            scene.straight((110.0, -40.0), (110.0, 40.0)),
            scene.left_turn((60.0, -2.0), 40.0, 12.0, 40.0),
        ],
    }
    R_true, t_true = truth
    for name, paths in scenes.items():
        result = refine_whole_box(
            R_true,
            t_true,
            scene.exact_tracks(paths, truth, camera),
            camera,
            scene.VEHICLE,
            RefinementParams(min_sigma_px=1.0),
        )
        about_road = math.degrees(math.sqrt(road @ result.covariance[:3, :3] @ road))
        print(
            f"telephoto, {name:18s} sigma 1 px: rotation std about the road {about_road:.4f} deg, "
            f"rotation std {result.rotation_std_deg:.4f} deg, position std {result.position_std_m:.4f} m, "
            f"worst direction std {result.worst_std_m:.4f} m, worst {np.round(result.worst_direction, 2)}"
        )


def timings() -> None:
    camera = scene.make_camera()
    truth = scene.camera_pose(*scene.STANDARD)
    tracks = scene.exact_tracks(scene.junction_paths(step_m=0.15), truth, camera)
    ground = scene.track_ground(tracks)
    R0, t0 = scene.perturbed(truth, np.random.default_rng(1))
    count = sum(len(tr.boxes) for tr in tracks)
    calls: dict[str, Callable[[], Refinement]] = {
        "whole box": lambda: refine_whole_box(R0, t0, tracks, camera, scene.VEHICLE, RefinementParams()),
        "iterated bottom": lambda: refine_bottom_edge(
            R0, t0, tracks, camera, scene.VEHICLE, ground, RefinementParams()
        ),
        "paper one-shot": lambda: refine_bottom_edge(
            R0, t0, tracks, camera, scene.VEHICLE, ground, RefinementParams(iterate_correspondences=False)
        ),
    }
    for name, call in calls.items():
        times = []
        for _ in range(7):
            begin = time.perf_counter()
            result = call()
            times.append(time.perf_counter() - begin)
        print(
            f"{name:16s} {count} boxes: min {1e3 * min(times):.1f} ms, "
            f"median {1e3 * np.median(times):.1f} ms, {result.iterations} evaluations"
        )


if __name__ == "__main__":
    bias_table()
    covariance_table()
    timings()
