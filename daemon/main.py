"""`rsucal daemon`: start-up, the two threads that own the daemon's state, and the shutdown order.

Zenoh callbacks only enqueue (key, payload, received_ns). The ingest thread owns the decoder, the MCAP
recorder and the traversal trackers: it decodes, logs, counts traversals and, when a camera is due, flushes
the recording and hands a job to the job runner (daemon.pool, separate processes). The supervisor thread
owns the results: it applies each finished job's Decision (daemon.publication: what to store, publish and
remember), so every camera's record (CameraRuntime) changes there.
Queryable threads read immutable snapshots only. The camera's state is persisted after every job, so
shutdown has nothing left to save: close the Zenoh session (no new input, no more queries), stop the
detectors, let the ingest thread drain the inbox and finish the MCAP file, stop the supervisor, then the
job workers (a job still running is lost; its window is used again after a restart).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import queue
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType

import mcap
import numpy as np
import zenoh

from daemon import __version__
from daemon.access import check_access_rules
from daemon.bus import Bus, BusError, Handlers, session_config
from daemon.clock import Clock, SystemClock
from daemon.detector import DetectorWorker, ImageRouter, build_workers
from daemon.foxglove import frame_transform
from daemon.ingest import Counters, Decoder, DetectionsIn, Inbound, RejectLog, V2xIn
from daemon.jobs import JobOutcome, JobSpec, new_job_id
from daemon.keys import parse_detections_key
from daemon.pool import JobRunner
from daemon.publication import decide, storing_failed
from daemon.recording import RotatingRecorder, iter_v2x, list_recordings
from daemon.state import CameraState, StateStore, prepare_state_dir
from daemon.traversals import (
    Coverage,
    JobWindow,
    TrackerSnapshot,
    TraversalEvent,
    TraversalTracker,
    coverage_from_config,
    coverage_from_result,
)
from pipeline.camera import lens_model_note
from pipeline.frames import UtmFrame, utm_epsg_for
from schemas.config import DaemonConfig
from schemas.messages import V2xPosition
from schemas.results import (
    CalibrationResult,
    CalibrationStatus,
    DiskUsage,
    Health,
    JobSummary,
)

log = logging.getLogger(__name__)

# How often the ingest thread checks timers (flush, rotation, quiet periods) while messages keep coming, and
# how long it blocks on an empty inbox: both bound how late a due job starts (wall seconds).
TICK_S = 0.05
# On SIGTERM the whole shutdown must fit in 2 s; draining the inbox gets at most this much of it.
DRAIN_BUDGET_S = 0.5
# Files whose first message is this much older than a job window's start may still hold its data: a file
# is named after its first receive time and rotated at most every storage.rotate_s.
WINDOW_FILE_MARGIN_NS = 60_000_000_000
# Positions projected per pyproj call when replaying recordings (one call per message would dominate).
REPLAY_BATCH = 10_000
PRUNE_INTERVAL_S = 5.0
# Inbox items handled between two timer checks when a backlog is waiting.
INGEST_BATCH = 256
# A trigger query waits this long (wall) for the ingest thread to start its job, then answers "busy".
TRIGGER_TIMEOUT_S = 2.0


@dataclass(slots=True)
class CameraRuntime:
    """One camera's runtime record in the daemon.

    The tracker and the detection count belong to the ingest thread. The rest belongs to the supervisor
    (the job fields are set by the ingest thread when it starts a job) and is read by the queryable threads:
    all under Daemon._lock.
    """

    tracker: TraversalTracker
    state: CameraState
    current: CalibrationResult | None = None
    current_json: bytes | None = None  # current, as the queryable answers it
    running_job: str | None = None  # id of the job running now
    job_started_ns: int | None = None
    pending_window_start_ns: int | None = None  # of the running job: its recordings must stay
    job_counts: dict[str, int] = field(
        default_factory=lambda: {"jobs": 0, "accepted": 0, "refused": 0, "failed": 0}
    )
    detections: int = 0  # detection frames received

    def set_current(self, result: CalibrationResult, payload: bytes | None = None) -> None:
        self.current = result
        self.current_json = payload if payload is not None else result.model_dump_json().encode("utf-8")


@dataclass(frozen=True, slots=True)
class DaemonEvent:
    """Something an operator watching live wants to see (the demo prints these)."""

    # entered | left | discarded | job_started | published | verified | refused | failed | withdrawn
    kind: str
    camera_id: str
    text: str
    traversals: int = 0


EventSink = Callable[[DaemonEvent], None]


def config_hash(config: DaemonConfig) -> str:
    """Short stable hash of the validated config, stored in each result's provenance."""
    return hashlib.sha256(config.model_dump_json().encode("utf-8")).hexdigest()[:16]


