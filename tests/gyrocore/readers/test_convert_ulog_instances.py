"""PX4 logs of a flight controller with several IMUs (a new user's CubeOrange): the
temperature column must come from the gyro that `sensor_combined` carries, not from
`sensor_gyro` instance 0."""

from __future__ import annotations

import numpy as np
import pytest
import pyulog

from gyrocore.readers import convert as cv


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


def test_gyro_instance_option(shared_data, tmp_path, monkeypatch, capsys):
    """`convert LOG.ulg --gyro-instance N`: one of a board's gyros, before PX4's calibration.

    On the real log the instances are at 1 Hz (PX4's default profile): one error line naming the
    rate and the profiles that log them faster. With instance 1 stretched to the 10 Hz of PX4's
    thermal-calibration profile (its own 6 samples, timestamps spread 10x denser, values
    untouched), it converts: that gyro's values and temperature, the selection named."""
    from gyrocore.cli import build_group, run_cli

    src = shared_data / "pyulog_samples" / "sample_log_small.ulg"
    g = build_group(["gyrocore.cli.commands"])
    assert run_cli(g, ["convert", str(src), "--gyro-instance", "1", "-o", str(tmp_path / "a.csv")]) == 2
    err = capsys.readouterr().err
    assert "logged at 1 Hz" in err and "10 Hz" in err and len(err.strip().splitlines()) == 1
    assert run_cli(g, ["convert", str(src), "--gyro-instance", "7", "-o", str(tmp_path / "a.csv")]) == 2
    assert "instances: 0, 1, 2" in capsys.readouterr().err

    class TenHz(pyulog.ULog):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            for d in self.data_list:
                if d.name == "sensor_gyro":
                    for key in ("timestamp", "timestamp_sample"):
                        t = d.data[key].astype(np.int64)
                        d.data[key] = (t[0] + (t - t[0]) // 10).astype(d.data[key].dtype)

    monkeypatch.setattr(pyulog, "ULog", TenHz)
    with pytest.warns(UserWarning, match="enough for bias against temperature"):
        rec = cv.load_any(src, gyro_instance=1)
    raw = pyulog.ULog(str(src)).get_dataset("sensor_gyro", 1)
    np.testing.assert_array_equal(rec.gyro_rad_s[:, 0], raw.data["x"].astype(float))
    assert 27.5 < float(np.median(rec.temp_c)) < 29.0 and rec.accel_m_s2 is None
    assert rec.rate_hz == pytest.approx(10.0, rel=0.05)
    assert "sensor_gyro[1] (device 3670050)" in rec.meta["sensor"] and "not this one" in rec.meta["selected_gyro"]
