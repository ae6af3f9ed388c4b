"""Vehicle motion for the simulator: the calibration vehicle's drive and the other traffic.

Every vehicle drives along a Path (sim_world) with the Intelligent Driver Model (Treiber et al. 2000) on a
global time grid t_k = k * DT_S (seconds from the recording start, camera clock): a desired speed from the
path's curves and the driver's cruise speed, a virtual obstacle at the stop line while the driver wants to
stop there, and the vehicles ahead in the same inbound lane (or on the same route) as leaders. Vehicles
enter in order of their entry time, so every leader's motion is known when its followers are driven; the
result is a queue that brakes, stops and pulls away like traffic, and never overlaps within a lane.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field, replace

import numpy as np

from sim.geometry import FloatArray, IntArray
from sim.presets import DriveSpec, TrafficSpec
from sim.world import (
    PATH_STEP_M,
    GroundSurface,
    Path,
    RoadNetwork,
    Route,
    extension_path,
    far_connector,
    ring_path,
)

DT_S = 0.1
# IDM constants shared by all drivers: acceleration exponent and jam distance (m).
IDM_DELTA = 4.0
IDM_MIN_GAP_M = 2.0
# The driver's stop at a stop line counts once the front is this close to the line and nearly still.
STOP_REACHED_M = 1.5
STOP_REACHED_MPS = 0.3
# Leaders in the same inbound lane but on another route stop constraining a follower once their rear is
# this far past the stop line (the paths have separated by then).
DIVERGE_AFTER_STOP_M = 6.0
EMERGENCY_DECEL_MPS2 = 9.0
# Other vehicles entering the calibration vehicle's lane less than this before it are moved behind it.
CALIB_ENTRY_GUARD_S = 4.0
# No vehicle drives longer than this past the planned end of the recording (a guard, never reached).
MAX_OVERRUN_S = 600.0

# Toolbox class ids and plausible dimensions (length, width, height ranges, m), cruise speeds (m/s) and
# accelerations (m/s^2) per class: car, truck, van, bus.
CLASS_IDS = (4, 5, 6, 7)
CLASS_DIMS = (
    ((3.9, 4.9), (1.70, 1.90), (1.40, 1.65)),
    ((7.5, 12.0), (2.45, 2.55), (3.0, 3.9)),
    ((4.9, 6.2), (1.90, 2.10), (1.90, 2.70)),
    ((11.0, 13.5), (2.50, 2.55), (2.95, 3.30)),
)
CLASS_CRUISE = ((10.0, 15.0), (8.0, 12.0), (9.0, 13.5), (8.0, 11.5))
CLASS_ACCEL = ((1.4, 2.6), (0.7, 1.2), (1.1, 1.8), (0.8, 1.2))


@dataclass(frozen=True, slots=True)
class DriverParams:
    """IDM parameters of one driver (m/s, m/s^2, s)."""

    cruise_mps: float
    accel_mps2: float
    decel_mps2: float
    headway_s: float


@dataclass(frozen=True, eq=False)
class Motion:
    """Arc length s (m) and speed v (m/s) along a path at grid steps k0, k0 + 1, ...: t = k * DT_S."""

    k0: int
    s: FloatArray
    v: FloatArray

    @property
    def k_last(self) -> int:
        return self.k0 + len(self.s) - 1

    def state_at(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(s, v) at times t inside [k0, k_last] * DT_S: cubic Hermite in s with the speeds as slopes.

        The driver update is trapezoidal (s' = s + (v + v') / 2 dt), so this is exactly the piecewise
        constant-acceleration motion between steps: smooth positions at any pose or frame instant. The
        clip keeps it monotonic on the rare steps a hard clamp behind a leader made inconsistent."""
        if len(self.s) == 1:
            return np.full(len(t), self.s[0]), np.full(len(t), self.v[0])
        x = t / DT_S - self.k0
        k = np.clip(np.floor(x).astype(np.int64), 0, len(self.s) - 2)
        u = np.clip(x - k, 0.0, 1.0)
        v0, v1 = self.v[k], self.v[k + 1]
        s = np.clip(self.s[k] + DT_S * (v0 * u + 0.5 * (v1 - v0) * u * u), self.s[k], self.s[k + 1])
        return s, v0 + (v1 - v0) * u


