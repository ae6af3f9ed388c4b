"""The straight-track solver (not in the paper): the camera pose of an image track whose vehicle drove a
straight line, from the boxes' shape and the assumption that the camera is mounted square.

Collinear 2D-3D correspondences fix a camera pose only up to a rotation about their line, so the paper's
EPnP (`pipeline.hypotheses`) returns an arbitrary member of that family. Here the vehicle's cuboid
(VehicleProfile), projected from each pose about the line, is compared with the boxes' edges, and the
camera's image roll about the ground normal is assumed near one of a few mounts (upright or portrait,
`StraightTrackParams`). `solve_straight_track` is the entry point; `pipeline.hypotheses` calls it when
EPnP leaves the pose unfixed or only weakly fixed, and `pose_box_misfit` lets it compare the two.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from pipeline.arrays import BoolArray, Boxes, FloatArray, IntArray, Points3, PoseArray, Rotation, Vec3
from pipeline.camera import (
    CameraModel,
    distort_xy,
    distortion_chain,
    rotation_angle_rad,
    rotation_from_rvec,
    within_model,
)
from pipeline.ground import GroundPlaneFit
from pipeline.vehicle import body_corners
from schemas.common import VehicleProfile


@dataclass(frozen=True, slots=True)
class StraightTrackParams:
    """The straight-track solver's settings (`pipeline.hypotheses.HypothesisParams.straight_track`).

    ASSUMED: the camera is mounted square, i.e. its image roll about the ground normal is within
    `max_roll_deg` of one of `mount_rolls_deg` (upright or portrait either way), and the calibration
    vehicle's cuboid (VehicleProfile) reproduces its boxes. The mount is chosen, and a roll measured from
    the box shape kept over the mount's exact roll, only on clear evidence (the ratios below); otherwise
    the exact roll of the first mount (upright) stands. A camera outside every window has its straight
    tracks rejected where the box shape shows it (it may be missed on far, small boxes). A fixed roll
    fixes the pose only when the road runs along the view: the sensitivity |sin(road, the image's level
    axis)| must reach `min_level_sensitivity`.
    """

    min_level_sensitivity: float = 0.3
    # False: the roll is always a mount's exact roll (the box shape only chooses the mount).
    roll_from_box_shape: bool = True
    # The mounts assumed and how far a camera may be rolled off them (deg, `camera_rotation_from_view`'s
    # roll: +90 turns the image's x axis down). Not 180 by default: on a straight track the camera
    # mirrored across the road and rolled nearly 180 deg reproduces the boxes about as well as the truth;
    # add it for a camera known to hang upside down with its image not flipped.
    mount_rolls_deg: tuple[float, ...] = (0.0, 90.0, -90.0)
    max_roll_deg: float = 15.0
    # A straight track whose boxes the vehicle's cuboid misses by more than this from every pose about
    # the line is another vehicle's (mean soft-L1 cost of the edge residuals in units of 2 % of the box
    # diagonal; about every edge 10 % of the diagonal off, in line with validation's 25 % of the height
    # for the worst edge; the calibration vehicle's tracks score 0.1-1 on the presets, others' 0.6-15).
    max_box_misfit: float = 4.0
    # A mount after the first is taken only if it fits the box shape this much better than the first.
    mount_evidence_ratio: float = 1.5
    # The mount's exact roll is kept when it turns the fitted camera by at most this (deg), or when the
    # free roll fits the boxes less than this much better.
    mount_snap_deg: float = 1.0
    roll_evidence_ratio: float = 1.1
    # A pose more than `mount_snap_deg` away fitting within this factor of the best makes the track
    # ambiguous, and it is rejected: in another mount's window always (the camera mirrored across the
    # road turns one portrait mount into the other; a far car's box barely tells upright from portrait),
    # in the same window when the roll is measured (a road running straight away from the camera looks
    # alike from a camera rolled either way). With 1 px box noise the two sides of such a symmetry
    # differ by up to ~1.3x; the truth's nearest rival on the presets scores 1.35x or more.
    ambiguity_ratio: float = 1.3


@dataclass(frozen=True, slots=True)
class StraightTrackFit:
    """The solver's pose: R_cam_from_local, camera centre C (local m), the solver name (level for an
    upright image, level+90 / level-90 for one turned into portrait, level+180 upside down if declared,
    box-roll for a roll measured from the box shape) and the 1-sigma (deg) of its worst fitted angle."""

    R: Rotation
    C: Vec3
    solver: str
    rotation_std_deg: float


def track_line(points: Points3) -> tuple[Vec3, Vec3]:
    """The best-fit 3D line of points (N, 3): (origin, unit direction), local frame m."""
    origin = points.mean(axis=0)
    direction = np.linalg.svd(points - origin, full_matrices=False)[2][0]
    return origin, direction


@dataclass(frozen=True, slots=True)
class TrackShape:
    """What the straight-track fit reads besides the centres: the boxes (N, 4) px and the vehicle's poses
    (N, 6) of the same rows, from which the body cuboid is projected."""

    boxes: Boxes
    poses: PoseArray
    vehicle: VehicleProfile


# Rotation about the track's line scanned for the box shape: a coarse full turn, then a fine window.
_FAMILY_COARSE_STEP = math.radians(4.0)
_FAMILY_FINE_STEP = math.radians(0.5)
_MAX_SHAPE_ROWS = 40  # rows, evenly spread, that carry the box shape
# Where the box-shape cost turns from quadratic to linear: 2 % of the box diagonal, about twice the
# scale-free spread of a good fit.
_BOX_SHAPE_SCALE = 0.02
# An edge off by 20 % of the box diagonal or more is a miss, whatever the size of the miss.
_BOX_EDGE_MAX_COST = 9.0
# Box fits per track: up to 3 from the first scan's best starts, those within 10x of its best misfit
# (the scan runs along the centres' family, which the box-centre approximation shifts: a start's misfit
# overstates that of its fit, the truth's several times over in tests), then up to 2 from the scan about
# the best fit. Starts within 3 deg of one taken end in the same fit.
_MAX_BOX_FITS = 3
_BOX_FIT_CANDIDATE_RATIO = 10.0
_MAX_SECOND_FITS = 2
_DISTINCT_START_RAD = math.radians(3.0)
# From a start 20-60 deg off (the scan's, on a shifted family) a fit can need 15 steps; the refinement
# downstream does the last digits.
_BOX_FIT_ITERATIONS = 25
# The box fit has settled when every parameter's step is below these: yaw, pitch, roll (rad), camera
# centre (m); 1e-5 rad puts a box edge 20 m away 0.2 mm off.
_BOX_FIT_SETTLED_STEPS = np.array([1e-5, 1e-5, 1e-5, 1e-3, 1e-3, 1e-3])


_IS_U_EDGE = np.array([True, False, True, False])  # x1, y1, x2, y2
# Column offsets of the u (0) and v (8) values per edge in the (M, 16) [u | v] of a box's 8 corners.
_UV_COLUMN = np.array([0, 8, 0, 8])


@dataclass(frozen=True, slots=True)
class _BoxData:
    """A track's boxes (M, 4) px with the vehicle cuboid's corners (M * 8, 3) local m at the same rows, the
    residual scale of each box (M, 1) px (`_BOX_SHAPE_SCALE` of its diagonal, so near and far vehicles
    count alike) and its edges on the image border (M, 4): they say nothing about the vehicle."""

    boxes: Boxes
    corners: Points3
    scale: FloatArray
    on_border: BoolArray
    # What each box-fit step needs of the E edges off the border, fixed per track: the mask (M, 4), whether
    # each is a u edge (E,), its box's scale (E,) and the index of its box's first corner (E,).
    keep: BoolArray = field(init=False, repr=False, compare=False)
    kept_is_u: BoolArray = field(init=False, repr=False, compare=False)
    kept_scale: FloatArray = field(init=False, repr=False, compare=False)
    kept_first_corner: IntArray = field(init=False, repr=False, compare=False)
    # Where each box's 4 edge values sit in the flattened (M, 16) [u | v] of its corners: the row's first
    # column (16 per row) plus `_UV_COLUMN`; (M, 4). A box's extreme corner index (0-7) is added to it.
    uv_edge_base: IntArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        rows = len(self.boxes)
        keep = ~self.on_border
        object.__setattr__(self, "uv_edge_base", 16 * np.arange(rows)[:, None] + _UV_COLUMN)
        object.__setattr__(self, "keep", keep)
        object.__setattr__(self, "kept_is_u", np.broadcast_to(_IS_U_EDGE, (rows, 4))[keep])
        object.__setattr__(self, "kept_scale", np.broadcast_to(self.scale, (rows, 4))[keep])
        first = np.broadcast_to(8 * np.arange(rows)[:, None], (rows, 4))
        object.__setattr__(self, "kept_first_corner", first[keep])

    @staticmethod
    def of(boxes: Boxes, poses: PoseArray, vehicle: VehicleProfile, camera: CameraModel) -> _BoxData:
        diagonal = np.hypot(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
        on_border = np.column_stack(
            [
                boxes[:, 0] <= 1.0,
                boxes[:, 1] <= 1.0,
                boxes[:, 2] >= camera.width - 1.0,
                boxes[:, 3] >= camera.height - 1.0,
            ]
        )
        corners = body_corners(poses, vehicle).reshape(-1, 3)
        return _BoxData(boxes, corners, _BOX_SHAPE_SCALE * diagonal[:, None], on_border)


@dataclass(frozen=True, slots=True)
class _LineFamily:
    """A straight track's line (origin, unit direction; local frame, m) and what scores a pose by the
    box shape: the boxes of up to `_MAX_SHAPE_ROWS` rows, the ground, and the mounts' rolls (rad)."""

    origin: Vec3
    direction: Vec3
    data: _BoxData
    camera: CameraModel
    ground: GroundPlaneFit
    mounts: FloatArray
    params: StraightTrackParams
    min_camera_height_m: float  # a pose with the camera lower above the ground is under the road
    basis: tuple[Vec3, Vec3]  # `_level_basis` of the ground normal

    def mount_of(self, R: FloatArray, C: FloatArray) -> IntArray:
        """Index (K,) of the mount whose window (`max_roll_deg`) holds the roll of each pose R (K, 3, 3)
        with centre C (K, 3): -1 for none, -2 for a camera under the ground."""
        up = self.ground.normal
        rolls = np.arctan2(-(R[:, 0] @ up), -(R[:, 1] @ up))
        off_mount = np.abs((rolls[:, None] - self.mounts + math.pi) % (2.0 * math.pi) - math.pi)
        mount = np.argmin(off_mount, axis=1)
        mount[off_mount[np.arange(len(R)), mount] > math.radians(self.params.max_roll_deg)] = -1
        mount[self.ground.height_of(C) < self.min_camera_height_m] = -2
        return np.asarray(mount, dtype=np.int64)

    def score(self, R: FloatArray, C: FloatArray) -> tuple[FloatArray, IntArray]:
        """Box-shape misfit (K,) of poses R (K, 3, 3), centres C (K, 3), and `mount_of` them. A camera
        under the ground (mount -2) is never a candidate and is not scored (inf): about half of a full
        turn about the line."""
        mount = self.mount_of(R, C)
        scores = np.full(len(R), np.inf)
        above = mount != -2
        if np.any(above):
            scores[above] = _box_shape_misfit(R[above], C[above], self.data, self.camera)
        return scores, mount


