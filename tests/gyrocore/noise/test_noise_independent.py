"""Noise identification held against generators that are not ours.

The generators (``tests/indep_noise.py``) follow other people's published recipes: a Kalibr /
OpenVINS-style cumulative-sum random walk, allantools' Kasdin power law, FFT 1/f shaping,
gnss-ins-sim's Gauss–Markov, integer-LSB rounding.  Each test here failed on the code before
its fix (named in the test).  The whole battery: ``bench/indep_noise_check.py`` (docs/noise.md
"Held against independent generators").
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gyrocore.noise.allan import identify_noise
from tests import indep_noise as G


def _white_rw(seed: int, fs: float, T: float, N: float, K: float) -> np.ndarray:
    return _white_rw_seeded([seed, 4242], fs, T, N, K)


def _white_rw_seeded(entropy, fs: float, T: float, N: float, K: float) -> np.ndarray:
    rng = np.random.default_rng(np.random.SeedSequence(entropy))
    n = int(fs * T)
    return np.column_stack([G.white(n, fs, N, rng) + G.random_walk(n, fs, K, rng) for _ in range(3)])


def test_generators_match_their_stated_allan_variance():
    """The generators' own truth (IEEE 952 levels), checked on the exact discrete AVAR formulas'
    asymptotes with allantools' oadev: white N²/τ, random walk K²τ/3, FFT and Kasdin flicker
    (2 ln2/π)B², gnss-ins-sim GM σ²·f(τ/τc).  Tolerance: the overlapping AVAR of 2¹⁸ samples at
    these τ has edf ≥ ~90 (Greenhall), averaged over 4 axes ≥ 360, so its relative SD is
    ≤ √(2/360) = 0.075; 4 SD = 0.30 on the variance."""
    import allantools

    fs, n = 100.0, 2**18
    rng = np.random.default_rng(12)
    tau = np.array([1.0, 4.0, 16.0])

    def avar(gen):
        v = []
        for _ in range(4):
            t, ad, _e, _n = allantools.oadev(gen(), rate=fs, data_type="freq", taus=tau)
            v.append(ad**2)
        return np.mean(v, axis=0)

    checks = {
        "white": (lambda: G.white(n, fs, 1e-3, rng), 1e-6 / tau),
        "random_walk": (lambda: G.random_walk(n, fs, 1e-3, rng), 1e-6 * tau / 3.0),
        "flicker_fft": (lambda: G.flicker_fft(n, fs, 1e-3, rng), np.full(3, G.FLICKER_FLOOR**2 * 1e-6)),
        "flicker_kasdin": (lambda: G.flicker_allantools(n, fs, 1e-3, rng), np.full(3, G.FLICKER_FLOOR**2 * 1e-6)),
        "gm": (lambda: G.gauss_markov_gnss_ins_sim(n, fs, 1e-3, 5.0, rng)[n // 8 :], G.gm_avar(tau, 1e-3, 5.0)),
    }
    for name, (gen, truth) in checks.items():
        ratio = avar(gen) / truth
        assert np.all(np.abs(ratio - 1.0) < 0.30), (name, ratio)


def test_resolved_rrw_interval_is_finite_next_to_a_nested_gm():
    """White + cumulative-sum random walk (Kalibr-style), 2 h at 50 Hz: K is resolved, and its
    95 % interval must be a finite interval containing the truth.  Before the fix the robust
    interval took the union with the enlarged N + K + GM fit, where a GM of τc ≈ 700 s
    *is* the random walk (nested, not identified): K there was ≈ 0 with ν = 2c²/se² → 0 and the
    upper end came out ∞ ([2.2e-6, ∞] for a true 4e-6 on this axis; 1 axis of 18 in a scan)."""
    K = 4e-6
    x = _white_rw(3, 50.0, 7200.0, 1.7e-4, K)
    r = identify_noise(x, rate_hz=50.0, check_static=False, axes=("x",))
    ax = r.axes["x"]
    lo, hi = ax.interval("rrw_rad_per_s_sqrt_s")
    assert ax.all_terms()["rrw_rad_per_s_sqrt_s"] is not None
    assert math.isfinite(hi), (lo, hi)
    # the selected N + K model's chi-square interval: ν = 2c²/se² is large for a resolved K, so
    # the ends are within a factor ~2 of the estimate (here [2.16, 3.67]e-6 around 2.72e-6 — this
    # axis' random walk sags: one of the ~5 % misses, which is what the slow test counts)
    k = ax.all_terms()["rrw_rad_per_s_sqrt_s"]
    assert k / 2.0 < lo < k < hi < 2.0 * k, (k, lo, hi)


@pytest.mark.slow
def test_rrw_interval_coverage_independent_random_walk():
    """Coverage of K's 95 % interval on 48 axes of white + cumulative-sum random walk (1 h at
    50 Hz, N = 1e-4 rad/√s, K = 2e-6 rad/s/√s: the issue's sensor, margin 1.36 by the rule) with
    the nested GM left out of the robust union.  Measured (seeds [s, 555],
    s < 16): K found 42/48, interval covers 44/48 (before the fix 45/48, one of them by an
    infinite upper end).  Bounds: K found ≥ 90 % where resolvable is the issue's goal, and at
    p = 0.9 P(X ≤ 37 | 48) = 0.007; coverage at p = 0.95, P(X ≤ 41 | 48) = 0.009 — each
    ≈ 1 % false failure at the nominal rates.  Every upper end finite.  ≈ 45 s CPU."""
    K, found, covered = 2e-6, 0, 0
    for s in range(16):
        rng = np.random.default_rng(np.random.SeedSequence([s, 555]))
        n = 50 * 3600
        x = np.column_stack([G.white(n, 50.0, 1e-4, rng) + G.random_walk(n, 50.0, K, rng) for _ in range(3)])
        r = identify_noise(x, rate_hz=50.0, check_static=False)
        for ax in r.axes.values():
            lo, hi = ax.interval("rrw_rad_per_s_sqrt_s")
            assert math.isfinite(hi)
            found += ax.all_terms()["rrw_rad_per_s_sqrt_s"] is not None
            covered += lo <= K <= hi
    assert found >= 38 and covered >= 42, (found, covered)


def test_upper_bound_of_an_unresolved_random_walk_covers():
    """White + cumulative-sum random walk (N = 1e-4 rad/√s, K = 2e-6 rad/s/√s, the issue's
    sensor) for 10 min at 50 Hz: K is unresolvable (rule margin −0.79), so it is reported null
    with a 95 % upper bound, which must cover the true K.  Before the fix the bound was the Wald
    end ĉ + 1.96·se with se at the fit (K ≈ 0 there, its own long-τ variance missing): 77 % of
    90 unresolved axes covered (seeds [s, 901], s < 32), the study's "K✗ (75–79)" cells; the
    profile bound of the log-space χ² covers 92 %.  Here 12 seeds (36 axes, ≈ 5 s): at the
    nominal 95 % (the bound is one-sided 97.5 %), P(X ≤ 0.85·n) ≤ 0.03 for n = 30–36; at the old
    77 % the expected count is 0.77·n."""
    K, unresolved, covered = 2e-6, 0, 0
    for s in range(12):
        x = _white_rw_seeded([s, 901], 50.0, 600.0, 1e-4, K)
        r = identify_noise(x, rate_hz=50.0, check_static=False)
        for ax in r.axes.values():
            if ax.all_terms()["rrw_rad_per_s_sqrt_s"] is None:
                unresolved += 1
                hi = ax.interval("rrw_rad_per_s_sqrt_s")[1]
                assert math.isfinite(hi)
                covered += hi >= K
    # K is claimed with probability Φ(margin) = Φ(−0.79) ≈ 21 % (a present but unresolvable term,
    # not a false claim): unresolved ~ Bin(36, 0.79), P(X < 22) = 0.4 %; 22 axes keep the coverage
    # check below meaningful (the old bound 30 sat above the mean 28.4: 27 measured in the sixth
    # session with the round-5 code, 29 with the round-6 check)
    assert unresolved >= 22, unresolved
    assert covered > 0.85 * unresolved, (covered, unresolved)
