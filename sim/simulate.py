"""Deterministic roadside-camera scenario simulator: `simulate(preset, seed, ideal) -> SimulationResult`.

It produces what a real RSU system receives, plus the truth: every camera's detection frames (stamped by
the camera pipeline: exposure plus an unknown latency), the calibration vehicle's IMU pose reports (absolute
UTM, 50 Hz, its own clock: the toolbox's poses.yaml) and its V2X broadcasts (ETSI CAMs from its GNSS receiver
in the real world, the IMU poses in the ideal one), and per camera the true extrinsic(s), the latency and
which box is the calibration vehicle in every frame. The world (sim.world), the traffic (sim.traffic), the
bodies (sim.shapes), the detector (sim.detector) and V2X (sim.v2x) are described in their modules; presets
and the two worlds in sim.presets. The ideal world draws from np.random.default_rng(seed) via one child
generator per component, exactly as the first simulator did; what the real world adds draws from streams
of its own, so the ideal world's numbers never move.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import ConvexHull

from schemas.common import Box, CameraIntrinsics, LocalOrigin, VehicleProfile
from schemas.files import CameraMove, GroundTruth, GroundTruthFrame
from schemas.messages import DetectionFrame, V2xAccuracies, V2xPosition, VehiclePose
from sim.detector import (
    GROSS_MERGED,
    GROSS_SPLIT,
    Instances,
    RealDetector,
    RenderedFrames,
    may_be_in_view,
    project_boxes,
    render_frames,
)
from sim.errors import SimulationError
from sim.geo import GeoFrame
from sim.geometry import FloatArray, IntArray, camera_position, mount_rotation
from sim.lens import Lens
from sim.presets import (
    PRESETS,
    CameraSpec,
    ClockSpec,
    PoseSpec,
    ScenarioConfig,
    world_clock,
    world_detector,
    world_ground,
    world_v2x_mode,
)
from sim.presets import ideal as ideal_world
from sim.shapes import (
    BodyShape,
    body_type_for_class,
    cuboid_body,
    cuboid_points,
    draw_body,
    footprint_points,
    place_points,
    reference_from_footprint_centre,
)
from sim.traffic import SimVehicle, TrafficResult, sample_vehicle, simulate_traffic
from sim.v2x import CamSpec, GnssSpec, cam_generation, measure_gnss
from sim.world import (
    GroundSurface,
    Occluder,
    WorldGeometry,
    build_network,
    build_occluders,
    lane_polylines,
)

__all__ = [
    "PRESETS",
    "Occluder",
    "ScenarioConfig",
    "SimulatedCamera",
    "SimulationResult",
    "WorldGeometry",
    "simulate",
]

# Child generators, in this fixed order (cameras last, one each), so adding a camera changes nothing else.
_STREAMS = ("clock", "drive", "traffic", "pose", "frames")


@dataclass(frozen=True)
class CameraPose:
    """A camera's true extrinsic X_cam = R @ X_local + t (local frame, m) from `from_s` (simulation
    seconds) on."""

    from_s: float
    R_cam_from_local: FloatArray  # (3, 3)
    t_cam_from_local: FloatArray  # (3,)


@dataclass(frozen=True)
class SimulatedCamera:
    """One simulated camera: intrinsics and the true extrinsic X_cam = R @ X_local + t (local frame, m) at
    the start; `moves` are later extrinsics (a camera knocked between drive-pasts), in time order."""

    camera_id: str
    intrinsics: CameraIntrinsics
    R_cam_from_local: FloatArray  # (3, 3)
    t_cam_from_local: FloatArray  # (3,)
    moves: tuple[CameraPose, ...] = ()


@dataclass(frozen=True, eq=False)
class CameraScene:
    """What one camera saw, for rendering its images: per (frame, vehicle) instance the frame index (P,),
    the footprint-centre pose (P, 6) local and the vehicle index (P,) into SimulationResult.bodies."""

    frame: IntArray
    poses: FloatArray
    vehicle: IntArray


@dataclass(frozen=True)
class SimulationResult:
    """Everything a simulated scenario produces (see the module docstring)."""

    preset: str
    seed: int
    origin: LocalOrigin  # crs + UTM origin of the local frame
    rsu_id: str
    station_id: int  # the calibration vehicle's V2X station id
    vehicle: VehicleProfile  # the calibration vehicle
    cameras: tuple[SimulatedCamera, ...]
    detections: dict[str, list[DetectionFrame]]  # camera_id -> frames in time order (camera clock)
    poses: list[VehiclePose]  # reported: absolute UTM, vehicle clock, noise/drift/dropouts/offset applied
    v2x: list[V2xPosition]  # what the vehicle broadcasts: CAMs (real world) or its IMU poses (ideal world)
    ground_truth: dict[str, GroundTruth]  # camera_id -> truth
    world: WorldGeometry
    traffic_count: int  # other vehicles simulated
    true_poses: FloatArray  # (N, 6) noise-free reference-point poses of the calibration vehicle, local frame
    true_stamps: IntArray  # (N,) the same instants in the camera clock (ns)
    bodies: tuple[BodyShape, ...] = ()  # every vehicle's body (vehicle 0: the calibration vehicle)
    scenes: dict[str, CameraScene] = field(default_factory=dict)  # camera_id -> what it saw
    v2x_mode: str = "imu"  # "cam": calibrate from the V2X broadcasts; "imu": from `poses`
    is_ideal: bool = True  # the first simulator's world


def _camera_from_spec(spec: CameraSpec, ground: GroundSurface) -> SimulatedCamera:
    """Mast at (x, y) on the ground, optical centre `height_m` above it, aimed by yaw/pitch/roll."""
    z = float(ground.height(np.array([[spec.x_m, spec.y_m]]))[0]) + spec.height_m
    centre = np.array([spec.x_m, spec.y_m, z])
    R = mount_rotation(
        math.radians(spec.yaw_deg), math.radians(spec.pitch_down_deg), math.radians(spec.roll_deg)
    )
    intrinsics = CameraIntrinsics(
        width=spec.width,
        height=spec.height,
        fx=spec.fx,
        fy=spec.fy if spec.fy is not None else spec.fx,
        cx=spec.width / 2.0 + spec.principal_offset_px[0],
        cy=spec.height / 2.0 + spec.principal_offset_px[1],
        dist=spec.dist,
    )
    return SimulatedCamera(spec.camera_id, intrinsics, R, -R @ centre)


def _frame_times(end_s: float, fps: float, jitter_s: float, rng: np.random.Generator) -> FloatArray:
    """Exposure times (s) of one camera: a random phase, nominal period, small clipped Gaussian jitter."""
    period = 1.0 / fps
    count = math.floor((end_s - period) * fps)
    jitter = (
        np.clip(rng.normal(0.0, jitter_s, size=count), -3 * jitter_s, 3 * jitter_s) if jitter_s > 0 else 0.0
    )
    return np.asarray(rng.uniform(0.0, period) + period * np.arange(count) + jitter, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class _CalibrationTrack:
    """The calibration vehicle at one camera's frames while it is on the road: frame indices (M,), true
    reference-point poses (M, 6) local, traversal labels (M,)."""

    frames: np.ndarray
    poses: FloatArray
    traversal: np.ndarray


def _instances(
    vehicles: list[SimVehicle],
    times: FloatArray,
    ground: GroundSurface,
    pose: CameraPose,
    lens: Lens,
    calib_vehicle: VehicleProfile,
    windows: tuple[tuple[float, float], ...],
    readout_s: float = 0.0,
) -> tuple[Instances, _CalibrationTrack | None]:
    """All (frame, vehicle) pairs of one camera with the vehicle on the road at the frame's time and
    possibly in view (a conservative cull), plus the calibration vehicle's track at all its frames.
    `vehicles[0]` is the calibration vehicle: owner 0 in the instances; vehicle i wears body i. With a
    rolling shutter (`readout_s` > 0) each instance also has its pose at the frame's last row."""
    frames, poses, late, cls, owner = [], [], [], [], []
    calib: _CalibrationTrack | None = None
    R, t = pose.R_cam_from_local, pose.t_cam_from_local
    view_bounds = lens.view_bounds()
    for index, vehicle in enumerate(vehicles):
        first, last = np.searchsorted(times, [vehicle.t_start, vehicle.t_end], side="left")
        if last <= first:
            continue
        rows = np.arange(first, last)
        centre = sample_vehicle(vehicle, times[rows], ground).centre_poses
        # Mirrors and roof boxes reach a little beyond the data-sheet box: a generous sphere.
        radius = 0.5 * math.sqrt(vehicle.length**2 + (vehicle.width + 0.6) ** 2 + (vehicle.height + 0.5) ** 2)
        middle = centre[:, :3] + np.array([0.0, 0.0, 0.5 * vehicle.height])
        visible = may_be_in_view(middle, np.full(len(rows), radius), R, t, view_bounds)
        if vehicle.is_calibration:
            calib = _CalibrationTrack(
                rows,
                reference_from_footprint_centre(centre, calib_vehicle),
                _traversal_labels(times[rows], windows),
            )
        frames.append(rows[visible])
        poses.append(centre[visible])
        if readout_s > 0:
            at = np.minimum(times[rows[visible]] + readout_s, vehicle.t_end)
            late.append(sample_vehicle(vehicle, at, ground).centre_poses)
        cls.append(np.full(int(visible.sum()), vehicle.cls))
        owner.append(np.full(int(visible.sum()), index))
    centre_poses = np.concatenate(poses) if poses else np.zeros((0, 6))
    owner_all = np.concatenate(owner).astype(np.int64) if owner else np.zeros(0, dtype=np.int64)
    distance = np.hypot(*(centre_poses[:, :2] - camera_position(R, t)[:2]).T)
    frame_all = np.concatenate(frames).astype(np.int64) if frames else np.zeros(0, dtype=np.int64)
    cls_all = np.concatenate(cls).astype(np.int64) if cls else np.zeros(0, dtype=np.int64)
    late_poses = (np.concatenate(late) if late else np.zeros((0, 6))) if readout_s > 0 else None
    instances = Instances(frame_all, centre_poses, owner_all, distance, cls_all, owner_all, late_poses)
    return instances, calib


