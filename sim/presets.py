"""Scenario configuration of the simulator (everything tunable, frozen) and the named presets.

A ScenarioConfig is plain data: the site (UTM zone and origin), the road layout, ground, occluders,
cameras, the calibration vehicle's drive, the other traffic, the vehicle's pose reporting and the
detector model. `dataclasses.replace` derives variants (the tests shrink presets that way).
Units: metres, seconds, degrees where the name says `_deg`, pixels for image quantities.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from schemas.common import VehicleProfile


@dataclass(frozen=True, slots=True)
class SiteSpec:
    """Where the junction centre (the local origin) is: UTM zone (EPSG code), easting, northing, height."""

    name: str
    crs: str
    east_m: float
    north_m: float
    alt_m: float


@dataclass(frozen=True, slots=True)
class ArmSpec:
    """One road leaving the junction: outward direction (deg from grid east, ccw) and an optional bend
    (`bend_deg`, positive = left, on `bend_radius_m`) starting `bend_start_m` from the centre."""

    name: str
    angle_deg: float
    bend_start_m: float = 0.0
    bend_deg: float = 0.0
    bend_radius_m: float = 200.0


@dataclass(frozen=True, slots=True)
class RoadSpec:
    """Junction layout; two arms make a plain road. Arms are `arm_length_m` long (path length from the
    centre); the far connectors run on a ring `connector_clearance_m` beyond the furthest arm end."""

    arms: tuple[ArmSpec, ...]
    lanes_per_direction: int = 1
    lane_width_m: float = 3.5
    arm_length_m: float = 300.0
    stop_line_margin_m: float = 4.0
    connector_clearance_m: float = 40.0


@dataclass(frozen=True, slots=True)
class BumpSpec:
    """A smooth Gaussian bump (or dip, negative height) in the ground."""

    x_m: float
    y_m: float
    height_m: float
    sigma_m: float


@dataclass(frozen=True, slots=True)
class VerticalCurveSpec:
    """A parabolic vertical curve on one arm: it starts `start_m` along the arm's centre line from the
    junction centre, runs `length_m`, and changes the grade by `grade_change` (dimensionless, e.g. -0.04:
    a crest; positive: a sag). The new grade then carries on to the arm's end and beyond."""

    arm: str
    start_m: float
    length_m: float
    grade_change: float


@dataclass(frozen=True, slots=True)
class GroundSpec:
    """Terrain z = slope . (x, y) + bumps (local frame), with the roads built into it as they are.

    The defaults are a real road (German RAL/RAS-L/RASt 06 and AASHTO Green Book figures): a 2 % crown
    falling from each arm's centre line to its edges, 12 cm kerbs up to level footways and verges, 4 %
    superelevation on the arms' bends (reached over `bank_transition_m`), kerb returns of 8 m radius at
    the junction corners, whose area is flattened. `GroundSpec.flat()` is the old terrain alone (the
    `ideal` world). Slopes are dimensionless (m/m), lengths metres."""

    slope: tuple[float, float] = (0.0, 0.0)
    bumps: tuple[BumpSpec, ...] = ()
    # RAS-Q / RAA minimum cross slope 2.5 %, RASt 06 and AASHTO 1.5-2 % on urban streets: 2 % both ways.
    crown_slope: float = 0.02
    # RASt 06: kerb face 10-15 cm (lower at crossings); 12 cm is the common "Hochbord".
    kerb_height_m: float = 0.12
    # RASt 06 minimum footway 2.5 m; behind it the verge continues at footway height.
    footway_width_m: float = 2.5
    # Superelevation of the arms' bends, falling toward the inside (RAL: 2.5-6 % for R 200-400 m at
    # 50-70 km/h; AASHTO e_max 4 % for urban roads).
    bank_slope: float = 0.04
    # Superelevation runoff: the carriageway revolves about its centre line from crown to bank over this
    # length, 2/3 of it before the bend (AASHTO Green Book 3.3.8); RAS-L ramp gradients give 20-30 m.
    bank_transition_m: float = 25.0
    # RASt 06 kerb return (Eckausrundung) radii 6-12 m for cars and lorries turning; 8 m by default.
    kerb_return_radius_m: float = 8.0
    vertical_curves: tuple[VerticalCurveSpec, ...] = ()

    @staticmethod
    def flat(slope: tuple[float, float] = (0.0, 0.0), bumps: tuple[BumpSpec, ...] = ()) -> GroundSpec:
        """The terrain alone, no road built into it: z = slope . (x, y) + bumps exactly (the old world)."""
        return GroundSpec(
            slope=slope, bumps=bumps, crown_slope=0.0, kerb_height_m=0.0, bank_slope=0.0, vertical_curves=()
        )

    @property
    def is_flat(self) -> bool:
        """No crown, kerb, bank or vertical curve: the ground is the terrain alone."""
        return (
            self.crown_slope == 0.0
            and self.kerb_height_m == 0.0
            and self.bank_slope == 0.0
            and not self.vertical_curves
        )


