"""gyroharness score / check: the command protocol, faults, the gate, JUnit, the pytest plugin."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from experiments import calibrators as C
from experiments import score as SC
from experiments.cli import main as cli_main  # noqa: F401  (import check)
from gyrocore.cli import build_group, run_cli
from gyrocore.errors import GyroInputError

pytest_plugins = ("pytester",)

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
PROBE = HERE / "routine_probe.py"
EXAMPLES = REPO / "experiments" / "examples"
PY = sys.executable
#: Short calibration runs for the default tests: a 40-s table run (the shortest profile with
#: turns about x, y, z both ways is 9.8 s) and a 60-s thermal run.
CAL_S = (40.0, 60.0)


def _cli(argv, capsys):
    rc = run_cli(build_group(["experiments.commands"]), argv)
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.fixture(scope="module")
def unit():
    """One unit's truth-free calibration runs and scored (static, 10 s) recording."""
    from sim import scenarios as S

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = S.simulate("static", sensor="icm42688p", duration_s=10.0, seed=7).recording
    cal = [C.strip_truth(r, references=True) for r in C.calibration_recordings("icm42688p", 7, durations_s=CAL_S)]
    return cal, C.strip_truth(rec, references=False)


def _probe(mode="ok", **kw):
    return C.CommandCalibrator(
        fit_cmd=f"{PY} {PROBE} fit {{params}} {{inputs}} --mode {mode}",
        apply_cmd=f"{PY} {PROBE} apply {{params}} {{input}} {{output}} --mode {mode}",
        **kw,
    )


# ------------------------------------------------------------------ templates: never a shell
def test_split_template_placeholders_are_whole_arguments():
    argv = C.split_template("./cal 'fit now' --out={params} {inputs}", allowed=("{params}", "{inputs}"))
    assert argv == ["./cal", "fit now", "--out={params}", "{inputs}"]
    vals = {"{params}": "/tmp/a b;rm -rf x/p", "{inputs}": ["/t/x y.csv", "/t/$(id).csv"]}
    assert C.expand(argv, vals) == ["./cal", "fit now", "--out=/tmp/a b;rm -rf x/p", "/t/x y.csv", "/t/$(id).csv"]
    for bad, allowed in (
        ("cal {output}", ("{params}", "{inputs}")),
        ("cal x{inputs}", ("{inputs}",)),
        ("", ("{params}",)),
        ("cal 'unclosed", ("{params}",)),
    ):
        with pytest.raises(GyroInputError):
            C.split_template(bad, allowed=allowed)


def test_command_sees_no_truth_gets_literal_paths_and_the_folder_is_removed(unit, tmp_path, monkeypatch):
    cal, scored = unit
    log = tmp_path / "probe.jsonl"
    monkeypatch.setenv("PROBE_OUT", str(log))
    parent = tmp_path / "dir with space; touch PWNED"
    parent.mkdir()
    routine = _probe(workdir=str(parent))
    w = C.run_routine(routine, cal, [scored])[0]
    assert w.shape == scored.gyro_rad_s.shape
    np.testing.assert_allclose(w, scored.gyro_rad_s - scored.gyro_rad_s[:100].mean(axis=0), rtol=0, atol=1e-15)
    steps = [json.loads(x) for x in log.read_text().splitlines()]
    fit, app = steps
    # each placeholder arrived as one argument, spaces and ';' included; nothing was executed
    assert fit["argv"][1].endswith("params") and " " in fit["argv"][1] and ";" in fit["argv"][1]
    assert [Path(p).name for p in fit["argv"][2:4]] == ["cal_1_turntable.csv", "cal_2_thermal.csv"]
    assert not (tmp_path / "PWNED").exists() and not Path("PWNED").exists()
    assert Path(fit["cwd"]).parent == parent
    # calibration runs keep the rig's references, the scored recording has no truth at all
    for c in fit["csvs"]:
        assert "ref_x_rad_s" in c["header"] and "params_true" not in c["meta"] and "seed" not in c["meta"]
    inp = [c for c in app["csvs"] if c["path"].endswith("input.csv")][0]
    assert not any(h.startswith("ref_") for h in inp["header"])
    assert not set(inp["meta"]) & {"params_true", "seed", "truth_seed", "effects", "run", "table_phases"}
    assert set(app["listing"]) <= {"cal_1_turntable.csv", "cal_2_thermal.csv", "params", "input.csv"}
    assert list(parent.iterdir()) == []  # the temporary folder is gone


