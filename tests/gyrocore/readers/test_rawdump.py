"""Raw MPU-6050 dumps as an Arduino sketch or a logger writes them (gyrocore.readers.rawdump).

Built here from tomisuarez2's 100-s static MPU-6050 log (../shared/data; raw LSB, 100 Hz) in
the layouts users post: ``millis,AcX,AcY,AcZ,Tmp,GyX,GyY,GyZ``; ``ax;ay;az;gx;gy;gz`` without
time; ``micros`` (tab-separated) across its 32-bit wrap. Before, each was "missing required
column t_s"; now the counts are scaled like the tomisuarez2 reader does (same numbers), and a
table that is not counts, or a time without a unit, is one line saying what to do.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from gyrocore.errors import GyroInputError, RepairWarning
from gyrocore.readers import convert as cv
from gyrocore.readers.rawdump import read_raw_dump
from tests.gyrocore.test_bad_input import gh


@pytest.fixture(scope="module")
def counts(shared_data):
    """(N, 6) ax, ay, az, gx, gy, gz counts and the tomisuarez2 reader's Recording of them."""
    src = shared_data / "tomisuarez2_mpu6050" / "imu_static_test.csv"
    return np.loadtxt(src, delimiter=",", skiprows=5), cv.read_tomisuarez2(src)


def _write(path, header, rows, sep=","):
    path.write_text(sep.join(header) + "\n" + "".join(sep.join(str(int(v)) for v in r) + "\n" for r in rows))
    return path


def test_arduino_sketch_layout_with_millis_and_temperature(tmp_path, counts):
    A, ref = counts
    n = A.shape[0]
    ms = np.arange(n) * 10 + 123456
    tmp = np.full(n, -2500)
    rows = np.column_stack([ms, A[:, :3], tmp, A[:, 3:]])
    p = _write(tmp_path / "dump.csv", ["millis", "AcX", "AcY", "AcZ", "Tmp", "GyX", "GyY", "GyZ"], rows)
    assert cv.detect_format(p) == "raw_dump"
    rec = cv.load_any(p)
    assert np.array_equal(rec.gyro_rad_s, ref.gyro_rad_s)  # same counts, same 131 LSB/(deg/s)
    assert np.array_equal(rec.accel_m_s2, ref.accel_m_s2)
    assert np.allclose(rec.t_s, np.arange(n) * 0.01, rtol=0, atol=1e-12)
    assert np.allclose(rec.temp_c, -2500 / 340 + 36.53)  # MPU-6050 register map: count/340 + 36.53


def test_no_time_column_needs_the_rate(tmp_path, counts):
    A, ref = counts
    p = _write(tmp_path / "d.csv", ["ax", "ay", "az", "gx", "gy", "gz"], A, sep=";")
    with pytest.raises(GyroInputError, match=r"raw dump without a time column .*--rate-hz HZ"):
        cv.load_any(p)
    rec = cv.load_any(p, rate_hz=100.0)
    assert np.array_equal(rec.gyro_rad_s, ref.gyro_rad_s) and np.array_equal(rec.t_s, ref.t_s)


def test_micros_wrap_is_undone(tmp_path, counts):
    A, _ = counts
    n = A.shape[0]
    us = (np.arange(n, dtype=np.int64) * 10_000 + 2**32 - 5_000_000) % 2**32  # wraps after 500 samples
    p = _write(tmp_path / "d.tsv", ["micros", "gyro_x", "gyro_y", "gyro_z"], np.column_stack([us, A[:, 3:]]), sep="\t")
    with pytest.warns(RepairWarning, match="1 32-bit counter wrap"):
        rec = read_raw_dump(p)
    assert np.allclose(np.diff(rec.t_s), 0.01, rtol=0, atol=1e-9)


