"""Speed benchmark: loading a long recording vs calibrating from it, and the peak memory of doing both.
Not part of the test suite.

    python -m bench.speed [--preset long] [--seed 0] [--repeat 3]
    python -m bench.speed --cli [--preset long] [--repeat 5] [--pair DIR] [--compare 'CMD {poses} ...']

--cli measures the whole `rsucal calibrate` command on the reference toolbox's YAML pair instead (block
style, written from the preset unless --pair gives real files), per part (imports, load, each stage) and
side by side with --compare's command: see bench/cli_speed.py.

The preset (default `long`: 15 min at 10 fps, 300 other vehicles) is simulated once, in a child process, and
written as the daemon would have recorded it (daemon.recording.write_simulation_mcap) to a temporary
directory. Then:
  (c) peak RSS of a child process doing (a) + (b) from a cold start (imports included): ru_maxrss of that
      child (os.wait4), next to the VmHWM the child reads from /proc at each step. It runs first, while this
      process is still small: Linux carries a process's peak RSS across exec() from the address space it
      was forked with, so a child of a big parent starts with the parent's size as its "peak".
  (a) load: read_recording() of the camera's detections and the vehicle's V2X, plus V2X -> VehiclePose
      (the time needed only to load the input);
  (b) calibrate(): wall time on this machine's cores, with the time per stage from the progress callback.
Targets: calibrate <= 5 s wall (median of --repeat runs), peak RSS <= 500 MB. Exit 1 when one fails.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bench.common import StageClock

CALIBRATE_TARGET_S = 5.0
RSS_TARGET_MB = 500.0  # 1 MB = 10^6 bytes


def load_inputs(job: dict[str, Any]) -> Any:
    """(a): the MCAP recording -> calibrate() inputs for one camera."""
    from daemon.recording import read_recording
    from pipeline.calibrate import CalibrationInputs
    from pipeline.frames import UtmFrame, poses_from_v2x
    from schemas.common import CameraIntrinsics, VehicleProfile

    recording = read_recording(Path(job["mcap"]), camera_id=job["camera_id"], station_id=job["station_id"])
    poses, _ = poses_from_v2x(recording.v2x, UtmFrame(job["crs"]))
    return CalibrationInputs(
        rsu_id=job["rsu_id"],
        camera_id=job["camera_id"],
        intrinsics=CameraIntrinsics.model_validate(job["intrinsics"]),
        vehicle=VehicleProfile.model_validate(job["vehicle"]),
        detections=recording.detections.get(job["camera_id"], []),
        poses=poses,
        crs=job["crs"],
        time_offset_ns=job["time_offset_ns"],
        station_id=job["station_id"],
    )


def run_calibrate(inputs: Any, seed: int) -> tuple[Any, float, float, dict[str, float]]:
    """(b): calibrate() once -> outcome, wall seconds, CPU seconds of this process, seconds per stage."""
    import numpy as np

    from daemon.workers import track_pool
    from pipeline.calibrate import PipelineParams, calibrate

    cpu_start = time.process_time()
    started = time.perf_counter()
    # The wall time includes starting and stopping the per-track worker pool (one process per core).
    with track_pool() as map_fn:
        clock = StageClock()
        outcome = calibrate(
            inputs,
            PipelineParams(),
            np.random.default_rng(seed),
            created_at_ns=time.time_ns(),
            progress=clock,
            map_fn=map_fn,
        )
        stages_end = time.perf_counter()
    end = time.perf_counter()
    return outcome, end - started, time.process_time() - cpu_start, clock.durations(stages_end)


def prepare_main(out_dir: Path, preset: str, seed: int, camera_id: str | None) -> int:
    """Child: simulate, write the MCAP, the job description and the camera's ground truth into out_dir."""
    from daemon.recording import write_simulation_mcap
    from sim.simulate import simulate

    started = time.perf_counter()
    sim = simulate(preset, seed)
    simulate_s = time.perf_counter() - started
    camera_id = camera_id or sim.cameras[0].camera_id
    camera = next(c for c in sim.cameras if c.camera_id == camera_id)
    truth = sim.ground_truth[camera_id]
    frames = sim.detections[camera_id]
    mcap = write_simulation_mcap(sim, out_dir / "recording.mcap")
    print(
        f"preset {preset} seed {seed}, camera {camera_id}: {len(frames)} frames, "
        f"{sum(len(f.boxes) for f in frames)} boxes, {len(sim.v2x)} V2X messages, "
        f"{sim.traffic_count} other vehicles (simulated in {simulate_s:.1f} s); "
        f"recording {mcap.stat().st_size / 1e6:.1f} MB MCAP"
    )
    job = {
        "mcap": str(mcap),
        "camera_id": camera_id,
        "station_id": sim.station_id,
        "rsu_id": sim.rsu_id,
        "crs": sim.origin.crs,
        "time_offset_ns": truth.clock_offset_ns,
        "intrinsics": camera.intrinsics.model_dump(mode="json"),
        "vehicle": sim.vehicle.model_dump(mode="json"),
        "seed": seed,
    }
    (out_dir / "job.json").write_text(json.dumps(job))
    (out_dir / "truth.json").write_text(truth.model_dump_json())
    return 0


