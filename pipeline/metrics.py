"""The paper's accuracy metrics (Sec. IV-B): delta_p, e %, and scoring a calibration against ground truth.

delta_p is the ground-plane distance between a calibration-vehicle box's bottom edge, back-projected with a
candidate calibration, and the vehicle footprint corner closest to it (the dark green line of the paper's
refinement figure, Sec. III-F). Inputs are boxes in pixels and footprints in the local frame; outputs are
metres and percent. `evaluate_against_ground_truth` applies it to a CalibrationResult and a simulator
GroundTruth (ground_truth.json) and adds the camera position and rotation errors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.arrays import (
    Boxes,
    Corners,
    FloatArray,
    IntArray,
    Mask,
    Rotation,
    Stamps,
    Vec3,
    as_float_array,
)
from pipeline.camera import (
    CameraModel,
    camera_centre,
    pose_difference,
    quaternion_wxyz_from_rotation,
    rotation_angle_rad,
    undistort_pixels,
)
from pipeline.errors import InputError, ShapeError
from pipeline.frames import UtmFrame
from pipeline.ground import GroundPlaneFit
from pipeline.tracking import touches_border
from schemas.files import GroundTruth
from schemas.results import CalibrationResult, CameraPosition, Provenance, ReferenceFrame, Verdict

# A chi-square of 6 dof: its median, and the value it exceeds as rarely (0.27 %) as a normal variable
# exceeds 3 std (scipy.stats.chi2.median(6), chi2.isf(0.0027, 6)).
POSE_CHI2_MEDIAN = 5.348
POSE_CHI2_3SIGMA = 20.06


@dataclass(frozen=True, slots=True)
class DeltaPParams:
    # Points along a box's bottom edge. Through a distorting lens the straight image edge back-projects to
    # a curve; 65 samples keep the chord sag far below a millimetre for boxes up to a few hundred pixels
    # wide. Without distortion the edge maps to a straight line and two points are exact.
    edge_samples: int = 65
    # Boxes with an edge this close to the image border are clipped: their bottom edge is not the
    # vehicle's (the lowest corner may lie outside the image), so they are excluded. A few pixels, not
    # one: a detector's box of a truncated vehicle ends near the border, not on it (box jitter).
    border_margin_px: float = 3.0


@dataclass(frozen=True, slots=True)
class BoxErrors:
    """Per-box delta_p (paper Sec. IV-B); NaN / -1 in rows that are not `valid`.

    delta_p_m (N,) m: in-plane distance of the closest footprint corner to the back-projected bottom edge.
    distance_m (N,) m: distance of that corner to the camera centre (the denominator of e).
    corner_index (N,): 0..3 into the footprint (rear-right, front-right, front-left, rear-left), -1 invalid.
    valid = not touches_border and not misses_ground.
    """

    delta_p_m: FloatArray
    distance_m: FloatArray
    corner_index: IntArray
    valid: Mask
    touches_border: Mask
    misses_ground: Mask

    @property
    def e_pct(self) -> FloatArray:
        """Relative error e = delta_p / distance * 100 (%) per box, NaN where invalid."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.asarray(100.0 * self.delta_p_m / self.distance_m, dtype=np.float64)

    def summary(self) -> DeltaPSummary:
        """Mean and max over the valid boxes: the paper's delta_{p,m}, delta_{p,w}, e_m, e_w."""
        return summarize(self)


@dataclass(frozen=True, slots=True)
class DeltaPSummary:
    """Paper Table I/II columns; None when no box was valid."""

    delta_p_mean_m: float | None
    delta_p_max_m: float | None
    e_mean_pct: float | None
    e_max_pct: float | None
    boxes_used: int
    boxes_excluded: int


