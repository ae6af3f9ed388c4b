"""Deterministic roadside-camera scenario simulator: `simulate(preset, seed) -> SimulationResult`.

It produces what a real RSU system receives, plus the truth: every camera's detection frames (camera
clock, 10 fps with jitter), the calibration vehicle's own pose reports (absolute UTM, its own clock, with
noise, drift, dropouts) and the same as V2X broadcasts (WGS84, true-north heading), and per camera the true
extrinsic and which box is the calibration vehicle in every frame. The world (sim.world), the traffic
(sim.traffic) and the detector (sim.detector) are described in their modules; presets in sim.presets.
Everything random comes from np.random.default_rng(seed) via one child generator per component.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from schemas.common import Box, CameraIntrinsics, LocalOrigin, VehicleProfile
from schemas.files import GroundTruth, GroundTruthFrame
from schemas.messages import DetectionFrame, V2xAccuracies, V2xPosition, VehiclePose
from sim.detector import Instances, RenderedFrames, cuboid_corners, may_be_in_view, render_frames
from sim.errors import SimulationError
from sim.geo import GeoFrame
from sim.geometry import FloatArray, IntArray, camera_position, mount_rotation
from sim.lens import Lens
from sim.presets import PRESETS, CameraSpec, PoseSpec, ScenarioConfig
from sim.shapes import cuboid_points, footprint_points, place_points, reference_from_footprint_centre
from sim.traffic import SimVehicle, TrafficResult, sample_vehicle, simulate_traffic
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
class SimulatedCamera:
    """One simulated camera: intrinsics and the true extrinsic X_cam = R @ X_local + t (local frame, m)."""

    camera_id: str
    intrinsics: CameraIntrinsics
    R_cam_from_local: FloatArray  # (3, 3)
    t_cam_from_local: FloatArray  # (3,)


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
    v2x: list[V2xPosition]  # the same poses as V2X broadcasts
    ground_truth: dict[str, GroundTruth]  # camera_id -> truth
    world: WorldGeometry
    traffic_count: int  # other vehicles simulated
    true_poses: FloatArray  # (N, 6) noise-free reference-point poses of the calibration vehicle, local frame
    true_stamps: IntArray  # (N,) the same instants in the camera clock (ns)


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


def _reference_poses(centre: FloatArray, profile: VehicleProfile) -> FloatArray:
    """Footprint-centre poses (N, 6) -> poses (N, 6) of the reference point (`imu_offset`, the IMU)."""
    return reference_from_footprint_centre(centre, profile)


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
    camera: SimulatedCamera,
    model: Lens,
    profile: VehicleProfile,
    windows: tuple[tuple[float, float], ...],
) -> tuple[Instances, _CalibrationTrack | None]:
    """All (frame, vehicle) pairs of one camera with the vehicle on the road at the frame's time and
    possibly in view (a conservative cull), plus the calibration vehicle's track at all its frames.
    `vehicles[0]` is the calibration vehicle: owner 0 in the instances."""
    frames, poses, dims, cls, owner = [], [], [], [], []
    calib: _CalibrationTrack | None = None
    calib_visible = np.zeros(0, dtype=bool)
    R, t = camera.R_cam_from_local, camera.t_cam_from_local
    view_bounds = model.view_bounds()
    for index, vehicle in enumerate(vehicles):
        first, last = np.searchsorted(times, [vehicle.t_start, vehicle.t_end], side="left")
        if last <= first:
            continue
        rows = np.arange(first, last)
        centre = sample_vehicle(vehicle, times[rows], ground).center_poses
        radius = 0.5 * math.sqrt(vehicle.length**2 + vehicle.width**2 + vehicle.height**2)
        middle = centre[:, :3] + np.array([0.0, 0.0, 0.5 * vehicle.height])
        visible = may_be_in_view(middle, np.full(len(rows), radius), R, t, view_bounds)
        if vehicle.is_calibration:
            calib = _CalibrationTrack(
                rows, _reference_poses(centre, profile), _traversal_labels(times[rows], windows)
            )
            calib_visible = visible
        frames.append(rows[visible])
        poses.append(centre[visible])
        dims.append(np.tile([vehicle.length, vehicle.width, vehicle.height], (int(visible.sum()), 1)))
        cls.append(np.full(int(visible.sum()), vehicle.cls))
        owner.append(np.full(int(visible.sum()), index))
    center_poses = np.concatenate(poses) if poses else np.zeros((0, 6))
    corners = cuboid_corners(center_poses, np.concatenate(dims) if dims else np.zeros((0, 3)))
    owner_all = np.concatenate(owner).astype(np.int64) if owner else np.zeros(0, dtype=np.int64)
    if calib is not None:
        # The calibration vehicle's cuboid straight from its reference-point pose and profile.
        corners[owner_all == 0] = place_points(
            calib.poses[calib_visible],
            cuboid_points(profile),
            np.asarray(profile.imu_offset, dtype=np.float64),
        )
    distance = np.hypot(*(center_poses[:, :2] - camera_position(R, t)[:2]).T)
    frame_all = np.concatenate(frames).astype(np.int64) if frames else np.zeros(0, dtype=np.int64)
    cls_all = np.concatenate(cls).astype(np.int64) if cls else np.zeros(0, dtype=np.int64)
    return Instances(frame_all, corners, distance, cls_all, owner_all), calib


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
    profile: VehicleProfile,
    accuracy_m: float,
) -> list[V2xPosition]:
    """The reported poses as V2X broadcasts: WGS84 position, true-north heading, the same stamps."""
    east = np.array([p.x for p in poses])
    north = np.array([p.y for p in poses])
    lat, lon = frame.to_wgs84(east, north)
    heading = frame.true_heading_deg(east, north, np.array([p.yaw for p in poses]))
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
            length=profile.length,
            width=profile.width,
            accuracies=accuracies,
        )
        for p, la, lo, h, v in zip(poses, lat, lon, heading, speed, strict=True)
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


def simulate(preset: str | ScenarioConfig, seed: int) -> SimulationResult:
    """Simulate one scenario; the same (preset, seed) always gives the same result."""
    config = resolve_config(preset)
    children = np.random.SeedSequence(seed).spawn(len(_STREAMS) + len(config.cameras))
    rng = {name: np.random.default_rng(child) for name, child in zip(_STREAMS, children, strict=False)}
    camera_rngs = [np.random.default_rng(child) for child in children[len(_STREAMS) :]]

    site = config.site
    origin = LocalOrigin(crs=site.crs, x=site.east_m, y=site.north_m, z=site.alt_m)
    origin_vec = np.array([origin.x, origin.y, origin.z])
    ground = GroundSurface.from_spec(config.ground)
    network = build_network(config.road)
    occluders = build_occluders(config.occluders, ground)
    world = WorldGeometry(lane_polylines(network, ground), occluders, ground)
    profile = config.vehicle
    traffic: TrafficResult = simulate_traffic(
        network,
        config.drive,
        config.traffic,
        (profile.length, profile.width, profile.height),
        config.duration_s,
        rng["drive"],
        rng["traffic"],
    )
    vehicles = [traffic.calibration, *traffic.others]
    # Camera clock at t = 0: the preset's start plus a seeded offset (< 3 h, ms resolution).
    start_ns = config.start_ns + int(rng["clock"].integers(0, 3 * 3600 * 1000)) * 1_000_000

    # --- the vehicle's own pose reports
    pose_t = _pose_instants(traffic.end_s, config.pose, rng["pose"])
    states = sample_vehicle(traffic.calibration, pose_t, ground)
    true_local, true_speed = _reference_poses(states.center_poses, profile), states.speed
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
    v2x = _v2x_messages(
        poses, reported_speed, GeoFrame(origin.crs), config.station_id, profile, config.pose.position_sigma_m
    )

    # --- cameras
    cameras = tuple(_camera_from_spec(spec, ground) for spec in config.cameras)
    occluder_corners = np.stack([o.corners for o in occluders]) if occluders else np.zeros((0, 8, 3))
    detections: dict[str, list[DetectionFrame]] = {}
    truths: dict[str, GroundTruth] = {}
    for camera, camera_rng in zip(cameras, camera_rngs, strict=True):
        times = _frame_times(
            traffic.end_s, config.detector.fps, config.detector.frame_jitter_s, rng["frames"]
        )
        stamps = start_ns + np.round(times * 1e9).astype(np.int64)
        model = Lens.from_intrinsics(camera.intrinsics)
        instances, calib = _instances(
            vehicles, times, ground, camera, model, profile, traffic.traversal_windows
        )
        rendered = render_frames(
            instances,
            len(times),
            occluder_corners,
            camera.R_cam_from_local,
            camera.t_cam_from_local,
            model,
            config.detector,
            camera_rng,
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
            camera, origin, origin_vec, config, stamps, rendered, calib, profile
        )
    return SimulationResult(
        preset=config.name,
        seed=seed,
        origin=origin,
        rsu_id=config.rsu_id,
        station_id=config.station_id,
        vehicle=profile,
        cameras=cameras,
        detections=detections,
        poses=poses,
        v2x=v2x,
        ground_truth=truths,
        world=world,
        traffic_count=len(traffic.others),
        true_poses=true_local,
        true_stamps=true_stamps,
    )


def _ground_truth(
    camera: SimulatedCamera,
    origin: LocalOrigin,
    origin_vec: FloatArray,
    config: ScenarioConfig,
    stamps: IntArray,
    rendered: RenderedFrames,
    calib: _CalibrationTrack | None,
    profile: VehicleProfile,
) -> GroundTruth:
    """Per frame: the calibration vehicle's box index and box, traversal (while detectable or detected) and
    true footprint at the frame's stamp."""
    calib_row, detectable = rendered.calib_row, rendered.calib_detectable
    traversal = np.full(len(stamps), -1, dtype=np.int64)
    footprints = np.full((len(stamps), 4, 3), np.nan)
    if calib is not None:
        traversal[calib.frames] = calib.traversal
        footprints[calib.frames] = place_points(
            calib.poses, footprint_points(profile), np.asarray(profile.imu_offset, dtype=np.float64)
        )
    frames = []
    for f, stamp in enumerate(stamps):
        row = int(calib_row[f])
        in_view = bool(detectable[f]) and traversal[f] >= 0
        if row < 0:
            frames.append(
                GroundTruthFrame(stamp_ns=int(stamp), traversal=int(traversal[f]) if in_view else None)
            )
            continue
        fp = footprints[f]
        box = rendered.boxes[f][row]
        frames.append(
            GroundTruthFrame(
                stamp_ns=int(stamp),
                calib_box=row,
                traversal=int(traversal[f]),
                footprint_local=(tuple(fp[0]), tuple(fp[1]), tuple(fp[2]), tuple(fp[3])),
                box=(float(box[0]), float(box[1]), float(box[2]), float(box[3])),
            )
        )
    R = camera.R_cam_from_local
    t_local = camera.t_cam_from_local
    detected = {int(traversal[f]) for f in range(len(stamps)) if calib_row[f] >= 0 and traversal[f] >= 0}
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
        frames=frames,
    )
