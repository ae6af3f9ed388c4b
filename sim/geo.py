"""Where the simulated world is on the Earth: UTM <-> WGS84 and true-north headings, via pyproj.

Headings come from the geodesic azimuth between a vehicle's position and a point a metre ahead of it along
its grid yaw, not from a meridian-convergence formula: the pipeline corrects for convergence with its own
formula, and the two must agree only because both are right.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pyproj import CRS, Geod, Transformer
from pyproj.exceptions import CRSError

from sim.errors import SimulationError
from sim.geometry import FloatArray

_STEP_M = 1.0  # the look-ahead of a heading (m): far below the grid's curvature, far above float noise


@dataclass(frozen=True)
class GeoFrame:
    """One UTM zone (an EPSG code) and its conversions to WGS84 latitude/longitude (degrees)."""

    crs: str
    _to_wgs84: Transformer = field(init=False, repr=False, compare=False)
    _geod: Geod = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        try:
            parsed = CRS.from_user_input(self.crs)
        except CRSError as err:
            raise SimulationError("crs", f"crs = {self.crs!r} is not a known CRS") from err
        if parsed.utm_zone is None:
            raise SimulationError("crs", f"crs = {self.crs!r} is not a UTM zone")
        object.__setattr__(self, "_to_wgs84", Transformer.from_crs(parsed, "EPSG:4326", always_xy=True))
        object.__setattr__(self, "_geod", Geod(ellps="WGS84"))

    def to_wgs84(self, east: FloatArray, north: FloatArray) -> tuple[FloatArray, FloatArray]:
        """UTM easting/northing (m) -> latitude, longitude (deg)."""
        lon, lat = self._to_wgs84.transform(np.asarray(east, float), np.asarray(north, float))
        return np.asarray(lat, dtype=np.float64), np.asarray(lon, dtype=np.float64)

    def true_heading_deg(self, east: FloatArray, north: FloatArray, yaw: FloatArray) -> FloatArray:
        """Heading (deg from true north, clockwise, [0, 360)) of a body at UTM (east, north) whose grid yaw
        (rad from grid east, counter-clockwise) is `yaw`."""
        east, north, yaw = (np.asarray(a, dtype=np.float64) for a in (east, north, yaw))
        lat0, lon0 = self.to_wgs84(east, north)
        lat1, lon1 = self.to_wgs84(east + _STEP_M * np.cos(yaw), north + _STEP_M * np.sin(yaw))
        azimuth, _, _ = self._geod.inv(lon0, lat0, lon1, lat1)
        heading_deg = np.mod(np.asarray(azimuth, dtype=np.float64), 360.0)
        return np.asarray(np.where(heading_deg >= 360.0, 0.0, heading_deg), dtype=np.float64)