def _traversal_labels(t: FloatArray, windows: tuple[tuple[float, float], ...]) -> np.ndarray:
    """Traversal index (N,) of the calibration vehicle at times t: the traversal it is on, or on a connector
    the nearer one in time (a long lens may still see it leave along an arm); -1 without traversals."""
    if not windows:
        return np.full(len(t), -1, dtype=np.int64)
    bounds = np.array(windows)
    gap = np.maximum(bounds[None, :, 0] - t[:, None], 0.0) + np.maximum(t[:, None] - bounds[None, :, 1], 0.0)
    return np.asarray(np.argmin(gap, axis=1), dtype=np.int64)


def _drift(t: FloatArray, rms_m: float, rng: np.random.Generator) -> FloatArray:
    """Slow smooth drift (N,): three sinusoids with periods of 1-5 minutes, total RMS `rms_m`."""
    periods = rng.uniform(60.0, 300.0, size=3)
    phases = rng.uniform(0.0, 2.0 * math.pi, size=3)
    amplitude = rms_m * math.sqrt(2.0 / 3.0)
    return np.asarray(
        amplitude * np.sin(2.0 * math.pi * t[:, None] / periods + phases).sum(axis=1), dtype=np.float64
    )


def _pose_instants(end_s: float, spec: PoseSpec, rng: np.random.Generator) -> FloatArray:
    """Measurement instants (s, camera clock) of the vehicle's pose reports: own rate and phase, ~1 ms
    jitter, then `dropouts` gaps of 0.2-1 s removed."""
    period = 1.0 / spec.rate_hz
    nominal = rng.uniform(0.0, period) + period * np.arange(math.floor(end_s / period))
    jitter = spec.timing_jitter_s
    if jitter > 0:
        nominal = nominal + np.clip(rng.normal(0.0, jitter, size=len(nominal)), -3 * jitter, 3 * jitter)
    times = np.sort(nominal[(nominal >= 0.0) & (nominal < end_s)])
    keep = np.ones(len(times), dtype=bool)
    for _ in range(spec.dropouts):
        length = rng.uniform(*spec.dropout_s)
        start = rng.uniform(0.05 * end_s, 0.95 * end_s - length)
        keep &= ~((times >= start) & (times < start + length))
    return np.asarray(times[keep], dtype=np.float64)


