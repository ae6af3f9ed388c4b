"""Vehicle bodies of the simulated world, in the vehicle frame of docs/design.md (x forward, y left, z up; the
data-sheet box [0, L] x [0, W] x [0, H] with its origin at the rear-right-bottom corner).

This module places bodies in the world from the pose of their reference point (the IMU, `imu_offset` in
that frame) or of their footprint centre, gives the data-sheet box's corner points, and draws real body
shapes (issue 9): `draw_body` returns a closed triangle mesh (BodyShape: vertices, faces, wheel contacts,
every drawn proportion) of a sedan, hatchback, estate, SUV, van, pickup, truck or bus whose data-sheet
L x W x H (mirrors and roof box excluded) it fills; `cuboid_body` is the `ideal` world's box as a mesh.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TypeAlias

import numpy as np

from schemas.common import VehicleProfile
from sim.errors import SimulationError
from sim.geometry import FloatArray, IntArray, attitude_matrices
from sim.world import UNIT_BOX_CORNERS


def place_points(poses: FloatArray, points_body: FloatArray, anchor_body: FloatArray) -> FloatArray:
    """Body-frame points (K, 3) -> local frame (N, K, 3) for bodies whose point `anchor_body` (3,) has
    the poses (N, 6) = x, y, z, yaw, pitch, roll."""
    R = attitude_matrices(poses[:, 3], poses[:, 4], poses[:, 5])
    relative = points_body - anchor_body
    return np.asarray(np.einsum("nij,kj->nki", R, relative) + poses[:, None, :3], dtype=np.float64)


def reference_from_footprint_centre(centre_poses: FloatArray, vehicle: VehicleProfile) -> FloatArray:
    """Poses (N, 6) of the footprint centre (L/2, W/2, 0) -> poses (N, 6) of the reference point."""
    anchor = np.array([vehicle.length / 2.0, vehicle.width / 2.0, 0.0])
    reference = place_points(centre_poses, np.asarray([vehicle.imu_offset], dtype=np.float64), anchor)[:, 0]
    return np.column_stack([reference, centre_poses[:, 3:]])


def cuboid_points(vehicle: VehicleProfile) -> FloatArray:
    """The data-sheet box's 8 corners (8, 3) in the vehicle frame: base RR, FR, FL, RL, then the top."""
    return np.asarray(
        UNIT_BOX_CORNERS * np.array([vehicle.length, vehicle.width, vehicle.height]), dtype=np.float64
    )


def footprint_points(vehicle: VehicleProfile) -> FloatArray:
    """The data-sheet footprint's 4 corners (4, 3): rear-right, front-right, front-left, rear-left."""
    return cuboid_points(vehicle)[:4]


# ---------------------------------------------------------------------------------------------------------
# Real vehicle body shapes (issue 9): a detector's box is the tight rectangle of the projected SHAPE, never
# of the L x W x H cuboid the calibration method fits.
#
# Ranges are data-sheet values of typical European vehicles (manufacturers' dimension drawings, mirrors and
# roof boxes excluded), e.g. sedan: VW Passat 4.775/1.832/1.456 m, Audi A4 4.762/1.847/1.431, BMW 3 (G20)
# 4.709/1.827/1.442, Skoda Octavia 4.689/1.829/1.470; hatchback: VW Polo 4.074/1.751/1.451, Golf 8
# 4.284/1.789/1.456, Ford Focus 4.378/1.825/1.454; estate: Passat Variant 4.773/1.832/1.516, Focus Turnier
# 4.668/1.825/1.481; SUV: VW Tiguan 4.509/1.859/1.675, BMW X3 4.708/1.891/1.676, Audi Q5 4.682/1.893/1.662;
# van: VW Transporter 4.904/1.904/1.990, Ford Transit 5.531/2.059/2.550, Mercedes Sprinter 5.932/2.020/2.356;
# pickup: Toyota Hilux DC 5.325/1.855/1.815, Ford Ranger DC 5.370/1.918/1.884; rigid truck 7.5-18 t (MAN TGL/
# TGM, Mercedes Atego with box body): 7.5-10.5 m, box 2.55 m wide (EU 96/53/EC maximum), 3.2-4.0 m tall;
# city bus: Mercedes Citaro 12.135/2.550/3.120, MAN Lion's City 12.2/2.55/3.3. Proportions not printed in
# data sheets (bonnet, deck, rakes, insets, radii) are read off the same vehicles' side and top dimension
# drawings to about +-5 cm, and the ranges are widened to cover the class. Tyre radii follow from the ETRTO
# sizes fitted (205/55R16: 0.316 m, 235/55R18: 0.358 m, 235/65R16C: 0.350 m, 265/65R17: 0.386 m,
# 295/80R22.5: 0.522 m, 315/80R22.5: 0.538 m, 275/70R22.5: 0.478 m); mirror overhangs from the data
# sheets' width with and without mirrors (Golf 2.027 vs 1.789 m: 0.12 per side; Transit 2.474 vs 2.059 m:
# 0.21; trucks and buses 2.9-3.2 m over mirrors on 2.55 m bodies: 0.2-0.33).
# Units: metres, except *_deg (degrees, rakes and tumblehome measured from the vertical) and *_frac
# (fractions of the data-sheet length L).
# ---------------------------------------------------------------------------------------------------------

VEHICLE_TYPES = ("sedan", "hatchback", "estate", "suv", "van", "pickup", "truck", "bus")

Range: TypeAlias = tuple[float, float]

