"""Readers of the real measured sets (../shared/data): shapes, units, flips, repairs, segments.

Every expected figure comes from the set's PROVENANCE.md (measured there independently with
numpy on the raw files); the tolerances say why they are what they are. Tests skip when the
shared data folder is absent.
"""

from __future__ import annotations

import json
import subprocess
import sys
import warnings

import numpy as np
import pytest

from gyrocore.readers import common as cm
from gyrocore.readers import convert as cv
from gyrocore.errors import GyroInputError, RepairWarning
from gyrocore.data.checks import G0_M_S2
from gyrocore.data.recording import read_csv, write_csv
from gyrocore.data.segments import read_segments

DEG = np.pi / 180.0


def _quiet(fn, *a, **k):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RepairWarning)
        return fn(*a, **k)


def _integral_deg(rec, seg, bias_rad_s=0.0):
    """Rectangle-rule integral of (gyro − bias) over a segment, degrees, per axis."""
    m = (rec.t_s >= seg.t_start_s) & (rec.t_s <= seg.t_end_s)
    dt = np.diff(rec.t_s)[m[:-1]]
    w = (rec.gyro_rad_s - bias_rad_s)[:-1][m[:-1]]
    return np.rad2deg((w * dt[:, None]).sum(axis=0))


# ------------------------------------------------------------------ sunsided MPU-6050
@pytest.fixture(scope="module")
def sun(shared_data):
    return shared_data / "sunsided_mpu6050"


def test_sunsided_static_units_and_noise(sun):
    with pytest.warns(RepairWarning, match="bursty host timestamps"):
        rec = cv.read_sunsided(sun / "set-2" / "unmoved-with-x-pointing-forward-10min")
    assert rec.n == 65067  # PROVENANCE: 65 067 samples, no padding
    # PROVENANCE: 655.1 s; the uniform grid keeps the first and last host time
    assert rec.duration_s == pytest.approx(655.1, abs=0.1)
    assert np.allclose(np.diff(rec.t_s), rec.duration_s / (rec.n - 1), rtol=1e-9)
    assert "t_host_s" in rec.extra and rec.extra["t_host_s"][-1] == rec.t_s[-1]
    assert 99.3 <= rec.rate_hz <= 100.7  # PROVENANCE: mean 99.3–100.7 Hz
    std_dps = np.rad2deg(rec.gyro_rad_s.std(axis=0))
    # PROVENANCE: static gyro std ≈ 0.09–0.15 °/s (1/131 °/s quantum is < 0.01 °/s of it)
    assert np.all((std_dps > 0.085) & (std_dps < 0.155)), std_dps
    bias_dps = np.rad2deg(rec.gyro_rad_s.mean(axis=0))
    # PROVENANCE bias ≈ (4.54, 0.05–0.12, 1.02–1.12) °/s raw; X is negated by the flip
    assert bias_dps[0] == pytest.approx(-4.54, abs=0.02)
    assert bias_dps[2] == pytest.approx(1.12, abs=0.02)
    # specific force: the board lies z up, so f_z ≈ +1 g; MPU-6050 accel sensitivity
    # tolerance ±3 % and zero-g offset ≤ ±80 mg (datasheet) → within 0.1 g of 1 g
    f = rec.accel_m_s2.mean(axis=0)
    assert f[2] == pytest.approx(G0_M_S2, abs=0.1 * G0_M_S2)
    assert abs(f[0]) < 0.1 * G0_M_S2 and abs(f[1]) < 0.1 * G0_M_S2
    assert 25.14 - 0.01 <= rec.temp_c.min() and rec.temp_c.max() <= 25.61 + 0.01  # PROVENANCE T range
    assert rec.meta["format"] == "sunsided" and "gyro X negated" in rec.meta["repairs"]


@pytest.mark.parametrize(
    "rel, pose",
    [
        ("set-1/unmoved-x-pointing-up", 0),
        ("set-1/unmoved-x-pointing-forward", 2),
        ("set-2/unmoved-with-z-pointing-front-and-x-up", 0),
        ("set-2/unmoved-with-x-pointing-forward", 2),
    ],
)
def test_sunsided_accel_is_specific_force_up(sun, rel, pose):
    """The axis named 'up' (or z for 'x pointing forward', lying flat) reads +1 g after the
    per-set accel convention is undone (set-1: X negated; set-2: gravity direction)."""
    rec = _quiet(cv.read_sunsided, sun / rel)
    f = rec.accel_m_s2.mean(axis=0)
    assert f[pose] == pytest.approx(G0_M_S2, abs=0.1 * G0_M_S2)  # datasheet ±3 % / ±80 mg, as above


