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
