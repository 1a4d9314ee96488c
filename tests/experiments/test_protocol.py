"""experiments.protocol: the shortest protocol by the error budget (no simulator needed here)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from experiments import protocol as P
from gyrocore.budget import ParameterGroup


def _fake_hover(rate=100.0, ground_s=3.0, flight_s=60.0):
    n = int((ground_s + flight_s) * rate)
    t = np.arange(n) / rate
    w = np.zeros((n, 3))
    w[int(ground_s * rate):, 2] = 0.2 * np.sin(0.5 * t[int(ground_s * rate):])  # gentle yaw
    ang = np.concatenate([[0.0], np.cumsum(w[1:, 2]) / rate])
    q = np.stack([np.cos(ang / 2), 0 * ang, 0 * ang, np.sin(ang / 2)], axis=1)
    truth = SimpleNamespace(omega_S_rad_s=w, f_S_m_s2=np.tile([0, 0, 9.81], (n, 1)), temp_c=np.full(n, 30.0),
                            q_SW_wxyz=q)
    params = {"arw": {"n_rad_per_sqrt_s": np.full(3, 5e-5)}, "bias_instability": {"b_rad_s": np.full(3, 3e-5)}}
    return SimpleNamespace(truth=truth, recording=SimpleNamespace(rate_hz=rate), params_true=params), ground_s


def _cand(label, cost, se=None, unobservable=()):
    return {"label": label, "cost_s": cost, "se": se, "t0_c": float("nan"), "unobservable": unobservable}


def test_longer_window_and_longer_runs_predict_less_drift_and_choose_is_cheapest():
    res, ground = _fake_hover()
    groups = [ParameterGroup("scale", {"scale": {"s": np.zeros(3)}}, {"scale": {"s": np.full(3, 1e-3)}})]
    table = [_cand("ref", 387.0), _cand("quarter", 97.0, {"scale": np.full(3, 2e-3)}),
             _cand("3 mounts", 50.0, {"scale": np.full(3, 1e-3)}, ("g_sensitivity.h_rad_s_per_m_s2[1]",))]
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