def test_sunsided_padding_rows_dropped(sun):
    with pytest.warns(RepairWarning, match="dropped 720 all-zero padding rows"):
        rec = cv.read_sunsided(sun / "set-1" / "unmoved-z-pointing-left")
    assert rec.n == 7000 - 720  # PROVENANCE: ends with 720 all-zero rows
    assert np.all(rec.extra["t_host_s"] > 0)
    with pytest.warns(RepairWarning, match="dropped 1 all-zero padding rows"):
        rec2 = cv.read_sunsided(sun / "set-2" / "unmoved-with-z-pointing-front-and-y-down")
    assert rec2.n == 10178 - 1
    assert rec2.temp_c.min() > 20.0  # the T == 0 padding value is gone


ROTATIONS = [
    ("set-1", "rotate-360ccw-around-x-pointing-forward", "x", "unmoved-x-pointing-forward"),
    ("set-1", "rotate-360ccw-around-y-pointing-left", "y", "unmoved-x-pointing-forward"),
    ("set-1", "rotate-360ccw-around-z-pointing-up", "z", "unmoved-x-pointing-forward"),
    ("set-2", "rotate-ccw-around-x-pointing-forward", "x", "unmoved-with-x-pointing-forward"),
    ("set-2", "rotate-ccw-around-x-pointing-up", "x", "unmoved-with-x-pointing-forward"),
    ("set-2", "rotate-ccw-around-y-pointing-left", "y", "unmoved-with-x-pointing-forward"),
    ("set-2", "rotate-ccw-around-z-pointing-up", "z", "unmoved-with-x-pointing-forward"),
]


@pytest.mark.parametrize("setname, name, axis, static", ROTATIONS)
def test_sunsided_rotations_integrate_to_plus_720_after_flip(sun, setname, name, axis, static):
    """README: two CCW 360° turns about the named axis. PROVENANCE's raw integrals are
    x −707…−721°, y/z +706…+728°; after the X flip every axis must give ≈ +720°.

    Tolerance 4 % (29°): MPU-6050 gyro sensitivity tolerance ±3 % (datasheet) plus ≈1 % for
    a hand rotation without end stops (PROVENANCE: ±2 % observed).
    """
    bias = _quiet(cv.read_sunsided, sun / setname / static).gyro_rad_s.mean(axis=0)
    conv = _quiet(cv.load_with_segments, sun / setname / name)
    assert conv.format == "sunsided"
    (seg,) = conv.segments
    i = "xyz".index(axis)
    assert seg.axis == axis and seg.angle_S_deg[i] == 720.0
    ang = _integral_deg(conv.recording, seg, bias)
    assert ang[i] == pytest.approx(720.0, rel=0.04)
    # and the raw X sign is really opposite (the flip is not a no-op)
    raw = _quiet(cv.load_with_segments, sun / setname / name, flip_gyro_x=False)
    assert raw.segments[0].angle_S_deg[i] == (-720.0 if axis == "x" else 720.0)
    bias_raw = bias * np.array([-1.0, 1.0, 1.0])
    assert _integral_deg(raw.recording, raw.segments[0], bias_raw)[i] == pytest.approx(
        raw.segments[0].angle_S_deg[i], rel=0.04
    )


def test_sunsided_no_retime_keeps_host_times(sun):
    with pytest.warns(RepairWarning, match="kept as recorded"):
        rec = cv.read_sunsided(sun / "set-2" / "rotate-ccw-around-z-pointing-up", retime=False)
    d = np.diff(rec.t_s)
    rep = cm.timing_report(rec.t_s)
    assert rep.bursty and rep.median_dt_s < 0.003 and d.max() > 0.2  # PROVENANCE: median 1–2 ms, gaps 0.25–0.5 s