@dataclass(frozen=True, slots=True)
class OccluderSpec:
    """A cuboid obstacle centred at (x, y) on the ground; its bottom `base_height_m` above the ground."""

    kind: str
    x_m: float
    y_m: float
    length_m: float
    width_m: float
    height_m: float
    base_height_m: float = 0.0
    yaw_deg: float = 0.0


def pole(x_m: float, y_m: float, height_m: float = 8.0, width_m: float = 0.3) -> tuple[OccluderSpec, ...]:
    """A lamp or signal pole."""
    return (OccluderSpec("pole", x_m, y_m, width_m, width_m, height_m),)


def tree(x_m: float, y_m: float, crown_m: float = 4.5, trunk_m: float = 2.5) -> tuple[OccluderSpec, ...]:
    """A tree: a trunk and a crown box on top of it."""
    return (
        OccluderSpec("trunk", x_m, y_m, 0.45, 0.45, trunk_m),
        OccluderSpec("crown", x_m, y_m, crown_m, crown_m, crown_m * 1.1, base_height_m=trunk_m),
    )


@dataclass(frozen=True, slots=True)
class CameraSpec:
    """One RSU camera: mast position (x, y), height above the ground there, viewing direction (optical
    axis azimuth from grid east ccw, tilt below the horizon, roll) and OpenCV intrinsics."""

    camera_id: str
    x_m: float
    y_m: float
    height_m: float
    yaw_deg: float
    pitch_down_deg: float
    roll_deg: float = 0.0
    width: int = 1920
    height: int = 1200
    fx: float = 1400.0
    fy: float | None = None  # None: fx (square pixels)
    principal_offset_px: tuple[float, float] = (0.0, 0.0)  # (cx, cy) minus the image centre
    # OpenCV's [k1, k2, p1, p2, k3], or with the rational model's k4, k5, k6
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)


def look_at(
    camera_id: str,
    x_m: float,
    y_m: float,
    height_m: float,
    target: tuple[float, float],
    width: int = 1920,
    height: int = 1200,
    fx: float = 1400.0,
    principal_offset_px: tuple[float, float] = (0.0, 0.0),
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0),
) -> CameraSpec:
    """A camera at (x, y, height) aimed at a ground point `target` (x, y): yaw and tilt computed."""
    dx, dy = target[0] - x_m, target[1] - y_m
    yaw = math.degrees(math.atan2(dy, dx))
    pitch = math.degrees(math.atan2(height_m, math.hypot(dx, dy)))
    return CameraSpec(
        camera_id,
        x_m,
        y_m,
        height_m,
        round(yaw, 3),
        round(pitch, 3),
        width=width,
        height=height,
        fx=fx,
        principal_offset_px=principal_offset_px,
        dist=dist,
    )


@dataclass(frozen=True, slots=True)
class DriveSpec:
    """The calibration vehicle's drive: one route ("A>B", arm names) per traversal, joined out of view.

    Speeds and accelerations are drawn per traversal from the (low, high) ranges; on each traversal it
    stops at the stop line with `stop_probability` (`stops` overrides per traversal). With `elsewhere`
    it never comes near the site (the no-target case)."""

    routes: tuple[str, ...] = ("W>E", "S>W", "E>S")
    stops: tuple[bool, ...] | None = None
    stop_probability: float = 0.5
    stop_dwell_s: tuple[float, float] = (2.0, 5.0)
    cruise_mps: tuple[float, float] = (8.0, 14.0)
    accel_mps2: tuple[float, float] = (1.5, 2.5)
    decel_mps2: tuple[float, float] = (2.0, 3.0)
    connector_speed_mps: float = 16.0
    followers_per_traversal: tuple[int, int] = (1, 2)  # hard distractors on the vehicle's own route
    follower_gap_s: tuple[float, float] = (1.5, 4.0)
    elsewhere: bool = False


