"""File formats that are not bus messages: the simulator's ground truth (ground_truth.json)."""

from __future__ import annotations

from pydantic import Field

from schemas.common import CameraIntrinsics, Identifier, Matrix3, StampNs, StrictModel, Vec3


class GroundTruthFrame(StrictModel):
    """One camera frame: which of its boxes (index into DetectionFrame.boxes) is the calibration vehicle."""

    stamp_ns: StampNs
    calib_box: int | None = Field(default=None, ge=0)
    traversal: int | None = Field(default=None, ge=0, description="traversal index of the vehicle, if in view")


class GroundTruth(StrictModel):
    """True extrinsic of one simulated camera, in the poses' frame (absolute UTM) and in the local frame.

    X_cam = R @ X_utm + t_utm = R @ (X_utm - origin) + t_local.
    """

    camera_id: Identifier
    crs: str = Field(pattern=r"^EPSG:\d{4,5}$")
    origin: Vec3
    R: Matrix3
    t_utm: Vec3
    t_local: Vec3
    camera_position_utm: Vec3
    intrinsics: CameraIntrinsics
    station_id: int = Field(ge=0, le=4_294_967_295)
    clock_offset_ns: int = Field(default=0, description="vehicle clock minus camera clock")
    traversals: int = Field(ge=0, description="traversals in which the vehicle was detected by this camera")
    frames: list[GroundTruthFrame] = Field(default_factory=list)
