"""Fuzzing daemon.recording's readers with truncated and corrupted MCAP files.

read_recording (what `rsucal calibrate --mcap` reads), read_window (the daemon's calibration jobs) and
iter_v2x (the daemon's restart recovery, Daemon._replay_traversals) get the small recording of fuzz_mcap.py
cut at any offset and with bytes flipped anywhere. Each must lose at most the messages of the chunks that
were damaged or cut off: every message of every other chunk is returned, nothing is invented, and the
only exception is RecordingError naming the file when nothing at all can be recovered.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from fuzz_mcap import MessageId, Recorded, SmallRecording, small_recording
from fuzzing import fuzz_settings, label, scratch_dir
from hypothesis import given
from hypothesis import strategies as st

from daemon.recording import RecordingError, iter_v2x, read_recording, read_window
from schemas.messages import DetectionFrame, V2xPosition

DIR = scratch_dir("rsucal-fuzz-recording-")
# Uniform positions mostly land in chunk data; the first bytes (magic, header, the first channel and
# schema records) and the last (summary, footer) are few but hold the file together, so they get extra weight.
positions = st.one_of(
    st.floats(0.0, 1.0, exclude_max=True),
    st.integers(0, 400).map(lambda n: -(n + 1)),  # from the end
    st.integers(0, 400).map(lambda n: n + 0.5),  # from the start (a float > 1 marks it)
)
flips = st.lists(st.tuples(positions, st.integers(1, 255)), min_size=1, max_size=3)


def offset_of(position: float | int, size: int) -> int:
    if isinstance(position, int):
        return max(0, size + position)
    if position >= 1.0:
        return min(size - 1, int(position))
    return int(position * size)


def damaged_copy(
    rec: SmallRecording, name: str, edits: list[tuple[float | int, int]], cut: int | None
) -> tuple[Path, list[tuple[int, int]]]:
    """Write `rec` with bytes flipped (position, xor mask) and cut; the edits as (offset, mask)."""
    data = bytearray(rec.data)
    done = []
    for position, mask in edits:
        offset = offset_of(position, len(data))
        data[offset] ^= mask
        done.append((offset, mask))
    path = DIR / name
    path.write_bytes(bytes(data[:cut]) if cut is not None else bytes(data))
    return path, done


def ids_of(messages: list[DetectionFrame | V2xPosition]) -> set[MessageId]:
    return {
        ("det", m.camera_id, m.stamp_ns)
        if isinstance(m, DetectionFrame)
        else ("v2x", m.station_id, m.stamp_ns)
        for m in messages
    }


def recording_ids(path: Path) -> set[MessageId] | None:
    """What read_recording recovered, or None after checking its RecordingError names the file."""
    try:
        recording = read_recording(path)
    except RecordingError as err:
        assert str(path) in str(err)
        return None
    return ids_of([f for frames in recording.detections.values() for f in frames] + recording.v2x)


FOOTER_OPCODE = 0x02
MAGIC_BYTES = 8


def kept(rec: SmallRecording, edits: list[tuple[int, int]], cut: int | None = None) -> list[Recorded]:
    """The messages that must survive (offset, mask) edits: those of every chunk neither damaged nor cut off.

    Only damaged magic bytes may lose the whole file (it is then no MCAP at all); a damaged header, a record
    opcode flipped into a footer's or a broken record length cost at most the chunk they hit."""
    offsets = [offset for offset, _ in edits]
    if any(offset < MAGIC_BYTES for offset in offsets):
        label("magic damaged")
        return []
    if edits:
        label(f"chunks damaged: {len(rec.damaged_chunks(offsets))}")
    return rec.kept(rec.damaged_chunks(offsets), cut)


def check_recovered(rec: SmallRecording, recovered: set[MessageId] | None, expected: set[MessageId]) -> None:
    everything = {m.id for m in rec.messages}
    if recovered is None:
        label("RecordingError")
        assert not expected, f"{len(expected)} messages of undamaged chunks lost with the whole file"
        return
    assert recovered <= everything, "a message was invented"
    missing = expected - recovered
    assert not missing, f"{len(missing)} messages of undamaged chunks lost, e.g. {sorted(missing)[:3]}"


