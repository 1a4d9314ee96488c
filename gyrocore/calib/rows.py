"""The rows a least-squares fit reads, a window at a time, and their reduction to block means.

Every fit of :mod:`gyrocore.calib.lsq` reads its data through a :class:`RowSource` — the
left-hand side r = y − ω_ref and the model inputs of rows a:b — and reduces the used rows
(every ``stride``-th with a non-zero weight) to the weighted means of ``average`` consecutive
used rows (:class:`BlockMeans`), window by window. The linear model holds exactly for the
means, so the solver sees at most N/``average`` rows whatever the record's length: memory is
bounded by the window (``CHUNK_ROWS`` × 3 × P) and the block means (N/``average`` × 3 × P).
Arrays in memory are an :class:`ArrayRows`; a recording's columns (in memory or on disk,
:mod:`gyrocore.data.columns`) against its reference rate are a :class:`ReferenceRows` — the
same windows, the same sums, the same numbers.
With ``average`` = 1 a block is one row and its "mean" is the row itself (no arithmetic).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from gyrocore.data.recording import ACCEL_COLS, GYRO_COLS, REF_RATE_COLS, TEMP_COL
from gyrocore.effects import registry as E
from gyrocore.errors import GyroInputError

__all__ = ["RowSource", "ArrayRows", "ReferenceRows", "BlockMeans", "BlockRows", "window_ranges", "CHUNK_ROWS"]

#: Window length (rows) of the design built by :func:`gyrocore.calib.lsq.fit_effects`; a record of
#: at most four windows is one window (its design, ≤ 4·CHUNK_ROWS rows, is within the same bound).
CHUNK_ROWS: int = 32768


def window_ranges(n: int, chunk_rows: int | None) -> list[tuple[int, int]]:
    """Consecutive row ranges [a, b) covering n rows: windows of ``chunk_rows`` rows, or one
    window when ``chunk_rows`` is None or n ≤ 4·``chunk_rows``."""
    if not chunk_rows or n <= 4 * int(chunk_rows):
        return [(0, n)]
    c = int(chunk_rows)
    return [(a, min(a + c, n)) for a in range(0, n, c)]


def _window_inputs(inp: E.ModelInputs, lo: int, hi: int) -> E.ModelInputs:
    """Rows lo:hi of ``inp``; the power-up time stays that of the whole record."""
    kw = {}
    for f in dataclasses.fields(inp):
        v = getattr(inp, f.name)
        kw[f.name] = None if v is None else np.asarray(v)[lo:hi]
    if inp.t_since_power_up_s is None:
        t = np.asarray(inp.t_s, float)
        kw["t_since_power_up_s"] = t[lo:hi] - t[0]
    return E.ModelInputs(**kw)


class RowSource:
    """Rows of a fit's left-hand side r = y − ω_ref and of its model inputs, a window at a time.

    Attributes
    ----------
    n : int
        Number of rows N.
    has_temp : bool
        Whether the inputs carry a temperature column.
    """

    n: int = 0
    has_temp: bool = False

    def r_rows(self, a: int, b: int) -> np.ndarray:
        """r on rows a:b, rad/s, shape (b − a, 3) (a fresh or read-only array)."""
        raise NotImplementedError

    def inputs(self, lo: int, hi: int) -> E.ModelInputs:
        """Model inputs of rows lo:hi (``t_since_power_up_s`` counted from the record's start)."""
        raise NotImplementedError

    def t_rows(self, a: int, b: int) -> np.ndarray:
        """Sample times of rows a:b, s."""
        return np.asarray(self.inputs(a, b).t_s, float)

    def temp_mean_c(self) -> float | None:
        """Mean temperature over all N rows, °C (the thermal T0 of :func:`gyrocore.effects.registry.design`)."""
        raise NotImplementedError


class ArrayRows(RowSource):
    """:class:`RowSource` over in-memory arrays ``r`` (N, 3) and ``inp`` (checked: shape, finite)."""

    def __init__(self, r: np.ndarray, inp: E.ModelInputs) -> None:
        r = np.asarray(r, float)
        if r.ndim != 2 or r.shape[1] != 3:
            raise GyroInputError(f"lsq: r has shape {r.shape}; expected (N,3)")
        if inp.n != r.shape[0]:
            raise GyroInputError(f"lsq: r has {r.shape[0]} rows, the model inputs {inp.n}")
        if not np.all(np.isfinite(r)):
            raise GyroInputError("lsq: non-finite values in the data or regressors")
        self.r = r
        self.inp = inp
        self.n = int(r.shape[0])
        self.has_temp = inp.temp_c is not None

    def r_rows(self, a: int, b: int) -> np.ndarray:
        return self.r[a:b]

    def inputs(self, lo: int, hi: int) -> E.ModelInputs:
        return _window_inputs(self.inp, lo, hi)

    def t_rows(self, a: int, b: int) -> np.ndarray:
        return np.asarray(self.inp.t_s, float)[a:b]

    def temp_mean_c(self) -> float | None:
        return None if self.inp.temp_c is None else float(np.mean(np.asarray(self.inp.temp_c, float)))


class ReferenceRows(RowSource):
    """r = y − ω_ref(t − τ) and the model inputs of a recording, a window at a time.

    Parameters
    ----------
    store : chunk source
        The recording's columns (:mod:`gyrocore.data.columns`: a recording in memory, or a
        :class:`gyrocore.data.spill.ColumnSpill` on disk): ``t_s``, the gyro and, when present,
        ``ref_*_rad_s`` (zeros without: the still parts' rate 0), accel and ``temp_c``.
    tau_s : float
        Time offset τ, s: the reference rate is taken at t − τ by linear interpolation (the
        catalogue's ``time_offset`` convention); rows outside the record hold the end values
        (``np.interp``).
    """

    def __init__(self, store, *, tau_s: float = 0.0) -> None:
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
            t_s=t[lo:hi],
            omega_S_rad_s=self._ref(lo, hi),
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


@dataclass(frozen=True, eq=False)
class BlockRows:
    """The rows the solver fits: block means r (n, 3), A (n, 3, P), their weights w (n, 3)
    and, for a noise-model covariance, each row's interval t0..t1 (s since the power-up, (n,))
    and effective sample count n_eff (n, 3) (None otherwise)."""

    r: np.ndarray
    A: np.ndarray
    w: np.ndarray
    t0_s: np.ndarray | None = None
    t1_s: np.ndarray | None = None
    n_eff: np.ndarray | None = None


def used_rows(n: int, weights, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """The (N, 3) weights (a read-only broadcast when given as (N,)) and the boolean (N,) mask
    of the rows a fit uses: every ``stride``-th row with a non-zero weight on some axis."""
    w_all = np.ones((n, 3)) if weights is None else np.broadcast_to(np.asarray(weights, float).reshape(n, -1), (n, 3))
    if np.any(~np.isfinite(w_all)) or np.any(w_all < 0):
        raise GyroInputError("lsq: weights must be finite and non-negative")
    keep = np.zeros(n, bool)
    keep[:: max(1, int(stride))] = True
    keep &= np.any(w_all > 0, axis=1)
    if int(np.count_nonzero(keep)) < 2:
        raise GyroInputError("lsq: fewer than 2 samples with non-zero weight")
    return w_all, keep


class BlockMeans:
    """Weighted means of ``average`` consecutive used rows, accumulated window by window.

    Block k holds used rows k·average … (k+1)·average − 1 (the last incomplete block is
    dropped). Each window adds its rows' weighted sums Σw·r, Σw·A, Σw, Σw² to the blocks they
    belong to; a block that straddles two windows is summed in two parts (its float rounding,
    ~average·eps relative, is the only difference from one window). ``times`` (N,) — the rows'
    times in s since the power-up, with the sample spacing ``dt_s`` — are reduced to each
    block's interval [first time, last time + dt_s] for a noise-model covariance.

    Parameters
    ----------
    w_all : ndarray, shape (N, 3)
    keep : ndarray of bool, shape (N,)
        The used rows (:func:`used_rows`).
    average : int
    with_times : bool
        Keep the rows' intervals and effective counts (:meth:`add` then needs ``t``).
    dt_s : float
    """

    def __init__(self, w_all: np.ndarray, keep: np.ndarray, average: int, *, with_times: bool, dt_s: float) -> None:
        self.w_all, self.keep = w_all, keep
        self.average = max(1, int(average))
        n_used = int(np.count_nonzero(keep))
        self.nb = n_used // self.average
        if self.nb < 2:
            raise GyroInputError(f"lsq: average={self.average} leaves fewer than 2 rows")
        self.m = self.nb * self.average  # used rows that fall in a complete block
        self.with_times, self.dt_s = with_times, float(dt_s)
        self.j0 = 0  # used rows seen so far
        self.Sr = self.SA = None
        self.Sw = np.zeros((self.nb, 3))
        self.Sw2 = np.zeros((self.nb, 3))
        self.T0 = np.full(self.nb, np.inf)
        self.T1 = np.full(self.nb, -np.inf)

    @property
    def done(self) -> bool:
        """Whether every complete block is filled (later rows are not used)."""
        return self.j0 >= self.m

    def rows_in(self, a: int, b: int) -> np.ndarray:
        """Indices (into a:b, relative to a) of the window's rows that go into a block."""
        rows = np.flatnonzero(self.keep[a:b])
        return rows[: max(0, min(rows.size, self.m - self.j0))]

    def add(self, a: int, rows: np.ndarray, r: np.ndarray, A: np.ndarray, t: np.ndarray | None = None) -> None:
        """Add the used rows ``a + rows`` of a window: their r (k, 3), A (k, 3, P) and, with
        times, t (k,) (s since the power-up)."""
        k_rows = rows.size
        if k_rows == 0:
            return
        wr = self.w_all[a + rows]
        if self.SA is None:
            self.SA = np.zeros((self.nb, 3, A.shape[2]))
            self.Sr = np.zeros((self.nb, 3))
        j1 = self.j0 + k_rows
        if self.average == 1:  # a block of one row: the row itself, its weight as given
            self.SA[self.j0 : j1] = A
            self.Sr[self.j0 : j1] = r
            self.Sw[self.j0 : j1] = wr
            if self.with_times:
                self.T0[self.j0 : j1] = t
                self.T1[self.j0 : j1] = t + self.dt_s
        else:
            self._add_blocks(r, A, wr, t, j1)
        self.j0 = j1

    def _add_blocks(self, r, A, wr, t, j1: int) -> None:
        """The window's used rows j0..j1 (in used-row numbering) into their blocks: the complete
        blocks inside the window as ``(x·w).reshape(blocks, average, …).sum(axis=1)``, a block cut
        by the window's start or end as the sum of its part here (added to its other part)."""
        avg, j0 = self.average, self.j0
        jb = min(-(-j0 // avg) * avg, j1)  # first block start at or after j0
        je = max((j1 // avg) * avg, jb)  # last block end at or before j1
        for lo, hi in ((j0, jb), (je, j1)):  # the cut blocks' parts
            if hi > lo:
                i, k = slice(lo - j0, hi - j0), lo // avg
                self.SA[k] += np.sum(A[i] * wr[i][..., None], axis=0)
                self.Sr[k] += np.sum(r[i] * wr[i], axis=0)
                self.Sw[k] += np.sum(wr[i], axis=0)
                self.Sw2[k] += np.sum(wr[i] ** 2, axis=0)
                if self.with_times:
                    self.T0[k] = min(self.T0[k], t[i][0])
                    self.T1[k] = max(self.T1[k], t[i][-1] + self.dt_s)
        if je > jb:  # the complete blocks
            i, kb = slice(jb - j0, je - j0), slice(jb // avg, je // avg)
            nbk = (je - jb) // avg
            wb = wr[i].reshape(nbk, avg, 3)
            self.SA[kb] = (A[i].reshape(nbk, avg, 3, -1) * wb[..., None]).sum(axis=1)
            self.Sr[kb] = (r[i].reshape(nbk, avg, 3) * wb).sum(axis=1)
            self.Sw[kb] = wb.sum(axis=1)
            self.Sw2[kb] = (wb**2).sum(axis=1)
            if self.with_times:
                self.T0[kb] = t[i][::avg]
                self.T1[kb] = t[i][avg - 1 :: avg] + self.dt_s

    def result(self) -> BlockRows:
        """The block means (the rows themselves when ``average`` = 1)."""
        if self.average == 1:
            r, A, w, n_eff = self.Sr, self.SA, self.Sw, np.ones((self.nb, 3))
        else:
            safe = np.where(self.Sw > 0, self.Sw, 1.0)
            r, A = self.Sr / safe, self.SA / safe[..., None]
            w = self.Sw / self.average
            n_eff = np.where(self.Sw2 > 0, self.Sw**2 / np.where(self.Sw2 > 0, self.Sw2, 1.0), 0.0)
        if not self.with_times:
            return BlockRows(r, A, w)
        return BlockRows(r, A, w, self.T0, self.T1, n_eff)
