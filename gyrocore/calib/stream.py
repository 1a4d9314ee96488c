"""The residual loop's view of a long recording held on disk (bounded memory).

A long data file is streamed once into per-column files (:func:`gyrocore.data.spill.spill_columns`,
with every check, repair and warning of a whole read). :class:`SpilledRecording` gives the
residual loop the attributes of a :class:`~gyrocore.data.recording.Recording` with every
column but the time read a window at a time (:class:`LazyColumn`, :class:`Rows`). The
least-squares fits read any recording, in memory or spilled, through
:class:`gyrocore.calib.rows.ReferenceRows` (one path, :func:`gyrocore.calib.lsq.fit_effects`).
"""

from __future__ import annotations


import numpy as np

from gyrocore.data.recording import ACCEL_COLS, GYRO_COLS, REF_RATE_COLS, TEMP_COL, Recording
from gyrocore.data.spill import ColumnSpill, release_arrow_memory

__all__ = [
    "Rows",
    "LazyColumn",
    "LazyRotations",
    "SpilledRecording",
    "rows_of",
    "held_correction",
    "NotStreamable",
    "release_memory",
    "bounded_heap",
]


# ---------------------------------------------------------------------------- the residual loop from disk
class NotStreamable(Exception):
    """What the residual loop cannot do from disk (another reference than the reference rate,
    segments, NaN rows in the reference): the caller reads the recording whole instead."""


class Rows:
    """A lazy (N, C) or (N,) array: rows lo:hi are computed by ``fn(lo, hi)`` when asked.

    The residual loop passes per-sample quantities of a spilled recording (the model
    correction, the sample-level residual, the motion columns) as ``Rows`` so that they are
    built a window at a time; ``np.asarray`` assembles the whole array (a fallback for code
    that needs it: correct, but O(N) memory).
    """

    def __init__(self, fn, n: int, ncol: int | None) -> None:
        self.fn = fn
        self.n = int(n)
        self.shape = (self.n,) if ncol is None else (self.n, int(ncol))
        self.ndim = len(self.shape)

    def rows(self, lo: int, hi: int) -> np.ndarray:
        lo, hi = max(0, int(lo)), min(self.n, int(hi))
        return self.fn(lo, hi)

    def axis(self, i: int, chunk: int = 1 << 17) -> np.ndarray:
        """Column i as a whole (N,) array, filled a chunk at a time."""
        out = np.empty(self.n)
        for a in range(0, self.n, chunk):
            b = min(a + chunk, self.n)
            out[a:b] = self.rows(a, b)[:, i]
        return out

    def __array__(self, dtype=None, copy=None):
        out = np.empty(self.shape)
        for a in range(0, self.n, 1 << 17):
            b = min(a + (1 << 17), self.n)
            out[a:b] = self.rows(a, b)
        return out if dtype is None else out.astype(dtype)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, key):
        if isinstance(key, slice) and key.step in (None, 1):
            lo, hi, _ = key.indices(self.n)
            return self.rows(lo, hi)
        return np.asarray(self)[key]


def rows_of(v, lo: int, hi: int):
    """Rows lo:hi of an array, a :class:`Rows` or a :class:`LazyColumn` (None stays None)."""
    if v is None:
        return None
    if isinstance(v, Rows):
        return v.rows(lo, hi)
    return np.asarray(v)[lo:hi]


class LazyColumn(Rows):
    """Columns of a :class:`~gyrocore.data.spill.ColumnSpill` read from disk rows lo:hi at a time
    (``squeeze``: one column, shape (N,))."""

    def __init__(self, store: ColumnSpill, names, *, squeeze: bool = False) -> None:
        names = list(names)
        self.store = store
        self.names = names
        if squeeze:
            fn = lambda lo, hi: store.rows(names[0], lo, hi)  # noqa: E731
        else:
            fn = lambda lo, hi: store.block(names, lo, hi)  # noqa: E731
        super().__init__(fn, store.n, None if squeeze else len(names))


class LazyRotations(Rows):
    """Rotation matrices R (N, 3, 3) of a quaternion column set (w, x, y, z), rows on demand."""

    def __init__(self, q: Rows) -> None:
        from gyrocore.attitude import rotation_matrices

        def fn(lo, hi):
            return rotation_matrices(q.rows(lo, hi))

        super().__init__(fn, q.n, 3)
        self.shape = (q.n, 3, 3)
        self.ndim = 3