def test_the_intact_recording_reads_completely() -> None:
    rec = small_recording()
    ids = [m.id for m in rec.messages]
    assert len(set(ids)) == len(ids)
    assert recording_ids(rec.path) == set(ids)


@fuzz_settings(0.5)
@given(fraction=st.floats(0.0, 1.0) | st.integers(0, 64).map(float))
def test_read_recording_of_a_truncated_file(fraction: float) -> None:
    rec = small_recording()
    cut = int(fraction) if fraction > 1.0 else int(len(rec.data) * fraction)
    path, _ = damaged_copy(rec, "cut.mcap", [], cut)
    check_recovered(rec, recording_ids(path), {m.id for m in kept(rec, [], cut)})


@fuzz_settings(0.5)
@given(edits=flips)
def test_read_recording_of_a_corrupted_file(edits: list[tuple[float | int, int]]) -> None:
    rec = small_recording()
    path, done = damaged_copy(rec, "flip.mcap", edits, None)
    check_recovered(rec, recording_ids(path), {m.id for m in kept(rec, done)})


@fuzz_settings()
@given(
    edits=flips,
    start=st.floats(0.0, 1.0),
    length=st.floats(0.0, 1.0),
    skew_ms=st.none() | st.sampled_from([50, 1000]),
)
def test_read_window_of_a_corrupted_file(
    edits: list[tuple[float | int, int]],
    start: float,
    length: float,
    skew_ms: int | None,
) -> None:
    rec = small_recording()
    path, done = damaged_copy(rec, "window.mcap", edits, None)
    stamps = sorted(m.stamp_ns for m in rec.messages)
    start_ns = stamps[0] + int((stamps[-1] - stamps[0]) * start)
    end_ns = start_ns + int((stamps[-1] - stamps[0]) * length)
    window = read_window(
        [path],
        rec.rsu_id,
        None,
        None,
        start_ns,
        end_ns,
        max_stamp_skew_ns=None if skew_ms is None else skew_ms * 1_000_000,
    )
    expected = {m.id for m in kept(rec, done) if start_ns <= m.stamp_ns <= end_ns}
    check_recovered(rec, ids_of([*window.detections, *window.v2x]), expected)
    assert all(start_ns <= m.stamp_ns <= end_ns for m in [*window.detections, *window.v2x])


def test_a_window_past_a_skipped_chunk_and_a_broken_record_ends() -> None:
    """Found by test_read_window_of_a_corrupted_file (it hung): with no verified summary and a stamp skew
    bound (chunks whose log times lie outside the window are stepped over), a chunk stepped over, then a
    record after it with a corrupt length. The resynchronisation searched from before the skipped chunk,
    found it intact, stepped over it again, and so on for ever."""
    rec = small_recording()
    data = bytearray(rec.data)
    after = rec.chunk_ranges[2][1]  # the record right after the third chunk
    data[after + 8] ^= 0x40  # its length's high byte: far past the end of the file
    data[rec.summary_start + 20] ^= 0xFF  # the summary no longer matches its CRC
    path = DIR / "skipped.mcap"
    path.write_bytes(bytes(data))
    first = rec.chunk_messages[0]  # the window: the first chunk's messages, read; the next ones stepped over
    start_ns, end_ns = min(m.stamp_ns for m in first), max(m.stamp_ns for m in first)
    window = read_window([path], rec.rsu_id, None, None, start_ns, end_ns, max_stamp_skew_ns=50_000_000)
    edits = [(after + 8, 0x40), (rec.summary_start + 20, 0xFF)]
    expected = {m.id for m in kept(rec, edits) if start_ns <= m.stamp_ns <= end_ns}
    assert expected  # the window's chunk is intact: this checks the reading, not only that it ends
    check_recovered(rec, ids_of([*window.detections, *window.v2x]), expected)


