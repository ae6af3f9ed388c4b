"""One calibration hypothesis per image track: EPnP inside RANSAC (paper Sec. III-D).

Every image track overlapping the calibration vehicle's time span is assumed, in turn, to be that vehicle:
its box centres (px) paired with the vehicle's body centre at the same stamps (local frame, m) give 2D-3D
correspondences, and EPnP + RANSAC turns them into a camera pose. Tracks too short, not moving, ill-posed,
badly fitting, or placing the camera far from the driven path or under the road are rejected, each with a
reason. Beyond the paper, a straight track (whose pose EPnP cannot fix) is solved from the boxes' shape and
the assumption that the camera is mounted square (upright or portrait): `pipeline.straight_track`.
Input: `MatchedTrack`s (`pipeline.association.match_tracks`); output: a `HypothesisSet`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from pipeline.arrays import FloatArray, Mask, Pixels, Points3, Rotation, Vec3
from pipeline.association import MatchedTrack, Trajectory
from pipeline.camera import (
    CameraModel,
    camera_centre,
    project_points,
    rotation_from_rvec,
    rvec_from_rotation,
)
from pipeline.ground import GroundPlaneFit
from pipeline.mapping import MapFn
from pipeline.stage import Reason
from pipeline.straight_track import (
    StraightTrackParams,
    TrackShape,
    pose_box_misfit,
    solve_straight_track,
    track_line,
)
from pipeline.vehicle import body_centres
from schemas.common import VehicleProfile

# LM runs until the step is negligible: EPnP and SQPnP undistort with OpenCV's approximate inverse and
# leave ~1e-3 px on exact barrel-distorted data, LM projects forward and reaches ~1e-9 px.
_LM_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-12)


@dataclass(frozen=True, slots=True)
class HypothesisParams:
    """Filters and solver settings of paper III-D. Defaults were checked on the simulator presets
    (sil-*, carla-like, dense-traffic) and follow the reference toolbox's SIL configuration where it has
    a value (RANSAC 8 px / 500 iterations, 3 m track, d_thr; its 100 px image track and 50 px median are
    for 1920 px images and loosened / tightened here as noted)."""

    # EPnP needs 4 points (paper); we ask for 8 because OpenCV's RANSAC draws 5-point minimal sets and
    # a track that short has no redundancy left to reject a single bad box.
    min_correspondences: int = 8
    # "The observed vehicle didn't move" (paper): diagonal of the bounding box of the box-centre track (px)
    # and of the body-centre track's horizontal extent (m).
    min_image_extent_px: float = 60.0
    min_track_extent_m: float = 3.0
    reproj_threshold_px: float = 8.0  # RANSAC inlier threshold
    ransac_iterations: int = 500
    ransac_confidence: float = 0.99
    # RANSAC stops looking for a consensus smaller than this share of the rows: a hypothesis must fit half
    # its rows within `max_median_reproj_px` anyway. It caps the iterations at those that find such a
    # consensus with `ransac_confidence` (146 for 5-point samples). The calibration vehicle's tracks
    # (consensus 0.5 to 1 on every preset) stop far earlier anyway; other vehicles' tracks with no consensus
    # ran all 500: 12-17 % of the stage on dense-traffic and long. 0.45 (248 iterations) gave the same
    # verdicts and errors on all 600 runs of bench.accuracy --seeds 10, both worlds (session 8).
    min_consensus_share: float = 0.5
    # Median over ALL rows, so it also rejects a consensus smaller than half the track. The box centre is
    # not the projection of the body centre (a few px to tens of px for near vehicles), hence not 1-2 px.
    max_median_reproj_px: float = 20.0
    # d_thr (paper: 10 m real to 30 m synthetic): horizontal distance from the camera to the nearest point
    # of the driven path. 40 m, not 30: the paper's own SIL-South camera stands ~30 m from any road, and a
    # single track's pose scatters by a metre or two, so 30 m drops true hypotheses there (it did on our
    # sil-south preset). Wrong hypotheses land 50 m to kilometres away, or by a far part of the route,
    # where this test cannot catch them anyway (grouping does).
    max_camera_distance_m: float = 40.0
    min_camera_height_m: float = 0.0  # paper: "below ground"; the 2 m mast gate is validation's job
    # Not in the paper: a straight track leaves the rotation about it unfixed and EPnP then returns an
    # arbitrary pose. We reject when the 1-sigma rotation uncertainty (at the fit's own pixel scatter)
    # exceeds this.
    max_rotation_std_deg: float = 5.0
    # Above this 1-sigma (deg) a free pose is only weakly fixed (a nearly straight track): the straight-
    # track fit below is tried too and the one whose vehicle cuboid fits the boxes better is kept.
    min_shape_check_std_deg: float = 1.5
    refine_on_inliers: bool = True  # LM / SQPnP refit on the RANSAC inliers, keep the best (see _solve)
    # Not in the paper: resolve a straight-line track (pose free about the line, EPnP cannot fix it) from
    # the boxes' shape and the assumption that the camera is mounted square (`pipeline.straight_track`,
    # whose settings and assumptions are `straight_track`). Curved tracks never use any of this: EPnP
    # fixes them, whatever the roll (see `max_rotation_std_deg`, `min_shape_check_std_deg`).
    level_camera_prior: bool = True
    straight_track: StraightTrackParams = field(default_factory=StraightTrackParams)


@dataclass(frozen=True, slots=True)
class Hypothesis:
    """Camera pose from one track: X_cam = R_cam_from_local @ X_local + t_cam_from_local (m).

    inliers (N,) selects the MatchedTrack rows within `reproj_threshold_px` of the final pose;
    median_reproj_px is over all rows; rotation_std_deg the 1-sigma rotation uncertainty of the fit;
    solver names the candidate that won (epnp, epnp+lm, sqpnp, sqpnp+lm; for a straight track, see
    `pipeline.straight_track.StraightTrackFit`: level for an upright image, level+90 / level-90 for one turned
    into portrait, level+180 upside down (if declared), box-roll for a roll measured from the box shape).
    """

    track_id: int
    R_cam_from_local: Rotation
    t_cam_from_local: Vec3
    inliers: Mask
    median_reproj_px: float
    rotation_std_deg: float = 0.0
    solver: str = "epnp"

    @property
    def camera_centre(self) -> Vec3:
        """Camera position in the local frame (m): -R^T t (paper III-D)."""
        return camera_centre(self.R_cam_from_local, self.t_cam_from_local)


@dataclass(frozen=True, slots=True)
class HypothesisSet:
    hypotheses: tuple[Hypothesis, ...]
    rejected: Mapping[int, Reason]  # track_id -> reason; nothing disappears silently


@dataclass(frozen=True, slots=True)
class _Pose:
    rvec: FloatArray
    tvec: FloatArray
    solver: str


def create_hypotheses(
    tracks: Sequence[MatchedTrack],
    camera: CameraModel,
    vehicle: VehicleProfile,
    ground: GroundPlaneFit,
    params: HypothesisParams,
    rng: np.random.Generator,
    *,
    trajectory: Trajectory | None = None,
    map_fn: MapFn = map,
    kept: Mapping[int, Hypothesis | Reason] | None = None,
) -> HypothesisSet:
    """One EPnP + RANSAC camera pose per matched track, filtered as in paper III-D.

    Correspondences: box centre (px, distorted image) <-> body-box centre of the vehicle (local frame, m,
    `vehicle.body_centres`); lens distortion is honoured (OpenCV undistorts inside solvePnP*).
    `trajectory` is the whole driven path for the d_thr test; without it the tracks' own poses stand in
    (shorter, so stricter). `ground` gives the camera height. Randomness: one OpenCV RNG seed per track
    drawn from `rng`, so results depend on `rng` alone. Returns hypotheses in track order and a reason for
    every rejected track. Tracks are independent: `map_fn` (e.g. a process pool's map, supplied by the
    caller; the pipeline starts no workers itself) may fit them in parallel with identical results.
    `kept`: track id -> an outcome known already (a rerun's, see pipeline.calibrate), taken instead of a fit;
    every track's seed is drawn all the same, so the others' fits do not depend on which are kept.
    """
    path = _driven_path(_path_xy(tracks, trajectory))
    hypotheses: list[Hypothesis] = []
    rejected: dict[int, Reason] = {}
    # Seeds are drawn in track order up front, so each track's seed does not depend on others' outcome.
    seeds = [int(rng.integers(0, 2**31 - 1)) for _ in tracks]
    kept = kept or {}
    fitted = [(track, seed) for track, seed in zip(tracks, seeds, strict=True) if track.track_id not in kept]
    fit = _TrackFit(camera, vehicle, ground, path, params)
    fits = iter(map_fn(fit, [t for t, _ in fitted], [seed for _, seed in fitted]) if fitted else ())
    for track in tracks:
        outcome = kept[track.track_id] if track.track_id in kept else next(fits)
        if isinstance(outcome, Reason):
            rejected[track.track_id] = outcome
        else:
            hypotheses.append(outcome)
    return HypothesisSet(hypotheses=tuple(hypotheses), rejected=rejected)


# shows_vehicle's reach beyond its box diagonals: a far vehicle's box is a few px, its pose's error is not.
_SHOWS_SLACK_PX = 100.0


def shows_vehicle(
    track: MatchedTrack,
    R_cam_from_local: Rotation,
    t_cam_from_local: Vec3,
    camera: CameraModel,
    vehicle: VehicleProfile,
    reach: float,
) -> bool:
    """Whether a camera pose shows the calibration vehicle near the track's boxes on any row: its body
    centre (at the row's pose, local frame m) projected in front of the camera within `reach` box
    diagonals + _SHOWS_SLACK_PX of the box centre (px). A track it shows on no row is not the calibration
    vehicle's, unless the pose is off by more than that: an early rejection once a pose is known."""
    pixels, depth = project_points(
        body_centres(track.poses, vehicle), R_cam_from_local, t_cam_from_local, camera
    )
    boxes = track.boxes
    centres = 0.5 * (boxes[:, :2] + boxes[:, 2:])
    diagonals = np.hypot(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
    miss = np.hypot(pixels[:, 0] - centres[:, 0], pixels[:, 1] - centres[:, 1])
    return bool(np.any((depth > 0.0) & (miss <= reach * diagonals + _SHOWS_SLACK_PX)))


def _path_xy(tracks: Sequence[MatchedTrack], trajectory: Trajectory | None) -> FloatArray:
    """Horizontal driven path (K, 2) m: the trajectory's positions, else every track's poses."""
    if trajectory is not None and len(trajectory.poses) > 0:
        return np.asarray(trajectory.poses[:, :2], dtype=np.float64)
    if not tracks:
        return np.zeros((0, 2))
    return np.concatenate([track.poses[:, :2] for track in tracks], axis=0)


@dataclass(frozen=True, slots=True)
class _DrivenPath:
    """The horizontal driven path as segments, prepared once for every track's d_thr test: start (K, 2) m,
    step (K, 2) m to the segment's end, inverse squared length (K,) 1/m^2 (0 for a point)."""

    start: FloatArray
    step: FloatArray
    inv_length2: FloatArray


# Vertices of the driven path kept at about this spacing (m, along the path): the trajectory has one per
# pose (50 Hz: ~0.3 m apart, 45 000 in 15 min) and a chord of 2 m departs from a path curving no tighter
# than 5 m radius by 0.1 m, nothing against d_thr; sparser poses (1 Hz: ~15 m apart) are all kept.
_PATH_SPACING_M = 1.0


def _driven_path(path_xy: FloatArray) -> _DrivenPath:
    """Segments of the polyline through `path_xy` (K, 2) m, thinned to about `_PATH_SPACING_M`."""
    if len(path_xy) > 2:
        arc_m = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path_xy, axis=0), axis=1))])
        bins = np.floor(arc_m / _PATH_SPACING_M)
        keep = np.concatenate([[True], bins[1:] != bins[:-1]])
        keep[-1] = True
        path_xy = path_xy[keep]
    if len(path_xy) == 1:
        path_xy = np.concatenate([path_xy, path_xy])  # one point: a zero-length segment
    start, step = path_xy[:-1], np.diff(path_xy, axis=0)
    length2 = np.einsum("ij,ij->i", step, step)
    inv_length2 = np.divide(1.0, length2, out=np.zeros_like(length2), where=length2 > 0.0)
    return _DrivenPath(start, step, inv_length2)


