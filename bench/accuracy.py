"""Accuracy benchmark: every simulator preset (but `long`) over seeds, calibrate() on every camera, scored
against the ground truth, beside the paper's figures and our targets. Not part of the test suite.

    python -m bench.accuracy [--seeds 10] [--presets a,b,...] [--ideal] [--readout MS] [--latency MS]
                             [--routes-times K] [--jobs 2] [--json out.json]

The world is the simulator's real one (shaped bodies, a biased detector, unknown latency, rolling shutters,
CAM V2X) unless `--ideal` asks for the first simulator's world (cuboid boxes, no latency, global shutters,
IMU poses as V2X). `--readout MS` gives every camera that rolling-shutter readout in either world,
`--latency MS` that latency (detection stamp minus exposure, unknown to rsucal; negative: a camera clock
ahead of the vehicle's) instead of the world's.

Per (preset, seed): simulate(preset, seed), then calibrate() for every camera with the true clock offset as
the known `time_offset_ns`, and evaluate_against_ground_truth() of the result (accepted results count) and of
the true calibration itself (result_from_ground_truth: the floor the box noise sets on delta_p).

Columns (aggregated per preset over all cameras and seeds):
  acc/runs   accepted results / calibrate() runs
  dp m/w     delta_p: mean over accepted runs of each run's mean / of each run's max (m)  [paper delta_p,m/w]
  e m/w      the same for e (%)                                                       [paper e_m / e_w]
  pos, rot   camera-centre and rotation error vs the truth: mean / max over accepted runs (m, deg)
  ref        refused runs;  FA  false accepts: accepted with position error > 0.5 m or rotation > 0.5 deg
  err        runs that raised;  t  median calibrate() seconds per camera
  floor      the true calibration on the same boxes: delta_p mean (m) / e_m (%), mean over all runs
  cover      accepted runs whose position or rotation error exceeds 3 x the reported std / accepted runs
  lat ms     the cameras' true latency (detection stamp minus exposure), mean over runs (unknown to rsucal)
  lat err    accepted runs: |estimated time offset - true one| (ms), mean / max (the truth: vehicle clock
             offset minus the latency, plus half the readout: the image's middle row's); target within 10 ms
  area       the calibration vehicle's detected box area / its data-sheet cuboid's rectangle, mean over
             frames where the cuboid lies wholly inside the image and the box is no merge or split
  pos std from  runs refused on their position std, by its largest share (validation.STD_SOURCES): b the
             body shape the template cannot describe, d the drive-pasts' disagreement, f the fit, g GNSS,
             r a rolling-shutter readout held at 0
Under the table: how many of all poses within 1 m / 1 deg (accepted or refused) lie beyond 3 of their
reported stds, in position, rotation and time offset; and the whole pose error in the whole reported
covariance (a chi-square of 6 dof where the covariance is honest: median 5.35, above 20.1 in 0.27 %), which
also sees a covariance too large (a median far below 5.35) that the 3-std count cannot.
Exit code 0 when every target passes, 1 otherwise. Per-run failures are printed under the table.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench.common import inputs_for, limit_threads, tree_state

if TYPE_CHECKING:
    from sim.presets import ScenarioConfig

FALSE_ACCEPT_POSITION_M = 0.5
FALSE_ACCEPT_ROTATION_DEG = 0.5
EXCLUDED_PRESETS = ("long",)

# Paper figures: Table I (delta_p,m m, delta_p,w m, e_m %, e_w %), Table III (noise on SIL-South: e_m, e_w).
PAPER: dict[str, str] = {
    "sil-north": "dp .36/1.52 e .83/2.80",
    "sil-south": "dp .54/.86 e 1.39/2.22",
    "sil-west": "dp .06/.40 e .22/1.80",
    "carla-like": "dp .087/.237 e .17/.68",
    "noise-0.2": "e 2.22/11.32 (T.III)",
    "noise-0.5": "e 2.30/12.36 (T.III)",
}

Run = dict[str, Any]
# (preset or a scene of its own, seed, ideal world, readout s, latency s): one run_seed call
Task = tuple["str | ScenarioConfig", int, bool, float | None, float | None]


# ------------------------------------------------------------------------------------------------ targets


@dataclass(frozen=True)
class Target:
    """A preset's target: `text` for the table, `failures(runs)` -> why it fails (empty: PASS), and
    `run_problem(run)` -> why one run counts against it (None: fine), for the listing under the table."""

    text: str
    failures: Callable[[Sequence[Run]], list[str]]
    run_problem: Callable[[Run], str | None]
    over_accepted: bool = False  # judged on the accepted runs only (the table then counts the others)


def _is_accepted(run: Run) -> bool:
    return bool(run["verdict"] == "accepted")


def is_false_accept(run: Run) -> bool:
    return _is_accepted(run) and (
        run["position_error_m"] is None
        or run["position_error_m"] > FALSE_ACCEPT_POSITION_M
        or run["rotation_error_deg"] > FALSE_ACCEPT_ROTATION_DEG
    )


def _mean(values: Sequence[float | None]) -> float | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return statistics.fmean(finite) if finite else None


def _max(values: Sequence[float | None]) -> float | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return max(finite) if finite else None


@dataclass(frozen=True)
class Limits:
    """Accuracy limits on the preset's aggregates over accepted runs (None: not limited)."""

    dp_mean_m: float | None = None  # mean over accepted runs of each run's delta_p mean
    e_mean_pct: float | None = None  # ... of each run's e_m
    e_max_pct: float | None = None  # ... of each run's e_w
    position_m: float | None = None  # worst accepted run
    rotation_deg: float | None = None  # worst accepted run

    def items(self) -> list[tuple[str, str, str, float]]:
        """(label, run key, aggregate, limit) of the limits that are set."""
        table = [
            ("dp", "delta_p_mean_m", "mean", self.dp_mean_m),
            ("e_m", "e_mean_pct", "mean", self.e_mean_pct),
            ("e_w", "e_max_pct", "mean", self.e_max_pct),
            ("pos", "position_error_m", "max", self.position_m),
            ("rot", "rotation_error_deg", "max", self.rotation_deg),
        ]
        return [(label, key, how, limit) for label, key, how, limit in table if limit is not None]


