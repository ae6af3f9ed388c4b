"""Simulated detector: vehicle cuboids -> the boxes an RSU camera's detector reports, frame by frame.

A vehicle's box is the tight rectangle around its 8 projected body corners (OpenCV lens model, with
distortion), clipped at the image border. It is dropped when a corner is behind the camera, when most of
it lies outside the image, when it is too small for a detector, or when most of it is hidden behind nearer
vehicles or static occluders (measured on a sample grid inside the box). Then the detector's errors: edge
jitter, misses, wrong classes and short-lived false positives. Everything is vectorised over all
(frame, vehicle) instances of a camera at once; only vehicles on the road at a frame's time take part.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.geometry import BoolArray, FloatArray, IntArray, attitude_matrices
from sim.lens import Lens
from sim.presets import DetectorSpec
from sim.world import UNIT_BOX_CORNERS

Boxes = FloatArray  # (N, 4) x1, y1, x2, y2 pixels
Mask = BoolArray
CLASS_CHOICES = np.array([4, 5, 6, 7])


def cuboid_corners(center_poses: FloatArray, dims: FloatArray) -> FloatArray:
    """Body corners (P, 8, 3), footprint RR, FR, FL, RL then the roof (vehicle.body_corners order), of
    boxes whose footprint centre and attitude are `center_poses` (P, 6) and size `dims` (P, 3) = L, W, H."""
    R = attitude_matrices(center_poses[:, 3], center_poses[:, 4], center_poses[:, 5])
    body = (UNIT_BOX_CORNERS[None, :, :] - np.array([0.5, 0.5, 0.0])) * dims[:, None, :]
    return np.asarray(np.einsum("pij,pkj->pki", R, body) + center_poses[:, None, :3], dtype=np.float64)


def may_be_in_view(
    centres: FloatArray,
    radius: FloatArray,
    R_cam_from_local: FloatArray,
    t_cam_from_local: FloatArray,
    view_bounds: FloatArray,
) -> Mask:
    """Conservative cull (P,): False only where a sphere (centre (P, 3) local, radius (P,) m) lies wholly
    outside the view (`view_bounds` from Lens.view_bounds): the exact box test runs on fewer cuboids."""
    cam = centres @ R_cam_from_local.T + t_cam_from_local
    z = cam[:, 2]
    near = z <= radius  # touching the camera plane: let the exact test decide
    with np.errstate(divide="ignore", invalid="ignore"):
        margin = radius / np.sqrt(np.maximum(z * z - radius * radius, 1e-9))  # sphere's angular half-size
        x, y = cam[:, 0] / z, cam[:, 1] / z
        inside = (
            (x + margin >= view_bounds[0])
            & (x - margin <= view_bounds[2])
            & (y + margin >= view_bounds[1])
            & (y - margin <= view_bounds[3])
        )
    return np.asarray(near | inside, dtype=np.bool_)


@dataclass(frozen=True, eq=False)
class ProjectedBoxes:
    """Boxes of projected cuboids: `raw` (P, 4) the tight bounds of all 8 corners (NaN when not
    projectable), `clipped` (P, 4) raw clipped to the image, `projectable` (P,) all corners in front of
    the camera within the lens model, `inside_fraction` (P,) clipped area / raw area."""

    raw: Boxes
    clipped: Boxes
    projectable: Mask
    inside_fraction: FloatArray


def project_boxes(
    corners: FloatArray, R_cam_from_local: FloatArray, t_cam_from_local: FloatArray, lens: Lens
) -> ProjectedBoxes:
    """Boxes (pixels) of point sets (P, K, 3) in the local frame: the tight bounds of all K projections."""
    count, per = corners.shape[:2]
    points_cam = corners.reshape(-1, 3) @ R_cam_from_local.T + t_cam_from_local
    pixels, imageable = lens.project_cam(points_cam)
    pixels = pixels.reshape(count, per, 2)
    projectable = np.all(imageable.reshape(count, per), axis=1)
    raw = np.full((count, 4), np.nan)
    if np.any(projectable):
        px = pixels[projectable]
        raw[projectable] = np.column_stack(
            [
                px[:, :, 0].min(axis=1),
                px[:, :, 1].min(axis=1),
                px[:, :, 0].max(axis=1),
                px[:, :, 1].max(axis=1),
            ]
        )
    clipped = np.column_stack(
        [
            np.clip(raw[:, 0], 0, lens.width),
            np.clip(raw[:, 1], 0, lens.height),
            np.clip(raw[:, 2], 0, lens.width),
            np.clip(raw[:, 3], 0, lens.height),
        ]
    )
    area = (raw[:, 2] - raw[:, 0]) * (raw[:, 3] - raw[:, 1])
    inside_area = (clipped[:, 2] - clipped[:, 0]) * (clipped[:, 3] - clipped[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        inside = np.where(projectable & (area > 0), inside_area / area, 0.0)
    return ProjectedBoxes(raw, clipped, projectable, np.nan_to_num(inside, nan=0.0))


def _group_pairs(frame: IntArray, max_pairs: int) -> list[tuple[IntArray, IntArray]]:
    """All ordered pairs (i, j), i != j, of rows sharing a frame, in chunks of at most ~max_pairs."""
    order = np.argsort(frame, kind="stable")
    _, starts, counts = np.unique(frame[order], return_index=True, return_counts=True)
    chunks = []
    sizes = counts.astype(np.int64) ** 2
    bounds = np.searchsorted(np.cumsum(sizes), np.arange(max_pairs, int(sizes.sum()) + max_pairs, max_pairs))
    first = 0
    for last in np.unique(np.minimum(bounds + 1, len(counts))):
        group_starts, group_counts, group_sizes = starts[first:last], counts[first:last], sizes[first:last]
        first = int(last)
        total = int(group_sizes.sum())
        if total == 0:
            continue
        group = np.repeat(np.arange(len(group_counts)), group_sizes)
        within = np.arange(total) - np.repeat(np.cumsum(group_sizes) - group_sizes, group_sizes)
        n = group_counts[group]
        i = order[group_starts[group] + within // n]
        j = order[group_starts[group] + within % n]
        keep = i != j
        chunks.append((i[keep], j[keep]))
    return chunks


def hidden_fractions(
    frame: IntArray,
    boxes: Boxes,
    distance: FloatArray,
    is_target: Mask,
    grid: int = 12,
    max_pairs: int = 2_000_000,
) -> tuple[FloatArray, Boxes]:
    """How much of each target box is covered by nearer boxes of the same frame (the union of them).

    frame (P,), boxes (P, 4) pixels, distance (P,) m from the camera (smaller = nearer), is_target (P,)
    rows to measure (occluders are never measured, but hide others). The box is sampled on a grid x grid
    of cell centres. Returns the hidden fraction (P,) (0 for non-targets) and the bounds (P, 4) of the
    uncovered samples' cells: the visible part's box (the box itself where nothing covers it)."""
    hidden = np.zeros(len(boxes))
    visible = boxes.copy()
    pair_i, pair_j = [], []
    for i, j in _group_pairs(frame, max_pairs):
        bi, bj = boxes[i], boxes[j]
        overlap = (np.minimum(bi[:, 2], bj[:, 2]) > np.maximum(bi[:, 0], bj[:, 0])) & (
            np.minimum(bi[:, 3], bj[:, 3]) > np.maximum(bi[:, 1], bj[:, 1])
        )
        keep = is_target[i] & (distance[j] < distance[i]) & overlap
        pair_i.append(i[keep])
        pair_j.append(j[keep])
    if not pair_i or sum(len(p) for p in pair_i) == 0:
        return hidden, visible
    i = np.concatenate(pair_i)
    j = np.concatenate(pair_j)
    order = np.argsort(i, kind="stable")
    i, j = i[order], j[order]
    cells = (np.arange(grid) + 0.5) / grid
    bi, bj = boxes[i], boxes[j]
    u = bi[:, 0:1] + cells * (bi[:, 2:3] - bi[:, 0:1])  # (n, grid) sample columns
    v = bi[:, 1:2] + cells * (bi[:, 3:4] - bi[:, 1:2])  # (n, grid) sample rows
    col_in = (u >= bj[:, 0:1]) & (u <= bj[:, 2:3])
    row_in = (v >= bj[:, 1:2]) & (v <= bj[:, 3:4])
    covered_by_pair = row_in[:, :, None] & col_in[:, None, :]  # (n, rows, cols)
    targets, starts = np.unique(i, return_index=True)
    covered: Mask = np.asarray(np.logical_or.reduceat(covered_by_pair, starts, axis=0), dtype=np.bool_)
    hidden[targets] = covered.mean(axis=(1, 2))
    free = np.logical_not(covered)
    rows_free: Mask = np.asarray(free.any(axis=2), dtype=np.bool_)
    cols_free: Mask = np.asarray(free.any(axis=1), dtype=np.bool_)
    has_free = rows_free.any(axis=1)
    first_row, last_row = rows_free.argmax(axis=1), grid - 1 - rows_free[:, ::-1].argmax(axis=1)
    first_col, last_col = cols_free.argmax(axis=1), grid - 1 - cols_free[:, ::-1].argmax(axis=1)
    b = boxes[targets]
    w, h = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
    part = np.column_stack(
        [
            b[:, 0] + w * first_col / grid,
            b[:, 1] + h * first_row / grid,
            b[:, 0] + w * (last_col + 1) / grid,
            b[:, 1] + h * (last_row + 1) / grid,
        ]
    )
    visible[targets[has_free]] = part[has_free]
    return hidden, visible


@dataclass(frozen=True, eq=False)
class Instances:
    """Vehicles at camera frames: frame index (P,), corners (P, 8, 3) local, ground distance (P,) m from
    the camera, class (P,), owner (P,) vehicle index (0 = the calibration vehicle when present)."""

    frame: IntArray
    corners: FloatArray
    distance: FloatArray
    cls: IntArray
    owner: IntArray


@dataclass(frozen=True, eq=False)
class RenderedFrames:
    """One camera's detections: per frame the boxes (K, 4), classes (K,), scores (K,) and the row index of
    the calibration vehicle's box (-1: not detected); `calib_detectable` (F,) says whether the vehicle
    would have been detectable (projectable, mostly inside, big enough) before occlusion and misses."""

    boxes: list[Boxes]
    classes: list[IntArray]
    scores: list[FloatArray]
    calib_row: IntArray
    calib_detectable: Mask


def _false_positives(
    frames: int, spec: DetectorSpec, camera: Lens, rng: np.random.Generator
) -> tuple[IntArray, Boxes]:
    """Short-lived spurious boxes: tracklets of 1-5 frames drifting a few pixels per frame."""
    mean_length = 2.5
    count = int(rng.poisson(spec.false_positives_per_frame * frames / mean_length))
    if count == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4))
    lengths = rng.integers(1, 6, size=count)
    start = rng.integers(0, frames, size=count)
    h = rng.uniform(18.0, 160.0, size=count)
    w = h * rng.uniform(0.7, 2.4, size=count)
    cu = rng.uniform(0.05, 0.95, size=count) * camera.width
    cv = rng.uniform(0.3, 0.95, size=count) * camera.height
    owner = np.repeat(np.arange(count), lengths)
    step = np.arange(len(owner)) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    drift = rng.normal(0.0, 4.0, size=(len(owner), 2)) * step[:, None]
    u, v = cu[owner] + drift[:, 0], cv[owner] + drift[:, 1]
    boxes = np.column_stack([u - w[owner] / 2, v - h[owner] / 2, u + w[owner] / 2, v + h[owner] / 2])
    frame = start[owner] + step
    return frame.astype(np.int64), boxes


def _finish_boxes(boxes: Boxes, camera: Lens) -> Boxes:
    """Ordered, clipped to the image, at least 1 px wide and tall (as a detector's output after NMS)."""
    x1 = np.clip(np.minimum(boxes[:, 0], boxes[:, 2]), 0.0, camera.width - 1.0)
    y1 = np.clip(np.minimum(boxes[:, 1], boxes[:, 3]), 0.0, camera.height - 1.0)
    x2 = np.clip(np.maximum(boxes[:, 0], boxes[:, 2]), x1 + 1.0, float(camera.width))
    y2 = np.clip(np.maximum(boxes[:, 1], boxes[:, 3]), y1 + 1.0, float(camera.height))
    return np.column_stack([x1, y1, x2, y2])


def _edge_noise(boxes: Boxes, spec: DetectorSpec, camera: Lens, rng: np.random.Generator) -> FloatArray:
    """Detector edge noise (N, 4): std grows with the box's size (floored at half the reference std), and
    an edge cut by the image border stays on the border, as a detector reports a cut-off vehicle."""
    size = np.column_stack([boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]])[:, [0, 1, 0, 1]]
    scale = np.maximum(0.5, size / spec.jitter_reference_px)
    noise = rng.normal(0.0, spec.box_jitter_px, size=boxes.shape) * scale
    on_border = np.column_stack(
        [boxes[:, 0] <= 0.0, boxes[:, 1] <= 0.0, boxes[:, 2] >= camera.width, boxes[:, 3] >= camera.height]
    )
    noise[on_border] = 0.0
    return np.asarray(noise, dtype=np.float64)


