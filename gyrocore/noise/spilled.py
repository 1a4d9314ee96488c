"""Noise identification of a long data file held on disk, one axis at a time (bounded memory).

The file is streamed once into per-column files (:func:`gyrocore.data.spill.spill_columns`:
the same repairs, checks and warnings as a whole read); each axis is then loaded alone with the
time column, so memory holds two columns instead of four; the numbers are those of
:func:`gyrocore.noise.allan.allan_analysis` on the whole record. ``gyroharness allan`` takes
this path for a file :func:`gyrocore.readers.large.is_large` calls large.
"""

from __future__ import annotations

import numpy as np

from gyrocore.errors import GyroInputError

__all__ = ["allan_by_axis", "t_rows"]


def t_rows(t_s: np.ndarray, t_from_s: float | None, t_to_s: float | None) -> tuple[int, int]:
    """Rows [a, b) with t_from_s <= t < t_to_s (one ``error:`` line when that leaves too little)."""
    a = 0 if t_from_s is None else int(np.searchsorted(t_s, t_from_s, side="left"))
    b = t_s.size if t_to_s is None else int(np.searchsorted(t_s, t_to_s, side="left"))
    if b - a < 2:
        raise GyroInputError(
            f"--t-from-s/--t-to-s select {max(b - a, 0)} samples; the recording spans t = {t_s[0]:.6g}-{t_s[-1]:.6g} s"
        )
    return a, b


def allan_by_axis(
    file: str,
    *,
    axes,
    max_tau_s,
    kalibr: bool,
    engine: str,
    method: str = "gmwm",
    check_static: bool = True,
    t_from_s: float | None = None,
    t_to_s: float | None = None,
):
    """:func:`gyrocore.noise.allan.allan_analysis` of a long recording, one axis at a time.

    The file is streamed once into per-column files in a temporary folder
    (:func:`gyrocore.data.spill.spill_columns`: the same repairs, checks and warnings as a
    whole read); each axis is then loaded alone with the time column. The results are
    identical to the whole-record analysis (same samples, same rate, same kernel); memory
    holds two columns (t and the axis) plus the ADEV buffers; the motion gate
    (``check_static``) reads only the windows it judges.
    """
    import tempfile
    import warnings

    from gyrocore.noise.allan import AllanAnalysis, allan_analysis
    from gyrocore.data.recording import AXES
    from gyrocore.data.spill import spill_columns

    with tempfile.TemporaryDirectory(prefix="gyroharness_allan_") as tmp:
        store = spill_columns(file, tmp, accel=kalibr)
        has_accel = "accel_x_m_s2" in store.names
        still = None
        rows = (0, store.n)
        span_s = None
        if t_from_s is not None or t_to_s is not None:
            rows = t_rows(store.t_s, t_from_s, t_to_s)
        if check_static and rows != (0, store.n):
            # a chosen part: the whole gate of allan_analysis on its three axes (memory O(3 × part))
            from gyrocore.noise.allan import analysed_span
            from gyrocore.data.recording import GYRO_COLS

            from gyrocore.data.recording import Recording

            part = Recording(t_s=store.t_s[rows[0] : rows[1]], gyro_rad_s=store.block(GYRO_COLS, *rows))
            sp = analysed_span(part.gyro_rad_s, part.rate_hz, t0_s=float(part.t_s[0]))
            still = sp.still_fraction
            if sp.cut:
                from gyrocore.errors import warn_repair

                warn_repair(sp.message)
                rows = (rows[0] + sp.start, rows[0] + sp.stop)
            del part
        elif check_static:  # the same gate as allan_analysis(check_static=True), on up to 200 windows
            import scipy.stats

            from gyrocore.data.recording import Recording
            from gyrocore.noise.allan import MAX_MOVING_FRACTION, _judged_windows

            rate = Recording(t_s=store.t_s, gyro_rad_s=np.broadcast_to(0.0, (store.n, 3))).rate_hz
            sw = _judged_windows(store, rate)  # reads only the windows it judges
            still = sw.fraction if sw is not None else float("nan")
            w_judged = sw.n_windows if sw is not None else 0
            k = int((~sw.still).sum()) if sw is not None else 0
            if sw is not None and (
                (1.0 - still) > MAX_MOVING_FRACTION or (k > 0 and scipy.stats.binom.sf(k - 1, w_judged, 1e-3) < 1e-3)
            ):
                raise GyroInputError(
                    f"recording is not static: the motion gate rejects {k} of {w_judged} 2-s windows spread over it "
                    f"(a still sensor: {w_judged * 1e-3:.2g} by chance); a long file is analysed whole: choose its still "
                    f"part with --t-from-s/--t-to-s"
                )
        if rows != (0, store.n):
            span_s = (float(store.t_s[rows[0]]), float(store.t_s[rows[1] - 1]))
        per_axis, per_accel = {}, {}
        seen: set[str] = set()
        last = None
        for a in axes:
            j = AXES.index(a)
            for kind in ("gyro", "accel") if has_accel else ("gyro",):
                rec = store.recording(j) if kind == "gyro" else store.recording(j, accel_axis=j)
                if rows != (0, store.n):
                    rec = rec.slice(*rows)
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    r = allan_analysis(
                        rec, axes=[a], max_tau_s=max_tau_s, accel=kind == "accel", engine=engine, method=method
                    )
                for w in caught:  # the record-level warnings once, not once per axis
                    if str(w.message).startswith("no long-tau term resolved"):
                        continue  # given once below, from all the axes (as allan_analysis does)
                    if str(w.message) not in seen:
                        seen.add(str(w.message))
                        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
                if kind == "gyro":
                    per_axis[a] = r.axes[a]
                else:
                    per_accel[a] = r.accel[a]
                last = r
                del rec
    from gyrocore.noise.allan import _warn_short

    if method != "adev_legacy":
        _warn_short(per_axis, last.duration_s, last.n_samples, last.rate_hz, method)
    return AllanAnalysis(
        axes=per_axis,
        accel=per_accel,
        rate_hz=last.rate_hz,
        n_samples=last.n_samples,
        duration_s=last.duration_s,
        dropped_taus_s=last.dropped_taus_s,
        method=method,
        still_fraction=still,
        analysed_span_s=span_s,
    )
