"""Units of the data file and the checks and repairs of a parsed recording.

SI units (``DEG``, ``G0_M_S2``); the rows kept (finite, strictly increasing time:
:func:`_valid_rows`); deg/s written as rad/s (:func:`_unit_checks`); a time column that is not
seconds, gaps and uneven sampling (:func:`_timing_checks`); clipped plateaus
(:func:`detect_saturation`). Each says what it repaired in a ``warning:`` line or refuses in
one ``error:`` line.
"""

from __future__ import annotations

import numpy as np

from gyrocore.errors import GyroInputError, warn_repair

from .csvtext import TIME_ALTS, TIME_NAME_ALTS

__all__ = [
    "DEG",
    "G0_M_S2",
    "DEG_S_SUSPECT_RAD_S",
    "STILL_NOISE_SUSPECT_RAD_S",
    "MAD_TO_SIGMA",
    "robust_diff_sigma",
    "still_noise_rad_s",
    "detect_saturation",
    "gap_threshold_s",
    "coarse_clock_retime",
]

DEG = np.pi / 180.0
G0_M_S2 = 9.80665

#: A t_s column whose median interval is above this is not seconds (no gyro recording is
#: sampled slower than 0.5 Hz; a millisecond counter at <= 500 Hz, or any microsecond or
#: nanosecond counter, lands above it): one error line naming t_ms / t_us / t_ns.
T_S_MAX_MEDIAN_DT_S = 2.0
#: ... and above this (but not above the limit) a warning: a millisecond counter at 1 kHz has
#: dt = 1 "s" — as would a genuine 1-Hz log, hence only a warning.
T_S_SUSPECT_MEDIAN_DT_S = 0.5

#: Largest plausible MEMS gyro full scale: ±2000 °/s = 34.9 rad/s (ICM-42688, BMI160, MPU-6050
#: at their widest range; the fastest parts stop at ±4000 °/s = 69.8 rad/s). Peaks above
#: :data:`DEG_S_SUSPECT_RAD_S` in a column labelled rad/s are taken as deg/s mislabelled.
DEG_S_SUSPECT_RAD_S = 70.0
#: Per-sample noise of a still MEMS gyro is far below 0.05 rad/s (2.9 °/s); a still recording
#: whose noise exceeds it is reported as probably deg/s labelled rad/s.
STILL_NOISE_SUSPECT_RAD_S = 0.05


def _valid_rows(t, gyro, accel, temp, path, repair, *, t_prev: float = -np.inf) -> tuple[np.ndarray, int, int]:
    """Mask of rows kept: finite time/gyro/accel/temp, strictly increasing time."""
    keep = np.isfinite(t) & np.all(np.isfinite(gyro), axis=1)
    if accel is not None:
        keep &= np.all(np.isfinite(accel), axis=1)
    if temp is not None:
        keep &= np.isfinite(temp)
    n_bad = int((~keep).sum())
    if n_bad and not repair:
        raise GyroInputError(f"{path}: {n_bad} rows with NaN/inf values")
    all_kept = not n_bad
    t_k = t if all_kept else t[keep]
    n_back = 0
    if t_k.size and all_kept and t_k[0] > t_prev and bool(np.all(t_k[1:] > t_k[:-1])):
        return keep, n_bad, 0  # strictly increasing (the usual case): no running-max copies
    if t_k.size:
        running_max = np.maximum.accumulate(np.concatenate([[t_prev], t_k]))
        mono = t_k > running_max[:-1]
        n_back = int((~mono).sum())
        if n_back:
            if not repair:
                raise GyroInputError(f"{path}: {n_back} timestamps go backwards or repeat")
            idx = np.flatnonzero(keep)
            keep[idx[~mono]] = False
    return keep, n_bad, n_back


#: A clock that ticks slower than the samples (Windows' 15.6 ms, Arduino millis() above 1 kHz, a
#: host stamp at 10 ms) repeats its value: at least this fraction of the intervals are 0.
COARSE_CLOCK_MIN_REPEAT = 0.01


