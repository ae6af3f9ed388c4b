"""WGS84 <-> UTM, the local origin, and V2X heading -> UTM yaw with the meridian convergence (DESIGN: frames).

A V2X heading is measured from TRUE north, clockwise; a UTM yaw from GRID east, counter-clockwise. Grid
north and true north differ by the meridian convergence gamma (pyproj's `meridian_convergence`, degrees,
positive east of the central meridian in the north): grid azimuth = heading - gamma. Several degrees off
the central meridian that is decimetres at a car's corners, so it is never skipped.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

import numpy as np
from pyproj import CRS, Proj, Transformer
from pyproj.exceptions import CRSError

from pipeline.arrays import FloatArray, Points3, PoseArray, Stamps
from pipeline.errors import InputError
from pipeline.tables import PoseTable
from schemas.common import LocalOrigin
from schemas.messages import V2xPosition, VehiclePose


def utm_epsg_for(lat_deg: float, lon_deg: float) -> str:
    """The standard WGS84/UTM zone code for a point, e.g. 'EPSG:32632' (no Norway/Svalbard exceptions)."""
    if not (-80.0 <= lat_deg <= 84.0):
        raise InputError("lat", f"lat = {lat_deg} outside the UTM range [-80, 84]")
    if not (-180.0 <= lon_deg <= 180.0):
        raise InputError("lon", f"lon = {lon_deg} outside [-180, 180]")
    zone = min(60, math.floor((lon_deg + 180.0) / 6.0) + 1)
    return f"EPSG:{32600 + zone if lat_deg >= 0 else 32700 + zone}"


@dataclass(frozen=True)
class UtmFrame:
    """Conversions between WGS84 (EPSG:4326, lon/lat order handled inside) and one UTM CRS."""

    crs: str
    _to_utm: Transformer = field(init=False, repr=False, compare=False)
    _to_wgs84: Transformer = field(init=False, repr=False, compare=False)
    _proj: Proj = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        try:
            parsed = CRS.from_user_input(self.crs)
        except CRSError as err:
            raise InputError("crs", f"crs = {self.crs!r} is not a known CRS") from err
        if parsed.utm_zone is None:
            raise InputError("crs", f"crs = {self.crs!r} is not a UTM zone")
        object.__setattr__(self, "_to_utm", Transformer.from_crs("EPSG:4326", parsed, always_xy=True))
        object.__setattr__(self, "_to_wgs84", Transformer.from_crs(parsed, "EPSG:4326", always_xy=True))
        object.__setattr__(self, "_proj", Proj(parsed))

    def to_utm(self, lat_deg: FloatArray, lon_deg: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Latitude/longitude (deg) -> easting/northing (m); heights pass through unchanged."""
        east, north = self._to_utm.transform(np.asarray(lon_deg, float), np.asarray(lat_deg, float))
        return np.asarray(east, dtype=np.float64), np.asarray(north, dtype=np.float64)

    def to_utm_point(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        """One latitude/longitude (deg) -> (easting, northing) m; ~2 us, for per-message use on the bus."""
        east, north = self._to_utm.transform(lon_deg, lat_deg)
        return float(east), float(north)

    def to_wgs84(self, east: FloatArray, north: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Easting/northing (m) -> latitude/longitude (deg)."""
        lon, lat = self._to_wgs84.transform(np.asarray(east, float), np.asarray(north, float))
        return np.asarray(lat, dtype=np.float64), np.asarray(lon, dtype=np.float64)

    def convergence_deg(self, lat_deg: FloatArray, lon_deg: FloatArray) -> FloatArray:
        """Meridian convergence gamma (deg) at the given points: grid azimuth = true azimuth - gamma."""
        factors = self._proj.get_factors(np.asarray(lon_deg, float), np.asarray(lat_deg, float))
        return np.asarray(factors.meridian_convergence, dtype=np.float64)

    def yaw_from_heading(
        self, heading_deg: FloatArray, lat_deg: FloatArray, lon_deg: FloatArray
    ) -> FloatArray:
        """True-north clockwise heading (deg) -> grid-east counter-clockwise yaw (rad) in [-pi, pi]."""
        grid_azimuth_deg = np.asarray(heading_deg, float) - self.convergence_deg(lat_deg, lon_deg)
        yaw = np.radians(90.0 - grid_azimuth_deg)
        return cast(FloatArray, np.angle(np.exp(1j * yaw)))

    def heading_from_yaw(self, yaw: FloatArray, lat_deg: FloatArray, lon_deg: FloatArray) -> FloatArray:
        """Inverse of `yaw_from_heading`: grid yaw (rad) -> true heading (deg) in [0, 360)."""
        grid_azimuth_deg = 90.0 - np.degrees(np.asarray(yaw, float))
        heading_deg = np.mod(grid_azimuth_deg + self.convergence_deg(lat_deg, lon_deg), 360.0)
        # mod of a tiny negative number rounds to 360.0, which V2xPosition rightly rejects.
        return cast(FloatArray, np.where(heading_deg >= 360.0, 0.0, heading_deg))


def pose_from_v2x(message: V2xPosition, frame: UtmFrame) -> VehiclePose:
    """V2X position (WGS84, true heading) -> VehiclePose in UTM with grid yaw; pitch/roll 0 when absent."""
    poses, rejected = poses_from_v2x([message], frame)
    if rejected:
        raise InputError("v2x", f"lat/lon = {message.lat}, {message.lon} not representable in {frame.crs}")
    return poses[0]


def poses_from_v2x(messages: Sequence[V2xPosition], frame: UtmFrame) -> tuple[list[VehiclePose], int]:
    """Many V2X positions -> VehiclePoses in one projection call (per message, pyproj's overhead would
    dominate loading a long recording). Returns the poses and how many messages had no finite UTM position."""
    if not messages:
        return [], 0
    lat = np.array([m.lat for m in messages])
    lon = np.array([m.lon for m in messages])
    east, north = frame.to_utm(lat, lon)
    yaw = frame.yaw_from_heading(np.array([m.heading_deg for m in messages]), lat, lon)
    finite = np.isfinite(east) & np.isfinite(north) & np.isfinite(yaw)
    poses = [
        VehiclePose(
            stamp_ns=m.stamp_ns,
            x=float(x),
            y=float(y),
            z=m.alt,
            yaw=float(w),
            pitch=m.pitch or 0.0,
            roll=m.roll or 0.0,
        )
        for m, x, y, w, ok in zip(messages, east, north, yaw, finite, strict=True)
        if ok
    ]
    return poses, int((~finite).sum())


def precise_v2x(
    messages: Sequence[V2xPosition], max_std_m: float, setting: str
) -> tuple[list[V2xPosition], str]:
    """The positions precise enough to calibrate from, and what was left out ("" when nothing; `setting`
    names where the limit is set): a station's reported 1-sigma accuracy (when it reports one) must be
    within `max_std_m` horizontally and twice that vertically (a GNSS height is about half as good as its
    position). RTK float and DGPS positions, 0.2-1 m off, would put the camera as far off; the receiver
    knows and says so, and its fixed positions stay usable."""
    kept = [message for message in messages if not _imprecise(message, max_std_m)]
    dropped = len(messages) - len(kept)
    if not dropped:
        return kept, ""
    return kept, (
        f"{dropped} of {len(messages)} V2X position(s) not used: the vehicle reported them less accurate "
        f"than {max_std_m} m (1 sigma, vertically twice that; {setting}): RTK float or no RTK"
    )


def _imprecise(message: V2xPosition, max_std_m: float) -> bool:
    accuracies = message.accuracies
    if accuracies is None:
        return False
    horizontal, vertical = accuracies.horizontal_m, accuracies.vertical_m
    return (horizontal is not None and horizontal > max_std_m) or (
        vertical is not None and vertical > 2.0 * max_std_m
    )


def v2x_from_pose(
    pose: VehiclePose, frame: UtmFrame, station_id: int, speed_mps: float, **extra: float | None
) -> V2xPosition:
    """VehiclePose in UTM -> V2X position with a true-north heading (what a calibration vehicle sends).

    The inverse of pose_from_v2x, used by the tests only: the oracle for the round trip and for the
    simulator's own batch conversion (sim/simulate.py, which may not import the pipeline)."""
    lat, lon = frame.to_wgs84(np.array([pose.x]), np.array([pose.y]))
    heading = frame.heading_from_yaw(np.array([pose.yaw]), lat, lon)
    heading_deg = float(heading[0])
    if heading_deg >= 360.0:  # float rounding of mod
        heading_deg = 0.0
    return V2xPosition(
        station_id=station_id,
        stamp_ns=pose.stamp_ns,
        lat=float(lat[0]),
        lon=float(lon[0]),
        alt=pose.z,
        heading_deg=heading_deg,
        speed=speed_mps,
        pitch=pose.pitch,
        roll=pose.roll,
        **extra,
    )


def local_points(points_utm: Points3, origin: LocalOrigin) -> Points3:
    """Absolute UTM (N, 3) -> local frame by subtracting the origin (float64 throughout)."""
    return cast(Points3, np.asarray(points_utm, dtype=np.float64) - np.array([origin.x, origin.y, origin.z]))


def poses_to_array(poses: Sequence[VehiclePose], origin: LocalOrigin) -> tuple[Stamps, PoseArray]:
    """VehiclePose list (or PoseTable) -> (stamps (N,) int64, PoseArray (N, 6) in the local frame)."""
    if isinstance(poses, PoseTable):
        array = poses.values.copy()
        # The same float64 subtraction as the per-pose expression below.
        array[:, 0] -= origin.x
        array[:, 1] -= origin.y
        array[:, 2] -= origin.z
        return poses.stamps.copy(), array
    stamps = np.array([p.stamp_ns for p in poses], dtype=np.int64)
    array = np.array(
        [[p.x - origin.x, p.y - origin.y, p.z - origin.z, p.yaw, p.pitch, p.roll] for p in poses],
        dtype=np.float64,
    ).reshape(-1, 6)
    return stamps, array
