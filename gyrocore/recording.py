"""The data file of DESIGN.md: one CSV row per sample, unit-suffixed columns, ``#`` metadata.

A :class:`Recording` is the in-memory form, shared by measured and simulated data. Arrays are
SI: rad/s, m/s², °C, seconds; frames: gyro, accel and reference rate in the sensor frame S,
reference attitude as a unit quaternion ``w, x, y, z`` rotating S to W.
"""

from __future__ import annotations

import hashlib
import io
import os
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from .errors import GyroInputError, warn_repair

__all__ = [
    "Recording",
    "read_csv",
    "write_csv",
    "atomic_write_text",
    "atomic_write_bytes",
    "file_sha256",
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
def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, overwrite: bool = True) -> None:
    """Write ``data`` to ``path`` atomically (temp file in the same folder + rename).

    An interrupted write leaves either the old file or nothing, never a partial file.
    With ``overwrite=False`` an existing file is an error.
    """
    path = Path(path)
    if not overwrite and path.exists():
        raise GyroInputError(f"{path} exists; pass --force to overwrite it")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


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
def _parse_header(lines: Iterable[str], path: str) -> tuple[dict[str, str], list[str], int]:
    meta: dict[str, str] = {}
    n_skip = 0
    for line in lines:
        n_skip += 1
        s = line.strip()
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


def _block(header, data, names, path, *, required=False):
    idx, fac = zip(*(_find(header, n) for n in names))
    if all(i is None for i in idx):
        if required:
            raise GyroInputError(f"{path}: missing required column(s) {', '.join(names)}")
        return None, ()
    if any(i is None for i in idx):
        missing = [n for n, i in zip(names, idx) if i is None]
        raise GyroInputError(f"{path}: incomplete column group, missing {', '.join(missing)}")
    return data[:, list(idx)] * np.asarray(fac), idx


def read_csv(path: str | os.PathLike, *, repair: bool = True) -> Recording:
    """Read a DESIGN.md data file.

    Parameters
    ----------
    path : path-like
        The CSV file.
    repair : bool
        When True, fixable defects are repaired with a :class:`RepairWarning` saying what
        was done (non-finite gyro rows dropped, non-increasing timestamps dropped). When
        False they raise :class:`GyroInputError`.

    Raises
    ------
    GyroInputError
        One-line message for anything that cannot be read as a data file.
    """
    path = str(path)
    if not os.path.exists(path):
        raise GyroInputError(f"{path}: no such file")
    if os.path.isdir(path):
        raise GyroInputError(f"{path}: is a directory, not a data file")
    with open(path, "rb") as fh:
        head = fh.read(8192)
    if b"\x00" in head:
        raise GyroInputError(f"{path}: binary file, expected a CSV data file")
    try:
        with open(path, "r", encoding="utf-8") as fh:
            meta, header, n_skip = _parse_header(fh, path)
    except UnicodeDecodeError:
        raise GyroInputError(f"{path}: not UTF-8 text, expected a CSV data file") from None
    if TIME_COL not in header:
        raise GyroInputError(f"{path}: missing required column t_s")
    if len(set(header)) != len(header):
        raise GyroInputError(f"{path}: duplicate column names in header")
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=n_skip, comments="#", ndmin=2, dtype=float)
    except ValueError as exc:
        msg = str(exc).splitlines()[0] if str(exc) else "unparseable value"
        raise GyroInputError(f"{path}: not numeric data ({msg})") from None
    if data.size == 0:
        raise GyroInputError(f"{path}: header only, no samples")
    if data.shape[1] != len(header):
        raise GyroInputError(
            f"{path}: rows have {data.shape[1]} values but the header names {len(header)} columns"
        )
    t = data[:, header.index(TIME_COL)]
    gyro, gidx = _block(header, data, GYRO_COLS, path, required=True)
    accel, aidx = _block(header, data, ACCEL_COLS, path)
    rref, ridx = _block(header, data, REF_RATE_COLS, path)
    qref, qidx = _block(header, data, REF_QUAT_COLS, path)
    temp = data[:, header.index(TEMP_COL)] if TEMP_COL in header else None
    used = {header.index(TIME_COL), *gidx, *aidx, *ridx, *qidx}
    if temp is not None:
        used.add(header.index(TEMP_COL))
    extra = {h: data[:, i] for i, h in enumerate(header) if i not in used}

    keep = np.isfinite(t) & np.all(np.isfinite(gyro), axis=1)
    if accel is not None:
        keep &= np.all(np.isfinite(accel), axis=1)
    if temp is not None:
        keep &= np.isfinite(temp)
    n_bad = int((~keep).sum())
    if n_bad:
        if not repair:
            raise GyroInputError(f"{path}: {n_bad} rows with NaN/inf values")
        warn_repair(f"{path}: dropped {n_bad} rows with NaN/inf time, gyro, accel or temperature")
    # Timestamps must increase strictly: drop rows that go backwards or repeat.
    t_k = t[keep]
    if t_k.size:
        running_max = np.maximum.accumulate(t_k)
        mono = np.concatenate([[True], t_k[1:] > running_max[:-1]])
        n_back = int((~mono).sum())
        if n_back:
            if not repair:
                raise GyroInputError(f"{path}: {n_back} timestamps go backwards or repeat")
            warn_repair(f"{path}: dropped {n_back} rows whose timestamp goes backwards or repeats")
            idx = np.flatnonzero(keep)
            keep[idx[~mono]] = False
    if keep.sum() < 2:
        raise GyroInputError(f"{path}: fewer than 2 valid samples")

    def k(a):
        return None if a is None else a[keep]

    return Recording(
        t_s=t[keep],
        gyro_rad_s=gyro[keep],
        accel_m_s2=k(accel),
        temp_c=k(temp),
        ref_rate_rad_s=k(rref),
        ref_quat_wxyz=k(qref),
        meta=meta,
        extra={h: v[keep] for h, v in extra.items()},
    )
