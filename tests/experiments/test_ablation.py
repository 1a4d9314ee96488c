"""Tests of experiments.ablation's scoring core (synthetic data; no simulator needed)."""

from __future__ import annotations

import numpy as np
import pytest

from experiments import ablation as A
from gyrocore.effects import registry as E


def _static_case(seed=0, n=6000, rate=200.0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    f = np.tile([0.0, 0.0, 9.80665], (n, 1))
    params = {
        "bias": {"b_rad_s": np.array([0.01, -0.02, 0.005]), "turn_on_sigma_rad_s": np.zeros(3)},
        "scale": {"s": np.array([0.01, -0.005, 0.02])},
        "g_sensitivity": {"h_rad_s_per_m_s2": rng.normal(0, 1e-4, (3, 3))},
    }
    inp = E.ModelInputs(t_s=t, omega_S_rad_s=np.zeros((n, 3)), f_S_m_s2=f)
    noise = rng.normal(0, 1e-3, (n, 3))
    y = E.deterministic(params, inp) + noise
    return t, y, noise, params, E.ModelInputs(t_s=t, f_S_m_s2=f)


def test_present_effects_and_rows():
    p = {
        "bias": {"b_rad_s": np.zeros(3), "turn_on_sigma_rad_s": np.full(3, 1e-3)},
        "scale": {"s": np.zeros(3)},
        "misalignment": {"m_rad": np.full(6, 1e-3)},
        "arw": {"n_rad_per_sqrt_s": np.full(3, 1e-4)},
    }
    assert A.present_effects(p) == ["bias", "misalignment"]  # zero scale is absent, noise is not a correction
    rows = A.row_names(["bias", "misalignment"])
    assert rows == [
        "none",
        "all",
        "all but bias",
        "all but misalignment",
        "only bias",
        "only misalignment",
        "true params",
        "floor",
    ]
    assert A.row_names(["bias"]) == ["none", "all", "true params", "floor"]


def test_corrected_gyro_static_removes_all_but_noise():
    t, y, noise, params, inp = _static_case()
    still = slice(0, 400)
    w = A.corrected_gyro(y, inp, params, ["bias", "scale", "g_sensitivity"], still)
    K = E.k_matrix(params)
    expect = (noise - noise[still].mean(axis=0)) @ np.linalg.inv(K).T
    assert np.allclose(w, expect, atol=1e-15)
    # without "bias": the bias stays in
    w2 = A.corrected_gyro(y, inp, params, ["scale", "g_sensitivity"], still)
    assert np.allclose(w2.mean(axis=0), params["bias"]["b_rad_s"] @ np.linalg.inv(K).T, atol=1e-4)  # 4σ/√N≈5e-5


def test_score_variants_orders_corrections():
    t, y, noise, params, inp = _static_case()
    q = np.tile([1.0, 0, 0, 0], (t.size, 1))
    still = slice(0, 400)
    variants = {
        "none": y,
        "all": A.corrected_gyro(y, inp, params, ["bias", "scale", "g_sensitivity"], still),
        "floor": noise,
    }
    sc = A.score_variants(t, q, variants, start=400)
    # none drifts at ~|b + H g| ≈ 0.023 rad/s for 28 s ≈ 37°; all and floor are noise-level:
    # σθ = 1e-3/√200·√28 ... per axis N√t with N = 1e-3/√200 → 3.7e-4 rad ≈ 0.02°, plus the
    # still-window mean error σ/√400·28 s ≈ 1.4e-3 rad ≈ 0.08° for "all".
    assert sc["none"][0].final_error_deg > 20
    assert sc["all"][0].final_error_deg < 0.5
    assert sc["floor"][0].final_error_deg < 0.2
    assert sc["all"][1].shape == (t.size - 400,)
    # integration starts from the truth at `start`
    assert sc["floor"][1][0] == 0.0


def test_instance_metrics_flattening():
    from gyrocore.attitude import AttitudeScore

    s = AttitudeScore(1.0, 0.5, 1.2, 0.1, 600.0, 100)
    f = AttitudeScore(0.1, 0.05, 0.12, 0.01, 600.0, 100)
    ab = A.InstanceAblation(
        "static",
        "x",
        1,
        ("bias",),
        ("bias",),
        {"none": s, "all": f, "floor": f},
        np.linspace(0, 600, len(A.CURVE_FRACTIONS)),
        {"none": np.ones(len(A.CURVE_FRACTIONS))},
    )
    m = A.instance_metrics(ab)
    assert m["none__final_deg"] == 1.0 and m["all__over_floor"] == 1.0 and m["none__over_floor"] == 10.0
    assert m["present__bias"] == 1.0 and m["present__scale"] == 0.0
    assert m["none__e00_deg"] == 1.0


def test_prediction_summary_budget_table_and_rows(tmp_path):
    """The ablation's JSON block "scenarios": medians over units of measured,
    predicted and floor RMS and of each budget component; prediction metrics are not rows."""
    from types import SimpleNamespace

    from experiments import ablation as A
    from experiments.montecarlo import MetricSummary, TaskResult

    def task(i, all_rms, pred):
        m = {
            "all__final_deg": 2 * all_rms,
            "all__rms_deg": all_rms,
            "all__drift_deg_per_min": 1.0,
            "floor__final_deg": 0.1,
            "floor__rms_deg": 0.05,
            "floor__drift_deg_per_min": 0.1,
            "pred__rms_deg": pred,
            "pred__final_deg": 2 * pred,
            "pred-floor__rms_deg": 0.05,
            "pred-floor__final_deg": 0.1,
            "all__over_pred": all_rms / pred,
            "budget__floor:arw__deg": 0.03,
            "budget__powerup-window__deg": 0.04,
        }
        return TaskResult(index=i, scenario="static", sensor="s", instance=i, seed=i, metrics=tuple(m.items()))

    tasks = [task(0, 0.10, 0.1), task(1, 0.20, 0.1), task(2, 0.05, 0.1)]
    summ = tuple(
        MetricSummary("static", "s", k, 3, float(np.median([t.metrics_dict[k] for t in tasks])), 0.0, 0.0, 0.0)
        for k in tasks[0].metrics_dict
    )
    camp = SimpleNamespace(scenarios=("static",), sensors=("s",), tasks=tasks, summary=summ)
    ps = A.prediction_summary(camp)["static"]
    assert ps["rms_all_deg"] == 0.10 and ps["rms_predicted_deg"] == 0.1 and ps["rms_floor_deg"] == 0.05
    assert ps["measured2_over_predicted2_mean"] == np.mean([1.0, 4.0, 0.25])
    assert ps["budget"] == {"floor:arw": 0.03, "powerup window": 0.04}
    assert np.isnan(ps["expected_r2_given_unit_mean"])  # no true-noise prediction in these metrics
    import dataclasses

    # E[r² | unit] = (true-noise / identified prediction)²
    camp.tasks = [
        dataclasses.replace(t, metrics=t.metrics + (("pred-true-noise__rms_deg", tn),))
        for t, tn in zip(tasks, (0.1, 0.12, 0.09))
    ]
    assert A.prediction_summary(camp)["static"]["expected_r2_given_unit_mean"] == pytest.approx(
        np.mean([1.0, 1.44, 0.81])
    )
    camp.tasks = tasks
    assert A._rows_in(camp, "static", "s") == ["all", "floor"]
    assert "powerup window" in A.budget_markdown({"static": ps})
    # a share that is float64 rounding of an unexcited parameter (1e-14 °) prints as 0, a real
    # small share (2e-4 °, above the 1e-6 ° cut) keeps its value
    tiny = {
        **ps,
        "budget": {"floor:arw": 0.03, "param:g_sensitivity": 2.07e-14, "param:scale": 2e-4, "powerup window": 0.04},
    }
    table = A.budget_markdown(
        {"static": tiny, "turntable": {**tiny, "budget": {**tiny["budget"], "param:g_sensitivity": 0.12}}}
    )
    assert "e-14" not in table and "0.12" in table
    assert A.budget_figure({"static": ps}, tmp_path).endswith(".png")


# ------------------------------------------------------------------ drift contract statistics
def test_mean_r2_is_unbiased_where_the_median_is_not_and_the_band_holds_its_rate():
    # A calibrated prediction: r² ~ Gamma(k, 1/k) (mean 1; a χ²_ν/ν with ν = 2k). Its mean over
    # units is centred on 1, the median of r is not: √(median χ²_ν/ν) = 0.86 at ν = 3.
    rng = np.random.default_rng(20261125)
    k, n, reps = 1.5, 2, 2_000_000
    r2 = rng.gamma(k, 1.0 / k, size=(reps, n))
    h = r2.mean(axis=1)
    assert abs(h.mean() - 1.0) < 5 * np.sqrt(1.0 / (n * k) / reps)  # 5σ of the Monte Carlo mean
    assert np.median(np.sqrt(rng.gamma(k, 1.0 / k, 200_001))) < 0.9
    # the band of the mean over n units leaves each side with probability α (Gamma(n·k)):
    # 2e6 replicates at α = 1e-3 give 2000 ± 45 per side; 5σ
    th = {"alpha": 1e-3, "scenarios": {"s": {"mc_units": 12, "r2_shape": k, "quality_mean": 0.0, "quality_sd": 0.0}}}
    b = A.drift_bands(th, "s", n)
    for tail in (np.count_nonzero(h < b["honesty_r2_lo"]), np.count_nonzero(h > b["honesty_r2_hi"])):
        assert abs(tail - 1e-3 * reps) < 5 * np.sqrt(1e-3 * reps)
    # pooled band over scenarios of equal shape: the mean of S·n such draws (Gamma(S·n·k) exactly)
    lo, hi = A.pooled_band({"alpha": 1e-3, "scenarios": {"a": {"r2_shape": k}, "b": {"r2_shape": k}}}, {"a": n, "b": n})
    from scipy import stats

    assert lo == pytest.approx(stats.gamma.ppf(1e-3, 2 * n * k, scale=1 / (2 * n * k)), rel=1e-9)
    assert hi == pytest.approx(stats.gamma.isf(1e-3, 2 * n * k, scale=1 / (2 * n * k)), rel=1e-9)


def test_r2_shape_lower_limit_covers_the_true_shape():
    # the lower 90 % limit of the Gamma shape from M = 12 units is below the true shape in
    # ≥ 90 % of samples (binomial: 60 samples, expect ≥ 54; ≥ 48 is 2.8σ below 54)
    rng = np.random.default_rng(7)
    below = sum(A.r2_shape(rng.gamma(2.0, 0.5, 12), seed=i, replicates=1000)[1] < 2.0 for i in range(60))
    assert below >= 48


def test_identified_noise_takes_slow_terms_from_the_longest_run():
    from types import SimpleNamespace

    from gyrocore.noise.model import NoiseModel

    def res(rate, n, N, B):
        nm = NoiseModel(arw_rad_per_sqrt_s=np.full(3, N), bias_instability_rad_s=np.full(3, B))
        return SimpleNamespace(noise_model={"rate_hz": rate}, n_samples=n, noise=lambda nm=nm: nm)

    table, thermal = res(1000.0, 320_000, 5e-5, 2.5e-5), res(100.0, 72_000, 6e-5, 3e-5)  # 320 s, 720 s
    cp = SimpleNamespace(results=(table, thermal))
    nm = A.identified_noise(cp, 1000.0)
    assert np.all(nm.arw_rad_per_sqrt_s == 5e-5) and np.all(nm.bias_instability_rad_s == 3e-5)
    assert np.all(A.identified_noise(cp, 1000.0, slow_from_longest=False).bias_instability_rad_s == 2.5e-5)
    nm100 = A.identified_noise(cp, 100.0)
    assert np.all(nm100.arw_rad_per_sqrt_s == 6e-5) and np.all(nm100.bias_instability_rad_s == 3e-5)
    # a longer table run keeps its own slow terms
    cp2 = SimpleNamespace(results=(res(1000.0, 2_000_000, 5e-5, 2.5e-5), thermal))
    assert np.all(A.identified_noise(cp2, 1000.0).bias_instability_rad_s == 2.5e-5)
    assert A.identified_noise(SimpleNamespace(results=()), 1000.0) is None