def test_sunsided_gyro_accel_kinematics_documented(sun):
    """The raw set-1 gyro/accel pair is kinematically right-handed (df/dt ≈ −ω×f, corr > 0.8
    on a fast tilt recording); the README's X flip makes it mirror-consistent (corr < 0).
    This pins the finding reported in docs/data.md."""
    d = sun / "set-1" / "tilt-around-x-pointing-forward"
    flipped = _quiet(cv.read_sunsided, d)
    raw = _quiet(cv.read_sunsided, d, flip_gyro_x=False)
    # undo the accel X flip too, so raw is the file's axes exactly
    from dataclasses import replace

    raw = replace(raw, accel_m_s2=raw.accel_m_s2 * np.array([-1.0, 1.0, 1.0]))
    assert cm.frame_consistency(raw) > 0.8
    assert cm.frame_consistency(flipped) < 0.0


# ------------------------------------------------------------------ tomisuarez2
@pytest.fixture(scope="module")
def tomi(shared_data):
    return shared_data / "tomisuarez2_mpu6050"


def test_tomisuarez2_static_scale(tomi):
    rec = cv.read_tomisuarez2(tomi / "example_data_tinit_calc.csv")
    assert rec.n == 44930 and rec.rate_hz == pytest.approx(100.0)
    assert rec.t_s[1] - rec.t_s[0] == pytest.approx(0.01)
    lsb = rec.gyro_rad_s / DEG * 131.0
    # PROVENANCE: std 9.8/14.6/12.3 LSB, bias (−438, 143, −65) LSB (rounded to 0.1 / 1 LSB)
    assert np.allclose(lsb.std(axis=0), [9.8, 14.6, 12.3], atol=0.06)
    assert np.allclose(lsb.mean(axis=0), [-438, 143, -65], atol=0.6)
    # |f| ≈ 1 g: datasheet sensitivity ±3 %, zero-g offset ±80 mg
    assert np.linalg.norm(rec.accel_m_s2.mean(axis=0)) == pytest.approx(G0_M_S2, abs=0.1 * G0_M_S2)


def test_tomisuarez2_scale_override_and_segment(tomi):
    a = cv.read_tomisuarez2(tomi / "imu_90_x_rot.csv")
    b = cv.read_tomisuarez2(tomi / "imu_90_x_rot.csv", lsb_per_dps=65.5, lsb_per_g=8192.0)
    assert np.allclose(b.gyro_rad_s, a.gyro_rad_s * 2.0) and np.allclose(b.accel_m_s2, a.accel_m_s2 * 2.0)
    conv = cv.load_with_segments(tomi / "imu_90_x_rot.csv")
    (seg,) = conv.segments
    assert seg.angle_S_deg == (90.0, 0.0, 0.0)
    # README: rotation 15.2–23.3 s; the segment brackets it
    assert seg.t_start_s <= 15.2 and seg.t_end_s >= 22.0
    rec = conv.recording
    bias = rec.gyro_rad_s[rec.t_s < 10.0].mean(axis=0)
    # PROVENANCE: +90.7°; tolerance 4 % as for sunsided (±3 % sensitivity + hand)
    assert _integral_deg(rec, seg, bias)[0] == pytest.approx(90.0, rel=0.04)


def test_tomisuarez2_clipping_is_flagged(tomi, tmp_path):
    """Hand rotations in the calibration file hit the ±250 °/s range: −32768 LSB / 131."""
    rec = cv.read_tomisuarez2(tomi / "example_data_calibration.csv")
    out = tmp_path / "cal.csv"
    write_csv(rec, out)
    with pytest.warns(RepairWarning, match="saturated samples"):
        back = read_csv(out)
    sat = back.extra["saturated"] > 0
    assert sat.sum() >= 10
    assert np.all(np.isclose(np.abs(back.gyro_rad_s[sat]).max(axis=1), 32768 / 131 * DEG))


def test_tomisuarez2_bad_scale_is_error(tomi):
    with pytest.raises(GyroInputError, match="lsb-per-dps"):
        cv.read_tomisuarez2(tomi / "imu_static_test.csv", lsb_per_dps=0.0)


# ------------------------------------------------------------------ imucal
@pytest.fixture(scope="module")
def imucal(shared_data):
    return shared_data / "imucal_ferraris"