def coarse_clock_retime(t: np.ndarray, gyro: np.ndarray, path: str, repair: bool) -> np.ndarray | None:
    """Uniform times for a record stamped by a clock coarser than its samples, else None.

    Such a clock repeats its value (≥ :data:`COARSE_CLOCK_MIN_REPEAT` of the intervals are 0)
    and never goes back; dropping the repeats (the rule for a time that repeats) would throw
    away real samples — a third to a half of them at 15.6 or 20 ms ticks on a 100-Hz stream,
    and the noise density with them (N 25-40 % high). The rows are kept on a uniform grid from
    the first to the last stamp (the mean rate (N−1)/duration, off by at most one tick over the
    record), with a warning. Rows that repeat the time *and* the gyro values are written twice,
    not a coarse clock: left to the usual drop.
    """
    if t.size < 3 or not np.all(np.isfinite(t)):  # NaN/inf times: dropped first, the usual way
        return None
    d = np.diff(t)
    n = d.size
    zero = d == 0
    n_zero = int(np.count_nonzero(zero))
    if n_zero < max(2.0, COARSE_CLOCK_MIN_REPEAT * n) or bool(np.any(d < 0)) or not t[-1] > t[0]:
        return None
    same = zero & np.all(gyro[1:] == gyro[:-1], axis=1)
    if int(np.count_nonzero(same)) > n_zero // 2:
        return None
    if not repair:
        raise GyroInputError(f"{path}: {n_zero} timestamps repeat the previous one (a clock coarser than the samples)")
    mean = float(t[-1] - t[0]) / n
    tick = float(np.min(d[d > 0]))
    warn_repair(
        f"{path}: {n_zero} timestamps repeat the previous one (a clock coarser than the samples — its smallest step "
        f"{tick * 1e3:.3g} ms, the mean interval {mean * 1e3:.3g} ms — or one that stalled); all rows kept, on a "
        f"uniform grid at the mean rate {1.0 / mean:.6g} Hz"
        + (
            f"; the stamps also jump {float(d.max()):.3g} s at t = {float(t[int(np.argmax(d))]):.6g} s, which the grid "
            f"spreads over the samples (right for a stalled clock, wrong if the logger paused there)"
            if float(d.max()) > 10.0 * max(mean, tick)
            else ""
        )
    )
    return t[0] + np.arange(t.size) * mean


#: MAD → σ of Gaussian data, 1/Φ⁻¹(3/4).
MAD_TO_SIGMA = 1.482602218505602
#: The same to four digits: the constant of the reader's deg/s check (:func:`still_noise_rad_s`),
#: kept so that its figures and warnings stay as they were.
MAD_TO_SIGMA_4 = 1.4826


def lag_diff_in_place(x: np.ndarray, lag: int, block: int = 1 << 20) -> np.ndarray:
    """x[k + lag] − x[k] written over x[k] block by block (block [a, b) reads x[a .. b + lag),
    none of it overwritten yet); returns the view x[:N − lag]."""
    n = x.shape[0] - lag
    for a in range(0, max(n, 0), block):
        b = min(a + block, n)
        x[a:b] = x[a + lag : b + lag] - x[a:b]
    return x[: max(n, 0)]


def robust_diff_sigma(
    x, *, lag: int = 1, per_sample: bool = False, zero_mad: str = "std", mad_to_sigma: float = MAD_TO_SIGMA
) -> float:
    """Robust σ of a series' lag differences Δ_k = x[k + lag] − x[k]: ``mad_to_sigma``·MAD(Δ).

    Parameters
    ----------
    x : ndarray, shape (N,), or a callable returning one
        The series (any unit). An array is copied; a callable must return a fresh array each
        call, which is overwritten (memory: one column) — it is called again only for the
        ``"std"`` or ``"step"`` answer below.
    lag : int
        Lag of the differences, samples.
    per_sample : bool
        Divide by √2: the per-sample σ of white noise (Var Δ = 2σ²), not Δ's own σ_Δ.
    zero_mad : {"std", "step"}
        The answer when the MAD is 0 (output quantized more coarsely than its noise): the plain
        standard deviation of Δ, or the smallest non-zero |Δ| (0 when none), neither divided by √2.
    mad_to_sigma : float
        MAD → σ factor (:data:`MAD_TO_SIGMA`; the reader's deg/s check uses :data:`MAD_TO_SIGMA_4`).

    Returns
    -------
    float
        σ, the unit of x (0 with fewer than lag + 1 samples).
    """
    fresh = x if callable(x) else (lambda: np.array(x, dtype=float))
    d = lag_diff_in_place(fresh(), lag)
    if d.size == 0:
        return 0.0
    # in place (the median and the MAD do not depend on the order of d, which the partition
    # permutes): no temporary
    med = np.median(d, overwrite_input=True)
    np.subtract(d, med, out=d)
    np.abs(d, out=d)
    mad = float(np.median(d, overwrite_input=True))
    if mad > 0:
        s = mad_to_sigma * mad
        return s / np.sqrt(2.0) if per_sample else s
    del d  # one column at a time
    d = lag_diff_in_place(fresh(), lag)
    if zero_mad == "std":
        return float(d.std())
    if zero_mad == "step":
        nz = np.abs(d[d != 0])
        return float(nz.min()) if nz.size else 0.0
    raise ValueError(f"zero_mad must be 'std' or 'step', not {zero_mad!r}")