@fuzz_settings()
@given(edits=flips, since=st.floats(0.0, 1.0) | st.just(0.0))
def test_restart_recovery_of_a_corrupted_file(edits: list[tuple[float | int, int]], since: float) -> None:
    """iter_v2x, as Daemon._replay_traversals calls it after a restart: a finished file (the daemon shut
    down) with flipped bytes."""
    rec = small_recording()
    path, done = damaged_copy(rec, rec.path.name, edits, None)
    log_times = sorted(m.log_ns for m in rec.messages)
    since_ns = log_times[0] + int((log_times[-1] - log_times[0]) * since)
    replayed = list(iter_v2x([path], None, since_ns))
    assert all(received_ns >= since_ns for _, received_ns in replayed)
    expected = {m.id for m in kept(rec, done) if m.id[0] == "v2x" and m.log_ns >= since_ns}
    check_recovered(rec, ids_of([message for message, _ in replayed]), expected)


# ---------------------------------------------------------------------------------------------- found


def lost_from_one_flip(offset: int, mask: int) -> tuple[set[MessageId], set[MessageId]]:
    """(messages lost by read_recording, V2X lost by iter_v2x) after flipping one byte."""
    rec = small_recording()
    path, _ = damaged_copy(rec, "one-flip.mcap", [(offset + 0.5, mask)], None)
    everything = {m.id for m in rec.messages}
    replayed = ids_of([m for m, _ in iter_v2x([path], None, 0)])
    return everything - (recording_ids(path) or set()), {i for i in everything if i[0] == "v2x"} - replayed


@pytest.mark.parametrize(
    ("where", "offset", "mask"), [("opcode", 8, 0x40), ("length", 12, 0x01), ("library", 30, 0x80)]
)
def test_a_damaged_header_loses_no_chunk(where: str, offset: int, mask: int) -> None:
    lost, lost_v2x = lost_from_one_flip(offset, mask)
    assert not lost and not lost_v2x, f"{len(lost)} messages lost"


@pytest.mark.parametrize("which", ["first schema", "first chunk", "middle chunk", "middle message index"])
def test_a_record_flipped_into_a_footer_loses_only_that_record(which: str) -> None:
    rec = small_recording()
    chunk = {"first chunk": 0, "middle chunk": len(rec.chunk_ranges) // 2}.get(which)
    if which == "first schema":
        offset = rec.header_end
    elif which == "middle message index":
        offset = rec.chunk_ranges[len(rec.chunk_ranges) // 2][1]
    else:
        assert chunk is not None
        offset = rec.chunk_ranges[chunk][0]
    mask = rec.data[offset] ^ FOOTER_OPCODE
    lost, lost_v2x = lost_from_one_flip(offset, mask)
    allowed = {m.id for m in rec.chunk_messages[chunk]} if chunk is not None else set()
    assert lost <= allowed and lost_v2x <= allowed, f"{len(lost - allowed)} messages of other chunks lost"


@pytest.mark.parametrize("record", ["chunk", "message index"])
def test_a_damaged_length_in_an_unfinished_file_loses_only_that_record(record: str) -> None:
    rec = small_recording()
    cut = rec.chunk_ranges[-3][1]  # crashed: no summary, no footer
    damaged = 10
    start, end = rec.chunk_ranges[damaged]
    offset = (start if record == "chunk" else end) + 1  # the lowest byte of the record's u64 length
    path, _ = damaged_copy(rec, rec.path.name, [(offset + 0.5, 0x01)], cut)
    replayed = ids_of([m for m, _ in iter_v2x([path], None, 0)])
    recovered = recording_ids(path) or set()
    allowed = {m.id for m in rec.chunk_messages[damaged]}
    expected = {m.id for m in rec.kept(set(), cut)} - allowed
    assert expected <= recovered, f"{len(expected - recovered)} messages of intact chunks lost"
    assert {i for i in expected if i[0] == "v2x"} <= replayed
