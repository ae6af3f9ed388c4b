"""Foxglove views of rsucal's data: official foxglove.* protobuf schemas, encoded for recordings and the bus.

Beside the raw JSON channels, recordings carry what Foxglove shows natively: V2X as foxglove.LocationFix (a
map), detections as foxglove.ImageAnnotations (an image overlay), each accepted result as
foxglove.FrameTransform plus foxglove.CameraCalibration (the camera in a 3D scene). Schemas are the
FileDescriptorSets of the `foxglove-schemas-protobuf` package (Foxglove's own .proto definitions, 3 MB with
protobuf; the `foxglove-sdk` wheel is 54 MB of Rust for the same schemas).

The two per-message encoders on the ingest path (LocationFix, ImageAnnotations) write the protobuf wire
format with struct: building the same ImageAnnotations of 30 boxes with the protobuf classes costs ~320 us,
these ~10 us. Results are rare and use the official classes. tests/daemon/test_foxglove.py decodes every
message with the official classes. No mcap and no zenoh here: bytes in, bytes out.
"""

from __future__ import annotations

import functools
import math
import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from google.protobuf.descriptor import Descriptor, FileDescriptor
from google.protobuf.descriptor_pb2 import FileDescriptorSet

from schemas.messages import V2xPosition
from schemas.results import CalibrationResult

# Colours (r, g, b, a in [0, 1]): every detector box, the calibration vehicle's boxes once known, and the
# map markers of other traffic and of calibration vehicles.
BOX_RGBA = (0.2, 0.6, 1.0, 1.0)
VEHICLE_BOX_RGBA = (1.0, 0.35, 0.1, 1.0)
OTHER_STATION_RGBA = (0.55, 0.55, 0.55, 1.0)
VEHICLE_STATION_RGBA = (1.0, 0.35, 0.1, 1.0)
BOX_THICKNESS_PX = 2.0
VEHICLE_BOX_THICKNESS_PX = 4.0
MAX_STAMP_NS = 2**63 - 1


@dataclass(frozen=True, slots=True)
class MessageSchema:
    """A channel's schema as MCAP stores it: name, schema encoding, schema data, and the message encoding."""

    name: str
    encoding: str
    data: bytes
    message_encoding: str


def _file_descriptor_set(descriptor: Descriptor) -> bytes:
    """The message's .proto file and everything it imports, as a serialised FileDescriptorSet."""
    files = FileDescriptorSet()
    seen: set[str] = set()

    def add(file: FileDescriptor) -> None:
        if file.name in seen:
            return
        seen.add(file.name)
        for dependency in file.dependencies:
            add(dependency)
        file.CopyToProto(files.file.add())

    add(descriptor.file)
    return bytes(files.SerializeToString())


@functools.cache
def protobuf_schema(name: str) -> MessageSchema:
    """foxglove.{name} (LocationFix, ImageAnnotations, FrameTransform, CameraCalibration, CompressedImage) as
    an MCAP schema."""
    classes: dict[str, Any] = {
        "CompressedImage": CompressedImage,
        "LocationFix": LocationFix,
        "ImageAnnotations": ImageAnnotations,
        "FrameTransform": FrameTransform,
        "CameraCalibration": CameraCalibration,
    }
    descriptor = classes[name].DESCRIPTOR
    return MessageSchema(descriptor.full_name, "protobuf", _file_descriptor_set(descriptor), "protobuf")


LOCATION_FIX = protobuf_schema("LocationFix")
IMAGE_ANNOTATIONS = protobuf_schema("ImageAnnotations")
FRAME_TRANSFORM = protobuf_schema("FrameTransform")
CAMERA_CALIBRATION = protobuf_schema("CameraCalibration")


# ------------------------------------------------------------------------------------------ topics, frames


def camera_frame_id(rsu_id: str, camera_id: str) -> str:
    """The camera's optical frame (OpenCV: x right, y down, z forward) in Foxglove's transform tree."""
    return f"rsu/{rsu_id}/camera/{camera_id}"


def local_frame_id(rsu_id: str, camera_id: str) -> str:
    """The result's local frame (UTM minus its origin), in which R and t are given."""
    return f"rsu/{rsu_id}/camera/{camera_id}/local"


