"""Every `rsucal` subcommand with random and hostile arguments: never a traceback, always a known exit code.

Each example is a command line built from the real options of a subcommand, each option absent, valid or
hostile (negative, zero, nan, huge numbers; empty, very long, non-UTF-8 or unicode text; paths that are
missing, directories, files in missing directories, /proc, /dev/null, garbage files, files of the wrong
kind), in random order, sometimes with unknown options, repeated options or stray words. main() runs
in-process, in a scratch working directory. A failure is any exception escaping main() (a traceback for
a user), main()'s last-resort "internal error" line, or an exit code other than 0-3; an exit 2 must come
with exactly one line on stderr.

Commands whose valid form runs long (simulate, demo, calibrate) always get at least one hostile value;
status only ever talks to 127.0.0.1 with a short time-out. The daemon never gets a usable config.
"""

from __future__ import annotations

import contextlib
import functools
import io
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import yaml
from fuzz_mcap import simulation, small_recording
from fuzzing import fuzz_settings, label, scratch_dir
from hypothesis import assume, given
from hypothesis import strategies as st

from daemon import cli
from daemon.bus import free_loopback_port

EXAMPLE_CONFIG = Path(__file__).resolve().parents[2] / "deploy" / "rsu.example.yaml"
DIR = scratch_dir("rsucal-fuzz-cli-")
KNOWN_EXIT_CODES = (0, 1, 2, 3)


@dataclass(frozen=True)
class Files:
    """Paths of every kind an option may be given."""

    camera_yaml: str
    vehicle_yaml: str
    mcap: str
    detections_yaml: str
    poses_yaml: str
    result_json: str
    truth_json: str
    zenoh_config: str
    hostile: tuple[str, ...]
    hostile_configs: tuple[str, ...]


@functools.cache
def files() -> Files:
    """Written once per process under DIR."""
    from pipeline.metrics import result_from_ground_truth
    from sim.files import format_toolbox_detections, format_toolbox_poses

    rec = small_recording()
    sim = simulation()
    camera_id = sim.cameras[0].camera_id
    detections = DIR / "detections.yaml"
    detections.write_text(format_toolbox_detections(sim.detections[camera_id][:40]))
    poses = DIR / "poses.yaml"
    poses.write_text(format_toolbox_poses(sim.poses[:200]))
    truth = sim.ground_truth[camera_id]
    truth_json = DIR / "truth.json"
    truth_json.write_text(truth.model_dump_json())
    result_json = DIR / "result.json"
    result_json.write_text(result_from_ground_truth(truth, rsu_id="fuzz").model_dump_json())

    zenoh_config = DIR / "client.json5"  # loopback only, as every endpoint here
    zenoh_config.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:1"] } }\n')
    (DIR / "a-dir").mkdir(exist_ok=True)
    garbage = DIR / "garbage.bin"
    garbage.write_bytes(bytes(range(256)) * 8)
    empty = DIR / "empty.yaml"
    empty.write_text("")
    a_list = DIR / "list.yaml"
    a_list.write_text("- 1\n- [2, 3]\n")
    hostile = (
        "",
        " ",
        "-",
        str(DIR / "missing.yaml"),
        str(DIR / "a-dir"),
        str(DIR / "a-dir") + "/",
        str(DIR / "missing-dir" / "file.json"),
        str(garbage),
        str(empty),
        str(a_list),
        str(garbage / "under-a-file"),
        "/proc/nope",
        "/proc/self/status",
        "/dev/null",
        "x" * 300,  # longer than a file name may be (ENAMETOOLONG)
        "/" + "d/" * 3000,  # longer than a path may be
        "é🙂.yaml",
        "\udcff\udcfe.yaml",  # an argument that was not UTF-8 (surrogateescape)
        str(rec.camera_yaml),  # a valid file of the wrong kind for most options
        str(truth_json),
    )
    configs = []
    for name, edit in (
        ("state-proc", {"storage": {"state_dir": "/proc/nope"}}),
        ("state-file", {"storage": {"state_dir": str(garbage)}}),
        ("bad-field", {"trigger": {"min_traversals": 1}}),
        ("bad-listen", {"zenoh": {"listen": ["not-an-endpoint"]}}),
    ):
        data = yaml.safe_load(EXAMPLE_CONFIG.read_text())
        for section, values in edit.items():
            data[section].update(values)
        if name != "bad-listen":
            data["zenoh"] = {"listen": [f"tcp/127.0.0.1:{free_loopback_port()}"]}
        path = DIR / f"rsu-{name}.yaml"
        path.write_text(yaml.safe_dump(data))
        configs.append(str(path))
    return Files(
        camera_yaml=str(rec.camera_yaml),
        vehicle_yaml=str(rec.vehicle_yaml),
        mcap=str(rec.path),
        detections_yaml=str(detections),
        poses_yaml=str(poses),
        result_json=str(result_json),
        truth_json=str(truth_json),
        zenoh_config=str(zenoh_config),
        hostile=hostile,
        hostile_configs=tuple(configs),
    )