def resolve_crs(config: DaemonConfig, store: StateStore) -> str | None:
    """UTM zone of the poses: configured, else at the first camera position, else a stored result's."""
    if config.crs is not None:
        return config.crs
    for camera in config.cameras:
        if camera.position is not None:
            return utm_epsg_for(camera.position.lat, camera.position.lon)
    for camera in config.cameras:
        current = store.load_current(camera.camera_id)
        if current is not None:
            return current.frame.crs
    return None


class Daemon:
    """The RSU service for one config. start() returns once it is on the bus; stop() within 2 s."""

    def __init__(
        self, config: DaemonConfig, clock: Clock | None = None, on_event: EventSink | None = None
    ) -> None:
        self.clock: Clock = clock or SystemClock()
        self.state_dir = Path(config.storage.state_dir)
        self.store = StateStore(self.state_dir)
        crs = resolve_crs(config, self.store)
        self.config = config if crs is None else config.model_copy(update={"crs": crs})
        self._on_event = on_event
        self._config_hash = config_hash(config)
        self._stop = threading.Event()
        self._inbox: queue.SimpleQueue[Inbound | Callable[[], None]] = queue.SimpleQueue()
        # Inbox accounting, shared by Zenoh's callback threads (add) and the ingest thread (remove).
        self._inbox_lock = threading.Lock()
        self._inbox_items = 0
        self._inbox_bytes = 0
        self._dropped = 0

        self.counters = Counters()
        self.rejects = RejectLog(self.counters, self.config.ingest.warn_interval_s, self.clock)
        self.decoder = Decoder(self.config, self.clock, self.counters, self.rejects)
        self.recordings_dir = self.state_dir / "recordings"
        self.recorder = RotatingRecorder(
            self.recordings_dir, self.config.rsu_id, self.config.storage, self.clock
        )
        self._frame = UtmFrame(crs) if crs is not None else None
        # One record per camera, made by _recover(); see CameraRuntime for which thread owns what.
        self._lock = threading.Lock()
        self._cameras: dict[str, CameraRuntime] = {}
        self._finished: queue.SimpleQueue[tuple[JobSpec, Future[JobOutcome]]] = queue.SimpleQueue()

        self._runner: JobRunner | None = None
        self._bus: Bus | None = None
        self._detectors: dict[str, DetectorWorker] = {}
        self._threads: list[threading.Thread] = []
        self.started_at_ns = self.clock.now_ns()
        self._next_prune = 0.0
        self._failure: str | None = None

    # ------------------------------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Recover state, start job workers and threads, then go on the bus (BusError on a bad endpoint;
        AccessControlError when a secure deployment's access rules do not match the config)."""
        prepare_state_dir(self.state_dir)  # InputError (exit 2) when unusable: a configuration error
        if check_access_rules(self.config):
            log.info("access rules match the config: each camera and vehicle may publish only its own keys")
        # Detector models load first: a bad one is a configuration error, before anything starts.
        self._detectors = build_workers(self.config, self._on_detected, self.counters, self.clock)
        self._recover()
        self._runner = JobRunner(self.config.jobs.max_parallel)
        self._threads = [
            threading.Thread(
                target=self._guarded, args=(self._ingest_loop,), name="rsucal-ingest", daemon=True
            ),
            threading.Thread(
                target=self._guarded, args=(self._supervise_loop,), name="rsucal-supervisor", daemon=True
            ),
        ]
        for thread in self._threads:
            thread.start()
        for worker in self._detectors.values():
            worker.start()
        on_image = None
        if self._detectors:
            image_rejects = RejectLog(self.counters, self.config.ingest.warn_interval_s, self.clock)
            on_image = ImageRouter(self.config.rsu_id, self._detectors, self.counters, image_rejects)
        handlers = Handlers(
            calibration=self._answer_calibration,
            status=self._answer_status,
            trigger=self._answer_trigger,
            health=self._answer_health,
        )
        self._bus = Bus(self.config, self._on_inbound, handlers, self.clock, on_image=on_image)
        try:
            self._bus.open()
        except BaseException:
            self.stop()
            raise
        effective = session_config(self.config.zenoh)
        log.info(
            "rsucal %s on the bus as rsu %s: %d camera(s), zenoh %s, listen %s, connect %s",
            __version__,
            self.config.rsu_id,
            len(self.config.cameras),
            json.loads(effective.get_json("mode")),
            effective.get_json("listen/endpoints"),
            effective.get_json("connect/endpoints"),
        )

    def stop(self) -> None:
        """Close the bus, stop the detectors, drain the inbox, finish the MCAP file, stop the job workers
        (the module docstring says why in this order). Idempotent."""
        if self._bus is not None:
            self._bus.close()  # no new input, no more queries
        # The detectors' frames go through the inbox: stop them before ingest drains it.
        for worker in self._detectors.values():
            worker.stop(timeout_s=DRAIN_BUDGET_S)
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=DRAIN_BUDGET_S + 0.5)
        self._threads = []
        # The ingest thread closes the recorder on exit; if it never ran (start failed early) do it here.
        self.recorder.close()
        if self._runner is not None:
            self._runner.shutdown(timeout_s=0.5)
            self._runner = None
        self._bus = None

    def __enter__(self) -> Daemon:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def failure(self) -> str | None:
        """Why one of the daemon's own threads died (the process must then exit non-zero), or None."""
        if self._failure is None:
            for camera_id, worker in self._detectors.items():
                if worker.failure is not None:
                    return f"detector of camera {camera_id}: {worker.failure}"
        return self._failure

    def _guarded(self, loop: Callable[[], None]) -> None:
        """Run a thread's loop; if it dies, say why and stop the daemon rather than run on half-alive (a
        supervisor like systemd restarts it, and the recordings and state are intact)."""
        try:
            loop()
        except BaseException as err:
            self._failure = f"{threading.current_thread().name}: {err!r}"
            log.critical(
                "thread %s died; stopping the daemon", threading.current_thread().name, exc_info=True
            )
            self._stop.set()

    # ------------------------------------------------------------------------------------------ recovery

    def _recover(self) -> None:
        """Load the latest validated results and rebuild traversal counts from the open window's MCAP."""
        now_ns = self.clock.now_ns()
        for camera in self.config.cameras:
            camera_id = camera.camera_id
            lens = lens_model_note(camera.intrinsics)
            if lens is not None:
                log.warning("camera %s: %s", camera_id, lens)
            current = self.store.load_current(camera_id)
            state = self.store.load_camera_state(camera_id) or CameraState()
            if current is not None and current.result_id == state.withdrawn_result_id:
                # Withdrawn, and the state saved, but a crash came before current.json was removed.
                log.warning(
                    "camera %s: result %s was withdrawn; removing its current.json",
                    camera_id,
                    current.result_id,
                )
                self._remove_current(camera_id)
                current = None
            if current is not None and state.current_result_id != current.result_id:
                # camera_state.json lost or older than current.json (a crash between the two writes, or a
                # state dir seeded by hand): the stored result is what the queryable answers, so say so.
                state = state.model_copy(
                    update={
                        "current_result_id": current.result_id,
                        "verified_at_ns": state.verified_at_ns or current.created_at_ns,
                    }
                )
            if current is None and state.current_result_id is not None:
                # current.json lost (removed or damaged beyond what the history can replace).
                state = state.model_copy(update={"current_result_id": None, "verified_at_ns": None})
            coverage = coverage_from_config(camera, self._frame) if self._frame is not None else None
            if coverage is None and current is not None:
                coverage = coverage_from_result(current)
            runtime = CameraRuntime(TraversalTracker(camera_id, coverage, self.config.trigger), state)
            if current is not None:
                runtime.set_current(current)
            with self._lock:
                self._cameras[camera_id] = runtime
        replayed = self._replay_traversals(now_ns)
        for camera_id, runtime in self._cameras.items():
            tracker = runtime.tracker
            if runtime.state.used_until_ns is not None:
                tracker.restore_used_until(runtime.state.used_until_ns)
            if runtime.state.not_before_ns is not None:
                tracker.set_not_before(runtime.state.not_before_ns)
            tracker.tick(now_ns)
            log.info(
                "camera %s: %d traversal(s) in the open window after replaying %d V2X message(s)%s",
                camera_id,
                tracker.snapshot().traversals,
                replayed,
                "" if runtime.current is None else f"; current result {runtime.current.result_id}",
            )

    def tracker_snapshot(self, camera_id: str) -> TrackerSnapshot:
        """The camera's traversal counts as of the ingest thread's last change (an immutable object)."""
        return self._cameras[camera_id].tracker.snapshot()

    def _replay_traversals(self, now_ns: int, trackers: list[TraversalTracker] | None = None) -> int:
        """Feed the open window's recorded calibration-vehicle positions through the trackers again."""
        if self._frame is None:
            return 0
        targets = [c.tracker for c in self._cameras.values()] if trackers is None else trackers
        since_ns = now_ns - int(self.config.trigger.max_window_s * 1e9) - WINDOW_FILE_MARGIN_NS
        files = [f.path for f in list_recordings(self.recordings_dir, self.config.rsu_id)]
        stations = {vehicle.station_id for vehicle in self.config.vehicles}
        replayed = 0
        batch: list[tuple[V2xPosition, int]] = []
        for item in iter_v2x(files, stations, since_ns):
            batch.append(item)
            if len(batch) >= REPLAY_BATCH:
                replayed += self._replay_batch(batch, targets)
                batch = []
        return replayed + self._replay_batch(batch, targets)

    def _replay_batch(self, batch: list[tuple[V2xPosition, int]], trackers: list[TraversalTracker]) -> int:
        if not batch or self._frame is None:
            return 0
        lat = np.array([message.lat for message, _ in batch])
        lon = np.array([message.lon for message, _ in batch])
        with np.errstate(all="ignore"):
            east, north = self._frame.to_utm(lat, lon)
        replayed = 0
        for (message, received_ns), x, y in zip(batch, east.tolist(), north.tolist(), strict=True):
            if not (math.isfinite(x) and math.isfinite(y)):
                continue
            for tracker in trackers:
                tracker.observe(message.station_id, message.stamp_ns, x, y, received_ns)
            replayed += 1
        return replayed

    # ------------------------------------------------------------------------------------------ bus side

    def _on_inbound(self, key: str, payload: bytes, received_ns: int) -> None:
        """Zenoh's threads: enqueue only. A full inbox (messages or bytes) drops the newest and counts it."""
        size = len(payload)
        with self._inbox_lock:
            if (
                self._inbox_items >= self.config.ingest.queue_size
                or self._inbox_bytes + size > self.config.ingest.queue_bytes
            ):
                self._dropped += 1
                return
            self._inbox_items += 1
            self._inbox_bytes += size
        self._inbox.put(Inbound(key, payload, received_ns))

    def _on_detected(self, key: str, payload: bytes, received_ns: int) -> None:
        """A detector thread's DetectionFrame: into the inbox like a bus message, and on the bus for other
        sessions (a live viewer, another consumer); a failed put is counted, the frame is kept anyway."""
        self._on_inbound(key, payload, received_ns)
        bus = self._bus
        if bus is None:
            return
        parsed = parse_detections_key(key)
        if parsed is None:
            return
        try:
            bus.publish_detections(parsed[1], payload)
        except BusError as err:
            self.counters.add("images.publish_failed")
            log.debug("publishing a detected frame: %s", err)

    # ------------------------------------------------------------------------------------------ ingest thread

    def _ingest_loop(self) -> None:
        next_tick = 0.0
        try:
            while not self._stop.is_set():
                try:
                    self._handle(self._inbox.get(timeout=TICK_S))
                    # Then whatever else is waiting, without blocking: one timer check per batch.
                    for _ in range(INGEST_BATCH):
                        self._handle(self._inbox.get_nowait())
                except queue.Empty:
                    pass
                now = time.monotonic()
                if now >= next_tick:
                    next_tick = now + TICK_S
                    self._tick()
            # Drain what arrived before the bus closed, within the shutdown budget.
            deadline = time.monotonic() + DRAIN_BUDGET_S
            while time.monotonic() < deadline:
                try:
                    self._handle(self._inbox.get_nowait())
                except queue.Empty:
                    break
        finally:
            self.recorder.close()

    def _handle(self, item: Inbound | Callable[[], None]) -> None:
        if not isinstance(item, Inbound):
            item()  # a control action posted by another thread, run where the state lives
            return
        with self._inbox_lock:
            self._inbox_items -= 1
            self._inbox_bytes -= len(item.payload)
        decoded = self.decoder.decode(item)
        if decoded is None:
            return
        if isinstance(decoded, DetectionsIn):
            self.recorder.write_detections(
                decoded.camera_id, decoded.stamp_ns, decoded.received_ns, decoded.payload, decoded.box_fields
            )
            self._cameras[decoded.camera_id].detections += 1
            return
        assert isinstance(decoded, V2xIn)
        self.recorder.write_v2x(
            decoded.station_id,
            decoded.message.stamp_ns,
            decoded.received_ns,
            decoded.payload,
            decoded.message,
            is_vehicle=decoded.utm is not None,
        )
        if decoded.utm is None:
            return
        if self._frame is None:
            self._frame = self.decoder.frame
        east, north = decoded.utm
        stamp_ns = decoded.message.stamp_ns
        for runtime in self._cameras.values():
            events = runtime.tracker.observe(decoded.station_id, stamp_ns, east, north, decoded.received_ns)
            if events:
                self._emit_all(events)

    def _tick(self) -> None:
        now_ns = self.clock.now_ns()
        self.recorder.tick()
        self.rejects.tick()
        for camera_id, runtime in self._cameras.items():
            self._emit_all(runtime.tracker.tick(now_ns))
            with self._lock:
                busy, calibrated = runtime.running_job is not None, runtime.current is not None
                not_before_ns = runtime.state.not_before_ns
            if not_before_ns is not None and not_before_ns != runtime.tracker.not_before_ns:
                # Set with the withdrawal, under the lock that cleared `current`: no window of this tick
                # reaches back before the move.
                runtime.tracker.set_not_before(not_before_ns)
            if not busy:
                # A calibrated camera is re-verified on new drive-pasts alone (daemon.traversals).
                window = runtime.tracker.due(now_ns, new_only=calibrated)
                if window is not None:
                    self._start_job(camera_id, window, new_job_id(camera_id, now_ns))
        self._prune(now_ns)

    def _prune(self, now_ns: int) -> None:
        # prune() lists and stats the recordings directory: every few seconds is plenty.
        if time.monotonic() < self._next_prune:
            return
        self._next_prune = time.monotonic() + PRUNE_INTERVAL_S
        with self._lock:
            pending = [c.pending_window_start_ns for c in self._cameras.values()]
        oldest_ns = min(
            [
                *(c.tracker.snapshot().window_start_ns or now_ns for c in self._cameras.values()),
                *(start_ns for start_ns in pending if start_ns is not None),
            ],
            default=now_ns,
        )
        pruned = self.recorder.prune(keep_after_ns=oldest_ns - WINDOW_FILE_MARGIN_NS)
        if pruned:
            self.counters.add("recordings.pruned", len(pruned))

    def _emit_all(self, events: list[TraversalEvent]) -> None:
        for event in events:
            text = {
                "entered": f"vehicle {event.station_id} entered the view",
                "left": f"vehicle {event.station_id} left: traversal {event.traversals} counted",
                "discarded": f"vehicle {event.station_id} visit too short, not counted",
            }.get(event.kind, event.kind)
            log.info("camera %s: %s", event.camera_id, text)
            self._emit(DaemonEvent(event.kind, event.camera_id, text, event.traversals))

    def _start_job(self, camera_id: str, window: JobWindow, job_id: str) -> bool:
        """Ingest thread: make the window's data readable on disk, then hand the job to a worker; whether it
        started."""
        assert self._runner is not None
        self.recorder.flush()
        now_ns = self.clock.now_ns()
        spec = self.job_spec(camera_id, window, job_id, now_ns)
        if spec is None:
            log.error("camera %s: job %s has no calibration vehicle or no UTM zone yet", camera_id, job_id)
            return False
        runtime = self._cameras[camera_id]
        runtime.tracker.mark_used(window)
        with self._lock:
            runtime.running_job = job_id
            runtime.job_started_ns = now_ns
            runtime.pending_window_start_ns = window.start_ns
            runtime.job_counts["jobs"] += 1
        future = self._runner.submit(spec)
        future.add_done_callback(lambda done, spec=spec: self._finished.put((spec, done)))  # type: ignore[misc]
        text = f"job {job_id} started on {len(window.traversals)} traversal(s)"
        log.info("camera %s: %s", camera_id, text)
        self._emit(DaemonEvent("job_started", camera_id, text, len(window.traversals)))
        return True

    def job_spec(self, camera_id: str, window: JobWindow, job_id: str, now_ns: int) -> JobSpec | None:
        """What a job of this camera on `window` is given (the recordings on disk now); None without a
        calibration vehicle for the window's station or a UTM zone."""
        camera = self.config.camera(camera_id)
        vehicle = self.config.vehicle(window.station_id)
        if vehicle is None or self.config.crs is None:
            return None
        # Files are named by the receive time of their first message, windows are producer stamps. Data can
        # arrive late (a detector's backlog after a link outage), so a file is ruled out only when all its
        # data was received before the window began (its successor started before), never by the end.
        recordings = list_recordings(self.recordings_dir, self.config.rsu_id)
        files = [
            str(f.path)
            for f, following in zip(recordings, [*recordings[1:], None], strict=True)
            if following is None or following.start_ns >= window.start_ns - WINDOW_FILE_MARGIN_NS
        ]
        with self._lock:
            estimated_offset_ns = self._cameras[camera_id].state.time_offset_ns
        return JobSpec(
            job_id=job_id,
            rsu_id=self.config.rsu_id,
            camera_id=camera_id,
            intrinsics=camera.intrinsics,
            vehicle=vehicle.profile,
            station_id=window.station_id,
            # The camera's last accepted estimate is the prior; the configured offset only until there is one.
            time_offset_ns=vehicle.time_offset_ns if estimated_offset_ns is None else estimated_offset_ns,
            crs=self.config.crs,
            recordings=tuple(files),
            window_start_ns=window.start_ns,
            window_end_ns=window.end_ns,
            gates=self.config.gates,
            seed=self.config.jobs.seed,
            track_workers=self.config.jobs.track_workers,
            created_at_ns=now_ns,
            config_hash=self._config_hash,
            timeout_s=self.config.jobs.timeout_s,
            labels=None if camera.labels is None else dict(camera.labels),
            report_dir=str(self.store.history_dir(camera_id)),
        )

    def _remove_current(self, camera_id: str) -> None:
        try:
            self.store.withdraw_current(camera_id)
        except OSError as err:  # withdrawn in memory and on the bus; the state makes the restart remove it
            log.error("camera %s: removing current.json failed: %s", camera_id, err)

    # ------------------------------------------------------------------------------------------ supervisor

    def _supervise_loop(self) -> None:
        while not self._stop.is_set():
            try:
                spec, future = self._finished.get(timeout=TICK_S)
            except queue.Empty:
                continue
            try:
                outcome = future.result()
            except Exception as err:  # the worker process died (killed, out of memory): the job failed
                outcome = JobOutcome(
                    spec.job_id, spec.camera_id, None, f"worker failed: {err!r}", 0.0, 0, 0, ()
                )
            self._finish_job(spec, outcome)

    def _finish_job(self, spec: JobSpec, outcome: JobOutcome) -> None:
        """Supervisor thread: apply the publication policy's Decision (daemon.publication) for a finished job:
        store the result, save the camera's state, publish, update the runtime record, tell observers."""
        camera_id = spec.camera_id
        runtime = self._cameras[camera_id]
        now_ns = self.clock.now_ns()
        with self._lock:
            started_ns = runtime.job_started_ns or spec.created_at_ns
            state = runtime.state
            current = runtime.current
        decision = decide(
            outcome,
            current,
            state,
            self.config.change,
            window_end_ns=spec.window_end_ns,
            started_ns=started_ns,
            now_ns=now_ns,
            window_start_ns=spec.window_start_ns,
        )
        for warning in decision.warnings:
            log.warning("camera %s: %s", camera_id, warning)
        if decision.result is not None:
            try:
                self.store.save_result(decision.result, current=decision.publish)
            except OSError as err:
                reason = f"result {decision.result.result_id} could not be stored: {err}"
                log.error("camera %s: job %s: %s", camera_id, spec.job_id, reason)
                decision = storing_failed(decision, state, reason)
        try:
            self.store.save_camera_state(camera_id, decision.state)
        except OSError as err:  # the state in memory still answers queries; the next save may succeed
            log.error("camera %s: saving the camera state failed: %s", camera_id, err)
        if decision.withdraw:
            # After the state, which names the withdrawn result and the move's not_before_ns: a crash in
            # between leaves a current.json that the restart recognises as withdrawn (_recover).
            self._remove_current(camera_id)
        storage = self.config.storage
        try:
            # After the state names the new current result: pruning never deletes the current one.
            self.store.prune_history(
                camera_id,
                keep=storage.history_keep,
                created_before_ns=now_ns - int(storage.history_max_age_s * 1e9),
            )
        except OSError as err:  # a full or read-only disk must not stop the supervisor; retried next job
            log.error("camera %s: pruning the result history failed: %s", camera_id, err)
        result = decision.result
        payload = result.model_dump_json().encode("utf-8") if decision.publish and result else None
        with self._lock:
            runtime.state = decision.state
            runtime.running_job = None
            runtime.pending_window_start_ns = None
            runtime.job_counts[decision.kind] += 1
            if payload is not None and result is not None:
                runtime.set_current(result, payload)
            if decision.withdraw:
                runtime.current = runtime.current_json = None
        if decision.withdraw and self._bus is not None:
            self._bus.withdraw_calibration(camera_id)  # the tracker learns not_before_ns on its next tick
        if result is not None:
            # The recorder belongs to the ingest thread: the result channels are written there.
            recorded = result
            self._inbox.put(lambda: self.recorder.write_result(recorded, self.clock.now_ns()))
        if decision.kind == "accepted" and outcome.vehicle_boxes:
            # Now that the fit says which boxes were the calibration vehicle's: a Foxglove overlay of them.
            boxes = outcome.vehicle_boxes

            def record_vehicle_boxes() -> None:
                self.recorder.write_vehicle_boxes(camera_id, boxes, self.clock.now_ns())

            self._inbox.put(record_vehicle_boxes)
        if payload is not None and result is not None:
            if self._bus is not None:
                self._bus.publish_calibration(camera_id, payload)
                self._bus.publish_transform(camera_id, frame_transform(result))
            if runtime.tracker.snapshot().learning:
                learned = coverage_from_result(result)
                self._inbox.put(lambda: self._learn_coverage(camera_id, learned))
        duration_s = max(0.0, (now_ns - started_ns) / 1e9)
        log.info("camera %s: job %s %s (%.1f s)", camera_id, spec.job_id, decision.text, duration_s)
        self._emit(DaemonEvent(decision.event, camera_id, f"job {spec.job_id} {decision.text}"))

    def _learn_coverage(self, camera_id: str, coverage: Coverage) -> None:
        """Ingest thread: count this camera's traversals where the calibrated view sees the vehicle from now
        on; the open window is recounted at once (its traversals stay used by the job that learned it)."""
        tracker = self._cameras[camera_id].tracker
        tracker.set_coverage(coverage)
        self.recorder.flush()
        replayed = self._replay_traversals(self.clock.now_ns(), [tracker])
        log.info(
            "camera %s: coverage learned from the calibration; %d positions recounted", camera_id, replayed
        )

    # ------------------------------------------------------------------------------------------ queries

    def _answer_calibration(self, camera_id: str) -> bytes | None:
        runtime = self._cameras.get(camera_id)
        if runtime is None:
            return None
        with self._lock:
            return runtime.current_json

    def status(self, camera_id: str) -> CalibrationStatus:
        """The camera's status as `.../calibration/status` answers it."""
        runtime = self._cameras[camera_id]
        with self._lock:
            state = runtime.state
            running = runtime.running_job
            started_ns = runtime.job_started_ns
            has_current = runtime.current is not None
            counts = dict(runtime.job_counts)
            detections = runtime.detections
        # Trackers are owned by the ingest thread; their snapshots are immutable and swapped whole.
        view = runtime.tracker.snapshot()
        last_job = state.last_job
        if running is not None and started_ns is not None:
            last_job = JobSummary(job_id=running, started_ns=started_ns)
            status_state = "calibrating"
        elif has_current:
            status_state = "calibrated"
        elif view.traversals > 0 or view.inside or (view.learning and view.learn_data_s > 0):
            status_state = "collecting"
        elif state.last_job is not None and state.last_job.verdict is not None:
            status_state = "refused"
        else:
            status_state = "idle"
        counters = {
            "detections": detections,
            **{f"jobs.{name}" if name != "jobs" else "jobs": value for name, value in counts.items()},
        }
        return CalibrationStatus(
            rsu_id=self.config.rsu_id,
            camera_id=camera_id,
            state=status_state,
            # A calibrated camera's next job is a re-verification on new drive-pasts only: count those.
            traversals=view.new_traversals if has_current else view.traversals,
            traversals_needed=self.config.trigger.min_traversals,
            last_job=last_job,
            current_result_id=state.current_result_id,
            verified_at_ns=state.verified_at_ns,
            time_offset_ns=state.time_offset_ns,
            time_offset_std_ns=state.time_offset_std_ns,
            counters=counters,
            updated_at_ns=self.clock.now_ns(),
        )

    def _answer_status(self, camera_id: str) -> bytes:
        return self.status(camera_id).model_dump_json().encode("utf-8")

    def trigger(self, camera_id: str, timeout_s: float = TRIGGER_TIMEOUT_S) -> tuple[str | None, str]:
        """Start a job now on the camera's open window; (job id, "") once it started, else (None, reason)."""
        self.config.camera(camera_id)
        runtime = self._cameras[camera_id]
        with self._lock:
            running = runtime.running_job
        if running is not None:
            return None, f"job {running} is already running"
        answer: Future[tuple[str | None, str]] = Future()

        def start_forced() -> None:
            # On the ingest thread, which starts every job: the check and the start cannot interleave
            # with another trigger or a due job.
            if not answer.set_running_or_notify_cancel():
                return  # the caller gave up waiting and was told so
            with self._lock:
                running, calibrated = runtime.running_job, runtime.current is not None
            if running is not None:
                answer.set_result((None, f"job {running} is already running"))
                return
            now_ns = self.clock.now_ns()
            window = runtime.tracker.force_window(now_ns, new_only=calibrated)
            if window is None:
                reason = "no calibration-vehicle data in the window"
                log.warning("camera %s: trigger: %s", camera_id, reason)
                self._emit(DaemonEvent("refused", camera_id, f"trigger: {reason}"))
                answer.set_result((None, reason))
                return
            job_id = new_job_id(camera_id, now_ns)
            if self._start_job(camera_id, window, job_id):
                answer.set_result((job_id, ""))
            else:
                answer.set_result((None, "no calibration vehicle or no UTM zone for the window"))

        self._inbox.put(start_forced)
        try:
            return answer.result(timeout=timeout_s)
        except TimeoutError:
            if answer.cancel():
                return None, f"the daemon is busy: no job started within {timeout_s:g} s, try again"
            return answer.result()  # it started meanwhile: the start itself is quick

    def _answer_trigger(self, camera_id: str) -> bytes:
        job_id, reason = self.trigger(camera_id)
        return json.dumps(
            {"camera_id": camera_id, "job_id": job_id, "accepted": job_id is not None, "reason": reason}
        ).encode("utf-8")

    def health(self) -> Health:
        """What `rsu/{rsu}/health` answers."""
        now_ns = self.clock.now_ns()
        counters = self.counters.snapshot()
        with self._inbox_lock:
            counters["inbox.dropped"] = self._dropped
            inbox_depth = self._inbox_items
        counters["recordings.messages_written"] = self.recorder.messages_written
        counters["recordings.messages_dropped"] = self.recorder.messages_dropped
        counters["recordings.files_written"] = self.recorder.files_written
        bus = self._bus
        if bus is not None:
            counters["bus.callback_errors"] = bus.callback_errors  # Zenoh callbacks that raised (a bug)
        files = list_recordings(self.recordings_dir, self.config.rsu_id)
        try:
            free_bytes = shutil.disk_usage(self.state_dir).free
        except OSError:
            free_bytes = 0
        with self._lock:
            jobs_running = sum(c.running_job is not None for c in self._cameras.values())
        return Health(
            rsu_id=self.config.rsu_id,
            started_at_ns=self.started_at_ns,
            updated_at_ns=now_ns,
            uptime_s=max(0.0, (now_ns - self.started_at_ns) / 1e9),
            cameras=[camera.camera_id for camera in self.config.cameras],
            counters=counters,
            inbox_depth=inbox_depth,
            jobs_running=jobs_running,
            disk=DiskUsage(
                state_dir=str(self.state_dir),
                free_bytes=free_bytes,
                recordings_bytes=sum(f.size_bytes for f in files),
                recordings_files=len(files),
            ),
            versions={
                "rsucal": __version__,
                "python": sys.version.split()[0],
                "zenoh": getattr(zenoh, "__version__", "1.x"),
                "mcap": mcap.__version__,
            },
        )

    def _answer_health(self) -> bytes:
        return self.health().model_dump_json().encode("utf-8")

    def _emit(self, event: DaemonEvent) -> None:
        if self._on_event is not None:
            try:
                self._on_event(event)
            except Exception:  # an observer's bug must not stop the daemon
                log.exception("event observer failed on %s", event)

    # ------------------------------------------------------------------------------------------ waiting

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until stop is requested; True if it was."""
        return self._stop.wait(timeout_s)


def run_daemon(config: DaemonConfig) -> int:
    """Run until SIGTERM/SIGINT; exit code 0 on a clean stop, 1 when one of the daemon's threads died."""
    daemon = Daemon(config)
    stop_requested = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        log.info("signal %d: shutting down", signum)
        stop_requested.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        daemon.start()
        while not stop_requested.wait(0.2):
            if daemon.failure is not None:
                break
    finally:
        started = time.monotonic()
        daemon.stop()
        log.info("stopped in %.2f s", time.monotonic() - started)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if daemon.failure is not None:
        log.error("exiting after a fatal error in %s", daemon.failure)
        return 1
    return 0
