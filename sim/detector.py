"""Simulated detector: vehicle bodies -> the boxes an RSU camera's detector reports, frame by frame.

A vehicle's box is the tight rectangle of its projected body (OpenCV lens model, with distortion): the
bounds of the projected vertices of its surface (a polyhedron's image is bounded by its vertices' images).
It is dropped when a vertex is behind the camera, when most of it lies outside the image, when it is too
small for a detector, or when most of it is hidden behind nearer vehicles or static occluders.

In the real world (`RealDetector` given) bodies are shapes, and the box is that of the *visible* outline:
the part of the body's silhouette (the convex hull of its projected vertices) that no nearer silhouette
covers and that lies inside the image, measured on a fine grid, with edges that nothing covers kept exact.
A real camera reads its rows out one after another (a rolling shutter): row v of a frame is exposed
v / height of the camera's readout time after the first, so each vertex is placed where the vehicle was when
the row it lands on was exposed (`exposed_points`; the ideal world's cameras read every row at once).
Then what a detector gets wrong: a per-camera bias (scale, per-edge offsets), edge jitter correlated along
each track (AR(1)), independent misses and misses in runs, wrong classes, two overlapping vehicles merged
into one box or one split into two for a few frames, and short-lived false positives.

In the ideal world (no `RealDetector`) boxes are the rectangles of cuboids, the hidden share is measured
against nearer boxes' rectangles, and the jitter is independent: the first simulator, reproduced exactly.
Random draws of the ideal world come from `rng` in its original order; everything the real world adds
draws from its own generator, so the ideal world's numbers do not move.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from sim.geometry import BoolArray, FloatArray, IntArray, attitude_matrices
from sim.lens import Lens
from sim.presets import DetectorSpec

Boxes = FloatArray  # (N, 4) x1, y1, x2, y2 pixels
Mask = BoolArray
CLASS_CHOICES = np.array([4, 5, 6, 7])


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
    return _clipped(raw, projectable, lens)


def _clipped(raw: Boxes, projectable: Mask, lens: Lens) -> ProjectedBoxes:
    """Raw boxes (P, 4) clipped to the image, with the share of each raw box inside it."""
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
    """Vehicles at camera frames: frame index (P,), footprint-centre poses (P, 6) local, the body (P,) as an
    index into the bodies' vertex arrays, ground distance (P,) m from the camera, class (P,), owner (P,)
    vehicle index (0 = the calibration vehicle when present). `poses` are at the exposure of the frame's
    first row; `late_poses` (P, 6), when the camera has a rolling shutter, one readout time later (at its
    last row)."""

    frame: IntArray
    poses: FloatArray
    body: IntArray
    distance: FloatArray
    cls: IntArray
    owner: IntArray
    late_poses: FloatArray | None = None

    def body_points(self, rows: IntArray, vertices: FloatArray) -> tuple[FloatArray, FloatArray | None]:
        """World points (n, K, 3) of one body's vertices at the given rows, at the first row's exposure
        and (None without a rolling shutter) at the last row's."""
        early = _placed(self.poses[rows], vertices)
        late = None if self.late_poses is None else _placed(self.late_poses[rows], vertices)
        return early, late


def _placed(poses: FloatArray, vertices: FloatArray) -> FloatArray:
    R = attitude_matrices(poses[:, 3], poses[:, 4], poses[:, 5])
    return np.asarray(np.einsum("nij,kj->nki", R, vertices) + poses[:, None, :3], dtype=np.float64)


def exposed_points(
    early: FloatArray,
    late: FloatArray | None,
    R_cam_from_local: FloatArray,
    t_cam_from_local: FloatArray,
    lens: Lens,
) -> FloatArray:
    """Rolling shutter: points (..., 3) where they were when the image row they land on was exposed.

    `early` is each point at the exposure of the frame's first row, `late` at its last row's (one readout
    time later; None: every row at once). A point on row v is at early + (v / height) (late - early): linear
    within the readout (tens of ms, over which a vehicle's motion is straight), with the row found by two
    fixed-point steps (the row moves by a few pixels between them). Points that do not project keep `early`.
    """
    if late is None:
        return early
    shape = early.shape
    start, step = early.reshape(-1, 3), (late - early).reshape(-1, 3)
    points = start
    for _ in range(2):
        pixels, ok = lens.project_cam(points @ R_cam_from_local.T + t_cam_from_local)
        share = np.where(ok, np.clip(np.nan_to_num(pixels[:, 1]) / lens.height, 0.0, 1.0), 0.0)
        points = start + share[:, None] * step
    return points.reshape(shape)


