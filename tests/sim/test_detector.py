"""The real world's detector: visible outlines, bias, correlated jitter, misses in runs, merges and splits.

Each mechanism is checked on inputs whose right answer is known by construction (a rectangle half hidden
by a nearer one, a track of 20,000 frames for the statistics), never against the detector's own code.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.common import CameraIntrinsics
from sim.detector import (
    GROSS_MERGED,
    GROSS_NONE,
    GROSS_SPLIT,
    RealDetector,
    _biased,
    _clip_hull_to_image,
    _correlate_along_tracks,
    _gross_errors,
    _missed_in_runs,
    _visible_outlines,
    exposed_points,
)
from sim.lens import Lens
from sim.presets import DetectorSpec

LENS = Lens.from_intrinsics(
    CameraIntrinsics(width=1920, height=1200, fx=1400.0, fy=1400.0, cx=960.0, cy=600.0)
)


def _rectangle(x1: float, y1: float, x2: float, y2: float) -> np.ndarray:
    return np.array([[x1, y1], [x2, y1], [x2, y2], [x1, y2]], dtype=np.float64)


@settings(max_examples=40, deadline=None)
@given(cut=st.floats(0.2, 0.8), grid=st.sampled_from([24, 32]))
def test_a_target_partly_behind_a_nearer_silhouette_gives_the_box_of_its_visible_part(
    cut: float, grid: int
) -> None:
    target = _rectangle(400.0, 300.0, 600.0, 400.0)
    x_cut = 400.0 + cut * 200.0
    occluder = _rectangle(x_cut, 250.0, 700.0, 450.0)  # nearer, covers the target's right part
    boxes = np.array([[400.0, 300.0, 600.0, 400.0], [x_cut, 250.0, 700.0, 450.0]])
    hidden, visible = _visible_outlines(
        np.array([0, 0]),
        boxes,
        np.array([30.0, 10.0]),
        [target, occluder],
        1,
        LENS,
        grid,
    )
    cell = 200.0 / grid
    assert hidden[0] == pytest.approx(1.0 - cut, abs=1.0 / grid)
    # Uncovered edges stay exact; the covered one ends at the occluder's edge, to a grid cell.
    assert visible[0, 0] == 400.0 and visible[0, 1] == 300.0 and visible[0, 3] == 400.0
    assert abs(visible[0, 2] - x_cut) <= cell


def test_a_farther_silhouette_hides_nothing_and_an_unoccluded_box_is_exact() -> None:
    target = _rectangle(400.0, 300.0, 600.0, 400.0)
    behind = _rectangle(450.0, 250.0, 700.0, 450.0)
    boxes = np.array([[400.0, 300.0, 600.0, 400.0], [450.0, 250.0, 700.0, 450.0]])
    hidden, visible = _visible_outlines(
        np.array([0, 0]),
        boxes,
        np.array([10.0, 30.0]),
        [target, behind],
        1,
        LENS,
        24,
    )
    assert hidden[0] == 0.0
    np.testing.assert_array_equal(visible[0], boxes[0])


def test_only_the_silhouette_counts_not_its_bounding_box() -> None:
    """A triangle's box corner is empty: a nearer shape covering only that corner hides nothing of it."""
    triangle = np.array([[400.0, 400.0], [600.0, 400.0], [400.0, 300.0]])
    corner = _rectangle(560.0, 300.0, 600.0, 330.0)  # inside the box, outside the triangle
    boxes = np.array([[400.0, 300.0, 600.0, 400.0], [560.0, 300.0, 600.0, 330.0]])
    hidden, visible = _visible_outlines(
        np.array([0, 0]),
        boxes,
        np.array([30.0, 10.0]),
        [triangle, corner],
        1,
        LENS,
        24,
    )
    assert hidden[0] == 0.0
    np.testing.assert_array_equal(visible[0], boxes[0])


def test_a_border_cut_silhouette_gives_the_box_of_its_part_inside_the_image() -> None:
    # A slanted quadrilateral leaving the image on the left: its lowest point is outside the image, so the
    # visible part's bottom is higher than the clipped box's.
    hull = np.array([[-100.0, 700.0], [200.0, 500.0], [300.0, 540.0], [0.0, 740.0]])
    bounds = _clip_hull_to_image(hull, LENS)
    assert bounds is not None
    assert bounds[0] == pytest.approx(0.0, abs=1e-3)
    assert bounds[2] == pytest.approx(300.0, abs=1e-3)
    assert bounds[3] == pytest.approx(740.0, abs=1e-3)  # the hull's point (0, 740) is on the border
    assert _clip_hull_to_image(hull - [1000.0, 0.0], LENS) is None