@dataclass(frozen=True, slots=True)
class _Member:
    """A camera pose (R_cam_from_local, centre C) with its box-shape misfit and image roll (rad)."""

    R: Rotation
    C: Vec3
    misfit: float
    roll: float
    rotation_std_deg: float = math.inf  # of a fit: 1-sigma of its worst angle (yaw, pitch, roll)


def solve_straight_track(
    points: Points3,
    line: tuple[Vec3, Vec3],
    shape: TrackShape,
    camera: CameraModel,
    ground: GroundPlaneFit,
    starts: Sequence[tuple[Rotation, Vec3]],
    params: StraightTrackParams,
    min_camera_height_m: float,
) -> StraightTrackFit | str:
    """Pose of a straight-line track from the boxes' shape and a square camera mount (not in the paper),
    with the 1-sigma (deg) of its worst fitted angle; or the reason there is none.

    Collinear points fix a camera pose only up to a rotation about their line: every member of that
    one-parameter family projects the box centres identically, so EPnP returns an arbitrary one and no
    reprojection error of the centres can choose. Two things can:
    - the box shape: the vehicle's cuboid (known size) must reproduce the boxes' extents, which turn with
      the camera about the line; near the truth this is sharp to a fraction of a degree, but a pose far
      off can come close (the camera mirrored across the road, a far car's box turned a quarter, or, for
      a road running straight away from the camera, the same view rolled the other way);
    - the mount: RSU cameras are installed upright or turned a quarter into portrait, so the image's
      roll about the ground normal is near 0 or +-90 deg (`StraightTrackParams.mount_rolls_deg`).
    A scan along the family (`_shape_candidates`) gives starts; from the best few the whole pose is fitted
    to the box edges with the roll free (`_fit_box`: edges, not centres, so the fit is not bound to the
    centres' family, which the box-centre approximation shifts by a few pixels), then again from a scan
    about the best fit. `_choose_fit` turns the fits into a mount and a roll, or rejects the track as
    off-mount or ambiguous. The roll fixes the track's pose only as far as it changes about the line,
    |sin(road, the image's level axis)|: below `min_level_sensitivity` (a road crossing an upright view
    side-on) the track is rejected too. `starts`: poses (R_cam_from_local, camera centre) of the family, at
    least one (the caller's general solvers give them, `pipeline.hypotheses`).
    """
    up = ground.normal
    origin, direction = line
    shape_rows = np.unique(
        np.linspace(0, len(points) - 1, min(len(points), _MAX_SHAPE_ROWS)).round().astype(np.int64)
    )
    family = _LineFamily(
        origin=origin,
        direction=direction,
        data=_BoxData.of(shape.boxes[shape_rows], shape.poses[shape_rows], shape.vehicle, camera),
        camera=camera,
        ground=ground,
        mounts=np.radians(np.asarray(params.mount_rolls_deg, dtype=np.float64)),
        params=params,
        min_camera_height_m=min_camera_height_m,
        basis=_level_basis(up),
    )
    scanned = _shape_candidates(family, starts)
    if not scanned:
        return "no pose of the line's family puts the camera above the ground"
    if scanned[0].misfit > params.max_box_misfit:
        # Most tracks of other vehicles end here, before any fit: the calibration vehicle's cuboid does
        # not reproduce their boxes from any pose about the line.
        return (
            f"the vehicle's cuboid misses the boxes by a misfit of {scanned[0].misfit:.1f} > "
            f"{params.max_box_misfit} from every pose about the line"
        )
    fits: list[_Member] = []
    _add_fits(family, scanned, fits, _MAX_BOX_FITS, _BOX_FIT_CANDIDATE_RATIO * scanned[0].misfit)
    ranked = _rank_fits(family, fits)
    if ranked:
        # Second round, scanned about the best fit: the first scan ran along the centres' family, which
        # the box-centre approximation shifts, so a basin can hide there (the camera mirrored across the
        # road turns a portrait mount into the other one). For a measured roll, also the mount's other
        # side, fitted first (misfit 0): a road running straight away from the camera looks alike from a
        # camera rolled either way.
        best, chosen = ranked[0]
        more = _shape_candidates(family, [(best.R, best.C)], per_window=2)
        mount = float(family.mounts[chosen])
        if abs(math.remainder(best.roll - mount, 2.0 * math.pi)) > math.radians(params.mount_snap_deg):
            _, mirrored = _level_members(best.R, best.C, origin, direction, up, 2.0 * mount - best.roll)
            more.extend(_Member(R, C, 0.0, 2.0 * mount - best.roll) for R, C in mirrored[:1])
        _add_fits(family, more, fits, len(fits) + _MAX_SECOND_FITS, math.inf)
    chosen_fit = _choose_fit(family, fits)
    if isinstance(chosen_fit, str):
        return chosen_fit
    final, mount, exact_mount = chosen_fit
    sensitivity, _ = _level_members(final.R, final.C, origin, direction, up, final.roll)
    if sensitivity < params.min_level_sensitivity:
        return (
            f"the road crosses the view side-on (sensitivity {sensitivity:.2f} < "
            f"{params.min_level_sensitivity}): a camera of roll {math.degrees(final.roll):.1f} deg does "
            "not fix it"
        )
    solver = _level_solver_name(mount) if exact_mount else "box-roll"
    return StraightTrackFit(final.R, final.C, solver, final.rotation_std_deg)


