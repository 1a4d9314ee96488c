"""Tests of the digital twin (experiments/twin.py, ``gyroharness twin``)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from click.testing import CliRunner

from experiments import twin as T
from gyrocore.errors import GyroInputError, RepairWarning
from gyrocore.data.recording import Recording, write_csv

RATE = 100.0
DEG = np.pi / 180.0
N_ARW = 1.5e-4  # rad/√s (MPU-6050 class, docs/noise.md)
LSB = DEG / 131.0  # ±250 °/s


def _true_model(*, t_nu=None) -> T.TwinModel:
    # the white noise: arw, or the registered Student-t term arw_student (same variance)
    white = T.shaped_white_noise_terms(np.full(3, N_ARW), nu=None if t_nu is None else np.full(3, float(t_nu)))
    return T.TwinModel(
        rate_hz=RATE,
        params={
            "bias": {"b_rad_s": np.array([0.01, -0.02, 0.005])},
            "quantization": {"lsb_rad_s": np.asarray(LSB)},
            **white,
        },
    )


def _recording(seed: int, *, n: int = 6000, line=None, t_nu=None, gaps: bool = False) -> Recording:
    """A rate-referenced recording from the twin's own generator (known truth).

    The reference rate is a slow multi-axis sinusoid (the replay drives the simulator with
    it); ``line`` = (f_hz, amplitude rad/s) adds a sinusoid on x, ``t_nu`` draws the white
    noise from a Student t with that many degrees of freedom (same variance).
    """
    from experiments.twin import _replica, _truth, reference_of

    t = np.arange(n) / RATE
    omega = 0.3 * np.sin(2 * np.pi * np.array([0.05, 0.07, 0.11]) * t[:, None] + np.array([0.0, 1.0, 2.0]))
    rec0 = Recording(t_s=t, gyro_rad_s=omega.copy(), ref_rate_rad_s=omega, meta={})
    model = _true_model(t_nu=t_nu)
    ref = reference_of(rec0)
    y, _ = _replica(model, _truth(rec0, ref, RATE), 10_000 + seed)
    if line is not None:
        f, a = line
        y = y.copy()
        y[:, 0] += a * np.sin(2 * np.pi * f * t + 0.3)
        y = np.round(y / LSB) * LSB
    ref_out = omega.copy()
    if gaps:
        ref_out[2000:2300] = np.nan
    return Recording(t_s=t, gyro_rad_s=y, ref_rate_rad_s=ref_out, meta={"source": "test"})


def test_true_params_twin_passes():
    """A recording twinned with its own true parameters passes every statistic.

    Under "the twin is right" the real series and the replicas are exchangeable, so each
    statistic's p-value is uniform on {1/M, 2/M, ...}: P(fail) ≤ α/S per statistic and ≤ α = 0.05
    for the whole twin (Bonferroni). This seed is one draw of that event (the slow test measures
    the rate over many recordings); the distance must also sit near its null level 2k/M.
    """
    rec = _recording(0)
    r = T.twin(rec, model=_true_model(), n_replicas=199, seed=1, close=False)
    assert all(r.before.passed.values()), r.before.to_json()
    assert r.before.null_out_rate == pytest.approx(2 * 5 / 200)
    # out-fraction of ~100 correlated bins with mean 0.05: well below 0.25 unless broken
    assert r.before.twin_distance < 0.25


def test_band_order_statistics_and_rank_count():
    """compare(): band = [x_(k), x_(N+1-k)], the real's out-bins match the band, p counts series."""
    rng = np.random.default_rng(3)
    reps = [{"s": rng.standard_normal((3, 4))} for _ in range(39)]
    real = {"s": np.full((3, 4), 10.0)}  # far outside everywhere
    c = T.compare(real, reps, alpha=0.05)
    X = np.sort(np.stack([r["s"] for r in reps]), axis=0)
    assert c.k == 1
    assert np.array_equal(c.lo["s"], X[0]) and np.array_equal(c.hi["s"], X[-1])
    assert c.out["s"].all() and c.in_band_fraction["s"] == 0.0
    assert c.p_value["s"] == pytest.approx(2 / 40)  # both tests at their minimum 1/M, ×2
    # a value tied with every replica (a count of 0 in all) is inside, never "out"
    tie = T.compare({"s": np.zeros((3, 4))}, [{"s": np.zeros((3, 4))} for _ in range(39)])
    assert tie.in_band_fraction["s"] == 1.0 and tie.passed["s"]