@dataclass(frozen=True, eq=False)
class RealDetector:
    """What the real world's detector adds, drawn once per camera: box scale (1 + bias) and per-edge pixel
    offsets (4,) x1, y1, x2, y2; `rng` draws everything else the real world adds."""

    scale: float
    edge_offsets_px: FloatArray
    rng: np.random.Generator

    @staticmethod
    def draw(spec: DetectorSpec, rng: np.random.Generator) -> RealDetector:
        scale = 1.0 + float(rng.uniform(-spec.scale_bias, spec.scale_bias))
        offsets = rng.normal(0.0, spec.edge_bias_px, size=4) if spec.edge_bias_px > 0 else np.zeros(4)
        return RealDetector(scale, np.asarray(offsets, dtype=np.float64), rng)


# Gross-error codes of the calibration vehicle's box in a frame (RenderedFrames.calib_gross).
GROSS_NONE, GROSS_MERGED, GROSS_SPLIT = 0, 1, 2


@dataclass(frozen=True, eq=False)
class RenderedFrames:
    """One camera's detections: per frame the boxes (K, 4), classes (K,), scores (K,) and the row index of
    the calibration vehicle's box (-1: not detected); `calib_detectable` (F,) says whether the vehicle
    would have been detectable (projectable, mostly inside, big enough) before occlusion and misses;
    `calib_visible_box` (F, 4) is the true box of its visible outline before the detector's errors (NaN
    where it was not detected) and `calib_gross` (F,) a GROSS_* code for its box."""

    boxes: list[Boxes]
    classes: list[IntArray]
    scores: list[FloatArray]
    calib_row: IntArray
    calib_detectable: Mask
    calib_visible_box: FloatArray
    calib_gross: IntArray


def _project_rows(
    rows: IntArray,
    instances: Instances,
    bodies: tuple[FloatArray, ...],
    R_cam_from_local: FloatArray,
    t_cam_from_local: FloatArray,
    lens: Lens,
) -> list[FloatArray]:
    """Projected vertices (K_b, 2) of each given instance row (rows already found projectable)."""
    pixels: list[FloatArray] = [np.zeros((0, 2))] * len(rows)
    body_of = instances.body[rows]
    for b in np.unique(body_of):
        sel = np.flatnonzero(body_of == b)
        vertices = bodies[int(b)]
        early, late = instances.body_points(rows[sel], vertices)
        world = exposed_points(early, late, R_cam_from_local, t_cam_from_local, lens)
        cam = world.reshape(-1, 3) @ R_cam_from_local.T + t_cam_from_local
        flat, _ = lens.project_cam(cam)
        px = flat.reshape(len(sel), len(vertices), 2)
        for n, index in enumerate(sel):
            pixels[index] = px[n]
    return pixels


def _raw_boxes(
    instances: Instances,
    bodies: tuple[FloatArray, ...],
    R_cam_from_local: FloatArray,
    t_cam_from_local: FloatArray,
    lens: Lens,
) -> ProjectedBoxes:
    """Boxes of every instance, body by body (bounded memory: one body's frames at a time)."""
    count = len(instances.frame)
    raw = np.full((count, 4), np.nan)
    projectable = np.zeros(count, dtype=bool)
    for b, vertices in enumerate(bodies):
        rows = np.flatnonzero(instances.body == b)
        if len(rows) == 0:
            continue
        early, late = instances.body_points(rows, vertices)
        points = exposed_points(early, late, R_cam_from_local, t_cam_from_local, lens)
        projected = project_boxes(points, R_cam_from_local, t_cam_from_local, lens)
        raw[rows] = projected.raw
        projectable[rows] = projected.projectable
    return _clipped(raw, projectable, lens)


def _hull(points: FloatArray) -> FloatArray:
    """Convex hull (M, 2) of image points, counter-clockwise in the image's (u right, v down) axes."""
    hull = cv2.convexHull(np.ascontiguousarray(points, dtype=np.float32), clockwise=False)
    return np.asarray(hull, dtype=np.float64).reshape(-1, 2)


