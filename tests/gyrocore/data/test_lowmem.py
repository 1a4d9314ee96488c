"""Long recordings: the one-column-at-a-time paths give the whole-record answers and warnings."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from gyrocore.cli import build_group, run_cli
from gyrocore.errors import GyroInputError, RepairWarning
from gyrocore.data.recording import Recording, read_recording, write_recording
from gyrocore.data.columns import RecordingColumns
from gyrocore.data.spill import spill_columns


def _still(n=20_000, rate_hz=200.0, seed=0, *, gap=False, scale=1.0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    if gap:
        t = np.concatenate([t[: n // 2], t[n // 2 :] + 0.5])
    g = (rng.normal(0, 0.002, (n, 3)) + [0.01, -0.02, 0.005]) * scale
    a = rng.normal(0, 0.01, (n, 3)) + [0, 0, 9.81]
    return Recording(t_s=t, gyro_rad_s=g, accel_m_s2=a, temp_c=np.full(n, 25.0), meta={"sensor": "u"})


def _messages(fn):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        out = fn()
    return out, [str(x.message) for x in w if issubclass(x.category, RepairWarning)]


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_spill_same_columns_and_warnings_as_a_whole_read(tmp_path, suffix):
    rec = _still(gap=True)
    p = tmp_path / f"r{suffix}"
    write_recording(rec, p)
    whole, w1 = _messages(lambda: read_recording(p, columns=()))
    store, w2 = _messages(lambda: spill_columns(p, tmp_path / "spill", rows=3000))
    assert w1 == w2 and any("gaps longer" in m for m in w1)
    assert np.array_equal(store.t_s, whole.t_s)
    for j in range(3):
        assert np.array_equal(store.column(f"gyro_{'xyz'[j]}_rad_s"), whole.gyro_rad_s[:, j])
    # deg/s numbers in a rad/s column: the same one-line error
    bad = _still(scale=57.3 * 100)  # peaks ~170 "rad/s"
    write_recording(bad, tmp_path / f"b{suffix}")
    with pytest.raises(GyroInputError) as e1:
        read_recording(tmp_path / f"b{suffix}", columns=())
    with pytest.raises(GyroInputError) as e2:
        spill_columns(tmp_path / f"b{suffix}", tmp_path / "spill2")
    assert str(e1.value) == str(e2.value) and "probably deg/s" in str(e1.value)
    # a still deg/s recording labelled rad/s: the same warning (accel read as moments only)
    slow = _still(scale=57.3)
    write_recording(slow, tmp_path / f"s{suffix}")
    _, w1 = _messages(lambda: read_recording(tmp_path / f"s{suffix}", columns=()))
    _, w2 = _messages(lambda: spill_columns(tmp_path / f"s{suffix}", tmp_path / "spill3", rows=777))
    assert w1 == w2 and any("is it deg/s labelled rad/s" in m for m in w1)


def test_allan_by_axis_equals_whole_record(tmp_path, capsys, monkeypatch):
    import gyrocore.readers.large as LG

    rec = _still(40_000, gap=True)
    p = tmp_path / "r.csv"
    write_recording(rec, p)
    outs = []
    for limit in (10**12, 0):  # whole record, then one axis at a time
        monkeypatch.setitem(LG.RULES, "allan", LG.MemoryRule(bytes_per_row=32, budget_bytes=limit))
        with warnings.catch_warnings():
            s = run_cli(build_group(), ["allan", str(p), "--json"])
        cap = capsys.readouterr()
        assert s == 0, cap.err
        outs.append((json.loads(cap.out), sorted(ln for ln in cap.err.splitlines() if ln.startswith("warning:"))))
    assert outs[0][0] == outs[1][0]  # every number, bit for bit (JSON of floats)
    assert outs[0][1] == outs[1][1] and outs[0][1]


def test_bias_blockwise_statistics_equal_whole_array(monkeypatch):
    """Long records: window statistics a block of windows at a time. The bias and the window
    are identical; the pooled sums (VIF, threshold, s.e.) only change their summation order:
    relative difference ≤ (number of blocks)·ε ≈ 1e-14 here, asserted at 1e-12."""
    import gyrocore.calib.bias as B

    rng = np.random.default_rng(1)
    n = 60_000
    g = rng.normal(0, 0.003, (n, 3)) + [0.01, -0.02, 0.004]
    g[20_000:25_000, 1] += 0.5 * np.sin(np.arange(5000) / 100)  # motion in the middle
    g += np.cumsum(rng.normal(0, 1e-5, (n, 3)), axis=0)  # coloured noise: VIF > 1
    rec = Recording(t_s=np.arange(n) / 1000.0, gyro_rad_s=g)
    for rule in ("mean", "median", "converge"):
        whole = B.StaticBiasCalibrator(rule=rule).fit(rec)
        monkeypatch.setattr(RecordingColumns, "block_bytes", 50_000)  # ~10 windows per block
        blocks = B.StaticBiasCalibrator(rule=rule).fit(rec)
        monkeypatch.undo()
        assert (
            np.array_equal(whole.bias_rad_s, blocks.bias_rad_s)
            and whole.window_start_index == blocks.window_start_index
        )
        for f in ("bias_se_rad_s", "noise_sigma_rad_s", "threshold", "vif"):
            assert np.allclose(getattr(whole, f), getattr(blocks, f), rtol=1e-12, atol=0), (rule, f)


def test_write_csv_streams_long_recordings_byte_identically(tmp_path, monkeypatch):
    import gyrocore.data.recording as rc

    rng = np.random.default_rng(0)
    n = 5001
    rec = Recording(
        t_s=np.arange(n) / 1000,
        gyro_rad_s=rng.normal(size=(n, 3)),
        temp_c=rng.normal(size=n),
        meta={"a": "b", "c": "d\ne"},
        extra={"f": rng.normal(size=n)},
    )
    rc.write_csv(rec, tmp_path / "whole.csv")
    monkeypatch.setattr(rc, "WRITE_CHUNK_ROWS", 700)
    rc.write_csv(rec, tmp_path / "chunked.csv")
    assert (tmp_path / "whole.csv").read_bytes() == (tmp_path / "chunked.csv").read_bytes()


def test_scratch_columns_read_back_what_was_written(tmp_path):
    # a work column of the chunk source, in memory or beside a spill: rows written window by
    # window read back exactly (float64 both ways), any row range, ends clipped
    from gyrocore.data.columns import ScratchArray, ScratchFiles

    x = np.random.default_rng(2).standard_normal((1000, 4))
    for col in (ScratchArray(1000, 4), ScratchFiles(tmp_path, "w", 1000, 4)):
        for a in range(0, 1000, 300):
            col.write(a, min(a + 300, 1000), x[a : a + 300])
        assert np.array_equal(col.rows(0, 1000), x)
        assert np.array_equal(col.rows(250, 700), x[250:700])
        assert np.array_equal(col.rows(-5, 2000), x)
        assert np.array_equal(col.axis(3), x[:, 3])
        col.close()
