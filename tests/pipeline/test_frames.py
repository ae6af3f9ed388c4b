"""WGS84 <-> UTM and V2X true heading -> grid yaw, checked against pyproj's geodesics, not our formulas.

The reference yaw is measured: walk 10 m along the true heading on the ellipsoid (pyproj.Geod.fwd) and
take the direction of that displacement in UTM. Several degrees from the central meridian the meridian
convergence exceeds 2 deg there, so skipping it fails these tests by a wide margin.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pyproj import CRS, Geod, Proj, Transformer

from pipeline.errors import InputError
from pipeline.frames import (
    UtmFrame,
    local_points,
    pose_from_v2x,
    poses_to_array,
    precise_v2x,
    utm_epsg_for,
    v2x_from_pose,
)
from schemas.common import LocalOrigin
from schemas.messages import V2xAccuracies, V2xPosition, VehiclePose

STAMP = 1_700_000_000_000_000_000
WGS84 = Geod(ellps="WGS84")
YAW_TOL_DEG = 1e-4  # the 10 m chord vs the grid tangent differs by ~3e-6 deg; the convergence is degrees

# (lat, lon, crs): far from the central meridian so the convergence is large (zone 32's meridian is 9 E,
# zone 59's is 171 E), one per hemisphere; and one on the central meridian where it vanishes.
FAR_NORTH = (48.4, 14.2, "EPSG:32632")
FAR_SOUTH = (-45.0, 168.0, "EPSG:32759")
ON_MERIDIAN = (48.4, 9.0, "EPSG:32632")


@functools.cache
def frame_for(crs: str) -> UtmFrame:
    return UtmFrame(crs)


@functools.cache
def wgs84_to(crs: str) -> Transformer:
    return Transformer.from_crs("EPSG:4326", crs, always_xy=True)


def angle_diff_deg(a_deg: float, b_deg: float) -> float:
    return abs((a_deg - b_deg + 180.0) % 360.0 - 180.0)


def measured_grid_yaw_deg(lat: float, lon: float, heading_deg: float, crs: str) -> float:
    """Grid yaw (deg from grid east, ccw) of a 10 m walk along the true heading, measured in UTM."""
    lon2, lat2, _ = WGS84.fwd(lon, lat, heading_deg, 10.0)
    (e1, e2), (n1, n2) = wgs84_to(crs).transform([lon, lon2], [lat, lat2])
    return math.degrees(math.atan2(n2 - n1, e2 - e1))


def v2x(lat: float, lon: float, heading_deg: float, **extra: float) -> V2xPosition:
    return V2xPosition(
        station_id=7,
        stamp_ns=STAMP,
        lat=lat,
        lon=lon,
        alt=250.0,
        heading_deg=heading_deg,
        speed=10.0,
        **extra,
    )


# --- zones -----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("lat", "lon", "expected"),
    [
        (48.4, 14.2, "EPSG:32633"),
        (48.4, 11.999999, "EPSG:32632"),
        (48.4, 12.0, "EPSG:32633"),  # a zone edge belongs to the zone east of it
        (0.0, 0.0, "EPSG:32631"),
        (0.0, -0.000001, "EPSG:32630"),
        (-0.000001, 0.0, "EPSG:32731"),  # south of the equator: the 327xx codes
        (-33.9, 18.4, "EPSG:32734"),
        (-45.0, 168.0, "EPSG:32759"),  # the west edge of zone 59 (171 E)
        (84.0, -180.0, "EPSG:32601"),
        (-80.0, 180.0, "EPSG:32760"),  # 180 E is the east edge of zone 60, not a zone 61
        (10.0, 179.999999, "EPSG:32660"),
    ],
)
def test_utm_zone_from_longitude(lat: float, lon: float, expected: str) -> None:
    assert utm_epsg_for(lat, lon) == expected


@pytest.mark.parametrize(
    ("lat", "lon", "field"),
    [
        (84.01, 0.0, "lat"),
        (-80.01, 0.0, "lat"),
        (math.nan, 0.0, "lat"),
        (10.0, 180.5, "lon"),
        (10.0, -181.0, "lon"),
        (10.0, math.nan, "lon"),
    ],
)
def test_utm_zone_outside_utm_is_refused(lat: float, lon: float, field: str) -> None:
    with pytest.raises(InputError) as info:
        utm_epsg_for(lat, lon)
    assert info.value.source == field


@settings(max_examples=100, deadline=None)
@given(lat=st.floats(-80.0, 84.0), lon=st.floats(-180.0, 180.0))
def test_chosen_zone_is_the_one_whose_central_meridian_is_nearest(lat: float, lon: float) -> None:
    code = utm_epsg_for(lat, lon)
    zone = CRS.from_user_input(code).utm_zone
    assert zone is not None and zone.endswith("N" if lat >= 0 else "S")
    number = int(zone[:-1])
    base = 32600 if lat >= 0 else 32700

    def off_meridian_m(n: int) -> float:
        east, _ = wgs84_to(f"EPSG:{base + (n - 1) % 60 + 1}").transform(lon, lat)
        return abs(float(east) - 500_000.0)

    # Measured in each zone's own projection: no neighbouring zone has the point nearer its meridian.
    assert off_meridian_m(number) <= min(off_meridian_m(number - 1), off_meridian_m(number + 1)) + 1e-3


def test_utm_frame_refuses_a_non_utm_crs() -> None:
    with pytest.raises(InputError, match="not a UTM zone"):
        UtmFrame("EPSG:3857")


# --- heading -> yaw with the meridian convergence --------------------------------------------------------


@pytest.mark.parametrize(("lat", "lon", "crs"), [FAR_NORTH, FAR_SOUTH])
def test_convergence_is_pyprojs_and_large_away_from_the_central_meridian(
    lat: float, lon: float, crs: str
) -> None:
    gamma = float(frame_for(crs).convergence_deg(np.array([lat]), np.array([lon]))[0])
    reference = Proj(crs).get_factors(lon, lat).meridian_convergence
    assert gamma == pytest.approx(reference, abs=1e-12)
    assert abs(gamma) > 2.0  # so a missing correction is caught by the yaw tests
    # Grid north seen from true north: measured, not taken from any formula.
    assert measured_grid_yaw_deg(lat, lon, 0.0, crs) == pytest.approx(90.0 + gamma, abs=YAW_TOL_DEG)


@pytest.mark.parametrize(("lat", "lon", "crs"), [FAR_NORTH, FAR_SOUTH, ON_MERIDIAN])
@settings(max_examples=60, deadline=None)
@given(heading_deg=st.floats(0.0, 360.0, exclude_max=True))
def test_yaw_is_the_measured_grid_direction_of_travel(
    lat: float, lon: float, crs: str, heading_deg: float
) -> None:
    pose = pose_from_v2x(v2x(lat, lon, heading_deg), frame_for(crs))
    expected_deg = measured_grid_yaw_deg(lat, lon, heading_deg, crs)
    assert angle_diff_deg(math.degrees(pose.yaw), expected_deg) < YAW_TOL_DEG
    naive_deg = 90.0 - heading_deg  # what forgetting the convergence would give
    if (lat, lon, crs) == ON_MERIDIAN:
        assert angle_diff_deg(math.degrees(pose.yaw), naive_deg) < YAW_TOL_DEG
    else:
        assert angle_diff_deg(math.degrees(pose.yaw), naive_deg) > 2.0


@pytest.mark.parametrize(("lat", "lon", "crs"), [FAR_NORTH, FAR_SOUTH])
def test_pose_position_is_pyprojs_utm(lat: float, lon: float, crs: str) -> None:
    pose = pose_from_v2x(v2x(lat, lon, 10.0, pitch=0.05, roll=-0.02), frame_for(crs))
    east, north = wgs84_to(crs).transform(lon, lat)
    assert (pose.x, pose.y, pose.z) == pytest.approx((east, north, 250.0), abs=1e-6)
    assert (pose.stamp_ns, pose.pitch, pose.roll) == (STAMP, 0.05, -0.02)


def test_missing_pitch_and_roll_become_zero() -> None:
    pose = pose_from_v2x(v2x(*FAR_NORTH[:2], 10.0), frame_for(FAR_NORTH[2]))
    assert (pose.pitch, pose.roll) == (0.0, 0.0)


@pytest.mark.parametrize(
    ("heading_deg", "yaw_deg"), [(0.0, 90.0), (90.0, 0.0), (180.0, -90.0), (270.0, 180.0), (359.0, 91.0)]
)
def test_yaw_on_the_central_meridian_and_its_wrapping(heading_deg: float, yaw_deg: float) -> None:
    lat, lon, crs = ON_MERIDIAN
    yaw = frame_for(crs).yaw_from_heading(np.array([heading_deg]), np.array([lat]), np.array([lon]))
    assert angle_diff_deg(math.degrees(float(yaw[0])), yaw_deg) < 1e-9
    assert -math.pi <= float(yaw[0]) <= math.pi


@settings(max_examples=100, deadline=None)
@given(heading_deg=st.floats(0.0, 360.0, exclude_max=True), turns=st.integers(-3, 3))
def test_heading_from_yaw_inverts_and_stays_below_360(heading_deg: float, turns: int) -> None:
    lat, lon, crs = FAR_NORTH
    frame = frame_for(crs)
    lat_a, lon_a = np.array([lat]), np.array([lon])
    yaw = frame.yaw_from_heading(np.array([heading_deg]), lat_a, lon_a)
    assert -math.pi <= float(yaw[0]) <= math.pi
    back = float(frame.heading_from_yaw(yaw + 2.0 * math.pi * turns, lat_a, lon_a)[0])
    assert 0.0 <= back < 360.0
    assert angle_diff_deg(back, heading_deg) < 1e-9


def test_due_north_round_trip_is_zero_not_360() -> None:
    lat, lon, crs = FAR_NORTH
    frame = frame_for(crs)
    yaw = frame.yaw_from_heading(np.array([0.0]), np.array([lat]), np.array([lon]))
    heading = float(frame.heading_from_yaw(yaw, np.array([lat]), np.array([lon]))[0])
    assert 0.0 <= heading < 1e-9 or heading == 0.0


# --- round trips over whole zones ------------------------------------------------------------------------


@st.composite
def points_in_a_zone(draw: st.DrawFn) -> tuple[float, float, str]:
    """(lat, lon, crs): a point within its zone's 6 degrees, both hemispheres, UTM latitudes."""
    zone = draw(st.integers(1, 60))
    lat = draw(st.floats(-80.0, 84.0))
    lon = draw(st.floats(-3.0, 3.0)) + (-183.0 + 6.0 * zone)
    return lat, lon, f"EPSG:{(32600 if lat >= 0 else 32700) + zone}"


