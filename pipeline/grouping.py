"""Hypothesis grouping and filtering (paper Sec. III-E): three similarity scores -> graph -> DBSCAN.

Input: the `HypothesisSet` of stage 3, the `MatchedTrack` each hypothesis came from, every camera frame's
boxes. For each ordered pair (i, j) the vehicle positions of h_i's track are projected with h_j's pose:
r_out = share outside the image, r_ov = share on a box detected in that same frame, and r_sim compares the
rotations. Pairs passing all three in both directions, from tracks not seen at the same time, are edges;
isolated hypotheses are discarded; each connected component is clustered by camera position with
DBSCAN. Output: groups, the score matrices, and a reason for every hypothesis left out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from pipeline.arrays import BoolArray, Boxes, FloatArray, IntArray, Points3, Vec3, check_shape
from pipeline.association import MatchedTrack
from pipeline.camera import CameraModel, project_points_cam, undistort_pixels
from pipeline.errors import InputError
from pipeline.hypotheses import Hypothesis, HypothesisSet
from pipeline.stage import Reason
from pipeline.tracking import FrameBoxes
from pipeline.vehicle import body_centres
from schemas.common import VehicleProfile


@dataclass(frozen=True, slots=True)
class GroupingParams:
    """Similarity thresholds and DBSCAN settings of paper III-E (the paper gives no values).

    Two hypotheses of the calibration vehicle put each other's positions inside the image (r_out ~ 0)
    and onto the vehicle's own box (r_ov ~ 1: the projected body centre lies inside the projected body's
    bounding box), so both thresholds can be tight. A car following the vehicle through the same pass
    is never linked to it (the tracks overlap in time); across passes, a gap that differs scores r_ov
    well below 0.8 (the mismatch puts the projected positions metres off any box). One following at the
    same gap on every pass is consistent with itself and forms its own group about a gap away, which
    DBSCAN keeps apart from the truth (see the tests); box centres cannot tell which of the two is right.
    """

    max_outlier_ratio: float = 0.2  # r_out(i, j) and r_out(j, i) at most this
    min_overlap_ratio: float = 0.8  # r_ov(i, j) and r_ov(j, i) at least this
    overlap_margin_px: float = 10.0  # k: a projected position within k px of a box (or inside) overlaps it
    # tr(R_j^T R_i) / 3 = (1 + 2 cos angle) / 3; 0.95 allows 22 deg, as in the reference toolbox: hypotheses
    # from single tracks are coarse and the overlap score does the fine separation.
    min_rotation_similarity: float = 0.95
    dbscan_eps_m: float = 8.0  # camera positions closer than this are neighbours (reference toolbox: 8 m)
    dbscan_min_samples: int = 2  # a group needs two traversals (paper III-B)


@dataclass(frozen=True, slots=True)
class HypothesisGroup:
    """Similar hypotheses: track ids sorted; mean camera centre (3,) m local; mean pairwise min(r_ov);
    correspondences: the members' inlier rows (`Hypothesis.inliers`) summed."""

    track_ids: tuple[int, ...]
    camera_centre: Vec3
    mean_overlap_ratio: float
    correspondences: int = 0


@dataclass(frozen=True, slots=True)
class GroupingResult:
    """Groups (most members first, then most correspondences, then highest mean overlap), reasons for
    the hypotheses left out, and the (H, H) scores.

    r_out[i, j], r_ov[i, j]: h_i's vehicle positions scored with h_j's pose; r_sim symmetric; rows and
    columns in the order of `track_ids` (the hypotheses' order).
    """

    groups: tuple[HypothesisGroup, ...]
    discarded: Mapping[int, Reason]  # track_id -> reason
    r_out: FloatArray
    r_ov: FloatArray
    r_sim: FloatArray
    track_ids: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class _TrackView:
    """h_i's vehicle positions (N, 3) local and the boxes of each row's frame (N, B, 4) px, NaN padded."""

    positions: Points3
    frame_boxes: FloatArray