def _distance_to_path(point_xy: FloatArray, path: _DrivenPath) -> float:
    """Horizontal distance (m) from a point (2,) to the driven path (inf without one).

    Segments, not just vertices: at a 1 Hz pose rate vertices lie ~15 m apart, half of d_thr.
    """
    if len(path.start) == 0:
        return math.inf
    offset = point_xy - path.start
    along = np.clip(np.einsum("ij,ij->i", offset, path.step) * path.inv_length2, 0.0, 1.0)
    miss = offset - along[:, None] * path.step
    return float(np.sqrt(np.min(np.einsum("ij,ij->i", miss, miss))))


def _extent(points: FloatArray) -> float:
    """Diagonal of the axis-aligned bounding box of points (N, D)."""
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def _line_residual(points: Points3) -> float:
    """RMS distance (m) of points (N, 3) from their best-fit 3D line."""
    centred = points - points.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    return float(np.sqrt(np.sum(singular[1:] ** 2) / len(points)))


def _reprojection_errors(
    points_local: Points3, pixels: Pixels, rvec: FloatArray, tvec: FloatArray, camera: CameraModel
) -> FloatArray:
    """Pixel distance (N,) between observed and projected points; inf for points behind the camera."""
    projected, _ = project_points(points_local, rotation_from_rvec(rvec), tvec.reshape(3), camera)
    errors = np.linalg.norm(projected - pixels, axis=1)
    return np.where(np.isfinite(errors), errors, np.inf)


