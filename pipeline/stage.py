"""What one stage of calibrate() kept and discarded, and why: each stage returns its own report.

Why something was left out is a value (`Reason`: the rule, the quantity measured, its value and the limit it
failed), rendered to text only where it is shown (`render`, `str()`); the report counts the reasons of a stage
by rule (`ReasonCount`), never by parsing their text.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Reason:
    """Why a track or hypothesis was left out.

    code: the rule that failed (stable, e.g. 'too_few_correspondences'); quantity: what was measured, with
    value (None where the rule has no measurement) and the limit it failed, both in `unit`; text: the
    sentence, with {value} and {limit} where they go (value written with `value_format`, the limit as
    configured); detail: words that follow the sentence for this case only (not counted, e.g. the solver's
    message or the closest partner).
    """

    code: str
    text: str
    quantity: str = ""
    value: float | None = None
    limit: float | None = None
    unit: str = ""
    value_format: str = ".1f"
    detail: str = ""

    def render(self) -> str:
        return _sentence(self, _number(self.value, self.value_format)) + self.detail

    def __str__(self) -> str:
        return self.render()

    def with_detail(self, detail: str) -> Reason:
        return Reason(
            self.code,
            self.text,
            self.quantity,
            self.value,
            self.limit,
            self.unit,
            self.value_format,
            self.detail + detail,
        )


@dataclass(frozen=True, slots=True)
class ReasonCount:
    """`count` reasons of one rule with the same sentence and limit; their values from `low` to `high`."""

    example: Reason
    count: int
    low: float | None
    high: float | None

    def render(self) -> str:
        """'3 x camera 42.2..57.3 m from the driven path > 40.0 m' (one value when all agree)."""
        fmt = self.example.value_format
        low, high = _number(self.low, fmt), _number(self.high, fmt)
        return f"{self.count} x {_sentence(self.example, low if low == high else f'{low}..{high}')}"


def count_reasons(reasons: Iterable[Reason]) -> tuple[ReasonCount, ...]:
    """The reasons counted by (rule, sentence, limit), most frequent first (ties in order of appearance)."""
    groups: dict[tuple[str, str, float | None], list[Reason]] = {}
    for reason in reasons:
        groups.setdefault((reason.code, reason.text, reason.limit), []).append(reason)
    counts = []
    for members in groups.values():
        values = [r.value for r in members if r.value is not None]
        low, high = (min(values), max(values)) if values else (None, None)
        counts.append(ReasonCount(members[0], len(members), low, high))
    return tuple(sorted(counts, key=lambda c: -c.count))


@dataclass(frozen=True, slots=True)
class StageReport:
    """What one stage kept and discarded, and why (for --verbose and the daemon's status): notes in words,
    and the reasons for what was discarded counted by rule."""

    stage: str
    kept: int
    discarded: int
    notes: tuple[str, ...] = ()
    reasons: tuple[ReasonCount, ...] = ()

    def lines(self) -> tuple[str, ...]:
        """The notes, then one line per counted reason."""
        return (*self.notes, *(count.render() for count in self.reasons))


def _number(value: float | None, fmt: str) -> str:
    return "?" if value is None else format(value, fmt)


def _sentence(reason: Reason, value: str) -> str:
    return reason.text.format(value=value, limit=reason.limit)
