"""The straight-track solver's box fit: its analytic Jacobian against finite differences of the box
residuals, and the fit itself on exact boxes (the solver end to end is in test_hypotheses.py)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.camera import CameraModel, camera_rotation_from_view, project_points, rotation_angle_rad
from pipeline.ground import GroundPlaneFit
from pipeline.straight_track import (
    StraightTrackParams,
    _box_fit_linearised,
    _box_fit_rotation,
    _box_residuals,
    _BoxData,
    _fit_box,
    _image_roll,
    _level_angles,
    _level_basis,
    _level_rotation,
    _level_rotations,
    _LineFamily,
    track_line,
)
from pipeline.vehicle import body_corners
from schemas.common import CameraIntrinsics, VehicleProfile

VEHICLE = VehicleProfile(length=4.6, width=1.9, height=1.5, imu_offset=(1.3, 0.95, 0.4))
GROUND = GroundPlaneFit(normal=np.array([0.0, 0.0, 1.0]), offset=0.0)
CAMERA_CENTRE = np.array([4.0, -14.0, 8.0])


def make_camera(dist: tuple[float, float, float, float, float] = (0.0,) * 5) -> CameraModel:
    return CameraModel.from_intrinsics(
        CameraIntrinsics(width=1920, height=1080, fx=1000.0, fy=1000.0, cx=960.0, cy=540.0, dist=dist)
    )


def straight_poses(count: int = 30) -> np.ndarray:
    zeros = np.zeros(count)
    return np.column_stack(
        [np.linspace(-4.0, 14.0, count), np.full(count, 8.0), np.full(count, 0.4), zeros, zeros, zeros]
    )


def family_of(camera: CameraModel, R: np.ndarray, centre: np.ndarray) -> _LineFamily:
    """The line family of an exact straight track seen from (R, centre): tight boxes of the cuboid."""
    poses = straight_poses()
    corners, depth = project_points(body_corners(poses, VEHICLE).reshape(-1, 3), R, -R @ centre, camera)
    assert np.all(depth > 0)
    corners = corners.reshape(len(poses), 8, 2)
    boxes = np.column_stack([corners.min(axis=1), corners.max(axis=1)])
    origin, direction = track_line(poses[:, :3])
    return _LineFamily(
        origin=origin,
        direction=direction,
        data=_BoxData.of(boxes, poses, VEHICLE, camera),
        camera=camera,
        ground=GROUND,
        mounts=np.radians([0.0, 90.0, -90.0]),
        params=StraightTrackParams(),
        min_camera_height_m=0.0,
        basis=_level_basis(GROUND.normal),
    )


def reference_residuals(x: np.ndarray, family: _LineFamily) -> np.ndarray:
    """The box fit's residuals the long way: `_level_rotations` and the batched `_box_residuals`."""
    R = _level_rotations(x[None, 0], x[None, 1], family.ground.normal, x[None, 2], family.basis)
    residual, in_front = _box_residuals(R, x[None, 3:6], family.data, family.camera)
    assert in_front[0]
    return np.asarray(residual[0][~family.data.on_border])


def pose_vector(R: np.ndarray, centre: np.ndarray) -> np.ndarray:
    up = GROUND.normal
    return np.array([*_level_angles(R, up), _image_roll(R, up), *centre])


