"""bench.oracle_fit's height noise: the statistics it claims (3 cm white; 6 cm wander over 60 s)."""

from __future__ import annotations

import math

import numpy as np

from bench.oracle_fit import height_errors


def test_white_height_noise_is_3_cm_and_uncorrelated():
    stamps = np.arange(200_000, dtype=np.int64) * 20_000_000  # 50 Hz
    errors = height_errors(stamps, "white", np.random.default_rng(0))
    assert abs(errors.std() - 0.03) < 0.001
    assert abs(np.corrcoef(errors[1:], errors[:-1])[0, 1]) < 0.01


def test_height_wander_is_6_cm_correlated_over_60_s():
    stamps = np.arange(0, 20 * 3600 * 10, dtype=np.int64) * 100_000_000  # 20 h at 10 Hz
    errors = height_errors(stamps, "wander", np.random.default_rng(1))
    assert abs(errors.std() - 0.06) < 0.006
    lag = 600  # 60 s
    assert abs(np.corrcoef(errors[lag:], errors[:-lag])[0, 1] - math.exp(-1.0)) < 0.08
    assert np.corrcoef(errors[1:], errors[:-1])[0, 1] > 0.99
