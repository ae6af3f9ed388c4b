"""Pose association (paper Sec. III-B): trajectory building, clock offset, interpolation, dropouts."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.arrays import FloatArray, IntArray
from pipeline.association import (
    AssociationParams,
    Trajectory,
    interpolate_poses,
    make_trajectory,
    wrap_angle,
)
from pipeline.errors import InputError, ShapeError
from schemas.common import LocalOrigin
from schemas.messages import VehiclePose

ORIGIN = LocalOrigin(crs="EPSG:32632", x=500_000.0, y=5_400_000.0, z=400.0)
T0_NS = 1_700_000_000_000_000_000
SECOND_NS = 1_000_000_000


def _linear_state(t_s: FloatArray) -> FloatArray:
    """Ground truth: a vehicle moving on straight lines in every pose component (local frame)."""
    return np.column_stack(
        [
            10.0 + 13.9 * t_s,  # x, m (50 km/h)
            -5.0 - 2.5 * t_s,  # y
            1.0 + 0.01 * t_s,  # z
            0.3 + 0.02 * t_s,  # yaw, rad (a slow turn that stays clear of +-pi)
            0.01 - 0.001 * t_s,  # pitch
            -0.02 + 0.002 * t_s,  # roll
        ]
    )


def _poses(stamps_ns: IntArray, local: FloatArray) -> list[VehiclePose]:
    """Local-frame poses -> VehiclePose messages in absolute UTM."""
    return [
        VehiclePose(
            stamp_ns=int(stamp),
            x=float(row[0]) + ORIGIN.x,
            y=float(row[1]) + ORIGIN.y,
            z=float(row[2]) + ORIGIN.z,
            yaw=float(row[3]),
            pitch=float(row[4]),
            roll=float(row[5]),
        )
        for stamp, row in zip(stamps_ns, local, strict=True)
    ]


# ---------------------------------------------------------------------------------------------- trajectory


def test_make_trajectory_sorts_drops_duplicates_and_moves_to_local_frame() -> None:
    stamps = T0_NS + np.array([2, 0, 1, 1, 3]) * SECOND_NS
    local = np.zeros((5, 6))
    local[:, 0] = [2.0, 0.0, 1.0, 99.0, 3.0]  # the second pose at t=1 s is a conflicting repeat
    trajectory = make_trajectory(_poses(stamps, local), ORIGIN, AssociationParams())
    np.testing.assert_array_equal(trajectory.stamps, T0_NS + np.arange(4) * SECOND_NS)
    np.testing.assert_allclose(trajectory.poses[:, 0], [0.0, 1.0, 2.0, 3.0])  # first received kept
    assert trajectory.stamps.dtype == np.int64


def test_make_trajectory_applies_clock_offset_by_subtracting() -> None:
    offset_ns = 250_000_000  # vehicle clock runs 250 ms ahead of the camera clock
    vehicle_stamps = T0_NS + np.arange(3) * SECOND_NS
    trajectory = make_trajectory(
        _poses(vehicle_stamps, np.zeros((3, 6))), ORIGIN, AssociationParams(time_offset_ns=offset_ns)
    )
    np.testing.assert_array_equal(trajectory.stamps, vehicle_stamps - offset_ns)


def test_make_trajectory_wraps_yaw_and_handles_empty_input() -> None:
    local = np.zeros((1, 6))
    local[0, 3] = 3.0 * math.pi / 2.0
    trajectory = make_trajectory(_poses(np.array([T0_NS]), local), ORIGIN, AssociationParams())
    assert trajectory.poses[0, 3] == pytest.approx(-math.pi / 2.0)
    empty = make_trajectory([], ORIGIN, AssociationParams())
    assert empty.stamps.shape == (0,) and empty.poses.shape == (0, 6)


def test_trajectory_rejects_unsorted_or_mismatched_arrays() -> None:
    with pytest.raises(ShapeError, match="strictly increasing"):
        Trajectory(stamps=np.array([2, 1], dtype=np.int64), poses=np.zeros((2, 6)))
    with pytest.raises(ShapeError, match="2 stamps but 3 poses"):
        Trajectory(stamps=np.array([1, 2], dtype=np.int64), poses=np.zeros((3, 6)))


# ------------------------------------------------------------------------------------------ interpolation


@pytest.mark.parametrize("rate_hz", [1, 10, 100])
def test_interpolation_is_exact_on_linear_motion(rate_hz: int) -> None:
    period_ns = SECOND_NS // rate_hz
    count = 20 * rate_hz + 1  # 20 s of poses
    pose_stamps = T0_NS + np.arange(count, dtype=np.int64) * period_ns
    trajectory = make_trajectory(
        _poses(pose_stamps, _linear_state((pose_stamps - T0_NS) / 1e9)), ORIGIN, AssociationParams()
    )
    rng = np.random.default_rng(rate_hz)
    query = np.sort(rng.integers(pose_stamps[0], pose_stamps[-1] + 1, size=500)).astype(np.int64)
    poses, mask = interpolate_poses(trajectory, query, AssociationParams())
    assert mask.all()
    # Tolerance: float64 rounding of the UTM round trip (5e6 m) is ~1e-9 m.
    np.testing.assert_allclose(poses, _linear_state((query - T0_NS) / 1e9), atol=1e-7)


def test_interpolation_accepts_unsorted_query_stamps() -> None:
    pose_stamps = T0_NS + np.arange(11, dtype=np.int64) * SECOND_NS
    trajectory = make_trajectory(
        _poses(pose_stamps, _linear_state((pose_stamps - T0_NS) / 1e9)), ORIGIN, AssociationParams()
    )
    query = T0_NS + np.array([7_500_000_000, 500_000_000, 3_250_000_000], dtype=np.int64)
    poses, mask = interpolate_poses(trajectory, query, AssociationParams())
    assert mask.all()
    np.testing.assert_allclose(poses, _linear_state((query - T0_NS) / 1e9), atol=1e-7)


def test_yaw_interpolates_along_the_short_arc_across_pi() -> None:
    stamps = T0_NS + np.arange(2, dtype=np.int64) * SECOND_NS
    local = np.zeros((2, 6))
    local[:, 3] = [math.pi - 0.1, -math.pi + 0.1]  # 0.2 rad apart across the +-pi seam, not 2 pi - 0.2
    trajectory = make_trajectory(_poses(stamps, local), ORIGIN, AssociationParams())
    query = T0_NS + np.array([250_000_000, 500_000_000, 750_000_000], dtype=np.int64)
    poses, mask = interpolate_poses(trajectory, query, AssociationParams())
    assert mask.all()
    expected = wrap_angle(np.array([math.pi - 0.05, math.pi, math.pi + 0.05]))
    # Compare on the circle: pi and -pi are the same heading.
    np.testing.assert_allclose(wrap_angle(poses[:, 3] - expected), 0.0, atol=1e-12)
    assert np.all(np.abs(poses[:, 3]) > math.pi - 0.1)  # never swings through 0


def test_yaw_of_a_full_turn_sampled_at_1_hz() -> None:
    # A vehicle turning at 0.5 rad/s through several full circles; the yaw wraps every ~12.6 s.
    pose_stamps = T0_NS + np.arange(40, dtype=np.int64) * SECOND_NS
    local = np.zeros((40, 6))
    local[:, 3] = wrap_angle(0.5 * np.arange(40.0))
    trajectory = make_trajectory(_poses(pose_stamps, local), ORIGIN, AssociationParams())
    query = T0_NS + np.arange(0, 39 * SECOND_NS, 37_000_000, dtype=np.int64)
    poses, mask = interpolate_poses(trajectory, query, AssociationParams())
    assert mask.all()
    expected = 0.5 * (query - T0_NS) / 1e9
    np.testing.assert_allclose(wrap_angle(poses[:, 3] - expected), 0.0, atol=1e-9)
    assert np.all(np.abs(poses[:, 3]) <= math.pi)


def test_dropout_gap_gives_no_pose() -> None:
    # 10 Hz poses with a 3 s dropout between t = 5 s and t = 8 s.
    t_s = np.concatenate([np.arange(0.0, 5.05, 0.1), np.arange(8.0, 10.05, 0.1)])
    pose_stamps = T0_NS + np.round(t_s * 1e9).astype(np.int64)
    trajectory = make_trajectory(_poses(pose_stamps, _linear_state(t_s)), ORIGIN, AssociationParams())
    query_s = np.array([4.95, 5.0, 5.01, 6.5, 7.99, 8.0, 8.05])
    query = T0_NS + np.round(query_s * 1e9).astype(np.int64)
    poses, mask = interpolate_poses(trajectory, query, AssociationParams())
    # Exactly at the last pose before / first pose after the gap: that pose, even though the gap is long.
    np.testing.assert_array_equal(mask, [True, True, False, False, False, True, True])
    assert np.isnan(poses[~mask]).all()
    np.testing.assert_allclose(poses[mask], _linear_state(query_s[mask]), atol=1e-7)


def test_gap_threshold_is_inclusive_and_configurable() -> None:
    stamps = T0_NS + np.array([0, 2 * SECOND_NS], dtype=np.int64)
    trajectory = make_trajectory(_poses(stamps, np.zeros((2, 6))), ORIGIN, AssociationParams())
    query = np.array([T0_NS + SECOND_NS], dtype=np.int64)
    assert not interpolate_poses(trajectory, query, AssociationParams())[1][0]  # default 1.5 s gap
    assert interpolate_poses(trajectory, query, AssociationParams(max_pose_gap_ns=2 * SECOND_NS))[1][0]


def test_stamps_outside_the_trajectory_need_the_extrapolation_allowance() -> None:
    pose_stamps = T0_NS + np.arange(11, dtype=np.int64) * 100_000_000  # 10 Hz for 1 s
    trajectory = make_trajectory(
        _poses(pose_stamps, _linear_state((pose_stamps - T0_NS) / 1e9)), ORIGIN, AssociationParams()
    )
    query_s = np.array([-0.3, -0.1, 0.0, 1.0, 1.1, 1.3])
    query = T0_NS + np.round(query_s * 1e9).astype(np.int64)
    _, strict = interpolate_poses(trajectory, query, AssociationParams())
    np.testing.assert_array_equal(strict, [False, False, True, True, False, False])
    poses, lenient = interpolate_poses(trajectory, query, AssociationParams(max_extrapolation_ns=200_000_000))
    np.testing.assert_array_equal(lenient, [False, True, True, True, True, False])
    # Linear motion: extrapolating along the end segment is exact too.
    np.testing.assert_allclose(poses[lenient], _linear_state(query_s[lenient]), atol=1e-7)


def test_clock_offset_aligns_poses_with_camera_stamps() -> None:
    offset_ns = -180_000_000  # vehicle clock 180 ms behind the camera clock
    camera_stamps = T0_NS + np.arange(101, dtype=np.int64) * 100_000_000
    truth = _linear_state((camera_stamps - T0_NS) / 1e9)
    reported = _poses(camera_stamps + offset_ns, truth)  # vehicle clock = camera clock + offset
    query = T0_NS + np.array([1_234_567_890, 5_000_000_000, 8_876_543_210], dtype=np.int64)
    expected = _linear_state((query - T0_NS) / 1e9)
    params = AssociationParams(time_offset_ns=offset_ns)
    poses, mask = interpolate_poses(make_trajectory(reported, ORIGIN, params), query, params)
    assert mask.all()
    np.testing.assert_allclose(poses, expected, atol=1e-7)
    # Ignoring the offset misplaces a 13.9 m/s vehicle by 13.9 * 0.18 = 2.5 m.
    naive, _ = interpolate_poses(make_trajectory(reported, ORIGIN, AssociationParams()), query, params)
    np.testing.assert_allclose(np.abs(naive[:, 0] - expected[:, 0]), 13.9 * 0.18, rtol=1e-6)


def test_duplicates_and_disorder_do_not_change_the_interpolation() -> None:
    pose_stamps = T0_NS + np.arange(21, dtype=np.int64) * 500_000_000
    local = _linear_state((pose_stamps - T0_NS) / 1e9)
    rng = np.random.default_rng(3)
    order = np.concatenate([rng.permutation(21), [4, 9]])  # shuffled, two poses sent twice
    messy = make_trajectory(_poses(pose_stamps[order], local[order]), ORIGIN, AssociationParams())
    clean = make_trajectory(_poses(pose_stamps, local), ORIGIN, AssociationParams())
    np.testing.assert_array_equal(messy.stamps, clean.stamps)
    np.testing.assert_array_equal(messy.poses, clean.poses)


def test_degenerate_trajectories() -> None:
    query = T0_NS + np.array([-1, 0, 1], dtype=np.int64)
    poses, mask = interpolate_poses(
        Trajectory(stamps=np.empty(0, dtype=np.int64), poses=np.empty((0, 6))), query, AssociationParams()
    )
    assert poses.shape == (3, 6) and not mask.any()
    single = Trajectory(stamps=np.array([T0_NS], dtype=np.int64), poses=np.arange(6.0)[None, :])
    poses, mask = interpolate_poses(single, query, AssociationParams())
    np.testing.assert_array_equal(mask, [False, True, False])
    np.testing.assert_array_equal(poses[1], np.arange(6.0))
    _, mask = interpolate_poses(single, query, AssociationParams(max_extrapolation_ns=1))
    assert mask.all()
    poses, mask = interpolate_poses(single, np.empty(0, dtype=np.int64), AssociationParams())
    assert poses.shape == (0, 6) and mask.shape == (0,)


def test_interpolate_checks_its_stamps() -> None:
    trajectory = Trajectory(stamps=np.array([T0_NS], dtype=np.int64), poses=np.zeros((1, 6)))
    with pytest.raises(ShapeError, match="integer nanoseconds"):
        interpolate_poses(trajectory, np.array([1.7e18]), AssociationParams())
    with pytest.raises(ShapeError, match=r"stamps: expected \(N,\)"):
        interpolate_poses(trajectory, np.zeros((2, 2), dtype=np.int64), AssociationParams())


# --------------------------------------------------------------------------------------------- properties

_pose_rows = st.tuples(
    st.floats(-1e3, 1e3),
    st.floats(-1e3, 1e3),
    st.floats(-50, 50),
    st.floats(-math.pi + 1e-9, math.pi - 1e-9),
    st.floats(-0.3, 0.3),
    st.floats(-0.3, 0.3),
)


@settings(max_examples=60, deadline=None)
@given(
    gaps=st.lists(st.integers(1, 3 * SECOND_NS), min_size=1, max_size=30),
    rows=st.lists(_pose_rows, min_size=31, max_size=31),
)
def test_interpolating_at_the_pose_stamps_returns_the_poses(
    gaps: list[int], rows: list[tuple[float, ...]]
) -> None:
    stamps = T0_NS + np.concatenate([[0], np.cumsum(gaps)]).astype(np.int64)
    local = np.array(rows[: len(stamps)])
    trajectory = Trajectory(stamps=stamps, poses=local)
    poses, mask = interpolate_poses(trajectory, stamps, AssociationParams())
    assert mask.all()  # a pose stamp always has its pose, however far its neighbours are
    np.testing.assert_array_equal(poses, local)


@settings(max_examples=60, deadline=None)
@given(
    yaw_a=st.floats(-math.pi, math.pi),
    turn=st.floats(-math.pi + 1e-6, math.pi - 1e-6),
    fraction=st.floats(0.0, 1.0),
)
def test_yaw_moves_monotonically_along_the_short_arc(yaw_a: float, turn: float, fraction: float) -> None:
    stamps = T0_NS + np.array([0, SECOND_NS], dtype=np.int64)
    local = np.zeros((2, 6))
    local[:, 3] = [yaw_a, float(wrap_angle(np.array(yaw_a + turn))[()])]
    query = np.array([T0_NS + round(fraction * SECOND_NS)], dtype=np.int64)
    poses, mask = interpolate_poses(Trajectory(stamps=stamps, poses=local), query, AssociationParams())
    weight = (query[0] - T0_NS) / SECOND_NS
    assert mask[0]
    assert abs(float(wrap_angle(poses[:, 3] - (yaw_a + weight * turn))[0])) < 1e-9
    assert -math.pi <= poses[0, 3] <= math.pi


def test_params_reject_negative_limits() -> None:
    with pytest.raises(InputError, match="max_pose_gap_ns = -1"):
        AssociationParams(max_pose_gap_ns=-1)
    with pytest.raises(InputError, match="max_extrapolation_ns = -5"):
        AssociationParams(max_extrapolation_ns=-5)
    assert AssociationParams(time_offset_ns=-5).time_offset_ns == -5  # an offset may have either sign
