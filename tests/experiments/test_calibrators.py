"""The calibrator door (experiments.calibrators): the core through it, truth stripping, entries."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from experiments import ablation as A
from experiments import calibrators as C
from gyrocore.effects import registry as E
from gyrocore.errors import GyroInputError


#: Calibration-run durations of the pin (table, thermal), s: short, the same in both paths.
CAL_S = (40.0, 60.0)


def _old_calibration(sensor, seed, present):
    """The ablation's calibration path before the calibrator door, verbatim, on un-stripped runs."""
    from gyrocore.calibrator import Calibrator
    from sim import scenarios as S

    tt = [e for e in A.TABLE_EFFECTS if e in present]
    th = [e for e in A.THERMAL_EFFECTS if e in present]
    stages = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = S.simulate("turntable", sensor=sensor, seed=seed, run=1, duration_s=CAL_S[0])
        r1 = Calibrator(effects=["bias"] + [e for e in tt if e != "bias"], **A._CAL_KW).fit(cal.recording)
        stages.append(A._stage_from(r1, 1))
        rec2 = S.simulate("thermal", sensor=sensor, seed=seed, run=2, duration_s=CAL_S[1]).recording
        inp2 = E.ModelInputs(t_s=rec2.t_s, f_S_m_s2=rec2.accel_m_s2, temp_c=rec2.temp_c)
        p1 = {eff: pd for _, (eff, pd, _) in A._as_stages(stages[0])[0].items() if eff != "bias"}
        rec2 = rec2.with_gyro(E.correct(p1, rec2.gyro_rad_s, inp2))
        eff2 = ["bias"] + (["scale"] if "scale_thermal" in th else []) + th
        eff2 += [e for e in A.THERMAL_NUISANCE if e not in eff2]  # the filter delay as a nuisance
        stages.append(A._stage_from(Calibrator(effects=eff2, **A._CAL_KW).fit(rec2), 2))
    return stages


SEED = 5


@pytest.fixture(scope="module")
def calibrations():
    """The unit's calibration by the old path and through the door (the same unit in both scenarios)."""
    from experiments import ablation as A
    from sim.presets import load_preset

    present = [e for e in E.CORRECTABLE if e in load_preset("icm42688p").effects]
    return (
        present,
        _old_calibration("icm42688p", SEED, present),
        A.calibrate_core("icm42688p", SEED, present, durations_s=CAL_S),
    )


@pytest.mark.parametrize("scenario,duration_s", [("static", 20.0), ("power_cycles", 30.0)])
def test_core_through_the_door_is_bit_identical_to_the_old_ablation(scenario, duration_s, calibrations):
    """Same numbers as the ablation before the door: the fit (on truth-stripped runs) and the
    'all' row (applied to the truth-stripped scored recording, datasheet gate σ) match the old
    path (truth-bearing inputs, σ from params_true) bit for bit."""
    from sim import scenarios as S

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = S.simulate(scenario, sensor="icm42688p", duration_s=duration_s, seed=SEED, run=0)
    rec, truth, p_true = res.recording, res.truth, res.params_true
    present, old_stages, new = calibrations
    assert A.present_effects(p_true) == present
    for so, sn in zip(old_stages, new.stages):
        assert so.keys() == sn.keys()
        for k in so:
            for name in so[k]:
                np.testing.assert_array_equal(so[k][name], sn[k][name])
    inp = E.ModelInputs(
        t_s=rec.t_s,
        f_S_m_s2=rec.accel_m_s2,
        temp_c=rec.temp_c,
        q_SW_wxyz=truth.q_SW_wxyz,
        t_since_power_up_s=truth.t_since_power_up_s,
    )
    still = A.powerup_windows(rec, p_true, bias_bound_rad_s=A.bias_bound_rad_s("icm42688p"))
    w_old = A.corrected_gyro(rec.gyro_rad_s, inp, old_stages, present, still)
    stripped = C.strip_truth(rec, references=False)
    w_new = C.CoreCalibrator(effects=present).apply(stripped, new)
    np.testing.assert_array_equal(w_old, w_new)
    # and the ablation's 'all' row is that gyro
    ab = A.ablate_instance(
        scenario,
        seed=SEED,
        duration_s=duration_s,
        quick=True,
        calibration=old_stages,
        mahony_kp_per_s=None,
        predict=False,
    )
    start = int(still[0][1].stop)
    sc = A.score_variants(rec.t_s, truth.q_SW_wxyz, {"all": w_old}, start=start)["all"][0]
    assert ab.scores["all"].rms_error_deg == sc.rms_error_deg
    assert ab.scores["all"].final_error_deg == sc.final_error_deg


def test_strip_truth_keeps_references_only_for_calibration_runs():
    from sim import scenarios as S

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = S.simulate("static", sensor="icm42688p", duration_s=3.0, seed=1).recording
    assert "params_true" in rec.meta and rec.ref_rate_rad_s is not None
    s = C.strip_truth(rec, references=False)
    assert s.ref_rate_rad_s is None and s.ref_quat_wxyz is None
    assert set(s.meta) <= set(C.TRUTH_FREE_META)
    for k in ("params_true", "seed", "truth_seed", "effects", "run"):
        assert k not in s.meta
    np.testing.assert_array_equal(s.gyro_rad_s, rec.gyro_rad_s)
    c = C.strip_truth(rec, references=True)
    np.testing.assert_array_equal(c.ref_rate_rad_s, rec.ref_rate_rad_s)
    assert "params_true" not in c.meta


def test_datasheet_gate_noise_equals_the_units_noise():
    """The core's power-up gate reads σ from the datasheet: noise is the same in every unit."""
    from sim import scenarios as S

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p_true = S.simulate("static", sensor="icm42688p", duration_s=3.0, seed=2).params_true
    d = C.datasheet_noise_params("icm42688p")
    np.testing.assert_array_equal(d["arw"]["n_rad_per_sqrt_s"], p_true["arw"]["n_rad_per_sqrt_s"])
    assert float(d["quantization"]["lsb_rad_s"]) == float(p_true["quantization"]["lsb_rad_s"])


def test_load_calibrator_registered_and_errors():
    for name in C.REGISTRY:
        obj = C.load_calibrator(name)
        assert isinstance(obj, C.CalibrationRoutine)
    assert isinstance(C.load_calibrator("experiments.calibrators:PX4Calibrator"), C.PX4Calibrator)
    for bad in ("nope", "no_such_module_xyz:f", "experiments.calibrators:nothing", "experiments.calibrators:DEG"):
        with pytest.raises(GyroInputError):
            C.load_calibrator(bad)
