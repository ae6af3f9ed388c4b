"""deploy/zenoh/*.json5: every file is a valid zenoh 1.x config (zenoh refuses unknown keys), the plain ones
carry a message end to end, and the secure ones agree with each other.

The secure files' behaviour (TLS, access control) is tested with real sessions in test_secure_zenoh.py.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import zenoh
from helpers import free_port, wait_until

from daemon.access import site_access_control
from pipeline.loaders import load_daemon_config
from schemas.config import ZenohConfig

ZENOH_DIR = Path(__file__).resolve().parents[2] / "deploy" / "zenoh"
FILES = sorted(path.name for path in ZENOH_DIR.glob("*.json5"))
MODES = {
    "peer.json5": "peer",
    "client.json5": "client",
    "router.json5": "router",
    "secure.json5": "peer",
    "secure-router.json5": "router",
    "secure-client.json5": "client",
}
SECURE = [name for name in MODES if name.startswith("secure")]


def _get(config: zenoh.Config, key: str) -> Any:
    return json.loads(config.get_json(key))


def _load(name: str, settings: dict[str, Any] | None = None) -> zenoh.Config:
    config = zenoh.Config.from_file(str(ZENOH_DIR / name))
    for key, value in (settings or {}).items():
        config.insert_json5(key, json.dumps(value))
    return config


def test_the_documented_files_are_all_there() -> None:
    assert sorted(MODES) == FILES


@pytest.mark.parametrize("name", FILES)
def test_file_is_a_strict_zenoh_config_without_multicast(name: str) -> None:
    config = _load(name)
    assert _get(config, "mode") == MODES[name]
    assert _get(config, "scouting/multicast/enabled") is False


def test_peer_file_is_the_daemon_default() -> None:
    config, default = _load("peer.json5"), ZenohConfig()
    assert _get(config, "mode") == default.mode
    assert _get(config, "listen/endpoints") == default.listen
    assert _get(config, "connect/endpoints") == default.connect
    assert _get(config, "scouting/multicast/enabled") == default.multicast_scouting


@pytest.mark.parametrize("name", SECURE)
def test_secure_files_speak_only_mutual_tls(name: str) -> None:
    config = _load(name)
    assert _get(config, "transport/link/protocols") == ["tls"]
    tls = _get(config, "transport/link/tls")
    assert tls["enable_mtls"] is True and tls["verify_name_on_connect"] is True
    assert tls["root_ca_certificate"] == "/etc/rsucal/tls/ca.pem"
    # A client only connects; a peer or router is connected to.
    side = "connect" if MODES[name] == "client" else "listen"
    endpoints = _get(config, f"{side}/endpoints")
    assert endpoints and all(endpoint.startswith("tls/") for endpoint in endpoints)


def test_secure_peer_and_router_enforce_the_same_access_control() -> None:
    peer, router = _load("secure.json5"), _load("secure-router.json5")
    acl = _get(peer, "access_control")
    assert acl == _get(router, "access_control")
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert _get(peer, "scouting/gossip/enabled") is False and _get(router, "scouting/gossip/enabled") is False


@pytest.mark.parametrize("name", ["secure.json5", "secure-router.json5"])
def test_secure_rules_are_what_the_generator_writes_for_the_example_site(name: str) -> None:
    """The deployed per-vehicle and per-camera rules are `rsucal access-control`'s for deploy/rsu.example.yaml
    (the daemon's start-up check of them is tested in tests/daemon/test_access.py)."""
    example = load_daemon_config(ZENOH_DIR.parent / "rsu.example.yaml")
    acl = _get(_load(name), "access_control")
    regenerated = _load(name, {"access_control": site_access_control(example, acl)})
    assert _get(regenerated, "access_control") == acl


def test_plain_router_client_and_peer_carry_a_message() -> None:
    """router.json5 + a daemon with client.json5 + a reader with peer.json5's settings, on loopback."""
    port = free_port()
    sessions: list[zenoh.Session] = []
    try:
        sessions.append(zenoh.open(_load("router.json5", {"listen/endpoints": [f"tcp/127.0.0.1:{port}"]})))
        daemon = zenoh.open(_load("client.json5", {"connect/endpoints": [f"tcp/127.0.0.1:{port}"]}))
        sessions.append(daemon)
        reader_settings = {"listen/endpoints": [], "connect/endpoints": [f"tcp/127.0.0.1:{port}"]}
        reader = zenoh.open(_load("peer.json5", reader_settings))
        sessions.append(reader)
        got: list[bytes] = []
        key = "rsu/r1/camera/c1/calibration"
        subscriber = reader.declare_subscriber(key, lambda sample: got.append(sample.payload.to_bytes()))

        def arrived() -> bool:
            daemon.put(key, b"ok")  # again until the new subscription has reached the daemon
            return bool(got)

        try:
            wait_until(arrived, timeout_s=5)
        finally:
            subscriber.undeclare()
        assert set(got) == {b"ok"}
    finally:
        for session in reversed(sessions):
            session.close()