def _choose_fit(family: _LineFamily, fits: Sequence[_Member]) -> tuple[_Member, float, bool] | str:
    """The pose of a straight track from its box fits (roll free): (pose, its mount's roll rad, whether the
    pose has the mount's exact roll), or the reason there is none.

    The best fit by misfit times its mount's preference picks the mount; a fit outside every window
    that is clearly better (`mount_evidence_ratio`) means the camera is not mounted as assumed. The
    mount's exact roll is fitted and kept unless the free roll turns the camera by more than
    `mount_snap_deg` and fits clearly better (`roll_evidence_ratio`). A rival, another pose fitting
    about as well or better (`ambiguity_ratio`), leaves the choice in doubt. In another mount's window it
    puts the mount in doubt: the first mount's exact roll settles that if it is the best (what is assumed
    when the boxes cannot tell, e.g. partly hidden vehicles' boxes or far, small ones), otherwise the
    track is ambiguous. Near a window's edge (a camera rolled close to `max_roll_deg`), or in the same
    window against a measured roll, it makes the track ambiguous too. Poses far from every mount (the
    camera mirrored across the road, nearly upside down) are what the mounts exclude.
    """
    params = family.params
    ranked = _rank_fits(family, fits)
    mount_of = family.mount_of(np.stack([f.R for f in fits]), np.stack([f.C for f in fits]))
    outside = sorted((f for f, k in zip(fits, mount_of, strict=True) if k == -1), key=lambda f: f.misfit)
    if not ranked:
        if outside:
            return _off_mount_reason(outside[0], params)
        return "no fit of the boxes puts the camera above the ground"
    (best, chosen), others = ranked[0], ranked[1:]
    if outside and outside[0].misfit * params.mount_evidence_ratio < best.misfit:
        return _off_mount_reason(outside[0], params)
    mount = float(family.mounts[chosen])
    exact = _fit_box(family, best.R, best.C, mount)
    snap_rad = math.radians(params.mount_snap_deg)
    exact_mount = (
        not params.roll_from_box_shape
        or rotation_angle_rad(exact.R, best.R) <= snap_rad
        or exact.misfit <= params.roll_evidence_ratio * best.misfit
    )
    near = [
        fit
        for fit in outside
        if min(abs(math.remainder(fit.roll - m, 2.0 * math.pi)) for m in family.mounts)
        <= 2.0 * math.radians(params.max_roll_deg)
    ]
    rivals = [
        (other, k)
        for other, k in [*others, *((fit, -1) for fit in near)]
        if other.misfit <= params.ambiguity_ratio * best.misfit
        and rotation_angle_rad(other.R, best.R) > snap_rad
    ]
    if chosen == 0 and any(k > 0 for _, k in rivals):
        exact_mount = True  # the first mount's exact roll, as assumed when the boxes cannot tell
    for other, k in rivals:
        if (k == chosen and not exact_mount) or k == -1 or (k != chosen and chosen != 0):
            return (
                f"ambiguous: the boxes fit about as well with a roll of {math.degrees(best.roll):.1f} and "
                f"{math.degrees(other.roll):.1f} deg"
            )
    final = exact if exact_mount else best
    if family.mount_of(final.R[None], final.C[None])[0] < 0:
        return f"the fit of roll {math.degrees(final.roll):.1f} deg puts the camera under the ground"
    return final, mount, exact_mount


