"""Parquet as a second data-file format, chosen by the file name in every command."""

from __future__ import annotations

import json

import numpy as np

from gyrocore.cli import build_group, run_cli
from gyrocore.data.recording import Recording, is_parquet, read_csv, read_recording, write_csv


def _still(n=6000, rate_hz=200.0, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    return Recording(
        t_s=t,
        gyro_rad_s=rng.normal(0, 0.002, (n, 3)) + [0.01, -0.02, 0.005],
        accel_m_s2=rng.normal(0, 0.01, (n, 3)) + [0, 0, 9.81],
        temp_c=np.full(n, 25.0),
        meta={"sensor": "unit 7", "rate_hz": "200"},
    )


def _gh(capsys, *argv):
    s = run_cli(build_group(), [str(a) for a in argv])
    out, err = capsys.readouterr()
    assert s == 0, err
    return out


def test_convert_to_parquet_and_back_bit_exact(tmp_path, capsys):
    rec = _still()
    write_csv(rec, tmp_path / "a.csv")
    _gh(capsys, "convert", tmp_path / "a.csv", "-o", tmp_path / "a.parquet")
    assert is_parquet(tmp_path / "a.parquet")
    _gh(capsys, "convert", tmp_path / "a.csv", "-o", tmp_path / "b.bin", "--to", "parquet")
    assert open(tmp_path / "b.bin", "rb").read(4) == b"PAR1"
    _gh(capsys, "convert", tmp_path / "a.parquet", "-o", tmp_path / "c.csv")
    back = read_csv(tmp_path / "c.csv")
    assert np.array_equal(back.gyro_rad_s, rec.gyro_rad_s) and np.array_equal(back.accel_m_s2, rec.accel_m_s2)
    assert back.meta == rec.meta
    assert read_recording(tmp_path / "a.parquet").meta == rec.meta


def test_every_command_reads_parquet_like_csv(tmp_path, capsys):
    rec = _still()
    write_csv(rec, tmp_path / "a.csv")
    _gh(capsys, "convert", tmp_path / "a.csv", "-o", tmp_path / "a.parquet")
    for cmd, extra in (("bias", []), ("allan", []), ("loop", ["--effects", "bias"])):
        a = json.loads(_gh(capsys, cmd, tmp_path / "a.csv", *extra, "--json"))
        b = json.loads(_gh(capsys, cmd, tmp_path / "a.parquet", *extra, "--json"))
        if cmd == "bias":
            assert a["bias_rad_s"] == b["bias_rad_s"]
        elif cmd == "allan":
            assert a["axes"]["x"]["arw_rad_per_sqrt_s"] == b["axes"]["x"]["arw_rad_per_sqrt_s"]
        else:
            assert a["found"] == b["found"]
    _gh(capsys, "calibrate", tmp_path / "a.parquet", "--effects", "bias", "-o", tmp_path / "p.json")
    _gh(capsys, "apply", tmp_path / "a.parquet", "--params", tmp_path / "p.json", "-o", tmp_path / "o.parquet")
    assert is_parquet(tmp_path / "o.parquet") and read_recording(tmp_path / "o.parquet").n == rec.n
