"""Tests of gyrocore.flight.filters: the article's coefficient and delay, PTn, biquads, Butterworth,
batch/streaming bit-identity, the pipeline."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from gyrocore.flight import filters as F
from gyrocore.errors import GyroInputError


def test_article_coefficient_holds_at_500_hz():
    # A = 1/(1 + 1/(2π·0.002·30)) = 0.2737789…; the article prints 0.2739 (its last digit is
    # off by one: 0.27378 rounds to 0.2738), which is within 1.3e-4.
    A = F.article_lpf_coefficient(30.0, 500.0)
    assert A == pytest.approx(0.2737789034, abs=1e-10)
    assert abs(A - 0.2739) < 1.5e-4
    # ... and not at the loop rates flight controllers run today
    assert F.article_lpf_coefficient(30.0, 1000.0) == pytest.approx(0.1586001376, abs=1e-10)  # 0.188496/1.188496
    assert F.article_lpf_coefficient(30.0, 8000.0) < 0.03


def test_article_filter_delay_exceeds_one_period():
    # H(z) = A / (1 − (1−A) z⁻¹): DC group delay (1−A)/A samples = 1/(2π·fc) s exactly.
    f = F.article_lpf(30.0, 500.0)
    d = f.delay_s(0.0)
    assert d == pytest.approx(1 / (2 * math.pi * 30.0), rel=1e-9)  # 5.305 ms
    assert d * 500.0 == pytest.approx(2.653, abs=1e-3)  # 2.65 samples > the article's 1-sample budget
    # the cutoff that meets the one-period budget at 500 Hz: 1/(2π·fc) = T -> fc = 79.6 Hz
    assert F.article_lpf(500 / (2 * math.pi), 500.0).delay_s() == pytest.approx(1 / 500.0, rel=1e-9)


def test_article_filter_is_betaflight_pt1():
    a = F.article_lpf(30.0, 500.0)
    p = F.pt1(30.0, 500.0)
    # same coefficient, two algebraic forms (1/(1+1/ω) vs ω/(ω+1)): equal to rounding
    assert np.allclose(a.sos, p.sos, rtol=4e-16, atol=0)


@pytest.mark.parametrize("order", [1, 2, 3])
def test_ptn_cutoff_correction(order):
    # Each section is y += k(x − y), k = ω/(ω+1), ω = 2π·fc·c_n/rate, with exact discrete
    # response |H1|² = k² / (1 − 2(1−k)cos w + (1−k)²); the cascade is |H1|^(2n).
    rate, fc = 1000.0, 20.0
    f = F.make_filter(f"pt{order}", fc, rate)
    om = 2 * math.pi * fc * F.pt_cutoff_correction(order) / rate
    k = om / (om + 1)
    w = 2 * math.pi * fc / rate
    h1sq = k**2 / (1 - 2 * (1 - k) * math.cos(w) + (1 - k) ** 2)
    assert f.magnitude(fc) ** 2 == pytest.approx(h1sq**order, rel=1e-12)
    # Betaflight's correction makes the continuous-time cascade −3 dB at fc; the discrete
    # (not prewarped) sections approach it as fc/rate -> 0: first-order error in ω, so at
    # fc/rate = 1e-3 the power at fc is 1/2 within ~1 % (order·ω·c ≈ 3·0.0063·2 ≈ 4e-2 bound
    # on the log, observed < 1 %).
    slow = F.make_filter(f"pt{order}", 1.0, 1000.0)
    assert slow.magnitude(1.0) ** 2 == pytest.approx(0.5, rel=0.01)
    assert F.pt_cutoff_correction(2) == pytest.approx(1.553773974, abs=1e-9)
    assert F.pt_cutoff_correction(3) == pytest.approx(1.961459177, abs=1e-9)


def test_biquad_lowpass_is_butterworth2():
    # RBJ low-pass with Q = 1/√2 is the bilinear-transform 2nd-order Butterworth (prewarped),
    # identical to scipy.signal.butter(2) up to rounding.
    bq = F.biquad_lowpass(80.0, 1000.0)
    bw = F.butterworth(80.0, 1000.0, order=2)
    f = np.array([1.0, 40.0, 80.0, 200.0, 450.0])
    assert np.allclose(bq.response(f).magnitude, bw.response(f).magnitude, rtol=1e-10, atol=1e-14)
    assert bq.magnitude(80.0) == pytest.approx(1 / math.sqrt(2), rel=1e-10)


def test_notch_kills_its_frequency():
    n = F.biquad_notch(150.0, 1000.0, q=3.0)
    assert n.magnitude(150.0) < 1e-12
    assert n.magnitude(0.0) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("kind", F.FILTER_KINDS)
@pytest.mark.parametrize("start", ["zero", "steady"])
def test_stream_is_bit_identical_to_batch(kind, start):
    rng = np.random.default_rng(7)
    x = rng.normal(0.1, 1.0, (400, 3))
    f = F.make_filter(kind, 60.0, 1000.0, start=start) if kind != "none" else F.identity_filter(1000.0)
    y = f.apply(x)
    f.reset()
    ys = np.stack([f.step(r) for r in x])
    assert np.array_equal(y, ys)
    f.reset()  # reset really restarts
    assert np.array_equal(np.stack([f.step(r) for r in x[:10]]), y[:10])


def test_steady_start_has_no_transient():
    f = F.pt3(30.0, 500.0, start="steady")
    x = np.tile([0.01, -0.02, 0.5], (50, 1))
    assert np.allclose(f.apply(x), x, rtol=1e-12, atol=1e-15)
    z = F.pt3(30.0, 500.0, start="zero").apply(x)
    assert abs(z[0, 2]) < 0.1  # zero start: output climbs from 0


def test_group_delay_matches_scipy_and_measured_lag():
    # DC group delay against a measured lag of a slow ramp: a linear-phase-at-DC filter
    # delays a ramp by exactly its DC group delay once the transient has died out.
    rate = 1000.0
    for kind in ("article", "pt2", "pt3", "biquad", "butter4"):
        f = F.make_filter(kind, 50.0, rate, start="zero")
        t = np.arange(3000) / rate
        x = (0.3 * t)[:, None] * np.ones(3)
        y = f.apply(x)
        lag_s = (x[-1, 0] - y[-1, 0]) / 0.3
        assert lag_s == pytest.approx(f.delay_s(0.0), rel=1e-6), kind
        b, a = signal.sos2tf(f.sos)
        _, gd = signal.group_delay((b, a), w=[10.0], fs=rate)
        assert f.delay_s(10.0) == pytest.approx(gd[0] / rate, rel=1e-12)


def test_pipeline_correction_then_filter_stream_equals_batch():
    rng = np.random.default_rng(1)
    x = rng.normal(0.0, 0.2, (300, 3)) + np.array([0.01, -0.02, 0.003])
    K = np.eye(3) + np.array([[0.01, 0.002, 0], [0, -0.02, 0.001], [0.003, 0, 0.015]])
    p = F.Pipeline([F.AffineCorrection([0.01, -0.02, 0.003], K), F.pt2(40.0, 1000.0)])
    yb = p.apply(x)
    p.reset()
    ys = np.stack([p.step(r) for r in x])
    assert np.array_equal(yb, ys)
    # the correction really inverts K(ω) + b
    w = rng.normal(0, 1, (5, 3))
    c = F.AffineCorrection([0.01, -0.02, 0.003], K)
    assert np.allclose(c.apply(w @ K.T + np.array([0.01, -0.02, 0.003])), w, atol=1e-14)
    assert p.delay_s() == pytest.approx(F.pt2(40.0, 1000.0).delay_s())


def test_bad_cutoffs():
    with pytest.raises(GyroInputError):
        F.pt1(600.0, 1000.0)
    with pytest.raises(GyroInputError):
        F.pt3(300.0, 1000.0)  # below Nyquist, but its sections would sit at 588 Hz
    with pytest.raises(GyroInputError):
        F.make_filter("kalman", 30.0, 1000.0)
