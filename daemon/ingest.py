"""Ingest: raw bus messages -> validated DetectionsIn / V2xIn, or a counted, warned rejection.

The bus callbacks only enqueue `Inbound(key, payload, received_ns)`; on the ingest thread the `Decoder`
checks, in this order, the key, the payload size (before any parsing), the schema (strict JSON), key and
payload agreeing, clock skew, per-camera / per-station order and, for calibration vehicles only, that the
position is kinematically plausible. Accepted messages keep their raw payload, so the recorder logs the
bytes that arrived without re-serialising them. Bad input never raises out of `Decoder.decode`.
"""

from __future__ import annotations

import logging
import math
import re
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

from pydantic import ValidationError
from pyproj.exceptions import ProjError

from daemon.clock import Clock
from daemon.keys import detections_key, parse_detections_key, parse_v2x_key, v2x_key
from pipeline.errors import InputError
from pipeline.frames import UtmFrame, utm_epsg_for
from schemas.common import describe_validation_error
from schemas.config import DaemonConfig, IngestConfig
from schemas.messages import V2xPosition, check_detection_frame_boxes

logger = logging.getLogger(__name__)

DETECTIONS = "detections"
V2X = "v2x"
UNKNOWN_KEY = "unknown_key"

# Counter names (notes/daemon.md); built once, not per message.
DETECTIONS_RECEIVED = "detections.received"
DETECTIONS_ACCEPTED = "detections.accepted"
V2X_RECEIVED = "v2x.received"
V2X_ACCEPTED = "v2x.accepted"
V2X_OTHER_STATION = "v2x.other_station"
V2X_REANCHORED = "v2x.reanchored"
UNKNOWN_KEY_REJECTED = "unknown_key.rejected"

MAX_STATION_ID = 4_294_967_295  # V2xPosition.station_id
# After this many consecutive, mutually consistent implausible fixes a calibration vehicle's track
# re-anchors on the newest, so one bad fix (e.g. the very first) cannot lock the vehicle out for good.
REANCHOR_AFTER = 5
# Speed and heading are noisy like positions; at 50 Hz a 0.1 m/s speed jitter alone would read as 5 m/s^2.
# Rates are therefore judged over at least this baseline (one period of a 10 Hz V2X stream).
RATE_BASELINE_S = 0.1
# Below this speed a GNSS heading is mostly noise (notes/daemon.md): no heading-rate check.
HEADING_CHECK_MIN_SPEED_MPS = 3.0
MAX_ROUTES = 4096  # cached key parses (our cameras and nearby stations: far fewer in practice)
MAX_THROTTLE_KEYS = 1024  # distinct (source, reason, field) warning states; beyond, shared per source
MAX_MESSAGE_CHARS = 600  # a warning quotes at most this much (a 2000-box frame can fail in 2000 places)
MAX_KEY_CHARS = 160

_INDEX = re.compile(r"\.\d+(?=\.|$)")
# A model-level check (e.g. Box: x2 > x1) is reported by pydantic at the model's path ("boxes.3: Value error,
# x2 = 10.0 must be ..."); our messages start with "field = value", so that field completes the path.
_VALUE_ERROR = re.compile(r"(?P<path>(?:^|(?<=; ))[^:;]+): Value error, (?:(?P<name>[A-Za-z_]\w*) = )?")


@dataclass(frozen=True, slots=True)
class Inbound:
    """What a bus callback enqueues, nothing more: key expression, raw payload, our receive time (ns)."""

    key: str
    payload: bytes
    received_ns: int


@dataclass(frozen=True, slots=True)
class DetectionsIn:
    """An accepted detection frame: its raw payload (logged as received), stamp and box count. The frame
    itself is not built here (schemas.messages.check_detection_frame): the calibration job decodes the
    recording, and the bus path is ~1.4x faster without 30 Box models per frame."""

    camera_id: str
    stamp_ns: int
    boxes: int
    received_ns: int
    payload: bytes
    box_fields: Sequence[Mapping[str, object]] = ()  # the validated boxes, as parsed (for the Foxglove view)