def test_imucal_ferraris_session(imucal):
    conv = cv.load_with_segments(imucal / "example_ferraris_session.csv")
    rec = conv.recording
    assert conv.format == "imucal" and rec.n == 10376
    assert rec.t_s[-1] == pytest.approx(10375 / 102.4)
    pose = rec.extra["static_pose_axis"]
    for code, axis, sign in [(1, 0, 1), (-1, 0, -1), (2, 1, 1), (-2, 1, -1), (3, 2, 1), (-3, 2, -1)]:
        f = rec.accel_m_s2[pose == code].mean(axis=0)
        # PROVENANCE: aligned axis reads ±(9.2…10.45) m/s² (uncalibrated accel)
        assert 9.1 < sign * f[axis] < 10.5
    still = pose != 0
    std_dps = np.rad2deg(rec.gyro_rad_s[still & (pose == 1)].std(axis=0))
    assert np.all((std_dps > 0.035) & (std_dps < 0.07))  # PROVENANCE: ≈0.045–0.06 °/s
    assert [s.axis for s in conv.segments] == ["x", "y", "z"]
    assert all(sum(s.angle_S_deg) == -360.0 for s in conv.segments)  # imucal expected_angle
    # PROVENANCE (raw, bias not removed, fs = 102.4): −371.9°, −354.8°, −359.2°
    got = [_integral_deg(rec, s)["xyz".index(s.axis)] for s in conv.segments]
    assert np.allclose(got, [-371.9, -354.8, -359.2], atol=0.6)  # one extra sample ≤ 0.5°


def test_imucal_annotated_session(imucal):
    conv = cv.load_with_segments(imucal / "annotated_session.csv")
    rec = conv.recording
    assert conv.format == "imucal_annotated" and rec.n == 9414
    assert np.all(np.diff(rec.t_s) > 0)  # file is grouped by part; rows sorted by index
    f = rec.accel_m_s2[rec.extra["static_pose_axis"] == 1].mean(axis=0)
    assert f[0] == pytest.approx(G0_M_S2, rel=0.05)  # 2048 LSB/g nominal; BMI160 sensitivity ±2 %+
    # PROVENANCE: integrated rotations ≈ 6016, 5800, 5821 LSB·s
    lsb_s = [_integral_deg(rec, s)["xyz".index(s.axis)] * 16.384 for s in conv.segments]
    assert np.allclose(lsb_s, [6016, 5800, 5821], rtol=0.005)


# ------------------------------------------------------------------ BROAD
BROAD = [
    ("02_undisturbed_slow_rotation_B.hdf5", 53240, 417, 3.2),
    ("05_undisturbed_slow_rotation_with_breaks_B.hdf5", 59212, 328, 3.4),
    ("07_undisturbed_fast_rotation_B.hdf5", 52518, 1454, 3.0),
    ("09_undisturbed_fast_rotation_with_breaks_B.hdf5", 53711, 1218, 1.3),
]


@pytest.mark.parametrize("name, n, max_dps, nan_pct", BROAD)
def test_broad(shared_data, tmp_path, name, n, max_dps, nan_pct):
    rec = cv.load_any(shared_data / "broad" / name)
    assert rec.n == n and rec.rate_hz == pytest.approx(285.714, abs=1e-3)
    assert np.rad2deg(np.linalg.norm(rec.gyro_rad_s, axis=1).max()) == pytest.approx(max_dps, abs=1.0)
    q = rec.ref_quat_wxyz
    bad = ~np.all(np.isfinite(q), axis=1)
    assert 100 * bad.mean() == pytest.approx(nan_pct, abs=0.05)
    assert np.allclose(np.linalg.norm(q[~bad], axis=1), 1.0, atol=1e-6)
    rest = rec.t_s < 20.0  # every trial rests ≥ 26 s at the start (PROVENANCE)
    assert np.linalg.norm(rec.accel_m_s2[rest], axis=1).mean() == pytest.approx(9.82, abs=0.05)
    std_dps = np.rad2deg(rec.gyro_rad_s[rest].std(axis=0))
    assert np.all((std_dps > 0.08) & (std_dps < 0.17))  # PROVENANCE: 0.09–0.16 °/s
    assert set(rec.extra) >= {"movement", "mag_x_uT"}
    # NaN reference rows survive the data file (only gyro/time/accel/temp NaN rows are repaired)
    out = tmp_path / "b.csv"
    write_csv(rec, out)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RepairWarning)
        back = read_csv(out)
    assert back.n == n and np.array_equal(np.isnan(back.ref_quat_wxyz), np.isnan(q))


