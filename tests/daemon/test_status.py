"""daemon.status (`rsucal status`) against a running Bus with stub handlers on real Zenoh peers; its table."""

from __future__ import annotations

import argparse
import json
import re
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from helpers import free_port
from test_bus import FixedClock, make_config

from daemon.bus import Bus, Handlers
from daemon.status import (
    EXIT_HEALTHY,
    EXIT_NO_ANSWER,
    StatusReport,
    fetch_status,
    format_age,
    format_bytes,
    format_duration,
    format_status,
    format_utc,
    status_main,
)
from pipeline.errors import InputError
from schemas.common import CameraIntrinsics
from schemas.results import (
    CalibrationResult,
    CalibrationStatus,
    CameraPosition,
    DiskUsage,
    Health,
    JobSummary,
    ReferenceFrame,
    Uncertainty,
    Verdict,
)

NOW_NS = 1_795_689_612_000_000_000  # 2026-11-26 10:40:12Z
S = 1_000_000_000
IDENTITY = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def _status(camera_id: str, now_ns: int) -> CalibrationStatus:
    if camera_id == "c1":
        return CalibrationStatus(
            rsu_id="r1",
            camera_id="c1",
            state="calibrated",
            traversals=3,
            traversals_needed=3,
            last_job=JobSummary(
                job_id="c1-job-7",
                started_ns=now_ns - 53 * S,
                finished_ns=now_ns - 12 * S,
                duration_s=41.2,
                verdict=Verdict(status="accepted"),
                report="/var/lib/rsucal/cameras/c1/history/0001-res-c1-7.html",
            ),
            current_result_id="res-c1-7",
            verified_at_ns=now_ns - 12 * S,
            time_offset_ns=81_040_000,
            time_offset_std_ns=2_500_000.0,
            updated_at_ns=now_ns,
        )
    return CalibrationStatus(
        rsu_id="r1",
        camera_id=camera_id,
        state="collecting",
        traversals=1,
        traversals_needed=3,
        last_job=JobSummary(
            job_id=f"{camera_id}-job-2",
            started_ns=now_ns - 7200 * S,
            finished_ns=now_ns - 7000 * S,
            duration_s=200.0,
            verdict=Verdict(status="refused", reasons=["delta_p mean 0.81 m > 0.5 m", "one traversal only"]),
        ),
        updated_at_ns=now_ns,
    )


def _result(now_ns: int) -> CalibrationResult:
    return CalibrationResult(
        rsu_id="r1",
        camera_id="c1",
        result_id="res-c1-7",
        created_at_ns=now_ns - 12 * S,
        frame=ReferenceFrame(crs="EPSG:32632", origin=(691_000.0, 5_335_000.0, 0.0)),
        R=IDENTITY,
        t=(0.0, 0.0, 10.0),
        camera_position=CameraPosition(
            utm=(691_010.0, 5_335_020.0, 527.25), lat=48.137154, lon=11.576124, alt=527.25
        ),
        intrinsics=CameraIntrinsics(width=1920, height=1080, fx=1000.0, fy=1000.0, cx=960.0, cy=540.0),
        uncertainty=Uncertainty(
            covariance=tuple(tuple(0.0 for _ in range(6)) for _ in range(6)),
            position_std_m=0.12,
            rotation_std_deg=0.08,
        ),
        verdict=Verdict(status="accepted"),
    )


def _health(now_ns: int) -> Health:
    return Health(
        rsu_id="r1",
        started_at_ns=now_ns - 11_520 * S,
        updated_at_ns=now_ns,
        uptime_s=11_520.0,
        cameras=["c1", "c2"],
        counters={"detections.received": 1240, "detections.accepted": 1234, "v2x.received": 310},
        inbox_depth=0,
        jobs_running=1,
        disk=DiskUsage(
            state_dir="/var/lib/rsucal",
            free_bytes=13_207_024_435,
            recordings_bytes=1_288_490_189,
            recordings_files=14,
        ),
        versions={"rsucal": "0.1.0", "zenoh": "1.10.2"},
    )


@dataclass
class Daemon:
    endpoint: str
    bad_status_for: set[str]


@pytest.fixture
def daemon() -> Iterator[Daemon]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    running = Daemon(endpoint, set())

    def status(camera_id: str) -> bytes:
        if camera_id in running.bad_status_for:
            return b'{"rsu_id": "r1", "camera_id": "c2", "state": "sleeping"}'
        return _status(camera_id, time.time_ns()).model_dump_json().encode()

    def calibration(camera_id: str) -> bytes | None:
        return _result(time.time_ns()).model_dump_json().encode() if camera_id == "c1" else None

    handlers = Handlers(
        calibration=calibration,
        status=status,
        trigger=lambda camera_id: b"{}",
        health=lambda: _health(time.time_ns()).model_dump_json().encode(),
    )
    with Bus(make_config(endpoint), lambda key, payload, received_ns: None, handlers, FixedClock()):
        yield running