@dataclass(frozen=True, slots=True)
class TrafficSpec:
    """Other vehicles: `count` of them, entering inbound lanes as a Poisson process with a minimum headway.

    class_mix = shares of car, truck, van, bus (toolbox classes 4, 5, 6, 7)."""

    count: int = 80
    class_mix: tuple[float, float, float, float] = (0.72, 0.07, 0.15, 0.06)
    straight_share: float = 0.6
    min_headway_s: float = 1.5
    stop_probability: float = 0.25
    stop_dwell_s: tuple[float, float] = (0.5, 3.0)
    lead_in_s: float = 45.0  # vehicles enter this long before the recording starts: a full scene at t=0


@dataclass(frozen=True, slots=True)
class ClockSpec:
    """The camera pipeline's clock: a DetectionFrame's stamp is the exposure time plus a latency drawn per
    camera and seed within `latency_s` (unknown to rsucal), with a few ms of per-frame jitter, and an
    optional slow drift (ppm of the elapsed time). The stamp is that of the first image row's exposure: a
    rolling shutter exposes row v of `height` rows v / height of the readout time later, the readout drawn
    per camera and seed within `readout_s` ((0, 0): a global shutter)."""

    latency_s: tuple[float, float] = (0.0, 0.0)
    latency_jitter_s: float = 0.0
    drift_ppm: float = 0.0
    readout_s: tuple[float, float] | None = None  # None: REAL_CLOCK's in the real world, 0 in the ideal


@dataclass(frozen=True, slots=True)
class BodySpec:
    """The calibration vehicle's body type, drawn per seed among `calibration_types` (its data-sheet
    dimensions then drawn within the type's range); the ideal world uses the preset's `vehicle` cuboid."""

    calibration_types: tuple[str, ...] = ("sedan", "hatchback", "estate", "suv")


@dataclass(frozen=True, slots=True)
class V2xSpec:
    """How the calibration vehicle broadcasts: `cam` = ETSI CAM from its GNSS receiver (1-10 Hz, motion
    triggered, no pitch or roll; errors from sim.v2x's GnssSpec, `rtk_float` adds float periods of 0.3-1 m
    errors); `imu` = its 50-100 Hz IMU poses as V2X (the toolbox's data, and the ideal world)."""

    mode: str = "cam"
    rtk_float: bool = False


@dataclass(frozen=True, slots=True)
class CameraMoveSpec:
    """The camera is knocked between two sets of drive-pasts: after traversal `after_traversal` (0-based)
    it turns `turn_deg` about the vertical and shifts `shift_m` sideways (for change detection)."""

    after_traversal: int
    turn_deg: float
    shift_m: float


@dataclass(frozen=True, slots=True)
class PoseSpec:
    """How the calibration vehicle reports its pose (GNSS/RTK + IMU): rate, noise, drift, dropouts, clock."""

    rate_hz: float = 50.0
    timing_jitter_s: float = 0.001
    position_sigma_m: float = 0.0  # white noise on x and y
    height_sigma_m: float = 0.0
    drift_m: float = 0.0  # RMS of a slow smooth drift on x, y (periods of minutes)
    yaw_sigma_rad: float = 0.0
    speed_sigma_mps: float = 0.0
    dropouts: int = 0  # gaps without any pose
    dropout_s: tuple[float, float] = (0.2, 1.0)
    clock_offset_ns: int = 0  # vehicle clock minus camera clock, added to every reported stamp


