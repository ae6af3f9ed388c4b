"""MCAP recordings: the daemon's log of every valid incoming message and the offline/simulated input format.

Layout (DESIGN.md): one channel per key expression, message_encoding "json", schema "jsonschema" from the
pydantic model, log_time = receive ns, publish_time = stamp_ns; chunked, zstd. This is the only module
that imports mcap. Reading is deliberately forgiving: a truncated or partly corrupted file yields every
message that can still be proven intact (chunk CRCs), and bad messages are counted, never fatal.
"""

from __future__ import annotations

import bisect
import io
import json
import os
import re
import struct
import zlib
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, TYPE_CHECKING, Literal

import mcap
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, Header, Message
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer
from pydantic import BaseModel, ValidationError

from daemon import __version__
from pipeline.errors import RecordingError
from schemas.common import decode_json, describe_validation_error
from schemas.messages import DetectionFrame, V2xPosition

if TYPE_CHECKING:
    from pipeline.simulate import SimulationResult

try:
    from zstandard import ZstdError as _ZstdError
except ImportError:  # mcap without zstd support reports UnsupportedCompressionError (an McapError) instead
    _ZstdError = McapError  # type: ignore[assignment, misc]

MCAP_MAGIC = b"\x89MCAP0\r\n"
DEFAULT_CHUNK_SIZE = 1024 * 1024
MAX_CHANNELS = 65_535  # channel ids are uint16 in the MCAP record; mcap's writer numbers them from 1
# Simulated transport + processing delays: the receive time a daemon would have logged.
SIM_DETECTION_LATENCY_NS = 30_000_000
SIM_V2X_LATENCY_NS = 20_000_000

_IDENTIFIER = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")  # schemas.common.Identifier: safe in a Zenoh key
_DETECTIONS_TOPIC = re.compile(r"^rsu/([^/]+)/camera/([^/]+)/detections$")
_V2X_TOPIC = re.compile(r"^v2x/cam/([^/]+)$")
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, record length (MCAP spec)
_FOOTER = struct.Struct("<BQQQI")  # head, summary_start, summary_offset_start, summary_crc

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
_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


def detections_key(rsu_id: str, camera_id: str) -> str:
    """Bus key (and MCAP topic) of a camera's detections."""
    return f"rsu/{rsu_id}/camera/{camera_id}/detections"


def v2x_key(station_id: int) -> str:
    """Bus key (and MCAP topic) of a station's V2X positions."""
    return f"v2x/cam/{station_id}"


# ---------------------------------------------------------------------------------------------- writing


class RecordingWriter:
    """Appends validated messages to a new MCAP file; one instance per file, owned by one thread.

    Channels are registered on first use of a key expression, schemas once per model. Use as a context
    manager (or call finish()) so the summary and indexes are written; a file that was never finished is
    still readable up to its last complete chunk (see read_recording), and flush() bounds that loss.
    """

    def __init__(
        self,
        path: Path,
        compression: Compression = "zstd",
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        overwrite: bool = False,
    ) -> None:
        if compression not in _COMPRESSION:
            raise ValueError(f"compression {compression!r} is not one of {', '.join(_COMPRESSION)}")
        self.path = Path(path)
        # Exclusive by default: a recording already on disk is evidence, never silently replaced.
        try:
            self._file: IO[bytes] = open(self.path, "wb" if overwrite else "xb")  # noqa: SIM115 - see finish()
        except FileExistsError as err:
            raise RecordingError(f"{self.path}: already exists; recordings are never overwritten") from err
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=_COMPRESSION[compression])
        self._writer.start(profile="", library=f"rsucal {__version__}; python mcap {mcap.__version__}")
        self._schema_ids: dict[type[BaseModel], int] = {}
        self._channel_ids: dict[str, int] = {}
        self._sequences: Counter[int] = Counter()
        self.messages_written = 0
        self._finished = False

    @property
    def channel_count(self) -> int:
        """Channels registered so far; MCAP channel ids are uint16, so rotate well before MAX_CHANNELS."""
        return len(self._channel_ids)

    def write(self, key: str, message: BaseModel, received_ns: int, stamp_ns: int) -> None:
        """Log one message under its key expression: log_time = received_ns, publish_time = stamp_ns."""
        if self._finished:
            raise RecordingError(f"{self.path}: recording already finished")
        if received_ns < 0 or stamp_ns < 0:
            raise ValueError(f"MCAP times are unsigned: received_ns={received_ns}, stamp_ns={stamp_ns}")
        channel_id = self._channel_ids.get(key)
        if channel_id is None:
            channel_id = self._register_channel(key, type(message))
        self._sequences[channel_id] += 1
        self._writer.add_message(
            channel_id=channel_id,
            log_time=received_ns,
            publish_time=stamp_ns,
            data=message.model_dump_json().encode("utf-8"),
            sequence=self._sequences[channel_id] & 0xFFFFFFFF,  # uint32 in the record
        )
        self.messages_written += 1

    def write_detections(self, rsu_id: str, frame: DetectionFrame, received_ns: int) -> None:
        """Log a DetectionFrame on rsu/{rsu_id}/camera/{frame.camera_id}/detections."""
        if not _IDENTIFIER.match(rsu_id):
            raise ValueError(f"rsu_id {rsu_id!r} is not a valid key segment ([A-Za-z0-9_.-], 1-64 chars)")
        self.write(detections_key(rsu_id, frame.camera_id), frame, received_ns, frame.stamp_ns)

    def write_v2x(self, msg: V2xPosition, received_ns: int) -> None:
        """Log a V2xPosition on v2x/cam/{msg.station_id}."""
        self.write(v2x_key(msg.station_id), msg, received_ns, msg.stamp_ns)

    def flush(self) -> None:
        """Close the open chunk and fsync, so a crash after this loses nothing already written.

        Each flush ends a chunk early (worse compression); call it on a timer, not per message.
        """
        self._writer.flush()  # type: ignore[no-untyped-call]
        os.fsync(self._file.fileno())

    def finish(self) -> None:
        """Write the last chunk, the summary and the footer, then close the file. Idempotent."""
        if self._finished:
            return
        self._finished = True
        try:
            self._writer.finish()  # type: ignore[no-untyped-call]
            self._file.flush()
            os.fsync(self._file.fileno())
        finally:
            self._file.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        # Finish even when the body raised: everything logged so far stays readable.
        self.finish()

    def _register_channel(self, key: str, model: type[BaseModel]) -> int:
        if len(self._channel_ids) >= MAX_CHANNELS:
            # Every V2X station is a channel; a file must be rotated before the uint16 ids run out.
            raise RecordingError(f"{self.path}: {MAX_CHANNELS} channels in one recording; rotate the file")
        schema_id = self._schema_ids.get(model)
        if schema_id is None:
            schema_id = self._writer.register_schema(
                name=f"rsucal.{model.__name__}",
                encoding="jsonschema",
                data=json.dumps(model.model_json_schema(), separators=(",", ":")).encode("utf-8"),
            )
            self._schema_ids[model] = schema_id
        channel_id: int = self._writer.register_channel(
            topic=key, message_encoding="json", schema_id=schema_id
        )
        self._channel_ids[key] = channel_id
        return channel_id


