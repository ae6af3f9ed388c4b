"""`rsucal` subcommands: argument parsing and exit codes only; each command is a plain call into the packages.

Exit codes: 0 success, 2 bad input (the message names file and field), 3 calibration refused.
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from pydantic import ValidationError

from daemon.bridge_cli import add_bridge_parser
from pipeline.errors import InputError, RecordingError, RsucalError
from schemas.common import describe_validation_error
from schemas.config import DEFAULT_MAX_V2X_STD_M, DaemonConfig
from sim.errors import SimulationError

if TYPE_CHECKING:
    from schemas.files import GroundTruth
    from schemas.results import CalibrationResult

# Duplicated from daemon.offline (imported lazily, like every command's dependencies) for --help.
DEFAULT_YAML_CRS = "EPSG:32632"

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_REFUSED = 3

EXIT_INTERRUPTED = 130

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
# Seeds feed numpy's SeedSequence, which takes any non-negative integer; beyond 2^128 they add nothing.
MAX_SEED = 2**128 - 1

log = logging.getLogger("rsucal")


# ----------------------------------------------------------------------------------- argument checking


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error: `rsucal calibrate: error: argument --seed: ... (see --help)`."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _integer(low: int, high: int | None = None, bounds: str | None = None) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < low or (high is not None and value > high):
            expected = bounds or (f">= {low}" if high is None else f"in [{low}, {high}]")
            raise argparse.ArgumentTypeError(f"must be {expected}, got {value}")
        return value

    return parse


def _positive_number(text: str) -> float:
    """A finite number > 0 (time-outs, rates, limits)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def _log_level(text: str) -> str:
    level = text.strip().upper()
    if level not in LOG_LEVELS:
        raise argparse.ArgumentTypeError(f"{text!r} is not one of {', '.join(LOG_LEVELS)}")
    return level


_SEED = _integer(0, MAX_SEED, ">= 0 (and below 2**128)")


def _output_file(option: str, text: str, suffix: str | None = None) -> Path:
    """A file to write: its directory must exist (nothing is created silently), it must not be a directory."""
    path = Path(text)
    if not text.strip() or text.endswith(os.sep):
        raise InputError(option, f"{text!r} is empty or a directory; expected a file name")
    if suffix is not None and path.suffix.lower() != suffix:
        raise InputError(option, f"{text!r} must end with {suffix}")
    try:
        if path.is_dir():
            raise InputError(option, f"{text!r} is a directory; expected a file name")
        parent = path.parent
        if not parent.is_dir():
            raise InputError(option, f"{text!r}: directory {str(parent)!r} does not exist")
        if not os.access(parent, os.W_OK):
            raise InputError(option, f"{text!r}: directory {str(parent)!r} is not writable")
    except OSError as err:  # a name too long, a loop of symlinks...
        raise InputError(option, f"{text!r}: {err.strerror or err}") from err
    return path


def _output_dir(option: str, text: str) -> Path:
    """A directory to write into, created if needed (like mkdir -p); an existing file there is refused."""
    path = Path(text)
    if not text.strip():
        raise InputError(option, "empty; expected a directory")
    try:
        if path.exists() and not path.is_dir():
            raise InputError(option, f"{text!r} exists and is not a directory")
        path.mkdir(parents=True, exist_ok=True)
        if not os.access(path, os.W_OK):
            raise InputError(option, f"{text!r} is not writable")
    except OSError as err:
        raise InputError(option, f"cannot create {text!r}: {err.strerror or err}") from err
    return path


def _check_preset(preset: str, presets: Iterable[str]) -> None:
    if preset not in presets:
        raise InputError("--preset", f"unknown preset {preset!r}; choose one of {', '.join(sorted(presets))}")


# ------------------------------------------------------------------------------------------- commands


