"""A stand-in for the firmware bridge in unit tests of the vehicle side (no binary needed).

It implements what :func:`sim.fw_flight.fly_firmware` relies on in Betaflight's conventions,
written from Betaflight's source (``fc/rc.c``, ``flight/pid.c``, ``flight/mixer.c``,
``flight/mixer_init.c``), not from sim.fw_flight: sticks -> rate set point through the rate curve
(roll/pitch FLU, yaw stick negated), a PT1 gyro filter, the PID with Betaflight's term scales
(P 0.032029, I 0.244381, D 0.000529 per deg/s, sum / 1000 to the mixer), the quad-X mixer in its
motor order (1 rear-right, 2 front-right, 3 rear-left, 4 front-left; yaw negated when
``yaw_motors_reversed`` is OFF) and the idle output. A sign or an order wrong on either side makes
the vehicle diverge in the tests.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from sim.fw_flight import RateProfile

_MIX = ((1.0, -1.0, 1.0, -1.0), (1.0, -1.0, -1.0, 1.0), (1.0, 1.0, 1.0, 1.0), (1.0, 1.0, -1.0, -1.0))


class FakeBetaflight:
    def __init__(
        self,
        *,
        loop_rate_hz=8000.0,
        pid=((45, 80, 30), (47, 84, 34), (45, 80, 0)),
        lpf_hz=150.0,
        idle=0.055,
        mincheck=1050,
        rates=None,
    ):
        self.dt = 1.0 / loop_rate_hz
        self.pid = pid
        self.a = self.dt / (self.dt + 1.0 / (2 * math.pi * lpf_hz))
        self.idle, self.mincheck = idle, mincheck
        self.rates = rates or RateProfile()
        self.y = np.zeros(3)
        self.i = np.zeros(3)
        self.prev = None
        self.count = 0
        self.rotor_seen = []

    def step(self, omega_S_rad_s, accel_S_m_s2, q_WB_wxyz, rotor_rad_s, rc):
        thr_us, r_us, p_us, y_us = rc
        self.rotor_seen.append(np.asarray(rotor_rad_s, float).copy())
        g_deg = np.degrees(np.asarray(omega_S_rad_s, float))  # Betaflight's gyro frame: roll x, pitch y, yaw z (FLU)
        g_deg = np.trunc(g_deg * 16.4) / 16.4  # int16 at 16.4 LSB per deg/s
        self.y = self.y + self.a * (g_deg - self.y)
        sp = np.array(
            [
                self.rates.rate_deg_s(0, (r_us - 1500) / 500.0),
                self.rates.rate_deg_s(1, (p_us - 1500) / 500.0),
                -self.rates.rate_deg_s(2, (y_us - 1500) / 500.0),
            ]
        )
        e = sp - self.y
        prev = self.y.copy() if self.prev is None else self.prev
        out = np.zeros(3)
        for ax in range(3):
            kp, ki, kd = self.pid[ax]
            self.i[ax] += ki * 0.244381 * e[ax] * self.dt
            out[ax] = kp * 0.032029 * e[ax] + self.i[ax] - kd * 0.000529 * (self.y[ax] - prev[ax]) / self.dt
        self.prev = self.y.copy()
        out /= 1000.0
        yaw = -out[2]
        mix = np.array([out[0] * m[1] + out[1] * m[2] + yaw * m[3] for m in _MIX])
        throttle = min(max((thr_us - self.mincheck) / (2000.0 - self.mincheck), 0.0), 1.0)
        mot = np.clip(throttle + mix, 0.0, 1.0)
        v = self.idle + (1.0 - self.idle) * mot
        self.count += 1
        return SimpleNamespace(motors=v, fw_gyro_S_rad_s=np.radians(self.y), fw_dterm=None, loop_count=self.count)
