"""Shared pieces of the benchmarks: thread limits, calibrate() inputs from a simulation, and stage timings
from calibrate()'s progress callback.

Nothing here imports numpy at module level, so `limit_threads()` can run before the first numpy import.
"""

from __future__ import annotations

import os
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pipeline.calibrate import CalibrationInputs
    from sim.simulate import SimulationResult

# The presets of issue 10's accepted-share target (bench.ablation's and bench.bound's default).
CORE_PRESETS = (
    "sil-north",
    "sil-south",
    "sil-west",
    "dense-traffic",
    "occluded",
    "slope",
    "crowned-road",
    "latency",
    "suv",
    "van",
)
THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
REPO_ROOT = Path(__file__).resolve().parents[1]


def limit_threads(threads: int = 1) -> None:
    """Set the BLAS/OpenMP thread counts in os.environ: effective for numpy imported after this call, in
    this process or in any process started from it (spawn inherits the environment)."""
    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)


def inputs_for(sim: SimulationResult, camera_id: str) -> CalibrationInputs:
    """calibrate() inputs for one camera of a simulation, with the true clock offset as the known one."""
    from daemon.offline import inputs_from_simulation

    return inputs_from_simulation(sim, camera_id)


@dataclass
class StageClock:
    """calibrate()'s progress callback that records when each stage started (perf_counter seconds)."""

    start_s: float = field(default_factory=time.perf_counter)
    marks: list[tuple[str, float]] = field(default_factory=list)

    def __call__(self, stage: str, fraction: float) -> None:
        self.marks.append((stage, time.perf_counter()))

    def durations(self, end_s: float | None = None) -> dict[str, float]:
        """Seconds per stage name (a stage reported several times, e.g. refinement per group, is summed
        from its first report to the next different stage). The time before the first report is
        'setup'; the last stage runs to `end_s` (default: now)."""
        end = time.perf_counter() if end_s is None else end_s
        out: dict[str, float] = {}
        previous_stage, previous_s = "setup", self.start_s
        for stage, at_s in [*self.marks, ("", end)]:
            if stage == previous_stage:
                continue
            out[previous_stage] = out.get(previous_stage, 0.0) + at_s - previous_s
            previous_stage, previous_s = stage, at_s
        return out


def tree_state(packages: Sequence[str]) -> str:
    """The code under test: HEAD and the uncommitted files of `packages` (repository-relative folders)."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", *packages],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.split("\n")
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"
    changed = sorted(line[3:] for line in dirty if line.strip())
    return f"{head}" + (f" + uncommitted {', '.join(changed)}" if changed else " (clean)")


def load_average() -> str:
    """The 1, 5 and 15 minute load averages, e.g. "0.52 / 0.80 / 1.10"."""
    return " / ".join(f"{value:.2f}" for value in os.getloadavg())


@dataclass(frozen=True, slots=True)
class ProcessUsage:
    """A process's CPU time so far (user + system, s) and resident set now (bytes), from /proc (Linux)."""

    cpu_s: float
    rss_bytes: int


def process_usage(pid: int | None = None) -> ProcessUsage:
    """CPU seconds and VmRSS of `pid` (default: this process); its threads included, its children not."""
    proc = Path("/proc") / (str(pid) if pid is not None else "self")
    # /proc/PID/stat: the command name may contain spaces, so split after its closing parenthesis;
    # utime and stime are then fields 12 and 13 (in clock ticks).
    fields = (proc / "stat").read_text().rsplit(")", 1)[1].split()
    cpu_s = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    rss_bytes = 0
    for line in (proc / "status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            rss_bytes = int(line.split()[1]) * 1024
            break
    return ProcessUsage(cpu_s, rss_bytes)