def _cmd_simulate(args: argparse.Namespace) -> int:
    from daemon.recording import write_simulation_mcap
    from sim.files import write_simulation_files
    from sim.simulate import PRESETS, simulate

    _check_preset(args.preset, PRESETS)
    # Every argument is checked before the simulation runs, so nothing is half-written on a bad one.
    out = _output_dir("--out", args.out)  # first: --preview may name a file inside it
    preview = _output_file("--preview", args.preview, suffix=".png") if args.preview is not None else None
    result = simulate(args.preset, seed=args.seed, ideal=args.ideal)
    try:
        mcap_path = write_simulation_mcap(result, out / "recording.mcap", image_every=args.image_every)
        written = [mcap_path, *write_simulation_files(result, out)]
    except OSError as err:
        raise InputError("--out", f"cannot write into {args.out!r}: {err.strerror or err}") from err
    if preview is not None:
        from sim.preview import write_previews

        written.extend(write_previews(result, preview))
    frames = sum(len(f) for f in result.detections.values())
    boxes = sum(len(fr.boxes) for f in result.detections.values() for fr in f)
    print(
        f"preset {args.preset} seed {args.seed}: {len(result.cameras)} camera(s), {frames} frames, "
        f"{boxes} boxes, {len(result.poses)} vehicle poses, {len(result.v2x)} V2X messages, "
        f"{result.traffic_count} other vehicles"
    )
    truth = next(iter(result.ground_truth.values()), None)
    if truth is not None:
        v = result.vehicle
        world = "ideal world" if result.is_ideal else "real world"
        latencies = ", ".join(
            f"{t.camera_id} {t.latency_ns / 1e6:.0f} ms"
            + (f" (readout {t.readout_ns / 1e6:.0f} ms)" if t.readout_ns else "")
            for t in result.ground_truth.values()
        )
        print(
            f"  {world}: calibration vehicle {truth.vehicle_type} {v.length:.2f} x {v.width:.2f} x "
            f"{v.height:.2f} m, V2X {truth.v2x}, camera latency {latencies} (in the ground truth only)"
        )
    for path in written:
        print(f"  wrote {path}")
    return EXIT_OK


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from pipeline.loaders import load_calibration_result, load_ground_truth
    from pipeline.metrics import evaluate_against_ground_truth, format_evaluation

    result = load_calibration_result(Path(args.calib))
    truth = load_ground_truth(Path(args.ground_truth))
    _check_same_scene(result, truth, args.ground_truth)
    evaluation = evaluate_against_ground_truth(result, truth)
    if args.json:
        print(json.dumps(evaluation.as_dict(), indent=2))
    else:
        print(format_evaluation(evaluation))
    return EXIT_OK


# A calibrated camera is within ~40 m of the driven path (pipeline.hypotheses' gate) and the path is in its
# view, so a truth whose camera is farther than this from the result's cannot be of the same camera.
SAME_SCENE_MAX_DISTANCE_M = 1000.0


def _check_same_scene(result: CalibrationResult, truth: GroundTruth, truth_path: str) -> None:
    """Refuse to score a result against the truth of another scene (crs, distance, data window)."""
    import numpy as np

    if result.frame.crs != truth.crs:
        raise InputError(
            "--ground-truth",
            f"{truth_path}: crs {truth.crs} differs from the result's {result.frame.crs}: another scene",
        )
    if result.camera_position is not None:
        distance_m = float(
            np.linalg.norm(np.subtract(result.camera_position.utm, truth.camera_position_utm)[:2])
        )
        if distance_m > SAME_SCENE_MAX_DISTANCE_M:
            raise InputError(
                "--ground-truth",
                f"{truth_path}: its camera is {distance_m / 1000.0:.1f} km from the result's; the truth of "
                f"another scene or camera (a calibrated camera is within {SAME_SCENE_MAX_DISTANCE_M:g} m)",
            )
    start, end = result.provenance.window_start_ns, result.provenance.window_end_ns
    stamps = [frame.stamp_ns for frame in truth.frames]
    if start is not None and end is not None and stamps and (max(stamps) < start or min(stamps) > end):
        raise InputError(
            "--ground-truth",
            f"{truth_path}: its frames ({min(stamps)}..{max(stamps)} ns) do not overlap the result's data "
            f"window ({start}..{end} ns): the truth of another recording",
        )


