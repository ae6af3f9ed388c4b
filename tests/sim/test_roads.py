"""Roads as they are: crown, kerbs and footways, vertical curves, banked bends, the flattened junction.

Expected heights are written from the road geometry by hand (an arm's centre line and its normal, a
parabola's grades), never from the simulator's own projection; the terrain is flat unless a test says so.
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.errors import SimulationError
from sim.presets import PRESETS, ArmSpec, BumpSpec, GroundSpec, RoadSpec, VerticalCurveSpec
from sim.traffic import surface_poses
from sim.world import CARRIAGEWAY, VERGE, GroundSurface, RoadNetwork, build_network, far_connector

SPEC = GroundSpec()
CROWN, KERB, BANK = SPEC.crown_slope, SPEC.kerb_height_m, SPEC.bank_slope
# A plain road along x (arm E outward east, arm W outward west), one 3.5 m lane each way.
STRAIGHT = RoadSpec(arms=(ArmSpec("E", 0.0), ArmSpec("W", 180.0)))
HALF_WIDTH = STRAIGHT.lanes_per_direction * STRAIGHT.lane_width_m
JUNCTION = RoadSpec(
    arms=(ArmSpec("E", 0.0), ArmSpec("N", 90.0), ArmSpec("W", 180.0), ArmSpec("S", 270.0)),
    lanes_per_direction=2,
)
# Left bend of 30 deg on 200 m from 100 m along the E arm, right bend of 20 deg on 250 m on the W arm.
BENT = RoadSpec(
    arms=(
        ArmSpec("E", 0.0, bend_start_m=100.0, bend_deg=30.0, bend_radius_m=200.0),
        ArmSpec("W", 180.0, bend_start_m=80.0, bend_deg=-20.0, bend_radius_m=250.0),
    )
)
# Well outside the junction's flattened area and the arm ends' kerb ramp.
STATIONS = st.floats(40.0, 250.0)


@functools.cache
def network(road: RoadSpec) -> RoadNetwork:
    return build_network(road)


def ground(road: RoadSpec, spec: GroundSpec = SPEC) -> GroundSurface:
    return GroundSurface.from_spec(spec, network(road))


def heights(surface: GroundSurface, xy: list[tuple[float, float]] | np.ndarray) -> np.ndarray:
    return surface.height(np.asarray(xy, dtype=np.float64).reshape(-1, 2))


# --- cross section: crown, kerb, footway -------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(s=STATIONS, offset=st.floats(-0.999, 0.999), east=st.booleans())  # the edge itself is the kerb face
def test_crown_falls_by_the_cross_slope_to_both_edges(s: float, offset: float, east: bool) -> None:
    surface = ground(STRAIGHT)
    x = s if east else -s
    lateral = offset * HALF_WIDTH
    z = heights(surface, [(x, lateral)])[0]
    assert z == pytest.approx(-CROWN * abs(lateral), abs=1e-9)


@settings(max_examples=40, deadline=None)
@given(s=STATIONS, side=st.sampled_from([-1.0, 1.0]), behind_m=st.floats(0.01, 30.0))
def test_kerb_steps_up_at_the_edge_to_a_level_footway_and_verge(
    s: float, side: float, behind_m: float
) -> None:
    surface = ground(STRAIGHT)
    edge = side * HALF_WIDTH
    z_in, z_out, z_behind = heights(
        surface, [(s, edge - side * 1e-4), (s, edge + side * 1e-4), (s, edge + side * behind_m)]
    )
    assert z_in == pytest.approx(-CROWN * HALF_WIDTH, abs=1e-5)
    assert z_out - z_in == pytest.approx(KERB, abs=1e-5)
    assert z_behind == pytest.approx(z_out, abs=1e-9)  # footway, then verge, level at footway height
    kinds = surface.surface_kind(
        np.array([[s, edge - side * 0.01], [s, edge + side * 0.5], [s, edge + side * 3.0]])
    )
    assert kinds.tolist() == [CARRIAGEWAY, 1, VERGE]  # footway_width_m = 2.5


def test_a_crowned_lane_rolls_the_car_toward_the_road_edge() -> None:
    """Right-hand traffic: the right lane's right side is the lower (edge) one. With R = Rz Ry Rx and the
    body's y axis to the left, Rx(roll) lifts the left side for roll > 0, so the roll is +atan(crown)."""
    surface = ground(STRAIGHT)
    lane = STRAIGHT.lane_width_m / 2.0
    xy = np.array([[60.0, -lane], [-60.0, lane]])  # eastbound and westbound, each in its right lane
    poses = surface_poses(xy, np.array([0.0, math.pi]), 4.8, 1.85, surface)
    np.testing.assert_allclose(poses[:, 5], math.atan(CROWN), atol=1e-9)
    np.testing.assert_allclose(poses[:, 4], 0.0, atol=1e-12)
    np.testing.assert_allclose(poses[:, 2], -CROWN * lane, atol=1e-9)  # contacts symmetric about the lane
    # Left-lane roll points the other way (driving on the wrong side of the crown).
    wrong = surface_poses(np.array([[60.0, lane]]), np.array([0.0]), 4.8, 1.85, surface)
    assert wrong[0, 5] == pytest.approx(-math.atan(CROWN), abs=1e-9)


