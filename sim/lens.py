"""The simulated camera's lens: OpenCV's pinhole + [k1, k2, p1, p2, k3] model (or the rational model's
[k1, k2, p1, p2, k3, k4, k5, k6]), through OpenCV itself.

It projects with cv2.projectPoints and inverts the lens with cv2.undistortPoints (tight stopping
criterion), never with the pipeline's own numpy projection: a sign or convention slip in either shows up
as a calibration error instead of cancelling out.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from schemas.common import CameraIntrinsics
from sim.geometry import FloatArray


def opencv_undistort(
    pixels: FloatArray, K: FloatArray, dist: FloatArray, criteria: tuple[int, int, float]
) -> FloatArray:
    """OpenCV's iterative undistortion of pixels (N, 2) to normalised coordinates (N, 2), run until
    `criteria` (type, count, eps) is met, on OpenCV 4 (undistortPointsIter) and 5 (undistortPoints, which
    took the criteria over)."""
    src = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
    if hasattr(cv2, "undistortPointsIter"):
        xy = cv2.undistortPointsIter(src, K, dist, None, None, criteria)
    else:
        xy = cv2.undistortPoints(src, K, dist, criteria=criteria)
    return np.asarray(xy, dtype=np.float64).reshape(-1, 2)


# A point closer than this to the camera plane (m) cannot be imaged: no detector box exists then.
NEAR_PLANE_M = 0.5
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


@dataclass(frozen=True, eq=False)
class Lens:
    """Intrinsics as OpenCV wants them: K (3, 3), dist (5,) or (8,), image size; `valid_radius` is the largest
    undistorted normalised radius the polynomial is trusted at (it folds back far outside the image)."""

    K: FloatArray
    dist: FloatArray
    width: int
    height: int
    valid_radius: float

    @staticmethod
    def from_intrinsics(intrinsics: CameraIntrinsics, margin: float = 1.15) -> Lens:
        K = np.array(
            [[intrinsics.fx, 0.0, intrinsics.cx], [0.0, intrinsics.fy, intrinsics.cy], [0.0, 0.0, 1.0]]
        )
        dist = np.array(intrinsics.dist, dtype=np.float64)
        lens = Lens(K, dist, intrinsics.width, intrinsics.height, float("inf"))
        if not np.any(dist != 0.0):
            return lens
        radius = float(np.max(np.hypot(*lens.undistort(lens.border_pixels(4)).T)))
        return Lens(K, dist, intrinsics.width, intrinsics.height, margin * radius)

    def border_pixels(self, per_side: int) -> FloatArray:
        """`per_side` points along each image edge, going round the border once (top left to right, right
        side down, bottom right to left, left side up): (4 * per_side, 2) pixels."""
        along = np.linspace(0.0, 1.0, per_side, endpoint=False)
        w, h = float(self.width), float(self.height)
        zeros, ones = np.zeros(per_side), np.ones(per_side)
        return np.concatenate(
            [
                np.column_stack([along * w, zeros]),
                np.column_stack([ones * w, along * h]),
                np.column_stack([(1 - along) * w, ones * h]),
                np.column_stack([zeros, (1 - along) * h]),
            ]
        )

    def project_cam(self, points_cam: FloatArray) -> tuple[FloatArray, np.ndarray]:
        """Camera-frame points (N, 3) -> distorted pixels (N, 2) and whether each is imageable (N,): in
        front of the near plane and inside the lens model's trusted radius. Others get NaN pixels."""
        points_cam = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        z = points_cam[:, 2]
        ok = z > NEAR_PLANE_M
        with np.errstate(divide="ignore", invalid="ignore"):
            radius = np.hypot(points_cam[:, 0], points_cam[:, 1]) / z
        ok &= radius <= self.valid_radius
        pixels = np.full((len(points_cam), 2), np.nan)
        if np.any(ok):
            projected, _ = cv2.projectPoints(points_cam[ok], np.zeros(3), np.zeros(3), self.K, self.dist)
            pixels[ok] = projected.reshape(-1, 2)
        return pixels, ok

    def undistort(self, pixels: FloatArray) -> FloatArray:
        """Distorted pixels (N, 2) -> undistorted normalised coordinates (N, 2) (x/z, y/z)."""
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if len(pixels) == 0:
            return np.zeros((0, 2))
        return opencv_undistort(pixels, self.K, self.dist, _UNDISTORT_CRITERIA)

    def view_bounds(self) -> FloatArray:
        """Normalised image-plane bounds [x_min, y_min, x_max, y_max] (undistorted) of the image."""
        xy = self.undistort(self.border_pixels(16))
        return np.array([xy[:, 0].min(), xy[:, 1].min(), xy[:, 0].max(), xy[:, 1].max()])