def _off_mount_reason(fit: _Member, params: StraightTrackParams) -> str:
    return (
        f"the boxes' shape puts the camera's roll at {math.degrees(fit.roll):.1f} deg, not within "
        f"{params.max_roll_deg} deg of {list(params.mount_rolls_deg)} deg"
    )


def _add_fits(
    family: _LineFamily, starts: Sequence[_Member], fits: list[_Member], limit: int, max_misfit: float
) -> None:
    """Box fits (`_fit_box`, roll free) from `starts`, best first, into `fits` until it holds `limit`;
    a start whose scanned misfit exceeds `max_misfit`, or within a few degrees of a fit or a start
    already taken (it would end in the same fit), is skipped."""
    taken: list[Rotation] = [fit.R for fit in fits]
    for start in sorted(starts, key=lambda member: member.misfit):
        if len(fits) >= limit:
            return
        if start.misfit > max_misfit or any(
            rotation_angle_rad(start.R, R) <= _DISTINCT_START_RAD for R in taken
        ):
            continue
        taken.append(start.R)
        fits.append(_fit_box(family, start.R, start.C, None))


def _rank_fits(family: _LineFamily, fits: Sequence[_Member]) -> list[tuple[_Member, int]]:
    """The fits within a mount's window, with that mount's index, best first by misfit times the mount's
    preference (1 for the first mount, `mount_evidence_ratio` for the others)."""
    if not fits:
        return []
    mount_of = family.mount_of(np.stack([f.R for f in fits]), np.stack([f.C for f in fits]))
    ranked = [(fit, int(k)) for fit, k in zip(fits, mount_of, strict=True) if k >= 0]
    ratio = family.params.mount_evidence_ratio
    return sorted(ranked, key=lambda item: item[0].misfit * (1.0 if item[1] == 0 else ratio))


