"""MCAP recordings: the daemon's log of every valid incoming message and the offline/simulated input format.

Layout (docs/design.md): one channel per key expression, message_encoding "json", schema "jsonschema" from the
pydantic model, log_time = receive ns, publish_time = stamp_ns; chunked, zstd. MCAP files are written and
read here (daemon.main imports mcap only to report its version). Reading is deliberately forgiving: a
truncated or partly corrupted file yields every message that can still be proven intact (chunk CRCs), and
bad messages are counted, never fatal. The daemon records through RotatingRecorder
({rsu_id}-{start_received_ns:019d}.mcap files, rotated by size and age, pruned by retention); jobs read a
stamp window across files with read_window.
"""

from __future__ import annotations

import bisect
import functools
import io
import json
import logging
import mmap
import os
import re
import struct
import zlib
from collections import Counter
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, TYPE_CHECKING, Literal

import mcap
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Header,
    McapRecord,
    Message,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.stream_reader import breakup_chunk
from pydantic import BaseModel, ValidationError

from daemon import __version__, foxglove, keys
from daemon.clock import Clock
from daemon.foxglove import MessageSchema
from pipeline.errors import RecordingError
from schemas.atomic import fsync_dir
from schemas.common import (
    IDENTIFIER,
    IDENTIFIER_CHARS,
    IDENTIFIER_MAX_LENGTH,
    decode_json,
    describe_validation_error,
)
from schemas.config import StorageConfig
from schemas.messages import DetectionFrame, V2xPosition
from schemas.results import CalibrationResult

if TYPE_CHECKING:
    from sim.simulate import SimulationResult

try:
    from zstandard import ZstdError as _ZstdError
except ImportError:  # mcap without zstd support reports UnsupportedCompressionError (an McapError) instead
    _ZstdError = McapError  # type: ignore[assignment, misc]

logger = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
DEFAULT_CHUNK_SIZE = 1024 * 1024
MAX_CHANNELS = 65_535  # channel ids are uint16 in the MCAP record; mcap's writer numbers them from 1
# zstd level 1 instead of the library default 3: on detection JSON it compresses ~2x faster (320 vs
# 150 MB/s measured) at the same or a better ratio, and compression is most of the per-message cost.
ZSTD_LEVEL = 1
# Simulated transport + processing delays: the receive time a daemon would have logged.
SIM_DETECTION_LATENCY_NS = 30_000_000
SIM_V2X_LATENCY_NS = 20_000_000

_RECORD_HEAD = struct.Struct("<BQ")  # opcode, record length (MCAP spec)
_FOOTER = struct.Struct("<BQQQI")  # head, summary_start, summary_offset_start, summary_crc
# Message record: head, channel_id u16, sequence u32, log_time u64, publish_time u64, then the payload.
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_MESSAGE_FIXED_BYTES = _MESSAGE_HEAD.size - _RECORD_HEAD.size
_CHUNK_TIMES = struct.Struct("<QQ")  # a chunk record body opens with message_start_time, message_end_time
_CHUNK_OPCODE = bytes([Opcode.CHUNK])
_KNOWN_OPCODES = frozenset(range(0x01, 0x10))  # MCAP v0: header 0x01 ... data end 0x0f
_LOST_HEADER = Header(profile="", library="")  # stands in for a damaged header record
_MAX_U64 = 2**64 - 1

# What a damaged chunk can raise inside mcap's parser: bad lengths (struct.error, EndOfFile), CRC mismatch
# and undecodable strings (ValueError), decompression failures (zstd; lz4 raises RuntimeError), sizes
# beyond ssize_t (OverflowError).
_CHUNK_ERRORS: tuple[type[BaseException], ...] = (
    McapError,
    struct.error,
    ValueError,
    RuntimeError,
    OverflowError,
    _ZstdError,
)
# Our chunks are ~1 MiB; a larger claimed size is a corrupt field, refused before anything is allocated.
MAX_CHUNK_BYTES = 256 * 1024 * 1024

Compression = Literal["zstd", "lz4", "none"]
# A channel's schema: an rsucal model (JSON, with its JSON Schema) or a foreign one (Foxglove's protobuf).
ChannelSchema = type[BaseModel] | MessageSchema
_COMPRESSION_NAMES: dict[str, str] = {"zstd": "zstd", "lz4": "lz4", "none": ""}  # as written in chunks


# ---------------------------------------------------------------------------------------------- writing


class _ChannelState:
    """Per-channel bookkeeping of a RecordingWriter (mutable, on the writing thread only)."""

    __slots__ = ("id", "messages", "sequence")

    def __init__(self, channel_id: int) -> None:
        self.id = channel_id
        self.sequence = 0
        self.messages = 0


def _record_bytes(record: McapRecord) -> bytes:
    """One MCAP record, serialised by mcap's own record classes (everything except the per-message path)."""
    builder = RecordBuilder()
    record.write(builder)
    data: bytes = builder.end()  # type: ignore[no-untyped-call]
    return data


@functools.cache
def _schema_data(model: type[BaseModel]) -> bytes:
    return json.dumps(model.model_json_schema(), separators=(",", ":")).encode("utf-8")


@functools.cache
def _message_schema(model: type[BaseModel]) -> MessageSchema:
    return MessageSchema(f"rsucal.{model.__name__}", "jsonschema", _schema_data(model), "json")


def _compressor(compression: Compression) -> Callable[[bytearray], bytes]:
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress
    if compression == "lz4":
        import lz4.frame

        compress: Callable[[bytearray], bytes] = lz4.frame.compress
        return compress
    return bytes


