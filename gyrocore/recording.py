"""The data file of DESIGN.md: one CSV row per sample, unit-suffixed columns, ``#`` metadata.

A :class:`Recording` is the in-memory form, shared by measured and simulated data. Arrays are
SI: rad/s, m/s², °C, seconds; frames: gyro, accel and reference rate in the sensor frame S,
reference attitude as a unit quaternion ``w, x, y, z`` rotating S to W.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import itertools
import os
import tempfile
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable, Iterator, Mapping

import numpy as np

from .errors import GyroInputError, warn_repair

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
    "detect_saturation",
    "locate_bad_value",
    "AXES",
]

AXES = ("x", "y", "z")
DEG = np.pi / 180.0
G0_M_S2 = 9.80665

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
    """SHA-256 hex digest of a file, read in 1 MiB chunks."""
    h = hashlib.sha256()
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


def write_csv(rec: Recording, path: str | os.PathLike, *, overwrite: bool = True) -> None:
    """Write ``rec`` as the DESIGN.md data file, atomically.

    Floats are written with 17 significant digits (``%.17g``) so that a write/read round
    trip is bit-exact.
    """
    names, cols = _columns(rec)
    data = np.hstack(cols) if cols else np.empty((0, 0))
    buf = io.StringIO()
    for k, v in rec.meta.items():
        buf.write(f"# {k}: {str(v).replace(chr(10), ' ')}\n")
    buf.write(",".join(names) + "\n")
    np.savetxt(buf, data, delimiter=",", fmt="%.17g")
    atomic_write_text(path, buf.getvalue(), overwrite=overwrite)


# ---------------------------------------------------------------------- reading
#: Largest plausible MEMS gyro full scale: ±2000 °/s = 34.9 rad/s (ICM-42688, BMI160, MPU-6050
#: at their widest range; the fastest parts stop at ±4000 °/s = 69.8 rad/s). Peaks above
#: :data:`DEG_S_SUSPECT_RAD_S` in a column labelled rad/s are taken as deg/s mislabelled.
DEG_S_SUSPECT_RAD_S = 70.0
#: Per-sample noise of a still MEMS gyro is far below 0.05 rad/s (2.9 °/s); a still recording
#: whose noise exceeds it is reported as probably deg/s labelled rad/s.
STILL_NOISE_SUSPECT_RAD_S = 0.05
#: Fraction of the available memory a whole-file read may use before it is refused.
MEMORY_FRACTION = 0.5
#: Bytes of memory per parsed value while reading: float64 table + column copies + masks.
#: Measured: a 1 M-row × 8-column file (164 MB) raised the peak RSS by ≈ 260 MB ≈ 32 B/value.
_BYTES_PER_VALUE = 32


def _available_memory_bytes() -> int:
    """Available physical memory (psutil); tests monkeypatch this."""
    import psutil

    return int(psutil.virtual_memory().available)


def _sniff_file(path: str) -> None:
    """Existence, folder, empty, binary and encoding checks with one-line errors."""
    if not os.path.exists(path):
        raise GyroInputError(f"{path}: no such file")
    if os.path.isdir(path):
        raise GyroInputError(f"{path}: is a directory, not a data file")
    if not os.access(path, os.R_OK):
        raise GyroInputError(f"{path}: not readable (permission denied)")
    if os.path.getsize(path) == 0:
        raise GyroInputError(f"{path}: empty file")
    with open(path, "rb") as fh:
        head = fh.read(8192)
    if head.startswith(b"\x89HDF") or head.startswith(b"ULog") or head.startswith(b"MATLAB"):
        raise GyroInputError(f"{path}: binary file (HDF5/MATLAB/ULog); convert it first: gyroharness convert {path} -o OUT.csv")
    if b"\x00" in head:
        raise GyroInputError(f"{path}: binary file, expected a CSV data file")
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 4:  # not just a multibyte char cut at the 8 KiB boundary
            raise GyroInputError(f"{path}: not UTF-8 text (binary file?), expected a CSV data file") from None


def locate_bad_value(path: str, *, skiprows: int, delimiter: str | None = ",", ncols: int | None = None) -> str:
    """One-line description of the first unparseable line of a numeric table.

    Names the file line number (1-based), the column (name when ``header`` known by the
    caller, else 1-based index) and the offending text.
    """
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            if lineno <= skiprows:
                continue
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            fields = s.split(delimiter) if delimiter else s.split()
            if ncols is not None and len(fields) != ncols:
                return f"{path}: line {lineno}: {len(fields)} values, expected {ncols}"
            for j, f in enumerate(fields, 1):
                try:
                    float(f)
                except ValueError:
                    return f"{path}: line {lineno}, column {j}: text in a number ({f.strip()[:40]!r})"
    return f"{path}: rows have different numbers of values"


def _parse_rows(lines: list[str], first_lineno: int, header: list[str], path: str) -> tuple[np.ndarray, int]:
    """Slow exact parser (used when the fast one fails): empty fields → NaN, else one-line errors.

    Returns the array and the number of empty fields that were read as NaN.
    """
    n = len(header)
    out = []
    n_empty = 0
    for k, line in enumerate(lines):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        f = s.split(",")
        if len(f) != n:
            raise GyroInputError(f"{path}: line {first_lineno + k}: {len(f)} values but the header names {n} columns")
        row = []
        for j, v in enumerate(f):
            v = v.strip()
            if v == "":
                n_empty += 1
                row.append(np.nan)
                continue
            try:
                row.append(float(v))
            except ValueError:
                raise GyroInputError(
                    f"{path}: line {first_lineno + k}, column {header[j]!r}: text in a number ({v[:40]!r})"
                ) from None
        out.append(row)
    return (np.asarray(out, dtype=float).reshape(-1, n), n_empty)


def _fast_parse(source, ncols: int) -> np.ndarray:
    """np.loadtxt on lines or an open file (C parser, no per-line Python objects).

    Raises ValueError (including UnicodeDecodeError) when the text is not a clean table.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = np.loadtxt(source, delimiter=",", comments="#", ndmin=2, dtype=float)
    if data.size and data.shape[1] != ncols:
        raise ValueError("column count")
    return data.reshape(-1, ncols) if data.size else np.empty((0, ncols))


