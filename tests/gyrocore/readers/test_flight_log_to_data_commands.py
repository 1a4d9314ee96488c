"""`bias`/`noise` (data-file commands) handed a flight log say to convert it.

A pilot runs `gyroharness bias FLIGHT.BBL` or `noise LOG.BIN`: before, "binary file, expected a
CSV data file" with no way forward; now the log kind and the convert command.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.gyrocore.test_bad_input import assert_error, gh

DATAFLASH = Path(__file__).resolve().parents[2] / "data" / "dataflash" / "ArduCopter-4.5.7_00000081_first650k.BIN"


@pytest.mark.parametrize("cmd", ["bias", "noise"])
def test_blackbox_log_names_convert(capsys, shared_data, cmd):
    s, _, err = gh(capsys, cmd, shared_data / "betaflight_blackbox" / "better_tune.BBL")
    assert_error(
        s, err, r"blackbox log, not a data file; convert it first: gyroharness convert .*better_tune\.BBL -o OUT\.csv"
    )


def test_dataflash_log_names_convert(capsys):
    s, _, err = gh(capsys, "bias", DATAFLASH)
    assert_error(s, err, r"ArduPilot DataFlash log, not a data file; convert it first")
