"""Experiments flown by the firmware (experiments/firmware_filter.py, firmware_cutoffs.py): the parts
without the binary. The flown campaigns are in tests/sim/test_fw_flight_firmware.py (they need the
``firmware_binary`` fixture of tests/sim/conftest.py)."""

from __future__ import annotations

import pytest

from experiments.firmware_cutoffs import cell_settings
from experiments.firmware_filter import candidates, changed_lines
from gyrocore.errors import GyroInputError


def test_recommendation_lines_change_only_what_they_must():
    tune = [
        "set gyro_lpf1_type = PT1",
        "set gyro_lpf1_static_hz = 90",
        "set gyro_lpf2_static_hz = 0",
        "set dyn_notch_count = 0",
        "aux 0 0 0 1700 2100 0 0",
    ]
    c = candidates()
    # the tune already has PT1 and no lpf2: only the cutoff and the dynamic-LPF switch are new
    assert changed_lines(tune, c["pt1 150 Hz"]) == ["set gyro_lpf1_static_hz = 150", "set gyro_lpf1_dyn_min_hz = 0"]
    assert changed_lines(tune, c["no_dyn_notch"]) == []  # already off in the tune
    assert changed_lines(tune, c["as_flown"]) == []
    assert set(c) >= {"as_flown", "none", "no_rpm_filter", "no_gyro_lowpass"}


def test_cutoffs_cells_are_firmware_settings():
    s = dict(x.split(" = ") for x in (f"{k} = {v}" for k, v in cell_settings("pt2", 90.0)))
    assert s["gyro_lpf1_type"] == "PT2" and s["gyro_lpf1_static_hz"] == "90"
    assert s["gyro_lpf2_static_hz"] == "0" and s["dyn_notch_count"] == "0" and s["rpm_filter_harmonics"] == "0"
    assert dict(cell_settings("none", 0.0))["gyro_lpf1_static_hz"] == "0"
    with pytest.raises(GyroInputError, match="no firmware gyro_lpf1_type"):
        cell_settings("butter4", 90.0)