def group_hypotheses(
    hypotheses: HypothesisSet,
    tracks: Mapping[int, MatchedTrack],
    frames: Sequence[FrameBoxes],
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: GroupingParams,
) -> GroupingResult:
    """Score every pair of hypotheses, build the similarity graph, cluster it (paper III-E).

    Vehicle positions are body-box centres (local frame, m) at h_i's matched stamps (camera clock);
    boxes (px) are all boxes of the camera frame with that stamp. Every hypothesis ends up either in a
    group or in `discarded` with a reason. Beyond the paper: hypotheses whose tracks overlap in time are
    never linked (`_simultaneous`), and a DBSCAN cluster is split into its similarity-linked pieces
    (`_cluster_component`). Cost: H projections of every track, vectorised per track.
    """
    items = hypotheses.hypotheses
    track_ids = tuple(h.track_id for h in items)
    count = len(items)
    if count == 0:
        empty = np.zeros((0, 0))
        return GroupingResult((), {}, empty, empty.copy(), empty.copy(), ())
    R_all = np.stack([h.R_cam_from_local for h in items])
    t_all = np.stack([h.t_cam_from_local for h in items])
    check_shape(R_all, "H,3,3", name="hypothesis rotations")
    check_shape(t_all, "H,3", name="hypothesis translations")

    boxes_by_stamp = {frame.stamp_ns: frame.boxes for frame in frames}
    max_r2 = _max_normalized_radius2(camera)
    r_out = np.zeros((count, count))
    r_ov = np.zeros((count, count))
    for i, hypothesis in enumerate(items):
        track = tracks.get(hypothesis.track_id)
        if track is None:
            raise InputError("tracks", f"no MatchedTrack for hypothesis track_id {hypothesis.track_id}")
        view = _track_view(track, boxes_by_stamp, vehicle)
        r_out[i], r_ov[i] = _scores_against_all(view, R_all, t_all, camera, max_r2, params.overlap_margin_px)
    # tr(R_j^T R_i) = sum of the element-wise product; symmetric in i and j.
    r_sim = np.einsum("iab,jab->ij", R_all, R_all) / 3.0

    simultaneous = _simultaneous(items, tracks)
    # Symmetrised: an edge needs both directions to pass (h_i explains h_j's data and vice versa).
    worst_out, worst_ov = np.maximum(r_out, r_out.T), np.minimum(r_ov, r_ov.T)
    is_edge = (
        (worst_out <= params.max_outlier_ratio)
        & (worst_ov >= params.min_overlap_ratio)
        & (r_sim >= params.min_rotation_similarity)
        & ~simultaneous
    )
    np.fill_diagonal(is_edge, False)

    centres = np.stack([h.camera_centre for h in items])
    discarded: dict[int, Reason] = {}
    member_sets: list[list[int]] = []
    for isolated in np.flatnonzero(~is_edge.any(axis=1)):
        i = int(isolated)
        closest = _closest_partner(i, worst_out, worst_ov, r_sim, simultaneous, track_ids)
        discarded[track_ids[i]] = Reason("isolated", "isolated: no similar hypothesis", detail=closest)
    _, component = connected_components(csr_matrix(is_edge), directed=False)
    for label in np.unique(component):
        members = np.flatnonzero(component == label)
        if len(members) < 2:
            continue  # isolated, reported above
        member_sets.extend(_cluster_component(members, centres, is_edge, params, track_ids, discarded))

    groups = [_make_group(members, items, centres, r_ov, track_ids) for members in member_sets]
    groups.sort(key=_group_rank)
    return GroupingResult(tuple(groups), discarded, r_out, r_ov, r_sim, track_ids)


def _simultaneous(items: Sequence[Hypothesis], tracks: Mapping[int, MatchedTrack]) -> BoolArray:
    """(H, H) True where two hypotheses' tracks overlap in time.

    The calibration vehicle is one box at a time, so of two tracks seen at the same time at most one is
    it: such a pair is never an edge. This is how we use the paper's requirement (III-B) that the
    vehicle is out of view between traversals: similar hypotheses must come from separate traversals.
    It cuts the strongest distractor, a car following the vehicle through the same pass, whose pose is
    the truth shifted by the gap and otherwise scores r_out ~ gap / view length against it.
    """
    spans = [tracks[h.track_id].stamps for h in items]
    # An empty track (hand-built input) gets an empty interval: first > last overlaps nothing.
    first = np.array([int(s.min()) if len(s) else np.iinfo(np.int64).max for s in spans], dtype=np.int64)
    last = np.array([int(s.max()) if len(s) else np.iinfo(np.int64).min for s in spans], dtype=np.int64)
    return np.asarray(
        np.minimum(last[:, None], last[None, :]) >= np.maximum(first[:, None], first[None, :]), dtype=bool
    )


def _track_view(
    track: MatchedTrack, boxes_by_stamp: Mapping[int, Boxes], vehicle: VehicleProfile
) -> _TrackView:
    positions = body_centres(track.poses, vehicle)
    per_row = [boxes_by_stamp.get(int(stamp), np.zeros((0, 4))) for stamp in track.stamps]
    width = max((len(b) for b in per_row), default=0)
    frame_boxes = np.full((len(per_row), max(width, 1), 4), np.nan)
    for row, boxes in enumerate(per_row):
        frame_boxes[row, : len(boxes)] = boxes
    return _TrackView(positions, frame_boxes)