@dataclass(frozen=True, slots=True)
class DetectorSpec:
    """The RSU detector: frame rate and what it gets wrong (box jitter, misses, false positives)."""

    fps: float = 10.0
    frame_jitter_s: float = 0.0015
    # Edge noise std (px) of a box `jitter_reference_px` tall; a detector's edge error grows with the
    # object's size, so the std scales with the box's width (x edges) / height (y edges), floored at half.
    box_jitter_px: float = 0.0
    jitter_reference_px: float = 80.0
    miss_rate: float = 0.0
    false_positives_per_frame: float = 0.0
    class_confusion: float = 0.0
    min_box_height_px: float = 12.0
    min_box_width_px: float = 8.0
    max_hidden_fraction: float = 0.5
    max_outside_fraction: float = 0.5
    # True: a partly hidden vehicle's box covers only its visible part (a modal detector); False: the
    # whole projected cuboid (amodal, as the paper's DeepSIL/CARLA boxes).
    visible_part_boxes: bool = False
    occlusion_grid: int = 12  # samples per side of the grid that measures how much of a box is hidden
    # --- what a real detector adds (all zero in the ideal world; see `ideal`)
    # Per camera, drawn once per seed: the box scaled about its centre by a factor within 1 +- scale_bias
    # (detectors trained on other data draw systematically loose or tight boxes), and each edge shifted by
    # N(0, edge_bias_px) (a few pixels: the annotation convention of the training set).
    scale_bias: float = 0.0
    edge_bias_px: float = 0.0
    # Edge jitter correlated along a track: AR(1) with this coefficient per frame (0 = independent). A
    # tracker-less detector at 10 fps still sees nearly the same image twice, so its errors persist.
    jitter_ar1: float = 0.0
    # Misses that come in runs (Gilbert-Elliott, per track): the chance per frame that a run of misses
    # starts, and the mean run length in frames. Independent misses (`miss_rate`) come on top.
    miss_run_start: float = 0.0
    miss_run_frames: float = 0.0
    # Gross errors, per track: two overlapping vehicles reported as one box for a few frames (chance per
    # overlapping pair and frame), and one vehicle reported as two boxes (chance per track and frame).
    merge_rate: float = 0.0
    split_rate: float = 0.0


SIM_VEHICLE = VehicleProfile(length=4.8, width=1.85, height=1.5, imu_offset=(1.3, 0.925, 0.35))


@dataclass(frozen=True, slots=True)
class ScenarioConfig:
    """Everything that defines a simulated scenario; `simulate(config, seed)` draws the rest from the seed."""

    name: str
    site: SiteSpec
    road: RoadSpec
    cameras: tuple[CameraSpec, ...]
    ground: GroundSpec = field(default_factory=GroundSpec)
    occluders: tuple[OccluderSpec, ...] = ()
    vehicle: VehicleProfile = SIM_VEHICLE
    drive: DriveSpec = field(default_factory=DriveSpec)
    traffic: TrafficSpec = field(default_factory=TrafficSpec)
    pose: PoseSpec = field(default_factory=PoseSpec)
    detector: DetectorSpec = field(default_factory=DetectorSpec)
    clock: ClockSpec = field(default_factory=ClockSpec)
    bodies: BodySpec = field(default_factory=BodySpec)
    v2x: V2xSpec = field(default_factory=V2xSpec)
    camera_move: CameraMoveSpec | None = None
    ideal: bool = False  # the first simulator's world for this scene (see `ideal`)
    duration_s: float | None = None  # None: until the vehicle has left after its last traversal
    rsu_id: str = "sim-rsu"
    station_id: int = 4242
    start_ns: int = 1_717_200_000_000_000_000  # camera clock at t = 0 (plus a seeded offset < 3 h)


# --- sites: real UTM places; munich-east is 2.9 deg east of zone 32's central meridian (convergence 2.2 deg)
ULM_LEHR = SiteSpec("ulm-lehr", "EPSG:32632", 572000.0, 5361000.0, 527.0)
KARLSRUHE = SiteSpec("karlsruhe", "EPSG:32632", 456123.0, 5428741.0, 165.0)
DRESDEN = SiteSpec("dresden", "EPSG:32633", 411683.0, 5656140.0, 160.0)
MUNICH_EAST = SiteSpec("munich-east", "EPSG:32632", 715689.0, 5337040.0, 560.0)
ROSENHEIM = SiteSpec("rosenheim", "EPSG:32632", 715407.0, 5304756.0, 495.0)

# --- road layouts
SIL_JUNCTION = RoadSpec(
    arms=(
        ArmSpec("E", 2.0, bend_start_m=120.0, bend_deg=15.0, bend_radius_m=300.0),
        ArmSpec("N", 93.0),
        ArmSpec("W", 181.0, bend_start_m=90.0, bend_deg=-20.0, bend_radius_m=250.0),
        ArmSpec("S", 271.0),
    ),
    lanes_per_direction=2,
)
PLAIN_JUNCTION = RoadSpec(
    arms=(ArmSpec("E", 0.0), ArmSpec("N", 90.0), ArmSpec("W", 180.0), ArmSpec("S", 270.0))
)
SKEWED_JUNCTION = RoadSpec(
    arms=(
        ArmSpec("E", -4.0),
        ArmSpec("N", 78.0, bend_start_m=60.0, bend_deg=25.0, bend_radius_m=180.0),
        ArmSpec("W", 176.0),
        ArmSpec("S", 265.0, bend_start_m=110.0, bend_deg=-18.0, bend_radius_m=220.0),
    ),
)
STRAIGHT_ROAD = RoadSpec(arms=(ArmSpec("E", 8.0), ArmSpec("W", 188.0)), arm_length_m=320.0)

