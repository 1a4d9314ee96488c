"""The data file of DESIGN.md: one CSV row per sample, unit-suffixed columns, ``#`` metadata
(or the same columns in a Parquet file, the metadata in its schema; chosen by the file name).

A :class:`Recording` is the in-memory form, shared by measured and simulated data. Arrays are
SI: rad/s, m/s², °C, seconds; frames: gyro, accel and reference rate in the sensor frame S,
reference attitude as a unit quaternion ``w, x, y, z`` rotating S to W.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable, Iterator, Mapping

import numpy as np

from gyrocore.errors import GyroInputError, warn_repair

from .checks import (
    DEG,
    G0_M_S2,
    _check_time_span,
    _timing_checks,
    _unit_checks,
    _valid_rows,
    coarse_clock_retime,
    detect_saturation,
)
from .csvtext import (
    TIME_ALTS,
    _MAX_BLOCK_BYTES,
    _Filler,
    _Moments,
    _NotClean,
    _arrow_stream,
    _check_header,
    _check_path,
    _count_lines,
    _csv_blocks,
    _data_offset,
    _exact_blocks,
    _header_info,
    _is_float64_array,
    _rechunk,
    _sniff_file,
    _time_col,
)

__all__ = [
    "Recording",
    "read_csv",
    "write_csv",
    "atomic_open",
    "atomic_write_text",
    "atomic_write_bytes",
    "file_sha256",
    "iter_csv_chunks",
    "write_csv_chunks",
    "read_parquet",
    "write_parquet",
    "iter_parquet_chunks",
    "write_parquet_chunks",
    "read_recording",
    "write_recording",
    "iter_chunks",
    "write_chunks",
    "is_parquet",
    "COLUMN_GROUPS",
    "concat_recordings",
    "file_layout",
    "AXES",
]

AXES = ("x", "y", "z")
GYRO_COLS = tuple(f"gyro_{a}_rad_s" for a in AXES)
ACCEL_COLS = tuple(f"accel_{a}_m_s2" for a in AXES)
REF_RATE_COLS = tuple(f"ref_{a}_rad_s" for a in AXES)
REF_QUAT_COLS = ("ref_qw", "ref_qx", "ref_qy", "ref_qz")
TEMP_COL = "temp_c"
TIME_COL = "t_s"
# Accepted alternative unit suffixes, converted on read: (suffix, factor to SI suffix).
_ALT_UNITS = {"_rad_s": [("_deg_s", DEG)], "_m_s2": [("_g", G0_M_S2)]}


@dataclass(frozen=True, eq=False)
class Recording:
    """One recording, measured or simulated.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Sample times in seconds, strictly increasing.
    gyro_rad_s : ndarray, shape (N, 3)
        Measured angular rate of S w.r.t. inertial space, in S, rad/s.
    accel_m_s2 : ndarray, shape (N, 3) or None
        Measured specific force in S, m/s².
    temp_c : ndarray, shape (N,) or None
        Sensor (die) temperature, °C.
    ref_rate_rad_s : ndarray, shape (N, 3) or None
        Reference (true or commanded) angular rate in S, rad/s.
    ref_quat_wxyz : ndarray, shape (N, 4) or None
        Reference attitude, unit quaternion (w, x, y, z) rotating S to W. NaN rows allowed
        (e.g. optical tracking lost).
    meta : dict
        ``# key: value`` metadata lines (strings).
    extra : dict
        Any other numeric columns, kept but ignored by the estimators.
    """

    t_s: np.ndarray
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray | None = None
    temp_c: np.ndarray | None = None
    ref_rate_rad_s: np.ndarray | None = None
    ref_quat_wxyz: np.ndarray | None = None
    meta: Mapping[str, str] = field(default_factory=dict)
    extra: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, dtype=float)
        n = t.shape[0]
        object.__setattr__(self, "t_s", t)
        for name, width in (
            ("gyro_rad_s", 3),
            ("accel_m_s2", 3),
            ("ref_rate_rad_s", 3),
            ("ref_quat_wxyz", 4),
            ("temp_c", None),
        ):
            v = getattr(self, name)
            if v is None:
                continue
            v = np.asarray(v, dtype=float)
            want = (n,) if width is None else (n, width)
            if v.shape != want:
                raise GyroInputError(f"{name} has shape {v.shape}, expected {want}")
            object.__setattr__(self, name, v)
        object.__setattr__(self, "meta", dict(self.meta))
        object.__setattr__(self, "extra", {k: np.asarray(v, float) for k, v in self.extra.items()})

    # ------------------------------------------------------------------ helpers
    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.t_s.shape[0])

    @property
    def duration_s(self) -> float:
        """Time span from first to last sample, s."""
        return float(self.t_s[-1] - self.t_s[0]) if self.n > 1 else 0.0

    @property
    def rate_hz(self) -> float:
        """Mean sample rate, Hz ((N-1)/duration; robust to jittery host timestamps)."""
        if self.n < 2 or self.duration_s <= 0:
            meta_rate = self.meta.get("rate_hz")
            return float(meta_rate) if meta_rate else float("nan")
        return (self.n - 1) / self.duration_s

    @property
    def dt_s(self) -> np.ndarray:
        """Per-sample interval, shape (N,), first element = median interval."""
        d = np.diff(self.t_s)
        med = float(np.median(d)) if d.size else 0.0
        return np.concatenate([[med], d])

    def slice(self, start: int, stop: int) -> "Recording":
        """Rows ``start:stop`` as a new recording."""
        s = np.s_[start:stop]
        return replace(
            self,
            t_s=self.t_s[s],
            gyro_rad_s=self.gyro_rad_s[s],
            accel_m_s2=None if self.accel_m_s2 is None else self.accel_m_s2[s],
            temp_c=None if self.temp_c is None else self.temp_c[s],
            ref_rate_rad_s=None if self.ref_rate_rad_s is None else self.ref_rate_rad_s[s],
            ref_quat_wxyz=None if self.ref_quat_wxyz is None else self.ref_quat_wxyz[s],
            extra={k: v[s] for k, v in self.extra.items()},
        )

    def with_gyro(self, gyro_rad_s: np.ndarray, **meta: str) -> "Recording":
        """Same recording with the gyro column replaced (e.g. after correction)."""
        m = dict(self.meta)
        m.update({k: str(v) for k, v in meta.items()})
        return replace(self, gyro_rad_s=np.asarray(gyro_rad_s, float), meta=m)


# ---------------------------------------------------------------------- writing
@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb", *, overwrite: bool = True, **open_kw):
    """Open a temporary file beside ``path``; on success fsync it and rename it onto ``path``.

    An exception (or interrupt) inside the ``with`` block removes the temporary file, so the
    target is either the old file or the complete new one, never partial. With
    ``overwrite=False`` an existing target is an error.
    """
    path = Path(path)
    if not overwrite and path.exists():
        raise GyroInputError(f"{path} exists; pass --force to overwrite it")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode, **open_kw) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, overwrite: bool = True) -> None:
    """Write ``data`` to ``path`` atomically (temp file in the same folder + rename).

    An interrupted write leaves either the old file or nothing, never a partial file.
    With ``overwrite=False`` an existing file is an error.
    """
    with atomic_open(path, "wb", overwrite=overwrite) as fh:
        fh.write(data)


def atomic_write_text(path: str | os.PathLike, text: str, *, overwrite: bool = True) -> None:
    """Text version of :func:`atomic_write_bytes` (UTF-8)."""
    atomic_write_bytes(path, text.encode("utf-8"), overwrite=overwrite)


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 hex digest of a file, read in 1 MiB chunks.

    A folder (a recording kept as several files: sunsided's ``mpu6050_*.mat``, gnss-ins-sim's
    ``gyro-0.csv``/``time.csv``): the digest of its files in sorted order of their relative
    paths, each entering as ``path NUL sha256(bytes) NUL`` — it changes when any file, or a
    name, does.
    """
    h = hashlib.sha256()
    if os.path.isdir(path):
        root = Path(path)
        for f in sorted(q for q in root.rglob("*") if q.is_file()):
            h.update(f.relative_to(root).as_posix().encode() + b"\0" + file_sha256(f).encode() + b"\0")
        return h.hexdigest()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _columns(rec: Recording) -> tuple[list[str], list[np.ndarray]]:
    names: list[str] = [TIME_COL, *GYRO_COLS]
    cols: list[np.ndarray] = [rec.t_s[:, None], rec.gyro_rad_s]
    if rec.accel_m_s2 is not None:
        names += ACCEL_COLS
        cols.append(rec.accel_m_s2)
    if rec.temp_c is not None:
        names.append(TEMP_COL)
        cols.append(rec.temp_c[:, None])
    if rec.ref_rate_rad_s is not None:
        names += REF_RATE_COLS
        cols.append(rec.ref_rate_rad_s)
    if rec.ref_quat_wxyz is not None:
        names += REF_QUAT_COLS
        cols.append(rec.ref_quat_wxyz)
    for k, v in rec.extra.items():
        names.append(k)
        cols.append(v[:, None])
    return names, cols


