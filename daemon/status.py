"""`rsucal status`: read every camera's calibration status, result and health over the bus, for operators.

A short-lived peer session connects to the daemon (or a router), sends the status, calibration, health and
liveliness gets at once, decodes the replies with the schemas (a bad reply is reported, never fatal) and
closes. The exit code (0: a health answer came, 1: nothing answered) serves the Docker HEALTHCHECK.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import textwrap
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TypeVar

import zenoh
from pydantic import BaseModel, ValidationError

from daemon.bus import (
    NO_CALIBRATION,
    BusError,
    client_config,
    connect_endpoints,
    open_session,
    split_replies,
    start_query,
    zenoh_message,
)
from daemon.keys import alive_key, calibration_key, health_key, parse_alive_key, status_key
from pipeline.errors import InputError
from schemas.common import decode_json, describe_validation_error
from schemas.results import CalibrationResult, CalibrationStatus, Health

EXIT_HEALTHY = 0
EXIT_NO_ANSWER = 1
DEFAULT_TIMEOUT_S = 2.0
# The same characters as schemas.common.Identifier: safe inside a key expression (no `/`, `*`, `$`).
_IDENTIFIER_CHARS = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_.-")
# <protocol>/<address>[?<metadata>][#<config>] as Zenoh takes it; checked here for a plain message.
_ENDPOINT = re.compile(r"^[a-z][a-z0-9+-]*/\S+$")
_CELL_MAX_CHARS = 44
_WIDTH = 110

M = TypeVar("M", bound=BaseModel)


@dataclass(frozen=True, slots=True)
class StatusReport:
    """Everything one `rsucal status` read: decoded answers, RSUs with a liveliness token, problems."""

    fetched_at_ns: int
    endpoints: tuple[str, ...]
    timeout_s: float
    statuses: tuple[CalibrationStatus, ...] = ()  # sorted by (rsu_id, camera_id)
    results: tuple[CalibrationResult, ...] = ()  # latest validated result of the cameras that have one
    health: tuple[Health, ...] = ()  # sorted by rsu_id
    alive: tuple[str, ...] = ()  # rsu ids whose `rsu/{rsu}/alive` token is present
    problems: tuple[str, ...] = ()  # bad or error replies, each naming its key

    @property
    def answered(self) -> bool:
        """True when at least one RSU's health answered (what the HEALTHCHECK asks)."""
        return bool(self.health)

    def result_for(self, rsu_id: str, camera_id: str) -> CalibrationResult | None:
        for result in self.results:
            if result.rsu_id == rsu_id and result.camera_id == camera_id:
                return result
        return None


def _check_identifier(option: str, value: str | None) -> str:
    """`value` or the wildcard `*`; InputError for anything that is not an rsucal identifier."""
    if value is None:
        return "*"
    if not value or len(value) > 64 or not set(value) <= _IDENTIFIER_CHARS:
        raise InputError(option, f"{value!r} is not an id (letters, digits, '_', '.', '-'; at most 64)")
    return value


def _decode_all(
    model: type[M], replies: Sequence[tuple[str, bytes]], problems: list[str]
) -> list[tuple[str, M]]:
    decoded: list[tuple[str, M]] = []
    for key, payload in replies:
        try:
            decoded.append((key, decode_json(model, payload)))
        except ValidationError as err:
            problems.append(f"{key}: bad {model.__name__}: {describe_validation_error(err)}")
    return decoded


def _check_key(key: str, expected: str, problems: list[str]) -> None:
    if key != expected:
        problems.append(f"{key}: the payload names {expected} (misconfigured rsu_id or camera_id?)")