def test_fetch_status_decodes_every_answer(daemon: Daemon) -> None:
    report = fetch_status([daemon.endpoint], None, None, timeout_s=5.0)
    assert [(s.rsu_id, s.camera_id, s.state) for s in report.statuses] == [
        ("r1", "c1", "calibrated"),
        ("r1", "c2", "collecting"),
    ]
    assert [r.result_id for r in report.results] == ["res-c1-7"]  # c2's "not yet" is no problem
    assert [h.rsu_id for h in report.health] == ["r1"] and report.alive == ("r1",)
    assert report.problems == () and report.answered


def test_fetch_status_filters_by_rsu_and_camera(daemon: Daemon) -> None:
    report = fetch_status([daemon.endpoint], "r1", "c2", timeout_s=5.0)
    assert [s.camera_id for s in report.statuses] == ["c2"] and report.results == ()
    assert report.answered
    elsewhere = fetch_status([daemon.endpoint], "r7", None, timeout_s=5.0)
    assert elsewhere.statuses == () and elsewhere.health == () and elsewhere.alive == ()
    assert not elsewhere.answered
    with pytest.raises(InputError, match=r"--rsu: 'r\*' is not an id"):
        fetch_status([daemon.endpoint], "r*", None, timeout_s=1.0)


def test_a_bad_reply_is_reported_and_the_good_ones_kept(daemon: Daemon) -> None:
    daemon.bad_status_for.add("c2")
    report = fetch_status([daemon.endpoint], None, None, timeout_s=5.0)
    assert [s.camera_id for s in report.statuses] == ["c1"]
    [problem] = report.problems
    assert problem.startswith("rsu/r1/camera/c2/calibration/status: bad CalibrationStatus: ")
    assert "state:" in problem and "traversals:" in problem
    assert "problems:" in format_status(report)


def test_format_status_prints_an_operator_table() -> None:
    report = StatusReport(
        fetched_at_ns=NOW_NS,
        endpoints=("tcp/127.0.0.1:7447",),
        timeout_s=2.0,
        statuses=(_status("c1", NOW_NS), _status("c2", NOW_NS)),
        results=(_result(NOW_NS),),
        health=(_health(NOW_NS),),
        alive=("r1",),
    )
    lines = format_status(report).splitlines()
    assert lines[0] == "rsucal status at 2026-11-26 10:40:12Z via tcp/127.0.0.1:7447: 1 RSU(s), 2 camera(s)"
    header, c1, c1_report, c2, reasons = lines[2:7]
    assert re.split(r"\s{2,}", header) == [
        "RSU", "CAMERA", "STATE", "TRAVERSALS", "LAST JOB", "RESULT", "VERIFIED", "POSITION (LAT, LON, ALT)",
        "ACCURACY", "TIME OFFSET",
    ]  # fmt: skip
    # Fixed-width columns: every row's cell starts where its header does.
    for column in ("STATE", "TRAVERSALS", "LAST JOB", "RESULT", "VERIFIED", "POSITION"):
        start = header.index(column)
        assert c1[start - 2 : start] == "  " and c1[start] != " ", column
    assert "calibrated  3/3 " in c1 and "12 s ago, took 41 s, accepted" in c1 and "res-c1-7" in c1
    assert "48.137154, 11.576124, 527.2 m" in c1 and "±0.12 m, ±0.08°" in c1
    # The camera's estimated time offset (latency included); none estimated yet for c2.
    assert c1.endswith("+81.0 ms ±2.5") and c2.endswith("  -")
    assert "collecting  1/3 " in c2 and "1 h 56 min ago, took 3 min 20 s, refused" in c2
    assert reasons.strip() == "c2-job-2 refused: delta_p mean 0.81 m > 0.5 m; one traversal only"
    assert c1_report.strip() == "c1-job-7 report: /var/lib/rsucal/cameras/c1/history/0001-res-c1-7.html"
    health_header, health_row, counters = lines[8:11]
    assert health_header.split()[:3] == ["RSU", "ALIVE", "UP"]
    assert health_row.split()[:3] == ["r1", "yes", "3"] and "3 h 12 min" in health_row
    assert "2026-11-26 07:28:12Z" in health_row and "12.3 GiB" in health_row
    assert "1.2 GiB in 14 files" in health_row and "rsucal 0.1.0, zenoh 1.10.2" in health_row
    assert (
        counters.strip() == "counters: detections.accepted 1234, detections.received 1240, v2x.received 310"
    )


