"""`rsucal bridge cam|yolo`: turn what a V2X stack or a detector already emits into rsucal's bus messages.

Both read JSON lines (a file, or `-` for stdin, e.g. piped from the producer) and publish on Zenoh next
to the daemon. `cam`: ETSI CAM in the JSON encoding of its ASN.1 definition (the field names of EN
302 637-2 / TS 103 900: header.stationID, cam.generationDeltaTime, camParameters.basicContainer...) in
CAM units -> V2xPosition on `v2x/cam/{station}`. `yolo`: one line per image with the detector's boxes ->
DetectionFrame on `rsu/{rsu}/camera/{cam}/detections`. A bad line is counted and named (line number and
field) and the bridge goes on; the summary at the end says how many lines went where.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from pydantic import ValidationError

from daemon.clock import Clock, SystemClock
from daemon.ingest import Counters, RejectLog
from daemon.keys import detections_key, v2x_key
from pipeline.errors import InputError
from schemas.common import STAMP_NS_MAX, STAMP_NS_MIN, describe_validation_error
from schemas.messages import DetectionFrame, V2xPosition

log = logging.getLogger(__name__)

# ------------------------------------------------------------------------------------------------- CAM

# TimestampIts: TAI milliseconds since 2004-01-01T00:00:00Z (ETSI TS 102 894-2); generationDeltaTime is it
# modulo 65536. TAI runs ahead of UTC by the leap seconds inserted since 2004 (UTC start of their effect).
ITS_EPOCH_NS = 1_072_915_200_000_000_000
_LEAP_SECONDS_SINCE_2004 = (
    (1_136_073_600_000_000_000, 1),  # 2006-01-01
    (1_230_768_000_000_000_000, 2),  # 2009-01-01
    (1_341_100_800_000_000_000, 3),  # 2012-07-01
    (1_435_708_800_000_000_000, 4),  # 2015-07-01
    (1_483_228_800_000_000_000, 5),  # 2017-01-01
)
DELTA_TIME_MODULUS_MS = 65_536
# ETSI confidences are 95 % bounds; V2xPosition's accuracies are 1 sigma.
SIGMA_PER_95_1D = 1.0 / 1.96
SIGMA_PER_95_2D = 1.0 / 2.4477  # the 95 % ellipse of a 2-D normal: sqrt(chi2(2, 0.95)) = 2.4477 sigma

# CAM data elements: (field, lowest valid, highest valid, unavailable sentinel, unit in project units).
LATITUDE = ("latitude", -900_000_000, 900_000_000, 900_000_001, 1e-7)  # deg
LONGITUDE = ("longitude", -1_800_000_000, 1_800_000_000, 1_800_000_001, 1e-7)  # deg
ALTITUDE = ("altitudeValue", -100_000, 800_000, 800_001, 0.01)  # m
HEADING = ("headingValue", 0, 3599, 3601, 0.1)  # deg from north; 3600 is "doNotUse"
SPEED = ("speedValue", 0, 16_382, 16_383, 0.01)  # m/s
VEHICLE_LENGTH = ("vehicleLengthValue", 1, 1021, 1023, 0.1)  # m; 1022 "outOfRange"
VEHICLE_WIDTH = ("vehicleWidth", 1, 60, 62, 0.1)  # m; 61 "outOfRange"
HEADING_CONFIDENCE = ("headingConfidence", 1, 125, 127, 0.1)  # deg (95 %); 126 "outOfRange"
SPEED_CONFIDENCE = ("speedConfidence", 1, 125, 127, 0.01)  # m/s (95 %); 126 "outOfRange"
SEMI_MAJOR_CONFIDENCE = ("semiMajorConfidence", 0, 4093, 4095, 0.01)  # m (95 %); 4094 "outOfRange"
CAM_MESSAGE_ID = 2


class LineError(ValueError):
    """One input line that cannot be bridged: `field` is its dotted path, `reason` the counter's name."""

    def __init__(self, field_name: str, message: str, reason: str = "invalid") -> None:
        super().__init__(f"{field_name}: {message}")
        self.field = field_name
        self.reason = reason


