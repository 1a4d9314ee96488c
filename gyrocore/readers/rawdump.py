"""A raw MPU-6050 (or any raw-count IMU) dump: a text table of integer counts, columns named the
way Arduino sketches and loggers name them (``gx,gy,gz``, ``GyX``, ``gyro_x``, ``AcX``,
``Tmp``, ``millis``), as a :class:`Recording`.

Counts are scaled by the datasheet sensitivity (MPU-6050 at power-up: 131 LSB/(°/s), 16384
LSB/g; ``--lsb-per-dps``/``--lsb-per-g`` for another range or part) — only when the values are
counts (integers, the accelerometer's magnitude at rest in the thousands); a table already in
physical units is refused with the column names a data file uses, never scaled. Time: a
``millis``/``micros`` column (Arduino ``millis()``/``micros()``, converted, with their 32-bit wrap
undone), a ``t_ms``/``t_us``/``t_s`` column, or ``--rate-hz`` (t = index / rate).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from gyrocore.data.checks import DEG, G0_M_S2
from gyrocore.data.recording import Recording
from gyrocore.errors import GyroInputError

from .common import _check_finite, _meta, _positive, _Repairs, _require_file

__all__ = ["read_raw_dump", "looks_like_raw_dump", "MPU6050_LSB_PER_DPS", "MPU6050_LSB_PER_G"]

MPU6050_LSB_PER_DPS = 131.0  # ±250 °/s, FS_SEL = 0 (the power-up range)
MPU6050_LSB_PER_G = 16384.0  # ±2 g, AFS_SEL = 0

#: Column names of each quantity (lower case, ``_``/space/``.`` removed), axis last.
_ALIASES = {
    "gyro": ("g{a}", "gy{a}", "gyr{a}", "gyro{a}", "w{a}", "gyroscope{a}", "rot{a}"),
    "accel": ("a{a}", "ac{a}", "acc{a}", "accel{a}", "accelerometer{a}"),
}
_TEMP = ("tmp", "temp", "temperature")
#: Time columns and their factor to seconds; ``millis``/``micros`` are Arduino's 32-bit counters.
_TIME = {"millis": 1e-3, "ms": 1e-3, "tms": 1e-3, "timems": 1e-3, "micros": 1e-6, "us": 1e-6, "tus": 1e-6, "ts": 1.0}
_WRAP = {"millis": 2.0**32, "micros": 2.0**32}
#: Time columns whose unit the name does not say: refused unless --rate-hz is given.
_TIME_NO_UNIT = ("t", "time", "timestamp", "stamp")


#: Units a header may give in brackets (``Gyro X (deg/s)``, ``time [ms]``), lower case, spaces
#: removed → (quantity, factor to SI).
_UNITS = {
    "rad/s": ("rate", 1.0),
    "rads": ("rate", 1.0),
    "deg/s": ("rate", DEG),
    "°/s": ("rate", DEG),
    "dps": ("rate", DEG),
    "degs": ("rate", DEG),
    "mdps": ("rate", DEG * 1e-3),
    "m/s^2": ("accel", 1.0),
    "m/s2": ("accel", 1.0),
    "m/s²": ("accel", 1.0),
    "ms^-2": ("accel", 1.0),
    "g": ("accel", G0_M_S2),
    "mg": ("accel", G0_M_S2 * 1e-3),
    "s": ("time", 1.0),
    "sec": ("time", 1.0),
    "ms": ("time", 1e-3),
    "us": ("time", 1e-6),
    "µs": ("time", 1e-6),
    "μs": ("time", 1e-6),
    "ns": ("time", 1e-9),
    "°c": ("temp", 1.0),
    "degc": ("temp", 1.0),
    "c": ("temp", 1.0),
}


def _split_unit(name: str) -> tuple[str, str | None]:
    """``'Gyro X (deg/s)'`` → (``'Gyro X'``, ``'deg/s'``); no bracketed unit → (name, None)."""
    m = re.match(r"^(.*?)\s*[\(\[]\s*([^\)\]]+?)\s*[\)\]]\s*$", name.strip().strip('"'))
    if not m:
        return name, None
    return m.group(1), m.group(2).replace(" ", "").lower()


def _key(name: str) -> str:
    return re.sub(r"[\s_.\-\"']", "", _split_unit(name)[0]).lower()


def _columns(header: list[str]) -> dict[str, list[int] | int]:
    """Indices of the gyro/accel triplets, temperature and time found in ``header``."""
    keys = [_key(h) for h in header]
    found: dict[str, list[int] | int] = {}
    for q, pats in _ALIASES.items():
        for pat in pats:
            idx = [keys.index(pat.format(a=a)) if pat.format(a=a) in keys else -1 for a in "xyz"]
            if all(i >= 0 for i in idx):
                found[q] = idx
                break
    for i, k in enumerate(keys):
        if k in _TEMP and "temp" not in found:
            found["temp"] = i
        unit = _split_unit(header[i])[1]
        timed = unit is not None and _UNITS.get(unit, ("",))[0] == "time"
        if (k in _TIME or (timed and k in _TIME_NO_UNIT)) and "time" not in found:
            found["time"] = i
        elif k in _TIME_NO_UNIT and "time_no_unit" not in found:
            found["time_no_unit"] = i
    return found


def _units_of(p: Path, header: list[str], idx: list[int], quantity: str) -> float | None:
    """The SI factor of a triplet whose names carry a unit (``(deg/s)``, ``[g]``), or None when
    none does (raw counts); one unit for the three, of the right quantity, else an error."""
    units = [_split_unit(header[i])[1] for i in idx]
    if all(u is None for u in units):
        return None
    names = [header[i] for i in idx]
    if any(u is None for u in units) or len(set(units)) > 1:
        raise GyroInputError(f"{p}: columns {names} give different units ({units}); give all three the same one")
    q, f = _UNITS.get(units[0], (None, 0.0))
    if q != quantity:
        raise GyroInputError(f"{p}: columns {names}: unit {units[0]!r} is not one this reader knows for {quantity}")
    return f


def _header_and_sep(path: Path) -> tuple[list[str], str | None, int]:
    """The header fields, the separator (None: whitespace) and the header's line index."""
    with open(path, encoding="utf-8-sig", errors="replace") as fh:
        for i, line in enumerate(fh):
            s = line.strip()
            if not s or s.startswith(("#", "%", "//")):
                continue
            for sep in (",", ";", "\t", None):
                fields = s.split(sep)
                if len(fields) >= 3:
                    return [f.strip() for f in fields], sep, i
            return [s], ",", i
    raise GyroInputError(f"{path}: empty file (raw dump)")


