"""The synthetic gyro: reproducibility, each effect against its formula (written out here,
not taken from gyrocore.effects.registry), independent per-effect streams, stream == batch."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gyrocore.effects.registry import EFFECTS, EARTH_RATE_RAD_S
from gyrocore.errors import GyroInputError
from sim.gyro import SyntheticGyro
from sim.truth import Truth

RATE = 1000.0
ALL_BUT_VIB = [e for e in EFFECTS if e != "vibration"]


def make_truth(n=2000, rate=RATE, *, seed=0, power_ups=None, omega=None, temp=None, q=None) -> Truth:
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    if omega is None:
        omega = 0.5 * np.sin(2 * np.pi * 1.3 * t)[:, None] * np.array([1.0, -2.0, 0.7]) + rng.normal(0, 0.3, (n, 3))
    f = np.array([0.3, -0.2, 9.81]) + rng.normal(0, 0.5, (n, 3))
    if q is None:
        q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    if temp is None:
        temp = 20.0 + 0.02 * t * rate / 10 + 3 * np.sin(t)
    pu = np.zeros(n, int) if power_ups is None else np.asarray(power_ups)
    since = t.copy()
    for k in np.unique(pu):
        m = pu == k
        since[m] = t[m] - t[m][0]
    return Truth(
        t_s=t, omega_S_rad_s=omega, f_S_m_s2=f, q_SW_wxyz=q, temp_c=temp, t_since_power_up_s=since, power_up_index=pu
    )


def only(effect, values=None, *, seed=1, rate=RATE, spec="icm42688p"):
    """A gyro with exactly one effect (given values, or the preset's draw)."""
    ov = {effect: values} if values is not None else {effect: {}}
    return SyntheticGyro(spec, rate_hz=rate, seed=seed, without=[e for e in ALL_BUT_VIB if e != effect], overrides=ov)


def test_same_seed_bit_identical_different_seed_differs():
    tr = make_truth()
    a = SyntheticGyro("icm42688p", rate_hz=RATE, seed=7).measure(tr)
    b = SyntheticGyro("icm42688p", rate_hz=RATE, seed=7).measure(tr)
    c = SyntheticGyro("icm42688p", rate_hz=RATE, seed=8).measure(tr)
    assert np.array_equal(a.gyro_rad_s, b.gyro_rad_s)
    assert not np.array_equal(a.gyro_rad_s, c.gyro_rad_s)


def test_no_effects_is_the_truth():
    tr = make_truth()
    g = SyntheticGyro("icm42688p", rate_hz=RATE, seed=1, without=ALL_BUT_VIB)
    assert g.effects == ()
    assert np.array_equal(g.measure(tr).gyro_rad_s, tr.omega_S_rad_s)


# ---------------------------------------------------------------- each effect vs its formula
RTOL = 1e-12  # same formula evaluated in a different operation order: a few ulp


def _y(effect, values, tr, **kw):
    return only(effect, values, **kw).measure(tr).gyro_rad_s


def test_bias():
    tr = make_truth()
    b = np.array([0.01, -0.02, 0.005])
    y = _y("bias", {"b_rad_s": b, "turn_on_sigma_rad_s": 0.0}, tr)
    assert np.allclose(y, tr.omega_S_rad_s + b, rtol=RTOL, atol=1e-15)


def test_bias_thermal_polynomial_clamped():
    tr = make_truth(temp=np.linspace(-50, 100, 2000))
    c = np.array([[1e-3, 1e-5], [-2e-3, 0.0], [5e-4, -1e-5]])
    y = _y("bias_thermal", {"poly_rad_s": c, "t0_c": 25.0, "temp_min_c": -40.0, "temp_max_c": 85.0}, tr)
    dT = np.clip(tr.temp_c, -40, 85) - 25.0
    expect = tr.omega_S_rad_s + dT[:, None] * c[:, 0] + dT[:, None] ** 2 * c[:, 1]
    assert np.allclose(y, expect, rtol=RTOL, atol=1e-15)


def test_bias_temp_rate():
    # linear temperature ramp: dT/dt = 0.5 °C/s exactly, whatever the difference scheme
    n = 2000
    tr = make_truth(n, temp=20.0 + 0.5 * np.arange(n) / RATE)
    k = np.array([1e-3, -2e-3, 3e-3])
    y = _y("bias_temp_rate", {"k_rad_s_per_c_per_s": k}, tr)
    assert np.allclose(y, tr.omega_S_rad_s + 0.5 * k, rtol=1e-9, atol=1e-15)


def test_bias_ramp_restarts_at_power_up():
    pu = np.repeat([0, 1], 1000)
    tr = make_truth(power_ups=pu)
    r = np.array([1e-4, -1e-4, 2e-4])
    y = _y("bias_ramp", {"ramp_rad_s2": r}, tr)
    t = tr.t_s
    since = np.where(pu == 0, t - t[0], t - t[1000])
    assert np.allclose(y, tr.omega_S_rad_s + since[:, None] * r, rtol=RTOL, atol=1e-15)


def test_scale():
    tr = make_truth()
    s = np.array([0.01, -0.02, 0.03])
    assert np.allclose(_y("scale", {"s": s}, tr), tr.omega_S_rad_s * (1 + s), rtol=RTOL)


def test_scale_thermal():
    tr = make_truth()
    c = np.array([1e-3, 2e-3, -1e-3])  # order 1 given as 3 values
    y = _y("scale_thermal", {"poly_per_c": c, "t0_c": 25.0}, tr)
    dT = tr.temp_c - 25.0
    assert np.allclose(y, tr.omega_S_rad_s * (1 + dT[:, None] * c), rtol=RTOL)


def test_scale_asymmetry():
    tr = make_truth()
    a = np.array([0.01, -0.005, 0.002])
    w = tr.omega_S_rad_s
    # positive rates scaled by (1 + a), negative by (1 − a)
    expect = np.where(w > 0, w * (1 + a), w * (1 - a))
    assert np.allclose(_y("scale_asymmetry", {"a": a}, tr), expect, rtol=RTOL)


def test_scale_nonlinearity():
    tr = make_truth()
    s2 = np.array([1e-3, -2e-3, 5e-4])
    w = tr.omega_S_rad_s
    assert np.allclose(_y("scale_nonlinearity", {"s2_s_per_rad": s2}, tr), w + s2 * w * np.abs(w), rtol=RTOL)


def test_misalignment():
    tr = make_truth()
    m = np.array([1e-3, 2e-3, -3e-3, 4e-3, -5e-3, 6e-3])  # xy, xz, yx, yz, zx, zy
    w = tr.omega_S_rad_s
    expect = np.stack(
        [
            w[:, 0] + m[0] * w[:, 1] + m[1] * w[:, 2],
            w[:, 1] + m[2] * w[:, 0] + m[3] * w[:, 2],
            w[:, 2] + m[4] * w[:, 0] + m[5] * w[:, 1],
        ],
        axis=1,
    )
    assert np.allclose(_y("misalignment", {"m_rad": m}, tr), expect, rtol=RTOL)


def test_g_sensitivity_and_g2():
    tr = make_truth()
    H = np.arange(9).reshape(3, 3) * 1e-4
    f = tr.f_S_m_s2
    y = _y("g_sensitivity", {"h_rad_s_per_m_s2": H}, tr)
    assert np.allclose(y, tr.omega_S_rad_s + np.einsum("ij,nj->ni", H, f), rtol=RTOL)
    G = (np.arange(18).reshape(3, 6) - 9) * 1e-6
    ff = np.stack(
        [f[:, 0] ** 2, f[:, 1] ** 2, f[:, 2] ** 2, f[:, 0] * f[:, 1], f[:, 0] * f[:, 2], f[:, 1] * f[:, 2]], 1
    )
    y2 = _y("g2_sensitivity", {"g_rad_s_per_m2_s4": G}, tr)
    assert np.allclose(y2, tr.omega_S_rad_s + ff @ G.T, rtol=RTOL)


def test_time_offset_delays_a_ramp():
    n = 1000
    t = np.arange(n) / RATE
    w = np.stack([0.1 + 2.0 * t, -3.0 * t, 0.5 * t], 1)
    tr = make_truth(n, omega=w)
    tau = 0.0073  # not a multiple of the 2 ms period
    y = _y("time_offset", {"tau_s": tau}, tr)
    inner = t >= tau  # before that the first sample is held
    expect = np.stack([0.1 + 2.0 * (t - tau), -3.0 * (t - tau), 0.5 * (t - tau)], 1)
    assert np.allclose(y[inner], expect[inner], rtol=1e-9, atol=1e-12)
    assert np.array_equal(y[~inner], np.tile(w[0], (int((~inner).sum()), 1)))


def test_earth_rate():
    lat, head = math.radians(47.0), math.radians(30.0)
    tr = make_truth()  # q = identity: S = W
    y = _y("earth_rate", {"latitude_rad": lat, "heading_rad": head}, tr)
    # W = ENU turned by the heading about Up: x_W = (cos h, sin h, 0), y_W = (−sin h, cos h, 0) in ENU;
    # Earth rate in ENU = Ω·(0, cos φ, sin φ)
    om = EARTH_RATE_RAD_S
    w_W = np.array([math.sin(head) * om * math.cos(lat), math.cos(head) * om * math.cos(lat), om * math.sin(lat)])
    assert np.allclose(y, tr.omega_S_rad_s + w_W, rtol=RTOL, atol=1e-18)


def test_quantization_and_saturation():
    tr = make_truth()
    q = 1e-3
    y = _y("quantization", {"lsb_rad_s": q}, tr)
    assert np.allclose(y / q, np.round(y / q), atol=1e-9)
    assert np.all(np.abs(y - tr.omega_S_rad_s) <= q / 2 + 1e-15)
    r = 0.4
    ys = _y("saturation", {"range_rad_s": r}, tr)
    assert np.array_equal(ys, np.where(tr.omega_S_rad_s > r, r, np.where(tr.omega_S_rad_s < -r, -r, tr.omega_S_rad_s)))


@pytest.mark.parametrize("f_hz", [5.0, 40.0, 60.0])
def test_lowpass_gain_is_butterworth(f_hz):
    rate, fc, n = 1000.0, 40.0, 4000
    t = np.arange(n) / rate
    w = np.sin(2 * np.pi * f_hz * t)[:, None] * np.ones(3)
    y = _y("lowpass", {"bandwidth_hz": fc}, make_truth(n, rate, omega=w), rate=rate)
    # digital 2nd-order Butterworth (bilinear, prewarped): |H| = 1/sqrt(1 + (tan(πf/fs)/tan(πfc/fs))^4)
    gain = 1 / math.sqrt(1 + (math.tan(math.pi * f_hz / rate) / math.tan(math.pi * fc / rate)) ** 4)
    tail = slice(n // 2, n)  # transient gone (poles |z| ≈ 0.84 → 1e-3 after ~40 samples)
    # amplitude by projection on sin/cos over whole periods (tail = 2 s)
    s, c = np.sin(2 * np.pi * f_hz * t[tail]), np.cos(2 * np.pi * f_hz * t[tail])
    amp = np.hypot(2 * np.mean(y[tail, 0] * s), 2 * np.mean(y[tail, 0] * c))
    assert amp == pytest.approx(gain, rel=1e-6)


def test_arw_level():
    n = 20000
    tr = make_truth(n, omega=np.zeros((n, 3)))
    N = 1e-3
    e = _y("arw", {"n_rad_per_sqrt_s": N}, tr)
    # per-sample σ = N·√rate; sample std s.e. = σ/√(2n) → 5 s.e. = 2.5 %
    assert np.allclose(e.std(axis=0), N * math.sqrt(RATE), rtol=5 / math.sqrt(2 * n))


def _shaped(n_f=60, level=1e-4):
    """A shaped-vibration parameter set: a flat PSD 50..109 Hz on x, twice it on y, none on z."""
    f = 50.0 + np.arange(n_f, dtype=float)
    psd = np.zeros((3, n_f))
    psd[0], psd[1] = level, 2 * level
    return {"f_hz": f, "psd_rad2_s2_hz": psd}


def test_vibration_enters_as_the_registry_effect():
    """The shaped part of `vibration` is one more noise term, on its own stream: the other draws
    are unchanged (bit for bit), the added term is sim.noise.ShapedNoise on ``noise/vibration``,
    ``{}`` (physics alone) adds nothing, and a bad shape is one error line."""
    from sim import noise as N

    tr = make_truth()
    base = SyntheticGyro("icm42688p", rate_hz=RATE, seed=5)
    phys = SyntheticGyro("icm42688p", rate_hz=RATE, seed=5, overrides={"vibration": {}})
    vib = SyntheticGyro("icm42688p", rate_hz=RATE, seed=5, overrides={"vibration": _shaped()})
    nb, _ = base.noise(tr.n)
    npx, _ = phys.noise(tr.n)
    nv, dv = vib.noise(tr.n)
    assert np.array_equal(nb, npx)
    pd = vib.params["vibration"]
    expect = N.ShapedNoise(
        N.effect_rng(5, "noise/vibration"), N.shaped_taps(pd["f_hz"], pd["psd_rad2_s2_hz"], rate_hz=RATE)
    ).next(tr.n)
    assert np.array_equal(nv, nb + expect)
    assert "vibration" in dv and np.all(dv["vibration"]["std_rad_s"][:2] > 0) and dv["vibration"]["std_rad_s"][2] == 0
    ob, ov = base.measure(tr), vib.measure(tr)
    assert np.array_equal(ob.noise_rad_s, nb) and "vibration" in ov.params
    with pytest.raises(GyroInputError, match="'n' dimensions differ"):
        SyntheticGyro(
            "icm42688p", seed=0, overrides={"vibration": {"f_hz": np.arange(5.0), "psd_rad2_s2_hz": np.zeros((3, 4))}}
        )


def test_shaped_noise_is_block_friendly_and_has_the_spec_psd():
    """ShapedNoise: any chunking gives the same bits; its Welch PSD at the spec's 1-Hz resolution
    matches the target. Design theory (sim.noise.shaped_taps): E[PSD] = S on the design grid and the
    variance is the grid sum exactly, so the mean Welch PSD over the 60 flat bins has expectation S;
    Welch with K = 2N/nperseg − 1 = 199 half-overlapped Hann segments has per-bin relative SD
    ≈ √(1 + 2·0.167²)/√K = 0.073 (Percival & Walden), and the mean of 60 bins (≈ 30 independent,
    adjacent Hann bins correlate) has relative SD 0.073/√30 = 0.013: within 4 SD = 5.3 %."""
    from scipy import signal

    from sim import noise as N

    pd = _shaped()
    h = N.shaped_taps(pd["f_hz"], pd["psd_rad2_s2_hz"], rate_hz=1000.0)
    whole = N.ShapedNoise(N.effect_rng(3, "k"), h).next(100_000)
    g = N.ShapedNoise(N.effect_rng(3, "k"), h)
    parts = [g.next(k) for k in (1, 0, 777, 12_345, 8192, 78_685)]
    assert np.array_equal(whole, np.concatenate(parts))
    f, p = signal.welch(whole, fs=1000.0, nperseg=1000, axis=0)
    inside = (f >= 52) & (f <= 107)
    for j, lev in ((0, 1e-4), (1, 2e-4)):
        assert abs(np.mean(p[inside, j]) / lev - 1.0) <= 4 * 0.013
    assert np.all(whole[:, 2] == 0)
    outside = (f < 40) | (f > 125)
    assert np.mean(p[outside, 0]) < 1e-3 * 1e-4


# ---------------------------------------------------------------- independent streams
def test_adding_effects_leaves_other_draws_unchanged():
    tr = make_truth()
    base = SyntheticGyro("icm42688p", rate_hz=RATE, seed=5)
    more = SyntheticGyro(
        "icm42688p",
        rate_hz=RATE,
        seed=5,
        overrides={"rrw": {}, "correlated": {}, "scale_asymmetry": {}, "bias_ramp": {}},
    )
    fewer = SyntheticGyro("icm42688p", rate_hz=RATE, seed=5, without=["arw", "scale", "misalignment"])
    ob, om, of = base.measure(tr), more.measure(tr), fewer.measure(tr)
    for eff in base.effects:
        for other, out in ((more, om), (fewer, of)):
            if eff not in other.effects:
                continue
            for k, v in base.params[eff].items():
                assert np.array_equal(v, other.params[eff][k]), (eff, k)
            for k, v in ob.draws[eff].items():
                assert np.array_equal(v, out.draws[eff][k]), (eff, k)
    # the noise of the added terms is purely additive: more − base = rrw + correlated realisations
    assert not np.array_equal(om.noise_rad_s, ob.noise_rad_s)
    # removing ARW removes exactly its realisation from the summed noise
    arw = ob.noise_rad_s - of.noise_rad_s
    assert arw.std(axis=0) == pytest.approx(ob.draws["arw"]["std_rad_s"], rel=1e-9)


def test_turn_on_bias_redrawn_per_power_up():
    pu = np.repeat([0, 1, 2], 400)
    n = pu.size
    tr = make_truth(n, power_ups=pu, omega=np.zeros((n, 3)))
    sig = np.array([0.01, 0.02, 0.03])
    g = only("bias", {"b_rad_s": [0.1, 0.2, 0.3], "turn_on_sigma_rad_s": sig}, seed=3)
    out = g.measure(tr)
    b = out.draws["bias"]["b_rad_s_per_power_up"]
    assert b.shape == (3, 3)
    for k in range(3):
        assert np.allclose(out.gyro_rad_s[pu == k], b[k], rtol=RTOL)
    assert not np.allclose(b[0], b[1]) and not np.allclose(b[1], b[2])
    # power-up 0 has the same bias whether or not more power-ups follow
    single = g.measure(make_truth(400, omega=np.zeros((400, 3))))
    assert np.array_equal(single.draws["bias"]["b_rad_s_per_power_up"][0], b[0])


def test_turn_on_population_spread():
    # over 300 power-ups the draws have std = σ; chi-square: s.e. of a std ≈ σ/√(2·300) = 4 %, 5 s.e.
    g = only("bias", {"b_rad_s": [0, 0, 0], "turn_on_sigma_rad_s": [0.01, 0.01, 0.01]}, seed=9)
    d = np.array([g.power_up_bias(k) for k in range(300)])
    assert np.allclose(d.std(axis=0), 0.01, rtol=5 / math.sqrt(600))


# ---------------------------------------------------------------- stream == batch
def _run_stream(g, tr, **kw):
    st = g.stream(tr.n, **kw)
    for k in range(tr.n):
        y = st.step(k, tr.t_s[k], tr.omega_S_rad_s[k], tr.f_S_m_s2[k], tr.temp_c[k], tr.q_SW_wxyz[k])
        assert y.shape == (3,)
    return st


@pytest.mark.parametrize("preset", ["icm42688p", "mpu6050", "adis16448"])
def test_stream_bit_identical_to_batch_default(preset):
    g = SyntheticGyro(preset, seed=11)
    tr = make_truth(1500, g.rate_hz)
    st = _run_stream(g, tr)
    assert np.array_equal(st.gyro_rad_s, g.measure(tr).gyro_rad_s)


def test_stream_bit_identical_to_batch_all_effects():
    rng = np.random.default_rng(2)
    n = 1500
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    tr = make_truth(n, q=q)
    ov = {
        e: {}
        for e in ("bias_temp_rate", "bias_ramp", "scale_asymmetry", "g2_sensitivity", "earth_rate", "rrw", "correlated")
    }
    ov["time_offset"] = {"tau_s": 0.0051}
    ov["bias_thermal"] = {"poly_rad_s": rng.normal(0, 1e-4, (3, 3))}
    ov["scale_thermal"] = {"poly_per_c": rng.normal(0, 1e-4, (3, 2))}
    g = SyntheticGyro("icm42688p", rate_hz=RATE, seed=4, overrides=ov)
    assert set(g.effects) == set(ALL_BUT_VIB)
    st = _run_stream(g, tr, t_s=tr.t_s, temp_c=tr.temp_c)
    assert np.array_equal(st.gyro_rad_s, g.measure(tr).gyro_rad_s)


def test_stream_refusals():
    g = SyntheticGyro("icm42688p", seed=0, overrides={"time_offset": {"tau_s": -0.001}})
    with pytest.raises(GyroInputError):
        g.stream(10)
    g = SyntheticGyro("icm42688p", seed=0, overrides={"bias_temp_rate": {}})
    with pytest.raises(GyroInputError):
        g.stream(10)
    st = SyntheticGyro("icm42688p", seed=0).stream(3)
    with pytest.raises(GyroInputError):
        st.step(1, 0.0, [0, 0, 0], [0, 0, 9.8], 25.0)


# ---------------------------------------------------------------- options and errors
def test_overrides_and_errors():
    g = SyntheticGyro("icm42688p", seed=0, overrides={"scale": {"s": 0.01}})
    assert np.array_equal(g.params["scale"]["s"], [0.01, 0.01, 0.01])
    with pytest.raises(GyroInputError):
        SyntheticGyro("icm42688p", seed=0, overrides={"scale": {"nope": 1}})
    with pytest.raises(GyroInputError):
        SyntheticGyro("icm42688p", seed=0, overrides={"warp_drive": {}})
    with pytest.raises(GyroInputError):
        SyntheticGyro("icm42688p", seed=0, without=["nope"])
    with pytest.raises(GyroInputError):
        SyntheticGyro("icm42688p", seed=-1)
    with pytest.raises(GyroInputError):
        SyntheticGyro("nosuchsensor", seed=0)
    with pytest.raises(GyroInputError):  # truth at another rate than the gyro
        SyntheticGyro("icm42688p", seed=0).measure(make_truth(100, 200.0))


def test_lowpass_moved_below_nyquist_at_low_rate():
    g = SyntheticGyro("icm42688p", rate_hz=200.0, seed=0)
    assert float(g.params["lowpass"]["bandwidth_hz"]) == pytest.approx(50.0)
    assert g.notes and "lowpass" in g.notes[0]


def test_run_is_a_new_session_of_the_same_unit():
    tr = make_truth()
    a = SyntheticGyro("icm42688p", seed=5)
    b = SyntheticGyro("icm42688p", seed=5, run=1)
    for eff in a.params:
        for k in a.params[eff]:
            assert np.array_equal(a.params[eff][k], b.params[eff][k])
    assert not np.array_equal(a.power_up_bias(0), b.power_up_bias(0))
    assert not np.array_equal(a.measure(tr).noise_rad_s, b.measure(tr).noise_rad_s)


@pytest.mark.parametrize(
    "effect, values",
    [
        ("bias_instability", {"b_rad_s": 1e-4}),
        ("rrw", {"k_rad_s_per_sqrt_s": 1e-4}),
        ("correlated", {"sigma_rad_s": 1e-3, "tau_c_s": 0.5}),
    ],
)
def test_stochastic_effects_are_purely_additive(effect, values):
    # the levels themselves are checked against IEEE 952 in test_noise.py; here: the gyro adds
    # exactly its realisation (y − ω = noise) and reports its summary
    tr = make_truth()
    out = only(effect, values).measure(tr)
    e = out.gyro_rad_s - tr.omega_S_rad_s
    assert np.allclose(e, out.noise_rad_s, rtol=0, atol=1e-15)
    assert np.allclose(out.draws[effect]["std_rad_s"], out.noise_rad_s.std(axis=0))
    assert np.all(out.noise_rad_s.std(axis=0) > 0)


# ---------------------------------------------------------------- registry family terms
FAMILY_TERMS = {
    "periodic[37.5]": {"a_cos_rad_s": [0.01, 0.0, -0.002], "a_sin_rad_s": [0.0, 0.004, 0.0]},
    "step[0.7]": {"size_rad_s": [0.003, -0.001, 0.0]},
    "regressor[omega_y*omega_z]": {"coef": [2e-3, 0.0, -1e-3]},
    "regressor[f_x^2]": {"coef": [0.0, 1e-3, 0.0]},
    "regressor[temp_c]": {"coef": [1e-4, 0.0, 0.0]},
    "regressor[dtemp_dt]": {"coef": [0.0, 0.0, 2e-3]},
    "regressor[t]": {"coef": [1e-3, 0.0, 0.0]},
    "regressor[omega_x*temp_c]": {"coef": [0.0, 1e-4, 0.0]},
}


@pytest.mark.parametrize("name", sorted(FAMILY_TERMS))
def test_family_term_is_its_formula(name):
    """A family term alone: measurement − truth = the registry's term (same numpy code) exactly."""
    from gyrocore.effects.registry import ModelInputs, resolve

    tr = make_truth(1200)
    g = SyntheticGyro("icm42688p", rate_hz=RATE, seed=1, without=ALL_BUT_VIB, overrides={name: FAMILY_TERMS[name]})
    assert g.effects == (name,)
    y = g.measure(tr).gyro_rad_s
    inp = ModelInputs(
        t_s=tr.t_s,
        omega_S_rad_s=tr.omega_S_rad_s,
        f_S_m_s2=tr.f_S_m_s2,
        temp_c=tr.temp_c,
        t_since_power_up_s=tr.t_since_power_up_s,
    )
    eff = resolve(name)
    term = eff.term(g.params[name], inp, tr.omega_S_rad_s)
    assert np.array_equal(y, tr.omega_S_rad_s + term)
    # and it is the documented formula (independent evaluation)
    t = tr.t_s
    p = {k: np.asarray(v) for k, v in FAMILY_TERMS[name].items()}
    if name.startswith("periodic"):
        ref = (
            np.cos(2 * np.pi * 37.5 * t)[:, None] * p["a_cos_rad_s"]
            + np.sin(2 * np.pi * 37.5 * t)[:, None] * p["a_sin_rad_s"]
        )
    elif name.startswith("step"):
        ref = (t >= 0.7)[:, None] * p["size_rad_s"]
    else:
        w, f, T = tr.omega_S_rad_s, tr.f_S_m_s2, tr.temp_c
        sig = {
            "regressor[omega_y*omega_z]": w[:, 1] * w[:, 2],
            "regressor[f_x^2]": f[:, 0] ** 2,
            "regressor[temp_c]": T,
            "regressor[dtemp_dt]": np.gradient(T, t),
            "regressor[t]": t,
            "regressor[omega_x*temp_c]": w[:, 0] * T,
        }[name]
        ref = sig[:, None] * p["coef"]
    # same formula in another operation order (2π·f·t grouping, powers): a few ulp of the phase
    np.testing.assert_allclose(y - tr.omega_S_rad_s, ref, rtol=0, atol=1e-12)


def test_stream_bit_identical_to_batch_with_family_terms():
    rng = np.random.default_rng(3)
    n = 1500
    tr = make_truth(n)
    ov = {e: {} for e in ("bias_temp_rate", "bias_ramp", "scale_asymmetry", "g2_sensitivity", "rrw", "correlated")}
    ov["time_offset"] = {"tau_s": 0.0031}
    ov["bias_thermal"] = {"poly_rad_s": rng.normal(0, 1e-4, (3, 2))}
    ov.update(FAMILY_TERMS)
    ov["periodic[ 37.50 ]"] = ov.pop("periodic[37.5]")  # another spelling of the same term
    g = SyntheticGyro("icm42688p", rate_hz=RATE, seed=5, overrides=ov)
    assert set(FAMILY_TERMS) <= set(g.effects)
    st = _run_stream(g, tr, t_s=tr.t_s, temp_c=tr.temp_c)
    assert np.array_equal(st.gyro_rad_s, g.measure(tr).gyro_rad_s)


def test_family_terms_in_stream_refusals_and_overrides():
    with pytest.raises(GyroInputError, match="rate derivative"):
        SyntheticGyro("icm42688p", seed=0, overrides={"regressor[alpha_x]": {"coef": 1e-3}}).stream(10)
    with pytest.raises(GyroInputError, match="temperature trajectory"):
        SyntheticGyro("icm42688p", seed=0, overrides={"regressor[dtemp_dt]": {"coef": 1e-3}}).stream(10)
    # missing coefficients are 0; scalars broadcast
    g = SyntheticGyro("icm42688p", seed=0, overrides={"periodic[5]": {"a_sin_rad_s": 0.002}})
    assert np.array_equal(g.params["periodic[5]"]["a_cos_rad_s"], np.zeros(3))
    assert np.array_equal(g.params["periodic[5]"]["a_sin_rad_s"], np.full(3, 0.002))
    with pytest.raises(GyroInputError, match="no parameter 'coef'"):
        SyntheticGyro("icm42688p", seed=0, overrides={"step[1]": {"coef": 1.0}})
    with pytest.raises(GyroInputError, match="overridden twice"):
        SyntheticGyro("icm42688p", seed=0, overrides={"step[1]": {}, "step[1.0]": {}})
    with pytest.raises(GyroInputError, match="unknown signal"):
        SyntheticGyro("icm42688p", seed=0, overrides={"regressor[omega_w]": {}})


# ---------------------------------------------------------------- add that effect: inject -> fit -> remove
SIGMA_ADD = 2e-3  # per-sample white noise, rad/s (arw N = σ/√rate)
N_ADD = 20000  # 20 s at 1 kHz

ADD_CASES = {
    "periodic[37.5]": {"a_cos_rad_s": [4e-3, 0.0, -2e-3], "a_sin_rad_s": [0.0, 3e-3, 1e-3]},
    "step[12.25]": {"size_rad_s": [5e-3, -3e-3, 0.0]},
    "regressor[omega_y*omega_z]": {"coef": [4e-3, 0.0, -3e-3]},
    "regressor[f_x^2]": {"coef": [0.0, 1e-3, 0.0]},
    "regressor[alpha_y]": {"coef": [5e-3, 0.0, 0.0]},
}


def _add_truth(seed):
    """Smooth, well-excited truth (the family regressors are far above their own sample noise)."""
    t = np.arange(N_ADD) / RATE
    w = np.stack(
        [
            0.8 * np.sin(2 * np.pi * 0.31 * t),
            1.1 * np.sin(2 * np.pi * 0.23 * t + 0.4),
            0.9 * np.cos(2 * np.pi * 0.17 * t),
        ],
        1,
    )
    f = np.array([0.4, -0.2, 9.81]) + np.stack(
        [3 * np.sin(2 * np.pi * 0.07 * t), np.cos(0.3 * t), 0.5 * np.sin(0.2 * t)], 1
    )
    temp = 25.0 + 0.1 * t
    return Truth(
        t_s=t,
        omega_S_rad_s=w,
        f_S_m_s2=f,
        q_SW_wxyz=np.tile([1.0, 0, 0, 0], (N_ADD, 1)),
        temp_c=temp,
        t_since_power_up_s=t.copy(),
        power_up_index=np.zeros(N_ADD, int),
    )


def _add_recording(name, run):
    from gyrocore.data.recording import Recording

    g = SyntheticGyro(
        "icm42688p",
        rate_hz=RATE,
        seed=21,
        run=run,
        without=[e for e in ALL_BUT_VIB if e != "arw"],
        overrides={"arw": {"n_rad_per_sqrt_s": SIGMA_ADD / math.sqrt(RATE)}, name: ADD_CASES[name]},
    )
    tr = _add_truth(run)
    out = g.measure(tr)
    return Recording(
        t_s=tr.t_s,
        gyro_rad_s=out.gyro_rad_s,
        accel_m_s2=tr.f_S_m_s2,
        temp_c=tr.temp_c,
        ref_rate_rad_s=tr.omega_S_rad_s,
        meta={"sensor": "icm42688p"},
    )


@pytest.mark.parametrize("name", sorted(ADD_CASES))
def test_injected_family_term_is_fitted_saved_and_removed(name, tmp_path):
    """simulate with the term -> Calibrator (least squares) recovers it within its standard error
    -> parameter file round trip -> apply on ANOTHER recording of the unit (held out) leaves
    the pure noise."""
    from gyrocore.calibrator import Calibrator
    from gyrocore.calib.params import load_params, save_params

    fit_rec = _add_recording(name, run=0)
    res = Calibrator(effects=["bias", name], covariance="ols").fit(fit_rec)
    assert not res.unobservable
    for pname, true in ADD_CASES[name].items():
        z = (res.params[name][pname] - np.asarray(true)) / res.stderr[name][pname]
        # the noise is white and Gaussian, so OLS standard errors are exact: z ~ N(0, 1) per
        # parameter; |z| < 4 has a false-failure probability 6e-5 per parameter
        assert np.all(np.abs(z) < 4), (pname, z)
    save_params(res, tmp_path / "p.json")
    back = load_params(tmp_path / "p.json")
    assert back.effects == ("bias", name) and back.format_version == "1.1"
    np.testing.assert_array_equal(
        back.params[name][next(iter(ADD_CASES[name]))], res.params[name][next(iter(ADD_CASES[name]))]
    )
    held = _add_recording(name, run=1)  # other noise realisation: the "after" is out of sample
    e_after = back.apply(held).gyro_rad_s - held.ref_rate_rad_s
    e_before = held.gyro_rad_s - held.ref_rate_rad_s
    ms_after = np.mean(e_after**2, axis=0) / SIGMA_ADD**2
    # pure noise: mean square / σ² ~ χ²_N / N, sd √(2/N) = 0.010 for N = 20000; 4 sd, plus the
    # parameter-error term (θ̂ − θ)·g of a held-out record, E = P_axis/N·σ² (P_axis ≤ 3: 1.5e-4)
    tol = 4 * math.sqrt(2 / N_ADD) + 3 / N_ADD
    assert np.all(np.abs(ms_after - 1) < tol), ms_after
    # before: the term is there, on the axes where it was injected
    term_axes = np.any([np.asarray(v) != 0 for v in ADD_CASES[name].values()], axis=0)
    ms_before = np.mean(e_before**2, axis=0) / SIGMA_ADD**2
    assert np.all(ms_before[term_axes] > 1 + 10 * tol), ms_before


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(ADD_CASES))
def test_family_standard_errors_are_calibrated_over_seeds(name):
    """Over K independent recordings (runs of the unit), the fitted term's z-scores
    (θ̂ − θ)/se are N(0, 1) under white noise: Σz² ~ χ²(K·P). Two-sided 1e-4 quantiles of
    χ²(K·P) bound it (a wrong standard error by 10 % moves Σz²/(K·P) by ±0.2, far outside)."""
    import scipy.stats

    from gyrocore.calibrator import Calibrator

    K = 40
    z2, dof = 0.0, 0
    for run in range(K):
        res = Calibrator(effects=["bias", name], covariance="ols").fit(_add_recording(name, run=run))
        for pname, true in ADD_CASES[name].items():
            z = (res.params[name][pname] - np.asarray(true)) / res.stderr[name][pname]
            z2 += float(np.sum(z**2))
            dof += z.size
    lo, hi = scipy.stats.chi2.ppf([1e-4, 1 - 1e-4], dof)
    assert lo < z2 < hi, (z2 / dof, lo / dof, hi / dof)


# ---------------------------------------------------------------- chunked measurement (bounded memory)
def _pieces(tr: Truth, sizes):
    """tr cut into consecutive pieces of the given sizes (cycled), as Truth objects."""
    i, k = 0, 0
    while i < tr.n:
        m = sizes[k % len(sizes)]
        k += 1
        j = min(tr.n, i + m)
        yield Truth(
            t_s=tr.t_s[i:j],
            omega_S_rad_s=tr.omega_S_rad_s[i:j],
            f_S_m_s2=tr.f_S_m_s2[i:j],
            q_SW_wxyz=tr.q_SW_wxyz[i:j],
            temp_c=tr.temp_c[i:j],
            t_since_power_up_s=tr.t_since_power_up_s[i:j],
            power_up_index=tr.power_up_index[i:j],
        )
        i = j


@pytest.mark.parametrize("sizes", [(997,), (4096,), (1, 7, 333), (10**6,)])
@pytest.mark.parametrize("tau_s", [0.0031, -0.0042])
def test_chunked_measure_is_bit_identical_to_batch(sizes, tau_s):
    """Every effect (catalogue + family terms incl. the rate derivative), a lagging and a
    leading time offset, the low-pass, three power-ups: the chunked path equals measure()
    bit for bit whatever the cut (chunks of 1 and 7 rows are shorter than the context)."""
    rng = np.random.default_rng(6)
    n = 5000
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    pu = (np.arange(n) * 3) // n
    tr = make_truth(n, q=q, power_ups=pu)
    ov = {
        e: {}
        for e in ("bias_temp_rate", "bias_ramp", "scale_asymmetry", "g2_sensitivity", "earth_rate", "rrw", "correlated")
    }
    ov["time_offset"] = {"tau_s": tau_s}
    ov["bias_thermal"] = {"poly_rad_s": rng.normal(0, 1e-4, (3, 3))}
    ov.update(FAMILY_TERMS)
    ov["regressor[alpha_x]"] = {"coef": [1e-4, 0.0, 0.0]}
    ov["bias"] = {"turn_on_sigma_rad_s": 1e-3}
    ov["vibration"] = _shaped()  # the shaped vibration noise term (ShapedNoise, fixed internal blocks)
    g = SyntheticGyro("icm42688p", rate_hz=RATE, seed=9, overrides=ov)
    assert set(ALL_BUT_VIB) | {"vibration"} <= set(g.effects)
    whole = g.measure(tr)
    parts = list(g.measure_chunks(_pieces(tr, sizes)))
    assert [p.start for p in parts] == list(np.cumsum([0] + [p.n for p in parts[:-1]]))
    y = np.concatenate([p.gyro_rad_s for p in parts])
    nz = np.concatenate([p.noise_rad_s for p in parts])
    assert np.array_equal(y, whole.gyro_rad_s)
    assert np.array_equal(nz, whole.noise_rad_s)
    assert np.array_equal(np.concatenate([p.t_s for p in parts]), tr.t_s)
    b = parts[-1].power_up_bias_rad_s
    assert np.array_equal(np.array([b[k] for k in sorted(b)]), whole.draws["bias"]["b_rad_s_per_power_up"])


def test_noise_blocks_equal_whole_noise():
    g = SyntheticGyro("adis16448", seed=3, overrides={"rrw": {}, "correlated": {}, "vibration": _shaped()})
    whole, _ = g.noise(10_007)
    blocks = g.noise_blocks()
    got = np.concatenate([blocks.take(m) for m in (997, 4096, 1, 4913)])
    assert np.array_equal(got, whole)