def summarize(errors: BoxErrors) -> DeltaPSummary:
    """Mean/max of delta_p (m) and e (%) over the valid boxes of `errors`."""
    used = int(np.count_nonzero(errors.valid))
    excluded = len(errors.valid) - used
    if used == 0:
        return DeltaPSummary(None, None, None, None, 0, excluded)
    d = errors.delta_p_m[errors.valid]
    e = errors.e_pct[errors.valid]
    return DeltaPSummary(float(d.mean()), float(d.max()), float(e.mean()), float(e.max()), used, excluded)


def _footprint_planes(footprints: Corners) -> tuple[FloatArray, FloatArray]:
    """Plane through each footprint (N, 4, 3) -> unit normals (N, 3) pointing up, offsets (N,).

    The cross product of the two diagonals is the normal of the rectangle's plane (exact for a rigid
    body's footprint, also when the vehicle pitches or rolls on a slope). Degenerate footprints get NaN.
    """
    normal = np.cross(footprints[:, 2] - footprints[:, 0], footprints[:, 3] - footprints[:, 1])
    norm = np.linalg.norm(normal, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        normal = normal / np.where(norm > 1e-9, norm, np.nan)[:, None]
    normal = np.where(normal[:, 2:3] < 0.0, -normal, normal)
    offset = np.einsum("nj,nj->n", footprints.mean(axis=1), normal)
    return normal, offset


def back_project_bottom_edges(
    boxes: Boxes,
    R_cam_from_local: Rotation,
    t_cam_from_local: Vec3,
    camera: CameraModel,
    normals: FloatArray,
    offsets: FloatArray,
    samples: int,
) -> FloatArray:
    """Sample each box's bottom edge (x1, y2)-(x2, y2) at `samples` pixels and intersect the (undistorted)
    rays with the box's plane {n . p = offset}: (N, samples, 3) local-frame points, NaN where a ray does
    not meet the plane in front of the camera."""
    n = len(boxes)
    fraction = np.linspace(0.0, 1.0, samples)
    u = boxes[:, 0:1] + fraction[None, :] * (boxes[:, 2:3] - boxes[:, 0:1])
    v = np.broadcast_to(boxes[:, 3:4], u.shape)
    xy = undistort_pixels(np.stack([u.ravel(), v.ravel()], axis=1), camera)
    rays_cam = np.column_stack([xy, np.ones(len(xy))])
    # Row-vector form of R^T d: camera-frame ray directions in the local frame.
    rays_local = (rays_cam @ R_cam_from_local).reshape(n, samples, 3)
    centre = camera_centre(R_cam_from_local, t_cam_from_local)
    denom = np.einsum("nsj,nj->ns", rays_local, normals)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (offsets - normals @ centre)[:, None] / denom
    hits = centre + s[..., None] * rays_local
    # s > 0 also rejects NaN/inf: rays parallel to the plane or pointing away from it (above the horizon).
    hits[~(s > 0.0) | ~np.isfinite(s)] = np.nan
    return np.asarray(hits, dtype=np.float64)


def _distance_to_polyline(points: FloatArray, polyline: FloatArray) -> FloatArray:
    """Distance of points (N, C, 3) to polylines (N, S, 3) whose first and last segments extend to infinity:
    (N, C). With S = 2 this is the distance to the infinite line through the two points."""
    start = polyline[:, :-1]  # (N, S-1, 3)
    seg = polyline[:, 1:] - start
    seg_len2 = np.einsum("nsj,nsj->ns", seg, seg)
    rel = points[:, :, None, :] - start[:, None, :, :]  # (N, C, S-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        along = np.einsum("ncsj,nsj->ncs", rel, seg) / np.where(seg_len2 > 0.0, seg_len2, np.nan)[:, None, :]
    along = np.nan_to_num(along, nan=0.0)
    lower = np.zeros(seg.shape[1])
    upper = np.ones(seg.shape[1])
    lower[0] = -np.inf  # the back-projected edge is a line, not the segment between the box's corners
    upper[-1] = np.inf
    along = np.clip(along, lower, upper)
    offset = rel - along[..., None] * seg[:, None, :, :]
    return np.asarray(np.linalg.norm(offset, axis=-1).min(axis=-1), dtype=np.float64)


def delta_p(
    boxes: Boxes,
    footprints: Corners,
    R_cam_from_local: Rotation,
    t_cam_from_local: Vec3,
    camera: CameraModel,
    ground: GroundPlaneFit | None = None,
    params: DeltaPParams = DeltaPParams(),
) -> BoxErrors:
    """delta_p per calibration-vehicle box (paper Sec. IV-B, refinement figure of Sec. III-F).

    boxes (N, 4) px (x1, y1, x2, y2, as detected: distorted image); footprints (N, 4, 3) local frame, the
    vehicle's true footprint corners at each box's stamp; R, t: candidate calibration X_cam = R X_local + t.
    The bottom edge is back-projected onto the ground plane (a polyline when the lens distorts, its end
    segments extended to infinity), every footprint corner is dropped onto that plane, and delta_p is the
    in-plane distance of the closest corner to the edge; e (BoxErrors.e_pct) divides it by that corner's
    distance to the camera centre.

    Ground plane: `None` uses each box's own footprint plane (the local road surface, right on slopes and
    in the evaluation); the pipeline passes its fitted GroundPlaneFit.

    Floor: with the true calibration and exact boxes (tight bounds of the projected body) delta_p is 0 up
    to floating point (and the chord sag of the distorted edge): the lowest projected body point is a
    footprint corner, which lies exactly on the box's bottom edge and on its own footprint plane. Detector
    jitter of the box's y2 moves the back-projected edge by roughly jitter_px * depth^2 / (f * height), so a
    perfect calibration scores > 0 on jittered boxes; compare results against the truth's own score.

    Excluded (valid False): boxes touching the image border, and boxes whose edge does not meet the ground
    in front of the camera at every sample (a box above the horizon, or a candidate calibration that looks
    away from the ground).
    """
    boxes = as_float_array(boxes, "N,4", name="boxes")
    footprints = as_float_array(footprints, "N,4,3", name="footprints")
    R = as_float_array(R_cam_from_local, "3,3", name="R_cam_from_local")
    t = as_float_array(t_cam_from_local, "3", name="t_cam_from_local")
    if len(boxes) != len(footprints):
        raise ShapeError(f"footprints: expected {len(boxes)} rows like boxes, got {len(footprints)}")
    if params.edge_samples < 2:
        raise ValueError(f"edge_samples = {params.edge_samples}, need at least 2")
    n = len(boxes)
    if ground is None:
        normals, offsets = _footprint_planes(footprints)
    else:
        normals = np.broadcast_to(np.asarray(ground.normal, dtype=np.float64), (n, 3))
        offsets = np.full(n, float(ground.offset))

    samples = params.edge_samples if camera.has_distortion else 2
    edges = back_project_bottom_edges(boxes, R, t, camera, normals, offsets, samples)
    clipped = touches_border(boxes, camera.width, camera.height, params.border_margin_px)
    misses = ~np.all(np.isfinite(edges), axis=(1, 2))
    valid = ~clipped & ~misses

    # Corners are dropped onto the plane along its normal, so the distance is measured within the plane
    # even when a fitted ground plane does not pass through the footprint.
    heights = np.einsum("ncj,nj->nc", footprints, normals) - offsets[:, None]
    on_plane = footprints - heights[..., None] * normals[:, None, :]
    delta = np.full(n, np.nan)
    distance = np.full(n, np.nan)
    corner = np.full(n, -1, dtype=np.int64)
    if np.any(valid):
        per_corner = _distance_to_polyline(on_plane[valid], edges[valid])  # (V, 4)
        best = np.argmin(per_corner, axis=1)
        rows = np.arange(len(best))
        delta[valid] = per_corner[rows, best]
        corner[valid] = best
        centre = camera_centre(R, t)
        distance[valid] = np.linalg.norm(footprints[valid][rows, best] - centre, axis=1)
    return BoxErrors(delta, distance, corner, valid, clipped, misses)


@dataclass(frozen=True, slots=True)
class Evaluation:
    """A CalibrationResult scored against simulator ground truth (paper Sec. IV-B plus pose errors).

    delta_p / e over every frame of the truth that holds the calibration vehicle's published box; pose
    errors compare the camera centre in absolute UTM (m) and the rotation (deg). `None` when not
    computable (a refused result without a pose, or no valid box). Per-box detail in `stamps` / `errors`.
    """

    camera_id: str
    result_id: str
    verdict: str
    boxes_total: int  # frames in which the truth marks a calib box
    boxes_used: int
    excluded_border: int
    excluded_no_ground: int
    missing_box: int  # calib box marked but its coordinates or footprint are not in the truth file
    delta_p_mean_m: float | None
    delta_p_max_m: float | None
    e_mean_pct: float | None
    e_max_pct: float | None
    position_error_m: float | None
    horizontal_error_m: float | None
    height_error_m: float | None  # signed: result minus truth
    rotation_error_deg: float | None
    # The pose error's squared length in the result's own reported covariance (6 dof): how honest the
    # reported uncertainty is. With an honest covariance it follows a chi-square of 6 dof (median 5.35,
    # above POSE_CHI2_3SIGMA in 0.27 % of results); None without a pose or a covariance.
    pose_chi2: float | None = None
    notes: tuple[str, ...] = ()
    stamps: Stamps = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    errors: BoxErrors | None = None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no per-box arrays); keys carry their units."""
        return {
            "camera_id": self.camera_id,
            "result_id": self.result_id,
            "verdict": self.verdict,
            "boxes_total": self.boxes_total,
            "boxes_used": self.boxes_used,
            "excluded_border": self.excluded_border,
            "excluded_no_ground": self.excluded_no_ground,
            "missing_box": self.missing_box,
            "delta_p_mean_m": self.delta_p_mean_m,
            "delta_p_max_m": self.delta_p_max_m,
            "e_mean_pct": self.e_mean_pct,
            "e_max_pct": self.e_max_pct,
            "position_error_m": self.position_error_m,
            "horizontal_error_m": self.horizontal_error_m,
            "height_error_m": self.height_error_m,
            "rotation_error_deg": self.rotation_error_deg,
            "pose_chi2": self.pose_chi2,
            "notes": list(self.notes),
        }


def _in_truth_frame(
    R_result: Rotation, t_result: Vec3, result: CalibrationResult, truth: GroundTruth
) -> tuple[Rotation, Vec3]:
    """The result's R, t re-expressed for points in the truth's local frame (the origins may differ).

    X_cam = R (X_utm - o_result) + t_result = R (X_truth_local + o_truth - o_result) + t_result.
    """
    shift = np.asarray(truth.origin, dtype=np.float64) - np.asarray(result.frame.origin, dtype=np.float64)
    return R_result, t_result + R_result @ shift


def true_time_offset_ns(truth: GroundTruth) -> int:
    """The simulated camera's true time offset (vehicle clock minus detection stamp) for the image's middle
    row, the result's convention: its stamp is the first row's exposure plus the latency, and a rolling
    shutter exposes the middle row half the readout later."""
    return truth.clock_offset_ns - truth.latency_ns + truth.readout_ns // 2


def evaluate_against_ground_truth(
    result: CalibrationResult, truth: GroundTruth, params: DeltaPParams = DeltaPParams()
) -> Evaluation:
    """Score `result` with the truth's calibration-vehicle boxes and footprints (paper Sec. IV-B).

    delta_p uses each box's own footprint plane and the result's intrinsics; position error is between
    camera centres in absolute UTM, rotation error is the angle of R_result^T R_truth. Raises InputError when
    the two are in different CRSs (no silent reprojection of a result).

    Floor: `result_from_ground_truth(truth)` scores delta_p ~1e-13 m on noise-free boxes (carla-like seed 0:
    mean 2.4e-14 m, max 2.6e-13 m; see `delta_p` for why), but clearly more once the simulator jitters the
    boxes (sil-west seed 0, 1 px: mean ~0.3 m, far vehicles worst). Judge a result against that floor.
    """
    if result.frame.crs != truth.crs:
        raise InputError(
            "calibration result",
            f"frame.crs = {result.frame.crs} differs from the ground truth's {truth.crs}",
        )
    notes: list[str] = []
    if result.camera_id != truth.camera_id:
        notes.append(
            f"camera_id {result.camera_id!r} of the result differs from the truth's {truth.camera_id!r}"
        )
    if result.intrinsics != truth.intrinsics:
        notes.append("the result's intrinsics differ from the truth's; delta_p uses the result's")

    marked = [frame for frame in truth.frames if frame.calib_box is not None]
    usable = [frame for frame in marked if frame.box is not None and frame.footprint_local is not None]
    stamps = np.array([frame.stamp_ns for frame in usable], dtype=np.int64)
    boxes = np.array([frame.box for frame in usable], dtype=np.float64).reshape(-1, 4)
    footprints = np.array([frame.footprint_local for frame in usable], dtype=np.float64).reshape(-1, 4, 3)

    errors: BoxErrors | None = None
    summary = DeltaPSummary(None, None, None, None, 0, 0)
    position_error = horizontal_error = height_error = rotation_error = pose_chi2 = None
    if result.R is not None and result.t is not None:
        R, t = _in_truth_frame(
            np.asarray(result.R, dtype=np.float64), np.asarray(result.t, dtype=np.float64), result, truth
        )
        camera = CameraModel.from_intrinsics(result.intrinsics)
        errors = delta_p(boxes, footprints, R, t, camera, params=params)
        summary = summarize(errors)
        R_truth = np.asarray(truth.R, dtype=np.float64)
        centre_utm = camera_centre(R, t) + np.asarray(truth.origin, dtype=np.float64)
        centre_truth = np.asarray(truth.camera_position_utm, dtype=np.float64)
        error_vec = centre_utm - centre_truth
        position_error = float(np.linalg.norm(error_vec))
        horizontal_error = float(np.linalg.norm(error_vec[:2]))
        height_error = float(error_vec[2])
        rotation_error = math.degrees(rotation_angle_rad(R, R_truth))
        if result.uncertainty is not None:
            pose_chi2 = normalised_pose_error(
                pose_difference(R, centre_utm, R_truth, centre_truth),
                np.asarray(result.uncertainty.covariance, dtype=np.float64),
            )
    else:
        notes.append("the result carries no pose (R, t); nothing to score")

    return Evaluation(
        camera_id=truth.camera_id,
        result_id=result.result_id,
        verdict=result.verdict.status,
        boxes_total=len(marked),
        boxes_used=summary.boxes_used,
        excluded_border=int(np.count_nonzero(errors.touches_border)) if errors is not None else 0,
        excluded_no_ground=(
            int(np.count_nonzero(errors.misses_ground & ~errors.touches_border)) if errors is not None else 0
        ),
        missing_box=len(marked) - len(usable),
        delta_p_mean_m=summary.delta_p_mean_m,
        delta_p_max_m=summary.delta_p_max_m,
        e_mean_pct=summary.e_mean_pct,
        e_max_pct=summary.e_max_pct,
        position_error_m=position_error,
        horizontal_error_m=horizontal_error,
        height_error_m=height_error,
        rotation_error_deg=rotation_error,
        pose_chi2=pose_chi2,
        notes=tuple(notes),
        stamps=stamps,
        errors=errors,
    )


def normalised_pose_error(difference: FloatArray, covariance: FloatArray) -> float | None:
    """d^T S^-1 d of a pose difference [w, C] (6,) (camera.pose_difference) under a pose covariance S (6, 6)
    in the same convention; None when S is not positive definite (no finite answer)."""
    d = as_float_array(difference, "6", "pose difference")
    S = as_float_array(covariance, "6,6", "covariance")
    try:
        L = np.linalg.cholesky((S + S.T) / 2.0)
    except np.linalg.LinAlgError:
        return None
    z = np.linalg.solve(L, d)
    return float(z @ z)


def _fmt(value: float | None, spec: str, unit: str) -> str:
    return "n/a" if value is None else f"{value:{spec}} {unit}"


def format_evaluation(evaluation: Evaluation) -> str:
    """Readable table of an Evaluation (what `rsucal evaluate` prints)."""
    ev = evaluation
    delta = f"{_fmt(ev.delta_p_mean_m, '.3f', 'm'):>11} / {_fmt(ev.delta_p_max_m, '.3f', 'm'):>11}"
    e_pct = f"{_fmt(ev.e_mean_pct, '.3f', '%'):>11} / {_fmt(ev.e_max_pct, '.3f', '%'):>11}"
    split = (
        f"horizontal {_fmt(ev.horizontal_error_m, '.3f', 'm')}, height {_fmt(ev.height_error_m, '+.3f', 'm')}"
    )
    rows = [
        f"Evaluation of {ev.result_id} ({ev.verdict}) against the ground truth of camera {ev.camera_id}",
        f"  boxes used           {ev.boxes_used} of {ev.boxes_total} with the calibration vehicle",
        f"  boxes excluded       {ev.excluded_border} touching the border, "
        f"{ev.excluded_no_ground} not meeting the ground, {ev.missing_box} not in the truth file",
        f"  delta_p  mean / max  {delta}   (paper delta_p,m / delta_p,w; truth boxes vs true footprints)",
        f"  e        mean / max  {e_pct}   (paper e_m / e_w; the same boxes)",
        f"  position error       {_fmt(ev.position_error_m, '.3f', 'm'):>11}   ({split})",
        f"  rotation error       {_fmt(ev.rotation_error_deg, '.4f', 'deg'):>11}",
        f"  error / reported std {_fmt(ev.pose_chi2, '.2f', ''):>11}   (the pose error's chi-square in the "
        f"result's covariance, 6 dof: honest ~{POSE_CHI2_MEDIAN:.2f}, rarely above {POSE_CHI2_3SIGMA:.1f})",
    ]
    rows.extend(f"  note: {note}" for note in ev.notes)
    return "\n".join(rows)


def result_from_ground_truth(
    truth: GroundTruth, rsu_id: str, result_id: str | None = None
) -> CalibrationResult:
    """An accepted CalibrationResult holding the truth's calibration (tests and benchmarks: the floor)."""
    R = np.asarray(truth.R, dtype=np.float64)
    position = truth.camera_position_utm
    lat, lon = UtmFrame(truth.crs).to_wgs84(np.array([position[0]]), np.array([position[1]]))
    quaternion = quaternion_wxyz_from_rotation(R.T)  # camera->world, as CalibrationResult documents
    stamps = [frame.stamp_ns for frame in truth.frames]
    return CalibrationResult(
        rsu_id=rsu_id,
        camera_id=truth.camera_id,
        result_id=result_id or f"ground-truth-{truth.camera_id}",
        created_at_ns=max(stamps, default=0),
        frame=ReferenceFrame(crs=truth.crs, origin=truth.origin),
        R=truth.R,
        t=truth.t_local,
        camera_position=CameraPosition(utm=position, lat=float(lat[0]), lon=float(lon[0]), alt=position[2]),
        orientation_wxyz=(
            float(quaternion[0]),
            float(quaternion[1]),
            float(quaternion[2]),
            float(quaternion[3]),
        ),
        intrinsics=truth.intrinsics,
        verdict=Verdict(status="accepted", reasons=["ground truth of the simulator"]),
        provenance=Provenance(
            window_start_ns=min(stamps, default=None),
            window_end_ns=max(stamps, default=None),
            station_id=truth.station_id,
        ),
    )