@settings(max_examples=100, deadline=None)
@given(point=points_in_a_zone())
def test_latlon_to_utm_and_back_is_sub_millimetre(point: tuple[float, float, str]) -> None:
    lat, lon, crs = point
    frame = frame_for(crs)
    east, north = frame.to_utm(np.array([lat]), np.array([lon]))
    lat2, lon2 = frame.to_wgs84(east, north)
    _, _, distance_m = WGS84.inv(lon, lat, float(lon2[0]), float(lat2[0]))
    assert distance_m < 1e-3


@settings(max_examples=100, deadline=None)
@given(
    point=points_in_a_zone(),
    z=st.floats(-400.0, 5000.0),
    yaw=st.floats(-math.pi, math.pi),
    pitch=st.floats(-0.3, 0.3),
    roll=st.floats(-0.3, 0.3),
)
def test_pose_to_v2x_to_pose_is_sub_millimetre(
    point: tuple[float, float, str], z: float, yaw: float, pitch: float, roll: float
) -> None:
    lat, lon, crs = point
    frame = frame_for(crs)
    east, north = frame.to_utm(np.array([lat]), np.array([lon]))
    pose = VehiclePose(
        stamp_ns=STAMP, x=float(east[0]), y=float(north[0]), z=z, yaw=yaw, pitch=pitch, roll=roll
    )
    message = v2x_from_pose(pose, frame, station_id=9, speed_mps=12.5, length=4.5)
    assert 0.0 <= message.heading_deg < 360.0
    assert (message.station_id, message.stamp_ns, message.speed, message.length) == (9, STAMP, 12.5, 4.5)
    back = pose_from_v2x(message, frame)
    assert math.hypot(back.x - pose.x, back.y - pose.y) < 1e-3
    assert back.z == z and back.stamp_ns == STAMP
    assert angle_diff_deg(math.degrees(back.yaw), math.degrees(yaw)) < 1e-7
    assert (back.pitch, back.roll) == (pitch, roll)