def looks_like_raw_dump(path: str | os.PathLike) -> bool:
    """A text table whose header names a gyro triplet the way a raw dump does (``gx``, ``GyX``,
    ...) and no DESIGN.md column (``t_s``, ``gyro_x_rad_s``)."""
    try:
        header, _, _ = _header_and_sep(Path(path))
    except (GyroInputError, OSError):
        return False
    if any(h.strip().strip('"') in ("t_s", "t_ms", "t_us", "t_ns", "gyro_x_rad_s", "gyro_x_deg_s") for h in header):
        return False
    return "gyro" in _columns(header)


def read_raw_dump(
    path: str | os.PathLike,
    *,
    lsb_per_dps: float = MPU6050_LSB_PER_DPS,
    lsb_per_g: float = MPU6050_LSB_PER_G,
    rate_hz: float | None = None,
) -> Recording:
    """Raw-count IMU dump (see the module docstring).

    Parameters
    ----------
    lsb_per_dps, lsb_per_g : float
        Sensitivities, LSB per °/s and per g (g = 9.80665 m/s²).
    rate_hz : float or None
        Sample rate, Hz, for a dump without a time column (t = index / rate); with one it is an
        error (the file's times are used).

    Raises
    ------
    GyroInputError
        No gyro triplet in the header, values that are not counts, no time and no rate, a
        text value (line and column named).
    """
    import pandas as pd

    p = Path(path)
    _require_file(p, "raw IMU dump")
    lsb_per_dps = _positive("--lsb-per-dps", lsb_per_dps)
    lsb_per_g = _positive("--lsb-per-g", lsb_per_g)
    header, sep, skip = _header_and_sep(p)
    cols = _columns(header)
    if "gyro" not in cols:
        raise GyroInputError(f"{p}: no gyro columns in the header {header[:8]} (gx,gy,gz / GyX,GyY,GyZ / gyro_x,...)")
    try:
        df = pd.read_csv(
            p,
            sep=sep if sep is not None else r"\s+",
            skiprows=skip,
            comment=None,
            encoding="utf-8-sig",
            skipinitialspace=True,
            on_bad_lines="error",
            engine="python" if sep is None else "c",
        )
    except (pd.errors.ParserError, UnicodeDecodeError, ValueError) as exc:
        raise GyroInputError(f"{p}: not a readable table ({str(exc).splitlines()[0][:120]})") from None
    repairs = _Repairs(p.name)
    data = {}
    for j, name in enumerate(df.columns):
        if j in _used(cols):
            v = pd.to_numeric(df[name], errors="coerce").to_numpy(dtype=float)
            bad = np.flatnonzero(np.isnan(v) & df[name].notna().to_numpy())
            if bad.size:
                raise GyroInputError(
                    f"{p}: line {skip + 2 + int(bad[0])}, column {name!r}: text in a number ({str(df[name].iloc[bad[0]])[:40]!r})"
                )
            data[j] = v
    gyro_c = np.column_stack([data[i] for i in cols["gyro"]])
    accel_c = np.column_stack([data[i] for i in cols["accel"]]) if "accel" in cols else None
    temp_c = data[cols["temp"]] if "temp" in cols else None
    g_si = _units_of(p, header, cols["gyro"], "rate")
    a_si = _units_of(p, header, cols["accel"], "accel") if "accel" in cols else None
    if g_si is None:  # raw counts: only counts are scaled by the sensitivities
        _check_counts(p, gyro_c, accel_c)
    elif "accel" in cols and a_si is None:
        raise GyroInputError(f"{p}: the gyro columns give a unit but the accel columns do not; give theirs too")
    t_raw = data[cols["time"]] if "time" in cols else None
    keep = _check_finite(
        p.name, {k: v for k, v in {"g": gyro_c, "a": accel_c, "t": t_raw}.items() if v is not None}, repairs
    )
    gyro = gyro_c[keep] * g_si if g_si is not None else gyro_c[keep] / lsb_per_dps * DEG
    if accel_c is None:
        accel = None
    else:
        accel = accel_c[keep] * a_si if a_si is not None else accel_c[keep] / lsb_per_g * G0_M_S2
    if temp_c is None:
        temp = None
    elif _split_unit(header[cols["temp"]])[1] is not None or g_si is not None:
        temp = temp_c[keep]  # a table in physical units: °C
    else:
        # MPU-6050 die temperature (register map §4.18): °C = count / 340 + 36.53
        temp = temp_c[keep] / 340.0 + 36.53
    if t_raw is None and "time_no_unit" in cols and rate_hz is None:
        name = header[cols["time_no_unit"]]
        raise GyroInputError(
            f"{p}: column {name!r} has no unit in its name: rename it millis, micros, t_ms, t_us or t_s, or give "
            f"--rate-hz to time the samples by their index instead"
        )
    if t_raw is not None:
        if rate_hz is not None:
            raise GyroInputError(f"{p}: the dump has a time column ({header[cols['time']]!r}); --rate-hz is not used")
        t_s, timing = _time(header[cols["time"]], t_raw[keep], repairs)
        up = np.concatenate([[True], np.diff(t_s) > 0])
        up &= t_s >= np.maximum.accumulate(t_s)  # a row behind an earlier time too
        if not up.all():
            repairs.add(f"dropped {int((~up).sum())} rows whose time repeats or goes backwards")
            t_s, gyro = t_s[up], gyro[up]
            accel = None if accel is None else accel[up]
            temp = None if temp is None else temp[up]
    else:
        if rate_hz is None:
            raise GyroInputError(
                f"{p}: raw dump without a time column (millis, micros, t_ms, ...): give its sample rate, "
                f"gyroharness convert {p} --rate-hz HZ -o OUT.csv"
            )
        rate_hz = _positive("--rate-hz", rate_hz)
        t_s = np.flatnonzero(keep) / rate_hz
        timing = f"no timestamps in file: t = index / {rate_hz:g} Hz"
    rate = (t_s.size - 1) / (t_s[-1] - t_s[0]) if t_s.size > 1 and t_s[-1] > t_s[0] else float(rate_hz or 0.0)
    meta = _meta(
        str(p),
        "raw_dump",
        "IMU table (units from its header)"
        if g_si is not None
        else "raw-count IMU dump (MPU-6050 scales unless given)",
        rate,
        repairs,
        scale=(
            "units from the header: "
            + ", ".join(
                str(_split_unit(header[i])[1])
                for i in [cols["gyro"][0]] + ([cols["accel"][0]] if "accel" in cols else [])
            )
            if g_si is not None
            else f"gyro {lsb_per_dps:g} LSB/(deg/s), accel {lsb_per_g:g} LSB/g (nominal, not calibrated)"
        ),
        timing=timing,
        columns=", ".join(
            f"{q}: {[header[i] for i in v] if isinstance(v, list) else header[v]}" for q, v in cols.items()
        ),
    )
    return Recording(t_s=t_s, gyro_rad_s=gyro, accel_m_s2=accel, temp_c=temp, meta=meta)


