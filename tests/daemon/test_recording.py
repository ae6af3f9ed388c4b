"""daemon.recording: MCAP layout, round trips (hand-made and simulated), damaged files and bad messages."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pytest
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import Writer

from daemon import foxglove, recording
from daemon.keys import detections_key, v2x_key
from daemon.recording import (
    MCAP_MAGIC,
    SIM_DETECTION_LATENCY_NS,
    SIM_V2X_LATENCY_NS,
    Recording,
    RecordingWriter,
    read_recording,
    read_window,
    write_simulation_mcap,
)
from pipeline.errors import RecordingError
from pipeline.loaders import (
    load_ground_truth,
    load_intrinsics,
    load_toolbox_detections,
    load_toolbox_poses,
    load_vehicle,
)
from schemas.common import Box, CameraIntrinsics
from schemas.files import GroundTruth, GroundTruthFrame
from schemas.messages import DetectionFrame, V2xPosition
from sim.files import write_simulation_files
from sim.simulate import SimulationResult, simulate

T0 = 1_700_000_000_000_000_000
RECEIVE_DELAY_NS = 25_000_000


def _frame(camera_id: str, i: int) -> DetectionFrame:
    boxes = [
        Box(x1=10.0 * j + i, y1=100.5, x2=10.0 * j + i + 8.25, y2=120.0, cls=4 + j % 4, score=0.9)
        for j in range(i % 4)
    ]
    return DetectionFrame(camera_id=camera_id, stamp_ns=T0 + i * 100_000_000, boxes=boxes)


def _v2x(station_id: int, i: int) -> V2xPosition:
    return V2xPosition(
        station_id=station_id,
        stamp_ns=T0 + i * 100_000_000 + 3,
        lat=48.137154 + 1e-6 * i,
        lon=11.576124,
        alt=519.5,
        heading_deg=(12.5 * i) % 360.0,
        speed=13.9,
        length=4.8,
    )


def _write_sample(
    path: Path, frames: int = 30, chunk_size: int = 1024 * 1024
) -> tuple[list[DetectionFrame], list[V2xPosition]]:
    """Two cameras of rsu-1 and two V2X stations, interleaved as a daemon would receive them."""
    written_frames: list[DetectionFrame] = []
    written_v2x: list[V2xPosition] = []
    with RecordingWriter(path, chunk_size=chunk_size) as writer:
        for i in range(frames):
            for camera_id in ("north", "south"):
                frame = _frame(camera_id, i)
                writer.write_detections("rsu-1", frame, frame.stamp_ns + RECEIVE_DELAY_NS)
                written_frames.append(frame)
            if i % 3 == 0:
                for station in (7, 4711):
                    msg = _v2x(station, i)
                    writer.write_v2x(msg, msg.stamp_ns + RECEIVE_DELAY_NS)
                    written_v2x.append(msg)
    return written_frames, written_v2x


def _all_messages(recording: Recording) -> list[str]:
    frames = [f.model_dump_json() for frames in recording.detections.values() for f in frames]
    return frames + [m.model_dump_json() for m in recording.v2x]


# ---------------------------------------------------------------------------------------------- round trips


def test_round_trip_returns_what_was_written(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    frames, v2x = _write_sample(path)
    recording = read_recording(path)
    assert recording.rsu_id == "rsu-1"
    assert recording.camera_ids == ("north", "south")
    for camera_id in ("north", "south"):
        assert recording.detections[camera_id] == [f for f in frames if f.camera_id == camera_id]
    assert recording.v2x == sorted(v2x, key=lambda m: (m.stamp_ns, m.station_id))
    assert recording.rejected == {} and recording.problems == () and recording.complete
    assert recording.channels == {
        "rsu/rsu-1/camera/north/detections": 30,
        "rsu/rsu-1/camera/south/detections": 30,
        "v2x/cam/7": 10,
        "v2x/cam/4711": 10,
    }


def test_layout_as_designed_read_by_the_reference_reader(tmp_path: Path) -> None:
    # docs/design.md: channel per key, json messages, jsonschema from the model, log_time = receive,
    # publish_time = stamp, chunked + zstd. Checked with mcap's own reader, not ours.
    path = tmp_path / "rec.mcap"
    _write_sample(path, frames=6)
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        topics = {channel.topic: channel for channel in summary.channels.values()}
        assert set(topics) == {
            detections_key("rsu-1", "north"),
            detections_key("rsu-1", "south"),
            v2x_key(7),
            v2x_key(4711),
        }
        for channel in topics.values():
            assert channel.message_encoding == "json"
            schema = summary.schemas[channel.schema_id]
            assert schema.encoding == "jsonschema"
            model = DetectionFrame if "detections" in channel.topic else V2xPosition
            assert schema.name == f"rsucal.{model.__name__}"
            assert json.loads(schema.data) == model.model_json_schema()
        assert len(summary.schemas) == 2  # one schema per model, shared by its channels
        assert {index.compression for index in summary.chunk_indexes} == {"zstd"}
        for _, _, message in reader.iter_messages():
            payload = json.loads(message.data)
            assert message.publish_time == payload["stamp_ns"]
            assert message.log_time == payload["stamp_ns"] + RECEIVE_DELAY_NS


@pytest.mark.parametrize("compression", ["lz4", "none"])
def test_other_compressions_round_trip(tmp_path: Path, compression: str) -> None:
    path = tmp_path / "rec.mcap"
    with RecordingWriter(path, compression=compression) as writer:  # type: ignore[arg-type]
        writer.write_detections("rsu-1", _frame("north", 3), T0)
    assert read_recording(path).detections == {"north": [_frame("north", 3)]}


def test_filters_select_camera_rsu_and_station(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    _, v2x = _write_sample(path, frames=9)
    north = read_recording(path, camera_id="north")
    assert list(north.detections) == ["north"] and len(north.v2x) == len(v2x)
    station = read_recording(path, station_id=4711)
    assert {m.station_id for m in station.v2x} == {4711} and len(station.detections) == 2
    assert read_recording(path, rsu_id="rsu-2").detections == {}
    assert read_recording(path, camera_id="west").detections == {}


def test_several_rsus_need_a_choice(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    with RecordingWriter(path) as writer:
        writer.write_detections("rsu-1", _frame("cam", 1), T0)
        writer.write_detections("rsu-2", _frame("cam", 2), T0)
    with pytest.raises(RecordingError, match=r"several RSUs \(rsu-1, rsu-2\)"):
        read_recording(path)
    chosen = read_recording(path, rsu_id="rsu-2")
    assert chosen.rsu_id == "rsu-2" and chosen.detections == {"cam": [_frame("cam", 2)]}


def test_empty_but_finished_recording_is_valid(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    with RecordingWriter(path):
        pass
    recording = read_recording(path)
    assert (
        recording.detections == {} and recording.v2x == [] and recording.rsu_id is None and recording.complete
    )


def test_a_new_recording_is_an_mcap_file_before_anything_is_written(tmp_path: Path) -> None:
    # Its magic and header are on disk when the writer is made: a job reading the directory (or a crash)
    # finds an empty recording in writing, not 0 bytes that are "not an MCAP file".
    path = tmp_path / "rec.mcap"
    writer = RecordingWriter(path)
    try:
        window = read_window([path], "rsu-1", None, None, 0, 2**63 - 1)
        assert window.detections == [] and window.v2x == []
        [problem] = window.problems
        assert "without a footer (truncated; not finished)" in problem
    finally:
        writer.finish()


def test_writer_guards(tmp_path: Path) -> None:
    writer = RecordingWriter(tmp_path / "rec.mcap")
    with pytest.raises(ValueError, match="rsu_id"):
        writer.write_detections("rsu/1", _frame("north", 1), T0)  # would change the key's shape
    with pytest.raises(ValueError, match="unsigned"):
        writer.write_v2x(_v2x(7, 1), -1)
    writer.finish()
    writer.finish()  # idempotent
    with pytest.raises(RecordingError, match="already finished"):
        writer.write_v2x(_v2x(7, 1), T0)


def test_existing_recording_is_never_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    with RecordingWriter(path) as writer:
        writer.write_v2x(_v2x(7, 1), T0)
    with pytest.raises(RecordingError, match="already exists"):
        RecordingWriter(path)
    assert read_recording(path).v2x == [_v2x(7, 1)]
    with RecordingWriter(path, overwrite=True):
        pass
    assert read_recording(path).v2x == []
    with pytest.raises(ValueError, match="compression 'gzip'"):
        RecordingWriter(tmp_path / "other.mcap", compression="gzip")  # type: ignore[arg-type]


def test_channel_limit_asks_for_rotation(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Every V2X station is its own channel; ids are uint16, so the daemon must rotate before they run out.
    monkeypatch.setattr(recording, "MAX_CHANNELS", 2)
    with RecordingWriter(tmp_path / "rec.mcap") as writer:
        writer.write_v2x(_v2x(1, 1), T0)
        writer.write_v2x(_v2x(2, 1), T0)
        writer.write_v2x(_v2x(2, 2), T0)  # an existing channel is fine
        assert writer.channel_count == 2
        with pytest.raises(RecordingError, match="rotate"):
            writer.write_v2x(_v2x(3, 1), T0)
    assert [m.station_id for m in read_recording(tmp_path / "rec.mcap").v2x] == [1, 2, 2]


def test_context_manager_finishes_when_the_body_raises(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    with pytest.raises(KeyError), RecordingWriter(path) as writer:
        writer.write_detections("rsu-1", _frame("north", 1), T0)
        raise KeyError("boom")
    recording = read_recording(path)
    assert recording.complete and recording.detections == {"north": [_frame("north", 1)]}


def test_flush_makes_messages_survive_a_crash(tmp_path: Path) -> None:
    # A crash leaves the file as it was at the last flush: no summary, no footer.
    path = tmp_path / "rec.mcap"
    writer = RecordingWriter(path)
    for i in range(5):
        writer.write_detections("rsu-1", _frame("north", i), T0 + i)
    writer.flush()
    crashed = tmp_path / "crashed.mcap"
    crashed.write_bytes(path.read_bytes())
    writer.write_detections("rsu-1", _frame("north", 9), T0 + 9)  # still in the open chunk
    writer.finish()
    recording = read_recording(crashed)
    assert recording.detections == {"north": [_frame("north", i) for i in range(5)]}
    assert not recording.complete and "without a footer" in recording.problems[0]


@dataclass(frozen=True)
class _FakeSimulation:
    """The SimulationResult fields write_simulation_mcap reads (the simulator is another module)."""

    rsu_id: str
    station_id: int
    detections: dict[str, list[DetectionFrame]]
    v2x: list[V2xPosition]
    ground_truth: dict[str, GroundTruth]


def _truth(camera_id: str, frames: list[DetectionFrame]) -> GroundTruth:
    """Ground truth naming the last box of every frame that has one as the calibration vehicle's."""
    return GroundTruth(
        camera_id=camera_id,
        crs="EPSG:32632",
        origin=(0.0, 0.0, 0.0),
        R=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
        t_utm=(0.0, 0.0, 0.0),
        t_local=(0.0, 0.0, 0.0),
        camera_position_utm=(0.0, 0.0, 0.0),
        intrinsics=CameraIntrinsics(width=640, height=480, fx=500.0, fy=500.0, cx=320.0, cy=240.0),
        station_id=99,
        traversals=1,
        frames=[
            GroundTruthFrame(stamp_ns=f.stamp_ns, calib_box=len(f.boxes) - 1 if f.boxes else None)
            for f in frames
        ],
    )