def test_correlated_jitter_keeps_its_spread_and_persists_along_the_track() -> None:
    rng = np.random.default_rng(5)
    frames = 20_000
    draws = rng.normal(0.0, 1.0, size=(frames, 4))
    owner = np.zeros(frames, dtype=np.int64)
    frame = np.arange(frames, dtype=np.int64)
    out = _correlate_along_tracks(draws, owner, frame, 0.8)
    # Standard errors over 20,000 frames of an AR(1) with rho 0.8: std ~0.012, lag-1 correlation ~0.005.
    assert np.std(out) == pytest.approx(1.0, abs=0.04)
    lag1 = np.mean([np.corrcoef(out[:-1, k], out[1:, k])[0, 1] for k in range(4)])
    assert lag1 == pytest.approx(0.8, abs=0.02)
    # A missing frame in between: the correlation over a gap of 2 frames is rho^2.
    gapped = _correlate_along_tracks(draws, owner, frame * 2, 0.8)
    lag = np.mean([np.corrcoef(gapped[:-1, k], gapped[1:, k])[0, 1] for k in range(4)])
    assert lag == pytest.approx(0.64, abs=0.03)
    # Tracks are independent of each other: a second owner starts afresh.
    two = _correlate_along_tracks(draws[:2], np.array([0, 1]), np.array([0, 1]), 0.8)
    np.testing.assert_array_equal(two, draws[:2])


def test_misses_come_in_runs_of_the_mean_length() -> None:
    frames = 50_000
    missed = _missed_in_runs(
        np.zeros(frames, dtype=np.int64),
        np.arange(frames, dtype=np.int64),
        0.02,
        5.0,
        np.random.default_rng(2),
    )
    edges = np.diff(np.concatenate([[0], missed.astype(int), [0]]))
    runs = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
    # Geometric run lengths with mean 5 (std ~4.5) over ~800 runs: standard error ~0.16.
    assert runs.mean() == pytest.approx(5.0, abs=0.6)
    assert (runs > 1).mean() > 0.6  # runs, not isolated misses
    # Stationary share of missed frames: start / (start + stop) = 0.02 / (0.02 + 0.2) ~ 0.09.
    assert missed.mean() == pytest.approx(0.02 / 0.22, abs=0.02)
    none = _missed_in_runs(np.zeros(10, np.int64), np.arange(10), 0.0, 5.0, np.random.default_rng(2))
    assert not none.any()


def test_a_merge_reports_two_overlapping_vehicles_as_their_union_and_keeps_the_calibration_vehicle() -> None:
    spec = DetectorSpec(merge_rate=1.0)
    # Frame 0: calibration vehicle (row 0, farther) and another (row 1, nearer) overlapping; frame 1: apart.
    boxes = np.array(
        [
            [100.0, 100.0, 200.0, 160.0],
            [150.0, 110.0, 260.0, 170.0],
            [100.0, 100.0, 200.0, 160.0],
            [500.0, 100.0, 600.0, 160.0],
        ]
    )
    gross = _gross_errors(
        np.array([0, 0, 1, 1]),
        np.array([0, 1, 0, 1]),
        np.array([40.0, 20.0, 40.0, 20.0]),
        boxes,
        np.array([True, False, True, False]),
        spec,
        np.random.default_rng(0),
    )
    assert list(gross.keep) == [False, True, True, True]
    np.testing.assert_array_equal(gross.boxes[1], [100.0, 100.0, 260.0, 170.0])
    assert list(gross.carries_calib) == [False, True, True, False]
    assert list(gross.gross) == [GROSS_MERGED, GROSS_MERGED, GROSS_NONE, GROSS_NONE]


