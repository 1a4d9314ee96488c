"""RpmNotch (Betaflight's RPM filter): notches every rotor harmonic, passes the flight band."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gyrocore.errors import GyroInputError
from gyrocore.flight.filters import RpmNotch


def _run(f_tone, rotor_hz, n=4000, rate=1000.0):
    flt = RpmNotch(rate)
    flt.set_rotor_hz(rotor_hz)
    flt.reset()
    t = np.arange(n) / rate
    x = np.cos(2 * math.pi * f_tone * t)
    y = np.array([flt.step(np.array([v, 0.0, -v]))[0] for v in x])
    return x[n // 2 :], y[n // 2 :]  # steady state (Q 5 notch at >= 100 Hz settles in < 20 ms)


def test_notches_rotor_and_harmonics():
    # exactly on the notch: an RBJ notch has a zero there; the residual is the transient's tail,
    # decaying as exp(-pi f / Q t): < 1e-3 of the input after 2 s
    for f in (140.5, 281.0, 421.5):
        x, y = _run(f, [140.5] * 4)
        assert np.sqrt(np.mean(y**2)) < 1e-3 * np.sqrt(np.mean(x**2))


def test_passes_the_flight_band():
    # at 10 Hz the Q-5 notches at 140/281/421 Hz: |H| = prod |1 - (f/fc)^2| / |1 - (f/fc)^2 + j f/(fc Q)| per notch,
    # 4 rotors x 3 harmonics: the gain loss is below 0.1 %
    x, y = _run(10.0, [140.5] * 4)
    assert np.sqrt(np.mean(y**2)) == pytest.approx(np.sqrt(np.mean(x**2)), rel=1e-3)


def test_min_hz_and_nyquist():
    flt = RpmNotch(1000.0, harmonics=3, min_hz=100.0)
    flt.set_rotor_hz([50.0, 200.0])
    # rotor 1: 100 (clamped), 100, 150; rotor 2: 200, 400, 600 -> 600 >= 480 off
    assert len(flt._coef) == 5
    with pytest.raises(GyroInputError):
        RpmNotch(0.0)
