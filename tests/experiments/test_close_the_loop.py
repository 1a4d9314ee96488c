"""Experiment close_the_loop: the Monte Carlo helpers (fast) and the whole run (slow)."""

from __future__ import annotations

import pytest

from experiments.close_the_loop import identification_rates, rates_markdown, run


def test_identification_rates_rows_and_table():
    rows = identification_rates(seeds=range(2), scales=(1.0,), effects=["none", "scale"], duration_s=20.0)
    assert [r["effect"] for r in rows] == ["none", "scale"]
    # 1× scale (0.5 %) on the tumbling reference is found on every seed (F in the thousands)
    assert rows[1]["identification_rate"] == 1.0 and rows[1]["false_alarm_rate"] == 0.0
    md = rates_markdown(rows)
    assert "| scale | 1 |" in md and "smallest magnitude" in md


@pytest.mark.slow
def test_run_quick(tmp_path):
    r = run(out_dir=tmp_path, quick=True)
    tt = r.summary["cases"][0]
    assert tt["scenario"] == "turntable" and "scale_asymmetry" in tt["found"]
    assert tt["residual_rms_after_rad_s"] < tt["residual_rms_before_rad_s"]
    assert (tmp_path / "close_the_loop.md").exists()
    assert all((tmp_path / f).exists() for f in r.figures)
