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
from pathlib import Path

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
RESAMPLE_METHOD = (
    "linear interpolation onto a uniform grid at the record's mean rate, then "
    "scipy.signal.resample_poly (Kaiser-windowed polyphase FIR) by the rational "
    "factor to the loop rate"
)


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


#: Added to a replay that follows a throttle (armed): the open-loop gyro is not the vehicle's
#: response to the motors, which the runaway-takeoff guard would read as a flyaway and disarm.
REPLAY_ARMED_SETTINGS = ("set runaway_takeoff_prevention = OFF",)


def replay_gyro(
    binary: str,
    gyro_S_rad_s: np.ndarray,
    *,
    settings: Sequence[str] = (),
    lenient_settings: Sequence[str] = (),
    rotor_rad_s: np.ndarray | None = None,
    throttle_us: np.ndarray | None = None,
    skip_unknown: bool = False,
    step_timeout_s: float = 5.0,
) -> ReplayResult:
    """Run a gyro record, already at the loop rate, through the firmware's filters.

    Parameters
    ----------
    binary : str
        Lockstep SITL binary (:func:`sim.firmware.build.ensure_binary`).
    gyro_S_rad_s : ndarray (N, 3)
        Gyro samples at :data:`~sim.firmware.bridge.LOOP_RATE_HZ`, sensor frame, rad/s.
    settings : sequence of str
        Firmware CLI lines (see :class:`~sim.firmware.bridge.BetaflightSITL`).
    lenient_settings : sequence of str
        Lines from a diff or log header, applied first; names this firmware lacks are skipped.
    rotor_rad_s : ndarray (N, 4) or None
        Rotor speeds per sample, Betaflight motor order, rad/s (the RPM filter's input).
    throttle_us : ndarray (N,) or None
        Throttle stick per sample, µs. Given: the firmware is armed (throttle low) after its
        calibration and the stick follows it, so the throttle-dependent parts (dynamic LPFs,
        TPA, anti-gravity) move as in flight; None: it stays disarmed (the dynamic LPFs sit at
        their minimum-throttle cutoffs).
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
    armed = throttle_us is not None
    if armed:
        thr = np.asarray(throttle_us, float)
        if thr.shape != (g.shape[0],) or not np.all(np.isfinite(thr)):
            raise GyroInputError(f"throttle must have shape ({g.shape[0]},) and be finite")
        settings = (*REPLAY_ARMED_SETTINGS, *settings)
    with BetaflightSITL(
        binary, settings, step_timeout_s=step_timeout_s, skip_unknown=skip_unknown, lenient_settings=lenient_settings
    ) as fc:
        boot = fc.boot(arm=armed)
        raw = fc.run_open_loop(lsb, motor_hz=hz, throttle_us=throttle_us)
        skipped = tuple(fc.skipped_settings)
    cols = replies_to_arrays(raw)
    return ReplayResult(
        gyro_lsb=lsb,
        fw_gyro_S_rad_s=cols["fw_gyro_S_rad_s"],
        fw_gyro_unfiltered_S_rad_s=cols["fw_gyro_unfiltered_S_rad_s"],
        fw_dterm_S_rad_s=cols["fw_dterm_S_rad_s"],
        debug=cols["debug"],
        loop_count=cols["loop_count"],
        boot=boot,
        settings=boot.settings,
        skipped_settings=skipped,
    )


def resample_to_loop_rate(
    t_s: np.ndarray, x: np.ndarray, rate_hz: float = LOOP_RATE_HZ, *, max_denominator: int = 1000
) -> tuple[np.ndarray, np.ndarray, dict]:
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
    return t_out, y, {"method": RESAMPLE_METHOD, "input_rate_hz": in_rate, "up": up, "down": down, "jitter_rel": jitter}


@dataclass(frozen=True)
class ReplayInput:
    """A record prepared for :func:`replay_gyro`: at the loop rate, with what was done to it."""

    t_s: np.ndarray
    gyro_S_rad_s: np.ndarray
    rotor_rad_s: np.ndarray | None
    throttle_us: np.ndarray | None
    resample: dict
    source: str
    meta: dict


def load_replay_input(
    path: str, rate_hz: float = LOOP_RATE_HZ, *, start_s: float = 0.0, duration_s: float | None = None
) -> ReplayInput:
    """Read a data file or a blackbox log and bring its gyro (and rotor speeds) to the loop rate.

    A blackbox log contributes its unfiltered gyro (``gyroUnfilt``, or the debug mode that
    carries the gyro before every software filter) and its rotor frequencies (``eRPM``, or
    ``debug_mode RPM_FILTER``) for the RPM filter; its filtered gyro (``gyroADC``) is not an
    input. A data file contributes ``gyro_*_rad_s`` and, when present, ``rotor_hz_0..3``
    (Betaflight motor order).
    """
    import json

    from gyrocore.readers.blackbox import is_blackbox, read_blackbox
    from gyrocore.data.recording import read_recording

    if is_blackbox(path):
        rec = read_blackbox(path)
        pre = json.loads(rec.meta.get("gyro_prefilter", "{}") or "{}")
        if not all(f"gyro_prefilter_{a}_rad_s" in rec.extra for a in "xyz"):
            raise GyroInputError(
                f"{path}: the log carries no unfiltered gyro (gyroUnfilt in 4.5+, or debug_mode "
                f"GYRO_SCALED/GYRO_RAW): nothing to replay through the filters"
            )
        if pre.get("filters_before"):
            done = ", ".join(
                f"{f.get('kind', '?')} {f.get('cutoff_hz', float('nan')):g} Hz" for f in pre["filters_before"]
            )
            raise GyroInputError(
                f"{path}: the log's least-filtered gyro ({pre.get('source', '?').split(';')[0]}) already "
                f"passed {done}: not the unfiltered gyro the firmware's filters start from"
            )
        g = np.column_stack([rec.extra[f"gyro_prefilter_{a}_rad_s"] for a in "xyz"])
        source = f"{Path(path).name}: {pre.get('source', 'unfiltered gyro')}"
    else:
        rec = read_recording(path)
        g = rec.gyro_rad_s
        source = f"{Path(path).name}: gyro_*_rad_s"
    thr = rec.extra.get("rc_throttle")
    rot = None
    if all(f"rotor_hz_{i}" in rec.extra for i in range(4)):
        rot = np.column_stack([rec.extra[f"rotor_hz_{i}"] for i in range(4)]) * (2 * math.pi)
    t = rec.t_s - rec.t_s[0]
    keep = t >= start_s
    if duration_s is not None:
        keep &= t <= start_s + duration_s
    if keep.sum() < 2:
        raise GyroInputError(
            f"{path}: fewer than 2 samples in the window from {start_s:g} s"
            + (f" for {duration_s:g} s" if duration_s is not None else "")
            + f" (the record is {t[-1]:.3g} s long)"
        )
    ts, g = rec.t_s[keep], g[keep]
    ok = np.all(np.isfinite(g), axis=1)
    if not np.all(ok):
        raise GyroInputError(f"{path}: {int((~ok).sum())} gyro rows are not finite; repair the file first")
    t_out, g_out, info = resample_to_loop_rate(ts, g, rate_hz)
    rot_out = None
    if rot is not None:
        # rotor speeds are slow, already-smoothed telemetry: linear interpolation onto the loop grid
        rot_out = np.column_stack([np.interp(t_out, rec.t_s, rot[:, i]) for i in range(4)])
    thr_out = None
    if thr is not None and np.all(np.isfinite(thr)):
        # the throttle stick (1000-2000 us), sample-and-hold like an RC link: previous value
        idx = np.clip(np.searchsorted(rec.t_s, t_out, side="right") - 1, 0, rec.t_s.size - 1)
        thr_out = np.asarray(thr, float)[idx]
    if start_s or duration_s is not None:
        info = {**info, "window_s": [float(ts[0] - rec.t_s[0]), float(ts[-1] - rec.t_s[0])]}
    return ReplayInput(t_out, g_out, rot_out, thr_out, info, source, dict(rec.meta))


def replay_recording(result: ReplayResult, inp: ReplayInput, *, firmware_label: str, patch_sha256: str):
    """The OUT data file of ``firmware replay``: input, the firmware's filtered gyro, its D-term input."""
    import json

    from gyrocore.data.recording import Recording

    extra = {}
    for name, arr in (
        ("fw_gyro", result.fw_gyro_S_rad_s),
        ("fw_gyro_unfiltered", result.fw_gyro_unfiltered_S_rad_s),
        ("fw_dterm", result.fw_dterm_S_rad_s),
    ):
        for i, a in enumerate("xyz"):
            extra[f"{name}_{a}_rad_s"] = arr[:, i]
    if inp.rotor_rad_s is not None:
        for i in range(4):
            extra[f"rotor_hz_{i}"] = inp.rotor_rad_s[:, i] / (2 * math.pi)
    if inp.throttle_us is not None:
        extra["rc_throttle"] = inp.throttle_us
    meta = {
        "firmware": firmware_label,
        "firmware_settings": "; ".join(result.settings),
        "firmware_patch_sha256": patch_sha256,
        "firmware_replay": (
            (
                "open loop, armed, throttle stick from rc_throttle"
                if inp.throttle_us is not None
                else "open loop, disarmed"
            )
            + ": one firmware loop per row at 8 kHz; fw_gyro = gyro.gyroADCf, "
            "fw_gyro_unfiltered = gyro.gyroADC (the int16 the firmware read), fw_dterm = the gyro "
            "after the D-term filters; sensor frame, rad/s"
        ),
        "resample": json.dumps({k: v for k, v in inp.resample.items()}),
        "source": inp.source,
        "rate_hz": f"{LOOP_RATE_HZ:g}",
    }
    if result.skipped_settings:
        meta["firmware_settings_skipped"] = "; ".join(result.skipped_settings)
    return Recording(t_s=inp.t_s, gyro_rad_s=inp.gyro_S_rad_s, meta=meta, extra=extra)