def _reported_poses(
    true_local: FloatArray, speed: FloatArray, t: FloatArray, spec: PoseSpec, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray]:
    """What the GNSS/IMU reports: white noise on x, y (and z), slow drift, yaw noise; speed noise."""
    n = len(t)
    reported = true_local.copy()
    for axis in range(2):
        reported[:, axis] += (
            rng.normal(0.0, spec.position_sigma_m, size=n) if spec.position_sigma_m > 0 else 0.0
        )
        reported[:, axis] += _drift(t, spec.drift_m, rng) if spec.drift_m > 0 else 0.0
    if spec.height_sigma_m > 0:
        reported[:, 2] += rng.normal(0.0, spec.height_sigma_m, size=n)
    if spec.yaw_sigma_rad > 0:
        reported[:, 3] = np.angle(np.exp(1j * (reported[:, 3] + rng.normal(0.0, spec.yaw_sigma_rad, size=n))))
    noisy_speed = speed + (rng.normal(0.0, spec.speed_sigma_mps, size=n) if spec.speed_sigma_mps > 0 else 0.0)
    return reported, np.clip(noisy_speed, 0.0, 99.0)


def _v2x_messages(
    poses: list[VehiclePose],
    speed: FloatArray,
    frame: GeoFrame,
    station_id: int,
    calib_vehicle: VehicleProfile,
    accuracy_m: float,
) -> list[V2xPosition]:
    """The reported poses as V2X broadcasts: WGS84 position, true-north heading, the same stamps."""
    east = np.array([p.x for p in poses])
    north = np.array([p.y for p in poses])
    lat, lon = frame.to_wgs84(east, north)
    heading_deg = frame.true_heading_deg(east, north, np.array([p.yaw for p in poses]))
    accuracies = V2xAccuracies(horizontal_m=max(accuracy_m, 0.02), vertical_m=max(accuracy_m, 0.02))
    return [
        V2xPosition(
            station_id=station_id,
            stamp_ns=p.stamp_ns,
            lat=float(la),
            lon=float(lo),
            alt=p.z,
            heading_deg=float(h),
            speed=float(v),
            pitch=p.pitch,
            roll=p.roll,
            length=calib_vehicle.length,
            width=calib_vehicle.width,
            accuracies=accuracies,
        )
        for p, la, lo, h, v in zip(poses, lat, lon, heading_deg, speed, strict=True)
    ]