# --- vertical curves -----------------------------------------------------------------------------------


@settings(max_examples=30, deadline=None)
@given(
    start=st.floats(30.0, 120.0),
    length=st.floats(30.0, 150.0),
    change=st.floats(0.005, 0.08),
    is_crest=st.booleans(),
    grade_in=st.floats(-0.05, 0.05),
)
def test_vertical_curve_is_a_parabola_joining_both_grades(
    start: float, length: float, change: float, is_crest: bool, grade_in: float
) -> None:
    """The centre line's profile: grade_in (the terrain's) up to the curve, a parabola whose grade changes
    linearly by `change` over its length, then the new grade; crests lie below the incoming tangent's
    extension, sags above it."""
    change = -change if is_crest else change
    spec = replace(
        SPEC, slope=(grade_in, 0.0), vertical_curves=(VerticalCurveSpec("E", start, length, change),)
    )
    surface = ground(STRAIGHT, spec)
    s = np.linspace(start - 20.0, start + length + 20.0, 801)
    z = heights(surface, np.column_stack([s, np.zeros_like(s)]))
    tangent = grade_in * s
    before, inside, after = s <= start, (s > start) & (s < start + length), s >= start + length
    np.testing.assert_allclose(z[before], tangent[before], atol=1e-9)
    u = s[inside] - start
    np.testing.assert_allclose(z[inside], tangent[inside] + change * u * u / (2.0 * length), atol=1e-9)
    grade_after = np.diff(z[after]) / np.diff(s[after])
    np.testing.assert_allclose(grade_after, grade_in + change, atol=1e-9)
    # Grades match at both ends (no kink): one-sided slopes over 1 mm agree.
    for joint in (start, start + length):
        left = np.diff(heights(surface, [(joint - 1e-3, 0.0), (joint, 0.0)]))[0] / 1e-3
        right = np.diff(heights(surface, [(joint, 0.0), (joint + 1e-3, 0.0)]))[0] / 1e-3
        assert left == pytest.approx(right, abs=abs(change) * 1e-3 / length * 2 + 1e-9)
    if is_crest:
        assert np.all(z[~before] - tangent[~before] < 1e-12) and z[-1] < tangent[-1]
    else:
        assert np.all(z[~before] - tangent[~before] > -1e-12) and z[-1] > tangent[-1]


def test_a_car_on_a_constant_grade_pitches_nose_up() -> None:
    """Past a sag on the E arm the grade is +3 %: driving east the nose is up, pitch = -atan(grade)."""
    spec = replace(SPEC, vertical_curves=(VerticalCurveSpec("E", 50.0, 60.0, 0.03),))
    surface = ground(STRAIGHT, spec)
    lane = STRAIGHT.lane_width_m / 2.0
    poses = surface_poses(
        np.array([[150.0, -lane], [150.0, lane]]), np.array([0.0, math.pi]), 4.8, 1.85, surface
    )
    assert poses[0, 4] == pytest.approx(-math.atan(0.03), abs=1e-6)
    assert poses[1, 4] == pytest.approx(math.atan(0.03), abs=1e-6)  # westbound: downhill, nose down
    np.testing.assert_allclose(poses[:, 5], [math.atan(CROWN), math.atan(CROWN)], atol=1e-6)


# --- banked bends --------------------------------------------------------------------------------------


