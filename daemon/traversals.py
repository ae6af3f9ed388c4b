"""Traversal counting per camera: calibration-vehicle positions -> visits of the camera's coverage -> jobs.

Input: every calibration-vehicle V2X position (absolute UTM east/north, producer `stamp_ns`, our
`received_ns`) through `TraversalTracker.observe`, plus `tick(now_ns)` about once a second. Output: events
("entered", "left", "discarded") and, from `due(now_ns)`, the `JobWindow` a calibration job should read.
Pure logic: no threads, clocks, bus or files; one tracker per camera, owned by the ingest thread.

Visits (per station, on producer stamps): a position inside the coverage starts a visit ("entered"); no
position inside for `exit_grace_s` ends it, whether the vehicle was seen outside or went silent. A visit of
at least `min_dwell_s` (first to last position inside) is a traversal ("left"), a shorter one is
"discarded". tick() ends visits of vehicles silent for `exit_grace_s` on our clock; if that was only a
backlog (the next position of the vehicle is inside and within the grace of its last one, by producer
stamps), the visit is resumed and the event is "entered" again with the visit's original stamp.

Due (coverage known): the station with the most traversals that ended within `max_window_s` (our clock)
has at least `min_traversals` of them, at least one not used by an earlier job, no vehicle is inside and
`quiet_period_s` passed since the last visit ended. The window is all of that station's traversals in
`max_window_s`: until the camera is calibrated, a refused job's drive-pasts count again in the next one.

Re-verification (`new_only`, the daemon's choice once the camera has a current result): only traversals that
ended after the last job's window (`used_until_ns`) count, at least `min_traversals` of them, and the window
starts after the last one used. Drive-pasts judged against the current result are never pooled with those
it was fitted on, nor with those of an earlier re-verification: a camera moved in between is judged on the
drive-pasts after the move (or, moved within a window, on the next window at the latest).

Learning mode (no coverage yet: no polygon/circle configured and no accepted result). Without coverage
nobody can tell a drive-past from a drive elsewhere, so the tracker collects time instead:
  - A station's "data" is the time it was heard, segment by segment (messages at most `exit_grace_s` apart
    form one segment), counting only what arrived within `max_window_s`.
  - Due when a station has at least `learn_window_s` of data (capped at `max_window_s`, else it could never
    be reached), some of it newer than the last job's window, and it has been silent for `quiet_period_s`
    on our clock (drove off, out of radio range or switched off). The window is all of that station's data
    in `max_window_s`; it has no traversals.
  - A vehicle that never goes silent (parked next to the RSU with V2X on, or a backend relaying it from
    anywhere) never makes a learning job due: the operator triggers one (`force_window`).
  - After a refused learning job, the next job needs new data and silence again, like a new traversal.
  - After the first accepted result the daemon calls `set_coverage(coverage_from_result(result))`, which
    forgets all visit state, then replays the window's V2X through observe() to recount. The replayed
    traversals ended before the learning job's window end, so they count as used: the next job waits for
    a new drive-past.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

from pipeline.arrays import BoolArray, FloatArray, check_shape
from pipeline.camera import CameraModel, camera_centre, opencv_dist, project_points_cam, undistort_pixels
from pipeline.errors import InputError
from pipeline.frames import UtmFrame
from schemas.common import CameraIntrinsics
from schemas.config import CameraConfig, TriggerConfig
from schemas.results import CalibrationResult, GroundPlane

NS_PER_S = 1_000_000_000
DEFAULT_MAX_RANGE_M = 250.0
# Job windows reach this far before the first entry and after the last exit: the camera may see the
# vehicle a little outside the coverage, and the pipeline's association needs poses around each frame.
WINDOW_MARGIN_S = 10.0
# Where on the vehicle ViewCoverage projects: this high above the ground under the V2X reference point,
# about the middle of a car's body, the part whose box the detector reports.
VEHICLE_POINT_HEIGHT_M = 0.75
# A ground-plane normal flatter than this is no road: the plane is ignored (level ground at the origin).
MIN_GROUND_NORMAL_Z = 0.5


class Coverage(Protocol):
    """Where the calibration vehicle is in the camera's view (absolute UTM east/north, metres)."""

    def contains(self, xy_utm: FloatArray) -> BoolArray:
        """(N, 2) absolute UTM east/north -> (N,) inside."""
        ...

    def contains_point(self, east: float, north: float) -> bool:
        """One point, without numpy overhead (called for every V2X message)."""
        ...