def resolve_config(preset: str | ScenarioConfig) -> ScenarioConfig:
    """A preset name or a config -> the config (SimulationError naming the choices for an unknown name)."""
    if isinstance(preset, ScenarioConfig):
        return preset
    if preset not in PRESETS:
        raise SimulationError(
            "preset", f"unknown preset {preset!r}; choose one of {', '.join(sorted(PRESETS))}"
        )
    return PRESETS[preset]


def _real_rng(seed: int, scene: str, stream: int) -> np.random.Generator:
    """A generator for what the real world adds, independent of the ideal world's streams (so the ideal
    world's numbers never move) and of the scene's name (so one seed does not draw the same vehicle and
    latencies in every preset)."""
    entropy = [seed, zlib.crc32(scene.encode())]
    return np.random.default_rng(np.random.SeedSequence(entropy, spawn_key=(1000 + stream,)))


def _centred(shape: BodyShape) -> FloatArray:
    """The vertices of the body's convex hull, about the footprint centre (L/2, W/2, 0) of the data-sheet
    box. They are all the detector needs: a box bounds, and a silhouette hull contains, the projections of
    the 3D hull's vertices exactly as those of all vertices (a third to half as many to project)."""
    vertices = shape.vertices[ConvexHull(shape.vertices).vertices]
    return np.asarray(vertices - np.array([shape.length_m / 2.0, shape.width_m / 2.0, 0.0]), np.float64)


def _calibration_body(config: ScenarioConfig, rng: np.random.Generator) -> tuple[BodyShape, VehicleProfile]:
    """The calibration vehicle: the preset's cuboid in the ideal world; in the real one a body of a type
    drawn per seed, its data sheet (L, W, H) drawn within the type's range, the IMU where the preset's is
    relative to the body (near the rear axle, on the centre line)."""
    if config.ideal:
        v = config.vehicle
        # The first simulator's poses wander only across (a drift of 3 cm over minutes; their heights carry
        # white noise alone): its vehicle says so.
        return cuboid_body(v.length, v.width, v.height), v.model_copy(update={"gnss_wander_m": (0.03, 0.0)})
    vehicle_type = str(rng.choice(list(config.bodies.calibration_types)))
    shape = draw_body(vehicle_type, rng)
    base = config.vehicle
    imu = (
        round(base.imu_offset[0] / base.length * shape.length_m, 3),
        round(shape.width_m / 2.0, 3),
        base.imu_offset[2],
    )
    calib_vehicle = VehicleProfile(
        length=round(shape.length_m, 3),
        width=round(shape.width_m, 3),
        height=round(shape.height_m, 3),
        imu_offset=imu,
    )
    return shape, calib_vehicle


def _traffic_bodies(
    vehicles: list[SimVehicle], calib: BodyShape, ideal: bool, rng: np.random.Generator
) -> tuple[BodyShape, ...]:
    """The body of every vehicle: the calibration vehicle's, then each other vehicle's (a cuboid of its
    traffic dimensions in the ideal world, else a shape of a type its class allows, with those dimensions)."""
    bodies = [calib]
    for vehicle in vehicles[1:]:
        if ideal:
            shape = cuboid_body(vehicle.length, vehicle.width, vehicle.height)
        else:
            kind = body_type_for_class(
                vehicle.cls, rng, length_m=vehicle.length, width_m=vehicle.width, height_m=vehicle.height
            )
            shape = draw_body(
                kind, rng, length_m=vehicle.length, width_m=vehicle.width, height_m=vehicle.height
            )
        bodies.append(shape)
    return tuple(bodies)


def _camera_poses(camera: SimulatedCamera) -> tuple[CameraPose, ...]:
    """The camera's extrinsics in time order, the first from the start."""
    return (CameraPose(-math.inf, camera.R_cam_from_local, camera.t_cam_from_local), *camera.moves)


def _segment_of(times: FloatArray, camera: SimulatedCamera) -> IntArray:
    """Index (N,) into _camera_poses(camera) of the extrinsic in effect at each time (s)."""
    starts = np.array([pose.from_s for pose in camera.moves])
    return np.asarray(np.searchsorted(starts, times, side="right"), dtype=np.int64)


def _moved(
    camera: SimulatedCamera, config: ScenarioConfig, windows: tuple[tuple[float, float], ...]
) -> SimulatedCamera:
    """The camera knocked halfway between two traversals: turned about the vertical through its optical
    centre and shifted sideways (horizontally, across its view), as config.camera_move says."""
    move = config.camera_move
    if move is None or move.after_traversal + 1 >= len(windows):
        return camera
    at_s = 0.5 * (windows[move.after_traversal][1] + windows[move.after_traversal + 1][0])
    R = camera.R_cam_from_local
    centre = camera_position(R, camera.t_cam_from_local)
    turn = math.radians(move.turn_deg)
    c, s_ = math.cos(turn), math.sin(turn)
    Rz = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    R_new = R @ Rz.T  # the camera body turned by Rz in the local frame
    right = R[0].copy()
    right[2] = 0.0
    right /= np.linalg.norm(right)
    centre_new = centre + move.shift_m * right
    return SimulatedCamera(
        camera.camera_id,
        camera.intrinsics,
        R,
        camera.t_cam_from_local,
        (CameraPose(at_s, R_new, -R_new @ centre_new),),
    )


