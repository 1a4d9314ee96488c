"""`bias`/`noise` read any source `convert` reads, as `calibrate`, `loop`, `vibration` do.

A user runs `gyroharness noise imu_static_test.csv` (tomisuarez2's raw-LSB CSV), `bias LOG.BIN` or
`noise FLIGHT.BBL`: before, "missing required column t_s" or "convert it first"; now the source's
own reader, with the same numbers as on the converted data file.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.gyrocore.test_bad_input import assert_error, gh

DATAFLASH = Path(__file__).resolve().parents[2] / "data" / "dataflash" / "ArduCopter-4.5.7_00000081_first650k.BIN"


@pytest.mark.parametrize("cmd", ["bias", "noise"])
def test_raw_source_gives_the_numbers_of_its_converted_file(capsys, shared_data, tmp_path, cmd):
    raw = shared_data / "tomisuarez2_mpu6050" / "imu_static_test.csv"  # "Fs,100" header, raw LSB, no time
    conv = tmp_path / "static.csv"
    s, _, err = gh(capsys, "convert", raw, "-o", conv)
    assert s == 0, err
    extra = ["--method", "adev"] if cmd == "noise" else []
    s1, out1, err1 = gh(capsys, cmd, raw, "--json", *extra)
    s2, out2, err2 = gh(capsys, cmd, conv, "--json", *extra)
    assert s1 == 0 and s2 == 0, (err1, err2)
    a, b = json.loads(out1), json.loads(out2)
    if cmd == "bias":
        assert a["bias_rad_s"] == b["bias_rad_s"] and a["window_start_s"] == b["window_start_s"]
    else:
        for ax in "xyz":  # same samples, same analysis; the converted file rounds to %.17g: exact
            assert a["axes"][ax]["arw_rad_per_sqrt_s"] == b["axes"][ax]["arw_rad_per_sqrt_s"]


def test_sunsided_folder_is_read(capsys, shared_data):
    s, out, err = gh(
        capsys, "bias", shared_data / "sunsided_mpu6050" / "set-1" / "unmoved-x-pointing-forward", "--json"
    )
    assert s == 0, err
    assert any("bursty host timestamps" in ln and "uniform grid" in ln for ln in err), err  # the reader's repair
    assert len(json.loads(out)["bias_rad_s"]) == 3


def test_flight_log_is_read_and_refused_for_its_motion(capsys, shared_data):
    """A blackbox flight is read by its reader; `noise` then refuses the flight (motion), one line."""
    s, _, err = gh(capsys, "noise", shared_data / "blackbox_public" / "LOG00037.BFL")
    assert_error(s, err, r"recording is not static")


def test_dataflash_log_is_read(capsys):
    s, _, err = gh(capsys, "bias", DATAFLASH)
    assert_error(s, err, r"motion detected throughout")  # read (not "binary file"), then judged by the gate


def test_unknown_folder_and_missing_file_one_line(capsys, tmp_path):
    s, _, err = gh(capsys, "noise", tmp_path)
    assert_error(s, err, r"folder is not a known recording")
    s, _, err = gh(capsys, "bias", tmp_path / "nope.csv")
    assert_error(s, err, r"no such file")


def test_apply_names_the_source_and_the_convert_command(capsys, shared_data, tmp_path):
    """`apply` rewrites a data file row for row: a raw source is one line saying to convert it
    (before: "missing required column t_s" on tomisuarez2's `Fs,100` header)."""
    raw = shared_data / "tomisuarez2_mpu6050" / "imu_90_x_rot.csv"
    conv = tmp_path / "rot.csv"
    assert gh(capsys, "convert", raw, "-o", conv)[0] == 0
    params = tmp_path / "p.json"
    s, _, err = gh(capsys, "calibrate", conv, "--effects", "bias", "-o", params)
    assert s == 0, err
    s, _, err = gh(capsys, "apply", raw, "--params", params, "-o", tmp_path / "c.csv")
    assert_error(
        s, err, r"a tomisuarez2 recording, not a data file; convert it first: gyroharness convert .*imu_90_x_rot"
    )
    assert not (tmp_path / "c.csv").exists()
