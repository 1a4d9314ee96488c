"""experiments.protocol: the shortest protocol by the error budget (no simulator needed here)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from experiments import protocol as P
from gyrocore.calib.budget import ParameterGroup


def _fake_hover(rate=100.0, ground_s=3.0, flight_s=60.0):
    n = int((ground_s + flight_s) * rate)
    t = np.arange(n) / rate
    w = np.zeros((n, 3))
    w[int(ground_s * rate) :, 2] = 0.2 * np.sin(0.5 * t[int(ground_s * rate) :])  # gentle yaw
    ang = np.concatenate([[0.0], np.cumsum(w[1:, 2]) / rate])
    q = np.stack([np.cos(ang / 2), 0 * ang, 0 * ang, np.sin(ang / 2)], axis=1)
    truth = SimpleNamespace(
        omega_S_rad_s=w, f_S_m_s2=np.tile([0, 0, 9.81], (n, 1)), temp_c=np.full(n, 30.0), q_SW_wxyz=q
    )
    params = {"arw": {"n_rad_per_sqrt_s": np.full(3, 5e-5)}, "bias_instability": {"b_rad_s": np.full(3, 3e-5)}}
    return SimpleNamespace(truth=truth, recording=SimpleNamespace(rate_hz=rate), params_true=params), ground_s


def _cand(label, cost, se=None, unobservable=()):
    return {"label": label, "cost_s": cost, "se": se, "t0_c": float("nan"), "unobservable": unobservable}


def test_longer_window_and_longer_runs_predict_less_drift_and_choose_is_cheapest():
    res, ground = _fake_hover()
    groups = [ParameterGroup("scale", {"scale": {"s": np.zeros(3)}}, {"scale": {"s": np.full(3, 1e-3)}})]
    table = [
        _cand("ref", 387.0),
        _cand("quarter", 97.0, {"scale": np.full(3, 2e-3)}),
        _cand("3 mounts", 50.0, {"scale": np.full(3, 1e-3)}, ("g_sensitivity.h_rad_s_per_m_s2[1]",)),
    ]
    rows = P.evaluate_grid(res, ground, groups, windows=(0.5, 2.0, 8.0), table=table)
    ref = {r["window_s"]: r for r in rows if r["table"] == "ref"}
    # white noise of the window: σ_b² = N²/T_w; a longer window always helps at this noise level
    assert ref[0.5]["final_deg"] > ref[2.0]["final_deg"] > ref[8.0]["final_deg"]
    # the floor hardly depends on the protocol: a later take-off only adds flicker power since
    # the power-up (the process starts at rest; its low-frequency variance grows like ln t)
    assert ref[0.5]["floor_rms_deg"] <= ref[8.0]["floor_rms_deg"] < 1.15 * ref[0.5]["floor_rms_deg"]
    # the short table run: SE × 2 on the scale group → 4× its variance, more drift
    short = {r["window_s"]: r for r in rows if r["table"] == "quarter"}
    assert short[2.0]["final_deg"] > ref[2.0]["final_deg"]
    np.testing.assert_allclose(short[2.0]["table_deg"], 2.0 * ref[2.0]["table_deg"], rtol=1e-9)
    target = P.Target("t", final_deg=ref[2.0]["final_deg"] * 1.0001)
    best = P.choose(rows, target)
    ok = [r for r in rows if r["eligible"] and target.met(r["pred"])]
    assert best is not None and best["cost_s"] == min(r["cost_s"] for r in ok)
    # a candidate that cannot observe a parameter is never chosen, however cheap
    assert all(not r["eligible"] for r in rows if r["table"] == "3 mounts")
    assert best["table"] != "3 mounts"
    assert P.choose(rows, P.Target("impossible", final_deg=1e-9)) is None


# ----------------------------------------------------------------------------- --noise and the record's support
def _cli(argv):
    """Run ``gyroharness argv`` in-process; returns (exit status, stdout, stderr)."""
    import contextlib
    import io

    from experiments.cli import build_group
    from gyrocore.cli import run_cli

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = run_cli(build_group(["experiments.commands"]), argv)
    return rc, out.getvalue(), err.getvalue()


def _unit_var_10min():
    """The floor's unit-level variances of a 10-min still-ish flight (the fake hover's trajectory)."""
    res, ground = _fake_hover(rate=100.0, ground_s=3.0, flight_s=600.0)
    inp, segs, start = P._prefixed_inputs(res, ground, 2.0)
    return P._unit_floor_var(inp, start, segs, None)


def test_record_support_follows_the_resolvability_rule():
    # icm42688p-like noise: N 5.0e-5 rad/√s, flicker B 2.9e-5 rad/s. The flicker term sets a
    # 10-min flight's floor; gmwm.expected_z says it is not resolvable (90 % power) from a
    # 387-s record at 1 kHz (margin 0.0 < 1.28) and is from 2400 s (margin ≈ 9 by the Fisher
    # form, > 1.28 by the stand-in form): the 387-s calibration residual must warn, 2400 s not.
    from gyrocore.noise import gmwm

    uv = _unit_var_10min()
    # the floor is linear in each term's variance coefficient (what record_support relies on)
    from gyrocore.noise.model import NoiseModel

    res, ground = _fake_hover(rate=100.0, ground_s=3.0, flight_s=600.0)
    inp, segs, start = P._prefixed_inputs(res, ground, 2.0)
    both = P._floor_ms(
        inp, start, segs, NoiseModel(arw_rad_per_sqrt_s=np.full(3, 5e-5), bias_instability_rad_s=np.full(3, 2.9e-5))
    )
    np.testing.assert_allclose(
        both, 5e-5**2 * uv["arw_rad_per_sqrt_s"] + 2.9e-5**2 * uv["bias_instability_rad_s"], rtol=1e-9
    )
    terms = {
        "arw_rad_per_sqrt_s": 5e-5,
        "bias_instability_rad_s": 2.9e-5,
        "rrw_rad_per_s_sqrt_s": 0.0,
        "correlated_sigma_rad_s": 0.0,
        "correlated_tau_c_s": None,
    }
    short = P.record_support(terms, n_samples=387_001, rate_hz=1000.0, unit_var=uv, max_record_s=20000.0)
    b = next(r for r in short if r["term"] == "bias_instability_rad_s")
    assert b["present"] and b["matters"] and not b["resolvable"] and b["warn"]
    assert b["margin"] < gmwm.Z_POWER
    assert 387.0 < b["needed_record_s"] <= 4 * 387.0 + 1  # resolvable by doubling within 4× (1200 s: margin 1.5)
    k = next(r for r in short if r["term"] == "rrw_rad_per_s_sqrt_s")
    # an absent random walk at the smallest level that matters (+10 % floor RMS) is an assumption, not a warning
    assert not k["present"] and abs(k["floor_rise"] - P.SUPPORT_RISE) < 1e-9 and not k["warn"]
    msg = P._support_message(
        short, P.NoiseSource(model=None, label="x", record_s=387.0, rate_hz=1000.0, kind="calibration"), 600.0
    )
    assert msg is not None and "387 s" in msg and "600-s flight" in msg and "\n" not in msg
    long = P.record_support(terms, n_samples=2_400_001, rate_hz=1000.0, unit_var=uv, max_record_s=20000.0)
    assert not any(r["warn"] for r in long)
    assert next(r for r in long if r["term"] == "bias_instability_rad_s")["resolvable"]
    # unknown record length: a term that matters cannot be checked -> warn
    unk = P.record_support(terms, n_samples=None, rate_hz=None, unit_var=uv)
    assert next(r for r in unk if r["term"] == "bias_instability_rad_s")["warn"]


def _still_csv(path, *, n=200_000, rate=1000.0, seed=5):
    from gyrocore.data.recording import Recording, write_csv

    rng = np.random.default_rng(seed)
    N = np.array([5e-5, 6e-5, 4e-5])
    t = np.arange(n) / rate
    y = 0.01 + N * math.sqrt(rate) * rng.standard_normal((n, 3))
    write_csv(Recording(t_s=t, gyro_rad_s=y, meta={"sensor": "s"}), path)
    return N


def test_load_noise_from_json_recording_and_bad_files(tmp_path):
    import json

    from gyrocore.errors import GyroInputError

    N = _still_csv(tmp_path / "still.csv")
    rc, out, err = _cli(["noise", str(tmp_path / "still.csv"), "--json"])
    assert rc == 0, err
    (tmp_path / "still.json").write_text(out)
    a = P.load_noise(tmp_path / "still.json")
    b = P.load_noise(tmp_path / "still.csv")
    assert a.kind == "noise-json" and b.kind == "recording"
    assert a.record_s == pytest.approx(199.999, rel=1e-9) and a.rate_hz == pytest.approx(1000.0)
    # the same identification either way (the JSON carries the values of the same GMWM fit)
    np.testing.assert_allclose(a.model.arw_rad_per_sqrt_s, b.model.arw_rad_per_sqrt_s, rtol=1e-12)
    # white noise of 200 s at 1 kHz: N within 5 σ of its relative SE 1/√(n/2) ≈ 0.32 % -> 1.6 %
    np.testing.assert_allclose(a.model.arw_rad_per_sqrt_s, N, rtol=0.016)
    for bad, msg in [
        ("missing.json", "no such noise file"),
        ("junk.json", "not a noise JSON"),
        ("other.json", "neither a noise JSON"),
    ]:
        if bad == "junk.json":
            (tmp_path / bad).write_text("{not json")
        if bad == "other.json":
            (tmp_path / bad).write_text(json.dumps({"a": 1}))
        with pytest.raises(GyroInputError, match=msg):
            P.load_noise(tmp_path / bad)
    doc = json.loads(out)
    doc["axes"]["x"]["arw_rad_per_sqrt_s"] = None
    (tmp_path / "non.json").write_text(json.dumps(doc))
    with pytest.raises(GyroInputError, match="no white rate noise"):
        P.load_noise(tmp_path / "non.json")


def test_experiment_noise_option_errors_in_one_line(tmp_path):
    rc, out, err = _cli(["experiment", "ablation", "--noise", str(tmp_path / "x.json"), "--out", str(tmp_path / "o")])
    assert rc == 2 and err.strip().startswith("error:") and "protocol experiment only" in err
    assert len(err.strip().splitlines()) == 1
    rc, out, err = _cli(["experiment", "protocol", "--noise", str(tmp_path / "x.json"), "--out", str(tmp_path / "o")])
    assert rc == 2 and "no such noise file" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_protocol_quick_with_noise_file_says_which_model_and_warns_once(tmp_path):
    # end to end (simulator): --noise from a 200-s white-noise still JSON. For the 60-s quick
    # hover, flicker that would raise the floor by 10 % is not resolvable from 200 s (no B in
    # the model: the smallest B that matters is tested) -> exactly one warning line; the report
    # and the JSON name the noise model; the held-out check flies fresh units.
    import json

    _still_csv(tmp_path / "still.csv")
    rc, out, err = _cli(["noise", str(tmp_path / "still.csv"), "--json"])
    assert rc == 0
    (tmp_path / "still.json").write_text(out)
    rc, out, err = _cli(
        [
            "experiment",
            "protocol",
            "--quick",
            "--noise",
            str(tmp_path / "still.json"),
            "--out",
            str(tmp_path / "o"),
            "--json",
        ]
    )
    assert rc == 0, err
    warn = [ln for ln in err.splitlines() if ln.startswith("warning:")]
    assert len(warn) == 1 and "does not support a 60-s flight" in warn[0] and "flicker" in warn[0], err
    doc = json.loads(out)
    src = doc["summary"]["noise_source"]
    assert src["kind"] == "noise-json" and "still.json" in src["label"] and src["supported"] is False
    assert src["record_s"] == pytest.approx(199.999, rel=1e-9)
    report = (tmp_path / "o" / "report.md").read_text()
    assert "still.json" in report and "How long must I calibrate" in report
    assert doc["summary"]["fresh_seeds"] and doc["summary"]["design_unit_seed"] not in doc["summary"]["fresh_seeds"]
    assert any(v is not None for v in doc["summary"]["how_long"].values())
