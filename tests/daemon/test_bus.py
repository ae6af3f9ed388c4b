"""daemon.bus on real Zenoh peers (127.0.0.1, a free port, no multicast): subscriptions, queryables,
liveliness, error replies, shutdown and start-up failures."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh
from helpers import free_port, wait_until

from daemon.bus import (
    NO_CALIBRATION,
    Bus,
    BusError,
    Handlers,
    client_config,
    open_session,
    query,
    query_replies,
    session_config,
)
from schemas.config import DaemonConfig, ZenohConfig

RECEIVED_NS = 1_700_000_000_123_456_789
CAMERAS = ("c1", "c2")


class FixedClock:
    def now_ns(self) -> int:
        return RECEIVED_NS


def make_config(endpoint: str, rsu_id: str = "r1") -> DaemonConfig:
    intrinsics = {"width": 1920, "height": 1080, "fx": 1000.0, "fy": 1000.0, "cx": 960.0, "cy": 540.0}
    return DaemonConfig.model_validate(
        {
            "rsu_id": rsu_id,
            "zenoh": {"listen": [endpoint]},
            "cameras": [{"camera_id": camera_id, "intrinsics": intrinsics} for camera_id in CAMERAS],
            "vehicles": [
                {
                    "station_id": 42,
                    "profile": {"length": 4.5, "width": 1.8, "height": 1.5, "imu_offset": [1.0, 0.9, 0.5]},
                }
            ],
        }
    )


@dataclass
class Stub:
    """Handlers that record their calls; `fail_next` makes the next call of that kind raise."""

    inbound: list[tuple[str, bytes, int]]
    triggers: list[str]
    results: dict[str, bytes]
    fail_next: set[str]
    inbound_fail_next: bool = False

    def on_inbound(self, key: str, payload: bytes, received_ns: int) -> None:
        if self.inbound_fail_next:
            self.inbound_fail_next = False
            raise RuntimeError("ingest queue exploded")
        self.inbound.append((key, payload, received_ns))

    def _maybe_fail(self, kind: str) -> None:
        if kind in self.fail_next:
            self.fail_next.discard(kind)
            raise RuntimeError(f"{kind} handler bug")

    def status(self, camera_id: str) -> bytes:
        self._maybe_fail(f"status:{camera_id}")
        return json.dumps({"camera_id": camera_id, "state": "collecting"}).encode()

    def calibration(self, camera_id: str) -> bytes | None:
        return self.results.get(camera_id)

    def trigger(self, camera_id: str) -> bytes:
        self.triggers.append(camera_id)
        return json.dumps({"camera_id": camera_id, "job_id": f"job-{camera_id}", "accepted": True}).encode()

    def health(self) -> bytes:
        self._maybe_fail("health")
        return json.dumps({"rsu_id": "r1"}).encode()

    def handlers(self) -> Handlers:
        return Handlers(
            calibration=self.calibration, status=self.status, trigger=self.trigger, health=self.health
        )


@dataclass
class Running:
    bus: Bus
    stub: Stub
    client: zenoh.Session
    endpoint: str


@pytest.fixture
def running() -> Iterator[Running]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    stub = Stub(inbound=[], triggers=[], results={}, fail_next=set())
    bus = Bus(make_config(endpoint), stub.on_inbound, stub.handlers(), FixedClock())
    bus.open()
    try:
        client = open_session(client_config([endpoint]), [endpoint])
        try:
            yield Running(bus, stub, client, endpoint)
        finally:
            client.close()  # type: ignore[no-untyped-call]  # zenoh stubs lack -> None
    finally:
        bus.close()


def _keys(replies: list[tuple[str, bytes]]) -> list[str]:
    return sorted(key for key, _ in replies)


def test_subscriptions_hand_detections_and_v2x_to_on_inbound_with_keys_intact(running: Running) -> None:
    sent = {
        "rsu/r1/camera/c1/detections": b'{"camera_id": "c1", "n": 1}',
        "rsu/r1/camera/c2/detections": b'{"camera_id": "c2", "n": 2}',
        "rsu/r1/camera/unknown/detections": b"not even json",  # ingest rejects it, the bus does not judge
        "v2x/cam/42": b'{"station_id": 42}',
    }
    running.client.put(
        "rsu/r2/camera/c1/detections",
        b"another RSU's camera",
        congestion_control=zenoh.CongestionControl.BLOCK,
    )  # not subscribed
    running.client.put(
        "rsu/r1/camera/c1/calibration", b"our own output", congestion_control=zenoh.CongestionControl.BLOCK
    )  # not subscribed
    for key, payload in sent.items():
        running.client.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: len(running.stub.inbound) >= len(sent), timeout_s=5)
    assert sorted(running.stub.inbound) == sorted((k, p, RECEIVED_NS) for k, p in sent.items())


def test_an_on_inbound_failure_is_counted_and_the_next_sample_still_arrives(running: Running) -> None:
    running.stub.inbound_fail_next = True
    running.client.put("v2x/cam/1", b"first", congestion_control=zenoh.CongestionControl.BLOCK)
    running.client.put("v2x/cam/2", b"second", congestion_control=zenoh.CongestionControl.BLOCK)
    wait_until(lambda: running.stub.inbound, timeout_s=5)
    assert running.stub.inbound == [("v2x/cam/2", b"second", RECEIVED_NS)]
    assert running.bus.callback_errors == 1


def test_queryables_answer_status_health_trigger_and_calibration_on_exact_keys(running: Running) -> None:
    running.stub.results["c1"] = b'{"result_id": "res-1"}'
    status = query(running.client, "rsu/r1/camera/c2/calibration/status", timeout_s=5)
    assert status == [("rsu/r1/camera/c2/calibration/status", b'{"camera_id": "c2", "state": "collecting"}')]
    assert query(running.client, "rsu/r1/health", timeout_s=5) == [("rsu/r1/health", b'{"rsu_id": "r1"}')]
    calibration = query(running.client, "rsu/r1/camera/c1/calibration", timeout_s=5)
    assert calibration == [("rsu/r1/camera/c1/calibration", b'{"result_id": "res-1"}')]
    [(key, payload)] = query(running.client, "rsu/r1/camera/c2/calibration/trigger", timeout_s=5)
    assert key == "rsu/r1/camera/c2/calibration/trigger" and json.loads(payload)["job_id"] == "job-c2"
    assert running.stub.triggers == ["c2"]


def test_calibration_without_a_result_is_an_error_reply_given_at_once(running: Running) -> None:
    started = time.monotonic()
    replies = query_replies(running.client, "rsu/r1/camera/c2/calibration", timeout_s=10)
    # Finalised as soon as answered: the getter does not sit out its 10 s timeout.
    assert time.monotonic() - started < 5
    assert replies.ok == []
    assert replies.errors == [f"rsu/r1/camera/c2/calibration: {NO_CALIBRATION}"]
    assert query(running.client, "rsu/r1/camera/c2/calibration", timeout_s=10) == []


def test_fleet_wildcard_queries_read_every_camera_and_never_trigger(running: Running) -> None:
    running.stub.results["c2"] = b'{"result_id": "res-2"}'
    statuses = query(running.client, "rsu/**/calibration/status", timeout_s=5)
    assert _keys(statuses) == [f"rsu/r1/camera/{c}/calibration/status" for c in CAMERAS]
    assert _keys(query(running.client, "rsu/*/camera/*/calibration/status", timeout_s=5)) == _keys(statuses)
    assert _keys(query(running.client, "rsu/*/health", timeout_s=5)) == ["rsu/r1/health"]

    everything = query_replies(running.client, "rsu/**", timeout_s=5)
    assert _keys(everything.ok) == [
        "rsu/r1/camera/c1/calibration/status",
        "rsu/r1/camera/c2/calibration",
        "rsu/r1/camera/c2/calibration/status",
        "rsu/r1/health",
    ]
    assert f"rsu/r1/camera/c1/calibration: {NO_CALIBRATION}" in everything.errors
    not_triggered = sorted(e for e in everything.errors if "trigger" in e)
    assert len(not_triggered) == 2 and all("needs the exact key" in e for e in not_triggered)
    assert query(running.client, "rsu/r1/camera/*/calibration/trigger", timeout_s=5) == []
    assert running.stub.triggers == []


def test_an_unknown_camera_gets_an_error_naming_the_configured_ones(running: Running) -> None:
    replies = query_replies(running.client, "rsu/r1/camera/c9/calibration/status", timeout_s=5)
    assert replies.ok == []
    assert replies.errors == [
        "rsu/r1/camera/c9/calibration/status: no such camera on rsu r1 (cameras: c1, c2)"
    ]
    assert query_replies(running.client, "rsu/r1/camera/c9/calibration/trigger", timeout_s=5).errors
    assert running.stub.triggers == []


def test_a_handler_that_raises_fails_only_its_own_answer(running: Running) -> None:
    running.stub.fail_next.update({"health", "status:c1"})
    failed = query_replies(running.client, "rsu/r1/health", timeout_s=5)
    assert failed.ok == [] and failed.errors == [
        "rsu/r1/health: internal error: RuntimeError: health handler bug"
    ]
    # The other camera of a wildcard query is still answered while c1's handler raises.
    mixed = query_replies(running.client, "rsu/r1/camera/*/calibration/status", timeout_s=5)
    assert _keys(mixed.ok) == ["rsu/r1/camera/c2/calibration/status"]
    assert mixed.errors == [
        "rsu/r1/camera/c1/calibration/status: internal error: RuntimeError: status:c1 handler bug"
    ]
    # The serving loops survived: later queries are answered normally.
    assert _keys(query(running.client, "rsu/r1/health", timeout_s=5)) == ["rsu/r1/health"]
    assert len(query(running.client, "rsu/r1/camera/*/calibration/status", timeout_s=5)) == 2


def test_publish_calibration_puts_on_the_camera_key(running: Running) -> None:
    received: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            received.append((str(sample.key_expr), sample.payload.to_bytes()))

    subscriber = running.client.declare_subscriber("rsu/*/camera/*/calibration", on_sample)
    try:
        # The subscription needs a moment to reach the bus's session: publish until one arrives.
        def published() -> bool:
            running.bus.publish_calibration("c2", b'{"result_id": "res-2"}')
            with lock:
                return bool(received)

        wait_until(published, timeout_s=5, interval_s=0.05)
        assert received[0] == ("rsu/r1/camera/c2/calibration", b'{"result_id": "res-2"}')
    finally:
        subscriber.undeclare()  # type: ignore[no-untyped-call]
    with pytest.raises(KeyError, match="c9"):
        running.bus.publish_calibration("c9", b"{}")


def test_liveliness_token_is_visible_while_open_and_gone_after_close(running: Running) -> None:
    def alive() -> list[str]:
        return _keys(query_replies_liveliness(running.client, "rsu/*/alive"))

    assert alive() == ["rsu/r1/alive"]
    running.bus.close()
    wait_until(lambda: alive() == [], timeout_s=5)
    # Closed means closed: its queryables are gone too.
    assert query_replies(running.client, "rsu/r1/health", timeout_s=1).ok == []


def query_replies_liveliness(session: zenoh.Session, key: str) -> list[tuple[str, bytes]]:
    return [(str(r.ok.key_expr), b"") for r in session.liveliness().get(key, timeout=2.0) if r.ok is not None]


def test_close_is_idempotent_quick_and_safe_before_open() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    stub = Stub(inbound=[], triggers=[], results={}, fail_next=set())
    never_opened = Bus(make_config(endpoint), stub.on_inbound, stub.handlers(), FixedClock())
    never_opened.close()
    never_opened.close()

    bus = Bus(make_config(endpoint), stub.on_inbound, stub.handlers(), FixedClock())
    bus.open()
    try:
        started = time.monotonic()
        bus.close()
        assert time.monotonic() - started < 1.0
    finally:
        bus.close()
    with pytest.raises(BusError, match="already closed"):
        bus.open()
    with pytest.raises(BusError, match="not open"):
        bus.publish_calibration("c1", b"{}")
    # The port is free again: a new bus can listen there.
    with Bus(make_config(endpoint), stub.on_inbound, stub.handlers(), FixedClock()):
        pass


def test_close_stays_quick_while_a_handler_is_stuck() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    stub = Stub(inbound=[], triggers=[], results={}, fail_next=set())
    entered, release = threading.Event(), threading.Event()

    def stuck_health() -> bytes:
        entered.set()
        release.wait(10)
        return b"{}"

    handlers = Handlers(stub.calibration, stub.status, stub.trigger, stuck_health)
    bus = Bus(make_config(endpoint), stub.on_inbound, handlers, FixedClock())
    bus.open()
    client = open_session(client_config([endpoint]), [endpoint])
    getter = threading.Thread(target=query, args=(client, "rsu/r1/health", 10.0), daemon=True)
    try:
        getter.start()
        assert entered.wait(5)
        started = time.monotonic()
        bus.close()
        assert time.monotonic() - started < 1.0
        # Closing the session finalises the pending query: the getter does not wait out its 10 s.
        getter.join(5)
        assert not getter.is_alive()
    finally:
        release.set()
        bus.close()
        client.close()  # type: ignore[no-untyped-call]


def test_a_port_already_in_use_is_a_clear_error_naming_the_endpoint() -> None:
    stub = Stub(inbound=[], triggers=[], results={}, fail_next=set())
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        endpoint = f"tcp/127.0.0.1:{taken.getsockname()[1]}"
        bus = Bus(make_config(endpoint), stub.on_inbound, stub.handlers(), FixedClock())
        with pytest.raises(BusError) as caught:
            bus.open()
        bus.close()  # safe after a failed open
    message = str(caught.value)
    assert endpoint in message and "Address already in use" in message
    assert ".rs:" not in message  # Zenoh's Rust source locations are stripped


def test_a_second_daemon_on_the_same_endpoint_fails_and_the_first_keeps_serving(running: Running) -> None:
    stub = Stub(inbound=[], triggers=[], results={}, fail_next=set())
    second = Bus(make_config(running.endpoint), stub.on_inbound, stub.handlers(), FixedClock())
    with pytest.raises(BusError, match="already listens there"):
        second.open()
    second.close()
    assert _keys(query(running.client, "rsu/r1/health", timeout_s=5)) == ["rsu/r1/health"]


def _get(config: zenoh.Config, key: str) -> Any:
    return json.loads(config.get_json(key))


def test_session_config_without_a_file_applies_every_field() -> None:
    zconf = ZenohConfig(listen=["tcp/127.0.0.1:7999"], connect=["tcp/10.0.0.1:7447"])
    config = session_config(zconf)
    assert _get(config, "mode") == "peer"
    assert _get(config, "listen/endpoints") == ["tcp/127.0.0.1:7999"]
    assert _get(config, "connect/endpoints") == ["tcp/10.0.0.1:7447"]
    assert _get(config, "scouting/multicast/enabled") is False


def test_session_config_keeps_the_file_unless_the_yaml_sets_a_field(tmp_path: Path) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text(
        "{ mode: 'peer', listen: { endpoints: ['tcp/0.0.0.0:7448'] },"
        " connect: { endpoints: ['tcp/10.0.0.9:7447'] }, scouting: { multicast: { enabled: true } } }"
    )
    from_file = session_config(ZenohConfig.model_validate({"config_file": str(path)}))
    assert _get(from_file, "listen/endpoints") == ["tcp/0.0.0.0:7448"]
    assert _get(from_file, "connect/endpoints") == ["tcp/10.0.0.9:7447"]
    # Multicast stays off unless the YAML itself asks for it.
    assert _get(from_file, "scouting/multicast/enabled") is False

    overridden = session_config(
        ZenohConfig.model_validate(
            {"config_file": str(path), "listen": ["tcp/127.0.0.1:7999"], "multicast_scouting": True}
        )
    )
    assert _get(overridden, "listen/endpoints") == ["tcp/127.0.0.1:7999"]
    assert _get(overridden, "connect/endpoints") == ["tcp/10.0.0.9:7447"]
    assert _get(overridden, "scouting/multicast/enabled") is True

    missing = tmp_path / "missing.json5"
    with pytest.raises(BusError, match=r"zenoh\.config_file .*missing\.json5"):
        session_config(ZenohConfig.model_validate({"config_file": str(missing)}))


def test_client_config_connects_listens_nowhere_and_never_multicasts() -> None:
    config = client_config(["tcp/10.0.0.1:7447"])
    assert _get(config, "mode") == "peer"
    assert _get(config, "connect/endpoints") == ["tcp/10.0.0.1:7447"]
    assert _get(config, "listen/endpoints") == []
    assert _get(config, "scouting/multicast/enabled") is False
    assert _get(client_config([]), "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _get(client_config(["tcp/10.0.0.2:7447"], mode="client"), "mode") == "client"
