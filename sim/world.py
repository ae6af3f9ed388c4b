"""Simulated road world: ground surface, drivable paths, the junction's lanes and routes, static occluders.

Everything is in the local frame (UTM minus the scenario's LocalOrigin: x east, y north, z up, metres).
A road network is built from a few arms leaving the junction centre (straight or bending), each with
inbound and outbound lanes (right-hand traffic); a route joins an inbound lane's far end, through its
stop line and a turning arc, to an outbound lane's far end. The far connectors that carry the
calibration vehicle from one traversal to the next run on a ring well outside every camera's view.

The ground is the terrain (a plane plus Gaussian bumps) with the roads built into it (GroundSurface,
RoadSurface): each arm's carriageway is crowned, banked on its bend and follows its vertical curves; kerbs
step up to level footways and verges; the junction area is flattened and the arms blend into each other.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from sim.errors import SimulationError
from sim.geometry import FloatArray, IntArray
from sim.presets import GroundSpec, OccluderSpec, RoadSpec

# Spacing of the dense path samples (m): arcs of 6 m radius deviate < 2 mm from their chords.
PATH_STEP_M = 0.25
# Curves are driven at most this lateral acceleration (m/s^2), and slowed for at this deceleration.
LATERAL_ACCEL_MPS2 = 2.5
CURVE_DECEL_MPS2 = 2.0

# The 8 corners of a unit box: the base (rear-right, front-right, front-left, rear-left; x forward, y left)
# then the top, for the world's cuboids (occluders, and the vehicles of the `ideal` world).
UNIT_BOX_CORNERS = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.float64
)


# Crown and bank fade in over this length (m) past the junction's kerb returns: the arms' cross slopes
# run out into a nearly plane intersection (RASt 06 6.3: the junction area is profiled as one plane).
JUNCTION_RAMP_M = 15.0
# Neighbouring arms' surfaces blend where their centre lines are about equally near, over a band of
# this width (m) plus the distance from the nearer road: narrow beside the carriageways, wide far out.
ARM_BLEND_M = 10.0
# The modelled site ends this far (m) inside the nearest arm end, where the out-of-view far connectors
# leave the roads: kerbs ramp down over KERB_TAPER_M before it, so those drives stay on one surface.
SITE_END_MARGIN_M = 10.0
KERB_TAPER_M = 20.0
# Straight arms get this "bend start" (m): never reached, so one vectorised formula serves every arm.
_NO_BEND_M = 1.0e9

CARRIAGEWAY, FOOTWAY, VERGE = 0, 1, 2


@dataclass(frozen=True, eq=False)
class RoadSurface:
    """The roads' part of the ground (added to the terrain), from the arms' centre lines.

    Every arm's centre line runs from the junction centre along `yaw`, then (`bend_start` on) a
    circular arc of `bend_radius` turning `bend_angle` rad to the side `bend_sign` (+1 left), then straight
    on (extrapolated beyond the arm's end, as Path.at does). A point's station s (m along the arm) and
    offset d (m, left of the outward direction) on each arm give that arm's height: its vertical curves
    along s plus its cross section in d (crown, or bank on the bend), which is level beyond the edges.
    Arms blend across their bisectors; kerbs lift everything off the carriageway (the union of the arms'
    strips, its concave corners rounded by the kerb returns). Arrays are (A,) per arm; curves (C, 4) rows
    of arm index, start (m), length (m), grade change."""

    yaw: FloatArray
    bend_start: FloatArray
    bend_sign: FloatArray
    bend_radius: FloatArray
    bend_angle: FloatArray
    curves: FloatArray
    half_width_m: float
    crown_slope: float
    bank_slope: float
    bank_transition_m: float
    kerb_height_m: float
    footway_width_m: float
    kerb_return_radius_m: float
    junction_flat_m: float | None  # None: no junction (a plain road of two arms), nothing flattened
    kerb_end_m: float  # kerbs are gone this far (m) from the junction centre

    def arm_coordinates(self, xy: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(N, 2) local x, y -> station s and left offset d (A, N) in metres, on every arm's centre line."""
        x, y = xy[:, 0][None, :], xy[:, 1][None, :]
        cos_h, sin_h = np.cos(self.yaw)[:, None], np.sin(self.yaw)[:, None]
        sign = self.bend_sign[:, None]
        u = cos_h * x + sin_h * y
        v = sign * (cos_h * y - sin_h * x)  # mirrored for right bends: every bend turns left below
        b, rho, tau = self.bend_start[:, None], self.bend_radius[:, None], self.bend_angle[:, None]
        qx, qy = u - b, v - rho  # from the arc's centre (b, rho)
        theta = np.arctan2(qx, -qy)  # angle swept from the arc's start; <= 0 before the bend
        end_x, end_y = b + rho * np.sin(tau), rho * (1.0 - np.cos(tau))
        cos_t, sin_t = np.cos(tau), np.sin(tau)
        after_s = b + rho * tau + (u - end_x) * cos_t + (v - end_y) * sin_t
        after_d = (v - end_y) * cos_t - (u - end_x) * sin_t
        on_arc = theta < tau
        s = np.where(theta <= 0.0, u, np.where(on_arc, b + rho * theta, after_s))
        d = np.where(theta <= 0.0, v, np.where(on_arc, rho - np.hypot(qx, qy), after_d))
        return s, sign * d

    def _carriageway_distance(self, s: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Distance (A, N) to each arm's centre line (its start is the junction centre), and the signed
        distance (N,) to the carriageway's edge, approximately (exact along straight edges): <= 0 on it."""
        dist = np.where(s < 0.0, np.hypot(s, d), np.abs(d))
        edge = dist - self.half_width_m
        if len(edge) == 1:
            return dist, edge[0]
        nearest = np.partition(edge, 1, axis=0)
        a, b = nearest[0], nearest[1]
        # Round union of the two nearest strips (hg_sdf fOpUnionRound): a circular kerb return of radius R
        # where two arms' edges meet at a right angle, close to one at other angles.
        radius = self.kerb_return_radius_m
        inset = np.hypot(np.maximum(radius - a, 0.0), np.maximum(radius - b, 0.0))
        return dist, np.maximum(radius, np.minimum(a, b)) - inset

    def height(self, xy: FloatArray) -> FloatArray:
        """(N, 2) local x, y -> (N,) height (m) the roads add to the terrain."""
        s, d = self.arm_coordinates(xy)
        dist, edge = self._carriageway_distance(s, d)
        z_arm = np.zeros_like(s)
        for arm, start, length, grade_change in self.curves:
            # Parabolic vertical curve (RAS-L 5.2, AASHTO 3.4.6): the grade changes linearly over its length.
            along = np.clip(s[int(arm)] - start, 0.0, length)
            beyond = np.maximum(s[int(arm)] - start - length, 0.0)
            z_arm[int(arm)] += grade_change * (0.5 * along * along / length + beyond)
        offset = np.clip(d, -self.half_width_m, self.half_width_m)  # level beyond the edges
        transition = self.bank_transition_m
        bend_end = self.bend_start + self.bend_radius * self.bend_angle
        ramp_up = (s - (self.bend_start - 2.0 * transition / 3.0)[:, None]) / transition
        ramp_down = ((bend_end + 2.0 * transition / 3.0)[:, None] - s) / transition
        banked = np.clip(np.minimum(ramp_up, ramp_down), 0.0, 1.0)
        # Revolving the carriageway about its centre line: each side's cross slope changes linearly.
        cross = (1.0 - banked) * (-self.crown_slope * np.abs(offset)) - banked * (
            self.bank_slope * self.bend_sign[:, None] * offset
        )
        if self.junction_flat_m is not None:
            t = np.clip((s - self.junction_flat_m) / JUNCTION_RAMP_M, 0.0, 1.0)
            cross = cross * (t * t * (3.0 - 2.0 * t))
        z_arm += cross
        nearest = dist.min(axis=0)
        t = (dist - nearest) / (ARM_BLEND_M + nearest)
        weight = np.where(t < 1.0, 1.0 - t * t * (3.0 - 2.0 * t), 0.0)
        z = (weight * z_arm).sum(axis=0) / weight.sum(axis=0)
        kerb = np.clip((self.kerb_end_m - np.hypot(xy[:, 0], xy[:, 1])) / KERB_TAPER_M, 0.0, 1.0)
        return np.asarray(z + np.where(edge > 0.0, self.kerb_height_m * kerb, 0.0), dtype=np.float64)

    def surface_kind(self, xy: FloatArray) -> IntArray:
        """(N, 2) -> (N,) CARRIAGEWAY, FOOTWAY (the first footway_width_m behind the kerb) or VERGE."""
        s, d = self.arm_coordinates(xy)
        _, edge = self._carriageway_distance(s, d)
        kind = np.where(edge <= 0.0, CARRIAGEWAY, np.where(edge <= self.footway_width_m, FOOTWAY, VERGE))
        return np.asarray(kind, dtype=np.int64)

    @staticmethod
    def from_spec(spec: GroundSpec, road: RoadSpec) -> RoadSurface:
        """The road surface of `road`'s arms as `spec` describes it (checked: names, lengths, slopes)."""
        arm_index = {arm.name: i for i, arm in enumerate(road.arms)}
        for name in ("crown_slope", "kerb_height_m", "footway_width_m", "bank_slope", "kerb_return_radius_m"):
            value = getattr(spec, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise SimulationError(f"ground.{name}", f"{value} is not a finite value >= 0")
        if not (math.isfinite(spec.bank_transition_m) and spec.bank_transition_m > 0.0):
            raise SimulationError("ground.bank_transition_m", f"{spec.bank_transition_m} is not > 0")
        curves = []
        for i, curve in enumerate(spec.vertical_curves):
            where = f"ground.vertical_curves[{i}]"
            if curve.arm not in arm_index:
                raise SimulationError(where, f"arm = {curve.arm!r}; arms are {', '.join(arm_index)}")
            if not (math.isfinite(curve.start_m) and curve.start_m >= 0.0):
                raise SimulationError(where, f"start_m = {curve.start_m} is not >= 0")
            if not (math.isfinite(curve.length_m) and curve.length_m > 0.0):
                raise SimulationError(where, f"length_m = {curve.length_m} is not > 0")
            if not math.isfinite(curve.grade_change):
                raise SimulationError(where, f"grade_change = {curve.grade_change} is not finite")
            curves.append([arm_index[curve.arm], curve.start_m, curve.length_m, curve.grade_change])
        yaw, bend_start, bend_sign, bend_radius, bend_angle = [], [], [], [], []
        for arm in road.arms:
            yaw.append(math.radians(arm.angle_deg))
            # The same bend as _arm_centreline draws: its arc clipped to the arm's length.
            is_bent = arm.bend_deg != 0.0 and arm.bend_start_m < road.arm_length_m
            arc_m = min(
                abs(math.radians(arm.bend_deg)) * arm.bend_radius_m, road.arm_length_m - arm.bend_start_m
            )
            bend_start.append(arm.bend_start_m if is_bent else _NO_BEND_M)
            bend_sign.append(math.copysign(1.0, arm.bend_deg) if is_bent else 1.0)
            bend_radius.append(arm.bend_radius_m if is_bent else 1.0)
            bend_angle.append(arc_m / arm.bend_radius_m if is_bent else 0.0)
        half_width = road.lanes_per_direction * road.lane_width_m
        junction_flat_m = None
        if len(road.arms) >= 3:
            # Kerb returns meet the arms' edges (w + R) / tan(phi / 2) from the centre, phi the angle
            # between neighbouring arms: the junction area reaches that far along the sharpest corner.
            angles = np.sort(np.mod(np.array(yaw), 2.0 * math.pi))
            gaps = np.diff(np.append(angles, angles[0] + 2.0 * math.pi))
            sharpest = float(gaps.min())
            junction_flat_m = (half_width + spec.kerb_return_radius_m) / math.tan(0.5 * sharpest)
        arm_ends = [
            float(
                np.hypot(
                    *_arm_centreline(
                        a.angle_deg, road.arm_length_m, a.bend_start_m, a.bend_deg, a.bend_radius_m
                    ).xy[-1]
                )
            )
            for a in road.arms
        ]
        return RoadSurface(
            yaw=np.array(yaw),
            bend_start=np.array(bend_start),
            bend_sign=np.array(bend_sign),
            bend_radius=np.array(bend_radius),
            bend_angle=np.array(bend_angle),
            curves=np.array(curves, dtype=np.float64).reshape(-1, 4),
            half_width_m=half_width,
            crown_slope=spec.crown_slope,
            bank_slope=spec.bank_slope,
            bank_transition_m=spec.bank_transition_m,
            kerb_height_m=spec.kerb_height_m,
            footway_width_m=spec.footway_width_m,
            kerb_return_radius_m=spec.kerb_return_radius_m,
            junction_flat_m=junction_flat_m,
            kerb_end_m=min(arm_ends) - SITE_END_MARGIN_M,
        )


@dataclass(frozen=True, eq=False)
class GroundSurface:
    """Ground z(x, y) = slope . (x, y) + sum of Gaussian bumps (the terrain) + the roads built into it
    (`road`; None: the terrain alone, the `ideal` world). Local frame, metres."""

    slope: FloatArray  # (2,) dz/dx, dz/dy
    bumps: FloatArray  # (K, 4) x, y, height, sigma
    road: RoadSurface | None = None

    @staticmethod
    def from_spec(spec: GroundSpec, network: RoadNetwork) -> GroundSurface:
        """The ground of `spec` with `network`'s roads built in (none when `spec.is_flat`)."""
        bumps = np.array([[b.x_m, b.y_m, b.height_m, b.sigma_m] for b in spec.bumps], dtype=np.float64)
        road = None if spec.is_flat else RoadSurface.from_spec(spec, network.road)
        return GroundSurface(np.array(spec.slope, dtype=np.float64), bumps.reshape(-1, 4), road)

    def height(self, xy: FloatArray) -> FloatArray:
        """(N, 2) -> (N,) ground height in metres."""
        z = xy @ self.slope
        for x0, y0, amplitude, sigma in self.bumps:
            d2 = (xy[:, 0] - x0) ** 2 + (xy[:, 1] - y0) ** 2
            z = z + amplitude * np.exp(-0.5 * d2 / (sigma * sigma))
        if self.road is not None:
            z = z + self.road.height(xy)
        return np.asarray(z, dtype=np.float64)

    def surface_kind(self, xy: FloatArray) -> IntArray:
        """(N, 2) -> (N,) CARRIAGEWAY, FOOTWAY or VERGE (all CARRIAGEWAY on the terrain alone)."""
        if self.road is None:
            return np.zeros(len(xy), dtype=np.int64)
        return self.road.surface_kind(xy)


@dataclass(frozen=True, eq=False)
class Occluder:
    """A static obstacle (pole, tree trunk or crown, sign) as a cuboid: corners (8, 3) in the local frame,
    footprint first (same order as vehicle.body_corners). Occluders hide vehicles but are never detected."""

    kind: str
    corners: FloatArray


@dataclass(frozen=True, eq=False)
class WorldGeometry:
    """What the preview and the tests need of the world: lane centre lines, occluders and the ground."""

    lanes: tuple[FloatArray, ...]  # each (K, 3) lane centre polyline, local frame
    occluders: tuple[Occluder, ...]
    ground: GroundSurface

    def ground_height(self, xy: FloatArray) -> FloatArray:
        """(N, 2) local x, y -> (N,) z of the road surface (m)."""
        return self.ground.height(xy)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def _left_normal(yaw: FloatArray) -> FloatArray:
    return np.stack([-np.sin(yaw), np.cos(yaw)], axis=-1)


@dataclass(frozen=True, eq=False)
class Path:
    """A drivable centre line resampled every PATH_STEP_M: arc length s (M,), xy (M, 2), yaw (M,) in
    radians (unwrapped, grid east = 0, counter-clockwise). Positions beyond either end extrapolate along
    the end yaw, so vehicles may enter before or leave after the sampled part without a jump."""

    s: FloatArray
    xy: FloatArray
    yaw: FloatArray

    @staticmethod
    def from_samples(xy: FloatArray, yaw: FloatArray) -> Path:
        """Resample an ordered polyline with tangent yaws to uniform arc-length spacing."""
        step = np.hypot(*np.diff(xy, axis=0).T)
        keep = np.concatenate([[True], step > 1e-9])
        xy, yaw = xy[keep], np.unwrap(yaw[keep])
        s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
        n = max(2, math.ceil(s[-1] / PATH_STEP_M) + 1)
        s_new = np.linspace(0.0, s[-1], n)
        xy_new = np.stack([np.interp(s_new, s, xy[:, 0]), np.interp(s_new, s, xy[:, 1])], axis=1)
        return Path(s_new, xy_new, np.interp(s_new, s, yaw))

    @staticmethod
    def join(parts: list[Path]) -> Path:
        """Concatenate paths whose ends meet (within a few cm); yaws are made continuous."""
        xy = [parts[0].xy]
        yaw = [parts[0].yaw]
        for part in parts[1:]:
            turn = yaw[-1][-1] - part.yaw[0]
            offset = 2.0 * math.pi * round(turn / (2.0 * math.pi))
            xy.append(part.xy[1:])
            yaw.append(part.yaw[1:] + offset)
        return Path.from_samples(np.concatenate(xy), np.concatenate(yaw))

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def at(self, s_query: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Position (N, 2) and yaw (N,) at arc lengths (N,); linear extrapolation beyond the ends."""
        s_clamped = np.clip(s_query, 0.0, self.length)
        xy = np.stack(
            [np.interp(s_clamped, self.s, self.xy[:, 0]), np.interp(s_clamped, self.s, self.xy[:, 1])], axis=1
        )
        yaw = np.interp(s_clamped, self.s, self.yaw)
        beyond = s_query - s_clamped
        if np.any(beyond != 0.0):
            xy = xy + beyond[:, None] * np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
        return xy, yaw

    def towed_yaw_at(self, s_query: FloatArray, lag_m: float) -> FloatArray:
        """Yaw (N,) at arc lengths (N,) of a rigid body whose point on this path (its footprint centre) is
        `lag_m` ahead of the point that moves along the body's axis: its rear axle, for wheels roll and do
        not slide sideways. See `_towed_yaw`; beyond the ends, the end values."""
        return np.asarray(np.interp(s_query, self.s, _towed_yaw(self, lag_m)), dtype=np.float64)

    def offset(self, lateral_m: float) -> Path:
        """Parallel path `lateral_m` to the left (negative: right) of this one."""
        return Path.from_samples(self.xy + lateral_m * _left_normal(self.yaw), self.yaw)

    def reversed(self) -> Path:
        return Path.from_samples(self.xy[::-1].copy(), self.yaw[::-1] + math.pi)

    def slice(self, s_from: float, s_to: float) -> Path:
        """The part between two arc lengths (clamped to the path)."""
        inner = (self.s > s_from) & (self.s < s_to)
        ends = np.array([max(s_from, 0.0), min(s_to, self.length)])
        xy_ends, yaw_ends = self.at(ends)
        xy = np.concatenate([xy_ends[:1], self.xy[inner], xy_ends[1:]])
        yaw = np.concatenate([yaw_ends[:1], self.yaw[inner], yaw_ends[1:]])
        return Path.from_samples(xy, yaw)

    def end_pose(self) -> tuple[FloatArray, float]:
        return self.xy[-1].copy(), float(self.yaw[-1])

    def start_pose(self) -> tuple[FloatArray, float]:
        return self.xy[0].copy(), float(self.yaw[0])

    def curve_speed_limit(self) -> FloatArray:
        """Comfortable speed (m/s) at every sample: lateral acceleration <= LATERAL_ACCEL_MPS2 in curves,
        reached by braking at CURVE_DECEL_MPS2 beforehand (a backward pass in v^2, vectorised as a
        running minimum), so a driver model following it slows down before a turn, not in it."""
        curvature = np.abs(np.gradient(self.yaw, self.s)) if len(self.s) > 2 else np.zeros(len(self.s))
        # Smooth over ~3 m: the sampled yaw of offset polylines is slightly noisy at joints.
        width = max(1, round(3.0 / PATH_STEP_M))
        curvature = np.convolve(curvature, np.ones(width) / width, mode="same")
        v2_limit = LATERAL_ACCEL_MPS2 / np.maximum(curvature, 1e-6)
        budget = 2.0 * CURVE_DECEL_MPS2 * self.s
        # w[i] = min_{j >= i} (limit[j] + budget[j] - budget[i]): reversed running minimum.
        v2 = np.minimum.accumulate((v2_limit + budget)[::-1])[::-1] - budget
        return np.asarray(np.sqrt(np.maximum(v2, 0.0)), dtype=np.float64)


@functools.lru_cache(maxsize=2048)
def _towed_yaw(path: Path, lag_m: float) -> FloatArray:
    """The towed body's yaw (M,) at the path's samples (Path.towed_yaw_at). The rear axle at distance a =
    `lag_m` behind the path point c moves along the body's heading psi: its sideways speed, that of c less
    a psi', is 0, so a dpsi/ds = sin(yaw_path - psi), with psi = the path's yaw at s = 0 (a straight
    start). In a steady turn of radius R the body lags the tangent by asin(a / R) (5.7 deg for a = 1.5 m,
    R = 15 m: the footprint centre of a turning car moves at that angle to its axis), on a straight it
    settles back within a few a. Solved on the uniform arc-length grid by the exact discrete low-pass of
    the linear part (a psi' + psi = yaw_path, trapezoid input), iterated on the small remainder
    x - sin x (x = yaw_path - psi) until a round moves the yaw by less than 1e-12 rad, 8 rounds at most
    (measured on a 180 deg arc: 6 rounds for a / R = 0.12; at a / R = 0.5 the 8th still moves it 2e-8 rad)."""
    if not lag_m > 0.0:
        raise SimulationError("rear_axle_m", f"must lie behind the body's centre (lag {lag_m} m)")
    yaw = path.yaw  # Path.from_samples: at least 2 samples, uniformly spaced
    alpha = 1.0 - math.exp(-float(path.s[1] - path.s[0]) / lag_m)
    b, a = [alpha / 2.0, alpha / 2.0], [1.0, alpha - 1.0]
    psi = yaw.copy()
    for _ in range(8):
        # The linear part's input with the remainder moved over: yaw - (x - sin x) = psi + sin x.
        updated = yaw[0] + lfilter(b, a, psi + np.sin(yaw - psi) - yaw[0])
        settled = float(np.max(np.abs(updated - psi))) < 1e-12
        psi = updated
        if settled:
            break
    return np.asarray(psi, dtype=np.float64)


def straight_samples(start: FloatArray, yaw: float, length: float) -> tuple[FloatArray, FloatArray]:
    n = max(2, math.ceil(length / PATH_STEP_M) + 1)
    d = np.linspace(0.0, length, n)
    xy = start + d[:, None] * np.array([math.cos(yaw), math.sin(yaw)])
    return xy, np.full(n, yaw)


def arc_samples(start: FloatArray, yaw: float, radius: float, turn: float) -> tuple[FloatArray, FloatArray]:
    """Circular arc from `start` (tangent `yaw`) turning `turn` rad (positive = left) on `radius` m."""
    sign = 1.0 if turn >= 0 else -1.0
    centre = start + sign * radius * _left_normal(np.array(yaw))
    n = max(2, math.ceil(abs(turn) * radius / PATH_STEP_M) + 1)
    yaws = yaw + np.linspace(0.0, turn, n)
    xy = centre - sign * radius * _left_normal(yaws)
    return xy, yaws


def bezier_samples(p0: FloatArray, h0: float, p1: FloatArray, h1: float) -> tuple[FloatArray, FloatArray]:
    """Cubic Bezier from pose (p0, h0) to (p1, h1); handle lengths follow the circular-arc rule so a
    symmetric turn comes out almost circular."""
    chord = float(np.hypot(*(p1 - p0)))
    turn = abs(_wrap(h1 - h0))
    handle = (
        chord / 3.0
        if turn < 1e-3
        else (4.0 / 3.0) * math.tan(turn / 4.0) * chord / (2.0 * math.sin(turn / 2.0))
    )
    c0 = p0 + handle * np.array([math.cos(h0), math.sin(h0)])
    c1 = p1 - handle * np.array([math.cos(h1), math.sin(h1)])
    n = max(8, math.ceil(1.5 * chord / PATH_STEP_M))
    u = np.linspace(0.0, 1.0, n)[:, None]
    xy = (1 - u) ** 3 * p0 + 3 * (1 - u) ** 2 * u * c0 + 3 * (1 - u) * u**2 * c1 + u**3 * p1
    d = 3 * (1 - u) ** 2 * (c0 - p0) + 6 * (1 - u) * u * (c1 - c0) + 3 * u**2 * (p1 - c1)
    return xy, np.unwrap(np.arctan2(d[:, 1], d[:, 0]))


def fillet_path(p0: FloatArray, h0: float, p1: FloatArray, h1: float) -> Path:
    """Junction connector from a stop line pose to an outbound lane start: straight, circular arc,
    straight (a turning lane as drawn on real junctions); a Bezier where no such arc fits."""
    d0 = np.array([math.cos(h0), math.sin(h0)])
    d1 = np.array([math.cos(h1), math.sin(h1)])
    cross = d0[0] * d1[1] - d0[1] * d1[0]
    delta = p1 - p0
    if abs(cross) < 1e-6:
        lateral = d0[0] * delta[1] - d0[1] * delta[0]
        if abs(lateral) < 0.05 and float(delta @ d0) > 0:
            return Path.from_samples(*straight_samples(p0, h0, float(np.hypot(*delta))))
        return Path.from_samples(*bezier_samples(p0, h0, p1, h1))
    along0, along1 = np.linalg.solve(np.column_stack([d0, d1]), delta)  # p0 + a0 d0 = p1 - a1 d1
    if along0 <= 0.5 or along1 <= 0.5:
        return Path.from_samples(*bezier_samples(p0, h0, p1, h1))
    tangent = min(along0, along1)
    turn = _wrap(h1 - h0)
    radius = tangent / math.tan(abs(turn) / 2.0)
    pieces = []
    if along0 - tangent > 1e-6:
        pieces.append(straight_samples(p0, h0, along0 - tangent))
    arc_start = p0 + (along0 - tangent) * d0
    pieces.append(arc_samples(arc_start, h0, radius, turn))
    if along1 - tangent > 1e-6:
        pieces.append(straight_samples(p1 - (along1 - tangent) * d1, h1, along1 - tangent))
    return Path.join([Path.from_samples(*piece) for piece in pieces])


@dataclass(frozen=True, eq=False)
class Route:
    """One way through the junction: inbound lane (entry_arm, entry_lane) -> outbound (exit_arm, exit_lane).

    `stop_s` is the arc length of the stop line; vehicles entering the same inbound lane share the path
    up to it (and whole routes are shared by vehicles on the same route)."""

    name: str  # e.g. "W>E" (arm names), lanes in entry_lane / exit_lane
    entry_arm: str
    entry_lane: int
    exit_arm: str
    exit_lane: int
    turn: str  # "straight", "left" or "right"
    path: Path
    stop_s: float
    speed_limit: FloatArray  # curve_speed_limit() of path, sampled at path.s

    @property
    def lane_key(self) -> tuple[str, int]:
        return (self.entry_arm, self.entry_lane)


@dataclass(frozen=True, eq=False)
class RoadNetwork:
    """Arms, lanes and all routes of the junction, plus the radius of the far ring used by connectors."""

    arm_names: tuple[str, ...]
    inbound: dict[tuple[str, int], Path]
    outbound: dict[tuple[str, int], Path]
    routes: dict[tuple[str, int, str, int], Route]
    ring_radius_m: float
    lanes_per_direction: int
    road: RoadSpec  # the layout it was built from (the ground builds the roads' surface from its arms)

    def route(self, name: str) -> Route:
        """The route called "A>B" (arm names): right lane for straight and right turns, inner for left."""
        try:
            entry, exit_ = name.split(">")
        except ValueError as err:
            raise SimulationError("route", f"route = {name!r} is not of the form 'A>B'") from err
        outer = self.lanes_per_direction - 1
        for lane in range(self.lanes_per_direction):
            candidate = self.routes.get((entry, lane, exit_, lane))
            if candidate is None:
                continue
            wanted = 0 if candidate.turn == "left" else outer
            if lane == wanted:
                return candidate
        raise SimulationError(
            "route", f"route = {name!r}: no such route; arms are {', '.join(self.arm_names)}"
        )


def _arm_centreline(
    angle_deg: float, length_m: float, bend_start_m: float, bend_deg: float, bend_radius_m: float
) -> Path:
    yaw = math.radians(angle_deg)
    origin = np.zeros(2)
    if bend_deg == 0.0 or bend_start_m >= length_m:
        return Path.from_samples(*straight_samples(origin, yaw, length_m))
    turn = math.radians(bend_deg)
    arc_length = min(abs(turn) * bend_radius_m, length_m - bend_start_m)
    turn = math.copysign(arc_length / bend_radius_m, turn)
    pieces = [Path.from_samples(*straight_samples(origin, yaw, bend_start_m))] if bend_start_m > 0 else []
    start = np.array([math.cos(yaw), math.sin(yaw)]) * bend_start_m
    pieces.append(Path.from_samples(*arc_samples(start, yaw, bend_radius_m, turn)))
    rest = length_m - bend_start_m - arc_length
    if rest > 1e-6:
        end, end_yaw = pieces[-1].end_pose()
        pieces.append(Path.from_samples(*straight_samples(end, end_yaw, rest)))
    return Path.join(pieces)


def _turn_kind(h_in: float, h_out: float) -> str:
    turn = _wrap(h_out - h_in)
    if abs(turn) < math.radians(35.0):
        return "straight"
    return "left" if turn > 0 else "right"


def build_network(road: RoadSpec) -> RoadNetwork:
    """Lanes and routes of a junction with `road.arms` (2 arms: a plain road; right-hand traffic)."""
    width = road.lane_width_m
    lanes = road.lanes_per_direction
    stop_m = lanes * width + road.stop_line_margin_m  # crossing road half-width + crosswalk
    inbound: dict[tuple[str, int], Path] = {}
    outbound: dict[tuple[str, int], Path] = {}
    for arm in road.arms:
        centre = _arm_centreline(
            arm.angle_deg, road.arm_length_m, arm.bend_start_m, arm.bend_deg, arm.bend_radius_m
        ).slice(stop_m, road.arm_length_m)
        for lane in range(lanes):
            # Right-hand traffic: outbound lanes lie right of the outward direction, inbound ones left.
            outbound[(arm.name, lane)] = centre.offset(-(lane + 0.5) * width)
            inbound[(arm.name, lane)] = centre.offset((lane + 0.5) * width).reversed()
    routes: dict[tuple[str, int, str, int], Route] = {}
    for a in road.arms:
        for b in road.arms:
            if a.name == b.name:
                continue
            for lane in range(lanes):
                lane_in, lane_out = inbound[(a.name, lane)], outbound[(b.name, lane)]
                p0, h0 = lane_in.end_pose()
                p1, h1 = lane_out.start_pose()
                turn = _turn_kind(h0, h1)
                # Left turns only from the inner lane, right turns only from the outer one.
                if (turn == "left" and lane != 0) or (turn == "right" and lane != lanes - 1):
                    continue
                path = Path.join([lane_in, fillet_path(p0, h0, p1, h1), lane_out])
                routes[(a.name, lane, b.name, lane)] = Route(
                    f"{a.name}>{b.name}",
                    a.name,
                    lane,
                    b.name,
                    lane,
                    turn,
                    path,
                    lane_in.length,
                    path.curve_speed_limit(),
                )
    far = max(float(np.hypot(*p.xy[-1])) for p in outbound.values())
    return RoadNetwork(
        tuple(a.name for a in road.arms),
        inbound,
        outbound,
        routes,
        far + road.connector_clearance_m,
        lanes,
        road,
    )


def far_connector(exit_path: Path, entry_path: Path, ring_radius_m: float) -> Path:
    """Path from the far end of one route to the far start of the next, around a ring of radius
    `ring_radius_m` about the junction (so the calibration vehicle is out of every camera's view between
    traversals while its poses stay physically continuous)."""
    p0, h0 = exit_path.end_pose()
    p1, h1 = entry_path.start_pose()
    theta0 = math.atan2(p0[1], p0[0])
    theta1 = math.atan2(p1[1], p1[0])
    sweep = (theta1 - theta0) % (2.0 * math.pi)
    if sweep > math.pi + 1e-6:
        sweep -= 2.0 * math.pi  # go the shorter way round (clockwise)
    steps = max(2, math.ceil(abs(sweep) / math.radians(30.0)) + 1)
    direction = 1.0 if sweep >= 0 else -1.0
    poses = [(p0, h0)]
    # Skip the ring points right at the ends: the ramps onto and off the ring need room to turn.
    for angle in np.linspace(theta0, theta0 + sweep, steps + 1)[1:-1]:
        point = ring_radius_m * np.array([math.cos(angle), math.sin(angle)])
        poses.append((point, float(angle + direction * math.pi / 2.0)))
    if len(poses) == 1:  # sweep too small for a ring point: loop out and back
        mid = 0.5 * (theta0 + theta1)
        poses.append((ring_radius_m * np.array([math.cos(mid), math.sin(mid)]), mid + math.pi / 2.0))
    poses.append((p1, h1))
    parts = [
        Path.from_samples(*bezier_samples(a, ha, b, hb)) for (a, ha), (b, hb) in itertools.pairwise(poses)
    ]
    return Path.join(parts)


def ring_path(radius_m: float, length_m: float, start_angle: float = 0.0) -> Path:
    """Counter-clockwise circle (repeated laps) of the given length: a drive far away from the site."""
    start = radius_m * np.array([math.cos(start_angle), math.sin(start_angle)])
    return Path.from_samples(*arc_samples(start, start_angle + math.pi / 2.0, radius_m, length_m / radius_m))


def extension_path(path: Path, length_m: float) -> Path:
    """Straight continuation of a path's end (the calibration vehicle driving away after its last pass)."""
    p, h = path.end_pose()
    return Path.from_samples(*straight_samples(p, h, length_m))


def build_occluders(specs: tuple[OccluderSpec, ...], ground: GroundSurface) -> tuple[Occluder, ...]:
    """Cuboids standing on the ground (their base `base_height_m` above it: a tree crown on its trunk)."""
    occluders = []
    for spec in specs:
        base_z = float(ground.height(np.array([[spec.x_m, spec.y_m]]))[0]) + spec.base_height_m
        yaw = math.radians(spec.yaw_deg)
        rot = np.array(
            [[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0, 0, 1.0]]
        )
        local = (UNIT_BOX_CORNERS - np.array([0.5, 0.5, 0.0])) * np.array(
            [spec.length_m, spec.width_m, spec.height_m]
        )
        corners = local @ rot.T + np.array([spec.x_m, spec.y_m, base_z])
        occluders.append(Occluder(spec.kind, corners))
    return tuple(occluders)


def lane_polylines(
    network: RoadNetwork, ground: GroundSurface, step_m: float = 1.0
) -> tuple[FloatArray, ...]:
    """Lane centre lines as (K, 3) polylines: every inbound and outbound lane, then every turning lane
    (the junction part of each route)."""
    polylines = []
    stride = max(1, round(step_m / PATH_STEP_M))

    def lift(xy: FloatArray) -> FloatArray:
        return np.column_stack([xy, ground.height(xy)])

    for path in [*network.inbound.values(), *network.outbound.values()]:
        polylines.append(lift(np.vstack([path.xy[::stride], path.xy[-1:]])))
    for route in network.routes.values():
        lane_in = network.inbound[route.lane_key]
        lane_out = network.outbound[(route.exit_arm, route.exit_lane)]
        inner = route.path.slice(lane_in.length, route.path.length - lane_out.length)
        polylines.append(lift(np.vstack([inner.xy[::stride], inner.xy[-1:]])))
    return tuple(polylines)
