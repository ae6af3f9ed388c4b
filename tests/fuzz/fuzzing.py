"""Shared fuzzing strategies for tests/fuzz: junk values, structure-aware mutations, byte mutations.

Example counts follow tests/schemas/test_models.py: every fuzz test runs RSUCAL_FUZZ_EXAMPLES examples
(default 100: about 20 s for the directory on 2 idle cores) times its share. With
RSUCAL_FUZZ_EXAMPLES=10000 (about 15 CPU minutes) each decoder gets at least 10,000 inputs:
  Decoder.decode                  60,000: 6 tests x 10,000 (bytes, JSON, mutations, byte edits, keys,
                                          well-formed but wrong values)
  load_intrinsics / load_vehicle / load_daemon_config / load_toolbox_detections / load_toolbox_poses
                                  10,000 each (plus 2,500 each of the toolbox pair via load_offline_inputs)
  read_recording                  10,000: 5,000 truncated + 5,000 corrupted files
  read_window, iter_v2x           10,000 corrupted files each
  load_offline_inputs             10,000: 5,000 damaged recordings + 2,500 + 2,500 damaged YAML pairs
  cli.main calibrate                 200: each runs a full calibration (~1 s); the decoding it does is
                                          load_offline_inputs' (above)
Every test is derandomized and keeps no example database, so CI and a developer see the same inputs.
"""

from __future__ import annotations

import atexit
import copy
import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from hypothesis import HealthCheck, currently_in_test_context, event, settings
from hypothesis import strategies as st

FUZZ_EXAMPLES = int(os.environ.get("RSUCAL_FUZZ_EXAMPLES", "100"))
# Deeper than this, YAML input currently crashes the loaders (RecursionError in json.dumps from ~1,000
# levels, a segfault in libyaml from ~25,000): those are pinned by xfail tests in test_fuzz_loaders.py,
# so the random inputs stay below them and keep testing everything else.
MAX_NESTING = 200


def fuzz_settings(share: float = 1.0, *, slow_data: bool = False) -> settings:
    """FUZZ_EXAMPLES x share examples (at least 5), reproducible. `slow_data`: inputs are whole files or
    long payloads, whose generation Hypothesis would otherwise flag as too slow."""
    return settings(
        max_examples=max(5, round(FUZZ_EXAMPLES * share)),
        deadline=None,
        derandomize=True,
        database=None,
        print_blob=False,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large] if slow_data else [],
    )


def scratch_dir(prefix: str) -> Path:
    """A temporary directory for the files a test module writes, removed when the process exits (the
    tests write thousands of inputs, so pytest's per-test tmp_path would be both slow and huge)."""
    directory = Path(tempfile.mkdtemp(prefix=prefix))
    atexit.register(shutil.rmtree, directory, ignore_errors=True)
    return directory


def label(outcome: str) -> None:
    """Count an outcome in --hypothesis-show-statistics (no-op outside a Hypothesis test)."""
    if currently_in_test_context():
        event(outcome)


# ---------------------------------------------------------------------------------------------- junk values


@dataclass(frozen=True)
class Raw:
    """A token written into JSON text verbatim (1e400, NaN, a bare word): what json.dumps cannot make."""

    text: str


@dataclass(frozen=True)
class Pairs:
    """A JSON object as written, key order and duplicate keys included."""

    items: tuple[tuple[str, Any], ...]


HUGE_NUMBERS = st.sampled_from(
    [10**19, 2**63, 2**64, -(2**63) - 1, 10**40, 10**400, 1e308, -1e308, 5e-324, -0.0]
)
SPECIAL_TOKENS = st.sampled_from(
    ["NaN", "Infinity", "-Infinity", "1e400", "-1e400", "1E999", "0x10", "01"]
).map(Raw)
long_strings = st.integers(200, 5_000).map(lambda n: "x" * n) | st.text(min_size=100, max_size=400)
unicode_strings = st.text(
    st.characters(codec="utf-8", exclude_categories=("Cs",)), min_size=1, max_size=20
) | st.sampled_from(["\u202e", "\ufeff", "é", "\U0001f697", "\x00", "cam\u0301", "\ud7ff", "Ⅻ"])
scalars = (
    st.none()
    | st.booleans()
    | st.integers()
    | HUGE_NUMBERS
    | st.floats()
    | st.text(max_size=20)
    | unicode_strings
)
json_values = st.recursive(
    scalars,
    lambda children: (
        st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=10), children, max_size=5)
    ),
    max_leaves=30,
)


