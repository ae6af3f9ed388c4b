"""Columnar forms of the pipeline's bulk inputs: a pose stream and a camera's detections as arrays.

A 15-minute toolbox recording holds ~45,000 poses and ~9,000 frames of ~30,000 boxes; a validated pydantic
object per pose and per box cost ~0.45 s to build and as much again to read back into the arrays the
stages work on. The toolbox loaders (pipeline.loaders) validate the columns at once and return these
tables instead. Each is a Sequence of the schema objects (VehiclePose, DetectionFrame), built on demand
and validated exactly as the loaders built them before, for any reader that wants objects; association,
tracking and the result read the columns directly (`poses_to_array`, `frames_from_detections`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, TypeVar, overload

from pipeline.arrays import Boxes, FloatArray, IntArray, PoseArray, Stamps
from schemas.messages import DetectionFrame, VehiclePose

_Row = TypeVar("_Row")


class _Table(Sequence[_Row]):
    """A Sequence of schema objects over columns whose first is `stamps`: rows built on demand by `_row`
    (index already in range, non-negative), slices as lists."""

    __slots__ = ("stamps",)

    def __init__(self, stamps: Stamps) -> None:
        self.stamps = stamps

    def __len__(self) -> int:
        return len(self.stamps)

    @overload
    def __getitem__(self, index: int) -> _Row: ...

    @overload
    def __getitem__(self, index: slice) -> list[_Row]: ...

    def __getitem__(self, index: int | slice) -> _Row | list[_Row]:
        if isinstance(index, slice):
            return [self._row(i) for i in range(*index.indices(len(self)))]
        if not -len(self) <= index < len(self):
            raise IndexError(f"row {index} of {len(self)}")
        return self._row(index % len(self))

    def _row(self, index: int) -> _Row:
        raise NotImplementedError


class PoseTable(_Table[VehiclePose]):
    """Vehicle poses sorted by stamp: stamps (N,) int64 ns, values (N, 6) x, y, z (m, absolute UTM or the
    file's frame), yaw, pitch, roll (rad); every row already valid as a VehiclePose."""

    __slots__ = ("values",)

    def __init__(self, stamps: Stamps, values: PoseArray) -> None:
        super().__init__(stamps)
        self.values = values

    def _row(self, index: int) -> VehiclePose:
        x, y, z, yaw, pitch, roll = self.values[index].tolist()
        return VehiclePose(stamp_ns=int(self.stamps[index]), x=x, y=y, z=z, yaw=yaw, pitch=pitch, roll=roll)

    def moved(self, east_m: float, north_m: float) -> PoseTable:
        """The same poses with `east_m` added to x and `north_m` to y (a local frame placed in UTM)."""
        values = self.values.copy()
        values[:, 0] += east_m
        values[:, 1] += north_m
        return PoseTable(self.stamps, values)


class DetectionTable(_Table[DetectionFrame]):
    """One camera's frames sorted by stamp: stamps (F,) int64 ns, starts (F + 1,) int64 (frame i's boxes are
    rows starts[i]:starts[i + 1]), boxes (B, 4) px x1, y1, x2, y2, classes (B,) int64 class ids (score 1.0);
    every frame already valid as a DetectionFrame."""

    __slots__ = ("boxes", "camera_id", "classes", "starts")

    def __init__(self, camera_id: str, stamps: Stamps, starts: IntArray, boxes: Boxes, classes: IntArray):
        super().__init__(stamps)
        self.camera_id = camera_id
        self.starts = starts
        self.boxes = boxes
        self.classes = classes

    def _row(self, index: int) -> DetectionFrame:
        lo, hi = self.starts[index], self.starts[index + 1]
        rows: list[list[float]] = self.boxes[lo:hi].tolist()
        classes: list[int] = self.classes[lo:hi].tolist()
        boxes: list[dict[str, Any]] = [
            {"x1": x1, "y1": y1, "x2": x2, "y2": y2, "cls": cls}
            for (x1, y1, x2, y2), cls in zip(rows, classes, strict=True)
        ]
        return DetectionFrame.model_validate(
            {"camera_id": self.camera_id, "stamp_ns": int(self.stamps[index]), "boxes": boxes}, strict=True
        )

    def frame_boxes(self, index: int) -> tuple[FloatArray, IntArray]:
        """Frame `index`'s boxes (n, 4) and class ids (n,), as new arrays."""
        lo, hi = self.starts[index], self.starts[index + 1]
        return self.boxes[lo:hi].copy(), self.classes[lo:hi].copy()