class RecordingWriter:
    """Appends validated messages to a new MCAP file; one instance per file, owned by one thread.

    Channels are registered on first use of a key expression, schemas once per model. Use as a context
    manager (or call finish()) so the summary and indexes are written; a file that was never finished is
    still readable up to its last complete chunk (see read_recording), and flush() bounds that loss.

    The layout is what mcap's Writer produces (schema and channel records inside the chunk where they are
    first used, message indexes after each chunk, summary with schemas, channels, statistics and chunk
    indexes, summary offsets, CRC'd footer), but messages are appended to the open chunk by one struct.pack
    instead of mcap's record objects: the daemon logs >= 20,000 messages/s on one core.
    """

    def __init__(
        self,
        path: Path,
        compression: Compression = "zstd",
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        overwrite: bool = False,
    ) -> None:
        if compression not in _COMPRESSION_NAMES:
            raise ValueError(f"compression {compression!r} is not one of {', '.join(_COMPRESSION_NAMES)}")
        if chunk_size < 1:
            raise ValueError(f"chunk_size = {chunk_size} must be positive")
        self.path = Path(path)
        self._compress = _compressor(compression)
        self._compression_name = _COMPRESSION_NAMES[compression]
        self._chunk_size = chunk_size
        # Exclusive by default: a recording already on disk is evidence, never silently replaced.
        try:
            self._file: IO[bytes] = open(self.path, "wb" if overwrite else "xb")  # noqa: SIM115 - see finish()
        except FileExistsError as err:
            raise RecordingError(f"{self.path}: already exists; recordings are never overwritten") from err
        self._bytes_written = 0
        self._schemas: dict[MessageSchema, Schema] = {}
        self._channels: dict[str, _ChannelState] = {}
        self._channel_records: list[Channel] = []
        self._chunk_indexes: list[ChunkIndex] = []
        # The open chunk: its records (uncompressed), log-time range, and per channel the message index
        # entries as a flat [log_time, offset, log_time, offset, ...] list.
        self._chunk = bytearray()
        self._chunk_messages = 0
        self._chunk_views = 0
        self._chunk_start_ns = _MAX_U64
        self._chunk_end_ns = 0
        self._chunk_index: dict[int, list[int]] = {}
        self._message_start_ns = _MAX_U64
        self._message_end_ns = 0
        self.messages_written = 0
        self._finished = False
        library = f"rsucal {__version__}; python mcap {mcap.__version__}"
        self._append(MCAP_MAGIC + _record_bytes(Header(profile="", library=library)))
        # On disk at once: a new file is a valid (empty) recording from its first microsecond, not 0 bytes
        # of "not an MCAP file" to a reader listing the directory (or after a crash) until the first flush.
        self._file.flush()

    @property
    def channel_count(self) -> int:
        """Channels registered so far; MCAP channel ids are uint16, so rotate well before MAX_CHANNELS."""
        return len(self._channels)

    @property
    def bytes_written(self) -> int:
        """Bytes handed to the file so far (counted, not stat'ed); the open chunk is not included."""
        return self._bytes_written

    @property
    def finished(self) -> bool:
        return self._finished

    @property
    def pending_messages(self) -> int:
        """Received messages in the open chunk (views not counted): in memory only, lost by a crash until
        the chunk is written."""
        return self._chunk_messages - self._chunk_views

    def has_channel(self, key: str) -> bool:
        """Whether `key` already has a channel (writing to it then needs no new channel id)."""
        return key in self._channels

    def write(self, key: str, message: BaseModel, received_ns: int, stamp_ns: int) -> None:
        """Log one message under its key expression: log_time = received_ns, publish_time = stamp_ns."""
        self.write_raw(key, type(message), message.model_dump_json().encode("utf-8"), received_ns, stamp_ns)

    def write_raw(
        self,
        key: str,
        model: ChannelSchema,
        payload: bytes,
        received_ns: int,
        stamp_ns: int,
        is_view: bool = False,
    ) -> None:
        """Log an already validated payload of `model` as it arrived (no re-serialisation).

        `model` names the channel's schema when `key` is new (an rsucal model: JSON; a MessageSchema: its
        own encoding, e.g. Foxglove's protobuf); the payload is not checked against it. `is_view`: derived
        from a received message (a Foxglove view, a result), so not in pending_messages.
        """
        if self._finished:
            raise RecordingError(f"{self.path}: recording already finished")
        if not (0 <= received_ns <= _MAX_U64 and 0 <= stamp_ns <= _MAX_U64):
            raise ValueError(
                f"MCAP times are unsigned 64-bit: received_ns={received_ns}, stamp_ns={stamp_ns}"
            )
        channel = self._channels.get(key)
        if channel is None:
            channel = self._register_channel(key, model)
        chunk = self._chunk
        channel.sequence = sequence = (channel.sequence + 1) & 0xFFFFFFFF  # uint32 in the record
        channel.messages += 1
        entries = self._chunk_index.get(channel.id)
        if entries is None:
            entries = self._chunk_index[channel.id] = []
        entries.append(received_ns)
        entries.append(len(chunk))
        chunk += _MESSAGE_HEAD.pack(
            Opcode.MESSAGE, _MESSAGE_FIXED_BYTES + len(payload), channel.id, sequence, received_ns, stamp_ns
        )
        chunk += payload
        if received_ns < self._chunk_start_ns:
            self._chunk_start_ns = received_ns
        if received_ns > self._chunk_end_ns:
            self._chunk_end_ns = received_ns
        self._chunk_messages += 1
        if is_view:
            self._chunk_views += 1
        self.messages_written += 1
        if len(chunk) >= self._chunk_size:
            self._end_chunk()

    def write_detections(self, rsu_id: str, frame: DetectionFrame, received_ns: int) -> None:
        """Log a DetectionFrame on rsu/{rsu_id}/camera/{frame.camera_id}/detections."""
        if not IDENTIFIER.match(rsu_id):
            raise ValueError(f"rsu_id {rsu_id!r} is not a valid key segment ([A-Za-z0-9_.-], 1-64 chars)")
        self.write(keys.detections_key(rsu_id, frame.camera_id), frame, received_ns, frame.stamp_ns)

    def write_v2x(self, msg: V2xPosition, received_ns: int) -> None:
        """Log a V2xPosition on v2x/cam/{msg.station_id}."""
        self.write(keys.v2x_key(msg.station_id), msg, received_ns, msg.stamp_ns)

    def write_result(self, result: CalibrationResult, received_ns: int) -> None:
        """Log a CalibrationResult (JSON) on .../calibration and, with a pose, its Foxglove views.

        log_time = publish_time = `received_ns` (when the daemon had it); the views are stamped
        created_at_ns inside their messages.
        """
        write_result_views(self.write_raw, result, received_ns)

    def flush(self) -> None:
        """Close the open chunk and fsync, so a crash after this loses nothing already written.

        Each flush ends a chunk early (worse compression); call it on a timer, not per message.
        """
        if self._finished:
            return
        self._end_chunk()
        self._file.flush()
        os.fsync(self._file.fileno())

    def finish(self) -> None:
        """Write the last chunk, the summary and the footer, then close the file. Idempotent."""
        if self._finished:
            return
        self._finished = True
        try:
            self._end_chunk()
            self._append(_record_bytes(DataEnd(data_section_crc=0)))
            self._append(self._summary_and_footer())
            self._file.flush()
            os.fsync(self._file.fileno())
        finally:
            self._file.close()

    def abandon(self) -> None:
        """Close the file as it is, without the open chunk or a summary (after a write error). Idempotent.

        What reached the file stays readable up to its last complete chunk, like after a crash.
        """
        if self._finished:
            return
        self._finished = True
        try:
            self._file.close()
        except OSError as err:  # the buffered tail is lost either way; the fd is closed regardless
            logger.warning("%s: closing after a write error failed too: %s", self.path, err)

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        # Finish even when the body raised: everything logged so far stays readable.
        self.finish()

    def _append(self, data: bytes) -> None:
        self._file.write(data)
        self._bytes_written += len(data)

    def _register_channel(self, key: str, model: ChannelSchema) -> _ChannelState:
        if len(self._channels) >= MAX_CHANNELS:
            # Every V2X station is a channel; a file must be rotated before the uint16 ids run out.
            raise RecordingError(f"{self.path}: {MAX_CHANNELS} channels in one recording; rotate the file")
        spec = model if isinstance(model, MessageSchema) else _message_schema(model)
        schema = self._schemas.get(spec)
        if schema is None:
            schema = Schema(id=len(self._schemas) + 1, name=spec.name, encoding=spec.encoding, data=spec.data)
            self._schemas[spec] = schema
            schema_bytes = _record_bytes(schema)
            self._append(schema_bytes)
            self._chunk += schema_bytes
        record = Channel(
            id=len(self._channels) + 1,
            topic=key,
            message_encoding=spec.message_encoding,
            schema_id=schema.id,
            metadata={},
        )
        # Written twice. Inside the chunk where it is first used, like mcap's writer: CRC-protected with
        # the messages, and a crashed file has no summary to supply it. And at top level (it lands before
        # that chunk): a reader skipping chunks by time still learns every channel of an unfinished file.
        channel_bytes = _record_bytes(record)
        self._append(channel_bytes)
        self._chunk += channel_bytes
        self._channel_records.append(record)
        state = self._channels[key] = _ChannelState(record.id)
        return state

    def _end_chunk(self) -> None:
        """Compress and write the open chunk and its message indexes (nothing when it holds no message)."""
        if self._chunk_messages == 0:
            return
        records = self._chunk
        compressed = self._compress(records)
        chunk = Chunk(
            message_start_time=self._chunk_start_ns,
            message_end_time=self._chunk_end_ns,
            uncompressed_size=len(records),
            uncompressed_crc=zlib.crc32(records),
            compression=self._compression_name,
            data=compressed,
        )
        chunk_start = self._bytes_written
        chunk_bytes = _record_bytes(chunk)
        self._append(chunk_bytes)
        index_start = self._bytes_written
        index_offsets: dict[int, int] = {}
        index_parts: list[bytes] = []
        position = index_start
        for channel_id, entries in self._chunk_index.items():
            index_offsets[channel_id] = position
            # MessageIndex: channel_id u16, records length u32, then (log_time u64, offset u64) pairs.
            part = struct.pack(
                f"<BQHI{len(entries)}Q",
                Opcode.MESSAGE_INDEX,
                6 + 8 * len(entries),
                channel_id,
                8 * len(entries),
                *entries,
            )
            index_parts.append(part)
            position += len(part)
        self._append(b"".join(index_parts))
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=self._chunk_start_ns,
                message_end_time=self._chunk_end_ns,
                chunk_start_offset=chunk_start,
                chunk_length=len(chunk_bytes),
                message_index_offsets=index_offsets,
                message_index_length=position - index_start,
                compression=self._compression_name,
                compressed_size=len(compressed),
                uncompressed_size=len(records),
            )
        )
        self._message_start_ns = min(self._message_start_ns, self._chunk_start_ns)
        self._message_end_ns = max(self._message_end_ns, self._chunk_end_ns)
        self._chunk = bytearray()
        self._chunk_messages = 0
        self._chunk_views = 0
        self._chunk_start_ns = _MAX_U64
        self._chunk_end_ns = 0
        self._chunk_index = {}

    def _summary_and_footer(self) -> bytes:
        """Summary section (schemas, channels, statistics, chunk indexes, offsets), footer and magic."""
        summary_start = self._bytes_written
        groups: list[tuple[Opcode, bytes]] = [
            (Opcode.SCHEMA, b"".join(_record_bytes(schema) for schema in self._schemas.values())),
            (Opcode.CHANNEL, b"".join(_record_bytes(channel) for channel in self._channel_records)),
            (Opcode.STATISTICS, _record_bytes(self._statistics())),
            (Opcode.CHUNK_INDEX, b"".join(_record_bytes(index) for index in self._chunk_indexes)),
        ]
        summary = bytearray()
        offsets = bytearray()
        for opcode, group in groups:
            offsets += _record_bytes(
                SummaryOffset(
                    group_opcode=opcode, group_start=summary_start + len(summary), group_length=len(group)
                )
            )
            summary += group
        summary_offset_start = summary_start + len(summary)
        summary += offsets
        # MCAP spec: the CRC covers the summary section and the footer up to the CRC field itself.
        footer_head = _FOOTER.pack(Opcode.FOOTER, _FOOTER.size - 9, summary_start, summary_offset_start, 0)
        summary_crc = zlib.crc32(footer_head[: _FOOTER.size - 4], zlib.crc32(summary))
        footer = _FOOTER.pack(
            Opcode.FOOTER, _FOOTER.size - 9, summary_start, summary_offset_start, summary_crc
        )
        return bytes(summary) + footer + MCAP_MAGIC

    def _statistics(self) -> Statistics:
        messages = self.messages_written
        return Statistics(
            message_count=messages,
            schema_count=len(self._schemas),
            channel_count=len(self._channels),
            attachment_count=0,
            metadata_count=0,
            chunk_count=len(self._chunk_indexes),
            message_start_time=self._message_start_ns if messages else 0,
            message_end_time=self._message_end_ns if messages else 0,
            channel_message_counts={state.id: state.messages for state in self._channels.values()},
        )


