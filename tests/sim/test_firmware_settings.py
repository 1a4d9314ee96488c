"""Firmware settings from --set, a diff file and a blackbox header (4.6.0 CLI lines)."""

from __future__ import annotations

import pytest

from gyrocore.errors import GyroInputError
from sim.firmware.bridge import BetaflightSITL
from sim.firmware.settings import parse_set_args, settings_from_blackbox, settings_from_diff

DIFF = """# diff
# version
# Betaflight / STM32F7X2 (S7X2) 4.5.1 Jun  1 2024 / 12:00:00 (abcdef) MSP API: 1.46
board_name SPEEDYBEEF7V3
manufacturer_id SPBE
mcu_id 0123456789
resource MOTOR 1 B06
feature -AIRMODE
serial 0 64 115200 57600 0 115200
aux 0 0 0 1800 2100 0 0
set motor_pwm_protocol = DSHOT600
set osd_vbat_pos = 2404
set gyro_lpf1_static_hz = 0
set dyn_notch_count = 2

profile 0
set p_roll = 48
save
"""


def test_set_args():
    assert parse_set_args(["gyro_lpf1_static_hz=150", "dyn_notch_q = 300"]).lines == (
        "set gyro_lpf1_static_hz = 150",
        "set dyn_notch_q = 300",
    )
    with pytest.raises(GyroInputError, match="NAME=VALUE"):
        parse_set_args(["gyro_lpf1_static_hz"])


def test_diff_keeps_flight_lines_only(tmp_path):
    p = tmp_path / "diff.txt"
    p.write_text(DIFF)
    fs = settings_from_diff(p)
    assert fs.lines == (
        "feature -AIRMODE",
        "aux 0 0 0 1800 2100 0 0",
        "set gyro_lpf1_static_hz = 0",
        "set dyn_notch_count = 2",
        "profile 0",
        "set p_roll = 48",
    )
    assert fs.lenient and "board/hardware" in fs.notes[0]


def test_blackbox_header_4_2_translated(shared_data):
    log = shared_data / "blackbox_public" / "LOG00037.BFL"
    if not log.exists():
        pytest.skip(f"{log} not present")
    lines = set(settings_from_blackbox(log).lines)
    # 4.2 names -> 4.6: gyro_lowpass_dyn_hz [240, 600], D 83 with d_min 55 (D-min -> D-max in 4.5)
    assert {
        "set gyro_lpf1_dyn_min_hz = 240",
        "set gyro_lpf1_dyn_max_hz = 600",
        "set gyro_lpf2_static_hz = 300",
        "set d_roll = 55",
        "set d_max_roll = 83",
        "set p_roll = 77",
        "set f_roll = 139",
        "set rpm_filter_harmonics = 3",
        "set rpm_filter_q = 800",
        "set dyn_notch_count = 1",
        "set dterm_lpf1_dyn_min_hz = 84",
        "set pid_process_denom = 1",
    } <= lines


def test_enum_index_from_a_header_is_read_as_the_name(firmware_binary):
    # blackbox headers log table indices: gyro_lpf1_type 1 = BIQUAD
    with BetaflightSITL(firmware_binary, lenient_settings=["set gyro_lpf1_type = 1"]) as fc:
        fc.boot(arm=False)
        assert fc.skipped_settings == []
    with pytest.raises(GyroInputError, match="gyro_lpf1_type = 9"):
        with BetaflightSITL(firmware_binary, ["set gyro_lpf1_type = 9"]) as fc:
            fc.boot(arm=False)
