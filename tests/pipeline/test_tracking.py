"""Image tracking (paper Sec. III-C, Eq. 2): IoU/DIoU, cost rules, identities, coasting, border boxes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.arrays import FloatArray
from pipeline.camera import CameraModel
from pipeline.errors import InputError, ShapeError
from pipeline.tracking import (
    FrameBoxes,
    ImageTrack,
    TrackingParams,
    TrackSet,
    frames_from_detections,
    overlap_terms,
    track_boxes,
)
from schemas.common import Box, CameraIntrinsics
from schemas.messages import DetectionFrame

WIDTH, HEIGHT = 1920, 1200
T0_NS = 1_700_000_000_000_000_000
FRAME_NS = 100_000_000  # 10 fps


def _box(cx: float, cy: float, w: float, h: float) -> list[float]:
    return [cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2]


def _frames(per_frame: list[list[list[float]]], stamps_ns: list[int] | None = None) -> list[FrameBoxes]:
    """FrameBoxes from per-frame box lists (class = 4 + index in frame, to follow boxes through tracking)."""
    if stamps_ns is None:
        stamps_ns = [T0_NS + k * FRAME_NS for k in range(len(per_frame))]
    return [
        FrameBoxes(
            stamp_ns=stamp,
            boxes=np.array(boxes, dtype=np.float64).reshape(-1, 4),
            classes=np.arange(4, 4 + len(boxes), dtype=np.int64),
        )
        for stamp, boxes in zip(stamps_ns, per_frame, strict=True)
    ]


def _track(frames: list[FrameBoxes], params: TrackingParams | None = None) -> TrackSet:
    return track_boxes(frames, WIDTH, HEIGHT, params or TrackingParams())


def _centres_x(track: ImageTrack) -> FloatArray:
    return 0.5 * (track.boxes[:, 0] + track.boxes[:, 2])


# ---------------------------------------------------------------------------------------------- IoU, DIoU


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return overlap_terms(a, b)[0]


def diou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    iou, penalty = overlap_terms(a, b)
    return iou - penalty


def test_diou_hand_values() -> None:
    a = np.array([[0.0, 0.0, 2.0, 2.0]])
    b = np.array([[1.0, 0.0, 3.0, 2.0]])
    # Intersection 2, union 6 -> IoU 1/3; centres (1, 1), (2, 1) -> d^2 = 1; enclosing 3 x 2 -> c^2 = 13.
    assert iou_matrix(a, b)[0, 0] == pytest.approx(1.0 / 3.0)
    assert diou_matrix(a, b)[0, 0] == pytest.approx(1.0 / 3.0 - 1.0 / 13.0)
    # Identical boxes: IoU = DIoU = 1 (cost 0).
    assert diou_matrix(a, a)[0, 0] == pytest.approx(1.0)
    # Disjoint and far apart: IoU 0, DIoU -d^2/c^2 = -100^2 / (101^2 + 1) close to -1.
    far = np.array([[100.0, 0.0, 101.0, 1.0]])
    unit = np.array([[0.0, 0.0, 1.0, 1.0]])
    assert iou_matrix(unit, far)[0, 0] == 0.0
    assert diou_matrix(unit, far)[0, 0] == pytest.approx(-(100.0**2) / (101.0**2 + 1.0))
    # A box inside another with the same centre: DIoU = IoU (no centre distance).
    inner = np.array([[0.5, 0.5, 1.5, 1.5]])
    assert diou_matrix(a, inner)[0, 0] == pytest.approx(0.25)


def test_iou_matrices_are_pairwise_with_shape_n_by_m() -> None:
    a = np.array([_box(10, 10, 4, 4), _box(50, 50, 10, 10), _box(11, 10, 4, 4)])
    b = np.array([_box(10, 10, 4, 4), _box(50, 52, 10, 10)])
    iou, diou = iou_matrix(a, b), diou_matrix(a, b)
    assert iou.shape == diou.shape == (3, 2)
    for i in range(3):
        for j in range(2):
            assert iou[i, j] == pytest.approx(iou_matrix(a[i : i + 1], b[j : j + 1])[0, 0])
    assert iou_matrix(np.empty((0, 4)), b).shape == (0, 2)
    assert diou_matrix(a, np.empty((0, 4))).shape == (3, 0)


def test_zero_area_boxes_give_zero_iou_not_nan() -> None:
    point = np.array([[5.0, 5.0, 5.0, 5.0]])
    assert iou_matrix(point, point)[0, 0] == 0.0
    assert diou_matrix(point, point)[0, 0] == 0.0


_boxes = st.builds(
    lambda x, y, w, h: [x, y, x + w, y + h],
    st.floats(-500, 500),
    st.floats(-500, 500),
    st.floats(0.5, 300),
    st.floats(0.5, 300),
)


@settings(max_examples=200, deadline=None)
@given(a=st.lists(_boxes, min_size=1, max_size=5), b=st.lists(_boxes, min_size=1, max_size=5))
def test_diou_range_and_symmetry(a: list[list[float]], b: list[list[float]]) -> None:
    boxes_a, boxes_b = np.array(a), np.array(b)
    iou, diou = iou_matrix(boxes_a, boxes_b), diou_matrix(boxes_a, boxes_b)
    assert np.all((iou >= 0.0) & (iou <= 1.0 + 1e-12))
    assert np.all((diou > -1.0) & (diou <= iou + 1e-12))
    cost = 1.0 - diou
    assert np.all((cost >= -1e-12) & (cost < 2.0))
    np.testing.assert_allclose(diou, diou_matrix(boxes_b, boxes_a).T, atol=1e-12)
    np.testing.assert_allclose(np.diag(diou_matrix(boxes_a, boxes_a)), 1.0, atol=1e-12)


# ------------------------------------------------------------------------------------------------- frames


def test_frames_from_detections_sorts_deduplicates_and_converts() -> None:
    def message(stamp: int, count: int) -> DetectionFrame:
        boxes = [Box(x1=10.0 * k, y1=1.0, x2=10.0 * k + 5, y2=9.0, cls=5 + k) for k in range(count)]
        return DetectionFrame(camera_id="cam", stamp_ns=stamp, boxes=boxes)

    frames = frames_from_detections(
        [message(T0_NS + 2, 1), message(T0_NS, 2), message(T0_NS + 2, 3), message(T0_NS + 1, 0)]
    )
    assert [f.stamp_ns for f in frames] == [T0_NS, T0_NS + 1, T0_NS + 2]
    np.testing.assert_array_equal(frames[0].boxes, [[0, 1, 5, 9], [10, 1, 15, 9]])
    np.testing.assert_array_equal(frames[0].classes, [5, 6])
    assert frames[1].boxes.shape == (0, 4) and frames[1].classes.shape == (0,)
    assert len(frames[2].boxes) == 1  # the first frame received at T0 + 2 wins
    assert frames[0].boxes.dtype == np.float64 and frames[0].classes.dtype == np.int64


def test_class_names_become_toolbox_ids() -> None:
    boxes = [
        Box(x1=0.0, y1=0.0, x2=1.0, y2=1.0, cls=cls)
        for cls in ("car", "Truck", "van", "bus", "motorcycle", 9)
    ]
    (frame,) = frames_from_detections([DetectionFrame(camera_id="cam", stamp_ns=T0_NS, boxes=boxes)])
    np.testing.assert_array_equal(frame.classes, [4, 5, 6, 7, -1, 9])


# ------------------------------------------------------------------------------------------- cost rules


def test_boxes_without_overlap_are_never_associated() -> None:
    # A lone box that jumps to a touching, non-overlapping position: IoU 0 -> cost 2 -> a new track, even
    # though the Hungarian algorithm pairs the only track with the only box.
    frames = _frames([[[100, 100, 200, 200]], [[200, 100, 300, 200]]])
    result = _track(frames)
    assert len(result.tracks) == 2
    # The same jump with the slightest overlap is associated.
    frames = _frames([[[100, 100, 200, 200]], [[199.5, 100, 299.5, 200]]])
    assert len(_track(frames).tracks) == 1


def test_pairs_assigned_at_cost_two_are_rejected() -> None:
    # Two tracks, two boxes; the cheapest assignment pairs A with its strongly overlapping box (cost ~0)
    # and leaves track B with a box it does not overlap (cost 2): that pair must not become an association.
    first = [_box(500, 500, 100, 100), _box(800, 500, 100, 100)]
    second = [_box(502, 500, 100, 100), _box(300, 500, 100, 100)]
    result = _track(_frames([first, second]))
    assert len(result.tracks) == 3
    lengths = sorted(len(t.stamps) for t in result.tracks)
    assert lengths == [1, 1, 2]


def test_hungarian_prefers_the_better_overlap() -> None:
    # Two overlapping candidates for one track: the closer box (higher DIoU) joins it.
    first = [_box(500, 500, 100, 100)]
    second = [_box(560, 500, 100, 100), _box(505, 500, 100, 100)]
    result = _track(_frames([first, second]))
    joined = next(t for t in result.tracks if len(t.stamps) == 2)
    np.testing.assert_array_equal(joined.boxes[1], second[1])


# ------------------------------------------------------------------------------------------- identities


@pytest.mark.parametrize("dy", [0.0, 15.0, 60.0])
@pytest.mark.parametrize("shuffle", [False, True])
def test_crossing_vehicles_keep_their_identities(dy: float, shuffle: bool) -> None:
    # Two cars in opposite directions pass each other in the image (fully overlapping when dy = 0).
    rng = np.random.default_rng(int(dy))
    per_frame = []
    for k in range(60):
        right = _box(300 + 22 * k, 600, 160, 110)
        left = _box(1600 - 21 * k, 600 + dy, 150, 100)
        boxes = [right, left]
        if shuffle and rng.random() < 0.5:
            boxes.reverse()
        per_frame.append(boxes)
    result = _track(_frames(per_frame))
    assert len(result.tracks) == 2
    for track in result.tracks:
        assert len(track.stamps) == 60
        steps = np.diff(_centres_x(track))
        assert np.all(steps > 0) or np.all(steps < 0)


def test_crossing_with_the_far_vehicle_hidden_keeps_identities() -> None:
    # While the near car covers the far one, the detector reports only the near box for 3 frames.
    per_frame = []
    for k in range(50):
        near = _box(300 + 25 * k, 650, 200, 140)
        far = _box(1500 - 25 * k, 600, 120, 80)
        hidden = abs(near[0] - far[0]) < 60
        per_frame.append([near] if hidden else [near, far])
    assert 1 <= sum(len(b) == 1 for b in per_frame) <= 5
    result = _track(_frames(per_frame))
    assert len(result.tracks) == 2
    for track in result.tracks:
        steps = np.diff(_centres_x(track))
        assert np.all(steps > 0) or np.all(steps < 0)
    assert sum(len(t.stamps) for t in result.tracks) == sum(len(b) for b in per_frame)


@pytest.mark.parametrize("missed", [1, 2, 3, 5])
def test_briefly_missed_vehicle_keeps_its_track(missed: int) -> None:
    # 40 px/frame with 100 px boxes: after 3 missed frames the last seen box is 160 px behind (no overlap),
    # so only the linear extrapolation can bridge the gap.
    all_boxes = [_box(300 + 40 * k, 500, 100, 80) for k in range(30)]
    per_frame = [[b] if not (10 <= k < 10 + missed) else [] for k, b in enumerate(all_boxes)]
    result = _track(_frames(per_frame))
    assert len(result.tracks) == 1
    track = result.tracks[0]
    # Extrapolated boxes are not in the output: exactly the real boxes, unchanged, at their stamps.
    seen = [k for k in range(30) if not (10 <= k < 10 + missed)]
    np.testing.assert_array_equal(track.stamps, [T0_NS + k * FRAME_NS for k in seen])
    np.testing.assert_array_equal(track.boxes, np.array(all_boxes)[seen])


def test_occlusion_beyond_the_coasting_limit_starts_a_new_track() -> None:
    all_boxes = [_box(300 + 10 * k, 500, 100, 80) for k in range(40)]
    params = TrackingParams(max_extrapolated_frames=5)
    for missed, expected_tracks in [(5, 1), (6, 2), (12, 2)]:
        per_frame = [[b] if not (10 <= k < 10 + missed) else [] for k, b in enumerate(all_boxes)]
        result = _track(_frames(per_frame), params)
        assert len(result.tracks) == expected_tracks, missed
    per_frame = [[b] if not (10 <= k < 16) else [] for k, b in enumerate(all_boxes)]
    first, second = _track(_frames(per_frame), params).tracks
    assert (first.track_id, second.track_id) == (0, 1)
    assert first.stamps[-1] < second.stamps[0]


def test_irregular_frame_spacing_uses_stamps_not_indices() -> None:
    # 500 px/s, 80 px wide boxes, 10 fps with +-10 ms jitter and two dropped frames (no message at all).
    # Across a dropped frame the box moves ~100 px, more than its width, so it only matches through a
    # velocity prediction that uses the elapsed time, not the frame count.
    rng = np.random.default_rng(5)
    times_s = [k * 0.1 + rng.uniform(-0.01, 0.01) for k in range(30) if k not in (8, 20)]
    stamps = [T0_NS + round(t * 1e9) for t in times_s]
    per_frame = [[_box(200 + 500 * t, 500, 80, 60)] for t in times_s]
    shifts = np.diff([b[0][0] for b in per_frame])
    assert shifts.max() > 80.0  # the last box before a dropped frame does not overlap the next one
    result = _track(_frames(per_frame, stamps))
    assert len(result.tracks) == 1
    assert len(result.tracks[0].stamps) == 28


def test_vehicle_stopping_and_starting_keeps_one_track() -> None:
    x = np.concatenate([300 + 30 * np.arange(10), np.full(20, 570.0), 570 + 30 * np.arange(1, 11)])
    per_frame = [[_box(float(cx), 500, 120, 90)] for cx in x]
    assert len(_track(_frames(per_frame)).tracks) == 1


# ----------------------------------------------------------------------------------------------- borders


def test_border_boxes_continue_the_track_but_are_not_output() -> None:
    # A car enters from the left edge: its first 3 boxes are clipped at x1 = 0 and growing.
    per_frame = []
    for k in range(20):
        x1, x2 = -150 + 40 * k, 40 * k
        per_frame.append([[max(x1, 0.0), 400.0, float(x2), 480.0]] if x2 > 0 else [])
    result = _track(_frames(per_frame))
    clipped = sum(1 for b in per_frame if b and b[0][0] <= 1.0)
    assert clipped == 3
    assert result.border_boxes_dropped == clipped
    assert len(result.tracks) == 1
    track = result.tracks[0]
    assert len(track.stamps) == sum(len(b) for b in per_frame) - clipped
    assert np.all(track.boxes[:, 0] > 1.0)


def test_border_margin_applies_to_every_edge() -> None:
    inside = [10.0, 10.0, 100.0, 100.0]
    touching = [
        [1.0, 10.0, 100.0, 100.0],  # left, within the 1 px margin
        [10.0, 0.5, 100.0, 100.0],  # top
        [1800.0, 10.0, WIDTH - 1.0, 100.0],  # right
        [10.0, 1100.0, 100.0, float(HEIGHT)],  # bottom
    ]
    per_frame = [[inside]] + [[box] for box in touching]
    stamps = [T0_NS + k * 10 * FRAME_NS for k in range(5)]  # far apart in time: separate tracks
    result = _track(_frames(per_frame, stamps), TrackingParams(max_extrapolated_frames=0))
    assert result.border_boxes_dropped == 4
    assert len(result.tracks) == 1  # tracks made only of border boxes are not output
    np.testing.assert_array_equal(result.tracks[0].boxes, [inside])
    wider = _track(_frames([[[5.0, 10.0, 100.0, 100.0]]]), TrackingParams(border_margin_px=8.0))
    assert wider.border_boxes_dropped == 1 and not wider.tracks


# ---------------------------------------------------------------------------------------- output contract


def test_busy_traffic_gives_one_pure_track_per_vehicle() -> None:
    # Four lanes of cars (two each way), 6 per lane, wrapping around the image; 1 px box noise. The class
    # id carries the true vehicle identity through the tracker.
    rng = np.random.default_rng(11)
    lanes = [(300.0, 25.0), (450.0, -30.0), (650.0, 35.0), (900.0, -20.0)]
    frames = []
    for k in range(200):
        boxes, identities = [], []
        for lane, (y, speed) in enumerate(lanes):
            for slot, start in enumerate(range(0, 2400, 400)):
                travelled = start + speed * k + 200.0
                cx = travelled % 2400.0 - 200.0
                box = np.clip(_box(cx, y, 120, 80), 0.0, [WIDTH, HEIGHT, WIDTH, HEIGHT])
                if box[2] - box[0] > 5:
                    boxes.append(box + rng.normal(0.0, 1.0, 4))
                    identities.append(1000 * (lane * 6 + slot) + int(travelled // 2400.0) + 100)
        frames.append(FrameBoxes(T0_NS + k * FRAME_NS, np.array(boxes), np.array(identities, dtype=np.int64)))
    result = _track(frames)
    assert [t.track_id for t in result.tracks] == list(range(len(result.tracks)))
    for track in result.tracks:
        assert len(track.stamps) >= 1
        assert np.all(np.diff(track.stamps) > 0)
        assert track.boxes.shape == (len(track.stamps), 4) and track.classes.shape == (len(track.stamps),)
        assert len(set(track.classes.tolist())) == 1  # pure: one vehicle per track
    total = sum(len(f.boxes) for f in frames)
    assert sum(len(t.stamps) for t in result.tracks) + result.border_boxes_dropped == total
    # Not fragmented: every vehicle seen away from the border is exactly one track.
    vehicles = {
        int(c)
        for f in frames
        for c, b in zip(f.classes, f.boxes, strict=True)
        if b[0] > 1 and b[2] < WIDTH - 1
    }
    assert sorted(int(t.classes[0]) for t in result.tracks) == sorted(vehicles)


@settings(max_examples=50, deadline=None)
@given(
    data=st.lists(st.lists(_boxes, max_size=6), min_size=1, max_size=12),
    margin=st.floats(0.0, 20.0),
    coast=st.integers(0, 4),
)
def test_every_box_is_output_once_or_counted_as_border(
    data: list[list[list[float]]], margin: float, coast: int
) -> None:
    frames = _frames(data)
    result = track_boxes(
        frames, 600, 400, TrackingParams(max_extrapolated_frames=coast, border_margin_px=margin)
    )
    inputs = {(f.stamp_ns, tuple(b)) for f in frames for b in f.boxes.tolist()}
    outputs = [
        (int(s), tuple(b)) for t in result.tracks for s, b in zip(t.stamps, t.boxes.tolist(), strict=True)
    ]
    assert len(outputs) + result.border_boxes_dropped == sum(len(f.boxes) for f in frames)
    assert set(outputs) <= inputs
    for track in result.tracks:
        assert np.all(np.diff(track.stamps) > 0)


def test_boxes_beyond_the_lens_model_keep_the_track_but_are_not_output() -> None:
    # A lens model that turns back at rho 1.01 (fx 900, principal point at the centre: 909 px out).
    camera = CameraModel.from_intrinsics(
        CameraIntrinsics(
            width=WIDTH, height=HEIGHT, fx=900.0, fy=900.0, cx=WIDTH / 2, cy=HEIGHT / 2,
            dist=(-0.30, 0.09, 0.0005, -0.0004, -0.012),
        )
    )  # fmt: skip
    # One vehicle driving from the centre towards the top-right corner, 40 px per frame.
    per_frame = [[_box(1000 + 40 * k, 650 - 20 * k, 80, 60)] for k in range(20)]
    frames = _frames(per_frame)
    corners = np.array([[b[0][x], b[0][y]] for b in per_frame for x, y in ((0, 1), (2, 1), (0, 3), (2, 3))])
    beyond = camera.beyond_model(corners).reshape(-1, 4).any(axis=1)
    assert 0 < beyond.sum() < len(per_frame)  # the drive crosses the limit inside the image
    plain = _track(frames)
    result = track_boxes(frames, WIDTH, HEIGHT, TrackingParams(), camera.beyond_model)
    assert plain.border_boxes_dropped == 0 and plain.lens_boxes_dropped == 0
    assert result.lens_boxes_dropped == result.border_boxes_dropped == int(beyond.sum())
    # One track all the same (the dropped boxes took part in association), holding exactly the boxes inside.
    assert len(result.tracks) == 1
    np.testing.assert_array_equal(result.tracks[0].boxes, plain.tracks[0].boxes[~beyond])


def test_empty_input_and_validation() -> None:
    assert _track([]) == TrackSet(tracks=(), border_boxes_dropped=0)
    assert _track(_frames([[], []])).tracks == ()
    frames = _frames([[_box(100, 100, 20, 20)], [_box(100, 100, 20, 20)]], [T0_NS, T0_NS])
    with pytest.raises(InputError, match=r"frames\[1\].stamp_ns"):
        _track(frames)
    bad = [FrameBoxes(stamp_ns=T0_NS, boxes=np.zeros((2, 3)), classes=np.zeros(2, dtype=np.int64))]
    with pytest.raises(ShapeError, match=r"frames\[0\].boxes"):
        _track(bad)
    mismatched = [FrameBoxes(stamp_ns=T0_NS, boxes=np.zeros((2, 4)), classes=np.zeros(1, dtype=np.int64))]
    with pytest.raises(ShapeError, match="2 boxes but 1 classes"):
        _track(mismatched)
    with pytest.raises(InputError, match="max_extrapolated_frames = -1"):
        TrackingParams(max_extrapolated_frames=-1)
    with pytest.raises(InputError, match="border_margin_px = nan"):
        TrackingParams(border_margin_px=float("nan"))
