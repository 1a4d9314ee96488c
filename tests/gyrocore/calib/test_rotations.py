"""Rotation calibration: the article's worked numbers, the integral method on known truth,
and imucal's Ferraris session beside imucal's own result."""

import warnings

import numpy as np
import pytest

from gyrocore.effects import registry as E
from gyrocore.data.segments import Segment, write_segments
from gyrocore.errors import GyroInputError, RepairWarning
from gyrocore.calibrator import Calibrator
from gyrocore.data.recording import Recording
from gyrocore.calib.rotations import STILL_GATE, article_worked_example, integral_calibration
from gyrocore.data.still import still_samples


# ------------------------------------------------------------------ the article's §5
def test_article_worked_numbers_and_where_they_fail():
    ex = article_worked_example()
    # B's diagonal is about 10 turns (2π·10 = 62.83 rad), not the 5 turns of C = 10π·I
    np.testing.assert_allclose(ex["turns_on_diagonal"], [10.249, 10.302, 10.216], atol=1e-3)
    # with the article's C = 10π·I, M ≈ 0.488·I: not a calibration matrix near I
    np.testing.assert_allclose(np.diag(ex["M_C_10pi"]), [0.4878, 0.4854, 0.4894], atol=1e-4)
    # with C = 20π·I (10 turns) the diagonal matches: M00 = 0.9757 vs the printed 0.9754
    M20 = ex["M_C_20pi"]
    assert abs(M20[0, 0] - 0.9754) < 5e-4
    assert abs(M20[2, 2] - 0.9851) < 0.007  # 0.9789 vs 0.9851
    # ... but the off-diagonal terms do not follow from B: printed M[2,1] = 0.107, B gives −0.0125
    assert M20[2, 1] == pytest.approx(-0.0125, abs=1e-4)
    assert abs(ex["M_printed_minus_C_20pi"][2, 1]) > 0.1
    # the signs of the printed off-diagonals disagree too (e.g. M[0,1]: −0.0135 printed, +0.0005 from B)
    assert np.sign(ex["M_printed"][0, 1]) != np.sign(M20[0, 1])
    # "5 turns" is 1800°, and 3600/3500 is 1.029, not "≈ 1.02"
    assert ex["five_turns_deg"] == 1800.0
    assert ex["scale_3600_over_3500"] == pytest.approx(1.0286, abs=1e-4)


# ------------------------------------------------------------------ integral method, known truth
TRUE = {
    "bias": {"b_rad_s": np.array([0.01, -0.006, 0.003])},
    "scale": {"s": np.array([0.02, -0.015, 0.005])},
    "misalignment": {"m_rad": np.array([4e-3, -6e-3, 2e-3, 3e-3, 9e-3, -7e-3])},
}
SIGMA_RAD_S = 0.001


def hand_session(seed, *, rate_hz=100.0, turns=(-1.0, -1.0, -1.0), still_s=20.0, rest_s=8.0, axes_S=None):
    """Still, then one rotation about each axis (smooth, 4 s, `turns` turns), rests between.

    Returns the recording and the segments (each covers its rotation plus 1 s either side)."""
    rng = np.random.default_rng(seed)
    pieces, segs = [np.zeros((int(still_s * rate_hz), 3))], []
    t_cur = still_s
    rot_s = 4.0
    for i, k in enumerate(turns):
        n_rot = int(rot_s * rate_hz)
        u = np.arange(n_rot) / n_rot
        w = np.zeros((n_rot, 3))
        profile = k * 2 * np.pi / rot_s * (1 - np.cos(2 * np.pi * u))  # integrates to k turns
        pieces += [w, np.zeros((int(rest_s * rate_hz), 3))]
        if axes_S is None:
            w[:, i] = profile
            segs.append(Segment.about_axis(t_cur - 1.0, t_cur + rot_s + 1.0, "xyz"[i], 360.0 * k))
        else:  # about the unit vector axes_S[:, i] (a fixed axis in S: the rotation vector is angle·axis)
            w[:] = profile[:, None] * axes_S[:, i]
            segs.append(Segment(t_cur - 1.0, t_cur + rot_s + 1.0, "rotation", tuple(360.0 * k * axes_S[:, i])))
        t_cur += rot_s + rest_s
    w = np.vstack(pieces)
    n = len(w)
    t = np.arange(n) / rate_hz
    y = E.deterministic(TRUE, E.ModelInputs(t_s=t, omega_S_rad_s=w)) + rng.normal(0, SIGMA_RAD_S, (n, 3))
    return Recording(t_s=t, gyro_rad_s=y, meta={"rate_hz": str(rate_hz)}), segs, w