def _shape_candidates(
    family: _LineFamily,
    bases: Sequence[tuple[Rotation, Vec3]],
    windows: Sequence[int] | None = None,
    per_window: int = 1,
) -> list[_Member]:
    """Starts for the box fit, best box shape first: along the family through each base (R_cam_from_local,
    camera centre), the `per_window` best local minima within each mount's window (only `windows`, if
    given) and the best outside every window, each refined on a fine grid; none with the camera under the
    ground. An outside member is kept only if it beats every window's: only then can its fit show that
    the camera is not mounted as assumed."""
    up = family.ground.normal
    coarse = np.arange(-math.pi, math.pi, _FAMILY_COARSE_STEP, dtype=np.float64)
    inside: list[_Member] = []
    outside: list[_Member] = []
    searched = range(-1, len(family.mounts)) if windows is None else windows
    for R0, C0 in bases:
        scores, mount_of = family.score(*_family_poses(R0, C0, family.origin, family.direction, coarse))
        for k in searched:
            for index in _local_minima(np.where(mount_of == k, scores, np.inf))[: 1 if k < 0 else per_window]:
                fine = coarse[index] + np.arange(-8.0, 9.0) * _FAMILY_FINE_STEP
                R_fine, C_fine = _family_poses(R0, C0, family.origin, family.direction, fine)
                fine_scores, fine_mount = family.score(R_fine, C_fine)
                fine_scores = np.where(fine_mount == k, fine_scores, np.inf)
                best = int(np.argmin(fine_scores))
                R, C, misfit = R_fine[best], C_fine[best], float(fine_scores[best])
                if math.isfinite(misfit):
                    (outside if k < 0 else inside).append(_Member(R, C, misfit, _image_roll(R, up)))
    best_inside = min((member.misfit for member in inside), default=math.inf)
    found = inside + [member for member in outside if member.misfit < best_inside][:1]
    return sorted(found, key=lambda member: member.misfit)


def _local_minima(values: FloatArray) -> IntArray:
    """Indices of the finite local minima of a circular sequence (K,), lowest first."""
    finite = np.isfinite(values)
    is_minimum = finite & (values <= np.roll(values, 1)) & (values <= np.roll(values, -1))
    indices = np.flatnonzero(is_minimum)
    return np.asarray(indices[np.argsort(values[indices], kind="stable")], dtype=np.int64)


def _fit_box(family: _LineFamily, R_start: Rotation, C_start: Vec3, roll: float | None) -> _Member:
    """Robust fit of the camera pose to the track's box edges (the vehicle cuboid's tight boxes), from a
    start: yaw, pitch, roll and centre (6 dof), or with the roll fixed at `roll` (rad; 5 dof).

    Levenberg-Marquardt on the soft-L1 cost, reweighted each step (IRLS), with the analytic Jacobian of
    `_BoxFitPoint`: it runs a few hundred times per camera, on most of the hypotheses stage's time.
    """
    up = family.ground.normal
    yaw, pitch = _level_angles(R_start, up)
    free = roll is None
    start = np.array([yaw, pitch, _image_roll(R_start, up) if roll is None else roll, *C_start])
    used = np.arange(6) if free else np.array([0, 1, 3, 4, 5])
    settled_steps = _BOX_FIT_SETTLED_STEPS[used]

    def evaluate(x: FloatArray) -> _BoxFitPoint:
        xs = start.copy()
        xs[used] = x
        return _BoxFitPoint.at(xs, family)

    def soft_l1(values: FloatArray) -> float:
        return float(np.sum(np.sqrt(1.0 + values**2) - 1.0))

    x = start[used].copy()
    point = evaluate(x)
    residual, J = point.values, point.jacobian(family)[:, used]
    cost = soft_l1(residual)
    damping = 1e-3
    for _ in range(_BOX_FIT_ITERATIONS):
        weights = 1.0 / np.sqrt(1.0 + residual**2)  # soft-L1 as iteratively reweighted least squares
        normal = J.T @ (weights[:, None] * J)
        try:
            step = np.linalg.solve(normal + damping * np.diag(np.diag(normal)), -J.T @ (weights * residual))
        except np.linalg.LinAlgError:
            break
        trial = evaluate(x + step)
        trial_cost = soft_l1(trial.values)
        if not trial_cost < cost:
            damping *= 10.0
            if damping > 1e6:
                break
            continue
        # Settled: the cost barely moves, or the step is negligible.
        settled = cost - trial_cost <= 1e-6 * cost or bool(np.all(np.abs(step) < settled_steps))
        x = x + step
        damping = max(damping * 0.3, 1e-7)
        residual, J, cost = trial.values, trial.jacobian(family)[:, used], trial_cost
        if settled:
            break
    params = start.copy()
    params[used] = x
    R = _level_rotation(float(params[0]), float(params[1]), up, float(params[2]))
    misfit = float(_box_shape_misfit(R[None], params[None, 3:6], family.data, family.camera)[0])
    # Gauss-Newton covariance of the fitted angles at the robust residual scale (at least 1 % of the box
    # diagonal: noise-free boxes still have a cuboid that is only a model of the vehicle).
    weights = 1.0 / np.sqrt(1.0 + residual**2)
    normal = J.T @ (weights[:, None] * J)
    sigma2 = max(2.0 * cost / max(len(residual), 1), 0.5**2)
    singular = np.linalg.svd(normal, compute_uv=False)
    rotation_std_deg = math.inf
    if np.all(np.isfinite(singular)) and singular[-1] > singular[0] * 1e-14:
        variances = sigma2 * np.diag(np.linalg.inv(normal))[: 3 if free else 2]
        rotation_std_deg = math.degrees(math.sqrt(max(float(np.max(variances)), 0.0)))
    return _Member(R, params[3:6].copy(), misfit, _image_roll(R, up), rotation_std_deg)


