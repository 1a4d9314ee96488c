"""`calibrate --px4-params` writes a TC_G0_ID PX4 will match, or says it does not.

PX4 (TemperatureCompensation::set_sensor_id_gyro) applies the TC_G<i> set only to the gyro whose
device id equals TC_G<i>_ID. The export wrote TC_G0_ID 0 without a word: loaded into a vehicle it
is never applied. Now `--px4-device-id` sets it; without it the file and the CLI say so.
"""

from __future__ import annotations

from gyrocore.data.recording import write_csv
from tests.gyrocore.test_bad_input import gh
from tests.gyrocore.calib.test_thermal import CUBIC, thermal_run


def _ids(path):
    rows = [ln.split("\t") for ln in path.read_text().splitlines() if not ln.startswith("#")]
    return {r[2]: r[3] for r in rows}


def test_px4_device_id_written_or_warned(tmp_path, capsys):
    rec, _ = thermal_run(4, CUBIC)
    f = tmp_path / "thermal.csv"
    write_csv(rec, f)
    tc = tmp_path / "tc.params"
    s, _, err = gh(
        capsys, "calibrate", f, "--effects", "bias,bias_thermal", "-o", tmp_path / "p.json", "--px4-params", tc
    )
    assert s == 0, err
    assert _ids(tc)["TC_G0_ID"] == "0"
    assert "TC_G0_ID is 0 and matches no gyro" in tc.read_text()
    assert any(ln.startswith("warning:") and "PX4 will not apply" in ln for ln in err), err
    s, _, err = gh(
        capsys,
        "calibrate",
        f,
        "--effects",
        "bias,bias_thermal",
        "-o",
        tmp_path / "p.json",
        "--px4-params",
        tc,
        "--px4-device-id",
        "2162688",
        "--force",
    )
    assert s == 0, err
    assert _ids(tc)["TC_G0_ID"] == "2162688" and "matches no gyro" not in tc.read_text()
    assert not any("PX4 will not apply" in ln for ln in err), err
