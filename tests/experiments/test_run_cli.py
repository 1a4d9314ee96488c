"""Tests of the report folder policy and the run/experiment commands (fast parts)."""

from __future__ import annotations

import pytest

from experiments import registry
from experiments.cli import main
from experiments.report import MARKER, ExperimentResult, build_report, md_table
from gyrocore.errors import GyroInputError


def _ok(*, out_dir, **kw):
    (out_dir / "figures").mkdir(exist_ok=True)
    (out_dir / "figures" / "a.png").write_bytes(b"x")
    return ExperimentResult(name="ok", title="OK section", markdown="hello ![a](figures/a.png)",
                            figures=("figures/a.png",), summary={"v": 1.5})


def _fail(*, out_dir, **kw):
    raise RuntimeError("boom\nsecond line")


def test_build_report_and_replace_policy(tmp_path):
    out = tmp_path / "out"
    p, res = build_report([("ok", _ok)], out)
    assert (p / "report.md").read_text().count("OK section") == 2  # contents + heading
    assert (p / MARKER).exists() and (p / "figures" / "a.png").exists()
    # re-run replaces a previous report
    build_report([("ok", _ok)], out)
    # a failing experiment names itself in one line and leaves the old report untouched
    before = (p / "report.md").read_text()
    with pytest.raises(GyroInputError, match=r"^experiment bad failed: RuntimeError: boom$"):
        build_report([("ok", _ok), ("bad", _fail)], out)
    assert (p / "report.md").read_text() == before
    assert not [q for q in tmp_path.iterdir() if q.name.startswith(".out.tmp")]
    # a folder that is not a report is refused without --force
    other = tmp_path / "mine"
    other.mkdir()
    (other / "thesis.tex").write_text("keep me")
    with pytest.raises(GyroInputError, match="--force"):
        build_report([("ok", _ok)], other)
    assert (other / "thesis.tex").exists()
    build_report([("ok", _ok)], other, force=True)
    assert not (other / "thesis.tex").exists()


def test_registry():
    assert {"article", "ablation", "cutoffs"} <= set(registry.names())
    with pytest.raises(GyroInputError, match="unknown experiment"):
        registry.get("nope")


def test_md_table():
    t = md_table(["a", "b"], [(1, 0.000123456), ("x", float("nan"))])
    assert "1.23e-04" in t and "—" in t


def test_cli_experiment_article(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["experiment", "article", "--quick", "--out", str(tmp_path / "o"), "--json"])
    assert e.value.code == 0
    import json

    d = json.loads(capsys.readouterr().out)
    assert d["name"] == "article" and d["summary"]["A_30hz_500hz"] > 0.27


def test_cli_unknown_experiment(capsys):
    with pytest.raises(SystemExit) as e:
        main(["experiment", "nope"])
    assert e.value.code == 2
    assert capsys.readouterr().err.startswith("error: unknown experiment")