@dataclass(frozen=True, slots=True)
class _TrackFit:
    """_hypothesis_for with the shared arguments bound (module level, so a process pool can pickle it)."""

    camera: CameraModel
    vehicle: VehicleProfile
    ground: GroundPlaneFit
    path: _DrivenPath
    params: HypothesisParams

    def __call__(self, track: MatchedTrack, seed: int) -> Hypothesis | Reason:
        return _hypothesis_for(track, self.camera, self.vehicle, self.ground, self.path, self.params, seed)


def _hypothesis_for(
    track: MatchedTrack,
    camera: CameraModel,
    vehicle: VehicleProfile,
    ground: GroundPlaneFit,
    path: _DrivenPath,
    params: HypothesisParams,
    seed: int,
) -> Hypothesis | Reason:
    """The hypothesis of one track, or the reason it is rejected."""
    count = len(track.stamps)
    if count < params.min_correspondences:
        return Reason(
            "too_few_correspondences",
            "too few correspondences: {value} < {limit}",
            "correspondences",
            count,
            params.min_correspondences,
            value_format="d",
        )
    pixels = track.box_centres
    points = body_centres(track.poses, vehicle)
    if not (np.all(np.isfinite(pixels)) and np.all(np.isfinite(points))):
        return Reason("non_finite", "degenerate: non-finite boxes or poses")
    image_extent = _extent(pixels)
    if image_extent < params.min_image_extent_px:
        return Reason(
            "not_moving_in_image",
            "not moving in the image: box centres span {value} px < {limit} px",
            "box centre extent",
            image_extent,
            params.min_image_extent_px,
            "px",
        )
    track_extent = _extent(points[:, :2])
    if track_extent < params.min_track_extent_m:
        return Reason(
            "vehicle_not_moving",
            "vehicle not moving: track spans {value} m < {limit} m",
            "track extent",
            track_extent,
            params.min_track_extent_m,
            "m",
            ".2f",
        )

    shape = TrackShape(track.boxes, track.poses, vehicle)
    fit = _fit_track(points, pixels, shape, camera, ground, params, seed, track_extent)
    if isinstance(fit, Reason):
        return fit
    solved, errors, median_px, rotation_std_deg = fit
    inliers = errors <= params.reproj_threshold_px
    R = rotation_from_rvec(solved.rvec)
    t = solved.tvec.reshape(3).copy()
    centre = camera_centre(R, t)
    misplaced = placement_reason(centre, path, ground, params)
    if misplaced is not None:
        return misplaced
    return Hypothesis(
        track_id=track.track_id,
        R_cam_from_local=R,
        t_cam_from_local=t,
        inliers=inliers,
        median_reproj_px=median_px,
        rotation_std_deg=rotation_std_deg,
        solver=solved.solver,
    )


