"""Lockstep bridge to the Betaflight SITL built by :mod:`sim.firmware.build`.

The firmware runs as a separate process (GPL-3.0 boundary) and talks over a Unix datagram
socket in its working folder (loopback UDP when that path is too long); its clock is virtual
and advances only with the simulator's packets, so one :meth:`BetaflightSITL.step` is exactly one gyro/filter/PID/mixer pass at the firmware's loop rate
(8 kHz by default), with no wall clock anywhere in the loop and byte-identical results for the
same inputs. Each instance has its own working folder (``eeprom.bin``, the socket, the log) and
takes a free TCP port from the kernel for the CLI on UART1, so several run side by side
(pytest-xdist, Dask workers).

Packets (little-endian, packed; defined in the patch's ``target/SITL/target.h``)
--------------------------------------------------------------------------------
In, 92 bytes, one per step (``<IId3h3h4f4f16H``):

=============  ==========  =====================================================================
field          type        meaning
=============  ==========  =====================================================================
magic          uint32      0x31494847 ("GHI1")
flags          uint32      0 (reserved)
timestamp      double      simulator time of this gyro sample, s (sets the firmware's clock)
gyro_lsb       int16 × 3   gyro, LSB: round(ω_S · 16.4 · 180/π) (S = the firmware's own axes)
acc_lsb        int16 × 3   specific force, LSB: round(f_S · 256/g) (level and still: (0, 0, 256))
quat_wxyz      float × 4   attitude q_WB (body to world, world z up); the SITL takes its attitude
                           from here (no estimator in the loop)
motor_hz       float × 4   rotor frequency |ω|/2π, Hz, Betaflight motor order; the firmware
                           turns it into bidirectional-DShot eRPM telemetry (period quantised as
                           the ESC sends it, ``motor_poles``, the ``rpm_filter_lpf_hz`` PT1)
channels       uint16 × 16 RC, µs: roll, pitch, throttle, yaw (AETR), then AUX1 (arm) … AUX12
=============  ==========  =====================================================================

Out, 188 bytes, one per step (``<IIIIQ4f4f3f3f3f3f3f3f3f3f3fIBBBB8h``): magic 0x314f4847
("GHO1"); step (packets processed); gyro_loops and pid_loops (task passes since boot);
time_us (firmware clock); motor[4] (throttle 0..1 = (command − 1000 µs)/1000 µs, Betaflight
order); motor_raw[4] (µs); gyro_adc[3] (``gyro.gyroADC``, °/s, firmware axes, calibration offset
removed, before the filters); gyro_adcf[3] (``gyro.gyroADCf``: the filtered gyro the PID uses);
dterm_in[3] (gyro after the D-term filters: the D term's input); pid_p/i/d/f[3] (``pidData``,
firmware units); setpoint[3] (°/s); gyro_zero[3] (LSB: the boot calibration's offset);
arming_disable_flags; armed; gyro_calibrated; motor_count; reserved; debug[8] (``debug_mode``).

Conventions
-----------
* Axes: Betaflight's body axes are the harness's sensor frame S: x forward, y left, z up, for
  the gyro and the accelerometer alike (its mixer: a positive roll command lowers the right side,
  a positive pitch command the nose, a positive yaw command turns the nose left; a still, level
  board reads +1 g on z). So vectors go in and come back unrotated, rad/s ↔ °/s only. (The stock
  SITL's (x, −y, −z) converts the Gazebo plugin's x-forward/y-right/z-down packet into these
  axes; the harness has no such packet.) The sign test in tests/sim/test_firmware_bridge.py
  checks that a rate about each axis drives the motors that oppose it.
* Quantisation: the firmware reads int16 LSB at 16.4 LSB/(°/s) (±2000 °/s, 0.061 °/s per LSB),
  as an ICM/MPU gyro's register delivers; the bridge rounds to the nearest LSB (the stock SITL
  truncated towards zero, a bias of up to one LSB) and clips to ±32767. The firmware converts
  counts with its own ``GYRO_SCALE_2000DPS`` = 2000/32768 °/s per LSB, 0.1 % above the
  datasheet's 1/16.4: a real board's scale error, kept (the replies are the firmware's °/s
  in rad/s; the boot-calibration offset is converted at the chip's 16.4 LSB/(°/s), so it compares
  with the simulated bias).
* Motors: Betaflight quad-X order (as PX4's output numbering is remapped by Betaflight's
  mixer): 1 rear-right, 2 front-right, 3 rear-left, 4 front-left; props-in (1 and 4 CW seen
  from above, 2 and 3 CCW) unless ``yaw_motors_reversed``. :data:`BF_MOTOR_POSITIONS_FLU`
  gives the positions.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from typing import NamedTuple
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gyrocore.errors import GyroInputError

__all__ = [
    "ACC_LSB_PER_M_S2",
    "BF_MOTOR_POSITIONS_FLU",
    "PX4_FROM_BF",
    "BF_FROM_PX4",
    "GYRO_LSB_PER_RAD_S",
    "IN_STRUCT",
    "LOOP_RATE_HZ",
    "OUT_STRUCT",
    "REPLY_DTYPE",
    "BetaflightSITL",
    "BootReport",
    "FirmwareError",
    "StepReply",
    "arming_flag_names",
    "gyro_to_lsb",
    "replies_to_arrays",
]

#: Virtual gyro sample rate of the SITL, Hz (one packet per sample).
LOOP_RATE_HZ = 8000.0
#: The firmware's gyro scale: 16.4 LSB per °/s (±2000 °/s range), in LSB per rad/s.
GYRO_LSB_PER_RAD_S = 16.4 * 180.0 / math.pi
#: The virtual accelerometer's scale: acc_1G = 256 LSB.
ACC_LSB_PER_M_S2 = 256.0 / 9.80665
_G = 9.80665
_DEG = math.pi / 180.0

MAGIC_IN = 0x31494847
MAGIC_OUT = 0x314F4847
IN_STRUCT = struct.Struct("<IId3h3h4f4f16H")
OUT_STRUCT = struct.Struct("<IIIIQ4f4f3f3f3f3f3f3f3f3f3fIBBBB8h")
#: The reply as a numpy structured dtype (same layout as :data:`OUT_STRUCT`).
REPLY_DTYPE = np.dtype(
    [
        ("magic", "<u4"),
        ("step", "<u4"),
        ("gyro_loops", "<u4"),
        ("pid_loops", "<u4"),
        ("time_us", "<u8"),
        ("motor", "<f4", 4),
        ("motor_raw", "<f4", 4),
        ("gyro_adc", "<f4", 3),
        ("gyro_adcf", "<f4", 3),
        ("dterm_in", "<f4", 3),
        ("pid_p", "<f4", 3),
        ("pid_i", "<f4", 3),
        ("pid_d", "<f4", 3),
        ("pid_f", "<f4", 3),
        ("setpoint", "<f4", 3),
        ("gyro_zero", "<f4", 3),
        ("arming_disable_flags", "<u4"),
        ("armed", "u1"),
        ("gyro_calibrated", "u1"),
        ("motor_count", "u1"),
        ("reserved", "u1"),
        ("debug", "<i2", 8),
    ]
)
assert IN_STRUCT.size == 92 and OUT_STRUCT.size == 188 == REPLY_DTYPE.itemsize

#: Betaflight quad-X motor positions in the body frame (x fwd, y left), unit arm: motor 1..4.
BF_MOTOR_POSITIONS_FLU = np.array([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]]) / math.sqrt(2.0)
#: PX4 quad-X numbering (the MuJoCo models' rotor_1..4: front-right, rear-left, front-left,
#: rear-right; 1-2 CCW, 3-4 CW) from Betaflight's (rear-right CW, front-right CCW, rear-left CCW,
#: front-left CW): ``px4 = bf[PX4_FROM_BF]``; and back: ``bf = px4[BF_FROM_PX4]``. Same spin
#: directions motor for motor, so only the numbering differs.
PX4_FROM_BF = np.array([1, 2, 3, 0])
BF_FROM_PX4 = np.array([3, 0, 1, 2])

_ARMING_FLAGS = (
    "NO_GYRO",
    "FAILSAFE",
    "RX_FAILSAFE",
    "NOT_DISARMED",
    "BOXFAILSAFE",
    "RUNAWAY_TAKEOFF",
    "CRASH_DETECTED",
    "THROTTLE",
    "ANGLE",
    "BOOT_GRACE_TIME",
    "NOPREARM",
    "LOAD",
    "CALIBRATING",
    "CLI",
    "CMS_MENU",
    "BST",
    "MSP",
    "PARALYZE",
    "GPS",
    "RESC",
    "DSHOT_TELEM",
    "REBOOT_REQUIRED",
    "DSHOT_BITBANG",
    "ACC_CALIBRATION",
    "MOTOR_PROTOCOL",
    "CRASHFLIP",
    "ALTHOLD",
    "POSHOLD",
    "ARM_SWITCH",
)
_ARM_SWITCH_FLAG = 1 << 28
_CALIBRATING_FLAG = 1 << 12

#: Settings the bridge applies before the user's (which may override them): the arm switch on
#: AUX1 (1700-2100 µs), and no 5-s power-on grace (a bench convenience; it does not change the
#: flight: the grace only blocks arming).
BASE_SETTINGS: tuple[str, ...] = ("aux 0 0 0 1700 2100 0 0", "set pwr_on_arm_grace = 0")

RC_LOW_US = 1000
RC_MID_US = 1500
ARM_ON_US = 1800


class FirmwareError(GyroInputError):
    """The firmware process died, hung, refused a setting or could not be armed (one line)."""


def arming_flag_names(flags: int) -> list[str]:
    """Names of the set bits of Betaflight's ``armingDisableFlags``."""
    return [n for i, n in enumerate(_ARMING_FLAGS) if flags & (1 << i)]


