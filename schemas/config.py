"""The daemon's configuration (`rsucal daemon --config rsu.yaml`): one validated, frozen model per section.

Every field has a default that works on one machine with nothing else installed, except what only the site
knows: rsu_id, the cameras and the calibration vehicles. deploy/rsu.example.yaml documents each field.
Durations are seconds (`_s`), sizes bytes (`_bytes`); names follow docs/design.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, model_validator

from schemas.common import (
    EPSG_PATTERN,
    CameraIntrinsics,
    ClassId,
    ClassLabel,
    ClassName,
    Identifier,
    StrictModel,
    VehicleProfile,
)

GIB = 1024**3
MIB = 1024**2

CommonName = Annotated[
    str,
    Field(
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9_.@\-]+$",
        description="a certificate's common name (CN), its identity in Zenoh's access control",
    ),
]


class ZenohConfig(StrictModel):
    """The daemon's Zenoh session (docs/design.md: peer on loopback, multicast scouting off)."""

    mode: Literal["peer", "client"] = Field(
        default="peer", description="peer: standalone or mesh; client: through a Zenoh router"
    )
    listen: list[str] = Field(
        default_factory=lambda: ["tcp/127.0.0.1:7447"],
        max_length=16,
        description="endpoints to listen on (peer mode), e.g. tcp/127.0.0.1:7447",
    )
    connect: list[str] = Field(
        default_factory=list, max_length=16, description="endpoints to connect to, e.g. a router's"
    )
    multicast_scouting: bool = Field(default=False, description="discover peers by UDP multicast")
    config_file: Path | None = Field(
        default=None,
        description="a Zenoh JSON5 config (TLS, access control) as the base; the fields above override it",
    )
    access_control_file: Path | None = Field(
        default=None,
        description="the enforcing router's Zenoh config (secure-router.json5), whose access rules the "
        "daemon checks at start when it is a mutual-TLS client",
    )

    @model_validator(mode="after")
    def _endpoints(self) -> ZenohConfig:
        for name, endpoints in (("listen", self.listen), ("connect", self.connect)):
            for index, endpoint in enumerate(endpoints):
                if "/" not in endpoint or endpoint.startswith("/") or len(endpoint) > 256:
                    raise ValueError(
                        f"{name}.{index} = {endpoint!r} is not a Zenoh endpoint like tcp/host:port"
                    )
        if self.mode == "client" and not self.connect and self.config_file is None:
            raise ValueError("mode client needs connect endpoints (a router) or a config_file")
        return self


class GeoPoint(StrictModel):
    """A WGS84 point: latitude, longitude (deg) and optional ellipsoidal height (m)."""

    lat: float = Field(ge=-90.0, le=90.0, allow_inf_nan=False)
    lon: float = Field(ge=-180.0, le=180.0, allow_inf_nan=False)
    alt: float | None = Field(default=None, ge=-500.0, le=9000.0, allow_inf_nan=False)


class DetectorConfig(StrictModel):
    """An ONNX detector the daemon runs on this camera's images (`rsu/{rsu}/camera/{cam}/image`, Foxglove
    CompressedImage, JPEG or PNG); its boxes enter ingest like bus detections, stamped with the image's."""

    model: Path = Field(description="the ONNX file (any export of the layout's family); never downloaded")
    layout: Literal["yolov5", "yolov8", "yolox"] = Field(
        description="output layout: yolov5 (1, N, 5+C), yolov8 (1, 4+C, N), yolox (1, N, 5+C) undecoded"
    )
    score_threshold: float = Field(default=0.3, gt=0.0, le=1.0, allow_inf_nan=False)
    nms_iou: float = Field(default=0.45, gt=0.0, le=1.0, allow_inf_nan=False, description="per class")
    classes: list[ClassLabel] | None = Field(
        default=None,
        min_length=1,
        max_length=1000,
        description="keep only these classes (names through the camera's labels, or ids); None: all",
    )
    max_boxes: int = Field(default=300, ge=1, le=2000, description="per image, best scores first")
    threads: int = Field(default=1, ge=1, le=64, description="onnxruntime intra-op threads")
    queue_images: int = Field(
        default=2, ge=1, le=100, description="images waiting; a newer one drops the oldest (counted)"
    )
    max_image_bytes: int = Field(
        default=32 * MIB, ge=64 * 1024, le=1024 * MIB, description="larger image payloads are rejected"
    )


