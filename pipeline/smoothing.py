"""High-rate vehicle poses smoothed before the method samples them between their stamps.

The final fit reads the vehicle's pose at each box's time minus the clock's shift, interpolating linearly
between reported poses. An IMU/INS reports at 50-100 Hz, a camera frames at 10-30 Hz, and the two rates are
commensurate: every box then falls at the same phase between two poses. With independent noise on each
pose, the interpolated noise depends on that phase (one pose's noise at phase 0, the mean of two at phase
1/2), so the fit's cost ripples with the pose interval and every shift of the clock by a pose interval is a
local minimum. Measured (the first simulator's sil-north seed 0, 50 Hz poses with 7.5 cm of noise each, a
400 ms latency): the clock settled 5-31 ms from where each pass started, 18.5 ms apart, at a reported std
of 0.6 ms; without the poses' noise the same scene gave -395 ms from every start, at a std of 9 ms.

So each coordinate is replaced by a local quadratic fit (tricube weights) over the poses within
`half_window_s`: a vehicle's path over 0.3 s is a quadratic to well below a millimetre (a 20 m radius at
12 m/s: 0.05 mm), the poses' noise is averaged over a dozen of them, and the phase no longer matters. Poses
with fewer than `min_samples` neighbours in the window (CAMs at 1-10 Hz, the ends of gaps) are kept as
reported: there is nothing to average there, and too few to fit a curve.
"""

from __future__ import annotations

import numpy as np

from pipeline.arrays import FloatArray
from pipeline.association import Trajectory, wrap_angle

_YAW = 3


def smoothed(trajectory: Trajectory, half_window_s: float = 0.15, min_samples: int = 7) -> Trajectory:
    """The trajectory with every pose that has at least `min_samples` poses (itself included) within
    `half_window_s` replaced by the local quadratic fit's value there (see the module); yaw is unwrapped for
    the fit and wrapped back."""
    count = len(trajectory.stamps)
    if count < min_samples:
        return trajectory
    t = (trajectory.stamps - trajectory.stamps[0]).astype(np.float64) / 1e9
    lo = np.searchsorted(t, t - half_window_s, side="left")
    hi = np.searchsorted(t, t + half_window_s, side="right")
    rows = np.flatnonzero(hi - lo >= min_samples)
    if len(rows) == 0:
        return trajectory
    reach = int(max(np.max(rows - lo[rows]), np.max(hi[rows] - 1 - rows)))
    neighbours = rows[:, None] + np.arange(-reach, reach + 1)  # (R, 2 * reach + 1)
    inside = (neighbours >= lo[rows, None]) & (neighbours < hi[rows, None])
    neighbours = np.clip(neighbours, 0, count - 1)
    dt = (t[neighbours] - t[rows, None]) / half_window_s  # in [-1, 1] inside the window
    weight = np.where(inside, (1.0 - np.minimum(np.abs(dt), 1.0) ** 3) ** 3, 0.0)
    powers = [weight, weight * dt, weight * dt * dt]
    s0, s1, s2 = (p.sum(axis=1) for p in powers)
    s3, s4 = (powers[2] * dt).sum(axis=1), (powers[2] * dt * dt).sum(axis=1)
    # The fit's value at dt = 0 is the first row of the inverse of the normal matrix [[s0, s1, s2], [s1, s2,
    # s3], [s2, s3, s4]] times the weighted sums of y, y dt, y dt^2: that row by cofactors.
    c0, c1, c2 = s2 * s4 - s3 * s3, s2 * s3 - s1 * s4, s1 * s3 - s2 * s2
    det = s0 * c0 + s1 * c1 + s2 * c2
    solvable = np.abs(det) > 1e-9 * np.maximum(s0, 1.0) ** 3
    poses = trajectory.poses.copy()
    values = poses.copy()
    values[:, _YAW] = np.unwrap(values[:, _YAW])
    sums = np.einsum("rkm,rkc->rmc", np.stack(powers, axis=2), values[neighbours])  # (R, 3, 6)
    row = np.stack([c0, c1, c2], axis=1) / np.where(solvable, det, 1.0)[:, None]
    fitted: FloatArray = np.einsum("rm,rmc->rc", row, sums)
    poses[rows[solvable]] = fitted[solvable]
    poses[:, _YAW] = wrap_angle(poses[:, _YAW])
    return Trajectory(stamps=trajectory.stamps, poses=poses)
