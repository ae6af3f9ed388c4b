"""The CalibrationResult calibrate() returns: accepted or refused, with the pose, its uncertainty, the quality
metrics, the verdict and the provenance. `created_at_ns` always comes from the caller (the pipeline reads no
clock)."""

from __future__ import annotations

import hashlib
import importlib.metadata
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.camera import quaternion_wxyz_from_rotation
from pipeline.frames import UtmFrame
from pipeline.ground import GroundPlaneFit
from pipeline.metrics import DeltaPSummary
from pipeline.tables import DetectionTable
from schemas.common import LOCAL_CRS, LocalOrigin
from schemas.results import (
    SCHEMA_VERSION,
    CalibrationResult,
    CameraPosition,
    GroundPlane,
    Provenance,
    Quality,
    ReferenceFrame,
    Uncertainty,
    Verdict,
)

if TYPE_CHECKING:  # calibrate imports this module
    from pipeline.calibrate import CalibrationInputs, PipelineParams
    from pipeline.final_fit import FinalFit

try:
    SOFTWARE_VERSION = importlib.metadata.version("rsucal")
except importlib.metadata.PackageNotFoundError:  # running from a source tree that is not installed
    SOFTWARE_VERSION = "unknown"


def refused_result(
    inputs: CalibrationInputs,
    params: PipelineParams,
    origin: LocalOrigin | None,
    created_at_ns: int,
    reasons: list[str],
) -> CalibrationResult:
    return _result(inputs, params, origin, created_at_ns, Verdict(status="refused", reasons=reasons))


def calibration_result(
    inputs: CalibrationInputs,
    params: PipelineParams,
    origin: LocalOrigin,
    created_at_ns: int,
    summary: DeltaPSummary,
    final: FinalFit,
    ground: GroundPlaneFit,
    verdict: Verdict,
) -> CalibrationResult:
    """The result of a final fit; `summary`: the chosen candidate's paper IV-B metrics (Quality)."""
    refined = final.fit
    R = refined.R_cam_from_local
    t = refined.t_cam_from_local
    centre_local = refined.camera_centre
    centre_utm = centre_local + np.array([origin.x, origin.y, origin.z])
    lat = lon = alt = None
    if inputs.crs != LOCAL_CRS:  # a local metric frame has no geographic position
        lats, lons = UtmFrame(inputs.crs).to_wgs84(np.array([centre_utm[0]]), np.array([centre_utm[1]]))
        lat, lon, alt = float(lats[0]), float(lons[0]), float(centre_utm[2])
    quality = Quality(
        delta_p_mean_m=_finite(summary.delta_p_mean_m),
        delta_p_max_m=_finite(summary.delta_p_max_m),
        e_mean_pct=_finite(summary.e_mean_pct),
        e_max_pct=_finite(summary.e_max_pct),
        reprojection_rmse_px=_finite(refined.box_rmse_px),
        correspondences=int(refined.used_residuals),
        tracks=len(final.tracks),
        traversals=final.traversals,
    )
    covariance = np.asarray(final.covariance, dtype=np.float64)
    finite_cov = np.all(np.isfinite(covariance))
    uncertainty = (
        Uncertainty(
            covariance=tuple(tuple(float(v) for v in row) for row in covariance),
            position_std_m=_finite(final.position_std_m),
            rotation_std_deg=_finite(final.rotation_std_deg),
        )
        if finite_cov
        else None
    )
    return _result(
        inputs,
        params,
        origin,
        created_at_ns,
        verdict,
        R=tuple(tuple(float(v) for v in row) for row in R),
        t=(float(t[0]), float(t[1]), float(t[2])),
        camera_position=CameraPosition(
            utm=(float(centre_utm[0]), float(centre_utm[1]), float(centre_utm[2])),
            lat=lat,
            lon=lon,
            alt=alt,
        ),
        orientation_wxyz=tuple(float(v) for v in quaternion_wxyz_from_rotation(R.T)),
        ground_plane=GroundPlane(
            normal=(float(ground.normal[0]), float(ground.normal[1]), float(ground.normal[2])),
            offset=float(ground.offset),
        ),
        uncertainty=uncertainty,
        quality=quality,
        time_offset_ns=final.time_offset_ns(inputs.time_offset_ns),
        time_offset_std_ns=_finite(final.time_offset_std_s * 1e9),
    )


def _result(
    inputs: CalibrationInputs,
    params: PipelineParams,
    origin: LocalOrigin | None,
    created_at_ns: int,
    verdict: Verdict,
    **pose: Any,
) -> CalibrationResult:
    """What every result carries (who, when, the frame, the intrinsics, the verdict, the provenance), plus
    `pose`: the fields of an accepted or gated pose (R, t, position, uncertainty, quality, ...)."""
    return CalibrationResult(
        schema_version=SCHEMA_VERSION,
        rsu_id=inputs.rsu_id,
        camera_id=inputs.camera_id,
        result_id=result_id(inputs, created_at_ns),
        created_at_ns=created_at_ns,
        frame=ReferenceFrame(
            crs=inputs.crs, origin=(origin.x, origin.y, origin.z) if origin else (0.0, 0.0, 0.0)
        ),
        intrinsics=inputs.intrinsics,
        verdict=verdict,
        provenance=provenance(inputs, params),
        **pose,
    )


def _finite(value: float | None) -> float:
    """Schema fields are finite: a metric that could not be computed is reported as a huge value, and the
    gates have already refused such a result."""
    return float(value) if value is not None and np.isfinite(value) else 1e9


def provenance(inputs: CalibrationInputs, params: PipelineParams) -> Provenance:
    detections = inputs.detections
    if isinstance(detections, DetectionTable):
        stamps: list[int] = detections.stamps.tolist()
    else:
        stamps = [f.stamp_ns for f in detections]
    return Provenance(
        window_start_ns=min(stamps) if stamps else None,
        window_end_ns=max(stamps) if stamps else None,
        recordings=list(inputs.recordings),
        station_id=inputs.station_id,
        software_version=SOFTWARE_VERSION,
        # Every parameter of every stage (frozen dataclasses: repr is complete and stable).
        config_hash=hashlib.sha256(repr(params).encode()).hexdigest()[:16],
    )


def result_id(inputs: CalibrationInputs, created_at_ns: int) -> str:
    digest = hashlib.sha256(f"{inputs.rsu_id}/{inputs.camera_id}/{created_at_ns}".encode()).hexdigest()[:12]
    return f"{inputs.rsu_id}-{inputs.camera_id}-{created_at_ns}-{digest}"
