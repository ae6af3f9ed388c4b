"""The simulator's real world, end to end: latency, CAM V2X, body shapes, detector errors, roads, a moved
camera; and the ideal world reproducing the first simulator's numbers.

Scenes are shrunk presets (two traversals, little traffic, fixed seeds) so the file runs in seconds.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from test_simulate import shrink as shrink_scene

from sim.presets import PRESETS, REAL_CLOCK, CameraMoveSpec, ScenarioConfig
from sim.shapes import TYPE_RANGES
from sim.simulate import SimulationResult, simulate


def shrink(
    config: ScenarioConfig, routes: tuple[str, ...] | None = None, traffic: int = 20
) -> ScenarioConfig:
    """The ideal-world tests' smaller scene, in the real world."""
    return shrink_scene(config, routes=routes, traffic=traffic, ideal=False)


@pytest.fixture(scope="module")
def north() -> SimulationResult:
    result = simulate(shrink(PRESETS["sil-north"]), seed=4)
    # This seed draws a hatchback without a roof box (one car in twenty carries one, and it makes the box
    # taller than the data sheet's: test_a_roof_box_makes_the_box_taller_than_the_data_sheet).
    assert result.ground_truth["north"].vehicle_proportions["roof_box"] == 0.0
    return result


def _area(box: tuple[float, float, float, float]) -> float:
    return (box[2] - box[0]) * (box[3] - box[1])


def test_detections_are_stamped_after_exposure_by_the_cameras_latency(north: SimulationResult) -> None:
    truth = north.ground_truth["north"]
    low_s, high_s = REAL_CLOCK.latency_s
    assert low_s * 1e9 <= truth.latency_ns <= high_s * 1e9
    lag = np.array([f.stamp_ns - f.exposure_ns for f in truth.frames if f.exposure_ns is not None])
    assert len(lag) == len(truth.frames)
    # The drawn latency plus a per-frame jitter clipped at 3 sigma (+1 ns of rounding).
    assert np.all(np.abs(lag - truth.latency_ns) <= 3 * REAL_CLOCK.latency_jitter_s * 1e9 + 1)
    assert np.std(lag) > 0.5e6  # jittered, not a constant
    assert [f.stamp_ns for f in north.detections["north"]] == [f.stamp_ns for f in truth.frames]


def test_each_camera_draws_a_rolling_shutter_readout_and_the_ideal_world_has_none(
    north: SimulationResult,
) -> None:
    low_s, high_s = REAL_CLOCK.readout_s or (0.0, 0.0)
    assert high_s > 0.0 and low_s * 1e9 <= north.ground_truth["north"].readout_ns <= high_s * 1e9
    ideal = simulate(shrink_scene(PRESETS["sil-north"], traffic=5, ideal=True), seed=4)
    assert ideal.ground_truth["north"].readout_ns == 0
    # Its vehicle's poses drift across but their heights do not wander: its profile says so; the real
    # world's CAM vehicle keeps the profile's RTK default.
    assert ideal.vehicle.gnss_wander_m == (0.03, 0.0)
    assert north.vehicle.gnss_wander_m == (0.03, 0.06)


def test_a_rolling_shutter_shows_each_box_later_by_its_rows_share_of_the_readout() -> None:
    # The same scene with a global shutter and with a 30 ms readout: every other draw is the same, so the
    # calibration vehicle's visible box moves by its own rate times the readout's share at its rows. Checked
    # against the global-shutter boxes' rate along the track (frames 0.1 s apart), not the simulator's code.
    config = shrink(PRESETS["sil-north"], routes=("S>N",), traffic=5)
    boxes = {}
    for readout in (0.0, 0.03):
        clock = replace(REAL_CLOCK, readout_s=(readout, readout))
        result = simulate(replace(config, clock=clock), seed=2)
        truth = result.ground_truth["north"]
        assert truth.readout_ns == round(readout * 1e9)
        boxes[readout] = np.array([f.visible_box or (math.nan,) * 4 for f in truth.frames])
        width, height = truth.intrinsics.width, truth.intrinsics.height
    still, rolling = boxes[0.0], boxes[0.03]

    def inside(b: np.ndarray) -> np.ndarray:  # not cut by the image border (a cut edge does not move)
        with np.errstate(invalid="ignore"):
            return (b[:, 0] > 2) & (b[:, 1] > 2) & (b[:, 2] < width - 2) & (b[:, 3] < height - 2)

    seen = np.flatnonzero(inside(still) & inside(rolling))
    inner = seen[np.isin(seen - 1, seen) & np.isin(seen + 1, seen)]
    assert len(inner) > 30
    rate = (still[inner + 1] - still[inner - 1]) / 0.2  # px/s (10 fps)
    top, bottom = still[inner, 1], still[inner, 3]
    # The top and bottom edges at their own rows' times (the side edges' rows lie somewhere between, and
    # which vertex forms them changes as the body turns).
    expected_y = np.column_stack([rate[:, 1] * 0.03 * top / height, rate[:, 3] * 0.03 * bottom / height])
    moved = rolling[inner] - still[inner]
    assert np.max(np.abs(moved)) > 3.0  # the readout matters: several pixels on the nearest boxes
    assert np.abs(moved[:, [1, 3]] - expected_y).max() < 0.1 * np.max(np.abs(moved)) + 0.3


