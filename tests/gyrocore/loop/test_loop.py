"""The residual loop: undeclared effects are named (and only they), null cases find nothing.

Recordings come from :func:`experiments.close_the_loop.synthetic_recording`: a rich tumbling
reference through the shared measurement model (:func:`gyrocore.effects.registry.deterministic`) plus
ARW (0.005 °/s/√Hz) and flicker bias instability (3 °/h). The effect magnitudes are the
"1×" sizes of :data:`experiments.close_the_loop.DEFAULT_MAGNITUDE` (typical consumer MEMS).

Why "found == [effect]" can be asserted on one seed: the loop's selection rule controls the
family-wise error at α = 0.01 (Holm over candidates and steps), so a spurious extra effect on a
given seed has probability ≤ 1 % by construction, and the seeds below are fixed; each effect
is tested at a size the Monte Carlo in docs/loop.md identifies on 20 of 20 seeds
(:data:`TEST_SIZE`), so a miss here is a regression, not bad luck. The slow Monte Carlo test
re-measures the rates.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from experiments.close_the_loop import effect_params, identification_rates, synthetic_recording
from gyrocore.cli.commands.loop import command as loop_command
from gyrocore.errors import GyroInputError
from gyrocore.loop.loop import run_loop
from gyrocore.loop.model import CANDIDATES, COMPANION
from gyrocore.data.recording import write_csv

DURATION_S = 40.0
RATE_HZ = 200.0


def _rec(effects: dict, seed: int, **kw):
    params = {"bias": effect_params("bias")}
    params.update(effects)
    return synthetic_recording(params, seed=seed, duration_s=DURATION_S, rate_hz=RATE_HZ, **kw)


#: Size (× the 1× magnitude) and length per effect for the single-seed tests: where 1× over
#: 40 s is near the detection limit (Monte Carlo, docs/loop.md: bias_ramp 25 %, g2 35 %,
#: earth_rate 90 % identified at 1×/40 s), the test uses a size found on 20/20 seeds (3×) or a
#: longer recording (earth rate: 80 s, √2 more signal-to-noise on the Earth-rate vector).
TEST_SIZE = {"bias_ramp": (3.0, DURATION_S), "g2_sensitivity": (3.0, DURATION_S), "earth_rate": (1.0, 80.0)}


@pytest.mark.parametrize("effect", [c for c in CANDIDATES if c != "bias"])
def test_undeclared_effect_is_named_and_only_it(effect):
    size, dur = TEST_SIZE.get(effect, (1.0, DURATION_S))
    params = {"bias": effect_params("bias"), effect: effect_params(effect, size)}
    rec = synthetic_recording(params, seed=11, duration_s=dur, rate_hz=RATE_HZ)
    r = run_loop(rec, declared=["bias"])
    if effect in COMPANION:
        # a thermal polynomial referenced to T0 = 25 °C also shifts the constant term at the
        # recording's mean temperature (≈ 33 °C): that constant is the companion effect
        # (scale/bias), which the loop may name first; nothing else is allowed
        assert effect in r.found_effects and set(r.found_effects) <= {effect, COMPANION[effect]}, r.found_effects
    else:
        assert r.found_effects == [effect], (effect, r.found_effects)
    step = r.found[0]
    # evidence below the Holm threshold, and the error goes down
    assert step.evidence.p_value < step.evidence.threshold
    assert step.residual_rms_after_rad_s < step.residual_rms_before_rad_s
    assert r.residual_rms_after_rad_s < r.residual_rms_before_rad_s


def test_undeclared_bias_is_found_when_nothing_is_declared():
    rec = _rec({}, seed=12)
    r = run_loop(rec, declared=[])
    assert r.found_effects == ["bias"]
    # bias estimate within 5 HAC standard errors of the truth (the LS estimate is unbiased;
    # 5σ keeps the false-failure rate < 1e-6 per component)
    true_b = effect_params("bias")["b_rad_s"]
    ev = r.found[0].evidence
    for i in range(3):
        est, se = ev.params[f"b_rad_s[{i}]"], ev.std_errors[f"b_rad_s[{i}]"]
        assert abs(est - true_b[i]) < 5 * se


@pytest.mark.parametrize("seed", [21, 22, 23])
def test_null_nothing_undeclared_finds_nothing(seed):
    rec = _rec({}, seed=seed)
    r = run_loop(rec, declared=["bias"])
    assert r.found_effects == []
    assert r.residual_rms_after_rad_s == r.residual_rms_before_rad_s


def test_null_with_a_full_declared_model():
    effs = {e: effect_params(e) for e in ("scale", "misalignment", "g_sensitivity")}
    rec = _rec(effs, seed=24)
    r = run_loop(rec, declared=["bias", "scale", "misalignment", "g_sensitivity"])
    assert r.found_effects == []
    # the declared fit recovers the scale within 5 HAC standard errors
    s_true = effect_params("scale")["s"]
    for i in range(3):
        v, se = r.params["scale"][f"s[{i}]"]
        assert abs(v - s_true[i]) < 5 * se


def test_two_undeclared_at_once():
    rec = _rec({"scale": effect_params("scale"), "bias_thermal": effect_params("bias_thermal")}, seed=31)
    r = run_loop(rec, declared=["bias"])
    assert sorted(r.found_effects) == ["bias_thermal", "scale"]
    # every step reduces the residual; the final attitude error is far below the start
    for s in r.found:
        assert s.residual_rms_after_rad_s < s.residual_rms_before_rad_s
    assert r.attitude_error_after_deg < 0.5 * r.attitude_error_before_deg


def test_collinear_thermal_and_ramp_reported_as_ambiguous():
    # temperature linear in time: bias_thermal (order 1) and bias_ramp are one regressor
    rec = _rec({"bias_ramp": effect_params("bias_ramp", 3.0)}, seed=41, temp_profile="linear")
    r = run_loop(rec, declared=["bias"])
    assert len(r.found) == 1
    step = r.found[0]
    assert {step.effect, *step.evidence.ambiguous_with} >= {"bias_ramp", "bias_thermal"}


def test_attitude_reference_finds_scale():
    """Reference attitude only (no reference rate): windowed rotation residual."""
    rec = _rec({"scale": effect_params("scale")}, seed=51, with_quat=True)
    from dataclasses import replace

    rec = replace(rec, ref_rate_rad_s=None)
    r = run_loop(rec, declared=["bias"])
    assert r.reference == "attitude"
    assert r.found_effects == ["scale"]
    s_true = effect_params("scale")["s"]
    ev = r.found[0].evidence
    # first-order window residual: the estimate is within 5 HAC standard errors plus the
    # second-order term of the linearisation (|s|² ≈ 2.5e-5)
    for i in range(3):
        assert abs(ev.params[f"s[{i}]"] - s_true[i]) < 5 * ev.std_errors[f"s[{i}]"] + 3e-5
    assert r.attitude_error_after_deg < 0.2 * r.attitude_error_before_deg


def test_still_reference_finds_ramp():
    """A still recording (no reference columns): true rate 0 is the reference."""

    from gyrocore.data.recording import Recording

    rng = np.random.default_rng(5)
    n = int(120 * 100)
    t = np.arange(n) / 100.0
    ramp = np.array([3e-6, -2e-6, 1e-6])  # rad/s² (≈ 0.6 °/s/h)
    gyro = 0.01 + ramp * t[:, None] + rng.standard_normal((n, 3)) * 0.002
    rec = Recording(
        t_s=t, gyro_rad_s=gyro, accel_m_s2=np.tile([0, 0, 9.81], (n, 1)) + rng.standard_normal((n, 3)) * 0.01
    )
    r = run_loop(rec, declared=["bias"], reference="still")
    assert r.reference == "still"
    assert r.found_effects == ["bias_ramp"]
    assert "scale" in r.untestable


def test_unknown_effect_and_bad_alpha():
    rec = _rec({}, seed=1)
    with pytest.raises(GyroInputError, match="unknown effect"):
        run_loop(rec, declared=["bias", "nope"])
    with pytest.raises(GyroInputError, match="alpha"):
        run_loop(rec, declared=["bias"], alpha=2.0)


def test_cli_json_contract(tmp_path):
    rec = _rec({"scale": effect_params("scale")}, seed=61)
    f = tmp_path / "rec.csv"
    write_csv(rec, f)
    res = CliRunner().invoke(loop_command, [str(f), "--effects", "bias", "--json", "--plot-dir", str(tmp_path / "p")])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    for k in (
        "declared",
        "found",
        "residual_rms_before_rad_s",
        "residual_rms_after_rad_s",
        "attitude_error_before_deg",
        "attitude_error_after_deg",
    ):
        assert k in out
    assert out["declared"] == ["bias"]
    assert [f["effect"] for f in out["found"]] == ["scale"]
    f0 = out["found"][0]
    assert {"effect", "evidence", "residual_rms_before_rad_s", "residual_rms_after_rad_s"} <= set(f0)
    assert f0["residual_rms_after_rad_s"] < f0["residual_rms_before_rad_s"]
    assert (tmp_path / "p" / "loop_step1_scale.png").stat().st_size > 1000
    text = CliRunner().invoke(loop_command, [str(f), "--effects", "bias"])
    assert text.exit_code == 0 and "step 1: scale" in text.output


@pytest.mark.slow
def test_identification_and_false_alarm_rates_monte_carlo():
    """Over 20 seeds: identification ≥ 90 % at 1× (3× for the three weak ones), false alarms ≤ 10 %.

    Bound: with a family-wise α = 0.01 the expected false-alarm rate is ≤ 1 %; over 20 seeds
    P(≥ 3 false alarms | p = 0.01) ≈ 1e-3, so ≤ 2/20 (10 %) is a strict yet safe bound.
    """
    table = identification_rates(seeds=range(20), scales=(1.0, 3.0), duration_s=DURATION_S, rate_hz=RATE_HZ)
    for row in table:
        if row["effect"] == "none":
            assert row["false_alarm_rate"] <= 0.10
        else:
            assert row["false_alarm_rate"] <= 0.10, row
            if row["scale"] == 3.0 or row["effect"] not in ("bias_ramp", "g2_sensitivity", "earth_rate"):
                assert row["identification_rate"] >= 0.90, row


# ---------------------------------------------------------------------------- measured data
def _load(path):
    import warnings

    from gyrocore.readers.convert import load_with_segments
    from gyrocore.errors import RepairWarning

    if not path.exists():
        pytest.skip(f"{path} absent")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RepairWarning)
        return load_with_segments(path)


def test_measured_broad_slow_rotation(shared_data):
    c = _load(shared_data / "broad" / "02_undisturbed_slow_rotation_B.hdf5")
    r = run_loop(c.recording, declared=["bias"])
    assert r.reference == "attitude"
    # the optical reference lags/leads the IMU: a time offset of a few ms is found first
    assert r.found_effects[0] == "time_offset"
    tau = r.found[0].evidence.params["tau_s"]
    assert 0.001 < abs(tau) < 0.02
    assert r.residual_rms_after_rad_s < r.residual_rms_before_rad_s


def test_measured_sunsided_static_and_rotation(shared_data):
    c = _load(shared_data / "sunsided_mpu6050" / "set-2" / "unmoved-with-x-pointing-forward-10min")
    r = run_loop(c.recording, declared=["bias"])
    assert r.reference == "still"
    assert set(r.found_effects) <= {"bias_ramp", "bias_thermal", "bias_temp_rate"}
    assert r.attitude_error_after_deg <= r.attitude_error_before_deg
    rot = _load(shared_data / "sunsided_mpu6050" / "set-1" / "rotate-360ccw-around-x-pointing-forward")
    with pytest.raises(GyroInputError, match="too poor"):
        run_loop(rot.recording, declared=["bias"], segments=rot.segments)


def test_measured_imucal_ferraris(shared_data):
    c = _load(shared_data / "imucal_ferraris" / "example_ferraris_session.csv")
    r = run_loop(c.recording, declared=["bias"], segments=c.segments)
    assert r.reference == "angles"
    assert "scale" in r.found_effects
    assert r.attitude_error_after_deg < r.attitude_error_before_deg


def test_measured_static_logs(shared_data):
    for p in (
        shared_data / "tomisuarez2_mpu6050" / "imu_static_test.csv",
        shared_data / "pyulog_samples" / "sample.ulg",
    ):
        c = _load(p)
        r = run_loop(c.recording, declared=["bias"])
        assert r.reference == "still"
        assert r.residual_rms_after_rad_s <= r.residual_rms_before_rad_s
        assert all(
            f in ("bias_ramp", "bias_thermal", "bias_temp_rate", "g_sensitivity", "g2_sensitivity")
            for f in r.found_effects
        )


def test_still_log_drift_is_not_a_product_in_disguise(shared_data):
    """tomisuarez2 static 449 s: the catalogue refuses ``bias_ramp`` (its drift does not carry
    half to half); the open search used to name the z drift ``regressor[f_x*t]`` (log10 p
    −4.7) — with f_x constant on a still log that is a one-axis ramp under another name. It is
    now refused as bias_ramp's equivalent (docs/loop.md §4c)."""
    c = _load(shared_data / "tomisuarez2_mpu6050" / "imu_static_test.csv")
    r = run_loop(c.recording, declared=["bias"])
    eq = r.open_search["regressor"]["collinear_with_simpler"]
    assert eq["f_x*t@z"].startswith("bias_ramp")
    assert not any(u.kind == "regressor" and "*t" in u.effect for u in r.unexplained)


