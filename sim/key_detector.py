"""A colour-key vehicle detector as an ONNX model (YOLOv8 output layout) for the simulator's keyed images.

No trained vehicle detector ships with rsucal (none in the package registry comes with its weights; models
are never downloaded), yet `rsucal demo --images` should run the daemon's whole image path: JPEG in,
letterbox, onnxruntime, the YOLOv8 decoder, NMS, the label map, DetectionFrames out. This module builds a
model that does that on `sim.images.render_images(..., keyed=True)` images, where every vehicle (wheels
included) is painted in one of four key colours no other surface has. It is not a learned detector: it
finds pixels of those colours, and boxes around connected areas of them, with ordinary ONNX operators:

1. key mask: a pixel is a vehicle's when max(R, B) > KEY_MIN_LEVEL and G < KEY_OTHER * max(R, B)
   (saturated red, blue, magenta, however the sun shades them): class red (0) when B < KEY_HUE_RATIO * R,
   blue (1) when R < KEY_HUE_RATIO * B, else magenta (2); or when G > KEY_MIN_LEVEL and max(R, B) <
   KEY_OTHER * G: green (3);
2. per CELL x CELL cell and class (MaxPool, AveragePool): the extent of its key pixels (min x, min y,
   max x + 1, max y + 1, network px) and the fraction of the cell they cover;
3. connected cells (per class, JOIN_CELLS: neighbours, and sideways across one empty cell) share their
   extents: a Loop of MaxPool steps until nothing changes (at most cells-many), so every cell of one area
   holds the area's box and its best coverage fraction as the score;
4. output (1, 4 + 4, 4 * cells): cx, cy, w, h and one-hot class scores per (class, cell), YOLOv8's layout;
   the daemon's NMS keeps one of each area's identical boxes.

Two vehicles of one key colour whose areas touch (within a cell, or two sideways) come out as one box,
and a vehicle cut by an occluder wider than a cell as two, as a simple detector would. The file ships as
KEY_DETECTOR_MODEL; `python -m sim.key_detector` rebuilds it (needs the `onnx` package, in the test
extra), and a test checks the shipped file is what this code builds.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

KEY_DETECTOR_MODEL = Path(__file__).parent / "models" / "key_detector.onnx"
INPUT_WIDTH = 960  # a 1920 x 1200 (or 1080) camera image at half scale, letterboxed
INPUT_HEIGHT = 608
CELL = 8  # network px per cell side
# Cells joined in one step (rows, columns): neighbours, and across one empty cell sideways, so a vehicle
# behind a pole (a gap of up to a cell, 16 px of a 1920 px image) stays one box. On sil-north in the ideal
# world 3 x 3 left a quarter of the calibration vehicle's boxes split (IoU < 0.8 with the truth), 3 x 5 an
# eighth, 3 x 7 merged more neighbours than it joined.
JOIN_CELLS = (3, 5)
KEY_MIN_LEVEL = 0.1
KEY_OTHER = 0.3
KEY_HUE_RATIO = 0.5
KEY_CLASSES = ("red", "blue", "magenta", "green")  # the model's class ids 0-3 (sim.images.KEY_PAINTS order)
OPSET = 17


def build_model(width: int = INPUT_WIDTH, height: int = INPUT_HEIGHT, cell: int = CELL) -> Any:
    """The key detector (an onnx.ModelProto) for a fixed (1, 3, height, width) RGB [0, 1] input."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    if width % cell or height % cell:
        raise ValueError(f"width {width} and height {height} must be multiples of the cell {cell}")
    rows, cols = height // cell, width // cell
    classes = len(KEY_CLASSES)
    cells = rows * cols
    nodes: list[Any] = []

    def const(name: str, value: Any) -> str:
        tensor = numpy_helper.from_array(np.asarray(value), name=f"{name}_value")
        nodes.append(helper.make_node("Constant", [], [name], value=tensor))
        return name

    def node(op: str, inputs: list[str], output: str, **attributes: Any) -> str:
        nodes.append(helper.make_node(op, inputs, [output], **attributes))
        return output

    def f32(value: float) -> Any:
        return np.array(value, dtype=np.float32)

    def i64(values: list[int]) -> Any:
        return np.array(values, dtype=np.int64)

    def channel(index: int, name: str) -> str:
        starts, ends, axes = const(f"{name}_s", i64([index])), const(f"{name}_e", i64([index + 1])), "axis1"
        return node("Slice", ["images", starts, ends, axes], name)

    # 1. the key mask per class, (1, 3, H, W) of 0/1
    const("axis1", i64([1]))
    red, green, blue = channel(0, "r"), channel(1, "g"), channel(2, "b")
    level = node("Max", [red, blue], "level")
    bright = node("Greater", [level, const("min_level", f32(KEY_MIN_LEVEL))], "bright")
    other = const("key_other", f32(KEY_OTHER))
    green_limit = node("Mul", [level, other], "green_limit")
    keyed = node("And", [bright, node("Less", [green, green_limit], "no_green")], "keyed")
    ratio = const("hue_ratio", f32(KEY_HUE_RATIO))
    is_red = node("And", [keyed, node("Less", [blue, node("Mul", [red, ratio], "r_ratio")], "b_low")], "m0")
    is_blue = node("And", [keyed, node("Less", [red, node("Mul", [blue, ratio], "b_ratio")], "r_low")], "m1")
    either = node("Or", [is_red, is_blue], "red_or_blue")
    is_magenta = node("And", [keyed, node("Not", [either], "neither")], "m2")
    green_bright = node("Greater", [green, "min_level"], "g_bright")
    red_blue_low = node("Less", [level, node("Mul", [green, other], "rb_limit")], "rb_low")
    is_green = node("And", [green_bright, red_blue_low], "m3")
    masks = [
        node("Cast", [m], f"{m}_f", to=TensorProto.FLOAT) for m in (is_red, is_blue, is_magenta, is_green)
    ]
    mask = node("Concat", masks, "mask", axis=1)

    # 2. per cell and class: extents of the key pixels (as maxima: W - x and H - y for the minima) and cover
    def coordinate(name: str, start: int, limit: int, delta: int, shape: list[int]) -> str:
        values = node(
            "Range",
            [const(f"{name}_0", f32(start)), const(f"{name}_1", f32(limit)), const(f"{name}_d", f32(delta))],
            f"{name}_range",
        )
        return node("Reshape", [values, const(f"{name}_shape", i64(shape))], name)

    right = coordinate("x_right", 1, width + 1, 1, [1, 1, 1, width])  # x + 1
    left = coordinate("x_left", width, 0, -1, [1, 1, 1, width])  # W - x
    bottom = coordinate("y_bottom", 1, height + 1, 1, [1, 1, height, 1])  # y + 1
    top = coordinate("y_top", height, 0, -1, [1, 1, height, 1])  # H - y
    pool = {"kernel_shape": [cell, cell], "strides": [cell, cell]}
    extents = [
        node("MaxPool", [node("Mul", [mask, coord], f"{name}_px")], f"{name}_cell", **pool)
        for name, coord in (("left", left), ("top", top), ("right", right), ("bottom", bottom))
    ]
    cover = node("AveragePool", [mask], "cover", **pool)
    state = node("Concat", [*extents, cover], "state0", axis=1)  # (1, 5 * classes, rows, cols): by quantity
    occupied = node(
        "Cast", [node("Greater", [cover, const("zero", f32(0.0))], "has_key")], "occ", to=TensorProto.FLOAT
    )
    occupied_all = node("Tile", [occupied, const("five", i64([1, 5, 1, 1]))], "occupied")

    # 3. connected cells share their extents and best cover: MaxPool over JOIN_CELLS on occupied cells until
    # stable
    body_nodes = [
        helper.make_node(
            "MaxPool",
            ["s_in"],
            ["s_pooled"],
            kernel_shape=list(JOIN_CELLS),
            pads=[JOIN_CELLS[0] // 2, JOIN_CELLS[1] // 2] * 2,
            strides=[1, 1],
        ),
        helper.make_node("Mul", ["s_pooled", occupied_all], ["s_out"]),
        helper.make_node("Sub", ["s_out", "s_in"], ["s_grown"]),
        helper.make_node("ReduceMax", ["s_grown"], ["s_change"], keepdims=0),
        helper.make_node("Constant", [], ["s_zero"], value=numpy_helper.from_array(f32(0.0), "s_zero_v")),
        helper.make_node("Greater", ["s_change", "s_zero"], ["cond_out"]),
    ]
    state_type = [1, 5 * classes, rows, cols]
    body = helper.make_graph(
        body_nodes,
        "grow",
        [
            helper.make_tensor_value_info("iteration", TensorProto.INT64, []),
            helper.make_tensor_value_info("cond_in", TensorProto.BOOL, []),
            helper.make_tensor_value_info("s_in", TensorProto.FLOAT, state_type),
        ],
        [
            helper.make_tensor_value_info("cond_out", TensorProto.BOOL, []),
            helper.make_tensor_value_info("s_out", TensorProto.FLOAT, state_type),
        ],
    )
    trips = const("max_trips", np.array(cells, dtype=np.int64))
    go = const("go", np.array(True))
    grown = node("Loop", [trips, go, state], "grown", body=body)

    # 4. YOLOv8 rows: (class, cell) -> cx, cy, w, h, one-hot class score
    def part(index: int, name: str) -> str:
        starts = const(f"{name}_s", i64([index * classes]))
        ends = const(f"{name}_e", i64([(index + 1) * classes]))
        return node("Slice", [grown, starts, ends, "axis1"], name)

    x1 = node("Sub", [const("width", f32(width)), part(0, "g_left")], "x1")
    y1 = node("Sub", [const("height", f32(height)), part(1, "g_top")], "y1")
    x2, y2, score = part(2, "x2"), part(3, "y2"), part(4, "score")
    half = const("half", f32(0.5))
    cx = node("Mul", [node("Add", [x1, x2], "x_sum"), half], "cx")
    cy = node("Mul", [node("Add", [y1, y2], "y_sum"), half], "cy")
    w = node("Sub", [x2, x1], "w")
    h = node("Sub", [y2, y1], "h")
    axes1 = const("unsqueeze_axes", i64([1]))
    box = node(
        "Concat", [node("Unsqueeze", [v, axes1], f"{v}_u") for v in (cx, cy, w, h)], "box5", axis=1
    )  # (1, 4, 3, rows, cols)
    boxes = node("Reshape", [box, const("box_shape", i64([1, 4, classes * cells]))], "boxes")
    flat_score = node("Reshape", [score, const("score_shape", i64([1, 1, classes, cells]))], "score_rows")
    one_hot = const("one_hot", np.eye(classes, dtype=np.float32).reshape(1, classes, classes, 1))
    score_shape = const("score_out_shape", i64([1, classes, classes * cells]))
    scores = node("Reshape", [node("Mul", [flat_score, one_hot], "class_grid"), score_shape], "scores")
    node("Concat", [boxes, scores], "output", axis=1)

    graph = helper.make_graph(
        nodes,
        "rsucal-key-detector",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, height, width])],
        [helper.make_tensor_value_info("output", TensorProto.FLOAT, [1, 4 + classes, classes * cells])],
    )
    model = helper.make_model(
        graph,
        opset_imports=[helper.make_opsetid("", OPSET)],
        producer_name="rsucal sim.key_detector",
        producer_version="1",
        doc_string="colour-key vehicle detector for the simulator's keyed images (not a learned model)",
    )
    model.ir_version = 8
    onnx.checker.check_model(model, full_check=True)
    return model


def model_bytes() -> bytes:
    """The serialized model, exactly as KEY_DETECTOR_MODEL holds it."""
    return bytes(build_model().SerializeToString())


def main() -> None:
    KEY_DETECTOR_MODEL.parent.mkdir(parents=True, exist_ok=True)
    KEY_DETECTOR_MODEL.write_bytes(model_bytes())
    print(f"wrote {KEY_DETECTOR_MODEL} ({KEY_DETECTOR_MODEL.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
