"""Replay through the real firmware's gyro filters matches the discrete filters at the loop rate.

Gain estimate: H1 = |P_xy / P_xx| (Welch, Hann, 4096-sample segments, 50 % overlap) from the
quantised input the firmware read to its filtered gyro. Its errors, for a 4-s record at 8 kHz
(32000 samples, n_d = 14 segments):

* random: σ(|H|)/|H| = sqrt(1 − γ²) / (|γ| sqrt(2 n_d)) (Bendat & Piersol, eq. 9.90). The only
  output not explained by the input is float32 rounding and the input's quantisation (±0.5 LSB on
  a 2 rad/s = 1880 LSB rms signal: 1 − γ² < 1e-6), so σ < 1e-3 / sqrt(28) ≈ 2e-4;
* bias from the filter's delay τ inside a segment of length T: ≈ τ/T; τ ≤ 1.1 ms (PT1 at
  150 Hz: 1/(2π·150)) against T = 0.512 s: 0.2 %; the Hann window's spectral smoothing (±2 bins
  = ±4 Hz) on the notch's slope adds < 0.5 % (the same estimator on the model's output, checked
  below, stays within 0.6 % of the analytic response).

So the 2 % criterion is 4× the estimator's worst error: a firmware that ran its filters at the
wrong rate (the stock SITL's PT1 passed 0.12 instead of 0.69 at 150 Hz) or a wrong filter fails.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import csd, sosfilt, sosfreqz, welch

from gyrocore.flight.filters import betaflight_notch, biquad_notch, pt1
from sim.firmware.bridge import GYRO_LSB_PER_RAD_S, LOOP_RATE_HZ
from sim.firmware.replay import replay_gyro

FS = LOOP_RATE_HZ
F_CHECK = np.array([50.0, 150.0, 300.0])
NPERSEG = 4096
N = 32000  # 4 s: see the module docstring
#: every gyro filter off (the dynamic LPF is off when its min is 0)
ALL_OFF = (
    "set gyro_lpf1_static_hz = 0",
    "set gyro_lpf1_dyn_min_hz = 0",
    "set gyro_lpf2_static_hz = 0",
    "set dyn_notch_count = 0",
    "set rpm_filter_harmonics = 0",
    "set gyro_notch1_hz = 0",
    "set gyro_notch2_hz = 0",
)


def _h1(x, y):
    f, pxy = csd(x, y, fs=FS, nperseg=NPERSEG)
    _, pxx = welch(x, fs=FS, nperseg=NPERSEG)
    return f, np.abs(pxy / pxx)


def _gain_at(x, y, f_hz):
    f, h = _h1(x, y)
    return np.interp(f_hz, f, h)


def _noise(seed, n=N, sigma=2.0):
    return np.random.default_rng(seed).normal(0.0, sigma, (n, 3))


def _replayed_gains(res, axis=0, skip=0):
    x = res.gyro_lsb[skip:, axis] / GYRO_LSB_PER_RAD_S
    return x, res.fw_gyro_S_rad_s[skip:, axis]


def test_pt1_150hz_matches_discrete_pt1(firmware_binary):
    res = replay_gyro(
        firmware_binary, _noise(11), settings=(*ALL_OFF, "set gyro_lpf1_type = PT1", "set gyro_lpf1_static_hz = 150")
    )
    assert np.all(np.diff(res.loop_count) == 1)
    model = pt1(150.0, FS)
    _, h_model = sosfreqz(model.sos, worN=F_CHECK, fs=FS)
    x, _ = _replayed_gains(res)
    for axis in range(3):
        xa, ya = _replayed_gains(res, axis)
        g = _gain_at(xa, ya, F_CHECK)
        assert g == pytest.approx(np.abs(h_model), rel=0.02), (axis, g, np.abs(h_model))
    # the estimator itself, on the model's own output from the same input: within its bias
    # bound from the module docstring (delay 0.2 % + smoothing 0.5 %)
    g_est = _gain_at(x, sosfilt(model.sos, x), F_CHECK)
    assert g_est == pytest.approx(np.abs(h_model), rel=0.007)


def test_static_notch_matches_discrete_notch(firmware_binary):
    res = replay_gyro(
        firmware_binary, _noise(12), settings=(*ALL_OFF, "set gyro_notch1_hz = 200", "set gyro_notch1_cutoff = 150")
    )
    _, h_model = sosfreqz(betaflight_notch(200.0, 150.0, FS).sos, worN=F_CHECK, fs=FS)
    x, y = _replayed_gains(res)
    g = _gain_at(x, y, F_CHECK)
    assert g == pytest.approx(np.abs(h_model), rel=0.02), (g, np.abs(h_model))


def test_dynamic_notch_tracks_a_tone(firmware_binary):
    # A 250 Hz tone on roll over white noise: the firmware's dynamic notch (one notch, Q 3,
    # 100-600 Hz) must find it and then act as the biquad notch at the centre it reports
    # (debug_mode FFT_FREQ: debug[1] = the notch centre on the debug axis, roll).
    n = N
    t = np.arange(n) / FS
    w = _noise(13, n, sigma=0.5)
    w[:, 0] += 1.0 * np.sin(2 * np.pi * 250.0 * t)
    res = replay_gyro(
        firmware_binary,
        w,
        settings=(
            *ALL_OFF,
            "set dyn_notch_count = 1",
            "set dyn_notch_q = 300",
            "set dyn_notch_min_hz = 100",
            "set dyn_notch_max_hz = 600",
            "set debug_mode = FFT_FREQ",
        ),
    )
    skip = 4000  # 0.5 s to lock on
    centre = res.debug[skip:, 1].astype(float)
    assert np.median(centre) == pytest.approx(250.0, abs=4.0)
    x, y = _replayed_gains(res, skip=skip)
    _, h_model = sosfreqz(biquad_notch(float(np.median(centre)), FS, q=3.0).sos, worN=F_CHECK, fs=FS)
    g = _gain_at(x, y, F_CHECK)
    assert g == pytest.approx(np.abs(h_model), rel=0.02), (g, np.abs(h_model))
    # and the tone itself is removed (stock SITL, notch compiled out: 0.86)
    assert _gain_at(x, y, np.array([250.0]))[0] < 0.05