def still_noise_rad_s(x) -> float:
    """Per-sample noise of a still gyro axis for the deg/s-as-rad/s check (rad/s): σ from first
    differences, 1.4826·MAD(Δx)/√2; the smallest non-zero step when more than half of the
    differences are exactly zero (coarse quantum). ``x`` as in :func:`robust_diff_sigma`."""
    return robust_diff_sigma(x, per_sample=True, zero_mad="step", mad_to_sigma=MAD_TO_SIGMA_4)


def detect_saturation(
    x: np.ndarray, *, min_run: int = 3, min_clip: np.ndarray | float = 0.0
) -> tuple[np.ndarray, list[tuple[int, float, int]]]:
    """Samples clipped at a plateau: runs of identical values at a column's extreme.

    Parameters
    ----------
    x : ndarray, shape (N, K)
        Samples (any unit), one column per axis.
    min_run : int
        Shortest run of identical extreme values counted as a plateau.
    min_clip : float or ndarray, shape (K,)
        Smallest |plateau| that can be a clip level, per column (same unit as ``x``): no
        sensor clips below its smallest full-scale setting, so a plateau below it (e.g. an
        exactly constant simulated 1 g at rest) is a steady reading, not saturation.

    Returns
    -------
    mask : ndarray of bool, shape (N,)
        True where any column sits at a detected plateau.
    found : list of (column, plateau value, sample count)

    Notes
    -----
    A clipped signal piles up at its limit: the value at the extreme repeats in runs, and
    more samples sit exactly at the extreme than in the 3σ band just inside it (a peak
    passes that band quickly). Gaussian noise about a constant rate (e.g. a rate table)
    has its maximum in the tail with far fewer samples than the band inside; the extreme
    must also be 10σ from the median, so a still recording never qualifies. Columns where
    most consecutive samples are identical (noise-free or coarsely quantized) get no
    verdict: there a run of equal values is normal.
    """
    x = np.asarray(x, float)
    if x.ndim == 1:
        x = x[:, None]
    mask = np.zeros(x.shape[0], bool)
    found = []
    floor = np.broadcast_to(np.asarray(min_clip, float), (x.shape[1],))
    for j in range(x.shape[1]):
        col = x[:, j]
        fin = np.isfinite(col)
        if fin.sum() < 10:
            continue
        c = col if fin.all() else col[fin]  # no copy of an all-finite column
        c_max, c_min = float(c.max()), float(c.min())
        if int(np.count_nonzero(c == c_max)) < min_run and int(np.count_nonzero(c == c_min)) < min_run:
            continue  # neither extreme repeats: no plateau possible (skips the medians below)
        inner = (c != c_max) & (c != c_min)
        d = np.diff(c)[inner[1:] & inner[:-1]]
        mad = float(np.median(np.abs(d - np.median(d)))) if d.size >= 10 else 0.0
        if d.size < 10 or mad == 0.0:
            # away from the extremes most consecutive samples are identical (noise-free
            # simulation, or a quantum coarser than the noise): repeated values are normal
            # there and clipping cannot be told from a constant rate — no verdict
            continue
        sigma = 1.4826 * mad / np.sqrt(2.0)
        med = float(np.median(c))
        for ext in (float(c.max()), float(c.min())):
            at = col == ext
            n_at = int(at.sum())
            if n_at < min_run or abs(ext - med) <= 10.0 * max(sigma, 1e-300) or abs(ext) < floor[j]:
                continue
            # longest run of consecutive samples at the extreme
            edges = np.diff(np.concatenate([[0], at.astype(np.int8), [0]]))
            runs = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
            if runs.max() < min_run:
                continue
            band = 3.0 * sigma if sigma > 0 else abs(ext - med) * 0.01
            inside = (np.abs(col - ext) <= band) & ~at
            if n_at <= int(inside.sum()):
                continue
            mask |= at
            found.append((j, ext, n_at))
    return mask, found


