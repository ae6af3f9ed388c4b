"""daemon.ingest: every rejection reason (counted, warned naming the field, the next good message decoded),
rate-limited warnings, key routing, the UTM frame, and V2X plausibility on simulated calibration drives."""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass
from typing import Any

import pytest

from daemon.ingest import (
    MAX_ROUTES,
    REANCHOR_AFTER,
    Counters,
    Decoder,
    DetectionsIn,
    Inbound,
    RejectLog,
    V2xIn,
)
from pipeline.frames import UtmFrame, pose_from_v2x
from schemas.common import Box
from schemas.config import DaemonConfig
from schemas.messages import DetectionFrame, V2xPosition
from sim.simulate import SimulationResult, simulate

T0 = 1_700_000_000_000_000_000
STATION = 4242  # the simulator's calibration vehicle
OTHER_STATION = 77
LAT0, LON0 = 48.4, 9.9  # UTM zone 32 (EPSG:32632)
M_PER_DEG_LAT = 111_200.0  # near 48 deg N; 0.1 % off is far below every threshold used here
DET_KEY = "rsu/r1/camera/c1/detections"
INTRINSICS = {"width": 1920, "height": 1080, "fx": 1000.0, "fy": 1000.0, "cx": 960.0, "cy": 540.0}
PROFILE = {"length": 4.8, "width": 1.85, "height": 1.5, "imu_offset": [1.3, 0.925, 0.35]}


@dataclass
class FakeClock:
    t_ns: int = T0

    def now_ns(self) -> int:
        return self.t_ns

    def advance_s(self, seconds: float) -> None:
        self.t_ns += int(seconds * 1e9)


def make_config(
    stations: tuple[int, ...] = (STATION,), crs: str | None = None, **ingest: Any
) -> DaemonConfig:
    return DaemonConfig.model_validate(
        {
            "rsu_id": "r1",
            "crs": crs,
            "cameras": [
                {"camera_id": "c1", "intrinsics": INTRINSICS},
                {"camera_id": "c2", "intrinsics": INTRINSICS},
            ],
            "vehicles": [{"station_id": s, "profile": PROFILE} for s in stations],
            "ingest": ingest,
        }
    )


@dataclass
class Harness:
    decoder: Decoder
    counters: Counters
    clock: FakeClock

    def count(self, name: str) -> int:
        return self.counters.get(name)


def make_harness(config: DaemonConfig | None = None, warn_interval_s: float = 10.0) -> Harness:
    clock = FakeClock()
    counters = Counters()
    rejects = RejectLog(counters, warn_interval_s, clock)
    return Harness(Decoder(config or make_config(), clock, counters, rejects), counters, clock)


def frame_payload(camera_id: str = "c1", stamp_ns: int = T0, n_boxes: int = 3) -> bytes:
    boxes = [Box(x1=10.0 * j, y1=100.0, x2=10.0 * j + 8.0, y2=120.0) for j in range(n_boxes)]
    return DetectionFrame(camera_id=camera_id, stamp_ns=stamp_ns, boxes=boxes).model_dump_json().encode()


def det(payload: bytes, key: str = DET_KEY, received_ns: int = T0) -> Inbound:
    return Inbound(key, payload, received_ns)


def v2x_message(
    i: int, station_id: int = STATION, hz: float = 10.0, speed: float = 10.0, **extra: Any
) -> V2xPosition:
    """Fix i of a vehicle driving due north at `speed` m/s, reporting at `hz`."""
    fields: dict[str, Any] = {
        "station_id": station_id,
        "stamp_ns": T0 + round(i * 1e9 / hz),
        "lat": LAT0 + i * speed / hz / M_PER_DEG_LAT,
        "lon": LON0,
        "alt": 500.0,
        "heading_deg": 0.0,
        "speed": speed,
    }
    fields.update(extra)
    return V2xPosition.model_validate(fields)


def v2x(message: V2xPosition | bytes, station_id: int = STATION, received_ns: int = T0) -> Inbound:
    payload = message if isinstance(message, bytes) else message.model_dump_json().encode()
    return Inbound(f"v2x/cam/{station_id}", payload, received_ns)