def test_integral_method_recovers_K_within_4_sigma(tmp_path):
    rec, segs, w = hand_session(0)
    write_segments(segs, tmp_path / "seg.csv")
    res = Calibrator(effects=["bias", "scale", "misalignment"], segments=tmp_path / "seg.csv").fit(rec)
    assert res.method == "integral"
    K_true = E.k_matrix(TRUE)
    K = np.asarray(res.integral["K"])
    z = (K - K_true) / np.asarray(res.integral["K_stderr"])
    # z ~ N(0,1) if the propagated errors (ARW·√T per integral + bias error·T) are right
    assert np.all(np.abs(z) < 4), z
    # the article's M = C·B⁻¹ is K⁻¹ (three segments: exact)
    np.testing.assert_allclose(
        res.integral["M"], res.integral["C_rad"] @ np.linalg.inv(res.integral["B_rad"]), rtol=1e-12
    )
    # theory for a diagonal entry: σ_K ≈ sqrt(n_k)·dt·σ / |angle| = sqrt(600)·0.01·0.001/2π
    # (600 samples per 6-s segment; the bias term T·σ/sqrt(n_still) adds ~ 6·1e-3/sqrt(~3000) ≈ 1e-4 rad,
    # i.e. ~ 1.3 %: combined σ_K ≈ 3.9e-5 ... 4.2e-5 depending on the still count)
    se = np.asarray(res.integral["K_stderr"])
    base = np.sqrt(601) * 0.01 * SIGMA_RAD_S / (2 * np.pi)
    assert np.all((se > base) & (se < 1.5 * base)), se / base
    z_b = (res.params["bias"]["b_rad_s"] - TRUE["bias"]["b_rad_s"]) / res.stderr["bias"]["b_rad_s"]
    assert np.all(np.abs(z_b) < 4)
    # apply: the corrected rate integrates to the true angles
    out = res.apply(rec)
    for s in segs:
        m = (rec.t_s >= s.t_start_s) & (rec.t_s <= s.t_end_s)
        ang = np.trapezoid(out.gyro_rad_s[m], rec.t_s[m], axis=0)
        want = np.asarray(s.angle_S_rad)
        assert np.all(np.abs(ang - want) < 4 * 6 * 2 * np.pi * base)  # 4σ of the angle ≈ 4·|angle|·σ_K·√(3 terms)


def test_integral_method_takes_rotations_about_oblique_axes():
    """K = B·C⁺ holds for any known rotation vectors c_k that span S: turns about three oblique
    axes give K within 4 σ of its propagated standard error, as turns about x, y, z do."""
    from scipy.spatial.transform import Rotation

    Q = Rotation.from_euler("xyz", [30.0, -20.0, 45.0], degrees=True).as_matrix()
    rec, segs, _ = hand_session(3, axes_S=Q)
    assert all(s.axis is None for s in segs)
    r = integral_calibration(rec, segs)
    z = (r.K - E.k_matrix(TRUE)) / r.K_stderr
    assert np.all(np.abs(z) < 4), z
    np.testing.assert_allclose(r.C_rad, -2 * np.pi * Q, rtol=1e-12)


def test_integral_method_refuses_still_segments():
    rec, segs, _ = hand_session(1)
    with pytest.raises(GyroInputError, match="is still; the method takes known rotations only"):
        integral_calibration(rec, [*segs, Segment.still(0.0, 10.0)])


