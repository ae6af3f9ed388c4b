"""bench.unseen: scenes drawn outside the presets, and its verdict on them."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.unseen import _distance_to_ray, draw_scene, report
from sim.presets import PRESETS, world_clock

ROOT = Path(__file__).resolve().parents[2]
SCENES = range(60)


def test_a_scene_number_always_draws_the_same_scene_and_another_number_another() -> None:
    assert draw_scene(7) == draw_scene(7)
    assert len({repr(draw_scene(n)) for n in range(10)}) == 10
    assert not {draw_scene(n).name for n in SCENES} & set(PRESETS)


@pytest.mark.parametrize("number", SCENES)
def test_drawn_cameras_stand_beside_the_road_and_see_near_the_junction(number: int) -> None:
    scene = draw_scene(number)
    half_width = scene.road.lanes_per_direction * scene.road.lane_width_m + 4.0
    latency = world_clock(scene).latency_s
    assert 0.0 <= latency[0] == latency[1] <= 0.45
    for camera in scene.cameras:
        assert 5.0 <= camera.height_m <= 16.0
        assert 8.0 <= camera.pitch_down_deg <= 50.0
        for arm in scene.road.arms:
            assert _distance_to_ray(camera.x_m, camera.y_m, math.radians(arm.angle_deg)) >= half_width
        # The lens never folds back inside the image: the radial polynomial grows out to its corner.
        k1, k2, _, _, k3 = camera.dist
        corner = math.hypot(camera.width, camera.height) / 2.0 / camera.fx
        r = np.linspace(0.0, corner, 100)
        assert np.all(np.diff(r * (1.0 + k1 * r**2 + k2 * r**4 + k3 * r**6)) > 0.0)


def _run(verdict: str, position_m: float, rotation_deg: float, scene: str = "unseen-0") -> dict[str, object]:
    return {
        "preset": scene,
        "seed": 0,
        "camera": "cam0",
        "verdict": verdict,
        "reasons": [] if verdict == "accepted" else ["position std = 0.3 m"],
        "position_error_m": position_m,
        "rotation_error_deg": rotation_deg,
        "position_std_m": 0.1,
        "rotation_std_deg": 0.1,
        "time_offset_error_ms": 4.0,
    }


def test_the_report_fails_on_a_false_accept_or_an_error_and_passes_on_refusals() -> None:
    fine = [_run("accepted", 0.12, 0.1), _run("refused", 3.0, 9.0, "unseen-1")]
    text, passed = report(fine)
    assert passed
    assert "2 cameras in 2 scenes: 1 accepted, 0 false accepts, 0 errors" in text
    assert "accepted: position mean 0.120 m, max 0.120 m" in text
    text, passed = report([*fine, _run("accepted", 0.62, 0.1, "unseen-2")])
    assert not passed and "1 false accepts" in text
    error = {**_run("error", 0.0, 0.0), "error": "ValueError: x", "position_error_m": None}
    text, passed = report([*fine, error])
    assert not passed and "ERROR unseen-0 cam0: ValueError: x" in text


def test_bad_options_are_refused_before_any_scene_runs() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "bench.unseen", "--scenes", "0"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert "--scenes and --jobs must be >= 1" in done.stderr and "Traceback" not in done.stderr