def _slow_parse(lines: list[str], first_lineno: int, header: list[str], path: str) -> np.ndarray:
    data, n_empty = _parse_rows(lines, first_lineno, header, path)
    if n_empty:
        warn_repair(f"{path}: {n_empty} empty fields read as missing values (NaN)")
    return data


def _parse_block(lines: list[str], first_lineno: int, header: list[str], path: str) -> np.ndarray:
    """Parse data lines: fast path np.loadtxt, fallback to :func:`_parse_rows` for messages."""
    try:
        return _fast_parse(lines, len(header))
    except ValueError:
        return _slow_parse(lines, first_lineno, header, path)


def _check_memory(path: str, n_header_lines: int, ncols: int) -> None:
    """Refuse a whole-file read that would not fit comfortably in memory."""
    size = os.path.getsize(path)
    with open(path, "rb") as fh:
        sample = fh.read(1 << 16)
    lines = sample.count(b"\n")
    avg_line = len(sample) / max(lines, 1)
    est_rows = int(size / max(avg_line, 1.0))
    need = est_rows * ncols * _BYTES_PER_VALUE
    avail = _available_memory_bytes()
    if need > MEMORY_FRACTION * avail:
        raise GyroInputError(
            f"{path}: {size / 2**20:.0f} MiB (~{est_rows:,} rows) needs ~{need / 2**20:.0f} MiB to load, more than "
            f"{MEMORY_FRACTION:.0%} of the {avail / 2**20:.0f} MiB available; read it in chunks "
            f"(gyrocore.recording.iter_csv_chunks, or gyroharness convert which streams CSV files)"
        )