def _arc_point(bend_start: float, radius: float, sweep: float, sign: float) -> tuple[np.ndarray, np.ndarray]:
    """Centre-line point of an arm along +x bending to `sign` (+1 left) and the unit normal toward the
    inside of the bend, `sweep` rad into the arc."""
    centre = np.array([bend_start, sign * radius])
    point = centre + radius * np.array([math.sin(sweep), -sign * math.cos(sweep)])
    return point, (centre - point) / radius


@settings(max_examples=40, deadline=None)
@given(fraction=st.floats(0.15, 0.85), across=st.floats(0.001, 0.999))
def test_bend_is_banked_toward_its_inside(fraction: float, across: float) -> None:
    """Well inside the E arm's left bend (beyond the runoff) the whole carriageway falls toward the inside
    by bank_slope: the inside edge is lower than the outside edge by bank_slope x width."""
    surface = ground(BENT)
    sweep = fraction * math.radians(30.0)
    point, inward = _arc_point(100.0, 200.0, sweep, 1.0)
    inside, outside = point + HALF_WIDTH * inward, point - HALF_WIDTH * inward
    z_in, z_out, z_centre = heights(surface, [inside - 1e-4 * inward, outside + 1e-4 * inward, point])
    assert z_out - z_in == pytest.approx(BANK * 2.0 * HALF_WIDTH, abs=1e-5)
    assert z_centre == pytest.approx(0.0, abs=1e-6)
    lateral = (2.0 * across - 1.0) * HALF_WIDTH
    z = heights(surface, [point + lateral * inward])[0]
    assert z == pytest.approx(-BANK * lateral, abs=1e-6)


def test_a_car_on_a_banked_bend_rolls_toward_the_inside() -> None:
    """Outbound on the E arm's left bend (right lane, heading along the arc): the inside (left) side is
    lower, so the roll is -atan(bank) whichever way the car drives; the pitch stays zero."""
    surface = ground(BENT)
    sweep = 0.5 * math.radians(30.0)
    point, inward = _arc_point(100.0, 200.0, sweep, 1.0)
    lane = BENT.lane_width_m / 2.0
    xy = np.array([point - lane * inward, point + lane * inward])  # outbound right lane, inbound right lane
    poses = surface_poses(xy, np.array([sweep, sweep + math.pi]), 4.8, 1.85, surface)
    assert poses[0, 5] == pytest.approx(-math.atan(BANK), abs=2e-4)  # 2e-4: contacts on a curved lane
    assert poses[1, 5] == pytest.approx(math.atan(BANK), abs=2e-4)  # inbound: the inside is to its right
    np.testing.assert_allclose(poses[:, 4], 0.0, atol=2e-4)


def test_right_bend_is_banked_toward_its_inside_and_runs_out_to_the_crown() -> None:
    surface = ground(BENT)
    # The W arm runs along -x: mirror the +x construction (a right bend seen from the arm stays a right bend).
    point, inward = _arc_point(80.0, 250.0, 0.5 * math.radians(20.0), -1.0)
    point, inward = -point, -inward
    z_in, z_out = heights(surface, [point + 0.999 * HALF_WIDTH * inward, point - 0.999 * HALF_WIDTH * inward])
    assert z_out - z_in == pytest.approx(BANK * 2.0 * 0.999 * HALF_WIDTH, abs=1e-6)
    # Before the runoff (2/3 of it ahead of the bend) the crown is back; along it heights change smoothly.
    runoff_start = 80.0 - 2.0 * SPEC.bank_transition_m / 3.0
    z_crown = heights(surface, [(-(runoff_start - 1.0), 3.0), (-(runoff_start - 1.0), -3.0)])
    np.testing.assert_allclose(z_crown, -CROWN * 3.0, atol=1e-9)
    # Along straight lines through the runoff (they stay on the carriageway to 5 m into the arc).
    s = np.arange(runoff_start - 5.0, 85.0, 0.05)
    for lateral in (-HALF_WIDTH + 0.5, HALF_WIDTH - 0.5):
        z = heights(surface, np.column_stack([-s, np.full_like(s, lateral)]))
        assert np.max(np.abs(np.diff(z))) < 0.05 * (BANK + CROWN) * 2.0 * HALF_WIDTH / 10.0


# --- the junction --------------------------------------------------------------------------------------