def test_integral_method_needs_all_three_axes_and_still_data():
    rec, segs, _ = hand_session(1)
    with pytest.raises(GyroInputError, match="all three axes"):
        integral_calibration(rec, segs[:2])
    with pytest.raises(GyroInputError, match="integral method"):
        Calibrator(effects=["bias", "scale", "bias_thermal"], segments=segs)


def test_still_mask_finds_the_still_parts():
    rec, segs, w = hand_session(2)
    m = still_samples(rec, STILL_GATE, exclude_s=[(s.t_start_s, s.t_end_s) for s in segs], margin_s=0.5)
    moving = np.any(w != 0, axis=1)
    assert not np.any(m & moving)
    # nearly all truly still time outside the segment margins is found (1-s windows, α = 1e-3)
    assert m.sum() > 0.8 * np.sum(~moving) - 3 * 700


@pytest.mark.slow
def test_monte_carlo_integral_errors_are_honest():
    """60 seeds: z = (K̂ − K)/σ̂ pooled over the 9 entries; effective count ≈ 60·3 →
    sd of var(z) ≈ 0.105; accept 0.7 < var(z) < 1.35."""
    K_true = E.k_matrix(TRUE)
    zs = []
    for seed in range(60):
        rec, segs, _ = hand_session(100 + seed)
        r = integral_calibration(rec, segs)
        zs.append(((r.K - K_true) / r.K_stderr).ravel())
    z = np.concatenate(zs)
    assert 0.7 < np.var(z) < 1.35, np.var(z)


# ------------------------------------------------------------------ imucal's Ferraris session
def test_imucal_ferraris_session_beside_imucal(shared_data):
    """Our core (integral method + still-pose g-sensitivity) on imucal's example session next
    to imucal's FerrarisCalibration on the same file. imucal: raw − b_g − K_ga·a = K_g·R_g·ω;
    ours: y − b − H·f = K·ω, so K ≡ K_g·R_g, b ≡ b_g, H ≡ K_ga (deg/s → rad/s)."""
    imucal = pytest.importorskip("imucal")
    pd = pytest.importorskip("pandas")
    from gyrocore.readers.datasets import imucal_segments, read_imucal

    d = shared_data / "imucal_ferraris"
    rec = read_imucal(d / "example_ferraris_session.csv")
    segs = imucal_segments(rec)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RepairWarning)
        res = Calibrator(effects=["bias", "scale", "misalignment", "g_sensitivity"], segments=segs).fit(rec)
    data = pd.read_csv(d / "example_ferraris_session.csv").set_index("n_samples")
    sl = pd.read_json(d / "example_ferraris_session_list.json").T
    regions = imucal.ferraris_regions_from_section_list(data, sl)
    cal = imucal.FerrarisCalibration().compute(
        regions, sampling_rate_hz=102.4, from_acc_unit="m/s^2", from_gyr_unit="deg/s"
    )
    K_imucal = cal.K_g @ cal.R_g
    K = np.asarray(res.integral["K"])
    K_se = np.asarray(res.integral["K_stderr"])
    b = np.degrees(res.params["bias"]["b_rad_s"])
    H = np.degrees(res.params["g_sensitivity"]["h_rad_s_per_m_s2"])
    # The two differ only in which samples give the bias/H (imucal: the six labelled pose
    # sections; ours: every still window outside the rotations) and in rectangle vs trapezoid
    # integration. A bias difference δb and H difference δH change a 360° integral by
    # (|δb| + 9.81·|δH|)·T, i.e. K by that / 360°; allow that plus 3 of our σ_K.
    T = float(np.max(res.integral["segment_duration_s"]))
    db = np.max(np.abs(b - cal.b_g))
    dH = np.max(np.abs(H - cal.K_ga))
    tol = (db + 9.81 * dH) * T / 360.0 + 3 * K_se
    assert np.all(np.abs(K - K_imucal) < tol), (K - K_imucal, tol)
    assert np.all(np.abs(K - K_imucal) < 2e-4)  # and both agree to 0.02 % in absolute terms
    # bias: the same static data, different selections -> agree within 0.01 deg/s (the
    # per-pose bias spread of this hand session is ~0.005 deg/s)
    assert np.all(np.abs(b - cal.b_g) < 0.01)
    np.set_printoptions(precision=5, suppress=True)
    print("\nimucal K_g@R_g\n", K_imucal, "\nours K\n", K, "\nours sigma_K\n", K_se)
    print("imucal b_g deg/s", cal.b_g, "ours", b, "+-", np.degrees(res.stderr["bias"]["b_rad_s"]))
    print(
        "imucal K_ga deg/s/(m/s2)\n",
        cal.K_ga,
        "\nours H\n",
        H,
        "\nours sigma_H\n",
        np.degrees(res.stderr["g_sensitivity"]["h_rad_s_per_m_s2"]),
    )


