"""Vehicle bodies of the simulated world, in the vehicle frame of DESIGN.md (x forward, y left, z up; the
data-sheet box [0, L] x [0, W] x [0, H] with its origin at the rear-right-bottom corner).

This module places bodies in the world from the pose of their reference point (the IMU, `imu_offset` in
that frame) or of their footprint centre, and gives the body's corner points.
"""

from __future__ import annotations

import numpy as np

from schemas.common import VehicleProfile
from sim.geometry import FloatArray, attitude_matrices
from sim.world import UNIT_BOX_CORNERS


def place_points(poses: FloatArray, points_body: FloatArray, anchor_body: FloatArray) -> FloatArray:
    """Body-frame points (K, 3) -> local frame (N, K, 3) for bodies whose point `anchor_body` (3,) has
    the poses (N, 6) = x, y, z, yaw, pitch, roll."""
    R = attitude_matrices(poses[:, 3], poses[:, 4], poses[:, 5])
    relative = points_body - anchor_body
    return np.asarray(np.einsum("nij,kj->nki", R, relative) + poses[:, None, :3], dtype=np.float64)


def reference_from_footprint_centre(centre_poses: FloatArray, profile: VehicleProfile) -> FloatArray:
    """Poses (N, 6) of the footprint centre (L/2, W/2, 0) -> poses (N, 6) of the reference point."""
    anchor = np.array([profile.length / 2.0, profile.width / 2.0, 0.0])
    reference = place_points(centre_poses, np.asarray([profile.imu_offset], dtype=np.float64), anchor)[:, 0]
    return np.column_stack([reference, centre_poses[:, 3:]])


def cuboid_points(profile: VehicleProfile) -> FloatArray:
    """The data-sheet box's 8 corners (8, 3) in the vehicle frame: base RR, FR, FL, RL, then the top."""
    return np.asarray(
        UNIT_BOX_CORNERS * np.array([profile.length, profile.width, profile.height]), dtype=np.float64
    )


def footprint_points(profile: VehicleProfile) -> FloatArray:
    """The data-sheet footprint's 4 corners (4, 3): rear-right, front-right, front-left, rear-left."""
    return cuboid_points(profile)[:4]
