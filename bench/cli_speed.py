"""Whole-command speed of `rsucal calibrate` on the reference toolbox's file format, and a side-by-side run
of any other command on the same files (`python -m bench.speed --cli`, see bench/speed.py).

The input is a toolbox file set written in the toolbox's own block style (one value per line, as its
published poses are), from a simulator preset (default `long`: 15 min, 50 Hz poses) or from a directory
the user gives (real toolbox data: camera.yaml, vehicle.yaml, detections.yaml, poses.yaml). Measured:
  - the whole command (`rsucal calibrate ... --out`), wall time best and median over --repeat runs and the
    peak RSS of its process tree (ru_maxrss of the child, which covers its waited-for workers);
  - one instrumented run: imports, loading the files, each stage of calibrate(), writing; with the share
    of load + imports in the whole;
  - with --compare 'CMD', CMD timed the same way, interleaved with rsucal's runs so both see the same
    machine load. CMD may use {camera} {vehicle} {detections} {poses} {out} {dir}.
Targets (issue 12): whole command <= reference / 20, where the reference is --compare's median or, without
it, the 25.8 s the toolbox took on a 16-minute 50 Hz track with 12k boxes; peak RSS <= 300 MB.
"""

from __future__ import annotations

import gc
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.common import REPO_ROOT, StageClock, load_average

REFERENCE_TOOLBOX_S = 25.8  # the toolbox on a 16-minute 50 Hz track, 12k boxes (issue 12, one machine)
SPEEDUP_TARGET = 20.0
RSS_TARGET_MB = 300.0
FILES = ("camera.yaml", "vehicle.yaml", "detections.yaml", "poses.yaml")


def write_toolbox_pair(out_dir: Path, preset: str, seed: int) -> str:
    """Simulate `preset` and write its first camera's file set in the toolbox's block style; -> summary."""
    import yaml

    from sim.files import write_simulation_files
    from sim.simulate import simulate

    sim = simulate(preset, seed)
    camera_id = sim.cameras[0].camera_id
    write_simulation_files(sim, out_dir)  # camera(_<id>).yaml, vehicle.yaml, ground truth
    suffix = f"_{camera_id}" if len(sim.cameras) > 1 else ""
    if suffix:
        (out_dir / f"camera{suffix}.yaml").rename(out_dir / "camera.yaml")
    frames = sim.detections[camera_id]
    detections = {
        frame.stamp_ns: [
            [0.5 * (b.x1 + b.x2), 0.5 * (b.y1 + b.y2), b.x2 - b.x1, b.y2 - b.y1, b.cls] for b in frame.boxes
        ]
        for frame in frames
    }
    poses = {p.stamp_ns: [p.x, p.y, p.z, p.yaw, p.pitch, p.roll] for p in sim.poses}
    dumper: Any = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
    # Block style with full float precision: what yaml.dump writes by default and the toolbox publishes.
    for name, data in (("detections.yaml", detections), ("poses.yaml", poses)):
        (out_dir / name).write_text(yaml.dump(data, Dumper=dumper, default_flow_style=False))
    stamps = [p.stamp_ns for p in sim.poses]
    span_s = (stamps[-1] - stamps[0]) / 1e9
    boxes = sum(len(f.boxes) for f in frames)
    return (
        f"preset {preset} seed {seed}, camera {camera_id}: {len(frames)} frames, {boxes} boxes; "
        f"{len(stamps)} poses over {span_s / 60:.1f} min ({len(stamps) / span_s:.0f} Hz); block style, "
        f"poses.yaml {(out_dir / 'poses.yaml').stat().st_size / 1e6:.1f} MB, "
        f"detections.yaml {(out_dir / 'detections.yaml').stat().st_size / 1e6:.1f} MB"
    )


@dataclass(frozen=True, slots=True)
class Timed:
    wall_s: float
    peak_mb: float
    code: int


def run_timed(argv: Sequence[str], cwd: Path) -> Timed:
    """Run a command to completion: wall seconds, peak RSS (MB) of its process tree, exit code."""
    with tempfile.TemporaryFile() as sink:
        started = time.perf_counter()
        child = subprocess.Popen(list(argv), cwd=cwd, stdout=sink, stderr=sink)
        _, status, usage = os.wait4(child.pid, 0)
        wall_s = time.perf_counter() - started
    return Timed(wall_s, usage.ru_maxrss * 1024 / 1e6, os.waitstatus_to_exitcode(status))


def rsucal_argv(pair_dir: Path, out: Path) -> list[str]:
    rsucal = Path(sys.executable).with_name("rsucal")
    return [
        str(rsucal),
        "calibrate",
        *("--camera", str(pair_dir / "camera.yaml"), "--vehicle", str(pair_dir / "vehicle.yaml")),
        *("--detections", str(pair_dir / "detections.yaml"), "--poses", str(pair_dir / "poses.yaml")),
        *("--out", str(out)),
    ]


def instrumented_main(pair_dir: Path) -> int:
    """Child: the same work as `rsucal calibrate`, timed by part; prints one JSON line."""
    t0 = time.perf_counter()
    import numpy as np

    from daemon.offline import load_offline_inputs, write_result
    from daemon.workers import track_pool
    from pipeline.calibrate import PipelineParams, calibrate

    gc.freeze()  # as `rsucal calibrate` does after its imports
    t1 = time.perf_counter()
    loaded = load_offline_inputs(
        pair_dir / "camera.yaml",
        pair_dir / "vehicle.yaml",
        detections_path=pair_dir / "detections.yaml",
        poses_path=pair_dir / "poses.yaml",
    )
    t2 = time.perf_counter()
    with track_pool(None) as map_fn:
        clock = StageClock()
        outcome = calibrate(
            loaded.inputs,
            PipelineParams(),
            np.random.default_rng(0),
            created_at_ns=time.time_ns(),
            progress=clock,
            map_fn=map_fn,
        )
        stages_end = time.perf_counter()
    t3 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        write_result(outcome.result, Path(tmp) / "r.json")
    t4 = time.perf_counter()
    print(
        json.dumps(
            {
                "imports_s": t1 - t0,
                "load_s": t2 - t1,
                "calibrate_s": t3 - t2,
                "pool_stop_s": t3 - stages_end,
                "write_s": t4 - t3,
                "stages": clock.durations(stages_end),
                "verdict": outcome.result.verdict.status,
                "frames": len(loaded.inputs.detections),
                "poses": len(loaded.inputs.poses),
            }
        )
    )
    return 0


