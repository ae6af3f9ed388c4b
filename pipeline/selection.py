"""Selection: from hypothesis groups to one chosen candidate pose (ours; the paper picks the lowest delta_p).

Each group of tracks is refined into a Candidate (paper III-F bottom-edge refinement, then our whole-box
refinement with outlier boxes trimmed) and scored by how well the calibration vehicle's cuboid, projected with
the candidate's pose, reproduces its boxes (scale-free whole-box error). Then:

- regroup: when grouping found no group, single-track poses refined on their own boxes that agree are grouped;
- merge: candidates whose refined poses agree are one camera seen through one vehicle: refined on the union;
- set aside: a candidate whose pose cannot reproduce another candidate's boxes, while that one's pose
  reproduces its boxes, describes less of the data (short or degenerate tracks of the vehicle fitted to a
  wrong pose fit their own few boxes closely, yet a right pose explains them as well);
- rank: by box error (groups seen on >= 2 traversals first); a second candidate that fits about as well with
  a clearly different pose makes the result ambiguous (the caller refuses);
- extend: tracks the chosen pose explains as the calibration vehicle are added and the union refined again.

Every stage function returns its own StageReport.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.arrays import FloatArray, Rotation, Vec3
from pipeline.association import MatchedTrack, Trajectory, apart_in_time, select_rows, track_spans
from pipeline.camera import CameraModel, pose_distance
from pipeline.errors import DegenerateGeometry
from pipeline.ground import GroundPlaneFit, fit_ground_plane
from pipeline.hypotheses import Hypothesis
from pipeline.metrics import DeltaPSummary, delta_p
from pipeline.refinement import (
    Refinement,
    RefinementParams,
    box_residuals,
    refine_bottom_edge,
    refine_whole_box,
)
from pipeline.stage import StageReport
from pipeline.validation import count_traversals
from pipeline.vehicle import footprint_centres, footprint_corners
from schemas.common import VehicleProfile


@dataclass(frozen=True, slots=True)
class SelectionParams:
    """How candidate groups are compared (ours; the paper picks the lowest delta_p)."""

    # Two groups whose scale-free box errors are within this factor of each other are a tie ...
    tie_ratio: float = 1.25
    # ... and so are errors both below this share of the box height (a fifth of a pixel on a 100 px box): on
    # exact boxes errors of 1e-9 and 1e-8 differ by rounding alone, which the BLAS build decides.
    tie_floor: float = 0.002
    # ... and a tie between poses further apart than this is an ambiguity: refuse.
    ambiguity_shift_m: float = 1.0
    ambiguity_angle_deg: float = 1.0


@dataclass(frozen=True, slots=True)
class Candidate:
    """One hypothesis group after refinement: its tracks, poses and scores."""

    track_ids: tuple[int, ...]
    paper: Refinement  # bottom-edge refinement of the merged group (paper III-F)
    whole_box: Refinement  # our final refinement, started from the best of the paper's
    box_error_rel: float  # median over boxes of max |edge residual| / box height (scale-free)
    metrics: DeltaPSummary  # paper IV-B on the merged tracks with the whole-box pose
    traversals: int
    track_spans: tuple[tuple[int, int], ...] = ()  # (first, last) stamp ns of each member track

    @property
    def delta_p_mean_m(self) -> float:
        value = self.metrics.delta_p_mean_m
        return float("inf") if value is None else value


@dataclass(frozen=True, slots=True)
class Scene:
    """What selection works on: the tracks matched to the vehicle's poses (by id, in matching order), the
    trajectory, the camera, the vehicle, and the parameters of refinement and selection."""

    tracks: Mapping[int, MatchedTrack]
    trajectory: Trajectory
    camera: CameraModel
    vehicle: VehicleProfile
    refinement: RefinementParams
    selection: SelectionParams

    def members(self, track_ids: Sequence[int]) -> list[MatchedTrack]:
        return [self.tracks[i] for i in track_ids]


@dataclass(frozen=True, slots=True)
class Choice:
    """The selection's outcome: the chosen candidate (extended), the ambiguity reason ('' when none) and every
    candidate (the chosen one as extended)."""

    chosen: Candidate
    ambiguity: str
    candidates: tuple[Candidate, ...]
    reports: tuple[StageReport, ...]  # "set aside" when a candidate was, "extension" when tracks were added


# --- scores ----------------------------------------------------------------------------------------------


def box_misfits(R: Rotation, t: Vec3, members: Sequence[MatchedTrack], scene: Scene) -> FloatArray:
    """Per box (all members stacked): max |edge residual| / box height; NaN where every edge is clipped."""
    residuals, heights = box_residuals(R, t, members, scene.camera, scene.vehicle, scene.refinement)
    finite_rows = np.isfinite(residuals).any(axis=1)
    misfit = np.full(len(residuals), np.nan)
    misfit[finite_rows] = np.nanmax(np.abs(residuals[finite_rows]), axis=1) / heights[finite_rows]
    return misfit


def box_error(R: Rotation, t: Vec3, members: Sequence[MatchedTrack], scene: Scene) -> float:
    """Scale-free whole-box misfit: median over boxes of max |edge residual| / box height.

    The calibration vehicle's cuboid projected with the right pose reproduces its own boxes to the detector's
    noise (~1-2 %); a pose made from another vehicle's track cannot match the calibration vehicle's size and
    shape along a whole drive-past."""
    misfit = box_misfits(R, t, members, scene)
    misfit = misfit[np.isfinite(misfit)]
    return float(np.median(misfit)) if len(misfit) else float("inf")


def trim(
    members: Sequence[MatchedTrack], R: Rotation, t: Vec3, scene: Scene, floor: float
) -> list[MatchedTrack]:
    """The member tracks without boxes whose misfit under (R, t) exceeds max(floor, 3 x median misfit)
    (misfit = max |edge residual| / box height); tracks left with no box are dropped."""
    misfit = box_misfits(R, t, members, scene)
    finite = misfit[np.isfinite(misfit)]
    threshold = max(floor, 3.0 * float(np.median(finite))) if len(finite) else floor
    return select_rows(members, np.isfinite(misfit) & (misfit <= threshold))


def ground_under(tracks: Sequence[MatchedTrack], vehicle: VehicleProfile) -> GroundPlaneFit:
    """PCA ground plane (paper III-F) of the vehicle's footprint centres while these tracks saw it."""
    return fit_ground_plane(np.concatenate([footprint_centres(m.poses, vehicle) for m in tracks]))


