"""The lockstep Betaflight bridge: one firmware loop per step, determinism, dead/hung SITL, settings."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from gyrocore.errors import GyroInputError
from sim.firmware.bridge import (
    GYRO_LSB_PER_RAD_S,
    BetaflightSITL,
    FirmwareError,
    gyro_to_lsb,
)


def test_gyro_to_lsb_axes_and_rounding():
    # S axes unchanged, 16.4 LSB/(°/s), nearest LSB, clipped to int16
    w = np.array([[1.0, 1.0, -1.0], [0.5 / GYRO_LSB_PER_RAD_S, -2.6 / GYRO_LSB_PER_RAD_S, 100.0]])
    got = gyro_to_lsb(w)
    assert got.dtype == np.int16
    k = GYRO_LSB_PER_RAD_S
    assert got[0].tolist() == [round(k), round(k), -round(k)]
    assert got[1].tolist() == [0, -3, 32767]  # 0.5 rounds to even (0); 100 rad/s saturates


def test_one_loop_per_step_virtual_clock(firmware_binary):
    with BetaflightSITL(firmware_binary) as fc:
        boot = fc.boot(arm=True)
        assert boot.armed
        # the firmware's own motion-gated boot calibration ran on the virtual gyro:
        # gyro_calib_duration 125 (1.25 s) = 10000 loops at 8 kHz
        assert boot.calibration_steps == 10000
        prev = None
        for _ in range(400):
            r = fc.step((0.0, 0.0, 0.0), rc=(1000, 1500, 1500, 1500))
            if prev is not None:
                assert r.loop_count == prev.loop_count + 1  # exactly one gyro pass
                assert r.pid_loop_count == prev.pid_loop_count + 1  # and one PID/mixer pass
                assert r.time_us == prev.time_us + 125  # 8 kHz of virtual time
            prev = r
        assert r.armed


# S = x forward, y left, z up. A rate the vehicle did not ask for must be opposed:
# +x (right side going down) -> the right motors (1 rear-right, 2 front-right) push harder;
# +y (nose going down) -> the front motors (2, 4); +z (nose turning left, counter-clockwise
# seen from above) -> a clockwise reaction torque: the counter-clockwise-spinning motors (2
# front-right and 3 rear-left in Betaflight's default quad-X) speed up.
@pytest.mark.parametrize("axis, up, down", [(0, (0, 1), (2, 3)), (1, (1, 3), (0, 2)), (2, (1, 2), (0, 3))])
def test_a_rate_about_each_axis_drives_the_motors_that_oppose_it(firmware_binary, axis, up, down):
    w = [0.0, 0.0, 0.0]
    w[axis] = 0.5
    with BetaflightSITL(firmware_binary) as fc:
        fc.boot()
        for _ in range(80):  # 10 ms, before the I term saturates the outputs
            r = fc.step(w, rc=(1400, 1500, 1500, 1500))
        m = r.motors
        assert min(m[i] for i in up) > max(m[i] for i in down) + 0.02, (axis, m)


def test_fw_gyro_is_the_input_in_s(firmware_binary):
    with BetaflightSITL(firmware_binary) as fc:
        fc.boot(arm=False)
        w = (0.5, -0.25, 0.125)
        for _ in range(800):  # 0.1 s: the dynamic notches (Q 3 at >= 100 Hz) ring out in ~10 ms
            r = fc.step(w)
        # a constant passes the low-passes and notches unchanged: same axes, same signs
        assert r.fw_gyro_S_rad_s == pytest.approx(w, abs=2 / GYRO_LSB_PER_RAD_S)
        # the firmware scales counts by its GYRO_SCALE_2000DPS = 2000/32768 °/s per LSB (0.1 % above
        # the 1/16.4 the chip's datasheet and the bridge use: a real board's scale error, kept)
        fw_scale = 2000.0 / 32768.0 * np.pi / 180.0
        assert r.fw_gyro_unfiltered_S_rad_s == pytest.approx(gyro_to_lsb(w) * fw_scale, rel=1e-6)


def test_boot_calibration_measures_the_still_gyro_bias(firmware_binary):
    # A still vehicle whose gyro reads a constant offset: the firmware's calibration estimates it
    # (to the LSB: the offset is averaged over 10000 identical quantised samples).
    bias = np.array([0.01, -0.02, 0.005])

    def still(k):
        return bias, (0.0, 0.0, 9.80665)

    with BetaflightSITL(firmware_binary) as fc:
        boot = fc.boot(still, arm=False)
        lsb = gyro_to_lsb(bias).astype(float)
        assert boot.gyro_bias_S_rad_s == pytest.approx(lsb / GYRO_LSB_PER_RAD_S, abs=1e-9)
        r = fc.step(bias)
        assert r.fw_gyro_unfiltered_S_rad_s == pytest.approx([0, 0, 0], abs=1e-9)


def _flight(binary, seed):
    rng = np.random.default_rng(seed)
    w = rng.normal(0.0, 0.3, (600, 3))
    out = []
    with BetaflightSITL(binary, ["set gyro_lpf1_static_hz = 120"]) as fc:
        fc.boot()
        for k in range(w.shape[0]):
            out.append(fc.step_raw(gyro_to_lsb(w[k]).tolist(), rc=(1300, 1500, 1500, 1500)))
    return np.array(out, dtype=object)


def test_same_inputs_byte_identical(firmware_binary):
    a, b = _flight(firmware_binary, 7), _flight(firmware_binary, 7)
    assert a.tolist() == b.tolist()


def test_killed_sitl_ends_with_one_line(firmware_binary):
    with BetaflightSITL(firmware_binary, step_timeout_s=2.0) as fc:
        fc.boot(arm=False)
        os.kill(fc.pid, signal.SIGKILL)
        t0 = time.monotonic()
        with pytest.raises(FirmwareError) as ei:
            for _ in range(10):
                fc.step((0.0, 0.0, 0.0))
        assert time.monotonic() - t0 < 2.0 + 1.0
    msg = str(ei.value)
    assert "\n" not in msg and "killed by signal 9" in msg and "last log lines" in msg


def test_hung_sitl_ends_with_one_line_within_the_timeout(firmware_binary):
    with BetaflightSITL(firmware_binary, step_timeout_s=0.5) as fc:
        fc.boot(arm=False)
        pid = fc.pid
        os.kill(pid, signal.SIGSTOP)
        t0 = time.monotonic()
        with pytest.raises(FirmwareError) as ei:
            fc.step((0.0, 0.0, 0.0))
        waited = time.monotonic() - t0
        assert fc.pid is None  # the bridge killed it
    msg = str(ei.value)
    assert "\n" not in msg and "did not answer" in msg and f"pid {pid}" in msg
    assert 0.5 <= waited < 0.5 + 1.0


def test_refused_setting_names_it(firmware_binary):
    with pytest.raises(FirmwareError, match="gyro_lpf1_static_hz = 99999.*Allowed range") as ei:
        with BetaflightSITL(firmware_binary, ["set gyro_lpf1_static_hz = 99999"]) as fc:
            fc.boot()
    assert "\n" not in str(ei.value)
    with pytest.raises(FirmwareError, match="no_such_setting"):
        with BetaflightSITL(firmware_binary, ["no_such_setting = 1"]) as fc:
            fc.boot()


def test_unknown_setting_skipped_when_asked(firmware_binary):
    with pytest.warns(UserWarning, match="osd_vbat_pos"):
        with BetaflightSITL(
            firmware_binary, ["set osd_vbat_pos = 2404", "set gyro_lpf1_static_hz = 100"], skip_unknown=True
        ) as fc:
            fc.boot(arm=False)
            assert fc.skipped_settings == ["set osd_vbat_pos = 2404"]


def test_instances_run_side_by_side(firmware_binary):
    with BetaflightSITL(firmware_binary) as a, BetaflightSITL(firmware_binary) as b:
        a.boot(arm=False)
        b.boot(arm=False)
        assert a.workdir != b.workdir
        ra, rb = a.step((0.1, 0, 0)), b.step((-0.1, 0, 0))
        assert ra.fw_gyro_unfiltered_S_rad_s[0] == -rb.fw_gyro_unfiltered_S_rad_s[0]


def test_bad_arguments_are_one_line(tmp_path, firmware_binary):
    with pytest.raises(GyroInputError, match="no firmware binary"):
        BetaflightSITL(tmp_path / "nope")
    with pytest.raises(GyroInputError, match="8000 Hz"):
        BetaflightSITL(firmware_binary, loop_rate_hz=4000)


def test_udp_link_when_the_socket_path_is_too_long(firmware_binary, tmp_path):
    # a Unix socket path is limited to 107 bytes: a deep working folder falls back to loopback UDP
    deep = tmp_path / ("d" * 120)
    with BetaflightSITL(firmware_binary, workdir=deep) as fc:
        fc.boot(arm=False)
        assert fc._sock.family.name == "AF_INET"
        r = fc.step((0.1, 0.0, 0.0))
        assert r.loop_count > 0
    with BetaflightSITL(firmware_binary) as fc:
        fc.boot(arm=False)
        assert fc._sock.family.name == "AF_UNIX"
