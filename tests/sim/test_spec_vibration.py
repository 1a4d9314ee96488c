"""A vibration spec's rotor line entered through the rotor physics (sim/spec_vibration.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gyrocore.errors import GyroInputError
from sim.quadrotor import fly_hover
from sim.spec_vibration import line_amplitude_in_gyro, rotor_line, vibration_from_spec


def _spec(amp_x=0.05, amp_y=0.08) -> dict:
    """A minimal spec (the keys ``gyroharness vibration -o`` writes that rotor_line reads)."""
    bands = [{"median": m} for m in (0.2, 0.3, 0.4)]
    lines = [
        {"axis": "x", "frequency_hz": 300.0, "follows": "throttle", "aliased": False, "harmonic": None,
         "amplitude_rad_s": amp_x, "law": {"hz_at_zero": 180.0, "hz_per_unit": 400.0},
         "per_band": [{"band": 0, "frequency_hz": 260.0, "amplitude_rad_s": amp_x}]},
        # the same line seen on y in band 0 (within 6 %), flagged aliased on its own: still counted there
        {"axis": "y", "frequency_hz": 250.0, "follows": "throttle", "aliased": True, "harmonic": None,
         "amplitude_rad_s": 0.2, "per_band": [{"band": 0, "frequency_hz": 265.0, "amplitude_rad_s": amp_y}]},
        # a weaker throttle line and a fixed one: not the rotor line
        {"axis": "z", "frequency_hz": 420.0, "follows": "throttle", "aliased": False, "harmonic": None,
         "amplitude_rad_s": 0.01, "per_band": []},
        {"axis": "z", "frequency_hz": 150.0, "follows": "fixed", "aliased": False, "harmonic": None,
         "amplitude_rad_s": 0.5, "per_band": []},
    ]
    return {"bands": bands, "lines": lines}


def test_rotor_line_per_band():
    s = _spec()
    b0 = rotor_line(s, 0)
    assert b0.frequency_hz == 260.0
    assert b0.amplitude_rad_s == {"x": 0.05, "y": 0.08, "z": 0.0}
    assert b0.total_rad_s == pytest.approx(math.hypot(0.05, 0.08))
    # a band without a per-band entry: frequency from the law at the band median, the line's overall amplitude
    b2 = rotor_line(s, 2)
    assert b2.frequency_hz == pytest.approx(180.0 + 400.0 * 0.4)
    assert b2.amplitude_rad_s == {"x": 0.05, "y": 0.0, "z": 0.0}
    assert rotor_line(s, "middle").band == 1
    with pytest.raises(GyroInputError, match="bands 0..2"):
        rotor_line(s, 5)
    s["lines"] = [ln for ln in s["lines"] if ln["follows"] == "fixed"]
    with pytest.raises(GyroInputError, match="no line that follows throttle or eRPM"):
        rotor_line(s, 0)


def test_line_amplitude_of_a_known_tone():
    # a 140.5-Hz tone of amplitude 0.03 rad/s on z in white noise (sigma 0.01 rad/s per sample,
    # PSD 2e-7 (rad/s)^2/Hz -> the 7 line bins carry 1.4e-6 of noise power, taken out by the baseline
    # to its median's scatter, ~ 0.1 % of the tone's 4.5e-4): amplitude within 1 %
    rng = np.random.default_rng(1)
    t = np.arange(20_000) / 1000.0
    x = 0.01 * rng.standard_normal((t.size, 3))
    x[:, 2] += 0.03 * np.cos(2 * math.pi * 140.5 * t + 0.4)
    a = line_amplitude_in_gyro(x, 1000.0, 140.5)
    assert a[2] == pytest.approx(0.03, rel=1e-2)
    assert a[0] < 2e-3 and a[1] < 2e-3


def test_spec_line_appears_at_the_commanded_rotor_frequency():
    v, info = vibration_from_spec(_spec(), "racing5", band=0, seed=3, calib_s=2.0, n_calib=2)
    assert v.imbalance_kg_m > 0 and info["vehicle"] == "racing5" and info["band"] == 0
    truth, log = fly_hover(duration_s=3.0, vehicle="racing5", vibration=v, seed=11)
    k0 = 1000
    f_cmd = float(np.abs(log.rotor_speed_rad_s[k0:]).mean()) / (2 * math.pi)
    from scipy import signal

    f, p = signal.welch(truth.omega_S_rad_s[k0:], fs=1000.0, nperseg=1000, axis=0)
    ptot = p.sum(axis=1)
    band = (f > 100.0) & (f < 200.0)  # around the 140.5-Hz racing5 rotor line, below its 2nd harmonic
    f_peak = f[band][np.argmax(ptot[band])]
    assert abs(f_peak - f_cmd) <= 1.0  # the Welch resolution, fs / nperseg
    assert abs(f_cmd - info["sim_rotor_hz"]) <= 1.0


@pytest.mark.slow
def test_mean_line_power_matches_the_spec():
    # The calibration's mean line power (16 hovers) and a check's (16 other seeds) each carry a
    # Monte Carlo error (relative SE of the mean power, reported / computed); the check's mean
    # must match the spec's power within 1.96 x the combined SE (log scale, delta method).
    spec = _spec()
    v, info = vibration_from_spec(spec, "racing5", band=0, seed=1, calib_s=3.0, n_calib=16)
    p_spec = info["real_line_total_rad_s"] ** 2 / 2.0
    p = []
    for s in range(16):
        truth, log = fly_hover(duration_s=3.0, vehicle="racing5", vibration=v, seed=1000 + s)
        a = line_amplitude_in_gyro(truth.omega_S_rad_s[1000:], 1000.0, info["sim_rotor_hz"])
        p.append(float((a**2).sum() / 2.0))
    p = np.array(p)
    se_check = p.std(ddof=1) / math.sqrt(p.size) / p.mean()
    se = math.hypot(se_check, info["calibration_power_se_rel"])
    assert abs(math.log(p.mean() / p_spec)) <= 1.96 * se


def _spec_file(tmp_path, *, with_rotor_line=True):
    """A spec file with a flat 1e-4 (rad/s)²/Hz band PSD 0..500 Hz and the rotor line of _spec()."""
    import json

    f = np.arange(0.0, 500.5, 1.0)
    s = _spec()
    if not with_rotor_line:
        s["lines"] = [ln for ln in s["lines"] if ln["follows"] == "fixed"]
    for i, b in enumerate(s["bands"]):
        b.update(throttle=[0.1 * i, 0.1 * i + 0.1], n_windows=20,
                 psd_rad2_s2_hz={a: [1e-4] * f.size for a in "xyz"})
    s.update(kind="gyroharness.vibration_spec", format_version="1.0", source="synthetic", f_hz=f.tolist(),
             reconstructed_reliable_below_hz=450.0)
    p = tmp_path / "spec.json"
    p.write_text(json.dumps(s))
    return p


def _run(argv, capsys):
    from experiments.cli import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def test_simulate_vibration_physics_cli(tmp_path, capsys):
    import json

    from gyrocore.recording import read_recording

    spec = _spec_file(tmp_path)
    out = tmp_path / "r.csv"
    code, _, err = _run(["simulate", "hover", "--vehicle", "racing5", "--vibration", str(spec), "--vibration-physics",
                         "--vibration-band", "0", "--duration-s", "3", "-o", str(out)], capsys)
    assert code == 0, err
    rec = read_recording(out)
    info = json.loads(rec.meta["vibration_physics"])
    assert info["vehicle"] == "racing5" and info["band"] == 0 and info["imbalance_kg_m"] > 0
    # the real line (260 Hz, ± max(3 bins, 6 %) = ± 15.6 Hz) is left out of the shaped part
    assert "without 244.4-275.6 Hz" in rec.meta["vibration_injection"]
    assert rec.meta["vehicle"] == "racing5"
    # no rotor line in the spec, or no --vibration: one error line
    sub = tmp_path / "b"
    sub.mkdir()
    bad = _spec_file(sub, with_rotor_line=False)
    code, _, err = _run(["simulate", "hover", "--vehicle", "racing5", "--vibration", str(bad), "--vibration-physics",
                         "--duration-s", "3", "-o", str(tmp_path / "x.csv")], capsys)
    assert code != 0 and "no line that follows throttle or eRPM" in err and err.count("\n") == 1
    code, _, err = _run(["simulate", "hover", "--vibration-physics", "--duration-s", "3", "-o", str(tmp_path / "y.csv")], capsys)
    assert code != 0 and "--vibration-physics needs --vibration SPEC" in err and err.count("\n") == 1