def write_simulation_mcap(result: SimulationResult, path: Path) -> Path:
    """Write a simulation as the daemon would have recorded it, in log-time order; returns `path`.

    Every camera's detections are logged 30 ms after their stamp, every V2X message 20 ms after.
    """
    path = Path(path)
    entries: list[tuple[int, int, int, str, BaseModel]] = []  # (log_time, kind, stamp, key, message)
    for camera_id, frames in result.detections.items():
        key = detections_key(result.rsu_id, camera_id)
        for frame in frames:
            entries.append((frame.stamp_ns + SIM_DETECTION_LATENCY_NS, 0, frame.stamp_ns, key, frame))
    for msg in result.v2x:
        entries.append((msg.stamp_ns + SIM_V2X_LATENCY_NS, 1, msg.stamp_ns, v2x_key(msg.station_id), msg))
    # Sort on the numeric fields only (messages are not orderable); ties keep camera, then V2X, order.
    entries.sort(key=lambda entry: entry[:3])
    with RecordingWriter(path, overwrite=True) as writer:
        for log_time, _, stamp_ns, key, message in entries:
            writer.write(key, message, received_ns=log_time, stamp_ns=stamp_ns)
    return path


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
    """Records recovered by the linear scan; messages are yielded separately as they are found."""

    header: Header | None = None
    channels: dict[int, Channel] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    complete: bool = False


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


def _scan_messages(stream: IO[bytes], size: int, scan: _Scan, path: Path) -> Iterator[Message]:
    """Walk the records of an MCAP file front to back, yielding every message that can be trusted.

    mcap's own readers stop at the first damaged byte (and the seeking reader needs the footer), so a
    crash-truncated recording would read as nothing. Here each record is framed by its length alone: a
    chunk whose CRC or decompression fails is skipped with a problem noted. A corrupt length field breaks
    the framing; reading then resumes at the next chunk listed in a CRC-verified summary, or stops
    there when the file has none (truncated, unfinished).
    """
    if stream.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
        raise RecordingError(f"{path}: not an MCAP file (bad magic bytes)")
    chunk_offsets = _verified_chunk_offsets(stream, size)
    offset = len(MCAP_MAGIC)
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
        if end > size or (next_chunk is not None and end > next_chunk):
            if scan.header is not None and next_chunk is not None:
                scan.problems.append(
                    f"record at byte {offset} (opcode {opcode:#04x}) has a corrupt length ({length}); "
                    f"resumed at the next indexed chunk, byte {next_chunk}"
                )
                offset = next_chunk
                stream.seek(offset)
                continue
            scan.problems.append(
                f"record at byte {offset} (opcode {opcode:#04x}) claims {length} bytes past the end of the "
                f"file (truncated or corrupt); reading stops there"
            )
            return
        body = stream.read(length)
        if scan.header is None:
            if opcode != Opcode.HEADER:
                raise RecordingError(f"{path}: header unreadable (first record has opcode {opcode:#04x})")
            try:
                scan.header = Header.read(_body_stream(body))
            except _CHUNK_ERRORS as err:
                raise RecordingError(f"{path}: header unreadable ({err})") from err
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
            for record in records:
                if isinstance(record, Message):
                    yield record
                elif isinstance(record, Channel):
                    scan.channels.setdefault(record.id, record)
        elif opcode in (Opcode.CHANNEL, Opcode.MESSAGE):
            # Unchunked files (other writers) keep these at top level; the summary repeats the channels.
            try:
                if opcode == Opcode.MESSAGE:
                    yield Message.read(_body_stream(body), length)
                else:
                    channel = Channel.read(_body_stream(body))
                    # First definition wins: a chunk's copy is CRC-checked, the summary's may not be.
                    scan.channels.setdefault(channel.id, channel)
            except _CHUNK_ERRORS as err:
                scan.problems.append(f"record at byte {offset} (opcode {opcode:#04x}) unreadable: {err}")
        elif opcode == Opcode.FOOTER:
            scan.complete = True
            return
        # Schemas, indexes, statistics, attachments, metadata: not needed to recover the messages.
        offset = end


