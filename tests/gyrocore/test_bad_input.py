"""Issue 7: every bad input gets a clear answer through the real command line.

One test per bad-input class. Each drives ``gyroharness`` (in-process through
``run_cli`` of the console-script group, plus a few real subprocesses) and asserts: an error
gives a non-zero exit status, exactly one ``error:`` line on stderr and no traceback; a
repair exits 0 with a ``warning:`` line saying what was done.
"""

from __future__ import annotations

import json
import subprocess
import sys
import warnings

import numpy as np
import pytest

from gyrocore.cli import build_group, run_cli
from gyrocore.data.recording import Recording, read_csv, write_csv

HEADER = "t_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s"


def gh(capsys, *argv):
    """Run ``gyroharness argv`` in-process; returns (status, stdout, stderr lines)."""
    with warnings.catch_warnings():  # run_cli installs its own warning printer; restore after
        status = run_cli(build_group(["experiments.commands"]), [str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, [ln for ln in err.splitlines() if ln.strip()]


def assert_error(status, err, pattern):
    import re

    errors = [ln for ln in err if ln.startswith("error:")]
    assert status != 0, err
    assert len(errors) == 1, err
    assert not any("Traceback" in ln for ln in err), err
    assert re.search(pattern, errors[0]), errors[0]


def assert_repaired(status, err, pattern):
    import re

    assert status == 0, err
    assert not any(ln.startswith("error:") or "Traceback" in ln for ln in err), err
    warn = [ln for ln in err if ln.startswith("warning:")]
    assert any(re.search(pattern, w) for w in warn), err


def _csv(tmp_path, text, name="in.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _rows(t, g, extra_cols=()):
    return "\n".join(
        ",".join(repr(float(v)) for v in (ti, *gi, *(c[i] for c in extra_cols))) for i, (ti, gi) in enumerate(zip(t, g))
    )


def _still(n=3000, rate_hz=200.0, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    return t, rng.normal(0, 0.002, (n, 3)) + [0.01, -0.02, 0.005]


# ------------------------------------------------------------------ file-level classes
def test_empty_file(tmp_path, capsys):
    s, _, err = gh(capsys, "convert", _csv(tmp_path, ""), "-o", tmp_path / "o.csv")
    assert_error(s, err, "empty file")
    assert not (tmp_path / "o.csv").exists()


def test_header_only(tmp_path, capsys):
    s, _, err = gh(capsys, "convert", _csv(tmp_path, HEADER + "\n"), "-o", tmp_path / "o.csv")
    assert_error(s, err, "header only, no samples")


def test_missing_required_column(tmp_path, capsys):
    s, _, err = gh(
        capsys, "convert", _csv(tmp_path, "t_s,gyro_x_rad_s,gyro_y_rad_s\n0,0,0\n"), "-o", tmp_path / "o.csv"
    )
    assert_error(s, err, "incomplete column group, missing gyro_z_rad_s")
    s, _, err = gh(capsys, "convert", _csv(tmp_path, "time,a\n0,0\n"), "-o", tmp_path / "o.csv")
    assert_error(s, err, "missing required column t_s")


def test_nan_inf_samples_repaired(tmp_path, capsys):
    t, g = _still(200)
    g[10, 1] = np.nan
    g[20, 2] = np.inf
    s, _, err = gh(capsys, "convert", _csv(tmp_path, HEADER + "\n" + _rows(t, g)), "-o", tmp_path / "o.csv")
    assert_repaired(s, err, "dropped 2 rows with NaN/inf")
    assert read_csv(tmp_path / "o.csv").n == 198


def test_gaps_reported(tmp_path, capsys):
    t, g = _still(500)
    keep = np.ones(500, bool)
    keep[100:130] = False  # 30 samples dropped by the logger
    s, _, err = gh(capsys, "convert", _csv(tmp_path, HEADER + "\n" + _rows(t[keep], g[keep])), "-o", tmp_path / "o.csv")
    assert_repaired(s, err, r"1 gaps longer than 1.5x the median interval 5 ms \(longest 0.155 s, ~30 samples missing")


def test_timestamps_backwards_or_repeated(tmp_path, capsys):
    t, g = _still(100)
    t = t.copy()
    t[50] = t[49]  # repeated
    t[70] = t[60]  # backwards
    s, _, err = gh(capsys, "convert", _csv(tmp_path, HEADER + "\n" + _rows(t, g)), "-o", tmp_path / "o.csv")
    assert_repaired(s, err, "dropped 2 rows whose timestamp goes backwards or repeats")
    assert np.all(np.diff(read_csv(tmp_path / "o.csv").t_s) > 0)


def test_bursty_host_timestamps(tmp_path, capsys, shared_data):
    # the real MPU-6050 set (PROVENANCE: median dt 1-2 ms, gaps 0.25-0.5 s): retimed by convert
    src = shared_data / "sunsided_mpu6050" / "set-2" / "unmoved-with-x-pointing-forward"
    s, _, err = gh(capsys, "convert", src, "-o", tmp_path / "r.csv")
    assert_repaired(s, err, r"bursty host timestamps \(median dt .* replaced by a uniform grid")
    # kept with --no-retime, then reading that file warns and suggests --retime
    s, _, err = gh(capsys, "convert", src, "-o", tmp_path / "h.csv", "--no-retime")
    assert_repaired(s, err, "bursty host timestamps .* kept as recorded; pass --retime")
    s, _, err = gh(capsys, "convert", tmp_path / "h.csv", "-o", tmp_path / "h2.csv", "--retime")
    assert_repaired(s, err, "bursty host timestamps .* replaced by a uniform grid")
    rec = read_csv(tmp_path / "h2.csv", checks=False)
    assert np.allclose(np.diff(rec.t_s), rec.duration_s / (rec.n - 1))


def test_text_in_a_number(tmp_path, capsys):
    t, g = _still(20)
    lines = (HEADER + "\n" + _rows(t, g)).splitlines()
    lines[7] = lines[7].replace(lines[7].split(",")[2], "0.0l2")  # a typo in gyro_y on file line 8
    s, _, err = gh(capsys, "convert", _csv(tmp_path, "\n".join(lines)), "-o", tmp_path / "o.csv")
    assert_error(s, err, r"line 8, column 'gyro_y_rad_s': text in a number \('0.0l2'\)")


def test_binary_file(tmp_path, capsys):
    p = tmp_path / "in.csv"
    p.write_bytes(bytes(range(256)) * 20)
    s, _, err = gh(capsys, "convert", p, "-o", tmp_path / "o.csv")
    assert_error(s, err, "binary file")


def test_file_does_not_exist(tmp_path, capsys):
    s, _, err = gh(capsys, "convert", tmp_path / "missing.csv", "-o", tmp_path / "o.csv")
    assert_error(s, err, "missing.csv: no such file")


def test_deg_s_labelled_rad_s(tmp_path, capsys):
    # motion peaks of 400 (deg/s) in a rad/s column: no MEMS gyro reaches 400 rad/s
    t = np.arange(1000) * 0.005
    g = np.column_stack([400 * np.sin(t), np.zeros_like(t), np.zeros_like(t)])
    s, _, err = gh(capsys, "convert", _csv(tmp_path, HEADER + "\n" + _rows(t, g)), "-o", tmp_path / "o.csv")
    assert_error(s, err, r"gyro peaks at 400.0 rad/s .* probably deg/s; rename it gyro_x_deg_s")
    # a still recording in deg/s (MPU-6050: 0.1 deg/s noise) labelled rad/s: warned with the evidence
    rng = np.random.default_rng(3)
    n = 2000
    t = np.arange(n) * 0.01
    g = rng.normal(0, 0.1, (n, 3)) + [4.5, 0.1, 1.0]
    a = rng.normal(0, 0.02, (n, 3)) + [0, 0, 9.81]
    text = HEADER + ",accel_x_m_s2,accel_y_m_s2,accel_z_m_s2\n" + _rows(t, g, a.T)
    s, _, err = gh(capsys, "convert", _csv(tmp_path, text, "s.csv"), "-o", tmp_path / "o2.csv")
    assert_repaired(s, err, r"still recording .* per-sample noise .* is it deg/s labelled rad/s")


def test_saturated_samples(tmp_path, capsys):
    t = np.arange(2000) * 0.002
    rng = np.random.default_rng(4)
    w = np.clip(8.0 * np.sin(2 * np.pi * t) + rng.normal(0, 0.005, t.size), -4.3633, 4.3633)  # ±250 deg/s range
    g = np.column_stack([np.zeros_like(t), w, np.zeros_like(t)])
    s, _, err = gh(capsys, "convert", _csv(tmp_path, HEADER + "\n" + _rows(t, g)), "-o", tmp_path / "o.csv")
    assert_repaired(s, err, r"saturated samples \(clipped plateaus: gyro_y .* at 4.3633.*flagged in column 'saturated'")
    rec = read_csv(tmp_path / "o.csv", checks=False)
    assert np.array_equal(rec.extra["saturated"] > 0, np.abs(w) >= 4.3633)


def test_large_file_refused_or_streamed(tmp_path, capsys, monkeypatch):
    import gyrocore.data.recording as rc

    t, g = _still(5000)
    write_csv(Recording(t_s=t, gyro_rad_s=g), tmp_path / "big.csv")
    monkeypatch.setattr(rc, "_available_memory_bytes", lambda: 50_000)
    # convert streams it in chunks ...
    s, _, err = gh(capsys, "convert", tmp_path / "big.csv", "-o", tmp_path / "o.csv", "--chunk-rows", "1000")
    assert s == 0 and not err
    # ... and a whole-file read (what the estimators do) is refused with a clear message
    with pytest.raises(Exception, match="read it in chunks"):
        read_csv(tmp_path / "big.csv")


def test_existing_output_not_overwritten(tmp_path, capsys):
    t, g = _still(100)
    src = _csv(tmp_path, HEADER + "\n" + _rows(t, g))
    out = tmp_path / "o.csv"
    out.write_text("precious")
    s, _, err = gh(capsys, "convert", src, "-o", out)
    assert_error(s, err, "exists; pass --force to overwrite it")
    assert out.read_text() == "precious"
    s, _, err = gh(capsys, "convert", src, "-o", src, "--force")
    assert_error(s, err, "output would overwrite the input")


# ------------------------------------------------------------------ bad CLI flags
@pytest.mark.parametrize(
    "argv, pattern",
    [
        (["convert", "X", "-o", "Y", "--format", "nope"], r"Invalid value for '--format'"),
        (["convert", "X", "-o", "Y", "--lsb-per-dps", "abc"], r"Invalid value for '--lsb-per-dps'"),
        (["convert", "X", "-o", "Y", "--bogus"], r"No such option '--bogus'"),
        (["convert", "X"], r"Missing option '-o'"),
        (["no-such-command"], r"No such command 'no-such-command'"),
    ],
)
def test_bad_cli_flags(capsys, argv, pattern):
    s, _, err = gh(capsys, *argv)
    assert_error(s, err, pattern)


def test_flag_that_does_not_apply(tmp_path, capsys, shared_data):
    s, _, err = gh(
        capsys,
        "convert",
        shared_data / "broad" / "02_undisturbed_slow_rotation_B.hdf5",
        "-o",
        tmp_path / "o.csv",
        "--lsb-per-dps",
        "131",
    )
    assert_error(s, err, "option --lsb-per-dps does not apply to format broad")
    s, _, err = gh(
        capsys,
        "convert",
        shared_data / "tomisuarez2_mpu6050" / "imu_static_test.csv",
        "-o",
        tmp_path / "o.csv",
        "--lsb-per-dps",
        "-5",
    )
    assert_error(s, err, "--lsb-per-dps must be a positive number")


# ------------------------------------------------------------------ the real console script
def test_console_script_one_line_error_and_json_only_stdout(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "experiments.cli",
            "convert",
            str(tmp_path / "nope.csv"),
            "-o",
            str(tmp_path / "o.csv"),
            "--json",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [f"error: {tmp_path / 'nope.csv'}: no such file or folder"]
    t, g = _still(300)
    g[5, 0] = np.nan
    src = _csv(tmp_path, HEADER + "\n" + _rows(t, g))
    r = subprocess.run(
        [sys.executable, "-m", "experiments.cli", "convert", str(src), "-o", str(tmp_path / "o.csv"), "--json"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)  # nothing but JSON on stdout
    assert summary["n_samples"] == 299 and any("dropped 1 rows" in w for w in summary["warnings"])
    assert [ln for ln in r.stderr.splitlines() if ln.startswith("warning:")]


# ------------------------------------------------------------------ classes owned by other commands
def _write_rec(path, n, rate_hz=200.0, *, seed=0, motion=None, accel=False):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    g = rng.normal(0, 0.002, (n, 3))  # 0.002 rad/s per sample: a typical MEMS at 200 Hz
    if motion is not None:
        g[:, 2] += motion(t)
    a = (rng.normal(0, 0.01, (n, 3)) + [0, 0, 9.81]) if accel else None
    write_csv(Recording(t_s=t, gyro_rad_s=g, accel_m_s2=a), path)
    return path


def test_recording_too_short_for_allan(tmp_path, capsys):
    s, _, err = gh(capsys, "allan", _write_rec(tmp_path / "tiny.csv", 3))
    assert_error(s, err, "too short for Allan analysis")
    # averaging times beyond what the record supports are dropped, and the warning says which
    s, _, err = gh(capsys, "allan", _write_rec(tmp_path / "short.csv", 1000), "--max-tau-s", "1000")
    assert_repaired(s, err, r"recording is [0-9.]+ s long: dropped tau = .* needs tau <= T/2")


def test_motion_during_bias_calibration(tmp_path, capsys):
    def moving(t):
        return 0.5 * np.sin(2 * np.pi * 0.5 * t)  # a hand swinging the board, ±29 deg/s

    p = _write_rec(tmp_path / "moving.csv", 4000, motion=moving)
    # noise known from the datasheet (0.12 deg/s per sample): every window is refused
    s, _, err = gh(capsys, "bias", p, "--noise-dps", "0.12")
    assert_error(s, err, "motion detected throughout")


def test_unknown_effect_name(tmp_path, capsys):
    p = _write_rec(tmp_path / "still.csv", 4000, accel=True)
    s, _, err = gh(capsys, "loop", p, "--effects", "bias,bais_thermal")
    assert_error(s, err, r"unknown effect 'bais_thermal'")


def _table_z_only(path, seed=0):
    """Rate-table run turning about z only: x/y scale cannot be observed."""
    rng = np.random.default_rng(seed)
    n = 6000
    t = np.arange(n) / 200.0
    ref = np.zeros((n, 3))
    ref[:, 2] = np.repeat([0.0, 1.0, -1.0, 2.0, -2.0, 0.0], n // 6)
    g = ref * [1.0, 1.0, 1.01] + [0.01, -0.02, 0.005] + rng.normal(0, 0.002, (n, 3))
    write_csv(Recording(t_s=t, gyro_rad_s=g, ref_rate_rad_s=ref), path)
    return path


def test_rotation_set_cannot_observe_parameters(tmp_path, capsys):
    p = _table_z_only(tmp_path / "zonly.csv")
    s, out, err = gh(capsys, "calibrate", p, "--effects", "bias,scale", "-o", tmp_path / "p.json", "--json")
    assert s == 0 and not any(ln.startswith("error:") or "Traceback" in ln for ln in err), err
    res = json.loads(out)
    # the two unexcited scale factors are named, not fitted to noise
    assert res["unobservable"] == ["scale.s[0]", "scale.s[1]"]
    assert res["standard_errors"]["scale"]["s"][:2] == [None, None]
    s, out, err = gh(capsys, "calibrate", p, "--effects", "bias,scale", "-o", tmp_path / "p2.json")
    assert s == 0 and "scale.s[0]" in out and "scale.s[1]" in out and "UNOBSERVABLE" in out


def _thermal_params(tmp_path, capsys):
    rng = np.random.default_rng(5)
    n = 6000
    t = np.arange(n) / 200.0
    temp = np.linspace(20.0, 30.0, n)
    g = 0.01 + 0.001 * (temp - 25.0)[:, None] * [1, 2, 3] + rng.normal(0, 0.002, (n, 3))
    write_csv(Recording(t_s=t, gyro_rad_s=g, temp_c=temp, ref_rate_rad_s=np.zeros((n, 3))), tmp_path / "cal.csv")
    s, _, err = gh(capsys, "calibrate", tmp_path / "cal.csv", "--effects", "bias_thermal", "-o", tmp_path / "pt.json")
    assert s == 0, err
    return tmp_path / "pt.json"


def test_temperature_outside_calibrated_range(tmp_path, capsys):
    params = _thermal_params(tmp_path, capsys)
    rng = np.random.default_rng(6)
    n = 2000
    temp = np.linspace(35.0, 45.0, n)
    g = 0.01 + 0.001 * (temp - 25.0)[:, None] * [1, 2, 3] + rng.normal(0, 0.002, (n, 3))
    write_csv(Recording(t_s=np.arange(n) / 200.0, gyro_rad_s=g, temp_c=temp), tmp_path / "hot.csv")
    s, _, err = gh(capsys, "apply", tmp_path / "hot.csv", "--params", params, "-o", tmp_path / "c.csv")
    assert_repaired(s, err, r"outside the calibrated range 20.00..30.00 C; bias_thermal is held at the range edge")


def test_parameter_file_corrupt_or_other_version(tmp_path, capsys):
    params = _thermal_params(tmp_path, capsys)
    data = _write_rec(tmp_path / "d.csv", 1000)
    doc = json.loads(params.read_text())
    doc["format_version"] = "2.0"
    (tmp_path / "v2.json").write_text(json.dumps(doc))
    s, _, err = gh(capsys, "apply", data, "--params", tmp_path / "v2.json", "-o", tmp_path / "c1.csv")
    assert_error(s, err, r"format_version 2.0 is not supported")
    (tmp_path / "bad.json").write_text(params.read_text()[:150])  # truncated: an interrupted copy
    s, _, err = gh(capsys, "apply", data, "--params", tmp_path / "bad.json", "-o", tmp_path / "c2.csv")
    assert_error(s, err, r"not a parameter file \(JSON error")
    (tmp_path / "bin.json").write_bytes(b"\x00\x01\x02garbage")
    s, _, err = gh(capsys, "apply", data, "--params", tmp_path / "bin.json", "-o", tmp_path / "c3.csv")
    assert_error(s, err, "not a parameter file")
    assert not any((tmp_path / f"c{i}.csv").exists() for i in (1, 2, 3))  # nothing half-written


def test_unknown_effect_name_in_calibrate(tmp_path, capsys):
    p = _table_z_only(tmp_path / "zonly.csv")
    s, _, err = gh(capsys, "calibrate", p, "--effects", "bias,scael", "-o", tmp_path / "p.json")
    assert_error(s, err, r"unknown effect 'scael'; known effects: bias, ")
    assert not (tmp_path / "p.json").exists()