@st.composite
def deep_nesting(draw: st.DrawFn) -> Any:
    """A list or object nested up to MAX_NESTING levels around a scalar."""
    depth = draw(st.integers(2, MAX_NESTING))
    value: Any = draw(scalars)
    as_object = draw(st.booleans())
    for _ in range(depth):
        value = {"a": value} if as_object else [value]
    return value


junk = (
    json_values
    | SPECIAL_TOKENS
    | HUGE_NUMBERS
    | long_strings
    | unicode_strings
    | deep_nesting()
    | st.sampled_from([math.nan, math.inf, -math.inf, "", "1", "1.5", "true", [], {}, 0, -1, 1, 1.5])
)


# ---------------------------------------------------------------------------------------------- structure

NodePath = tuple[str | int, ...]


def node_paths(value: Any, path: NodePath = ()) -> list[NodePath]:
    """Every node's path (the root is ())."""
    paths = [path]
    if isinstance(value, dict):
        for key, child in value.items():
            paths += node_paths(child, (*path, key))
    elif isinstance(value, list):
        for index, child in enumerate(value):
            paths += node_paths(child, (*path, index))
    return paths


def _get(value: Any, path: NodePath) -> Any:
    for part in path:
        value = value[part]
    return value


def _type_swapped(value: Any) -> Any:
    """The same content in another JSON type: 12 -> "12", "12" -> 12 if numeric, [x] -> {"0": x}..."""
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, int | float):
        return str(value)
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return [value]
    if isinstance(value, list):
        return {str(i): v for i, v in enumerate(value)}
    if isinstance(value, dict):
        return list(value.values())
    return False


MUTATIONS = ("replace", "delete", "add_key", "duplicate", "type_swap", "duplicate_key")


@st.composite
def mutated(draw: st.DrawFn, good: Any, extra: st.SearchStrategy[Any] = junk) -> Any:
    """`good` (a parsed JSON/YAML document) after 1-3 structural mutations: a node replaced by junk or
    its own value in another type, a key or item deleted, duplicated or added. Duplicate keys come back as
    `Pairs`, verbatim tokens as `Raw` (see dump_json)."""
    doc = copy.deepcopy(good)
    for _ in range(draw(st.integers(1, 3), label="mutations")):
        paths = node_paths(doc)
        path = draw(st.sampled_from(paths), label="path")
        kind = draw(st.sampled_from(MUTATIONS), label="kind")
        node = _get(doc, path)
        if kind in ("replace", "type_swap") or (kind == "delete" and not path):
            # Copies: a drawn [] or {} is shared with the strategy and later mutations must not reach it.
            new = copy.deepcopy(draw(extra) if kind != "type_swap" else _type_swapped(node))
            if not path:
                doc = new
            else:
                _get(doc, path[:-1])[path[-1]] = new
        elif kind == "delete":
            parent = _get(doc, path[:-1])
            del parent[path[-1]]
        elif kind == "add_key" and isinstance(node, dict):
            key = draw(st.sampled_from(["extra", "", "x1", "camera_id", "é"]) | st.text(max_size=8))
            node[key] = copy.deepcopy(draw(extra))
        elif kind == "duplicate" and path and isinstance(_get(doc, path[:-1]), list):
            _get(doc, path[:-1]).insert(path[-1], copy.deepcopy(node))
        elif kind == "duplicate_key" and isinstance(node, dict) and node:
            key = draw(st.sampled_from(sorted(node, key=str)))
            items = [*node.items(), (key, copy.deepcopy(draw(extra | st.just(node[key]))))]
            pairs = Pairs(tuple((str(k), v) for k, v in items))
            if not path:
                return pairs  # nothing below the root can be mutated after this
            _get(doc, path[:-1])[path[-1]] = pairs
    return doc