def world_frame_id(crs: str) -> str:
    """The UTM frame (east, north, up; metres) named by its EPSG code, the root of the transform tree."""
    return crs


# ------------------------------------------------------------------------------------------ wire format
# Protobuf wire format (https://protobuf.dev/programming-guides/encoding/): a field is a varint key
# (number << 3 | wire type), then a varint, 8 little-endian bytes (double), or a varint length and bytes.

_VARINT, _I64, _LEN = 0, 1, 2
_DOUBLE = struct.Struct("<d")


def _varint(value: int) -> bytes:
    out = bytearray()
    while value > 0x7F:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _key(number: int, wire_type: int) -> bytes:
    return _varint(number << 3 | wire_type)


def _double(number: int, value: float) -> bytes:
    return _key(number, _I64) + _DOUBLE.pack(value) if value != 0.0 else b""  # proto3: 0 is not written


def _submessage(number: int, body: bytes) -> bytes:
    return _key(number, _LEN) + _varint(len(body)) + body


def _timestamp(number: int, stamp_ns: int) -> bytes:
    """google.protobuf.Timestamp {seconds = 1, nanos = 2} of a non-negative stamp (ns since the epoch)."""
    return _submessage(number, _timestamp_body(stamp_ns))


def _color(number: int, rgba: tuple[float, float, float, float]) -> bytes:
    r, g, b, a = rgba
    return _submessage(number, _double(1, r) + _double(2, g) + _double(3, b) + _double(4, a))


# ------------------------------------------------------------------------------------------ LocationFix

_COVARIANCE_APPROXIMATED = 1  # LocationFix.PositionCovarianceType
_COVARIANCE_DIAGONAL_KNOWN = 2
_NINE_DOUBLES = struct.Struct("<9d")


@functools.cache
def _location_tail(station_id: int, is_vehicle: bool) -> bytes:
    frame_id = f"v2x/{station_id}".encode()
    rgba = VEHICLE_STATION_RGBA if is_vehicle else OTHER_STATION_RGBA
    return _key(7, _LEN) + _varint(len(frame_id)) + frame_id + _color(8, rgba)


_LOCATION_HEAD = struct.Struct("<BdBdBd")  # latitude (1), longitude (2), altitude (3): always written


def location_fix(message: V2xPosition, is_vehicle: bool) -> bytes:
    """A V2X position as foxglove.LocationFix: WGS84 degrees, ellipsoidal altitude (m), colour by kind.

    The covariance (ENU, m^2) is diagonal from the station's reported 1-sigma accuracies when it gives them
    (horizontal for east and north, vertical for up, or horizontal when vertical is missing), else unknown.
    frame_id is v2x/{station_id}; calibration vehicles are orange, other traffic grey.
    """
    parts = [
        _LOCATION_HEAD.pack(0x09, message.lat, 0x11, message.lon, 0x19, message.alt),
    ]
    accuracies = message.accuracies
    if accuracies is not None and accuracies.horizontal_m is not None:
        horizontal = accuracies.horizontal_m**2
        vertical = (
            accuracies.vertical_m if accuracies.vertical_m is not None else accuracies.horizontal_m
        ) ** 2
        kind = _COVARIANCE_DIAGONAL_KNOWN if accuracies.vertical_m is not None else _COVARIANCE_APPROXIMATED
        covariance = _NINE_DOUBLES.pack(horizontal, 0.0, 0.0, 0.0, horizontal, 0.0, 0.0, 0.0, vertical)
        parts.append(b"\x22" + _varint(len(covariance)) + covariance)  # packed repeated double, field 4
        parts.append(_key(5, _VARINT) + _varint(kind))
    parts.append(_timestamp(6, message.stamp_ns))
    parts.append(_location_tail(message.station_id, is_vehicle))
    return b"".join(parts)


# ------------------------------------------------------------------------------------------ ImageAnnotations

_POINT_HEAD = b"\x1a\x12\x09"  # PointsAnnotation.points (3), length 18, Point2.x (1) double
_POINT_Y = b"\x11"  # Point2.y (2) double
_LINE_LOOP_TYPE = b"\x10\x02"  # PointsAnnotation.type (2) = LINE_LOOP
_POINTS_BYTES = 4 * 20  # 4 corners, each a points (3) entry of 2 + 18 bytes


