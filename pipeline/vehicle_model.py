"""The final fit: camera pose, time offset, vehicle shape and detector bias from the boxes (beyond the paper).

The whole-box refinement (`refinement.refine_whole_box`) models a detector box as the tight box of the
vehicle's L x W x H cuboid, on the clock the caller assumed. Real detectors do not draw that box: a car's
silhouette is smaller than its cuboid (rounded corners, a cabin narrower and shorter than the body, ground
clearance under the bumpers), detectors have their own annotation convention (boxes a few per cent tight or
loose, edges a few pixels in or out) and stamp a frame some unknown 40-200 ms after its exposure. Fitting the
cuboid on such boxes moved simulated cameras 0.58-0.84 m even with the right tracks and the latency known, and
an unknown 180 ms latency alone moved them 3 m (tools: bench.accuracy, the realistic world).

So the pose is fitted jointly with the unknowns it would otherwise absorb, each with a weak prior:
- time shift `delta` (s): the box stamped t shows the vehicle at trajectory time t - delta; observable
  because the vehicle moves at varying speed and direction across the drive-pasts;
- the body as a template of 12 points in the vehicle box frame (docs/method.md): the body's lower rectangle
  (full L x W) at a height `z_low`, the wheels' contact rectangle on the road (in from the ends by an
  overhang, from the sides by an inset) and a roof rectangle at the profile's height H spanning
  [x_back, x_front] along the body, inset from each side. The profile's L, W, H stay the vehicle's
  data-sheet extents; the template only says which part of that box the silhouette fills. It starts as,
  and its prior is centred on, the cuboid;
- the detector's convention: a scale of every box about its centre, a shift and a growth in x and y (px),
  the same for all boxes of the camera. A shift of every box looks like a turn of the camera: its prior
  (2 px) is what bounds it, and it enters the rotation's std.
Box size changes tenfold along a drive-past, so metric shape and pixel convention separate; what the data
cannot separate from the pose shows up in the pose's marginal covariance, the block of the full inverse with
the nuisance parameters included (their priors keep it finite). Whether the template, the convention and
the time shift are needed at all is decided in final_fit.final_fit (cross-validation, significance).

Uncertainty: detector errors are correlated over consecutive frames (a box edge stays a few pixels off for
a second) and GNSS errors drift, so independent-residual least squares overstates the information many times.
Each residual is weighted by its own std (detector noise plus a per-edge share of the box height the template
misses) times the variance inflation of the residuals' frame-to-frame correlation; the covariance is the
cluster-robust sandwich A^-1 B A^-1 (clusters: one track, `cluster_s` of time), never below A^-1, plus the
common GNSS offset; check_traversals then raises it to the scatter of the traversals left out in turn.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field, replace
from statistics import NormalDist

import numpy as np
from scipy.optimize import least_squares, nnls

from pipeline.arrays import BoolArray, Boxes, FloatArray, IntArray, Rotation, Stamps, Vec3
from pipeline.association import MatchedTrack, Trajectory, select_rows
from pipeline.camera import CameraModel, camera_centre, pose_difference, rotation_from_ypr
from pipeline.errors import DegenerateGeometry
from pipeline.mapping import MapFn
from pipeline.refinement import (
    _camera_points,
    _camera_points_jacobian,
    _clipped_edges,
    _pose_from_params,
    _project,
    _project_jacobian,
    _robust_weights,
)
from pipeline.vehicle import body_points_to_world, rotated_body_points
from schemas.common import VehicleProfile

_POSE, _DELTA, _SHAPE, _BIAS, _READOUT = slice(0, 6), 6, slice(7, 14), slice(14, 19), 19
N_PARAMS = 20
TIME_SHIFT = _DELTA  # the time shift's column in a parameter vector (consider_moves)
POSE_COLUMNS = _POSE  # the pose's columns [w, C] in a parameter vector
READOUT = _READOUT  # the readout's column
_HELD = 1e-6  # prior std of a parameter held at its start
HELD_STD = _HELD  # a prior std at or below this holds its parameter
# Tracks more than this apart in time (s) are separate drive-pasts for the leave-one-out check.
TRAVERSAL_GAP_S = 5.0
SHAPE_NAMES = (
    "z_low_m",
    "wheel_overhang_m",
    "wheel_inset_m",
    "roof_x_front_m",
    "roof_x_back_m",
    "roof_inset_m",
    "roof_raise_m",
)
ROOF_RAISE_INDEX = SHAPE_NAMES.index("roof_raise_m")  # the roof's raise among the shape parameters
ROOF_RAISE = _SHAPE.start + ROOF_RAISE_INDEX  # its column in a parameter vector
BIAS_NAMES = ("scale", "shift_x_px", "shift_y_px", "grow_x_px", "grow_y_px")
# Edge offsets of the detector convention from (shift_x, shift_y, grow_x, grow_y), per edge x1, y1, x2, y2.
_OFFSET_FROM_BIAS = np.array(
    [[1.0, 0.0, -0.5, 0.0], [0.0, 1.0, 0.0, -0.5], [1.0, 0.0, 0.5, 0.0], [0.0, 1.0, 0.0, 0.5]]
)


@dataclass(frozen=True, slots=True)
class ModelParams:
    """Priors and solver settings of the joint fit. Stds are of the prior around the start (cuboid, no bias,
    the caller's time offset); pixel quantities in distorted image pixels."""

    loss: str = "huber"
    f_scale_px: float = 2.0
    max_evaluations: int = 100  # per pass (the weights of the second come from the first's residuals)
    time_shift_std_s: float = 0.5  # a configured or last estimated offset is a prior, not a requirement
    # A rolling shutter exposes the image's rows one after another: a box on row v shows the trajectory
    # (v / height - 1/2) x readout later than one on the middle row (whose time the time shift is). CMOS
    # roadside cameras read a frame in 10-35 ms, global-shutter ones at once; negative when the sensor is
    # read bottom-up (a flipped image).
    readout_std_s: float = 0.02
    readout_s: float = 0.0  # the prior's mean
    # A fitted readout within max(3 std, this) of 0 is held at 0 (a global shutter): left free it absorbs
    # what else varies with the image row (the first simulator's drifting IMU poses: -2.5 +- 0.8 ms).
    min_readout_s: float = 0.005
    # Template: clearance and shoulder heights (m), roof span ends (m along the body), roof inset (m) and
    # the roof's raise above the data sheet's height (m). The data sheet's H excludes what a calibration
    # vehicle may carry on its roof (a roof box or rack: 0.1-0.55 m; a survey vehicle's sensor rack), and a
    # box top the model puts at H that the detector draws higher moves a low camera down by the difference:
    # the raise is held (at the data sheet's roof) in every fit, and final_fit.with_roof_raise fits it
    # again with this prior, keeping it where the boxes show one.
    # The template's prior stds about the cuboid (SHAPE_NAMES; with typical_body only the held entries count).
    shape_std: tuple[float, ...] = (0.3, 0.8, 0.2, 1.2, 1.2, 0.4, _HELD)
    # Where the template's prior is centred: on a road vehicle's usual proportions for the profile's L, W, H
    # (typical_shape), with their spread as its std, or (False) on the cuboid with `shape_std`. A prior
    # centred on the cuboid leaves the template's heights free to trade with the camera's: the lower
    # rectangle rises, the camera with it (docs/method.md, "What limits it"). Entries of shape_std at or
    # below HELD_STD stay held either way (the roof's raise; cuboid_params).
    typical_body: bool = True
    roof_raise_std_m: float = 0.6
    # A fitted raise within max(3 std, this) of 0 stays held at 0, and its std enters the pose's uncertainty
    # as a consider parameter: a roof the data barely fix is a camera height they barely fix (0.05 m: a
    # roof's rails and antenna, within the template's own point std).
    min_roof_raise_m: float = 0.05
    scale_std: float = 0.1  # detector box scale about its centre
    # The detector's convention: boxes shifted as a whole (px) and grown or shrunk by a constant (px). A shift
    # of every box by d px looks almost exactly like the camera turned by d / f rad: the data tell them apart
    # only by second-order effects (perspective, distortion), and the template's misfit of a real body
    # drives those. Fitted, the shift ran to 6-15 px on the exact boxes of simulated bodies and turned the
    # camera 0.3-1 deg with it (true poses and clock; held at 0: 0.01-0.03 deg). So by default the shift is
    # held at 0 and its std is what the rotation can be known to: consider covariance
    # (consider_moves), not a fitted parameter. Detectors are trained on boxes drawn symmetric about
    # the object: 2 px.
    shift_std_px: float = 2.0
    fit_shift: bool = False
    grow_std_px: float = 8.0
    cluster_s: float = 1.0  # residuals within this much time on one track count as one cluster
    # The vehicle's GNSS error, which no number of boxes averages out (metres, 1 std per axis). Common to
    # every pose: horizontal `pose_bias_std_m`, height `pose_bias_height_std_m`: receivers fix height about
    # twice as loosely as position (vertical dilution of precision; RTK data sheets: Septentrio mosaic-X5
    # 0.6 cm H / 1 cm V, Trimble 8 mm H / 15 mm V), and a camera's height moves with it one to one.
    pose_bias_std_m: float = 0.05
    pose_bias_height_std_m: float = 0.10
    # ... and each drive-past's own (horizontal, height): RTK errors wander over tens of seconds (multipath
    # and troposphere change with the satellites' geometry), so drive-pasts minutes apart sit centimetres
    # apart. Unlike the common offset that turns the camera: a height difference between drive-pasts in
    # different lanes looks like a roll. Propagated as consider parameters (drive_past_gnss_moves): without
    # them, boxes of the cuboid itself from a perfect detector and a GNSS receiver wandering 3 / 6 cm gave
    # rotations 0.17-0.20 deg off with a reported std of 0.03-0.05 deg (docs/method.md, "The GNSS
    # error in the uncertainty"). calibrate() sets it from the vehicle's profile (its gnss_wander_m).
    drive_past_gnss_std_m: tuple[float, float] = (0.0, 0.0)
    min_sigma_px: float = 0.5
    min_depth_m: float = 0.1
    border_margin_px: float = 1.0
    # A left-out traversal disagrees when the others predict its boxes with a mean squared Mahalanobis
    # residual above this (1 expected: prediction uncertainty and noise both counted; see check_traversals).
    holdout_chi2_per_residual: float = 4.0
    # ... or when the boxes of the left-out traversal pull the others' pose further than their uncertainty,
    # the prediction's and the noise allow: a chi-square of 6 degrees of freedom above this (p about 4e-5).
    # The per-residual statistic divides a pose offset, a 6-dimensional signal, by the hundreds of residuals
    # of a drive-past: a drive-past seen from a camera moved 1 m scored 1.0 on it, and 37-11000 on this.
    holdout_pull_chi2: float = 30.0
    # Moves below these never make traversals disagree: the first simulator's drifting IMU poses move it by
    # up to 0.08 m / 0.11 deg between drive-pasts that agree (rolled seed 0, ideal world: chi-square 57),
    # and a move below the std an accepted result may have (0.5 / 3) does not matter.
    min_disagreement_m: float = 0.15
    min_disagreement_deg: float = 0.15
    shape_step: float = 1e-4  # finite-difference step of the shape parameters (m) and the time shift (s)
    # The body the 12-point template cannot describe: how far (m, per axis) each template point may lie from
    # where the real silhouette's extremes are (a car's plan-view corners are rounded with radii of 0.3-0.55
    # m, which a sharp corner misses by 0.4 r at 45 deg; mirrors stand 0.1-0.2 m proud of the body; a
    # bumper's lowest point sits behind its face). Every view of the same body shares that misfit, so no
    # residual statistic sees it (the fit absorbs it into the pose); it is propagated into the pose's
    # covariance as consider parameters (shape_model_covariance). 0 turns it off.
    template_point_std_m: float = 0.1
    # The template and convention must predict the left-out traversals better than the cuboid by more than
    # this (median |edge residual| px per traversal): below it both fit to within the detector's rounding.
    template_floor_px: float = 0.2
    # The boxes show a body other than the cuboid when the template fit departs from it by more than this
    # chi-square (6 dof, the shape parameters but the roof's raise against their own covariance; measured
    # before the raise was a parameter). Measured: 11-33 on the first
    # simulator's cuboid boxes (its drifting IMU poses give more than the 6 expected), 196-1976 on shaped
    # bodies (8 scenes); p = 1e-19 at 100.
    cuboid_rejection_chi2: float = 100.0
    # The vehicle's height per drive-past. GNSS heights wander by several centimetres over minutes (RTK:
    # 2-5 cm 1 sigma, correlated over tens of seconds), so drive-pasts minutes apart sit at heights that
    # differ by about as much; for a camera looking along the road such a difference between drive-pasts in
    # different lanes is the same image change as a roll. With `drive_past_heights` each drive-past (tracks
    # within TRAVERSAL_GAP_S) gets its own height offset, prior 0 +- drive_past_height_std_m, fitted with the
    # pose; final_fit.joint_fit tries them with `try_drive_past_heights` and keeps them only where the boxes
    # ask for them (heights_chi2_p). On by default since session 28, wherever the vehicle's profile says
    # its heights wander (calibrate: VehicleProfile.gnss_wander_m's height above 0): over the realistic
    # world's 300 runs (27 presets, seeds 0-9) 7 accepted instead of 3, no false accept either way, none
    # beyond 3 std, the near poses' rotation error 0.167 -> 0.158 deg in the median (docs/method.md, "What
    # limits it", has the numbers, and what they did to the first simulator's world, whose profile says its
    # heights hold).
    try_drive_past_heights: bool = True
    drive_past_heights: bool = False
    drive_past_height_std_m: float = 0.1
    # The offsets are kept when their chi-square against their own covariance exceeds the (1 - p) quantile
    # of chi-square with one degree of freedom per drive-past, and never with fewer than
    # min_height_drive_pasts (with two, their difference trades with a turn of the camera).
    heights_chi2_p: float = 0.01
    min_height_drive_pasts: int = 3

    def prior_std(self) -> FloatArray:
        return np.array(
            [math.inf] * 6
            + [self.time_shift_std_s]
            + list(self.shape_std)
            + [self.scale_std]
            + [self.shift_std_px if self.fit_shift else _HELD] * 2
            + [self.grow_std_px] * 2
            + [self.readout_std_s]
        )

    def gnss_covariance(self) -> FloatArray:
        """(3, 3) the common GNSS offset's covariance in the local frame (x east, y north, z up)."""
        h, v = self.pose_bias_std_m, self.pose_bias_height_std_m
        return np.diag([h * h, h * h, v * v])

    def height_count(self, drive_pasts: int) -> int:
        """How many height offsets a fit of `drive_pasts` drive-pasts has: one each, or none."""
        return drive_pasts if self.drive_past_heights else 0


@dataclass(frozen=True, slots=True)
class ModelFit:
    """The joint fit. Pose as in `refinement.Refinement` (local frame); covariance (6, 6) of [w, C], the
    marginal block of the full N_PARAMS-parameter sandwich covariance, plus the common GNSS offset's
    (ModelParams.gnss_covariance) on C.

    time_shift_s / time_shift_std_s: delta (the box stamped t shows the trajectory at t - delta, on the
    image's middle row); readout_s / readout_std_s: the rolling shutter's readout time (a box centred on row
    v of an image `height` rows tall shows the trajectory at t - delta + readout_s (v / height - 1/2)).
    shape (7,) SHAPE_NAMES, bias (5,) BIAS_NAMES, with their stds.
    residuals_px (N, 4): model box minus detected box, NaN on clipped edges; box_track_ids, stamps (N,).
    """

    R_cam_from_local: Rotation
    t_cam_from_local: Vec3
    camera_centre: Vec3
    covariance: FloatArray
    position_std_m: float
    rotation_std_deg: float
    time_shift_s: float
    time_shift_std_s: float
    shape: FloatArray
    shape_std: FloatArray
    bias: FloatArray
    bias_std: FloatArray
    residuals_px: FloatArray
    box_rmse_px: float
    sigma_px: float
    used_residuals: int
    clusters: int
    box_track_ids: IntArray
    stamps: Stamps
    converged: bool
    iterations: int
    full_covariance: FloatArray = field(repr=False)
    row_scale_px: FloatArray = field(repr=False)  # (N, 4) each used residual's effective std (NaN unused)
    edge_fraction: FloatArray = field(repr=False)  # (4,) per-edge model misfit as a share of the box height
    rho: float = 0.0  # residual correlation from frame to frame
    readout_s: float = 0.0
    readout_std_s: float = 0.0
    # With ModelParams.drive_past_heights: each drive-past's height offset (K,) m and its std, and the
    # drive-past's first and last box stamp (K, 2) ns (by which _model_of gives other boxes their offset).
    height_offsets_m: FloatArray = field(default_factory=lambda: np.zeros(0), repr=False)
    height_offsets_std_m: FloatArray = field(default_factory=lambda: np.zeros(0), repr=False)
    drive_past_spans_ns: IntArray = field(
        default_factory=lambda: np.zeros((0, 2), dtype=np.int64), repr=False
    )

    def heights_chi2(self) -> float:
        """Chi-square (one dof per drive-past) of the height offsets against their own covariance (the
        marginal block of the full one); 0 without offsets."""
        k = len(self.height_offsets_m)
        if k == 0:
            return 0.0
        block = self.full_covariance[N_PARAMS:, N_PARAMS:]
        offsets = self.height_offsets_m
        return max(float(offsets @ _inverse(block) @ offsets), 0.0)

    def footprint_body_frame(self, vehicle: VehicleProfile) -> FloatArray:
        """The fitted template's contact with the road: the wheels' rectangle (4, 3), vehicle box frame."""
        return template_points(self.shape, vehicle)[4:8]


def template_points(shape: FloatArray, vehicle: VehicleProfile) -> FloatArray:
    """The 12 template points (12, 3) in the vehicle box frame for shape parameters (7,) SHAPE_NAMES: the
    body's lower rectangle (full length and width) at z_low, the wheels' contact rectangle on the road
    (overhang in from each end, inset from each side) and the roof rectangle at the height H plus the
    roof's raise."""
    L, W = vehicle.length, vehicle.width
    z_low, overhang, inset, x_front, x_back, y_in, raise_m = (float(v) for v in shape)
    H = vehicle.height + raise_m
    rect = np.array([[0.0, 0.0], [L, 0.0], [L, W], [0.0, W]])
    wheels = np.array(
        [[overhang, inset], [L - overhang, inset], [L - overhang, W - inset], [overhang, W - inset]]
    )
    roof = np.array([[x_back, y_in], [x_front, y_in], [x_front, W - y_in], [x_back, W - y_in]])
    return np.vstack(
        [
            np.column_stack([rect, np.full(4, z_low)]),
            np.column_stack([wheels, np.zeros(4)]),
            np.column_stack([roof, np.full(4, H)]),
        ]
    )


def cuboid_shape(vehicle: VehicleProfile) -> FloatArray:
    """Shape parameters of the profile's cuboid (the start and prior mean without typical_body)."""
    return np.array([0.0, 0.0, 0.0, vehicle.length, 0.0, 0.0, 0.0])


def typical_shape(vehicle: VehicleProfile) -> tuple[FloatArray, FloatArray]:
    """The template's prior for a road vehicle of the profile's L x W x H (SHAPE_NAMES; mean and std, m):
    what road vehicles' data sheets and photographs show, not any one body. The body reaches its full
    length and width a few decimetres up (bumpers, sills: 0.35 +- 0.15 m); the wheels stand about a fifth
    of the length in from each end and a few centimetres in from the sides; a car's roof, at its full
    height, spans from behind the windscreen's top (about 0.6 of the length from the rear) to above the
    rear window (0.15 of it), inset by the cabin's tumblehome (0.2 m); the taller the body, the boxier (a
    van's or a bus's roof runs nearly end to end, 0.87 / 0.03 of the length, inset 0.1 m), by a share
    rising from 0 at 1.5 m to 1 at 2.0 m of height. The stds are the spread between vehicles of a class:
    a fit from a few drive-pasts moves the shape within it, and further where its boxes ask for it. The
    roof's raise: 0 (what the vehicle carries is fitted by with_roof_raise)."""
    L, H = vehicle.length, vehicle.height
    boxy = min(max((H - 1.5) / 0.5, 0.0), 1.0)
    mean = np.array(
        [0.35, 0.18 * L, 0.08, (0.62 + 0.25 * boxy) * L, (0.15 - 0.12 * boxy) * L, 0.2 - 0.1 * boxy, 0.0]
    )
    std = np.array([0.15, 0.05 * L, 0.05, 0.1 * L, 0.12 * L, 0.1, _HELD])
    return mean, std


def shape_prior(params: ModelParams, vehicle: VehicleProfile) -> tuple[FloatArray, FloatArray]:
    """The template's prior (mean, std) under `params`: typical_shape's, or the cuboid with shape_std;
    entries of shape_std at or below HELD_STD held at the mean either way (the roof's raise with
    typical_body: its shape_std entry, as with_roof_raise frees it)."""
    given = np.asarray(params.shape_std, dtype=np.float64)
    if not params.typical_body:
        return cuboid_shape(vehicle), given
    mean, std = typical_shape(vehicle)
    std = np.where(given <= _HELD, given, std)
    std[ROOF_RAISE_INDEX] = given[ROOF_RAISE_INDEX]
    return mean, std


class PoseSampler:
    """The trajectory as functions of time: poses at float seconds (linear in x, y, z, pitch, roll,
    unwrapped yaw), held at the ends."""

    def __init__(self, trajectory: Trajectory) -> None:
        if len(trajectory.stamps) < 2:
            raise DegenerateGeometry("joint fit: the trajectory has fewer than 2 poses")
        self.t0 = int(trajectory.stamps[0])
        self.times = (trajectory.stamps - self.t0).astype(np.float64) / 1e9
        poses = trajectory.poses.copy()
        poses[:, 3] = np.unwrap(poses[:, 3])
        self.poses = poses

    @staticmethod
    def of(trajectory: Trajectory) -> PoseSampler:
        """The sampler of `trajectory`, reused while the same trajectory object is asked for again (the
        final fit samples one trajectory for hundreds of tracks and fits: unwrapping it each time cost more
        than the fits' sampling)."""
        last = _last_sampler
        if last is not None and last[0] is trajectory:
            return last[1]
        sampler = PoseSampler(trajectory)
        _remember_sampler((trajectory, sampler))
        return sampler

    def seconds(self, stamps: Stamps) -> FloatArray:
        return np.asarray((stamps - self.t0).astype(np.float64) / 1e9, dtype=np.float64)

    def at(self, t_s: FloatArray) -> FloatArray:
        """np.interp of each column, held at the ends (one search for all six: the same arithmetic)."""
        times, poses = self.times, self.poses
        j = np.clip(np.searchsorted(times, t_s, side="right") - 1, 0, len(times) - 2)
        slope = (poses[j + 1] - poses[j]) / (times[j + 1] - times[j])[:, None]
        out = slope * (t_s - times[j])[:, None] + poses[j]
        out[t_s <= times[0]] = poses[0]
        out[t_s >= times[-1]] = poses[-1]
        return np.asarray(out, dtype=np.float64)


# The last trajectory sampled and its sampler (PoseSampler.of); a strong reference, so `is` cannot match
# a new object at a recycled address.
_last_sampler: tuple[Trajectory, PoseSampler] | None = None


def _remember_sampler(entry: tuple[Trajectory, PoseSampler]) -> None:
    global _last_sampler
    _last_sampler = entry


@dataclass(frozen=True, slots=True)
class _Data:
    boxes: Boxes
    t_s: FloatArray
    track_ids: IntArray
    stamps: Stamps
    used: BoolArray  # (N, 4)
    # (N,) the box centre's row / the image height, minus 1/2: when the readout reached it, from the middle
    row_share: FloatArray
    # (N, 4) px per second of readout: how far each edge moves between the exposure of the box centre's row
    # and of the row of the point forming it, from the model's rate of the edge (_Model.set_skew). A rolling
    # shutter's box at readout r shows edge k at boxes[:, k] - r * skew[:, k] had every row been exposed
    # with the centre's.
    skew: FloatArray
    drive_past: IntArray  # (N,) each box's drive-past, an index into drive_past_spans_ns
    drive_past_spans_ns: IntArray  # (K, 2) first and last stamp of each drive-past, in time order

    def corrected(self, readout_s: float) -> Boxes:
        """The boxes as if every row had been exposed with the box centre's (see `skew`)."""
        return self.boxes if readout_s == 0.0 else self.boxes - readout_s * self.skew


# fit_vehicle_model's `patience` for the trials whose freedom is kept only from a converged fit.
TRIAL_PATIENCE = 3


def fit_vehicle_model(
    R_cam_from_local: Rotation,
    t_cam_from_local: Vec3,
    tracks: Sequence[MatchedTrack],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
    patience: int = 1,
) -> ModelFit:
    """Fit pose, time shift, template and detector bias to the tracks' boxes, from the given pose. Where the
    solver stops at its evaluation limit, with `patience` above 1 the fit runs once more from the same start
    with that many times the limit: for the trials whose freedom is kept only from a converged fit (a
    height per drive-past, the roof's raise; TRIAL_PATIENCE), where a trial the limit cut short is no answer
    and losing it silently decided for the held model (unseen scene 15's roof box: the trial with the
    heights free stopped at 100 evaluations on a raise of +0.48 +- 0.04 m, converged in 142 at the same
    raise, and the camera went from 0.25 m off, refused, to 0.05 m off)."""
    if not tracks or sum(len(t.boxes) for t in tracks) == 0:
        raise DegenerateGeometry("joint fit: no boxes")
    R0 = np.asarray(R_cam_from_local, dtype=np.float64)
    C0 = camera_centre(R0, np.asarray(t_cam_from_local, dtype=np.float64))
    model, mean = start_model(R0, C0, tracks, trajectory, camera, vehicle, params)
    data, heights = model.data, model.heights
    needed = 2 * (N_PARAMS + heights)
    if int(data.used.sum()) < needed:
        raise DegenerateGeometry(
            f"joint fit: {int(data.used.sum())} unclipped box edges in front of the camera, need >= {needed}"
        )
    model.set_skew(mean)
    scene_range = _scene_range(model, C0)
    x_scale = np.concatenate(
        [
            [1.0 / scene_range] * 3,
            [1.0] * 3,
            [0.05],
            [0.1] * len(SHAPE_NAMES),
            [0.01],
            [1.0] * 4,
            [0.01],
            [0.05] * heights,
        ]
    )
    # Two passes: the data rows are weighted against the priors and each other by the residuals' effective
    # std (per edge and box size, times the square root of their correlation's variance inflation), which
    # the first pass measures.
    x = mean.copy()
    evaluations, converged = 0, False
    for first in (True, False):
        if first:
            model.data_scale = np.full(model.data_rows, 2.0 * params.f_scale_px)
            model.f_scale = 0.5
        else:
            model.set_skew(x)  # from the first pass's solution: the start's clock may be far off
            model.weigh(x)
        solution = least_squares(
            model.residuals,
            x,
            jac=model.jacobian,
            method="trf",
            loss=params.loss,
            f_scale=model.f_scale,
            x_scale=x_scale,
            max_nfev=params.max_evaluations,
        )
        x = solution.x
        evaluations += int(solution.nfev)
        converged = bool(solution.status > 0)
    if not converged and patience > 1:
        longer = replace(params, max_evaluations=patience * params.max_evaluations)
        return fit_vehicle_model(
            R_cam_from_local, t_cam_from_local, tracks, trajectory, camera, vehicle, longer
        )
    return _assemble(model, x, converged, evaluations, scene_range)


def start_model(
    R0: Rotation,
    C0: Vec3,
    tracks: Sequence[MatchedTrack],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
    shared: Collection[str] = (),
) -> tuple[_Model, FloatArray]:
    """The model `params` describes on the tracks' boxes, around the pose (R0, C0), and its prior mean (the
    parameter vector a fit starts from): the template's prior, the readout's, no height offsets. The parts
    named in `shared` ("shape": the template, "heights": the drive-pasts' height offsets) get no prior rows:
    a caller that fits several cameras together carries those priors once (bench.joint_fit)."""
    sampler = PoseSampler.of(trajectory)
    data = _data_of(tracks, sampler, camera, params)
    heights = params.height_count(len(data.drive_past_spans_ns))
    mean = np.zeros(N_PARAMS + heights)
    mean[_SHAPE] = shape_prior(params, vehicle)[0]
    mean[_READOUT] = params.readout_s
    prior_std = _prior_std(params, heights, vehicle)
    if "shape" in shared:
        prior_std[_SHAPE] = math.inf
    if "heights" in shared:
        prior_std[N_PARAMS:] = math.inf
    model = _Model(data, sampler, R0, C0, camera, vehicle, params, mean, prior_std)
    # A box whose vehicle the start puts partly behind the camera has no tight box in the model: its clamped
    # projection misses by up to 10^5 px with a Jacobian to match, and even a robust loss lets such rows
    # drag the pose off (an identity switch onto another car while the calibration vehicle had driven
    # under and past the camera: an exact scene's fit from the true pose ended 14 m off). Its edges are
    # left out of the fit, as clipped ones are (NaN residuals: fit_trimmed then drops the box).
    behind = model.behind_camera(mean)
    if behind.any():
        data = replace(data, used=data.used & ~behind[:, None])
        model = _Model(data, sampler, R0, C0, camera, vehicle, params, mean, prior_std)
    return model, mean


class _Model:
    """Residuals (data rows, then prior rows) and their Jacobian; the last evaluation is cached."""

    def __init__(
        self,
        data: _Data,
        sampler: PoseSampler,
        R0: Rotation,
        C0: Vec3,
        camera: CameraModel,
        vehicle: VehicleProfile,
        params: ModelParams,
        mean: FloatArray,
        prior_std: FloatArray,
    ) -> None:
        self.data, self.sampler, self.R0, self.C0 = data, sampler, R0, C0
        self.camera, self.vehicle, self.params = camera, vehicle, params
        self.mean = mean
        self.heights = len(mean) - N_PARAMS  # height offsets (ModelParams.drive_past_heights) at the end
        self.has_prior = np.isfinite(prior_std)
        self.prior_weight = np.where(self.has_prior, 1.0 / np.where(self.has_prior, prior_std, 1.0), 0.0)
        self.prior_jacobian = np.diag(self.prior_weight)[self.has_prior]  # constant: the priors are linear
        self.box_index, self.edge_index = np.nonzero(data.used)
        self._cache: dict[str, FloatArray] = {}
        # What the Jacobian at the cached x reuses: raw boxes, camera points, edge corners, R, poses,
        # body rotations, projected points.
        self._state: (
            tuple[Boxes, FloatArray, IntArray, Rotation, FloatArray, FloatArray, FloatArray] | None
        ) = None
        self.data_scale = np.ones(len(self.box_index))  # px per unit, per data row
        self.f_scale = 1.0  # where the robust loss bends, in data-row units
        self.sigma_px = params.f_scale_px
        self.edge_fraction = np.zeros(4)
        self.rho = 0.0
        heights = data.boxes[:, 3] - data.boxes[:, 1]
        self.row_height = np.maximum(heights, 1.0)[self.box_index]

    def pixel_residuals(self, x: FloatArray) -> FloatArray:
        self._evaluate(x)
        return np.asarray(self._cache["r"][: self.data_rows] * self.data_scale, dtype=np.float64)

    def weigh(self, x: FloatArray) -> None:
        """Per-edge reliability from the residuals at x: each row's std is sqrt(s0^2 + (c_k h)^2), s0 the
        detector's noise (px) and c_k the share of the box height h by which edge k's model misses (a body
        template never matches every silhouette: the bottom edge of a near car misses by several per cent,
        its sides by one or two); rows are then divided by that std times sqrt((1 + rho) / (1 - rho)), the
        variance inflation of the residuals' correlation from frame to frame. Sets data_scale, f_scale."""
        r = self.pixel_residuals(x)
        edge, h = self.edge_index, self.row_height
        spread = 1.4826 * float(np.median(np.abs(r))) if len(r) else 1.0
        inlier = np.abs(r) <= max(3.0 * spread, 3.0 * self.params.min_sigma_px)
        design = np.zeros((int(inlier.sum()), 5))
        design[:, 0] = 1.0
        design[np.arange(len(design)), 1 + edge[inlier]] = h[inlier] ** 2
        solution, _ = nnls(design, r[inlier] ** 2) if len(design) >= 5 else (np.zeros(5), 0.0)
        s0_squared = max(float(solution[0]), self.params.min_sigma_px**2)
        self.sigma_px = math.sqrt(s0_squared)
        self.edge_fraction = np.sqrt(solution[1:])
        sigma = np.sqrt(s0_squared + (self.edge_fraction[edge] * h) ** 2)
        weights = _robust_weights(r / sigma, self.params.loss, 2.0)  # type: ignore[arg-type]
        bi = self.box_index
        self.rho = _lag_one_correlation(
            r / sigma * np.sqrt(weights), self.data.track_ids[bi], self.data.t_s[bi], edge
        )
        inflation = math.sqrt((1.0 + self.rho) / (1.0 - self.rho))
        self.data_scale = sigma * inflation
        self.f_scale = 2.0 / inflation  # the loss bends at 2 of a row's own std
        self._cache = {}  # rows are scaled anew

    def set_skew(self, x: FloatArray, always: bool = False) -> None:
        """The data's skew (_Data.skew) from the model at x: each edge's rate, and the row of the point that
        forms it. Noise-free, where the boxes' differences along a track would put their noise into the
        readout's regressor; held for the fit (rates and rows barely change with the small moves of the
        pose a fit makes from its start). Nothing to do where the readout is held at 0: the boxes are then
        their own correction and the readout's column is pinned by its prior; `always` sets it there too (the
        readout's whole response, for consider_moves)."""
        if self.params.readout_std_s <= _HELD and x[_READOUT] == 0.0 and not always:
            return
        step = self.params.shape_step
        later = x.copy()
        later[_DELTA] -= step  # the trajectory `step` later
        now, cam, corner, _ = self.raw(x)
        then, _, _, _ = self.raw(later)
        rate = np.nan_to_num((then - now) / step)
        n = len(now)
        edge_points = cam[np.arange(n)[:, None], corner].reshape(-1, 3)
        rows = _project(edge_points, self.camera, self.params.min_depth_m)[:, 1].reshape(n, 4)
        boxes = self.data.boxes
        rows[:, 1], rows[:, 3] = boxes[:, 1], boxes[:, 3]  # the top and bottom edges' rows are measured
        rows_apart = np.nan_to_num(rows - 0.5 * (boxes[:, 1] + boxes[:, 3])[:, None])
        self.data = replace(self.data, skew=rate * rows_apart / self.camera.height)
        self._cache = {}

    def poses_at(self, x: FloatArray) -> FloatArray:
        """The vehicle's pose (N, 6) when each box's centre row was exposed: its stamp minus the time shift
        (of the image's middle row), plus the readout's share from there to the box centre's row."""
        poses = self.sampler.at(self.data.t_s - x[_DELTA] + x[_READOUT] * self.data.row_share)
        if self.heights:
            poses[:, 2] += x[N_PARAMS:][self.data.drive_past]
        return poses

    def behind_camera(self, x: FloatArray) -> BoolArray:
        """(N,) whether any template point of the box's vehicle at x lies nearer the camera plane than
        `min_depth_m` (or behind it), where `_project` clamps it."""
        _, cam, _, _ = self.raw(x)
        return np.asarray((cam[..., 2] < self.params.min_depth_m).any(axis=1), dtype=np.bool_)

    # Raw tight boxes of the template and the points forming their edges.
    def raw(self, x: FloatArray) -> tuple[Boxes, FloatArray, IntArray, Rotation]:
        return self.raw_at(x, self.poses_at(x))

    def raw_at(self, x: FloatArray, poses: FloatArray) -> tuple[Boxes, FloatArray, IntArray, Rotation]:
        """`raw` with the vehicle at the given poses (N, 6) instead of x's."""
        R, C = _pose_from_params(x[_POSE], self.R0, self.C0)
        world = body_points_to_world(poses, template_points(x[_SHAPE], self.vehicle), self.vehicle)
        n, k = world.shape[:2]
        cam = _camera_points(world.reshape(-1, 3), R, C)
        uv = _project(cam, self.camera, self.params.min_depth_m).reshape(n, k, 2)
        raw, corner = _tight_boxes(uv)
        return raw, cam.reshape(n, k, 3), corner, R

    def _shape_steps(
        self, x: FloatArray, poses: FloatArray, R_body: FloatArray, uv: FloatArray
    ) -> FloatArray:
        """The raw boxes (7, N, 4) with each shape parameter in turn stepped by shape_step (the forward
        differences of the template), from the poses, body rotations and projected template points (N, 12,
        2) at x: only the points a step moves (24 of the 7 x 12) are placed and projected again."""
        points = template_points(x[_SHAPE], self.vehicle)
        point_sets, moved = [], []
        for j in range(_SHAPE.start, _SHAPE.stop):
            xp = x.copy()
            xp[j] += self.params.shape_step
            stepped = template_points(xp[_SHAPE], self.vehicle)
            moved.append(np.any(stepped != points, axis=1))
            point_sets.append(stepped[moved[-1]])
        R, C = _pose_from_params(x[_POSE], self.R0, self.C0)
        world = rotated_body_points(R_body, poses, np.vstack(point_sets), self.vehicle)
        n, k = world.shape[:2]
        cam = _camera_points(world.reshape(-1, 3), R, C)
        moved_uv = _project(cam, self.camera, self.params.min_depth_m).reshape(n, k, 2)
        stepped_uv = np.broadcast_to(uv, (len(moved), *uv.shape)).copy()
        start = 0
        for j, rows in enumerate(moved):
            stop = start + int(rows.sum())
            stepped_uv[j][:, rows] = moved_uv[:, start:stop]
            start = stop
        stepped_raw, _ = _tight_boxes(stepped_uv.reshape(-1, *uv.shape[1:]))
        return stepped_raw.reshape(len(moved), n, 4)

    @staticmethod
    def biased(raw: Boxes, bias: FloatArray) -> Boxes:
        s = bias[0]
        x1, y1, x2, y2 = raw.T
        return (
            np.column_stack(
                [
                    x1 * (1 + s / 2) - x2 * s / 2,
                    y1 * (1 + s / 2) - y2 * s / 2,
                    x2 * (1 + s / 2) - x1 * s / 2,
                    y2 * (1 + s / 2) - y1 * s / 2,
                ]
            )
            + _OFFSET_FROM_BIAS @ bias[1:]
        )

    def _evaluate(self, x: FloatArray) -> None:
        """The residuals at x (the Jacobian only when asked for: the solver does not need it at the points
        whose step it rejects)."""
        if "x" in self._cache and np.array_equal(self._cache["x"], x):
            return
        R, C = _pose_from_params(x[_POSE], self.R0, self.C0)
        poses = self.poses_at(x)
        R_body = rotation_from_ypr(poses[:, 3], poses[:, 4], poses[:, 5])
        world = rotated_body_points(R_body, poses, template_points(x[_SHAPE], self.vehicle), self.vehicle)
        n, k = world.shape[:2]
        cam = _camera_points(world.reshape(-1, 3), R, C)
        uv = _project(cam, self.camera, self.params.min_depth_m).reshape(n, k, 2)
        raw, corner = _tight_boxes(uv)
        model = self.biased(raw, x[_BIAS])
        bi, ei = self.box_index, self.edge_index
        residual = model[bi, ei] - self.data.corrected(float(x[_READOUT]))[bi, ei]
        prior_r = ((x - self.mean) * self.prior_weight)[self.has_prior]
        self._cache = {
            "x": x.copy(),
            "r": np.concatenate([residual / self.data_scale, prior_r]),
            "model": model,
        }
        self._state = (raw, cam.reshape(n, k, 3), corner, R, poses, R_body, uv)

    def _evaluate_jacobian(self, x: FloatArray) -> None:
        self._evaluate(x)
        if "J" in self._cache:
            return
        assert self._state is not None
        raw, cam, corner, R, poses, R_body, uv = self._state
        model = self._cache["model"]
        bi, ei = self.box_index, self.edge_index
        m = len(bi)
        J = np.zeros((m, N_PARAMS + self.heights))
        # Pose: the edge-forming point's projection (analytic), through the bias transform.
        s = x[_BIAS][0]
        axis = np.array([0, 1, 0, 1])
        opposite = np.array([2, 3, 0, 1])
        n = len(raw)
        # The four edges' points in one call (element-wise arithmetic: the same values as one per edge).
        pts = cam[np.arange(n)[:, None], corner].reshape(-1, 3)  # (n * 4, 3), box-major
        d_uv = _project_jacobian(
            pts, _camera_points_jacobian(pts, R, x[:3]), self.camera, self.params.min_depth_m
        ).reshape(n, 4, 2, 6)
        d_raw = d_uv[:, np.arange(4), axis, :]
        d_model = (1 + s / 2) * d_raw - (s / 2) * d_raw[:, opposite, :]
        J[:, _POSE] = d_model[bi, ei]
        # Time shift and template: forward differences of the raw boxes.
        step = self.params.shape_step
        xp = x.copy()
        xp[_DELTA] += step
        raw_p, _, _, _ = self.raw(xp)
        J[:, _DELTA] = (self.biased(raw_p, x[_BIAS])[bi, ei] - model[bi, ei]) / step
        # The same time, later by the centre row's share; and each edge's own row.
        J[:, _READOUT] = -J[:, _DELTA] * self.data.row_share[bi] + self.data.skew[bi, ei]
        for j, raw_p in enumerate(self._shape_steps(x, poses, R_body, uv)):
            J[:, _SHAPE.start + j] = (self.biased(raw_p, x[_BIAS])[bi, ei] - model[bi, ei]) / step
        # Bias: analytic.
        J[:, _BIAS.start] = ((raw - raw[:, opposite]) / 2.0)[bi, ei]
        J[:, _BIAS.start + 1 : _BIAS.stop] = _OFFSET_FROM_BIAS[ei]
        if self.heights:  # every box raised at once: each box's change goes to its drive-past's column
            xp = x.copy()
            xp[N_PARAMS:] += step
            raw_p, _, _, _ = self.raw(xp)
            change = (self.biased(raw_p, x[_BIAS])[bi, ei] - model[bi, ei]) / step
            J[np.arange(m), N_PARAMS + self.data.drive_past[bi]] = change
        self._cache["J"] = np.vstack([J / self.data_scale[:, None], self.prior_jacobian])

    def residuals(self, x: FloatArray) -> FloatArray:
        self._evaluate(x)
        return self._cache["r"]

    def jacobian(self, x: FloatArray) -> FloatArray:
        self._evaluate_jacobian(x)
        return self._cache["J"]

    @property
    def data_rows(self) -> int:
        return len(self.box_index)


def _assemble(
    model: _Model, x: FloatArray, converged: bool, evaluations: int, scene_range: float
) -> ModelFit:
    params = model.params
    r_all, J_all = model.residuals(x), model.jacobian(x)
    m = model.data_rows
    r = r_all[:m]  # in units of the effective residual std (model.data_scale px)
    weights = _robust_weights(r, params.loss, model.f_scale)  # type: ignore[arg-type]
    sigma = model.sigma_px
    Js, scale, A, prior_info = _normal_matrix(model, J_all, weights, scene_range)
    # Clusters: one track and cluster_s seconds.
    data = model.data
    bi = model.box_index
    block = np.floor((data.t_s[bi] - data.t_s.min()) / params.cluster_s).astype(np.int64)
    keys = np.column_stack([data.track_ids[bi], block])
    _, cluster = np.unique(keys, axis=0, return_inverse=True)
    cluster = cluster.ravel()
    clusters = int(cluster.max()) + 1
    scores = (weights * r)[:, None] * Js
    sums = np.zeros((clusters, J_all.shape[1]))
    np.add.at(sums, cluster, scores)
    correction = clusters / max(clusters - 1, 1)
    B = correction * (sums.T @ sums) + prior_info
    A_inv = _inverse(A)
    sandwich = A_inv @ B @ A_inv
    # With few clusters the sandwich misses directions (B has at most one rank per cluster); the classical
    # covariance (the data rows already carry the variance inflation of their correlation) stands in.
    classical = A_inv
    # Never below the classical covariance in any direction: add the positive part of their difference.
    difference = classical - sandwich
    values, vectors = np.linalg.eigh((difference + difference.T) / 2)
    covariance_scene = sandwich + (vectors * np.maximum(values, 0.0)) @ vectors.T
    covariance_full = covariance_scene / np.outer(scale, scale)
    pose_cov = covariance_full[:6, :6].copy()
    pose_cov[3:, 3:] += params.gnss_covariance()
    R, C = _pose_from_params(x[_POSE], model.R0, model.C0)
    model_boxes = model._cache["model"]
    residuals = np.full(data.boxes.shape, np.nan)
    residuals[data.used] = (model_boxes - data.corrected(float(x[_READOUT])))[data.used]
    row_scale = np.full(data.boxes.shape, np.nan)
    row_scale[model.box_index, model.edge_index] = model.data_scale
    stds = np.sqrt(np.maximum(np.diag(covariance_full), 0.0))
    finite = np.isfinite(residuals)
    position_std_m, rotation_std_deg = largest_stds(pose_cov)
    return ModelFit(
        R_cam_from_local=R,
        t_cam_from_local=-R @ C,
        camera_centre=C,
        covariance=pose_cov,
        position_std_m=position_std_m,
        rotation_std_deg=rotation_std_deg,
        time_shift_s=float(x[_DELTA]),
        time_shift_std_s=float(stds[_DELTA]),
        shape=x[_SHAPE].copy(),
        shape_std=stds[_SHAPE].copy(),
        bias=x[_BIAS].copy(),
        bias_std=stds[_BIAS].copy(),
        residuals_px=residuals,
        box_rmse_px=float(np.sqrt(np.mean(residuals[finite] ** 2))) if finite.any() else math.nan,
        sigma_px=sigma,
        used_residuals=m,
        clusters=clusters,
        box_track_ids=data.track_ids,
        stamps=data.stamps,
        converged=converged,
        iterations=evaluations,
        full_covariance=covariance_full,
        row_scale_px=row_scale,
        edge_fraction=model.edge_fraction.copy(),
        rho=model.rho,
        readout_s=float(x[_READOUT]),
        readout_std_s=float(stds[_READOUT]),
        height_offsets_m=x[N_PARAMS:].copy(),
        height_offsets_std_m=stds[N_PARAMS:].copy(),
        drive_past_spans_ns=data.drive_past_spans_ns if model.heights else np.zeros((0, 2), dtype=np.int64),
    )


def _scene_range(model: _Model, C: Vec3) -> float:
    """Median distance (m, at least 1) from the camera centre C to the vehicle at the model's boxes: the
    scale that makes a rotation comparable with a position (conditioning of the normal matrix)."""
    centres = model.sampler.at(model.data.t_s)[:, :3]
    return max(1.0, float(np.median(np.linalg.norm(centres - C, axis=1))))


def _normal_matrix(
    model: _Model, J_all: FloatArray, weights: FloatArray, scene_range: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The weighted normal matrix of a model's Jacobian (data rows, then prior rows), in scene
    units (rotation scaled by the scene range): (Js the data rows' Jacobian in those units, the scale per
    parameter, A = Js^T W Js + prior information, the prior information)."""
    m = model.data_rows
    scale = np.ones(J_all.shape[1])
    scale[:3] = scene_range
    Js = J_all[:m] / scale
    Jp = J_all[m:] / scale
    prior_info = Jp.T @ Jp
    return Js, scale, Js.T @ (weights[:, None] * Js) + prior_info, prior_info


def largest_stds(covariance: FloatArray) -> tuple[float, float]:
    """(m, deg): the largest position and rotation std of a pose covariance (6, 6) [w, C]."""
    position = math.sqrt(max(float(np.linalg.eigvalsh(covariance[3:, 3:])[-1]), 0.0))
    rotation = math.sqrt(max(float(np.linalg.eigvalsh(covariance[:3, :3])[-1]), 0.0))
    return position, math.degrees(rotation)


def _quick(params: ModelParams, fit: ModelFit) -> ModelParams:
    """The settings of the refits inside the checks (left-out traversals, halves): half the evaluations,
    started from the full fit, with the readout time the full fit found as their prior, at the full fit's
    std (held where it held it). The readout is a property of the camera, which a single drive-past, whose
    boxes keep to a band of rows, barely fixes apart from the clock; but held exactly, a readout the full
    fit took up to absorb a drive-past seen from a moved camera kept the others from their own fit (one of
    five synthetic drive-pasts from a camera turned 1 deg, a full-fit readout of 55-69 ms where there is
    none: the turn went unflagged in 4 of 10 scenes held, in none with the prior; a 0.5 deg turn between
    three drive-pasts and three more, 1 of 10 and none). Static: 0 of 10 five-drive-past scenes flagged
    either way; of 10 six-drive-past ones, 1 (the halves, 0.41 m / 0.97 deg: a half fitted into a
    template's local minimum) with the prior, 0 held."""
    return replace(
        params,
        max_evaluations=max(8, params.max_evaluations // 2),
        readout_s=fit.readout_s,
        readout_std_s=max(min(fit.readout_std_s, params.readout_std_s), _HELD),
    )


def _move_size(difference: FloatArray) -> tuple[float, float]:
    """(m, deg): how far a pose difference [w, C] (camera.pose_difference) moves the camera and turns it."""
    return float(np.linalg.norm(difference[3:])), math.degrees(float(np.linalg.norm(difference[:3])))


def _tight_boxes(uv: FloatArray) -> tuple[Boxes, IntArray]:
    """Projected points (N, K, 2) -> their tight boxes (N, 4) x1, y1, x2, y2 and the index of the point
    forming each edge (N, 4)."""
    corner = np.column_stack(
        [uv[:, :, 0].argmin(1), uv[:, :, 1].argmin(1), uv[:, :, 0].argmax(1), uv[:, :, 1].argmax(1)]
    )
    rows = np.arange(len(uv))[:, None]
    axis = np.array([0, 1, 0, 1])
    return uv[rows, corner, axis], corner


def _lag_one_correlation(
    residual: FloatArray, track_ids: IntArray, t_s: FloatArray, edges: IntArray
) -> float:
    """Pooled correlation of consecutive residuals of the same edge on the same track, clipped to
    [0, 0.95]: the variance of a mean of n AR(1) residuals is (1 + rho) / (1 - rho) times the i.i.d. one."""
    order = np.lexsort((t_s, edges, track_ids))
    r, same = residual[order], np.zeros(len(order) - 1, dtype=bool) if len(order) else np.zeros(0, bool)
    if len(order) < 3:
        return 0.0
    same = (track_ids[order][1:] == track_ids[order][:-1]) & (edges[order][1:] == edges[order][:-1])
    numerator = float(np.sum(r[1:][same] * r[:-1][same]))
    denominator = float(np.sum(r[1:][same] ** 2 + r[:-1][same] ** 2)) / 2.0
    if denominator <= 0.0:
        return 0.0
    return min(0.95, max(0.0, numerator / denominator))


def _inverse(A: FloatArray) -> FloatArray:
    """Inverse of a symmetric positive semi-definite matrix, its eigenvalues floored at 1e-14 of the largest
    after scaling to unit diagonal. Without the scaling the floor is relative to the stiffest parameter: a
    parameter held by a 1e-9 prior (1e18 of information) floored every direction the data fix to less
    than 1e4, and the pose's std read 0.01 (m, or m at the scene range) whatever the data said: a refused
    single drive-past 150 m off reported 0.051 m / 0.007 deg."""
    diagonal = np.diag(A)
    d = np.sqrt(np.where(diagonal > 0.0, diagonal, 1.0))
    scaled = A / np.outer(d, d)
    values, vectors = np.linalg.eigh((scaled + scaled.T) / 2)
    values = np.maximum(values, max(float(values[-1]), 1e-300) * 1e-14)
    return np.asarray(((vectors / values) @ vectors.T) / np.outer(d, d), dtype=np.float64)


# ---------------------------------------------------------------------------------------------------------
# Trimming, delta_p of the fitted model, and the check of the traversals against each other
# ---------------------------------------------------------------------------------------------------------


def fit_trimmed(
    R_cam_from_local: Rotation,
    t_cam_from_local: Vec3,
    tracks: Sequence[MatchedTrack],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
    floor: float = 0.08,
    rounds: int = 2,
) -> tuple[ModelFit, list[MatchedTrack]]:
    """`fit_vehicle_model`, then boxes whose misfit (max |edge residual| / box height) exceeds
    max(floor, 3 x median misfit) are dropped and the fit repeated from its own solution (an identity switch
    or an occluder makes misfits of tens of per cent that even a robust loss lets weigh). Returns the fit and
    the tracks it used."""
    fit = fit_vehicle_model(R_cam_from_local, t_cam_from_local, tracks, trajectory, camera, vehicle, params)
    used = list(tracks)
    for _ in range(rounds):
        kept = _trim_by(fit, used, floor)
        if sum(len(t.boxes) for t in kept) == sum(len(t.boxes) for t in used):
            break
        used = kept
        fit = fit_vehicle_model(
            fit.R_cam_from_local, fit.t_cam_from_local, used, trajectory, camera, vehicle, params
        )
    return fit, used


def _trim_by(fit: ModelFit, tracks: Sequence[MatchedTrack], floor: float) -> list[MatchedTrack]:
    boxes = np.concatenate([t.boxes for t in tracks])
    heights = np.maximum(boxes[:, 3] - boxes[:, 1], 1.0)
    residuals = fit.residuals_px
    finite_rows = np.isfinite(residuals).any(axis=1)
    misfit = np.full(len(boxes), np.inf)
    misfit[finite_rows] = np.nanmax(np.abs(residuals[finite_rows]), axis=1) / heights[finite_rows]
    finite = misfit[np.isfinite(misfit)]
    threshold = max(floor, 3.0 * float(np.median(finite))) if len(finite) else floor
    return select_rows(tracks, misfit <= threshold)


def unbiased_boxes(boxes: Boxes, bias: FloatArray) -> Boxes:
    """Detected boxes with the fitted detector convention undone: the boxes the template's tight box
    predicts (inverse of the scale about the centre and the edge offsets)."""
    s = float(bias[0])
    shifted = boxes - _OFFSET_FROM_BIAS @ bias[1:]
    a, b = 1.0 + s / 2.0, -s / 2.0  # [x1', x2'] = [[a, b], [b, a]] [x1, x2]
    det = a * a - b * b
    x1, y1, x2, y2 = shifted.T
    return np.column_stack(
        [(a * x1 - b * x2) / det, (a * y1 - b * y2) / det, (a * x2 - b * x1) / det, (a * y2 - b * y1) / det]
    )


def model_footprints(
    fit: ModelFit,
    tracks: Sequence[MatchedTrack],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
) -> FloatArray:
    """The fitted template's lowest rectangle at every box (N, 4, 3), local frame, at its time shift and
    readout."""
    sampler = PoseSampler.of(trajectory)
    stamps = np.concatenate([t.stamps for t in tracks])
    shares = _row_shares(np.concatenate([t.boxes for t in tracks]), camera)
    poses = sampler.at(sampler.seconds(stamps) - fit.time_shift_s + fit.readout_s * shares)
    return body_points_to_world(poses, fit.footprint_body_frame(vehicle), vehicle)


@dataclass(frozen=True, slots=True)
class TraversalCheck:
    """Leave-one-traversal-out fits of the final model.

    traversals: clusters of tracks (a new one after a gap of more than `gap_s` without the vehicle's track);
    covariance (6, 6): the jackknife covariance of [w, C] over them (model error between drive-pasts
    included), plus with six or more the split-half term of the two halves' difference, None with fewer
    than 2 clusters; shift_m / angle_deg: the largest move of the pose when one
    traversal is left out; disagreeing: reason text, else '', when some left-out traversal cannot be fitted,
    or its boxes are predicted by the others beyond their uncertainty and the noise (mean squared Mahalanobis
    residual above `holdout_chi2_per_residual`) or pull their pose beyond `holdout_pull_chi2`, and leaving it
    out moves the pose materially (see check_traversals). time_shift_var_s2: the jackknife variance (s^2) of
    the time shift over the left-out fits (0 where the model held it, or with fewer than two of them)."""

    traversals: int
    covariance: FloatArray | None
    shift_m: float
    angle_deg: float
    disagreeing: str
    time_shift_var_s2: float = 0.0


@dataclass(frozen=True, slots=True)
class LeftOut:
    """The fits of a model class with each traversal left out in turn, from one full fit.

    clusters: the traversals (tracks; a new one after `gap_s` without the vehicle's track); fits[k]: the
    fit without clusters[k], or the reason it could not be made."""

    full: ModelFit
    clusters: tuple[tuple[MatchedTrack, ...], ...]
    fits: tuple[ModelFit | str, ...]


@dataclass(frozen=True, slots=True)
class _SubsetFit:
    """fit_vehicle_model of a subset of the tracks, started from one fit (module level: a process pool's map
    pickles it); the reason text when the subset cannot be fitted."""

    start: ModelFit
    trajectory: Trajectory
    camera: CameraModel
    vehicle: VehicleProfile
    params: ModelParams

    def __call__(self, tracks: Sequence[MatchedTrack]) -> ModelFit | str:
        try:
            return fit_vehicle_model(
                self.start.R_cam_from_local,
                self.start.t_cam_from_local,
                tracks,
                self.trajectory,
                self.camera,
                self.vehicle,
                self.params,
            )
        except DegenerateGeometry as err:
            return str(err)


def leave_one_out(
    fit: ModelFit,
    tracks: Sequence[MatchedTrack],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
    gap_s: float = TRAVERSAL_GAP_S,
    map_fn: MapFn = map,
) -> LeftOut:
    """Fit the model class of `params` without each traversal in turn, started from `fit` (none with fewer
    than 2 traversals). Shared by the choice of model class (holdout_error) and check_traversals. The fits
    are independent: `map_fn` (e.g. a process pool's map) may run them side by side, with identical
    results."""
    clusters = tuple(tuple(c) for c in _traversal_clusters(tracks, gap_s))
    if len(clusters) < 2:
        return LeftOut(fit, clusters, ())
    rests = [[t for i, c in enumerate(clusters) if i != index for t in c] for index in range(len(clusters))]
    fits = tuple(map_fn(_SubsetFit(fit, trajectory, camera, vehicle, _quick(params, fit)), rests))
    return LeftOut(fit, clusters, fits)


def check_traversals(
    left_out: LeftOut,
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
    map_fn: MapFn = map,
) -> TraversalCheck:
    """Compare the full fit with each fit that leaves a traversal out (see TraversalCheck); `map_fn` runs
    the two halves' fits (see _halves_disagree)."""
    fit, clusters = left_out.full, left_out.clusters
    if len(clusters) < 2:
        return TraversalCheck(len(clusters), None, 0.0, 0.0, "")
    deltas: list[FloatArray] = []
    time_shifts: list[float] = []
    worst_shift = worst_angle = 0.0
    problems: list[str] = []
    for index, loo in enumerate(left_out.fits):
        if isinstance(loo, str):
            problems.append(f"without traversal {index + 1}: {loo}")
            continue
        delta = pose_difference(
            fit.R_cam_from_local, fit.camera_centre, loo.R_cam_from_local, loo.camera_centre
        )
        deltas.append(delta)
        time_shifts.append(loo.time_shift_s)
        shift, angle = _move_size(delta)
        worst_shift, worst_angle = max(worst_shift, shift), max(worst_angle, angle)
        # Cross-validation: the left-out traversal's boxes as predicted by the others. Judged on the boxes,
        # not on the pose move against the left-out fit's own std (that std leaves out errors shared within
        # a drive-past, GNSS drift, and moves of 2-3 of it were common between drive-pasts that agree), and
        # only where it matters: leaving the traversal out must also move the pose by more than 3 of the
        # joint fit's stds (the first simulator's drifting poses made traversals differ by 3-5 x the noise in
        # pixels while moving the pose by 0.02 m / 0.06 deg).
        statistic, predicted, pull = _holdout_statistic(
            loo, clusters[index], trajectory, camera, vehicle, params
        )
        material = shift > 3.0 * fit.position_std_m or angle > 3.0 * fit.rotation_std_deg
        if statistic > params.holdout_chi2_per_residual and material:
            problems.append(
                f"the others predict traversal {index + 1}'s boxes {predicted:.1f} px off, "
                f"{statistic:.1f} x the variance their uncertainty and the detector's noise allow"
            )
        elif pull > params.holdout_pull_chi2 and (
            shift > max(3.0 * loo.position_std_m, params.min_disagreement_m)
            or angle > max(3.0 * loo.rotation_std_deg, params.min_disagreement_deg)
        ):
            # Material against the fit without it: a foreign drive-past inflates the joint fit's own std
            # (its residuals are correlated: rho 0.95 with one drive-past 1 m off), which hid a 0.6 m move.
            problems.append(
                f"traversal {index + 1}'s boxes pull the others' pose by a chi-square of {pull:.0f} "
                f"(6 dof) > {params.holdout_pull_chi2:.0f}"
            )
    halves, difference = _halves_disagree(fit, clusters, trajectory, camera, vehicle, params, map_fn)
    if halves:
        problems.append(halves)
    if difference is not None:
        halves_shift, halves_angle = _move_size(difference)
        worst_shift, worst_angle = max(worst_shift, halves_shift), max(worst_angle, halves_angle)
    k = len(deltas)
    covariance = None
    # With two traversals each left-out fit is a single drive-past, often weak, so this overstates the
    # joint fit's uncertainty: accepted. Without it a scene of two drive-pasts that moved the pose 0.6 m /
    # 2.5 deg when either was left out reported 0.05 m / 0.013 deg and was published 0.6 deg off.
    time_shift_var = 0.0
    if k >= 2:
        stacked = np.array(deltas)
        centred = stacked - stacked.mean(axis=0)
        covariance = (k - 1) / k * centred.T @ centred
        time_shift_var = (k - 1) / k * float(np.sum((np.array(time_shifts) - np.mean(time_shifts)) ** 2))
    # Leaving one traversal out treats drive-pasts as independent; errors that drift over minutes (GNSS
    # wander, a warming mount) are shared by neighbouring ones and hide from it. The two halves in time
    # show them: their difference d, of two independent estimates whose mean the joint fit is, is d d^T / 4
    # in its direction (the toolbox pair of the `long` preset: halves 0.52 m apart, within their own
    # uncertainty, a jackknife std of 0.13 m and the joint fit 0.38 m off).
    if difference is not None:
        split = np.outer(difference, difference) / 4.0
        covariance = split if covariance is None else covariance + split
    reason = ""
    if problems:
        reason = f"traversals disagree by {worst_shift:.2f} m / {worst_angle:.2f} deg: " + "; ".join(problems)
    return TraversalCheck(len(clusters), covariance, worst_shift, worst_angle, reason, time_shift_var)


def _halves_disagree(
    fit: ModelFit,
    clusters: Sequence[Sequence[MatchedTrack]],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
    map_fn: MapFn = map,
) -> tuple[str, FloatArray | None]:
    """A camera knocked between drive-pasts: the earlier and the later half of the traversals (in time, at
    least 3 each) fitted apart must agree within the two fits' uncertainty (chi-square of the pose
    difference, 6 dof, above holdout_pull_chi2) or by the minimum disagreement. One traversal left out
    cannot see it: with four drive-pasts before a 0.4 m / 0.6 deg move and four after, each left-out fit
    still has both sides, and the pooled fit was accepted 0.29-0.35 m / 0.48 deg off (moved-camera, first
    simulator). Halves of two drive-pasts fix the pose too weakly for their own covariance: on a static
    camera they refused 5 more of 40 four-drive-past fits (bench.daemon reverify). Returns the reason (''
    when they agree) and the halves' pose difference [w, C] (None when not fitted)."""
    if len(clusters) < 6:
        return "", None
    middle = len(clusters) // 2
    parts = [[t for c in part for t in c] for part in (clusters[:middle], clusters[middle:])]
    halves = list(map_fn(_SubsetFit(fit, trajectory, camera, vehicle, _quick(params, fit)), parts))
    early, late = halves
    if isinstance(early, str) or isinstance(late, str):
        return "", None  # a half too weak to fit on its own says nothing about a move
    difference = pose_difference(
        early.R_cam_from_local, early.camera_centre, late.R_cam_from_local, late.camera_centre
    )
    chi2 = float(difference @ _inverse(early.covariance + late.covariance) @ difference)
    shift, angle = _move_size(difference)
    if chi2 > params.holdout_pull_chi2 and (
        shift > params.min_disagreement_m or angle > params.min_disagreement_deg
    ):
        reason = (
            f"traversals 1-{middle} and {middle + 1}-{len(clusters)} fitted apart differ by {shift:.2f} m / "
            f"{angle:.2f} deg, a chi-square of {chi2:.0f} (6 dof) > {params.holdout_pull_chi2:.0f}: "
            "the camera may have moved between them, or the vehicle model fits their views differently"
        )
        return reason, difference
    return "", difference


def combined_covariance(independent: FloatArray, check: TraversalCheck) -> FloatArray:
    """The covariance of the errors independent between drive-pasts (6, 6: the fit's, and each drive-past's
    own GNSS error), raised in every direction where the traversals scatter more (jackknife). The scatter
    measures those same errors (and what the body does differently in each view), so the larger of the two
    counts, never their sum."""
    if check.covariance is None:
        return independent
    return dominating_covariance(independent, check.covariance)


def dominating_covariance(A: FloatArray, B: FloatArray) -> FloatArray:
    """The covariance that is A raised in every direction where B is larger: in the coordinates where A is
    the identity, B's eigenvalues below 1 are lifted to 1. That is unit-free: the positive part of B - A
    taken directly mixes rad^2 with m^2 in the pose's [w, C], and lifted a rotation std of 0.03 deg (fit) /
    0.09 deg (jackknife) to 0.38 deg through a position direction (sil-west seed 0, first simulator)."""
    A = (A + A.T) / 2
    B = (B + B.T) / 2
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        values, vectors = np.linalg.eigh(B - A)
        return np.asarray(A + (vectors * np.maximum(values, 0.0)) @ vectors.T, dtype=np.float64)
    L_inv = np.linalg.inv(L)
    M = L_inv @ B @ L_inv.T
    values, vectors = np.linalg.eigh((M + M.T) / 2)
    lifted = (vectors * np.maximum(values, 1.0)) @ vectors.T
    return np.asarray(L @ lifted @ L.T, dtype=np.float64)


def _holdout_statistic(
    loo: ModelFit,
    held_out: Sequence[MatchedTrack],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
) -> tuple[float, float, float]:
    """How well the fit without a traversal predicts that traversal's boxes, two ways.

    With r the left-out boxes' residuals (px) under the fit without them, J their Jacobian, S that fit's
    full covariance and D the detector noise and model misfit the other traversals show (per edge and box
    size, correlation included), the prediction's covariance is C = D + J S J^T. Returned: the mean squared
    Mahalanobis residual r^T C^-1 r / m over the m residuals (residuals beyond 3 of their own std clipped
    there: outlier boxes); the median |r|; and the pull, b^T A^-1 b with A = Jp^T C^-1 Jp, b = Jp^T C^-1 r
    (Jp the pose columns): the chi-square, 6 degrees of freedom, of the pose offset the left-out boxes ask
    for. The pull's residuals are clipped about each edge's median instead, so that an offset common to the
    drive-past survives while single outlier boxes do not."""
    model, x = _model_of(loo, held_out, trajectory, camera, vehicle, params)
    boxes = model.data.boxes
    model.data_scale = np.ones(model.data_rows)
    residuals = model.residuals(x)[: model.data_rows]
    J = model.jacobian(x)[: model.data_rows]
    if len(residuals) == 0:
        return 0.0, 0.0, 0.0
    height = np.maximum(boxes[:, 3] - boxes[:, 1], 1.0)[model.box_index]
    # The noise as the other traversals measured it: a foreign traversal would inflate the joint fit's.
    sigma = np.sqrt(loo.sigma_px**2 + (loo.edge_fraction[model.edge_index] * height) ** 2)
    sigma *= math.sqrt((1.0 + loo.rho) / (1.0 - loo.rho))
    r = np.clip(residuals, -3.0 * sigma, 3.0 * sigma)
    # Woodbury: C^-1 = (D + J S J^T)^-1 = D^-1 - D^-1 J (S^-1 + J^T D^-1 J)^-1 J^T D^-1.
    inv_d = 1.0 / sigma**2
    # Each drive-past's positions carry their own GNSS offset (ModelParams.gnss_covariance): to the boxes
    # of the left-out one it looks like a shift of the camera centre, so it joins the prediction's covariance.
    # With height offsets, the left-out drive-pasts' own are unknown to the others: their prior.
    S = np.zeros((len(x), len(x)))
    S[:N_PARAMS, :N_PARAMS] = loo.full_covariance[:N_PARAMS, :N_PARAMS]
    S[N_PARAMS:, N_PARAMS:] = params.drive_past_height_std_m**2 * np.eye(len(x) - N_PARAMS)
    S[3:6, 3:6] += params.gnss_covariance()
    inner = _inverse(_inverse(S) + J.T @ (inv_d[:, None] * J))

    def c_inv(M: FloatArray) -> FloatArray:
        DM = inv_d[:, None] * M if M.ndim == 2 else inv_d * M
        return np.asarray(DM - (inv_d[:, None] * J) @ (inner @ (J.T @ DM)), dtype=np.float64)

    quadratic = float(r @ c_inv(r))
    median = np.zeros_like(residuals)
    for edge in range(4):
        on_edge = model.edge_index == edge
        if np.any(on_edge):
            median[on_edge] = np.median(residuals[on_edge])
    centred = median + np.clip(residuals - median, -3.0 * sigma, 3.0 * sigma)
    Jp = J[:, :6]
    b = Jp.T @ c_inv(centred)
    pull = float(b @ _inverse(Jp.T @ c_inv(Jp)) @ b)
    return max(quadratic, 0.0) / len(r), float(np.median(np.abs(r))), max(pull, 0.0)


def _median_abs(residuals: FloatArray) -> float:
    finite = residuals[np.isfinite(residuals)]
    return float(np.median(np.abs(finite))) if len(finite) else math.inf


def _traversal_clusters(tracks: Sequence[MatchedTrack], gap_s: float) -> list[list[MatchedTrack]]:
    ordered = sorted(tracks, key=lambda t: int(t.stamps[0]))
    clusters: list[list[MatchedTrack]] = []
    end = None
    for track in ordered:
        if end is None or int(track.stamps[0]) - end > gap_s * 1e9:
            clusters.append([])
        clusters[-1].append(track)
        end = max(end or 0, int(track.stamps[-1]))
    return clusters


def predicted_residuals(
    fit: ModelFit,
    tracks: Sequence[MatchedTrack],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
) -> FloatArray:
    """|model edge - detected edge| (N, 4) px of the fitted model on any boxes (NaN on clipped edges)."""
    model, x = _model_of(fit, tracks, trajectory, camera, vehicle, params)
    raw, _, _, _ = model.raw(x)
    data = model.data
    return np.where(data.used, np.abs(model.biased(raw, fit.bias) - data.corrected(fit.readout_s)), np.nan)


def _model_of(
    fit: ModelFit,
    tracks: Sequence[MatchedTrack],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
) -> tuple[_Model, FloatArray]:
    """The model of a fit (its pose, shift, template and convention) on other boxes, and its parameter
    vector there (pose part zero: the model is built around the fit's pose)."""
    sampler = PoseSampler.of(trajectory)
    data = _data_of(tracks, sampler, camera, params)
    heights = params.height_count(len(data.drive_past_spans_ns))
    x = np.zeros(N_PARAMS + heights)
    x[_DELTA], x[_SHAPE], x[_BIAS], x[_READOUT] = fit.time_shift_s, fit.shape, fit.bias, fit.readout_s
    x[N_PARAMS:] = _offsets_for(fit, data.drive_past_spans_ns[:heights])
    model = _Model(
        data,
        sampler,
        fit.R_cam_from_local,
        fit.camera_centre,
        camera,
        vehicle,
        params,
        x,
        _prior_std(params, heights, vehicle),
    )
    model.set_skew(x)
    return model, x


def _prior_std(params: ModelParams, heights: int, vehicle: VehicleProfile) -> FloatArray:
    """The prior stds of a parameter vector with `heights` height offsets at its end."""
    stds = params.prior_std()
    stds[_SHAPE] = shape_prior(params, vehicle)[1]
    return np.concatenate([stds, [params.drive_past_height_std_m] * heights])


def _offsets_for(fit: ModelFit, spans_ns: IntArray) -> FloatArray:
    """Height offsets (K,) for drive-pasts spanning `spans_ns` (K, 2): the fit's offset of the drive-past
    it fitted at that time (within TRAVERSAL_GAP_S), else 0 (a drive-past the fit did not see: its height
    is known only to the prior)."""
    offsets = np.zeros(len(spans_ns))
    gap_ns = int(TRAVERSAL_GAP_S * 1e9)
    for k, (first, last) in enumerate(spans_ns):
        for (fit_first, fit_last), offset in zip(fit.drive_past_spans_ns, fit.height_offsets_m, strict=True):
            if first <= fit_last + gap_ns and last >= fit_first - gap_ns:
                offsets[k] = offset
                break
    return offsets


def _data_of(
    tracks: Sequence[MatchedTrack], sampler: PoseSampler, camera: CameraModel, params: ModelParams
) -> _Data:
    """The tracks' boxes stacked, with their times on the sampler's clock and the unclipped edges."""
    boxes = np.concatenate([np.asarray(t.boxes, dtype=np.float64) for t in tracks])
    stamps = np.concatenate([np.asarray(t.stamps, dtype=np.int64) for t in tracks])
    drive_past, spans = _drive_pasts(tracks, TRAVERSAL_GAP_S)
    return _Data(
        boxes=boxes,
        t_s=sampler.seconds(stamps),
        row_share=_row_shares(boxes, camera),
        skew=np.zeros_like(boxes),  # set from a model (_Model.set_skew)
        track_ids=np.concatenate([np.full(len(t.boxes), t.track_id, dtype=np.int64) for t in tracks]),
        stamps=stamps,
        used=~_clipped_edges(boxes, camera, params.border_margin_px),
        drive_past=np.repeat(drive_past, [len(t.boxes) for t in tracks]),
        drive_past_spans_ns=spans,
    )


def _drive_pasts(tracks: Sequence[MatchedTrack], gap_s: float) -> tuple[IntArray, IntArray]:
    """Each track's drive-past (K,), an index in time order (_traversal_clusters), and the drive-pasts' first
    and last stamps (K, 2) ns."""
    clusters = _traversal_clusters([t for t in tracks if len(t.stamps)], gap_s)
    which = {id(t): k for k, cluster in enumerate(clusters) for t in cluster}
    index = np.array([which.get(id(t), 0) for t in tracks], dtype=np.int64)
    spans = [[int(c[0].stamps[0]), max(int(t.stamps[-1]) for t in c)] for c in clusters]
    return index, np.array(spans, dtype=np.int64).reshape(-1, 2)


def _row_shares(boxes: Boxes, camera: CameraModel) -> FloatArray:
    """Each box centre's row as a share of the image height from its middle (-1/2 top, 1/2 bottom): when a
    rolling shutter's readout reached it, relative to the middle row (whose time the time shift is: it is
    the one least tied to the readout, as the boxes' rows centre on it more or less)."""
    share = np.clip(0.5 * (boxes[:, 1] + boxes[:, 3]) / camera.height, 0.0, 1.0) - 0.5
    return np.asarray(share, dtype=np.float64)


def model_box_error(
    fit: ModelFit,
    tracks: Sequence[MatchedTrack],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
) -> float:
    """Scale-free misfit of the fitted model on all `tracks` (trimmed boxes included): median over boxes of
    max |model edge - detected edge| / box height; inf without a usable box. The right vehicle under the
    right pose reproduces its boxes to the detector's noise; another vehicle's track does not."""
    residuals = predicted_residuals(fit, tracks, trajectory, camera, vehicle, params)
    boxes = np.concatenate([np.asarray(t.boxes, dtype=np.float64) for t in tracks])
    return _median_relative_misfit(residuals, boxes)


def model_box_errors(
    fit: ModelFit,
    tracks: Sequence[MatchedTrack],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
) -> FloatArray:
    """`model_box_error` of each track on its own (K,), from one model per batch of up to
    `_SCORED_BOXES` boxes: every box's model edges depend on that box alone, so this is K calls' result for
    the cost of a few (it scores every track of a recording against a fit) and bounded memory."""
    errors = np.zeros(len(tracks))
    start, boxes = 0, 0
    for end, track in enumerate(tracks, start=1):
        boxes += len(track.boxes)
        if boxes < _SCORED_BOXES and end < len(tracks):
            continue
        batch = tracks[start:end]
        residuals = predicted_residuals(fit, batch, trajectory, camera, vehicle, params)
        ends = np.cumsum([len(t.boxes) for t in batch])[:-1]
        for index, (part, t) in enumerate(zip(np.split(residuals, ends), batch, strict=True)):
            errors[start + index] = _median_relative_misfit(part, np.asarray(t.boxes, dtype=np.float64))
        start, boxes = end, 0
    return errors


_SCORED_BOXES = 4096  # boxes per model in model_box_errors: ~10 MB of model arrays, most of the speed


def _median_relative_misfit(residuals: FloatArray, boxes: Boxes) -> float:
    """Median over boxes of the largest unclipped edge residual (N, 4) px over the box height; inf
    without a usable box."""
    rows = np.isfinite(residuals).any(axis=1)
    if not rows.any():
        return math.inf
    heights = np.maximum(boxes[rows, 3] - boxes[rows, 1], 1.0)
    return float(np.median(np.nanmax(residuals[rows], axis=1) / heights))


def consider_moves(
    fit: ModelFit,
    tracks: Sequence[MatchedTrack],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
    point_std_m: float,
    shift_std_px: float,
    readout_std_s: float = 0.0,
    roof_raise_std_m: float = 0.0,
) -> FloatArray:
    """What the fit holds but the world may not (Schmidt's consider parameters): the fit's response
    (K, N_PARAMS) to each moved by its std, one row each. The pose columns' outer product is the pose's
    consider covariance; the time shift's column is what they do to the clock.

    Each consider parameter changes the model boxes; the fit's own linear solution (pose, time shift,
    template and convention together, as `params` fitted them, so the fitted nuisance parameters absorb what
    they can) maps the change to a move of every parameter. The parameters, in row order: every box shifted
    by `shift_std_px` in x, then in y (ModelParams.fit_shift: held, never fitted, by default); each template
    point displaced by `point_std_m` along each body axis in turn (36 rows; the data cannot tell them from
    the pose: every view of the body shares them, and fitted to the truth's own tracks from the true pose
    the template still landed 0.15-0.5 m / 0.1-0.45 deg off with a sandwich std of 0.07-0.1 m / 0.09-0.12
    deg); then, with `roof_raise_std_m`, the roof's raise moved by that std, for a fit that held it at the
    data sheet's roof (known only to the std of a fit with it free); last, with `readout_std_s`, the readout
    moved by that std, for a fit that held it (a readout the data could not tell from 0 is known only to
    their std). (0, N_PARAMS) when every std is 0."""
    if point_std_m <= 0.0 and shift_std_px <= 0.0 and readout_std_s <= 0.0 and roof_raise_std_m <= 0.0:
        return np.zeros((0, N_PARAMS + len(fit.height_offsets_m)))
    response = _Response.of(fit, tracks, trajectory, camera, vehicle, params, readout_std_s > 0.0)
    if response is None:
        return np.zeros((0, N_PARAMS + len(fit.height_offsets_m)))
    model, x = response.model, response.x
    changes = [_OFFSET_FROM_BIAS[model.edge_index, :2].T * shift_std_px] if shift_std_px > 0.0 else []
    if point_std_m > 0.0:
        changes.append(_displaced_point_changes(model, x, vehicle, camera, params, point_std_m))
    rows = np.vstack(changes) / model.data_scale if changes else np.zeros((0, model.data_rows))
    if roof_raise_std_m > 0.0:  # the Jacobian is in row units
        rows = np.vstack([rows, roof_raise_std_m * response.J_all[: model.data_rows, ROOF_RAISE]])
    if readout_std_s > 0.0:
        rows = np.vstack([rows, readout_std_s * response.J_all[: model.data_rows, _READOUT]])
    return response.moves(rows)


def drive_past_gnss_moves(
    fit: ModelFit,
    tracks: Sequence[MatchedTrack],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
) -> FloatArray:
    """The fit's response (3 K, N_PARAMS) to each drive-past's positions moved by its own GNSS error
    (ModelParams.drive_past_gnss_std_m: east, north, then height, per drive-past in turn), as consider
    parameters (see consider_moves): the pose columns' outer product is their part of the pose's covariance.
    The offset common to every pose is the fit's own covariance's (ModelParams.gnss_covariance)."""
    horizontal, height = params.drive_past_gnss_std_m
    none = np.zeros((0, N_PARAMS + len(fit.height_offsets_m)))
    if max(horizontal, height) <= 0.0:
        return none
    response = _Response.of(fit, tracks, trajectory, camera, vehicle, params, False)
    if response is None:
        return none
    model, x = response.model, response.x
    bi, ei = model.box_index, model.edge_index
    poses = model.poses_at(x)
    base = model.biased(model.raw_at(x, poses)[0], x[_BIAS])[bi, ei]
    changes = []
    for axis, std in enumerate((horizontal, horizontal, height)):
        moved = poses.copy()
        moved[:, axis] += std
        changes.append(model.biased(model.raw_at(x, moved)[0], x[_BIAS])[bi, ei] - base)
    drive_past = model.data.drive_past[bi]
    rows = [
        np.where(drive_past == k, change, 0.0) for k in range(int(drive_past.max()) + 1) for change in changes
    ]
    return response.moves(np.array(rows) / model.data_scale)


@dataclass(frozen=True, slots=True)
class _Response:
    """A fit's linear response to a change of its model boxes: the model rebuilt on the fit's boxes, its rows
    weighted as the fit's second pass weighted them, and the normal matrix there."""

    model: _Model
    x: FloatArray
    J_all: FloatArray
    weights: FloatArray
    Js: FloatArray
    A_inv: FloatArray
    scale: FloatArray

    @staticmethod
    def of(
        fit: ModelFit,
        tracks: Sequence[MatchedTrack],
        trajectory: Trajectory,
        camera: CameraModel,
        vehicle: VehicleProfile,
        params: ModelParams,
        readout_skew: bool,
    ) -> _Response | None:
        """None where the boxes are too few for the parameters. `readout_skew`: the data's skew set even
        where the readout is held (the readout moves the edges apart as well as the box's time)."""
        model, x = _model_of(fit, tracks, trajectory, camera, vehicle, params)
        if model.data_rows < 2 * len(x):
            return None
        if readout_skew:
            model.set_skew(x, always=True)
        model.weigh(x)
        r_all, J_all = model.residuals(x), model.jacobian(x)
        weights = _robust_weights(r_all[: model.data_rows], params.loss, model.f_scale)  # type: ignore[arg-type]
        Js, scale, A, _ = _normal_matrix(model, J_all, weights, _scene_range(model, fit.camera_centre))
        return _Response(model, x, J_all, weights, Js, _inverse(A), scale)

    def moves(self, rows: FloatArray) -> FloatArray:
        """(K, parameters): the fit's move for each row (K, data rows) of model-box changes in row units."""
        return np.asarray(-(rows * self.weights) @ self.Js @ self.A_inv / self.scale, dtype=np.float64)


def _displaced_point_changes(
    model: _Model,
    x: FloatArray,
    vehicle: VehicleProfile,
    camera: CameraModel,
    params: ModelParams,
    std_m: float,
) -> FloatArray:
    """The model boxes' change (3k, m) px, row by row, with each of the k template points displaced by std_m
    along each body axis: the points placed and projected once, the displaced copies once more."""
    points = template_points(x[_SHAPE], vehicle)
    k = len(points)
    R, C = _pose_from_params(x[_POSE], model.R0, model.C0)
    poses = model.poses_at(x)
    R_body = rotation_from_ypr(poses[:, 3], poses[:, 4], poses[:, 5])
    displaced = (points[:, None, :] + std_m * np.eye(3)[None, :, :]).reshape(-1, 3)  # point-major (3k, 3)
    world = rotated_body_points(R_body, poses, np.vstack([points, displaced]), vehicle)
    n = len(poses)
    uv = _project(_camera_points(world.reshape(-1, 3), R, C), camera, params.min_depth_m).reshape(n, 4 * k, 2)
    base_uv, moved_uv = uv[:, :k], uv[:, k:]
    stepped = np.broadcast_to(base_uv, (3 * k, n, k, 2)).copy()
    which = np.arange(3 * k)
    stepped[which, :, which // 3] = moved_uv.transpose(1, 0, 2)
    raw, _ = _tight_boxes(np.vstack([base_uv[None], stepped]).reshape(-1, k, 2))
    boxes = np.stack([model.biased(b, x[_BIAS]) for b in raw.reshape(3 * k + 1, n, 4)])
    bi, ei = model.box_index, model.edge_index
    return np.asarray(boxes[1:, bi, ei] - boxes[0, bi, ei], dtype=np.float64)


def with_drive_past_heights(
    fit: ModelFit,
    tracks: Sequence[MatchedTrack],
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
) -> tuple[ModelFit, ModelParams]:
    """With ModelParams.try_drive_past_heights, the fit again with a height offset per drive-past
    (ModelParams.drive_past_heights), started from it, where the boxes ask for them: at least
    min_height_drive_pasts drive-pasts, the refit converged and its offsets' chi-square (one dof each)
    beyond the (1 - heights_chi2_p) quantile. Else `fit` and `params` unchanged: where the heights agree
    (the first simulator's IMU poses, post-processed tracks) the freedom would only widen the covariance
    and move the pose in a flat valley."""
    drive_pasts = len(_drive_pasts(tracks, TRAVERSAL_GAP_S)[1])
    if (
        not params.try_drive_past_heights
        or params.drive_past_heights
        or drive_pasts < params.min_height_drive_pasts
    ):
        return fit, params
    heights = replace(params, drive_past_heights=True)
    try:
        refit = fit_vehicle_model(
            fit.R_cam_from_local,
            fit.t_cam_from_local,
            tracks,
            trajectory,
            camera,
            vehicle,
            heights,
            patience=TRIAL_PATIENCE,
        )
    except DegenerateGeometry:
        return fit, params
    if not refit.converged or refit.heights_chi2() <= chi2_quantile(params.heights_chi2_p, drive_pasts):
        return fit, params
    return refit, heights


def chi2_quantile(upper: float, dof: int) -> float:
    """The value a chi-square of `dof` degrees of freedom exceeds with probability `upper` (Wilson and
    Hilferty's cube-root normal approximation: within 1 % of the exact quantile from 3 dof at p = 0.01)."""
    z = NormalDist().inv_cdf(1.0 - upper)
    a = 2.0 / (9.0 * dof)
    return float(dof * (1.0 - a + z * math.sqrt(a)) ** 3)


def cuboid_rejection(fit: ModelFit, vehicle: VehicleProfile) -> float:
    """Chi-square (6 dof) of the fitted template's departure from the profile's cuboid, against the shape
    parameters' own covariance (the marginal block of the full one): how strongly the boxes reject the
    cuboid body. 0 for a fit whose shape was held at the cuboid. The roof's raise is not counted: it is
    what the vehicle carries, not its body (and cuboid_rejection_chi2 was measured on the six)."""
    body = [i for i in range(len(SHAPE_NAMES)) if i != ROOF_RAISE_INDEX]
    departure = (fit.shape - cuboid_shape(vehicle))[body]
    block = fit.full_covariance[_SHAPE, _SHAPE][np.ix_(body, body)]
    if not np.all(np.isfinite(block)) or float(np.max(np.abs(departure))) == 0.0:
        return 0.0
    return max(float(departure @ _inverse(block) @ departure), 0.0)


def cuboid_params(params: ModelParams) -> ModelParams:
    """The same fit with the body held to the profile's cuboid and no detector convention: only pose and
    time shift free (the first simulator's world, and any detector that boxes the cuboid)."""
    return replace(
        params,
        shape_std=(_HELD,) * len(SHAPE_NAMES),
        typical_body=False,
        scale_std=_HELD,
        shift_std_px=_HELD,
        fit_shift=False,
        grow_std_px=_HELD,
    )


def holdout_error(
    left_out: LeftOut,
    trajectory: Trajectory,
    camera: CameraModel,
    vehicle: VehicleProfile,
    params: ModelParams,
) -> float:
    """Cross-validated misfit of a model class: each traversal's boxes predicted by the fit of the others,
    the median |edge residual| (px) per traversal, summed; inf with fewer than 2 traversals or when a
    left-out fit is impossible. Used to choose between model classes: a class that fits the noise of the
    traversals it saw predicts the others worse."""
    if not left_out.fits:
        return math.inf
    total = 0.0
    for loo, held_out in zip(left_out.fits, left_out.clusters, strict=True):
        if isinstance(loo, str):
            return math.inf
        total += _median_abs(predicted_residuals(loo, held_out, trajectory, camera, vehicle, params))
    return total