def test_the_latency_preset_lags_by_250_ms() -> None:
    result = simulate(shrink(PRESETS["latency"], routes=("S>N",), traffic=5), seed=1)
    assert result.ground_truth["north"].latency_ns == 250_000_000


@pytest.mark.parametrize("ideal", [False, True])
def test_a_given_latency_moves_every_stamp_and_nothing_else(ideal: bool) -> None:
    # bench.accuracy --latency: the same scene with the camera's stamps late (or early: a camera clock
    # behind the vehicle's) by the given latency instead of the world's (drawn, or none in the ideal world).
    config = shrink(PRESETS["sil-north"], routes=("S>N",), traffic=5)
    drawn = simulate(config, seed=2, ideal=ideal)
    for latency_s in (0.45, -0.4):
        given = simulate(config, seed=2, ideal=ideal, latency_s=latency_s)
        truth, before = given.ground_truth["north"], drawn.ground_truth["north"]
        assert truth.latency_ns == round(latency_s * 1e9)
        moved = truth.latency_ns - before.latency_ns
        stamps = np.array([f.stamp_ns for f in truth.frames]) - moved
        assert np.abs(stamps - [f.stamp_ns for f in before.frames]).max() <= 1  # ns of rounding
        assert [f.exposure_ns for f in truth.frames] == [f.exposure_ns for f in before.frames]
        boxes = [[b.model_dump() for b in f.boxes] for f in given.detections["north"]]
        assert boxes == [[b.model_dump() for b in f.boxes] for f in drawn.detections["north"]]
        assert given.v2x == drawn.v2x


def test_v2x_are_cams_at_1_to_10_hz_without_pitch_or_roll(north: SimulationResult) -> None:
    assert north.v2x_mode == "cam" and north.ground_truth["north"].v2x == "cam"
    stamps = np.array([m.stamp_ns for m in north.v2x])
    gaps_s = np.diff(stamps) / 1e9
    assert gaps_s.min() >= 0.1 - 1e-6 and gaps_s.max() <= 1.0 + 0.1 + 1e-6
    assert 1.0 < len(stamps) / ((stamps[-1] - stamps[0]) / 1e9) < 10.0
    assert all(m.pitch is None and m.roll is None for m in north.v2x)
    assert all(m.accuracies is not None and m.accuracies.horizontal_m is not None for m in north.v2x)
    # The IMU's 50 Hz poses stay for the toolbox's poses.yaml.
    assert len(north.poses) > 5 * len(north.v2x)


def test_cam_positions_carry_correlated_gnss_errors_and_rtk_float_makes_them_large(
    north: SimulationResult,
) -> None:
    floated = simulate(shrink(PRESETS["rtk-float"], traffic=5), seed=2)

    def errors(result: SimulationResult) -> np.ndarray:
        origin = np.array([result.origin.x, result.origin.y])
        from pyproj import Transformer

        to_utm = Transformer.from_crs("EPSG:4326", result.origin.crs, always_xy=True)
        east, north_m = to_utm.transform([m.lon for m in result.v2x], [m.lat for m in result.v2x])
        cam_xy = np.column_stack([east, north_m]) - origin
        stamps = (
            np.array([m.stamp_ns for m in result.v2x])
            - result.ground_truth[result.cameras[0].camera_id].clock_offset_ns
        )
        true_xy = np.column_stack(
            [np.interp(stamps, result.true_stamps, result.true_poses[:, k]) for k in range(2)]
        )
        return np.asarray(np.hypot(*(cam_xy - true_xy).T))

    fixed, lost = errors(north), errors(floated)
    assert 0.005 < float(np.median(fixed)) < 0.15  # RTK fixed: centimetres, never exactly zero
    assert float(np.max(lost)) > 0.3 and float(np.median(lost)) < float(np.max(lost)) / 2


