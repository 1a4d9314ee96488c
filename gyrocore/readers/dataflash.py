"""ArduPilot DataFlash logs (.bin) as the DESIGN.md data file (pymavlink's DFReader decodes).

What is read, and from where
    * Decoding is pymavlink's (``pymavlink.DFReader.DFReader_binary``); the format is described
      inside the log itself: FMT messages give each message's fields, FMTU/UNIT/MULT their units.
      The units are checked per log on those: the IMU gyro must be ``rad/s`` and the accelerometer
      ``m/s/s`` (a log without FMTU units is refused with one error line).
    * ``IMU`` (instance ``I``) is written by ArduPilot's ``AP_Logger::Write_IMU_instance`` with
      ``ins.get_gyro(i)`` / ``ins.get_accel(i)``: the gyro the controllers use, after the
      INS_GYRO_FILTER low-pass and the harmonic notches; body frame x forward, y right, z down.
      It is logged at the logger's IMU rate (25 Hz in the log tested), far below the motor lines.
    * ``INS_GYRO_FILTER`` is a 2nd-order Butterworth low-pass (``DigitalBiquadFilter::
      compute_params``, libraries/Filter/LowPassFilter2p.cpp: bilinear, c = 1 + 2cos(π/4)Ω + Ω²)
      at the gyro sample rate (``IMU.GHz``); the harmonic notch (``INS_HNTCH_*``, ``INS_HNTC2_*``)
      moves with throttle/RPM/FFT: listed as dynamic.
    * ``RCOU`` C1…Cn: motor PWM in µs (n from FRAME_CLASS), normalised by MOT_PWM_MIN/MAX;
      ``CTUN.ThO``: throttle output 0–1. Both held to the IMU times (zero-order hold).
    * The batch sampler (``ISBH``/``ISBD``: windows of ``smp_cnt`` raw samples at ``smp_rate``,
      int16 ``multiplier · sample``, AP_InertialSensor/BatchSampler.cpp) is the gyro before the
      filters at the sensor rate: ``stream="batch"`` (``convert --stream batch``) gives those
      windows, with gaps between them, as the recording (:func:`_batch_recording`).
Tested on one real log (ArduCopter 4.5.7, CubeOrangePlus; PROVENANCE in tests/data/dataflash).
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
from pathlib import Path

import numpy as np

from gyrocore.errors import GyroInputError, warn_repair

__all__ = ["read_dataflash", "is_dataflash"]

#: DataFlash binary message header (0xA3 0x95) followed by the FMT message id (128).
DATAFLASH_MAGIC = b"\xa3\x95\x80"
#: Motors per ArduPilot FRAME_CLASS (AP_Motors: 1 quad, 2 hexa, 3 octa, 4 octaquad, 5 Y6, 7 tri).
FRAME_CLASS_MOTORS = {1: 4, 2: 6, 3: 8, 4: 8, 5: 6, 7: 3}
_FW = re.compile(r"^(Ardu\w+|ArduPilot)\s+V(\d+)\.(\d+)\.(\d+)")


def is_dataflash(path: str | os.PathLike) -> bool:
    """True when the file starts with a DataFlash FMT message."""
    try:
        with open(path, "rb") as fh:
            return fh.read(3) == DATAFLASH_MAGIC
    except OSError:
        return False


def _hold(t_src: np.ndarray, v_src: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Zero-order hold of samples (t_src, v_src) at times t (NaN before the first sample)."""
    j = np.searchsorted(t_src, t, side="right") - 1
    out = np.full((t.size,) + v_src.shape[1:], np.nan)
    ok = j >= 0
    out[ok] = v_src[j[ok]]
    return out


@contextlib.contextmanager
def _captured_output():
    """Capture what pymavlink prints, at the Python and the file-descriptor level (its Cython
    indexer, dfindexer_cy, writes "bad header" lines from C): yields a StringIO filled on exit."""
    import sys
    import tempfile

    out = io.StringIO()
    for s in (sys.stdout, sys.stderr):
        try:
            s.flush()
        except Exception:  # noqa: BLE001
            pass
    saved = []
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        try:
            for fd in (1, 2):
                saved.append((fd, os.dup(fd)))
                os.dup2(tmp.fileno(), fd)
        except OSError:  # no real descriptors (embedded use): Python-level capture only
            for fd, dup in saved:
                os.dup2(dup, fd)
                os.close(dup)
            saved = []
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
                yield out
        finally:
            for fd, dup in saved:
                os.dup2(dup, fd)
                os.close(dup)
            tmp.seek(0)
            out.write(tmp.read().decode(errors="replace"))