# Small real-lens distortion of the regular cameras.
REGULAR_DIST = (-0.08, 0.03, 0.0004, -0.0003, 0.0)

SIL_NOISE = PoseSpec(
    position_sigma_m=0.075,
    height_sigma_m=0.03,
    drift_m=0.03,
    yaw_sigma_rad=math.radians(0.15),
    speed_sigma_mps=0.05,
    dropouts=3,
)
# A YOLO-class detector on a 1920 px image: ~1 px edge noise on an 80 px car, nothing found under ~20 px.
SIL_DETECTOR = DetectorSpec(
    box_jitter_px=1.0,
    miss_rate=0.03,
    false_positives_per_frame=0.05,
    class_confusion=0.02,
    min_box_height_px=20.0,
    min_box_width_px=14.0,
)

SIL_NORTH = ScenarioConfig(
    name="sil-north",
    site=ULM_LEHR,
    road=SIL_JUNCTION,
    cameras=(
        look_at("north", 14.0, 24.0, 10.0, (-4.0, -18.0), principal_offset_px=(4.2, -3.1), dist=REGULAR_DIST),
    ),
    occluders=pole(11.0, 12.0) + pole(-12.0, -12.5),
    drive=DriveSpec(routes=("S>N", "W>S", "E>N")),
    pose=SIL_NOISE,
    detector=SIL_DETECTOR,
)
SIL_SOUTH = replace(
    SIL_NORTH,
    name="sil-south",
    # About 30 m from the nearest road edge: the E-W road's edge is at y = -7, the N-S road's at x = -7.
    cameras=(
        look_at(
            "south",
            -38.0,
            -37.0,
            14.0,
            (4.0, 6.0),
            fx=1500.0,
            principal_offset_px=(-2.5, 5.0),
            dist=REGULAR_DIST,
        ),
    ),
    drive=DriveSpec(routes=("W>E", "S>W", "E>S")),
)
SIL_WEST = replace(
    SIL_NORTH,
    name="sil-west",
    # One RSU mast on the west arm carrying two cameras: one towards the junction, one along the arm.
    cameras=(
        look_at(
            "west-junction", -30.0, 11.0, 9.0, (6.0, -2.0), principal_offset_px=(1.5, 2.0), dist=REGULAR_DIST
        ),
        look_at(
            "west-arm",
            -30.0,
            11.0,
            9.0,
            (-72.0, -4.0),
            fx=1450.0,
            principal_offset_px=(-3.0, 1.0),
            dist=REGULAR_DIST,
        ),
    ),
    drive=DriveSpec(routes=("W>E", "S>W", "N>W")),
)

CARLA_LIKE = ScenarioConfig(
    name="carla-like",
    site=KARLSRUHE,
    road=PLAIN_JUNCTION,
    # CARLA's default camera: 90 deg horizontal field of view, no distortion.
    cameras=(look_at("carla", 11.0, -13.0, 8.0, (-6.0, 8.0), width=1920, height=1080, fx=960.0),),
    drive=DriveSpec(routes=("E>W", "N>E", "S>N"), stops=(False, True, False)),
    # The paper's CARLA data comes as the toolbox's 50 Hz IMU poses, not as CAMs.
    v2x=V2xSpec(mode="imu"),
)

NOISE_02 = replace(SIL_SOUTH, name="noise-0.2", pose=replace(SIL_NOISE, position_sigma_m=0.2))
NOISE_05 = replace(SIL_SOUTH, name="noise-0.5", pose=replace(SIL_NOISE, position_sigma_m=0.5))

DENSE_TRAFFIC = ScenarioConfig(
    name="dense-traffic",
    site=DRESDEN,
    road=replace(SKEWED_JUNCTION, lanes_per_direction=2),
    cameras=(
        look_at("dense", 16.0, 15.0, 12.0, (-8.0, -14.0), principal_offset_px=(2.0, -1.0), dist=REGULAR_DIST),
    ),
    occluders=pole(12.0, 11.5),
    drive=DriveSpec(routes=("W>E", "S>W", "N>S"), followers_per_traversal=(3, 4)),
    traffic=TrafficSpec(count=300, min_headway_s=1.5),
    pose=SIL_NOISE,
    detector=SIL_DETECTOR,
)