@settings(max_examples=40, deadline=None)
@given(
    yaw_deg=st.floats(85.0, 105.0),
    pitch_deg=st.floats(12.0, 25.0),
    roll_deg=st.floats(-10.0, 10.0),
    k1=st.floats(-0.2, 0.1),
    k2=st.floats(-0.05, 0.05),
    p1=st.floats(-0.005, 0.005),
    p2=st.floats(-0.005, 0.005),
    k3=st.floats(-0.01, 0.01),
    nudge=st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6),
)
def test_box_fit_jacobian_matches_finite_differences(
    yaw_deg: float,
    pitch_deg: float,
    roll_deg: float,
    k1: float,
    k2: float,
    p1: float,
    p2: float,
    k3: float,
    nudge: list[float],
) -> None:
    camera = make_camera((k1, k2, p1, p2, k3))
    R = camera_rotation_from_view(math.radians(yaw_deg), math.radians(pitch_deg), math.radians(roll_deg))
    family = family_of(make_camera(), R, CAMERA_CENTRE)  # boxes of the pinhole view, lens of `camera`
    family = _LineFamily(**{**{f: getattr(family, f) for f in family.__slots__}, "camera": camera})
    # Away from the exact pose, so residuals are not all zero: up to 2 deg and 0.5 m off.
    x = pose_vector(R, CAMERA_CENTRE) + np.array(nudge) * np.radians([2.0, 2.0, 2.0, 0, 0, 0])
    x[3:] += 0.5 * np.array(nudge[3:])
    # Off any exact symmetry (a view straight across the road ties two corners for half the edges, where
    # the derivative is one-sided by nature): a fixed turn far larger than the difference steps below.
    x[:3] += np.array([1.3e-4, -0.7e-4, 0.9e-4])
    values, jacobian = _box_fit_linearised(x, family, jacobian=True)
    np.testing.assert_allclose(values, reference_residuals(x, family), rtol=1e-9, atol=1e-9)
    assert jacobian.shape == (len(values), 6)

    def central(h: np.ndarray) -> np.ndarray:
        columns = []
        for k in range(6):
            step = np.zeros(6)
            step[k] = h[k]
            columns.append(
                (reference_residuals(x + step, family) - reference_residuals(x - step, family)) / (2 * h[k])
            )
        return np.column_stack(columns)

    def one_sided(h: np.ndarray, sign: float) -> np.ndarray:
        base = reference_residuals(x, family)
        columns = []
        for k in range(6):
            step = np.zeros(6)
            step[k] = sign * h[k]
            columns.append(sign * (reference_residuals(x + step, family) - base) / h[k])
        return np.column_stack(columns)

    steps = np.array([1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4])
    coarse, fine = central(steps), central(steps / 4.0)
    # An edge whose extreme corner changes within the step has a kink there: the differences are then
    # wrong and disagree with each other. At an exact tie of two corners (a symmetric view) both central
    # differences average the two sides and agree, so the one-sided ones are compared too. Every other
    # edge must match the analytic derivative.
    scale = np.max(np.abs(fine), axis=0) + 1e-12
    forward, backward = one_sided(steps / 4.0, 1.0), one_sided(steps / 4.0, -1.0)
    smooth = np.all(np.abs(coarse - fine) <= 1e-4 * scale, axis=1) & np.all(
        np.abs(forward - backward) <= 1e-3 * scale, axis=1
    )
    assert np.count_nonzero(smooth) >= 0.9 * len(values)
    np.testing.assert_allclose(jacobian[smooth], fine[smooth], rtol=0, atol=1e-4 * float(np.max(scale)))
    # And not trivially: the Jacobian has full rank (every parameter moves some edge).
    assert np.linalg.matrix_rank(jacobian) == 6


def test_box_fit_residuals_of_a_camera_facing_away() -> None:
    R = camera_rotation_from_view(math.radians(95.0), math.radians(18.0), 0.0)
    family = family_of(make_camera(), R, CAMERA_CENTRE)
    x = pose_vector(R, CAMERA_CENTRE)
    x[0] += math.pi  # looking the other way: every corner behind the camera
    values, jacobian = _box_fit_linearised(x, family, jacobian=True)
    assert np.all(values == 1e3) and np.all(jacobian == 0.0)


@pytest.mark.parametrize(
    "dist", [(0.0,) * 5, (-0.12, 0.02, 0.001, -0.001, 0.0)], ids=["pinhole", "distorted"]
)
@pytest.mark.parametrize("free_roll", [True, False])
def test_box_fit_converges_to_the_exact_pose(
    dist: tuple[float, float, float, float, float], free_roll: bool
) -> None:
    camera = make_camera(dist)
    R = camera_rotation_from_view(math.radians(95.0), math.radians(18.0), math.radians(4.0))
    family = family_of(camera, R, CAMERA_CENTRE)
    x = pose_vector(R, CAMERA_CENTRE)
    start_R = _level_rotation(x[0] + math.radians(3.0), x[1] - math.radians(2.0), GROUND.normal, x[2] + 0.03)
    fit = _fit_box(family, start_R, CAMERA_CENTRE + np.array([0.6, -0.4, 0.3]), None if free_roll else x[2])
    assert rotation_angle_rad(fit.R, R) < math.radians(0.01)
    assert np.linalg.norm(fit.C - CAMERA_CENTRE) < 0.01
    assert fit.misfit < 1e-6
    # At the residual floor (1 % of the box diagonal), the 30-row track fixes every angle to a degree.
    assert 0.0 < fit.rotation_std_deg < 1.0


def test_box_fit_rotation_is_level_rotations_to_the_last_bit_and_its_derivative_matches():
    """The per-step rotation is `_level_rotations` written out in Python floats: the same values, and
    dR/d(yaw, pitch, roll) its derivative (central differences)."""
    rng = np.random.default_rng(7)
    for tilt in (0.0, 0.03):
        up = np.array([tilt, -0.5 * tilt, 1.0])
        up /= np.linalg.norm(up)
        family = SimpleNamespace(ground=SimpleNamespace(normal=up), basis=_level_basis(up))
        for _ in range(20):
            x = np.concatenate([rng.uniform(-math.pi, math.pi, 3), rng.normal(0.0, 10.0, 3)])
            R, dR = _box_fit_rotation(x, family, derivatives=True)
            expected = _level_rotations(x[None, 0], x[None, 1], up, x[None, 2], family.basis)[0]
            np.testing.assert_array_equal(R, expected)
            np.testing.assert_array_equal(_box_fit_rotation(x, family, derivatives=False)[0], R)
            for k in range(3):
                step = np.zeros(6)
                step[k] = 1e-6
                plus = _box_fit_rotation(x + step, family, derivatives=False)[0]
                minus = _box_fit_rotation(x - step, family, derivatives=False)[0]
                np.testing.assert_allclose(dR[k], (plus - minus) / 2e-6, atol=1e-8)
