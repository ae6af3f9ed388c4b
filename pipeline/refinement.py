"""Stage 5: refine a camera pose on the calibration vehicle's boxes (paper Sec. III-F, and beyond it).

Inputs: a start pose (R_cam_from_local, t_cam_from_local), the calibration vehicle's matched tracks (boxes
with the vehicle pose at each box's stamp), the camera intrinsics and the vehicle profile. Output: a
`Refinement` with the refined pose, its 6x6 covariance, per-box residuals and delta_p (paper Sec. IV-B).

Three estimators, one result type:
- `refine_bottom_edge(..., RefinementParams(iterate_correspondences=False))`: the paper's refinement,
  one-shot correspondences (footprint corner <-> point on the bottom box edge) + point-to-line registration.
- `refine_bottom_edge(...)` (default): the same bottom-edge information with the exact residual, so the
  correspondences are iterated to their fixed point inside the optimisation. This removes the paper's
  Sec. IV-B systematic error, except along the one direction bottom edges cannot see at all (a shift of
  the camera along its own x axis, to which delta_p is blind too); the covariance reports it.
- `refine_whole_box(...)`: robust least squares over all four box edges of the projected vehicle cuboid;
  converges to the truth on exact data and is the estimator to validate and publish.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.optimize import OptimizeResult, least_squares

from pipeline.arrays import (
    BoolArray,
    Boxes,
    FloatArray,
    IntArray,
    Rotation,
    Stamps,
    Vec3,
    check_shape,
)
from pipeline.association import MatchedTrack
from pipeline.camera import (
    CameraModel,
    camera_centre,
    distort_normalized,
    distortion_chain,
    rotation_from_rvec,
    undistort_pixels,
    within_model,
)
from pipeline.errors import DegenerateGeometry, ShapeError
from pipeline.ground import GroundPlaneFit
from pipeline.metrics import DeltaPParams, delta_p
from pipeline.vehicle import body_corners
from schemas.common import VehicleProfile

Loss = Literal["linear", "huber", "soft_l1", "cauchy", "arctan"]
Method = Literal["bottom_edge_paper", "bottom_edge_iterated", "whole_box"]

_N_PARAMS = 6  # [rotation vector (rad, local frame), camera centre offset (m, local frame)]


@dataclass(frozen=True, slots=True)
class RefinementParams:
    """Settings of both refinements. Pixel quantities are in distorted image pixels."""

    loss: Loss = "huber"  # scipy.optimize.least_squares loss for the pixel residuals
    f_scale_px: float = 2.0  # residual (px) where the robust loss starts to bend: ~2 sigma of box jitter
    border_margin_px: float = 1.0  # an edge this close to the image border is clipped: not used
    max_evaluations: int = 200  # residual evaluations per least-squares solve
    tolerance: float = 1e-12  # ftol = xtol = gtol of the solver
    min_sigma_px: float = 0.5  # floor of the residual std behind the covariance (see _covariance)
    pose_bias_std_m: float = 0.0  # common offset of all vehicle positions (GNSS drift), std per axis (m)
    min_depth_m: float = 0.1  # points nearer the camera plane are clamped there while iterating
    # Bottom-edge refinement only:
    iterate_correspondences: bool = True  # False: the paper's one-shot pairs (Sec. III-F) for comparison
    paper_rounds: int = 1  # one-shot variant: select pairs + register this many times (paper: once)
    edge_samples: int = 16  # samples of a bottom edge back-projected to the ground (distortion bends it)
    null_anchor_px_per_m: float = 1e-3  # iterated variant: holds the direction bottom edges cannot see

    def __post_init__(self) -> None:
        if not (self.f_scale_px > 0 and self.min_depth_m > 0):
            raise ValueError("RefinementParams: f_scale_px and min_depth_m must be > 0")
        if not (self.min_sigma_px >= 0 and self.pose_bias_std_m >= 0 and self.null_anchor_px_per_m >= 0):
            raise ValueError(
                "RefinementParams: min_sigma_px, pose_bias_std_m, null_anchor_px_per_m must be >= 0"
            )
        if self.max_evaluations < 1 or self.paper_rounds < 1 or self.edge_samples < 2:
            raise ValueError("RefinementParams: max_evaluations, paper_rounds >= 1 and edge_samples >= 2")


@dataclass(frozen=True, slots=True)
class Refinement:
    """A refined camera pose with its uncertainty and per-box fit.

    R_cam_from_local (3, 3), t_cam_from_local (3,) m, camera_centre (3,) m, local frame.
    covariance: (6, 6) of [w (rad), camera centre (m)], local frame, w the small rotation of the camera's
        axes about its centre: R_local_from_cam = expm([w]x) R_est^T, i.e. R = R_est @ expm(-[w]x).
        Box noise (from the residuals) plus params.pose_bias_std_m^2 on the centre block; see _covariance.
    position_std_m / rotation_std_deg: std along the worst axis of the position / rotation block.
    principal_directions: (6, 6) eigen-decomposition of the covariance in scene units [w * scene_range_m,
        C] (both metres): column k a unit direction, principal_stds_m[k] (6,) its std, largest first.
    worst_direction / worst_std_m: the first of them. A rotation about a line the data cannot fix shows up
        here as w parallel to that line, with the matching swing of the centre.
    scene_range_m: median camera-to-vehicle distance used for that scaling.
    box_track_ids / stamps: (N,) the track and stamp of each box, in the order of the per-box arrays.
    residuals_px: (N, 4) tight box of the projected vehicle cuboid minus the detected box (x1, y1, x2, y2)
        at the final pose; NaN for edges at the image border (clipped, not used).
    box_rmse_px: RMS of the finite entries of residuals_px.
    delta_p_m: (N,) paper Sec. IV-B, metrics.delta_p: distance on the ground between the back-projected
        bottom box edge and the closest footprint corner (NaN for boxes at the image border or whose edge
        does not reach the ground).
    sigma_px: the residual std behind the covariance (after the min_sigma_px floor).
    used_residuals: pixel residuals behind the covariance; iterations: residual evaluations (all rounds);
    converged: the solver met its tolerance; cost: its final cost (0.5 sum rho(r^2)).
    """

    method: Method
    R_cam_from_local: Rotation
    t_cam_from_local: Vec3
    camera_centre: Vec3
    covariance: FloatArray
    position_std_m: float
    rotation_std_deg: float
    principal_directions: FloatArray
    principal_stds_m: FloatArray
    worst_direction: FloatArray
    worst_std_m: float
    scene_range_m: float
    box_track_ids: IntArray
    stamps: Stamps
    residuals_px: FloatArray
    box_rmse_px: float
    delta_p_m: FloatArray
    sigma_px: float
    used_residuals: int
    iterations: int
    converged: bool
    cost: float


# ---------------------------------------------------------------------------------------------------------
# Public stages
# ---------------------------------------------------------------------------------------------------------


def refine_bottom_edge(
    R_cam_from_local: Rotation,
    t_cam_from_local: Vec3,
    tracks: Sequence[MatchedTrack],
    camera: CameraModel,
    vehicle: VehicleProfile,
    ground: GroundPlaneFit,
    params: RefinementParams,
) -> Refinement:
    """Refine the pose so that the vehicle footprint touches every box's bottom edge (paper Sec. III-F).

    R_cam_from_local (3, 3), t_cam_from_local (3,): start pose (a hypothesis or a merged group), local frame.
    tracks: calibration-vehicle tracks; boxes (n, 4) px, poses (n, 6) local frame, one pose per box.
    ground: the plane the bottom edges are back-projected onto (fit_ground_plane of the vehicle track).

    params.iterate_correspondences=False is the paper: per box, the bottom edge is back-projected onto the
    ground with the start pose; the footprint corner closest to it is x_n; b_n is the point of the bottom
    edge closest to x_n's projection; then a point-to-line registration (each b_n's viewing ray is a line
    through the camera centre, Briales & Gonzalez-Jimenez 2017) moves the pose. b_n's position along the
    edge is taken from the start pose's perspective, which is the systematic error named in Sec. IV-B.

    The default (True) evaluates the same constraint exactly, at every step of the solver: x_n is the
    lowest projected footprint corner and the residual is its projected row minus the box's y2 (distorted
    px), the signed distance to the bottom-edge line. The correspondences thus reach their fixed point
    inside the optimisation, and the residual no longer depends on the start pose.

    What the bottom edges cannot fix (found while building this; reported through the covariance): the
    edge is a horizontal image line, so the v residual, and delta_p, are exactly invariant to a shift of
    the camera along its own x axis (an undistorted image row back-projects to a plane containing that
    axis), and the along-edge position of x_n is known only up to x1 <= u <= x2. The paper's pairing fills
    that direction, and biases the others, from the start pose. The iterated variant holds only that
    direction at the start pose (min-norm, `null_anchor_px_per_m`) and returns it as `worst_direction` with
    a huge std; on exact data it reaches delta_p = 0 and the true pose in every other direction. Through a
    distorting lens the direction becomes barely visible, so with box noise it can end up decimetres to
    metres off (simulated SIL scenes), again with a std that says so. `refine_whole_box` fixes it with the
    box's side edges: it is the estimator to validate and publish.
    """
    data = _stack_tracks(tracks, vehicle)
    _check_pose(R_cam_from_local, t_cam_from_local)
    R0 = np.asarray(R_cam_from_local, dtype=np.float64)
    C0 = camera_centre(R0, np.asarray(t_cam_from_local, dtype=np.float64))
    usable = data.boxes[:, 3] < camera.height - params.border_margin_px  # a clipped bottom edge says nothing
    index = np.flatnonzero(usable)
    if len(index) < _N_PARAMS:
        raise DegenerateGeometry(f"bottom-edge refinement: {len(index)} unclipped bottom edges, need >= 6")
    scale = _x_scale(data, C0)
    footprint = data.corners[:, :4, :]
    method: Method
    if params.iterate_correspondences:
        fun = _bottom_edge_residuals(footprint[index], data.boxes[index], R0, C0, camera, params)
        solution = _solve(
            fun, scale, params.loss, params.f_scale_px, params, anchor=params.null_anchor_px_per_m
        )
        p, evaluations, method = solution.x, int(solution.nfev), "bottom_edge_iterated"
        converged, cost = bool(solution.status > 0), float(solution.cost)
        loss = params.loss
    else:
        p = np.zeros(_N_PARAMS)
        evaluations, converged, cost = 0, False, math.inf
        for _ in range(params.paper_rounds):
            R_k, C_k = _pose_from_params(p, R0, C0)
            pairs = _paper_pairs(footprint, data.boxes, R_k, C_k, camera, ground, usable, params)
            if int(pairs.mask.sum()) < 3:  # each pair gives two equations
                raise DegenerateGeometry("paper refinement: fewer than 3 bottom edges reach the ground")
            ray_fun = _point_to_ray_residuals(pairs.points[pairs.mask], pairs.rays[pairs.mask], R0, C0)
            # The paper's registration is plain least squares on object-space distances (m).
            solution = _solve(ray_fun, scale, "linear", 1.0, params, p_start=p)
            p = solution.x
            evaluations += int(solution.nfev)
            converged, cost = bool(solution.status > 0), float(solution.cost)
        method = "bottom_edge_paper"
        loss = "linear"
    # Both variants report the covariance of the bottom-edge rows (v - y2, px), without the anchor: the
    # paper's own objective (m, fixed pairs) has no pixel noise model.
    R, C = _pose_from_params(p, R0, C0)
    final = _bottom_edge_residuals(footprint[index], data.boxes[index], R, C, camera, params)
    return _make_result(
        method,
        R,
        C,
        data,
        camera,
        ground,
        final,
        loss,
        params.f_scale_px,
        evaluations,
        converged,
        cost,
        params,
    )


def refine_whole_box(
    R_cam_from_local: Rotation,
    t_cam_from_local: Vec3,
    tracks: Sequence[MatchedTrack],
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: RefinementParams,
    ground: GroundPlaneFit | None = None,
) -> Refinement:
    """Refine the pose on all four edges of every box: robust nonlinear least squares (beyond the paper).

    Each box is modelled as the tight box around the vehicle cuboid's 8 projected corners (lens distortion
    included); residuals are its x1, y1, x2, y2 minus the detected box (px), except edges at the image border
    (a clipped edge is the border, not the vehicle). Which corner forms each edge is re-chosen at every
    evaluation. The paper uses the bottom edge only; the side and top edges add the vehicle's extent across
    and above the road, which fixes what bottom edges cannot see (the camera's shift along its x axis) and
    makes a rotation about a single straight road observable through the changing shape of the boxes.
    Loss and scale from params (pixel residuals). `ground` is used only for the reported delta_p (None:
    each box's own footprint plane, as metrics.delta_p does).
    """
    data = _stack_tracks(tracks, vehicle)
    _check_pose(R_cam_from_local, t_cam_from_local)
    R0 = np.asarray(R_cam_from_local, dtype=np.float64)
    C0 = camera_centre(R0, np.asarray(t_cam_from_local, dtype=np.float64))
    edge_used = ~_clipped_edges(data.boxes, camera, params.border_margin_px)
    if int(edge_used.sum()) < _N_PARAMS:
        raise DegenerateGeometry(
            f"whole-box refinement: {int(edge_used.sum())} unclipped box edges, need >= 6"
        )
    fun = _whole_box_residuals(data.corners, data.boxes, edge_used, R0, C0, camera, params)
    solution = _solve(fun, _x_scale(data, C0), params.loss, params.f_scale_px, params)
    R, C = _pose_from_params(solution.x, R0, C0)
    final = _whole_box_residuals(data.corners, data.boxes, edge_used, R, C, camera, params)
    return _make_result(
        "whole_box",
        R,
        C,
        data,
        camera,
        ground,
        final,
        params.loss,
        params.f_scale_px,
        int(solution.nfev),
        solution.status > 0,
        float(solution.cost),
        params,
    )


# ---------------------------------------------------------------------------------------------------------
# Data and parametrisation
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Stacked:
    """All tracks' boxes stacked: boxes (N, 4) px, corners (N, 8, 3) local m, track ids and stamps (N,)."""

    boxes: Boxes
    corners: FloatArray
    track_ids: IntArray
    stamps: Stamps


def _stack_tracks(tracks: Sequence[MatchedTrack], vehicle: VehicleProfile) -> _Stacked:
    """Concatenate the tracks (MatchedTrack checked its own shapes) and place the vehicle's body corners."""
    if sum(len(track.boxes) for track in tracks) == 0:
        raise DegenerateGeometry("refinement: no boxes")
    boxes = np.concatenate([np.asarray(track.boxes, dtype=np.float64) for track in tracks])
    poses = np.concatenate([np.asarray(track.poses, dtype=np.float64) for track in tracks])
    if not (np.all(np.isfinite(boxes)) and np.all(np.isfinite(poses))):
        raise ShapeError("refinement: boxes or poses contain NaN or inf")
    track_ids = np.concatenate(
        [np.full(len(track.boxes), track.track_id, dtype=np.int64) for track in tracks]
    )
    stamps = np.concatenate([np.asarray(track.stamps, dtype=np.int64) for track in tracks])
    return _Stacked(boxes, body_corners(poses, vehicle), track_ids, stamps)


def _check_pose(R: Rotation, t: Vec3) -> None:
    check_shape(R, "3,3", name="R_cam_from_local")
    check_shape(t, "3", name="t_cam_from_local")
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise ShapeError("R_cam_from_local, t_cam_from_local: contain NaN or inf")


def _pose_from_params(p: FloatArray, R0: Rotation, C0: Vec3) -> tuple[Rotation, Vec3]:
    """p = [w, dC] -> (R_cam_from_local, camera centre). R_local_from_cam = expm([w]x) R0^T: the camera's
    axes turned by w about the camera centre, w in the local frame. Rotating about the centre (not the local
    origin, hundreds of metres away) and using the centre instead of t decouples rotation and translation,
    which keeps the normal equations well conditioned."""
    return R0 @ rotation_from_rvec(p[:3]).T, C0 + p[3:]


def _left_jacobian(w: FloatArray) -> FloatArray:
    """SO(3) left Jacobian: expm([w + e]x) = expm([J e]x) expm([w]x) + O(e^2)."""
    theta = float(np.linalg.norm(w))
    W = _skew(w)
    if theta < 1e-6:
        return np.eye(3) + 0.5 * W + W @ W / 6.0
    return np.eye(3) + (1.0 - math.cos(theta)) / theta**2 * W + (theta - math.sin(theta)) / theta**3 * (W @ W)


def _skew(v: FloatArray) -> FloatArray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _x_scale(data: _Stacked, C0: Vec3) -> FloatArray:
    """Solver variable scales: a rotation of 1/range rad moves the scene by ~1 m, like 1 m of centre."""
    scene_range = _scene_range(data, C0)
    return np.array([1.0 / scene_range] * 3 + [1.0] * 3)


def _scene_range(data: _Stacked, C: Vec3) -> float:
    centres = data.corners[:, :4, :].mean(axis=1)
    return max(1.0, float(np.median(np.linalg.norm(centres - C, axis=1))))


# ---------------------------------------------------------------------------------------------------------
# Projection with its analytic Jacobian
# ---------------------------------------------------------------------------------------------------------


def _camera_points(points: FloatArray, R: Rotation, C: Vec3) -> FloatArray:
    """Local points (..., 3) -> camera frame (..., 3)."""
    return np.asarray((points - C) @ R.T, dtype=np.float64)


def _camera_points_jacobian(points_cam: FloatArray, R: Rotation, w: FloatArray) -> FloatArray:
    """d X_cam / d p for points (M, 3) in the camera frame -> (M, 3, 6).

    R = R0 expm(-[w]x) and X_cam = R (X - C). Perturbing w by e turns the camera's axes by J e (J the left
    Jacobian at w), i.e. turns X - C by -J e relative to them: dX_cam/dw = R [X - C]x J = [X_cam]x (R J)
    (since R [q]x = [R q]x R); dX_cam/dC = -R.
    """
    B = R @ _left_jacobian(w)
    x, y, z = (points_cam[:, k : k + 1] for k in range(3))
    jac = np.empty((len(points_cam), 3, _N_PARAMS))
    # Rows of [X_cam]x B, written out: (0, -z, y) B, (z, 0, -x) B, (-y, x, 0) B.
    jac[:, 0, :3] = y * B[2] - z * B[1]
    jac[:, 1, :3] = z * B[0] - x * B[2]
    jac[:, 2, :3] = x * B[1] - y * B[0]
    jac[:, :, 3:] = -R
    return jac


def _project(points_cam: FloatArray, camera: CameraModel, min_depth_m: float) -> FloatArray:
    """Camera-frame points (M, 3) -> distorted pixels (M, 2), depth clamped at min_depth_m.

    Same model as camera.project_points_cam; the clamps keep a bad start pose (vehicle partly behind the
    camera, or further off axis than the lens model holds: camera.within_model) finite instead of NaN, so
    the solver can walk back."""
    z = np.maximum(points_cam[:, 2], min_depth_m)
    xy = points_cam[:, :2] / z[:, None]
    if not math.isinf(camera.undistorted_limit):
        xy = np.stack(within_model(xy[:, 0], xy[:, 1], camera.undistorted_limit), axis=1)
    if camera.has_distortion:
        xy = distort_normalized(xy, camera.dist)
    K = camera.K
    return np.column_stack([K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2], K[1, 1] * xy[:, 1] + K[1, 2]])


def _project_jacobian(
    points_cam: FloatArray, d_points_cam: FloatArray, camera: CameraModel, min_depth_m: float
) -> FloatArray:
    """Chain rule of `_project`: d pixels / d p (M, 2, 6) from points (M, 3) and d X_cam / d p (M, 3, 6)."""
    clamped = points_cam[:, 2] < min_depth_m
    z = np.maximum(points_cam[:, 2], min_depth_m)
    x, y = points_cam[:, 0] / z, points_cam[:, 1] / z
    inv_z = 1.0 / z
    dz = np.where(clamped, 0.0, 1.0)[:, None] * d_points_cam[:, 2, :]
    dx = inv_z[:, None] * (d_points_cam[:, 0, :] - x[:, None] * dz)
    dy = inv_z[:, None] * (d_points_cam[:, 1, :] - y[:, None] * dz)
    dx, dy = distortion_chain(x, y, dx, dy, camera)
    K = camera.K
    return np.stack([K[0, 0] * dx + K[0, 1] * dy, K[1, 1] * dy], axis=1)


# ---------------------------------------------------------------------------------------------------------
# Residual models: each returns fun(p) -> (residuals (m,), Jacobian (m, 6))
# ---------------------------------------------------------------------------------------------------------

ResidualFn = Callable[[FloatArray], tuple[FloatArray, FloatArray]]


def _whole_box_residuals(
    corners: FloatArray,
    boxes: Boxes,
    edge_used: BoolArray,
    R0: Rotation,
    C0: Vec3,
    camera: CameraModel,
    params: RefinementParams,
) -> ResidualFn:
    """Tight box of the 8 projected corners (N, 8, 3) minus the detected boxes (N, 4), used edges only."""
    n = len(boxes)
    flat = corners.reshape(-1, 3)
    box_index, edge_index = np.nonzero(edge_used)
    axis = _EDGE_AXIS[edge_index]
    rows = np.arange(len(box_index))

    def fun(p: FloatArray) -> tuple[FloatArray, FloatArray]:
        R, C = _pose_from_params(p, R0, C0)
        cam = _camera_points(flat, R, C).reshape(n, 8, 3)
        uv = _project(cam.reshape(-1, 3), camera, params.min_depth_m).reshape(n, 8, 2)
        # The corner forming each edge is re-chosen at every evaluation (correspondences iterated).
        corner = _edge_corners(uv)[box_index, edge_index]
        residual = uv[box_index, corner, axis] - boxes[box_index, edge_index]
        points_cam = cam[box_index, corner]
        d_uv = _project_jacobian(
            points_cam, _camera_points_jacobian(points_cam, R, p[:3]), camera, params.min_depth_m
        )
        return residual, d_uv[rows, axis, :]

    return fun


# Edge k of a box (x1, y1, x2, y2) is the min u, min v, max u, max v of its corners: the image axis of each.
_EDGE_AXIS = np.array([0, 1, 0, 1])


def _edge_corners(uv: FloatArray) -> IntArray:
    """Index of the corner forming each edge of the tight box of points (N, K, 2): (N, 4)."""
    return np.column_stack(
        [
            uv[:, :, 0].argmin(axis=1),
            uv[:, :, 1].argmin(axis=1),
            uv[:, :, 0].argmax(axis=1),
            uv[:, :, 1].argmax(axis=1),
        ]
    ).astype(np.int64)


def _bottom_edge_residuals(
    footprint: FloatArray,
    boxes: Boxes,
    R0: Rotation,
    C0: Vec3,
    camera: CameraModel,
    params: RefinementParams,
) -> ResidualFn:
    """Row of the lowest projected footprint corner (footprints (N, 4, 3)) minus y2 of its box (N, 4), px.

    Deviation from the paper's corner choice (closest to the back-projected edge): at the solution both pick
    the same corner, but "closest" also reaches zero when a far corner merely touches the line while the
    near one hangs below it (a spurious solution); the lowest corner is the one that forms the tight box's
    bottom edge, so its residual is the exact model of the edge at every pose.
    The distorted image is used because the detector's edge is a straight horizontal line there; it is the
    same constraint as the corner lying on the edge's viewing surface through the camera centre (a plane
    without distortion), measured in pixels, with no need to sample the bent undistorted edge.
    The along-edge inequality x1 <= u <= x2 is left out: as a hinge residual it stalls the robust solver
    (zero curvature where it is inactive, a kink where it is not) and it fixes nothing on exact data.
    """
    n = len(footprint)
    flat = footprint.reshape(-1, 3)
    rows = np.arange(n)

    def fun(p: FloatArray) -> tuple[FloatArray, FloatArray]:
        R, C = _pose_from_params(p, R0, C0)
        cam = _camera_points(flat, R, C).reshape(n, 4, 3)
        v = _project(cam.reshape(-1, 3), camera, params.min_depth_m)[:, 1].reshape(n, 4)
        lowest = v.argmax(axis=1)
        points_cam = cam[rows, lowest]
        d_uv = _project_jacobian(
            points_cam, _camera_points_jacobian(points_cam, R, p[:3]), camera, params.min_depth_m
        )
        return v[rows, lowest] - boxes[:, 3], d_uv[:, 1, :]

    return fun


@dataclass(frozen=True, slots=True)
class _Pairs:
    """Paper Sec. III-F pairs: footprint corner x_n (N, 3) local <-> unit viewing ray of b_n (N, 3) camera
    frame; mask (N,) where a pair exists."""

    points: FloatArray
    rays: FloatArray
    mask: BoolArray


def _paper_pairs(
    footprint: FloatArray,
    boxes: Boxes,
    R: Rotation,
    C: Vec3,
    camera: CameraModel,
    ground: GroundPlaneFit,
    usable: BoolArray,
    params: RefinementParams,
) -> _Pairs:
    """x_n: the footprint corner closest to the bottom edge back-projected onto `ground` with the current
    pose (the choice metrics.delta_p makes); b_n: the point of the bottom edge closest to x_n's projection."""
    t = -R @ C
    errors = delta_p(
        boxes,
        footprint,
        R,
        t,
        camera,
        ground,
        DeltaPParams(edge_samples=params.edge_samples, border_margin_px=params.border_margin_px),
    )
    # delta_p refuses boxes clipped at any border; the paper's pairs only need the bottom edge.
    mask = errors.valid & usable
    corner = np.where(mask, errors.corner_index, 0)
    points = footprint[np.arange(len(boxes)), corner]
    u = _project(_camera_points(points, R, C), camera, params.min_depth_m)[:, 0]
    # The closest point of a horizontal edge (distorted image) is straight above/below the projection.
    b = np.column_stack([np.clip(u, boxes[:, 0], boxes[:, 2]), boxes[:, 3]])
    xy = undistort_pixels(b, camera)
    rays = np.column_stack([xy, np.ones(len(xy))])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return _Pairs(points, rays, mask)


def _point_to_ray_residuals(points: FloatArray, rays: FloatArray, R0: Rotation, C0: Vec3) -> ResidualFn:
    """Point-to-line registration (paper Sec. III-F, Briales & Gonzalez-Jimenez 2017): the two components
    (m) of each camera-frame point R (x_n - C) perpendicular to its fixed viewing ray (M, 3) -> (2M,)."""
    helper = np.where(np.abs(rays[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(rays, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(rays, e1)
    basis = np.stack([e1, e2], axis=1)  # (M, 2, 3), orthonormal, perpendicular to the ray

    def fun(p: FloatArray) -> tuple[FloatArray, FloatArray]:
        R, C = _pose_from_params(p, R0, C0)
        cam = _camera_points(points, R, C)
        residual = np.einsum("mij,mj->mi", basis, cam).ravel()
        jac = np.einsum("mij,mjk->mik", basis, _camera_points_jacobian(cam, R, p[:3])).reshape(-1, _N_PARAMS)
        return residual, jac

    return fun


# ---------------------------------------------------------------------------------------------------------
# Solver, covariance, result
# ---------------------------------------------------------------------------------------------------------


def _solve(
    fun: ResidualFn,
    x_scale: FloatArray,
    loss: Loss,
    f_scale: float,
    params: RefinementParams,
    p_start: FloatArray | None = None,
    anchor: float = 0.0,
) -> OptimizeResult:
    """scipy least_squares (trust region reflective) with the analytic Jacobian of `fun`.

    anchor > 0 appends the 6 residuals anchor * p / x_scale (p in scene units): a pull of `anchor` px per
    metre towards the start pose, which decides directions the data leave free (min-norm solution) and is
    negligible against real pixel residuals in every other direction.
    """
    last: dict[str, FloatArray] = {}  # residual and Jacobian share one evaluation
    prior_jac = np.diag(anchor / x_scale)

    def residual(p: FloatArray) -> FloatArray:
        r, J = fun(p)
        if anchor > 0.0:
            r, J = np.concatenate([r, prior_jac @ p]), np.vstack([J, prior_jac])
        last["p"], last["J"] = p.copy(), J
        return r

    def jacobian(p: FloatArray) -> FloatArray:
        if not ("p" in last and np.array_equal(last["p"], p)):
            residual(p)
        return last["J"]

    x0 = np.zeros(_N_PARAMS) if p_start is None else p_start
    return least_squares(
        residual,
        x0,
        jac=jacobian,
        method="trf",
        loss=loss,
        f_scale=f_scale,
        x_scale=x_scale,
        ftol=params.tolerance,
        xtol=params.tolerance,
        gtol=params.tolerance,
        max_nfev=params.max_evaluations,
    )


def _robust_weights(residual: FloatArray, loss: Loss, f_scale: float) -> FloatArray:
    """IRLS weights rho'(z), z = (r / f_scale)^2, of scipy's losses: 1 for inliers, smaller for outliers."""
    z = (residual / f_scale) ** 2
    if loss == "huber":
        return np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1.0)))
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + z)
    if loss == "cauchy":
        return 1.0 / (1.0 + z)
    if loss == "arctan":
        return 1.0 / (1.0 + z * z)
    return np.ones_like(z)


@dataclass(frozen=True, slots=True)
class _Uncertainty:
    covariance: FloatArray
    sigma_px: float
    directions: FloatArray  # (6, 6) columns, scene units, largest std first
    stds_m: FloatArray  # (6,)


def _covariance(
    residual: FloatArray,
    J: FloatArray,
    loss: Loss,
    f_scale: float,
    scene_range_m: float,
    params: RefinementParams,
) -> _Uncertainty:
    """Covariance of p = [w (rad), C (m)]: sigma^2 (J^T W J)^-1 at the solution (Gauss-Newton / IRLS),
    plus pose_bias_std_m^2 on the camera-centre block.

    W = diag(rho'(r^2 / f^2)), the robust loss's weights, so rejected outliers do not count as information.
    sigma^2 = sum(w r^2) / (sum(w) - 6), the weighted residual variance, floored at min_sigma_px^2: exact
    synthetic boxes would otherwise claim zero uncertainty, and a detector never localises an edge better
    than about a pixel. The inverse is taken in scene units (w scaled by the scene range) by eigen-
    decomposition, with eigenvalues floored relative to the largest, so an unobservable direction comes
    out as a huge but finite variance along the worst direction. A common offset of all vehicle positions
    (GNSS drift) shifts the fitted camera by the same vector and no number of boxes averages it away, hence
    the additive term.
    """
    weights = _robust_weights(residual, loss, f_scale)
    dof = max(float(weights.sum()) - _N_PARAMS, 1.0)
    sigma = max(math.sqrt(float(np.sum(weights * residual**2)) / dof), params.min_sigma_px)
    scale = np.array([scene_range_m] * 3 + [1.0] * 3)
    J_scene = J / scale  # d r / d (scene-unit parameters)
    information = (J_scene.T @ (weights[:, None] * J_scene)) / sigma**2
    eigenvalues, eigenvectors = np.linalg.eigh(information)
    eigenvalues = np.maximum(eigenvalues, max(float(eigenvalues[-1]), 1e-300) * 1e-16)
    covariance_scene = (eigenvectors / eigenvalues) @ eigenvectors.T
    covariance_scene[3:, 3:] += params.pose_bias_std_m**2 * np.eye(3)
    variances, directions = np.linalg.eigh(covariance_scene)
    variances, directions = variances[::-1], directions[:, ::-1]  # largest std first
    largest = directions[np.argmax(np.abs(directions), axis=0), np.arange(_N_PARAMS)]
    directions = directions * np.where(largest < 0.0, -1.0, 1.0)  # sign: largest component positive
    covariance = covariance_scene / np.outer(scale, scale)
    return _Uncertainty(covariance, sigma, directions, np.sqrt(np.maximum(variances, 0.0)))


def box_residuals(
    R_cam_from_local: Rotation,
    t_cam_from_local: Vec3,
    tracks: Sequence[MatchedTrack],
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: RefinementParams,
) -> tuple[FloatArray, FloatArray]:
    """Whole-box misfit of a given pose without refining.

    Returns the tight box of the projected vehicle cuboid minus the detected box (N, 4) px, NaN on edges
    clipped by the image border, and the detected box heights (N,) px.
    """
    data = _stack_tracks(tracks, vehicle)
    _check_pose(R_cam_from_local, t_cam_from_local)
    C = camera_centre(R_cam_from_local, t_cam_from_local)
    residuals = _model_boxes(data.corners, R_cam_from_local, C, camera, params.min_depth_m) - data.boxes
    residuals[_clipped_edges(data.boxes, camera, params.border_margin_px)] = np.nan
    return residuals, data.boxes[:, 3] - data.boxes[:, 1]


def _clipped_edges(boxes: Boxes, camera: CameraModel, margin: float) -> BoolArray:
    """(N, 4) True where a box edge lies on the image border (within margin): the border, not the vehicle."""
    return np.column_stack(
        [
            boxes[:, 0] <= margin,
            boxes[:, 1] <= margin,
            boxes[:, 2] >= camera.width - margin,
            boxes[:, 3] >= camera.height - margin,
        ]
    )


def _model_boxes(corners: FloatArray, R: Rotation, C: Vec3, camera: CameraModel, min_depth_m: float) -> Boxes:
    """Tight boxes (N, 4) of the projected corners (N, K, 3)."""
    uv = _project(_camera_points(corners.reshape(-1, 3), R, C), camera, min_depth_m).reshape(
        len(corners), -1, 2
    )
    return np.column_stack([uv[:, :, 0].min(1), uv[:, :, 1].min(1), uv[:, :, 0].max(1), uv[:, :, 1].max(1)])


def _make_result(
    method: Method,
    R: Rotation,
    C: Vec3,
    data: _Stacked,
    camera: CameraModel,
    ground: GroundPlaneFit | None,
    final: ResidualFn,
    loss: Loss,
    f_scale: float,
    evaluations: int,
    converged: bool,
    cost: float,
    params: RefinementParams,
) -> Refinement:
    """Assemble the result at the final pose. `final` is the residual model built around that pose: its
    Jacobian at p = 0 is with respect to a small turn and shift of the final camera (no SO(3) Jacobian)."""
    t = -R @ C
    final_residual, final_jacobian = final(np.zeros(_N_PARAMS))
    scene_range = _scene_range(data, C)
    uncertainty = _covariance(final_residual, final_jacobian, loss, f_scale, scene_range, params)
    cov = uncertainty.covariance
    box_residuals = _model_boxes(data.corners, R, C, camera, params.min_depth_m) - data.boxes
    box_residuals[_clipped_edges(data.boxes, camera, params.border_margin_px)] = np.nan
    finite = np.isfinite(box_residuals)
    errors = delta_p(
        data.boxes,
        data.corners[:, :4, :],
        R,
        t,
        camera,
        ground,
        DeltaPParams(border_margin_px=params.border_margin_px),
    )
    return Refinement(
        method=method,
        R_cam_from_local=R,
        t_cam_from_local=t,
        camera_centre=C,
        covariance=cov,
        position_std_m=math.sqrt(max(float(np.linalg.eigvalsh(cov[3:, 3:])[-1]), 0.0)),
        rotation_std_deg=math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(cov[:3, :3])[-1]), 0.0))),
        principal_directions=uncertainty.directions,
        principal_stds_m=uncertainty.stds_m,
        worst_direction=uncertainty.directions[:, 0],
        worst_std_m=float(uncertainty.stds_m[0]),
        scene_range_m=scene_range,
        box_track_ids=data.track_ids,
        stamps=data.stamps,
        residuals_px=box_residuals,
        box_rmse_px=float(np.sqrt(np.mean(box_residuals[finite] ** 2))) if finite.any() else math.nan,
        delta_p_m=errors.delta_p_m,
        sigma_px=uncertainty.sigma_px,
        used_residuals=len(final_residual),
        iterations=evaluations,
        converged=converged,
        cost=cost,
    )