def _max_normalized_radius2(camera: CameraModel) -> float:
    """Largest squared normalised radius of the image's border, sampled along its four edges.

    Beyond the image the distortion polynomial may fold far-off points back into it (k1 < 0 at large
    radii); points farther out than the border's largest radius count as outside whatever pixel they map to.
    """
    w, h = float(camera.width), float(camera.height)
    s = np.linspace(0.0, 1.0, 33)
    border = np.concatenate(
        [
            np.column_stack([s * w, np.zeros_like(s)]),
            np.column_stack([s * w, np.full_like(s, h)]),
            np.column_stack([np.zeros_like(s), s * h]),
            np.column_stack([np.full_like(s, w), s * h]),
        ]
    )
    xy = undistort_pixels(border, camera)
    # 5 % slack: the sampled border can miss the true maximum between samples.
    return float(np.max(np.sum(xy * xy, axis=1))) * 1.05


def _scores_against_all(
    view: _TrackView,
    R_all: FloatArray,
    t_all: FloatArray,
    camera: CameraModel,
    max_r2: float,
    margin_px: float,
) -> tuple[FloatArray, FloatArray]:
    """r_out and r_ov (H,) of one track's positions under all H poses at once."""
    count, rows = len(R_all), len(view.positions)
    if rows == 0:
        return np.ones(count), np.zeros(count)
    # (H, N, 3): "hab,nb->hna" contracted in the order einsum runs fast and transposed (the same values).
    rotated = np.einsum("hab,nb->han", R_all, view.positions).transpose(0, 2, 1)
    points_cam = np.ascontiguousarray(rotated + t_all[:, None, :])
    depth = points_cam[..., 2]
    in_front = depth > 1e-6
    safe = points_cam.reshape(-1, 3).copy()
    safe[~in_front.reshape(-1), 2] = 1.0  # projected anyway, then ignored
    normalized = safe[:, :2] / safe[:, 2:3]
    in_lens = (np.sum(normalized * normalized, axis=1) <= max_r2).reshape(count, rows)
    pixels = project_points_cam(safe, camera).reshape(count, rows, 2)
    u, v = pixels[..., 0], pixels[..., 1]
    valid = in_front & in_lens
    inside = valid & (u >= 0.0) & (u <= camera.width) & (v >= 0.0) & (v <= camera.height)

    # Distance (px) from each projected position to each box of its own frame: 0 inside the box. Only
    # positions within the margin of their frame's boxes' extent can be near one, so the (M, B) distances
    # are computed for those alone: under another track's pose most positions land away from every box
    # (the stage took 0.94 s instead of 0.54 s on dense-traffic with all H x N x B of them).
    # fmin / fmax skip the NaN padding; a frame without boxes gets a NaN extent, which excludes its row.
    lower = np.fmin.reduce(view.frame_boxes[..., :2], axis=1) - margin_px  # (N, 2)
    upper = np.fmax.reduce(view.frame_boxes[..., 2:], axis=1) + margin_px
    candidate = valid & (u >= lower[:, 0]) & (v >= lower[:, 1]) & (u <= upper[:, 0]) & (v <= upper[:, 1])
    pose_index, row_index = np.nonzero(candidate)
    boxes = view.frame_boxes[row_index]  # (M, B, 4), NaN padded
    u_c, v_c = u[pose_index, row_index, None], v[pose_index, row_index, None]
    du = np.maximum(np.maximum(boxes[..., 0] - u_c, u_c - boxes[..., 2]), 0.0)
    dv = np.maximum(np.maximum(boxes[..., 1] - v_c, v_c - boxes[..., 3]), 0.0)
    near: BoolArray = np.zeros((count, rows), dtype=bool)
    near[pose_index, row_index] = np.any(np.hypot(du, dv) <= margin_px, axis=1)  # NaN compares False
    return 1.0 - inside.mean(axis=1), near.mean(axis=1)


def _closest_partner(
    i: int,
    worst_out: FloatArray,
    worst_ov: FloatArray,
    r_sim: FloatArray,
    simultaneous: BoolArray,
    track_ids: tuple[int, ...],
) -> str:
    """' (closest: track 7 r_out 0.31, r_ov 0.55, r_sim 0.990)' by the symmetric overlap, or ''."""
    if len(track_ids) < 2:
        return ""
    overlap = worst_ov[i].copy()
    overlap[i] = -1.0
    j = int(np.argmax(overlap))
    when = ", seen at the same time" if simultaneous[i, j] else ""
    return (
        f" (closest: track {track_ids[j]} r_out {worst_out[i, j]:.2f}, r_ov {worst_ov[i, j]:.2f}, "
        f"r_sim {r_sim[i, j]:.3f}{when})"
    )


