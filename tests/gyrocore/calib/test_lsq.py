"""Joint least squares: truth recovery within the LS covariance, observability, honest errors."""

import numpy as np
import pytest
from scipy import signal

from gyrocore.effects import registry as E
from gyrocore.calib import covariance, lsq
from gyrocore.errors import GyroInputError, UnobservableError

TRUE = {
    "bias": {"b_rad_s": np.array([0.01, -0.02, 0.005])},
    "scale": {"s": np.array([0.01, -0.02, 0.003])},
    "misalignment": {"m_rad": np.array([1e-3, 2e-3, -3e-3, 1e-3, 0.0, 2e-3])},
}
SIGMA_RAD_S = 0.005  # per-sample white noise


def _table(n=12000, rate_hz=100.0, rate_rad_s=1.5, axes=(0, 1, 2)):
    """Rate table: still, then each axis in `axes` turned + and − (equal durations)."""
    t = np.arange(n) / rate_hz
    w = np.zeros((n, 3))
    segs = [(a, s) for a in axes for s in (1, -1)]
    seg = n // (len(segs) + 1)
    for k, (ax, s) in enumerate(segs):
        w[(k + 1) * seg : (k + 2) * seg, ax] = s * rate_rad_s
    return t, w


def _run(seed, *, n=12000, axes=(0, 1, 2), noise=None, f=None):
    rng = np.random.default_rng(seed)
    t, w = _table(n=n, axes=axes)
    inp = E.ModelInputs(t_s=t, omega_S_rad_s=w, f_S_m_s2=f)
    e = rng.normal(0, SIGMA_RAD_S, (n, 3)) if noise is None else noise(rng, n)
    return inp, E.deterministic(TRUE, inp) + e


def _truth_vector(fit):
    v = np.zeros(len(fit.names))
    for eff, sl in fit.slices.items():
        v[sl] = np.concatenate([np.ravel(x) for x in TRUE[eff].values()])
    return v


def test_recovers_bias_scale_misalignment_within_4_sigma():
    inp, y = _run(0)
    fit = lsq.fit_effects(y - inp.omega_S_rad_s, ["bias", "scale", "misalignment"], inp)
    assert fit.unobservable == ()
    assert fit.cov_kind == "ols"  # white noise: Ljung-Box does not reject
    z = (fit.theta - _truth_vector(fit)) / fit.stderr
    # each z ~ N(0,1) if the LS covariance is right; |z| < 4 fails with prob 6e-5 per entry
    assert np.all(np.abs(z) < 4), z
    # theory: scale s_i is fitted from 2 segments of n/7 samples at |ω| = 1.5 rad/s:
    # σ_s = σ/(1.5·sqrt(2n/7)) (bias and misalignment are orthogonal here)
    n = inp.n
    expect = SIGMA_RAD_S / (1.5 * np.sqrt(2 * (n // 7)))
    np.testing.assert_allclose(fit.effect_stderr("scale"), expect, rtol=0.05)  # σ̂ from 36k dof: ±1 %
    np.testing.assert_allclose(fit.residual_rms_rad_s, SIGMA_RAD_S, rtol=0.03)  # sample σ of 12k: ±1 %


def test_never_rotated_axis_is_named_unobservable():
    inp, y = _run(1, axes=(0, 1))  # z never turned
    fit = lsq.fit_effects(y - inp.omega_S_rad_s, ["bias", "scale", "misalignment"], inp)
    # scale z (column ω_z ≡ 0) and the misalignments driven by ω_z (K[0,2], K[1,2]) are null
    assert set(fit.unobservable) == {"scale.s[2]", "misalignment.m_rad[1]", "misalignment.m_rad[3]"}
    assert "no excitation" in fit.unobservable_reason["scale.s[2]"]
    assert np.all(np.isinf(fit.stderr[~fit.observable_mask()]))
    assert np.all(np.isfinite(fit.stderr[fit.observable_mask()]))
    with pytest.raises(UnobservableError, match=r"scale\.s\[2\]"):
        lsq.fit_effects(y - inp.omega_S_rad_s, ["bias", "scale", "misalignment"], inp, on_unobservable="raise")


def test_constant_gravity_g_sensitivity_is_unobservable_not_fitted_to_noise():
    rng = np.random.default_rng(2)
    n = 12000
    f = np.tile([0.0, 0.0, 9.81], (n, 1)) + rng.normal(0, 0.02, (n, 3))
    inp, y = _run(3, n=n, f=f)
    fit = lsq.fit_effects(y - inp.omega_S_rad_s, ["bias", "scale", "misalignment", "g_sensitivity"], inp)
    assert all(u.startswith("g_sensitivity.") for u in fit.unobservable)
    assert len(fit.unobservable) == 9
    # bias keeps its white-noise precision σ/sqrt(n) (it would be ~10× worse if H[:,2]
    # were fitted: f_z ≈ 9.81 is collinear with the bias column)
    assert np.all(fit.effect_stderr("bias") < 2 * SIGMA_RAD_S / np.sqrt(n / 7 * 1))


def test_g_sensitivity_observable_with_varied_gravity():
    rng = np.random.default_rng(4)
    n = 12000
    # six static poses (each axis up and down) then the table turns: f changes in steps
    poses = np.repeat(
        np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]]) * 9.81, n // 6, axis=0
    )
    f = poses + rng.normal(0, 0.02, (n, 3))
    H = np.array([[1e-3, 2e-4, -3e-4], [0, 5e-4, 1e-4], [2e-4, 0, -8e-4]])
    t, w = _table(n=n)
    inp = E.ModelInputs(t_s=t, omega_S_rad_s=w, f_S_m_s2=f)
    p = dict(TRUE, g_sensitivity={"h_rad_s_per_m_s2": H})
    y = E.deterministic(p, inp) + rng.normal(0, SIGMA_RAD_S, (n, 3))
    fit = lsq.fit_effects(y - w, ["bias", "scale", "misalignment", "g_sensitivity"], inp)
    assert fit.unobservable == ()
    z = (fit.effect_theta("g_sensitivity") - H.ravel()) / fit.effect_stderr("g_sensitivity")
    assert np.all(np.abs(z) < 4), z