OCCLUDED = ScenarioConfig(
    name="occluded",
    site=KARLSRUHE,
    road=replace(PLAIN_JUNCTION, lanes_per_direction=2),
    cameras=(
        look_at(
            "occluded", -22.0, 16.0, 9.0, (8.0, -6.0), principal_offset_px=(-1.0, 3.0), dist=REGULAR_DIST
        ),
    ),
    # Poles and trees on the verges in front of the camera (paper Sec. IV-C: a pole at ~45 m hiding the
    # vehicles behind it, a tree over one lane at ~60 m).
    occluders=(
        pole(-9.5, 9.5, 9.0, 0.35)
        + pole(10.0, -10.0, 9.0, 0.35)
        + pole(-1.0, 9.5, 7.0)
        + tree(30.0, -9.5, crown_m=5.5)
        + tree(14.0, 9.5)
        + tree(-9.5, -24.0)
    ),
    drive=DriveSpec(routes=("W>E", "N>S", "E>N")),
    pose=SIL_NOISE,
    detector=replace(SIL_DETECTOR, visible_part_boxes=True),
)

SLOPE = ScenarioConfig(
    name="slope",
    site=ROSENHEIM,
    road=SKEWED_JUNCTION,
    ground=GroundSpec(
        slope=(0.045, -0.02),
        bumps=(
            BumpSpec(-35.0, 2.0, 0.9, 14.0),
            BumpSpec(30.0, -25.0, -0.7, 18.0),
            BumpSpec(5.0, 45.0, 1.2, 25.0),
        ),
    ),
    cameras=(
        look_at("slope", 15.0, -16.0, 11.0, (-10.0, 10.0), principal_offset_px=(3.0, 2.0), dist=REGULAR_DIST),
    ),
    drive=DriveSpec(routes=("W>E", "N>W", "S>N")),
    pose=SIL_NOISE,
    detector=SIL_DETECTOR,
)

V2X_10HZ = replace(SIL_NORTH, name="v2x-10hz", pose=replace(SIL_NOISE, rate_hz=10.0))
CLOCK_OFFSET = replace(SIL_NORTH, name="clock-offset", pose=replace(SIL_NOISE, clock_offset_ns=150_000_000))

WIDE_DISTORTED = ScenarioConfig(
    name="wide-distorted",
    site=MUNICH_EAST,
    road=PLAIN_JUNCTION,
    cameras=(
        look_at(
            "wide",
            10.0,
            11.0,
            7.0,
            (-3.0, -3.0),
            width=1920,
            height=1080,
            fx=800.0,
            principal_offset_px=(6.0, -4.0),
            dist=(-0.05, 0.0, 0.0, 0.0, 0.0),
        ),
    ),
    drive=DriveSpec(routes=("W>E", "S>W", "E>S")),
    pose=SIL_NOISE,
    detector=SIL_DETECTOR,
)

COLLINEAR = ScenarioConfig(
    name="collinear",
    site=MUNICH_EAST,
    road=STRAIGHT_ROAD,
    # Telephoto from 25 m beside the road: only a 60 m stretch of it is in view.
    cameras=(CameraSpec("tele", 5.0, -25.0, 12.0, 43.0, 13.0, fx=3500.0, principal_offset_px=(2.0, -2.0)),),
    drive=DriveSpec(routes=("W>E", "W>E", "W>E"), stop_probability=0.0, followers_per_traversal=(1, 1)),
    traffic=TrafficSpec(count=40),
    pose=SIL_NOISE,
    detector=SIL_DETECTOR,
)

SINGLE_TRAVERSAL = replace(
    SIL_NORTH, name="single-traversal", drive=DriveSpec(routes=("S>N",)), traffic=TrafficSpec(count=30)
)
NO_TARGET = replace(SIL_SOUTH, name="no-target", drive=DriveSpec(routes=(), elsewhere=True), duration_s=240.0)

LONG = ScenarioConfig(
    name="long",
    site=MUNICH_EAST,
    road=replace(SKEWED_JUNCTION, lanes_per_direction=2),
    cameras=(
        look_at("long", -15.0, 16.0, 12.0, (8.0, -10.0), principal_offset_px=(1.0, 1.0), dist=REGULAR_DIST),
    ),
    occluders=pole(-11.0, 11.0),
    drive=DriveSpec(routes=("W>E", "S>W", "E>S", "N>E", "W>N", "S>N")),
    traffic=TrafficSpec(count=300),
    pose=SIL_NOISE,
    detector=SIL_DETECTOR,
    duration_s=900.0,
)

