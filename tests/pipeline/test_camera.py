"""Camera geometry against independent references: cv2.projectPoints, scipy rotations, round trips."""

from __future__ import annotations

import math
import warnings

import cv2
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation as SciRotation

from pipeline.arrays import FloatArray
from pipeline.camera import (
    MAX_MODEL_RADIUS,
    MIN_RADIAL_MAGNIFICATION,
    CameraModel,
    camera_centre,
    camera_rotation_from_view,
    distort_normalized,
    model_radius_limit,
    opencv_dist,
    project_points,
    project_points_cam,
    quaternion_wxyz_from_rotation,
    rotation_angle_rad,
    rotation_from_rvec,
    rotation_from_ypr,
    rvec_from_rotation,
    undistort_pixels,
)
from pipeline.errors import ShapeError
from pipeline.refinement import _project, _project_jacobian
from schemas.common import CameraIntrinsics
from sim.lens import opencv_undistort

angles = st.floats(-math.pi, math.pi)
unit = st.floats(-1.0, 1.0)


# Wide lenses fitted with OpenCV's rational model (CALIB_RATIONAL_MODEL): numerator and denominator
# coefficients of similar size that nearly cancel, as such fits give.
RATIONAL_WIDE = (2.1, 0.6, 0.0004, -0.0003, 0.01, 2.45, 1.3, 0.08)


@st.composite
def cameras(draw: st.DrawFn, distortion: bool = True, rational: bool = False) -> CameraModel:
    """Realistic pinhole cameras with OpenCV distortion of the size real lenses show: [k1, k2, p1, p2, k3],
    or with `rational` the rational model's [k1, k2, p1, p2, k3, k4, k5, k6]."""
    width = draw(st.integers(320, 4096))
    height = draw(st.integers(240, 3000))
    fx = draw(st.floats(300.0, 4000.0))
    dist: tuple[float, ...] = (0.0,) * 5
    if rational:
        k4 = draw(st.floats(-0.3, 3.0))
        dist = (
            k4 + draw(st.floats(-0.5, 0.3)),  # k1: close to k4, a little barrel or pincushion
            draw(st.floats(-0.2, 1.5)),  # k2
            draw(st.floats(-0.005, 0.005)),  # p1
            draw(st.floats(-0.005, 0.005)),  # p2
            draw(st.floats(-0.05, 0.1)),  # k3
            k4,
            draw(st.floats(-0.2, 2.0)),  # k5
            draw(st.floats(-0.05, 0.3)),  # k6
        )
    elif distortion:
        dist = (
            draw(st.floats(-0.4, 0.4)),  # k1
            draw(st.floats(-0.2, 0.2)),  # k2
            draw(st.floats(-0.005, 0.005)),  # p1
            draw(st.floats(-0.005, 0.005)),  # p2
            draw(st.floats(-0.05, 0.05)),  # k3
        )
    intrinsics = CameraIntrinsics(
        width=width,
        height=height,
        fx=fx,
        fy=fx * draw(st.floats(0.95, 1.05)),
        cx=width / 2.0 + draw(st.floats(-50.0, 50.0)),
        cy=height / 2.0 + draw(st.floats(-50.0, 50.0)),
        dist=dist,
    )
    return CameraModel.from_intrinsics(intrinsics)


def rational_radial(dist: FloatArray, r: FloatArray) -> FloatArray:
    """rho(r) of OpenCV's rational model, written out from its documentation (independent of the module);
    `dist` of 5 or 8 values (a drawn rational lens with k4 = k5 = k6 = 0 is held as 5)."""
    k1, k2, _, _, k3, k4, k5, k6 = np.concatenate([dist, np.zeros(8 - len(dist))])
    r2 = r * r
    return np.asarray(r * (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3))


@st.composite
def rotations(draw: st.DrawFn) -> FloatArray:
    """Uniform-ish random rotations (normalised Gaussian quaternion)."""
    q = np.array([draw(st.floats(-1.0, 1.0)) for _ in range(4)])
    assume(np.linalg.norm(q) > 0.1)
    return np.asarray(SciRotation.from_quat(q / np.linalg.norm(q)).as_matrix())


