"""ArduPilot DataFlash reader (gyrocore.readers.dataflash) on a real ArduCopter 4.5.7 log (tests/data/dataflash).

Expected figures come from outside the reader: the fixture's PROVENANCE (read with pymavlink
directly), the log's own FMTU units, gravity (|a| = g with the motors stopped) and the header
parameters of the log.
"""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from gyrocore.readers.convert import detect_format, load_any  # noqa: E402
from gyrocore.readers.dataflash import read_dataflash  # noqa: E402
from gyrocore.errors import GyroInputError, RepairWarning  # noqa: E402

LOG = Path(__file__).resolve().parents[2] / "data" / "dataflash" / "ArduCopter-4.5.7_00000081_first650k.BIN"
G0 = 9.80665


def _read(path, **kw):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always", RepairWarning)
        rec = read_dataflash(path, **kw)
    return rec, [str(x.message) for x in w if issubclass(x.category, RepairWarning)]


def test_real_arducopter_log_units_rates_and_header():
    rec, warns = _read(LOG)
    assert not warns
    assert detect_format(LOG) == "dataflash"
    # 318 IMU0 messages at 25 Hz over 12.68 s (PROVENANCE, read with pymavlink directly)
    assert rec.n == 318 and abs(float(rec.meta["log_rate_measured_hz"]) - 25.0) < 0.1
    assert rec.meta["firmware"].startswith("ArduCopter V4.5.7") and rec.meta["firmware_version"] == "4.5.7"
    assert float(rec.meta["gyro_sample_rate_hz"]) == 6406 and float(rec.meta["loop_rate_hz"]) == 400
    # units on the data: with the motors at MOT_PWM_MIN the copter stands still: |a| = g within
    # 1 % (a unit error in g or cm/s² would be a factor ≥ 9.8) and |gyro| < 0.5 deg/s (a deg/s
    # stream labelled rad/s would read ~57x larger)
    still = rec.extra["motor_cmd_mean"] <= 0.0
    assert still.sum() >= 40
    assert abs(np.median(np.linalg.norm(rec.accel_m_s2[still], axis=1)) / G0 - 1) < 0.01
    assert np.degrees(np.abs(rec.gyro_rad_s[still])).max() < 0.5
    # motors: RCOU C1..C4 (QUAD), normalised by MOT_PWM_MIN 1100 / MOT_PWM_MAX 1900
    assert [k for k in sorted(rec.extra) if k.startswith("motor_cmd_") and k[-1].isdigit()] == [
        f"motor_cmd_{i}" for i in range(4)
    ]
    assert rec.extra["motor_0"].min() == 1100 and 0 < rec.extra["motor_cmd_mean"].max() <= 1
    chain = json.loads(rec.meta["gyro_filters"])
    assert [(c["kind"], c["cutoff_hz"], c["dynamic"]) for c in chain][0] == ("butter2", 42.0, False)
    assert chain[1]["kind"] == "dyn_notch" and chain[1]["dynamic"]
    assert "Nyquist 12.5 Hz" in rec.meta["lacks"] and "convert --stream batch" in rec.meta["lacks"]


