"""Tests of gyrocore.attitude: exact integration, error angles, Mahony, the floor theory."""

from __future__ import annotations

import numpy as np
import pytest

from gyrocore import attitude as A
from gyrocore.errors import GyroInputError


def _axis_angle(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def test_vectorised_matches_loop_random_rates_and_jittery_steps(monkeypatch):
    # Small chunks/blocks so the test crosses chunk and block boundaries and recursion levels.
    monkeypatch.setattr(A, "_CHUNK", 1000)
    rng = np.random.default_rng(3)
    n = 5003
    t = np.cumsum(rng.uniform(0.5e-3, 1.5e-3, n))
    w = rng.normal(0.0, 3.0, (n, 3))
    q0 = A.qnormalize(rng.normal(size=4))
    for hold in ("backward", "forward"):
        qv = A.integrate_gyro(t, w, q0_wxyz=q0, hold=hold)
        ql = A.integrate_gyro_loop(t, w, q0_wxyz=q0, hold=hold)
        # Both are exact products of the same unit quaternions; only rounding differs:
        # ≲ n·ε ≈ 5e3 · 1.1e-16 ≈ 6e-13 rad worst case.
        assert np.max(A.error_angle_rad(qv, ql)) < 1e-11
        assert np.allclose(np.linalg.norm(qv, axis=1), 1.0, atol=1e-14)
    # backward hold of ω is forward hold of ω shifted by one sample
    ws = np.vstack([w[1:], w[:1]])
    assert np.array_equal(A.integrate_gyro(t, w), A.integrate_gyro(t, ws, hold="forward"))
    with pytest.raises(GyroInputError):
        A.integrate_gyro(t, w, hold="midpoint")


def test_windows_carry_the_attitude_across_the_cuts():
    rng = np.random.default_rng(11)
    n = 3001
    t = np.cumsum(rng.uniform(0.5e-3, 1.5e-3, n))
    w = rng.normal(0.0, 3.0, (n, 3))
    q0 = A.qnormalize(rng.normal(size=4))
    whole = A.integrate_gyro(t, w, q0_wxyz=q0)
    # one window is the whole-record call itself: the same numbers
    ((lo, hi, q),) = list(A.integrate_gyro_windows(t, lambda a, b: w[a:b], [(0, n)], q0_wxyz=q0))
    assert (lo, hi) == (0, n) and np.array_equal(q, whole)
    # windows of 700 rows: each restarts from the carried, renormalised attitude (ε per cut,
    # the product's rounding ≲ n·ε ≈ 3e3 · 1.1e-16 ≈ 3e-13 rad as in the test above)
    cuts = [(a, min(a + 700, n)) for a in range(0, n, 700)]
    parts = list(A.integrate_gyro_windows(t, lambda a, b: w[a:b], cuts, q0_wxyz=q0))
    assert [(a, b) for a, b, _ in parts] == cuts
    assert np.max(A.error_angle_rad(np.vstack([q for *_, q in parts]), whole)) < 1e-11
    # a window that forgot the carried step would be off by one step's rotation (|ω|·Δt ~ 5e-3 rad)
    first = A.integrate_gyro(t[700:1400], w[700:1400], q0_wxyz=parts[0][2][-1])
    assert np.max(A.error_angle_rad(first, whole[700:1400])) > 1e-4


def test_constant_rate_is_exact_rotation():
    # ZOH exact step: constant ω about a fixed axis integrates to exp(ω t / 2) exactly.
    t = np.linspace(0.0, 7.3, 7301)
    w = np.tile([0.3, -1.2, 2.0], (t.size, 1))
    q = A.integrate_gyro(t, w)
    wn = np.linalg.norm(w[0])
    truth = np.stack([_axis_angle(w[0], wn * tk) for tk in t])
    assert np.max(A.error_angle_rad(q, truth)) < 1e-12


def test_half_vector_and_rotation_vector_exponentials():
    # quat_exp_half takes θ/2, quat_from_rotvec takes θ: the same rotation, the names say which
    # argument; both unit quaternions, so components agree to rounding (a few ulp of 1: 1e-15)
    rng = np.random.default_rng(7)
    theta = 0.5 * rng.normal(size=(200, 3)) * np.array([[1.0], [1e-9]]).repeat(100, axis=0)  # |θ| < π
    q_half = A.quat_exp_half(0.5 * theta)
    q_rv = A.quat_from_rotvec(theta)
    np.testing.assert_allclose(q_half, q_rv, rtol=0, atol=1e-15)
    np.testing.assert_allclose(A.rotvec_from_quat(q_rv), theta, rtol=1e-12, atol=1e-18)
    # half the vector is not the whole: a 2-rad rotation vector read as a half-vector turns 4 rad
    v = np.array([[2.0, 0.0, 0.0]])
    np.testing.assert_allclose(A.error_angle_rad(A.quat_exp_half(v), A.quat_from_rotvec(v)), 2.0, atol=1e-12)


def test_body_to_world_convention():
    # +z rate for 90° turns the sensor x axis onto the world y axis (q rotates S -> W).
    t = np.linspace(0.0, 1.0, 101)
    w = np.tile([0.0, 0.0, np.pi / 2], (t.size, 1))
    q = A.integrate_gyro(t, w)[-1]
    x_W = A.qmul(A.qmul(q, [0, 1, 0, 0]), A.qconj(q))[1:]
    assert np.allclose(x_W, [0, 1, 0], atol=1e-12)
    # and body-frame rates compose on the right: x then z rotation
    t2 = np.linspace(0.0, 2.0, 201)
    w2 = np.zeros((201, 3))
    w2[1:101, 0] = np.pi / 2  # backward hold: samples 1..100 cover [0, 1] s: 90° about x
    w2[101:, 2] = np.pi / 2  # 90° about the (new) body z
    q2 = A.integrate_gyro(t2, w2)[-1]
    expect = A.qmul(_axis_angle([1, 0, 0], np.pi / 2), _axis_angle([0, 0, 1], np.pi / 2))
    assert A.error_angle_rad(q2, expect) < 1e-12


def test_error_angle_and_tilt():
    q1 = _axis_angle([0, 0, 1], 0.3)
    assert A.error_angle_rad(q1, q1) == pytest.approx(0.0, abs=1e-15)
    assert A.error_angle_rad(-q1, q1) == pytest.approx(0.0, abs=1e-15)  # q and −q: same attitude
    q2 = A.qmul(q1, _axis_angle([1, 1, 0], 0.25))
    assert A.error_angle_rad(q2, q1) == pytest.approx(0.25, abs=1e-14)
    # pure heading error: no tilt error; pure roll error: tilt error equals it
    assert A.tilt_error_rad(A.qmul(_axis_angle([0, 0, 1], 0.7), q1), q1) == pytest.approx(0.0, abs=1e-14)
    q3 = A.qmul(q1, _axis_angle([1, 0, 0], 0.2))
    assert A.tilt_error_rad(q3, q1) == pytest.approx(0.2, abs=1e-14)


def test_score_attitude():
    t = np.linspace(0.0, 120.0, 1201)
    e = np.radians(0.5 * t / 60.0)  # 0.5 deg/min linear drift
    s = A.score_attitude(t, e)
    assert s.final_error_deg == pytest.approx(1.0)
    assert s.drift_deg_per_min == pytest.approx(0.5)
    assert s.rms_error_deg == pytest.approx(1.0 / np.sqrt(3), rel=1e-3)  # RMS of a ramp = end/√3
    with pytest.raises(GyroInputError):
        A.score_attitude(t[:1], e[:1])


def test_bad_input():
    with pytest.raises(GyroInputError):
        A.integrate_gyro(np.array([0.0, 0.0, 1.0]), np.zeros((3, 3)))
    with pytest.raises(GyroInputError):
        A.integrate_gyro(np.arange(3.0), np.zeros((3, 2)))
    with pytest.raises(GyroInputError):
        A.integrate_gyro(np.arange(3.0), np.full((3, 3), np.nan))


def _tilted_static(n=4001, rate_hz=200.0, tilt_rad=0.2):
    t = np.arange(n) / rate_hz
    q_true = _axis_angle([1, 0.5, 0], tilt_rad)
    up_S = A._up_in_S(q_true[None, :])[0]
    f = np.tile(9.80665 * up_S, (n, 1))
    return t, q_true, f


def test_mahony_proportional_steady_state_tilt_equals_bias_over_kp():
    # Static, level-ish sensor with a horizontal gyro bias b: the P-only Mahony loop settles
    # where kp·e cancels b, so the steady tilt error is |b_horizontal| / kp (small-angle).
    t, q_true, f = _tilted_static(tilt_rad=0.0)
    b = np.array([0.004, -0.003, 0.0])
    w = np.tile(b, (t.size, 1))
    kp = 2.0
    q, _ = A.mahony(t, w, f, q0_wxyz=q_true, kp_per_s=kp)
    tilt = A.tilt_error_rad(q, np.tile(q_true, (t.size, 1)))
    # 20 s = 40 time constants: settled; small-angle error of sin(x)≈x is x³/6 ≈ 1e-8 rel.
    assert tilt[-1] == pytest.approx(np.linalg.norm(b) / kp, rel=1e-4)


def test_mahony_integral_removes_bias_and_initial_tilt():
    t, q_true, f = _tilted_static(n=12001)
    b = np.array([0.01, -0.02, 0.0])
    w = np.tile(b, (t.size, 1))
    q, bhat = A.mahony(t, w, f, kp_per_s=1.0, ki_per_s2=0.3)
    tilt = A.tilt_error_rad(q, np.tile(q_true, (t.size, 1)))
    assert tilt[0] == pytest.approx(0.2, abs=1e-12)
    # PI loop poles: s² + kp·s + ki → both damped (τ ≈ 1.4–3.3 s); after 60 s ≈ 18 slow time
    # constants the tilt error is below 1e-6 of its start.
    assert tilt[-1] < 1e-6
    # horizontal bias (in the level-ish W frame the up-axis bias component is unobservable)
    up_S = A._up_in_S(q_true[None, :])[0]
    b_h = b - up_S * (b @ up_S)
    bh_h = bhat[-1] - up_S * (bhat[-1] @ up_S)
    assert np.allclose(bh_h, b_h, atol=1e-6)


def test_mahony_without_accel_correction_equals_integration():
    rng = np.random.default_rng(0)
    t = np.arange(500) / 100.0
    w = rng.normal(0, 0.5, (500, 3))
    q, _ = A.mahony(t, w, np.zeros((500, 3)), kp_per_s=1.0)  # |f| = 0: gated out
    assert np.max(A.error_angle_rad(q, A.integrate_gyro(t, w))) < 1e-12


def test_floor_theory_white_and_rrw_monte_carlo():
    """Integrated noise follows σθ²(t) = N²t + K²t³/3 per axis over Monte Carlo seeds.

    For a static truth the error vector is the integral of the noise; the squared error angle
    at time t is Σ_i θ_i², a σθ²·χ²₃ variable, so its mean over M seeds has a relative
    standard deviation √(2/(3M)). With M = 240: 0.053; we allow 4σ = 21 %.
    """
    rate_hz, T_s, M = 100.0, 60.0, 240
    N, K = 2e-3, 4e-4  # rad/√s, rad/s/√s. At t=3 s: N²t=1.2e-5 ≫ K²t³/3=1.4e-6 (ARW);
    # at t=60 s: K²t³/3=1.2e-2 ≫ N²t=2.4e-4 (RRW) — both terms are tested.
    n = int(T_s * rate_hz) + 1
    t = np.arange(n) / rate_hz
    dt = 1.0 / rate_hz
    rng = np.random.default_rng(12345)
    idx = [n // 20, n // 4, n - 1]
    e2 = np.zeros((M, len(idx)))
    for m in range(M):
        white = rng.normal(0.0, N * np.sqrt(rate_hz), (n, 3))  # σ = N·√fs (DESIGN.md)
        rrw = np.cumsum(rng.normal(0.0, K * np.sqrt(dt), (n, 3)), axis=0)
        rrw -= rrw[0]  # the walk starts at zero at t0 (its start is the calibrated bias)
        q = A.integrate_gyro(t, white + rrw)
        e2[m] = A.error_angle_rad(q[idx], np.tile([1.0, 0, 0, 0], (len(idx), 1))) ** 2
    sig = A.floor_sigma_theta_rad(t[idx], arw_rad_per_sqrt_s=N, rrw_rad_s_per_sqrt_s=K)
    theory = np.sum(sig**2, axis=1)
    rel = e2.mean(axis=0) / theory - 1.0
    assert np.all(np.abs(rel) < 4 * np.sqrt(2 / (3 * M))), rel


def test_floor_theory_gauss_markov_limits():
    # For t ≪ τc the GM bias acts as a constant of spread σ: variance σ²t² (series branch);
    # for t ≫ τc it acts as white noise of density N = σ·√(2τc): variance 2σ²τc·t.
    s = A.floor_sigma_theta_rad(np.array([1e-3, 1e4]), gm_sigma_rad_s=0.01, gm_tau_c_s=10.0)
    assert s[0, 0] ** 2 == pytest.approx(0.01**2 * 1e-6, rel=1e-3)
    assert s[1, 0] ** 2 == pytest.approx(2 * 0.01**2 * 10.0 * 1e4, rel=2e-3)  # −2σ²τc² term: 1e-3 rel