def test_write_simulation_mcap_in_log_time_order(tmp_path: Path) -> None:
    detections = {"a": [_frame("a", i) for i in range(10)], "b": [_frame("b", i) for i in range(0, 10, 2)]}
    sim = _FakeSimulation(
        rsu_id="sim-rsu",
        station_id=99,
        detections=detections,
        v2x=[*(_v2x(99, i) for i in range(10)), _v2x(7, 11)],
        ground_truth={"a": _truth("a", detections["a"])},
    )
    path = write_simulation_mcap(sim, tmp_path / "sim.mcap")  # type: ignore[arg-type]
    annotated: dict[str, list[ImageAnnotations]] = {}
    fixes: dict[str, list[LocationFix]] = {}
    with open(path, "rb") as stream:
        log_times = []
        for schema, channel, message in make_reader(stream).iter_messages(log_time_order=False):  # file order
            latency = SIM_V2X_LATENCY_NS if channel.topic.startswith("v2x/") else SIM_DETECTION_LATENCY_NS
            assert message.log_time == message.publish_time + latency
            log_times.append(message.log_time)
            assert schema is not None
            if schema.name == "foxglove.ImageAnnotations":
                annotated.setdefault(channel.topic, []).append(ImageAnnotations.FromString(message.data))
            elif schema.name == "foxglove.LocationFix":
                fixes.setdefault(channel.topic, []).append(LocationFix.FromString(message.data))
    assert log_times == sorted(log_times) and len(log_times) == 2 * (10 + 5 + 11)
    recording = read_recording(path)
    assert recording.rsu_id == "sim-rsu"
    assert recording.detections == sim.detections and recording.v2x == sim.v2x
    # Every frame has its view, with every box; the truth's vehicle box (camera a only) in its own colour.
    for camera_id, frames in detections.items():
        views = annotated[f"rsu/sim-rsu/camera/{camera_id}/detections/annotations"]
        assert [v.timestamp.ToNanoseconds() for v in views] == [f.stamp_ns for f in frames]
        for frame, view in zip(frames, views, strict=True):
            assert len(view.points) == len(frame.boxes)
            colors = [(p.outline_color.r, p.outline_color.g, p.outline_color.b) for p in view.points]
            vehicle = [c == pytest.approx(foxglove.VEHICLE_BOX_RGBA[:3]) for c in colors]
            assert sum(vehicle) == (1 if camera_id == "a" and frame.boxes else 0)
            if camera_id == "a" and frame.boxes:
                last = frame.boxes[-1]
                corners = [(p.x, p.y) for p in view.points[-1].points]
                assert vehicle[-1] and corners[0] == (last.x1, last.y1) and corners[2] == (last.x2, last.y2)
    assert [f.latitude for f in fixes["v2x/cam/99/location"]] == [m.lat for m in sim.v2x[:10]]
    assert fixes["v2x/cam/99/location"][0].color.r == pytest.approx(foxglove.VEHICLE_STATION_RGBA[0])
    assert fixes["v2x/cam/7/location"][0].color.r == pytest.approx(foxglove.OTHER_STATION_RGBA[0])


