"""A small real recording to damage, and what each of its chunks holds.

The recording is the simulator's carla-like scene (seed 0) thinned to ~500 messages (every 10th camera
frame, every 50th V2X position) and written by daemon.recording.RecordingWriter in 4 KiB chunks, so a
~125 KB file has ~60 chunks: enough that "only the damaged chunk is lost" means something, small enough
to read thousands of times (~10 ms each). The same thinned scene still calibrates (exit 0), so
`rsucal calibrate` is exercised on damaged files that remain usable as well as on hopeless ones.
"""

from __future__ import annotations

import functools
import io
import json
import struct
from dataclasses import dataclass
from pathlib import Path

from fuzzing import scratch_dir
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk

from daemon.keys import detections_key, v2x_key
from daemon.recording import SIM_DETECTION_LATENCY_NS, SIM_V2X_LATENCY_NS, RecordingWriter, recording_name
from sim.files import write_simulation_files
from sim.simulate import SimulationResult, simulate

CHUNK_BYTES = 4096
DETECTION_EVERY = 10
V2X_EVERY = 50

# A message, as the readers return it: ("det", camera_id, stamp_ns) or ("v2x", station_id, stamp_ns).
MessageId = tuple[str, str | int, int]


@dataclass(frozen=True)
class Recorded:
    """One message of the intact recording: its id, receive time (log_time) and stamp."""

    id: MessageId
    log_ns: int
    stamp_ns: int


@dataclass(frozen=True)
class SmallRecording:
    """The intact recording (bytes and a copy on disk) and, per chunk, its byte range and messages."""

    data: bytes
    path: Path
    rsu_id: str
    camera_yaml: Path
    vehicle_yaml: Path
    chunk_ranges: tuple[tuple[int, int], ...]  # [start, end) of each chunk record, file order
    chunk_messages: tuple[tuple[Recorded, ...], ...]

    @property
    def record_starts(self) -> list[int]:
        """Offsets of every top-level record (opcode byte) of the intact file, footer included."""
        starts, offset = [], 8
        while offset + 9 <= len(self.data) - 8:
            starts.append(offset)
            (length,) = struct.unpack_from("<Q", self.data, offset + 1)
            offset += 9 + length
        return starts

    @property
    def summary_start(self) -> int:
        """Where the summary section starts (from the footer: opcode, length, summary_start u64, ...)."""
        (start,) = struct.unpack_from("<Q", self.data, len(self.data) - 8 - 29 + 9)
        return int(start)

    @property
    def header_end(self) -> int:
        """Where the header record (after the 8 magic bytes) ends."""
        (length,) = struct.unpack_from("<Q", self.data, 9)
        return 8 + 9 + length

    @property
    def messages(self) -> list[Recorded]:
        return [m for chunk in self.chunk_messages for m in chunk]

    def damaged_chunks(self, offsets: list[int]) -> set[int]:
        """Chunks whose record holds any of the byte offsets."""
        return {i for i, (start, end) in enumerate(self.chunk_ranges) for o in offsets if start <= o < end}

    def kept(self, damaged: set[int], cut: int | None = None) -> list[Recorded]:
        """Messages of the chunks that are neither damaged nor cut off (a chunk must end before `cut`)."""
        return [
            m
            for i, ((_, end), chunk) in enumerate(zip(self.chunk_ranges, self.chunk_messages, strict=True))
            if i not in damaged and (cut is None or end <= cut)
            for m in chunk
        ]


def _message_id(data: bytes) -> MessageId:
    doc = json.loads(data)
    if "camera_id" in doc:
        return ("det", doc["camera_id"], doc["stamp_ns"])
    return ("v2x", doc["station_id"], doc["stamp_ns"])


def _chunk_contents(data: bytes) -> tuple[tuple[tuple[int, int], ...], tuple[tuple[Recorded, ...], ...]]:
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None
    ranges, contents = [], []
    for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        start = index.chunk_start_offset
        (length,) = struct.unpack_from("<Q", data, start + 1)  # opcode u8, then the record length u64
        chunk = Chunk.read(ReadDataStream(io.BytesIO(data[start + 9 : start + 9 + length])))
        ranges.append((start, start + index.chunk_length))
        contents.append(
            tuple(
                Recorded(_message_id(r.data), r.log_time, r.publish_time)
                for r in breakup_chunk(chunk)
                if isinstance(r, Message)
            )
        )
    return tuple(ranges), tuple(contents)


@functools.cache
def simulation() -> SimulationResult:
    """The scene every MCAP and toolbox-pair fuzz test starts from (simulated once per process)."""
    return simulate("carla-like", 0, ideal=True)


@functools.cache
def small_recording() -> SmallRecording:
    """Simulate, thin and record the scene once per process (with camera.yaml and vehicle.yaml).

    A function rather than a fixture: Hypothesis prints a test's fixtures with a failing example."""
    sim = simulation()
    directory = scratch_dir("rsucal-fuzz-mcap-")
    entries = []
    for camera_id, frames in sim.detections.items():
        key = detections_key(sim.rsu_id, camera_id)
        entries += [
            (f.stamp_ns + SIM_DETECTION_LATENCY_NS, f.stamp_ns, key, f) for f in frames[::DETECTION_EVERY]
        ]
    entries += [
        (m.stamp_ns + SIM_V2X_LATENCY_NS, m.stamp_ns, v2x_key(m.station_id), m) for m in sim.v2x[::V2X_EVERY]
    ]
    entries.sort(key=lambda e: e[:2])
    path = directory / recording_name(sim.rsu_id, entries[0][0])
    with RecordingWriter(path, chunk_size=CHUNK_BYTES) as writer:
        for log_ns, stamp_ns, key, message in entries:
            writer.write(key, message, received_ns=log_ns, stamp_ns=stamp_ns)
    write_simulation_files(sim, directory)  # camera.yaml and vehicle.yaml for `rsucal calibrate`
    data = path.read_bytes()
    ranges, contents = _chunk_contents(data)
    recording = SmallRecording(
        data=data,
        path=path,
        rsu_id=sim.rsu_id,
        camera_yaml=directory / "camera.yaml",
        vehicle_yaml=directory / "vehicle.yaml",
        chunk_ranges=ranges,
        chunk_messages=contents,
    )
    assert len(recording.messages) == len(entries) and len(ranges) > 30
    return recording
