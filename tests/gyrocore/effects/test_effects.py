"""The shared measurement model: forward vs formula, inverse, regressors."""

import numpy as np
import pytest

from gyrocore.effects import effect as EF
from gyrocore.effects import registry as E
from gyrocore.errors import GyroInputError


def _inputs(n=2000, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 200.0
    w = rng.normal(size=(n, 3))
    f = rng.normal(size=(n, 3)) * 9.8
    T = 20 + np.linspace(0, 10, n)
    return E.ModelInputs(t_s=t, omega_S_rad_s=w, f_S_m_s2=f, temp_c=T)


def test_scale_and_bias_follow_formula():
    inp = _inputs()
    p = {"bias": {"b_rad_s": [0.01, -0.02, 0.03]}, "scale": {"s": [0.01, -0.02, 0.005]}}
    y = E.deterministic(p, inp)
    expect = inp.omega_S_rad_s * (1 + np.array([0.01, -0.02, 0.005])) + np.array([0.01, -0.02, 0.03])
    np.testing.assert_allclose(y, expect, rtol=0, atol=1e-15)


def test_misalignment_and_g_sensitivity_formula():
    inp = _inputs()
    m = np.array([1e-3, 2e-3, -3e-3, 4e-3, -5e-3, 6e-3])
    H = np.arange(9).reshape(3, 3) * 1e-4
    y = E.deterministic({"misalignment": {"m_rad": m}, "g_sensitivity": {"h_rad_s_per_m_s2": H}}, inp)
    K = np.array([[1, m[0], m[1]], [m[2], 1, m[3]], [m[4], m[5], 1]])
    np.testing.assert_allclose(y, inp.omega_S_rad_s @ K.T + inp.f_S_m_s2 @ H.T, atol=1e-15)


def test_nonlinear_and_asymmetry_formula():
    inp = _inputs()
    w = inp.omega_S_rad_s
    y = E.deterministic(
        {"scale_asymmetry": {"a": [1e-3, 2e-3, 3e-3]}, "scale_nonlinearity": {"s2_s_per_rad": [1e-3, 0, -1e-3]}}, inp
    )
    expect = w + np.array([1e-3, 2e-3, 3e-3]) * np.abs(w) + np.array([1e-3, 0, -1e-3]) * w * np.abs(w)
    np.testing.assert_allclose(y, expect, atol=1e-15)


def test_correct_inverts_deterministic():
    inp = _inputs()
    p = {
        "bias": {"b_rad_s": [0.01, 0.02, -0.01]},
        "scale": {"s": [0.01, -0.02, 0.003]},
        "misalignment": {"m_rad": [0.001, 0.002, -0.003, 0.001, 0, 0.002]},
        "g_sensitivity": {"h_rad_s_per_m_s2": np.eye(3) * 1e-3},
        "scale_asymmetry": {"a": [0.001, 0.002, 0.003]},
        "bias_thermal": {"poly_rad_s": np.ones((3, 2)) * 1e-3, "t0_c": 25, "temp_min_c": 10, "temp_max_c": 40},
    }
    y = E.deterministic(p, inp)
    back = E.correct(p, y, E.ModelInputs(t_s=inp.t_s, f_S_m_s2=inp.f_S_m_s2, temp_c=inp.temp_c), iterations=8)
    # fixed-point contraction factor ~|a| = 3e-3 per iteration: 8 iterations -> < 1e-12 relative
    np.testing.assert_allclose(back, inp.omega_S_rad_s, atol=1e-12)


def test_design_matches_finite_difference():
    """A·θ equals deterministic(θ) − ω for effects linear in their parameters."""
    inp = _inputs(500)
    rng = np.random.default_rng(1)
    for eff in (
        "bias",
        "scale",
        "misalignment",
        "g_sensitivity",
        "g2_sensitivity",
        "scale_asymmetry",
        "scale_nonlinearity",
        "bias_ramp",
    ):
        names, A = E.design(eff, inp)
        theta = rng.normal(size=len(names)) * 1e-3
        pname = next(iter(E.PARAM_SCHEMA[eff]))
        shape = E.PARAM_SCHEMA[eff][pname]
        p = {eff: {pname: theta.reshape(shape)}}
        y = E.deterministic(p, inp)
        np.testing.assert_allclose(y - inp.omega_S_rad_s, A @ theta, atol=1e-12, err_msg=eff)


def test_article_form_round_trip():
    K = np.array([[1.02, 0.01, -0.003], [0.002, 0.98, 0.004], [-0.01, 0.003, 1.01]])
    M, s = E.article_from_k(K)
    np.testing.assert_allclose(np.diag(M), 1.0)
    np.testing.assert_allclose(E.k_from_article(M, s), K, atol=1e-14)


def test_unknown_effect_is_one_line_error():
    with pytest.raises(GyroInputError, match="unknown effect 'bogus'"):
        E.check_effect_names(["bias", "bogus"])


def test_earth_rate_magnitude_and_vertical_component():
    q = np.tile([1.0, 0, 0, 0], (10, 1))
    lat = np.deg2rad(49.0)
    w = E.earth_rate_S(lat, 0.3, q)
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), E.EARTH_RATE_RAD_S, rtol=1e-12)
    np.testing.assert_allclose(w[:, 2], E.EARTH_RATE_RAD_S * np.sin(lat), rtol=1e-12)