# ---------------------------------------------------------------------------------------------- damage


@pytest.fixture(scope="module")
def chunked_recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[bytes, set[str]]:
    """A finished file of ~15 small chunks, and every message written (as JSON)."""
    path = tmp_path_factory.mktemp("rec") / "rec.mcap"
    frames, v2x = _write_sample(path, frames=60, chunk_size=2048)
    return path.read_bytes(), {m.model_dump_json() for m in [*frames, *v2x]}


def test_truncated_file_yields_its_complete_chunks(
    tmp_path: Path, chunked_recording: tuple[bytes, set[str]]
) -> None:
    data, written = chunked_recording
    path = tmp_path / "cut.mcap"
    path.write_bytes(data[: len(data) // 2])
    recording = read_recording(path)
    recovered = _all_messages(recording)
    assert 0 < len(recovered) < len(written)
    assert set(recovered) <= written
    assert not recording.complete and "truncated" in recording.problems[0]
    # What survives is a prefix of the recording: every frame up to some time, none after.
    north = [f.stamp_ns for f in recording.detections["north"]]
    assert north == [T0 + i * 100_000_000 for i in range(len(north))]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(fraction=st.floats(0.0, 1.0))
def test_any_truncation_reads_a_subset_or_raises(
    tmp_path: Path, chunked_recording: tuple[bytes, set[str]], fraction: float
) -> None:
    data, written = chunked_recording
    path = tmp_path / "cut.mcap"
    cut = int(len(data) * fraction)
    path.write_bytes(data[:cut])
    try:
        recording = read_recording(path)
    except RecordingError:
        return
    assert set(_all_messages(recording)) <= written
    # "complete" means the footer record was read; only the closing magic bytes may be missing then.
    assert recording.complete == (cut >= len(data) - len(MCAP_MAGIC))


def test_truncated_header_and_empty_file_raise(
    tmp_path: Path, chunked_recording: tuple[bytes, set[str]]
) -> None:
    data, _ = chunked_recording
    path = tmp_path / "cut.mcap"
    for cut, message in [
        (0, "not an MCAP file"),
        (5, "not an MCAP file"),
        (20, "no message could be recovered"),
    ]:
        path.write_bytes(data[:cut])
        with pytest.raises(RecordingError, match=message) as info:
            read_recording(path)
        assert str(path) in str(info.value)


def test_missing_and_foreign_files_raise(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="cannot read"):
        read_recording(tmp_path / "missing.mcap")
    path = tmp_path / "notes.mcap"
    path.write_text("width: 1280\n")
    with pytest.raises(RecordingError, match="bad magic"):
        read_recording(path)


def test_corrupted_byte_in_a_chunk_loses_only_that_chunk(
    tmp_path: Path, chunked_recording: tuple[bytes, set[str]]
) -> None:
    data, written = chunked_recording
    corrupted = bytearray(data)
    corrupted[len(data) // 3] ^= 0x5A
    path = tmp_path / "flip.mcap"
    path.write_bytes(bytes(corrupted))
    recording = read_recording(path)
    recovered = _all_messages(recording)
    assert set(recovered) <= written
    assert len(written) - 40 < len(recovered) < len(written)  # one 2 KiB chunk holds well under 40 messages
    assert recording.complete and any("chunk at byte" in p for p in recording.problems)
    # mcap's own reader gives up on the whole file at the bad chunk.
    with open(path, "rb") as stream, pytest.raises(Exception):  # noqa: B017 - zstd, CRC or struct errors
        list(make_reader(stream, validate_crcs=True).iter_messages())


def _chunk_offsets(path: Path) -> list[int]:
    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    return sorted(index.chunk_start_offset for index in summary.chunk_indexes)


@pytest.mark.parametrize("mask", [0x01, 0x80])
def test_corrupt_chunk_length_resumes_at_the_next_indexed_chunk(
    tmp_path: Path, chunked_recording: tuple[bytes, set[str]], mask: int
) -> None:
    # A flipped bit in a record length breaks the framing of everything after it. The CRC-checked summary
    # of a finished file says where the next chunk starts, so at most the damaged chunk is lost (none when
    # the chunk's own fields still parse from the mis-sized body).
    data, written = chunked_recording
    (tmp_path / "good.mcap").write_bytes(data)
    offsets = _chunk_offsets(tmp_path / "good.mcap")
    corrupted = bytearray(data)
    corrupted[offsets[2] + 1] ^= mask  # lowest byte of the third chunk's u64 length
    path = tmp_path / "len.mcap"
    path.write_bytes(bytes(corrupted))
    recording = read_recording(path)
    recovered = _all_messages(recording)
    assert set(recovered) <= written
    assert len(recovered) > len(written) - 40
    assert any("resumed at the next indexed chunk" in problem for problem in recording.problems)
    # Without the summary (an unfinished file) the same damage ends the readable part.
    unfinished = tmp_path / "len_unfinished.mcap"
    unfinished.write_bytes(bytes(corrupted[: offsets[-1]]))
    partial = read_recording(unfinished)
    assert 0 < len(_all_messages(partial)) < len(recovered) and not partial.complete


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(position=st.floats(0.0, 1.0, exclude_max=True), mask=st.integers(1, 255))
def test_any_flipped_byte_never_invents_a_message(
    tmp_path: Path, chunked_recording: tuple[bytes, set[str]], position: float, mask: int
) -> None:
    data, written = chunked_recording
    corrupted = bytearray(data)
    corrupted[int(len(data) * position)] ^= mask
    path = tmp_path / "flip.mcap"
    path.write_bytes(bytes(corrupted))
    try:
        recording = read_recording(path)
    except RecordingError:
        return
    assert set(_all_messages(recording)) <= written


# ---------------------------------------------------------------------------------------------- bad messages


def test_bad_messages_are_counted_and_good_ones_kept(tmp_path: Path) -> None:
    # Written with mcap's raw writer: a buggy or hostile producer, not our RecordingWriter.
    path = tmp_path / "bad.mcap"
    good_frame, good_v2x = _frame("north", 2), _v2x(7, 1)
    det_topic, v2x_topic = detections_key("rsu-1", "north"), v2x_key(7)
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        schema = writer.register_schema(name="x", encoding="jsonschema", data=b"{}")
        det = writer.register_channel(topic=det_topic, message_encoding="json", schema_id=schema)
        v2x = writer.register_channel(topic=v2x_topic, message_encoding="json", schema_id=schema)
        cbor = writer.register_channel(
            topic=detections_key("rsu-1", "east"), message_encoding="cbor", schema_id=0
        )
        other = writer.register_channel(topic="rsu/rsu-1/health", message_encoding="json", schema_id=0)
        bad_box = json.loads(good_frame.model_dump_json())
        bad_box["boxes"][0]["x2"] = 0.0
        wrong_camera = good_frame.model_copy(update={"camera_id": "south", "stamp_ns": T0 + 1})
        payloads = [
            (det, b"{not json"),
            (det, json.dumps(bad_box).encode()),
            (det, good_frame.model_dump_json().encode()),
            (det, wrong_camera.model_dump_json().encode()),
            (det, good_frame.model_dump_json().replace('"score":0.9', '"score":NaN').encode()),
            (v2x, good_v2x.model_dump_json().encode()),
            (v2x, _v2x(8, 1).model_dump_json().encode()),  # station 8 on station 7's key
            (v2x, good_v2x.model_dump_json().replace('"lat":48.137155', '"lat":"48.137155"').encode()),
            (cbor, b"\xa0"),
            (other, b"{}"),
        ]
        for n, (channel, data) in enumerate(payloads):
            writer.add_message(channel_id=channel, log_time=T0 + n, data=data, publish_time=T0 + n)
        writer.finish()
    recording = read_recording(path)
    assert recording.detections == {"north": [good_frame]}
    assert recording.v2x == [good_v2x]
    assert recording.rejected == {det_topic: 4, v2x_topic: 2, detections_key("rsu-1", "east"): 1}
    assert "Invalid JSON" in recording.rejection_examples[det_topic]  # the first error of each topic
    assert recording.rejection_examples[v2x_topic].startswith("station_id: 8")
    assert "is not json" in recording.rejection_examples[detections_key("rsu-1", "east")]
    assert recording.channels["rsu/rsu-1/health"] == 1  # foreign channels are listed, not decoded
    assert recording.problems == () and recording.complete


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda d: d["boxes"][0].update(x2=0.0), "boxes.0"),
        (lambda d: d.update(stamp_ns=1_700_000_000), "stamp_ns"),  # seconds, not ns
        (lambda d: d.update(extra=1), "extra"),
        (lambda d: d["boxes"][0].update(cls="4"), "boxes.0.cls"),
    ],
)
def test_rejection_names_the_field(tmp_path: Path, mutate: object, field: str) -> None:
    path = tmp_path / "bad.mcap"
    payload = json.loads(_frame("north", 2).model_dump_json())
    mutate(payload)  # type: ignore[operator]
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        channel = writer.register_channel(
            topic=detections_key("r", "north"), message_encoding="json", schema_id=0
        )
        writer.add_message(
            channel_id=channel, log_time=T0, data=json.dumps(payload).encode(), publish_time=T0
        )
        writer.add_message(
            channel_id=channel,
            log_time=T0 + 1,
            data=_frame("north", 1).model_dump_json().encode(),
            publish_time=T0,
        )
        writer.finish()
    recording = read_recording(path)
    assert recording.rejected == {detections_key("r", "north"): 1}
    assert recording.rejection_examples[detections_key("r", "north")].startswith(field)
    assert recording.detections == {"north": [_frame("north", 1)]}  # the next good message still arrives


