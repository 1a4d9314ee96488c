"""Thermal calibration: order chosen from the data, range/clamp warning, PX4 TC_G export."""

import numpy as np
import pytest

from gyrocore.effects import registry as E
from gyrocore.errors import GyroInputError, RepairWarning
from gyrocore.calibrator import Calibrator
from gyrocore.data.recording import Recording
from gyrocore.calib.thermal import px4_tc_params, write_px4_params

SIGMA_RAD_S = 0.003


def thermal_run(seed, poly, *, n=20000, rate_hz=50.0, t0_c=30.0):
    """Still sensor warming from 10 to 50 °C (first-order approach), bias = b + Σ c_k (T − t0)^k.

    White noise σ from an explicit Generator; the temperature is noise-free (a die sensor
    with 0.01 °C resolution would not change the design at this SNR)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    T = 10.0 + 40.0 * (1 - np.exp(-t / (0.4 * t[-1])))
    params = {
        "bias": {"b_rad_s": np.array([0.01, -0.005, 0.002])},
        "bias_thermal": {"poly_rad_s": np.asarray(poly, float), "t0_c": t0_c, "temp_min_c": -40.0, "temp_max_c": 85.0},
    }
    inp = E.ModelInputs(t_s=t, omega_S_rad_s=np.zeros((n, 3)), temp_c=T)
    y = E.deterministic(params, inp) + rng.normal(0, SIGMA_RAD_S, (n, 3))
    rec = Recording(t_s=t, gyro_rad_s=y, temp_c=T, ref_rate_rad_s=np.zeros((n, 3)))
    return rec, params


# Coefficients per axis for powers 1..3 of (T − 30 °C). The top-order coefficients are large
# against their standard error (σ / (sqrt(n)·sd of the k-th orthogonal power) ≈ 1e-8 for k = 3
# over ±20 °C), so the Wald test at α = 0.01 has power ≈ 1; a zero top order is rejected with
# probability ≤ α per test.
LINEAR = [[2e-4, 0, 0], [-1e-4, 0, 0], [5e-5, 0, 0]]
QUADRATIC = [[2e-4, 3e-6, 0], [-1e-4, -2e-6, 0], [5e-5, 1e-6, 0]]
CUBIC = [[2e-4, 3e-6, 2e-7], [-1e-4, -2e-6, -1e-7], [5e-5, 1e-6, 1e-7]]


@pytest.mark.parametrize("poly,order", [(LINEAR, 1), (QUADRATIC, 2), (CUBIC, 3)])
def test_order_is_chosen_from_the_data(poly, order):
    rec, params = thermal_run(1, poly)
    res = Calibrator(effects=["bias", "bias_thermal"]).fit(rec)
    assert res.thermal_order == {"bias_thermal": order}
    assert len(res.thermal_tests) == 3 - order + 1  # down from 3 until the first significant
    pd = res.params["bias_thermal"]
    assert pd["poly_rad_s"].shape == (3, order)
    assert float(pd["temp_min_c"]) == pytest.approx(rec.temp_c.min())
    assert float(pd["temp_max_c"]) == pytest.approx(rec.temp_c.max())
    # the fitted bias curve matches the true one within 4 σ of the fit at every temperature:
    # compare b̂ + polŷ(T − T0̂) with the truth on a grid (the fit re-centres on T0̂ = mean T)
    Tg = np.linspace(rec.temp_c.min(), rec.temp_c.max(), 9)
    inp = E.ModelInputs(t_s=np.arange(9.0), omega_S_rad_s=np.zeros((9, 3)), temp_c=Tg)
    fitted = E.deterministic({k: res.params[k] for k in ("bias", "bias_thermal")}, inp)
    truth = E.deterministic(params, inp)
    # σ of the fitted curve ≤ σ·sqrt((p+1)/n)·(max leverage factor ≈ 3 at the ends) ≈ 1.5e-4·σ
    assert np.all(np.abs(fitted - truth) < 4 * 3 * SIGMA_RAD_S * np.sqrt((order + 1) / rec.n))


def test_fixed_order_and_bad_order():
    rec, _ = thermal_run(2, QUADRATIC)
    res = Calibrator(effects=["bias", "bias_thermal"], thermal_order=3).fit(rec)
    assert res.thermal_order == {"bias_thermal": 3} and res.thermal_tests == ()
    with pytest.raises(GyroInputError, match="thermal order"):
        Calibrator(effects=["bias", "bias_thermal"], thermal_order=4)
    with pytest.raises(GyroInputError, match="temp_c"):
        Calibrator(effects=["bias", "bias_thermal"]).fit(
            Recording(t_s=rec.t_s, gyro_rad_s=rec.gyro_rad_s, ref_rate_rad_s=rec.ref_rate_rad_s)
        )


def test_apply_warns_outside_the_calibrated_range():
    rec, _ = thermal_run(3, LINEAR)
    res = Calibrator(effects=["bias", "bias_thermal"]).fit(rec)
    T = np.linspace(0.0, 60.0, 100)  # calibrated range ≈ 10..50 °C
    hot = Recording(t_s=np.arange(100) / 50.0, gyro_rad_s=np.zeros((100, 3)), temp_c=T)
    n_out = int(np.sum((T < res.params["bias_thermal"]["temp_min_c"]) | (T > res.params["bias_thermal"]["temp_max_c"])))
    with pytest.warns(RepairWarning, match=f"{n_out} of 100 samples"):
        out = res.apply(hot)
    # clamped: the correction beyond the range equals the correction at the range edge
    assert np.allclose(out.gyro_rad_s[0], out.gyro_rad_s[T <= res.params["bias_thermal"]["temp_min_c"]][-1])


def test_px4_export_reproduces_the_correction(tmp_path):
    rec, _ = thermal_run(4, CUBIC)
    res = Calibrator(effects=["bias", "bias_thermal"]).fit(rec)
    p = px4_tc_params(res.params, instance=1, device_id=123)
    assert p["TC_G1_TREF"] == pytest.approx(float(res.params["bias_thermal"]["t0_c"]))
    # PX4 (TemperatureCompensation::calc_thermal_offsets_3D): offset = X0 + X1 dT + X2 dT² + X3 dT³,
    # dT = clamp(T, TMIN, TMAX) − TREF, corrected = raw − offset. Must equal our correction.
    T = np.linspace(0.0, 60.0, 61)
    dT = np.clip(T, p["TC_G1_TMIN"], p["TC_G1_TMAX"]) - p["TC_G1_TREF"]
    off = np.stack([sum(p[f"TC_G1_X{k}_{i}"] * dT**k for k in range(4)) for i in range(3)], axis=1)
    raw = np.full((T.size, 3), 0.05)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RepairWarning)
        ours = res.apply(Recording(t_s=np.arange(T.size) / 50.0, gyro_rad_s=raw, temp_c=T)).gyro_rad_s
    np.testing.assert_allclose(raw - off, ours, atol=1e-12)
    f = tmp_path / "tc.params"
    write_px4_params(f, res.params, instance=1, device_id=123)
    rows = [ln.split("\t") for ln in f.read_text().splitlines() if not ln.startswith("#")]
    d = {r[2]: (float(r[3]), r[4]) for r in rows}
    assert d["TC_G1_ID"] == (123.0, "6") and d["TC_G_ENABLE"] == (1.0, "6")
    assert d["TC_G1_X3_2"][1] == "9" and d["TC_G1_X3_2"][0] == pytest.approx(p["TC_G1_X3_2"], rel=1e-8)
    with pytest.raises(GyroInputError, match="exists"):
        write_px4_params(f, res.params)
    with pytest.raises(GyroInputError, match="bias_thermal"):
        px4_tc_params({"bias": res.params["bias"]})