def gyro_to_lsb(omega_S_rad_s: np.ndarray) -> np.ndarray:
    """The int16 LSB the firmware reads for a sensor-frame rate: round(ω_S · 16.4 · 180/π), clipped.

    Parameters
    ----------
    omega_S_rad_s : array (..., 3), rad/s, sensor frame S.

    Returns
    -------
    ndarray (..., 3) int16 (the firmware's axes are S's).
    """
    x = np.rint(np.asarray(omega_S_rad_s, float) * GYRO_LSB_PER_RAD_S)
    return np.clip(x, -32767, 32767).astype(np.int16)


def _acc_to_lsb(accel_S_m_s2: np.ndarray) -> np.ndarray:
    x = np.rint(np.asarray(accel_S_m_s2, float) * ACC_LSB_PER_M_S2)
    return np.clip(x, -32767, 32767).astype(np.int16)


class StepReply(NamedTuple):
    """The firmware's answer to one step (one gyro/filter/PID/mixer pass).

    An immutable named tuple (built once per firmware loop: a tuple is the cheapest immutable
    record in Python); the vector fields are views into one array, taken when read.

    Attributes
    ----------
    motors : ndarray (4,)
        Throttle commands 0..1, Betaflight quad-X order (see module docstring).
    motors_raw_us : ndarray (4,)
        Motor commands as output, µs.
    fw_gyro_S_rad_s : ndarray (3,)
        The firmware's filtered gyro (``gyro.gyroADCf``) in the sensor frame S, rad/s.
    fw_gyro_unfiltered_S_rad_s : ndarray (3,)
        ``gyro.gyroADC`` (quantised, boot-calibration offset removed, before the filters), S, rad/s.
    fw_dterm_S_rad_s : ndarray (3,)
        The gyro after the D-term filters (the D term's input), S, rad/s.
    setpoint_S_rad_s : ndarray (3,)
        The rate setpoint, S, rad/s.
    pid_rpy : ndarray (4, 3)
        ``pidData`` P, I, D, F rows for roll, pitch, yaw (firmware axes and units).
    gyro_bias_S_rad_s : ndarray (3,)
        The firmware's boot-calibration estimate of the gyro offset (``gyroZero``), S, rad/s.
    loop_count : int
        Gyro task passes since boot.
    pid_loop_count : int
        PID task passes since boot.
    time_us : int
        Firmware clock, µs.
    armed, gyro_calibrated : bool
    arming_disable_flags : int
    debug : tuple of 8 int
        The firmware's ``debug[]`` (meaning set by ``debug_mode``).
    values : ndarray (35,)
        The reply's 35 floats in SI and S (motors, motors_raw_us, unfiltered gyro, filtered
        gyro, D-term input, P/I/D/F, setpoint, bias), the storage of the fields above.
    """

    values: np.ndarray
    loop_count: int
    pid_loop_count: int
    time_us: int
    armed: bool
    gyro_calibrated: bool
    arming_disable_flags: int
    debug: tuple

    @property
    def motors(self) -> np.ndarray:
        return self.values[0:4]

    @property
    def motors_raw_us(self) -> np.ndarray:
        return self.values[4:8]

    @property
    def fw_gyro_unfiltered_S_rad_s(self) -> np.ndarray:
        return self.values[8:11]

    @property
    def fw_gyro_S_rad_s(self) -> np.ndarray:
        return self.values[11:14]

    @property
    def fw_dterm_S_rad_s(self) -> np.ndarray:
        return self.values[14:17]

    @property
    def pid_rpy(self) -> np.ndarray:
        return self.values[17:29].reshape(4, 3)

    @property
    def setpoint_S_rad_s(self) -> np.ndarray:
        return self.values[29:32]

    @property
    def gyro_bias_S_rad_s(self) -> np.ndarray:
        return self.values[32:35]


