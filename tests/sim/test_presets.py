"""Sensor presets: every file loads, conversions to SI are right, every value cites a source,
instances are drawn reproducibly from the stated distributions."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from gyrocore.effects.registry import PARAM_SCHEMA, validate_params
from gyrocore.errors import GyroInputError
from sim.presets import NL_MINIMAX_FACTOR, PRESETS, TOL_SIGMAS, SensorSpec, load_preset

DEG = math.pi / 180
REQUIRED = {"mpu6050", "icm20602", "icm42688p", "bmi088", "adis16448"}


def test_registry_has_the_required_parts():
    assert REQUIRED <= set(PRESETS)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_preset_loads_and_draws_valid_instance(name):
    spec = load_preset(name)
    assert isinstance(spec, SensorSpec) and spec.name == name
    assert spec.datasheet and spec.rate_hz > 0 and spec.full_scale_rad_s > 0 and spec.lsb_rad_s > 0
    for eff in ("bias", "scale", "misalignment", "arw", "bias_instability", "quantization", "saturation", "lowpass"):
        assert eff in spec.effects, eff
    p = spec.draw_instance(0)
    validate_params(p)
    assert set(p) == set(spec.effects)
    assert np.array_equal(p["bias"]["b_rad_s"], spec.draw_instance(0)["bias"]["b_rad_s"])
    assert not np.array_equal(p["bias"]["b_rad_s"], spec.draw_instance(1)["bias"]["b_rad_s"])
    assert float(p["lowpass"]["bandwidth_hz"]) < spec.rate_hz / 2


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_value_has_a_source_comment(name):
    text = PRESETS[name].read_text(encoding="utf-8")
    for line in text.splitlines():
        if re.match(r"^[a-z_0-9]+\s*=\s*[-0-9.]", line):
            assert "#" in line, f"{name}: value without a source comment: {line!r}"


def test_conversions_to_si():
    icm = load_preset("icm42688p")
    # 0.0028 dps/√Hz -> rad/√s
    assert icm.effects["arw"]["n_rad_per_sqrt_s"] == pytest.approx(0.0028 * DEG)
    # ±0.5 dps initial ZRO tolerance read as ±3σ
    assert icm.effects["bias"]["b_sigma_rad_s"] == pytest.approx(0.5 / TOL_SIGMAS * DEG)
    assert icm.lsb_rad_s == pytest.approx(DEG / 16.4)
    assert icm.effects["quantization"]["lsb_rad_s"] == pytest.approx(DEG / 16.4)
    assert icm.effects["saturation"]["range_rad_s"] == pytest.approx(2000 * DEG)
    # ±0.005 %/°C scale tempco -> 1/°C
    assert icm.effects["scale_thermal"]["c1_sigma_per_c"] == pytest.approx(0.005e-2 / TOL_SIGMAS)
    adis = load_preset("adis16448")
    # ARW 0.66 °/√h = 0.66·(π/180)/√3600 rad/√s
    assert adis.effects["arw"]["n_rad_per_sqrt_s"] == pytest.approx(0.66 * DEG / math.sqrt(3600))
    # in-run bias stability 14.5 °/h is the Allan floor = B·sqrt(2 ln2/π)
    B = adis.effects["bias_instability"]["b_rad_s"]
    assert B * math.sqrt(2 * math.log(2) / math.pi) == pytest.approx(14.5 * DEG / 3600)
    # misalignment 0.05° (1σ)
    assert adis.effects["misalignment"]["m_sigma_rad"] == pytest.approx(0.05 * DEG)
    mpu = load_preset("mpu6050")
    # 0.1 °/s/g -> rad/s per m/s²
    assert mpu.effects["g_sensitivity"]["h_sigma_rad_s_per_m_s2"] == pytest.approx(0.1 * DEG / 9.80665)
    # RRW °/h/√h -> rad/s/√s
    assert mpu.disabled["rrw"]["k_rad_s_per_sqrt_s"] == pytest.approx(30 * DEG / 3600 / 60)


def test_nonlinearity_minimax_factor():
    # brute force: max |ω|ω| − cω| over [0, F] minimised over c equals (3 − 2√2)·F² (F = 1)
    from scipy.optimize import minimize_scalar

    w = np.linspace(0, 1, 200001)  # grid error on the smooth interior maximum is O(h²) ~ 1e-11

    def dev(c):
        return np.max(np.abs(w**2 - c * w))

    res = minimize_scalar(dev, bounds=(0.5, 1.0), method="bounded", options={"xatol": 1e-12})
    assert res.fun == pytest.approx(NL_MINIMAX_FACTOR, rel=1e-6)
    icm = load_preset("icm42688p")
    s2 = icm.effects["scale_nonlinearity"]["s2_sigma_s_per_rad"]
    assert s2 * NL_MINIMAX_FACTOR * icm.full_scale_rad_s == pytest.approx(0.1e-2 / TOL_SIGMAS)


def test_population_matches_distribution():
    # over 400 units the drawn scale errors have std σ: s.e. of a std ≈ σ/√(2·1200) (3 axes
    # pooled) = 2 %; 5 s.e. = 10 %
    spec = load_preset("bmi088")
    s = np.array([spec.draw_effect("scale", seed)["s"] for seed in range(400)]).ravel()
    sigma = spec.effects["scale"]["s_sigma"]
    assert s.std() == pytest.approx(sigma, rel=5 / math.sqrt(2 * s.size))
    assert abs(s.mean()) < 5 * sigma / math.sqrt(s.size)


def test_include_switches_on_disabled_effect_without_changing_others():
    spec = load_preset("icm42688p")
    a = spec.draw_instance(3)
    b = spec.draw_instance(3, include=["rrw", "bias_temp_rate"])
    assert "rrw" in b and "rrw" not in a
    for eff in a:
        for k in a[eff]:
            assert np.array_equal(a[eff][k], b[eff][k])
    assert set(PARAM_SCHEMA["rrw"]) <= set(b["rrw"])


def test_load_from_path_and_errors(tmp_path):
    p = tmp_path / "mine.toml"
    p.write_text(
        PRESETS["bmi088"].read_text(encoding="utf-8").replace('name = "bmi088"', 'name = "mine"'), encoding="utf-8"
    )
    assert load_preset(str(p)).name == "mine"
    with pytest.raises(GyroInputError, match="unknown sensor preset"):
        load_preset("nope")
    bad = tmp_path / "bad.toml"
    bad.write_text(
        "[output]\nrate_hz = 100\nfull_scale_dps = 250\nsensitivity_lsb_per_dps = 131\n[warp]\nx = 1\n",
        encoding="utf-8",
    )
    with pytest.raises(GyroInputError, match="unknown effect section"):
        load_preset(str(bad))
    bad.write_text(
        "[output]\nrate_hz = 100\nfull_scale_dps = 250\nsensitivity_lsb_per_dps = 131\n[arw]\nfoo_dps = 1\n",
        encoding="utf-8",
    )
    with pytest.raises(GyroInputError, match="unknown key"):
        load_preset(str(bad))
    bad.write_text("[output]\nrate_hz = 100\n", encoding="utf-8")
    with pytest.raises(GyroInputError, match="full_scale_dps"):
        load_preset(str(bad))
    bad.write_text("not toml [", encoding="utf-8")
    with pytest.raises(GyroInputError, match="not valid TOML"):
        load_preset(str(bad))