#: Rows formatted at a time when a long recording is written (bounded text buffer).
WRITE_CHUNK_ROWS = 65_536


def write_csv(rec: Recording, path: str | os.PathLike, *, overwrite: bool = True) -> None:
    """Write ``rec`` as the DESIGN.md data file, atomically.

    Floats are written with 17 significant digits (``%.17g``) so that a write/read round
    trip is bit-exact.
    """
    if rec.n > WRITE_CHUNK_ROWS:  # streamed, same bytes: no whole-file text in memory
        write_csv_chunks(
            (rec.slice(i, i + WRITE_CHUNK_ROWS) for i in range(0, rec.n, WRITE_CHUNK_ROWS)), path, overwrite=overwrite
        )
        return
    names, cols = _columns(rec)
    data = np.hstack(cols) if cols else np.empty((0, 0))
    buf = io.StringIO()
    for k, v in rec.meta.items():
        buf.write(f"# {k}: {str(v).replace(chr(10), ' ')}\n")
    buf.write(",".join(names) + "\n")
    np.savetxt(buf, data, delimiter=",", fmt="%.17g")
    atomic_write_text(path, buf.getvalue(), overwrite=overwrite)


# ---------------------------------------------------------------------- reading
#: Fraction of the available memory a whole-file read may use before it is refused.
MEMORY_FRACTION = 0.5
#: Bytes of memory per parsed value while reading: float64 table + column copies + masks.
#: Measured: a 1 M-row × 8-column file (164 MB) raised the peak RSS by ≈ 260 MB ≈ 32 B/value.
_BYTES_PER_VALUE = 32


