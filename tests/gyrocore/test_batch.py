"""``gyroharness batch``: a fleet of simulated units on a Dask LocalCluster; bad files are rows."""

from __future__ import annotations

import json
import os
import warnings

import numpy as np
import pandas as pd
import pytest

from gyrocore.cli import build_group, run_cli
from gyrocore import fleet as B
from gyrocore.data.recording import Recording, write_csv, write_recording

N_UNITS = 20
DURATION_S = 40.0
RATE_HZ = 200.0


def _gh(capsys, *argv):
    with warnings.catch_warnings():
        s = run_cli(build_group(), [str(a) for a in argv])
    out, err = capsys.readouterr()
    return s, out, err


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """20 ICM-42688-P units (static, 40 s at 200 Hz; seeds 0..19) from the preset; unit 07 has
    ~50x the white noise of its preset; plus an empty, a binary and a deg/s-labelled-rad/s file."""
    from sim import scenarios as S

    d = tmp_path_factory.mktemp("fleet")
    spec = S.load_scenario("static")
    for k in range(N_UNITS):
        over = None
        if k == 7:
            over = {"arw": {"n_rad_per_sqrt_s": np.full(3, 2.4e-3)}}  # ~50x the preset's 4.9e-5
        r = S.simulate(spec, sensor="icm42688p", duration_s=DURATION_S, seed=k, gyro_rate_hz=RATE_HZ, overrides=over)
        write_recording(r.recording, d / (f"unit{k:02d}.parquet" if k % 4 == 3 else f"unit{k:02d}.csv"))
    (d / "empty.csv").write_text("")
    (d / "garbage.csv").write_bytes(bytes(range(256)) * 8)
    t = np.arange(2000) / 200.0
    g = np.column_stack([300 * np.sin(t), np.zeros_like(t), np.zeros_like(t)])  # deg/s in rad/s columns
    write_csv(Recording(t_s=t, gyro_rad_s=g), d / "degs.csv")
    return d


def test_batch_allan_fleet_on_local_cluster(fleet, tmp_path, capsys):
    table = tmp_path / "allan.csv"
    s, out, err = _gh(capsys, "batch", "allan", fleet, "-o", table, "--workers", "2", "--json")
    assert not [ln for ln in err.splitlines() if ln.startswith("error:")], err
    summary = json.loads(out)
    assert summary["backend"] == "dask-local" and summary["workers"] == 2
    assert s == 3 and summary["n_failed"] == 3  # exit status = number of failed files
    df = pd.read_csv(table, keep_default_na=False, na_values=[""])
    df["error"] = df["error"].fillna("")
    assert len(df) == N_UNITS + 3
    bad = df.set_index(df["file"].map(os.path.basename))["error"]
    assert "empty file" in bad["empty.csv"] and "binary file" in bad["garbage.csv"]
    assert "probably deg/s" in bad["degs.csv"]
    ok = df[df["error"] == ""]
    assert len(ok) == N_UNITS and ok["sha256"].str.len().eq(64).all()
    # the ARW of the 19 normal units agree; unit 07 (50x the preset's N) is named as the
    # outlier of every axis (robust z >> 3.5), and no other unit is
    arw = ok.set_index(ok["file"].map(os.path.basename))[[f"arw_{a}_rad_per_sqrt_s" for a in "xyz"]]
    normal = arw.drop(index=[f for f in arw.index if f.startswith("unit07")])
    ratio = normal.to_numpy() / np.median(normal.to_numpy())
    # the 19 units share the preset's noise density, so their spread is the estimator's: a
    # relative s.e. of ~3 % per estimate (8000 samples; bench_efficiency: Allan N std over its
    # chi-square spread) -> every one of 57 within 10 % (> 3 s.e.) of the fleet median.
    # (The level itself is 1.10x the datasheet density here: the 1 kHz noise through the
    # 250 Hz low-pass, sampled at 200 Hz, aliases — a simulator fact, not the batch's.)
    assert np.all(np.abs(ratio - 1) < 0.10)
    flagged = {(os.path.basename(o["file"]), o["metric"]) for o in summary["outliers"]}
    for a in "xyz":
        assert ("unit07.parquet", f"arw_{a}_rad_per_sqrt_s") in flagged
    assert all(f == "unit07.parquet" for f, m in flagged if m.startswith("arw_"))
    assert (tmp_path / "allan.png").stat().st_size > 10_000
    # rerun: every successful file is skipped by its hash; the three failures are retried
    s2, out2, _ = _gh(capsys, "batch", "allan", fleet, "-o", table, "--workers", "0", "--json")
    again = json.loads(out2)
    assert s2 == 3 and again["n_skipped"] == N_UNITS and again["n_run"] == 3
    df2 = pd.read_csv(table, keep_default_na=False, na_values=[""])
    assert len(df2) == N_UNITS + 3 and set(df2["sha256"]) == set(df["sha256"])