def placement_reason(
    centre: Vec3, path: _DrivenPath, ground: GroundPlaneFit, params: HypothesisParams
) -> Reason | None:
    """Why a camera at `centre` (local m) cannot be this one (paper III-D: d_thr from the driven path, not
    below the road), or None."""
    distance_m = _distance_to_path(centre[:2], path)
    if not distance_m <= params.max_camera_distance_m:
        return Reason(
            "far_from_path",
            "camera {value} m from the driven path > {limit} m",
            "camera distance from the driven path",
            distance_m,
            params.max_camera_distance_m,
            "m",
        )
    height_m = float(ground.height_of(centre[None, :])[0])
    if height_m < params.min_camera_height_m:
        return Reason(
            "below_road",
            "camera {value} m above ground < {limit} m (below the road)",
            "camera height above ground",
            height_m,
            params.min_camera_height_m,
            "m",
        )
    return None


def _fit_track(
    points: Points3,
    pixels: Pixels,
    shape: TrackShape,
    camera: CameraModel,
    ground: GroundPlaneFit,
    params: HypothesisParams,
    seed: int,
    track_extent_m: float,
) -> tuple[_Pose, FloatArray, float, float] | Reason:
    """Pose, per-row reprojection errors (px), their median and the rotation 1-sigma (deg); or a reason.

    The paper's unconstrained EPnP + RANSAC first; when the track leaves the pose unfixed (a straight
    line) or the solvers fail on it, the straight-track fit (`_checked_level`) instead (if enabled), and
    when it fixes the pose only weakly, whichever of the two reproduces the boxes' shape better.
    """
    line_residual_m = _line_residual(points)
    degenerate: Reason
    if line_residual_m <= 1e-3 * track_extent_m:
        # Exactly collinear: OpenCV may raise, loop or return any member of the family of poses about
        # the line, so the unconstrained solvers are not even tried.
        degenerate = Reason(
            "straight_line",
            "degenerate: straight-line track (within {value} m of a line)",
            "distance from a line",
            line_residual_m,
            unit="m",
            value_format=".3f",
        )
        bases: list[_Pose] = []
    else:
        solved = _solve(points, pixels, camera, params, seed)
        if isinstance(solved, _Pose):
            errors = _reprojection_errors(points, pixels, solved.rvec, solved.tvec, camera)
            median_px = float(np.median(errors))
            if not median_px <= params.max_median_reproj_px:
                return _reprojection_reason(median_px, params)
            inliers = errors <= params.reproj_threshold_px
            rotation_std_deg = _rotation_std_deg(points[inliers], pixels[inliers], solved, camera)
            if rotation_std_deg <= params.max_rotation_std_deg:
                free = (solved, errors, median_px, rotation_std_deg)
                if not (params.level_camera_prior and rotation_std_deg > params.min_shape_check_std_deg):
                    return free
                # Fixed, but weakly (a nearly straight track): the straight-track fit is the alternative,
                # and the box shape, which neither fit used, decides.
                level = _checked_level(points, pixels, shape, camera, ground, [solved], params, seed)
                if isinstance(level, str) or _box_misfit(solved, shape, camera) <= _box_misfit(
                    level[0], shape, camera
                ):
                    return free
                return level
            degenerate = Reason(
                "rotation_not_fixed",
                "degenerate: rotation not fixed by the track (1-sigma {value} deg > {limit} deg; "
                "straight-line track?)",
                "rotation 1-sigma",
                rotation_std_deg,
                params.max_rotation_std_deg,
                "deg",
            )
            bases = [solved]
        else:
            degenerate, bases = solved, []
    if not params.level_camera_prior:
        return degenerate
    level = _checked_level(points, pixels, shape, camera, ground, bases, params, seed)
    if isinstance(level, str):
        return degenerate.with_detail(f"; straight-track fit: {level}")
    return level


