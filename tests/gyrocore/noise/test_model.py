"""The one noise model: its Allan variance, spectrum, bias process, views and checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.integrate

from gyrocore.errors import GyroInputError
from gyrocore.noise import allan as AL
from gyrocore.noise.model import TERMS, NoiseModel, model_value

RATE = 100.0


def test_avar_is_the_ieee_952_model_in_its_discrete_form():
    N, K, B = 1e-3, 2e-5, 3e-5
    taus = np.array([0.01, 0.1, 1.0, 10.0, 100.0])
    white = NoiseModel(N).avar(taus, RATE)
    # white rate noise: σ²(τ) = N²/τ exactly at every whole number of samples
    np.testing.assert_allclose(white, np.broadcast_to(N**2 / taus, (3, taus.size)), rtol=1e-12)
    rw = NoiseModel(0.0, rrw_rad_per_s_sqrt_s=K).avar(taus, RATE)[0]
    # discrete random walk: K²τ/3 + K²τ0²/(6τ) (→ the IEEE asymptote K²τ/3)
    np.testing.assert_allclose(rw, K**2 * taus / 3 + K**2 / RATE**2 / (6 * taus), rtol=1e-12)
    flicker = NoiseModel(0.0, bias_instability_rad_s=B).avar(np.array([100.0]), RATE)[0, 0]
    # m = 10⁴ > 4096: the flat IEEE floor (2 ln2/π)B²
    assert flicker == pytest.approx(2 * math.log(2) / math.pi * B**2, rel=1e-12)
    with pytest.raises(GyroInputError, match="one sample"):
        NoiseModel(N).avar(np.array([0.001]), RATE)


def test_psd_of_the_gauss_markov_term_integrates_to_its_variance():
    sigma, tau_c = 2e-4, 0.5
    m = NoiseModel(0.0, correlated_sigma_rad_s=sigma, correlated_tau_c_s=tau_c)
    # two-sided PSD over (−rate/2, rate/2]: its integral is the process variance σ² (AR(1), exact);
    # quad to 1e-10 relative, the Lorentzian is smooth
    val, _err = scipy.integrate.quad(
        lambda f: float(m.psd(np.array([f]), RATE)[0, 0]), 1e-9, RATE / 2, points=[1 / tau_c], limit=200
    )
    assert 2 * val == pytest.approx(sigma**2, rel=1e-6)
    white = NoiseModel(1e-3).psd(np.array([1.0, 10.0, 50.0]), RATE)
    np.testing.assert_allclose(white, 1e-6)  # N² per Hz, two-sided: N²·rate per sample
    with pytest.raises(GyroInputError, match="rate/2"):
        m.psd(np.array([60.0]), RATE)


def test_bias_process_gauss_markov_where_present_else_random_walk():
    m = NoiseModel(
        1e-3,
        rrw_rad_per_s_sqrt_s=[2e-5, 2e-5, 0.0],
        correlated_sigma_rad_s=[0.0, 1e-4, 0.0],
        correlated_tau_c_s=[math.inf, 5.0, math.inf],
    )
    dt = 0.01
    phi, q = m.bias_process(dt)
    np.testing.assert_allclose(phi, [1.0, math.exp(-dt / 5.0), 1.0])
    np.testing.assert_allclose(q[[0, 2]], [(2e-5) ** 2 * dt, 0.0])
    assert q[1] / (1 - phi[1] ** 2) == pytest.approx(1e-4**2)  # stationary variance σ²


def test_values_are_checked():
    with pytest.raises(GyroInputError, match="finite and >= 0"):
        NoiseModel(-1e-3)
    with pytest.raises(GyroInputError, match="per axis"):
        NoiseModel(np.ones(2))
    with pytest.raises(GyroInputError, match="tau_c_s must be > 0"):
        NoiseModel(1e-3, correlated_tau_c_s=0.0)
    assert np.all(NoiseModel(1e-3).correlated_tau_c_s == math.inf)


def test_model_value_rule():
    amb = {"bias_instability_rad_s": "correlated_sigma_rad_s", "correlated_sigma_rad_s": "x"}
    est = {"bias_instability_rad_s": 3e-5, "correlated_sigma_rad_s": 1e-4, "correlated_tau_c_s": 7.0}
    assert model_value("arw_rad_per_sqrt_s", 1e-3, {}, {}) == 1e-3  # resolved: its value
    assert model_value("bias_instability_rad_s", None, amb, est) == 3e-5  # ambiguous: the fitted estimate
    assert model_value("correlated_tau_c_s", None, amb, est) == 7.0
    assert model_value("rrw_rad_per_s_sqrt_s", None, amb, {"rrw_rad_per_s_sqrt_s": 1.0}) == 0.0  # unresolved
    assert model_value("correlated_tau_c_s", None, {}, est) == math.inf  # no Gauss–Markov term


def test_identification_carries_one_model_per_axis_and_the_analysis_one_for_all():
    rng = np.random.default_rng(5)
    N = 1e-3
    g = N * math.sqrt(RATE) * rng.standard_normal((30000, 2))
    an = AL.identify_noise(g, rate_hz=RATE, check_static=False)
    r = an.axes["x"]
    assert r.model.axes == ("x",) and r.model.resolved["arw_rad_per_sqrt_s"][0]
    assert r.all_terms()["arw_rad_per_sqrt_s"] == float(r.model.arw_rad_per_sqrt_s[0])
    assert r.all_terms()["bias_instability_rad_s"] is None and r.model.bias_instability_rad_s[0] == 0.0
    lo, hi = r.interval("arw_rad_per_sqrt_s")
    assert lo < N < hi  # 95 % interval, one draw (seeded)
    js = r.to_json()
    assert set(TERMS) <= set(js) and js["ci95"]["arw_rad_per_sqrt_s"] == [lo, hi]
    both = an.noise_model()
    assert both.axes == ("x", "y") and both.ci95["arw_rad_per_sqrt_s"].shape == (2, 2)
    full = an.noise_model(("x", "y", "z"))  # z not analysed: the mean of x and y
    assert full.arw_rad_per_sqrt_s[2] == pytest.approx(np.mean(both.arw_rad_per_sqrt_s), rel=1e-12)
    assert full.axis("y").arw_rad_per_sqrt_s[0] == both.arw_rad_per_sqrt_s[1]
