"""Camera geometry: OpenCV pinhole + [k1, k2, p1, p2, k3] distortion (or the rational model's
[k1, k2, p1, p2, k3, k4, k5, k6]), rotations, camera poses.

Conventions (docs/design.md): camera frame x right, y down, z forward; X_cam = R_cam_from_local @ X_local + t.
Projection is our own vectorised numpy (bit-compatible with cv2.projectPoints, see the property tests)
because the simulator and the refinement project millions of points in small batches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from pipeline.arrays import FloatArray, Mask, Pixels, Points3, Rotation, Vec3, check_shape
from schemas.common import DIST_LENGTHS, CameraIntrinsics

# How far out the lens model is used: to the distorted radius where its radial magnification (d rho / d r,
# distorted over undistorted normalised radius, 1 at the centre) has fallen to this. A fitted polynomial
# (k1 < 0 with k2, k3) can turn back inside the image, where two directions share a pixel and no pixel beyond
# the turn can be undistorted at all; near the turn a pixel of noise is ten of the model's. A physical lens
# stays well above it: an equidistant fisheye (rho = theta) falls to 0.1 only 72 deg off axis.
MIN_RADIAL_MAGNIFICATION = 0.1
# No image reaches further than this undistorted normalised radius (84 deg off axis).
MAX_MODEL_RADIUS = 10.0


@dataclass(frozen=True, slots=True)
class CameraModel:
    """Intrinsics as arrays: K (3, 3) and dist (5,) = [k1, k2, p1, p2, k3], or (8,) with the rational
    model's k4, k5, k6 (`opencv_dist`: any of OpenCV's 4, 5 or 8 given); image size in pixels."""

    K: FloatArray
    dist: FloatArray
    width: int
    height: int
    # Whether any distortion coefficient is non-zero; fixed at construction (asked at every projection in
    # the solvers' inner loops).
    has_distortion: bool = field(init=False, repr=False, compare=False)
    # The distorted normalised radius out to which the lens model holds (`model_radius_limit`), and the
    # undistorted one it comes from (the direction's tan of the angle off axis); inf for a model that never
    # turns back.
    radius_limit: float = field(init=False, repr=False, compare=False)
    undistorted_limit: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "dist", opencv_dist(self.dist))
        object.__setattr__(self, "has_distortion", bool(np.any(np.asarray(self.dist) != 0.0)))
        r_limit, rho_limit = model_radius_limits(np.asarray(self.dist, dtype=np.float64))
        object.__setattr__(self, "radius_limit", rho_limit)
        object.__setattr__(self, "undistorted_limit", r_limit)

    def beyond_model(self, pixels: Pixels) -> Mask:
        """Pixels (N, 2) beyond the radius the lens model holds to (`radius_limit`): (N,)."""
        check_shape(pixels, "N,2", name="pixels")
        if math.isinf(self.radius_limit):
            return np.zeros(len(pixels), dtype=np.bool_)
        rho = np.hypot(*_normalised(pixels, self.K).T)
        return np.asarray(rho > self.radius_limit, dtype=np.bool_)

    def model_limit_px(self) -> float:
        """The radius (px along x from the principal point) out to which the lens model holds; inf if it
        always does. For messages."""
        return self.radius_limit * float(self.K[0, 0])

    @staticmethod
    def from_intrinsics(intrinsics: CameraIntrinsics) -> CameraModel:
        K = np.array(
            [[intrinsics.fx, 0.0, intrinsics.cx], [0.0, intrinsics.fy, intrinsics.cy], [0.0, 0.0, 1.0]]
        )
        return CameraModel(
            K, np.array(intrinsics.dist, dtype=np.float64), intrinsics.width, intrinsics.height
        )


def opencv_dist(values: object) -> FloatArray:
    """An OpenCV distortion vector of 4 [k1, k2, p1, p2], 5 (+ k3) or 8 (+ k4, k5, k6: the rational model)
    values as the pipeline holds it: (5,), or (8,) when the rational terms are not all 0. The two give the
    same projection where they are (the rational model's denominator is then exactly 1)."""
    dist = np.asarray(values, dtype=np.float64).reshape(-1)
    if len(dist) not in DIST_LENGTHS:
        raise ValueError(f"dist: {len(dist)} coefficients, expected 4, 5 or 8 (OpenCV's pinhole models)")
    if len(dist) == 8 and np.any(dist[5:] != 0.0):
        return dist.copy()
    return np.concatenate([dist[:5], np.zeros(5 - min(len(dist), 5))])


def lens_model_note(intrinsics: CameraIntrinsics) -> str | None:
    """A warning when the lens model turns back inside the image (`model_radius_limit`), else None."""
    camera = CameraModel.from_intrinsics(intrinsics)
    corners = np.array(
        [[0.0, 0.0], [intrinsics.width, 0.0], [0.0, intrinsics.height], [intrinsics.width, intrinsics.height]]
    )
    beyond = camera.beyond_model(corners)
    if not beyond.any():
        return None
    corner_px = float(np.max(np.hypot(corners[:, 0] - intrinsics.cx, corners[:, 1] - intrinsics.cy)))
    return (
        f"dist: the distortion turns back {camera.model_limit_px():.0f} px from the principal point, inside "
        f"the image (its farthest corner is {corner_px:.0f} px away): boxes reaching beyond are not used; "
        "refit the intrinsics to use the whole image"
    )


def model_radius_limit(dist: FloatArray) -> float:
    """The distorted normalised radius rho out to which the radial model rho = r f(r^2) is used (f = 1 +
    k1 r^2 + k2 r^4 + k3 r^6, divided by 1 + k4 r^2 + k5 r^4 + k6 r^6 in the rational model): where d rho /
    d r first falls to MIN_RADIAL_MAGNIFICATION, or the rational model's denominator to 0, searched out to
    MAX_MODEL_RADIUS (inf if neither happens). The tangential terms (p1, p2: a few thousandths) are left
    out."""
    return model_radius_limits(dist)[1]


def model_radius_limits(dist: FloatArray) -> tuple[float, float]:
    """(r, rho): the undistorted normalised radius where the lens model stops holding
    (`model_radius_limit`), and the distorted radius it maps to; (inf, inf) if it never does."""
    lens = opencv_dist(dist)

    def beyond(r: FloatArray) -> FloatArray:
        with np.errstate(divide="ignore", invalid="ignore"):  # at and past a rational model's pole
            radial, d_radial = _radial_terms(r * r, lens)
            slope = radial + 2.0 * r * r * d_radial  # d (r radial(r^2)) / d r
        return np.asarray((slope <= MIN_RADIAL_MAGNIFICATION) | ~(_denominator(r * r, lens) > 0.0))

    # A scan, then bisection: robust for any coefficients (a root finder on the polynomials overflows when
    # the leading coefficient is tiny) and cheap (once per camera).
    r = np.linspace(0.0, MAX_MODEL_RADIUS, 10001)
    low = np.flatnonzero(beyond(r))
    if len(low) == 0:
        return math.inf, math.inf
    a, b = float(r[low[0] - 1]), float(r[low[0]])  # slope(0) = 1: low[0] >= 1
    for _ in range(60):
        mid = 0.5 * (a + b)
        if bool(beyond(np.array([mid]))[0]):
            b = mid
        else:
            a = mid
    if not _denominator(np.array([b * b]), lens)[0] > 0.0:
        b = a  # the rational model's pole: b has no finite image, a is just inside
    return b, b * float(_radial(np.array([b * b]), lens)[0])


def _denominator(r2: FloatArray, dist: FloatArray) -> FloatArray:
    """The rational model's denominator 1 + k4 r^2 + k5 r^4 + k6 r^6 (1 without one) at r2 = r^2."""
    if len(dist) < 8:
        return np.ones_like(r2)
    return np.asarray(1.0 + r2 * (dist[5] + r2 * (dist[6] + r2 * dist[7])), dtype=np.float64)


def _radial(r2: FloatArray, dist: FloatArray) -> FloatArray:
    """The radial factor at squared undistorted radii r2 for a (5,) or (8,) `opencv_dist` vector."""
    k1, k2, k3 = dist[0], dist[1], dist[4]
    radial: FloatArray = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return radial if len(dist) < 8 else radial / _denominator(r2, dist)


def _radial_terms(r2: FloatArray, dist: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The radial factor at squared undistorted radii r2 and its derivative d / d r2, for a (5,) or (8,)
    `opencv_dist` vector."""
    k1, k2, k3 = dist[0], dist[1], dist[4]
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    if len(dist) < 8:
        return radial, d_radial
    denominator = _denominator(r2, dist)
    d_denominator = dist[5] + r2 * (2.0 * dist[6] + 3.0 * dist[7] * r2)
    quotient = radial / denominator
    return quotient, (d_radial - quotient * d_denominator) / denominator


def within_model(x: FloatArray, y: FloatArray, limit: float) -> tuple[FloatArray, FloatArray]:
    """Undistorted normalised coordinates (same shape) pulled in along their radius to at most `limit`
    (`CameraModel.undistorted_limit`). Beyond it the lens polynomial turns back: a point 75 deg off axis
    would land inside the image, near the corner. The solvers project through this clamp, as through their
    depth clamp: a pose that puts the vehicle that far off axis sees it on the model's rim, never inside the
    image, and the step back is continuous. Unchanged (the same arrays) when nothing lies beyond."""
    if math.isinf(limit):
        return x, y
    r2 = x * x + y * y
    beyond = r2 > limit * limit
    if not beyond.any():
        return x, y
    shrink = np.where(beyond, limit / np.sqrt(np.where(beyond, r2, 1.0)), 1.0)
    return x * shrink, y * shrink


def distortion_chain(
    x: FloatArray, y: FloatArray, dx: FloatArray, dy: FloatArray, camera: CameraModel
) -> tuple[FloatArray, FloatArray]:
    """The derivatives of the distorted normalised coordinates of `within_model(x, y)`: from those of the
    undistorted ones dx, dy (M, P) at points x, y (M,) -> (M, P) each. The clamp's derivative keeps only the
    tangential part (the radius is pinned at the limit); the distortion's is the analytic 2 x 2 Jacobian."""
    limit = camera.undistorted_limit
    if not math.isinf(limit):
        r2 = x * x + y * y
        beyond = r2 > limit * limit
        if beyond.any():
            r = np.sqrt(np.where(beyond, r2, 1.0))
            ux, uy = x / r, y / r
            radial = ux[:, None] * dx + uy[:, None] * dy
            shrink = (limit / r)[:, None]
            b = beyond[:, None]
            dx = np.where(b, shrink * (dx - ux[:, None] * radial), dx)
            dy = np.where(b, shrink * (dy - uy[:, None] * radial), dy)
            x, y = within_model(x, y, limit)
    if not camera.has_distortion:
        return dx, dy
    _, j11, j12, j22 = _radial_and_jacobian(x, y, camera.dist)
    return j11[:, None] * dx + j12[:, None] * dy, j12[:, None] * dx + j22[:, None] * dy


def _radial_and_jacobian(
    x: FloatArray, y: FloatArray, dist: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The distortion model's radial factor at undistorted normalised (x, y) and its 2 x 2 Jacobian
    d(xd, yd) / d(x, y) as j11, j12 (= j21), j22."""
    p1, p2 = dist[2], dist[3]
    r2 = x * x + y * y
    radial, d_radial = _radial_terms(r2, dist)  # and d radial / d r2
    j11 = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
    j12 = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
    j22 = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
    return radial, j11, j12, j22


def distort_normalized(xy: FloatArray, dist: FloatArray) -> FloatArray:
    """Apply the OpenCV radial-tangential model (`distort_xy`) to normalised coordinates (N, 2) -> (N, 2)."""
    return np.stack(distort_xy(xy[:, 0], xy[:, 1], dist), axis=1)


def distort_xy(x: FloatArray, y: FloatArray, dist: FloatArray) -> tuple[FloatArray, FloatArray]:
    """`distort_normalized` on the normalised coordinates as two arrays x, y (same shape) -> (xd, yd), for
    callers that use the columns apart (the straight-track solver's inner loop). `dist` (5,) or (8,)."""
    p1, p2 = dist[2], dist[3]
    r2 = x * x + y * y
    radial = _radial(r2, dist)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def project_points_cam(points_cam: Points3, camera: CameraModel) -> Pixels:
    """Project points already in the camera frame (N, 3), z > 0 assumed, to distorted pixels (N, 2).

    Points further off axis than the lens model holds (`CameraModel.undistorted_limit`) have no pixel: NaN.
    """
    check_shape(points_cam, "N,3", name="points_cam")
    undistorted = points_cam[:, :2] / points_cam[:, 2:3]
    K = camera.K
    # Far off axis the lens polynomials overflow; those points get NaN below (beyond the model) or inf.
    with np.errstate(over="ignore", invalid="ignore"):
        xy = distort_normalized(undistorted, camera.dist) if camera.has_distortion else undistorted
        pixels = np.stack(
            [K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2], K[1, 1] * xy[:, 1] + K[1, 2]], axis=1
        )
    limit = camera.undistorted_limit
    if not math.isinf(limit):
        with np.errstate(invalid="ignore"):
            pixels[np.sum(undistorted**2, axis=1) > limit * limit] = np.nan
    return pixels


def project_points(
    points_local: Points3, R_cam_from_local: Rotation, t_cam_from_local: Vec3, camera: CameraModel
) -> tuple[Pixels, FloatArray]:
    """Project local-frame points (N, 3) to pixels (N, 2); also returns the depth z_cam (N,) in metres.

    Points with z_cam <= 0 get NaN pixels: they are behind the camera; so do points beyond the lens model
    (project_points_cam).
    """
    check_shape(points_local, "N,3", name="points_local")
    points_cam = points_local @ R_cam_from_local.T + t_cam_from_local
    depth = points_cam[:, 2].copy()
    safe = points_cam.copy()
    behind = depth <= 1e-9
    safe[behind, 2] = 1.0
    pixels = project_points_cam(safe, camera)
    pixels[behind] = np.nan
    return pixels, depth


def undistort_pixels(pixels: Pixels, camera: CameraModel) -> FloatArray:
    """Distorted pixels (N, 2) -> normalised undistorted coordinates (N, 2) (x/z, y/z in the camera frame)."""
    check_shape(pixels, "N,2", name="pixels")
    if len(pixels) == 0:
        return np.zeros((0, 2))
    target = _normalised(pixels, camera.K)
    if not camera.has_distortion:
        return target
    return _invert_distortion(target, camera.dist, camera.undistorted_limit)


def _normalised(pixels: Pixels, K: FloatArray) -> FloatArray:
    """Pixels (N, 2) -> distorted normalised coordinates (N, 2): the inverse of K including its skew K[0, 1],
    as project_points_cam applies it."""
    return np.stack(
        [
            (pixels[:, 0] - K[0, 2] - K[0, 1] * (pixels[:, 1] - K[1, 2]) / K[1, 1]) / K[0, 0],
            (pixels[:, 1] - K[1, 2]) / K[1, 1],
        ],
        axis=1,
    )


def _invert_distortion(xy_distorted: FloatArray, dist: FloatArray, limit: float = math.inf) -> FloatArray:
    """Solve distort_normalized(xy) = xy_distorted by Newton's method with the analytic 2x2 Jacobian.

    Starts from the distorted point; converges to ~1e-14 in a few steps for any lens whose model is
    monotonic over the image (OpenCV's own fixed-point loop stalls on strong barrel distortion). Steps are
    held within the undistorted radius `limit` where the model holds (`CameraModel.undistorted_limit`):
    beyond it a model that turns back maps other directions to the same pixels. Where that start fails (a
    strong pincushion pixel starts further out than its direction, and Newton's method can leave for the
    turn or through the centre), the radial part is solved first by bisection on [0, limit], where the
    model is monotonic, and Newton's method finishes from there.
    """
    xy = _newton_undistort(xy_distorted, xy_distorted.copy(), dist, limit)
    if math.isinf(limit):
        return xy
    xd, yd = distort_xy(xy[:, 0], xy[:, 1], dist)
    missed = ~(np.hypot(xd - xy_distorted[:, 0], yd - xy_distorted[:, 1]) <= 1e-9)
    if missed.any():
        start = _radial_start(xy_distorted[missed], dist, limit)
        xy[missed] = _newton_undistort(xy_distorted[missed], start, dist, limit)
    return xy


def _newton_undistort(xy_distorted: FloatArray, xy: FloatArray, dist: FloatArray, limit: float) -> FloatArray:
    """`_invert_distortion`'s Newton iterations from `xy` (changed in place and returned)."""
    p1, p2 = dist[2], dist[3]
    for _ in range(30):
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial, j11, j12, j22 = _radial_and_jacobian(x, y, dist)
        j21 = j12
        fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xy_distorted[:, 0]
        fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - xy_distorted[:, 1]
        det = j11 * j22 - j12 * j21
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        dx = (j22 * fx - j12 * fy) / det
        dy = (j11 * fy - j21 * fx) / det
        xy[:, 0] -= dx
        xy[:, 1] -= dy
        xy[:, 0], xy[:, 1] = within_model(xy[:, 0], xy[:, 1], limit)
        if float(np.max(np.abs(dx) + np.abs(dy), initial=0.0)) < 1e-15:
            break
    return xy


def _radial_start(xy_distorted: FloatArray, dist: FloatArray, limit: float) -> FloatArray:
    """The points (N, 2) in the distorted points' directions whose radial distortion alone gives their
    radius: r f(r^2) = |xy_distorted| solved by bisection on [0, limit] (monotonic there); the rim for a
    radius beyond the model's."""
    rho = np.hypot(xy_distorted[:, 0], xy_distorted[:, 1])
    low, high = np.zeros(len(rho)), np.full(len(rho), limit)
    for _ in range(60):
        mid = 0.5 * (low + high)
        inside = mid * _radial(mid * mid, dist) < rho
        low, high = np.where(inside, mid, low), np.where(inside, high, mid)
    scale = np.where(rho > 0.0, low / np.where(rho > 0.0, rho, 1.0), 1.0)
    return np.asarray(xy_distorted * scale[:, None], dtype=np.float64)


def rotation_from_ypr(yaw: FloatArray, pitch: FloatArray, roll: FloatArray) -> FloatArray:
    """Rz(yaw) @ Ry(pitch) @ Rx(roll) for arrays of angles (N,) -> (N, 3, 3) (vehicle body -> world)."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    R = np.empty((np.size(yaw), 3, 3))
    R[:, 0, 0] = cy * cp
    R[:, 0, 1] = cy * sp * sr - sy * cr
    R[:, 0, 2] = cy * sp * cr + sy * sr
    R[:, 1, 0] = sy * cp
    R[:, 1, 1] = sy * sp * sr + cy * cr
    R[:, 1, 2] = sy * sp * cr - cy * sr
    R[:, 2, 0] = -sp
    R[:, 2, 1] = cp * sr
    R[:, 2, 2] = cp * cr
    return R


def camera_rotation_from_view(yaw: float, pitch_down: float, roll: float = 0.0) -> Rotation:
    """R_cam_from_world for a camera whose optical axis points at azimuth `yaw` (rad from east, ccw),
    tilted `pitch_down` (rad) below the horizon and rolled `roll` (rad, clockwise in the image)."""
    forward = np.array(
        [math.cos(pitch_down) * math.cos(yaw), math.cos(pitch_down) * math.sin(yaw), -math.sin(pitch_down)]
    )
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(forward, right)
    # Roll turns the image axes about the optical axis.
    c, s = math.cos(roll), math.sin(roll)
    right_r = c * right + s * down
    down_r = -s * right + c * down
    R_world_from_cam = np.stack([right_r, down_r, forward], axis=1)
    return R_world_from_cam.T.copy()


def camera_centre(R_cam_from_local: Rotation, t_cam_from_local: Vec3) -> Vec3:
    """Camera position in the local frame: -R^T t (paper Sec. III-D)."""
    return -R_cam_from_local.T @ t_cam_from_local


def rotation_angle_rad(R_a: Rotation, R_b: Rotation) -> float:
    """Angle of the relative rotation R_a^T R_b, in radians (0 for equal rotations): the norm of its rotation
    vector, from the quaternion (2 atan2(|v|, w)); acos of the trace loses half the digits near 0 (an angle
    of 1e-8 rad reads as 0)."""
    return float(np.linalg.norm(rvec_from_rotation(R_a.T @ R_b)))


def pose_distance(R_a: Rotation, centre_a: Vec3, R_b: Rotation, centre_b: Vec3) -> tuple[float, float]:
    """(distance between the camera centres in m, angle of the relative rotation in deg) of two poses: the
    one measure of how far apart two poses are (selection, validation, the daemon's change policy)."""
    return float(np.linalg.norm(centre_a - centre_b)), math.degrees(rotation_angle_rad(R_a, R_b))


def pose_difference(R_a: Rotation, centre_a: Vec3, R_b: Rotation, centre_b: Vec3) -> FloatArray:
    """[w, C] (6,) of pose b relative to pose a, in the convention of every pose covariance (the fit's,
    schemas.results.Uncertainty's): R_b = R_a expm(-[w]x), a rotation vector in the local frame (rad), and
    C = centre_b - centre_a (m)."""
    return np.concatenate([-rvec_from_rotation(R_a.T @ R_b), centre_b - centre_a])


def rotation_from_rvec(rvec: FloatArray) -> Rotation:
    """Rodrigues vector (3,) -> rotation matrix (3, 3)."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return np.asarray(R, dtype=np.float64)


def rvec_from_rotation(R: Rotation) -> FloatArray:
    """Rotation matrix (3, 3) -> Rodrigues vector (3,)."""
    # Not cv2.Rodrigues: it returns exactly zero for any rotation below 1e-5 rad (sin theta < 1e-5). From
    # the unit quaternion (w >= 0) instead, as scipy's Rotation.as_rotvec does: angle = 2 atan2(|v|, w) is
    # accurate at every angle (atan2 keeps full relative precision for tiny |v|), 2 / w its limit at 0.
    q = quaternion_wxyz_from_rotation(np.asarray(R, dtype=np.float64))
    w, v = float(q[0]), q[1:]
    norm = float(np.linalg.norm(v))
    angle = 2.0 * math.atan2(norm, w)
    scale = angle / norm if norm > 0.0 else 2.0 / w
    return np.asarray(scale * v, dtype=np.float64)


def quaternion_wxyz_from_rotation(R: Rotation) -> FloatArray:
    """Unit quaternion [w, x, y, z] (w >= 0) of a rotation matrix."""
    m = R
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = np.array([(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s])
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = np.array([(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s])
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = np.array([(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q
