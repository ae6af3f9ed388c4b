"""Bus messages (docs/design.md, bus keys): camera detections and V2X positions, and the decoded pose."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Annotated, NotRequired

from pydantic import ConfigDict, Field, TypeAdapter
from typing_extensions import TypedDict

from schemas.common import (
    Box,
    ClassId,
    ClassName,
    Finite,
    Identifier,
    PixelCoord,
    StampNs,
    StrictModel,
    class_name,
)

MAX_BOXES_PER_FRAME = 2000


class DetectionFrame(StrictModel):
    """All boxes of one camera image, stamped by the camera at exposure time."""

    camera_id: Identifier
    stamp_ns: StampNs
    boxes: list[Box] = Field(default_factory=list, max_length=MAX_BOXES_PER_FRAME)


# The bus path (daemon ingest, ~20,000 messages/s on one core) only needs to know that a DetectionFrame is
# valid, plus its camera_id and stamp_ns; building 30 frozen Box models per frame is most of its cost. These
# mirror DetectionFrame and Box field for field (tests/schemas/test_models.py checks that both accept exactly
# the same payloads); only Box's x1 < x2, y1 < y2 check is done in check_detection_frame below. `cls` is a
# plain union here (validated in Rust), the model's tagged one only improves its error messages.
class _BoxFields(TypedDict):
    __pydantic_config__ = ConfigDict(extra="forbid", allow_inf_nan=False)  # type: ignore[misc]
    x1: PixelCoord
    y1: PixelCoord
    x2: PixelCoord
    y2: PixelCoord
    cls: NotRequired[ClassId | ClassName]
    score: NotRequired[Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)]]


class _DetectionFrameFields(TypedDict):
    __pydantic_config__ = ConfigDict(extra="forbid", allow_inf_nan=False)  # type: ignore[misc]
    camera_id: Identifier
    stamp_ns: StampNs
    boxes: NotRequired[Annotated[list[_BoxFields], Field(max_length=MAX_BOXES_PER_FRAME)]]


_DETECTION_FRAME_FIELDS = TypeAdapter(_DetectionFrameFields)


def check_detection_frame(raw: bytes | str) -> tuple[str, int, int]:
    """Validate a DetectionFrame JSON payload exactly as `decode_json(DetectionFrame, raw)` does, without
    building it (about 1.4x faster); returns (camera_id, stamp_ns, number of boxes).

    Raises the same pydantic.ValidationError as DetectionFrame would: on any failure the payload is validated
    again by the model itself, so the error (and its field names) is always the model's.
    """
    camera_id, stamp_ns, boxes = check_detection_frame_boxes(raw)
    return camera_id, stamp_ns, len(boxes)


def check_detection_frame_boxes(raw: bytes | str) -> tuple[str, int, Sequence[Mapping[str, object]]]:
    """check_detection_frame, returning the validated boxes (x1, y1, x2, y2 px; cls, score when given) as
    read-only mappings instead of their number: what the recorder draws, at no extra parsing."""
    try:
        fields = _DETECTION_FRAME_FIELDS.validate_json(raw, strict=True)
        boxes = fields.get("boxes", [])
        if all(box["x2"] > box["x1"] and box["y2"] > box["y1"] for box in boxes):
            return fields["camera_id"], fields["stamp_ns"], boxes
    except ValueError:  # pydantic's ValidationError included; the model says what exactly is wrong
        pass
    frame = DetectionFrame.model_validate_json(raw, strict=True)
    # only reached if the two ever disagree
    return frame.camera_id, frame.stamp_ns, [box.model_dump() for box in frame.boxes]


def apply_labels(frames: Sequence[DetectionFrame], labels: Mapping[int, str] | None) -> list[DetectionFrame]:
    """Frames with every integer class the camera's label map names replaced by that name (lower case);
    other boxes and frames are returned as they are (the same objects)."""
    if not labels:
        return list(frames)
    named = []
    for frame in frames:
        if not any(isinstance(box.cls, int) and box.cls in labels for box in frame.boxes):
            named.append(frame)
            continue
        boxes = [
            box.model_copy(update={"cls": class_name(box.cls, labels)}) if isinstance(box.cls, int) else box
            for box in frame.boxes
        ]
        named.append(frame.model_copy(update={"boxes": boxes}))
    return named


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