def test_injected_line_fails_psd_and_closing_adds_it():
    """A 13.7 Hz line (amplitude 2 σ_white/√(samples per PSD segment)… well above the band)
    fails the PSD statistic; the closing step finds it and the PSD passes after."""
    sigma = N_ARW * np.sqrt(RATE)
    rec = _recording(1, line=(13.7, 0.5 * sigma))
    r = T.twin(rec, model=_true_model(), n_replicas=199, seed=2)
    assert not r.before.passed["psd"]
    assert any("periodic[13.7" in a for a in r.added), r.added
    assert r.after is not None and r.after.passed["psd"], r.after.to_json()
    assert r.after.twin_distance < r.before.twin_distance


def test_heavier_tails_fail_distribution_and_closing_adds_them():
    """Student-t white noise (ν = 5: excess kurtosis 6) fails ``distribution`` against a
    Gaussian twin; the closing step adds heavy-tailed noise and it passes after."""
    rec = _recording(2, t_nu=5.0)
    r = T.twin(rec, model=_true_model(), n_replicas=199, seed=3)
    assert not r.before.passed["distribution"]
    assert r.before.passed["psd"] and r.before.passed["adev"]
    assert any("heavy-tailed" in a for a in r.added), r.added
    assert r.after.passed["distribution"], r.after.to_json()
    nu = r.model_after.params["arw_student"][
        "nu"
    ]  # a registered simulator term (gyrocore.effects.registry.NOISE_TERMS)
    assert np.all((nu > 4.2) & (nu < 9.0)), nu  # kurtosis estimate from 6000 samples is rough


def test_no_reference_is_one_error_naming_what_is_needed():
    rng = np.random.default_rng(0)
    t = np.arange(3000) / RATE
    moving = np.cumsum(rng.standard_normal((3000, 3)), axis=0) * 0.05  # wanders: no still part
    rec = Recording(t_s=t, gyro_rad_s=moving, meta={})
    with pytest.raises(GyroInputError, match="twin needs a reference: ref_x/y/z_rad_s"):
        T.twin(rec, n_replicas=19)


def test_reference_with_gaps_warns_once_and_uses_covered_spans():
    rec = _recording(3, gaps=True)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        ref = T.reference_of(rec)
        r = T.twin(rec, model=_true_model(), n_replicas=19, seed=0, close=False)
    msgs = [str(x.message) for x in w if issubclass(x.category, RepairWarning)]
    assert len(msgs) == 1 and "covered spans only" in msgs[0], msgs
    assert len(ref.spans) == 2
    assert not ref.covered[2000:2300].any()
    assert r.before.n_replicas == 19


def test_lsb_from_differences():
    rng = np.random.default_rng(1)
    x = np.round(rng.standard_normal((5000, 3)) * 10) * LSB
    assert T.lsb_from_differences(x) == pytest.approx(LSB, rel=1e-9)
    assert T.lsb_from_differences(rng.standard_normal((5000, 3))) is None


def test_cli_json(tmp_path):
    from experiments.commands.twin import command

    rec = _recording(4, n=3000)
    f = tmp_path / "rec.csv"
    write_csv(rec, f)
    res = CliRunner().invoke(command, [str(f), "--replicas", "39", "-o", str(tmp_path / "out"), "--json"])
    assert res.exit_code == 0, res.output
    d = json.loads(res.output)
    assert set(d["statistics"]) == {"adev", "psd", "distribution", "window_acf"}
    for v in d["statistics"].values():
        assert 0.0 <= v["in_band_fraction"] <= 1.0 and isinstance(v["pass"], bool)
    assert 0.0 <= d["twin_distance"] <= 1.0
    assert (tmp_path / "out" / "twin.json").exists() and (tmp_path / "out" / "figures" / "twin_adev.png").exists()