def _camera_stamps(
    times: FloatArray,
    start_ns: int,
    clock: ClockSpec,
    rng: np.random.Generator,
    latency_override_s: float | None = None,
) -> tuple[IntArray, int]:
    """Detection stamps (N,) ns: exposure + the camera's latency (drawn per camera within clock.latency_s,
    or `latency_override_s`) + a few ms of jitter (+ drift); and the latency in ns. Stamps stay strictly
    increasing."""
    low, high = clock.latency_s
    # Drawn even when overridden, so that every later draw (jitter, the detector's) stays the same.
    drawn = float(rng.uniform(low, high)) if high > low else float(low)
    latency_s = drawn if latency_override_s is None else latency_override_s
    jitter = clock.latency_jitter_s
    noise = np.clip(rng.normal(0.0, jitter, size=len(times)), -3 * jitter, 3 * jitter) if jitter > 0 else 0.0
    drift = clock.drift_ppm * 1e-6 * times
    stamps = start_ns + np.round((times + latency_s + noise + drift) * 1e9).astype(np.int64)
    # Frames are 1/fps apart and the jitters a few ms: the stamps stay strictly increasing.
    return np.asarray(stamps, dtype=np.int64), round(latency_s * 1e9)


def _course_over_ground(
    vehicle: SimVehicle,
    t: FloatArray,
    ground: GroundSurface,
    calib_vehicle: VehicleProfile,
    body_yaw: FloatArray,
    half_step_s: float = 0.02,
) -> FloatArray:
    """The direction (N,) in which the reference point (the receiver's antenna) moves at times t (s): what
    a receiver's course over ground measures, from the point's own positions half_step_s either side. A
    body turning about its rear axle moves a point ahead of that axle at asin(d / R) to its heading (d its
    distance ahead, R its turn radius): a course is not the body's yaw. Where the point barely moves, the
    body's yaw (`body_yaw`)."""
    before = np.clip(t - half_step_s, vehicle.t_start, vehicle.t_end)
    after = np.clip(t + half_step_s, vehicle.t_start, vehicle.t_end)
    ends = [
        reference_from_footprint_centre(sample_vehicle(vehicle, when, ground).centre_poses, calib_vehicle)
        for when in (before, after)
    ]
    move = ends[1][:, :2] - ends[0][:, :2]
    course = np.arctan2(move[:, 1], move[:, 0])
    moving = np.hypot(move[:, 0], move[:, 1]) > 1e-4
    # Keep the course on the yaw's branch (the yaw is unwrapped along the path).
    course = body_yaw + np.angle(np.exp(1j * (course - body_yaw)))
    return np.asarray(np.where(moving, course, body_yaw), dtype=np.float64)


def _cam_broadcasts(
    vehicle: SimVehicle,
    end_s: float,
    ground: GroundSurface,
    calib_vehicle: VehicleProfile,
    origin: LocalOrigin,
    geo: GeoFrame,
    config: ScenarioConfig,
    start_ns: int,
    rng: np.random.Generator,
) -> list[V2xPosition]:
    """The calibration vehicle's CAMs: its GNSS receiver's fixes (sim.v2x's error model, RTK fixed or with
    float periods) at the CAM generation rules' instants; position of the reference point, course-over-
    ground heading, odometry speed, the receiver's reported accuracies, no pitch or roll; stamped with the
    fix time in the vehicle's clock."""
    gnss = GnssSpec.rtk_float() if config.v2x.rtk_float else GnssSpec.rtk_fixed()
    period = 1.0 / gnss.fix_rate_hz
    fix_t = np.asarray(rng.uniform(0.0, period) + period * np.arange(math.floor(end_s / period)), np.float64)
    states = sample_vehicle(vehicle, fix_t, ground)
    reference = reference_from_footprint_centre(states.centre_poses, calib_vehicle)
    course = _course_over_ground(vehicle, fix_t, ground, calib_vehicle, reference[:, 3])
    track = measure_gnss(fix_t, reference[:, :3], course, states.speed, gnss, rng)
    sent = cam_generation(track.t_s, track.position, track.yaw, track.speed_mps, CamSpec())
    east = track.position[sent, 0] + origin.x
    north = track.position[sent, 1] + origin.y
    lat, lon = geo.to_wgs84(east, north)
    heading_deg = geo.true_heading_deg(east, north, track.yaw[sent])
    stamps = start_ns + np.round(fix_t[sent] * 1e9).astype(np.int64) + config.pose.clock_offset_ns
    return [
        V2xPosition(
            station_id=config.station_id,
            stamp_ns=int(stamp),
            lat=float(la),
            lon=float(lo),
            alt=float(z + origin.z),
            heading_deg=float(h),
            speed=float(v),
            length=calib_vehicle.length,
            width=calib_vehicle.width,
            accuracies=V2xAccuracies(horizontal_m=float(sh), vertical_m=float(sv)),
        )
        for stamp, la, lo, z, h, v, sh, sv in zip(
            stamps,
            lat,
            lon,
            track.position[sent, 2],
            heading_deg,
            track.speed_mps[sent],
            track.horizontal_std_m[sent],
            track.vertical_std_m[sent],
            strict=True,
        )
    ]


