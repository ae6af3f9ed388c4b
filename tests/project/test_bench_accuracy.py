"""bench.accuracy's summaries: every std source has a tag in the table, and the coverage line counts the
poses beyond their stds and their covariance (the benchmark is how the uncertainty's honesty is measured)."""

from __future__ import annotations

from typing import Any

from bench.accuracy import _SOURCE_TAGS, coverage_line
from pipeline.validation import STD_SOURCES


def test_every_std_source_has_a_table_tag() -> None:
    assert set(STD_SOURCES) <= set(_SOURCE_TAGS)
    assert len(set(_SOURCE_TAGS.values())) == len(_SOURCE_TAGS)


def _run(
    pos: float, rot: float, clock: float | None, pos_std: float = 0.1, clock_std: float = 5.0
) -> dict[str, float | None]:
    return {
        "position_error_m": pos,
        "rotation_error_deg": rot,
        "position_std_m": pos_std,
        "rotation_std_deg": 0.1,
        "time_offset_error_ms": clock,
        "time_offset_std_ms": None if clock is None else clock_std,
    }


def test_the_coverage_line_counts_every_pose_within_1_m_beyond_3_std() -> None:
    runs: list[dict[str, Any]] = [
        _run(0.05, 0.05, 1.0),  # within all
        _run(0.35, 0.05, -16.0),  # position and clock beyond 3 std
        _run(0.05, 0.31, None),  # rotation beyond, no clock estimate
        _run(2.0, 0.05, 0.0),  # a wrong pose: not counted
        {"position_error_m": None, "rotation_error_deg": None, "position_std_m": None},  # no pose
    ]
    assert coverage_line(runs) == (
        "uncertainty over the 3 poses within 1 m / 1 deg (accepted or refused): beyond 3 std in position 1, "
        "in rotation 1, in time offset 1 of 2; error / covariance: -"
    )


def test_the_chi2_line_counts_the_poses_beyond_their_whole_covariance() -> None:
    runs: list[dict[str, Any]] = [
        {**_run(0.05, 0.05, 1.0), "pose_chi2": chi2}
        for chi2 in (1.0, 4.0, 6.0, 25.0)  # one beyond the 6-dof 3-sigma value (20.06)
    ] + [{**_run(2.0, 0.05, 0.0), "pose_chi2": 900.0}]  # a wrong pose: not counted
    assert coverage_line(runs).endswith(
        "error / covariance (chi-square, 6 dof) median 5.00 (honest 5.35), above 20.1 1 of 4 (honest 0.27 %)"
    )


def test_routes_driven_k_times_over_keep_the_presets_name_and_its_stops() -> None:
    from bench.accuracy import repeated_routes
    from sim.presets import PRESETS

    assert repeated_routes("sil-north", 1) == "sil-north"
    base = PRESETS["sil-north"]
    tripled = repeated_routes("sil-north", 3)
    assert not isinstance(tripled, str)
    assert tripled.name == "sil-north" and tripled.drive.routes == base.drive.routes * 3
    assert tripled.cameras == base.cameras and tripled.drive.stops is None
    carla = PRESETS["carla-like"].drive  # stops given per traversal
    doubled = repeated_routes("carla-like", 2)
    assert not isinstance(doubled, str) and carla.stops is not None
    assert doubled.drive.routes == carla.routes * 2 and doubled.drive.stops == carla.stops * 2
