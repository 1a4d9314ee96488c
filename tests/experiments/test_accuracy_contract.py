"""The project's accuracy contract (docs/accuracy.md): tests that fail when the calibration gets
worse than it claims, when the protocol or its standard errors get worse, or when a correction
stops paying off.

Each scenario is simulated for CONTRACT_UNITS fixed sensor units (icm42688p) on a short run,
calibrated the way a user would (rate-table and thermal calibration runs of the same unit,
power-up bias from the motion-gated still start), scored by the attitude error against the
truth, and its error *predicted* from the calibration's own standard errors and the noise
(:func:`experiments.ablation.ablate_instance`, :mod:`gyrocore.calib.budget`). Checked per scenario
(:func:`experiments.ablation.drift_contract_failures`):

1. honesty: the mean over the units of r² = (measured/predicted RMS error)² lies in a band
   around 1 (the prediction is an expected mean-square error, so E[r²] = 1 exactly when it is
   calibrated; the prediction uses the calibration's noise-model standard errors and the noise
   model it identified);
2. quality: the geometric mean of predicted/floor RMS error (both with the unit's true noise,
   so that it moves with the protocol and the standard errors, not with the identification's
   scatter) stays below a bound (nearly deterministic, so this band is tight: a shorter still
   window, a worse protocol or inflated standard errors move it);
3. pooled honesty: the mean over all scenarios of their mean r² (a shift common to all);
4. every correction that pays off in the Monte Carlo still does: RMS(all but X) > RMS(all).

The bands (DRIFT_THRESHOLDS) come from ``experiments.ablation.drift_thresholds`` on a Monte
Carlo of fresh units (docs/accuracy.md, "The contract"): the honesty band of the mean of n units
is the Gamma(n·k, 1/(n·k)) interval around 1, k the Gamma shape of one unit's r² at its lower
90 % limit from the Monte Carlo; the quality bound a Student-t prediction bound; one-sided tail
α = 1e-4 each (20 tails: a correct calibration fails CI with probability ≤ 2e-3). Mutation
tests below prove that the contract bites (half still window, scale dropped, standard errors
×3; slow: thermal order forced to 1 on a unit with a quadratic thermal bias); the slow test
checks it over fresh units (campaign seed 99).
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mujoco")

from experiments import ablation as A

#: The fixed units of the default tests (not among the campaign's instances).
CONTRACT_UNITS = (20240607, 20240608)

#: Effects that must keep paying off per scenario (omitting them raised the RMS error by ≥ 5 %
#: in every unit of the Monte Carlo; contract_thresholds(...)["pays_off"]).
PAYS_OFF = {
    "static": ["bias"],
    "static_bumped": ["bias"],
    "turntable": ["bias", "scale", "misalignment", "g_sensitivity"],
    "thermal": ["bias", "bias_thermal"],
    "hover": ["bias"],
    "power_cycles": ["bias"],
}

#: Bands of the drift contract for len(CONTRACT_UNITS) units, from ``drift_thresholds`` on
#: 17 fresh units: instances 0-8 of campaign seed 31 and 0-7 of campaign seed 32
#: (experiments.montecarlo.instance_seeds; contract durations, full calibration runs)
#: (docs/accuracy.md, "The contract": honesty = mean r² with a Gamma
#: band around 1, k = "r2_shape" the lower 90 % limit of the Gamma shape; quality with the true
#: noise); the bands for n units are evaluated by experiments.ablation.drift_bands.
DRIFT_THRESHOLDS = {
    "alpha": 0.0001,
    "scenarios": {
        "static": {
            "mc_units": 17,
            "r2_mean": 0.92887,
            "r2_mean_se": 0.21124,
            "r2_shape_mle": 1.3761,
            "r2_shape": 0.79742,
            "quality_mean": 0.6022,
            "quality_sd": 5.216e-06,
        },
        "static_bumped": {
            "mc_units": 17,
            "r2_mean": 1.2017,
            "r2_mean_se": 0.20086,
            "r2_shape_mle": 1.8394,
            "r2_shape": 1.0422,
            "quality_mean": 0.4532,
            "quality_sd": 8.3414e-07,
        },
        "turntable": {
            "mc_units": 17,
            "r2_mean": 0.9111,
            "r2_mean_se": 0.095828,
            "r2_shape_mle": 5.0544,
            "r2_shape": 2.8106,
            "quality_mean": 0.49525,
            "quality_sd": 0.032234,
        },
        "thermal": {
            "mc_units": 17,
            "r2_mean": 0.9902,
            "r2_mean_se": 0.16294,
            "r2_shape_mle": 2.8824,
            "r2_shape": 1.6454,
            "quality_mean": 0.30019,
            "quality_sd": 0.0046555,
        },
        "hover": {
            "mc_units": 17,
            "r2_mean": 1.2186,
            "r2_mean_se": 0.28964,
            "r2_shape_mle": 1.1207,
            "r2_shape": 0.64125,
            "quality_mean": 0.44902,
            "quality_sd": 3.8112e-05,
        },
        "power_cycles": {
            "mc_units": 17,
            "r2_mean": 1.0335,
            "r2_mean_se": 0.18012,
            "r2_shape_mle": 2.2236,
            "r2_shape": 1.2748,
            "quality_mean": -0.1799,
            "quality_sd": 5.0627e-06,
        },
    },
}


def _score(scenario, seed, cache, **kw):
    from experiments.report import single_thread_blas

    with single_thread_blas():
        return A.ablate_instance(
            scenario,
            sensor=A.CONTRACT_SENSOR,
            seed=seed,
            duration_s=A.CONTRACT_DURATIONS_S[scenario],
            quick=A.CONTRACT_QUICK_CALIBRATION,
            cache_dir=cache,
            **kw,
        )


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("calcache"))


@pytest.fixture(scope="module")
def results(cache):
    return {sc: [_score(sc, u, cache, mahony_kp_per_s=None) for u in CONTRACT_UNITS] for sc in A.SCENARIOS}


def _stats(abs_):
    return A.drift_statistics([A.instance_metrics(ab) for ab in abs_])


def _failures(by_scenario):
    return A.drift_contract_failures({sc: _stats(v) for sc, v in by_scenario.items()}, DRIFT_THRESHOLDS)


def test_drift_contract_holds(results):
    fails = _failures(results)
    assert not fails, "; ".join(fails)


@pytest.mark.parametrize("scenario", A.SCENARIOS)
def test_each_correction_pays_off(results, scenario):
    for ab in results[scenario]:
        for eff in PAYS_OFF[scenario]:
            assert eff in ab.present, f"{scenario}: {eff} no longer present in the unit"
            worse = ab.scores[f"all but {eff}"].rms_error_deg
            best = ab.scores["all"].rms_error_deg
            assert worse > best, (
                f"{scenario}: omitting {eff} no longer raises the error ({worse:.4g} <= {best:.4g} deg)"
            )
        # and the corrections together beat no correction by a wide margin
        assert ab.scores["all"].rms_error_deg < 0.5 * ab.scores["none"].rms_error_deg


# ------------------------------------------------------------------ mutations: the contract bites
def _mutated(calibration, *, drop=(), se_factor=1.0):
    out = []
    for st in calibration:
        d = {}
        for key, pd in st.items():
            if key.partition("@")[0] in drop:
                continue
            d[key] = {k: (np.asarray(v) * se_factor if k.endswith(A.SE_SUFFIX) else v) for k, v in pd.items()}
        out.append(d)
    return out


def _calibration(seed, cache):
    from sim import scenarios as S

    pt = S.simulate("static", sensor=A.CONTRACT_SENSOR, seed=seed, duration_s=2.0).params_true
    return A.calibrate_instance(
        A.CONTRACT_SENSOR, seed, A.present_effects(pt), quick=A.CONTRACT_QUICK_CALIBRATION, cache_dir=cache
    )


def test_mutation_half_power_up_window_fails(results, cache):
    # 1-s still window instead of 2 s: the power-up bias error doubles its variance; the
    # prediction sees it (quality band), whatever the noise draw.
    mut = {
        sc: [
            _score(sc, u, cache, mahony_kp_per_s=None, powerup_window_s=A.POWERUP_WINDOW_S / 2) for u in CONTRACT_UNITS
        ]
        for sc in ("static",)
    }
    fails = _failures(mut)
    assert any(f.startswith("static:") for f in fails), fails


def test_mutation_dropped_scale_fails(results, cache):
    # the calibration "forgets" scale (both the table's and the thermal run's): the budget's
    # uncorrected term (completeness: ×6.0 > 1.05) and, on the rate table, the measured error
    # against what the calibration claims (honesty: mean r² 22 against a band of [0.11, 3.4])
    # both say so.
    mut = {
        "turntable": [
            _score(
                "turntable",
                u,
                cache,
                mahony_kp_per_s=None,
                calibration=_mutated(_calibration(u, cache), drop=("scale",)),
            )
            for u in CONTRACT_UNITS
        ]
    }
    fails = _failures(mut)
    assert any(f.startswith("turntable:") for f in fails), fails


@pytest.mark.parametrize("scenario", ["turntable"])
def test_mutation_inflated_standard_errors_fail(results, cache, scenario):
    # every reported standard error × 3: the calibration claims a worse result than it has
    # (quality band; on the thermal run, whose order selection spreads predicted/floor over
    # units, the bound is ×1.55 and a ×3 inflation sits at it — docs/accuracy.md).
    mut = {
        scenario: [
            _score(
                scenario, u, cache, mahony_kp_per_s=None, calibration=_mutated(_calibration(u, cache), se_factor=3.0)
            )
            for u in CONTRACT_UNITS
        ]
    }
    fails = _failures(mut)
    assert any(f.startswith(f"{scenario}:") for f in fails), fails


def test_integration_reproduces_simulated_truth():
    # The scoring convention (hold="backward") integrates the simulator's true rate to its true
    # attitude: over 18 s of rate-table turns and re-poses the error stays at ~4e-9 rad
    # (2e-7 deg; the re-pose motion is not exactly a constant rate per step), four orders below
    # the smallest error scored (the floor, ≥ 1e-2 deg). The other convention is 1e-3 rad off.
    import warnings

    from gyrocore.attitude import error_angle_rad, integrate_gyro
    from sim.scenarios import simulate

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = simulate("turntable", sensor="icm42688p", seed=1, duration_s=20.0)
    q = integrate_gyro(r.truth.t_s, r.truth.omega_S_rad_s, q0_wxyz=r.truth.q_SW_wxyz[0])
    assert np.max(error_angle_rad(q, r.truth.q_SW_wxyz)) < 1e-7
    qf = integrate_gyro(r.truth.t_s, r.truth.omega_S_rad_s, q0_wxyz=r.truth.q_SW_wxyz[0], hold="forward")
    assert np.max(error_angle_rad(qf, r.truth.q_SW_wxyz)) > 1e-3


@pytest.mark.slow
def test_drift_contract_holds_for_fresh_units():
    """Fresh units (campaign seed 99, 4 units): the contract with its bands for 4 units holds,
    and every pays-off effect still pays off in each. False failure ≤ 19·α ≈ 2e-3."""
    camp = A.contract_campaign(instances=4, seed=99)
    by = {sc: [t.metrics_dict for t in camp.tasks if t.scenario == sc] for sc in A.SCENARIOS}
    fails = A.drift_contract_failures({sc: A.drift_statistics(v) for sc, v in by.items()}, DRIFT_THRESHOLDS)
    assert not fails, "; ".join(fails)
    for sc, ms in by.items():
        for m in ms:
            for eff in PAYS_OFF[sc]:
                assert m[f"all-but-{eff}__rms_deg"] > m["all__rms_deg"], (sc, eff)


@pytest.mark.slow
def test_mutation_wrong_thermal_order_fails(tmp_path, monkeypatch):
    """A unit whose thermal bias is quadratic (the preset plus σ = 0.0005 dps/°C² per axis: 0.11 dps of curvature over ±15 °C; all three axes below 0.2σ has probability 0.4 %), calibrated
    with the thermal order forced to 1: the thermal scenario's measured error leaves the band of
    what the calibration claims or its own standard errors blow up (quality: the wrong model
    leaves a structured residual). The same unit with the order chosen from the data keeps its
    honesty and completeness (first session: 0.37° measured vs 0.51° predicted)."""
    from sim.presets import PRESETS

    src = PRESETS[A.CONTRACT_SENSOR].read_text()
    assert "tol_dps_per_c = 0.005" in src
    toml = tmp_path / "icm42688p_quadratic.toml"
    toml.write_text(src.replace("tol_dps_per_c = 0.005", "tol_dps_per_c = 0.005\nsigma_dps_per_c2 = 0.0005"))
    sensor = str(toml)
    unit = CONTRACT_UNITS[0]

    def run(cache):
        from experiments.report import single_thread_blas

        with single_thread_blas():
            ab = A.ablate_instance(
                "thermal",
                sensor=sensor,
                seed=unit,
                duration_s=A.CONTRACT_DURATIONS_S["thermal"],
                quick=A.CONTRACT_QUICK_CALIBRATION,
                cache_dir=cache,
                mahony_kp_per_s=None,
            )
        return A.drift_contract_failures({"thermal": A.drift_statistics([A.instance_metrics(ab)])}, DRIFT_THRESHOLDS)

    # the unit is outside the Monte Carlo's population (the preset has no quadratic term): the
    # order chosen from the data (2) legitimately costs a little more than the population's
    # order-1 units (predicted/floor 1.43 against the population's 1.35, quality bound ×1.05
    # above it), so it is held to honesty and completeness — its prediction must describe its
    # error — not to the population's quality bound
    auto = run(str(tmp_path / "auto"))
    assert not [f for f in auto if "predicted/floor" not in f], auto
    monkeypatch.setitem(A._CAL_KW, "thermal_order", 1)
    fails = run(str(tmp_path / "order1"))
    assert any(f.startswith("thermal:") for f in fails), fails