def agree(a: Candidate, b: Candidate, params: SelectionParams) -> bool:
    """Two refined poses within the ambiguity thresholds of each other."""
    shift, angle = _distance(a.whole_box, b.whole_box)
    return shift <= params.ambiguity_shift_m and angle <= params.ambiguity_angle_deg


def describe(candidate: Candidate) -> str:
    paper_dp = candidate.paper.delta_p_m[np.isfinite(candidate.paper.delta_p_m)]
    return (
        f"tracks {list(candidate.track_ids)}, {candidate.traversals} traversal(s), "
        f"box error {100 * candidate.box_error_rel:.2f} %, delta_p {candidate.delta_p_mean_m:.3f} m, "
        f"paper refinement delta_p {float(np.mean(paper_dp)) if len(paper_dp) else float('nan'):.3f} m"
    )


def _distance(a: Refinement, b: Refinement) -> tuple[float, float]:
    return pose_distance(a.R_cam_from_local, a.camera_centre, b.R_cam_from_local, b.camera_centre)


# --- candidates ------------------------------------------------------------------------------------------


def refine_group(members: Sequence[MatchedTrack], starts: Sequence[Hypothesis], scene: Scene) -> Candidate:
    """Paper III-F: refine each hypothesis on its own track, merge, refine again; keep the merge only if no
    single hypothesis beats it on the merged tracks. Then our whole-box refinement from the winner."""
    ground = ground_under(members, scene.vehicle)
    camera, vehicle, refinement = scene.camera, scene.vehicle, scene.refinement
    singles = [
        refine_bottom_edge(h.R_cam_from_local, h.t_cam_from_local, [m], camera, vehicle, ground, refinement)
        for h, m in zip(starts, members, strict=True)
    ]
    # Start the merged refinement from the single whose pose explains all member tracks best.
    start_scores = [box_error(s.R_cam_from_local, s.t_cam_from_local, members, scene) for s in singles]
    best_single = singles[int(np.argmin(start_scores))]
    merged = refine_bottom_edge(
        best_single.R_cam_from_local,
        best_single.t_cam_from_local,
        members,
        camera,
        vehicle,
        ground,
        refinement,
    )
    merged_score = box_error(merged.R_cam_from_local, merged.t_cam_from_local, members, scene)
    paper = merged if merged_score <= min(start_scores) else best_single

    # Ours: whole-box robust least squares, started from whichever candidate pose (the paper's result, the
    # best single, every member hypothesis) explains the merged boxes best; the bottom edge cannot fix the
    # camera-x shift, so the paper's result is not always the best start.
    poses: list[tuple[Rotation, Vec3]] = [
        (paper.R_cam_from_local, paper.t_cam_from_local),
        (best_single.R_cam_from_local, best_single.t_cam_from_local),
        *((h.R_cam_from_local, h.t_cam_from_local) for h in starts),
    ]
    errors = [box_error(R, t, members, scene) for R, t in poses]
    R0, t0 = poses[int(np.argmin(errors))]
    # Boxes that are not the calibration vehicle's (an identity switch of the tracker) or are cut by an
    # occluder have misfits of tens of percent; even a robust loss with linear tails (Huber) lets a few of
    # those hundreds-of-pixel residuals outweigh hundreds of good boxes, so they are trimmed before and
    # after the fit (relative to the median misfit, never below the detector's noise level).
    return finish_candidate(members, R0, t0, paper, ground, scene)