#: Rows per window of a :class:`SpilledRecording` (the residual loop's per-sample passes): the
#: largest per-sample design, ``g2_sensitivity`` (3 × 18 columns), is 14 MB per window of
#: 32 768 rows (86 MB at the in-memory path's 200 000).
SPILL_CHUNK_ROWS = 32_768

#: Extra samples on each side of a window when the gyro is advanced by a time offset with a
#: not-a-knot cubic spline fitted to the window only: the spline's dependence on a sample k
#: rows away decays as (2 − √3)^k ≈ 0.268^k, so 64 rows put the cut's influence at ~1e-37 of
#: the data — below the float64 rounding of the whole-record spline.
SPLINE_CONTEXT = 64


class SpilledRecording:
    """A long recording held on disk (:func:`gyrocore.data.spill.spill_columns`), with the
    attributes of :class:`~gyrocore.data.recording.Recording` the residual loop reads: ``t_s`` in
    memory, every other column a :class:`LazyColumn` read a window at a time.

    The loop's two changes of the gyro are applied on the fly, per window, in the order of the
    in-memory path: narrow-band lines removed (``held``: ``{name: [(axis, f_hz, a_cos, a_sin),
    …]}``, raw time frame), then the advance by a time offset τ (``tau_s``: gyro'(t) =
    gyro(t + τ), cubic spline; see :data:`SPLINE_CONTEXT`).
    """

    def __init__(
        self,
        store: ColumnSpill,
        *,
        held: dict | None = None,
        tau_s: float = 0.0,
        chunk_rows: int | None = None,
        q_integrated: Rows | None = None,
    ) -> None:
        self.store = store
        self.t_s = store.t_s
        self.n = int(store.n)
        self.meta = store.meta
        self.extra: dict = {}
        self.held = {k: list(v) for k, v in (held or {}).items()}
        self.tau_s = float(tau_s)
        self.chunk_rows = int(chunk_rows or SPILL_CHUNK_ROWS)
        names = store.names
        self.ref_rate_rad_s = LazyColumn(store, REF_RATE_COLS) if all(c in names for c in REF_RATE_COLS) else None
        self.accel_m_s2 = LazyColumn(store, ACCEL_COLS) if all(c in names for c in ACCEL_COLS) else None
        self.temp_c = LazyColumn(store, [TEMP_COL], squeeze=True) if TEMP_COL in names else None
        from gyrocore.data.recording import REF_QUAT_COLS

        self.ref_quat_wxyz = LazyColumn(store, REF_QUAT_COLS) if all(c in names for c in REF_QUAT_COLS) else None
        self.gyro_rad_s = Rows(self._gyro_rows, self.n, 3)
        self._q_integrated = q_integrated
        self._finite: dict = {}

    # Recording's own properties (they read only t_s, n and meta, which this class holds too)
    duration_s = Recording.duration_s
    rate_hz = Recording.rate_hz

    def with_ops(self, *, held: dict | None = None, tau_s: float | None = None) -> "SpilledRecording":
        """The same file with other lines removed and/or another time offset."""
        return SpilledRecording(
            self.store,
            held=self.held if held is None else held,
            tau_s=self.tau_s if tau_s is None else tau_s,
            chunk_rows=self.chunk_rows,
            q_integrated=self._q_integrated,
        )

    def chunks(self):
        """(lo, hi) of consecutive windows of ``chunk_rows`` rows."""
        for lo in range(0, self.n, self.chunk_rows):
            yield lo, min(lo + self.chunk_rows, self.n)

    def all_finite(self, name: str) -> bool:
        """Whether every row of a column group (``ref_rate``, ``ref_quat``) is finite."""
        if name not in self._finite:
            col = {"ref_rate": self.ref_rate_rad_s, "ref_quat": self.ref_quat_wxyz}[name]
            ok = col is not None
            if ok:
                for lo, hi in self.chunks():
                    if not np.all(np.isfinite(col.rows(lo, hi))):
                        ok = False
                        break
            self._finite[name] = ok
        return self._finite[name]

    def _base_rows(self, lo: int, hi: int) -> np.ndarray:
        g = self.store.block(GYRO_COLS, lo, hi)
        if self.held:
            g = g - held_correction(self.t_s[lo:hi], self.held)
        return g

    def _gyro_rows(self, lo: int, hi: int) -> np.ndarray:
        if self.tau_s == 0.0:
            return self._base_rows(lo, hi)
        from scipy.interpolate import CubicSpline

        t = self.t_s
        fs = self.rate_hz
        m = SPLINE_CONTEXT + int(np.ceil(abs(self.tau_s) * fs)) + 2
        a, b = max(0, lo - m), min(self.n, hi + m)
        tq = np.clip(t[lo:hi] + self.tau_s, t[0], t[-1])
        return CubicSpline(t[a:b], self._base_rows(a, b), axis=0)(tq)

    def reference_quaternions(self) -> Rows | None:
        """The reference attitude S→W per sample: ``ref_q*`` when finite everywhere, else the
        reference rate integrated window by window (the attitude carried across windows;
        :func:`gyrocore.attitude.integrate_gyro_windows`, backward hold), kept in a work column of
        the spill (:meth:`~gyrocore.data.spill.ColumnSpill.scratch`). None without either."""
        if self.ref_quat_wxyz is not None and self.all_finite("ref_quat"):
            return self.ref_quat_wxyz
        if self.ref_rate_rad_s is None or not self.all_finite("ref_rate"):
            return None
        if self._q_integrated is None:
            from gyrocore.attitude import integrate_gyro_windows

            q_col = self.store.scratch("ref_int_q", 4)  # w, x, y, z: files beside the spill
            for lo, hi, q in integrate_gyro_windows(self.t_s, self.ref_rate_rad_s.rows, self.chunks()):
                q_col.write(lo, hi, q)
            self._q_integrated = Rows(q_col.rows, self.n, 4)
        return self._q_integrated