def test_a_split_cuts_a_box_into_two_pieces_that_cover_it() -> None:
    spec = DetectorSpec(split_rate=1.0)
    boxes = np.array([[100.0, 100.0, 300.0, 180.0]])
    gross = _gross_errors(
        np.array([0]),
        np.array([0]),
        np.array([20.0]),
        boxes,
        np.array([True]),
        spec,
        np.random.default_rng(1),
    )
    assert gross.gross[0] == GROSS_SPLIT and len(gross.split_rows) == 1
    first, second = gross.boxes[0], gross.split_boxes[0]
    assert first[0] == 100.0 and second[2] == 300.0 and first[2] == second[0]
    assert 0.35 * 200 <= first[2] - 100.0 <= 0.65 * 200
    assert first[1] == second[1] == 100.0 and first[3] == second[3] == 180.0


def test_the_camera_bias_scales_and_shifts_boxes_but_never_moves_a_border_edge() -> None:
    real = RealDetector(
        scale=1.04, edge_offsets_px=np.array([1.0, -2.0, 3.0, 0.5]), rng=np.random.default_rng(0)
    )
    boxes = np.array([[100.0, 100.0, 200.0, 150.0], [0.0, 500.0, 80.0, 1200.0]])
    out = _biased(boxes, real, LENS)
    np.testing.assert_allclose(out[0], [98.0 + 1.0, 99.0 - 2.0, 202.0 + 3.0, 151.0 + 0.5])
    assert out[1, 0] == 0.0 and out[1, 3] == 1200.0  # cut by the border: stays on it
    drawn = RealDetector.draw(DetectorSpec(scale_bias=0.04, edge_bias_px=2.5), np.random.default_rng(3))
    assert abs(drawn.scale - 1.0) <= 0.04 and drawn.edge_offsets_px.shape == (4,)
    assert math.isfinite(float(drawn.edge_offsets_px.sum()))


@given(
    st.floats(-6.0, 6.0),  # lateral position (m) of a point 20 m ahead
    st.floats(-4.0, 4.0),  # its height offset
    st.floats(-20.0, 20.0),  # the vehicle's velocity across and along (m/s)
    st.floats(-20.0, 20.0),
    st.floats(0.0, 0.04),  # readout (s)
)
@settings(max_examples=60, deadline=None)
def test_a_rolling_shutter_places_each_point_where_it_was_when_its_row_was_exposed(
    x: float, y: float, vx: float, vz: float, readout: float
) -> None:
    # A point moving at constant velocity: at the exposure of row v it is at p0 + (v / height) readout vel.
    # The returned point must lie on that line, at the share its own row gives (to a hundredth of a pixel's
    # time: the row is found by iteration).
    R, t = np.eye(3), np.zeros(3)
    early = np.array([[[x, y, 20.0]]])
    velocity = np.array([vx, 0.0, vz])
    late = early + readout * velocity
    exposed = exposed_points(early, late, R, t, LENS)
    pixel, ok = LENS.project_cam(exposed.reshape(-1, 3))
    if not ok[0]:
        return
    share = float(np.clip(pixel[0, 1] / LENS.height, 0.0, 1.0))
    expected = early + share * (late - early)
    # Error of the fixed point after two steps: the row moves by at most |velocity| readout f / z between
    # them (under 0.6 px here), so its time by a share of that over the height.
    assert np.allclose(exposed, expected, atol=1e-3)


def test_without_a_rolling_shutter_the_points_are_the_frames_own() -> None:
    early = np.array([[[1.0, 2.0, 20.0], [0.0, 0.0, 15.0]]])
    assert exposed_points(early, None, np.eye(3), np.zeros(3), LENS) is early


def test_the_bottom_row_sees_the_vehicle_one_readout_later_than_the_top_row() -> None:
    # Two points on the same vertical line, one imaged near the top and one near the bottom, moving
    # sideways at 10 m/s, readout 30 ms: the lower one is exposed about 30 ms x (row difference / height)
    # later, so it has moved further by 10 m/s times that.
    z = 20.0
    top_y, bottom_y = -0.45 * LENS.height / 1400.0 * z, 0.45 * LENS.height / 1400.0 * z
    early = np.array([[[0.0, top_y, z], [0.0, bottom_y, z]]])
    late = early + np.array([0.3, 0.0, 0.0])  # 10 m/s x 0.03 s
    exposed = exposed_points(early, late, np.eye(3), np.zeros(3), LENS)
    moved = exposed[0, :, 0]
    assert moved[0] == pytest.approx(0.3 * 0.05, abs=2e-3)  # row 60 of 1200
    assert moved[1] == pytest.approx(0.3 * 0.95, abs=2e-3)
