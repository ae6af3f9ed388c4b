"""Access control by identity: each detector and calibration vehicle may publish only its own keys.

A secure deployment (deploy/zenoh/secure*.json5, mutual TLS) ends every link at a node that enforces Zenoh's
`access_control`: the daemon as a secure peer, or a router. Both halves here are driven by rsu.yaml:

- `render_site_config` (`rsucal access-control`) writes the per-site entries into a base config: per
  calibration vehicle a rule allowing a put on exactly `v2x/cam/{station_id}`, per camera one allowing puts
  on exactly its `.../detections` and `.../image`, each bound by a policy to a subject that lists the
  certificate common names of that vehicle or of that camera's detectors. Generated ids name what they grant
  (rule `v2x/4242`, subject and policy `vehicle/4242`; `detections/{rsu}/{cam}`, `detectors/{rsu}/{cam}`),
  so a re-run replaces them and keeps every other entry of the base.
- `check_access_rules` (daemon start) evaluates the rules the daemon runs with as Zenoh does and raises
  AccessControlError (exit 2) unless exactly the configured identities may put each configured vehicle's
  and camera's keys, and no rule hands out a wildcard or a stale key among them.
"""

from __future__ import annotations

import functools
import itertools
import json
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from daemon.bus import BusError, session_config, zenoh_message
from daemon.keys import ALL_V2X, detections_key, image_key, v2x_key
from pipeline.errors import InputError
from schemas.atomic import write_atomic
from schemas.config import DaemonConfig

# Messages that publish data on a key (the daemon subscribes to detections and V2X; it never queries them).
PUBLISHING = ("put", "delete")
# Links whose remote end is known by a certificate common name; on any other link a node has no CN.
CN_LINKS = frozenset({"tls", "quic"})
# Zenoh's link protocols, for a node whose `transport/link/protocols` is null (every one enabled).
ALL_LINKS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial", "vsock")
# Stands for every certificate of the CA whose CN no subject lists (the intruder of issue 14).
OTHER_CERTIFICATE = "any other certificate"
MAX_PROBLEMS = 12  # the start-up error names this many mismatches, then counts the rest


class AccessControlError(InputError):
    """The access rules of a secure deployment do not bind the configured detectors and vehicles."""


def expected_publishers(config: DaemonConfig) -> dict[str, tuple[str, tuple[str, ...]]]:
    """key -> (owner, common names that alone may put it): every vehicle's V2X key and every camera's
    detections and image keys, from rsu.yaml."""
    expected: dict[str, tuple[str, tuple[str, ...]]] = {}
    for vehicle in config.vehicles:
        expected[v2x_key(vehicle.station_id)] = (f"vehicle {vehicle.station_id}", vehicle.common_names())
    for camera in config.cameras:
        names = config.detector_common_names(camera.camera_id)
        for key in (
            detections_key(config.rsu_id, camera.camera_id),
            image_key(config.rsu_id, camera.camera_id),
        ):
            expected[key] = (f"camera {camera.camera_id}", names)
    return expected


# ------------------------------------------------------------------------------------------ the generator


def _generated(
    config: DaemonConfig,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[dict[str, Any]]]:
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def grant(rule_id: str, subject_id: str, keys: list[str], names: Sequence[str]) -> None:
        rules.append(
            {
                "id": rule_id,
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["put"],
                "key_exprs": keys,
            }
        )
        subjects.append({"id": subject_id, "cert_common_names": list(names), "link_protocols": ["tls"]})
        policies.append({"id": subject_id, "subjects": [subject_id], "rules": [rule_id]})

    for vehicle in config.vehicles:
        station = vehicle.station_id
        grant(f"v2x/{station}", f"vehicle/{station}", [v2x_key(station)], vehicle.common_names())
    for camera in config.cameras:
        rsu, cam = config.rsu_id, camera.camera_id
        keys = [detections_key(rsu, cam), image_key(rsu, cam)]
        grant(f"detections/{rsu}/{cam}", f"detectors/{rsu}/{cam}", keys, config.detector_common_names(cam))
    return rules, subjects, policies


def site_access_control(config: DaemonConfig, base: Mapping[str, Any]) -> dict[str, Any]:
    """`base` (an `access_control` section) with its generated entries replaced by those of `config`: every
    `v2x/`/`vehicle/` entry and this RSU's `detections/{rsu}/`/`detectors/{rsu}/` entries (on a router shared
    by several RSUs, other RSUs' camera entries stay; the vehicles are the fleet of the last rsu.yaml)."""
    rule_prefixes = ("v2x/", f"detections/{config.rsu_id}/")
    subject_prefixes = ("vehicle/", f"detectors/{config.rsu_id}/")

    def kept(entries: Any, prefixes: tuple[str, ...]) -> list[dict[str, Any]]:
        return [dict(entry) for entry in entries or [] if not str(entry.get("id") or "").startswith(prefixes)]

    rules, subjects, policies = _generated(config)
    return {
        **base,
        "enabled": True,
        "default_permission": "deny",
        "rules": kept(base.get("rules"), rule_prefixes) + rules,
        "subjects": kept(base.get("subjects"), subject_prefixes) + subjects,
        "policies": kept(base.get("policies"), subject_prefixes) + policies,
    }