_SEDAN: dict[str, Range] = {
    "length_m": (4.40, 5.10),
    "width_m": (1.75, 1.90),
    "height_m": (1.40, 1.50),
    "clearance_m": (0.12, 0.16),  # sill / underbody height, laden data-sheet values 120-160 mm
    "front_bumper_low_m": (0.20, 0.30),  # lower edge of the front apron (approach angle 12-16 deg)
    "front_bumper_m": (0.40, 0.55),  # height of the bumper's foremost point
    "rear_bumper_low_m": (0.28, 0.40),
    "rear_bumper_m": (0.50, 0.65),
    "bonnet_front_m": (0.62, 0.78),  # bonnet leading edge; pedestrian-protection rules keep it high
    "nose_setback_m": (0.08, 0.20),  # bonnet leading edge behind the bumper face
    "bonnet_frac": (0.25, 0.30),  # front face to windscreen base (Passat: 1.30 m of 4.78 m)
    "belt_m": (0.92, 1.02),  # side-window sill line = cowl height
    "deck_drop_m": (0.0, 0.08),  # boot-lid rear edge below the belt
    "deck_frac": (0.18, 0.23),  # rear face to rear-window base (sedan boot)
    "deck_round_m": (0.05, 0.15),  # boot-lid edge behind the rear face
    "windscreen_rake_deg": (58.0, 66.0),  # windscreens of cars lean 24-32 deg from the horizontal
    "rear_window_rake_deg": (50.0, 64.0),
    "cabin_inset_m": (0.06, 0.12),  # greenhouse base inside the body side (shoulder), per side
    "tumblehome_deg": (15.0, 25.0),  # side glass inclination: roof 1.20-1.40 m wide on a 1.8 m body
    "roof_round_m": (0.03, 0.06),  # roof crown: the roof edge lies this far below H and inside the roof
    "sill_inset_m": (0.04, 0.09),  # rocker panel inside the widest point (door shoulder)
    "shoulder_inset_m": (0.01, 0.04),  # belt line inside the widest point
    "front_radius_m": (0.35, 0.55),  # plan-view corner radius of the front bumper
    "rear_radius_m": (0.30, 0.50),
    "cabin_front_radius_m": (0.25, 0.45),  # plan-view curvature of the windscreen base / roof front
    "cabin_rear_radius_m": (0.25, 0.45),
    "front_lip_m": (0.05, 0.15),  # apron's lower edge behind the bumper face
    "rear_lip_m": (0.05, 0.12),
    "underbody_front_frac": (0.45, 0.75),  # share of the front overhang whose underside rises to the apron
    "underbody_rear_frac": (0.45, 0.75),
    "front_overhang_frac": (0.17, 0.21),  # Passat 0.94 m of 4.78, BMW 3 0.79 of 4.71
    "rear_overhang_frac": (0.20, 0.24),
    "wheel_radius_m": (0.31, 0.34),
    "tyre_width_m": (0.205, 0.245),
    "rear_tyre_width_m": (0.205, 0.245),
    "tyre_gap_m": (0.005, 0.04),  # outer sidewall inside the body side (BMW 3: 6 mm, Golf: 19 mm)
    "mirror_out_m": (0.09, 0.13),
    "mirror_rise_m": (0.05, 0.15),  # mirror centre above the belt
    "mirror_height_m": (0.12, 0.16),
    "mirror_depth_m": (0.10, 0.15),
    "mirror_setback_m": (0.0, 0.20),  # mirror centre behind the windscreen base
}
_HATCHBACK = _SEDAN | {
    "length_m": (3.90, 4.45),
    "width_m": (1.70, 1.86),
    "height_m": (1.40, 1.52),
    "bonnet_frac": (0.23, 0.28),
    "deck_frac": (0.01, 0.04),  # steep tailgate: the rear glass starts almost at the rear face
    "deck_drop_m": (0.0, 0.05),
    "deck_round_m": (0.02, 0.06),
    "rear_window_rake_deg": (25.0, 45.0),
    "front_overhang_frac": (0.19, 0.22),  # Golf 0.88 m of 4.28
    "rear_overhang_frac": (0.16, 0.20),
    "wheel_radius_m": (0.30, 0.33),
    "tyre_width_m": (0.185, 0.225),
    "rear_tyre_width_m": (0.185, 0.225),
}
_ESTATE = _SEDAN | {
    "length_m": (4.55, 4.95),
    "width_m": (1.78, 1.90),
    "height_m": (1.43, 1.53),
    "deck_frac": (0.01, 0.03),
    "deck_drop_m": (0.0, 0.05),
    "deck_round_m": (0.02, 0.06),
    "rear_window_rake_deg": (12.0, 28.0),  # near-vertical tailgate
}
_SUV = _SEDAN | {
    "length_m": (4.20, 4.95),
    "width_m": (1.80, 1.95),
    "height_m": (1.58, 1.76),
    "clearance_m": (0.17, 0.22),
    "front_bumper_low_m": (0.30, 0.40),
    "front_bumper_m": (0.50, 0.65),
    "rear_bumper_low_m": (0.38, 0.48),
    "rear_bumper_m": (0.60, 0.75),
    "bonnet_front_m": (0.85, 0.98),
    "bonnet_frac": (0.24, 0.28),
    "belt_m": (1.02, 1.15),
    "deck_frac": (0.01, 0.04),
    "deck_drop_m": (0.0, 0.05),
    "deck_round_m": (0.02, 0.06),
    "windscreen_rake_deg": (52.0, 60.0),
    "rear_window_rake_deg": (15.0, 35.0),
    "tumblehome_deg": (15.0, 22.0),
    "roof_round_m": (0.03, 0.07),
    "front_overhang_frac": (0.18, 0.21),  # Tiguan 0.89 m of 4.51
    "rear_overhang_frac": (0.19, 0.22),
    "wheel_radius_m": (0.34, 0.37),
    "tyre_width_m": (0.215, 0.255),
    "rear_tyre_width_m": (0.215, 0.255),
    "mirror_out_m": (0.10, 0.14),
    "mirror_height_m": (0.14, 0.19),
}
_VAN = _SEDAN | {
    "length_m": (4.90, 6.40),
    "width_m": (1.90, 2.06),
    "height_m": (1.90, 2.80),
    "clearance_m": (0.15, 0.20),
    "front_bumper_low_m": (0.28, 0.36),
    "front_bumper_m": (0.45, 0.60),
    "rear_bumper_low_m": (0.40, 0.50),
    "rear_bumper_m": (0.55, 0.70),
    "bonnet_front_m": (0.85, 1.00),
    "nose_setback_m": (0.10, 0.25),
    "bonnet_frac": (0.13, 0.19),  # short bonnet: Transit 0.95 m, Sprinter 1.0 m
    "belt_m": (1.05, 1.25),
    "deck_frac": (0.002, 0.006),  # vertical rear doors
    "deck_drop_m": (0.0, 0.03),
    "deck_round_m": (0.01, 0.03),
    "windscreen_rake_deg": (38.0, 55.0),
    "rear_window_rake_deg": (0.0, 5.0),
    "cabin_inset_m": (0.02, 0.06),  # slab sides
    "tumblehome_deg": (2.0, 8.0),
    "roof_round_m": (0.05, 0.12),
    "sill_inset_m": (0.03, 0.07),
    "front_radius_m": (0.35, 0.55),
    "rear_radius_m": (0.08, 0.18),
    "cabin_front_radius_m": (0.30, 0.50),
    "cabin_rear_radius_m": (0.08, 0.18),
    "front_overhang_frac": (0.15, 0.19),  # Transit L2 0.95 m of 5.53
    "rear_overhang_frac": (0.18, 0.24),
    "wheel_radius_m": (0.33, 0.36),
    "tyre_width_m": (0.205, 0.235),
    "rear_tyre_width_m": (0.205, 0.235),
    "mirror_out_m": (0.16, 0.22),
    "mirror_rise_m": (0.10, 0.25),
    "mirror_height_m": (0.30, 0.40),
    "mirror_depth_m": (0.12, 0.18),
}
_PICKUP = _SEDAN | {
    "length_m": (5.05, 5.45),
    "width_m": (1.78, 1.93),
    "height_m": (1.75, 1.90),
    "clearance_m": (0.20, 0.29),
    "front_bumper_low_m": (0.35, 0.45),
    "front_bumper_m": (0.60, 0.75),
    "rear_bumper_low_m": (0.50, 0.60),
    "rear_bumper_m": (0.65, 0.80),
    "bonnet_front_m": (1.00, 1.15),
    "bonnet_frac": (0.25, 0.29),
    "belt_m": (1.15, 1.30),  # also the bed's rim
    "windscreen_rake_deg": (55.0, 62.0),
    "rear_window_rake_deg": (0.0, 6.0),  # cab back wall
    "tumblehome_deg": (12.0, 20.0),
    "front_radius_m": (0.30, 0.50),
    "rear_radius_m": (0.05, 0.12),
    "cabin_rear_radius_m": (0.10, 0.25),
    "front_overhang_frac": (0.16, 0.18),  # Hilux 0.90 m of 5.33
    "rear_overhang_frac": (0.24, 0.27),  # Hilux 1.34 m
    "wheel_radius_m": (0.37, 0.40),
    "tyre_width_m": (0.255, 0.265),
    "rear_tyre_width_m": (0.255, 0.265),
    "mirror_out_m": (0.10, 0.15),
    "mirror_height_m": (0.16, 0.22),
    "bed_frac": (0.30, 0.35),  # load bed outside length 1.6-1.85 m
    "bed_depth_m": (0.45, 0.55),
    "bed_wall_m": (0.04, 0.06),
    "cab_gap_m": (0.03, 0.08),  # between the cab's back wall and the bed's front wall
}
_TRUCK = _SEDAN | {
    "length_m": (7.50, 10.50),
    "width_m": (2.45, 2.55),
    "height_m": (3.20, 4.00),
    "clearance_m": (0.30, 0.45),  # cab step / bumper underside
    "front_bumper_low_m": (0.34, 0.50),
    "front_bumper_m": (0.55, 0.75),
    "bonnet_front_m": (0.95, 1.20),  # cab-over: the "bonnet" is the front panel's top edge
    "nose_setback_m": (0.0, 0.05),
    "bonnet_frac": (0.003, 0.008),
    "belt_m": (1.70, 2.00),
    "windscreen_rake_deg": (5.0, 15.0),
    "rear_window_rake_deg": (0.0, 3.0),
    "cabin_inset_m": (0.0, 0.04),
    "tumblehome_deg": (2.0, 6.0),
    "roof_round_m": (0.05, 0.12),
    "sill_inset_m": (0.0, 0.04),
    "shoulder_inset_m": (0.0, 0.02),
    "front_radius_m": (0.15, 0.30),
    "rear_radius_m": (0.03, 0.08),
    "cabin_front_radius_m": (0.15, 0.30),
    "cabin_rear_radius_m": (0.03, 0.08),
    "front_lip_m": (0.0, 0.05),
    "underbody_front_frac": (0.0, 0.05),
    "front_overhang_frac": (0.13, 0.18),  # 1.25-1.5 m
    "rear_overhang_frac": (0.20, 0.30),
    "wheel_radius_m": (0.50, 0.54),
    "tyre_width_m": (0.295, 0.315),
    "rear_tyre_width_m": (0.60, 0.64),  # twin tyres
    "tyre_gap_m": (0.03, 0.10),
    "mirror_out_m": (0.20, 0.32),
    "mirror_rise_m": (0.20, 0.50),
    "mirror_height_m": (0.45, 0.65),  # main + wide-angle mirror (UN R46 classes II and IV)
    "mirror_depth_m": (0.08, 0.12),
    "mirror_setback_m": (0.10, 0.35),
    "cab_length_m": (1.90, 2.40),  # day or short sleeper cab
    "cab_height_m": (2.80, 3.30),
    "cab_inset_m": (0.0, 0.08),  # cab narrower than the 2.55 m box, per side
    "box_floor_m": (1.00, 1.30),
    "cab_gap_m": (0.05, 0.30),
    "box_radius_m": (0.02, 0.06),
}
_BUS = _SEDAN | {
    "length_m": (10.50, 13.50),
    "width_m": (2.50, 2.55),
    "height_m": (2.90, 3.40),
    "clearance_m": (0.25, 0.32),
    "front_bumper_low_m": (0.30, 0.40),
    "front_bumper_m": (0.50, 0.70),
    "rear_bumper_low_m": (0.35, 0.45),
    "rear_bumper_m": (0.50, 0.70),
    "bonnet_front_m": (0.85, 0.95),
    "nose_setback_m": (0.02, 0.08),
    "bonnet_frac": (0.004, 0.012),
    "belt_m": (1.00, 1.30),
    "deck_frac": (0.002, 0.006),
    "deck_drop_m": (0.0, 0.05),
    "deck_round_m": (0.01, 0.04),
    "windscreen_rake_deg": (3.0, 10.0),
    "rear_window_rake_deg": (1.0, 5.0),
    "cabin_inset_m": (0.0, 0.03),
    "tumblehome_deg": (1.0, 4.0),
    "roof_round_m": (0.08, 0.18),
    "sill_inset_m": (0.02, 0.05),
    "shoulder_inset_m": (0.0, 0.02),
    "front_radius_m": (0.25, 0.50),
    "rear_radius_m": (0.20, 0.40),
    "cabin_front_radius_m": (0.25, 0.50),
    "cabin_rear_radius_m": (0.20, 0.40),
    "front_lip_m": (0.02, 0.08),
    "rear_lip_m": (0.02, 0.08),
    "underbody_front_frac": (0.05, 0.15),
    "underbody_rear_frac": (0.05, 0.15),
    "front_overhang_frac": (0.21, 0.24),  # Citaro 2.81 m of 12.14
    "rear_overhang_frac": (0.25, 0.29),  # Citaro 3.49 m
    "wheel_radius_m": (0.47, 0.49),
    "tyre_width_m": (0.275, 0.285),
    "rear_tyre_width_m": (0.58, 0.60),
    "tyre_gap_m": (0.03, 0.08),
    "mirror_out_m": (0.20, 0.35),
    "mirror_rise_m": (0.80, 1.20),  # arm-mounted mirrors at 1.9-2.5 m, in front of the A-pillars
    "mirror_height_m": (0.35, 0.45),
    "mirror_depth_m": (0.08, 0.12),
    "mirror_setback_m": (0.10, 0.40),
}
TYPE_RANGES: dict[str, dict[str, Range]] = {
    "sedan": _SEDAN,
    "hatchback": _HATCHBACK,
    "estate": _ESTATE,
    "suv": _SUV,
    "van": _VAN,
    "pickup": _PICKUP,
    "truck": _TRUCK,
    "bus": _BUS,
}
# A roof box on about one car in twenty (the ~5 % of the brief; rental and holiday traffic has more, a
# commuter road fewer). Boxes: Thule Motion/Force class, 1.4-2.1 m long, 0.7-0.9 m wide, 0.35-0.45 m tall
# on 0.05-0.08 m roof bars.
ROOF_BOX_PROBABILITY = {"sedan": 0.05, "hatchback": 0.05, "estate": 0.05, "suv": 0.05}
_ROOF_BOX: dict[str, Range] = {
    "roof_box_length_m": (1.40, 2.10),
    "roof_box_width_m": (0.70, 0.90),
    "roof_box_height_m": (0.40, 0.53),  # box plus roof bars, above H
}
# Given data-sheet dimensions are accepted this far outside a type's range (fraction of the range's ends):
# a small city car drawn as a "sedan" is odd but drawable; a 3 m tall sedan is not.
DIMENSION_TOLERANCE = 0.20
# Car body types of toolbox class 4, by approximate share of the German car stock (KBA body-type
# statistics, order of magnitude: hatchbacks and small cars about a third, SUVs and off-roaders a
# quarter to a third, estates a fifth, saloons a sixth; pickups a few per cent).
CAR_TYPE_SHARES = {"hatchback": 0.34, "suv": 0.27, "estate": 0.20, "sedan": 0.16, "pickup": 0.03}
CLASS_BODY_TYPES = {5: "truck", 6: "van", 7: "bus"}
# Plan-view corner arcs are sampled with this many points (ends included) and wheels with this many
# sides: enough for a silhouette within about 1 cm at a car's radii, few enough that ~10^5 instances per
# camera project quickly (the box of a polyhedron is the bounds of its projected vertices).
_ARC_POINTS = 3
_WHEEL_SIDES = 8
# Rings of the lower body closer than this in height are merged (m).
_MERGE_DZ_M = 0.02
_MIN_RADIUS_M = 0.01
# A ring's corner arcs: rear-right (from pointing -x to -y), front-right, front-left, rear-left.
_RING_ANGLES = np.concatenate(
    [
        start + np.linspace(0.0, 0.5 * math.pi, _ARC_POINTS)
        for start in (math.pi, 1.5 * math.pi, 0.0, 0.5 * math.pi)
    ]
)
_RING_COS, _RING_SIN = np.cos(_RING_ANGLES), np.sin(_RING_ANGLES)
_RING_FRONT = np.repeat([False, True, True, False], _ARC_POINTS)
_RING_LEFT = np.repeat([False, False, True, True], _ARC_POINTS)