# ------------------------------------------------------------------ multi-pose (gravity reference)
def pose_session(seed, K, *, clip_rad_s=None):
    """Still start, then 12 tilting rotations (2 s, 0.8–2 rad about mixed axes) with 3-s
    poses between; gravity seen by the accelerometer in each pose (noise 0.02 m/s²)."""
    from scipy.spatial.transform import Rotation

    from gyrocore.attitude import integrate_gyro

    rng = np.random.default_rng(seed)
    rate = 100.0
    ws = [np.zeros((3000, 3))]
    axes = [
        [1, 0, 0],
        [0, 1, 0],
        [0, 0, 1],
        [1, 1, 0],
        [0, 1, 1],
        [1, 0, 1],
        [1, -1, 0],
        [0, 1, -1],
        [-1, 0, 1],
        [1, 1, 1],
        [1, 0, 0],
        [0, 1, 0],
    ]
    for a in axes:
        a = np.asarray(a, float) / np.linalg.norm(a)
        u = np.arange(200) / 200
        ang = rng.uniform(0.8, 2.0) * rng.choice([-1, 1])
        ws += [np.outer(ang / 2.0 * (1 - np.cos(2 * np.pi * u)), a), np.zeros((300, 3))]
    w = np.vstack(ws)
    n = len(w)
    t = np.arange(n) / rate
    q = integrate_gyro(t, w)
    up = np.array([0.0, 0.3, 0.95]) / np.linalg.norm([0.0, 0.3, 0.95])
    f = 9.81 * Rotation.from_quat(q[:, [1, 2, 3, 0]]).inv().apply(up) + rng.normal(0, 0.02, (n, 3))
    y = w @ K.T + np.array([0.01, -0.02, 0.005]) + rng.normal(0, 0.002, (n, 3))
    if clip_rad_s is not None:
        y = np.clip(y, -clip_rad_s, clip_rad_s)
    return Recording(t_s=t, gyro_rad_s=y, accel_m_s2=f)


K_POSE = np.array([[1.02, 0.01, -0.005], [0.003, 0.98, 0.008], [-0.006, 0.004, 1.01]])


def test_gravity_pose_calibration_recovers_K():
    from gyrocore.calib.rotations import gravity_pose_calibration

    r = gravity_pose_calibration(pose_session(0, K_POSE))
    assert len(r.intervals) == 13 and r.n_motions_saturated == 0
    # standard errors from the LM Jacobian × residual variance (accel-direction noise
    # 0.02/9.81 = 2 mrad per pose); they omit the first-pose bias error (σ_b·T ≈ 4e-5·2 s
    # ≈ 1e-4 rad per motion, about 5 % of the pose noise), hence 5σ rather than 4σ
    z = (r.K - K_POSE) / r.K_stderr
    assert np.all(np.abs(z) < 5), z
    assert r.rms_residual_rad < 3 * 0.02 / 9.81  # the misfit is the pose-direction noise


