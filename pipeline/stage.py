"""What one stage of calibrate() kept and discarded, and why: each stage returns its own report."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class StageReport:
    """What one stage kept and discarded, and why (for --verbose and the daemon's status)."""

    stage: str
    kept: int
    discarded: int
    notes: tuple[str, ...] = ()


def summarise_reasons(reasons: Mapping[int, str]) -> tuple[str, ...]:
    """Count identical reasons (the part before the first ':' or '=') so --verbose stays readable."""
    counts: dict[str, int] = {}
    for reason in reasons.values():
        key = str(reason).split(":")[0].split("=")[0].strip()
        counts[key] = counts.get(key, 0) + 1
    return tuple(f"{n} x {key}" for key, n in sorted(counts.items(), key=lambda kv: -kv[1]))