def _ar1_noise(phi, sigma):
    """AR(1) noise with marginal σ (a first-order Gauss–Markov bias sampled at the rate)."""

    def make(rng, n):
        e = rng.normal(0, sigma * np.sqrt(1 - phi**2), (n, 3))
        return signal.lfilter([1.0], [1.0, -phi], e, axis=0, zi=rng.normal(0, sigma, (1, 3)))[0]

    return make


def test_coloured_residual_switches_to_hac():
    inp, y = _run(5, noise=_ar1_noise(0.9, SIGMA_RAD_S))
    fit = lsq.fit_effects(y - inp.omega_S_rad_s, ["bias", "scale", "misalignment"], inp)
    assert fit.cov_kind == "hac"
    assert fit.ljung_box_p < 0.01
    ols = lsq.fit_effects(y - inp.omega_S_rad_s, ["bias", "scale", "misalignment"], inp, covariance="ols")
    # AR(1) long-run variance factor (1+φ)/(1−φ) = 19 -> HAC stderr ≈ sqrt(19) ≈ 4.4× OLS;
    # the Bartlett/pre-whitened estimate is within ±30 % of that on 12k samples
    ratio = fit.effect_stderr("bias") / ols.effect_stderr("bias")
    assert np.all((ratio > 4.4 * 0.7) & (ratio < 4.4 * 1.3)), ratio


def test_bad_input_is_one_line_error():
    inp, y = _run(6, n=200)
    with pytest.raises(GyroInputError, match="unknown effect"):
        lsq.fit_effects(y, ["bias", "nonsense"], inp)
    with pytest.raises(GyroInputError, match="shape"):
        lsq.solve(y[:, :2], np.zeros((200, 3, 1)), ["a"], {"a": slice(0, 1)})


def _mix_noise(rng, n):
    """White (σ) plus a strong first-order Gauss–Markov bias (φ = 0.99, τc = 100 samples,
    2 mrad/s): the GM part dominates the long-run variance ~30× though lag-1 correlation
    is only 0.14 — the case where score-kernel (Newey–West) estimators understate errors."""
    return rng.normal(0, SIGMA_RAD_S, (n, 3)) + _ar1_noise(0.99, 0.002)(rng, n)


