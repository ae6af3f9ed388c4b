"""What fitting a junction's cameras together would give, on the oracle's tracks and clock.

rsucal fits each camera alone. On a camera looking along a road (sil-west's `west-arm`), drive-pasts in
lanes a few metres apart whose GNSS heights wandered apart by centimetres look like a roll of the camera,
and the Cramer-Rao bound (`bench.bound --joint`, docs/method.md) says a second camera that sees the same
drive-pasts (the junction's, which sees the vehicle turn) would fix those heights. This measures what
rsucal's own model makes of that: for each scene with two or more cameras, each camera's pose fitted
(`pipeline.vehicle_model`, from the true pose, with the truth's own tracks on the true clock, as
bench.oracle_fit does) alone, alone with a height per drive-past (`ModelParams.drive_past_heights`), and
all the scene's cameras in one fit: each camera its own pose, clock, detector convention and readout; the
vehicle's height on each drive-past (matched across cameras by time) shared, and with --share-shape its
template too.

    python -m bench.joint_fit --presets sil-west,suv --seeds 0-9

The stds printed are the fits' own: for the fits alone ModelFit.covariance (a sandwich, with the common GNSS
offset), for the joint fit the classical covariance of its robust weighted least squares with the common GNSS
offset. Neither has the consider parts (the body the template cannot describe, each drive-past's GNSS) or the
drive-pasts' scatter that the pipeline's final fit adds: they are less than what the pipeline would report,
and a count "within both 3-std gates" on them is an upper bound.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import least_squares

from pipeline.arrays import FloatArray
from pipeline.camera import CameraModel, rotation_angle_rad
from pipeline.refinement import _pose_from_params

# With the model's internals: this measures a fit the pipeline does not make yet, from the same residuals.
from pipeline.vehicle_model import (
    _BIAS,
    _DELTA,
    _POSE,
    _READOUT,
    _SHAPE,
    N_PARAMS,
    TRAVERSAL_GAP_S,
    ModelFit,
    ModelParams,
    _Model,
    fit_trimmed,
    largest_stds,
    shape_prior,
    start_model,
)

SHAPE_ROWS = list(range(_SHAPE.start, _SHAPE.stop))

if TYPE_CHECKING:
    from pipeline.association import MatchedTrack, Trajectory
    from schemas.common import VehicleProfile


@dataclass(frozen=True)
class CameraCase:
    """One camera's data for a joint fit, and its start (its own fit)."""

    camera_id: str
    tracks: list[MatchedTrack]
    trajectory: Trajectory  # on this camera's boxes' clock
    camera: CameraModel
    latency_ns: int  # the boxes' clock less the vehicle's: drive-pasts are matched on the vehicle's
    start: ModelFit


@dataclass(frozen=True)
class JointPose:
    """One camera's pose from the joint fit."""

    R_cam_from_local: FloatArray
    camera_centre: FloatArray
    position_std_m: float  # classical, with the common GNSS offset
    rotation_std_deg: float
    height_offsets_m: FloatArray  # the shared heights of this camera's drive-pasts


def drive_past_groups(spans_ns: Sequence[np.ndarray], gap_s: float = TRAVERSAL_GAP_S) -> list[np.ndarray]:
    """Each camera's drive-pasts (spans (K_i, 2) on a common clock) mapped to shared ones: spans within
    `gap_s` of each other are the same drive-past seen by two cameras. Returns per camera the shared
    index (K_i,) of each of its drive-pasts, shared indices in time order."""
    rows = [(int(a), int(b), i, k) for i, spans in enumerate(spans_ns) for k, (a, b) in enumerate(spans)]
    rows.sort()
    gap = int(gap_s * 1e9)
    shared = [np.zeros(len(spans), dtype=np.int64) for spans in spans_ns]
    group, end = -1, None
    for a, b, i, k in rows:
        if end is None or a > end + gap:
            group += 1
            end = b
        end = max(end, b)
        shared[i][k] = group
    return shared