def accuracy_target(limits: Limits) -> Target:
    """Accuracy on the accepted runs (at least one run must be accepted)."""
    units = {"dp": "m", "e_m": "%", "e_w": "%", "pos": "m", "rot": "deg"}
    text = " ".join(f"{label}<={limit:g}{units[label]}" for label, _, _, limit in limits.items())

    def failures(runs: Sequence[Run]) -> list[str]:
        accepted = [r for r in runs if _is_accepted(r)]
        if not accepted:
            return ["no run accepted"]
        out = []
        for label, key, how, limit in limits.items():
            value = (_mean if how == "mean" else _max)([r[key] for r in accepted])
            if value is None or value > limit:
                shown = "n/a" if value is None else f"{value:.4g}"
                out.append(f"{label} ({how} over accepted) = {shown} > {limit:g}")
        return out

    def run_problem(run: Run) -> str | None:
        if not _is_accepted(run):
            return "refused (expected accepted)"
        over = [
            f"{label} {run[key]:.4g} > {limit:g}"
            for label, key, _, limit in limits.items()
            if run[key] is None or run[key] > limit
        ]
        return "above the limit: " + ", ".join(over) if over else None

    return Target(text, failures, run_problem, over_accepted=True)


def success_target(min_rate: float, dp_mean_m: float) -> Target:
    """Accepted with delta_p mean <= dp_mean_m (and no false accept) on >= min_rate of the runs."""

    def succeeded(run: Run) -> bool:
        return (
            _is_accepted(run)
            and not is_false_accept(run)
            and run["delta_p_mean_m"] is not None
            and run["delta_p_mean_m"] <= dp_mean_m
        )

    def failures(runs: Sequence[Run]) -> list[str]:
        rate = sum(succeeded(r) for r in runs) / max(len(runs), 1)
        return [] if rate >= min_rate else [f"success {100 * rate:.0f} % < {100 * min_rate:.0f} %"]

    def run_problem(run: Run) -> str | None:
        if not _is_accepted(run):
            return "refused (expected accepted)"
        if is_false_accept(run):
            return "false accept"
        if run["delta_p_mean_m"] is None or run["delta_p_mean_m"] > dp_mean_m:
            return f"delta_p mean {run['delta_p_mean_m']} > {dp_mean_m} m"
        return None

    return Target(f"succ>={100 * min_rate:g}% dp<={dp_mean_m:g}m", failures, run_problem)


def correct_or_refused_target() -> Target:
    def run_problem(run: Run) -> str | None:
        return "accepted but wrong (> 0.5 m or > 0.5 deg)" if is_false_accept(run) else None

    def failures(runs: Sequence[Run]) -> list[str]:
        bad = sum(run_problem(r) is not None for r in runs)
        return [f"{bad} run(s) accepted a wrong calibration"] if bad else []

    return Target("right(0.5m,0.5deg) or refused 100%", failures, run_problem)


def refused_target() -> Target:
    def run_problem(run: Run) -> str | None:
        return "accepted (expected refused)" if _is_accepted(run) else None

    def failures(runs: Sequence[Run]) -> list[str]:
        bad = sum(run_problem(r) is not None for r in runs)
        return [f"{bad} run(s) accepted"] if bad else []

    return Target("refused 100%", failures, run_problem)


