"""Streamed (on-disk, window by window) fits and statistics equal the in-memory ones."""

from __future__ import annotations

import numpy as np
import pytest

from gyrocore.effects import registry as E
from gyrocore.calib import lsq
from gyrocore.calibrator import Calibrator
from gyrocore.data.recording import Recording, read_csv, write_csv
from gyrocore.data.columns import RecordingColumns
from gyrocore.data.spill import ColumnSpill, spill_columns


def _spy_spill(monkeypatch) -> list:
    """Count the commands' spills (the streamed path) through gyrocore.data.spill.spill_columns."""
    import gyrocore.data.spill as SP

    called: list = []
    orig = SP.spill_columns
    monkeypatch.setattr(SP, "spill_columns", lambda *a, **k: called.append(1) or orig(*a, **k))
    return called


def _thermal_rate_record(n: int = 12000, seed: int = 11, *, outliers: int = 40) -> Recording:
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 200.0
    w = np.stack(
        [
            0.8 * np.sin(2 * np.pi * t / 7.0),
            0.6 * np.sin(2 * np.pi * t / 5.0 + 1),
            0.5 * np.sin(2 * np.pi * t / 11.0 + 2),
        ],
        1,
    )
    T = 25 + 20 * (1 - np.exp(-t / 20.0))
    params = {
        "bias": {"b_rad_s": np.array([0.01, -0.007, 0.004])},
        "scale": {"s": np.array([0.01, -0.02, 0.005])},
        "bias_thermal": {
            "poly_rad_s": np.array([[2e-4, -3e-6], [-1.5e-4, 2e-6], [1e-4, 4e-6]]),
            "t0_c": np.asarray(30.0),
            "temp_min_c": np.asarray(0.0),
            "temp_max_c": np.asarray(100.0),
        },
        "time_offset": {"tau_s": np.asarray(0.004)},
    }
    y = w + E.deterministic(params, E.ModelInputs(t_s=t, omega_S_rad_s=w, temp_c=T))
    y = y + 2e-3 * rng.standard_normal((n, 3))
    if outliers:
        y[rng.choice(n, outliers, replace=False)] += 0.5  # transients for the robust pass
    acc = np.tile([0.0, 0.0, 9.80665], (n, 1)) + 0.02 * rng.standard_normal((n, 3))
    return Recording(t_s=t, gyro_rad_s=y, accel_m_s2=acc, temp_c=T, ref_rate_rad_s=w, meta={"sensor": "s"})


def _assert_same(a, b, rtol):
    assert a.notes == b.notes and a.thermal_order == b.thermal_order and a.covariance == b.covariance
    assert a.unobservable == b.unobservable and a.n_samples == b.n_samples
    for e in a.params:
        for p, v in a.params[e].items():
            np.testing.assert_allclose(b.params[e][p], v, rtol=rtol, atol=1e-15, err_msg=f"{e}.{p}")
            s = a.stderr[e][p]
            if np.all(np.isfinite(s)):
                np.testing.assert_allclose(b.stderr[e][p], s, rtol=rtol, err_msg=f"{e}.{p}")
    np.testing.assert_allclose(b.residual_rms_rad_s, a.residual_rms_rad_s, rtol=rtol)


@pytest.mark.parametrize("chunk", [1500, 4096, 7001])
def test_streamed_calibration_equals_in_memory(tmp_path, monkeypatch, chunk):
    # Calibrator.fit of the spilled columns reads the record back from per-column files a window
    # at a time (gyrocore.calib.rows.ReferenceRows); with the same windows it does exactly the
    # in-memory arithmetic (bit for bit), and against one window (chunk_rows=None) it
    # differs only by the float-addition order where blocks straddle windows: relative
    # rounding ~average·eps ≈ 1e-14 times the normal-equation condition (< 1e3 here) → 1e-9.
    rec = _thermal_rate_record()
    path = tmp_path / "rec.csv"
    write_csv(rec, path)
    rec = read_csv(path)  # the %.17g round trip is exact; read back for the same warnings
    eff = ["bias", "scale", "bias_thermal", "time_offset"]
    monkeypatch.setitem(lsq.fit_effects.__kwdefaults__, "chunk_rows", None)
    whole = Calibrator(effects=eff, max_rows=1000).fit(rec)
    monkeypatch.setitem(lsq.fit_effects.__kwdefaults__, "chunk_rows", chunk)
    in_memory = Calibrator(effects=eff, max_rows=1000).fit(rec)
    store = spill_columns(path, tmp_path / "spill", accel=True, groups=("temp", "ref_rate"))
    streamed = Calibrator(effects=eff, max_rows=1000).fit(store)
    assert any("excluded" in s for s in streamed.notes)
    _assert_same(in_memory, streamed, rtol=1e-13)
    _assert_same(whole, streamed, rtol=1e-9)


