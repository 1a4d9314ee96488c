"""simulate --vibration SPEC and experiments.vibration_fidelity (simulator side)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from gyrocore.data.recording import Recording, read_csv
from gyrocore.flight.vibration import analyse, write_spec


def _spec(tmp_path):
    """A spec from a closed-form signal: white noise plus a 180 Hz line on y, one band."""
    rng = np.random.default_rng(3)
    n = 60_000
    t = np.arange(n) / 1000.0
    g = rng.normal(0, 0.01, (n, 3))
    g[:, 1] += 0.05 * np.sin(2 * np.pi * 180.0 * t)
    res = analyse(Recording(t_s=t, gyro_rad_s=g, meta={"source": "synthetic"}))
    p = tmp_path / "spec.json"
    write_spec(res, p, source="synthetic")
    return p, res


def test_simulate_with_vibration_spec_and_fidelity(tmp_path):
    spec, res = _spec(tmp_path)
    out = tmp_path / "static.csv"
    cp = subprocess.run(
        [
            sys.executable,
            "-m",
            "experiments.cli",
            "simulate",
            "static",
            "-o",
            str(out),
            "--duration-s",
            "40",
            "--seed",
            "2",
            "--vibration",
            str(spec),
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert cp.returncode == 0, cp.stderr
    rec = read_csv(out)
    assert "vibration_injection" in rec.meta
    from experiments.vibration_fidelity import run

    # the still recording without the spec has no vibration; with it, the spec's band is met
    plain = tmp_path / "plain.csv"
    cp = subprocess.run(
        [
            sys.executable,
            "-m",
            "experiments.cli",
            "simulate",
            "static",
            "-o",
            str(plain),
            "--duration-s",
            "40",
            "--seed",
            "2",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert cp.returncode == 0, cp.stderr
    fid = run(spec_path=str(spec), hover_path=str(plain), t_from_s=0.0)
    row = fid["rows"][0]
    assert row["before"]["y"]["in_band_fraction"] < 0.2
    # m ≈ 460 bins compared, adjacent Hann bins correlated (≈ m/2 independent): 0.95 − 4 SD
    assert row["after"]["y"]["in_band_fraction"] >= 0.95 - 4 * np.sqrt(0.95 * 0.05 / 230)
    sim = analyse(rec)
    line = [ln for ln in sim.lines if ln["axis"] == "y"]
    assert line and min(abs(ln["frequency_hz"] - 180.0) for ln in line) <= 1.5


def test_simulate_vibration_bad_band_is_one_error(tmp_path):
    spec, _ = _spec(tmp_path)
    cp = subprocess.run(
        [
            sys.executable,
            "-m",
            "experiments.cli",
            "simulate",
            "static",
            "-o",
            str(tmp_path / "x.csv"),
            "--duration-s",
            "5",
            "--vibration",
            str(spec),
            "--vibration-band",
            "7",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert cp.returncode != 0 and cp.stderr.strip().startswith("error:") and len(cp.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_closed_loop_flight_filter_with_measured_vibration(tmp_path):
    """experiments.flight_filter: a chain flies (no crash) with the spec's vibration in the loop (the
    registry effect's shaped part in the gyro stream), and filtering lowers the motor noise the
    unfiltered gyro causes at a delay cost."""
    from experiments.flight_filter import fly
    from gyrocore.flight.vibration import read_spec
    from sim.spec_vibration import spec_injection

    spec, _ = _spec(tmp_path)
    _, shaped, _ = spec_injection(read_spec(spec))
    none, _ = fly([], duration_s=8.0, seed=1, vehicle="f450", shaped=shaped)
    pt1, chain = fly(
        [{"kind": "pt1", "cutoff_hz": 60.0, "rate_hz": 8000.0}], duration_s=8.0, seed=1, vehicle="f450", shaped=shaped
    )
    assert chain == ["pt1 60 Hz"]
    assert np.all(np.isfinite(none.q_WB_wxyz)) and np.all(np.isfinite(pt1.q_WB_wxyz))
    assert pt1.motor_noise_n() < none.motor_noise_n()
    assert pt1.gyro_delay_s() > none.gyro_delay_s()


def test_flight_filter_flies_the_racing_class_with_the_rpm_filter():
    """experiments.flight_filter on racing5: the RPM notch on the simulated rotors takes the rotor
    line out of the motor commands (lower motor noise than no filter) at a delay cost."""
    from experiments.flight_filter import fly

    none, _ = fly([], duration_s=4.0, seed=1, vehicle="racing5")
    rpm, chain = fly([], duration_s=4.0, seed=1, vehicle="racing5", rpm=True)
    assert np.all(np.isfinite(none.q_WB_wxyz)) and np.all(np.isfinite(rpm.q_WB_wxyz))
    assert chain == ["rpm notch x3 Q5"]
    assert rpm.motor_noise_n(t_from_s=1.0) < none.motor_noise_n(t_from_s=1.0)
    assert rpm.gyro_delay_s() > none.gyro_delay_s()


def test_analyse_halves_with_shared_band_edges():
    """vibration on a part of a recording (t_from_s / t_to_s) with another part's band edges: the
    bands line up (same throttle spans) and each half sees only its own windows."""
    rng = np.random.default_rng(4)
    n, fs = 80_000, 1000.0
    t = np.arange(n) / fs
    u = 0.2 + 0.3 * (np.arange(n) // 4000 % 5) / 4.0  # stepped motor command 0.2..0.5
    g = rng.normal(0, 0.01, (n, 3))
    g[:, 0] += 0.05 * np.sin(2 * np.pi * np.cumsum(100.0 + 400.0 * u) / fs)
    rec = Recording(t_s=t, gyro_rad_s=g, meta={"source": "synthetic"}, extra={"motor_cmd_mean": u})
    a = analyse(rec, t_to_s=40.0, n_bands=5)
    edges = [b["throttle"][0] for b in a.bands] + [a.bands[-1]["throttle"][1]]
    b = analyse(rec, t_from_s=40.0, band_edges=edges)
    assert [x["throttle"] for x in b.bands] == [x["throttle"] for x in a.bands]
    # 40 s of 1-s Hann windows at 50 % overlap: 79 windows per half
    assert sum(x["n_windows"] for x in a.bands) == sum(x["n_windows"] for x in b.bands) == 79
    with pytest.raises(Exception, match="band edges must be an increasing"):
        analyse(rec, band_edges=[0.3, 0.2])


def test_simulated_hover_with_a_known_spec_is_recovered(tmp_path):
    """Issue 16 evidence: a hover scenario TOML with a known spec (the registry effect `vibration`,
    rotor physics off so the spec is the only vibration) -> `vibration` recovers the spec's line
    within the frequency resolution, its amplitude within the estimator's interval, and the
    broadband level within its interval. The expected level is known in closed form: the shaped
    part's power ∫S (40 Hz .. the spec's reliable limit; sim.noise.shaped_taps reproduces the grid
    sum exactly) plus the sensor's white noise 2N²·(fs/2 − 40) (one-sided PSD of ARW N) and the
    quantization q²/12 over the band's share of 0..fs/2."""
    import math as _m

    from gyrocore.flight.synthesis import shaped_params
    from gyrocore.flight.vibration import read_spec
    from sim import scenarios as S

    spec_path, spec_res = _spec(tmp_path)
    toml = tmp_path / "hover_spec.toml"
    toml.write_text(
        f'name = "hover_spec"\nkind = "hover"\nduration_s = 40.0\n[hover]\nvibration = false\n'
        f'manoeuvres = false\n[vibration]\nspec = "{spec_path.name}"\nband = 0\n'
    )
    res = S.simulate(str(toml), seed=3)
    rec = res.recording
    assert "vibration" in rec.meta["effects"].split(",") and "vibration_injection" in rec.meta
    sim = analyse(rec, t_from_s=2.0)
    # the line: y at 180 Hz (the spec's), within the resolution; its amplitude inside the interval
    spec_line = max((ln for ln in spec_res.lines if ln["axis"] == "y"), key=lambda ln: ln["amplitude_rad_s"])
    got = [ln for ln in sim.lines if ln["axis"] == "y" and abs(ln["frequency_hz"] - spec_line["frequency_hz"]) <= 1.5]
    assert got, sim.lines
    lo, hi = got[0]["amplitude_interval_rad_s"]
    assert lo <= spec_line["amplitude_rad_s"] <= hi
    # the broadband level on x (no line there): expectation inside the 95 % interval
    pd = shaped_params(read_spec(spec_path), band=0)
    f = pd["f_hz"]
    P_shaped = float(np.sum(pd["psd_rad2_s2_hz"][0]) * (f[1] - f[0]))
    N = float(res.params_true["arw"]["n_rad_per_sqrt_s"][0])
    q = float(res.params_true["quantization"]["lsb_rad_s"])
    band = 500.0 - 40.0
    expect = _m.sqrt(P_shaped + 2 * N * N * band + q * q / 12.0 * band / 500.0)
    lo, hi = sim.rms_above_40hz_interval_rad_s["x"]
    assert lo <= expect <= hi, (lo, expect, hi)