SIL_LIMITS = Limits(dp_mean_m=0.25, e_mean_pct=0.8)
TARGETS: dict[str, Target] = {
    "carla-like": accuracy_target(Limits(dp_mean_m=0.03, e_max_pct=0.4, position_m=0.1, rotation_deg=0.1)),
    "sil-north": accuracy_target(SIL_LIMITS),
    "sil-south": accuracy_target(SIL_LIMITS),
    "sil-west": accuracy_target(SIL_LIMITS),
    # sil-north with a 150 ms vehicle clock offset, known here: the sil target is the natural one.
    "clock-offset": accuracy_target(SIL_LIMITS),
    "noise-0.5": accuracy_target(Limits(e_mean_pct=1.5)),
    "dense-traffic": success_target(0.98, 0.3),
    "occluded": success_target(0.98, 0.3),
    "slope": success_target(0.98, 0.3),
    "v2x-10hz": success_target(0.98, 0.3),
    "wide-distorted": accuracy_target(Limits(dp_mean_m=0.25, position_m=0.3)),
    "collinear": correct_or_refused_target(),
    "single-traversal": refused_target(),
    "no-target": refused_target(),
}


# ------------------------------------------------------------------------------------------------- worker


def _track_purity(sim: Any, camera_id: str, params: Any) -> dict[int, tuple[int, float]]:
    """Image track id -> (boxes, share of them that are the calibration vehicle's, per the truth): the
    tracks calibrate() builds, rebuilt with the same (deterministic) tracker."""
    import numpy as np

    from pipeline.tracking import frames_from_detections, track_boxes

    camera = next(c for c in sim.cameras if c.camera_id == camera_id)
    truth = sim.ground_truth[camera_id]
    calib_box = {f.stamp_ns: f.box for f in truth.frames if f.calib_box is not None and f.box is not None}
    frames = frames_from_detections(sim.detections[camera_id])
    tracks = track_boxes(frames, camera.intrinsics.width, camera.intrinsics.height, params.tracking)
    out: dict[int, tuple[int, float]] = {}
    for track in tracks.tracks:
        hits = 0
        for stamp, box in zip(track.stamps, track.boxes, strict=True):
            truth_box = calib_box.get(int(stamp))
            hits += truth_box is not None and bool(np.allclose(box, truth_box, atol=1e-6))
        out[track.track_id] = (len(track.stamps), hits / max(len(track.stamps), 1))
    return out


def _group_purity(track_ids: Sequence[int], purity: dict[int, tuple[int, float]]) -> float:
    boxes = sum(purity.get(i, (0, 0.0))[0] for i in track_ids)
    calib = sum(n * share for n, share in (purity.get(i, (0, 0.0)) for i in track_ids))
    return calib / boxes if boxes else 0.0


def _evaluation_fields(evaluation: Any, prefix: str = "") -> dict[str, Any]:
    return {
        f"{prefix}delta_p_mean_m": evaluation.delta_p_mean_m,
        f"{prefix}delta_p_max_m": evaluation.delta_p_max_m,
        f"{prefix}e_mean_pct": evaluation.e_mean_pct,
        f"{prefix}e_max_pct": evaluation.e_max_pct,
    }


@contextmanager
def _stage_spy() -> Iterator[dict[str, tuple[tuple[Any, ...], Any]]]:
    """Keep the arguments and outputs of calibrate()'s stage calls (diagnosis only): the functions are
    wrapped in pipeline.calibrate's namespace for the duration and restored after."""
    import pipeline.calibrate as module

    seen: dict[str, tuple[tuple[Any, ...], Any]] = {}
    originals = {
        name: getattr(module, name)
        for name in ("make_trajectory", "match_tracks", "create_hypotheses", "group_hypotheses")
        if hasattr(module, name)
    }

    def wrap(name: str, original: Callable[..., Any]) -> Callable[..., Any]:
        def spy(*args: Any, **kwargs: Any) -> Any:
            out = original(*args, **kwargs)
            seen[name] = (args, out)
            return out

        return spy

    for name, original in originals.items():
        setattr(module, name, wrap(name, original))
    try:
        yield seen
    finally:
        for name, original in originals.items():
            setattr(module, name, original)


def _calib_track_fates(
    seen: dict[str, tuple[tuple[Any, ...], Any]], purity: dict[int, tuple[int, float]], truth: Any
) -> list[str]:
    """What became of each track that is mostly the calibration vehicle: no poses, hypothesis rejected
    (why), or its hypothesis' pose error vs the truth and its group (or why it was left out)."""
    import numpy as np

    from pipeline.camera import rotation_angle_rad

    matched = {m.track_id for m in seen["match_tracks"][1]} if "match_tracks" in seen else set()
    origin = seen["make_trajectory"][0][1] if "make_trajectory" in seen else None
    hypotheses = seen["create_hypotheses"][1] if "create_hypotheses" in seen else None
    grouping = seen["group_hypotheses"][1] if "group_hypotheses" in seen else None
    by_id = {h.track_id: h for h in hypotheses.hypotheses} if hypotheses is not None else {}
    truth_centre = np.asarray(truth.camera_position_utm)
    fates = []
    for track_id, (boxes, share) in sorted(purity.items()):
        if share < 0.5:
            continue
        head = f"t{track_id} ({boxes} boxes, {100 * share:.0f} % calib)"
        if track_id not in matched:
            fates.append(f"{head}: no poses in time (association)")
        elif hypotheses is not None and track_id in hypotheses.rejected:
            fates.append(f"{head}: hypothesis rejected: {hypotheses.rejected[track_id]}")
        elif track_id in by_id and origin is not None:
            h = by_id[track_id]
            centre = h.camera_centre + np.array([origin.x, origin.y, origin.z])
            angle = math.degrees(rotation_angle_rad(h.R_cam_from_local, np.asarray(truth.R)))
            where = "not grouped"
            if grouping is not None:
                groups = [i for i, g in enumerate(grouping.groups) if track_id in g.track_ids]
                where = (
                    f"group {groups[0]}" if groups else f"left out: {grouping.discarded.get(track_id, '?')}"
                )
            fates.append(
                f"{head}: hypothesis off by {np.linalg.norm(centre - truth_centre):.2f} m / {angle:.2f} deg, "
                f"{where}"
            )
        else:
            fates.append(f"{head}: never reached the hypotheses")
    return fates


