"""daemon.traversals: coverages, visits (dwell, grace, silence), counts against the simulator's truth,
when a job is due (quiet period, re-trigger, pruning, restart) and learning mode."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import pytest

from daemon.traversals import (
    WINDOW_MARGIN_S,
    CircleCoverage,
    Coverage,
    JobWindow,
    PolygonCoverage,
    Traversal,
    TraversalEvent,
    TraversalTracker,
    ViewCoverage,
    coverage_from_config,
    coverage_from_result,
)
from pipeline.camera import (
    CameraModel,
    camera_centre,
    camera_rotation_from_view,
    distort_normalized,
    project_points,
)
from pipeline.errors import InputError
from pipeline.frames import UtmFrame, poses_from_v2x
from schemas.common import CameraIntrinsics
from schemas.config import CameraConfig, GeoPoint, TriggerConfig
from schemas.results import CalibrationResult, GroundPlane, ReferenceFrame, Verdict
from sim.simulate import SimulatedCamera, SimulationResult, simulate

S = 1_000_000_000
T0 = 1_700_000_000_000_000_000
LATENCY_NS = 40_000_000  # V2X transport delay: received_ns = stamp_ns + this
MARGIN_NS = round(WINDOW_MARGIN_S * S)
STATION = 7
# A synthetic site: a circle of 50 m around (E0, N0); a straight pass from 100 m before to 100 m after
# its centre at 10 m/s is inside for 10 s.
E0, N0 = 500_000.0, 5_400_000.0
INTRINSICS = CameraIntrinsics(width=1920, height=1080, fx=1000.0, fy=1000.0, cx=960.0, cy=540.0)

Sample = tuple[int, float, float]  # stamp_ns, east, north


@dataclass(frozen=True)
class Scene:
    sim: SimulationResult
    samples: list[Sample]  # the calibration vehicle's V2X converted to UTM, as the daemon does

    @property
    def origin(self) -> np.ndarray:
        return np.array([self.sim.origin.x, self.sim.origin.y, self.sim.origin.z])

    def camera(self, camera_id: str) -> SimulatedCamera:
        return next(c for c in self.sim.cameras if c.camera_id == camera_id)

    def centre_utm(self, camera_id: str) -> np.ndarray:
        camera = self.camera(camera_id)
        centre = camera_centre(camera.R_cam_from_local, camera.t_cam_from_local) + self.origin
        return np.asarray(centre, dtype=np.float64)

    def visible_runs(self, camera_id: str) -> dict[int, tuple[int, int]]:
        """Per traversal label of the truth: first and last stamp at which the vehicle is visible."""
        runs: dict[int, tuple[int, int]] = {}
        for frame in self.sim.ground_truth[camera_id].frames:
            if frame.traversal is not None:
                first, last = runs.get(frame.traversal, (frame.stamp_ns, frame.stamp_ns))
                runs[frame.traversal] = (min(first, frame.stamp_ns), max(last, frame.stamp_ns))
        return runs


@pytest.fixture(scope="module")
def scenes() -> dict[str, Scene]:
    """The simulator's scenes, once per module (about a second in all)."""
    result = {}
    for preset in ("sil-west", "v2x-10hz", "single-traversal"):
        sim = simulate(preset, 0, ideal=True)
        poses, rejected = poses_from_v2x(sim.v2x, UtmFrame(sim.origin.crs))
        assert rejected == 0
        result[preset] = Scene(sim, [(p.stamp_ns, p.x, p.y) for p in poses])
    return result


# ---------------------------------------------------------------------------------------------- helpers


def feed(
    tracker: TraversalTracker, samples: Sequence[Sample], station_id: int = STATION
) -> list[TraversalEvent]:
    """observe() every sample, received LATENCY_NS after its stamp; no ticks."""
    events: list[TraversalEvent] = []
    for stamp_ns, east, north in samples:
        events += tracker.observe(station_id, stamp_ns, east, north, stamp_ns + LATENCY_NS)
    return events


def replay(
    tracker: TraversalTracker,
    samples: Sequence[Sample],
    *,
    until_ns: int | None = None,
    station_id: int = STATION,
    on_tick: Callable[[int], None] | None = None,
) -> list[TraversalEvent]:
    """As the daemon runs: observe() each sample when received, tick() every second of our clock (then
    `on_tick(now)`), and keep ticking until `until_ns` (default: 10 s after the last message)."""
    events: list[TraversalEvent] = []
    now_ns = samples[0][0] + LATENCY_NS
    end_ns = until_ns if until_ns is not None else samples[-1][0] + LATENCY_NS + 10 * S

    def tick_until(limit_ns: int) -> None:
        nonlocal now_ns, events
        while now_ns <= limit_ns:
            events += tracker.tick(now_ns)
            if on_tick is not None:
                on_tick(now_ns)
            now_ns += S

    for stamp_ns, east, north in samples:
        tick_until(stamp_ns + LATENCY_NS)
        events += tracker.observe(station_id, stamp_ns, east, north, stamp_ns + LATENCY_NS)
    tick_until(end_ns)
    return events