def _available_memory_bytes() -> int:
    """Available physical memory (psutil); tests monkeypatch this."""
    import psutil

    return int(psutil.virtual_memory().available)


def _check_memory(path: str, n_header_lines: int, ncols: int, *, est_rows: int | None = None) -> None:
    """Refuse a whole-file read that would not fit comfortably in memory (``ncols``: the
    columns actually read)."""
    size = os.path.getsize(path)
    if est_rows is not None:
        _refuse_if_large(path, size, est_rows, ncols)
        return
    with open(path, "rb") as fh:
        sample = fh.read(1 << 16)
    lines = sample.count(b"\n")
    avg_line = len(sample) / max(lines, 1)
    _refuse_if_large(path, size, int(size / max(avg_line, 1.0)), ncols)


def _refuse_if_large(path: str, size: int, est_rows: int, ncols: int) -> None:
    need = est_rows * ncols * _BYTES_PER_VALUE
    avail = _available_memory_bytes()
    if need > MEMORY_FRACTION * avail:
        raise GyroInputError(
            f"{path}: {size / 2**20:.0f} MiB (~{est_rows:,} rows) needs ~{need / 2**20:.0f} MiB to load, more than "
            f"{MEMORY_FRACTION:.0%} of the {avail / 2**20:.0f} MiB available; read it in chunks "
            f"(gyrocore.data.recording.iter_csv_chunks, or gyroharness convert which streams CSV files)"
        )


def file_layout(path: str | os.PathLike) -> tuple[tuple[str, ...], int, int]:
    """Column groups present in a data file (CSV or Parquet), its estimated number of rows and
    its number of columns, from the header and the file size only (no data read).

    Returns
    -------
    groups : tuple of str
        Those of :data:`COLUMN_GROUPS` the header holds (``extra``: any other column).
    est_rows : int
        Parquet: the row count of its metadata; CSV: the file size over the mean length of
        the first 64 KiB of lines.
    n_columns : int
        Columns of the header.
    """
    path = str(path)
    if is_parquet(path):
        pf, header, _m = _open_parquet(path)
        est = int(pf.metadata.num_rows)
    else:
        _sniff_file(path)
        _m, header, _n = _header_info(path)
        with open(path, "rb") as fh:
            sample = fh.read(1 << 16)
        est = int(os.path.getsize(path) / max(len(sample) / max(sample.count(b"\n"), 1), 1.0))
    lay = _Layout(header, path)
    present = {
        "accel": lay.accel is not None,
        "temp": lay.temp is not None,
        "ref_rate": lay.rref is not None,
        "ref_quat": lay.qref is not None,
        "extra": bool(lay.extra),
    }
    return tuple(g for g in COLUMN_GROUPS if present[g]), est, len(header)


#: Column groups a reader can be asked for (``columns=``); ``t_s`` and the gyro are always read.
COLUMN_GROUPS = ("accel", "temp", "ref_rate", "ref_quat", "extra")


class _Layout:
    """Which header columns go where, with their SI factors; ``keep`` limits the groups read
    (None: all). Every group of the header is validated either way."""

    def __init__(self, header: list[str], path: str, keep: Iterable[str] | None = None) -> None:
        self.header = header
        self.check_accel: list[int] = []
        self.accel_factor = None
        self.t, self.t_factor = _time_col(header, path)
        self.gyro = self._block(GYRO_COLS, path, required=True)
        self.accel = self._block(ACCEL_COLS, path)
        self.rref = self._block(REF_RATE_COLS, path)
        self.qref = self._block(REF_QUAT_COLS, path)
        self.temp = header.index(TEMP_COL) if TEMP_COL in header else None
        used = {
            self.t,
            *(self.gyro[0] if self.gyro else ()),
            *(self.accel[0] if self.accel else ()),
            *(self.rref[0] if self.rref else ()),
            *(self.qref[0] if self.qref else ()),
        }
        if self.temp is not None:
            used.add(self.temp)
        self.extra = [(h, i) for i, h in enumerate(header) if i not in used]
        self.gyro_unit_col = header[self.gyro[0][0]]
        if keep is not None:
            keep = set(keep)
            bad = sorted(keep - set(COLUMN_GROUPS))
            if bad:
                raise ValueError(f"unknown column group(s) {bad}; choose from {COLUMN_GROUPS}")
            if "accel" not in keep:
                # still read for the unit check (accel steady?), as running moments only
                self.check_accel = list(self.accel[0]) if self.accel is not None else []
                self.accel_factor = None if self.accel is None else self.accel[1]
                self.accel = None
            if "temp" not in keep:
                self.temp = None
            if "ref_rate" not in keep:
                self.rref = None
            if "ref_quat" not in keep:
                self.qref = None
            if "extra" not in keep:
                self.extra = []
        want = {self.t, *self.gyro[0]}
        for blk in (self.accel, self.rref, self.qref):
            if blk is not None:
                want.update(blk[0])
        if self.temp is not None:
            want.add(self.temp)
        want.update(i for _, i in self.extra)
        want.update(self.check_accel)
        #: header indices to read, in file order (with the check-only accel columns)
        self.want = sorted(want)

    def moments(self) -> "_Moments":
        return _Moments(self.check_accel)

    def accel_std(self, moments: "_Moments"):
        """Per-axis std (m/s²) of accel columns read for the check only, or None."""
        sd = moments.std()
        return None if sd is None else sd * self.accel_factor

    def _block(self, names, path, *, required=False):
        idx, fac = zip(*(_find(self.header, n) for n in names))
        if all(i is None for i in idx):
            if required:
                have = [h for h in self.header if h not in TIME_ALTS]
                raise GyroInputError(
                    f"{path}: missing required column(s) {', '.join(names)} (the other columns are "
                    f"{', '.join(repr(h[:30]) for h in have[:6])}{', ...' if len(have) > 6 else ''}; rad/s or deg/s "
                    f"columns named gyro_x_rad_s / gyro_x_deg_s are read)"
                )
            return None
        if any(i is None for i in idx):
            missing = [n for n, i in zip(names, idx) if i is None]
            raise GyroInputError(f"{path}: incomplete column group, missing {', '.join(missing)}")
        return list(idx), np.asarray(fac)

    def take(self, cols: dict[int, np.ndarray], block, *, pop: bool = False):
        """(N, k) SI array of a column group from ``{header index: column}`` (a new array)."""
        if block is None:
            return None
        get = cols.pop if pop else cols.__getitem__
        out = np.empty((cols[block[0][0]].shape[0], len(block[0])))
        for j, (i, f) in enumerate(zip(block[0], block[1])):
            c = get(i)  # popped one at a time: the single column is freed once copied
            if f == 1.0:
                out[:, j] = c
            else:
                np.multiply(c, f, out=out[:, j])
            del c
        return out