def fetch_status(
    connect: Sequence[str],
    rsu: str | None,
    camera: str | None,
    timeout_s: float,
    zenoh_config: Path | None = None,
) -> StatusReport:
    """Query `rsu/{rsu or *}/camera/{camera or *}/calibration[/status]`, `rsu/{rsu or *}/health` and the
    liveliness tokens `rsu/{rsu or *}/alive` through `connect`; `zenoh_config` is a Zenoh JSON5 base config
    (TLS certificates for a secure site) whose own endpoints are used when `connect` is empty (without a
    file: tcp/127.0.0.1:7447). The report names the endpoints used.

    Raises InputError for a malformed --rsu/--camera and BusError when no session can be opened.
    """
    rsu_part = _check_identifier("--rsu", rsu)
    camera_part = _check_identifier("--camera", camera)
    if not (math.isfinite(timeout_s) and timeout_s > 0.0):
        raise InputError("--timeout", f"{timeout_s} must be a finite number of seconds > 0")
    for endpoint in connect:
        if not _ENDPOINT.match(endpoint):
            raise InputError(
                "--connect",
                f"{endpoint!r} is not a Zenoh endpoint like tcp/127.0.0.1:7447 or tls/host:7447 "
                "(<protocol>/<address>)",
            )
    if zenoh_config is not None and not zenoh_config.is_file():
        raise InputError("--zenoh-config", f"{zenoh_config} is not a readable file")
    try:
        config = client_config(connect, config_file=zenoh_config)
    except BusError as err:  # the file or an endpoint is malformed: bad input, not an absent daemon
        raise InputError("--zenoh-config" if zenoh_config is not None else "--connect", str(err)) from err
    # Without --connect, the endpoints are those the --zenoh-config file gives (or loopback without one).
    endpoints = tuple(connect) or tuple(connect_endpoints(config))
    session = open_session(config, endpoints or (f"no endpoints in {zenoh_config}",))
    try:
        # All gets in flight at once: the read takes one timeout at worst, not four.
        pending_statuses = start_query(session, status_key(rsu_part, camera_part), timeout_s)
        pending_results = start_query(session, calibration_key(rsu_part, camera_part), timeout_s)
        pending_health = start_query(session, health_key(rsu_part), timeout_s)
        try:
            pending_alive = session.liveliness().get(alive_key(rsu_part), timeout=timeout_s)
        except zenoh.ZError as err:
            raise BusError(f"liveliness get {alive_key(rsu_part)}: {zenoh_message(err)}") from err
        statuses_replies = split_replies(pending_statuses)
        results_replies = split_replies(pending_results)
        health_replies = split_replies(pending_health)
        alive_replies = split_replies(pending_alive)
    finally:
        session.close()  # type: ignore[no-untyped-call]  # zenoh stubs lack -> None
    fetched_at_ns = time.time_ns()

    problems: list[str] = []
    problems.extend(statuses_replies.errors)
    # "no validated calibration" is an answer (the status row says so), not a problem.
    problems.extend(e for e in results_replies.errors if not e.endswith(NO_CALIBRATION))
    problems.extend(health_replies.errors)
    statuses = _decode_all(CalibrationStatus, statuses_replies.ok, problems)
    for key, status in statuses:
        _check_key(key, status_key(status.rsu_id, status.camera_id), problems)
    results = _decode_all(CalibrationResult, results_replies.ok, problems)
    for key, result in results:
        _check_key(key, calibration_key(result.rsu_id, result.camera_id), problems)
    health = _decode_all(Health, health_replies.ok, problems)
    for key, answer in health:
        _check_key(key, health_key(answer.rsu_id), problems)
    alive = sorted({rsu for key, _ in alive_replies.ok if (rsu := parse_alive_key(key)) is not None})
    return StatusReport(
        fetched_at_ns=fetched_at_ns,
        endpoints=endpoints,
        timeout_s=timeout_s,
        statuses=tuple(sorted((s for _, s in statuses), key=lambda s: (s.rsu_id, s.camera_id))),
        results=tuple(r for _, r in results),
        health=tuple(sorted((h for _, h in health), key=lambda h: h.rsu_id)),
        alive=tuple(alive),
        problems=tuple(problems),
    )


# ------------------------------------------------------------------------------------------- formatting