# ---------------------------------------------------------------------------------------------- values

HOSTILE_NUMBERS = (
    "-1",
    "-3",
    "0",
    "-0",
    "nan",
    "-inf",
    "inf",
    "1e309",
    "1.5",
    "0x10",
    "9" * 400,
    "-" + "9" * 5000,  # beyond Python's int() digit limit
    "",
    " ",
    "one",
    "١٢",  # Arabic-Indic digits: int() accepts them
)
HOSTILE_WORDS = ("", " ", "-", "--", "nope", "a/b", "*", "**", "$*", "x" * 200, "é", "\udcff", "--out")
HOSTILE_ENDPOINTS = (
    "foo",
    "tcp/",
    "tcp",
    "/",
    "tcp/127.0.0.1",
    "tcp/127.0.0.1:99999",
    "tcp/127.0.0.1:-1",
    "udp/127.0.0.1:1",
    "tls/127.0.0.1:1",
    "tcp/[::1]:1",
    "unixsock-stream//nonexistent/socket",
    "tcp/127.0.0.1:1?x=y#z",
    "TCP/127.0.0.1:1",
    "tcp/127.0.0.1:1 tcp/127.0.0.1:2",
)
COMMANDS = ("simulate", "evaluate", "calibrate", "daemon", "status", "demo", "report", "access-control")
STRAY = ("--unknown", "-x", "stray", "--", "--help-me", "--seed=", "--out=")


@dataclass(frozen=True)
class Choice:
    """A drawn argument: its tokens and whether any of them was hostile."""

    tokens: tuple[str, ...]
    hostile: bool


@st.composite
def option(
    draw: st.DrawFn, name: str, valid: tuple[str, ...], hostile: tuple[str, ...], required: bool = False
) -> Choice:
    kinds = ["valid", "hostile"] if required else ["absent", "valid", "hostile", "bare"]
    kind = draw(st.sampled_from(kinds))
    if kind == "absent":
        return Choice((), False)
    if kind == "bare":  # the option without its value
        return Choice((name,), True)
    value = draw(st.sampled_from(valid if kind == "valid" else hostile))
    return Choice((name, value), kind == "hostile")


def flag(name: str) -> st.SearchStrategy[Choice]:
    return st.sampled_from([Choice((), False), Choice((name,), False), Choice((name, name), False)])


@st.composite
def command_line(draw: st.DrawFn) -> tuple[list[str], bool]:
    """(argv, whether any argument was hostile)."""
    f = files()
    paths = f.hostile
    command = draw(st.sampled_from(COMMANDS))
    seeds = ("0", "7", str(2**64))
    out_dir = str(DIR / "out")
    if command == "simulate":
        choices = [
            option("--preset", ("carla-like",), HOSTILE_WORDS),
            option("--seed", seeds, HOSTILE_NUMBERS),
            option("--out", (out_dir,), paths, required=True),
            option("--preview", (str(DIR / "out" / "p.png"),), paths),
        ]
    elif command == "evaluate":
        choices = [
            option("--calib", (f.result_json,), paths, required=True),
            option("--ground-truth", (f.truth_json,), paths, required=True),
            flag("--json"),
        ]
    elif command == "calibrate":
        source = draw(st.sampled_from(["mcap", "yaml", "both", "none"]))
        choices = [
            option("--camera", (f.camera_yaml,), paths, required=True),
            option("--vehicle", (f.vehicle_yaml,), paths, required=True),
            option("--out", (str(DIR / "r.json"),), paths, required=True),
            option("--camera-id", ("carla",), HOSTILE_WORDS),
            option("--station-id", ("4242",), HOSTILE_NUMBERS),
            option("--crs", ("EPSG:32632", "epsg:32633"), ("EPSG:4326", "EPSG:99999", "EPSG:", "utm", "")),
            option("--time-offset-ns", ("0", "-50000000"), HOSTILE_NUMBERS),
            option("--frame", ("utm", "local"), HOSTILE_WORDS),
            option(
                "--origin", ("456400,5428700",), ("1,2", "1,2,3", ",", "nan,1", "1e400,5", *HOSTILE_WORDS)
            ),
            option("--seed", seeds, HOSTILE_NUMBERS),
            option("--workers", ("1",), HOSTILE_NUMBERS),
            option("--max-v2x-std", ("0.1", "0.5"), HOSTILE_NUMBERS),
            flag("--verbose"),
        ]
        if source in ("mcap", "both"):
            choices.append(option("--mcap", (f.mcap,), paths, required=True))
        if source in ("yaml", "both"):
            choices.append(option("--detections", (f.detections_yaml,), paths, required=True))
            choices.append(option("--poses", (f.poses_yaml,), paths, required=True))
    elif command == "report":
        choices = [
            Choice((draw(st.sampled_from((f.result_json, *paths))),), False),  # the positional RESULT.json
            option("--vehicle", (f.vehicle_yaml,), paths, required=True),
            option("--mcap", (f.mcap,), paths, required=True),
            option("--station-id", ("4242",), HOSTILE_NUMBERS),
            option("--seed", seeds, HOSTILE_NUMBERS),
            option("--workers", ("1",), HOSTILE_NUMBERS),
            option("--max-v2x-std", ("0.1",), HOSTILE_NUMBERS),
            option("--out", (str(DIR / "report"),), paths, required=True),
        ]
    elif command == "access-control":
        choices = [
            option("--config", f.hostile_configs, paths, required=True),
            option("--base", (f.zenoh_config,), paths, required=True),
            option("--out", (str(DIR / "acl.json5"),), paths, required=True),
        ]
    elif command == "daemon":
        choices = [option("--config", f.hostile_configs, paths, required=True)]
    elif command == "status":
        free = f"tcp/127.0.0.1:{free_loopback_port()}"
        choices = [
            option("--connect", (free,), HOSTILE_ENDPOINTS, required=True),
            option("--connect", (free,), HOSTILE_ENDPOINTS),
            option("--zenoh-config", (f.zenoh_config,), paths),
            option("--rsu", ("r1",), HOSTILE_WORDS),
            option("--camera", ("c1",), HOSTILE_WORDS),
            # Always a time-out, and a short one when valid: every run waits for it.
            option("--timeout", ("0.05", "0.2"), HOSTILE_NUMBERS, required=True),
            flag("--json"),
        ]
    else:  # demo
        choices = [
            option("--preset", ("single-traversal",), HOSTILE_WORDS),
            option("--seed", seeds, HOSTILE_NUMBERS),
            option("--rate", ("50",), HOSTILE_NUMBERS),
            option("--timeout", ("60",), HOSTILE_NUMBERS),
        ]
    drawn = [draw(choice) if isinstance(choice, st.SearchStrategy) else choice for choice in choices]
    drawn = draw(st.permutations(drawn))
    stray = draw(st.lists(st.sampled_from(STRAY), max_size=2))
    tokens = [token for choice in drawn for token in choice.tokens] + stray
    # Mostly no global option: a bad --log-level stops argparse before the subcommand's own checks.
    prefix = draw(
        st.sampled_from([[]] * 5 + [["--log-level", "error"], ["--log-level", "LOUD"], ["--log-level"]])
    )
    hostile = (
        any(choice.hostile for choice in drawn) or bool(stray) or (prefix[1:] != ["error"] and bool(prefix))
    )
    return [*prefix, command, *tokens], hostile