# ------------------------------------------------------------------ PX4 ULog
def test_ulog_sample(shared_data):
    rec = cv.load_any(shared_data / "pyulog_samples" / "sample.ulg")
    assert rec.n == 17070 and rec.meta["format"] == "ulog"
    assert rec.ref_quat_wxyz is None  # the EKF attitude is not a reference
    assert {"ekf_qw", "ekf_qx", "ekf_qy", "ekf_qz"} <= set(rec.extra)
    still = rec.t_s > 10.0
    assert still.sum() == pytest.approx(14592, abs=30)  # PROVENANCE: 14 592 samples after 10 s
    mean_dps = np.rad2deg(rec.gyro_rad_s[still].mean(axis=0))
    std_dps = np.rad2deg(rec.gyro_rad_s[still].std(axis=0))
    assert np.allclose(mean_dps, [-0.073, -0.122, -0.159], atol=0.002)
    assert np.all((std_dps > 0.036) & (std_dps < 0.040))  # PROVENANCE: 0.037–0.039 °/s
    assert np.linalg.norm(rec.accel_m_s2[still], axis=1).mean() == pytest.approx(9.81, abs=0.2)
    assert np.median(np.diff(rec.t_s)) == pytest.approx(0.004, abs=1e-4)


def test_ulog_temperature(shared_data):
    with pytest.warns(RepairWarning, match="temperature"):
        rec = cv.read_ulog(shared_data / "pyulog_samples" / "sample_log_small.ulg")
    assert rec.temp_c is not None and np.all(np.isfinite(rec.temp_c))
    assert 0.0 < rec.temp_c.mean() < 80.0


def test_ulog_corrupt_is_one_line_error(tmp_path):
    p = tmp_path / "bad.ulg"
    p.write_bytes(b"ULog\x01\x12\x35" + b"\x00garbage" * 10)
    with pytest.raises(GyroInputError):
        cv.load_any(p)


# ------------------------------------------------------------------ IMU-TK, gnss-ins-sim, x-io
def test_imutk(shared_data):
    with pytest.warns(RepairWarning, match="accel scale estimated"):
        rec = cv.load_any(shared_data / "imu_tk_xsens" / "xsens_gyro.mat")
    assert rec.n == 51175 and rec.rate_hz == pytest.approx(100.0, abs=0.05)
    still = rec.t_s < 50.0
    adc = rec.gyro_rad_s[still] * 6258.0 + 32768.0
    assert np.allclose(adc.mean(axis=0), [32777.1, 32459.8, 32511.8], atol=0.6)  # PROVENANCE
    assert np.all((adc.std(axis=0) > 26.5) & (adc.std(axis=0) < 27.6))
    assert np.linalg.norm(rec.accel_m_s2[still], axis=1).mean() == pytest.approx(G0_M_S2, rel=1e-3)


@pytest.mark.parametrize("dev, total", [("bosch", (5.1, -1.2, 357.3)), ("nxp", (-0.3, -0.4, 359.8))])
def test_gnss_ins_sim(shared_data, dev, total):
    rec = cv.load_any(shared_data / "gnss_ins_sim_logged_360z" / dev)
    assert rec.n == 1000 and rec.rate_hz == pytest.approx(100.0)
    # PROVENANCE: Σω / 100 Hz, rounded to 0.1°
    assert np.allclose(np.rad2deg(rec.gyro_rad_s.sum(axis=0) / 100.0), total, atol=0.06)
    assert rec.accel_m_s2[:100, 2].mean() == pytest.approx(-9.82, abs=0.02)