@dataclass(frozen=True, slots=True)
class V2xIn:
    """An accepted V2X position; `utm` (easting, northing m) only for calibration vehicles, else None.

    Only the position is projected here (~2 us); the full pose with the meridian-convergence-corrected yaw
    is made by the calibration job from the recorded messages, in one vectorised call."""

    station_id: int
    message: V2xPosition
    utm: tuple[float, float] | None
    received_ns: int
    payload: bytes


class Counters:
    """Named event counts. Written by the ingest thread (add is thread-safe too, e.g. for inbox overflow);
    snapshot() copies under the lock, so health queries on other threads see a consistent view."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: dict[str, int] = {}

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._counts[name] = self._counts.get(name, 0) + n

    def get(self, name: str) -> int:
        """One counter's value (0 when never counted)."""
        with self._lock:
            return self._counts.get(name, 0)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)


@dataclass(slots=True)
class _Throttle:
    last_logged_ns: int
    suppressed: int = 0
    latest: str = ""


class RejectLog:
    """Counts rejections and warns about them without flooding the log: the first occurrence of each
    (source, reason, field) is logged at once with its message; later ones are summarised at most once per
    `warn_interval_s` ("... 1234 more in the last 10.0 s, latest: <message>"), on the next one or tick()."""

    def __init__(self, counters: Counters, warn_interval_s: float, clock: Clock) -> None:
        if not warn_interval_s > 0.0:
            raise ValueError(f"warn_interval_s = {warn_interval_s} must be positive")
        self._counters = counters
        self._interval_ns = int(warn_interval_s * 1e9)
        self._clock = clock
        self._states: dict[tuple[str, str, str], _Throttle] = {}

    def reject(self, source: str, reason_key: str, message: str, field: str | None = None) -> None:
        """Count `{source}.rejected.{reason_key}` and warn (rate-limited); `field` refines the rate-limit
        key (e.g. "boxes.*.x2"), so a new kind of problem is always reported at once."""
        self._counters.add(f"{source}.rejected.{reason_key}")
        self.warn(source, f"rejected ({reason_key})", message, field)

    def warn(self, source: str, event: str, message: str, field: str | None = None) -> None:
        """The rate-limited warning alone ("<source> <event>: <message>"), for events counted elsewhere."""
        now_ns = self._clock.now_ns()
        throttle_key = (source, event, field or "")
        state = self._states.get(throttle_key)
        if state is None:
            if len(self._states) >= MAX_THROTTLE_KEYS:
                throttle_key = (source, event, "*")
                state = self._states.get(throttle_key)
            if state is None:
                self._states[throttle_key] = _Throttle(last_logged_ns=now_ns)
                logger.warning("%s %s: %s", source, event, _shorten(message))
                return
        state.suppressed += 1
        state.latest = message
        if now_ns - state.last_logged_ns >= self._interval_ns:
            self._summarise(throttle_key, state, now_ns)

    def tick(self) -> None:
        """Emit the summaries that are due (call now and then, so a burst that stopped is still reported)."""
        now_ns = self._clock.now_ns()
        for throttle_key, state in self._states.items():
            if state.suppressed and now_ns - state.last_logged_ns >= self._interval_ns:
                self._summarise(throttle_key, state, now_ns)

    def _summarise(self, throttle_key: tuple[str, str, str], state: _Throttle, now_ns: int) -> None:
        source, event, field_name = throttle_key
        logger.warning(
            "%s %s%s: %d more in the last %.1f s, latest: %s",
            source,
            event,
            f" [{field_name}]" if field_name else "",
            state.suppressed,
            (now_ns - state.last_logged_ns) / 1e9,
            _shorten(state.latest),
        )
        state.last_logged_ns = now_ns
        state.suppressed = 0
        state.latest = ""