@dataclass(frozen=True, eq=False)
class BodyShape:
    """One vehicle body in the design vehicle frame (x forward, y left, z up, origin at the rear-right-bottom
    corner of the data-sheet box [0, L] x [0, W] x [0, H]); metres.

    `proportions`: every drawn parameter (JSON-able, for the ground truth). `vertices` (K, 3) and `faces`
    (F, 3, indices into vertices, counter-clockwise seen from outside) form closed surfaces; `parts` maps a
    part ("body", "cab", "box", "bed", "wheel_rr", ..., "mirror_r", "mirror_l", "roof_box") to its vertex
    range [start, stop). `wheel_contacts` (4, 3): tyre contact points at z = 0, rear-right, front-right,
    front-left, rear-left."""

    vehicle_type: str
    length_m: float
    width_m: float
    height_m: float
    proportions: dict[str, float]
    vertices: FloatArray
    faces: IntArray
    wheel_contacts: FloatArray
    parts: dict[str, tuple[int, int]] = field(default_factory=dict)


def body_type_for_class(
    cls: int,
    rng: np.random.Generator,
    *,
    length_m: float | None = None,
    width_m: float | None = None,
    height_m: float | None = None,
) -> str:
    """Body type of a vehicle of toolbox class `cls` (4 car, 5 truck, 6 van, 7 bus); cars by share, among
    the car types whose data-sheet ranges (with DIMENSION_TOLERANCE) admit the given dimensions (m)."""
    if cls in CLASS_BODY_TYPES:
        return CLASS_BODY_TYPES[cls]
    if cls != 4:
        raise SimulationError("cls", f"{cls!r} is not a toolbox vehicle class (4 car, 5 truck, 6 van, 7 bus)")
    given = {"length_m": length_m, "width_m": width_m, "height_m": height_m}
    names = [
        name
        for name in CAR_TYPE_SHARES
        if all(value is None or _dimension_fits(name, dim, value) for dim, value in given.items())
    ]
    if not names:
        dims = ", ".join(f"{dim} = {value!r}" for dim, value in given.items() if value is not None)
        raise SimulationError("cls", f"4 (car): no car body type admits {dims}")
    shares = np.array([CAR_TYPE_SHARES[n] for n in names])
    return names[int(rng.choice(len(names), p=shares / shares.sum()))]