def fit_together(
    cases: Sequence[CameraCase], vehicle: VehicleProfile, params: ModelParams, share_shape: bool = False
) -> list[JointPose]:
    """All cameras in one robust least-squares fit (see the module): the parameter vector is the shared
    part (the template with `share_shape`, then a height per shared drive-past) and each camera's own
    parameters; each camera's `_Model` gives its residuals and Jacobian at its part, with the shared
    priors counted once."""
    heights = replace(params, drive_past_heights=True)
    models: list[_Model] = []
    starts: list[FloatArray] = []
    shared = ("shape", "heights") if share_shape else ("heights",)
    for case in cases:
        R0, C0 = case.start.R_cam_from_local, case.start.camera_centre
        model, mean = start_model(R0, C0, case.tracks, case.trajectory, case.camera, vehicle, heights, shared)
        x = mean.copy()
        x[_DELTA], x[_SHAPE] = case.start.time_shift_s, case.start.shape
        x[_BIAS], x[_READOUT] = case.start.bias, case.start.readout_s
        model.set_skew(x)
        model.weigh(x)
        models.append(model)
        starts.append(x)
    groups = drive_past_groups(
        [m.data.drive_past_spans_ns - case.latency_ns for m, case in zip(models, cases, strict=True)]
    )
    shared_heights = max(int(g.max()) + 1 if len(g) else 0 for g in groups)
    own = [i for i in range(N_PARAMS) if not (share_shape and _SHAPE.start <= i < _SHAPE.stop)]
    n_shared = (len(SHAPE_ROWS) if share_shape else 0) + shared_heights
    size = n_shared + len(own) * len(cases)
    maps: list[FloatArray] = []  # x_i = M_i z
    z = np.zeros(size)
    shape_mean, shape_std = shape_prior(heights, vehicle)
    if share_shape:
        z[: len(SHAPE_ROWS)] = cases[0].start.shape
    for i, x in enumerate(starts):
        M = np.zeros((len(x), size))
        first = n_shared + i * len(own)
        M[own, range(first, first + len(own))] = 1.0
        if share_shape:
            M[SHAPE_ROWS, range(len(SHAPE_ROWS))] = 1.0
        offset = len(SHAPE_ROWS) if share_shape else 0
        M[range(N_PARAMS, len(x)), offset + groups[i]] = 1.0
        z[first : first + len(own)] = x[own]
        maps.append(M)
    prior_mean = np.zeros(n_shared)
    prior_std = np.full(n_shared, heights.drive_past_height_std_m)
    if share_shape:
        prior_mean[: len(SHAPE_ROWS)], prior_std[: len(SHAPE_ROWS)] = shape_mean, shape_std

    def residuals(v: FloatArray) -> FloatArray:
        own_rows = [m.residuals(M @ v) for m, M in zip(models, maps, strict=True)]
        return np.concatenate([*own_rows, (v[:n_shared] - prior_mean) / prior_std])

    def jacobian(v: FloatArray) -> FloatArray:
        own_rows = [m.jacobian(M @ v) @ M for m, M in zip(models, maps, strict=True)]
        prior_rows = np.zeros((n_shared, size))
        prior_rows[range(n_shared), range(n_shared)] = 1.0 / prior_std
        return np.vstack([*own_rows, prior_rows])

    f = np.concatenate(
        [np.full(len(m.residuals(x)), m.f_scale) for m, x in zip(models, starts, strict=True)]
        + [np.full(n_shared, math.inf)]
    )
    solution = least_squares(
        residuals, z, jac=jacobian, method="trf", loss=_huber(f), f_scale=1.0, x_scale="jac", max_nfev=100
    )
    v = solution.x
    r, J = residuals(v), jacobian(v)
    weights = np.where(np.abs(r) <= f, 1.0, f / np.maximum(np.abs(r), 1e-300))
    covariance = np.linalg.pinv(J.T @ (weights[:, None] * J))
    poses = []
    for model, M in zip(models, maps, strict=True):
        x = M @ v
        R, C = _pose_from_params(x[_POSE], model.R0, model.C0)
        columns = [int(np.flatnonzero(M[row])[0]) for row in range(6)]
        pose_covariance = np.asarray(covariance[np.ix_(columns, columns)], dtype=np.float64)
        pose_covariance[3:, 3:] += params.gnss_covariance()
        position_std, rotation_std = largest_stds(pose_covariance)
        poses.append(JointPose(R, C, position_std, rotation_std, x[N_PARAMS:].copy()))
    return poses


def _huber(f: FloatArray) -> Callable[[FloatArray], FloatArray]:
    """scipy's Huber loss with a bend of its own per row (`f`, in the rows' units; inf: quadratic):
    rho_i(z) = f_i^2 rho(z / f_i^2) for z = r^2, with scipy's f_scale at 1. The cameras' rows bend where
    each camera's own fit bends them (`_Model.weigh`)."""
    f2 = f * f

    def loss(z: FloatArray) -> FloatArray:
        u = z / f2
        outer = u > 1.0
        root = np.sqrt(np.where(outer, u, 1.0))
        rho = np.where(outer, f2 * (2.0 * root - 1.0), z)
        first = np.where(outer, 1.0 / root, 1.0)
        second = np.where(outer, -0.5 / (root**3 * np.where(np.isfinite(f2), f2, 1.0)), 0.0)
        return np.vstack([rho, first, second])

    return loss