#: Short stems other tools write for a DESIGN.md stem (pyulog-style ``acc_x_m_s2``).
_ALT_STEMS = {"accel_": "acc_"}


def _find(header: list[str], si_name: str) -> tuple[int | None, float]:
    """Index of column ``si_name`` or of an accepted alternative unit (or short stem: ``acc_x_m_s2``),
    and its SI factor."""
    names = [si_name] + [alt + si_name[len(st) :] for st, alt in _ALT_STEMS.items() if si_name.startswith(st)]
    for name in names:
        if name in header:
            return header.index(name), 1.0
        for si_suffix, alts in _ALT_UNITS.items():
            if name.endswith(si_suffix):
                stem = name[: -len(si_suffix)]
                for suffix, factor in alts:
                    if stem + suffix in header:
                        return header.index(stem + suffix), factor
    return None, 1.0


def _finish(
    t, gyro, accel, temp, rref, qref, meta, extra, path, *, checks: bool, retime: bool, accel_std=None
) -> Recording:
    """Post-parse checks common to the whole-file and chunked readers."""
    _check_time_span(t, path)
    if checks:
        with np.errstate(all="ignore"):  # absurd finite values (1e300) must not print overflow warnings
            _unit_checks(t, gyro, accel, path, meta.pop("__gyro_col__", "gyro_x_rad_s"), accel_std=accel_std)
            if meta.get("stream") == "batch":  # ArduPilot batch sampler: windows with gaps by design
                meta.pop("__time_col__", None)
            else:
                t = _timing_checks(t, path, retime, meta.pop("__time_col__", TIME_COL))
        with np.errstate(all="ignore"):
            # smallest full scales on the market: gyro ±125 deg/s (BMI088, ICM-42688-P low
            # ranges), accel ±2 g; a plateau below 90 % of these cannot be clipping.
            # (gyro and accel separately: no (N, 6) copy of the columns)
            sat, found = detect_saturation(gyro, min_clip=0.9 * 125.0 * DEG)
            if accel is not None:
                sat_a, found_a = detect_saturation(accel, min_clip=0.9 * 2.0 * G0_M_S2)
                sat |= sat_a
                found += [(j + 3, v, n) for j, v, n in found_a]
        if found:
            names = [f"gyro_{a}" for a in AXES] + [f"accel_{a}" for a in AXES]
            desc = ", ".join(f"{names[j]} {n} at {v:.6g}" for j, v, n in found)
            warn_repair(
                f"{path}: {int(sat.sum())} saturated samples (clipped plateaus: {desc}); flagged in column 'saturated'"
            )
            prev = extra.get("saturated")
            extra["saturated"] = (sat | (prev > 0)).astype(float) if prev is not None else sat.astype(float)
    meta.pop("__gyro_col__", None)
    meta.pop("__time_col__", None)
    return Recording(
        t_s=t,
        gyro_rad_s=gyro,
        accel_m_s2=accel,
        temp_c=temp,
        ref_rate_rad_s=rref,
        ref_quat_wxyz=qref,
        meta=meta,
        extra=extra,
    )


