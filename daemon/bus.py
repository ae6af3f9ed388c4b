"""The daemon's Zenoh side: session configuration, key expressions, subscribers, queryables, liveliness.

In: detections `rsu/{rsu}/camera/*/detections` and V2X `v2x/cam/*`, handed to `on_inbound(key, payload,
received_ns)` straight from Zenoh's callback threads (no decoding here: the ingest thread decodes).
Out: calibration results put on `.../calibration`; queryables for calibration, status, trigger and health,
served on our own threads; liveliness token `rsu/{rsu}/alive`. Keys are docs/design.md's bus table.
"""

from __future__ import annotations

import functools
import json
import logging
import re
import socket
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import zenoh

from daemon.clock import Clock
from daemon.foxglove import FRAME_TRANSFORM
from daemon.keys import (
    ALL_V2X,
    alive_key,
    calibration_key,
    detections_key,
    health_key,
    image_key,
    status_key,
    transform_key,
    trigger_key,
)
from pipeline.errors import RsucalError
from schemas.config import DaemonConfig, ZenohConfig

log = logging.getLogger(__name__)

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
JSON = zenoh.Encoding.APPLICATION_JSON
FRAME_TRANSFORM_ENCODING = zenoh.Encoding.APPLICATION_PROTOBUF.with_schema(FRAME_TRANSFORM.name)
# The text of the error reply to `.../calibration` before a camera has a validated result: fleet readers
# (`rsucal status`) recognise it as "not calibrated yet" rather than a fault.
NO_CALIBRATION = "no validated calibration: none accepted yet, or withdrawn (see the camera's status)"
# close() joins the serving threads within this budget in total (they end as soon as their queryable is
# undeclared, unless a handler is stuck; those threads are daemons and are left behind with a warning).
JOIN_BUDGET_S = 0.3
_ZENOH_SOURCE_LOCATION = re.compile(r"\s+at /\S+\.rs:\d+\.?")
_RUST_DEBUG_MSG = re.compile(r'\w+\(Message \{ msg: "((?:[^"\\]|\\.)*)".*$')
_WILDCARD = re.compile(r"\*|\$")

OnInbound = Callable[[str, bytes, int], None]
"""(key, payload, received_ns) of every detections/V2X sample, called on Zenoh's callback threads: one per
subscription, so detections and V2X arrive concurrently (each in publication order); must not block."""


class BusError(RsucalError):
    """The Zenoh session cannot be opened or used; the message names the endpoint or file."""


# ------------------------------------------------------------------------------------------------ keys


def has_wildcard(key: str) -> bool:
    """True for key expressions with `*`, `**` or `$*` chunks (they may name many resources)."""
    return _WILDCARD.search(key) is not None


# ------------------------------------------------------------------------------------------ configuration


def zenoh_message(err: BaseException) -> str:
    """Zenoh's error text without the Rust source locations (`at /root/.cargo/...rs:61.`) or the Debug form
    of a JSON5 error (`Json5Err(Message { msg: "...", location: ... })` -> its msg)."""
    text = _ZENOH_SOURCE_LOCATION.sub("", str(err)).strip()
    debug = _RUST_DEBUG_MSG.search(text)
    if debug is not None:
        text = text[: debug.start()] + debug.group(1).replace('\\"', '"')
    return text


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (demo, tests, benchmarks: never a fixed port)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def session_config(zenoh_config: ZenohConfig) -> zenoh.Config:
    """The daemon's session config: `config_file` as the base (TLS, access control), then our fields.

    Without a file every field applies. With a file, mode/listen/connect override it only when set in the
    YAML, so a TLS file's `tls/...` listeners survive the `listen` default; multicast_scouting always
    applies (off unless the YAML turns it on), so no file silently enables UDP multicast (docs/design.md).
    """
    explicit = zenoh_config.model_fields_set
    has_file = zenoh_config.config_file is not None
    try:
        if zenoh_config.config_file is not None:
            config = zenoh.Config.from_file(zenoh_config.config_file)
        else:
            config = zenoh.Config()
        if not has_file or "mode" in explicit:
            config.insert_json5("mode", json.dumps(zenoh_config.mode))
        mode = json.loads(config.get_json("mode"))
        # Clients never listen; a router or peer does.
        if mode != "client" and (not has_file or "listen" in explicit):
            config.insert_json5("listen/endpoints", json.dumps(zenoh_config.listen))
        if zenoh_config.connect or "connect" in explicit:
            config.insert_json5("connect/endpoints", json.dumps(zenoh_config.connect))
        config.insert_json5("scouting/multicast/enabled", json.dumps(zenoh_config.multicast_scouting))
    except zenoh.ZError as err:
        where = f"zenoh.config_file {zenoh_config.config_file}" if has_file else "zenoh"
        raise BusError(f"{where}: {zenoh_message(err)}") from err
    return config


