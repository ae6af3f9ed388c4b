"""Reasons as values (pipeline.stage): rendered to text where shown, counted by rule, never parsed."""

from __future__ import annotations

from pipeline.stage import Reason, StageReport, count_reasons


def far(distance_m: float, limit_m: float = 40.0) -> Reason:
    return Reason(
        "far_from_path",
        "camera {value} m from the driven path > {limit} m",
        "camera distance from the driven path",
        distance_m,
        limit_m,
        "m",
    )


def test_a_reason_renders_its_value_and_limit_and_keeps_its_numbers() -> None:
    reason = far(42.25)
    assert str(reason) == reason.render() == "camera 42.2 m from the driven path > 40.0 m"
    assert (reason.code, reason.quantity, reason.value, reason.limit, reason.unit) == (
        "far_from_path",
        "camera distance from the driven path",
        42.25,
        40.0,
        "m",
    )
    counted = Reason("too_few", "too few correspondences: {value} < {limit}", "n", 6, 8, value_format="d")
    assert str(counted) == "too few correspondences: 6 < 8"
    # Detail follows the sentence (braces in it are words, not a format).
    failed = Reason("epnp_failed", "degenerate: EPnP + RANSAC failed", detail=" (bad {input})")
    assert str(failed) == "degenerate: EPnP + RANSAC failed (bad {input})"
    assert str(failed.with_detail("; more")) == "degenerate: EPnP + RANSAC failed (bad {input}); more"


def test_reasons_are_counted_by_rule_and_limit_with_their_value_range() -> None:
    isolated = Reason("isolated", "isolated: no similar hypothesis", detail=" (closest: track 7)")
    reasons = [far(42.2), isolated, far(313.0), far(57.25), far(50.0, limit_m=45.0), isolated]
    counts = count_reasons(reasons)
    assert [(c.example.code, c.count, c.low, c.high) for c in counts] == [
        ("far_from_path", 3, 42.2, 313.0),
        ("isolated", 2, None, None),
        ("far_from_path", 1, 50.0, 50.0),
    ]
    assert [c.render() for c in counts] == [
        "3 x camera 42.2..313.0 m from the driven path > 40.0 m",
        "2 x isolated: no similar hypothesis",  # the detail of one case is not counted
        "1 x camera 50.0 m from the driven path > 45.0 m",
    ]
    assert count_reasons([]) == ()


def test_a_stage_report_lists_its_notes_then_its_counted_reasons() -> None:
    report = StageReport("grouping", 1, 2, ("group 0: tracks [1, 2]",), count_reasons([far(41.0), far(41.0)]))
    assert report.lines() == ("group 0: tracks [1, 2]", "2 x camera 41.0 m from the driven path > 40.0 m")
    assert StageReport("tracking", 3, 0).lines() == ()
