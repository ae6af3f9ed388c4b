"""`rsucal bridge cam|yolo`: CAM units and the generationDeltaTime wrap, the detector spellings, bad lines
counted and named without stopping, and both bridges end to end into a daemon over Zenoh on 127.0.0.1."""

from __future__ import annotations

import copy
import json
import logging
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh
from helpers import free_port, wait_until

from daemon.bridges import (
    BridgeReport,
    LineError,
    cam_converter,
    cam_to_v2x,
    generation_time_ns,
    run_bridge,
    yolo_converter,
    yolo_to_frame,
)
from daemon.bus import client_config, query
from daemon.cli import main
from daemon.main import Daemon
from daemon.recording import list_recordings, read_window
from schemas.common import CameraIntrinsics, VehicleProfile, decode_json
from schemas.config import CalibrationVehicle, CameraConfig, DaemonConfig, ZenohConfig
from schemas.results import Health

# 2026-01-01T00:00:00Z. TimestampIts counts TAI ms since 2004-01-01, 5 leap seconds ahead of UTC by then:
# (1767225600 - 1072915200) * 1000 + 5000 = 694310405000, and 694310405000 mod 65536 = 904.
NEW_YEAR_2026_NS = 1_767_225_600_000_000_000
NEW_YEAR_2026_DELTA_MS = 904
MS = 1_000_000

# A CAM as the JSON encoding of its ASN.1 definition (EN 302 637-2), CAM units throughout.
CAM: dict[str, Any] = {
    "header": {"protocolVersion": 2, "messageID": 2, "stationID": 4242},
    "cam": {
        "generationDeltaTime": NEW_YEAR_2026_DELTA_MS,
        "camParameters": {
            "basicContainer": {
                "stationType": 5,
                "referencePosition": {
                    "latitude": 483981487,
                    "longitude": 99723139,
                    "positionConfidenceEllipse": {
                        "semiMajorConfidence": 245,
                        "semiMinorConfidence": 200,
                        "semiMajorOrientation": 900,
                    },
                    "altitude": {"altitudeValue": 53612, "altitudeConfidence": "alt-000-20"},
                },
            },
            "highFrequencyContainer": {
                "basicVehicleContainerHighFrequency": {
                    "heading": {"headingValue": 905, "headingConfidence": 10},
                    "speed": {"speedValue": 1389, "speedConfidence": 98},
                    "driveDirection": "forward",
                    "vehicleLength": {
                        "vehicleLengthValue": 48,
                        "vehicleLengthConfidenceIndication": "noTrailerPresent",
                    },
                    "vehicleWidth": 19,
                    "longitudinalAcceleration": {
                        "longitudinalAccelerationValue": 0,
                        "longitudinalAccelerationConfidence": 102,
                    },
                    "curvature": {"curvatureValue": 0, "curvatureConfidence": "unavailable"},
                    "curvatureCalculationMode": "yawRateUsed",
                    "yawRate": {"yawRateValue": 0, "yawRateConfidence": "unavailable"},
                }
            },
        },
    },
}


def _cam(**edits: Any) -> dict[str, Any]:
    """CAM with `edits` applied: dotted paths ("cam.generationDeltaTime") to new values (None: delete)."""
    message = copy.deepcopy(CAM)
    for path, value in edits.items():
        *parents, last = path.split("__")
        target = message
        for part in parents:
            target = target[part]
        if value is None:
            del target[last]
        else:
            target[last] = value
    return message


HF = "cam__camParameters__highFrequencyContainer__basicVehicleContainerHighFrequency"
POSITION = "cam__camParameters__basicContainer__referencePosition"


def test_a_cam_becomes_a_v2x_position_in_project_units() -> None:
    message = cam_to_v2x(CAM, NEW_YEAR_2026_NS + 40 * MS)
    assert message.station_id == 4242
    assert message.stamp_ns == NEW_YEAR_2026_NS  # generated 40 ms before it was received
    assert (message.lat, message.lon, message.alt) == pytest.approx((48.3981487, 9.9723139, 536.12), abs=1e-9)
    assert (message.heading_deg, message.speed) == pytest.approx((90.5, 13.89))
    assert (message.length, message.width) == pytest.approx((4.8, 1.9))
    assert message.accuracies is not None
    # 95 % confidences -> 1 sigma: 2.45 m semi-major / 2.4477, 1.0 deg / 1.96, 0.98 m/s / 1.96
    assert message.accuracies.horizontal_m == pytest.approx(2.45 / 2.4477)
    assert message.accuracies.heading_deg == pytest.approx(1.0 / 1.96)
    assert message.accuracies.speed_mps == pytest.approx(0.5)
    # TS 103 900 spells the header's ids messageId / stationId.
    renamed = _cam(header={"protocolVersion": 2, "messageId": 2, "stationId": 7})
    assert cam_to_v2x(renamed, NEW_YEAR_2026_NS).station_id == 7