def _header_info(path: str) -> tuple[dict[str, str], list[str], int]:
    try:
        with open(path, "r", encoding="utf-8") as fh:
            meta, header, n_skip = _parse_header(fh, path)
    except UnicodeDecodeError:
        raise GyroInputError(f"{path}: not UTF-8 text, expected a CSV data file") from None
    if TIME_COL not in header:
        raise GyroInputError(f"{path}: missing required column t_s")
    if len(set(header)) != len(header):
        dup = sorted({h for h in header if header.count(h) > 1})
        raise GyroInputError(f"{path}: duplicate column names in header ({', '.join(dup)})")
    if "" in header:
        raise GyroInputError(f"{path}: empty column name in header")
    return meta, header, n_skip


class _Layout:
    """Which header columns go where, with their SI factors."""

    def __init__(self, header: list[str], path: str) -> None:
        self.header = header
        self.t = header.index(TIME_COL)
        self.gyro = self._block(GYRO_COLS, path, required=True)
        self.accel = self._block(ACCEL_COLS, path)
        self.rref = self._block(REF_RATE_COLS, path)
        self.qref = self._block(REF_QUAT_COLS, path)
        self.temp = header.index(TEMP_COL) if TEMP_COL in header else None
        used = {self.t, *(self.gyro[0] if self.gyro else ()), *(self.accel[0] if self.accel else ()),
                *(self.rref[0] if self.rref else ()), *(self.qref[0] if self.qref else ())}
        if self.temp is not None:
            used.add(self.temp)
        self.extra = [(h, i) for i, h in enumerate(header) if i not in used]
        self.gyro_unit_col = header[self.gyro[0][0]]

    def _block(self, names, path, *, required=False):
        idx, fac = zip(*(_find(self.header, n) for n in names))
        if all(i is None for i in idx):
            if required:
                raise GyroInputError(f"{path}: missing required column(s) {', '.join(names)}")
            return None
        if any(i is None for i in idx):
            missing = [n for n, i in zip(names, idx) if i is None]
            raise GyroInputError(f"{path}: incomplete column group, missing {', '.join(missing)}")
        return list(idx), np.asarray(fac)

    def take(self, data: np.ndarray, block):
        return None if block is None else data[:, block[0]] * block[1]


def _find(header: list[str], si_name: str) -> tuple[int | None, float]:
    """Index of column ``si_name`` or of an accepted alternative unit, and its SI factor."""
    if si_name in header:
        return header.index(si_name), 1.0
    for si_suffix, alts in _ALT_UNITS.items():
        if si_name.endswith(si_suffix):
            stem = si_name[: -len(si_suffix)]
            for suffix, factor in alts:
                if stem + suffix in header:
                    return header.index(stem + suffix), factor
    return None, 1.0


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
    t_k = t[keep]
    n_back = 0
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


def _robust_noise(x: np.ndarray) -> float:
    """Per-sample white-noise σ from first differences: 1.4826·MAD(Δx)/√2; the smallest
    non-zero step when more than half of the differences are exactly zero (coarse quantum)."""
    d = np.diff(x)
    if d.size == 0:
        return 0.0
    mad = float(np.median(np.abs(d - np.median(d))))
    if mad > 0:
        return 1.4826 * mad / np.sqrt(2.0)
    nz = np.abs(d[d != 0])
    return float(nz.min()) if nz.size else 0.0


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
        c = col[fin]
        inner = (c != c.max()) & (c != c.min())
        d = np.diff(c)[inner[1:] & inner[:-1]]
        if d.size < 10 or float(np.median(np.abs(d - np.median(d)))) == 0.0:
            # away from the extremes most consecutive samples are identical (noise-free
            # simulation, or a quantum coarser than the noise): repeated values are normal
            # there and clipping cannot be told from a constant rate — no verdict
            continue
        sigma = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / np.sqrt(2.0)
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