def test_streamed_rows_equal_in_memory_rows(tmp_path):
    # ReferenceRows of the spilled columns gives the same r and inputs as the arrays, also with a
    # time offset (the reference interpolated at t − τ reads only the bracketing rows of the window)
    from gyrocore.calib.rows import ReferenceRows

    def _shift_rate(t, w, tau):  # w(t − τ) by linear interpolation over the whole column
        return np.stack([np.interp(t - tau, t, w[:, i]) for i in range(3)], axis=1)

    rec = _thermal_rate_record(n=3000, outliers=0)
    path = tmp_path / "rec.csv"
    write_csv(rec, path)
    store = spill_columns(path, tmp_path / "spill", accel=True, groups=("temp", "ref_rate"))
    for tau in (0.0, 0.0123, -0.05, 20.0):
        src = ReferenceRows(store, tau_s=tau)
        w = _shift_rate(rec.t_s, rec.ref_rate_rad_s, tau)
        for a, b in [(0, 17), (1000, 1777), (2990, 3000), (0, 3000)]:
            np.testing.assert_array_equal(src.r_rows(a, b), (rec.gyro_rad_s - w)[a:b])
            inp = src.inputs(a, b)
            np.testing.assert_array_equal(inp.omega_S_rad_s, w[a:b])
            np.testing.assert_array_equal(inp.temp_c, rec.temp_c[a:b])
            np.testing.assert_array_equal(inp.f_S_m_s2, rec.accel_m_s2[a:b])
            np.testing.assert_array_equal(inp.t_since_power_up_s, rec.t_s[a:b] - rec.t_s[0])


def test_calibrate_cli_streams_long_files(tmp_path, monkeypatch):
    # the command takes the streamed path for a large file (gyrocore.readers.large) and writes the same
    # parameter file as the in-memory fit (thermal order selection, robust pass included)
    import json

    from click.testing import CliRunner

    import gyrocore.readers.large as LG
    from gyrocore.cli.commands import calibrate as C
    from gyrocore.calib.params import load_params

    rec = _thermal_rate_record(n=36000, seed=3)  # > max_rows = 30000: block means of 2
    path = tmp_path / "rec.csv"
    write_csv(rec, path)
    eff = "bias,scale,bias_thermal"
    monkeypatch.setitem(LG.RULES, "calibrate", LG.MemoryRule(bytes_per_row=512, budget_bytes=0))  # every file is large
    monkeypatch.setitem(lsq.fit_effects.__kwdefaults__, "chunk_rows", 1000)
    called = _spy_spill(monkeypatch)
    r = CliRunner().invoke(C.command, [str(path), "--effects", eff, "-o", str(tmp_path / "p.json"), "--json"])
    assert r.exit_code == 0, r.output
    assert called
    streamed = load_params(tmp_path / "p.json")
    mem = Calibrator(effects=eff.split(","), max_rows=30000).fit(read_csv(path))
    assert json.loads(r.output)["n_samples"] == mem.n_samples
    _assert_same(mem, streamed, rtol=1e-9)