def box_area_ratio(truth: Any) -> float | None:
    """Mean detected-box area over data-sheet-cuboid-rectangle area of the calibration vehicle (frames with
    the cuboid wholly inside the image and no gross error); None without such frames."""
    width, height = truth.intrinsics.width, truth.intrinsics.height
    ratios = []
    for f in truth.frames:
        if f.box is None or f.cuboid_box is None or f.gross_error is not None:
            continue
        x1, y1, x2, y2 = f.cuboid_box
        if x1 < 0 or y1 < 0 or x2 > width or y2 > height:
            continue
        b = f.box
        ratios.append((b[2] - b[0]) * (b[3] - b[1]) / max((x2 - x1) * (y2 - y1), 1e-9))
    return statistics.fmean(ratios) if ratios else None


def beyond_reported(run: Run, sigmas: float = 3.0) -> bool:
    """An accepted run whose camera position or rotation error exceeds `sigmas` x its reported std."""
    position_std, rotation_std = run.get("position_std_m"), run.get("rotation_std_deg")
    if position_std is None or rotation_std is None or run.get("position_error_m") is None:
        return True
    return bool(
        run["position_error_m"] > sigmas * position_std or run["rotation_error_deg"] > sigmas * rotation_std
    )


def std_source(run: Run) -> str | None:
    """The largest share (validation.STD_SOURCES) of the position std a run was refused on, '?' when its
    reason does not say, None when it was not refused on it."""
    from pipeline.validation import STD_SOURCES

    for reason in run.get("reasons", []):
        if reason.startswith("position std"):
            return next((name for name, text in STD_SOURCES.items() if f"mostly from {text}" in reason), "?")
    return None


_SOURCE_TAGS = {"body": "b", "drive-pasts": "d", "fit": "f", "gnss": "g", "readout": "r", "?": "?"}


def near_poses(runs: Sequence[Run]) -> list[Run]:
    """The runs, accepted or refused, that reached a pose within 1 m and 1 deg of the truth and reported its
    std."""
    return [
        r
        for r in runs
        if r.get("position_error_m") is not None
        and r.get("position_std_m") is not None
        and r["position_error_m"] <= 1.0
        and r["rotation_error_deg"] <= 1.0
    ]


def coverage_line(runs: Sequence[Run], sigmas: float = 3.0) -> str:
    """How honest the reported stds are over every pose within 1 m and 1 deg of the truth, accepted or
    refused (the table's `cover` counts accepted runs only, which are few where most are refused): how many
    lie beyond `sigmas` x their std in position, rotation and time offset."""
    posed = near_poses(runs)
    position = sum(r["position_error_m"] > sigmas * r["position_std_m"] for r in posed)
    rotation = sum(r["rotation_error_deg"] > sigmas * r["rotation_std_deg"] for r in posed)
    timed = [r for r in posed if r.get("time_offset_std_ms") and r.get("time_offset_error_ms") is not None]
    clock = sum(abs(r["time_offset_error_ms"]) > sigmas * r["time_offset_std_ms"] for r in timed)
    return (
        f"uncertainty over the {len(posed)} poses within 1 m / 1 deg (accepted or refused): beyond "
        f"{sigmas:g} std in position {position}, in rotation {rotation}, in time offset {clock} of "
        f"{len(timed)}; {chi2_line(posed)}"
    )


def chi2_line(posed: Sequence[Run]) -> str:
    """The whole pose error against the whole reported covariance (metrics.Evaluation.pose_chi2): the
    largest-std test above passes a covariance several times too large, or one too small across its long
    axis; this one sees both. An honest covariance gives a chi-square of 6 dof."""
    from pipeline.metrics import POSE_CHI2_3SIGMA, POSE_CHI2_MEDIAN

    values = [r["pose_chi2"] for r in posed if r.get("pose_chi2") is not None]
    if not values:
        return "error / covariance: -"
    beyond = sum(v > POSE_CHI2_3SIGMA for v in values)
    return (
        f"error / covariance (chi-square, 6 dof) median {statistics.median(values):.2f} (honest "
        f"{POSE_CHI2_MEDIAN:.2f}), above {POSE_CHI2_3SIGMA:.1f} {beyond} of {len(values)} (honest 0.27 %)"
    )