def simulate(
    preset: str | ScenarioConfig,
    seed: int,
    ideal: bool = False,
    readout_s: float | None = None,
    latency_s: float | None = None,
) -> SimulationResult:
    """Simulate one scenario; the same (preset, seed, ideal, readout_s, latency_s) always gives the same
    result. `ideal` runs the scene in the first simulator's world (see sim.presets.ideal); `readout_s` gives
    every camera that rolling-shutter readout instead of the world's (0 in the ideal world, drawn in the real
    one); `latency_s` every camera that latency (s, stamp minus exposure; negative for a camera clock ahead
    of the vehicle's) instead of the world's, the rest of the scene unchanged."""
    config = resolve_config(preset)
    if ideal:
        config = ideal_world(config)
    children = np.random.SeedSequence(seed).spawn(len(_STREAMS) + len(config.cameras))
    rng = {name: np.random.default_rng(child) for name, child in zip(_STREAMS, children, strict=False)}
    camera_rngs = [np.random.default_rng(child) for child in children[len(_STREAMS) :]]

    site = config.site
    origin = LocalOrigin(crs=site.crs, x=site.east_m, y=site.north_m, z=site.alt_m)
    origin_vec = np.array([origin.x, origin.y, origin.z])
    network = build_network(config.road)
    ground = GroundSurface.from_spec(world_ground(config), network)
    occluders = build_occluders(config.occluders, ground)
    world = WorldGeometry(lane_polylines(network, ground), occluders, ground)
    calib_shape, calib_vehicle = _calibration_body(config, _real_rng(seed, config.name, 0))
    traffic: TrafficResult = simulate_traffic(
        network,
        config.drive,
        config.traffic,
        (calib_vehicle.length, calib_vehicle.width, calib_vehicle.height),
        config.duration_s,
        rng["drive"],
        rng["traffic"],
    )
    vehicles = [traffic.calibration, *traffic.others]
    shapes = _traffic_bodies(vehicles, calib_shape, config.ideal, _real_rng(seed, config.name, 1))
    if not config.ideal:
        # Each body turns about its own rear axle (its drawn wheels'), not about its centre.
        vehicles = [
            replace(vehicle, rear_axle_m=float(shape.wheel_contacts[0, 0]))
            for vehicle, shape in zip(vehicles, shapes, strict=True)
        ]
    calibration = vehicles[0]
    bodies = tuple(_centred(shape) for shape in shapes)
    # Camera clock at t = 0: the preset's start plus a seeded offset (< 3 h, ms resolution).
    start_ns = config.start_ns + int(rng["clock"].integers(0, 3 * 3600 * 1000)) * 1_000_000

    # --- the vehicle's own pose reports (its IMU, 50 Hz: the toolbox's poses.yaml)
    pose_t = _pose_instants(traffic.end_s, config.pose, rng["pose"])
    states = sample_vehicle(calibration, pose_t, ground)
    true_local, true_speed = reference_from_footprint_centre(states.centre_poses, calib_vehicle), states.speed
    reported, reported_speed = _reported_poses(true_local, true_speed, pose_t, config.pose, rng["pose"])
    true_stamps = start_ns + np.round(pose_t * 1e9).astype(np.int64)
    vehicle_stamps = true_stamps + config.pose.clock_offset_ns
    poses = [
        VehiclePose(
            stamp_ns=int(stamp),
            x=float(p[0] + origin.x),
            y=float(p[1] + origin.y),
            z=float(p[2] + origin.z),
            yaw=float(p[3]),
            pitch=float(p[4]),
            roll=float(p[5]),
        )
        for stamp, p in zip(vehicle_stamps, reported, strict=True)
    ]
    geo = GeoFrame(origin.crs)
    v2x_mode = world_v2x_mode(config)
    if v2x_mode == "cam":
        v2x = _cam_broadcasts(
            calibration,
            traffic.end_s,
            ground,
            calib_vehicle,
            origin,
            geo,
            config,
            start_ns,
            _real_rng(seed, config.name, 2),
        )
    else:
        v2x = _v2x_messages(
            poses, reported_speed, geo, config.station_id, calib_vehicle, config.pose.position_sigma_m
        )

    # --- cameras
    detector = world_detector(config)
    clock = world_clock(config)
    cameras = tuple(
        _moved(_camera_from_spec(spec, ground), config, traffic.traversal_windows) for spec in config.cameras
    )
    occluder_corners = np.stack([o.corners for o in occluders]) if occluders else np.zeros((0, 8, 3))
    detections: dict[str, list[DetectionFrame]] = {}
    truths: dict[str, GroundTruth] = {}
    scenes: dict[str, CameraScene] = {}
    for index, (camera, camera_rng) in enumerate(zip(cameras, camera_rngs, strict=True)):
        times = _frame_times(traffic.end_s, detector.fps, detector.frame_jitter_s, rng["frames"])
        real_rng = _real_rng(seed, config.name, 100 + index)
        stamps, latency_ns = _camera_stamps(times, start_ns, clock, real_rng, latency_s)
        low, high = clock.readout_s or (0.0, 0.0)
        # Its own generator: the other draws do not move.
        readout = float(_real_rng(seed, config.name, 200 + index).uniform(low, high)) if high > 0 else 0.0
        readout = readout if readout_s is None else readout_s
        lens = Lens.from_intrinsics(camera.intrinsics)
        real = None if config.ideal else RealDetector.draw(detector, real_rng)
        segments = _camera_poses(camera)
        parts: list[RenderedFrames] = []
        calib: _CalibrationTrack | None = None
        segment = _segment_of(times, camera)
        seen: list[tuple[IntArray, FloatArray, IntArray]] = []
        for n, pose in enumerate(segments):
            first = int(np.searchsorted(segment, n, side="left"))
            last = int(np.searchsorted(segment, n, side="right"))
            instances, seg_calib = _instances(
                vehicles,
                times[first:last],
                ground,
                pose,
                lens,
                calib_vehicle,
                traffic.traversal_windows,
                readout,
            )
            parts.append(
                render_frames(
                    instances,
                    bodies,
                    last - first,
                    occluder_corners,
                    pose.R_cam_from_local,
                    pose.t_cam_from_local,
                    lens,
                    detector,
                    camera_rng,
                    real,
                )
            )
            seen.append((instances.frame + first, instances.poses, instances.owner))
            if seg_calib is not None:
                shifted = _CalibrationTrack(seg_calib.frames + first, seg_calib.poses, seg_calib.traversal)
                calib = (
                    shifted
                    if calib is None
                    else _CalibrationTrack(
                        np.concatenate([calib.frames, shifted.frames]),
                        np.concatenate([calib.poses, shifted.poses]),
                        np.concatenate([calib.traversal, shifted.traversal]),
                    )
                )
        rendered = _join(parts)
        scenes[camera.camera_id] = CameraScene(
            np.concatenate([f for f, _, _ in seen]),
            np.concatenate([p for _, p, _ in seen]),
            np.concatenate([v for _, _, v in seen]),
        )
        detections[camera.camera_id] = [
            DetectionFrame(
                camera_id=camera.camera_id,
                stamp_ns=int(stamp),
                boxes=[
                    Box(
                        x1=float(b[0]),
                        y1=float(b[1]),
                        x2=float(b[2]),
                        y2=float(b[3]),
                        cls=int(c),
                        score=float(s),
                    )
                    for b, c, s in zip(boxes, classes, scores, strict=True)
                ],
            )
            for stamp, boxes, classes, scores in zip(
                stamps, rendered.boxes, rendered.classes, rendered.scores, strict=True
            )
        ]
        truths[camera.camera_id] = _ground_truth(
            camera,
            origin,
            origin_vec,
            config,
            stamps,
            times,
            start_ns,
            latency_ns,
            round(readout * 1e9),
            rendered,
            calib,
            calib_vehicle,
            lens,
            v2x_mode,
            calib_shape,
        )
    return SimulationResult(
        preset=config.name,
        seed=seed,
        origin=origin,
        rsu_id=config.rsu_id,
        station_id=config.station_id,
        vehicle=calib_vehicle,
        cameras=cameras,
        detections=detections,
        poses=poses,
        v2x=v2x,
        ground_truth=truths,
        world=world,
        traffic_count=len(traffic.others),
        true_poses=true_local,
        true_stamps=true_stamps,
        bodies=shapes,
        scenes=scenes,
        v2x_mode=v2x_mode,
        is_ideal=config.ideal,
    )