def _dimension_fits(vehicle_type: str, dim: str, value: float) -> bool:
    lo, hi = TYPE_RANGES[vehicle_type][dim]
    return (
        math.isfinite(value) and (1.0 - DIMENSION_TOLERANCE) * lo <= value <= (1.0 + DIMENSION_TOLERANCE) * hi
    )


def draw_body(
    vehicle_type: str,
    rng: np.random.Generator,
    *,
    length_m: float | None = None,
    width_m: float | None = None,
    height_m: float | None = None,
) -> BodyShape:
    """A body of `vehicle_type` with proportions drawn within the type's ranges; given data-sheet
    dimensions (m) are kept exactly and the other proportions are made consistent with them."""
    if vehicle_type not in TYPE_RANGES:
        raise SimulationError("vehicle_type", f"{vehicle_type!r} not one of {', '.join(VEHICLE_TYPES)}")
    ranges = TYPE_RANGES[vehicle_type]
    # Every parameter is drawn, given or not, so a seed's stream does not depend on what was given.
    p = {name: float(rng.uniform(lo, hi)) for name, (lo, hi) in ranges.items()}
    has_roof_box = bool(rng.random() < ROOF_BOX_PROBABILITY.get(vehicle_type, 0.0))
    box = {name: float(rng.uniform(lo, hi)) for name, (lo, hi) in _ROOF_BOX.items()}
    for name, given in (("length_m", length_m), ("width_m", width_m), ("height_m", height_m)):
        if given is None:
            continue
        lo, hi = ranges[name]
        if not (
            math.isfinite(given)
            and (1.0 - DIMENSION_TOLERANCE) * lo <= given <= (1.0 + DIMENSION_TOLERANCE) * hi
        ):
            raise SimulationError(
                name,
                f"{given!r} impossible for a {vehicle_type} (data sheets: {lo}-{hi} m, "
                f"+-{DIMENSION_TOLERANCE:.0%} accepted)",
            )
        p[name] = float(given)
    if has_roof_box:
        p.update(box)
    p["roof_box"] = 1.0 if has_roof_box else 0.0
    return _build(vehicle_type, p)