def render_site_config(config: DaemonConfig, base_file: Path) -> str:
    """The Zenoh config `base_file` (e.g. deploy/zenoh/secure.json5) with this site's access rules, as JSON
    (a valid JSON5 file; the base's comments are not kept). AccessControlError when an entry of the base
    still contradicts the site (e.g. an old `v2x/**` rule), naming it."""
    try:
        zconfig = zenoh.Config.from_file(str(base_file))
        acl = site_access_control(config, json.loads(zconfig.get_json("access_control")))
        zconfig.insert_json5("access_control", json.dumps(acl))
        protocols = json.loads(zconfig.get_json("transport/link/protocols"))
        mode = json.loads(zconfig.get_json("mode"))
    except zenoh.ZError as err:
        raise BusError(f"zenoh config {base_file}: {zenoh_message(err)}") from err
    if mode == "client":
        raise AccessControlError(
            f"--base {base_file}",
            "a client enforces no access control; start from the enforcing node's config "
            "(secure.json5 for the daemon as a secure peer, secure-router.json5 for a router)",
        )
    problems = access_problems(config, AccessRules.parse(acl, protocols), owns_rules=mode != "router")
    if problems:
        raise AccessControlError(
            f"--base {base_file}", _summary(problems, "entries of the base contradict rsu.yaml")
        )
    return json.dumps(json.loads(str(zconfig)), indent=2) + "\n"


def write_site_config(config: DaemonConfig, base_file: Path, out: Path) -> Path:
    """render_site_config, written atomically (schemas.atomic): a node never reads half a config."""
    text = render_site_config(config, base_file)
    try:
        write_atomic(out, text.encode("utf-8"))
    except OSError as err:
        raise InputError(f"--out {out}", f"cannot write: {err.strerror or err}") from err
    return out


# ------------------------------------------------------------------------------------------ Zenoh's semantics


@dataclass(frozen=True, slots=True)
class Combination:
    """One subject combination as Zenoh builds them: the cartesian product of a subject's property lists,
    an absent list matching anything (None). Identical combinations of several subjects are one, sharing
    their rules."""

    interface: str | None
    cert_common_name: str | None
    username: str | None
    link_protocol: str | None
    zid: str | None

    def may_match(self, common_name: str | None, link: str) -> bool:
        """True if some link of `link` protocol with that certificate CN can match (interface, username and
        zid are unknown here, so a combination that names them might)."""
        return self.cert_common_name in (None, common_name) and self.link_protocol in (None, link)

    def surely_matches(self, common_name: str, link: str) -> bool:
        return (
            self.may_match(common_name, link)
            and self.interface is None
            and self.username is None
            and self.zid is None
        )


@dataclass(slots=True)
class _Grants:
    allow: list[tuple[str, str]] = field(default_factory=list)  # (key expression, rule id)
    deny: list[tuple[str, str]] = field(default_factory=list)


@functools.lru_cache(maxsize=65536)
def _includes(rule_key: str, key: str) -> bool:
    return bool(zenoh.KeyExpr(rule_key).includes(zenoh.KeyExpr(key)))


@functools.lru_cache(maxsize=65536)
def _intersects(rule_key: str, key: str) -> bool:
    return bool(zenoh.KeyExpr(rule_key).intersects(zenoh.KeyExpr(key)))


