"""Hypotheses from straight tracks solved together (not in the paper): for scenes where every drive-past
the camera saw was a straight line.

A straight track fixes the camera pose only up to a rotation about its line (pipeline.straight_track), and
the straight-track solver picks the member from the boxes' shape and a square-mount assumption. Where the
camera is rolled off its mount or the vehicle's body is not its cuboid, that pick can be degrees off, and
no two single-track hypotheses agree (the `rolled` preset in the realistic world: 10 of 10 refused so).
Drive-pasts along lines that are not parallel fix the pose by geometry alone: their points span the road
plane, and PnP on their union needs neither the box shape nor the mount.

So, when grouping finds nothing, the tracks whose own pose their line left unfixed are paired (separate
drive-pasts: never two tracks seen within `min_gap_s` of each other) and each pair is solved as one track,
with one camera and one clock shift for both: an unknown latency s puts each track's points v s along its
own line, which two lines in different directions cannot both absorb. One pair is no evidence: the
rotation about a straight track is free, so a true track paired with another vehicle's can fit both
(rolled seed 5: 5.9 m / 11 deg off, with a lower box error than the truth's tracks). A pose counts only
when a third drive-past corroborates it: a track more than `min_gap_s` from both that the pair's pose
explains, the three solved as one fitting every track. Those unions become groups for refinement, and the
final fit and its gates judge them like any other.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from pipeline.arrays import FloatArray, IntArray, Mask, Pixels, Points3, Rotation, Vec3
from pipeline.association import MatchedTrack, Trajectory
from pipeline.camera import CameraModel, camera_centre, rotation_from_rvec, rvec_from_rotation
from pipeline.clock import ClockParams, track_velocity
from pipeline.ground import GroundPlaneFit
from pipeline.hypotheses import (
    Hypothesis,
    HypothesisParams,
    _append_finite,
    _driven_path,
    _DrivenPath,
    _path_xy,
    _Pose,
    _refits,
    _reprojection_errors,
    _reprojection_reason,
    _rotation_std_deg,
    placement_reason,
)
from pipeline.stage import Reason, StageReport, count_reasons
from pipeline.straight_track import track_line
from pipeline.vehicle import body_centres
from pipeline.vehicle_model import TRAVERSAL_GAP_S
from schemas.common import VehicleProfile

# The single-track rejections that mean "the line left the pose unfixed".
STRAIGHT_CODES = frozenset({"straight_line", "rotation_not_fixed"})


@dataclass(frozen=True, slots=True)
class PairParams:
    # Two lines closer to parallel than this (deg) leave the rotation about them nearly unfixed.
    min_angle_deg: float = 20.0
    # At most this many tracks take part (the longest along their line): pairs grow as its square.
    max_tracks: int = 40
    # Separate drive-pasts: tracks this far apart in time (s), as the final fit's leave-one-out check
    # tells them apart (vehicle_model.TRAVERSAL_GAP_S).
    min_gap_s: float = TRAVERSAL_GAP_S
    # Trial clocks (s) each pair is first solved on, out to the clock scan's reach (clock.ClockParams); the
    # best is then refined with the pose (at 10 m/s, 0.1 s off is 1 m along each line: the pose lands near).
    scan_step_s: float = 0.2
    # Rows of each track the pose is solved from (evenly spread along it), and the trial clocks scored on.
    rows_per_track: int = 60
    scan_rows_per_track: int = 20


@dataclass(frozen=True, slots=True)
class JointFit:
    """Tracks of separate drive-pasts solved as one: one camera pose and one clock shift (s: the boxes
    show the vehicle where the assumed clock puts it s later) for all; each track's median reprojection
    error (px) and inliers (rows within the RANSAC threshold)."""

    tracks: tuple[MatchedTrack, ...]
    R: Rotation
    t: Vec3
    shift_s: float
    medians_px: tuple[float, ...]
    inliers: tuple[Mask, ...]
    rotation_std_deg: float
    solver: str

    @property
    def track_ids(self) -> tuple[int, ...]:
        return tuple(t.track_id for t in self.tracks)

    def hypotheses(self) -> tuple[Hypothesis, ...]:
        """The pose as a hypothesis of each track (refinement's starts)."""
        return tuple(
            Hypothesis(track.track_id, self.R, self.t, inliers, median, self.rotation_std_deg, self.solver)
            for track, inliers, median in zip(self.tracks, self.inliers, self.medians_px, strict=True)
        )

    def describe(self) -> str:
        return f"tracks {list(self.track_ids)} fit as one (clock {self.shift_s * 1e3:+.0f} ms)"


def straight_tracks(
    tracks: Sequence[MatchedTrack], rejected: Mapping[int, Reason], hypotheses: Sequence[Hypothesis]
) -> list[MatchedTrack]:
    """The tracks whose own pose their line left unfixed: rejected for it, or fitted by the straight-track
    solver (whose pick may be the one that is off)."""
    solved = {h.track_id for h in hypotheses if not h.solver.startswith(("epnp", "sqpnp"))}
    return [
        t
        for t in tracks
        if t.track_id in solved or (t.track_id in rejected and rejected[t.track_id].code in STRAIGHT_CODES)
    ]


def corroborated_pairs(
    tracks: Sequence[MatchedTrack],
    others: Sequence[MatchedTrack],
    camera: CameraModel,
    vehicle: VehicleProfile,
    ground: GroundPlaneFit,
    trajectory: Trajectory,
    params: HypothesisParams,
    pairs: PairParams,
    clock: ClockParams,
) -> tuple[list[JointFit], StageReport]:
    """Every pair of `tracks` from separate drive-pasts whose lines cross at `min_angle_deg` or more, solved
    as one; then each pair with every track of `others` from a third drive-past that the pair's pose
    explains, solved as one again. The unions that fit (each track within the single-track tests of
    pipeline.hypotheses), with a report."""
    solver = _Solver(
        camera, vehicle, ground, _driven_path(_path_xy(tracks, trajectory)), params, pairs, clock
    )
    lines = []
    for track in tracks:
        points = body_centres(track.poses, vehicle)
        _origin, direction = track_line(points)
        horizontal = direction[:2] / max(float(np.linalg.norm(direction[:2])), 1e-12)
        lines.append((float(np.ptp(points[:, :2] @ horizontal)), track, horizontal))
    lines.sort(key=lambda line: -line[0])
    lines = lines[: pairs.max_tracks]
    min_sin = math.sin(math.radians(pairs.min_angle_deg))
    found: list[JointFit] = []
    rejected: list[Reason] = []
    tried = 0
    for i, (_, track_a, dir_a) in enumerate(lines):
        for _, track_b, dir_b in lines[i + 1 :]:
            if not _apart(track_a, track_b, pairs.min_gap_s):
                continue
            if abs(float(dir_a[0] * dir_b[1] - dir_a[1] * dir_b[0])) < min_sin:
                continue
            tried += 1
            pair = solver.solve((track_a, track_b))
            if isinstance(pair, JointFit):
                found.append(pair)
            else:
                rejected.append(pair)
    unions: dict[tuple[int, ...], JointFit] = {}
    corroborated: set[tuple[int, ...]] = set()
    for pair in found:
        for third in others:
            if third.track_id in pair.track_ids or not all(
                _apart(third, t, pairs.min_gap_s) for t in pair.tracks
            ):
                continue
            if not solver.explains(pair, third):
                continue
            ordered = sorted((*pair.tracks, third), key=lambda t: t.track_id)
            key = tuple(t.track_id for t in ordered)
            if key in unions:
                continue
            union = solver.solve(ordered, pair)
            if isinstance(union, JointFit):
                unions[key] = union
                corroborated.add(pair.track_ids)
    notes = [
        f"{len(tracks)} straight tracks, {tried} pairs across non-parallel lines tried, "
        f"{len(found)} fit as one",
        *(f"pair: {p.describe()}" for p in found),
        *(f"corroborated: {u.describe()}" for u in unions.values()),
    ]
    if found and not unions:
        notes.append("no pair is corroborated by a third drive-past")
    # Kept: the corroborated unions; discarded: every pair tried that is in none, each with its reason.
    uncorroborated = Reason("pair_uncorroborated", "fits as one, but no third drive-past fits its pose")
    rejected.extend(uncorroborated for p in found if p.track_ids not in corroborated)
    report = StageReport("straight pairs", len(unions), len(rejected), tuple(notes), count_reasons(rejected))
    return list(unions.values()), report


def _apart(a: MatchedTrack, b: MatchedTrack, gap_s: float) -> bool:
    """Separate drive-pasts: more than `gap_s` between the two tracks."""
    gap_ns = max(int(b.stamps[0]) - int(a.stamps[-1]), int(a.stamps[0]) - int(b.stamps[-1]))
    return gap_ns > gap_s * 1e9


@dataclass(frozen=True, slots=True)
class _Solver:
    """The joint solve of some tracks, with what every solve shares."""

    camera: CameraModel
    vehicle: VehicleProfile
    ground: GroundPlaneFit
    path: _DrivenPath
    params: HypothesisParams
    pairs: PairParams
    clock: ClockParams

    def solve(self, tracks: Sequence[MatchedTrack], start: JointFit | None = None) -> JointFit | Reason:
        """One pose and clock for `tracks` (from `start`'s, else searched over trial clocks), or why there
        is none.

        RANSAC over the union would find the longest track's line alone (any member of its family is a
        consensus), so the pose is solved from as many rows of each track, evenly spread, and every track
        must fit on its own (median reprojection error).
        """
        camera, params = self.camera, self.params
        sizes = [len(t.stamps) for t in tracks]
        base = np.vstack([body_centres(t.poses, self.vehicle) for t in tracks])
        velocity = np.vstack([np.repeat(track_velocity(t)[None], len(t.stamps), axis=0) for t in tracks])
        pixels = np.vstack([t.box_centres for t in tracks])
        reach_s = self.clock.max_shift_s
        rows = _balanced_rows(sizes, self.pairs.rows_per_track)
        if start is None:
            shift_s, score = self._scan(base, velocity, pixels, sizes, reach_s)
            if not score <= 2.0 * params.max_median_reproj_px:
                return Reason(
                    "pair_scan_misfit",
                    "median reprojection error {value} px > {limit} px on every trial clock",
                    "worst track's median reprojection error",
                    score,
                    2.0 * params.max_median_reproj_px,
                    "px",
                )
            found = self._best_start(base[rows] - velocity[rows] * shift_s, pixels[rows], len(tracks))
            if found is None:
                return Reason("pair_no_pose", "no PnP pose from the tracks' rows")
            solved = found
        else:
            shift_s = start.shift_s
            solved = _Pose(rvec_from_rotation(start.R), start.t.copy(), start.solver)
        joint = _with_clock(
            base[rows], velocity[rows], pixels[rows], solved, shift_s, reach_s, camera, params
        )
        if joint is not None:
            solved, shift_s = joint
        if abs(shift_s) >= reach_s - 1e-6:
            # Pinned to the edge of the search: no clock within it explains the tracks together.
            return Reason(
                "pair_clock_at_edge",
                "clock shift {value} ms at the edge of the search (+-{limit} ms)",
                "clock shift",
                shift_s * 1e3,
                reach_s * 1e3,
                "ms",
                ".0f",
            )
        points = base - velocity * shift_s
        errors = _reprojection_errors(points, pixels, solved.rvec, solved.tvec, camera)
        parts = np.split(errors, np.cumsum(sizes)[:-1])
        medians = tuple(float(np.median(part)) for part in parts)
        if not max(medians) <= params.max_median_reproj_px:
            return _reprojection_reason(max(medians), params)  # the worst track's
        inliers = errors <= params.reproj_threshold_px
        rotation_std_deg = _rotation_std_deg(points[inliers], pixels[inliers], solved, camera)
        if not rotation_std_deg <= params.max_rotation_std_deg:
            return Reason(
                "pair_rotation_not_fixed",
                "rotation 1-sigma {value} deg > {limit} deg",
                "rotation 1-sigma",
                rotation_std_deg,
                params.max_rotation_std_deg,
                "deg",
            )
        R = rotation_from_rvec(solved.rvec)
        t = solved.tvec.reshape(3).copy()
        centre = camera_centre(R, t)
        misplaced = placement_reason(centre, self.path, self.ground, params)
        if misplaced is not None:
            return misplaced
        return JointFit(
            tuple(tracks),
            R,
            t,
            shift_s,
            medians,
            tuple(np.split(inliers, np.cumsum(sizes)[:-1])),
            rotation_std_deg,
            f"straight-pair:{solved.solver}",
        )

    def explains(self, fit: JointFit, track: MatchedTrack) -> bool:
        """Whether `fit`'s pose and clock put the vehicle's body centre near `track`'s boxes: median
        reprojection error within twice the single-track limit (a quick test before a joint solve)."""
        if len(track.stamps) < self.params.min_correspondences:
            return False
        points = body_centres(track.poses, self.vehicle) - track_velocity(track) * fit.shift_s
        errors = _reprojection_errors(
            points, track.box_centres, rvec_from_rotation(fit.R), fit.t, self.camera
        )
        return bool(np.median(errors) <= 2.0 * self.params.max_median_reproj_px)

    def _scan(
        self, base: Points3, velocity: FloatArray, pixels: Pixels, sizes: Sequence[int], reach_s: float
    ) -> tuple[float, float]:
        """The trial clock (s, `scan_step_s` apart within +-reach_s) on which SQPnP from a few rows of each
        track fits the worst track best (SQPnP: 0.05 ms a solve), and that track's median error (px)."""
        steps = math.floor(reach_s / self.pairs.scan_step_s + 1e-9)
        rows = _balanced_rows(sizes, self.pairs.scan_rows_per_track)
        best_shift, best_score = 0.0, math.inf
        for shift_s in self.pairs.scan_step_s * np.arange(-steps, steps + 1):
            moved = base[rows] - velocity[rows] * shift_s
            pose = _sqpnp(moved, pixels[rows], self.camera)
            if pose is None:
                continue
            score = _worst_median(_errors(moved, pixels[rows], pose, self.camera), len(sizes))
            if score < best_score:
                best_shift, best_score = float(shift_s), score
        return best_shift, best_score

    def _best_start(self, points: Points3, pixels: Pixels, tracks: int) -> _Pose | None:
        """EPnP, then LM from it, SQPnP and LM from that (hypotheses._refits) on balanced rows of `tracks`
        tracks; the one whose worst track fits best."""
        starts: list[_Pose] = []
        try:
            found, rvec, tvec = cv2.solvePnP(
                points, pixels, self.camera.K, self.camera.dist, flags=cv2.SOLVEPNP_EPNP
            )
        except cv2.error:
            found = False
        if not (found and _append_finite(starts, rvec, tvec, "epnp")):
            fallback = _sqpnp(points, pixels, self.camera)
            if fallback is None:
                return None
            starts.append(fallback)
        starts.extend(_refits(points, pixels, starts[0], self.camera))
        return min(starts, key=lambda pose: _worst_median(_errors(points, pixels, pose, self.camera), tracks))


def _errors(points: Points3, pixels: Pixels, pose: _Pose, camera: CameraModel) -> FloatArray:
    """Reprojection errors (N,) px, inf behind the camera: hypotheses._reprojection_errors through OpenCV's
    projection, 3x faster on the few rows of a scan."""
    R, _ = cv2.Rodrigues(pose.rvec.reshape(3, 1))
    depth = points @ R[2] + pose.tvec.reshape(3)[2]
    projected, _ = cv2.projectPoints(points, pose.rvec, pose.tvec, camera.K, camera.dist)
    errors = np.hypot(*(projected.reshape(-1, 2) - pixels).T)
    return np.where(depth > 0.0, errors, np.inf)


def _sqpnp(points: Points3, pixels: Pixels, camera: CameraModel) -> _Pose | None:
    try:
        found, rvec, tvec = cv2.solvePnP(points, pixels, camera.K, camera.dist, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        return None
    poses: list[_Pose] = []
    if found and _append_finite(poses, rvec, tvec, "sqpnp"):
        return poses[0]
    return None


def _with_clock(
    points: Points3,
    velocity: FloatArray,
    pixels: Pixels,
    start: _Pose,
    shift_s: float,
    reach_s: float,
    camera: CameraModel,
    params: HypothesisParams,
) -> tuple[_Pose, float] | None:
    """Pose and clock shift s (within +-reach_s) fitted together, robustly (Huber at half the RANSAC
    threshold), on the reprojection error of `points - velocity s`; None when the solver fails."""

    def residuals(x: FloatArray) -> FloatArray:
        projected, _ = cv2.projectPoints(points - velocity * x[6], x[:3], x[3:6], camera.K, camera.dist)
        return np.asarray((projected.reshape(-1, 2) - pixels).ravel(), dtype=np.float64)

    x0 = np.concatenate([start.rvec, start.tvec, [min(max(shift_s, -reach_s), reach_s)]])
    bounds = (np.r_[np.full(6, -np.inf), -reach_s], np.r_[np.full(6, np.inf), reach_s])
    try:
        fit = least_squares(
            residuals, x0, bounds=bounds, loss="huber", f_scale=params.reproj_threshold_px / 2.0, max_nfev=50
        )
    except (ValueError, np.linalg.LinAlgError, cv2.error):
        return None
    if not np.all(np.isfinite(fit.x)):
        return None
    return _Pose(fit.x[:3].copy(), fit.x[3:6].copy(), start.solver + "+clock"), float(fit.x[6])


def _worst_median(errors: FloatArray, tracks: int) -> float:
    """The largest of the tracks' median errors, for errors of `_balanced_rows` (as many rows each)."""
    return float(np.max(np.median(errors.reshape(tracks, -1), axis=1)))


def _balanced_rows(sizes: Sequence[int], per_track: int) -> IntArray:
    """Row indices into the stacked rows of tracks of `sizes`: as many of each (at most `per_track`),
    evenly spread along it, track after track."""
    k = min(*sizes, per_track)
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    return np.concatenate(
        [
            offset + np.linspace(0, size - 1, k).round().astype(np.int64)
            for offset, size in zip(offsets, sizes, strict=True)
        ]
    )
