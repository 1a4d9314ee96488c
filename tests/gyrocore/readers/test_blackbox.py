"""Blackbox reader (gyrocore.readers.blackbox) on the shared Betaflight 3.1.5 log and on damaged copies.

Expected figures come from ../shared/data/betaflight_blackbox/PROVENANCE.md (measured there
with orangebox 0.4.0 and numpy, independently of this reader) and from the Betaflight source
(debug.h / gyro.c of the tags named in gyrocore/readers/blackbox.py).
"""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest

from gyrocore.readers import blackbox as bb
from gyrocore.readers import blackbox_firmware as bf
from gyrocore.readers.convert import detect_format, load_any
from gyrocore.errors import GyroInputError, RepairWarning

DEG = math.pi / 180.0
#: Bytes of the shared log used for the damaged copies: the header (~2.4 kB) and ~12k frames.
PREFIX_BYTES = 400_000


@pytest.fixture(scope="module")
def log_path(shared_data):
    p = shared_data / "betaflight_blackbox" / "better_tune.BBL"
    if not p.exists():
        pytest.skip("shared blackbox log absent")
    return p


@pytest.fixture(scope="module")
def full(log_path):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always", RepairWarning)
        rec = bb.read_blackbox(log_path)
    return rec, [str(x.message) for x in w]


def _read(path, **kw):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always", RepairWarning)
        rec = bb.read_blackbox(path, **kw)
    return rec, [str(x.message) for x in w if issubclass(x.category, RepairWarning)]


def test_shared_log_frames_span_units_and_header(full):
    rec, warns = full
    # PROVENANCE: orangebox yields 127,527 main frames, the first three P frames carry
    # timestamps near 0 (decoded before any I frame): our loop drops exactly those.
    assert rec.n == 127_527 - 3
    # PROVENANCE: the flight runs from t = 75.2 s to 204.7 s (129.5 s continuous).
    assert rec.duration_s == pytest.approx(129.5, abs=0.05)
    assert json.loads(rec.meta["logs"])[0]["time_us_first"] == pytest.approx(75.2e6, abs=0.05e6)
    # gyroADC is deg/s (gyro_scale 1.0): roll/pitch reach ±1998 °/s (±2000 °/s full scale met).
    peak_deg_s = np.degrees(np.abs(rec.gyro_rad_s).max(axis=0))
    assert peak_deg_s[0] == pytest.approx(1998, abs=2) and peak_deg_s[1] == pytest.approx(1998, abs=3)
    # header: loop 8 kHz, logged 1/8 → 1 kHz nominal; measured median Δt 1012 µs (PROVENANCE).
    assert float(rec.meta["gyro_rate_hz"]) == 8000
    assert float(rec.meta["log_rate_nominal_hz"]) == 1000
    assert 1e6 / float(rec.meta["log_rate_measured_hz"]) == pytest.approx(1012, abs=1)
    chain = json.loads(rec.meta["gyro_filters"])
    assert [c["kind"] for c in chain] == ["pt1", "notch"]  # 3.1: LPF, then the notches
    assert chain[0]["cutoff_hz"] == 90 and chain[1]["cutoff_hz"] == 305
    # Q of Betaflight's filterGetNotchQ(305, 205) = 305·205/(305² − 205²)
    assert chain[1]["q"] == pytest.approx(305 * 205 / (305**2 - 205**2), rel=1e-12)
    assert rec.meta["debug_mode"] == "8 = DEBUG_NOTCH"
    pre = json.loads(rec.meta["gyro_prefilter"])
    assert pre["signal"] == "partly_filtered" and [f["kind"] for f in pre["filters_before"]] == ["pt1"]
    # accelerometer: acc_1G 2048 LSB/g; the median |f| over the flight is near 1 g in hover
    # and higher in manoeuvres, never near 0 or 8 g (a unit error would be a factor ≥ 2).
    fmag = np.linalg.norm(rec.accel_m_s2, axis=1)
    assert 0.7 * 9.81 < np.median(fmag) < 2.5 * 9.81
    # motors in motorOutput 138..2047 → 0..1; throttle 1000..2000 after the signed read
    assert 0 <= rec.extra["motor_cmd_mean"].min() and rec.extra["motor_cmd_mean"].max() <= 1.0
    assert rec.extra["rc_throttle"].min() >= 1000 and rec.extra["rc_throttle"].max() <= 2000
    assert any("rcCommand[3]" in w for w in warns)
    lacks = rec.meta["lacks"]
    assert "no eRPM" in lacks and "Nyquist" in lacks