class _Decoder:
    """Turns messages into schema objects, counting rejections per topic (first error kept)."""

    def __init__(self, camera_id: str | None, rsu_id: str | None, station_id: int | None) -> None:
        self.camera_id, self.rsu_id, self.station_id = camera_id, rsu_id, station_id
        self.detections: dict[tuple[str, str], list[DetectionFrame]] = {}
        self.v2x: list[V2xPosition] = []
        self.rejected: Counter[str] = Counter()
        self.examples: dict[str, str] = {}
        self.topic_counts: Counter[str] = Counter()

    def reject(self, topic: str, reason: str) -> None:
        self.rejected[topic] += 1
        self.examples.setdefault(topic, reason)

    def add(self, channel: Channel, message: Message) -> None:
        topic = channel.topic
        self.topic_counts[topic] += 1
        det = _DETECTIONS_TOPIC.match(topic)
        v2x = None if det else _V2X_TOPIC.match(topic)
        if det is not None:
            rsu, cam = det.groups()
            if (self.rsu_id is not None and rsu != self.rsu_id) or (
                self.camera_id is not None and cam != self.camera_id
            ):
                return
        elif v2x is not None:
            if self.station_id is not None and v2x.group(1) != str(self.station_id):
                return
        else:
            return  # not an rsucal input channel: listed in `channels`, otherwise ignored
        if channel.message_encoding != "json":
            self.reject(topic, f"message_encoding {channel.message_encoding!r} is not json")
            return
        if det is not None:
            try:
                frame = decode_json(DetectionFrame, message.data)
            except ValidationError as err:
                self.reject(topic, describe_validation_error(err))
                return
            if frame.camera_id != cam:
                self.reject(topic, f"camera_id: {frame.camera_id!r} does not match the key's camera {cam!r}")
                return
            self.detections.setdefault((rsu, cam), []).append(frame)
        else:
            assert v2x is not None
            try:
                msg = decode_json(V2xPosition, message.data)
            except ValidationError as err:
                self.reject(topic, describe_validation_error(err))
                return
            if str(msg.station_id) != v2x.group(1):
                self.reject(topic, f"station_id: {msg.station_id} does not match the key's {v2x.group(1)!r}")
                return
            self.v2x.append(msg)


def read_recording(
    path: Path, camera_id: str | None = None, rsu_id: str | None = None, station_id: int | None = None
) -> Recording:
    """Read the detections and V2X positions of an rsucal MCAP recording.

    Filters select one camera, one RSU or one V2X station. A recording holding several RSUs must name
    one (camera ids are only unique per RSU). Damage is reported in `problems`; RecordingError only when
    the file is not an MCAP, its header is unreadable, or it is damaged and nothing could be recovered.
    """
    path = Path(path)
    decoder = _Decoder(camera_id, rsu_id, station_id)
    scan = _Scan()
    orphans: list[Message] = []  # messages whose channel record was not (yet) seen
    recovered = 0
    try:
        with open(path, "rb") as stream:
            size = os.fstat(stream.fileno()).st_size
            for message in _scan_messages(stream, size, scan, path):
                recovered += 1
                channel = scan.channels.get(message.channel_id)
                if channel is None:
                    orphans.append(message)
                else:
                    decoder.add(channel, message)
    except OSError as err:
        raise RecordingError(f"{path}: cannot read: {err.strerror or err}") from err
    # Channels are repeated in the summary, so a message whose chunk-local channel record was lost may
    # still be placed once the whole file has been read.
    for message in orphans:
        channel = scan.channels.get(message.channel_id)
        if channel is None:
            decoder.reject("(unknown channel)", f"channel id {message.channel_id} has no channel record")
        else:
            decoder.add(channel, message)
    damaged = bool(scan.problems) or not scan.complete
    if damaged and recovered == 0:
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
        channels={ch.topic: decoder.topic_counts[ch.topic] for ch in scan.channels.values()},
        problems=tuple(scan.problems),
        complete=scan.complete,
    )
