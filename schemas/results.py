"""What rsucal publishes and persists: the calibration result and the per-camera status (docs/design.md)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from schemas.common import (
    CRS_PATTERN,
    CameraIntrinsics,
    Finite,
    Identifier,
    Matrix3,
    StampNs,
    StrictModel,
    Vec3,
)

SCHEMA_VERSION = "1.0"

Covariance6 = tuple[
    tuple[Finite, Finite, Finite, Finite, Finite, Finite],
    tuple[Finite, Finite, Finite, Finite, Finite, Finite],
    tuple[Finite, Finite, Finite, Finite, Finite, Finite],
    tuple[Finite, Finite, Finite, Finite, Finite, Finite],
    tuple[Finite, Finite, Finite, Finite, Finite, Finite],
    tuple[Finite, Finite, Finite, Finite, Finite, Finite],
]


class ReferenceFrame(StrictModel):
    """The frame R, t refer to: the world frame (crs: a UTM zone, or 'local' for the poses' own metric
    frame) minus `origin` (m)."""

    crs: str = Field(pattern=CRS_PATTERN)
    origin: Vec3


class CameraPosition(StrictModel):
    """Camera centre in absolute world coordinates (m: UTM, or the local frame's own for crs 'local') and
    WGS84 (deg, ellipsoidal height m; None in a local frame, which has no geographic position)."""

    utm: Vec3
    lat: float | None = Field(default=None, ge=-90.0, le=90.0, allow_inf_nan=False)
    lon: float | None = Field(default=None, ge=-180.0, le=180.0, allow_inf_nan=False)
    alt: Finite | None = None


class GroundPlane(StrictModel):
    """Ground plane in the local frame: points p with normal . p = offset (normal unit, pointing up)."""

    normal: Vec3
    offset: Finite


class Uncertainty(StrictModel):
    """6x6 covariance of [rotation vector (rad, local frame), camera position (m, local frame)]."""

    covariance: Covariance6
    position_std_m: float = Field(ge=0.0, allow_inf_nan=False)
    rotation_std_deg: float = Field(ge=0.0, allow_inf_nan=False)


class Quality(StrictModel):
    """Paper Sec. IV-B metrics on the merged calibration-vehicle tracks, plus fit statistics."""

    delta_p_mean_m: float = Field(ge=0.0, allow_inf_nan=False)
    delta_p_max_m: float = Field(ge=0.0, allow_inf_nan=False)
    e_mean_pct: float = Field(ge=0.0, allow_inf_nan=False)
    e_max_pct: float = Field(ge=0.0, allow_inf_nan=False)
    reprojection_rmse_px: float = Field(ge=0.0, allow_inf_nan=False)
    correspondences: int = Field(ge=0)
    tracks: int = Field(ge=0)
    traversals: int = Field(ge=0)


class Verdict(StrictModel):
    """Accepted or refused, always with the reasons (a refusal is an answer, not an exception)."""

    status: Literal["accepted", "refused"]
    reasons: list[str] = Field(default_factory=list)

    @property
    def is_accepted(self) -> bool:
        return self.status == "accepted"


class ChangeInfo(StrictModel):
    """How this result differs from the previously published one, and the numbers the move decision used:
    moved when shift_m > max(min_shift_m, sigmas * shift_std_m) or shift_deg > max(min_shift_deg, sigmas *
    shift_std_deg) (docs/design.md, "Re-verification")."""

    previous_result_id: str
    shift_m: float = Field(ge=0.0, allow_inf_nan=False, description="distance of the camera centres, m")
    shift_deg: float = Field(ge=0.0, allow_inf_nan=False, description="angle of the relative rotation, deg")
    moved: bool
    shift_std_m: float | None = Field(
        default=None,
        ge=0.0,
        allow_inf_nan=False,
        description="std of the centre difference along the shift (both results' covariances), m",
    )
    shift_std_deg: float | None = Field(
        default=None,
        ge=0.0,
        allow_inf_nan=False,
        description="std of the rotation difference about its axis (both results' covariances), deg",
    )
    sigmas: float | None = Field(default=None, ge=0.0, allow_inf_nan=False, description="k (change.sigmas)")
    min_shift_m: float | None = Field(default=None, ge=0.0, allow_inf_nan=False, description="change.shift_m")
    min_shift_deg: float | None = Field(
        default=None, ge=0.0, allow_inf_nan=False, description="change.shift_deg"
    )


class Provenance(StrictModel):
    """Where a result came from."""

    window_start_ns: StampNs | None = None
    window_end_ns: StampNs | None = None
    recordings: list[str] = Field(default_factory=list)
    station_id: int | None = Field(default=None, ge=0, le=4_294_967_295)
    software_version: str = ""
    config_hash: str = ""


class CalibrationResult(StrictModel):
    """One camera's geo-referenced extrinsic: X_cam = R @ (X_utm - origin) + t (docs/design.md)."""

    schema_version: str = SCHEMA_VERSION
    rsu_id: Identifier
    camera_id: Identifier
    result_id: str = Field(min_length=1, max_length=128)
    created_at_ns: StampNs
    frame: ReferenceFrame
    R: Matrix3 | None = Field(default=None, description="world(local)->camera rotation")
    t: Vec3 | None = Field(default=None, description="world(local)->camera translation, m")
    camera_position: CameraPosition | None = None
    orientation_wxyz: tuple[Finite, Finite, Finite, Finite] | None = Field(
        default=None, description="camera->world rotation as a unit quaternion [w, x, y, z]"
    )
    intrinsics: CameraIntrinsics
    ground_plane: GroundPlane | None = None
    uncertainty: Uncertainty | None = None
    quality: Quality | None = None
    verdict: Verdict
    change: ChangeInfo | None = None
    provenance: Provenance = Field(default_factory=Provenance)
    time_offset_ns: int | None = Field(
        default=None,
        description=(
            "estimated vehicle (V2X) clock minus camera stamp of the frame showing the same instant, ns: the "
            "clock offset plus the detector's latency (a rolling shutter's: of the image's middle row); what "
            "the pipeline subtracts from pose stamps"
        ),
    )
    time_offset_std_ns: float | None = Field(default=None, ge=0.0, allow_inf_nan=False)

    @model_validator(mode="after")
    def _accepted_has_pose(self) -> CalibrationResult:
        if self.verdict.status == "accepted" and (self.R is None or self.t is None):
            raise ValueError("an accepted result needs R and t")
        return self


class JobSummary(StrictModel):
    """The last calibration job of a camera."""

    job_id: str
    # Published field names (wire contract, kept): a job's started_ns / finished_ns pair, where Health says
    # started_at_ns / updated_at_ns; the daemon's variables follow the schema they fill.
    started_ns: StampNs
    finished_ns: StampNs | None = None
    duration_s: float | None = Field(default=None, ge=0.0, allow_inf_nan=False)
    verdict: Verdict | None = None
    report: str | None = Field(
        default=None, max_length=4096, description="the job's HTML report on the RSU (history/*.html)"
    )


class CalibrationStatus(StrictModel):
    """What `.../calibration/status` answers for one camera."""

    rsu_id: Identifier
    camera_id: Identifier
    state: Literal["idle", "collecting", "calibrating", "calibrated", "refused"]
    traversals: int = Field(ge=0)
    traversals_needed: int = Field(ge=2)
    last_job: JobSummary | None = None
    current_result_id: str | None = None
    verified_at_ns: StampNs | None = None
    time_offset_ns: int | None = Field(
        default=None, description="the camera's last estimated time offset (CalibrationResult.time_offset_ns)"
    )
    time_offset_std_ns: float | None = Field(default=None, ge=0.0, allow_inf_nan=False)
    counters: dict[str, int] = Field(default_factory=dict)
    updated_at_ns: StampNs


class DiskUsage(StrictModel):
    """Storage of one RSU: free space where the state lives, and what the recordings take."""

    state_dir: str
    free_bytes: int = Field(ge=0)
    recordings_bytes: int = Field(ge=0)
    recordings_files: int = Field(ge=0)


class Health(StrictModel):
    """What `rsu/{rsu}/health` answers: liveness details, counters, disk and versions."""

    rsu_id: Identifier
    started_at_ns: StampNs  # published (kept): the job summary's start is started_ns (JobSummary)
    updated_at_ns: StampNs
    uptime_s: float = Field(ge=0.0, allow_inf_nan=False)
    cameras: list[str] = Field(default_factory=list)
    counters: dict[str, int] = Field(default_factory=dict)
    inbox_depth: int = Field(default=0, ge=0)
    jobs_running: int = Field(default=0, ge=0)
    disk: DiskUsage | None = None
    versions: dict[str, str] = Field(default_factory=dict)
