"""Validation gates (docs/design.md) and traversal counting from the data."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from pydantic import ValidationError

from pipeline.camera import CameraModel, camera_rotation_from_view
from pipeline.validation import ValidationEvidence, count_traversals, imprecise_only, validate
from schemas.common import CameraIntrinsics
from schemas.config import GatesConfig

GOOD = ValidationEvidence(
    traversals=3,
    tracks=4,
    correspondences=800,
    delta_p_mean_m=0.12,
    camera_height_m=9.5,
    position_std_m=0.06,
    rotation_std_deg=0.03,
    box_error_pct=3.0,
)


def test_good_evidence_is_accepted_with_no_reason() -> None:
    verdict = validate(GOOD, GatesConfig())
    assert verdict.is_accepted
    assert verdict.reasons == []


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"traversals": 1}, "traversals = 1"),
        ({"correspondences": 10}, "correspondences = 10"),
        ({"delta_p_mean_m": 0.8}, "delta_p mean = 0.800 m"),
        ({"delta_p_mean_m": math.nan}, "delta_p mean"),
        ({"camera_height_m": 1.0}, "camera height = 1.00 m"),
        ({"camera_height_m": 75.0}, "camera height = 75.00 m"),
        ({"position_std_m": 0.2}, "position std = 0.200 m"),
        ({"rotation_std_deg": 0.2}, "rotation std = 0.200 deg"),
        ({"rotation_std_deg": math.inf}, "rotation std"),
        ({"box_error_pct": 40.0}, "whole-box error = 40.0 %"),
    ],
)
def test_each_gate_refuses_with_a_reason_naming_quantity_and_value(
    change: dict[str, float], words: str
) -> None:
    verdict = validate(replace(GOOD, **change), GatesConfig())
    assert not verdict.is_accepted
    assert len(verdict.reasons) == 1
    assert words in verdict.reasons[0]


def test_a_std_refusal_names_its_largest_source_and_every_share() -> None:
    evidence = replace(
        GOOD,
        position_std_m=0.25,
        position_std_parts=(("fit", 0.05), ("gnss", 0.05), ("drive-pasts", 0.1), ("body", math.sqrt(0.0475))),
        rotation_std_deg=0.3,
        rotation_std_parts=(("fit", 0.06), ("drive-pasts", math.sqrt(0.3**2 - 0.06**2))),
    )
    position, rotation = validate(evidence, GatesConfig()).reasons
    assert position.startswith(
        "position std = 0.250 m (3 sigma 0.75 m > 0.5 m): mostly from the vehicle's body"
    )
    assert "more of them do not lower it" in position
    assert position.endswith("(in quadrature: body 0.218 m, drive-pasts 0.100 m, fit 0.050 m, gnss 0.050 m)")
    assert rotation.startswith(
        "rotation std = 0.300 deg (3 sigma 0.90 deg > 0.5 deg): mostly from the drive-pasts"
    )
    assert rotation.endswith("(in quadrature: drive-pasts 0.294 deg, fit 0.060 deg)")
    # Without its parts a std refusal says what it always said.
    unknown = validate(replace(evidence, position_std_parts=()), GatesConfig()).reasons[0]
    assert unknown.endswith("): the data leave the camera position unfixed in some direction")


def test_std_gates_hold_at_three_sigma() -> None:
    """0.15 deg passes a 0.5 deg gate at 3 sigma (0.45); 0.17 deg does not (0.51)."""
    assert validate(replace(GOOD, rotation_std_deg=0.15), GatesConfig()).is_accepted
    assert not validate(replace(GOOD, rotation_std_deg=0.17), GatesConfig()).is_accepted
    assert validate(replace(GOOD, rotation_std_deg=0.17), GatesConfig(std_sigmas=1.0)).is_accepted


def test_a_single_traversal_is_never_accepted_even_if_configured() -> None:
    with pytest.raises(ValidationError, match="min_traversals"):
        GatesConfig(min_traversals=1)
    # A caller that builds the model unchecked still gets the floor of two.
    verdict = validate(replace(GOOD, traversals=1), GatesConfig.model_construct(min_traversals=1))
    assert not verdict.is_accepted
    assert "two separate drive-pasts" in verdict.reasons[0]


def test_extra_reasons_refuse_and_are_kept_first() -> None:
    verdict = validate(replace(GOOD, extra_reasons=("ambiguous: x",)), GatesConfig())
    assert not verdict.is_accepted
    assert verdict.reasons == ["ambiguous: x"]


# Traversals: a camera 10 m up looking east along a road; the vehicle drives east past it, leaves the view
# (far beyond range, on a connector), and comes back.
_CAMERA = CameraModel.from_intrinsics(
    CameraIntrinsics(width=1920, height=1080, fx=1200.0, fy=1200.0, cx=960.0, cy=540.0)
)
_R = camera_rotation_from_view(0.0, math.radians(15.0))
_T = -_R @ np.array([0.0, 0.0, 10.0])
_S = 1_000_000_000  # ns per second


def _drive(x_of_second: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """Trajectory sampled at 10 Hz from positions given once per second (linear in between)."""
    seconds = np.arange(0.0, len(x_of_second) - 1 + 1e-9, 0.1)
    x = np.interp(seconds, np.arange(len(x_of_second)), x_of_second)
    poses = np.zeros((len(seconds), 6))
    poses[:, 0] = x
    poses[:, 1] = -3.0
    return (seconds * _S).astype(np.int64), poses


def test_two_tracks_of_one_pass_split_by_an_occlusion_count_once() -> None:
    stamps, poses = _drive([10.0 + 5.0 * i for i in range(12)])  # always in view, 10..65 m ahead
    spans = [(0, 4 * _S), (5 * _S, 10 * _S)]
    assert count_traversals(spans, stamps, poses, _R, _T, _CAMERA) == 1


def test_leaving_the_view_between_tracks_makes_a_second_traversal() -> None:
    # In view for 4 s, then 600 m away for 10 s, then back in view.
    xs = [10.0, 20.0, 30.0, 40.0, 50.0] + [600.0] * 10 + [10.0, 20.0, 30.0, 40.0]
    stamps, poses = _drive(xs)
    spans = [(0, 4 * _S), (15 * _S, 18 * _S)]
    assert count_traversals(spans, stamps, poses, _R, _T, _CAMERA) == 2


def test_a_short_excursion_out_of_view_does_not_count() -> None:
    xs = [10.0, 20.0, 30.0, 600.0, 30.0, 20.0, 10.0]  # out of view for about one second only
    stamps, poses = _drive(xs)
    spans = [(0, 2 * _S), (4 * _S, 6 * _S)]
    assert count_traversals(spans, stamps, poses, _R, _T, _CAMERA, min_absence_ns=2 * _S) == 1


def test_missing_poses_never_prove_the_vehicle_left() -> None:
    stamps, poses = _drive([10.0 + 5.0 * i for i in range(20)])
    gap = (stamps > 5 * _S) & (stamps < 14 * _S)  # a 9 s dropout while in view
    spans = [(0, 5 * _S), (14 * _S, 19 * _S)]
    assert count_traversals(spans, stamps[~gap], poses[~gap], _R, _T, _CAMERA) == 1


def test_no_tracks_no_traversals() -> None:
    stamps, poses = _drive([10.0, 20.0])
    assert count_traversals([], stamps, poses, _R, _T, _CAMERA) == 0


def test_a_vehicle_beyond_the_lens_model_is_out_of_view() -> None:
    """A wide lens whose polynomial (k1 -0.05) turns back 69 deg off axis: the vehicle waiting 16 m to the
    camera's side, 75 deg off axis, would project back inside the image (near (1692, 1023) px) if the
    polynomial were followed past its turn. It is out of view, so the drive-pasts before and after count
    twice."""
    camera = CameraModel.from_intrinsics(
        CameraIntrinsics(
            width=1920, height=1200, fx=800.0, fy=800.0, cx=960.0, cy=600.0, dist=(-0.05, 0.0, 0.0, 0.0, 0.0)
        )
    )  # fmt: skip
    stamps, poses = _drive([10.0, 20.0, 30.0, 40.0, 50.0] + [0.0] * 10 + [10.0, 20.0, 30.0, 40.0])
    aside = (stamps > 4.5 * _S) & (stamps < 14.5 * _S)
    poses[aside, :2] = (2.26, -15.71)
    spans = [(0, 4 * _S), (15 * _S, 18 * _S)]
    assert count_traversals(spans, stamps, poses, _R, _T, camera) == 2


def test_a_refusal_on_stds_alone_is_told_from_one_on_other_gates() -> None:
    # calibrate() searches the clock after a refusal unless the pose was refused on its stds alone.
    imprecise = replace(GOOD, position_std_m=1.0, rotation_std_deg=1.0)
    verdict = validate(imprecise, GatesConfig())
    assert len(verdict.reasons) == 2 and imprecise_only(verdict.reasons)
    assert not imprecise_only(validate(replace(imprecise, traversals=1), GatesConfig()).reasons)
    assert not imprecise_only(validate(replace(GOOD, delta_p_mean_m=0.8), GatesConfig()).reasons)
    assert not imprecise_only(validate(GOOD, GatesConfig()).reasons)  # accepted: no reasons
    # The caller's tolerated reasons (calibrate: drive-pasts that disagree within the gates' limits) count
    # as imprecision; any other reason does not.
    disagree = "traversals disagree by 0.28 m / 0.28 deg: traversal 3's boxes pull the others' pose"
    both = validate(replace(imprecise, extra_reasons=(disagree,)), GatesConfig()).reasons
    assert not imprecise_only(both)
    assert imprecise_only(both, (disagree,))
    assert not imprecise_only(
        validate(replace(GOOD, extra_reasons=(disagree,), traversals=1), GatesConfig()).reasons, (disagree,)
    )