def _inside_hull(hull: FloatArray, points: FloatArray) -> Mask:
    """Whether each point (N, 2) lies inside the convex polygon `hull` (M, 2), boundary included."""
    if len(hull) < 3:
        return np.zeros(len(points), dtype=bool)
    edge = np.roll(hull, -1, axis=0) - hull  # (M, 2)
    rel = points[:, None, :] - hull[None, :, :]  # (N, M, 2)
    cross = edge[None, :, 0] * rel[:, :, 1] - edge[None, :, 1] * rel[:, :, 0]
    return np.asarray(np.all(cross >= -1e-9, axis=1) | np.all(cross <= 1e-9, axis=1), dtype=np.bool_)


def _strictly_inside_hull(hull: FloatArray, points: FloatArray) -> Mask:
    """Whether each point (N, 2) lies inside the convex polygon `hull` (M, 2), its boundary excluded (a
    vertex on a nearer silhouette's edge is still seen)."""
    if len(hull) < 3:
        return np.zeros(len(points), dtype=bool)
    edge = np.roll(hull, -1, axis=0) - hull
    rel = points[:, None, :] - hull[None, :, :]
    cross = edge[None, :, 0] * rel[:, :, 1] - edge[None, :, 1] * rel[:, :, 0]
    return np.asarray(np.all(cross > 1e-9, axis=1) | np.all(cross < -1e-9, axis=1), dtype=np.bool_)


def _clip_hull_to_image(hull: FloatArray, lens: Lens) -> FloatArray | None:
    """Bounds [x1, y1, x2, y2] of the part of a convex silhouette inside the image (None: nothing)."""
    image = np.array([[0, 0], [lens.width, 0], [lens.width, lens.height], [0, lens.height]], np.float32)
    area, polygon = cv2.intersectConvexConvex(hull.astype(np.float32), image)
    if polygon is None or area <= 0:
        return None
    pts = polygon.reshape(-1, 2).astype(np.float64)
    return np.array([pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max()])


def _visible_outlines(
    frame: IntArray,
    boxes: Boxes,
    distance: FloatArray,
    hulls: list[FloatArray],
    n_targets: int,
    lens: Lens,
    grid: int,
) -> tuple[FloatArray, Boxes]:
    """The real world's occlusion: for each of the first `n_targets` rows, the share of its silhouette
    covered by nearer silhouettes of the same frame (vehicles and static occluders), and the box of what
    remains visible inside the image.

    `boxes` (P, 4) bound the silhouettes `hulls` (P of (M, 2)). The visible part's box bounds the hull
    vertices nothing covers (exact) and the uncovered cells of a grid x grid sample of the silhouette (an
    edge cut by a nearer silhouette is found to a cell)."""
    hidden = np.zeros(n_targets)
    visible = boxes[:n_targets].copy()
    pair_i, pair_j = [], []
    for i, j in _group_pairs(frame, 2_000_000):
        bi, bj = boxes[i], boxes[j]
        overlap = (np.minimum(bi[:, 2], bj[:, 2]) > np.maximum(bi[:, 0], bj[:, 0])) & (
            np.minimum(bi[:, 3], bj[:, 3]) > np.maximum(bi[:, 1], bj[:, 1])
        )
        keep = (i < n_targets) & (distance[j] < distance[i]) & overlap
        pair_i.append(i[keep])
        pair_j.append(j[keep])
    occluders_of: dict[int, list[int]] = {}
    if pair_i:
        for i, j in zip(np.concatenate(pair_i).tolist(), np.concatenate(pair_j).tolist(), strict=True):
            occluders_of.setdefault(i, []).append(j)
    cells = (np.arange(grid) + 0.5) / grid
    for target in range(n_targets):
        box = boxes[target]
        outside_image = box[0] < 0 or box[1] < 0 or box[2] > lens.width or box[3] > lens.height
        nearer = occluders_of.get(target, [])
        if not nearer and not outside_image:
            continue
        hull = hulls[target]
        in_image = box.copy()
        if outside_image:
            clipped = _clip_hull_to_image(hull, lens)
            if clipped is None:
                hidden[target] = 1.0
                continue
            in_image = clipped
        if not nearer:
            visible[target] = in_image
            continue
        w, h = box[2] - box[0], box[3] - box[1]
        uu, vv = np.meshgrid(box[0] + cells * w, box[1] + cells * h)
        samples = np.column_stack([uu.ravel(), vv.ravel()])
        inside = _inside_hull(hull, samples)
        inside &= (samples[:, 0] >= 0) & (samples[:, 0] <= lens.width)
        inside &= (samples[:, 1] >= 0) & (samples[:, 1] <= lens.height)
        covered = np.zeros(len(samples), dtype=bool)
        vertex_covered = np.zeros(len(hull), dtype=bool)
        for other in nearer:
            covered |= _inside_hull(hulls[other], samples)
            vertex_covered |= _strictly_inside_hull(hulls[other], hull)
        n_inside = int(inside.sum())
        if n_inside == 0:
            hidden[target] = 1.0
            continue
        free = inside & ~covered
        hidden[target] = 1.0 - free.sum() / n_inside
        if not free.any():
            continue
        cells_free = samples[free]
        half = 0.5 * np.array([w, h]) / grid
        corners = np.concatenate([cells_free - half, cells_free + half, hull[~vertex_covered]])
        # The visible part never reaches beyond the silhouette inside the image.
        visible[target] = np.array(
            [
                max(corners[:, 0].min(), in_image[0]),
                max(corners[:, 1].min(), in_image[1]),
                min(corners[:, 0].max(), in_image[2]),
                min(corners[:, 1].max(), in_image[3]),
            ]
        )
    return hidden, visible