def _as_points(xy_utm: FloatArray) -> FloatArray:
    points = np.asarray(xy_utm, dtype=np.float64)
    check_shape(points, "N,2", name="xy_utm")
    return points


@dataclass(frozen=True, slots=True)
class CircleCoverage:
    """Within `radius_m` (horizontal) of a point, e.g. the camera's approximate position."""

    centre_east: float
    centre_north: float
    radius_m: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.centre_east) and math.isfinite(self.centre_north)):
            raise InputError(
                "coverage", f"circle centre = ({self.centre_east}, {self.centre_north}) not finite"
            )
        if not (math.isfinite(self.radius_m) and self.radius_m > 0.0):
            raise InputError("coverage", f"coverage_radius_m = {self.radius_m} must be positive and finite")

    def contains(self, xy_utm: FloatArray) -> BoolArray:
        points = _as_points(xy_utm)
        d2 = (points[:, 0] - self.centre_east) ** 2 + (points[:, 1] - self.centre_north) ** 2
        return np.asarray(d2 <= self.radius_m * self.radius_m, dtype=np.bool_)

    def contains_point(self, east: float, north: float) -> bool:
        dx = east - self.centre_east
        dy = north - self.centre_north
        return dx * dx + dy * dy <= self.radius_m * self.radius_m


class PolygonCoverage:
    """Inside a simple polygon (even-odd rule; vertices absolute UTM east/north, either orientation)."""

    __slots__ = ("_east", "_max_east", "_max_north", "_min_east", "_min_north", "_north", "vertices_utm")

    def __init__(self, vertices_utm: FloatArray | Sequence[tuple[float, float]]) -> None:
        vertices = np.asarray(vertices_utm, dtype=np.float64)
        if vertices.ndim != 2 or vertices.shape[1] != 2 or len(vertices) < 3:
            raise InputError("coverage", f"coverage_polygon: need (N >= 3, 2) vertices, got {vertices.shape}")
        if not np.all(np.isfinite(vertices)):
            raise InputError("coverage", "coverage_polygon: vertices must be finite")
        self.vertices_utm: FloatArray = vertices
        # Plain floats: the per-point test is a Python loop, faster than numpy below ~1000 vertices.
        self._east = tuple(float(v) for v in vertices[:, 0])
        self._north = tuple(float(v) for v in vertices[:, 1])
        self._min_east, self._min_north = (float(v) for v in vertices.min(axis=0))
        self._max_east, self._max_north = (float(v) for v in vertices.max(axis=0))

    def contains(self, xy_utm: FloatArray) -> BoolArray:
        points = _as_points(xy_utm)
        x, y = points[:, 0], points[:, 1]
        inside = np.zeros(len(points), dtype=np.bool_)
        xs, ys = self.vertices_utm[:, 0], self.vertices_utm[:, 1]
        for i in range(len(xs)):
            xi, yi, xj, yj = xs[i], ys[i], xs[i - 1], ys[i - 1]
            if yi == yj:
                continue  # a horizontal edge never crosses the horizontal ray
            crosses = (yi > y) != (yj > y)
            inside ^= crosses & (x < (xj - xi) * (y - yi) / (yj - yi) + xi)
        return inside

    def contains_point(self, east: float, north: float) -> bool:
        if not (self._min_east <= east <= self._max_east and self._min_north <= north <= self._max_north):
            return False
        inside = False
        xs, ys = self._east, self._north
        xj, yj = xs[-1], ys[-1]
        for xi, yi in zip(xs, ys, strict=True):
            if (yi > north) != (yj > north) and east < (xj - xi) * (north - yi) / (yj - yi) + xi:
                inside = not inside
            xj, yj = xi, yi
        return inside


