"""The whole pipeline on scenes of the simulator's real world: right or refused.

Shaped bodies the method never saw, a biased detector, 40-200 ms of latency the method is not told, CAM V2X
without pitch, real roads. The promise checked here is the product's: a result is either within its reported
uncertainty of the truth (and, when accepted, within the false-accept limits of 0.5 m / 0.5 deg), or refused
with a reason; and the camera's time offset is estimated rather than assumed. Each scene is simulated once
with a fixed seed and calibrated once with a fixed RANSAC seed; the measured values at the time of writing
are in the comments.
"""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from daemon.offline import inputs_from_simulation as calibration_inputs
from pipeline.calibrate import CalibrationOutcome, PipelineParams, calibrate
from pipeline.metrics import Evaluation, evaluate_against_ground_truth, true_time_offset_ns
from sim.presets import look_at
from sim.simulate import resolve_config, simulate

CREATED_AT_NS = 1_700_000_000_000_000_000  # the result's creation time: the caller's clock

pytestmark = pytest.mark.slow

CALIBRATION_SEED = 0


@cache
def _run(
    preset: str, seed: int, camera_index: int = 0, latency_s: float | None = None
) -> tuple[CalibrationOutcome, Evaluation, float]:
    """Calibrate one camera of the scene (default its first) on the assumed clock 0; the true offset (ms, of
    the image's middle row) comes back too. `latency_s`: the camera's instead of the drawn one."""
    sim = simulate(preset, seed=seed, latency_s=latency_s)
    camera = sim.cameras[camera_index]
    truth = sim.ground_truth[camera.camera_id]
    inputs = calibration_inputs(sim, camera.camera_id)
    assert inputs.time_offset_ns == 0  # the latency is not told to the method
    outcome = calibrate(
        inputs, PipelineParams(), np.random.default_rng(CALIBRATION_SEED), created_at_ns=CREATED_AT_NS
    )
    evaluation = evaluate_against_ground_truth(outcome.result, truth)
    return outcome, evaluation, true_time_offset_ns(truth) / 1e6


def _stage_notes(outcome: CalibrationOutcome, stage: str) -> str:
    return " ".join(note for s in outcome.stages if s.stage == stage for note in s.notes)


def _assert_right_or_refused(outcome: CalibrationOutcome, evaluation: Evaluation) -> None:
    """Accepted only within the false-accept limits; any pose given lies within 3 of its reported stds,
    unless it is refused because the vehicle was seen on fewer than two drive-pasts: then nothing confirms
    that the track was the calibration vehicle's, and a std (noise and model, given that track) says nothing
    about a pose fitted to another vehicle (truck seed 0 with a rolling shutter: 18 m off, std 1.9 m,
    refused so)."""
    result = outcome.result
    if result.verdict.status == "accepted":
        assert evaluation.position_error_m is not None and evaluation.position_error_m <= 0.5
        assert evaluation.rotation_error_deg is not None and evaluation.rotation_error_deg <= 0.5
    else:
        assert result.verdict.reasons
    unconfirmed = any(
        reason.startswith(("traversals = 0 <", "traversals = 1 <")) for reason in result.verdict.reasons
    )
    if result.uncertainty is not None and evaluation.position_error_m is not None and not unconfirmed:
        assert evaluation.position_error_m <= 3.0 * result.uncertainty.position_std_m
        assert evaluation.rotation_error_deg is not None
        assert evaluation.rotation_error_deg <= 3.0 * result.uncertainty.rotation_std_deg


@pytest.mark.parametrize(("preset", "seed"), [("occluded", 2), ("slope", 3)])
def test_an_unknown_latency_is_found_through_the_grouping_and_estimated(preset: str, seed: int) -> None:
    # On the assumed clock (0 ms; the camera's latency, drawn by the simulator, is not told) opposite
    # drive-pasts' hypotheses lie metres apart and no group forms (session 4: "no two hypotheses
    # agree"). The clock scan finds a clock where they agree, the final fit estimates the offset from
    # there (at the time of writing: 4.8 and 5.5 ms off). Slope seed 4, the case before session 27,
    # now groups on the assumed clock: its vehicle's course is no longer its yaw in the simulator.
    outcome, evaluation, true_offset_ms = _run(preset, seed)
    assert "the assumed clock grouped no two drive-pasts" in _stage_notes(outcome, "clock scan")
    offset_ns = outcome.result.time_offset_ns
    assert offset_ns is not None
    # The target: within 10 ms of the truth.
    assert abs(offset_ns / 1e6 - true_offset_ms) <= 10.0
    assert outcome.result.time_offset_std_ns is not None
    _assert_right_or_refused(outcome, evaluation)