class CameraConfig(StrictModel):
    """One camera of the RSU. Coverage (where the calibration vehicle is in view) is a polygon, or a circle
    around the approximate position; without either it is learned from the first accepted calibration."""

    camera_id: Identifier
    intrinsics: CameraIntrinsics
    position: GeoPoint | None = Field(default=None, description="approximate camera position")
    coverage_radius_m: float | None = Field(
        default=None, gt=0.0, le=2000.0, allow_inf_nan=False, description="circle around `position`, m"
    )
    coverage_polygon: list[GeoPoint] | None = Field(
        default=None, min_length=3, max_length=256, description="area of the road in view (WGS84 vertices)"
    )
    labels: dict[ClassId, ClassName] | None = Field(
        default=None,
        max_length=1001,
        description="the detector's class id -> name (e.g. COCO's 2: car); None: ids are toolbox ids",
    )
    detector: DetectorConfig | None = Field(
        default=None, description="run this ONNX detector on the camera's images (no bus detections needed)"
    )
    detector_cert_common_names: list[CommonName] | None = Field(
        default=None,
        min_length=1,
        max_length=16,
        description="certificates that alone may publish this camera's detections and images under access "
        "control; None: the RSU's detector_cert_common_names",
    )

    @model_validator(mode="after")
    def _coverage(self) -> CameraConfig:
        if self.coverage_radius_m is not None and self.position is None:
            raise ValueError("coverage_radius_m needs position (the circle's centre)")
        return self


class CalibrationVehicle(StrictModel):
    """A vehicle whose V2X positions are trusted for calibration: its station id and body."""

    station_id: int = Field(ge=0, le=4_294_967_295)
    # `profile` is the rsu.yaml key (a published contract, kept); in code a VehicleProfile is `vehicle`.
    profile: VehicleProfile
    time_offset_ns: int = Field(
        default=0,
        ge=-10_000_000_000,
        le=10_000_000_000,
        description="vehicle clock minus camera clock, ns, when known",
    )
    cert_common_names: list[CommonName] | None = Field(
        default=None,
        min_length=1,
        max_length=16,
        description="certificates that alone may publish v2x/cam/{station_id} under access control; "
        "None: vehicle-{station_id}",
    )

    def common_names(self) -> tuple[str, ...]:
        """The certificate common names that may speak for this station (default vehicle-{station_id})."""
        if self.cert_common_names is not None:
            return tuple(self.cert_common_names)
        return (f"vehicle-{self.station_id}",)


class TriggerConfig(StrictModel):
    """When a calibration job starts: enough traversals, then a quiet period after the vehicle left."""

    min_traversals: int = Field(default=3, ge=2, le=100, description="drive-pasts per job (never below 2)")
    quiet_period_s: float = Field(
        default=60.0, ge=0.0, le=86_400.0, allow_inf_nan=False, description="wait after the vehicle left"
    )
    max_window_s: float = Field(
        default=3600.0, gt=0.0, le=30 * 86_400.0, allow_inf_nan=False, description="oldest traversal used"
    )
    min_dwell_s: float = Field(
        default=1.0, ge=0.0, le=600.0, allow_inf_nan=False, description="shorter visits are not traversals"
    )
    exit_grace_s: float = Field(
        default=3.0,
        gt=0.0,
        le=600.0,
        allow_inf_nan=False,
        description="outside coverage (or silent) this long = the vehicle left",
    )
    learn_window_s: float = Field(
        default=1800.0,
        gt=0.0,
        le=30 * 86_400.0,
        allow_inf_nan=False,
        description="without coverage: run a job on this much data (then the quiet period) to learn it",
    )


class StorageConfig(StrictModel):
    """State and MCAP recordings: rotation and retention."""

    state_dir: Path = Field(default=Path("/var/lib/rsucal"), description="results, state, recordings")
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    chunk_bytes: int = Field(default=1 * MIB, ge=4096, le=64 * MIB, description="MCAP chunk size")
    flush_interval_s: float = Field(
        default=1.0, gt=0.0, le=60.0, allow_inf_nan=False, description="a crash loses at most this much"
    )
    rotate_bytes: int = Field(default=256 * MIB, ge=1 * MIB, le=64 * GIB, description="new file after this")
    rotate_s: float = Field(default=3600.0, ge=1.0, le=7 * 86_400.0, allow_inf_nan=False)
    retention_bytes: int = Field(
        default=20 * GIB, ge=16 * MIB, le=2**50, description="recordings kept, total"
    )
    retention_s: float = Field(default=7 * 86_400.0, ge=60.0, le=3650 * 86_400.0, allow_inf_nan=False)
    foxglove_views: bool = Field(
        default=True,
        description="also record Foxglove views: LocationFix, ImageAnnotations, FrameTransform, camera info",
    )
    history_keep: int = Field(
        default=500, ge=1, le=1_000_000, description="results (and their reports) kept per camera in history/"
    )
    history_max_age_s: float = Field(
        default=365 * 86_400.0,
        ge=3600.0,
        le=3650 * 86_400.0,
        allow_inf_nan=False,
        description="history entries older than this are deleted (the current result never)",
    )