@st.composite
def poses_and_points(
    draw: st.DrawFn, max_normalized: float = 0.8
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(R_cam_from_local, t_cam_from_local, points_local (N, 3)) with every point 1-200 m in front."""
    R = draw(rotations())
    t = np.array([draw(st.floats(-100.0, 100.0)) for _ in range(3)])
    n = draw(st.integers(1, 20))
    xy = draw(arrays(np.float64, (n, 2), elements=st.floats(-max_normalized, max_normalized)))
    z = draw(arrays(np.float64, (n, 1), elements=st.floats(1.0, 200.0)))
    points_cam = np.hstack([xy * z, z])
    return R, t, (points_cam - t) @ R  # R^T (X_cam - t), row-wise


def is_monotonic(dist: FloatArray, max_r: float) -> bool:
    """r -> r (1 + k1 r^2 + k2 r^4 + k3 r^6) keeps increasing out to max_r (else the lens model folds)."""
    k1, k2, _, _, k3 = dist
    r = np.linspace(0.0, max_r, 200)
    slope = 1.0 + 3.0 * k1 * r**2 + 5.0 * k2 * r**4 + 7.0 * k3 * r**6
    return bool(np.all(slope > 0.2))


# --- projection ------------------------------------------------------------------------------------------


@settings(max_examples=150, deadline=None)
@given(camera=st.one_of(cameras(), cameras(rational=True)), scene=poses_and_points())
def test_project_points_equals_opencv(
    camera: CameraModel, scene: tuple[FloatArray, FloatArray, FloatArray]
) -> None:
    R, t, points_local = scene
    pixels, depth = project_points(points_local, R, t, camera)
    rvec = SciRotation.from_matrix(R).as_rotvec()
    expected, _ = cv2.projectPoints(points_local, rvec, t, camera.K, camera.dist)
    # OpenCV's polynomial everywhere; ours only out to where the lens model holds, no pixel beyond.
    points_cam = points_local @ R.T + t
    r = np.hypot(points_cam[:, 0], points_cam[:, 1]) / points_cam[:, 2]
    held = r <= camera.undistorted_limit
    assume(abs(r - camera.undistorted_limit).min() > 1e-9)
    np.testing.assert_allclose(pixels[held], expected.reshape(-1, 2)[held], rtol=0, atol=1e-6)
    assert np.isnan(pixels[~held]).all()
    np.testing.assert_allclose(depth, points_cam[:, 2], rtol=1e-12, atol=1e-9)


@settings(max_examples=50, deadline=None)
@given(camera=cameras(distortion=False), scene=poses_and_points())
def test_project_points_without_distortion_equals_opencv(
    camera: CameraModel, scene: tuple[FloatArray, FloatArray, FloatArray]
) -> None:
    R, t, points_local = scene
    pixels, _ = project_points(points_local, R, t, camera)
    expected, _ = cv2.projectPoints(points_local, SciRotation.from_matrix(R).as_rotvec(), t, camera.K, None)
    np.testing.assert_allclose(pixels, expected.reshape(-1, 2), rtol=0, atol=1e-6)


def test_points_behind_or_on_the_camera_plane_project_to_nan() -> None:
    camera = CameraModel.from_intrinsics(
        CameraIntrinsics(width=1920, height=1080, fx=1000.0, fy=1000.0, cx=960.0, cy=540.0)
    )
    points_cam = np.array([[0.0, 0.0, 10.0], [1.0, 2.0, -5.0], [1.0, 1.0, 0.0], [0.5, 0.5, 1e-12]])
    pixels, depth = project_points(points_cam, np.eye(3), np.zeros(3), camera)
    np.testing.assert_allclose(pixels[0], [960.0, 540.0])
    assert np.isnan(pixels[1:]).all()
    np.testing.assert_array_equal(depth, points_cam[:, 2])


def test_project_points_checks_shapes() -> None:
    camera = CameraModel(np.eye(3), np.zeros(5), 100, 100)
    with pytest.raises(ShapeError, match=r"points_local: expected \(N, 3\), got \(4, 2\)"):
        project_points(np.zeros((4, 2)), np.eye(3), np.zeros(3), camera)
    with pytest.raises(ShapeError, match="points_cam"):
        project_points_cam(np.zeros(3), camera)


# --- distortion ------------------------------------------------------------------------------------------


@settings(max_examples=100, deadline=None)
@given(camera=cameras(), data=st.data())
def test_undistort_inverts_the_distortion(camera: CameraModel, data: st.DataObject) -> None:
    max_r = 0.8
    assume(is_monotonic(camera.dist, max_r * math.sqrt(2.0)))
    xy = data.draw(arrays(np.float64, (data.draw(st.integers(1, 30)), 2), elements=st.floats(-max_r, max_r)))
    pixels = project_points_cam(np.hstack([xy, np.ones((len(xy), 1))]), camera)
    recovered = undistort_pixels(pixels, camera)
    np.testing.assert_allclose(recovered, xy, rtol=0, atol=1e-11)
    reprojected = project_points_cam(np.hstack([recovered, np.ones((len(xy), 1))]), camera)
    np.testing.assert_allclose(reprojected, pixels, rtol=0, atol=1e-9)


def test_undistort_wide_angle_up_to_the_image_corners() -> None:
    # fx 800 on a 1920 x 1080 sensor: 100 deg horizontal field of view, barrel k1 = -0.05.
    camera = CameraModel.from_intrinsics(
        CameraIntrinsics(
            width=1920, height=1080, fx=800.0, fy=800.0, cx=960.0, cy=540.0, dist=(-0.05, 0.0, 0.0, 0.0, 0.0)
        )
    )
    u, v = np.meshgrid(np.linspace(0.0, 1919.0, 41), np.linspace(0.0, 1079.0, 23))
    pixels = np.column_stack([u.ravel(), v.ravel()])
    xy = undistort_pixels(pixels, camera)
    assert np.isfinite(xy).all()
    reprojected = project_points_cam(np.hstack([xy, np.ones((len(xy), 1))]), camera)
    np.testing.assert_allclose(reprojected, pixels, rtol=0, atol=1e-9)
    # Barrel distortion: the corner's true ray lies further out than the distorted pixel suggests.
    corner = undistort_pixels(np.array([[0.0, 0.0]]), camera)[0]
    assert np.all(np.abs(corner) > np.array([960.0, 540.0]) / 800.0)


def test_undistort_matches_opencv_for_mild_distortion() -> None:
    camera = CameraModel.from_intrinsics(
        CameraIntrinsics(
            width=1280,
            height=720,
            fx=900.0,
            fy=905.0,
            cx=640.0,
            cy=360.0,
            dist=(-0.1, 0.02, 0.001, -0.0005, 0.0),
        )
    )
    pixels = np.array([[0.0, 0.0], [640.0, 360.0], [1279.0, 719.0], [100.0, 600.0]])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    expected = opencv_undistort(pixels, camera.K, camera.dist, criteria)
    np.testing.assert_allclose(undistort_pixels(pixels, camera), expected, atol=1e-8)


def test_undistort_with_skew_inverts_projection() -> None:
    K = np.array([[1000.0, 3.0, 640.0], [0.0, 990.0, 360.0], [0.0, 0.0, 1.0]])
    xy = np.array([[0.1, -0.2], [-0.3, 0.25], [0.0, 0.0]])
    for dist in (np.zeros(5), np.array([-0.1, 0.01, 0.0, 0.0, 0.0])):
        camera = CameraModel(K, dist, 1280, 720)
        pixels = project_points_cam(np.hstack([xy, np.ones((3, 1))]), camera)
        np.testing.assert_allclose(undistort_pixels(pixels, camera), xy, atol=1e-12)


# --- where the lens model holds --------------------------------------------------------------------------


def radial_slope(dist: FloatArray, r: FloatArray) -> FloatArray:
    """d rho / d r of rho = r (1 + k1 r^2 + k2 r^4 + k3 r^6)."""
    k1, k2, _, _, k3 = dist
    return np.asarray(1.0 + 3.0 * k1 * r**2 + 5.0 * k2 * r**4 + 7.0 * k3 * r**6)


def radial(dist: FloatArray, r: FloatArray) -> FloatArray:
    k1, k2, _, _, k3 = dist
    return np.asarray(r * (1.0 + k1 * r**2 + k2 * r**4 + k3 * r**6))


@settings(max_examples=200, deadline=None)
@given(camera=cameras())
def test_radius_limit_is_where_the_radial_slope_reaches_its_floor(camera: CameraModel) -> None:
    limit = camera.radius_limit
    r = np.linspace(0.0, MAX_MODEL_RADIUS, 100001)
    slope = radial_slope(camera.dist, r)
    below = np.flatnonzero(slope <= MIN_RADIAL_MAGNIFICATION)
    if math.isinf(limit):
        assert len(below) == 0
        return
    # The first radius where the slope falls to the floor, found by a dense scan, maps to the limit.
    assert len(below) > 0
    r_floor = r[below[0]]
    assert radial(camera.dist, np.array(r_floor)) == pytest.approx(limit, abs=2e-4 * max(1.0, limit))


def test_radius_limit_of_lenses_with_and_without_a_turn() -> None:
    assert model_radius_limit(np.zeros(5)) == math.inf
    # A strong but physical barrel lens never turns back; pincushion never does.
    assert model_radius_limit(np.array([-0.25, 0.06, 0.0005, -0.0004, 0.0])) == math.inf
    assert model_radius_limit(np.array([0.2, 0.0, 0.0, 0.0, 0.0])) == math.inf
    # k1 alone: slope 1 + 3 k1 r^2 = 0.1 at r^2 = 0.9 / (-3 k1); rho = r (1 + k1 r^2).
    r2 = 0.9 / 0.9
    assert model_radius_limit(np.array([-0.3, 0.0, 0.0, 0.0, 0.0])) == pytest.approx(
        math.sqrt(r2) * (1.0 - 0.3 * r2)
    )


def test_a_fitted_polynomial_that_turns_back_inside_the_image_is_flagged_there_only() -> None:
    # fx 900 on 1920 x 1080: the corners lie at rho 1.22; this polynomial turns back at rho 1.01.
    camera = CameraModel.from_intrinsics(
        CameraIntrinsics(
            width=1920, height=1080, fx=900.0, fy=900.0, cx=960.0, cy=540.0,
            dist=(-0.30, 0.09, 0.0005, -0.0004, -0.012),
        )
    )  # fmt: skip
    assert 1.0 < camera.radius_limit < math.hypot(960.0, 540.0) / 900.0
    pixels = np.array([[960.0, 540.0], [1800.0, 540.0], [1919.0, 1079.0], [0.0, 0.0], [960.0, 1079.0]])
    np.testing.assert_array_equal(camera.beyond_model(pixels), [False, False, True, True, False])
    assert camera.model_limit_px() == pytest.approx(900.0 * camera.radius_limit)
    # Inside the limit every pixel undistorts and reprojects exactly; beyond it the model cannot reach the
    # corner at all (no undistorted point projects there).
    inside = np.array([[960.0 + 0.99 * camera.model_limit_px(), 540.0], [1500.0, 900.0]])
    xy = undistort_pixels(inside, camera)
    reprojected = project_points_cam(np.hstack([xy, np.ones((len(xy), 1))]), camera)
    np.testing.assert_allclose(reprojected, inside, rtol=0, atol=1e-6)
    r = np.linspace(0.0, 5.0, 50001)
    assert radial(camera.dist, r).max() < math.hypot(960.0, 540.0) / 900.0


def _turning_camera() -> CameraModel:
    # The k1 -0.05 polynomial (a wide 800 px lens on 1920 x 1200): the image ends at rho 1.41, the model
    # turns at r 2.58 / rho 1.71, and a point at r 3.5 (74 deg off axis) would land back at rho 1.36.
    return CameraModel.from_intrinsics(
        CameraIntrinsics(
            width=1920, height=1200, fx=800.0, fy=800.0, cx=960.0, cy=600.0, dist=(-0.05, 0.0, 0.0, 0.0, 0.0)
        )
    )  # fmt: skip


def test_points_beyond_the_lens_model_have_no_pixel() -> None:
    camera = _turning_camera()
    r_limit = camera.undistorted_limit
    assert radial(camera.dist, np.array(r_limit)) == pytest.approx(camera.radius_limit)
    assert radial_slope(camera.dist, np.array(r_limit)) == pytest.approx(MIN_RADIAL_MAGNIFICATION)
    # Without the limit the point 74 deg off axis would project inside the image.
    folded = 800.0 * float(radial(camera.dist, np.array(3.5)))
    assert folded < math.hypot(960.0, 600.0)
    directions = np.array([[3.5, 0.0, 1.0], [0.0, -3.5, 1.0], [0.99 * r_limit, 0.0, 1.0], [1.2, 0.5, 1.0]])
    pixels = project_points_cam(directions, camera)
    assert np.isnan(pixels[:2]).all()
    assert np.isfinite(pixels[2:]).all()
    pixels, depth = project_points(3.0 * directions, np.eye(3), np.zeros(3), camera)
    assert np.isnan(pixels[:2]).all() and np.isfinite(pixels[2:]).all()
    np.testing.assert_array_equal(depth, 3.0)


def test_solver_projection_holds_points_beyond_the_lens_model_on_its_rim() -> None:
    camera = _turning_camera()
    r_limit, rim_px = camera.undistorted_limit, camera.model_limit_px()
    angles = np.linspace(0.0, 2.0 * math.pi, 7)
    for r in (1.01 * r_limit, 3.5, 9.0):
        points = np.column_stack([r * np.cos(angles), r * np.sin(angles), np.ones_like(angles)])
        uv = _project(points, camera, 0.1)
        # On the rim, in the point's own direction: never back inside the image.
        np.testing.assert_allclose(np.hypot(uv[:, 0] - 960.0, uv[:, 1] - 600.0), rim_px, rtol=1e-9)
        np.testing.assert_allclose(np.arctan2(uv[:, 1] - 600.0, uv[:, 0] - 960.0), np.arctan2(
            np.sin(angles), np.cos(angles)), atol=1e-9)  # fmt: skip
    # Inside the limit the solver's projection is the camera's.
    inside = np.array([[0.5 * r_limit, 0.3, 1.0], [0.0, 0.999 * r_limit, 1.0]])
    np.testing.assert_array_equal(_project(inside, camera, 0.1), project_points_cam(inside, camera))


@settings(max_examples=100, deadline=None)
@given(
    r=st.floats(0.2, 8.0),
    angle=st.floats(-math.pi, math.pi),
    depth=st.floats(2.0, 50.0),
    dist=st.sampled_from(
        [(-0.05, 0.0, 0.001, -0.002, 0.0), (-0.30, 0.09, 0.0005, -0.0004, -0.012), RATIONAL_WIDE]
    ),
)
def test_solver_projection_jacobian_matches_finite_differences_inside_and_beyond_the_model(
    r: float, angle: float, depth: float, dist: tuple[float, ...]
) -> None:
    camera = CameraModel.from_intrinsics(
        CameraIntrinsics(width=1920, height=1200, fx=800.0, fy=820.0, cx=955.0, cy=610.0, dist=dist)
    )
    assume(abs(r - camera.undistorted_limit) > 1e-3)  # the clamp's kink
    point = np.array([[r * math.cos(angle) * depth, r * math.sin(angle) * depth, depth]])
    d_point = np.zeros((1, 3, 6))
    d_point[0, :, 3:] = np.eye(3)  # derivatives with respect to the point itself
    analytic = _project_jacobian(point, d_point, camera, 0.1)[0, :, 3:]
    step = 1e-6 * depth
    numeric = np.column_stack(
        [(_project(point + step * e, camera, 0.1) - _project(point - step * e, camera, 0.1))[0] / (2 * step)
         for e in np.eye(3)]
    )  # fmt: skip
    np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-5 * np.abs(numeric).max())


def test_a_lens_that_never_turns_back_flags_no_pixel() -> None:
    camera = CameraModel(np.array([[900.0, 0, 960], [0, 900, 540], [0, 0, 1]]), np.zeros(5), 1920, 1080)
    assert not camera.beyond_model(np.array([[-1e6, -1e6], [0.0, 0.0]])).any()


# --- the rational model and OpenCV's other vector lengths -------------------------------------------------


@settings(max_examples=100, deadline=None)
@given(camera=cameras(rational=True), data=st.data())
def test_undistort_inverts_the_rational_model(camera: CameraModel, data: st.DataObject) -> None:
    max_r = 0.8
    xy = data.draw(arrays(np.float64, (data.draw(st.integers(1, 30)), 2), elements=st.floats(-max_r, max_r)))
    # Directions where the model holds (beyond, one that turns back shares their pixels with others).
    assume(np.hypot(xy[:, 0], xy[:, 1]).max() < 0.999 * camera.undistorted_limit)
    pixels = project_points_cam(np.hstack([xy, np.ones((len(xy), 1))]), camera)
    recovered = undistort_pixels(pixels, camera)
    np.testing.assert_allclose(recovered, xy, rtol=0, atol=1e-10)


@settings(max_examples=200, deadline=None)
@given(camera=cameras(rational=True))
def test_the_rational_model_holds_to_its_slope_floor_or_its_pole(camera: CameraModel) -> None:
    k4, k5, k6 = np.concatenate([camera.dist, np.zeros(8 - len(camera.dist))])[5:]
    r = np.linspace(0.0, MAX_MODEL_RADIUS, 100001)
    r2 = r * r
    pole = (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3) <= 0.0
    pole[:-1] |= pole[1:]  # the scan's last point before the pole: its central difference spans it
    slope = np.gradient(rational_radial(camera.dist, r), r)
    below = np.flatnonzero((slope <= MIN_RADIAL_MAGNIFICATION) | pole)
    if len(below) == 0:
        assert math.isinf(camera.radius_limit)
        return
    r_end = r[below[0]]
    assert camera.undistorted_limit == pytest.approx(r_end, abs=3e-4)
    if not pole[below[0]]:
        assert camera.radius_limit == pytest.approx(
            float(rational_radial(camera.dist, np.array(r_end))), rel=1e-3
        )


def test_a_wide_rational_lens_undistorts_and_reprojects_to_the_image_corners() -> None:
    # 1920 x 1080 at fx 1000: 114 deg horizontal field of view, a barrel no 5-coefficient fit holds.
    camera = CameraModel.from_intrinsics(
        CameraIntrinsics(
            width=1920, height=1080, fx=1000.0, fy=1000.0, cx=960.0, cy=540.0, dist=RATIONAL_WIDE
        )
    )
    assert camera.dist.shape == (8,)
    assert not camera.beyond_model(np.array([[0.0, 0.0], [1919.0, 1079.0]])).any()
    u, v = np.meshgrid(np.linspace(0.0, 1919.0, 41), np.linspace(0.0, 1079.0, 23))
    pixels = np.column_stack([u.ravel(), v.ravel()])
    xy = undistort_pixels(pixels, camera)
    reprojected = project_points_cam(np.hstack([xy, np.ones((len(xy), 1))]), camera)
    np.testing.assert_allclose(reprojected, pixels, rtol=0, atol=1e-8)
    expected, _ = cv2.projectPoints(
        np.hstack([xy, np.ones((len(xy), 1))]), np.zeros(3), np.zeros(3), camera.K, camera.dist
    )
    np.testing.assert_allclose(expected.reshape(-1, 2), pixels, rtol=0, atol=1e-6)


@pytest.mark.parametrize("dist", [RATIONAL_WIDE, (-0.30, 0.09, 0.0005, -0.0004, -0.012)])
def test_points_far_beyond_the_lens_model_have_no_pixel_and_raise_no_warning(dist: tuple[float, ...]) -> None:
    # A junk pose in the hypotheses put points 1e60 off axis: the polynomials overflowed (RuntimeWarning on
    # the user's terminal) before those pixels were set to NaN.
    camera = CameraModel(np.array([[1000.0, 0, 960], [0, 1000, 540], [0, 0, 1]]), np.array(dist), 1920, 1080)
    points = np.array([[1e60, 3e59, 1.0], [0.3, -0.2, 1.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pixels = project_points_cam(points, camera)
    assert np.isnan(pixels[0]).all() and np.isfinite(pixels[1]).all()


@pytest.mark.parametrize(
    "values, expected",
    [
        ((0.1, -0.02, 0.001, 0.002), (0.1, -0.02, 0.001, 0.002, 0.0)),  # [k1, k2, p1, p2]: k3 = 0
        ((0.1, -0.02, 0.001, 0.002, 0.01), (0.1, -0.02, 0.001, 0.002, 0.01)),
        ((0.1, -0.02, 0.001, 0.002, 0.01, 0.0, 0.0, 0.0), (0.1, -0.02, 0.001, 0.002, 0.01)),  # not rational
        (RATIONAL_WIDE, RATIONAL_WIDE),
    ],
)
def test_opencv_dist_keeps_what_projects_alike(
    values: tuple[float, ...], expected: tuple[float, ...]
) -> None:
    dist = opencv_dist(values)
    np.testing.assert_array_equal(dist, expected)
    # The same projection as OpenCV's of the vector given.
    K = np.array([[900.0, 0.0, 640.0], [0.0, 900.0, 360.0], [0.0, 0.0, 1.0]])
    points = np.array([[0.3, -0.2, 1.0], [-0.5, 0.4, 2.0], [0.0, 0.0, 3.0]])
    ours = project_points_cam(points, CameraModel(K, np.array(values), 1280, 720))
    theirs, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, np.array(values))
    np.testing.assert_allclose(ours, theirs.reshape(-1, 2), rtol=0, atol=1e-9)


@pytest.mark.parametrize("length", [0, 3, 6, 7, 12, 14])
def test_other_distortion_vector_lengths_are_refused_naming_dist(length: int) -> None:
    with pytest.raises(ValueError, match="dist"):
        opencv_dist(np.zeros(length))
    with pytest.raises(ValueError, match=r"dist\n.*coefficients; OpenCV's pinhole model takes 4"):
        CameraIntrinsics(width=640, height=480, fx=500.0, fy=500.0, cx=320.0, cy=240.0, dist=(0.0,) * length)


def test_undistort_of_no_pixels() -> None:
    camera = CameraModel(np.eye(3), np.array([0.1, 0.0, 0.0, 0.0, 0.0]), 10, 10)
    assert undistort_pixels(np.zeros((0, 2)), camera).shape == (0, 2)


def test_distort_normalized_is_identity_without_distortion() -> None:
    xy = np.array([[0.3, -0.2], [0.0, 0.0]])
    np.testing.assert_array_equal(distort_normalized(xy, np.zeros(5)), xy)


# --- rotations -------------------------------------------------------------------------------------------


@settings(max_examples=100, deadline=None)
@given(yaw=st.lists(angles, min_size=1, max_size=5), data=st.data())
def test_rotation_from_ypr_is_intrinsic_zyx(yaw: list[float], data: st.DataObject) -> None:
    n = len(yaw)
    pitch = data.draw(st.lists(st.floats(-1.5, 1.5), min_size=n, max_size=n))
    roll = data.draw(st.lists(angles, min_size=n, max_size=n))
    R = rotation_from_ypr(np.array(yaw), np.array(pitch), np.array(roll))
    expected = SciRotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll])).as_matrix()
    assert R.shape == (n, 3, 3)
    np.testing.assert_allclose(R, expected, atol=1e-12)


def test_rotation_from_ypr_meaning() -> None:
    # yaw +90 deg turns the body's forward axis (x) to world north (+y); pitch +90 deg turns it down.
    forward = np.array([1.0, 0.0, 0.0])
    quarter, zero = np.array([math.pi / 2]), np.zeros(1)
    np.testing.assert_allclose(
        rotation_from_ypr(quarter, zero, zero)[0] @ forward, [0.0, 1.0, 0.0], atol=1e-15
    )
    np.testing.assert_allclose(
        rotation_from_ypr(zero, quarter, zero)[0] @ forward, [0.0, 0.0, -1.0], atol=1e-15
    )


@settings(max_examples=100, deadline=None)
@given(R=rotations())
def test_quaternion_matches_scipy_with_w_non_negative(R: FloatArray) -> None:
    q = quaternion_wxyz_from_rotation(R)
    x, y, z, w = SciRotation.from_matrix(R).as_quat()
    expected = np.array([w, x, y, z]) * (1.0 if w >= 0 else -1.0)
    assert q[0] >= 0.0
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-12)
    if abs(expected[0]) < 1e-9:  # a half turn: q and -q both have w = 0
        assert min(np.abs(q - expected).max(), np.abs(q + expected).max()) < 1e-9
    else:
        np.testing.assert_allclose(q, expected, atol=1e-9)


@pytest.mark.parametrize(
    "rotvec",
    [[0.0, 0.0, 0.0], [math.pi, 0.0, 0.0], [0.0, math.pi, 0.0], [0.0, 0.0, math.pi], [2.0, 2.0, 1.0]],
)
def test_quaternion_of_special_rotations(rotvec: list[float]) -> None:
    R = SciRotation.from_rotvec(rotvec).as_matrix()
    q = quaternion_wxyz_from_rotation(R)
    back = SciRotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
    np.testing.assert_allclose(back, R, atol=1e-12)
    assert q[0] >= 0.0


@settings(max_examples=100, deadline=None)
@given(axis=st.tuples(unit, unit, unit), angle=st.floats(0.0, math.pi - 1e-3))
def test_rvec_round_trip(axis: tuple[float, float, float], angle: float) -> None:
    direction = np.array(axis)
    assume(np.linalg.norm(direction) > 0.1)
    rvec = direction / np.linalg.norm(direction) * angle
    R = rotation_from_rvec(rvec)
    np.testing.assert_allclose(R, SciRotation.from_rotvec(rvec).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(rvec_from_rotation(R), rvec, atol=1e-9)
    assert rotation_angle_rad(np.eye(3), R) == pytest.approx(angle, abs=1e-7)
    assert rotation_angle_rad(R, R) < 1e-7


@pytest.mark.parametrize("angle", [1e-12, 1e-9, 1e-6, 1e-5, 2e-5])
def test_rvec_of_tiny_rotations_is_not_rounded_to_zero(angle: float) -> None:
    # Refinement and uncertainty work with small rotation increments; cv2.Rodrigues zeroes these below 1e-5.
    rvec = np.array([0.3, -0.4, 0.5]) / np.linalg.norm([0.3, -0.4, 0.5]) * angle
    np.testing.assert_allclose(rvec_from_rotation(rotation_from_rvec(rvec)), rvec, rtol=1e-6, atol=1e-15)


@settings(max_examples=100, deadline=None)
@given(
    R=rotations(), t=st.tuples(st.floats(-100.0, 100.0), st.floats(-100.0, 100.0), st.floats(-100.0, 100.0))
)
def test_camera_centre_maps_to_the_camera_origin(R: FloatArray, t: tuple[float, float, float]) -> None:
    centre = camera_centre(R, np.array(t))
    np.testing.assert_allclose(R @ centre + np.array(t), np.zeros(3), atol=1e-10)


# --- camera_rotation_from_view ---------------------------------------------------------------------------


@settings(max_examples=100, deadline=None)
@given(yaw=angles, pitch_down=st.floats(-1.5, 1.5), roll=st.floats(-0.5, 0.5))
def test_view_rotation_is_proper_and_looks_where_asked(yaw: float, pitch_down: float, roll: float) -> None:
    R = camera_rotation_from_view(yaw, pitch_down, roll)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    optical_axis = R.T @ np.array([0.0, 0.0, 1.0])  # camera z in the world frame
    assert math.asin(-optical_axis[2]) == pytest.approx(pitch_down, abs=1e-9)
    if abs(pitch_down) < 1.5:
        azimuth = math.atan2(optical_axis[1], optical_axis[0])
        assert abs(math.remainder(azimuth - yaw, 2.0 * math.pi)) < 1e-9
    # Roll turns the image about the optical axis and leaves the axis alone.
    np.testing.assert_allclose(
        camera_rotation_from_view(yaw, pitch_down, 0.0).T[:, 2], optical_axis, atol=1e-12
    )
    assert rotation_angle_rad(camera_rotation_from_view(yaw, pitch_down, 0.0), R) == pytest.approx(
        abs(roll), abs=1e-7
    )


@settings(max_examples=100, deadline=None)
@given(yaw=angles, pitch_down=st.floats(0.05, 1.4))
def test_unrolled_camera_keeps_the_horizon_level(yaw: float, pitch_down: float) -> None:
    R = camera_rotation_from_view(yaw, pitch_down)
    right, down = R[0], R[1]  # camera x and y axes in world coordinates
    assert abs(right[2]) < 1e-12  # image rows are horizontal
    assert down[2] < 0.0  # image y points down in the world


@settings(max_examples=100, deadline=None)
@given(
    yaw=angles,
    pitch_down=st.floats(0.05, 1.5),
    height=st.floats(2.0, 60.0),
    xy=st.tuples(st.floats(-1000.0, 1000.0), st.floats(-1000.0, 1000.0)),
)
def test_ground_point_straight_ahead_projects_to_the_principal_point(
    yaw: float, pitch_down: float, height: float, xy: tuple[float, float]
) -> None:
    intrinsics = CameraIntrinsics(
        width=1920,
        height=1080,
        fx=1200.0,
        fy=1200.0,
        cx=955.0,
        cy=547.0,
        dist=(-0.2, 0.05, 0.001, 0.001, 0.0),
    )
    camera = CameraModel.from_intrinsics(intrinsics)
    R = camera_rotation_from_view(yaw, pitch_down)
    centre = np.array([xy[0], xy[1], height])
    ahead_m = height / math.tan(pitch_down)
    ground_point = centre + np.array([ahead_m * math.cos(yaw), ahead_m * math.sin(yaw), -height])
    pixels, depth = project_points(ground_point[None, :], R, -R @ centre, camera)
    np.testing.assert_allclose(pixels[0], [955.0, 547.0], atol=1e-6)
    assert depth[0] == pytest.approx(math.hypot(ahead_m, height), rel=1e-9)
    # A point to the camera's right on the ground appears right of the centre (u grows).
    right_world = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    pixels_right, _ = project_points((ground_point + right_world)[None, :], R, -R @ centre, camera)
    assert pixels_right[0, 0] > 955.0


@settings(max_examples=300, deadline=None)
@given(
    axis=st.tuples(*[st.floats(-1.0, 1.0) for _ in range(3)]).filter(lambda a: sum(v * v for v in a) > 1e-4),
    angle=st.one_of(st.floats(0.0, math.pi - 1e-6), st.floats(0.0, 1e-5), st.floats(math.pi - 1e-3, math.pi)),
)
def test_rvec_from_rotation_matches_scipy_at_every_angle(
    axis: tuple[float, float, float], angle: float
) -> None:
    """Tiny rotations (where cv2.Rodrigues returns 0) and near half turns included."""
    rotvec = np.asarray(axis) / np.linalg.norm(axis) * angle
    R = SciRotation.from_rotvec(rotvec).as_matrix()
    ours = rvec_from_rotation(R)
    expected = SciRotation.from_matrix(R).as_rotvec()
    if angle < math.pi - 1e-3:
        np.testing.assert_allclose(ours, expected, rtol=1e-9, atol=1e-15)
    else:  # about pi, v and -v describe the same rotation: compare the rotations
        np.testing.assert_allclose(rotation_from_rvec(ours), R, atol=1e-12)