WriteRaw = Callable[[str, ChannelSchema, bytes, int, int], None]  # key, schema, payload, log_time, stamp


def write_result_views(write_raw: WriteRaw, result: CalibrationResult, received_ns: int) -> None:
    """The result channels: CalibrationResult JSON on rsu/{rsu}/camera/{cam}/calibration and, for an
    accepted result, foxglove.FrameTransform (UTM -> camera) on .../calibration/transform, the local origin
    (UTM -> local frame) on .../calibration/origin and foxglove.CameraCalibration on .../camera_info."""
    rsu_id, camera_id = result.rsu_id, result.camera_id
    payload = result.model_dump_json().encode("utf-8")
    write_raw(keys.calibration_key(rsu_id, camera_id), CalibrationResult, payload, received_ns, received_ns)
    if not result.verdict.is_accepted or result.R is None or result.t is None:
        return  # a refused result's pose (if any) is not the camera's: nothing to place in a 3D scene
    for key, schema, data in (
        (
            keys.transform_key(rsu_id, camera_id),
            foxglove.FRAME_TRANSFORM,
            foxglove.frame_transform(result),
        ),
        (
            keys.origin_topic(rsu_id, camera_id),
            foxglove.FRAME_TRANSFORM,
            foxglove.origin_transform(result),
        ),
        (
            keys.camera_info_topic(rsu_id, camera_id),
            foxglove.CAMERA_CALIBRATION,
            foxglove.camera_calibration(result),
        ),
    ):
        write_raw(key, schema, data, received_ns, received_ns)


def _vehicle_boxes(result: SimulationResult) -> dict[tuple[str, int], int]:
    """(camera_id, stamp_ns) -> index of the calibration vehicle's box, from the simulator's ground truth."""
    found: dict[tuple[str, int], int] = {}
    for camera_id, truth in result.ground_truth.items():
        for frame in truth.frames:
            if frame.calib_box is not None:
                found[(camera_id, frame.stamp_ns)] = frame.calib_box
    return found


def write_simulation_mcap(
    result: SimulationResult,
    path: Path,
    calibrations: Sequence[CalibrationResult] = (),
    image_every: int | None = None,
) -> Path:
    """Write a simulation as the daemon would have recorded it, in log-time order; returns `path`.

    Every camera's detections are logged 30 ms after their stamp, every V2X message 20 ms after; beside
    each its Foxglove view (ImageAnnotations with the calibration vehicle's box in its own colour, known
    here from the ground truth; LocationFix). With `image_every`, every image_every-th frame's rendered
    camera image too (foxglove.CompressedImage, JPEG, on `.../image`, logged with its detections).
    `calibrations` are logged after the last message, with their result channels (write_result_views).
    """
    path = Path(path)
    vehicle_boxes = _vehicle_boxes(result)
    # (log_time, kind, stamp, key, schema, payload)
    entries: list[tuple[int, int, int, str, ChannelSchema, bytes]] = []
    if image_every is not None:
        from daemon.images import encode_compressed_image
        from sim.images import render_images

        image_schema = foxglove.protobuf_schema("CompressedImage")
        for camera_id in result.detections:
            key = keys.image_key(result.rsu_id, camera_id)
            for stamp_ns, image in render_images(result, camera_id, image_every):
                payload = encode_compressed_image(image, stamp_ns, camera_id, "jpeg", jpeg_quality=85)
                entries.append(
                    (stamp_ns + SIM_DETECTION_LATENCY_NS, -1, stamp_ns, key, image_schema, payload)
                )
    for camera_id, frames in result.detections.items():
        key = keys.detections_key(result.rsu_id, camera_id)
        view_key = keys.annotations_topic(result.rsu_id, camera_id)
        for frame in frames:
            log_time = frame.stamp_ns + SIM_DETECTION_LATENCY_NS
            entries.append(
                (log_time, 0, frame.stamp_ns, key, DetectionFrame, frame.model_dump_json().encode())
            )
            calib = vehicle_boxes.get((camera_id, frame.stamp_ns))
            others = [box.model_dump() for i, box in enumerate(frame.boxes) if i != calib]
            vehicle = [] if calib is None else [_corners(frame.boxes[calib].model_dump())]
            view = foxglove.image_annotations(frame.stamp_ns, others, vehicle)
            entries.append((log_time, 1, frame.stamp_ns, view_key, foxglove.IMAGE_ANNOTATIONS, view))
    for msg in result.v2x:
        log_time = msg.stamp_ns + SIM_V2X_LATENCY_NS
        entries.append(
            (
                log_time,
                2,
                msg.stamp_ns,
                keys.v2x_key(msg.station_id),
                V2xPosition,
                msg.model_dump_json().encode(),
            )
        )
        fix = foxglove.location_fix(msg, is_vehicle=msg.station_id == result.station_id)
        entries.append(
            (log_time, 3, msg.stamp_ns, keys.location_topic(msg.station_id), foxglove.LOCATION_FIX, fix)
        )
    # Sort on the numeric fields only; ties keep camera, annotation, V2X, location order.
    entries.sort(key=lambda entry: entry[:3])
    with RecordingWriter(path, overwrite=True) as writer:
        for log_time, _, stamp_ns, key, schema, payload in entries:
            writer.write_raw(key, schema, payload, received_ns=log_time, stamp_ns=stamp_ns)
        last_ns = entries[-1][0] if entries else 0
        for calibration in calibrations:
            write_result_views(writer.write_raw, calibration, max(last_ns, calibration.created_at_ns))
    return path


def _corners(box: dict[str, float]) -> tuple[float, float, float, float]:
    return box["x1"], box["y1"], box["x2"], box["y2"]


# ---------------------------------------------------------------------------------------------- reading


