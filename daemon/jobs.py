"""Calibration jobs: one camera's data window read from the MCAP recordings, calibrated in a worker process.

The daemon builds a JobSpec (plain, picklable values) and hands it to a JobRunner, a pool of spawned worker
processes started and warmed (pipeline imported) when the daemon starts. In the worker, run_job reads the
window, converts the calibration vehicle's V2X positions to UTM poses and makes the same calibrate() call
as `rsucal calibrate --mcap`; it never raises: every failure becomes JobOutcome.error. compare_results
tells whether a new accepted result means the camera moved.
"""

from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing
import os
import signal
import threading
import time
import traceback
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from multiprocessing.process import BaseProcess
from pathlib import Path
from types import FrameType

import numpy as np
from pydantic import ValidationError

from daemon.offline import collapse_counted_notes
from daemon.recording import MCAP_MAGIC, read_window
from daemon.workers import track_pool
from pipeline.calibrate import SOFTWARE_VERSION, CalibrationInputs, PipelineParams, calibrate
from pipeline.errors import RsucalError
from pipeline.frames import UtmFrame, poses_from_v2x
from pipeline.validation import ValidationGates
from schemas.common import CameraIntrinsics, VehicleProfile, describe_validation_error
from schemas.config import ChangeConfig, GatesConfig
from schemas.results import CalibrationResult, ChangeInfo, Provenance

log = logging.getLogger(__name__)

WARM_TIMEOUT_S = 120.0  # spawning a worker and importing the pipeline takes ~2 s; a slow SD card, more
# After SIGTERM a worker stops its own track-pool processes and exits; this long, then SIGKILL for all.
TERMINATE_GRACE_S = 0.5
_TRACEBACK_LINES = 6


@dataclass(frozen=True, slots=True)
class JobSpec:
    """Everything a worker needs for one job; plain values (pickled to a spawned process)."""

    job_id: str
    rsu_id: str
    camera_id: str
    intrinsics: CameraIntrinsics
    vehicle: VehicleProfile
    station_id: int
    time_offset_ns: int  # vehicle clock minus camera clock
    crs: str  # UTM zone of the poses and the result, e.g. EPSG:32632
    recordings: tuple[str, ...]  # MCAP files that may hold the window's messages
    window_start_ns: int  # producer stamps, inclusive
    window_end_ns: int
    gates: GatesConfig
    seed: int
    track_workers: int
    created_at_ns: int  # the result's created_at_ns (our clock, when the job was started)
    config_hash: str  # of the daemon's config, stored in the result's provenance


@dataclass(frozen=True, slots=True)
class JobOutcome:
    """What a job returns: a result (accepted or refused) as JSON, or an error; never both."""

    job_id: str
    camera_id: str
    result_json: str | None
    error: str | None
    duration_s: float
    detections: int  # detection frames of the camera in the window
    poses: int  # calibration-vehicle poses in the window
    stage_notes: tuple[str, ...]  # window reading and each stage's kept/discarded, for logs and status


# ---------------------------------------------------------------------------------------------- the job


def pipeline_params(gates: GatesConfig) -> PipelineParams:
    """The pipeline's parameters for the daemon: defaults, with the configured validation gates."""
    # Same field names on both sides (schemas.config documents them); a field added to one only fails here.
    return PipelineParams(gates=ValidationGates(**gates.model_dump()))


def new_job_id(camera_id: str, now_ns: int) -> str:
    """A readable, sortable job id: '{camera_id}-{now_ns:019d}'."""
    return f"{camera_id}-{now_ns:019d}"


