"""The noise-model covariance of the least-squares fit: standard errors from the
identified noise model (white + flicker + rate random walk + Gauss–Markov), exact against a
dense covariance, honest by Monte Carlo, and carried in the parameter file."""

import numpy as np
import pytest
from scipy import signal

from gyrocore.effects import registry as E
from gyrocore.calib import covariance, lsq
from gyrocore.calib.budget import Blocks, block_covariance
from gyrocore.noise.model import NoiseModel
from gyrocore.errors import GyroInputError


def _design(n, rate_hz):
    """A rate-table-like design per axis: bias, gravity along 6 mounts (g-sensitivity-like),
    ±rate plateaus (scale-like). Shape (n, 3, 15); columns 5i.. of axis i."""
    t = np.arange(n) / rate_hz
    dirs = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]]) * 9.81
    g = np.zeros((n, 3))
    w = np.zeros((n, 3))
    seg = n // 6
    for k in range(6):
        sl = slice(k * seg, (k + 1) * seg if k < 5 else n)
        g[sl] = dirs[k]
        tt = t[sl] - t[sl][0]
        w[sl, k // 2] = np.where((tt % 4.0) < 2.0, 1.0, -1.0)
    A = np.zeros((n, 3, 15))
    for i in range(3):
        A[:, i, 5 * i] = 1.0
        A[:, i, 5 * i + 1 : 5 * i + 4] = g
        A[:, i, 5 * i + 4] = w[:, i]
    names = [f"x.p[{j}]" for j in range(15)]
    return t, A, names, {"x": slice(0, 15)}


def _flicker(rng, n, b):
    """Kasdin & Walter α = 1 flicker (the process of sim.noise and of gyrocore.calib.budget): white of
    σ = B through h_0 = 1, h_k = h_{k−1}(k − 1/2)/k, started at rest."""
    k = np.arange(1, n, dtype=float)
    h = np.concatenate([[1.0], np.cumprod((k - 0.5) / k)])
    return signal.fftconvolve(rng.standard_normal((n, 3)) * b, h[:, None], mode="full", axes=0)[:n]


def test_meat_equals_dense_sandwich_when_every_bin_is_a_row():
    # n rows ≤ max_bins: each bin is one row, so the meat is U_iᵀ C_i U_i with C the exact
    # block-mean covariance (budget.block_covariance) plus the white diagonal; compare with the
    # dense product built by hand, per axis and term.
    rng = np.random.default_rng(0)
    n, dt, avg = 300, 0.01, 4
    U = rng.standard_normal((n, 3, 5))
    t0 = np.arange(n) * avg * dt + 5.0  # rows of 4 samples, 5 s after the power-up
    t1 = t0 + avg * dt
    nm = NoiseModel(
        arw_rad_per_sqrt_s=np.array([1e-4, 2e-4, 3e-4]),
        bias_instability_rad_s=np.array([3e-5, 0, 1e-5]),
        rrw_rad_per_s_sqrt_s=np.array([0, 1e-6, 2e-6]),
        correlated_sigma_rad_s=np.array([5e-5, 0, 0]),
        correlated_tau_c_s=np.array([2.0, np.inf, np.inf]),
    )
    S = covariance.noise_model_meat(U, t0, t1, np.full(n, avg), nm, dt_s=dt)
    blk = Blocks(
        i0=np.arange(n),
        i1=np.arange(n) + 1,
        t0_s=t0,
        t1_s=t1,
        scored=np.ones(n, bool),
        segment=np.zeros(n, int),
        window=np.full(n, -1),
    )
    Cf, Ck, Cg = (
        block_covariance(blk, "bias_instability"),
        block_covariance(blk, "rrw"),
        block_covariance(blk, "correlated", tau_c_s=2.0),
    )
    ref = np.zeros((5, 5))
    for i in range(3):
        C = (
            (nm.arw_rad_per_sqrt_s[i] ** 2 / (avg * dt)) * np.eye(n)
            + nm.bias_instability_rad_s[i] ** 2 * Cf
            + nm.rrw_rad_per_s_sqrt_s[i] ** 2 * Ck
            + nm.correlated_sigma_rad_s[i] ** 2 * Cg
        )
        ref += U[:, i, :].T @ C @ U[:, i, :]
    np.testing.assert_allclose(S, ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())


def test_noise_model_standard_errors_are_honest_by_monte_carlo():
    # Flicker-dominated noise on a six-mount design (the rate table's situation: the bias
    # drifts between mounts). If the covariance is right, z = (θ̂ − θ)/SE ~ N(0, 1); the
    # g-sensitivity-like columns of different axes are independent, and within an axis the
    # three are nearly orthogonal, so mean z² over R runs × 9 columns is ≈ χ²_{9R}/(9R)
    # (sd √(2/(9R)) = 0.054 for R = 75; the within-axis correlation < 0.1 adds < 1 %).
    # Band ±4 sd: [0.78, 1.22]; OLS standard errors on the same data are far too small.
    rate, n, R = 25.0, 3000, 75
    t, A, names, slices = _design(n, rate)
    N, B = 2e-4, 2e-4  # rad/√s, rad/s: flicker dominates the variance of 20-s means
    nm = NoiseModel(arw_rad_per_sqrt_s=np.full(3, N), bias_instability_rad_s=np.full(3, B))
    gcols = [5 * i + j for i in range(3) for j in (1, 2, 3)]
    z2, z2_ols = [], []
    for ss in np.random.SeedSequence(12).spawn(R):
        rng = np.random.default_rng(ss)
        e = rng.standard_normal((n, 3)) * N * np.sqrt(rate) + _flicker(rng, n, B)
        fit = lsq.solve(e, A, names, slices, covariance="noise_model", noise_model=nm, t_s=t, average=10)
        z2.append((fit.theta[gcols] / fit.stderr[gcols]) ** 2)
        fo = lsq.solve(e, A, names, slices, covariance="ols", average=10)
        z2_ols.append((fo.theta[gcols] / fo.stderr[gcols]) ** 2)
    m = float(np.mean(z2))
    assert 0.78 < m < 1.22, m
    assert float(np.mean(z2_ols)) > 3.0  # the white-noise covariance is far too small here


def test_chunked_path_gives_the_same_noise_model_standard_errors():
    rate, n = 50.0, 6000
    t, A, names, slices = _design(n, rate)
    rng = np.random.default_rng(3)
    e = rng.standard_normal((n, 3)) * 1e-3 + _flicker(rng, n, 1e-4)
    nm = NoiseModel(arw_rad_per_sqrt_s=np.full(3, 1e-3 / np.sqrt(rate)), bias_instability_rad_s=np.full(3, 1e-4))
    inp = E.ModelInputs(t_s=t, omega_S_rad_s=A[:, 0, 4:5] * np.array([[1.0, 0, 0]]))
    kw = dict(covariance="noise_model", noise_model=nm, t_s=t, average=4)
    whole = lsq.fit_effects(e, ["bias", "scale"], inp, chunk_rows=None, **kw)
    chunk = lsq.fit_effects(e, ["bias", "scale"], inp, chunk_rows=1000, **kw)
    np.testing.assert_allclose(chunk.stderr, whole.stderr, rtol=1e-9)
    assert whole.cov_kind == "noise_model"


def test_noise_model_covariance_needs_the_model():
    t, A, names, slices = _design(600, 50.0)
    with pytest.raises(GyroInputError, match="noise model"):
        lsq.solve(np.zeros((600, 3)), A, names, slices, covariance="noise_model")


def test_calibrator_noise_model_covariance_identifies_the_noise_and_keeps_it_in_the_parameter_file(tmp_path):
    # A rate-table recording (6 mounts, ±rate plateaus with 0.2-s raised-cosine ramps) with white
    # + flicker noise: the calibrator identifies N and B on the residual away from the ramps
    # (GMWM), reports noise-model standard errors, and the parameter file round-trips the model.
    from gyrocore.calibrator import Calibrator, near_rate_changes
    from gyrocore.calib.params import load_params, save_params
    from gyrocore.data.recording import Recording

    rate, n = 200.0, 200 * 180
    t, A, _, _ = _design(n, rate)
    w = A[:, :, 4] * 1.0  # ±1 rad/s plateaus about the mount's axis
    ker = np.hanning(int(0.2 * rate))
    w = signal.fftconvolve(w, (ker / ker.sum())[:, None], mode="same", axes=0)  # ramps instead of steps
    f = A[:, 0, 1:4]
    true = {
        "bias": {"b_rad_s": np.array([0.01, -0.02, 0.005])},
        "scale": {"s": np.array([0.01, -0.02, 0.003])},
        "g_sensitivity": {"h_rad_s_per_m_s2": np.full((3, 3), 2e-4)},
    }
    inp = E.ModelInputs(t_s=t, omega_S_rad_s=w, f_S_m_s2=f)
    rng = np.random.default_rng(7)
    N, B = 1e-3, 6e-4  # Allan floor 0.664·B = 4e-4 rad/s above the white 1e-3/√τ beyond τ ≈ 6 s
    y = E.deterministic(true, inp) + rng.standard_normal((n, 3)) * N * np.sqrt(rate) + _flicker(rng, n, B)
    rec = Recording(t_s=t, gyro_rad_s=y, accel_m_s2=f, ref_rate_rad_s=w, meta={"sensor": "synthetic"})
    assert 0.05 < near_rate_changes(t, w, 0.25).mean() < 0.5
    res = Calibrator(effects=["bias", "scale", "g_sensitivity"], covariance="noise_model", ramp_margin_s=0.25).fit(rec)
    assert res.covariance == "noise_model"
    nm = res.noise()
    # N from ≈ 1.5e5 samples per axis: a few % (GMWM); B from 3 min: within a factor 2
    np.testing.assert_allclose(nm.arw_rad_per_sqrt_s, N, rtol=0.1)
    assert np.all((nm.bias_instability_rad_s > B / 2) & (nm.bias_instability_rad_s < 2 * B))
    assert any("left out" in x for x in res.notes) and any("GMWM" in x for x in res.notes)
    assert np.all(np.isfinite(res.stderr["g_sensitivity"]["h_rad_s_per_m_s2"]))
    save_params(res, tmp_path / "p.json")
    back = load_params(tmp_path / "p.json")
    np.testing.assert_allclose(back.noise().arw_rad_per_sqrt_s, nm.arw_rad_per_sqrt_s)
    assert back.noise_model["rate_hz"] == pytest.approx(rate, rel=1e-9)