def _box_fit_linearised(
    x: FloatArray, family: _LineFamily, *, jacobian: bool
) -> tuple[FloatArray, FloatArray]:
    """The box fit's residuals at one pose x (6,) = (yaw, pitch, roll, centre xyz; `_level_rotations`):
    the scaled edge residuals of `_box_residuals` on the E edges off the image border, (E,); and with
    `jacobian` their analytic Jacobian (E, 6) (else (E, 0)). See `_BoxFitPoint`."""
    point = _BoxFitPoint.at(x, family)
    return point.values, point.jacobian(family) if jacobian else np.zeros((len(point.values), 0))


@dataclass(frozen=True, slots=True)
class _BoxFitPoint:
    """The box fit at one pose x (6,) = (yaw, pitch, roll, centre xyz; `_level_rotations`): its residuals
    (E,), the scaled edge residuals of `_box_residuals` on the E edges off the image border, and what
    their analytic Jacobian needs. A pose with a corner behind the camera has residuals 1e3 and a zero
    Jacobian.

    A box edge is its extreme projected cuboid corner's coordinate, so its derivative is that corner's:
    the rotation's from `_level_rotations` differentiated by hand, the camera centre's -R, through the
    division by depth, the OpenCV distortion and K. Where two corners tie for an edge the derivative is
    one-sided, as a finite difference's is. Only the E extreme corners are differentiated, and only
    when a step is taken: a trial step that fails needs the residuals alone.
    """

    x: FloatArray
    values: FloatArray
    in_front: bool
    corner: IntArray  # (E,) index of each edge's extreme corner in `_BoxData.corners`
    is_u: BoolArray  # (E,) whether the edge is a u (x1, x2) or a v (y1, y2) edge
    scale: FloatArray  # (E,) the residual scale of each edge's box

    @staticmethod
    def at(x: FloatArray, family: _LineFamily) -> _BoxFitPoint:
        data, camera = family.data, family.camera
        keep = data.keep
        R, _ = _box_fit_rotation(x, family, derivatives=False)
        points_cam = (data.corners - x[3:6]) @ R.T
        depth = points_cam[:, 2]
        if not (depth > 1e-6).all():
            edges = len(data.kept_scale)
            empty = np.zeros(0, dtype=np.int64)
            return _BoxFitPoint(x, np.full(edges, 1e3), False, empty, np.zeros(0, dtype=bool), np.zeros(0))
        xn, yn = within_model(points_cam[:, 0] / depth, points_cam[:, 1] / depth, camera.undistorted_limit)
        if camera.has_distortion:
            xn, yn = distort_xy(xn, yn, camera.dist)
        K = camera.K
        rows = len(data.boxes)
        # [u | v] of each box's 8 corners, (M, 16); the extreme corner of each edge picked by flat index.
        uv = np.empty((rows, 16))
        uv[:, :8] = (K[0, 0] * xn + K[0, 1] * yn + K[0, 2]).reshape(rows, 8)
        uv[:, 8:] = (K[1, 1] * yn + K[1, 2]).reshape(rows, 8)
        u, v = uv[:, :8], uv[:, 8:]
        extremes = np.stack([u.argmin(axis=1), v.argmin(axis=1), u.argmax(axis=1), v.argmax(axis=1)], axis=1)
        model = uv.ravel()[extremes + data.uv_edge_base]
        values = ((model - data.boxes) / data.scale)[keep]
        corner = data.kept_first_corner + extremes[keep]
        return _BoxFitPoint(x, values, True, corner, data.kept_is_u, data.kept_scale)

    def jacobian(self, family: _LineFamily) -> FloatArray:
        """d values / d x (E, 6)."""
        if not self.in_front:
            return np.zeros((len(self.values), 6))
        camera, x = family.camera, self.x
        R, dR = _box_fit_rotation(x, family, derivatives=True)
        offsets = family.data.corners[self.corner] - x[3:6]  # (E, 3) corner minus camera centre
        points_cam = offsets @ R.T
        d_cam = np.empty((len(offsets), 3, 6))  # d points_cam / d x
        # "ajk,nk->nja" contracted in the order einsum runs fast and transposed: the same values, bit for bit.
        d_cam[:, :, :3] = np.einsum("ajk,nk->naj", dR, offsets).transpose(0, 2, 1)
        d_cam[:, :, 3:] = -R
        inv_depth = 1.0 / points_cam[:, 2]
        xn, yn = points_cam[:, 0] * inv_depth, points_cam[:, 1] * inv_depth
        dx = (d_cam[:, 0] - xn[:, None] * d_cam[:, 2]) * inv_depth[:, None]
        dy = (d_cam[:, 1] - yn[:, None] * d_cam[:, 2]) * inv_depth[:, None]
        dx, dy = distortion_chain(xn, yn, dx, dy, camera)
        K = camera.K
        d_edge = np.where(self.is_u[:, None], K[0, 0] * dx + K[0, 1] * dy, K[1, 1] * dy)
        return np.asarray(d_edge / self.scale[:, None], dtype=np.float64)