@dataclass(frozen=True, eq=False)
class Leg:
    """A vehicle's motion along one path; `traversal` numbers the calibration vehicle's passes (None on
    connectors and for other vehicles)."""

    path: Path
    motion: Motion
    traversal: int | None = None


@dataclass(frozen=True, eq=False)
class SimVehicle:
    """One simulated vehicle: a cuboid (length, width, height in m) with a toolbox class, driving its legs
    back to back in time (each leg ends on the step where the next starts)."""

    vehicle_id: int
    cls: int
    length: float
    width: float
    height: float
    legs: tuple[Leg, ...]
    route: str  # arm and lane in > arm and lane out, e.g. "W1>E1"; "calibration" for the calibration vehicle
    is_calibration: bool = False
    # The rear axle's distance from the body's rear end (m): its footprint centre follows the path and the
    # body turns about the rear axle, as wheels that roll make it (Path.towed_yaw_at). None: the body's yaw
    # is the path's tangent at its centre (the first simulator's kinematics).
    rear_axle_m: float | None = None

    @property
    def t_start(self) -> float:
        return self.legs[0].motion.k0 * DT_S

    @property
    def t_end(self) -> float:
        return self.legs[-1].motion.k_last * DT_S


@dataclass(frozen=True, eq=False)
class VehicleStates:
    """Sampled states of one vehicle at N instants: footprint-centre poses (N, 6) x, y, z, yaw, pitch, roll
    (local frame, the body resting on the ground), speed (N,) m/s, and the traversal index (N,), -1 when
    the vehicle is not on a traversal."""

    centre_poses: FloatArray
    speed: FloatArray
    traversal: IntArray


def sample_vehicle(vehicle: SimVehicle, t: FloatArray, ground: GroundSurface) -> VehicleStates:
    """States at times t (N,) within [t_start, t_end] (seconds): each leg covers [its start, next start)."""
    starts = np.array([leg.motion.k0 * DT_S for leg in vehicle.legs[1:]])
    leg_index = np.searchsorted(starts, t, side="right")
    xy = np.empty((len(t), 2))
    yaw = np.empty(len(t))
    speed = np.empty(len(t))
    traversal = np.full(len(t), -1, dtype=np.int64)
    for i, leg in enumerate(vehicle.legs):
        rows = np.flatnonzero(leg_index == i)
        if len(rows) == 0:
            continue
        s, v = leg.motion.state_at(t[rows])
        xy[rows], yaw[rows] = leg.path.at(s)
        if vehicle.rear_axle_m is not None:
            yaw[rows] = leg.path.towed_yaw_at(s, 0.5 * vehicle.length - vehicle.rear_axle_m)
        speed[rows] = v
        if leg.traversal is not None:
            traversal[rows] = leg.traversal
    return VehicleStates(surface_poses(xy, yaw, vehicle.length, vehicle.width, ground), speed, traversal)


def surface_poses(
    xy: FloatArray, yaw: FloatArray, length: float, width: float, ground: GroundSurface
) -> FloatArray:
    """Footprint-centre poses (N, 6) of bodies resting on the ground: z from the four wheel contacts,
    pitch from the axles' height difference (positive = nose down, R = Rz Ry Rx), roll from the sides'."""
    forward = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    left = np.stack([-forward[:, 1], forward[:, 0]], axis=1)
    half_base = 0.3 * length  # axles at +-30 % of the length: a typical wheelbase of 60 %
    half_track = 0.5 * width
    z_front = ground.height(xy + half_base * forward)
    z_rear = ground.height(xy - half_base * forward)
    z_left = ground.height(xy + half_track * left)
    z_right = ground.height(xy - half_track * left)
    z = 0.25 * (z_front + z_rear + z_left + z_right)
    pitch = -np.arctan2(z_front - z_rear, 2.0 * half_base)
    roll = np.arctan2(z_left - z_right, 2.0 * half_track)
    wrapped = np.angle(np.exp(1j * yaw))
    return np.column_stack([xy, z, wrapped, pitch, roll])