def test_fusion(shared_data):
    rec = cv.load_any(shared_data / "fusion_xio" / "sensor_data.csv")
    assert rec.n == 13514 and rec.duration_s == pytest.approx(135.3, abs=0.1)
    first = rec.t_s < 5.0
    std_dps = np.rad2deg(rec.gyro_rad_s[first].std(axis=0))
    assert np.all((std_dps > 0.09) & (std_dps < 0.14))  # PROVENANCE 0.10–0.13 °/s
    assert (np.linalg.norm(rec.accel_m_s2, axis=1).mean() / G0_M_S2) == pytest.approx(1.005, abs=0.002)
    assert "mag_z_uT" in rec.extra


def test_known_good_sets_are_kinematically_consistent(shared_data):
    """Sanity of frame_consistency: sets documented as one right-handed IMU frame give > 0."""
    for rec in (
        cv.load_any(shared_data / "broad" / "02_undisturbed_slow_rotation_B.hdf5"),
        cv.load_any(shared_data / "imucal_ferraris" / "example_ferraris_session.csv"),
        cv.load_any(shared_data / "tomisuarez2_mpu6050" / "example_data_calibration.csv"),
    ):
        assert cm.frame_consistency(rec) > 0.3


# ------------------------------------------------------------------ dispatcher, CLI, determinism
def test_detect_format(shared_data):
    d = shared_data
    cases = {
        d / "pyulog_samples" / "sample.ulg": "ulog",
        d / "sunsided_mpu6050" / "set-1" / "pan-x-pointing-forward": "sunsided",
        d / "sunsided_mpu6050" / "set-1" / "pan-x-pointing-forward" / "mpu6050_gyroscope.mat": "sunsided",
        d / "tomisuarez2_mpu6050" / "imu_static_test.csv": "tomisuarez2",
        d / "imucal_ferraris" / "example_ferraris_session.csv": "imucal",
        d / "imucal_ferraris" / "annotated_session.csv": "imucal_annotated",
        d / "broad" / "02_undisturbed_slow_rotation_B.hdf5": "broad",
        d / "imu_tk_xsens" / "xsens_gyro.mat": "imutk",
        d / "gnss_ins_sim_logged_360z" / "nxp": "gnss_ins_sim",
        d / "fusion_xio" / "sensor_data.csv": "fusion",
    }
    for p, fmt in cases.items():
        assert cv.detect_format(p) == fmt, p


def test_option_not_applicable_is_error(shared_data):
    with pytest.raises(GyroInputError, match="--lsb-per-dps does not apply to format broad"):
        cv.load_any(shared_data / "broad" / "02_undisturbed_slow_rotation_B.hdf5", lsb_per_dps=131.0)


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "experiments.cli", *map(str, args)], capture_output=True, text=True)


def test_cli_convert_json_segments_force_and_determinism(shared_data, tmp_path):
    src = shared_data / "sunsided_mpu6050" / "set-2" / "rotate-ccw-around-y-pointing-left"
    out1, out2, seg = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "seg.csv"
    r1 = _cli("convert", src, "-o", out1, "--segments-out", seg, "--json")
    assert r1.returncode == 0, r1.stderr
    summary = json.loads(r1.stdout)  # stdout is only JSON
    assert summary["format"] == "sunsided" and summary["segments"] == 1
    assert [ln for ln in r1.stderr.splitlines() if ln.startswith("warning:")]  # the retiming is announced
    assert "Traceback" not in r1.stderr
    assert read_segments(seg)[0].axis == "y"
    # determinism across processes: same input, same bytes
    r2 = _cli("convert", src, "-o", out2)
    assert r2.returncode == 0 and out1.read_bytes() == out2.read_bytes()
    # no silent overwrite
    r3 = _cli("convert", src, "-o", out1)
    assert r3.returncode != 0 and r3.stderr.strip().splitlines() == [
        f"error: {out1} exists; pass --force to overwrite it"
    ]
    r4 = _cli("convert", src, "-o", out1, "--force")
    assert r4.returncode == 0


def test_convert_refuses_source_too_large_for_memory(shared_data, monkeypatch):
    import gyrocore.data.recording as rc

    monkeypatch.setattr(rc, "_available_memory_bytes", lambda: 10 * 2**20)  # 10 MiB free
    with pytest.raises(GyroInputError, match=r"MiB of broad data needs ~\d+ MiB to convert"):
        cv.load_any(shared_data / "broad" / "02_undisturbed_slow_rotation_B.hdf5")
    with pytest.raises(GyroInputError, match="MiB of sunsided data"):
        cv.load_any(shared_data / "sunsided_mpu6050" / "set-2" / "unmoved-with-x-pointing-forward-10min")