def straight(
    start_ns: int,
    from_m: tuple[float, float],
    to_m: tuple[float, float],
    speed_mps: float = 10.0,
    rate_hz: float = 10.0,
) -> list[Sample]:
    """A straight drive (positions relative to (E0, N0)) at constant speed, sampled at rate_hz."""
    length = math.dist(from_m, to_m)
    count = round(length / speed_mps * rate_hz) + 1
    return [
        (
            start_ns + round(i / rate_hz * S),
            E0 + from_m[0] + (to_m[0] - from_m[0]) * i / (count - 1),
            N0 + from_m[1] + (to_m[1] - from_m[1]) * i / (count - 1),
        )
        for i in range(count)
    ]


def drive_past(start_ns: int) -> list[Sample]:
    """A pass through the synthetic circle: inside from start + 5 s to start + 15 s."""
    return straight(start_ns, (-100.0, 0.0), (100.0, 0.0))


def trigger(**changes: float) -> TriggerConfig:
    values: dict[str, float] = {"min_traversals": 3, "quiet_period_s": 20.0, "exit_grace_s": 3.0}
    values.update(changes)
    return TriggerConfig.model_validate(values)


def circle_tracker(**changes: float) -> TraversalTracker:
    return TraversalTracker("cam", CircleCoverage(E0, N0, 50.0), trigger(**changes))


def truth_result(scene: Scene, camera_id: str) -> CalibrationResult:
    """An accepted result with the simulator's true extrinsic (the sites' ground is level at the origin)."""
    camera = scene.camera(camera_id)
    R, t = camera.R_cam_from_local, camera.t_cam_from_local
    return CalibrationResult(
        rsu_id=scene.sim.rsu_id,
        camera_id=camera_id,
        result_id="truth",
        created_at_ns=T0,
        frame=ReferenceFrame(crs=scene.sim.origin.crs, origin=tuple(scene.origin)),
        R=tuple(tuple(float(v) for v in row) for row in R),
        t=tuple(float(v) for v in t),
        intrinsics=camera.intrinsics,
        ground_plane=GroundPlane(normal=(0.0, 0.0, 1.0), offset=0.0),
        verdict=Verdict(status="accepted"),
    )


def kinds(events: Sequence[TraversalEvent]) -> list[str]:
    return [event.kind for event in events]


# ---------------------------------------------------------------------------------------------- coverages


def test_circle_and_polygon_agree_point_by_point_and_vectorised() -> None:
    rng = np.random.default_rng(3)
    points = np.column_stack([E0 + rng.uniform(-120, 120, 2000), N0 + rng.uniform(-120, 120, 2000)])
    # A concave "U" (opening north), given clockwise: the notch between its arms is outside.
    u_shape = [(-60, -60), (-60, 60), (-20, 60), (-20, -20), (20, -20), (20, 60), (60, 60), (60, -60)]
    polygon = PolygonCoverage([(E0 + x, N0 + y) for x, y in u_shape])
    circle = CircleCoverage(E0, N0, 50.0)
    for coverage in (polygon, circle):
        vectorised = coverage.contains(points)
        assert vectorised.dtype == np.bool_ and vectorised.shape == (2000,)
        assert [coverage.contains_point(e, n) for e, n in points] == vectorised.tolist()
        assert 200 < vectorised.sum() < 500  # ~19 % (polygon) and ~14 % (circle) of the square
    assert circle.contains_point(E0 + 30.0, N0 + 40.0) and not circle.contains_point(E0 + 30.0, N0 + 40.1)
    assert polygon.contains_point(E0 - 40.0, N0 + 50.0) and polygon.contains_point(E0, N0 - 40.0)
    assert not polygon.contains_point(E0, N0 + 20.0)  # in the notch
    assert not polygon.contains_point(E0 + 61.0, N0)
    with pytest.raises(InputError, match="coverage_polygon"):
        PolygonCoverage([(E0, N0), (E0 + 1.0, N0)])
    with pytest.raises(InputError, match="coverage_radius_m"):
        CircleCoverage(E0, N0, 0.0)


def test_coverage_from_config_polygon_circle_or_learning() -> None:
    frame = UtmFrame("EPSG:32632")
    east, north = 572_000.0, 5_361_000.0
    lat, lon = frame.to_wgs84(
        np.array([east, east + 80.0, east + 80.0, east]), np.array([north] * 2 + [north + 60.0] * 2)
    )
    polygon = [GeoPoint(lat=float(a), lon=float(o)) for a, o in zip(lat, lon, strict=True)]
    position = GeoPoint(lat=float(lat[0]), lon=float(lon[0]))
    base = {"camera_id": "c1", "intrinsics": INTRINSICS}

    circle = coverage_from_config(CameraConfig(**base, position=position, coverage_radius_m=30.0), frame)
    assert isinstance(circle, CircleCoverage)
    assert circle.contains_point(east + 29.9, north) and not circle.contains_point(east + 30.1, north)

    both = CameraConfig(**base, position=position, coverage_radius_m=30.0, coverage_polygon=polygon)
    rectangle = coverage_from_config(both, frame)
    assert isinstance(rectangle, PolygonCoverage)  # the polygon wins: it is the more precise
    assert rectangle.contains_point(east + 79.0, north + 59.0)
    assert not rectangle.contains_point(east - 1.0, north + 30.0)

    assert coverage_from_config(CameraConfig(**base), frame) is None
    assert coverage_from_config(CameraConfig(**base, position=position), frame) is None


