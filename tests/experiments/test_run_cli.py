"""Tests of the report folder policy and the run/experiment commands (fast parts)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from experiments import registry
from experiments.cli import main
from experiments.report import MARKER, ExperimentResult, ReportIncomplete, build_report, md_table
from gyrocore.errors import GyroInputError


def _ok(*, out_dir, **kw):
    (out_dir / "figures").mkdir(exist_ok=True)
    (out_dir / "figures" / "a.png").write_bytes(b"x")
    return ExperimentResult(
        name="ok",
        title="OK section",
        markdown="hello ![a](figures/a.png)",
        figures=("figures/a.png",),
        summary={"v": 1.5},
    )


def _ok2(*, out_dir, **kw):
    return ExperimentResult(name="ok2", title="OK2 section", markdown="world", summary={"v": 2})


def _fail(*, out_dir, **kw):
    raise RuntimeError("boom\nsecond line")


def test_build_report_and_replace_policy(tmp_path):
    out = tmp_path / "out"
    p, res = build_report([("ok", _ok)], out)
    assert (p / "report.md").read_text().count("OK section") == 2  # contents + heading
    assert (p / MARKER).exists() and (p / "figures" / "a.png").exists()
    # re-run replaces a previous report
    build_report([("ok", _ok)], out)
    # a failing section names itself in one line, the others still run, the finished ones are kept
    # in out.incomplete, and the old report is untouched
    before = (p / "report.md").read_text()
    with pytest.raises(
        ReportIncomplete, match=r"^section bad failed: RuntimeError: boom; finished sections \(ok, ok2\)"
    ) as ei:
        build_report([("ok", _ok), ("bad", _fail), ("ok2", _ok2)], out)
    assert (p / "report.md").read_text() == before
    assert not [q for q in tmp_path.iterdir() if q.name.startswith(".out.tmp")]
    part = ei.value.partial
    assert part == tmp_path / "out.incomplete" and (part / MARKER).exists()
    assert sorted(q.name for q in (part / "sections").iterdir()) == ["ok.json", "ok.md", "ok2.json", "ok2.md"]
    text = (part / "report.md").read_text()
    assert "`bad` failed (RuntimeError: boom)" in text and "OK2 section" in text
    status = json.loads((part / "summary.json").read_text())
    assert status["complete"] is False and status["sections"]["bad"]["state"] == "failed"
    # a later complete run removes the stale incomplete folder
    build_report([("ok", _ok)], out)
    assert not part.exists()
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


_SLOW_SECTIONS = """
import signal, sys, time
from experiments.report import ExperimentResult, build_report, ReportIncomplete

# Ctrl-C as a terminal delivers it: a process started in the background of a non-interactive shell
# (as CI may start the suite) inherits SIGINT ignored, and Python then installs no handler for it
signal.signal(signal.SIGINT, signal.default_int_handler)

def make(name, sleep_s):
    def run(*, out_dir, progress=None, **kw):
        for i in range(int(sleep_s * 10)):
            time.sleep(0.1)
            if progress is not None:
                progress(i + 1, int(sleep_s * 10))
        return ExperimentResult(name=name, title=name.upper(), markdown=name, summary={})
    return run

try:
    build_report([("one", make("one", 0)), ("two", make("two", 0)), ("three", make("three", 60)),
                  ("four", make("four", 0))], sys.argv[1])
except ReportIncomplete as exc:
    print(exc, file=sys.stderr)
    sys.exit(130 if exc.interrupted else 2)
"""


def test_sigint_after_two_sections_keeps_them(tmp_path):
    """Ctrl-C (SIGINT to the process) while the third section runs: the two finished sections are
    in out.incomplete with a report naming the interrupted and the not-run sections; the previous
    report in out is untouched."""
    out = tmp_path / "out"
    build_report([("ok", _ok)], out)
    before = (out / "report.md").read_text()
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    proc = subprocess.Popen(
        [sys.executable, "-c", _SLOW_SECTIONS, str(out)], cwd=root, env=env, stderr=subprocess.PIPE, text=True
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:  # wait until section two is saved in the staging folder
        if any((d / "sections" / "two.json").exists() for d in tmp_path.glob(".out.tmp-*")):
            break
        time.sleep(0.05)
    else:
        proc.kill()
        pytest.fail("the first two sections were never written")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130
    assert "section three interrupted; not run: four; finished sections (one, two) kept in" in err
    assert (out / "report.md").read_text() == before
    part = tmp_path / "out.incomplete"
    doc = json.loads((part / "summary.json").read_text())
    assert {k: v["state"] for k, v in doc["sections"].items()} == {
        "one": "done",
        "two": "done",
        "three": "interrupted",
        "four": "not run",
    }
    assert (part / "sections" / "two.md").read_text().startswith("## TWO")
    assert not list(tmp_path.glob(".out.tmp-*"))


def test_run_cli_sizes_and_json(tmp_path, capsys, monkeypatch):
    """`run` passes size "standard" by default, "full" with --full (with quick=False, as the old
    default did), "quick" with --quick; --json keeps stdout to the JSON document."""
    seen = []

    def fake(*, out_dir, quick=False, size=None, seeds=None, workers=None, progress=None, **kw):
        seen.append((quick, size, seeds, workers))
        if progress is not None:
            progress(1, 2)
            progress(2, 2)
        return ExperimentResult(name="fake", title="Fake", markdown="x", summary={"k": 1})

    monkeypatch.setattr(registry, "EXPERIMENTS", {"fake": "x:y"})
    monkeypatch.setattr(registry, "get", lambda name: fake)
    for flags, want in (([], (False, "standard")), (["--full"], (False, "full")), (["--quick"], (True, "quick"))):
        with pytest.raises(SystemExit) as e:
            main(["run", "--out", str(tmp_path / "o"), "--json", *flags])
        assert e.value.code == 0
        cap = capsys.readouterr()
        doc = json.loads(cap.out)
        assert doc["size"] == want[1] and doc["experiments"]["fake"]["summary"] == {"k": 1}
        assert "fake" in cap.err and "total:" in cap.err  # progress lines on stderr only
        assert seen[-1] == (*want, None, None)
    with pytest.raises(SystemExit) as e:
        main(["run", "--quick", "--full"])
    assert e.value.code == 2