@dataclass(frozen=True, slots=True)
class Recording:
    """What read_recording recovered from one MCAP file.

    detections: camera_id -> frames sorted by stamp; v2x: sorted by (stamp, station); rejected: topic ->
    messages that failed validation (with the first error each in rejection_examples); channels: every
    topic seen -> messages on it, ours or not; problems: file-level damage (truncation, bad chunks);
    complete: the footer was reached, i.e. the writer finished the file.
    """

    path: Path
    rsu_id: str | None
    detections: dict[str, list[DetectionFrame]]
    v2x: list[V2xPosition]
    rejected: dict[str, int] = field(default_factory=dict)
    rejection_examples: dict[str, str] = field(default_factory=dict)
    channels: dict[str, int] = field(default_factory=dict)
    problems: tuple[str, ...] = ()
    complete: bool = True

    @property
    def camera_ids(self) -> tuple[str, ...]:
        return tuple(sorted(self.detections))


@dataclass
class _Scan:
    """Records recovered by the linear scan; messages are yielded separately as they are found.

    channels: definitions read inside chunks (CRC-checked); loose_channels: top-level copies (our writer
    repeats each definition there so a reader may skip chunks) and the summary's. Chunk copies win.
    """

    header: Header | None = None
    channels: dict[int, Channel] = field(default_factory=dict)
    loose_channels: dict[int, Channel] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    complete: bool = False
    recovered: int = 0  # messages yielded
    skipped_chunks: int = 0  # chunks outside the requested log-time range, not decompressed

    def channel(self, channel_id: int) -> Channel | None:
        found = self.channels.get(channel_id)
        return found if found is not None else self.loose_channels.get(channel_id)

    def topics(self) -> list[str]:
        return [channel.topic for channel in {**self.loose_channels, **self.channels}.values()]


def _body_stream(body: bytes) -> ReadDataStream:
    return ReadDataStream(io.BytesIO(body))


def _verified_chunk_offsets(stream: IO[bytes], size: int) -> list[int]:
    """Chunk start offsets from the summary's chunk index, if the footer's summary CRC proves it intact.

    Used only to resynchronise after a corrupt record length; [] when there is no trustworthy summary
    (unfinished file, no CRC, damaged summary).
    """
    tail_size = _FOOTER.size + len(MCAP_MAGIC)
    if size < len(MCAP_MAGIC) + tail_size:
        return []
    footer_at = size - tail_size
    stream.seek(footer_at)
    tail = stream.read(tail_size)
    opcode, length, summary_start, _, summary_crc = _FOOTER.unpack_from(tail)
    if tail[_FOOTER.size :] != MCAP_MAGIC or opcode != Opcode.FOOTER or length != _FOOTER.size - 9:
        return []
    if summary_crc == 0 or not len(MCAP_MAGIC) < summary_start <= footer_at:
        return []
    stream.seek(summary_start)
    summary = stream.read(footer_at - summary_start)
    # MCAP spec: the CRC covers the summary section and the footer up to the CRC field itself.
    if zlib.crc32(tail[: _FOOTER.size - 4], zlib.crc32(summary)) != summary_crc:
        return []
    offsets = []
    position = 0
    try:
        while position + _RECORD_HEAD.size <= len(summary):
            opcode, length = _RECORD_HEAD.unpack_from(summary, position)
            if opcode == Opcode.CHUNK_INDEX:
                body = summary[position + _RECORD_HEAD.size : position + _RECORD_HEAD.size + length]
                offsets.append(ChunkIndex.read(_body_stream(body)).chunk_start_offset)
            position += _RECORD_HEAD.size + length
    except _CHUNK_ERRORS:
        return []
    return sorted(offset for offset in set(offsets) if len(MCAP_MAGIC) < offset < summary_start)


def _find_intact_chunk(stream: IO[bytes], size: int, start: int) -> int | None:
    """Offset of the first record at or after `start` that is a chunk whose CRC proves it intact, or None.

    Resynchronises after a corrupt record length or header when no verified summary lists the chunks (a
    crashed, unfinished recording): only a chunk opcode whose length fits the file and whose body
    decompresses to its recorded CRC is trusted, so a stray 0x06 byte in other data is never taken."""
    with mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as view:
        at = view.find(_CHUNK_OPCODE, start)
        while at != -1 and at + _RECORD_HEAD.size <= size:
            _, length = _RECORD_HEAD.unpack_from(view, at)
            end = at + _RECORD_HEAD.size + length
            if _CHUNK_TIMES.size <= length and end <= size:
                try:
                    chunk = Chunk.read(_body_stream(view[at + _RECORD_HEAD.size : end]))
                    if chunk.uncompressed_crc != 0 and chunk.uncompressed_size <= MAX_CHUNK_BYTES:
                        breakup_chunk(chunk, validate_crc=True)
                        return at
                except _CHUNK_ERRORS:
                    pass
            at = view.find(_CHUNK_OPCODE, at + 1)
    return None


def _scan_messages(
    stream: IO[bytes], size: int, scan: _Scan, path: Path, log_range: tuple[int, int] | None = None
) -> Iterator[Message]:
    """Walk the records of an MCAP file front to back, yielding every message that can be trusted.

    mcap's own readers stop at the first damaged byte (and the seeking reader needs the footer), so a
    crash-truncated recording would read as nothing. Here each record is framed by its length alone: a
    chunk whose CRC or decompression fails is skipped with a problem noted. A corrupt length field breaks
    the framing; reading then resumes at the next chunk listed in a CRC-verified summary, or stops
    there when the file has none (truncated, unfinished). With `log_range` = (first_ns, last_ns), chunks
    whose log times lie entirely outside it are stepped over without being read or decompressed.
    """
    if stream.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
        raise RecordingError(f"{path}: not an MCAP file (bad magic bytes)")
    chunk_offsets = _verified_chunk_offsets(stream, size)
    offset = len(MCAP_MAGIC)
    # Without a verified summary a corrupt length is only noticed a record later (an unknown opcode, or a
    # length past the end): resynchronise from just after the record that sent us there, but never before
    # the end of the last chunk already read (no message twice).
    previous_offset = offset
    read_until = offset
    stream.seek(offset)
    while True:
        head = stream.read(_RECORD_HEAD.size)
        if len(head) < _RECORD_HEAD.size:
            scan.problems.append(f"file ends at byte {offset} without a footer (truncated; not finished)")
            return
        opcode, length = _RECORD_HEAD.unpack(head)
        end = offset + _RECORD_HEAD.size + length
        following = bisect.bisect_right(chunk_offsets, offset)
        next_chunk = chunk_offsets[following] if following < len(chunk_offsets) else None
        # Records never straddle a chunk start, so a record that does has a corrupt length.
        is_garbage = not chunk_offsets and scan.header is not None and opcode not in _KNOWN_OPCODES
        if end > size or (next_chunk is not None and end > next_chunk) or is_garbage:
            resume, which = next_chunk, "indexed"
            if resume is None:
                search_from = max(min(offset, previous_offset + 1), read_until)
                resume, which = _find_intact_chunk(stream, size, search_from), "intact"
            if resume is not None:
                scan.problems.append(
                    f"record at byte {offset} (opcode {opcode:#04x}) has a corrupt length ({length}); "
                    f"resumed at the next {which} chunk, byte {resume}"
                )
                scan.header = scan.header or _LOST_HEADER
                offset = resume
                stream.seek(offset)
                continue
            scan.problems.append(
                f"record at byte {offset} (opcode {opcode:#04x}) claims {length} bytes past the end of the "
                f"file (truncated or corrupt); reading stops there"
            )
            return
        if (
            log_range is not None
            and opcode == Opcode.CHUNK
            and scan.header is not None
            and length >= _CHUNK_TIMES.size
        ):
            first_ns, last_ns = _CHUNK_TIMES.unpack(stream.read(_CHUNK_TIMES.size))
            if last_ns < log_range[0] or first_ns > log_range[1]:
                scan.skipped_chunks += 1
                # Stepped over as if read: a resynchronisation after a corrupt record that follows must
                # not search from before it again (found intact, skipped again: it looped for ever).
                read_until = max(read_until, end)
                previous_offset, offset = offset, end
                stream.seek(offset)
                continue
            stream.seek(offset + _RECORD_HEAD.size)
        body = stream.read(length)
        if scan.header is None:
            problem = None
            if opcode != Opcode.HEADER:
                problem = f"first record has opcode {opcode:#04x}"
            else:
                try:
                    scan.header = Header.read(_body_stream(body))
                except _CHUNK_ERRORS as err:
                    problem = str(err)
            if problem is not None:
                # The header holds nothing the messages need: resume at the first chunk that is intact.
                resume = chunk_offsets[0] if chunk_offsets else _find_intact_chunk(stream, size, end)
                if resume is None:
                    raise RecordingError(f"{path}: header unreadable ({problem})")
                scan.problems.append(
                    f"header unreadable ({problem}); resumed at the first intact chunk, byte {resume}"
                )
                scan.header = _LOST_HEADER
                offset = resume
                stream.seek(offset)
                continue
        elif opcode == Opcode.CHUNK:
            try:
                chunk = Chunk.read(_body_stream(body))
                if chunk.uncompressed_size > MAX_CHUNK_BYTES:
                    raise ValueError(f"uncompressed size {chunk.uncompressed_size} is implausible")
                # CRC validation is what makes a flipped byte a skipped chunk instead of garbage data.
                records = breakup_chunk(chunk, validate_crc=True)
            except _CHUNK_ERRORS as err:
                scan.problems.append(f"chunk at byte {offset} unreadable, its messages are lost: {err}")
                records = []
            if records:
                read_until = end
            for record in records:
                if isinstance(record, Message):
                    scan.recovered += 1
                    yield record
                elif isinstance(record, Channel):
                    scan.channels.setdefault(record.id, record)
        elif opcode in (Opcode.CHANNEL, Opcode.MESSAGE):
            # Top-level copies: unchunked files (other writers), our writer's repeated definitions, and
            # the summary.
            try:
                if opcode == Opcode.MESSAGE:
                    message = Message.read(_body_stream(body), length)
                    scan.recovered += 1
                    yield message
                else:
                    channel = Channel.read(_body_stream(body))
                    # First definition wins; a chunk's copy (CRC-checked) wins over all of these.
                    scan.loose_channels.setdefault(channel.id, channel)
            except _CHUNK_ERRORS as err:
                scan.problems.append(f"record at byte {offset} (opcode {opcode:#04x}) unreadable: {err}")
        elif opcode == Opcode.FOOTER:
            # Only the last record (before the closing magic) is the footer; a footer opcode anywhere else
            # is a flipped byte, and taking it as the end would silently drop every later chunk.
            if end >= size - len(MCAP_MAGIC):
                scan.complete = True
                return
            scan.problems.append(
                f"record at byte {offset} has a footer's opcode but is not at the end of the file; skipped"
            )
        # Schemas, indexes, statistics, attachments, metadata: not needed to recover the messages.
        previous_offset, offset = offset, end