class IngestConfig(StrictModel):
    """Limits on incoming messages; anything beyond is rejected, counted and warned about (rate-limited)."""

    max_payload_bytes: int = Field(default=1 * MIB, ge=1024, le=64 * MIB)
    queue_size: int = Field(default=200_000, ge=100, le=10_000_000, description="inbox; overflow is counted")
    queue_bytes: int = Field(
        default=256 * MIB, ge=1 * MIB, le=64 * GIB, description="inbox payload bytes; overflow is counted"
    )
    warn_interval_s: float = Field(default=10.0, gt=0.0, le=3600.0, allow_inf_nan=False)
    max_clock_skew_s: float | None = Field(
        default=None,
        gt=0.0,
        allow_inf_nan=False,
        description="reject stamps this far from our clock (None: off, e.g. for replays)",
    )
    max_speed_mps: float = Field(default=70.0, gt=0.0, le=200.0, allow_inf_nan=False)
    max_accel_mps2: float = Field(default=15.0, gt=0.0, le=100.0, allow_inf_nan=False)
    max_yaw_rate_deg_s: float = Field(default=120.0, gt=0.0, le=2000.0, allow_inf_nan=False)
    max_position_error_m: float = Field(
        default=1.0,
        gt=0.0,
        le=10.0,
        allow_inf_nan=False,
        description="jump-check margin (GNSS noise)",
    )


# gates.max_v2x_std_m's default, for the offline commands that have no rsu.yaml (1 sigma, m: RTK fixed).
DEFAULT_MAX_V2X_STD_M = 0.1


class GatesConfig(StrictModel):
    """Validation gates before anything is published (docs/design.md defaults); the one definition of the
    gates: the pipeline's validation (pipeline.validation.validate) takes this model."""

    min_traversals: int = Field(default=2, ge=2, le=100)
    max_delta_p_mean_m: float = Field(default=0.5, gt=0.0, le=10.0, allow_inf_nan=False)
    min_camera_height_m: float = Field(default=2.0, ge=0.0, le=1000.0, allow_inf_nan=False)
    max_camera_height_m: float = Field(default=60.0, gt=0.0, le=1000.0, allow_inf_nan=False)
    max_position_std_m: float = Field(default=0.5, gt=0.0, le=100.0, allow_inf_nan=False)
    max_rotation_std_deg: float = Field(default=0.5, gt=0.0, le=90.0, allow_inf_nan=False)
    # The std gates hold at this many sigmas: a result is accepted only if its 3-sigma uncertainty lies
    # inside the limits above. At 1 sigma a nearly degenerate scene (all passes along one straight road)
    # with std 0.35 deg would pass while its pose is 0.5 deg off one time in three.
    std_sigmas: float = Field(default=3.0, gt=0.0, le=10.0, allow_inf_nan=False)
    min_correspondences: int = Field(default=30, ge=4, le=1_000_000)
    # Median over boxes of the worst edge misfit relative to the box height: detector noise gives ~1-4 %,
    # 0.5 m GNSS noise ~10-15 %, another vehicle's track far more (its size and path do not fit the cuboid).
    # A median is robust to the few foreign boxes an identity switch puts into a track.
    max_box_error_pct: float = Field(default=25.0, gt=0.0, le=100.0, allow_inf_nan=False)
    # V2X positions whose reported 1-sigma accuracy is worse than this horizontally (or twice this
    # vertically: GNSS heights are about half as good) are not used: RTK fixed reports 1-3 cm, RTK float and
    # DGPS 0.2-1 m, and a pose half a metre off is a camera half a metre off. Positions without a reported
    # accuracy are used (the toolbox's poses.yaml has none).
    max_v2x_std_m: float = Field(default=DEFAULT_MAX_V2X_STD_M, gt=0.0, le=100.0, allow_inf_nan=False)

    @model_validator(mode="after")
    def _heights(self) -> GatesConfig:
        if self.min_camera_height_m >= self.max_camera_height_m:
            raise ValueError("min_camera_height_m must be below max_camera_height_m")
        return self


