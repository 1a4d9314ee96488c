"""The vehicle side of the firmware flight (sim/fw_flight.py), with a stand-in firmware
(tests/sim/fake_firmware.py: Betaflight's conventions written from its source). The flights with
the real firmware are in tests/sim/test_fw_flight_firmware.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gyrocore.data.recording import write_csv
from gyrocore.errors import GyroInputError
from sim.fw_flight import (
    ROTOR_OF_BF_MOTOR,
    FwFlightOptions,
    RateProfile,
    fly_firmware,
    motor_law,
    rate_pulses,
    to_recording,
)
from tests.sim.fake_firmware import FakeBetaflight

CASES = [
    RateProfile(),
    RateProfile(rates_type="BETAFLIGHT", rc_rate=(100, 120, 250), expo=(0, 20, 10), srate=(70, 0, 50)),
    RateProfile(rates_type="RACEFLIGHT", rc_rate=(37, 37, 37), expo=(50, 0, 30), srate=(80, 0, 40)),
    RateProfile(rates_type="KISS", rc_rate=(100, 110, 90), expo=(10, 0, 40), srate=(70, 60, 50)),
    RateProfile(rates_type="QUICK", rc_rate=(100, 100, 100), expo=(0, 30, 0), srate=(67, 70, 50)),
    RateProfile(rates_type="QUICK", rc_rate=(100, 100, 100), expo=(20, 30, 0), srate=(67, 70, 50), quick_rc_expo=True),
]


@pytest.mark.parametrize("prof", CASES, ids=lambda p: p.rates_type + ("e" if p.quick_rc_expo else ""))
def test_stick_deflection_inverts_the_firmware_rate_curve(prof):
    # bisection to 2^-34 in deflection: the rate curve's slope is at most ~2000 deg/s per unit of
    # deflection, so the rate matches to 2000 x 2^-34 = 1.2e-7 deg/s
    for axis in range(3):
        for d in np.linspace(-0.99, 0.99, 23):
            r = prof.rate_deg_s(axis, d)
            assert prof.rate_deg_s(axis, prof.deflection(axis, r)) == pytest.approx(r, abs=2e-7)


def test_default_rates_are_betaflight_4_6s():
    p = RateProfile()  # ACTUAL: centre sensitivity 70 deg/s, max rate 670 deg/s
    assert p.rate_deg_s(0, 1.0) == pytest.approx(670.0)
    assert p.rate_deg_s(0, 1e-6) / 1e-6 == pytest.approx(70.0, rel=1e-4)
    assert p.deflection(0, 5000.0) == 1.0
    s = RateProfile.from_settings({"rates_type": "betaflight", "roll_rc_rate": "100", "roll_srate": "70"})
    assert s.rates_type == "BETAFLIGHT" and s.rc_rate[0] == 100 and s.srate == (70, 67, 67)
    assert RateProfile.from_settings({"rates_type": "0"}).rates_type == "BETAFLIGHT"  # a header's lookup index
    assert RateProfile.from_settings({"rates_type": "3"}).rates_type == "ACTUAL"
    with pytest.raises(GyroInputError):
        RateProfile(rates_type="FAST")


def test_racing25_motor_law_is_the_logs_and_gives_its_hover_speed():
    from sim.vehicles import get_vehicle

    law = motor_law("racing25", 0.055)
    # the log's rotor-line law at its hover command u = 0.21 (models/racing25.xml): 326.84 Hz, and
    # the model's hover rotor speed (327.0 Hz, the same law rounded) agree to 0.05 %
    assert law.speed_rad_s(0.21) == pytest.approx(2 * math.pi * (242.5 + 401.6 * 0.21))
    assert law.speed_rad_s(0.21) == pytest.approx(get_vehicle("racing25").hover_rotor_speed_rad_s, rel=1e-3)
    assert law.command_for_speed(law.speed_rad_s(0.37)) == pytest.approx(0.37)
    f = motor_law("racing5", 0.055)  # proportional to the ESC output: full output at sqrt(T_max / c_T)
    assert f.speed_rad_s(1.0) == pytest.approx(math.sqrt(13.4 / 1.562522e-6))
    assert f.speed_rad_s(0.0) == pytest.approx(0.055 * f.speed_rad_s(1.0))


def test_bf_motor_order_maps_onto_the_model_rotors():
    from sim.vehicles import get_vehicle

    # Betaflight 1 rear-right, 2 front-right, 3 rear-left, 4 front-left (x forward, y left)
    want = [(-1, -1), (1, -1), (-1, 1), (1, 1)]
    xy = get_vehicle("racing5").params.rotor_xy_m
    for j, (sx, sy) in enumerate(want):
        x, y = xy[ROTOR_OF_BF_MOTOR[j]]
        assert np.sign(x) == sx and np.sign(y) == sy


def test_fake_firmware_hovers_level_and_the_flight_is_deterministic(tmp_path):
    opts = FwFlightOptions(scenario="hover", vehicle="racing25", duration_s=2.0, seed=3)
    a = fly_firmware(opts, FakeBetaflight())
    b = fly_firmware(opts, FakeBetaflight())
    s = a.scores(opts.settle_s)
    assert not s["crashed"]
    # bound: the sticks are whole microseconds, 1/500 of a half range = 0.14 deg/s at the ACTUAL
    # curve's 70 deg/s centre; the pilot's attitude loop (racing25: 6 /s) leaves a dead zone of
    # 0.14 / 2 / 6 = 0.012 deg, and its limit cycle with the firmware's I term a few of those; the
    # rigid-body vibration angle (0.01 rad/s at 327 Hz: 3e-4 deg) and the gyro noise through the
    # attitude loop (N / sqrt(2 K) = 4.9e-5 / sqrt(12) rad: 8e-4 deg) are far below. 0.1 deg = 8
    # dead zones.
    assert s["hover_att_rms_deg"] < 0.1
    assert s["altitude_error_rms_m"] < 0.05
    fa, fb = tmp_path / "a.csv", tmp_path / "b.csv"
    write_csv(to_recording(a), fa)
    write_csv(to_recording(b), fb)
    assert fa.read_bytes() == fb.read_bytes()
    head = fa.read_text().splitlines()
    assert any(h.startswith("# motor_order: betaflight quad-X") for h in head)
    cols = next(h for h in head if h.startswith("t_s,")).split(",")
    for c in ("fw_gyro_x_rad_s", "motor_1", "motor_4", "ref_x_rad_s", "rate_sp_x_rad_s", "rc_throttle_us"):
        assert c in cols


def test_rate_pulses_are_flown_as_stick_steps():
    opts = FwFlightOptions(scenario="steps", vehicle="racing25", duration_s=3.0, seed=1)
    log = fly_firmware(opts, FakeBetaflight())
    s = log.scores(opts.settle_s)
    assert not s["crashed"]
    assert [x["axis"] for x in s["steps"]] == ["roll", "roll", "pitch", "pitch", "yaw", "yaw"]
    # the fake's rate loop (Betaflight's default P on racing25's inertia) reaches 90 % of a
    # 115 deg/s step well inside the 0.08-s pulse
    for x in s["steps"]:
        assert np.isfinite(x["rise_s"]) and x["rise_s"] < 0.06
    # during a pulse the stick on its axis is the pulse alone
    p = log.manoeuvres[0]
    k = np.flatnonzero((log.t_s >= p.t_start_s + 0.01) & (log.t_s < p.t_start_s + p.duration_s))
    assert np.allclose(log.rate_sp_rad_s[k, p.axis], p.rate_rad_s)


def test_bad_scenario_and_short_steps_are_one_error_line():
    with pytest.raises(GyroInputError, match="unknown firmware flight scenario"):
        FwFlightOptions(scenario="loop")
    with pytest.raises(GyroInputError, match="steps scenario needs"):
        rate_pulses(1.8, 1.0)
