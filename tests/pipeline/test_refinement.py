"""Stage 5 (paper III-F and beyond): bottom-edge refinement (paper one-shot vs iterated) and whole-box
refinement on exact synthetic passes: tight boxes of the vehicle cuboid's 8 projected corners."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.association import MatchedTrack
from pipeline.camera import (
    CameraModel,
    camera_centre,
    camera_rotation_from_view,
    project_points,
    rotation_angle_rad,
    rotation_from_rvec,
    rvec_from_rotation,
)
from pipeline.errors import DegenerateGeometry, ShapeError
from pipeline.ground import GroundPlaneFit, fit_ground_plane
from pipeline.metrics import delta_p
from pipeline.refinement import (
    Refinement,
    RefinementParams,
    _whole_box_residuals,
    refine_bottom_edge,
    refine_whole_box,
)
from pipeline.vehicle import body_corners, footprint_corners
from schemas.common import CameraIntrinsics, VehicleProfile

VEHICLE = VehicleProfile(length=4.7, width=1.85, height=1.5, imu_offset=(1.4, 0.92, 0.3))
START_NS = 1_700_000_000_000_000_000
FRAME_NS = 100_000_000  # 10 fps

Pose = tuple[np.ndarray, np.ndarray]


# ---------------------------------------------------------------------------------------------------------
# Synthetic scene: camera, paths, exact boxes
# ---------------------------------------------------------------------------------------------------------


def make_camera(fx: float = 1000.0, k1: float = 0.0) -> CameraModel:
    return CameraModel.from_intrinsics(
        CameraIntrinsics(
            width=1920, height=1080, fx=fx, fy=fx, cx=960.0, cy=540.0, dist=(k1, 0.0, 0.0, 0.0, 0.0)
        )
    )


def camera_pose(centre: tuple[float, float, float], yaw_deg: float, pitch_down_deg: float) -> Pose:
    R = camera_rotation_from_view(math.radians(yaw_deg), math.radians(pitch_down_deg))
    return R, -R @ np.asarray(centre, dtype=np.float64)


STANDARD = ((0.0, 0.0, 10.0), 0.0, 25.0)  # 10 m high, looking east, 25 deg down


def straight(a: tuple[float, float], b: tuple[float, float], step_m: float = 1.0) -> np.ndarray:
    start, end = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    count = int(np.linalg.norm(end - start) / step_m) + 1
    return start + np.linspace(0.0, 1.0, count)[:, None] * (end - start)


def left_turn(
    start: tuple[float, float], run_in_m: float, radius_m: float, run_out_m: float, step_m: float = 1.0
) -> np.ndarray:
    """Drive east from `start` for run_in_m, turn left 90 deg on radius_m, drive north run_out_m."""
    x0, y0 = start
    run_in = [(x0 + d, y0) for d in np.arange(0.0, run_in_m, step_m)]
    centre = (x0 + run_in_m, y0 + radius_m)
    arc = [
        (centre[0] + radius_m * math.sin(a), centre[1] - radius_m * math.cos(a))
        for a in np.arange(0.0, math.pi / 2, step_m / radius_m)
    ]
    run_out = [(centre[0] + radius_m, centre[1] + d) for d in np.arange(0.0, run_out_m, step_m)]
    return np.array(run_in + arc + run_out)


def junction_paths(step_m: float = 1.0) -> list[np.ndarray]:
    """Three passes in front of the STANDARD camera: across the view, towards it, and a left turn."""
    return [
        straight((25.0, -30.0), (25.0, 30.0), step_m),
        straight((70.0, -4.0), (10.0, -4.0), step_m),
        left_turn((8.0, 3.0), 15.0, 10.0, 30.0, step_m),
    ]


def poses_along(xy: np.ndarray) -> np.ndarray:
    """Level poses (n, 6) along a polyline (n, 2), yaw along the path, reference point at imu height."""
    direction = np.gradient(xy, axis=0)
    poses = np.zeros((len(xy), 6))
    poses[:, :2] = xy
    poses[:, 2] = VEHICLE.imu_offset[2]
    poses[:, 3] = np.arctan2(direction[:, 1], direction[:, 0])
    return poses


def exact_tracks(
    paths: list[np.ndarray], pose: Pose, camera: CameraModel, clip: bool = False
) -> list[MatchedTrack]:
    """One track per path: the tight box of the 8 projected body corners, for every pose in front of the
    camera. clip=False keeps boxes wholly inside the image; clip=True clips boxes at the border instead."""
    R, t = pose
    tracks = []
    for index, xy in enumerate(paths):
        poses = poses_along(xy)
        pixels, depth = project_points(body_corners(poses, VEHICLE).reshape(-1, 3), R, t, camera)
        uv = pixels.reshape(len(poses), 8, 2)
        in_front = np.all(depth.reshape(len(poses), 8) > 1.0, axis=1)
        boxes = np.column_stack(
            [uv[:, :, 0].min(1), uv[:, :, 1].min(1), uv[:, :, 0].max(1), uv[:, :, 1].max(1)]
        )
        if clip:
            keep = in_front & (boxes[:, 2] > 20) & (boxes[:, 0] < camera.width - 20)
            keep &= (boxes[:, 3] > 20) & (boxes[:, 1] < camera.height - 20)
            boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0.0, camera.width)
            boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0.0, camera.height)
        else:
            keep = in_front & (boxes[:, 0] > 2) & (boxes[:, 1] > 2)
            keep &= (boxes[:, 2] < camera.width - 2) & (boxes[:, 3] < camera.height - 2)
        stamps = START_NS + index * 10**12 + FRAME_NS * np.arange(len(poses), dtype=np.int64)
        assert keep.sum() >= 8, "scene: a pass must stay in view"
        tracks.append(MatchedTrack(track_id=index, stamps=stamps[keep], boxes=boxes[keep], poses=poses[keep]))
    return tracks


def with_boxes(tracks: list[MatchedTrack], boxes: list[np.ndarray]) -> list[MatchedTrack]:
    return [MatchedTrack(tr.track_id, tr.stamps, b, tr.poses) for tr, b in zip(tracks, boxes, strict=True)]


def perturbed(pose: Pose, rng: np.random.Generator, shift_m: float = 0.5, angle_deg: float = 2.0) -> Pose:
    """The pose turned by angle_deg about a random axis and its centre moved by shift_m."""
    R, t = pose
    axis = rng.normal(size=3)
    shift = rng.normal(size=3)
    R_new = R @ rotation_from_rvec(axis / np.linalg.norm(axis) * math.radians(angle_deg)).T
    C_new = camera_centre(R, t) + shift / np.linalg.norm(shift) * shift_m
    return R_new, -R_new @ C_new


def track_ground(tracks: list[MatchedTrack]) -> GroundPlaneFit:
    return fit_ground_plane(
        np.concatenate([footprint_corners(tr.poses, VEHICLE).reshape(-1, 3) for tr in tracks])
    )


def pose_errors(result: Refinement, truth: Pose) -> tuple[float, float]:
    """(camera centre error m, rotation error deg)."""
    R, t = truth
    position = float(np.linalg.norm(result.camera_centre - camera_centre(R, t)))
    return position, math.degrees(rotation_angle_rad(result.R_cam_from_local, R))


def start_delta_p(
    tracks: list[MatchedTrack], pose: Pose, camera: CameraModel, ground: GroundPlaneFit
) -> float:
    boxes = np.concatenate([tr.boxes for tr in tracks])
    footprints = np.concatenate([footprint_corners(tr.poses, VEHICLE) for tr in tracks])
    return float(np.nanmean(delta_p(boxes, footprints, pose[0], pose[1], camera, ground).delta_p_m))


# ---------------------------------------------------------------------------------------------------------
# Model and Jacobian
# ---------------------------------------------------------------------------------------------------------


def test_whole_box_model_and_jacobian_match_projection_and_finite_differences() -> None:
    camera = make_camera(fx=800.0, k1=-0.05)
    truth = camera_pose(*STANDARD)
    tracks = exact_tracks(junction_paths(step_m=4.0), truth, camera)
    boxes = np.concatenate([tr.boxes for tr in tracks])
    corners = body_corners(np.concatenate([tr.poses for tr in tracks]), VEHICLE)
    start = perturbed(truth, np.random.default_rng(3))
    R0 = start[0]
    C0 = camera_centre(*start)
    fun = _whole_box_residuals(
        corners, boxes, np.ones(boxes.shape, dtype=bool), R0, C0, camera, RefinementParams()
    )
    p = np.array([0.01, -0.02, 0.015, 0.3, -0.2, 0.1])  # away from 0: exercises the SO(3) left Jacobian
    residual, jac = fun(p)

    # The model box is the tight box of camera.project_points at the pose p describes.
    R = R0 @ rotation_from_rvec(p[:3]).T
    pixels, _ = project_points(corners.reshape(-1, 3), R, -R @ (C0 + p[3:]), camera)
    uv = pixels.reshape(len(boxes), 8, 2)
    model = np.column_stack([uv[:, :, 0].min(1), uv[:, :, 1].min(1), uv[:, :, 0].max(1), uv[:, :, 1].max(1)])
    np.testing.assert_allclose(residual, (model - boxes).ravel(), atol=1e-9)

    step = np.array([1e-6] * 3 + [1e-4] * 3)
    numeric = np.column_stack(
        [
            (fun(p + step[k] * np.eye(6)[k])[0] - fun(p - step[k] * np.eye(6)[k])[0]) / (2 * step[k])
            for k in range(6)
        ]
    )
    np.testing.assert_allclose(jac, numeric, rtol=1e-5, atol=1e-3)


# ---------------------------------------------------------------------------------------------------------
# Whole-box refinement
# ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("fx", "k1"), [(1000.0, 0.0), (800.0, -0.05)])
def test_whole_box_converges_to_truth_on_exact_data(fx: float, k1: float) -> None:
    camera = make_camera(fx, k1)
    truth = camera_pose(*STANDARD)
    tracks = exact_tracks(junction_paths(), truth, camera)
    ground = track_ground(tracks)
    start = perturbed(truth, np.random.default_rng(0))
    result = refine_whole_box(*start, tracks, camera, VEHICLE, RefinementParams(), ground=ground)
    position_m, rotation_deg = pose_errors(result, truth)
    assert position_m < 0.01 and rotation_deg < 0.01
    assert result.converged and result.box_rmse_px < 1e-6
    assert start_delta_p(tracks, start, camera, ground) > 0.1
    assert float(np.nanmax(result.delta_p_m)) < 1e-4  # 0 up to the chord sag of the sampled distorted edge
    np.testing.assert_allclose(result.t_cam_from_local, -result.R_cam_from_local @ result.camera_centre)


def test_whole_box_skips_edges_clipped_at_the_image_border() -> None:
    camera = make_camera()
    truth = camera_pose(*STANDARD)
    tracks = exact_tracks(junction_paths(), truth, camera, clip=True)
    boxes = np.concatenate([tr.boxes for tr in tracks])
    width, height = camera.width - 1.0, camera.height - 1.0
    clipped = np.column_stack(
        [boxes[:, 0] <= 1.0, boxes[:, 1] <= 1.0, boxes[:, 2] >= width, boxes[:, 3] >= height]
    )
    assert clipped.sum() >= 10, "scene: some boxes must be clipped"
    result = refine_whole_box(
        *perturbed(truth, np.random.default_rng(1)), tracks, camera, VEHICLE, RefinementParams()
    )
    position_m, rotation_deg = pose_errors(result, truth)
    assert position_m < 0.01 and rotation_deg < 0.01
    assert np.all(np.isnan(result.residuals_px[clipped])) and np.all(
        np.isfinite(result.residuals_px[~clipped])
    )
    assert result.used_residuals == int((~clipped).sum())


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_whole_box_robust_loss_resists_ten_percent_outlier_boxes(loss: str) -> None:
    camera = make_camera()
    truth = camera_pose(*STANDARD)
    tracks = exact_tracks(junction_paths(), truth, camera)
    rng = np.random.default_rng(5)
    corrupted = []
    for tr in tracks:
        boxes = tr.boxes.copy()
        bad = rng.random(len(boxes)) < 0.1
        boxes[bad] += rng.normal(0.0, 30.0, size=(int(bad.sum()), 4))  # another car, a merged box, ...
        boxes[:, :2] = np.minimum(boxes[:, :2], boxes[:, 2:] - 1.0)
        corrupted.append(boxes)
    noisy = with_boxes(tracks, corrupted)
    start = perturbed(truth, np.random.default_rng(2))
    robust = refine_whole_box(*start, noisy, camera, VEHICLE, RefinementParams(loss=loss))  # type: ignore[arg-type]
    plain = refine_whole_box(*start, noisy, camera, VEHICLE, RefinementParams(loss="linear"))
    position_m, rotation_deg = pose_errors(robust, truth)
    assert position_m < 0.05 and rotation_deg < 0.05
    plain_position_m, plain_rotation_deg = pose_errors(plain, truth)
    assert plain_position_m > 3 * position_m and plain_rotation_deg > 3 * rotation_deg


@settings(max_examples=8, deadline=None)
@given(
    height_m=st.floats(8.0, 12.0),
    yaw_deg=st.floats(-20.0, 20.0),
    pitch_deg=st.floats(18.0, 35.0),
    seed=st.integers(0, 2**16),
)
def test_whole_box_recovers_any_exact_camera(
    height_m: float, yaw_deg: float, pitch_deg: float, seed: int
) -> None:
    camera = make_camera()
    truth = camera_pose((0.0, 0.0, height_m), yaw_deg, pitch_deg)
    tracks = exact_tracks(junction_paths(step_m=2.0), truth, camera)
    start = perturbed(truth, np.random.default_rng(seed))
    result = refine_whole_box(*start, tracks, camera, VEHICLE, RefinementParams())
    position_m, rotation_deg = pose_errors(result, truth)
    assert position_m < 0.01 and rotation_deg < 0.01


# ---------------------------------------------------------------------------------------------------------
# Bottom-edge refinement: the paper's one-shot pairs vs the iterated exact residual
# ---------------------------------------------------------------------------------------------------------


def test_paper_one_shot_leaves_a_bias_that_the_iterated_bottom_edge_removes() -> None:
    camera = make_camera()
    truth = camera_pose(*STANDARD)
    R, t = truth
    tracks = exact_tracks(junction_paths(), truth, camera)
    ground = track_ground(tracks)
    x_axis = R[0]  # the camera's x axis in the local frame
    before, paper_delta_p, paper_rotation_deg = [], [], []
    for seed in range(5):
        start = perturbed(truth, np.random.default_rng(seed))
        before.append(start_delta_p(tracks, start, camera, ground))
        paper = refine_bottom_edge(
            *start, tracks, camera, VEHICLE, ground, RefinementParams(iterate_correspondences=False)
        )
        paper_delta_p.append(float(np.nanmean(paper.delta_p_m)))
        paper_rotation_deg.append(pose_errors(paper, truth)[1])

        iterated = refine_bottom_edge(*start, tracks, camera, VEHICLE, ground, RefinementParams())
        # Iterated to the fixed point: delta_p -> 0 and the rotation is exact...
        assert float(np.nanmax(iterated.delta_p_m)) < 1e-6
        assert pose_errors(iterated, truth)[1] < 0.01
        # ...but a shift of the camera along its own x axis is invisible to bottom edges (and to delta_p):
        # the error lies all in that direction, stays at the start's, and the covariance names it.
        error = iterated.camera_centre - camera_centre(R, t)
        assert np.linalg.norm(error - (error @ x_axis) * x_axis) < 0.01
        assert abs(error @ x_axis) < 0.5 + 1e-3
        assert abs(float(np.dot(iterated.worst_direction, np.concatenate([[0.0] * 3, x_axis])))) > 0.99
        assert iterated.position_std_m > 100.0 and iterated.rotation_std_deg < 0.5

    # Paper Sec. IV-B: pairs taken from the start pose's perspective reduce delta_p but leave a systematic
    # error on exact data (here, from 0.5 m / 2 deg starts, decimetres and about a degree).
    assert np.mean(paper_delta_p) < 0.5 * np.mean(before)
    assert np.mean(paper_delta_p) > 0.05 and np.mean(paper_rotation_deg) > 0.3


def test_delta_p_cannot_see_a_camera_shift_along_its_x_axis_but_the_whole_box_can() -> None:
    camera = make_camera()
    truth = camera_pose(*STANDARD)
    tracks = exact_tracks(junction_paths(), truth, camera)
    ground = track_ground(tracks)
    R, t = truth
    shifted = (R, t - R @ (R[0] * 1.0))  # camera centre moved 1 m along its x axis
    assert start_delta_p(tracks, shifted, camera, ground) < 1e-9
    result = refine_whole_box(*shifted, tracks, camera, VEHICLE, RefinementParams())
    position_m, _ = pose_errors(result, truth)
    assert position_m < 0.01


def test_iterated_bottom_edge_reaches_truth_through_a_distorting_lens() -> None:
    # Distortion bends image rows, which makes the x-axis shift weakly visible to bottom edges as well.
    camera = make_camera(fx=800.0, k1=-0.05)
    truth = camera_pose(*STANDARD)
    tracks = exact_tracks(junction_paths(), truth, camera)
    ground = track_ground(tracks)
    start = perturbed(truth, np.random.default_rng(4))
    iterated = refine_bottom_edge(*start, tracks, camera, VEHICLE, ground, RefinementParams())
    paper = refine_bottom_edge(
        *start, tracks, camera, VEHICLE, ground, RefinementParams(iterate_correspondences=False)
    )
    position_m, rotation_deg = pose_errors(iterated, truth)
    assert position_m < 0.01 and rotation_deg < 0.01
    assert float(np.nanmax(iterated.delta_p_m)) < 1e-4
    assert pose_errors(paper, truth)[1] > 0.2


def test_iterated_bottom_edge_with_cauchy_resists_outlier_bottom_edges() -> None:
    camera = make_camera(fx=800.0, k1=-0.05)
    truth = camera_pose(*STANDARD)
    tracks = exact_tracks(junction_paths(), truth, camera)
    rng = np.random.default_rng(6)
    corrupted = []
    for tr in tracks:
        boxes = tr.boxes.copy()
        bad = rng.random(len(boxes)) < 0.1
        boxes[bad, 3] += rng.choice([-1.0, 1.0], int(bad.sum())) * rng.uniform(10.0, 40.0, int(bad.sum()))
        corrupted.append(boxes)
    result = refine_bottom_edge(
        *perturbed(truth, np.random.default_rng(7)),
        with_boxes(tracks, corrupted),
        camera,
        VEHICLE,
        track_ground(tracks),
        RefinementParams(loss="cauchy"),
    )
    position_m, rotation_deg = pose_errors(result, truth)
    assert position_m < 0.05 and rotation_deg < 0.05


# ---------------------------------------------------------------------------------------------------------
# Covariance
# ---------------------------------------------------------------------------------------------------------


def test_covariance_shows_rotation_about_a_single_straight_road() -> None:
    camera = make_camera(fx=3000.0)  # telephoto, looking down a straight road 60-200 m away
    truth = camera_pose((0.0, 0.0, 10.0), 0.0, math.degrees(math.atan2(10.0, 110.0)))
    road = np.array([1.0, 0.0, 0.0])
    one_line = [
        straight((60.0, 3.0), (200.0, 3.0)),
        straight((200.0, 3.0), (60.0, 3.0)),
        straight((65.0, 3.0), (190.0, 3.0), 1.3),
    ]
    junction = [
        straight((60.0, 3.0), (200.0, 3.0)),
        straight((110.0, -40.0), (110.0, 40.0)),
        left_turn((60.0, -2.0), 40.0, 12.0, 40.0),
    ]
    params = RefinementParams(min_sigma_px=1.0)
    results = {}
    for name, paths in (("line", one_line), ("junction", junction)):
        results[name] = refine_whole_box(*truth, exact_tracks(paths, truth, camera), camera, VEHICLE, params)
    std_about_road = {
        name: math.degrees(math.sqrt(road @ result.covariance[:3, :3] @ road))
        for name, result in results.items()
    }
    assert std_about_road["line"] > 4.0 * std_about_road["junction"]
    assert results["line"].worst_std_m > 4.0 * results["junction"].worst_std_m
    worst_rotation = results["line"].worst_direction[:3]
    assert abs(worst_rotation @ road) > 0.9 * np.linalg.norm(worst_rotation)
    for result in results.values():
        np.testing.assert_allclose(result.covariance, result.covariance.T, rtol=1e-9, atol=1e-18)
        assert np.all(np.linalg.eigvalsh(result.covariance) > 0)


def test_covariance_matches_the_spread_of_estimates_over_noise_seeds() -> None:
    camera = make_camera()
    truth = camera_pose(*STANDARD)
    R, t = truth
    tracks = exact_tracks(junction_paths(), truth, camera)
    errors, covariances, sigmas = [], [], []
    for seed in range(30):
        rng = np.random.default_rng(100 + seed)
        noisy = with_boxes(tracks, [tr.boxes + rng.normal(0.0, 1.0, tr.boxes.shape) for tr in tracks])
        result = refine_whole_box(*truth, noisy, camera, VEHICLE, RefinementParams())
        # Refinement.covariance is of [w, C] with R_true = R_est expm(-[w]x), C_true = C_est + dC; the
        # negated error [rvec(R_est^T R_true), C_est - C_true] has the same covariance.
        errors.append(
            np.concatenate(
                [
                    rvec_from_rotation(result.R_cam_from_local.T @ R),
                    result.camera_centre - camera_centre(R, t),
                ]
            )
        )
        covariances.append(result.covariance)
        sigmas.append(result.sigma_px)
    empirical = np.cov(np.array(errors).T)
    predicted = np.mean(covariances, axis=0)
    # Generalised eigenvalues: the std ratio along every direction, invariant to units and correlations.
    ratios = np.sqrt(np.linalg.eigvals(np.linalg.solve(predicted, empirical)).real)
    assert np.all(ratios > 0.5) and np.all(ratios < 2.0)
    assert 0.8 < float(np.mean(sigmas)) < 1.2  # the residual std recovers the 1 px box noise


# ---------------------------------------------------------------------------------------------------------
# Bookkeeping and bad input
# ---------------------------------------------------------------------------------------------------------


def test_result_rows_follow_the_tracks() -> None:
    camera = make_camera()
    truth = camera_pose(*STANDARD)
    tracks = exact_tracks(junction_paths(step_m=2.0), truth, camera)
    result = refine_whole_box(*truth, tracks, camera, VEHICLE, RefinementParams())
    n = sum(len(tr.boxes) for tr in tracks)
    assert result.residuals_px.shape == (n, 4) and result.delta_p_m.shape == (n,)
    assert result.covariance.shape == (6, 6) and result.worst_direction.shape == (6,)
    np.testing.assert_array_equal(
        result.box_track_ids, np.concatenate([np.full(len(tr.boxes), tr.track_id) for tr in tracks])
    )
    np.testing.assert_array_equal(result.stamps, np.concatenate([tr.stamps for tr in tracks]))
    assert result.method == "whole_box" and result.sigma_px == 0.5  # exact data: the floor
    # The eigen-decomposition in scene units reproduces the covariance, largest std first.
    V, stds = result.principal_directions, result.principal_stds_m
    np.testing.assert_allclose(V.T @ V, np.eye(6), atol=1e-12)
    assert np.all(np.diff(stds) <= 0) and result.worst_std_m == stds[0]
    scale = np.array([result.scene_range_m] * 3 + [1.0] * 3)
    np.testing.assert_allclose(
        (V * stds**2) @ V.T, result.covariance * np.outer(scale, scale), rtol=1e-8, atol=1e-16
    )


def test_pose_bias_adds_to_the_camera_centre_variance_only() -> None:
    camera = make_camera()
    truth = camera_pose(*STANDARD)
    tracks = exact_tracks(junction_paths(step_m=2.0), truth, camera)
    plain = refine_whole_box(*truth, tracks, camera, VEHICLE, RefinementParams())
    biased = refine_whole_box(*truth, tracks, camera, VEHICLE, RefinementParams(pose_bias_std_m=0.05))
    expected = plain.covariance.copy()
    expected[3:, 3:] += 0.05**2 * np.eye(3)
    np.testing.assert_allclose(biased.covariance, expected, rtol=1e-9, atol=1e-15)
    assert biased.position_std_m > 0.05 > plain.position_std_m


def test_bad_input_is_refused_with_a_reason() -> None:
    camera = make_camera()
    truth = camera_pose(*STANDARD)
    tracks = exact_tracks(junction_paths(step_m=2.0), truth, camera)
    ground = track_ground(tracks)
    with pytest.raises(DegenerateGeometry, match="no boxes"):
        refine_whole_box(*truth, [], camera, VEHICLE, RefinementParams())
    with pytest.raises(ShapeError, match="R_cam_from_local"):
        refine_whole_box(truth[0][:2], truth[1], tracks, camera, VEHICLE, RefinementParams())
    nan_boxes = tracks[0].boxes.copy()
    nan_boxes[0, 0] = np.nan
    with pytest.raises(ShapeError, match="NaN"):
        refine_bottom_edge(
            *truth,
            [MatchedTrack(0, tracks[0].stamps, nan_boxes, tracks[0].poses)],
            camera,
            VEHICLE,
            ground,
            RefinementParams(),
        )
    few = [MatchedTrack(0, tracks[0].stamps[:3], tracks[0].boxes[:3], tracks[0].poses[:3])]
    with pytest.raises(DegenerateGeometry, match="bottom edges"):
        refine_bottom_edge(*truth, few, camera, VEHICLE, ground, RefinementParams())
    with pytest.raises(ValueError, match="f_scale_px"):
        RefinementParams(f_scale_px=0.0)
