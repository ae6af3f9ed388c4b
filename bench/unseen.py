"""Scenes no preset describes: right or refused where rsucal was never tuned. Not part of the test suite.

    python -m bench.unseen [--scenes 40] [--first-scene 0] [--jobs 2] [--json out.json]

rsucal is judged on scenes it never saw: other masts, lenses, latencies, roads and vehicles. The presets are
the scenes the method was developed on; this benchmark draws new ones, one per scene number, from ranges an
operator meets (all in the realistic world: shaped bodies, a biased detector, CAM V2X from an RTK receiver):

  site       one of the simulator's five UTM sites
  road       the four junction and road layouts, 1 or 2 lanes each way; terrain slope up to 4 % each way,
             crown 1-3 %, banked bends 2-6 %, vertical curves (crests and sags) and bumps on some
  cameras    1 or 2 on one mast beside the road, 5-16 m up, 12-55 m from where they look (near the
             junction), tilted 8-50 deg down; 720p to 1440p, 45-100 deg horizontal field of view, radial
             distortion growing with the field of view (never folding inside the image), principal point up
             to 10 px off, rolled up to 6 deg on some, portrait on a few
  clock      latency 0-450 ms with 1-6 ms jitter, clock drift up to 10 ppm, the vehicle's clock up to 50 ms
             off; rolling shutters as the realistic world draws them
  detector   10-30 fps, box jitter 0.8-2.5 px, misses and false positives (the realistic world's floor
             applies on top), a night-like detector on some
  vehicle    the calibration vehicle's body type: sedan, hatchback, estate, suv, van, pickup (rarely a
             truck or bus); 3 or 4 drive-pasts on random routes with 1-4 followers; 30-250 other vehicles;
             RTK float periods on some

A scene's number seeds both its drawing and its simulation, so `--first-scene K --scenes 1` repeats scene K.
Per camera: calibrate() with the truth's vehicle clock offset unknown (as bench.accuracy), scored by
pipeline.metrics. Printed: one line per camera (scene, verdict, errors, stds, the first reason), then the
accepted share, the false accepts (accepted more than 0.5 m or 0.5 deg off), the accuracy of the accepted
runs, and how many poses within 1 m / 1 deg lie beyond 3 of their reported stds.
Exit code 0 when no run is falsely accepted and none raised, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench.accuracy import Run, _fmt, _is_accepted, coverage_line, is_false_accept, run_tasks
from bench.common import limit_threads, tree_state

if TYPE_CHECKING:
    import numpy as np

    from sim.presets import ArmSpec, CameraSpec, RoadSpec, ScenarioConfig

BODY_TYPES = ("sedan", "hatchback", "estate", "suv", "van", "pickup")
RARE_BODY_TYPES = ("truck", "bus")
IMAGE_SIZES = ((1280, 720), (1920, 1080), (1920, 1200), (2560, 1440))
FRAME_RATES = (10.0, 12.5, 15.0, 20.0, 25.0, 30.0)


def draw_scene(number: int) -> ScenarioConfig:
    """Scene `number`, drawn from the ranges in the module docstring (the same number, the same scene)."""
    import numpy as np

    from sim import presets as p

    rng = np.random.default_rng([number, 0x5CE4E])
    lanes = int(rng.integers(1, 3))
    layout = [p.SIL_JUNCTION, p.PLAIN_JUNCTION, p.SKEWED_JUNCTION, p.STRAIGHT_ROAD][int(rng.integers(0, 4))]
    road = replace(layout, lanes_per_direction=lanes)
    arms = road.arms
    names = [arm.name for arm in arms]

    n_routes = int(rng.integers(3, 5))
    if len(arms) == 2:
        routes = tuple(f"{names[i % 2]}>{names[(i + 1) % 2]}" for i in range(n_routes))
    else:
        routes = tuple(">".join(rng.choice(names, size=2, replace=False)) for _ in range(n_routes))
    followers = (1, 2) if rng.random() < 0.6 else (2, 4)

    half_width = lanes * road.lane_width_m + 4.0  # carriageway, kerb and footway
    mast = _beside_the_road(rng, arms, half_width, (14.0, 45.0))
    mast_height = float(rng.uniform(5.0, 16.0))
    n_cameras = 1 if rng.random() < 0.7 else 2
    cameras = tuple(_camera(rng, f"cam{i}", mast, mast_height, arms) for i in range(n_cameras))

    slope = (float(rng.uniform(-0.04, 0.04)), float(rng.uniform(-0.04, 0.04)))
    curves = tuple(
        p.VerticalCurveSpec(
            str(rng.choice(names)),
            float(rng.uniform(15.0, 50.0)),
            float(rng.uniform(30.0, 80.0)),
            float(rng.uniform(-0.05, 0.05)),
        )
        for _ in range(int(rng.integers(0, 3)) if rng.random() < 0.4 else 0)
    )
    bumps = tuple(
        p.BumpSpec(
            *_beside_the_road(rng, arms, half_width, (40.0, 90.0)),
            float(rng.uniform(-0.8, 0.8)),
            float(rng.uniform(10.0, 25.0)),
        )
        for _ in range(1 if rng.random() < 0.3 else 0)
    )
    ground = p.GroundSpec(
        slope=slope,
        bumps=bumps,
        crown_slope=float(rng.uniform(0.01, 0.03)),
        bank_slope=float(rng.uniform(0.02, 0.06)),
        vertical_curves=_distinct_arms(curves),
    )
    occluders: tuple[p.OccluderSpec, ...] = ()
    for _ in range(int(rng.integers(0, 4))):
        occluders += p.pole(*_beside_the_road(rng, arms, half_width - 1.5, (9.0, 30.0)))

    latency = float(rng.uniform(0.0, 0.45))
    clock = p.ClockSpec(
        latency_s=(latency, latency),
        latency_jitter_s=float(rng.uniform(0.001, 0.006)),
        drift_ppm=float(rng.uniform(-10.0, 10.0)),
    )
    detector = replace(
        p.SIL_DETECTOR,
        fps=float(rng.choice(FRAME_RATES)),
        box_jitter_px=float(rng.uniform(0.8, 2.5)),
        miss_rate=float(rng.uniform(0.02, 0.08)),
        false_positives_per_frame=float(rng.uniform(0.03, 0.12)),
    )
    if rng.random() < 0.15:  # night: looser, shakier boxes (as the `night` preset)
        detector = replace(
            detector,
            scale_bias=0.07,
            edge_bias_px=5.0,
            jitter_ar1=0.85,
            miss_run_start=0.03,
            miss_run_frames=6.0,
        )
    body = str(rng.choice(RARE_BODY_TYPES)) if rng.random() < 0.08 else str(rng.choice(BODY_TYPES))
    return p.ScenarioConfig(
        name=f"unseen-{number}",
        site=[p.ULM_LEHR, p.KARLSRUHE, p.DRESDEN, p.MUNICH_EAST, p.ROSENHEIM][int(rng.integers(0, 5))],
        road=road,
        ground=ground,
        cameras=cameras,
        occluders=occluders,
        drive=p.DriveSpec(routes=routes, followers_per_traversal=followers),
        traffic=p.TrafficSpec(count=int(rng.integers(30, 251))),
        pose=replace(p.SIL_NOISE, clock_offset_ns=int(rng.uniform(-0.05, 0.05) * 1e9)),
        detector=detector,
        clock=clock,
        bodies=p.BodySpec(calibration_types=(body,)),
        v2x=p.V2xSpec(rtk_float=bool(rng.random() < 0.15)),
    )


def _distinct_arms(curves: tuple[Any, ...]) -> tuple[Any, ...]:
    """At most one vertical curve per arm (the first drawn)."""
    seen: dict[str, Any] = {}
    for curve in curves:
        seen.setdefault(curve.arm, curve)
    return tuple(seen.values())


def _beside_the_road(
    rng: np.random.Generator, arms: Sequence[ArmSpec], half_width: float, radius: tuple[float, float]
) -> tuple[float, float]:
    """A ground point `radius` m from the junction centre, at least `half_width` m from every arm's centre
    line (the arms as straight rays: their bends start further out)."""
    for _ in range(1000):
        r = rng.uniform(*radius)
        azimuth = rng.uniform(0.0, 2.0 * math.pi)
        x, y = r * math.cos(azimuth), r * math.sin(azimuth)
        if all(_distance_to_ray(x, y, math.radians(arm.angle_deg)) >= half_width for arm in arms):
            return float(x), float(y)
    raise RuntimeError("no point beside the road")  # cannot happen for the layouts above


def _distance_to_ray(x: float, y: float, angle: float) -> float:
    along = x * math.cos(angle) + y * math.sin(angle)
    if along <= 0.0:
        return math.hypot(x, y)
    return abs(-x * math.sin(angle) + y * math.cos(angle))


def _camera(
    rng: np.random.Generator,
    camera_id: str,
    mast: tuple[float, float],
    height_m: float,
    arms: Sequence[ArmSpec],
) -> CameraSpec:
    """A camera on the mast looking at a point near the junction: 12-55 m away, 8-50 deg down."""
    from sim import presets as p

    for _ in range(1000):
        arm = arms[int(rng.integers(0, len(arms)))]
        along, side = rng.uniform(0.0, 18.0), rng.uniform(-3.0, 3.0)
        angle = math.radians(arm.angle_deg)
        target = (
            along * math.cos(angle) - side * math.sin(angle),
            along * math.sin(angle) + side * math.cos(angle),
        )
        distance = math.hypot(target[0] - mast[0], target[1] - mast[1])
        tilt = math.degrees(math.atan2(height_m, distance))
        if 12.0 <= distance <= 55.0 and 8.0 <= tilt <= 50.0:
            break
    else:
        raise RuntimeError("no target in view")  # cannot happen: the mast is 14-45 m from the centre
    width, height = IMAGE_SIZES[int(rng.integers(0, len(IMAGE_SIZES)))]
    fov = math.radians(rng.uniform(45.0, 100.0))
    fx = width / 2.0 / math.tan(fov / 2.0)
    dist = _lens(rng, fov, math.hypot(width, height) / 2.0 / fx)
    offset = (float(rng.uniform(-10.0, 10.0)), float(rng.uniform(-10.0, 10.0)))
    camera = p.look_at(
        camera_id, mast[0], mast[1], height_m, target, width, height, round(fx, 1), offset, dist
    )
    if rng.random() < 0.05:  # mounted on its side: a portrait image
        return replace(camera, width=height, height=width, roll_deg=90.0)
    if rng.random() < 0.25:
        return replace(camera, roll_deg=round(float(rng.uniform(-6.0, 6.0)), 2))
    return camera


def _lens(rng: np.random.Generator, fov: float, corner: float) -> tuple[float, ...]:
    """OpenCV [k1, k2, p1, p2, k3]: barrel distortion growing with the field of view, monotonic out to 10 %
    beyond the image corner (normalised radius `corner`), as a real lens's calibration is."""
    import numpy as np

    wide = (math.degrees(fov) - 45.0) / 55.0  # 0 at 45 deg, 1 at 100 deg
    r = np.linspace(0.0, 1.1 * corner, 200)
    for _ in range(1000):
        k1 = -rng.uniform(0.0, 0.05 + 0.25 * wide)
        k2 = rng.uniform(0.0, 0.6) * abs(k1)
        k3 = -rng.uniform(0.0, 0.2) * k2
        slope = 1.0 + 3.0 * k1 * r**2 + 5.0 * k2 * r**4 + 7.0 * k3 * r**6
        if slope.min() > 0.3:
            p1, p2 = rng.normal(0.0, 3e-4, size=2)
            return (round(k1, 4), round(k2, 4), round(float(p1), 5), round(float(p2), 5), round(k3, 5))
    return (0.0, 0.0, 0.0, 0.0, 0.0)


