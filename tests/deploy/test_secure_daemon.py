"""The REAL daemon behind the secure Zenoh config (deploy/zenoh/secure.json5): mutual TLS + access control.

A Daemon runs with `zenoh.config_file` = the deployed secure peer config (only the certificate paths point at
certificates made in the test by deploy/make-test-certs.sh) and, as deploy/README.md documents, its `listen`
in the RSU config: a TLS endpoint on a free loopback port. Its RSU is deploy/rsu.example.yaml's (sil-west),
whose cameras and vehicle the deployed rules name, so the daemon's start-up check of them passes. Its state
directory is pre-seeded with an accepted current result (the simulator's true pose of a sil-west camera), so
it answers a calibration as soon as it is on the bus. Every other node is a real Zenoh session in client mode,
with a copy of secure-client.json5 holding its own certificate: the operator, the calibration vehicle
(vehicle-4242), the cameras' detector (detector-sil-west) and an intruder with a valid certificate of the CA
but no rights (untrusted-client). One test runs the router topology of compose.secure.yaml instead.

"Never arrives" is proved without sleeping, from the order of messages on one link: a sender's put and its
following query travel in order, and the daemon hands an admitted put to its subscriber callback (which
enqueues it on the ingest inbox) before it reads the next message of that link. So once the daemon has
answered the intruder's query, any put of the intruder's that got past the access control is in the inbox.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import zenoh
from helpers import free_port, wait_until

from daemon import cli
from daemon.bus import NO_CALIBRATION, query_replies
from daemon.demo import demo_config
from daemon.ingest import (
    DETECTIONS_ACCEPTED,
    DETECTIONS_RECEIVED,
    UNKNOWN_KEY_REJECTED,
    V2X_ACCEPTED,
    V2X_OTHER_STATION,
    V2X_RECEIVED,
)
from daemon.keys import alive_key, calibration_key, detections_key, health_key, trigger_key, v2x_key
from daemon.main import Daemon
from daemon.recording import list_recordings, read_recording, read_window
from daemon.state import StateStore
from daemon.status import fetch_status, status_main
from pipeline.metrics import result_from_ground_truth
from schemas.common import decode_json
from schemas.config import DaemonConfig
from schemas.messages import DetectionFrame
from schemas.results import CalibrationResult
from sim.simulate import simulate

ZENOH_DIR = Path(__file__).resolve().parents[2] / "deploy" / "zenoh"
RSU = "sil-west"  # deploy/rsu.example.yaml's, with the cameras of the simulator's sil-west preset
OTHER_STATION = 777  # a station no certificate may speak for
ANSWERED_S = 5.0  # an allowed query is answered within this (loopback; generous for loaded CI)
REFUSED_S = 0.5  # a query nobody can answer: the getter waits this long for nothing
COUNTED_S = 5.0  # an admitted V2X message is counted by the ingest thread within this


# ---------------------------------------------------------------------------------------------- configs


def _tls(certs: Path, identity: str | None) -> dict[str, Any]:
    """Certificate settings of one identity (None: no certificate of its own; the CA to check servers)."""
    settings: dict[str, Any] = {"transport/link/tls/root_ca_certificate": str(certs / "ca.pem")}
    for side in ("listen", "connect"):
        for suffix, kind in (("pem", "certificate"), ("key", "private_key")):
            path = f"transport/link/tls/{side}_{kind}"
            settings[path] = str(certs / f"{identity}.{suffix}") if identity is not None else None
    return settings


def _deployed(file_name: str, settings: dict[str, Any]) -> zenoh.Config:
    """A file of deploy/zenoh, strictly parsed by zenoh, with `settings` (json5 path -> value) replaced."""
    config = zenoh.Config.from_file(str(ZENOH_DIR / file_name))
    for path, value in settings.items():
        config.insert_json5(path, json.dumps(value))
    return config


def _write(config: zenoh.Config, path: Path) -> Path:
    """The config as a file (zenoh prints a Config as JSON, which is JSON5)."""
    path.write_text(str(config), encoding="utf-8")
    return path


# ---------------------------------------------------------------------------------------------- the site


@dataclass
class Site:
    """A started daemon on the secure config, with what it was seeded with."""

    certs: Path
    files: Path  # where client config files are written
    endpoint: str  # tls/127.0.0.1:PORT
    config: DaemonConfig
    daemon: Daemon
    result: CalibrationResult  # the seeded current result
    current_json: Path  # cameras/{cam}/current.json
    current_bytes: bytes  # its bytes as seeded
    drive: Iterator[bytes]  # the calibration vehicle's V2X positions of the simulation, restamped to now
    frames: Iterator[DetectionFrame]  # the seeded camera's detections of the simulation, restamped too

    @property
    def rsu(self) -> str:
        return self.config.rsu_id

    @property
    def camera(self) -> str:
        return self.result.camera_id

    @property
    def station(self) -> int:
        return self.config.vehicles[0].station_id

    def client_file(self, identity: str, connect: bool = True) -> Path:
        """A copy of secure-client.json5 with `identity`'s certificate; connecting to the daemon, or (with
        connect=False) to the deployed `tls/router:7447`, which must then be overridden (--connect)."""
        settings = _tls(self.certs, identity)
        if connect:
            settings["connect/endpoints"] = [self.endpoint]
        suffix = "" if connect else "-router"
        return _write(_deployed("secure-client.json5", settings), self.files / f"{identity}{suffix}.json5")

    def counters(self) -> dict[str, int]:
        return self.daemon.health().counters

    def position(self) -> bytes:
        """The vehicle's next position (each a new stamp, so the daemon accepts it, no duplicate)."""
        return next(self.drive)

    def frame(self) -> DetectionFrame:
        """The camera's next detection frame (a new stamp each)."""
        return next(self.frames)

    def recorded(self) -> tuple[set[int], dict[int, set[int]]]:
        """Stamps in the daemon's recordings so far: the seeded camera's detections, and V2X per station.
        The recorder flushes every storage.flush_interval_s; read as the daemon's jobs read them (read_window:
        a file in writing to its last chunk, a file just opened as empty, where read_recording refuses a
        file with nothing in it yet)."""
        files = [recording.path for recording in list_recordings(self.daemon.recordings_dir, self.rsu)]
        window = read_window(files, self.rsu, self.camera, None, 0, 2**63 - 1)
        positions: dict[int, set[int]] = {}
        for message in window.v2x:
            positions.setdefault(message.station_id, set()).add(message.stamp_ns)
        return {frame.stamp_ns for frame in window.detections}, positions


