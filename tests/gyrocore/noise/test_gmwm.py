"""GMWM / fixed joint ADEV fit: exact term variances, covariance model, selection, API, CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import scipy.stats

from gyrocore.noise import allan as AL
from gyrocore.noise import adev as ADEV
from gyrocore.noise import ieee952 as IEEE
from gyrocore.noise import avar as V
from gyrocore.noise import gmwm as G
from gyrocore.noise.model import TERMS
from gyrocore.noise.options import NoiseOptions
from gyrocore.cli import build_group, run_cli
from gyrocore.errors import GyroInputError, RepairWarning
from gyrocore.data.recording import Recording, write_csv
from sim import noise as SN

RATE = 100.0


def _mean_avar(gen, n, m, reps, seed):
    """Mean over reps × 3 axes of the overlapping AVAR of generated noise, and its per-point SE."""
    rng = np.random.default_rng(seed)
    acc = []
    for _ in range(reps):
        g = gen(rng, n)
        for ax in range(3):
            _t, d, _n = ADEV.oadev(g[:, ax], RATE, m)
            acc.append(d**2)
    acc = np.array(acc)
    return acc.mean(0), acc.std(0, ddof=1) / math.sqrt(acc.shape[0])


@pytest.mark.parametrize("kind", ["flicker", "gm", "rw"])
def test_exact_discrete_term_avar_matches_simulation(kind):
    """The exact discrete Allan variance of each GMWM term equals the simulated one.

    Tolerance: 4 standard errors of the Monte Carlo mean (24 independent series), at the
    short and middle octaves (m ≤ 256, ≥ 60 EDF each, so the mean is close to normal).
    """
    n = 1 << 14
    m = 2 ** np.arange(9)
    if kind == "flicker":
        # the GMWM models the exact Kasdin–Walter discretisation; the simulator's block flicker
        # (sim.noise.FlickerBlocks) equals it for m >= 8 but is lower at m < 8 (tests/sim/test_noise.py)
        gen = lambda rng, n_: SN.kasdin_walter_flicker(rng, n_, rate_hz=RATE, b_rad_s=1.0)  # noqa: E731
        theory = V.term_avar(m, RATE)[:, 2]
        # at m = 1 the exact value is 1.44× the IEEE asymptote (2 ln2/π)B²
        assert theory[0] / (2 * math.log(2) / math.pi) == pytest.approx(1.4427, rel=1e-3)
    elif kind == "gm":
        gen = lambda rng, n_: SN.gauss_markov(rng, n_, rate_hz=RATE, sigma_rad_s=1.0, tau_c_s=0.3)  # noqa: E731
        theory = V.term_avar(m, RATE, tau_c_s=0.3)[:, 5]
    else:
        gen = lambda rng, n_: SN.rate_random_walk(rng, n_, rate_hz=RATE, k_rad_s_per_sqrt_s=1.0)  # noqa: E731
        theory = V.term_avar(m, RATE)[:, 3]
    mean, se = _mean_avar(gen, n, m, 8, 7)
    z = (mean - theory) / se
    assert np.all(np.abs(z) < 4.0), (kind, np.round(z, 2))


def test_spectral_correlation_matches_exact_white_plus_random_walk():
    """The spectral (all-terms) correlation of AVAR estimates agrees with the exact finite-filter
    one of gyrocore.noise.allan for white + random walk (checked there against Monte Carlo) to 0.05
    (the log-grid averaging of the fast sin⁴ factors is the approximation)."""
    n = 200000
    m = ADEV.octave_m(n)
    coef = np.array([0.0, 1e-8, 0.0, 4e-12, 0.0])
    R_exact = IEEE.avar_correlation_model(m, n + 1, RATE, coef)
    model = V.term_avar(m, RATE) @ np.r_[coef, 0.0]
    C, _edf, _a = V.avar_covariance(m, n, RATE, np.r_[coef, 0.0], None, model)
    d = np.sqrt(np.diag(C))
    assert np.max(np.abs(C / np.outer(d, d) - R_exact)) < 0.05


def _nk(rng, n):
    return SN.white_rate_noise(rng, n, rate_hz=RATE, n_rad_per_sqrt_s=1e-4) + SN.rate_random_walk(
        rng, n, rate_hz=RATE, k_rad_s_per_sqrt_s=2e-6
    )


@pytest.mark.parametrize("method", ["gmwm", "adev"])
def test_arw_plus_rrw_is_not_reported_as_bias_instability(method):
    """Issue 11's case: N = 1e-4, K = 2e-6, 1 h at 100 Hz, no flicker. B must not be claimed,
    K must be found (predicted resolvable with a wide margin), N and K intervals must hold.

    Two seeds × 3 axes; the study (docs/noise.md) gives the rates over 24 axes.
    """
    n = 360000
    zs = G.expected_z(
        {"arw_rad_per_sqrt_s": 1e-4, "rrw_rad_per_s_sqrt_s": 2e-6}, n_samples=n, rate_hz=RATE, method=method
    )
    assert zs["rrw_rad_per_s_sqrt_s"] > G.Z_POWER
    for seed in (11, 12):
        g = _nk(np.random.default_rng(seed), n)
        res = AL.identify_noise(g, rate_hz=RATE, method=method, check_static=False)
        for r in res.axes.values():
            assert r.all_terms()["bias_instability_rad_s"] is None
            assert r.all_terms()["correlated_sigma_rad_s"] is None
            assert r.all_terms()["rrw_rad_per_s_sqrt_s"] is not None
            lo, hi = r.interval("arw_rad_per_sqrt_s")
            assert lo <= 1e-4 <= hi
            # K interval: 95 %; 6 axes, allow one miss (P(≥ 2 misses) ≈ 3 %)
    misses = 0
    for seed in (11, 12):
        res = AL.identify_noise(_nk(np.random.default_rng(seed), n), rate_hz=RATE, method=method, check_static=False)
        misses += sum(
            not (r.interval("rrw_rad_per_s_sqrt_s")[0] <= 2e-6 <= r.interval("rrw_rad_per_s_sqrt_s")[1])
            for r in res.axes.values()
        )
    assert misses <= 1


def test_gauss_markov_identified_with_its_correlation_time():
    """N + GM (σ = 3e-5 rad/s, τc = 20 s), 4 h at 50 Hz: GM predicted resolvable, found on every
    axis with τc and σ intervals covering the truth on at least 2 of 3 (95 % intervals)."""
    n = int(14400 * 50)
    truth = {"arw_rad_per_sqrt_s": 1e-4, "correlated_sigma_rad_s": 3e-5, "correlated_tau_c_s": 20.0}
    assert G.expected_z(truth, n_samples=n, rate_hz=50.0)["correlated_sigma_rad_s"] > G.Z_POWER
    rng = np.random.default_rng(21)
    g = SN.white_rate_noise(rng, n, rate_hz=50.0, n_rad_per_sqrt_s=1e-4) + SN.gauss_markov(
        rng, n, rate_hz=50.0, sigma_rad_s=3e-5, tau_c_s=20.0
    )
    res = AL.identify_noise(g, rate_hz=50.0, check_static=False)
    cov_s = cov_t = 0
    for r in res.axes.values():
        assert r.all_terms()["correlated_sigma_rad_s"] is not None and r.all_terms()["bias_instability_rad_s"] is None
        lo, hi = r.interval("correlated_tau_c_s")
        cov_t += lo <= 20.0 <= hi
        lo, hi = r.interval("correlated_sigma_rad_s")
        cov_s += lo <= 3e-5 <= hi
    assert cov_t >= 2 and cov_s >= 2


def test_identify_noise_api_shapes_and_errors():
    rng = np.random.default_rng(3)
    g = 1e-3 * rng.standard_normal(20000)
    res = AL.identify_noise(g, rate_hz=RATE, check_static=False)
    assert isinstance(res, AL.AllanAnalysis) and list(res.axes) == ["x"]
    r = res.axes["x"]
    assert isinstance(r, AL.AllanResult) and r.method == "gmwm"
    js = r.to_json()
    for k in TERMS:
        assert k in js
    assert js["correlated_sigma_rad_s"] is None and js["correlated_tau_c_s"] is None
    assert r.model.resolved["arw_rad_per_sqrt_s"][0] and not r.model.resolved["bias_instability_rad_s"][0]
    with pytest.raises(GyroInputError, match="rate_hz"):
        AL.identify_noise(g)
    with pytest.raises(GyroInputError, match="shape"):
        AL.identify_noise(np.zeros((10, 4)), rate_hz=RATE)
    with pytest.raises(GyroInputError, match="method"):
        AL.identify_noise(g, rate_hz=RATE, method="kalman")
    with pytest.raises((AttributeError, TypeError)):
        r.model = None  # frozen


def test_short_record_one_warning_naming_terms():
    """A 3-min white record: N found, long-τ terms null with bounds, one warning naming how long
    a record each needs (at half its upper bound)."""
    rng = np.random.default_rng(4)
    g = 1e-3 * rng.standard_normal((18000, 3))
    with pytest.warns(RepairWarning) as rec:
        res = AL.identify_noise(g, rate_hz=RATE, check_static=False)
    msgs = [str(w.message) for w in rec if issubclass(w.category, RepairWarning)]
    assert len(msgs) == 1 and "no long-tau term resolved" in msgs[0]
    assert "B at half its upper bound needs >=" in msgs[0] and "K at half" in msgs[0]
    for r in res.axes.values():
        assert r.all_terms()["rrw_rad_per_s_sqrt_s"] is None and r.interval("rrw_rad_per_s_sqrt_s")[1] > 0


def _gh(capsys, *args):
    status = run_cli(build_group(), list(args))
    out = capsys.readouterr()
    return status, out.out, out.err


def test_noise_alias_cli_json_and_motion_error(tmp_path, capsys):
    rng = np.random.default_rng(5)
    n = 30000
    t = np.arange(n) / RATE
    g = 2e-3 * rng.standard_normal((n, 3))
    p = tmp_path / "still.csv"
    write_csv(Recording(t_s=t, gyro_rad_s=g), p)
    s1, o1, _e = _gh(capsys, "noise", str(p), "--json")
    s2, o2, _e = _gh(capsys, "allan", str(p), "--json", "--method", "gmwm")
    assert s1 == 0 and s2 == 0
    j1, j2 = json.loads(o1), json.loads(o2)
    assert j1["method"] == "gmwm" and j1["axes"]["x"]["arw_rad_per_sqrt_s"] == j2["axes"]["x"]["arw_rad_per_sqrt_s"]
    assert "correlated_tau_c_s" in j1["axes"]["y"]
    s3, o3, _e = _gh(capsys, "noise", str(p), "--json", "--method", "adev", "--plot", str(tmp_path / "a.png"))
    assert s3 == 0 and json.loads(o3)["method"] == "adev" and (tmp_path / "a.png").stat().st_size > 1000
    # a hand swinging the board: the motion gate refuses it, naming the fraction
    g2 = g + 0.5 * np.sin(2 * np.pi * 0.5 * t)[:, None] * (t[:, None] % 40 < 30)
    p2 = tmp_path / "moving.csv"
    write_csv(Recording(t_s=t, gyro_rad_s=g2), p2)
    s4, _o, e4 = _gh(capsys, "noise", str(p2))
    assert s4 != 0 and e4.startswith("error: recording is not static: the motion gate rejects")
    assert "%" in e4 and len(e4.strip().splitlines()) == 1


@pytest.mark.slow
def test_arw_rrw_monte_carlo_rates():
    """20 seeds × 3 axes (60) of the issue's ARW + RRW sensor (N = 1e-4, K = 2e-6, 1 h at 100 Hz):
    the issue's goals checked with tolerances from the binomial spread of 60 axes.

    K is resolvable there by the rule (``expected_z`` margin ≥ 1.28), so the goal is "found on
    ≥ 90 %": a correct estimator (p = 0.90) gives ≥ binom.ppf(0.01, 60, 0.90) = 48 finds with
    probability ≥ 99 %. The K interval's coverage goal is 90–97 %: at p = 0.90 the count is
    ≥ 48 with probability ≥ 99 %, at p = 0.97 it is ≤ 60 (no upper constraint at 60 axes; the
    central 95 % range of the count at p = 0.95 is 53–60). B (absent) claimed ≤ 5 %: at p = 0.05 the
    count is ≤ binom.ppf(0.99, 60, 0.05) = 7 with probability ≥ 99 %. N's interval: same
    coverage bound as K. (With the selected model's weights for the enlarged fits: K covered 27/36 = 75 %, 45 of 60 expected.)
    The seeds (SeedSequence(900 + s)) were not used to develop the estimator.
    """
    n = 360000
    zs = G.expected_z({"arw_rad_per_sqrt_s": 1e-4, "rrw_rad_per_s_sqrt_s": 2e-6}, n_samples=n, rate_hz=RATE)
    assert zs["rrw_rad_per_s_sqrt_s"] >= G.Z_POWER
    b = k = cov_k = cov_n = 0
    axes = 0
    for seed in range(20):
        res = AL.identify_noise(
            _nk(np.random.default_rng(np.random.SeedSequence(900 + seed)), n), rate_hz=RATE, check_static=False
        )
        for r in res.axes.values():
            axes += 1
            b += r.all_terms()["bias_instability_rad_s"] is not None
            k += r.all_terms()["rrw_rad_per_s_sqrt_s"] is not None
            lo, hi = r.interval("rrw_rad_per_s_sqrt_s")
            cov_k += lo <= 2e-6 <= hi
            lo, hi = r.interval("arw_rad_per_sqrt_s")
            cov_n += lo <= 1e-4 <= hi
    assert axes == 60
    k_min = int(scipy.stats.binom.ppf(0.01, 60, 0.90))
    b_max = int(scipy.stats.binom.ppf(0.99, 60, 0.05))
    assert (k_min, b_max) == (48, 7)
    assert b <= b_max and k >= k_min and cov_k >= k_min and cov_n >= k_min, (b, k, cov_k, cov_n)


def test_adev_plot_label_mentions_shading_only_when_shaded():
    """The ADEV plot's x-label says what is shaded only on a panel where a long-τ term's region
    is shaded (white noise alone: nothing shaded, the label says no long-τ term is resolved)."""
    from gyrocore.cli.commands.allan import adev_figure
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(8)
    n = 360000
    white = AL.identify_noise(1e-3 * rng.standard_normal(60000), rate_hz=RATE, check_static=False)
    fig = adev_figure(white)
    try:
        label = fig.axes[0].get_xlabel()
        assert "shaded" not in label and "no long-tau term resolved" in label
        assert not any(p.__class__.__name__ == "Polygon" and p.get_alpha() == 0.07 for p in fig.axes[0].patches)
    finally:
        plt.close(fig)
    nk = AL.identify_noise(_nk(rng, n)[:, 0], rate_hz=RATE, check_static=False)
    assert nk.axes["x"].all_terms()["rrw_rad_per_s_sqrt_s"] is not None
    fig = adev_figure(nk)
    try:
        assert "shaded: where K dominates" in fig.axes[0].get_xlabel()
    finally:
        plt.close(fig)


def test_stand_in_check_flicker_floor_against_gauss_markov():
    """An Allan variance halfway between a flicker floor and a Gauss–Markov hump (noise-free
    blend, N = 1e-4, B = 1.5e-5 / GM 3e-5, 20 s): over 1 h B is selected (cheaper penalty) but
    a GM fits as well, so B is fitted and reported unresolved, ambiguous with GM — the rule
    predicts B unresolvable at 1 h; over 4 h a blend dominated by the floor has B resolved."""

    def blend(T, w):
        n = int(T * RATE)
        m = V.scales(n)
        b = V.term_avar(m, RATE) @ np.array([0, 1e-8, 2.25e-10, 0, 0, 0])
        g = V.term_avar(m, RATE, tau_c_s=20.0) @ np.array([0, 1e-8, 0, 0, 0, 9e-10])
        return G.fit_noise(m / RATE, w * b + (1 - w) * g, m, n)

    truth_b = {"arw_rad_per_sqrt_s": 1e-4, "bias_instability_rad_s": 1.5e-5}
    assert G.expected_z(truth_b, n_samples=360000, rate_hz=RATE)["bias_instability_rad_s"] < G.Z_POWER
    assert G.expected_z(truth_b, n_samples=1440000, rate_hz=RATE)["bias_instability_rad_s"] >= G.Z_POWER
    f = blend(3600, 0.5)
    assert "bias_instability_rad_s" in f.selected and f.all_terms()["bias_instability_rad_s"] is None
    assert f.ambiguous == {"bias_instability_rad_s": "correlated_sigma_rad_s"}
    assert f.estimate["bias_instability_rad_s"] > 0 and f.interval("bias_instability_rad_s")[0] == 0.0
    f4 = blend(14400, 0.7)
    assert f4.all_terms()["bias_instability_rad_s"] is not None and not f4.ambiguous


def test_chi_square_interval_of_a_coefficient():
    """The 95 % interval of a fitted coefficient c with variance v is the chi-square interval
    cν/χ²_ν(0.975) … cν/χ²_ν(0.025), ν = 2c²/v; for large ν it tends to c ± 1.96√v."""
    c, v = 4.0, 2.0  # ν = 16
    _c, lo, hi = G._interval(c, v)
    assert lo == pytest.approx(c * 16 / scipy.stats.chi2.isf(0.025, 16))
    assert hi == pytest.approx(c * 16 / scipy.stats.chi2.ppf(0.025, 16))
    _c, lo, hi = G._interval(1.0, 1e-8)
    assert lo == pytest.approx(1 - 1.96e-4, abs=2e-6) and hi == pytest.approx(1 + 1.96e-4, abs=2e-6)
    _c, lo, hi = G._interval(1.0, 1e-8, pivot=False)
    assert (lo, hi) == pytest.approx((1 - 1.959964e-4, 1 + 1.959964e-4))


def test_arw_interval_with_quantization_at_1khz_covers():
    """N's 95 % interval when white angle noise Q shares N's octaves (N+Q+K at 1 kHz).

    Q = 2e-5 rad dominates the AVAR up to τ = 3Q²/N² = 0.12 s (m ≈ 120); N is fitted on the
    octaves where both terms weigh. With one power law's EDF the EDF there was the white-PM law's
    (≈ n/2 at every m), 3.5× too large at m = 64, and the interval covered ~70 % (30 axes;
    62–79 % in the study). 20 seeds × 3 axes of 10 min at 1 kHz, fixed Q+N+K fit (the
    interval itself, not the selection). Tolerance: covered ≥ 53/60 — for a true 95 %
    interval P(X ≤ 52 | Bin(60, 0.95)) = 0.003; at the old ~70 % P(X ≥ 53 | Bin(60, 0.7)) < 0.001.
    The edf of a pure law is unchanged by the mixture correction (ratio exactly 1).
    """
    rate, n = 1000.0, 600_000
    m = V.scales(n)
    covered = 0
    for s in range(20):
        rng = np.random.default_rng(np.random.SeedSequence([1103, s]))
        g = (
            SN.white_rate_noise(rng, n, rate_hz=rate, n_rad_per_sqrt_s=1e-4)
            + SN.rate_random_walk(rng, n, rate_hz=rate, k_rad_s_per_sqrt_s=2e-6)
            + np.diff(rng.standard_normal((n + 1, 3)) * 2e-5, axis=0) * rate
        )
        for ax in range(3):
            t, d, _ = ADEV.oadev(g[:, ax], rate, m)
            f = G.fit_noise(
                t, d**2, m, n, candidates=("quantization_rad", "arw_rad_per_sqrt_s", "rrw_rad_per_s_sqrt_s")
            )
            lo, hi = f.interval("arw_rad_per_sqrt_s")
            covered += lo <= 1e-4 <= hi
    assert covered >= 53, covered
    # pure white rate noise: Greenhall's EDF untouched
    c = np.array([0.0, 1e-8, 0.0, 0.0, 0.0, 0.0])
    model = V.term_avar(m, rate) @ c
    _C, edf, alpha = V.avar_covariance(m, n, rate, c, None, model)
    assert np.allclose(edf, [V.power_law_edf(0, int(v), n + 1) for v in m], rtol=1e-9)


def _ramp2(r_world, m):
    """R² of a noise-free N + R Allan variance (N = 1e-4): its excess over N at the last octave."""
    t = m[-1] / RATE
    return float((r_world[-1] - 1e-8 / t) / (t * t / 2.0))


def test_ramp_must_reject_the_random_walk_world():
    """R (rate ramp) against K (rate random walk), equal penalties. An Allan variance
    halfway between N + K and the N + R fit to it (noise-free blend, 1 h at 100 Hz) has R
    selected by a hair; R is claimed only when the K world is rejected, which a blend
    cannot do, so the random walk stands in its place (K reported, R null). Without the check R
    was claimed here (the study: R for a true K on 8–12 % of the 1-h axes). A pure ramp world
    3× the N + R fit to N + K is still reported as R. The N + R fit itself — the ramp that best
    mimics the random walk — is now reported as K: the K model in its place fits it (goodness of
    fit p = 0.72), and a random walk over the record looks like such a ramp often enough that the
    claim needs the K model rejected by the data too (:data:`ALPHA_RAMP_GOF`; issue 25: R claimed for
    K on 3/24 axes of a 1-h N + B + K cell)."""
    n = 360000
    m = V.scales(n)
    k_world = V.term_avar(m, RATE) @ np.array([0, 1e-8, 0, 4e-12, 0, 0])
    r_world = G.fit_noise(m / RATE, k_world, m, n, candidates=("arw_rad_per_sqrt_s", "rate_ramp_rad_s2")).fit_avar
    f = G.fit_noise(m / RATE, 0.5 * k_world + 0.5 * r_world, m, n)
    assert f.selected == ("arw_rad_per_sqrt_s", "rrw_rad_per_s_sqrt_s"), f.selected
    assert f.all_terms()["rate_ramp_rad_s2"] is None and f.all_terms()["rrw_rad_per_s_sqrt_s"] is not None
    f0 = G.fit_noise(m / RATE, G.term_avar(m, RATE) @ np.array([0, 1e-8, 0, 0, 9.0 * _ramp2(r_world, m), 0]), m, n)
    assert f0.all_terms()["rate_ramp_rad_s2"] is not None and f0.all_terms()["rrw_rad_per_s_sqrt_s"] is None
    f1 = G.fit_noise(m / RATE, r_world, m, n)
    assert f1.all_terms()["rate_ramp_rad_s2"] is None and f1.all_terms()["rrw_rad_per_s_sqrt_s"] is not None
    # the rule: a ramp claimed for a true K only when the K world is rejected (level ALPHA_RAMP),
    # so K's margin against R is at least z_{1−α} — the R stand-in alone no longer caps it at ≈ 1.3
    z_k = G.expected_z({"arw_rad_per_sqrt_s": 1e-4, "rrw_rad_per_s_sqrt_s": 2e-6}, n_samples=n, rate_hz=RATE)
    assert z_k["rrw_rad_per_s_sqrt_s"] >= G.Z_POWER


def test_ramp_claimed_at_the_level_of_every_claim():
    """The R-against-K check at the level α = 1 % of every other claim (ALPHA_RAMP), not
    5 %. Noise-free Allan variance 3/4 of the way from N + K (1 h, 100 Hz) to the N + R fit to it:
    R is selected and its check statistic z = (λ − D)/(2√λ) is 2.01, between z₀.₉₅ = 1.645 (R
    claimed at a 5 % level, a 5 % false ramp per cell) and z₀.₉₉ = 2.33: now the random walk stands in
    (K reported, R null). A pure ramp world 3× the N + R fit to N + K is still reported as a
    ramp; the rule's margin of K against R is at least z₀.₉₉."""
    n = 360000
    m = V.scales(n)
    k_world = V.term_avar(m, RATE) @ np.array([0, 1e-8, 0, 4e-12, 0, 0])
    r_world = G.fit_noise(m / RATE, k_world, m, n, candidates=("arw_rad_per_sqrt_s", "rate_ramp_rad_s2")).fit_avar
    f = G.fit_noise(m / RATE, 0.25 * k_world + 0.75 * r_world, m, n)
    assert f.all_terms()["rate_ramp_rad_s2"] is None and f.all_terms()["rrw_rad_per_s_sqrt_s"] is not None, f.selected
    f1 = G.fit_noise(m / RATE, G.term_avar(m, RATE) @ np.array([0, 1e-8, 0, 0, 9.0 * _ramp2(r_world, m), 0]), m, n)
    assert f1.all_terms()["rate_ramp_rad_s2"] is not None and f1.all_terms()["rrw_rad_per_s_sqrt_s"] is None
    assert G.ALPHA_RAMP == G.ALPHA


def test_interval_robust_to_an_omitted_confounder():
    """A flicker floor B too weak to be selected next to a GM (noise-free N + B + K + GM,
    4 h at 50 Hz) is absorbed by the GM, whose σ moves by more than its own SE when B is added;
    the σ interval is then the union of the selected model's and the enlarged model's (in the
    study the conditional interval covered 54 % of the N+B+K+GM 4-h axes). A weaker floor that
    moves σ by less than its SE leaves the interval as it was."""
    rate = 50.0
    n = int(14400 * rate)
    m = V.scales(n)

    def fit(b, robust):
        av = V.term_avar(m, rate, tau_c_s=20.0) @ np.array([0, 1e-8, b * b, 4e-12, 0, 9e-10])
        return G.fit_noise(m / rate, av, m, n, options=NoiseOptions(robust_ci=robust))

    f0, f1 = fit(1e-5, False), fit(1e-5, True)
    assert "bias_instability_rad_s" not in f1.selected and "correlated_sigma_rad_s" in f1.selected
    lo0, hi0 = f0.interval("correlated_sigma_rad_s")
    lo1, hi1 = f1.interval("correlated_sigma_rad_s")
    assert lo1 < 0.9 * lo0 and hi1 >= hi0  # widened towards the enlarged model's σ (smaller: B takes its share)
    assert f1.interval("arw_rad_per_sqrt_s") == f0.interval("arw_rad_per_sqrt_s")  # N is not touched
    assert fit(5e-6, True).interval("correlated_sigma_rad_s") == fit(5e-6, False).interval("correlated_sigma_rad_s")


def test_n_interval_covers_the_model_without_a_marginal_term():
    """A white-angle term Q claimed on marginal evidence beside N (its removal raises the selection
    χ² by less than twice its penalty) shares N's octaves and moves N: on white noise (10 min at
    100 Hz, Q on 2 of 120 study axes) N came out 1.1 % (4 SE) low and its (Q, N)-model interval
    missed. N's interval is then the union with the N-only model's interval; a Q claimed on
    decisive evidence leaves it as it was. The record: one seeded white-noise axis with a Q-shaped
    excess of growing size added to its Allan variance."""
    rate, n = 100.0, 60_000
    m = V.scales(n)
    g = np.random.default_rng(np.random.SeedSequence(20261128)).standard_normal(n) * 1e-4 * math.sqrt(rate)
    taus, dev, _ = ADEV.oadev(g, rate, m)
    q_col = V.term_avar(m, rate)[:, 0]
    n_key, q_key = "arw_rad_per_sqrt_s", "quantization_rad"
    seen = set()
    for q in np.geomspace(2e-7, 2e-6, 13):
        av = dev**2 + q * q * q_col
        f = G.fit_noise(taus, av, m, n)
        if q_key not in f.selected:
            continue
        margin = f.criteria[tuple(k for k in f.selected if k != q_key)] - f.criteria[f.selected]
        marginal = margin < 2.0 * G._PEN_LINEAR
        lo, hi = f.interval(n_key)
        lo_p, hi_p = G.fit_noise(taus, av, m, n, options=NoiseOptions(robust_ci=False)).interval(n_key)
        lo_n, hi_n = G.fit_noise(taus, av, m, n, candidates=(n_key,)).interval(n_key)
        if marginal:
            assert (lo, hi) == (min(lo_p, lo_n), max(hi_p, hi_n))
            assert hi > hi_p  # the N-only model's N lies above the (Q, N) model's
        else:
            assert (lo, hi) == (lo_p, hi_p)
        seen.add(marginal)
    assert seen == {True, False}