def release_memory() -> None:
    """Return freed memory to the system after a spill: Arrow's pool (``release_unused``) and
    the C heap (glibc ``malloc_trim``; nothing elsewhere) — the reader's blocks otherwise stay
    in the process's resident set (~20 MiB after a CSV of 10⁶ rows)."""
    import ctypes

    release_arrow_memory()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        pass


#: glibc ``mallopt`` parameter number of ``M_MMAP_THRESHOLD`` (malloc.h).
_M_MMAP_THRESHOLD = -3


def bounded_heap(threshold_bytes: int = 1024 * 1024) -> bool:
    """Serve allocations above ``threshold_bytes`` by mmap, returned to the system when freed
    (glibc ``mallopt(M_MMAP_THRESHOLD)``; nothing elsewhere). glibc's default threshold starts
    at 128 KiB and rises to the largest block freed (up to 32 MiB): after the spill frees its
    whole columns, the windows' arrays come from the heap and their freed space stays resident
    (one hour at 1 kHz: 35 MiB kept after the regressor passes, 212 → 177 MiB after a
    ``malloc_trim``; with a fixed threshold 180 MiB throughout). 256 KiB cost 4× the system
    time of the default (every window array mmapped and page-faulted anew: 4.2 vs 1.0 s on 10
    min of 1 kHz), 1 MiB 2.7 s for the same peak (227 vs 222 MiB): the default here. Returns
    whether it was set."""
    import ctypes

    try:
        return bool(ctypes.CDLL("libc.so.6").mallopt(_M_MMAP_THRESHOLD, int(threshold_bytes)))
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        return False


def held_correction(t: np.ndarray, held: dict) -> np.ndarray | float:
    """Σ of the narrow-band lines removed from the gyro, rad/s, (n, 3) on times t (s): per
    name the sum of its lines a·cos(2πft) + b·sin(2πft) on its axis (the loop's ``held``)."""
    total = 0
    for lines in held.values():
        acc = 0.0
        for i, f, a, b in lines:
            c = np.zeros((t.size, 3))
            c[:, i] = a * np.cos(2 * np.pi * f * t) + b * np.sin(2 * np.pi * f * t)
            acc = acc + c
        total = total + acc
    return total