def _checked_level(
    points: Points3,
    pixels: Pixels,
    shape: TrackShape,
    camera: CameraModel,
    ground: GroundPlaneFit,
    bases: list[_Pose],
    params: HypothesisParams,
    seed: int,
) -> tuple[_Pose, FloatArray, float, float] | str:
    """The straight-track solver's pose (`pipeline.straight_track.solve_straight_track`) with the tests of
    a free pose: pose, per-row reprojection errors (px), their median and the 1-sigma (deg) of its worst
    fitted angle; or the reason there is none.

    Starts: `bases`, poses of the line's family from the general solvers, else EPnP + RANSAC on the points
    nudged off their line; a track whose starts miss the box centres by far is another vehicle's and is
    rejected before any search.
    """
    up = ground.normal
    candidates = list(bases)
    origin, direction = track_line(points)
    if not candidates:
        # The solvers fail on exactly collinear points; a zig-zag of 0.1 % of the track's length across
        # the line lets EPnP + RANSAC (robust to bad boxes) return a pose near the family, which is all a
        # start needs: the fit uses the true points.
        across = np.cross(up, direction)
        across /= max(float(np.linalg.norm(across)), 1e-12)
        zigzag = np.where(np.arange(len(points)) % 2 == 0, 1.0, -1.0)[:, None] * across
        lever = 1e-3 * float(np.ptp(points @ direction))
        near_family = _solve(points + lever * zigzag, pixels, camera, params, seed)
        if isinstance(near_family, _Pose):
            candidates.append(near_family)
    if not candidates:
        return "no pose of the line's family to start from"
    # Cheap exit before any search: every member of the family projects the centres as its base does,
    # so a base whose median error is far above the limit belongs to another vehicle's boxes (most
    # tracks reaching here in dense traffic), and no roll would rescue it.
    base_medians = [
        float(np.median(_reprojection_errors(points, pixels, base.rvec, base.tvec, camera)))
        for base in candidates
    ]
    if min(base_medians) > 2.0 * params.max_median_reproj_px:
        return f"start misses by a median {min(base_medians):.1f} px"
    rotations = [rotation_from_rvec(base.rvec) for base in candidates]
    starts = [(R, camera_centre(R, base.tvec)) for R, base in zip(rotations, candidates, strict=True)]
    fit = solve_straight_track(
        points,
        (origin, direction),
        shape,
        camera,
        ground,
        starts,
        params.straight_track,
        params.min_camera_height_m,
    )
    if isinstance(fit, str):
        return fit
    level = _Pose(rvec_from_rotation(fit.R), -fit.R @ fit.C, fit.solver)
    errors = _reprojection_errors(points, pixels, level.rvec, level.tvec, camera)
    median_px = float(np.median(errors))
    if not median_px <= params.max_median_reproj_px:
        return _reprojection_reason(median_px, params).render()
    if not fit.rotation_std_deg <= params.max_rotation_std_deg:
        return f"1-sigma {fit.rotation_std_deg:.1f} deg"
    return level, errors, median_px, fit.rotation_std_deg


