"""The camera's clock offset searched through the grouping, when the assumed clock groups nothing.

A box stamped t on the camera clock shows the vehicle where it was a detector latency earlier. Paired with
the pose at t instead, every 3D point of a track lies `v * s` from the truth (v the vehicle's velocity, s
the clock error), and the hypothesis fitted to that track is the true camera displaced by the same `v * s`:
to first order the image does not change when world points and camera move together. Tracks driven in
different directions are displaced in different directions: at 150 ms and 12 m/s two opposite drive-pasts
put their hypotheses 3.6 m apart, and grouping, which expects one camera, finds no two that agree.

So when the assumed clock groups nothing, grouping is tried on trial clocks: for a trial shift s, each
hypothesis is moved back by `v_i s` (v_i its track's least-squares velocity over its inliers), refitted by
Levenberg-Marquardt on its rows re-paired with the poses on the shifted clock (free PnP solutions only),
and the similarity scores and clustering of grouping are applied unchanged. That move holds only near the
clock a hypothesis was fitted on: a few tenths of a second off, the poses of a curve no longer match its
boxes by a displacement, and the track's fit lands under the road or leaves the rotation unfixed, so the
track has no hypothesis to move (a test scene's opposite drive-pasts: one of the two lost from 0.3 s on),
and a weakly fixed one refitted by LM settles in whichever minimum is near (OpenCV 4 and 5 differ there).
So the trial clocks are split among anchor clocks `solve_step_s` apart (the assumed one among them), and
the hypotheses of every anchor but the assumed clock's are fitted afresh on its re-paired tracks (the
caller's `solve`, every stage of pipeline.hypotheses); a trial clock moves those of its nearest anchor.

The drive-pasts are those of the largest group found on the most trial clocks. They agree over a plateau
of clocks 0.1-0.3 s wide (r_ov cannot see a camera displaced along the road by up to half a car length), so
the clock is not the plateau's edge or centre but the trial, refined by a parabola, on which their corrected
cameras lie closest together. The caller runs every stage again on that clock, starting from the
hypotheses moved there. The final fit estimates the offset itself (vehicle_model), with this as its prior,
and the pipeline reruns once more when that estimate moves (calibrate).
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.arrays import FloatArray, IntArray
from pipeline.association import AssociationParams, MatchedTrack, Trajectory, match_tracks
from pipeline.camera import CameraModel, rotation_from_rvec, rvec_from_rotation
from pipeline.grouping import GroupingParams, group_hypotheses
from pipeline.hypotheses import Hypothesis, HypothesisSet, lm_refine
from pipeline.tracking import FrameBoxes, ImageTrack
from pipeline.vehicle import body_centres
from schemas.common import VehicleProfile

# Matched tracks on the clock shifted by s seconds: track id -> track (the caller pairs boxes and poses).
Rematch = Callable[[float], Mapping[int, MatchedTrack]]
# Hypotheses fitted afresh on the tracks (by id) re-paired on the clock shifted by s seconds.
Solve = Callable[[float, Mapping[int, MatchedTrack]], Sequence[Hypothesis]]


@dataclass(frozen=True, slots=True)
class ClockParams:
    """Trial shifts of the clock scan (s, relative to the assumed offset)."""

    # The floor is +-0.5 s; a latency beyond this is a misconfigured clock the operator must fix.
    max_shift_s: float = 0.6
    step_s: float = 0.025  # well inside the 0.1-0.3 s plateaus single-track hypotheses agree over
    # Anchor clocks (s apart) whose hypotheses are fitted afresh: a trial moves hypotheses by at most half
    # this, where the moved hypotheses of the test scenes still agree (0.25 s from their clock they did).
    solve_step_s: float = 0.25


@dataclass(frozen=True, slots=True)
class ClockScan:
    """The best trial shift (s; the corrected offset is the assumed one minus it), its largest group, and
    how many trial shifts gave a group at all."""

    shift_s: float
    track_ids: tuple[int, ...]
    mean_overlap: float
    shifts_with_groups: int
    shifts_tried: int
    max_shift_s: float
    # Every hypothesis moved to that clock and refitted there: the next pass groups these (fresh EPnP on
    # the re-paired boxes can miss the agreement the scan found: occluded seed 2).
    hypotheses: tuple[Hypothesis, ...] = ()

    @property
    def found(self) -> bool:
        return bool(self.track_ids)

    def describe(self) -> str:
        if not self.found:
            return f"no trial clock within +-{self.max_shift_s * 1e3:.0f} ms groups two drive-pasts either"
        return (
            f"on a clock {self.shift_s * 1e3:+.0f} ms from the assumed one, tracks {list(self.track_ids)} "
            f"agree (overlap {self.mean_overlap:.2f}; {self.shifts_with_groups} of {self.shifts_tried} trial "
            "clocks group some)"
        )


def track_velocity(track: MatchedTrack, rows: IntArray | None = None) -> FloatArray:
    """Least-squares velocity (3,) m/s of the vehicle over a track's rows (all rows when `rows` is None)."""
    stamps = track.stamps if rows is None else track.stamps[rows]
    positions = track.poses[:, :3] if rows is None else track.poses[rows, :3]
    if len(stamps) < 2:
        return np.zeros(3)
    t = (stamps - stamps[0]).astype(np.float64) / 1e9
    t -= t.mean()
    denominator = float(t @ t)
    if denominator <= 0.0:
        return np.zeros(3)
    return np.asarray(t @ (positions - positions.mean(axis=0)) / denominator, dtype=np.float64)


