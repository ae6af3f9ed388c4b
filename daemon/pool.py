"""The job process pool: spawned worker processes running daemon.jobs.run_job, with a watchdog.

JobRunner keeps `max_parallel` spawned workers, started and warmed (pipeline imported) when the daemon
starts. A job's own timer ends it at its time limit (daemon.jobs.run_job); as a backstop each worker reports
which job it starts and the watchdog kills a worker still running its job `kill_grace_s` after the limit.

Worker processes die with their parent (prctl PR_SET_PDEATHSIG on Linux, daemon.workers.die_with_parent):
a daemon killed with SIGKILL leaves no job worker or track-pool process behind.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
import threading
import time
import weakref
from concurrent.futures import Future, InvalidStateError, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from types import FrameType

from daemon.jobs import JobOutcome, JobSpec, run_job
from daemon.workers import descendant_pids, die_with_parent, kill_pid

log = logging.getLogger(__name__)

WARM_TIMEOUT_S = 120.0  # spawning a worker and importing the pipeline takes ~2 s; a slow SD card, more
# After SIGTERM a worker stops its own track-pool processes and exits; this long, then SIGKILL for all.
TERMINATE_GRACE_S = 0.5
# A job past its time limit normally ends within milliseconds (its timer's exception); a worker that has not
# answered this long after the limit is stuck in native code and is killed from the daemon's side.
KILL_GRACE_S = 30.0
_WATCH_MAX_WAIT_S = 3600.0  # the watchdog's longest sleep (poll() takes no more than ~24 days anyway)

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
    worker did not stop and was killed"; the pool is replaced at once, and every other unfinished job of
    the killed pool (queued, in its call queue, or running on a worker the broken pool terminates) runs
    again in the new one. A worker that dies of other causes (out of memory) fails its pool's jobs with
    BrokenProcessPool.

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
        # Pools the watchdog broke: their other jobs run again (weak: a replaced pool is not kept for this).
        self._killed_pools: weakref.WeakSet[ProcessPoolExecutor] = weakref.WeakSet()
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
        killed worker, or run the job again if a pool replacement cancelled it, or if the watchdog's kill of
        another job's worker broke its pool."""
        with self._lock:
            job = self._jobs.get(seq)
            ran_s = self._killed.pop(seq, None)
            if job is None or job.task is not task:
                return  # the caller cancelled its future (see _forget)
            retry: Future[JobOutcome] | None = None
            broken_by_us = (
                ran_s is None
                and job.pool in self._killed_pools
                and not task.cancelled()
                and isinstance(task.exception(), BrokenProcessPool)
            )
            if (task.cancelled() or broken_by_us) and not self._closed:
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
            self._killed_pools.add(job.pool)
            stale = self._replace_pool_locked() if self._pool is job.pool else None
        # The pool's other jobs fail with BrokenProcessPool once the kill breaks it, and _settle runs them
        # again in the new pool. They are not cancelled here: CPython 3.11's pool manager sets that error on
        # every work item it still holds, and on one cancelled a moment before it raised InvalidStateError
        # and died mid-cleanup (a full suite's worker process misbehaved from then on). The kill comes
        # before the log line: nothing the watchdog does after deciding may stand between it and the kill
        # (a full suite once hung with this thread waiting on the logging module's lock, the worker alive).
        for child in descendant_pids(pid):
            kill_pid(child)
        kill_pid(pid)
        log.warning(
            "job %s (camera %s) still running %.0f s after its %g s time limit: killed its worker (pid %d)",
            job.spec.job_id,
            job.spec.camera_id,
            self.kill_grace_s,
            job.spec.timeout_s,
            pid,
        )
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
        # Bounded: the sentinel wakes the watchdog at once, and a shutdown must not hang on it if something
        # it called is stuck (it is a daemon thread: it cannot keep the process alive either).
        self._watchdog.join(timeout=10.0)
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