def test_generation_delta_time_wraps_against_our_clock() -> None:
    assert generation_time_ns(NEW_YEAR_2026_DELTA_MS, NEW_YEAR_2026_NS) == NEW_YEAR_2026_NS
    assert generation_time_ns(NEW_YEAR_2026_DELTA_MS - 136, NEW_YEAR_2026_NS) == NEW_YEAR_2026_NS - 136 * MS
    # Received when TimestampIts mod 65536 had wrapped to 40: a CAM stamped 65500 is 76 ms old, not 65 s.
    after_wrap_ns = NEW_YEAR_2026_NS + (65536 - NEW_YEAR_2026_DELTA_MS + 40) * MS
    assert generation_time_ns(65500, after_wrap_ns) == after_wrap_ns - 76 * MS
    # A sender clock 50 ms ahead of ours, across the wrap the other way.
    assert generation_time_ns(90, after_wrap_ns) == after_wrap_ns + 50 * MS
    # Sub-millisecond parts of our clock do not leak into the stamp.
    assert generation_time_ns(NEW_YEAR_2026_DELTA_MS, NEW_YEAR_2026_NS + 999_999) == NEW_YEAR_2026_NS


@pytest.mark.parametrize(
    ("edits", "field", "reason"),
    [
        ({f"{POSITION}__latitude": 900000001}, f"{POSITION}__latitude", "unavailable"),
        ({f"{POSITION}__longitude": 1800000001}, f"{POSITION}__longitude", "unavailable"),
        (
            {f"{POSITION}__altitude": {"altitudeValue": 800001}},
            f"{POSITION}__altitude__altitudeValue",
            "unavailable",
        ),
        ({f"{HF}__heading": {"headingValue": 3601}}, f"{HF}__heading__headingValue", "unavailable"),
        ({f"{HF}__speed": {"speedValue": 16383}}, f"{HF}__speed__speedValue", "unavailable"),
        ({f"{HF}__heading": {"headingValue": 3600}}, f"{HF}__heading__headingValue", "out_of_range"),
        ({f"{POSITION}__latitude": 48.39}, f"{POSITION}__latitude", "invalid"),  # degrees, not 1e-7 deg
        ({"cam__generationDeltaTime": 65536}, "cam__generationDeltaTime", "out_of_range"),
        ({"cam__generationDeltaTime": None}, "cam__generationDeltaTime", "missing"),
        ({"header__stationID": None}, "header__stationID", "missing"),
        ({"header__messageID": 1}, "header__messageID", "not_cam"),  # a DENM
        (
            {"cam__camParameters__highFrequencyContainer": {"rsuContainerHighFrequency": {}}},
            "cam__camParameters__highFrequencyContainer__basicVehicleContainerHighFrequency",
            "missing",
        ),
        ({f"{HF}__speed": {"speedValue": 12000}}, "speed", "schema"),  # 120 m/s: beyond V2xPosition's range
    ],
)
def test_bad_cams_name_the_field(edits: dict[str, Any], field: str, reason: str) -> None:
    with pytest.raises(LineError) as info:
        cam_to_v2x(_cam(**edits), NEW_YEAR_2026_NS)
    assert (info.value.field, info.value.reason) == (field.replace("__", "."), reason), str(info.value)


def test_unavailable_optional_fields_are_left_out() -> None:
    message = cam_to_v2x(
        _cam(
            **{
                f"{HF}__vehicleLength": {"vehicleLengthValue": 1023},
                f"{HF}__vehicleWidth": 62,
                f"{HF}__heading": {"headingValue": 905, "headingConfidence": 127},
                f"{HF}__speed": {"speedValue": 1389},
                f"{POSITION}__positionConfidenceEllipse": None,
            }
        ),
        NEW_YEAR_2026_NS,
    )
    assert (message.length, message.width, message.accuracies) == (None, None, None)