@dataclass(frozen=True, slots=True)
class AccessRules:
    """An `access_control` section evaluated as Zenoh 1.x does (interceptor/authorization.rs): a link
    matches every combination whose properties it has; a message passes if one matched combination passes
    it, i.e. no deny rule of that combination includes the message's key and an allow rule does (default
    deny; a rule applies only when its key expression INCLUDES the message's)."""

    enabled: bool
    default_permission: str
    links: tuple[str, ...]  # protocols a node can connect over
    common_names: tuple[str, ...]  # every CN a subject lists
    grants: Mapping[tuple[Combination, str], _Grants]  # (combination, message) of ingress rules
    problems: tuple[str, ...]  # entries Zenoh itself would refuse (unknown rule or subject ids)

    @staticmethod
    def parse(acl: Mapping[str, Any], protocols: Sequence[str] | None) -> AccessRules:
        problems: list[str] = []
        rules = {str(rule.get("id")): rule for rule in acl.get("rules") or []}
        combinations: dict[str, list[Combination]] = {}
        names: set[str] = set()
        for subject in acl.get("subjects") or []:
            lists = [
                subject.get(prop) or [None]
                for prop in ("interfaces", "cert_common_names", "usernames", "link_protocols", "zids")
            ]
            names.update(subject.get("cert_common_names") or [])
            combinations[str(subject.get("id"))] = [
                Combination(*combo) for combo in itertools.product(*lists)
            ]
        grants: dict[tuple[Combination, str], _Grants] = {}
        for index, policy in enumerate(acl.get("policies") or []):
            name = policy.get("id") or f"#{index}"
            for subject_id in policy.get("subjects") or []:
                if subject_id not in combinations:
                    problems.append(f"policy {name} names no subject {subject_id!r}")
            for rule_id in policy.get("rules") or []:
                rule = rules.get(rule_id)
                if rule is None:
                    problems.append(f"policy {name} names no rule {rule_id!r}")
                    continue
                if "ingress" not in (rule.get("flows") or ["ingress", "egress"]):
                    continue
                for subject_id in policy.get("subjects") or []:
                    for combination in combinations.get(subject_id, []):
                        for message in set(rule.get("messages") or []) & set(PUBLISHING):
                            entry = grants.setdefault((combination, message), _Grants())
                            side = entry.allow if rule.get("permission") == "allow" else entry.deny
                            side.extend((key, rule_id) for key in rule.get("key_exprs") or [])
        return AccessRules(
            enabled=bool(acl.get("enabled")),
            default_permission=str(acl.get("default_permission")),
            links=tuple(protocols) if protocols else ALL_LINKS,
            common_names=tuple(sorted(names)),
            grants=grants,
            problems=tuple(problems),
        )

    def identities(self) -> Iterator[tuple[str | None, str, str]]:
        """(common name, link, label) standing for every kind of node that can connect: each listed CN and
        one unlisted certificate on every certificate link, and a node without a CN on every other link."""
        for link in self.links:
            if link in CN_LINKS:
                for name in (*self.common_names, OTHER_CERTIFICATE):
                    yield name, link, name if link == "tls" else f"{name} over {link}"
            else:
                yield None, link, f"a node over plain {link}"

    def passing(self, message: str, key: str) -> list[tuple[Combination, list[str]]]:
        """The combinations that pass `message` on `key`, each with the ids of the allow rules that do."""
        passing: list[tuple[Combination, list[str]]] = []
        for (combination, kind), entry in self.grants.items():
            if kind != message or any(_includes(rule_key, key) for rule_key, _ in entry.deny):
                continue
            rule_ids = [rule_id for rule_key, rule_id in entry.allow if _includes(rule_key, key)]
            if rule_ids:
                passing.append((combination, rule_ids))
        return passing

    def allowing(
        self,
        common_name: str | None,
        link: str,
        message: str,
        key: str,
        surely: bool = False,
        passing: Sequence[tuple[Combination, list[str]]] | None = None,
    ) -> list[str]:
        """Ids of the allow rules that let such a node send `message` on `key` (empty: refused). With
        `surely`, only combinations that match whatever its interface, username or zid count. `passing`:
        the result of passing(message, key), when the caller asks about many nodes."""
        rule_ids: set[str] = set()
        for combination, ids in self.passing(message, key) if passing is None else passing:
            matches = (
                combination.surely_matches(common_name, link)
                if surely and common_name is not None
                else combination.may_match(common_name, link)
            )
            if matches:
                rule_ids.update(ids)
        return sorted(rule_ids)

    def allowed_keys(self) -> Iterator[tuple[str, str, str]]:
        """(message, key expression, rule id) of every publishing allow rule some subject has."""
        seen: set[tuple[str, str, str]] = set()
        for (_, message), entry in self.grants.items():
            for key, rule_id in entry.allow:
                if (message, key, rule_id) not in seen:
                    seen.add((message, key, rule_id))
                    yield message, key, rule_id


# ------------------------------------------------------------------------------------------ the check


