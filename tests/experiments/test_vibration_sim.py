"""simulate --vibration SPEC and experiments.vibration_fidelity (issue 16, simulator side)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from gyrocore.recording import Recording, read_csv
from gyrocore.vibration import analyse, write_spec


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
    cp = subprocess.run([sys.executable, "-m", "experiments.cli", "simulate", "static", "-o", str(out), "--duration-s", "40",
                         "--seed", "2", "--vibration", str(spec), "--json"], capture_output=True, text=True, timeout=600)
    assert cp.returncode == 0, cp.stderr
    rec = read_csv(out)
    assert "vibration_injection" in rec.meta
    from experiments.vibration_fidelity import run

    # the still recording without the spec has no vibration; with it, the spec's band is met
    plain = tmp_path / "plain.csv"
    cp = subprocess.run([sys.executable, "-m", "experiments.cli", "simulate", "static", "-o", str(plain), "--duration-s", "40",
                         "--seed", "2"], capture_output=True, text=True, timeout=600)
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
    cp = subprocess.run([sys.executable, "-m", "experiments.cli", "simulate", "static", "-o", str(tmp_path / "x.csv"),
                         "--duration-s", "5", "--vibration", str(spec), "--vibration-band", "7"], capture_output=True,
                        text=True, timeout=600)
    assert cp.returncode != 0 and cp.stderr.strip().startswith("error:") and len(cp.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_closed_loop_flight_filter_with_measured_vibration(tmp_path):
    """experiments.flight_filter: every chain flies (no crash) with the spec's vibration in the
    loop, and filtering lowers the motor noise the unfiltered gyro causes."""
    from experiments.flight_filter import fly
    from gyrocore.vibration import read_spec, synthesize

    spec, _ = _spec(tmp_path)
    d = synthesize(read_spec(spec), n=8001, rate_hz=1000.0, seed=1)
    none = fly([], d, duration_s=8.0, seed=1)
    pt1 = fly([{"kind": "pt1", "cutoff_hz": 60.0, "rate_hz": 8000.0}], d, duration_s=8.0, seed=1)
    assert not none["crashed"] and not pt1["crashed"]
    assert pt1["motor_noise_n"] < none["motor_noise_n"]
    assert pt1["delay_ms"] > none["delay_ms"]


def test_flight_filter_flies_the_racing_class_with_the_rpm_filter():
    """experiments.flight_filter on racing5: the RPM notch on the simulated rotors takes the rotor
    line out of the motor commands (lower motor noise than no filter) at a delay cost."""
    from experiments.flight_filter import fly

    d = np.zeros((4001, 3))
    none = fly([], d, duration_s=4.0, seed=1, vehicle="racing5")
    rpm = fly([], d, duration_s=4.0, seed=1, vehicle="racing5", rpm=True)
    assert not none["crashed"] and not rpm["crashed"]
    assert rpm["chain"] == ["rpm notch x3 Q5"]
    assert rpm["motor_noise_n"] < none["motor_noise_n"]
    assert rpm["delay_ms"] > none["delay_ms"]
