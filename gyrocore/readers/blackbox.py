"""Betaflight / INAV / Cleanflight blackbox logs (.BBL/.BFL/.TXT) as the DESIGN.md data file.

What is ours and what is orangebox's
    Byte-level decoding (headers, field definitions, the variable-byte and tag encodings, the
    field predictors) is orangebox's (``orangebox==0.4.0``, pure Python; 0.5.0's wheel declares
    console scripts ``bb2csv = scripts/bb2csv`` without a callable, which pip refuses to
    install: "Invalid script entry point ... A callable suffix is required"). The frame loop is
    ours (:func:`_iter_frames`), because orangebox's own ``Parser.frames`` (a) accepts P frames
    before the first I frame and after a corrupt frame (their predictions start from garbage:
    the shared log's first three frames carry timestamps near 0), (b) raises ``TypeError`` when
    the data stops inside a frame (a truncated log), and (c) mis-sizes a group of TAG8_8SVB
    fields that ends the frame (``(count-1) - index``: one field short, and zero fields, an
    endless loop, for a single last field; atomgomba/orangebox#7). Our loop follows
    blackbox-log-viewer's rules: a P frame is only accepted while the stream is valid (an I
    frame has been read since the last corrupt frame), a frame must be followed by a valid
    frame marker, its ``loopIteration`` and ``time`` must move forward, and corrupt frames are
    skipped (resynchronised byte by byte) and counted. orangebox's stub decoders
    (``tag8_4s16`` of data version 1, ``tag2_3svariable``) return a string: a log whose fields
    need them is refused with one error line, never passed on.

What the firmware logged (read in the Betaflight source, tags v3.1.0 … 2026.6.1)
    * ``gyroADC[i]`` = ``lrintf(gyro.gyroADCf[i])``: the gyro after every software gyro filter,
      deg/s rounded to 1 °/s (×10 when ``blackbox_high_resolution`` = 1, 4.3+); the header's
      ``gyro_scale`` is ``1.0f`` in every Betaflight version from 3.1 (src/main/blackbox/blackbox.c).
    * ``debug[0..3]`` depends on ``debug_mode``, an index into ``debugType_e``
      (src/main/build/debug.h) whose list changes between releases
      (:data:`gyrocore.readers.blackbox_firmware.DEBUG_MODE_TABLES`, extracted from each tag). What
      the gyro debug modes hold (src/main/sensors/gyro.c, gyro_filter_impl.*):
      :func:`gyrocore.readers.blackbox_firmware.debug_gyro_meaning`. The header's firmware,
      rates and filter chain are read in :mod:`gyrocore.readers.blackbox_firmware`.
    * ``gyroUnfilt[i]`` (4.5+): the gyro before every software filter (same scale as gyroADC).
    * ``eRPM[i]`` (4.5+): eRPM/100 from bidirectional DShot; rotor Hz = eRPM·100/(poles/2)/60.
    * ``accSmooth[i]``: accelerometer in LSB, ``acc_1G`` LSB per g.
    * ``motor[i]``: motor command in the range ``motorOutput`` (low, high).
    * ``rcCommand[3]``: throttle, 1000–2000 (µs-like); written as unsigned ``throttle −
      minthrottle`` in 3.x, so a throttle below ``minthrottle`` wraps to ~4.29e9: read as a
      signed 32-bit value (a repair that is counted).
INAV 9.0.x (source read: :data:`gyrocore.readers.blackbox_firmware.INAV_READ`)
    * ``gyroADC[i]`` = ``lrintf(gyro.gyroADCf[i])``, deg/s after every gyro filter; ``gyroRaw[i]``
      = ``lrintf(gyro.gyroRaw[i])``, deg/s after zero calibration and alignment, before every
      software filter (sensors/gyro.c ``gyroUpdate``): the less-filtered gyro.
    * ``accSmooth[i]`` = ``lrintf(acc.accADCf[i] · acc_1G)``; ``motor[i]`` in ``motorOutput``;
      ``rcCommand[3]`` written as unsigned ``throttle − idle`` (same wrap as Betaflight 3.x).
    * ``looptime`` is the PID loop period; ``P interval`` is ``num/denom``; the end-of-log event
      carries "End of log (disarm reason:N)"; event 40 is an IMU failure.
    * Only some gyro filters are in the header (main LPF ``gyro_lpf_hz``, dynamic notch, RPM
      filter); the rest (anti-alias LPF, LULU, Kalman, …) are said to be missing in ``lacks``.
Cleanflight 2.4.0, 2.4.1, 2.5.0, 4.2.0, 4.2.2: read as the Betaflight release whose source they
equal (:data:`gyrocore.readers.blackbox_firmware.CLEANFLIGHT_AS_BETAFLIGHT`). Every other firmware/version is refused with one error
line naming it: its units and debug modes have not been read in its source here.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from gyrocore.errors import GyroInputError, warn_repair
from gyrocore.readers.blackbox_firmware import (
    INAV_READ,
    NEWEST_KNOWN,
    debug_gyro_meaning,
    debug_mode_name,
    firmware_info,
    gyro_filter_chain,
    inav_filter_chain,
    inav_loop_rates,
    loop_rates,
)

__all__ = [
    "BlackboxLog",
    "read_blackbox_logs",
    "read_blackbox",
    "ORANGEBOX_VERSION",
    "is_blackbox",
]

ORANGEBOX_VERSION = "0.4.0"
DEG = math.pi / 180.0
G0_M_S2 = 9.80665


# ============================================================================ frame loop
@dataclass(frozen=True)
class BlackboxLog:
    """One log of a blackbox file, decoded.

    Attributes
    ----------
    index : int
        1-based index of the log in the file.
    headers : dict
        Header values (orangebox's types: int, float, str or list).
    fields : tuple of str
        Main-frame field names.
    data : ndarray, shape (N, F)
        Main-frame values as logged (float64), accepted frames only.
    n_corrupt : int
        Frames (or byte runs) skipped as corrupt.
    n_unanchored : int
        P frames dropped because no valid I frame preceded them.
    truncated : bool
        The data stops inside a frame or without an end-of-log marker.
    ended : bool
        An "End of log" event was read.
    n_wrapped_throttle : int
        rcCommand[3] values read back as signed 32-bit (below minthrottle in 3.x).
    """

    index: int
    headers: dict
    fields: tuple[str, ...]
    data: np.ndarray
    n_corrupt: int
    n_unanchored: int
    truncated: bool
    ended: bool
    n_wrapped_throttle: int = 0

    def column(self, name: str) -> np.ndarray | None:
        try:
            return self.data[:, self.fields.index(name)]
        except ValueError:
            return None


def _tag8_8svb_fixed(data, ctx):
    """TAG8_8SVB with blackbox-log-viewer's group count (orangebox 0.4.0 is one short at the frame end)."""
    _signed_vb = _SIGNED_VB[0]
    fdefs = ctx.field_defs[ctx.frame_type]
    n = ctx.field_def_counts[ctx.frame_type]
    i0 = ctx.field_index
    j = i0 + 1
    while j < i0 + 8 and j < n and fdefs[j].encoding == 6:
        j += 1
    group = j - i0
    if group == 1:
        return _signed_vb(data, ctx)
    header = next(data)
    values = ()
    for _ in range(group):
        values += (_signed_vb(data, ctx) if header & 0x01 else 0,)
        header >>= 1
    return values


_STUB_ENCODINGS = {10: "tag2_3svariable"}
_SIGNED_VB: list = [None]  # orangebox.decoders._signed_vb, bound on first use (optional dependency)


_END_OF_LOG = b"End of log\x00"


#: INAV blackbox.c ``blackboxLogEvent(FLIGHT_LOG_EVENT_LOG_END)``: "End of log (disarm reason:%d)" and a 0 byte.
_INAV_END_OF_LOG = re.compile(rb"End of log \(disarm reason:-?\d+\)\x00")


def _read_event(reader, data: bytes, n: int, inav: bool = False) -> str:
    """Consume one event frame's payload (blackbox-log-viewer's ``parseEventFrame``).

    Events: 0 sync beep (time), 13 in-flight adjustment (function byte; a float when the
    function ≥ 128, else a signed VB), 14 logging resume (iteration, time), 15 disarm
    (reason), 30 flight mode (new, old flags), 255 end of log ("End of log\\0" follows).
    INAV (``inav``): 40 IMU failure (error code), and 255 is followed by "End of log (disarm
    reason:N)\\0" (blackbox.c / blackbox_fielddefs.h of the INAV source read, :data:`INAV_READ`).
    Returns "ok", "resume", "end" or "bad" (unknown event type or malformed end marker).
    orangebox 0.4.0 leaves the payload of events 13 and 14 unread (stubs) and has no 15.
    """
    from orangebox.decoders import _signed_vb, _unsigned_vb

    etype = next(reader)
    if etype is None:
        raise TypeError("end of data in an event")
    if etype == 255:
        p = reader.tell()
        if data[p : p + len(_END_OF_LOG)] == _END_OF_LOG:
            reader.seek(p + len(_END_OF_LOG))
            return "end"
        m = _INAV_END_OF_LOG.match(data, p, p + 64) if inav else None
        if m:
            reader.seek(m.end())
            return "end"
        return "bad"
    if etype == 40 and inav:  # INAV FLIGHT_LOG_EVENT_IMU_FAILURE: errorCode (unsigned VB)
        _unsigned_vb(reader)
        return "ok"
    if etype == 0 or etype == 15:
        _unsigned_vb(reader)
        return "ok"
    if etype == 13:
        func = next(reader)
        if func is None:
            raise TypeError("end of data in an event")
        if func > 127:
            for _ in range(4):
                next(reader)
        else:
            _signed_vb(reader)
        return "ok"
    if etype == 14:
        _unsigned_vb(reader)
        _unsigned_vb(reader)
        return "resume"
    if etype == 30:
        _unsigned_vb(reader)
        _unsigned_vb(reader)
        return "ok"
    return "bad"


# One piece on purpose: a byte-stream state machine over orangebox's frame decoder (the
# resynchronisation after a corrupt frame, the loop-iteration/time plausibility of each I/P frame
# and the predictor context share the loop's local state; split, they would pass it around).
def _iter_frames(parser, stats: dict) -> Iterator[tuple]:
    """Accepted main frames of the parser's current log (see the module docstring)."""
    from orangebox.types import Frame, FrameType

    reader = parser.reader
    ctx = parser._ctx
    fdefs = reader.field_defs
    valid_types = {ft.value for ft in FrameType}
    n = len(reader)
    data_bytes = reader._frame_data
    i_names = ctx._names_to_indices.get(FrameType.INTRA, {})
    it_idx = i_names.get("loopIteration")
    t_idx = i_names.get("time")
    stream_valid = False
    last_it = last_t = None
    i_interval = max(1, int(ctx.i_interval))
    inav = str(parser.headers.get("Firmware revision", "")).strip().upper().startswith("INAV")
    while True:
        pos = reader.tell()
        if pos >= n:
            stats["truncated"] = not stats["ended"]
            return
        b = data_bytes[pos]
        ch = chr(b)
        if ch not in valid_types:
            # resynchronise: skip to the next byte that can start a frame; one corrupt run
            stats["n_corrupt"] += 1
            stream_valid = False
            p = pos + 1
            while p < n and chr(data_bytes[p]) not in valid_types:
                p += 1
            reader.seek(p)
            continue
        ftype = FrameType(ch)
        reader.seek(pos + 1)
        try:
            if ftype == FrameType.EVENT:
                status = _read_event(reader, data_bytes, n, inav=inav)
                if status == "end":
                    stats["ended"] = True
                    stats["truncated"] = False
                    return
                if status == "bad":
                    stats["n_corrupt"] += 1
                    stream_valid = False
                    reader.seek(pos + 1)
                elif status == "resume":
                    stream_valid = False  # logging resumed after a pause: wait for an I frame
                continue
            if ftype not in fdefs:
                stats["n_corrupt"] += 1
                stream_valid = False
                continue
            ctx.frame_type = ftype
            frame = parser._parse_frame(fdefs[ftype], reader)
        except (TypeError, IndexError, StopIteration):
            # ran past the end of the data inside a frame: truncated (or a corrupt tail)
            if reader.tell() >= n or n - pos < 256:
                stats["truncated"] = True
                return
            stats["n_corrupt"] += 1
            stream_valid = False
            reader.seek(pos + 1)
            continue
        end = reader.tell()
        nxt_ok = end >= n or chr(data_bytes[end]) in valid_types
        if ftype in (FrameType.SLOW, FrameType.GPS, FrameType.GPS_HOME):
            if not nxt_ok:
                stats["n_corrupt"] += 1
                reader.seek(pos + 1)
                continue
            if ftype == FrameType.GPS_HOME:
                ctx.add_frame(frame)
            continue
        if not nxt_ok:
            stats["n_corrupt"] += 1
            stream_valid = False
            reader.seek(pos + 1)
            continue
        it = frame.data[it_idx] if it_idx is not None else None
        t = frame.data[t_idx] if t_idx is not None else None
        if ftype == FrameType.INTRA:
            ok = True
            if last_it is not None and it is not None and stream_valid:
                ok = (it > last_it) and (t is None or last_t is None or (0 < t - last_t < 10_000_000))
            if last_t is not None and t is not None and t <= last_t:
                ok = False
            if not ok:
                stats["n_corrupt"] += 1
                stream_valid = False
                continue
            stream_valid = True
        else:  # INTER
            if not stream_valid:
                stats["n_unanchored"] += 1
                continue
            ok = (it is None or last_it is None or 0 < it - last_it <= i_interval) and (
                t is None or last_t is None or 0 < t - last_t < 1_000_000
            )
            if not ok:
                stats["n_corrupt"] += 1
                stream_valid = False
                continue
        ctx.add_frame(Frame(ftype, frame.data))
        ctx.last_iter = it if it is not None else ctx.last_iter
        last_it, last_t = it, t
        yield frame.data


def _open_parser(path: Path):
    logging.getLogger("orangebox").setLevel(logging.ERROR)
    try:
        from orangebox import Parser
        from orangebox.decoders import _signed_vb

        _SIGNED_VB[0] = _signed_vb
    except ImportError:  # pragma: no cover - dependency declared in pyproject
        raise GyroInputError("reading blackbox logs needs orangebox (pip install orangebox==0.4.0)") from None
    try:
        return Parser.load(str(path))
    except Exception as exc:  # orangebox raises RuntimeError/InvalidHeaderException/UnicodeDecodeError
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise GyroInputError(f"{path}: not a readable blackbox log ({type(exc).__name__}: {msg})") from None


def read_blackbox_logs(path: str | os.PathLike, *, log_index: int | None = None) -> list[BlackboxLog]:
    """Decode every log in a blackbox file (or the 1-based ``log_index`` one).

    Raises
    ------
    GyroInputError
        Not a blackbox file, an unknown data version, a field whose encoding orangebox
        0.4.0 only stubs, or no complete main frame.
    """
    p = Path(path)
    if not p.exists():
        raise GyroInputError(f"{p}: no such file")
    with open(p, "rb") as fh:
        head = fh.read(64)
    if not head.startswith(b"H Product:Blackbox"):
        raise GyroInputError(f"{p}: not a blackbox log (no 'H Product:Blackbox' header)")
    parser = _open_parser(p)
    count = parser.reader.log_count
    indices = range(1, count + 1) if log_index is None else [int(log_index)]
    logs = []
    for li in indices:
        if not 1 <= li <= count:
            raise GyroInputError(f"{p}: log {li} requested, the file holds {count}")
        try:
            parser.set_log_index(li)
        except Exception as exc:
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            if log_index is None and count > 1:
                # one damaged log of a multi-log file (a dump cut inside a header): the others are read
                warn_repair(f"{p.name}: log {li} of {count}: header cut off or unreadable ({msg}); skipped")
                continue
            raise GyroInputError(f"{p}: log {li}: unreadable header ({msg})") from None
        hdr = parser.headers
        if hdr.get("Data version") not in (1, 2):
            raise GyroInputError(
                f"{p}: log {li}: blackbox data version {hdr.get('Data version')!r} is not one this reader knows (1, 2)"
            )
        fdefs = parser.reader.field_defs
        for ft, defs in fdefs.items():
            for d in defs:
                if d.encoding in _STUB_ENCODINGS or (d.encoding == 8 and hdr.get("Data version") < 2):
                    enc = _STUB_ENCODINGS.get(d.encoding, "tag8_4s16 (data version 1)")
                    raise GyroInputError(
                        f"{p}: log {li}: field {d.name} uses encoding {enc}, which orangebox 0.4.0 does not decode"
                    )
                if d.encoding == 6:
                    d.decoderfun = _tag8_8svb_fixed
        from orangebox.types import FrameType

        if FrameType.INTRA not in fdefs or FrameType.INTER not in fdefs:
            if log_index is None and count > 1:
                warn_repair(
                    f"{p.name}: log {li} of {count}: header has no main-frame field definitions (cut off?); skipped"
                )
                continue
            raise GyroInputError(f"{p}: log {li}: header has no main-frame field definitions (truncated header?)")
        names = tuple(d.name for d in fdefs[FrameType.INTRA])
        stats = {"n_corrupt": 0, "n_unanchored": 0, "truncated": False, "ended": False}
        rows = list(_iter_frames(parser, stats))
        arr = np.array(rows, dtype=float) if rows else np.empty((0, len(names)))
        wrapped = 0
        if "rcCommand[3]" in names and arr.size:
            j = names.index("rcCommand[3]")
            big = arr[:, j] >= 2.0**31
            wrapped = int(big.sum())
            arr[big, j] -= 2.0**32
        logs.append(
            BlackboxLog(
                index=li,
                headers=hdr,
                fields=names,
                data=arr,
                n_corrupt=stats["n_corrupt"],
                n_unanchored=stats["n_unanchored"],
                truncated=bool(stats["truncated"]),
                ended=bool(stats["ended"]),
                n_wrapped_throttle=wrapped,
            )
        )
    return logs


def is_blackbox(path: str | os.PathLike) -> bool:
    """True when the file starts with a blackbox header line."""
    try:
        with open(path, "rb") as fh:
            return fh.read(18) == b"H Product:Blackbox"
    except OSError:
        return False


# ============================================================================ to a Recording
def _float_header(v) -> float:
    """``gyro_scale`` is logged as the hex of a float's bits (0x3f800000 = 1.0); orangebox casts it to int."""
    if isinstance(v, str) and v.startswith("0x"):
        v = int(v, 16)
    if isinstance(v, int):
        return struct.unpack("<f", struct.pack("<I", v & 0xFFFFFFFF))[0]
    return float(v)


def _triplet(log: BlackboxLog, stem: str) -> np.ndarray | None:
    cols = [log.column(f"{stem}[{i}]") for i in range(3)]
    return None if any(c is None for c in cols) else np.column_stack(cols)


def _indexed(log: BlackboxLog, pattern: str) -> list[tuple[int, np.ndarray]]:
    rx = re.compile(pattern)
    out = []
    for k, name in enumerate(log.fields):
        m = rx.fullmatch(name)
        if m:
            out.append((int(m.group(1)), log.data[:, k]))
    return sorted(out, key=lambda x: x[0])


@dataclass
class _LogConversion:
    t_us: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray | None
    extra: dict
    meta: dict
    lacks: list
    notes: list


def _prefilter_gyro(
    log: BlackboxLog, rows, fw, chain, dmode_idx, dname, gyro_div: float, extra: dict, lacks: list
) -> dict:
    """The less-filtered gyro (INAV gyroRaw, Betaflight 4.5+ gyroUnfilt, or a debug mode that
    carries it) into ``extra`` as ``gyro_prefilter_*_rad_s``; returns what it is (metadata
    ``gyro_prefilter``), ``{}`` when the log has none (then a ``lacks`` entry says why)."""
    inav = fw.name == "inav"
    unf = _triplet(log, "gyroUnfilt")
    raw_inav = _triplet(log, "gyroRaw") if inav else None
    pre_meta = {}
    if inav:
        # INAV blackbox.c loadMainState: gyroRaw[i] = lrintf(gyro.gyroRaw[i]); sensors/gyro.c gyroUpdate:
        # gyro.gyroRaw = deg/s after zero calibration and sensor/board alignment, before the anti-alias
        # LPF and every later filter ("unfiltered gyro value [deg/s]"). Logged when the blackbox
        # include flag GYRO_RAW is set (FLIGHT_LOG_FIELD_CONDITION_GYRO_RAW).
        if raw_inav is not None:
            extra.update({f"gyro_prefilter_{ax}_rad_s": raw_inav[rows, i] * DEG for i, ax in enumerate("xyz")})
            pre_meta = {
                "source": f"gyroRaw[0..2] (INAV {fw.version_str}: gyro before every software filter, "
                "sensors/gyro.c gyroUpdate); rounded to 1 deg/s by lrintf",
                "signal": "raw",
                "filters_before": [],
            }
        else:
            lacks.append("no unfiltered gyro: INAV logs gyroRaw only with the blackbox GYRO_RAW field enabled")
    elif unf is not None:
        extra.update({f"gyro_prefilter_{ax}_rad_s": unf[rows, i] / gyro_div * DEG for i, ax in enumerate("xyz")})
        pre_meta = {
            "source": "gyroUnfilt[0..2] (4.5+: gyro before every software filter)",
            "signal": "raw",
            "filters_before": [],
        }
    else:
        dbg = _triplet(log, "debug")
        meaning = debug_gyro_meaning(fw, dname, chain) if dname else None
        if dbg is not None and meaning is not None:
            extra.update({f"gyro_prefilter_{ax}_rad_s": dbg[rows, i] * DEG for i, ax in enumerate("xyz")})
            pre_meta = {
                "source": f"debug[0..2], debug_mode {dmode_idx} = DEBUG_{meaning.mode} in {fw.label} ({meaning.source}); "
                f"rounded to 1 deg/s by lrintf",
                "signal": meaning.kind,
                "filters_before": [chain[i].to_dict() for i in meaning.before],
            }
        else:
            what = (
                f"DEBUG_{dname}"
                if dname
                else ("an index not mapped for this version" if isinstance(dmode_idx, int) else "not in the header")
            )
            lacks.append(
                f"no unfiltered gyro: debug_mode {dmode_idx} is {what} (log with debug_mode GYRO_SCALED, or 4.5+ gyroUnfilt)"
            )
    return pre_meta


def _motor_columns(
    log: BlackboxLog, rows, hdr, fw, dname, dmode_idx, extra: dict, meta: dict, lacks: list
) -> tuple[float, float]:
    """Motor outputs, throttle, eRPM / rotor frequency into ``extra`` (what is missing into
    ``lacks``); returns the header's motorOutput range (lo, hi)."""
    inav = fw.name == "inav"
    mot = _indexed(log, r"motor\[(\d+)\]")
    lo_hi = hdr.get("motorOutput", [0, 0])
    lo, hi = (
        (float(lo_hi[0]), float(lo_hi[1]))
        if isinstance(lo_hi, list) and len(lo_hi) == 2
        else (float("nan"), float("nan"))
    )
    if mot:
        for i, col in mot:
            extra[f"motor_{i}"] = col[rows]
            if hi > lo:
                extra[f"motor_cmd_{i}"] = (col[rows] - lo) / (hi - lo)
        if hi > lo:
            extra["motor_cmd_mean"] = np.mean([extra[f"motor_cmd_{i}"] for i, _ in mot], axis=0)
    else:
        lacks.append("no motor outputs (motor[i] fields disabled)")
    thr = log.column("rcCommand[3]")
    if thr is not None:
        extra["rc_throttle"] = thr[rows]
        extra["throttle"] = np.clip((thr[rows] - 1000.0) / 1000.0, 0.0, 1.0)
    else:
        lacks.append("no throttle (rcCommand[3] missing)")
    erpm = _indexed(log, r"eRPM(?:\(/100\))?\[(\d+)\]")
    poles = hdr.get("motor_poles")
    if erpm:
        for i, col in erpm:
            extra[f"erpm100_{i}"] = col[rows]
            if isinstance(poles, int) and poles > 0:
                extra[f"rotor_hz_{i}"] = col[rows] * 100.0 / (poles / 2.0) / 60.0
        if not (isinstance(poles, int) and poles > 0):
            lacks.append("eRPM logged but no motor_poles in the header: rotor speed in Hz unknown")
    elif dname == "RPM_FILTER" and fw.version >= (4, 0, 0) and _triplet(log, "debug") is not None:
        # 4.0-2026.6 rpm_filter.c: DEBUG_SET(DEBUG_RPM_FILTER, motor, motorFrequency[Hz][motor]) for
        # motors 0..3: the PT1-smoothed rotor frequency (erpmToHz = 100/60/(poles/2)), integer Hz
        for i in range(4):
            col = log.column(f"debug[{i}]")
            if col is not None:
                extra[f"rotor_hz_{i}"] = col[rows].astype(float)
        meta["rotor_hz_source"] = (
            f"debug[0..3], debug_mode {dmode_idx} = DEBUG_RPM_FILTER in {fw.label}: "
            "rotor frequency per motor, Hz (PT1-smoothed eRPM telemetry, rounded)"
        )
    elif inav:
        lacks.append("no eRPM per motor (INAV logs one escRPM value in slow frames only): line laws from throttle only")
    else:
        lacks.append(
            "no eRPM (fields need bidirectional DShot and Betaflight 4.5+, or debug_mode RPM_FILTER in 4.0+): "
            "line laws from throttle only"
        )
    return lo, hi


def _log_meta(
    hdr,
    fw,
    rates,
    chain,
    *,
    log_hz: float,
    loop_hz_meas: float,
    dmode_idx,
    dname,
    hires: bool,
    full: float,
    sat_n: int,
    lo: float,
    hi: float,
) -> dict:
    """The recording metadata of one converted log (firmware, rates, filter chain, units check)."""
    inav = fw.name == "inav"
    return {
        "firmware": fw.revision,
        "firmware_version": fw.release_str,
        "betaflight_equivalent_version": "" if inav else fw.version_str,
        "blackbox_data_version": str(fw.data_version),
        "craft_name": str(hdr.get("Craft name", "")),
        "gyro_rate_hz": f"{rates['gyro_hz']:.6g}",
        "pid_rate_hz": f"{rates['pid_hz']:.6g}",
        "gyro_filter_rate_hz": f"{rates['filter_hz']:.6g}",
        "log_rate_nominal_hz": f"{rates['log_hz_nominal']:.6g}",
        "log_rate_measured_hz": f"{log_hz:.6g}",
        "loop_rate_measured_hz": f"{loop_hz_meas:.6g}",
        "gyro_filters": json.dumps([s.to_dict() for s in chain]),
        "gyro_signal": "filtered (gyroADC: after every software gyro filter listed in gyro_filters)",
        "debug_mode": (
            f"{dmode_idx} (INAV debug list not mapped: gyroRaw carries the unfiltered gyro)"
            if inav
            else f"{dmode_idx} = {('DEBUG_' + dname) if dname else 'unmapped'}"
        ),
        "gyro_units_check": (
            f"gyroADC logged in deg/s (gyro_scale 1.0{', high resolution x10' if hires else ''}"
            f"{'; INAV blackbox.c: lrintf(gyro.gyroADCf), deg/s' if inav else ''}); max |gyro| "
            f"{full:.0f} deg/s, {sat_n} samples at the +-2000 deg/s full scale"
        ),
        "firmware_name": fw.name,
        "firmware_source_read": (
            INAV_READ[fw.version[:2]]
            if inav
            else (
                "cleanflight/cleanflight commits of that version (version.h), matched to "
                if fw.name == "cleanflight"
                else ""
            )
            + "betaflight/betaflight tags v3.1.0-2026.6.1: build/debug.h, blackbox/blackbox.c, sensors/gyro*.c"
        ),
        "motor_output_range": f"{lo:g},{hi:g}",
        "header_filters": json.dumps(
            {
                k: v
                for k, v in hdr.items()
                if re.match(
                    r"(gyro_|dyn_|rpm_|dterm_|dshot_bidir|motor_poles|looptime|pid_process_denom|P interval|I interval|debug_mode|blackbox_high|dynamicGyroNotch)",
                    k,
                )
            }
        ),
    }


def _convert_log(log: BlackboxLog, src: str) -> _LogConversion:
    """One decoded log → SI arrays, extra columns and metadata (see :func:`read_blackbox`)."""
    hdr = log.headers
    fw = firmware_info(hdr, f"{src} log {log.index}")
    inav = fw.name == "inav"
    if not inav and fw.version > NEWEST_KNOWN:
        raise GyroInputError(
            f"{src}: Betaflight {fw.version_str} is newer than the newest release read here (2026.6); "
            f"its field meanings were not checked"
        )
    gscale = _float_header(hdr.get("gyro_scale", "0x3f800000"))
    if not math.isclose(gscale, 1.0, rel_tol=1e-6):
        raise GyroInputError(f"{src}: gyro_scale {gscale:g} ≠ 1.0: not the deg/s gyroADC of Betaflight 3.1+")
    hires = bool(hdr.get("blackbox_high_resolution", 0)) and not inav
    gyro_div = 10.0 if hires else 1.0
    lacks: list[str] = []
    notes: list[str] = []
    if log.data.shape[0] < 2:
        raise GyroInputError(f"{src}: log {log.index} holds {log.data.shape[0]} complete main frames")
    t_us = log.column("time")
    g = _triplet(log, "gyroADC")
    if t_us is None or g is None:
        raise GyroInputError(f"{src}: log {log.index} has no time/gyroADC fields")
    # strictly increasing time (the frame loop already rejects backwards frames)
    keep = np.concatenate([[True], np.diff(t_us) > 0])
    rows = np.nonzero(keep)[0]
    t_us = t_us[rows]
    gyro_deg_s = g[rows] / gyro_div
    it = log.column("loopIteration")
    dt = np.diff(t_us) * 1e-6
    log_hz = 1.0 / float(np.median(dt))
    # loop rate as it ran: logged iterations per second (the gyro clock differs from the nominal)
    if it is not None and rows.size > 1:
        di = np.diff(it[rows])
        ok = di > 0
        loop_hz_meas = float(np.sum(di[ok]) / np.sum(dt[ok])) if ok.any() else float("nan")
    else:
        loop_hz_meas = float("nan")
    where = f"{Path(src).name}: log {log.index}: "
    rates = (
        inav_loop_rates(hdr, measured_loop_hz=loop_hz_meas, where=where)
        if inav
        else loop_rates(hdr, fw, measured_loop_hz=loop_hz_meas, where=where)
    )
    chain = inav_filter_chain(hdr, rates) if inav else gyro_filter_chain(hdr, fw, rates)
    # unit check on the data: full scale and still part
    full = float(np.max(np.abs(gyro_deg_s)))
    if full > 4100:
        raise GyroInputError(
            f"{src}: |gyroADC| reaches {full:.0f} after scaling: not deg/s (largest MEMS full scale ±4000 °/s)"
        )
    sat_n = int(np.sum(np.abs(gyro_deg_s) >= 1990)) if full < 2100 else int(np.sum(np.abs(gyro_deg_s) >= 0.995 * full))
    extra: dict[str, np.ndarray] = {}
    meta: dict[str, str] = {}
    # accelerometer
    a = _triplet(log, "accSmooth")
    acc_1g = hdr.get("acc_1G")
    accel = None
    if a is not None and isinstance(acc_1g, (int, float)) and acc_1g > 0:
        accel = a[rows] / float(acc_1g) * G0_M_S2
    else:
        lacks.append("no accelerometer (accSmooth or acc_1G missing)")
    # debug gyro / gyroUnfilt
    dmode_idx = hdr.get("debug_mode")
    dname = debug_mode_name(fw.version, int(dmode_idx)) if isinstance(dmode_idx, int) and not inav else None
    pre_meta = _prefilter_gyro(log, rows, fw, chain, dmode_idx, dname, gyro_div, extra, lacks)
    lo, hi = _motor_columns(log, rows, hdr, fw, dname, dmode_idx, extra, meta, lacks)
    nyq = log_hz / 2.0
    runs = (
        f"gyro runs at {rates['gyro_hz']:.0f} Hz"
        if math.isfinite(rates["gyro_hz"])
        else f"PID loop at {rates['pid_hz']:.0f} Hz, gyro sampling rate not in the header"
    )
    lacks.append(
        f"logged at {log_hz:.0f} Hz: content above its Nyquist {nyq:.0f} Hz ({runs}, "
        f"decimated without anti-alias filter) folds into the band"
    )
    if inav:
        lacks.append(
            "INAV header lacks filters that gyroADC has been through (anti-alias PT1 gyro_anti_aliasing_lpf_hz at "
            "the gyro rate, LULU, dynamic and secondary dynamic notches, Kalman, the main LPF mode/adaptive "
            "cutoff): gyro_filters lists the logged ones only"
        )
    if log.truncated:
        notes.append(
            "log ends inside a frame or without an end-of-log marker (flash full or power cut): complete frames kept"
        )
    meta.update(
        _log_meta(
            hdr,
            fw,
            rates,
            chain,
            log_hz=log_hz,
            loop_hz_meas=loop_hz_meas,
            dmode_idx=dmode_idx,
            dname=dname,
            hires=hires,
            full=full,
            sat_n=sat_n,
            lo=lo,
            hi=hi,
        )
    )
    if pre_meta:
        meta["gyro_prefilter"] = json.dumps(pre_meta)
    if sat_n:
        notes.append(f"{sat_n} gyro samples at full scale (saturated during flips)")
    return _LogConversion(
        t_us=t_us, gyro=gyro_deg_s * DEG, accel=accel, extra=extra, meta=meta, lacks=lacks, notes=notes
    )


def read_blackbox(path: str | os.PathLike, *, log_index: int | None = None):
    """A blackbox file as one :class:`~gyrocore.data.recording.Recording`; several logs become segments.

    Columns: ``gyro_*_rad_s`` = gyroADC (what the flight controller flew on); accel from
    accSmooth/acc_1G; extra: ``gyro_prefilter_*_rad_s`` (the less-filtered gyro where the
    debug mode or gyroUnfilt carries it; metadata ``gyro_prefilter`` says what it is),
    ``motor_i`` (as logged), ``motor_cmd_i`` (0–1 of motorOutput), ``motor_cmd_mean``,
    ``rc_throttle`` (1000–2000), ``throttle`` (0–1), ``erpm100_i`` / ``rotor_hz_i`` (4.5+),
    ``log_index`` (1-based log of the file). ``t_s`` is seconds from the first frame of the
    first log; later logs follow after a gap of one logged interval (each log's own clock
    restarts at power-up), their spans listed in metadata ``logs``.

    Warnings (one line each): truncated log, corrupt frames skipped, wrapped throttle values.
    Metadata ``lacks``: what the log lacks for vibration and filter work.
    """
    from gyrocore.data.recording import Recording

    p = Path(path)
    logs = read_blackbox_logs(p, log_index=log_index)
    convs, spans = [], []
    for lg in logs:
        if lg.data.shape[0] < 2:
            warn_repair(f"{p.name}: log {lg.index} has {lg.data.shape[0]} complete main frames; skipped")
            continue
        convs.append((lg, _convert_log(lg, p.name)))
    if not convs:
        raise GyroInputError(f"{p}: no log with complete main frames")
    t_parts, g_parts, a_parts, idx_parts = [], [], [], []
    extras: dict[str, list] = {}
    t_next = 0.0
    for lg, c in convs:
        t = (c.t_us - c.t_us[0]) * 1e-6 + t_next
        spans.append(
            {
                "log": lg.index,
                "t_start_s": float(t[0]),
                "t_end_s": float(t[-1]),
                "frames": int(t.size),
                "corrupt_skipped": lg.n_corrupt,
                "unanchored_p_frames": lg.n_unanchored,
                "truncated": lg.truncated,
                "firmware": c.meta["firmware"],
                "time_us_first": int(c.t_us[0]),
            }
        )
        t_parts.append(t)
        g_parts.append(c.gyro)
        a_parts.append(c.accel)
        idx_parts.append(np.full(t.size, float(lg.index)))
        med = float(np.median(np.diff(t)))
        t_next = float(t[-1]) + med
        msgs = []
        if lg.truncated:
            msgs.append(f"log {lg.index} is truncated (no end-of-log marker): {t.size} complete frames kept")
        if lg.n_corrupt:
            msgs.append(f"log {lg.index}: {lg.n_corrupt} corrupt frame(s) skipped")
        if lg.n_wrapped_throttle:
            msgs.append(f"log {lg.index}: {lg.n_wrapped_throttle} rcCommand[3] values below minthrottle read as signed")
        if not np.any(c.gyro):
            # INAV 9.0.1's ground logs (PROVENANCE): gyroADC 0 in every frame, gyroRaw not; kept as logged
            pre = [
                k
                for k in ("gyro_prefilter_x_rad_s", "gyro_prefilter_y_rad_s", "gyro_prefilter_z_rad_s")
                if k in c.extra
            ]
            alive = bool(pre) and any(np.any(c.extra[k]) for k in pre)
            msgs.append(
                f"log {lg.index}: gyroADC is 0 in every frame (the field logged nothing): the gyro columns of this log "
                f"are zero" + ("; gyro_prefilter_x/y/z_rad_s hold the logged unfiltered gyro" if alive else "")
            )
        for m in msgs:
            warn_repair(f"{p.name}: {m}")
    keys = set.intersection(*(set(c.extra) for _, c in convs))
    dropped = set.union(*(set(c.extra) for _, c in convs)) - keys
    for k in sorted(keys):
        extras[k] = np.concatenate([c.extra[k] for _, c in convs])
    if len(convs) > 1:
        extras["log_index"] = np.concatenate(idx_parts)
    accel = None if any(a is None for a in a_parts) else np.concatenate(a_parts)
    first = convs[0][1]
    meta = {
        "source": str(p),
        "format": "blackbox",
        "sensor": f"{first.meta['firmware']} gyro ({first.meta['craft_name'] or 'craft unnamed'})",
        "rate_hz": first.meta["log_rate_measured_hz"],
        "units": "SI (rad/s, m/s^2, s); motor/throttle columns as logged",
        "frame": "Betaflight body axes as logged (roll, pitch, yaw rates)",
        "parser": f"orangebox {ORANGEBOX_VERSION} decoders + gyrocore frame validation",
    }
    meta.update(first.meta)
    if len(convs) > 1:
        meta["segments"] = "several logs: column log_index, spans in 'logs'"
        for k in ("gyro_filters", "header_filters", "gyro_prefilter", "debug_mode", "log_rate_nominal_hz"):
            vals = {c.meta.get(k) for _, c in convs}
            if len(vals) > 1:
                meta[k + "_per_log"] = json.dumps({lg.index: c.meta.get(k) for lg, c in convs})
    meta["logs"] = json.dumps(spans)
    lacks = list(dict.fromkeys(sum((c.lacks for _, c in convs), [])))
    if dropped:
        lacks.append(f"columns not in every log, left out: {', '.join(sorted(dropped))}")
    meta["lacks"] = " | ".join(lacks) if lacks else "nothing for vibration work"
    notes = list(dict.fromkeys(sum((c.notes for _, c in convs), [])))
    meta["repairs"] = "; ".join(notes) if notes else "none"
    return Recording(
        t_s=np.concatenate(t_parts), gyro_rad_s=np.concatenate(g_parts), accel_m_s2=accel, meta=meta, extra=extras
    )
