"""Fuzzing daemon.ingest.Decoder.decode: bus detections and V2X payloads, and their keys.

Each example primes a fresh Decoder with one good message per stream, sends one junk message, then the
stream's next good message. Clean rejection means: decode returns None or an accepted item, nothing is
raised, the source's counters move by exactly one message (received = accepted + rejected), every
rejection names a field in its warning, and the next good message is accepted after a rejected one.
"""

from __future__ import annotations

import json
from typing import Any

from fuzzing import dump_json, fuzz_settings, json_values, label, mutated, mutated_bytes, unicode_strings
from hypothesis import given
from hypothesis import strategies as st

from daemon.ingest import Counters, Decoder, DetectionsIn, Inbound, RejectLog, V2xIn
from schemas.config import DaemonConfig

T0 = 1_700_000_000_000_000_000
RSU = "r1"
CAMERA = "c1"
VEHICLE = 4242  # a calibration vehicle: order, UTM and plausibility checks
OTHER = 77  # other traffic: schema and key only
LAT0, LON0 = 48.4, 9.9
INTRINSICS = {"width": 1920, "height": 1080, "fx": 1000.0, "fy": 1000.0, "cx": 960.0, "cy": 540.0}
PROFILE = {"length": 4.8, "width": 1.85, "height": 1.5, "imu_offset": [1.3, 0.925, 0.35]}
DET_KEY = f"rsu/{RSU}/camera/{CAMERA}/detections"
BOX = {"x1": 10.0, "y1": 100.0, "x2": 18.0, "y2": 120.0, "cls": 4, "score": 0.9}


def detection_doc(i: int) -> dict[str, Any]:
    boxes = [{**BOX, "x1": 10.0 + j, "x2": 18.0 + j} for j in range(3)]
    return {"camera_id": CAMERA, "stamp_ns": T0 + i * 100_000_000, "boxes": boxes}


def v2x_doc(i: int, station_id: int = VEHICLE) -> dict[str, Any]:
    """Fix i of a vehicle driving north at 10 m/s, 10 Hz, every optional field set."""
    return {
        "station_id": station_id,
        "stamp_ns": T0 + i * 100_000_000,
        "lat": LAT0 + i * 1.0 / 111_200.0,
        "lon": LON0,
        "alt": 500.0,
        "heading_deg": 0.0,
        "speed": 10.0,
        "length": 4.8,
        "width": 1.85,
        "roll": 0.0,
        "pitch": 0.0,
        "accuracies": {"horizontal_m": 0.02, "vertical_m": 0.04, "heading_deg": 0.3, "speed_mps": 0.1},
    }


CONFIG = DaemonConfig.model_validate(
    {
        "rsu_id": RSU,
        "cameras": [
            {"camera_id": CAMERA, "intrinsics": INTRINSICS},
            {"camera_id": "c2", "intrinsics": INTRINSICS},
        ],
        "vehicles": [{"station_id": VEHICLE, "profile": PROFILE}],
        # A skew limit exercises that check too; the clock below sits at the good messages' stamps.
        "ingest": {"max_clock_skew_s": 3600.0, "max_payload_bytes": 4096},
    }
)
# (key, good message i, the source's counter prefix)
STREAMS = {
    "detections": (DET_KEY, detection_doc, "detections"),
    "vehicle": (f"v2x/cam/{VEHICLE}", v2x_doc, "v2x"),
    "other": (f"v2x/cam/{OTHER}", lambda i: v2x_doc(i, OTHER), "v2x"),
}


class FixedClock:
    def now_ns(self) -> int:
        return T0


class RecordingRejects(RejectLog):
    """RejectLog that also keeps every (source, reason, message, field) it was given."""

    def __init__(self, counters: Counters) -> None:
        super().__init__(counters, 10.0, FixedClock())
        self.seen: list[tuple[str, str, str, str | None]] = []

    def reject(self, source: str, reason_key: str, message: str, field: str | None = None) -> None:
        self.seen.append((source, reason_key, message, field))
        super().reject(source, reason_key, message, field)


def totals(counters: Counters, source: str) -> tuple[int, int, int]:
    """(received, accepted, rejected) of a source."""
    snapshot = counters.snapshot()
    rejected = sum(n for name, n in snapshot.items() if name.startswith(f"{source}.rejected."))
    return snapshot.get(f"{source}.received", 0), snapshot.get(f"{source}.accepted", 0), rejected


def payload(doc: Any) -> bytes:
    return dump_json(doc).encode("utf-8")


