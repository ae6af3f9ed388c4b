"""Vehicle poses -> vehicle states at camera stamps (paper Sec. III-B, plus a known clock offset).

`make_trajectory` turns the calibration vehicle's reported poses (absolute UTM, vehicle clock, possibly out
of order or repeated) into a `Trajectory` in the local frame on the camera clock; `interpolate_poses`
evaluates it at detection stamps, refusing where the poses cannot vouch for the vehicle's state (dropouts,
stamps outside the recorded span). The paper assumes synchronous clocks; a known offset is removed here.
`match_tracks` pairs every image track with the vehicle's poses at its stamps (`MatchedTrack`s: paper
III-D's correspondences before the solve).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.arrays import Boxes, FloatArray, Mask, Pixels, PoseArray, Stamps, check_shape
from pipeline.errors import InputError, ShapeError
from pipeline.frames import poses_to_array
from pipeline.tracking import ImageTrack
from schemas.common import LocalOrigin
from schemas.messages import VehiclePose

_YAW = 3  # PoseArray column of the yaw; the others (x, y, z, pitch, roll) interpolate linearly


@dataclass(frozen=True, slots=True)
class AssociationParams:
    max_pose_gap_ns: int = 1_500_000_000  # bracketing poses further apart -> no pose (1 Hz still works)
    max_extrapolation_ns: int = 0  # how far beyond the first/last pose a stamp may lie
    time_offset_ns: int = 0  # vehicle clock minus camera clock (subtracted from pose stamps)

    def __post_init__(self) -> None:
        for name in ("max_pose_gap_ns", "max_extrapolation_ns"):
            if getattr(self, name) < 0:
                raise InputError("association", f"{name} = {getattr(self, name)} must be >= 0")


@dataclass(frozen=True, slots=True)
class Trajectory:
    """The calibration vehicle's poses on the camera clock.

    stamps: (N,) int64 ns, camera clock, strictly increasing.
    poses:  (N, 6) x, y, z (m, local frame), yaw, pitch, roll (rad); yaw wrapped to [-pi, pi].
    """

    stamps: Stamps
    poses: PoseArray

    def __post_init__(self) -> None:
        check_shape(self.stamps, "N", name="trajectory.stamps")
        check_shape(self.poses, "N,6", name="trajectory.poses")
        if len(self.stamps) != len(self.poses):
            raise ShapeError(f"trajectory: {len(self.stamps)} stamps but {len(self.poses)} poses")
        if np.any(np.diff(self.stamps) <= 0):
            raise ShapeError("trajectory.stamps: must be strictly increasing")


def wrap_angle(angle: FloatArray) -> FloatArray:
    """Angles (rad) wrapped to [-pi, pi]; values already inside are returned bit-exact."""
    # a - 2 pi round(a / 2 pi) leaves in-range values untouched, unlike angle(exp(1j a)) which rounds them.
    return np.asarray(angle - 2.0 * math.pi * np.round(angle / (2.0 * math.pi)), dtype=np.float64)


def make_trajectory(
    poses: Sequence[VehiclePose], origin: LocalOrigin, params: AssociationParams
) -> Trajectory:
    """Reported poses -> Trajectory (paper III-B pre-processing).

    Sorts by stamp, drops exact duplicate stamps (the first received wins: a repeated stamp is a re-sent
    or conflicting message and the earliest is what the vehicle first committed to), subtracts `origin`
    (absolute UTM -> local frame, m) and moves the stamps onto the camera clock: pose stamps are in the
    vehicle clock = camera clock + `params.time_offset_ns`. An empty input gives an empty trajectory.
    """
    stamps_vehicle, local = poses_to_array(poses, origin)
    # Stable sort so that among equal stamps the first in input order comes first and is the one kept.
    order = np.argsort(stamps_vehicle, kind="stable")
    stamps_vehicle, local = stamps_vehicle[order], local[order]
    is_first = np.ones(len(stamps_vehicle), dtype=bool)
    is_first[1:] = np.diff(stamps_vehicle) != 0
    local = local[is_first]
    local[:, _YAW] = wrap_angle(local[:, _YAW])
    stamps_camera = stamps_vehicle[is_first] - np.int64(params.time_offset_ns)
    return Trajectory(stamps=stamps_camera, poses=local)


def interpolate_poses(
    trajectory: Trajectory, stamps: Stamps, params: AssociationParams
) -> tuple[PoseArray, Mask]:
    """Vehicle pose at each camera stamp (paper III-B): (M,) int64 ns, camera clock -> ((M, 6), (M,) bool).

    Between two poses, x, y, z, pitch and roll interpolate linearly and yaw along the shorter arc of the
    circle (wrapped to [-pi, pi]). A row is valid (mask True) when the stamp equals a pose stamp, or lies
    between two poses at most `max_pose_gap_ns` apart (a longer gap is a dropout: the vehicle may have
    turned or stopped in it), or lies within `max_extrapolation_ns` before the first / after the last pose
    (extrapolated linearly along the end segment when that segment is no dropout, else held). Invalid rows
    are NaN. `params.time_offset_ns` is NOT applied again: the trajectory is already on the camera clock.
    Vectorised (searchsorted), so 1 Hz and 100 Hz pose rates cost the same; `stamps` need not be sorted.
    """
    check_shape(stamps, "N", name="stamps")
    if not np.issubdtype(stamps.dtype, np.integer):
        raise ShapeError(f"stamps: expected integer nanoseconds, got dtype {stamps.dtype}")
    query = stamps.astype(np.int64)
    count = len(trajectory.stamps)
    result = np.full((len(query), 6), np.nan)
    if count == 0 or len(query) == 0:
        return result, np.zeros(len(query), dtype=bool)
    known = trajectory.stamps
    if count == 1:
        is_valid = np.abs(query - known[0]) <= params.max_extrapolation_ns
        result[is_valid] = trajectory.poses[0]
        return result, is_valid

    # Segment [lo, lo + 1] for every query; end segments are reused for stamps beyond either end.
    lo = np.clip(np.searchsorted(known, query, side="right") - 1, 0, count - 2)
    hi = lo + 1
    segment_ns = known[hi] - known[lo]
    weight = (query - known[lo]).astype(np.float64) / segment_ns.astype(np.float64)
    is_short_segment = segment_ns <= params.max_pose_gap_ns
    before, after = query < known[0], query > known[-1]
    outside = before | after
    # Beyond the ends: extrapolate along the end segment only when it is no dropout, otherwise hold the pose.
    weight = np.where(outside & ~is_short_segment, np.where(before, 0.0, 1.0), weight)

    pose_lo, pose_hi = trajectory.poses[lo], trajectory.poses[hi]
    # (1 - w) a + w b (not a + w (b - a)) is exact at w = 0 and w = 1.
    result = (1.0 - weight)[:, None] * pose_lo + weight[:, None] * pose_hi
    yaw_step = wrap_angle(pose_hi[:, _YAW] - pose_lo[:, _YAW])
    result[:, _YAW] = wrap_angle(pose_lo[:, _YAW] + weight * yaw_step)
    # Exactly at a pose stamp: return that pose bit-exact, whatever its neighbours.
    at_lo, at_hi = query == known[lo], query == known[hi]
    result[at_lo] = pose_lo[at_lo]
    result[at_hi] = pose_hi[at_hi]

    distance_outside = np.where(before, known[0] - query, np.where(after, query - known[-1], 0))
    is_valid = np.where(outside, distance_outside <= params.max_extrapolation_ns, is_short_segment)
    is_valid |= at_lo | at_hi
    result[~is_valid] = np.nan
    return result, is_valid


@dataclass(frozen=True, slots=True)
class MatchedTrack:
    """An image track restricted to the rows that got a vehicle pose (paper III-D, h_i before the solve).

    stamps (N,) int64 ns camera clock, increasing; boxes (N, 4) px x1, y1, x2, y2; poses (N, 6) the
    calibration vehicle's pose at each stamp (x, y, z m local frame; yaw, pitch, roll rad).
    """

    track_id: int
    stamps: Stamps
    boxes: Boxes
    poses: PoseArray

    def __post_init__(self) -> None:
        check_shape(self.stamps, "N", name="matched_track.stamps")
        check_shape(self.boxes, "N,4", name="matched_track.boxes")
        check_shape(self.poses, "N,6", name="matched_track.poses")
        if not len(self.stamps) == len(self.boxes) == len(self.poses):
            raise ShapeError(
                f"matched_track {self.track_id}: {len(self.stamps)} stamps, {len(self.boxes)} boxes, "
                f"{len(self.poses)} poses"
            )

    @property
    def box_centres(self) -> Pixels:
        """Box centres (N, 2) px: the image half of the paper's correspondences."""
        return np.column_stack(
            [(self.boxes[:, 0] + self.boxes[:, 2]) / 2.0, (self.boxes[:, 1] + self.boxes[:, 3]) / 2.0]
        )