def read_csv(
    path: str | os.PathLike,
    *,
    repair: bool = True,
    retime: bool = False,
    checks: bool = True,
    columns: Iterable[str] | None = None,
) -> Recording:
    """Read a DESIGN.md data file.

    The table is parsed by Arrow's C++ CSV reader (``pyarrow.csv``, multithreaded, correctly
    rounded floats: the ``%.17g`` round trip is bit-exact). A table it refuses — text in a
    number, a wrong number of values, empty fields, ``#`` lines among the data, bad UTF-8 —
    is read again by the exact line parser, which names the file line and column (or reads
    empty fields as NaN with a warning).

    Parameters
    ----------
    path : path-like
        The CSV file.
    repair : bool
        When True, fixable defects are repaired with a :class:`RepairWarning` saying what
        was done (rows with NaN/inf time, gyro, accel or temperature dropped — NaN in the
        ``ref_`` columns is kept, e.g. tracking lost —, non-increasing timestamps dropped,
        empty fields read as NaN). When False they raise :class:`GyroInputError`.
    retime : bool
        Replace bursty host timestamps (median interval < ½ mean, gaps > 4 × mean) by a
        uniform grid at the mean rate (N−1)/duration, with a warning. Without it they are
        only reported.
    checks : bool
        Plausibility checks (warnings only, data unchanged unless stated): gaps, bursty
        timestamps, deg/s labelled rad/s (peaks above 70 rad/s are an error), saturated
        plateaus (flagged in the extra column ``saturated``, 1.0 = clipped).
    columns : iterable of str, optional
        Column groups to read besides ``t_s`` and the gyro, from :data:`COLUMN_GROUPS`
        (``accel``, ``temp``, ``ref_rate``, ``ref_quat``, ``extra``); None reads all. The
        others are not parsed (less memory and time); the header is validated either way.

    Raises
    ------
    GyroInputError
        One-line message for anything that cannot be read as a data file (missing, folder,
        empty, binary, no header, missing column, text in a number with its line and column,
        too large for memory: use :func:`iter_csv_chunks`).
    """
    path = str(path)
    _sniff_file(path)
    meta, header, n_skip = _header_info(path)
    layout = _Layout(header, path, columns)
    _check_memory(path, n_skip, len(layout.want) - len(layout.check_accel))
    offset = _data_offset(path, n_skip)
    fill = None
    if offset is not None:
        fill = _Filler(layout, _count_lines(path, offset))
        try:
            for blk in _arrow_stream(path, offset, header, layout.want, _MAX_BLOCK_BYTES):
                fill.add(blk)
        except _NotClean:
            fill = None
    if fill is None:  # not a clean table: the exact parser, chunk by chunk (line numbers, empty fields)
        fill = _Filler(layout, _count_lines(path, 0))
        for blk in _exact_blocks(path, header, n_skip, layout.want, 0, n_skip + 1):
            fill.add(blk)
    if fill.n == 0:
        raise GyroInputError(f"{path}: header only, no samples")
    return _assemble_filled(fill, meta, path, repair=repair, retime=retime, checks=checks)


def _assemble_filled(fill: _Filler, meta, path, *, repair, retime, checks, min_rows=2) -> Recording:
    """Filled columns -> checked :class:`Recording` (rows with NaN or non-increasing time
    dropped with a warning; copies only when rows are dropped)."""
    t, gyro, accel, temp, rref, qref, extra = fill.columns()
    layout = fill.layout
    t_even = coarse_clock_retime(t, gyro, path, repair)
    if t_even is not None:
        t[:] = t_even
    keep, n_bad, n_back = _valid_rows(t, gyro, accel, temp, path, repair)
    if n_bad:
        warn_repair(f"{path}: dropped {n_bad} rows with NaN/inf time, gyro, accel or temperature")
    if n_back:
        warn_repair(f"{path}: dropped {n_back} rows whose timestamp goes backwards or repeats")
    n_keep = int(keep.sum())
    if n_keep < min_rows:
        raise GyroInputError(f"{path}: fewer than {min_rows} valid samples")
    all_kept = n_keep == keep.size

    def k(a):
        return None if a is None else (a if all_kept else a[keep])

    meta = dict(meta)
    meta["__gyro_col__"] = layout.gyro_unit_col
    meta["__time_col__"] = layout.header[layout.t]
    accel_std = layout.accel_std(fill.moments)
    del fill
    return _finish(
        k(t),
        k(gyro),
        k(accel),
        k(temp),
        k(rref),
        k(qref),
        meta,
        {h: k(v) for h, v in extra.items()},
        path,
        checks=checks,
        retime=retime,
        accel_std=accel_std,
    )


def _chunk_records(
    blocks: Iterable[dict[int, np.ndarray]], layout: _Layout, meta, path: str, repair: bool
) -> Iterator[Recording]:
    """Checked :class:`Recording` chunks from column blocks (NaN rows and non-increasing
    timestamps dropped across chunk boundaries, one warning each at the end)."""
    t_prev = -np.inf
    n_bad_all = n_back_all = n_rows = 0
    for cols in blocks:
        for i in layout.check_accel:  # no whole-series checks on chunks
            cols.pop(i, None)
        t = cols[layout.t] if layout.t_factor == 1.0 else cols[layout.t] * layout.t_factor
        gyro = layout.take(cols, layout.gyro)
        accel = layout.take(cols, layout.accel)
        temp = cols[layout.temp] if layout.temp is not None else None
        keep, n_bad, n_back = _valid_rows(t, gyro, accel, temp, path, repair, t_prev=t_prev)
        n_bad_all += n_bad
        n_back_all += n_back
        if not keep.any():
            continue
        all_kept = bool(keep.all())

        def k(a):
            return None if a is None else (a if all_kept else a[keep])

        t_prev = float(t[keep][-1])
        n_rows += int(keep.sum())
        yield Recording(
            t_s=k(t),
            gyro_rad_s=k(gyro),
            accel_m_s2=k(accel),
            temp_c=k(temp),
            ref_rate_rad_s=k(layout.take(cols, layout.rref)),
            ref_quat_wxyz=k(layout.take(cols, layout.qref)),
            meta=dict(meta),
            extra={h: k(cols[i]) for h, i in layout.extra},
        )
    if n_bad_all:
        warn_repair(f"{path}: dropped {n_bad_all} rows with NaN/inf time, gyro, accel or temperature")
    if n_back_all:
        warn_repair(f"{path}: dropped {n_back_all} rows whose timestamp goes backwards or repeats")
    if n_rows == 0:
        raise GyroInputError(f"{path}: header only, no samples")