def _unit_checks(rec_t, gyro, accel, path, gyro_col, *, accel_std=None) -> None:
    """Warn when a column labelled rad/s carries deg/s (magnitude evidence), or error."""
    if not gyro_col.endswith("_rad_s") or gyro.shape[0] < 2:
        return
    peak = max(float(np.max(gyro)), -float(np.min(gyro)))  # = max |gyro|, without an (N, 3) temporary
    _refuse_deg_s_peak(peak, path, gyro_col)
    # still recording (accel steady, std < 0.05 g): a MEMS gyro at rest has per-sample noise
    # < 0.05 rad/s (2.9 deg/s; even 0.01 deg/s/sqrt(Hz) at 8 kHz is 0.9 deg/s); deg/s numbers
    # read as rad/s are 57x too big (an MPU-6050's 0.1 deg/s becomes 0.1 "rad/s").
    # (accel_std: the accel was read for this check only, as running moments)
    sd = np.std(accel, axis=0) if accel is not None else accel_std
    if sd is None or not bool(np.all(sd < 0.05 * G0_M_S2)):
        return
    med = np.array([np.median(gyro[:, i]) for i in range(3)])  # per column: no (N, 3) copy
    noise = np.array([still_noise_rad_s(gyro[:, i]) for i in range(3)])
    _warn_still_noise(path, med, noise)


def _refuse_deg_s_peak(peak_rad_s: float, path, gyro_col: str) -> None:
    """One error line when a column labelled rad/s peaks beyond any MEMS full scale."""
    if peak_rad_s > DEG_S_SUSPECT_RAD_S:
        raise GyroInputError(
            f"{path}: gyro peaks at {peak_rad_s:.1f} rad/s ({np.rad2deg(peak_rad_s):.0f} deg/s), beyond any MEMS full "
            f"scale (<= 4000 deg/s = 70 rad/s): the column is probably deg/s; rename it "
            f"{gyro_col.replace('_rad_s', '_deg_s')}"
        )


def _warn_still_noise(path, med, noise) -> None:
    """The warning of a still recording (accel steady) whose per-sample noise (3,) rad/s is beyond
    any MEMS gyro at rest; ``med`` the gyro's median per axis (3,), rad/s."""
    # (a large median alone is not evidence: a centred sensor on a turning rate table also has steady accel)
    if np.any(np.asarray(noise) > STILL_NOISE_SUSPECT_RAD_S):
        warn_repair(
            f"{path}: still recording (accel steady) but gyro median ({', '.join(f'{m:.3g}' for m in med)}) rad/s "
            f"and per-sample noise ({', '.join(f'{v:.3g}' for v in noise)}) rad/s : the noise exceeds any MEMS gyro at rest "
            f"({STILL_NOISE_SUSPECT_RAD_S} rad/s per sample): is it deg/s labelled rad/s? "
            f"Data left unchanged"
        )


def _check_time_span(t: np.ndarray, path) -> None:
    """One error line when the time column's span or steps overflow float64."""
    span = np.subtract(t[-1], t[0], dtype=float) if t.size else 0.0
    with np.errstate(all="ignore"):
        if not np.isfinite(span) or not np.all(np.isfinite(np.diff(t))):
            raise GyroInputError(
                f"{path}: time column spans beyond the float range (t_s from {t[0]:.3g} to {t[-1]:.3g})"
            )


#: Quantile of the sample intervals whose distance below the median measures the timestamps'
#: jitter (:func:`gap_threshold_s`): the lower tail, which no lost sample reaches.
JITTER_QUANTILE = 1e-3