@pytest.mark.slow
@pytest.mark.parametrize(
    "kind,noise,n",
    [("white", None, 6000), ("ar1", _ar1_noise(0.8, SIGMA_RAD_S), 6000), ("white+gm", _mix_noise, 20000)],
)
def test_monte_carlo_standard_errors_are_honest(kind, noise, n):
    """Over 60 seeds, z = (θ̂ − θ)/σ̂ must have unit variance (honest standard errors).

    Pooling the 12 parameters × 60 seeds = 720 z values (correlated within a seed, so take
    the effective count as 60·3 = 180): the sample variance of z has relative sd
    sqrt(2/180) ≈ 0.105; accept 0.7 < var(z) < 1.35 (≈ 3 sd either side, with room for the
    covariance estimator's own small-sample bias of a few %, which grows with τc/T: for
    the white+GM case the record is 200 τc long).
    """
    zs = []
    for seed in range(60):
        inp, y = _run(1000 + seed, n=n, noise=noise)
        fit = lsq.fit_effects(y - inp.omega_S_rad_s, ["bias", "scale", "misalignment"], inp)
        zs.append((fit.theta - _truth_vector(fit)) / fit.stderr)
    z = np.concatenate(zs)
    assert 0.7 < np.var(z) < 1.35, np.var(z)


def test_slow_noise_invisible_to_ljung_box_is_caught_by_block_means():
    """White σ = 1 plus a weak slow Gauss–Markov part (σ = 0.05, τc = 2000 samples): its
    lag-l correlations are ≈ 0.0025, so Ljung–Box (20 lags, Q ≈ N·20·0.0025² ≈ 5 against
    χ²₂₀) does not see it, yet it carries ≈ 0.0025·2τc = 10× the white long-run variance.
    Blocks of 2048 samples (19 of them): predicted white Var(mean) = 1/2048 = 4.9e-4, the GM
    part adds ≈ 0.0025·0.6 = 1.5e-3 — a ratio of 4 against a χ²₁₈(0.999)/18 = 2.4 bound."""
    rng = np.random.default_rng(12)
    n = 40000
    white = rng.normal(0, 1.0, n)
    x = white + _ar1_noise(np.exp(-1 / 2000), 0.05)(rng, n)[:, 0]
    assert covariance.ljung_box_p(x) > 0.01
    assert covariance.low_frequency_excess(x)
    assert not covariance.low_frequency_excess(white)
    g = covariance.residual_autocov_model(x)
    lr_model = g[0] + 2 * g[1:].sum()
    lr_true = 1.0 + 0.05**2 * (1 + np.exp(-1 / 2000)) / (1 - np.exp(-1 / 2000))  # = 11
    # Only part of that is visible in 20 correlation times (block variances at L ≥ 2048 rest
    # on 19 and 9 blocks, relative sd 0.33 and 0.5, and the mean is removed); the model must
    # add the visible part — above the short-lag model's own long-run variance (≈ 1.0 + its
    # sampling noise 2·5·1/sqrt(N) ≈ 0.05) — and must not exceed the truth by much.
    g0 = covariance._short_and_tail(x, 5, None, 1e-4)
    assert lr_model > 1.5 * (g0[0] + 2 * g0[1:].sum())
    assert lr_model < 1.5 * lr_true


