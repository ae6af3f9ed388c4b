"""daemon/access.py: a secure deployment's access rules against rsu.yaml, and the daemon's start-up check.

The rules are the deployed ones (deploy/zenoh/secure.json5, secure-router.json5) for the example site
(deploy/rsu.example.yaml), parsed by zenoh itself, then changed the way an operator could get them wrong.
That the evaluation agrees with what Zenoh really delivers is tested with real TLS sessions in
tests/deploy/test_secure_zenoh.py; the daemon's refusal here goes through `rsucal daemon` (cli.main).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from daemon import cli
from daemon.access import AccessControlError, AccessRules, access_problems, check_access_rules
from pipeline.loaders import load_daemon_config
from schemas.config import DaemonConfig

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
ZENOH_DIR = DEPLOY / "zenoh"
EXAMPLE = load_daemon_config(DEPLOY / "rsu.example.yaml")
JUNCTION = "rsu/sil-west/camera/west-junction/detections"

Acl = dict[str, Any]


def _deployed_acl(name: str = "secure.json5") -> Acl:
    acl = json.loads(zenoh.Config.from_file(str(ZENOH_DIR / name)).get_json("access_control"))
    assert isinstance(acl, dict)
    return acl


def _through_zenoh(acl: Acl) -> Acl:
    """The section as zenoh parses it (a mutation zenoh would refuse fails here, not in the check)."""
    config = zenoh.Config.from_file(str(ZENOH_DIR / "secure.json5"))
    config.insert_json5("access_control", json.dumps(acl))
    parsed = json.loads(config.get_json("access_control"))
    assert isinstance(parsed, dict)
    return parsed


def _problems(
    acl: Acl, config: DaemonConfig = EXAMPLE, owns_rules: bool = True, protocols: list[str] | None = None
) -> list[str]:
    rules = AccessRules.parse(_through_zenoh(acl), protocols or ["tls"])
    return access_problems(config, rules, owns_rules=owns_rules)


def _rule(acl: Acl, rule_id: str) -> dict[str, Any]:
    [rule] = [rule for rule in acl["rules"] if rule["id"] == rule_id]
    assert isinstance(rule, dict)
    return rule


def _policy(acl: Acl, policy_id: str) -> dict[str, Any]:
    [policy] = [policy for policy in acl["policies"] if policy["id"] == policy_id]
    assert isinstance(policy, dict)
    return policy


def _config(**changes: Any) -> DaemonConfig:
    data = EXAMPLE.model_dump(mode="json", exclude_unset=True)
    data.update(changes)
    return DaemonConfig.model_validate(data)


def _add_rule(acl: Acl, policy_id: str, rule: dict[str, Any]) -> None:
    acl["rules"].append({"permission": "allow", "flows": ["ingress"], "messages": ["put"], **rule})
    _policy(acl, policy_id)["rules"].append(rule["id"])


# ------------------------------------------------------------------------------------------ the rules


@pytest.mark.parametrize("name", ["secure.json5", "secure-router.json5"])
def test_deployed_rules_bind_every_camera_and_vehicle_of_the_example(name: str) -> None:
    assert _problems(_deployed_acl(name)) == []
    assert _problems(_deployed_acl(name), owns_rules=False) == []


def _everyone_publishes_detections(acl: Acl) -> None:
    """The rule of the first secure configs: any certificate of the CA may publish detections."""
    _add_rule(acl, "everyone", {"id": "publish-detections", "key_exprs": ["rsu/*/camera/*/detections"]})


def _vehicles_on_all_of_v2x(acl: Acl) -> None:
    _rule(acl, "v2x/4242")["key_exprs"] = ["v2x/**"]


def _vehicle_also_for_777(acl: Acl) -> None:
    _rule(acl, "v2x/4242")["key_exprs"].append("v2x/cam/777")


def _daemon_on_all_of_rsu(acl: Acl) -> None:
    _rule(acl, "serve-rsu")["key_exprs"] = ["rsu/**"]


def _detector_only_on_lo(acl: Acl) -> None:
    [subject] = [s for s in acl["subjects"] if s["id"] == "detectors/sil-west/west-junction"]
    subject["interfaces"] = ["lo"]


MUTATIONS: dict[str, tuple[Callable[[Acl], None], list[str]]] = {
    "any certificate publishes detections (issue 14)": (
        _everyone_publishes_detections,
        [
            # untrusted-client is in no subject: "any other certificate" stands for it.
            f"camera west-junction: any other certificate may put {JUNCTION} (rule publish-detections)",
            f"camera west-junction: vehicle-4242 may put {JUNCTION} (rule publish-detections)",
            "rule publish-detections allows put on rsu/*/camera/*/detections, a wildcard over vehicle or "
            "detector keys (one exact key each)",
        ],
    ),
    "a vehicle rule on a wildcard": (
        _vehicles_on_all_of_v2x,
        ["rule v2x/4242 allows put on v2x/**, a wildcard over vehicle or detector keys (one exact key each)"],
    ),
    "a vehicle may speak for another station (issue 14)": (
        _vehicle_also_for_777,
        [
            "rule v2x/4242 allows put on v2x/cam/777: station 777 is not in vehicles",
            "vehicle-4242 may put v2x/cam/777, not its own station's key (rule v2x/4242)",
        ],
    ),
    "the daemon's rule covers detections": (
        _daemon_on_all_of_rsu,
        [
            f"camera west-junction: rsucal-daemon may put {JUNCTION} (rule serve-rsu)",
            f"camera west-junction: rsucal-daemon may delete {JUNCTION} (rule serve-rsu)",
        ],
    ),
    "the detector's subject matches one interface only": (
        _detector_only_on_lo,
        [
            f"camera west-junction: detector-sil-west may not put {JUNCTION} (no rule of a subject naming it "
            "allows it)"
        ],
    ),
}


@pytest.mark.parametrize("name", sorted(MUTATIONS))
def test_a_rule_that_lets_the_wrong_identity_publish_is_named(name: str) -> None:
    mutate, expected = MUTATIONS[name]
    acl = _deployed_acl()
    mutate(acl)
    problems = _problems(acl)
    for problem in expected:
        assert problem in problems
    assert len(problems) == len(set(problems))


def test_on_a_router_only_this_rsus_cameras_are_held_to_the_config() -> None:
    """A router may serve other RSUs' vehicles: a stranger's station rule is no mismatch there, but one of
    our vehicles speaking for it still is."""
    acl = _deployed_acl("secure-router.json5")
    _add_rule(acl, "operators", {"id": "v2x/777", "key_exprs": ["v2x/cam/777"]})
    assert _problems(acl, owns_rules=False) == []
    assert _problems(acl, owns_rules=True) == [
        "rule v2x/777 allows put on v2x/cam/777: station 777 is not in vehicles"
    ]
    _vehicle_also_for_777(acl)
    assert _problems(acl, owns_rules=False) == [
        "vehicle-4242 may put v2x/cam/777, not its own station's key (rule v2x/4242)"
    ]


def test_deny_beats_allow_within_one_subject_only() -> None:
    """Zenoh's semantics: a deny of the same subject cancels an allow; another subject's deny does not."""
    acl = _deployed_acl()
    _everyone_publishes_detections(acl)
    deny = {"id": "no-detections", "permission": "deny", "key_exprs": [JUNCTION]}
    _add_rule(acl, "operators", deny)
    assert (
        f"camera west-junction: any other certificate may put {JUNCTION} (rule publish-detections)"
        in _problems(acl)
    )
    _policy(acl, "everyone")["rules"].append("no-detections")
    problems = _problems(acl)
    assert not any(JUNCTION in problem for problem in problems)
    assert (
        "camera west-arm: any other certificate may put rsu/sil-west/camera/west-arm/detections (rule "
        "publish-detections)" in problems
    )


def test_nodes_without_a_certificate_count_where_plain_links_are_open() -> None:
    acl = _deployed_acl()
    acl["subjects"].append({"id": "anyone"})
    acl["policies"].append({"id": "anyone", "subjects": ["anyone"], "rules": ["v2x/4242"]})
    assert "vehicle 4242: a node over plain tcp may put v2x/cam/4242 (rule v2x/4242)" in _problems(
        acl, protocols=["tls", "tcp"]
    )
    # With TLS only (the deployed files), such a subject still opens the key to every certificate.
    assert "vehicle 4242: any other certificate may put v2x/cam/4242 (rule v2x/4242)" in _problems(acl)


def test_config_changes_without_new_rules_are_mismatches() -> None:
    acl = _deployed_acl()
    vehicles = [*EXAMPLE.model_dump(mode="json")["vehicles"]]
    added = _config(vehicles=[*vehicles, {**vehicles[0], "station_id": 777, "cert_common_names": None}])
    assert _problems(acl, added) == [
        "vehicle 777: vehicle-777 may not put v2x/cam/777 (no rule of a subject naming it allows it)"
    ]
    cameras = EXAMPLE.model_dump(mode="json")["cameras"]
    own_detector = _config(
        cameras=[cameras[0], {**cameras[1], "detector_cert_common_names": ["detector-arm"]}]
    )
    problems = _problems(acl, own_detector)
    assert (
        "camera west-arm: detector-arm may not put rsu/sil-west/camera/west-arm/detections (no rule of a "
        "subject naming it allows it)" in problems
    )
    assert (
        "camera west-arm: detector-sil-west may put rsu/sil-west/camera/west-arm/image (rule "
        "detections/sil-west/west-arm)" in problems
    )
    removed = _config(cameras=[cameras[0]])
    assert _problems(acl, removed) == [
        "rule detections/sil-west/west-arm allows put on rsu/sil-west/camera/west-arm/detections: camera "
        "west-arm is not in cameras",
        "rule detections/sil-west/west-arm allows put on rsu/sil-west/camera/west-arm/image: camera "
        "west-arm is not in cameras",
    ]


def test_access_control_off_or_default_allow_is_refused() -> None:
    assert _problems({**_deployed_acl(), "enabled": False}) == [
        "access_control.enabled is false: every certificate of the CA may publish anything"
    ]
    assert _problems({**_deployed_acl(), "default_permission": "allow"}) == [
        "access_control.default_permission must be deny: with allow, any key no rule names is open"
    ]


# ------------------------------------------------------------------------------------------ start-up


def _secure_config(tmp_path: Path, **zenoh_fields: Any) -> dict[str, Any]:
    data = EXAMPLE.model_dump(mode="json", exclude_unset=True)
    data["storage"] = {**data["storage"], "state_dir": str(tmp_path / "state")}
    data["zenoh"] = {"config_file": str(ZENOH_DIR / "secure.json5"), **zenoh_fields}
    return data


def _run_daemon(tmp_path: Path, data: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    path = tmp_path / "rsu.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    capsys.readouterr()
    code = cli.main(["daemon", "--config", str(path)])
    return code, capsys.readouterr().err


def test_daemon_refuses_to_start_when_a_vehicle_has_no_rule(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _secure_config(tmp_path)
    data["vehicles"].append({**data["vehicles"][0], "station_id": 777, "cert_common_names": ["gateway-7"]})
    code, err = _run_daemon(tmp_path, data, capsys)
    assert code == 2
    assert err == (
        f"error: zenoh.config_file {ZENOH_DIR / 'secure.json5'}: access rules do not match rsu.yaml: vehicle "
        "777: gateway-7 may not put v2x/cam/777 (no rule of a subject naming it allows it)\n"
    )
    # Refused before it recorded anything or went on the bus.
    assert list((tmp_path / "state").rglob("*.mcap")) == []


def test_daemon_refuses_to_start_when_another_identity_feeds_a_camera(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _secure_config(tmp_path)
    data["cameras"][0]["detector_cert_common_names"] = ["detector-junction"]
    code, err = _run_daemon(tmp_path, data, capsys)
    assert code == 2
    assert "camera west-junction: detector-junction may not put " + JUNCTION in err
    assert f"camera west-junction: detector-sil-west may put {JUNCTION}" in err
    assert err.count("\n") == 1 and "Traceback" not in err


def test_mutual_tls_client_needs_the_routers_rules(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    client = {"mode": "client", "config_file": str(ZENOH_DIR / "secure-client.json5")}
    data = _secure_config(tmp_path)
    data["zenoh"] = client
    code, err = _run_daemon(tmp_path, data, capsys)
    assert code == 2
    assert err.startswith("error: zenoh.access_control_file: the daemon speaks mutual TLS")
    # With the router's file named, the check passes (the session then connects as usual).
    router_file = ZENOH_DIR / "secure-router.json5"
    assert (
        check_access_rules(
            DaemonConfig.model_validate(
                {**data, "zenoh": {**client, "access_control_file": str(router_file)}}
            )
        )
        == 1
    )
    # ... and a router file that does not match is refused like the daemon's own rules.
    data["cameras"][1]["detector_cert_common_names"] = ["detector-arm"]
    with pytest.raises(
        AccessControlError, match=r"^zenoh.access_control_file .*camera west-arm: detector-arm"
    ):
        check_access_rules(
            DaemonConfig.model_validate(
                {**data, "zenoh": {**client, "access_control_file": str(router_file)}}
            )
        )


def test_plain_bus_has_nothing_to_check() -> None:
    assert check_access_rules(EXAMPLE) == 0
    assert check_access_rules(_config(zenoh={"config_file": str(ZENOH_DIR / "secure.json5")})) == 1


# ------------------------------------------------------------------------------------------ the generator


def test_generator_writes_rules_the_daemon_accepts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = EXAMPLE.model_dump(mode="json", exclude_unset=True)
    data["vehicles"].append({**data["vehicles"][0], "station_id": 777, "cert_common_names": ["gateway-7"]})
    data["cameras"][1]["detector_cert_common_names"] = ["detector-arm"]
    rsu_yaml = tmp_path / "rsu.yaml"
    rsu_yaml.write_text(yaml.safe_dump(data), encoding="utf-8")
    out = tmp_path / "site.json5"
    argv = [
        "access-control",
        "--config",
        str(rsu_yaml),
        "--base",
        str(ZENOH_DIR / "secure.json5"),
        "--out",
        str(out),
    ]
    assert cli.main(argv) == 0
    site = zenoh.Config.from_file(str(out))  # zenoh's strict parser accepts it
    acl = json.loads(site.get_json("access_control"))
    config = DaemonConfig.model_validate(data)
    assert access_problems(config, AccessRules.parse(acl, ["tls"]), owns_rules=True) == []
    assert _rule(acl, "v2x/777")["key_exprs"] == ["v2x/cam/777"]
    [subject] = [s for s in acl["subjects"] if s["id"] == "vehicle/777"]
    assert subject["cert_common_names"] == ["gateway-7"]
    # Everything else of the base is kept as it was.
    base = zenoh.Config.from_file(str(ZENOH_DIR / "secure.json5"))
    for path in ("transport/link/tls", "listen/endpoints", "scouting", "mode"):
        assert site.get_json(path) == base.get_json(path)
    # A re-run on its own output changes nothing.
    again = tmp_path / "again.json5"
    assert cli.main([*argv[:3], "--base", str(out), "--out", str(again)]) == 0
    assert again.read_text() == out.read_text()
    # And the daemon's start-up check passes with it.
    assert (
        check_access_rules(
            config.model_copy(update={"zenoh": config.zenoh.model_copy(update={"config_file": out})})
        )
        == 1
    )


def test_generator_refuses_a_base_that_contradicts_the_site(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    acl = _deployed_acl()
    _everyone_publishes_detections(acl)
    base = zenoh.Config.from_file(str(ZENOH_DIR / "secure.json5"))
    base.insert_json5("access_control", json.dumps(acl))
    base_file = tmp_path / "old.json5"
    base_file.write_text(str(base), encoding="utf-8")
    out = tmp_path / "site.json5"
    argv = [
        "access-control",
        "--config",
        str(DEPLOY / "rsu.example.yaml"),
        "--base",
        str(base_file),
        "--out",
        str(out),
    ]
    capsys.readouterr()
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --base {base_file}: entries of the base contradict rsu.yaml: ")
    assert "(rule publish-detections)" in err
    assert not out.exists()


def test_generator_refuses_a_client_config_as_base(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = ZENOH_DIR / "secure-client.json5"
    out = tmp_path / "site.json5"
    argv = [
        "access-control",
        "--config",
        str(DEPLOY / "rsu.example.yaml"),
        "--base",
        str(base),
        "--out",
        str(out),
    ]
    capsys.readouterr()
    assert cli.main(argv) == 2
    assert capsys.readouterr().err == (
        f"error: --base {base}: a client enforces no access control; start from the enforcing node's config "
        "(secure.json5 for the daemon as a secure peer, secure-router.json5 for a router)\n"
    )
    assert not out.exists()