def _errors(R: FloatArray, C: FloatArray, R_true: FloatArray, C_true: FloatArray) -> tuple[float, float]:
    return float(np.linalg.norm(C - C_true)), math.degrees(rotation_angle_rad(R, R_true))


def scene(
    preset: str, seed: int, poses: str, share_shape: bool
) -> list[dict[str, tuple[float, float, float, float]]]:
    """Per camera of the scene (two or more that saw the vehicle; else none): the pose's (position error m,
    rotation error deg, position std m, rotation std deg) alone, alone with drive-past heights, and joint."""
    from bench.oracle_fit import oracle_inputs
    from sim.simulate import simulate

    sim = simulate(preset, seed)
    params = ModelParams()
    cases, truths, rows = [], [], []
    for camera in sim.cameras:
        inputs = oracle_inputs(sim, camera.camera_id, seed, poses)
        if inputs is None:
            continue
        tracks, trajectory = inputs
        R, t = camera.R_cam_from_local, camera.t_cam_from_local
        model = CameraModel.from_intrinsics(camera.intrinsics)
        alone, used = fit_trimmed(R, t, tracks, trajectory, model, sim.vehicle, params)
        with_heights, _ = fit_trimmed(
            R, t, tracks, trajectory, model, sim.vehicle, replace(params, drive_past_heights=True)
        )
        C = -R.T @ t
        latency = sim.ground_truth[camera.camera_id].latency_ns
        cases.append(CameraCase(camera.camera_id, used, trajectory, model, latency, alone))
        truths.append((R, C))
        rows.append(
            {
                "camera": camera.camera_id,
                **{
                    name: (
                        *_errors(fit.R_cam_from_local, fit.camera_centre, R, C),
                        *largest_stds(fit.covariance),
                    )
                    for name, fit in (("alone", alone), ("heights", with_heights))
                },
            }
        )
    if len(cases) < 2:
        return []
    for row, pose, (R, C) in zip(
        rows, fit_together(cases, sim.vehicle, params, share_shape), truths, strict=True
    ):
        row["joint"] = (
            *_errors(pose.R_cam_from_local, pose.camera_centre, R, C),
            pose.position_std_m,
            pose.rotation_std_deg,
        )
    return rows  # type: ignore[return-value]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.joint_fit", description=__doc__.split("\n\n")[0])
    parser.add_argument("--presets", default="sil-west,suv")
    parser.add_argument("--seeds", default="0-4", help="a range a-b or a list a,b,c")
    parser.add_argument("--poses", choices=("true", "cam"), default="cam")
    parser.add_argument("--share-shape", action="store_true", help="the template shared too")
    args = parser.parse_args(argv)
    if "-" in args.seeds:
        first, last = (int(s) for s in args.seeds.split("-"))
        seeds = list(range(first, last + 1))
    else:
        seeds = [int(s) for s in args.seeds.split(",")]
    variants = ("alone", "heights", "joint")
    found: dict[str, list[tuple[float, float, float, float]]] = {name: [] for name in variants}
    for preset in args.presets.split(","):
        for seed in seeds:
            for row in scene(preset, seed, args.poses, args.share_shape):
                print(
                    f"{preset:12s} {seed:3d} {row['camera']:14s} "
                    + "  ".join(
                        f"{name} {row[name][0]:.3f} m {row[name][1]:.3f} deg (std {row[name][2]:.3f} m "
                        f"{row[name][3]:.3f} deg)"
                        for name in variants
                    ),
                    flush=True,
                )
                for name in variants:
                    found[name].append(row[name])
    for name in variants:
        a = np.array(found[name]).reshape(-1, 4)
        if len(a) == 0:
            continue
        inside = (3 * a[:, 2] <= 0.5) & (3 * a[:, 3] <= 0.5)
        beyond = inside & ((a[:, 0] > 3 * a[:, 2]) | (a[:, 1] > 3 * a[:, 3]))
        print(
            f"{name:8s} {len(a)} cameras: error median {np.median(a[:, 0]):.3f} m / "
            f"{np.median(a[:, 1]):.3f} deg (max {a[:, 0].max():.3f} m / {a[:, 1].max():.3f} deg), std "
            f"median {np.median(a[:, 2]):.3f} m / {np.median(a[:, 3]):.3f} deg, within both 3-std gates "
            f"{int(inside.sum())}, of them beyond 3 std {int(beyond.sum())}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