def cuboid_body(length_m: float, width_m: float, height_m: float) -> BodyShape:
    """The `ideal` world's body: the data-sheet box itself (8 vertices in cuboid_points' order, 12
    triangles), wheel contacts at the footprint corners."""
    for name, value in (("length_m", length_m), ("width_m", width_m), ("height_m", height_m)):
        if not (math.isfinite(value) and value > 0.0):
            raise SimulationError(name, f"{value!r} is not a positive length")
    dims = np.array([length_m, width_m, height_m])
    corners = np.asarray(UNIT_BOX_CORNERS * dims, dtype=np.float64)
    mesh = _Mesh()
    mesh.add("body", [corners[:4], corners[4:]])
    return BodyShape(
        "cuboid",
        float(length_m),
        float(width_m),
        float(height_m),
        {"length_m": float(length_m), "width_m": float(width_m), "height_m": float(height_m)},
        mesh.vertices(),
        mesh.faces(),
        corners[:4].copy(),
        dict(mesh.parts),
    )


class _Mesh:
    """Closed surfaces built from stacks of rings: ring i (n, 3) joined to ring i + 1 by quads, the first
    ring capped facing against the stacking direction, the last along it. Every ring must run
    counter-clockwise seen from the stacking direction (from "above"), rings of one stack having n points."""

    def __init__(self) -> None:
        self._vertices: list[FloatArray] = []
        self._faces: list[IntArray] = []
        self._count = 0
        self.parts: dict[str, tuple[int, int]] = {}

    def add(self, part: str, rings: list[FloatArray]) -> None:
        n = len(rings[0])
        start = self._count
        index = start + np.arange(len(rings) * n).reshape(len(rings), n)
        lower, upper = index[:-1], index[1:]
        lower_next, upper_next = np.roll(lower, -1, axis=1), np.roll(upper, -1, axis=1)
        sides = np.concatenate(
            [
                np.stack([lower, lower_next, upper_next], axis=-1),
                np.stack([lower, upper_next, upper], axis=-1),
            ],
            axis=1,
        ).reshape(-1, 3)
        fan = np.arange(1, n - 1)
        first, last = index[0], index[-1]
        bottom = np.column_stack([np.full(n - 2, first[0]), first[fan + 1], first[fan]])
        top = np.column_stack([np.full(n - 2, last[0]), last[fan], last[fan + 1]])
        self._vertices += rings
        self._faces.append(np.concatenate([sides, bottom, top]).astype(np.int64))
        self._count += len(rings) * n
        self.parts[part] = (start, self._count)

    def vertices(self) -> FloatArray:
        return np.asarray(np.concatenate(self._vertices), dtype=np.float64)

    def faces(self) -> IntArray:
        return np.asarray(np.concatenate(self._faces), dtype=np.int64)