def test_view_coverage_matches_the_pipeline_projection(scenes: dict[str, Scene]) -> None:
    scene = scenes["sil-west"]
    camera = scene.camera("west-arm")
    coverage = coverage_from_result(truth_result(scene, "west-arm"))
    centre = scene.centre_utm("west-arm")
    rng = np.random.default_rng(5)
    xy = centre[:2] + rng.uniform(-300.0, 300.0, size=(4000, 2))
    inside = coverage.contains(xy)
    assert [coverage.contains_point(e, n) for e, n in xy] == inside.tolist()

    # Reference: the pipeline's own projection of the point 0.75 m above the level ground.
    local = np.column_stack([xy - scene.origin[:2], np.full(len(xy), 0.75)])
    pixels, depth = project_points(
        local,
        camera.R_cam_from_local,
        camera.t_cam_from_local,
        CameraModel.from_intrinsics(camera.intrinsics),
    )
    distance = np.linalg.norm(local - (centre - scene.origin), axis=1)
    with np.errstate(invalid="ignore"):
        expected = (
            (depth > 0)
            & (distance <= 250.0)
            & (pixels[:, 0] >= 0)
            & (pixels[:, 0] <= camera.intrinsics.width)
            & (pixels[:, 1] >= 0)
            & (pixels[:, 1] <= camera.intrinsics.height)
        )
    assert inside.tolist() == expected.tolist()
    assert 100 < inside.sum() < 2000


def test_view_coverage_range_margin_and_refused_result(scenes: dict[str, Scene]) -> None:
    scene = scenes["sil-west"]
    result = truth_result(scene, "west-arm")
    near = coverage_from_result(result, max_range_m=60.0)
    wide = coverage_from_result(result, margin_px=200.0)
    default = coverage_from_result(result)
    rng = np.random.default_rng(6)
    xy = scene.centre_utm("west-arm")[:2] + rng.uniform(-200.0, 200.0, size=(3000, 2))
    assert near.contains(xy).sum() < default.contains(xy).sum() < wide.contains(xy).sum()
    assert not np.any(near.contains(xy) & ~default.contains(xy))
    refused = result.model_copy(update={"R": None, "t": None, "verdict": Verdict(status="refused")})
    with pytest.raises(InputError, match="no coverage"):
        coverage_from_result(refused)


def test_view_coverage_rejects_directions_a_strong_lens_folds_into_the_image() -> None:
    # k1 = -0.05 is monotonic over this 1920 x 1080 image, but beyond ~77 deg off axis the polynomial turns
    # negative: a point at normalised x = 4.8 "projects" to u ~ 376 px although it is far outside the view.
    intrinsics = CameraIntrinsics(
        width=1920, height=1080, fx=800.0, fy=800.0, cx=960.0, cy=540.0, dist=(-0.05, 0.0, 0.0, 0.0, 0.0)
    )
    R = camera_rotation_from_view(math.pi / 2.0, 0.0)  # looking north, level: x_cam = east, z_cam = north
    height_m = 0.75
    t = -R @ np.array([0.0, 0.0, height_m])  # centre at the height of the vehicle point
    coverage = ViewCoverage(R, t, (E0, N0, 100.0), intrinsics)
    folded = np.array([[4.8 * 10.0, 10.0, height_m]])
    # The polynomial lands it in the image; the camera model gives it no pixel.
    naive = 800.0 * distort_normalized(np.array([[4.8, 0.0]]), np.array(intrinsics.dist))[0, 0] + 960.0
    assert 0.0 < naive < 1920.0
    pixels, _ = project_points(folded, R, t, CameraModel.from_intrinsics(intrinsics))
    assert np.isnan(pixels).all()
    assert not coverage.contains_point(E0 + 48.0, N0 + 10.0)
    assert not coverage.contains(np.array([[E0 + 48.0, N0 + 10.0]]))[0]
    assert coverage.contains_point(E0 + 5.0, N0 + 10.0)
    assert not coverage.contains_point(E0 + 5.0, N0 - 10.0)  # behind the camera