def test_junction_surface_is_continuous_except_across_kerbs() -> None:
    """400 transects of 5 cm steps in every direction across the 90 m square of a skewed two-lane
    junction with bumpy, sloped terrain and vertical curves starting inside it: neighbouring points
    differ by at most a few mm unless one is on the carriageway and the other off it (the kerb step)."""
    road = replace(PRESETS["dense-traffic"].road, arm_length_m=200.0)
    spec = replace(
        SPEC,
        slope=(0.03, -0.01),
        bumps=(BumpSpec(-20.0, 5.0, 0.6, 12.0),),
        vertical_curves=(VerticalCurveSpec("N", 15.0, 40.0, -0.05), VerticalCurveSpec("W", 20.0, 30.0, 0.04)),
    )
    surface = ground(road, spec)
    rng = np.random.default_rng(9)
    starts = rng.uniform(-45.0, 45.0, (400, 1, 2))
    angles = rng.uniform(0.0, 2.0 * math.pi, (400, 1))
    steps = np.arange(0.0, 40.0, 0.05)[None, :, None]
    lines = starts + steps * np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    xy = lines.reshape(-1, 2)
    z = surface.height(xy).reshape(lines.shape[:2])
    on_road = (surface.surface_kind(xy) == CARRIAGEWAY).reshape(lines.shape[:2])
    step = np.abs(np.diff(z, axis=1))
    kerb = np.diff(on_road.astype(np.int8), axis=1) != 0
    # The junction area only: far out between arms whose grades part, the verge is an embankment.
    inside = np.all(np.abs(lines) <= 45.0, axis=-1)
    inside = inside[:, 1:] & inside[:, :-1]
    assert step[~kerb & inside].max() < 0.005
    assert np.all(np.abs(step[kerb] - KERB) < 0.01)
    assert kerb.sum() > 100  # the kerbs are there


def test_junction_area_is_flattened() -> None:
    """Inside the junction (within the crossing roads' half width of the centre) the crowns are run out:
    the road adds nothing to the terrain there."""
    surface = ground(JUNCTION)
    half = JUNCTION.lanes_per_direction * JUNCTION.lane_width_m
    axis = np.linspace(-half, half, 41)
    grid = np.stack(np.meshgrid(axis, axis), axis=-1).reshape(-1, 2)
    np.testing.assert_allclose(surface.height(grid), 0.0, atol=1e-12)
    assert np.all(surface.surface_kind(grid) == CARRIAGEWAY)
    # ...and the crown is back further out along every arm.
    for angle in (0.0, 90.0, 180.0, 270.0):
        direction = np.array([math.cos(math.radians(angle)), math.sin(math.radians(angle))])
        left = np.array([-direction[1], direction[0]])
        z = heights(surface, [60.0 * direction + 5.0 * left, 60.0 * direction - 5.0 * left])
        np.testing.assert_allclose(z, -CROWN * 5.0, atol=1e-9)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_route_is_on_the_carriageway_and_every_camera_off_it(name: str) -> None:
    """The widest vehicle (a 2.55 m bus) on any lane or turn never puts a wheel over a kerb; every preset's
    mast stands on the verge (its height above ground is measured from there)."""
    config = PRESETS[name]
    surface = ground(config.road, config.ground)
    for route in network(config.road).routes.values():
        left = np.stack([-np.sin(route.path.yaw), np.cos(route.path.yaw)], axis=1)
        for offset in (-1.3, 0.0, 1.3):
            assert np.all(surface.surface_kind(route.path.xy + offset * left) == CARRIAGEWAY), route.name
    masts = np.array([[camera.x_m, camera.y_m] for camera in config.cameras])
    assert np.all(surface.surface_kind(masts) == VERGE)


def test_far_connectors_drive_on_one_surface() -> None:
    """Out of view, beyond the modelled site, the kerbs have ramped down: the connector from one
    traversal's exit to the next one's entry never meets a step."""
    junction = network(JUNCTION)
    surface = ground(JUNCTION)
    exit_path = junction.route("W>E").path
    entry_path = junction.route("S>W").path
    path = far_connector(exit_path, entry_path, junction.ring_radius_m)
    xy = path.at(np.arange(0.0, path.length, 0.05))[0]
    assert np.max(np.abs(np.diff(surface.height(xy)))) < 0.005


# --- the flat (ideal) world and bad specs -----------------------------------------------------------


