"""daemon.recording: RotatingRecorder (rotation, flush, retention, write errors, kill -9) and window reads."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader

from daemon import recording
from daemon.keys import detections_key, v2x_key
from daemon.recording import (
    RETRY_AFTER_ERROR_S,
    RecordingFile,
    RecordingWriter,
    RotatingRecorder,
    iter_v2x,
    list_recordings,
    read_recording,
    read_window,
    recording_name,
)
from pipeline.errors import RecordingError
from schemas.common import Box
from schemas.config import StorageConfig
from schemas.messages import DetectionFrame, V2xPosition

ROOT = Path(__file__).resolve().parents[2]
T0 = 1_717_200_000_000_000_000
MIB = 1024 * 1024
SECOND_NS = 1_000_000_000
LATENCY_NS = 30_000_000  # receive = stamp + this, as a daemon would log it
RSU = "rsu-1"


class FakeClock:
    """A Clock whose time only moves when a test says so."""

    def __init__(self, now_ns: int = T0) -> None:
        self.now = now_ns

    def now_ns(self) -> int:
        return self.now


def _frame(camera_id: str, i: int, boxes: int = 3) -> DetectionFrame:
    return DetectionFrame(
        camera_id=camera_id,
        stamp_ns=T0 + i * 100_000_000,
        boxes=[
            Box(x1=10.0 * j + i % 97 + 0.123456789, y1=100.5, x2=10.0 * j + i % 97 + 8.25, y2=120.0, cls=4)
            for j in range(boxes)
        ],
    )


def _v2x(station_id: int, i: int) -> V2xPosition:
    return V2xPosition(
        station_id=station_id,
        stamp_ns=T0 + i * 100_000_000 + 7,
        lat=48.137154 + 1e-6 * i,
        lon=11.576124,
        alt=519.5,
        heading_deg=(12.5 * i) % 360.0,
        speed=13.9,
    )


def _payload(message: DetectionFrame | V2xPosition) -> bytes:
    return message.model_dump_json().encode()


def _write_frame(recorder: RotatingRecorder, frame: DetectionFrame, received_ns: int | None = None) -> None:
    received = frame.stamp_ns + LATENCY_NS if received_ns is None else received_ns
    recorder.write_detections(frame.camera_id, frame.stamp_ns, received, _payload(frame))


def _write_v2x(recorder: RotatingRecorder, msg: V2xPosition, received_ns: int | None = None) -> None:
    received = msg.stamp_ns + LATENCY_NS if received_ns is None else received_ns
    recorder.write_v2x(msg.station_id, msg.stamp_ns, received, _payload(msg))


def _storage(**overrides: object) -> StorageConfig:
    return StorageConfig.model_validate({"chunk_bytes": 4096, **overrides})


def _paths(directory: Path) -> list[Path]:
    return [rec.path for rec in list_recordings(directory, RSU)]


def _summary_start(path: Path) -> int:
    """Where the footer says the summary section starts, i.e. where the data section ends."""
    footer = path.read_bytes()[-(8 + 29) : -8]  # opcode, length, summary_start, ... then the magic
    return int.from_bytes(footer[9:17], "little")


def _fake_recording(directory: Path, start_ns: int, size_bytes: int) -> Path:
    """A file named like a recording (sparse: only its size matters to retention)."""
    path = directory / recording_name(RSU, start_ns)
    with open(path, "wb") as stream:
        stream.truncate(size_bytes)
    return path


# ---------------------------------------------------------------------------------------------- layout


def test_files_are_named_by_first_receive_time_and_hold_the_raw_payloads(tmp_path: Path) -> None:
    clock = FakeClock()
    frame, msg = _frame("north", 1), _v2x(4711, 2)
    # Key order and spacing as a producer might send them: logged byte for byte, never re-serialised.
    frame_payload = json.dumps(json.loads(_payload(frame)), indent=1).encode()
    with RotatingRecorder(tmp_path, RSU, _storage(), clock) as recorder:
        assert recorder.current_path is None and recorder.files_written == 0  # opened lazily
        recorder.write_detections("north", frame.stamp_ns, T0 + 5, frame_payload)
        recorder.write_v2x(4711, msg.stamp_ns, T0 + 6, _payload(msg))
        assert recorder.current_path == tmp_path / f"{RSU}-{T0 + 5:019d}.mcap"
    assert recorder.current_path is None and recorder.files_written == 1
    (path,) = _paths(tmp_path)
    assert path.name == f"rsu-1-{T0 + 5:019d}.mcap"
    assert recorder.bytes_written == path.stat().st_size  # counted, not stat'ed, and exact
    with open(path, "rb") as stream:  # mcap's reference reader: the layout of docs/design.md
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        messages = [(channel, message) for _, channel, message in reader.iter_messages()]
        schemas = {summary.schemas[channel.schema_id].name for channel, _ in messages}
        assert schemas == {"rsucal.DetectionFrame", "rsucal.V2xPosition"}
        assert {summary.schemas[channel.schema_id].encoding for channel, _ in messages} == {"jsonschema"}
    (det_channel, det_message), (v2x_channel, v2x_message) = messages
    assert det_channel.topic == detections_key(RSU, "north") and det_channel.message_encoding == "json"
    assert (det_message.data, det_message.log_time, det_message.publish_time) == (
        frame_payload,
        T0 + 5,
        frame.stamp_ns,
    )
    assert v2x_channel.topic == v2x_key(4711)
    assert (v2x_message.log_time, v2x_message.publish_time) == (T0 + 6, msg.stamp_ns)
    loaded = read_recording(path)
    assert loaded.detections == {"north": [frame]} and loaded.v2x == [msg] and loaded.complete


def test_write_raw_keeps_the_writer_api(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    frame = _frame("north", 4)
    with RecordingWriter(path, chunk_size=4096) as writer:
        writer.write_detections(RSU, _frame("north", 3), T0)  # the model path still works
        writer.write_raw(
            detections_key(RSU, "north"), DetectionFrame, _payload(frame), T0 + 1, frame.stamp_ns
        )
        assert writer.channel_count == 1 and writer.messages_written == 2
    assert read_recording(path).detections == {"north": [_frame("north", 3), frame]}


def test_list_recordings_ignores_foreign_files(tmp_path: Path) -> None:
    newer = _fake_recording(tmp_path, T0 + 10, 10)
    older = _fake_recording(tmp_path, T0, 20)
    for name in [
        "notes.txt",
        f"rsu-2-{T0:019d}.mcap",  # another RSU
        f"rsu-{T0:019d}.mcap",  # an RSU called "rsu"
        f"rsu-1-{T0}.mcap.tmp",
        "rsu-1-123.mcap",  # not 19 digits
    ]:
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / recording_name(RSU, T0 + 5)).mkdir()  # a directory named like a recording
    assert list_recordings(tmp_path, RSU) == [RecordingFile(older, T0, 20), RecordingFile(newer, T0 + 10, 10)]
    assert list_recordings(tmp_path / "missing", RSU) == []


# ---------------------------------------------------------------------------------------------- rotation


def test_rotation_by_size(tmp_path: Path) -> None:
    clock = FakeClock()
    storage = _storage(compression="none", rotate_bytes=1 * MIB)
    frames = [_frame("north", i, boxes=30) for i in range(1200)]  # ~2.3 KB each: 2.6 MiB in all
    with RotatingRecorder(tmp_path, RSU, storage, clock) as recorder:
        for frame in frames:
            _write_frame(recorder, frame)
    recordings = list_recordings(tmp_path, RSU)
    assert len(recordings) == recorder.files_written == 3
    assert sum(rec.size_bytes for rec in recordings) == recorder.bytes_written
    # Rotated once the written bytes reach rotate_bytes: the data section ends at most one chunk (plus
    # its message index) beyond it; the summary (chunk indexes) follows.
    for rec in recordings[:-1]:
        assert 1 * MIB <= _summary_start(rec.path) <= 1 * MIB + 2 * storage.chunk_bytes
    # Each file starts at the receive time of its first message; together they hold everything once.
    first_frames = [read_recording(rec.path).detections["north"][0] for rec in recordings]
    assert [rec.start_ns for rec in recordings] == [f.stamp_ns + LATENCY_NS for f in first_frames]
    window = read_window([rec.path for rec in recordings], RSU, "north", (), 0, 2**63)
    assert window.detections == frames and window.problems == [] and window.duplicates == 0


def test_rotation_by_time_on_our_clock(tmp_path: Path) -> None:
    clock = FakeClock()
    recorder = RotatingRecorder(tmp_path, RSU, _storage(rotate_s=10.0), clock)
    for i in range(30):  # received at T0 + 0, 1, ..., 29 s
        clock.now = T0 + i * SECOND_NS
        _write_v2x(recorder, _v2x(7, i), received_ns=clock.now)
        recorder.tick()
    assert [rec.start_ns for rec in list_recordings(tmp_path, RSU)] == [
        T0,
        T0 + 10 * SECOND_NS,
        T0 + 20 * SECOND_NS,
    ]
    # No traffic: tick() alone closes a file that has grown too old, on the clock.
    clock.now = T0 + 30 * SECOND_NS - 1  # the last file started at T0 + 20 s
    recorder.tick()
    assert recorder.current_path is not None
    clock.now += 1
    recorder.tick()
    assert recorder.current_path is None
    for k, rec in enumerate(list_recordings(tmp_path, RSU)):
        loaded = read_recording(rec.path)
        assert loaded.complete and loaded.v2x == [_v2x(7, i) for i in range(10 * k, 10 * k + 10)]
    recorder.close()
    assert recorder.files_written == 3


def test_channel_limit_forces_rotation(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Every V2X station is a channel and MCAP channel ids are uint16: a crowd of stations starts a new file.
    monkeypatch.setattr(recording, "MAX_CHANNELS", 3)
    messages = [_v2x(station, i) for i in range(2) for station in (1, 2, 3, 4, 5)]
    with RotatingRecorder(tmp_path, RSU, _storage(), FakeClock()) as recorder:
        for msg in messages:
            _write_v2x(recorder, msg)
    paths = _paths(tmp_path)
    assert len(paths) == 4  # {1,2,3} {4,5,1} {2,3,4} {5}
    assert all(len(read_recording(path).channels) <= 3 for path in paths)
    window = read_window(paths, RSU, None, None, 0, 2**63)
    assert window.v2x == sorted(messages, key=lambda m: (m.stamp_ns, m.station_id))


def test_same_start_time_gets_a_unique_name(tmp_path: Path) -> None:
    clock = FakeClock()
    taken = _fake_recording(tmp_path, T0, 0)
    with RotatingRecorder(tmp_path, RSU, _storage(), clock) as recorder:
        _write_v2x(recorder, _v2x(7, 0), received_ns=T0)
    assert taken.stat().st_size == 0  # never overwritten
    assert [rec.start_ns for rec in list_recordings(tmp_path, RSU)] == [T0, T0 + 1]


def test_close_is_idempotent_and_final(tmp_path: Path) -> None:
    recorder = RotatingRecorder(tmp_path, RSU, _storage(), FakeClock())
    recorder.tick()
    recorder.flush()
    recorder.close()  # nothing was ever written: no file
    assert _paths(tmp_path) == []
    recorder.close()
    with pytest.raises(RecordingError, match="closed"):
        _write_v2x(recorder, _v2x(7, 0))
    with pytest.raises(ValueError, match="camera_id"):
        RotatingRecorder(tmp_path, RSU, _storage(), FakeClock()).write_detections("a/b", T0, T0, b"{}")
    with pytest.raises(ValueError, match="rsu_id"):
        RotatingRecorder(tmp_path, "rsu/1", _storage(), FakeClock())


# ---------------------------------------------------------------------------------------------- crash safety


def test_tick_flushes_on_the_clock(tmp_path: Path) -> None:
    clock = FakeClock()
    recorder = RotatingRecorder(tmp_path, RSU, _storage(flush_interval_s=2.0), clock)
    frames = [_frame("north", i) for i in range(5)]
    for frame in frames:
        _write_frame(recorder, frame)
    path = recorder.current_path
    assert path is not None

    def on_disk() -> list[DetectionFrame]:
        return read_window([path], RSU, "north", (), 0, 2**63).detections

    clock.now += 2 * SECOND_NS - 1
    recorder.tick()
    assert on_disk() == []  # still in the open chunk, in memory
    clock.now += 1
    recorder.tick()
    assert on_disk() == frames
    _write_frame(recorder, _frame("north", 5))
    recorder.flush()  # on demand, e.g. before a job reads the open file
    assert on_disk() == [*frames, _frame("north", 5)]
    recorder.close()


_CRASHING_WRITER = """
import os, signal, sys
from pathlib import Path
from daemon.clock import SystemClock
from daemon.recording import RotatingRecorder
from schemas.config import StorageConfig
from schemas.messages import DetectionFrame, V2xPosition
from schemas.common import Box

