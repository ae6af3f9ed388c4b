"""The scenario simulator's ideal world: determinism, rendering geometry, ground truth, pose reports,
traffic, presets.

The ideal world (cuboid boxes, stamps at exposure, IMU poses as V2X) is the first simulator's, kept so that
its numbers stay reproducible; its geometry is exact, so it is checked here to the micrometre against
cv2.projectPoints, never against the simulator's own code. The real world has tests of its own
(test_real_world.py, test_detector.py, test_shapes.py, test_roads.py, test_v2x.py). Scenes are shrunk
presets (shorter arms, two traversals, little traffic) so the file runs in a few seconds.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation as SciRotation

from pipeline.frames import UtmFrame, v2x_from_pose
from pipeline.vehicle import footprint_corners
from schemas.common import CameraIntrinsics
from sim.detector import Instances, hidden_fractions, project_boxes, render_frames
from sim.errors import SimulationError
from sim.geometry import camera_position as camera_centre
from sim.geometry import mount_rotation as camera_rotation_from_view
from sim.lens import Lens
from sim.presets import PRESETS, DetectorSpec, ScenarioConfig
from sim.simulate import SimulationResult, simulate
from sim.traffic import DT_S, simulate_traffic
from sim.world import GroundSurface, build_network


def cuboid_corners(centre_poses: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """Corners (P, 8, 3) of boxes whose footprint centre has the poses (P, 6) = x, y, z, yaw, pitch, roll and
    whose size is `dims` (P, 3) = L, W, H: the test's own geometry (scipy's z-y-x Euler angles)."""
    unit = np.array(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float
    )
    body = (unit[None] - [0.5, 0.5, 0.0]) * dims[:, None, :]
    R = SciRotation.from_euler("ZYX", centre_poses[:, 3:6]).as_matrix()
    return np.einsum("pij,pkj->pki", R, body) + centre_poses[:, None, :3]


CLEAN_DETECTOR = DetectorSpec(frame_jitter_s=0.0015)  # no box jitter, misses or false positives


def shrink(
    config: ScenarioConfig,
    routes: tuple[str, ...] | None = None,
    traffic: int = 20,
    detector: DetectorSpec | None = None,
    ideal: bool = True,
) -> ScenarioConfig:
    """A faster variant: 260 m arms (connectors still ~300 m out), two traversals, little traffic; in the
    ideal world unless asked otherwise."""
    drive = replace(config.drive, routes=routes if routes is not None else config.drive.routes[:2])
    return replace(
        config,
        road=replace(config.road, arm_length_m=260.0),
        drive=drive,
        traffic=replace(config.traffic, count=traffic),
        detector=detector if detector is not None else config.detector,
        ideal=ideal,
    )


@pytest.fixture(scope="module")
def noisy() -> SimulationResult:
    return simulate(shrink(PRESETS["sil-north"]), seed=3)


@pytest.fixture(scope="module")
def clean() -> SimulationResult:
    return simulate(shrink(PRESETS["carla-like"]), seed=4)


@pytest.fixture(scope="module")
def two_cameras() -> SimulationResult:
    return simulate(shrink(PRESETS["sil-west"]), seed=5)


def calib_frames(result: SimulationResult, camera_id: str) -> list[int]:
    return [i for i, f in enumerate(result.ground_truth[camera_id].frames) if f.calib_box is not None]


def true_box(result: SimulationResult, camera_id: str, frame: int, distorted: bool = True) -> np.ndarray:
    """Tight clipped box of the cuboid rebuilt from the ground truth footprint, projected by OpenCV."""
    truth = result.ground_truth[camera_id]
    footprint = np.array(truth.frames[frame].footprint_local)
    x_axis = (footprint[1] - footprint[0]) / np.linalg.norm(footprint[1] - footprint[0])
    y_axis = (footprint[3] - footprint[0]) / np.linalg.norm(footprint[3] - footprint[0])
    roof = footprint + result.vehicle.height * np.cross(x_axis, y_axis)
    corners = np.vstack([footprint, roof])
    camera = next(c for c in result.cameras if c.camera_id == camera_id)
    intr = camera.intrinsics
    K = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1.0]])
    dist = np.array(intr.dist) if distorted else np.zeros(5)
    rvec, _ = cv2.Rodrigues(camera.R_cam_from_local)
    pixels, _ = cv2.projectPoints(corners, rvec, camera.t_cam_from_local, K, dist)
    pixels = pixels.reshape(-1, 2)
    box = np.array([*pixels.min(axis=0), *pixels.max(axis=0)])
    return np.clip(box, 0, [intr.width, intr.height, intr.width, intr.height])


# --- determinism -------------------------------------------------------------------------------------


def test_same_seed_gives_identical_output_and_another_seed_does_not() -> None:
    config = shrink(PRESETS["sil-south"], routes=("W>E",), traffic=8, ideal=False)  # the real world
    a, b, c = simulate(config, 11), simulate(config, 11), simulate(config, 12)

    def dump(r: SimulationResult) -> tuple[object, ...]:
        return (
            [f.model_dump() for f in r.detections["south"]],
            [p.model_dump() for p in r.poses],
            r.ground_truth["south"].model_dump(),
        )

    assert dump(a) == dump(b)
    assert np.array_equal(a.true_poses, b.true_poses)
    assert dump(a)[0] != dump(c)[0]
    assert dump(a)[1] != dump(c)[1]
    assert [m.model_dump() for m in a.v2x] == [m.model_dump() for m in b.v2x]


# --- rendering geometry (property tests) -------------------------------------------------------------

camera_setups = st.fixed_dictionaries(
    {
        "yaw": st.floats(-math.pi, math.pi),
        "pitch": st.floats(0.17, 0.6),
        "roll": st.floats(-0.05, 0.05),
        "fx": st.floats(700.0, 3000.0),
        "k1": st.floats(-0.08, 0.0),
        "k2": st.floats(0.0, 0.03),
    }
)
cuboids = st.fixed_dictionaries(
    {
        "ahead": st.floats(5.0, 120.0),
        "side": st.floats(-40.0, 40.0),
        "yaw": st.floats(-math.pi, math.pi),
        "length": st.floats(3.5, 13.0),
        "width": st.floats(1.6, 2.6),
        "height": st.floats(1.3, 4.0),
    }
)


@settings(max_examples=60, deadline=None)
@given(setup=camera_setups, body=cuboids)
def test_box_is_the_clipped_tight_bounds_of_the_projected_corners(
    setup: dict[str, float], body: dict[str, float]
) -> None:
    intr = CameraIntrinsics(
        width=1920,
        height=1200,
        fx=setup["fx"],
        fy=setup["fx"],
        cx=955.0,
        cy=603.0,
        dist=(setup["k1"], setup["k2"], 0.0, 0.0, 0.0),
    )
    model = Lens.from_intrinsics(intr)
    R = camera_rotation_from_view(setup["yaw"], setup["pitch"], setup["roll"])
    t = -R @ np.array([0.0, 0.0, 10.0])
    forward = np.array([math.cos(setup["yaw"]), math.sin(setup["yaw"])])
    centre = body["ahead"] * forward + body["side"] * np.array([-forward[1], forward[0]])
    pose = np.array([[centre[0], centre[1], 0.0, body["yaw"], 0.0, 0.0]])
    corners = cuboid_corners(pose, np.array([[body["length"], body["width"], body["height"]]]))
    projected = project_boxes(corners, R, t, model)
    if not projected.projectable[0]:
        return  # a corner behind the camera or outside the lens model: no box, nothing to compare
    pixels, _ = cv2.projectPoints(corners[0], cv2.Rodrigues(R)[0], t, model.K, model.dist)
    pixels = pixels.reshape(-1, 2)
    raw = np.array([*pixels.min(axis=0), *pixels.max(axis=0)])
    np.testing.assert_allclose(projected.raw[0], raw, atol=1e-6)
    clipped = projected.clipped[0]
    np.testing.assert_allclose(clipped, np.clip(raw, 0, [1920, 1200, 1920, 1200]), atol=1e-6)
    inside = (pixels[:, 0] >= 0) & (pixels[:, 0] <= 1920) & (pixels[:, 1] >= 0) & (pixels[:, 1] <= 1200)
    assert np.all(pixels[inside] >= clipped[:2] - 1e-6) and np.all(pixels[inside] <= clipped[2:] + 1e-6)
    area = (raw[2] - raw[0]) * (raw[3] - raw[1])
    expected_inside = (clipped[2] - clipped[0]) * (clipped[3] - clipped[1]) / area
    assert projected.inside_fraction[0] == pytest.approx(expected_inside, abs=1e-9)


boxes = st.tuples(st.floats(0, 1500), st.floats(0, 1000), st.floats(10, 400), st.floats(10, 300)).map(
    lambda b: (b[0], b[1], b[0] + b[2], b[1] + b[3])
)


@settings(max_examples=80, deadline=None)
@given(target=boxes, occluder=boxes, occluder_nearer=st.booleans())
def test_hidden_fraction_is_the_covered_share_of_the_box(
    target: tuple[float, ...], occluder: tuple[float, ...], occluder_nearer: bool
) -> None:
    grid = 12
    hidden, visible = hidden_fractions(
        np.array([0, 0]),
        np.array([target, occluder]),
        np.array([20.0, 10.0 if occluder_nearer else 30.0]),
        np.array([True, False]),
        grid=grid,
    )
    t, o = np.array(target), np.array(occluder)
    overlap_w = max(0.0, min(t[2], o[2]) - max(t[0], o[0]))
    overlap_h = max(0.0, min(t[3], o[3]) - max(t[1], o[1]))
    share = overlap_w * overlap_h / ((t[2] - t[0]) * (t[3] - t[1]))
    if not occluder_nearer:
        assert hidden[0] == 0.0  # a farther box never hides a nearer one
        np.testing.assert_array_equal(visible[0], t)
        return
    # Sampled on cell centres: each direction is off by at most one cell.
    assert hidden[0] == pytest.approx(share, abs=2.0 / grid + 1.0 / grid**2)
    assert hidden[1] == 0.0  # occluders are never measured
    if hidden[0] < 1.0:  # the visible part lies inside the box
        assert np.all(visible[0, :2] >= t[:2] - 1e-9) and np.all(visible[0, 2:] <= t[2:] + 1e-9)


def test_a_box_mostly_behind_a_nearer_one_is_dropped_and_the_nearer_one_kept() -> None:
    frame = np.array([0, 0, 0, 1])
    boxes_px = np.array(
        [[100, 100, 200, 200], [90, 90, 210, 190], [500, 500, 600, 600], [100, 100, 200, 200]], float
    )
    distance = np.array([30.0, 10.0, 5.0, 30.0])
    hidden, _ = hidden_fractions(frame, boxes_px, distance, np.ones(4, bool))
    assert hidden[0] > 0.5  # behind box 1 of the same frame
    assert hidden[1] == 0.0 and hidden[2] == 0.0
    assert hidden[3] == 0.0  # same place, another frame: nothing in front of it


def test_render_drops_hidden_tiny_and_behind_vehicles_and_never_detects_occluders() -> None:
    intr = CameraIntrinsics(width=1920, height=1080, fx=1200.0, fy=1200.0, cx=960.0, cy=540.0)
    model = Lens.from_intrinsics(intr)
    R = camera_rotation_from_view(0.0, math.radians(15.0))
    t = -R @ np.array([0.0, 0.0, 8.0])
    # Frame 0: a car 30 m ahead; frame 1: the same car, a car behind the camera and one 600 m away.
    centres = np.array([[30.0, 0.0], [30.0, 0.0], [-20.0, 0.0], [600.0, 0.0]])
    poses = np.column_stack([centres, np.zeros((4, 4))])
    car = cuboid_corners(np.zeros((1, 6)), np.array([[4.5, 1.8, 1.5]]))[0]  # about the footprint centre
    owners = np.arange(4)
    instances = Instances(np.array([0, 1, 1, 1]), poses, owners, np.hypot(*centres.T), np.full(4, 4), owners)
    bodies = (car, car, car, car)
    wall = cuboid_corners(np.array([[12.0, 0.0, 0.0, 0.0, 0.0, 0.0]]), np.array([[0.5, 6.0, 9.0]]))
    rng = np.random.default_rng(0)
    free = render_frames(instances, bodies, 2, np.zeros((0, 8, 3)), R, t, model, CLEAN_DETECTOR, rng)
    assert [len(b) for b in free.boxes] == [1, 1]  # behind the camera and too small: dropped
    hidden = render_frames(instances, bodies, 2, wall, R, t, model, CLEAN_DETECTOR, rng)
    assert [len(b) for b in hidden.boxes] == [0, 0]  # the wall hides the car and is never detected itself
    # Owner 0 is the calibration vehicle (frame 0 only): detectable, but hidden, so no box.
    assert hidden.calib_row.tolist() == [-1, -1] and hidden.calib_detectable.tolist() == [True, False]
    assert free.calib_row.tolist() == [0, -1]


# --- ground truth ------------------------------------------------------------------------------------


def test_calib_box_is_the_projection_of_the_true_pose(clean: SimulationResult) -> None:
    frames = calib_frames(clean, "carla")
    assert len(frames) > 50
    detections = clean.detections["carla"]
    for f in frames:
        truth = clean.ground_truth["carla"].frames[f]
        box = detections[f].boxes[truth.calib_box]  # type: ignore[index]
        got = np.array([box.x1, box.y1, box.x2, box.y2])
        np.testing.assert_allclose(got, true_box(clean, "carla", f), atol=1e-6)
        assert truth.box == (box.x1, box.y1, box.x2, box.y2)
        assert truth.stamp_ns == detections[f].stamp_ns


def test_footprint_matches_the_true_pose_track(clean: SimulationResult) -> None:
    """A frame's footprint is the true pose at the frame's stamp: between the bracketing pose samples."""
    for f in calib_frames(clean, "carla")[::25]:
        truth = clean.ground_truth["carla"].frames[f]
        nearest = int(np.argmin(np.abs(clean.true_stamps - truth.stamp_ns)))
        dt_s = abs(int(clean.true_stamps[nearest]) - truth.stamp_ns) / 1e9
        expected = footprint_corners(clean.true_poses[nearest : nearest + 1], clean.vehicle)[0]
        assert np.max(np.abs(np.array(truth.footprint_local) - expected)) <= 17.0 * dt_s + 1e-6


def test_camera_ground_truth_is_consistent(noisy: SimulationResult) -> None:
    truth = noisy.ground_truth["north"]
    camera = noisy.cameras[0]
    R, t_local = np.array(truth.R), np.array(truth.t_local)
    origin = np.array(truth.origin)
    np.testing.assert_allclose(R, camera.R_cam_from_local)
    np.testing.assert_allclose(np.array(truth.t_utm), t_local - R @ origin)
    np.testing.assert_allclose(np.array(truth.camera_position_utm), camera_centre(R, t_local) + origin)
    height = camera_centre(R, t_local)[2] - noisy.world.ground_height(camera_centre(R, t_local)[None, :2])[0]
    assert height == pytest.approx(10.0)
    assert truth.station_id == noisy.station_id and truth.crs == noisy.origin.crs


def test_vehicle_is_out_of_view_between_traversals(
    noisy: SimulationResult, two_cameras: SimulationResult
) -> None:
    for result in (noisy, two_cameras):
        distance = np.hypot(*result.true_poses[:, :2].T)
        for camera in result.cameras:
            truth = result.ground_truth[camera.camera_id]
            frames = [f for f in truth.frames if f.calib_box is not None]
            labels = [f.traversal for f in frames]
            assert truth.traversals == 2 and sorted(set(labels)) == [0, 1]  # type: ignore[type-var]
            assert labels == sorted(labels)  # type: ignore[type-var]
            last_of_first = max(f.stamp_ns for f in frames if f.traversal == 0)
            first_of_second = min(f.stamp_ns for f in frames if f.traversal == 1)
            between = (result.true_stamps > last_of_first) & (result.true_stamps < first_of_second)
            assert distance[between].max() >= 250.0  # it drove far away: no track joins two traversals


def test_two_cameras_of_one_rsu(two_cameras: SimulationResult) -> None:
    ids = [c.camera_id for c in two_cameras.cameras]
    assert ids == ["west-junction", "west-arm"]
    centres = [camera_centre(c.R_cam_from_local, c.t_cam_from_local) for c in two_cameras.cameras]
    np.testing.assert_allclose(centres[0], centres[1])  # one mast
    axes = [c.R_cam_from_local[2] for c in two_cameras.cameras]
    assert float(axes[0] @ axes[1]) < 0.5  # looking at different arms
    stamps = [np.array([f.stamp_ns for f in two_cameras.detections[i]]) for i in ids]
    assert all(np.all(np.diff(s) > 90_000_000) and np.all(np.diff(s) < 110_000_000) for s in stamps)


# --- pose reports ------------------------------------------------------------------------------------


def test_clean_poses_are_the_true_poses(clean: SimulationResult) -> None:
    origin = np.array([clean.origin.x, clean.origin.y, clean.origin.z])
    reported = np.array([[p.x, p.y, p.z, p.yaw, p.pitch, p.roll] for p in clean.poses])
    np.testing.assert_allclose(reported[:, :3] - origin, clean.true_poses[:, :3], atol=1e-6)
    np.testing.assert_allclose(reported[:, 3:], clean.true_poses[:, 3:], atol=1e-12)
    assert [p.stamp_ns for p in clean.poses] == clean.true_stamps.tolist()


def test_noisy_poses_have_the_preset_noise_and_dropouts(noisy: SimulationResult) -> None:
    origin = np.array([noisy.origin.x, noisy.origin.y])
    reported = np.array([[p.x, p.y] for p in noisy.poses]) - origin
    error = reported - noisy.true_poses[:, :2]
    sigma = PRESETS["sil-north"].pose.position_sigma_m
    assert np.std(error[:, 0]) == pytest.approx(sigma, rel=0.3)
    assert np.max(np.abs(np.mean(error, axis=0))) < 0.06  # drift of a few cm at most
    gaps_s = np.diff(noisy.true_stamps) / 1e9
    assert 1 <= int(np.sum(gaps_s > 0.15)) <= 3 and gaps_s.max() <= 1.05


def test_pose_rate_phase_and_clock_offset_are_honoured() -> None:
    base = shrink(PRESETS["sil-north"], routes=("S>N",), traffic=5)
    offset = PRESETS["clock-offset"].pose.clock_offset_ns
    slow = simulate(replace(base, pose=replace(PRESETS["v2x-10hz"].pose, clock_offset_ns=offset)), seed=8)
    stamps = np.array([p.stamp_ns for p in slow.poses])
    np.testing.assert_array_equal(stamps - slow.true_stamps, offset)
    assert slow.ground_truth["north"].clock_offset_ns == offset == 150_000_000
    period = np.diff(slow.true_stamps)
    assert np.median(period) == pytest.approx(100e6, abs=2e6)
    assert np.percentile(np.abs(period - 100e6), 5) > 0  # jittered, not a perfect grid
    frames = np.array([f.stamp_ns for f in slow.detections["north"]])
    # Not aligned with the camera: the pose instants fall anywhere between frames.
    offset_to_frame = np.min(np.abs(slow.true_stamps[:, None] - frames[None, :200]), axis=1)[:100]
    assert np.mean(offset_to_frame > 2_000_000) > 0.5


def test_v2x_messages_are_the_poses_in_wgs84(noisy: SimulationResult) -> None:
    frame = UtmFrame(noisy.origin.crs)
    assert len(noisy.v2x) == len(noisy.poses)
    for i in range(0, len(noisy.poses), len(noisy.poses) // 7):
        message = noisy.v2x[i]
        expected = v2x_from_pose(
            noisy.poses[i],
            frame,
            noisy.station_id,
            message.speed,
            length=noisy.vehicle.length,
            width=noisy.vehicle.width,
        )
        assert message.lat == pytest.approx(expected.lat, abs=1e-12)
        assert message.lon == pytest.approx(expected.lon, abs=1e-12)
        # Two independent methods (the world's geodesic azimuth, the pipeline's convergence formula):
        # 1e-6 deg is 1e-7 m at a car's corner, far below anything a calibration could see.
        assert message.heading_deg == pytest.approx(expected.heading_deg, abs=1e-6)
        assert (message.stamp_ns, message.alt, message.station_id) == (
            expected.stamp_ns,
            expected.alt,
            expected.station_id,
        )
        assert message.length == noisy.vehicle.length


# --- scenarios ---------------------------------------------------------------------------------------


def test_no_target_never_shows_the_vehicle() -> None:
    result = simulate(
        replace(
            PRESETS["no-target"], duration_s=60.0, traffic=replace(PRESETS["no-target"].traffic, count=15)
        ),
        seed=2,
    )  # the real world: nothing there either
    truth = result.ground_truth["south"]
    assert truth.traversals == 0
    assert all(f.calib_box is None and f.traversal is None for f in truth.frames)
    assert np.hypot(*result.true_poses[:, :2].T).min() > 250.0
    assert sum(len(f.boxes) for f in result.detections["south"]) > 100  # the traffic is still there


def test_distortion_changes_the_boxes() -> None:
    config = shrink(PRESETS["wide-distorted"], routes=("W>E",), traffic=5, detector=CLEAN_DETECTOR)
    result = simulate(config, seed=6)
    frames = calib_frames(result, "wide")
    differences = []
    for f in frames:
        truth = result.ground_truth["wide"].frames[f]
        box = np.array(truth.box)
        np.testing.assert_allclose(box, true_box(result, "wide", f), atol=1e-6)
        differences.append(np.max(np.abs(box - true_box(result, "wide", f, distorted=False))))
    assert max(differences) > 20.0  # k1 = -0.05 at fx = 800 moves boxes near the border by tens of pixels


def test_unknown_preset_is_refused_by_name() -> None:
    with pytest.raises(SimulationError, match="no-such-preset"):
        simulate("no-such-preset", seed=0)


# --- traffic -----------------------------------------------------------------------------------------


def test_traffic_queues_without_overlap_and_followers_trail_the_vehicle() -> None:
    config = shrink(PRESETS["dense-traffic"], traffic=120)
    network = build_network(config.road)
    rngs = [np.random.default_rng(s) for s in (1, 2)]
    dims = (config.vehicle.length, config.vehicle.width, config.vehicle.height)
    result = simulate_traffic(network, config.drive, config.traffic, dims, None, *rngs)
    assert len(result.others) == 120
    calib_route_legs = [leg for leg in result.calibration.legs if leg.traversal is not None]
    # (route, length, motion, processing order): vehicles are driven in order of entry, ties by id.
    movers = [
        (v.route, v.length, v.legs[0].motion, (v.legs[0].motion.k0, v.vehicle_id)) for v in result.others
    ]
    for leg, route_name in zip(calib_route_legs, config.drive.routes, strict=True):
        route = network.route(route_name)
        movers.append(
            (
                f"{route.entry_arm}{route.entry_lane}>{route.exit_arm}{route.exit_lane}",
                dims[0],
                leg.motion,
                (leg.motion.k0, 0),
            )
        )
        # Hard distractors: other vehicles on the vehicle's own route entering 1.5-4 s after it.
        followers = [
            v
            for v in result.others
            if v.route == movers[-1][0] and 1.4 <= (v.legs[0].motion.k0 - leg.motion.k0) * DT_S <= 4.1
        ]
        assert len(followers) >= 3
    stop_s = 260.0 - 2 * 3.5 - 4.0  # inbound lane length: arm minus stop line distance
    closest = math.inf
    for a_route, a_len, a, a_order in movers:
        for b_route, b_len, b, b_order in movers:
            if a_route.split(">")[0] != b_route.split(">")[0] or b_order <= a_order:
                continue
            lo, hi = max(a.k0, b.k0), min(a.k_last, b.k_last)
            if hi <= lo:
                continue
            lead = a.s[lo - a.k0 : hi - a.k0]
            follow = b.s[lo - b.k0 : hi - b.k0]
            shared = lead - a_len / 2 <= (np.inf if a_route == b_route else stop_s)
            if np.any(shared):
                closest = min(closest, float(np.min((lead - a_len / 2 - follow - b_len / 2)[shared])))
    assert 0.0 <= closest < 5.0  # queues form (gaps of a few metres) but bodies never overlap


def test_bodies_rest_on_a_sloped_ground() -> None:
    from sim.traffic import surface_poses

    ground = GroundSurface(np.array([0.05, 0.0]), np.zeros((0, 4)))
    poses = surface_poses(
        np.array([[10.0, 3.0], [10.0, 3.0]]), np.array([0.0, math.pi / 2]), 4.8, 1.85, ground
    )
    assert poses[0, 4] == pytest.approx(-math.atan(0.05))  # uphill: nose up = negative pitch (Rz Ry Rx)
    assert poses[0, 5] == pytest.approx(0.0)
    assert poses[1, 4] == pytest.approx(0.0) and poses[1, 5] == pytest.approx(-math.atan(0.05))
    np.testing.assert_allclose(poses[:, 2], 0.5)


# --- presets -----------------------------------------------------------------------------------------


def test_presets_are_plausible_generic_scenes() -> None:
    required = {
        "carla-like",
        "sil-north",
        "sil-south",
        "sil-west",
        "noise-0.2",
        "noise-0.5",
        "dense-traffic",
        "occluded",
        "slope",
        "v2x-10hz",
        "clock-offset",
        "wide-distorted",
        "collinear",
        "single-traversal",
        "no-target",
        "long",
    }
    assert required <= set(PRESETS)
    convergence = []
    for name, config in PRESETS.items():
        assert config.name == name
        for camera in config.cameras:
            assert 6.0 <= camera.height_m <= 15.0 and 10.0 <= camera.pitch_down_deg <= 35.0, name
        site = config.site
        lat, lon = UtmFrame(site.crs).to_wgs84(np.array([site.east_m]), np.array([site.north_m]))
        convergence.append(abs(float(UtmFrame(site.crs).convergence_deg(lat, lon)[0])))
    assert max(convergence) > 1.5  # at least one site far enough off its central meridian to matter
    assert len(PRESETS["sil-west"].cameras) == 2
    assert PRESETS["carla-like"].pose.position_sigma_m == 0 and PRESETS["carla-like"].detector.miss_rate == 0
    assert PRESETS["noise-0.5"].pose.position_sigma_m == 0.5 and PRESETS["v2x-10hz"].pose.rate_hz == 10.0
    assert (
        PRESETS["wide-distorted"].cameras[0].fx == 800.0
        and PRESETS["wide-distorted"].cameras[0].dist[0] == -0.05
    )
    assert PRESETS["dense-traffic"].traffic.count == 300 and PRESETS["long"].duration_s == 900.0
