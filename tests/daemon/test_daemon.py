"""The daemon end to end on real Zenoh sessions (loopback, free ports): a simulated RSU and calibration
vehicle publish, the daemon counts traversals, calibrates in its worker process, publishes and answers
queries.

Time is accelerated with a ScaledClock shared by the daemon and the publisher, so a 4-minute drive takes
seconds. Every wait polls with a deadline.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from helpers import free_port, wait_until

from daemon.bus import client_config, query
from daemon.clock import ScaledClock
from daemon.demo import BusMessage, demo_config, publish_messages, simulation_messages
from daemon.main import Daemon
from daemon.recording import list_recordings, read_window
from daemon.state import CameraState, StateStore
from pipeline.camera import camera_centre
from schemas.common import decode_json
from schemas.config import DaemonConfig
from schemas.results import CalibrationResult, CalibrationStatus, Health
from sim.simulate import SimulationResult, simulate

RATE = 40.0  # time acceleration: the 251 s sil-west drive in ~6 s


@pytest.fixture(scope="module")
def sim() -> SimulationResult:
    return simulate("sil-west", 0, ideal=True)  # the daemon's mechanics need a scene it calibrates


@pytest.fixture(scope="module")
def messages(sim: SimulationResult) -> list[BusMessage]:
    return simulation_messages(sim)


def _config(sim: SimulationResult, state_dir: Path) -> DaemonConfig:
    return demo_config(sim, state_dir, free_port())


@pytest.fixture
def client_for() -> Iterator[object]:
    sessions: list[zenoh.Session] = []

    def open_client(config: DaemonConfig, connected: bool = True) -> zenoh.Session:
        """A client of the daemon; `connected`: wait until the daemon answers it, so the daemon's
        declarations (its subscribers among them) have reached this session and a put is routed."""
        session = zenoh.open(client_config(config.zenoh.listen))
        sessions.append(session)
        if connected:
            wait_until(lambda: _health(session, config) is not None, timeout_s=30)
        return session

    try:
        yield open_client
    finally:
        for session in sessions:
            session.close()


def _status(session: zenoh.Session, config: DaemonConfig, camera_id: str) -> CalibrationStatus | None:
    replies = query(session, f"rsu/{config.rsu_id}/camera/{camera_id}/calibration/status", timeout_s=2.0)
    return decode_json(CalibrationStatus, replies[0][1]) if replies else None


def _health(session: zenoh.Session, config: DaemonConfig) -> Health | None:
    replies = query(session, f"rsu/{config.rsu_id}/health", timeout_s=2.0)
    return decode_json(Health, replies[0][1]) if replies else None


def _play(
    session: zenoh.Session, messages: list[BusMessage], clock: ScaledClock, until_ns: int | None = None
) -> None:
    selected = [m for m in messages if until_ns is None or m.stamp_ns <= until_ns]
    publish_messages(session, selected, clock, threading.Event())


def _traversal_ends(sim: SimulationResult, camera_id: str) -> list[int]:
    """Last stamp at which the truth shows the calibration vehicle, per traversal of this camera."""
    ends: dict[int, int] = {}
    for frame in sim.ground_truth[camera_id].frames:
        if frame.calib_box is not None and frame.traversal is not None:
            ends[frame.traversal] = max(ends.get(frame.traversal, 0), frame.stamp_ns)
    return [ends[k] for k in sorted(ends)]


def test_two_cameras_calibrate_over_the_bus_and_survive_a_restart(
    sim: SimulationResult, messages: list[BusMessage], tmp_path: Path, client_for: object
) -> None:
    config = _config(sim, tmp_path / "state")
    clock = ScaledClock(messages[0].stamp_ns - 1_000_000_000, RATE)
    published: list[bytes] = []
    daemon = Daemon(config, clock=clock)
    try:
        daemon.start()
        client = client_for(config)  # type: ignore[operator]
        subscriber = client.declare_subscriber(
            f"rsu/{config.rsu_id}/camera/*/calibration", lambda s: published.append(s.payload.to_bytes())
        )
        _play(client, messages, clock)
        cameras = [camera.camera_id for camera in config.cameras]
        wait_until(
            lambda: all(
                (s := _status(client, config, c)) is not None and s.state == "calibrated" for c in cameras
            ),
            timeout_s=90,
        )
        wait_until(lambda: len(published) >= 2, timeout_s=10)
        subscriber.undeclare()
        results = {}
        for payload in published:
            result = decode_json(CalibrationResult, payload)
            results[result.camera_id] = result
        assert set(results) == set(cameras)
        origin = np.array([sim.origin.x, sim.origin.y, sim.origin.z])
        for camera in sim.cameras:
            result = results[camera.camera_id]
            assert result.verdict.is_accepted
            assert result.quality is not None and result.quality.traversals >= 2
            assert result.provenance.station_id == sim.station_id
            true_centre = camera_centre(camera.R_cam_from_local, camera.t_cam_from_local) + origin
            assert result.camera_position is not None
            # the pipeline benchmark's sil-west worst case is 0.19 m; 0.5 m is the demo's acceptance bound
            assert np.linalg.norm(np.array(result.camera_position.utm) - true_centre) < 0.5
            status = _status(client, config, camera.camera_id)
            assert status is not None and status.current_result_id == result.result_id
            assert status.traversals_needed == 3 and status.last_job is not None
            assert status.last_job.verdict is not None and status.last_job.verdict.is_accepted
        health = _health(client, config)
        assert health is not None
        assert health.counters["detections.accepted"] == sum(len(f) for f in sim.detections.values())
        assert health.counters["v2x.accepted"] == len(sim.v2x)
        assert health.disk is not None and health.disk.recordings_files >= 1
    finally:
        daemon.stop()

    # Restart on the same state: the queryable answers the stored result at once.
    daemon = Daemon(config, clock=clock)
    try:
        daemon.start()
        client = client_for(config)  # type: ignore[operator]
        for camera_id, result in results.items():
            replies = query(client, f"rsu/{config.rsu_id}/camera/{camera_id}/calibration", timeout_s=2.0)
            assert [decode_json(CalibrationResult, p).result_id for _, p in replies] == [result.result_id]
            status = _status(client, config, camera_id)
            assert status is not None and status.state == "calibrated"
    finally:
        daemon.stop()


@pytest.mark.parametrize("withdrawn", [False, True], ids=["plain", "after-a-withdrawal"])
def test_restart_mid_collection_keeps_traversals(
    sim: SimulationResult, messages: list[BusMessage], tmp_path: Path, client_for: object, withdrawn: bool
) -> None:
    """The restarted daemon counts the drive-pasts again from its recordings. `withdrawn`: a result was
    withdrawn before the stop (daemon.publication: the camera moved after the first drive-past); the
    restart neither finds it current again (its current.json is gone while the state still names it, as
    when the file is lost) nor counts the drive-past from before the move."""
    config = _config(sim, tmp_path / "state")
    camera_id = config.cameras[0].camera_id
    ends = _traversal_ends(sim, camera_id)
    assert len(ends) == 3
    # Stop between the second and the third drive-past, once the vehicle has been gone for a while.
    cut_ns = ends[1] + 10_000_000_000
    clock = ScaledClock(messages[0].stamp_ns - 1_000_000_000, RATE)
    daemon = Daemon(config, clock=clock)
    try:
        daemon.start()
        client = client_for(config)  # type: ignore[operator]
        _play(client, messages, clock, until_ns=cut_ns)
        wait_until(lambda: (s := _status(client, config, camera_id)) is not None and s.traversals == 2, 20)
        status = _status(client, config, camera_id)
        assert status is not None and status.state == "collecting"
    finally:
        daemon.stop()
    if withdrawn:
        store = StateStore(config.storage.state_dir)
        state = (store.load_camera_state(camera_id) or CameraState()).model_copy(
            update={"current_result_id": "withdrawn", "not_before_ns": ends[0] + 1}
        )
        store.save_camera_state(camera_id, state)

    daemon = Daemon(config, clock=clock)
    try:
        daemon.start()
        client = client_for(config)  # type: ignore[operator]
        status = _status(client, config, camera_id)
        assert status is not None and status.traversals == (1 if withdrawn else 2), status
        assert status.current_result_id is None and status.state == "collecting"
    finally:
        daemon.stop()


def messages_v2x_with_infinite_lat(message: dict[str, object]) -> bytes:
    text = json.dumps({**message, "lat": 1.5})
    return text.replace('"lat": 1.5', '"lat": 1e999').encode()  # JSON has no inf; 1e999 overflows to it


def test_bad_input_is_counted_and_good_traffic_carries_on(
    sim: SimulationResult, messages: list[BusMessage], tmp_path: Path, client_for: object
) -> None:
    config = _config(sim, tmp_path / "state")
    camera_id = config.cameras[0].camera_id
    key = f"rsu/{config.rsu_id}/camera/{camera_id}/detections"
    good = [m for m in messages if m.key == key][:40]
    frame = json.loads(good[0].payload)
    station = sim.station_id
    v2x = [json.loads(m.payload) for m in messages if m.key == f"v2x/cam/{station}"][:3]
    bad: list[tuple[str, bytes]] = [
        (key, b"{not json"),
        (key, json.dumps({**frame, "stamp_ns": "12"}).encode()),  # wrong type
        (key, json.dumps(frame).replace('"x1":', '"x1":NaN,"_":').encode()),  # NaN
        (key, b"[" + b"1," * (config.ingest.max_payload_bytes // 2) + b"1]"),  # oversized
        (key, good[5].payload),  # out of order after good[10] below
        (
            f"v2x/cam/{station + 1}",
            json.dumps({**v2x[0], "station_id": station + 1}).encode(),
        ),  # other station
        (f"v2x/cam/{station}", messages_v2x_with_infinite_lat(v2x[1])),
    ]
    clock = ScaledClock(messages[0].stamp_ns - 1_000_000_000, 1.0)
    daemon = Daemon(config, clock=clock)
    try:
        daemon.start()
        client = client_for(config)  # type: ignore[operator]
        # BLOCK: under load Zenoh may otherwise drop a put at the sender, which would look like a loss here.
        publisher = client.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        for message in good[:11]:
            publisher.put(message.payload)
        publisher.put(good[10].payload)  # duplicate stamp
        for bad_key, payload in bad:
            client.put(bad_key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
        for message in good[11:]:
            publisher.put(message.payload)
        # Detections and V2X arrive on different keys, whose callbacks Zenoh does not order against each
        # other: wait for the last of each (CI once read the counters before the V2X rejection was counted).
        wait_until(
            lambda: (
                (h := _health(client, config)) is not None
                and h.counters.get("detections.accepted") == 40
                and "v2x.other_station" in h.counters
                and "v2x.rejected.json" in h.counters
            ),
            timeout_s=10,
        )
        health = _health(client, config)
        assert health is not None
        counters = health.counters
        assert counters["detections.rejected.json"] == 3  # not JSON, a wrong type, NaN
        assert counters["detections.rejected.oversized"] == 1
        assert counters["detections.rejected.duplicate"] == 1
        assert counters["detections.rejected.out_of_order"] == 1
        assert counters["v2x.other_station"] == 1
        assert counters["v2x.rejected.json"] == 1
        publisher.undeclare()
    finally:
        daemon.stop()
    # Only the valid messages were logged.
    files = [f.path for f in list_recordings(tmp_path / "state" / "recordings", config.rsu_id)]
    window = read_window(files, config.rsu_id, camera_id, {station, station + 1}, 0, 2**62)
    assert [f.stamp_ns for f in window.detections] == [m.stamp_ns for m in good]


def test_sigterm_finishes_the_recording_and_exits(
    sim: SimulationResult, messages: list[BusMessage], tmp_path: Path, client_for: object
) -> None:
    import signal
    import subprocess
    import sys

    import yaml
    from mcap.reader import make_reader

    config = _config(sim, tmp_path / "state")
    config_path = tmp_path / "rsu.yaml"
    config_path.write_text(yaml.safe_dump(config.model_dump(mode="json")))
    process = subprocess.Popen(
        [sys.executable, "-m", "daemon.cli", "daemon", "--config", str(config_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        client = client_for(config)  # type: ignore[operator]
        wait_until(lambda: _health(client, config) is not None, timeout_s=30)
        sent = messages[:200]
        # BLOCK: under load Zenoh may otherwise drop a put at the sender (the default for puts), which would
        # look like a loss here (seen once in CI: the count never reached 200).
        for message in sent:
            client.put(message.key, message.payload, congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(
            lambda: (
                (h := _health(client, config)) is not None
                and h.counters.get("detections.accepted", 0) + h.counters.get("v2x.accepted", 0) == len(sent)
            ),
            timeout_s=10,
        )
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=10) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    files = list_recordings(tmp_path / "state" / "recordings", config.rsu_id)
    assert len(files) == 1
    with open(files[0].path, "rb") as stream:
        summary = make_reader(stream).get_summary()  # a finished file has a summary section
    assert summary is not None and summary.statistics is not None
    # Every message received, once on its raw channel and once as its Foxglove view (storage.foxglove_views).
    per_schema: dict[str, int] = {}
    for channel_id, count in summary.statistics.channel_message_counts.items():
        name = summary.schemas[summary.channels[channel_id].schema_id].name
        per_schema[name] = per_schema.get(name, 0) + count
    assert per_schema["rsucal.DetectionFrame"] + per_schema["rsucal.V2xPosition"] == len(sent)
    assert per_schema["foxglove.ImageAnnotations"] == per_schema["rsucal.DetectionFrame"]
    assert per_schema["foxglove.LocationFix"] == per_schema["rsucal.V2xPosition"]
    assert summary.statistics.message_count == 2 * len(sent)


def test_a_dead_thread_stops_the_daemon_with_its_reason(sim: SimulationResult, tmp_path: Path) -> None:
    """Half-alive is worse than dead: a supervisor (systemd, Docker) restarts a daemon that exits."""
    config = _config(sim, tmp_path / "state")
    daemon = Daemon(config)
    try:
        daemon.start()

        def broken_control_action() -> None:
            raise ZeroDivisionError("injected")

        # The inbox carries control actions run on the ingest thread; this one stands for any bug there.
        daemon._inbox.put(broken_control_action)
        wait_until(lambda: daemon.failure is not None, timeout_s=5)
        assert "rsucal-ingest" in str(daemon.failure) and "ZeroDivisionError" in str(daemon.failure)
        assert daemon.wait(timeout_s=5)  # the stop event is set
    finally:
        daemon.stop()


def test_a_lens_model_that_turns_back_inside_the_image_is_warned_at_start(
    sim: SimulationResult, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    config = _config(sim, tmp_path / "state")
    turning = config.cameras[0].intrinsics.model_copy(
        update={"fx": 900.0, "fy": 900.0, "dist": (-0.30, 0.09, 0.0005, -0.0004, -0.012)}
    )
    cameras = [config.cameras[0].model_copy(update={"intrinsics": turning}), *config.cameras[1:]]
    caplog.set_level(logging.WARNING, logger="daemon.main")
    daemon = Daemon(config.model_copy(update={"cameras": cameras}))
    try:
        daemon.start()
    finally:
        daemon.stop()
    warned = [r.getMessage() for r in caplog.records if "distortion turns back" in r.getMessage()]
    assert len(warned) == 1 and warned[0].startswith(f"camera {config.cameras[0].camera_id}: dist: "), warned


def test_kill_9_leaves_a_readable_recording_and_the_restart_keeps_the_count(
    sim: SimulationResult, messages: list[BusMessage], tmp_path: Path, client_for: object
) -> None:
    """No shutdown at all: what was flushed (every storage.flush_interval_s) survives, and a restarted daemon
    rebuilds its traversal count from the unfinished file."""
    import subprocess
    import sys

    import yaml

    config = _config(sim, tmp_path / "state")
    camera_id = config.cameras[0].camera_id
    config_path = tmp_path / "rsu.yaml"
    config_path.write_text(yaml.safe_dump(config.model_dump(mode="json")))
    recordings = tmp_path / "state" / "recordings"
    # Everything up to shortly after the first drive-past, sent as fast as the bus takes it.
    sent = [m for m in messages if m.stamp_ns <= _traversal_ends(sim, camera_id)[0] + 10_000_000_000]
    station_ids = {sim.station_id}
    process = subprocess.Popen(
        [sys.executable, "-m", "daemon.cli", "daemon", "--config", str(config_path)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        client = client_for(config)  # type: ignore[operator]
        wait_until(lambda: _health(client, config) is not None, timeout_s=30)
        publishers = {
            key: client.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            for key in {m.key for m in sent}
        }
        for message in sent:
            publishers[message.key].put(message.payload)

        def flushed() -> int:
            files = [f.path for f in list_recordings(recordings, config.rsu_id)]
            window = read_window(files, config.rsu_id, None, station_ids, 0, 2**62)
            return len(window.detections) + len(window.v2x)

        wait_until(lambda: flushed() == len(sent), timeout_s=30)
        process.kill()  # SIGKILL: no summary, no footer
        process.wait(timeout=10)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert flushed() == len(sent)

    daemon = Daemon(config)  # the same state dir: recovery reads the unfinished file
    try:
        daemon.start()
        client = client_for(config)  # type: ignore[operator]
        status = _status(client, config, camera_id)
        assert status is not None and status.traversals == 1
    finally:
        daemon.stop()