@settings(max_examples=30, deadline=None)
@given(
    xy=st.lists(st.tuples(st.floats(-300, 300), st.floats(-300, 300)), min_size=1, max_size=20),
    slope=st.tuples(st.floats(-0.1, 0.1), st.floats(-0.1, 0.1)),
)
def test_flat_spec_is_exactly_the_plane_plus_bumps(
    xy: list[tuple[float, float]], slope: tuple[float, float]
) -> None:
    bumps = (BumpSpec(10.0, -5.0, 0.8, 12.0), BumpSpec(-40.0, 30.0, -0.5, 20.0))
    spec = GroundSpec.flat(slope=slope, bumps=bumps)
    assert spec.is_flat and not GroundSpec().is_flat
    surface = ground(JUNCTION, spec)
    assert surface.road is None
    points = np.array(xy)
    expected = points @ np.array(slope)
    for bump in bumps:
        d2 = (points[:, 0] - bump.x_m) ** 2 + (points[:, 1] - bump.y_m) ** 2
        expected = expected + bump.height_m * np.exp(-0.5 * d2 / bump.sigma_m**2)
    np.testing.assert_array_equal(surface.height(points), expected)


@pytest.mark.parametrize(
    ("spec", "field"),
    [
        (
            replace(SPEC, vertical_curves=(VerticalCurveSpec("X", 10.0, 50.0, 0.02),)),
            "ground.vertical_curves[0]",
        ),
        (
            replace(SPEC, vertical_curves=(VerticalCurveSpec("E", 10.0, 0.0, 0.02),)),
            "ground.vertical_curves[0]",
        ),
        (replace(SPEC, crown_slope=-0.02), "ground.crown_slope"),
        (replace(SPEC, kerb_height_m=float("nan")), "ground.kerb_height_m"),
        (replace(SPEC, bank_transition_m=0.0), "ground.bank_transition_m"),
    ],
)
def test_bad_ground_specs_are_refused_by_name(spec: GroundSpec, field: str) -> None:
    with pytest.raises(SimulationError) as err:
        ground(STRAIGHT, spec)
    assert err.value.source == field


@settings(max_examples=30, deadline=None)
@given(radius=st.floats(6.0, 60.0), lag=st.floats(0.5, 3.0), turn_deg=st.floats(30.0, 180.0))
def test_a_body_turns_about_its_rear_axle(radius: float, lag: float, turn_deg: float) -> None:
    """A body whose centre follows a path (30 m straight, an arc, 40 m straight) and whose rear axle lies
    `lag` behind it: the axle moves along the body's axis everywhere (its wheels do not slide sideways),
    on a long enough arc the body lags the path's tangent by asin(lag / R), and it is back on the tangent
    at the end of the last straight."""
    from sim.world import Path, arc_samples, straight_samples

    xy1, yaw1 = straight_samples(np.array([0.0, 0.0]), 0.3, 30.0)
    xy2, yaw2 = arc_samples(xy1[-1], 0.3, radius, math.radians(turn_deg))
    xy3, yaw3 = straight_samples(xy2[-1], float(yaw2[-1]), 40.0)
    path = Path.from_samples(
        np.concatenate([xy1, xy2[1:], xy3[1:]]), np.concatenate([yaw1, yaw2[1:], yaw3[1:]])
    )
    # On the path's own samples (0.25 m apart), the axle's move between the neighbouring ones.
    s = path.s
    centre, tangent = path.at(s)
    body = path.towed_yaw_at(s, lag)
    axle = centre - lag * np.column_stack([np.cos(body), np.sin(body)])
    move = axle[2:] - axle[:-2]
    heading = np.arctan2(move[:, 1], move[:, 0])
    arc_length = radius * math.radians(turn_deg)
    clear = (np.abs(s[1:-1] - 30.0) > 0.6) & (np.abs(s[1:-1] - 30.0 - arc_length) > 0.6)  # curvature steps
    assert np.max(np.abs(np.angle(np.exp(1j * (heading - body[1:-1]))))[clear]) < math.radians(0.2)
    arc_end = np.searchsorted(s, 30.0 + arc_length)
    if arc_length > 8.0 * lag:
        steady = math.asin(lag / radius)
        assert float(tangent[arc_end - 1] - body[arc_end - 1]) == pytest.approx(steady, abs=math.radians(0.1))
    assert abs(float(tangent[-1] - body[-1])) < math.radians(0.05)  # 40 m is at least 13 lags
    with pytest.raises(SimulationError, match="rear_axle_m"):
        path.towed_yaw_at(s, 0.0)