def test_detector_lines_in_every_spelling_become_one_frame() -> None:
    line = {
        "stamp_ns": NEW_YEAR_2026_NS,
        "detections": [
            {"x1": 10.0, "y1": 20.0, "x2": 110.0, "y2": 80.0, "cls": 4, "score": 0.9},
            {"name": "car", "class": 2, "confidence": 0.8, "box": {"x1": 1, "y1": 2, "x2": 3, "y2": 4}},
            {"xyxy": [5.5, 6.0, 7.5, 8.0], "cls": 7, "conf": 0.7},
            {"bbox": [100.0, 200.0, 50.0, 25.0], "category_id": 3, "score": 0.6},
        ],
    }
    frame = yolo_to_frame(line, "west")
    assert (frame.camera_id, frame.stamp_ns) == ("west", NEW_YEAR_2026_NS)
    assert [(b.x1, b.y1, b.x2, b.y2, b.cls, b.score) for b in frame.boxes] == [
        (10.0, 20.0, 110.0, 80.0, 4, 0.9),
        (1.0, 2.0, 3.0, 4.0, "car", 0.8),  # the name wins over the id
        (5.5, 6.0, 7.5, 8.0, 7, 0.7),
        (100.0, 200.0, 150.0, 225.0, 3, 0.6),
    ]
    assert yolo_to_frame({"stamp_ns": NEW_YEAR_2026_NS, "boxes": []}, "west").boxes == []


@pytest.mark.parametrize(
    ("line", "field"),
    [
        ({"boxes": []}, "stamp_ns"),
        ({"stamp_ns": 1_767_225_600, "boxes": []}, "stamp_ns"),  # seconds, not ns
        ({"stamp_ns": NEW_YEAR_2026_NS}, "boxes"),
        ({"stamp_ns": NEW_YEAR_2026_NS, "boxes": [{"x1": 5, "y1": 0, "x2": 1, "y2": 4}]}, "boxes.0"),
        ({"stamp_ns": NEW_YEAR_2026_NS, "boxes": [{"xyxy": [1, 2, 3]}]}, "boxes.0.xyxy"),
        ({"stamp_ns": NEW_YEAR_2026_NS, "boxes": [{"box": {"x1": 1}}]}, "boxes.0.box.y1"),
        (
            {"stamp_ns": NEW_YEAR_2026_NS, "boxes": [{"x1": 1, "y1": 2, "x2": 3, "y2": 4, "cls": "4x4!"}]},
            "boxes.0.cls",
        ),
        ({"stamp_ns": NEW_YEAR_2026_NS, "boxes": [], "camera_id": "east"}, "camera_id"),
    ],
)
def test_bad_detector_lines_name_the_field(line: dict[str, Any], field: str) -> None:
    with pytest.raises(LineError) as info:
        yolo_to_frame(line, "west")
    assert info.value.field == field, str(info.value)


def test_bad_lines_are_counted_named_and_skipped(caplog: pytest.LogCaptureFixture) -> None:
    published: list[tuple[str, bytes]] = []
    lines = [
        json.dumps(_cam()),
        "{not json",
        "",
        json.dumps(_cam(**{f"{HF}__speed": {"speedValue": 16383}})),
        json.dumps(_cam(**{"cam__generationDeltaTime": NEW_YEAR_2026_DELTA_MS + 100})),
    ]
    caplog.set_level(logging.WARNING, logger="daemon.ingest")
    clock = _FixedClock(NEW_YEAR_2026_NS)
    report = run_bridge("cam", lines, cam_converter(), lambda k, p: published.append((k, p)), clock)
    assert (report.lines, report.published, report.rejected) == (4, 2, {"json": 1, "unavailable": 1})
    assert report.summary("cam") == "bridge cam: 4 line(s), 2 published, 2 rejected (json 1, unavailable 1)"
    warnings = [r.getMessage() for r in caplog.records]
    assert any("line 2: (root): not JSON" in w for w in warnings)
    assert any(
        f"line 4: {HF.replace('__', '.')}.speed.speedValue: 16383 means 'unavailable'" in w for w in warnings
    )
    assert [key for key, _ in published] == ["v2x/cam/4242"] * 2
    assert [json.loads(p)["stamp_ns"] for _, p in published] == [
        NEW_YEAR_2026_NS,
        NEW_YEAR_2026_NS + 100 * MS,
    ]


class _FixedClock:
    def __init__(self, now_ns: int) -> None:
        self.now = now_ns

    def now_ns(self) -> int:
        return self.now


