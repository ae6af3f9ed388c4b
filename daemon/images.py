"""Camera images on the bus and in recordings: Foxglove's `foxglove.CompressedImage` (JPEG or PNG).

In: `rsu/{rsu}/camera/{cam}/image`, protobuf-encoded with the official schema (foxglove-schemas-protobuf),
or Foxglove's JSON form of the same message (`data` base64). `decode_compressed_image` turns a payload
into a stamped BGR image or raises ImageError naming the field. Out: `put_image` (publish),
`add_image_channel` + `encode_compressed_image` (record in MCAP) are what a producer (the simulator's
export, a camera bridge) calls to publish or record images the daemon's detector reads.
"""

from __future__ import annotations

import base64
import binascii
import json
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
import numpy.typing as npt
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf import descriptor_pb2
from google.protobuf.message import DecodeError

from daemon.keys import image_key
from pipeline.errors import InputError
from schemas.common import STAMP_NS_MAX, STAMP_NS_MIN

SCHEMA_NAME = "foxglove.CompressedImage"
PROTOBUF_ENCODING = "application/protobuf"  # the Zenoh encoding a publisher should declare
IMAGE_FORMATS = ("jpeg", "png")
# Larger than any camera this daemon calibrates (intrinsics allow 20000 px, but a 16k x 16k BGR image is
# already 768 MB): decoding refuses before allocating.
MAX_IMAGE_PIXELS = 50_000_000

ImageBgr = npt.NDArray[np.uint8]  # (H, W, 3) uint8, OpenCV's BGR order


class ImageError(InputError):
    """An image payload that cannot be used; the message names the field ("format", "data", ...)."""


@dataclass(frozen=True, slots=True)
class DecodedImage:
    """One camera image: producer stamp (ns since the Unix epoch), frame_id, format and pixels (BGR)."""

    stamp_ns: int
    frame_id: str
    format: str
    image: ImageBgr


def encode_compressed_image(
    image: ImageBgr,
    stamp_ns: int,
    frame_id: str,
    image_format: Literal["jpeg", "png"] = "jpeg",
    jpeg_quality: int = 90,
) -> bytes:
    """A BGR image (H, W, 3) uint8 -> foxglove.CompressedImage protobuf bytes, stamped `stamp_ns`."""
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image: expected (H, W, 3) uint8 BGR, got {image.shape} {image.dtype}")
    if image_format == "jpeg":
        ok, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    elif image_format == "png":
        ok, encoded = cv2.imencode(".png", image)
    else:
        raise ValueError(f"image_format = {image_format!r} is not one of {', '.join(IMAGE_FORMATS)}")
    if not ok:
        raise ValueError(f"image: OpenCV could not encode a {image.shape} image as {image_format}")
    message = CompressedImage(frame_id=frame_id, format=image_format, data=encoded.tobytes())
    message.timestamp.FromNanoseconds(stamp_ns)
    return bytes(message.SerializeToString())


def put_image(
    session: Any,
    rsu_id: str,
    camera_id: str,
    image: ImageBgr,
    stamp_ns: int,
    image_format: Literal["jpeg", "png"] = "jpeg",
) -> bytes:
    """Publish a camera image where the daemon's detector reads it (`rsu/{rsu}/camera/{cam}/image`, a
    zenoh.Session), encoded and declared as foxglove.CompressedImage protobuf; returns the payload sent."""
    import zenoh

    payload = encode_compressed_image(image, stamp_ns, camera_id, image_format)
    session.put(
        image_key(rsu_id, camera_id),
        payload,
        encoding=zenoh.Encoding.APPLICATION_PROTOBUF.with_schema(SCHEMA_NAME),
        congestion_control=zenoh.CongestionControl.BLOCK,
    )
    return payload


def compressed_image_schema() -> bytes:
    """The schema's FileDescriptorSet (what MCAP and Foxglove expect for protobuf channels)."""
    files: list[Any] = []
    seen: set[str] = set()

    def add(file: Any) -> None:
        if file.name in seen:
            return
        seen.add(file.name)
        for dependency in file.dependencies:
            add(dependency)
        proto = descriptor_pb2.FileDescriptorProto()
        file.CopyToProto(proto)
        files.append(proto)

    add(CompressedImage.DESCRIPTOR.file)
    return bytes(descriptor_pb2.FileDescriptorSet(file=files).SerializeToString())


def add_image_channel(writer: Any, rsu_id: str, camera_id: str) -> int:
    """Register the camera's image channel on an `mcap.writer.Writer` (protobuf, the official schema);
    returns the channel id for `writer.add_message(channel_id, log_time, data, publish_time)`."""
    schema_id = writer.register_schema(name=SCHEMA_NAME, encoding="protobuf", data=compressed_image_schema())
    return int(
        writer.register_channel(
            topic=image_key(rsu_id, camera_id), message_encoding="protobuf", schema_id=schema_id
        )
    )