@dataclass
class Sessions:
    """Opens client sessions to the daemon; the fixture closes them all."""

    site: Site
    opened: list[zenoh.Session] = field(default_factory=list)

    def open(
        self, identity: str | None, certs: Path | None = None, mode: str = "client", protocol: str = "tls"
    ) -> zenoh.Session:
        """A session with `identity`'s certificate (of `certs`, default our CA) to the daemon's port."""
        endpoint = self.site.endpoint.replace("tls/", f"{protocol}/")
        settings = {
            "mode": mode,
            "connect/endpoints": [endpoint],
            # One attempt: the daemon already listens, and a refused client fails at once.
            "connect/timeout_ms": 0,
            "listen/endpoints": [],
            **_tls(certs or self.site.certs, identity),
            # Our CA checks the daemon in every case: only the client's own certificate varies.
            "transport/link/tls/root_ca_certificate": str(self.site.certs / "ca.pem"),
        }
        if protocol != "tls":
            settings["transport/link/protocols"] = [protocol]
        session = zenoh.open(_deployed("secure-client.json5", settings))
        self.opened.append(session)
        return session


@pytest.fixture(scope="module")
def site(certs: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    tmp = tmp_path_factory.mktemp("secure-daemon")
    sim = simulate("sil-west", 0, ideal=True)
    camera_id = sim.cameras[0].camera_id
    state_dir = tmp / "state"
    # The RSU of deploy/rsu.example.yaml, whose cameras and vehicle the deployed access rules name.
    result = result_from_ground_truth(sim.ground_truth[camera_id], RSU)
    StateStore(state_dir).save_result(result, current=True)
    current_json = state_dir / "cameras" / camera_id / "current.json"
    # The daemon's Zenoh file: the deployed secure.json5, only its certificate paths moved.
    zenoh_file = _write(_deployed("secure.json5", _tls(certs, "rsucal-daemon")), tmp / "secure.json5")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    # rsu.yaml as deploy/README.md section 5 writes it: config_file plus a TLS listener (no mode/connect).
    site_config = demo_config(sim, state_dir, 0).model_dump(mode="json", exclude={"zenoh"})
    config = DaemonConfig.model_validate(
        {**site_config, "rsu_id": RSU, "zenoh": {"config_file": str(zenoh_file), "listen": [endpoint]}}
    )
    shift_ns = time.time_ns() - sim.v2x[0].stamp_ns
    drive = (
        m.model_copy(update={"stamp_ns": m.stamp_ns + shift_ns}).model_dump_json().encode("utf-8")
        for m in sim.v2x
        if m.station_id == sim.station_id
    )
    # The camera's detector output, each frame with a stamp of its own (recordings are checked by stamp).
    frames = (
        frame.model_copy(update={"stamp_ns": frame.stamp_ns + shift_ns})
        for frame in sim.detections[camera_id]
    )
    daemon = Daemon(config)
    try:
        daemon.start()
        yield Site(
            certs=certs,
            files=tmp,
            endpoint=endpoint,
            config=config,
            daemon=daemon,
            result=result,
            current_json=current_json,
            current_bytes=current_json.read_bytes(),
            drive=drive,
            frames=frames,
        )
    finally:
        daemon.stop()


@pytest.fixture
def sessions(site: Site) -> Iterator[Sessions]:
    opened = Sessions(site)
    try:
        yield opened
    finally:
        for session in reversed(opened.opened):
            session.close()  # type: ignore[no-untyped-call]


# ---------------------------------------------------------------------------------------------- helpers


def _replies(session: zenoh.Session, key: str, timeout_s: float) -> list[bytes]:
    """Payloads of every ok reply from every matching queryable (no consolidation: a fake cannot hide)."""
    replies = session.get(
        key, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s
    )
    return [reply.ok.payload.to_bytes() for reply in replies if reply.ok is not None]


def _round_trip(site: Site, session: zenoh.Session) -> None:
    """Barrier: the daemon has read everything `session` sent before (see the module docstring)."""
    assert len(_replies(session, health_key(site.rsu), ANSWERED_S)) == 1, "the daemon must answer health"


def _put_counted(site: Site, vehicle: zenoh.Session) -> int:
    """The vehicle puts one position; returns `v2x.received` once the daemon has counted it."""
    before = site.counters()[V2X_RECEIVED]
    vehicle.put(v2x_key(site.station), site.position())
    wait_until(lambda: site.counters()[V2X_RECEIVED] > before, timeout_s=COUNTED_S)
    return site.counters()[V2X_RECEIVED]


# ---------------------------------------------------------------------------------------------- tests


def test_operator_reads_the_calibration_and_status(
    site: Site, sessions: Sessions, capsys: pytest.CaptureFixture[str]
) -> None:
    operator = sessions.open("rsucal-operator")
    key = calibration_key(site.rsu, site.camera)
    replies = query_replies(operator, key, ANSWERED_S)
    assert replies.errors == []
    [(reply_key, payload)] = replies.ok
    assert reply_key == key
    assert payload == site.result.model_dump_json().encode("utf-8")
    assert decode_json(CalibrationResult, payload) == site.result
    # The second camera has no result: the daemon says so (an error reply, not silence).
    other = query_replies(operator, calibration_key(site.rsu, site.config.cameras[1].camera_id), ANSWERED_S)
    assert other.ok == [] and len(other.errors) == 1 and NO_CALIBRATION in other.errors[0]

    # rsucal status's reader, with the operator's copy of secure-client.json5 and its endpoints.
    operator_file = site.client_file("rsucal-operator")
    report = fetch_status([], site.rsu, None, ANSWERED_S, zenoh_config=operator_file)
    assert report.problems == ()
    assert report.answered and [h.rsu_id for h in report.health] == [site.rsu]
    assert report.alive == (site.rsu,)
    assert report.result_for(site.rsu, site.camera) == site.result
    states = {status.camera_id: status.state for status in report.statuses}
    assert states == {site.camera: "calibrated", site.config.cameras[1].camera_id: "idle"}
    args = {"connect": None, "zenoh_config": str(operator_file), "rsu": site.rsu, "camera": None}
    capsys.readouterr()
    assert status_main(argparse.Namespace(**args, timeout_s=ANSWERED_S, json=True)) == 0
    answers = json.loads(capsys.readouterr().out)
    assert [c["result_id"] for c in answers["calibrations"]] == [site.result.result_id]
    assert answers["problems"] == []


def test_nodes_without_a_valid_certificate_cannot_connect(
    site: Site, sessions: Sessions, rogue_certs: Path, expired_certs: Path, self_signed_certs: Path
) -> None:
    # A client fails at open: TLS without a certificate of its own, a certificate of another CA claiming
    # the vehicle's or the operator's name, the vehicle's name on a certificate of our CA that has expired
    # or on a self-signed one, plain tcp to the TLS port.
    for identity, certs, protocol in (
        (None, None, "tls"),
        ("vehicle-4242", rogue_certs, "tls"),
        ("rsucal-operator", rogue_certs, "tls"),
        ("vehicle-4242", expired_certs, "tls"),
        ("vehicle-4242", self_signed_certs, "tls"),
        (None, None, "tcp"),
    ):
        with pytest.raises(zenoh.ZError):
            sessions.open(identity, certs, protocol=protocol)

    # A peer opens anyway (peers do not fail on unreachable endpoints) but stays alone: no transport, its
    # gets return nothing and its puts reach nobody.
    vehicle = sessions.open("vehicle-4242")
    received = _put_counted(site, vehicle)
    unknown = site.counters()[UNKNOWN_KEY_REJECTED]
    for protocol in ("tls", "tcp"):
        loner = sessions.open(None, mode="peer", protocol=protocol)
        assert list(loner.info.transports()) == []
        assert _replies(loner, calibration_key(site.rsu, site.camera), REFUSED_S) == []
        assert _replies(loner, health_key(site.rsu), REFUSED_S) == []
        for key in (v2x_key(site.station), "v2x/**", "**"):
            loner.put(key, site.position())
        assert list(loner.info.transports()) == []
    # A loner has no link at all, so nothing it put can still be under way; the vehicle's next position is
    # counted alone.
    assert _put_counted(site, vehicle) == received + 1
    assert site.counters()[UNKNOWN_KEY_REJECTED] == unknown


def test_unauthorised_identity_cannot_fake_v2x_positions(site: Site, sessions: Sessions) -> None:
    vehicle = sessions.open("vehicle-4242")
    intruder = sessions.open("untrusted-client")
    # The authorised vehicle's positions reach the daemon and are counted.
    received = _put_counted(site, vehicle)
    accepted = site.counters()[V2X_ACCEPTED]
    unknown = site.counters()[UNKNOWN_KEY_REJECTED]

    # The intruder (a valid certificate of our CA, in no access-control list) fakes the vehicle's positions:
    # on its exact key, and on wildcards a deny-list would miss (`**` would count as unknown_key).
    spoofed = json.loads(site.position())
    spoofed["lat"] += 0.0005  # ~55 m north
    fake = json.dumps(spoofed).encode("utf-8")
    for key in (v2x_key(site.station), "v2x/cam/*", "v2x/**", "**"):
        intruder.put(key, fake)
    # Order: the intruder's puts, then its query, travel on its one link; once the daemon has answered the
    # query, every put of the intruder that got past the access control is in the daemon's ingest inbox
    # (the subscriber callback enqueues before the next message of the link is read). The vehicle's put
    # below is enqueued after that reply, and the inbox is FIFO: when the ingest thread has counted the
    # vehicle's position it has counted any leaked fake too. (Putting the vehicle's first and the intruder's
    # second would prove nothing: they travel on two links, and a leaked fake could be counted later.)
    _round_trip(site, intruder)
    assert _put_counted(site, vehicle) == received + 1
    counters = site.counters()
    assert counters[V2X_ACCEPTED] == accepted + 1  # the vehicle's own, a plausible next position
    assert counters[UNKNOWN_KEY_REJECTED] == unknown


def test_unauthorised_identity_cannot_publish_or_serve_a_fake_calibration(
    site: Site, sessions: Sessions
) -> None:
    key = calibration_key(site.rsu, site.camera)
    original = site.result.model_dump_json().encode("utf-8")
    # A well-formed result that moves the camera: what an attacker would want operators to read.
    fake_result = CalibrationResult.model_validate(
        {**site.result.model_dump(mode="json"), "result_id": "fake", "t": [0.0, 0.0, 0.0]}
    )
    fake = fake_result.model_dump_json().encode("utf-8")

    operator = sessions.open("rsucal-operator")
    seen: list[tuple[zenoh.SampleKind, bytes]] = []
    watcher = operator.declare_subscriber(key, lambda s: seen.append((s.kind, s.payload.to_bytes())))
    intruder = sessions.open("untrusted-client")
    fake_queryables: list[zenoh.Queryable[Any]] = []
    try:
        # Declarations and queries travel in order: the daemon now routes calibrations to the operator.
        _round_trip(site, operator)

        def answer_fake(query: zenoh.Query) -> None:
            with query:
                if query.key_expr.intersects(key):
                    query.reply(key, fake)

        fake_queryables = [intruder.declare_queryable(k, answer_fake) for k in (key, "rsu/**")]
        for target in (key, "rsu/*/camera/*/calibration", "rsu/**", "**"):
            intruder.put(target, fake)
            intruder.delete(target)
        _round_trip(site, intruder)  # the daemon has read (and refused) all of it
        # The daemon publishes on the same key to the same subscriber: a fake the daemon had forwarded would
        # have been queued on the operator's link before it, so it would have arrived first.
        bus = site.daemon._bus  # the publication path of an accepted result, without replacing current.json
        assert bus is not None
        bus.publish_calibration(site.camera, original)
        wait_until(lambda: len(seen) >= 1, timeout_s=ANSWERED_S)
        assert seen == [(zenoh.SampleKind.PUT, original)]

        # The daemon's queryable is the only one answering, with the original; on disk, current.json is
        # byte-identical and the history holds the seeded result alone.
        assert _replies(operator, key, ANSWERED_S) == [original]
        assert fake not in _replies(operator, "rsu/**", ANSWERED_S)
        assert site.current_json.read_bytes() == site.current_bytes
        assert site.daemon.store.load_current(site.camera) == site.result
        assert len(site.daemon.store.history(site.camera)) == 1
    finally:
        for queryable in fake_queryables:
            queryable.undeclare()  # type: ignore[no-untyped-call]
        watcher.undeclare()  # type: ignore[no-untyped-call]


def test_rsucal_status_cli_with_the_secure_client_config(
    site: Site, capsys: pytest.CaptureFixture[str]
) -> None:
    # The operator's copy of secure-client.json5 still names the deployed `tls/router:7447`: --connect
    # replaces it (a session that tried the router would fail, so exit 0 shows it did).
    config_file = site.client_file("rsucal-operator", connect=False)
    argv = ["status", "--zenoh-config", str(config_file), "--connect", site.endpoint, "--timeout", "5"]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    assert f"via {site.endpoint}" in out
    assert site.camera in out and "calibrated" in out


# ------------------------------------------------------------------------------- identities bound to keys


def _payload(frame: DetectionFrame) -> bytes:
    return frame.model_dump_json().encode("utf-8")


def _put_frame_counted(site: Site, detector: zenoh.Session) -> int:
    """The detector puts the camera's next frame; returns its stamp once the daemon has counted it, both
    as received (counted on arrival) and in the camera's status (counted once ingested, a moment later)."""
    before = site.counters()[DETECTIONS_RECEIVED]
    before_camera = site.daemon.status(site.camera).counters["detections"]
    frame = site.frame()
    detector.put(detections_key(site.rsu, site.camera), _payload(frame))
    wait_until(
        lambda: (
            site.counters()[DETECTIONS_RECEIVED] > before
            and site.daemon.status(site.camera).counters["detections"] > before_camera
        ),
        timeout_s=COUNTED_S,
    )
    return frame.stamp_ns


def _put_position_counted(site: Site, vehicle: zenoh.Session) -> int:
    """The vehicle puts its next position; returns its stamp once the daemon has counted it."""
    before = site.counters()[V2X_RECEIVED]
    payload = site.position()
    vehicle.put(v2x_key(site.station), payload)
    wait_until(lambda: site.counters()[V2X_RECEIVED] > before, timeout_s=COUNTED_S)
    return int(json.loads(payload)["stamp_ns"])


def test_only_the_cameras_detector_feeds_its_detections(site: Site, sessions: Sessions) -> None:
    """Issue 14, gap 1: a valid certificate of the CA (untrusted-client) published detections that were
    accepted and recorded. Now only the camera's detector identity (detector-sil-west) may; every other
    identity's frames, on the exact key or a wildcard, are never counted, recorded or used (jobs read
    their windows from the recordings; the camera's `detections` counter is what its status shows)."""
    detector = sessions.open("detector-sil-west")
    key = detections_key(site.rsu, site.camera)
    legit = [_put_frame_counted(site, detector)]
    counters = site.counters()
    camera_detections = site.daemon.status(site.camera).counters["detections"]

    fakes: list[int] = []
    # The daemon's own identity too: its rule names its own keys, not `rsu/**`.
    for identity in ("untrusted-client", "vehicle-4242", "rsucal-operator", "rsucal-daemon"):
        other = sessions.open(identity)
        for target in (key, "rsu/*/camera/*/detections", "rsu/**", "**"):
            fake = site.frame()
            fakes.append(fake.stamp_ns)
            other.put(target, _payload(fake))
        _round_trip(site, other)  # every fake put that passed is in the inbox (module docstring)
    legit.append(_put_frame_counted(site, detector))

    after = site.counters()
    assert after[DETECTIONS_RECEIVED] == counters[DETECTIONS_RECEIVED] + 1
    assert after[DETECTIONS_ACCEPTED] == counters[DETECTIONS_ACCEPTED] + 1
    assert after[UNKNOWN_KEY_REJECTED] == counters[UNKNOWN_KEY_REJECTED]
    assert site.daemon.status(site.camera).counters["detections"] == camera_detections + 1
    # Recorded in order of ingest: once the detector's frames are in the file, a leaked fake would be too.
    wait_until(lambda: set(legit) <= site.recorded()[0], timeout_s=COUNTED_S)
    assert site.recorded()[0].isdisjoint(fakes)


def test_a_vehicle_speaks_only_for_its_own_station(site: Site, sessions: Sessions) -> None:
    """Issue 14, gap 2: with the certificate of vehicle 4242, positions put on v2x/cam/777 were accepted
    (`v2x.other_station`). Now each vehicle certificate may put only its own station's key: vehicle 4242's
    positions for another station, and the detector's for vehicle 4242, are never counted or recorded,
    while vehicle 4242's own still are."""
    vehicle = sessions.open("vehicle-4242")
    detector = sessions.open("detector-sil-west")
    legit = [_put_position_counted(site, vehicle)]
    counters = site.counters()

    spoofed: list[int] = []
    for sender, station, targets in (
        (vehicle, OTHER_STATION, (v2x_key(OTHER_STATION), "v2x/cam/*", "v2x/**", "**")),
        (detector, site.station, (v2x_key(site.station), "v2x/**")),
    ):
        for target in targets:
            spoof = json.loads(site.position())
            spoof["station_id"] = station
            spoof["lat"] += 0.0005  # ~55 m north: a position the real vehicle never had
            spoofed.append(spoof["stamp_ns"])
            sender.put(target, json.dumps(spoof).encode("utf-8"))
        _round_trip(site, sender)
    legit.append(_put_position_counted(site, vehicle))

    after = site.counters()
    assert after[V2X_RECEIVED] == counters[V2X_RECEIVED] + 1
    assert after[V2X_ACCEPTED] == counters[V2X_ACCEPTED] + 1  # the vehicle's own: used for traversals
    assert after[V2X_OTHER_STATION] == counters[V2X_OTHER_STATION]
    assert after[UNKNOWN_KEY_REJECTED] == counters[UNKNOWN_KEY_REJECTED]
    wait_until(lambda: set(legit) <= site.recorded()[1].get(site.station, set()), timeout_s=COUNTED_S)
    positions = site.recorded()[1]
    assert OTHER_STATION not in positions
    assert positions[site.station].isdisjoint(spoofed)


def test_rsucal_status_names_the_endpoints_of_its_zenoh_config(
    site: Site, capsys: pytest.CaptureFixture[str]
) -> None:
    """Without --connect, status connects where the --zenoh-config file says and names those endpoints
    (it printed "via :" and "endpoints": [] before)."""
    config_file = site.client_file("rsucal-operator")  # connect/endpoints: [the daemon's endpoint]
    argv = ["status", "--zenoh-config", str(config_file), "--timeout", "5"]
    capsys.readouterr()
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    assert f"via {site.endpoint}:" in out
    assert cli.main([*argv, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["endpoints"] == [site.endpoint]


def test_behind_the_secure_router_only_the_detector_feeds_the_daemon(certs: Path, tmp_path: Path) -> None:
    """compose.secure.yaml's topology: a router on secure-router.json5 enforces the rules, the daemon is its
    mutual-TLS client (secure-client.json5) and checks at start the router's file, named in
    zenoh.access_control_file. An intruder's detections through the router never reach the daemon."""
    sim = simulate("sil-west", 0, ideal=True)
    camera = sim.cameras[0].camera_id
    endpoint = f"tls/127.0.0.1:{free_port()}"
    router_settings = {**_tls(certs, "rsucal-router"), "listen/endpoints": [endpoint]}
    router_file = _write(_deployed("secure-router.json5", router_settings), tmp_path / "router.json5")
    client_settings = {**_tls(certs, "rsucal-daemon"), "connect/endpoints": [endpoint]}
    client_file = _write(_deployed("secure-client.json5", client_settings), tmp_path / "daemon.json5")
    site_config = demo_config(sim, tmp_path / "state", 0).model_dump(mode="json", exclude={"zenoh"})
    zenoh_fields = {
        "mode": "client",
        "config_file": str(client_file),
        "access_control_file": str(router_file),
    }
    config = DaemonConfig.model_validate({**site_config, "rsu_id": RSU, "zenoh": zenoh_fields})
    frames = iter(sim.detections[camera])
    key = detections_key(RSU, camera)
    opened: list[zenoh.Session] = []
    router = zenoh.open(zenoh.Config.from_file(str(router_file)))
    daemon = Daemon(config)
    fakes: list[int] = []
    try:
        daemon.start()

        def client(identity: str) -> zenoh.Session:
            settings = {**_tls(certs, identity), "connect/endpoints": [endpoint]}
            opened.append(zenoh.open(_deployed("secure-client.json5", settings)))
            return opened[-1]

        detector, intruder = client("detector-sil-west"), client("untrusted-client")

        def detector_counted() -> bool:
            # Again until the daemon's subscription, declared through the router, has reached the detector.
            detector.put(key, _payload(next(frames)))
            return daemon.health().counters[DETECTIONS_RECEIVED] > 0

        wait_until(detector_counted, timeout_s=COUNTED_S)
        for target in (key, "rsu/*/camera/*/detections", "rsu/**", "**"):
            fake = next(frames)
            fakes.append(fake.stamp_ns)
            intruder.put(target, _payload(fake))
        # Through the router too, the intruder's puts and its query reach the daemon in order.
        assert len(_replies(intruder, health_key(RSU), ANSWERED_S)) == 1
        last = next(frames)
        before = daemon.health().counters[DETECTIONS_RECEIVED]
        detector.put(key, _payload(last))
        wait_until(lambda: daemon.health().counters[DETECTIONS_RECEIVED] > before, timeout_s=COUNTED_S)
    finally:
        for session in reversed(opened):
            session.close()  # type: ignore[no-untyped-call]
        daemon.stop()  # finishes the recording
        router.close()  # type: ignore[no-untyped-call]
    [recording] = list_recordings(daemon.recordings_dir, RSU)
    recorded = {frame.stamp_ns for frame in read_recording(recording.path, rsu_id=RSU).detections[camera]}
    # Recorded in order of arrival: the detector's last frame is there, so a leaked fake would be too. And
    # every frame the daemon counted is one of the detector's.
    assert last.stamp_ns in recorded and recorded.isdisjoint(fakes)
    counters = daemon.health().counters
    assert counters[DETECTIONS_RECEIVED] == counters[DETECTIONS_ACCEPTED] == len(recorded)


def test_only_an_operator_reaches_the_trigger(site: Site, sessions: Sessions) -> None:
    """The trigger queryable answers every exact-key query (a job id, a reason, or an error for an unknown
    camera), so an unanswered query never reached the daemon. The unknown camera starts no job."""
    unknown = trigger_key(site.rsu, "no-such-camera")
    for identity in ("untrusted-client", "vehicle-4242", "detector-sil-west"):
        other = sessions.open(identity)
        for key in (trigger_key(site.rsu, site.camera), unknown):
            replies = query_replies(other, key, REFUSED_S)
            assert replies.ok == [] and replies.errors == []
    operator = sessions.open("rsucal-operator")
    replies = query_replies(operator, unknown, ANSWERED_S)
    assert replies.ok == [] and len(replies.errors) == 1 and "no such camera" in replies.errors[0]


def test_unauthorised_identity_cannot_fake_a_liveliness_token(site: Site, sessions: Sessions) -> None:
    intruder = sessions.open("untrusted-client")
    tokens = [
        intruder.liveliness().declare_token(key) for key in (alive_key("fake-rsu"), alive_key(site.rsu))
    ]
    try:
        _round_trip(site, intruder)  # its declarations reached the daemon (and were refused there)
        operator = sessions.open("rsucal-operator")
        alive = [
            str(reply.ok.key_expr)
            for reply in operator.liveliness().get("rsu/*/alive", timeout=ANSWERED_S)
            if reply.ok is not None
        ]
        assert alive == [alive_key(site.rsu)]  # the daemon's own token only
    finally:
        for token in tokens:
            token.undeclare()  # type: ignore[no-untyped-call]
