"""Long recordings held on disk, one column at a time (bounded memory).

:func:`spill_columns` streams a data file once into per-column binary files (with every check,
repair and warning of a whole read); :class:`ColumnSpill` reads them back a block of rows or a
column at a time (the fits of :mod:`gyrocore.calib.stream`, the per-axis noise analysis of
:mod:`gyrocore.noise.spilled`).
"""

from __future__ import annotations

import os
from functools import partial
from pathlib import Path
from typing import Iterable

import numpy as np

from gyrocore.errors import GyroInputError, warn_repair

from .columns import DISK_BLOCK_BYTES, ScratchFiles
from .checks import (
    DEG,
    G0_M_S2,
    _check_time_span,
    _refuse_deg_s_peak,
    _timing_checks,
    _warn_still_noise,
    detect_saturation,
    still_noise_rad_s,
)
from .csvtext import _header_info, _Moments, _sniff_file
from .recording import (
    ACCEL_COLS,
    AXES,
    GYRO_COLS,
    REF_QUAT_COLS,
    REF_RATE_COLS,
    TEMP_COL,
    TIME_COL,
    Recording,
    _Layout,
    _open_parquet,
    is_parquet,
    iter_chunks,
)

__all__ = ["ColumnSpill", "spill_columns", "release_arrow_memory"]


class ColumnSpill:
    """The checked columns of a long recording kept on disk, loaded one at a time.

    Made by :func:`spill_columns`. ``t_s`` is in memory (it is needed for the rate and the
    timestamp checks); every other column (SI units, names of :func:`_columns`: e.g.
    ``gyro_x_rad_s``) is loaded by :meth:`column`. An analysis that needs the whole series of
    one axis at a time (overlapping ADEV) then holds two columns, not the whole table. It is the
    on-disk chunk source of :mod:`gyrocore.data.columns` (``rows``, ``block``, ``column``,
    ``scratch``, ``block_bytes``).
    """

    block_bytes = DISK_BLOCK_BYTES

    def __init__(self, folder: Path, names: list[str], n: int, t_s: np.ndarray, meta: dict[str, str]) -> None:
        self.folder = folder
        self.names = names
        self.n = n
        self.t_s = t_s
        self.meta = meta

    def column(self, name: str) -> np.ndarray:
        """One column, shape (N,), float64 (a fresh array)."""
        if name not in self.names:
            raise KeyError(name)
        return np.fromfile(self.folder / f"{name}.f64", dtype=np.float64, count=self.n)

    def rows(self, name: str, a: int, b: int) -> np.ndarray:
        """Rows a:b of one column, shape (b − a,), float64 (a fresh array)."""
        if name not in self.names:
            raise KeyError(name)
        a, b = max(0, int(a)), min(self.n, int(b))
        return np.fromfile(self.folder / f"{name}.f64", dtype=np.float64, count=max(b - a, 0), offset=8 * a)

    def block(self, names, a: int, b: int) -> np.ndarray:
        """Rows a:b of several columns side by side, shape (b − a, len(names))."""
        a, b = max(0, int(a)), min(self.n, int(b))
        out = np.empty((max(b - a, 0), len(names)))
        for j, nm in enumerate(names):
            out[:, j] = self.rows(nm, a, b)
        return out

    def scratch(self, name: str, ncol: int) -> ScratchFiles:
        """A writable (N, ncol) work column on disk beside the spill (one file per column)."""
        return ScratchFiles(self.folder, name, self.n, ncol)

    def recording(self, gyro_axis: int, *, accel_axis: int | None = None) -> Recording:
        """A :class:`Recording` holding only gyro axis ``gyro_axis`` (the other two axes are
        views of the same column: use only that axis), optionally one accel axis likewise."""
        g = self.column(GYRO_COLS[gyro_axis])
        a = None if accel_axis is None else self.column(ACCEL_COLS[accel_axis])
        return Recording(
            t_s=self.t_s,
            gyro_rad_s=np.broadcast_to(g[:, None], (self.n, 3)),
            accel_m_s2=None if a is None else np.broadcast_to(a[:, None], (self.n, 3)),
            meta=self.meta,
        )


def release_arrow_memory() -> None:
    """Return the memory Arrow's allocator keeps after a read to the system (its pools hold
    freed blocks for reuse: ~20 MiB after streaming a long CSV)."""
    import sys

    pa = sys.modules.get("pyarrow")
    if pa is not None:
        pa.default_memory_pool().release_unused()