def test_measured_sunsided_session_hand_turns(shared_data):
    """Static + three 2-turn hand rotations of set-2, angle about the axis only.

    The PROVENANCE integrates −707°, +728°, +706° for ±720°: scale errors of about −1.8 %,
    +1.0 %, −1.9 %; the loop's per-axis scale must match within 3 standard errors plus the
    2° hand-turn uncertainty over 720° (0.3 %) that the PROVENANCE figures also carry.
    """
    from experiments.close_the_loop import concat_session

    base = shared_data / "sunsided_mpu6050" / "set-2"
    names = [
        "unmoved-with-x-pointing-forward",
        "rotate-ccw-around-x-pointing-forward",
        "rotate-ccw-around-y-pointing-left",
        "rotate-ccw-around-z-pointing-up",
    ]
    if not all((base / n).exists() for n in names):
        pytest.skip("sunsided set-2 absent")
    import warnings

    from gyrocore.errors import RepairWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RepairWarning)
        rec, segs = concat_session([base / n for n in names])
    r = run_loop(rec, declared=["bias"], segments=segs, angle_mode="axis")
    assert r.reference == "angles" and r.found_effects == ["scale"]
    expected = np.array([707.2 / 720 - 1, 727.5 / 720 - 1, 706.2 / 720 - 1])
    for i in range(3):
        v, se = r.params["scale"][f"s[{i}]"]
        assert abs(v - expected[i]) < 3 * se + 0.003, (i, v, se, expected[i])


@pytest.mark.parametrize("seed", [48, 73, 194])
def test_coloured_noise_null_is_not_a_slow_effect(seed):
    """White + flicker + RRW + Gauss–Markov (τc 20 s) nulls on which the HAC test (with the
    halves guard) named ``bias_thermal`` (seeds 48, 73) or ``bias_ramp`` (194) in the Monte Carlo
    of docs/loop.md §4a: with the model-based test the loop names nothing. The family-wise bound
    makes a claim on a given null seed a ≤ α event; the seeds are the measured failures of the
    HAC-only rule (at the time of measurement, lsq of c2979b0), so the test fails if the
    model-based test stops doing its job."""
    from experiments.close_the_loop import OPEN_NOISE

    rec = _rec({}, seed=seed, **OPEN_NOISE)
    r = run_loop(rec, declared=["bias"], alpha=0.005, open_search=False)
    assert r.found_effects == [], r.found_effects
    ev = r.tested["bias_ramp"]
    assert np.isfinite(ev.model_log10_p) and np.isfinite(ev.hac_log10_p)
    assert ev.log10_p == max(ev.hac_log10_p, ev.model_log10_p)