@pytest.mark.parametrize(
    "kw",
    [
        dict(rule="mean"),
        dict(rule="median", statistic="abs_diff"),
        dict(rule="converge"),
        dict(rule="article", lsb_rad_s=1e-4, article_threshold_counts=5000.0),
        dict(rule="mean", noise_sigma_rad_s=2e-3),
    ],
)
def test_streamed_bias_equals_in_memory(tmp_path, monkeypatch, kw):
    # StaticBiasCalibrator.fit reads the windows through the chunk source a block at a time and
    # the noise one column at a time, in memory or from disk: the same blocks and operations,
    # so the same numbers (checked bit for bit, with blocks of 7 windows)
    from gyrocore.calib import bias as B

    rng = np.random.default_rng(5)
    n = 40_000
    t = np.arange(n) / 400.0
    y = np.array([0.01, -0.02, 0.003]) + 2e-3 * rng.standard_normal((n, 3))
    y[:900] += 0.05 * np.sin(2 * np.pi * 20.0 * t[:900])[:, None]  # motion first: windows rejected
    rec = Recording(t_s=t, gyro_rad_s=y, meta={"sensor": "s"})
    path = tmp_path / "still.csv"
    write_csv(rec, path)
    monkeypatch.setattr(RecordingColumns, "block_bytes", 7 * 200 * 3 * 8)  # several blocks in memory
    monkeypatch.setattr(ColumnSpill, "block_bytes", 7 * 200 * 3 * 8)  # the same blocks from disk
    mem = B.StaticBiasCalibrator(**kw).fit(read_csv(path, columns=()))
    streamed = B.StaticBiasCalibrator(**kw).fit(spill_columns(path, tmp_path / "spill"))
    assert mem.n_rejected_windows > 0 or kw["rule"] == "converge"
    for f in mem.__dataclass_fields__:
        a, b = getattr(mem, f), getattr(streamed, f)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(b, a, err_msg=f)
        elif isinstance(a, float) and np.isnan(a):
            assert np.isnan(b), f
        else:
            assert a == b, f


def test_still_fraction_from_disk_reads_the_same_windows(tmp_path):
    # the allan motion gate of a long file reads only the 200 windows it judges from disk
    from gyrocore.noise.allan import _judged_windows

    rng = np.random.default_rng(8)
    n = 60_000  # 300 windows of 2 s at 100 Hz: 200 of them picked
    t = np.arange(n) / 100.0
    y = 1e-3 * rng.standard_normal((n, 3))
    y[20_000:35_000] += 0.2 * np.sin(2 * np.pi * 0.7 * t[20_000:35_000])[:, None]  # a quarter moving
    path = tmp_path / "r.csv"
    write_csv(Recording(t_s=t, gyro_rad_s=y), path)
    rec = read_csv(path, columns=())
    mem = _judged_windows(rec.gyro_rad_s, rec.rate_hz)
    disk = _judged_windows(spill_columns(path, tmp_path / "spill"), rec.rate_hz)
    assert mem.n_windows == disk.n_windows == 200
    assert 0.6 < mem.fraction < 0.85 and disk.fraction == mem.fraction
    np.testing.assert_array_equal(disk.statistic, mem.statistic)


def test_streamed_bias_with_its_own_blocks_equals_in_memory_to_rounding(tmp_path, monkeypatch):
    # from disk the windows are read in smaller blocks than the in-memory path uses: only the
    # order of the lag sums over blocks changes, so the numbers agree to float rounding
    # (relative ~W·eps ≈ 1e-14 for W = 200 windows; 1e-12 asserted)
    from gyrocore.calib import bias as B

    rng = np.random.default_rng(6)
    n = 40_000
    y = np.array([0.01, -0.02, 0.003]) + 2e-3 * rng.standard_normal((n, 3))
    path = tmp_path / "still.csv"
    write_csv(Recording(t_s=np.arange(n) / 400.0, gyro_rad_s=y), path)
    monkeypatch.setattr(RecordingColumns, "block_bytes", 7 * 200 * 3 * 8)
    monkeypatch.setattr(ColumnSpill, "block_bytes", 3 * 200 * 3 * 8)
    mem = B.StaticBiasCalibrator().fit(read_csv(path, columns=()))
    streamed = B.StaticBiasCalibrator().fit(spill_columns(path, tmp_path / "spill"))
    assert streamed.window_start_index == mem.window_start_index
    for f in ("bias_rad_s", "bias_se_rad_s", "vif", "threshold", "noise_sigma_rad_s", "min_step_rad_s"):
        np.testing.assert_allclose(getattr(streamed, f), getattr(mem, f), rtol=1e-12, err_msg=f)