def _rounded_ring(
    z: float, x0: float, x1: float, y_mid: float, half_w: float, r0: float, r1: float
) -> FloatArray:
    """Plan-view rounded rectangle at height z: x in [x0, x1], y in y_mid +- half_w, rear corners of radius
    r0, front corners r1; (4 * _ARC_POINTS, 3) counter-clockwise from above, from the rear-right corner."""
    r_max = min(0.49 * (x1 - x0), 0.99 * half_w)
    r0 = min(max(r0, _MIN_RADIUS_M), r_max)
    r1 = min(max(r1, _MIN_RADIUS_M), r_max)
    y0, y1 = y_mid - half_w, y_mid + half_w
    r = np.where(_RING_FRONT, r1, r0)
    x = np.where(_RING_FRONT, x1 - r1, x0 + r0) + r * _RING_COS
    y = np.where(_RING_LEFT, y1 - r, y0 + r) + r * _RING_SIN
    # Snap the arcs' ends onto the rectangle's sides: cos(3 pi / 2) is -1.8e-16, not 0, and the body must
    # touch its data-sheet box exactly.
    return np.column_stack([np.clip(x, x0, x1), np.clip(y, y0, y1), np.full(len(x), z)])


def _box_ring(z: float, x0: float, x1: float, y0: float, y1: float) -> FloatArray:
    return np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=np.float64)


def _interp(z: float, breakpoints: list[tuple[float, float]]) -> float:
    zs, values = zip(*sorted(breakpoints), strict=True)
    return float(np.interp(z, zs, values))


@dataclass(frozen=True, slots=True)
class _Span:
    """Where a car-like body (monocoque, truck cab, pickup cab) lies: x in [x0, x1], its own height, its
    half-width about y_mid, and whether its rear is a flat wall (a cab's back)."""

    x0: float
    x1: float
    height: float
    y_mid: float
    half_w: float
    flat_rear: bool