def iter_csv_chunks(
    path: str | os.PathLike, *, rows: int = 200_000, repair: bool = True, columns: Iterable[str] | None = None
) -> Iterator[Recording]:
    """Read a data file of any size as consecutive :class:`Recording` chunks of ≤ ``rows`` rows.

    Memory stays O(``rows``). Same parser as :func:`read_csv` (Arrow's streaming reader,
    the exact line parser from the first block it refuses). Each chunk carries the file's
    metadata; the timestamps are checked for monotonicity across chunk boundaries
    (non-increasing rows are dropped with one warning at the end, as are NaN rows).
    Per-chunk plausibility checks (gaps, saturation) are not run: they need the whole series.

    Parameters
    ----------
    rows : int
        Rows per chunk (≥ 2).
    columns : iterable of str, optional
        Column groups to read (see :func:`read_csv`).
    """
    path = str(path)
    if rows < 2:
        raise GyroInputError(f"rows per chunk must be >= 2, got {rows}")
    _sniff_file(path)
    meta, header, n_skip = _header_info(path)
    layout = _Layout(header, path, columns)
    return _chunk_records(_csv_blocks(path, header, n_skip, layout.want, rows), layout, meta, path, repair)


#: Rows formatted at a time by :func:`write_csv_chunks` (bounds the text held: ~6 MiB).
_FORMAT_ROWS = 4096


def _format_rows(rec: Recording) -> tuple[list[str], str]:
    names, cols = _columns(rec)
    data = np.hstack(cols) if cols else np.empty((0, 0))
    buf = io.StringIO()
    np.savetxt(buf, data, delimiter=",", fmt="%.17g")
    text = buf.getvalue()
    buf.close()  # release the buffer now: chunked writes otherwise grow until GC (measured 76-124 B/sample)
    return names, text


def write_csv_chunks(
    chunks: Iterable[Recording],
    path: str | os.PathLike,
    *,
    overwrite: bool = True,
    meta: Mapping[str, str] | None = None,
) -> int:
    """Write consecutive recording chunks as one data file, streaming, atomically.

    The file is written to a temporary name in the target folder and renamed at the end;
    an exception (or interrupt) part way leaves no output. The header and metadata come
    from the first chunk (``meta`` replaces its metadata when given); every chunk must have
    the same columns. Returns the number of rows written.
    """
    n = 0
    with atomic_open(path, "w", overwrite=overwrite, encoding="utf-8", newline="\n") as fh:
        names0 = None
        for rec in chunks:
            # formatted _FORMAT_ROWS rows at a time (the same text: savetxt formats row by row):
            # the text of a chunk is ~350 characters a row, held by StringIO at 4 bytes each
            for i in range(0, max(rec.n, 1), _FORMAT_ROWS):
                names, body = _format_rows(rec if rec.n <= _FORMAT_ROWS else rec.slice(i, i + _FORMAT_ROWS))
                if names0 is None:
                    names0 = names
                    for k, v in (rec.meta if meta is None else meta).items():
                        fh.write(f"# {k}: {str(v).replace(chr(10), ' ')}\n")
                    fh.write(",".join(names) + "\n")
                elif names != names0:
                    raise GyroInputError(f"{path}: chunk columns changed ({','.join(names)})")
                fh.write(body)
            n += rec.n
        if names0 is None:
            raise GyroInputError(f"{path}: nothing to write (no samples)")
    return n


# ---------------------------------------------------------------------- Parquet
#: Suffixes of Parquet data files (every command chooses the format by the file's name).
PARQUET_SUFFIXES = (".parquet", ".pq")
#: Schema metadata key holding the ``#`` metadata lines (JSON object of strings, in order).
PARQUET_META_KEY = b"gyroharness.meta"
#: Rows per Parquet row group when a whole recording is written (chunked readers read one
#: row group at a time, so this bounds their memory).
PARQUET_ROW_GROUP = 131_072


def is_parquet(path: str | os.PathLike) -> bool:
    """True when ``path`` names a Parquet data file (by suffix, else by its ``PAR1`` magic)."""
    p = str(path)
    if p.lower().endswith(PARQUET_SUFFIXES):
        return True
    try:
        with open(p, "rb") as fh:
            return fh.read(4) == b"PAR1"
    except OSError:
        return False


