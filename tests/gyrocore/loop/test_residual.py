"""The residual builders: window operator, reference kinds, segments, motion gate."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from experiments.close_the_loop import effect_params, synthetic_recording
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording
from gyrocore.data.segments import Segment, read_segments, write_segments
from gyrocore.data.still import still_samples
from gyrocore.loop.residual import STILL_GATE, build_residual


def _still_rec(n=6000, rate=100.0, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    return Recording(t_s=t, gyro_rad_s=0.01 + rng.standard_normal((n, 3)) * 0.002)


def test_rate_kind_window_mean_of_a_constant_is_exact():
    rec = synthetic_recording(
        {"bias": effect_params("bias")}, seed=1, duration_s=10.0, bias_instability_rad_s=0.0, arw_rad_per_sqrt_s=0.0
    )
    res = build_residual(rec)
    assert res.kind == "rate"
    # noise-free: gyro − ref = b exactly; the block mean comes from differences of a running
    # sum over N = 2001 samples, so its rounding error is ≤ N·eps·|b| ≈ 2000·2.2e-16·0.009 ≈ 4e-15
    np.testing.assert_allclose(
        res.y_rad_s, np.broadcast_to(effect_params("bias")["b_rad_s"], res.y_rad_s.shape), rtol=0, atol=1e-14
    )
    names, X = res.regressors("bias")
    np.testing.assert_allclose(X[:, 0, 0], 1.0, atol=1e-12)


def test_attitude_kind_is_first_order_window_mean():
    """Noise-free bias b on a tumbling body: the window rotation residual is b to first order.

    E = exp(∫R_{b←k}·b dt) exactly for a constant error; the attitude kind takes the same
    operator on the regressors, so y − X·b is only the second-order (BCH) term,
    ≤ |b|²·T/2 = (0.0087)²·1/2 ≈ 4e-5 rad/s for T = 1 s windows.
    """
    b = effect_params("bias")["b_rad_s"]
    rec = synthetic_recording(
        {"bias": effect_params("bias")},
        seed=2,
        duration_s=20.0,
        bias_instability_rad_s=0.0,
        arw_rad_per_sqrt_s=0.0,
        with_quat=True,
    )
    rec = replace(rec, ref_rate_rad_s=None)
    res = build_residual(rec)
    assert res.kind == "attitude" and res.m >= 15
    _, X = res.regressors("bias")
    pred = np.einsum("mip,p->mi", X, b)
    assert np.max(np.abs(res.y_rad_s - pred)) < 0.5 * np.linalg.norm(b) ** 2 * 1.0 + 1e-9


def test_attitude_kind_drops_windows_with_nan_reference():
    rec = synthetic_recording({"bias": effect_params("bias")}, seed=3, duration_s=20.0, with_quat=True)
    q = rec.ref_quat_wxyz.copy()
    q[500:900] = np.nan  # tracking lost for 2 s at 200 Hz
    res = build_residual(replace(rec, ref_rate_rad_s=None, ref_quat_wxyz=q))
    assert any("NaN" in n for n in res.notes)
    for a, b in zip(res.win_start, res.win_stop):
        assert np.isfinite(q[a]).all() and np.isfinite(q[b]).all()


def test_still_kind_auto_and_segments(tmp_path):
    rec = _still_rec()
    res = build_residual(rec)
    assert res.kind == "still"
    np.testing.assert_allclose(res.y_rad_s.mean(axis=0), 0.01, atol=5 * 0.002 / np.sqrt(rec.n))  # 5σ of a mean
    seg = tmp_path / "seg.csv"
    write_segments([Segment.still(0.0, 20.0)], seg)
    segs = read_segments(seg)
    res2 = build_residual(rec, reference="still", segments=segs)
    assert rec.t_s[res2.win_stop].max() <= 20.0 + 1e-9


def test_angles_kind_needs_more_than_one_rotation():
    rng = np.random.default_rng(4)
    t = np.arange(1000) / 100.0
    gyro = np.zeros((1000, 3)) + rng.standard_normal((1000, 3)) * 0.001
    gyro[:, 0] += 2 * np.pi * 2 / 10.0  # two turns about x over the whole recording
    rec = Recording(t_s=t, gyro_rad_s=gyro)
    with pytest.raises(GyroInputError, match="too poor"):
        build_residual(rec, segments=[Segment.about_axis(0.0, 9.99, "x", 720.0)])


def test_motion_gate():
    rec = _still_rec()
    g = rec.gyro_rad_s.copy()
    g[2000:3000, 2] += 1.0  # 10 s of rotation about z
    m = still_samples(Recording(t_s=rec.t_s, gyro_rad_s=g), STILL_GATE)
    assert m[:1900].mean() > 0.95 and m[2100:2900].mean() == 0.0 and m[3100:].mean() > 0.95


@pytest.mark.parametrize("kind", ["rate", "attitude"])
def test_chunked_regressors_equal_whole(monkeypatch, kind):
    """Long recordings are regressed in chunks; the windows must come out the same (to
    rounding of the running sums, ≤ N·eps relative)."""
    import gyrocore.loop.residual as R

    rec = synthetic_recording({"bias": effect_params("bias")}, seed=6, duration_s=20.0, with_quat=True)
    if kind == "attitude":
        rec = replace(rec, ref_rate_rad_s=None)
    whole = build_residual(rec)
    effs = ("g2_sensitivity", "misalignment", "bias_ramp")
    Xws = {eff: whole.regressors(eff)[1] for eff in effs}  # computed before the patch: one pass
    th = np.linspace(-1e-5, 1e-5, 18)
    c_whole = whole.sample_correction("g2_sensitivity", th)
    monkeypatch.setattr(R, "CHUNK_SAMPLES", 777)  # forces ~6 chunks over 4001 samples
    chunked = build_residual(rec)
    for eff in effs:
        Xw = Xws[eff]
        _, Xc = chunked.regressors(eff)
        scale = np.max(np.abs(Xw)) + 1e-300
        assert np.max(np.abs(Xw - Xc)) <= 1e-10 * scale, eff
    # the per-sample correction is computed chunk by chunk: identical (no running sums)
    np.testing.assert_array_equal(chunked.sample_correction("g2_sensitivity", th), c_whole)
