"""Integral method with uncertain known angles (hand turns): the propagated standard errors of K
must match the spread of K over hand-turn errors (z-scores of unit variance), where the noise-only
standard errors are far too small (the report of imucal's session printed scale ± 0.019 % for a
turn good to ±1 %)."""

from __future__ import annotations

import numpy as np

from gyrocore.data.segments import Segment
from gyrocore.data.recording import Recording
from gyrocore.calib.rotations import integral_calibration

RATE = 100.0
SIG_ANGLE = np.radians(3.0)
SIG_AXIS = np.radians(4.0)


def _session(rng, K_true):
    """Still 2 s, then a 2-s turn about x, y, z (each nominally +360°) with still 2 s between;
    the true turn has an angle error σθ and an axis tilt σφ per orthogonal component."""
    segs, pieces = [], []
    t0 = 0.0
    n_still, n_turn = int(2 * RATE), int(2 * RATE)
    for j in range(3):
        pieces.append(np.zeros((n_still, 3)))
        t0 += n_still / RATE
        a = np.eye(3)[j]
        tilt = SIG_AXIS * rng.standard_normal(3)
        tilt -= a * (tilt @ a)
        axis = a + tilt
        axis /= np.linalg.norm(axis)
        theta = 2 * np.pi + SIG_ANGLE * rng.standard_normal()
        w = np.tile(axis * theta / (n_turn / RATE), (n_turn, 1))
        segs.append(Segment.about_axis(t0 - 0.5 / RATE, t0 + n_turn / RATE - 0.5 / RATE, "xyz"[j], 360.0))
        pieces.append(w)
        t0 += n_turn / RATE
    pieces.append(np.zeros((n_still, 3)))
    omega = np.concatenate(pieces)
    gyro = omega @ K_true.T + [0.01, -0.02, 0.005] + 1e-5 * rng.standard_normal(omega.shape)
    t = np.arange(omega.shape[0]) / RATE
    return Recording(t_s=t, gyro_rad_s=gyro), segs


def test_angle_and_axis_uncertainty_gives_honest_standard_errors():
    """200 seeds: var(z) of the 9 K entries within [0.75, 1.3] with the uncertainty propagated
    (each entry's var(z) from 200 draws has SE sqrt(2/199) = 0.10; their mean over 9 correlated
    entries is bounded by that: ±0.3 is 3 SE), and > 100 with the angles taken as exact."""
    rng = np.random.default_rng(20261125)
    K_true = np.eye(3) + np.array([[0.01, 0.002, -0.003], [0.001, -0.02, 0.004], [-0.002, 0.003, 0.015]])
    z_with, z_without = [], []
    for _ in range(200):
        rec, segs = _session(rng, K_true)
        r = integral_calibration(rec, segs, angle_sigma_rad=SIG_ANGLE, axis_sigma_rad=SIG_AXIS)
        r0 = integral_calibration(rec, segs)
        z_with.append(((r.K - K_true) / r.K_stderr).ravel())
        z_without.append(((r0.K - K_true) / r0.K_stderr).ravel())
    v_with = np.var(np.array(z_with), axis=0)
    v_without = np.var(np.array(z_without), axis=0)
    assert 0.75 < float(np.mean(v_with)) < 1.3, v_with
    assert float(np.min(v_without)) > 100.0, v_without
