"""Vehicle body geometry from pose + VehicleProfile (DESIGN: the vehicle box frame).

Body frame: x forward, y left, z up; the body is [0, L] x [0, W] x [0, H] with its origin at the
rear-right-bottom corner, and the pose gives the position of `imu_offset` in that frame.
"""

from __future__ import annotations

import numpy as np

from pipeline.arrays import Corners, FloatArray, Points3, PoseArray, check_shape
from pipeline.camera import rotation_from_ypr
from schemas.common import VehicleProfile

# Corner order of the 8-corner body: the footprint (rear-right, front-right, front-left, rear-left) at z=0,
# then the same four at z=H.
_FOOTPRINT_UNIT = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])


def body_points_to_world(poses: PoseArray, points_body: FloatArray, vehicle: VehicleProfile) -> FloatArray:
    """Points given in the vehicle box frame (K, 3) -> world/local frame for every pose: (N, K, 3)."""
    check_shape(poses, "N,6", name="poses")
    return rotated_body_points(
        rotation_from_ypr(poses[:, 3], poses[:, 4], poses[:, 5]), poses, points_body, vehicle
    )


def rotated_body_points(
    R: FloatArray, poses: PoseArray, points_body: FloatArray, vehicle: VehicleProfile
) -> FloatArray:
    """`body_points_to_world` with the poses' body rotations (N, 3, 3) already computed (callers that
    place several point sets on the same poses compute them once)."""
    check_shape(points_body, "K,3", name="points_body")
    relative = points_body - np.asarray(vehicle.imu_offset, dtype=np.float64)
    # Contracted into (N, 3, K) and transposed: the same sums of products as "nij,kj->nki", bit for bit,
    # at a third of the time (einsum's loop for that output order is slow).
    rotated = np.einsum("nij,kj->nik", R, relative).transpose(0, 2, 1)
    return np.ascontiguousarray(rotated + poses[:, None, :3], dtype=np.float64)


def body_corners_body_frame(vehicle: VehicleProfile) -> FloatArray:
    """The 8 corners of the body box in the vehicle box frame (8, 3): footprint first, then the roof."""
    L, W, H = vehicle.length, vehicle.width, vehicle.height
    base = np.column_stack([_FOOTPRINT_UNIT[:, 0] * L, _FOOTPRINT_UNIT[:, 1] * W, np.zeros(4)])
    roof = base + np.array([0.0, 0.0, H])
    return np.vstack([base, roof])


def body_corners(poses: PoseArray, vehicle: VehicleProfile) -> FloatArray:
    """World positions of the 8 body corners for every pose: (N, 8, 3)."""
    return body_points_to_world(poses, body_corners_body_frame(vehicle), vehicle)


def footprint_corners(poses: PoseArray, vehicle: VehicleProfile) -> Corners:
    """World positions of the 4 footprint corners, rear-right, front-right, front-left, rear-left:
    (N, 4, 3)."""
    return body_points_to_world(poses, body_corners_body_frame(vehicle)[:4], vehicle)


def body_centres(poses: PoseArray, vehicle: VehicleProfile) -> Points3:
    """World position of the body box's geometric centre for every pose: (N, 3).

    The paper's box-centre correspondence (Sec. III-D).
    """
    centre = np.array([[vehicle.length / 2.0, vehicle.width / 2.0, vehicle.height / 2.0]])
    return body_points_to_world(poses, centre, vehicle)[:, 0, :]


def footprint_centres(poses: PoseArray, vehicle: VehicleProfile) -> Points3:
    """World position of the footprint's centre (L/2, W/2, 0) for every pose: (N, 3)."""
    centre = np.array([[vehicle.length / 2.0, vehicle.width / 2.0, 0.0]])
    return np.asarray(body_points_to_world(poses, centre, vehicle)[:, 0, :], dtype=np.float64)


def reference_from_centre_footprint(
    centres: Points3, yaw: FloatArray, pitch: FloatArray, roll: FloatArray, vehicle: VehicleProfile
) -> Points3:
    """Pose reference point (N, 3) of a body whose footprint centre (L/2, W/2, 0) is at `centres`."""
    R = rotation_from_ypr(yaw, pitch, roll)
    offset = np.asarray(vehicle.imu_offset, dtype=np.float64) - np.array(
        [vehicle.length / 2.0, vehicle.width / 2.0, 0.0]
    )
    return np.asarray(centres + np.einsum("nij,j->ni", R, offset), dtype=np.float64)