def _box_fit_rotation(
    x: FloatArray, family: _LineFamily, *, derivatives: bool
) -> tuple[Rotation, FloatArray]:
    """R_cam_from_local of the box fit's pose x (`_level_rotations` for one pose, written out for one in
    Python floats, the same operations in the same order: it runs at every step of every fit) and, with
    `derivatives`, dR/d(yaw, pitch, roll) (3, 3, 3), else an empty array."""
    up = family.ground.normal.tolist()
    east, north = family.basis[0].tolist(), family.basis[1].tolist()
    c, s = math.cos(float(x[0])), math.sin(float(x[0]))
    cp, sp = math.cos(float(x[1])), math.sin(float(x[1]))
    cr, sr = math.cos(float(x[2])), math.sin(float(x[2]))
    horizontal = [c * e + s * n for e, n in zip(east, north, strict=True)]
    right0 = [s * e - c * n for e, n in zip(east, north, strict=True)]  # d horizontal / d yaw = -right0
    down0 = [-sp * h - cp * u for h, u in zip(horizontal, up, strict=True)]
    forward = [cp * h - sp * u for h, u in zip(horizontal, up, strict=True)]
    right = [cr * r + sr * d for r, d in zip(right0, down0, strict=True)]
    down = [-sr * r + cr * d for r, d in zip(right0, down0, strict=True)]
    R = np.array([right, down, forward])
    if not derivatives:
        return R, np.zeros(0)
    down0_pitch = [-cp * h + sp * u for h, u in zip(horizontal, up, strict=True)]  # d down0 / d pitch
    srsp, crsp = sr * sp, cr * sp
    dR = np.array(
        [
            [
                [cr * h + srsp * r for h, r in zip(horizontal, right0, strict=True)],
                [-sr * h + crsp * r for h, r in zip(horizontal, right0, strict=True)],
                [-cp * r for r in right0],
            ],
            [[sr * d for d in down0_pitch], [cr * d for d in down0_pitch], down0],
            [down, [-r for r in right], [0.0, 0.0, 0.0]],
        ]
    )
    return R, dR


def _box_residuals(
    R: FloatArray, C: FloatArray, data: _BoxData, camera: CameraModel
) -> tuple[FloatArray, BoolArray]:
    """Tight box of the projected cuboid minus the box, for K poses R (K, 3, 3), centres C (K, 3):
    (K, M, 4) in units of each box's scale; and (K,) whether every corner is in front of the camera.

    The projection of `project_points_cam`, written out for K poses at once: it runs in the inner loop of
    every box fit.
    """
    count, rows = len(R), len(data.boxes)
    points_cam = np.matmul(data.corners, R.transpose(0, 2, 1)) - np.matmul(R, C[:, :, None])[:, None, :, 0]
    depth = points_cam[..., 2]
    is_ahead = depth > 1e-6
    in_front = np.all(is_ahead, axis=1)
    safe_depth = np.where(is_ahead, depth, 1.0)
    xn, yn = within_model(
        points_cam[..., 0] / safe_depth, points_cam[..., 1] / safe_depth, camera.undistorted_limit
    )
    if camera.has_distortion:
        xn, yn = distort_xy(xn, yn, camera.dist)
    K = camera.K
    u = (K[0, 0] * xn + K[0, 1] * yn + K[0, 2]).reshape(count, rows, 8)
    v = (K[1, 1] * yn + K[1, 2]).reshape(count, rows, 8)
    model = np.stack([u.min(axis=2), v.min(axis=2), u.max(axis=2), v.max(axis=2)], axis=2)
    return (model - data.boxes) / data.scale, in_front


def _box_shape_misfit(R: FloatArray, C: FloatArray, data: _BoxData, camera: CameraModel) -> FloatArray:
    """How badly K poses reproduce the boxes: (K,), the mean soft-L1 cost of the scaled edge residuals of
    `_box_residuals` off the image border, each capped at `_BOX_EDGE_MAX_COST`; inf for a pose with a
    corner behind the camera.

    A capped mean, not a median: the mean locates the best rotation about a line 2-3 times more precisely
    (0.2-0.5 deg against 0.5-2 deg on the rolled preset), the cap keeps a wrong box (another vehicle's,
    an occluded one) from counting more than a clear miss.
    """
    residual, in_front = _box_residuals(R, C, data, camera)
    used = int(np.count_nonzero(~data.on_border))
    if used == 0:
        return np.full(len(R), np.inf)
    edge_cost = np.minimum(np.sqrt(1.0 + residual**2) - 1.0, _BOX_EDGE_MAX_COST)
    cost = np.sum(np.where(data.on_border, 0.0, edge_cost), axis=(1, 2)) / used
    return np.asarray(np.where(in_front, cost, np.inf), dtype=np.float64)


def _level_solver_name(roll: float) -> str:
    """'level' for an upright image, 'level+90' / 'level-90' / 'level+180' for the quarter turns."""
    degrees = round(math.degrees(roll))
    return "level" if degrees == 0 else f"level{degrees:+d}"


def _image_roll(R: Rotation, up: Vec3) -> float:
    """Roll (rad) of a camera about its optical axis relative to `up`, as `camera_rotation_from_view`
    defines it: 0 with the image x axis level and y pointing down, +90 deg with x pointing down."""
    return math.atan2(-float(R[0] @ up), -float(R[1] @ up))


