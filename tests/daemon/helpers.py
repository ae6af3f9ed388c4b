"""Shared helpers for daemon tests: polling with a deadline (never fixed sleeps) and free loopback ports."""

from __future__ import annotations

import time
from collections.abc import Callable

from daemon.bus import free_loopback_port as free_port
from schemas.common import CameraIntrinsics

__all__ = ["free_port", "ros_camera_info", "wait_until"]


def ros_camera_info(intrinsics: CameraIntrinsics, model: str = "plumb_bob") -> dict[str, object]:
    """The camera as ROS's camera_calibration saves it (ost.yaml), as YAML data."""
    k = intrinsics
    return {
        "image_width": k.width,
        "image_height": k.height,
        "camera_name": "rsu_cam",
        "camera_matrix": {"rows": 3, "cols": 3, "data": [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0]},
        "distortion_model": model,
        "distortion_coefficients": {"rows": 1, "cols": len(k.dist), "data": list(k.dist)},
    }


def wait_until(predicate: Callable[[], object], timeout_s: float = 10.0, interval_s: float = 0.01) -> None:
    """Poll `predicate` until it returns something truthy; AssertionError after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        if predicate():
            return
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout_s} s")
        time.sleep(interval_s)