def test_debug_mode_index_changes_meaning_between_versions():
    # betaflight/betaflight#5211: NOTCH was 8 in 3.2.5 and 6 in 3.3; in 4.3, 6 is GYRO_SCALED.
    assert bf.debug_mode_name((3, 1, 5), 8) == "NOTCH"
    assert bf.debug_mode_name((3, 2, 5), 8) == "GYRO_NOTCH"
    assert bf.debug_mode_name((3, 3, 0), 6) == "GYRO_NOTCH"
    assert bf.debug_mode_name((4, 3, 0), 6) == "GYRO_SCALED"
    assert bf.debug_mode_name((2025, 12, 0), 6) == "RC_INTERPOLATION"  # GYRO_SCALED removed (gyroUnfilt)
    assert bf.debug_mode_name((4, 5, 9), 6) is None  # a release not read: no guess
    assert bf.debug_mode_name((3, 0, 1), 3) is None


def test_detect_and_load_through_convert(log_path, tmp_path):
    assert detect_format(log_path) == "blackbox"
    cut = tmp_path / "head.BBL"
    cut.write_bytes(log_path.read_bytes()[:60_000])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RepairWarning)
        rec = load_any(cut)
    assert rec.meta["format"] == "blackbox" and rec.n > 1000


def test_truncated_log_keeps_complete_frames_with_one_warning(log_path, full, tmp_path):
    rec_full, _ = full
    cut = tmp_path / "cut.BBL"
    cut.write_bytes(log_path.read_bytes()[:PREFIX_BYTES])
    rec, warns = _read(cut)
    trunc = [w for w in warns if "truncated" in w]
    assert len(trunc) == 1
    n = rec.n
    assert 5000 < n < rec_full.n
    # every kept frame is bit-identical to the same frame of the full read
    assert np.array_equal(rec.gyro_rad_s, rec_full.gyro_rad_s[:n])
    assert np.array_equal(rec.t_s, rec_full.t_s[:n])
    assert json.loads(rec.meta["logs"])[0]["truncated"] is True


def test_corrupt_bytes_are_skipped_and_counted(log_path, full, tmp_path):
    rec_full, _ = full
    data = bytearray(log_path.read_bytes()[:PREFIX_BYTES])
    rng = np.random.default_rng(16)
    spots = rng.integers(50_000, PREFIX_BYTES - 50_000, size=5)
    for s in spots:
        data[s : s + 7] = b"\x00\x81\xff\x13\x99\x00\x42"
    bad = tmp_path / "corrupt.BBL"
    bad.write_bytes(bytes(data))
    rec, warns = _read(bad)
    assert any("corrupt frame" in w for w in warns)
    info = json.loads(rec.meta["logs"])[0]
    assert info["corrupt_skipped"] >= 1
    # what is kept is real: each kept frame's time appears in the clean read with the same gyro
    t_clean = np.round(rec_full.t_s * 1e6).astype(np.int64)
    t_kept = np.round(rec.t_s * 1e6).astype(np.int64)
    idx = np.searchsorted(t_clean, t_kept)
    ok = (idx < t_clean.size) & (t_clean[np.minimum(idx, t_clean.size - 1)] == t_kept)
    assert ok.mean() > 0.99
    same = np.all(rec.gyro_rad_s[ok] == rec_full.gyro_rad_s[idx[ok]], axis=1)
    assert same.mean() > 0.99
    # at most a few hundred frames lost per damaged spot (until the next I frame: I interval 32
    # loops = 4 logged frames, plus resynchronisation)
    assert rec.n > (12_000 - 5 * 300)