_K_DEG = np.full(3, _DEG)
_K_LSB = np.full(3, 1.0 / GYRO_LSB_PER_RAD_S)
_INV_2PI = 1.0 / (2.0 * math.pi)
# one scale vector for the 35 floats of a reply (motors, motor_raw, gyro_adc, gyro_adcf, dterm_in,
# pid p/i/d/f, setpoint, gyro_zero): one array operation per step
_REPLY_SCALE = np.concatenate([np.ones(8), np.tile(_K_DEG, 3), np.ones(12), _K_DEG, _K_LSB])


def _clip16(v: int) -> int:
    return -32767 if v < -32767 else (min(v, 32767))


def _reply_from_tuple(r: tuple) -> StepReply:
    v = np.array(r[5:40], dtype=float)
    v *= _REPLY_SCALE
    return _new_reply((v, r[2], r[3], r[4], r[41] != 0, r[42] != 0, r[40], r[45:53]))


def _new_reply(values: tuple) -> StepReply:
    return tuple.__new__(StepReply, values)


def replies_to_arrays(replies: np.ndarray) -> dict[str, np.ndarray]:
    """Columns in SI and the sensor frame from an array of raw replies (dtype :data:`REPLY_DTYPE`).

    Returns a dict with the :class:`StepReply` field names, each stacked over steps (N, ...).
    """
    r = np.asarray(replies)
    f = lambda k, s: r[k].astype(float) * s
    return {
        "motors": r["motor"].astype(float),
        "motors_raw_us": r["motor_raw"].astype(float),
        "fw_gyro_S_rad_s": f("gyro_adcf", _K_DEG),
        "fw_gyro_unfiltered_S_rad_s": f("gyro_adc", _K_DEG),
        "fw_dterm_S_rad_s": f("dterm_in", _K_DEG),
        "setpoint_S_rad_s": f("setpoint", _K_DEG),
        "pid_rpy": np.stack([r["pid_p"], r["pid_i"], r["pid_d"], r["pid_f"]], axis=1).astype(float),
        "gyro_bias_S_rad_s": f("gyro_zero", _K_LSB),
        "loop_count": r["gyro_loops"].astype(np.int64),
        "pid_loop_count": r["pid_loops"].astype(np.int64),
        "time_us": r["time_us"].astype(np.int64),
        "armed": r["armed"].astype(bool),
        "gyro_calibrated": r["gyro_calibrated"].astype(bool),
        "arming_disable_flags": r["arming_disable_flags"].astype(np.int64),
        "debug": r["debug"].astype(np.int64),
    }


