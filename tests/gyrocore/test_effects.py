"""The shared measurement model: forward vs formula, inverse, regressors."""

import numpy as np
import pytest

from gyrocore import effects as E
from gyrocore.errors import GyroInputError


def _inputs(n=2000, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 200.0
    w = rng.normal(size=(n, 3))
    f = rng.normal(size=(n, 3)) * 9.8
    T = 20 + np.linspace(0, 10, n)
    return E.ModelInputs(t_s=t, omega_S_rad_s=w, f_S_m_s2=f, temp_c=T)


def test_scale_and_bias_follow_formula():
    inp = _inputs()
    p = {"bias": {"b_rad_s": [0.01, -0.02, 0.03]}, "scale": {"s": [0.01, -0.02, 0.005]}}
    y = E.deterministic(p, inp)
    expect = inp.omega_S_rad_s * (1 + np.array([0.01, -0.02, 0.005])) + np.array([0.01, -0.02, 0.03])
    np.testing.assert_allclose(y, expect, rtol=0, atol=1e-15)


def test_misalignment_and_g_sensitivity_formula():
    inp = _inputs()
    m = np.array([1e-3, 2e-3, -3e-3, 4e-3, -5e-3, 6e-3])
    H = np.arange(9).reshape(3, 3) * 1e-4
    y = E.deterministic({"misalignment": {"m_rad": m}, "g_sensitivity": {"h_rad_s_per_m_s2": H}}, inp)
    K = np.array([[1, m[0], m[1]], [m[2], 1, m[3]], [m[4], m[5], 1]])
    np.testing.assert_allclose(y, inp.omega_S_rad_s @ K.T + inp.f_S_m_s2 @ H.T, atol=1e-15)


def test_nonlinear_and_asymmetry_formula():
    inp = _inputs()
    w = inp.omega_S_rad_s
    y = E.deterministic({"scale_asymmetry": {"a": [1e-3, 2e-3, 3e-3]},
                         "scale_nonlinearity": {"s2_s_per_rad": [1e-3, 0, -1e-3]}}, inp)
    expect = w + np.array([1e-3, 2e-3, 3e-3]) * np.abs(w) + np.array([1e-3, 0, -1e-3]) * w * np.abs(w)
    np.testing.assert_allclose(y, expect, atol=1e-15)


def test_correct_inverts_deterministic():
    inp = _inputs()
    p = {
        "bias": {"b_rad_s": [0.01, 0.02, -0.01]},
        "scale": {"s": [0.01, -0.02, 0.003]},
        "misalignment": {"m_rad": [0.001, 0.002, -0.003, 0.001, 0, 0.002]},
        "g_sensitivity": {"h_rad_s_per_m_s2": np.eye(3) * 1e-3},
        "scale_asymmetry": {"a": [0.001, 0.002, 0.003]},
        "bias_thermal": {"poly_rad_s": np.ones((3, 2)) * 1e-3, "t0_c": 25, "temp_min_c": 10, "temp_max_c": 40},
    }
    y = E.deterministic(p, inp)
    back = E.correct(p, y, E.ModelInputs(t_s=inp.t_s, f_S_m_s2=inp.f_S_m_s2, temp_c=inp.temp_c), iterations=8)
    # fixed-point contraction factor ~|a| = 3e-3 per iteration: 8 iterations -> < 1e-12 relative
    np.testing.assert_allclose(back, inp.omega_S_rad_s, atol=1e-12)


def test_design_matches_finite_difference():
    """A·θ equals deterministic(θ) − ω for effects linear in their parameters."""
    inp = _inputs(500)
    rng = np.random.default_rng(1)
    for eff in ("bias", "scale", "misalignment", "g_sensitivity", "g2_sensitivity",
                "scale_asymmetry", "scale_nonlinearity", "bias_ramp"):
        names, A = E.design(eff, inp)
        theta = rng.normal(size=len(names)) * 1e-3
        pname = next(iter(E.PARAM_SCHEMA[eff]))
        shape = E.PARAM_SCHEMA[eff][pname]
        p = {eff: {pname: theta.reshape(shape)}}
        y = E.deterministic(p, inp)
        np.testing.assert_allclose(y - inp.omega_S_rad_s, A @ theta, atol=1e-12, err_msg=eff)


def test_article_form_round_trip():
    K = np.array([[1.02, 0.01, -0.003], [0.002, 0.98, 0.004], [-0.01, 0.003, 1.01]])
    M, s = E.article_from_k(K)
    np.testing.assert_allclose(np.diag(M), 1.0)
    np.testing.assert_allclose(E.k_from_article(M, s), K, atol=1e-14)


def test_unknown_effect_is_one_line_error():
    with pytest.raises(GyroInputError, match="unknown effect 'bogus'"):
        E.check_effect_names(["bias", "bogus"])


def test_earth_rate_magnitude_and_vertical_component():
    q = np.tile([1.0, 0, 0, 0], (10, 1))
    lat = np.deg2rad(49.0)
    w = E.earth_rate_S(lat, 0.3, q)
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), E.EARTH_RATE_RAD_S, rtol=1e-12)
    np.testing.assert_allclose(w[:, 2], E.EARTH_RATE_RAD_S * np.sin(lat), rtol=1e-12)
