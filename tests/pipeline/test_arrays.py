"""check_shape / as_float_array: the one place array shapes are checked, with messages naming the argument."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.arrays import as_float_array, check_shape
from pipeline.errors import RsucalError, ShapeError


@pytest.mark.parametrize(
    ("array", "spec", "name", "message"),
    [
        (np.zeros((7, 5)), "N,4", "boxes", "boxes: expected (N, 4), got (7, 5)"),
        (np.zeros((7,)), "N,4", "boxes", "boxes: expected (N, 4), got (7,)"),
        (np.zeros((3, 4)), "N", "stamps", "stamps: expected (N,), got (3, 4)"),
        (np.zeros((3, 2)), "3,3", "R", "R: expected (3, 3), got (3, 2)"),
        (np.zeros((2, 3, 3)), "N,4,3", "corners", "corners: expected (N, 4, 3), got (2, 3, 3)"),
        (np.zeros(()), "N", "stamps", "stamps: expected (N,), got ()"),
    ],
)
def test_wrong_shape_message_names_argument_expected_and_actual(
    array: np.ndarray, spec: str, name: str, message: str
) -> None:
    with pytest.raises(ShapeError) as info:
        check_shape(array, spec, name=name)
    assert str(info.value) == message


@pytest.mark.parametrize(
    ("shape", "spec"), [((0, 4), "N,4"), ((7, 4), "N,4"), ((3, 3), "3,3"), ((5,), "N"), ((2, 4, 3), "N,4,3")]
)
def test_matching_shapes_pass(shape: tuple[int, ...], spec: str) -> None:
    check_shape(np.zeros(shape), spec, name="x")


def test_non_arrays_are_refused_with_their_type() -> None:
    with pytest.raises(ShapeError, match=r"boxes: expected a numpy array \(N,4\), got list"):
        check_shape([[1.0, 2.0, 3.0, 4.0]], "N,4", name="boxes")


def test_shape_error_is_an_rsucal_error_and_a_value_error() -> None:
    assert issubclass(ShapeError, RsucalError) and issubclass(ShapeError, ValueError)


def test_as_float_array_converts_and_checks() -> None:
    array = as_float_array([[1, 2, 3]], "N,3", name="points")
    assert array.dtype == np.float64 and array.shape == (1, 3)
    with pytest.raises(ShapeError, match="points: contains NaN or inf"):
        as_float_array([[1.0, np.nan, 3.0]], "N,3", name="points")
    with pytest.raises(ShapeError, match="points: contains NaN or inf"):
        as_float_array([[1.0, np.inf, 3.0]], "N,3", name="points")
    with pytest.raises(ShapeError, match=r"points: expected \(N, 3\), got \(1, 2\)"):
        as_float_array([[1.0, 2.0]], "N,3", name="points")
