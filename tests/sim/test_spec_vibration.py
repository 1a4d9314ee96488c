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
        {
            "axis": "x",
            "frequency_hz": 300.0,
            "follows": "throttle",
            "aliased": False,
            "harmonic": None,
            "amplitude_rad_s": amp_x,
            "law": {"hz_at_zero": 180.0, "hz_per_unit": 400.0},
            "per_band": [{"band": 0, "frequency_hz": 260.0, "amplitude_rad_s": amp_x}],
        },
        # the same line seen on y in band 0 (within 6 %), flagged aliased on its own: still counted there
        {
            "axis": "y",
            "frequency_hz": 250.0,
            "follows": "throttle",
            "aliased": True,
            "harmonic": None,
            "amplitude_rad_s": 0.2,
            "per_band": [{"band": 0, "frequency_hz": 265.0, "amplitude_rad_s": amp_y}],
        },
        # a weaker throttle line and a fixed one: not the rotor line
        {
            "axis": "z",
            "frequency_hz": 420.0,
            "follows": "throttle",
            "aliased": False,
            "harmonic": None,
            "amplitude_rad_s": 0.01,
            "per_band": [],
        },
        {
            "axis": "z",
            "frequency_hz": 150.0,
            "follows": "fixed",
            "aliased": False,
            "harmonic": None,
            "amplitude_rad_s": 0.5,
            "per_band": [],
        },
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
    assert v.imbalance_kg_m + v.hub_moment_kg_m2 > 0 and info["vehicle"] == "racing5" and info["band"] == 0
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


def test_hub_moment_puts_the_rotor_line_on_roll_and_pitch():
    # A rotating moment U Omega² in each rotor plane (couple / aerodynamic unbalance) drives the
    # frame about x and y: rate amplitude M / (J Omega) per rotor, so with four rotors of
    # independent phases the mean line power per axis is E[P_i] = 4 (U Omega / J_i)² / 2 =
    # 2 U² Omega² / J_i² (rigid body; the rate loop's crossover, 9 rad/s, is far below Omega =
    # 882 rad/s). No yaw: the moment has no z component. Mean over 12 seeded 2-s hovers within
    # 3 Monte Carlo SE (the per-flight power of a 4-phasor sum scatters ~100 %).
    from sim.vehicles import VibrationSpec
    from sim.vehicles import get_vehicle

    J = get_vehicle("racing5").params.inertia_kg_m2
    U = 2e-9
    vib = VibrationSpec(imbalance_kg_m=0.0, harmonic2_ratio=0.0, blade_pass_ripple=0.0, hub_moment_kg_m2=U)
    P, W = [], []
    for s in range(12):
        truth, log = fly_hover(duration_s=2.0, vehicle="racing5", vibration=vib, seed=100 + s)
        w = float(np.abs(log.rotor_speed_rad_s[500:]).mean())
        a = line_amplitude_in_gyro(truth.omega_S_rad_s[500:], 1000.0, w / (2 * math.pi))
        P.append(a**2 / 2.0)
        W.append(w)
    P = np.asarray(P)
    m, se = P.mean(axis=0), P.std(axis=0, ddof=1) / math.sqrt(len(P))
    theory = 2 * U**2 * np.mean(W) ** 2 / np.asarray(J[:2]) ** 2
    assert np.all(np.abs(m[:2] - theory) <= 3 * se[:2])
    assert m[2] < 1e-9 * m[:2].sum()
    # the static unbalance alone (the earlier model) loads yaw: per rotor the roll/pitch share is
    # (h/d)² (J_z/J_x)² ≈ (1.5 mm / 110 mm)² · 3.8 ≈ 1e-3 (moment arm of the rotor height h above the
    # centre of mass against the arm d); one flight's four yaw contributions partly cancel (random
    # phases), so the bound is z > 90 % of the line power
    vib_u = VibrationSpec(imbalance_kg_m=5e-7, harmonic2_ratio=0.0, blade_pass_ripple=0.0)
    truth, log = fly_hover(duration_s=2.0, vehicle="racing5", vibration=vib_u, seed=100)
    a = line_amplitude_in_gyro(truth.omega_S_rad_s[500:], 1000.0, np.mean(W) / (2 * math.pi))
    assert a[2] ** 2 > 0.9 * (a**2).sum()


@pytest.mark.slow
def test_mean_line_power_matches_the_spec():
    # The calibration's mean line powers (16 hovers per source) and a check's (16 other seeds)
    # each carry a Monte Carlo error (relative SE of the mean power, reported / computed); the
    # check's mean power on roll+pitch and on yaw must match the spec's within 1.96 x the combined
    # SE (log scale, delta method). The spec's line is on x and y: it goes to the hub moment.
    spec = _spec()
    spec["lines"][2]["per_band"] = [{"band": 0, "frequency_hz": 262.0, "amplitude_rad_s": 0.02}]  # a z part too
    v, info = vibration_from_spec(spec, "racing5", band=0, seed=1, calib_s=3.0, n_calib=16)
    assert v.hub_moment_kg_m2 > 0 and v.imbalance_kg_m > 0
    target = np.asarray(info["target_power_xy_z"])
    p = []
    for s in range(16):
        truth, log = fly_hover(duration_s=3.0, vehicle="racing5", vibration=v, seed=1000 + s)
        a = line_amplitude_in_gyro(truth.omega_S_rad_s[1000:], 1000.0, info["sim_rotor_hz"])
        p.append([float((a[:2] ** 2).sum() / 2.0), float(a[2] ** 2 / 2.0)])
    p = np.array(p)
    se_check = p.std(axis=0, ddof=1) / math.sqrt(len(p)) / p.mean(axis=0)
    se = np.hypot(se_check, info["calibration_power_se_rel"])
    assert np.all(np.abs(np.log(p.mean(axis=0) / target)) <= 1.96 * se)


