"""Tests of experiments.article: the article's numbers, computed (not hard-coded)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from experiments import article as X


def test_m_from_printed_b():
    # M = C·B⁻¹ must satisfy M·B = C exactly (solve, not a stored answer)
    C = 20 * math.pi * np.eye(3)
    M = X.article_m(C)
    assert np.allclose(M @ X.ARTICLE_B, C, rtol=0, atol=1e-12)
    # C = 20π·I reproduces the article's M00 to its 4 printed digits (±3e-4 incl. rounding of B)
    assert M[0, 0] == pytest.approx(X.ARTICLE_M[0, 0], abs=3e-4)
    # ... but not its M[2,1] = 0.107: the printed B has B[2,1] = 0.825 -> M[2,1] ≈ −20π·0.825/64.4² ≈ −0.0125
    assert M[2, 1] == pytest.approx(-20 * math.pi * 0.825 / (64.7262 * 64.1897), rel=0.02)
    assert abs(M[2, 1] - X.ARTICLE_M[2, 1]) > 0.1
    # the article's C = 10π·I halves it
    assert np.allclose(X.article_m(C / 2), M / 2)


def test_gate_statistic_white_noise_theory():
    # Σ over 199 |Δ| of white noise σ: E = 199·2σ/√π. |Δ| has sd σ·√2·√(1−2/π) = 0.853σ; adjacent
    # |Δ| are correlated, so bound the window-mean sd loosely by 199·0.853σ/√(199/2) ≈ 12σ per window;
    # over 500 windows the mean has sd < 0.6σ; test within 3σ-equivalent = 2σ (σ = 10 counts -> ±20).
    rng = np.random.default_rng(0)
    sigma = 10.0
    g = rng.normal(0, sigma, (200 * 500, 3))
    s = X.gate_sums_counts(g)
    assert s.shape == (500, 3)
    assert np.allclose(s.mean(axis=0), 199 * 2 * sigma / math.sqrt(math.pi), atol=2 * sigma)
    # a constant rate offset does not change the statistic at all
    assert np.array_equal(X.gate_sums_counts(g + 65.5), X.gate_sums_counts(g)) or np.allclose(
        X.gate_sums_counts(g + 65.5), s, rtol=1e-12
    )


def test_run_writes_section(tmp_path):
    r = X.run(out_dir=tmp_path, quick=True)
    assert r.name == "article"
    for f in r.figures:
        assert (tmp_path / f).stat().st_size > 1000
        assert f in r.markdown
    assert r.summary["A_30hz_500hz"] == pytest.approx(0.27378, abs=1e-5)
    assert r.summary["entries_matching_article"] == 1  # only M00
    if r.summary["real_data"]:
        # the still MPU-6050 at ±250 °/s: the article's gate rejects every window
        assert r.summary["gate_reject_fraction_250dps"] == 1.0