T0 = {t0}
storage = StorageConfig(compression="none", chunk_bytes=4096, rotate_bytes=1024 * 1024, flush_interval_s=60.0)
recorder = RotatingRecorder(Path(sys.argv[1]), "rsu-1", storage, SystemClock())
flushed = int(sys.argv[2])
for i in range(flushed + 300):
    stamp = T0 + i * 100_000_000
    x = i % 500
    boxes = [Box(x1=x + 0.5 * j, y1=10.0, x2=x + 80.0 + j, y2=90.0 + j / 7, cls=4) for j in range(20)]
    frame = DetectionFrame(camera_id="north", stamp_ns=stamp, boxes=boxes)
    recorder.write_detections("north", stamp, stamp + 1, frame.model_dump_json().encode())
    if i % 10 == 0:
        v2x = V2xPosition(
            station_id=7, stamp_ns=stamp, lat=48.1 + i * 1e-6, lon=11.5, alt=5.0, heading_deg=9.0, speed=1.0
        )
        recorder.write_v2x(7, stamp, stamp + 2, v2x.model_dump_json().encode())
    if i == flushed - 1:
        recorder.flush()
        print(recorder.files_written, flush=True)
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_kill_9_loses_nothing_before_the_last_flush(tmp_path: Path) -> None:
    flushed = 1000  # ~2.5 KB frames, 1 MiB files: the first file rotated (finished), the second one open
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    done = subprocess.run(
        [sys.executable, "-c", _CRASHING_WRITER.format(t0=T0), str(tmp_path), str(flushed)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == -signal.SIGKILL, done.stderr
    assert int(done.stdout.split()[0]) >= 2  # the flush happened in the second (or a later) file
    paths = _paths(tmp_path)
    assert len(paths) >= 2
    last = read_recording(paths[-1])
    assert not last.complete and "without a footer" in last.problems[-1]  # never finished: killed

    window = read_window(paths, RSU, "north", (7,), 0, 2**63)
    stamps = [frame.stamp_ns for frame in window.detections]
    # Everything up to the flush, then possibly some chunks written after it: a gapless prefix.
    assert flushed <= len(stamps) < flushed + 300
    assert stamps == [T0 + i * 100_000_000 for i in range(len(stamps))]
    assert [m.stamp_ns for m in window.v2x][: flushed // 10] == [
        T0 + i * 100_000_000 for i in range(0, flushed, 10)
    ]
    assert window.rejected == 0 and window.duplicates == 0
    assert any("without a footer" in problem for problem in window.problems)


def test_write_errors_drop_messages_but_never_raise(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    clock = FakeClock()
    recorder = RotatingRecorder(tmp_path, RSU, _storage(), clock)
    frames = [_frame("north", i) for i in range(6)]
    for frame in frames[:3]:
        _write_frame(recorder, frame, received_ns=clock.now)
    recorder.flush()
    broken = recorder.current_path
    assert broken is not None

    def disk_full(self: RecordingWriter, data: bytes) -> None:
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as patch:
        patch.setattr(RecordingWriter, "_append", disk_full)
        _write_frame(recorder, frames[3], received_ns=clock.now)  # the chunk is only written on flush
        recorder.flush()
        assert recorder.current_path is None and "No space left" in (recorder.last_error or "")
        _write_frame(recorder, frames[4], received_ns=clock.now + 1)  # paused: dropped, not raised
    assert recorder.messages_dropped == 2  # the lost chunk's message and the paused one
    _write_frame(recorder, frames[5], received_ns=clock.now + int(RETRY_AFTER_ERROR_S * SECOND_NS))
    recorder.close()
    paths = _paths(tmp_path)
    assert paths[0] == broken and len(paths) == 2
    window = read_window(paths, RSU, "north", (), 0, 2**63)
    assert window.detections == [*frames[:3], frames[5]]


# ---------------------------------------------------------------------------------------------- retention


def test_prune_by_bytes_oldest_first(tmp_path: Path) -> None:
    clock = FakeClock(T0 + 100 * SECOND_NS)
    files = [_fake_recording(tmp_path, T0 + i * SECOND_NS, 6 * MIB) for i in range(5)]  # 30 MiB
    foreign = tmp_path / "other.bin"
    with open(foreign, "wb") as stream:
        stream.truncate(100 * MIB)
    recorder = RotatingRecorder(tmp_path, RSU, _storage(retention_bytes=16 * MIB), clock)
    assert recorder.prune() == files[:3]  # 30 -> 24 -> 18 -> 12 MiB
    assert _paths(tmp_path) == files[3:] and foreign.exists()
    assert recorder.prune() == []


def test_prune_by_age_uses_where_the_next_file_starts(tmp_path: Path) -> None:
    now = T0 + 1000 * SECOND_NS
    files = [_fake_recording(tmp_path, now - age_s * SECOND_NS, 100) for age_s in (300, 200, 100, 50)]
    recorder = RotatingRecorder(tmp_path, RSU, _storage(retention_s=60.0), FakeClock(now))
    # files[1] started 200 s ago but received until files[2] started, 100 s ago: both too old. files[2]
    # ends 50 s ago; the last file's end is unknown, so it counts as receiving until now.
    assert recorder.prune() == files[:2]


def test_prune_keeps_the_collection_window(tmp_path: Path) -> None:
    now = T0 + 1000 * SECOND_NS
    files = [_fake_recording(tmp_path, now - age_s * SECOND_NS, 6 * MIB) for age_s in (300, 200, 100, 50)]
    recorder = RotatingRecorder(
        tmp_path, RSU, _storage(retention_s=60.0, retention_bytes=16 * MIB), FakeClock(now)
    )
    # A job window opening 250 s ago may need files[0] (it received until 200 s ago): nothing goes.
    assert recorder.prune(keep_after_ns=now - 250 * SECOND_NS) == []
    assert recorder.prune(keep_after_ns=now - 150 * SECOND_NS) == files[:1]
    assert recorder.prune(keep_after_ns=now - 100 * SECOND_NS) == files[1:2]  # ends exactly at the window
    assert _paths(tmp_path) == files[2:]


def test_prune_never_deletes_the_open_file(tmp_path: Path) -> None:
    clock = FakeClock()
    recorder = RotatingRecorder(tmp_path, RSU, _storage(retention_bytes=16 * MIB, retention_s=60.0), clock)
    _write_frame(recorder, _frame("north", 0), received_ns=T0)
    recorder.flush()
    open_path = recorder.current_path
    old = _fake_recording(tmp_path, T0 - 500 * SECOND_NS, 10 * MIB)
    # A file sorting after the open one (our clock went back after a restart) and far too large.
    later = _fake_recording(tmp_path, T0 + 10 * SECOND_NS, 20 * MIB)
    clock.now = T0 + 3600 * SECOND_NS  # every file is past retention_s by now
    assert recorder.prune() == [old, later]
    assert _paths(tmp_path) == [open_path]
    _write_frame(recorder, _frame("north", 1), received_ns=T0 + 1)
    recorder.close()
    assert open_path is not None
    assert read_recording(open_path).detections == {"north": [_frame("north", 0), _frame("north", 1)]}


# ---------------------------------------------------------------------------------------------- reading


@pytest.fixture()
def three_files(tmp_path: Path) -> tuple[list[Path], list[DetectionFrame], list[V2xPosition]]:
    """Two cameras and two stations over three files, 10 s each; stamps 0.1 s apart."""
    clock = FakeClock()
    frames: list[DetectionFrame] = []
    positions: list[V2xPosition] = []
    with RotatingRecorder(tmp_path, RSU, _storage(rotate_s=10.0), clock) as recorder:
        for i in range(300):
            for camera_id in ("north", "south"):
                frames.append(_frame(camera_id, i))
                _write_frame(recorder, frames[-1])
            for station in (7, 8):
                positions.append(_v2x(station, i))
                _write_v2x(recorder, positions[-1])
    paths = _paths(tmp_path)
    assert len(paths) == 3
    return paths, frames, positions


def test_read_window_merges_files_and_filters_by_stamp(
    three_files: tuple[list[Path], list[DetectionFrame], list[V2xPosition]],
) -> None:
    paths, frames, positions = three_files
    start, end = _frame("north", 80).stamp_ns, _frame("north", 220).stamp_ns  # spans all three files
    window = read_window(paths, RSU, "north", {8}, start, end)
    assert window.detections == [f for f in frames if f.camera_id == "north" and start <= f.stamp_ns <= end]
    assert [f.stamp_ns for f in window.detections][::140] == [start, end]  # both ends inclusive
    assert window.v2x == [m for m in positions if m.station_id == 8 and start <= m.stamp_ns <= end]
    assert window.problems == [] and window.rejected == 0
    # Every camera, no V2X; and the same answer when chunks are skipped by receive time.
    every = read_window(paths, RSU, None, (), start, end)
    assert every.v2x == [] and len(every.detections) == 2 * 141
    assert [f.stamp_ns for f in every.detections] == sorted(f.stamp_ns for f in every.detections)
    skipping = read_window(paths, RSU, None, None, start, end, max_stamp_skew_ns=SECOND_NS)
    assert skipping.detections == every.detections and len(skipping.v2x) == 2 * 140  # V2X: stamp + 7 ns
    assert read_window(paths, "rsu-2", None, (), start, end).detections == []
    with pytest.raises(ValueError, match="before start_ns"):
        read_window(paths, RSU, None, (), end, start)


def test_read_window_drops_replayed_duplicates(tmp_path: Path) -> None:
    frames = [_frame("north", i) for i in range(10)]
    with RotatingRecorder(tmp_path, RSU, _storage(rotate_s=5.0), FakeClock()) as recorder:
        for frame in frames:
            _write_frame(recorder, frame)
        for frame in frames[3:6]:  # replayed 10 s later, into the next file
            _write_frame(recorder, frame, received_ns=frame.stamp_ns + 10 * SECOND_NS)
        _write_v2x(recorder, _v2x(7, 1))
        _write_v2x(recorder, _v2x(7, 1), received_ns=T0 + 20 * SECOND_NS)
    paths = _paths(tmp_path)
    assert len(paths) == 3
    window = read_window(paths, RSU, "north", (7,), 0, 2**63)
    assert window.detections == frames and window.v2x == [_v2x(7, 1)]
    assert window.duplicates == 4


def test_read_window_carries_damage_as_problems(
    tmp_path: Path, three_files: tuple[list[Path], list[DetectionFrame], list[V2xPosition]]
) -> None:
    paths, frames, _ = three_files
    with open(paths[1], "rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    chunk = sorted(summary.chunk_indexes, key=lambda index: index.chunk_start_offset)[5]
    data = bytearray(paths[1].read_bytes())
    data[chunk.chunk_start_offset + chunk.chunk_length // 2] ^= 0x5A  # inside a chunk of the middle file
    paths[1].write_bytes(bytes(data))
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap at all")
    window = read_window([*paths, tmp_path / "missing.mcap", garbage], RSU, "north", (), 0, 2**63)
    north = [f for f in frames if f.camera_id == "north"]
    assert 0 < len(north) - len(window.detections) < 40  # one 4 KiB chunk of the middle file is lost
    assert {f.model_dump_json() for f in window.detections} <= {f.model_dump_json() for f in north}
    assert any(str(paths[1]) in p and "chunk at byte" in p for p in window.problems)
    assert any("missing.mcap: cannot read" in p for p in window.problems)
    assert any("garbage.mcap: not an MCAP file" in p for p in window.problems)
    nothing = read_window([garbage], RSU, "north", (), 0, 2**63)  # nothing readable: empty, not raised
    assert nothing.detections == [] and nothing.v2x == [] and len(nothing.problems) == 1


def test_read_window_counts_rejected_messages(tmp_path: Path) -> None:
    with RotatingRecorder(tmp_path, RSU, _storage(), FakeClock()) as recorder:
        _write_frame(recorder, _frame("north", 1))
        recorder.write_detections("north", T0 + 5, T0 + 5, b'{"camera_id": "north"}')  # no stamp_ns
        recorder.write_detections("north", T0 + 6, T0 + 6, _payload(_frame("south", 0)))  # wrong camera
        recorder.write_detections("north", T0 + 10**15, T0, b"{not json")  # outside the window: not read
    window = read_window(_paths(tmp_path), RSU, "north", (), T0, T0 + 10**12)
    assert window.detections == [_frame("north", 1)] and window.rejected == 2
    (problem,) = window.problems
    assert problem.startswith(f"{detections_key(RSU, 'north')}: 2 message(s) rejected, first: stamp_ns")


def test_iter_v2x_replays_since_a_receive_time(
    three_files: tuple[list[Path], list[DetectionFrame], list[V2xPosition]], caplog: pytest.LogCaptureFixture
) -> None:
    paths, _, positions = three_files
    since = T0 + 150 * 100_000_000  # received time: the middle of the second file
    replayed = list(iter_v2x(paths, {7}, since))
    expected = [m for m in positions if m.station_id == 7 and m.stamp_ns + LATENCY_NS >= since]
    assert [m for m, _ in replayed] == expected
    assert [received for _, received in replayed] == [m.stamp_ns + LATENCY_NS for m in expected]
    assert len(list(iter_v2x(paths, None, 0))) == len(positions)
    # Files that ended before `since` are not even opened: the first one can be garbage.
    paths[0].write_bytes(b"garbage")
    with caplog.at_level(logging.WARNING, logger="daemon.recording"):
        assert list(iter_v2x(paths, {7}, since)) == replayed
        assert caplog.records == []
        assert len(list(iter_v2x(paths, {7}, 0))) == 200  # read from the start: logged, not raised
    assert "not an MCAP file" in caplog.text


@pytest.mark.parametrize("views", [True, False])
def test_recorder_writes_foxglove_views_beside_the_raw_channels(tmp_path: Path, views: bool) -> None:
    """With storage.foxglove_views, every detection frame given its boxes gets ImageAnnotations and every
    V2X position given its message a LocationFix, in the same file; they are not counted as received."""
    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
    from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
    from mcap_protobuf.decoder import DecoderFactory

    from schemas.messages import check_detection_frame_boxes

    storage = StorageConfig(state_dir=tmp_path, foxglove_views=views)
    frames = [_frame("north", i, boxes=1 + i % 5) for i in range(20)]
    fixes = [_v2x(4711, i) for i in range(20)]
    with RotatingRecorder(tmp_path, RSU, storage, FakeClock()) as recorder:
        for frame, fix in zip(frames, fixes, strict=True):
            payload = _payload(frame)
            _, _, boxes = check_detection_frame_boxes(payload)  # what ingest hands over
            recorder.write_detections("north", frame.stamp_ns, frame.stamp_ns + LATENCY_NS, payload, boxes)
            recorder.write_v2x(
                4711, fix.stamp_ns, fix.stamp_ns + LATENCY_NS, _payload(fix), fix, is_vehicle=True
            )
        assert recorder.messages_written == 40
    [path] = list(tmp_path.glob("*.mcap"))
    decoded: dict[str, list[object]] = {}
    factory = DecoderFactory()
    with open(path, "rb") as stream:
        for schema, channel, message in make_reader(stream).iter_messages():
            assert schema is not None
            if schema.encoding == "protobuf":
                assert message.log_time in {f.stamp_ns + LATENCY_NS for f in [*frames, *fixes]}
                # Decoded with the schema stored in the file (mcap's protobuf decoder builds it from the
                # file's descriptors), then again with the official classes.
                decoder = factory.decoder_for(channel.message_encoding, schema)
                assert decoder is not None
                decoded.setdefault(channel.topic, []).append(decoder(message.data))
    loaded = read_recording(path)
    assert loaded.detections == {"north": frames} and loaded.v2x == fixes  # raw channels unchanged
    if not views:
        assert decoded == {}
        return
    annotations = decoded[f"rsu/{RSU}/camera/north/detections/annotations"]
    assert [len(a.points) for a in annotations] == [len(f.boxes) for f in frames]  # type: ignore[attr-defined]
    official = [ImageAnnotations.FromString(a.SerializeToString()) for a in annotations]  # type: ignore[attr-defined]
    for frame, annotation in zip(frames, official, strict=True):
        assert annotation.timestamp.ToNanoseconds() == frame.stamp_ns
        assert [(p.points[0].x, p.points[2].y) for p in annotation.points] == [
            (b.x1, b.y2) for b in frame.boxes
        ]
    locations = [LocationFix.FromString(m.SerializeToString()) for m in decoded["v2x/cam/4711/location"]]  # type: ignore[attr-defined]
    assert [(f.latitude, f.longitude, f.timestamp.ToNanoseconds()) for f in locations] == [
        (m.lat, m.lon, m.stamp_ns) for m in fixes
    ]


def test_read_images_finds_the_recorded_image_nearest_each_stamp(tmp_path: Path) -> None:
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    from daemon import foxglove
    from daemon.keys import image_key
    from daemon.recording import read_images

    path = tmp_path / "images.mcap"
    with RecordingWriter(path, chunk_size=4096) as writer:
        for i in range(10):
            image = CompressedImage(format="jpeg", data=bytes([i]) * 100, frame_id="cam")
            image.timestamp.FromNanoseconds(T0 + i * 100_000_000)
            topic = image_key(RSU, "north" if i != 5 else "south")
            writer.write_raw(
                topic,
                foxglove.protobuf_schema("CompressedImage"),
                image.SerializeToString(),
                T0,
                T0 + i * 100_000_000,
            )
        writer.write_raw(
            image_key(RSU, "north"), foxglove.protobuf_schema("CompressedImage"), b"\xff\xff", T0, T0 + 3
        )
    wanted = [T0 + 200_000_000 + 400_000, T0 + 500_000_000, T0 + 700_000_000 + 2_000_000, T0]
    found = read_images([path], RSU, "north", wanted)
    # Within 1 ms: frame 2 and frame 0 (the undecodable message is skipped); frame 5 is another camera's,
    # and 2 ms from frame 7 is too far.
    assert found == {wanted[0]: bytes([2]) * 100, T0: bytes([0]) * 100}
    assert read_images([path], RSU, "north", []) == {}