def _monocoque_rings(p: dict[str, float], span: _Span) -> list[FloatArray]:
    """Horizontal sections of a car-like body from the sill to the roof: the lower body up to the belt
    (bumpers, bonnet, boot deck), then the greenhouse (cabin inset, rakes, tumblehome, roof crown).
    Heights in `p` are clamped into a consistent order and written back (the ground truth records what
    was drawn)."""
    height, hw = span.height, span.half_w
    # Heights from the top down, each kept below the one above it: greenhouse at least 0.3 m or a quarter
    # of the height (a 0.85 x nominal sedan still has side windows), then bonnet, bumpers, sill.
    p["belt_m"] = min(p["belt_m"], height - max(0.30, 0.25 * height))
    belt = p["belt_m"]
    p["bonnet_front_m"] = min(p["bonnet_front_m"], belt - 0.05)
    p["front_bumper_m"] = min(p["front_bumper_m"], p["bonnet_front_m"] - 0.05)
    p["front_bumper_low_m"] = min(p["front_bumper_low_m"], p["front_bumper_m"] - 0.05)
    p["deck_drop_m"] = max(p["deck_drop_m"], 0.01)  # the boot-lid edge and the belt are separate levels
    deck_edge = belt - p["deck_drop_m"]
    p["rear_bumper_m"] = min(p["rear_bumper_m"], deck_edge - 0.05)
    p["rear_bumper_low_m"] = min(p["rear_bumper_low_m"], p["rear_bumper_m"] - 0.05)
    p["clearance_m"] = min(p["clearance_m"], p["front_bumper_low_m"] - 0.03, p["rear_bumper_low_m"] - 0.03)
    clearance = p["clearance_m"]
    L = p["length_m"]
    bonnet = p["bonnet_frac"] * L
    deck = 0.0 if span.flat_rear else p["deck_frac"] * L
    under_front = p["underbody_front_frac"] * p["front_overhang_frac"] * L
    under_rear = p["underbody_rear_frac"] * p["rear_overhang_frac"] * L
    x0, x1 = span.x0, span.x1
    front = [
        (clearance, x1 - under_front),
        (p["front_bumper_low_m"], x1 - p["front_lip_m"]),
        (p["front_bumper_m"], x1),
        (p["bonnet_front_m"], x1 - p["nose_setback_m"]),
        (belt, x1 - bonnet),
    ]
    if span.flat_rear:
        rear = [(clearance, x0), (belt, x0)]
        z_widest_rear = clearance
    else:
        rear = [
            (clearance, x0 + under_rear),
            (p["rear_bumper_low_m"], x0 + p["rear_lip_m"]),
            (p["rear_bumper_m"], x0),
            (deck_edge, x0 + p["deck_round_m"]),
            (belt, x0 + max(deck, p["deck_round_m"])),
        ]
        z_widest_rear = p["rear_bumper_m"]
    # The body is widest at the door shoulder, between the bumper line and the belt.
    z_widest = 0.5 * (p["front_bumper_m"] + belt)
    half = [(clearance, hw - p["sill_inset_m"]), (z_widest, hw), (belt, hw - p["shoulder_inset_m"])]
    r_front = [(clearance, p["front_radius_m"]), (belt, p["cabin_front_radius_m"])]
    r_rear = [(z_widest_rear, p["rear_radius_m"]), (belt, p["cabin_rear_radius_m"])]
    # The levels where the body touches its data-sheet box (length at the bumpers, width at the shoulder),
    # the sill and the belt are kept; other breakpoints closer than _MERGE_DZ_M to a kept level are dropped.
    kept = {clearance, p["front_bumper_m"], z_widest, belt} | (
        {p["rear_bumper_m"]} if not span.flat_rear else set()
    )
    others = sorted(({z for z, _ in front} | {z for z, _ in rear}) - kept)
    merged = sorted(kept)
    for z in others:
        if min(abs(z - k) for k in merged) >= _MERGE_DZ_M:
            merged = sorted([*merged, z])
    rings = [
        _rounded_ring(
            z,
            _interp(z, rear),
            _interp(z, front),
            span.y_mid,
            _interp(z, half),
            _interp(z, r_rear),
            _interp(z, r_front),
        )
        for z in merged
    ]
    # Greenhouse: base at the belt inside the shoulder, screens raked back, side glass leaning in, then the
    # roof crown: an edge ring roof_round below H and the roof top inset by as much again.
    g_x0, g_x1 = _interp(belt, rear), _interp(belt, front)
    g_hw = hw - max(p["cabin_inset_m"], p["shoulder_inset_m"] + 0.005)
    rise = height - p["roof_round_m"] - belt
    run_front = rise * math.tan(math.radians(p["windscreen_rake_deg"]))
    run_rear = rise * math.tan(math.radians(p["rear_window_rake_deg"]))
    # The roof must stay a roof (at least a fifth of the greenhouse base, minimum 0.3 m + the crown): when
    # a short body meets long screens, both screens are steepened alike and the rakes recorded as drawn.
    roof_min = max(0.2 * (g_x1 - g_x0), 0.3) + 2.0 * p["roof_round_m"]
    if g_x1 - g_x0 - run_front - run_rear < roof_min:
        scale = max(g_x1 - g_x0 - roof_min, 0.0) / (run_front + run_rear)
        run_front, run_rear = scale * run_front, scale * run_rear
        p["windscreen_rake_deg"] = math.degrees(math.atan2(run_front, rise))
        p["rear_window_rake_deg"] = math.degrees(math.atan2(run_rear, rise))
    lean = min(rise * math.tan(math.radians(p["tumblehome_deg"])), 0.35 * g_hw)
    p["tumblehome_deg"] = math.degrees(math.atan2(lean, rise))
    crown = p["roof_round_m"]
    t_x0, t_x1, t_hw = g_x0 + run_rear, g_x1 - run_front, g_hw - lean
    rings += [
        _rounded_ring(
            belt, g_x0, g_x1, span.y_mid, g_hw, p["cabin_rear_radius_m"], p["cabin_front_radius_m"]
        ),
        _rounded_ring(
            height - crown, t_x0, t_x1, span.y_mid, t_hw, p["cabin_rear_radius_m"], p["cabin_front_radius_m"]
        ),
        _rounded_ring(
            height,
            t_x0 + crown,
            t_x1 - crown,
            span.y_mid,
            t_hw - crown,
            p["cabin_rear_radius_m"] - crown,
            p["cabin_front_radius_m"] - crown,
        ),
    ]
    p["roof_length_m"] = t_x1 - t_x0 - 2.0 * crown
    return rings


def _wheel_rings(x_axle: float, y_centre: float, radius: float, width: float) -> list[FloatArray]:
    """A tyre as a short _WHEEL_SIDES-gon cylinder about the y axis, its lowest vertex on z = 0; the two
    rings run counter-clockwise seen from -y, so they are stacked from the +y face to the -y face."""
    angle = 2.0 * math.pi * np.arange(_WHEEL_SIDES) / _WHEEL_SIDES
    x = x_axle + radius * np.sin(angle)
    z = radius * (1.0 - np.cos(angle))
    z[0] = 0.0
    ones = np.ones(_WHEEL_SIDES)
    return [np.column_stack([x, (y_centre + s * 0.5 * width) * ones, z]) for s in (1.0, -1.0)]