def check_one(stream: str, junk_payload: bytes, key: str | None = None) -> None:
    """Prime, send junk (on the stream's key or `key`), then the next good message: see the module doc."""
    good_key, good_doc, _ = STREAMS[stream]
    counters = Counters()
    rejects = RecordingRejects(counters)
    decoder = Decoder(CONFIG, FixedClock(), counters, rejects)
    for name, (k, doc, _) in STREAMS.items():
        assert decoder.decode(Inbound(k, payload(doc(0)), T0)) is not None, name
    key = good_key if key is None else key
    before = {name: totals(counters, name) for name in ("detections", "v2x")}
    unknown_before = counters.get("unknown_key.rejected")
    seen_before = len(rejects.seen)

    result = decoder.decode(Inbound(key, junk_payload, T0))

    after = {name: totals(counters, name) for name in ("detections", "v2x")}
    moved = [name for name in after if after[name] != before[name]]
    new_rejections = rejects.seen[seen_before:]
    if not moved:  # a key that is neither a camera's nor a station's
        assert result is None and counters.get("unknown_key.rejected") == unknown_before + 1
        assert not new_rejections
        label("unknown key rejected")
        return
    (source,) = moved
    received, accepted, rejected = (a - b for a, b in zip(after[source], before[source], strict=True))
    assert received == 1 and accepted + rejected == 1, (source, received, accepted, rejected)
    assert (result is not None) == (accepted == 1)
    assert result is None or isinstance(result, DetectionsIn if source == "detections" else V2xIn)
    if result is not None:
        assert not new_rejections
        label(f"{source} accepted")
        return

    # Rejected: exactly one reason, whose warning names the field it gives.
    assert len(new_rejections) == 1, new_rejections
    _, reason, message, field_name = new_rejections[0]
    label(f"{source} rejected: {reason}")
    assert field_name, (reason, message)
    head = field_name.split(".", 1)[0].split("/", 1)[0]
    assert head in message, (field_name, message)
    # The stream's next good message still arrives.
    follow = decoder.decode(Inbound(good_key, payload(good_doc(1)), T0))
    assert follow is not None, rejects.seen[-1:]


streams = st.sampled_from(sorted(STREAMS))


@fuzz_settings()
@given(stream=streams, raw=st.binary(max_size=400))
def test_arbitrary_bytes_are_rejected_cleanly(stream: str, raw: bytes) -> None:
    check_one(stream, raw)


@fuzz_settings()
@given(stream=streams, doc=json_values)
def test_arbitrary_json_is_rejected_cleanly(stream: str, doc: Any) -> None:
    check_one(stream, payload(doc))


@fuzz_settings()
@given(stream=streams, data=st.data())
def test_structural_mutations_are_rejected_cleanly_or_accepted(stream: str, data: st.DataObject) -> None:
    _, good_doc, _ = STREAMS[stream]
    doc = data.draw(mutated(good_doc(1)), label="doc")
    check_one(stream, payload(doc))


@fuzz_settings()
@given(stream=streams, data=st.data())
def test_byte_mutations_of_good_payloads_are_rejected_cleanly_or_accepted(
    stream: str, data: st.DataObject
) -> None:
    _, good_doc, _ = STREAMS[stream]
    raw = data.draw(mutated_bytes(payload(good_doc(1))), label="raw")
    check_one(stream, raw)


# Well-formed values that a check after the schema must catch: stamps that repeat, go back or lie far
# from our clock, positions that jump, speeds and headings that change too fast, ids that disagree with
# the key. The primed message is stamp T0 at (LAT0, LON0), 10 m/s due north.
plausible_values: dict[str, st.SearchStrategy[Any]] = {
    "stamp_ns": st.sampled_from([T0, T0 - 1, T0 + 1, T0 + 3_600 * 10**9 + 1, T0 - 3_600 * 10**9 - 1])
    | st.integers(T0 - 10**13, T0 + 10**13),
    "lat": st.sampled_from([LAT0, LAT0 + 0.01, -80.0, 84.0, 84.000001, 90.0]) | st.floats(-90.0, 90.0),
    "lon": st.sampled_from([LON0, LON0 + 0.01, -180.0, 180.0, 3.0, 15.0]) | st.floats(-180.0, 180.0),
    "speed": st.sampled_from([0.0, 10.0, 12.0, 70.0, 70.1, 100.0]) | st.floats(0.0, 100.0),
    "heading_deg": st.sampled_from([0.0, 90.0, 180.0, 359.999]) | st.floats(0.0, 360.0, exclude_max=True),
    "camera_id": st.sampled_from([CAMERA, "c2", "c9"]),
    "station_id": st.sampled_from([VEHICLE, OTHER, 0, 2**32 - 1]),
}


@fuzz_settings()
@given(stream=streams, data=st.data())
def test_well_formed_but_wrong_messages_are_rejected_by_their_check(stream: str, data: st.DataObject) -> None:
    _, good_doc, _ = STREAMS[stream]
    doc = good_doc(1)
    names = sorted(name for name in plausible_values if name in doc)
    for name in data.draw(
        st.lists(st.sampled_from(names), min_size=1, max_size=3, unique=True), label="fields"
    ):
        doc[name] = data.draw(plausible_values[name], label=name)
    check_one(stream, payload(doc))


keys = st.one_of(
    st.text(max_size=80),
    unicode_strings,
    st.builds(
        "/".join,
        st.lists(
            st.sampled_from(["rsu", RSU, "camera", CAMERA, "c9", "detections", "v2x", "cam", "", "*"]),
            max_size=6,
        ),
    ),
    st.integers(-(10**12), 10**12).map(lambda n: f"v2x/cam/{n}"),
    st.from_regex(r"v2x/cam/0[0-9]{1,3}|v2x/cam/ [0-9]+|v2x/cam/[0-9]{11}|v2x/cam/4242/", fullmatch=True),
    st.integers(300, 20_000).map(lambda n: "rsu/" + "x" * n + "/camera/c1/detections"),
)


@fuzz_settings()
@given(stream=streams, key=keys, data=st.data())
def test_any_key_routes_cleanly(stream: str, key: str, data: st.DataObject) -> None:
    """A good payload under any key: routed, rejected by key or payload mismatch, never raised."""
    _, good_doc, _ = STREAMS[stream]
    raw = payload(good_doc(1)) if data.draw(st.booleans()) else json.dumps(good_doc(1)).encode()
    check_one(stream, raw, key=key)
