"""Ground plane from the driven track (PCA): recovers known planes, falls back for straight tracks."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.arrays import FloatArray
from pipeline.errors import DegenerateGeometry, ShapeError
from pipeline.ground import GroundPlaneFit, fit_ground_plane


def tilted_normal(tilt_rad: float, azimuth_rad: float) -> FloatArray:
    return np.array(
        [
            math.sin(tilt_rad) * math.cos(azimuth_rad),
            math.sin(tilt_rad) * math.sin(azimuth_rad),
            math.cos(tilt_rad),
        ]
    )


def on_plane(xy: FloatArray, normal: FloatArray, offset: float) -> FloatArray:
    """Lift ground-track xy (N, 2) onto the plane normal . p = offset."""
    z = (offset - xy @ normal[:2]) / normal[2]
    return np.column_stack([xy, z])


def angle_deg(a: FloatArray, b: FloatArray) -> float:
    return math.degrees(math.acos(min(1.0, abs(float(a @ b)) / float(np.linalg.norm(a) * np.linalg.norm(b)))))


def intersection_track(rng: np.random.Generator, n: int) -> FloatArray:
    """xy (n, 2): passes through an intersection, straight both ways and a right turn (radius 15 m)."""
    s = rng.uniform(-40.0, 40.0, n)
    kind = rng.integers(0, 3, n)
    turn = rng.uniform(0.0, math.pi / 2, n)
    x = np.where(kind == 0, s, np.where(kind == 1, -s, 15.0 - 15.0 * np.cos(turn)))
    y = np.where(kind == 0, -1.75, np.where(kind == 1, 1.75, 15.0 * np.sin(turn)))
    return np.column_stack([x, y])


tilts = st.floats(0.0, math.radians(15.0))
azimuths = st.floats(-math.pi, math.pi)
seeds = st.integers(0, 2**32 - 1)


@settings(max_examples=100, deadline=None)
@given(tilt=tilts, azimuth=azimuths, offset=st.floats(-200.0, 200.0), seed=seeds)
def test_recovers_a_tilted_plane_exactly(tilt: float, azimuth: float, offset: float, seed: int) -> None:
    normal = tilted_normal(tilt, azimuth)
    points = on_plane(intersection_track(np.random.default_rng(seed), 200), normal, offset)
    fit = fit_ground_plane(points)
    np.testing.assert_allclose(fit.normal, normal, atol=1e-9)  # unit and up, whatever sign SVD picked
    assert fit.offset == pytest.approx(offset, abs=1e-6)
    np.testing.assert_allclose(fit.height_of(points), 0.0, atol=1e-6)


@settings(max_examples=100, deadline=None)
@given(tilt=tilts, azimuth=azimuths, seed=seeds)
def test_recovers_a_tilted_plane_from_a_noisy_track(tilt: float, azimuth: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    normal = tilted_normal(tilt, azimuth)
    rtk_noise = rng.normal(0.0, 0.03, (400, 3))
    points = on_plane(intersection_track(rng, 400), normal, 3.0) + rtk_noise
    fit = fit_ground_plane(points)
    assert angle_deg(fit.normal, normal) < 0.5
    assert fit.normal[2] > 0.0
    assert np.linalg.norm(fit.normal) == pytest.approx(1.0, abs=1e-12)


@settings(max_examples=100, deadline=None)
@given(heading=azimuths, grade=st.floats(-0.12, 0.12), seed=seeds)
def test_straight_track_is_taken_as_level_across(heading: float, grade: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    s = rng.uniform(-50.0, 50.0, 300)
    along = np.array([math.cos(heading), math.sin(heading), grade])
    points = np.array([10.0, -5.0, 2.0]) + s[:, None] * along
    fit = fit_ground_plane(points)
    across_level = np.array([-math.sin(heading), math.cos(heading), 0.0])
    assert abs(fit.normal @ along) < 1e-9  # contains the track
    assert abs(fit.normal @ across_level) < 1e-9  # level across it
    assert fit.normal[2] > 0.0
    np.testing.assert_allclose(fit.height_of(points), 0.0, atol=1e-9)


@pytest.mark.parametrize(("lateral_m", "vertical_m"), [(0.01, 0.03), (0.01, 0.05), (0.0, 0.02), (0.02, 0.02)])
def test_noisy_straight_pass_never_gives_a_steep_plane(lateral_m: float, vertical_m: float) -> None:
    # One straight pass: lateral wander and height noise are both noise; the least-variance direction of
    # PCA is then arbitrary (horizontal when the height noise is larger). The fit must stay level across.
    rng = np.random.default_rng(3)
    s = np.linspace(-30.0, 30.0, 300)
    points = np.column_stack(
        [s, lateral_m * rng.standard_normal(300), 0.04 * s + vertical_m * rng.standard_normal(300)]
    )
    fit = fit_ground_plane(points)
    expected = np.array([-0.04, 0.0, 1.0]) / math.hypot(0.04, 1.0)
    assert angle_deg(fit.normal, expected) < 1.0


def test_two_lanes_of_a_straight_road_fix_its_cross_slope() -> None:
    # Both directions of a straight road 3.5 m apart: the 3 % cross slope is observable, so it is kept.
    rng = np.random.default_rng(5)
    s = rng.uniform(-40.0, 40.0, 400)
    lane = np.where(rng.random(400) < 0.5, -1.75, 1.75)
    points = np.column_stack([s, lane, 0.03 * lane + rng.normal(0.0, 0.01, 400)])
    fit = fit_ground_plane(points)
    assert angle_deg(fit.normal, np.array([0.0, -0.03, 1.0])) < 0.3


@pytest.mark.parametrize(
    "points",
    [
        np.array([[1.0, 2.0, 3.0]]),
        np.array([[1.0, 2.0, 3.0], [5.0, 2.0, 3.0]]),
        np.tile([[1.0, 2.0, 3.0]], (50, 1)),  # a parked vehicle
        np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.1, 0.1, 0.01]]),
    ],
    ids=["one point", "two points", "standing still", "10 cm patch"],
)
def test_too_little_track_is_degenerate(points: FloatArray) -> None:
    with pytest.raises(DegenerateGeometry, match="ground plane"):
        fit_ground_plane(points)


def test_vertical_track_is_degenerate() -> None:
    points = np.column_stack([np.zeros(20), np.zeros(20), np.linspace(0.0, 30.0, 20)])
    with pytest.raises(DegenerateGeometry, match="vertical"):
        fit_ground_plane(points)


def test_track_shape_is_checked() -> None:
    with pytest.raises(ShapeError, match=r"track_points: expected \(N, 3\), got \(5, 2\)"):
        fit_ground_plane(np.zeros((5, 2)))


@settings(max_examples=100, deadline=None)
@given(tilt=tilts, azimuth=azimuths, offset=st.floats(-50.0, 50.0), seed=seeds)
def test_heights_and_ray_hits(tilt: float, azimuth: float, offset: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    plane = GroundPlaneFit(normal=tilted_normal(tilt, azimuth), offset=offset)
    ground = on_plane(rng.uniform(-50.0, 50.0, (20, 2)), plane.normal, offset)
    heights = rng.uniform(-5.0, 30.0, 20)
    np.testing.assert_allclose(plane.height_of(ground + heights[:, None] * plane.normal), heights, atol=1e-9)

    camera = ground[0] + 12.0 * plane.normal  # 12 m above the ground
    directions = ground - camera
    directions[-1] *= -1.0  # pointing away from the ground: no hit
    hits = plane.intersect_rays(camera, directions)
    np.testing.assert_allclose(hits[:-1], ground[:-1], atol=1e-9)
    assert np.isnan(hits[-1]).all()


def test_ray_parallel_to_the_plane_has_no_hit() -> None:
    plane = GroundPlaneFit(normal=np.array([0.0, 0.0, 1.0]), offset=0.0)
    hits = plane.intersect_rays(np.array([0.0, 0.0, 10.0]), np.array([[1.0, 0.0, 0.0], [1.0, 0.0, -1.0]]))
    assert np.isnan(hits[0]).all()
    np.testing.assert_allclose(hits[1], [10.0, 0.0, 0.0])