def match_tracks(
    tracks: Sequence[ImageTrack], trajectory: Trajectory, params: AssociationParams
) -> list[MatchedTrack]:
    """Pair every image track with the calibration vehicle's poses at its stamps (paper III-D).

    Tracks lying wholly outside the trajectory's time span (widened by `params.max_extrapolation_ns`)
    are skipped before any interpolation: only tracks that overlap the vehicle's presence in time can be
    hypotheses. Rows without a pose (dropouts, see `interpolate_poses`) are dropped; a track left with no
    row is skipped. Order follows `tracks`.
    """
    if len(trajectory.stamps) == 0:
        return []
    span_start = int(trajectory.stamps[0]) - params.max_extrapolation_ns
    span_end = int(trajectory.stamps[-1]) + params.max_extrapolation_ns
    matched: list[MatchedTrack] = []
    for track in tracks:
        check_shape(track.stamps, "N", name=f"track {track.track_id}.stamps")
        check_shape(track.boxes, "N,4", name=f"track {track.track_id}.boxes")
        if len(track.stamps) == 0:
            continue
        if int(track.stamps.max()) < span_start or int(track.stamps.min()) > span_end:
            continue  # cheap skip: no pose can exist for any row
        poses, has_pose = interpolate_poses(trajectory, track.stamps, params)
        if not np.any(has_pose):
            continue
        matched.append(
            MatchedTrack(
                track_id=track.track_id,
                stamps=track.stamps[has_pose],
                boxes=track.boxes[has_pose],
                poses=poses[has_pose],
            )
        )
    return matched