def test_gravity_pose_calibration_drops_clipped_motions():
    from gyrocore.calib.rotations import gravity_pose_calibration

    # peak rate of a 2-rad, 2-s motion is 2 rad/s; clip at 1.5 rad/s cuts the larger turns
    with pytest.warns(RepairWarning, match="clipped"):
        r = gravity_pose_calibration(pose_session(1, K_POSE, clip_rad_s=1.5))
    assert r.n_motions_saturated > 0
    assert np.all(np.abs(r.K - K_POSE) < 5 * r.K_stderr)


def test_tomisuarez2_multipose_beside_authors(shared_data):
    """The tomisuarez2 hand session (Tedaldi protocol) calibrated by our multi-pose method,
    beside the authors' params_gyro.csv (their model ω = T·diag(k)·(raw − b), raw in LSB).
    The session is weak for the gyro: 2 of its 9 motions clip at ±250 °/s and the rest leave a
    gravity misfit of ~5° rms, so σ_K ≈ 0.04–0.07. The test states what the data support:
    the bias (same first-pose average) agrees to 0.001 °/s, and K agrees within 2.5 σ."""
    from gyrocore.readers.datasets import read_tomisuarez2
    from gyrocore.calib.rotations import gravity_pose_calibration

    d = shared_data / "tomisuarez2_mpu6050"
    rec = read_tomisuarez2(d / "example_data_calibration.csv")
    with pytest.warns(RepairWarning, match="clipped"):
        r = gravity_pose_calibration(rec, pose_std_factor=10.0)
    p = np.loadtxt(d / "params_gyro.csv")
    m, k, b_lsb = p[:6], p[6:9], p[9:]
    T = np.array([[1, -m[0], m[1]], [m[2], 1, -m[3]], [-m[4], m[5], 1]])
    k0 = np.radians(1.0) / 131.0  # rad/s per LSB at ±250 °/s, as read by gyrocore.readers.convert
    K_auth = np.linalg.inv(T @ np.diag(k / k0))
    assert r.n_motions_saturated == 2
    np.testing.assert_allclose(np.degrees(r.bias_rad_s), b_lsb / 131.0, atol=1e-3)
    assert np.all(np.abs(r.K - K_auth) < 2.5 * r.K_stderr), (r.K - K_auth) / r.K_stderr
    np.set_printoptions(precision=4, suppress=True)
    print(
        "\nours K\n",
        r.K,
        "\nsigma\n",
        r.K_stderr,
        "\nauthors K\n",
        K_auth,
        "\nbias ours deg/s",
        np.degrees(r.bias_rad_s),
        "authors",
        b_lsb / 131.0,
        "\nrms gravity misfit deg",
        np.degrees(r.rms_residual_rad),
        "poses",
        len(r.intervals),
    )


# ------------------------------------------------------------------ external bias (no still part)
def _no_still_session(seed, *, rate_hz=100.0):
    """One turn about each axis (4 s each, smooth), only 0.3 s rest between them and at the
    ends: no still window of 1 s exists. Segments: each rotation ± 0.1 s (no overlap)."""
    rng = np.random.default_rng(seed)
    rot_s, rest_s = 4.0, 0.3
    n_rot, n_rest = int(rot_s * rate_hz), int(rest_s * rate_hz)
    pieces, segs = [np.zeros((n_rest, 3))], []
    t_cur = rest_s
    for i in range(3):
        u = np.arange(n_rot) / n_rot
        w = np.zeros((n_rot, 3))
        w[:, i] = -2 * np.pi / rot_s * (1 - np.cos(2 * np.pi * u))  # −1 turn
        pieces += [w, np.zeros((n_rest, 3))]
        segs.append(Segment.about_axis(t_cur - 0.1, t_cur + rot_s + 0.1, "xyz"[i], -360.0))
        t_cur += rot_s + rest_s
    w = np.vstack(pieces)
    t = np.arange(len(w)) / rate_hz
    y = E.deterministic(TRUE, E.ModelInputs(t_s=t, omega_S_rad_s=w)) + rng.normal(0, SIGMA_RAD_S, w.shape)
    return Recording(t_s=t, gyro_rad_s=y, meta={"rate_hz": str(rate_hz)}), segs, w


