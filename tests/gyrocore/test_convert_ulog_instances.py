"""PX4 logs of a flight controller with several IMUs (a new user's CubeOrange): the
temperature column must come from the gyro that `sensor_combined` carries, not from
`sensor_gyro` instance 0."""

from __future__ import annotations

import numpy as np
import pytest
import pyulog

from gyrocore import convert as cv


def test_temperature_of_the_selected_gyro(shared_data):
    """sample_log_small.ulg: three gyros at 40.0, 28.2 and 29.6 °C; PX4 selected device 2424842
    (instance 0)."""
    with pytest.warns(UserWarning, match="held at its nearest value"):
        rec = cv.read_ulog(shared_data / "pyulog_samples" / "sample_log_small.ulg")
    assert "sensor_gyro[0]" in rec.meta["temperature"] and "2424842" in rec.meta["temperature"]
    assert 39.5 < float(np.median(rec.temp_c)) < 41.0


def test_temperature_follows_a_selection_of_the_second_imu(shared_data, monkeypatch):
    """The same log with sensor_selection naming the second IMU (device 3670050, instance 1, as
    when CAL_GYRO_PRIME or a failover picks it): the temperature is that chip's 28 °C, not
    instance 0's 40 °C (before: always instance 0, 12 °C off)."""

    class Selected2(pyulog.ULog):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            for d in self.data_list:
                if d.name == "sensor_selection":
                    d.data["gyro_device_id"] = np.full_like(d.data["gyro_device_id"], 3670050)

    monkeypatch.setattr(pyulog, "ULog", Selected2)
    with pytest.warns(UserWarning, match="held at its nearest value"):
        rec = cv.read_ulog(shared_data / "pyulog_samples" / "sample_log_small.ulg")
    assert "sensor_gyro[1]" in rec.meta["temperature"] and "3670050" in rec.meta["temperature"]
    assert 27.5 < float(np.median(rec.temp_c)) < 29.0
