"""daemon.jobs: a calibration job in a spawned worker, its failure modes, the pool's shutdown, and the change
between two results.

The scene is the simulator's sil-west preset (seed 0) recorded to MCAP exactly as the daemon would have
logged it; the job calibrates its first camera.
"""

from __future__ import annotations

import base64
import dataclasses
import math
import multiprocessing
import os
import pickle
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import CancelledError
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import wait_until

from daemon import jobs
from daemon.jobs import (
    TIMEOUT_RETRY_S,
    JobOutcome,
    JobSpec,
    JobTimeout,
    _time_limit,
    new_job_id,
    run_job,
)
from daemon.pool import JobRunner
from daemon.recording import write_simulation_mcap
from pipeline.calibrate import SOFTWARE_VERSION
from schemas.config import GatesConfig
from schemas.results import CalibrationResult
from sim.simulate import SimulationResult, simulate

ROOT = Path(__file__).resolve().parents[2]
CREATED_AT_NS = 1_800_000_000_000_000_000
MARGIN_NS = 10_000_000_000
JOB_TIMEOUT_S = 120.0  # a sil-west job takes ~2.5 s; generous for a loaded CI machine


@dataclass(frozen=True)
class Scene:
    sim: SimulationResult
    mcap: Path
    spec: JobSpec  # the whole recording as the window, first camera


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    sim = simulate("sil-west", seed=0, ideal=True)
    mcap = write_simulation_mcap(sim, tmp_path_factory.mktemp("jobs") / "sil-west.mcap")
    camera = sim.cameras[0]
    stamps = [m.stamp_ns for m in sim.v2x]
    spec = JobSpec(
        job_id=new_job_id(camera.camera_id, CREATED_AT_NS),
        rsu_id=sim.rsu_id,
        camera_id=camera.camera_id,
        intrinsics=camera.intrinsics,
        vehicle=sim.vehicle,
        station_id=sim.station_id,
        time_offset_ns=sim.ground_truth[camera.camera_id].clock_offset_ns,
        crs=sim.origin.crs,
        recordings=(str(mcap),),
        window_start_ns=min(stamps) - MARGIN_NS,
        window_end_ns=max(stamps) + MARGIN_NS,
        gates=GatesConfig(),
        seed=0,
        track_workers=2,
        created_at_ns=CREATED_AT_NS,
        config_hash="0123456789abcdef",
    )
    return Scene(sim, mcap, spec)