def test_external_bias_errors_are_propagated_montecarlo():
    """200 seeds without a still part; the bias comes from outside with a known error
    δb ~ N(0, σ_b²), σ_b = 2 mrad/s (dominant: δb·T over T ≈ 4.2 s is ≈ 0.5° per segment).
    z = (K̂ − K)/σ̂ pooled over the 9 entries: the bias error is shared by a row's three
    segments, so the effective count is ≈ 200·3 → sd of var(z) ≈ √(2/600) = 0.058; accept
    0.8 < var(z) < 1.2 (±3.4 sd). Ignoring σ_b (se given as 0) must fail that band."""
    K_true = E.k_matrix(TRUE)
    se_b = 2e-3
    z_ok, z_naive = [], []
    for seed in range(200):
        rec, segs, _ = _no_still_session(300 + seed)
        rng = np.random.default_rng(10_000 + seed)
        b_ext = TRUE["bias"]["b_rad_s"] + se_b * rng.standard_normal(3)
        noise_lr = np.full(3, SIGMA_RAD_S**2 / 100.0)  # white noise: N² = σ²·dt
        r = integral_calibration(
            rec, segs, bias_rad_s=b_ext, bias_stderr_rad_s=np.full(3, se_b), noise_lr_rad2_s=noise_lr
        )
        r0 = integral_calibration(rec, segs, bias_rad_s=b_ext, bias_stderr_rad_s=np.zeros(3), noise_lr_rad2_s=noise_lr)
        assert r.n_still == 0 and np.array_equal(r.bias_rad_s, b_ext)
        z_ok.append(((r.K - K_true) / r.K_stderr).ravel())
        z_naive.append(((r0.K - K_true) / r0.K_stderr).ravel())
    assert 0.8 < np.var(np.concatenate(z_ok)) < 1.2, np.var(np.concatenate(z_ok))
    assert np.var(np.concatenate(z_naive)) > 1.2


def test_external_bias_options_and_errors(tmp_path):
    rec, segs, _ = _no_still_session(5)
    with pytest.raises(GyroInputError, match="no still part found.*--bias-from"):
        integral_calibration(rec, segs)
    with pytest.raises(GyroInputError, match="standard error"):
        integral_calibration(rec, segs, bias_rad_s=np.zeros(3))
    with pytest.raises(GyroInputError, match="3 finite"):
        integral_calibration(
            rec, segs, bias_rad_s=np.zeros(2), bias_stderr_rad_s=np.zeros(3), noise_lr_rad2_s=np.zeros(3)
        )
    ext = {
        "bias_rad_s": TRUE["bias"]["b_rad_s"],
        "bias_stderr_rad_s": np.full(3, 1e-4),
        "noise_lr_rad2_s": np.full(3, SIGMA_RAD_S**2 / 100.0),
    }
    with pytest.raises(GyroInputError, match="integral method only"):
        Calibrator(effects=["bias", "scale"], external_bias=ext)
    res = Calibrator(effects=["bias", "scale", "misalignment"], segments=segs, external_bias=ext).fit(rec)
    np.testing.assert_array_equal(res.params["bias"]["b_rad_s"], ext["bias_rad_s"])
    np.testing.assert_array_equal(res.stderr["bias"]["b_rad_s"], ext["bias_stderr_rad_s"])
    z = (np.asarray(res.integral["K"]) - E.k_matrix(TRUE)) / np.asarray(res.integral["K_stderr"])
    assert np.all(np.abs(z) < 4), z  # N(0,1) per entry
    assert any("external bias" in n for n in res.notes)