def test_view_coverage_of_a_wide_rational_lens_matches_the_pipeline_projection() -> None:
    # A 114 deg lens calibrated with OpenCV's rational model: its denominator matters most at the image's
    # edge, which is where the coverage decides (its first 5 coefficients alone would project the corner's
    # direction over 50000 px from the image centre).
    intrinsics = CameraIntrinsics(
        width=1920, height=1080, fx=1000.0, fy=1000.0, cx=960.0, cy=540.0,
        dist=(2.1, 0.6, 0.0004, -0.0003, 0.01, 2.45, 1.3, 0.08),
    )  # fmt: skip
    R = camera_rotation_from_view(math.pi / 2.0, math.radians(30.0))  # looking north, 30 deg down
    t = -R @ np.array([0.0, 0.0, 10.0])
    coverage = ViewCoverage(R, t, (E0, N0, 100.0), intrinsics, point_height_m=0.0)
    east, north = np.meshgrid(np.linspace(-60.0, 60.0, 61), np.linspace(-5.0, 60.0, 66))
    points = np.column_stack([east.ravel(), north.ravel(), np.zeros(east.size)])
    pixels, depth = project_points(points, R, t, CameraModel.from_intrinsics(intrinsics))
    inside = (
        (depth > 0)
        & (pixels[:, 0] >= 0)
        & (pixels[:, 0] <= 1920)
        & (pixels[:, 1] >= 0)
        & (pixels[:, 1] <= 1080)
    )
    found = np.array([coverage.contains_point(E0 + e, N0 + n) for e, n, _ in points])
    assert inside.sum() > 500 and (~inside).sum() > 500
    np.testing.assert_array_equal(found, inside)


# ---------------------------------------------------------------------------------------------- the simulator


def _coverage(scene: Scene, camera_id: str, kind: str) -> Coverage:
    if kind == "circle":
        centre = scene.centre_utm(camera_id)
        return CircleCoverage(float(centre[0]), float(centre[1]), 80.0)
    return coverage_from_result(truth_result(scene, camera_id))


@pytest.mark.parametrize("kind", ["circle", "view"])
@pytest.mark.parametrize(
    ("preset", "camera_id"),
    [
        ("sil-west", "west-junction"),
        ("sil-west", "west-arm"),
        ("v2x-10hz", "north"),
        ("single-traversal", "north"),
    ],
)
def test_live_count_equals_the_simulator_traversals(
    scenes: dict[str, Scene], preset: str, camera_id: str, kind: str
) -> None:
    scene = scenes[preset]
    runs = scene.visible_runs(camera_id)
    tracker = TraversalTracker(camera_id, _coverage(scene, camera_id, kind), TriggerConfig())
    events = replay(tracker, scene.samples)
    assert tracker.snapshot().traversals == len(runs) >= 1
    assert kinds(events) == ["entered", "left"] * len(runs)
    assert [e.traversals for e in events if e.kind == "left"] == list(range(1, len(runs) + 1))
    assert all(e.camera_id == camera_id and e.station_id == STATION for e in events)
    # Every stretch in which the camera sees the vehicle lies in the job window of its traversal.
    window = tracker.force_window(scene.samples[-1][0] + 20 * S)
    assert window is not None and len(window.traversals) == len(runs)
    for (first_ns, last_ns), traversal in zip(sorted(runs.values()), window.traversals, strict=True):
        assert traversal.enter_ns - MARGIN_NS <= first_ns and last_ns <= traversal.leave_ns + MARGIN_NS


def test_due_only_after_min_traversals_and_the_quiet_period(scenes: dict[str, Scene]) -> None:
    scene = scenes["sil-west"]
    coverage = _coverage(scene, "west-junction", "circle")
    tracker = TraversalTracker("west-junction", coverage, trigger(quiet_period_s=20.0))
    due_at: list[tuple[int, JobWindow]] = []

    def check(now_ns: int) -> None:
        window = tracker.due(now_ns)
        snap = tracker.snapshot()
        if window is not None:
            due_at.append((now_ns, window))
            assert snap.traversals >= 3 and not snap.inside
            assert snap.last_left_received_ns is not None
            assert now_ns - snap.last_left_received_ns >= 20 * S

    replay(tracker, scene.samples, until_ns=scene.samples[-1][0] + 120 * S, on_tick=check)
    assert due_at, "never due"
    first_ns, window = due_at[0]
    third = window.traversals[-1]
    # Due at the first tick (1 s steps) after the quiet period that followed the third traversal.
    assert 20 * S <= first_ns - third.left_received_ns < 21 * S
    assert len(window.traversals) == 3 and window.station_id == STATION
    assert window.start_ns == window.traversals[0].enter_ns - MARGIN_NS
    assert window.end_ns == third.leave_ns + MARGIN_NS
    # due() has no side effects: it stays due until the job is marked.
    assert len(due_at) > 10 and all(w == window for _, w in due_at)

    # Not enough traversals: never due.
    strict = TraversalTracker("west-junction", coverage, trigger(min_traversals=4))
    replay(strict, scene.samples, until_ns=scene.samples[-1][0] + 120 * S, on_tick=lambda now: None)
    assert strict.snapshot().traversals == 3
    assert strict.due(scene.samples[-1][0] + 200 * S) is None