def finish_candidate(
    members: Sequence[MatchedTrack],
    R0: Rotation,
    t0: Vec3,
    paper: Refinement,
    ground: GroundPlaneFit,
    scene: Scene,
) -> Candidate:
    """Whole-box refinement of `members` from (R0, t0), with outlier boxes trimmed, then the candidate's
    scores: scale-free box error, paper metrics on the kept boxes, traversals counted from the data."""
    camera, vehicle, refinement = scene.camera, scene.vehicle, scene.refinement
    fit_tracks = trim(members, R0, t0, scene, floor=0.25)
    whole_box = refine_whole_box(R0, t0, fit_tracks, camera, vehicle, refinement, ground)
    for _ in range(2):
        trimmed = trim(members, whole_box.R_cam_from_local, whole_box.t_cam_from_local, scene, 0.08)
        if sum(len(m.boxes) for m in trimmed) == sum(len(m.boxes) for m in fit_tracks):
            break
        fit_tracks = trimmed
        whole_box = refine_whole_box(
            whole_box.R_cam_from_local,
            whole_box.t_cam_from_local,
            fit_tracks,
            camera,
            vehicle,
            refinement,
            ground,
        )
    R, t = whole_box.R_cam_from_local, whole_box.t_cam_from_local
    spans = track_spans(members)
    return Candidate(
        track_ids=tuple(m.track_id for m in members),
        paper=paper,
        whole_box=whole_box,
        box_error_rel=box_error(R, t, members, scene),
        metrics=_delta_p_on(fit_tracks, R, t, camera, vehicle),
        traversals=count_traversals(spans, scene.trajectory.stamps, scene.trajectory.poses, R, t, camera),
        track_spans=tuple(spans),
    )


