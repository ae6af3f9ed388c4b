"""Calibration jobs: one camera's data window read from the MCAP recordings, calibrated in a worker process.

The daemon builds a JobSpec (plain, picklable values) and hands it to a JobRunner, a pool of spawned worker
processes started and warmed (pipeline imported) when the daemon starts. In the worker, run_job reads the
window, converts the calibration vehicle's V2X positions to UTM poses and makes the same calibrate() call
as `rsucal calibrate --mcap`; it never raises: every failure becomes JobOutcome.error. compare_results
tells whether a new accepted result means the camera moved.

Time limit (JobSpec.timeout_s): run_job arms a timer (SIGALRM, in the worker's main thread) whose handler
raises JobTimeout; the job's track pool is killed on the way out and the outcome is the error "timed out
after N s", with the worker kept for the next job. A worker that does not answer its timer (stuck in one
native call) is killed from the daemon's side `kill_grace_s` later; see JobRunner.

Worker processes die with their parent (prctl PR_SET_PDEATHSIG on Linux, daemon.workers.die_with_parent):
a daemon killed with SIGKILL leaves no job worker or track-pool process behind.
"""

from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import Future, InvalidStateError, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from pathlib import Path
from types import FrameType

import numpy as np
from pydantic import ValidationError

from daemon.offline import collapse_counted_notes
from daemon.recording import MCAP_MAGIC, read_window
from daemon.workers import descendant_pids, die_with_parent, kill_pid, track_pool
from pipeline.calibrate import (
    SOFTWARE_VERSION,
    CalibrationInputs,
    CalibrationOutcome,
    PipelineParams,
    calibrate,
)
from pipeline.errors import RsucalError
from pipeline.frames import UtmFrame, poses_from_v2x
from pipeline.validation import ValidationGates
from schemas.common import CameraIntrinsics, VehicleProfile, describe_validation_error
from schemas.config import ChangeConfig, GatesConfig, JobsConfig
from schemas.messages import apply_labels
from schemas.results import CalibrationResult, ChangeInfo, Provenance

log = logging.getLogger(__name__)

WARM_TIMEOUT_S = 120.0  # spawning a worker and importing the pipeline takes ~2 s; a slow SD card, more
# After SIGTERM a worker stops its own track-pool processes and exits; this long, then SIGKILL for all.
TERMINATE_GRACE_S = 0.5
# A job past its time limit normally ends within milliseconds (its timer's exception); a worker that has not
# answered this long after the limit is stuck in native code and is killed from the daemon's side.
KILL_GRACE_S = 30.0
TIMEOUT_RETRY_S = 0.25  # a job's timer repeats this often after its limit until the job has ended
DEFAULT_TIMEOUT_S = JobsConfig().timeout_s
_WATCH_MAX_WAIT_S = 3600.0  # the watchdog's longest sleep (poll() takes no more than ~24 days anyway)
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
    timeout_s: float = DEFAULT_TIMEOUT_S  # jobs.timeout_s: wall time from the job's start in its worker
    labels: dict[int, str] | None = None  # the camera's label map (its detector's class ids -> names)
    # Where the job writes its HTML report (the camera's history/, beside the result), or None for none.
    report_dir: str | None = None


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
    # Last stamp of the newest image track in the chosen group: tells whether a re-verification really used
    # the new drive-past, or only the older ones still in the window.
    newest_track_end_ns: int | None = None
    report_path: str | None = None  # the job's HTML report, when written


# ---------------------------------------------------------------------------------------------- the job


def pipeline_params(gates: GatesConfig) -> PipelineParams:
    """The pipeline's parameters for the daemon: defaults, with the configured validation gates."""
    # Same field names on both sides (schemas.config documents them); a field added to one only fails here.
    return PipelineParams(gates=ValidationGates(**gates.model_dump()))


def new_job_id(camera_id: str, now_ns: int) -> str:
    """A readable, sortable job id: '{camera_id}-{now_ns:019d}'."""
    return f"{camera_id}-{now_ns:019d}"


class JobTimeout(BaseException):
    """Raised in the job's thread when its time limit is up. A BaseException, like KeyboardInterrupt, so
    that no `except Exception` on the way (the job's own worker boundary included) takes it for a failure
    of the step it interrupted."""


