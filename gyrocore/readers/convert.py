"""Any supported source as a :class:`Recording`: the format detected (:func:`detect_format`) and
its reader called (:func:`load_with_segments`, :func:`load_any`); the readers are in
:mod:`gyrocore.readers.datasets`, :mod:`gyrocore.readers.ulog`, :mod:`gyrocore.readers.blackbox`
and :mod:`gyrocore.readers.dataflash`, the shared pieces in :mod:`gyrocore.readers.common`.

Every reader returns SI arrays in the DESIGN.md columns (rad/s, m/s², °C, s), with metadata
lines ``source``, ``format``, ``sensor``, ``rate_hz`` and ``repairs`` (what was changed, e.g.
padding rows dropped, an axis sign flipped, host timestamps replaced by a uniform grid). Every
repair is also announced once with :func:`gyrocore.errors.warn_repair`.

Known total rotation angles (hand-rotation sessions) are returned as
:class:`~gyrocore.data.segments.Segment` rows (the segments file of
:func:`~gyrocore.data.segments.write_segments`).

The sources and their quirks are documented in ``docs/data.md`` and in each folder's
PROVENANCE.md under ``../shared/data``.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording, is_parquet, read_csv, read_parquet, read_recording

from gyrocore.data.segments import Segment

from .common import Converted, _positive
from .datasets import (
    _sunsided_dir,
    imucal_segments,
    read_broad,
    read_fusion,
    read_gnss_ins_sim,
    read_imucal,
    read_imucal_annotated,
    read_imutk,
    read_sunsided,
    read_tomisuarez2,
    sunsided_segments,
    tomisuarez2_segments,
)
from .ulog import read_ulog

__all__ = ["FORMATS", "detect_format", "load_with_segments", "load_any", "read_any", "concat_converted"]


# ============================================================================ dispatcher
FORMATS = (
    "auto",
    "blackbox",
    "dataflash",
    "ulog",
    "sunsided",
    "tomisuarez2",
    "imucal",
    "imucal_annotated",
    "broad",
    "imutk",
    "gnss_ins_sim",
    "fusion",
    "raw_dump",
    "csv",
    "parquet",
)


def detect_format(path: str | os.PathLike) -> str:
    """Guess the source format of ``path`` (file or folder) from its name and first bytes."""
    p = Path(path)
    if not p.exists():
        raise GyroInputError(f"{p}: no such file or folder")
    if p.is_dir():
        if (p / "mpu6050_gyroscope.mat").exists():
            return "sunsided"
        if (p / "gyro-0.csv").exists():
            return "gnss_ins_sim"
        if (p / "xsens_gyro.mat").exists():
            return "imutk"
        raise GyroInputError(f"{p}: folder is not a known recording (sunsided, gnss-ins-sim or IMU-TK)")
    with open(p, "rb") as fh:
        head = fh.read(4096)
    if is_parquet(p):
        return "parquet"
    if head.startswith(b"ULog\x01\x12\x35"):
        return "ulog"
    if head.startswith(b"H Product:Blackbox"):  # Betaflight/INAV/Cleanflight blackbox (.BBL/.BFL/.TXT)
        return "blackbox"
    if head.startswith(b"\xa3\x95\x80"):  # ArduPilot DataFlash: a FMT message first (.bin)
        return "dataflash"
    if head.startswith(b"\x89HDF\r\n\x1a\n") or head[512:520] == b"\x89HDF\r\n\x1a\n" or b"MATLAB 7.3" in head[:128]:
        if p.name.startswith("mpu6050_"):
            return "sunsided"
        return "broad"
    if p.name in ("gyro-0.csv", "accel-0.csv", "time.csv"):
        return "gnss_ins_sim"
    text = head.decode("utf-8", errors="replace")
    first = text.splitlines()[0].strip() if text.strip() else ""
    if p.suffix == ".mat" and re.match(r"^\s*[-+0-9.eE]+\s+[-+0-9.eE]+\s+[-+0-9.eE]+\s+[-+0-9.eE]+\s*$", first):
        return "imutk"
    if first.startswith("Fs,"):
        return "tomisuarez2"
    if first.startswith("n_samples,gyr_x"):
        return "imucal"
    if first.startswith("part,samples"):
        return "imucal_annotated"
    if first.startswith("Time (s),Gyroscope"):
        return "fusion"
    from .rawdump import looks_like_raw_dump

    if looks_like_raw_dump(p):  # gx,gy,gz / GyX... counts (an Arduino MPU-6050 sketch's log)
        return "raw_dump"
    return "csv"


def concat_converted(parts: Sequence[Converted], *, gap_s: float | None = None) -> Converted:
    """Join recordings of one session (e.g. sunsided's three ``rotate-*`` runs) end to end.

    Each part's time axis is shifted to start ``gap_s`` (default: one mean sample interval of
    the previous part, so the file has no gap) after the previous part's last sample and its
    segments are shifted with it, so that a single segments file covers turns about
    all three axes (the integral method needs them in one recording). Columns present in
    every part are kept (accel, temperature, references, extra columns); metadata of the
    first part, with ``source`` listing all parts.

    Raises
    ------
    GyroInputError
        No parts, or ``gap_s`` not positive.
    """
    parts = list(parts)
    if not parts:
        raise GyroInputError("nothing to concatenate")
    if gap_s is not None:
        gap_s = _positive("gap_s", gap_s)
    recs, segs, t0, gap = [], [], None, 0.0
    for c in parts:
        r = c.recording
        shift = 0.0 if t0 is None else t0 + gap - float(r.t_s[0])
        gap = gap_s if gap_s is not None else 1.0 / r.rate_hz
        recs.append((r, shift))
        segs.extend(s.shifted(shift) for s in c.segments)
        t0 = float(r.t_s[-1]) + shift

    def cat(get):
        cols = [get(r) for r, _ in recs]
        return None if any(c is None for c in cols) else np.concatenate(cols)

    extra_keys = set.intersection(*(set(r.extra) for r, _ in recs))
    first = recs[0][0]
    meta = dict(first.meta)
    meta["source"] = " + ".join(str(r.meta.get("source", "?")) for r, _ in recs)
    meta["concatenated"] = f"{len(recs)} recordings" + (f", {gap_s:g} s gaps" if gap_s is not None else ", no gaps")
    rec = Recording(
        t_s=np.concatenate([r.t_s + sh for r, sh in recs]),
        gyro_rad_s=cat(lambda r: r.gyro_rad_s),
        accel_m_s2=cat(lambda r: r.accel_m_s2),
        temp_c=cat(lambda r: r.temp_c),
        ref_rate_rad_s=cat(lambda r: r.ref_rate_rad_s),
        ref_quat_wxyz=cat(lambda r: r.ref_quat_wxyz),
        meta=meta,
        extra={
            k: np.concatenate([r.extra[k] + (sh if k.startswith("t_") and k.endswith("_s") else 0.0) for r, sh in recs])
            for k in sorted(extra_keys)
        },
    )
    fmts = {c.format for c in parts}
    return Converted(recording=rec, segments=tuple(segs), format=fmts.pop() if len(fmts) == 1 else "mixed")


def load_with_segments(path: str | os.PathLike, *, format: str = "auto", **options) -> Converted:
    """Read any supported source; returns the recording and its known-rotation segments.

    Parameters
    ----------
    path : path-like
        File or recording folder.
    format : str
        One of :data:`FORMATS`; ``auto`` uses :func:`detect_format`.
    **options
        Passed to the reader when it takes them: ``lsb_per_dps``, ``lsb_per_g``,
        ``rate_hz``, ``retime``, ``flip_gyro_x``, ``sections``, ``multi_id``. An option the
        chosen reader does not take is an error (so a flag is never silently ignored).
    """
    fmt = detect_format(path) if format == "auto" else format
    if fmt not in FORMATS:
        raise GyroInputError(f"unknown format {format!r}; choose one of {', '.join(FORMATS)}")
    readers: dict[str, Callable[..., Recording]] = {
        "blackbox": _read_blackbox,
        "dataflash": _read_dataflash,
        "ulog": read_ulog,
        "sunsided": read_sunsided,
        "tomisuarez2": read_tomisuarez2,
        "imucal": read_imucal,
        "imucal_annotated": read_imucal_annotated,
        "broad": read_broad,
        "imutk": read_imutk,
        "gnss_ins_sim": read_gnss_ins_sim,
        "fusion": read_fusion,
        "raw_dump": _read_raw_dump,
        "csv": read_csv,
        "parquet": read_parquet,
    }
    reader = readers[fmt]
    if fmt not in (
        "csv",
        "parquet",
    ):  # read_csv/read_parquet check memory themselves (and the CLI streams large CSV files)
        _check_convert_memory(Path(path), fmt)
    import inspect

    accepted = set(inspect.signature(reader).parameters) - {"path"}
    opts = {k: v for k, v in options.items() if v is not None}
    bad = sorted(set(opts) - accepted)
    if bad:
        flags = ", ".join("--" + b.replace("_", "-") for b in bad)
        raise GyroInputError(f"option {flags} does not apply to format {fmt}")
    rec = reader(path, **opts)
    segs: list[Segment] = []
    if fmt == "sunsided":
        segs = sunsided_segments(rec, _sunsided_dir(Path(path)))
    elif fmt == "tomisuarez2":
        segs = tomisuarez2_segments(rec, path)
    elif fmt in ("imucal", "imucal_annotated"):
        segs = imucal_segments(rec)
    return Converted(recording=rec, segments=tuple(segs), format=fmt)


def _read_blackbox(path: str | os.PathLike, *, log_index: int | None = None) -> Recording:
    """Betaflight blackbox log (all logs of the file as segments): :func:`gyrocore.readers.blackbox.read_blackbox`."""
    from .blackbox import read_blackbox

    return read_blackbox(path, log_index=log_index)


def _read_raw_dump(
    path: str | os.PathLike,
    *,
    lsb_per_dps: float | None = None,
    lsb_per_g: float | None = None,
    rate_hz: float | None = None,
) -> Recording:
    """Raw-count IMU dump (``gx,gy,gz``, ``GyX``, ``millis``, ...): :func:`gyrocore.readers.rawdump.read_raw_dump`."""
    from .rawdump import MPU6050_LSB_PER_DPS, MPU6050_LSB_PER_G, read_raw_dump

    return read_raw_dump(
        path,
        lsb_per_dps=lsb_per_dps or MPU6050_LSB_PER_DPS,
        lsb_per_g=lsb_per_g or MPU6050_LSB_PER_G,
        rate_hz=rate_hz,
    )


def _read_dataflash(path: str | os.PathLike, *, stream: str | None = None) -> Recording:
    """ArduPilot DataFlash log (IMU instance 0; ``stream`` imu or batch): :func:`gyrocore.readers.dataflash.read_dataflash`."""
    from .dataflash import read_dataflash

    return read_dataflash(path, stream=stream or "imu")


#: Blackbox: ~30 B of compressed log per frame become ~35 Python ints in a tuple (~1.3 kB)
#: before the float64 table: ≈ 50 bytes of memory per byte of log.
_BLACKBOX_BYTES_PER_BYTE = 50.0

#: Memory needed per byte of source file while converting (parsed float64 arrays, copies,
#: the Recording and the text written out): text ≈ 4 (a value takes ≥ 5 characters and ends
#: up in ≈ 3 float64 copies), binary (HDF5 / ULog) ≈ 6 (pyulog/h5py hold every topic/dataset).
_BYTES_PER_SOURCE_BYTE = {
    "ulog": 6.0,
    "broad": 6.0,
    "sunsided": 6.0,
    "blackbox": _BLACKBOX_BYTES_PER_BYTE,
    "dataflash": 6.0,
}


def _check_convert_memory(path: Path, fmt: str) -> None:
    """Refuse a conversion whose in-memory arrays would not fit comfortably."""
    from gyrocore.data import recording as _rc

    files = [f for f in path.iterdir() if f.is_file()] if path.is_dir() else [path]
    size = sum(f.stat().st_size for f in files)
    need = size * _BYTES_PER_SOURCE_BYTE.get(fmt, 4.0)
    avail = _rc._available_memory_bytes()
    if need > _rc.MEMORY_FRACTION * avail:
        raise GyroInputError(
            f"{path}: {size / 2**20:.0f} MiB of {fmt} data needs ~{need / 2**20:.0f} MiB to convert, more than "
            f"{_rc.MEMORY_FRACTION:.0%} of the {avail / 2**20:.0f} MiB available; split the recording first"
        )


def read_any(path: str | os.PathLike, *, columns: Sequence[str] | None = None) -> Recording:
    """A DESIGN.md data file (CSV or Parquet), or any set `gyroharness convert` reads (BROAD
    .hdf5, ULog, blackbox, a tomisuarez2/x-io CSV, a sunsided folder, ...).

    ``columns``: the column groups a data file is read for (see
    :func:`gyrocore.data.recording.read_csv`); another source is read whole by its reader."""
    if detect_format(path) in ("csv", "parquet"):
        return read_recording(path, columns=columns)
    return load_with_segments(path).recording


def load_any(path: str | os.PathLike, *, format: str = "auto", **options) -> Recording:
    """Read any supported source as a :class:`Recording` (see :func:`load_with_segments`)."""
    return load_with_segments(path, format=format, **options).recording