# ---------------------------------------------------------------- the registry
FAMILY_EXAMPLES = (
    "periodic[37.5]",
    "step[1.25]",
    "regressor[omega_y*omega_z]",
    "regressor[f_x^2]",
    "regressor[alpha_x]",
    "regressor[temp_c]",
    "regressor[dtemp_dt]",
    "regressor[t]",
    "regressor[omega_x*temp_c]",
)


def _smooth_inputs(n=1500, rate=200.0):
    """Smooth signals (np.gradient is exact to O(dt²) on them)."""
    t = np.arange(n) / rate
    w = np.stack(
        [np.sin(2 * np.pi * 0.3 * t), 0.7 * np.cos(2 * np.pi * 0.17 * t), 0.4 * np.sin(2 * np.pi * 0.11 * t + 1)], 1
    )
    f = np.array([0.5, -0.3, 9.8]) + np.stack([np.sin(0.5 * t), np.cos(0.3 * t), 0.2 * np.sin(0.2 * t)], 1)
    T = 25 + 5 * np.sin(2 * np.pi * 0.05 * t)
    return E.ModelInputs(t_s=t, omega_S_rad_s=w, f_S_m_s2=f, temp_c=T)


def test_registry_derives_the_old_tuples():
    assert E.EFFECTS == tuple(E.REGISTRY) and len(E.EFFECTS) == 21
    assert E.STOCHASTIC == ("arw", "bias_instability", "rrw", "correlated")
    assert set(E.DETERMINISTIC) == set(E.EFFECTS) - set(E.STOCHASTIC) - {"vibration"}
    assert set(E.CORRECTABLE) == set(E.DETERMINISTIC) - {"quantization", "saturation", "lowpass"}
    for name, eff in E.REGISTRY.items():
        assert eff.name == name and E.resolve(name) is eff and E.PARAM_SCHEMA[name] == dict(eff.schema)
        assert eff.kind in EF.KINDS and (eff.stage in EF.STAGES or eff.kind in ("stochastic", "physics"))
        assert set(eff.inputs) <= set(EF.INPUTS)
    # fittable = the catalogue effects with regressors (earth_rate has none)
    assert [e for e in E.CORRECTABLE if E.resolve(e).fittable] == [e for e in E.CORRECTABLE if e != "earth_rate"]


