"""Fits of long recordings held on disk, a window at a time (issue 13: bounded memory).

A long data file is streamed once into per-column files (:func:`gyrocore.recording.spill_columns`,
with every check, repair and warning of a whole read); the least-squares fits then read it
back a window of ``lsq.CHUNK_ROWS`` rows at a time through :class:`SpillRows`, a
:class:`gyrocore.lsq.RowSource`. The chunked path of :func:`gyrocore.lsq.fit_effects` reduces
each window to the weighted block means that :func:`gyrocore.lsq.solve` fits (an exact
reduction for the linear model, see ``solve(average=)``), so the fit, its rank test, axis
weights, covariance (OLS/HAC/...) and standard errors are computed by the same function on
the same numbers as for a record in memory; a second pass gives the full-resolution residual
(its RMS, or per axis on disk for the robust pass). Memory: the time column, one (N,) weight
column and one residual axis at a time, plus a window (``CHUNK_ROWS`` × 3 × P) and the block
means (≤ ``max_rows`` × 3 × P).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from . import effects as E
from . import lsq
from .recording import ACCEL_COLS, GYRO_COLS, REF_RATE_COLS, TEMP_COL, ColumnSpill

__all__ = ["SpillRows", "ResidualFiles"]


class SpillRows(lsq.RowSource):
    """r = y − ω_ref(t − τ) and the model inputs of a spilled recording, a window at a time.

    Parameters
    ----------
    store : ColumnSpill
        The spilled columns (``t_s`` in memory; gyro, ``ref_*_rad_s`` and, when present,
        accel and ``temp_c`` on disk).
    tau_s : float
        Time offset τ, s: the reference rate is taken at t − τ by linear interpolation (the
        catalogue's ``time_offset`` convention, as ``model._shift_rate``); rows outside the
        record hold the end values (``np.interp``).
    """

    def __init__(self, store: ColumnSpill, *, tau_s: float = 0.0) -> None:
        self.store = store
        self.tau_s = float(tau_s)
        self.n = int(store.n)
        self.t = store.t_s
        self.has_ref = all(c in store.names for c in REF_RATE_COLS)
        self.has_accel = all(c in store.names for c in ACCEL_COLS)
        self.has_temp = TEMP_COL in store.names
        self._temp_mean = None

    def _ref(self, a: int, b: int) -> np.ndarray:
        """ω_ref(t − τ) on rows a:b, shape (b − a, 3)."""
        if not self.has_ref:
            return np.zeros((b - a, 3))
        if self.tau_s == 0.0:
            return self.store.block(REF_RATE_COLS, a, b)
        t = self.t
        tq = t[a:b] - self.tau_s
        # the rows of the reference that bracket every query point (np.interp uses only the
        # bracketing pair, and the end values beyond the record): the same numbers as on the
        # whole column
        i0 = max(int(np.searchsorted(t, tq[0], side="left")) - 1, 0)
        i1 = min(int(np.searchsorted(t, tq[-1], side="right")) + 1, self.n)
        w = self.store.block(REF_RATE_COLS, i0, i1)
        return np.stack([np.interp(tq, t[i0:i1], w[:, i]) for i in range(3)], axis=1)

    def ref_rows(self, a: int, b: int) -> np.ndarray:
        """ω_ref(t − τ) on rows a:b, shape (b − a, 3) (zeros without reference columns)."""
        return self._ref(a, b)

    def r_rows(self, a: int, b: int) -> np.ndarray:
        return self.store.block(GYRO_COLS, a, b) - self._ref(a, b)

    def inputs(self, lo: int, hi: int) -> E.ModelInputs:
        t = self.t
        return E.ModelInputs(
            t_s=t[lo:hi], omega_S_rad_s=self._ref(lo, hi),
            f_S_m_s2=self.store.block(ACCEL_COLS, lo, hi) if self.has_accel else None,
            temp_c=self.store.rows(TEMP_COL, lo, hi) if self.has_temp else None,
            t_since_power_up_s=t[lo:hi] - t[0],
        )

    def temp_mean_c(self) -> float | None:
        if not self.has_temp:
            return None
        if self._temp_mean is None:  # np.mean of the whole column: the same number as in memory
            self._temp_mean = float(np.mean(self.store.column(TEMP_COL)))
        return self._temp_mean


class ResidualFiles:
    """A ``residual_sink`` for :func:`gyrocore.lsq.fit_effects` writing each axis of the
    full-resolution residual to its own file; :meth:`axis` reads one axis back (N,)."""

    def __init__(self, folder: str | os.PathLike, n: int) -> None:
        self.n = int(n)
        self.paths = [Path(folder) / f"residual_{a}.f64" for a in "xyz"]
        for p in self.paths:
            with open(p, "wb") as fh:
                fh.truncate(8 * self.n)

    def __call__(self, a: int, b: int, e: np.ndarray) -> None:
        for i, p in enumerate(self.paths):
            with open(p, "r+b") as fh:
                fh.seek(8 * int(a))
                fh.write(np.ascontiguousarray(e[:, i], dtype=np.float64).tobytes())

    def axis(self, i: int) -> np.ndarray:
        return np.fromfile(self.paths[i], dtype=np.float64, count=self.n)