def _track_order(owner: IntArray, frame: IntArray) -> list[IntArray]:
    """Row indices of each track (one vehicle's boxes), in frame order."""
    order = np.lexsort((frame, owner))
    bounds = np.flatnonzero(np.diff(owner[order])) + 1
    return [np.asarray(part, dtype=np.int64) for part in np.split(order, bounds) if len(part)]


def _correlate_along_tracks(noise: FloatArray, owner: IntArray, frame: IntArray, rho: float) -> FloatArray:
    """AR(1) along each track: e_k = rho^gap e_(k-1) + sqrt(1 - rho^(2 gap)) z_k, same marginal std as z."""
    out = noise.copy()
    for rows in _track_order(owner, frame):
        gaps = np.diff(frame[rows]).astype(np.float64)
        for n in range(1, len(rows)):
            a = rho ** gaps[n - 1]
            out[rows[n]] = a * out[rows[n - 1]] + math.sqrt(max(0.0, 1.0 - a * a)) * noise[rows[n]]
    return out


def _missed_in_runs(
    owner: IntArray, frame: IntArray, start_p: float, mean_frames: float, rng: np.random.Generator
) -> Mask:
    """Gilbert-Elliott misses per track: a run starts with `start_p` per frame and lasts ~ geometric with
    mean `mean_frames` frames."""
    missed = np.zeros(len(owner), dtype=bool)
    if start_p <= 0 or mean_frames <= 0:
        return missed
    stop_p = 1.0 / max(1.0, mean_frames)
    for rows in _track_order(owner, frame):
        draws = rng.random(len(rows))
        in_run = False
        for n, row in enumerate(rows):
            in_run = draws[n] >= stop_p if in_run else draws[n] < start_p
            missed[row] = in_run
    return missed


def _iou_pairs(frame: IntArray, boxes: Boxes, min_iou: float) -> tuple[IntArray, IntArray]:
    """Pairs (i < j) of boxes in the same frame overlapping with IoU >= min_iou."""
    out_i, out_j = [], []
    for i, j in _group_pairs(frame, 2_000_000):
        keep = i < j
        i, j = i[keep], j[keep]
        bi, bj = boxes[i], boxes[j]
        iw = np.clip(np.minimum(bi[:, 2], bj[:, 2]) - np.maximum(bi[:, 0], bj[:, 0]), 0, None)
        ih = np.clip(np.minimum(bi[:, 3], bj[:, 3]) - np.maximum(bi[:, 1], bj[:, 1]), 0, None)
        inter = iw * ih
        union = (bi[:, 2] - bi[:, 0]) * (bi[:, 3] - bi[:, 1]) + (bj[:, 2] - bj[:, 0]) * (bj[:, 3] - bj[:, 1])
        union = union - inter
        ok = inter >= min_iou * np.maximum(union, 1e-9)
        out_i.append(i[ok])
        out_j.append(j[ok])
    if not out_i:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    i_all, j_all = np.concatenate(out_i), np.concatenate(out_j)
    order = np.argsort(frame[i_all], kind="stable")
    return i_all[order], j_all[order]


