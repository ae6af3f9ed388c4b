"""The simulated world's own geometry: array aliases, attitudes and camera mounting.

sim/ shares no model with pipeline/ (docs/design.md): attitudes are built with scipy's Euler sequence, camera
mountings from a look direction, and the world's conventions are written down here once. Local frame: x east,
y north, z up (metres, UTM minus the scenario's origin); yaw from grid east counter-clockwise, then pitch,
then roll (intrinsic z-y'-x''), as docs/design.md's pose convention.
"""

from __future__ import annotations

import math
from typing import TypeAlias

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation as SciRotation

FloatArray: TypeAlias = npt.NDArray[np.float64]
IntArray: TypeAlias = npt.NDArray[np.int64]
BoolArray: TypeAlias = npt.NDArray[np.bool_]


def attitude_matrices(yaw: FloatArray, pitch: FloatArray, roll: FloatArray) -> FloatArray:
    """World-from-body rotations (N, 3, 3) of bodies with the given yaw, pitch, roll (N,) in radians."""
    angles = np.column_stack([np.atleast_1d(yaw), np.atleast_1d(pitch), np.atleast_1d(roll)])
    return np.asarray(SciRotation.from_euler("ZYX", angles).as_matrix(), dtype=np.float64).reshape(-1, 3, 3)


def mount_rotation(azimuth: float, tilt_down: float, roll: float = 0.0) -> FloatArray:
    """cam_from_local rotation (3, 3) of a camera (OpenCV axes: x right, y down, z forward) whose optical
    axis points at `azimuth` (rad from grid east, ccw), `tilt_down` (rad) below the horizon, turned `roll`
    (rad) about the optical axis (clockwise in the image)."""
    # Start level, looking east (cam z = east, cam x = south, cam y = down), then turn the camera body.
    level_east = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # cam_from_local
    body = SciRotation.from_euler("ZYX", [azimuth, tilt_down, 0.0]).as_matrix()  # local_from_turned
    image_roll = SciRotation.from_rotvec([0.0, 0.0, roll]).as_matrix()  # about the optical axis
    return np.asarray(image_roll.T @ level_east @ body.T, dtype=np.float64)


def camera_position(R_cam_from_local: FloatArray, t_cam_from_local: FloatArray) -> FloatArray:
    """Optical centre (3,) in the local frame of X_cam = R X_local + t."""
    return np.asarray(-R_cam_from_local.T @ t_cam_from_local, dtype=np.float64)


def wrap_angle(angle: FloatArray | float) -> FloatArray:
    """Angles (rad) wrapped to [-pi, pi)."""
    return np.asarray((np.asarray(angle) + math.pi) % (2.0 * math.pi) - math.pi, dtype=np.float64)