def _vm_hwm_mb() -> float:
    """This address space's peak resident set (VmHWM, /proc/self/status) in MB; NaN where unavailable."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024 / 1e6
    except OSError:
        pass
    return float("nan")


def measure_main(job_path: Path) -> int:
    """(c)'s child: load + calibrate from a cold start; prints its timings and peaks as one JSON line."""
    # Import everything first, to separate the imports' share of the peak from the data's.
    import daemon.recording  # noqa: F401
    import pipeline.calibrate  # noqa: F401

    job = json.loads(job_path.read_text())
    imported_mb = _vm_hwm_mb()
    started = time.perf_counter()
    inputs = load_inputs(job)
    loaded = time.perf_counter()
    loaded_mb = _vm_hwm_mb()
    outcome, calibrate_s, _, _ = run_calibrate(inputs, job["seed"])
    report = {
        "load_s": loaded - started,
        "calibrate_s": calibrate_s,
        "verdict": outcome.result.verdict.status,
        "hwm_after_imports_mb": imported_mb,
        "hwm_after_load_mb": loaded_mb,
        "hwm_after_calibrate_mb": _vm_hwm_mb(),
    }
    print(json.dumps(report))
    return 0


def _run_child(args: list[str]) -> tuple[int, str, str, float]:
    """Run `python -m bench.speed ARGS`; -> exit code, stdout, stderr, the child's ru_maxrss in MB."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        child = subprocess.Popen([sys.executable, "-m", "bench.speed", *args], stdout=out, stderr=err)
        _, status, usage = os.wait4(child.pid, 0)
        child.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        return child.returncode, out.read(), err.read(), usage.ru_maxrss * 1024 / 1e6  # Linux: KiB


def _stats(values: Sequence[float]) -> str:
    return f"median {statistics.median(values):.3f} s (min {min(values):.3f}, max {max(values):.3f})"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.speed", description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="long")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--camera", help="camera id (default: the preset's first camera)")
    parser.add_argument(
        "--cli", action="store_true", help="whole `rsucal calibrate` on the toolbox YAML pair"
    )
    parser.add_argument("--pair", type=Path, help="--cli: a directory with the toolbox files to use instead")
    parser.add_argument(
        "--compare", help="--cli: time this command too ({camera} {vehicle} {detections} {poses} {out})"
    )
    parser.add_argument("--instrumented", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--write-pair", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--prepare", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--measure", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.write_pair:
        from bench.cli_speed import write_toolbox_pair

        print(write_toolbox_pair(args.write_pair, args.preset, args.seed))
        return 0
    if args.instrumented:
        from bench.cli_speed import instrumented_main

        return instrumented_main(args.instrumented)
    if args.cli:
        from bench.cli_speed import cli_main

        return cli_main(args.preset, args.seed, args.repeat, args.pair, args.compare)
    if args.prepare:
        return prepare_main(args.prepare, args.preset, args.seed, args.camera)
    if args.measure:
        return measure_main(args.measure)

    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} (1 min) at the start")
    with tempfile.TemporaryDirectory(prefix="rsucal-bench-") as tmp:
        prepare = ["--prepare", tmp, "--preset", args.preset, "--seed", str(args.seed)]
        code, out, err, _ = _run_child(prepare + (["--camera", args.camera] if args.camera else []))
        if code != 0:
            print(f"simulation failed ({code}):\n{err}")
            return 1
        print(out.strip())
        job_path = Path(tmp) / "job.json"

        # (c) first, while this process holds nothing but the interpreter.
        code, out, err, peak_mb = _run_child(["--measure", str(job_path)])
        child_report = json.loads(out.strip().splitlines()[-1]) if code == 0 else None

        job = json.loads(job_path.read_text())
        load_s: list[float] = []
        for _ in range(args.repeat):
            started = time.perf_counter()
            inputs = load_inputs(job)
            load_s.append(time.perf_counter() - started)
        calibrate_s: list[float] = []
        cpu_s: list[float] = []
        stages: list[dict[str, float]] = []
        outcome: Any = None
        for _ in range(args.repeat):
            outcome, seconds, cpu, per_stage = run_calibrate(inputs, args.seed)
            calibrate_s.append(seconds)
            cpu_s.append(cpu)
            stages.append(per_stage)
        truth_json = (Path(tmp) / "truth.json").read_text()

    from pipeline.metrics import evaluate_against_ground_truth
    from schemas.files import GroundTruth

    evaluation = evaluate_against_ground_truth(outcome.result, GroundTruth.model_validate_json(truth_json))
    median_index = calibrate_s.index(sorted(calibrate_s)[len(calibrate_s) // 2])
    load_median = statistics.median(load_s)
    calibrate_median = statistics.median(calibrate_s)
    print(
        f"calibrate verdict {outcome.result.verdict.status} {outcome.result.verdict.reasons or ''}; "
        f"vs truth: delta_p mean {evaluation.delta_p_mean_m:.3f} m, "
        f"position {evaluation.position_error_m:.3f} m, rotation {evaluation.rotation_error_deg:.3f} deg"
    )
    for report in outcome.stages:
        print(f"  stage {report.stage}: kept {report.kept}, discarded {report.discarded}")
    print(f"\n(a) load (read_recording + V2X -> poses, {args.repeat}x): {_stats(load_s)}")
    print(f"(b) calibrate ({args.repeat}x):                            {_stats(calibrate_s)}")
    print(f"    CPU time of this process:                   {_stats(cpu_s)}")
    print("    per stage (median run; 'tracking' includes matching tracks to poses and the ground plane):")
    for stage, seconds in stages[median_index].items():
        print(f"      {stage:<12} {seconds:7.3f} s")
    print(f"    calibrate / load = {calibrate_median / load_median:.2f}")
    if child_report is None:
        print(f"(c) child process failed ({code}):\n{err}")
    else:
        print(
            f"(c) child load + calibrate (cold start): load {child_report['load_s']:.3f} s, "
            f"calibrate {child_report['calibrate_s']:.3f} s, verdict {child_report['verdict']}; "
            f"peak RSS (ru_maxrss) {peak_mb:.0f} MB ({peak_mb * 1e6 / 2**20:.0f} MiB)"
        )
        print(
            f"    the child's VmHWM after its imports {child_report['hwm_after_imports_mb']:.0f} MB, "
            f"after loading {child_report['hwm_after_load_mb']:.0f} MB, "
            f"after calibrate {child_report['hwm_after_calibrate_mb']:.0f} MB"
        )

    checks = [
        (
            f"calibrate {calibrate_median:.2f} s <= {CALIBRATE_TARGET_S:g} s",
            calibrate_median <= CALIBRATE_TARGET_S,
        ),
        (
            f"peak RSS {peak_mb:.0f} MB <= {RSS_TARGET_MB:g} MB",
            child_report is not None and peak_mb <= RSS_TARGET_MB,
        ),
    ]
    print(f"\nload average {os.getloadavg()[0]:.2f} (1 min) at the end (other processes share the cores)")
    for text, ok in checks:
        print(f"{'PASS' if ok else 'FAIL'}  {text}")
    return 0 if all(ok for _, ok in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