def _descendants(pid: int) -> set[int]:
    """Live (non-zombie) descendants of `pid`, from /proc: the test's own oracle, not the module's helper."""
    parents: dict[int, set[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_bytes()
            except OSError:
                continue
            fields = stat[stat.rfind(b")") + 2 :].split()
            if fields[0] != b"Z":
                parents.setdefault(int(fields[1]), set()).add(int(entry))
    found: set[int] = set()
    frontier = [pid]
    while frontier:
        children = parents.get(frontier.pop(), set())
        found |= children
        frontier.extend(children)
    return found


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_bytes()
    except OSError:
        return False
    return stat[stat.rfind(b")") + 2 :].split()[0] != b"Z"


def _parent(pid: int) -> int | None:
    try:
        stat = Path(f"/proc/{pid}/stat").read_bytes()
    except OSError:
        return None
    return int(stat[stat.rfind(b")") + 2 :].split()[1])


def _cpu_ticks(pid: int) -> int:
    """User + system CPU time of `pid` in clock ticks (0 once gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_bytes()
    except OSError:
        return 0
    fields = stat[stat.rfind(b")") + 2 :].split()
    return int(fields[11]) + int(fields[12])


def _worker_pids() -> set[int]:
    return {p.pid for p in multiprocessing.active_children() if p.pid is not None}


@dataclass(frozen=True)
class Warm:
    runner: JobRunner
    worker: int  # pid of its one worker process


@pytest.fixture(scope="module")
def warm() -> Iterator[Warm]:
    """One runner for several tests: a job that timed out must leave its worker fit for the next one."""
    before = _worker_pids()
    job_runner = JobRunner(1)
    workers = [p for p in multiprocessing.active_children() if p.pid not in before]
    assert len(workers) == 1 and workers[0].pid is not None
    try:
        yield Warm(job_runner, workers[0].pid)
    finally:
        job_runner.shutdown(timeout_s=10.0)
        # Idle at shutdown: the worker ends on the pool's stop sentinel (exit code 0), it is not terminated.
        assert [p.exitcode for p in workers] == [0]


def _result_of(outcome: JobOutcome) -> CalibrationResult:
    assert outcome.error is None, outcome.error
    assert outcome.result_json is not None
    return CalibrationResult.model_validate_json(outcome.result_json)


# ---------------------------------------------------------------------------------------------- jobs


def test_job_in_a_spawned_worker_calibrates_sil_west(scene: Scene, warm: Warm) -> None:
    spec, sim, runner = scene.spec, scene.sim, warm.runner
    future = runner.submit(spec)
    assert runner.running() == 1
    outcome = future.result(timeout=JOB_TIMEOUT_S)
    wait_until(lambda: runner.running() == 0, timeout_s=5.0)

    result = _result_of(outcome)
    assert result.verdict.is_accepted, result.verdict.reasons
    camera = sim.cameras[0]
    origin = np.array([sim.origin.x, sim.origin.y, sim.origin.z])
    true_centre_utm = origin - camera.R_cam_from_local.T @ camera.t_cam_from_local
    assert result.camera_position is not None
    # The scenario tests hold sil-west to a few cm; 0.5 m is the daemon's own position gate.
    assert np.linalg.norm(np.array(result.camera_position.utm) - true_centre_utm) < 0.5
    assert (result.rsu_id, result.camera_id, result.created_at_ns) == (
        sim.rsu_id,
        spec.camera_id,
        CREATED_AT_NS,
    )
    provenance = result.provenance
    assert (provenance.window_start_ns, provenance.window_end_ns) == (
        spec.window_start_ns,
        spec.window_end_ns,
    )
    assert provenance.recordings == [str(scene.mcap)]
    assert provenance.station_id == sim.station_id
    assert provenance.software_version == SOFTWARE_VERSION
    assert provenance.config_hash == spec.config_hash

    assert (outcome.job_id, outcome.camera_id) == (spec.job_id, spec.camera_id)
    assert outcome.detections == len(sim.detections[spec.camera_id])
    assert outcome.poses == sum(1 for m in sim.v2x if m.station_id == sim.station_id)
    assert outcome.duration_s > 0.0
    assert any(note.startswith("validation: ") for note in outcome.stage_notes)
    # The boxes the fit took for the calibration vehicle's (the daemon records them as an overlay): the
    # detector's own boxes of the camera's frames, and the truth's calibration-vehicle box in nearly all.
    frames = {frame.stamp_ns: frame for frame in sim.detections[spec.camera_id]}
    truth = {frame.stamp_ns: frame for frame in sim.ground_truth[spec.camera_id].frames}
    assert len(outcome.vehicle_boxes) > 100
    assert [b[0] for b in outcome.vehicle_boxes] == sorted(b[0] for b in outcome.vehicle_boxes)
    hits = 0
    for stamp_ns, *corners in outcome.vehicle_boxes:
        detected = [(b.x1, b.y1, b.x2, b.y2) for b in frames[stamp_ns].boxes]
        assert tuple(corners) in detected
        index = truth[stamp_ns].calib_box
        hits += index is not None and detected[index] == tuple(corners)
    assert hits >= 0.95 * len(outcome.vehicle_boxes), (hits, len(outcome.vehicle_boxes))


def test_window_without_vehicle_data_is_refused_not_failed(scene: Scene) -> None:
    first_stamp = scene.spec.window_start_ns + MARGIN_NS
    before_any_data = dataclasses.replace(
        scene.spec, window_start_ns=first_stamp - 100 * 10**9, window_end_ns=first_stamp - 50 * 10**9
    )
    outcome = run_job(before_any_data)
    result = _result_of(outcome)
    assert result.verdict.status == "refused"
    assert result.verdict.reasons == ["no calibration-vehicle poses in the data window"]
    assert (outcome.detections, outcome.poses) == (0, 0) and outcome.vehicle_boxes == ()
    assert result.provenance.window_start_ns == before_any_data.window_start_ns

    # Detections, but the station named is not in the recording: no vehicle data either.
    other_station = run_job(dataclasses.replace(scene.spec, station_id=scene.sim.station_id + 1))
    result = _result_of(other_station)
    assert result.verdict.reasons == ["no calibration-vehicle poses in the data window"]
    assert other_station.detections == len(scene.sim.detections[scene.spec.camera_id])
    assert other_station.poses == 0


def test_positions_reported_too_imprecise_are_left_out_and_the_refusal_says_so(scene: Scene) -> None:
    # The simulated vehicle reports 0.075 m (1 sigma): with a limit of 0.05 m none of its positions is used.
    strict = dataclasses.replace(scene.spec, gates=GatesConfig(max_v2x_std_m=0.05))
    outcome = run_job(strict)
    result = _result_of(outcome)
    sent = sum(1 for m in scene.sim.v2x if m.station_id == scene.sim.station_id)
    said = f"{sent} of {sent} V2X position(s) not used: the vehicle reported them less accurate than 0.05 m"
    assert result.verdict.status == "refused"
    assert result.verdict.reasons[0].startswith("no calibration-vehicle poses in the data window (" + said)
    assert any(note.startswith(said) for note in outcome.stage_notes)
    assert outcome.poses == 0


def _embedded_pngs(html_text: str) -> list[np.ndarray]:
    """Every data:image/png figure of a report, decoded (an image that does not decode fails here)."""
    images = []
    for encoded in re.findall(r"src='data:image/png;base64,([A-Za-z0-9+/=]+)'", html_text):
        image = cv2.imdecode(np.frombuffer(base64.b64decode(encoded), np.uint8), cv2.IMREAD_COLOR)
        assert image is not None and image.shape[0] > 100 and image.shape[1] > 100
        images.append(image)
    return images


def test_job_writes_its_report_beside_the_result(scene: Scene, tmp_path: Path) -> None:
    history = tmp_path / "cameras" / scene.spec.camera_id / "history"
    outcome = run_job(dataclasses.replace(scene.spec, report_dir=str(history), track_workers=1))
    result = _result_of(outcome)
    assert result.verdict.is_accepted
    expected = history / f"{CREATED_AT_NS:019d}-{result.result_id}.html"
    assert outcome.report_path == str(expected)
    # Drawn on a thread of the worker after the answer is returned (the result is not held back for it).
    wait_until(expected.exists, timeout_s=60.0)
    text = expected.read_text(encoding="utf-8")
    assert "Accepted: every validation gate passed" in text
    assert result.result_id in text and "http" not in text.replace("http-equiv", "")  # nothing fetched
    # Overlays (one per drive-past), map, distance, residuals, hypotheses, uncertainty.
    assert result.quality is not None
    assert len(_embedded_pngs(text)) == result.quality.traversals + 5
    assert [p.name for p in history.iterdir()] == [expected.name]  # no temporary file left behind


# A job worker's life in short: run one job with a report, then end the interpreter at once (as a pool
# worker does when the daemon stops), with the report thread still drawing.
_RUN_AND_EXIT = """
import pickle, sys
from daemon.jobs import run_job
spec = pickle.loads(open(sys.argv[1], "rb").read())
outcome = run_job(spec)
print(outcome.report_path)
"""


def test_a_worker_ending_right_after_its_job_finishes_the_report_first(scene: Scene, tmp_path: Path) -> None:
    # A daemon report thread was cut off at the interpreter's exit inside matplotlib's native code: the
    # worker died of SIGABRT ("terminate called without an active exception", ~1 in 8 demos) or left no
    # page. The exit now waits for the page.
    spec_path = tmp_path / "spec.pickle"
    history = tmp_path / "history"
    spec_path.write_bytes(
        pickle.dumps(dataclasses.replace(scene.spec, report_dir=str(history), track_workers=1))
    )
    done = subprocess.run(
        [sys.executable, "-c", _RUN_AND_EXIT, str(spec_path)], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    assert "terminate called" not in done.stderr
    page = Path(done.stdout.strip().splitlines()[-1])
    assert page.parent == history
    text = page.read_text(encoding="utf-8")  # there when the process ended, not some time after
    assert "Accepted: every validation gate passed" in text and text.rstrip().endswith("</html>")


def test_a_report_that_cannot_be_drawn_says_why(
    scene: Scene, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from daemon import report

    def broken(*args: object, **kwargs: object) -> None:
        raise RuntimeError("no fonts on this RSU")

    monkeypatch.setattr(report, "write_report", broken)
    outcome = run_job(dataclasses.replace(scene.spec, report_dir=str(tmp_path), track_workers=1))
    result = _result_of(outcome)
    assert outcome.report_path is not None
    page = Path(outcome.report_path)
    wait_until(page.exists, timeout_s=60.0)
    text = page.read_text(encoding="utf-8")
    assert "the figures could not be drawn: RuntimeError: no fonts on this RSU" in text
    assert result.result_id in text and "Accepted: every validation gate passed" in text


def test_a_report_that_cannot_be_written_never_fails_the_job(scene: Scene, tmp_path: Path) -> None:
    blocker = tmp_path / "history"
    blocker.write_text("a file where the history directory should be")
    outcome = run_job(dataclasses.replace(scene.spec, report_dir=str(blocker), track_workers=1))
    assert _result_of(outcome).verdict.is_accepted
    assert outcome.report_path is None
    [note] = [n for n in outcome.stage_notes if n.startswith("report not written: ")]
    assert str(blocker) in note


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        pytest.param({"recordings": ()}, "no recordings", id="no-recordings"),
        pytest.param({"recordings": ("/nonexistent/r.mcap",)}, "/nonexistent/r.mcap", id="missing-file"),
        pytest.param({"crs": "EPSG:4326"}, "is not a UTM zone", id="not-utm"),
        pytest.param({"camera_id": "bad/camera"}, "camera_id", id="bad-camera-id"),
        pytest.param({"window_start_ns": 0, "window_end_ns": 10}, "window_start_ns", id="window-in-seconds"),
        pytest.param(
            {"window_end_ns": 1_700_000_000_000_000_000}, "is before window_start_ns", id="inverted"
        ),
        pytest.param({"timeout_s": 0.0}, "timeout_s = 0.0 must be a positive", id="no-time"),
        pytest.param({"timeout_s": math.nan}, "timeout_s = nan must be a positive", id="nan-time"),
    ],
)
def test_failures_become_outcome_errors(scene: Scene, change: dict[str, object], expected: str) -> None:
    outcome = run_job(dataclasses.replace(scene.spec, **change))  # type: ignore[arg-type]
    assert outcome.result_json is None
    assert outcome.error is not None and expected in outcome.error
    assert outcome.job_id == scene.spec.job_id


def test_unreadable_recording_is_an_error_a_damaged_one_among_good_ones_a_note(
    scene: Scene, tmp_path: Path
) -> None:
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_text("hello")
    alone = run_job(dataclasses.replace(scene.spec, recordings=(str(not_mcap),)))
    assert alone.error is not None and "not an MCAP file" in alone.error

    # The same bad file beside a good recording: the job runs on what can be read and says what was not.
    # A window of the first 40 s keeps this quick (refused: too little of the vehicle).
    start = scene.spec.window_start_ns
    mixed = run_job(
        dataclasses.replace(
            scene.spec, recordings=(str(not_mcap), str(scene.mcap)), window_end_ns=start + 40 * 10**9
        )
    )
    assert mixed.error is None and mixed.detections > 0 and mixed.poses > 0
    assert any("not an MCAP file" in note for note in mixed.stage_notes)


def test_a_bug_in_the_job_is_caught_with_its_traceback(scene: Scene, monkeypatch: pytest.MonkeyPatch) -> None:
    def broken_calibrate(*args: object, **kwargs: object) -> None:
        raise TypeError("simulated bug")

    monkeypatch.setattr(jobs, "calibrate", broken_calibrate)
    outcome = run_job(dataclasses.replace(scene.spec, window_end_ns=scene.spec.window_start_ns + 20 * 10**9))
    assert outcome.error == "internal error: TypeError: simulated bug"
    assert any("broken_calibrate" in note for note in outcome.stage_notes if note.startswith("traceback: "))


# ---------------------------------------------------------------------------------------------- time limits


def test_a_job_past_its_time_limit_fails_and_the_next_one_runs(scene: Scene, warm: Warm) -> None:
    # The whole sil-west job takes ~2.5 s; half a second ends it while it is still reading the window.
    slow = dataclasses.replace(scene.spec, job_id="slow", timeout_s=0.5)
    outcome = warm.runner.submit(slow).result(timeout=JOB_TIMEOUT_S)
    assert (outcome.job_id, outcome.result_json, outcome.error) == ("slow", None, "timed out after 0.5 s")
    assert 0.5 <= outcome.duration_s < 0.5 + JOB_TIMEOUT_S / 10
    assert _alive(warm.worker) and not _descendants(warm.worker)
    wait_until(lambda: warm.runner.running() == 0, timeout_s=5.0)

    # The camera's next job runs in the same worker, with the default 900 s, and calibrates.
    assert scene.spec.timeout_s == 900.0
    result = _result_of(warm.runner.submit(scene.spec).result(timeout=JOB_TIMEOUT_S))
    assert result.verdict.is_accepted, result.verdict.reasons
    assert _alive(warm.worker)


def test_the_time_limit_stops_the_track_pool_and_keeps_the_worker(scene: Scene, warm: Warm) -> None:
    future = warm.runner.submit(scene.spec)
    # Once the job's track pool is at work, deliver what the job's own timer delivers at its limit: the
    # test decides when (inside calibrate(), with processes to stop), not the machine's speed. At work:
    # both forked and busy, so the worker is past fork() (whose callbacks swallow exceptions, which the
    # real timer survives by repeating; this single signal would not).
    wait_until(
        lambda: len(busy := _descendants(warm.worker)) == 2 and all(_cpu_ticks(pid) > 1 for pid in busy),
        timeout_s=JOB_TIMEOUT_S,
    )
    track_workers = _descendants(warm.worker)
    os.kill(warm.worker, signal.SIGALRM)
    outcome = future.result(timeout=JOB_TIMEOUT_S)
    assert outcome.error == "timed out after 900 s"
    # What the job had found is kept: the window's counts and notes.
    assert outcome.detections == len(scene.sim.detections[scene.spec.camera_id]) and outcome.poses > 0
    assert any(note.startswith("window: ") for note in outcome.stage_notes)
    assert not any(_alive(pid) for pid in track_workers)
    assert not _descendants(warm.worker) and _alive(warm.worker)


# The timed-out job's SIGALRM may land in a callback that cannot let the JobTimeout out (hypothesis's GC
# callback, seen in a CI run): Python prints "Exception ignored" and the repeating timer raises again, the
# designed way out (test_a_swallowed_timeout_is_raised_again). pytest reports the ignored one as a warning.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_run_job_disarms_its_timer_and_restores_the_handler(scene: Scene) -> None:
    def mine(signum: int, frame: object) -> None:
        raise AssertionError("SIGALRM after the job")

    previous = signal.signal(signal.SIGALRM, mine)
    try:
        done = run_job(dataclasses.replace(scene.spec, station_id=scene.sim.station_id + 1, timeout_s=60.0))
        assert done.error is None
        timed_out = run_job(dataclasses.replace(scene.spec, timeout_s=0.2))
        assert timed_out.error == "timed out after 0.2 s"
        assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)
        assert signal.getsignal(signal.SIGALRM) is mine
    finally:
        signal.signal(signal.SIGALRM, previous)


def test_a_swallowed_timeout_is_raised_again() -> None:
    # As when the signal lands in an os.fork() callback or a __del__: Python prints "Exception ignored"
    # and carries on; the timer repeats, so the job still ends.
    swallowed = 0
    with pytest.raises(JobTimeout), _time_limit(0.05):
        try:
            wait_until(lambda: False, timeout_s=5.0)
        except JobTimeout:
            swallowed += 1
        wait_until(lambda: False, timeout_s=5.0)
    assert swallowed == 1
    assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)


def test_the_repeating_timer_spares_the_cleanup_of_a_timeout() -> None:
    cleaned_up = False
    with pytest.raises(JobTimeout), _time_limit(0.05):
        try:
            wait_until(lambda: False, timeout_s=5.0)
        finally:
            # A cleanup (killing and reaping a track pool) longer than the repeat interval runs to its end.
            cleanup_done = time.monotonic() + 2.5 * TIMEOUT_RETRY_S
            wait_until(lambda: time.monotonic() > cleanup_done, timeout_s=5.0)
            cleaned_up = True
    assert cleaned_up


def test_a_worker_deaf_to_its_time_limit_is_killed_and_queued_jobs_move_on(scene: Scene) -> None:
    before = _worker_pids()
    job_runner = JobRunner(1, kill_grace_s=0.5)
    try:
        (worker,) = _worker_pids() - before
        stuck = job_runner.submit(dataclasses.replace(scene.spec, job_id="stuck", timeout_s=3.0))
        quick = dataclasses.replace(scene.spec, station_id=scene.sim.station_id + 1)  # refused at once
        queued = [job_runner.submit(dataclasses.replace(quick, job_id=f"queued-{i}")) for i in range(4)]
        wait_until(lambda: _descendants(worker), timeout_s=JOB_TIMEOUT_S)
        processes = {worker} | _descendants(worker)
        # Stopped, it cannot run its timer's handler: as stuck as a native call that never returns.
        os.kill(worker, signal.SIGSTOP)

        outcome = stuck.result(timeout=JOB_TIMEOUT_S)
        assert outcome.error == "timed out after 3 s: the worker did not stop and was killed"
        assert outcome.result_json is None and outcome.duration_s >= 3.5
        wait_until(lambda: not any(_alive(pid) for pid in processes), timeout_s=10.0)

        # Every other job of the killed pool (in its call queue or still queued) runs in the new pool.
        finished = [future.result(timeout=JOB_TIMEOUT_S) for future in queued]
        assert [o.job_id for o in finished] == [f"queued-{i}" for i in range(4)]
        assert all(o.error is None for o in finished)
        (new_worker,) = _worker_pids() - before
        assert new_worker != worker
        assert job_runner.running() == 0
    finally:
        job_runner.shutdown(timeout_s=5.0)


def test_shutdown_mid_job_cancels_the_queue_and_leaves_no_process(scene: Scene) -> None:
    before = _worker_pids()
    job_runner = JobRunner(2)
    workers = _worker_pids() - before
    assert len(workers) == 2  # both started (and warmed) before any job
    # 2 running + 3 in the pool's call queue (max_workers + 1) cannot be cancelled; the 6th is still queued.
    futures = [job_runner.submit(dataclasses.replace(scene.spec, job_id=f"job-{i}")) for i in range(6)]
    assert job_runner.running() == 6
    # Wait until the jobs' own track pools (forked from the workers) exist: the orphans to be avoided.
    wait_until(lambda: any(_descendants(pid) for pid in workers), timeout_s=JOB_TIMEOUT_S)
    processes = workers | {child for pid in workers for child in _descendants(pid)}
    job_runner.shutdown(timeout_s=0.0)

    assert not any(_alive(pid) for pid in processes)
    assert not (_worker_pids() & workers)
    for future in futures:
        assert future.done()
        with pytest.raises((CancelledError, BrokenProcessPool)):
            future.result(timeout=0)
    assert futures[-1].cancelled()  # never handed to a worker
    assert job_runner.running() == 0
    with pytest.raises(RuntimeError, match="shut down"):
        job_runner.submit(scene.spec)
    job_runner.shutdown(timeout_s=0.0)  # idempotent


def test_a_worker_that_died_is_replaced(scene: Scene) -> None:
    before = _worker_pids()
    job_runner = JobRunner(1)
    try:
        (worker,) = _worker_pids() - before
        os.kill(worker, signal.SIGKILL)  # what the kernel's OOM killer does
        quick = dataclasses.replace(scene.spec, station_id=scene.sim.station_id + 1)  # refused at once
        # A job submitted before the pool noticed the death fails with BrokenProcessPool (the daemon counts
        # it as failed); the next submit starts a fresh pool and runs.
        outcomes: list[JobOutcome] = []
        for _attempt in range(2):
            try:
                outcomes.append(job_runner.submit(quick).result(timeout=JOB_TIMEOUT_S))
                break
            except BrokenProcessPool:
                continue
        assert len(outcomes) == 1 and outcomes[0].error is None
        assert not _alive(worker)
    finally:
        job_runner.shutdown(timeout_s=5.0)
    assert job_runner.running() == 0


# ------------------------------------------------------------------------------------- dying with the daemon

_DAEMON = """
import pickle, sys
from pathlib import Path
from daemon.pool import JobRunner
runner = JobRunner(1)
runner.submit(pickle.loads(Path(sys.argv[1]).read_bytes()))
print("submitted", flush=True)
sys.stdin.read()  # until the test kills this process
"""


def test_a_killed_daemon_leaves_no_worker_behind(scene: Scene, tmp_path: Path) -> None:
    spec_path = tmp_path / "spec.pickle"
    spec_path.write_bytes(pickle.dumps(scene.spec))
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    process = subprocess.Popen(
        [sys.executable, "-c", _DAEMON, str(spec_path)],
        cwd=ROOT,
        env=env,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None
        assert process.stdout.readline().strip() == "submitted"
        # The job worker and the track pool it forked: processes two levels below the "daemon".
        tree: set[int] = set()

        def job_running() -> bool:
            tree.clear()
            tree.update(_descendants(process.pid))
            return any(_parent(pid) in tree for pid in tree)

        wait_until(job_running, timeout_s=JOB_TIMEOUT_S)
        assert len(tree) >= 3  # worker + 2 track-pool processes (and multiprocessing's resource tracker)
        process.kill()  # SIGKILL: no shutdown code of the daemon runs
        process.wait(timeout=10)
        wait_until(lambda: not any(_alive(pid) for pid in tree), timeout_s=10.0)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(timeout=10)


def test_a_runner_made_on_a_passing_thread_keeps_its_workers(scene: Scene) -> None:
    # The kernel's parent-death signal fires when the *thread* that created a worker ends; the runner
    # creates its pools on a thread of its own, so the caller's thread may come and go.
    before = _worker_pids()
    made: list[JobRunner] = []
    thread = threading.Thread(target=lambda: made.append(JobRunner(1)))
    thread.start()
    thread.join()
    (job_runner,) = made
    try:
        (worker,) = _worker_pids() - before
        quick = dataclasses.replace(scene.spec, station_id=scene.sim.station_id + 1)
        assert job_runner.submit(quick).result(timeout=JOB_TIMEOUT_S).error is None
        assert _alive(worker)
    finally:
        job_runner.shutdown(timeout_s=5.0)


# ---------------------------------------------------------------------------------------------- helpers


def test_job_ids_name_the_camera_and_sort_by_time() -> None:
    assert new_job_id("west-arm", 1_717_000_000_000_000_000) == "west-arm-1717000000000000000"
    assert new_job_id("c", 5) < new_job_id("c", 10)