@dataclass(frozen=True, slots=True)
class _Leader:
    motion: Motion
    half_length: float
    shared_until: float  # follower-path arc length up to which the leader constrains the follower


def drive_path(
    path: Path,
    speed_limit: FloatArray,
    driver: DriverParams,
    length: float,
    k0: int,
    s0: float,
    v0: float,
    stops: list[tuple[float, float]],
    leaders: list[_Leader],
    k_max: int,
) -> Motion:
    """Drive `path` from arc length s0 at speed v0, starting at step k0, until the path's end (or k_max).

    stops: (arc length of the stop line, dwell s): the front stops at the line and waits. Leaders ahead
    constrain the driver through the IDM interaction term, plus a hard clamp so no numerical corner case
    lets two bodies overlap."""
    limit = speed_limit.tolist()
    n_limit = len(limit)
    end = path.length
    a, b, headway = driver.accel_mps2, driver.decel_mps2, driver.headway_s
    cruise = driver.cruise_mps
    sqrt_ab2 = 2.0 * math.sqrt(a * b)
    half = 0.5 * length
    leader_data = [
        (ld.motion.k0, ld.motion.s.tolist(), ld.motion.v.tolist(), ld.half_length, ld.shared_until)
        for ld in leaders
    ]
    pending = sorted(stops)
    dwell_end: int | None = None
    s, v, k = s0, v0, k0
    s_out, v_out = [s], [v]
    while s < end and k < k_max:
        v_desired = min(cruise, limit[min(max(int(s / PATH_STEP_M), 0), n_limit - 1)])
        acc = a * (1.0 - (v / max(v_desired, 0.5)) ** IDM_DELTA)
        gap, v_lead = math.inf, 0.0
        clamp = math.inf  # the furthest the front may be at the next step
        if pending:
            stop_s, dwell_s = pending[0]
            to_line = stop_s - (s + half)
            if dwell_end is None and to_line < STOP_REACHED_M and v < STOP_REACHED_MPS:
                dwell_end = k + round(dwell_s / DT_S)
            if dwell_end is not None and k >= dwell_end:
                pending.pop(0)
                dwell_end = None
            else:
                # A standing obstacle placed so that IDM's jam gap puts the front 0.3 m before the line.
                gap = to_line + IDM_MIN_GAP_M - 0.3
        for lk0, ls, lv, lhalf, shared in leader_data:
            j = k - lk0
            if j < 0 or j + 1 >= len(ls):
                continue
            rear = ls[j] - lhalf
            if rear > shared:
                continue
            g = rear - (s + half)
            if g < gap:
                gap, v_lead = g, lv[j]
            clamp = min(clamp, ls[j + 1] - lhalf - 0.5)
        if gap < math.inf:
            desired_gap = IDM_MIN_GAP_M + max(0.0, v * headway + v * (v - v_lead) / sqrt_ab2)
            acc -= a * (desired_gap / max(gap, 0.1)) ** 2
        acc = max(acc, -EMERGENCY_DECEL_MPS2)
        v_next = max(0.0, v + acc * DT_S)
        s_next = s + 0.5 * (v + v_next) * DT_S
        if s_next + half > clamp:
            s_next = max(s, clamp - half)
            v_next = max(0.0, 2.0 * (s_next - s) / DT_S - v)
        s, v = s_next, v_next
        k += 1
        s_out.append(s)
        v_out.append(v)
    return Motion(k0, np.array(s_out), np.array(v_out))


def _uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(rng.uniform(bounds[0], bounds[1]))


@dataclass(frozen=True, slots=True)
class _TrafficEntry:
    k_entry: int
    route: Route
    cls: int
    dims: tuple[float, float, float]
    driver: DriverParams
    stop_dwell_s: float | None


