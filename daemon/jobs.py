"""Calibration jobs: one camera's data window read from the MCAP recordings, calibrated in a worker process.

The daemon builds a JobSpec (plain, picklable values) and hands it to a JobRunner (daemon.pool), a pool of
spawned worker processes. In the worker, run_job reads the window, converts the calibration vehicle's V2X
positions to UTM poses and makes the same calibrate() call as `rsucal calibrate --mcap`; it never raises:
every failure becomes JobOutcome.error. What the daemon does with the outcome is daemon.publication's.

Time limit (JobSpec.timeout_s): run_job arms a timer (SIGALRM, in the worker's main thread) whose handler
raises JobTimeout; the job's track pool is killed on the way out and the outcome is the error "timed out
after N s", with the worker kept for the next job. A worker that does not answer its timer (stuck in one
native call) is killed from the daemon's side `kill_grace_s` later; see daemon.pool.JobRunner.
"""

from __future__ import annotations

import contextlib
import logging
import math
import signal
import sys
import threading
import time
import traceback
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import FrameType

import numpy as np
from pydantic import ValidationError

from daemon.recording import MCAP_MAGIC, read_window
from daemon.workers import track_pool
from pipeline.calibrate import (
    SOFTWARE_VERSION,
    CalibrationInputs,
    CalibrationOutcome,
    PipelineParams,
    calibrate,
)
from pipeline.errors import RsucalError
from pipeline.frames import UtmFrame, poses_from_v2x, precise_v2x
from schemas.common import CameraIntrinsics, VehicleProfile, describe_validation_error
from schemas.config import GatesConfig, JobsConfig
from schemas.messages import apply_labels
from schemas.results import CalibrationResult, Provenance

log = logging.getLogger(__name__)

TIMEOUT_RETRY_S = 0.25  # a job's timer repeats this often after its limit until the job has ended
DEFAULT_TIMEOUT_S = JobsConfig().timeout_s
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


VehicleBox = tuple[int, float, float, float, float]  # stamp_ns, x1, y1, x2, y2 (px)


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
    # The calibration vehicle's boxes as an accepted fit identified them: (stamp_ns, x1, y1, x2, y2) of each
    # box of the chosen group's tracks, camera stamps; the daemon records them as a Foxglove overlay.
    vehicle_boxes: tuple[VehicleBox, ...] = ()


# ---------------------------------------------------------------------------------------------- the job


def pipeline_params(gates: GatesConfig) -> PipelineParams:
    """The pipeline's parameters for the daemon: defaults, with the configured validation gates."""
    return PipelineParams(gates=gates)


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
    # Not a daemon thread: the worker's interpreter waits for it at exit. A daemon thread still drawing
    # when the worker ends is stopped by pthread_exit inside matplotlib's native code, which unwinds through
    # C++ frames that allow no exception: "terminate called without an active exception" and SIGABRT
    # (seen in about 1 of 8 demos at the daemon's stop). A worker that does not end in time is terminated
    # by the pool (daemon.pool: SIGTERM, then os._exit, no unwinding).
    threading.Thread(target=_draw_report, args=arguments, name="rsucal-report", daemon=False).start()
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
        precise, left_out = precise_v2x(window.v2x, spec.gates.max_v2x_std_m, "gates.max_v2x_std_m")
        vehicle_poses, unrepresentable = poses_from_v2x(precise, UtmFrame(spec.crs))
        detections, poses = len(window.detections), len(vehicle_poses)
        progress.detections, progress.poses = detections, poses
        notes.append(
            f"window: {detections} detection frame(s) of camera {spec.camera_id}, {poses} pose(s) of "
            f"station {spec.station_id} from {len(spec.recordings)} recording(s)"
        )
        if left_out:
            notes.append(left_out)
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
            poses_left_out=left_out,
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
            notes.extend(f"{report.stage}: {line}" for line in report.lines())
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
            vehicle_boxes=_vehicle_boxes(outcome) if result.verdict.is_accepted else (),
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


def _vehicle_boxes(outcome: CalibrationOutcome) -> tuple[VehicleBox, ...]:
    """Every box of the chosen group's tracks, in stamp order: the boxes the fit took for the vehicle's."""
    if outcome.chosen is None or outcome.diagnostics is None:
        return ()
    chosen = set(outcome.chosen.track_ids)
    boxes = [
        (int(stamp), float(x1), float(y1), float(x2), float(y2))
        for track in outcome.diagnostics.tracks
        if track.track_id in chosen
        for stamp, (x1, y1, x2, y2) in zip(track.stamps.tolist(), track.boxes.tolist(), strict=True)
    ]
    return tuple(sorted(boxes))


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
