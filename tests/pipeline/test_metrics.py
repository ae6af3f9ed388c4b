"""delta_p / e (paper Sec. IV-B): hand-computed cases, the ground-truth floor, exclusions, evaluation, CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from daemon.cli import main as cli_main
from pipeline.arrays import FloatArray
from pipeline.camera import (
    CameraModel,
    camera_centre,
    camera_rotation_from_view,
    project_points,
    rotation_from_rvec,
)
from pipeline.errors import InputError, ShapeError
from pipeline.ground import GroundPlaneFit
from pipeline.metrics import (
    POSE_CHI2_3SIGMA,
    POSE_CHI2_MEDIAN,
    DeltaPParams,
    delta_p,
    evaluate_against_ground_truth,
    format_evaluation,
    normalised_pose_error,
    result_from_ground_truth,
)
from pipeline.vehicle import body_corners, footprint_corners
from schemas.common import CameraIntrinsics, VehicleProfile
from schemas.files import GroundTruth, GroundTruthFrame
from schemas.results import Uncertainty, Verdict

F = 1000.0
INTRINSICS = CameraIntrinsics(width=1280, height=720, fx=F, fy=F, cx=640.0, cy=360.0)
CAMERA = CameraModel.from_intrinsics(INTRINSICS)
BARREL = (-0.28, 0.09, 0.0005, -0.0004, -0.012)
CAMERA_DISTORTED = CameraModel.from_intrinsics(INTRINSICS.model_copy(update={"dist": BARREL}))
VEHICLE = VehicleProfile(length=4.6, width=1.9, height=1.5, imu_offset=(1.2, 0.95, 0.3))


def extrinsic(
    centre: tuple[float, float, float], yaw: float, pitch_down: float
) -> tuple[FloatArray, FloatArray]:
    """R_cam_from_local, t_cam_from_local of a non-rolled camera at `centre` looking along `yaw`."""
    R = camera_rotation_from_view(yaw, pitch_down)
    return R, -R @ np.asarray(centre, dtype=np.float64)


def exact_boxes(poses: FloatArray, R: FloatArray, t: FloatArray, camera: CameraModel) -> FloatArray:
    """Tight bounds of the 8 projected body corners: what a perfect detector reports."""
    corners = body_corners(poses, VEHICLE)
    pixels, _ = project_points(corners.reshape(-1, 3), R, t, camera)
    pixels = pixels.reshape(len(poses), 8, 2)
    return np.concatenate([pixels.min(axis=1), pixels.max(axis=1)], axis=1)


def poses_in_view(rng: np.random.Generator, n: int, ground_z: float = 0.0) -> FloatArray:
    """Vehicle poses 18-45 m in front of a camera at the origin looking along +x, any heading."""
    poses = np.zeros((n, 6))
    poses[:, 0] = rng.uniform(18.0, 45.0, n)
    poses[:, 1] = rng.uniform(-4.0, 4.0, n)
    poses[:, 2] = ground_z + VEHICLE.imu_offset[2]
    poses[:, 3] = rng.uniform(-math.pi, math.pi, n)
    return poses


# --- hand-computed cases ---------------------------------------------------------------------------------


def test_camera_looking_straight_down_hand_value() -> None:
    # Camera 10 m above the origin looking down with yaw 0: image right = world -y, image down = world -x.
    # The row v = 460 (y = 0.1) back-projects to the ground line x = -0.1 * 10 = -1 m.
    R, t = extrinsic((0.0, 0.0, 10.0), 0.0, math.pi / 2)
    boxes = np.array([[600.0, 400.0, 700.0, 460.0]])
    # A quadrilateral on z = 0 whose corner (-1.25, 0.5) is the one nearest to x = -1.
    footprint = np.array([[[-1.25, 0.5, 0.0], [-3.0, 0.0, 0.0], [-3.5, 2.0, 0.0], [-1.6, 2.6, 0.0]]])
    errors = delta_p(boxes, footprint, R, t, CAMERA)
    assert errors.valid.tolist() == [True]
    assert errors.corner_index.tolist() == [0]
    assert errors.delta_p_m[0] == pytest.approx(0.25, abs=1e-12)
    assert errors.distance_m[0] == pytest.approx(math.sqrt(1.25**2 + 0.5**2 + 10.0**2), abs=1e-12)
    assert errors.e_pct[0] == pytest.approx(25.0 / math.sqrt(101.8125), abs=1e-10)


def test_pitched_camera_hand_value() -> None:
    # Camera 6 m high, pitched 30 deg down, looking along +x. A row 15 deg below the optical axis
    # (v = cy + f tan 15 deg) sees the ground 45 deg below the horizon: the line x = 6 m.
    R, t = extrinsic((0.0, 0.0, 6.0), 0.0, math.radians(30.0))
    v = 360.0 + F * math.tan(math.radians(15.0))
    boxes = np.array([[500.0, v - 120.0, 800.0, v]])
    footprint = np.array([[[6.4, -1.0, 0.0], [10.9, -1.2, 0.0], [11.0, 0.7, 0.0], [6.5, 0.9, 0.0]]])
    errors = delta_p(boxes, footprint, R, t, CAMERA)
    assert errors.corner_index.tolist() == [0]
    assert errors.delta_p_m[0] == pytest.approx(0.4, abs=1e-9)
    distance = math.sqrt(6.4**2 + 1.0 + 36.0)
    assert errors.distance_m[0] == pytest.approx(distance, abs=1e-9)
    assert errors.e_pct[0] == pytest.approx(40.0 / distance, abs=1e-9)
    summary = errors.summary()
    assert summary.delta_p_mean_m == summary.delta_p_max_m == pytest.approx(0.4, abs=1e-9)
    assert (summary.boxes_used, summary.boxes_excluded) == (1, 0)


def test_corner_beyond_the_box_ends_uses_the_infinite_edge_line() -> None:
    # Same geometry; the corner lies far to the side of the box's horizontal extent. The back-projected
    # edge is a line, not the segment under the box, so delta_p is still the perpendicular 0.4 m.
    R, t = extrinsic((0.0, 0.0, 6.0), 0.0, math.radians(30.0))
    v = 360.0 + F * math.tan(math.radians(15.0))
    boxes = np.array([[630.0, v - 50.0, 650.0, v]])  # covers y in about [-0.1, 0.1] m on the ground
    footprint = np.array([[[6.4, -7.0, 0.0], [10.9, -7.2, 0.0], [11.0, -5.3, 0.0], [6.5, -5.1, 0.0]]])
    assert delta_p(boxes, footprint, R, t, CAMERA).delta_p_m[0] == pytest.approx(0.4, abs=1e-9)


def test_explicit_ground_plane_measures_in_that_plane() -> None:
    # Footprint 0.3 m above the given plane z = 0: the corner is dropped onto the plane first, so the
    # distance is the in-plane 0.25 m of the first case, not a slanted 3D distance.
    R, t = extrinsic((0.0, 0.0, 10.0), 0.0, math.pi / 2)
    boxes = np.array([[600.0, 400.0, 700.0, 460.0]])
    footprint = np.array([[[-1.25, 0.5, 0.3], [-3.0, 0.0, 0.3], [-3.5, 2.0, 0.3], [-1.6, 2.6, 0.3]]])
    flat = GroundPlaneFit(normal=np.array([0.0, 0.0, 1.0]), offset=0.0)
    assert delta_p(boxes, footprint, R, t, CAMERA, ground=flat).delta_p_m[0] == pytest.approx(0.25, abs=1e-12)
    # Default: the footprint's own plane z = 0.3 (9.7 m below the camera): the line is x = -0.97.
    assert delta_p(boxes, footprint, R, t, CAMERA).delta_p_m[0] == pytest.approx(0.28, abs=1e-12)


# --- ground-truth floor and perturbations ----------------------------------------------------------------


@pytest.mark.parametrize("camera", [CAMERA, CAMERA_DISTORTED], ids=["pinhole", "distorted"])
def test_true_calibration_scores_zero_on_exact_boxes(camera: CameraModel) -> None:
    rng = np.random.default_rng(3)
    R, t = extrinsic((0.0, 0.0, 8.0), 0.05, math.radians(14.0))
    poses = poses_in_view(rng, 200)
    boxes = exact_boxes(poses, R, t, camera)
    errors = delta_p(boxes, footprint_corners(poses, VEHICLE), R, t, camera)
    assert errors.valid.sum() > 150
    # Pinhole: exact up to floating point. Distorted: the sampled edge's chord sag, well under a mm.
    tolerance = 1e-9 if not camera.has_distortion else 1e-4
    assert np.nanmax(errors.delta_p_m) < tolerance


def test_true_calibration_scores_zero_on_a_slope_with_its_footprint_plane() -> None:
    # Vehicles pitched 6 % uphill on a road rising along +x; a level plane through the camera's foot
    # would misplace the edge, the footprint's own plane does not.
    rng = np.random.default_rng(4)
    R, t = extrinsic((0.0, 0.0, 8.0), 0.0, math.radians(14.0))
    poses = poses_in_view(rng, 50)
    poses[:, 3] = 0.0  # along the slope
    slope = math.atan(0.06)
    poses[:, 4] = -slope  # Ry(pitch) with negative pitch lifts the nose
    poses[:, 2] = poses[:, 0] * 0.06 + VEHICLE.imu_offset[2] / math.cos(slope)
    boxes = exact_boxes(poses, R, t, CAMERA)
    footprints = footprint_corners(poses, VEHICLE)
    own = delta_p(boxes, footprints, R, t, CAMERA)
    level = delta_p(boxes, footprints, R, t, CAMERA, ground=GroundPlaneFit(np.array([0.0, 0.0, 1.0]), 0.0))
    assert np.nanmax(own.delta_p_m) < 1e-9
    assert np.nanmean(level.delta_p_m) > 0.5


def test_delta_p_grows_with_a_perturbed_calibration() -> None:
    rng = np.random.default_rng(5)
    R, t = extrinsic((0.0, 0.0, 8.0), 0.0, math.radians(14.0))
    poses = poses_in_view(rng, 200)
    boxes = exact_boxes(poses, R, t, CAMERA)
    footprints = footprint_corners(poses, VEHICLE)
    means = []
    for tilt_deg in (0.0, 0.1, 0.3, 1.0):
        R_bad, t_bad = extrinsic((0.0, 0.0, 8.0), 0.0, math.radians(14.0 + tilt_deg))
        means.append(np.nanmean(delta_p(boxes, footprints, R_bad, t_bad, CAMERA).delta_p_m))
    assert means[0] < 1e-9
    assert means[1] < means[2] < means[3]
    # Tilting 1 deg down moves a ~30 m edge ~30 * 30 * 0.0175 / 8 m toward the camera: metres, not cm.
    assert means[3] > 1.0


def test_distortion_matters_when_ignored() -> None:
    # Boxes from a distorting lens scored as if the lens were a pinhole: the curve is back-projected
    # wrongly and delta_p is far from zero; with the right model it is ~0. Vehicles spread across the
    # image, where barrel distortion is strong.
    rng = np.random.default_rng(6)
    R, t = extrinsic((0.0, 0.0, 8.0), 0.0, math.radians(14.0))
    poses = poses_in_view(rng, 100)
    poses[:, 0] = rng.uniform(12.0, 22.0, 100)
    poses[:, 1] = rng.uniform(-10.0, 10.0, 100)
    boxes = exact_boxes(poses, R, t, CAMERA_DISTORTED)
    footprints = footprint_corners(poses, VEHICLE)
    right = delta_p(boxes, footprints, R, t, CAMERA_DISTORTED)
    wrong = delta_p(boxes, footprints, R, t, CAMERA)
    assert right.valid.sum() > 60
    assert np.nanmax(right.delta_p_m) < 1e-4
    assert np.nanmean(wrong.delta_p_m) > 0.2
    # Fewer edge samples: a coarser polyline, still close (the chord sag shrinks with the square).
    coarse = delta_p(boxes, footprints, R, t, CAMERA_DISTORTED, params=DeltaPParams(edge_samples=5))
    assert 1e-4 < np.nanmax(coarse.delta_p_m) < 0.02


# --- exclusions and input checks -------------------------------------------------------------------------


def test_border_touching_and_sky_boxes_are_excluded() -> None:
    R, t = extrinsic((0.0, 0.0, 6.0), 0.0, math.radians(30.0))
    horizon_v = 360.0 - F * math.tan(math.radians(30.0))  # about v = -217: use a camera pitched less
    R_low, t_low = extrinsic((0.0, 0.0, 6.0), 0.0, math.radians(5.0))
    horizon_low = 360.0 - F * math.tan(math.radians(5.0))  # v = 272.5
    assert horizon_v < 0.0
    boxes = np.array(
        [
            [0.0, 500.0, 200.0, 600.0],  # touches the left border
            [1000.0, 500.0, 1279.5, 600.0],  # within 1 px of the right border
            [600.0, 620.0, 700.0, 719.5],  # within 1 px of the bottom
            [600.0, 500.0, 700.0, 600.0],  # fine
        ]
    )
    footprint = np.tile(
        np.array([[6.4, -1.0, 0.0], [10.9, -1.2, 0.0], [11.0, 0.7, 0.0], [6.5, 0.9, 0.0]]), (4, 1, 1)
    )
    errors = delta_p(boxes, footprint, R, t, CAMERA)
    assert errors.touches_border.tolist() == [True, True, True, False]
    assert errors.valid.tolist() == [False, False, False, True]
    assert np.isnan(errors.delta_p_m[:3]).all() and errors.corner_index[:3].tolist() == [-1, -1, -1]
    assert errors.summary().boxes_excluded == 3

    sky = np.array([[600.0, 100.0, 700.0, horizon_low - 20.0], [600.0, 100.0, 700.0, horizon_low + 20.0]])
    low = delta_p(sky, footprint[:2], R_low, t_low, CAMERA)
    assert low.misses_ground.tolist() == [True, False]
    assert low.valid.tolist() == [False, True]


def test_all_invalid_summary_is_none_and_shapes_are_checked() -> None:
    R, t = extrinsic((0.0, 0.0, 6.0), 0.0, math.radians(30.0))
    footprint = np.zeros((1, 4, 3))
    summary = delta_p(np.array([[0.0, 0.0, 10.0, 10.0]]), footprint, R, t, CAMERA).summary()
    assert summary.delta_p_mean_m is None and summary.e_max_pct is None and summary.boxes_used == 0
    empty = delta_p(np.zeros((0, 4)), np.zeros((0, 4, 3)), R, t, CAMERA)
    assert empty.delta_p_m.shape == (0,)
    with pytest.raises(ShapeError, match="footprints"):
        delta_p(np.zeros((2, 4)), np.zeros((3, 4, 3)), R, t, CAMERA)
    with pytest.raises(ShapeError, match="boxes"):
        delta_p(np.zeros((2, 5)), np.zeros((2, 4, 3)), R, t, CAMERA)


# --- property: translating the calibration along the ground ----------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    camera_yaw=st.floats(-math.pi, math.pi),
    pitch_deg=st.floats(12.0, 40.0),
    height=st.floats(5.0, 15.0),
    vehicle_yaw=st.floats(-math.pi, math.pi),
    ahead=st.floats(20.0, 35.0),
    back=st.floats(0.0, 3.0),
    sideways=st.floats(-3.0, 3.0),
)
def test_translation_along_the_ground_shifts_delta_p_by_the_forward_component(
    camera_yaw: float,
    pitch_deg: float,
    height: float,
    vehicle_yaw: float,
    ahead: float,
    back: float,
    sideways: float,
) -> None:
    # A non-rolled camera maps an image row to a ground line across its view direction, and the exact box's
    # bottom row holds the nearest footprint corner (all others lie beyond the line). Moving the camera
    # `back` metres backwards and `sideways` metres sideways moves that line `back` metres towards the
    # camera and along itself: delta_p = back, whatever the sideways shift.
    forward = np.array([math.cos(camera_yaw), math.sin(camera_yaw), 0.0])
    right = np.array([math.sin(camera_yaw), -math.cos(camera_yaw), 0.0])
    R, t = extrinsic((0.0, 0.0, height), camera_yaw, math.radians(pitch_deg))
    centre_xy = ahead * forward
    pose = np.array([[centre_xy[0], centre_xy[1], VEHICLE.imu_offset[2], vehicle_yaw, 0.0, 0.0]])
    boxes = exact_boxes(pose, R, t, CAMERA)
    footprints = footprint_corners(pose, VEHICLE)
    moved_centre = camera_centre(R, t) - back * forward + sideways * right
    t_moved = -R @ moved_centre
    errors = delta_p(boxes, footprints, R, t_moved, CAMERA)
    assume(bool(errors.valid[0]))
    assert errors.delta_p_m[0] == pytest.approx(back, abs=1e-7)
    corner = footprints[0, errors.corner_index[0]]
    assert errors.e_pct[0] == pytest.approx(100.0 * back / np.linalg.norm(corner - moved_centre), abs=1e-6)


# --- evaluation against ground truth and the CLI ---------------------------------------------------------

ORIGIN = (500_000.0, 5_400_000.0, 480.0)


def synthetic_truth(n: int = 60, jitter_px: float = 0.0, seed: int = 7) -> GroundTruth:
    """A GroundTruth like the simulator writes: one straight pass, exact (or jittered) calib boxes."""
    rng = np.random.default_rng(seed)
    R, t_local = extrinsic((0.0, 0.0, 8.0), 0.0, math.radians(14.0))
    poses = poses_in_view(rng, n)
    boxes = exact_boxes(poses, R, t_local, CAMERA) + rng.normal(0.0, jitter_px, (n, 4))
    footprints = footprint_corners(poses, VEHICLE)
    origin = np.asarray(ORIGIN)
    frames = [
        GroundTruthFrame(
            stamp_ns=1_700_000_000_000_000_000 + i * 100_000_000,
            calib_box=0,
            traversal=0,
            box=(float(b[0]), float(b[1]), float(b[2]), float(b[3])),
            footprint_local=tuple(tuple(float(c) for c in corner) for corner in fp),
        )
        for i, (b, fp) in enumerate(zip(boxes, footprints, strict=True))
    ]
    frames.append(GroundTruthFrame(stamp_ns=1_700_000_010_000_000_000))  # vehicle out of view
    return GroundTruth(
        camera_id="cam0",
        crs="EPSG:32632",
        origin=ORIGIN,
        R=tuple(tuple(float(v) for v in row) for row in R),
        t_utm=tuple(float(v) for v in t_local - R @ origin),
        t_local=tuple(float(v) for v in t_local),
        camera_position_utm=tuple(float(v) for v in camera_centre(R, t_local) + origin),
        intrinsics=INTRINSICS,
        station_id=42,
        traversals=1,
        frames=frames,
    )


def test_ground_truth_result_scores_its_floor() -> None:
    truth = synthetic_truth()
    evaluation = evaluate_against_ground_truth(result_from_ground_truth(truth, "rsu-1"), truth)
    assert evaluation.boxes_total == 60
    assert evaluation.boxes_used + evaluation.excluded_border + evaluation.excluded_no_ground == 60
    assert evaluation.boxes_used > 40
    assert evaluation.delta_p_max_m is not None and evaluation.delta_p_max_m < 1e-9
    assert evaluation.position_error_m == pytest.approx(0.0, abs=1e-9)
    assert evaluation.rotation_error_deg == pytest.approx(0.0, abs=1e-6)
    assert evaluation.verdict == "accepted" and evaluation.notes == ()
    # Published boxes carry detector jitter: the truth itself no longer scores 0 (the floor to compare to).
    jittered = synthetic_truth(jitter_px=1.0)
    floor = evaluate_against_ground_truth(result_from_ground_truth(jittered, "rsu-1"), jittered)
    assert floor.delta_p_mean_m is not None and 0.01 < floor.delta_p_mean_m < 0.5


def test_evaluation_handles_another_origin_and_measures_pose_errors() -> None:
    truth = synthetic_truth()
    gt = result_from_ground_truth(truth, "rsu-1")
    R = np.asarray(gt.R)
    # The same calibration expressed about an origin 123 m east: t changes, the metrics do not.
    new_origin = np.asarray(ORIGIN) + np.array([123.0, -45.0, 2.0])
    t_new = np.asarray(truth.t_utm) + R @ new_origin
    moved_frame = gt.model_copy(
        update={
            "frame": gt.frame.model_copy(update={"origin": tuple(new_origin)}),
            "t": tuple(float(v) for v in t_new),
        }
    )
    same = evaluate_against_ground_truth(moved_frame, truth)
    assert same.position_error_m == pytest.approx(0.0, abs=1e-6)
    assert same.delta_p_max_m is not None and same.delta_p_max_m < 1e-6
    # Camera centre 0.3 m east and 0.4 m up of the truth: position error 0.5 m, height +0.4 m.
    centre = camera_centre(R, np.asarray(gt.t)) + np.array([0.3, 0.0, 0.4])
    shifted = gt.model_copy(update={"t": tuple(float(v) for v in -R @ centre)})
    ev = evaluate_against_ground_truth(shifted, truth)
    assert ev.position_error_m == pytest.approx(0.5, abs=1e-9)
    assert ev.horizontal_error_m == pytest.approx(0.3, abs=1e-9)
    assert ev.height_error_m == pytest.approx(0.4, abs=1e-9)
    assert ev.rotation_error_deg == pytest.approx(0.0, abs=1e-6)
    assert ev.delta_p_mean_m is not None and ev.delta_p_mean_m > 0.3


def test_evaluation_of_a_refused_result_and_of_another_crs() -> None:
    truth = synthetic_truth(n=5)
    gt = result_from_ground_truth(truth, "rsu-1")
    refused = gt.model_copy(
        update={"R": None, "t": None, "verdict": Verdict(status="refused", reasons=["x"])}
    )
    ev = evaluate_against_ground_truth(refused, truth)
    assert ev.delta_p_mean_m is None and ev.position_error_m is None and ev.boxes_total == 5
    assert "n/a" in format_evaluation(ev)
    other_crs = gt.model_copy(update={"frame": gt.frame.model_copy(update={"crs": "EPSG:32633"})})
    with pytest.raises(InputError, match="EPSG:32633"):
        evaluate_against_ground_truth(other_crs, truth)


def test_cli_evaluate_prints_table_and_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    truth = synthetic_truth(n=20)
    truth_path = tmp_path / "ground_truth.json"
    truth_path.write_text(truth.model_dump_json(indent=2))
    result_path = tmp_path / "result.json"
    result_path.write_text(result_from_ground_truth(truth, "rsu-1").model_dump_json(indent=2))

    assert cli_main(["evaluate", "--calib", str(result_path), "--ground-truth", str(truth_path)]) == 0
    table = capsys.readouterr().out
    assert "delta_p" in table and "ground-truth-cam0" in table and "of 20" in table
    assert "error / reported std" in table

    assert (
        cli_main(["evaluate", "--calib", str(result_path), "--ground-truth", str(truth_path), "--json"]) == 0
    )
    data = json.loads(capsys.readouterr().out)
    assert data["boxes_total"] == 20
    assert "pose_chi2" in data
    assert data["delta_p_max_m"] < 1e-9
    assert data["position_error_m"] == pytest.approx(0.0, abs=1e-9)


_SMALL = st.floats(-0.05, 0.05, allow_nan=False)


@settings(max_examples=40, deadline=None)
@given(
    w=st.tuples(_SMALL, _SMALL, _SMALL),
    c=st.tuples(*(st.floats(-2.0, 2.0, allow_nan=False),) * 3),
    seed=st.integers(0, 2**31 - 1),
)
def test_the_pose_chi2_is_the_error_in_the_reported_covariance(
    w: tuple[float, float, float], c: tuple[float, float, float], seed: int
) -> None:
    """A result off the truth by a known [w, C] (the covariance's convention: R_truth = R expm(-[w]x), C =
    truth minus result) with a reported covariance S scores d^T S^-1 d, whatever the frame's origin."""
    truth = synthetic_truth(n=5)
    gt = result_from_ground_truth(truth, "rsu-1")
    R_truth = np.asarray(truth.R)
    d = np.array([*w, *c])
    R = R_truth @ rotation_from_rvec(d[:3])
    centre_local = camera_centre(R_truth, np.asarray(truth.t_local)) - d[3:]
    origin = np.asarray(ORIGIN) + np.array([55.0, -7.0, 1.0])  # the result's frame about another origin
    t = -R @ (centre_local + np.asarray(ORIGIN) - origin)
    factor = np.random.default_rng(seed).normal(size=(6, 6))
    S = factor @ factor.T + 1e-3 * np.eye(6)
    result = gt.model_copy(
        update={
            "R": tuple(tuple(float(v) for v in row) for row in R),
            "t": tuple(float(v) for v in t),
            "frame": gt.frame.model_copy(update={"origin": tuple(float(v) for v in origin)}),
            "uncertainty": Uncertainty(
                covariance=tuple(tuple(float(v) for v in row) for row in S),  # type: ignore[arg-type]
                position_std_m=1.0,
                rotation_std_deg=1.0,
            ),
        }
    )
    ev = evaluate_against_ground_truth(result, truth)
    assert ev.position_error_m == pytest.approx(float(np.linalg.norm(d[3:])), abs=1e-6)
    assert ev.pose_chi2 == pytest.approx(float(d @ np.linalg.solve(S, d)), rel=1e-5, abs=1e-6)


def test_the_pose_chi2_without_a_covariance_or_of_a_singular_one() -> None:
    truth = synthetic_truth(n=5)
    gt = result_from_ground_truth(truth, "rsu-1")
    assert evaluate_against_ground_truth(gt.model_copy(update={"uncertainty": None}), truth).pose_chi2 is None
    d = np.array([0.0, 0.0, 0.001, 0.1, 0.0, 0.0])
    assert normalised_pose_error(d, np.eye(6)) == pytest.approx(0.010001)
    assert normalised_pose_error(d, np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 0.0])) is None
    with pytest.raises(ShapeError, match="covariance"):
        normalised_pose_error(d, np.eye(5))


def test_the_chi2_reference_values_are_a_6_dof_chi_square() -> None:
    """The honest median and 3-sigma value that evaluate and bench.accuracy print (kept as numbers so
    that pipeline.metrics does not import scipy.stats)."""
    from scipy.stats import chi2

    assert abs(POSE_CHI2_MEDIAN - chi2.median(6)) < 1e-3
    assert abs(POSE_CHI2_3SIGMA - chi2.isf(0.0027, 6)) < 5e-3