@pytest.mark.parametrize("name", FAMILY_EXAMPLES)
def test_family_round_trip(name):
    """resolve -> canonical name -> resolve is the same effect; schema/design/forward/inverse agree."""
    eff = E.resolve(name)
    assert eff.name == name and E.resolve(eff.name) is eff and eff.family == name.split("[")[0]
    assert name in E.PARAM_SCHEMA and E.PARAM_SCHEMA[name] == dict(eff.schema)
    assert name not in E.EFFECTS  # the catalogue tuple is unchanged
    inp = _smooth_inputs()
    names, A = E.design(name, inp)
    rng = np.random.default_rng(4)
    theta = rng.normal(size=len(names)) * 1e-3
    p = {name: eff.unflatten(theta)}
    assert E.validate_params(p).keys() == {name}
    y = E.deterministic(p, inp)
    # linear in θ and no other stage: A·θ is the term exactly (to rounding)
    np.testing.assert_allclose(y - inp.omega_S_rad_s, A @ theta, rtol=0, atol=1e-12)
    # the inverse removes it; rate-dependent terms by fixed-point iteration (contraction
    # |∂term/∂ω| ≲ 1e-3·|ω| per step: 8 steps -> < 1e-15 relative)
    back = E.correct(p, y, E.ModelInputs(t_s=inp.t_s, f_S_m_s2=inp.f_S_m_s2, temp_c=inp.temp_c), iterations=8)
    if "alpha" in eff.inputs:
        # the inverse differentiates the estimate with a quadratic Savitzky-Golay filter over
        # +-m samples, the forward with central differences: on a smooth rate both are exact to
        # O(m^2 dt^2 max|d3w/dt3|) (Taylor remainder); ends (one-sided differences) excluded
        dt = float(inp.t_s[1] - inp.t_s[0])
        m = max(2, round(E.ALPHA_HALF_WINDOW_S / dt))
        w3 = np.max(
            np.abs(np.gradient(np.gradient(np.gradient(inp.omega_S_rad_s, dt, axis=0), dt, axis=0), dt, axis=0))
        )
        bound = np.max(np.abs(theta)) * m**2 * dt**2 * w3
        assert np.max(np.abs(back - inp.omega_S_rad_s)[m + 1 : -m - 1]) < bound
    else:
        np.testing.assert_allclose(back, inp.omega_S_rad_s, rtol=0, atol=1e-12)


def test_family_with_catalogue_effects_inverts():
    inp = _smooth_inputs()
    p = {
        "bias": {"b_rad_s": [0.01, 0.02, -0.01]},
        "scale": {"s": [0.01, -0.02, 0.003]},
        "scale_nonlinearity": {"s2_s_per_rad": [1e-3, 0, -2e-3]},
        "time_offset": {"tau_s": 0.004},
        "periodic[2.5]": {"a_cos_rad_s": [1e-3, 0, 0], "a_sin_rad_s": [0, -2e-3, 0]},
        "regressor[omega_y*omega_z]": {"coef": [3e-3, 0, -1e-3]},
        "step[3]": {"size_rad_s": [0, 0, 5e-3]},
    }
    y = E.deterministic(p, inp)
    back = E.correct(p, y, E.ModelInputs(t_s=inp.t_s), iterations=10)
    # time_offset is applied and undone by linear interpolation: each costs at most dt²/8·max|ω''|
    # (linear-interpolation error bound), so two cost dt²/4·max|ω''| per axis (edges held: inside only)
    dt = float(inp.t_s[1] - inp.t_s[0])
    w2 = np.gradient(np.gradient(inp.omega_S_rad_s, inp.t_s, axis=0), inp.t_s, axis=0)
    bound = dt**2 / 4 * np.abs(w2).max(axis=0) * 1.05  # 5 %: the K, s2 and family terms scale ω by < 1 %
    assert np.all(np.abs(back - inp.omega_S_rad_s)[5:-5].max(axis=0) < bound)
    no_delay = {k: v for k, v in p.items() if k != "time_offset"}
    back = E.correct(no_delay, E.deterministic(no_delay, inp), E.ModelInputs(t_s=inp.t_s), iterations=10)
    np.testing.assert_allclose(back, inp.omega_S_rad_s, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "given, canonical",
    [
        ("periodic[37.50]", "periodic[37.5]"),
        ("periodic[ 50 ]", "periodic[50]"),
        ("periodic[5e1]", "periodic[50]"),
        ("periodic[0.001]", "periodic[0.001]"),
        ("step[12.250]", "step[12.25]"),
        ("step[-0.0]", "step[0]"),
        ("step[+3]", "step[3]"),
        ("regressor[omega_z*omega_y]", "regressor[omega_y*omega_z]"),
        ("regressor[omega_x*omega_x]", "regressor[omega_x^2]"),
        ("regressor[ f_x ^ 2 ]", "regressor[f_x^2]"),
        ("regressor[temp_c*omega_x]", "regressor[omega_x*temp_c]"),
        ("regressor[t^1]", "regressor[t]"),
        ("regressor[omega_x*omega_x*f_y]", "regressor[omega_x^2*f_y]"),
    ],
)
def test_names_are_canonical(given, canonical):
    assert E.canonical_name(given) == canonical
    assert E.check_effect_names([given, "bias"]) == [canonical, "bias"]
    assert E.validate_params({given: E.resolve(canonical).defaults}).keys() == {canonical}


