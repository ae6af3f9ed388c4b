"""daemon.workers: track pools that map like `map`, stop at once when left by an exception, and whose
processes die with their parent (prctl PR_SET_PDEATHSIG), including a parent that died before they could ask.

Processes are found through /proc with the test's own reader, not the module's helpers.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from helpers import wait_until

from daemon.workers import chunk_size, track_pool

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
PR_GET_PDEATHSIG = 2

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl and /proc are Linux")


def _stat(pid: int) -> list[bytes] | None:
    """The fields of /proc/pid/stat after `pid (comm)`: state, ppid, ...; None once gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_bytes()
    except OSError:
        return None
    return stat[stat.rfind(b")") + 2 :].split()


def _alive(pid: int) -> bool:
    fields = _stat(pid)
    return fields is not None and fields[0] != b"Z"


def _children(pid: int) -> set[int]:
    """Live (non-zombie) children of `pid`."""
    found: set[int] = set()
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            fields = _stat(int(entry))
            if fields is not None and fields[0] != b"Z" and int(fields[1]) == pid:
                found.add(int(entry))
    return found


def _run(script: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)],
        cwd=ROOT,
        env=ENV,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


# ---------------------------------------------------------------------------------------------- the pool


def test_a_pool_maps_like_map_and_ends_with_its_block() -> None:
    before = _children(os.getpid())
    with track_pool(2) as map_fn:
        assert list(map_fn(abs, range(-20, 0))) == list(range(20, 0, -1))
        assert list(map_fn(pow, [2, 3], [3, 2])) == [8, 9]
        pool_processes = _children(os.getpid()) - before
        assert len(pool_processes) == 2
    assert not any(_alive(pid) for pid in pool_processes)
    with track_pool(1) as map_fn:
        assert map_fn is map  # no processes for one worker


@pytest.mark.parametrize(
    ("items", "workers", "expected"),
    [(613, 2, 8), (16, 2, 8), (15, 2, 7), (2, 2, 1), (1, 2, 1), (0, 2, 1), (6, 1, 6)],
)
def test_chunks_shrink_so_few_items_still_reach_every_worker(items: int, workers: int, expected: int) -> None:
    # The final fit maps its two model classes' leave-one-out fits: one chunk of two would run on one worker.
    assert chunk_size(items, workers, 8) == expected


@linux_only
def test_leaving_the_block_by_an_exception_kills_the_workers_at_once() -> None:
    before = _children(os.getpid())
    started = time.monotonic()
    with pytest.raises(RuntimeError, match="time is up"), track_pool(2, chunksize=1) as map_fn:
        map_fn(time.sleep, [30.0] * 8)  # 2 running, the rest queued: 2 minutes of work
        wait_until(lambda: len(_children(os.getpid()) - before) == 2, timeout_s=10)
        pool_processes = _children(os.getpid()) - before
        raise RuntimeError("time is up")  # what a job's JobTimeout does inside calibrate()
    # Killed, not drained: a normal exit would wait for the sleeps.
    assert time.monotonic() - started < 20.0
    assert not any(_alive(pid) for pid in pool_processes)


# ------------------------------------------------------------------------------------- dying with the parent


@linux_only
def test_die_with_parent_asks_the_kernel_for_sigkill() -> None:
    done = _run(
        f"""
        import ctypes, os
        from daemon.workers import die_with_parent
        die_with_parent(os.getppid())
        signal_number = ctypes.c_int(-1)
        ctypes.CDLL(None).prctl({PR_GET_PDEATHSIG}, ctypes.byref(signal_number), 0, 0, 0)
        print(signal_number.value)
        """
    )
    assert done.returncode == 0, done.stderr
    assert int(done.stdout) == signal.SIGKILL


@linux_only
def test_a_worker_whose_parent_died_before_it_asked_kills_itself() -> None:
    # As after a parent's death between fork() and die_with_parent(): getppid() is no longer the pid the
    # parent passed (the orphan now belongs to init or a subreaper), and no death signal will ever come.
    done = _run(
        """
        import os
        from daemon.workers import die_with_parent
        die_with_parent(os.getppid() + 1)
        print("survived")
        """
    )
    assert done.returncode == -signal.SIGKILL, done.stderr
    assert "survived" not in done.stdout


_POOL_IN_A_PROCESS = """
import sys, time
from daemon.workers import track_pool
with track_pool(2) as map_fn:
    map_fn(time.sleep, [60.0] * 4)
    print("mapping", flush=True)
    sys.stdin.read()  # until the test kills this process
"""


@linux_only
def test_pool_workers_die_with_a_killed_parent() -> None:
    process = subprocess.Popen(
        [sys.executable, "-c", _POOL_IN_A_PROCESS],
        cwd=ROOT,
        env=ENV,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None
        assert process.stdout.readline().strip() == "mapping"
        wait_until(lambda: len(_children(process.pid)) == 2, timeout_s=10)
        pool_processes = _children(process.pid)
        process.kill()  # SIGKILL: no cleanup code of the parent runs
        process.wait(timeout=10)
        wait_until(lambda: not any(_alive(pid) for pid in pool_processes), timeout_s=10)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(timeout=10)
