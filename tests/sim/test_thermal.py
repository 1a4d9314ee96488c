"""Thermal model: exact step and ramp response; heater holds the set point."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gyrocore.errors import GyroInputError
from sim.thermal import HeaterSpec, TemperatureChunks, ThermalSpec, ThermalState, ambient_ramps, simulate_temperature


def test_step_response_matches_exponential():
    # ambient steps 20 -> 30 °C at t = 0 (the break point 20 at t<0 is represented by starting
    # the die at 20 with ambient 30 from t=0); self-heating 1.5 °C.
    tau = 60.0
    spec = ThermalSpec(time_constant_s=tau, ambient_c=((0.0, 30.0),), self_heating_c=1.5, initial_temp_c=20.0)
    t = np.arange(0.0, 300.0, 0.37)
    temp = simulate_temperature(t, spec)
    expect = 31.5 - 11.5 * np.exp(-t / tau)
    # the discretisation is exact for a constant input: only rounding (~1e-13 °C) remains
    np.testing.assert_allclose(temp, expect, rtol=0, atol=1e-10)


def test_ramp_response_and_streaming_match():
    tau = 45.0
    spec = ThermalSpec(time_constant_s=tau, ambient_c=((0.0, 10.0), (500.0, 60.0)), motor_c_per_w=0.01)
    t = np.arange(0.0, 400.0, 0.25)
    temp = simulate_temperature(t, spec)
    r = 50.0 / 500.0
    # analytic: T = 10 + r t - r tau (1 - exp(-t/tau)) (first-order hold is exact for a ramp)
    np.testing.assert_allclose(temp, 10 + r * t - r * tau * (1 - np.exp(-t / tau)), atol=1e-10)
    # streaming form with motor power equals the batch form (same recursion, same inputs)
    p = np.where(t > 100, 80.0, 0.0)
    batch = simulate_temperature(t, spec, motor_power_w=p)
    st = ThermalState.start(spec, 0.0)
    stream = [st.temp_c] + [st.step(t[k], motor_power_w=p[k - 1]) for k in range(1, t.size)]
    np.testing.assert_allclose(stream, batch, atol=1e-10)
    # motor heating: 80 W * 0.01 °C/W = 0.8 °C steady rise, reached as 1 - exp(-(t-t_on)/tau);
    # the power is held from the first sample after t=100 (t_on = 100.25 s)
    t_on = t[t > 100][0]
    assert batch[-1] - temp[-1] == pytest.approx(0.8 * (1 - math.exp(-(t[-1] - t_on) / tau)), abs=1e-9)


def test_heater_holds_setpoint_through_ambient_ramps():
    tau, tau_cl = 120.0, 10.0
    heater = HeaterSpec(setpoint_c=45.0, max_power_w=4.0, heater_c_per_w=10.0, closed_loop_time_constant_s=tau_cl)
    amb = ambient_ramps(start_c=20.0, peak_c=30.0, start_s=400.0, ramp_s=600.0, hold_s=300.0)
    spec = ThermalSpec(time_constant_s=tau, ambient_c=amb, heater=heater)
    t = np.arange(0.0, 2300.0, 0.1)
    temp = simulate_temperature(t, spec)
    # warm-up at full power (4 W -> +40 °C, tau 120 s) reaches 45 °C at ~118 s
    assert temp[int(100 / 0.1)] < 45.0
    slope = 10.0 / 600.0
    # PI with both closed-loop poles at -1/tau_cl: an ambient ramp of slope r leaves the steady
    # error r tau_cl^2 / tau (final-value theorem on s / (tau s^2 + (1+kp R) s + ki R) * r/s^2),
    # approached monotonically (step response t exp(-t/tau_cl)). Band: that error plus 2 %
    # for the discrete-time PI (h/tau_cl = 1e-2).
    ramp_err = slope * tau_cl**2 / tau
    band = ramp_err * 1.02
    hold = (t > 300.0) & (t < 400.0)  # constant ambient: error decays to ~0
    assert np.abs(temp[hold] - 45.0).max() < 1e-3
    up = (t > 400.0) & (t < 1000.0)
    err_up = temp[up] - 45.0
    assert np.all(np.abs(err_up) <= band)
    assert err_up[-1] == pytest.approx(ramp_err, rel=0.02)  # the predicted offset, not zero
    down = (t > 1300.0) & (t < 1900.0)
    err_dn = temp[down] - 45.0
    assert np.all(np.abs(err_dn) <= band)
    assert err_dn[-1] == pytest.approx(-ramp_err, rel=0.02)
    # without the heater the die would follow ambient: 10 °C of swing
    free = simulate_temperature(t, ThermalSpec(time_constant_s=tau, ambient_c=amb))
    assert free.max() - free[t > 300].min() > 9.0


def test_bad_inputs():
    with pytest.raises(GyroInputError):
        ThermalSpec(time_constant_s=0.0)
    with pytest.raises(GyroInputError):
        simulate_temperature(np.array([0.0, 0.0]), ThermalSpec())


@pytest.mark.parametrize("heater", [False, True])
@pytest.mark.parametrize("sizes", [(1,), (2,), (997,), (4096,), (3, 1, 50)])
def test_temperature_chunks_bit_identical_to_whole(heater, sizes):
    """Issue 13: the die temperature of a long record in chunks equals the whole-series
    evaluation bit for bit (motor power held, ambient ramps, optional heater)."""
    spec = ThermalSpec(
        ambient_c=ambient_ramps(start_c=10.0, peak_c=40.0, start_s=1.0, ramp_s=5.0, hold_s=2.0, end_c=20.0),
        time_constant_s=3.0,
        self_heating_c=0.7,
        motor_c_per_w=0.01,
        heater=HeaterSpec(setpoint_c=45.0) if heater else None,
    )
    n = 12_000
    t = np.arange(n) / 1000.0
    p = 50.0 + 10.0 * np.sin(t)
    whole = simulate_temperature(t, spec, motor_power_w=p)
    tc = TemperatureChunks(spec, n_total=n)
    got, i, k = [], 0, 0
    while i < n:
        j = min(n, i + sizes[k % len(sizes)])
        got.append(tc.take(t[i:j], motor_power_w=p[i:j]))
        i, k = j, k + 1
    assert np.array_equal(np.concatenate(got), whole)


def test_long_uniform_clock_takes_the_recursion_in_chunks_too():
    """Ten hours at 1 kHz: the clock k/rate is uniform although its differences vary by an ulp of
    t (> 1e-9 of the interval beyond ~2 h); the whole series and the chunks both take the
    recursion (same numbers), and it matches the step loop to rounding."""
    spec = ThermalSpec(ambient_c=((0.0, 15.0), (36_000.0, 45.0)), time_constant_s=60.0)
    t = np.arange(35_990_000, 36_000_000) / 1000.0  # the last 10 s of ten hours
    whole = simulate_temperature(t, spec)
    tc = TemperatureChunks(spec, n_total=t.size)
    assert np.array_equal(np.concatenate([tc.take(t[:4000]), tc.take(t[4000:])]), whole)
    st = ThermalState.start(spec, t[0])
    loop = [st.temp_c] + [st.step(tk) for tk in t[1:200]]
    np.testing.assert_allclose(whole[:200], loop, rtol=0, atol=1e-9)