def test_truncated_log_keeps_complete_messages_with_one_warning(tmp_path):
    full, _ = _read(LOG)
    data = LOG.read_bytes()
    cut = tmp_path / "cut.BIN"
    cut.write_bytes(data[: len(data) * 2 // 3 - 7])
    rec, warns = _read(cut)
    assert len([w for w in warns if "truncated" in w]) == 1
    assert 50 < rec.n < full.n and np.array_equal(rec.gyro_rad_s, full.gyro_rad_s[: rec.n])


def test_not_dataflash_or_no_units_is_one_error(tmp_path):
    p = tmp_path / "x.bin"
    p.write_bytes(b"\x00" * 100)
    with pytest.raises(GyroInputError):
        read_dataflash(p)
    with pytest.raises(GyroInputError) as e:
        read_dataflash(LOG, imu_instance=7)
    assert "instance 7" in str(e.value) and "\n" not in str(e.value)


def test_convert_cli_and_vibration_refusal(tmp_path):
    out = tmp_path / "ap.csv"
    cp = subprocess.run(
        [sys.executable, "-m", "experiments.cli", "convert", str(LOG), "-o", str(out), "--json"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert cp.returncode == 0, cp.stderr
    d = json.loads(cp.stdout)
    assert d["format"] == "dataflash" and d["n_samples"] == 318
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RepairWarning)
        assert load_any(LOG).meta["format"] == "dataflash"
    # 25 Hz IMU data cannot show vibration above 40 Hz: one error line, no traceback
    cp2 = subprocess.run(
        [sys.executable, "-m", "experiments.cli", "vibration", str(out)], capture_output=True, text=True, timeout=300
    )
    assert cp2.returncode != 0 and "Traceback" not in cp2.stderr
    assert len([ln for ln in cp2.stderr.splitlines() if ln.startswith("error:")]) == 1


def test_corrupt_headers_are_skipped_and_counted_in_one_warning(tmp_path):
    """DataFlash has no checksum: corruption is seen where a message header (0xA3 0x95 type) is
    broken; pymavlink resynchronises on the next header. Three headers in the middle third are
    broken: one warning, and every kept IMU sample is one of the clean read's, bit-identical."""
    full, _ = _read(LOG)
    data = bytearray(LOG.read_bytes())
    starts = [i for i in range(len(data) // 3, 2 * len(data) // 3) if data[i] == 0xA3 and data[i + 1] == 0x95]
    rng = np.random.default_rng(1603)
    for s in rng.choice(starts, size=3, replace=False):
        data[s : s + 2] = b"\x00\x00"
    bad = tmp_path / "bad.BIN"
    bad.write_bytes(bytes(data))
    rec, warns = _read(bad)
    assert len([w for w in warns if "corrupt data skipped" in w]) == 1
    t_clean = np.round(full.t_s * 1e6).astype(np.int64)
    t_kept = np.round(rec.t_s * 1e6).astype(np.int64) + (t_clean[0] if rec.t_s[0] == 0 else 0)
    idx = np.searchsorted(t_clean, t_kept)
    assert np.all(idx < t_clean.size) and np.array_equal(t_clean[idx], t_kept)
    assert rec.n >= full.n - 3 and np.array_equal(rec.gyro_rad_s, full.gyro_rad_s[idx])


def test_batch_sampler_stream_and_vibration_on_it(tmp_path):
    """The batch sampler's raw gyro (ISBH/ISBD): windows of 1024 samples at IMU.GHz. With
    INS_LOG_BAT_OPT 4 (pre and post filter) the pre-filter instance is told on the data: above
    4·INS_GYRO_FILTER the 2nd-order Butterworth attenuates by 1/sqrt(1 + 4^4) ≈ 1/16, so the
    pre-filter rms there must exceed the post-filter one by far more than the 3x demanded."""
    rec, _ = _read(LOG, stream="batch")
    assert rec.meta["stream"] == "batch" and rec.meta["batch_windows"] == "3" and rec.n == 3 * 1024
    assert abs(float(rec.meta["rate_hz"]) - float(rec.meta["gyro_sample_rate_hz"])) < 1.0
    assert json.loads(rec.meta["gyro_prefilter"])["signal"] == "raw" and rec.accel_m_s2 is None
    assert "instance 0 taken as pre-filter" in rec.meta["batch_prepost_check"]
    # inside a window the samples are 1/rate apart; windows are separated by gaps of seconds
    dt = np.diff(rec.t_s)
    assert np.allclose(dt[dt < 0.01], 1 / float(rec.meta["rate_hz"]), rtol=1e-6) and (dt > 1).sum() == 2
    out = tmp_path / "isb.csv"
    cp = subprocess.run(
        [sys.executable, "-m", "experiments.cli", "convert", str(LOG), "--stream", "batch", "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert cp.returncode == 0, cp.stderr
    cp2 = subprocess.run(
        [sys.executable, "-m", "experiments.cli", "vibration", str(out), "--window-s", "0.15", "--json"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert cp2.returncode == 0, cp2.stderr
    d = json.loads(cp2.stdout)
    assert d["signal"] == "raw" and abs(d["rate_hz"] - float(rec.meta["rate_hz"])) < 1 and d["n_windows"] >= 2
    for ax in "xyz":
        lo, hi = d["rms_above_40hz_interval_rad_s"][ax]
        assert lo <= d["rms_above_40hz_rad_s"][ax] <= hi