class ChangeConfig(StrictModel):
    """When a re-verification means the camera moved: its shift (position or rotation) from the current result
    exceeds both the minimum here and `sigmas` standard deviations of the difference of the two results."""

    shift_m: float = Field(default=0.3, gt=0.0, le=100.0, allow_inf_nan=False, description="minimum, m")
    shift_deg: float = Field(default=0.5, gt=0.0, le=180.0, allow_inf_nan=False, description="minimum, deg")
    sigmas: float = Field(
        default=3.0,
        ge=0.0,
        le=100.0,
        allow_inf_nan=False,
        description="k: the shift must also exceed k std of the difference (both results' covariances)",
    )


class JobsConfig(StrictModel):
    """Calibration jobs: separate processes, so the bus loop never waits."""

    max_parallel: int = Field(default=1, ge=1, le=16, description="jobs running at once (cameras queue)")
    track_workers: int = Field(default=2, ge=1, le=64, description="processes per job for the track fits")
    timeout_s: float = Field(default=900.0, gt=0.0, le=86_400.0, allow_inf_nan=False)
    seed: int = Field(default=0, ge=0, le=2**32 - 1, description="RANSAC seed: jobs are reproducible")


class DaemonConfig(StrictModel):
    """Everything `rsucal daemon` needs; validated once at start, then passed down explicitly."""

    rsu_id: Identifier
    crs: str | None = Field(
        default=None,
        pattern=EPSG_PATTERN,
        description="UTM zone of results; default from the first camera position or V2X message",
    )
    zenoh: ZenohConfig = Field(default_factory=ZenohConfig)
    cameras: list[CameraConfig] = Field(min_length=1, max_length=64)
    vehicles: list[CalibrationVehicle] = Field(min_length=1, max_length=256)
    trigger: TriggerConfig = Field(default_factory=TriggerConfig)
    storage: StorageConfig = Field(default_factory=StorageConfig)
    ingest: IngestConfig = Field(default_factory=IngestConfig)
    gates: GatesConfig = Field(default_factory=GatesConfig)
    change: ChangeConfig = Field(default_factory=ChangeConfig)
    jobs: JobsConfig = Field(default_factory=JobsConfig)
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    detector_cert_common_names: list[CommonName] | None = Field(
        default=None,
        min_length=1,
        max_length=16,
        description="certificates that alone may publish detections and images of every camera without "
        "its own list, under access control; None: detector-{rsu_id}",
    )

    @model_validator(mode="after")
    def _unique_and_consistent(self) -> DaemonConfig:
        camera_ids = [camera.camera_id for camera in self.cameras]
        if len(set(camera_ids)) != len(camera_ids):
            raise ValueError(f"cameras: camera_id values must be unique, got {camera_ids}")
        station_ids = [vehicle.station_id for vehicle in self.vehicles]
        if len(set(station_ids)) != len(station_ids):
            raise ValueError(f"vehicles: station_id values must be unique, got {station_ids}")
        if self.gates.min_traversals > self.trigger.min_traversals:
            raise ValueError("gates.min_traversals must not exceed trigger.min_traversals")
        if self.storage.retention_s < self.trigger.max_window_s:
            raise ValueError("storage.retention_s must cover trigger.max_window_s (jobs read that window)")
        return self

    def camera(self, camera_id: str) -> CameraConfig:
        """The camera with this id; KeyError names it when unknown."""
        for camera in self.cameras:
            if camera.camera_id == camera_id:
                return camera
        raise KeyError(f"camera_id {camera_id!r} is not configured")

    def detector_common_names(self, camera_id: str) -> tuple[str, ...]:
        """The certificate common names that may publish this camera's detections and images: the camera's
        own list, else the RSU's, else detector-{rsu_id}. KeyError names an unknown camera."""
        own = self.camera(camera_id).detector_cert_common_names
        if own is not None:
            return tuple(own)
        if self.detector_cert_common_names is not None:
            return tuple(self.detector_cert_common_names)
        return (f"detector-{self.rsu_id}",)

    def vehicle(self, station_id: int) -> CalibrationVehicle | None:
        """The calibration vehicle with this station id, or None for any other station."""
        for vehicle in self.vehicles:
            if vehicle.station_id == station_id:
                return vehicle
        return None