def _bytes_after_last_message(log, size: int) -> int:
    """Bytes after the end of the last complete message (pymavlink's index of message offsets)."""
    try:
        ends = [
            o + log.formats[t].len for t, offs in enumerate(log.offsets) if offs and t in log.formats for o in offs[-2:]
        ]
    except Exception:  # noqa: BLE001 - index layout differs: no truncation check
        return 0
    ok = [e for e in ends if e <= size]
    return size - max(ok) if ok else 0


def read_dataflash(path: str | os.PathLike, *, imu_instance: int = 0, stream: str = "imu"):
    """An ArduPilot DataFlash log as a :class:`~gyrocore.data.recording.Recording`.

    Columns: ``gyro_*_rad_s`` / ``accel_*_m_s2`` = IMU instance ``imu_instance`` (as flown, see the
    module docstring); extra ``motor_i`` (PWM µs), ``motor_cmd_i`` (0–1 of MOT_PWM_MIN..MAX),
    ``motor_cmd_mean``, ``throttle`` (CTUN.ThO). Metadata: firmware, board, IMU log rate (nominal
    = median, measured), gyro sample rate, ``gyro_filters`` (INS_GYRO_FILTER, harmonic notches),
    ``header_filters`` (the INS_/SCHED_/MOT_PWM_ parameters), ``lacks`` one line each.

    ``stream="batch"``: the gyro of the IMU batch sampler instead (:func:`_batch_recording`):
    windows of raw samples at the sensor rate, with gaps between them (no accelerometer columns:
    its windows are at other times).

    Raises
    ------
    GyroInputError
        Not a DataFlash log, no FMTU units, IMU units other than rad/s and m/s/s, no IMU
        messages of that instance.
    """
    p = Path(path)
    if stream not in ("imu", "batch"):
        raise GyroInputError(f"stream {stream!r}: choose imu or batch")
    if not p.exists():
        raise GyroInputError(f"{p}: no such file")
    if not is_dataflash(p):
        raise GyroInputError(f"{p}: not an ArduPilot DataFlash log (no FMT message at the start)")
    try:
        from pymavlink import DFReader
    except ImportError:  # pragma: no cover - dependency declared in pyproject
        raise GyroInputError("reading DataFlash logs needs pymavlink (pip install pymavlink)") from None
    size = p.stat().st_size
    # pymavlink reports skipped bad bytes with print() on stdout/stderr: captured, counted, and
    # said in one warning (stdout is the CLI's JSON channel)
    with _captured_output() as chatter:
        log, imu, rcou, ctun, params, msgs, isb, imu_units, stopped = _scan(
            p, DFReader, imu_instance, size, want_isb=(stream == "batch")
        )
    for msg in stopped:
        warn_repair(msg)
    rest = _bytes_after_last_message(log, size)
    try:
        log.filehandle.close()
    except Exception:  # noqa: BLE001 - pymavlink versions differ in what they keep open
        pass
    text = chatter.getvalue()
    skipped = [int(m.group(1)) for m in re.finditer(r"Skipped (\d+) bad bytes", text)]
    bad_hdr = len(re.findall(r"bad header|unknown msg type", text))
    if skipped or bad_hdr:
        what = [f"{len(skipped)} stretch(es), {sum(skipped)} bytes"] if skipped else []
        if bad_hdr:
            # pymavlink's index steps a byte at a time past a bad header: one per byte of garbage
            what.append(f"{bad_hdr} bad message header(s) stepped over while indexing (about one per byte)")
        warn_repair(f"{p.name}: corrupt data skipped: {'; '.join(what)}")
    rec = _to_recording(p, log, imu, rcou, ctun, params, msgs, len(isb["hdr"]), imu_units, rest, imu_instance)
    if stream == "batch":
        return _batch_recording(p, rec, isb, rcou, ctun, params, imu_instance)
    rec.meta["time_us_first"] = rec.meta.pop("_t0_us")
    return rec