def test_bias_cli_streams_long_files(tmp_path, capsys, monkeypatch):
    # for a large file the command spills t + gyro and fits from disk: the same JSON, bit for
    # bit, and the same warnings as the whole read
    import json
    import warnings

    import gyrocore.readers.large as LG
    from gyrocore.cli import build_group, run_cli

    rng = np.random.default_rng(9)
    n = 30_000
    y = np.array([0.01, -0.02, 0.003]) + 2e-3 * rng.standard_normal((n, 3))
    t = np.arange(n) / 400.0
    t[20_000:] += 0.5  # a gap: one warning, from either path
    path = tmp_path / "still.csv"
    write_csv(Recording(t_s=t, gyro_rad_s=y), path)
    called = _spy_spill(monkeypatch)
    outs = []
    for limit in (10**15, 0):  # whole read, then from disk
        monkeypatch.setitem(LG.RULES, "bias", LG.MemoryRule(bytes_per_row=64, budget_bytes=limit))
        with warnings.catch_warnings():
            s = run_cli(build_group(), ["bias", str(path), "--json"])
        cap = capsys.readouterr()
        assert s == 0, cap.err
        outs.append((json.loads(cap.out), sorted(ln for ln in cap.err.splitlines() if ln.startswith("warning:"))))
    assert called == [1]
    assert outs[0] == outs[1] and any("gaps" in w for w in outs[0][1])