def _parquet_table(names: list[str], cols: list[np.ndarray], meta: Mapping[str, str] | None):
    import json

    import pyarrow as pa

    arrays = []
    fields = []
    for name, c in zip(names, cols):
        # the float64 values as the Arrow array's buffer (zero-copy; the same table, so the same
        # file): pa.array()'s numpy conversion keeps ~40 MiB resident once used (measured:
        # writing 22 row groups of 16 384 × 16 columns peaks 57 MiB above the imports with
        # pa.array, 17 MiB with the buffer), a third of `simulate hover`'s 300 MiB budget
        v = np.ascontiguousarray(c, dtype=np.float64)
        arrays.append(pa.Array.from_buffers(pa.float64(), v.shape[0], [None, pa.py_buffer(v)]))
        fields.append(pa.field(name, pa.float64()))
    md = None if meta is None else {PARQUET_META_KEY: json.dumps({str(k): str(v) for k, v in meta.items()}).encode()}
    return pa.Table.from_arrays(arrays, schema=pa.schema(fields, metadata=md))


def _split_columns(rec: Recording) -> tuple[list[str], list[np.ndarray]]:
    names, blocks = _columns(rec)
    cols: list[np.ndarray] = []
    for b in blocks:
        cols.extend(b[:, j] for j in range(b.shape[1]))
    return names, cols


def write_parquet(rec: Recording, path: str | os.PathLike, *, overwrite: bool = True) -> None:
    """Write ``rec`` as a Parquet data file (same columns as the CSV, float64; the ``#``
    metadata in the schema metadata under ``gyroharness.meta``), atomically."""
    write_parquet_chunks(
        (rec.slice(i, i + PARQUET_ROW_GROUP) for i in range(0, max(rec.n, 1), PARQUET_ROW_GROUP)),
        path,
        overwrite=overwrite,
    )


def write_parquet_chunks(
    chunks: Iterable[Recording],
    path: str | os.PathLike,
    *,
    overwrite: bool = True,
    meta: Mapping[str, str] | None = None,
) -> int:
    """Parquet version of :func:`write_csv_chunks`: one row group per chunk, streaming, atomic."""
    import pyarrow.parquet as pq

    n = 0
    with atomic_open(path, "wb", overwrite=overwrite) as fh:
        writer = None
        names0 = None
        try:
            for rec in chunks:
                names, cols = _split_columns(rec)
                if writer is None:
                    names0 = names
                    table = _parquet_table(names, cols, rec.meta if meta is None else meta)
                    writer = pq.ParquetWriter(fh, table.schema, compression="zstd", use_dictionary=False)
                elif names != names0:
                    raise GyroInputError(f"{path}: chunk columns changed ({','.join(names)})")
                else:
                    table = _parquet_table(names, cols, None).replace_schema_metadata(writer.schema.metadata)
                if rec.n:
                    writer.write_table(table)
                n += rec.n
            if writer is None or n == 0:
                raise GyroInputError(f"{path}: nothing to write (no samples)")
        finally:
            if writer is not None:
                writer.close()
    return n