def test_a_latency_of_400_ms_is_found_from_anchor_clocks_fitted_afresh() -> None:
    # sil-west seed 1's junction camera stamping its frames 400 ms after exposure (386 ms for the middle
    # row, with its rolling shutter): no two drive-pasts group on the assumed clock, and the hypotheses of
    # that clock, moved 0.3-0.4 s, no longer agree either (before the anchors: no pose at all). From the
    # +0.25 s anchor's own hypotheses the scan finds +294 ms, the final fit -384 ms and the rerun there
    # -385.2 ms (measured at the time of writing: 0.6 ms off; the pose 0.58 m off, refused with its
    # drive-pasts disagreeing).
    outcome, evaluation, true_offset_ms = _run("sil-west", 1, 0, 0.4)
    assert "the assumed clock grouped no two drive-pasts" in _stage_notes(outcome, "clock scan")
    offset_ns = outcome.result.time_offset_ns
    assert offset_ns is not None and abs(offset_ns / 1e6 - true_offset_ms) <= 10.0
    _assert_right_or_refused(outcome, evaluation)


def test_no_calibration_vehicle_is_refused_on_every_clock() -> None:
    outcome, _, _ = _run("no-target", 0)
    assert outcome.result.verdict.status == "refused"
    assert outcome.result.uncertainty is None
    reasons = " ".join(outcome.result.verdict.reasons)
    assert "no two hypotheses agree" in reasons or "no image track" in reasons


def test_a_refusal_on_precision_alone_does_not_search_the_clock_again() -> None:
    # sil-north seed 1: the pose is refused on its stds alone: the vehicle's own tracks, on the right clock
    # (0.10 m off, measured; its roof fitted 0.26 m below the data sheet's height, a rounded roof seen from
    # above; with the roof held there its drive-pasts disagreed by 0.28 m / 0.28 deg, within the gates, and
    # it was 0.18 m off). A search of every clock after that refusal took 6.7 of its 12.3 s and could only
    # repeat it; the passes are the first and the one on the clock its fit estimated.
    sim = simulate("sil-north", seed=1)
    camera = sim.cameras[0]
    passes: list[str] = []
    outcome = calibrate(
        calibration_inputs(sim, camera.camera_id),
        PipelineParams(),
        np.random.default_rng(CALIBRATION_SEED),
        created_at_ns=CREATED_AT_NS,
        progress=lambda stage, _fraction: passes.append(stage) if stage == "association" else None,
    )
    reasons = outcome.result.verdict.reasons
    precision = ("position std", "rotation std", "traversals disagree by")
    assert reasons and all(reason.startswith(precision) for reason in reasons), reasons
    assert outcome.imprecise
    assert len(passes) <= 2
    assert "after the refusal" not in _stage_notes(outcome, "clock scan")


def test_after_a_refusal_the_scanned_clocks_refusal_on_precision_alone_is_the_result() -> None:
    # latency seed 5 (since session 27; slope seed 0 before the simulator's courses): on the assumed clock
    # (0; the camera's latency is 250 ms) a pose is found and refused. The clock scan after that refusal
    # finds the drive-pasts agreeing about 250 ms away, where the pose is refused on its stds alone (at the
    # time of writing 0.16 m off, the clock within 4 ms). That is the refusal the result gives: its
    # drive-pasts agree, which the assumed clock's refusal could not say.
    outcome, evaluation, true_ms = _run("latency", 5)
    assert "the assumed clock's pose was refused" in _stage_notes(outcome, "clock scan")
    assert outcome.result.verdict.status == "refused" and outcome.imprecise
    assert evaluation.position_error_m is not None and evaluation.position_error_m < 0.5
    assert outcome.result.time_offset_ns is not None
    assert abs(outcome.result.time_offset_ns / 1e6 - true_ms) < 10.0


