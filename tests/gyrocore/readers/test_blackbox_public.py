"""Blackbox reader on logs it was not developed on, and the INAV path.

Data: ``../shared/data/blackbox_public`` (PROVENANCE.md there): a Betaflight 4.2.0 flight
(LOG00037.BFL, fc-blackbox test data, MIT/Apache-2.0) and an INAV 9.0.1 file of three ground logs
(INAV-Toolkit, GPL-3.0). Fetched public data is not committed to the project: the data tests skip
when the folder is absent; ``GYROHARNESS_BLACKBOX_PUBLIC`` may point at another copy of it.
The tests that need no data (INAV header handling, version refusal) always run.

Expected figures come from outside this reader: the Rust parser blackbox-log's snapshot of
LOG00037.BFL (frame count, field extremes), INAV's blackbox.c / blackbox_fielddefs.h /
sensors/gyro.c (revision named in ``gyrocore.readers.blackbox_firmware.INAV_READ``), and an independent Welch
estimate with scipy.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from gyrocore.readers import blackbox as bb
from gyrocore.readers import blackbox_firmware as bf
from gyrocore.errors import GyroInputError, RepairWarning

DEG = math.pi / 180.0
BF42 = "LOG00037.BFL"
INAV = "blackbox_log_2026-02-21_145057.TXT"


@pytest.fixture(scope="module")
def public_dir(request):
    env = os.environ.get("GYROHARNESS_BLACKBOX_PUBLIC")
    if env:
        d = Path(env)
    else:
        d = request.getfixturevalue("shared_data") / "blackbox_public"
    if not d.is_dir():
        pytest.skip(f"public blackbox logs folder {d} absent (see its PROVENANCE.md)")
    return d


def _path(public_dir, name):
    p = public_dir / name
    if not p.exists():
        pytest.skip(f"{p} absent")
    return p


def _read(path, **kw):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always", RepairWarning)
        rec = bb.read_blackbox(path, **kw)
    return rec, [str(x.message) for x in w if issubclass(x.category, RepairWarning)]


# ----------------------------------------------------------------------------- no data needed
#: INAV blackbox.c ``blackboxWriteSysinfo`` header keys, in the order the source writes them
#: (USE_ADC, USE_BARO, USE_MAG, USE_DYNAMIC_FILTERS, USE_RPM_FILTER targets; currentMeter only
#: with FEATURE_CURRENT_METER).
INAV_SYSINFO_KEYS = (
    "Firmware type",
    "Firmware revision",
    "Firmware date",
    "Log start datetime",
    "Craft name",
    "P interval",
    "minthrottle",
    "maxthrottle",
    "gyro_scale",
    "motorOutput",
    "acc_1G",
    "vbat_scale",
    "vbatcellvoltage",
    "vbatref",
    "currentMeter",
    "looptime",
    "rc_rate",
    "rc_expo",
    "rc_yaw_expo",
    "thr_mid",
    "thr_expo",
    "tpa_rate",
    "tpa_breakpoint",
    "rates",
    "rollPID",
    "pitchPID",
    "yawPID",
    "altPID",
    "posPID",
    "posrPID",
    "levelPID",
    "magPID",
    "velPID",
    "yaw_lpf_hz",
    "dterm_lpf_hz",
    "dterm_lpf_type",
    "deadband",
    "yaw_deadband",
    "gyro_lpf",
    "gyro_lpf_hz",
    "dynamicGyroNotchQ",
    "dynamicGyroNotchMinHz",
    "acc_lpf_hz",
    "acc_hardware",
    "baro_hardware",
    "mag_hardware",
    "serialrx_provider",
    "motor_pwm_protocol",
    "motor_pwm_rate",
    "debug_mode",
    "features",
    "waypoints",
    "acc_notch_hz",
    "acc_notch_cutoff",
    "axisAccelerationLimitYaw",
    "axisAccelerationLimitRollPitch",
    "rpm_gyro_filter_enabled",
    "rpm_gyro_harmonics",
    "rpm_gyro_min_hz",
    "rpm_gyro_q",
)


def _inav_header(rev="INAV 9.0.1 (d44f2cf6) IFLIGHT_BLITZ_F722", **kw):
    h = {
        "Data version": 2,
        "Firmware revision": rev,
        "Firmware type": "Cleanflight",
        "looptime": 500,
        "P interval": "1/2",
        "gyro_lpf_hz": 30,
        "dynamicGyroNotchMinHz": 50,
        "dynamicGyroNotchQ": 250,
        "rpm_gyro_filter_enabled": 0,
        "rpm_gyro_min_hz": 100,
    }
    h.update(kw)
    return h


@pytest.mark.parametrize("rev", ["INAV 8.0.1 (abc) X", "INAV 7.1.2 (4e1e59eb) Y", "INAV 9.1.0 (1) Z"])
def test_inav_release_not_read_is_one_error_naming_it(rev):
    with pytest.raises(GyroInputError) as e:
        bf.firmware_info(_inav_header(rev=rev), "f.TXT")
    msg = str(e.value)
    assert rev.split(" (")[0] in msg and "\n" not in msg and "9.0" in msg


def test_inav_rates_and_filters_from_header():
    fw = bf.firmware_info(_inav_header(), "f.TXT")
    assert (fw.name, fw.version) == ("inav", (9, 0, 1))
    r = bf.inav_loop_rates(_inav_header())
    # looptime 500 µs → 2 kHz loop; P interval 1/2 → one frame per two loops
    assert r["pid_hz"] == 2000 and r["log_hz_nominal"] == 1000 and math.isnan(r["gyro_hz"])
    chain = bf.inav_filter_chain(_inav_header(rpm_gyro_filter_enabled=1), r)
    assert [(s.kind, s.dynamic) for s in chain] == [("rpm_notch", True), ("pt1", False), ("dyn_notch", True)]
    assert chain[1].cutoff_hz == 30 and chain[1].rate_hz == 2000
    assert [s.kind for s in bf.inav_filter_chain(_inav_header(gyro_lpf_hz=0), r)] == ["dyn_notch"]


def test_inav_end_of_log_marker():
    # blackbox.c: blackboxPrintf("End of log (disarm reason:%d)", getDisarmReason()); blackboxWrite(0)
    assert bb._INAV_END_OF_LOG.match(b"End of log (disarm reason:4)\x00")
    assert not bb._INAV_END_OF_LOG.match(b"End of log (disarm reason:4)")


# ----------------------------------------------------------------------------- Betaflight 4.2.0
def test_betaflight_420_flight_matches_an_independent_parser(public_dir):
    rec, warns = _read(_path(public_dir, BF42))
    info = json.loads(rec.meta["logs"])
    # blackbox-log (Rust) snapshot of this file: 16,774 main frames, one log, End event read
    assert [g["frames"] for g in info] == [16774] and info[0]["corrupt_skipped"] == 0 and not info[0]["truncated"]
    assert not warns
    # blackbox-log snapshot extremes of gyroADC (deg/s, gyro_scale 1.0) and debug[0..2] (GYRO_SCALED).
    # Not bit-equal: 6 of the 12 extremes differ by 1-2 deg/s (ours are continuous with their
    # neighbouring frames, e.g. pitch -117, -120, -122, -122, -122 near the end). Betaflight 4.2.0's
    # writer predicts P-frame gyro/debug values by (prev1 + prev2) / 2 in C (truncation toward
    # zero, blackbox.c:643), as orangebox decodes it; a decoder that rounds that average otherwise
    # drifts by 1 LSB (= 1 deg/s) per differing P frame until the next I frame (every
    # 32nd frame here: I interval 256 loops / P interval 8); the largest difference seen is 2 deg/s.
    snap_g = [(-30, 37), (-120, 197), (-43, 28)]
    snap_d = [(-33, 45), (-125, 214), (-54, 33)]
    g = np.round(np.degrees(rec.gyro_rad_s)).astype(int)
    d = np.column_stack([np.round(np.degrees(rec.extra[f"gyro_prefilter_{a}_rad_s"])).astype(int) for a in "xyz"])
    for arr, snap in ((g, snap_g), (d, snap_d)):
        for c, (lo, hi) in zip(arr.T, snap):
            assert abs(c.min() - lo) <= 2 and abs(c.max() - hi) <= 2
    # header: 8 kHz loop (looptime 125), P interval 8 → 1 kHz; 4.2: debug_mode 6 = GYRO_SCALED = raw gyro
    assert rec.meta["firmware_name"] == "betaflight" and rec.meta["firmware_version"] == "4.2.0"
    assert float(rec.meta["gyro_rate_hz"]) == 8000 and float(rec.meta["log_rate_nominal_hz"]) == 1000
    assert (
        rec.meta["debug_mode"] == "6 = DEBUG_GYRO_SCALED" and json.loads(rec.meta["gyro_prefilter"])["signal"] == "raw"
    )
    chain = [(s["kind"], s["cutoff_hz"]) for s in json.loads(rec.meta["gyro_filters"])]
    assert chain == [("dyn_notch", 125), ("rpm_notch", 100), ("dyn_lpf", 240), ("pt1", 300)]
    # accSmooth / acc_1G (2048 LSB/g): |a| median within 0.5–3 g over a flight
    assert 0.5 * 9.81 < np.median(np.linalg.norm(rec.accel_m_s2, axis=1)) < 3 * 9.81


def test_vibration_on_betaflight_420_flight(public_dir, tmp_path):
    """`gyroharness vibration` on a flight it was not developed on: the raw (GYRO_SCALED) gyro's
    rms above 40 Hz agrees with an independent whole-flight Welch estimate (scipy, 1 s segments)
    inside the estimator's interval (91 % of the frames are the same airborne ones), and the
    as-flown gyroADC carries less (every firmware filter has |H| ≤ 1)."""
    from scipy import signal as ss

    p = _path(public_dir, BF42)
    cp = subprocess.run(
        [sys.executable, "-m", "experiments.cli", "vibration", str(p), "--json", "-o", str(tmp_path / "spec.json")],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert cp.returncode == 0, cp.stderr
    d = json.loads(cp.stdout)
    assert d["signal"] == "raw" and abs(d["rate_hz"] - 1000) < 1 and (tmp_path / "spec.json").exists()
    rec, _ = _read(p)
    g = np.column_stack([rec.extra[f"gyro_prefilter_{a}_rad_s"] for a in "xyz"])
    f, P = ss.welch(g, fs=1000.0, nperseg=1000, axis=0)
    welch = np.sqrt(np.sum(P[f >= 40], axis=0) * (f[1] - f[0]))
    for i, ax in enumerate("xyz"):
        lo, hi = d["rms_above_40hz_interval_rad_s"][ax]
        assert lo <= welch[i] <= hi, (ax, lo, welch[i], hi)
    cp2 = subprocess.run(
        [sys.executable, "-m", "experiments.cli", "vibration", str(p), "--json", "--signal", "gyro", "--no-undo"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert cp2.returncode == 0, cp2.stderr
    flown = json.loads(cp2.stdout)["rms_above_40hz_rad_s"]
    assert all(flown[a] < d["rms_above_40hz_rad_s"][a] for a in "xyz")


# ----------------------------------------------------------------------------- INAV 9.0.1
def test_inav_901_logs_header_layout_units_and_gyro_raw(public_dir):
    p = _path(public_dir, INAV)
    data = p.read_bytes()
    # the header writer of the source read: every sysinfo key, in the source's order
    first = data[: data.index(b"H Product", 10)] if data.count(b"H Product") > 1 else data
    keys = [ln[2:].split(b":", 1)[0].decode() for ln in first.split(b"\n") if ln.startswith(b"H ")]
    sysinfo = [k for k in keys if not k.startswith("Field ") and k not in ("Product", "Data version", "I interval")]
    assert tuple(sysinfo) == INAV_SYSINFO_KEYS
    rec, warns = _read(p)
    info = json.loads(rec.meta["logs"])
    # three logs, each closed by INAV's "End of log (disarm reason:N)" event, nothing corrupt;
    # frame counts agree with the INAV-Toolkit native decoder (25,092 in all)
    assert [g["frames"] for g in info] == [1814, 15497, 7781]
    assert all(g["corrupt_skipped"] == 0 and not g["truncated"] for g in info)
    assert rec.meta["firmware_name"] == "inav" and rec.meta["firmware_version"] == "9.0.1"
    assert "00b5622b" in rec.meta["firmware_source_read"]
    # loop 2 kHz (looptime 500), P interval 1/2 → 1 kHz nominal; measured within 3 %
    assert float(rec.meta["pid_rate_hz"]) == 2000 and float(rec.meta["log_rate_nominal_hz"]) == 1000
    assert abs(float(rec.meta["log_rate_measured_hz"]) / 1000 - 1) < 0.03
    pre = json.loads(rec.meta["gyro_prefilter"])
    assert pre["signal"] == "raw" and "gyroRaw" in pre["source"]
    assert [(s["kind"], s["cutoff_hz"]) for s in json.loads(rec.meta["gyro_filters"])] == [
        ("pt1", 30),
        ("dyn_notch", 50),
    ]
    # units on the data: the quad sits on the ground (motors at idle), so |a| = 1 g
    # (accSmooth = lrintf(acc.accADCf · acc_1G), acc_1G 2048) and the gyro in deg/s stays within
    # a few deg/s of zero (a count unit, 16.4 LSB per deg/s, would not)
    li = rec.extra["log_index"]
    still = li == 1
    assert abs(np.median(np.linalg.norm(rec.accel_m_s2[still], axis=1)) / 9.80665 - 1) < 0.02
    raw = np.column_stack([rec.extra[f"gyro_prefilter_{a}_rad_s"] for a in "xyz"])
    assert np.max(np.abs(np.degrees(raw[still]))) <= 3
    # the filtered gyro (main LPF 30 Hz and more) varies less than the raw one
    assert np.all(rec.gyro_rad_s.std(axis=0) < raw.std(axis=0))
    assert "INAV header lacks filters" in rec.meta["lacks"]


def test_inav_ground_log_vibration_says_no_airborne_stretch(public_dir):
    p = _path(public_dir, INAV)
    cp = subprocess.run(
        [sys.executable, "-m", "experiments.cli", "vibration", str(p), "--log-index", "2"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert cp.returncode != 0
    err = [ln for ln in cp.stderr.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "airborne" in err[0] and "Traceback" not in cp.stderr


def test_inav_truncated_and_corrupt(public_dir, tmp_path):
    p = _path(public_dir, INAV)
    full, _ = _read(p, log_index=2)
    data = p.read_bytes()
    starts = [i for i in range(len(data)) if data.startswith(b"H Product:Blackbox", i)]
    log2 = data[starts[1] : starts[2]]
    cut = tmp_path / "cut.TXT"
    cut.write_bytes(log2[: len(log2) // 2])
    rec, warns = _read(cut)
    assert len([w for w in warns if "truncated" in w]) == 1
    assert 1000 < rec.n < full.n and np.array_equal(rec.gyro_rad_s, full.gyro_rad_s[: rec.n])
    bad = bytearray(log2)
    rng = np.random.default_rng(1601)
    for s in rng.integers(len(log2) // 4, 3 * len(log2) // 4, size=4):
        bad[s : s + 5] = b"\x00\xff\x13\x99\x42"
    q = tmp_path / "bad.TXT"
    q.write_bytes(bytes(bad))
    rec2, warns2 = _read(q)
    assert json.loads(rec2.meta["logs"])[0]["corrupt_skipped"] >= 1 and any("corrupt" in w for w in warns2)
    # what is kept is real: kept frames' times are frames of the clean read with the same gyro
    t_clean = np.round(full.t_s * 1e6).astype(np.int64)
    t_kept = np.round(rec2.t_s * 1e6).astype(np.int64)
    idx = np.searchsorted(t_clean, t_kept)
    ok = (idx < t_clean.size) & (t_clean[np.minimum(idx, t_clean.size - 1)] == t_kept)
    assert ok.mean() > 0.99 and rec2.n > full.n - 4 * 300


# ----------------------------------------------------------------------------- Cleanflight
@pytest.mark.parametrize(
    "rev,equiv", [("Cleanflight 2.4.1", (3, 4, 1)), ("Cleanflight 2.5.0", (3, 5, 0)), ("Cleanflight 4.2.2", (4, 2, 2))]
)
def test_cleanflight_release_reads_as_its_betaflight_source(rev, equiv):
    """Cleanflight's debug list per release, read in cleanflight/cleanflight (see
    CLEANFLIGHT_AS_BETAFLIGHT): 2.4.x = Betaflight 3.4, 2.5.0 = 3.5.0, 4.2.x = 4.2.x."""
    fw = bf.firmware_info({"Data version": 2, "Firmware revision": f"{rev} (abc) OMNIBUSF4"}, "f.BFL")
    assert fw.name == "cleanflight" and fw.version == equiv and fw.release_str == rev.split()[1]
    # debug_mode 6 is GYRO_SCALED (the unfiltered gyro) in Betaflight 3.4-4.2 and so in these
    assert bf.debug_mode_name(fw.version, 6) == "GYRO_SCALED"


@pytest.mark.parametrize("rev", ["Cleanflight 2.2.0", "Cleanflight 2.3.1", "Cleanflight 1.14.2", "Cleanflight 2.1.0"])
def test_cleanflight_release_not_read_is_one_error(rev):
    with pytest.raises(GyroInputError) as e:
        bf.firmware_info({"Data version": 2, "Firmware revision": f"{rev} (abc) X"}, "f.BFL")
    assert rev in str(e.value) and "\n" not in str(e.value)


def test_cleanflight_header_on_the_shared_log(shared_data, tmp_path):
    """The shared Betaflight 3.1.5 frames under a Cleanflight 2.4.1 header (a header patch: no real
    Cleanflight log was found): debug_mode 6 maps to GYRO_SCALED of Betaflight 3.4.1, named so."""
    p = shared_data / "betaflight_blackbox" / "better_tune.BBL"
    if not p.exists():
        pytest.skip("shared blackbox log absent")
    data = p.read_bytes()[:200_000]
    q = tmp_path / "cf.BFL"
    q.write_bytes(
        data.replace(b"Betaflight 3.1.5", b"Cleanflight 2.4.1", 1)
        .replace(b"H debug_mode:8", b"H debug_mode:6", 1)
        .replace(b"H P interval:1/8", b"H P interval:8", 1)
    )
    rec, _ = _read(q)
    assert rec.meta["firmware_name"] == "cleanflight" and rec.meta["firmware_version"] == "2.4.1"
    assert rec.meta["betaflight_equivalent_version"] == "3.4.1"
    assert "Cleanflight 2.4.1 (= Betaflight 3.4.1 source)" in json.loads(rec.meta["gyro_prefilter"])["source"]


def test_filter_says_when_its_set_lines_drop_a_flown_dynamic_lowpass(public_dir, capsys):
    """Betaflight 4.2.0 flight with a dynamic gyro LPF (240-600 Hz), dynamic notch and RPM filter:
    the recommendation is scored against the static part of what was flown, and its `set` lines
    turn the dynamic LPF off. The text output printed none of the caveats; now a comment above the
    set lines and a note say so."""
    from gyrocore.cli import build_group, run_cli

    status = run_cli(build_group(["gyrocore.cli.commands"]), ["filter", str(_path(public_dir, BF42))])
    out = capsys.readouterr().out
    assert status == 0
    assert "# the set lines turn off the dynamic gyro low-pass you flew (240-600 Hz)" in out
    assert "note: as flown: dynamic filters" in out
