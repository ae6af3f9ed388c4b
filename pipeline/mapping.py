"""MapFn: how the pipeline runs independent pieces of work (per-track hypotheses, left-out fits).

The caller passes `map` or a drop-in replacement such as a process pool's map (daemon.workers.track_pool);
the pipeline starts no workers itself, and results must not depend on which one runs them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, TypeAlias

MapFn: TypeAlias = Callable[..., Iterable[Any]]