def run_seed(task: Task) -> list[Run]:
    """simulate(preset, seed), calibrate() every camera, evaluate: one record per camera. The preset may
    be a ScenarioConfig of its own (bench.unseen's drawn scenes)."""
    import numpy as np

    from pipeline.calibrate import PipelineParams, calibrate
    from pipeline.metrics import evaluate_against_ground_truth, result_from_ground_truth, true_time_offset_ns
    from sim.simulate import simulate

    preset, seed, ideal, readout_s, latency_s = task
    name = preset if isinstance(preset, str) else preset.name
    base: Run = {"preset": name, "seed": seed, "ideal": ideal}
    try:
        started = time.perf_counter()
        sim = simulate(preset, seed, ideal=ideal, readout_s=readout_s, latency_s=latency_s)
        simulate_s = time.perf_counter() - started
    except Exception as err:
        return [{**base, "camera": "*", "verdict": "error", "error": _describe(err), "reasons": []}]
    params = PipelineParams()
    runs: list[Run] = []
    for index, camera in enumerate(sim.cameras):
        camera_id = camera.camera_id
        truth = sim.ground_truth[camera_id]
        run: Run = {
            **base,
            "camera": camera_id,
            "simulate_s": simulate_s,
            "truth_traversals": truth.traversals,
            "truth_boxes": sum(f.calib_box is not None for f in truth.frames),
            "latency_ms": truth.latency_ns / 1e6,
            "readout_ms": truth.readout_ns / 1e6,
            # The offset of the image's middle row (the result's convention): with a rolling shutter it is
            # exposed half the readout after the first row, whose time the stamp minus the latency is.
            "true_time_offset_ms": true_time_offset_ns(truth) / 1e6,
            "vehicle_type": truth.vehicle_type,
            "box_area_ratio": box_area_ratio(truth),
        }
        try:
            floor = evaluate_against_ground_truth(result_from_ground_truth(truth, sim.rsu_id), truth)
            run.update(_evaluation_fields(floor, "floor_"))
            with _stage_spy() as seen:
                started = time.perf_counter()
                outcome = calibrate(
                    inputs_for(sim, camera_id),
                    params,
                    np.random.default_rng([seed, index]),
                    created_at_ns=time.time_ns(),
                )
                run["seconds"] = time.perf_counter() - started
            result = outcome.result
            evaluation = evaluate_against_ground_truth(result, truth)
            run.update(
                verdict=result.verdict.status,
                reasons=list(result.verdict.reasons),
                position_error_m=evaluation.position_error_m,
                horizontal_error_m=evaluation.horizontal_error_m,
                height_error_m=evaluation.height_error_m,
                rotation_error_deg=evaluation.rotation_error_deg,
                pose_chi2=evaluation.pose_chi2,
                position_std_m=result.uncertainty.position_std_m if result.uncertainty else None,
                rotation_std_deg=result.uncertainty.rotation_std_deg if result.uncertainty else None,
                time_offset_ms=None if result.time_offset_ns is None else result.time_offset_ns / 1e6,
                time_offset_std_ms=None
                if result.time_offset_std_ns is None
                else result.time_offset_std_ns / 1e6,
                time_offset_error_ms=(
                    None
                    if result.time_offset_ns is None
                    else abs(result.time_offset_ns - true_time_offset_ns(truth)) / 1e6
                ),
                boxes_used=evaluation.boxes_used,
                boxes_total=evaluation.boxes_total,
                **_evaluation_fields(evaluation),
            )
            run["stages"] = [
                f"{s.stage}: kept {s.kept}, discarded {s.discarded}"
                + (f" ({'; '.join(s.lines())})" if s.lines() else "")
                for s in outcome.stages
            ]
            purity = _track_purity(sim, camera_id, params)
            run["calib_tracks"] = sorted(i for i, (_, share) in purity.items() if share >= 0.5)
            run["calib_track_fates"] = _calib_track_fates(seen, purity, truth)
            run["candidates"] = [
                {
                    "tracks": list(c.track_ids),
                    "calib_share": round(_group_purity(c.track_ids, purity), 3),
                    "traversals": c.traversals,
                    "box_error_pct": round(100 * c.box_error_rel, 3),
                    "delta_p_mean_m": round(c.delta_p_mean_m, 4),
                    "chosen": outcome.chosen is not None and c.track_ids == outcome.chosen.track_ids,
                }
                for c in outcome.candidates
            ]
            run["chosen_calib_share"] = (
                _group_purity(outcome.chosen.track_ids, purity) if outcome.chosen is not None else None
            )
        except Exception as err:
            run.update(verdict="error", error=_describe(err), reasons=[])
        runs.append(run)
    return runs


def _describe(err: BaseException) -> str:
    frames = traceback.extract_tb(err.__traceback__)
    where = f" at {Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else ""
    message = " ".join(str(err).split())
    return f"{type(err).__name__}: {message}{where}"


# ------------------------------------------------------------------------------------------------- report


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def _pair(a: float | None, b: float | None, spec: str) -> str:
    return f"{_fmt(a, spec)}/{_fmt(b, spec)}"