def test_batch_bias_serial_equals_command_and_glob(fleet, tmp_path, capsys):
    table = tmp_path / "bias.parquet"
    s, out, err = _gh(capsys, "batch", "bias", str(fleet / "unit0*.csv"), "-o", table, "--workers", "0", "--json")
    assert s == 0, err
    df = pd.read_parquet(table)
    assert len(df) == 8  # unit00..09 minus the two Parquet ones (03, 07)
    s, out, _ = _gh(capsys, "bias", fleet / "unit01.csv", "--json")
    one = json.loads(out)
    row = df[df["file"].str.endswith("unit01.csv")].iloc[0]
    assert [row[f"bias_{a}_rad_s"] for a in "xyz"] == one["bias_rad_s"]


def test_batch_calibrate_and_loop_rows(fleet, tmp_path, capsys):
    s, out, err = _gh(
        capsys,
        "batch",
        "calibrate",
        str(fleet / "unit1[0-2].*"),
        "-o",
        tmp_path / "c.csv",
        "--effects",
        "bias",
        "--params-dir",
        tmp_path / "params",
        "--workers",
        "0",
        "--json",
        "--no-plot",
    )
    assert s == 0, err
    df = pd.read_csv(tmp_path / "c.csv")
    assert {"bias.b_rad_s_x", "bias.b_rad_s_x_se", "residual_rms_x_rad_s"} <= set(df.columns)
    assert len(list((tmp_path / "params").glob("*.json"))) == 3
    s, out, err = _gh(
        capsys, "batch", "loop", str(fleet / "unit1[0-1].*"), "-o", tmp_path / "l.csv", "--workers", "0", "--json"
    )
    assert s == 0, err
    df = pd.read_csv(tmp_path / "l.csv", keep_default_na=False)
    assert {"found", "n_found", "residual_rms_after_rad_s"} <= set(df.columns) and (df["error"] == "").all()


def test_disk_full_while_writing_the_table_is_one_error_line(fleet, tmp_path, capsys, monkeypatch):
    import errno

    table = tmp_path / "t.csv"
    table.write_text("precious")
    import gyrocore.data.recording as rc

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(rc.os, "fsync", full)
    s, out, err = _gh(
        capsys, "batch", "bias", str(fleet / "unit01.csv"), "-o", table, "--workers", "0", "--no-resume", "--no-plot"
    )
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert s == 2 and len(lines) == 1 and lines[0].startswith("error:") and "No space left on device" in lines[0]
    assert table.read_text() == "precious"  # nothing half-written
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".t.csv")]  # no temporary left behind


def test_robust_z_flags_only_far_values():
    x = np.array([1.0, 1.1, 0.9, 1.05, 0.95, 1.02, 5.0])
    z = B.robust_z(x)
    assert np.flatnonzero(np.abs(z) > B.OUTLIER_Z).tolist() == [6]
    assert np.all(np.isnan(B.robust_z(np.array([1.0, 2.0, 3.0]))))  # fewer than MIN_FLEET: no verdict