@contextmanager
def _time_limit(timeout_s: float) -> Iterator[bool]:
    """Raise JobTimeout in this thread after `timeout_s` s of wall time; yields whether the limit is armed.

    SIGALRM (setitimer) interrupts Python code and blocking waits (the track pool's results, file reads)
    alike; a native call that never returns to the interpreter is the parent's business (JobRunner).
    Signals are handled in the main thread only: elsewhere (and without setitimer) nothing is armed.

    The handler may run where an exception cannot get out: a callback of os.fork() (the track pool
    forking), a __del__; Python prints "Exception ignored" and carries on. So the timer repeats every
    TIMEOUT_RETRY_S after the limit, and raises again unless a JobTimeout is already being handled (the
    way out: cleanups in except and finally blocks, which must not be interrupted). Disarmed, and the
    previous handler put back, on the way out.
    """
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "setitimer"):
        yield False
        return

    def expire(signum: int, frame: FrameType | None) -> None:
        if not _handling_timeout():
            raise JobTimeout

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, timeout_s, TIMEOUT_RETRY_S)
    try:
        yield True
    finally:
        # Disarm first: from here on no new SIGALRM. One that fired a moment ago may still raise inside
        # this block; the caller's `except JobTimeout` encloses it, so the job then reports the timeout.
        signal.setitimer(signal.ITIMER_REAL, 0.0, 0.0)
        signal.signal(signal.SIGALRM, previous)


def _handling_timeout() -> bool:
    """Whether a JobTimeout is being handled in this thread (itself, or as the context of another)."""
    error: BaseException | None = sys.exc_info()[1]
    while error is not None:
        if isinstance(error, JobTimeout):
            return True
        error = error.__context__
    return False


@dataclass(slots=True)
class _Progress:
    """What a job has found so far: reported with an error too, a timeout included."""

    started: float = field(default_factory=time.monotonic)
    notes: list[str] = field(default_factory=list)
    detections: int = 0
    poses: int = 0
    # For the report, written after the job's time limit: the calibrate() outcome and what it was given.
    calibration: CalibrationOutcome | None = None
    inputs: CalibrationInputs | None = None

    def failed(self, spec: JobSpec, message: str) -> JobOutcome:
        return JobOutcome(
            spec.job_id,
            spec.camera_id,
            None,
            message,
            time.monotonic() - self.started,
            self.detections,
            self.poses,
            tuple(self.notes),
        )


def run_job(spec: JobSpec) -> JobOutcome:
    """Read the window, build the calibrate() inputs, calibrate; in a worker process. Never raises.

    Outcomes: a result (accepted, or refused with reasons) whenever at least one recording could be read,
    including a window with too little data (calibrate refuses it: "no calibration-vehicle poses in the data
    window", "no detections from this camera ...", too few traversals); unreadable files among readable ones
    are stage notes. `error` when the job could not produce an answer at all: no recordings named, none
    readable, a bad spec (crs, ids, window, timeout), the time limit reached ("timed out after N s", with
    the notes of what was done so far), or an unexpected failure (its traceback in the notes).
    """
    progress = _Progress()
    if not (math.isfinite(spec.timeout_s) and spec.timeout_s > 0.0):
        return progress.failed(spec, f"timeout_s = {spec.timeout_s} must be a positive number of seconds")
    try:
        with _time_limit(spec.timeout_s) as armed:
            if not armed:
                progress.notes.append("time limit not enforced: the job does not run on a main thread")
            outcome = _run_job(spec, progress)
    except JobTimeout:
        return progress.failed(spec, f"timed out after {spec.timeout_s:g} s")
    # Outside the time limit: the answer is made; a report that fails only costs its note.
    return _with_report(spec, outcome, progress)


# One report at a time in a worker process: matplotlib's pyplot state is not thread-safe.
_REPORT_LOCK = threading.Lock()


def _with_report(spec: JobSpec, outcome: JobOutcome, progress: _Progress) -> JobOutcome:
    """Start the job's HTML report (spec.report_dir) on a thread of this worker and name it in the outcome.

    Drawing takes seconds; the answer is published without waiting for it. Never raises: a report
    directory that cannot be made is a note (no report named); a drawing that fails leaves a page saying
    why at the named path.
    """
    if spec.report_dir is None or outcome.result_json is None or progress.calibration is None:
        return outcome
    assert progress.inputs is not None
    from daemon.state import history_name

    result = CalibrationResult.model_validate_json(outcome.result_json)
    directory = Path(spec.report_dir)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        note = f"report not written: {type(err).__name__}: {err}"
        return replace(outcome, stage_notes=(*outcome.stage_notes, note))
    path = directory / history_name(result, ".html")
    arguments = (path, result, progress.calibration, progress.inputs, outcome.stage_notes)
    threading.Thread(target=_draw_report, args=arguments, name="rsucal-report", daemon=True).start()
    return replace(outcome, report_path=str(path))