# ------------------------------------------------------------------------------------------------ runs


@contextlib.contextmanager
def in_scratch_dir() -> Iterator[None]:
    """Relative paths (and what a hostile --out may create) land in DIR, never in the checkout."""
    previous = os.getcwd()
    os.chdir(DIR)
    try:
        yield
    finally:
        os.chdir(previous)


def run(argv: list[str]) -> tuple[int, str, str]:
    """main(argv) in-process -> (exit code, stdout, stderr); an exception escaping main fails the test."""
    out, err = io.StringIO(), io.StringIO()
    with in_scratch_dir(), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = cli.main(argv)
        except SystemExit as stop:  # argparse: --help, --version, usage errors
            code = stop.code if isinstance(stop.code, int) else 0
    return code, out.getvalue(), err.getvalue()


def check(argv: list[str], code: int, stdout: str, stderr: str) -> None:
    command = next((token for token in argv if token in COMMANDS), "no command")
    label(f"{command} exit {code}")
    assert code in KNOWN_EXIT_CODES, (argv, code, stderr)
    assert "Traceback" not in stderr + stdout, (argv, stderr)
    assert "internal error" not in stderr, (argv, stderr)
    if code == 2:
        assert len(stderr.strip().splitlines()) == 1, (argv, stderr)
        assert stderr.strip(), argv


@fuzz_settings(2.0)
@given(case=command_line())
def test_every_subcommand_with_hostile_arguments(case: tuple[list[str], bool]) -> None:
    argv, hostile = case
    command = next(token for token in argv if token in COMMANDS)
    # A fully valid simulate/demo/calibrate/report is a long run, tested elsewhere (tests/daemon, scenarios).
    assume(hostile or command in ("evaluate", "status", "daemon", "access-control"))
    check(argv, *run(argv))


WORDS = st.sampled_from([*COMMANDS, "--help", "-h", "--version", *STRAY, *HOSTILE_WORDS, *HOSTILE_NUMBERS])


@fuzz_settings(0.5)
@given(argv=st.lists(st.one_of(WORDS, st.text(max_size=12)), min_size=0, max_size=5))
def test_random_words_never_reach_a_traceback(argv: list[str]) -> None:
    # Random words rarely form a valid command; the few that would run long are left to the test above.
    assume(
        not any(word in ("simulate", "demo", "status", "calibrate", "daemon", "report") for word in argv[:1])
    )
    assume(not (argv[:1] == ["evaluate"] and len(argv) > 4))
    check(argv, *run(argv))