def summarise(preset: str, runs: Sequence[Run]) -> dict[str, Any]:
    accepted = [r for r in runs if _is_accepted(r)]
    target = TARGETS.get(preset)
    failures = target.failures(runs) if target else []
    errors = [r for r in runs if r["verdict"] == "error"]
    if errors:
        failures.append(f"{len(errors)} run(s) raised")
    return {
        "preset": preset,
        "runs": len(runs),
        "accepted": len(accepted),
        "success_rate": len(accepted) / max(len(runs), 1),
        "delta_p_mean_m": _mean([r["delta_p_mean_m"] for r in accepted]),
        "delta_p_max_m": _mean([r["delta_p_max_m"] for r in accepted]),
        "e_mean_pct": _mean([r["e_mean_pct"] for r in accepted]),
        "e_max_pct": _mean([r["e_max_pct"] for r in accepted]),
        "position_mean_m": _mean([r["position_error_m"] for r in accepted]),
        "position_max_m": _max([r["position_error_m"] for r in accepted]),
        "rotation_mean_deg": _mean([r["rotation_error_deg"] for r in accepted]),
        "rotation_max_deg": _max([r["rotation_error_deg"] for r in accepted]),
        "refused": sum(r["verdict"] == "refused" for r in runs),
        "false_accepts": sum(is_false_accept(r) for r in runs),
        "errors": len(errors),
        "median_seconds": statistics.median([r["seconds"] for r in runs if "seconds" in r] or [math.nan]),
        "floor_delta_p_mean_m": _mean([r.get("floor_delta_p_mean_m") for r in runs]),
        "floor_e_mean_pct": _mean([r.get("floor_e_mean_pct") for r in runs]),
        "beyond_3_std": sum(beyond_reported(r) for r in accepted),
        "latency_ms": _mean([r.get("latency_ms") for r in runs]),
        "offset_error_mean_ms": _mean([r.get("time_offset_error_ms") for r in accepted]),
        "offset_error_max_ms": _max([r.get("time_offset_error_ms") for r in accepted]),
        "box_area_ratio": _mean([r.get("box_area_ratio") for r in runs]),
        "std_sources": {
            name: count for name in _SOURCE_TAGS if (count := sum(std_source(r) == name for r in runs))
        },
        "paper": PAPER.get(preset, ""),
        "target": target.text if target else "(none)",
        "failures": failures,
        "result": _result_text(
            failures,
            target is not None or bool(errors),
            len(runs) - len(accepted) if target is not None and target.over_accepted else 0,
        ),
    }


def _result_text(failures: Sequence[str], judged: bool, not_accepted: int) -> str:
    """PASS / FAIL, or '-' without a target; a PASS over accepted runs says how many were not accepted."""
    if not judged:
        return "-"
    if failures:
        return "FAIL"
    return "PASS" if not_accepted == 0 else f"PASS ({not_accepted} not acc.)"


def format_table(summaries: Sequence[dict[str, Any]], false_accepts: int, errors: int) -> str:
    header = (
        "preset",
        "acc/runs",
        "dp m/w m",
        "e m/w %",
        "pos mean/max m",
        "rot mean/max deg",
        "ref",
        "FA",
        "err",
        "t s",
        "floor dp/e_m",
        "cover",
        "lat ms",
        "lat err",
        "area",
        "pos std from",
        "paper",
        "target",
        "result",
    )
    rows = [header]
    for s in summaries:
        rows.append(
            (
                s["preset"],
                f"{s['accepted']}/{s['runs']}",
                _pair(s["delta_p_mean_m"], s["delta_p_max_m"], ".3f"),
                _pair(s["e_mean_pct"], s["e_max_pct"], ".2f"),
                _pair(s["position_mean_m"], s["position_max_m"], ".3f"),
                _pair(s["rotation_mean_deg"], s["rotation_max_deg"], ".3f"),
                str(s["refused"]),
                str(s["false_accepts"]),
                str(s["errors"]),
                _fmt(s["median_seconds"], ".1f"),
                _pair(s["floor_delta_p_mean_m"], s["floor_e_mean_pct"], ".3f"),
                f"{s.get('beyond_3_std', 0)}/{s['accepted']}" if s["accepted"] else "-",
                _fmt(s.get("latency_ms"), ".0f"),
                _pair(s.get("offset_error_mean_ms"), s.get("offset_error_max_ms"), ".1f"),
                _fmt(s.get("box_area_ratio"), ".3f"),
                " ".join(f"{_SOURCE_TAGS[k]}{n}" for k, n in s.get("std_sources", {}).items()) or "-",
                s["paper"],
                s["target"],
                s["result"],
            )
        )
    rows.append(
        ("ALL", "", "", "", "", "", "", str(false_accepts), str(errors), "", "", "", "", "", "", "", "",
         "false accepts = 0", "PASS" if false_accepts == 0 and errors == 0 else "FAIL")
    )  # fmt: skip
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip() for row in rows]
    lines.insert(1, "-" * len(lines[0]))
    return "\n".join(lines)