def access_problems(config: DaemonConfig, rules: AccessRules, *, owns_rules: bool) -> list[str]:
    """What keeps `rules` from binding exactly the configured identities to their keys (empty: they do).

    `owns_rules`: the rules are the daemon's own (a secure peer), so a rule for a station or camera that
    rsu.yaml does not list is stale; a router may serve other RSUs and vehicles, so only this RSU's camera
    keys are held to rsu.yaml there.
    """
    if not rules.enabled:
        return ["access_control.enabled is false: every certificate of the CA may publish anything"]
    if rules.default_permission != "deny":
        return ["access_control.default_permission must be deny: with allow, any key no rule names is open"]
    problems = list(rules.problems)
    expected = expected_publishers(config)
    identities = list(rules.identities())
    for key, (owner, names) in expected.items():
        passing = {message: rules.passing(message, key) for message in PUBLISHING}
        for name in names:
            if not rules.allowing(name, "tls", "put", key, surely=True, passing=passing["put"]):
                problems.append(
                    f"{owner}: {name} may not put {key} (no rule of a subject naming it allows it)"
                )
        for identity, link, label in identities:
            if identity in names and link in CN_LINKS:
                continue
            for message in PUBLISHING:
                rule_ids = rules.allowing(identity, link, message, key, passing=passing[message])
                if rule_ids:
                    problems.append(f"{owner}: {label} may {message} {key} (rule {', '.join(rule_ids)})")

    vehicle_names = sorted({name for vehicle in config.vehicles for name in vehicle.common_names()})
    own_inputs = [detections_key(config.rsu_id, "*"), image_key(config.rsu_id, "*")]
    for message, rule_key, rule_id in rules.allowed_keys():
        if rule_key in expected:
            continue
        on_v2x = _intersects(rule_key, ALL_V2X)
        if not on_v2x and not any(_intersects(rule_key, key) for key in own_inputs):
            continue
        granted = f"rule {rule_id} allows {message} on {rule_key}"
        if "*" in rule_key or "$" in rule_key:
            problems.append(f"{granted}, a wildcard over vehicle or detector keys (one exact key each)")
        elif on_v2x:
            if owns_rules:
                problems.append(f"{granted}: station {rule_key.removeprefix('v2x/cam/')} is not in vehicles")
            for name in vehicle_names:
                rule_ids = rules.allowing(name, "tls", message, rule_key)
                if rule_ids:
                    by_rules = ", ".join(rule_ids)
                    problems.append(
                        f"{name} may {message} {rule_key}, not its own station's key (rule {by_rules})"
                    )
        else:
            problems.append(f"{granted}: camera {rule_key.split('/')[3]} is not in cameras")
    return list(dict.fromkeys(problems))  # in order, each once


def _summary(problems: Sequence[str], what: str) -> str:
    shown = "; ".join(problems[:MAX_PROBLEMS])
    more = f"; and {len(problems) - MAX_PROBLEMS} more" if len(problems) > MAX_PROBLEMS else ""
    return f"{what}: {shown}{more}"


def _rules_of(zconfig: zenoh.Config) -> tuple[dict[str, Any], list[str] | None, str]:
    acl = json.loads(zconfig.get_json("access_control"))
    protocols = json.loads(zconfig.get_json("transport/link/protocols"))
    return acl, protocols, json.loads(zconfig.get_json("mode"))


def check_access_rules(config: DaemonConfig) -> int:
    """At start: the access rules the daemon runs with must bind its cameras and vehicles (see the module).

    The rules are those of its own Zenoh config when it enforces access control (a secure peer), and those
    of `zenoh.access_control_file` (the router's) when given. A mutual-TLS daemon with neither cannot show
    that any rule protects its inputs and is refused too. Returns how many rule sets were checked (0 on a
    plain bus); raises AccessControlError naming every mismatch, BusError for an unreadable Zenoh file.
    """
    zconf = config.zenoh
    own = session_config(zconf)
    acl, protocols, mode = _rules_of(own)
    checked: list[tuple[str, dict[str, Any], list[str] | None, bool]] = []
    where = f"zenoh.config_file {zconf.config_file}" if zconf.config_file is not None else "zenoh"
    if acl.get("enabled"):
        checked.append((where, acl, protocols, mode != "router"))
    if zconf.access_control_file is not None:
        try:
            router = zenoh.Config.from_file(str(zconf.access_control_file))
        except zenoh.ZError as err:
            raise BusError(
                f"zenoh.access_control_file {zconf.access_control_file}: {zenoh_message(err)}"
            ) from err
        router_acl, router_protocols, _ = _rules_of(router)
        checked.append(
            (f"zenoh.access_control_file {zconf.access_control_file}", router_acl, router_protocols, False)
        )
    if not checked and json.loads(own.get_json("transport/link/tls/enable_mtls")) is True:
        raise AccessControlError(
            "zenoh.access_control_file",
            f"the daemon speaks mutual TLS ({where}) but enforces no access control itself: name the config "
            "of the router that does (e.g. secure-router.json5) so its rules can be checked",
        )
    for source, rules_acl, rules_protocols, owns in checked:
        problems = access_problems(config, AccessRules.parse(rules_acl, rules_protocols), owns_rules=owns)
        if problems:
            raise AccessControlError(source, _summary(problems, "access rules do not match rsu.yaml"))
    return len(checked)
