"""PX4 ULog logs (pyulog): the sensor_gyro / sensor_combined topics as a :class:`Recording`."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording

from .common import _check_finite, _meta, _Repairs, _require_file

__all__ = ["read_ulog", "ULOG_MIN_GYRO_RATE_HZ", "ULOG_NOISE_GYRO_RATE_HZ"]


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
        raise GyroInputError(
            f"{p}: not a readable ULog file ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        ) from None
    if gyro_instance is not None:
        return _read_ulog_sensor_gyro(ulog, p, int(gyro_instance))
    repairs = _Repairs(p.name)
    try:
        sc = ulog.get_dataset("sensor_combined", multi_id)
    except (KeyError, IndexError, ValueError):
        raise GyroInputError(
            f"{p}: no sensor_combined topic (instance {multi_id}) in the log{_gyro_topics_hint(ulog)}"
        ) from None
    if sc.data["timestamp"].size == 0:
        raise GyroInputError(f"{p}: sensor_combined (instance {multi_id}) holds no samples")
    missing = [f for f in ("gyro_rad[0]", "gyro_rad[1]", "gyro_rad[2]") if f not in sc.data]
    if missing:
        # a PX4 release whose sensor_combined names its fields otherwise: not guessed
        raise GyroInputError(
            f"{p}: sensor_combined has no {', '.join(missing)} (its fields: {', '.join(sorted(sc.data)[:12])}): a "
            f"layout this reader does not know{_gyro_topics_hint(ulog)}"
        )
    ts_us = np.asarray(sc.data["timestamp"], dtype=np.int64)
    gyro = np.column_stack([sc.data[f"gyro_rad[{i}]"] for i in range(3)]).astype(float)
    if all(f"accelerometer_m_s2[{i}]" in sc.data for i in range(3)):
        accel = np.column_stack([sc.data[f"accelerometer_m_s2[{i}]"] for i in range(3)]).astype(float)
    else:
        accel = None
        repairs.note("sensor_combined has no accelerometer_m_s2[0..2]: gyro only")
    keep = _check_finite(p.name, {"g": gyro} if accel is None else {"g": gyro, "a": accel}, repairs)
    # timestamps must increase strictly
    order_ok = np.concatenate([[True], np.diff(ts_us) > 0])
    if not order_ok.all():
        repairs.add(f"dropped {int((~order_ok).sum())} rows whose timestamp repeats or goes backwards")
        keep &= order_ok
    ts_us, gyro = ts_us[keep], gyro[keep]
    accel = None if accel is None else accel[keep]
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
                repairs.add(
                    f"temperature (sensor_gyro, {tt.size} samples) held at its nearest value for {n_out} gyro samples outside its span"
                )
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
        str(p),
        "ulog",
        sensor,
        rate,
        repairs,
        t0_us=str(int(ts_us[0])),
        calibration="gyro already calibrated (CAL_GYRO offsets) and board-rotated by PX4",
        temperature=temp_note,
        note="ekf_q* columns are PX4's attitude estimate (vehicle_attitude), NOT a reference",
    )
    return Recording(t_s=t_s, gyro_rad_s=gyro, accel_m_s2=accel, temp_c=temp, meta=meta, extra=extra)


def _gyro_topics_hint(ulog) -> str:
    """'' or "; it logs sensor_gyro 0 (...Hz), ...: read one with --gyro-instance N" — what the log
    holds instead, so the user knows which reader option applies."""
    out, readable = [], []
    for d in ulog.data_list:
        if d.name in ("sensor_gyro", "sensor_gyro_fifo", "vehicle_angular_velocity"):
            t = np.asarray(d.data["timestamp"], float)
            hz = (t.size - 1) / ((t[-1] - t[0]) * 1e-6) if t.size > 1 and t[-1] > t[0] else float("nan")
            out.append(f"{d.name} {d.multi_id} ({hz:.3g} Hz)")
            if d.name == "sensor_gyro" and hz >= ULOG_MIN_GYRO_RATE_HZ:
                readable.append(str(d.multi_id))
    if not out:
        return "; it logs no gyro topic (sensor_gyro, sensor_gyro_fifo, vehicle_angular_velocity)"
    tail = f"; read sensor_gyro with --gyro-instance {' or '.join(readable)}" if readable else ""
    return f"; it logs {', '.join(out)}{tail}"


def _read_ulog_sensor_gyro(ulog, p: Path, inst: int) -> Recording:
    """``sensor_gyro`` instance ``inst`` of a ULog as a recording (see :func:`read_ulog`)."""
    have = sorted(int(d.multi_id) for d in ulog.data_list if d.name == "sensor_gyro")
    if inst not in have:
        raise GyroInputError(
            f"{p}: no sensor_gyro instance {inst} in the log (instances: {', '.join(map(str, have)) or 'none'})"
        )
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
        repairs.add(
            f"sensor_gyro[{inst}] is logged at {rate:.3g} Hz: enough for bias against temperature, "
            f"not for noise identification or vibration"
        )
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
        str(p),
        "ulog",
        f"PX4 {info.get('ver_hw', 'unknown hardware')} sensor_gyro[{inst}] (device {dev})",
        (t_s.size - 1) / t_s[-1],
        repairs,
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