def test_physical_units_and_unitless_time_are_refused(tmp_path, counts):
    A, _ = counts
    p = tmp_path / "phys.csv"
    p.write_text(
        "t_ms,gx,gy,gz\n"
        + "".join(f"{10 * i},{r[3] / 131:.4f},{r[4] / 131:.4f},{r[5] / 131:.4f}\n" for i, r in enumerate(A[:50]))
    )
    with pytest.raises(GyroInputError, match="hold fractions, not raw counts"):
        read_raw_dump(p)
    p = _write(tmp_path / "t.csv", ["time", "gx", "gy", "gz"], np.column_stack([np.arange(50), A[:50, 3:]]))
    with pytest.raises(GyroInputError, match=r"column 'time' has no unit in its name"):
        read_raw_dump(p)
    p.write_text("millis,gx,gy,gz\n0,1,2,3\n10,1,x2,3\n")
    with pytest.raises(GyroInputError, match=r"line 3, column 'gy': text in a number \('x2'\)"):
        read_raw_dump(p)


def test_commands_read_a_dump_directly(capsys, tmp_path, counts):
    A, _ = counts
    n = A.shape[0]
    p = _write(
        tmp_path / "dump.csv", ["millis", "ax", "ay", "az", "gx", "gy", "gz"], np.column_stack([np.arange(n) * 10, A])
    )
    conv = tmp_path / "c.csv"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s1, out1, e1 = gh(capsys, "bias", p, "--json")
        assert gh(capsys, "convert", p, "-o", conv)[0] == 0
        s2, out2, e2 = gh(capsys, "bias", conv, "--json")
    assert s1 == 0 and s2 == 0, (e1, e2)
    assert json.loads(out1)["bias_rad_s"] == json.loads(out2)["bias_rad_s"]


def test_batch_reads_dumps_as_the_commands_do(capsys, tmp_path, counts):
    """`batch bias DIR` ran read_recording: a raw dump in the folder failed with "missing t_s"."""
    A, _ = counts
    n = A.shape[0]
    d = tmp_path / "logs"
    d.mkdir()
    _write(d / "dump.csv", ["millis", "ax", "ay", "az", "gx", "gy", "gz"], np.column_stack([np.arange(n) * 10, A]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s, out, err = gh(capsys, "batch", "bias", d, "--json", "-o", tmp_path / "t.csv")
    res = json.loads(out)
    assert s == 0 and res["n_failed"] == 0, (err, res.get("failed"))


def test_units_in_brackets_are_converted(tmp_path, counts):
    """Another user's table with its units in the header (``Timestamp [ms]``, ``Gyro X (deg/s)``,
    ``Acc X [g]``, ``Temp [°C]``): converted to SI, never scaled as counts; the same numbers as
    the tomisuarez2 reader to float rounding (the %.9g text of the values)."""
    A, ref = counts
    n = A.shape[0]
    dps = A[:, 3:] / 131.0
    g = A[:, :3] / 16384.0
    p = tmp_path / "units.csv"
    p.write_text(
        "Timestamp [ms],Gyro X (deg/s),Gyro Y (deg/s),Gyro Z (deg/s),Acc X [g],Acc Y [g],Acc Z [g],Temp [°C]\n"
        + "".join(
            f"{10 * i},{r[0]:.9g},{r[1]:.9g},{r[2]:.9g},{a[0]:.9g},{a[1]:.9g},{a[2]:.9g},25.5\n"
            for i, (r, a) in enumerate(zip(dps, g))
        )
    )
    assert cv.detect_format(p) == "raw_dump"
    rec = cv.load_any(p)
    assert np.allclose(rec.gyro_rad_s, ref.gyro_rad_s, rtol=1e-8, atol=0)
    assert np.allclose(rec.accel_m_s2, ref.accel_m_s2, rtol=1e-8, atol=0)
    assert np.allclose(rec.t_s, np.arange(n) * 0.01) and np.all(rec.temp_c == 25.5)
    p.write_text("time (s),gx (deg/s),gy (rad/s),gz (deg/s)\n0,1,2,3\n0.01,1,2,3\n")
    with pytest.raises(GyroInputError, match="give different units"):
        cv.load_any(p)


def test_the_x_io_layout_stays_its_own_reader(shared_data):
    assert cv.detect_format(shared_data / "fusion_xio" / "sensor_data.csv") == "fusion"