def gap_threshold_s(d_s: np.ndarray, median_dt_s: float, *, overwrite_input: bool = False) -> float:
    """Shortest sample interval counted as a gap (samples missing), s.

    A lost sample makes an interval ≈ 2 × the nominal one T; 1.5 × median sits half way when
    the clock is clean. Timestamps taken by a host on receipt jitter: each interval is
    T + e_{i+1} − e_i, the difference of two draws of the same latency, symmetric about T
    whatever the latency's law, so long intervals come with as many short ones and are no
    gaps (counted as gaps, they would raise the rate of "the intervals without gaps": ±4 ms of
    jitter at 100 Hz read as 104.5 Hz). The jitter's reach J is measured below the median
    (median − the :data:`JITTER_QUANTILE` quantile: −3.1 σ for Gaussian jitter, the bound for
    a bounded one), and a gap must exceed median + 2 J: the mirror image of the lower tail, with
    room for the largest of 10⁶ Gaussian intervals (+4.9 σ < 6.2 σ). A clean clock has
    J ≈ 0 and keeps 1.5 × median.

    Parameters
    ----------
    d_s : ndarray, shape (N−1,)
        Sample intervals, s (positive).
    median_dt_s : float
        Their median, s.
    overwrite_input : bool
        Let the quantile partition ``d_s`` in place (its order is lost; no copy is made).
    """
    if d_s.size == 0 or not median_dt_s > 0:
        return 1.5 * median_dt_s
    lo = float(np.quantile(d_s, JITTER_QUANTILE, overwrite_input=overwrite_input))
    return max(1.5 * median_dt_s, median_dt_s + 2.0 * (median_dt_s - lo))


def _time_unit_check(med_dt_s: float, path: str, time_col: str) -> None:
    """One error line (median interval > :data:`T_S_MAX_MEDIAN_DT_S`) or warning
    (> :data:`T_S_SUSPECT_MEDIAN_DT_S`) when a column labelled seconds is evidently a counter."""
    if {**TIME_ALTS, **TIME_NAME_ALTS}.get(time_col) != 1.0 or not (med_dt_s > T_S_SUSPECT_MEDIAN_DT_S):  # not seconds
        return
    what = f"{path}: column t_s has a median sample interval of {med_dt_s:.6g} s ({1 / med_dt_s:.3g} Hz)"
    if med_dt_s > T_S_MAX_MEDIAN_DT_S:
        raise GyroInputError(
            f"{what}, slower than any gyro log: the time is probably in ms, us or ns — rename the column "
            f"t_ms, t_us or t_ns (converted on read)"
        )
    warn_repair(
        f"{what}: if the time is a millisecond counter (a 1 kHz log), rename the column t_ms; data kept as seconds"
    )


def _timing_checks(t: np.ndarray, path: str, retime: bool, time_col: str) -> np.ndarray:
    """Warn on gaps (dropped samples) and bursty host timestamps; retime on request."""
    d = np.diff(t)
    if d.size < 2:
        return t
    mean = float((t[-1] - t[0]) / d.size)
    mx = float(d.max())
    # the partition permutes d in place; what follows (max, counts, a sum of integers) does
    # not depend on the order: the same values with d as the only temporary
    med = float(np.median(d, overwrite_input=True))
    _time_unit_check(med, path, time_col)
    if med < 0.5 * mean and mx > 4.0 * mean:
        if retime:
            warn_repair(
                f"{path}: bursty host timestamps (median dt {med * 1e3:.3g} ms, mean {mean * 1e3:.3g} ms, gaps up to "
                f"{mx:.3g} s) replaced by a uniform grid at the mean rate {1 / mean:.6g} Hz"
            )
            return t[0] + np.arange(t.size) * ((t[-1] - t[0]) / (t.size - 1))
        warn_repair(
            f"{path}: bursty host timestamps (median dt {med * 1e3:.3g} ms, mean {mean * 1e3:.3g} ms, gaps up to "
            f"{mx:.3g} s); rates and Allan variance need a uniform grid: use --retime (gyroharness convert)"
        )
        return t
    lo = float(d.min())
    gap_s = gap_threshold_s(d, med, overwrite_input=True)
    gaps = d > gap_s
    if med > 0 and gaps.any():
        n_missing = int(np.sum(np.round(d[gaps] / med) - 1))
        how = (
            f"1.5x the median interval {med * 1e3:.3g} ms"
            if gap_s == 1.5 * med
            else f"{gap_s * 1e3:.3g} ms (the median interval {med * 1e3:.3g} ms plus twice its jitter)"
        )
        warn_repair(
            f"{path}: {int(gaps.sum())} gaps longer than {how} "
            f"(longest {mx:.3g} s, ~{n_missing} samples missing in all); data kept as recorded"
        )
    if med > 0 and lo < 0.5 * med:
        hi = float(d[~gaps].max()) if gaps.any() else mx
        warn_repair(
            f"{path}: timestamps jitter (intervals {lo * 1e3:.3g}-{hi * 1e3:.3g} ms about the median "
            f"{med * 1e3:.3g} ms: a host clock?); long intervals mirrored by short ones are not gaps; "
            f"data kept as recorded"
        )
    return t