def _delta_p_on(
    members: Sequence[MatchedTrack], R: Rotation, t: Vec3, camera: CameraModel, vehicle: VehicleProfile
) -> DeltaPSummary:
    """Paper IV-B metrics on the merged tracks, each box against the plane of its own (reported) footprint:
    the local road surface, right on slopes where the track's PCA plane is not."""
    boxes = np.concatenate([m.boxes for m in members])
    footprints = footprint_corners(np.concatenate([m.poses for m in members]), vehicle)
    return delta_p(boxes, footprints, R, t, camera).summary()


# --- stages ----------------------------------------------------------------------------------------------


def regroup(hypotheses: Sequence[Hypothesis], scene: Scene) -> tuple[list[tuple[int, ...]], StageReport]:
    """Connected components (>= 2 tracks) of single-track whole-box poses that agree within twice the
    ambiguity thresholds, from tracks never seen at the same time (the vehicle is one box at a time).

    For when grouping found no group: single-track hypotheses can be too coarse for the overlap score (a pose
    1-2 deg off puts the vehicle's positions beside its boxes); refined on their own whole boxes they agree.
    """
    refined: list[tuple[MatchedTrack, Refinement]] = []
    for hypothesis in hypotheses:
        track = scene.tracks[hypothesis.track_id]
        R, t = hypothesis.R_cam_from_local, hypothesis.t_cam_from_local
        try:
            kept = trim([track], R, t, scene, floor=0.25)
            if kept:
                pose = refine_whole_box(R, t, kept, scene.camera, scene.vehicle, scene.refinement)
                refined.append((track, pose))
        except DegenerateGeometry:
            continue
    n = len(refined)
    shift_limit = 2.0 * scene.selection.ambiguity_shift_m
    angle_limit = 2.0 * scene.selection.ambiguity_angle_deg
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(n):
        track_i, pose_i = refined[i]
        for j in range(i + 1, n):
            track_j, pose_j = refined[j]
            if track_i.stamps[0] <= track_j.stamps[-1] and track_j.stamps[0] <= track_i.stamps[-1]:
                continue
            shift, angle = _distance(pose_i, pose_j)
            if shift <= shift_limit and angle <= angle_limit:
                parent[root(i)] = root(j)
    components: dict[int, list[int]] = {}
    for i in range(n):
        components.setdefault(root(i), []).append(refined[i][0].track_id)
    groups = [tuple(sorted(ids)) for ids in components.values() if len(ids) >= 2]
    notes = tuple(f"refined hypotheses agree: tracks {list(g)}" for g in groups)
    return groups, StageReport(
        "regrouping", len(groups), 0, notes or ("no two refined hypotheses agree either",)
    )


def refine_groups(
    groups: Sequence[tuple[int, ...]],
    hypotheses: Sequence[Hypothesis],
    scene: Scene,
    say: Callable[[str, float], None],
    starts: Sequence[Sequence[Hypothesis]] | None = None,
) -> tuple[list[Candidate], StageReport]:
    """Every group refined into a candidate (a group whose refinement fails is noted and left out), then the
    candidates whose refined poses agree merged. `starts`: each group's own hypotheses, one per track in
    its order (pairs of tracks solved as one, pipeline.pairs); else each track's from `hypotheses`."""
    by_id = {h.track_id: h for h in hypotheses}
    candidates: list[Candidate] = []
    notes: list[str] = []
    for index, track_ids in enumerate(groups):
        say("refinement", 0.55 + 0.35 * index / len(groups))
        try:
            own = starts[index] if starts is not None else [by_id[i] for i in track_ids]
            candidate = refine_group(scene.members(track_ids), own, scene)
        except DegenerateGeometry as err:
            notes.append(f"group {index}: refinement failed: {err}")
            continue
        candidates.append(candidate)
        notes.append(f"group {index}: {describe(candidate)}")
    # Grouping splits one vehicle's drive-pasts into several groups when single-track hypotheses are coarse;
    # refined poses that agree are the same camera seen through the same vehicle: merge them and refine the
    # union, which adds traversals and data (kept only if the union still fits as well).
    merged = merge_agreeing(candidates, by_id, scene)
    notes.extend(f"merged agreeing groups: {describe(c)}" for c in merged if c not in candidates)
    return merged, StageReport("refinement", len(merged), len(groups) - len(merged), tuple(notes))