def rematcher(
    image_tracks: Sequence[ImageTrack], trajectory: Trajectory, association: AssociationParams
) -> Rematch:
    """The image tracks paired with the trajectory's poses on a clock shifted by s seconds (the trajectory's
    stamps later by s: the assumed offset minus s)."""

    def rematch(shift_s: float) -> dict[int, MatchedTrack]:
        moved = Trajectory(trajectory.stamps + np.int64(round(shift_s * 1e9)), trajectory.poses)
        return {m.track_id: m for m in match_tracks(image_tracks, moved, association)}

    return rematch


def shifted(hypothesis: Hypothesis, velocity: FloatArray, shift_s: float) -> Hypothesis:
    """The hypothesis with its camera moved back by `velocity * shift_s` (rotation kept)."""
    centre = hypothesis.camera_centre - velocity * shift_s
    return dataclasses.replace(hypothesis, t_cam_from_local=-hypothesis.R_cam_from_local @ centre)


def refitted(
    hypothesis: Hypothesis, track: MatchedTrack, camera: CameraModel, vehicle: VehicleProfile
) -> Hypothesis:
    """The hypothesis refitted by Levenberg-Marquardt from its pose on its inlier rows of `track` (box
    centre <-> body centre, as fitted in pipeline.hypotheses). Only for a free PnP solution: a straight
    track's pose rests on the box shapes (pipeline.straight_track), which the centres alone do not fix."""
    if not hypothesis.solver.startswith(("epnp", "sqpnp")):
        return hypothesis
    rows = np.flatnonzero(hypothesis.inliers)
    points = body_centres(track.poses[rows], vehicle)
    pixels = track.box_centres[rows]
    refined = lm_refine(
        points, pixels, rvec_from_rotation(hypothesis.R_cam_from_local), hypothesis.t_cam_from_local, camera
    )
    if refined is None:
        return hypothesis
    rvec, tvec = refined
    return dataclasses.replace(hypothesis, R_cam_from_local=rotation_from_rvec(rvec), t_cam_from_local=tvec)


