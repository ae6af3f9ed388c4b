"""What the daemon does with a finished job: the publication and change policy, as a pure decision.

decide() takes the job's outcome, the camera's current (published) result and its persisted state, and
returns a Decision: what to store, whether to publish it, the status text, the verdict and the camera's
new state. It reads no clock, file or bus; the supervisor (daemon.main) applies the Decision: stores the
result, publishes it, saves the state. When storing fails, storing_failed() turns the Decision into the
failure the supervisor then applies.

The rules (docs/design.md, "Publication" and "Re-verification"):
  - a failed job (no result) publishes nothing; its error is the status;
  - a refused result is stored and publishes nothing; the current result stays;
  - an accepted result with no current one is published and becomes current;
  - an accepted result with a current one is a re-verification: compare_results() measures the shift and
    says whether the camera moved. Moved: the new result is published and replaces the current one.
    Agrees: only verified_at is refreshed. A fit that used no box newer than the last job's window
    (outcome.newest_track_end_ns) re-verifies nothing and can move nothing.
  - a refused result refused on its precision alone (pipeline.validation.imprecise_only: std gates only)
    on new drive-pasts is compared too. Its drive-pasts agree with each other and with the boxes, so a
    shift beyond the limits (its own larger covariance included) shows the camera moved: the current
    result is withdrawn, nothing replaces it, and the camera's next jobs use no drive-past that began
    before the refused job's window (state.not_before_ns). A refusal for any other reason (the tracks may
    not be the vehicle's) moves nothing.
  - the camera's time offset (state.time_offset_ns) follows every accepted result that estimated one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from daemon.jobs import JobOutcome
from daemon.state import CameraState
from pipeline.camera import rvec_from_rotation
from pipeline.validation import imprecise_only
from schemas.config import ChangeConfig
from schemas.results import CalibrationResult, ChangeInfo, JobSummary, Verdict

JobKind = Literal["accepted", "refused", "failed"]
EventKind = Literal["published", "verified", "refused", "failed", "withdrawn"]


@dataclass(frozen=True, slots=True)
class Decision:
    """What the supervisor applies for one finished job."""

    kind: JobKind  # counted in the camera's job counters (jobs.accepted, ...)
    event: EventKind  # the DaemonEvent's kind
    text: str  # the log line and the event's text: what happened and why
    verdict: Verdict  # the job's verdict as the status shows it
    result: CalibrationResult | None  # to store in the history (change filled in); None for a failed job
    publish: bool  # the result becomes current.json and goes on the bus
    state: CameraState  # the camera's state after the job
    withdraw: bool = False  # the current result is withdrawn (current.json removed, deleted on the bus)
    warnings: tuple[str, ...] = ()  # for the log: e.g. results that could not be compared


def decide(
    outcome: JobOutcome,
    current: CalibrationResult | None,
    state: CameraState,
    change: ChangeConfig,
    *,
    window_end_ns: int,
    started_ns: int,
    now_ns: int,
    window_start_ns: int | None = None,
) -> Decision:
    """The Decision for a job that read data up to `window_end_ns`, started at `started_ns` and is handled at
    `now_ns` (the daemon's clock), on a camera whose current result is `current` (None: not calibrated).
    `window_start_ns`: where the job's window began (the camera's next jobs start there if it moved)."""
    result_json = outcome.result_json
    result = None if result_json is None else CalibrationResult.model_validate_json(result_json)
    warnings: list[str] = []
    verified_at_ns = state.verified_at_ns
    publish = withdraw = False
    # Only a fit that used boxes of a drive-past newer than the last job's window can confirm or overturn
    # the current result; older drive-pasts alone would just repeat it.
    is_fresh = outcome.newest_track_end_ns is not None and (
        state.used_until_ns is None or outcome.newest_track_end_ns > state.used_until_ns
    )
    if result is None:
        verdict = Verdict(status="refused", reasons=[outcome.error or "the job produced no result"])
        kind: JobKind = "failed"
        text = "failed: " + "; ".join(verdict.reasons)
    elif not result.verdict.is_accepted:
        verdict, kind = result.verdict, "refused"
        text = "refused: " + "; ".join(verdict.reasons)
        info = _imprecise_change(result, current, change) if is_fresh else None
        if info is not None:
            result = result.model_copy(update={"change": info})
            if info.moved:
                withdraw = True
                text = (
                    f"camera moved {describe_change(info)} by a fit refused only on its precision: "
                    f"{info.previous_result_id} withdrawn, no calibration until one from the new drive-pasts "
                    f"is accepted; {text}"
                )
    elif current is None:
        verdict, kind = result.verdict, "accepted"
        text = "calibrated: result published"
        publish = True
    else:
        verdict, kind = result.verdict, "accepted"
        try:
            info = compare_results(result, current, change)
        except ValueError as err:  # e.g. the UTM zone changed since current.json was written
            warnings.append(f"{err}; the new result replaces the current one")
            info = ChangeInfo(previous_result_id=current.result_id, shift_m=0.0, shift_deg=0.0, moved=True)
        result = result.model_copy(update={"change": info})
        if not is_fresh:
            text = (
                f"not a re-verification: the fit used no box of a new drive-past "
                f"({info.shift_m:.2f} m, {info.shift_deg:.2f} deg from {current.result_id})"
            )
        elif info.moved:
            text = f"camera moved {describe_change(info)}: new result published"
            publish = True
        else:
            text = f"re-verified: agrees with {current.result_id} ({describe_change(info)})"
            verified_at_ns = now_ns
    current_id, not_before_ns = state.current_result_id, state.not_before_ns
    withdrawn_id = state.withdrawn_result_id
    if publish:
        assert result is not None
        verified_at_ns, current_id = now_ns, result.result_id
    if withdraw:
        assert current is not None
        verified_at_ns, current_id, withdrawn_id = None, None, current.result_id
        if window_start_ns is not None:
            not_before_ns = max(window_start_ns, not_before_ns or 0)
    time_offset_ns, time_offset_std_ns = state.time_offset_ns, state.time_offset_std_ns
    if result is not None and result.verdict.is_accepted and result.time_offset_ns is not None:
        time_offset_ns, time_offset_std_ns = result.time_offset_ns, result.time_offset_std_ns
    summary = JobSummary(
        job_id=outcome.job_id,
        started_ns=started_ns,
        finished_ns=now_ns,
        duration_s=max(0.0, (now_ns - started_ns) / 1e9),
        verdict=verdict,
        report=outcome.report_path,
    )
    new_state = state.model_copy(
        update={
            "last_job": summary,
            "verified_at_ns": verified_at_ns,
            "used_until_ns": max(window_end_ns, state.used_until_ns or 0),
            "current_result_id": current_id,
            "last_reasons": list(verdict.reasons),
            "time_offset_ns": time_offset_ns,
            "time_offset_std_ns": time_offset_std_ns,
            "not_before_ns": not_before_ns,
            "withdrawn_result_id": withdrawn_id,
        }
    )
    event: EventKind = "published" if publish else ("verified" if kind == "accepted" else kind)
    if withdraw:
        event = "withdrawn"
    return Decision(kind, event, text, verdict, result, publish, new_state, withdraw, tuple(warnings))


def _imprecise_change(
    result: CalibrationResult, current: CalibrationResult | None, change: ChangeConfig
) -> ChangeInfo | None:
    """compare_results of a refused `result` with the current one when the refusal is on precision alone
    (its drive-pasts agree, its pose is known loosely: its covariance widens the limits), else None."""
    if current is None or not imprecise_only(result.verdict.reasons):
        return None
    try:
        return compare_results(result, current, change)
    except ValueError:  # no pose, or another frame: nothing to compare
        return None


def storing_failed(decision: Decision, previous: CameraState, reason: str) -> Decision:
    """`decision` after its result could not be stored: nothing published, the job failed with `reason`.

    Not stored, not published, nothing withdrawn: after a restart the queryable must answer what was
    published. The camera keeps its previous verification and time offset; the job's window still counts
    as used.
    """
    verdict = Verdict(status="refused", reasons=[*decision.verdict.reasons, reason])
    last_job = decision.state.last_job
    assert last_job is not None
    state = decision.state.model_copy(
        update={
            "last_job": last_job.model_copy(update={"verdict": verdict}),
            "verified_at_ns": previous.verified_at_ns,
            "current_result_id": previous.current_result_id,
            "last_reasons": list(verdict.reasons),
            "time_offset_ns": previous.time_offset_ns,
            "time_offset_std_ns": previous.time_offset_std_ns,
            "not_before_ns": previous.not_before_ns,
            "withdrawn_result_id": previous.withdrawn_result_id,
        }
    )
    return replace(
        decision,
        kind="failed",
        event="failed",
        text="failed: " + reason,
        verdict=verdict,
        publish=False,
        state=state,
        withdraw=False,
    )


def describe_change(info: ChangeInfo) -> str:
    """'0.41 m / 0.62 deg' plus the limits the decision used when known: '(limit 0.30 m / 0.50 deg)'."""
    text = f"{info.shift_m:.2f} m / {info.shift_deg:.2f} deg"
    if info.min_shift_m is None or info.min_shift_deg is None:
        return text
    limit_m, limit_deg = change_limits(info)
    return f"{text}, limit {limit_m:.2f} m / {limit_deg:.2f} deg"


def change_limits(info: ChangeInfo) -> tuple[float, float]:
    """The shifts (m, deg) beyond which `info` counts as a move: max(minimum, sigmas x std), each."""
    sigmas = info.sigmas or 0.0
    limit_m = max(info.min_shift_m or 0.0, sigmas * (info.shift_std_m or 0.0))
    limit_deg = max(info.min_shift_deg or 0.0, sigmas * (info.shift_std_deg or 0.0))
    return limit_m, limit_deg


# ---------------------------------------------------------------------------------------------- comparison


def compare_results(new: CalibrationResult, current: CalibrationResult, change: ChangeConfig) -> ChangeInfo:
    """How far `new` is from `current` and whether that means the camera moved.

    shift_m: distance of the camera centres (absolute UTM); shift_deg: angle of the relative rotation. Each
    is judged against its own limit, the larger of the configured minimum (change.shift_m / shift_deg) and
    change.sigmas standard deviations of the difference: the two results are fitted on separate drive-pasts
    (re-verification never pools them), so the difference's covariance is the sum of theirs, taken along
    the shift (position) and about the relative rotation's axis (rotation). A result without uncertainty
    contributes none. Moved when either shift exceeds its limit.

    Both results need a pose and the same crs (ValueError otherwise: their frames are not comparable).
    """
    for name, result in (("new", new), ("current", current)):
        if result.R is None or result.camera_position is None:
            raise ValueError(f"{name} result {result.result_id} has no pose ({result.verdict.status})")
    assert new.R is not None and new.camera_position is not None
    assert current.R is not None and current.camera_position is not None
    if new.frame.crs != current.frame.crs:
        raise ValueError(
            f"results {new.result_id} ({new.frame.crs}) and {current.result_id} ({current.frame.crs}) are in "
            "different UTM zones"
        )
    delta = np.asarray(new.camera_position.utm) - np.asarray(current.camera_position.utm)
    shift_m = float(np.linalg.norm(delta))
    # R maps the local frame (UTM minus origin, a pure translation) to the camera, so rotations of results
    # with different origins compare directly. The covariance's rotation w is in the local frame:
    # R_local_from_cam = expm([w]x) R^T (pipeline.refinement.Refinement), so the small rotation taking the
    # current camera to the new one is w = rotvec(R_new^T R_current).
    relative = np.asarray(new.R, dtype=np.float64).T @ np.asarray(current.R, dtype=np.float64)
    w = rvec_from_rotation(relative)  # its norm is pipeline.camera.rotation_angle_rad
    shift_deg = math.degrees(float(np.linalg.norm(w)))
    cov_rot = _block(new, 0) + _block(current, 0)
    cov_pos = _block(new, 3) + _block(current, 3)
    std_m = _std_along(cov_pos, delta)
    std_deg = math.degrees(_std_along(cov_rot, w))
    limit_m = max(change.shift_m, change.sigmas * std_m)
    limit_deg = max(change.shift_deg, change.sigmas * std_deg)
    return ChangeInfo(
        previous_result_id=current.result_id,
        shift_m=shift_m,
        shift_deg=shift_deg,
        moved=shift_m > limit_m or shift_deg > limit_deg,
        shift_std_m=std_m,
        shift_std_deg=std_deg,
        sigmas=change.sigmas,
        min_shift_m=change.shift_m,
        min_shift_deg=change.shift_deg,
    )


def _block(result: CalibrationResult, start: int) -> np.ndarray:
    """The 3x3 block of the result's covariance at [start:start+3] (0: rotation rad^2, 3: centre m^2); zeros
    without one."""
    if result.uncertainty is None:
        return np.zeros((3, 3))
    cov = np.asarray(result.uncertainty.covariance, dtype=np.float64)
    return cov[start : start + 3, start : start + 3]


def _std_along(cov: np.ndarray, direction: np.ndarray) -> float:
    """Std of a 3-vector with covariance `cov` along `direction`; along the worst axis when the direction is
    zero (the two results coincide: any direction could be the one)."""
    norm = float(np.linalg.norm(direction))
    if norm == 0.0:
        return math.sqrt(max(0.0, float(np.max(np.linalg.eigvalsh(cov)))))
    unit = direction / norm
    return math.sqrt(max(0.0, float(unit @ cov @ unit)))
