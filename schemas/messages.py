"""Bus messages (DESIGN.md, bus table): camera detections and V2X positions, plus the decoded vehicle pose."""

from __future__ import annotations

from pydantic import Field

from schemas.common import Box, Finite, Identifier, StampNs, StrictModel

MAX_BOXES_PER_FRAME = 2000


class DetectionFrame(StrictModel):
    """All boxes of one camera image, stamped by the camera at exposure time."""

    camera_id: Identifier
    stamp_ns: StampNs
    boxes: list[Box] = Field(default_factory=list, max_length=MAX_BOXES_PER_FRAME)


class V2xAccuracies(StrictModel):
    """Optional 1-sigma accuracies a station reports with its position."""

    horizontal_m: float | None = Field(default=None, ge=0.0, le=1000.0, allow_inf_nan=False)
    vertical_m: float | None = Field(default=None, ge=0.0, le=1000.0, allow_inf_nan=False)
    heading_deg: float | None = Field(default=None, ge=0.0, le=360.0, allow_inf_nan=False)
    speed_mps: float | None = Field(default=None, ge=0.0, le=100.0, allow_inf_nan=False)


class V2xPosition(StrictModel):
    """ETSI CAM-style position broadcast: WGS84 degrees, heading from TRUE north clockwise (degrees)."""

    station_id: int = Field(ge=0, le=4_294_967_295)
    stamp_ns: StampNs
    lat: float = Field(ge=-90.0, le=90.0, allow_inf_nan=False, description="WGS84 latitude, deg")
    lon: float = Field(ge=-180.0, le=180.0, allow_inf_nan=False, description="WGS84 longitude, deg")
    alt: float = Field(ge=-1000.0, le=10000.0, allow_inf_nan=False, description="ellipsoidal height, m")
    heading_deg: float = Field(ge=0.0, lt=360.0, allow_inf_nan=False, description="from true north, cw")
    speed: float = Field(ge=0.0, le=100.0, allow_inf_nan=False, description="m/s")
    length: float | None = Field(default=None, gt=0.0, le=30.0, allow_inf_nan=False, description="m")
    width: float | None = Field(default=None, gt=0.0, le=5.0, allow_inf_nan=False, description="m")
    roll: float | None = Field(default=None, ge=-1.6, le=1.6, allow_inf_nan=False, description="rad")
    pitch: float | None = Field(default=None, ge=-1.6, le=1.6, allow_inf_nan=False, description="rad")
    accuracies: V2xAccuracies | None = None


class VehiclePose(StrictModel):
    """Pose of the vehicle reference point in UTM (m); yaw from grid east, ccw (rad);
    orientation R = Rz(yaw) Ry(pitch) Rx(roll)."""

    stamp_ns: StampNs
    x: Finite
    y: Finite
    z: Finite
    yaw: Finite
    pitch: Finite = 0.0
    roll: Finite = 0.0