def its_leap_ms(utc_ns: int) -> int:
    """TAI - UTC minus its 2004 value, in ms, at `utc_ns` (leap seconds to date: 5 since 2017)."""
    leap = 0
    for since_ns, count in _LEAP_SECONDS_SINCE_2004:
        if utc_ns >= since_ns:
            leap = count
    return leap * 1000


def generation_time_ns(generation_delta_time_ms: int, received_ns: int) -> int:
    """The CAM's generation time (UTC ns) from its 16-bit generationDeltaTime (TimestampIts mod 65536):
    the time with that remainder nearest to our receive time (`received_ns`, UTC ns), so stamps up to
    32.767 s before or after our clock resolve correctly across the wrap."""
    leap_ms = its_leap_ms(received_ns)
    received_its_ms = (received_ns - ITS_EPOCH_NS) // 1_000_000 + leap_ms
    behind_ms = (received_its_ms - generation_delta_time_ms) % DELTA_TIME_MODULUS_MS
    if behind_ms > DELTA_TIME_MODULUS_MS // 2:
        behind_ms -= DELTA_TIME_MODULUS_MS  # a sender clock slightly ahead of ours
    its_ms = received_its_ms - behind_ms
    return ITS_EPOCH_NS + (its_ms - leap_ms) * 1_000_000


def _member(obj: Any, path: str, *names: str) -> Any:
    """obj[name] for the first of `names` present; LineError naming `path.name` when none is."""
    if not isinstance(obj, dict):
        raise LineError(path, f"expected an object, got {type(obj).__name__}")
    for name in names:
        if name in obj:
            return obj[name]
    raise LineError(f"{path}.{names[0]}" if path else names[0], "missing", "missing")