@pytest.mark.slow
def test_closed_loop_recommendation_is_stable_across_noise_seeds(shared_data):
    """gyroharness filter-closed-loop on the shared log (racing25 with the log's own vibration):
    every noise seed (gyro noise, rotor phases, shaped-vibration draw) picks the same chain, it
    meets the as-flown motor-noise budget, and it is reported in firmware parameter names beside
    the pilot's chain and the defaults (DESIGN.md keys)."""
    log = shared_data / "betaflight_blackbox" / "better_tune.BBL"
    if not log.exists():
        pytest.skip("shared blackbox log absent")
    from experiments.flight_filter import run

    out = run(flight=str(log), seeds=(0, 1, 2), duration_s=4.0, n_calib=4, calib_s=2.0)
    assert out["stable"], out["picks_per_seed"]
    r = out["recommended"]
    for k in ("filter", "cutoff_hz", "notches_hz", "attitude_cost", "delay_ms", "motor_noise"):
        assert k in r and k in out["as_flown"]
    assert r["name"] != "none"
    for ps in out["per_seed"]:
        rows = ps["rows"]
        assert rows[ps["pick"]]["motor_noise_n"] <= rows["as_flown"]["motor_noise_n"] * (1 + 1e-9)
        # filtering takes the vibration out of the motors: every low-pass below the unfiltered gyro's noise
        assert rows["as_flown"]["motor_noise_n"] < rows["none"]["motor_noise_n"]
    bf = out["firmware"]["betaflight"]
    assert any(s.startswith("set gyro_lowpass") for s in bf) or bf[0].startswith("#")
    assert set(out["defaults"]) == {"betaflight_default", "px4_default", "ardupilot_default"}