def _box_misfit(pose: _Pose, shape: TrackShape, camera: CameraModel) -> float:
    """How badly the pose reproduces the track's boxes (`pipeline.straight_track.pose_box_misfit`)."""
    R = rotation_from_rvec(pose.rvec)
    return pose_box_misfit(R, camera_centre(R, pose.tvec), shape, camera)


def _solve(
    points: Points3, pixels: Pixels, camera: CameraModel, params: HypothesisParams, seed: int
) -> _Pose | Reason:
    """EPnP + RANSAC (paper III-D), then the best of several refits on the inliers; or a reason.

    EPnP is unstable on the (near-)coplanar, near-collinear points a vehicle on a flat road gives: on
    exact planar data it returned poses 140 deg off in our tests while SQPnP and LM were exact. RANSAC's
    5-point EPnP samples fare better, so RANSAC stays EPnP as in the paper, but on its inliers we also run
    Levenberg-Marquardt from the RANSAC pose, SQPnP, and LM from SQPnP, and keep whichever has the lowest
    RMS reprojection error on those inliers (the RANSAC pose itself is a candidate, so this never worsens
    the fit).
    """
    # OpenCV's RANSAC draws from its global cv::theRNG(); seeding it here makes the result a function of
    # `rng` only (and independent of what other code ran before in this thread).
    cv2.setRNGSeed(seed)
    try:
        found, rvec, tvec, inlier_index = cv2.solvePnPRansac(
            points,
            pixels,
            camera.K,
            camera.dist,
            iterationsCount=_ransac_iterations(params),
            reprojectionError=params.reproj_threshold_px,
            confidence=params.ransac_confidence,
            flags=cv2.SOLVEPNP_EPNP,
        )
    except cv2.error as err:
        return Reason("epnp_failed", "degenerate: EPnP + RANSAC failed", detail=f" ({_cv2_message(err)})")
    if not found or inlier_index is None or len(inlier_index) < 4:
        return Reason(
            "no_consensus", "no camera pose fits: RANSAC found no consensus of 4 or more correspondences"
        )
    candidates: list[_Pose] = []
    if not _append_finite(candidates, rvec, tvec, "epnp"):
        return Reason("epnp_non_finite", "degenerate: EPnP returned a non-finite pose")
    selected = np.asarray(inlier_index, dtype=np.int64).reshape(-1)
    if params.refine_on_inliers:
        candidates.extend(_refits(points[selected], pixels[selected], candidates[0], camera))
    rms = [_rms(points[selected], pixels[selected], pose, camera) for pose in candidates]
    best = int(np.argmin(rms))
    if not math.isfinite(rms[best]):
        return Reason("behind_camera", "degenerate: no candidate pose has the inliers in front of the camera")
    return candidates[best]