@functools.lru_cache(maxsize=64)
def _seconds_field(seconds: int) -> bytes:
    """Timestamp.seconds (1) as key and varint; the same for every frame of one second."""
    return _key(1, _VARINT) + _varint(seconds) if seconds else b""


def _timestamp_body(stamp_ns: int) -> bytes:
    if not 0 <= stamp_ns <= MAX_STAMP_NS:
        raise ValueError(f"stamp_ns = {stamp_ns} is outside [0, 2^63)")
    seconds, nanos = divmod(stamp_ns, 1_000_000_000)
    return _seconds_field(seconds) + (b"\x10" + _varint(nanos) if nanos else b"")


@functools.cache
def _box_suffix(is_vehicle: bool) -> bytes:
    rgba, thickness = (
        (VEHICLE_BOX_RGBA, VEHICLE_BOX_THICKNESS_PX) if is_vehicle else (BOX_RGBA, BOX_THICKNESS_PX)
    )
    return _color(4, rgba) + _double(7, thickness)


@functools.cache
def _box_struct(prefix_bytes: int, suffix_bytes: int) -> struct.Struct:
    """One whole ImageAnnotations.points entry: prefix, a LINE_LOOP of 4 corners, suffix; one pack per box."""
    return struct.Struct(f"<{prefix_bytes}s" + "3sd1sd" * 4 + f"{suffix_bytes}s")


BoxCorners = tuple[float, float, float, float]


def image_annotations(
    stamp_ns: int, boxes: Iterable[Mapping[str, Any]], vehicle_boxes: Sequence[BoxCorners] = ()
) -> bytes:
    """One camera frame's boxes (mappings with x1, y1, x2, y2 in px) as foxglove.ImageAnnotations.

    Each box is a LINE_LOOP of its corners stamped `stamp_ns`; `vehicle_boxes` (x1, y1, x2, y2), the
    calibration vehicle's once known, are drawn thicker in another colour. On the ingest path: one
    struct.pack per box (~0.4 us), everything else once per frame.
    """
    stamp = _timestamp_body(stamp_ns)
    head = b"\x0a" + _varint(len(stamp)) + stamp + _LINE_LOOP_TYPE  # PointsAnnotation.timestamp (1), type
    h, y = _POINT_HEAD, _POINT_Y
    parts = []
    for is_vehicle, group in ((False, None), (True, vehicle_boxes)):
        if is_vehicle and not vehicle_boxes:
            break
        suffix = _box_suffix(is_vehicle)
        prefix = (
            b"\x12" + _varint(len(head) + _POINTS_BYTES + len(suffix)) + head
        )  # ImageAnnotations.points (2)
        pack = _box_struct(len(prefix), len(suffix)).pack
        if group is None:
            parts = [
                pack(
                    prefix,
                    h,
                    b["x1"],
                    y,
                    b["y1"],
                    h,
                    b["x2"],
                    y,
                    b["y1"],
                    h,
                    b["x2"],
                    y,
                    b["y2"],
                    h,
                    b["x1"],
                    y,
                    b["y2"],
                    suffix,
                )
                for b in boxes
            ]
        else:
            parts.extend(
                pack(prefix, h, x1, y, y1, h, x2, y, y1, h, x2, y, y2, h, x1, y, y2, suffix)
                for x1, y1, x2, y2 in group
            )
    parts.append(b"\x2a" + _varint(len(stamp)) + stamp)  # ImageAnnotations.timestamp (5)
    return b"".join(parts)


# ------------------------------------------------------------------------------------------ results