# ------------------------------------------------------------------ faults: one line each
@pytest.mark.parametrize(
    "mode,reason",
    [
        ("crash", "apply command exited with status 3: ZeroDivisionError: division by zero"),
        ("fit-crash", "fit command exited with status 4: cannot fit: table run has no still part"),
        ("nothing", "apply command wrote no output file"),
        ("nan", "output file rejected: output.csv: 1 rows with NaN/inf values"),
        ("rows", "rows, the input has"),
        ("degs", "× the raw rate: deg/s written where rad/s belong"),
    ],
)
def test_faults_end_in_one_line(unit, mode, reason):
    cal, scored = unit
    with pytest.raises(C.RoutineFailure) as ei:
        C.run_routine(_probe(mode), cal, [scored])
    msg = str(ei.value)
    assert reason in msg and "\n" not in msg


def test_hang_is_killed_at_the_timeout(unit):
    import time

    cal, scored = unit
    t0 = time.perf_counter()
    with pytest.raises(C.RoutineFailure, match=r"apply command timed out after 2 s \(killed\)"):
        C.run_routine(_probe("hang", timeout_s=2.0), cal, [scored])
    assert time.perf_counter() - t0 < 60  # killed, not waited for (the routine sleeps 600 s)


class _Raises:
    def fit(self, recordings):
        return {}

    def apply(self, recording, params):
        raise ValueError("bad\nmultiline")


class _Degs:
    def fit(self, recordings):
        return {}

    def apply(self, recording, params):
        return np.degrees(recording.gyro_rad_s)


def test_python_form_faults(unit):
    cal, scored = unit
    with pytest.raises(C.RoutineFailure, match="apply raised ValueError: bad multiline"):
        C.run_routine(_Raises(), cal, [scored])
    with pytest.raises(C.RoutineFailure, match="deg/s written where rad/s belong"):
        C.run_routine(_Degs(), cal, [scored])


def test_python_routine_runs_isolated_with_a_timeout(unit):
    """A user's module:factory runs in its own process: its params need not pickle, a hang is
    killed at the timeout, a dying process and an exception are one line each."""
    import time

    cal, scored = unit
    mod = "tests.experiments.python_routine_probe"
    w = C.run_routine(C.IsolatedCalibrator(f"{mod}:ok", timeout_s=60.0), cal, [scored])[0]
    g = scored.gyro_rad_s
    np.testing.assert_array_equal(w, g - g[:100].mean(axis=0))  # pickled through the pipe: exact
    t0 = time.perf_counter()
    with pytest.raises(C.RoutineFailure, match=r"^apply timed out after 3 s \(killed\)$"):
        C.run_routine(C.IsolatedCalibrator(f"{mod}:hang", timeout_s=3.0), cal, [scored])
    assert time.perf_counter() - t0 < 60  # killed, not waited for (the routine sleeps 600 s)
    with pytest.raises(C.RoutineFailure, match=r"^apply: the routine's process died \(exit code 7\)$"):
        C.run_routine(C.IsolatedCalibrator(f"{mod}:die", timeout_s=60.0), cal, [scored])
    with pytest.raises(C.RoutineFailure, match=r"^apply raised RuntimeError: no luck$"):
        C.run_routine(C.IsolatedCalibrator(f"{mod}:fails", timeout_s=60.0), cal, [scored])
    with pytest.raises(C.RoutineFailure, match="cannot import"):
        C.run_routine(C.IsolatedCalibrator("no_such_module_xyz:f", timeout_s=60.0), cal, [scored])


def test_make_routine_isolates_user_modules_only():
    assert isinstance(
        SC.make_routine({"calibrator": "tests.experiments.python_routine_probe:ok"}), C.IsolatedCalibrator
    )
    assert isinstance(SC.make_routine({"calibrator": "core"}), C.CoreCalibrator)


def test_units_check_accepts_real_calibrations():
    """A calibration changes the raw→corrected slope by percent; 57.3× is refused (and ≈ 1 kept)."""
    rng = np.random.default_rng(0)
    raw = rng.normal(0, 0.5, (1000, 3)) + 0.01
    C.check_output(raw, (raw - 0.01) * 1.02)
    with pytest.raises(C.RoutineFailure):
        C.check_output(raw, np.radians(raw))


