"""`rsucal` subcommands: argument parsing and exit codes only; each command is a plain call into the packages.

Exit codes: 0 success, 2 bad input (the message names file and field), 3 calibration refused.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from pydantic import ValidationError

from pipeline.errors import InputError, RecordingError, RsucalError
from schemas.common import describe_validation_error

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_REFUSED = 3

log = logging.getLogger("rsucal")


def _cmd_simulate(args: argparse.Namespace) -> int:
    from daemon.recording import write_simulation_mcap
    from pipeline.loaders import write_simulation_files
    from pipeline.simulate import PRESETS, simulate

    if args.preset not in PRESETS:
        raise InputError(
            "--preset", f"unknown preset {args.preset!r}; choose one of {', '.join(sorted(PRESETS))}"
        )
    result = simulate(args.preset, seed=args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    mcap_path = write_simulation_mcap(result, out / "recording.mcap")
    written = [mcap_path, *write_simulation_files(result, out)]
    if args.preview:
        from pipeline.preview import write_preview

        written.append(write_preview(result, Path(args.preview)))
    frames = sum(len(f) for f in result.detections.values())
    boxes = sum(len(fr.boxes) for f in result.detections.values() for fr in f)
    print(
        f"preset {args.preset} seed {args.seed}: {len(result.cameras)} camera(s), {frames} frames, "
        f"{boxes} boxes, {len(result.poses)} vehicle poses, {result.traffic_count} other vehicles"
    )
    for path in written:
        print(f"  wrote {path}")
    return EXIT_OK


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from pipeline.loaders import load_calibration_result, load_ground_truth
    from pipeline.metrics import evaluate_against_ground_truth, format_evaluation

    result = load_calibration_result(Path(args.calib))
    truth = load_ground_truth(Path(args.ground_truth))
    evaluation = evaluate_against_ground_truth(result, truth)
    if args.json:
        print(json.dumps(evaluation.as_dict(), indent=2))
    else:
        print(format_evaluation(evaluation))
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rsucal", description="Automatic roadside camera calibration.")
    parser.add_argument("--log-level", default="WARNING", help="logging level (default WARNING)")
    sub = parser.add_subparsers(dest="command", required=True)

    sim = sub.add_parser(
        "simulate", help="generate a seeded RSU scenario: MCAP, toolbox YAML pair, ground truth"
    )
    sim.add_argument("--preset", default="sil-west", help="scenario preset (default sil-west)")
    sim.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sim.add_argument("--out", required=True, help="output directory")
    sim.add_argument("--preview", help="write a PNG of one busy frame here")
    sim.set_defaults(func=_cmd_simulate)

    ev = sub.add_parser(
        "evaluate", help="score a calibration against simulator ground truth (paper Sec. IV-B)"
    )
    ev.add_argument("--calib", required=True, help="CalibrationResult JSON")
    ev.add_argument("--ground-truth", required=True, help="ground_truth.json of the same camera")
    ev.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ev.set_defaults(func=_cmd_evaluate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    try:
        code: int = args.func(args)
    except ValidationError as err:
        print(f"error: {describe_validation_error(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (InputError, RecordingError) as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except RsucalError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_FAILED
    return code


if __name__ == "__main__":
    sys.exit(main())
