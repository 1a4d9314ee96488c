"""Readers for the real measured sets: each turns one source format into a :class:`Recording`.

Every reader returns SI arrays in the DESIGN.md columns (rad/s, m/s², °C, s), with metadata
lines ``source``, ``format``, ``sensor``, ``rate_hz`` and ``repairs`` (what was changed, e.g.
padding rows dropped, an axis sign flipped, host timestamps replaced by a uniform grid). Every
repair is also announced once with :func:`gyrocore.errors.warn_repair`.

Known total rotation angles (hand-rotation sessions) are returned as :class:`Segment` rows,
written as the segments file ``t_start_s,t_end_s,axis,angle_deg`` (see
:func:`write_segments_csv`) used by the integral calibration method (article §2, M = C·B⁻¹).

The sources and their quirks are documented in ``docs/data.md`` and in each folder's
PROVENANCE.md under ``../shared/data``.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from gyrocore.errors import GyroInputError, warn_repair
from gyrocore.data.recording import AXES, DEG, G0_M_S2, Recording, atomic_write_text, is_parquet, read_csv, read_parquet, read_recording

__all__ = [
    "Segment",
    "Converted",
    "FORMATS",
    "detect_format",
    "load_any",
    "load_with_segments",
    "concat_converted",
    "read_ulog",
    "read_sunsided",
    "read_tomisuarez2",
    "read_imucal",
    "read_imucal_annotated",
    "read_broad",
    "read_imutk",
    "read_gnss_ins_sim",
    "read_fusion",
    "sunsided_segments",
    "tomisuarez2_segments",
    "imucal_segments",
    "timing_report",
    "TimingReport",
    "retime_uniform",
    "motion_span",
    "frame_consistency",
    "write_segments_csv",
    "read_segments_csv",
]

#: MPU-6050 datasheet sensitivities at the ±250 °/s and ±2 g settings (tomisuarez2 defaults).
MPU6050_LSB_PER_DPS = 131.0
MPU6050_LSB_PER_G = 16384.0
#: imucal annotated session: 16-bit ±2000 °/s gyro (quantum 1/16.384 °/s, verified in
#: PROVENANCE) and ±16 g accel (2048 LSB/g); datasheet-nominal, not calibrated values.
IMUCAL_RAW_LSB_PER_DPS = 16.384
IMUCAL_RAW_LSB_PER_G = 2048.0
#: imu_tk xsens raw ADC: offset 32768 and the initial gyro scale guess of IMU-TK's
#: test_imu_calib.cpp (1/6258 rad/s per LSB), i.e. 6258 LSB/(rad/s) = 109.22 LSB/(°/s).
IMUTK_ADC_OFFSET = 32768.0
IMUTK_LSB_PER_RAD_S = 6258.0
IMUTK_STATIC_S = 50.0


# ============================================================================ segments
@dataclass(frozen=True)
class Segment:
    """A time span with a known total rotation about one sensor axis.

    Parameters
    ----------
    t_start_s, t_end_s : float
        Span on the recording's time axis, s.
    axis : str
        ``"x"``, ``"y"`` or ``"z"`` (sensor frame S).
    angle_deg : float
        Total rotation of S about ``axis`` over the span, degrees, right-hand positive.
    label : str
        Where it comes from (not written to the segments file).
    """

    t_start_s: float
    t_end_s: float
    axis: str
    angle_deg: float
    label: str = ""


@dataclass(frozen=True)
class Converted:
    """A converted recording and its known-rotation segments."""

    recording: Recording
    segments: tuple[Segment, ...] = ()
    format: str = ""


def write_segments_csv(segments: Sequence[Segment], path: str | os.PathLike, *, overwrite: bool = True) -> None:
    """Write the segments file ``t_start_s,t_end_s,axis,angle_deg`` atomically."""
    buf = io.StringIO()
    buf.write("t_start_s,t_end_s,axis,angle_deg\n")
    for s in segments:
        buf.write(f"{s.t_start_s!r},{s.t_end_s!r},{s.axis},{s.angle_deg!r}\n")
    atomic_write_text(path, buf.getvalue(), overwrite=overwrite)


def read_segments_csv(path: str | os.PathLike) -> list[Segment]:
    """Read a segments file written by :func:`write_segments_csv` (``#`` lines ignored)."""
    path = str(path)
    if not os.path.isfile(path):
        raise GyroInputError(f"{path}: no such segments file")
    out: list[Segment] = []
    header_seen = False
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = [p.strip() for p in s.split(",")]
            if not header_seen:
                if parts[:4] != ["t_start_s", "t_end_s", "axis", "angle_deg"]:
                    raise GyroInputError(f"{path}: header must be t_start_s,t_end_s,axis,angle_deg")
                header_seen = True
                continue
            if len(parts) < 4:
                raise GyroInputError(f"{path}: line {lineno}: expected 4 values")
            try:
                t0, t1, ang = float(parts[0]), float(parts[1]), float(parts[3])
            except ValueError:
                raise GyroInputError(f"{path}: line {lineno}: not a number") from None
            if parts[2] not in AXES:
                raise GyroInputError(f"{path}: line {lineno}: axis must be x, y or z, got {parts[2]!r}")
            if not (math.isfinite(t0) and math.isfinite(t1) and math.isfinite(ang)) or t1 <= t0:
                raise GyroInputError(f"{path}: line {lineno}: need finite t_start_s < t_end_s and angle")
            out.append(Segment(t0, t1, parts[2], ang))
    if not header_seen:
        raise GyroInputError(f"{path}: empty segments file")
    return out


# ============================================================================ timing
@dataclass(frozen=True)
class TimingReport:
    """Sample-interval statistics of a time column.

    Attributes
    ----------
    median_dt_s, mean_dt_s, max_dt_s : float
        Median, mean ((N−1)/duration) and largest interval, s.
    n_gaps : int
        Intervals longer than ``gap_factor`` × median (dropped samples, when not bursty).
    bursty : bool
        Host receive times: the median interval is under half the mean one and the longest
        interval is over 4 × the mean (samples arrive in bursts, e.g. USB/serial buffering).
    """

    median_dt_s: float
    mean_dt_s: float
    max_dt_s: float
    n_gaps: int
    bursty: bool


def timing_report(t_s: np.ndarray, *, gap_factor: float = 1.5) -> TimingReport:
    """Classify the intervals of ``t_s`` (strictly increasing, s).

    A dropped sample makes an interval ≈ 2 × the nominal one; ``gap_factor = 1.5`` sits half
    way, so jitter up to ±50 % of the interval is not counted as a gap.
    """
    d = np.diff(np.asarray(t_s, float))
    if d.size == 0:
        return TimingReport(float("nan"), float("nan"), float("nan"), 0, False)
    med = float(np.median(d))
    mean = float((t_s[-1] - t_s[0]) / d.size)
    mx = float(d.max())
    bursty = bool(med < 0.5 * mean and mx > 4.0 * mean)
    n_gaps = int(np.count_nonzero(d > gap_factor * med)) if med > 0 else 0
    return TimingReport(med, mean, mx, n_gaps, bursty)


def retime_uniform(t_s: np.ndarray) -> np.ndarray:
    """Uniform grid with the same start, end and count: rate (N−1)/duration."""
    t_s = np.asarray(t_s, float)
    n = t_s.size
    if n < 2:
        return t_s.copy()
    return t_s[0] + np.arange(n) * ((t_s[-1] - t_s[0]) / (n - 1))


def motion_span(
    t_s: np.ndarray,
    omega_rad_s: np.ndarray,
    *,
    threshold_rad_s: float = np.deg2rad(10.0),
    pad_s: float = 0.5,
    window_s: float = 0.5,
) -> tuple[float, float]:
    """First and last time |ω − b| exceeds ``threshold_rad_s``, padded by ``pad_s``.

    ``b`` is the mean rate over the quietest ``window_s`` window (smallest summed standard
    deviation), i.e. the bias seen while the hand held the board still. Used to place a
    known-rotation segment around the actual motion of a hand rotation, so that the still
    parts before and after stay outside the segment (they can give the bias).
    """
    t_s = np.asarray(t_s, float)
    n = t_s.size
    rate = (n - 1) / (t_s[-1] - t_s[0]) if n > 1 and t_s[-1] > t_s[0] else 1.0
    k = max(2, int(round(window_s * rate)))
    if n >= 2 * k:
        starts = np.arange(0, n - k + 1, max(1, k // 4))
        sd = np.array([omega_rad_s[i : i + k].std(axis=0).sum() for i in starts])
        i0 = int(starts[int(np.argmin(sd))])
        b = omega_rad_s[i0 : i0 + k].mean(axis=0)
    else:
        b = np.median(omega_rad_s, axis=0)
    dev = np.linalg.norm(omega_rad_s - b, axis=1)
    idx = np.flatnonzero(dev > threshold_rad_s)
    if idx.size == 0:
        return float(t_s[0]), float(t_s[-1])
    return max(float(t_s[0]), float(t_s[idx[0]]) - pad_s), min(float(t_s[-1]), float(t_s[idx[-1]]) + pad_s)


def frame_consistency(rec: Recording, *, window: int = 21) -> float:
    """Correlation between d f/dt and −ω × f (kinematic check of the gyro/accel axes).

    For a sensor moved by hand, the specific force f is nearly constant in the world frame,
    so in the sensor frame df/dt ≈ −ω × f. With gyro and accelerometer in one right-handed
    frame the correlation is positive (≈ +0.4…+0.95 for hand motion); a flipped axis in one
    of them makes it negative or near zero. Uses Savitzky–Golay smoothing over ``window``
    samples and the sample index with dt = 1/rate (robust to bursty host timestamps).
    """
    from scipy.signal import savgol_filter

    if rec.accel_m_s2 is None or rec.n < window + 2:
        return float("nan")
    dt = 1.0 / rec.rate_hz
    w = savgol_filter(rec.gyro_rad_s - np.median(rec.gyro_rad_s, axis=0), window, 2, axis=0)
    f = savgol_filter(rec.accel_m_s2, window, 2, axis=0)
    df = savgol_filter(rec.accel_m_s2, window, 2, deriv=1, delta=dt, axis=0)
    pred = -np.cross(w, f)
    den = math.sqrt(float(np.sum(pred**2) * np.sum(df**2)))
    return float(np.sum(pred * df) / den) if den > 0 else float("nan")


# ============================================================================ helpers
class _Repairs:
    """Collects repairs: each is warned once and listed in the ``repairs`` metadata line."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.items: list[str] = []

    def add(self, message: str) -> None:
        self.items.append(message)
        warn_repair(f"{self.source}: {message}", stacklevel=3)

    def note(self, message: str) -> None:
        """A change that is part of the documented conversion (listed, not warned)."""
        self.items.append(message)

    def meta(self) -> str:
        return "; ".join(self.items) if self.items else "none"


def _meta(source: str, fmt: str, sensor: str, rate_hz: float, repairs: _Repairs, **more: str) -> dict[str, str]:
    m = {"source": source, "format": fmt, "sensor": sensor, "rate_hz": f"{rate_hz:.6g}", "units": "SI (rad/s, m/s^2, degC, s)"}
    m.update({k: str(v) for k, v in more.items()})
    m["repairs"] = repairs.meta()
    return m


def _require_file(path: Path, what: str) -> None:
    if not path.exists():
        raise GyroInputError(f"{path}: no such file ({what})")
    if path.is_dir():
        raise GyroInputError(f"{path}: is a directory, expected {what}")


def _positive(name: str, value: float) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise GyroInputError(f"{name} must be a positive number, got {value!r}")
    return v


def _check_finite(rec_source: str, arrays: dict[str, np.ndarray], repairs: _Repairs) -> np.ndarray:
    """Mask of rows whose listed arrays are all finite; drop the rest with a repair note."""
    keep = None
    for a in arrays.values():
        ok = np.all(np.isfinite(a.reshape(a.shape[0], -1)), axis=1)
        keep = ok if keep is None else keep & ok
    assert keep is not None
    n_bad = int((~keep).sum())
    if n_bad:
        repairs.add(f"dropped {n_bad} rows with NaN/inf samples")
    return keep


def _h5(path: Path):
    import h5py

    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise GyroInputError(f"{path}: not an HDF5 / MATLAB v7.3 file ({str(exc).splitlines()[0]})") from None


# ============================================================================ PX4 ULog
#: A ``sensor_gyro`` instance logged slower than this is a housekeeping stream (PX4's default
#: profile: 1 Hz); its thermal-calibration and sensor-comparison profiles log every instance at
#: 10 Hz (logged_topics.cpp: add_topic_multi("sensor_gyro", 100 ms)) — enough for bias against
#: temperature (PX4's own TC_G fit), not for noise or vibration (below
#: :data:`ULOG_NOISE_GYRO_RATE_HZ` a warning says so).
ULOG_MIN_GYRO_RATE_HZ = 5.0
ULOG_NOISE_GYRO_RATE_HZ = 50.0


def read_ulog(path: str | os.PathLike, *, multi_id: int = 0, gyro_instance: int | None = None) -> Recording:
    """PX4 ULog: ``sensor_combined`` gyro/accel, ``sensor_gyro`` temperature when logged.

    Parameters
    ----------
    path : path-like
        A ``.ulg`` file.
    multi_id : int
        Instance of ``sensor_combined`` to read.
    gyro_instance : int, optional
        Read ``sensor_gyro`` instance N instead (one of a board's several gyros, as its driver
        published it: rotated to the board frame, *before* PX4's CAL_GYRO calibration), with its
        own temperature; no accel. Refused (one line) when that instance is logged slower than
        :data:`ULOG_MIN_GYRO_RATE_HZ` (PX4's default logging profile keeps it at 1 Hz; its
        thermal-calibration profile at 10 Hz, read with a warning below 50 Hz).

    Notes
    -----
    PX4 logs ``sensor_combined.gyro_rad`` already calibrated (its CAL_GYRO offsets removed)
    and rotated to the board frame, integrated over ``gyro_integral_dt``: this is the
    *output* of PX4's calibration, not raw sensor data. ``t_s`` is seconds since the first
    sample (``t0_us`` metadata: the PX4 boot-time stamp of that sample). ``vehicle_attitude``
    is PX4's estimator output (EKF), not an independent reference: it goes to the extra
    columns ``ekf_qw..ekf_qz`` (linearly interpolated, renormalised; NaN outside its span),
    never to ``ref_q*``. ``sensor_gyro.temperature`` (when present, e.g. 1 Hz) is linearly
    interpolated to the gyro times inside its span; outside it the row keeps the nearest
    value (a repair that is reported).
    """
    from pyulog import ULog

    p = Path(path)
    _require_file(p, "PX4 .ulg log")
    try:
        ulog = ULog(str(p))
    except Exception as exc:  # pyulog raises bare Exceptions on corrupt files
        raise GyroInputError(f"{p}: not a readable ULog file ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
    if gyro_instance is not None:
        return _read_ulog_sensor_gyro(ulog, p, int(gyro_instance))
    repairs = _Repairs(p.name)
    try:
        sc = ulog.get_dataset("sensor_combined", multi_id)
    except (KeyError, IndexError, ValueError):
        raise GyroInputError(f"{p}: no sensor_combined topic (instance {multi_id}) in the log") from None
    ts_us = np.asarray(sc.data["timestamp"], dtype=np.int64)
    gyro = np.column_stack([sc.data[f"gyro_rad[{i}]"] for i in range(3)]).astype(float)
    accel = np.column_stack([sc.data[f"accelerometer_m_s2[{i}]"] for i in range(3)]).astype(float)
    keep = _check_finite(p.name, {"g": gyro, "a": accel}, repairs)
    # timestamps must increase strictly
    order_ok = np.concatenate([[True], np.diff(ts_us) > 0])
    if not order_ok.all():
        repairs.add(f"dropped {int((~order_ok).sum())} rows whose timestamp repeats or goes backwards")
        keep &= order_ok
    ts_us, gyro, accel = ts_us[keep], gyro[keep], accel[keep]
    t_s = (ts_us - ts_us[0]) * 1e-6
    extra: dict[str, np.ndarray] = {}
    temp = None
    temp_note = "none logged"
    try:
        inst, inst_note = _ulog_selected_gyro_instance(ulog)
        sg = ulog.get_dataset("sensor_gyro", inst)
        tt = np.asarray(sg.data["timestamp"], float)
        tv = np.asarray(sg.data["temperature"], float)
        ok = np.isfinite(tv) & (tv != 0)
        if ok.sum() >= 1:
            tt, tv = tt[ok], tv[ok]
            temp = np.interp(ts_us.astype(float), tt, tv)
            n_out = int(np.count_nonzero((ts_us < tt[0]) | (ts_us > tt[-1])))
            if n_out:
                repairs.add(f"temperature (sensor_gyro, {tt.size} samples) held at its nearest value for {n_out} gyro samples outside its span")
            temp_note = f"sensor_gyro[{inst}].temperature ({tt.size} samples, interpolated; {inst_note})"
    except (KeyError, IndexError, ValueError):
        pass
    try:
        va = ulog.get_dataset("vehicle_attitude", 0)
        qt = np.asarray(va.data["timestamp"], float)
        q = np.column_stack([va.data[f"q[{i}]"] for i in range(4)]).astype(float)
        x = ts_us.astype(float)
        qi = np.column_stack([np.interp(x, qt, q[:, i], left=np.nan, right=np.nan) for i in range(4)])
        qi /= np.linalg.norm(qi, axis=1, keepdims=True)
        for name, col in zip(("ekf_qw", "ekf_qx", "ekf_qy", "ekf_qz"), qi.T):
            extra[name] = col
    except (KeyError, IndexError, ValueError):
        pass
    info = ulog.msg_info_dict
    sensor = f"PX4 {info.get('ver_hw', 'unknown hardware')} sensor_combined[{multi_id}]"
    rate = (t_s.size - 1) / t_s[-1] if t_s.size > 1 and t_s[-1] > 0 else float("nan")
    meta = _meta(
        str(p), "ulog", sensor, rate, repairs,
        t0_us=str(int(ts_us[0])),
        calibration="gyro already calibrated (CAL_GYRO offsets) and board-rotated by PX4",
        temperature=temp_note,
        note="ekf_q* columns are PX4's attitude estimate (vehicle_attitude), NOT a reference",
    )
    return Recording(t_s=t_s, gyro_rad_s=gyro, accel_m_s2=accel, temp_c=temp, meta=meta, extra=extra)


def _read_ulog_sensor_gyro(ulog, p: Path, inst: int) -> Recording:
    """``sensor_gyro`` instance ``inst`` of a ULog as a recording (see :func:`read_ulog`)."""
    have = sorted(int(d.multi_id) for d in ulog.data_list if d.name == "sensor_gyro")
    if inst not in have:
        raise GyroInputError(f"{p}: no sensor_gyro instance {inst} in the log (instances: "
                             f"{', '.join(map(str, have)) or 'none'})")
    sg = ulog.get_dataset("sensor_gyro", inst)
    key = "timestamp_sample" if "timestamp_sample" in sg.data else "timestamp"
    ts_us = np.asarray(sg.data[key], dtype=np.int64)
    dev = int(np.asarray(sg.data["device_id"])[0]) if "device_id" in sg.data else None
    span = (ts_us[-1] - ts_us[0]) * 1e-6 if ts_us.size > 1 else 0.0
    rate = (ts_us.size - 1) / span if span > 0 else 0.0
    if rate < ULOG_MIN_GYRO_RATE_HZ:
        sc_rate = ""
        try:
            t_sc = np.asarray(ulog.get_dataset("sensor_combined", 0).data["timestamp"], float)
            sc_rate = f"; sensor_combined carries the selected gyro at {(t_sc.size - 1) / ((t_sc[-1] - t_sc[0]) * 1e-6):.0f} Hz"
        except (KeyError, IndexError, ValueError, ZeroDivisionError):
            pass
        raise GyroInputError(
            f"{p}: sensor_gyro instance {inst} (device {dev}) is logged at {rate:.3g} Hz ({ts_us.size} samples), too slow "
            f"to calibrate from: PX4's thermal-calibration or sensor-comparison profile (SDLOG_PROFILE) logs every "
            f"gyro at 10 Hz; the full-rate raw gyro is sensor_gyro_fifo (not read here){sc_rate}"
        )
    repairs = _Repairs(p.name)
    if rate < ULOG_NOISE_GYRO_RATE_HZ:
        repairs.add(f"sensor_gyro[{inst}] is logged at {rate:.3g} Hz: enough for bias against temperature, "
                    f"not for noise identification or vibration")
    gyro = np.column_stack([np.asarray(sg.data[a], float) for a in "xyz"])
    temp = np.asarray(sg.data["temperature"], float) if "temperature" in sg.data else None
    keep = _check_finite(p.name, {"g": gyro}, repairs)
    order_ok = np.concatenate([[True], np.diff(ts_us) > 0])
    if not order_ok.all():
        repairs.add(f"dropped {int((~order_ok).sum())} rows whose timestamp repeats or goes backwards")
        keep &= order_ok
    ts_us, gyro = ts_us[keep], gyro[keep]
    if temp is not None:
        temp = temp[keep]
        if not np.all(np.isfinite(temp)) or np.all(temp == 0):
            temp = None
    t_s = (ts_us - ts_us[0]) * 1e-6
    sel, how = _ulog_selected_gyro_instance(ulog)
    info = ulog.msg_info_dict
    meta = _meta(
        str(p), "ulog", f"PX4 {info.get('ver_hw', 'unknown hardware')} sensor_gyro[{inst}] (device {dev})",
        (t_s.size - 1) / t_s[-1], repairs,
        t0_us=str(int(ts_us[0])),
        calibration="sensor_gyro as the driver published it: board-rotated, before PX4's CAL_GYRO offsets/scale",
        temperature=f"sensor_gyro[{inst}].temperature" if temp is not None else "none logged",
        selected_gyro=f"instance {sel} ({how})" + (" = this one" if sel == inst else ": not this one"),
    )
    return Recording(t_s=t_s, gyro_rad_s=gyro, temp_c=temp, meta=meta)


def _ulog_selected_gyro_instance(ulog) -> tuple[int, str]:
    """The ``sensor_gyro`` instance whose device is the gyro ``sensor_combined`` carries.

    A flight controller with several IMUs logs one ``sensor_gyro`` instance per gyro, and the
    instance numbers need not follow the selection (PX4 picks the gyro by ``CAL_GYRO_PRIME`` in
    older releases and publishes the choice in ``sensor_selection.gyro_device_id`` in newer
    ones). Temperature taken from instance 0 when another gyro is selected belongs to another
    chip (on a CubeOrange the three read 40, 28 and 30 °C). Returns (instance, how it was
    chosen); instance 0 when nothing in the log says which.
    """
    dev = None
    how = ""
    try:
        sel = ulog.get_dataset("sensor_selection", 0)
        ids = np.asarray(sel.data["gyro_device_id"])
        if ids.size and int(ids[-1]) != 0:
            dev, how = int(ids[-1]), "sensor_selection.gyro_device_id"
    except (KeyError, IndexError, ValueError):
        pass
    if dev is None:
        prime = ulog.initial_parameters.get("CAL_GYRO_PRIME")
        if prime:
            dev, how = int(prime), "CAL_GYRO_PRIME"
    if dev is None:
        return 0, "instance 0: the log does not say which gyro is selected"
    for d in ulog.data_list:
        if d.name == "sensor_gyro" and "device_id" in d.data:
            ids = np.asarray(d.data["device_id"])
            if ids.size and int(ids[0]) == dev:
                return int(d.multi_id), f"device {dev} = {how}"
    return 0, f"instance 0: no sensor_gyro instance has the selected device {dev} ({how})"


# ============================================================================ sunsided
_SUNSIDED_ROT = re.compile(r"rotate-(?:360)?ccw-around-([xyz])")


def _sunsided_dir(path: Path) -> Path:
    if path.is_file() and path.name.startswith("mpu6050_") and path.suffix == ".mat":
        return path.parent
    if path.is_dir() and (path / "mpu6050_gyroscope.mat").exists():
        return path
    if not path.exists():
        raise GyroInputError(f"{path}: no such file or folder")
    raise GyroInputError(f"{path}: expected a sunsided recording folder with mpu6050_gyroscope.mat")


def read_sunsided(path: str | os.PathLike, *, retime: bool = True, flip_gyro_x: bool = True) -> Recording:
    """sunsided/sensor-fusion MPU-6050 recording (MATLAB v7.3 files of one folder).

    Parameters
    ----------
    path : path-like
        The recording folder (with ``mpu6050_{gyroscope,accelerometer,temperature}.mat``) or
        one of its ``.mat`` files.
    retime : bool
        Replace the bursty host receive times by a uniform grid at the mean rate
        (N−1)/duration (default; right for Allan variance and integration, which assume
        uniform sampling). With False the host times are kept (with a warning).
    flip_gyro_x : bool
        Negate gyro X, which the set-2 README documents as "positive = clockwise" (Y/Z are
        counter-clockwise-positive); after the flip the documented 2 × 360° CCW hand
        rotations integrate to ≈ +720° about every axis.

    Notes
    -----
    Datasets are stored (cols × N) and transposed. Units: gyro °/s, accel g, die °C.
    Rows with t == 0 (all-zero padding at the end of some files) are dropped. Accelerometer
    conventions differ between the sets (PROVENANCE): set-1 gives "up" with X negated, set-2
    gives the gravity direction (minus specific force); both are mapped to specific force so
    that the axis named "up" in the folder name reads +1 g.
    """
    d = _sunsided_dir(Path(path))
    repairs = _Repairs(f"{d.parent.name}/{d.name}")
    files = {k: d / f"mpu6050_{k}.mat" for k in ("gyroscope", "accelerometer", "temperature")}
    _require_file(files["gyroscope"], "mpu6050_gyroscope.mat")

    def load(kind: str, key: str, ncol: int) -> np.ndarray | None:
        f = files[kind]
        if not f.exists():
            return None
        with _h5(f) as h:
            if key not in h:
                raise GyroInputError(f"{f}: dataset {key!r} missing")
            a = np.asarray(h[key][()], dtype=float)
        if a.ndim != 2 or ncol not in a.shape:
            raise GyroInputError(f"{f}: dataset {key} has shape {a.shape}, expected ({ncol}, N)")
        return a.T if a.shape[0] == ncol and a.shape[1] != ncol else a

    g = load("gyroscope", "gyroBuffer", 4)
    a = load("accelerometer", "accelBuffer", 4)
    T = load("temperature", "temperatureBuffer", 2)
    assert g is not None
    n = g.shape[0]
    for name, arr in (("accelerometer", a), ("temperature", T)):
        if arr is not None and (arr.shape[0] != n or not np.array_equal(arr[:, 0], g[:, 0])):
            raise GyroInputError(f"{d}: {name} file does not share the gyroscope time column")
    keep = g[:, 0] != 0.0
    n_pad = int((~keep).sum())
    if n_pad:
        repairs.add(f"dropped {n_pad} all-zero padding rows (t == 0)")
    arrays = {"g": g[:, 1:]}
    if a is not None:
        arrays["a"] = a[:, 1:]
    if T is not None:
        arrays["T"] = T[:, 1]
    keep &= _check_finite(repairs.source, {**arrays, "t": g[:, 0]}, repairs)
    t = g[keep, 0]
    inc = np.concatenate([[True], np.diff(t) > 0])
    if not inc.all():
        repairs.add(f"dropped {int((~inc).sum())} rows whose timestamp repeats or goes backwards")
        idx = np.flatnonzero(keep)
        keep[idx[~inc]] = False
        t = g[keep, 0]
    gyro = g[keep, 1:] * DEG
    if flip_gyro_x:
        gyro[:, 0] *= -1.0
        repairs.note("gyro X negated (README: X positive = clockwise) to make it counter-clockwise-positive like Y and Z")
    accel = None
    set_name = d.parent.name
    if a is not None:
        accel = a[keep, 1:] * G0_M_S2
        if set_name == "set-2":
            accel *= -1.0
            repairs.note("accel negated (set-2 logs the gravity direction; converted to specific force)")
        elif set_name == "set-1":
            accel[:, 0] *= -1.0
            repairs.note("accel X negated (set-1 README: X sign flipped)")
        else:
            accel[:, 0] *= -1.0
            repairs.add(
                f"folder {set_name!r} is neither set-1 nor set-2: accel convention unknown, set-1's assumed (X negated)"
            )
    temp = T[keep, 1] if T is not None else None
    rep = timing_report(t)
    t_host = t
    if rep.bursty:
        if retime:
            t = retime_uniform(t)
            repairs.add(
                f"bursty host timestamps (median dt {rep.median_dt_s * 1e3:.1f} ms, mean {rep.mean_dt_s * 1e3:.1f} ms, "
                f"gaps up to {rep.max_dt_s:.2f} s) replaced by a uniform grid at {1 / rep.mean_dt_s:.3f} Hz"
            )
        else:
            warn_repair(
                f"{repairs.source}: bursty host timestamps (median dt {rep.median_dt_s * 1e3:.1f} ms, gaps up to "
                f"{rep.max_dt_s:.2f} s) kept as recorded; pass --retime for a uniform grid"
            )
    extra = {"t_host_s": t_host} if (rep.bursty and retime) else {}
    rate = (t.size - 1) / (t[-1] - t[0])
    meta = _meta(
        f"sunsided/sensor-fusion data/{set_name}/{d.name}", "sunsided", "InvenSense MPU-6050 (+-250 dps, +-2 g)", rate, repairs,
        recording=f"{set_name}/{d.name}",
        timing="uniform grid at the mean rate (host times in t_host_s)" if (rep.bursty and retime) else "host receive times",
        frame_note=(
            "gyro X flip follows the README; the raw gyro/accel pair is kinematically right-handed in set-1, "
            "so with the flip gyro and accel are mirror-consistent only: see docs/data.md"
            if flip_gyro_x else "raw gyro axes (no X flip)"
        ),
    )
    return Recording(t_s=t, gyro_rad_s=gyro, accel_m_s2=accel, temp_c=temp, meta=meta, extra=extra)


def sunsided_segments(rec: Recording, recording_dir: str | os.PathLike) -> list[Segment]:
    """Known rotations of a sunsided ``rotate-*`` recording: 2 × 360° CCW about the named axis.

    The segment spans the motion (|ω − median| > 10 °/s, ±0.5 s) so that the still parts
    before and after can serve for the bias. The angle is +720° (counter-clockwise = right-hand
    positive) when the gyro X flip was applied, and for X −720° without it.
    """
    name = Path(recording_dir).name
    m = _SUNSIDED_ROT.search(name)
    if not m:
        return []
    axis = m.group(1)
    angle = 720.0
    if axis == "x" and "gyro X negated" not in rec.meta.get("repairs", ""):
        angle = -720.0
    t0, t1 = motion_span(rec.t_s, rec.gyro_rad_s)
    return [Segment(t0, t1, axis, angle, label=f"{name}: two CCW 360 deg turns (README)")]


# ============================================================================ tomisuarez2
def read_tomisuarez2(
    path: str | os.PathLike,
    *,
    lsb_per_dps: float = MPU6050_LSB_PER_DPS,
    lsb_per_g: float = MPU6050_LSB_PER_G,
    rate_hz: float | None = None,
) -> Recording:
    """tomisuarez2/ImuCalibration MPU-6050 raw-LSB CSV.

    Five header lines (``Fs,100``, ``Logging Type``, ``Initialization time``,
    ``Waiting time``, then ``ax,ay,az,gx,gy,gz``), integer LSB rows, no timestamps.

    Parameters
    ----------
    lsb_per_dps : float
        Gyro sensitivity, LSB per °/s (datasheet 131 at ±250 °/s).
    lsb_per_g : float
        Accel sensitivity, LSB per g (datasheet 16384 at ±2 g); g = 9.80665 m/s².
    rate_hz : float or None
        Sample rate; default the file's ``Fs`` line. ``t_s = k / rate_hz``.
    """
    p = Path(path)
    _require_file(p, "tomisuarez2 CSV")
    lsb_per_dps = _positive("--lsb-per-dps", lsb_per_dps)
    lsb_per_g = _positive("--lsb-per-g", lsb_per_g)
    header: dict[str, str] = {}
    with open(p, encoding="utf-8", errors="replace") as fh:
        lines = [fh.readline() for _ in range(5)]
    for ln in lines[:4]:
        k, _, v = ln.strip().partition(",")
        header[k.strip()] = v.strip()
    cols = [c.strip() for c in lines[4].strip().split(",")]
    if "Fs" not in header or cols != ["ax", "ay", "az", "gx", "gy", "gz"]:
        raise GyroInputError(f"{p}: not a tomisuarez2 file (expected 'Fs,...' and the header ax,ay,az,gx,gy,gz on line 5)")
    if rate_hz is None:
        try:
            rate_hz = float(header["Fs"])
        except ValueError:
            raise GyroInputError(f"{p}: line 1: Fs is not a number ({header['Fs']!r})") from None
    rate_hz = _positive("rate_hz", rate_hz)
    data = _loadtxt(p, skiprows=5, ncols=6)
    repairs = _Repairs(p.name)
    keep = _check_finite(p.name, {"d": data}, repairs)
    if not keep.all():
        repairs.items[-1] += " (the sample clock is assumed uniform: later samples keep their index times)"
    idx = np.flatnonzero(keep)
    data = data[keep]
    t = idx / rate_hz
    gyro = data[:, 3:6] / lsb_per_dps * DEG
    accel = data[:, 0:3] / lsb_per_g * G0_M_S2
    meta = _meta(
        str(p), "tomisuarez2", "InvenSense MPU-6050 (raw LSB)", rate_hz, repairs,
        scale=f"gyro {lsb_per_dps:g} LSB/(deg/s), accel {lsb_per_g:g} LSB/g (nominal, not calibrated)",
        timing=f"no timestamps in file: t = index / {rate_hz:g} Hz",
        logging_type=header.get("Logging Type", ""),
        initialization_time_s=header.get("Initialization time", ""),
        waiting_time_s=header.get("Waiting time", ""),
    )
    return Recording(t_s=t, gyro_rad_s=gyro, accel_m_s2=accel, meta=meta)


def tomisuarez2_segments(rec: Recording, path: str | os.PathLike) -> list[Segment]:
    """``imu_90_x_rot.csv``: one +90° rotation about X (authors' README), around the motion."""
    if Path(path).name != "imu_90_x_rot.csv":
        return []
    t0, t1 = motion_span(rec.t_s, rec.gyro_rad_s)
    return [Segment(t0, t1, "x", 90.0, label="imu_90_x_rot: +90 deg about X (README)")]


# ============================================================================ imucal
_IMUCAL_POSE = {"x_p": 1.0, "x_a": -1.0, "y_p": 2.0, "y_a": -2.0, "z_p": 3.0, "z_a": -3.0}
IMUCAL_EXPECTED_ANGLE_DEG = -360.0


def read_imucal(
    path: str | os.PathLike,
    *,
    rate_hz: float = 102.4,
    sections: str | os.PathLike | None = None,
) -> Recording:
    """imucal Ferraris session (``n_samples,gyr_x..z [°/s],acc_x..z [m/s²]``, no timestamps).

    Parameters
    ----------
    rate_hz : float
        Sample rate (102.4 Hz per imucal's basic_ferraris example); ``t_s = n_samples / rate_hz``.
    sections : path-like or None
        The session's section list JSON (``{"x_p": {"start":…, "end":…}, …}``); default
        ``<stem>_list.json`` beside the CSV when it exists.

    Notes
    -----
    Static sections (``x_p`` = +x up reads +1 g, ``x_a`` = −x up, …) go to the extra column
    ``static_pose_axis`` (±1/±2/±3 for ±x/±y/±z up, 0 elsewhere); rotation sections become
    :class:`Segment` rows via :func:`imucal_segments` (one turn, imucal's expected −360°).
    """
    p = Path(path)
    _require_file(p, "imucal session CSV")
    rate_hz = _positive("rate_hz", rate_hz)
    with open(p, encoding="utf-8", errors="replace") as fh:
        head = [h.strip() for h in fh.readline().strip().split(",")]
    want = ["n_samples", "gyr_x", "gyr_y", "gyr_z", "acc_x", "acc_y", "acc_z"]
    if head != want:
        raise GyroInputError(f"{p}: not an imucal session (expected header {','.join(want)})")
    data = _loadtxt(p, skiprows=1, ncols=7)
    repairs = _Repairs(p.name)
    idx = data[:, 0]
    if not np.all(np.diff(idx) > 0):
        raise GyroInputError(f"{p}: n_samples does not increase")
    keep = _check_finite(p.name, {"d": data}, repairs)
    data = data[keep]
    t = data[:, 0] / rate_hz
    gyro = data[:, 1:4] * DEG
    accel = data[:, 4:7]
    sec = _imucal_sections(p, sections)
    pose = np.zeros(t.size)
    desc = []
    for name, (s0, s1) in sec.items():
        m = (data[:, 0] >= s0) & (data[:, 0] <= s1)
        if name in _IMUCAL_POSE:
            pose[m] = _IMUCAL_POSE[name]
        desc.append(f"{name}={s0}-{s1}")
    extra = {"static_pose_axis": pose} if sec else {}
    meta = _meta(
        str(p), "imucal", "likely Bosch BMI160 (NilsPod), +-2000 dps", rate_hz, repairs,
        timing=f"no timestamps in file: t = n_samples / {rate_hz:g} Hz",
        sections=", ".join(desc) if desc else "none",
        static_pose_axis="extra column: +-1/2/3 = +-x/y/z axis up (reads +-1 g), 0 = not a static section",
        rotation_reference=f"one full turn per *_rot section, imucal expected_angle = {IMUCAL_EXPECTED_ANGLE_DEG:g} deg",
    )
    return Recording(t_s=t, gyro_rad_s=gyro, accel_m_s2=accel, meta=meta, extra=extra)


def _imucal_sections(p: Path, sections) -> dict[str, tuple[int, int]]:
    sp = Path(sections) if sections is not None else p.with_name(p.stem + "_list.json")
    if not sp.exists():
        if sections is not None:
            raise GyroInputError(f"{sp}: no such section list")
        return {}
    try:
        raw = json.loads(sp.read_text(encoding="utf-8"))
        return {str(k): (int(v["start"]), int(v["end"])) for k, v in raw.items()}
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise GyroInputError(f"{sp}: not an imucal section list ({type(exc).__name__})") from None


def imucal_segments(rec: Recording) -> list[Segment]:
    """Rotation sections of an imucal recording as segments (one turn, −360° each)."""
    rate = float(rec.meta.get("rate_hz", "nan"))
    out = []
    for m in re.finditer(r"\b([xyz])_rot=(\d+)-(\d+)", rec.meta.get("sections", "")):
        s0, s1 = int(m.group(2)), int(m.group(3))
        out.append(Segment(s0 / rate, s1 / rate, m.group(1), IMUCAL_EXPECTED_ANGLE_DEG, label=f"imucal {m.group(1)}_rot"))
    return out


def read_imucal_annotated(
    path: str | os.PathLike,
    *,
    rate_hz: float = 204.8,
    lsb_per_dps: float = IMUCAL_RAW_LSB_PER_DPS,
    lsb_per_g: float = IMUCAL_RAW_LSB_PER_G,
) -> Recording:
    """imucal ``annotated_session.csv``: raw LSB, a ``part`` label per row, 204.8 Hz.

    Rows are stored grouped by part; they are sorted by the ``samples`` index (0…N−1,
    contiguous: only the annotated parts were kept, the gaps between them were cut out by the
    authors, so the time axis ``samples / rate_hz`` jumps between parts without a gap).
    Scales are datasheet-nominal (±2000 °/s: 16.384 LSB/(°/s); ±16 g: 2048 LSB/g).
    """
    p = Path(path)
    _require_file(p, "imucal annotated session CSV")
    rate_hz = _positive("rate_hz", rate_hz)
    lsb_per_dps = _positive("--lsb-per-dps", lsb_per_dps)
    lsb_per_g = _positive("--lsb-per-g", lsb_per_g)
    with open(p, encoding="utf-8", errors="replace") as fh:
        head = [h.strip() for h in fh.readline().strip().split(",")]
        want = ["part", "samples", "acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z"]
        if head != want:
            raise GyroInputError(f"{p}: not an imucal annotated session (expected header {','.join(want)})")
        parts: list[str] = []
        rows: list[list[float]] = []
        for lineno, line in enumerate(fh, 2):
            s = line.strip()
            if not s:
                continue
            f = s.split(",")
            if len(f) != 8:
                raise GyroInputError(f"{p}: line {lineno}: expected 8 values, got {len(f)}")
            try:
                rows.append([float(x) for x in f[1:]])
            except ValueError:
                raise GyroInputError(f"{p}: line {lineno}: text in a number") from None
            parts.append(f[0].strip())
    if not rows:
        raise GyroInputError(f"{p}: header only, no samples")
    data = np.asarray(rows)
    order = np.argsort(data[:, 0], kind="stable")
    data = data[order]
    part = np.asarray(parts)[order]
    if np.any(np.diff(data[:, 0]) <= 0):
        raise GyroInputError(f"{p}: repeated sample indices")
    repairs = _Repairs(p.name)
    repairs.note("rows sorted by the samples index (file is grouped by part)")
    keep = _check_finite(p.name, {"d": data}, repairs)
    data, part = data[keep], part[keep]
    t = data[:, 0] / rate_hz
    accel = data[:, 1:4] / lsb_per_g * G0_M_S2
    gyro = data[:, 4:7] / lsb_per_dps * DEG
    pose = np.array([_IMUCAL_POSE.get(x, 0.0) for x in part])
    sec: dict[str, tuple[int, int]] = {}
    for name in dict.fromkeys(part):
        idx = data[part == name, 0]
        sec[name] = (int(idx.min()), int(idx.max()))
    meta = _meta(
        str(p), "imucal_annotated", "likely Bosch BMI160 (NilsPod), raw LSB", rate_hz, repairs,
        scale=f"gyro {lsb_per_dps:g} LSB/(deg/s), accel {lsb_per_g:g} LSB/g (datasheet-nominal, not calibrated)",
        timing=f"t = samples / {rate_hz:g} Hz; only annotated parts kept, joined without gaps",
        sections=", ".join(f"{k}={a}-{b}" for k, (a, b) in sec.items()),
        static_pose_axis="extra column: +-1/2/3 = +-x/y/z axis up, 0 = rotation part",
        rotation_reference=(
            f"one full turn per *_rot part, imucal expected_angle = {IMUCAL_EXPECTED_ANGLE_DEG:g} deg; the raw gyro "
            "integrates to about +360 deg, so a fit against this reference gives R ~ -I as imucal's own snapshot"
        ),
    )
    return Recording(t_s=t, gyro_rad_s=gyro, accel_m_s2=accel, meta=meta, extra={"static_pose_axis": pose})


# ============================================================================ BROAD
def read_broad(path: str | os.PathLike) -> Recording:
    """BROAD benchmark trial (HDF5): IMU rad/s, m/s², OptiTrack orientation as the reference.

    ``opt_quat`` (w, x, y, z: the IMU frame w.r.t. ENU, i.e. S→W with W = ENU) goes to the
    ``ref_q*`` columns with its NaN rows kept (tracking lost). ``movement`` (1 = use for error
    metrics) and the magnetometer (µT) are extra columns. ``t_s = k / sampling_rate``.
    """
    p = Path(path)
    _require_file(p, "BROAD .hdf5 trial")
    repairs = _Repairs(p.name)
    with _h5(p) as h:
        for k in ("imu_gyr", "imu_acc"):
            if k not in h:
                raise GyroInputError(f"{p}: dataset {k!r} missing: not a BROAD trial")
        gyro = np.asarray(h["imu_gyr"][()], float)
        accel = np.asarray(h["imu_acc"][()], float)
        quat = np.asarray(h["opt_quat"][()], float) if "opt_quat" in h else None
        mov = np.asarray(h["movement"][()], float) if "movement" in h else None
        mag = np.asarray(h["imu_mag"][()], float) if "imu_mag" in h else None
        try:
            rate_hz = float(h.attrs["sampling_rate"])
        except (KeyError, ValueError, TypeError):
            raise GyroInputError(f"{p}: no sampling_rate attribute") from None
        info = h.attrs.get("info", "")
    rate_hz = _positive("sampling_rate", rate_hz)
    n = gyro.shape[0]
    if gyro.shape != (n, 3) or accel.shape != (n, 3):
        raise GyroInputError(f"{p}: imu_gyr/imu_acc shapes {gyro.shape}/{accel.shape} differ")
    keep = _check_finite(p.name, {"g": gyro, "a": accel}, repairs)
    idx = np.flatnonzero(keep)
    extra = {}
    if mov is not None:
        extra["movement"] = mov[keep]
    if mag is not None:
        for i, a in enumerate(AXES):
            extra[f"mag_{a}_uT"] = mag[keep, i]
    n_nan = int(np.count_nonzero(~np.all(np.isfinite(quat), axis=1))) if quat is not None else 0
    trial = str(info).splitlines()[2].replace("Trial: ", "") if isinstance(info, str) and len(str(info).splitlines()) > 2 else p.stem
    meta = _meta(
        str(p), "broad", "myon aktos-t", rate_hz, repairs,
        trial=trial,
        reference=f"ref_q* = OptiTrack opt_quat, S->W with W = ENU; {n_nan} rows NaN (tracking lost)",
        citation="Laidig et al., BROAD, Data 6(7):72, 2021, doi:10.3390/data6070072 (CC BY 4.0)",
    )
    return Recording(
        t_s=idx / rate_hz, gyro_rad_s=gyro[keep], accel_m_s2=accel[keep],
        ref_quat_wxyz=None if quat is None else quat[keep], meta=meta, extra=extra,
    )


# ============================================================================ imu_tk
def read_imutk(
    path: str | os.PathLike,
    *,
    lsb_per_dps: float | None = None,
    lsb_per_g: float | None = None,
) -> Recording:
    """IMU-TK xsens test data: ASCII (despite ``.mat``) ``t, x, y, z`` raw unsigned ADC.

    ``path`` is ``xsens_gyro.mat`` (or its folder); ``xsens_acc.mat`` beside it is read too.
    Gyro: (ADC − 32768) / 6258 rad/s (IMU-TK's initial guess, 109.22 LSB/(°/s)) unless
    ``lsb_per_dps`` is given. Accel: (ADC − 32768) / ``lsb_per_g`` g; with no value given the
    scale is estimated from the mean |ADC − 32768| over the initial 50 s static phase
    (announced as a repair; it absorbs the accel biases — calibrate for real numbers).
    """
    p = Path(path)
    if p.is_dir():
        p = p / "xsens_gyro.mat"
    _require_file(p, "IMU-TK xsens_gyro.mat (ASCII)")
    repairs = _Repairs(p.name)
    g = _loadtxt(p, skiprows=0, ncols=4, delimiter=None)
    ap = p.with_name(p.name.replace("gyro", "acc"))
    a = _loadtxt(ap, skiprows=0, ncols=4, delimiter=None) if ap.exists() and ap != p else None
    if a is not None and (a.shape != g.shape or not np.array_equal(a[:, 0], g[:, 0])):
        raise GyroInputError(f"{ap}: does not share the gyro file's timestamps")
    keep = _check_finite(p.name, {"g": g} if a is None else {"g": g, "a": a}, repairs)
    g = g[keep]
    a = a[keep] if a is not None else None
    t = g[:, 0] - g[0, 0]
    if lsb_per_dps is None:
        gyro = (g[:, 1:] - IMUTK_ADC_OFFSET) / IMUTK_LSB_PER_RAD_S
        gscale = f"(ADC - 32768) / {IMUTK_LSB_PER_RAD_S:g} LSB/(rad/s) (IMU-TK initial guess)"
    else:
        lsb_per_dps = _positive("--lsb-per-dps", lsb_per_dps)
        gyro = (g[:, 1:] - IMUTK_ADC_OFFSET) / lsb_per_dps * DEG
        gscale = f"(ADC - 32768) / {lsb_per_dps:g} LSB/(deg/s)"
    accel = None
    ascale = "none"
    if a is not None:
        araw = a[:, 1:] - IMUTK_ADC_OFFSET
        if lsb_per_g is None:
            still = t < IMUTK_STATIC_S
            lsb_per_g = float(np.mean(np.linalg.norm(araw[still], axis=1)))
            repairs.add(f"accel scale estimated as {lsb_per_g:.1f} LSB/g from |ADC - 32768| over the initial {IMUTK_STATIC_S:g} s static phase")
        lsb_per_g = _positive("--lsb-per-g", lsb_per_g)
        accel = araw / lsb_per_g * G0_M_S2
        ascale = f"(ADC - 32768) / {lsb_per_g:.6g} LSB/g"
    rate = (t.size - 1) / t[-1]
    meta = _meta(
        str(p), "imutk", "Xsens (raw 16-bit ADC)", rate, repairs,
        scale=f"gyro {gscale}; accel {ascale}; nominal, biases not removed",
        t0_s=repr(float(g[0, 0])),
    )
    return Recording(t_s=t, gyro_rad_s=gyro, accel_m_s2=accel, meta=meta)


# ============================================================================ gnss-ins-sim
def read_gnss_ins_sim(path: str | os.PathLike) -> Recording:
    """gnss-ins-sim logged data folder: ``gyro-0.csv`` (°/s), ``accel-0.csv`` (m/s²), ``time.csv`` (s)."""
    p = Path(path)
    d = p.parent if p.is_file() else p
    _require_file(d / "gyro-0.csv", "gnss-ins-sim gyro-0.csv")
    repairs = _Repairs(f"{d.name}")
    g = _loadtxt(d / "gyro-0.csv", skiprows=1, ncols=3)
    t = _loadtxt(d / "time.csv", skiprows=1, ncols=1)[:, 0] if (d / "time.csv").exists() else None
    a = _loadtxt(d / "accel-0.csv", skiprows=1, ncols=3) if (d / "accel-0.csv").exists() else None
    n = g.shape[0]
    if t is None:
        raise GyroInputError(f"{d}: time.csv missing")
    if t.shape[0] != n or (a is not None and a.shape[0] != n):
        raise GyroInputError(f"{d}: gyro-0.csv, accel-0.csv and time.csv have different row counts")
    arrs = {"g": g, "t": t} if a is None else {"g": g, "t": t, "a": a}
    keep = _check_finite(d.name, arrs, repairs)
    inc = np.concatenate([[True], np.diff(t) > 0])
    if not inc.all():
        raise GyroInputError(f"{d}/time.csv: timestamps do not increase")
    t, g = t[keep], g[keep]
    a = a[keep] if a is not None else None
    rate = (t.size - 1) / (t[-1] - t[0])
    meta = _meta(
        str(d), "gnss_ins_sim", f"{d.name} (part undocumented; Aceinna OpenIMU context)", rate, repairs,
        note="about one turn about Z (inferred from the integral, not a documented reference); bias apparently already removed",
    )
    return Recording(t_s=t, gyro_rad_s=g * DEG, accel_m_s2=a, meta=meta)


# ============================================================================ x-io Fusion
def read_fusion(path: str | os.PathLike) -> Recording:
    """x-io Fusion ``sensor_data.csv``: ``Time (s)``, gyro °/s, accel g, magnetometer µT.

    The timestamps jitter (7.6–30 ms around 10 ms); they are kept as recorded and the
    intervals longer than 1.5 × median are reported.
    """
    p = Path(path)
    _require_file(p, "x-io Fusion sensor_data.csv")
    with open(p, encoding="utf-8", errors="replace") as fh:
        head = [h.strip() for h in fh.readline().strip().split(",")]
    need = ["Time (s)"] + [f"Gyroscope {a} (deg/s)" for a in "XYZ"] + [f"Accelerometer {a} (g)" for a in "XYZ"]
    if any(h not in head for h in need):
        raise GyroInputError(f"{p}: not an x-io Fusion file (needs columns {', '.join(need)})")
    data = _loadtxt(p, skiprows=1, ncols=len(head))
    col = {h: i for i, h in enumerate(head)}
    repairs = _Repairs(p.name)
    keep = _check_finite(p.name, {"d": data[:, [col[h] for h in need]]}, repairs)
    data = data[keep]
    t = data[:, col["Time (s)"]]
    inc = np.concatenate([[True], np.diff(t) > 0])
    if not inc.all():
        repairs.add(f"dropped {int((~inc).sum())} rows whose timestamp repeats or goes backwards")
        data, t = data[inc], t[inc]
    gyro = data[:, [col[f"Gyroscope {a} (deg/s)"] for a in "XYZ"]] * DEG
    accel = data[:, [col[f"Accelerometer {a} (g)"] for a in "XYZ"]] * G0_M_S2
    extra = {}
    for a in "XYZ":
        h = f"Magnetometer {a} (uT)"
        if h in col:
            extra[f"mag_{a.lower()}_uT"] = data[:, col[h]]
    rep = timing_report(t)
    rate = (t.size - 1) / (t[-1] - t[0])
    meta = _meta(
        str(p), "fusion", "x-io Technologies device (model unstated)", rate, repairs,
        timing=f"jittery timestamps kept: median dt {rep.median_dt_s * 1e3:.2f} ms, max {rep.max_dt_s * 1e3:.1f} ms, {rep.n_gaps} intervals > 1.5 x median",
    )
    return Recording(t_s=t, gyro_rad_s=gyro, accel_m_s2=accel, meta=meta, extra=extra)


# ============================================================================ generic text
def _loadtxt(path: Path, *, skiprows: int, ncols: int, delimiter: str | None = ",") -> np.ndarray:
    """Numeric table with one-line errors naming the line and column of a bad value."""
    _require_file(path, "data file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data = np.loadtxt(path, delimiter=delimiter, skiprows=skiprows, ndmin=2, dtype=float)
    except (ValueError, UnicodeDecodeError):
        from gyrocore.data.recording import locate_bad_value

        raise GyroInputError(locate_bad_value(str(path), skiprows=skiprows, delimiter=delimiter)) from None
    if data.size == 0:
        raise GyroInputError(f"{path}: header only, no samples")
    if data.shape[1] != ncols:
        raise GyroInputError(f"{path}: rows have {data.shape[1]} values, expected {ncols}")
    return data


# ============================================================================ dispatcher
FORMATS = ("auto", "blackbox", "dataflash", "ulog", "sunsided", "tomisuarez2", "imucal", "imucal_annotated", "broad", "imutk", "gnss_ins_sim", "fusion", "csv", "parquet")


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
        segs.extend(Segment(s.t_start_s + shift, s.t_end_s + shift, s.axis, s.angle_deg, s.label) for s in c.segments)
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
        extra={k: np.concatenate([r.extra[k] + (sh if k.startswith("t_") and k.endswith("_s") else 0.0) for r, sh in recs])
               for k in sorted(extra_keys)},
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
        "csv": read_csv,
        "parquet": read_parquet,
    }
    reader = readers[fmt]
    if fmt not in ("csv", "parquet"):  # read_csv/read_parquet check memory themselves (and the CLI streams large CSV files)
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
_BYTES_PER_SOURCE_BYTE = {"ulog": 6.0, "broad": 6.0, "sunsided": 6.0, "blackbox": _BLACKBOX_BYTES_PER_BYTE, "dataflash": 6.0}


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


def read_any(path: str | os.PathLike) -> Recording:
    """A DESIGN.md data file (CSV or Parquet), or any set `gyroharness convert` reads (BROAD
    .hdf5, ULog, ...)."""
    if detect_format(path) in ("csv", "parquet"):
        return read_recording(path)
    return load_with_segments(path).recording


def load_any(path: str | os.PathLike, *, format: str = "auto", **options) -> Recording:
    """Read any supported source as a :class:`Recording` (see :func:`load_with_segments`)."""
    return load_with_segments(path, format=format, **options).recording
