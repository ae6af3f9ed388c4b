"""deploy/compose.yaml (+ compose.secure.yaml), checked without Docker: what each service mounts exists and
is what its command reads, the daemon keeps its state in a volume, and its health check parses with the real
CLI. `docker compose config` / `up` cannot run here (no Docker engine); deploy/README.md says how to.
"""

from __future__ import annotations

import json
import re
from importlib.metadata import version
from pathlib import Path
from typing import Any

import yaml
import zenoh

from daemon.cli import build_parser

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def _compose(name: str) -> dict[str, Any]:
    data = yaml.safe_load((DEPLOY / name).read_text())
    assert isinstance(data, dict)
    return data


def _binds(service: dict[str, Any]) -> dict[str, str]:
    """target -> source of a service's bind mounts (long syntax)."""
    return {v["target"]: v["source"] for v in service.get("volumes", []) if v["type"] == "bind"}


def test_router_runs_the_mounted_router_config_of_our_zenoh_version() -> None:
    router = _compose("compose.yaml")["services"]["router"]
    image, tag = router["image"].split(":")
    assert image == "eclipse/zenoh"
    # Same major version as the daemon's zenoh: the same wire protocol.
    assert tag.split(".")[0] == version("eclipse-zenoh").split(".")[0]
    config_path = router["command"][router["command"].index("-c") + 1]
    source = _binds(router)[config_path]
    zenoh.Config.from_file(str(DEPLOY / source))  # zenoh itself accepts it
    assert Path(source).name == "router.json5"


def test_daemon_service_builds_the_image_and_keeps_state_in_a_volume() -> None:
    compose = _compose("compose.yaml")
    rsucal = compose["services"]["rsucal"]
    assert (DEPLOY / rsucal["build"]["context"] / rsucal["build"]["dockerfile"]).is_file()
    volumes = {v["target"]: v for v in rsucal["volumes"]}
    assert volumes["/var/lib/rsucal"]["type"] == "volume"
    assert volumes["/var/lib/rsucal"]["source"] in compose["volumes"]
    config = volumes["/etc/rsucal/rsu.yaml"]
    assert config["type"] == "bind" and config["read_only"] is True
    assert config["bind"]["create_host_path"] is False  # a missing rsu.yaml stops compose, loudly
    assert rsucal["stop_grace_period"] == "10s"
    assert "ALL" in rsucal["cap_drop"] and rsucal["read_only"] is True


def _healthcheck_argv(name: str) -> list[str]:
    test = _compose(name)["services"]["rsucal"]["healthcheck"]["test"]
    assert test[0] == "CMD" and test[1] == "rsucal"
    return [str(arg) for arg in test[2:]]


def test_daemon_healthcheck_asks_through_the_router() -> None:
    argv = _healthcheck_argv("compose.yaml")
    assert argv[argv.index("--connect") + 1] == "tcp/router:7447"
    build_parser().parse_args(argv)


def test_secure_override_mounts_what_its_configs_read() -> None:
    secure = _compose("compose.secure.yaml")["services"]
    router_config = secure["router"]["command"][-1]
    assert Path(_binds(secure["router"])[router_config]).name == "secure-router.json5"
    for service in ("router", "rsucal"):
        assert _binds(secure[service])["/etc/rsucal/tls"] == "./tls"
    # The daemon checks the very file the router runs (zenoh.access_control_file, deploy/README.md).
    assert (
        _binds(secure["rsucal"])["/etc/rsucal/zenoh/secure-router.json5"]
        == _binds(secure["router"])[router_config]
    )
    # The files the secure configs name are those make-test-certs.sh writes into ./tls.
    script = (DEPLOY / "make-test-certs.sh").read_text()
    made = {"ca", *re.findall(r"^issue (\S+) ", script, flags=re.MULTILINE)}
    for name in ("secure-router.json5", "secure-client.json5"):
        tls = json.loads(zenoh.Config.from_file(str(DEPLOY / "zenoh" / name)).get_json("transport/link/tls"))
        paths = [
            value for key, value in tls.items() if key.endswith(("_certificate", "_private_key")) and value
        ]
        assert paths
        for path in paths:
            assert Path(path).parent == Path("/etc/rsucal/tls") and Path(path).stem in made, path


def test_secure_healthcheck_parses() -> None:
    build_parser().parse_args(_healthcheck_argv("compose.secure.yaml"))
