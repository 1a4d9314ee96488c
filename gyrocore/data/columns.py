"""Named columns of a recording read a block of rows at a time: the one chunk source.

Every bounded-memory analysis on the calibration side (the least-squares fits of
:mod:`gyrocore.calib.lsq`, the static-bias gate of :mod:`gyrocore.calib.bias`) reads its data
through this small protocol instead of asking whether the recording is in memory or on disk
(and so does the one still gate of :mod:`gyrocore.data.still`):

``n``, ``t_s`` (the time column, in memory), ``meta``, ``names`` (SI column names of the file
format: ``gyro_x_rad_s``, ``ref_x_rad_s``, ``temp_c``, …), ``rows(name, a, b)``,
``block(names, a, b)`` (rows a:b of several columns, (b − a, k)), ``column(name)`` (a fresh
(N,) array), ``scratch(name, ncol)`` (a writable (N, ncol) work column of the same kind: in
memory, or a file beside the spill) and ``block_bytes`` (the size of the blocks worth reading
at a time: views of memory cost nothing, reads from disk are fresh arrays).

:func:`columns_of` gives the source of a :class:`~gyrocore.data.recording.Recording` in memory
(:class:`RecordingColumns`: views, no copy), of a bare (N, 3) gyro array (:class:`GyroColumns`,
its columns the gyro's: views, no copy) or passes a
:class:`~gyrocore.data.spill.ColumnSpill` (the columns of a long file on disk) through.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from gyrocore.errors import GyroInputError

from .recording import ACCEL_COLS, GYRO_COLS, REF_QUAT_COLS, REF_RATE_COLS, TEMP_COL, TIME_COL, Recording

__all__ = [
    "GyroColumns",
    "RecordingColumns",
    "ScratchArray",
    "ScratchFiles",
    "columns_of",
    "MEMORY_BLOCK_BYTES",
    "DISK_BLOCK_BYTES",
]

#: Block of rows worth handling at a time in memory (views of the recording: no copy).
MEMORY_BLOCK_BYTES = 32 * 2**20
#: Block of rows read at a time from disk (each a fresh array: small).
DISK_BLOCK_BYTES = 4 * 2**20


class ScratchArray:
    """A writable (N, ncol) work column in memory: ``write(a, b, x)`` rows a:b, ``rows(a, b)``
    rows a:b back, ``axis(i)`` a fresh (N,) copy of column i."""

    def __init__(self, n: int, ncol: int) -> None:
        self.n = int(n)
        self.data = np.empty((self.n, int(ncol)))

    def write(self, a: int, b: int, x: np.ndarray) -> None:
        self.data[a:b] = x

    def rows(self, a: int, b: int) -> np.ndarray:
        """Rows a:b of every column, (b − a, ncol) (a view)."""
        return self.data[max(0, int(a)) : min(self.n, int(b))]

    def axis(self, i: int) -> np.ndarray:
        return self.data[:, i].copy()

    def close(self) -> None:
        """Free the column."""
        self.data = None


class ScratchFiles:
    """A writable (N, ncol) work column on disk, one file per column in ``folder``:
    ``write(a, b, x)`` rows a:b, ``rows(a, b)`` rows a:b read back, ``axis(i)`` column i read
    back (N,)."""

    def __init__(self, folder: str | os.PathLike, name: str, n: int, ncol: int) -> None:
        self.n = int(n)
        self.paths = [Path(folder) / f"{name}_{i}.f64" for i in range(int(ncol))]
        for p in self.paths:
            with open(p, "wb") as fh:
                fh.truncate(8 * self.n)

    def write(self, a: int, b: int, x: np.ndarray) -> None:
        for i, p in enumerate(self.paths):
            with open(p, "r+b") as fh:
                fh.seek(8 * int(a))
                fh.write(np.ascontiguousarray(x[:, i], dtype=np.float64).tobytes())

    def rows(self, a: int, b: int) -> np.ndarray:
        """Rows a:b of every column read back, (b − a, ncol) (a fresh array)."""
        a, b = max(0, int(a)), min(self.n, int(b))
        out = np.empty((max(b - a, 0), len(self.paths)))
        for j, p in enumerate(self.paths):
            out[:, j] = np.fromfile(p, dtype=np.float64, count=max(b - a, 0), offset=8 * a)
        return out

    def axis(self, i: int) -> np.ndarray:
        return np.fromfile(self.paths[i], dtype=np.float64, count=self.n)

    def close(self) -> None:
        """Delete the files."""
        for p in self.paths:
            p.unlink(missing_ok=True)


class _MemoryColumns:
    """The chunk-source protocol over arrays in memory, a group of named columns per 2-D array
    (rows and a whole group's block are views; :meth:`column` and a mixed :meth:`block` copy)."""

    block_bytes = MEMORY_BLOCK_BYTES

    def __init__(self, n: int, t_s, meta: dict, cols: dict[str, np.ndarray], groups: dict[tuple, np.ndarray]) -> None:
        self.n = int(n)
        self.t_s = t_s
        self.meta = meta
        self._cols = cols
        self._groups = groups
        self.names = list(cols)

    def rows(self, name: str, a: int, b: int) -> np.ndarray:
        """Rows a:b of one column, (b − a,) (a view)."""
        return self._cols[name][max(0, int(a)) : int(b)]

    def block(self, names, a: int, b: int) -> np.ndarray:
        """Rows a:b of several columns side by side, (b − a, len(names)) (a view when the names
        are a whole column group, e.g. the gyro)."""
        a, b = max(0, int(a)), min(self.n, int(b))
        arr = self._groups.get(tuple(names))
        if arr is not None:
            return arr[a:b]
        return np.stack([self._cols[nm][a:b] for nm in names], axis=1)

    def column(self, name: str) -> np.ndarray:
        """One column, (N,), a fresh array."""
        return np.array(self._cols[name], dtype=float)

    def scratch(self, name: str, ncol: int) -> ScratchArray:
        """A writable (N, ncol) work column in memory."""
        return ScratchArray(self.n, ncol)


class RecordingColumns(_MemoryColumns):
    """The chunk-source protocol over a :class:`~gyrocore.data.recording.Recording` in memory
    (rows are views of its arrays; :meth:`column` and :meth:`block` of several columns copy)."""

    def __init__(self, rec: Recording) -> None:
        self.recording = rec
        cols: dict[str, np.ndarray] = {TIME_COL: rec.t_s}
        groups = (
            (GYRO_COLS, rec.gyro_rad_s),
            (ACCEL_COLS, rec.accel_m_s2),
            (REF_RATE_COLS, rec.ref_rate_rad_s),
            (REF_QUAT_COLS, rec.ref_quat_wxyz),
        )
        for names, arr in groups:
            if arr is not None:
                cols.update({nm: arr[:, j] for j, nm in enumerate(names)})
        if rec.temp_c is not None:
            cols[TEMP_COL] = rec.temp_c
        super().__init__(rec.n, rec.t_s, rec.meta, cols, {names: arr for names, arr in groups if arr is not None})


class GyroColumns(_MemoryColumns):
    """The chunk-source protocol over a bare gyro array (N, 3), rad/s, sensor frame S, in memory:
    its columns are :data:`~gyrocore.data.recording.GYRO_COLS` (views of the array, converted to
    float64 once: no copy when it is float64 already). No time column (``t_s`` None)."""

    def __init__(self, gyro_rad_s) -> None:
        x = np.asarray(gyro_rad_s, float)
        if x.ndim != 2 or x.shape[1] != len(GYRO_COLS):
            raise GyroInputError(f"gyro must be (N, 3), got shape {x.shape}")
        cols = {nm: x[:, j] for j, nm in enumerate(GYRO_COLS)}
        super().__init__(x.shape[0], None, {}, cols, {GYRO_COLS: x})


def columns_of(data):
    """The chunk source of ``data``: a :class:`Recording` → :class:`RecordingColumns`; a bare
    (N, 3) gyro array → :class:`GyroColumns`; a source already (a
    :class:`~gyrocore.data.spill.ColumnSpill`, any object with ``block`` and ``column``) → itself."""
    if isinstance(data, Recording):
        return RecordingColumns(data)
    if hasattr(data, "block") and hasattr(data, "column"):
        return data
    return GyroColumns(data)
