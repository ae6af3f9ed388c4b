"""What each part of the realistic world costs: bench.accuracy's runs with parts of that world taken out.

    python -m bench.ablation --remove body,detector --presets sil-north,crowned-road --seeds 3
    python -m bench.ablation --remove body,detector --gnss-wander 0,0 --seeds 3

Every run is bench.accuracy's (simulate, calibrate every camera on the assumed clock 0, evaluate), in the
realistic world with the named parts removed from it:

- `body`: the calibration vehicle drawn as its data-sheet cuboid (a body the template can describe);
- `corners`: its plan-view corners sharp (every corner radius 1 cm);
- `detector`: the detector's per-camera bias (scale, edge offsets) and its box jitter at 0 (misses, false
  positives, merges and the visible outline stay);
- `gnss`: a perfect GNSS receiver; `gnss-height`: no height error at all; `gnss-wander`: no wander.

An instrument, not a world: the parts are switched off by replacing the simulator's functions and
settings in the worker processes (sim.simulate's body and detector, sim.v2x.GnssSpec.rtk_fixed), so what
is measured is exactly the realistic world less those parts. `--gnss-wander H,V` gives the calibration
vehicle's profile that wander (VehicleProfile.gnss_wander_m, which the final fit takes for each drive-past's
GNSS error) instead of the world's default. Prints, per
setting, the accepted runs, false accepts, accepted runs beyond 3 reported std, and the error and std of
the poses within 1 m / 1 deg.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from typing import Any

from bench.accuracy import beyond_reported, is_false_accept, near_poses
from bench.common import CORE_PRESETS

PARTS = ("body", "corners", "detector", "gnss", "gnss-height", "gnss-wander")
CORE = ",".join(CORE_PRESETS)


def _remove(parts: frozenset[str], gnss_wander: tuple[float, float] | None) -> None:
    """Switch the named parts of the realistic world off in this process (see the module)."""
    import sim.presets as presets
    import sim.shapes as shapes
    import sim.simulate as simulate
    import sim.v2x as v2x

    receiver = v2x.GnssSpec.rtk_fixed()
    if "gnss" in parts:
        receiver = v2x.GnssSpec.perfect()
    if "gnss-height" in parts:
        receiver = replace(receiver, vertical_factor=1e-9)
    if "gnss-wander" in parts:
        receiver = replace(receiver, wander_sigma_m=0.0)
    v2x.GnssSpec.rtk_fixed = classmethod(lambda cls: receiver)  # type: ignore[method-assign, assignment]
    if "detector" in parts:
        detector = presets.world_detector

        def exact(config: Any) -> Any:
            return replace(
                detector(config), scale_bias=0.0, edge_bias_px=0.0, box_jitter_px=0.0, jitter_ar1=0.0
            )

        setattr(simulate, "world_detector", exact)  # noqa: B010 (sim.simulate imports it; replaced there)
    if "body" in parts:
        drawn = simulate._calibration_body

        def cuboid(config: Any, rng: Any) -> Any:
            shape, vehicle = drawn(config, rng)
            return shapes.cuboid_body(shape.length_m, shape.width_m, shape.height_m), vehicle

        simulate._calibration_body = cuboid
    if "corners" in parts:
        for ranges in shapes.TYPE_RANGES.values():
            for name in ranges:
                if name.endswith("radius_m") and not name.startswith("wheel"):
                    ranges[name] = (0.01, 0.01)
    if gnss_wander is not None:
        profiled = simulate._calibration_body

        def said(config: Any, rng: Any) -> Any:
            shape, vehicle = profiled(config, rng)
            return shape, vehicle.model_copy(update={"gnss_wander_m": gnss_wander})

        simulate._calibration_body = said


def _run(task: tuple[str, int]) -> list[dict[str, Any]]:
    from bench.accuracy import run_seed

    preset, seed = task
    return run_seed((preset, seed, False, None, None))


def summary(runs: Sequence[dict[str, Any]]) -> str:
    """One line: accepted, false accepts, accepted beyond 3 std; the poses within 1 m / 1 deg (each as
    bench.accuracy defines it)."""
    accepted = [r for r in runs if r["verdict"] == "accepted"]
    near = near_poses(runs)
    line = (
        f"{len(runs)} runs: {len(accepted)} accepted, {sum(map(is_false_accept, accepted))} false accepts, "
        f"{sum(map(beyond_reported, accepted))} accepted beyond 3 std; {len(near)} poses within 1 m / 1 deg"
    )
    if not near:
        return line
    med = statistics.median
    return line + (
        f": error median {med(r['position_error_m'] for r in near):.3f} m / "
        f"{med(r['rotation_error_deg'] for r in near):.3f} deg, std median "
        f"{med(r['position_std_m'] for r in near):.3f} m / "
        f"{med(r['rotation_std_deg'] for r in near):.3f} deg, "
        f"{sum(map(beyond_reported, near))} beyond 3 std"
    )


def _pair(text: str) -> tuple[float, float]:
    horizontal, vertical = (float(v) for v in text.split(","))
    if min(horizontal, vertical) < 0.0:
        raise ValueError("negative std")
    return horizontal, vertical


def main(argv: Sequence[str] | None = None) -> int:
    known = ", ".join(PARTS)
    parser = argparse.ArgumentParser(prog="python -m bench.ablation", description=__doc__.split("\n")[0])
    parser.add_argument("--remove", default="", help=f"comma-separated parts of the world: {known}")
    parser.add_argument("--presets", default=CORE, help="comma-separated presets (default: the core ones)")
    parser.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 (default 3)")
    parser.add_argument(
        "--gnss-wander",
        type=_pair,
        default=None,
        metavar="H,V",
        help="the vehicle profile's gnss_wander_m (m)",
    )
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument("--json", default=None, help="also write every run here")
    args = parser.parse_args(argv)
    parts = frozenset(p for p in args.remove.split(",") if p)
    if unknown := parts - set(PARTS):
        parser.error(f"--remove: unknown part(s) {', '.join(sorted(unknown))} (known: {known})")
    if args.seeds < 1 or args.jobs < 1:
        parser.error("--seeds and --jobs must be at least 1")
    tasks = [(preset, seed) for preset in args.presets.split(",") for seed in range(args.seeds)]
    with ProcessPoolExecutor(args.jobs, initializer=_remove, initargs=(parts, args.gnss_wander)) as pool:
        runs = [run for batch in pool.map(_run, tasks) for run in batch]
    removed = ", ".join(sorted(parts)) or "nothing"
    wander = "as drawn" if args.gnss_wander is None else f"{args.gnss_wander}"
    print(f"removed {removed}; the vehicle's GNSS wander {wander}: {summary(runs)}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as out:
            json.dump({"removed": sorted(parts), "gnss_wander": args.gnss_wander, "runs": runs}, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