def _patched_header(log_path, tmp_path, old: bytes, new: bytes):
    data = log_path.read_bytes()[:PREFIX_BYTES]
    assert old in data[:4000]
    p = tmp_path / "patched.BBL"
    p.write_bytes(data.replace(old, new, 1))
    return p


@pytest.mark.parametrize(
    "old,new,needle",
    [
        (b"H Data version:2", b"H Data version:7", "data version 7"),
        (b"Betaflight 3.1.5", b"INAV 2.6.0", "INAV 2.6.0"),
        (b"Betaflight 3.1.5", b"Betaflight 2.9.1", "Betaflight 2.9.1"),
        (b"Betaflight 3.1.5", b"Betaflight 9999.1", "newer than"),
    ],
)
def test_unknown_firmware_or_data_version_is_one_error(log_path, tmp_path, old, new, needle):
    p = _patched_header(log_path, tmp_path, old, new)
    with pytest.raises(GyroInputError) as e:
        _read(p)
    msg = str(e.value)
    assert needle in msg and "\n" not in msg


def test_unmapped_debug_mode_says_what_is_lacking(log_path, tmp_path):
    p = _patched_header(log_path, tmp_path, b"H debug_mode:8", b"H debug_mode:2")
    rec, _ = _read(p)
    assert "gyro_prefilter_x_rad_s" not in rec.extra
    assert "no unfiltered gyro: debug_mode 2 is DEBUG_BATTERY" in rec.meta["lacks"]


def test_several_logs_in_one_file_become_segments(log_path, tmp_path):
    part = log_path.read_bytes()[:150_000]
    two = tmp_path / "two.BBL"
    two.write_bytes(part + part)
    rec, warns = _read(two)
    logs = json.loads(rec.meta["logs"])
    assert [g["log"] for g in logs] == [1, 2]
    assert logs[0]["frames"] == logs[1]["frames"]
    li = rec.extra["log_index"]
    assert set(np.unique(li)) == {1.0, 2.0}
    assert np.all(np.diff(rec.t_s) > 0)
    n1 = logs[0]["frames"]
    assert np.array_equal(rec.gyro_rad_s[:n1], rec.gyro_rad_s[n1:])
    one, _ = _read(two, log_index=2)
    assert one.n == n1


def test_not_a_blackbox_is_one_error(tmp_path):
    p = tmp_path / "x.BBL"
    p.write_bytes(b"hello\n")
    with pytest.raises(GyroInputError):
        bb.read_blackbox(p)