def _ransac_iterations(params: HypothesisParams) -> int:
    """RANSAC's iteration budget: enough to draw one all-inlier 5-point sample with `ransac_confidence`
    when a `min_consensus_share` of the rows are inliers, at most `ransac_iterations`."""
    all_inlier = min(max(params.min_consensus_share, 0.0), 1.0) ** _RANSAC_SAMPLE
    if not (0.0 < all_inlier < 1.0 and 0.0 < params.ransac_confidence < 1.0):
        return params.ransac_iterations
    needed = math.ceil(math.log(1.0 - params.ransac_confidence) / math.log(1.0 - all_inlier))
    return max(1, min(params.ransac_iterations, needed))


_RANSAC_SAMPLE = 5  # points per minimal sample of OpenCV's EPnP RANSAC


def _refits(points: Points3, pixels: Pixels, start: _Pose, camera: CameraModel) -> list[_Pose]:
    """LM from the RANSAC pose, SQPnP, and LM from SQPnP, each on the inliers; failures are skipped
    (an ill-posed straight-line track makes cv2 raise or return NaN)."""
    refits: list[_Pose] = []

    def refine_lm(pose: _Pose) -> None:
        refined = lm_refine(points, pixels, pose.rvec, pose.tvec, camera)
        if refined is not None:
            _append_finite(refits, refined[0], refined[1], pose.solver + "+lm")

    refine_lm(start)
    try:
        found, rvec, tvec = cv2.solvePnP(points, pixels, camera.K, camera.dist, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        found = False
    if found and _append_finite(refits, rvec, tvec, "sqpnp"):
        refine_lm(refits[-1])
    return refits


def lm_refine(
    points: Points3, pixels: Pixels, rvec: FloatArray, tvec: FloatArray, camera: CameraModel
) -> tuple[FloatArray, FloatArray] | None:
    """Levenberg-Marquardt on the reprojection error of points (N, 3) <-> pixels (N, 2) from (rvec, tvec);
    None when OpenCV fails or returns a non-finite pose."""
    try:
        # (3, 1) in and out: given (3,) arrays, cv2 refines a temporary copy and returns the start.
        found = cv2.solvePnPRefineLM(
            points,
            pixels,
            camera.K,
            camera.dist,
            np.asarray(rvec, dtype=np.float64).reshape(3, 1).copy(),
            np.asarray(tvec, dtype=np.float64).reshape(3, 1).copy(),
            _LM_CRITERIA,
        )
    except cv2.error:
        return None
    rvec_out = np.asarray(found[0], dtype=np.float64).reshape(3)
    tvec_out = np.asarray(found[1], dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(rvec_out)) and np.all(np.isfinite(tvec_out))):
        return None
    return rvec_out, tvec_out