class _Route(NamedTuple):
    """A parsed key: which decoder, and what the key names."""

    source: str  # DETECTIONS, V2X or UNKNOWN_KEY
    camera_id: str  # detections: the key's camera ("" otherwise)
    station_id: int  # v2x: the key's station (-1 otherwise)
    known: bool  # detections: camera configured; v2x: a calibration vehicle


_UNKNOWN_ROUTE = _Route(UNKNOWN_KEY, "", -1, False)


@dataclass(frozen=True, slots=True)
class _Fix:
    """What the plausibility checks need of one V2X position (UTM metres, reported speed and heading)."""

    stamp_ns: int
    east: float
    north: float
    speed_mps: float
    heading_deg: float


@dataclass(slots=True)
class _Track:
    """A calibration vehicle's last accepted fix and the implausible fixes that agree with each other."""

    anchor: _Fix | None = None
    candidates: list[_Fix] = field(default_factory=list)


class Decoder:
    """Validates inbound messages (see the module docstring for the order of checks). No bus, no files;
    call only on the ingest thread. Counters: `detections.received/accepted/rejected.<reason>`,
    `v2x.received/accepted/rejected.<reason>`, `v2x.other_station` (accepted, no pose), `v2x.reanchored`,
    `unknown_key.rejected`; received == accepted + rejected for each source."""

    def __init__(self, config: DaemonConfig, clock: Clock, counters: Counters, rejects: RejectLog) -> None:
        self._rsu_id = config.rsu_id
        self._limits: IngestConfig = config.ingest
        self._max_payload_bytes = config.ingest.max_payload_bytes
        skew_s = config.ingest.max_clock_skew_s
        self._max_skew_ns = None if skew_s is None else int(skew_s * 1e9)
        # Skew is measured against inbound.received_ns, which the bus stamped with this same clock.
        self._clock = clock
        self._counters = counters
        self._rejects = rejects
        self._camera_ids = frozenset(camera.camera_id for camera in config.cameras)
        self._vehicle_ids = frozenset(vehicle.station_id for vehicle in config.vehicles)
        self._routes: dict[str, _Route] = {}
        self._last_detection_ns: dict[str, int] = {}
        self._tracks: dict[int, _Track] = {station_id: _Track() for station_id in self._vehicle_ids}
        self._frame: UtmFrame | None = None
        if config.crs is not None:
            self._frame = UtmFrame(config.crs)
        else:
            for camera in config.cameras:
                if camera.position is not None:
                    self._frame = UtmFrame(utm_epsg_for(camera.position.lat, camera.position.lon))
                    break
        # Health shows the main counters from the start, not only once something arrived.
        for name in (DETECTIONS_RECEIVED, DETECTIONS_ACCEPTED, V2X_RECEIVED, V2X_ACCEPTED, V2X_OTHER_STATION):
            counters.add(name, 0)
        counters.add(UNKNOWN_KEY_REJECTED, 0)

    @property
    def frame(self) -> UtmFrame | None:
        """The UTM frame of the poses: config.crs, else the first camera position's zone, else the zone of
        the first calibration-vehicle V2X message (None until then)."""
        return self._frame

    def decode(self, inbound: Inbound) -> DetectionsIn | V2xIn | None:
        """One inbound message -> the accepted item, or None when rejected (counted and warned)."""
        route = self._routes.get(inbound.key)
        if route is None:
            route = self._route(inbound.key)
        if route.source == DETECTIONS:
            return self._decode_detections(inbound, route)
        if route.source == V2X:
            return self._decode_v2x(inbound, route)
        self._counters.add(UNKNOWN_KEY_REJECTED)
        self._rejects.warn(
            UNKNOWN_KEY,
            "rejected",
            f"{_shorten(inbound.key, MAX_KEY_CHARS)!r}: neither "
            f"{detections_key(self._rsu_id, '<camera_id>')} nor {v2x_key('<station_id>')}",
        )
        return None

    # ------------------------------------------------------------------------------------------ keys

    def _route(self, key: str) -> _Route:
        route = _UNKNOWN_ROUTE
        camera_key = parse_detections_key(key)
        station = None if camera_key is not None else parse_v2x_key(key)
        if camera_key is not None and camera_key[0] == self._rsu_id:
            camera_id = camera_key[1]
            route = _Route(DETECTIONS, camera_id, -1, camera_id in self._camera_ids)
        elif station is not None and _is_canonical_uint(station):
            station_id = int(station)
            if station_id <= MAX_STATION_ID:
                route = _Route(V2X, "", station_id, station_id in self._vehicle_ids)
        if route is _UNKNOWN_ROUTE:
            return route  # not cached: rare, and the key may be anything (any length)
        if len(self._routes) >= MAX_ROUTES:
            self._routes.clear()
        self._routes[key] = route
        return route

    # ------------------------------------------------------------------------------------ detections

    def _decode_detections(self, inbound: Inbound, route: _Route) -> DetectionsIn | None:
        self._counters.add(DETECTIONS_RECEIVED)
        key = inbound.key
        camera_id = route.camera_id
        if not route.known:
            known = ", ".join(sorted(self._camera_ids))
            self._reject(
                DETECTIONS,
                "unknown_camera",
                f"{key}: camera_id {_shorten(camera_id, 64)!r} is not configured (cameras: {known})",
                "camera_id",
            )
            return None
        if not self._fits(DETECTIONS, inbound):
            return None
        try:
            frame_camera_id, stamp_ns, boxes = check_detection_frame_boxes(inbound.payload)
        except ValidationError as err:
            self._reject_schema(DETECTIONS, key, err)
            return None
        except (UnicodeDecodeError, ValueError) as err:
            self._reject(DETECTIONS, "json", f"{key}: (root): {err}", "(root)")
            return None
        if frame_camera_id != camera_id:
            self._reject(
                DETECTIONS,
                "camera_mismatch",
                f"{key}: camera_id = {frame_camera_id!r} does not match the key's camera {camera_id!r}",
                "camera_id",
            )
            return None
        if not self._stamp_ok(DETECTIONS, key, stamp_ns, inbound.received_ns):
            return None
        last_ns = self._last_detection_ns.get(camera_id)
        if last_ns is not None and stamp_ns <= last_ns:
            self._reject_order(DETECTIONS, key, f"camera {camera_id!r}", stamp_ns, last_ns)
            return None
        self._last_detection_ns[camera_id] = stamp_ns
        self._counters.add(DETECTIONS_ACCEPTED)
        return DetectionsIn(camera_id, stamp_ns, len(boxes), inbound.received_ns, inbound.payload, boxes)

    # ------------------------------------------------------------------------------------------- V2X

    def _decode_v2x(self, inbound: Inbound, route: _Route) -> V2xIn | None:
        self._counters.add(V2X_RECEIVED)
        key = inbound.key
        station_id = route.station_id
        if not self._fits(V2X, inbound):
            return None
        try:
            message = V2xPosition.model_validate_json(inbound.payload, strict=True)
        except ValidationError as err:
            self._reject_schema(V2X, key, err)
            return None
        except (UnicodeDecodeError, ValueError) as err:
            self._reject(V2X, "json", f"{key}: (root): {err}", "(root)")
            return None
        if message.station_id != station_id:
            self._reject(
                V2X,
                "station_mismatch",
                f"{key}: station_id = {message.station_id} does not match the key's station {station_id}",
                "station_id",
            )
            return None
        if not self._stamp_ok(V2X, key, message.stamp_ns, inbound.received_ns):
            return None
        if not route.known:
            # Other traffic: logged for later analysis, schema-checked only (no order, no plausibility).
            self._counters.add(V2X_OTHER_STATION)
            self._counters.add(V2X_ACCEPTED)
            return V2xIn(station_id, message, None, inbound.received_ns, inbound.payload)
        return self._decode_vehicle(inbound, message, self._tracks[station_id])

    def _decode_vehicle(self, inbound: Inbound, message: V2xPosition, track: _Track) -> V2xIn | None:
        """Order, pose and plausibility of a calibration vehicle's position."""
        key = inbound.key
        anchor = track.anchor
        if anchor is not None and message.stamp_ns <= anchor.stamp_ns:
            self._reject_order(V2X, key, f"station {message.station_id}", message.stamp_ns, anchor.stamp_ns)
            return None
        limits = self._limits
        if message.speed > limits.max_speed_mps:
            self._reject(
                V2X,
                "implausible",
                f"{key}: speed = {message.speed:.1f} m/s exceeds "
                f"ingest.max_speed_mps = {limits.max_speed_mps}",
                "speed",
            )
            return None
        utm = self._utm(key, message)
        if utm is None:
            return None
        fix = _Fix(message.stamp_ns, utm[0], utm[1], message.speed, message.heading_deg)
        problem = None if anchor is None else _implausibility(anchor, fix, limits)
        if problem is not None:
            candidates = track.candidates
            if candidates and _implausibility(candidates[-1], fix, limits) is None:
                candidates.append(fix)
            else:
                candidates[:] = [fix]
            if len(candidates) < REANCHOR_AFTER:
                field_name, why = problem
                self._reject(V2X, "implausible", f"{key}: {field_name}: {why}", field_name)
                return None
            # The newest of REANCHOR_AFTER mutually consistent fixes: the old anchor was the outlier.
            self._counters.add(V2X_REANCHORED)
            self._rejects.warn(
                V2X,
                "re-anchored",
                f"{key}: {REANCHOR_AFTER} consecutive consistent positions disagree with the last "
                f"accepted one ({problem[0]}: {problem[1]}); continuing from stamp_ns = {fix.stamp_ns}",
            )
        track.anchor = fix
        track.candidates.clear()
        self._counters.add(V2X_ACCEPTED)
        return V2xIn(message.station_id, message, utm, inbound.received_ns, inbound.payload)

    def _utm(self, key: str, message: V2xPosition) -> tuple[float, float] | None:
        """UTM position of a calibration vehicle's message; None (rejected: implausible)."""
        try:
            frame = self._frame
            if frame is None:
                frame = UtmFrame(utm_epsg_for(message.lat, message.lon))
                self._frame = frame
                logger.info("UTM frame %s from the first calibration-vehicle position (%s)", frame.crs, key)
            if not -80.0 <= message.lat <= 84.0:  # UTM's domain (utm_epsg_for)
                raise ValueError("outside UTM's latitude range [-80, 84]")
            east, north = frame.to_utm_point(message.lat, message.lon)
            if not (math.isfinite(east) and math.isfinite(north)):
                raise ValueError("the projection is not finite there")
            return east, north
        except (InputError, ProjError, ValueError) as err:
            self._reject(
                V2X,
                "implausible",
                f"{key}: lat/lon: lat = {message.lat}, lon = {message.lon} has no UTM position: {err}",
                "lat/lon",
            )
            return None

    # ---------------------------------------------------------------------------------------- shared

    def _fits(self, source: str, inbound: Inbound) -> bool:
        size = len(inbound.payload)
        if size <= self._max_payload_bytes:
            return True
        self._reject(
            source,
            "oversized",
            f"{inbound.key}: payload: {size} bytes exceeds "
            f"ingest.max_payload_bytes = {self._max_payload_bytes}",
            "payload",
        )
        return False

    def _stamp_ok(self, source: str, key: str, stamp_ns: int, received_ns: int) -> bool:
        if self._max_skew_ns is None or abs(stamp_ns - received_ns) <= self._max_skew_ns:
            return True
        self._reject(
            source,
            "clock_skew",
            f"{key}: stamp_ns = {stamp_ns} is {(stamp_ns - received_ns) / 1e9:+.3f} s from our clock "
            f"(received_ns = {received_ns}), beyond "
            f"ingest.max_clock_skew_s = {self._limits.max_clock_skew_s}",
            "stamp_ns",
        )
        return False

    def _reject_order(self, source: str, key: str, stream: str, stamp_ns: int, last_ns: int) -> None:
        if stamp_ns == last_ns:
            message = f"{key}: stamp_ns = {stamp_ns} equals the last accepted stamp of {stream}"
            self._reject(source, "duplicate", message, "stamp_ns")
        else:
            message = (
                f"{key}: stamp_ns = {stamp_ns} is {(last_ns - stamp_ns) / 1e6:.3f} ms older than the last "
                f"accepted stamp of {stream} ({last_ns})"
            )
            self._reject(source, "out_of_order", message, "stamp_ns")

    def _reject_schema(self, source: str, key: str, err: ValidationError) -> None:
        details = _VALUE_ERROR.sub(_name_checked_field, describe_validation_error(err))
        first_path = details.split(": ", 1)[0]
        self._reject(source, "json", f"{key}: {details}", _INDEX.sub(".*", first_path))

    def _reject(self, source: str, reason_key: str, message: str, field_name: str) -> None:
        self._rejects.reject(source, reason_key, message, field_name)