def fits_as_well(error: float, reference: float, params: SelectionParams) -> bool:
    """Is a scale-free box error a tie with (or better than) the reference: within tie_ratio of it, or both
    below tie_floor?"""
    return error <= params.tie_ratio * max(reference, params.tie_floor)


def merge_agreeing(
    candidates: Sequence[Candidate], hypotheses: Mapping[int, Hypothesis], scene: Scene
) -> list[Candidate]:
    """Candidates whose refined poses agree, refined again on the union of their tracks (greedy, best
    first); the union is kept only when it fits as well (tie_ratio) and agrees with the best member."""
    params = scene.selection
    clusters: list[list[Candidate]] = []
    for candidate in sorted(candidates, key=lambda c: c.box_error_rel):
        for cluster in clusters:
            if agree(cluster[0], candidate, params):
                cluster.append(candidate)
                break
        else:
            clusters.append([candidate])
    result: list[Candidate] = []
    for cluster in clusters:
        if len(cluster) == 1:
            result.append(cluster[0])
            continue
        ids = sorted({i for c in cluster for i in c.track_ids})
        try:
            union = refine_group(scene.members(ids), [hypotheses[i] for i in ids], scene)
        except DegenerateGeometry:
            result.extend(cluster)
            continue
        if fits_as_well(union.box_error_rel, cluster[0].box_error_rel, params) and agree(
            union, cluster[0], params
        ):
            result.append(union)
        else:
            result.extend(cluster)
    return result


def rank(candidates: Sequence[Candidate], params: SelectionParams) -> tuple[Candidate, str]:
    """Best candidate by scale-free box error (groups seen on >= 2 traversals first); refuse-worthy ambiguity
    (a reason, '' when none) when another candidate fits about as well with a clearly different pose."""
    ranked = sorted(
        candidates, key=lambda c: (c.traversals < 2, c.box_error_rel, -c.traversals, c.delta_p_mean_m)
    )
    best = ranked[0]
    for other in ranked[1:]:
        if other.traversals < 2 or not fits_as_well(other.box_error_rel, best.box_error_rel, params):
            continue
        shift, angle = _distance(other.whole_box, best.whole_box)
        if shift > params.ambiguity_shift_m or angle > params.ambiguity_angle_deg:
            return best, (
                f"ambiguous: tracks {list(other.track_ids)} fit about as well "
                f"(box error {100 * other.box_error_rel:.2f} % vs {100 * best.box_error_rel:.2f} %) "
                f"with a pose {shift:.2f} m / {angle:.2f} deg away"
            )
    return best, ""


def explain_limit(candidate: Candidate) -> float:
    """The median box misfit up to which the candidate's pose explains a track as the calibration vehicle:
    2.5 x its own box error, at least 10 % of the box height."""
    return max(0.10, 2.5 * candidate.box_error_rel)


def median_misfit(pose_of: Candidate, members: Sequence[MatchedTrack], scene: Scene) -> float:
    """Median box misfit of `members` under `pose_of`'s pose; inf with fewer than 5 boxes to judge by."""
    R, t = pose_of.whole_box.R_cam_from_local, pose_of.whole_box.t_cam_from_local
    misfit = box_misfits(R, t, members, scene)
    misfit = misfit[np.isfinite(misfit)]
    return float(np.median(misfit)) if len(misfit) >= 5 else float("inf")