def _rotation_matrix_to_quaternion(R: Sequence[Sequence[float]]) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method: stable for every rotation)."""
    trace = R[0][0] + R[1][1] + R[2][2]
    if trace > 0.0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = (0.25 * s, (R[2][1] - R[1][2]) / s, (R[0][2] - R[2][0]) / s, (R[1][0] - R[0][1]) / s)
    elif R[0][0] > R[1][1] and R[0][0] > R[2][2]:
        s = 2.0 * math.sqrt(1.0 + R[0][0] - R[1][1] - R[2][2])
        q = ((R[2][1] - R[1][2]) / s, 0.25 * s, (R[0][1] + R[1][0]) / s, (R[0][2] + R[2][0]) / s)
    elif R[1][1] > R[2][2]:
        s = 2.0 * math.sqrt(1.0 + R[1][1] - R[0][0] - R[2][2])
        q = ((R[0][2] - R[2][0]) / s, (R[0][1] + R[1][0]) / s, 0.25 * s, (R[1][2] + R[2][1]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + R[2][2] - R[0][0] - R[1][1])
        q = ((R[1][0] - R[0][1]) / s, (R[0][2] + R[2][0]) / s, (R[1][2] + R[2][1]) / s, 0.25 * s)
    norm = math.sqrt(sum(c * c for c in q))
    w, x, y, z = (c / norm for c in q)
    return (w, x, y, z) if w >= 0.0 else (-w, -x, -y, -z)


def camera_in_world(result: CalibrationResult) -> tuple[tuple[float, float, float], tuple[float, ...]]:
    """(camera centre in absolute UTM m, camera->world quaternion w, x, y, z) of a result with a pose."""
    if result.R is None or result.t is None:
        raise ValueError(f"result {result.result_id} has no pose (R, t): refused results have no transform")
    R, t = result.R, result.t
    # Centre: C_local = -R^T t; world = local + origin (the local frame is only translated).
    centre = tuple(
        -(R[0][i] * t[0] + R[1][i] * t[1] + R[2][i] * t[2]) + result.frame.origin[i] for i in range(3)
    )
    R_world_from_cam = [[R[j][i] for j in range(3)] for i in range(3)]
    return (centre[0], centre[1], centre[2]), _rotation_matrix_to_quaternion(R_world_from_cam)


def frame_transform(result: CalibrationResult) -> bytes:
    """An accepted result as foxglove.FrameTransform: parent the UTM frame (its EPSG code), child the camera's
    optical frame, translation the camera centre (absolute UTM, m), rotation camera -> world.

    Foxglove composes transforms in double precision, so absolute UTM metres keep millimetres here.
    """
    centre, (w, x, y, z) = camera_in_world(result)
    message = FrameTransform(
        parent_frame_id=world_frame_id(result.frame.crs),
        child_frame_id=camera_frame_id(result.rsu_id, result.camera_id),
    )
    message.timestamp.FromNanoseconds(result.created_at_ns)
    message.translation.x, message.translation.y, message.translation.z = centre
    message.rotation.w, message.rotation.x, message.rotation.y, message.rotation.z = w, x, y, z
    return bytes(message.SerializeToString())


def origin_transform(result: CalibrationResult) -> bytes:
    """The result's local frame (UTM minus frame.origin, unrotated) in the UTM frame, as FrameTransform."""
    message = FrameTransform(
        parent_frame_id=world_frame_id(result.frame.crs),
        child_frame_id=local_frame_id(result.rsu_id, result.camera_id),
    )
    message.timestamp.FromNanoseconds(result.created_at_ns)
    message.translation.x, message.translation.y, message.translation.z = result.frame.origin
    message.rotation.w = 1.0
    return bytes(message.SerializeToString())


def camera_calibration(result: CalibrationResult) -> bytes:
    """The result's intrinsics as foxglove.CameraCalibration: OpenCV's plumb_bob, D = k1, k2, p1, p2, k3 (4
    coefficients padded with k3 = 0), or its rational_polynomial, D = k1, k2, p1, p2, k3, k4, k5, k6."""
    k = result.intrinsics
    rational = len(k.dist) == 8
    message = CameraCalibration(
        frame_id=camera_frame_id(result.rsu_id, result.camera_id),
        width=k.width,
        height=k.height,
        distortion_model="rational_polynomial" if rational else "plumb_bob",
        D=list(k.dist) if rational else [*k.dist, *[0.0] * (5 - len(k.dist))],
        K=[k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    )
    message.timestamp.FromNanoseconds(result.created_at_ns)
    return bytes(message.SerializeToString())
