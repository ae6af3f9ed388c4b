"""File formats that are not bus messages: the simulator's ground truth (ground_truth.json)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from schemas.common import (
    EPSG_PATTERN,
    CameraIntrinsics,
    Finite,
    Identifier,
    Matrix3,
    StampNs,
    StrictModel,
    Vec3,
)


class GroundTruthFrame(StrictModel):
    """One camera frame: which of its boxes (index into DetectionFrame.boxes) is the calibration vehicle.

    `footprint_local` (set with `calib_box`) is the vehicle's true footprint at the frame's stamp: corners
    rear-right, front-right, front-left, rear-left in the local frame (UTM minus `GroundTruth.origin`), m.
    """

    stamp_ns: StampNs
    calib_box: int | None = Field(default=None, ge=0)
    traversal: int | None = Field(
        default=None, ge=0, description="traversal index of the vehicle, if in view"
    )
    footprint_local: tuple[Vec3, Vec3, Vec3, Vec3] | None = Field(
        default=None, description="true footprint RR, FR, FL, RL at stamp_ns, local frame, m"
    )
    box: tuple[Finite, Finite, Finite, Finite] | None = Field(
        default=None, description="x1, y1, x2, y2 (px) of the calib box as published (with detector jitter)"
    )
    exposure_ns: StampNs | None = Field(
        default=None, description="when the image was exposed (stamp_ns minus the camera's latency)"
    )
    visible_box: tuple[Finite, Finite, Finite, Finite] | None = Field(
        default=None,
        description="x1, y1, x2, y2 (px): true box of the visible outline, before detector errors",
    )
    cuboid_box: tuple[Finite, Finite, Finite, Finite] | None = Field(
        default=None,
        description="x1, y1, x2, y2 (px): rectangle of the data-sheet cuboid at exposure (unclipped)",
    )
    gross_error: Literal["merged", "split"] | None = Field(
        default=None, description="the calib box is merged with another vehicle's, or one of two pieces"
    )


class CameraMove(StrictModel):
    """The camera's true extrinsic from `from_exposure_ns` on (it was knocked between drive-pasts)."""

    from_exposure_ns: StampNs
    R: Matrix3
    t_utm: Vec3
    t_local: Vec3
    camera_position_utm: Vec3


class GroundTruth(StrictModel):
    """True extrinsic of one simulated camera, in the poses' frame (absolute UTM) and in the local frame.

    X_cam = R @ X_utm + t_utm = R @ (X_utm - origin) + t_local.
    """

    camera_id: Identifier
    crs: str = Field(pattern=EPSG_PATTERN)
    origin: Vec3
    R: Matrix3
    t_utm: Vec3
    t_local: Vec3
    camera_position_utm: Vec3
    intrinsics: CameraIntrinsics
    station_id: int = Field(ge=0, le=4_294_967_295)
    clock_offset_ns: int = Field(default=0, description="vehicle clock minus camera clock")
    traversals: int = Field(ge=0, description="traversals in which the vehicle was detected by this camera")
    latency_ns: int = Field(
        default=0,
        description="detection stamp minus exposure time (unknown to rsucal; negative: a camera clock that "
        "lags the vehicle's by more than the latency)",
    )
    readout_ns: int = Field(
        default=0,
        ge=0,
        description="rolling shutter: last image row's exposure minus the first's (the stamp's), 0: global",
    )
    world: Literal["real", "ideal"] = Field(default="ideal", description="the simulated world's kind")
    v2x: Literal["cam", "imu"] = Field(default="imu", description="CAM broadcasts or the IMU poses as V2X")
    vehicle_type: str | None = Field(default=None, description="the calibration vehicle's body type")
    vehicle_proportions: dict[str, float] = Field(
        default_factory=dict, description="the calibration vehicle's drawn body proportions (m)"
    )
    moves: list[CameraMove] = Field(default_factory=list, description="later extrinsics, in time order")
    frames: list[GroundTruthFrame] = Field(default_factory=list)