def _append_finite(poses: list[_Pose], rvec: object, tvec: object, solver: str) -> bool:
    """Append the pose if finite; report whether it was."""
    rvec_array = np.asarray(rvec, dtype=np.float64).reshape(3)
    tvec_array = np.asarray(tvec, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(rvec_array)) and np.all(np.isfinite(tvec_array))):
        return False
    poses.append(_Pose(rvec_array, tvec_array, solver))
    return True


def _rms(points: Points3, pixels: Pixels, pose: _Pose, camera: CameraModel) -> float:
    errors = _reprojection_errors(points, pixels, pose.rvec, pose.tvec, camera)
    return float(np.sqrt(np.mean(errors**2)))


def _rotation_std_deg(points: Points3, pixels: Pixels, pose: _Pose, camera: CameraModel) -> float:
    """1-sigma rotation uncertainty (deg, largest axis) of a pose fitted to points (N, 3) <-> pixels (N, 2).

    Gauss-Newton covariance sigma^2 (J^T J)^-1 over (rvec, tvec), marginalised to rvec; sigma is the
    fit's RMS residual but at least 1 px (noise-free data still has pixel-quantised boxes in practice).
    A straight-line track makes J^T J singular along "rotate about the line": inf.
    """
    if len(points) < 4:
        return math.inf
    try:
        _, jacobian = cv2.projectPoints(points, pose.rvec, pose.tvec, camera.K, camera.dist)
    except cv2.error:
        return math.inf
    J = np.asarray(jacobian, dtype=np.float64)[:, :6]
    if not np.all(np.isfinite(J)):
        return math.inf
    sigma_px = max(1.0, _rms(points, pixels, pose, camera))
    normal = J.T @ J
    # Relative conditioning guard: an exactly singular normal matrix may still invert to finite noise.
    singular = np.linalg.svd(normal, compute_uv=False)
    if singular[-1] <= singular[0] * 1e-12:
        return math.inf
    covariance = sigma_px**2 * np.linalg.inv(normal)
    largest = float(np.max(np.linalg.eigvalsh(covariance[:3, :3])))
    return math.degrees(math.sqrt(max(largest, 0.0)))


def _cv2_message(err: cv2.error) -> str:
    """The first line of an OpenCV error, without its source path."""
    text = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
    return text[-200:]


def _reprojection_reason(median_px: float, params: HypothesisParams) -> Reason:
    return Reason(
        "reprojection_error",
        "median reprojection error {value} px > {limit} px",
        "median reprojection error",
        median_px,
        params.max_median_reproj_px,
        "px",
    )