def _unit_checks(rec_t, gyro, accel, path, gyro_col) -> None:
    """Warn when a column labelled rad/s carries deg/s (magnitude evidence), or error."""
    if not gyro_col.endswith("_rad_s") or gyro.shape[0] < 2:
        return
    peak = float(np.max(np.abs(gyro)))
    if peak > DEG_S_SUSPECT_RAD_S:
        raise GyroInputError(
            f"{path}: gyro peaks at {peak:.1f} rad/s ({np.rad2deg(peak):.0f} deg/s), beyond any MEMS full scale "
            f"(<= 4000 deg/s = 70 rad/s): the column is probably deg/s; rename it {gyro_col.replace('_rad_s', '_deg_s')}"
        )
    # still recording (accel steady, std < 0.05 g): a MEMS gyro at rest has per-sample noise
    # < 0.05 rad/s (2.9 deg/s; even 0.01 deg/s/sqrt(Hz) at 8 kHz is 0.9 deg/s); deg/s numbers
    # read as rad/s are 57x too big (an MPU-6050's 0.1 deg/s becomes 0.1 "rad/s").
    if accel is None or not bool(np.all(np.std(accel, axis=0) < 0.05 * G0_M_S2)):
        return
    med = np.median(gyro, axis=0)
    noise = np.array([_robust_noise(gyro[:, i]) for i in range(3)])
    # (a large median alone is not evidence: a centred sensor on a turning rate table also has steady accel)
    if np.any(noise > STILL_NOISE_SUSPECT_RAD_S):
        warn_repair(
            f"{path}: still recording (accel steady) but gyro median ({', '.join(f'{m:.3g}' for m in med)}) rad/s "
            f"and per-sample noise ({', '.join(f'{v:.3g}' for v in noise)}) rad/s : the noise exceeds any MEMS gyro at rest "
            f"({STILL_NOISE_SUSPECT_RAD_S} rad/s per sample): is it deg/s labelled rad/s? "
            f"Data left unchanged"
        )


def _timing_checks(t: np.ndarray, path: str, retime: bool) -> np.ndarray:
    """Warn on gaps (dropped samples) and bursty host timestamps; retime on request."""
    d = np.diff(t)
    if d.size < 2:
        return t
    med = float(np.median(d))
    mean = float((t[-1] - t[0]) / d.size)
    mx = float(d.max())
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
    gaps = d > 1.5 * med
    if med > 0 and gaps.any():
        n_missing = int(np.sum(np.round(d[gaps] / med) - 1))
        warn_repair(
            f"{path}: {int(gaps.sum())} gaps longer than 1.5x the median interval {med * 1e3:.3g} ms "
            f"(longest {mx:.3g} s, ~{n_missing} samples missing in all); data kept as recorded"
        )
    return t


def _finish(t, gyro, accel, temp, rref, qref, meta, extra, path, *, checks: bool, retime: bool) -> Recording:
    """Post-parse checks common to the whole-file and chunked readers."""
    span = np.subtract(t[-1], t[0], dtype=float) if t.size else 0.0
    with np.errstate(all="ignore"):
        if not np.isfinite(span) or not np.all(np.isfinite(np.diff(t))):
            raise GyroInputError(f"{path}: time column spans beyond the float range (t_s from {t[0]:.3g} to {t[-1]:.3g})")
    if checks:
        with np.errstate(all="ignore"):  # absurd finite values (1e300) must not print overflow warnings
            _unit_checks(t, gyro, accel, path, meta.pop("__gyro_col__", "gyro_x_rad_s"))
            t = _timing_checks(t, path, retime)
        sat_parts = [gyro] + ([accel] if accel is not None else [])
        with np.errstate(all="ignore"):
            # smallest full scales on the market: gyro ±125 deg/s (BMI088, ICM-42688-P low
            # ranges), accel ±2 g; a plateau below 90 % of these cannot be clipping.
            min_clip = [0.9 * 125.0 * DEG] * 3 + ([0.9 * 2.0 * G0_M_S2] * 3 if accel is not None else [])
            sat, found = detect_saturation(np.hstack(sat_parts), min_clip=np.asarray(min_clip))
        if found:
            names = [f"gyro_{a}" for a in AXES] + [f"accel_{a}" for a in AXES]
            desc = ", ".join(f"{names[j]} {n} at {v:.6g}" for j, v, n in found)
            warn_repair(f"{path}: {int(sat.sum())} saturated samples (clipped plateaus: {desc}); flagged in column 'saturated'")
            prev = extra.get("saturated")
            extra["saturated"] = (sat | (prev > 0)).astype(float) if prev is not None else sat.astype(float)
    meta.pop("__gyro_col__", None)
    return Recording(t_s=t, gyro_rad_s=gyro, accel_m_s2=accel, temp_c=temp, ref_rate_rad_s=rref,
                     ref_quat_wxyz=qref, meta=meta, extra=extra)