class ViewCoverage:
    """Covered where the vehicle would appear in the image of a calibrated camera (paper Sec. III-A model).

    The vehicle point is `point_height_m` above the ground under the V2X position: the result's ground
    plane (local frame) when it has one, else level ground at the frame origin's height (calibrate() puts
    the origin at the median reported position, i.e. on the road to within the antenna height). Covered:
    in front of the camera (depth > 0), within `max_range_m` (3-D) of its centre, and projecting (OpenCV
    distortion) into the image grown by `margin_px` on every side. Points whose undistorted direction lies
    outside the image's field of view are rejected before distorting, so a strong lens model cannot fold
    a far-off direction back into the image.
    """

    __slots__ = (
        "_R",
        "_bounds_xy",
        "_camera",
        "_centre",
        "_dist",
        "_ground",
        "_has_dist",
        "_intr",
        "_max_range2",
        "_origin",
        "_pixel_bounds",
        "_t",
        "max_range_m",
    )

    def __init__(
        self,
        R_cam_from_local: FloatArray,
        t_cam_from_local: FloatArray,
        origin_utm: Sequence[float] | FloatArray,
        intrinsics: CameraIntrinsics,
        ground_plane: GroundPlane | None = None,
        *,
        max_range_m: float = DEFAULT_MAX_RANGE_M,
        margin_px: float = 0.0,
        point_height_m: float = VEHICLE_POINT_HEIGHT_M,
    ) -> None:
        R = np.asarray(R_cam_from_local, dtype=np.float64)
        t = np.asarray(t_cam_from_local, dtype=np.float64)
        origin = np.asarray(origin_utm, dtype=np.float64)
        check_shape(R, "3,3", name="R_cam_from_local")
        check_shape(t, "3", name="t_cam_from_local")
        check_shape(origin, "3", name="origin_utm")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and np.all(np.isfinite(origin))):
            raise InputError("coverage", "R, t and origin must be finite")
        if not (math.isfinite(max_range_m) and max_range_m > 0.0):
            raise InputError("coverage", f"max_range_m = {max_range_m} must be positive")
        if not (math.isfinite(margin_px) and margin_px > -0.5 * min(intrinsics.width, intrinsics.height)):
            raise InputError("coverage", f"margin_px = {margin_px} leaves no image")
        self.max_range_m = float(max_range_m)
        self._max_range2 = self.max_range_m**2
        self._R = tuple(float(v) for v in R.ravel())
        self._t = tuple(float(v) for v in t)
        self._origin = (float(origin[0]), float(origin[1]))
        centre = camera_centre(R, t)
        self._centre = (float(centre[0]), float(centre[1]), float(centre[2]))
        # Local height of the vehicle point as z = a + b x + c y.
        if ground_plane is not None and ground_plane.normal[2] >= MIN_GROUND_NORMAL_Z:
            nx, ny, nz = ground_plane.normal
            self._ground = (ground_plane.offset / nz + point_height_m, -nx / nz, -ny / nz)
        else:
            self._ground = (float(point_height_m), 0.0, 0.0)
        self._intr = (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
        # [k1, k2, p1, p2, k3, k4, k5, k6], the rational terms 0 where the lens has none.
        dist = [float(v) for v in opencv_dist(intrinsics.dist)]
        self._dist = (*dist, *[0.0] * (8 - len(dist)))
        self._has_dist = any(v != 0.0 for v in self._dist)
        u_lo, v_lo = -margin_px, -margin_px
        u_hi, v_hi = intrinsics.width + margin_px, intrinsics.height + margin_px
        self._pixel_bounds = (u_lo, u_hi, v_lo, v_hi)
        self._camera = CameraModel.from_intrinsics(intrinsics)
        # Field of view as undistorted normalised coordinates: the bounding box of the image border.
        steps = np.linspace(0.0, 1.0, 33)
        border = np.concatenate(
            [
                np.column_stack([u_lo + steps * (u_hi - u_lo), np.full(33, v_lo)]),
                np.column_stack([u_lo + steps * (u_hi - u_lo), np.full(33, v_hi)]),
                np.column_stack([np.full(33, u_lo), v_lo + steps * (v_hi - v_lo)]),
                np.column_stack([np.full(33, u_hi), v_lo + steps * (v_hi - v_lo)]),
            ]
        )
        xy = undistort_pixels(border, self._camera)
        self._bounds_xy = (
            float(xy[:, 0].min()),
            float(xy[:, 0].max()),
            float(xy[:, 1].min()),
            float(xy[:, 1].max()),
        )

    def _local(self, east: FloatArray, north: FloatArray) -> FloatArray:
        x = east - self._origin[0]
        y = north - self._origin[1]
        a, b, c = self._ground
        return np.column_stack([x, y, a + b * x + c * y])

    def contains(self, xy_utm: FloatArray) -> BoolArray:
        points = _as_points(xy_utm)
        local = self._local(points[:, 0], points[:, 1])
        R = np.array(self._R).reshape(3, 3)
        points_cam = local @ R.T + np.array(self._t)
        depth = points_cam[:, 2]
        in_front = depth > 0.0
        near = np.sum((local - np.array(self._centre)) ** 2, axis=1) <= self._max_range2
        safe = points_cam.copy()
        safe[~in_front, 2] = 1.0
        x_n, y_n = safe[:, 0] / safe[:, 2], safe[:, 1] / safe[:, 2]
        x_lo, x_hi, y_lo, y_hi = self._bounds_xy
        in_fov = (x_n >= x_lo) & (x_n <= x_hi) & (y_n >= y_lo) & (y_n <= y_hi)
        pixels = project_points_cam(safe, self._camera)
        u_lo, u_hi, v_lo, v_hi = self._pixel_bounds
        in_image = (
            (pixels[:, 0] >= u_lo) & (pixels[:, 0] <= u_hi) & (pixels[:, 1] >= v_lo) & (pixels[:, 1] <= v_hi)
        )
        return np.asarray(in_front & near & in_fov & in_image, dtype=np.bool_)

    def contains_point(self, east: float, north: float) -> bool:
        # The same test as contains(), unrolled for one point: ~20x faster than numpy on a single row.
        x = east - self._origin[0]
        y = north - self._origin[1]
        a, b, c = self._ground
        z = a + b * x + c * y
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = self._R
        t0, t1, t2 = self._t
        depth = r20 * x + r21 * y + r22 * z + t2
        if not depth > 0.0:
            return False
        cx_, cy_, cz_ = self._centre
        dx, dy, dz = x - cx_, y - cy_, z - cz_
        if dx * dx + dy * dy + dz * dz > self._max_range2:
            return False
        xn = (r00 * x + r01 * y + r02 * z + t0) / depth
        yn = (r10 * x + r11 * y + r12 * z + t1) / depth
        x_lo, x_hi, y_lo, y_hi = self._bounds_xy
        if not (x_lo <= xn <= x_hi and y_lo <= yn <= y_hi):
            return False
        if self._has_dist:
            k1, k2, p1, p2, k3, k4, k5, k6 = self._dist
            r2 = xn * xn + yn * yn
            radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
            xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
            yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
        else:
            xd, yd = xn, yn
        fx, fy, cx, cy = self._intr
        u = fx * xd + cx
        v = fy * yd + cy
        u_lo, u_hi, v_lo, v_hi = self._pixel_bounds
        return u_lo <= u <= u_hi and v_lo <= v <= v_hi


def coverage_from_config(camera: CameraConfig, frame: UtmFrame) -> Coverage | None:
    """The configured coverage in `frame`: the polygon if given (it is the more precise of the two), else
    the circle around `position`, else None (learning mode)."""
    if camera.coverage_polygon is not None:
        lat = np.array([p.lat for p in camera.coverage_polygon])
        lon = np.array([p.lon for p in camera.coverage_polygon])
        east, north = frame.to_utm(lat, lon)
        if not (np.all(np.isfinite(east)) and np.all(np.isfinite(north))):
            raise InputError(camera.camera_id, f"coverage_polygon is not representable in {frame.crs}")
        return PolygonCoverage(np.column_stack([east, north]))
    if camera.position is not None and camera.coverage_radius_m is not None:
        east, north = frame.to_utm(np.array([camera.position.lat]), np.array([camera.position.lon]))
        if not (math.isfinite(east[0]) and math.isfinite(north[0])):
            raise InputError(camera.camera_id, f"position is not representable in {frame.crs}")
        return CircleCoverage(float(east[0]), float(north[0]), camera.coverage_radius_m)
    return None


def coverage_from_result(
    result: CalibrationResult,
    *,
    max_range_m: float = DEFAULT_MAX_RANGE_M,
    margin_px: float = 0.0,
    point_height_m: float = VEHICLE_POINT_HEIGHT_M,
) -> ViewCoverage:
    """The coverage a calibration implies: where the vehicle projects into the image (see ViewCoverage).
    Raises InputError for a result without a pose (a refused one)."""
    if result.R is None or result.t is None:
        raise InputError(f"result {result.result_id}", "has no R, t (refused): no coverage can be learned")
    return ViewCoverage(
        np.array(result.R, dtype=np.float64),
        np.array(result.t, dtype=np.float64),
        result.frame.origin,
        result.intrinsics,
        result.ground_plane,
        max_range_m=max_range_m,
        margin_px=margin_px,
        point_height_m=point_height_m,
    )


@dataclass(frozen=True, slots=True)
class Traversal:
    """One drive-past: first and last position inside the coverage (producer stamps, ns), and when we
    decided it had left (our clock, ns)."""

    station_id: int
    enter_ns: int
    leave_ns: int
    left_received_ns: int


@dataclass(frozen=True, slots=True)
class TraversalEvent:
    """A change of a camera's visit state; `traversals` is the count (see TrackerSnapshot) after it."""

    camera_id: str
    kind: Literal["entered", "left", "discarded"]
    station_id: int
    stamp_ns: int  # entered: first position inside; left/discarded: last position inside
    traversals: int


@dataclass(frozen=True, slots=True)
class JobWindow:
    """What a job reads: producer stamps [start_ns, end_ns] of one station's V2X and the camera's frames.
    With coverage: the traversals used, start/end `WINDOW_MARGIN_S` around them. Learning: no traversals,
    the station's data in max_window_s."""

    start_ns: int
    end_ns: int
    station_id: int
    traversals: tuple[Traversal, ...]


@dataclass(frozen=True, slots=True)
class TrackerSnapshot:
    """A tracker's state for status and health (safe to read from any thread: immutable, swapped whole).

    `traversals` is the count of the station with the most traversals in max_window_s (one station is one
    job's data; with one calibration vehicle simply the count). As of the last event, tick() or call that
    changed state.
    """

    camera_id: str
    learning: bool
    inside: bool  # some calibration vehicle is in the coverage now
    traversals: int
    traversals_total: int  # all stations
    new_traversals: int  # all stations, not yet used by a job
    needed: int  # trigger.min_traversals
    last_leave_ns: int | None  # producer stamp of the last visit's end (traversal or discarded)
    last_left_received_ns: int | None  # our clock: when that end was decided
    used_until_ns: int | None  # traversals ending up to this stamp were used by a job
    window_start_ns: int | None  # oldest producer stamp a job may still read (keep recordings after it)
    learn_data_s: float  # learning: seconds of data of the best station in max_window_s
    stations: int  # calibration stations heard since the last set_coverage
    stale: int  # messages ignored: stamp not after the station's last, or position not finite


class _Segment:
    """A stretch of one station's messages with gaps <= exit_grace_s (learning mode's 'data')."""

    __slots__ = ("end_ns", "end_received_ns", "start_ns")

    def __init__(self, stamp_ns: int, received_ns: int) -> None:
        self.start_ns = stamp_ns
        self.end_ns = stamp_ns
        self.end_received_ns = received_ns


class _Station:
    """One calibration vehicle's visit state for one camera."""

    __slots__ = (
        "enter_ns",
        "in_visit",
        "last_inside_ns",
        "last_inside_received_ns",
        "last_received_ns",
        "last_stamp_ns",
        "resumable",
        "resumable_traversal",
        "segments",
    )

    def __init__(self) -> None:
        self.last_stamp_ns = -1
        self.last_received_ns = 0
        self.in_visit = False
        self.enter_ns = 0
        self.last_inside_ns = 0
        self.last_inside_received_ns = 0
        # tick() ended the visit on silence and it may still be resumed; the traversal it recorded (None
        # when the visit was discarded as too short).
        self.resumable = False
        self.resumable_traversal: Traversal | None = None
        self.segments: deque[_Segment] = deque()


class TraversalTracker:
    """Counts one camera's traversals and says when a calibration job is due (see the module docstring).

    Call observe() for every calibration-vehicle position in stamp order per station (older or equal
    stamps are ignored), tick(now) about once a second before due(now). due() has no side effects: call
    mark_used(window) when the job starts. After a restart replay V2X through observe(), then
    restore_used_until(the persisted used_until_ns) and tick(now).
    """

    def __init__(
        self,
        camera_id: str,
        coverage: Coverage | None,
        trigger: TriggerConfig,
        *,
        window_margin_s: float = WINDOW_MARGIN_S,
    ) -> None:
        self.camera_id = camera_id
        self.trigger = trigger
        self._coverage = coverage
        self._grace_ns = round(trigger.exit_grace_s * NS_PER_S)
        self._dwell_ns = round(trigger.min_dwell_s * NS_PER_S)
        self._quiet_ns = round(trigger.quiet_period_s * NS_PER_S)
        self._max_window_ns = round(trigger.max_window_s * NS_PER_S)
        self._learn_ns = round(min(trigger.learn_window_s, trigger.max_window_s) * NS_PER_S)
        self._margin_ns = round(window_margin_s * NS_PER_S)
        self._used_until_ns: int | None = None
        self._not_before_ns: int | None = None  # set_not_before
        self._tick_ns: int | None = None  # now_ns of the last tick()
        self._stale = 0
        self._reset()

    def _reset(self) -> None:
        self._stations: dict[int, _Station] = {}
        self._traversals: list[Traversal] = []  # in the order they ended
        self._per_station: Counter[int] = Counter()
        self._inside = 0  # stations in a visit
        self._last_leave_ns: int | None = None
        self._last_left_received_ns: int | None = None
        self._learn_data_ns = 0
        self._snapshot = self._make_snapshot()

    # ------------------------------------------------------------------------------------------ input

    def observe(
        self, station_id: int, stamp_ns: int, east: float, north: float, received_ns: int
    ) -> list[TraversalEvent]:
        """One calibration-vehicle position (absolute UTM, m) -> the events it causes (usually none)."""
        station = self._stations.get(station_id)
        if station is None:
            station = self._stations[station_id] = _Station()
        elif stamp_ns <= station.last_stamp_ns:
            self._stale += 1
            return []
        if not (math.isfinite(east) and math.isfinite(north)):
            self._stale += 1
            return []
        station.last_stamp_ns = stamp_ns
        station.last_received_ns = received_ns
        segments = station.segments
        if segments and stamp_ns - segments[-1].end_ns <= self._grace_ns:
            segment = segments[-1]
            segment.end_ns = stamp_ns
            segment.end_received_ns = received_ns
        else:
            segments.append(_Segment(stamp_ns, received_ns))
        if self._coverage is None:
            return []

        events: list[TraversalEvent] = []
        away_long_enough = stamp_ns - station.last_inside_ns >= self._grace_ns
        if station.in_visit and away_long_enough:
            events.append(self._close(station_id, station, received_ns))
        if away_long_enough:
            station.resumable = False
            station.resumable_traversal = None
        if self._coverage.contains_point(east, north):
            if not station.in_visit:
                events.append(self._enter(station_id, station, stamp_ns))
            station.last_inside_ns = stamp_ns
            station.last_inside_received_ns = received_ns
        if events:
            self._snapshot = self._make_snapshot()
        return events

    def tick(self, now_ns: int) -> list[TraversalEvent]:
        """End visits of vehicles silent for exit_grace_s (our clock); forget traversals and learning data
        older than max_window_s; refresh the snapshot."""
        self._tick_ns = now_ns
        events = []
        for station_id, station in self._stations.items():
            if station.in_visit and now_ns - station.last_inside_received_ns >= self._grace_ns:
                events.append(self._close(station_id, station, now_ns))
                station.resumable = True
                station.resumable_traversal = self._traversals[-1] if events[-1].kind == "left" else None
        cutoff_ns = now_ns - self._max_window_ns
        expired = [t for t in self._traversals if t.left_received_ns < cutoff_ns]
        if expired:
            self._traversals = [t for t in self._traversals if t.left_received_ns >= cutoff_ns]
            self._per_station.subtract(t.station_id for t in expired)
            self._per_station = +self._per_station  # drop zero counts
        for station in self._stations.values():
            segments = station.segments
            while segments and segments[0].end_received_ns < cutoff_ns:
                segments.popleft()
        self._learn_data_ns = max((self._data_ns(s, now_ns) for s in self._stations.values()), default=0)
        self._snapshot = self._make_snapshot()
        return events

    def _enter(self, station_id: int, station: _Station, stamp_ns: int) -> TraversalEvent:
        station.in_visit = True
        self._inside += 1
        if station.resumable:
            # tick() ended this visit on our clock, but by the vehicle's stamps it never left: resume it.
            resumed = station.resumable_traversal
            station.resumable = False
            station.resumable_traversal = None
            if resumed is not None and resumed in self._traversals:
                self._traversals.remove(resumed)
                self._per_station.subtract([station_id])
                self._per_station = +self._per_station
            return TraversalEvent(self.camera_id, "entered", station_id, station.enter_ns, self._count())
        station.enter_ns = stamp_ns
        return TraversalEvent(self.camera_id, "entered", station_id, stamp_ns, self._count())

    def _close(self, station_id: int, station: _Station, decided_ns: int) -> TraversalEvent:
        station.in_visit = False
        self._inside -= 1
        self._last_leave_ns = station.last_inside_ns
        self._last_left_received_ns = decided_ns
        if station.last_inside_ns - station.enter_ns < self._dwell_ns:
            return TraversalEvent(
                self.camera_id, "discarded", station_id, station.last_inside_ns, self._count()
            )
        self._traversals.append(Traversal(station_id, station.enter_ns, station.last_inside_ns, decided_ns))
        self._per_station[station_id] += 1
        return TraversalEvent(self.camera_id, "left", station_id, station.last_inside_ns, self._count())

    # ------------------------------------------------------------------------------------------ jobs

    def due(self, now_ns: int, *, new_only: bool = False) -> JobWindow | None:
        """The window of the job that should start now, or None (see the module docstring); `new_only`: a
        re-verification, on traversals newer than the last job's window only."""
        if self._coverage is None:
            return self._learning_window(now_ns, require_due=True)
        if self._inside or self._last_left_received_ns is None:
            return None
        if now_ns - self._last_left_received_ns < self._quiet_ns:
            return None
        by_station = self._live_by_station(now_ns, new_only=new_only)
        used = self._used_until_ns
        eligible = [
            group
            for group in by_station.values()
            if len(group) >= self.trigger.min_traversals
            and (used is None or any(t.leave_ns > used for t in group))
        ]
        if not eligible:
            return None
        return self._traversal_window(max(eligible, key=lambda g: (len(g), g[-1].leave_ns)), new_only)

    def force_window(self, now_ns: int, *, new_only: bool = False) -> JobWindow | None:
        """The window of a job started by hand now: all traversals of the station with the most in
        max_window_s (however few); with `new_only` those newer than the last job's window when there are
        any (else the others: such a fit re-verifies nothing, see daemon.publication); without coverage or
        traversals all data of the station heard longest (as in learning mode); None without any
        calibration-vehicle data."""
        if self._coverage is not None:
            by_station = self._live_by_station(now_ns, new_only=new_only) if new_only else {}
            if not by_station:
                by_station, new_only = self._live_by_station(now_ns), False
            if by_station:
                return self._traversal_window(
                    max(by_station.values(), key=lambda g: (len(g), g[-1].leave_ns)), new_only
                )
        return self._learning_window(now_ns, require_due=False)

    def mark_used(self, window: JobWindow) -> None:
        """A job was started on `window`: traversals (and learning data) up to window.end_ns are used.
        Persist `used_until_ns` (= the largest window.end_ns) for restore_used_until() after a restart.
        window.end_ns includes the margin: with quiet_period_s below it, a visit begun and ended within the
        margin after due() would count as used; the defaults (60 s vs 10 s) leave no such gap."""
        self.restore_used_until(window.end_ns)

    def restore_used_until(self, stamp_ns: int) -> None:
        """Traversals ending at or before `stamp_ns` count as used (never moves back: restart recovery)."""
        if self._used_until_ns is None or stamp_ns > self._used_until_ns:
            self._used_until_ns = stamp_ns
        self._snapshot = self._make_snapshot()

    def set_not_before(self, stamp_ns: int) -> None:
        """Traversals that began before `stamp_ns` are never used again (the camera moved after them: a
        withdrawn result); like used_until it never moves back."""
        if self._not_before_ns is None or stamp_ns > self._not_before_ns:
            self._not_before_ns = stamp_ns
        self._snapshot = self._make_snapshot()

    def set_coverage(self, coverage: Coverage) -> None:
        """Switch to a (learned or changed) coverage. Forgets visits, traversals and learning data (they
        belong to the old coverage) but not used_until; replay the window's V2X through observe() next."""
        self._coverage = coverage
        self._reset()

    @property
    def used_until_ns(self) -> int | None:
        return self._used_until_ns

    @property
    def not_before_ns(self) -> int | None:
        return self._not_before_ns

    @property
    def coverage(self) -> Coverage | None:
        return self._coverage

    def snapshot(self) -> TrackerSnapshot:
        """The state as of the last event, tick() or state-changing call (an immutable object)."""
        return self._snapshot

    # ------------------------------------------------------------------------------------------ helpers

    def _count(self) -> int:
        if self._not_before_ns is None:
            return max(self._per_station.values(), default=0)
        first = self._not_before_ns
        counts = Counter(t.station_id for t in self._traversals if t.enter_ns >= first)
        return max(counts.values(), default=0)

    def _live_by_station(self, now_ns: int, *, new_only: bool = False) -> dict[int, list[Traversal]]:
        """Traversals within max_window_s by station; with `new_only` those ending after used_until_ns."""
        cutoff_ns = now_ns - self._max_window_ns
        used = self._used_until_ns if new_only else None
        first = self._not_before_ns
        groups: dict[int, list[Traversal]] = {}
        for traversal in self._traversals:
            if (
                traversal.left_received_ns >= cutoff_ns
                and (used is None or traversal.leave_ns > used)
                and (first is None or traversal.enter_ns >= first)
            ):
                groups.setdefault(traversal.station_id, []).append(traversal)
        return groups

    def _traversal_window(self, group: Sequence[Traversal], new_only: bool = False) -> JobWindow:
        """The traversals with WINDOW_MARGIN_S around them; with `new_only` starting after used_until_ns, so
        the margin never reaches back into the last job's window."""
        start_ns = min(t.enter_ns for t in group) - self._margin_ns
        if new_only and self._used_until_ns is not None:
            start_ns = max(start_ns, self._used_until_ns + 1)
        if self._not_before_ns is not None:
            start_ns = max(start_ns, self._not_before_ns)
        return JobWindow(
            start_ns=start_ns,
            end_ns=max(t.leave_ns for t in group) + self._margin_ns,
            station_id=group[0].station_id,
            traversals=tuple(group),
        )

    def _data_ns(self, station: _Station, now_ns: int) -> int:
        """Time the station was heard within max_window_s (producer time, cut at the window on our clock)."""
        cutoff_ns = now_ns - self._max_window_ns
        total = 0
        for segment in station.segments:
            if segment.end_received_ns >= cutoff_ns:
                total += min(segment.end_ns - segment.start_ns, segment.end_received_ns - cutoff_ns)
        return total

    def _data_start_ns(self, station: _Station, now_ns: int) -> int | None:
        cutoff_ns = now_ns - self._max_window_ns
        for segment in station.segments:
            if segment.end_received_ns >= cutoff_ns:
                in_window_ns = segment.end_received_ns - cutoff_ns
                return max(segment.start_ns, segment.end_ns - in_window_ns)
        return None

    def _learning_window(self, now_ns: int, *, require_due: bool) -> JobWindow | None:
        best: tuple[int, int, int] | None = None  # (data_ns, last stamp, station_id)
        for station_id, station in self._stations.items():
            data_ns = self._data_ns(station, now_ns)
            if not station.segments or station.segments[-1].end_received_ns < now_ns - self._max_window_ns:
                continue
            if require_due and not (
                data_ns >= self._learn_ns
                and now_ns - station.last_received_ns >= self._quiet_ns
                and (self._used_until_ns is None or station.segments[-1].end_ns > self._used_until_ns)
            ):
                continue
            candidate = (data_ns, station.segments[-1].end_ns, station_id)
            if best is None or candidate > best:
                best = candidate
        if best is None:
            return None
        station = self._stations[best[2]]
        start_ns = self._data_start_ns(station, now_ns)
        assert start_ns is not None  # the station has a segment in the window
        if self._not_before_ns is not None:  # never data from before a move (set_not_before)
            if best[1] <= self._not_before_ns:
                return None
            start_ns = max(start_ns, self._not_before_ns)
        return JobWindow(start_ns=start_ns, end_ns=best[1], station_id=best[2], traversals=())

    def _window_start_ns(self) -> int | None:
        starts = [t.enter_ns for t in self._traversals]
        starts += [s.enter_ns for s in self._stations.values() if s.in_visit]
        if self._coverage is None:
            # Learning: the oldest data still in max_window_s as of the last tick().
            for station in self._stations.values():
                if not station.segments:
                    continue
                if self._tick_ns is None:
                    starts.append(station.segments[0].start_ns)
                elif (start_ns := self._data_start_ns(station, self._tick_ns)) is not None:
                    starts.append(start_ns)
            return min(starts, default=None)
        return min(starts) - self._margin_ns if starts else None

    def _make_snapshot(self) -> TrackerSnapshot:
        used = self._used_until_ns
        return TrackerSnapshot(
            camera_id=self.camera_id,
            learning=self._coverage is None,
            inside=self._inside > 0,
            traversals=self._count(),
            traversals_total=len(self._traversals),
            new_traversals=sum(1 for t in self._traversals if used is None or t.leave_ns > used),
            needed=self.trigger.min_traversals,
            last_leave_ns=self._last_leave_ns,
            last_left_received_ns=self._last_left_received_ns,
            used_until_ns=used,
            window_start_ns=self._window_start_ns(),
            learn_data_s=self._learn_data_ns / NS_PER_S,
            stations=len(self._stations),
            stale=self._stale,
        )
