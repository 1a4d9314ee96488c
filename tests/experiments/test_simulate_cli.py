"""``gyroharness simulate``: writes the data file, refuses to overwrite, one-line errors, JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments.cli import main
from experiments.commands.simulate import parse_set
from gyrocore.errors import GyroInputError
from gyrocore.recording import file_sha256, read_csv
from sim.scenarios import simulate


def run(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def test_writes_the_recording_and_json(tmp_path, capsys):
    f = tmp_path / "s.csv"
    code, out, err = run(["simulate", "static", "-o", str(f), "--duration-s", "2", "--rate-hz", "200",
                          "--seed", "3", "--set", "scale.s=0.01,0.02,-0.01", "--set", "bias_ramp.ramp_rad_s2=1e-4",
                          "--without", "arw,quantization", "--json"], capsys)
    assert code == 0, err
    js = json.loads(out)  # only JSON on stdout
    assert js["path"] == str(f) and js["n_samples"] == 400 and js["sha256"] == file_sha256(f)
    assert js["params_true"]["scale"]["s"] == [0.01, 0.02, -0.01]
    assert "bias_ramp" in js["effects"] and "arw" not in js["effects"] and "quantization" in js["without"]
    rec = read_csv(f)
    # the same as the library call, bit for bit
    res = simulate("static", duration_s=2.0, gyro_rate_hz=200.0, seed=3,
                   overrides={"scale": {"s": [0.01, 0.02, -0.01]}, "bias_ramp": {"ramp_rad_s2": 1e-4}},
                   without=["arw", "quantization"])
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
    code, out, err = run(["simulate", "static", "-o", str(f), "--duration-s", "1", "--rate-hz", "100", "--force"], capsys)
    assert code == 0 and out.startswith("wrote ")
    assert read_csv(f).n == 100


@pytest.mark.parametrize("args, needle", [
    (["nope"], "unknown scenario"),
    (["static", "--sensor", "nope"], "unknown sensor preset"),
    (["static", "--set", "warp.x=1"], "unknown effect"),
    (["static", "--set", "scale.q=1"], "no parameter"),
    (["static", "--set", "scale.s=a"], "not a number"),
    (["static", "--set", "scale.s=1,2"], "needs 1 or 3"),
    (["static", "--without", "nope"], "unknown effect"),
    (["static", "--duration-s", "-1"], "must be > 0"),
    (["turntable", "--duration-s", "8"], "at least"),
])
def test_one_line_errors(tmp_path, capsys, args, needle):
    f = tmp_path / "x.csv"
    code, out, err = run(["simulate", *args[:1], "-o", str(f), *args[1:]], capsys)
    assert code == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and err.startswith("error:") and needle in err
    assert not f.exists()


def test_parse_set_shapes():
    p = parse_set(["g_sensitivity.h_rad_s_per_m_s2=1,2,3,4,5,6,7,8,9", "bias_thermal.poly_rad_s=1,2,3,4,5,6",
                   "time_offset.tau_s=0.001", "bias.turn_on_sigma_rad_s=0.01"])
    assert p["g_sensitivity"]["h_rad_s_per_m_s2"].shape == (3, 3)
    assert p["g_sensitivity"]["h_rad_s_per_m_s2"][1, 0] == 4
    assert p["bias_thermal"]["poly_rad_s"].shape == (3, 2)
    assert float(p["time_offset"]["tau_s"]) == 0.001
    with pytest.raises(GyroInputError):
        parse_set(["scale"])
