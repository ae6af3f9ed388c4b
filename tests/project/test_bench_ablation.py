"""bench.ablation: the realistic world with parts taken out, in its own processes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from bench.ablation import summary

ROOT = Path(__file__).resolve().parents[2]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "bench.ablation", *args], cwd=ROOT, capture_output=True, text=True, timeout=300
    )


def test_without_body_detector_and_gnss_errors_a_realistic_scene_is_calibrated(tmp_path: Path) -> None:
    # sil-south seed 0 in the realistic world is refused (0.22 m off, std 0.20 m, session 19); with the
    # calibration vehicle drawn as its cuboid, an exact detector and a perfect receiver it is accepted
    # within centimetres (0.04 m): what is left is the CAMs' rate, the latency and the road (its profile
    # still says 3 / 6 cm of wander, which the std carries).
    out = tmp_path / "runs.json"
    done = _run(
        "--remove",
        "body,detector,gnss",
        "--presets",
        "sil-south",
        "--seeds",
        "1",
        "--jobs",
        "1",
        "--json",
        str(out),
    )
    assert done.returncode == 0, done.stderr
    assert (
        "removed body, detector, gnss; the vehicle's GNSS wander as drawn: 1 runs: 1 accepted" in done.stdout
    )
    runs = json.loads(out.read_text())["runs"]
    assert runs[0]["verdict"] == "accepted" and runs[0]["position_error_m"] < 0.1


def test_an_unknown_part_is_a_one_line_error() -> None:
    done = _run("--remove", "body,weather")
    assert done.returncode == 2
    assert "--remove: unknown part(s) weather (known: body, corners" in done.stderr
    assert "Traceback" not in done.stderr
    done = _run("--gnss-wander", "0.03,-1")
    assert done.returncode == 2 and "--gnss-wander" in done.stderr and "Traceback" not in done.stderr


def test_the_summary_counts_accepted_runs_beyond_their_stds() -> None:
    def run(verdict: str, error_m: float, std_m: float) -> dict[str, object]:
        return {
            "verdict": verdict,
            "position_error_m": error_m,
            "position_std_m": std_m,
            "rotation_error_deg": 0.1,
            "rotation_std_deg": 0.1,
        }

    runs = [
        run("accepted", 0.3, 0.05),
        run("accepted", 0.05, 0.05),
        run("refused", 2.0, 0.5),
        {"verdict": "refused"},
    ]
    assert summary(runs).startswith(
        "4 runs: 2 accepted, 0 false accepts, 1 accepted beyond 3 std; "
        "2 poses within 1 m / 1 deg: error median 0.175 m"
    )