def _endpoints(config: zenoh.Config, side: Literal["listen", "connect"]) -> list[str]:
    # zenoh's per-mode form {"peer": [...], "client": [...]} resolved for the config's own mode.
    mode = json.loads(config.get_json("mode"))
    value = json.loads(config.get_json(f"{side}/endpoints"))
    return list(value.get(mode, []) if isinstance(value, dict) else value)


def effective_endpoints(config: zenoh.Config) -> list[str]:
    """The listen and connect endpoints a session config will use (with a config_file these can be the
    file's, not rsu.yaml's defaults)."""
    return _endpoints(config, "listen") + _endpoints(config, "connect")


def connect_endpoints(config: zenoh.Config) -> list[str]:
    """The endpoints a session config connects to (a client config file's own, unless replaced)."""
    return _endpoints(config, "connect")


def client_config(
    connect: Sequence[str], mode: Literal["peer", "client"] = "peer", config_file: Path | None = None
) -> zenoh.Config:
    """A short-lived reader's session (`rsucal status`): connects, listens nowhere, no multicast.

    `config_file` (a Zenoh JSON5 file, e.g. deploy/zenoh/secure-client.json5 with its TLS certificate) is the
    base; `connect`, when given, replaces its endpoints. Without a file, `connect` defaults to loopback.
    """
    try:
        if config_file is not None:
            config = zenoh.Config.from_file(str(config_file))
        else:
            config = zenoh.Config()
            config.insert_json5("mode", json.dumps(mode))
        if connect or config_file is None:
            config.insert_json5("connect/endpoints", json.dumps(list(connect) or [DEFAULT_ENDPOINT]))
        if json.loads(config.get_json("mode")) == "peer":
            config.insert_json5("listen/endpoints", "[]")
        config.insert_json5("scouting/multicast/enabled", "false")
    except zenoh.ZError as err:
        where = f"zenoh config {config_file}" if config_file is not None else "zenoh client config"
        raise BusError(f"{where}: {zenoh_message(err)}") from err
    return config


def open_session(config: zenoh.Config, endpoints: Sequence[str]) -> zenoh.Session:
    """zenoh.open, with a BusError naming the endpoint at fault (e.g. a port already in use)."""
    try:
        return zenoh.open(config)
    except zenoh.ZError as err:
        detail = zenoh_message(err)
        named = [endpoint for endpoint in endpoints if endpoint in detail]
        where = ", ".join(named or endpoints) or "(no endpoints)"
        hint = ""
        if "Address already in use" in detail:
            hint = " (another process, perhaps another rsucal daemon, already listens there)"
        raise BusError(f"zenoh: cannot open a session on {where}: {detail}{hint}") from err


# ---------------------------------------------------------------------------------------------- queries


@dataclass(frozen=True, slots=True)
class QueryReplies:
    """What a get returned: (key, payload) of every ok reply, and the text of every error reply."""

    ok: list[tuple[str, bytes]]
    errors: list[str]


def split_replies(replies: Iterable[zenoh.Reply]) -> QueryReplies:
    """Drain a get's replies (blocks until the query is finalised or times out)."""
    ok: list[tuple[str, bytes]] = []
    errors: list[str] = []
    for reply in replies:
        sample = reply.ok
        if sample is not None:
            ok.append((str(sample.key_expr), sample.payload.to_bytes()))
        else:
            failure = reply.err
            errors.append(failure.payload.to_string() if failure is not None else "empty reply")
    return QueryReplies(ok, errors)


def start_query(session: zenoh.Session, key: str, timeout_s: float) -> zenoh.handlers.Handler[zenoh.Reply]:
    """Send a get to every matching queryable (fleet reads: all RSUs, not only the nearest); do not wait."""
    try:
        return session.get(key, target=zenoh.QueryTarget.ALL, timeout=timeout_s)
    except zenoh.ZError as err:
        raise BusError(f"get {key}: {zenoh_message(err)}") from err


def query_replies(session: zenoh.Session, key: str, timeout_s: float) -> QueryReplies:
    """Ok and error replies of one get."""
    return split_replies(start_query(session, key, timeout_s))


