"""How good a model is on its recording: the attitude error of the corrected gyro against the
reference, and what the final window residual still holds (:class:`~gyrocore.loop.result.Remaining`)."""

from __future__ import annotations


import numpy as np
from scipy import signal

from gyrocore.calib import covariance
from gyrocore.attitude import error_angle_rad, integrate_gyro
from gyrocore.data.recording import Recording
from gyrocore.calib.stream import rows_of
from . import source
from .residual import Residual
from .result import Remaining
from .evidence import rms

__all__ = ["attitude_error_deg", "describe_remaining", "window_line_series", "longest_chain"]


def attitude_error_deg(res: Residual, rec: Recording, correction_rad_s: np.ndarray) -> float:
    """RMS attitude error of the corrected gyro against the reference, deg (NaN if undefined).

    ``rate``: integrate from the reference's first attitude (``ref_q*`` or the integrated
    reference rate) and compare over the recording (in memory or on disk, a window at a time). ``attitude``: same against ``ref_q*``
    where valid. ``still``: the integrated angle from each still window's start. ``angles``:
    RMS over the known-rotation segments of |∫ω dt − φ|.
    """
    if res.kind == "rate":
        return _rate_attitude_error(rec, correction_rad_s)
    t = rec.t_s
    w = rec.gyro_rad_s - correction_rad_s
    if res.kind == "angles":
        T = res.duration_s
        # y_after·T = ∫(ω − c)dt − φ
        d = (res.y_rad_s - res.window_mean(correction_rad_s)) * T[:, None]
        rot = res.is_rotation if res.is_rotation is not None else np.ones(res.m, bool)
        d = d[rot]
        if res.angle_mode == "axis" and res.angle_S_rad is not None:
            phi = res.angle_S_rad[rot]
            u = phi / np.maximum(np.linalg.norm(phi, axis=1, keepdims=True), 1e-300)
            d = np.sum(d * u, axis=1, keepdims=True)  # only the along-axis angle is known
        return float(np.degrees(np.sqrt(np.mean(np.sum(d**2, axis=1)))))
    if res.kind == "still":
        # windows are contiguous blocks: the angle accumulates inside each still run
        return _still_runs_error(res, integrate_gyro(t, w, hold="backward"))
    # attitude
    q_ref = rec.ref_quat_wxyz
    ok = np.all(np.isfinite(q_ref), axis=1)
    i0 = int(np.flatnonzero(ok)[0])
    q = integrate_gyro(t[i0:], w[i0:], q0_wxyz=q_ref[i0], hold="backward")
    e = error_angle_rad(q[ok[i0:]], q_ref[i0:][ok[i0:]])
    return float(np.degrees(rms(e)))


def _rate_attitude_error(rec, correction) -> float:
    """The ``rate`` reference's attitude error: the corrected gyro integrated from the reference's
    first attitude a window at a time (a recording in memory is one window; on disk the attitude
    is carried across windows, :func:`gyrocore.loop.source.integrated_windows`), the squared error
    angles against the reference attitude summed over the windows."""
    src = source.of(rec)
    q_ref = src.reference_attitude()
    if q_ref is None:
        return float("nan")
    w = src.per_sample(lambda lo, hi: rows_of(rec.gyro_rad_s, lo, hi) - rows_of(correction, lo, hi), 3)
    s2, cnt = 0.0, 0
    for lo, hi, q in source.integrated_windows(src, w, q0_wxyz=rows_of(q_ref, 0, 1)[0]):
        e = error_angle_rad(q, rows_of(q_ref, lo, hi))
        s2 += float(np.sum(e * e))
        cnt += e.size
    return float(np.degrees(np.sqrt(s2 / cnt)))


def _still_runs_error(res: Residual, q: np.ndarray) -> float:
    """RMS over still windows of the angle integrated since the start of their still run."""
    a, b = res.win_start, res.win_stop
    run_start = a.copy()
    for k in range(1, a.size):
        run_start[k] = run_start[k - 1] if a[k] == b[k - 1] else a[k]
    e = error_angle_rad(q[b], q[run_start])
    return float(np.degrees(rms(e)))


def describe_remaining(res: Residual, e: np.ndarray) -> Remaining:
    win = float(np.median(res.duration_s))
    lb = covariance.ljung_box_p(e)
    # spectrum and Allan deviation on the longest run of evenly spaced windows (still
    # segments, dropped windows and known-rotation windows break the spacing)
    e_run, _, fs, _ = window_line_series(res, e)
    if e_run.shape[0] > 16:
        e = e_run
        f, P = signal.welch(e, fs=fs, axis=0, nperseg=min(256, e.shape[0]))
        from gyrocore.noise.adev import octave_m, oadev

        m = octave_m(e.shape[0])
        m = m[m <= e.shape[0] // 3] if (m <= e.shape[0] // 3).any() else m[:1]
        taus, adev = None, []
        for i in range(3):
            taus, d, _ = oadev(e[:, i], fs, m)
            adev.append(d)
        adev = np.stack(adev, axis=1)
        ok = np.all(adev > 0, axis=1)
        slope = np.polyfit(np.log(taus[ok]), np.log(adev[ok]), 1)[0] if ok.sum() >= 2 else np.full(3, np.nan)
    else:
        f, P = np.zeros(0), np.zeros((0, 3))
        taus, adev, slope = np.zeros(0), np.zeros((0, 3)), np.full(3, np.nan)
    return Remaining(
        ljung_box_p=float(lb),
        window_s=win,
        welch_freq_hz=f,
        welch_psd=P,
        allan_tau_s=np.asarray(taus),
        allan_adev_rad_s=adev,
        allan_slope=np.asarray(slope),
    )


def window_line_series(res: Residual, e: np.ndarray):
    """Longest evenly spaced run of windows of the window residual: (x, t_mid, fs, idx)."""
    T = res.duration_s
    win = float(np.median(T))
    even = np.concatenate(
        [[False], (np.abs(np.diff(res.t_mid_s) - win) <= 0.05 * win) & (np.abs(T[1:] - win) <= 0.05 * win)]
    )
    bst, best = longest_chain(even)
    idx = np.arange(bst, bst + best)
    return e[idx], res.t_mid_s[idx], 1.0 / win, idx


def longest_chain(cont: np.ndarray) -> tuple[int, int]:
    """Start and length of the longest chain of windows each continuing the previous one
    (``cont[k]``: window k continues window k − 1; ``cont[0]`` is not read); the first on a tie."""
    best, cur, st, bst = 0, 0, 0, 0
    for k in range(cont.shape[0]):
        if k > 0 and cont[k]:
            cur += 1
        else:
            cur, st = 1, k
        if cur > best:
            best, bst = cur, st
    return bst, best