# A camera turned 90 deg about its optical axis (paper IV-A: real cameras "rotated into a portrait
# orientation"): its image x axis points down the mast, so the scene lies turned a quarter in the 1200 x
# 1920 image (the horizon runs down its left side). It looks down the N-S road: two of its three
# traversals are straight along the view, which an upright-image assumption gets ~85 deg wrong.
PORTRAIT = replace(
    SIL_NORTH,
    name="portrait",
    cameras=(
        replace(
            look_at(
                "portrait",
                -13.0,
                21.0,
                10.0,
                (2.0, -15.0),
                width=1200,
                height=1920,
                principal_offset_px=(-3.0, 4.0),
                dist=REGULAR_DIST,
            ),
            roll_deg=90.0,
        ),
    ),
    drive=DriveSpec(routes=("N>S", "W>S", "S>N")),
)
# A camera mounted with a visible tilt of its image (8 deg roll): neither upright nor a quarter turn. All
# three traversals are straight, so no track's pose is fixed by its path alone.
ROLLED = replace(
    SIL_NORTH,
    name="rolled",
    cameras=(
        replace(
            look_at(
                "rolled", 20.0, -22.0, 9.0, (-6.0, 10.0), principal_offset_px=(2.5, -1.5), dist=REGULAR_DIST
            ),
            roll_deg=8.0,
        ),
    ),
    drive=DriveSpec(routes=("W>E", "S>N", "E>W")),
)

# --- scenes of the real world that the first simulator could not make
LATENCY = replace(SIL_NORTH, name="latency", clock=ClockSpec(latency_s=(0.25, 0.25), latency_jitter_s=0.003))
# Night: headlights and noise make boxes looser and shakier and vehicles harder to find.
NIGHT = replace(
    SIL_SOUTH,
    name="night",
    detector=replace(
        SIL_DETECTOR,
        box_jitter_px=2.5,
        miss_rate=0.08,
        false_positives_per_frame=0.12,
        scale_bias=0.07,
        edge_bias_px=5.0,
        jitter_ar1=0.85,
        miss_run_start=0.03,
        miss_run_frames=6.0,
    ),
)
SUV = replace(SIL_WEST, name="suv", bodies=BodySpec(calibration_types=("suv",)))
VAN = replace(SIL_NORTH, name="van", bodies=BodySpec(calibration_types=("van",)))
# Calibration vehicles no other preset drives, whose shapes the method's template knows least: a pickup (its
# open bed behind a tall cab), a rigid box truck and a city bus (buses broadcast CAMs too).
PICKUP = replace(SIL_SOUTH, name="pickup", bodies=BodySpec(calibration_types=("pickup",)))
TRUCK = replace(SIL_NORTH, name="truck", bodies=BodySpec(calibration_types=("truck",)))
BUS = replace(SIL_WEST, name="bus", bodies=BodySpec(calibration_types=("bus",)))
RTK_FLOAT = replace(SIL_SOUTH, name="rtk-float", v2x=V2xSpec(rtk_float=True))
# A junction on a real road: a pronounced crown (2.5 %), banked bends (5 %), a crest on the west arm and a
# sag on the south arm in front of the camera, on sloping terrain.
CROWNED_ROAD = ScenarioConfig(
    name="crowned-road",
    site=ROSENHEIM,
    road=SKEWED_JUNCTION,
    ground=GroundSpec(
        slope=(0.015, -0.01),
        crown_slope=0.025,
        bank_slope=0.05,
        vertical_curves=(
            VerticalCurveSpec("W", 25.0, 60.0, -0.05),
            VerticalCurveSpec("S", 20.0, 50.0, 0.04),
            VerticalCurveSpec("N", 40.0, 80.0, -0.03),
        ),
    ),
    cameras=(
        look_at(
            "crowned", 14.0, -15.0, 10.0, (-8.0, 6.0), principal_offset_px=(2.0, -3.0), dist=REGULAR_DIST
        ),
    ),
    drive=DriveSpec(routes=("W>E", "S>N", "N>W")),
    pose=SIL_NOISE,
    detector=SIL_DETECTOR,
)
# One junction camera, eight drive-pasts; after the fourth the camera is knocked: 0.6 deg, 0.4 m.
MOVED_CAMERA = replace(
    SIL_NORTH,
    name="moved-camera",
    drive=DriveSpec(routes=("S>N", "W>S", "E>N", "N>S", "S>N", "W>S", "E>N", "N>S")),
    camera_move=CameraMoveSpec(after_traversal=3, turn_deg=0.6, shift_m=0.4),
)


