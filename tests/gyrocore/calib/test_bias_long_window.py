"""`bias --window-s 20` on BROAD trial 05 (35 s of rest, then slow rotations with breaks).

With 20-s windows only 1-2 of the 10 windows are still; the variance gate's noise (the 25 %
quantile of the window variances) then held motion and the run was refused: "motion detected
throughout ... the recording moves smoothly the whole time" — about a recording whose first
20 s are still. Now the gate falls back to the differences' noise (as `noise`'s still-span gate
does) with a warning, and the first window is taken: its plain numpy mean is the bias.
"""

from __future__ import annotations

import warnings

import numpy as np

from gyrocore.calib.bias import StaticBiasCalibrator
from gyrocore.readers.convert import load_any
from gyrocore.errors import RepairWarning


def test_first_still_window_found_with_long_windows(shared_data):
    rec = load_any(shared_data / "broad" / "05_undisturbed_slow_rotation_with_breaks_B.hdf5")
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always", RepairWarning)
        r = StaticBiasCalibrator(window_s=20.0).fit(rec)
    assert any("motion in most windows" in str(x.message) for x in w)
    assert r.window_start_index == 0 and r.n_rejected_windows == 0
    np.testing.assert_allclose(r.bias_rad_s, rec.gyro_rad_s[: r.window_samples].mean(axis=0), rtol=1e-12)
    # the rest-phase bias of the PROVENANCE (0.20, 0.12, -0.23) deg/s, to its stated 2 digits
    assert np.all(np.abs(np.degrees(r.bias_rad_s) - [0.20, 0.12, -0.23]) < 0.015)