def _sample_class(
    rng: np.random.Generator, class_index: int
) -> tuple[int, tuple[float, float, float], DriverParams]:
    (l_lo, l_hi), (w_lo, w_hi), (h_lo, h_hi) = CLASS_DIMS[class_index]
    dims = (float(rng.uniform(l_lo, l_hi)), float(rng.uniform(w_lo, w_hi)), float(rng.uniform(h_lo, h_hi)))
    driver = DriverParams(
        cruise_mps=_uniform(rng, CLASS_CRUISE[class_index]),
        accel_mps2=_uniform(rng, CLASS_ACCEL[class_index]),
        decel_mps2=float(rng.uniform(2.0, 3.0)),
        headway_s=float(rng.uniform(1.0, 1.8)),
    )
    return CLASS_IDS[class_index], dims, driver


def _traffic_entries(
    network: RoadNetwork, spec: TrafficSpec, count: int, t_end: float, rng: np.random.Generator
) -> list[_TrafficEntry]:
    """`count` vehicles spread over the inbound lanes; per lane a Poisson process (sorted uniform times)
    pushed apart to the minimum headway; each picks a route from its lane and a class."""
    lanes = sorted(network.inbound)
    routes_by_lane: dict[tuple[str, int], list[Route]] = {lane: [] for lane in lanes}
    for route in network.routes.values():
        routes_by_lane[route.lane_key].append(route)
    lane_of = rng.integers(0, len(lanes), size=count)
    entries: list[_TrafficEntry] = []
    mix = np.array(spec.class_mix) / np.sum(spec.class_mix)
    for lane_index, lane in enumerate(lanes):
        n = int(np.sum(lane_of == lane_index))
        times = np.sort(rng.uniform(-spec.lead_in_s, t_end, size=n))
        for i in range(1, n):
            times[i] = max(times[i], times[i - 1] + spec.min_headway_s)
        candidates = routes_by_lane[lane]
        straight = [r for r in candidates if r.turn == "straight"]
        turns = [r for r in candidates if r.turn != "straight"]
        for t in times:
            if straight and (not turns or rng.random() < spec.straight_share):
                route = straight[int(rng.integers(len(straight)))]
            else:
                route = turns[int(rng.integers(len(turns)))]
            cls, dims, driver = _sample_class(rng, int(rng.choice(4, p=mix)))
            dwell = _uniform(rng, spec.stop_dwell_s) if rng.random() < spec.stop_probability else None
            entries.append(_TrafficEntry(round(t / DT_S), route, cls, dims, driver, dwell))
    return entries


@dataclass(frozen=True, slots=True)
class _TraversalPlan:
    route: Route
    driver: DriverParams
    stop_dwell_s: float | None
    followers: int


@dataclass(frozen=True, eq=False)
class TrafficResult:
    """All simulated vehicles: the calibration vehicle and the others (ids 1, 2, ... in the order they were
    driven); `end_s` is the recording length in seconds."""

    calibration: SimVehicle
    others: tuple[SimVehicle, ...]
    end_s: float
    traversal_windows: tuple[tuple[float, float], ...]  # (start, end) s of every traversal leg


@dataclass
class _LaneState:
    last_in_lane: dict[tuple[str, int], tuple[Motion, Route, float]] = field(default_factory=dict)
    last_on_route: dict[str, tuple[Motion, Route, float]] = field(default_factory=dict)

    def leaders_for(self, route: Route) -> list[_Leader]:
        found: list[_Leader] = []
        seen: set[int] = set()
        for entry in (self.last_in_lane.get(route.lane_key), self.last_on_route.get(_route_key(route))):
            if entry is None or id(entry[0]) in seen:
                continue
            motion, leader_route, half = entry
            seen.add(id(entry[0]))
            shared = math.inf if leader_route is route else route.stop_s + DIVERGE_AFTER_STOP_M
            found.append(_Leader(motion, half, shared))
        return found

    def record(self, route: Route, motion: Motion, length: float) -> None:
        self.last_in_lane[route.lane_key] = (motion, route, 0.5 * length)
        self.last_on_route[_route_key(route)] = (motion, route, 0.5 * length)