def _cluster_component(
    members: IntArray,
    centres: Points3,
    is_edge: BoolArray,
    params: GroupingParams,
    track_ids: tuple[int, ...],
    discarded: dict[int, Reason],
) -> list[list[int]]:
    """DBSCAN on the camera centres of one connected component (paper III-E), then each cluster split into
    its similarity-connected pieces.

    The split is ours: DBSCAN sees positions only, so two hypotheses of one component that never passed
    the scores together (e.g. followers at different gaps, each linked to the truth) could share a
    cluster merely by sitting a few metres apart. A group is kept only where similarity links it.
    """
    labels = dbscan_labels(centres[members], params.dbscan_eps_m, params.dbscan_min_samples)
    pieces: list[list[int]] = []
    for label in np.unique(labels):
        cluster = members[labels == label]
        if label == -1:
            for i in cluster:
                discarded[track_ids[i]] = Reason(
                    "dbscan_noise",
                    "DBSCAN noise: camera position more than {limit} m from the positions of similar "
                    "hypotheses",
                    "distance to similar hypotheses' camera positions",
                    limit=params.dbscan_eps_m,
                    unit="m",
                )
            continue
        _, piece_of = connected_components(csr_matrix(is_edge[np.ix_(cluster, cluster)]), directed=False)
        for piece in np.unique(piece_of):
            piece_members = cluster[piece_of == piece]
            if len(piece_members) >= 2:
                pieces.append([int(i) for i in piece_members])
            else:
                discarded[track_ids[piece_members[0]]] = Reason(
                    "alone_in_cluster",
                    "alone in its DBSCAN cluster: no similar hypothesis with a nearby camera position",
                )
    return pieces


def _group_rank(group: HypothesisGroup) -> tuple[int, int, float, tuple[int, ...]]:
    """Sort key: more members first, then more inlier correspondences, then higher mean overlap.

    Only an ordering for the next stage, which refines every group: a pair of unrelated tracks that
    happen to agree (seen while the vehicle passed the same far-off spot twice) can match the truth in
    size and overlap, and the truth's tracks are usually the longer ones.
    """
    return (-len(group.track_ids), -group.correspondences, -group.mean_overlap_ratio, group.track_ids)


def _make_group(
    members: list[int],
    items: Sequence[Hypothesis],
    centres: Points3,
    r_ov: FloatArray,
    track_ids: tuple[int, ...],
) -> HypothesisGroup:
    index = np.array(sorted(members, key=lambda i: track_ids[i]))
    overlap = np.minimum(r_ov, r_ov.T)[np.ix_(index, index)]
    off_diagonal = overlap[~np.eye(len(index), dtype=bool)]
    return HypothesisGroup(
        track_ids=tuple(track_ids[i] for i in index),
        camera_centre=centres[index].mean(axis=0),
        mean_overlap_ratio=float(off_diagonal.mean()) if off_diagonal.size else 0.0,
        correspondences=int(sum(int(items[i].inliers.sum()) for i in index)),
    )


def dbscan_labels(points: FloatArray, eps: float, min_samples: int) -> IntArray:
    """DBSCAN cluster labels (N,) of points (N, D), -1 for noise: scikit-learn's DBSCAN(eps, min_samples)
    with the Euclidean metric, label for label.

    Neighbours are the points within `eps` (inclusive, the point itself counted); a core point has at
    least `min_samples`. Clusters grow from the core points in index order and are numbered in that order;
    a border point (a neighbour of a core point, not core itself) joins the first cluster that reaches it.
    Written out (N is a few dozen camera positions) because importing scikit-learn costs more than the
    rest of a calibration's start-up.
    """
    points = np.asarray(points, dtype=np.float64)
    count = len(points)
    labels = np.full(count, -1, dtype=np.int64)
    if count == 0:
        return labels
    differences = points[:, None, :] - points[None, :, :]
    is_neighbour = np.einsum("ijk,ijk->ij", differences, differences) <= eps * eps
    is_core = is_neighbour.sum(axis=1) >= min_samples
    cluster = 0
    for seed in range(count):
        if labels[seed] != -1 or not is_core[seed]:
            continue
        labels[seed] = cluster
        stack = [seed]
        while stack:
            point = stack.pop()
            for neighbour in np.flatnonzero(is_neighbour[point]):
                if labels[neighbour] == -1:
                    labels[neighbour] = cluster
                    if is_core[neighbour]:
                        stack.append(int(neighbour))
        cluster += 1
    return labels