def select_rows(tracks: Sequence[MatchedTrack], keep: Mask) -> list[MatchedTrack]:
    """The tracks restricted to the rows where `keep` (all tracks' rows stacked, in order) is True; a track
    left with no row is dropped."""
    kept: list[MatchedTrack] = []
    start = 0
    for track in tracks:
        rows = keep[start : start + len(track.boxes)]
        start += len(track.boxes)
        if rows.any():
            kept.append(
                MatchedTrack(track.track_id, track.stamps[rows], track.boxes[rows], track.poses[rows])
            )
    return kept


def apart_in_time(
    scored: Sequence[tuple[float, MatchedTrack]], spans: Sequence[tuple[int, int]]
) -> list[MatchedTrack]:
    """Best-scored first, the tracks that overlap in time neither `spans` (the vehicle's tracks) nor each
    other: a track seen together with one of the vehicle's is another vehicle."""
    taken = list(spans)
    added: list[MatchedTrack] = []
    for _, track in sorted(scored, key=lambda pair: pair[0]):
        span = (int(track.stamps[0]), int(track.stamps[-1]))
        if any(span[0] <= end and start <= span[1] for start, end in taken):
            continue
        added.append(track)
        taken.append(span)
    return added


def track_spans(tracks: Sequence[MatchedTrack]) -> list[tuple[int, int]]:
    """(first, last) stamp ns of each track."""
    return [(int(m.stamps[0]), int(m.stamps[-1])) for m in tracks]
