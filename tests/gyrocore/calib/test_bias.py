"""Static bias with a motion gate (gyrocore.calib.bias): synthetic truth, rules, gate honesty, real MPU-6050."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.signal
import scipy.stats

from gyrocore.calib.bias import StaticBiasCalibrator, startup_still_slice
from gyrocore.data.still import abs_diff_moments, robust_diff_noise
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording

RATE_HZ = 100.0
N_RAD_SQRT_S = 0.002  # white rate noise density, rad/s/√Hz
SIGMA = N_RAD_SQRT_S * math.sqrt(RATE_HZ)  # per-sample σ = N √rate (DESIGN.md)
BIAS = np.array([0.01, -0.02, 0.005])


def _still(rng: np.random.Generator, n: int, sigma: float = SIGMA) -> np.ndarray:
    return BIAS + sigma * rng.standard_normal((n, 3))


def _rec(g: np.ndarray) -> Recording:
    return Recording(t_s=np.arange(g.shape[0]) / RATE_HZ, gyro_rad_s=g)


def _binom_ok(k: int, n: int, p: float, level: float = 1e-3) -> bool:
    """k consistent with Binomial(n, p) at two-sided level ``level``."""
    return scipy.stats.binom.cdf(k, n, p) > level / 2 and scipy.stats.binom.sf(k - 1, n, p) > level / 2


def test_bias_within_4sigma_and_se_is_n_over_sqrt_t():
    rng = np.random.default_rng(11)
    r = StaticBiasCalibrator(correlation="white").fit(_rec(_still(rng, 4000)))
    T = r.window_s  # 200 samples = 2 s
    sigma_b = N_RAD_SQRT_S / math.sqrt(T)  # theory: bias error σ = N/√T
    assert np.all(np.abs(r.bias_rad_s - BIAS) < 4 * sigma_b)
    # reported SE uses σ from the MAD of 3999 differences: relative SE of a MAD-σ is
    # ≈ 1.167/√n ≈ 1.8 %; 4.4 of those = 8 %.
    np.testing.assert_allclose(r.bias_se_rad_s, sigma_b, rtol=0.08)
    assert r.window_start_index == 0 and r.n_rejected_windows == 0
    assert r.units == "rad/s" and r.format_version


def test_median_and_converge_rules():
    rng = np.random.default_rng(12)
    rec = _rec(_still(rng, 4000))
    mean = StaticBiasCalibrator(rule="mean", correlation="white").fit(rec)
    med = StaticBiasCalibrator(rule="median", correlation="white").fit(rec)
    conv = StaticBiasCalibrator(rule="converge", correlation="white").fit(rec)
    # median efficiency 2/π for Gaussian data: SE ratio √(π/2) exactly by construction
    np.testing.assert_allclose(med.bias_se_rad_s / mean.bias_se_rad_s, math.sqrt(math.pi / 2), rtol=1e-12)
    assert np.all(np.abs(med.bias_rad_s - BIAS) < 4 * med.bias_se_rad_s)
    # converge averages two windows: SE = σ/√(2n)
    np.testing.assert_allclose(conv.bias_se_rad_s, mean.bias_se_rad_s / math.sqrt(2), rtol=1e-12)
    assert conv.window_samples == 400
    assert np.all(np.abs(conv.bias_rad_s - BIAS) < 4 * conv.bias_se_rad_s)


def test_motion_bursts_rejected_then_retry():
    rng = np.random.default_rng(13)
    n = 200
    g = _still(rng, 20 * n)
    # three windows with hand-like motion: a 0.5 s half-sine rate burst of 0.2 rad/s
    burst = 0.2 * np.sin(np.linspace(0, np.pi, 50))
    for w in range(3):
        g[w * n + 60 : w * n + 110, w % 3] += burst
    r = StaticBiasCalibrator(window_samples=n).fit(_rec(g))
    assert r.n_rejected_windows == 3
    assert r.window_start_index == 3 * n
    assert np.all(np.abs(r.bias_rad_s - BIAS) < 4 * N_RAD_SQRT_S / math.sqrt(n / RATE_HZ))
    with pytest.raises(GyroInputError, match="motion detected throughout"):
        StaticBiasCalibrator(window_samples=n, max_retries=1, noise_sigma_rad_s=SIGMA).fit(_rec(g))


def test_motion_throughout_is_one_line_error():
    rng = np.random.default_rng(14)
    t = np.arange(3000) / RATE_HZ
    g = _still(rng, 3000) + 0.3 * np.sin(2 * np.pi * 0.7 * t)[:, None]  # waving the board
    g_fast = _still(rng, 3000) + 0.3 * np.sin(2 * np.pi * 8.0 * t)[:, None]  # vibration
    # Σ|Δ| sees only the fast motion (0.7 Hz waving changes Δ by ≤ 0.013 rad/s, below σ_Δ = 0.028)
    for kw, gg in (({}, g), ({"statistic": "abs_diff"}, g_fast), ({"rule": "median"}, g), ({}, g_fast)):
        with pytest.raises(GyroInputError) as e:
            # σ from the sensor spec: a recording that moves throughout cannot tell its own noise
            StaticBiasCalibrator(noise_sigma_rad_s=SIGMA, **kw).fit(_rec(gg))
        assert "motion detected throughout" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(GyroInputError, match="motion detected throughout"):
        StaticBiasCalibrator(rule="converge", noise_sigma_rad_s=SIGMA).fit(_rec(g))


@pytest.mark.parametrize("statistic", ["variance", "abs_diff"])
def test_false_reject_rate_at_rest_is_honest(statistic):
    """20 000 still windows: refused windows ~ Binomial(20 000, α = 1e-3) (two-sided 0.1 %)."""
    rng = np.random.default_rng(15)
    W, n = 20000, 200
    r = StaticBiasCalibrator(statistic=statistic, window_samples=n).fit(_rec(_still(rng, W * n)))
    rejected = r.n_windows_total - r.n_windows_still
    assert r.false_reject_rate == 1e-3
    assert _binom_ok(rejected, W, 1e-3), rejected


def test_abs_diff_moments_match_simulation():
    """E and Var of Σ|Δ| (with the −1/2 neighbour correlation) against 20 000 windows."""
    rng = np.random.default_rng(16)
    x = rng.standard_normal((20000, 200))
    S = np.abs(np.diff(x, axis=1)).sum(axis=1)
    mean, var = abs_diff_moments(199, np.array([math.sqrt(2.0)]), np.array([-0.5]))
    # SE of the MC mean = √(var/20000) ≈ 0.1; of the MC variance ≈ var·√(2/20000) ≈ 1 %
    assert abs(S.mean() - mean[0]) < 4 * math.sqrt(var[0] / 20000)
    assert abs(S.var() / var[0] - 1) < 4 * math.sqrt(2 / 20000)
    sd, rho = robust_diff_noise(rng.standard_normal((100000, 3)))
    np.testing.assert_allclose(sd, math.sqrt(2), rtol=0.02)  # MAD σ: rel. SE 1.167/√1e5 = 0.4 %
    np.testing.assert_allclose(rho, -0.5, atol=0.03)  # from two MAD-σ ratios, ≈ 4σ


def test_smallest_motion_is_caught_half_of_the_time():
    """Variance gate: a step (or ramp) of the stated size trips 50 % of windows (exact ncχ²)."""
    rng = np.random.default_rng(17)
    W, n = 4000, 200
    cal = StaticBiasCalibrator(window_samples=n, noise_sigma_rad_s=SIGMA)
    sd = np.full(3, SIGMA * math.sqrt(2))
    thr, _, _, step, ramp = cal.gate(n, sd, np.full(3, -0.5), 1 / RATE_HZ)
    for kind, size in (("step", step[0]), ("ramp", ramp[0])):
        x = SIGMA * rng.standard_normal((W * n, 3))
        k = np.arange(n)
        sig = np.where(k >= n // 2, size, 0.0) if kind == "step" else size * k / RATE_HZ
        x[:, 0] += np.tile(sig, W)
        caught = int(np.any(x.reshape(W, n, 3).var(axis=1, ddof=1) > thr, axis=1).sum())
        # P(caught) = 1 − 0.5·(1 − α_axis)² ≈ 0.5003 (other two axes at rest)
        p = 1 - 0.5 * (1 - (1 - (1 - 1e-3) ** (1 / 3))) ** 2
        assert _binom_ok(caught, W, p), (kind, caught)
    # and the variance gate is far more sensitive to slow motion than the article's Σ|Δ|
    cal_ad = StaticBiasCalibrator(window_samples=n, noise_sigma_rad_s=SIGMA, statistic="abs_diff")
    _, _, _, step_ad, ramp_ad = cal_ad.gate(n, sd, np.full(3, -0.5), 1 / RATE_HZ)
    assert np.all(step_ad > 10 * step) and np.all(ramp_ad > 10 * ramp)


def test_reported_se_is_honest_montecarlo_white_and_coloured():
    """100 seeds × 3 axes: Σ z² ~ χ²(300) for white noise and for DLPF-like AR(1) noise."""
    for a in (0.0, 0.5):
        z = []
        for seed in range(100):
            rng = np.random.default_rng(1000 + seed)
            e = SIGMA * rng.standard_normal((2000, 3))
            if a:
                e = scipy.signal.lfilter([1 - a], [1, -a], e, axis=0)  # on-chip low-pass
            r = StaticBiasCalibrator().fit(_rec(BIAS + e))
            z.append((r.bias_rad_s - BIAS) / r.bias_se_rad_s)
        z2 = float(np.sum(np.square(z)))
        lo, hi = scipy.stats.chi2.ppf([5e-4, 1 - 5e-4], 300)
        assert lo < z2 < hi, (a, z2, lo, hi)


def test_startup_still_slice():
    rng = np.random.default_rng(18)
    g = _still(rng, 5000)
    g[1000:] += np.linspace(0, 2.0, 4000)[:, None]  # takes off after 10 s
    s = startup_still_slice(_rec(g), max_duration_s=30.0)
    assert s == slice(0, 1000)
    assert startup_still_slice(_rec(g), max_duration_s=4.0) == slice(0, 400)
    g2 = g.copy()
    g2[:200] += 0.5 * np.sin(np.linspace(0, 6 * np.pi, 200))[:, None]
    assert startup_still_slice(_rec(g2)) is None


def test_bad_options():
    with pytest.raises(GyroInputError):
        StaticBiasCalibrator(rule="nope")
    with pytest.raises(GyroInputError, match="lsb"):
        StaticBiasCalibrator(rule="article")
    with pytest.raises(GyroInputError, match="shorter than"):
        StaticBiasCalibrator().fit(_rec(np.zeros((100, 3))))


# ---------------------------------------------------------------------------- real data
def _tomisuarez_static(shared_data):
    p = shared_data / "tomisuarez2_mpu6050" / "example_data_tinit_calc.csv"
    if not p.exists():
        pytest.skip("tomisuarez2 static set not present")
    raw = np.loadtxt(p, delimiter=",", skiprows=5)[:, 3:6]  # gx, gy, gz raw LSB
    return raw


def test_mpu6050_article_gate_never_calibrates_ours_does(shared_data):
    raw = _tomisuarez_static(shared_data)
    lsb_rad_s = math.radians(1 / 131)  # ±250 °/s: 131 LSB per °/s
    n = 200
    W = raw.shape[0] // n
    sums = np.abs(np.diff(raw[: W * n].reshape(W, n, 3), axis=1)).sum(axis=1)
    # the article's gate: every window of the still sensor exceeds 500 counts on every axis
    assert np.all(sums > 500)
    rec = Recording(t_s=np.arange(raw.shape[0]) / 100.0, gyro_rad_s=raw * lsb_rad_s)
    with pytest.raises(GyroInputError, match="motion detected throughout"):
        StaticBiasCalibrator(rule="article", lsb_rad_s=lsb_rad_s).fit(rec)
    for statistic in ("variance", "abs_diff"):
        r = StaticBiasCalibrator(statistic=statistic).fit(rec)
        assert r.n_rejected_windows == 0
        # refused still windows: Binomial(224, 1e-3) ⇒ ≤ 2 at the 0.1 % level
        assert r.n_windows_total - r.n_windows_still <= scipy.stats.binom.ppf(0.999, W, 1e-3)
        np.testing.assert_allclose(r.bias_rad_s, raw[:n].mean(axis=0) * lsb_rad_s, rtol=1e-12)


# ---------------------------------------------------------------------------- noise sanity bound
@pytest.mark.parametrize("kw", [{}, {"rule": "median"}, {"rule": "converge"}])
def test_smooth_motion_throughout_refused_without_given_noise(kw):
    """A ±29 °/s (0.5 rad/s) 0.2 Hz sine for 300 s, σ self-estimated: every window variance
    holds the motion (the 25 % quantile gave σ ≈ 8 °/s and the gate accepted it before); the
    first differences hold only the noise (the sine changes Δ by ≤ 0.5·2π·0.2/100 = 0.006
    rad/s ≪ σ_Δ = 0.028 rad/s), so the variance/difference ratio (≈ 60 ≫ 4) refuses it."""
    rng = np.random.default_rng(21)
    t = np.arange(30000) / RATE_HZ
    g = _still(rng, t.size) + 0.5 * np.sin(2 * np.pi * 0.2 * t)[:, None]
    with pytest.raises(GyroInputError) as e:
        StaticBiasCalibrator(**kw).fit(_rec(g))
    msg = str(e.value)
    assert "motion detected throughout" in msg and "moves smoothly" in msg and "\n" not in msg


def test_noise_bound_keeps_still_recordings_at_the_stated_rate():
    """Still recordings (white and on-chip low-pass AR(1) φ = 0.5, 0.8 noise) are never refused
    by the σ sanity bound, and the gate's own false-reject rate is unchanged: 60 short
    recordings (10 windows of 200 samples, the smallest that self-estimates σ from window
    variances) per noise; refused windows ~ Binomial(60·10, 1e-3) ⇒ ≤ 3 at the 0.1 % level.
    Theory: the bound is 4× the AR(1) prediction, the ratio's sampling spread here is ~10 %."""
    from gyrocore.data.still import NOISE_RATIO_BOUND

    for phi in (0.0, 0.5, 0.8):
        refused = 0
        for seed in range(60):
            rng = np.random.default_rng(2000 + seed)
            e = SIGMA * rng.standard_normal((2000, 3))
            if phi:
                e = scipy.signal.lfilter([1 - phi], [1, -phi], e, axis=0)
            r = StaticBiasCalibrator().fit(_rec(BIAS + e))  # raises if the bound refused it
            refused += r.n_windows_total - r.n_windows_still
        assert refused <= scipy.stats.binom.ppf(0.999, 600, 1e-3), (phi, refused)
    assert NOISE_RATIO_BOUND == 4.0


def test_real_static_logs_pass_the_noise_bound(shared_data):
    """Real static MPU-6050 logs (sunsided, tomisuarez2) still calibrate with self-estimated σ."""
    import warnings

    from gyrocore.readers.convert import load_any
    from gyrocore.errors import RepairWarning

    paths = [
        shared_data / "sunsided_mpu6050" / "set-2" / "unmoved-with-x-pointing-forward",
        shared_data / "tomisuarez2_mpu6050" / "imu_static_test.csv",
    ]
    if not all(p.exists() for p in paths):
        pytest.skip("static logs absent")
    for p in paths:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RepairWarning)
            rec = load_any(p)
        r = StaticBiasCalibrator().fit(rec)
        assert r.n_rejected_windows == 0