def _cmd_calibrate(args: argparse.Namespace) -> int:
    import numpy as np

    from daemon.offline import (
        TerminalProgress,
        format_stage_reports,
        format_summary,
        load_offline_inputs,
        write_result,
    )
    from daemon.workers import track_pool
    from pipeline.calibrate import PipelineParams, calibrate

    # The modules just imported are hundreds of thousands of objects that live as long as the command; moved
    # out of the collector's generations, they are not traversed again by every full collection (loading
    # and calibrating the `long` toolbox pair runs ~210 collections: 0.09 s of GC in this process, 0.015 s
    # with them frozen). The forked track workers inherit the frozen set. Results are unchanged.
    gc.freeze()
    out = _output_file("--out", args.out)
    loaded = load_offline_inputs(
        Path(args.camera),
        Path(args.vehicle),
        mcap_path=Path(args.mcap) if args.mcap else None,
        detections_path=Path(args.detections) if args.detections else None,
        poses_path=Path(args.poses) if args.poses else None,
        camera_id=args.camera_id,
        station_id=args.station_id,
        crs=args.crs,
        time_offset_ns=args.time_offset_ns,
        frame=args.frame,
        origin=args.origin,
        max_v2x_std_m=args.max_v2x_std,
    )
    for note in loaded.notes:
        print(f"note: {note}")
    with track_pool(args.workers) as map_fn, TerminalProgress() as progress:
        outcome = calibrate(
            loaded.inputs,
            PipelineParams(),
            np.random.default_rng(args.seed),
            created_at_ns=time.time_ns(),
            progress=progress,
            map_fn=map_fn,
        )
    written = write_result(outcome.result, out)
    if args.verbose:
        print(format_stage_reports(outcome))
    print(format_summary(outcome.result, written))
    return EXIT_OK if outcome.result.verdict.is_accepted else EXIT_REFUSED


def _cmd_report(args: argparse.Namespace) -> int:
    from daemon.report import run_report

    written = run_report(
        Path(args.result),
        Path(args.vehicle),
        Path(args.out),
        mcap_path=Path(args.mcap) if args.mcap else None,
        detections_path=Path(args.detections) if args.detections else None,
        poses_path=Path(args.poses) if args.poses else None,
        station_id=args.station_id,
        time_offset_ns=args.time_offset_ns,
        seed=args.seed,
        workers=args.workers,
        max_v2x_std_m=args.max_v2x_std,
    )
    for path in written:
        print(f"wrote {path}")
    return EXIT_OK


def _cmd_daemon(args: argparse.Namespace) -> int:
    from daemon.main import run_daemon
    from daemon.state import prepare_state_dir
    from pipeline.loaders import load_daemon_config

    config_path = Path(args.config)
    config = load_daemon_config(config_path)
    config = _resolve_relative_paths(config, config_path.parent)
    prepare_state_dir(config.storage.state_dir)
    if args.log_level is None:
        logging.getLogger().setLevel(config.log_level)
    return run_daemon(config)


def _resolve_relative_paths(config: DaemonConfig, base: Path) -> DaemonConfig:
    """Relative paths in rsu.yaml are relative to the file, as an operator would expect."""
    storage = config.storage
    if not storage.state_dir.is_absolute():
        storage = storage.model_copy(update={"state_dir": (base / storage.state_dir).resolve()})
    zenoh_config = config.zenoh
    for name in ("config_file", "access_control_file"):
        path = getattr(zenoh_config, name)
        if path is not None and not path.is_absolute():
            zenoh_config = zenoh_config.model_copy(update={name: (base / path).resolve()})
    cameras = [
        camera.model_copy(
            update={"detector": camera.detector.model_copy(update={"model": (base / camera.detector.model)})}
        )
        if camera.detector is not None and not camera.detector.model.is_absolute()
        else camera
        for camera in config.cameras
    ]
    return config.model_copy(update={"storage": storage, "zenoh": zenoh_config, "cameras": cameras})


def _cmd_access_control(args: argparse.Namespace) -> int:
    from daemon.access import write_site_config
    from pipeline.loaders import load_daemon_config

    config_path = Path(args.config)
    config = _resolve_relative_paths(load_daemon_config(config_path), config_path.parent)
    out = write_site_config(config, Path(args.base), Path(args.out))
    print(
        f"wrote {out}: {args.base} with put rules for {len(config.vehicles)} vehicle(s) and "
        f"{len(config.cameras)} camera(s) of rsu {config.rsu_id}; restart the node that enforces it"
    )
    return EXIT_OK


def _cmd_status(args: argparse.Namespace) -> int:
    from daemon.status import status_main

    return status_main(args)


