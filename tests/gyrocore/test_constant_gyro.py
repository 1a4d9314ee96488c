"""A gyro that never changes (rounded coarser than its noise) is refused in one line.

INAV 9.0.1 logs gyroADC after its 30-Hz low-pass rounded to 1 deg/s: the NAZGUL 10 log
(blackbox_public, log 2) at rest reads exactly 0 on every axis. `noise` ended in a
ZeroDivisionError traceback (the gate's σ² = 0), `bias` in "motion detected throughout ...
threshold [nan nan nan]". The same file is built here: 16 s at 1 kHz, zeros on x, y, z.
"""

from __future__ import annotations

import numpy as np
import pytest

from gyrocore.data.recording import Recording, write_csv
from tests.gyrocore.test_bad_input import assert_error, gh


@pytest.mark.parametrize("cmd", ["noise", "bias"])
def test_constant_gyro_is_one_error_line(tmp_path, capsys, cmd):
    t = np.arange(16000) / 1000.0
    g = np.zeros((t.size, 3))
    g[:, 2] = np.round(np.random.default_rng(1).normal(0, 0.3, t.size)) * np.radians(1.0)  # z moves by 1-deg/s steps
    f = tmp_path / "flat.csv"
    write_csv(Recording(t_s=t, gyro_rad_s=g, meta={}), f)
    s, _, err = gh(capsys, cmd, f)
    assert_error(s, err, r"gyro axis x, y never changes over the record \(x = 0 rad/s, y = 0 rad/s\)")
