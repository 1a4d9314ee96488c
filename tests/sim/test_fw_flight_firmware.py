"""Closed-loop flights with the real firmware in the loop (the lockstep Betaflight SITL: the
``firmware_binary`` fixture builds it once per run, and fails in CI when it cannot)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sim.fw_flight import FwFlightOptions

SHORT_S = 2.5


def _cli(argv, capsys):
    from experiments.cli import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err  # 1 s settling + 1.5 s of hover: a few simulated seconds per test


def _fly(binary, **kw):
    from experiments.firmware_fly import fly

    opts = FwFlightOptions(**kw)
    return opts, fly(opts, binary=binary)


def test_hover_with_the_firmware_stays_level(firmware_binary):
    opts, (log, info) = _fly(firmware_binary, scenario="hover", vehicle="racing25", duration_s=SHORT_S, seed=2)
    s = log.scores(opts.settle_s)
    assert not s["crashed"]
    assert info["firmware"].startswith("betaflight")
    # Bound on the hover attitude error, RMS over the steady hover. The pilot flies whole-µs sticks:
    # one µs is 1/500 of the half range, 0.14 deg/s at the ACTUAL curve's 70 deg/s centre, so its
    # attitude loop (racing25: 6 /s) does not correct inside a dead zone of 0.14 / 2 / 6 = 0.012 deg;
    # inside it the attitude drifts with what the firmware's rate loop cannot see (its boot
    # calibration's bias residual, at most half an LSB = 5.3e-4 rad/s: 0.012 deg in 0.4 s) and
    # jitters with the vibration, so it stays within a few dead zones (measured here: 0.007 deg
    # without vibration, 0.016 deg with it). 0.1 deg = 8 dead zones.
    assert s["hover_att_rms_deg"] < 0.1
    assert s["hover_att_max_deg"] < 0.5
    # level and at height: the pilot's altitude loop through the throttle stick
    assert s["altitude_error_rms_m"] < 0.05
    hov = log.hover_mask(opts.settle_s)
    # the firmware drives the rotors (not saturated, above its idle) at the hover command of the
    # log's rotor law, u = 0.21 of the output range (v = 0.055 + 0.945 u = 0.25)
    assert np.all(log.motors[hov] > 0.055) and np.all(log.motors[hov] < 0.95)
    assert np.mean(log.motors[hov]) == pytest.approx(0.055 + 0.945 * 0.21, abs=0.05)
    # the firmware's filtered gyro follows the true rate (its filters pass the flight band)
    assert np.all(np.isfinite(log.fw_gyro_rad_s))
    # the firmware's boot calibration estimated the unit's turn-on bias (it sees the still gyro)
    b = info["boot"]
    assert b["calibration_steps"] > 0
    err = np.abs(np.array(b["bias_estimate_error_rad_s"]))
    # Betaflight averages the still gyro over its calibration (gyro_calib_duration 1.25 s at 8 kHz =
    # 10,000 samples, int16 LSB 1.06e-3 rad/s): the mean's error is the quantisation (<= LSB/2)
    # plus noise / sqrt(10000) (icm42688p: 4.9e-5 rad/s/sqrt(Hz) x sqrt(4000 Hz) / 100 = 3e-5 rad/s)
    assert np.all(err < 1.06e-3 / 2 + 3 * 3.1e-5)


def test_rate_steps_with_the_firmware_are_sane(firmware_binary):
    opts, (log, _) = _fly(firmware_binary, scenario="steps", vehicle="racing25", duration_s=3.0, seed=1)
    s = log.scores(opts.settle_s)
    assert not s["crashed"]
    rp = [x for x in s["steps"] if x["axis"] != "yaw"]
    assert len(rp) == 4
    # A Betaflight rate loop crossing over at omega_c rises (10-90 %) in about 2.2 / omega_c for a
    # first-order closed loop; its default tune crosses over at tens of Hz on a racing quad
    # (omega_c >= 2 pi x 10 /s: rise <= 35 ms); 60 ms is a loop five times slower than that and
    # still flyable. Overshoot below 50 % keeps the phase margin above ~20 deg (second-order
    # approximation, zeta >= 0.2).
    for x in rp:
        assert np.isfinite(x["rise_s"]) and x["rise_s"] < 0.06
        assert x["overshoot_pct"] < 50.0
    assert s["gyro_delay_ms"] is not None and 0.0 < s["gyro_delay_ms"] < 10.0


def test_same_firmware_flight_twice_is_byte_identical(firmware_binary, tmp_path):
    from experiments.firmware_fly import run

    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    ja = run(scenario="hover", out=a, vehicle="racing25", duration_s=1.5, seed=4, binary=firmware_binary)
    jb = run(scenario="hover", out=b, vehicle="racing25", duration_s=1.5, seed=4, binary=firmware_binary)
    assert a.read_bytes() == b.read_bytes()
    assert ja["hover_att_rms_deg"] == jb["hover_att_rms_deg"]
    head = a.read_text().splitlines()[:40]
    assert any(h.startswith("# firmware: betaflight") for h in head)
    cols = next(h for h in head if h.startswith("t_s,")).split(",")
    for c in ("fw_gyro_x_rad_s", "fw_dterm_x_rad_s", "motor_1", "motor_4", "ref_qw", "rate_sp_x_rad_s"):
        assert c in cols


def test_fly_cli_json_and_a_refused_setting(firmware_binary, tmp_path, capsys):
    out = tmp_path / "f.csv"
    code, so, se = _cli(
        [
            "firmware",
            "fly",
            "hover",
            "--duration-s",
            "1.5",
            "--set",
            "gyro_lpf1_static_hz=200",
            "-o",
            str(out),
            "--json",
        ],
        capsys,
    )
    assert code == 0, se
    j = json.loads(so)
    assert j["firmware"].startswith("betaflight") and "set gyro_lpf1_static_hz = 200" in j["settings"]
    assert j["sim_s_per_wall_s"] > 0 and math.isfinite(j["motor_noise_above_20hz"])
    code, so, se = _cli(
        [
            "firmware",
            "fly",
            "hover",
            "--duration-s",
            "1.5",
            "--set",
            "gyro_lpf1_static_hz=9999",
            "-o",
            str(tmp_path / "g.csv"),
        ],
        capsys,
    )
    assert code != 0
    lines = [x for x in se.strip().splitlines() if x.startswith("error:")]
    assert len(lines) == 1 and "gyro_lpf1_static_hz" in lines[0] and "Traceback" not in se
    assert not (tmp_path / "g.csv").exists()


def test_cutoffs_on_the_firmware_short_grid(firmware_binary, tmp_path):
    from experiments.cutoffs import run

    r = run(
        out_dir=tmp_path,
        firmware="betaflight",
        presets=("icm42688p",),
        seeds=1,
        duration_s=2.6,
        kinds=("article",),
        cutoffs=(90.0,),
        binary=firmware_binary,
        vehicle="racing25",
    )
    s = r.summary
    assert s["firmware"].startswith("betaflight")
    p = s["presets"]["icm42688p"]
    assert set(p["firmware"]) == {"none", "article 90 Hz"} and set(p["ours"]) == {"none", "article 90 Hz"}
    assert p["firmware_best"] in p["firmware"]
    assert "betaflight" in r.markdown and "article 90 Hz" in r.markdown
    f, n = p["firmware"]["article 90 Hz"], p["firmware"]["none"]
    # the firmware's PT1 adds its group delay to the measured gyro delay (paired flights): at low
    # frequency Betaflight's discrete PT1 (k = dt / (dt + RC)) delays by (1 - k) / k samples = RC =
    # 1 / (2 pi 90 Hz) = 1.768 ms (1.4 % less at the 15-Hz top of the measuring band); 0.2 ms = 1.6
    # samples of the cross-correlation's interpolated peak
    assert f["delay_ms"] - n["delay_ms"] == pytest.approx(1e3 / (2 * math.pi * 90.0), abs=0.2)
    # and it filters the D term's input: less D-term noise than no gyro filter at all
    assert f["dterm_noise"] < n["dterm_noise"]


@pytest.mark.slow
def test_experiment_cutoffs_firmware_cli_quick(firmware_binary, tmp_path, capsys):
    code, so, se = _cli(
        ["experiment", "cutoffs", "--firmware", "betaflight", "--quick", "--out", str(tmp_path / "rep"), "--json"],
        capsys,
    )
    assert code == 0, se
    j = json.loads(so)
    assert j["summary"]["firmware"].startswith("betaflight")
    assert (tmp_path / "rep" / "report.md").read_text().count("betaflight") >= 2


@pytest.mark.slow
def test_filter_closed_loop_firmware_cli(firmware_binary, shared_data, capsys):
    bbl = shared_data / "betaflight_blackbox" / "better_tune.BBL"
    code, so, se = _cli(
        ["filter-closed-loop", str(bbl), "--firmware", "betaflight", "--seeds", "1", "--duration-s", "3", "--json"],
        capsys,
    )
    assert code == 0, se
    j = json.loads(so)
    assert j["firmware"].startswith("betaflight") and j["as_flown"]["name"] == "as_flown"
    assert j["recommended"]["name"] in j["chains"]
    assert any(x.startswith("set gyro_lpf1") for x in j["tune"])  # the log's own filters reached the firmware
    n = j["chains"]["none"]["motor_noise_pct"]["mean"]
    a = j["chains"]["as_flown"]["motor_noise_pct"]["mean"]
    assert a < n  # the pilot's filters quiet the motors against no gyro filter at all


@pytest.mark.slow
def test_fidelity_against_the_logs_own_filtered_gyro(firmware_binary, shared_data):
    from experiments.firmware_fidelity import run

    out = run(
        flight=str(shared_data / "blackbox_public" / "LOG00037.BFL"),
        vehicle="racing5",
        duration_s=3.0,
        n_calib=4,
        bands={1},
        binary=firmware_binary,
    )
    r = out["bands"][0]
    assert out["settings_applied"] and r["held_out"] is not None
    for a in "xyz":
        h = r["held_out"][a]
        assert (
            np.isfinite(h["rms_sim_rad_s"]) and np.isfinite(h["rms_real_rad_s"]) and 0.0 <= h["in_band_fraction"] <= 1.0
        )