def format_run(run: Run, problem: str) -> str:
    lines = [f"  {run['preset']} seed {run['seed']} camera {run['camera']}: {problem}"]
    if run.get("error"):
        lines.append(f"    error: {run['error']}")
        return "\n".join(lines)
    lines.append(
        f"    verdict {run['verdict']}; dp {_fmt(run.get('delta_p_mean_m'), '.3f')} m, "
        f"e_m {_fmt(run.get('e_mean_pct'), '.2f')} %, pos {_fmt(run.get('position_error_m'), '.3f')} m "
        f"(height {_fmt(run.get('height_error_m'), '+.3f')}), "
        f"rot {_fmt(run.get('rotation_error_deg'), '.3f')} deg (reported std "
        f"{_fmt(run.get('position_std_m'), '.3f')} m / {_fmt(run.get('rotation_std_deg'), '.3f')} deg); "
        f"floor dp {_fmt(run.get('floor_delta_p_mean_m'), '.3f')} m; truth: {run.get('truth_traversals')} "
        f"traversal(s), {run.get('truth_boxes')} calib boxes; calib-vehicle tracks {run.get('calib_tracks')}"
    )
    lines.extend(f"    reason: {reason}" for reason in run.get("reasons", []))
    lines.extend(f"    calib track {fate}" for fate in run.get("calib_track_fates", []))
    for candidate in run.get("candidates", []):
        mark = "*" if candidate["chosen"] else " "
        lines.append(
            f"   {mark}candidate tracks {candidate['tracks']}: calib share {candidate['calib_share']:.2f}, "
            f"{candidate['traversals']} traversal(s), box error {candidate['box_error_pct']:.2f} %, "
            f"dp {candidate['delta_p_mean_m']:.3f} m"
        )
    lines.extend(
        f"    stage {stage}"
        for stage in run.get("stages", [])
        if stage.split(":")[0] in ("hypotheses", "grouping", "association")
    )
    return "\n".join(lines)


def run_problems(runs: Sequence[Run]) -> list[tuple[Run, str]]:
    """Runs to list under the table: errors, false accepts, and runs that count against their target;
    refusals of presets without a target are listed for information."""
    out = []
    for run in runs:
        target = TARGETS.get(run["preset"])
        if run["verdict"] == "error":
            out.append((run, "ERROR"))
        elif is_false_accept(run):
            out.append((run, "FALSE ACCEPT"))
        elif target is not None and (problem := target.run_problem(run)) is not None:
            out.append((run, problem))
        elif target is None and run["verdict"] == "refused":
            out.append((run, "refused (no target; for information)"))
    return out


# --------------------------------------------------------------------------------------------------- main


def _task_weight(preset: str | ScenarioConfig) -> float:
    """Rough cost of one (preset, seed), to start the slow ones first."""
    from sim.simulate import PRESETS

    config = PRESETS[preset] if isinstance(preset, str) else preset
    return len(config.cameras) * (config.traffic.count + 50) * (config.duration_s or 300.0)


def _run_all(
    names: Sequence[str],
    seeds: range,
    jobs: int,
    ideal: bool,
    readout_s: float | None = None,
    latency_s: float | None = None,
    routes_times: int = 1,
) -> list[Run]:
    presets: list[str | ScenarioConfig] = [repeated_routes(p, routes_times) for p in names]
    return run_tasks([(p, s, ideal, readout_s, latency_s) for p in presets for s in seeds], jobs)


def repeated_routes(preset: str, times: int) -> str | ScenarioConfig:
    """The preset (by name) with its calibration vehicle driving its routes `times` times over (3
    drive-pasts become 3 x times; stops per traversal repeated with them), same name; the name itself
    when times is 1."""
    if times == 1:
        return preset
    from dataclasses import replace

    from sim.simulate import PRESETS

    config = PRESETS[preset]
    drive = config.drive
    stops = None if drive.stops is None else drive.stops * times
    return replace(config, drive=replace(drive, routes=drive.routes * times, stops=stops))