def dump_json(value: Any) -> str:
    """JSON text of a mutated document: NaN/Infinity for non-finite floats, Raw tokens, duplicate keys."""
    if isinstance(value, Raw):
        return value.text
    if isinstance(value, Pairs):
        return "{" + ", ".join(f"{json.dumps(k)}: {dump_json(v)}" for k, v in value.items) + "}"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))}: {dump_json(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list):
        return "[" + ", ".join(dump_json(v) for v in value) + "]"
    return json.dumps(value, allow_nan=True)


def _yaml_ready(value: Any) -> Any:
    """Raw tokens become strings and duplicate keys collapse: yaml.safe_dump can write the rest."""
    if isinstance(value, Raw):
        return value.text
    if isinstance(value, Pairs):
        return {k: _yaml_ready(v) for k, v in value.items}
    if isinstance(value, dict):
        return {k: _yaml_ready(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_yaml_ready(v) for v in value]
    return value


def dump_yaml(value: Any, style: str) -> str:
    """YAML text of a mutated document: block or flow style, or the JSON text (YAML reads JSON; that
    form keeps duplicate keys and verbatim tokens)."""
    if style == "json":
        return dump_json(value)
    return yaml.safe_dump(
        _yaml_ready(value), default_flow_style=style == "flow", allow_unicode=True, width=10**6
    )


# ---------------------------------------------------------------------------------------------- bytes

INTERESTING_BYTES = b'\x00\xff\x80"{}[]\\:,-\n\r\t #&*!|>%@`'


@st.composite
def mutated_bytes(draw: st.DrawFn, good: bytes, max_ops: int = 4) -> bytes:
    """`good` after 1..max_ops byte-level edits: bit flips, truncation, deletion, insertion, duplication."""
    data = bytearray(good)
    for _ in range(draw(st.integers(1, max_ops), label="edits")):
        kind = draw(st.sampled_from(["flip", "flip", "truncate", "delete", "insert", "duplicate", "set"]))
        at = draw(st.integers(0, max(0, len(data) - 1)), label="at")
        if kind == "flip" and data:
            data[at] ^= draw(st.integers(1, 255))
        elif kind == "set" and data:
            data[at] = draw(st.sampled_from(INTERESTING_BYTES))
        elif kind == "truncate":
            del data[at:]
        elif kind == "delete":
            del data[at : at + draw(st.integers(1, 16))]
        elif kind == "insert":
            data[at:at] = draw(
                st.binary(min_size=1, max_size=16) | st.sampled_from([b"\x00", b"\xc3", b"\xed\xa0\x80"])
            )
        elif kind == "duplicate":
            data[at:at] = data[at : at + draw(st.integers(1, 64))]
    return bytes(data)


@st.composite
def mutated_lines(draw: st.DrawFn, good: str) -> str:
    """`good` text after 1-3 line edits: a line deleted, duplicated, swapped, re-indented or cut short."""
    lines = good.split("\n")
    for _ in range(draw(st.integers(1, 3))):
        if not lines:
            break
        at = draw(st.integers(0, len(lines) - 1))
        kind = draw(st.sampled_from(["delete", "duplicate", "swap", "indent", "cut"]))
        if kind == "delete":
            del lines[at]
        elif kind == "duplicate":
            lines.insert(at, lines[at])
        elif kind == "swap":
            other = draw(st.integers(0, len(lines) - 1))
            lines[at], lines[other] = lines[other], lines[at]
        elif kind == "indent":
            lines[at] = " " * draw(st.integers(1, 5)) + lines[at]
        else:
            lines[at] = lines[at][: draw(st.integers(0, len(lines[at])))]
    return "\n".join(lines)


def document_inputs(good_text: str, parse: Callable[[str], Any]) -> st.SearchStrategy[bytes]:
    """Every kind of input a file decoder gets: arbitrary bytes, arbitrary documents, structural
    mutations of the good document (block, flow or JSON style), byte and line edits of the good text."""
    good = parse(good_text)
    styles = st.sampled_from(["block", "flow", "json"])
    return st.one_of(
        st.binary(max_size=300),
        st.tuples(json_values, styles).map(lambda d: dump_yaml(*d).encode("utf-8")),
        st.tuples(mutated(good), styles).map(lambda d: dump_yaml(*d).encode("utf-8")),
        st.tuples(mutated(good), styles).map(lambda d: dump_yaml(*d).encode("utf-8")),
        mutated_bytes(good_text.encode("utf-8")),
        mutated_lines(good_text).map(lambda text: text.encode("utf-8")),
    )