def read_csv(path: str | os.PathLike, *, repair: bool = True, retime: bool = False, checks: bool = True) -> Recording:
    """Read a DESIGN.md data file.

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
    layout = _Layout(header, path)
    _check_memory(path, n_skip, len(header))
    try:
        with open(path, "r", encoding="utf-8", errors="strict") as fh:
            for _ in range(n_skip):
                fh.readline()
            data = _fast_parse(fh, len(header))  # streams the file: no list of lines in memory
    except UnicodeDecodeError as exc:
        raise GyroInputError(f"{path}: not UTF-8 text after the header ({exc.reason})") from None
    except ValueError:
        # not a clean table: the exact parser names the line and column (or reads empty fields)
        try:
            with open(path, "r", encoding="utf-8", errors="strict") as fh:
                for _ in range(n_skip):
                    fh.readline()
                lines = fh.readlines()
        except UnicodeDecodeError as exc:  # found by bench/fuzz_reader.py (atheris)
            raise GyroInputError(f"{path}: not UTF-8 text after the header ({exc.reason})") from None
        data = _slow_parse(lines, n_skip + 1, header, path)
    if data.shape[0] == 0:
        raise GyroInputError(f"{path}: header only, no samples")
    return _assemble(data, layout, meta, path, repair=repair, retime=retime, checks=checks)


def _assemble(data, layout: _Layout, meta, path, *, repair, retime, checks, t_prev=-np.inf, min_rows=2):
    t = data[:, layout.t]
    gyro = layout.take(data, layout.gyro)
    accel = layout.take(data, layout.accel)
    rref = layout.take(data, layout.rref)
    qref = layout.take(data, layout.qref)
    temp = data[:, layout.temp] if layout.temp is not None else None
    keep, n_bad, n_back = _valid_rows(t, gyro, accel, temp, path, repair, t_prev=t_prev)
    if n_bad:
        warn_repair(f"{path}: dropped {n_bad} rows with NaN/inf time, gyro, accel or temperature")
    if n_back:
        warn_repair(f"{path}: dropped {n_back} rows whose timestamp goes backwards or repeats")
    if keep.sum() < min_rows:
        raise GyroInputError(f"{path}: fewer than {min_rows} valid samples")

    def k(a):
        return None if a is None else a[keep]

    meta = dict(meta)
    meta["__gyro_col__"] = layout.gyro_unit_col
    extra = {h: data[keep, i] for h, i in layout.extra}
    return _finish(t[keep], gyro[keep], k(accel), k(temp), k(rref), k(qref), meta, extra, path,
                   checks=checks, retime=retime)


def iter_csv_chunks(path: str | os.PathLike, *, rows: int = 200_000, repair: bool = True) -> Iterator[Recording]:
    """Read a data file of any size as consecutive :class:`Recording` chunks of ≤ ``rows`` rows.

    Memory stays O(``rows``). Each chunk carries the file's metadata; the timestamps are
    checked for monotonicity across chunk boundaries (non-increasing rows are dropped with
    one warning at the end, as are NaN rows). Per-chunk plausibility checks (gaps,
    saturation) are not run: they need the whole series.

    Parameters
    ----------
    rows : int
        Rows per chunk (≥ 2).
    """
    path = str(path)
    if rows < 2:
        raise GyroInputError(f"rows per chunk must be >= 2, got {rows}")
    _sniff_file(path)
    meta, header, n_skip = _header_info(path)
    layout = _Layout(header, path)
    t_prev = -np.inf
    n_bad_all = n_back_all = n_rows = 0
    lineno = n_skip + 1
    with open(path, "r", encoding="utf-8", errors="strict") as fh:
        for _ in range(n_skip):
            fh.readline()
        while True:
            try:
                lines = list(itertools.islice(fh, rows))
            except UnicodeDecodeError as exc:
                raise GyroInputError(f"{path}: not UTF-8 text near line {lineno} ({exc.reason})") from None
            if not lines:
                break
            data = _parse_block(lines, lineno, header, path)
            lineno += len(lines)
            if data.shape[0] == 0:
                continue
            t = data[:, layout.t]
            gyro = layout.take(data, layout.gyro)
            accel = layout.take(data, layout.accel)
            temp = data[:, layout.temp] if layout.temp is not None else None
            keep, n_bad, n_back = _valid_rows(t, gyro, accel, temp, path, repair, t_prev=t_prev)
            n_bad_all += n_bad
            n_back_all += n_back
            if not keep.any():
                continue
            t_prev = float(t[keep][-1])
            n_rows += int(keep.sum())
            rref = layout.take(data, layout.rref)
            qref = layout.take(data, layout.qref)
            yield Recording(
                t_s=t[keep], gyro_rad_s=gyro[keep],
                accel_m_s2=None if accel is None else accel[keep],
                temp_c=None if temp is None else temp[keep],
                ref_rate_rad_s=None if rref is None else rref[keep],
                ref_quat_wxyz=None if qref is None else qref[keep],
                meta=dict(meta), extra={h: data[keep, i] for h, i in layout.extra},
            )
    if n_bad_all:
        warn_repair(f"{path}: dropped {n_bad_all} rows with NaN/inf time, gyro, accel or temperature")
    if n_back_all:
        warn_repair(f"{path}: dropped {n_back_all} rows whose timestamp goes backwards or repeats")
    if n_rows == 0:
        raise GyroInputError(f"{path}: header only, no samples")


def _parse_header(lines: Iterable[str], path: str) -> tuple[dict[str, str], list[str], int]:
    """``# key: value`` metadata lines, then the header row; returns (meta, header, lines used)."""
    meta: dict[str, str] = {}
    n_skip = 0
    for line in lines:
        n_skip += 1
        s = line.strip().lstrip("\ufeff")
        if not s:
            continue
        if s.startswith("#"):
            body = s[1:].strip()
            if ":" in body:
                k, v = body.split(":", 1)
                meta[k.strip()] = v.strip()
            continue
        header = [h.strip() for h in s.split(",")]
        return meta, header, n_skip
    raise GyroInputError(f"{path}: no header row (file is empty or only has comments)")


def _format_rows(rec: Recording) -> tuple[list[str], str]:
    names, cols = _columns(rec)
    data = np.hstack(cols) if cols else np.empty((0, 0))
    buf = io.StringIO()
    np.savetxt(buf, data, delimiter=",", fmt="%.17g")
    text = buf.getvalue()
    buf.close()  # release the buffer now: chunked writes otherwise grow until GC (measured 76-124 B/sample)
    return names, text


def write_csv_chunks(chunks: Iterable[Recording], path: str | os.PathLike, *, overwrite: bool = True,
                     meta: Mapping[str, str] | None = None) -> int:
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
            names, body = _format_rows(rec)
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
