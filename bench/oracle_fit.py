"""What the final fit's model does with the right tracks, the right clock and the right start.

For each camera of a simulated scene, the calibration vehicle's own detected boxes (the truth says which
they are) are fitted by `pipeline.vehicle_model.fit_trimmed` from the TRUE camera pose, with the boxes'
stamps moved by the camera's true latency: no hypotheses, no grouping, no clock search. What is left of
the pose error is what the model (body template, detector convention) and the vehicle's poses do to it.

    python -m bench.oracle_fit --presets sil-north,slope --seeds 0,1 --poses cam
    python -m bench.oracle_fit --presets sil-north --seeds 0 --poses cam --true-heights

--poses true: the simulator's noise-free poses (with pitch and roll); cam: the poses rsucal would use, from
the vehicle's CAMs (GNSS errors, no pitch or roll: pitch from the path as the pipeline takes it);
--true-heights: the CAM poses with the true heights put in (what the GNSS height costs); --hold-z-low: the
template's lower rectangle held at the road (its height is what trades with the vehicle's; the template's
prior then centred on the cuboid); --height-noise
(with --poses true): the true heights with noise added, the realistic world's vertical GNSS white noise
(`white`, 3 cm a pose) or wander (`wander`, 6 cm correlated over 60 s: sim.v2x.GnssSpec's RTK fixed
receiver), drawn from a generator seeded by the scene's seed (what height noise alone does to the pose).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pipeline.association import MatchedTrack, Trajectory
    from sim.simulate import SimulationResult


def fit_errors(
    preset: str,
    seed: int,
    poses: str,
    true_heights: bool,
    hold_z_low: bool = False,
    height_noise: str | None = None,
) -> list[dict[str, object]]:
    """One record per camera that saw the vehicle in at least 50 frames."""
    from pipeline.camera import CameraModel, rotation_angle_rad
    from pipeline.vehicle_model import ModelParams, fit_trimmed
    from sim.simulate import simulate

    sim = simulate(preset, seed)
    records: list[dict[str, object]] = []
    for camera in sim.cameras:
        case = oracle_inputs(sim, camera.camera_id, seed, poses, true_heights, height_noise)
        if case is None:
            continue
        tracks, trajectory = case
        R, t = camera.R_cam_from_local, camera.t_cam_from_local
        model = CameraModel.from_intrinsics(camera.intrinsics)
        params = ModelParams()
        if hold_z_low:  # the template's lower rectangle held at the road (1e-9 m: the pipeline's hold)
            # (a held entry stays at its prior's mean: the cuboid's, 0 m, not a typical body's 0.35 m)
            params = replace(params, typical_body=False, shape_std=(1e-9, *params.shape_std[1:]))
        fit, _ = fit_trimmed(R, t, tracks, trajectory, model, sim.vehicle, params)
        error = fit.camera_centre - (-R.T @ t)
        records.append(
            {
                "preset": preset,
                "seed": seed,
                "camera": camera.camera_id,
                "vehicle_type": sim.ground_truth[camera.camera_id].vehicle_type,
                "position_error_m": float(np.linalg.norm(error)),
                "horizontal_error_m": float(np.hypot(error[0], error[1])),
                "height_error_m": float(error[2]),
                "rotation_error_deg": math.degrees(rotation_angle_rad(fit.R_cam_from_local, R)),
                "converged": fit.converged,
            }
        )
    return records


def oracle_inputs(
    sim: SimulationResult,
    camera_id: str,
    seed: int,
    poses: str,
    true_heights: bool = False,
    height_noise: str | None = None,
) -> tuple[list[MatchedTrack], Trajectory] | None:
    """The calibration vehicle's own detected boxes in `camera_id`, one track per traversal (the truth
    says which), and the vehicle's trajectory on those boxes' clock (the true instants plus the camera's
    latency): the true poses (`poses` "true", with `height_noise` on their heights) or the CAM poses as the
    pipeline builds them (`poses` "cam", with the true heights where `true_heights`). None where the camera
    saw the vehicle in fewer than 50 frames."""
    from bench.common import inputs_for
    from pipeline.association import AssociationParams, MatchedTrack, Trajectory, make_trajectory
    from pipeline.attitude import with_path_pitch

    truth = sim.ground_truth[camera_id]
    rows = [
        (frame.stamp_ns, frame.boxes[seen.calib_box], seen.traversal)
        for frame, seen in zip(sim.detections[camera_id], truth.frames, strict=True)
        if seen.calib_box is not None
    ]
    if len(rows) < 50:
        return None
    tracks = []
    for traversal in sorted({row[2] for row in rows if row[2] is not None}):
        chosen = [row for row in rows if row[2] == traversal]
        stamps = np.array([row[0] for row in chosen], dtype=np.int64)
        boxes = np.array([[b.x1, b.y1, b.x2, b.y2] for _, b, _ in chosen], dtype=np.float64)
        tracks.append(MatchedTrack(traversal, stamps, boxes, np.zeros((len(stamps), 6))))
    true_stamps = sim.true_stamps.astype(np.int64) + truth.latency_ns
    true_poses = sim.true_poses.copy()
    if height_noise is not None:
        true_poses[:, 2] += height_errors(true_stamps, height_noise, np.random.default_rng([seed, 7]))
    trajectory = Trajectory(true_stamps, true_poses)
    if poses == "cam":
        # As the pipeline builds it (make_trajectory: sorted, on the camera clock), then on the boxes'.
        inputs = inputs_for(sim, camera_id)
        cam = make_trajectory(
            inputs.poses, sim.origin, AssociationParams(time_offset_ns=inputs.time_offset_ns)
        )
        stamps, local = cam.stamps + truth.latency_ns, cam.poses.copy()
        if true_heights:
            local[:, 2] = np.interp(
                stamps.astype(np.float64), true_stamps.astype(np.float64), sim.true_poses[:, 2]
            )
        trajectory = with_path_pitch(Trajectory(stamps, local))
    return tracks, trajectory


def height_errors(stamps_ns: np.ndarray, kind: str, rng: np.random.Generator) -> np.ndarray:
    """Height errors (m) at the stamps, as the realistic world's RTK fixed receiver makes them vertically
    (sim.v2x.GnssSpec, its horizontal sigmas times vertical_factor): `white` independent per stamp, or
    `wander` its first-order Gauss-Markov process."""
    from sim.v2x import GnssSpec, gauss_markov

    spec = GnssSpec.rtk_fixed()
    if kind == "white":
        return rng.normal(0.0, spec.white_sigma_m * spec.vertical_factor, len(stamps_ns))
    t_s = (stamps_ns - stamps_ns[0]).astype(np.float64) / 1e9
    sigma = spec.wander_sigma_m * spec.vertical_factor
    return np.asarray(gauss_markov(t_s, sigma, spec.wander_tau_s, 1, rng)[:, 0], dtype=np.float64)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.oracle_fit", description=__doc__.split("\n\n")[0])
    parser.add_argument("--presets", default="sil-north,sil-south,sil-west,slope,van")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--poses", choices=("true", "cam"), default="cam")
    parser.add_argument("--true-heights", action="store_true", help="--poses cam with the true heights")
    parser.add_argument("--hold-z-low", action="store_true", help="the template's lower rectangle at 0 m")
    parser.add_argument(
        "--height-noise", choices=("white", "wander"), help="--poses true: noise on the heights"
    )
    args = parser.parse_args(argv)
    if args.height_noise and args.poses != "true":
        parser.error("--height-noise goes with --poses true")
    records = [
        record
        for preset in args.presets.split(",")
        for seed in (int(s) for s in args.seeds.split(","))
        for record in fit_errors(
            preset, seed, args.poses, args.true_heights, args.hold_z_low, args.height_noise
        )
    ]
    for r in records:
        print(
            f"{r['preset']:14s} {r['seed']:3d} {r['camera']:14s} {r['vehicle_type']:10s} "
            f"pos {r['position_error_m']:.3f} m  horizontal {r['horizontal_error_m']:.3f} m  "
            f"height {r['height_error_m']:+.3f} m  rot {r['rotation_error_deg']:.3f} deg"
            + ("" if r["converged"] else "  (not converged)")
        )
    if records:
        position = np.array([r["position_error_m"] for r in records], dtype=np.float64)
        height = np.array([r["height_error_m"] for r in records], dtype=np.float64)
        print(
            f"{len(records)} cameras: position median {np.median(position):.3f} m, mean "
            f"{position.mean():.3f} m; height error mean {height.mean():+.3f} m"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