def decode_compressed_image(payload: bytes, max_pixels: int = MAX_IMAGE_PIXELS) -> DecodedImage:
    """A foxglove.CompressedImage (protobuf, or Foxglove's JSON with base64 `data`) -> stamped BGR image.

    Raises ImageError naming the field: timestamp, format ("jpeg" or "png"), data (not decodable as that
    format, or larger than `max_pixels`).
    """
    # A protobuf CompressedImage never starts with '{' (0x7B would be field 15, a group): JSON it is.
    if payload[:1] == b"{":
        stamp_ns, frame_id, image_format, data = _fields_from_json(payload)
    else:
        try:
            message = CompressedImage.FromString(payload)
        except DecodeError as err:
            raise ImageError("image", f"(root): not a {SCHEMA_NAME} protobuf message: {err}") from err
        if not message.HasField("timestamp"):
            raise ImageError("image", "timestamp: missing")
        stamp_ns = _stamp_ns(message.timestamp.seconds, message.timestamp.nanos)
        frame_id, image_format, data = message.frame_id, message.format, message.data
    image_format = image_format.strip().lower()
    if image_format not in IMAGE_FORMATS:
        raise ImageError("image", f"format: {image_format[:32]!r} is not one of {', '.join(IMAGE_FORMATS)}")
    image = _decode_pixels(data, image_format, max_pixels)
    return DecodedImage(stamp_ns, frame_id, image_format, image)


def _stamp_ns(seconds: Any, nanos: Any) -> int:
    if (
        isinstance(seconds, bool)
        or isinstance(nanos, bool)
        or not isinstance(seconds, int)
        or not isinstance(nanos, int)
    ):
        raise ImageError("image", "timestamp: sec and nsec must be integers")
    if not 0 <= nanos < 1_000_000_000:
        raise ImageError("image", f"timestamp.nsec: {nanos} outside [0, 1e9)")
    stamp_ns = seconds * 1_000_000_000 + nanos
    if not STAMP_NS_MIN <= stamp_ns <= STAMP_NS_MAX:
        raise ImageError("image", f"timestamp: {stamp_ns} ns is not a time between 2000 and 2200")
    return stamp_ns


def _fields_from_json(payload: bytes) -> tuple[int, str, str, bytes]:
    try:
        document = json.loads(payload)
    except (UnicodeDecodeError, ValueError) as err:
        raise ImageError("image", f"(root): not JSON: {err}") from err
    if not isinstance(document, dict):
        raise ImageError("image", "(root): expected a JSON object")
    timestamp = document.get("timestamp")
    if not isinstance(timestamp, dict):
        raise ImageError("image", "timestamp: missing or not an object {sec, nsec}")
    stamp_ns = _stamp_ns(timestamp.get("sec"), timestamp.get("nsec", 0))
    frame_id, image_format, data = document.get("frame_id", ""), document.get("format"), document.get("data")
    if not isinstance(frame_id, str):
        raise ImageError("image", "frame_id: expected a string")
    if not isinstance(image_format, str):
        raise ImageError("image", "format: missing or not a string")
    if not isinstance(data, str):
        raise ImageError("image", "data: missing or not a base64 string")
    try:
        return stamp_ns, frame_id, image_format, base64.b64decode(data, validate=True)
    except (binascii.Error, ValueError) as err:
        raise ImageError("image", f"data: not base64: {err}") from err


def _decode_pixels(data: bytes, image_format: str, max_pixels: int) -> ImageBgr:
    if not data:
        raise ImageError("image", "data: empty")
    width, height = _header_size(data, image_format)
    if width * height > max_pixels:
        raise ImageError("image", f"data: {width} x {height} px exceeds the limit of {max_pixels} pixels")
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if image is None or image.ndim != 3 or image.shape[2] != 3:
        raise ImageError("image", f"data: not a decodable {image_format} image ({len(data)} bytes)")
    return np.asarray(image, dtype=np.uint8)  # IMREAD_COLOR: always 8-bit BGR (16-bit PNGs scaled down)


def _header_size(data: bytes, image_format: str) -> tuple[int, int]:
    """Width and height from the file header, read before decoding (a small file can claim a huge image)."""
    if image_format == "png":
        if data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR":
            raise ImageError("image", "data: not a PNG file (format says png)")
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:2] != b"\xff\xd8":
        raise ImageError("image", "data: not a JPEG file (format says jpeg)")
    # Walk the JPEG segments to the first start-of-frame marker, which holds the size.
    index = 2
    while index + 9 < len(data):
        if data[index] != 0xFF:
            raise ImageError("image", f"data: corrupt JPEG segment at byte {index}")
        marker = data[index + 1]
        if marker == 0xFF:  # fill byte
            index += 1
            continue
        length = int.from_bytes(data[index + 2 : index + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            height = int.from_bytes(data[index + 5 : index + 7], "big")
            width = int.from_bytes(data[index + 7 : index + 9], "big")
            return width, height
        if length < 2:
            raise ImageError("image", f"data: corrupt JPEG segment at byte {index}")
        index += 2 + length
    raise ImageError("image", "data: JPEG without a frame header (truncated?)")