def _iter_file(
    path: Path, scan: _Scan, log_range: tuple[int, int] | None = None
) -> Iterator[tuple[Channel | None, Message]]:
    """(channel, message) for every message recovered from `path`, in file order.

    A message read before its channel definition (whose chunk-local record was lost) is held back and
    yielded at the end, once the summary may have supplied the channel; None when nothing ever did.
    """
    orphans: list[Message] = []
    try:
        with open(path, "rb") as stream:
            size = os.fstat(stream.fileno()).st_size
            for message in _scan_messages(stream, size, scan, path, log_range):
                channel = scan.channel(message.channel_id)
                if channel is None:
                    orphans.append(message)
                else:
                    yield channel, message
    except OSError as err:
        raise RecordingError(f"{path}: cannot read: {err.strerror or err}") from err
    for message in orphans:
        yield scan.channel(message.channel_id), message


@dataclass(frozen=True, slots=True)
class _Route:
    """What a topic is, once parsed: detections of (rsu, camera) or V2X of a station (key segment)."""

    is_detections: bool
    rsu_id: str
    name: str  # camera id, or the station id as written in the key


class _Decoder:
    """Turns messages into schema objects, counting rejections per topic (first error kept).

    Selection: rsu_id / camera_id / station_ids (None: all), `detections` / `v2x` switch a kind off,
    `stamp_range` keeps stamps (publish_time, then the payload's stamp_ns) inside [first, last], and
    `log_since_ns` keeps log times from there on. Unselected messages are skipped before any parsing.
    """

    def __init__(
        self,
        camera_id: str | None = None,
        rsu_id: str | None = None,
        station_ids: Collection[int] | None = None,
        *,
        detections: bool = True,
        v2x: bool = True,
        stamp_range: tuple[int, int] | None = None,
        log_since_ns: int | None = None,
    ) -> None:
        self.camera_id, self.rsu_id = camera_id, rsu_id
        # Compared as key text, so "v2x/cam/007" never passes for station 7 (its payload would not match).
        self.station_keys = None if station_ids is None else frozenset(str(s) for s in station_ids)
        self.want_detections, self.want_v2x = detections, v2x
        self.stamp_range = stamp_range
        self.log_since_ns = log_since_ns
        self.detections: dict[tuple[str, str], list[DetectionFrame]] = {}
        self.v2x: list[V2xPosition] = []
        self.rejected: Counter[str] = Counter()
        self.examples: dict[str, str] = {}
        self.topic_counts: Counter[str] = Counter()
        self._routes: dict[str, _Route | None] = {}

    def reject(self, topic: str, reason: str) -> None:
        self.rejected[topic] += 1
        self.examples.setdefault(topic, reason)

    def _route(self, topic: str) -> _Route | None:
        """The parsed topic when this decoder selects it, else None (cached per topic)."""
        if topic in self._routes:
            return self._routes[topic]
        route = None
        det = keys.parse_detections_key(topic)
        station = None if det else keys.parse_v2x_key(topic)
        if det is not None:
            rsu, cam = det
            if (
                self.want_detections
                and (self.rsu_id is None or rsu == self.rsu_id)
                and (self.camera_id is None or cam == self.camera_id)
            ):
                route = _Route(True, rsu, cam)
        elif (
            station is not None
            and self.want_v2x
            and (self.station_keys is None or station in self.station_keys)
        ):
            route = _Route(False, "", station)
        # Anything else is not an rsucal input channel: listed in `channels`, otherwise ignored.
        self._routes[topic] = route
        return route

    def selects(self, message: Message) -> bool:
        """Whether the message's times are wanted (checked before its channel is known)."""
        if self.stamp_range is not None and not (
            self.stamp_range[0] <= message.publish_time <= self.stamp_range[1]
        ):
            return False
        return self.log_since_ns is None or message.log_time >= self.log_since_ns

    def decode(self, channel: Channel, message: Message) -> DetectionFrame | V2xPosition | None:
        """The validated message, or None when it is not selected or rejected (counted)."""
        topic = channel.topic
        self.topic_counts[topic] += 1
        if not self.selects(message):
            return None
        route = self._route(topic)
        if route is None:
            return None
        if channel.message_encoding != "json":
            self.reject(topic, f"message_encoding {channel.message_encoding!r} is not json")
            return None
        decoded: DetectionFrame | V2xPosition
        if route.is_detections:
            try:
                decoded = decode_json(DetectionFrame, message.data)
            except ValidationError as err:
                self.reject(topic, describe_validation_error(err))
                return None
            if decoded.camera_id != route.name:
                self.reject(
                    topic, f"camera_id: {decoded.camera_id!r} does not match the key's camera {route.name!r}"
                )
                return None
        else:
            try:
                decoded = decode_json(V2xPosition, message.data)
            except ValidationError as err:
                self.reject(topic, describe_validation_error(err))
                return None
            if str(decoded.station_id) != route.name:
                self.reject(
                    topic, f"station_id: {decoded.station_id} does not match the key's {route.name!r}"
                )
                return None
        if self.stamp_range is not None and not (
            self.stamp_range[0] <= decoded.stamp_ns <= self.stamp_range[1]
        ):
            return None  # publish_time disagreed with the payload (another writer); the payload decides
        return decoded

    def add(self, channel: Channel | None, message: Message) -> None:
        if channel is None:
            if self.selects(message):
                self.reject("(unknown channel)", f"channel id {message.channel_id} has no channel record")
            return
        decoded = self.decode(channel, message)
        if isinstance(decoded, DetectionFrame):
            route = self._routes[channel.topic]
            assert route is not None
            self.detections.setdefault((route.rsu_id, route.name), []).append(decoded)
        elif decoded is not None:
            self.v2x.append(decoded)


