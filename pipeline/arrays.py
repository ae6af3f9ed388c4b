"""Array shape aliases and `check_shape`: the ONE place the pipeline's array shapes are defined (STYLE 3).

| alias     | shape, dtype        | meaning                                                         |
| Points3   | (N, 3) float64      | metres, local frame (UTM minus LocalOrigin) unless named _cam   |
| Pixels    | (N, 2) float64      | u right, v down                                                 |
| Boxes     | (N, 4) float64      | x1, y1, x2, y2 with x1 < x2, y1 < y2                            |
| Stamps    | (N,) int64          | ns since the Unix epoch                                         |
| Mask      | (N,) bool           | row selector                                                    |
| Rotation  | (3, 3) float64      | det +1                                                          |
| Vec3      | (3,) float64        | metres                                                          |
| Corners   | (N, 4, 3) float64   | footprint: rear-right, front-right, front-left, rear-left       |
| PoseArray | (N, 6) float64      | x, y, z, yaw, pitch, roll of the vehicle reference point        |
"""

from __future__ import annotations

import functools
from typing import Any, TypeAlias

import numpy as np
import numpy.typing as npt

from pipeline.errors import ShapeError

FloatArray: TypeAlias = npt.NDArray[np.float64]
IntArray: TypeAlias = npt.NDArray[np.int64]
BoolArray: TypeAlias = npt.NDArray[np.bool_]

Points3: TypeAlias = FloatArray
Pixels: TypeAlias = FloatArray
Boxes: TypeAlias = FloatArray
Stamps: TypeAlias = IntArray
Mask: TypeAlias = BoolArray
Rotation: TypeAlias = FloatArray
Vec3: TypeAlias = FloatArray
Corners: TypeAlias = FloatArray
PoseArray: TypeAlias = FloatArray


def check_shape(array: Any, spec: str, name: str) -> None:
    """Raise ShapeError unless `array` is an ndarray matching `spec`, e.g. "N,4", "3,3", "N", "N,4,3".

    Letters match any size; digits must match exactly.
    """
    if not isinstance(array, np.ndarray):
        raise ShapeError(f"{name}: expected a numpy array ({spec}), got {type(array).__name__}")
    dims, sizes = _parsed(spec)
    if array.ndim != len(sizes) or any(
        size is not None and size != n for size, n in zip(sizes, array.shape, strict=True)
    ):
        expected = "(" + ", ".join(dims) + (",)" if len(dims) == 1 else ")")
        raise ShapeError(f"{name}: expected {expected}, got {tuple(array.shape)}")


@functools.cache
def _parsed(spec: str) -> tuple[tuple[str, ...], tuple[int | None, ...]]:
    """`check_shape`'s spec as its dimensions and one size per dimension, None for a letter (parsed once per
    spec: the check runs in the solvers' inner loops)."""
    dims = tuple(d.strip() for d in spec.split(",")) if spec else ()
    return dims, tuple(int(d) if d.isdigit() else None for d in dims)


def as_float_array(values: Any, spec: str, name: str) -> FloatArray:
    """Convert to float64 and check the shape and finiteness in one go."""
    array = np.asarray(values, dtype=np.float64)
    check_shape(array, spec, name)
    if not np.all(np.isfinite(array)):
        raise ShapeError(f"{name}: contains NaN or inf")
    return array