# --- local frame -----------------------------------------------------------------------------------------

ORIGIN = LocalOrigin(crs="EPSG:32632", x=512_000.0, y=5_400_000.0, z=100.0)


def test_local_points_subtract_the_origin() -> None:
    utm = np.array([[512_010.25, 5_400_020.5, 103.0], [511_990.0, 5_399_999.0, 99.5]])
    local = local_points(utm, ORIGIN)
    assert local.dtype == np.float64 and local.shape == (2, 3)
    np.testing.assert_array_equal(local, [[10.25, 20.5, 3.0], [-10.0, -1.0, -0.5]])


def test_poses_to_array_is_local_and_in_pose_array_order() -> None:
    poses = [
        VehiclePose(stamp_ns=STAMP, x=512_001.0, y=5_400_002.0, z=103.0, yaw=0.5, pitch=0.01, roll=-0.02),
        VehiclePose(stamp_ns=STAMP + 100_000_000, x=512_011.0, y=5_400_012.0, z=104.0, yaw=-3.0),
    ]
    stamps, array = poses_to_array(poses, ORIGIN)
    assert stamps.dtype == np.int64 and array.dtype == np.float64
    np.testing.assert_array_equal(stamps, [STAMP, STAMP + 100_000_000])
    np.testing.assert_array_equal(
        array, [[1.0, 2.0, 3.0, 0.5, 0.01, -0.02], [11.0, 12.0, 4.0, -3.0, 0.0, 0.0]]
    )


