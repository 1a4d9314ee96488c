"""gyrocore.calib.budget: predicted attitude error from noise and parameter uncertainty."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from gyrocore.calib import budget as B
from gyrocore.effects import registry as E
from gyrocore.attitude import floor_sigma_theta_rad
from gyrocore.noise.model import NoiseModel


def _still(n, rate):
    t = np.arange(n) / rate
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return t, q


def test_floor_matches_the_closed_form_for_white_rrw_and_gauss_markov():
    # A still sensor integrated from its power-up (no window): the block sums of the exact
    # block-integral covariances add up to Var ∫_0^t x, so the prediction must equal
    # N²t + K²t³/3 + 2σ²τc²(t/τc − 1 + e^(−t/τc)) per axis (attitude.floor_sigma_theta_rad)
    # to rounding (the only approximation, R constant within a block, is exact here).
    rate, n = 100.0, 6000
    t, q = _still(n, rate)
    N, K, sg, tc = 1e-4, 3e-6, 2e-4, 7.0
    nm = NoiseModel(
        arw_rad_per_sqrt_s=np.full(3, N),
        rrw_rad_per_s_sqrt_s=np.full(3, K),
        correlated_sigma_rad_s=np.full(3, sg),
        correlated_tau_c_s=np.full(3, tc),
    )
    pr = B.predict_error(E.ModelInputs(t_s=t, q_SW_wxyz=q), start=0, segments=[(slice(0, n), None)], noise=nm)
    want = np.sum(
        floor_sigma_theta_rad(pr.t_s, arw_rad_per_sqrt_s=N, rrw_rad_s_per_sqrt_s=K, gm_sigma_rad_s=sg, gm_tau_c_s=tc)
        ** 2,
        axis=1,
    )
    got = sum(pr.floor_var_rad2.values())
    np.testing.assert_allclose(got, want, rtol=1e-9)
    # no window: the prediction is the floor
    np.testing.assert_allclose(pr.total_var_rad2(), got, rtol=1e-12)


def _kasdin_walter(rng, n, b):
    k = np.arange(1, n, dtype=float)
    h = np.concatenate([[1.0], np.cumprod((k - 0.5) / k)])
    w = rng.standard_normal((n, 3)) * b
    return signal.fftconvolve(w, h[:, None], axes=0)[:n]


def test_window_and_flicker_against_monte_carlo_rotating():
    # White + flicker noise (Kasdin & Walter's discrete α = 1 filter, innovation σ = B, started
    # at power-up: an independent reference for the continuous model), power-up bias from a
    # 2-s still window, then a steady rotation of 1 rad/s about a tilted axis. M = 300 runs:
    # the mean of |ε|² (≈ σ²·χ²₃/3 per run, slightly correlated axes) has relative sd
    # ≤ √(2/M) = 8 % (χ²₁ worst case); tested within 3 sd = 25 %.
    rate, T = 100.0, 40.0
    n = int(T * rate)
    t = np.arange(n) / rate
    win = slice(0, int(2 * rate))
    ang = np.where(t < 2.0, 0.0, t - 2.0)
    ax = np.array([0.0, 0.6, 0.8])
    q = np.concatenate([np.cos(ang / 2)[:, None], np.sin(ang / 2)[:, None] * ax[None, :]], axis=1)
    N, Bf = 1e-4, 3e-5
    nm = NoiseModel(arw_rad_per_sqrt_s=np.full(3, N), bias_instability_rad_s=np.full(3, Bf))
    pr = B.predict_error(E.ModelInputs(t_s=t, q_SW_wxyz=q), start=win.stop, segments=[(slice(0, n), win)], noise=nm)
    R = B.rotation_matrices(q)[win.stop :]
    M = 300
    e2 = np.zeros(n - win.stop)
    f2 = np.zeros(n - win.stop)
    rng = np.random.default_rng(12)
    for _ in range(M):
        x = rng.standard_normal((n, 3)) * N * np.sqrt(rate) + _kasdin_walter(rng, n, Bf)
        y = x - x[win].mean(axis=0)
        e2 += np.sum((np.cumsum(np.einsum("nij,nj->ni", R, y[win.stop :]), 0) / rate) ** 2, 1) / M
        f2 += np.sum((np.cumsum(np.einsum("nij,nj->ni", R, x[win.stop :]), 0) / rate) ** 2, 1) / M
    tt = t[win.stop :] - t[win.stop]
    for tq in (3.0, 15.0, 37.0):
        i = np.searchsorted(tt, tq)
        j = np.searchsorted(pr.t_s, tq)
        assert pr.total_var_rad2()[j] == pytest.approx(e2[i], rel=0.25), tq
        assert sum(pr.floor_var_rad2.values())[j] == pytest.approx(f2[i], rel=0.25), tq
    # the window term is what separates the two: prediction above the floor here
    assert pr.rms_predicted_deg > 1.5 * pr.rms_floor_deg


def test_sensitivity_of_scale_and_bias_on_a_turn_about_z():
    # Still 2 s (window), then ω = 0.5 rad/s about z: a z-scale error δs gives
    # δω = −ω δs ẑ and ε(t) = −ω (t − t_s) δs ẑ (ẑ fixed in W), i.e. S[:, 2, s_z] = ω (t − t_s).
    # A bias error is constant: the window mean removes it, S = 0 exactly.
    rate, n = 100.0, 2000
    t = np.arange(n) / rate
    w = np.zeros((n, 3))
    w[200:, 2] = 0.5
    ang = np.concatenate([[0.0], np.cumsum(w[1:, 2]) / rate])
    q = np.stack([np.cos(ang / 2), 0 * ang, 0 * ang, np.sin(ang / 2)], axis=1)
    inp = E.ModelInputs(t_s=t, omega_S_rad_s=w, q_SW_wxyz=q)
    segs = [(slice(0, n), slice(0, 200))]
    blocks = B.make_blocks(t, start=200, segments=segs, max_blocks=100)
    R = B.rotation_matrices(q)
    g = B.ParameterGroup(
        "x",
        {"scale": {"s": np.zeros(3)}, "bias": {"b_rad_s": np.zeros(3)}},
        {"scale": {"s": np.full(3, 1e-3)}, "bias": {"b_rad_s": np.full(3, 1e-4)}},
    )
    names, S, se = B.sensitivity(inp, R, blocks, segs, g)
    assert names[2] == "scale.s[2]" and names[5] == "bias.b_rad_s[2]"
    tm = blocks.t1_s - 2.0
    sc = blocks.scored
    np.testing.assert_allclose(S[sc, 2, 2], 0.5 * tm[sc], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(S[:, :, 3:], 0.0, atol=1e-12)
    np.testing.assert_allclose(se, [1e-3] * 3 + [1e-4] * 3)
    pr = B.predict_error(inp, start=200, segments=segs, noise=NoiseModel(arw_rad_per_sqrt_s=np.zeros(3)), groups=[g])
    np.testing.assert_allclose(pr.var_rad2["param:x"][-1], (0.5 * (t[-1] + 0.01 - 2.0) * 1e-3) ** 2, rtol=1e-9)
    b = pr.budget_deg()
    assert set(b) == {"param:x"}


def test_budget_squares_add_up_and_uncorrected_is_reported_not_predicted():
    rate, n = 100.0, 3000
    t, q = _still(n, rate)
    segs = [(slice(0, n), slice(0, 200))]
    nm = NoiseModel(arw_rad_per_sqrt_s=np.full(3, 1e-4), bias_instability_rad_s=np.full(3, 2e-5))
    dw = np.zeros((n, 3))
    dw[:, 0] = 1e-5 * t  # a ramp: not removed by the window mean
    pr = B.predict_error(
        E.ModelInputs(t_s=t, q_SW_wxyz=q),
        start=200,
        segments=segs,
        noise=nm,
        uncorrected={"ramp": dw, "lp": 0.1 * dw},
        expected_uncorrected=("lp",),
    )
    b = pr.budget_deg()
    tot = sum(np.sign(v) * v * v for v in b.values())
    assert np.degrees(np.sqrt(pr._mean(pr.total_var_rad2(list(pr.var_rad2))))) ** 2 == pytest.approx(tot, rel=1e-9)
    assert "uncorrected:ramp" not in pr.predicted and "uncorrected:lp" in pr.predicted
    assert pr.rms_with_uncorrected_deg > pr.rms_predicted_deg
    assert b["powerup window"] > 0  # a 2-s window adds more white noise than it removes flicker


def test_noise_model_from_catalogue_params():
    nm = NoiseModel.from_params(
        {"arw": {"n_rad_per_sqrt_s": np.array([1e-4, 2e-4, 3e-4])}, "quantization": {"lsb_rad_s": np.array(1e-3)}}
    )
    np.testing.assert_allclose(nm.white_var_rad2_s(1000.0), np.array([1e-4, 2e-4, 3e-4]) ** 2 + 1e-6 / 12e3)
    assert np.all(nm.bias_instability_rad_s == 0) and np.all(np.isinf(nm.correlated_tau_c_s))


def test_flicker_block_covariance_kernel_matches_the_numpy_form():
    """The compiled flicker second difference equals the numpy expression: log from libm instead of
    numpy may differ by one ulp, which the second difference's cancellation (four F values of size
    ~t², differences of size ~block²) amplifies by about t²/block² ≈ 1e4 here: 1e-9 of the largest
    entry bounds it with two orders to spare."""
    import numpy as np

    from gyrocore.calib import budget as B

    rng = np.random.default_rng(7)
    a0 = np.sort(rng.uniform(0.0, 600.0, 300))
    a1 = a0 + rng.uniform(0.05, 3.0, 300)
    k = B._flicker_kernel()
    assert k is not None
    ref = (
        B._F_flicker(a1[:, None], a1[None, :])
        - B._F_flicker(a1[:, None], a0[None, :])
        - B._F_flicker(a0[:, None], a1[None, :])
        + B._F_flicker(a0[:, None], a0[None, :])
    )
    got = B._second_difference(B._F_flicker, a0, a1, a0, a1)
    assert np.max(np.abs(got - ref)) <= 1e-9 * np.max(np.abs(ref))
    # the block covariance of flicker is symmetric positive semi-definite up to that rounding
    assert np.allclose(got, got.T, rtol=0, atol=1e-9 * np.max(np.abs(ref)))