@pytest.mark.parametrize(
    "bad, msg",
    [
        ("periodic[abc]", "decimal number"),
        ("periodic[-2]", "> 0 Hz"),
        ("periodic[0]", "> 0 Hz"),
        ("periodic[nan]", "decimal number"),
        ("periodic[inf]", "decimal number"),
        ("step[]", "decimal number"),
        ("step[1e999]", "finite"),
        ("regressor[]", "product of signals"),
        ("regressor[omega_w]", "unknown signal 'omega_w'"),
        ("regressor[omega_x+1]", "cannot read"),
        ("regressor[omega_x^4]", "degree 4"),
        ("regressor[omega_x^0]", "cannot read|>= 1"),
        ("regressor[omega_x**2]", "product of signals"),
        ("regressor[2*omega_x]", "cannot read"),
        ("regressor[omega_x*omega_x*omega_x*omega_x]", "degree 4"),
        ("wobble[3]", "unknown effect 'wobble\\[3\\]'"),
        ("periodic37.5", "unknown effect"),
    ],
)
def test_bad_family_names_are_one_line_errors(bad, msg):
    with pytest.raises(GyroInputError, match=msg) as ei:
        E.resolve(bad)
    assert "\n" not in str(ei.value) and bad.strip()[:8] in str(ei.value)


def test_family_name_and_canonical_expr():
    assert E.family_name("periodic", 37.5) == "periodic[37.5]"
    assert E.family_name("periodic", 1e-7) == "periodic[0.0000001]"  # never an exponent
    assert E.family_name("step", 12.0) == "step[12]"
    assert E.family_name("step", -0.0) == "step[0]"
    assert E.family_name("regressor", "omega_z*omega_y") == "regressor[omega_y*omega_z]"
    f = 0.1 + 0.2  # a frequency that is not a short decimal reads back to the same float
    assert E.resolve(E.family_name("periodic", f)).arg == f
    assert E.canonical_expr("f_x*f_x") == "f_x^2" and E.canonical_expr(" t ") == "t"
    with pytest.raises(GyroInputError, match="unknown signal"):
        E.canonical_expr("omega_q")
    with pytest.raises(GyroInputError, match="> 0 Hz"):
        E.family_name("periodic", -1.0)