def test_a_new_traversal_after_a_job_makes_it_due_again(scenes: dict[str, Scene]) -> None:
    scene = scenes["sil-west"]
    centre = scene.centre_utm("west-arm")
    coverage = CircleCoverage(float(centre[0]), float(centre[1]), 80.0)
    tracker = TraversalTracker("west-arm", coverage, trigger())
    replay(tracker, scene.samples)
    now_ns = scene.samples[-1][0] + 60 * S
    tracker.tick(now_ns)
    first = tracker.due(now_ns)
    assert first is not None and len(first.traversals) == 3
    tracker.mark_used(first)
    assert tracker.used_until_ns == first.end_ns
    assert tracker.snapshot().new_traversals == 0 and tracker.snapshot().traversals == 3
    for later_s in (0, 60, 600, 3000):
        tracker.tick(now_ns + later_s * S)
        assert tracker.due(now_ns + later_s * S) is None

    # The vehicle comes back along the same road (shifted in time): one more traversal makes a job on all four
    # due (an uncalibrated camera's; a calibrated one's re-verification needs new ones alone, see below).
    offset_ns = now_ns + 600 * S - scene.samples[0][0]
    again = [(s + offset_ns, e, n) for s, e, n in scene.samples if s < scene.samples[0][0] + 60 * S]
    events = replay(tracker, again, until_ns=again[-1][0] + 60 * S)
    assert kinds(events) == ["entered", "left"] and events[-1].traversals == 4
    later_ns = again[-1][0] + 60 * S
    second = tracker.due(later_ns)
    assert second is not None and len(second.traversals) == 4  # all in max_window_s, the used ones too
    assert second.traversals[:3] == first.traversals
    tracker.mark_used(second)
    assert tracker.due(later_ns + 60 * S) is None


def test_traversals_older_than_max_window_are_forgotten() -> None:
    tracker = circle_tracker(min_traversals=2, quiet_period_s=10.0, max_window_s=600.0)
    for start_s in (0, 100, 400):
        feed(tracker, drive_past(T0 + start_s * S))
    left = [T0 + s * S + 15 * S + 3 * S + LATENCY_NS for s in (0, 100, 400)]  # last inside + grace
    tracker.tick(T0 + 430 * S)
    assert tracker.snapshot().traversals == 3
    assert tracker.snapshot().window_start_ns == T0 + 5 * S - MARGIN_NS
    window = tracker.due(T0 + 430 * S)
    assert window is not None and len(window.traversals) == 3

    # The first traversal ends up to 600 s ago (our clock) and no further.
    tracker.tick(left[0] + 600 * S)
    assert tracker.snapshot().traversals == 3
    tracker.tick(left[0] + 600 * S + 1)
    assert tracker.snapshot().traversals == 2
    assert tracker.snapshot().window_start_ns == T0 + 105 * S - MARGIN_NS
    window = tracker.due(left[0] + 600 * S + 1)
    assert window is not None and [t.enter_ns for t in window.traversals] == [T0 + 105 * S, T0 + 405 * S]
    # due() filters by the window itself, even before tick() prunes.
    assert tracker.due(left[1] + 600 * S + 1) is None
    tracker.tick(left[2] + 600 * S + 1)
    assert tracker.snapshot().traversals == 0 and tracker.snapshot().window_start_ns is None


def test_reverification_counts_only_drive_pasts_after_the_last_jobs_window() -> None:
    """A calibrated camera (new_only): the next job needs min_traversals NEW drive-pasts and its window holds
    only those, starting after the last window, so fits before and after a possible move are never pooled."""
    tracker = circle_tracker(min_traversals=2, quiet_period_s=10.0)
    for start_s in (0, 100):
        feed(tracker, drive_past(T0 + start_s * S))
    first = tracker.due(T0 + 200 * S)
    assert first is not None and len(first.traversals) == 2
    tracker.mark_used(first)
    # One new drive-past: enough to re-fit on all three (not calibrated yet), not to re-verify.
    feed(tracker, drive_past(T0 + 200 * S))
    window = tracker.due(T0 + 300 * S)
    assert window is not None and len(window.traversals) == 3
    assert tracker.due(T0 + 300 * S, new_only=True) is None
    assert tracker.snapshot().new_traversals == 1
    # A second new one: the re-verification's window holds the two new drive-pasts only.
    feed(tracker, drive_past(T0 + 300 * S))
    window = tracker.due(T0 + 400 * S, new_only=True)
    assert window is not None and [t.enter_ns for t in window.traversals] == [T0 + 205 * S, T0 + 305 * S]
    assert window.start_ns == T0 + 205 * S - MARGIN_NS and window.start_ns > first.end_ns
    # A hand-triggered re-verification takes the new drive-pasts too; with none new, the old ones.
    forced = tracker.force_window(T0 + 400 * S, new_only=True)
    assert forced is not None and forced.traversals == window.traversals
    tracker.mark_used(window)
    forced = tracker.force_window(T0 + 400 * S, new_only=True)
    assert forced is not None and len(forced.traversals) == 4


def test_a_reverification_window_never_reaches_into_the_last_one() -> None:
    """A drive-past starting within the margin after the last window: the window starts after it."""
    tracker = circle_tracker(min_traversals=2, quiet_period_s=0.0)
    feed(tracker, drive_past(T0))
    feed(tracker, drive_past(T0 + 30 * S))
    first = tracker.due(T0 + 60 * S)
    assert first is not None
    tracker.mark_used(first)  # ends at T0 + 45 s + margin (10 s)
    feed(tracker, drive_past(T0 + 50 * S))  # inside from T0 + 55 s: the margin would reach T0 + 45 s
    feed(tracker, drive_past(T0 + 80 * S))
    window = tracker.due(T0 + 120 * S, new_only=True)
    assert window is not None and len(window.traversals) == 2
    assert window.start_ns == first.end_ns + 1


