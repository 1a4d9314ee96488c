"""experiments/noise_study.py: a tiny grid runs, is deterministic for a seed, and scores the terms."""

from __future__ import annotations

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