@dataclass(frozen=True, eq=False)
class _Gross:
    """Boxes after gross errors: which input rows survive (merged rows vanish into their partner), the
    merged partner's union box replacing a survivor's, and extra split pieces appended."""

    keep: Mask
    boxes: Boxes
    gross: IntArray  # (N,) GROSS_* of each input row's box
    split_rows: IntArray  # (S,) input rows that were split: their second piece
    split_boxes: Boxes  # (S, 4)
    carries_calib: Mask  # (N,) the row's box is the calibration vehicle's (a merge passes it to the survivor)


def _gross_errors(
    frame: IntArray,
    owner: IntArray,
    distance: FloatArray,
    boxes: Boxes,
    is_calib: Mask,
    spec: DetectorSpec,
    rng: np.random.Generator,
) -> _Gross:
    """Two overlapping vehicles reported as one union box for 2-8 frames (a merge starts with
    `merge_rate` per overlapping pair and frame; the nearer one's row carries it), and one vehicle
    reported as two boxes for 1-4 frames (a split starts with `split_rate` per box), cut at 35-65 % of its
    longer side."""
    boxes = boxes.copy()
    keep = np.ones(len(boxes), dtype=bool)
    carries = is_calib.copy()
    gross = np.full(len(boxes), GROSS_NONE, dtype=np.int64)
    if spec.merge_rate > 0:
        pi, pj = _iou_pairs(frame, boxes, 0.15)
        active: dict[tuple[int, int], int] = {}  # (owner a, owner b) -> last frame of the merge
        draws = rng.random(len(pi))
        lengths = rng.integers(2, 9, size=len(pi))
        for n, (i, j) in enumerate(zip(pi.tolist(), pj.tolist(), strict=True)):
            if not (keep[i] and keep[j]):
                continue
            key = (int(min(owner[i], owner[j])), int(max(owner[i], owner[j])))
            until = active.get(key, -1)
            if frame[i] > until:
                if draws[n] >= spec.merge_rate:
                    continue
                until = int(frame[i]) + int(lengths[n]) - 1
                active[key] = until
            near, far = (i, j) if distance[i] <= distance[j] else (j, i)
            boxes[near] = [
                min(boxes[i, 0], boxes[j, 0]),
                min(boxes[i, 1], boxes[j, 1]),
                max(boxes[i, 2], boxes[j, 2]),
                max(boxes[i, 3], boxes[j, 3]),
            ]
            keep[far] = False
            carries[near] |= carries[far]
            carries[far] = False
            gross[near] = gross[far] = GROSS_MERGED
    split_rows: list[int] = []
    split_boxes: list[list[float]] = []
    if spec.split_rate > 0:
        for rows in _track_order(owner, frame):
            draws = rng.random(len(rows))
            remaining = 0
            for n, row in enumerate(rows):
                if remaining == 0 and draws[n] < spec.split_rate:
                    remaining = int(rng.integers(1, 5))
                if remaining == 0 or not keep[row] or gross[row] != GROSS_NONE:
                    remaining = max(0, remaining - 1)
                    continue
                remaining -= 1
                x1, y1, x2, y2 = boxes[row]
                cut = float(rng.uniform(0.35, 0.65))
                if x2 - x1 >= y2 - y1:
                    xm = x1 + cut * (x2 - x1)
                    boxes[row] = [x1, y1, xm, y2]
                    split_boxes.append([xm, y1, x2, y2])
                else:
                    ym = y1 + cut * (y2 - y1)
                    boxes[row] = [x1, y1, x2, ym]
                    split_boxes.append([x1, ym, x2, y2])
                split_rows.append(row)
                gross[row] = GROSS_SPLIT
    return _Gross(
        keep,
        boxes,
        gross,
        np.asarray(split_rows, dtype=np.int64),
        np.asarray(split_boxes, dtype=np.float64).reshape(-1, 4),
        carries,
    )


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