def _cmd_demo(args: argparse.Namespace) -> int:
    from daemon.demo import run_demo
    from sim.presets import PRESETS

    _check_preset(args.preset, PRESETS)
    return run_demo(
        preset=args.preset,
        seed=args.seed,
        rate=args.rate,
        timeout_s=args.timeout if args.timeout is not None else (3600.0 if args.images else 300.0),
        ideal=args.ideal,
        keep_dir=Path(args.keep) if args.keep else None,
        images=args.images,
        detector_model=Path(args.detector_model) if args.detector_model else None,
        detector_layout=args.detector_layout,
    )


def build_parser() -> argparse.ArgumentParser:
    from daemon import __version__

    parser = _Parser(prog="rsucal", description="Automatic roadside camera calibration.")
    parser.add_argument("--version", action="version", version=f"rsucal {__version__}")
    parser.add_argument(
        "--log-level",
        default=None,
        type=_log_level,
        help=f"logging level: {', '.join(LOG_LEVELS)} (default WARNING; the daemon: log_level of its config)",
    )
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    sim = sub.add_parser(
        "simulate", help="generate a seeded RSU scenario: MCAP, toolbox YAML pair, ground truth"
    )
    from sim.presets import PRESETS  # plain data: cheap to import for the help text

    sim.add_argument(
        "--preset",
        default="sil-west",
        help=f"scenario preset (default sil-west): {', '.join(sorted(PRESETS))}",
    )
    sim.add_argument("--seed", type=_SEED, default=0, help="random seed, >= 0 (default 0)")
    sim.add_argument("--out", required=True, help="output directory (created if needed)")
    sim.add_argument(
        "--preview",
        help="write a PNG of one busy frame per camera to this .png file (PATH_<camera>.png when there are "
        "several); its directory must exist",
    )
    sim.add_argument(
        "--ideal",
        action="store_true",
        help="the first simulator's world: cuboid boxes, no latency, i.i.d. jitter, IMU poses as V2X",
    )
    sim.add_argument(
        "--images",
        dest="image_every",
        type=_integer(1, 1000),
        nargs="?",
        const=5,
        default=None,
        metavar="EVERY",
        help="also record rendered camera images (foxglove.CompressedImage, JPEG) of every EVERY-th frame "
        "(default 5: 2 per second at 10 fps); about 30 ms per image",
    )
    sim.set_defaults(func=_cmd_simulate)

    ev = sub.add_parser(
        "evaluate", help="score a calibration against simulator ground truth (paper Sec. IV-B)"
    )
    ev.add_argument("--calib", required=True, help="CalibrationResult JSON")
    ev.add_argument("--ground-truth", required=True, help="ground_truth.json of the same camera")
    ev.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ev.set_defaults(func=_cmd_evaluate)

    cal = sub.add_parser(
        "calibrate",
        help="calibrate one camera offline from an MCAP recording or the toolbox YAML pair",
        description="Calibrate one camera from a recording (--mcap) or the reference toolbox's YAML pair "
        "(--detections + --poses). Exit 0 accepted, 3 refused (reasons printed), 2 bad input.",
    )
    cal.add_argument(
        "--camera",
        required=True,
        help="camera.yaml: intrinsics (px) and distortion; or a ROS camera_info calibration file (ost.yaml) "
        "or OpenCV FileStorage (YAML or XML) with camera_matrix and distortion_coefficients",
    )
    cal.add_argument("--vehicle", required=True, help="vehicle.yaml: the calibration vehicle's box and IMU")
    source = cal.add_mutually_exclusive_group(required=True)
    source.add_argument("--mcap", help="rsucal MCAP recording: detections and V2X positions")
    source.add_argument("--detections", help="toolbox detections.yaml (needs --poses)")
    cal.add_argument("--poses", help="toolbox poses.yaml: absolute UTM of --crs (with --detections)")
    cal.add_argument(
        "--camera-id",
        help="MCAP: which camera (needed if it holds several); YAML: its id (default: camera.yaml's stem)",
    )
    cal.add_argument(
        "--station-id", type=int, help="MCAP: the calibration vehicle's V2X station (needed if several)"
    )
    cal.add_argument(
        "--crs",
        help=f"UTM EPSG code of the poses/result, e.g. EPSG:32632 (MCAP default: the zone of the first "
        f"V2X position; YAML default: {DEFAULT_YAML_CRS}, which only the lat/lon output depends on)",
    )
    cal.add_argument(
        "--frame",
        choices=("utm", "local"),
        default="utm",
        help="frame of --poses: utm (absolute, default) or local (a local metric frame: the result stays in "
        "it, without lat/lon)",
    )
    cal.add_argument(
        "--origin",
        metavar="E,N",
        help="place local --poses in UTM: their origin is at easting E, northing N of --crs (axes along grid "
        "east/north); the result is then UTM with lat/lon",
    )
    cal.add_argument(
        "--time-offset-ns", type=int, default=0, help="vehicle clock minus camera clock, ns (default 0)"
    )
    cal.add_argument(
        "--max-v2x-std",
        metavar="M",
        type=_positive_number,
        default=DEFAULT_MAX_V2X_STD_M,
        help="--mcap: V2X positions the vehicle reports less accurate than this (1 sigma, m; vertically "
        "twice) are not used (default %(default)s: RTK fixed; the daemon's gates.max_v2x_std_m)",
    )
    cal.add_argument("--seed", type=_SEED, default=0, help="RANSAC random seed, >= 0 (default 0)")
    cal.add_argument(
        "--workers",
        type=_integer(1, 1024),
        default=None,
        help="processes for the per-track fits (default: one per core; 1 = no pool); results are identical",
    )
    cal.add_argument(
        "--verbose", action="store_true", help="print what every stage kept and discarded, and why"
    )
    cal.add_argument(
        "--out", required=True, help="CalibrationResult JSON to write (atomically; its directory must exist)"
    )
    cal.set_defaults(func=_cmd_calibrate)

    rep = sub.add_parser(
        "report",
        help="RESULT.json + its recording or YAML pair -> one self-contained HTML report and PNG figures",
        description="Re-run the calibration on the result's data and draw it: the vehicle model over its "
        "boxes, a map, delta_p against distance, residuals, hypothesis groups, uncertainty, the verdict.",
    )
    rep.add_argument("result", help="CalibrationResult JSON (rsucal calibrate --out, or a daemon's history/)")
    rep.add_argument("--vehicle", required=True, help="vehicle.yaml: the calibration vehicle's box and IMU")
    rep_source = rep.add_mutually_exclusive_group(required=True)
    rep_source.add_argument("--mcap", help="the rsucal MCAP recording the result was made from")
    rep_source.add_argument("--detections", help="toolbox detections.yaml (needs --poses)")
    rep.add_argument("--poses", help="toolbox poses.yaml (with --detections)")
    rep.add_argument("--station-id", type=int, help="MCAP: the calibration vehicle (default: the result's)")
    rep.add_argument("--time-offset-ns", type=int, default=0, help="vehicle clock minus camera clock, ns")
    rep.add_argument(
        "--max-v2x-std",
        metavar="M",
        type=_positive_number,
        default=DEFAULT_MAX_V2X_STD_M,
        help="--mcap: as for calibrate (default %(default)s)",
    )
    rep.add_argument(
        "--seed", type=_SEED, default=0, help="RANSAC random seed of the re-run, >= 0 (default 0)"
    )
    rep.add_argument(
        "--workers", type=_integer(1, 1024), default=None, help="processes for the per-track fits"
    )
    rep.add_argument("--out", required=True, help="directory for report.html and the PNGs")
    rep.set_defaults(func=_cmd_report)

    dmn = sub.add_parser("daemon", help="run the RSU service (Zenoh in, MCAP log, calibration out)")
    dmn.add_argument("--config", required=True, help="rsu.yaml (see deploy/rsu.example.yaml)")
    dmn.set_defaults(func=_cmd_daemon)

    acl = sub.add_parser(
        "access-control",
        help="write a secure Zenoh config whose access rules let each detector and vehicle publish only its "
        "own keys",
        description="Copy a secure Zenoh config (--base: deploy/zenoh/secure.json5 for a secure peer, "
        "secure-router.json5 for a router) with one put rule per calibration vehicle (v2x/cam/{station_id}) "
        "and per camera (its detections and images), bound to the certificate common names of rsu.yaml. "
        "The daemon refuses to start (exit 2) when the rules it runs with do not match its config.",
    )
    acl.add_argument("--config", required=True, help="rsu.yaml: cameras, vehicles and their certificates")
    acl.add_argument("--base", required=True, help="the Zenoh config to start from (its other rules stay)")
    acl.add_argument("--out", required=True, help="the Zenoh config to write (JSON, valid JSON5)")
    acl.set_defaults(func=_cmd_access_control)

    st = sub.add_parser("status", help="query calibration status and health over Zenoh, as a table")
    st.add_argument(
        "--connect",
        action="append",
        default=None,
        help="Zenoh endpoint of the daemon or a router (repeatable; default: those of --zenoh-config, "
        "else tcp/127.0.0.1:7447)",
    )
    st.add_argument(
        "--zenoh-config",
        default=None,
        help="Zenoh JSON5 base config (TLS client certificate), e.g. deploy/zenoh/secure-client.json5",
    )
    st.add_argument("--rsu", default=None, help="only this RSU (default: every RSU that answers)")
    st.add_argument("--camera", default=None, help="only this camera")
    st.add_argument(
        "--timeout", dest="timeout_s", type=_positive_number, default=3.0, help="seconds to wait for answers"
    )
    st.add_argument("--json", action="store_true", help="print the raw JSON answers")
    st.set_defaults(func=_cmd_status)

    demo = sub.add_parser(
        "demo", help="daemon + simulated RSU and calibration vehicle on loopback, checked against the truth"
    )
    demo.add_argument("--preset", default="sil-west", help="simulator preset (default sil-west, 2 cameras)")
    demo.add_argument("--seed", type=_SEED, default=0, help="simulator seed, >= 0 (default 0)")
    demo.add_argument(
        "--rate", type=_positive_number, default=20.0, help="time acceleration, > 0 (default 20x)"
    )
    demo.add_argument(
        "--timeout",
        type=_positive_number,
        help="give up after this many seconds (default 300; 3600 with --images)",
    )
    demo.add_argument(
        "--ideal",
        action="store_true",
        help="the first simulator's world (cuboid boxes, no latency, IMU poses): every camera must calibrate",
    )
    demo.add_argument(
        "--keep",
        metavar="DIR",
        help="keep the daemon's recordings, results and reports in DIR (new or empty), plus simulation.mcap",
    )
    demo.add_argument(
        "--images",
        action="store_true",
        help="the cameras send rendered images (foxglove.CompressedImage) and the daemon's ONNX detector "
        "makes the boxes; replayed at the detector's pace (minutes); without --detector-model, the "
        "simulator's colour-key model on key-painted vehicles",
    )
    demo.add_argument(
        "--detector-model",
        metavar="ONNX",
        help="with --images: your detector (an ONNX export with COCO classes, fixed input size) on images "
        "of ordinarily painted vehicles",
    )
    demo.add_argument(
        "--detector-layout",
        choices=["yolov5", "yolov8", "yolox"],
        default="yolov8",
        help="output layout of --detector-model (default yolov8)",
    )
    demo.set_defaults(func=_cmd_demo)

    add_bridge_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=args.log_level or "WARNING", format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    try:
        code: int = args.func(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except ValidationError as err:
        print(f"error: {describe_validation_error(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (InputError, RecordingError, SimulationError) as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except RsucalError as err:
        from daemon.bus import BusError  # imported here: `rsucal simulate` should not load zenoh

        print(f"error: {err}", file=sys.stderr)
        # A daemon that cannot go on the bus (endpoint in use, bad Zenoh config) is a configuration error.
        return EXIT_BAD_INPUT if isinstance(err, BusError) else EXIT_FAILED
    except Exception as err:
        # The last line of defence: a bug must still not show a user a traceback. It is logged at DEBUG
        # (--log-level DEBUG shows it); tests/fuzz/test_fuzz_cli.py fails on this message.
        log.debug("internal error", exc_info=True)
        print(
            f"error: internal error in rsucal {args.command}: {type(err).__name__}: {err} "
            "(please report it; --log-level DEBUG shows where)",
            file=sys.stderr,
        )
        return EXIT_FAILED
    return code


if __name__ == "__main__":
    sys.exit(main())
