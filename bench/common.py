"""Shared pieces of the benchmarks: thread limits, calibrate() inputs from a simulation, and stage timings
from calibrate()'s progress callback.

Nothing here imports numpy at module level, so `limit_threads()` can run before the first numpy import.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pipeline.calibrate import CalibrationInputs
    from pipeline.simulate import SimulationResult

THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def limit_threads(threads: int = 1) -> None:
    """Set the BLAS/OpenMP thread counts in os.environ: effective for numpy imported after this call, in
    this process or in any process started from it (spawn inherits the environment)."""
    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)


def inputs_for(sim: SimulationResult, camera_id: str) -> CalibrationInputs:
    """calibrate() inputs for one camera of a simulation, with the true clock offset as the known one."""
    from pipeline.simulate import calibration_inputs

    return calibration_inputs(sim, camera_id)


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