def test_expr_values_are_the_regressor_signal():
    """expr_values is the signal g of regressor[expr]: its design has g on the diagonal; a
    cache shared across expressions gives the same values; a single sample's derivatives are 0."""
    inp = _inputs()
    cache: dict = {}
    for expr in ("omega_y*omega_z", "f_x^2", "alpha_z", "temp_c*omega_x", "dtemp_dt", "t", "omega_x^2*f_y"):
        g = E.expr_values(expr, inp, cache=cache)
        _, A = E.design(f"regressor[{expr}]", inp)
        for i in range(3):
            np.testing.assert_array_equal(A[:, i, i], g)
        np.testing.assert_array_equal(E.expr_values(expr, inp), g)
    assert {"omega_y", "omega_z", "f_x", "alpha_z"} <= set(cache)
    np.testing.assert_array_equal(E.expr_values("alpha_x", inp), np.gradient(inp.omega_S_rad_s[:, 0], inp.t_s))
    one = E.ModelInputs(t_s=np.array([0.0]), omega_S_rad_s=np.ones((1, 3)), temp_c=np.array([20.0]))
    assert E.expr_values("alpha_x", one).tolist() == [0.0] and E.expr_values("dtemp_dt", one).tolist() == [0.0]
    with pytest.raises(GyroInputError, match="accel"):
        E.expr_values("f_x", E.ModelInputs(t_s=inp.t_s))


def test_twice_under_two_spellings_is_an_error():
    with pytest.raises(GyroInputError, match="given twice"):
        E.validate_params({"step[1]": {"size_rad_s": np.zeros(3)}, "step[1.0]": {"size_rad_s": np.zeros(3)}})


@pytest.mark.parametrize(
    "term, axis, expect",
    [
        ("omega_x", "x", "scale"),
        ("regressor[omega_x]", 0, "scale"),
        ("omega_y", "x", "misalignment"),
        ("alpha_z", "z", None),
        ("alpha_z", "x", None),
        ("f_y", "x", "g_sensitivity"),
        ("regressor[f_y]", "z", "g_sensitivity"),
        ("f_x*f_z", "y", "g2_sensitivity"),
        ("f_y^2", "y", "g2_sensitivity"),
        ("t", "y", "bias_ramp"),
        ("dtemp_dt", "x", "bias_temp_rate"),
        ("temp_c", "z", "bias_thermal"),
        ("temp_c^2", "z", "bias_thermal"),
        ("temp_c^3", "x", "bias_thermal"),
        ("omega_x*temp_c", "x", "scale_thermal"),
        ("omega_x*temp_c", "y", None),
        ("omega_x*omega_x", "x", None),
        ("omega_y*omega_z", "x", None),
        ("f_x*omega_x", "x", None),
        ("periodic[37.5]", "x", None),
        ("step[2]", "y", None),
        ("t*temp_c", "x", None),
        ("f_x^2*f_y", "x", None),
    ],
)
def test_catalogue_equivalent(term, axis, expect):
    assert E.catalogue_equivalent(term, axis) == expect


def _in_span(y, cols):
    """Residual of projecting y (N·3,) on the columns (N·3, P), relative to |y|."""
    coef, *_ = np.linalg.lstsq(cols, y, rcond=None)
    return np.max(np.abs(cols @ coef - y)) / np.max(np.abs(y))


def test_catalogue_equivalent_is_the_catalogue_regressor():
    """A term mapped to a catalogue effect is, as a column on all three axes (the term on its
    axis, 0 on the others), in the span of that effect's design (+ its constant companion):
    reporting it again would double count. A term mapped to None is not."""
    inp = _smooth_inputs()
    for term in (
        "omega_x",
        "omega_z",
        "alpha_x",
        "f_y",
        "f_x*f_z",
        "t",
        "dtemp_dt",
        "temp_c",
        "temp_c^2",
        "omega_x*temp_c",
        "omega_x^2",
        "omega_y*omega_z",
    ):
        _, g = E.design(f"regressor[{term}]", inp)
        for i in range(3):
            y = g[:, :, i].ravel()  # coef[i] column: the signal on axis i, 0 elsewhere
            cat = E.catalogue_equivalent(term, i)
            names = [cat] if cat else ["scale", "misalignment", "time_offset", "scale_nonlinearity", "scale_asymmetry"]
            blocks = [E.design("bias", inp)[1]]
            for c in names:
                blocks.append(E.design(c, inp, order=3 if c in ("bias_thermal", "scale_thermal") else 1)[1])
            if cat == "scale_thermal":
                blocks.append(E.design("scale", inp)[1])
            cols = np.concatenate(blocks, axis=2).reshape(-1, sum(b.shape[2] for b in blocks))
            rel = _in_span(y, cols)
            if cat:
                assert rel < 1e-8, (term, i, cat, rel)
            else:  # not spanned by the rate-dependent catalogue effects either
                assert rel > 1e-3, (term, i, rel)


