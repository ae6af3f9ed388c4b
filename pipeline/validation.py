"""Validation (paper Sec. IV-B metrics as gates, docs/design.md 'Validation gates'): evidence -> Verdict.

A wrong calibration is worse than none: every gate that fails adds a reason and the verdict is refused.
Traversals are counted from the data, not trusted from the caller: two tracks belong to separate traversals
only if the calibration vehicle left the camera's view between them (its projected position under the
candidate calibration went out of the image, or beyond detection range).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.arrays import PoseArray, Rotation, Stamps, Vec3, check_shape
from pipeline.camera import CameraModel, project_points
from schemas.config import GatesConfig
from schemas.results import Verdict


@dataclass(frozen=True, slots=True)
class ValidationEvidence:
    """What the gates look at, all measured on the merged calibration-vehicle tracks of the chosen group."""

    traversals: int
    tracks: int
    correspondences: int
    delta_p_mean_m: float
    camera_height_m: float
    position_std_m: float
    rotation_std_deg: float
    box_error_pct: float
    extra_reasons: tuple[str, ...] = ()
    # Where the largest position / rotation std comes from: (source, std) pairs that add up in quadrature
    # (m, deg; sources in STD_SOURCES), so a refusal on a std says what would lower it. Empty: not known.
    position_std_parts: tuple[tuple[str, float], ...] = ()
    rotation_std_parts: tuple[tuple[str, float], ...] = ()


# The sources of a pose's std (final_fit.FinalFit.std_parts) and what each means to an operator.
STD_SOURCES = {
    "fit": "the fit: the boxes fix the pose only weakly in some direction (e.g. every pass along one "
    "straight line)",
    "drive-pasts": "the drive-pasts' disagreement: the pose moves when one of them is left out",
    "body": "the vehicle's body shape, which the template cannot describe (and the detector's box "
    "convention): the same in every drive-past, so more of them do not lower it",
    "gnss": "the vehicle's GNSS error: its offset common to every pose and each drive-past's own wander "
    "(its profile's gnss_wander_m)",
    "readout": "the camera's rolling-shutter readout, which the data could not tell from 0 (held there)",
}


# How the std gates' reasons begin (validate writes them, imprecise_only reads them).
_POSITION_STD, _ROTATION_STD = "position std = ", "rotation std = "


def imprecise_only(reasons: Sequence[str], tolerated: Sequence[str] = ()) -> bool:
    """Whether a refusal's reasons (`validate`'s) are all std gates, or among `tolerated` (the caller's: the
    drive-pasts' disagreement where it lies within the gates' limits): a pose whose drive-pasts agree with
    each other and with the boxes, known too loosely to accept."""
    return bool(reasons) and all(
        reason.startswith((_POSITION_STD, _ROTATION_STD)) or reason in tolerated for reason in reasons
    )


def validate(evidence: ValidationEvidence, gates: GatesConfig) -> Verdict:
    """Apply every gate; accepted only if all pass. Reasons name the quantity, its value and the limit.

    The gates are the daemon's configuration model (schemas.config.GatesConfig, the one definition of their
    fields and defaults); `rsucal calibrate` and the benchmarks use its defaults."""
    reasons: list[str] = list(evidence.extra_reasons)
    e, g = evidence, gates
    if e.traversals < max(2, g.min_traversals):
        reasons.append(
            f"traversals = {e.traversals} < {max(2, g.min_traversals)}: the vehicle must be seen on "
            "at least two separate drive-pasts"
        )
    if e.correspondences < g.min_correspondences:
        reasons.append(f"correspondences = {e.correspondences} < {g.min_correspondences}")
    if not np.isfinite(e.delta_p_mean_m) or e.delta_p_mean_m > g.max_delta_p_mean_m:
        reasons.append(f"delta_p mean = {e.delta_p_mean_m:.3f} m > {g.max_delta_p_mean_m} m")
    if not (g.min_camera_height_m <= e.camera_height_m <= g.max_camera_height_m):
        reasons.append(
            f"camera height = {e.camera_height_m:.2f} m above the fitted ground outside "
            f"[{g.min_camera_height_m}, {g.max_camera_height_m}] m"
        )
    k = g.std_sigmas
    if not np.isfinite(e.position_std_m) or k * e.position_std_m > g.max_position_std_m:
        reasons.append(
            f"{_POSITION_STD}{e.position_std_m:.3f} m ({k:g} sigma {k * e.position_std_m:.2f} m > "
            f"{g.max_position_std_m} m): "
            + _std_source(
                e.position_std_parts, "m", "the data leave the camera position unfixed in some direction"
            )
        )
    if not np.isfinite(e.rotation_std_deg) or k * e.rotation_std_deg > g.max_rotation_std_deg:
        reasons.append(
            f"{_ROTATION_STD}{e.rotation_std_deg:.3f} deg ({k:g} sigma {k * e.rotation_std_deg:.2f} deg > "
            f"{g.max_rotation_std_deg} deg): "
            + _std_source(
                e.rotation_std_parts,
                "deg",
                "the data leave a rotation unfixed (e.g. all passes along one straight line)",
            )
        )
    if not np.isfinite(e.box_error_pct) or e.box_error_pct > g.max_box_error_pct:
        reasons.append(
            f"whole-box error = {e.box_error_pct:.1f} % of the box height > {g.max_box_error_pct} %: the "
            "calibration vehicle's cuboid does not reproduce its boxes"
        )
    return Verdict(status="refused" if reasons else "accepted", reasons=reasons)


def count_traversals(
    track_spans: Sequence[tuple[int, int]],
    trajectory_stamps: Stamps,
    trajectory_poses: PoseArray,
    R_cam_from_local: Rotation,
    t_cam_from_local: Vec3,
    camera: CameraModel,
    max_range_m: float = 250.0,
    min_absence_ns: int = 2_000_000_000,
) -> int:
    """Number of separate drive-pasts among tracks with time spans [(start_ns, end_ns), ...].

    Tracks are sorted by start; consecutive ones belong to one traversal unless, in the gap between them,
    the vehicle's reference point projected with the candidate calibration was outside the image (or behind
    the camera, or farther than `max_range_m`) for at least `min_absence_ns`. A track fragmented by an
    occlusion therefore never counts twice, and a second drive-past always counts once more.
    """
    check_shape(trajectory_poses, "N,6", name="trajectory_poses")
    if not track_spans:
        return 0
    spans = sorted(track_spans)
    camera_centre = -R_cam_from_local.T @ t_cam_from_local
    pixels, depth = project_points(trajectory_poses[:, :3], R_cam_from_local, t_cam_from_local, camera)
    distance = np.linalg.norm(trajectory_poses[:, :3] - camera_centre, axis=1)
    with np.errstate(invalid="ignore"):
        in_view = (
            (depth > 0)
            & (distance <= max_range_m)
            & (pixels[:, 0] >= 0)
            & (pixels[:, 0] <= camera.width)
            & (pixels[:, 1] >= 0)
            & (pixels[:, 1] <= camera.height)
        )
    traversals = 1
    current_end = spans[0][1]
    for start, end in spans[1:]:
        if start > current_end and _was_absent(
            trajectory_stamps, in_view, current_end, start, min_absence_ns
        ):
            traversals += 1
        current_end = max(current_end, end)
    return traversals


def _was_absent(stamps: Stamps, in_view: np.ndarray, start_ns: int, end_ns: int, min_absence_ns: int) -> bool:
    """True if the vehicle was out of view for a contiguous stretch >= min_absence_ns within (start, end).

    A gap in the trajectory itself (no poses) of that length also counts as absence only if the poses
    bracketing it are out of view: missing data never proves the vehicle left.
    """
    lo, hi = np.searchsorted(stamps, [start_ns, end_ns])
    if hi - lo < 2:
        return False
    window_stamps = stamps[lo:hi]
    out = ~in_view[lo:hi]
    if not out.any():
        return False
    # Longest run of consecutive out-of-view samples, measured in time between its first and last sample.
    edges = np.flatnonzero(np.diff(np.concatenate([[0], out.astype(np.int8), [0]])))
    run_starts, run_ends = edges[::2], edges[1::2] - 1
    longest = np.max(window_stamps[run_ends] - window_stamps[run_starts])
    return bool(longest >= min_absence_ns)


def _std_source(parts: tuple[tuple[str, float], ...], unit: str, unknown: str) -> str:
    """What a refusal on a std says: its largest source and what that means, then every source's share (in
    quadrature); `unknown` when the parts are not given or not finite."""
    if not parts or not all(np.isfinite(std) for _, std in parts):
        return unknown
    ranked = sorted(parts, key=lambda part: -part[1])
    listed = ", ".join(f"{name} {std:.3f} {unit}" for name, std in ranked if std > 0.0)
    return f"mostly from {STD_SOURCES[ranked[0][0]]} (in quadrature: {listed})"