def render_frames(
    instances: Instances,
    frames: int,
    occluder_corners: FloatArray,
    R_cam_from_local: FloatArray,
    t_cam_from_local: FloatArray,
    camera: Lens,
    spec: DetectorSpec,
    rng: np.random.Generator,
) -> RenderedFrames:
    """The detector output of one camera for `frames` frames (see the module docstring for the rules)."""
    projected = project_boxes(instances.corners, R_cam_from_local, t_cam_from_local, camera)
    clipped = projected.clipped
    width, height = clipped[:, 2] - clipped[:, 0], clipped[:, 3] - clipped[:, 1]
    detectable = (
        projected.projectable
        & (projected.inside_fraction >= 1.0 - spec.max_outside_fraction)
        & (height >= spec.min_box_height_px)
        & (width >= spec.min_box_width_px)
    )
    rows = np.flatnonzero(detectable)
    is_calib = instances.owner == 0
    calib_detectable = np.zeros(frames, dtype=bool)
    calib_detectable[instances.frame[rows[is_calib[rows]]]] = True

    # Static occluders take part in every frame as boxes that hide but are never detected or hidden.
    occ = project_boxes(occluder_corners.reshape(-1, 8, 3), R_cam_from_local, t_cam_from_local, camera)
    occ_ok = np.flatnonzero(occ.projectable & (occ.inside_fraction > 0.0))
    camera_xy = (-R_cam_from_local.T @ t_cam_from_local)[:2]
    occ_distance = np.hypot(*(occluder_corners.reshape(-1, 8, 3)[occ_ok, :4, :2].mean(axis=1) - camera_xy).T)
    n_occ = len(occ_ok)
    frame = np.concatenate([instances.frame[rows], np.repeat(np.arange(frames), n_occ)])
    boxes = np.concatenate([clipped[rows], np.tile(occ.clipped[occ_ok], (frames, 1))])
    distance = np.concatenate([instances.distance[rows], np.tile(occ_distance, frames)])
    is_target = np.concatenate([np.ones(len(rows), bool), np.zeros(frames * n_occ, bool)])
    hidden, visible = hidden_fractions(frame, boxes, distance, is_target, grid=spec.occlusion_grid)
    hidden, visible = hidden[: len(rows)], visible[: len(rows)]
    keep = hidden <= spec.max_hidden_fraction
    rows, hidden = rows[keep], hidden[keep]
    det_boxes = visible[keep] if spec.visible_part_boxes else clipped[rows]

    box_height = det_boxes[:, 3] - det_boxes[:, 1]
    small = np.clip(1.0 - (box_height - spec.min_box_height_px) / (2.0 * spec.min_box_height_px), 0.0, 1.0)
    if spec.miss_rate > 0:
        # Misses are likelier for small and partly hidden vehicles.
        p_miss = np.clip(spec.miss_rate * (1.0 + 2.0 * hidden + 2.0 * small), 0.0, 0.9)
        found = rng.random(len(rows)) >= p_miss
        rows, hidden, small, det_boxes = rows[found], hidden[found], small[found], det_boxes[found]
    if spec.box_jitter_px > 0:
        det_boxes = det_boxes + _edge_noise(det_boxes, spec, camera, rng)
    det_boxes = _finish_boxes(det_boxes, camera)
    cls = instances.cls[rows].copy()
    if spec.class_confusion > 0:
        wrong = rng.random(len(rows)) < spec.class_confusion
        cls[wrong] = rng.choice(CLASS_CHOICES, size=int(wrong.sum()))
    score = 0.95 - 0.4 * hidden - 0.25 * small
    if spec.box_jitter_px > 0:
        score = score + rng.normal(0.0, 0.04, size=len(score))
    score = np.clip(score, 0.3, 0.99)

    fp_frame, fp_boxes = _false_positives(frames, spec, camera, rng)
    in_range = fp_frame < frames
    fp_frame, fp_boxes = fp_frame[in_range], _finish_boxes(fp_boxes[in_range], camera)
    fp_cls = np.where(rng.random(len(fp_frame)) < 0.85, 4, rng.choice(CLASS_CHOICES, size=len(fp_frame)))
    fp_score = rng.uniform(0.25, 0.6, size=len(fp_frame))

    all_frame = np.concatenate([instances.frame[rows], fp_frame])
    all_boxes = np.concatenate([det_boxes, fp_boxes])
    all_cls = np.concatenate([cls, fp_cls]).astype(np.int64)
    all_score = np.concatenate([score, fp_score])
    all_calib = np.concatenate([is_calib[rows], np.zeros(len(fp_frame), bool)])
    # A detector lists boxes in no particular order: shuffle within each frame.
    order = np.lexsort((rng.random(len(all_frame)), all_frame))
    all_frame, all_boxes, all_cls = all_frame[order], all_boxes[order], all_cls[order]
    all_score, all_calib = all_score[order], all_calib[order]
    bounds = np.searchsorted(all_frame, np.arange(frames + 1))
    calib_row = np.full(frames, -1, dtype=np.int64)
    calib_positions = np.flatnonzero(all_calib)
    calib_row[all_frame[calib_positions]] = calib_positions - bounds[all_frame[calib_positions]]
    return RenderedFrames(
        boxes=[all_boxes[bounds[f] : bounds[f + 1]] for f in range(frames)],
        classes=[all_cls[bounds[f] : bounds[f + 1]] for f in range(frames)],
        scores=[all_score[bounds[f] : bounds[f + 1]] for f in range(frames)],
        calib_row=calib_row,
        calib_detectable=calib_detectable,
    )
