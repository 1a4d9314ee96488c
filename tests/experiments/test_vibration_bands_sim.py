"""Spec round trip of an energy band: band → ``simulate --vibration SPEC`` → ``vibration`` finds it again.

The spec is written from the synthetic swept-rotor flight of tests/gyrocore/flight/test_vibration_bands.py
(a line sweeping ±15 % within each window); its throttle band 2 (command 0.4: the line sweeps
221-299 Hz) is simulated by ``gyroharness simulate static --vibration SPEC --vibration-band 2`` (the
registry effect ``vibration``'s shaped part, a Gaussian disturbance with the band's PSD) and the
simulated recording is analysed again.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from gyrocore.data.recording import read_csv
from gyrocore.flight.vibration import analyse, read_spec, write_spec
from tests.gyrocore.flight.test_vibration_bands import EDGES, swept_flight

BAND = 2


def test_energy_band_survives_the_spec_round_trip(tmp_path):
    res = analyse(swept_flight(1), band_edges=list(EDGES))
    p = tmp_path / "spec.json"
    write_spec(res, p, source="synthetic swept rotor line")
    spec_band = read_spec(p)["bands"][BAND]["energy_bands"][0]
    assert spec_band["axis"] == "y"
    out = tmp_path / "sim.csv"
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
            str(p),
            "--vibration-band",
            str(BAND),
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert cp.returncode == 0, cp.stderr
    rec = read_csv(out)
    # the injection says it carries the whole band (below the spec's reliable limit)
    carried = json.loads(rec.meta["vibration_injection"])["energy_bands"][0]
    assert carried["carried_fraction"] == pytest.approx(1.0, rel=1e-9)
    sim = analyse(rec)
    top = sim.energy_bands[0]
    assert top["axis"] == "y"
    # centre and power: the simulation draws a fresh Gaussian disturbance with the spec band's
    # PSD (its expectation), so the two estimates differ by the two sampling errors: within
    # 1.96 x their combined standard error (from each one's window spread); the sensor's own
    # white noise adds < 0.1 % of the band's power inside its extent (icm42688p ARW against the
    # band's density, 200x the floor)
    se_c = math.hypot(top["centre_se_hz"], spec_band["centre_se_hz"])
    assert abs(top["centre_hz"] - spec_band["centre_hz"]) <= 1.96 * se_c, (
        top["centre_hz"],
        spec_band["centre_hz"],
        se_c,
    )
    se_p = math.hypot(top["power_se"], spec_band["power_se"])
    assert abs(top["power_rad2_s2"] - spec_band["power_rad2_s2"]) <= 1.96 * se_p + 1e-3 * spec_band["power_rad2_s2"]
    # edges: both are the half-height crossings of the same expected spectrum; a crossing moves by
    # sd(S̃)/|dS̃/df|. sd(S̃)/S̃ ≤ √(2/ν) (one bin of ν = 2K/1.056 degrees of freedom; the 11-bin
    # median and mean only reduce it); the edge of a swept band rises over at most its
    # instantaneous bandwidth √β (β = 2W/T the sweep rate), so at the half-height crossing
    # |dS̃/df| ≥ S̃/√β and the crossing moves by at most √(2/ν)·√β per estimate: 3 SD of the
    # two estimates combined
    w = spec_band["width_hz"]
    sqrt_beta = math.sqrt(2 * w / 0.9)
    for got, ref, k in ((top, spec_band, 0), (top, spec_band, 1)):
        nu_sim = 2 * sim.n_windows / 1.056
        nu_spec = 2 * res.bands[BAND]["n_windows"] / 1.056
        tol = 3 * math.hypot(math.sqrt(2 / nu_sim), math.sqrt(2 / nu_spec)) * sqrt_beta
        assert abs(got["edges_hz"][k] - ref["edges_hz"][k]) <= tol, (k, got["edges_hz"], ref["edges_hz"], tol)