def set_aside(candidates: Sequence[Candidate], scene: Scene) -> tuple[list[Candidate], StageReport | None]:
    """The candidates without those another one explains but which cannot explain it (both seen on at
    least two traversals): the other's pose reproduces their boxes as the calibration vehicle
    (explain_limit), theirs does not reproduce the other's, and on the boxes of both together the other's
    pose fits better (so a pose whose own fit is poor, and whose limit is wide, cannot set a better one
    aside). Two wrong poses, or a right and a mirrored one that explain each other's boxes, set nothing
    aside: rank's ambiguity rule judges them."""
    multi = [c for c in candidates if c.traversals >= 2]
    lines: list[str] = []
    aside: set[int] = set()
    for weaker in multi:
        for stronger in multi:
            if stronger is weaker:
                continue
            covers = median_misfit(stronger, scene.members(weaker.track_ids), scene)
            if covers > explain_limit(stronger):
                continue
            back = median_misfit(weaker, scene.members(stronger.track_ids), scene)
            if back <= explain_limit(weaker):
                continue
            both = scene.members(sorted(set(weaker.track_ids) | set(stronger.track_ids)))
            if median_misfit(stronger, both, scene) >= median_misfit(weaker, both, scene):
                continue
            aside.add(id(weaker))
            lines.append(
                f"tracks {list(weaker.track_ids)} set aside: the pose of tracks {list(stronger.track_ids)} "
                f"explains their boxes (median misfit {100 * covers:.1f} %), theirs does not explain its "
                f"({100 * back:.1f} %)"
            )
            break
    kept = [c for c in candidates if id(c) not in aside]
    if not aside or not any(c.traversals >= 2 for c in kept):
        return list(candidates), None
    return kept, StageReport("set aside", len(kept), len(aside), tuple(lines))


def extend(chosen: Candidate, scene: Scene) -> Candidate:
    """Add every other track that the chosen pose explains as the calibration vehicle, and refine again.

    Beyond the paper: occlusions and tracker decay cut the vehicle's drive-pasts into fragments too short or
    too straight for a hypothesis of their own, yet with a good pose each fragment is recognisable: the
    vehicle's cuboid, projected at the fragment's stamps, reproduces its boxes. A track of another vehicle
    does not (wrong place or size), and a track seen at the same time as one of ours cannot be the vehicle.
    Kept only if the union's pose agrees with the chosen one and fits as well.
    """
    R, t = chosen.whole_box.R_cam_from_local, chosen.whole_box.t_cam_from_local
    limit = explain_limit(chosen)
    members = scene.members(chosen.track_ids)
    extra: list[tuple[float, MatchedTrack]] = []
    for track in scene.tracks.values():
        if track.track_id in chosen.track_ids or len(track.boxes) < 5:
            continue
        misfit = median_misfit(chosen, [track], scene)
        if misfit <= limit:
            extra.append((misfit, track))
    added = apart_in_time(extra, track_spans(members))
    if not added:
        return chosen
    union = sorted([*members, *added], key=lambda m: int(m.stamps[0]))
    ground = ground_under(union, scene.vehicle)
    try:
        candidate = finish_candidate(union, R, t, chosen.paper, ground, scene)
    except DegenerateGeometry:
        return chosen
    if fits_as_well(candidate.box_error_rel, chosen.box_error_rel, scene.selection) and agree(
        candidate, chosen, scene.selection
    ):
        return candidate
    return chosen


def choose(candidates: Sequence[Candidate], scene: Scene) -> Choice:
    """Set aside the candidates another one explains, rank the rest (with the ambiguity rule), then extend
    the best by the tracks its pose explains."""
    kept, aside = set_aside(candidates, scene)
    reports = () if aside is None else (aside,)
    best, ambiguity = rank(kept, scene.selection)
    extended = extend(best, scene)
    if extended is best:
        return Choice(best, ambiguity, tuple(candidates), reports)
    report = StageReport(
        "extension",
        len(extended.track_ids) - len(best.track_ids),
        0,
        (f"tracks the chosen pose explains added: {describe(extended)}",),
    )
    return Choice(
        extended, ambiguity, tuple(extended if c is best else c for c in candidates), (*reports, report)
    )
