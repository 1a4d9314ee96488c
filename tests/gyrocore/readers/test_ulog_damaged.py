"""PX4 ULogs that lack what the reader expects, built from sample_log_small.ulg (../shared/data).

The field and topic names are renamed in place (same length, so the file stays a valid ULog):
a sensor_combined without ``gyro_rad`` (a layout this reader does not know) was a KeyError
traceback, one without the accelerometer the same; a log without sensor_combined said only
"no sensor_combined topic". Now: one line naming the fields / the gyro topics the log has, and
a gyro-only recording when only the accelerometer is missing.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from gyrocore.errors import GyroInputError
from gyrocore.readers.ulog import read_ulog


@pytest.fixture(scope="module")
def small(shared_data):
    return (shared_data / "pyulog_samples" / "sample_log_small.ulg").read_bytes()


def _read(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_ulog(path)


def test_unknown_sensor_combined_layout_is_one_line(small, tmp_path):
    p = tmp_path / "f.ulg"
    p.write_bytes(small.replace(b"gyro_rad", b"gyro_rax"))
    with pytest.raises(GyroInputError, match=r"sensor_combined has no gyro_rad\[0\].*its fields: .*gyro_rax"):
        _read(p)


def test_sensor_combined_without_accelerometer_is_gyro_only(small, shared_data, tmp_path):
    p = tmp_path / "f.ulg"
    p.write_bytes(small.replace(b"accelerometer_m_s2", b"accelerometer_m_sX"))
    rec, ref = _read(p), _read(shared_data / "pyulog_samples" / "sample_log_small.ulg")
    assert rec.accel_m_s2 is None and np.array_equal(rec.gyro_rad_s, ref.gyro_rad_s)
    assert "gyro only" in rec.meta["repairs"]


def test_missing_sensor_combined_names_the_gyro_topics(small, tmp_path):
    p = tmp_path / "f.ulg"
    p.write_bytes(small.replace(b"sensor_combined", b"sensor_combinex"))
    # sample_log_small logs sensor_gyro 0-2 at 1 Hz (too slow for --gyro-instance) and
    # vehicle_angular_velocity at ~279 Hz
    with pytest.raises(
        GyroInputError, match=r"no sensor_combined topic .*it logs sensor_gyro 0 \(1 Hz\).*vehicle_angular_velocity 0"
    ) as e:
        _read(p)
    assert "--gyro-instance" not in str(e.value)
