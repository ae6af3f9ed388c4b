"""foxglove.CompressedImage in and out: the official schema's encoding, JPEG and PNG, bad payloads named."""

from __future__ import annotations

import base64
import json

import mcap.reader
import mcap.writer
import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf import descriptor_pb2

from daemon.images import (
    SCHEMA_NAME,
    ImageError,
    add_image_channel,
    decode_compressed_image,
    encode_compressed_image,
)
from daemon.keys import image_key

T0 = 1_700_000_000_123_456_789


def _picture() -> np.ndarray:
    rng = np.random.default_rng(3)
    return rng.integers(0, 256, size=(48, 64, 3), dtype=np.uint8)


def test_png_round_trips_exactly_with_the_official_schema() -> None:
    image = _picture()
    payload = encode_compressed_image(image, T0, "west", image_format="png")
    message = CompressedImage.FromString(payload)  # the official class reads what we wrote
    assert (message.format, message.frame_id, message.timestamp.ToNanoseconds()) == ("png", "west", T0)
    decoded = decode_compressed_image(payload)
    assert (decoded.stamp_ns, decoded.frame_id, decoded.format) == (T0, "west", "png")
    assert np.array_equal(decoded.image, image)


def test_jpeg_and_foxglove_json_are_decoded() -> None:
    image = np.full((48, 64, 3), (30, 120, 200), dtype=np.uint8)
    decoded = decode_compressed_image(encode_compressed_image(image, T0, "cam"))
    assert decoded.format == "jpeg" and decoded.image.shape == (48, 64, 3)
    assert np.abs(decoded.image.astype(int) - image).max() <= 3  # lossy, but a flat colour survives
    png = CompressedImage.FromString(encode_compressed_image(image, T0, "cam", image_format="png")).data
    document = {
        "timestamp": {"sec": T0 // 10**9, "nsec": T0 % 10**9},
        "frame_id": "cam",
        "format": "PNG",
        "data": base64.b64encode(png).decode(),
    }
    decoded = decode_compressed_image(json.dumps(document).encode())
    assert decoded.stamp_ns == T0 and np.array_equal(decoded.image, image)


def _proto(**fields: object) -> bytes:
    png = CompressedImage.FromString(encode_compressed_image(_picture(), T0, "c", image_format="png")).data
    message = CompressedImage(frame_id="c", format=str(fields.get("format", "png")))
    message.data = fields.get("data", png)  # type: ignore[assignment]
    if fields.get("timestamp", True):
        message.timestamp.FromNanoseconds(T0)
    return bytes(message.SerializeToString())


@pytest.mark.parametrize(
    ("payload", "expected"),
    [
        (b"\xff\xff\x00", "(root): not a foxglove.CompressedImage protobuf message"),
        (_proto(timestamp=False), "timestamp: missing"),
        (_proto(format="webp"), "format: 'webp' is not one of jpeg, png"),
        (_proto(data=b""), "data: empty"),
        (_proto(data=b"\x89PNG\r\n\x1a\n" + b"\x00" * 30), "data: not a PNG file"),
        (_proto(format="jpeg"), "data: not a JPEG file"),
        # A 30-byte PNG header claiming 100000 x 100000 px: refused before decoding.
        (
            _proto(
                data=b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + (100000).to_bytes(4, "big") * 2 + b"\x08\x02"
            ),
            "data: 100000 x 100000 px exceeds the limit",
        ),
        (_proto(data=b"\xff\xd8\xff\xe0\x00\x10JFIF\x00" + b"\x00" * 40), "data: "),
        (b'{"timestamp": {"sec": 1700000000}, "format": "png", "data": "%%%"}', "data: not base64"),
        (b'{"timestamp": {"sec": 1700000000, "nsec": 2000000000}}', "timestamp.nsec: 2000000000 outside"),
        (
            b'{"timestamp": {"sec": 17}, "format": "png", "data": ""}',
            "timestamp: 17000000000 ns is not a time",
        ),
        (b'{"format": "png"}', "timestamp: missing"),
        (b"{not json", "(root): not JSON"),
    ],
)
def test_bad_images_name_the_field(payload: bytes, expected: str) -> None:
    with pytest.raises(ImageError) as info:
        decode_compressed_image(payload)
    assert expected in str(info.value), str(info.value)


def test_an_mcap_image_channel_carries_the_official_schema(tmp_path: object) -> None:
    path = tmp_path / "images.mcap"  # type: ignore[operator]
    payload = encode_compressed_image(_picture(), T0, "cam", image_format="png")
    with open(path, "wb") as stream:
        writer = mcap.writer.Writer(stream)
        writer.start()
        channel_id = add_image_channel(writer, "r1", "cam")
        writer.add_message(channel_id, log_time=T0, data=payload, publish_time=T0)
        writer.finish()
    with open(path, "rb") as stream:
        ((schema, channel, message),) = list(mcap.reader.make_reader(stream).iter_messages())
    assert (schema.name, schema.encoding, channel.message_encoding) == (SCHEMA_NAME, "protobuf", "protobuf")
    assert channel.topic == image_key("r1", "cam") == "rsu/r1/camera/cam/image"
    files = descriptor_pb2.FileDescriptorSet.FromString(schema.data).file
    assert {f.name for f in files} == {"foxglove/CompressedImage.proto", "google/protobuf/timestamp.proto"}
    assert decode_compressed_image(message.data).stamp_ns == T0


def test_put_image_arrives_over_zenoh_decodable() -> None:
    import zenoh
    from helpers import free_port, wait_until

    from daemon.bus import client_config
    from daemon.images import put_image

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    listener_config = zenoh.Config()
    listener_config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    listener_config.insert_json5("scouting/multicast/enabled", "false")
    received: list[tuple[str, bytes, str]] = []
    listener = zenoh.open(listener_config)
    sender = None
    try:
        subscriber = listener.declare_subscriber(
            "rsu/r1/camera/*/image",
            lambda s: received.append((str(s.key_expr), s.payload.to_bytes(), str(s.encoding))),
        )
        sender = zenoh.open(client_config([endpoint]))
        image = _picture()
        # Connected once a publisher on the key sees the listener's subscriber.
        publisher = sender.declare_publisher("rsu/r1/camera/cam/image")
        wait_until(lambda: publisher.matching_status.matching)
        publisher.undeclare()
        sent = put_image(sender, "r1", "cam", image, T0, image_format="png")
        wait_until(lambda: len(received) == 1)
        subscriber.undeclare()
    finally:
        if sender is not None:
            sender.close()
        listener.close()
    key, payload, encoding = received[0]
    assert key == "rsu/r1/camera/cam/image" and payload == sent
    assert encoding == "application/protobuf;foxglove.CompressedImage"
    decoded = decode_compressed_image(payload)
    assert decoded.stamp_ns == T0 and np.array_equal(decoded.image, image)