def test_cli_calibrate_with_external_bias(tmp_path, capsys):
    import json

    from gyrocore.cli import build_group, run_cli
    from gyrocore.data.recording import write_csv

    rec, segs, _ = _no_still_session(6)
    write_csv(rec, tmp_path / "rot.csv")
    write_segments(segs, tmp_path / "seg.csv")
    base = [
        "calibrate",
        str(tmp_path / "rot.csv"),
        "--effects",
        "bias,scale,misalignment",
        "-o",
        str(tmp_path / "p.json"),
    ]
    assert run_cli(build_group(), base + ["--segments", str(tmp_path / "seg.csv")]) == 2
    assert "--bias-from" in capsys.readouterr().err
    assert run_cli(build_group(), base + ["--bias-dps", "1,2,3"]) == 2
    assert "give --segments too" in capsys.readouterr().err
    b_dps = ",".join(f"{v:.9f}" for v in np.degrees(TRUE["bias"]["b_rad_s"]))
    rc = run_cli(
        build_group(),
        base
        + [
            "--segments",
            str(tmp_path / "seg.csv"),
            "--bias-dps",
            b_dps,
            "--bias-se-dps",
            "0.001,0.001,0.001",
            "--arw-dps-rt-hz",
            f"{np.degrees(SIGMA_RAD_S) / 10:.9f}",
            "--json",
        ],
    )
    out = capsys.readouterr()
    assert rc == 0, out.err
    d = json.loads(out.out)
    K = np.asarray(d["integral"]["K"])
    z = (K - E.k_matrix(TRUE)) / np.asarray(d["integral"]["K_stderr"])
    assert np.all(np.abs(z) < 4), z


def test_sunsided_set1_turns_with_bias_from_the_static_recording(shared_data):
    """The sunsided hand turns have no still part (the hand moves within 0.5 s of both ends);
    bias from set-1's static recording (StaticBiasCalibrator). Each diagonal K_jj must be 1
    within its hand-rotation uncertainty: 3 standard errors (noise + bias error·T), plus the
    end pose put back by eye (±5° over 720°: 0.7 %), plus the tilt θ_j of the hand's turn axis
    from the sensor axis, which shortens the on-axis integral by 1 − cos θ_j (θ_j measured
    from column j's off-diagonals). MPU-6050 sensitivity tolerance is ±3 % (datasheet), so
    the test can fail on a wrong scale, sign or unit. The column norms (tilt-free) must be 1
    within 3 SE + 0.7 % as well."""
    from gyrocore.calib.bias import StaticBiasCalibrator
    from gyrocore.readers.convert import concat_converted, load_with_segments

    base = shared_data / "sunsided_mpu6050" / "set-1"
    names = [
        "rotate-360ccw-around-x-pointing-forward",
        "rotate-360ccw-around-y-pointing-left",
        "rotate-360ccw-around-z-pointing-up",
    ]
    if not (base / "unmoved-x-pointing-forward").exists():
        pytest.skip("sunsided set-1 absent")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RepairWarning)
        conv = concat_converted([load_with_segments(base / n) for n in names])
        static = load_with_segments(base / "unmoved-x-pointing-forward").recording
    with pytest.raises(GyroInputError, match="no still part"):
        Calibrator(effects=["bias", "scale", "misalignment"], segments=conv.segments).fit(conv.recording)
    sb = StaticBiasCalibrator().fit(static)
    res = Calibrator(effects=["bias", "scale", "misalignment"], segments=conv.segments, external_bias=sb).fit(
        conv.recording
    )
    K = np.asarray(res.integral["K"])
    Ks = np.asarray(res.integral["K_stderr"])
    hand = 5.0 / 720.0
    norms = np.linalg.norm(K, axis=0)
    tilt = np.arccos(np.clip(np.diag(K) / norms, -1, 1))
    for j in range(3):
        assert abs(K[j, j] - 1) < 3 * Ks[j, j] + hand + (1 - np.cos(tilt[j])), (j, K[j, j], Ks[j, j], tilt[j])
        assert abs(norms[j] - 1) < 3 * np.linalg.norm(Ks[:, j]) + hand, (j, norms[j])
    # the bias's standard error reaches K: every diagonal SE exceeds the pure-noise part
    assert np.all(np.asarray(res.stderr["bias"]["b_rad_s"]) == sb.bias_se_rad_s)