def _edge_noise(boxes: Boxes, draws: FloatArray, spec: DetectorSpec, camera: Lens) -> FloatArray:
    """Detector edge noise (N, 4) from `draws` (N, 4) of the reference std: the std grows with the box's
    size (floored at half the reference std), and an edge cut by the image border stays on the border, as
    a detector reports a cut-off vehicle."""
    size = np.column_stack([boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]])[:, [0, 1, 0, 1]]
    scale = np.maximum(0.5, size / spec.jitter_reference_px)
    noise = draws * scale
    on_border = np.column_stack(
        [boxes[:, 0] <= 0.0, boxes[:, 1] <= 0.0, boxes[:, 2] >= camera.width, boxes[:, 3] >= camera.height]
    )
    noise[on_border] = 0.0
    return np.asarray(noise, dtype=np.float64)


def _biased(boxes: Boxes, real: RealDetector, camera: Lens) -> Boxes:
    """The camera's systematic box error: scaled about the centre, then each edge shifted; an edge cut by
    the image border stays on it."""
    centre = 0.5 * (boxes[:, :2] + boxes[:, 2:])
    half = 0.5 * (boxes[:, 2:] - boxes[:, :2]) * real.scale
    out = np.column_stack([centre - half, centre + half]) + real.edge_offsets_px
    on_border = np.column_stack(
        [boxes[:, 0] <= 0.0, boxes[:, 1] <= 0.0, boxes[:, 2] >= camera.width, boxes[:, 3] >= camera.height]
    )
    return np.asarray(np.where(on_border, boxes, out), dtype=np.float64)