def run_job(spec: JobSpec) -> JobOutcome:
    """Read the window, build the calibrate() inputs, calibrate; in a worker process. Never raises.

    Outcomes: a result (accepted, or refused with reasons) whenever at least one recording could be read,
    including a window with too little data (calibrate refuses it: "no calibration-vehicle poses in the data
    window", "no detections from this camera ...", too few traversals); unreadable files among readable ones
    are stage notes. `error` when the job could not produce an answer at all: no recordings named, none
    readable, a bad spec (crs, ids, window), or an unexpected failure (its traceback in the notes).
    """
    started = time.monotonic()
    notes: list[str] = []
    detections = poses = 0

    def failed(message: str) -> JobOutcome:
        return JobOutcome(
            spec.job_id,
            spec.camera_id,
            None,
            message,
            time.monotonic() - started,
            detections,
            poses,
            tuple(notes),
        )

    try:
        if spec.window_end_ns < spec.window_start_ns:
            return failed(
                f"window_end_ns = {spec.window_end_ns} is before window_start_ns = {spec.window_start_ns}"
            )
        if not spec.recordings:
            return failed("no recordings cover the window: nothing to read")
        # The reader recovers what it can and only describes the rest; whether that is enough is decided
        # here: with no usable recording at all the answer is an error, not a refusal for lack of data.
        unusable = [problem for problem in map(_unusable_recording, spec.recordings) if problem]
        if len(unusable) == len(spec.recordings):
            return failed("no recording of the window could be read: " + "; ".join(unusable))
        # Switch to daemon.recording.read_window once it exists: same arguments, same fields.
        window = read_window(
            [Path(p) for p in spec.recordings],
            spec.rsu_id,
            spec.camera_id,
            {spec.station_id},
            spec.window_start_ns,
            spec.window_end_ns,
        )
        notes.extend(window.problems)
        if window.rejected:
            notes.append(f"{window.rejected} message(s) in the recordings failed validation and were skipped")
        vehicle_poses, unrepresentable = poses_from_v2x(window.v2x, UtmFrame(spec.crs))
        detections, poses = len(window.detections), len(vehicle_poses)
        notes.append(
            f"window: {detections} detection frame(s) of camera {spec.camera_id}, {poses} pose(s) of "
            f"station {spec.station_id} from {len(spec.recordings)} recording(s)"
        )
        if unrepresentable:
            notes.append(f"{unrepresentable} V2X position(s) not representable in {spec.crs}: skipped")
        inputs = CalibrationInputs(
            rsu_id=spec.rsu_id,
            camera_id=spec.camera_id,
            intrinsics=spec.intrinsics,
            vehicle=spec.vehicle,
            detections=window.detections,
            poses=vehicle_poses,
            crs=spec.crs,
            time_offset_ns=spec.time_offset_ns,
            station_id=spec.station_id,
            recordings=spec.recordings,
        )
        # Forking the track pool from this worker is safe: a spawned pool worker runs no other thread. With
        # nothing to fit, calibrate() refuses at once and a pool would only cost its start-up.
        workers = spec.track_workers if detections and poses else 1
        with track_pool(workers) as map_fn:
            outcome = calibrate(
                inputs,
                pipeline_params(spec.gates),
                np.random.default_rng(spec.seed),
                created_at_ns=spec.created_at_ns,
                map_fn=map_fn,
            )
        for report in outcome.stages:
            notes.append(f"{report.stage}: kept {report.kept}, discarded {report.discarded}")
            notes.extend(f"{report.stage}: {note}" for note in collapse_counted_notes(report.notes))
        # calibrate() knows the detections' span and its own parameters; the job knows the window it was
        # asked for and the whole daemon config.
        provenance = Provenance(
            window_start_ns=spec.window_start_ns,
            window_end_ns=spec.window_end_ns,
            recordings=list(spec.recordings),
            station_id=spec.station_id,
            software_version=SOFTWARE_VERSION,
            config_hash=spec.config_hash or outcome.result.provenance.config_hash,
        )
        result = outcome.result.model_copy(update={"provenance": provenance})
        return JobOutcome(
            spec.job_id,
            spec.camera_id,
            result.model_dump_json(),
            None,
            time.monotonic() - started,
            detections,
            poses,
            tuple(notes),
        )
    except RsucalError as err:  # RecordingError, InputError, DegenerateGeometry, ShapeError
        return failed(f"{type(err).__name__}: {err}")
    except ValidationError as err:
        return failed(f"invalid value: {describe_validation_error(err)}")
    except OSError as err:
        return failed(f"{type(err).__name__}: {err}")
    except Exception as err:
        # The worker boundary: a bug must end this job with a message, not the pool. The traceback goes
        # to the notes (the daemon logs them) because logging is configured only in the daemon process.
        lines = traceback.format_exc().rstrip().splitlines()
        notes.extend(f"traceback: {line}" for line in lines[-_TRACEBACK_LINES:])
        return failed(f"internal error: {type(err).__name__}: {err}")


def _unusable_recording(path: str) -> str | None:
    """Why `path` cannot be a recording (missing, unreadable, not MCAP), or None; reads 8 bytes."""
    try:
        with open(path, "rb") as stream:
            head = stream.read(len(MCAP_MAGIC))
    except OSError as err:
        return f"{path}: cannot read: {err.strerror or err}"
    if head != MCAP_MAGIC:
        return f"{path}: not an MCAP file (bad magic bytes)"
    return None


# ---------------------------------------------------------------------------------------------- comparison


