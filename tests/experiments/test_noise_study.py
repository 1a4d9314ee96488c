"""experiments/noise_study.py: a tiny grid runs, is deterministic for a seed, and scores the terms."""

from __future__ import annotations

import pytest

from experiments import noise_study as S


def test_tiny_study_runs_deterministic_and_scores():
    opts = dict(methods=("gmwm",), replicates=1, mixes=("N+K",), cells=((600.0, 100.0),), workers=1, seed=3)
    r1 = S.run(**opts)
    r2 = S.run(**opts)
    assert [row["terms"] for row in r1["rows"]] == [row["terms"] for row in r2["rows"]]  # same seed, same draws
    assert len(r1["rows"]) == 3  # one replicate × 3 axes
    terms = {s["term"]: s for s in r1["summary"]}
    assert terms["N"]["present"] and terms["N"]["claimed"] == 1.0 and terms["N"]["rmse_rel"] < 0.02
    assert terms["K"]["present"] and "z_pred" in terms["K"]
    assert not terms["B"]["present"]
    assert "gmwm" in r1["goals"]
    assert "N+K" in S.compact([r1["summary"]], ["gmwm"])


def test_selection_census_counts_every_axis():
    c = S.selection_census("N+K", 600.0, 100.0, seeds=1)
    assert c["axes"] == 3 and sum(r["axes"] for r in c["selected"]) == 3
    assert all(r["selected"].startswith("N") or " N" in r["selected"] for r in c["selected"])
    assert "N R" in c["D_vs_true"] and 0.0 <= c["D_vs_true"]["N R"]["p_below_0"] <= 1.0


@pytest.mark.slow
def test_n_interval_covers_beside_a_short_flicker_plateau():
    """N's 95 % interval in N + B + K with a 2-octave flicker plateau, 1 h at 20 Hz (the cell where
    it covered 79–92 % before the exact first-octave EDF and N's robust ends): 48 axes on a seed
    used nowhere else. Nominal coverage 0.95: P(X ≤ 41 | Bin(48, 0.95)) = 0.9 %, so ≥ 42 covered
    (a 90 % interval, the goal's lower end, passes this with probability 0.65)."""
    r = S.run(
        methods=("gmwm",), replicates=16, mixes=("N+B+K-2oct",), cells=((3600.0, 20.0),), workers=1, seed=20261210
    )
    n_rows = [s for s in r["summary"] if s["term"] == "N"]
    assert len(n_rows) == 1 and n_rows[0]["runs"] == 48
    assert round(n_rows[0]["coverage"] * 48) >= 42, n_rows[0]
