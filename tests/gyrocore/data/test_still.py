"""The one still gate (gyrocore.data.still): known spans recovered, chunked == in memory, and the
false-motion rate on pure white noise against the theory of its threshold."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats

from gyrocore.data.recording import Recording, read_csv, write_csv
from gyrocore.data.spill import spill_columns
from gyrocore.data.still import StillGate, robust_diff_noise, runs, still_windows
from gyrocore.errors import GyroInputError

RATE_HZ = 100.0
SIGMA = 0.02  # rad/s per sample (N = 2e-3 rad/s/√Hz at 100 Hz)


def _binom_interval(W: int, p: float, z: float = 4.0) -> tuple[float, float]:
    """Count of Bernoulli(p) successes in W trials: mean ± z standard deviations (normal
    approximation; z = 4 is two-sided 6e-5)."""
    mu, sd = W * p, math.sqrt(W * p * (1 - p))
    return mu - z * sd, mu + z * sd


def _session(seed: int):
    """100 s at 100 Hz: still, a hand turn (sine, 20 deg/s), still, a slow ramp to 30 deg/s and
    back, still. Returns the gyro (N, 3) and the true still spans in samples."""
    rng = np.random.default_rng(seed)
    n = int(100 * RATE_HZ)
    t = np.arange(n) / RATE_HZ
    g = np.array([0.01, -0.02, 0.005]) + SIGMA * rng.standard_normal((n, 3))
    turn = (t >= 30.3) & (t < 40.7)
    g[turn, 0] += np.deg2rad(20.0) * np.sin(2 * np.pi * 0.5 * (t[turn] - 30.3))
    ramp = (t >= 70.45) & (t < 75.55)
    g[ramp, 2] += np.deg2rad(30.0) * np.sin(np.pi * (t[ramp] - 70.45) / 5.1)
    still = [(0, 3030), (4070, 7045), (7555, n)]
    return g, still


def test_known_still_spans_are_recovered_within_one_window():
    """Windows of 1 s (n = 100): each true still span is found as one run of still windows whose
    ends lie within one window of the true ends (a window that holds any motion is refused; the
    windows wholly inside a span pass). α = 1e-4 per window: P(a false reject among the ~90 still
    windows) = 1 − (1 − 1e-4)^90 ≈ 0.9 %, whatever the seed."""
    g, truth = _session(seed=20261128)
    sw = still_windows(g, RATE_HZ, StillGate(window_s=1.0, false_reject_rate=1e-4))
    n = sw.window_samples
    found = [(a * n, b * n) for a, b in runs(sw.still)]
    assert len(found) == len(truth), found
    N = g.shape[0]
    for (fa, fb), (ta, tb) in zip(found, truth):
        assert ta <= fa < ta + n and (tb - n < fb <= tb or (tb == N and fb == (N // n) * n)), (fa, fb, ta, tb)
    mask = sw.sample_mask()
    assert mask.shape == (N,) and mask.sum() == sw.still.sum() * n


def test_constant_rotation_needs_the_mean_test():
    """A constant 5 deg/s turn adds no window variance: only the mean test refuses it."""
    rng = np.random.default_rng(3)
    g = SIGMA * rng.standard_normal((6000, 3))
    g[2000:3000, 1] += np.deg2rad(5.0)
    plain = still_windows(g, RATE_HZ, StillGate(window_s=1.0))
    turn = np.arange(20, 30)
    assert plain.still[turn].all()  # variance blind to it (the windows at its ends aside)
    with_mean = still_windows(g, RATE_HZ, StillGate(window_s=1.0, mean_tolerance_rad_s=np.deg2rad(0.5)))
    assert not with_mean.still[turn].any() and with_mean.still[:20].all() and with_mean.still[30:].all()


def test_chunked_equals_in_memory_exactly(tmp_path):
    """A record on disk (a ColumnSpill, blocks of a few windows) and the same record in memory
    (one block) give bit-identical statistics, noise and verdicts."""
    g, _ = _session(seed=7)
    path = tmp_path / "r.csv"
    write_csv(Recording(t_s=np.arange(g.shape[0]) / RATE_HZ, gyro_rad_s=g), path)
    rec = read_csv(path, columns=())
    store = spill_columns(path, tmp_path / "spill")
    for gate in (StillGate(window_s=1.0), StillGate(window_s=0.5, statistic="abs_diff"), StillGate(window_s=2.0)):
        mem = still_windows(rec.gyro_rad_s, RATE_HZ, gate)
        for block_bytes in (7 * 100 * 3 * 8, 1):  # 7 windows per block; one window per block
            disk = still_windows(store, RATE_HZ, gate, block_bytes=block_bytes)
            for f in ("still", "statistic", "threshold", "sigma2", "dof", "sigma_diff_rad_s", "diff_corr", "means"):
                np.testing.assert_array_equal(getattr(disk, f), getattr(mem, f), err_msg=f)


def test_false_motion_rate_on_white_noise_matches_theory():
    """Pure white noise with the sensor's σ given: (n − 1)s²/σ² ~ χ²(n − 1) exactly, so each
    window is refused with probability α (all axes); the count over W windows is binomial(W, α)
    and must lie within 4 of its standard deviations of W·α. With σ measured from the record
    (quantile of 20 000 window variances: relative error of σ² ≈ 1 %, moving α by ≈ 10 % of itself
    at α = 1e-2 for ν = 49) the count is within the same band widened by that 10 %."""
    rng = np.random.default_rng(11)
    W, n, alpha = 20_000, 50, 1e-2
    x = SIGMA * rng.standard_normal((W * n, 3))
    lo, hi = _binom_interval(W, alpha)
    given = still_windows(x, RATE_HZ, StillGate(window_samples=n, false_reject_rate=alpha, noise_sigma_rad_s=SIGMA))
    k = int((~given.still).sum())
    assert lo <= k <= hi, (k, lo, hi)
    measured = still_windows(x, RATE_HZ, StillGate(window_samples=n, false_reject_rate=alpha))
    k2 = int((~measured.still).sum())
    assert 0.9 * lo <= k2 <= 1.1 * hi, (k2, lo, hi)
    # the threshold itself: σ² χ²_ν(1 − α_axis)/ν with α_axis = 1 − (1 − α)^(1/3)
    a_axis = 1 - (1 - alpha) ** (1 / 3)
    np.testing.assert_allclose(given.threshold, SIGMA**2 * scipy.stats.chi2.isf(a_axis, n - 1) / (n - 1), rtol=1e-12)


def test_abs_diff_false_motion_rate_is_at_most_its_alpha():
    """The article's Σ|Δ| against the gamma-law quantile: slightly conservative (the gamma law's
    upper tail is heavier than S's), so the count is at most W·α + 4 standard deviations and more
    than half of W·α."""
    rng = np.random.default_rng(12)
    W, n, alpha = 20_000, 50, 1e-2
    x = SIGMA * rng.standard_normal((W * n, 3))
    sw = still_windows(x, RATE_HZ, StillGate(window_samples=n, false_reject_rate=alpha, statistic="abs_diff"))
    k = int((~sw.still).sum())
    lo, hi = _binom_interval(W, alpha)
    assert 0.5 * W * alpha <= k <= hi, (k, W * alpha)


def test_strict_rate_and_exclusion():
    g, _ = _session(seed=5)
    sw = still_windows(g, RATE_HZ, StillGate(window_s=1.0))
    strict = sw.still_at(1e-6)
    assert np.all(strict >= sw.still)  # a higher threshold refuses fewer windows
    excl = np.zeros(sw.n_windows, bool)
    excl[:10] = True
    sx = still_windows(g, RATE_HZ, StillGate(window_s=1.0), exclude=excl)
    assert not sx.still[:10].any()


def test_bad_input_is_one_line():
    with pytest.raises(GyroInputError, match="unknown gate statistic"):
        StillGate(statistic="rms")
    with pytest.raises(GyroInputError, match="shorter than one still window"):
        still_windows(np.zeros((50, 3)), RATE_HZ, StillGate(window_s=1.0))
    with pytest.raises(GyroInputError, match="never changes"):
        still_windows(np.ones((1000, 3)), RATE_HZ, StillGate(window_s=1.0))
    sd, rho = robust_diff_noise(np.random.default_rng(1).standard_normal((100_000, 3)))
    np.testing.assert_allclose(sd, math.sqrt(2), rtol=0.02)  # MAD σ: rel. SE 1.167/√1e5 = 0.4 %
    np.testing.assert_allclose(rho, -0.5, atol=0.03)


def test_robust_diff_sigma_flavours():
    # the one robust noise of differences: σ_Δ (the still gate), per-sample σ_Δ/√2 (the
    # reader's deg/s check), the two zero-MAD answers; an array is not touched, a callable's
    # fresh arrays are
    from gyrocore.data.checks import MAD_TO_SIGMA, MAD_TO_SIGMA_4, robust_diff_sigma, still_noise_rad_s

    x = 0.01 * np.random.default_rng(4).standard_normal(50_001)
    x0 = x.copy()
    s = robust_diff_sigma(x)
    assert np.array_equal(x, x0)
    assert robust_diff_sigma(lambda: x.copy()) == s
    assert robust_diff_sigma(x, per_sample=True) == s / np.sqrt(2.0)
    assert still_noise_rad_s(x) == robust_diff_sigma(x, per_sample=True, mad_to_sigma=MAD_TO_SIGMA_4)
    # the same MAD, another factor (a few roundings apart: 1e-14)
    np.testing.assert_allclose(still_noise_rad_s(x), s / np.sqrt(2.0) * MAD_TO_SIGMA_4 / MAD_TO_SIGMA, rtol=1e-14)
    # white noise: σ_Δ = √2·σ; the MAD σ has relative SE ≈ 1.167/√N = 0.5 %, the lag-1
    # differences' MA(1) correlation inflates it a little: 3 % is > 4 SE
    np.testing.assert_allclose(s, 0.01 * math.sqrt(2), rtol=0.03)
    # a quantum of 5 σ: more than half the differences are 0, the MAD is 0
    q = 0.05 * np.round(x / 0.05)
    assert robust_diff_sigma(q, zero_mad="step") == 0.05
    assert robust_diff_sigma(q, zero_mad="std") == float(np.diff(q).std())
    assert robust_diff_sigma(np.zeros(10), zero_mad="step") == 0.0
    assert robust_diff_sigma(np.zeros(1)) == 0.0
    with pytest.raises(ValueError, match="zero_mad"):
        robust_diff_sigma(q, zero_mad="min")