def _config(tmp_path: Path, port: int) -> DaemonConfig:
    return DaemonConfig(
        rsu_id="r1",
        zenoh=ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]),
        cameras=[
            CameraConfig(
                camera_id="west",
                intrinsics=CameraIntrinsics(width=1920, height=1080, fx=1800, fy=1800, cx=960, cy=540),
            )
        ],
        vehicles=[
            CalibrationVehicle(
                station_id=4242,
                profile=VehicleProfile(length=4.8, width=1.9, height=1.5, imu_offset=(1.5, 0.95, 0.3)),
            )
        ],
        storage={"state_dir": tmp_path / "state"},  # type: ignore[arg-type]
    )


def test_both_bridges_feed_a_daemon_over_zenoh(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    # Ten CAMs 100 ms apart, driving north at 13.89 m/s, stamped around now (the bridge uses our clock).
    now_ns = time.time_ns()
    start_ms = (now_ns - 1_072_915_200_000_000_000) // MS + 5000 - 2000
    cams = [
        _cam(
            **{
                "cam__generationDeltaTime": (start_ms + 100 * i) % 65536,
                f"{POSITION}__latitude": 483981487 + 125 * i,
            }
        )
        for i in range(10)
    ]
    cam_file = tmp_path / "cams.jsonl"
    cam_file.write_text("\n".join([*map(json.dumps, cams[:5]), "{broken", *map(json.dumps, cams[5:])]) + "\n")
    frames = [
        {
            "stamp_ns": now_ns - 2_000_000_000 + i * 100_000_000,
            "boxes": [{"x1": 10 + i, "y1": 20, "x2": 50, "y2": 60, "cls": "car"}],
        }
        for i in range(6)
    ]
    yolo_file = tmp_path / "boxes.jsonl"
    lines = [json.dumps(f) for f in frames]
    lines.insert(3, json.dumps({"stamp_ns": now_ns, "boxes": [{"x1": 5, "y1": 1, "x2": 1, "y2": 4}]}))
    yolo_file.write_text("\n".join(lines) + "\n")

    daemon = Daemon(_config(tmp_path, port))
    client: zenoh.Session | None = None
    try:
        daemon.start()
        assert main(["bridge", "cam", "--input", str(cam_file), "--connect", endpoint]) == 0
        assert "bridge cam: 11 line(s), 10 published, 1 rejected (json 1)" in capsys.readouterr().err
        code = main(
            [
                "bridge",
                "yolo",
                "--rsu",
                "r1",
                "--camera",
                "west",
                "--input",
                str(yolo_file),
                "--connect",
                endpoint,
            ]
        )
        assert code == 0
        assert "bridge yolo: 7 line(s), 6 published, 1 rejected (schema 1)" in capsys.readouterr().err
        client = zenoh.open(client_config([endpoint]))

        def counters() -> dict[str, int]:
            assert client is not None
            replies = query(client, "rsu/r1/health", 2.0)
            return decode_json(Health, replies[0][1]).counters if replies else {}

        wait_until(
            lambda: counters().get("v2x.accepted") == 10 and counters().get("detections.accepted") == 6
        )
    finally:
        if client is not None:
            client.close()  # type: ignore[no-untyped-call]
        daemon.stop()
    files = [f.path for f in list_recordings(tmp_path / "state" / "recordings", "r1")]
    window = read_window(files, "r1", "west", {4242}, 0, 2**62)
    assert [f.stamp_ns for f in window.detections] == [f["stamp_ns"] for f in frames]
    assert [f.boxes[0].cls for f in window.detections] == ["car"] * 6
    assert len(window.v2x) == 10
    steps = [b.stamp_ns - a.stamp_ns for a, b in zip(window.v2x, window.v2x[1:], strict=False)]
    assert steps == [100 * MS] * 9
    assert [round(m.lat * 1e7) for m in window.v2x] == [483981487 + 125 * i for i in range(10)]


def test_bridge_bad_options_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bridge", "cam", "--input", str(tmp_path / "absent.jsonl")]) == 2
    assert "absent.jsonl" in capsys.readouterr().err
    assert main(["bridge", "yolo", "--rsu", "r/1", "--camera", "west"]) == 2
    assert "--rsu" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main(["bridge", "yolo", "--camera", "west"])
    assert info.value.code == 2


def test_report_starts_empty() -> None:
    assert BridgeReport().summary("yolo") == "bridge yolo: 0 line(s), 0 published, 0 rejected"
    assert yolo_converter("r1", "west")({"stamp_ns": NEW_YEAR_2026_NS, "boxes": []}, 0)[0] == (
        "rsu/r1/camera/west/detections"
    )