def test_format_status_says_who_did_not_answer() -> None:
    nothing = StatusReport(fetched_at_ns=NOW_NS, endpoints=("tcp/127.0.0.1:7447",), timeout_s=0.5)
    assert format_status(nothing) == (
        "no RSU answered on tcp/127.0.0.1:7447 within 0.5 s (is rsucal daemon running there?)"
    )
    silent = StatusReport(fetched_at_ns=NOW_NS, endpoints=("tcp/a:1",), timeout_s=2.0, alive=("r2",))
    row, note = format_status(silent).splitlines()[-2:]
    assert row.split() == ["r2", "yes", *["-"] * 8]
    assert note == "     no health answer within 2 s"


def test_human_times_and_sizes() -> None:
    assert format_utc(NOW_NS + 999_999_999) == "2026-11-26 10:40:12Z"
    assert format_age(NOW_NS - 12 * S - 400_000_000, NOW_NS) == "12 s ago"
    assert format_age(NOW_NS, NOW_NS) == "0 s ago"
    assert format_age(NOW_NS + 300 * S, NOW_NS) == "in 5 min"
    assert [format_duration(s) for s in (4.25, 41.2, 303.0, 7500.0, 3 * 86_400 + 4 * 3600 + 5.0)] == [
        "4.2 s",
        "41 s",
        "5 min 3 s",
        "2 h 5 min",
        "3 d 4 h",
    ]
    assert [format_bytes(n) for n in (512, 1536, 13_207_024_435)] == ["512 B", "1.5 KiB", "12.3 GiB"]


def _args(endpoint: str, *, json_out: bool = False, timeout_s: float = 5.0) -> argparse.Namespace:
    return argparse.Namespace(connect=[endpoint], rsu=None, camera=None, timeout_s=timeout_s, json=json_out)


def test_status_main_prints_the_table_and_exits_0(daemon: Daemon, capsys: pytest.CaptureFixture[str]) -> None:
    assert status_main(_args(daemon.endpoint)) == EXIT_HEALTHY
    out = capsys.readouterr().out
    assert "RSU  CAMERA  STATE" in out and "calibrated" in out and "collecting" in out


def test_status_main_json_is_the_raw_answers(daemon: Daemon, capsys: pytest.CaptureFixture[str]) -> None:
    assert status_main(_args(daemon.endpoint, json_out=True)) == EXIT_HEALTHY
    data = json.loads(capsys.readouterr().out)
    assert [s["camera_id"] for s in data["statuses"]] == ["c1", "c2"]
    assert data["calibrations"][0]["result_id"] == "res-c1-7"
    assert data["health"][0]["counters"]["detections.accepted"] == 1234
    assert data["alive"] == ["r1"] and data["problems"] == []


def test_status_main_exits_1_when_nothing_listens(capsys: pytest.CaptureFixture[str]) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    assert status_main(_args(endpoint, timeout_s=0.3)) == EXIT_NO_ANSWER
    assert capsys.readouterr().out.startswith(f"no RSU answered on {endpoint} within 0.3 s")


def test_an_unknown_camera_on_an_answering_daemon_exits_2_naming_it(
    daemon: Daemon, capsys: pytest.CaptureFixture[str]
) -> None:
    from daemon.cli import main

    code = main(["status", "--connect", daemon.endpoint, "--camera", "nope", "--timeout", "5"])
    captured = capsys.readouterr()
    assert code == 2
    assert captured.err.startswith("error: --camera: no camera 'nope'") and "r1" in captured.err
    assert captured.out == ""  # no "0 camera(s)" table
    # The camera that exists still answers with exit 0.
    assert main(["status", "--connect", daemon.endpoint, "--camera", "c1", "--timeout", "5"]) == 0


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["--connect", "foo"], "--connect"),
        (["--connect", "tcp/127.0.0.1:7447", "--connect", " "], "--connect"),
        (["--zenoh-config", "/nonexistent/client.json5"], "--zenoh-config"),
        (["--timeout", "0"], "--timeout"),
        (["--timeout", "-1"], "--timeout"),
        (["--timeout", "nan"], "--timeout"),
        (["--rsu", "a/b"], "--rsu"),
    ],
)
def test_bad_status_arguments_exit_2_with_one_line_naming_the_option(
    argv: list[str], option: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from daemon.cli import main

    try:
        code = main(["status", *argv])
    except SystemExit as stop:  # argparse's own checks (--timeout) exit from parse_args
        code = int(stop.code or 0)
    err = capsys.readouterr().err
    assert code == 2
    assert option in err and "--timeout-s" not in err
    assert "Json5Err" not in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err


def test_a_malformed_zenoh_config_file_is_bad_input_not_an_absent_daemon(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from daemon.cli import main

    config = tmp_path / "client.json5"
    config.write_text("{ mode: 'client', connect: { endpoints: ['foo'] } }")
    assert main(["status", "--zenoh-config", str(config), "--timeout", "0.2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --zenoh-config:") and "Json5Err" not in err, err
