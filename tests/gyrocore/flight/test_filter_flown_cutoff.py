"""`filter` on an ArduPilot log: the PX4/ArduPilot low-pass line keeps the flown cutoff when it is best.

The ArduCopter 4.5.7 fixture flew INS_GYRO_FILTER 42 Hz (2nd-order Butterworth at 6406 Hz) and
`filter` recommended "as flown", yet printed "ardupilot: INS_GYRO_FILTER 40": the Butterworth
grid (…, 40, 45, …) had no 42 Hz, so its best under the same motor-noise budget was 40 Hz, at a
larger attitude cost than the flown chain (0.0538 vs 0.0512 deg). The flown cutoff is now a
candidate of that grid, at the flown stage's rate (the same chain as the "as flown" row).
"""

from __future__ import annotations

import warnings
from pathlib import Path

from gyrocore.flight.preview import recommend_filter
from gyrocore.readers.dataflash import read_dataflash

LOG = Path(__file__).resolve().parents[2] / "data" / "dataflash" / "ArduCopter-4.5.7_00000081_first650k.BIN"


def test_ardupilot_lowpass_line_keeps_the_flown_cutoff():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = read_dataflash(LOG, stream="batch")
        out = recommend_filter(rec, window_s=0.15)
    assert out["recommended"]["name"] == "as flown"
    assert out["firmware"]["ardupilot"]["INS_GYRO_FILTER"] == 42
    assert out["px4_ardupilot_lowpass"]["attitude_cost"] <= out["as_flown"]["attitude_cost"] * (1 + 1e-9)


def test_low_rate_log_keeps_the_butterworth_grid_below_a_quarter_of_its_rate(shared_data):
    """A PX4 ULog's sensor_combined is logged at ~200-250 Hz and carries no filter rate: the
    PX4/ArduPilot Butterworth grid ran at that rate up to 300 Hz and `filter` died on "cutoff
    140.0 Hz must be in (0, 125) Hz" for every PX4 log. Its grid now follows the candidates'
    rule (a cutoff below a quarter of the filter rate)."""
    from gyrocore.readers.ulog import read_ulog

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = read_ulog(shared_data / "pyulog_samples" / "sample_log_small.ulg")
        out = recommend_filter(rec)
    rate = out["filter_rate_hz"]
    assert rate < 250.0  # the logged rate (~204.6 Hz): nothing to run the filters faster
    assert out["px4_ardupilot_lowpass"]["cutoff_hz"] < rate / 4
    assert out["firmware"]["px4"]["IMU_GYRO_CUTOFF"] < rate / 4