def test_parameter_schema_view_still_a_dict_of_the_catalogue():
    assert list(E.PARAM_SCHEMA) == list(E.EFFECTS)
    assert "periodic[3]" in E.PARAM_SCHEMA and "nope" not in E.PARAM_SCHEMA and "periodic[x]" not in E.PARAM_SCHEMA
    assert E.PARAM_SCHEMA.get("nope") is None
    with pytest.raises(KeyError):
        E.PARAM_SCHEMA["nope"]


@pytest.mark.parametrize("name", [e for e in E.CORRECTABLE])
def test_catalogue_registry_round_trip(name):
    """Every correctable catalogue effect: resolve/schema/validate round trip, forward minus its
    regressors is second order in θ (design is ∂y/∂θ at zero error), and correct inverts it."""
    eff = E.resolve(name)
    assert eff.name == name and eff.correctable and E.canonical_name(name) == name
    inp = _smooth_inputs()
    inp = E.ModelInputs(
        t_s=inp.t_s,
        omega_S_rad_s=inp.omega_S_rad_s,
        f_S_m_s2=inp.f_S_m_s2,
        temp_c=inp.temp_c,
        q_SW_wxyz=np.tile([0.9, 0.1, -0.3, 0.2], (inp.n, 1)),
    )
    rng = np.random.default_rng(5)
    if eff.fittable:
        order = 2 if eff.polynomial else 1
        cols, A = E.design(name, inp, order=order)
        theta = rng.normal(size=len(cols)) * (1e-4 if name != "time_offset" else 1e-3)
        pd = eff.unflatten(theta, order)
        if eff.polynomial:
            pd.update(
                t0_c=np.asarray(float(np.mean(inp.temp_c))), temp_min_c=np.asarray(-50.0), temp_max_c=np.asarray(150.0)
            )
    else:  # earth_rate: no regressors (a known input, not fitted)
        pd = {"latitude_rad": np.asarray(0.8), "heading_rad": np.asarray(0.3)}
    p = {name: pd}
    assert set(E.validate_params(p)[name]) == set(eff.schema)
    y = E.deterministic(p, inp)
    sl = slice(3, -3) if name == "time_offset" else slice(None)  # the shift holds the edge values
    if eff.fittable:
        # linear-in-θ effects exactly; time_offset's shift is linear to O(τ²·|ω''|) ≤ 1e-6·4: 1e-5
        np.testing.assert_allclose(
            (y - inp.omega_S_rad_s)[sl], (A @ theta)[sl], rtol=0, atol=1e-5 if name == "time_offset" else 1e-12
        )
    back = E.correct(
        p,
        y,
        E.ModelInputs(t_s=inp.t_s, f_S_m_s2=inp.f_S_m_s2, temp_c=inp.temp_c, q_SW_wxyz=inp.q_SW_wxyz),
        iterations=8,
    )
    # time_offset: two linear interpolations at dt = 5 ms, dt²/4·max|ω''| ≤ 2.5e-5 (see above)
    np.testing.assert_allclose(back[sl], inp.omega_S_rad_s[sl], rtol=0, atol=2.5e-5 if name == "time_offset" else 1e-12)
