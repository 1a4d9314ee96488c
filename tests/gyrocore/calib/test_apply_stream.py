"""Streamed ``apply`` (chunk by chunk, with neighbour context) equals the whole-record apply."""

from __future__ import annotations

import dataclasses
import json
import warnings

import numpy as np
import pytest

from gyrocore.cli import build_group, run_cli
from gyrocore.errors import RepairWarning
from gyrocore.calibrator import Calibrator
from gyrocore.calib.params import load_params, save_params
from gyrocore.data.recording import Recording, read_csv, read_recording, write_recording


def _recording(n=3000, rate_hz=200.0, seed=0):
    rng = np.random.default_rng(seed)
    t = 5.0 + np.arange(n) / rate_hz  # does not start at 0: time since power-up must come from the file
    ref = np.zeros((n, 3))
    ref[:, 2] = np.sin(2 * np.pi * 0.3 * t)
    ref[:, 0] = 0.5 * np.cos(2 * np.pi * 0.2 * t)
    temp = 20.0 + 15.0 * (t - t[0]) / (t[-1] - t[0]) + 0.5 * np.sin(t)
    g = ref + [0.01, -0.02, 0.005] + rng.normal(0, 0.002, (n, 3))
    a = rng.normal(0, 0.01, (n, 3)) + [0, 0, 9.81]
    return Recording(t_s=t, gyro_rad_s=g, accel_m_s2=a, temp_c=temp, ref_rate_rad_s=ref, meta={"sensor": "t"})


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_streamed_apply_is_bit_identical_to_whole_record(tmp_path, capsys, suffix):
    rec = _recording()
    src = tmp_path / f"in{suffix}"
    write_recording(rec, src)
    res = Calibrator(effects=("bias", "bias_thermal", "scale")).fit(read_csv(_csv(tmp_path, rec)))
    # every term that needs neighbours or the power-up time, with sizes beyond the fit
    params = dict(res.params)
    params["bias_temp_rate"] = {"k_rad_s_per_c_per_s": np.array([1e-3, -2e-3, 5e-4])}
    params["bias_ramp"] = {"ramp_rad_s2": np.array([1e-5, 0.0, -2e-5])}
    params["time_offset"] = {"tau_s": np.asarray(0.012)}  # 2.4 samples
    bt = dict(params["bias_thermal"])
    bt["temp_max_c"] = np.asarray(30.0)  # part of the file is outside the range: one warning for the file
    params["bias_thermal"] = bt
    res = dataclasses.replace(res, params=params, effects=tuple(params))
    save_params(res, tmp_path / "p.json")
    res = load_params(tmp_path / "p.json")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RepairWarning)
        whole = res.apply(read_recording(src, checks=False))
    out = tmp_path / f"out{suffix}"
    s = run_cli(
        build_group(),
        ["apply", str(src), "--params", str(tmp_path / "p.json"), "-o", str(out), "--chunk-rows", "137", "--json"],
    )
    cap = capsys.readouterr()
    assert s == 0, cap.err
    warn = [ln for ln in cap.err.splitlines() if ln.startswith("warning:")]
    assert len(warn) == 1 and "outside the calibrated range" in warn[0], cap.err
    got = read_recording(out, checks=False)
    assert np.array_equal(got.gyro_rad_s, whole.gyro_rad_s)
    assert np.array_equal(got.t_s, rec.t_s) and np.array_equal(got.temp_c, rec.temp_c)
    d = json.loads(cap.out)
    assert d["n_samples"] == rec.n
    assert np.allclose(
        d["mean_correction_rad_s"], np.mean(rec.gyro_rad_s - whole.gyro_rad_s, axis=0), rtol=1e-9, atol=0
    )


def _csv(tmp_path, rec):
    p = tmp_path / "fit.csv"
    write_recording(rec, p)
    return p


def test_streamed_power_up_bias_matches_whole(tmp_path, capsys):
    rng = np.random.default_rng(2)
    n = 4000
    t = np.arange(n) / 200.0
    ref = np.zeros((n, 3))
    ref[2000:, 1] = 0.8  # still for 10 s, then turning
    rec = Recording(t_s=t, gyro_rad_s=ref + [0.01, -0.02, 0.005] + rng.normal(0, 0.002, (n, 3)), ref_rate_rad_s=ref)
    write_recording(rec, tmp_path / "a.csv")
    res = Calibrator(effects=("bias", "scale")).fit(rec)
    save_params(res, tmp_path / "p.json")
    res = load_params(tmp_path / "p.json")
    whole = res.apply(rec, power_up_bias=True)
    s = run_cli(
        build_group(),
        [
            "apply",
            str(tmp_path / "a.csv"),
            "--params",
            str(tmp_path / "p.json"),
            "-o",
            str(tmp_path / "o.csv"),
            "--power-up-bias",
            "--chunk-rows",
            "2500",
            "--json",
        ],
    )
    cap = capsys.readouterr()
    assert s == 0, cap.err
    got = read_csv(tmp_path / "o.csv", checks=False)
    assert np.array_equal(got.gyro_rad_s, whole.gyro_rad_s)
    assert got.meta["power_up_bias_rad_s"] == whole.meta["power_up_bias_rad_s"]


def test_streamed_apply_with_family_terms_is_bit_identical(tmp_path, capsys):
    """Registry family terms (time, rate, rate-derivative, temperature-rate regressors) need the
    reach gyrocore.effects.registry.context_rows gives; the streamed apply equals the whole-record one."""
    rec = _recording()
    src = tmp_path / "in.csv"
    write_recording(rec, src)
    res = Calibrator(effects=("bias", "scale")).fit(read_csv(src))
    params = dict(res.params)
    params["time_offset"] = {"tau_s": np.asarray(0.012)}
    params["periodic[7.5]"] = {"a_cos_rad_s": np.array([1e-3, 0, 0]), "a_sin_rad_s": np.array([0, 2e-3, 0])}
    params["step[12.25]"] = {"size_rad_s": np.array([0, 0, 3e-3])}
    params["regressor[alpha_z]"] = {"coef": np.array([2e-3, 0, -1e-3])}
    params["regressor[omega_x*omega_z]"] = {"coef": np.array([0, 1e-3, 0])}
    params["regressor[t]"] = {"coef": np.array([1e-5, 0, 0])}
    params["regressor[dtemp_dt]"] = {"coef": np.array([0, 0, 1e-3])}
    res = dataclasses.replace(res, params=params, effects=tuple(params))
    save_params(res, tmp_path / "p.json")
    res = load_params(tmp_path / "p.json")
    whole = res.apply(read_recording(src, checks=False))
    out = tmp_path / "out.csv"
    s = run_cli(
        build_group(), ["apply", str(src), "--params", str(tmp_path / "p.json"), "-o", str(out), "--chunk-rows", "137"]
    )
    assert s == 0, capsys.readouterr().err
    assert np.array_equal(read_recording(out, checks=False).gyro_rad_s, whole.gyro_rad_s)