def query(session: zenoh.Session, key: str, timeout_s: float) -> list[tuple[str, bytes]]:
    """(key, payload) of the ok replies; error replies (e.g. NO_CALIBRATION) are logged at debug."""
    replies = query_replies(session, key, timeout_s)
    for text in replies.errors:
        log.debug("get %s: error reply: %s", key, text)
    return replies.ok


# ---------------------------------------------------------------------------------------------- the bus


@dataclass(frozen=True)
class Handlers:
    """Answers to the queryables, called on the serving threads: fast and thread-safe (read snapshots)."""

    calibration: Callable[[str], bytes | None]  # camera_id -> latest validated result JSON; None: not yet
    status: Callable[[str], bytes]  # camera_id -> CalibrationStatus JSON
    trigger: Callable[[str], bytes]  # camera_id -> {"camera_id", "job_id" | null, "accepted", "reason"}
    health: Callable[[], bytes]  # Health JSON


Kind = Literal["calibration", "status", "trigger", "health"]


class Bus:
    """The daemon's session: subscribers feed `on_inbound`, queryables answer from `handlers`.

    One queryable per kind (per-camera kinds use a `camera/*` key and reply for each configured camera the
    query names), each served by its own thread, so a slow trigger never delays status or health and the
    subscriber callbacks never wait for either. Every query is finalised as soon as it is answered.
    """

    def __init__(
        self,
        config: DaemonConfig,
        on_inbound: OnInbound,
        handlers: Handlers,
        clock: Clock,
        on_image: OnInbound | None = None,
    ) -> None:
        self._config = config
        self._on_image = on_image  # images of `rsu/{rsu}/camera/*/image`, only when a camera has a detector
        self._rsu_id = config.rsu_id
        self._camera_ids = tuple(camera.camera_id for camera in config.cameras)
        self._on_inbound = on_inbound
        self._handlers = handlers
        self._clock = clock
        self._lock = threading.Lock()
        self._state: Literal["new", "open", "closed"] = "new"
        self._session: zenoh.Session | None = None
        self._subscribers: list[zenoh.Subscriber[Any]] = []
        self._detection_publishers: dict[str, zenoh.Publisher] = {}
        self._queryables: list[zenoh.Queryable[Any]] = []
        self._threads: list[threading.Thread] = []
        self._token: zenoh.LivelinessToken | None = None
        self._callback_errors = 0

    @property
    def callback_errors(self) -> int:
        """How many times on_inbound raised (approximate: counted without a lock on Zenoh's threads)."""
        return self._callback_errors

    def open(self) -> None:
        """Open the session and declare everything; on failure undo what was declared and raise BusError."""
        with self._lock:
            if self._state != "new":
                raise BusError(f"bus of rsu {self._rsu_id} was already {self._state}")
            self._state = "open"
        zconf = self._config.zenoh
        try:
            config = session_config(zconf)
            self._session = session = open_session(config, effective_endpoints(config))
            on_sample = self._sample_callback()
            # Input keys are those of the recordings (daemon.recording), with wildcards.
            for key in (detections_key(self._rsu_id, "*"), ALL_V2X):
                self._subscribers.append(session.declare_subscriber(key, on_sample))
            if self._on_image is not None:
                on_image = self._sample_callback(self._on_image)
                images = image_key(self._rsu_id, "*")
                self._subscribers.append(session.declare_subscriber(images, on_image))
            answers: dict[Kind, tuple[str, Callable[[zenoh.Query], None]]] = {
                "calibration": (calibration_key(self._rsu_id, "*"), self._answer_calibration),
                "status": (status_key(self._rsu_id, "*"), self._answer_status),
                "trigger": (trigger_key(self._rsu_id, "*"), self._answer_trigger),
                "health": (health_key(self._rsu_id), self._answer_health),
            }
            for kind, (key, answer) in answers.items():
                queryable = session.declare_queryable(key)
                self._queryables.append(queryable)
                thread = threading.Thread(
                    target=self._serve, args=(queryable, key, answer), name=f"rsucal-bus-{kind}", daemon=True
                )
                thread.start()
                self._threads.append(thread)
            self._token = session.liveliness().declare_token(alive_key(self._rsu_id))
        except BusError:
            self.close()
            raise
        except zenoh.ZError as err:
            self.close()
            raise BusError(f"zenoh: declaring the bus of rsu {self._rsu_id}: {zenoh_message(err)}") from err
        log.info(
            "bus open: rsu %s, cameras %s, endpoints %s",
            self._rsu_id,
            ", ".join(self._camera_ids),
            ", ".join(effective_endpoints(config)) or "(none)",
        )

    def publish_detections(self, camera_id: str, payload: bytes) -> None:
        """Put a DetectionFrame the daemon's own detector made on `.../detections`, for other sessions only
        (Locality.REMOTE: our own subscriber must not ingest it a second time). Called from the camera's
        detector thread; a slow remote loses frames (congestion DROP) rather than holding the detector."""
        key = detections_key(self._rsu_id, camera_id)
        try:
            # The put too under the lock close() takes the publishers with: undeclaring a publisher while
            # another thread puts on it raises zenoh's "Already borrowed" (seen in bench.daemon's stop).
            with self._lock:
                session = self._session
                if session is None or self._state != "open":
                    raise BusError(f"bus of rsu {self._rsu_id} is not open")
                publisher = self._detection_publishers.get(camera_id)
                if publisher is None:
                    publisher = session.declare_publisher(
                        key,
                        encoding=JSON,
                        congestion_control=zenoh.CongestionControl.DROP,
                        allowed_destination=zenoh.Locality.REMOTE,
                    )
                    self._detection_publishers[camera_id] = publisher
                publisher.put(payload)
        except zenoh.ZError as err:
            raise BusError(f"put {key}: {zenoh_message(err)}") from err

    def publish_calibration(self, camera_id: str, payload: bytes) -> None:
        """Put a validated CalibrationResult (JSON) on `rsu/{rsu}/camera/{camera_id}/calibration`."""
        self._put_for_camera(camera_id, calibration_key(self._rsu_id, camera_id), payload, JSON)

    def publish_transform(self, camera_id: str, payload: bytes) -> None:
        """Put an accepted result as foxglove.FrameTransform (protobuf) on `.../calibration/transform`, so a
        live Foxglove session over Zenoh shows the camera (daemon.foxglove.frame_transform)."""
        self._put_for_camera(
            camera_id, transform_key(self._rsu_id, camera_id), payload, FRAME_TRANSFORM_ENCODING
        )

    def withdraw_calibration(self, camera_id: str) -> None:
        """Delete `.../calibration` and `.../calibration/transform`: the camera moved and its published result
        no longer describes it (subscribers get a DELETE sample; the queryable answers nothing)."""
        session = self._open_for_camera(camera_id)
        for key in (calibration_key(self._rsu_id, camera_id), transform_key(self._rsu_id, camera_id)):
            try:
                session.delete(key)
            except zenoh.ZError as err:
                raise BusError(f"delete {key}: {zenoh_message(err)}") from err

    def _open_for_camera(self, camera_id: str) -> zenoh.Session:
        """The open session, for a configured camera (KeyError, BusError otherwise)."""
        if camera_id not in self._camera_ids:
            raise KeyError(f"camera_id {camera_id!r} is not configured")
        session = self._session
        if session is None or self._state != "open":
            raise BusError(f"bus of rsu {self._rsu_id} is not open")
        return session

    def _put_for_camera(self, camera_id: str, key: str, payload: bytes, encoding: zenoh.Encoding) -> None:
        session = self._open_for_camera(camera_id)
        try:
            session.put(key, payload, encoding=encoding)
        except zenoh.ZError as err:
            raise BusError(f"put {key}: {zenoh_message(err)}") from err

    def close(self) -> None:
        """Undeclare (ends the serving loops), join the threads, close the session. Idempotent."""
        with self._lock:
            if self._state == "closed":
                return
            self._state = "closed"
        token, self._token = self._token, None
        with self._lock:
            publishers = list(self._detection_publishers.values())
            self._detection_publishers = {}
        entities: list[
            zenoh.LivelinessToken | zenoh.Subscriber[Any] | zenoh.Queryable[Any] | zenoh.Publisher
        ] = [
            *([token] if token is not None else []),
            *self._subscribers,
            *self._queryables,
            *publishers,
        ]
        self._subscribers, self._queryables = [], []
        for entity in entities:
            try:
                entity.undeclare()  # type: ignore[no-untyped-call]  # zenoh stubs lack -> None
            except zenoh.ZError as err:
                log.warning("undeclaring %s: %s", type(entity).__name__, zenoh_message(err))
        deadline = time.monotonic() + JOIN_BUDGET_S
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))
            if thread.is_alive():
                log.warning("thread %s still busy in a handler; leaving it behind", thread.name)
        self._threads = []
        session, self._session = self._session, None
        if session is not None:
            try:
                session.close()  # type: ignore[no-untyped-call]
            except zenoh.ZError as err:
                log.warning("closing the zenoh session: %s", zenoh_message(err))
        log.info("bus closed: rsu %s", self._rsu_id)

    def __enter__(self) -> Bus:
        self.open()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------ inbound

    def _sample_callback(self, target: OnInbound | None = None) -> Callable[[zenoh.Sample], None]:
        # Runs on Zenoh's callback thread for every sample: the least work possible (local names, no
        # attribute lookups on self), so ingest, not the bus, limits throughput.
        on_inbound = self._on_inbound if target is None else target
        now_ns = self._clock.now_ns

        def on_sample(sample: zenoh.Sample) -> None:
            received_ns = now_ns()
            try:
                on_inbound(str(sample.key_expr), sample.payload.to_bytes(), received_ns)
            except Exception:  # an exception must not reach Zenoh's thread; log the first, then sample
                self._callback_errors += 1
                if self._callback_errors == 1 or self._callback_errors % 10_000 == 0:
                    log.exception("on_inbound failed (%d times so far)", self._callback_errors)

        return on_sample

    # -------------------------------------------------------------------------------------- queryables

    def _serve(
        self, queryable: zenoh.Queryable[Any], key: str, answer: Callable[[zenoh.Query], None]
    ) -> None:
        """Answer queries until the queryable is undeclared; one failing query never ends the loop."""
        for query in queryable:
            try:
                with query:  # leaving the block finalises the query: the getter stops waiting at once
                    try:
                        answer(query)
                    except Exception as err:  # a handler bug: this query gets an error, the next is served
                        log.exception("answering %s (queryable %s) failed", query.key_expr, key)
                        query.reply_err(f"{query.key_expr}: internal error: {type(err).__name__}: {err}")
            except zenoh.ZError as err:  # the getter is gone or the session closing: nothing to answer
                log.warning("query %s on %s: %s", query.key_expr, key, zenoh_message(err))

    def _cameras_asked(self, query: zenoh.Query, key_of: Callable[[str, str], str]) -> list[tuple[str, str]]:
        """(camera_id, key) of the configured cameras a query names; an error reply for an unknown one."""
        asked = [
            (camera_id, key_of(self._rsu_id, camera_id))
            for camera_id in self._camera_ids
            if query.key_expr.intersects(key_of(self._rsu_id, camera_id))
        ]
        if not asked and not has_wildcard(str(query.key_expr)):
            query.reply_err(
                f"{query.key_expr}: no such camera on rsu {self._rsu_id} "
                f"(cameras: {', '.join(self._camera_ids)})"
            )
        return asked

    def _answer_status(self, query: zenoh.Query) -> None:
        for camera_id, key in self._cameras_asked(query, status_key):
            self._reply_each(query, key, functools.partial(self._handlers.status, camera_id))

    def _answer_calibration(self, query: zenoh.Query) -> None:
        for camera_id, key in self._cameras_asked(query, calibration_key):
            produce = functools.partial(self._handlers.calibration, camera_id)
            self._reply_each(query, key, produce, if_none=NO_CALIBRATION)

    def _answer_trigger(self, query: zenoh.Query) -> None:
        # A trigger starts a job: only an exact key does, never a fleet-wide `rsu/**` read.
        asked = self._cameras_asked(query, trigger_key)
        for camera_id, key in asked:
            if str(query.key_expr) != key:
                query.reply_err(f"{key}: not triggered: a trigger needs the exact key, not {query.key_expr}")
                continue
            self._reply_each(query, key, functools.partial(self._handlers.trigger, camera_id))

    def _answer_health(self, query: zenoh.Query) -> None:
        self._reply_each(query, health_key(self._rsu_id), self._handlers.health)

    @staticmethod
    def _reply_each(
        query: zenoh.Query, key: str, produce: Callable[[], bytes | None], if_none: str = "no answer"
    ) -> None:
        """Reply on `key` with what `produce` returns; its failure becomes an error reply for this key only,
        and None the error reply `if_none`."""
        try:
            payload = produce()
        except Exception as err:  # a handler bug: the other cameras of a wildcard query still get answers
            log.exception("handler for %s failed", key)
            query.reply_err(f"{key}: internal error: {type(err).__name__}: {err}")
            return
        if payload is None:
            query.reply_err(f"{key}: {if_none}")
        else:
            query.reply(key, payload, encoding=JSON)