def _route_key(route: Route) -> str:
    return f"{route.entry_arm}{route.entry_lane}>{route.exit_arm}{route.exit_lane}"


def _entry_state(
    leaders: list[_Leader], k: int, cruise: float, half_length: float, headway_s: float
) -> tuple[float, float]:
    """Where (arc length, <= 0) and how fast a vehicle enters its route at step k: at the lane's far start at
    cruise speed, unless a leader is close ahead; then no faster than it and far enough behind it (further
    back along the road, still hundreds of metres from any camera)."""
    s, speed = 0.0, cruise
    for leader in leaders:
        j = k - leader.motion.k0
        if not 0 <= j < len(leader.motion.s):
            continue
        rear = float(leader.motion.s[j]) - leader.half_length
        if rear < 80.0:
            speed = min(speed, float(leader.motion.v[j]))
            s = min(s, rear - IDM_MIN_GAP_M - speed * headway_s - half_length)
    return s, speed


def _plan_traversals(
    network: RoadNetwork, drive: DriveSpec, rng: np.random.Generator
) -> list[_TraversalPlan]:
    plans = []
    for i, name in enumerate(drive.routes):
        route = network.route(name)
        driver = DriverParams(
            cruise_mps=_uniform(rng, drive.cruise_mps),
            accel_mps2=_uniform(rng, drive.accel_mps2),
            decel_mps2=_uniform(rng, drive.decel_mps2),
            headway_s=1.5,
        )
        wants_stop = (
            drive.stops[i]
            if drive.stops is not None and i < len(drive.stops)
            else (rng.random() < drive.stop_probability)
        )
        dwell = _uniform(rng, drive.stop_dwell_s) if wants_stop else None
        lo, hi = drive.followers_per_traversal
        plans.append(_TraversalPlan(route, driver, dwell, int(rng.integers(lo, hi + 1))))
    return plans


def _connector_driver(drive: DriveSpec) -> DriverParams:
    return DriverParams(cruise_mps=drive.connector_speed_mps, accel_mps2=1.8, decel_mps2=2.5, headway_s=1.5)


def _drive_free(
    path: Path,
    drive: DriveSpec,
    length: float,
    k0: int,
    s0: float,
    v0: float,
    park_s: float,
    k_max: int,
    end_speed_mps: float | None = None,
) -> Motion:
    """Drive a path nobody else uses (connectors, tail, the far ring), optionally parking half way and
    arriving at `end_speed_mps` (the next traversal's cruise speed, reached by comfortable braking)."""
    stops = [(0.5 * path.length, park_s)] if park_s > 0 else []
    limit = path.curve_speed_limit()
    if end_speed_mps is not None:
        limit = np.minimum(limit, np.sqrt(end_speed_mps**2 + 2.0 * 1.5 * (path.length - path.s)))
    return drive_path(path, limit, _connector_driver(drive), length, k0, s0, v0, stops, [], k_max)


def _continue_from(leg: Leg) -> tuple[int, float, float]:
    """Step, arc length on the next path and speed where the next leg starts (the overshoot carries over)."""
    return leg.motion.k_last, float(leg.motion.s[-1]) - leg.path.length, float(leg.motion.v[-1])


