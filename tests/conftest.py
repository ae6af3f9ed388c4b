"""Settings for the whole test run.

BLAS on one thread: the suite runs in two worker processes (pytest-xdist, `-n 2`) on two cores, and each
worker's OpenBLAS starting a thread per core oversubscribed them: a test of vehicle-model fits took 61 s
with two workers against 21 s alone (each worker's BLAS threads spinning beside the other's). The
pipeline's tiny matrices gain nothing from BLAS threads anyway (`pipeline.calibrate` holds one thread for
the same reason).

Hypothesis in CI: with CI set (as .ci/run's environment has it), every property test draws the same
examples on every run and keeps no example database, so a landing is judged on the code, not on the draw.
A developer's run (no CI) explores new examples each time, which is how property tests find new cases;
a failure found that way is pinned with @example before it is fixed."""

from __future__ import annotations

import os

# Before NumPy and SciPy load their OpenBLAS builds (each has its own), so that processes the tests start
# inherit it too; threadpoolctl then limits libraries already loaded (it sees only those).
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import numpy  # noqa: E402, F401  (loaded for threadpool_limits below)
import scipy.linalg  # noqa: E402, F401  (its own OpenBLAS)
from hypothesis import settings  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

threadpool_limits(limits=1)

settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