# ------------------------------------------------------------------ the article through both doors
def test_article_script_equals_the_registered_article_method(unit):
    cal, scored = unit
    script = EXAMPLES / "article_cmd.py"
    cmd = C.CommandCalibrator(
        fit_cmd=f"{PY} {script} fit {{params}} {{inputs}} --lsb-per-dps 16.4",
        apply_cmd=f"{PY} {script} apply {{params}} {{input}} {{output}} --lsb-per-dps 16.4",
    )
    w_cmd = C.run_routine(cmd, cal, [scored])[0]
    w_py = C.run_routine(C.ArticleCalibrator(), cal, [scored])[0]
    # same algorithm, same float64 operations; the only difference is the CSV round trip (%.17g: exact)
    np.testing.assert_allclose(w_cmd, w_py, rtol=1e-12, atol=1e-15)


# ------------------------------------------------------------------ score / check end to end
def _contract(tmp_path, body, name="contract.toml"):
    p = tmp_path / name
    p.write_text(f"units = 2\nseed = 0\ncalibration_s = [{CAL_S[0]}, {CAL_S[1]}]\ntimeout_s = 60\n" + body)
    return p


def test_score_cli_records_failed_units_and_completes(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("PROBE_STATE", str(tmp_path / "state"))
    rc, out, err = _cli(
        [
            "score",
            "--fit-cmd",
            f"{PY} {PROBE} fit {{params}} {{inputs}}",
            "--apply-cmd",
            f"{PY} {PROBE} apply {{params}} {{input}} {{output}} --mode every-second-crash",
            "--scenarios",
            "static",
            "--units",
            "2",
            "--duration-s",
            "10",
            "--calibration-s",
            "40,60",
            "--workers",
            "1",
            "--json",
            "--out",
            str(tmp_path / "rep"),
        ],
        capsys,
    )
    assert rc == 1, err
    d = json.loads(out)
    s = d["scenarios"]["static"]
    assert set(SC.scenario_summary([])) >= {
        "rms_user_deg",
        "rms_none_deg",
        "rms_core_deg",
        "rms_floor_deg",
        "failed_units",
    }
    assert [f["unit"] for f in s["failed_units"]] == [1]
    assert "apply command exited with status 139: segfault-like failure" in s["failed_units"][0]["reason"]
    assert math.isfinite(s["rms_user_deg"]) and s["rms_core_deg"] < s["rms_none_deg"]
    assert (tmp_path / "rep" / "figures" / "score.png").is_file()
    assert "Failed units" in (tmp_path / "rep" / "score.md").read_text()


def test_check_passes_the_core_fails_the_wrong_sign_and_writes_junit(tmp_path, capsys):
    bounds = (
        "[scenario.static]\nduration_s = 10\nmax_ratio_to_none = 0.5\nmax_ratio_to_floor = 10\n"
        "max_ratio_to_core = 1.5\n"
    )
    contract = _contract(tmp_path, bounds)
    rc, out, err = _cli(
        ["check", "--contract", str(contract), "--calibrator", "core", "--workers", "1", "--units", "1"], capsys
    )
    assert rc == 0, out + err
    assert "passed (3 of 3 bounds hold)" in out
    wrong = EXAMPLES / "wrong_calibrator.py"
    junit = tmp_path / "junit.xml"
    rc, out, err = _cli(
        [
            "check",
            "--contract",
            str(contract),
            "--workers",
            "1",
            "--junit",
            str(junit),
            "--units",
            "1",
            "--fit-cmd",
            f"{PY} {wrong} fit {{params}} {{inputs}}",
            "--apply-cmd",
            f"{PY} {wrong} apply {{params}} {{input}} {{output}} --mistake sign",
        ],
        capsys,
    )
    assert rc == 1, out + err
    lines = out.strip().splitlines()
    broken = [ln for ln in lines if "(median over units)" in ln]
    assert len(broken) == 3 and any("max_ratio_to_none" in ln for ln in broken)
    assert "FAILED (0 of 3 bounds hold)" in lines[-1]
    root = ET.parse(junit).getroot()
    suite = root.find("testsuite")
    assert suite.get("tests") == "3" and suite.get("failures") == "3"
    assert all(tc.find("failure") is not None for tc in suite.iter("testcase"))


def test_check_bad_contract_is_one_line(tmp_path, capsys):
    for body, why in (
        ("[scenario.static]\nmax_rms = 1\n", "unknown key"),
        ("[scenario.static]\nmax_rms_deg = -1\n", "positive number"),
        ("units = 2\n", "no [scenario.NAME]"),
        ("[scenario.nosuch]\nmax_rms_deg = 1\n", "nosuch"),
    ):
        p = tmp_path / "c.toml"
        p.write_text(body)
        rc, out, err = _cli(["check", "--contract", str(p), "--calibrator", "core"], capsys)
        assert rc == 2 and err.startswith("error:") and len(err.strip().splitlines()) == 1 and why in err, err


@pytest.mark.skipif(
    shutil.which("cc") is None and shutil.which("gcc") is None,
    reason="no C compiler (cc/gcc) on this machine: the C example cannot be built",
)
def test_c_calibrator_compiled_at_test_time_passes_its_contract(tmp_path, capsys):
    compiler = shutil.which("cc") or shutil.which("gcc")
    exe = tmp_path / "bias_scale"
    subprocess.run(
        [compiler, "-O2", "-std=c99", "-Wall", "-Werror", "-o", str(exe), str(EXAMPLES / "bias_scale.c"), "-lm"],
        check=True,
    )
    contract = _contract(tmp_path, "[scenario.static]\nduration_s = 10\nmax_ratio_to_none = 0.5\n")
    rc, out, err = _cli(
        [
            "check",
            "--contract",
            str(contract),
            "--workers",
            "1",
            "--json",
            "--fit-cmd",
            f"{exe} fit {{params}} {{inputs}}",
            "--apply-cmd",
            f"{exe} apply {{params}} {{input}} {{output}}",
        ],
        capsys,
    )
    d = json.loads(out)
    assert rc == 0 and d["passed"], d["lines"]
    assert d["scenarios"]["static"]["failed_units"] == []


# ------------------------------------------------------------------ false-failure rate
def test_false_failure_rate_matches_monte_carlo():
    """Under the log-normal model the median of n units exceeds the bound at the stated rate.

    20000 draws of 5 units: the empirical rate's sd is √(r(1−r)/20000) ≤ 0.0016 at r = 0.05;
    the check allows 4 sd. The model's parameters come from 20000 reference values (plug-in
    error of the rate ≈ 1 %, below that)."""
    rng = np.random.default_rng(17)
    mu, sd, n = math.log(0.3), 0.6, 5
    ref = np.exp(rng.normal(mu, sd, 20000))
    bound = SC.suggest_bound(ref, n, 0.05)
    assert SC.false_failure_rate(ref, bound, n) == pytest.approx(0.05, rel=1e-6)
    med = np.median(np.exp(rng.normal(mu, sd, (20000, n))), axis=1)
    emp = float(np.mean(med > bound))
    assert abs(emp - 0.05) < 4 * math.sqrt(0.05 * 0.95 / 20000)


# ------------------------------------------------------------------ pytest plugin
def test_pytest_plugin_fixture(pytester, tmp_path, monkeypatch):
    contract = _contract(tmp_path, "[scenario.static]\nduration_s = 10\nmax_ratio_to_none = 0.5\n")
    wrong = EXAMPLES / "wrong_calibrator.py"
    pytester.makepyfile(
        test_user=f"""
def test_core_holds(gyroharness_check):
    res = gyroharness_check({str(contract)!r}, calibrator="core", units=1)
    assert res.passed

def test_wrong_sign_breaks(gyroharness_check):
    gyroharness_check({str(contract)!r}, units=1,
                      fit_cmd={f"{PY} {wrong} fit {{params}} {{inputs}}"!r},
                      apply_cmd={f"{PY} {wrong} apply {{params}} {{input}} {{output}} --mistake sign"!r})
"""
    )
    # the entry point may or may not be installed here: load the plugin explicitly, once
    monkeypatch.setenv("PYTEST_DISABLE_PLUGIN_AUTOLOAD", "1")
    res = pytester.runpytest("-p", "experiments.pytest_plugin", "-p", "no:cacheprovider")
    res.assert_outcomes(passed=1, failed=1)
    res.stdout.fnmatch_lines(["*static: RMS/none * > max_ratio_to_none 0.5 (median over units)*"])


# ------------------------------------------------------------------ slow: the core through score = the ablation
@pytest.mark.slow
def test_score_core_equals_the_ablation_all_row_in_every_scenario():
    """`score --calibrator core` (the registered entry, effects from the datasheet) reproduces the
    ablation's 'all' row bit for bit, and so does the harness's own core column."""
    from experiments import ablation as A
    from experiments.montecarlo import instance_seeds

    seed = instance_seeds(0, 1)[0]
    durations = {
        "static": 30.0,
        "static_bumped": 30.0,
        "turntable": 60.0,
        "thermal": 120.0,
        "hover": 15.0,
        "power_cycles": 60.0,
    }
    for sc, dur in durations.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ab = A.ablate_instance(sc, seed=seed, duration_s=dur, quick=True, mahony_kp_per_s=None, predict=False)
        u = SC.score_unit(sc, routine_spec={"calibrator": "core"}, seed=seed, duration_s=dur, quick=True)
        assert u.failed is None
        assert u.rms_deg["user"] == ab.scores["all"].rms_error_deg, sc
        assert u.rms_deg["core"] == ab.scores["all"].rms_error_deg, sc
        assert u.rms_deg["none"] == ab.scores["none"].rms_error_deg, sc
        assert u.rms_deg["floor"] == ab.scores["floor"].rms_error_deg, sc


@pytest.mark.slow
@pytest.mark.skipif(
    shutil.which("cc") is None and shutil.which("gcc") is None,
    reason="no C compiler (cc/gcc) on this machine: the C example cannot be built",
)
def test_example_contract_passes_the_c_calibrator_and_fails_the_wrong_one(tmp_path, capsys):
    """The shipped contract (bounds from 16 other units at a 1e-3 false-failure rate each) holds
    for the C example on its own 4 units and breaks for the sign error."""
    compiler = shutil.which("cc") or shutil.which("gcc")
    exe = tmp_path / "bias_scale"
    subprocess.run(
        [compiler, "-O2", "-std=c99", "-Wall", "-Werror", "-o", str(exe), str(EXAMPLES / "bias_scale.c"), "-lm"],
        check=True,
    )
    contract = EXAMPLES / "contract_c.toml"
    rc, out, err = _cli(
        [
            "check",
            "--contract",
            str(contract),
            "--workers",
            "2",
            "--fit-cmd",
            f"{exe} fit {{params}} {{inputs}}",
            "--apply-cmd",
            f"{exe} apply {{params}} {{input}} {{output}}",
        ],
        capsys,
    )
    assert rc == 0, out + err
    wrong = EXAMPLES / "wrong_calibrator.py"
    rc, out, err = _cli(
        [
            "check",
            "--contract",
            str(contract),
            "--workers",
            "2",
            "--units",
            "1",
            "--fit-cmd",
            f"{PY} {wrong} fit {{params}} {{inputs}}",
            "--apply-cmd",
            f"{PY} {wrong} apply {{params}} {{input}} {{output}} --mistake sign",
        ],
        capsys,
    )
    assert rc == 1 and "max_ratio_to_none" in out, out + err


def test_predicted_column_appears_when_the_drift_prediction_exists(monkeypatch, tmp_path):
    """The score carries the core's predicted RMS error once ablation.predict_instance exists."""
    from types import SimpleNamespace

    from experiments import ablation as A

    seen = {}

    def stub(res, cal, present, still, start, *, noise=None):
        seen["noise"] = noise
        return SimpleNamespace(rms_predicted_deg=0.25)

    monkeypatch.setattr(A, "predict_instance", stub, raising=False)
    # the prediction uses the noise model the core's calibration identified (the run at the
    # scored rate), as the ablation's does, not the unit's true noise
    identified = object()
    stage = SimpleNamespace(noise_model={"rate_hz": 100.0}, noise=lambda: identified)
    other = SimpleNamespace(noise_model={"rate_hz": 1000.0}, noise=lambda: None)
    res = SimpleNamespace(recording=SimpleNamespace(rate_hz=100.0))
    assert SC._predicted_rms_deg(res, SimpleNamespace(stages=(), results=(other, stage)), [], [], 0) == 0.25
    assert seen["noise"] is identified
    units = [
        SC.UnitScore(
            "static",
            "icm42688p",
            i,
            i,
            {"none": 2.0, "core": 0.2, "user": 0.4, "floor": 0.1},
            {r: 1.0 for r in SC.ROWS},
            rms_predicted_deg=0.25,
        )
        for i in range(3)
    ]
    s = SC.scenario_summary(units)
    assert s["rms_predicted_deg"] == 0.25 and s["ratio_to_core"] == 2.0 and s["ratio_to_floor"] == 4.0
    camp = SC.ScoreCampaign("x", "icm42688p", 0, 3, ("static",), {"static": None}, True, tuple(units), 1.0, 1)
    assert "predicted (core), °" in SC.report_markdown(camp)
    monkeypatch.delattr(A, "predict_instance", raising=False)
    assert math.isnan(SC._predicted_rms_deg(None, None, [], [], 0))
    assert "rms_predicted_deg" not in SC.scenario_summary(
        [SC.UnitScore("static", "icm42688p", 0, 0, {r: 1.0 for r in SC.ROWS}, {r: 1.0 for r in SC.ROWS})]
    )
