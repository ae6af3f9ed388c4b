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
    powers = weight[:, :, None] * dt[:, :, None] ** np.arange(5)  # (R, K, 5): w dt^m
    moments = powers.sum(axis=1)  # (R, 5)
    normal = moments[:, np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4]])]  # (R, 3, 3)
    poses = trajectory.poses.copy()
    values = poses.copy()
    values[:, _YAW] = np.unwrap(values[:, _YAW])
    right = np.einsum("rkm,rkc->rmc", powers[:, :, :3], values[neighbours])  # (R, 3, 6)
    solvable = np.abs(np.linalg.det(normal)) > 1e-12 * np.maximum(moments[:, 0], 1.0) ** 3
    rows, normal, right = rows[solvable], normal[solvable], right[solvable]
    fitted: FloatArray = np.linalg.solve(normal, right)[:, 0, :]  # (R, 6): the fit's value at dt = 0
    poses[rows] = fitted
    poses[:, _YAW] = wrap_angle(poses[:, _YAW])
    return Trajectory(stamps=trajectory.stamps, poses=poses)