def _implausibility(previous: _Fix, fix: _Fix, limits: IngestConfig) -> tuple[str, str] | None:
    """(field, why) when `fix` cannot follow `previous` for a real vehicle, else None. `fix` is newer.

    Jump: the distance must fit max_speed_mps over the time between them plus max_position_error_m of
    GNSS noise. Speed and heading changes are judged over at least RATE_BASELINE_S (noise, see there)."""
    dt_s = (fix.stamp_ns - previous.stamp_ns) * 1e-9
    distance_m = math.hypot(fix.east - previous.east, fix.north - previous.north)
    if distance_m > limits.max_speed_mps * dt_s + limits.max_position_error_m:
        return "lat/lon", (
            f"moved {distance_m:.1f} m in {dt_s:.3f} s ({distance_m / dt_s:.1f} m/s) since the last accepted "
            f"position; allowed: ingest.max_speed_mps = {limits.max_speed_mps} plus "
            f"ingest.max_position_error_m = {limits.max_position_error_m}"
        )
    rate_dt_s = max(dt_s, RATE_BASELINE_S)
    speed_change_mps = abs(fix.speed_mps - previous.speed_mps)
    if speed_change_mps > limits.max_accel_mps2 * rate_dt_s:
        return "speed", (
            f"speed = {fix.speed_mps:.1f} m/s after {previous.speed_mps:.1f} m/s {dt_s:.3f} s earlier "
            f"({speed_change_mps / rate_dt_s:.1f} m/s^2 > ingest.max_accel_mps2 = {limits.max_accel_mps2})"
        )
    if min(fix.speed_mps, previous.speed_mps) > HEADING_CHECK_MIN_SPEED_MPS:
        turn_deg = abs((fix.heading_deg - previous.heading_deg + 180.0) % 360.0 - 180.0)
        if turn_deg > limits.max_yaw_rate_deg_s * rate_dt_s:
            return "heading_deg", (
                f"heading_deg = {fix.heading_deg:.1f} after {previous.heading_deg:.1f} {dt_s:.3f} s earlier "
                f"({turn_deg / rate_dt_s:.0f} deg/s > "
                f"ingest.max_yaw_rate_deg_s = {limits.max_yaw_rate_deg_s})"
            )
    return None


def _name_checked_field(match: re.Match[str]) -> str:
    path, name = match["path"], match["name"]
    if name is None:
        return f"{path}: "
    if path == "(root)":
        return f"{name}: {name} = "
    return f"{path}: {name} = " if path.endswith(f".{name}") or path == name else f"{path}.{name}: {name} = "


def _is_canonical_uint(text: str) -> bool:
    """Plain ASCII decimal without sign, spaces or leading zeros (so one station has one key)."""
    return 0 < len(text) <= 10 and text.isascii() and text.isdigit() and (text == "0" or text[0] != "0")


def _shorten(text: str, max_chars: int = MAX_MESSAGE_CHARS) -> str:
    return text if len(text) <= max_chars else f"{text[: max_chars - 3]}..."