class _TrafficSim:
    """Drives vehicles in order of entry; remembers the last vehicle per inbound lane and per route."""

    def __init__(self, k_limit: int, entries: list[_TrafficEntry], rng: np.random.Generator) -> None:
        self.k_limit = k_limit
        self.state = _LaneState()
        self.heap: list[tuple[int, int, _TrafficEntry]] = [(e.k_entry, i, e) for i, e in enumerate(entries)]
        heapq.heapify(self.heap)
        self.order = len(entries)
        self.others: list[SimVehicle] = []
        self.rng = rng

    def drive_entries(self, until_k: int) -> None:
        """Drive every queued vehicle entering at or before step `until_k`."""
        while self.heap and self.heap[0][0] <= until_k:
            _, _, entry = heapq.heappop(self.heap)
            route = entry.route
            leaders = self.state.leaders_for(route)
            s0, v0 = _entry_state(
                leaders, entry.k_entry, entry.driver.cruise_mps, 0.5 * entry.dims[0], entry.driver.headway_s
            )
            stops = [(route.stop_s, entry.stop_dwell_s)] if entry.stop_dwell_s is not None else []
            motion = drive_path(
                route.path,
                route.speed_limit,
                entry.driver,
                entry.dims[0],
                entry.k_entry,
                s0,
                v0,
                stops,
                leaders,
                self.k_limit,
            )
            self.state.record(route, motion, entry.dims[0])
            self.others.append(
                SimVehicle(
                    len(self.others) + 1,
                    entry.cls,
                    *entry.dims,
                    legs=(Leg(route.path, motion),),
                    route=_route_key(route),
                )
            )

    def defer_lane_entries(self, lane: tuple[str, int], k_from: int, k_to: int) -> None:
        """Move queued entries of `lane` in (k_from, k_to] to just after k_to: the calibration vehicle,
        arriving continuously from its connector, cannot wait for them, so they enter behind it."""
        moved = [item for item in self.heap if item[2].route.lane_key == lane and k_from < item[0] <= k_to]
        if not moved:
            return
        self.heap = [item for item in self.heap if item not in moved]
        for _, order, entry in moved:
            later = replace(entry, k_entry=k_to + 1)
            self.heap.append((later.k_entry, order, later))
        heapq.heapify(self.heap)

    def add_followers(self, plan: _TraversalPlan, k_entry: int, gap_s: tuple[float, float]) -> None:
        """Queue the hard distractors: cars on the vehicle's own route, 1.5-4 s behind, keeping up with it."""
        for _ in range(plan.followers):
            cls, dims, driver = _sample_class(self.rng, 0 if self.rng.random() < 0.8 else 2)
            driver = DriverParams(
                cruise_mps=plan.driver.cruise_mps * float(self.rng.uniform(1.0, 1.12)),
                accel_mps2=max(driver.accel_mps2, plan.driver.accel_mps2),
                decel_mps2=driver.decel_mps2,
                headway_s=float(self.rng.uniform(0.9, 1.4)),
            )
            dwell = float(self.rng.uniform(0.5, 2.0)) if plan.stop_dwell_s is not None else None
            k_follow = k_entry + round(_uniform(self.rng, gap_s) / DT_S)
            self.order += 1
            heapq.heappush(
                self.heap,
                (k_follow, self.order, _TrafficEntry(k_follow, plan.route, cls, dims, driver, dwell)),
            )


def _drive_calibration(
    network: RoadNetwork,
    plans: list[_TraversalPlan],
    drive: DriveSpec,
    length: float,
    park_s: float,
    sim: _TrafficSim,
) -> list[Leg]:
    """The calibration vehicle's traversals back to back, joined by far connectors.

    Before each traversal every vehicle entering earlier is driven (any of them may be its leader); its
    followers are queued after it like any other entry."""
    legs: list[Leg] = []
    k, s, v = 0, 0.0, plans[0].driver.cruise_mps
    guard = round(CALIB_ENTRY_GUARD_S / DT_S)
    for i, plan in enumerate(plans):
        route = plan.route
        sim.drive_entries(k - guard)
        sim.defer_lane_entries(route.lane_key, k - guard, k)
        sim.drive_entries(k)
        leaders = sim.state.leaders_for(route)
        stops = [(route.stop_s, plan.stop_dwell_s)] if plan.stop_dwell_s is not None else []
        # No step limit: the vehicle always completes its traversals; the recording is made to fit.
        motion = drive_path(
            route.path, route.speed_limit, plan.driver, length, k, s, v, stops, leaders, 10**9
        )
        legs.append(Leg(route.path, motion, traversal=i))
        sim.state.record(route, motion, length)
        sim.add_followers(plan, k, drive.follower_gap_s)
        k, s, v = _continue_from(legs[-1])
        if i + 1 < len(plans):
            path = far_connector(route.path, plans[i + 1].route.path, network.ring_radius_m)
            legs.append(
                Leg(
                    path,
                    _drive_free(
                        path,
                        drive,
                        length,
                        k,
                        s,
                        v,
                        park_s,
                        10**9,
                        end_speed_mps=plans[i + 1].driver.cruise_mps,
                    ),
                )
            )
            k, s, v = _continue_from(legs[-1])
    return legs


