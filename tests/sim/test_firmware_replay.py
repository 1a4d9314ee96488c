"""``gyroharness firmware replay``: a data file through the firmware's filters, byte-identical twice."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments.cli import build_group
from gyrocore.cli import run_cli
from gyrocore.data.recording import Recording, read_recording, write_csv
from sim.firmware.replay import resample_to_loop_rate


def _cli(argv, capsys):
    code = run_cli(build_group(["experiments.commands"]), [str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture
def gyro_file(tmp_path):
    # 0.25 s at 1 kHz: a 40 Hz roll tone plus seeded noise
    rng = np.random.default_rng(5)
    t = np.arange(250) / 1000.0
    g = rng.normal(0.0, 0.2, (t.size, 3))
    g[:, 0] += 0.5 * np.sin(2 * np.pi * 40.0 * t)
    path = tmp_path / "in.csv"
    write_csv(Recording(t_s=t, gyro_rad_s=g), path)
    return path


def test_replay_writes_the_firmware_view_byte_identically(firmware_binary, gyro_file, tmp_path, capsys):
    outs = []
    for k in range(2):
        out = tmp_path / f"out{k}.csv"
        code, stdout, err = _cli(
            [
                "firmware",
                "replay",
                gyro_file,
                "--set",
                "gyro_lpf1_static_hz=100",
                "--set",
                "gyro_lpf1_dyn_min_hz=0",
                "-o",
                out,
                "--json",
            ],
            capsys,
        )
        assert code == 0, err
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]
    d = json.loads(stdout)
    assert d["firmware"] == "betaflight" and d["version"] == "4.6.0"
    assert d["resample"]["up"] == 8 and d["resample"]["down"] == 1 and "resample_poly" in d["resample"]["method"]
    rec = read_recording(tmp_path / "out0.csv")
    assert rec.meta["firmware"] == "betaflight 4.6.0"
    assert "set gyro_lpf1_static_hz = 100" in rec.meta["firmware_settings"]
    assert rec.n == 2000  # 0.25 s at 8 kHz
    for a in "xyz":
        assert f"fw_gyro_{a}_rad_s" in rec.extra and f"fw_dterm_{a}_rad_s" in rec.extra
    # the 40 Hz tone passes the 100 Hz filters (mostly); the broadband noise is cut
    fw = rec.extra["fw_gyro_x_rad_s"]
    assert 0.2 < np.std(fw) < np.std(rec.gyro_rad_s[:, 0])


def test_replay_refused_setting_is_one_line(firmware_binary, gyro_file, tmp_path, capsys):
    code, out, err = _cli(
        ["firmware", "replay", gyro_file, "--set", "gyro_lpf1_type=NOPE", "-o", tmp_path / "o.csv"], capsys
    )
    assert code == 2 and out == "" and not (tmp_path / "o.csv").exists()
    lines = [x for x in err.splitlines() if x.startswith("error:")]
    assert len(lines) == 1 and "gyro_lpf1_type = NOPE" in lines[0] and "Allowed values" in lines[0]


def test_replay_of_a_real_log_uses_its_header(firmware_binary, shared_data, tmp_path, capsys):
    log = shared_data / "blackbox_public" / "LOG00037.BFL"
    if not log.exists():
        pytest.skip(f"{log} not present")
    out = tmp_path / "o.csv"
    code, stdout, err = _cli(
        ["firmware", "replay", log, "--start-s", "5", "--duration-s", "1", "-o", out, "--json"], capsys
    )
    assert code == 0, err
    d = json.loads(stdout)
    assert "set gyro_lpf1_dyn_min_hz = 240" in d["settings"] and "set dyn_notch_count = 1" in d["settings"]
    assert d["skipped_settings"] == []
    assert "no rotor speeds" in err  # 4.2 debug GYRO_SCALED log: no eRPM for the RPM filter
    assert d["armed_with_throttle"]  # the log's throttle stick drives the dynamic LPFs
    assert d["resample"]["window_s"][0] == pytest.approx(5.0, abs=0.002) and 7900 < d["n_samples"] < 8100


def test_resample_to_loop_rate_is_rational_polyphase():
    t = np.arange(1000) / 1000.0
    x = np.sin(2 * np.pi * 10 * t)[:, None]
    t2, y, info = resample_to_loop_rate(t, x, 8000.0)
    assert (info["up"], info["down"]) == (8, 1) and y.shape == (8000, 1)
    # a 10 Hz sine is reproduced between the input samples (away from the record ends)
    assert np.max(np.abs(y[400:-400, 0] - np.sin(2 * np.pi * 10 * t2[400:-400]))) < 1e-3


def test_replay_armed_follows_the_throttle(firmware_binary):
    # dynamic gyro LPF 100-500 Hz: at full throttle its cutoff is 5x higher than at idle, so more
    # of a white-noise input passes (disarmed it would sit at 100 Hz whatever the stick)
    from sim.firmware.replay import replay_gyro

    w = np.random.default_rng(3).normal(0.0, 1.0, (4000, 3))
    off = (
        "set gyro_lpf2_static_hz = 0",
        "set dyn_notch_count = 0",
        "set rpm_filter_harmonics = 0",
        "set gyro_lpf1_dyn_min_hz = 100",
        "set gyro_lpf1_dyn_max_hz = 500",
    )
    rms = {}
    for thr in (1000.0, 2000.0):
        r = replay_gyro(firmware_binary, w, settings=off, throttle_us=np.full(w.shape[0], thr))
        assert r.boot.armed
        rms[thr] = float(np.std(r.fw_gyro_S_rad_s[800:, 0]))
    # white noise through a PT1 at fc << fs: output variance ∝ fc, so the rms ratio is
    # sqrt(500/100) = 2.2; 1.5 leaves room for the discrete filter and the 0.1-s start
    assert rms[2000.0] > 1.5 * rms[1000.0], rms


def test_replay_refuses_a_log_without_the_unfiltered_gyro(shared_data, tmp_path, capsys):
    # Betaflight 3.1.5, debug_mode NOTCH: the least-filtered gyro in the log is after the 90 Hz PT1
    log = shared_data / "betaflight_blackbox" / "better_tune.BBL"
    if not log.exists():
        pytest.skip(f"{log} not present")
    code, out, err = _cli(["firmware", "replay", log, "-o", tmp_path / "o.csv"], capsys)
    errors = [x for x in err.splitlines() if x.startswith("error:")]
    assert code == 2 and out == "" and len(errors) == 1
    assert "pt1 90 Hz" in errors[0] and "not the unfiltered gyro" in errors[0]
