"""Pitch from the driven path when the vehicle reports none (ETSI CAMs carry no pitch or roll).

A body on a 6 % grade is pitched 3.4 deg: its front and rear ends sit 7 cm above and below a level body's
and its roof moves 9 cm along the road, which a level template turns into a camera pose decimetres off. The
path's own height profile gives the grade: per pose, a straight line of height against distance travelled
is fitted over the poses within `window_m` (GNSS height noise of a few cm averages out over metres), shrunk
towards level by its own standard error, and the pitch is the slope's angle (Rz Ry Rx convention:
positive pitch = nose down, so pitch = -atan(dz/ds)).

Roll stays 0. A road's cross slope (crown, camber: 2-3 %) turns the body by about 1.5 deg, which moves a
side of the template by about 2 cm at roof height: far below what the data can resolve, and a single path
cannot observe it anyway.
"""

from __future__ import annotations

import numpy as np

from pipeline.arrays import FloatArray
from pipeline.association import Trajectory

_PITCH, _ROLL = 4, 5


def reports_attitude(trajectory: Trajectory) -> bool:
    """True when any pose carries a pitch or roll (an IMU); CAM-derived poses have both exactly 0."""
    return bool(np.any(trajectory.poses[:, [_PITCH, _ROLL]] != 0.0))


def with_path_pitch(
    trajectory: Trajectory, window_m: float = 20.0, max_gap_ns: int = 1_500_000_000
) -> Trajectory:
    """The trajectory with pitch from the path's height profile (see the module); poses with an attitude
    of their own, or too few neighbours, keep theirs."""
    if reports_attitude(trajectory) or len(trajectory.stamps) < 3:
        return trajectory
    poses = trajectory.poses.copy()
    poses[:, _PITCH] = path_pitch(trajectory.stamps, poses[:, :3], window_m, max_gap_ns)
    return Trajectory(stamps=trajectory.stamps, poses=poses)


def path_pitch(stamps: np.ndarray, positions: FloatArray, window_m: float, max_gap_ns: int) -> FloatArray:
    """Pitch (rad) per pose (N,) from positions (N, 3): the local slope of height over distance travelled,
    within runs of poses no more than max_gap_ns apart (a dropout may hide a stop or a turn)."""
    pitch = np.zeros(len(stamps))
    breaks = np.flatnonzero(np.diff(stamps) > max_gap_ns) + 1
    for run in np.split(np.arange(len(stamps)), breaks):
        if len(run) < 3:
            continue
        xyz = positions[run]
        step = np.linalg.norm(np.diff(xyz[:, :2], axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(step)])
        z = xyz[:, 2]
        lo = np.searchsorted(s, s - window_m / 2.0, side="left")
        hi = np.searchsorted(s, s + window_m / 2.0, side="right")
        # Windowed least-squares slope from prefix sums: slope = cov(s, z) / var(s) over [lo, hi).
        cs = np.concatenate([[0.0], np.cumsum(s)])
        cz = np.concatenate([[0.0], np.cumsum(z)])
        css = np.concatenate([[0.0], np.cumsum(s * s)])
        csz = np.concatenate([[0.0], np.cumsum(s * z)])
        czz = np.concatenate([[0.0], np.cumsum(z * z)])
        n = (hi - lo).astype(np.float64)
        sum_s, sum_z = cs[hi] - cs[lo], cz[hi] - cz[lo]
        var = (css[hi] - css[lo]) - sum_s**2 / np.maximum(n, 1.0)
        cov = (csz[hi] - csz[lo]) - sum_s * sum_z / np.maximum(n, 1.0)
        var_z = (czz[hi] - czz[lo]) - sum_z**2 / np.maximum(n, 1.0)
        spread = s[np.minimum(hi, len(s)) - 1] - s[lo]
        ok = (n >= 3) & (spread >= window_m / 4.0) & (var > 0)
        safe_var = np.where(ok, var, 1.0)
        slope = np.where(ok, cov / safe_var, 0.0)
        # Height noise makes a slope out of a level road (7 cm of noise over 20 m: ~0.5 deg). The slope is
        # shrunk by slope^2 / (slope^2 + se^2), se its standard error from the line's residuals: a grade the
        # heights clearly show is kept, one within their noise fades to level.
        residual = np.maximum(var_z - slope * cov, 0.0) / np.maximum(n - 2.0, 1.0)
        se_squared = np.where(ok, residual / safe_var, np.inf)
        shrink = np.where(ok, slope**2 / np.maximum(slope**2 + se_squared, 1e-300), 0.0)
        pitch[run] = -np.arctan(slope * shrink)
    return pitch