def _chunk_case(seed: int, n: int = 6000):
    """A record exercising every window-sensitive regressor: time derivatives (time_offset,
    bias_temp_rate), the whole-record T0 (bias_thermal) and power-up time (bias_ramp)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 200.0 + 1e-4 * rng.random(n).cumsum()  # slightly uneven sampling
    w = np.stack(
        [
            0.8 * np.sin(2 * np.pi * t / 7.0),
            0.6 * np.sin(2 * np.pi * t / 5.0 + 1),
            0.5 * np.sin(2 * np.pi * t / 11.0 + 2),
        ],
        1,
    )
    T = 25 + 20 * (1 - np.exp(-t / 10.0)) + 0.01 * rng.standard_normal(n)
    params = {
        "bias": {"b_rad_s": np.array([0.01, -0.007, 0.004])},
        "scale": {"s": np.array([0.01, -0.02, 0.005])},
        "bias_thermal": {
            "poly_rad_s": np.array([[2e-4, -3e-6], [-1.5e-4, 2e-6], [1e-4, 4e-6]]),
            "t0_c": np.asarray(30.0),
            "temp_min_c": np.asarray(0.0),
            "temp_max_c": np.asarray(100.0),
        },
        "bias_ramp": {"ramp_rad_s2": np.array([1e-5, -2e-5, 0.0])},
        "time_offset": {"tau_s": np.asarray(0.003)},
    }
    inp = E.ModelInputs(t_s=t, omega_S_rad_s=w, temp_c=T)
    r = E.deterministic(params, inp) + 2e-3 * rng.standard_normal((n, 3))
    wts = np.ones(n)
    wts[1000:1500] = 0.0  # an excluded stretch: blocks straddle it and the windows
    wts[::97] = 0.0
    return r, inp, wts


@pytest.mark.parametrize("stride,average,chunk", [(1, 7, 1000), (2, 5, 333), (1, 40, 64)])
def test_chunked_design_equals_whole_array_fit(stride, average, chunk):
    # The chunked path (design built in windows, only block means kept) is algebraically the
    # whole-array path; only the order of float additions differs where an averaging block
    # straddles two windows (relative rounding ~ average·eps ≈ 1e-14), amplified by the
    # condition number of the normal equations (< 1e2 here) → θ, standard errors and the
    # full-resolution residual agree to 1e-10 relative (≥ 100× margin).
    r, inp, wts = _chunk_case(3)
    eff = ["bias", "scale", "bias_thermal", "bias_ramp", "bias_temp_rate", "time_offset"]
    kw = dict(orders={"bias_thermal": 2}, weights=wts, stride=stride, average=average, covariance="hac")
    whole = lsq.fit_effects(r, eff, inp, chunk_rows=None, **kw)
    chunked = lsq.fit_effects(r, eff, inp, chunk_rows=chunk, **kw)
    assert chunked.unobservable == whole.unobservable and chunked.rank == whole.rank
    assert chunked.n_rows == whole.n_rows and chunked.dof == whole.dof and chunked.cov_kind == whole.cov_kind
    np.testing.assert_allclose(chunked.theta, whole.theta, rtol=1e-10, atol=1e-10 * np.abs(whole.theta).max())
    ok = np.isfinite(whole.stderr)
    np.testing.assert_allclose(chunked.stderr[ok], whole.stderr[ok], rtol=1e-10)
    np.testing.assert_allclose(chunked.residual_rad_s, whole.residual_rad_s, rtol=0, atol=1e-12)
    np.testing.assert_allclose(chunked.residual_rms_rad_s, whole.residual_rms_rad_s, rtol=1e-10)
    assert chunked.residual_rad_s.shape == r.shape


@pytest.mark.parametrize("stride,average", [(1, 1), (1, 7), (2, 5)])
def test_solve_is_fit_effects_over_one_window(stride, average):
    # one code path: solve(r, A, average=) is the block reduction of fit_effects over a single
    # window (the design of the whole record), so the two are bit-identical, not merely close
    r, inp, wts = _chunk_case(3)
    eff = ["bias", "scale", "bias_thermal", "bias_ramp", "bias_temp_rate", "time_offset"]
    orders = {"bias_thermal": 2}
    kw = dict(weights=wts, stride=stride, average=average, covariance="hac")
    A, names, slices = lsq.build_design(eff, inp, orders=orders)
    whole = lsq.solve(r, A, names, slices, **kw)
    one = lsq.fit_effects(r, eff, inp, orders=orders, chunk_rows=None, **kw)
    for f in ("theta", "stderr", "residual_rad_s", "residual_rms_rad_s", "axis_sigma_rad_s"):
        np.testing.assert_array_equal(getattr(one, f), getattr(whole, f), err_msg=f)
    assert one.cov_kind == whole.cov_kind and one.n_rows == whole.n_rows and one.unobservable == whole.unobservable


def test_chunked_fit_never_holds_the_whole_design(monkeypatch):
    # every design the chunked path builds has at most chunk_rows + 2 rows (one-sample overlap)
    r, inp, wts = _chunk_case(4)
    sizes = []
    real = lsq.build_design

    def spy(effects, inp_, **kw):
        sizes.append(inp_.n)
        return real(effects, inp_, **kw)

    monkeypatch.setattr(lsq, "build_design", spy)
    lsq.fit_effects(r, ["bias", "time_offset"], inp, weights=wts, average=10, chunk_rows=500)
    assert sizes and max(sizes) <= 502
