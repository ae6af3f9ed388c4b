"""Small ONNX "detectors" built here (no weights downloaded), with the output layout of each supported family.

The model cuts the network input into STRIDE x STRIDE cells. Each cell is a candidate box (the cell itself,
in network pixels) whose class scores are the mean red, green and blue of the cell in [0, 1]: class 0 is
red, 1 green, 2 blue, so a solid red rectangle is found as class 0 with score 1.0 in every cell it covers.
YOLOv5/v8 versions add, for every cell, a 1.25x larger box with 0.9x the scores: the duplicate NMS must
remove. The YOLOX version reads BGR in [0, 255] (its preprocessing) and is undecoded: grid offsets and
log sizes for strides 8, 16 and 32, the 8 and 16 levels all zero. Which pixels a cell sees therefore
tests the letterbox, the channel order and the scaling; its box tests the mapping back to image pixels.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

STRIDE = 32
CLASSES = 3  # red, green, blue
DUPLICATE_SCALE = 1.25
DUPLICATE_SCORE = 0.9
OPSET = 17


def _const(name: str, value: np.ndarray) -> onnx.NodeProto:
    tensor = numpy_helper.from_array(value, name=f"{name}_value")
    return helper.make_node("Constant", [], [name], value=tensor)


def cell_centres(width: int, height: int, stride: int = STRIDE) -> np.ndarray:
    """(n, 2) network px centres of the cells, row-major (as AveragePool + Reshape order them)."""
    ys, xs = np.mgrid[0 : height // stride, 0 : width // stride]
    return np.stack([(xs.ravel() + 0.5) * stride, (ys.ravel() + 0.5) * stride], axis=1)


def build_model(layout: str, width: int = 320, height: int = 256) -> onnx.ModelProto:
    """The cell detector for `layout` (yolov5, yolov8, yolox) with a fixed (1, 3, height, width) input."""
    if width % STRIDE or height % STRIDE:
        raise ValueError("width and height must be multiples of STRIDE")
    n = (width // STRIDE) * (height // STRIDE)
    nodes: list[onnx.NodeProto] = []
    source = "images"
    if layout == "yolox":
        # BGR 0..255 in: back to RGB 0..1, so the classes mean the same colours for every layout.
        nodes += [
            _const("rgb_index", np.array([2, 1, 0], dtype=np.int64)),
            helper.make_node("Gather", ["images", "rgb_index"], ["rgb"], axis=1),
            _const("inv255", np.array(1.0 / 255.0, dtype=np.float32)),
            helper.make_node("Mul", ["rgb", "inv255"], ["rgb01"]),
        ]
        source = "rgb01"
    nodes += [
        helper.make_node(
            "AveragePool", [source], ["pooled"], kernel_shape=[STRIDE] * 2, strides=[STRIDE] * 2
        ),
        _const("flat_shape", np.array([1, CLASSES, n], dtype=np.int64)),
        helper.make_node("Reshape", ["pooled", "flat_shape"], ["flat"]),
        helper.make_node("Transpose", ["flat"], ["cell_scores"], perm=[0, 2, 1]),  # (1, n, 3)
    ]
    centres = cell_centres(width, height)
    if layout in ("yolov5", "yolov8"):
        size = np.full((n, 2), float(STRIDE))
        cells = np.concatenate([centres, size], axis=1)
        duplicates = np.concatenate([centres, size * DUPLICATE_SCALE], axis=1)
        boxes = np.concatenate([cells, duplicates])[None].astype(np.float32)
        nodes += [
            _const("dup_factor", np.array(DUPLICATE_SCORE, dtype=np.float32)),
            helper.make_node("Mul", ["cell_scores", "dup_factor"], ["dup_scores"]),
            helper.make_node("Concat", ["cell_scores", "dup_scores"], ["class_scores"], axis=1),
            _const("boxes", boxes),
        ]
        if layout == "yolov5":
            nodes += [
                _const("objectness", np.ones((1, 2 * n, 1), dtype=np.float32)),
                helper.make_node("Concat", ["boxes", "objectness", "class_scores"], ["output"], axis=2),
            ]
            shape = [1, 2 * n, 5 + CLASSES]
        else:
            nodes += [
                helper.make_node("Concat", ["boxes", "class_scores"], ["rows"], axis=2),
                helper.make_node("Transpose", ["rows"], ["output"], perm=[0, 2, 1]),
            ]
            shape = [1, 4 + CLASSES, 2 * n]
    elif layout == "yolox":
        small = sum((width // s) * (height // s) for s in (8, 16))
        raw = np.zeros((1, n, 4), dtype=np.float32)
        raw[..., :2] = 0.5  # centre of the cell: (offset + grid) * stride
        raw[..., 2:] = math.log(1.0)  # exp(0) * stride: the cell's size
        nodes += [
            _const("raw_boxes", raw),
            _const("objectness", np.ones((1, n, 1), dtype=np.float32)),
            helper.make_node("Concat", ["raw_boxes", "objectness", "cell_scores"], ["level32"], axis=2),
            _const("levels_8_16", np.zeros((1, small, 5 + CLASSES), dtype=np.float32)),
            helper.make_node("Concat", ["levels_8_16", "level32"], ["output"], axis=1),
        ]
        shape = [1, small + n, 5 + CLASSES]
    else:
        raise ValueError(f"unknown layout {layout!r}")
    graph = helper.make_graph(
        nodes,
        f"cell-detector-{layout}",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, height, width])],
        [helper.make_tensor_value_info("output", TensorProto.FLOAT, shape)],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model


# (output channels, stride) of a convolution stack sized like a small YOLO backbone (YOLOv8n: 8.7 GFLOPs at
# 640 x 640); for benchmarks, so onnxruntime has a real network's arithmetic to do on every image.
BACKBONE = (
    (16, 2),
    (32, 2),
    (32, 1),
    (32, 1),
    (64, 2),
    (64, 1),
    (64, 1),
    (64, 1),
    (128, 2),
    (128, 1),
    (128, 1),
    (256, 2),
    (256, 1),
    (256, 1),
)


def add_backbone(model: onnx.ModelProto, seed: int = 0) -> tuple[onnx.ModelProto, float]:
    """`model` with BACKBONE's random-weight 3x3 convolutions (ReLU) run on its input and added to its
    output times zero: the detections are unchanged, the work is a backbone's. Returns (model, GFLOPs)."""
    rng = np.random.default_rng(seed)
    graph = model.graph
    _, channels, height, width = (d.dim_value for d in graph.input[0].type.tensor_type.shape.dim)
    source, flops = graph.input[0].name, 0.0
    nodes: list[onnx.NodeProto] = []
    for index, (out_channels, stride) in enumerate(BACKBONE):
        weight = (rng.standard_normal((out_channels, channels, 3, 3)) * (2.0 / (9 * channels)) ** 0.5).astype(
            np.float32
        )
        height, width = (height + stride - 1) // stride, (width + stride - 1) // stride
        flops += 2.0 * out_channels * channels * 9 * height * width
        nodes += [
            _const(f"bb_w{index}", weight),
            helper.make_node(
                "Conv",
                [source, f"bb_w{index}"],
                [f"bb_c{index}"],
                kernel_shape=[3, 3],
                pads=[1, 1, 1, 1],
                strides=[stride, stride],
            ),
            helper.make_node("Relu", [f"bb_c{index}"], [f"bb_r{index}"]),
        ]
        source, channels = f"bb_r{index}", out_channels
    output = graph.output[0].name
    for node in graph.node:  # the old output becomes an intermediate
        node.output[:] = [f"{name}_cells" if name == output else name for name in node.output]
    nodes += [
        helper.make_node("ReduceMean", [source], ["bb_mean"], keepdims=0),
        _const("bb_zero", np.array(0.0, dtype=np.float32)),
        helper.make_node("Mul", ["bb_mean", "bb_zero"], ["bb_nothing"]),
        helper.make_node("Add", [f"{output}_cells", "bb_nothing"], [output]),
    ]
    graph.node.extend(nodes)
    onnx.checker.check_model(model)
    return model, flops / 1e9


def write_model(path: Path, layout: str, width: int = 320, height: int = 256, backbone: bool = False) -> Path:
    model = build_model(layout, width, height)
    if backbone:
        model, _ = add_backbone(model)
    onnx.save(model, str(path))
    return path
