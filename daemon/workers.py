"""Process pools for the pipeline's independent per-track work (the pipeline itself starts no workers), and
the process-tree helpers the daemon's worker processes share: die with the parent, find and kill descendants.

calibrate(..., map_fn=...) fits one hypothesis per image track; on a 2-core RSU a pool of two processes
nearly halves that stage, which dominates a long recording. Results are identical to plain `map`.
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import os
import signal
import sys
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any

from pipeline.mapping import MapFn

_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(parent_pid: int) -> None:
    """Make this (worker) process get SIGKILL when its parent dies; call it first thing in the worker.

    Linux prctl(PR_SET_PDEATHSIG); elsewhere only the check below. The parent may have died before the
    call (then the signal never comes: this process was already re-parented), so getppid() is compared
    with `parent_pid`, the parent's pid as the parent saw it, and on a mismatch the process kills itself.
    The kernel sends the signal when the *thread* that created this process ends, not only the process:
    create worker processes from a thread that lives as long as they should (the main thread, or a
    long-lived one such as the daemon's ingest thread).
    """
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        unused = ctypes.c_ulong(0)
        if libc.prctl(_PR_SET_PDEATHSIG, ctypes.c_ulong(signal.SIGKILL), unused, unused, unused) != 0:
            errno = ctypes.get_errno()
            raise OSError(errno, f"prctl(PR_SET_PDEATHSIG): {os.strerror(errno)}")
    if os.getppid() != parent_pid:
        os.kill(os.getpid(), signal.SIGKILL)  # what the kernel would have done, had we been in time


def _init_track_worker(parent_pid: int) -> None:
    """Track-pool worker start-up: die with the process that forked it (a job worker killed for its
    timeout, the CLI interrupted); and one BLAS thread: the per-track fits are tiny, more threads would
    only fight over the cores."""
    die_with_parent(parent_pid)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)


def chunk_size(items: int, workers: int, largest: int) -> int:
    """Items per chunk a pool of `workers` hands out for `items` items: `largest`, fewer when that would
    leave a worker without a chunk (at least 1)."""
    return max(1, min(largest, items // max(workers, 1)))


@contextmanager
def track_pool(workers: int | None = None, chunksize: int = 8) -> Iterator[MapFn]:
    """A map function backed by `workers` processes (default: the machine's cores); plain map for 1.

    Leaving the block normally waits for the workers to finish; leaving it by an exception (a job's time
    limit, Ctrl-C, a failed stage), or an exception during that wait, kills them at once instead of
    letting the queued chunks run out.
    """
    count = workers if workers is not None else (os.cpu_count() or 1)
    if count <= 1:
        yield map
        return
    # fork: workers start in milliseconds and share the parent's loaded modules; the callers (CLI, bench,
    # the daemon's job process) create the pool before any thread of their own exists.
    context = multiprocessing.get_context("fork")
    parent_pid = os.getpid()
    children_before = set(child_pids(parent_pid))
    pool = ProcessPoolExecutor(
        max_workers=count, mp_context=context, initializer=_init_track_worker, initargs=(parent_pid,)
    )

    def pool_map(fn: Callable[..., Any], *iterables: Iterable[Any]) -> Iterable[Any]:
        # Chunks of at most `chunksize` items, fewer when the items are few: the final fit's two model
        # classes (or a short track list) still run on two workers, not as one chunk on one.
        columns = [list(items) for items in iterables]
        items = min((len(column) for column in columns), default=0)
        return pool.map(fn, *columns, chunksize=chunk_size(items, count, chunksize))

    try:
        yield pool_map
        pool.shutdown(wait=True)
    except BaseException:
        # The pool's own list misses a worker forked a moment ago (registered only after fork() returns
        # to Python, which the exception may have interrupted); this process's new children do not. The
        # callers run no other thread that starts processes, so every new child is the pool's.
        workers_now = set(child_pids(parent_pid)) - children_before
        workers_now.update(p.pid for p in (pool._processes or {}).values() if p.pid is not None)
        for pid in workers_now:
            kill_pid(pid)
        # The management thread sees the deaths, fails the outstanding futures and reaps the workers.
        pool.shutdown(wait=True, cancel_futures=True)
        raise


# ---------------------------------------------------------------------------------------------- process tree


def _parents() -> dict[int, list[int]]:
    """ppid -> live child pids, from Linux /proc ({} elsewhere)."""
    parents: dict[int, list[int]] = {}
    try:
        entries = os.listdir("/proc")
    except OSError:
        return parents
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
    return parents


def child_pids(pid: int) -> list[int]:
    """The direct children of `pid` (Linux /proc; [] elsewhere)."""
    return _parents().get(pid, [])


def descendant_pids(pid: int) -> list[int]:
    """Every descendant of `pid` (Linux /proc; [] elsewhere)."""
    parents = _parents()
    found: list[int] = []
    frontier = [pid]
    while frontier:
        children = parents.get(frontier.pop(), [])
        found.extend(children)
        frontier.extend(children)
    return found


def kill_pid(pid: int) -> None:
    """SIGKILL `pid`; nothing if it has exited meanwhile."""
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)
