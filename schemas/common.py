"""Building blocks shared by messages, files and results: strict base model, boxes, intrinsics, vehicle.

Every model forbids unknown fields, rejects NaN/inf and validates strictly (no "12" for 12), so a
decoder error always names the offending field (pydantic's `loc`).
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from typing import Annotated, Any, TypeVar

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PlainValidator,
    ValidationError,
    field_validator,
    model_validator,
)

# 2000..2200 in ns: rejects seconds, milliseconds or microseconds passed where nanoseconds belong (a stamp
# in seconds read as ns falls in January 1970) and negative or overflowed stamps.
STAMP_NS_MIN = 946_684_800_000_000_000
STAMP_NS_MAX = 7_258_118_400_000_000_000

StampNs = Annotated[int, Field(ge=STAMP_NS_MIN, le=STAMP_NS_MAX, description="ns since the Unix epoch")]
Finite = Annotated[float, Field(allow_inf_nan=False)]
GnssStd = Annotated[float, Field(ge=0.0, le=10.0, allow_inf_nan=False, description="m")]
# Boxes may reach past the image border, but never by more than any image is wide.
PixelCoord = Annotated[float, Field(ge=-1e5, le=1e5, allow_inf_nan=False, description="px")]
# The one identifier pattern (rsu, camera ids): safe in a Zenoh key and a file name. IDENTIFIER checks a
# string outside a model; UNSAFE_IN_IDENTIFIER finds the characters to replace when making one.
IDENTIFIER_CHARS = r"A-Za-z0-9_.\-"
IDENTIFIER_MAX_LENGTH = 64
IDENTIFIER = re.compile(rf"^[{IDENTIFIER_CHARS}]{{1,{IDENTIFIER_MAX_LENGTH}}}$")
UNSAFE_IN_IDENTIFIER = re.compile(rf"[^{IDENTIFIER_CHARS}]")
Identifier = Annotated[
    str,
    Field(
        min_length=1,
        max_length=IDENTIFIER_MAX_LENGTH,
        pattern=rf"^[{IDENTIFIER_CHARS}]+$",
        description="safe in a Zenoh key",
    ),
]
Vec3 = tuple[Finite, Finite, Finite]
Matrix3 = tuple[Vec3, Vec3, Vec3]

# A detector's class: an integer id or a name ("car", "truck", "traffic light"). Names start with a letter,
# so the string "4" is neither (strict JSON: an id is a JSON number).
MAX_CLASS_ID = 1000
ClassId = Annotated[int, Field(ge=0, le=MAX_CLASS_ID, description="detector class id")]
ClassName = Annotated[
    str,
    Field(min_length=1, max_length=32, pattern=r"^[A-Za-z][A-Za-z0-9_ \-]*$", description="class name"),
]
# Integer ids of the reference toolbox (docs/design.md: boxes), the ids the pipeline works with.
TOOLBOX_CLASS_IDS: Mapping[str, int] = {"car": 4, "truck": 5, "van": 6, "bus": 7}
OTHER_CLASS_ID = -1  # a class name the toolbox has no id for (e.g. "motorcycle")


_CLASS_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_ \-]{0,31}")


def _class_label(value: Any) -> int | str:
    # One validator rather than a union, so an error names `cls` itself and says what would be right.
    # JSON true is not 1: only real integers are ids (strict, like every other field).
    if isinstance(value, int) and not isinstance(value, bool):
        if not 0 <= value <= MAX_CLASS_ID:
            raise ValueError(f"class id {value} is outside [0, {MAX_CLASS_ID}]")
        return value
    if isinstance(value, str):
        if _CLASS_NAME.fullmatch(value) is None:
            raise ValueError(
                f"class name {value[:40]!r} must be 1-32 letters, digits, spaces, '_' or '-', "
                "starting with a letter"
            )
        return value
    raise ValueError(f"expected an integer class id or a class name like 'car', got {type(value).__name__}")


ClassLabel = Annotated[int | str, PlainValidator(_class_label, json_schema_input_type=ClassId | ClassName)]


def class_name(label: int | str, labels: Mapping[int, str] | None = None) -> int | str:
    """A box's class as a name where one is known: ids through a camera's label map (`labels`, the
    detector's id -> name), names as given (lower case); ids without a map stay ids (toolbox ids)."""
    if isinstance(label, str):
        return label.lower()
    if labels is not None and label in labels:
        return labels[label].lower()
    return label


def toolbox_class_id(label: int | str) -> int:
    """The toolbox id of a class: ids as they are, names through TOOLBOX_CLASS_IDS (case-insensitive),
    OTHER_CLASS_ID (-1) for a name the toolbox has no id for."""
    if isinstance(label, str):
        return TOOLBOX_CLASS_IDS.get(label.lower(), OTHER_CLASS_ID)
    return label


class StrictModel(BaseModel):
    """Base of every rsucal model: frozen, no unknown fields, no NaN/inf; decode with `decode_json`."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Box(StrictModel):
    """One detected box in pixels (x right, y down) with the detector's class (id or name) and score."""

    x1: PixelCoord
    y1: PixelCoord
    x2: PixelCoord
    y2: PixelCoord
    cls: ClassLabel = Field(
        default=4,
        description="class id (toolbox ids 4 car, 5 truck, 6 van, 7 bus, unless the camera has a label map) "
        "or name ('car')",
    )
    score: float = Field(default=1.0, ge=0.0, le=1.0, allow_inf_nan=False)

    @model_validator(mode="after")
    def _ordered(self) -> Box:
        if not self.x2 > self.x1:
            raise ValueError(f"x2 = {self.x2} must be greater than x1 = {self.x1}")
        if not self.y2 > self.y1:
            raise ValueError(f"y2 = {self.y2} must be greater than y1 = {self.y1}")
        return self


# OpenCV's pinhole distortion vectors the pipeline models: [k1, k2, p1, p2], + k3 (OpenCV's default, ROS's
# plumb_bob), + k4, k5, k6 (the rational model, CALIB_RATIONAL_MODEL; ROS's rational_polynomial).
DIST_LENGTHS = (4, 5, 8)


class CameraIntrinsics(StrictModel):
    """Pinhole + OpenCV distortion; YAML keys exactly width, height, fx, fy, cx, cy, dist."""

    width: int = Field(gt=0, le=20000, description="image width, px")
    height: int = Field(gt=0, le=20000, description="image height, px")
    fx: float = Field(gt=0.0, le=1e6, allow_inf_nan=False, description="focal length x, px")
    fy: float = Field(gt=0.0, le=1e6, allow_inf_nan=False, description="focal length y, px")
    cx: float = Field(ge=-1e5, le=1e5, allow_inf_nan=False, description="principal point x, px")
    cy: float = Field(ge=-1e5, le=1e5, allow_inf_nan=False, description="principal point y, px")
    dist: tuple[Finite, ...] = Field(
        default=(0.0, 0.0, 0.0, 0.0, 0.0),
        description="OpenCV distortion: [k1, k2, p1, p2], [k1, k2, p1, p2, k3] or the rational model's "
        "[k1, k2, p1, p2, k3, k4, k5, k6]",
        json_schema_extra={"minItems": 4, "maxItems": 8},  # and not 6 or 7 (checked below)
    )

    @field_validator("dist")
    @classmethod
    def _dist_length(cls, dist: tuple[float, ...]) -> tuple[float, ...]:
        if len(dist) not in DIST_LENGTHS:
            raise ValueError(
                f"{len(dist)} coefficients; OpenCV's pinhole model takes 4 [k1, k2, p1, p2], 5 (+ k3) or 8 "
                "(+ k3, k4, k5, k6: the rational model); the thin-prism and tilted models (12, 14) are not "
                "supported"
            )
        return dist


class VehicleProfile(StrictModel):
    """Calibration vehicle body: box [0, L] x [0, W] x [0, H] in the vehicle box frame (x fwd, y left, z up,
    origin rear-right-bottom); `imu_offset` is the pose reference point in that frame (m)."""

    length: float = Field(gt=0.0, le=30.0, allow_inf_nan=False, description="m")
    width: float = Field(gt=0.0, le=5.0, allow_inf_nan=False, description="m")
    height: float = Field(gt=0.0, le=6.0, allow_inf_nan=False, description="m")
    imu_offset: Vec3 = Field(description="pose reference point [x, y, z] in the vehicle box frame, m")
    # How far the vehicle's reported positions wander between drive-pasts minutes apart (1 sigma; across,
    # in height): RTK fixed a few centimetres, twice that in height; 0 for a track known to hold (e.g. post-
    # processed). The final fit carries it into the pose's uncertainty (vehicle_model.drive_past_gnss_moves).
    gnss_wander_m: tuple[GnssStd, GnssStd] = Field(
        default=(0.03, 0.06),
        description="GNSS wander between drive-pasts, 1 sigma [horizontal, height], m",
    )


# A world frame is a UTM zone named by its EPSG code, or LOCAL_CRS: the poses' own local metric frame
# (`rsucal calibrate --frame local`), which has no geographic position.
LOCAL_CRS = "local"
EPSG_PATTERN = r"^EPSG:\d{4,5}$"  # a UTM zone's EPSG code: the one pattern (config, files, results, CLI)
CRS_PATTERN = rf"^(EPSG:\d{{4,5}}|{LOCAL_CRS})$"


class LocalOrigin(StrictModel):
    """The world point subtracted inside the pipeline for numerical stability (docs/design.md: frames)."""

    crs: str = Field(pattern=CRS_PATTERN, description="e.g. EPSG:32632, or 'local'")
    x: Finite
    y: Finite
    z: Finite = 0.0


M = TypeVar("M", bound=BaseModel)


def decode_json(model: type[M], raw: bytes | str) -> M:
    """Validate a JSON payload strictly (no "12" for 12, no true for 1); raises pydantic.ValidationError."""
    return model.model_validate_json(raw, strict=True)


def decode_mapping(model: type[M], data: Any) -> M:
    """Validate already-parsed data (e.g. YAML) with the same strict JSON rules as `decode_json`.

    Going through JSON keeps one set of rules for bus and files: lists are accepted for fixed-length
    arrays, but strings and booleans never pass for numbers.
    """
    try:
        raw = json.dumps(data, allow_nan=True)
    except (TypeError, ValueError) as err:
        raise ValueError(f"not JSON-representable data: {err}") from err
    return decode_json(model, raw)


def _path_part(part: str | int) -> str:
    """A key as written, unless it would vanish, break the line or read as a path or another field: repr()."""
    text = str(part)
    plain = bool(text) and text.isprintable() and text.strip() == text and not any(c in text for c in ".:;")
    return text if plain else repr(text)


def describe_validation_error(err: ValidationError) -> str:
    """One line per problem, each starting with the dotted field path: 'boxes.0.x1: ...'."""
    lines = []
    for item in err.errors(include_url=False):
        where = ".".join(_path_part(part) for part in item["loc"]) or "(root)"
        lines.append(f"{where}: {item['msg']}")
    return "; ".join(lines)
