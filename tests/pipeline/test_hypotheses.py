"""Stage 3 (paper III-D): MatchedTrack pairing and EPnP + RANSAC hypotheses on exact synthetic passes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.association import AssociationParams, MatchedTrack, Trajectory, match_tracks
from pipeline.camera import (
    CameraModel,
    camera_centre,
    camera_rotation_from_view,
    project_points,
    rotation_angle_rad,
)
from pipeline.errors import ShapeError
from pipeline.ground import GroundPlaneFit
from pipeline.hypotheses import HypothesisParams, HypothesisSet, create_hypotheses, shows_vehicle
from pipeline.stage import Reason
from pipeline.straight_track import StraightTrackParams
from pipeline.tracking import ImageTrack
from pipeline.vehicle import body_centres, body_corners
from schemas.common import CameraIntrinsics, VehicleProfile

VEHICLE = VehicleProfile(length=4.6, width=1.9, height=1.5, imu_offset=(1.3, 0.95, 0.4))
GROUND = GroundPlaneFit(normal=np.array([0.0, 0.0, 1.0]), offset=0.0)
CAMERA_CENTRE = np.array([4.0, -14.0, 8.0])
START_NS = 1_700_000_000_000_000_000
FRAME_NS = 100_000_000  # 10 fps


def make_camera(fx: float = 1000.0, k1: float = 0.0, width: int = 1920, height: int = 1080) -> CameraModel:
    return CameraModel.from_intrinsics(
        CameraIntrinsics(
            width=width,
            height=height,
            fx=fx,
            fy=fx,
            cx=width / 2.0,
            cy=height / 2.0,
            dist=(k1, 0.0, 0.0, 0.0, 0.0),
        )
    )


def true_pose(
    yaw_deg: float = 95.0, pitch_deg: float = 18.0, roll_deg: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    R = camera_rotation_from_view(math.radians(yaw_deg), math.radians(pitch_deg), math.radians(roll_deg))
    return R, -R @ CAMERA_CENTRE


def curved_poses(count: int = 120) -> np.ndarray:
    """A left turn of radius 40 m in front of the camera: (count, 6) poses, yaw along the arc."""
    theta = np.linspace(math.radians(-85.0), math.radians(-15.0), count)
    x, y = -10.0 + 40.0 * np.cos(theta), 40.0 + 40.0 * np.sin(theta)
    zeros = np.zeros(count)
    return np.column_stack([x, y, np.full(count, 0.4), theta + math.pi / 2, zeros, zeros])


def straight_poses(count: int = 120) -> np.ndarray:
    zeros = np.zeros(count)
    return np.column_stack(
        [np.linspace(-8.0, 20.0, count), np.full(count, 8.0), np.full(count, 0.4), zeros, zeros, zeros]
    )


def exact_track(
    poses: np.ndarray, camera: CameraModel, R: np.ndarray, t: np.ndarray, track_id: int = 1
) -> MatchedTrack:
    """Boxes of the projected vehicle cuboid's size, centred on the exact projections of the body centres
    (a tight box's centre is a few px off that projection; here the centre correspondences are exact)."""
    pixels, depth = project_points(body_centres(poses, VEHICLE), R, t, camera)
    assert np.all(depth > 0)
    assert np.all((pixels >= 0) & (pixels <= [camera.width, camera.height]))
    corners, _ = project_points(body_corners(poses, VEHICLE).reshape(-1, 3), R, t, camera)
    corners = corners.reshape(len(poses), 8, 2)
    half_size = (corners.max(axis=1) - corners.min(axis=1)) / 2.0
    boxes = np.column_stack([pixels - half_size, pixels + half_size])
    stamps = START_NS + FRAME_NS * np.arange(len(poses), dtype=np.int64)
    return MatchedTrack(track_id=track_id, stamps=stamps, boxes=boxes, poses=poses)


def solve_one(
    track: MatchedTrack,
    camera: CameraModel,
    params: HypothesisParams | None = None,
    ground: GroundPlaneFit = GROUND,
    trajectory: Trajectory | None = None,
) -> HypothesisSet:
    return create_hypotheses(
        [track],
        camera,
        VEHICLE,
        ground,
        params or HypothesisParams(),
        np.random.default_rng(7),
        trajectory=trajectory,
    )


@pytest.mark.parametrize(("fx", "k1"), [(1000.0, 0.0), (800.0, -0.05)], ids=["pinhole", "barrel"])
def test_epnp_recovers_exact_pose(fx: float, k1: float) -> None:
    camera = make_camera(fx, k1)
    R, t = true_pose(roll_deg=2.0)
    result = solve_one(exact_track(curved_poses(), camera, R, t), camera)
    assert result.rejected == {}
    (hypothesis,) = result.hypotheses
    assert rotation_angle_rad(hypothesis.R_cam_from_local, R) < 1e-7
    np.testing.assert_allclose(hypothesis.camera_centre, CAMERA_CENTRE, atol=1e-5)
    assert hypothesis.inliers.all()
    assert hypothesis.median_reproj_px < 1e-4
    assert hypothesis.rotation_std_deg < 0.5


def test_distortion_is_honoured_not_ignored() -> None:
    # The same barrel-distorted boxes read as pinhole give a worse pose: the solver really used dist.
    distorted, pinhole = make_camera(800.0, -0.05), make_camera(800.0, 0.0)
    R, t = true_pose()
    track = exact_track(curved_poses(), distorted, R, t)
    (with_dist,) = solve_one(track, distorted).hypotheses
    without = solve_one(track, pinhole, HypothesisParams(max_median_reproj_px=1e9, reproj_threshold_px=1e9))
    (no_dist,) = without.hypotheses
    assert rotation_angle_rad(with_dist.R_cam_from_local, R) < 1e-7
    assert rotation_angle_rad(no_dist.R_cam_from_local, R) > 1e-3


@settings(max_examples=25, deadline=None)
@given(
    yaw_deg=st.floats(85.0, 105.0),
    pitch_deg=st.floats(12.0, 25.0),
    roll_deg=st.floats(-5.0, 5.0),
    k1=st.floats(-0.08, 0.02),
)
def test_exact_pose_round_trips_for_any_view(
    yaw_deg: float, pitch_deg: float, roll_deg: float, k1: float
) -> None:
    camera = make_camera(900.0, k1)
    R, t = true_pose(yaw_deg, pitch_deg, roll_deg)
    poses = curved_poses()
    pixels, depth = project_points(body_centres(poses, VEHICLE), R, t, camera)
    visible = (depth > 0) & np.all((pixels > 0) & (pixels < [camera.width, camera.height]), axis=1)
    track = exact_track(poses[visible], camera, R, t)
    (hypothesis,) = solve_one(track, camera).hypotheses
    assert rotation_angle_rad(hypothesis.R_cam_from_local, R) < 1e-6
    np.testing.assert_allclose(hypothesis.camera_centre, CAMERA_CENTRE, atol=1e-4)


def test_ransac_rejects_twenty_percent_gross_outliers() -> None:
    camera = make_camera()
    R, t = true_pose()
    track = exact_track(curved_poses(), camera, R, t)
    rng = np.random.default_rng(3)
    bad = rng.choice(len(track.boxes), size=len(track.boxes) // 5, replace=False)
    boxes = track.boxes.copy()
    # Move the box by 60 to 400 px in a random direction: gross detector / tracking errors.
    angle = rng.uniform(0.0, 2.0 * math.pi, len(bad))
    shift = rng.uniform(60.0, 400.0, len(bad))[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    boxes[bad] += np.hstack([shift, shift])
    corrupted = MatchedTrack(track.track_id, track.stamps, boxes, track.poses)
    (hypothesis,) = solve_one(corrupted, camera).hypotheses
    assert rotation_angle_rad(hypothesis.R_cam_from_local, R) < 1e-7
    np.testing.assert_allclose(hypothesis.camera_centre, CAMERA_CENTRE, atol=1e-5)
    expected = np.ones(len(boxes), dtype=bool)
    expected[bad] = False
    np.testing.assert_array_equal(hypothesis.inliers, expected)


def test_same_rng_same_hypotheses() -> None:
    camera = make_camera()
    R, t = true_pose()
    track = exact_track(curved_poses(), camera, R, t)
    noisy = MatchedTrack(
        1,
        track.stamps,
        track.boxes + np.random.default_rng(1).normal(0, 3, (len(track.boxes), 1)),
        track.poses,
    )
    runs = [
        create_hypotheses([noisy], camera, VEHICLE, GROUND, HypothesisParams(), np.random.default_rng(11))
        for _ in range(2)
    ]
    np.testing.assert_array_equal(
        runs[0].hypotheses[0].R_cam_from_local, runs[1].hypotheses[0].R_cam_from_local
    )
    np.testing.assert_array_equal(runs[0].hypotheses[0].inliers, runs[1].hypotheses[0].inliers)


def test_rejects_too_few_correspondences() -> None:
    camera = make_camera()
    R, t = true_pose()
    track = exact_track(curved_poses(6), camera, R, t, track_id=9)
    result = solve_one(track, camera)
    assert result.hypotheses == ()
    assert str(result.rejected[9]).startswith("too few correspondences: 6 < 8")
    reason = result.rejected[9]
    assert (reason.code, reason.quantity, reason.value, reason.limit) == (
        "too_few_correspondences",
        "correspondences",
        6,
        8,
    )


def test_rejects_vehicle_parked_in_view() -> None:
    camera = make_camera()
    R, t = true_pose()
    parked = np.repeat(curved_poses()[40:41], 50, axis=0)
    result = solve_one(exact_track(parked, camera, R, t), camera)
    assert str(result.rejected[1]).startswith("not moving in the image")


def test_rejects_box_track_moving_while_the_vehicle_is_parked() -> None:
    # Another car drives through the view while the calibration vehicle waits elsewhere.
    camera = make_camera()
    R, t = true_pose()
    moving = exact_track(curved_poses(50), camera, R, t)
    parked = np.repeat(curved_poses()[:1], 50, axis=0)
    parked[:, 1] += 200.0
    result = solve_one(MatchedTrack(1, moving.stamps, moving.boxes, parked), camera)
    assert str(result.rejected[1]).startswith("vehicle not moving")


def test_rejects_camera_far_from_the_driven_path() -> None:
    camera = make_camera()
    R, t = true_pose()
    track = exact_track(curved_poses(), camera, R, t)
    # The camera stands ~15 m from the turn; with d_thr = 10 m that is too far.
    result = solve_one(track, camera, HypothesisParams(max_camera_distance_m=10.0))
    assert "from the driven path > 10.0 m" in str(result.rejected[1])
    far = result.rejected[1]
    assert far.code == "far_from_path" and far.limit == 10.0 and far.value is not None and far.value > 10.0
    assert solve_one(track, camera, HypothesisParams(max_camera_distance_m=20.0)).rejected == {}


def test_distance_to_path_uses_segments_of_a_sparse_trajectory() -> None:
    # Two poses 400 m apart whose segment passes the turn: vertices are far, the path is not.
    camera = make_camera()
    R, t = true_pose()
    track = exact_track(curved_poses(), camera, R, t)
    sparse = Trajectory(
        stamps=np.array([START_NS, START_NS + 40_000_000_000], dtype=np.int64),
        poses=np.array([[-200.0, 0.0, 0.4, 0.0, 0.0, 0.0], [200.0, 0.0, 0.4, 0.0, 0.0, 0.0]]),
    )
    assert solve_one(track, camera, trajectory=sparse).rejected == {}
    far_poses = sparse.poses.copy()
    far_poses[:, 1] += 300.0
    far_away = Trajectory(stamps=sparse.stamps, poses=far_poses)
    assert "from the driven path" in str(solve_one(track, camera, trajectory=far_away).rejected[1])


def test_rejects_camera_below_ground() -> None:
    camera = make_camera()
    R, t = true_pose()
    track = exact_track(curved_poses(), camera, R, t)
    # A ground plane 12 m up puts the (correct) camera 4 m under it.
    above_camera = GroundPlaneFit(normal=np.array([0.0, 0.0, 1.0]), offset=12.0)
    result = solve_one(track, camera, ground=above_camera)
    assert str(result.rejected[1]).startswith("camera -4.0 m above ground")


def test_rejects_high_median_reprojection_error() -> None:
    # Two rows in three jump 40 px left or right (two vehicles' boxes swapped by the tracker, say): any
    # camera misses at least half of the rows by ~40 px.
    camera = make_camera()
    R, t = true_pose()
    track = exact_track(curved_poses(), camera, R, t)
    jump = np.array([0.0, 40.0, -40.0])[np.arange(len(track.boxes)) % 3]
    boxes = track.boxes + np.column_stack([jump, np.zeros_like(jump), jump, np.zeros_like(jump)])
    result = solve_one(MatchedTrack(1, track.stamps, boxes, track.poses), camera)
    assert str(result.rejected[1]).startswith("median reprojection error")


def road_poses(heading_deg: float, count: int = 120, length_m: float = 40.0) -> np.ndarray:
    """A straight drive from (0, 2) at `heading_deg` (from east, ccw): collinear body centres."""
    heading = math.radians(heading_deg)
    s = np.linspace(0.0, length_m, count)
    zeros = np.zeros(count)
    return np.column_stack(
        [
            s * math.cos(heading),
            2.0 + s * math.sin(heading),
            np.full(count, 0.4),
            np.full(count, heading),
            zeros,
            zeros,
        ]
    )


def tight_boxes(poses: np.ndarray, camera: CameraModel, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The tight boxes (N, 4) of the projected vehicle cuboid, as the simulator's detector draws them."""
    corners, _ = project_points(body_corners(poses, VEHICLE).reshape(-1, 3), R, t, camera)
    corners = corners.reshape(len(poses), 8, 2)
    return np.column_stack([corners.min(axis=1), corners.max(axis=1)])


def visible_track(poses: np.ndarray, camera: CameraModel, R: np.ndarray, t: np.ndarray) -> MatchedTrack:
    """The rows of `poses` whose vehicle box lies inside the image, with tight cuboid boxes (a straight
    track is solved from the box shape, so here the boxes, not the centres, are exact)."""
    _, depth = project_points(body_corners(poses, VEHICLE).reshape(-1, 3), R, t, camera)
    boxes = tight_boxes(poses, camera, R, t)
    inside = (boxes[:, :2] > 0).all(axis=1) & (boxes[:, 2:] < [camera.width, camera.height]).all(axis=1)
    visible = (depth.reshape(len(poses), 8) > 0).all(axis=1) & inside
    stamps = START_NS + FRAME_NS * np.arange(int(visible.sum()), dtype=np.int64)
    return MatchedTrack(track_id=1, stamps=stamps, boxes=boxes[visible], poses=poses[visible])


def test_rejects_straight_line_track_seen_side_on() -> None:
    # The road runs across the image (along the camera's x axis): collinear centres leave the rotation
    # about the road free, and a level camera does not fix it either.
    camera = make_camera()
    R, t = true_pose()
    result = solve_one(exact_track(straight_poses(), camera, R, t), camera)
    reason = str(result.rejected[1])
    assert reason.startswith("degenerate: straight-line track")
    assert "side-on" in reason


def test_straight_line_track_without_the_level_prior_is_rejected() -> None:
    camera = make_camera()
    R, t = true_pose()
    track = visible_track(road_poses(60.0), camera, R, t)
    result = solve_one(track, camera, HypothesisParams(level_camera_prior=False))
    assert str(result.rejected[1]).startswith("degenerate: straight-line track")
    assert "level" not in str(result.rejected[1])


@pytest.mark.parametrize("heading_deg", [30.0, 60.0, 95.0])
def test_straight_track_along_the_view_is_solved_for_a_level_camera(heading_deg: float) -> None:
    camera = make_camera(800.0, -0.05)
    R, t = true_pose(roll_deg=0.0)
    (hypothesis,) = solve_one(visible_track(road_poses(heading_deg), camera, R, t), camera).hypotheses
    assert hypothesis.solver == "level"
    assert rotation_angle_rad(hypothesis.R_cam_from_local, R) < 1e-6
    np.testing.assert_allclose(hypothesis.camera_centre, CAMERA_CENTRE, atol=1e-4)


def test_level_prior_error_follows_the_camera_roll() -> None:
    # A camera rolled 0.7 deg: the exact upright roll turns the camera less than `mount_snap_deg` (1 deg)
    # from the box shape's measurement, so the mount wins and the pose is off by about
    # roll / |sin(road, image x axis)| ~ 0.7 deg; with the snap off, the measured roll is kept.
    camera = make_camera()
    R, t = true_pose(roll_deg=0.7)
    track = visible_track(road_poses(80.0), camera, R, t)
    (hypothesis,) = solve_one(track, camera).hypotheses
    assert hypothesis.solver == "level"
    assert math.radians(0.4) < rotation_angle_rad(hypothesis.R_cam_from_local, R) < math.radians(1.0)
    (measured,) = solve_one(
        track, camera, HypothesisParams(straight_track=StraightTrackParams(mount_snap_deg=0.0))
    ).hypotheses
    assert measured.solver == "box-roll"
    assert rotation_angle_rad(measured.R_cam_from_local, R) < math.radians(0.05)


def test_level_prior_survives_outliers_and_noise() -> None:
    camera = make_camera()
    R, t = true_pose()
    track = visible_track(road_poses(70.0), camera, R, t)
    rng = np.random.default_rng(4)
    boxes = track.boxes + np.tile(rng.normal(0.0, 1.5, (len(track.boxes), 2)), 2)
    bad = rng.choice(len(boxes), size=len(boxes) // 10, replace=False)
    boxes[bad] += 150.0
    result = solve_one(MatchedTrack(1, track.stamps, boxes, track.poses), camera)
    (hypothesis,) = result.hypotheses
    assert hypothesis.solver == "level"
    assert rotation_angle_rad(hypothesis.R_cam_from_local, R) < math.radians(0.5)
    assert not hypothesis.inliers[bad].any()


@pytest.mark.parametrize(("roll_deg", "solver"), [(90.0, "level+90"), (-90.0, "level-90")])
@pytest.mark.parametrize("heading_deg", [30.0, 80.0])
def test_straight_track_seen_by_a_portrait_camera_is_solved(
    roll_deg: float, solver: str, heading_deg: float
) -> None:
    # A camera turned a quarter into portrait (paper IV-A). Assuming it upright puts it ~90 deg off with
    # a perfect fit of the centres; the box shape picks the quarter, and its exact roll fixes the pose.
    camera = make_camera(800.0, -0.05, width=1080, height=1920)
    R, t = true_pose(roll_deg=roll_deg)
    (hypothesis,) = solve_one(visible_track(road_poses(heading_deg), camera, R, t), camera).hypotheses
    assert hypothesis.solver == solver
    assert rotation_angle_rad(hypothesis.R_cam_from_local, R) < 1e-6
    np.testing.assert_allclose(hypothesis.camera_centre, CAMERA_CENTRE, atol=1e-4)


@settings(max_examples=12, deadline=None)
@given(
    mount_deg=st.sampled_from([0.0, 90.0, -90.0]),
    tilt_deg=st.floats(6.0, 14.0),
    sign=st.sampled_from([-1.0, 1.0]),
    heading_deg=st.floats(25.0, 100.0),
    seed=st.integers(0, 2**16),
)
def test_tilted_camera_on_a_straight_track_is_close_or_rejected(
    mount_deg: float, tilt_deg: float, sign: float, heading_deg: float, seed: int
) -> None:
    # A camera mounted 6-14 deg off square (upright or portrait), boxes with 1 px noise: the box shape
    # measures the roll. Where it cannot (a road running straight away from the camera looks alike
    # rolled either way) the track is rejected. Never confidently wrong: 2 deg / 1 m is what grouping
    # tolerates; measured over 480 random draws: worst 1.5 deg / 0.4 m, about 1 in 5 rejected.
    roll_deg = mount_deg + sign * tilt_deg
    camera = make_camera(width=1080, height=1920) if mount_deg else make_camera()
    R, t = true_pose(roll_deg=roll_deg)
    track = visible_track(road_poses(heading_deg), camera, R, t)
    noisy = track.boxes + np.random.default_rng(seed).normal(0.0, 1.0, track.boxes.shape)
    result = solve_one(MatchedTrack(1, track.stamps, noisy, track.poses), camera)
    for hypothesis in result.hypotheses:
        assert rotation_angle_rad(hypothesis.R_cam_from_local, R) < math.radians(2.0)
        assert np.linalg.norm(hypothesis.camera_centre - CAMERA_CENTRE) < 1.0
    assert len(result.hypotheses) + len(result.rejected) == 1


def test_tilted_camera_is_measured_not_assumed_square() -> None:
    # 8 deg of roll: assumed upright, the pose is ~8 deg off; measured from the box shape, within 0.5 deg.
    camera = make_camera()
    R, t = true_pose(roll_deg=8.0)
    track = visible_track(road_poses(60.0), camera, R, t)
    (measured,) = solve_one(track, camera).hypotheses
    assert measured.solver == "box-roll"
    assert rotation_angle_rad(measured.R_cam_from_local, R) < math.radians(0.5)
    (assumed,) = solve_one(
        track, camera, HypothesisParams(straight_track=StraightTrackParams(roll_from_box_shape=False))
    ).hypotheses
    assert assumed.solver == "level"
    assert rotation_angle_rad(assumed.R_cam_from_local, R) > math.radians(5.0)


@pytest.mark.parametrize("heading_deg", [30.0, 80.0])
def test_upside_down_camera_is_rejected_unless_assumed(heading_deg: float) -> None:
    # Roll 180 is not among the default mounts: the box shape shows the camera is not mounted as assumed,
    # and the track is rejected rather than fitted upright. Declared as a mount, it is solved.
    camera = make_camera()
    R, t = true_pose(roll_deg=180.0)
    track = visible_track(road_poses(heading_deg), camera, R, t)
    result = solve_one(track, camera)
    assert result.hypotheses == ()
    assert "not within 15.0 deg of [0.0, 90.0, -90.0] deg" in str(result.rejected[1])
    mounts = HypothesisParams(straight_track=StraightTrackParams(mount_rolls_deg=(0.0, 90.0, -90.0, 180.0)))
    (hypothesis,) = solve_one(track, camera, mounts).hypotheses
    assert hypothesis.solver == "level+180"
    assert rotation_angle_rad(hypothesis.R_cam_from_local, R) < 1e-6


def test_boxes_of_another_size_are_not_the_calibration_vehicle() -> None:
    # A straight track of boxes half as large again as the vehicle's cuboid (a van where the calibration
    # car drove): no pose about the line of a square-mounted camera reproduces them; rejected, not fitted.
    camera = make_camera()
    R, t = true_pose()
    track = visible_track(road_poses(60.0), camera, R, t)
    centres = (track.boxes[:, :2] + track.boxes[:, 2:]) / 2.0
    half = (track.boxes[:, 2:] - track.boxes[:, :2]) * 0.75
    result = solve_one(
        MatchedTrack(1, track.stamps, np.hstack([centres - half, centres + half]), track.poses), camera
    )
    assert result.hypotheses == ()
    assert str(result.rejected[1]).startswith("degenerate: straight-line track")
    assert "straight-track fit" in str(result.rejected[1])


def test_nearly_straight_track_is_settled_by_the_box_shape() -> None:
    # A 40 m stretch of a 800 m radius bend: EPnP's pose is fixed only weakly (1-sigma > 1.5 deg) and
    # several degrees off; the box shape picks the straight-track fit, within 0.5 deg.
    camera = make_camera()
    R, t = true_pose(roll_deg=6.0)
    heading, radius = math.radians(70.0), 800.0
    angle = heading + np.linspace(0.0, 40.0, 120) / radius
    zeros = np.zeros(len(angle))
    poses = np.column_stack(
        [
            radius * (np.sin(angle) - math.sin(heading)),
            2.0 - radius * (np.cos(angle) - math.cos(heading)),
            np.full(len(angle), 0.4),
            angle,
            zeros,
            zeros,
        ]
    )
    track = visible_track(poses, camera, R, t)
    noisy = MatchedTrack(
        1,
        track.stamps,
        track.boxes + np.random.default_rng(0).normal(0.0, 1.0, track.boxes.shape),
        track.poses,
    )
    (free,) = solve_one(noisy, camera, HypothesisParams(level_camera_prior=False)).hypotheses
    assert free.rotation_std_deg > 1.5
    assert rotation_angle_rad(free.R_cam_from_local, R) > math.radians(3.0)
    (settled,) = solve_one(noisy, camera).hypotheses
    assert settled.solver == "box-roll"
    assert rotation_angle_rad(settled.R_cam_from_local, R) < math.radians(0.5)


def test_every_track_is_accounted_for() -> None:
    camera = make_camera()
    R, t = true_pose()
    good = exact_track(curved_poses(), camera, R, t, track_id=1)
    short = exact_track(curved_poses(5), camera, R, t, track_id=2)
    straight = exact_track(straight_poses(), camera, R, t, track_id=3)
    result = create_hypotheses(
        [good, short, straight], camera, VEHICLE, GROUND, HypothesisParams(), np.random.default_rng(0)
    )
    assert [h.track_id for h in result.hypotheses] == [1]
    assert set(result.rejected) == {2, 3}


def test_matched_track_checks_shapes() -> None:
    with pytest.raises(ShapeError, match=r"matched_track\.boxes"):
        MatchedTrack(1, np.zeros(3, dtype=np.int64), np.zeros((3, 5)), np.zeros((3, 6)))
    with pytest.raises(ShapeError, match="2 stamps, 3 boxes"):
        MatchedTrack(1, np.zeros(2, dtype=np.int64), np.zeros((3, 4)), np.zeros((3, 6)))


def image_track(track_id: int, first_frame: int, count: int) -> ImageTrack:
    stamps = START_NS + FRAME_NS * np.arange(first_frame, first_frame + count, dtype=np.int64)
    boxes = np.column_stack(
        [np.arange(count) * 5.0, np.full(count, 100.0), np.arange(count) * 5.0 + 40, np.full(count, 140.0)]
    )
    return ImageTrack(
        track_id=track_id, stamps=stamps, boxes=boxes, classes=np.full(count, 4, dtype=np.int64)
    )


def test_match_tracks_keeps_rows_with_a_pose_and_skips_tracks_outside_the_span() -> None:
    # Poses every 0.5 s over frames 10..50, with a 3 s dropout between frames 20 and 50's first pose.
    pose_frames = np.array([10, 15, 20, 50, 55, 60])
    stamps = START_NS + FRAME_NS * pose_frames
    poses = np.column_stack([pose_frames.astype(float), np.zeros((len(pose_frames), 5))])
    trajectory = Trajectory(stamps=stamps.astype(np.int64), poses=poses)
    params = AssociationParams(max_pose_gap_ns=1_000_000_000)
    tracks = [
        image_track(1, 0, 8),  # frames 0..7: ends before the vehicle's first pose -> skipped
        image_track(2, 5, 20),  # frames 5..24: rows 10..20 have poses
        image_track(3, 18, 40),  # frames 18..57: rows 18..20 and 50..57; the dropout rows are dropped
        image_track(4, 70, 10),  # after the last pose -> skipped
    ]
    matched = match_tracks(tracks, trajectory, params)
    assert [m.track_id for m in matched] == [2, 3]
    frames_2 = (matched[0].stamps - START_NS) // FRAME_NS
    np.testing.assert_array_equal(frames_2, np.arange(10, 21))
    np.testing.assert_allclose(matched[0].poses[:, 0], np.arange(10, 21))  # x interpolates the frame index
    np.testing.assert_array_equal(matched[0].boxes, tracks[1].boxes[5:16])
    frames_3 = (matched[1].stamps - START_NS) // FRAME_NS
    np.testing.assert_array_equal(frames_3, np.concatenate([np.arange(18, 21), np.arange(50, 58)]))


def test_match_tracks_with_empty_trajectory() -> None:
    empty = Trajectory(stamps=np.zeros(0, dtype=np.int64), poses=np.zeros((0, 6)))
    assert match_tracks([image_track(1, 0, 5)], empty, AssociationParams()) == []


def test_camera_centre_property_matches_camera_module() -> None:
    camera = make_camera()
    R, t = true_pose()
    (hypothesis,) = solve_one(exact_track(curved_poses(), camera, R, t), camera).hypotheses
    np.testing.assert_allclose(
        hypothesis.camera_centre, camera_centre(hypothesis.R_cam_from_local, hypothesis.t_cam_from_local)
    )


def test_ransac_budget_still_finds_a_sixty_percent_consensus() -> None:
    # RANSAC's iterations are capped at those that find a 45 % consensus (HypothesisParams.
    # min_consensus_share); 40 % gross outliers leave 60 %, found exactly.
    camera = make_camera()
    R, t = true_pose()
    track = exact_track(curved_poses(), camera, R, t)
    rng = np.random.default_rng(5)
    bad = rng.choice(len(track.boxes), size=len(track.boxes) * 2 // 5, replace=False)
    boxes = track.boxes.copy()
    angle = rng.uniform(0.0, 2.0 * math.pi, len(bad))
    shift = rng.uniform(60.0, 400.0, len(bad))[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    boxes[bad] += np.hstack([shift, shift])
    (hypothesis,) = solve_one(MatchedTrack(1, track.stamps, boxes, track.poses), camera).hypotheses
    assert rotation_angle_rad(hypothesis.R_cam_from_local, R) < 1e-7
    expected = np.ones(len(boxes), dtype=bool)
    expected[bad] = False
    np.testing.assert_array_equal(hypothesis.inliers, expected)


@pytest.mark.parametrize(("slack_m", "accepted"), [(0.02, True), (-0.02, False)])
def test_distance_to_a_dense_trajectory_is_exact_to_centimetres(slack_m: float, accepted: bool) -> None:
    # A 50 Hz trajectory (0.2 m between poses) round the turn's full circle, with a 30 s stop: the path is
    # thinned before the d_thr test, which must still measure the camera's 15.79 m to the circle.
    camera = make_camera()
    R, t = true_pose()
    track = exact_track(curved_poses(), camera, R, t)
    theta = np.linspace(0.0, 2.0 * math.pi, 1257)
    circle = np.column_stack([-10.0 + 40.0 * np.cos(theta), 40.0 + 40.0 * np.sin(theta)])
    xy = np.concatenate([circle[:600], np.repeat(circle[600:601], 1500, axis=0), circle[601:]])
    poses = np.column_stack([xy, np.full(len(xy), 0.4), np.zeros((len(xy), 3))])
    trajectory = Trajectory(START_NS + 20_000_000 * np.arange(len(xy), dtype=np.int64), poses)
    distance_m = float(np.hypot(4.0 + 10.0, -14.0 - 40.0)) - 40.0
    params = HypothesisParams(max_camera_distance_m=distance_m + slack_m)
    result = solve_one(track, camera, params, trajectory=trajectory)
    assert (result.rejected == {}) is accepted


def test_kept_outcomes_are_taken_and_the_other_tracks_fit_as_without_them() -> None:
    camera = make_camera()
    R, t = true_pose()
    exact = exact_track(curved_poses(), camera, R, t)
    noise = np.random.default_rng(3).normal(0.0, 2.0, (2, len(exact.boxes), 1))
    tracks = [MatchedTrack(i + 1, exact.stamps, exact.boxes + noise[i], exact.poses) for i in range(2)]
    reason = Reason("not_seen_before", "kept")

    def run(kept: dict[int, Reason] | None) -> HypothesisSet:
        return create_hypotheses(
            tracks, camera, VEHICLE, GROUND, HypothesisParams(), np.random.default_rng(11), kept=kept
        )

    plain, with_kept = run(None), run({1: reason})
    assert [h.track_id for h in plain.hypotheses] == [1, 2]
    assert with_kept.rejected == {1: reason}
    # Seeds are drawn for every track, kept or not: track 2 fits exactly as it did.
    (second,) = with_kept.hypotheses
    np.testing.assert_array_equal(second.R_cam_from_local, plain.hypotheses[1].R_cam_from_local)
    np.testing.assert_array_equal(second.t_cam_from_local, plain.hypotheses[1].t_cam_from_local)
    np.testing.assert_array_equal(second.inliers, plain.hypotheses[1].inliers)


@pytest.mark.parametrize("poses", [curved_poses(), straight_poses()], ids=["curved", "straight"])
@pytest.mark.parametrize(
    ("moved_m", "turned_deg"), [(0.0, 0.0), (3.0, 0.0), (0.0, 3.0), (2.0, -2.0)], ids=str
)
def test_the_vehicle_track_is_always_shown_by_a_pose_near_the_truth(
    poses: np.ndarray, moved_m: float, turned_deg: float
) -> None:
    """Exact boxes of the vehicle: a pose off by a clock error's v * s (0.2 s at 15 m/s: 3 m along the road)
    or a few degrees still shows the vehicle on them, so an early rejection never drops its track."""
    camera = make_camera()
    R, _ = true_pose()
    track = exact_track(poses, camera, R, -R @ CAMERA_CENTRE)
    R_off = camera_rotation_from_view(math.radians(95.0 + turned_deg), math.radians(18.0), 0.0)
    centre = CAMERA_CENTRE + np.array([moved_m, 0.0, 0.0])
    assert shows_vehicle(track, R_off, -R_off @ centre, camera, VEHICLE, reach=1.0)


def test_another_vehicle_track_is_not_shown() -> None:
    """Boxes where the calibration vehicle was not (another vehicle, seen while it drove elsewhere), and a
    pose that puts the vehicle behind the camera, show nothing."""
    camera = make_camera()
    R, t = true_pose()
    track = exact_track(curved_poses(), camera, R, t)
    away = track.poses + np.array([80.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # 80 m to the side
    elsewhere = MatchedTrack(2, track.stamps, track.boxes, away)
    assert not shows_vehicle(elsewhere, R, t, camera, VEHICLE, reach=1.0)
    behind = camera_rotation_from_view(math.radians(95.0 + 180.0), math.radians(18.0), 0.0)
    assert not shows_vehicle(track, behind, -behind @ CAMERA_CENTRE, camera, VEHICLE, reach=1.0)
