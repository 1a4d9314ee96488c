"""The data file: bit-exact round trip, reader hardening, chunked reading, atomic writes.

Property tests (hypothesis): write/read is bit-exact for any finite floats; arbitrary text or
bytes never make the reader raise anything but GyroInputError.
"""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from gyrocore.data import csvtext, recording as rc
from gyrocore.errors import GyroInputError, RepairWarning
from gyrocore.data.recording import Recording, iter_csv_chunks, read_csv, write_csv, write_csv_chunks

HEADER = "t_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s"


def _rec(n=50, *, seed=0, accel=True, temp=True, quat=True, rate_hz=100.0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Recording(
        t_s=t,
        gyro_rad_s=rng.normal(0.0, 0.01, (n, 3)),
        accel_m_s2=(rng.normal(0.0, 0.05, (n, 3)) + [0, 0, 9.81]) if accel else None,
        temp_c=(25 + rng.normal(0, 0.1, n)) if temp else None,
        ref_rate_rad_s=np.zeros((n, 3)),
        ref_quat_wxyz=q if quat else None,
        meta={"sensor": "test", "note": "a: b"},
        extra={"flag": rng.integers(0, 2, n).astype(float)},
    )


def _write(tmp_path, text, name="f.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _strict(fn, *a, **k):
    """Call with RepairWarning turned into an error (no repair expected)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RepairWarning)
        return fn(*a, **k)


# ------------------------------------------------------------------ round trip
def test_round_trip_bit_exact_all_columns(tmp_path):
    rec = _rec()
    p = tmp_path / "r.csv"
    write_csv(rec, p)
    back = _strict(read_csv, p)
    for name in ("t_s", "gyro_rad_s", "accel_m_s2", "temp_c", "ref_rate_rad_s", "ref_quat_wxyz"):
        assert np.array_equal(getattr(back, name), getattr(rec, name)), name
    assert back.meta == rec.meta and np.array_equal(back.extra["flag"], rec.extra["flag"])


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    gyro=arrays(np.float64, st.tuples(st.integers(2, 30), st.just(3)), elements=st.floats(-30, 30, allow_nan=False)),
    t0=st.floats(-1e6, 1e6, allow_nan=False),
    dt=st.floats(1e-4, 1.0),
    extra=finite,
)
def test_round_trip_property(tmp_path, gyro, t0, dt, extra):
    """Any finite values (gyro within the plausible ±30 rad/s) survive write/read bit-exactly."""
    n = gyro.shape[0]
    t = t0 + dt * np.arange(n)
    if not np.all(np.diff(t) > 0):  # t0 so large that dt vanishes in float64
        return
    rec = Recording(t_s=t, gyro_rad_s=gyro, meta={"k": "v"}, extra={"x": np.full(n, extra)})
    p = tmp_path / "p.csv"
    write_csv(rec, p)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RepairWarning)  # gaps/saturation checks may speak on random data
        back = read_csv(p)
    assert np.array_equal(back.t_s, rec.t_s) and np.array_equal(back.gyro_rad_s, rec.gyro_rad_s)
    assert np.array_equal(back.extra["x"], rec.extra["x"])


def _read_any(p):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            read_csv(p)
        except GyroInputError as exc:
            msg = str(exc)
            assert msg and "\n" not in msg  # one line


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=400))
def test_arbitrary_bytes_only_gyroinputerror(tmp_path, data):
    p = tmp_path / "b.csv"
    p.write_bytes(data)
    _read_any(p)


_alphabet = st.sampled_from(
    list("0123456789.,-+eE \n#:naifNI\t\r")
    + ["t_s", "gyro_x_rad_s", "gyro_y_rad_s", "gyro_z_rad_s", "accel_x_g", "temp_c", "ref_qw"]
)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(body=st.lists(_alphabet, max_size=120).map("".join))
def test_csv_like_text_only_gyroinputerror(tmp_path, body):
    p = tmp_path / "c.csv"
    p.write_text(HEADER + "\n" + body)
    _read_any(p)


_any_float = st.floats(allow_nan=True, allow_infinity=True)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.lists(st.tuples(*[_any_float] * 8), max_size=40))
def test_extreme_values_only_gyroinputerror_no_overflow_warnings(tmp_path, rows):
    """Any float64 (±1e308, inf, NaN) in any column: a Recording or one GyroInputError, and no
    numpy overflow RuntimeWarning (the CLI would print it as a stray warning line)."""
    p = tmp_path / "e.csv"
    p.write_text(
        "t_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s,accel_x_m_s2,accel_y_m_s2,accel_z_m_s2,temp_c\n"
        + "".join(",".join(repr(v) for v in r) + "\n" for r in rows)
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        warnings.simplefilter("ignore", RepairWarning)
        try:
            read_csv(p)
        except GyroInputError as exc:
            assert "\n" not in str(exc)


# ------------------------------------------------------------------ hardening (unit level)
def test_missing_file_folder_empty(tmp_path):
    with pytest.raises(GyroInputError, match="no such file"):
        read_csv(tmp_path / "nope.csv")
    with pytest.raises(GyroInputError, match="is a directory"):
        read_csv(tmp_path)
    with pytest.raises(GyroInputError, match="empty file"):
        read_csv(_write(tmp_path, ""))
    with pytest.raises(GyroInputError, match="no header row"):
        read_csv(_write(tmp_path, "# sensor: x\n\n"))
    with pytest.raises(GyroInputError, match="header only"):
        read_csv(_write(tmp_path, HEADER + "\n"))


def test_binary_and_hdf5(tmp_path):
    p = tmp_path / "b.csv"
    p.write_bytes(b"\x00\x01\x02" * 100)
    with pytest.raises(GyroInputError, match="binary file"):
        read_csv(p)
    p.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 100)
    with pytest.raises(GyroInputError, match="gyroharness convert"):
        read_csv(p)
    p.write_bytes("t_s\n".encode() + bytes([0xFF, 0xFE, 0xFA]) * 10)
    with pytest.raises(GyroInputError, match="UTF-8"):
        read_csv(p)


@pytest.mark.parametrize(
    "kind, pack",
    [
        ("gzip", lambda b: __import__("gzip").compress(b)),
        ("bzip2", lambda b: __import__("bz2").compress(b)),
        ("xz", lambda b: __import__("lzma").compress(b)),
    ],
)
def test_compressed_file_is_named_with_the_command_that_unpacks_it(tmp_path, kind, pack):
    p = tmp_path / "log.csv.x"
    p.write_bytes(pack((HEADER + "\n0,0,0,0\n0.01,0,0,0\n").encode()))
    with pytest.raises(GyroInputError, match=rf"{kind}-compressed file; decompress it first \(\w+ .*log\.csv\.x"):
        read_csv(p)


def test_text_encodings_are_named(tmp_path):
    """Windows exports: a Latin-1 '°' in a comment, UTF-16 (with and without a BOM); and an
    erased-flash dump. Each was "not UTF-8 text (binary file?)" or "binary file"."""
    body = HEADER + "\n0,0,0,0\n0.01,0,0,0\n"
    p = tmp_path / "a.csv"
    p.write_bytes("# sensor: MPU-6050 ±250°/s\n".encode("latin-1") + body.encode())
    with pytest.raises(GyroInputError, match=r"line 1 is not UTF-8 \('# sensor: MPU-6050 ±250°/s' in Windows-1252"):
        read_csv(p)
    for enc in ("utf-16", "utf-16-le"):
        p.write_bytes(body.encode(enc))
        with pytest.raises(GyroInputError, match=r"UTF-16 text .*iconv -f UTF-16 -t UTF-8"):
            read_csv(p)
    p.write_bytes(b"\xff" * 4096)
    with pytest.raises(GyroInputError, match=r"erased flash \(every byte 0xFF\)"):
        read_csv(p)


def test_zip_file_is_named(tmp_path):
    import zipfile

    p = tmp_path / "logs.zip"
    with zipfile.ZipFile(p, "w") as z:
        z.writestr("a.csv", HEADER + "\n0,0,0,0\n")
    with pytest.raises(GyroInputError, match=r"zip-compressed file; decompress it first \(unzip .*logs\.zip\)"):
        read_csv(p)


def test_fuzz_regression_bad_text_then_invalid_utf8(tmp_path):
    """Found by bench/fuzz_reader.py (atheris): a bad number sends the reader to its exact
    parser, which then met an invalid UTF-8 byte at the end and raised UnicodeDecodeError."""
    p = tmp_path / "crash.csv"
    p.write_bytes(
        b"# sens\n# rate_hz: 1 sens\n# rate_hz: 100\nt_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n"
        b"1,0\x0f.1,0.2t_s,gyr00\nt_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n0,0\x0f.1,0.2t_s,gy\xf2"
    )
    with pytest.raises(GyroInputError, match="not UTF-8 text after the header"):
        read_csv(p)


def test_text_in_number_names_line_and_column(tmp_path):
    p = _write(tmp_path, "# a: b\n" + HEADER + "\n0,0,0,0\n0.01,0,abc,0\n")
    with pytest.raises(GyroInputError, match=r"line 4, column 'gyro_y_rad_s': text in a number \('abc'\)"):
        read_csv(p)
    p = _write(tmp_path, HEADER + "\n0,0,0,0\n0.01,0,0\n0.02,0,0,0\n")
    with pytest.raises(GyroInputError, match="line 3: 3 values but the header names 4 columns"):
        read_csv(p)


@pytest.mark.parametrize("cut", ["0.03,0.5,0.2", "0.03,0.5,0.2,1.5e-", "0.03,0."])
def test_last_line_cut_short_is_dropped_with_a_warning(tmp_path, cut):
    """A logger stopped mid-write leaves its last line short: that line is dropped and said;
    the same line with a row after it (not the end of the file) stays an error."""
    body = "".join(f"{k * 0.01:.2f},{k},0.5,{-k}\n" for k in range(3))
    for tail in ("", "\n", "\n\n"):  # with and without the final newline, blank lines after
        p = _write(tmp_path, HEADER + "\n" + body + cut + tail)
        with pytest.warns(RepairWarning, match=r"last line 5 is cut short \(\d of 4 values.*dropped"):
            rec = read_csv(p)
        assert np.array_equal(rec.gyro_rad_s[:, 0], [0.0, 1.0, 2.0]) and rec.n == 3
        chunks = list(iter_csv_chunks(p, rows=2))  # the chunked path drops it too
        assert sum(c.n for c in chunks) == 3
    p = _write(tmp_path, HEADER + "\n" + body + cut + "\n0.04,0,0,0\n")
    with pytest.raises(GyroInputError, match="line 5"):
        read_csv(p)


def _rows(n=6):
    return "".join(f"{k * 0.01:.2f},{k},0.5,{-k}\n" for k in range(n))


def test_units_row_under_the_header_is_skipped_or_refused_when_it_contradicts(tmp_path):
    """LabVIEW/motion-capture exports put a units row under the names."""
    p = _write(tmp_path, HEADER + "\ns,rad/s,rad/s,rad/s\n" + _rows())
    with pytest.warns(RepairWarning, match=r"line 2 is a row of units \('s,rad/s,rad/s,rad/s'\): skipped"):
        rec = read_csv(p)
    assert rec.n == 6 and np.array_equal(rec.gyro_rad_s[:, 0], np.arange(6.0))
    p = _write(tmp_path, HEADER + "\ns,deg/s,deg/s,deg/s\n" + _rows())  # which is right? refuse
    with pytest.raises(GyroInputError, match=r"line 2 gives column 'gyro_x_rad_s' the unit 'deg/s'"):
        read_csv(p)
    p = _write(tmp_path, HEADER + "\n" + _rows(2) + "s,rad/s,rad/s,rad/s\n" + _rows())  # not under the header
    with pytest.raises(GyroInputError, match=r"line 4, column 't_s': text in a number"):
        read_csv(p)


def test_repeated_header_of_joined_files_is_skipped(tmp_path):
    later = "".join(f"{1 + k * 0.01:.2f},{k},0.5,{-k}\n" for k in range(4))
    p = _write(tmp_path, HEADER + "\n" + _rows() + HEADER + "\n" + later)
    with pytest.warns(RepairWarning, match=r"line 8 repeats the header \(files joined\?\): skipped"):
        rec = read_csv(p)
    assert rec.n == 10


def test_trailing_comma_on_data_rows_only(tmp_path):
    p = _write(tmp_path, HEADER + "\n" + "".join(r + ",\n" for r in _rows().splitlines()))
    with pytest.warns(RepairWarning, match="data rows end with a comma"):
        rec = read_csv(p)
    assert rec.n == 6 and np.array_equal(rec.gyro_rad_s[:, 2], -np.arange(6.0))
    p = _write(tmp_path, HEADER + "\n0,0,0,0,,\n0.01,0,0,0\n")  # two extra fields: still an error
    with pytest.raises(GyroInputError, match="line 2: 6 values"):
        read_csv(p)


def test_space_separated_file_is_named(tmp_path):
    p = _write(tmp_path, HEADER.replace(",", " ") + "\n0 0 0 0\n0.01 0 0 0\n")
    with pytest.raises(GyroInputError, match="separated by spaces"):
        read_csv(p)


def test_last_line_with_text_or_too_many_values_is_still_an_error(tmp_path):
    for last in ("0.03,abc,0.2,0.1", "0.03,0.1,0.2,0.3,0.4"):
        p = _write(tmp_path, HEADER + "\n0,0,0,0\n0.01,0,0,0\n" + last + "\n")
        with pytest.raises(GyroInputError, match="line 4"):
            read_csv(p)


def test_missing_and_incomplete_columns(tmp_path):
    with pytest.raises(GyroInputError, match="missing required column t_s"):
        read_csv(_write(tmp_path, "time,gyro_x_rad_s\n0,0\n"))
    with pytest.raises(GyroInputError, match="missing required column"):
        read_csv(_write(tmp_path, "t_s,foo\n0,0\n1,1\n"))
    with pytest.raises(GyroInputError, match="incomplete column group, missing accel_z_m_s2"):
        read_csv(_write(tmp_path, HEADER + ",accel_x_m_s2,accel_y_m_s2\n0,0,0,0,0,0\n1,0,0,0,0,0\n"))
    with pytest.raises(GyroInputError, match="duplicate column names"):
        read_csv(_write(tmp_path, HEADER + ",t_s\n0,0,0,0,0\n"))


def test_missing_column_errors_say_what_the_header_holds(tmp_path):
    """Another tool's CSV: the error names the header found (or says there is none) and the
    names a data file uses, on one line."""
    with pytest.raises(GyroInputError, match=r"the header names 'Time \(s\)', 'Gyro X \(deg/s\)'.*t_s, gyro_x_rad_s"):
        read_csv(_write(tmp_path, "Time (s),Gyro X (deg/s),Gyro Y (deg/s),Gyro Z (deg/s)\n0,1,2,3\n0.01,1,2,3\n"))
    with pytest.raises(GyroInputError, match=r"is numbers: the file has no header row"):
        read_csv(_write(tmp_path, "0,1,2,3\n0.01,1,2,3\n"))
    with pytest.raises(
        GyroInputError, match=r"missing required column\(s\) gyro_x_rad_s.*other columns are 'gx', 'gy'"
    ):
        read_csv(_write(tmp_path, "t_s,gx,gy,gz\n0,1,2,3\n0.01,1,2,3\n"))


def test_long_time_names_and_acc_stem_are_read(tmp_path, shared_data):
    """pyulog-style CSVs (``timestamp_us``, ``acc_x_m_s2``; the shared
    sample_ulg_sensor_combined.csv) were "missing required column t_s"; a long time name is read
    only when no t_* column is there (a file with both keeps t_s, no 'several time columns')."""
    p = _write(
        tmp_path,
        "timestamp_us,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s,acc_x_m_s2,acc_y_m_s2,acc_z_m_s2\n"
        + "".join(f"{1000000 + 4000 * k},0.1,0.2,0.3,0,0,9.8\n" for k in range(5)),
    )
    rec = read_csv(p)
    assert np.allclose(rec.t_s, 1.0 + np.arange(5) * 0.004) and np.all(rec.accel_m_s2[:, 2] == 9.8)  # us -> s
    p = _write(tmp_path, HEADER + ",timestamp_us\n" + "".join(f"{k * 0.01},0,0,0,{123 + k}\n" for k in range(5)))
    rec = read_csv(p)
    assert np.allclose(rec.t_s, np.arange(5) * 0.01) and "timestamp_us" in rec.extra
    csv = shared_data / "pyulog_samples" / "sample_ulg_sensor_combined.csv"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = read_csv(csv)
        from gyrocore.readers.ulog import read_ulog

        b = read_ulog(shared_data / "pyulog_samples" / "sample.ulg")
    assert a.n == b.n and np.allclose(a.gyro_rad_s, b.gyro_rad_s, rtol=1e-8, atol=1e-12)  # 9 significant digits


def test_nan_rows_repaired_and_ref_nan_kept(tmp_path):
    text = (
        HEADER
        + ",ref_qw,ref_qx,ref_qy,ref_qz\n"
        + "\n".join(
            f"{k * 0.01},{'nan' if k == 3 else 0},{'inf' if k == 5 else 0},0,{'nan' if k == 7 else 1},0,0,0"
            for k in range(10)
        )
    )
    with pytest.warns(RepairWarning, match="dropped 2 rows with NaN/inf"):
        rec = read_csv(_write(tmp_path, text))
    assert rec.n == 8 and np.isnan(rec.ref_quat_wxyz[:, 0]).sum() == 1
    with pytest.raises(GyroInputError, match="2 rows with NaN/inf"):
        read_csv(tmp_path / "f.csv", repair=False)


def test_empty_field_read_as_missing(tmp_path):
    text = HEADER + ",temp_c\n" + "\n".join(f"{k * 0.01},0,0,0,{'' if k == 2 else 25}" for k in range(6))
    with pytest.warns(RepairWarning) as rec_w:
        rec = read_csv(_write(tmp_path, text))
    msgs = " | ".join(str(w.message) for w in rec_w)
    assert "1 empty fields read as missing" in msgs and "dropped 1 rows" in msgs
    assert rec.n == 5


def test_backwards_and_repeated_timestamps(tmp_path):
    t = [0.0, 0.01, 0.02, 0.02, 0.015, 0.03, 0.04]
    text = HEADER + "\n" + "\n".join(f"{x},0,0,0" for x in t)
    with pytest.warns(RepairWarning, match="dropped 2 rows whose timestamp goes backwards or repeats"):
        rec = read_csv(_write(tmp_path, text))
    assert np.array_equal(rec.t_s, [0.0, 0.01, 0.02, 0.03, 0.04])


def test_gap_warning_counts_missing_samples(tmp_path):
    t = np.concatenate([np.arange(100), np.arange(110, 200)]) * 0.01
    text = HEADER + "\n" + "\n".join(f"{float(x)!r},0,0,0" for x in t)
    with pytest.warns(
        RepairWarning, match=r"1 gaps longer than 1.5x the median interval 10 ms \(longest 0.11 s, ~10 samples missing"
    ):
        rec = read_csv(_write(tmp_path, text))
    assert rec.n == 190  # reported, not changed


def test_bursty_timestamps_warn_and_retime(tmp_path):
    # 10 samples arrive 1 ms apart, then a 0.2 s pause: host buffering (mean dt 20 ms)
    t = np.concatenate([k * 0.2 + np.arange(10) * 0.001 for k in range(20)])
    text = HEADER + "\n" + "\n".join(f"{float(x)!r},0,0,0" for x in t)
    p = _write(tmp_path, text)
    with pytest.warns(RepairWarning, match="bursty host timestamps.*use --retime"):
        rec = read_csv(p)
    assert np.array_equal(rec.t_s, t)
    with pytest.warns(RepairWarning, match="replaced by a uniform grid"):
        rec2 = read_csv(p, retime=True)
    assert np.allclose(np.diff(rec2.t_s), (t[-1] - t[0]) / (t.size - 1))


def test_deg_s_labelled_rad_s(tmp_path):
    rng = np.random.default_rng(1)
    n = 2000
    t = np.arange(n) * 0.01
    # motion peaks 300 deg/s written as "rad/s": beyond any MEMS full scale → error
    g = np.zeros((n, 3))
    g[:, 2] = 300 * np.sin(np.linspace(0, 3, n))
    rows = "\n".join(",".join(repr(float(v)) for v in (a, b, c, d)) for a, (b, c, d) in zip(t, g))
    with pytest.raises(GyroInputError, match="probably deg/s; rename it gyro_x_deg_s"):
        read_csv(_write(tmp_path, HEADER + "\n" + rows))
    # still MPU-6050-like recording (0.1 deg/s noise, 4.5 deg/s bias) labelled rad/s → warning
    g = rng.normal(0, 0.1, (n, 3)) + [4.5, 0.1, 1.0]
    a = rng.normal(0, 0.02, (n, 3)) + [0, 0, 9.81]
    rows = "\n".join(",".join(repr(float(v)) for v in (ti, *gi, *ai)) for ti, gi, ai in zip(t, g, a))
    hdr = HEADER + ",accel_x_m_s2,accel_y_m_s2,accel_z_m_s2"
    with pytest.warns(RepairWarning, match="is it deg/s labelled rad/s"):
        read_csv(_write(tmp_path, hdr + "\n" + rows))
    # the same numbers in rad/s units of a real still gyro (÷57.3) raise nothing
    g2 = np.deg2rad(g)
    rows = "\n".join(",".join(repr(float(v)) for v in (ti, *gi, *ai)) for ti, gi, ai in zip(t, g2, a))
    _strict(read_csv, _write(tmp_path, hdr + "\n" + rows))


def test_saturation_detected_and_flagged(tmp_path):
    n = 1000
    t = np.arange(n) * 0.005
    rng = np.random.default_rng(2)
    w = 6.0 * np.sin(2 * np.pi * 0.5 * t) + rng.normal(0, 0.01, n)
    full_scale = np.deg2rad(250.0)  # 4.363 rad/s
    w_clip = np.clip(w, -full_scale, full_scale)
    g = np.column_stack([w_clip, np.zeros(n), np.zeros(n)])
    write_csv(Recording(t_s=t, gyro_rad_s=g), tmp_path / "s.csv")
    with pytest.warns(RepairWarning, match="saturated samples"):
        rec = read_csv(tmp_path / "s.csv")
    assert np.array_equal(rec.extra["saturated"] > 0, np.abs(w) >= full_scale)
    # an unclipped constant-rate "rate table" with quantized noise is not flagged
    q = np.deg2rad(1 / 131)
    g = np.round((1.0 + rng.normal(0, 0.002, (n, 3))) / q) * q
    write_csv(Recording(t_s=t, gyro_rad_s=g), tmp_path / "c.csv")
    _strict(read_csv, tmp_path / "c.csv")
    # a noise-free simulated rate-table step profile (exactly repeated values) is not flagged
    steps = np.repeat([0.0, 1.0, 2.0, 5.0, 2.0, 0.0], n // 6 + 1)[:n]
    write_csv(Recording(t_s=t, gyro_rad_s=np.column_stack([steps, 0 * steps, -steps])), tmp_path / "n.csv")
    _strict(read_csv, tmp_path / "n.csv")


def test_deg_s_and_g_columns_converted(tmp_path):
    text = "t_s,gyro_x_deg_s,gyro_y_deg_s,gyro_z_deg_s,accel_x_g,accel_y_g,accel_z_g\n0,180,0,0,0,0,1\n0.01,180,0,0,0,0,1\n"
    rec = _strict(read_csv, _write(tmp_path, text))
    assert rec.gyro_rad_s[0, 0] == pytest.approx(np.pi) and rec.accel_m_s2[0, 2] == pytest.approx(9.80665)


# ------------------------------------------------------------------ large input
def test_large_file_refused_with_clear_message(tmp_path, monkeypatch):
    rec = _rec(2000)
    p = tmp_path / "big.csv"
    write_csv(rec, p)
    monkeypatch.setattr(rc, "_available_memory_bytes", lambda: 100_000)
    with pytest.raises(GyroInputError, match="read it in chunks"):
        read_csv(p)
    # the chunked reader still reads it, in order, with O(rows) memory
    chunks = list(iter_csv_chunks(p, rows=300))
    assert [c.n for c in chunks] == [300] * 6 + [200]
    assert np.array_equal(np.concatenate([c.t_s for c in chunks]), rec.t_s)
    assert np.array_equal(np.vstack([c.ref_quat_wxyz for c in chunks]), rec.ref_quat_wxyz)


def test_chunks_drop_backwards_across_boundary(tmp_path):
    t = [0.0, 0.01, 0.02, 0.015, 0.03]
    p = _write(tmp_path, HEADER + "\n" + "\n".join(f"{x},0,0,0" for x in t))
    with pytest.warns(RepairWarning, match="dropped 1 rows whose timestamp"):
        chunks = list(iter_csv_chunks(p, rows=3))
    assert np.array_equal(np.concatenate([c.t_s for c in chunks]), [0.0, 0.01, 0.02, 0.03])


def test_cli_streams_large_csv(tmp_path, monkeypatch, capsys):
    from gyrocore.cli import build_group, run_cli

    rec = _rec(3000)
    src, out = tmp_path / "in.csv", tmp_path / "out.csv"
    write_csv(rec, src)
    monkeypatch.setattr(rc, "_available_memory_bytes", lambda: 200_000)
    assert run_cli(build_group(), ["convert", str(src), "-o", str(out), "--chunk-rows", "500"]) == 0
    monkeypatch.setattr(rc, "_available_memory_bytes", lambda: 10**12)
    back = read_csv(out)
    assert np.array_equal(back.gyro_rad_s, rec.gyro_rad_s) and back.meta == rec.meta


@pytest.mark.slow
def test_multi_hundred_mb_file_streams(tmp_path):
    """~400 MB data file (3 h at 1 kHz... here 3.6 M rows × 7 columns): chunked read works and
    peak memory of the consumer stays bounded by the chunk size."""
    import psutil

    n_chunk, n_chunks = 200_000, 18
    p = tmp_path / "huge.csv"
    import shutil

    free = shutil.disk_usage(tmp_path).free
    if free < 2 * 2**30:  # the file is ~400 MB; keep a margin for the rest of the machine
        pytest.skip(f"needs 2 GiB free disk for a ~400 MB file, {free / 2**30:.2f} GiB free")

    def gen():
        rng = np.random.default_rng(0)
        for k in range(n_chunks):
            t = (k * n_chunk + np.arange(n_chunk)) * 1e-3
            yield Recording(
                t_s=t,
                gyro_rad_s=rng.normal(0, 0.01, (n_chunk, 3)),
                accel_m_s2=rng.normal(0, 0.1, (n_chunk, 3)) + [0, 0, 9.81],
            )

    write_csv_chunks(gen(), p)
    assert os.path.getsize(p) > 300 * 2**20
    proc = psutil.Process()
    rss0 = proc.memory_info().rss
    total, s = 0, 0.0
    for c in iter_csv_chunks(p, rows=n_chunk):
        total += c.n
        s += float(c.gyro_rad_s[:, 0].sum())
    assert total == n_chunk * n_chunks
    assert proc.memory_info().rss - rss0 < 300 * 2**20


# ------------------------------------------------------------------ nothing lost
def test_interrupted_write_leaves_no_partial_file(tmp_path):
    p = tmp_path / "out.csv"

    def gen():
        yield _rec(100)
        raise KeyboardInterrupt  # e.g. Ctrl-C half way

    with pytest.raises(KeyboardInterrupt):
        write_csv_chunks(gen(), p)
    assert os.listdir(tmp_path) == []
    # an existing file survives an interrupted overwrite unchanged
    p.write_text("old")
    with pytest.raises(KeyboardInterrupt):
        write_csv_chunks(gen(), p)
    assert p.read_text() == "old" and os.listdir(tmp_path) == ["out.csv"]


def test_atomic_write_exception_mid_write(tmp_path, monkeypatch):
    p = tmp_path / "x.txt"
    p.write_text("old")

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(rc.os, "fsync", boom)
    with pytest.raises(OSError):
        rc.atomic_write_text(p, "new content")
    assert p.read_text() == "old" and sorted(os.listdir(tmp_path)) == ["x.txt"]


def test_no_silent_overwrite(tmp_path):
    p = tmp_path / "r.csv"
    write_csv(_rec(), p)
    with pytest.raises(GyroInputError, match="pass --force"):
        write_csv(_rec(), p, overwrite=False)
    with pytest.raises(GyroInputError, match="pass --force"):
        write_csv_chunks([_rec()], p, overwrite=False)


def test_exact_one_g_plateau_is_not_saturation():
    """A noise-free simulated accelerometer at rest reads exactly 9.81 m/s² for long runs.

    No accelerometer clips below ±2 g (the smallest full scale sold), so a plateau at 1 g is a
    steady reading: it must not be flagged. A gyro plateau at a real full scale still is.
    """
    from gyrocore.data.checks import detect_saturation

    rng = np.random.default_rng(7)
    n = 2000
    acc = np.zeros((n, 1))
    acc[:, 0] = 9.80665
    acc[500:700, 0] = 9.80665 * np.cos(np.linspace(0, np.pi, 200))  # a smooth re-pose
    acc[700:1500, 0] = -9.80665
    mask, found = detect_saturation(acc, min_clip=0.9 * 2 * 9.80665)
    assert not found and not mask.any()
    # a gyro clipped at ±250 deg/s = 4.363 rad/s, noise 0.01 rad/s: found at the limit
    g = rng.normal(0, 0.01, n) + 6.0 * np.sin(np.linspace(0, 6 * np.pi, n))
    g = np.clip(g, -4.3633, 4.3633)[:, None]
    mask, found = detect_saturation(g, min_clip=0.9 * 125 * np.pi / 180)
    assert found and mask.sum() == np.sum(np.abs(g[:, 0]) == 4.3633)


# ------------------------------------------------------------------ Arrow parser, Parquet, column groups
def test_arrow_and_exact_parsers_agree_bit_for_bit(tmp_path):
    """The clean file goes through Arrow; the same rows with one empty field in the last
    row go through the exact parser: every other value is identical."""
    rec = _rec(500, seed=3)
    p = tmp_path / "clean.csv"
    write_csv(rec, p)
    fast = _strict(read_csv, p, checks=False)
    lines = p.read_text().splitlines()
    lines[-1] = ",".join(lines[-1].split(",")[:-1] + [""])  # empty 'flag' field: not a clean table
    q = _write(tmp_path, "\n".join(lines) + "\n", "dirty.csv")
    with pytest.warns(RepairWarning, match="1 empty fields read as missing"):
        slow = read_csv(q, checks=False)
    for name in ("t_s", "gyro_rad_s", "accel_m_s2", "temp_c", "ref_quat_wxyz"):
        assert np.array_equal(getattr(fast, name), getattr(slow, name)), name
    assert np.array_equal(fast.extra["flag"][:-1], slow.extra["flag"][:-1]) and np.isnan(slow.extra["flag"][-1])


def test_chunked_error_in_a_late_chunk_names_the_file_line(tmp_path):
    """Arrow streams the clean chunks; the exact parser takes over at the refused block and
    names the file line (metadata lines and a blank line counted)."""
    rec = _rec(12000, seed=4, quat=False)  # ~3 MB: several 1 MiB Arrow blocks
    p = tmp_path / "late.csv"
    write_csv(rec, p)
    lines = p.read_text().splitlines()
    n_meta = sum(1 for ln in lines if ln.startswith("#"))
    lines.insert(n_meta + 1 + 1000, "")  # a blank line after data row 1000
    bad = n_meta + 1 + 11001 + 1  # file line of data row 11001 (1-based; +1 for the blank line)
    f = lines[bad - 1].split(",")
    f[2] = "1.2.3"
    lines[bad - 1] = ",".join(f)
    _write(tmp_path, "\n".join(lines) + "\n", "late.csv")
    got = []
    with pytest.raises(GyroInputError, match=rf"line {bad}, column 'gyro_y_rad_s': text in a number \('1.2.3'\)"):
        for c in iter_csv_chunks(p, rows=2000):
            got.append(c.n)
    assert got == [2000] * 5  # the clean chunks before it were read
    with pytest.raises(GyroInputError, match=rf"line {bad}, column 'gyro_y_rad_s'"):
        read_csv(p)


def test_comment_and_whitespace_lines_among_data_still_read(tmp_path):
    text = HEADER + "\n0,1,2,3\n# operator note\n0.01,1,2,3\n   \n0.02 , 1,2,3\n"
    rec = _strict(read_csv, _write(tmp_path, text), checks=False)
    assert np.array_equal(rec.t_s, [0.0, 0.01, 0.02]) and np.all(rec.gyro_rad_s == [1, 2, 3])


def test_column_groups_read_only_what_is_asked(tmp_path):
    rec = _rec(400, seed=5)
    p = tmp_path / "r.csv"
    write_csv(rec, p)
    part = _strict(read_csv, p, columns=("temp",))
    assert part.accel_m_s2 is None and part.ref_quat_wxyz is None and part.ref_rate_rad_s is None and not part.extra
    assert np.array_equal(part.gyro_rad_s, rec.gyro_rad_s) and np.array_equal(part.temp_c, rec.temp_c)
    chunks = list(iter_csv_chunks(p, rows=150, columns=("accel",)))
    assert np.array_equal(np.vstack([c.accel_m_s2 for c in chunks]), rec.accel_m_s2)
    assert all(c.temp_c is None for c in chunks)
    with pytest.raises(ValueError, match="unknown column group"):
        read_csv(p, columns=("gyroscope",))
    # the header is validated whatever is asked
    with pytest.raises(GyroInputError, match="incomplete column group, missing accel_z_m_s2"):
        read_csv(_write(tmp_path, HEADER + ",accel_x_m_s2,accel_y_m_s2\n0,0,0,0,0,0\n", "g.csv"), columns=())


def test_parquet_round_trip_bit_exact_with_metadata(tmp_path):
    rec = _rec(1000, seed=6)
    p = tmp_path / "r.parquet"
    rc.write_recording(rec, p)
    assert rc.is_parquet(p)
    back = _strict(rc.read_recording, p)
    for name in ("t_s", "gyro_rad_s", "accel_m_s2", "temp_c", "ref_rate_rad_s", "ref_quat_wxyz"):
        assert np.array_equal(getattr(back, name), getattr(rec, name)), name
    assert back.meta == rec.meta and np.array_equal(back.extra["flag"], rec.extra["flag"])
    chunks = list(rc.iter_chunks(p, rows=300, columns=("ref_quat",)))
    assert [c.n for c in chunks] == [300, 300, 300, 100]
    assert np.array_equal(np.vstack([c.ref_quat_wxyz for c in chunks]), rec.ref_quat_wxyz)
    # CSV -> Parquet -> CSV by streaming is bit-exact too
    rc.write_chunks(rc.iter_chunks(p, rows=256), tmp_path / "b.csv")
    assert np.array_equal(_strict(read_csv, tmp_path / "b.csv").gyro_rad_s, rec.gyro_rad_s)


def test_parquet_bad_input_one_line_errors(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    p = tmp_path / "x.parquet"
    p.write_bytes(b"PAR1 not really")
    with pytest.raises(GyroInputError, match="not a readable Parquet file"):
        rc.read_recording(p)
    (tmp_path / "e.parquet").write_bytes(b"")
    with pytest.raises(GyroInputError, match="empty file"):
        rc.read_recording(tmp_path / "e.parquet")
    pq.write_table(pa.table({"t_s": [0.0, 0.1], "gyro_x_rad_s": ["a", "b"]}), tmp_path / "s.parquet")
    with pytest.raises(GyroInputError, match="column 'gyro_x_rad_s' is not numeric"):
        rc.read_recording(tmp_path / "s.parquet")
    pq.write_table(pa.table({"t_s": [0.0, 0.1], "gyro_x_rad_s": [0.0, 1.0]}), tmp_path / "m.parquet")
    with pytest.raises(GyroInputError, match="incomplete column group, missing gyro_y_rad_s"):
        rc.read_recording(tmp_path / "m.parquet")
    # nulls are read as NaN and those rows dropped, with the same warnings as empty CSV fields
    cols = {
        "t_s": [0.0, 0.1, 0.2],
        "gyro_x_rad_s": [0.0, None, 0.0],
        "gyro_y_rad_s": [0.0] * 3,
        "gyro_z_rad_s": [0.0] * 3,
    }
    pq.write_table(pa.table(cols), tmp_path / "n.parquet")
    with pytest.warns(RepairWarning) as w:
        r = rc.read_recording(tmp_path / "n.parquet", checks=False)
    msgs = " | ".join(str(x.message) for x in w)
    assert "1 empty fields read as missing" in msgs and "dropped 1 rows" in msgs and r.n == 2


def test_still_check_without_reading_the_accel_columns(tmp_path):
    """A still deg/s recording labelled rad/s is warned about even when only the gyro is
    asked for (the accel is reduced to running moments, never held)."""
    rng = np.random.default_rng(3)
    n = 2000
    rec = Recording(
        t_s=np.arange(n) * 0.01,
        gyro_rad_s=rng.normal(0, 0.1, (n, 3)) + [4.5, 0.1, 1.0],
        accel_m_s2=rng.normal(0, 0.02, (n, 3)) + [0, 0, 9.81],
    )
    for name in ("s.csv", "s.parquet"):
        rc.write_recording(rec, tmp_path / name)
        with pytest.warns(RepairWarning, match="is it deg/s labelled rad/s"):
            got = rc.read_recording(tmp_path / name, columns=())
        assert got.accel_m_s2 is None
    m = csvtext._Moments([0])
    x = rec.accel_m_s2[:, 2]
    for k in range(0, n, 300):
        m.update({0: x[k : k + 300].copy()})
    assert m.std()[0] == pytest.approx(np.std(x), rel=1e-12)