def test_poses_to_array_of_nothing_has_the_right_shapes() -> None:
    stamps, array = poses_to_array([], ORIGIN)
    assert stamps.shape == (0,) and array.shape == (0, 6)


def _reported(stamp: int, horizontal: float | None, vertical: float | None) -> V2xPosition:
    accuracies = (
        None
        if horizontal is None and vertical is None
        else V2xAccuracies(horizontal_m=horizontal, vertical_m=vertical)
    )
    return V2xPosition(
        station_id=1,
        stamp_ns=1_700_000_000_000_000_000 + stamp,
        lat=48.0,
        lon=9.0,
        alt=500.0,
        heading_deg=0.0,
        speed=10.0,
        accuracies=accuracies,
    )


def test_positions_reported_imprecise_are_left_out_and_counted() -> None:
    # RTK fixed (1-3 cm), its height (twice), none reported (kept), RTK float horizontally, then vertically;
    # the limits themselves are still precise enough.
    messages = [
        _reported(0, 0.014, 0.028),
        _reported(1, None, None),
        _reported(2, 0.1, 0.2),
        _reported(3, 0.35, 0.7),
        _reported(4, 0.02, 0.25),
        _reported(5, None, 0.5),
        _reported(6, 0.5, None),
        _reported(7, 0.05, None),
    ]
    kept, note = precise_v2x(messages, 0.1, "the limit")
    assert [m.stamp_ns - 1_700_000_000_000_000_000 for m in kept] == [0, 1, 2, 7]
    assert note == (
        "4 of 8 V2X position(s) not used: the vehicle reported them less accurate than 0.1 m (1 sigma, "
        "vertically twice that; the limit): RTK float or no RTK"
    )
    assert precise_v2x(messages, 1.0, "the limit") == (messages, "")
    assert precise_v2x([], 0.1, "the limit") == ([], "")