def read_recording(
    path: Path, camera_id: str | None = None, rsu_id: str | None = None, station_id: int | None = None
) -> Recording:
    """Read the detections and V2X positions of an rsucal MCAP recording.

    Filters select one camera, one RSU or one V2X station. A recording holding several RSUs must name
    one (camera ids are only unique per RSU). Damage is reported in `problems`; RecordingError only when
    the file is not an MCAP, its header is unreadable, or it is damaged and nothing could be recovered.
    """
    path = Path(path)
    decoder = _Decoder(camera_id, rsu_id, None if station_id is None else (station_id,))
    scan = _Scan()
    for channel, message in _iter_file(path, scan):
        decoder.add(channel, message)
    damaged = bool(scan.problems) or not scan.complete
    if damaged and scan.recovered == 0:
        raise RecordingError(f"{path}: damaged and no message could be recovered: {'; '.join(scan.problems)}")

    rsu_ids = sorted({rsu for rsu, _ in decoder.detections})
    if rsu_id is None and len(rsu_ids) > 1:
        raise RecordingError(
            f"{path}: detections from several RSUs ({', '.join(rsu_ids)}); choose one with rsu_id"
        )
    detections: dict[str, list[DetectionFrame]] = {}
    for (_, cam), frames in decoder.detections.items():
        detections[cam] = sorted(frames, key=lambda f: f.stamp_ns)
    return Recording(
        path=path,
        rsu_id=rsu_id if rsu_id is not None else (rsu_ids[0] if rsu_ids else None),
        detections=detections,
        v2x=sorted(decoder.v2x, key=lambda m: (m.stamp_ns, m.station_id)),
        rejected=dict(decoder.rejected),
        rejection_examples=dict(decoder.examples),
        channels={topic: decoder.topic_counts[topic] for topic in scan.topics()},
        problems=tuple(scan.problems),
        complete=scan.complete,
    )


def read_images(
    files: Sequence[Path], rsu_id: str, camera_id: str, stamps: Collection[int], tolerance_ns: int = 1_000_000
) -> dict[int, bytes]:
    """The recorded image (compressed bytes) nearest each of `stamps` within `tolerance_ns`, by stamp.

    Reads foxglove.CompressedImage messages on keys.image_key(rsu_id, camera_id); stamps without an image
    are left out (most recordings hold none). Damaged files and undecodable messages are skipped.
    """
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from google.protobuf.message import DecodeError

    wanted = sorted(stamps)
    if not wanted:
        return {}
    topic = keys.image_key(rsu_id, camera_id)
    found: dict[int, tuple[int, bytes]] = {}  # wanted stamp -> (|dt|, image)
    low, high = wanted[0] - tolerance_ns, wanted[-1] + tolerance_ns
    for path in files:
        scan = _Scan()
        try:
            for channel, message in _iter_file(Path(path), scan):
                if channel is None or channel.topic != topic or not low <= message.publish_time <= high:
                    continue
                try:
                    image = CompressedImage.FromString(message.data)
                except DecodeError:
                    continue
                stamp_ns = (
                    image.timestamp.ToNanoseconds() if image.HasField("timestamp") else message.publish_time
                )
                i = bisect.bisect_left(wanted, stamp_ns)
                for j in (i - 1, i):
                    if 0 <= j < len(wanted) and abs(wanted[j] - stamp_ns) <= tolerance_ns:
                        distance = abs(wanted[j] - stamp_ns)
                        if wanted[j] not in found or distance < found[wanted[j]][0]:
                            found[wanted[j]] = (distance, bytes(image.data))
        except RecordingError as err:
            logger.warning("images: %s", err)
    return {stamp: image for stamp, (_, image) in found.items()}


# ---------------------------------------------------------------------------------------------- windows


@dataclass(frozen=True, slots=True)
class WindowData:
    """What read_window recovered: messages stamped inside the window, sorted by stamp, duplicates dropped.

    detections: sorted by (stamp_ns, camera_id); v2x: by (stamp_ns, station_id). problems: damage and
    unreadable files ("{path}: ..."), and a line per topic with rejected messages. rejected: messages in
    the window that failed validation. duplicates: messages dropped because the same key and stamp was
    already read (a replayed message); the first one read is kept.
    """

    detections: list[DetectionFrame]
    v2x: list[V2xPosition]
    problems: list[str]
    rejected: int
    duplicates: int = 0


def read_window(
    files: Sequence[Path],
    rsu_id: str,
    camera_id: str | None,
    station_ids: Collection[int] | None,
    start_ns: int,
    end_ns: int,
    *,
    max_stamp_skew_ns: int | None = None,
) -> WindowData:
    """Detections of `camera_id` (None: every camera of `rsu_id`) and V2X of `station_ids` (None: every
    station; empty: none) stamped in [start_ns, end_ns], merged across `files` (oldest first).

    Never raises for damaged or missing files: what can be recovered is returned (an unfinished or
    crashed last file up to its last complete chunk) and the rest is described in `problems`; the caller
    decides whether that is enough. `max_stamp_skew_ns`: when our receive time is known to be within this
    of the producer's stamp, chunks received entirely outside the widened window are not even
    decompressed; leave None for replays, whose stamps may lie anywhere.
    """
    if end_ns < start_ns:
        raise ValueError(f"window end_ns = {end_ns} is before start_ns = {start_ns}")
    decoder = _Decoder(camera_id, rsu_id, station_ids, stamp_range=(start_ns, end_ns))
    log_range = None
    if max_stamp_skew_ns is not None:
        log_range = (max(0, start_ns - max_stamp_skew_ns), end_ns + max_stamp_skew_ns)
    problems: list[str] = []
    for path in files:
        scan = _Scan()
        try:
            for channel, message in _iter_file(Path(path), scan, log_range):
                decoder.add(channel, message)
        except RecordingError as err:
            problems.append(str(err))
        problems.extend(f"{path}: {problem}" for problem in scan.problems)
    for topic, count in sorted(decoder.rejected.items()):
        problems.append(f"{topic}: {count} message(s) rejected, first: {decoder.examples[topic]}")

    frames = sorted(
        (frame for per_camera in decoder.detections.values() for frame in per_camera),
        key=lambda f: (f.stamp_ns, f.camera_id),
    )
    positions = sorted(decoder.v2x, key=lambda m: (m.stamp_ns, m.station_id))
    # Sorting is stable, so of two messages with the same key and stamp the first one read stays.
    detections = [
        f for i, f in enumerate(frames) if i == 0 or _detection_id(frames[i - 1]) != _detection_id(f)
    ]
    v2x = [m for i, m in enumerate(positions) if i == 0 or _v2x_id(positions[i - 1]) != _v2x_id(m)]
    return WindowData(
        detections=detections,
        v2x=v2x,
        problems=problems,
        rejected=sum(decoder.rejected.values()),
        duplicates=len(frames) - len(detections) + len(positions) - len(v2x),
    )


def _detection_id(frame: DetectionFrame) -> tuple[int, str]:
    return frame.stamp_ns, frame.camera_id


def _v2x_id(msg: V2xPosition) -> tuple[int, int]:
    return msg.stamp_ns, msg.station_id


def iter_v2x(
    files: Sequence[Path], station_ids: Collection[int] | None, since_ns: int
) -> Iterator[tuple[V2xPosition, int]]:
    """(message, received_ns) of every valid V2X position logged at received_ns >= since_ns.

    For rebuilding traversal state after a restart. `files` oldest first (list_recordings order); output
    in file order, which is log order for our recordings. `since_ns` is on our clock (log_time): whole
    files whose successor started before it are skipped by name, older chunks without decompressing.
    Damage and rejections are logged as warnings, never raised.
    """
    starts = [_recording_start_ns(Path(path)) for path in files]
    for i, path in enumerate(files):
        path = Path(path)
        successor = starts[i + 1] if i + 1 < len(starts) else None
        # Our files hold messages received before the next file starts (rotation by received time).
        if starts[i] is not None and successor is not None and successor <= since_ns:
            continue
        decoder = _Decoder(station_ids=station_ids, detections=False, log_since_ns=since_ns)
        scan = _Scan()
        try:
            for channel, message in _iter_file(path, scan, (since_ns, _MAX_U64)):
                if channel is None:
                    decoder.add(None, message)
                    continue
                decoded = decoder.decode(channel, message)
                if isinstance(decoded, V2xPosition):
                    yield decoded, message.log_time
        except RecordingError as err:
            logger.warning("V2X replay: %s", err)
        if scan.problems:
            logger.warning("V2X replay: %s: %s", path, "; ".join(scan.problems))
        for topic, count in sorted(decoder.rejected.items()):
            logger.warning(
                "V2X replay: %s: %d message(s) on %s rejected, first: %s",
                path,
                count,
                topic,
                decoder.examples[topic],
            )


