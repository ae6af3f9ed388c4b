"""Detector boxes -> image tracks, model-less, DIoU cost + Hungarian assignment (paper Sec. III-C, Eq. 2).

Input: one `FrameBoxes` per camera image (camera clock, pixels). Output: a `TrackSet` of `ImageTrack`s,
each the real (detected, not extrapolated, not border-clipped) boxes of one vehicle in time order. The
extrinsic is unknown at this stage, so tracking stays in image space with no kinematic model beyond a
constant box velocity used to predict where a track's box should be in the next frame.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from pipeline.arrays import Boxes, FloatArray, IntArray, Mask, Pixels, Stamps, check_shape
from pipeline.errors import InputError, ShapeError
from pipeline.tables import DetectionTable
from schemas.common import toolbox_class_id
from schemas.messages import DetectionFrame

_NO_MATCH_COST = 2.0  # Eq. 2: cost of a pair whose IoU is 0; such pairs are never associated
_MIN_PREDICTED_SIZE_PX = 1.0  # an extrapolated box may shrink, but never below this width/height
# Columns of the tracker's per-track state rows.
_LAST, _VELOCITY, _TIME_S, _MISSES = slice(0, 4), slice(4, 8), 8, 9
_STATE_COLUMNS = 10
_TINY = 1e-12  # px^2; floor of denominators that are 0 only when their numerator is 0 too


@dataclass(frozen=True, slots=True)
class FrameBoxes:
    """One camera image: stamp_ns (camera clock), boxes (N, 4) px x1, y1, x2, y2, classes (N,) toolbox
    class ids (names mapped by schemas.common.toolbox_class_id; -1 for a name the toolbox has no id for)."""

    stamp_ns: int
    boxes: Boxes
    classes: IntArray


@dataclass(frozen=True, slots=True)
class TrackingParams:
    max_extrapolated_frames: int = 5  # consecutive frames a track may go unmatched before it is closed
    border_margin_px: float = 1.0  # a box within this distance of an image edge is clipped: not output

    def __post_init__(self) -> None:
        if self.max_extrapolated_frames < 0:
            raise InputError(
                "tracking", f"max_extrapolated_frames = {self.max_extrapolated_frames} must be >= 0"
            )
        if not self.border_margin_px >= 0.0:
            raise InputError("tracking", f"border_margin_px = {self.border_margin_px} must be >= 0")


@dataclass(frozen=True, slots=True)
class ImageTrack:
    """One vehicle's real boxes: stamps (N,) int64 strictly increasing, boxes (N, 4) px, classes (N,)."""

    track_id: int
    stamps: Stamps
    boxes: Boxes
    classes: IntArray


@dataclass(frozen=True, slots=True)
class TrackSet:
    tracks: tuple[ImageTrack, ...]  # sorted by track_id (0, 1, ... in order of first appearance)
    border_boxes_dropped: int  # boxes that took part in tracking but are absent from the output
    # ... of them, those reaching beyond the radius the lens model holds to (CameraModel.beyond_model)
    lens_boxes_dropped: int = 0


def frames_from_detections(frames: Sequence[DetectionFrame]) -> list[FrameBoxes]:
    """DetectionFrame messages -> FrameBoxes sorted by stamp (camera clock, px).

    A frame whose stamp repeats an earlier one is dropped (the first received wins), so the result has
    strictly increasing stamps as `track_boxes` requires; in-order, unique input maps one to one.
    """
    if isinstance(frames, DetectionTable):
        return _frames_from_table(frames)
    order = sorted(range(len(frames)), key=lambda i: frames[i].stamp_ns)  # stable: first received first
    result: list[FrameBoxes] = []
    for index in order:
        frame = frames[index]
        if result and result[-1].stamp_ns == frame.stamp_ns:
            continue
        boxes = np.array([(b.x1, b.y1, b.x2, b.y2) for b in frame.boxes], dtype=np.float64).reshape(-1, 4)
        classes = np.array([toolbox_class_id(b.cls) for b in frame.boxes], dtype=np.int64)
        result.append(FrameBoxes(stamp_ns=frame.stamp_ns, boxes=boxes, classes=classes))
    return result