def _spec_file(tmp_path, *, with_rotor_line=True):
    """A spec file with a flat 1e-4 (rad/s)²/Hz band PSD 0..500 Hz and the rotor line of _spec()."""
    import json

    f = np.arange(0.0, 500.5, 1.0)
    s = _spec()
    if not with_rotor_line:
        s["lines"] = [ln for ln in s["lines"] if ln["follows"] == "fixed"]
    for i, b in enumerate(s["bands"]):
        b.update(throttle=[0.1 * i, 0.1 * i + 0.1], n_windows=20, psd_rad2_s2_hz={a: [1e-4] * f.size for a in "xyz"})
    s.update(
        kind="gyroharness.vibration_spec",
        format_version="1.0",
        source="synthetic",
        f_hz=f.tolist(),
        reconstructed_reliable_below_hz=450.0,
    )
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

    from gyrocore.data.recording import read_recording

    spec = _spec_file(tmp_path)
    out = tmp_path / "r.csv"
    code, _, err = _run(
        [
            "simulate",
            "hover",
            "--vehicle",
            "racing5",
            "--vibration",
            str(spec),
            "--vibration-physics",
            "--vibration-band",
            "0",
            "--duration-s",
            "3",
            "-o",
            str(out),
        ],
        capsys,
    )
    assert code == 0, err
    rec = read_recording(out)
    capsys.readouterr()  # the reader's own notes on the recording are not this command's output
    inj = json.loads(rec.meta["vibration_injection"])
    info = inj["physics"]
    assert info["vehicle"] == "racing5" and info["band"] == 0 and info["imbalance_kg_m"] + info["hub_moment_kg_m2"] > 0
    # the real line's power (260 Hz) is taken out of the shaped part (the physics carries it)
    assert "without the rotor line's power at 260.0 Hz" in inj["shaped"]
    # the shaped part is the registry effect `vibration`, in the sensor's parameters
    assert (
        "vibration" in rec.meta["effects"].split(",")
        and "psd_rad2_s2_hz" in json.loads(rec.meta["params_true"])["vibration"]
    )
    assert rec.meta["vehicle"] == "racing5"
    # no rotor line in the spec, or no --vibration: one error line
    sub = tmp_path / "b"
    sub.mkdir()
    bad = _spec_file(sub, with_rotor_line=False)
    code, _, err = _run(
        [
            "simulate",
            "hover",
            "--vehicle",
            "racing5",
            "--vibration",
            str(bad),
            "--vibration-physics",
            "--duration-s",
            "3",
            "-o",
            str(tmp_path / "x.csv"),
        ],
        capsys,
    )
    assert code != 0 and "no line that follows throttle or eRPM" in err and err.count("\n") == 1
    code, _, err = _run(
        ["simulate", "hover", "--vibration-physics", "--duration-s", "3", "-o", str(tmp_path / "y.csv")], capsys
    )
    assert code != 0 and "--vibration-physics needs --vibration SPEC" in err and err.count("\n") == 1


def test_shaped_part_without_the_line_keeps_the_floor():
    """shaped_params(subtract_lines=...): the line's power leaves the band's PSD at the line, the
    broadband around and under it stays (a flat 1e-4 floor plus a 7-bin bump of 0.02 (rad/s)²)."""
    from gyrocore.flight.synthesis import shaped_params

    s = {
        "f_hz": list(np.arange(0.0, 400.5, 1.0)),
        "reconstructed_reliable_below_hz": 380.0,
        "bands": [
            {"throttle": [0, 1], "median": 0.5, "n_windows": 20, "psd_rad2_s2_hz": {a: [1e-4] * 401 for a in "xyz"}}
        ],
    }
    s["bands"][0]["psd_rad2_s2_hz"]["y"] = [1e-4 + (0.02 / 7 if abs(f - 260) <= 3 else 0.0) for f in s["f_hz"]]
    pd = shaped_params(s, band=0, subtract_lines=((260.0, {"x": 0.0, "y": 0.02, "z": 0.0}),))
    f, P = pd["f_hz"], pd["psd_rad2_s2_hz"]
    near = np.abs(f - 260) <= 3
    np.testing.assert_allclose(P[1, near], 1e-4, rtol=1e-9)  # the bump is gone, the floor stays
    np.testing.assert_allclose(P[0], np.where((f >= 40) & (f < 380), 1e-4, 0.0), rtol=1e-12)  # other axes untouched
    # a line weaker than the bump takes only its own power out
    half = shaped_params(s, band=0, subtract_lines=((260.0, {"y": 0.01}),))["psd_rad2_s2_hz"][1]
    assert (half[near].sum() - 7e-4) == pytest.approx(0.01, rel=1e-9)
