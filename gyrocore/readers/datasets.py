"""Readers of the public research sets (docs/data.md; each folder's PROVENANCE.md under
``../shared/data``): sunsided, tomisuarez2, imucal, BROAD, imu_tk, gnss-ins-sim, x-io Fusion.
Each returns SI arrays in the DESIGN.md columns with metadata ``source``, ``format``,
``sensor``, ``rate_hz`` and ``repairs``; the hand-rotation sessions also give their known
rotations as :class:`~gyrocore.data.segments.Segment` rows."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from gyrocore.errors import GyroInputError, warn_repair
from gyrocore.data.checks import DEG, G0_M_S2
from gyrocore.data.recording import AXES, Recording

from gyrocore.data.segments import Segment

from .common import (
    _check_finite,
    _h5,
    _loadtxt,
    _meta,
    _positive,
    _Repairs,
    _require_file,
    motion_span,
    retime_uniform,
    timing_report,
)

__all__ = [
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
        repairs.note(
            "gyro X negated (README: X positive = clockwise) to make it counter-clockwise-positive like Y and Z"
        )
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
        f"sunsided/sensor-fusion data/{set_name}/{d.name}",
        "sunsided",
        "InvenSense MPU-6050 (+-250 dps, +-2 g)",
        rate,
        repairs,
        recording=f"{set_name}/{d.name}",
        timing="uniform grid at the mean rate (host times in t_host_s)"
        if (rep.bursty and retime)
        else "host receive times",
        frame_note=(
            "gyro X flip follows the README; the raw gyro/accel pair is kinematically right-handed in set-1, "
            "so with the flip gyro and accel are mirror-consistent only: see docs/data.md"
            if flip_gyro_x
            else "raw gyro axes (no X flip)"
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
    return [Segment.about_axis(t0, t1, axis, angle, label=f"{name}: two CCW 360 deg turns (README)")]


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
        raise GyroInputError(
            f"{p}: not a tomisuarez2 file (expected 'Fs,...' and the header ax,ay,az,gx,gy,gz on line 5)"
        )
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
        str(p),
        "tomisuarez2",
        "InvenSense MPU-6050 (raw LSB)",
        rate_hz,
        repairs,
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
    return [Segment.about_axis(t0, t1, "x", 90.0, label="imu_90_x_rot: +90 deg about X (README)")]


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
        str(p),
        "imucal",
        "likely Bosch BMI160 (NilsPod), +-2000 dps",
        rate_hz,
        repairs,
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
        out.append(
            Segment.about_axis(
                s0 / rate, s1 / rate, m.group(1), IMUCAL_EXPECTED_ANGLE_DEG, label=f"imucal {m.group(1)}_rot"
            )
        )
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
        str(p),
        "imucal_annotated",
        "likely Bosch BMI160 (NilsPod), raw LSB",
        rate_hz,
        repairs,
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
    trial = (
        str(info).splitlines()[2].replace("Trial: ", "")
        if isinstance(info, str) and len(str(info).splitlines()) > 2
        else p.stem
    )
    meta = _meta(
        str(p),
        "broad",
        "myon aktos-t",
        rate_hz,
        repairs,
        trial=trial,
        reference=f"ref_q* = OptiTrack opt_quat, S->W with W = ENU; {n_nan} rows NaN (tracking lost)",
        citation="Laidig et al., BROAD, Data 6(7):72, 2021, doi:10.3390/data6070072 (CC BY 4.0)",
    )
    return Recording(
        t_s=idx / rate_hz,
        gyro_rad_s=gyro[keep],
        accel_m_s2=accel[keep],
        ref_quat_wxyz=None if quat is None else quat[keep],
        meta=meta,
        extra=extra,
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
            repairs.add(
                f"accel scale estimated as {lsb_per_g:.1f} LSB/g from |ADC - 32768| over the initial {IMUTK_STATIC_S:g} s static phase"
            )
        lsb_per_g = _positive("--lsb-per-g", lsb_per_g)
        accel = araw / lsb_per_g * G0_M_S2
        ascale = f"(ADC - 32768) / {lsb_per_g:.6g} LSB/g"
    rate = (t.size - 1) / t[-1]
    meta = _meta(
        str(p),
        "imutk",
        "Xsens (raw 16-bit ADC)",
        rate,
        repairs,
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
        str(d),
        "gnss_ins_sim",
        f"{d.name} (part undocumented; Aceinna OpenIMU context)",
        rate,
        repairs,
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
        str(p),
        "fusion",
        "x-io Technologies device (model unstated)",
        rate,
        repairs,
        timing=f"jittery timestamps kept: median dt {rep.median_dt_s * 1e3:.2f} ms, max {rep.max_dt_s * 1e3:.1f} ms, {rep.n_gaps} intervals > 1.5 x median",
    )
    return Recording(t_s=t, gyro_rad_s=gyro, accel_m_s2=accel, meta=meta, extra=extra)