def _frames_from_table(table: DetectionTable) -> list[FrameBoxes]:
    """frames_from_detections on a DetectionTable's columns (its class ids are toolbox ids already)."""
    order = np.argsort(table.stamps, kind="stable")  # stable: first received first
    # One copy of the columns, each frame a slice of it: the frames share no memory with the table, and
    # slicing is several times cheaper than a copy per frame (9,000 frames).
    boxes, classes = table.boxes.copy(), table.classes.copy()
    stamps, starts = table.stamps.tolist(), table.starts.tolist()
    result: list[FrameBoxes] = []
    for index in order.tolist():
        stamp_ns = stamps[index]
        if result and result[-1].stamp_ns == stamp_ns:
            continue
        lo, hi = starts[index], starts[index + 1]
        result.append(FrameBoxes(stamp_ns=stamp_ns, boxes=boxes[lo:hi], classes=classes[lo:hi]))
    return result


def overlap_terms(a: Boxes, b: Boxes) -> tuple[FloatArray, FloatArray]:
    """IoU (N, M) and the DIoU penalty d^2 / c^2 (N, M) of every pair of boxes (N, 4), (M, 4) px x1, y1, x2,
    y2, by broadcasting. Distance-IoU (Zheng et al. 2020; paper III-C) is IoU - penalty, with d the distance
    of the box centres and c the diagonal of the smallest box enclosing both: in (-1, 1], so the association
    cost 1 - DIoU lies in [0, 2).

    Written for the tracker's hot loop (tens of boxes, every frame): few temporaries, no masked divides.
    """
    ax1, ay1, ax2, ay2 = a.T[:, :, None]  # columns of a as (N, 1), of b as (M,): broadcast to (N, M)
    bx1, by1, bx2, by2 = b.T
    # Signed overlap extents; negative means a gap. The enclosing box extent is w_a + w_b - overlap.
    overlap_w = np.minimum(ax2, bx2) - np.maximum(ax1, bx1)
    overlap_h = np.minimum(ay2, by2) - np.maximum(ay1, by1)
    inter = np.maximum(overlap_w, 0.0) * np.maximum(overlap_h, 0.0)
    width_a, height_a = ax2 - ax1, ay2 - ay1
    width_b, height_b = bx2 - bx1, by2 - by1
    union = width_a * height_a + width_b * height_b - inter
    # Zero-area boxes have union 0 and intersection 0: the floor turns 0/0 into IoU 0 instead of NaN.
    iou = inter / np.maximum(union, _TINY)
    enclose_w = width_a + width_b - overlap_w
    enclose_h = height_a + height_b - overlap_h
    # d^2 from the sums x1 + x2 (twice the centre), hence the 1/4.
    dx = (ax1 + ax2) - (bx1 + bx2)
    dy = (ay1 + ay2) - (by1 + by2)
    # c = 0 only for two identical points, whose centre distance is 0 too: the floor gives no penalty.
    penalty = 0.25 * (dx * dx + dy * dy) / np.maximum(enclose_w * enclose_w + enclose_h * enclose_h, _TINY)
    return iou, penalty


def touches_border(boxes: Boxes, width: int, height: int, margin_px: float) -> Mask:
    """Boxes (N, 4) with any edge within `margin_px` of the image border: clipped by the image (or the
    detector), their geometry not trustworthy: (N,). The one border test (tracking, metrics.delta_p)."""
    return np.asarray(
        (boxes[:, 0] <= margin_px)
        | (boxes[:, 1] <= margin_px)
        | (boxes[:, 2] >= width - margin_px)
        | (boxes[:, 3] >= height - margin_px),
        dtype=np.bool_,
    )