def _build(vehicle_type: str, p: dict[str, float]) -> BodyShape:
    L, W, H = p["length_m"], p["width_m"], p["height_m"]
    mesh = _Mesh()
    if vehicle_type == "truck":
        # Cab-over cab at the front, a box body on the chassis behind it; the box is the widest part.
        p["cab_height_m"] = min(p["cab_height_m"], H)
        p["box_floor_m"] = max(p["box_floor_m"], 2.0 * p["wheel_radius_m"] + 0.05)
        cab = _Span(L - p["cab_length_m"], L, p["cab_height_m"], 0.5 * W, 0.5 * W - p["cab_inset_m"], True)
        mesh.add("cab", _monocoque_rings(p, cab))
        box_x1 = cab.x0 - p["cab_gap_m"]
        r = p["box_radius_m"]
        mesh.add(
            "box",
            [_rounded_ring(z, 0.0, box_x1, 0.5 * W, 0.5 * W, r, r) for z in (p["box_floor_m"], H)],
        )
        body_x1 = L  # mirrors hang from the cab
    elif vehicle_type == "pickup":
        bed_x1 = p["bed_frac"] * L
        cab = _Span(bed_x1 + p["cab_gap_m"], L, H, 0.5 * W, 0.5 * W, True)
        mesh.add("cab", _monocoque_rings(p, cab))
        # The open bed: a cup (outer walls up to the rim at the belt, then the inner walls down to the floor).
        rim, wall, hw = p["belt_m"], p["bed_wall_m"], 0.5 * W
        p["bed_depth_m"] = min(p["bed_depth_m"], rim - p["rear_bumper_low_m"] - 0.10)
        floor = rim - p["bed_depth_m"]
        r0, r1 = p["rear_radius_m"], 0.03
        mesh.add(
            "bed",
            [
                _rounded_ring(
                    p["rear_bumper_low_m"], p["rear_lip_m"], bed_x1, 0.5 * W, hw - p["sill_inset_m"], r0, r1
                ),
                _rounded_ring(p["rear_bumper_m"], 0.0, bed_x1, 0.5 * W, hw, r0, r1),
                _rounded_ring(rim, 0.0, bed_x1, 0.5 * W, hw - p["shoulder_inset_m"], r0, r1),
                _rounded_ring(rim, wall, bed_x1 - wall, 0.5 * W, hw - p["shoulder_inset_m"] - wall, r0, r1),
                _rounded_ring(floor, wall, bed_x1 - wall, 0.5 * W, hw - p["shoulder_inset_m"] - wall, r0, r1),
            ],
        )
        body_x1 = L
    else:
        mesh.add("body", _monocoque_rings(p, _Span(0.0, L, H, 0.5 * W, 0.5 * W, False)))
        body_x1 = L
    # Wheels: axles from the overhangs, tyres inset from the body side by the drawn gap.
    x_rear, x_front = p["rear_overhang_frac"] * L, L - p["front_overhang_frac"] * L
    radius = p["wheel_radius_m"]
    contacts = []
    for name, x_axle, width, y_side in (
        ("wheel_rr", x_rear, p["rear_tyre_width_m"], -1.0),
        ("wheel_fr", x_front, p["tyre_width_m"], -1.0),
        ("wheel_fl", x_front, p["tyre_width_m"], 1.0),
        ("wheel_rl", x_rear, p["rear_tyre_width_m"], 1.0),
    ):
        y_centre = 0.5 * W + y_side * (0.5 * W - p["tyre_gap_m"] - 0.5 * width)
        mesh.add(name, _wheel_rings(x_axle, y_centre, radius, width))
        contacts.append([x_axle, y_centre, 0.0])
    p["wheelbase_m"] = x_front - x_rear
    p["front_track_m"] = W - 2.0 * p["tyre_gap_m"] - p["tyre_width_m"]
    p["rear_track_m"] = W - 2.0 * p["tyre_gap_m"] - p["rear_tyre_width_m"]
    p["front_overhang_m"], p["rear_overhang_m"] = L - x_front, x_rear
    # Mirrors: boxes from the door (inside the belt line) to mirror_out beyond the data-sheet width.
    windscreen_base = body_x1 - p["bonnet_frac"] * L
    xm = min(windscreen_base - p["mirror_setback_m"], L - 0.5 * p["mirror_depth_m"])
    zm = min(p["belt_m"] + p["mirror_rise_m"], H - 0.5 * p["mirror_height_m"])
    p["mirror_x_m"], p["mirror_z_m"] = xm, zm
    root = p["shoulder_inset_m"] + 0.03
    for name, y0, y1 in (
        ("mirror_r", -p["mirror_out_m"], root),
        ("mirror_l", W - root, W + p["mirror_out_m"]),
    ):
        mesh.add(
            name,
            [
                _box_ring(
                    zm + s * 0.5 * p["mirror_height_m"],
                    xm - 0.5 * p["mirror_depth_m"],
                    xm + 0.5 * p["mirror_depth_m"],
                    y0,
                    y1,
                )
                for s in (-1.0, 1.0)
            ],
        )
    if p["roof_box"]:
        # Centred on the roof, no longer than the car, resting on bars above H.
        roof_mid = 0.5 * (windscreen_base + p["deck_frac"] * L)
        box_len = min(p["roof_box_length_m"], 0.9 * L)
        p["roof_box_length_m"] = box_len
        bx0 = float(np.clip(roof_mid - 0.5 * box_len, 0.0, L - box_len))
        bars = 0.06
        rings = [
            _rounded_ring(z, bx0, bx0 + box_len, 0.5 * W, 0.5 * p["roof_box_width_m"], 0.15, 0.35)
            for z in (H + bars, H + p["roof_box_height_m"])
        ]
        mesh.add("roof_box", rings)
    return BodyShape(
        vehicle_type,
        L,
        W,
        H,
        dict(p),
        mesh.vertices(),
        mesh.faces(),
        np.array(contacts, dtype=np.float64),
        dict(mesh.parts),
    )