def _join(parts: list[RenderedFrames]) -> RenderedFrames:
    """One camera's detections from consecutive time segments (a camera moved between them)."""
    if len(parts) == 1:
        return parts[0]
    return RenderedFrames(
        boxes=[b for part in parts for b in part.boxes],
        classes=[c for part in parts for c in part.classes],
        scores=[s for part in parts for s in part.scores],
        calib_row=np.concatenate([part.calib_row for part in parts]),
        calib_detectable=np.concatenate([part.calib_detectable for part in parts]),
        calib_visible_box=np.concatenate([part.calib_visible_box for part in parts]),
        calib_gross=np.concatenate([part.calib_gross for part in parts]),
    )


def _ground_truth(
    camera: SimulatedCamera,
    origin: LocalOrigin,
    origin_vec: FloatArray,
    config: ScenarioConfig,
    stamps: IntArray,
    times: FloatArray,
    start_ns: int,
    latency_ns: int,
    readout_ns: int,
    rendered: RenderedFrames,
    calib: _CalibrationTrack | None,
    calib_vehicle: VehicleProfile,
    lens: Lens,
    v2x_mode: str,
    calib_shape: BodyShape,
) -> GroundTruth:
    """Per frame: the calibration vehicle's box index and box, traversal (while detectable or detected),
    true footprint at the frame's exposure, the true box of its visible outline and of its data-sheet
    cuboid; per camera: the extrinsic(s), the latency, the vehicle's body."""
    calib_row, detectable = rendered.calib_row, rendered.calib_detectable
    traversal = np.full(len(stamps), -1, dtype=np.int64)
    footprints = np.full((len(stamps), 4, 3), np.nan)
    cuboid_boxes = np.full((len(stamps), 4), np.nan)
    imu = np.asarray(calib_vehicle.imu_offset, dtype=np.float64)
    if calib is not None:
        traversal[calib.frames] = calib.traversal
        footprints[calib.frames] = place_points(calib.poses, footprint_points(calib_vehicle), imu)
        corners = place_points(calib.poses, cuboid_points(calib_vehicle), imu)
        segment = _segment_of(times[calib.frames], camera)
        for n, pose in enumerate(_camera_poses(camera)):
            rows = np.flatnonzero(segment == n)
            if len(rows):
                projected = project_boxes(corners[rows], pose.R_cam_from_local, pose.t_cam_from_local, lens)
                cuboid_boxes[calib.frames[rows]] = projected.raw
    frames = []
    gross_names = {GROSS_MERGED: "merged", GROSS_SPLIT: "split"}
    for f, stamp in enumerate(stamps):
        row = int(calib_row[f])
        in_view = bool(detectable[f]) and traversal[f] >= 0
        if row < 0:
            frames.append(
                GroundTruthFrame(
                    stamp_ns=int(stamp),
                    exposure_ns=start_ns + round(float(times[f]) * 1e9),
                    traversal=int(traversal[f]) if in_view else None,
                )
            )
            continue
        fp = footprints[f]
        box = rendered.boxes[f][row]
        visible = rendered.calib_visible_box[f]
        cuboid = cuboid_boxes[f]
        frames.append(
            GroundTruthFrame(
                stamp_ns=int(stamp),
                exposure_ns=start_ns + round(float(times[f]) * 1e9),
                calib_box=row,
                traversal=int(traversal[f]),
                footprint_local=(tuple(fp[0]), tuple(fp[1]), tuple(fp[2]), tuple(fp[3])),
                box=(float(box[0]), float(box[1]), float(box[2]), float(box[3])),
                visible_box=None if np.isnan(visible[0]) else tuple(float(v) for v in visible),
                cuboid_box=None if np.isnan(cuboid[0]) else tuple(float(v) for v in cuboid),
                gross_error=gross_names.get(int(rendered.calib_gross[f])),
            )
        )
    R = camera.R_cam_from_local
    t_local = camera.t_cam_from_local
    detected = {int(traversal[f]) for f in range(len(stamps)) if calib_row[f] >= 0 and traversal[f] >= 0}
    moves = [
        CameraMove(
            from_exposure_ns=start_ns + round(pose.from_s * 1e9),
            R=(
                tuple(pose.R_cam_from_local[0]),
                tuple(pose.R_cam_from_local[1]),
                tuple(pose.R_cam_from_local[2]),
            ),
            t_utm=tuple(pose.t_cam_from_local - pose.R_cam_from_local @ origin_vec),
            t_local=tuple(pose.t_cam_from_local),
            camera_position_utm=tuple(
                camera_position(pose.R_cam_from_local, pose.t_cam_from_local) + origin_vec
            ),
        )
        for pose in camera.moves
    ]
    return GroundTruth(
        camera_id=camera.camera_id,
        crs=origin.crs,
        origin=(origin.x, origin.y, origin.z),
        R=(tuple(R[0]), tuple(R[1]), tuple(R[2])),
        t_utm=tuple(t_local - R @ origin_vec),
        t_local=tuple(t_local),
        camera_position_utm=tuple(camera_position(R, t_local) + origin_vec),
        intrinsics=camera.intrinsics,
        station_id=config.station_id,
        clock_offset_ns=config.pose.clock_offset_ns,
        traversals=len(detected),
        latency_ns=latency_ns,
        readout_ns=readout_ns,
        world="ideal" if config.ideal else "real",
        v2x="cam" if v2x_mode == "cam" else "imu",
        vehicle_type=calib_shape.vehicle_type,
        vehicle_proportions=dict(calib_shape.proportions),
        moves=moves,
        frames=frames,
    )