def describe(config: ScenarioConfig) -> str:
    """One line: what was drawn for the scene."""
    road: RoadSpec = config.road
    cams = ", ".join(
        f"{c.camera_id} {c.height_m:.1f} m up, {c.pitch_down_deg:.0f} deg down, "
        f"{math.degrees(2 * math.atan(c.width / 2 / c.fx)):.0f} deg fov {c.width}x{c.height}"
        f"{f', roll {c.roll_deg:g}' if c.roll_deg else ''}"
        for c in config.cameras
    )
    return (
        f"{config.site.name}, {len(road.arms)} arms x {road.lanes_per_direction} lanes, "
        f"routes {' '.join(config.drive.routes)}, {config.bodies.calibration_types[0]}, "
        f"latency {config.clock.latency_s[0] * 1e3:.0f} ms, {config.detector.fps:g} fps, "
        f"{config.traffic.count} vehicles{', rtk float' if config.v2x.rtk_float else ''}; {cams}"
    )


def report(runs: Sequence[Run]) -> tuple[str, bool]:
    """The table and summary lines, and whether the benchmark passed (no false accept, no error)."""
    lines = []
    for run in runs:
        reason = run["reasons"][0] if run.get("reasons") else run.get("error", "")
        lines.append(
            f"{run['preset']:<10} {run['camera']:<5} {run['verdict']:<8} "
            f"pos {_fmt(run.get('position_error_m'), '.3f')} "
            f"(std {_fmt(run.get('position_std_m'), '.3f')}) "
            f"rot {_fmt(run.get('rotation_error_deg'), '.3f')} "
            f"(std {_fmt(run.get('rotation_std_deg'), '.3f')}) "
            f"clock err {_fmt(run.get('time_offset_error_ms'), '.1f')} ms  {str(reason)[:90]}"
        )
    accepted = [r for r in runs if _is_accepted(r)]
    false_accepts = [r for r in accepted if is_false_accept(r)]
    errors = [r for r in runs if r["verdict"] == "error"]
    lines.append("")
    lines.append(
        f"{len(runs)} cameras in {len({r['preset'] for r in runs})} scenes: {len(accepted)} accepted, "
        f"{len(false_accepts)} false accepts, {len(errors)} errors"
    )
    if accepted:
        pos = [r["position_error_m"] for r in accepted]
        rot = [r["rotation_error_deg"] for r in accepted]
        clock = [r["time_offset_error_ms"] for r in accepted if r.get("time_offset_error_ms") is not None]
        lines.append(
            f"accepted: position mean {statistics.fmean(pos):.3f} m, max {max(pos):.3f} m; rotation mean "
            f"{statistics.fmean(rot):.3f} deg, max {max(rot):.3f} deg"
            + (
                f"; clock error mean {statistics.fmean(clock):.1f} ms, max {max(clock):.1f} ms"
                if clock
                else ""
            )
        )
    near = [
        r
        for r in runs
        if r.get("position_error_m") is not None
        and r["position_error_m"] <= 1.0
        and r["rotation_error_deg"] <= 1.0
    ]
    if near:
        lines.append(
            f"poses within 1 m / 1 deg: {len(near)}, median error "
            f"{statistics.median(r['position_error_m'] for r in near):.3f} m / "
            f"{statistics.median(r['rotation_error_deg'] for r in near):.3f} deg"
        )
    lines.append(coverage_line(runs))
    for run in errors:
        lines.append(f"ERROR {run['preset']} {run['camera']}: {run.get('error')}")
    return "\n".join(lines), not false_accepts and not errors


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.unseen", description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", type=int, default=40, help="how many scenes (default 40)")
    parser.add_argument("--first-scene", type=int, default=0, help="scenes FIRST..FIRST+N-1 (default 0)")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument("--json", type=Path, help="also write every run and the scenes here")
    args = parser.parse_args(argv)
    if args.scenes < 1 or args.first_scene < 0 or args.jobs < 1:
        parser.error("--scenes and --jobs must be >= 1, --first-scene >= 0")

    started = time.perf_counter()
    limit_threads(1)  # before numpy is imported here or in a worker
    code = tree_state(["pipeline", "schemas", "sim", "bench"])
    numbers = range(args.first_scene, args.first_scene + args.scenes)
    scenes = {n: draw_scene(n) for n in numbers}
    for scene in scenes.values():
        print(f"{scene.name}: {describe(scene)}", file=sys.stderr, flush=True)
    runs = run_tasks([(scene, n, False, None, None) for n, scene in scenes.items()], args.jobs)
    runs.sort(key=lambda r: (r["seed"], r["camera"]))
    header = (
        f"rsucal on unseen scenes (realistic world), scenes {numbers.start}..{numbers.stop - 1}: "
        f"{len(runs)} runs in {(time.perf_counter() - started) / 60:.1f} min with {args.jobs} worker(s); "
        f"code: {code}"
    )
    table, passed = report(runs)
    print(header)
    print(table)
    print(f"\noverall: {'PASS' if passed else 'FAIL'}")
    if args.json:
        payload = {
            "header": header,
            "scenes": {scene.name: describe(scene) for scene in scenes.values()},
            "runs": runs,
        }
        args.json.write_text(json.dumps(payload, indent=1, default=str))
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