# --- the real world and the ideal one
# Every scenario runs in the real world unless `ideal` is set: shaped bodies, a detector whose errors are at
# least REAL_DETECTOR_FLOOR's (never lowered below a preset's own), an unknown camera latency and CAM V2X
# from a GNSS receiver. `ideal` reproduces the first simulator's world for the same scene (cuboid bodies
# whose boxes are the cuboid's rectangle, i.i.d. jitter, stamps at exposure, the IMU poses as V2X), so the
# numbers measured in it stay reproducible. The figures below are the floor of realism, not a ceiling.
REAL_DETECTOR_FLOOR = DetectorSpec(
    box_jitter_px=1.0,
    miss_rate=0.02,
    false_positives_per_frame=0.03,
    class_confusion=0.02,
    visible_part_boxes=True,
    scale_bias=0.04,
    edge_bias_px=2.5,
    jitter_ar1=0.8,
    miss_run_start=0.01,
    miss_run_frames=4.0,
    merge_rate=0.02,
    split_rate=0.002,
)
# CMOS sensors of roadside cameras read a frame out in about 10-35 ms (1080p at 25-30 fps); global-shutter
# ones at once.
REAL_CLOCK = ClockSpec(latency_s=(0.04, 0.20), latency_jitter_s=0.003, readout_s=(0.0, 0.035))
_FLOORED = (
    "box_jitter_px",
    "miss_rate",
    "false_positives_per_frame",
    "class_confusion",
    "scale_bias",
    "edge_bias_px",
    "jitter_ar1",
    "miss_run_start",
    "miss_run_frames",
    "merge_rate",
    "split_rate",
)
_REAL_ONLY = _FLOORED[4:]


def world_detector(config: ScenarioConfig) -> DetectorSpec:
    """The detector the scenario's world has (see the block comment above)."""
    det = config.detector
    if config.ideal:
        zeros: dict[str, Any] = {name: 0.0 for name in _REAL_ONLY}
        return replace(det, **zeros)
    floored: dict[str, Any] = {
        name: max(getattr(det, name), getattr(REAL_DETECTOR_FLOOR, name)) for name in _FLOORED
    }
    return replace(det, visible_part_boxes=True, **floored)


def world_clock(config: ScenarioConfig) -> ClockSpec:
    """The camera clock: stamps at exposure in the ideal world, a preset's own latency or REAL_CLOCK's, and
    REAL_CLOCK's rolling shutter unless the preset gives its own readout ((0, 0): a global shutter)."""
    if config.ideal:
        return ClockSpec()
    clock = config.clock if config.clock.latency_s[1] > 0 else REAL_CLOCK
    return clock if clock.readout_s is not None else replace(clock, readout_s=REAL_CLOCK.readout_s)


def world_v2x_mode(config: ScenarioConfig) -> str:
    """ "imu" (poses as V2X) in the ideal world, else the preset's ("cam" unless it needs IMU poses)."""
    return "imu" if config.ideal else config.v2x.mode


def world_ground(config: ScenarioConfig) -> GroundSpec:
    """The ground: the preset's road (crown, kerbs, banks, vertical curves) in the real world, the terrain
    alone (plane + bumps) in the ideal one."""
    if config.ideal:
        return GroundSpec.flat(config.ground.slope, config.ground.bumps)
    return config.ground


def ideal(config: ScenarioConfig) -> ScenarioConfig:
    """The same scene in the first simulator's world."""
    return replace(config, ideal=True)


PRESETS: dict[str, ScenarioConfig] = {
    config.name: config
    for config in (
        CARLA_LIKE,
        SIL_NORTH,
        SIL_SOUTH,
        SIL_WEST,
        NOISE_02,
        NOISE_05,
        DENSE_TRAFFIC,
        OCCLUDED,
        SLOPE,
        V2X_10HZ,
        CLOCK_OFFSET,
        WIDE_DISTORTED,
        COLLINEAR,
        SINGLE_TRAVERSAL,
        NO_TARGET,
        LONG,
        PORTRAIT,
        ROLLED,
        LATENCY,
        NIGHT,
        SUV,
        VAN,
        PICKUP,
        TRUCK,
        BUS,
        RTK_FLOAT,
        CROWNED_ROAD,
        MOVED_CAMERA,
    )
}