def _table_steps_record(n: int = 60_000, rate: float = 200.0, seed: int = 21) -> Recording:
    """A rate-table-like record: plateaus of constant reference rate joined by 0.5-s linear
    ramps, each ramp followed by a filter transient (first-order, τ 0.02 s) the model does not
    describe; white + random-walk noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    w = np.zeros((n, 3))
    level = np.zeros(3)
    plateau, ramp = int(6.0 * rate), int(0.5 * rate)
    i = 0
    while i < n:
        new = rng.uniform(-3.0, 3.0, 3) * (rng.random(3) < 0.6)
        j = min(i + ramp, n)
        w[i:j] = level + (new - level) * np.linspace(0.0, 1.0, j - i, endpoint=False)[:, None]
        k = min(j + plateau, n)
        w[j:k] = new
        level = new
        i = k
    params = {"bias": {"b_rad_s": np.array([0.01, -0.007, 0.004])}, "scale": {"s": np.array([0.01, -0.02, 0.005])}}
    y = E.deterministic(params, E.ModelInputs(t_s=t, omega_S_rad_s=w))  # (1 + s)·ω + b
    # the chip filter's lag at every ramp (what ramp_margin_s leaves out): y − w low-passed
    a = np.exp(-1.0 / (0.02 * rate))  # gone to e^-12.5 of its size 0.25 s after a ramp
    lag = np.zeros((n, 3))
    dw = np.r_[np.zeros((1, 3)), np.diff(w, axis=0)]
    for m in range(1, n):
        lag[m] = a * lag[m - 1] + a * dw[m]
    y = y - lag
    y = y + 2e-3 * rng.standard_normal((n, 3)) + np.cumsum(2e-7 * rng.standard_normal((n, 3)), axis=0)
    acc = np.tile([0.0, 0.0, 9.80665], (n, 1))
    return Recording(t_s=t, gyro_rad_s=y, accel_m_s2=acc, ref_rate_rad_s=w, meta={"sensor": "s"})


@pytest.mark.parametrize("chunk", [4096, 7001])
def test_streamed_noise_model_fit_leaves_ramps_out_like_in_memory(tmp_path, monkeypatch, chunk):
    # Issue 12: the streamed calibrate path leaves the rate ramps out (ramp_margin_s: the mask
    # from the reference column read window by window, gyrocore.calibrator.near_rate_changes) and
    # identifies the noise model without the samples near a ramp, as in memory. The streamed
    # and in-memory fits run the same arithmetic on the same windows (the chunked block-mean
    # path, the same full-resolution residual for GMWM), so parameters, noise-model standard
    # errors and the identified model agree to rounding: 1e-13 as the OLS case above.
    rec = _table_steps_record()
    path = tmp_path / "rec.csv"
    write_csv(rec, path)
    rec = read_csv(path)
    eff = ["bias", "scale"]
    kw = dict(effects=eff, max_rows=3000, covariance="noise_model", ramp_margin_s=0.25)
    monkeypatch.setitem(lsq.fit_effects.__kwdefaults__, "chunk_rows", chunk)
    in_memory = Calibrator(**kw).fit(rec)
    store = spill_columns(path, tmp_path / "spill", accel=True, groups=("ref_rate",))
    streamed = Calibrator(**kw).fit(store)
    assert any(s.startswith("left out") for s in streamed.notes)
    assert any("noise identified on" in s for s in streamed.notes)
    assert streamed.covariance == "noise_model" and streamed.n_samples < rec.n
    _assert_same(in_memory, streamed, rtol=1e-13)
    for k, v in in_memory.noise_model.items():
        np.testing.assert_allclose(streamed.noise_model[k], v, rtol=1e-13, err_msg=k)
    # the ramps matter here (the check can fail): without the margin the fit uses every
    # sample and the transient biases the scale by many standard errors (z −7, −9 on this
    # record); with the ramps out z is N(0, 1) if the noise-model standard errors are honest,
    # so |z| < 5 on all three fails with probability 3·6e-7
    no_margin = Calibrator(**dict(kw, ramp_margin_s=0.0)).fit(store)
    assert no_margin.n_samples == rec.n
    s_true = np.array([0.01, -0.02, 0.005])
    z_out = (streamed.params["scale"]["s"] - s_true) / streamed.stderr["scale"]["s"]
    z_in = (no_margin.params["scale"]["s"] - s_true) / no_margin.stderr["scale"]["s"]
    assert np.max(np.abs(z_in)) > 5.0 > np.max(np.abs(z_out)), (z_in, z_out)


def test_near_rate_changes_window_by_window_equals_the_box_convolution():
    # the ramp mask read a window at a time (one row of overlap each side, runs dilated by k)
    # is the whole-column definition: ramp samples convolved with a box of 2k + 1 > 0.5
    from gyrocore.calibrator import near_rate_changes

    rng = np.random.default_rng(3)
    for _ in range(40):
        n = int(rng.integers(400, 3000))
        t = np.cumsum(rng.uniform(0.0005, 0.0015, n))
        w = np.zeros((n, 3))
        for _j in range(int(rng.integers(0, 6))):
            a = int(rng.integers(0, n))
            b = min(n, a + int(rng.integers(1, 200)))
            w[a:b, int(rng.integers(0, 3))] += np.linspace(0.0, rng.uniform(-3, 3), b - a)
        margin = float(rng.uniform(0.0, 0.15))
        dw = np.max(np.abs(np.diff(w, axis=0)), axis=1) / np.diff(t)
        ramp = np.r_[dw > 1e-2, False] | np.r_[False, dw > 1e-2]
        k = int(round(margin / float(np.median(np.diff(t)))))
        ref = (np.convolve(ramp.astype(float), np.ones(2 * k + 1), mode="same") > 0.5) if ramp.any() else ramp
        for chunk in (3, 997, n):
            np.testing.assert_array_equal(near_rate_changes(t, w, margin, chunk_rows=chunk), ref)
            np.testing.assert_array_equal(near_rate_changes(t, lambda a, b: w[a:b], margin, chunk_rows=chunk), ref)


def test_calibrate_cli_streamed_path_takes_the_ramp_margin(tmp_path, monkeypatch):
    # `calibrate --covariance noise_model --ramp-margin-s 0.25` on a long file (streamed path):
    # the margin reaches the streamed fit (it was dropped there) and the parameter file equals
    # the in-memory fit (same windows: 1e-13, as above)
    from click.testing import CliRunner

    import gyrocore.readers.large as LG
    from gyrocore.cli.commands import calibrate as C
    from gyrocore.calib.params import load_params

    rec = _table_steps_record(n=40_000)
    path = tmp_path / "rec.csv"
    write_csv(rec, path)
    monkeypatch.setitem(LG.RULES, "calibrate", LG.MemoryRule(bytes_per_row=512, budget_bytes=0))  # every file is large
    monkeypatch.setitem(lsq.fit_effects.__kwdefaults__, "chunk_rows", 4096)
    called = _spy_spill(monkeypatch)
    r = CliRunner().invoke(
        C.command,
        [
            str(path),
            "--effects",
            "bias,scale",
            "--covariance",
            "noise_model",
            "--ramp-margin-s",
            "0.25",
            "-o",
            str(tmp_path / "p.json"),
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    assert called
    streamed = load_params(tmp_path / "p.json")
    mem = Calibrator(effects=["bias", "scale"], covariance="noise_model", ramp_margin_s=0.25).fit(read_csv(path))
    assert any(s.startswith("left out") for s in streamed.notes) and streamed.n_samples == mem.n_samples < rec.n
    _assert_same(mem, streamed, rtol=1e-13)
