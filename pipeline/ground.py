"""Ground plane by PCA of the driven track (paper Sec. III-F), and heights above it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.arrays import FloatArray, Points3, Vec3, check_shape
from pipeline.errors import DegenerateGeometry


@dataclass(frozen=True, slots=True)
class GroundPlaneFit:
    """Plane {p : normal . p = offset} in the local frame; `normal` is unit length and points up (+z)."""

    normal: Vec3
    offset: float

    def height_of(self, points: Points3) -> FloatArray:
        """Signed height (m) of points (N, 3) above the plane."""
        return np.asarray(points @ self.normal - self.offset, dtype=np.float64)

    def intersect_rays(self, origin: Vec3, directions: FloatArray) -> FloatArray:
        """Points (N, 3) where rays origin + s * direction (s > 0) meet the plane; NaN where they do not."""
        denom = directions @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (self.offset - origin @ self.normal) / denom
            hits = origin + s[:, None] * directions  # a ray along the plane: inf * 0, NaN, dropped below
        hits[~(s > 0)] = np.nan
        return np.asarray(hits, dtype=np.float64)


# The tilt about the track's axis is only observed when the track's cross-track spread clearly exceeds its
# out-of-plane scatter (GNSS height noise). Otherwise PCA's least-variance direction is noise and can even be
# horizontal: a straight pass with 3 cm height noise and 1 cm lateral wander gives a vertical "plane".
_MIN_ACROSS_OVER_SCATTER = 3.0
_MAX_ROAD_TILT_RAD = np.radians(30.0)  # steeper than any road: the "plane" is the track's noise


def fit_ground_plane(track_points: Points3, min_spread_m: float = 1.0) -> GroundPlaneFit:
    """Least-squares plane through the vehicle's ground track (N, 3) by PCA: the normal is the direction of
    least variance. A (nearly) straight track does not fix the tilt about itself: the road is then assumed
    level across the track. Raises DegenerateGeometry when the track spans less than `min_spread_m`."""
    check_shape(track_points, "N,3", name="track_points")
    if len(track_points) < 3:
        raise DegenerateGeometry(f"ground plane: {len(track_points)} points, need at least 3")
    centroid = track_points.mean(axis=0)
    _, singular, vt = np.linalg.svd(track_points - centroid, full_matrices=False)
    spread = singular / np.sqrt(len(track_points))
    normal = vt[2]
    if spread[0] < min_spread_m:
        raise DegenerateGeometry(f"ground plane: track spans only {spread[0]:.2f} m")
    is_line = spread[1] < max(1e-3 * spread[0], _MIN_ACROSS_OVER_SCATTER * spread[2])
    if is_line or abs(normal[2]) < np.cos(_MAX_ROAD_TILT_RAD):
        # A (nearly) straight track: the plane's tilt about the track is unobservable; assume the road is
        # level across its width (normal orthogonal to the track and to horizontal).
        along = vt[0]
        across = np.cross(along, np.array([0.0, 0.0, 1.0]))
        normal = np.cross(across, along)
        if np.linalg.norm(normal) < 1e-9:
            raise DegenerateGeometry("ground plane: vertical track")
    normal = normal / np.linalg.norm(normal)
    if normal[2] < 0:
        normal = -normal
    return GroundPlaneFit(normal=normal, offset=float(normal @ centroid))
