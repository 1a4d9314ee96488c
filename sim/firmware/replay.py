"""Open-loop replay of a gyro record through the firmware's own gyro filter chain.

The record is brought to the firmware's loop rate (:func:`resample_to_loop_rate`), quantised to
the firmware's int16 LSB exactly as :func:`sim.firmware.bridge.gyro_to_lsb` does, and fed one
sample per firmware loop after the firmware has booted and finished its gyro calibration on a
still (zero) gyro, so the calibration offset is zero and the filters see the record unchanged.
The firmware stays disarmed (the gyro filters, dynamic notch and the D-term filters all run
disarmed); ``rotor_rad_s`` feeds the RPM filter.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from gyrocore.errors import GyroInputError

from .bridge import (
    LOOP_RATE_HZ,
    BetaflightSITL,
    BootReport,
    gyro_to_lsb,
    replies_to_arrays,
)

__all__ = ["RESAMPLE_METHOD", "ReplayResult", "replay_gyro", "resample_to_loop_rate"]

#: How a record is brought to the loop rate (named in the output's metadata).
RESAMPLE_METHOD = ("linear interpolation onto a uniform grid at the record's mean rate, then "
                   "scipy.signal.resample_poly (Kaiser-windowed polyphase FIR) by the rational "
                   "factor to the loop rate")


@dataclass(frozen=True)
class ReplayResult:
    """The firmware's view of a replayed gyro record, one row per firmware loop.

    Attributes
    ----------
    gyro_lsb : ndarray (N, 3) int16
        What the firmware read (firmware axes).
    fw_gyro_S_rad_s : ndarray (N, 3)
        ``gyro.gyroADCf`` (the filtered gyro), sensor frame, rad/s.
    fw_gyro_unfiltered_S_rad_s : ndarray (N, 3)
        ``gyro.gyroADC`` (quantised input, calibration offset removed), sensor frame, rad/s.
    fw_dterm_S_rad_s : ndarray (N, 3)
        The gyro after the D-term filters (the D term's input), sensor frame, rad/s.
    debug : ndarray (N, 8)
        ``debug[]`` per loop (``debug_mode``).
    loop_count : ndarray (N,)
        The firmware's gyro-loop counter per row (consecutive: one loop per sample).
    boot : BootReport
    settings : tuple of str
        Every CLI line applied (the bridge's base lines first).
    skipped_settings : tuple of str
        Lines skipped because this firmware has no such setting (only with ``skip_unknown``).
    """

    gyro_lsb: np.ndarray
    fw_gyro_S_rad_s: np.ndarray
    fw_gyro_unfiltered_S_rad_s: np.ndarray
    fw_dterm_S_rad_s: np.ndarray
    debug: np.ndarray
    loop_count: np.ndarray
    boot: BootReport
    settings: tuple[str, ...]
    skipped_settings: tuple[str, ...]


def replay_gyro(binary: str, gyro_S_rad_s: np.ndarray, *, settings: Sequence[str] = (),
                rotor_rad_s: np.ndarray | None = None, skip_unknown: bool = False,
                step_timeout_s: float = 5.0) -> ReplayResult:
    """Run a gyro record, already at the loop rate, through the firmware's filters.

    Parameters
    ----------
    binary : str
        Lockstep SITL binary (:func:`sim.firmware.build.ensure_binary`).
    gyro_S_rad_s : ndarray (N, 3)
        Gyro samples at :data:`~sim.firmware.bridge.LOOP_RATE_HZ`, sensor frame, rad/s.
    settings : sequence of str
        Firmware CLI lines (see :class:`~sim.firmware.bridge.BetaflightSITL`).
    rotor_rad_s : ndarray (N, 4) or None
        Rotor speeds per sample, Betaflight motor order, rad/s (the RPM filter's input).
    skip_unknown : bool
        Skip settings this firmware does not have (one warning) instead of failing.

    Returns
    -------
    ReplayResult
    """
    g = np.asarray(gyro_S_rad_s, float)
    if g.ndim != 2 or g.shape[1] != 3 or g.shape[0] < 1:
        raise GyroInputError(f"gyro must have shape (N, 3), got {g.shape}")
    if not np.all(np.isfinite(g)):
        raise GyroInputError("gyro has non-finite samples; the firmware cannot read NaN")
    hz = None
    if rotor_rad_s is not None:
        r = np.asarray(rotor_rad_s, float)
        if r.shape != (g.shape[0], 4):
            raise GyroInputError(f"rotor speeds must have shape ({g.shape[0]}, 4), got {r.shape}")
        hz = np.abs(r) / (2 * math.pi)
    lsb = gyro_to_lsb(g)
    with BetaflightSITL(binary, settings, step_timeout_s=step_timeout_s, skip_unknown=skip_unknown) as fc:
        boot = fc.boot(arm=False)
        raw = fc.run_open_loop(lsb, motor_hz=hz)
        skipped = tuple(fc.skipped_settings)
    cols = replies_to_arrays(raw)
    return ReplayResult(gyro_lsb=lsb, fw_gyro_S_rad_s=cols["fw_gyro_S_rad_s"],
                        fw_gyro_unfiltered_S_rad_s=cols["fw_gyro_unfiltered_S_rad_s"],
                        fw_dterm_S_rad_s=cols["fw_dterm_S_rad_s"], debug=cols["debug"],
                        loop_count=cols["loop_count"], boot=boot, settings=boot.settings, skipped_settings=skipped)


def resample_to_loop_rate(t_s: np.ndarray, x: np.ndarray, rate_hz: float = LOOP_RATE_HZ,
                          *, max_denominator: int = 1000) -> tuple[np.ndarray, np.ndarray, dict]:
    """Bring a record to ``rate_hz`` (method: :data:`RESAMPLE_METHOD`).

    Parameters
    ----------
    t_s : ndarray (N,)
        Sample times, s, increasing.
    x : ndarray (N, C)
        Samples.
    rate_hz : float
        Target rate, Hz.

    Returns
    -------
    t_out_s : ndarray (M,)
        Uniform times from ``t_s[0]`` at ``rate_hz``.
    x_out : ndarray (M, C)
    info : dict
        ``{"method", "input_rate_hz", "up", "down", "jitter_rel"}``: the factor applied and the
        input's timing jitter (max |Δt − mean Δt| / mean Δt) that the first interpolation removed.
    """
    from scipy.signal import resample_poly

    t = np.asarray(t_s, float)
    x = np.asarray(x, float)
    if t.ndim != 1 or t.shape[0] != x.shape[0] or t.shape[0] < 2:
        raise GyroInputError("resampling needs at least 2 samples with one time each")
    dt = np.diff(t)
    if not np.all(dt > 0):
        raise GyroInputError("sample times must be strictly increasing to resample")
    mean_dt = (t[-1] - t[0]) / (t.shape[0] - 1)
    in_rate = 1.0 / mean_dt
    jitter = float(np.max(np.abs(dt - mean_dt)) / mean_dt)
    tu = t[0] + mean_dt * np.arange(t.shape[0])
    xu = x if jitter < 1e-9 else np.column_stack([np.interp(tu, t, x[:, c]) for c in range(x.shape[1])])
    frac = Fraction(rate_hz / in_rate).limit_denominator(max_denominator)
    up, down = frac.numerator, frac.denominator
    if up == down:
        y = xu.copy()
    else:
        y = resample_poly(xu, up, down, axis=0)
    t_out = t[0] + np.arange(y.shape[0]) / rate_hz
    return t_out, y, {"method": RESAMPLE_METHOD, "input_rate_hz": in_rate, "up": up, "down": down,
                      "jitter_rel": jitter}
