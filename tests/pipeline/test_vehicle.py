"""Vehicle body corners from pose + profile: order, placement, imu_offset, against scipy's rotations."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation as SciRotation

from pipeline.arrays import FloatArray
from pipeline.camera import rotation_from_ypr
from pipeline.errors import ShapeError
from pipeline.vehicle import (
    body_centres,
    body_corners,
    body_points_to_world,
    footprint_corners,
    reference_from_centre_footprint,
)
from schemas.common import VehicleProfile

RR, FR, FL, RL = range(4)


@st.composite
def profiles(draw: st.DrawFn) -> VehicleProfile:
    length = draw(st.floats(2.0, 20.0))
    width = draw(st.floats(1.0, 3.0))
    height = draw(st.floats(1.0, 4.5))
    # The reference point (IMU, GNSS antenna, rear axle...) may sit anywhere in or near the body.
    imu = (
        draw(st.floats(-1.0, length + 1.0)),
        draw(st.floats(-1.0, width + 1.0)),
        draw(st.floats(-1.0, height)),
    )
    return VehicleProfile(length=length, width=width, height=height, imu_offset=imu)


pose_arrays = st.integers(1, 8).flatmap(
    lambda n: st.tuples(
        arrays(np.float64, (n, 3), elements=st.floats(-1000.0, 1000.0)),
        arrays(np.float64, (n,), elements=st.floats(-math.pi, math.pi)),
        arrays(np.float64, (n, 2), elements=st.floats(-0.3, 0.3)),
    ).map(lambda parts: np.column_stack([parts[0], parts[1], parts[2]]))
)


def body_axes(poses: FloatArray) -> FloatArray:
    """Body x (forward), y (left), z (up) in the world for each pose, from scipy: (N, 3, 3) columns."""
    return np.asarray(SciRotation.from_euler("ZYX", poses[:, 3:6]).as_matrix())


@settings(max_examples=100, deadline=None)
@given(poses=pose_arrays, profile=profiles())
def test_footprint_corners_are_rr_fr_fl_rl(poses: FloatArray, profile: VehicleProfile) -> None:
    corners = footprint_corners(poses, profile)
    assert corners.shape == (len(poses), 4, 3)
    axes = body_axes(poses)
    forward, left = axes[:, :, 0], axes[:, :, 1]
    along = np.einsum("nkj,nj->nk", corners, forward)
    across = np.einsum("nkj,nj->nk", corners, left)
    # Rear-right has the smallest forward and the smallest left coordinate; the order goes round the box.
    np.testing.assert_allclose(along[:, FR] - along[:, RR], profile.length, atol=1e-9)
    np.testing.assert_allclose(along[:, FL] - along[:, RL], profile.length, atol=1e-9)
    np.testing.assert_allclose(along[:, RL] - along[:, RR], 0.0, atol=1e-9)
    np.testing.assert_allclose(across[:, RL] - across[:, RR], profile.width, atol=1e-9)
    np.testing.assert_allclose(across[:, FL] - across[:, FR], profile.width, atol=1e-9)
    np.testing.assert_allclose(across[:, FR] - across[:, RR], 0.0, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(poses=pose_arrays, profile=profiles())
def test_footprint_is_the_bottom_of_the_body_and_the_centre_its_mean(
    poses: FloatArray, profile: VehicleProfile
) -> None:
    corners = body_corners(poses, profile)
    assert corners.shape == (len(poses), 8, 3)
    np.testing.assert_allclose(corners[:, :4], footprint_corners(poses, profile), atol=1e-12)
    up = body_axes(poses)[:, :, 2]
    heights = np.einsum("nkj,nj->nk", corners, up)
    np.testing.assert_allclose(heights[:, 4:] - heights[:, :4], profile.height, atol=1e-9)  # roof above each
    roof_offset = np.broadcast_to(profile.height * up[:, None, :], (len(poses), 4, 3))
    np.testing.assert_allclose(corners[:, 4:] - corners[:, :4], roof_offset, atol=1e-9)
    np.testing.assert_allclose(body_centres(poses, profile), corners.mean(axis=1), atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(poses=pose_arrays, profile=profiles())
def test_the_pose_is_the_position_of_the_imu_offset(poses: FloatArray, profile: VehicleProfile) -> None:
    imu_body = np.array([profile.imu_offset])
    np.testing.assert_allclose(body_points_to_world(poses, imu_body, profile)[:, 0], poses[:, :3], atol=1e-9)
    # The reference point sits at imu_offset from the rear-right-bottom corner, in body axes.
    rear_right = footprint_corners(poses, profile)[:, RR]
    offset_world = np.einsum("nij,j->ni", body_axes(poses), np.array(profile.imu_offset))
    np.testing.assert_allclose(rear_right + offset_world, poses[:, :3], atol=1e-9)


def test_footprint_of_a_level_car_heading_east() -> None:
    # 4 m x 2 m car, reference point at the centre of the rear axle on the ground, 1 m ahead of the rear.
    profile = VehicleProfile(length=4.0, width=2.0, height=1.5, imu_offset=(1.0, 1.0, 0.0))
    poses = np.array([[10.0, 20.0, 0.5, 0.0, 0.0, 0.0], [10.0, 20.0, 0.5, math.pi / 2, 0.0, 0.0]])
    corners = footprint_corners(poses, profile)
    # East (+x): rear-right is south-west of the reference point.
    np.testing.assert_allclose(
        corners[0], [[9.0, 19.0, 0.5], [13.0, 19.0, 0.5], [13.0, 21.0, 0.5], [9.0, 21.0, 0.5]], atol=1e-12
    )
    # North (+y): forward is +y and right is +x.
    np.testing.assert_allclose(
        corners[1], [[11.0, 19.0, 0.5], [11.0, 23.0, 0.5], [9.0, 23.0, 0.5], [9.0, 19.0, 0.5]], atol=1e-12
    )
    np.testing.assert_allclose(body_centres(poses[:1], profile), [[11.0, 20.0, 1.25]], atol=1e-12)


@settings(max_examples=100, deadline=None)
@given(poses=pose_arrays, profile=profiles())
def test_reference_from_centre_footprint_round_trips(poses: FloatArray, profile: VehicleProfile) -> None:
    centres = footprint_corners(poses, profile).mean(axis=1)
    reference = reference_from_centre_footprint(centres, poses[:, 3], poses[:, 4], poses[:, 5], profile)
    np.testing.assert_allclose(reference, poses[:, :3], atol=1e-9)


def test_moving_the_imu_offset_moves_the_body_the_other_way() -> None:
    pose = np.array([[5.0, 6.0, 7.0, 0.7, 0.05, -0.03]])
    a = VehicleProfile(length=4.0, width=2.0, height=1.5, imu_offset=(1.0, 1.0, 0.5))
    b = VehicleProfile(length=4.0, width=2.0, height=1.5, imu_offset=(2.0, 1.0, 0.5))
    forward = body_axes(pose)[0, :, 0]
    shift = body_corners(pose, b) - body_corners(pose, a)
    np.testing.assert_allclose(shift, np.tile(-forward, (1, 8, 1)), atol=1e-12)


def test_shapes_are_checked() -> None:
    profile = VehicleProfile(length=4.0, width=2.0, height=1.5, imu_offset=(1.0, 1.0, 0.5))
    with pytest.raises(ShapeError, match=r"poses: expected \(N, 6\), got \(3, 3\)"):
        footprint_corners(np.zeros((3, 3)), profile)
    with pytest.raises(ShapeError, match="points_body"):
        body_points_to_world(np.zeros((2, 6)), np.zeros(3), profile)
    assert footprint_corners(np.zeros((0, 6)), profile).shape == (0, 4, 3)


@pytest.mark.parametrize("count", [1, 7, 3000])
@pytest.mark.parametrize("points", [1, 12, 20])
def test_body_points_to_world_is_the_plain_contraction_to_the_last_bit(count: int, points: int) -> None:
    """The fast contraction order gives exactly the sums of products of R (p - imu_offset) + position, as
    the straightforward einsum does (the final fit's finite differences rely on repeatable placement)."""
    rng = np.random.default_rng(count * 100 + points)
    profile = VehicleProfile(length=4.6, width=1.8, height=1.5, imu_offset=(1.3, 0.9, 0.3))
    poses = np.column_stack(
        [
            rng.normal(0.0, 300.0, (count, 3)),
            rng.uniform(-math.pi, math.pi, count),
            rng.normal(0.0, 0.1, (count, 2)),
        ]
    )
    body = rng.uniform(-1.0, 5.0, (points, 3))
    R = SciRotation.from_euler("ZYX", poses[:, 3:6]).as_matrix()
    world = body_points_to_world(poses, body, profile)
    assert world.flags.c_contiguous
    expected = np.einsum("nij,kj->nki", R, body - np.array(profile.imu_offset)) + poses[:, None, :3]
    np.testing.assert_allclose(world, expected, rtol=0, atol=1e-9)  # the placement itself
    R_own = rotation_from_ypr(poses[:, 3], poses[:, 4], poses[:, 5])
    exact = np.einsum("nij,kj->nki", R_own, body - np.array(profile.imu_offset)) + poses[:, None, :3]
    np.testing.assert_array_equal(world, exact)