def compare_results(new: CalibrationResult, current: CalibrationResult, change: ChangeConfig) -> ChangeInfo:
    """How far `new` is from `current`: camera-centre distance (m, absolute UTM) and the angle (deg) of the
    relative rotation; moved when either exceeds change.shift_m / change.shift_deg.

    Both results need a pose and the same crs (ValueError otherwise: their frames are not comparable).
    """
    for name, result in (("new", new), ("current", current)):
        if result.R is None or result.camera_position is None:
            raise ValueError(f"{name} result {result.result_id} has no pose ({result.verdict.status})")
    assert new.R is not None and new.camera_position is not None
    assert current.R is not None and current.camera_position is not None
    if new.frame.crs != current.frame.crs:
        raise ValueError(
            f"results {new.result_id} ({new.frame.crs}) and {current.result_id} ({current.frame.crs}) are in "
            "different UTM zones"
        )
    shift_m = float(
        np.linalg.norm(np.asarray(new.camera_position.utm) - np.asarray(current.camera_position.utm))
    )
    # R maps the local frame (UTM minus origin, a pure translation) to the camera, so rotations of results
    # with different origins compare directly. The angle from the quaternion of R_a^T R_b via atan2 stays
    # accurate for the small angles that matter here (acos of the trace loses half the digits near 0).
    relative = np.asarray(current.R, dtype=np.float64).T @ np.asarray(new.R, dtype=np.float64)
    axis_part = 0.5 * np.linalg.norm(
        [relative[2, 1] - relative[1, 2], relative[0, 2] - relative[2, 0], relative[1, 0] - relative[0, 1]]
    )
    cos_part = 0.5 * (float(np.trace(relative)) - 1.0)
    shift_deg = math.degrees(math.atan2(float(axis_part), cos_part))
    return ChangeInfo(
        previous_result_id=current.result_id,
        shift_m=shift_m,
        shift_deg=shift_deg,
        moved=shift_m > change.shift_m or shift_deg > change.shift_deg,
    )


# ---------------------------------------------------------------------------------------------- the pool


def _init_worker() -> None:
    """Worker start-up (spawned): load the pipeline now, and leave shutdown to the daemon.

    SIGINT (a terminal's Ctrl-C reaches the whole process group) is ignored: the daemon decides when jobs
    end. SIGTERM (JobRunner.shutdown) kills this worker's own track-pool processes first, so none is
    orphaned, then exits at once.
    """
    import pipeline.calibrate  # noqa: F401 - the point: importing cv2, scipy, sklearn takes ~1.5 s

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _terminate_worker)


def _terminate_worker(signum: int, frame: FrameType | None) -> None:
    """SIGTERM in a worker: kill its track-pool processes, reap them, exit.

    The children are taken from the process tree, not from multiprocessing's registry: a child forked a
    moment ago is registered only after fork() returns to Python, and this handler may run in between
    (forks and handlers both run on the main thread, so /proc already lists every child). SIGKILL, because
    they hold nothing worth saving and one stuck in native code would ignore SIGTERM. Reaping them here
    keeps zombies away from PID 1, which in a container is the daemon itself.
    """
    children = set(_descendant_pids(os.getpid()))
    children.update(c.pid for c in multiprocessing.active_children() if c.pid is not None)
    for pid in children:
        _kill(pid)
    deadline = time.monotonic() + TERMINATE_GRACE_S / 2
    waiting = set(children)
    while waiting and time.monotonic() < deadline:
        for pid in list(waiting):
            try:
                done, _ = os.waitpid(pid, os.WNOHANG)
            except ChildProcessError:  # not our direct child, or already reaped
                done = pid
            if done:
                waiting.discard(pid)
        if waiting:
            time.sleep(0.005)
    os._exit(128 + signum)


def _warm() -> int:
    return os.getpid()