def test_sensor_preset_carries_the_shaped_vibration(tmp_path):
    """A sensor preset TOML's [vibration] spec = "..." (path relative to the TOML) puts the spec
    band's shaped part into every unit of that sensor, as the registry effect's parameters; a bad
    key or a bad scenario [vibration] section is one error line."""
    from gyrocore.errors import GyroInputError
    from gyrocore.flight.synthesis import shaped_params
    from gyrocore.flight.vibration import read_spec
    from sim.gyro import SyntheticGyro
    from sim.presets import load_preset
    from sim.scenarios import load_scenario

    spec_path, _ = _spec(tmp_path)
    base = (
        'name = "vib"\n[output]\nrate_hz = 1000.0\nfull_scale_dps = 2000.0\nsensitivity_lsb_per_dps = 16.4\n'
        "[arw]\ndensity_dps_per_sqrt_hz = 0.0028\n"
    )
    p = tmp_path / "vib.toml"
    p.write_text(base + f'[vibration]\nspec = "{spec_path.name}"\nband = 0\n')
    g = SyntheticGyro(load_preset(str(p)), seed=1)
    want = shaped_params(read_spec(spec_path), band=0)
    np.testing.assert_array_equal(g.params["vibration"]["psd_rad2_s2_hz"], want["psd_rad2_s2_hz"])
    assert "vibration" in g.noise(4000)[1]
    p.write_text(base + f'[vibration]\nspec = "{spec_path.name}"\nbnd = 0\n')
    with pytest.raises(GyroInputError, match=r"unknown key\(s\) in \[vibration\]: bnd"):
        load_preset(str(p))
    sc = tmp_path / "s.toml"
    sc.write_text(
        f'kind = "table"\nduration_s = 5.0\n[table]\nprofile = "static"\n[vibration]\nspec = "{spec_path.name}"\nphysics = true\n'
    )
    with pytest.raises(GyroInputError, match="physics = true needs kind"):
        load_scenario(str(sc))
