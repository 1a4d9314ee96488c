"""``gyroharness simulate``: writes the data file, refuses to overwrite, one-line errors, JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments.cli import main
from experiments.commands.simulate import parse_set
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import file_sha256, read_csv
from sim.scenarios import simulate


def run(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def test_writes_the_recording_and_json(tmp_path, capsys):
    f = tmp_path / "s.csv"
    code, out, err = run(
        [
            "simulate",
            "static",
            "-o",
            str(f),
            "--duration-s",
            "2",
            "--rate-hz",
            "200",
            "--seed",
            "3",
            "--set",
            "scale.s=0.01,0.02,-0.01",
            "--set",
            "bias_ramp.ramp_rad_s2=1e-4",
            "--without",
            "arw,quantization",
            "--json",
        ],
        capsys,
    )
    assert code == 0, err
    js = json.loads(out)  # only JSON on stdout
    assert js["path"] == str(f) and js["n_samples"] == 400 and js["sha256"] == file_sha256(f)
    assert js["params_true"]["scale"]["s"] == [0.01, 0.02, -0.01]
    assert "bias_ramp" in js["effects"] and "arw" not in js["effects"] and "quantization" in js["without"]
    rec = read_csv(f)
    # the same as the library call, bit for bit
    res = simulate(
        "static",
        duration_s=2.0,
        gyro_rate_hz=200.0,
        seed=3,
        overrides={"scale": {"s": [0.01, 0.02, -0.01]}, "bias_ramp": {"ramp_rad_s2": 1e-4}},
        without=["arw", "quantization"],
    )
    assert np.array_equal(rec.gyro_rad_s, res.recording.gyro_rad_s)
    assert np.array_equal(rec.ref_rate_rad_s, res.truth.omega_S_rad_s)
    assert rec.meta["scenario"] == "static" and rec.meta["sensor"] == "icm42688p" and rec.meta["seed"] == "3"
    assert json.loads(rec.meta["params_true"])["bias_ramp"]["ramp_rad_s2"] == [1e-4] * 3


def test_refuses_to_overwrite_without_force(tmp_path, capsys):
    f = tmp_path / "s.csv"
    f.write_text("keep me", encoding="utf-8")
    code, out, err = run(["simulate", "static", "-o", str(f), "--duration-s", "1", "--rate-hz", "100"], capsys)
    assert code == 2 and err.startswith("error:") and "--force" in err and len(err.strip().splitlines()) == 1
    assert f.read_text(encoding="utf-8") == "keep me"
    code, out, err = run(
        ["simulate", "static", "-o", str(f), "--duration-s", "1", "--rate-hz", "100", "--force"], capsys
    )
    assert code == 0 and out.startswith("wrote ")
    assert read_csv(f).n == 100


@pytest.mark.parametrize(
    "args, needle",
    [
        (["nope"], "unknown scenario"),
        (["static", "--sensor", "nope"], "unknown sensor preset"),
        (["static", "--set", "warp.x=1"], "unknown effect"),
        (["static", "--set", "scale.q=1"], "no parameter"),
        (["static", "--set", "scale.s=a"], "not a number"),
        (["static", "--set", "scale.s=1,2"], "needs 1 or 3"),
        (["static", "--without", "nope"], "unknown effect"),
        (["static", "--duration-s", "-1"], "must be > 0"),
        (["turntable", "--duration-s", "8"], "at least"),
    ],
)
def test_one_line_errors(tmp_path, capsys, args, needle):
    f = tmp_path / "x.csv"
    code, out, err = run(["simulate", *args[:1], "-o", str(f), *args[1:]], capsys)
    assert code == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and err.startswith("error:") and needle in err
    assert not f.exists()


def test_parse_set_shapes():
    p = parse_set(
        [
            "g_sensitivity.h_rad_s_per_m_s2=1,2,3,4,5,6,7,8,9",
            "bias_thermal.poly_rad_s=1,2,3,4,5,6",
            "time_offset.tau_s=0.001",
            "bias.turn_on_sigma_rad_s=0.01",
        ]
    )
    assert p["g_sensitivity"]["h_rad_s_per_m_s2"].shape == (3, 3)
    assert p["g_sensitivity"]["h_rad_s_per_m_s2"][1, 0] == 4
    assert p["bias_thermal"]["poly_rad_s"].shape == (3, 2)
    assert float(p["time_offset"]["tau_s"]) == 0.001
    with pytest.raises(GyroInputError):
        parse_set(["scale"])


def test_family_terms_from_set_and_sensor_toml_round_trip(tmp_path, capsys):
    """simulate with a term from --set and one from a sensor TOML -> calibrate -> apply (CLI):
    the parameter file carries both by name and apply leaves the white noise."""
    import math

    from gyrocore.calib.params import load_params

    sigma, rate, dur = 2e-3, 1000.0, 20.0
    toml = tmp_path / "unit.toml"
    toml.write_text(
        'name = "unit"\n[output]\nrate_hz = 1000.0\nfull_scale_dps = 2000.0\nsensitivity_lsb_per_dps = 16.4\n'
        f"[arw]\ndensity_dps_per_sqrt_hz = {sigma / math.sqrt(rate) * 180 / math.pi!r}\n"
        '["periodic[37.50]"]\na_cos_rad_s = [0.004, 0.0, -0.002]\na_sin_rad_s = 0.001\n',
        encoding="utf-8",
    )
    f = tmp_path / "s.csv"
    code, out, err = run(
        [
            "simulate",
            "static",
            "-o",
            str(f),
            "--sensor",
            str(toml),
            "--duration-s",
            str(dur),
            "--seed",
            "2",
            "--set",
            "step[12.5].size_rad_s=0.003,0,-0.001",
            "--json",
        ],
        capsys,
    )
    assert code == 0, err
    js = json.loads(out)
    assert js["params_true"]["periodic[37.5]"]["a_sin_rad_s"] == [0.001] * 3
    assert js["params_true"]["step[12.5]"]["size_rad_s"] == [0.003, 0.0, -0.001]
    rec = read_csv(f)
    res = simulate(
        "static",
        sensor=str(toml),
        duration_s=dur,
        seed=2,
        overrides={"step[12.50]": {"size_rad_s": [0.003, 0.0, -0.001]}},
    )
    assert np.array_equal(rec.gyro_rad_s, res.recording.gyro_rad_s)
    p = tmp_path / "p.json"
    code, out, err = run(
        ["calibrate", str(f), "--effects", "bias,periodic[37.5],step[12.5]", "-o", str(p), "--json"], capsys
    )
    assert code == 0, err
    cal = load_params(p)
    assert cal.effects == ("bias", "periodic[37.5]", "step[12.5]")
    z = (cal.params["step[12.5]"]["size_rad_s"] - [0.003, 0.0, -0.001]) / cal.stderr["step[12.5]"]["size_rad_s"]
    assert np.all(np.abs(z) < 4), z  # N(0,1) under white noise (see tests/sim/test_gyro.py)
    g = tmp_path / "c.csv"
    code, out, err = run(["apply", str(f), "--params", str(p), "-o", str(g)], capsys)
    assert code == 0, err
    e = read_csv(g).gyro_rad_s - rec.ref_rate_rad_s
    n = rec.n
    # in-sample: mean square of the residual of a P-parameter fit per axis ~ σ²·χ²_{N−P}/N
    ms = np.mean(e**2, axis=0) / sigma**2
    assert np.all(np.abs(ms - 1) < 4 * math.sqrt(2 / n) + 4 / n), ms


@pytest.mark.parametrize(
    "args, needle",
    [
        (["static", "--set", "periodic[abc].a_cos_rad_s=1"], "decimal number"),
        (["static", "--set", "periodic[5].coef=1"], "no parameter 'coef'"),
        (["static", "--set", "regressor[omega_q].coef=1"], "unknown signal"),
        (["static", "--set", "periodic[5]a_cos_rad_s=1"], "effect.param=value"),
    ],
)
def test_family_term_errors_are_one_line(tmp_path, capsys, args, needle):
    f = tmp_path / "x.csv"
    code, out, err = run(["simulate", *args[:1], "-o", str(f), *args[1:]], capsys)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1 and needle in err, err


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_streamed_file_equals_the_whole_write(tmp_path, capsys, suffix):
    """Issue 13: the command writes chunk by chunk; the file holds exactly what writing
    simulate()'s whole recording gives (CSV: the same bytes)."""
    from gyrocore.data.recording import read_recording, write_recording

    f = tmp_path / f"s{suffix}"
    code, out, err = run(
        ["simulate", "power_cycles", "-o", str(f), "--duration-s", "150", "--rate-hz", "500", "--seed", "5", "--json"],
        capsys,
    )
    assert code == 0, err
    js = json.loads(out)
    assert js["n_samples"] == 75_000 and js["power_ups"] == 5  # [power] cycles = 5
    ref = tmp_path / f"ref{suffix}"
    write_recording(simulate("power_cycles", duration_s=150.0, gyro_rate_hz=500.0, seed=5).recording, ref)
    if suffix == ".csv":
        assert f.read_bytes() == ref.read_bytes()
    a, b = read_recording(f), read_recording(ref)
    assert (
        a.meta == b.meta
        and np.array_equal(a.gyro_rad_s, b.gyro_rad_s)
        and np.array_equal(a.ref_quat_wxyz, b.ref_quat_wxyz)
    )


@pytest.mark.parametrize("chunk_rows", ["700", "16384"])
def test_hover_file_is_the_whole_write_for_any_chunk_rows(tmp_path, capsys, chunk_rows):
    """Issue 13: `simulate hover` flies and writes block by block (--chunk-rows); the CSV is the
    whole-array path's byte for byte (ground phase, take-off and manoeuvres in 16 s)."""
    from gyrocore.data.recording import write_recording

    f = tmp_path / "h.csv"
    code, out, err = run(
        ["simulate", "hover", "-o", str(f), "--duration-s", "16", "--seed", "2", "--chunk-rows", chunk_rows, "--json"],
        capsys,
    )
    assert code == 0, err
    ref = tmp_path / "ref.csv"
    write_recording(simulate("hover", duration_s=16.0, seed=2).recording, ref)
    assert f.read_bytes() == ref.read_bytes()