# ---------------------------------------------------------------------------------------------- simulator


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> tuple[SimulationResult, Path]:
    out = tmp_path_factory.mktemp("sim")
    # The smallest preset: one camera, one pass (~1 s).
    result = simulate("single-traversal", seed=3, ideal=True)
    write_simulation_mcap(result, out / "recording.mcap")
    write_simulation_files(result, out)
    return result, out


def test_simulation_round_trips_through_mcap_exactly(simulated: tuple[SimulationResult, Path]) -> None:
    result, out = simulated
    recording = read_recording(out / "recording.mcap")
    assert recording.rsu_id == result.rsu_id
    assert recording.detections == result.detections  # JSON keeps every float exactly
    assert recording.v2x == sorted(result.v2x, key=lambda m: (m.stamp_ns, m.station_id))
    assert recording.rejected == {} and recording.complete
    assert recording.channels[v2x_key(result.station_id)] == len(result.v2x)


def test_simulation_round_trips_through_toolbox_yaml(simulated: tuple[SimulationResult, Path]) -> None:
    result, out = simulated
    (camera,) = result.cameras
    frames = load_toolbox_detections(out / "detections.yaml", camera_id=camera.camera_id)
    expected = result.detections[camera.camera_id]
    assert [f.stamp_ns for f in frames] == [f.stamp_ns for f in expected]
    for got, want in zip(frames, expected, strict=True):
        assert [b.cls for b in got.boxes] == [b.cls for b in want.boxes]
        corners_got = [(b.x1, b.y1, b.x2, b.y2) for b in got.boxes]
        corners_want = [(b.x1, b.y1, b.x2, b.y2) for b in want.boxes]
        # 0.01 px file resolution: corner = centre - size/2 is off by at most 0.0075 px. Scores are not
        # part of the toolbox format and come back as 1.0.
        assert corners_got == [pytest.approx(c, abs=0.0075 + 1e-9) for c in corners_want]
    poses = load_toolbox_poses(out / "poses.yaml")
    assert [p.stamp_ns for p in poses] == [p.stamp_ns for p in result.poses]
    for got_pose, want_pose in zip(poses, result.poses, strict=True):
        assert (got_pose.x, got_pose.y, got_pose.z) == pytest.approx(
            (want_pose.x, want_pose.y, want_pose.z), abs=5e-4
        )
        assert (got_pose.yaw, got_pose.pitch, got_pose.roll) == pytest.approx(
            (want_pose.yaw, want_pose.pitch, want_pose.roll), abs=1e-9
        )
    assert load_intrinsics(out / "camera.yaml") == camera.intrinsics
    assert load_vehicle(out / "vehicle.yaml") == result.vehicle
    assert load_ground_truth(out / "ground_truth.json") == result.ground_truth[camera.camera_id]