# ---------------------------------------------------------------------------------------------- rotation

_RECORDING_NAME = re.compile(rf"^[{IDENTIFIER_CHARS}]{{1,{IDENTIFIER_MAX_LENGTH}}}-(\d{{19,20}})\.mcap$")
RETRY_AFTER_ERROR_S = 5.0  # after a failed write, messages are dropped (counted) this long before a new file


@dataclass(frozen=True, slots=True)
class RecordingFile:
    """One of the daemon's recordings: start_ns (from the name) is the receive time of its first message."""

    path: Path
    start_ns: int
    size_bytes: int


def recording_name(rsu_id: str, start_ns: int) -> str:
    """{rsu_id}-{start_ns:019d}.mcap: sorts by start time as text and as a number."""
    return f"{rsu_id}-{start_ns:019d}.mcap"


def _recording_start_ns(path: Path) -> int | None:
    match = _RECORDING_NAME.match(path.name)
    return int(match.group(1)) if match else None


def list_recordings(directory: Path, rsu_id: str) -> list[RecordingFile]:
    """The recordings of `rsu_id` in `directory`, oldest first; other files are ignored ([] if none)."""
    pattern = re.compile(rf"^{re.escape(rsu_id)}-(\d{{19,20}})\.mcap$")
    found: list[RecordingFile] = []
    try:
        entries = list(os.scandir(directory))
    except FileNotFoundError:
        return []
    for entry in entries:
        match = pattern.match(entry.name)
        if match is None:
            continue
        try:
            if not entry.is_file(follow_symlinks=False):
                continue
            size = entry.stat(follow_symlinks=False).st_size
        except FileNotFoundError:  # pruned by someone else meanwhile
            continue
        found.append(RecordingFile(Path(entry.path), int(match.group(1)), size))
    found.sort(key=lambda rec: (rec.start_ns, rec.path.name))
    return found