def test_real_tomisuarez2_static_smoke(shared_data):
    """The 100-s static MPU-6050 log: runs end to end, LSB 1/131 °/s found, N in the
    docs/noise.md range, JSON shape."""
    p = shared_data / "tomisuarez2_mpu6050" / "imu_static_test.csv"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec, segs = T.load_recording(p)
        r = T.twin(rec, segments=segs, n_replicas=39, seed=0)
    assert float(r.model.params["quantization"]["lsb_rad_s"]) == pytest.approx(DEG / 131.0, rel=1e-6)
    N = r.model.params["arw"]["n_rad_per_sqrt_s"]
    assert np.all((N > 1.0e-4) & (N < 2.5e-4)), N
    d = r.to_json()
    assert "twin_distance" in d and "adev" in d["statistics"]


@pytest.mark.slow
def test_false_fail_rate_of_the_band(tmp_path):
    """Over 30 recordings twinned with their true parameters, each statistic fails with
    probability ≤ α/S (exact permutation p-values; α = 0.2, S = 4 → 0.05). 120 trials:
    failures ≤ 14 (the Binomial(120, 0.05) 0.999 quantile)."""
    fails = 0
    for s in range(30):
        rec = _recording(100 + s, n=3000)
        r = T.twin(rec, model=_true_model(), n_replicas=59, seed=s, close=False, alpha=0.2)
        fails += sum(not v for v in r.before.passed.values())
    print(f"false fails: {fails} of 120 statistic verdicts (expected <= 6)")
    assert fails <= 14, fails


@pytest.mark.slow
def test_real_sets_run(shared_data):
    """The smaller real sets of docs/twin.md run (reduced replicas) and give a distance in [0, 1]
    (the BROAD trials and the 10-min log take minutes each: the docs command covers them)."""
    for name, rel in T.SETS:
        if name not in T.QUICK_SETS + ("PX4 sample.ulg (still part)",):
            continue
        p = shared_data / rel
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rec, segs = T.load_recording(p)
            r = T.twin(rec, segments=segs, n_replicas=19, seed=0, close=False)
        assert 0.0 <= r.before.twin_distance <= 1.0, name


def test_holdout_runs_on_halves():
    """holdout(): noise from the first half, compared with the second (smoke: keys, a distance)."""
    rec = _recording(5, n=4000)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        h = T.holdout(rec, n_replicas=19, seed=0)
    assert h["error"] is None
    assert 0.0 <= h["before"]["twin_distance"] <= 1.0
    assert set(h["before"]["statistics"]) == {"adev", "psd", "distribution", "window_acf"}


def test_cli_params_file_is_the_declared_model(tmp_path):
    """--params P: the file's deterministic and noise terms replace the identified ones."""
    from experiments.commands.twin import command

    rec = _recording(6, n=3000)
    f = tmp_path / "rec.csv"
    write_csv(rec, f)
    pf = tmp_path / "params.json"
    pf.write_text(
        json.dumps(
            {
                "format_version": "1.1",
                "sensor": "test",
                "effects": ["bias", "arw"],
                "parameters": {"bias": {"b_rad_s": [0.01, -0.02, 0.005]}, "arw": {"n_rad_per_sqrt_s": [N_ARW] * 3}},
            }
        )
    )
    res = CliRunner().invoke(
        command, [str(f), "--params", str(pf), "--replicas", "19", "--no-close", "-o", str(tmp_path / "out"), "--json"]
    )
    assert res.exit_code == 0, res.output
    d = json.loads(res.output)
    assert "parameter file" in d["model"]["sources"]["bias"] and d["model"]["sources"]["arw"] == "parameter file"
    assert d["model"]["params"]["arw"]["n_rad_per_sqrt_s"] == pytest.approx([N_ARW] * 3)
    assert "after" not in d