def run_tasks(tasks: Sequence[Task], jobs: int) -> list[Run]:
    """run_seed over `tasks` in `jobs` spawned worker processes, the costly ones first; progress on stderr."""
    tasks = sorted(tasks, key=lambda t: -_task_weight(t[0]))
    runs: list[Run] = []
    started = time.perf_counter()

    def record(batch: list[Run], done: int) -> None:
        runs.extend(batch)
        elapsed = time.perf_counter() - started
        for run in batch:
            print(
                f"[{done:>3}/{len(tasks)} {elapsed / 60:5.1f} min] {run['preset']} seed {run['seed']} "
                f"{run['camera']}: {run['verdict']} dp {_fmt(run.get('delta_p_mean_m'), '.3f')} "
                f"pos {_fmt(run.get('position_error_m'), '.3f')} "
                f"rot {_fmt(run.get('rotation_error_deg'), '.3f')} "
                f"({_fmt(run.get('seconds'), '.1f')} s)",
                file=sys.stderr,
                flush=True,
            )

    if jobs <= 1:
        for done, task in enumerate(tasks, 1):
            record(run_seed(task), done)
    else:
        import multiprocessing

        with multiprocessing.get_context("spawn").Pool(jobs) as pool:
            for done, batch in enumerate(pool.imap_unordered(run_seed, tasks), 1):
                record(batch, done)
    return runs


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.accuracy", description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=10, help="how many seeds (default 10)")
    parser.add_argument("--first-seed", type=int, default=0, help="seeds FIRST..FIRST+N-1 (default 0)")
    parser.add_argument("--presets", default="", help="comma-separated presets (default: all but long)")
    parser.add_argument("--ideal", action="store_true", help="the first simulator's world (see above)")
    parser.add_argument(
        "--readout",
        type=float,
        metavar="MS",
        help="every camera's rolling-shutter readout (ms) in either world",
    )
    parser.add_argument(
        "--latency",
        type=float,
        metavar="MS",
        help="every camera's latency (ms, stamp minus exposure; may be negative) in either world",
    )
    parser.add_argument(
        "--routes-times",
        type=int,
        default=1,
        metavar="K",
        help="the calibration vehicle drives each preset's routes K times over (default 1)",
    )
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument("--json", type=Path, help="also write every run and the summary here")
    parser.add_argument(
        "--load", type=Path, nargs="+", help="report the runs of earlier --json files together, run nothing"
    )
    args = parser.parse_args(argv)

    started = time.perf_counter()
    if args.load:
        saved = [json.loads(path.read_text()) for path in args.load]
        runs: list[Run] = [run for part in saved for run in part["runs"]]
        names = list(dict.fromkeys(r["preset"] for r in runs))
        header = "\n".join(
            part.get("header", f"runs loaded from {path}")
            for part, path in zip(saved, args.load, strict=True)
        )
    else:
        # Before numpy is imported here or in any worker (spawned workers inherit the environment).
        limit_threads(1)
        from sim.simulate import PRESETS

        names = [p.strip() for p in args.presets.split(",") if p.strip()] or [
            p for p in PRESETS if p not in EXCLUDED_PRESETS
        ]
        unknown = [p for p in names if p not in PRESETS]
        if unknown:
            parser.error(f"unknown preset(s) {', '.join(unknown)}; choose from {', '.join(PRESETS)}")
        # Now: the workers import the code as it is when they start.
        code = tree_state(["pipeline", "schemas", "sim"])
        seeds = range(args.first_seed, args.first_seed + args.seeds)
        if args.readout is not None and not 0.0 <= args.readout <= 1000.0:
            parser.error(f"--readout {args.readout}: a readout time in ms, 0-1000")
        readout_s = None if args.readout is None else args.readout / 1e3
        if args.latency is not None and not -1000.0 <= args.latency <= 1000.0:
            parser.error(f"--latency {args.latency}: a latency in ms, -1000..1000")
        latency_s = None if args.latency is None else args.latency / 1e3
        if not 1 <= args.routes_times <= 10:
            parser.error(f"--routes-times {args.routes_times}: how many times over, 1-10")
        runs = _run_all(names, seeds, args.jobs, args.ideal, readout_s, latency_s, args.routes_times)
        world = "IDEAL world (cuboid boxes, no latency, IMU poses)" if args.ideal else "real world"
        if args.routes_times > 1:
            world += f", every preset's routes driven {args.routes_times} times over"
        if readout_s is not None:
            world += f", every camera with a {args.readout:g} ms rolling-shutter readout"
        if latency_s is not None:
            world += f", every camera with a {args.latency:g} ms latency"
        header = (
            f"rsucal accuracy benchmark, {world}: {len(names)} presets x seeds {seeds.start}.."
            f"{seeds.stop - 1}, every camera, known vehicle clock offset; {len(runs)} runs in "
            f"{(time.perf_counter() - started) / 60:.1f} min "
            f"with {args.jobs} worker(s); code: {code}"
        )

    order = {name: i for i, name in enumerate(names)}
    runs.sort(key=lambda r: (order[r["preset"]], r["seed"], r["camera"]))
    summaries = [summarise(p, [r for r in runs if r["preset"] == p]) for p in names]
    false_accepts = sum(is_false_accept(r) for r in runs)
    errors = sum(r["verdict"] == "error" for r in runs)
    passed = false_accepts == 0 and errors == 0 and all(s["result"] != "FAIL" for s in summaries)

    print(header)
    print(format_table(summaries, false_accepts, errors))
    print(coverage_line(runs))
    for s in summaries:
        for failure in s["failures"]:
            print(f"FAIL {s['preset']}: {failure}")
    problems = run_problems(runs)
    if problems:
        print(
            "\nPer-run details (errors, false accepts, runs counting against their target, other refusals):"
        )
        for run, problem in problems:
            print(format_run(run, problem))
    print(f"\noverall: {'PASS' if passed else 'FAIL'}")
    if args.json:
        payload = {"header": header, "summaries": summaries, "runs": runs}
        args.json.write_text(json.dumps(payload, indent=1, default=str))
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
