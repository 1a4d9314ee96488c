"""The recording the loop reads, a window of rows at a time: in memory (one window) or on disk.

The loop's per-sample passes — the rate residual's block means, the attitude error against the
reference rate, the line search's sample-level series, the gyro with narrow-band lines removed
or advanced by a time offset — are written once, over windows of rows. :func:`of` wraps the
recording in the one object that tells the two storages apart:

* a :class:`~gyrocore.data.recording.Recording` in memory is **one window**: per-sample values
  are whole arrays (the same operations on the same numbers as a whole-array computation);
* a :class:`~gyrocore.calib.stream.SpilledRecording` on disk is read ``chunk_rows`` rows at a
  time: per-sample values are :class:`~gyrocore.calib.stream.Rows`, computed when a window asks,
  and the gyro's lines and time offset are applied as each window is read.

Recurrences cut by a window (the attitude integration) are carried across it: each window
starts from the previous one's last attitude and sample, so the backward-hold step across the
cut is taken once (:func:`gyrocore.attitude.integrate_gyro_windows`).

This is not a second chunk source beside :func:`gyrocore.data.columns.columns_of`, which stays
the one way a recording's *stored* columns are read a block at a time: on disk every read here
goes through it (a :class:`~gyrocore.calib.stream.SpilledRecording`'s columns are
:class:`~gyrocore.data.spill.ColumnSpill` ``rows``/``block`` reads, its integrated reference
attitude a ``scratch`` work column). What this module windows is different, for two reasons:

* its per-sample values are *derived* (the model's correction, the residual, the attitude error,
  the gyro with the loop's lines removed or advanced by τ), computed where a window asks for
  them, with recurrences carried across windows — not named file columns;
* in memory the loop is **one window** (whole arrays), so that its numbers are those of the
  whole-array computation; the chunk source cuts a recording in memory into blocks of
  ``MEMORY_BLOCK_BYTES``, and windows that cut the loop's sums and its attitude recurrence
  move its numbers by rounding (≲ 1e-9 relative in the estimates: the tolerance of
  tests/gyrocore/loop/test_loop_stream.py, which compares the two storages). On disk the
  window is ``chunk_rows`` rows (sized by the largest per-sample design,
  :data:`~gyrocore.calib.stream.SPILL_CHUNK_ROWS`), not a byte budget of raw columns.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gyrocore.attitude import integrate_gyro, integrate_gyro_windows, rotation_matrices
from gyrocore.calib.stream import LazyRotations, Rows, SpilledRecording, held_correction, rows_of
from gyrocore.data.recording import Recording

__all__ = ["of", "column", "integrated_windows"]


def of(rec: Recording | SpilledRecording) -> _InMemory | _OnDisk:
    """The window source of a recording (in memory: one window; on disk: ``chunk_rows`` rows)."""
    return _OnDisk(rec) if isinstance(rec, SpilledRecording) else _InMemory(rec)


def column(x, i: int) -> np.ndarray:
    """Column i of per-sample values as one (n,) array (a lazy one is read a window at a time)."""
    return x.axis(i) if isinstance(x, Rows) else x[:, i]


def integrated_windows(src, rate, q0_wxyz: np.ndarray | None = None):
    """The rate (N, 3) rad/s integrated window by window over the source's windows, the
    attitude carried across them (:func:`gyrocore.attitude.integrate_gyro_windows`, backward
    hold): yields (lo, hi, q (hi − lo, 4) w,x,y,z) per window, starting from ``q0_wxyz``
    (default: identity)."""
    return integrate_gyro_windows(src.rec.t_s, lambda lo, hi: rows_of(rate, lo, hi), src.windows(), q0_wxyz=q0_wxyz)


class _InMemory:
    """A recording in memory: one window, per-sample values as arrays."""

    on_disk = False
    chunk_rows = 0

    def __init__(self, rec: Recording) -> None:
        self.rec = rec

    def windows(self):
        yield 0, self.rec.n

    def per_sample(self, fn, ncol: int, lo: int = 0, hi: int | None = None):
        """Per-sample values ``fn(a, b)`` (rows a:b, absolute) of rows lo:hi."""
        return fn(lo, self.rec.n if hi is None else hi)

    def finite_rows(self, x) -> np.ndarray:
        """Rows of x (N, C) whose values are all finite, (N,) bool."""
        return np.all(np.isfinite(x), axis=1)

    def reference_attitude(self, rate=None) -> np.ndarray | None:
        """The reference attitude S→W per sample (N, 4): ``ref_q*`` when finite everywhere, else
        ``rate`` (default: the reference rate) integrated from the identity when finite
        everywhere; None without either."""
        q = self.rec.ref_quat_wxyz
        if q is not None and np.all(np.isfinite(q)):
            return q
        w = self.rec.ref_rate_rad_s if rate is None else rate
        if w is None or not np.all(np.isfinite(w)):
            return None
        return integrate_gyro(self.rec.t_s, w, hold="backward")

    def rotations(self, q) -> np.ndarray:
        """Rotation matrices (N, 3, 3) of quaternions (N, 4) w,x,y,z."""
        return rotation_matrices(q)

    def without_lines(self, held: dict) -> Recording:
        """The recording with the narrow-band lines ``held`` removed from the gyro (raw time frame)."""
        rec = self.rec
        return replace(rec, gyro_rad_s=rec.gyro_rad_s - held_correction(rec.t_s, held))

    def advance(self, tau_s: float) -> Recording:
        """The recording with the gyro advanced by τ: gyro'(t) = gyro(t + τ) (cubic spline, ends held)."""
        from scipy.interpolate import CubicSpline

        rec = self.rec
        t = rec.t_s
        tq = np.clip(t + tau_s, t[0], t[-1])
        return replace(rec, gyro_rad_s=CubicSpline(t, rec.gyro_rad_s, axis=0)(tq))


class _OnDisk:
    """A recording on disk: windows of ``chunk_rows`` rows, per-sample values as lazy :class:`Rows`."""

    on_disk = True

    def __init__(self, rec: SpilledRecording) -> None:
        self.rec = rec
        self.chunk_rows = rec.chunk_rows

    def windows(self):
        return self.rec.chunks()

    def per_sample(self, fn, ncol: int, lo: int = 0, hi: int | None = None) -> Rows:
        if lo != 0 or hi not in (None, self.rec.n):
            raise ValueError("a recording on disk is read whole, a window at a time")
        return Rows(fn, self.rec.n, ncol)

    def finite_rows(self, x) -> np.ndarray:
        return np.concatenate([np.all(np.isfinite(rows_of(x, lo, hi)), axis=1) for lo, hi in self.windows()])

    def reference_attitude(self, rate=None) -> Rows | None:
        """As :meth:`_InMemory.reference_attitude` for the reference rate, integrated window by
        window into a file beside the spill (:meth:`SpilledRecording.reference_quaternions`)."""
        if rate is not None and rate is not self.rec.ref_rate_rad_s:
            raise ValueError("a recording on disk integrates its own reference rate only")
        return self.rec.reference_quaternions()

    def rotations(self, q) -> LazyRotations:
        return LazyRotations(q)

    def without_lines(self, held: dict) -> SpilledRecording:
        # removed a window at a time where the gyro is read
        return self.rec.with_ops(held=held, tau_s=0.0)

    def advance(self, tau_s: float) -> SpilledRecording:
        # advanced a window at a time where the gyro is read (spline on the window plus context)
        return self.rec.with_ops(tau_s=tau_s)
