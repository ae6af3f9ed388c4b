"""Pydantic models of every message, file and result of rsucal (docs/design.md); imports nothing of ours."""

from schemas.common import Box, CameraIntrinsics, LocalOrigin, VehicleProfile
from schemas.config import DaemonConfig
from schemas.files import GroundTruth, GroundTruthFrame
from schemas.messages import DetectionFrame, V2xAccuracies, V2xPosition, VehiclePose
from schemas.results import (
    CalibrationResult,
    CalibrationStatus,
    CameraPosition,
    ChangeInfo,
    DiskUsage,
    GroundPlane,
    Health,
    JobSummary,
    Provenance,
    Quality,
    ReferenceFrame,
    Uncertainty,
    Verdict,
)

__all__ = [
    "Box",
    "CalibrationResult",
    "CalibrationStatus",
    "CameraIntrinsics",
    "CameraPosition",
    "ChangeInfo",
    "DaemonConfig",
    "DetectionFrame",
    "DiskUsage",
    "GroundPlane",
    "GroundTruth",
    "GroundTruthFrame",
    "Health",
    "JobSummary",
    "LocalOrigin",
    "Provenance",
    "Quality",
    "ReferenceFrame",
    "Uncertainty",
    "V2xAccuracies",
    "V2xPosition",
    "VehiclePose",
    "VehicleProfile",
    "Verdict",
]