def test_concat_converted_joins_a_session_and_shifts_segments(shared_data, tmp_path):
    """Three sunsided rotate-* runs → one recording with three segments on its time axis;
    the CLI's --append gives the same file."""
    base = shared_data / "sunsided_mpu6050" / "set-1"
    names = [
        "rotate-360ccw-around-x-pointing-forward",
        "rotate-360ccw-around-y-pointing-left",
        "rotate-360ccw-around-z-pointing-up",
    ]
    parts = [_quiet(cv.load_with_segments, base / n) for n in names]
    c = cv.concat_converted(parts)
    r = c.recording
    assert r.n == sum(p.recording.n for p in parts)
    assert np.all(np.diff(r.t_s) > 0)
    # default gap: one sample interval of the previous part (no gap warning when read back)
    k = parts[0].recording.n
    assert r.t_s[k] - r.t_s[k - 1] == pytest.approx(1 / parts[0].recording.rate_hz)
    assert [s.axis for s in c.segments] == ["x", "y", "z"]
    for p, s in zip(parts, c.segments):
        (s0,) = p.segments
        # the shifted segment spans the same samples (same gyro integral)
        m0 = (p.recording.t_s >= s0.t_start_s) & (p.recording.t_s <= s0.t_end_s)
        m = (r.t_s >= s.t_start_s) & (r.t_s <= s.t_end_s)
        assert m.sum() == m0.sum()
        np.testing.assert_array_equal(r.gyro_rad_s[m], p.recording.gyro_rad_s[m0])
        assert s.angle_S_deg == s0.angle_S_deg
    assert "t_host_s" in r.extra and np.all(np.diff(r.extra["t_host_s"]) > 0)
    assert c.format == "sunsided" and "3 recordings" in r.meta["concatenated"]
    with pytest.raises(GyroInputError):
        cv.concat_converted([])
    # CLI
    out, seg = tmp_path / "rot.csv", tmp_path / "seg.csv"
    res = _cli(
        "convert",
        base / names[0],
        "--append",
        base / names[1],
        "--append",
        base / names[2],
        "-o",
        out,
        "--segments-out",
        seg,
        "--json",
    )
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["segments"] == 3
    back = read_csv(out)
    np.testing.assert_allclose(back.gyro_rad_s, r.gyro_rad_s, rtol=1e-15, atol=0)
    assert [s.axis for s in read_segments(seg)] == ["x", "y", "z"]


def test_sunsided_frames_per_set(sun):
    """Evidence for docs/data.md (H10 follow-up): with the accel as converted, the raw gyro is
    not frame-consistent (set-1 y turn, all of set-2), the README X flip neither, but a 180°
    turn of the gyro is, different per set: set-1 (+,−,−), set-2 (−,−,+)."""
    from dataclasses import replace

    cases = {
        "set-1": (["rotate-360ccw-around-y-pointing-left", "tilt-around-y-pointing-left", "tilt-sphere"], (1, -1, -1)),
        "set-2": (
            ["rotate-ccw-around-x-pointing-forward", "rotate-ccw-around-y-pointing-left", "full-sphere"],
            (-1, -1, 1),
        ),
    }
    for setname, (names, pattern) in cases.items():
        fc_flipped = []
        for name in names:
            flipped = _quiet(cv.read_sunsided, sun / setname / name)  # README flip: gyro (−, +, +) of raw
            raw = replace(flipped, gyro_rad_s=flipped.gyro_rad_s * np.array([-1.0, 1.0, 1.0]))
            turned = replace(raw, gyro_rad_s=raw.gyro_rad_s * np.array(pattern, float))
            # measured: turned +0.57 … +0.88, raw −0.26 … −0.82 (docs/data.md)
            assert cm.frame_consistency(turned) > 0.2, (setname, name)
            assert cm.frame_consistency(raw) < -0.2, (setname, name)
            fc_flipped.append(cm.frame_consistency(flipped))
        # the README flip is inconsistent on at least one of them too (set-1 all, set-2 the y turn)
        assert min(fc_flipped) < -0.2, (setname, fc_flipped)