@pytest.mark.parametrize(
    ("preset", "seed", "camera_index"), [("slope", 4, 0), ("sil-west", 0, 1), ("van", 3, 0)]
)
def test_the_reported_uncertainty_covers_a_body_the_template_cannot_describe(
    preset: str, seed: int, camera_index: int
) -> None:
    # Scenes whose pose the body template's misfit moved beyond 3 of the reported stds before the body's
    # consider covariance (session 5, measured: slope seed 4 accepted 0.144 m / 0.320 deg off with a
    # rotation std of 0.051 deg; sil-west seed 0's west-arm 0.252 m / 0.553 deg against 0.155 deg; van seed
    # 0, where cross-validation kept the cuboid, 0.514 m against 0.136 m). Each must now be within 3 of its
    # stds, or refused with a reason and no pose. Van seed 0 reaches no pose since cameras have a rolling
    # shutter; van seed 3, whose boxes reject the cuboid body, stands in (0.13 m / 0.09 deg off, stds 0.24 m
    # / 0.33 deg).
    outcome, evaluation, _ = _run(preset, seed, camera_index)
    _assert_right_or_refused(outcome, evaluation)
    assert outcome.result.uncertainty is not None  # a pose was reached: the covering is what is tested


def test_a_roof_raise_that_predicts_the_left_out_drive_pasts_no_better_stays_held() -> None:
    # latency seed 9, a sedan that carries a roof box: the final fit's trial fits the roof +0.34 m above
    # its data sheet's height, beyond 3 of its std; fitted without each drive-past in turn, the raised roof
    # predicts the left-out boxes no better than the held one, so it stays held (a raise is kept only where
    # the drive-pasts confirm it: on its std alone a raise that took up another of the template's errors
    # landed the camera 0.83 m off, sil-south seed 4 in session 23). Here the raise was real and holding it
    # costs precision, not correctness: the pose is 0.16 m off and refused on its stds (at the time of
    # writing). Before the simulator's courses (session 27) this was dense-traffic seed 1, a sedan without
    # a roof box fitted -0.40 m.
    outcome, evaluation, _ = _run("latency", 9)
    notes = _stage_notes(outcome, "final fit")
    assert "with the roof held at the data sheet's height" in notes, notes
    raise_m = float(notes.split("a raise of ")[1].split(" m predicted the left-out drive-pasts no better")[0])
    assert abs(raise_m) > 0.3
    assert evaluation.position_error_m is not None and evaluation.position_error_m < 0.5
    _assert_right_or_refused(outcome, evaluation)


def test_a_roof_box_the_drive_pasts_heights_took_up_is_fitted_in_their_place() -> None:
    # bench.unseen's scene 15: a hatchback with a roof box 0.45 m above its data sheet's height, four
    # drive-pasts, its second camera 6.4 m up. Under the roof held at the data sheet's height the boxes ask
    # for a height per drive-past (chi-square 15, 4 dof), and with those heights the roof's raise predicts
    # the left-out drive-pasts no better (7.0 px against 6.5 px): the camera ended 0.43 m off, 0.42 m low.
    # Tried in their place the raise predicts them better (5.5 px) and is kept (measured: +0.56 +- 0.04 m,
    # the camera 0.09 m off, accepted).
    from bench.unseen import draw_scene

    sim = simulate(draw_scene(15), seed=15)
    camera_id = sim.cameras[1].camera_id
    outcome = calibrate(
        calibration_inputs(sim, camera_id),
        PipelineParams(),
        np.random.default_rng([15, 1]),  # bench.unseen's
        created_at_ns=CREATED_AT_NS,
    )
    evaluation = evaluate_against_ground_truth(outcome.result, sim.ground_truth[camera_id])
    notes = _stage_notes(outcome, "final fit")
    assert "m off the data sheet's height (in place of a height per drive-past" in notes, notes
    raise_m = float(notes.split("the roof ")[1].split(" m +- ")[0])
    assert 0.3 < raise_m < 0.8
    assert "above its GNSS heights" not in notes  # the heights are gone
    assert evaluation.height_error_m is not None and abs(evaluation.height_error_m) < 0.2
    _assert_right_or_refused(outcome, evaluation)


