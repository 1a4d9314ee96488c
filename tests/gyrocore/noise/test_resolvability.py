"""The resolvability rule predicts what the selection does, and the fit says when a record is too short.

A term is claimed on marginal evidence only when its Wald z = c/se(c) reaches z₀.₉₉
(:func:`gyrocore.noise.gmwm.fit_noise`'s guard); the rule (:func:`gyrocore.noise.gmwm.expected_z`)
simulates that guard, and the fit reports an unclaimed B, K or R whose expected z at its fitted
level and this record length is below z₀.₉₉ + z₀.₉ as not resolvable, with the length needed.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from experiments import noise_study as NS
from gyrocore.noise import allan as AL
from gyrocore.noise import gmwm as G
from gyrocore.noise.avar import model_avar

K = "rrw_rad_per_s_sqrt_s"
R = "rate_ramp_rad_s2"
RATE = 20.0
#: N + B + K whose flicker plateau spans 5 octaves (issue 25's cells): N 1e-4, B 6.95e-5, K 6.53e-6
TRUTH = {G.LINEAR[1]: 1e-4} | {NS.TERM_KEYS[k]: v for k, v in NS.plateau_mix(5.0).items() if k != "N"}


def _fit_truth(T_s: float):
    n = int(T_s * RATE)
    m = G.scales(n)
    return G.fit_noise(m / RATE, model_avar(m, RATE, TRUTH), m, n), n


def test_k_below_the_guard_is_declared_not_resolvable_with_the_reason():
    """1 h: K's Fisher z at the truth is 1.98 < z₀.₉₉ = 2.33 (the 5-octave plateau and N take the
    information of the last octaves). The noise-free Allan variance is fitted: the selection
    takes K (its removal costs the noncentrality λ) but the guard drops it, and the fit says why —
    expected z at the fitted level (here the truth: 1.98 ± 0.05) below the threshold, and a finite
    record length that would resolve it (K's information grows with the number of long octaves:
    between 2 and 4 h here). The rule at the truth agrees: K not resolvable at 1 h."""
    f, n = _fit_truth(3600.0)
    assert f.all_terms()[K] is None
    v = f.not_resolvable[K]
    assert v["expected_z"] < v["threshold"] == G.Z_NEEDED
    assert abs(v["expected_z"] - 1.98) < 0.05, v
    assert v["record_s"] == 3600.0 and 2 * 3600.0 < v["needed_s"] < 4 * 3600.0, v
    assert G.expected_z(TRUTH, n_samples=n, rate_hz=RATE)[K] < G.Z_POWER


def test_k_above_the_guard_is_found_and_not_declared():
    """4 h: K's Fisher z at the truth is ≈ 4 (> z₀.₉₉ + z₀.₉ = 3.61): the rule calls it resolvable and
    the noise-free fit claims it, with no "not resolvable" entry."""
    f, n = _fit_truth(14400.0)
    assert f.all_terms()[K] is not None and K not in f.not_resolvable
    assert abs(f.estimate[K] / TRUTH[K] - 1.0) < 0.02
    assert G.expected_z(TRUTH, n_samples=n, rate_hz=RATE)[K] >= G.Z_POWER


def test_the_rule_counts_the_guard():
    """2 h at 20 Hz, 5-octave plateau: K's Fisher z at the truth is 2.8, above z₀.₉₉ but within
    the realised z's spread of it; the guard dropped K on 1–3 of 24 axes per seed (K found 75–88 %),
    and the rule, which now simulates the guard on its 400 draws, predicts a miss rate of that order
    (margin < z₀.₉ = 1.28, i.e. found on < 90 %), where without the guard it said 1.62."""
    n = int(7200 * RATE)
    z = G.expected_z(TRUTH, n_samples=n, rate_hz=RATE)[K]
    assert 0.5 < z < G.Z_POWER, z


def test_fit_reports_the_reason_on_a_record():
    """identify_noise on a simulated 1-h N + B + K record (5-octave plateau, 20 Hz): on every axis
    where K is not claimed, the result says it is not resolvable at this length (expected z below
    the threshold, finite length needed) and the text report prints it."""
    from gyrocore.cli.commands.allan import report_text

    g = NS.simulate(np.random.default_rng(np.random.SeedSequence([0, 2525])), NS.plateau_mix(5.0), 72000, RATE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = AL.identify_noise(g, rate_hz=RATE, check_static=False)
    missed = [a for a, r in res.axes.items() if r.all_terms()[K] is None]
    assert missed, "this seed was chosen with K unclaimed on some axis"
    for a in missed:
        v = res.axes[a].not_resolvable[K]
        assert v["expected_z"] < v["threshold"] and math.isfinite(v["needed_s"])
        assert res.axes[a].to_json()["not_resolvable"][K]["expected_z"] == v["expected_z"]
    assert f"({K})" in report_text(res) and "not resolvable at 60 min" in report_text(res)


def test_random_walk_that_rises_like_a_ramp_is_no_ramp():
    """A 1-h N + B + K record (5-octave plateau, 20 Hz; development seed) whose random walk
    rises over the last octaves like τ²: the R-against-K check's z was 2.41 > z₀.₉₉ and R was
    claimed for the K that is there. The K model in R's place fits it (goodness of fit p = 0.62,
    each octave with its exact chi-square law), so the ramp is not claimed and K stands."""
    g = NS.simulate(np.random.default_rng(np.random.SeedSequence([3, 7701])), NS.plateau_mix(5.0), 72000, RATE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = AL.identify_noise(g[:, 2:3], rate_hz=RATE, check_static=False)
    (r,) = res.axes.values()
    assert r.all_terms()["rate_ramp_rad_s2"] is None and r.all_terms()["rrw_rad_per_s_sqrt_s"] is not None
