"""daemon.publication: the publication and change policy as a pure decision, without Zenoh or a daemon.

decide() gets a job's outcome, the camera's current result and its state, and says what to store, publish
and remember; compare_results() says whether a re-verification means the camera moved, judging the shift
against the configured minimum and k sigma of the two results' honest uncertainty. The daemon applying
these decisions over the bus is tested in test_publication.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from daemon.jobs import JobOutcome
from daemon.publication import Decision, change_limits, compare_results, decide, storing_failed
from daemon.state import CameraState
from schemas.common import CameraIntrinsics
from schemas.config import ChangeConfig
from schemas.results import CalibrationResult, CameraPosition, ReferenceFrame, Uncertainty, Verdict

CREATED_AT_NS = 1_800_000_000_000_000_000
NS_PER_S = 1_000_000_000
WINDOW_END_NS = CREATED_AT_NS - 60 * NS_PER_S
STARTED_NS = CREATED_AT_NS
NOW_NS = CREATED_AT_NS + 5 * NS_PER_S
EARLIER_NS = CREATED_AT_NS - 3600 * NS_PER_S  # the last verification
REFUSAL_REASONS = ["position std 0.82 m > 0.5 m"]
# A refusal on precision alone, as pipeline.validation words it (its std gates only).
IMPRECISE_REASONS = [
    "position std = 0.185 m (3 sigma 0.56 m > 0.5 m): mostly from the vehicle's body shape",
    "rotation std = 0.201 deg (3 sigma 0.60 deg > 0.5 deg): mostly from the vehicle's body shape",
]
WINDOW_START_NS = WINDOW_END_NS - 600 * NS_PER_S


def _outcome(
    result: CalibrationResult | None,
    error: str | None = None,
    newest_track_end_ns: int | None = WINDOW_END_NS,
) -> JobOutcome:
    result_json = None if result is None else result.model_dump_json()
    return JobOutcome(
        "cam-job", "cam", result_json, error, 1.0, 0, 0, (), newest_track_end_ns=newest_track_end_ns
    )


def _decide(
    result: CalibrationResult | None,
    current: CalibrationResult | None,
    state: CameraState,
    change: ChangeConfig | None = None,
    window_start_ns: int | None = None,
    **outcome: object,
) -> Decision:
    return decide(
        _outcome(result, **outcome),  # type: ignore[arg-type]
        current,
        state,
        change or ChangeConfig(),
        window_end_ns=WINDOW_END_NS,
        started_ns=STARTED_NS,
        now_ns=NOW_NS,
        window_start_ns=window_start_ns,
    )


def _with_std(result: CalibrationResult, position_std_m: float, rotation_std_deg: float) -> CalibrationResult:
    """`result` reporting an isotropic covariance with these stds (rotation block first, as the pipeline)."""
    rot_var = math.radians(rotation_std_deg) ** 2
    diagonal = [rot_var] * 3 + [position_std_m**2] * 3
    covariance = tuple(tuple(diagonal[i] if i == j else 0.0 for j in range(6)) for i in range(6))
    uncertainty = Uncertainty(
        covariance=covariance,  # type: ignore[arg-type]
        position_std_m=position_std_m,
        rotation_std_deg=rotation_std_deg,
    )
    return result.model_copy(update={"uncertainty": uncertainty})


def _moved(
    result: CalibrationResult, result_id: str, shift_east_m: float = 0.0, yaw_deg: float = 0.0
) -> CalibrationResult:
    """`result` with the camera moved east and turned about the vertical through its centre."""
    assert result.R is not None and result.camera_position is not None
    turn = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    R_new = np.asarray(result.R) @ turn.T
    centre = np.asarray(result.camera_position.utm) + np.array([shift_east_m, 0.0, 0.0])
    moved = _posed_result(result_id, R_new, centre, np.asarray(result.frame.origin))
    return moved.model_copy(update={"uncertainty": result.uncertainty})


def _posed_result(
    result_id: str, R_cam_from_local: np.ndarray, centre_utm: np.ndarray, origin: np.ndarray
) -> CalibrationResult:
    """An accepted result with camera centre `centre_utm` (absolute) in a local frame of `origin`."""
    t = -R_cam_from_local @ (centre_utm - origin)
    return CalibrationResult(
        rsu_id="rsu-1",
        camera_id="cam",
        result_id=result_id,
        created_at_ns=CREATED_AT_NS,
        frame=ReferenceFrame(crs="EPSG:32632", origin=tuple(float(v) for v in origin)),  # type: ignore[arg-type]
        R=tuple(tuple(float(v) for v in row) for row in R_cam_from_local),  # type: ignore[arg-type]
        t=tuple(float(v) for v in t),  # type: ignore[arg-type]
        camera_position=CameraPosition(
            utm=tuple(float(v) for v in centre_utm),  # type: ignore[arg-type]
            lat=48.4,
            lon=9.97,
            alt=float(centre_utm[2]),
        ),
        intrinsics=CameraIntrinsics(width=1920, height=1080, fx=1000.0, fy=1000.0, cx=960.0, cy=540.0),
        verdict=Verdict(status="accepted"),
    )


@pytest.fixture
def current() -> CalibrationResult:
    # A camera 9 m up looking north and 20 deg down: camera->local columns x east, y down-ish, z forward.
    look = Rotation.from_euler("x", -110.0, degrees=True).as_matrix()
    return _posed_result(
        "old", look.T, np.array([572000.0, 5361000.0, 536.0]), np.array([572000.0, 5361000.0, 527.0])
    )


def test_compare_measures_shift_and_rotation_in_absolute_terms(current: CalibrationResult) -> None:
    assert current.R is not None and current.camera_position is not None
    R_old = np.array(current.R)
    # Turned 0.8 deg about a tilted axis in the camera frame and moved 0.3 m east, 0.4 m north, 0.12 m up;
    # the new result's local origin differs, so t alone would mislead.
    turn = Rotation.from_rotvec(math.radians(0.8) * np.array([1.0, 2.0, 2.0]) / 3.0).as_matrix()
    centre = np.array(current.camera_position.utm) + np.array([0.3, 0.4, 0.12])
    new = _posed_result("new", turn @ R_old, centre, np.array([571990.0, 5361020.0, 530.0]))

    change = compare_results(new, current, ChangeConfig())
    assert change.previous_result_id == "old"
    assert change.shift_m == pytest.approx(math.sqrt(0.3**2 + 0.4**2 + 0.12**2), abs=1e-9)
    assert change.shift_deg == pytest.approx(0.8, abs=1e-9)
    assert change.moved  # 0.52 m > 0.3 m and 0.8 deg > 0.5 deg

    assert not compare_results(new, current, ChangeConfig(shift_m=0.6, shift_deg=1.0)).moved
    assert compare_results(new, current, ChangeConfig(shift_m=0.6, shift_deg=0.7)).moved  # rotation alone
    assert compare_results(new, current, ChangeConfig(shift_m=0.5, shift_deg=1.0)).moved  # shift alone


def test_compare_same_pose_and_tiny_rotations(current: CalibrationResult) -> None:
    same = compare_results(current, current, ChangeConfig())
    assert (same.shift_m, same.moved) == (0.0, False) and same.shift_deg == pytest.approx(0.0, abs=1e-6)
    assert current.R is not None and current.camera_position is not None
    tiny = Rotation.from_rotvec([0.0, 0.0, math.radians(0.001)]).as_matrix() @ np.array(current.R)
    nudged = _posed_result(
        "nudged", tiny, np.array(current.camera_position.utm), np.array(current.frame.origin)
    )
    assert compare_results(nudged, current, ChangeConfig()).shift_deg == pytest.approx(0.001, rel=1e-6)


def test_compare_needs_two_poses_in_one_zone(current: CalibrationResult) -> None:
    refused = current.model_copy(
        update={"R": None, "t": None, "camera_position": None, "verdict": Verdict(status="refused")}
    )
    with pytest.raises(ValueError, match="no pose"):
        compare_results(refused, current, ChangeConfig())
    other_zone = current.model_copy(
        update={"frame": ReferenceFrame(crs="EPSG:32633", origin=(0.0, 0.0, 0.0))}
    )
    with pytest.raises(ValueError, match="different UTM zones"):
        compare_results(other_zone, current, ChangeConfig())


# ---------------------------------------------------------------------------------------------- decide


def test_first_accepted_result_is_published_and_becomes_current(current: CalibrationResult) -> None:
    first = current.model_copy(update={"time_offset_ns": 81_000_000, "time_offset_std_ns": 2.5e6})

    decision = _decide(first, None, CameraState())

    assert decision.publish and decision.kind == "accepted" and decision.event == "published"
    assert decision.result == first and decision.result.change is None  # nothing to compare with
    state = decision.state
    assert state.current_result_id == "old" and state.verified_at_ns == NOW_NS
    assert state.used_until_ns == WINDOW_END_NS
    assert state.last_job is not None and state.last_job.job_id == "cam-job"
    assert (state.last_job.started_ns, state.last_job.finished_ns) == (STARTED_NS, NOW_NS)
    assert state.last_job.duration_s == pytest.approx(5.0)
    assert state.last_job.verdict is not None and state.last_job.verdict.is_accepted
    # The estimated time offset is remembered: the prior of the camera's next job.
    assert (state.time_offset_ns, state.time_offset_std_ns) == (81_000_000, 2.5e6)


def test_agreeing_reverification_refreshes_verification_only(current: CalibrationResult) -> None:
    state = CameraState(
        current_result_id="old", verified_at_ns=EARLIER_NS, used_until_ns=WINDOW_END_NS - NS_PER_S
    )
    agreeing = _moved(current, "agreeing", shift_east_m=0.1, yaw_deg=0.2)

    decision = _decide(agreeing, current, state)

    assert not decision.publish and decision.kind == "accepted" and decision.event == "verified"
    assert decision.state.verified_at_ns == NOW_NS and decision.state.current_result_id == "old"
    assert decision.result is not None and decision.result.change is not None
    change = decision.result.change
    assert not change.moved and change.previous_result_id == "old"
    assert change.shift_m == pytest.approx(0.1, abs=1e-9) and change.shift_deg == pytest.approx(0.2, abs=1e-9)
    assert decision.text.startswith("re-verified: agrees with old")


def test_a_fit_on_old_drive_pasts_only_neither_verifies_nor_moves(current: CalibrationResult) -> None:
    state = CameraState(current_result_id="old", verified_at_ns=EARLIER_NS, used_until_ns=WINDOW_END_NS)
    for shift_m in (0.1, 1.0):
        stale = _moved(current, "stale", shift_east_m=shift_m)

        decision = _decide(stale, current, state, newest_track_end_ns=WINDOW_END_NS - NS_PER_S)

        assert not decision.publish and decision.event == "verified"
        assert decision.state.verified_at_ns == EARLIER_NS and decision.state.current_result_id == "old"
        assert decision.text.startswith("not a re-verification")
    # No box at all (nothing chosen) is no re-verification either.
    decision = _decide(_moved(current, "none", 1.0), current, state, newest_track_end_ns=None)
    assert not decision.publish and decision.state.verified_at_ns == EARLIER_NS


def test_a_move_beyond_tolerance_is_published_as_a_change(current: CalibrationResult) -> None:
    state = CameraState(
        current_result_id="old", verified_at_ns=EARLIER_NS, used_until_ns=WINDOW_END_NS - NS_PER_S
    )
    shifted = _moved(current, "shifted", shift_east_m=1.0)

    decision = _decide(shifted, current, state)

    assert decision.publish and decision.event == "published"
    assert decision.result is not None and decision.result.change is not None
    assert decision.result.change.moved and decision.result.change.shift_m == pytest.approx(1.0, abs=1e-9)
    assert decision.state.current_result_id == "shifted" and decision.state.verified_at_ns == NOW_NS
    assert decision.text.startswith("camera moved 1.00 m / 0.00 deg")


def test_a_shift_within_the_uncertainty_of_both_results_is_no_move(current: CalibrationResult) -> None:
    """0.5 m and 0.8 deg exceed the configured minimum (0.3 m, 0.5 deg); whether that is a move depends on
    how well both results know the pose: the difference's std is sqrt(2) x each result's std."""
    state = CameraState(current_result_id="old", used_until_ns=WINDOW_END_NS - NS_PER_S)
    for std_m, std_deg, moved in ((0.2, 0.3, False), (0.05, 0.05, True)):
        old = _with_std(current, std_m, std_deg)
        new = _with_std(_moved(current, "new", shift_east_m=0.5, yaw_deg=0.8), std_m, std_deg)

        change = compare_results(new, old, ChangeConfig())

        assert change.moved is moved, (std_m, std_deg)
        assert change.shift_std_m == pytest.approx(math.sqrt(2) * std_m, rel=1e-9)
        assert change.shift_std_deg == pytest.approx(math.sqrt(2) * std_deg, rel=1e-9)
        assert (change.sigmas, change.min_shift_m, change.min_shift_deg) == (3.0, 0.3, 0.5)
        limit_m, limit_deg = change_limits(change)
        assert limit_m == pytest.approx(max(0.3, 3 * math.sqrt(2) * std_m))
        assert limit_deg == pytest.approx(max(0.5, 3 * math.sqrt(2) * std_deg))
        assert _decide(new, old, state).publish is moved
    # k is configurable: at k = 1 the 0.2 m / 0.3 deg results' difference is beyond 1 sigma.
    old, new = _with_std(current, 0.2, 0.3), _with_std(_moved(current, "new", 0.5, 0.8), 0.2, 0.3)
    assert compare_results(new, old, ChangeConfig(sigmas=1.0)).moved


def test_the_uncertainty_counts_along_the_shift_only(current: CalibrationResult) -> None:
    """A result unsure of its depth (north, the view direction) but sure across it: a shift east is judged
    on the east std alone."""
    cov = np.zeros((6, 6))
    cov[3, 3], cov[4, 4], cov[5, 5] = 0.02**2, 1.0**2, 0.02**2
    uncertainty = Uncertainty(
        covariance=tuple(tuple(float(v) for v in row) for row in cov),  # type: ignore[arg-type]
        position_std_m=1.0,
        rotation_std_deg=0.0,
    )
    old = current.model_copy(update={"uncertainty": uncertainty})
    new = _moved(old, "east", shift_east_m=0.4)
    change = compare_results(new, old, ChangeConfig())
    assert change.moved and change.shift_std_m == pytest.approx(math.sqrt(2) * 0.02, rel=1e-6)


def test_refused_and_failed_jobs_publish_nothing(current: CalibrationResult) -> None:
    state = CameraState(current_result_id="old", verified_at_ns=EARLIER_NS, time_offset_ns=50_000_000)
    refused = current.model_copy(
        update={
            "result_id": "refused",
            "verdict": Verdict(status="refused", reasons=REFUSAL_REASONS),
            "time_offset_ns": 200_000_000,  # a refused fit's estimate is not trusted
        }
    )

    decision = _decide(refused, current, state)

    assert not decision.publish and decision.kind == "refused" and decision.event == "refused"
    assert decision.result == refused and decision.verdict.reasons == REFUSAL_REASONS
    assert decision.state.current_result_id == "old" and decision.state.verified_at_ns == EARLIER_NS
    assert decision.state.last_reasons == REFUSAL_REASONS and decision.state.time_offset_ns == 50_000_000
    assert decision.text == "refused: " + REFUSAL_REASONS[0]

    failed = _decide(None, current, state, error="timed out after 900 s")

    assert not failed.publish and failed.kind == "failed" and failed.result is None
    assert (
        failed.verdict.reasons == ["timed out after 900 s"] and failed.text == "failed: timed out after 900 s"
    )
    assert failed.state.used_until_ns == WINDOW_END_NS  # its window is used all the same
    assert _decide(None, None, CameraState()).verdict.reasons == ["the job produced no result"]


def test_an_accepted_result_without_a_time_offset_keeps_the_last_estimate(current: CalibrationResult) -> None:
    state = CameraState(current_result_id="old", time_offset_ns=50_000_000, time_offset_std_ns=1e6)
    decision = _decide(_moved(current, "agreeing", 0.05), current, state)
    assert (decision.state.time_offset_ns, decision.state.time_offset_std_ns) == (50_000_000, 1e6)
    estimated = _moved(current, "estimated", 0.05).model_copy(
        update={"time_offset_ns": -120_000_000, "time_offset_std_ns": 3e6}
    )
    decision = _decide(estimated, current, state)
    assert (decision.state.time_offset_ns, decision.state.time_offset_std_ns) == (-120_000_000, 3e6)


def test_a_result_that_cannot_be_stored_fails_the_job(current: CalibrationResult) -> None:
    previous = CameraState(verified_at_ns=EARLIER_NS, time_offset_ns=7)
    first = current.model_copy(update={"time_offset_ns": 81_000_000})
    decision = _decide(first, None, previous)
    assert decision.publish

    failed = storing_failed(decision, previous, "result old could not be stored: disk full")

    assert not failed.publish and failed.kind == "failed" and failed.event == "failed"
    assert failed.text == "failed: result old could not be stored: disk full"
    assert failed.state.current_result_id is None and failed.state.verified_at_ns == EARLIER_NS
    assert failed.state.time_offset_ns == 7
    assert failed.state.last_job is not None and failed.state.last_job.verdict == failed.verdict
    assert not failed.verdict.is_accepted and failed.verdict.reasons[-1].endswith("disk full")


def test_results_in_different_zones_replace_the_current_one(current: CalibrationResult) -> None:
    other_zone = current.model_copy(
        update={"result_id": "new", "frame": ReferenceFrame(crs="EPSG:32633", origin=(0.0, 0.0, 0.0))}
    )
    decision = _decide(other_zone, current, CameraState(current_result_id="old"))
    assert decision.publish and decision.warnings and "different UTM zones" in decision.warnings[0]


def _refused(result: CalibrationResult, reasons: list[str]) -> CalibrationResult:
    return result.model_copy(update={"verdict": Verdict(status="refused", reasons=reasons)})


def test_a_move_shown_by_a_fit_refused_on_its_precision_withdraws_the_current_result(
    current: CalibrationResult,
) -> None:
    """The new drive-pasts agree with each other but fix the pose too loosely to publish it; still, 1 m and
    1 deg from the current result is far beyond both results' uncertainty: the current result no longer
    describes the camera, so it is withdrawn and nothing replaces it."""
    state = CameraState(
        current_result_id="old",
        verified_at_ns=EARLIER_NS,
        used_until_ns=WINDOW_START_NS - NS_PER_S,
        time_offset_ns=50_000_000,
    )
    old = _with_std(current, 0.05, 0.05)
    new = _refused(_with_std(_moved(current, "new", 1.0, 1.0), 0.185, 0.201), IMPRECISE_REASONS)

    decision = _decide(new, old, state, window_start_ns=WINDOW_START_NS)

    assert decision.withdraw and not decision.publish
    assert decision.kind == "refused" and decision.event == "withdrawn"
    assert decision.result is not None and decision.result.change is not None
    change = decision.result.change
    assert change.moved and change.previous_result_id == "old"
    assert change.shift_m == pytest.approx(1.0, abs=1e-9) and change.shift_deg == pytest.approx(1.0, abs=1e-6)
    assert decision.state.current_result_id is None and decision.state.verified_at_ns is None
    assert decision.state.withdrawn_result_id == "old"  # a restart never takes its current.json again
    # The next jobs use none of the drive-pasts before the move: not before this job's window.
    assert decision.state.not_before_ns == WINDOW_START_NS
    assert decision.state.time_offset_ns == 50_000_000  # a refused fit's clock is not trusted
    assert decision.text.startswith("camera moved 1.00 m / 1.00 deg")
    assert "old withdrawn" in decision.text
    assert decision.text.endswith("refused: " + "; ".join(IMPRECISE_REASONS))

    # Storing the refused result failed: nothing is withdrawn, the camera keeps its current result.
    failed = storing_failed(decision, state, "disk full")
    assert not failed.withdraw and failed.state.current_result_id == "old"
    assert failed.state.not_before_ns is None and failed.state.verified_at_ns == EARLIER_NS
    assert failed.state.withdrawn_result_id is None


def test_a_refused_fit_moves_nothing_unless_only_its_precision_failed_on_new_drive_pasts(
    current: CalibrationResult,
) -> None:
    state = CameraState(current_result_id="old", verified_at_ns=EARLIER_NS, used_until_ns=WINDOW_START_NS)
    old = _with_std(current, 0.05, 0.05)
    far = _with_std(_moved(current, "new", 1.0, 1.0), 0.185, 0.201)
    cases = {
        # Another reason says its tracks may not be the vehicle's: its pose is no evidence of a move.
        "other reason": (_refused(far, [*IMPRECISE_REASONS, "delta_p mean = 0.912 m > 0.5 m"]), {}),
        "no precision reason": (_refused(far, REFUSAL_REASONS), {}),
        # Only drive-pasts the current result already judged: nothing new to judge.
        "old drive-pasts": (_refused(far, IMPRECISE_REASONS), {"newest_track_end_ns": WINDOW_START_NS}),
        "no pose": (_refused(far, IMPRECISE_REASONS).model_copy(update={"R": None, "t": None}), {}),
    }
    for name, (new, outcome) in cases.items():
        decision = _decide(new, old, state, window_start_ns=WINDOW_START_NS, **outcome)
        assert not decision.withdraw and decision.event == "refused", name
        assert decision.state.current_result_id == "old" and decision.state.not_before_ns is None, name
        assert decision.state.withdrawn_result_id is None, name
        assert decision.result is not None and decision.result.change is None, name
    assert _decide(_refused(far, IMPRECISE_REASONS), None, CameraState()).event == "refused"


def test_a_fit_refused_on_its_precision_within_the_limits_keeps_the_current_result(
    current: CalibrationResult,
) -> None:
    """0.5 m from the current result, but the refused fit's own std (0.3 m) widens the limit to 3 sigma of
    both: no provable move. The comparison is kept with the refused result."""
    state = CameraState(current_result_id="old", verified_at_ns=EARLIER_NS, used_until_ns=WINDOW_START_NS)
    old = _with_std(current, 0.05, 0.05)
    near = _refused(_with_std(_moved(current, "new", 0.5, 0.2), 0.3, 0.3), IMPRECISE_REASONS)

    decision = _decide(near, old, state, window_start_ns=WINDOW_START_NS)

    assert not decision.withdraw and decision.event == "refused"
    assert decision.state.current_result_id == "old" and decision.state.verified_at_ns == EARLIER_NS
    assert decision.result is not None and decision.result.change is not None
    assert not decision.result.change.moved and decision.result.change.shift_m == pytest.approx(0.5, abs=1e-9)
    assert decision.text == "refused: " + "; ".join(IMPRECISE_REASONS)