@pytest.mark.parametrize(("preset", "seed"), [("sil-south", 1), ("dense-traffic", 4)])
def test_the_reported_time_offset_std_covers_the_clocks_error(preset: str, seed: int) -> None:
    # The body the template cannot describe moves the vehicle along its track as the fit sees it, and the
    # clock follows (0.1 m at 10 m/s is 10 ms). With the fit's own std alone these scenes' clocks were 10.0
    # ms off against 2.0 ms and 10.7 ms against 1.9 ms (46 of 229 realistic runs beyond 3 std); with the
    # left-out fits' scatter and the consider parameters' share the stds are 12.8 and 21.9 ms.
    outcome, evaluation, true_offset_ms = _run(preset, seed)
    result = outcome.result
    assert result.time_offset_ns is not None and result.time_offset_std_ns is not None
    assert abs(result.time_offset_ns / 1e6 - true_offset_ms) <= 3.0 * result.time_offset_std_ns / 1e6
    assert "(in quadrature: fit" in _stage_notes(outcome, "final fit")
    # The vehicle's GNSS wander (its profile's default, RTK fixed) is in the uncertainty, and said.
    assert "each drive-past's own GNSS error (3.0 cm across, 6.0 cm in height)" in _stage_notes(
        outcome, "final fit"
    )
    _assert_right_or_refused(outcome, evaluation)


@pytest.mark.parametrize("preset", ["pickup", "truck", "bus"])
def test_calibration_vehicles_no_other_scene_drives_are_right_or_refused(preset: str) -> None:
    # A pickup's bed, a box truck's and a bus's bodies are the template's worst matches (measured over seeds
    # 0-3 on four junctions, session 8: 0 of 60 runs accepted, poses 0.06-1.5 m off, 1 of 51 beyond 3 of its
    # stds, a wrong minimum 21 m off that was refused). Seed 0 of each: right or refused.
    outcome, evaluation, _ = _run(preset, 0)
    _assert_right_or_refused(outcome, evaluation)


def test_a_rolled_camera_that_sees_only_straight_drive_pasts_is_solved_from_pairs_of_them() -> None:
    # `rolled`: a camera 8 deg off square, three straight drive-pasts (two roads). The single-track poses
    # are metres apart and never group (10 of 10 seeds refused so before pipeline.pairs); solved together,
    # pairs on the two roads corroborated by the third drive-past give the pose (seed 0 at the time of
    # writing: 0.14 m / 0.17 deg off, refused on its position std 0.24 m).
    outcome, evaluation, _ = _run("rolled", 0)
    notes = _stage_notes(outcome, "straight pairs")
    assert "corroborated: tracks" in notes, notes
    assert evaluation.position_error_m is not None and evaluation.position_error_m < 0.5
    assert evaluation.rotation_error_deg is not None and evaluation.rotation_error_deg < 0.5
    _assert_right_or_refused(outcome, evaluation)


def test_boxes_that_reject_the_cuboid_body_are_fitted_with_the_template() -> None:
    # van seed 0: cross-validation over its drive-pasts preferred the cuboid, whose pose was 0.51 m / 0.29
    # deg off (session 6); the boxes reject the cuboid body far beyond chance (the template fit's departure
    # from it), so the cuboid is no candidate and the pose is the template's (measured 0.27 m / 0.13 deg).
    # Since cameras have a rolling shutter van seed 0 reaches no pose; seed 3 (chi-square 1516, 0.13 m /
    # 0.09 deg off) shows the same.
    outcome, evaluation, _ = _run("van", 3, 0)
    notes = _stage_notes(outcome, "final fit")
    assert "body the template: the boxes reject the cuboid body" in notes, notes
    _assert_right_or_refused(outcome, evaluation)