def test_the_calibration_vehicle_is_a_drawn_body_type_whose_data_sheet_the_pipeline_gets(
    north: SimulationResult,
) -> None:
    truth = north.ground_truth["north"]
    assert truth.vehicle_type in PRESETS["sil-north"].bodies.calibration_types
    ranges = TYPE_RANGES[truth.vehicle_type]
    for name, value in (
        ("length_m", north.vehicle.length),
        ("width_m", north.vehicle.width),
        ("height_m", north.vehicle.height),
    ):
        low, high = ranges[name]
        assert low - 1e-3 <= value <= high + 1e-3
    assert truth.vehicle_proportions and all(math.isfinite(v) for v in truth.vehicle_proportions.values())
    van = simulate(shrink(PRESETS["van"], routes=("S>N",), traffic=5), seed=4)
    assert van.ground_truth["north"].vehicle_type == "van"


def test_the_detected_box_bounds_the_visible_shape_not_the_cuboid(north: SimulationResult) -> None:
    truth = north.ground_truth["north"]
    width, height = truth.intrinsics.width, truth.intrinsics.height
    whole = [
        f
        for f in truth.frames
        if f.visible_box is not None
        and f.cuboid_box is not None
        and f.gross_error is None
        and f.cuboid_box[0] > 0
        and f.cuboid_box[1] > 0
        and f.cuboid_box[2] < width
        and f.cuboid_box[3] < height
    ]
    assert len(whole) > 50
    ratio = np.array([_area(f.visible_box) / _area(f.cuboid_box) for f in whole])  # type: ignore[arg-type]
    assert 0.6 < float(np.mean(ratio)) < 0.92  # a car's outline fills 75-85 % of its cuboid's rectangle
    # The detector's box is the visible one plus its errors: close, never equal.
    offsets = np.array([np.subtract(f.box, f.visible_box) for f in whole])  # type: ignore[arg-type]
    assert float(np.median(np.abs(offsets))) < 8.0
    assert float(np.mean(np.abs(offsets) > 1e-6)) > 0.9


def test_a_roof_box_makes_the_box_taller_than_the_data_sheet() -> None:
    result = simulate(shrink(PRESETS["sil-north"], traffic=5), seed=3)  # draws a hatchback with a roof box
    truth = result.ground_truth["north"]
    assert truth.vehicle_proportions["roof_box"] == 1.0
    height = np.array(
        [
            (f.visible_box[3] - f.visible_box[1]) / (f.cuboid_box[3] - f.cuboid_box[1])
            for f in truth.frames
            if f.visible_box and f.cuboid_box and f.gross_error is None
        ]
    )
    assert float(np.median(height)) > 1.0


def test_roads_tilt_the_vehicle_and_the_ideal_world_has_flat_ground() -> None:
    preset = PRESETS["crowned-road"]
    level = replace(shrink(preset, traffic=5), ground=replace(preset.ground, slope=(0.0, 0.0)))
    real = simulate(level, seed=1)
    flat = simulate(level, seed=1, ideal=True)
    # On the arms (30-120 m out, past the flattened junction) a crowned road rolls the body toward the kerb
    # by about the crown (2.5 %, 0.025 rad) or the bank; on the terrain alone (level here) nothing does.
    for result, low, high in ((real, 0.015, 0.06), (flat, -1.0, 1e-12)):
        distance = np.hypot(*result.true_poses[:, :2].T)
        roll = np.abs(result.true_poses[(distance > 30.0) & (distance < 120.0), 5])
        assert low < float(np.median(roll)) < high