def _integer(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise LineError(where, f"expected an integer (CAM units), got {json.dumps(value)[:40]}")
    return value


Element = tuple[str, int, int, int, float]


def _scaled(container: Any, path: str, element: Element, required: bool) -> float | None:
    """A CAM data element in project units; None when optional and absent or "unavailable"."""
    name, low, high, unavailable, unit = element
    where = f"{path}.{name}"
    if not isinstance(container, dict) or name not in container:
        if required:
            _member(container, path, name)
        return None
    value = _integer(container[name], where)
    if value == unavailable:
        if required:
            raise LineError(where, f"{value} means 'unavailable'", "unavailable")
        return None
    if not low <= value <= high:
        raise LineError(where, f"{value} is outside [{low}, {high}]", "out_of_range")
    return value * unit


def cam_to_v2x(document: Any, received_ns: int) -> V2xPosition:
    """An ETSI CAM (JSON of its ASN.1 definition, CAM units) -> V2xPosition; LineError names the field.

    Required: header.stationID (or stationId), cam.generationDeltaTime, the basic container's
    referencePosition (latitude, longitude 1e-7 deg; altitude.altitudeValue 0.01 m) and the vehicle
    high-frequency container's heading.headingValue (0.1 deg from true north) and speed.speedValue
    (0.01 m/s). Optional: vehicleLength, vehicleWidth (0.1 m) and the confidences (95 % -> 1 sigma).
    "unavailable" in a required field rejects the message; in an optional one it is left out.
    """
    header = _member(document, "", "header")
    station_id = _integer(_member(header, "header", "stationID", "stationId"), "header.stationID")
    message_id = header.get("messageID", header.get("messageId", CAM_MESSAGE_ID))
    if message_id != CAM_MESSAGE_ID:
        raise LineError("header.messageID", f"{json.dumps(message_id)[:20]} is not a CAM (2)", "not_cam")
    cam = _member(document, "", "cam")
    delta_ms = _integer(_member(cam, "cam", "generationDeltaTime"), "cam.generationDeltaTime")
    if not 0 <= delta_ms < DELTA_TIME_MODULUS_MS:
        raise LineError("cam.generationDeltaTime", f"{delta_ms} is outside [0, 65535]", "out_of_range")
    parameters = _member(cam, "cam", "camParameters")
    where = "cam.camParameters.basicContainer.referencePosition"
    basic = _member(parameters, "cam.camParameters", "basicContainer")
    position = _member(basic, "cam.camParameters.basicContainer", "referencePosition")
    lat = _scaled(position, where, LATITUDE, required=True)
    lon = _scaled(position, where, LONGITUDE, required=True)
    alt = _scaled(_member(position, where, "altitude"), f"{where}.altitude", ALTITUDE, required=True)
    high_frequency = _member(parameters, "cam.camParameters", "highFrequencyContainer")
    hf_where = "cam.camParameters.highFrequencyContainer"
    if isinstance(high_frequency, dict) and "basicVehicleContainerHighFrequency" not in high_frequency:
        kinds = ", ".join(sorted(high_frequency)) or "nothing"
        raise LineError(
            f"{hf_where}.basicVehicleContainerHighFrequency",
            f"missing (holds {kinds}: not a vehicle)",
            "missing",
        )
    vehicle = _member(high_frequency, hf_where, "basicVehicleContainerHighFrequency")
    hf_where += ".basicVehicleContainerHighFrequency"
    heading_container = _member(vehicle, hf_where, "heading")
    speed_container = _member(vehicle, hf_where, "speed")
    heading_deg = _scaled(heading_container, f"{hf_where}.heading", HEADING, required=True)
    speed_mps = _scaled(speed_container, f"{hf_where}.speed", SPEED, required=True)
    length_m = _scaled(vehicle.get("vehicleLength"), f"{hf_where}.vehicleLength", VEHICLE_LENGTH, False)
    width_m = _scaled(vehicle, hf_where, VEHICLE_WIDTH, required=False)
    heading_95 = _scaled(heading_container, f"{hf_where}.heading", HEADING_CONFIDENCE, required=False)
    speed_95 = _scaled(speed_container, f"{hf_where}.speed", SPEED_CONFIDENCE, required=False)
    ellipse = position.get("positionConfidenceEllipse") if isinstance(position, dict) else None
    semi_major_95 = _scaled(ellipse, f"{where}.positionConfidenceEllipse", SEMI_MAJOR_CONFIDENCE, False)
    accuracies = {
        "horizontal_m": None if semi_major_95 is None else semi_major_95 * SIGMA_PER_95_2D,
        "heading_deg": None if heading_95 is None else heading_95 * SIGMA_PER_95_1D,
        "speed_mps": None if speed_95 is None else speed_95 * SIGMA_PER_95_1D,
    }
    fields: dict[str, Any] = {
        "station_id": station_id,
        "stamp_ns": generation_time_ns(delta_ms, received_ns),
        "lat": lat,
        "lon": lon,
        "alt": alt,
        "heading_deg": heading_deg,
        "speed": speed_mps,
    }
    if length_m is not None:
        fields["length"] = length_m
    if width_m is not None:
        fields["width"] = width_m
    if any(value is not None for value in accuracies.values()):
        fields["accuracies"] = {k: v for k, v in accuracies.items() if v is not None}
    message: V2xPosition = _validated(V2xPosition, fields)
    return message


def _validated(model: type[V2xPosition] | type[DetectionFrame], fields: dict[str, Any]) -> Any:
    try:
        return model.model_validate_json(json.dumps(fields), strict=True)
    except ValidationError as err:
        details = describe_validation_error(err)
        raise LineError(details.split(":", 1)[0], details.split(": ", 1)[-1], "schema") from err


# ------------------------------------------------------------------------------------------------ YOLO


def _box(entry: Any, where: str) -> dict[str, Any]:
    """One detector box in any of the common spellings -> Box fields (x1, y1, x2, y2, cls, score).

    x1/y1/x2/y2 (rsucal); box: {x1, y1, x2, y2} with name/class and confidence (Ultralytics' JSON summary);
    xyxy: [x1, y1, x2, y2] with cls and conf; bbox: [x, y, w, h] with category_id and score (COCO results).
    The class is the name when one is given, else the id.
    """
    if not isinstance(entry, dict):
        raise LineError(where, f"expected a box object, got {type(entry).__name__}")
    if "box" in entry:
        corners = _member(entry, where, "box")
        x1, y1, x2, y2 = (_member(corners, f"{where}.box", name) for name in ("x1", "y1", "x2", "y2"))
    elif "xyxy" in entry:
        x1, y1, x2, y2 = _four(entry["xyxy"], f"{where}.xyxy")
    elif "bbox" in entry:
        x, y, w, h = _four(entry["bbox"], f"{where}.bbox")
        x1, y1, x2, y2 = x, y, _sum(x, w, f"{where}.bbox"), _sum(y, h, f"{where}.bbox")
    else:
        x1, y1, x2, y2 = (_member(entry, where, name) for name in ("x1", "y1", "x2", "y2"))
    box: dict[str, Any] = {"x1": x1, "y1": y1, "x2": x2, "y2": y2}
    for name in ("name", "cls", "class", "category_id"):
        if name in entry:
            box["cls"] = entry[name]
            break
    for name in ("score", "confidence", "conf"):
        if name in entry:
            box["score"] = entry[name]
            break
    return box


def _four(value: Any, where: str) -> tuple[Any, Any, Any, Any]:
    if not isinstance(value, list) or len(value) != 4:
        raise LineError(where, f"expected 4 numbers, got {json.dumps(value)[:60]}")
    return value[0], value[1], value[2], value[3]


def _sum(origin: Any, size: Any, where: str) -> Any:
    numbers = all(isinstance(v, int | float) and not isinstance(v, bool) for v in (origin, size))
    if not numbers:
        raise LineError(where, "expected numbers")
    return origin + size


def yolo_to_frame(document: Any, camera_id: str) -> DetectionFrame:
    """One image's detections -> DetectionFrame of `camera_id`; LineError names the field.

    The line is an object with `stamp_ns` (int, ns since the Unix epoch, the image's exposure time as
    well as it is known) and `boxes` (or `detections`): a list of boxes in any spelling `_box` reads.
    """
    stamp_ns = _member(document, "", "stamp_ns")
    is_int = isinstance(stamp_ns, int) and not isinstance(stamp_ns, bool)
    if is_int and not STAMP_NS_MIN <= stamp_ns <= STAMP_NS_MAX:
        raise LineError("stamp_ns", f"{stamp_ns} is not ns since the Unix epoch (2000..2200)", "out_of_range")
    entries = _member(document, "", "boxes", "detections")
    if not isinstance(entries, list):
        raise LineError("boxes", f"expected a list, got {type(entries).__name__}")
    key = "boxes" if "boxes" in document else "detections"
    boxes = [_box(entry, f"{key}.{index}") for index, entry in enumerate(entries)]
    if "camera_id" in document and document["camera_id"] != camera_id:
        raise LineError("camera_id", f"{json.dumps(document['camera_id'])[:70]} is not --camera {camera_id}")
    fields = {"camera_id": camera_id, "stamp_ns": stamp_ns, "boxes": boxes}
    frame: DetectionFrame = _validated(DetectionFrame, fields)
    return frame


# ---------------------------------------------------------------------------------------------- runner


@dataclass(slots=True)
class BridgeReport:
    """What a bridge did: lines read, messages published, and rejected lines by reason."""

    lines: int = 0
    published: int = 0
    rejected: dict[str, int] = field(default_factory=dict)

    def summary(self, name: str) -> str:
        rejected = sum(self.rejected.values())
        reasons = ", ".join(f"{reason} {count}" for reason, count in sorted(self.rejected.items()))
        return f"bridge {name}: {self.lines} line(s), {self.published} published, {rejected} rejected" + (
            f" ({reasons})" if reasons else ""
        )


Convert = Callable[[Any, int], tuple[str, bytes]]
"""(parsed JSON line, received_ns) -> (bus key, payload); raises LineError for a bad line."""
Publish = Callable[[str, bytes], None]


def run_bridge(
    name: str,
    lines: Iterable[str],
    convert: Convert,
    publish: Publish,
    clock: Clock,
    warn_interval_s: float = 10.0,
    report: BridgeReport | None = None,
) -> BridgeReport:
    """Convert and publish every line; a bad line is counted (`<name>.rejected.<reason>`), warned about
    (line number and field, rate-limited per field) and skipped. Blank lines are ignored. `report` is
    filled as lines go (so an interrupted run still has its counts)."""
    report = BridgeReport() if report is None else report
    counters = Counters()
    rejects = RejectLog(counters, warn_interval_s, clock)
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        report.lines += 1
        received_ns = clock.now_ns()
        try:
            try:
                document = json.loads(line)
            except ValueError as err:
                raise LineError("(root)", f"not JSON: {err}", "json") from err
            key, payload = convert(document, received_ns)
        except LineError as err:
            report.rejected[err.reason] = report.rejected.get(err.reason, 0) + 1
            rejects.reject(name, err.reason, f"line {number}: {err}", err.field)
            continue
        publish(key, payload)
        report.published += 1
    rejects.tick()
    return report


def cam_converter() -> Convert:
    def convert(document: Any, received_ns: int) -> tuple[str, bytes]:
        message = cam_to_v2x(document, received_ns)
        return v2x_key(message.station_id), message.model_dump_json(exclude_none=True).encode("utf-8")

    return convert


def yolo_converter(rsu_id: str, camera_id: str) -> Convert:
    key = detections_key(rsu_id, camera_id)

    def convert(document: Any, received_ns: int) -> tuple[str, bytes]:
        return key, yolo_to_frame(document, camera_id).model_dump_json().encode("utf-8")

    return convert


# ------------------------------------------------------------------------------------------------- CLI


@contextmanager
def _input_lines(path: str) -> Iterator[Iterable[str]]:
    if path == "-":
        yield sys.stdin
        return
    try:
        stream: TextIO = Path(path).open(encoding="utf-8", errors="replace")  # noqa: SIM115  (closed below)
    except OSError as err:
        raise InputError(path, f"--input: cannot read: {err.strerror or err}") from err
    with stream:
        yield stream


class ZenohPublisher:
    """Puts on the bus; before the first message of a key waits up to `match_timeout_s` for a subscriber
    (the daemon), so the first lines of a file are not sent before the session is connected."""

    def __init__(self, session: Any, match_timeout_s: float) -> None:
        self._session = session
        self._publishers: dict[str, Any] = {}
        self._match_timeout_s = match_timeout_s

    def __call__(self, key: str, payload: bytes) -> None:
        import zenoh

        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self._session.declare_publisher(
                key,
                encoding=zenoh.Encoding.APPLICATION_JSON,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            self._publishers[key] = publisher
            deadline = time.monotonic() + self._match_timeout_s
            while not publisher.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.01)
            if not publisher.matching_status.matching:
                log.warning("%s: no subscriber after %.1f s; publishing anyway", key, self._match_timeout_s)
        publisher.put(payload)

    def close(self) -> None:
        for publisher in self._publishers.values():
            publisher.undeclare()
        self._publishers.clear()


def bridge_main(args: argparse.Namespace) -> int:
    """`rsucal bridge cam|yolo`: exit 0 when the input ended (bad lines are counted, not fatal)."""
    from daemon.bus import client_config, open_session

    if args.kind == "cam":
        convert = cam_converter()
    else:
        for option, value in (("--rsu", args.rsu), ("--camera", args.camera)):
            is_id = 0 < len(value) <= 64 and all(c.isascii() and (c.isalnum() or c in "_.-") for c in value)
            if not is_id:
                raise InputError(option, f"{value!r} is not an id (letters, digits, '_', '.', '-')")
        convert = yolo_converter(args.rsu, args.camera)
    zenoh_file = Path(args.zenoh_config) if args.zenoh_config else None
    config = client_config(args.connect or [], config_file=zenoh_file)
    with _input_lines(args.input) as lines:
        session = open_session(config, args.connect or [])
        publisher = ZenohPublisher(session, args.wait_s)
        report = BridgeReport()
        try:
            run_bridge(args.kind, lines, convert, publisher, SystemClock(), report=report)
        except KeyboardInterrupt:
            pass  # Ctrl-C on a live pipe: the summary below says how far it got
        finally:
            publisher.close()
            session.close()  # type: ignore[no-untyped-call]
    print(report.summary(args.kind), file=sys.stderr)
    return 0