def _open_parquet(path: str):
    """(ParquetFile, header, meta) with one-line errors."""
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    _check_path(path)
    try:
        # no pre-buffering: with it, iterating row groups kept the file's column chunks
        # (measured: 343 vs 136 MiB peak for a one-hour 15-column file, 2.6 GiB at ten hours)
        pf = pq.ParquetFile(path, memory_map=False, pre_buffer=False, buffer_size=1 << 20)
        schema = pf.schema_arrow
    except (pa.ArrowException, OSError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise GyroInputError(f"{path}: not a readable Parquet file ({first[:160]})") from None
    header = list(schema.names)
    _check_header(header, path)
    for f in schema:
        if not (pa.types.is_floating(f.type) or pa.types.is_integer(f.type) or pa.types.is_boolean(f.type)):
            hint = ""
            if pa.types.is_timestamp(f.type) or pa.types.is_duration(f.type) or pa.types.is_date(f.type):
                hint = (
                    "; store the time as numbers: seconds in t_s (pandas: df['t_s'] = (df[col] - df[col].iloc[0])"
                    ".dt.total_seconds()) or a counter in t_ms / t_us / t_ns"
                )
            raise GyroInputError(f"{path}: column {f.name!r} is not numeric ({f.type}){hint}")
    meta: dict[str, str] = {}
    raw = (schema.metadata or {}).get(PARQUET_META_KEY)
    if raw is not None:
        try:
            meta = {str(k): str(v) for k, v in json.loads(raw.decode("utf-8")).items()}
        except (ValueError, AttributeError, UnicodeDecodeError):
            raise GyroInputError(f"{path}: schema metadata {PARQUET_META_KEY.decode()} is not a JSON object") from None
    return pf, header, meta


def _parquet_cols(
    batch_or_table, header: list[str], want: list[int], path: str, counter: list[int]
) -> dict[int, np.ndarray]:
    cols = {}
    for i in want:
        c = batch_or_table.column(header[i])
        counter[0] += c.null_count
        if not c.null_count and _is_float64_array(c):  # the values buffer, copied (see _to_numpy)
            cols[i] = np.frombuffer(c.buffers()[1], dtype=np.float64, count=len(c), offset=c.offset * 8).copy()
            continue
        arr = np.asarray(c.to_numpy(zero_copy_only=False), dtype=np.float64)
        cols[i] = arr if arr.flags.writeable else arr.copy()
    return cols


def _parquet_read_error(path: str, exc: Exception) -> GyroInputError:
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return GyroInputError(f"{path}: corrupt Parquet data ({first[:160]})")


def read_parquet(
    path: str | os.PathLike,
    *,
    repair: bool = True,
    retime: bool = False,
    checks: bool = True,
    columns: Iterable[str] | None = None,
) -> Recording:
    """Read a Parquet data file (same columns, units and checks as :func:`read_csv`; nulls
    are read as NaN with a warning, like empty CSV fields)."""
    import pyarrow as pa

    path = str(path)
    pf, header, meta = _open_parquet(path)
    layout = _Layout(header, path, columns)
    _check_memory(path, 0, len(layout.want) - len(layout.check_accel), est_rows=pf.metadata.num_rows)
    nulls = [0]
    fill = _Filler(layout, pf.metadata.num_rows)
    try:
        for batch in pf.iter_batches(batch_size=PARQUET_ROW_GROUP, columns=[header[i] for i in layout.want]):
            fill.add(_parquet_cols(batch, header, layout.want, path, nulls))
    except (pa.ArrowException, OSError) as exc:
        raise _parquet_read_error(path, exc) from None
    if nulls[0]:
        warn_repair(f"{path}: {nulls[0]} empty fields read as missing values (NaN)")
    if fill.n == 0:
        raise GyroInputError(f"{path}: header only, no samples")
    return _assemble_filled(fill, meta, path, repair=repair, retime=retime, checks=checks)


def iter_parquet_chunks(
    path: str | os.PathLike, *, rows: int = 200_000, repair: bool = True, columns: Iterable[str] | None = None
) -> Iterator[Recording]:
    """Parquet version of :func:`iter_csv_chunks` (chunks of exactly ``rows`` rows, the last
    shorter; memory O(``rows`` + one row group))."""
    path = str(path)
    if rows < 2:
        raise GyroInputError(f"rows per chunk must be >= 2, got {rows}")
    pf, header, meta = _open_parquet(path)
    layout = _Layout(header, path, columns)

    def blocks():
        import pyarrow as pa

        nulls = [0]
        try:
            for batch in pf.iter_batches(batch_size=rows, columns=[header[i] for i in layout.want], use_threads=False):
                yield _parquet_cols(batch, header, layout.want, path, nulls)
        except (pa.ArrowException, OSError) as exc:
            raise _parquet_read_error(path, exc) from None
        if nulls[0]:
            warn_repair(f"{path}: {nulls[0]} empty fields read as missing values (NaN)")

    return _chunk_records(_rechunk(blocks(), rows), layout, meta, path, repair)


# ---------------------------------------------------------------------- by extension
def read_recording(path: str | os.PathLike, **options) -> Recording:
    """Read a data file, CSV or Parquet (chosen by :func:`is_parquet`); options as :func:`read_csv`."""
    return read_parquet(path, **options) if is_parquet(path) else read_csv(path, **options)


def iter_chunks(
    path: str | os.PathLike, *, rows: int = 200_000, repair: bool = True, columns: Iterable[str] | None = None
) -> Iterator[Recording]:
    """Chunks of a CSV or Parquet data file (see :func:`iter_csv_chunks`)."""
    fn = iter_parquet_chunks if is_parquet(path) else iter_csv_chunks
    return fn(path, rows=rows, repair=repair, columns=columns)


def write_recording(rec: Recording, path: str | os.PathLike, *, overwrite: bool = True) -> None:
    """Write a data file, Parquet when ``path`` ends in .parquet/.pq, else CSV; atomically."""
    if str(path).lower().endswith(PARQUET_SUFFIXES):
        write_parquet(rec, path, overwrite=overwrite)
    else:
        write_csv(rec, path, overwrite=overwrite)


def write_chunks(
    chunks: Iterable[Recording],
    path: str | os.PathLike,
    *,
    overwrite: bool = True,
    meta: Mapping[str, str] | None = None,
) -> int:
    """Stream chunks into one data file, Parquet or CSV by ``path``'s suffix; atomically."""
    fn = write_parquet_chunks if str(path).lower().endswith(PARQUET_SUFFIXES) else write_csv_chunks
    return fn(chunks, path, overwrite=overwrite, meta=meta)


def concat_recordings(recs: list[Recording]) -> Recording:
    """Consecutive pieces of one recording (same columns) joined; metadata of the first."""
    recs = [r for r in recs if r is not None and r.n]
    if len(recs) == 1:
        return recs[0]

    def cat(name):
        v = [getattr(r, name) for r in recs]
        return None if v[0] is None else np.concatenate(v)

    return Recording(
        t_s=cat("t_s"),
        gyro_rad_s=cat("gyro_rad_s"),
        accel_m_s2=cat("accel_m_s2"),
        temp_c=cat("temp_c"),
        ref_rate_rad_s=cat("ref_rate_rad_s"),
        ref_quat_wxyz=cat("ref_quat_wxyz"),
        meta=recs[0].meta,
        extra={k: np.concatenate([r.extra[k] for r in recs]) for k in recs[0].extra},
    )