def _scan(p, DFReader, imu_instance, size, want_isb=False):
    """Decode the messages the reader needs (pymavlink)."""
    try:
        log = DFReader.DFReader_binary(str(p), zero_time_base=False)
    except Exception as exc:  # pymavlink raises plain Exceptions on a bad file
        raise GyroInputError(
            f"{p}: not a readable DataFlash log ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        ) from None
    imu, rcou, ctun, params, msgs = [], [], [], {}, []
    isb = {"hdr": {}, "data": {}}
    imu_units = None
    stopped: list[str] = []
    while True:
        try:
            m = log.recv_match(type=["IMU", "RCOU", "CTUN", "PARM", "MSG", "ISBH"] + (["ISBD"] if want_isb else []))
        except Exception as exc:  # a damaged message pymavlink cannot skip
            stopped.append(
                f"{p.name}: DataFlash decoding stopped at byte {log.offset} of {size} "
                f"({type(exc).__name__}); messages before it kept"
            )
            break
        if m is None:
            break
        ty = m.get_type()
        if ty == "IMU":
            if int(getattr(m, "I", 0)) == imu_instance:
                imu.append((m.TimeUS, m.GyrX, m.GyrY, m.GyrZ, m.AccX, m.AccY, m.AccZ, getattr(m, "GHz", float("nan"))))
                if imu_units is None:
                    fmt = log.formats[log.name_to_id["IMU"]]
                    imu_units = dict(zip(fmt.columns, fmt.units)) if fmt.units else {}
        elif ty == "RCOU":
            rcou.append([m.TimeUS] + [getattr(m, f"C{i}", 0) for i in range(1, 9)])
        elif ty == "CTUN":
            ctun.append((m.TimeUS, m.ThO))
        elif ty == "PARM":
            params[m.Name] = float(m.Value)
        elif ty == "MSG":
            msgs.append(str(m.Message))
        elif ty == "ISBH":
            isb["hdr"][int(m.N)] = (
                int(m.type),
                int(m.instance),
                float(m.mul),
                int(m.smp_cnt),
                float(m.SampleUS),
                float(m.smp_rate),
            )
        elif ty == "ISBD":
            isb["data"].setdefault(int(m.N), []).append(
                (int(m.seqno), np.asarray(m.x, float), np.asarray(m.y, float), np.asarray(m.z, float))
            )
    return log, imu, rcou, ctun, params, msgs, isb, imu_units, stopped


def _motor_extras(t_us, rcou, ctun, params, lacks, notes) -> dict:
    """RCOU motors (PWM, 0-1 of MOT_PWM_MIN..MAX, mean) and CTUN.ThO held at times ``t_us``."""
    extra: dict[str, np.ndarray] = {}
    frame_class = int(params.get("FRAME_CLASS", 0) or 0)
    n_mot = FRAME_CLASS_MOTORS.get(frame_class)
    if rcou:
        r = np.asarray(rcou, dtype=float)
        if n_mot is None:
            n_mot = 4
            notes.append(f"FRAME_CLASS {frame_class} not in the motor table: motors taken as RCOU C1-C4")
        lo, hi = params.get("MOT_PWM_MIN", float("nan")), params.get("MOT_PWM_MAX", float("nan"))
        held = _hold(r[:, 0], r[:, 1 : 1 + n_mot], t_us)
        cmds = []
        for i in range(n_mot):
            extra[f"motor_{i}"] = held[:, i]
            if hi > lo > 0:
                extra[f"motor_cmd_{i}"] = np.clip((held[:, i] - lo) / (hi - lo), 0.0, 1.0)
                cmds.append(extra[f"motor_cmd_{i}"])
        if cmds:
            extra["motor_cmd_mean"] = np.mean(cmds, axis=0)
        else:
            lacks.append("no MOT_PWM_MIN/MAX parameters: motor outputs not normalised")
    else:
        lacks.append("no RCOU messages: no motor outputs")
    if ctun:
        c = np.asarray(ctun, dtype=float)
        extra["throttle"] = _hold(c[:, 0], c[:, 1:2], t_us)[:, 0]
    else:
        lacks.append("no CTUN messages: no throttle")
    for k in list(extra):
        if np.isnan(extra[k]).any():  # before the first RCOU/CTUN message: hold its first value back
            v = extra[k]
            first = np.flatnonzero(~np.isnan(v))
            extra[k] = np.where(np.isnan(v), v[first[0]] if first.size else 0.0, v)
    return extra


def _to_recording(p, log, imu, rcou, ctun, params, msgs, isb, imu_units, rest, imu_instance):
    """Decoded messages → :class:`~gyrocore.data.recording.Recording` (see :func:`read_dataflash`)."""
    from gyrocore.data.recording import Recording

    _check_imu(p, imu, imu_units, rest, imu_instance)
    a = np.asarray(imu, dtype=float)
    keep = np.concatenate([[True], np.diff(a[:, 0]) > 0])
    n_back = int((~keep).sum())
    a = a[keep]
    if a.shape[0] < 2:
        raise GyroInputError(f"{p}: {a.shape[0]} IMU samples of instance {imu_instance}")
    t_us = a[:, 0]
    t_s = (t_us - t_us[0]) * 1e-6
    dt = np.diff(t_s)
    log_hz = 1.0 / float(np.median(dt))
    lacks: list[str] = []
    notes: list[str] = []
    fw = next((s for s in msgs if _FW.match(s)), "")
    board = next(
        (s for s in msgs if re.match(r"^(CubeOrange|Cube|Pixhawk|Matek|SpeedyBee|Kakute|MatekH7|\w+ [0-9A-F]{8} )", s)),
        "",
    )
    extra = _motor_extras(t_us, rcou, ctun, params, lacks, notes)
    ghz = float(np.nanmedian(a[:, 7])) if np.isfinite(a[:, 7]).any() else float("nan")
    chain = _filter_chain(params, ghz, log_hz)
    lacks.extend(_imu_lacks(log_hz, ghz, isb))
    if n_back:
        warn_repair(f"{p.name}: {n_back} IMU samples whose time did not move forward dropped")
    hdr = {
        k: v
        for k, v in sorted(params.items())
        if k.startswith(
            ("INS_GYRO", "INS_HNTC", "INS_FAST", "INS_LOG_BAT", "SCHED_LOOP", "MOT_PWM", "FRAME_", "INS_ACCEL_FILTER")
        )
    }
    full = float(np.degrees(np.abs(a[:, 1:4]).max()))
    still = extra["motor_cmd_mean"] <= 0.0 if "motor_cmd_mean" in extra else np.zeros(t_s.size, bool)
    g_still = float(np.median(np.linalg.norm(a[still, 4:7], axis=1))) if still.sum() >= 10 else float("nan")
    meta = {
        "source": str(p),
        "format": "dataflash",
        "sensor": f"{fw or 'ArduPilot'} IMU{imu_instance} ({board or 'board unnamed'})",
        "rate_hz": f"{log_hz:.6g}",
        "units": "SI (rad/s, m/s^2, s); motor columns PWM us and 0-1",
        "frame": "ArduPilot body frame as logged (x forward, y right, z down)",
        "parser": "pymavlink DFReader (units from the log's FMTU messages)",
        "firmware": fw,
        "firmware_name": "ardupilot",
        "firmware_version": ".".join(_FW.match(fw).groups()[1:]) if fw else "",
        "board": board,
        "imu_instance": str(imu_instance),
        "log_rate_measured_hz": f"{log_hz:.6g}",
        "gyro_sample_rate_hz": f"{ghz:.6g}",
        "loop_rate_hz": f"{params.get('SCHED_LOOP_RATE', float('nan')):.6g}",
        "gyro_filters": json.dumps(chain),
        "gyro_signal": "filtered (IMU: ins.get_gyro after INS_GYRO_FILTER and the harmonic notches)",
        "gyro_units_check": (
            f"FMTU units GyrX/Y/Z rad/s, AccX/Y/Z m/s/s; max |gyro| {full:.0f} deg/s; "
            f"median |accel| with motors at MOT_PWM_MIN or below {g_still:.3f} m/s^2"
        ),
        "header_filters": json.dumps(hdr),
        "batch_sampler_windows": str(isb),
        "lacks": " | ".join(lacks),
        "repairs": "; ".join(notes) if notes else "none",
        "_t0_us": f"{t_us[0]:.0f}",
    }
    return Recording(t_s=t_s, gyro_rad_s=a[:, 1:4].copy(), accel_m_s2=a[:, 4:7].copy(), meta=meta, extra=extra)


def _check_imu(p, imu, imu_units, rest, imu_instance) -> None:
    """One error line for a log without IMU messages or without SI units for them; a repair
    warning for a truncated last message."""
    if not imu:
        raise GyroInputError(f"{p}: no IMU messages of instance {imu_instance}")
    if rest > 0:
        warn_repair(
            f"{p.name}: the log ends with {rest} bytes that do not form a complete message (truncated): "
            f"the complete messages are kept"
        )
    if not imu_units:
        raise GyroInputError(f"{p}: the log has no FMTU units for IMU: gyro/accel units cannot be checked")
    bad = {k: imu_units.get(k) for k in ("GyrX", "GyrY", "GyrZ") if imu_units.get(k) != "rad/s"}
    bad.update({k: imu_units.get(k) for k in ("AccX", "AccY", "AccZ") if imu_units.get(k) != "m/s/s"})
    if bad:
        raise GyroInputError(f"{p}: IMU units {bad} are not rad/s and m/s/s: not read")


def _filter_chain(params: dict, ghz: float, log_hz: float) -> list[dict]:
    """The gyro filter chain the parameters declare (INS_GYRO_FILTER, harmonic notches), in
    the ``gyro_filters`` metadata form; ``ghz`` is the gyro sample rate (IMU.GHz), Hz."""
    chain = []
    f_lpf = params.get("INS_GYRO_FILTER", 0.0)
    if f_lpf > 0 and math.isfinite(ghz):
        chain.append(
            {
                "kind": "butter2",
                "cutoff_hz": f_lpf,
                "rate_hz": ghz,
                "dynamic": False,
                "header": "INS_GYRO_FILTER (LowPassFilter2p: 2nd-order Butterworth at the gyro rate IMU.GHz)",
            }
        )
    for pre in ("INS_HNTCH", "INS_HNTC2"):
        if params.get(f"{pre}_ENABLE", 0) >= 1:
            chain.append(
                {
                    "kind": "dyn_notch",
                    "cutoff_hz": params.get(f"{pre}_FREQ", 0.0),
                    "rate_hz": ghz if math.isfinite(ghz) else log_hz,
                    "dynamic": True,
                    "max_hz": None,
                    "header": f"{pre}_* (harmonic notch, mode {params.get(f'{pre}_MODE', float('nan')):g}, "
                    f"{params.get(f'{pre}_HMNCS', float('nan')):g} harmonics bitmask, BW {params.get(f'{pre}_BW', float('nan')):g} Hz)",
                }
            )
    return chain


def _imu_lacks(log_hz: float, ghz: float, isb: int) -> list[str]:
    """What the IMU messages lack for vibration work (the ``lacks`` metadata lines)."""
    return [
        f"gyro logged at {log_hz:.0f} Hz (IMU messages): Nyquist {log_hz / 2:.1f} Hz, far below the motor lines "
        f"(gyro sampled at {ghz:.0f} Hz)",
        "no unfiltered gyro stream: IMU holds the gyro after INS_GYRO_FILTER and the notches"
        + (
            f"; the batch sampler's {isb} ISBH windows are in the log: convert --stream batch"
            if isb
            else " (INS_LOG_BAT_* batch sampler not logged)"
        ),
        "no per-motor RPM converted (ESC telemetry not read)",
    ]


#: INS_LOG_BAT_OPT bits (AP_InertialSensor BatchSampler ``batch_opt_t``): sensor-rate logging,
#: post-filter sampling, pre- and post-filter sampling.
BATCH_OPT_SENSOR_RATE, BATCH_OPT_POST_FILTER, BATCH_OPT_PRE_POST_FILTER = 1, 2, 4


def _hf_rms(windows, f_lo_hz: float) -> float:
    """Mean over windows of the rms above ``f_lo_hz`` (rad/s), all axes."""
    out = []
    for _t0, rate, g in windows:
        spec = np.abs(np.fft.rfft(g - g.mean(axis=0), axis=0)) ** 2
        f = np.fft.rfftfreq(g.shape[0], 1.0 / rate)
        out.append(np.sqrt(spec[f >= f_lo_hz].sum() * 2.0 / g.shape[0] ** 2))
    return float(np.mean(out)) if out else float("nan")


def _batch_recording(p, imu_rec, isb, rcou, ctun, params, imu_instance):
    """The batch sampler's gyro windows (ISBH/ISBD) of one IMU as a Recording with gaps.

    Read in AP_InertialSensor/BatchSampler.cpp: a batch is ``smp_cnt`` consecutive samples of
    one sensor (ISBH ``type`` 0 accel, 1 gyro; pymavlink tools/mavfft_isb.py names them so),
    stored as int16 ``multiplier · sample`` — so value/``mul`` is the gyro in the backend's
    unit, rad/s — at ``smp_rate`` from ``SampleUS``; batches rotate accel → gyro → next IMU.
    Without option bits the samples are taken before the filters; bit 1 samples after them. With
    bit 2 (pre and post filter) the log holds two instances per IMU; which one is post-filter
    was not read in the source: it is told on the data (the pre-filter one carries ≥ 3× the rms
    above 4·INS_GYRO_FILTER; the ratio is in the metadata) and the pre-filter one is used.
    Incomplete batches (missing ISBD sequence numbers) are dropped and counted.
    """
    from gyrocore.data.recording import Recording

    opt = int(params.get("INS_LOG_BAT_OPT", 0) or 0)
    by_inst, dropped = _gyro_batches(p, isb, imu_instance)
    post = bool(opt & BATCH_OPT_POST_FILTER) and not opt & BATCH_OPT_PRE_POST_FILTER
    check = _check_batch_instance(p, by_inst, params, opt, imu_instance)
    wins = sorted(by_inst[imu_instance], key=lambda w: w[0])
    t_parts, g_parts = [], []
    last = -np.inf
    for t0_us, rate, g in wins:
        t_us = t0_us + np.arange(g.shape[0]) * 1e6 / rate
        if t_us[0] <= last:
            dropped += 1
            continue
        last = t_us[-1]
        t_parts.append(t_us)
        g_parts.append(g)
    t_us = np.concatenate(t_parts)
    gyro = np.concatenate(g_parts)
    rate = float(np.median([w[1] for w in wins]))
    lacks, notes = [], []
    extra = _motor_extras(t_us, rcou, ctun, params, lacks, notes)
    if post:
        pre_meta = None
        signal_txt = "filtered (batch sampler, post-filter: INS_LOG_BAT_OPT bit 1)"
    else:
        for i, ax in enumerate("xyz"):
            extra[f"gyro_prefilter_{ax}_rad_s"] = gyro[:, i]
        pre_meta = {
            "source": f"ISBH/ISBD gyro batches of IMU {imu_instance} (pre-filter: INS_LOG_BAT_OPT {opt}), "
            f"value/mul in rad/s",
            "signal": "raw",
            "filters_before": [],
        }
        signal_txt = "raw (batch sampler, before INS_GYRO_FILTER and the notches)"
    if dropped:
        warn_repair(f"{p.name}: {dropped} incomplete or overlapping gyro batch(es) dropped")
    meta = _batch_meta(imu_rec.meta, wins, rate, signal_txt, check, lacks)
    if pre_meta:
        meta["gyro_prefilter"] = json.dumps(pre_meta)
    meta["time_us_first"] = f"{t_us[0]:.0f}"
    return Recording(t_s=(t_us - t_us[0]) * 1e-6, gyro_rad_s=gyro, accel_m_s2=None, meta=meta, extra=extra)


def _gyro_batches(p, isb: dict, imu_instance: int) -> tuple[dict[int, list], int]:
    """The complete gyro batches by instance, ``{inst: [(t0_us, rate_hz, gyro (n, 3) rad/s)]}``,
    and the number of incomplete ones of ``imu_instance`` dropped."""
    hdr, data = isb["hdr"], isb["data"]
    by_inst: dict[int, list] = {}
    dropped = 0
    for n, (typ, inst, mul, cnt, t0_us, rate) in sorted(hdr.items()):
        if typ != 1:
            continue
        seg = sorted(data.get(n, []), key=lambda r: r[0])
        if not seg or [r[0] for r in seg] != list(range(len(seg))) or sum(r[1].size for r in seg) != cnt or mul <= 0:
            dropped += inst == imu_instance
            continue
        g = np.column_stack([np.concatenate([r[k] for r in seg]) for k in (1, 2, 3)]) / mul
        by_inst.setdefault(inst, []).append((t0_us, rate, g))
    if not by_inst:
        raise GyroInputError(
            f"{p}: no complete gyro batch (ISBH/ISBD) in the log: the batch sampler was off "
            f"(INS_LOG_BAT_MASK) or its batches are incomplete"
        )
    return by_inst, dropped


def _check_batch_instance(p, by_inst: dict, params: dict, opt: int, imu_instance: int) -> str:
    """One error line unless ``imu_instance`` has gyro batches (and, with pre- and post-filter
    batches, is told on the data to be the pre-filter one); returns that check's text."""
    f_lpf = float(params.get("INS_GYRO_FILTER", 0.0) or 0.0)
    check = ""
    inst = imu_instance
    if opt & BATCH_OPT_PRE_POST_FILTER:
        if inst not in by_inst or len(by_inst) < 2 or f_lpf <= 0:
            raise GyroInputError(
                f"{p}: INS_LOG_BAT_OPT {opt} (pre and post filter) but the gyro batches of IMU "
                f"{imu_instance} and their counterpart are not both in the log"
            )
        f_lo = 4.0 * f_lpf
        hf = {k: _hf_rms(v, f_lo) for k, v in by_inst.items()}
        others = [k for k in hf if k != inst]
        ratio = hf[inst] / max(min(hf[k] for k in others), 1e-12)
        if ratio < 3.0:
            raise GyroInputError(
                f"{p}: cannot tell the pre-filter gyro batches of IMU {imu_instance} from the "
                f"post-filter ones (rms above {f_lo:.0f} Hz only {ratio:.1f}x the quietest instance)"
            )
        check = (
            f"INS_LOG_BAT_OPT {opt}: batch instances {sorted(hf)}; instance {inst} taken as pre-filter on the data: rms above "
            f"{f_lo:.0f} Hz " + ", ".join(f"instance {k} {np.degrees(v):.2f} deg/s" for k, v in sorted(hf.items()))
        )
    elif inst not in by_inst:
        raise GyroInputError(f"{p}: no gyro batch of IMU {imu_instance} (instances {sorted(by_inst)})")
    return check


def _batch_meta(imu_meta: dict, wins: list, rate: float, signal_txt: str, check: str, lacks: list[str]) -> dict:
    """The IMU recording's metadata restated for the batch stream (rate, windows, lacks)."""
    meta = dict(imu_meta)
    meta.pop("_t0_us", None)
    meta.update(
        {
            "stream": "batch",
            "rate_hz": f"{rate:.6g}",
            "log_rate_measured_hz": f"{rate:.6g}",
            "sensor": meta["sensor"] + " batch sampler",
            "gyro_signal": signal_txt,
            "batch_windows": str(len(wins)),
            "batch_window_s": f"{wins[0][2].shape[0] / rate:.6g}",
            "batch_prepost_check": check or "n/a",
            "lacks": " | ".join(
                [
                    f"gyro in {len(wins)} batch windows of {wins[0][2].shape[0]} samples ({wins[0][2].shape[0] / rate:.3f} s) "
                    f"at {rate:.0f} Hz with gaps between them; no accelerometer columns (its batches are at other times)"
                ]
                + [x for x in meta["lacks"].split(" | ") if not x.startswith(("gyro logged at", "no unfiltered gyro"))]
                + lacks
            ),
        }
    )
    return meta