def simulate_traffic(
    network: RoadNetwork,
    drive: DriveSpec,
    traffic: TrafficSpec,
    vehicle_dims: tuple[float, float, float],
    duration_s: float | None,
    drive_rng: np.random.Generator,
    traffic_rng: np.random.Generator,
) -> TrafficResult:
    """The calibration vehicle's drive and `traffic.count` other vehicles (its followers included).

    The recording lasts until the vehicle has finished its last traversal (it is then ~300 m away, out of
    view), or `duration_s`; with a duration the vehicle parks on its connectors (out of view) to spread its
    passes over the recording."""
    length = vehicle_dims[0]
    plans = [] if drive.elsewhere else _plan_traversals(network, drive, drive_rng)
    park_s = 0.0
    if plans:
        # Drive once alone to learn how long the passes take; traffic can only delay the vehicle.
        solo_plans = [replace(plan, followers=0) for plan in plans]
        alone = _drive_calibration(network, solo_plans, drive, length, 0.0, _TrafficSim(0, [], drive_rng))
        k_alone = alone[-1].motion.k_last
        if duration_s is not None and len(plans) > 1:
            # Keep a minute in hand: the traffic delays the vehicle a few seconds per traversal.
            park_s = max(0.0, (duration_s - k_alone * DT_S - 60.0) / (len(plans) - 1))
        k_planned = k_alone + round(((len(plans) - 1) * park_s + 3.0) / DT_S)
    else:
        k_planned = round((duration_s if duration_s is not None else 240.0) / DT_S)
    k_end = max(k_planned, round(duration_s / DT_S)) if duration_s is not None else k_planned
    followers = sum(p.followers for p in plans)
    entries = _traffic_entries(network, traffic, max(0, traffic.count - followers), k_end * DT_S, traffic_rng)
    # Vehicles are driven to the ends of their routes: the limit only guards against a never-ending loop
    # (the recording may grow past k_end when traffic delays the calibration vehicle).
    sim = _TrafficSim(k_end + round(MAX_OVERRUN_S / DT_S), entries, traffic_rng)
    if plans:
        legs = _drive_calibration(network, plans, drive, length, park_s, sim)
        # The recording ends 3 s after the vehicle has left the last traversal's route (or at duration_s).
        k_end = max(k_end if duration_s is not None else 0, legs[-1].motion.k_last + round(3.0 / DT_S))
        windows = tuple(
            (leg.motion.k0 * DT_S, leg.motion.k_last * DT_S) for leg in legs if leg.traversal is not None
        )
        k, s, v = _continue_from(legs[-1])
        tail = extension_path(
            legs[-1].path, max(50.0, (k_end - k + 50) * DT_S * drive.connector_speed_mps * 1.2)
        )
        legs.append(Leg(tail, _drive_free(tail, drive, length, k, s, v, 0.0, k_end + 1)))
    else:
        # Elsewhere: laps of a ring far from the site for the whole recording.
        ring = ring_path(
            network.ring_radius_m + 200.0,
            drive.connector_speed_mps * (k_end * DT_S + 10.0) * 1.2,
            start_angle=float(drive_rng.uniform(0.0, 2.0 * math.pi)),
        )
        legs = [
            Leg(ring, _drive_free(ring, drive, length, 0, 0.0, drive.connector_speed_mps, 0.0, k_end + 1))
        ]
        windows = ()
    sim.drive_entries(10**9)
    calibration = SimVehicle(
        0, CLASS_IDS[0], *vehicle_dims, legs=tuple(legs), route="calibration", is_calibration=True
    )
    return TrafficResult(calibration, tuple(sim.others), k_end * DT_S, windows)