def _used(cols: dict) -> set[int]:
    out: set[int] = set()
    for v in cols.values():
        out.update(v if isinstance(v, list) else [v])
    return out


def _check_counts(p: Path, gyro: np.ndarray, accel: np.ndarray | None) -> None:
    """Refuse a table that is not raw counts: scaling physical units by 131 would be silently wrong."""
    fin = gyro[np.isfinite(gyro)]
    if fin.size and np.any(fin != np.round(fin)):
        raise GyroInputError(
            f"{p}: the gyro columns hold fractions, not raw counts: the dump is already in physical units; name "
            f"its columns as a data file does (t_s, gyro_x_deg_s or gyro_x_rad_s, ...: docs/data.md)"
        )
    if accel is not None:
        g = np.linalg.norm(accel[np.all(np.isfinite(accel), axis=1)], axis=1)
        if g.size and np.median(g) < 100.0:  # counts of any MEMS accel range are >= 1024 per g
            raise GyroInputError(
                f"{p}: the accel magnitude (median {np.median(g):.3g}) is not raw counts (thousands per g): the dump "
                f"is in physical units; name its columns as a data file does (docs/data.md)"
            )


def _time(name: str, t_raw: np.ndarray, repairs: _Repairs) -> tuple[np.ndarray, str]:
    """Seconds from the dump's time column; an Arduino counter's 32-bit wrap undone."""
    k = _key(name)
    unit = _split_unit(name)[1]
    if k not in _TIME:  # 'time (ms)': the unit in brackets
        t = t_raw.astype(float)
        f = _UNITS[unit][1]
        return (t - t[0]) * f, f"column {name!r} ({unit}), from its first value"
    t = t_raw.astype(float)
    wrap = _WRAP.get(k)
    if wrap is not None:
        jumps = np.flatnonzero(np.diff(t) < -wrap / 2)
        if jumps.size:
            t = t + np.concatenate([[0], np.cumsum(np.isin(np.arange(1, t.size), jumps + 1))]) * wrap
            repairs.add(f"{name}: {jumps.size} 32-bit counter wrap(s) undone")
    t_s = (t - t[0]) * _TIME[k]
    return (
        t_s,
        f"column {name!r} ({'ms' if _TIME[k] == 1e-3 else 'us' if _TIME[k] == 1e-6 else 's'}), from its first value",
    )