def test_after_a_withdrawal_no_drive_past_from_before_the_move_is_pooled() -> None:
    """A re-verification showed the camera moved but was refused (daemon.publication: the current result is
    withdrawn): the camera is uncalibrated again, so refused drive-pasts count again in the next job, but
    none that began before the re-verification's window (the old pose's)."""
    tracker = circle_tracker(min_traversals=2, quiet_period_s=10.0)
    for start_s in (0, 100):
        feed(tracker, drive_past(T0 + start_s * S))
    first = tracker.due(T0 + 200 * S)
    assert first is not None
    tracker.mark_used(first)
    for start_s in (200, 300):
        feed(tracker, drive_past(T0 + start_s * S))
    reverification = tracker.due(T0 + 400 * S, new_only=True)
    assert reverification is not None
    tracker.mark_used(reverification)

    tracker.set_not_before(reverification.start_ns)

    assert tracker.snapshot().traversals == 2  # the two after the move, of four
    assert tracker.due(T0 + 400 * S) is None  # nothing new since the refused job
    forced = tracker.force_window(T0 + 400 * S)
    assert forced is not None and [t.enter_ns for t in forced.traversals] == [T0 + 205 * S, T0 + 305 * S]
    feed(tracker, drive_past(T0 + 400 * S))
    window = tracker.due(T0 + 500 * S)
    assert window is not None
    assert [t.enter_ns for t in window.traversals] == [T0 + 205 * S, T0 + 305 * S, T0 + 405 * S]
    assert window.start_ns == reverification.start_ns
    # Like used_until it never moves back (a restart restores the persisted stamp).
    tracker.set_not_before(T0)
    assert tracker.snapshot().traversals == 3