class RotatingRecorder:
    """The daemon's recording: every valid message, as received, in a series of rotated MCAP files.

    Files are {directory}/{rsu_id}-{start_received_ns:019d}.mcap, opened at the first message and rotated
    when they reach storage.rotate_bytes (bytes counted as written, not stat'ed; overshoot at most one
    chunk) or storage.rotate_s (our clock: received_ns when writing, clock.now_ns() in tick()), or would
    need more than MAX_CHANNELS channels. A file holds messages received before the next one starts.
    Payloads are logged as they arrived (already validated by the decoder, never re-serialised).
    tick() flushes every storage.flush_interval_s, so a crash loses at most that much. prune() applies
    retention. Owned by the ingest thread; the properties may be read from others.

    A failing disk never raises out of write_*: the file is abandoned (readable up to its last complete
    chunk), the error logged (last_error), and messages are dropped for RETRY_AFTER_ERROR_S before a new
    file is tried. messages_dropped counts those and the messages of the chunk that failed.

    With storage.foxglove_views, each message also gets its Foxglove view in the same file (daemon.foxglove:
    LocationFix per station, ImageAnnotations per camera; results with write_result). Views are not counted
    in messages_written or messages_dropped, which count the messages received.
    """

    def __init__(self, directory: Path, rsu_id: str, storage: StorageConfig, clock: Clock) -> None:
        if not IDENTIFIER.match(rsu_id):
            raise ValueError(f"rsu_id {rsu_id!r} is not a valid key segment ([A-Za-z0-9_.-], 1-64 chars)")
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.rsu_id = rsu_id
        self.storage = storage
        self._clock = clock
        self._rotate_ns = int(storage.rotate_s * 1e9)
        self._flush_ns = int(storage.flush_interval_s * 1e9)
        self._writer: RecordingWriter | None = None
        self._file_start_ns = 0
        self._file_opened_ns = 0  # our clock when the open file was created
        self._last_flush_ns = 0
        self._dirty = False  # messages written since the last flush
        self._closed = False
        self._retry_at_ns: int | None = None
        self._detection_keys: dict[str, tuple[str, str]] = {}  # camera_id -> (raw key, annotations topic)
        self._views = storage.foxglove_views
        self._bytes_finished = 0
        self.files_written = 0
        self.messages_written = 0
        self.messages_dropped = 0
        self.last_error: str | None = None

    @property
    def current_path(self) -> Path | None:
        """The open file (None before the first message, after a rotation until the next, after close)."""
        return self._writer.path if self._writer is not None else None

    @property
    def bytes_written(self) -> int:
        """Bytes written to all files by this recorder (the open chunk not included)."""
        writer = self._writer
        return self._bytes_finished + (writer.bytes_written if writer is not None else 0)

    def write_detections(
        self,
        camera_id: str,
        stamp_ns: int,
        received_ns: int,
        payload: bytes,
        boxes: Sequence[Mapping[str, object]] | None = None,
    ) -> None:
        """Log a validated DetectionFrame payload on rsu/{rsu_id}/camera/{camera_id}/detections and, given its
        `boxes` (x1, y1, x2, y2 px) and with views on, their foxglove.ImageAnnotations beside it."""
        keys = self._detection_keys.get(camera_id)
        if keys is None:
            keys = self._detection_key(camera_id)
        if (
            self._write(keys[0], DetectionFrame, stamp_ns, received_ns, payload)
            and boxes is not None
            and self._views
        ):
            view = foxglove.image_annotations(stamp_ns, boxes)
            self._write_view(keys[1], foxglove.IMAGE_ANNOTATIONS, view, received_ns, stamp_ns)

    def write_v2x(
        self,
        station_id: int,
        stamp_ns: int,
        received_ns: int,
        payload: bytes,
        message: V2xPosition | None = None,
        is_vehicle: bool = False,
    ) -> None:
        """Log a validated V2xPosition payload on v2x/cam/{station_id} and, given the decoded `message` and
        with views on, its foxglove.LocationFix on v2x/cam/{station_id}/location (calibration vehicles in
        their own colour)."""
        if self._write(keys.v2x_key(station_id), V2xPosition, stamp_ns, received_ns, payload) and (
            message is not None and self._views
        ):
            view = foxglove.location_fix(message, is_vehicle)
            self._write_view(
                keys.location_topic(station_id), foxglove.LOCATION_FIX, view, received_ns, stamp_ns
            )

    def write_result(self, result: CalibrationResult, received_ns: int) -> None:
        """Log a finished job's result on .../calibration and, with a pose and views on, its FrameTransform,
        origin and CameraCalibration (write_result_views); not counted as a received message."""
        if self._views:
            write_result_views(self._write_view, result, received_ns)
        else:
            payload = result.model_dump_json().encode("utf-8")
            key = keys.calibration_key(result.rsu_id, result.camera_id)
            self._write_view(key, CalibrationResult, payload, received_ns, received_ns)

    def write_vehicle_boxes(
        self,
        camera_id: str,
        boxes: Sequence[tuple[int, float, float, float, float]],
        received_ns: int,
    ) -> int:
        """Log the calibration vehicle's boxes as a finished job identified them (stamp_ns, x1, y1, x2, y2),
        one foxglove.ImageAnnotations per frame on .../calibration/annotations, in the vehicle's colour, so
        that Foxglove shows them over the camera's detections. With views off, nothing; returns the frames
        written."""
        if not self._views or not boxes:
            return 0
        topic = keys.calibration_annotations_topic(self.rsu_id, camera_id)
        by_stamp: dict[int, list[tuple[float, float, float, float]]] = {}
        for stamp_ns, x1, y1, x2, y2 in boxes:
            by_stamp.setdefault(stamp_ns, []).append((x1, y1, x2, y2))
        for stamp_ns in sorted(by_stamp):
            view = foxglove.image_annotations(stamp_ns, (), by_stamp[stamp_ns])
            self._write_view(topic, foxglove.IMAGE_ANNOTATIONS, view, received_ns, stamp_ns)
        return len(by_stamp)

    def tick(self) -> None:
        """Rotate a file older than rotate_s, else flush when flush_interval_s has passed since the last."""
        writer = self._writer
        if writer is None:
            return
        now_ns = self._clock.now_ns()
        # Measured from when the file was opened, not from its first receive time: during an inbox backlog
        # the messages written are older than now, and a file started by one of them would rotate at once.
        if now_ns - self._file_opened_ns >= self._rotate_ns:
            self._finish_current()
        elif self._dirty and now_ns - self._last_flush_ns >= self._flush_ns:
            self._flush(writer, now_ns)

    def flush(self) -> None:
        """End the open chunk and fsync now, e.g. before a job reads the open file."""
        if self._writer is not None and self._dirty:
            self._flush(self._writer, self._clock.now_ns())

    def prune(self, keep_after_ns: int | None = None) -> list[Path]:
        """Delete the oldest recordings beyond storage.retention_bytes (all files) or retention_s; the paths.

        Never the open file, nor a file that may hold messages received after `keep_after_ns` (a
        collection window still to be read: a file's data ends where the next file starts). Times are our
        receive times, so pass a window start minus any expected stamp-to-receive difference.
        """
        now_ns = self._clock.now_ns()
        retention_ns = int(self.storage.retention_s * 1e9)
        recordings = list_recordings(self.directory, self.rsu_id)
        open_path = self.current_path
        sizes = [rec.size_bytes for rec in recordings]
        for i, rec in enumerate(recordings):
            if rec.path == open_path and self._writer is not None:
                sizes[i] = max(rec.size_bytes, self._writer.bytes_written)
        total_bytes = sum(sizes)
        pruned: list[Path] = []
        for i, rec in enumerate(recordings):
            if rec.path == open_path:
                continue
            # The last file's end is unknown (a previous run): treat it as receiving until now.
            data_end_ns = recordings[i + 1].start_ns if i + 1 < len(recordings) else now_ns
            if keep_after_ns is not None and data_end_ns > keep_after_ns:
                break  # this and every newer file may hold the window
            too_old = now_ns - data_end_ns > retention_ns
            if not too_old and total_bytes <= self.storage.retention_bytes:
                break  # oldest first: every newer file is younger, and the total only shrinks
            try:
                rec.path.unlink()
            except FileNotFoundError:
                pass
            except OSError as err:
                logger.warning("cannot delete recording %s: %s", rec.path, err)
                continue
            total_bytes -= sizes[i]
            pruned.append(rec.path)
        if pruned:
            logger.info(
                "pruned %d recording(s), %d bytes of recordings left in %s",
                len(pruned),
                total_bytes,
                self.directory,
            )
        return pruned

    def close(self) -> None:
        """Finish the open file (summary and footer). Idempotent; writing afterwards raises RecordingError."""
        self._closed = True
        self._finish_current()

    def __enter__(self) -> RotatingRecorder:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _detection_key(self, camera_id: str) -> tuple[str, str]:
        if not IDENTIFIER.match(camera_id):
            raise ValueError(
                f"camera_id {camera_id!r} is not a valid key segment ([A-Za-z0-9_.-], 1-64 chars)"
            )
        if len(self._detection_keys) >= 4096:  # bounded: camera ids come from outside (validated, though)
            self._detection_keys.clear()
        pair = self._detection_keys[camera_id] = (
            keys.detections_key(self.rsu_id, camera_id),
            keys.annotations_topic(self.rsu_id, camera_id),
        )
        return pair

    def _write_view(
        self, key: str, schema: ChannelSchema, payload: bytes, received_ns: int, stamp_ns: int
    ) -> None:
        """Append a view (or a result) to the open file, opening one if needed; failures as in _write, but
        never counted as received messages."""
        writer = self._writer
        if writer is None or (writer.channel_count >= MAX_CHANNELS and not writer.has_channel(key)):
            writer = self._rotate(received_ns)
            if writer is None:
                return
        try:
            writer.write_raw(key, schema, payload, received_ns, stamp_ns, is_view=True)
        except OSError as err:
            self._fail(writer, err, received_ns)
            return
        self._dirty = True
        if writer.bytes_written >= self.storage.rotate_bytes:
            self._finish_current()

    def _write(self, key: str, model: ChannelSchema, stamp_ns: int, received_ns: int, payload: bytes) -> bool:
        """Log a received message; whether it was written (not dropped)."""
        # The hot path (>= 20,000 messages/s): int compares, one dict lookup, then the writer's append.
        writer = self._writer
        if (
            writer is None
            or received_ns - self._file_start_ns >= self._rotate_ns
            or (writer.channel_count >= MAX_CHANNELS and not writer.has_channel(key))
        ):
            writer = self._rotate(received_ns)
            if writer is None:
                self.messages_dropped += 1
                return False
        written_before = writer.messages_written
        try:
            writer.write_raw(key, model, payload, received_ns, stamp_ns)
        except OSError as err:
            # Raised while writing a full chunk (this message in it) or, rarely, a channel record (not).
            self.messages_dropped += writer.messages_written == written_before
            self._fail(writer, err, received_ns)
            return False
        self.messages_written += 1
        self._dirty = True
        if writer.bytes_written >= self.storage.rotate_bytes:
            self._finish_current()
            return False  # the view would open the next file on its own: it follows its message or nothing
        return True

    def _rotate(self, received_ns: int) -> RecordingWriter | None:
        """Finish the open file (if any) and open the next; None while paused after a write error."""
        if self._closed:
            raise RecordingError(f"{self.directory}: recorder closed; nothing more can be written")
        self._finish_current()
        if self._retry_at_ns is not None:
            if received_ns < self._retry_at_ns:
                return None
            self._retry_at_ns = None
        start_ns = max(received_ns, 0)
        # Names are unique: two files starting in the same nanosecond (a fake clock, the channel limit)
        # get consecutive start times.
        while (self.directory / recording_name(self.rsu_id, start_ns)).exists():
            start_ns += 1
        path = self.directory / recording_name(self.rsu_id, start_ns)
        try:
            writer = RecordingWriter(path, self.storage.compression, chunk_size=self.storage.chunk_bytes)
            fsync_dir(self.directory)
        except OSError as err:
            self._retry_at_ns = received_ns + int(RETRY_AFTER_ERROR_S * 1e9)
            self.last_error = f"{path}: cannot create: {err}"
            logger.error("recording paused for %.0f s: %s", RETRY_AFTER_ERROR_S, self.last_error)
            return None
        self._writer = writer
        self._file_start_ns = received_ns
        self._file_opened_ns = self._clock.now_ns()
        self._last_flush_ns = self._clock.now_ns()
        self._dirty = False
        self.files_written += 1
        logger.info("recording to %s", path)
        return writer

    def _flush(self, writer: RecordingWriter, now_ns: int) -> None:
        try:
            writer.flush()
        except OSError as err:
            self._fail(writer, err, now_ns)
            return
        self._dirty = False
        self._last_flush_ns = now_ns

    def _finish_current(self) -> None:
        writer = self._writer
        if writer is None:
            return
        self._writer = None
        try:
            writer.finish()
        except OSError as err:
            self.messages_dropped += writer.pending_messages
            self.last_error = f"{writer.path}: cannot finish: {err}"
            logger.error("%s (readable up to its last complete chunk)", self.last_error)
        self._bytes_finished += writer.bytes_written
        self._dirty = False

    def _fail(self, writer: RecordingWriter, err: OSError, now_ns: int) -> None:
        """A write or flush failed (disk full, I/O error): abandon the file, pause, carry on."""
        self._writer = None
        self.messages_dropped += writer.pending_messages  # the chunk being written is lost with the file
        writer.abandon()
        self._bytes_finished += writer.bytes_written
        self._dirty = False
        self._retry_at_ns = now_ns + int(RETRY_AFTER_ERROR_S * 1e9)
        self.last_error = f"{writer.path}: {err}"
        logger.error(
            "recording paused for %.0f s after a write error: %s (file kept up to its last complete chunk)",
            RETRY_AFTER_ERROR_S,
            self.last_error,
        )