def test_boxes_beyond_where_the_lens_model_turns_back_are_dropped_and_said() -> None:
    # A fitted distortion polynomial that turns back inside the image (fx 900 on 1920 x 1080: the corners at
    # normalised radius 1.22, the turn at 1.01) on sil-south's far camera. Seed 0 at the time of writing:
    # 407 boxes dropped, refused on its position std (0.25 m), 0.21 m / 0.21 deg off.
    camera = look_at(
        "south", -38.0, -37.0, 14.0, (4.0, 6.0), width=1920, height=1080, fx=900.0,
        dist=(-0.30, 0.09, 0.0005, -0.0004, -0.012),
    )  # fmt: skip
    sim = simulate(replace(resolve_config("sil-south"), name="sil-south-turning-lens", cameras=(camera,)), 0)
    inputs = calibration_inputs(sim, "south")
    outcome = calibrate(inputs, PipelineParams(), np.random.default_rng(0), created_at_ns=CREATED_AT_NS)
    notes = _stage_notes(outcome, "tracking")
    assert "px from the principal point dropped: there the lens model's distortion turns back" in notes, notes
    tracking = next(s for s in outcome.stages if s.stage == "tracking")
    assert tracking.discarded > 0
    evaluation = evaluate_against_ground_truth(outcome.result, sim.ground_truth["south"])
    _assert_right_or_refused(outcome, evaluation)


def test_cuboid_boxes_keep_the_cuboid() -> None:
    # The first simulator's world draws the boxes from the cuboid: nothing rejects it, and cross-validation
    # keeps it (the template would only widen the uncertainty).
    sim = simulate("sil-south", seed=0, ideal=True)
    camera = sim.cameras[0]
    outcome = calibrate(
        calibration_inputs(sim, camera.camera_id),
        PipelineParams(),
        np.random.default_rng(0),
        created_at_ns=1_700_000_000_000_000_000,
    )
    notes = _stage_notes(outcome, "final fit")
    assert "body the cuboid" in notes, notes


def _calibrated(preset: str, seed: int) -> CalibrationOutcome:
    sim = simulate(preset, seed=seed)
    inputs = calibration_inputs(sim, sim.cameras[0].camera_id)
    return calibrate(
        inputs, PipelineParams(), np.random.default_rng(CALIBRATION_SEED), created_at_ns=CREATED_AT_NS
    )


def _stages(outcome: CalibrationOutcome) -> list[tuple[str, int, int, tuple[str, ...]]]:
    return [(s.stage, s.kept, s.discarded, tuple(s.notes)) for s in outcome.stages]


@pytest.mark.parametrize("second_pass_finds_nothing", [False, True])
def test_a_first_pass_on_the_wrong_clock_is_finished_only_when_it_stands(
    monkeypatch: pytest.MonkeyPatch, second_pass_finds_nothing: bool
) -> None:
    # sil-south seed 0: the first pass's joint fit settles the body (the boxes reject the cuboid) and moves
    # the clock by more than 30 ms, so its leave-one-out fits are skipped and every stage runs again on the
    # corrected clock. The result must be the one the whole first pass would have led to: with the second
    # pass's result when it finds a pose, with the first pass finished when it does not.
    import pipeline.calibrate as pipeline_calibrate

    passes = pipeline_calibrate._calibrate
    kinds: list[str] = []
    whole_first_pass = False

    def counted(*args, **kwargs):  # type: ignore[no-untyped-def]
        # calibrate's run() passes (inputs, params, rng, progress, created_at_ns, map_fn, tracked, scan,
        # hypotheses, focus, first) by position.
        focus = args[9]
        if whole_first_pass:
            args = (*args[:10], False)  # no pass may stop before its leave-one-out fits
        if second_pass_finds_nothing and focus is not None:
            # On the corrected clock no group forms (as single-track hypotheses sometimes do not).
            inputs, params = args[0], args[1]
            result = pipeline_calibrate.refused_result(inputs, params, None, CREATED_AT_NS, ["no group"])
            kinds.append("refused")
            return CalibrationOutcome(result, (), (), None, None)
        outcome = passes(*args, **kwargs)
        kinds.append(type(outcome).__name__)
        return outcome

    monkeypatch.setattr(pipeline_calibrate, "_calibrate", counted)
    deferred = _calibrated("sil-south", 0)
    assert kinds[0] == "_Pending"
    # The same with the first pass run whole.
    kinds.clear()
    whole_first_pass = True
    whole = _calibrated("sil-south", 0)
    assert kinds[0] == "CalibrationOutcome"
    assert deferred.result.model_dump() == whole.result.model_dump()
    assert _stages(deferred) == _stages(whole)
    notes = " ".join(note for s in deferred.stages if s.stage == "time offset" for note in s.notes)
    assert ("the first pass stands" in notes) == second_pass_finds_nothing, notes