def warnings_text(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [
        r.getMessage() for r in caplog.records if r.name == "daemon.ingest" and r.levelno == logging.WARNING
    ]


# ------------------------------------------------------------------------------------------- detections


def test_good_detection_is_decoded_with_its_raw_payload() -> None:
    h = make_harness()
    payload = frame_payload(n_boxes=5)
    item = h.decoder.decode(det(payload, received_ns=T0 + 7))
    assert isinstance(item, DetectionsIn)
    assert item.camera_id == "c1"
    assert item.stamp_ns == T0 and item.boxes == 5
    assert item.payload is payload and item.received_ns == T0 + 7
    assert h.counters.snapshot() == {
        "detections.received": 1,
        "detections.accepted": 1,
        "v2x.received": 0,
        "v2x.accepted": 0,
        "v2x.other_station": 0,
        "unknown_key.rejected": 0,
    }


def _bad_box_payload() -> bytes:
    data = json.loads(frame_payload(n_boxes=5))
    data["boxes"][3]["x1"], data["boxes"][3]["x2"] = 12.0, 10.0
    return json.dumps(data).encode()


def _edit(payload: bytes, **changes: Any) -> bytes:
    data = json.loads(payload)
    data.update(changes)
    return json.dumps(data).encode()


DETECTION_CASES: list[tuple[str, Inbound, str, str]] = [
    # (case, inbound, reason, text the warning must contain: the key and the field)
    ("oversized", det(b"{" * 1025), "oversized", f"{DET_KEY}: payload: 1025 bytes"),
    ("not_json", det(b"not json"), "json", f"{DET_KEY}: (root): Invalid JSON"),
    ("not_utf8", det(b'{"camera_id": "\xff\xfe"}'), "json", DET_KEY),
    (
        "box_order",
        det(_bad_box_payload()),
        "json",
        f"{DET_KEY}: boxes.3.x2: x2 = 10.0 must be greater than x1 = 12.0",
    ),
    ("string_stamp", det(_edit(frame_payload(), stamp_ns=str(T0))), "json", f"{DET_KEY}: stamp_ns:"),
    (
        "stamp_in_seconds",
        det(_edit(frame_payload(), stamp_ns=1_700_000_000)),
        "json",
        "stamp_ns: Input should be",
    ),
    ("extra_field", det(_edit(frame_payload(), color="red")), "json", "color: Extra inputs"),
    ("missing_field", det(b'{"camera_id": "c1", "boxes": []}'), "json", "stamp_ns: Field required"),
    ("nan_score", det(frame_payload().replace(b'"score":1.0', b'"score":NaN', 1)), "json", "boxes.0.score"),
    (
        "bad_class_name",
        det(frame_payload().replace(b'"cls":4', b'"cls":"4x4!"', 1)),
        "json",
        f"{DET_KEY}: boxes.0.cls: class name '4x4!' must be 1-32 letters",
    ),
    ("unknown_camera", det(frame_payload("c9"), key="rsu/r1/camera/c9/detections"), "unknown_camera", "'c9'"),
    ("camera_mismatch", det(frame_payload("c2")), "camera_mismatch", "camera_id = 'c2'"),
]


@pytest.mark.parametrize(
    ("inbound", "reason", "expected"), [c[1:] for c in DETECTION_CASES], ids=[c[0] for c in DETECTION_CASES]
)
def test_bad_detection_is_counted_warned_and_the_next_good_one_decoded(
    caplog: pytest.LogCaptureFixture, inbound: Inbound, reason: str, expected: str
) -> None:
    h = make_harness(make_config(max_payload_bytes=1024))
    caplog.set_level(logging.WARNING, logger="daemon.ingest")
    assert h.decoder.decode(inbound) is None
    assert h.count(f"detections.rejected.{reason}") == 1
    assert h.count("detections.received") == 1 and h.count("detections.accepted") == 0
    (warning,) = warnings_text(caplog)
    assert f"rejected ({reason})" in warning and expected in warning
    good = h.decoder.decode(det(frame_payload(stamp_ns=T0 + 1)))
    assert isinstance(good, DetectionsIn)
    assert h.count("detections.received") == 2 and h.count("detections.accepted") == 1


def test_class_names_and_ids_are_accepted_as_sent() -> None:
    h = make_harness()
    payload = (
        frame_payload()
        .replace(b'"cls":4', b'"cls":"car"', 1)
        .replace(b'"cls":4', b'"cls":"traffic light"', 1)
    )
    item = h.decoder.decode(det(payload))
    assert isinstance(item, DetectionsIn) and item.boxes == 3
    assert item.payload == payload  # recorded as received
    assert [box["cls"] for box in json.loads(item.payload)["boxes"]] == ["car", "traffic light", 4]


def test_size_is_checked_before_parsing() -> None:
    h = make_harness(make_config(max_payload_bytes=1024))
    big_but_valid = frame_payload(n_boxes=40)
    assert len(big_but_valid) > 1024
    assert h.decoder.decode(det(big_but_valid)) is None
    assert h.count("detections.rejected.oversized") == 1 and h.count("detections.rejected.json") == 0


def test_detection_duplicates_and_out_of_order_per_camera(caplog: pytest.LogCaptureFixture) -> None:
    h = make_harness()
    caplog.set_level(logging.WARNING, logger="daemon.ingest")
    assert h.decoder.decode(det(frame_payload("c1", T0 + 10))) is not None
    assert h.decoder.decode(det(frame_payload("c1", T0 + 10))) is None
    assert h.decoder.decode(det(frame_payload("c1", T0 + 5))) is None
    assert h.count("detections.rejected.duplicate") == 1
    assert h.count("detections.rejected.out_of_order") == 1
    duplicate, older = warnings_text(caplog)
    assert "stamp_ns = 1700000000000000010 equals the last accepted stamp of camera 'c1'" in duplicate
    assert "stamp_ns = 1700000000000000005 is" in older and "older" in older
    # Each camera has its own order; c1 goes on from its last accepted stamp.
    c2_key = "rsu/r1/camera/c2/detections"
    assert h.decoder.decode(det(frame_payload("c2", T0 + 1), key=c2_key)) is not None
    assert h.decoder.decode(det(frame_payload("c1", T0 + 11))) is not None
    assert h.count("detections.accepted") == 3 and h.count("detections.received") == 5


def test_detection_clock_skew() -> None:
    h = make_harness(make_config(max_clock_skew_s=2.0))
    assert h.decoder.decode(det(frame_payload(stamp_ns=T0), received_ns=T0 + 3_000_000_000)) is None
    assert h.decoder.decode(det(frame_payload(stamp_ns=T0 + 5_000_000_000), received_ns=T0)) is None
    assert h.count("detections.rejected.clock_skew") == 2
    assert h.decoder.decode(det(frame_payload(stamp_ns=T0), received_ns=T0 + 1_900_000_000)) is not None
    # Off by default (replays carry old stamps).
    h2 = make_harness()
    assert h2.decoder.decode(det(frame_payload(stamp_ns=T0), received_ns=T0 + 10**15)) is not None


# ------------------------------------------------------------------------------------------------ keys


@pytest.mark.parametrize(
    "key",
    [
        "rsu/other/camera/c1/detections",
        "rsu/r1/camera/c1/calibration",
        "rsu/r1/camera//detections",
        "rsu/r1/camera/c1/detections/extra",
        "v2x/cam/abc",
        "v2x/cam/007",
        "v2x/cam/-1",
        "v2x/cam/+5",
        "v2x/cam/4294967296",
        "v2x/cam/\u0661\u0662",  # Arabic-Indic digits: str.isdigit() says yes, int() too
        "v2x/cam/1/x",
        "v2x/cam/",
        "",
        "x" * 5000,
    ],
)
def test_unknown_keys_are_counted_and_warned(caplog: pytest.LogCaptureFixture, key: str) -> None:
    h = make_harness()
    caplog.set_level(logging.WARNING, logger="daemon.ingest")
    assert h.decoder.decode(Inbound(key, frame_payload(), T0)) is None
    assert h.count("unknown_key.rejected") == 1
    assert h.count("detections.received") == 0 and h.count("v2x.received") == 0
    (warning,) = warnings_text(caplog)
    assert "unknown_key rejected" in warning and "neither rsu/r1/camera/<camera_id>/detections" in warning
    assert len(warning) < 400  # a huge key is quoted shortened
    assert isinstance(h.decoder.decode(det(frame_payload())), DetectionsIn)


def test_key_cache_stays_bounded_and_correct() -> None:
    h = make_harness()
    for i in range(MAX_ROUTES + 100):
        h.decoder.decode(Inbound(f"rsu/r1/camera/x{i}/detections", b"{}", T0))
        h.decoder.decode(Inbound(f"noise/{i}", b"{}", T0))
    assert h.count("detections.rejected.unknown_camera") == MAX_ROUTES + 100
    assert h.count("unknown_key.rejected") == MAX_ROUTES + 100
    assert len(h.decoder._routes) <= MAX_ROUTES
    assert isinstance(h.decoder.decode(det(frame_payload())), DetectionsIn)
    assert isinstance(h.decoder.decode(v2x(v2x_message(0, OTHER_STATION), OTHER_STATION)), V2xIn)


# ------------------------------------------------------------------------------------------------- V2X


def test_calibration_vehicle_gets_a_pose_other_stations_none() -> None:
    h = make_harness()
    message = v2x_message(0, heading_deg=30.0, pitch=0.02)
    item = h.decoder.decode(v2x(message))
    assert isinstance(item, V2xIn) and item.station_id == STATION and item.message == message
    assert h.decoder.frame is not None and h.decoder.frame.crs == "EPSG:32632"
    assert item.utm == pytest.approx(_utm_of(message, "EPSG:32632"), abs=1e-6)
    other = h.decoder.decode(v2x(v2x_message(0, OTHER_STATION), OTHER_STATION))
    assert isinstance(other, V2xIn) and other.utm is None and other.station_id == OTHER_STATION
    assert h.count("v2x.received") == 2 and h.count("v2x.accepted") == 2 and h.count("v2x.other_station") == 1


def test_other_stations_get_schema_checks_only() -> None:
    h = make_harness()
    fast = v2x_message(0, OTHER_STATION, speed=95.0)  # beyond max_speed_mps, fine for other traffic
    for inbound in (
        v2x(fast, OTHER_STATION),
        v2x(fast, OTHER_STATION),
        v2x(v2x_message(-5, OTHER_STATION), 77),
    ):
        item = h.decoder.decode(inbound)
        assert isinstance(item, V2xIn) and item.utm is None
    assert h.count("v2x.other_station") == 3 and h.count("v2x.accepted") == 3
    assert h.decoder.decode(v2x(_edit(fast.model_dump_json().encode(), lat=91.0), OTHER_STATION)) is None
    assert h.count("v2x.rejected.json") == 1


V2X_GOOD = v2x_message(0).model_dump_json().encode()
V2X_CASES: list[tuple[str, Inbound, str, str]] = [
    ("oversized", v2x(b" " * 1025), "oversized", "v2x/cam/4242: payload: 1025 bytes"),
    ("not_json", v2x(b"\x00\x01"), "json", "v2x/cam/4242: (root)"),
    (
        "heading_range",
        v2x(_edit(V2X_GOOD, heading_deg=360.0)),
        "json",
        "v2x/cam/4242: heading_deg: Input should be less than 360",
    ),
    ("bool_speed", v2x(_edit(V2X_GOOD, speed=True)), "json", "speed: Input should be a valid number"),
    (
        "accuracies",
        v2x(_edit(V2X_GOOD, accuracies={"horizontal_m": -1.0})),
        "json",
        "accuracies.horizontal_m",
    ),
    ("station_mismatch", v2x(v2x_message(0, 4343), STATION), "station_mismatch", "station_id = 4343"),
    (
        "speed_limit",
        v2x(v2x_message(0, speed=80.0)),
        "implausible",
        "speed = 80.0 m/s exceeds ingest.max_speed_mps = 70.0",
    ),
    ("polar", v2x(v2x_message(0, lat=89.0)), "implausible", "lat/lon: lat = 89.0"),
]


@pytest.mark.parametrize(
    ("inbound", "reason", "expected"), [c[1:] for c in V2X_CASES], ids=[c[0] for c in V2X_CASES]
)
def test_bad_v2x_is_counted_warned_and_the_next_good_one_decoded(
    caplog: pytest.LogCaptureFixture, inbound: Inbound, reason: str, expected: str
) -> None:
    h = make_harness(make_config(max_payload_bytes=1024))
    caplog.set_level(logging.WARNING, logger="daemon.ingest")
    assert h.decoder.decode(inbound) is None
    assert h.count(f"v2x.rejected.{reason}") == 1
    assert h.count("v2x.received") == 1 and h.count("v2x.accepted") == 0
    (warning,) = warnings_text(caplog)
    assert f"v2x rejected ({reason})" in warning and expected in warning
    good = h.decoder.decode(v2x(v2x_message(1)))
    assert isinstance(good, V2xIn) and good.utm is not None
    assert h.count("v2x.received") == 2 and h.count("v2x.accepted") == 1


def test_v2x_duplicates_and_out_of_order_per_station() -> None:
    h = make_harness(make_config(stations=(STATION, 4343)))
    assert h.decoder.decode(v2x(v2x_message(5))) is not None
    assert h.decoder.decode(v2x(v2x_message(5))) is None
    assert h.decoder.decode(v2x(v2x_message(4))) is None
    assert h.count("v2x.rejected.duplicate") == 1 and h.count("v2x.rejected.out_of_order") == 1
    # A second calibration vehicle has its own order.
    assert h.decoder.decode(v2x(v2x_message(1, 4343), 4343)) is not None
    assert h.decoder.decode(v2x(v2x_message(6))) is not None
    assert h.count("v2x.accepted") == 3 and h.count("v2x.received") == 5


def test_v2x_clock_skew() -> None:
    h = make_harness(make_config(max_clock_skew_s=1.0))
    assert h.decoder.decode(v2x(v2x_message(0), received_ns=T0 - 1_500_000_000)) is None
    assert (
        h.decoder.decode(v2x(v2x_message(0, OTHER_STATION), OTHER_STATION, received_ns=T0 + 10**10)) is None
    )
    assert h.count("v2x.rejected.clock_skew") == 2
    assert h.decoder.decode(v2x(v2x_message(0), received_ns=T0 + 900_000_000)) is not None


def test_received_equals_accepted_plus_rejected() -> None:
    h = make_harness(make_config(max_payload_bytes=1024))
    inbounds = [c[1] for c in DETECTION_CASES + V2X_CASES] + [det(frame_payload(stamp_ns=T0 + 9))]
    inbounds += [v2x(v2x_message(i)) for i in range(3)] + [v2x(v2x_message(0, OTHER_STATION), OTHER_STATION)]
    for inbound in inbounds:
        h.decoder.decode(inbound)
    counts = h.counters.snapshot()
    for source in ("detections", "v2x"):
        rejected = sum(n for name, n in counts.items() if name.startswith(f"{source}.rejected."))
        assert counts[f"{source}.received"] == counts[f"{source}.accepted"] + rejected > 0


# ----------------------------------------------------------------------------------------------- frame


def test_frame_from_config_crs_camera_position_or_first_v2x() -> None:
    assert make_harness(make_config(crs="EPSG:32633")).decoder.frame == UtmFrame("EPSG:32633")
    data = make_config().model_dump(mode="json")
    data["cameras"][1]["position"] = {"lat": 51.05, "lon": 13.74}  # Dresden, zone 33
    assert make_harness(DaemonConfig.model_validate(data)).decoder.frame == UtmFrame("EPSG:32633")
    h = make_harness()
    assert h.decoder.frame is None
    h.decoder.decode(v2x(v2x_message(0, OTHER_STATION), OTHER_STATION))
    assert h.decoder.frame is None  # other traffic needs no poses
    h.decoder.decode(v2x(v2x_message(0)))
    assert h.decoder.frame == UtmFrame("EPSG:32632")


def test_configured_frame_is_used_for_poses() -> None:
    h = make_harness(make_config(crs="EPSG:32633"))  # next zone east: valid, just far from its meridian
    message = v2x_message(0, heading_deg=45.0)
    item = h.decoder.decode(v2x(message))
    assert isinstance(item, V2xIn)
    assert item.utm == pytest.approx(_utm_of(message, "EPSG:32633"), abs=1e-6)


# ---------------------------------------------------------------------------------------- plausibility


@pytest.fixture(scope="module")
def sil_west() -> SimulationResult:
    return simulate("sil-west", 0, ideal=True)  # 50 Hz V2X (the IMU poses)


@pytest.fixture(scope="module")
def v2x_10hz() -> SimulationResult:
    return simulate("v2x-10hz", 0, ideal=True)


@pytest.mark.parametrize("preset", ["sil-west", "v2x-10hz"])
def test_simulated_calibration_drives_are_accepted_completely(
    preset: str, request: pytest.FixtureRequest, caplog: pytest.LogCaptureFixture
) -> None:
    sim: SimulationResult = request.getfixturevalue(preset.replace("-", "_"))
    h = make_harness(make_config(stations=(sim.station_id,)))
    caplog.set_level(logging.WARNING, logger="daemon.ingest")
    poses = []
    for message in sim.v2x:
        item = h.decoder.decode(v2x(message, sim.station_id, received_ns=message.stamp_ns))
        assert isinstance(item, V2xIn) and item.utm is not None
        poses.append(item.utm)
    assert h.count("v2x.accepted") == len(sim.v2x) > 1000
    assert warnings_text(caplog) == []
    assert h.decoder.frame is not None and h.decoder.frame.crs == sim.origin.crs
    assert poses[0] == pytest.approx(_utm_of(sim.v2x[0], sim.origin.crs), abs=1e-6)


def _moving_index(sim: SimulationResult, start: int, min_speed_mps: float = 8.0) -> int:
    """First fix from `start` on where the vehicle drives steadily (so heading checks apply)."""
    return next(i for i in range(start, len(sim.v2x)) if sim.v2x[i].speed > min_speed_mps)


def _feed_with_fault(sim: SimulationResult, h: Harness, index: int, fault: V2xPosition) -> list[bool]:
    """Feed the drive up to `index`, then `fault` (in place of fix `index`), then 20 more real fixes."""
    accepted = []
    for message in [*sim.v2x[:index], fault, *sim.v2x[index + 1 : index + 21]]:
        accepted.append(h.decoder.decode(v2x(message, sim.station_id)) is not None)
    return accepted[index:]


def test_a_50_m_jump_is_rejected_and_the_track_goes_on(
    sil_west: SimulationResult, caplog: pytest.LogCaptureFixture
) -> None:
    h = make_harness(make_config(stations=(sil_west.station_id,)))
    caplog.set_level(logging.WARNING, logger="daemon.ingest")
    i = _moving_index(sil_west, 1000)
    fault = sil_west.v2x[i].model_copy(update={"lat": sil_west.v2x[i].lat + 50.0 / M_PER_DEG_LAT})
    assert _feed_with_fault(sil_west, h, i, fault) == [False] + [True] * 20
    assert h.count("v2x.rejected.implausible") == 1
    (warning,) = warnings_text(caplog)
    assert f"v2x/cam/{sil_west.station_id}: lat/lon: moved 5" in warning and "max_speed_mps = 70.0" in warning


def test_a_200_kmh_speed_is_rejected(sil_west: SimulationResult, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="daemon.ingest")
    i = _moving_index(sil_west, 2000)
    fault = sil_west.v2x[i].model_copy(update={"speed": 200.0 / 3.6})
    # Default limits (max_speed_mps 70 m/s = 252 km/h): ~45 m/s more within 20 ms is the acceleration check.
    h = make_harness(make_config(stations=(sil_west.station_id,)))
    assert _feed_with_fault(sil_west, h, i, fault) == [False] + [True] * 20
    assert (
        "speed = 55.6 m/s after" in warnings_text(caplog)[-1]
        and "max_accel_mps2 = 15.0" in warnings_text(caplog)[-1]
    )
    # With a road-appropriate max_speed_mps the reported speed alone is refused.
    h = make_harness(make_config(stations=(sil_west.station_id,), max_speed_mps=45.0))
    assert _feed_with_fault(sil_west, h, i, fault) == [False] + [True] * 20
    assert "speed = 55.6 m/s exceeds ingest.max_speed_mps = 45.0" in warnings_text(caplog)[-1]


def test_a_90_deg_heading_flip_in_100_ms_is_rejected(
    v2x_10hz: SimulationResult, caplog: pytest.LogCaptureFixture
) -> None:
    sim = v2x_10hz
    h = make_harness(make_config(stations=(sim.station_id,)))
    caplog.set_level(logging.WARNING, logger="daemon.ingest")
    i = _moving_index(sim, 300)
    assert 0.08 < (sim.v2x[i].stamp_ns - sim.v2x[i - 1].stamp_ns) / 1e9 < 0.12
    fault = sim.v2x[i].model_copy(update={"heading_deg": (sim.v2x[i].heading_deg + 90.0) % 360.0})
    assert _feed_with_fault(sim, h, i, fault) == [False] + [True] * 20
    assert (
        "heading_deg = " in warnings_text(caplog)[-1]
        and "max_yaw_rate_deg_s = 120.0" in warnings_text(caplog)[-1]
    )


def test_thresholds_come_from_config() -> None:
    slow = make_harness(make_config(max_speed_mps=5.0, max_position_error_m=0.5))
    fast = make_harness(make_config())
    for h in (slow, fast):
        h.decoder.decode(v2x(v2x_message(0, speed=4.0)))
    # 1.5 s later, 30 m north: 20 m/s, reporting 4 m/s
    jump = v2x_message(15, speed=4.0, lat=LAT0 + 30.0 / M_PER_DEG_LAT)
    assert slow.decoder.decode(v2x(jump)) is None
    assert fast.decoder.decode(v2x(jump)) is not None
    gentle = make_harness(make_config(max_accel_mps2=1.0))
    gentle.decoder.decode(v2x(v2x_message(0, speed=10.0)))
    assert gentle.decoder.decode(v2x(v2x_message(1, speed=12.0))) is None  # 2 m/s in 0.1 s: 20 m/s^2
    assert gentle.decoder.decode(v2x(v2x_message(2, speed=10.05))) is not None


def test_heading_is_not_checked_when_slow() -> None:
    h = make_harness()
    h.decoder.decode(v2x(v2x_message(0, speed=1.0)))
    assert h.decoder.decode(v2x(v2x_message(1, speed=1.0, heading_deg=180.0))) is not None
    assert h.decoder.decode(v2x(v2x_message(2, speed=1.0, heading_deg=359.0))) is not None


def test_heading_wraps_around_north() -> None:
    h = make_harness()
    h.decoder.decode(v2x(v2x_message(0, heading_deg=359.0)))
    assert h.decoder.decode(v2x(v2x_message(1, heading_deg=1.0))) is not None


def test_a_bad_first_fix_re_anchors_after_consistent_fixes(caplog: pytest.LogCaptureFixture) -> None:
    h = make_harness()
    caplog.set_level(logging.WARNING, logger="daemon.ingest")
    bad_first = v2x_message(0, lat=LAT0 + 1000.0 / M_PER_DEG_LAT)  # 1 km off
    assert h.decoder.decode(v2x(bad_first)) is not None  # nothing to compare the first fix with
    results = [h.decoder.decode(v2x(v2x_message(i))) is not None for i in range(1, 10)]
    assert results == [False] * (REANCHOR_AFTER - 1) + [True] * (10 - REANCHOR_AFTER)
    assert h.count("v2x.rejected.implausible") == REANCHOR_AFTER - 1
    assert h.count("v2x.reanchored") == 1
    assert any("v2x re-anchored" in w for w in warnings_text(caplog))


def test_interleaved_outliers_never_re_anchor() -> None:
    h = make_harness()
    h.decoder.decode(v2x(v2x_message(0)))
    results = []
    for i in range(1, 40, 2):
        outlier = v2x_message(i, lat=LAT0 + 500.0 / M_PER_DEG_LAT + i / M_PER_DEG_LAT)
        results.append(
            (h.decoder.decode(v2x(outlier)) is None, h.decoder.decode(v2x(v2x_message(i + 1))) is not None)
        )
    assert all(rejected and accepted for rejected, accepted in results)
    assert h.count("v2x.reanchored") == 0


def test_inconsistent_outliers_do_not_re_anchor() -> None:
    h = make_harness()
    h.decoder.decode(v2x(v2x_message(0)))
    # Scattered fixes: each implausible, and none agrees with the one before.
    for i in range(1, 20):
        offset_m = 300.0 * (1 + i % 2) * (-1) ** i
        assert h.decoder.decode(v2x(v2x_message(i, lat=LAT0 + offset_m / M_PER_DEG_LAT))) is None
    assert h.count("v2x.reanchored") == 0
    assert h.decoder.decode(v2x(v2x_message(20))) is not None


# --------------------------------------------------------------------------------------------- warnings


def test_warnings_are_rate_limited_per_source_and_field(caplog: pytest.LogCaptureFixture) -> None:
    h = make_harness(warn_interval_s=10.0)
    caplog.set_level(logging.WARNING, logger="daemon.ingest")
    for _ in range(100):
        assert h.decoder.decode(det(b"not json")) is None
    assert h.count("detections.rejected.json") == 100
    assert len(warnings_text(caplog)) == 1
    # Another field is news: logged at once.
    h.decoder.decode(det(_bad_box_payload()))
    h.decoder.decode(det(_edit(_bad_box_payload(), stamp_ns=T0 + 1)))  # same field (boxes.*.x2), other values
    assert len(warnings_text(caplog)) == 2 and "boxes.3.x2" in warnings_text(caplog)[1]
    # After the interval the next rejection brings the summary with the latest message.
    h.clock.advance_s(9.9)
    h.decoder.decode(det(b"still not json"))
    assert len(warnings_text(caplog)) == 2
    h.clock.advance_s(0.2)
    h.decoder.decode(det(b"[1, 2"))
    summary = warnings_text(caplog)[2]
    assert "detections rejected (json) [(root)]: 101 more in the last 10.1 s" in summary
    assert f"latest: {DET_KEY}: (root): Invalid JSON" in summary
    assert h.count("detections.rejected.json") == 104


def test_tick_reports_a_burst_that_stopped(caplog: pytest.LogCaptureFixture) -> None:
    counters, clock = Counters(), FakeClock()
    rejects = RejectLog(counters, 5.0, clock)
    caplog.set_level(logging.WARNING, logger="daemon.ingest")
    for i in range(7):
        rejects.reject("v2x", "json", f"v2x/cam/1: speed: bad {i}", "speed")
    rejects.tick()
    assert len(warnings_text(caplog)) == 1
    clock.advance_s(5.0)
    rejects.tick()
    rejects.tick()  # nothing new: no second summary
    first, summary = warnings_text(caplog)
    assert first == "v2x rejected (json): v2x/cam/1: speed: bad 0"
    assert summary == "v2x rejected (json) [speed]: 6 more in the last 5.0 s, latest: v2x/cam/1: speed: bad 6"
    assert counters.snapshot() == {"v2x.rejected.json": 7}


def test_reject_log_bounds_its_state(caplog: pytest.LogCaptureFixture) -> None:
    counters = Counters()
    rejects = RejectLog(counters, 10.0, FakeClock())
    caplog.set_level(logging.WARNING, logger="daemon.ingest")
    for i in range(5000):
        rejects.reject("detections", "json", "x", f"field{i}")
    assert len(rejects._states) <= 1025
    assert len(warnings_text(caplog)) <= 1025
    assert counters.get("detections.rejected.json") == 5000


def test_counters_are_consistent_across_threads() -> None:
    counters = Counters()
    snapshots: list[dict[str, int]] = []

    def work() -> None:
        for _ in range(20_000):
            counters.add("a")
            counters.add("b", 2)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for thread in threads:
        thread.start()
    while any(thread.is_alive() for thread in threads):
        snapshots.append(counters.snapshot())
    for thread in threads:
        thread.join()
    assert counters.snapshot() == {"a": 80_000, "b": 160_000}
    # Each thread adds a before b, so a snapshot can only catch up to one pair per thread half done.
    assert all(0 <= 2 * s.get("a", 0) - s.get("b", 0) <= 2 * len(threads) for s in snapshots)
    copy = counters.snapshot()
    copy["a"] = 0
    assert counters.get("a") == 80_000


def _utm_of(message: V2xPosition, crs: str) -> tuple[float, float]:
    """The position pose_from_v2x gives (vectorised path), to compare with the decoder's scalar one."""
    pose = pose_from_v2x(message, UtmFrame(crs))
    return pose.x, pose.y
