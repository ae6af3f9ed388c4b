"""Hypothesis in CI: with CI set (as .ci/run's environment has it), every property test draws the same
examples on every run and keeps no example database, so a landing is judged on the code, not on the draw.
A developer's run (no CI) explores new examples each time, which is how property tests find new cases;
a failure found that way is pinned with @example before it is fixed."""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