def test_short_visits_are_discarded_but_restart_the_quiet_period() -> None:
    tracker = circle_tracker(min_traversals=2, min_dwell_s=2.0, quiet_period_s=30.0)
    feed(tracker, drive_past(T0))
    feed(tracker, drive_past(T0 + 100 * S))
    # Clipping the circle's edge: inside (|y| = 49.9 m) for ~0.6 s, below min_dwell_s.
    clip = straight(T0 + 200 * S, (-100.0, 49.9), (100.0, 49.9))
    events = feed(tracker, clip)
    assert kinds(events) == ["entered", "discarded"]
    discarded = events[-1]
    assert discarded.traversals == 2 and tracker.snapshot().traversals == 2
    assert tracker.snapshot().last_leave_ns == discarded.stamp_ns
    left_ns = tracker.snapshot().last_left_received_ns
    assert left_ns is not None and left_ns > T0 + 200 * S
    tracker.tick(left_ns + 29 * S)
    assert tracker.due(left_ns + 29 * S) is None  # the vehicle was just there
    assert tracker.due(left_ns + 30 * S) is not None

    # A visit of exactly min_dwell_s counts.
    exact = circle_tracker(min_dwell_s=2.0)
    events = feed(exact, [(T0 + i * S // 2, E0, N0) for i in range(5)] + [(T0 + 6 * S, E0 + 90.0, N0)])
    assert kinds(events) == ["entered", "left"]
    assert exact.snapshot().traversals == 1


def test_exit_grace_outside_or_silent() -> None:
    # Outside for 2 s (< exit_grace_s = 3 s) and back: one visit; 5 s outside: two.
    for outside_s, expected in ((2, ["entered"]), (5, ["entered", "left", "entered"])):
        tracker = circle_tracker()
        samples = [(T0 + i * S // 10, E0, N0) for i in range(50)]  # 5 s inside at 10 Hz
        samples += [(T0 + 5 * S + i * S // 10, E0 + 70.0, N0) for i in range(outside_s * 10)]
        samples += [(T0 + (5 + outside_s) * S + i * S // 10, E0, N0) for i in range(20)]
        assert kinds(feed(tracker, samples)) == expected

    # Silent inside (a V2X dropout) for 2 s: the same visit; silent for 4 s then inside: left and re-entered.
    for gap_s, expected in ((2, ["entered"]), (4, ["entered", "left", "entered"])):
        tracker = circle_tracker()
        samples = [(T0 + i * S // 10, E0, N0) for i in range(50)]
        samples += [(T0 + (5 + gap_s) * S + i * S // 10, E0, N0) for i in range(20)]
        events = feed(tracker, samples)
        assert kinds(events) == expected
        if len(events) == 3:
            assert events[1].stamp_ns == T0 + 49 * S // 10  # the last position inside
            assert tracker.snapshot().inside


def test_tick_ends_a_silent_visit_and_a_backlog_resumes_it() -> None:
    tracker = circle_tracker()
    feed(tracker, [(T0 + i * S // 10, E0, N0) for i in range(30)])  # 2.9 s inside, then silence
    last_received = T0 + 29 * S // 10 + LATENCY_NS
    assert tracker.tick(last_received + 3 * S - 1) == []
    events = tracker.tick(last_received + 3 * S)
    assert kinds(events) == ["left"] and events[0].stamp_ns == T0 + 29 * S // 10
    assert tracker.snapshot().traversals == 1 and not tracker.snapshot().inside
    # The next message was only stuck in a queue: by the vehicle's stamps it never left.
    events = tracker.observe(STATION, T0 + 3 * S, E0, N0, last_received + 4 * S)
    assert [(e.kind, e.stamp_ns, e.traversals) for e in events] == [("entered", T0, 0)]
    assert tracker.snapshot().inside and tracker.snapshot().traversals == 0
    events = feed(
        tracker, [(T0 + 3 * S + i * S // 10, E0, N0) for i in range(1, 20)] + [(T0 + 8 * S, E0 + 90, N0)]
    )
    assert kinds(events) == ["left"] and events[0].traversals == 1
    window = tracker.force_window(T0 + 20 * S)
    assert window is not None
    assert window.traversals == (Traversal(STATION, T0, T0 + 49 * S // 10, T0 + 8 * S + LATENCY_NS),)


def test_restore_used_until_after_a_restart(scenes: dict[str, Scene]) -> None:
    scene = scenes["sil-west"]
    coverage = _coverage(scene, "west-junction", "circle")
    before = TraversalTracker("west-junction", coverage, trigger())
    replay(before, scene.samples)
    now_ns = scene.samples[-1][0] + 60 * S
    window = before.due(now_ns)
    assert window is not None
    before.mark_used(window)

    # Restart: replay the log, restore the persisted stamp: the same traversals, nothing due.
    after = TraversalTracker("west-junction", coverage, trigger())
    feed(after, scene.samples)
    after.restore_used_until(window.end_ns)
    after.restore_used_until(window.end_ns - 100 * S)  # never moves back
    after.tick(now_ns)
    snap = after.snapshot()
    assert snap.traversals == 3 and snap.new_traversals == 0 and snap.used_until_ns == window.end_ns
    assert after.due(now_ns) is None and after.due(now_ns + 600 * S) is None
    # Without the restored stamp the replayed traversals would start a second job on the same data.
    unrestored = TraversalTracker("west-junction", coverage, trigger())
    feed(unrestored, scene.samples)
    unrestored.tick(now_ns)
    assert unrestored.due(now_ns) == window


def test_stale_and_non_finite_positions_are_ignored() -> None:
    tracker = circle_tracker()
    feed(tracker, [(T0 + i * S // 10, E0, N0) for i in range(30)])
    # Older, duplicate and non-finite positions far outside: none of them may end the visit.
    assert tracker.observe(STATION, T0 + S, E0 + 500.0, N0, T0 + 10 * S) == []
    assert tracker.observe(STATION, T0 + 29 * S // 10, E0 + 500.0, N0, T0 + 10 * S) == []
    assert tracker.observe(STATION, T0 + 10 * S, math.nan, N0, T0 + 10 * S) == []
    assert tracker.observe(STATION, T0 + 11 * S, E0, math.inf, T0 + 11 * S) == []
    events = tracker.observe(STATION, T0 + 12 * S, E0 + 90.0, N0, T0 + 12 * S)
    assert [(e.kind, e.stamp_ns) for e in events] == [("left", T0 + 29 * S // 10)]
    tracker.tick(T0 + 12 * S)
    assert tracker.snapshot().stale == 4 and tracker.snapshot().traversals == 1


def test_each_calibration_vehicle_has_its_own_visits() -> None:
    tracker = circle_tracker(min_traversals=2, quiet_period_s=10.0)
    a, b = 7, 4711
    pass_a = drive_past(T0)
    parked_b = [(T0 + i * S, E0 + 300.0, N0) for i in range(25)]  # B idles outside meanwhile
    merged = sorted([(s, e, n, a) for s, e, n in pass_a] + [(s, e, n, b) for s, e, n in parked_b])
    events: list[TraversalEvent] = []
    for stamp_ns, east, north, station in merged:
        events += tracker.observe(station, stamp_ns, east, north, stamp_ns + LATENCY_NS)
    assert [(e.kind, e.station_id) for e in events] == [("entered", a), ("left", a)]
    feed(tracker, drive_past(T0 + 100 * S), station_id=b)
    feed(tracker, drive_past(T0 + 200 * S), station_id=b)
    tracker.tick(T0 + 300 * S)
    snap = tracker.snapshot()
    assert snap.traversals == 2 and snap.traversals_total == 3 and snap.stations == 2
    window = tracker.due(T0 + 300 * S)
    assert window is not None and window.station_id == b and len(window.traversals) == 2
    assert window.start_ns == T0 + 105 * S - MARGIN_NS


def test_force_window_uses_whatever_there_is() -> None:
    tracker = circle_tracker()
    assert tracker.force_window(T0) is None
    feed(tracker, drive_past(T0))
    window = tracker.force_window(T0 + 30 * S)
    assert window is not None and len(window.traversals) == 1
    assert window.start_ns == T0 + 5 * S - MARGIN_NS and window.end_ns == T0 + 15 * S + MARGIN_NS
    assert tracker.due(T0 + 300 * S) is None  # one traversal is not enough for a triggered job
    # Data but no traversal (the vehicle drove elsewhere): all of it, as in learning mode.
    elsewhere = circle_tracker()
    feed(elsewhere, straight(T0, (300.0, 0.0), (300.0, 200.0)))
    window = elsewhere.force_window(T0 + 30 * S)
    assert window == JobWindow(T0, T0 + 20 * S, STATION, ())


# ---------------------------------------------------------------------------------------------- learning


def test_learning_mode_is_due_after_learn_window_of_data_and_silence(scenes: dict[str, Scene]) -> None:
    scene = scenes["sil-west"]
    samples = scene.samples
    first_ns, last_ns = samples[0][0], samples[-1][0]
    span_s = (last_ns - first_ns) / S
    assert span_s > 200.0
    tracker = TraversalTracker("west-arm", None, trigger(learn_window_s=150.0, quiet_period_s=30.0))
    due_at: list[int] = []

    def check(now_ns: int) -> None:
        if tracker.due(now_ns) is not None:
            due_at.append(now_ns)

    events = replay(tracker, samples, until_ns=last_ns + 60 * S, on_tick=check)
    assert events == []
    snap = tracker.snapshot()
    assert snap.learning and snap.traversals == 0 and not snap.inside
    assert snap.learn_data_s == pytest.approx(span_s, abs=5.0)  # the dropouts (< exit_grace_s) count
    assert snap.window_start_ns == first_ns
    # Due once the vehicle has been silent for the quiet period (30 s after its last message).
    assert due_at and 30 * S <= due_at[0] - (last_ns + LATENCY_NS) < 31 * S
    window = tracker.due(due_at[0])
    assert window == JobWindow(first_ns, last_ns, STATION, ())

    # Too little data: never due, but a trigger by hand gets all of it.
    patient = TraversalTracker("west-arm", None, trigger(learn_window_s=600.0))
    replay(patient, samples, until_ns=last_ns + 200 * S, on_tick=lambda now: None)
    assert patient.due(last_ns + 200 * S) is None
    assert patient.force_window(last_ns + 200 * S) == window
    # After a withdrawal (the camera moved) a learning window starts where the data after the move start.
    middle_ns = (first_ns + last_ns) // 2
    patient.set_not_before(middle_ns)
    assert patient.force_window(last_ns + 200 * S) == JobWindow(middle_ns, last_ns, STATION, ())
    patient.set_not_before(last_ns)
    assert patient.force_window(last_ns + 200 * S) is None  # nothing heard since


def test_learning_mode_retriggers_on_new_data_and_forgets_old_data() -> None:
    tracker = TraversalTracker(
        "cam", None, trigger(learn_window_s=60.0, quiet_period_s=10.0, max_window_s=1000.0)
    )
    session = [(T0 + i * S // 10, E0 + 500.0, N0 + i * 0.5) for i in range(900)]  # 90 s of data
    feed(tracker, session)
    end_received = session[-1][0] + LATENCY_NS
    assert tracker.due(end_received + 9 * S) is None
    window = tracker.due(end_received + 10 * S)
    assert window is not None and window.start_ns == T0 and window.end_ns == session[-1][0]
    tracker.mark_used(window)
    assert tracker.due(end_received + 100 * S) is None

    # The vehicle passes again for 10 s: new data, silence, and a job on everything in max_window_s.
    later = [(T0 + 300 * S + i * S // 10, E0 + 500.0, N0) for i in range(100)]
    feed(tracker, later)
    later_received = later[-1][0] + LATENCY_NS
    again = tracker.due(later_received + 10 * S)
    assert again is not None and again.start_ns == T0 and again.end_ns == later[-1][0]

    # 950 s after the first session only its last 50 s are in max_window_s: 59.9 s of data in all.
    now_ns = end_received + 950 * S
    tracker.tick(now_ns)
    assert tracker.snapshot().learn_data_s == pytest.approx(50.0 + 9.9)
    assert tracker.snapshot().window_start_ns == session[-1][0] - 50 * S
    assert tracker.due(now_ns) is None  # below learn_window_s now
    window = tracker.force_window(now_ns)
    assert window is not None and window.start_ns == session[-1][0] - 50 * S


def test_learned_coverage_recounts_a_replayed_window(scenes: dict[str, Scene]) -> None:
    scene = scenes["sil-west"]
    tracker = TraversalTracker("west-arm", None, trigger(learn_window_s=150.0, quiet_period_s=30.0))
    feed(tracker, scene.samples)
    now_ns = scene.samples[-1][0] + LATENCY_NS + 30 * S
    window = tracker.due(now_ns)
    assert window is not None
    tracker.mark_used(window)

    # The learning job was accepted: its result becomes the coverage and the daemon replays the window.
    tracker.set_coverage(coverage_from_result(truth_result(scene, "west-arm")))
    snap = tracker.snapshot()
    assert not snap.learning and snap.traversals == 0 and snap.used_until_ns == window.end_ns
    feed(tracker, scene.samples)
    tracker.tick(now_ns)
    snap = tracker.snapshot()
    assert snap.traversals == len(scene.visible_runs("west-arm")) and snap.new_traversals == 0
    assert tracker.due(now_ns + 600 * S) is None  # the learning job already used these