def _checks(store: ColumnSpill, path: str, layout, *, accel: bool, has_accel: bool, gyro_peak: float, mom) -> None:
    """The checks of a whole read (``recording._finish``), in its order, one column at a time:
    deg/s labelled rad/s (peak, and the noise of a still record), timing, saturation."""
    t = store.t_s
    gyro_col = layout.gyro_unit_col
    with np.errstate(all="ignore"):
        if gyro_col.endswith("_rad_s"):
            _refuse_deg_s_peak(gyro_peak, path, gyro_col)
            sd = mom.std() if has_accel else None  # chunks are SI already
            if sd is not None and bool(np.all(sd < 0.05 * G0_M_S2)):
                med, noise = [], []
                for j in range(3):
                    # one column in memory at a time: the noise from a read overwritten in place,
                    # then the median from the column read again (the same values)
                    noise.append(still_noise_rad_s(partial(store.column, GYRO_COLS[j])))
                    c = store.column(GYRO_COLS[j])
                    med.append(float(np.median(c, overwrite_input=True)))  # c is not used again
                    del c
                _warn_still_noise(path, med, noise)
        _timing_checks(t, path, False, layout.header[layout.t])
        found, n_sat = [], 0
        sat_any = None
        for j, nm in enumerate(GYRO_COLS + (ACCEL_COLS if has_accel and accel else ())):
            c = store.column(nm)
            clip = 0.9 * 125.0 * DEG if j < 3 else 0.9 * 2.0 * G0_M_S2
            m, f = detect_saturation(c[:, None], min_clip=clip)
            if f:
                sat_any = m if sat_any is None else (sat_any | m)
                found += [(j, v, cnt) for _, v, cnt in f]
            del c
        if found:
            n_sat = int(sat_any.sum())
            names6 = [f"gyro_{a}" for a in AXES] + [f"accel_{a}" for a in AXES]
            desc = ", ".join(f"{names6[j]} {cnt} at {v:.6g}" for j, v, cnt in found)
            warn_repair(f"{path}: {n_sat} saturated samples (clipped plateaus: {desc}); flagged in column 'saturated'")


def spill_columns(
    path: str | os.PathLike,
    folder: str | os.PathLike,
    *,
    accel: bool = False,
    rows: int = 32_768,
    repair: bool = True,
    groups: Iterable[str] = (),
) -> ColumnSpill:
    """Stream a data file (CSV or Parquet) into per-column files in ``folder``, with the
    same repairs, checks, warnings and errors as :func:`read_recording` — run one column at
    a time, so memory stays O(2 columns) instead of O(all columns).

    Columns kept: ``t_s``, the gyro (SI) and, with ``accel``, the accel; ``groups`` adds
    ``temp`` (``temp_c``), ``ref_rate`` (``ref_*_rad_s``) and ``ref_quat`` (``ref_q*``)
    when the file has them. The saturation check warns as usual but the ``saturated`` flag
    column is not kept. No ``retime``.
    """
    path = str(path)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    names = [TIME_COL, *GYRO_COLS]
    if is_parquet(path):
        _pf, header, _m = _open_parquet(path)
    else:
        _sniff_file(path)
        _m, header, _ = _header_info(path)
    groups = tuple(groups)
    bad = sorted(set(groups) - {"temp", "ref_rate", "ref_quat"})
    if bad:
        raise ValueError(f"spill_columns: unknown column group(s) {bad}")
    layout = _Layout(header, path, ("accel", *groups))
    has_accel = layout.accel is not None
    if has_accel and accel:
        names += list(ACCEL_COLS)
    if layout.temp is not None:
        names.append(TEMP_COL)
    if layout.rref is not None:
        names += list(REF_RATE_COLS)
    if layout.qref is not None:
        names += list(REF_QUAT_COLS)
    read_groups = (("accel",) if has_accel else ()) + groups
    files = {nm: open(folder / f"{nm}.f64", "wb") for nm in names}
    n = 0
    meta: dict[str, str] = {}
    g_max, g_min = -np.inf, np.inf
    mom = _Moments([0, 1, 2])
    try:
        for ch in iter_chunks(path, rows=rows, repair=repair, columns=read_groups):
            meta = dict(ch.meta)
            cols = {TIME_COL: ch.t_s, **{GYRO_COLS[j]: ch.gyro_rad_s[:, j] for j in range(3)}}
            if layout.temp is not None:
                cols[TEMP_COL] = ch.temp_c
            if layout.rref is not None:
                cols.update({REF_RATE_COLS[j]: ch.ref_rate_rad_s[:, j] for j in range(3)})
            if layout.qref is not None:
                cols.update({REF_QUAT_COLS[j]: ch.ref_quat_wxyz[:, j] for j in range(4)})
            if has_accel:
                mom.update({j: ch.accel_m_s2[:, j].copy() for j in range(3)})
                if accel:
                    cols.update({ACCEL_COLS[j]: ch.accel_m_s2[:, j] for j in range(3)})
            for nm in names:
                np.ascontiguousarray(cols[nm], dtype=np.float64).tofile(files[nm])
            g_max = max(g_max, float(ch.gyro_rad_s.max()))
            g_min = min(g_min, float(ch.gyro_rad_s.min()))
            n += ch.n
    finally:
        for fh in files.values():
            fh.close()
    release_arrow_memory()
    if n < 2:
        raise GyroInputError(f"{path}: fewer than 2 valid samples")
    t = np.fromfile(folder / f"{TIME_COL}.f64", dtype=np.float64, count=n)
    store = ColumnSpill(folder, names, n, t, meta)
    _check_time_span(t, path)
    _checks(store, path, layout, accel=accel, has_accel=has_accel, gyro_peak=max(g_max, -g_min), mom=mom)
    return store