@dataclass(frozen=True)
class BootReport:
    """What :meth:`BetaflightSITL.boot` took (excluded from any scored flight).

    Attributes
    ----------
    steps : int
        Packets sent during boot (calibration wait + arming).
    sim_s : float
        Simulated time they cover, s.
    firmware_boot_s : float
        Firmware clock at the first packet (its own boot delays), s.
    calibration_steps : int
        Steps until the firmware's gyro calibration completed.
    gyro_bias_S_rad_s : ndarray (3,)
        The firmware's calibration estimate of the gyro offset, S, rad/s.
    armed : bool
    wall_s : float
        Wall-clock time of the boot (configuration run included), s.
    """

    steps: int
    sim_s: float
    firmware_boot_s: float
    calibration_steps: int
    gyro_bias_S_rad_s: np.ndarray
    armed: bool
    wall_s: float
    settings: tuple[str, ...] = field(default=())


StillSource = Callable[[int], tuple[Sequence[float], Sequence[float]]]


def _normalise_setting(line: str) -> str:
    s = line.strip()
    if not s:
        return s
    head = s.split(None, 1)[0].lower()
    if "=" in s and head not in {
        "set",
        "aux",
        "feature",
        "profile",
        "rateprofile",
        "beeper",
        "map",
        "serial",
        "adjrange",
        "rxrange",
        "vtx",
        "mixer",
        "mmix",
        "smix",
        "dshotprog",
    }:
        k, v = s.split("=", 1)
        return f"set {k.strip()} = {v.strip()}"
    return s