def format_utc(stamp_ns: int) -> str:
    """'2026-11-21 10:40:12Z' (UTC, whole seconds)."""
    return datetime.fromtimestamp(stamp_ns // 1_000_000_000, tz=UTC).strftime("%Y-%m-%d %H:%M:%SZ")


def format_duration(seconds: float) -> str:
    """'4.2 s', '41 s', '5 min 3 s', '2 h 5 min', '3 d 4 h': two units at most; tenths only below 10 s."""
    if seconds < 10.0 and seconds != int(seconds):
        return f"{seconds:.1f} s"
    whole = round(seconds)
    if whole < 60:
        return f"{whole} s"
    if whole < 3600:
        minutes, secs = divmod(whole, 60)
        return f"{minutes} min {secs} s" if minutes < 10 and secs else f"{minutes} min"
    if whole < 86_400:
        hours, rest = divmod(whole, 3600)
        return f"{hours} h {rest // 60} min" if rest >= 60 else f"{hours} h"
    days, rest = divmod(whole, 86_400)
    return f"{days} d {rest // 3600} h" if rest >= 3600 else f"{days} d"


def format_age(stamp_ns: int, now_ns: int) -> str:
    """'12 s ago', '3 h 5 min ago'; 'in 12 s' for a stamp ahead of `now_ns` (a daemon on a scaled clock)."""
    delta_s = (now_ns - stamp_ns) // 1_000_000_000  # whole seconds: "12 s ago", never "12.4 s ago"
    if delta_s >= 0:
        return f"{format_duration(delta_s)} ago"
    return f"in {format_duration(-delta_s)}"


def format_bytes(size: int) -> str:
    """'512 B', '12.3 GiB'."""
    value = float(size)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if value < 1024.0 or unit == "TiB":
            return f"{size} B" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024.0
    raise AssertionError("unreachable")


def _cell(text: str) -> str:
    return text if len(text) <= _CELL_MAX_CHARS else text[: _CELL_MAX_CHARS - 1] + "…"


def _table(headers: Sequence[str], rows: Sequence[tuple[Sequence[str], Sequence[str]]]) -> list[str]:
    """Fixed-width columns (two spaces apart); each row may carry indented continuation lines."""
    cells = [[_cell(c) for c in row] for row, _ in rows]
    widths = [max([len(h)] + [len(r[i]) for r in cells]) for i, h in enumerate(headers)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(headers, widths, strict=True)).rstrip()]
    indent = " " * (widths[0] + 2)
    for row, (_, extra) in zip(cells, rows, strict=True):
        lines.append("  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip())
        for note in extra:
            lines.extend(textwrap.wrap(note, _WIDTH, initial_indent=indent, subsequent_indent=indent + "  "))
    return lines


def _camera_row(
    status: CalibrationStatus, result: CalibrationResult | None, now_ns: int
) -> tuple[list[str], list[str]]:
    job = status.last_job
    notes: list[str] = []
    if job is None:
        last_job = "-"
    elif job.finished_ns is None:
        last_job = f"running, started {format_age(job.started_ns, now_ns)}"
    else:
        took = f", took {format_duration(job.duration_s)}" if job.duration_s is not None else ""
        verdict = job.verdict.status if job.verdict is not None else "failed (no verdict)"
        last_job = f"{format_age(job.finished_ns, now_ns)}{took}, {verdict}"
        if job.verdict is not None and job.verdict.reasons:
            notes.append(f"{job.job_id} {job.verdict.status}: " + "; ".join(job.verdict.reasons))
        if job.report is not None:
            notes.append(f"{job.job_id} report: {job.report}")
    verified = format_age(status.verified_at_ns, now_ns) if status.verified_at_ns is not None else "-"
    position = accuracy = "-"
    if result is not None and result.camera_position is not None:
        where = result.camera_position
        if where.lat is not None and where.lon is not None and where.alt is not None:
            position = f"{where.lat:.6f}, {where.lon:.6f}, {where.alt:.1f} m"
        else:  # a result in a local frame (never the daemon's own, which are UTM)
            position = f"{result.frame.crs} {where.utm[0]:.1f}, {where.utm[1]:.1f}, {where.utm[2]:.1f} m"
    if result is not None and result.uncertainty is not None:
        accuracy = f"±{result.uncertainty.position_std_m:.2f} m, ±{result.uncertainty.rotation_std_deg:.2f}°"
    row = [
        status.rsu_id,
        status.camera_id,
        status.state,
        f"{status.traversals}/{status.traversals_needed}",
        last_job,
        status.current_result_id or "-",
        verified,
        position,
        accuracy,
        format_time_offset(status.time_offset_ns, status.time_offset_std_ns),
    ]
    return row, notes


def format_time_offset(offset_ns: int | None, std_ns: float | None) -> str:
    """The camera's estimated time offset (vehicle clock minus camera stamp): '+81.0 ms ±2.5', or '-'."""
    if offset_ns is None:
        return "-"
    text = f"{offset_ns / 1e6:+.1f} ms"
    return text if std_ns is None else f"{text} ±{std_ns / 1e6:.1f}"


def _health_row(
    rsu_id: str, health: Health | None, is_alive: bool, report: StatusReport
) -> tuple[list[str], list[str]]:
    alive = "yes" if is_alive else "no"
    if health is None:
        return [rsu_id, alive, *["-"] * 8], [f"no health answer within {report.timeout_s:g} s"]
    disk = health.disk
    row = [
        rsu_id,
        alive,
        format_duration(health.uptime_s),
        format_utc(health.started_at_ns),
        str(len(health.cameras)),
        str(health.inbox_depth),
        str(health.jobs_running),
        format_bytes(disk.free_bytes) if disk is not None else "-",
        f"{format_bytes(disk.recordings_bytes)} in {disk.recordings_files} files" if disk else "-",
        ", ".join(f"{name} {version}" for name, version in sorted(health.versions.items())) or "-",
    ]
    counters = ", ".join(f"{name} {value}" for name, value in sorted(health.counters.items()))
    return row, [f"counters: {counters}"] if counters else []


def format_status(report: StatusReport) -> str:
    """The operator's table: one row per camera, then one per RSU (health), then any problems."""
    now_ns = report.fetched_at_ns
    where = ", ".join(report.endpoints)
    rsu_ids = sorted(
        {h.rsu_id for h in report.health} | set(report.alive) | {s.rsu_id for s in report.statuses}
    )
    if not rsu_ids:
        lines = [
            f"no RSU answered on {where} within {report.timeout_s:g} s (is rsucal daemon running there?)"
        ]
    else:
        lines = [
            f"rsucal status at {format_utc(now_ns)} via {where}: {len(rsu_ids)} RSU(s), "
            f"{len(report.statuses)} camera(s)",
            "",
        ]
        if report.statuses:
            rows = [_camera_row(s, report.result_for(s.rsu_id, s.camera_id), now_ns) for s in report.statuses]
            headers = ["RSU", "CAMERA", "STATE", "TRAVERSALS", "LAST JOB", "RESULT", "VERIFIED"]
            lines += _table([*headers, "POSITION (LAT, LON, ALT)", "ACCURACY", "TIME OFFSET"], rows)
            lines.append("")
        health_by_rsu = {h.rsu_id: h for h in report.health}
        rows = [_health_row(r, health_by_rsu.get(r), r in report.alive, report) for r in rsu_ids]
        headers = ["RSU", "ALIVE", "UP", "STARTED", "CAMERAS", "INBOX", "JOBS", "DISK FREE", "RECORDINGS"]
        lines += _table([*headers, "VERSIONS"], rows)
    if report.problems:
        lines += ["", "problems:"]
        lines += [f"  {problem}" for problem in report.problems]
    return "\n".join(lines)


def report_json(report: StatusReport) -> str:
    """The report as JSON: the decoded answers as the daemon sent them, plus liveliness and problems."""
    return json.dumps(
        {
            "fetched_at_ns": report.fetched_at_ns,
            "endpoints": list(report.endpoints),
            "health": [h.model_dump(mode="json") for h in report.health],
            "alive": list(report.alive),
            "statuses": [s.model_dump(mode="json") for s in report.statuses],
            "calibrations": [r.model_dump(mode="json") for r in report.results],
            "problems": list(report.problems),
        },
        indent=2,
    )


def status_main(args: argparse.Namespace) -> int:
    """`rsucal status`: print the table (or --json); 0 when a health answered, 1 when nothing did.

    args: connect (list of endpoints, empty: the --zenoh-config file's, else tcp/127.0.0.1:7447), rsu,
    camera, timeout_s, json.
    """
    connect = [str(endpoint) for endpoint in (args.connect or [])]
    try:
        zenoh_config = Path(args.zenoh_config) if getattr(args, "zenoh_config", None) else None
        report = fetch_status(connect, args.rsu, args.camera, float(args.timeout_s), zenoh_config)
    except BusError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_NO_ANSWER
    if report.answered and args.camera is not None and not report.statuses:
        # Daemons answered, but none has this camera: a typo, not an outage.
        rsus = ", ".join(h.rsu_id for h in report.health)
        raise InputError("--camera", f"no camera {args.camera!r} on the RSU(s) that answered ({rsus})")
    print(report_json(report) if args.json else format_status(report))
    return EXIT_HEALTHY if report.answered else EXIT_NO_ANSWER