class JobRunner:
    """A pool of `max_parallel` spawned worker processes running run_job, warm before the first job.

    Spawn, not fork: the daemon process runs Zenoh's native threads, and a forked child of a threaded
    process can inherit a held lock. Jobs beyond max_parallel queue. Thread-safe.
    """

    def __init__(self, max_parallel: int, warm_timeout_s: float = WARM_TIMEOUT_S) -> None:
        if max_parallel < 1:
            raise ValueError(f"max_parallel = {max_parallel} must be at least 1")
        self.max_parallel = max_parallel
        self._lock = threading.Lock()
        self._pending: set[Future[JobOutcome]] = set()
        self._closed = False
        self._pool = self._new_pool()
        # A spawn-context pool starts a worker only when work arrives and none is idle: submitting one task
        # per worker at once starts all of them, each importing the pipeline in its initializer.
        started = time.monotonic()
        warm = [self._pool.submit(_warm) for _ in range(max_parallel)]
        try:
            pids = {future.result(timeout=warm_timeout_s) for future in warm}
        except BaseException:
            self.shutdown(timeout_s=0.0)
            raise
        log.info(
            "%d job worker(s) ready in %.1f s (pids %s)", len(pids), time.monotonic() - started, sorted(pids)
        )

    def _new_pool(self) -> ProcessPoolExecutor:
        context = multiprocessing.get_context("spawn")
        return ProcessPoolExecutor(
            max_workers=self.max_parallel, mp_context=context, initializer=_init_worker
        )

    def submit(self, spec: JobSpec) -> Future[JobOutcome]:
        """Queue a job; the future's result is run_job's outcome. If a worker died (killed, out of memory),
        the job's future fails with BrokenProcessPool and the next submit starts a fresh pool."""
        with self._lock:
            if self._closed:
                raise RuntimeError("JobRunner is shut down")
            try:
                future = self._pool.submit(run_job, spec)
            except BrokenProcessPool:
                log.warning("job worker pool broken (a worker died); starting a new one")
                self._stop_pool(self._pool, timeout_s=0.0)
                self._pool = self._new_pool()
                future = self._pool.submit(run_job, spec)
            self._pending.add(future)
        future.add_done_callback(self._forget)
        return future

    def _forget(self, future: Future[JobOutcome]) -> None:
        with self._lock:
            self._pending.discard(future)

    def running(self) -> int:
        """Jobs submitted and not yet finished (running or queued)."""
        with self._lock:
            return len(self._pending)

    def shutdown(self, timeout_s: float) -> None:
        """Cancel queued jobs, give running ones `timeout_s` to finish, then terminate the workers (and their
        track-pool processes): no process outlives this call. Futures of killed jobs fail with
        BrokenProcessPool, cancelled ones are cancelled. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            pool = self._pool
        self._stop_pool(pool, timeout_s)

    @staticmethod
    def _stop_pool(pool: ProcessPoolExecutor, timeout_s: float) -> None:
        processes: list[BaseProcess] = list((pool._processes or {}).values())
        # typeshed calls this a _ThreadWakeup; it is the pool's management thread (None before any submit).
        manager: threading.Thread | None = getattr(pool, "_executor_manager_thread", None)
        pool.shutdown(wait=False, cancel_futures=True)
        # The management thread sends idle workers their stop sentinel, waits for running jobs and reaps
        # every worker before it ends. Wait for it rather than join the workers here as well: two threads
        # reaping one process race, and the loser sees a dead worker as alive.
        if manager is not None:
            manager.join(max(0.0, timeout_s))
        else:
            deadline = time.monotonic() + max(0.0, timeout_s)
            for process in processes:
                process.join(max(0.0, deadline - time.monotonic()))
        stragglers = [p for p in processes if p.is_alive()]
        if stragglers:
            log.warning("terminating %d job worker(s) still running after %.1f s", len(stragglers), timeout_s)
            for process in stragglers:
                process.terminate()  # the worker kills its track pool first, see _terminate_worker
            deadline = time.monotonic() + TERMINATE_GRACE_S
            for process in stragglers:
                process.join(max(0.0, deadline - time.monotonic()))
            for process in stragglers:
                if process.is_alive() and process.pid is not None:
                    # Stuck in native code: kill its descendants before it, while they can still be found.
                    for pid in _descendant_pids(process.pid):
                        _kill(pid)
                    process.kill()
                    process.join(TERMINATE_GRACE_S)
        if manager is not None:
            # After a termination it marks the killed jobs' futures failed (BrokenProcessPool), then ends.
            manager.join(TERMINATE_GRACE_S)


def _descendant_pids(pid: int) -> list[int]:
    """Every live descendant of `pid` (Linux /proc; [] elsewhere)."""
    parents: dict[int, list[int]] = {}
    try:
        entries = os.listdir("/proc")
    except OSError:
        return []
    for entry in entries:
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as stream:
                stat = stream.read()
        except OSError:
            continue  # exited meanwhile
        # pid (comm) state ppid ...: comm may hold spaces and parentheses, so split after the last ')'.
        fields = stat[stat.rfind(b")") + 2 :].split()
        if len(fields) > 1:
            parents.setdefault(int(fields[1]), []).append(int(entry))
    found: list[int] = []
    frontier = [pid]
    while frontier:
        children = parents.get(frontier.pop(), [])
        found.extend(children)
        frontier.extend(children)
    return found


def _kill(pid: int) -> None:
    with contextlib.suppress(ProcessLookupError):  # exited meanwhile
        os.kill(pid, signal.SIGKILL)