class BetaflightSITL:
    """One lockstep Betaflight SITL process: configure, boot, arm, step.

    Parameters
    ----------
    binary : str or path
        The lockstep SITL (:func:`sim.firmware.build.ensure_binary`).
    settings : sequence of str
        Firmware CLI lines applied after :data:`BASE_SETTINGS` (``set NAME = VALUE``, ``NAME =
        VALUE``, ``aux …``, ``feature …``, ``profile N``…), saved to the instance's eeprom.
    loop_rate_hz : float
        Packet (gyro sample) rate; must be the SITL's virtual gyro rate, 8000 Hz (use
        ``pid_process_denom`` for a slower PID loop).
    step_timeout_s : float
        Wall-clock limit for one step's reply (only to detect a dead or hung process).
    workdir : path or None
        Working folder (``eeprom.bin``, ``sitl.log``); default a fresh temporary folder that is
        removed on :meth:`close`.
    skip_unknown : bool
        Settings whose NAME this firmware does not have are skipped with one warning instead of
        an error. A refused VALUE is always an error; a number given for an enum setting (as a
        blackbox header logs it) is read as the index into the firmware's allowed names.
    lenient_settings : sequence of str
        Lines applied before ``settings`` with unknown names skipped (one warning): for diffs and
        log headers from other boards (OSD, VTX, …) (:mod:`sim.firmware.settings`).
    idle_exit_s : float
        The SITL exits by itself when no packet arrives for this long (wall clock): no orphan
        process outlives a caller that died without :meth:`close`. Keep it longer than any pause
        between :meth:`boot` and the flight's steps.
    """

    def __init__(
        self,
        binary: str | os.PathLike,
        settings: Sequence[str] = (),
        *,
        loop_rate_hz: float = LOOP_RATE_HZ,
        step_timeout_s: float = 5.0,
        workdir: str | os.PathLike | None = None,
        skip_unknown: bool = False,
        lenient_settings: Sequence[str] = (),
        cli_timeout_s: float = 10.0,
        idle_exit_s: float = 300.0,
    ) -> None:
        self.binary = str(binary)
        if not (os.path.isfile(self.binary) and os.access(self.binary, os.X_OK)):
            raise GyroInputError(f"{binary}: no firmware binary there (build it: gyroharness firmware build)")
        if abs(float(loop_rate_hz) - LOOP_RATE_HZ) > 1e-9:
            raise GyroInputError(
                f"loop_rate_hz={loop_rate_hz}: the SITL's virtual gyro samples at "
                f"{LOOP_RATE_HZ:.0f} Hz (set pid_process_denom for a slower PID loop)"
            )
        if not step_timeout_s > 0:
            raise GyroInputError(f"step_timeout_s must be > 0, got {step_timeout_s}")
        self.loop_rate_hz = float(loop_rate_hz)
        self.dt_s = 1.0 / self.loop_rate_hz
        self.step_timeout_s = float(step_timeout_s)
        self.cli_timeout_s = float(cli_timeout_s)
        if not idle_exit_s > step_timeout_s:
            raise GyroInputError(f"idle_exit_s ({idle_exit_s}) must exceed step_timeout_s ({step_timeout_s})")
        self.idle_exit_s = float(idle_exit_s)
        self.skip_unknown = bool(skip_unknown)
        self.settings = tuple(s for s in (_normalise_setting(x) for x in settings) if s)
        self.lenient_settings = tuple(s for s in (_normalise_setting(x) for x in lenient_settings) if s)
        self._own_workdir = workdir is None
        self.workdir = Path(tempfile.mkdtemp(prefix="gyroharness-sitl-")) if workdir is None else Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.skipped_settings: list[str] = []
        self._proc: subprocess.Popen | None = None
        self._log = None
        self._sock: socket.socket | None = None
        self._k = 0  # packets sent to the current process
        self._rbuf = bytearray(OUT_STRUCT.size)
        self._rview = memoryview(self._rbuf)
        self._pbuf = bytearray(IN_STRUCT.size)
        self._rc = [RC_MID_US, RC_MID_US, RC_LOW_US, RC_MID_US] + [RC_LOW_US] * 12
        self._rc_last: tuple = ()
        self._configured = False
        self.boot_report: BootReport | None = None

    # ------------------------------------------------------------------ process
    @property
    def log_path(self) -> Path:
        return self.workdir / "sitl.log"

    def log_tail(self, n: int = 5) -> str:
        """The last ``n`` lines of the firmware's output, joined with `` | ``."""
        try:
            lines = self.log_path.read_text(errors="replace").strip().splitlines()
        except OSError:
            return "(no log)"
        return " | ".join(x.strip() for x in lines[-n:]) or "(empty log)"

    def _spawn(self) -> tuple[int | str, int]:
        self._kill()
        self._log = open(self.log_path, "ab")
        mark = self.log_path.stat().st_size
        # the lockstep link: a Unix datagram socket in the working folder (about 1 µs less per
        # send/receive than loopback UDP), UDP on a free port when the path is too long
        sitl_sock = self.workdir / "sitl.sock"
        unix = len(str(sitl_sock)) < 100
        link = ["--unix", str(sitl_sock)] if unix else ["--port", "0"]
        self._proc = subprocess.Popen(
            [self.binary, *link, "--tcp-port", "0", "--idle-exit-s", str(self.idle_exit_s)],
            cwd=self.workdir,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
        deadline = time.monotonic() + max(10.0, self.step_timeout_s)
        link_addr = tcp = None
        while time.monotonic() < deadline:
            with open(self.log_path, "rb") as fh:
                fh.seek(mark)
                text = fh.read().decode(errors="replace")
            m = re.search(r"lockstep unix socket (\S+)" if unix else r"lockstep udp port (\d+)", text)
            m2 = re.search(r"UART1 tcp port (\d+)", text)
            if m and m2:
                link_addr, tcp = (m.group(1) if unix else int(m.group(1))), int(m2.group(1))
                break
            if self._proc.poll() is not None:
                raise FirmwareError(
                    f"betaflight SITL exited with code {self._proc.returncode} while starting: {self.log_tail()}"
                )
            time.sleep(0.002)
        if link_addr is None:
            self._kill()
            raise FirmwareError(
                f"betaflight SITL did not report its ports within {max(10.0, self.step_timeout_s):.0f} s: {self.log_tail()}"
            )
        if unix:
            mine = self.workdir / "bridge.sock"
            if mine.exists():
                mine.unlink()
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self._sock.bind(str(mine))
            self._sock.connect(link_addr)
        else:
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.bind(("127.0.0.1", 0))
            self._sock.connect(("127.0.0.1", link_addr))
        self._sock.settimeout(self.step_timeout_s)
        self._k = 0
        return link_addr, tcp

    def _kill(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._proc is not None:
            if self._proc.poll() is None:
                try:
                    os.killpg(self._proc.pid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    self._proc.kill()
            try:
                self._proc.wait(timeout=5)
            except subprocess.TimeoutExpired:  # pragma: no cover - SIGKILL does not fail
                pass
            self._proc = None
        if self._log is not None:
            self._log.close()
            self._log = None

    def close(self) -> None:
        """Stop the process and remove the working folder if this instance made it."""
        self._kill()
        if self._own_workdir:
            shutil.rmtree(self.workdir, ignore_errors=True)

    def __enter__(self) -> BetaflightSITL:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    # ------------------------------------------------------------------ stepping
    def _fail(self, what: str) -> FirmwareError:
        proc = self._proc
        if proc is not None and proc.poll() is None:
            try:
                proc.wait(timeout=0.2)
            except subprocess.TimeoutExpired:
                pass
        if proc is None:
            msg = f"betaflight SITL is not running ({what})"
        elif proc.returncode is not None:
            rc = proc.returncode
            how = f"was killed by signal {-rc}" if rc < 0 else f"exited with code {rc}"
            msg = f"betaflight SITL (pid {proc.pid}) {how} at step {self._k} ({what})"
        else:
            msg = (
                f"betaflight SITL (pid {proc.pid}) did not answer step {self._k} within "
                f"{self.step_timeout_s:g} s: hung or stopped ({what}); killed it"
            )
        tail = self.log_tail()
        self._kill()
        return FirmwareError(f"{msg}; last log lines: {tail}")

    def _exchange(self, gyro_lsb, acc_lsb, quat, motor_hz, channels) -> memoryview:
        IN_STRUCT.pack_into(
            self._pbuf, 0, MAGIC_IN, 0, self._k * self.dt_s, *gyro_lsb, *acc_lsb, *quat, *motor_hz, *channels
        )
        sock = self._sock
        if sock is None:
            raise self._fail("no connection")
        try:
            sock.send(self._pbuf)
            while True:
                n = sock.recv_into(self._rbuf)
                if n == OUT_STRUCT.size and self._rbuf[:4] == b"GHO1":
                    break
        except TimeoutError:
            raise self._fail("timeout") from None
        except OSError as exc:  # ConnectionRefused: the process is gone
            raise self._fail(type(exc).__name__) from None
        self._k += 1
        return self._rview

    @staticmethod
    def _inputs(omega_S_rad_s, accel_S_m_s2, q_WB_wxyz, rotor_rad_s):
        # plain floats and no helper calls: this runs once per firmware loop (per-call overhead
        # of numpy or generators would cost more than the firmware's own pass)
        k = GYRO_LSB_PER_RAD_S
        w = omega_S_rad_s.tolist() if type(omega_S_rad_s) is np.ndarray else omega_S_rad_s
        g0, g1, g2 = round(w[0] * k), round(w[1] * k), round(w[2] * k)
        if not (-32767 <= g0 <= 32767 and -32767 <= g1 <= 32767 and -32767 <= g2 <= 32767):
            g0, g1, g2 = _clip16(g0), _clip16(g1), _clip16(g2)
        if accel_S_m_s2 is None:
            a = (0, 0, 256)
        else:
            f = accel_S_m_s2.tolist() if type(accel_S_m_s2) is np.ndarray else accel_S_m_s2
            ka = ACC_LSB_PER_M_S2
            a = (_clip16(round(f[0] * ka)), _clip16(round(f[1] * ka)), _clip16(round(f[2] * ka)))
        if q_WB_wxyz is None:
            quat = (1.0, 0.0, 0.0, 0.0)
        else:
            q = q_WB_wxyz.tolist() if type(q_WB_wxyz) is np.ndarray else q_WB_wxyz
            quat = (q[0], q[1], q[2], q[3])
        if rotor_rad_s is None:
            hz = (0.0, 0.0, 0.0, 0.0)
        else:
            r = rotor_rad_s.tolist() if type(rotor_rad_s) is np.ndarray else rotor_rad_s
            c = _INV_2PI
            hz = (abs(r[0]) * c, abs(r[1]) * c, abs(r[2]) * c, abs(r[3]) * c)
        return (g0, g1, g2), a, quat, hz

    def step(
        self,
        omega_S_rad_s: Sequence[float],
        accel_S_m_s2: Sequence[float] | None = None,
        q_WB_wxyz: Sequence[float] | None = None,
        rotor_rad_s: Sequence[float] | None = None,
        rc: Sequence[int] | None = None,
    ) -> StepReply:
        """One firmware loop at the next gyro sample.

        Parameters
        ----------
        omega_S_rad_s : (3,)
            Gyro sample (what the sensor measures), sensor frame S, rad/s.
        accel_S_m_s2 : (3,) or None
            Specific force, S, m/s² (default (0, 0, g): level and still).
        q_WB_wxyz : (4,) or None
            Attitude, body to world (world z up, body x fwd y left z up); default level.
        rotor_rad_s : (4,) or None
            Rotor speeds, Betaflight motor order, rad/s (sign ignored): the RPM filter's input.
        rc : (4,) or None
            (throttle, roll, pitch, yaw) in µs, 1000-2000; default the last one sent. The arm
            switch (AUX1) is the bridge's: :meth:`boot` arms, :meth:`disarm` disarms.

        Returns
        -------
        StepReply
        """
        if self._proc is None:
            raise GyroInputError("step() before boot(): boot the firmware first")
        if rc is not None and rc != self._rc_last:
            self._set_rc(rc)
        g, a, q, hz = self._inputs(omega_S_rad_s, accel_S_m_s2, q_WB_wxyz, rotor_rad_s)
        self._exchange(g, a, q, hz, self._rc)
        return _reply_from_tuple(OUT_STRUCT.unpack_from(self._rbuf))

    def step_raw(
        self,
        gyro_lsb: Sequence[int],
        acc_lsb: Sequence[int] = (0, 0, 256),
        quat_fw_wxyz: Sequence[float] = (1.0, 0.0, 0.0, 0.0),
        motor_hz: Sequence[float] = (0.0,) * 4,
        rc: Sequence[int] | None = None,
    ) -> tuple:
        """One firmware loop with inputs already in the firmware's axes and units (see packet table).

        Returns the raw reply tuple (:data:`OUT_STRUCT` field order); for fast loops that convert
        in bulk with :func:`replies_to_arrays`.
        """
        if rc is not None:
            self._set_rc(rc)
        self._exchange(gyro_lsb, acc_lsb, quat_fw_wxyz, motor_hz, self._rc)
        return OUT_STRUCT.unpack_from(self._rbuf)

    def run_open_loop(
        self,
        gyro_lsb: np.ndarray,
        motor_hz: np.ndarray | None = None,
        rc: Sequence[int] | None = None,
        throttle_us: np.ndarray | None = None,
    ) -> np.ndarray:
        """Feed N gyro samples (int16 LSB) one per step; return the N raw replies.

        Parameters
        ----------
        gyro_lsb : (N, 3) int16
        motor_hz : (N, 4) or None
            Rotor frequencies, Hz, Betaflight motor order (the RPM filter's input).
        rc : (throttle, roll, pitch, yaw) µs or None
            Sticks for the whole run.
        throttle_us : (N,) or None
            Throttle stick per step, µs (overrides ``rc``'s throttle): the dynamic LPFs and TPA
            follow it when armed.

        Returns
        -------
        ndarray (N,) of :data:`REPLY_DTYPE`
        """
        g = np.asarray(gyro_lsb, dtype=np.int16)
        n = g.shape[0]
        out = np.empty(n, dtype=REPLY_DTYPE)
        ob = out.view(np.uint8).reshape(n, OUT_STRUCT.size)
        if rc is not None:
            self._set_rc(rc)
        hz = np.zeros((n, 4)) if motor_hz is None else np.asarray(motor_hz, float)
        gl = g.tolist()
        hl = hz.tolist()
        acc, q, ch = (0, 0, 256), (1.0, 0.0, 0.0, 0.0), self._rc
        if throttle_us is None:
            for i in range(n):
                self._exchange(gl[i], acc, q, hl[i], ch)
                ob[i] = self._rbuf
        else:
            thr = np.clip(np.rint(np.asarray(throttle_us, float)), 1000, 2000).astype(int).tolist()
            if len(thr) != n:
                raise GyroInputError(f"throttle_us has {len(thr)} values for {n} samples")
            for i in range(n):
                ch[2] = thr[i]
                self._exchange(gl[i], acc, q, hl[i], ch)
                ob[i] = self._rbuf
            self._rc_last = ()
        return out

    def _set_rc(self, rc: Sequence[int]) -> None:
        if len(rc) != 4:
            raise GyroInputError(f"rc must be (throttle, roll, pitch, yaw) in µs, got {len(rc)} values")
        thr, roll, pitch, yaw = (int(round(v)) for v in rc)
        for name, v in (("throttle", thr), ("roll", roll), ("pitch", pitch), ("yaw", yaw)):
            if not 800 <= v <= 2200:
                raise GyroInputError(f"rc {name} = {v} µs is outside 800-2200 µs")
        self._rc[0:4] = [roll, pitch, thr, yaw]
        self._rc_last = tuple(rc)

    # ------------------------------------------------------------------ configuration
    def _cli_session(self, tcp_port: int, lines: Sequence[str]) -> None:
        """Apply ``lines`` through the firmware's CLI and ``save`` (the process then exits)."""
        proc = self._proc
        assert proc is not None
        conn = socket.create_connection(("127.0.0.1", tcp_port), timeout=self.cli_timeout_s)
        conn.setblocking(False)
        try:

            def send_and_wait(text: bytes) -> str:
                conn.sendall(text)
                buf = b""
                deadline = time.monotonic() + self.cli_timeout_s
                while time.monotonic() < deadline:
                    # the CLI runs in the firmware's serial task: give it virtual time
                    for _ in range(80):
                        self._exchange((0, 0, 0), (0, 0, 256), (1.0, 0.0, 0.0, 0.0), (0.0,) * 4, self._rc)
                    try:
                        chunk = conn.recv(65536)
                        buf += chunk
                    except BlockingIOError:
                        pass
                    if buf.endswith(b"\r\n# "):
                        return buf.decode(errors="replace")
                raise FirmwareError(
                    f"betaflight CLI did not answer {text.decode(errors='replace').strip()!r} "
                    f"within {self.cli_timeout_s:g} s: {self.log_tail()}"
                )

            send_and_wait(b"#")
            for line, lenient in lines:
                out = send_and_wait(line.encode() + b"\r\n")
                m = re.search(r"###ERROR[^#]*###", out)
                if m is None:
                    continue
                err = m.group(0).strip("#").strip()
                if "INVALID NAME" in err and (lenient or self.skip_unknown):
                    self.skipped_settings.append(line)
                    continue
                allowed = re.search(r"Allowed (?:values|range)[^\r\n]*", out)
                # a blackbox header logs an enum setting's table index: use the name at that index
                num = re.fullmatch(r"set\s+(\w+)\s*=\s*(\d+)", line.strip())
                if "INVALID VALUE" in err and num and allowed and allowed.group(0).startswith("Allowed values"):
                    names = [x.strip() for x in allowed.group(0).split(":", 1)[1].split(",")]
                    idx = int(num.group(2))
                    if idx < len(names):
                        out = send_and_wait(f"set {num.group(1)} = {names[idx]}\r\n".encode())
                        if re.search(r"###ERROR[^#]*###", out) is None:
                            continue
                hint = f" ({allowed.group(0).strip()})" if allowed else ""
                raise FirmwareError(f"the firmware refused setting {line!r}: {err}{hint}")
            # 'save' writes eeprom.bin and exits (code 0) inside one step, which then never
            # answers: step with a short wait until the process is gone, never killing it
            # (that could cut the write short).
            conn.sendall(b"save\r\n")
            deadline = time.monotonic() + self.cli_timeout_s
            sock = self._sock
            assert sock is not None
            sock.settimeout(0.02)
            while proc.poll() is None and time.monotonic() < deadline:
                IN_STRUCT.pack_into(
                    self._pbuf,
                    0,
                    MAGIC_IN,
                    0,
                    self._k * self.dt_s,
                    0,
                    0,
                    0,
                    0,
                    0,
                    256,
                    1.0,
                    0.0,
                    0.0,
                    0.0,
                    0.0,
                    0.0,
                    0.0,
                    0.0,
                    *self._rc,
                )
                try:
                    sock.send(self._pbuf)
                    sock.recv_into(self._rbuf)
                    self._k += 1
                except (TimeoutError, OSError):
                    time.sleep(0.001)
        finally:
            conn.close()
        try:
            proc.wait(timeout=self.cli_timeout_s)
        except subprocess.TimeoutExpired:
            self._kill()
            raise FirmwareError(f"betaflight SITL did not restart after 'save': {self.log_tail()}") from None
        self._kill()
        if proc.returncode != 0:
            raise FirmwareError(f"betaflight SITL exited with code {proc.returncode} on 'save': {self.log_tail()}")

    def configure(self) -> None:
        """Write :data:`BASE_SETTINGS` and the settings into a fresh ``eeprom.bin`` (CLI + save)."""
        eeprom = self.workdir / "eeprom.bin"
        if eeprom.exists():
            eeprom.unlink()
        _, tcp = self._spawn()
        self._cli_session(
            tcp,
            [(x, False) for x in BASE_SETTINGS]
            + [(x, True) for x in self.lenient_settings]
            + [(x, False) for x in self.settings],
        )
        if self.skipped_settings:
            warnings.warn(
                f"skipped {len(self.skipped_settings)} setting(s) this SITL does not have: "
                + ", ".join(s.split("=")[0].replace("set ", "").strip() for s in self.skipped_settings[:8])
                + (" …" if len(self.skipped_settings) > 8 else ""),
                stacklevel=2,
            )
        self._configured = True

    def boot(self, still: StillSource | None = None, *, arm: bool = True, max_boot_s: float = 20.0) -> BootReport:
        """Configure (once), start the firmware, wait out its gyro calibration with the vehicle still, arm.

        Parameters
        ----------
        still : callable k -> (omega_S_rad_s (3,), accel_S_m_s2 (3,)), or None
            The gyro and accelerometer samples of the still vehicle during boot (the sensor
            model's bias and noise, so the firmware's motion-gated calibration measures what a
            real board would); default exact zeros and (0, 0, g).
        arm : bool
            Raise the arm switch (throttle low) once the firmware allows it.
        max_boot_s : float
            Simulated-time limit for calibration + arming (a calibration the motion gate keeps
            restarting ends here with an error).

        Returns
        -------
        BootReport
            Also kept as :attr:`boot_report`. The flight's first :meth:`step` follows it.
        """
        t0 = time.monotonic()
        if not self._configured:
            self.configure()
        self._spawn()
        self._rc = [RC_MID_US, RC_MID_US, RC_LOW_US, RC_MID_US] + [RC_LOW_US] * 12
        self._rc_last = ()
        max_steps = int(round(max_boot_s * self.loop_rate_hz))
        cal_steps = None
        fw_boot_s = float("nan")
        r = None
        for k in range(max_steps):
            if still is None:
                g, a = (0.0, 0.0, 0.0), None
            else:
                g, a = still(k)
            r = self.step(g, a)
            if k == 0:
                fw_boot_s = r.time_us * 1e-6
            if cal_steps is None and r.gyro_calibrated:
                cal_steps = k + 1
            if cal_steps is None:
                continue
            if not arm:
                break
            if r.armed:
                break
            blocking = r.arming_disable_flags & ~_ARM_SWITCH_FLAG
            if blocking == 0 and self._rc[4] != ARM_ON_US:
                self._rc[4] = ARM_ON_US
        else:
            flags = arming_flag_names(r.arming_disable_flags) if r is not None else []
            what = (
                "the gyro calibration did not complete (vehicle not still? gyro_calib_noise_limit)"
                if cal_steps is None
                else f"it did not arm (arming disabled by: {', '.join(flags) or 'nothing reported'})"
            )
            raise FirmwareError(f"betaflight SITL boot failed within {max_boot_s:g} s simulated: {what}")
        assert r is not None
        self.boot_report = BootReport(
            steps=self._k,
            sim_s=self._k * self.dt_s,
            firmware_boot_s=fw_boot_s,
            calibration_steps=int(cal_steps or 0),
            gyro_bias_S_rad_s=r.gyro_bias_S_rad_s,
            armed=r.armed,
            wall_s=time.monotonic() - t0,
            settings=(*BASE_SETTINGS, *self.lenient_settings, *self.settings),
        )
        return self.boot_report

    def disarm(self) -> None:
        """Lower the arm switch (takes effect with the next step)."""
        self._rc[4] = RC_LOW_US

    @property
    def steps(self) -> int:
        """Packets sent to the running process (boot included)."""
        return self._k