def _family_poses(
    R0: Rotation, C0: Vec3, origin: Vec3, direction: Vec3, angles: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Members of the pose family about the line (origin, direction) through (R0, C0): the camera turned
    by `angles` (K,) rad about the line. Returns R_cam_from_local (K, 3, 3) and camera centres (K, 3)."""
    d = direction
    cross = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    c, s = np.cos(angles)[:, None, None], np.sin(angles)[:, None, None]
    turns = c * np.eye(3) + s * cross + (1.0 - c) * np.outer(d, d)  # Rodrigues
    R = np.einsum("ab,kcb->kac", R0, turns)  # R0 @ turn^T
    C = origin + np.einsum("kab,b->ka", turns, C0 - origin)
    return R, C


def _level_members(
    R: Rotation, centre: Vec3, origin: Vec3, direction: Vec3, up: Vec3, roll: float
) -> tuple[float, list[tuple[Rotation, Vec3]]]:
    """Members of the pose family about the line (origin, direction) through the pose (R, centre) whose
    image is rolled by `roll` (rad) about the ground normal `up`: (sensitivity, [(R_cam_from_local,
    camera centre)]).

    Roll rho makes a = cos(rho) x - sin(rho) y level (x, y the image axes) and b = sin(rho) x + cos(rho) y
    point down. Rotating the camera by phi about the line turns a into Rot(phi) a; a . up = 0 then reads
    A cos(phi) + B sin(phi) + C = 0 (Rodrigues), solvable for two angles, of which the one with b down is
    kept; sqrt(A^2 + B^2) is the sensitivity of the roll to phi, the same for every member of the family.
    """
    cos_roll, sin_roll = math.cos(roll), math.sin(roll)
    a = cos_roll * R[0] - sin_roll * R[1]
    along = float(direction @ a)
    A = float(a @ up) - along * float(direction @ up)
    B = float(np.cross(direction, a) @ up)
    C = along * float(direction @ up)
    sensitivity = math.hypot(A, B)
    if sensitivity < 1e-12 or abs(C) > sensitivity:
        return sensitivity, []
    base_angle, half_width = math.atan2(B, A), math.acos(-C / sensitivity)
    members: list[tuple[Rotation, Vec3]] = []
    for angle in (base_angle + half_width, base_angle - half_width):
        turn = rotation_from_rvec(direction * angle)
        R_member = R @ turn.T
        if (sin_roll * R_member[0] + cos_roll * R_member[1]) @ up < 0.0:  # the image's down is world down
            members.append((R_member, origin + turn @ (centre - origin)))
    return sensitivity, members


def _level_basis(up: Vec3) -> tuple[Vec3, Vec3]:
    """Right-handed (east, north) perpendicular to `up`, east the local x axis projected."""
    east = np.array([1.0, 0.0, 0.0]) - up[0] * up
    east /= np.linalg.norm(east)
    return east, np.cross(up, east)


def _level_rotations(
    yaw: FloatArray,
    pitch: FloatArray,
    up: Vec3,
    roll: float | FloatArray = 0.0,
    basis: tuple[Vec3, Vec3] | None = None,
) -> FloatArray:
    """R_cam_from_local (K, 3, 3) of cameras looking at azimuths `yaw` (K,) rad (from east, about up),
    tilted `pitch` (K,) rad down and rolled `roll` (scalar or (K,)) rad about the optical axis
    (`camera_rotation_from_view`'s convention; roll 0: the x axis perpendicular to `up`). `basis`:
    `_level_basis(up)` if already at hand.

    With h = cos(yaw) east + sin(yaw) north: right = h x up, forward = cos(pitch) h - sin(pitch) up,
    down = forward x right, written out (np.cross costs more than the rest of a fit here); the roll turns
    right and down into cos right + sin down and -sin right + cos down.
    """
    east, north = basis if basis is not None else _level_basis(up)
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    cp, sp = np.cos(pitch)[:, None], np.sin(pitch)[:, None]
    horizontal = c * east + s * north
    right = s * east - c * north
    down = -sp * horizontal - cp * up
    forward = cp * horizontal - sp * up
    if np.any(roll):
        rolls = np.broadcast_to(np.asarray(roll, dtype=np.float64), yaw.shape)[:, None]
        cos_roll, sin_roll = np.cos(rolls), np.sin(rolls)
        right, down = cos_roll * right + sin_roll * down, -sin_roll * right + cos_roll * down
    return np.stack([right, down, forward], axis=1)


def _level_rotation(yaw: float, pitch: float, up: Vec3, roll: float = 0.0) -> Rotation:
    """One rotation of `_level_rotations`."""
    return np.asarray(_level_rotations(np.array([yaw]), np.array([pitch]), up, roll)[0], dtype=np.float64)


def _level_angles(R: Rotation, up: Vec3) -> tuple[float, float]:
    """(yaw, pitch) of `_level_rotations` for the optical axis of R (whatever its roll)."""
    east, north = _level_basis(up)
    forward = R[2]
    yaw = math.atan2(float(forward @ north), float(forward @ east))
    return yaw, -math.asin(float(np.clip(forward @ up, -1.0, 1.0)))


def pose_box_misfit(R: Rotation, C: Vec3, shape: TrackShape, camera: CameraModel) -> float:
    """How badly the pose (R_cam_from_local, camera centre C) reproduces the track's boxes: the
    `_box_shape_misfit` over up to `_MAX_SHAPE_ROWS` rows of the track."""
    rows = np.unique(
        np.linspace(0, len(shape.boxes) - 1, min(len(shape.boxes), _MAX_SHAPE_ROWS)).round().astype(np.int64)
    )
    data = _BoxData.of(shape.boxes[rows], shape.poses[rows], shape.vehicle, camera)
    return float(_box_shape_misfit(R[None], C[None], data, camera)[0])