def render_frames(
    instances: Instances,
    bodies: tuple[FloatArray, ...],
    frames: int,
    occluder_corners: FloatArray,
    R_cam_from_local: FloatArray,
    t_cam_from_local: FloatArray,
    camera: Lens,
    spec: DetectorSpec,
    rng: np.random.Generator,
    real: RealDetector | None = None,
) -> RenderedFrames:
    """The detector output of one camera for `frames` frames (see the module docstring for the rules).

    `bodies` are vertex arrays (K_b, 3) relative to the footprint centre of each body (x forward, y left,
    z up); `real` switches on the real world's detector (None: the ideal world, reproduced exactly)."""
    projected = _raw_boxes(instances, bodies, R_cam_from_local, t_cam_from_local, camera)
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

    # Static occluders take part in every frame: they hide vehicles but are never detected or hidden.
    occ = project_boxes(occluder_corners.reshape(-1, 8, 3), R_cam_from_local, t_cam_from_local, camera)
    occ_ok = np.flatnonzero(occ.projectable & (occ.inside_fraction > 0.0))
    camera_xy = (-R_cam_from_local.T @ t_cam_from_local)[:2]
    occ_distance = np.hypot(*(occluder_corners.reshape(-1, 8, 3)[occ_ok, :4, :2].mean(axis=1) - camera_xy).T)
    n_occ = len(occ_ok)
    frame = np.concatenate([instances.frame[rows], np.repeat(np.arange(frames), n_occ)])
    distance = np.concatenate([instances.distance[rows], np.tile(occ_distance, frames)])
    if real is None:
        boxes = np.concatenate([clipped[rows], np.tile(occ.clipped[occ_ok], (frames, 1))])
        is_target = np.concatenate([np.ones(len(rows), bool), np.zeros(frames * n_occ, bool)])
        hidden, visible = hidden_fractions(frame, boxes, distance, is_target, grid=spec.occlusion_grid)
        hidden, visible = hidden[: len(rows)], visible[: len(rows)]
    else:
        pixels = _project_rows(rows, instances, bodies, R_cam_from_local, t_cam_from_local, camera)
        occ_points = occluder_corners.reshape(-1, 8, 3)[occ_ok].reshape(-1, 3)
        occ_pixels, _ = camera.project_cam(occ_points @ R_cam_from_local.T + t_cam_from_local)
        occ_hulls = [_hull(p) for p in occ_pixels.reshape(-1, 8, 2)]
        hulls = [_hull(p) for p in pixels] + occ_hulls * frames
        boxes = np.concatenate([projected.raw[rows], np.tile(occ.raw[occ_ok], (frames, 1))])
        hidden, visible = _visible_outlines(
            frame, boxes, distance, hulls, len(rows), camera, max(spec.occlusion_grid, 24)
        )
    keep = hidden <= spec.max_hidden_fraction
    rows, hidden = rows[keep], hidden[keep]
    det_boxes = visible[keep] if spec.visible_part_boxes else clipped[rows]
    true_boxes = det_boxes.copy()

    box_height = det_boxes[:, 3] - det_boxes[:, 1]
    small = np.clip(1.0 - (box_height - spec.min_box_height_px) / (2.0 * spec.min_box_height_px), 0.0, 1.0)
    found = np.ones(len(rows), dtype=bool)
    if spec.miss_rate > 0:
        # Misses are likelier for small and partly hidden vehicles.
        p_miss = np.clip(spec.miss_rate * (1.0 + 2.0 * hidden + 2.0 * small), 0.0, 0.9)
        found = rng.random(len(rows)) >= p_miss
    if real is not None:
        owner, frame_of = instances.owner[rows], instances.frame[rows]
        found &= ~_missed_in_runs(owner, frame_of, spec.miss_run_start, spec.miss_run_frames, real.rng)
    rows, hidden, small, det_boxes, true_boxes = (
        rows[found],
        hidden[found],
        small[found],
        det_boxes[found],
        true_boxes[found],
    )
    if spec.box_jitter_px > 0:
        unit = rng.normal(0.0, spec.box_jitter_px, size=det_boxes.shape)
        if real is not None and spec.jitter_ar1 > 0:
            unit = _correlate_along_tracks(
                unit, instances.owner[rows], instances.frame[rows], spec.jitter_ar1
            )
        det_boxes = det_boxes + _edge_noise(det_boxes, unit, spec, camera)
    if real is not None:
        det_boxes = _biased(det_boxes, real, camera)
    det_boxes = _finish_boxes(det_boxes, camera)
    cls = instances.cls[rows].copy()
    if spec.class_confusion > 0:
        wrong = rng.random(len(rows)) < spec.class_confusion
        cls[wrong] = rng.choice(CLASS_CHOICES, size=int(wrong.sum()))
    score = 0.95 - 0.4 * hidden - 0.25 * small
    if spec.box_jitter_px > 0:
        score = score + rng.normal(0.0, 0.04, size=len(score))
    score = np.clip(score, 0.3, 0.99)
    det_frame = instances.frame[rows]
    det_calib = is_calib[rows]
    # The truth: the calibration vehicle's visible-outline box before the detector's errors, per frame.
    calib_true = np.full((frames, 4), np.nan)
    calib_true[det_frame[det_calib]] = true_boxes[det_calib]
    calib_gross = np.zeros(frames, dtype=np.int64)
    if real is not None:
        gross = _gross_errors(
            det_frame, instances.owner[rows], instances.distance[rows], det_boxes, det_calib, spec, real.rng
        )
        calib_gross[det_frame[det_calib]] = gross.gross[det_calib]
        extra = gross.split_rows
        det_frame = np.concatenate([det_frame[gross.keep], det_frame[extra]])
        det_boxes = np.concatenate(
            [_finish_boxes(gross.boxes[gross.keep], camera), _finish_boxes(gross.split_boxes, camera)]
        )
        cls = np.concatenate([cls[gross.keep], cls[extra]])
        score = np.concatenate([score[gross.keep], np.clip(score[extra] - 0.2, 0.3, 0.99)])
        det_calib = np.concatenate([gross.carries_calib[gross.keep], np.zeros(len(extra), bool)])

    fp_frame, fp_boxes = _false_positives(frames, spec, camera, rng)
    in_range = fp_frame < frames
    fp_frame, fp_boxes = fp_frame[in_range], _finish_boxes(fp_boxes[in_range], camera)
    fp_cls = np.where(rng.random(len(fp_frame)) < 0.85, 4, rng.choice(CLASS_CHOICES, size=len(fp_frame)))
    fp_score = rng.uniform(0.25, 0.6, size=len(fp_frame))

    all_frame = np.concatenate([det_frame, fp_frame])
    all_boxes = np.concatenate([det_boxes, fp_boxes])
    all_cls = np.concatenate([cls, fp_cls]).astype(np.int64)
    all_score = np.concatenate([score, fp_score])
    all_calib = np.concatenate([det_calib, np.zeros(len(fp_frame), bool)])
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
        calib_visible_box=calib_true,
        calib_gross=calib_gross,
    )