def test_a_moved_camera_has_two_extrinsics_and_frames_after_the_move_see_through_the_second() -> None:
    config = replace(
        shrink(PRESETS["sil-north"], routes=("S>N", "N>S"), traffic=5),
        camera_move=CameraMoveSpec(after_traversal=0, turn_deg=0.6, shift_m=0.4),
    )
    result = simulate(config, seed=2, ideal=True)  # cuboid boxes: the rectangle is checked exactly
    truth = result.ground_truth["north"]
    assert len(truth.moves) == 1
    move = truth.moves[0]
    R0, R1 = np.array(truth.R), np.array(move.R)
    angle = math.degrees(math.acos(min(1.0, (np.trace(R0.T @ R1) - 1.0) / 2.0)))
    assert angle == pytest.approx(0.6, abs=1e-6)
    shift = np.subtract(move.camera_position_utm, truth.camera_position_utm)
    assert np.hypot(shift[0], shift[1]) == pytest.approx(0.4, abs=1e-6) and abs(shift[2]) < 1e-9
    intr = truth.intrinsics
    K = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1.0]])
    after = [f for f in truth.frames if f.cuboid_box is not None and f.exposure_ns >= move.from_exposure_ns]  # type: ignore[operator]
    before = [f for f in truth.frames if f.cuboid_box is not None and f.exposure_ns < move.from_exposure_ns]  # type: ignore[operator]
    assert after and before
    for frames, R, t in ((after, R1, np.array(move.t_local)), (before, R0, np.array(truth.t_local))):
        f = frames[len(frames) // 2]
        footprint = np.array(f.footprint_local)
        x = (footprint[1] - footprint[0]) / np.linalg.norm(footprint[1] - footprint[0])
        y = (footprint[3] - footprint[0]) / np.linalg.norm(footprint[3] - footprint[0])
        corners = np.vstack([footprint, footprint + result.vehicle.height * np.cross(x, y)])
        pixels, _ = cv2.projectPoints(corners, cv2.Rodrigues(R)[0], t, K, np.array(intr.dist))
        pixels = pixels.reshape(-1, 2)
        np.testing.assert_allclose(f.cuboid_box, [*pixels.min(axis=0), *pixels.max(axis=0)], atol=1e-6)


# The first simulator (pipeline/simulate.py at 8f669c2) on two scenes: frames, boxes, the sum of all box
# coordinates, calibration-vehicle frames, the sum of frame stamps after the first, V2X messages. The ideal
# world must reproduce them (headings come from another, independent method now: 1e-4 deg in a sum of
# ~12,600 headings).
FIRST_WORLD = {
    ("carla-like", 0, "carla"): (
        2525,
        12431,
        36733499.26983996,
        518,
        318654407297616,
        12630,
        2842042.907908875,
    ),
    ("single-traversal", 0, "north"): (
        668,
        3462,
        8712033.657076165,
        200,
        22277640034314,
        3259,
        1146114.365430922,
    ),
}


@pytest.mark.parametrize("scene", sorted(FIRST_WORLD))
def test_the_ideal_world_reproduces_the_first_simulator(scene: tuple[str, int, str]) -> None:
    preset, seed, camera = scene
    result = simulate(preset, seed, ideal=True)
    frames = result.detections[camera]
    boxes = np.array([[b.x1, b.y1, b.x2, b.y2] for f in frames for b in f.boxes])
    calib = sum(f.calib_box is not None for f in result.ground_truth[camera].frames)
    stamps = sum(f.stamp_ns - frames[0].stamp_ns for f in frames)
    n_frames, n_boxes, coord_sum, n_calib, stamp_sum, n_v2x, heading_sum = FIRST_WORLD[scene]
    assert (len(frames), len(boxes), calib, stamps, len(result.v2x)) == (
        n_frames,
        n_boxes,
        n_calib,
        stamp_sum,
        n_v2x,
    )
    assert float(boxes.sum()) == pytest.approx(coord_sum, rel=1e-12)
    assert sum(m.heading_deg for m in result.v2x) == pytest.approx(heading_sum, abs=1e-3)
    assert result.ground_truth[camera].latency_ns == 0 and result.ground_truth[camera].world == "ideal"


def test_a_cam_heading_is_the_antennas_course_not_the_bodys_yaw(north: SimulationResult) -> None:
    """A receiver's course is the direction its antenna moves. The body turns about its rear axle, so in a
    turn an antenna ahead of that axle moves at an angle to the body's axis: the CAM headings follow the
    reference point's own motion (within the course noise), and not the body's yaw. Both directions are
    taken from the true 50 Hz track (the motion as the reference point's step between neighbouring poses)."""
    from sim.geo import GeoFrame

    truth = north.ground_truth["north"]
    stamps = np.array([m.stamp_ns for m in north.v2x]) - truth.clock_offset_ns
    xy, yaw = north.true_poses[:, :2], np.unwrap(north.true_poses[:, 3])
    step = xy[2:] - xy[:-2]
    moving = np.hypot(*step.T) > 0.05  # 1.25 m/s over the two 20 ms steps
    motion = np.unwrap(np.arctan2(step[:, 1], step[:, 0]))
    t_mid = north.true_stamps[1:-1].astype(np.float64)
    keep = moving[np.clip(np.searchsorted(t_mid, stamps), 0, len(t_mid) - 1)]
    at = stamps.astype(np.float64)
    body = np.interp(at, north.true_stamps.astype(np.float64), yaw)
    course = np.interp(at, t_mid[moving], motion[moving])
    east = np.interp(at, north.true_stamps.astype(np.float64), xy[:, 0]) + north.origin.x
    north_m = np.interp(at, north.true_stamps.astype(np.float64), xy[:, 1]) + north.origin.y
    geo = GeoFrame(north.origin.crs)
    sent = np.array([m.heading_deg for m in north.v2x])

    def off(yaw_rad: np.ndarray) -> np.ndarray:
        return np.abs((sent - geo.true_heading_deg(east, north_m, yaw_rad) + 180.0) % 360.0 - 180.0)

    turning = keep & (np.abs(np.degrees(course - body)) > 1.0)
    assert turning.sum() >= 10  # the scene's turns
    assert float(np.median(off(course)[turning])) < 0.5
    assert float(np.median(off(body)[turning])) > 1.0