def test_betaflight_44_header_names_and_gyro_scaled(log_path, tmp_path):
    """A 4.4 header (the same frames): debug_mode 6 is GYRO_SCALED (raw gyro), LPF1 from
    gyro_lpf1_static_hz with type 2 = PT2 (4.3+ lowpassFilterType_e), dynamic notch from
    dyn_notch_count, RPM filter from rpm_filter_harmonics with dshot_bidir, integer P interval,
    and blackbox_high_resolution: gyroADC ×10 (debug fields are not scaled)."""
    data = log_path.read_bytes()[:PREFIX_BYTES]
    extra = (
        b"H gyro_lpf1_static_hz:90\nH gyro_lpf1_type:2\nH gyro_lpf1_dyn_hz:0,0\nH gyro_lpf2_static_hz:0\n"
        b"H dyn_notch_count:3\nH dyn_notch_min_hz:100\nH dyn_notch_max_hz:600\nH rpm_filter_harmonics:3\n"
        b"H dshot_bidir:1\nH motor_poles:14\nH blackbox_high_resolution:1\n"
    )
    s = (
        data.replace(b"Betaflight 3.1.5", b"Betaflight 4.4.2")
        .replace(b"H debug_mode:8", b"H debug_mode:6")
        .replace(b"H gyro_lowpass_hz:90\n", extra)
        .replace(b"H P interval:1/8", b"H P interval:8")
    )
    p = tmp_path / "bf44.BBL"
    p.write_bytes(s)
    rec, _ = _read(p)
    base, _ = _read(_patched_header(log_path, tmp_path, b"H debug_mode:8", b"H debug_mode:8"))
    assert rec.meta["debug_mode"] == "6 = DEBUG_GYRO_SCALED"
    pre = json.loads(rec.meta["gyro_prefilter"])
    assert pre["signal"] == "raw" and pre["filters_before"] == []
    kinds = [(c["kind"], c["dynamic"]) for c in json.loads(rec.meta["gyro_filters"])]
    assert kinds == [("dyn_notch", True), ("rpm_notch", True), ("notch", False), ("pt2", False)]
    assert float(rec.meta["log_rate_nominal_hz"]) == 1000
    np.testing.assert_allclose(rec.gyro_rad_s, base.gyro_rad_s / 10.0, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(rec.extra["gyro_prefilter_x_rad_s"], base.extra["gyro_prefilter_x_rad_s"])


def test_rpm_filter_debug_mode_gives_rotor_frequency(log_path, tmp_path):
    """4.x debug_mode RPM_FILTER: debug[0..3] = rotor frequency per motor in Hz (rpm_filter.c)."""
    from gyrocore.readers.blackbox_firmware import DEBUG_MODE_TABLES

    names = [n for lo, hi, n in DEBUG_MODE_TABLES if lo <= (4, 2, 0) <= hi][0]
    idx = names.index("RPM_FILTER")
    data = log_path.read_bytes()[:PREFIX_BYTES]
    s = data.replace(b"Betaflight 3.1.5", b"Betaflight 4.2.0").replace(b"H debug_mode:8", b"H debug_mode:%d" % idx)
    p = tmp_path / "rpm.BBL"
    p.write_bytes(s)
    rec, _ = _read(p)
    base, _ = _read(_patched_header(log_path, tmp_path, b"H debug_mode:8", b"H debug_mode:8"))
    assert "no eRPM" not in rec.meta["lacks"] and "DEBUG_RPM_FILTER" in rec.meta["rotor_hz_source"]
    np.testing.assert_allclose(rec.extra["rotor_hz_0"], np.degrees(base.extra["gyro_prefilter_x_rad_s"]), atol=1e-9)


def test_convert_cli_writes_data_file_with_metadata(log_path, tmp_path):
    import subprocess
    import sys

    from gyrocore.data.recording import read_csv

    cut = tmp_path / "cut.BBL"
    cut.write_bytes(log_path.read_bytes()[:80_000])
    out = tmp_path / "f.csv"
    cp = subprocess.run(
        [sys.executable, "-m", "experiments.cli", "convert", str(cut), "-o", str(out), "--json", "--log-index", "1"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert cp.returncode == 0, cp.stderr
    d = json.loads(cp.stdout)
    assert d["format"] == "blackbox" and "gyro_prefilter_x_rad_s" in d["columns"]["extra"]
    warn = [ln for ln in cp.stderr.splitlines() if ln.startswith("warning:")]
    assert any("truncated" in w for w in warn)
    rec = read_csv(out)
    assert rec.n == d["n_samples"] and json.loads(rec.meta["gyro_filters"])[0]["kind"] == "pt1"
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "experiments.cli",
            "convert",
            str(cut),
            "-o",
            str(tmp_path / "g.csv"),
            "--log-index",
            "3",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert bad.returncode != 0 and bad.stderr.strip().startswith("error:") and "holds 1" in bad.stderr
