"""The residual loop from disk, a window at a time, equals the loop in memory.

The two paths do the same operations on the same numbers except where a window boundary cuts
a running sum or a recursion: the window sums of the regressors are carried across windows
(float addition reassociated: relative error ≲ n·ε ≈ 1e-12 of a sum over n ≈ 10⁴ samples),
the attitude integration restarts each window from the carried, renormalised quaternion (ε per
window), and the time-offset advance fits its not-a-knot spline on each window plus 64 samples
of context (the cut's influence decays as (2 − √3)^64 ≈ 1e-37, below rounding). Propagated
through the least-squares fits (condition number of the window design ≲ 1e3), estimates,
statistics and errors agree to ≲ 1e-9 relative: the tolerance is rtol 1e-8 (one decade of
margin) with atol 1e-12 for values that are differences near zero (RMS reductions,
out-of-sample reductions: ε × the condition number of the quantities they are differences
of). Decisions (effects found, open-search descriptions, frequencies to 1 µHz) must be equal.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

import numpy as np
import pytest

from gyrocore.loop.loop import run_loop
from gyrocore.data.recording import read_csv, write_csv
from gyrocore.data.spill import spill_columns
from gyrocore.calib.stream import NotStreamable, SpilledRecording

RTOL, ATOL = 1e-8, 1e-12


def _record(kind: str, seed: int = 3, duration_s: float = 40.0, rate_hz: float = 200.0):
    from experiments.close_the_loop import OPEN_NOISE, effect_params, inject_open, synthetic_recording

    eff = {
        "bias": effect_params("bias"),
        "time_offset": effect_params("time_offset"),
        "scale": effect_params("scale"),
        "bias_thermal": effect_params("bias_thermal", 3.0),
    }
    rec = synthetic_recording(eff, seed=seed, duration_s=duration_s, rate_hz=rate_hz, **OPEN_NOISE)
    return inject_open(rec, kind, 2e-3)


def _same(x, y, path="", rtol=RTOL, atol=ATOL):
    if isinstance(x, dict):
        assert set(x) == set(y), f"{path}: keys {set(x) ^ set(y)}"
        for k in x:
            _same(x[k], y[k], f"{path}.{k}", rtol, atol)
    elif isinstance(x, (list, tuple)):
        assert len(x) == len(y), path
        for i, (u, v) in enumerate(zip(x, y)):
            _same(u, v, f"{path}[{i}]", rtol, atol)
    elif isinstance(x, (bool, str)) or x is None:
        assert x == y, f"{path}: {x!r} != {y!r}"
    else:
        np.testing.assert_allclose(
            np.asarray(y, float), np.asarray(x, float), rtol=rtol, atol=atol, equal_nan=True, err_msg=path
        )


@pytest.mark.parametrize("kind, chunk", [("periodic", 997), ("step", 1500)])
def test_loop_from_disk_equals_in_memory(tmp_path, kind, chunk):
    # a tumbling 30-s recording with bias, scale, a 3× thermal bias, a time offset (the loop
    # re-linearises it: the gyro advanced by a spline, window by window on disk) and one
    # out-of-catalogue term (a line is removed from the gyro at the sample level: on disk it is
    # subtracted on the fly), coloured noise of every kind; the spilled loop with windows of
    # `chunk` samples (6000 samples: 4–7 windows) against the whole-array loop (the regressor
    # kind: the CLI test below)
    path = tmp_path / "rec.csv"
    write_csv(_record(kind, duration_s=30.0), path)
    rec = read_csv(path)
    mem = run_loop(rec, declared=["bias"], seed=1)
    store = spill_columns(path, tmp_path / "spill", accel=True, groups=("temp", "ref_rate", "ref_quat"))
    disk = run_loop(SpilledRecording(store, chunk_rows=chunk), declared=["bias"], seed=1)
    a, b = mem.to_json(), disk.to_json()
    assert [s["effect"] for s in a["found"]] == [s["effect"] for s in b["found"]]
    assert [u["effect"] for u in a["unexplained"]] == [u["effect"] for u in b["unexplained"]]
    assert "time_offset" in disk.found_effects  # the advance ran on the windows
    if kind == "periodic":
        assert [u.kind for u in disk.unexplained] == ["periodic"]  # the line was held on disk
    _same(a, b)
    assert disk.remaining.allan_adev_rad_s.shape == mem.remaining.allan_adev_rad_s.shape


def test_spilled_residual_rows_equal_the_arrays(tmp_path):
    # the lazy columns, the reference attitude integrated window by window and the window
    # operator applied to lazy rows give the in-memory numbers
    from gyrocore.loop.residual import build_residual

    path = tmp_path / "rec.csv"
    write_csv(_record("none", duration_s=20.0), path)
    rec = read_csv(path)
    store = spill_columns(path, tmp_path / "spill", accel=True, groups=("temp", "ref_rate", "ref_quat"))
    sp = SpilledRecording(store, chunk_rows=777)
    np.testing.assert_array_equal(np.asarray(sp.gyro_rad_s), rec.gyro_rad_s)
    np.testing.assert_array_equal(np.asarray(sp.accel_m_s2), rec.accel_m_s2)
    r_mem, r_disk = build_residual(rec), build_residual(sp)
    assert r_disk.lazy and not r_mem.lazy
    np.testing.assert_array_equal(r_disk.win_start, r_mem.win_start)
    np.testing.assert_allclose(r_disk.y_rad_s, r_mem.y_rad_s, rtol=RTOL, atol=1e-15)
    for eff in ("bias_thermal", "time_offset", "g2_sensitivity", "earth_rate", "regressor[alpha_x*temp_c]"):
        n_m, X_m = r_mem.regressors(eff)
        n_d, X_d = r_disk.regressors(eff)
        assert n_m == n_d
        np.testing.assert_allclose(X_d, X_m, rtol=RTOL, atol=1e-12 * np.max(np.abs(X_m)), err_msg=eff)
    # a time offset: the spline on windows + context equals the whole-record spline
    from gyrocore.loop.model import advance

    adv_m, adv_d = advance(rec, 0.0037), advance(sp, 0.0037)
    np.testing.assert_allclose(np.asarray(adv_d.gyro_rad_s), adv_m.gyro_rad_s, rtol=0, atol=1e-15)


def test_loop_cli_streams_long_files_and_falls_back(tmp_path, monkeypatch, capsys):
    # large files (gyrocore.readers.large) with reference rates take the disk
    # path; the JSON and parameter file equal the in-memory loop's. A reference with NaN rows
    # is not streamed (NotStreamable): the command reads the file whole instead
    from click.testing import CliRunner

    import gyrocore.readers.large as LG
    import gyrocore.loop.loop as L
    from gyrocore.cli.commands.loop import command as main

    monkeypatch.setitem(LG.RULES, "loop", LG.MemoryRule(bytes_per_row=512, budget_bytes=0))
    seen = []
    real = L.run_loop

    def spy(rec, **kw):
        seen.append(type(rec).__name__)
        return real(rec, **kw)

    monkeypatch.setattr(L, "run_loop", spy)
    path = tmp_path / "rec.csv"
    write_csv(_record("regressor", duration_s=30.0), path)
    r = CliRunner().invoke(main, [str(path), "--effects", "bias", "-o", str(tmp_path / "p.json"), "--json"])
    assert r.exit_code == 0, r.output
    assert seen == ["SpilledRecording"]
    mem = real(read_csv(path), declared=["bias"])
    got = json.loads(r.output)
    got.pop("params_file")
    _same(mem.to_json(), json.loads(json.dumps(got)))  # through JSON both ways
    assert json.loads((tmp_path / "p.json").read_text())["effects"]

    rec = read_csv(path)
    rec.ref_rate_rad_s[100:110] = np.nan
    write_csv(rec, tmp_path / "nan.csv")
    seen.clear()
    r = CliRunner().invoke(main, [str(tmp_path / "nan.csv"), "--effects", "bias", "--json"])
    assert r.exit_code == 0, r.output
    assert seen == ["SpilledRecording", "Recording"]
    assert "NaN reference rate excluded" in " ".join(json.loads(r.output)["notes"])


def test_spilled_residual_refuses_what_it_cannot_stream(tmp_path):
    from gyrocore.data.segments import Segment
    from gyrocore.loop.residual import build_residual

    path = tmp_path / "rec.csv"
    write_csv(_record("none", duration_s=10.0), path)
    store = spill_columns(path, tmp_path / "spill", accel=True, groups=("temp", "ref_rate"))
    sp = SpilledRecording(store)
    with pytest.raises(NotStreamable):
        build_residual(sp, reference="still")
    with pytest.raises(NotStreamable):
        build_residual(sp, segments=[Segment.still(0.0, 1.0)])


@pytest.mark.slow
def test_loop_memory_grows_sublinearly(tmp_path):
    # bounded memory, not a timed assertion: the peak RSS of `gyroharness loop` on a 15-column
    # 1 kHz file at two lengths; the in-memory loop grew by ~500 B per sample (1.8 GiB at one
    # hour); from disk it holds t (8 B/sample), the temperature column once for its mean (8 B,
    # transient), the window mask (1 B) and, for a significant line, one residual axis (8 B) —
    # the growth must stay below 64 B/sample (0.59 M samples × 64 B = 36 MiB; run-to-run jitter
    # of the peak is ≈ ±7 MiB = ±12 B/sample). Both lengths are whole multiples of the line
    # test's 65 536-sample segment (3 and 12 segments), so its window-level work is the same at
    # both: at 200 s and 800 s the segments are 50 000 and 61 538 samples and the slope was
    # 54 B/sample — the segment's growth, not the record's. Measured at these lengths: 216 →
    # 224 MiB, 13.4 and 15.7 B/sample in two runs (t plus the transient temperature column)
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "..", "bench"))
    import bench_memory as B

    peaks = {}
    short, long_ = 3 * 65536 / 1000.0, 12 * 65536 / 1000.0
    for dur in (short, long_):
        work = tmp_path / f"d{int(dur * 1000)}"
        work.mkdir()
        rows = B._run_stages(
            argparse.Namespace(
                duration_s=dur,
                rate_hz=1000.0,
                csv=str(work / "one_hour.parquet"),
                params=str(work / "p.json"),
                corrected=str(work / "c.csv"),
                source="synth",
                format="parquet",
                long_duration_s=0.0,
            ),
            dur,
            work,
            ["synth", "cli_loop"],
            quiet=True,
        )
        assert all(r["exit"] == 0 for r in rows), rows
        peaks[dur] = next(r["peak_rss_bytes"] for r in rows if r["stage"] == "cli_loop")
    growth = (peaks[long_] - peaks[short]) / (9 * 65536)
    assert growth < 64, f"peak RSS grows {growth:.0f} B/sample ({peaks})"
    assert math.isfinite(growth)