def _draw_report(
    path: Path,
    result: CalibrationResult,
    calibration: CalibrationOutcome,
    inputs: CalibrationInputs,
    notes: tuple[str, ...],
) -> None:
    """The report thread: the figures and the page, or a page with the reason they could not be drawn."""
    with _REPORT_LOCK:
        from daemon.recording import read_images
        from daemon.report import write_report, write_report_failure  # matplotlib: only once needed

        def images(stamps: Sequence[int]) -> Mapping[int, bytes]:
            return read_images([Path(p) for p in inputs.recordings], result.rsu_id, result.camera_id, stamps)

        try:
            write_report(
                result, calibration, inputs.vehicle, inputs.detections, path, notes=notes, images=images
            )
        except Exception as err:  # the report is a view of the answer, never a reason to lose it
            with contextlib.suppress(OSError):
                write_report_failure(result, path, f"{type(err).__name__}: {err}", notes)


def _run_job(spec: JobSpec, progress: _Progress) -> JobOutcome:
    """run_job's work, within its time limit: errors become outcomes, JobTimeout passes through."""
    notes = progress.notes

    def failed(message: str) -> JobOutcome:
        return progress.failed(spec, message)

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
        progress.detections, progress.poses = detections, poses
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
            detections=apply_labels(window.detections, spec.labels),
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
        progress.calibration, progress.inputs = outcome, inputs
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
            time.monotonic() - progress.started,
            detections,
            poses,
            tuple(notes),
            newest_track_end_ns=max((end for _, end in outcome.chosen.track_spans), default=None)
            if outcome.chosen is not None
            else None,
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

# In a job worker: the pipe on which it tells the daemon which job it starts (set by _init_worker).
_started_channel: Connection | None = None


def _init_worker(parent_pid: int, started_channel: Connection) -> None:
    """Worker start-up (spawned): die with the daemon, load the pipeline now, leave shutdown to the daemon.

    die_with_parent comes first, so a daemon killed during the import already leaves nothing behind.
    SIGINT (a terminal's Ctrl-C reaches the whole process group) is ignored: the daemon decides when jobs
    end. SIGTERM (JobRunner.shutdown) kills this worker's own track-pool processes first, so none is
    orphaned, then exits at once.
    """
    global _started_channel
    die_with_parent(parent_pid)
    _started_channel = started_channel
    import pipeline.calibrate  # noqa: F401 - the point: importing cv2 and scipy takes ~1 s

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _terminate_worker)


def _run_reported(seq: int, spec: JobSpec) -> JobOutcome:
    """The pool's task: tell the daemon that this process starts its job `seq` (JobRunner's watchdog
    measures the time limit's backstop from here), then run it."""
    if _started_channel is not None:
        # A few dozen bytes are one atomic pipe write: the workers share the pipe without a lock.
        with contextlib.suppress(OSError):  # the daemon is going away; the job does not care
            _started_channel.send((seq, os.getpid()))
    return run_job(spec)


def _terminate_worker(signum: int, frame: FrameType | None) -> None:
    """SIGTERM in a worker: kill its track-pool processes, reap them, exit.

    The children are taken from the process tree, not from multiprocessing's registry: a child forked a
    moment ago is registered only after fork() returns to Python, and this handler may run in between
    (forks and handlers both run on the main thread, so /proc already lists every child). SIGKILL, because
    they hold nothing worth saving and one stuck in native code would ignore SIGTERM. Reaping them here
    keeps zombies away from PID 1, which in a container is the daemon itself.
    """
    children = set(descendant_pids(os.getpid()))
    children.update(c.pid for c in multiprocessing.active_children() if c.pid is not None)
    for pid in children:
        kill_pid(pid)
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


@dataclass(slots=True)
class _Job:
    """A submitted job: the caller's future, the pool task now carrying it (changed under the lock)."""

    spec: JobSpec
    future: Future[JobOutcome]
    pool: ProcessPoolExecutor
    task: Future[JobOutcome]