def scan_clock(
    hypotheses: Sequence[Hypothesis],
    tracks_by_id: Mapping[int, MatchedTrack],
    rematch: Rematch,
    frames: Sequence[FrameBoxes],
    camera: CameraModel,
    vehicle: VehicleProfile,
    grouping: GroupingParams,
    params: ClockParams,
    solve: Solve | None = None,
) -> ClockScan:
    """Group the hypotheses on trial clocks (see the module); the best trial, or none found. `hypotheses`
    and `tracks_by_id` are the assumed clock's; `solve` fits the other anchors' (None: every trial moves the
    assumed clock's)."""
    anchors = {0: _Anchor.of(0.0, hypotheses, tracks_by_id)}

    def anchor_of(shift_s: float) -> _Anchor:
        """The anchor nearest a trial clock (ties towards the assumed clock), fitted on first use."""
        k = 0 if solve is None else _anchor_index(shift_s, params.solve_step_s)
        if k not in anchors:
            assert solve is not None
            clock_s = k * params.solve_step_s
            tracks = rematch(clock_s)
            anchors[k] = _Anchor.of(clock_s, tuple(solve(clock_s, tracks)), tracks)
        return anchors[k]

    def moved_to(shift_s: float, tracks: Mapping[int, MatchedTrack]) -> tuple[Hypothesis, ...]:
        # A track whose rows change with the clock (poses missing at an end) is left out on that clock.
        anchor = anchor_of(shift_s)
        return tuple(
            refitted(
                shifted(h, anchor.velocity[h.track_id], shift_s - anchor.clock_s),
                tracks[h.track_id],
                camera,
                vehicle,
            )
            for h in anchor.hypotheses
            if h.track_id in tracks
            and len(tracks[h.track_id].stamps) == len(anchor.tracks[h.track_id].stamps)
        )

    count = round(params.max_shift_s / params.step_s)
    shifts = params.step_s * np.arange(-count, count + 1)
    trials: list[tuple[float, tuple[int, ...], float]] = []  # shift, largest group, its mean overlap
    centres: list[dict[int, FloatArray]] = []  # per trial: track id -> corrected camera centre
    for shift in shifts:
        shift_s = float(shift)
        tracks = rematch(shift_s)
        trial = moved_to(shift_s, tracks)
        centres.append({h.track_id: h.camera_centre for h in trial})
        result = group_hypotheses(HypothesisSet(trial, {}), tracks, frames, camera, vehicle, grouping)
        if result.groups:
            group = result.groups[0]
            trials.append((shift_s, group.track_ids, group.mean_overlap_ratio))
    if not trials:
        return ClockScan(math.nan, (), 0.0, 0, len(shifts), params.max_shift_s)
    # Which drive-pasts: the largest group, the one found on the most trial clocks (then the best overlap).
    members = max(len(ids) for _, ids, _ in trials)
    sets = Counter(ids for _, ids, _ in trials if len(ids) == members)
    chosen = max(
        sets, key=lambda ids: (sets[ids], max(o for _, i, o in trials if i == ids), -min(ids, default=0))
    )
    # Which clock: r_ov cannot see a camera displaced along the road by up to half a car length, so the
    # drive-pasts group over a plateau of clocks 0.1-0.3 s wide, and its edges are where the hypotheses'
    # own errors happen to put them. Within the plateau, the estimate is the clock on which the chosen
    # drive-pasts' corrected cameras lie closest together (mean squared pair distance, minimum refined by a
    # parabola through its neighbours).
    on_plateau = [
        k for k, shift in enumerate(shifts) if any(t[0] == float(shift) and t[1] == chosen for t in trials)
    ]
    spread = np.full(len(shifts), np.inf)
    for k in range(min(on_plateau), max(on_plateau) + 1):
        if all(i in centres[k] for i in chosen):
            points = np.array([centres[k][i] for i in chosen])
            spread[k] = float(np.mean(np.sum((points[:, None, :] - points[None, :, :]) ** 2, axis=2)))
    k = int(np.argmin(spread))
    estimate = float(shifts[k])
    if 0 < k < len(shifts) - 1 and np.all(np.isfinite(spread[k - 1 : k + 2])):
        left, mid, right = spread[k - 1], spread[k], spread[k + 1]
        curvature = left - 2.0 * mid + right
        if curvature > 0.0:
            estimate += 0.5 * params.step_s * float(left - right) / float(curvature)
    overlap = max(o for _, i, o in trials if i == chosen)
    moved = moved_to(estimate, rematch(estimate))
    return ClockScan(estimate, chosen, overlap, len(trials), len(shifts), params.max_shift_s, moved)


@dataclass(frozen=True, slots=True)
class _Anchor:
    """An anchor clock of the scan (s from the assumed one), the hypotheses fitted on it, its tracks by id
    and the vehicle's velocity over each hypothesis's inlier rows there (track id -> (3,) m/s)."""

    clock_s: float
    hypotheses: Sequence[Hypothesis]
    tracks: Mapping[int, MatchedTrack]
    velocity: Mapping[int, FloatArray]

    @staticmethod
    def of(clock_s: float, hypotheses: Sequence[Hypothesis], tracks: Mapping[int, MatchedTrack]) -> _Anchor:
        velocity = {
            h.track_id: track_velocity(tracks[h.track_id], np.flatnonzero(h.inliers)) for h in hypotheses
        }
        return _Anchor(clock_s, hypotheses, tracks, velocity)


def _anchor_index(shift_s: float, step_s: float) -> int:
    """The index k of the anchor clock k * step_s nearest `shift_s`; a tie goes to the one nearer 0."""
    k = max(math.ceil(abs(shift_s) / step_s - 0.5 - 1e-9), 0)
    return k if shift_s >= 0 else -k
