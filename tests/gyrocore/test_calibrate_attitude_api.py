"""Calibrating against a reference attitude (BROAD's OptiTrack) is the same through every door.

`gyroharness calibrate` fitted BROAD trials against the optical attitude, but the Python API
(`Calibrator.fit`) and `gyroharness batch calibrate` fitted only the still parts against rate 0:
on trial 05, scale and misalignment came back 0 with standard error inf ("unobservable") and
the bias from the 47 % of still samples, silently different from the single-file command.

Expected scale from outside the code: a scipy least-squares fit of b, diag(s) and the six
misalignment angles to the relative rotations of 1-s windows (strapdown integration of
``imu_gyr`` with scipy's Rotation, backward hold, compared with ``opt_quat``), run once on
trial 05 (/tmp check script of helper newuser2): s = (-0.00163, -0.00161, -0.00139),
b = (0.00381, 0.00228, -0.00409) rad/s. Tolerance: 3 of the tool's own (HAC) standard errors
(the two fits differ only in linearisation and weighting, far below one SE).
"""

from __future__ import annotations

import numpy as np
import pytest

from gyrocore.fleet import headline_calibrate
from gyrocore.readers.convert import load_any
from gyrocore.calibrator import Calibrator
from gyrocore.data.recording import write_csv

TRIAL = "05_undisturbed_slow_rotation_with_breaks_B.hdf5"
S_INDEP = np.array([-0.00163, -0.00161, -0.00139])
B_INDEP = np.array([0.00381, 0.00228, -0.00409])


@pytest.fixture(scope="module")
def broad05(shared_data):
    return load_any(shared_data / "broad" / TRIAL)


def test_calibrator_fit_uses_the_reference_attitude(broad05):
    assert broad05.ref_rate_rad_s is None and broad05.ref_quat_wxyz is not None
    res = Calibrator(effects=["bias", "scale", "misalignment"]).fit(broad05)
    assert res.method == "attitude_reference"
    assert not res.unobservable
    s, s_se = res.params["scale"]["s"], res.stderr["scale"]["s"]
    assert np.all(np.isfinite(s_se)) and np.all(s_se < 1e-3)
    assert np.all(np.abs(s - S_INDEP) < 3 * s_se), (s, s_se)
    b, b_se = res.params["bias"]["b_rad_s"], res.stderr["bias"]["b_rad_s"]
    assert np.all(np.abs(b - B_INDEP) < 3 * b_se), (b, b_se)


def test_batch_calibrate_equals_the_single_file_command(broad05, tmp_path):
    path = tmp_path / "b05.csv"
    write_csv(broad05, path)
    row = headline_calibrate(str(path), {"effects": "bias,scale,misalignment"})
    single = Calibrator(effects=["bias", "scale", "misalignment"]).fit(broad05)
    assert row["unobservable"] == ""
    for i, a in enumerate("xyz"):
        assert row[f"scale.s_{a}"] == pytest.approx(single.params["scale"]["s"][i], rel=1e-6, abs=1e-9)
        assert row[f"scale.s_{a}_se"] == pytest.approx(single.stderr["scale"]["s"][i], rel=1e-6)


def test_batch_calibrate_reads_what_calibrate_reads(shared_data):
    """`calibrate TRIAL.hdf5` reads the BROAD file directly; `batch calibrate '*.hdf5'` failed
    every file with "binary file ... convert it first"."""
    row = headline_calibrate(str(shared_data / "broad" / TRIAL), {"effects": "bias,scale"})
    single = Calibrator(effects=["bias", "scale"]).fit(load_any(shared_data / "broad" / TRIAL))
    assert row["scale.s_x"] == pytest.approx(single.params["scale"]["s"][0], rel=1e-6)


def test_rate_effects_without_a_motion_reference_say_what_would_excite_them():
    """IMU-TK's multi-pose session (turns between poses, no rate or attitude reference) gave
    "scale.s[0]: regressor is zero in the data (no excitation)" and nothing on why: the fit is
    against rate 0 on the still parts; the note now names the references that would do."""
    from gyrocore.data.recording import Recording

    rng = np.random.default_rng(3)
    t = np.arange(2000) / 100.0
    rec = Recording(t_s=t, gyro_rad_s=0.01 + rng.normal(0, 1e-3, (t.size, 3)), meta={})
    res = Calibrator(effects=["bias", "scale"]).fit(rec)
    assert res.method == "still" and len(res.unobservable) == 3
    assert any(
        "scale need a reference for the motion" in n and "--segments" in n and "--poses" in n for n in res.notes
    ), res.notes
    only_bias = Calibrator(effects=["bias"]).fit(rec)
    assert not any("reference for the motion" in n for n in only_bias.notes)