class JobRunner:
    """A pool of `max_parallel` spawned worker processes running run_job, warm before the first job.

    Spawn, not fork: the daemon process runs Zenoh's native threads, and a forked child of a threaded
    process can inherit a held lock. Jobs beyond max_parallel queue. Thread-safe.

    Time limits: a job's own timer ends it (run_job: "timed out after N s"; the worker stays for the next
    job). As a backstop each worker reports which job it starts, and a watchdog thread kills a worker (and
    its track pool) whose job is still running `kill_grace_s` after its limit: stuck in a native call that
    never returns to Python, or stopped. That job's future then holds the outcome "timed out after N s: the
    worker did not stop and was killed"; the pool is replaced at once; its jobs that no worker had taken
    yet move to the new pool, the others (running, or already in the pool's call queue) fail with
    BrokenProcessPool, as when a worker dies of other causes.

    Every pool is created on one thread of the runner's own: a worker dies with the thread that started it
    (daemon.workers.die_with_parent), and that thread lives until shutdown, whichever thread submits.
    """

    def __init__(
        self, max_parallel: int, warm_timeout_s: float = WARM_TIMEOUT_S, kill_grace_s: float = KILL_GRACE_S
    ) -> None:
        if max_parallel < 1:
            raise ValueError(f"max_parallel = {max_parallel} must be at least 1")
        if not kill_grace_s >= 0.0:
            raise ValueError(f"kill_grace_s = {kill_grace_s} must be at least 0")
        self.max_parallel = max_parallel
        self.kill_grace_s = kill_grace_s
        self._context = multiprocessing.get_context("spawn")
        self._lock = threading.Lock()
        self._jobs: dict[int, _Job] = {}  # by a sequence number of the runner's (job ids may repeat)
        self._killed: dict[int, float] = {}  # jobs whose worker the watchdog killed: seconds they ran
        self._next_seq = 0
        self._closed = False
        self._started_reader, self._started_writer = self._context.Pipe(duplex=False)
        self._spawner = ThreadPoolExecutor(max_workers=1, thread_name_prefix="rsucal-job-spawner")
        self._watchdog = threading.Thread(target=self._watch, name="rsucal-job-watchdog", daemon=True)
        started = time.monotonic()
        try:
            self._pool, warm = self._spawner.submit(self._new_pool).result()
        except BaseException:
            self._spawner.shutdown()
            self._started_reader.close()
            self._started_writer.close()
            raise
        self._watchdog.start()
        try:
            pids = {future.result(timeout=warm_timeout_s) for future in warm}
        except BaseException:
            self.shutdown(timeout_s=0.0)
            raise
        log.info(
            "%d job worker(s) ready in %.1f s (pids %s)", len(pids), time.monotonic() - started, sorted(pids)
        )

    def _new_pool(self) -> tuple[ProcessPoolExecutor, list[Future[int]]]:
        """A pool with all its workers starting now, on the spawner thread. A spawn-context pool starts a
        worker only when work arrives and none is idle: one quick task per worker starts each, each
        importing the pipeline in its initializer; the tasks' results are the workers' pids once warm."""
        pool = ProcessPoolExecutor(
            max_workers=self.max_parallel,
            mp_context=self._context,
            initializer=_init_worker,
            initargs=(os.getpid(), self._started_writer),
        )
        return pool, [pool.submit(_warm) for _ in range(self.max_parallel)]

    def _replace_pool_locked(self) -> ProcessPoolExecutor:
        """Start a new pool (not waiting for it to warm) as the current one; returns the old one to stop."""
        stale = self._pool
        self._pool, _ = self._spawner.submit(self._new_pool).result()
        return stale

    def submit(self, spec: JobSpec) -> Future[JobOutcome]:
        """Queue a job; the future's result is run_job's outcome. If a worker died (killed, out of memory),
        the job's future fails with BrokenProcessPool and the next submit starts a fresh pool."""
        future: Future[JobOutcome] = Future()
        stale: ProcessPoolExecutor | None = None
        with self._lock:
            if self._closed:
                raise RuntimeError("JobRunner is shut down")
            seq = self._next_seq
            self._next_seq += 1
            try:
                task = self._pool.submit(_run_reported, seq, spec)
            except BrokenProcessPool:
                log.warning("job worker pool broken (a worker died); starting a new one")
                stale = self._replace_pool_locked()
                task = self._pool.submit(_run_reported, seq, spec)
            self._jobs[seq] = _Job(spec, future, self._pool, task)
        # Callbacks outside the lock: on a future already done they run at once, here, and take the lock.
        future.add_done_callback(lambda done: self._forget(seq, done))
        task.add_done_callback(lambda done: self._settle(seq, done))
        if stale is not None:
            self._stop_pool(stale, timeout_s=0.0)
        return future

    def _settle(self, seq: int, task: Future[JobOutcome]) -> None:
        """A pool task ended: pass its outcome to the caller's future, the backstop's timeout outcome for a
        killed worker, or run the job again if a pool replacement cancelled it before any worker took it."""
        with self._lock:
            job = self._jobs.get(seq)
            ran_s = self._killed.pop(seq, None)
            if job is None or job.task is not task:
                return  # the caller cancelled its future (see _forget)
            retry: Future[JobOutcome] | None = None
            if task.cancelled() and not self._closed:
                with contextlib.suppress(BrokenProcessPool):  # the new pool broke too: the job fails
                    retry = job.task = self._pool.submit(_run_reported, seq, job.spec)
                    job.pool = self._pool
        if retry is not None:
            retry.add_done_callback(lambda done: self._settle(seq, done))
            return
        with contextlib.suppress(InvalidStateError):  # the caller cancelled its future meanwhile
            if task.cancelled():
                job.future.cancel()
            elif (error := task.exception()) is None:
                job.future.set_result(task.result())
            elif ran_s is not None:
                message = f"timed out after {job.spec.timeout_s:g} s: the worker did not stop and was killed"
                job.future.set_result(
                    JobOutcome(job.spec.job_id, job.spec.camera_id, None, message, ran_s, 0, 0, ())
                )
            else:
                job.future.set_exception(error)

    def _forget(self, seq: int, future: Future[JobOutcome]) -> None:
        with self._lock:
            job = self._jobs.pop(seq, None)
        if job is not None and future.cancelled():
            job.task.cancel()  # the caller cancelled: drop the job if no worker has taken it yet

    def running(self) -> int:
        """Jobs submitted and not yet finished (running or queued)."""
        with self._lock:
            return len(self._jobs)

    def _watch(self) -> None:
        """Watchdog thread: learn which worker starts which job; kill a worker whose job is still running
        kill_grace_s after its time limit. Ends on None from shutdown()."""
        started: dict[int, tuple[int, float, float]] = {}  # seq -> (worker pid, start, kill time)
        while True:
            wait_s = None  # nothing running: sleep until a worker reports
            if started:
                next_kill = min(kill_at for _, _, kill_at in started.values())
                wait_s = min(_WATCH_MAX_WAIT_S, max(0.0, next_kill - time.monotonic()))
            try:
                message = self._started_reader.recv() if self._started_reader.poll(wait_s) else ()
                if message is None:
                    return
                self._check(message, started)
            except (EOFError, OSError):
                return  # the pipe is closed: the runner is gone
            except Exception:
                # Carry on whatever happened: unread reports would fill the pipe and block the workers.
                log.exception("job watchdog: unexpected error; carrying on")

    def _check(self, message: object, started: dict[int, tuple[int, float, float]]) -> None:
        """The watchdog's step: note a worker's report (seq, pid) if any, forget jobs that have ended, kill
        the workers of jobs past their limit and grace."""
        now = time.monotonic()
        if isinstance(message, tuple) and len(message) == 2:
            seq, pid = message
            with self._lock:
                job = self._jobs.get(seq)
            if job is not None:
                started[seq] = (pid, now, now + job.spec.timeout_s + self.kill_grace_s)
        for seq, (pid, start, kill_at) in list(started.items()):
            with self._lock:
                alive = seq in self._jobs
            if not alive or now >= kill_at:
                del started[seq]
            if alive and now >= kill_at:
                self._kill_stuck(seq, pid, now - start)

    def _kill_stuck(self, seq: int, pid: int, ran_s: float) -> None:
        """Kill worker `pid`, which has not ended job `seq` in time, and its track pool; replace the pool."""
        with self._lock:
            job = self._jobs.get(seq)
            if self._closed or job is None:
                return
            self._killed[seq] = ran_s
            stale = self._replace_pool_locked() if self._pool is job.pool else None
            waiting = [other.task for other in self._jobs.values() if other.pool is job.pool]
        log.warning(
            "job %s (camera %s) still running %.0f s after its %g s time limit: killing its worker (pid %d)",
            job.spec.job_id,
            job.spec.camera_id,
            self.kill_grace_s,
            job.spec.timeout_s,
            pid,
        )
        # Jobs no worker has taken yet cancel here and run in the new pool (see _settle).
        for task in waiting:
            task.cancel()
        for child in descendant_pids(pid):
            kill_pid(child)
        kill_pid(pid)
        if stale is not None:
            self._stop_pool(stale, timeout_s=0.0)

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
        with contextlib.suppress(OSError):
            self._started_writer.send(None)  # ends the watchdog
        self._watchdog.join()
        self._spawner.shutdown()
        self._started_reader.close()
        self._started_writer.close()

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
                    for pid in descendant_pids(process.pid):
                        kill_pid(pid)
                    process.kill()
                    process.join(TERMINATE_GRACE_S)
        if manager is not None:
            # After a termination it marks the killed jobs' futures failed (BrokenProcessPool), then ends.
            manager.join(TERMINATE_GRACE_S)