def _stats(values: Sequence[float]) -> str:
    return f"best {min(values):.2f} s, median {statistics.median(values):.2f} s ({len(values)} runs)"


def cli_main(preset: str, seed: int, repeat: int, pair_dir: Path | None, compare: str | None) -> int:
    print(f"machine: {os.cpu_count()} cores, load average {load_average()} at the start")
    with tempfile.TemporaryDirectory(prefix="rsucal-cli-speed-") as tmp:
        work = Path(tmp)
        if pair_dir is None:
            pair_dir = work / "pair"
            pair_dir.mkdir()
            # In a child: Linux carries a process's peak RSS across fork + exec, so if this process held
            # the simulation, every command started from it would report that size as its own peak.
            write_argv = [sys.executable, "-m", "bench.speed", "--write-pair", str(pair_dir)]
            writer = subprocess.run(
                [*write_argv, "--preset", preset, "--seed", str(seed)],
                cwd=REPO_ROOT,
                capture_output=True,
                text=True,
                check=False,
            )
            if writer.returncode != 0:
                print(f"writing the pair failed:\n{writer.stderr}")
                return 1
            print(writer.stdout.strip())
        else:
            missing = [name for name in FILES if not (pair_dir / name).is_file()]
            if missing:
                print(f"{pair_dir}: missing {', '.join(missing)}")
                return 2
            print(f"files: {pair_dir}")

        # One instrumented run first: where the time goes.
        child = subprocess.run(
            [sys.executable, "-m", "bench.speed", "--instrumented", str(pair_dir)],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            check=False,
        )
        if child.returncode != 0:
            print(f"instrumented run failed:\n{child.stderr}")
            return 1
        parts = json.loads(child.stdout.strip().splitlines()[-1])

        ours: list[Timed] = []
        theirs: list[Timed] = []
        template = shlex.split(compare) if compare else None
        fields = {"camera": "camera.yaml", "vehicle": "vehicle.yaml", "detections": "detections.yaml"}
        for _ in range(repeat):  # interleaved: both commands see the same machine load
            ours.append(run_timed(rsucal_argv(pair_dir, work / "rsucal.json"), REPO_ROOT))
            if template is not None:
                values = {key: str(pair_dir / name) for key, name in fields.items()}
                values.update(
                    poses=str(pair_dir / "poses.yaml"), out=str(work / "other.out"), dir=str(pair_dir)
                )
                theirs.append(run_timed([arg.format(**values) for arg in template], pair_dir))

    whole = parts["imports_s"] + parts["load_s"] + parts["calibrate_s"] + parts["write_s"]
    print(
        f"\ninstrumented run ({parts['frames']} frames, {parts['poses']} poses, verdict {parts['verdict']}): "
        f"{whole:.2f} s in-process"
    )
    print(f"  imports      {parts['imports_s']:7.3f} s")
    print(f"  load         {parts['load_s']:7.3f} s   (YAML -> detections and poses)")
    for stage, seconds in parts["stages"].items():
        print(f"  {stage:<12} {seconds:7.3f} s")
    print(f"  (pool stop   {parts['pool_stop_s']:7.3f} s)")
    print(f"  write        {parts['write_s']:7.3f} s")
    print(f"  load + imports share: {100.0 * (parts['imports_s'] + parts['load_s']) / whole:.0f} %")

    codes = {t.code for t in ours}
    print(f"\nrsucal calibrate, whole command: {_stats([t.wall_s for t in ours])}; exit {sorted(codes)}")
    peak_mb = max(t.peak_mb for t in ours)
    print(f"  peak RSS (process tree) {peak_mb:.0f} MB")
    reference_s = REFERENCE_TOOLBOX_S
    if theirs:
        print(
            f"compared command: {_stats([t.wall_s for t in theirs])}; exit {sorted({t.code for t in theirs})}"
        )
        print(f"  peak RSS {max(t.peak_mb for t in theirs):.0f} MB")
        reference_s = statistics.median(t.wall_s for t in theirs)
        print(f"speed-up (median / median): {reference_s / statistics.median(t.wall_s for t in ours):.1f}x")
    else:
        print(f"reference (no --compare): the toolbox's {REFERENCE_TOOLBOX_S} s measured in issue 12")
    target_s = reference_s / SPEEDUP_TARGET
    median_s = statistics.median(t.wall_s for t in ours)
    print(f"\nload average {load_average()} at the end (other processes share the cores)")
    checks = [
        (
            f"whole command median {median_s:.2f} s <= {target_s:.2f} s (reference / {SPEEDUP_TARGET:g})",
            median_s <= target_s,
        ),
        (f"peak RSS {peak_mb:.0f} MB <= {RSS_TARGET_MB:g} MB", peak_mb <= RSS_TARGET_MB),
    ]
    for text, ok in checks:
        print(f"{'PASS' if ok else 'FAIL'}  {text}")
    return 0 if all(ok for _, ok in checks) and codes <= {0, 3} else 1
