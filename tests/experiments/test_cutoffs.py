"""Tests of experiments.cutoffs on short closed-loop flights (MuJoCo quadrotor)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mujoco")

from experiments import cutoffs as C
from gyrocore.flight.filters import make_filter

DUR = 3.0


@pytest.fixture(scope="module")
def flights():
    _, ref, _, _ = C._fly(None, 5, "none", 30.0, DUR, steps=True)
    raw = C.fly_config("icm42688p", 5, "none", 30.0, DUR, ref_steps=ref)
    art = C.fly_config("icm42688p", 5, "article", 30.0, DUR, ref_steps=ref)
    return raw, art


def test_filter_reduces_motor_noise_and_adds_its_delay(flights):
    (m0, *_), (m1, *_) = flights
    # PT1 at 30 Hz attenuates the >20 Hz gyro noise and vibration by ≥ 2× above ~60 Hz:
    # the motor commands above 20 Hz must get quieter (paired: same unit, same rotor phases).
    assert m1["motor_noise_n"] < 0.7 * m0["motor_noise_n"]
    # Measured lag = on-chip filter lag (raw flight) + our filter's group delay somewhere in the
    # 0.2–15 Hz band: PT1 τ(f) = τ0/(1 + (f/fc)²) ∈ [0.8 τ0, τ0] for f ≤ 15 Hz, fc = 30 Hz.
    tau0 = make_filter("article", 30.0, 1000.0).delay_s(0.0) * 1e3
    extra = m1["delay_ms"] - m0["delay_ms"]
    assert 0.8 * tau0 - 0.2 <= extra <= tau0 + 0.2, (extra, tau0)  # ±0.2 ms: parabolic-peak resolution at 1 kHz
    assert m1["filter_delay_ms"] == pytest.approx(tau0)
    assert m0["crashed"] == 0.0 and m1["crashed"] == 0.0


def test_open_loop_scores(flights):
    (_, truth, log, b0), _ = flights
    none = C.open_loop_scores(truth, log.gyro_meas_rad_s, b0, "none", 30.0)
    art = C.open_loop_scores(truth, log.gyro_meas_rad_s, b0, "article", 30.0)
    # Integrating the gyro: a filter only adds lag to real motion (vibration included), so the
    # open-loop attitude error cannot improve with filtering.
    assert art["att_err_rms_deg"] > none["att_err_rms_deg"]
    assert np.isfinite(none["rate_err_rms_deg_s"])