def _check_frames(frames: Sequence[FrameBoxes]) -> None:
    previous_ns: int | None = None
    for index, frame in enumerate(frames):
        boxes, classes = frame.boxes, frame.classes
        # check_shape builds its message from a spec string; the cheap test keeps 10^4 frames fast.
        if not (isinstance(boxes, np.ndarray) and boxes.ndim == 2 and boxes.shape[1] == 4):
            check_shape(boxes, "N,4", name=f"frames[{index}].boxes")
        if not (isinstance(classes, np.ndarray) and classes.ndim == 1):
            check_shape(classes, "N", name=f"frames[{index}].classes")
        if len(classes) != len(boxes):
            raise ShapeError(f"frames[{index}]: {len(boxes)} boxes but {len(classes)} classes")
        if previous_ns is not None and frame.stamp_ns <= previous_ns:
            raise InputError(
                "frames",
                f"frames[{index}].stamp_ns = {frame.stamp_ns} not after the previous {previous_ns}; "
                "stamps must be strictly increasing (frames_from_detections sorts and de-duplicates)",
            )
        previous_ns = frame.stamp_ns


def track_boxes(
    frames: Sequence[FrameBoxes],
    width: int,
    height: int,
    params: TrackingParams,
    beyond_lens: Callable[[Pixels], Mask] | None = None,
) -> TrackSet:
    """Track boxes through an image sequence offline (paper III-C, Eq. 2).

    frames: strictly increasing stamps (ns, camera clock), boxes in px; width, height: image size (px).

    Each frame, the active tracks' predicted boxes and the frame's boxes are assigned by the Hungarian
    algorithm with cost 1 - DIoU where IoU > 0 and 2 otherwise; assigned pairs with IoU = 0 are rejected,
    never associated. Deviation from the paper, which compares with the previous frame's box: a track's box
    is predicted at the frame's stamp with a constant box velocity from its last two real boxes, so fast or
    crossing vehicles and irregular frame spacing (jitter, dropped frames) keep their overlap. Unmatched
    tracks coast on that prediction (the paper's linear extrapolation) for up to `max_extrapolated_frames`
    frames, then close; unmatched boxes open new tracks. Extrapolated boxes never enter the output.

    Border boxes (within `border_margin_px` of an edge) DO take part in association, so a vehicle entering
    or leaving the image keeps one track, but are left out of every output track (their clipped geometry
    would corrupt the 2D-3D correspondences) and counted in `border_boxes_dropped`; so are boxes with a
    corner where `beyond_lens` (CameraModel.beyond_model) says the lens model no longer holds (counted in
    `lens_boxes_dropped` as well). Tracks with no box left are not output. Track ids are renumbered 0, 1,
    ... in order of first appearance. Classes do not gate association: detectors flicker between car, van
    and truck on the same vehicle.
    """
    _check_frames(frames)
    counts = np.array([len(frame.boxes) for frame in frames], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    track_of_box = np.empty(int(offsets[-1]), dtype=np.int64)  # internal track id of every input box
    if not frames:
        return TrackSet(tracks=(), border_boxes_dropped=0)
    first_ns = frames[0].stamp_ns

    # Active tracks: ids (K,) and one float state row each (layout _LAST, _VELOCITY, _TIME_S, _MISSES):
    # last real box (px), its velocity (px/s, from the last two real boxes, 0 after a single box), the
    # last real box's time (s since the first frame; float64 keeps sub-microsecond resolution for days)
    # and the consecutive frames missed. One array keeps the per-frame bookkeeping to a few numpy calls.
    active_ids = np.empty(0, dtype=np.int64)
    state = np.empty((0, _STATE_COLUMNS))
    next_id = 0
    max_misses = params.max_extrapolated_frames

    for index, frame in enumerate(frames):
        boxes = frame.boxes
        count = len(boxes)
        time_s = (frame.stamp_ns - first_ns) * 1e-9
        rows = cols = np.empty(0, dtype=np.intp)
        if len(active_ids) and count:
            elapsed_s = time_s - state[:, _TIME_S]
            predicted = state[:, _LAST] + state[:, _VELOCITY] * elapsed_s[:, None]
            sizes = predicted[:, 2:] - predicted[:, :2]
            if sizes.min() < _MIN_PREDICTED_SIZE_PX:
                predicted = _keep_min_size(predicted)
            iou, penalty = overlap_terms(predicted, boxes)
            is_overlapping = iou > 0.0
            cost = np.where(is_overlapping, (1.0 + penalty) - iou, _NO_MATCH_COST)
            rows, cols = linear_sum_assignment(cost)
            # Eq. 2: the assignment may pair leftovers at cost 2; those are no association.
            keep = is_overlapping[rows, cols]
            if not keep.all():
                rows, cols = rows[keep], cols[keep]
            matched = state[rows]
            matched[:, _VELOCITY] = (boxes[cols] - matched[:, _LAST]) / elapsed_s[rows, None]
            matched[:, _LAST] = boxes[cols]
            matched[:, _TIME_S] = time_s
            matched[:, _MISSES] = -1.0  # the increment below brings it to 0
            state[rows] = matched

        assigned = track_of_box[offsets[index] : offsets[index + 1]]
        assigned[cols] = active_ids[rows]
        state[:, _MISSES] += 1.0
        if len(state) and state[:, _MISSES].max() > max_misses:
            is_alive = state[:, _MISSES] <= max_misses
            active_ids, state = active_ids[is_alive], state[is_alive]
        new_count = count - len(cols)
        if new_count:
            is_new = np.ones(count, dtype=bool)
            is_new[cols] = False
            new_ids = np.arange(next_id, next_id + new_count, dtype=np.int64)
            next_id += new_count
            assigned[is_new] = new_ids
            new_state = np.zeros((new_count, _STATE_COLUMNS))
            new_state[:, _LAST] = boxes[is_new]
            new_state[:, _TIME_S] = time_s
            active_ids = np.concatenate([active_ids, new_ids])
            state = np.concatenate([state, new_state])

    return _collect_tracks(frames, counts, track_of_box, width, height, params.border_margin_px, beyond_lens)


def _keep_min_size(boxes: Boxes) -> Boxes:
    """Predicted boxes (K, 4) whose extrapolated size fell below the minimum, regrown about their centre."""
    centre = 0.5 * (boxes[:, :2] + boxes[:, 2:])
    half = np.maximum(0.5 * (boxes[:, 2:] - boxes[:, :2]), 0.5 * _MIN_PREDICTED_SIZE_PX)
    return np.concatenate([centre - half, centre + half], axis=1)


def _collect_tracks(
    frames: Sequence[FrameBoxes],
    counts: IntArray,
    track_of_box: IntArray,
    width: int,
    height: int,
    margin_px: float,
    beyond_lens: Callable[[Pixels], Mask] | None,
) -> TrackSet:
    """Group every input box by its track in one pass, drop border boxes and those beyond the lens model,
    renumber the survivors."""
    if len(track_of_box) == 0:
        return TrackSet(tracks=(), border_boxes_dropped=0)
    all_boxes = np.concatenate([frame.boxes for frame in frames])
    all_classes = np.concatenate([frame.classes for frame in frames]).astype(np.int64)
    all_stamps = np.repeat(np.array([frame.stamp_ns for frame in frames], dtype=np.int64), counts)
    is_border = touches_border(all_boxes, width, height, margin_px)
    lens_count = 0
    if beyond_lens is not None:
        corners = all_boxes[:, [0, 1, 2, 1, 0, 3, 2, 3]].reshape(-1, 2)
        is_beyond = beyond_lens(corners).reshape(-1, 4).any(axis=1)
        lens_count = int(np.count_nonzero(is_beyond & ~is_border))
        is_border |= is_beyond
    border_count = int(np.count_nonzero(is_border))
    kept = np.flatnonzero(~is_border)
    if len(kept) == 0:
        return TrackSet(tracks=(), border_boxes_dropped=border_count, lens_boxes_dropped=lens_count)
    # Stable sort by track keeps each track's boxes in frame order; internal ids already follow first
    # appearance, so renumbering the surviving ids densely preserves that order.
    kept = kept[np.argsort(track_of_box[kept], kind="stable")]
    kept_tracks = track_of_box[kept]
    starts = np.flatnonzero(np.r_[True, np.diff(kept_tracks) != 0])
    ends = np.r_[starts[1:], len(kept)]
    tracks = tuple(
        ImageTrack(
            track_id=number,
            stamps=all_stamps[kept[start:end]],
            boxes=all_boxes[kept[start:end]],
            classes=all_classes[kept[start:end]],
        )
        for number, (start, end) in enumerate(zip(starts.tolist(), ends.tolist(), strict=True))
    )
    return TrackSet(tracks=tracks, border_boxes_dropped=border_count, lens_boxes_dropped=lens_count)
