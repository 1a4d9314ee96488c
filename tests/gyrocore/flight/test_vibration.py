"""gyrocore.flight.vibration on simulated signals with a known line set, and the CLI on the shared log.

The simulated recordings are built here from closed-form signals (white noise + sinusoids
whose frequency is a known function of a stepped motor command), so every expected value is
exact; tolerances are the estimator's own intervals (frequency: the Hann resolution; level:
the χ²/window-spread interval the result reports).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from gyrocore.flight import filters as F
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording
from gyrocore.flight.vibration import analyse, read_spec, write_spec

RATE = 1000.0
LEVELS = (0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.55)
HOLD_S = 16.0
N_WHITE = 0.004  # rad/s per sample (white), PSD 2σ²/fs one-sided
F_FIXED, A_FIXED = 137.0, 0.02  # frame resonance on x, rad/s amplitude
F0, K_U, A_MOV = 100.0, 400.0, 0.03  # y: f = F0 + K_U·u (a motor line following throttle)


def _flight(seed: int, *, with_cmd: bool = True) -> Recording:
    rng = np.random.default_rng(seed)
    n_per = int(HOLD_S * RATE)
    u = np.repeat(LEVELS, n_per)
    t = np.arange(u.size) / RATE
    g = rng.normal(0.0, N_WHITE, (u.size, 3))
    g[:, 0] += A_FIXED * np.sin(2 * np.pi * F_FIXED * t + 0.3)
    phase = 2 * np.pi * np.cumsum(F0 + K_U * u) / RATE
    g[:, 1] += A_MOV * np.sin(phase)
    extra = {"motor_cmd_mean": u} if with_cmd else {}
    return Recording(t_s=t, gyro_rad_s=g, meta={"source": "synthetic"}, extra=extra)


def _line(res, axis, follows):
    c = [ln for ln in res.lines if ln["axis"] == axis and ln["follows"] == follows]
    assert c, f"no {follows} line on {axis}: {res.lines}"
    return max(c, key=lambda ln: ln["amplitude_rad_s"])


@pytest.fixture(scope="module")
def res():
    return analyse(_flight(1))


def test_fixed_line_recovered_within_resolution_and_interval(res):
    ln = _line(res, "x", "fixed")
    resol = res.to_json()["frequency_resolution_hz"]
    assert abs(ln["frequency_hz"] - F_FIXED) <= resol / 2
    lo, hi = ln["amplitude_interval_rad_s"]
    assert lo <= A_FIXED <= hi
    assert ln["n_bands"] == len(LEVELS)


def test_moving_line_follows_throttle_with_its_law(res):
    ln = _line(res, "y", "throttle")
    resol = res.to_json()["frequency_resolution_hz"]
    # frequency at the median band: the exact law at that band's command
    u_med = float(np.median([b["median"] for b in res.bands]))
    assert abs(ln["frequency_hz"] - (F0 + K_U * u_med)) <= resol
    law = ln["law"]
    # slope from 8 band frequencies, each within ±resolution/2: LS standard error bound
    assert abs(law["hz_per_unit"] - K_U) <= max(3 * law["hz_per_unit_se"], resol / np.ptp(LEVELS))
    lo, hi = ln["amplitude_interval_rad_s"]
    assert lo <= A_MOV <= hi
    assert ln["aliased"] is False
    assert not [x for x in res.lines if x["axis"] == "z"]  # white noise only: no line (Bonferroni 0.1 %)


def test_broadband_rms_within_interval(res):
    # truth over the integration band [40, band_hi]: white σ²·(band/(fs/2)) plus the line power A²/2
    lo_hz, hi_hz = res.rms_band_hz
    frac = (hi_hz - lo_hz) / (RATE / 2)
    truth = {
        "x": math.sqrt(N_WHITE**2 * frac + A_FIXED**2 / 2),
        "y": math.sqrt(N_WHITE**2 * frac + A_MOV**2 / 2),
        "z": N_WHITE * math.sqrt(frac),
    }
    for a in "xyz":
        lo, hi = res.rms_above_40hz_interval_rad_s[a]
        # the Hann leakage of the DC-removed windows and the bin at the band edge: ±1 bin of
        # white power (1/500 relative) — far inside the interval
        assert lo <= truth[a] <= hi, (a, lo, truth[a], hi)
    assert res.signal == "raw" and res.filters_before == []


def test_no_throttle_column_gives_lines_without_law():
    r = analyse(_flight(2, with_cmd=False))
    assert any("no motor or throttle column" in n for n in r.notes)
    xs = [ln for ln in r.lines if ln["axis"] == "x"]
    assert xs and all(ln["follows"] is None for ln in xs)
    assert min(abs(ln["frequency_hz"] - F_FIXED) for ln in xs) <= 1.5


def test_undo_firmware_pt1_recovers_the_line_before_the_filter():
    """A 150 Hz line through Betaflight's PT1 90 Hz at 8 kHz, logged every 8th loop, is
    recovered at its pre-filter amplitude (the PT1 divides it by |H(150)| = 0.515)."""
    rng = np.random.default_rng(7)
    loop = 8000.0
    n = int(60 * loop)
    t = np.arange(n) / loop
    a_true, f_line = 0.05, 150.0
    x = rng.normal(0, 0.002, (n, 3))
    x[:, 0] += a_true * np.sin(2 * np.pi * f_line * t)
    y = F.pt1(90.0, loop).apply(x)[::8]
    stage = {"kind": "pt1", "cutoff_hz": 90.0, "rate_hz": loop, "dynamic": False, "header": "gyro_lowpass_hz"}
    meta = {
        "gyro_prefilter": json.dumps({"source": "test", "signal": "partly_filtered", "filters_before": [stage]}),
        "loop_rate_measured_hz": str(loop),
        "pid_rate_hz": str(loop),
        "gyro_rate_hz": str(loop),
    }
    rec = Recording(
        t_s=t[::8], gyro_rad_s=y, meta=meta, extra={f"gyro_prefilter_{a}_rad_s": y[:, i] for i, a in enumerate("xyz")}
    )
    r = analyse(rec)
    assert r.signal == "raw" and r.filters_before[0]["undone"] is True
    ln = _line(r, "x", None)
    lo, hi = ln["amplitude_interval_rad_s"]
    assert lo <= a_true <= hi
    assert abs(ln["frequency_hz"] - f_line) <= 0.75
    r0 = analyse(rec, undo=False)
    ln0 = _line(r0, "x", None)
    assert ln0["amplitude_rad_s"] == pytest.approx(a_true * F.pt1(90.0, loop).magnitude(f_line), rel=0.05)


def test_spec_round_trip_and_version_check(res, tmp_path):
    p = tmp_path / "spec.json"
    write_spec(res, p, source="synthetic")
    spec = read_spec(p)
    assert spec["format_version"] == "1.1" and len(spec["bands"]) == len(LEVELS)
    assert len(spec["f_hz"]) == len(spec["bands"][0]["psd_rad2_s2_hz"]["x"])
    spec["format_version"] = "2.0"
    p.write_text(json.dumps(spec))
    with pytest.raises(GyroInputError, match="format_version"):
        read_spec(p)


def test_cli_on_shared_blackbox(shared_data, tmp_path):
    log = shared_data / "betaflight_blackbox" / "better_tune.BBL"
    if not log.exists():
        pytest.skip("shared blackbox log absent")
    spec, png = tmp_path / "s.json", tmp_path / "v.png"
    cp = subprocess.run(
        [sys.executable, "-m", "experiments.cli", "vibration", str(log), "--json", "-o", str(spec), "--plot", str(png)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert cp.returncode == 0, cp.stderr
    d = json.loads(cp.stdout)
    for k in ("rate_hz", "signal", "filters_before", "rms_above_40hz_rad_s", "lines", "bands"):
        assert k in d
    # debug (NOTCH mode) is after the PT1 90 Hz: undone → raw, the PT1 listed as undone
    assert d["signal"] == "raw" and d["filters_before"][0]["kind"] == "pt1" and d["filters_before"][0]["undone"]
    # PROVENANCE: after the PT1 the flight carries 2–10 °/s rms above 40 Hz, before it ~12–35:
    # the undone level (below the folding limit) sits above the as-logged one
    raw = np.degrees([d["rms_above_40hz_rad_s"][a] for a in "xyz"])
    assert np.all(raw > 3.0) and np.all(raw < 60.0)
    assert all(ln["follows"] in ("throttle", "erpm", "fixed") for ln in d["lines"])
    assert png.stat().st_size > 10_000 and read_spec(spec)["kind"] == "gyroharness.vibration_spec"


# ---------------------------------------------------------------- filter recommendation
def _flown(seed):
    r = _flight(seed)
    # rigid-body motion of the flight (the delay's attitude cost needs a rate): 1 rad/s at 0.7 Hz
    g = r.gyro_rad_s.copy()
    g[:, :2] += 1.0 * np.sin(2 * np.pi * 0.7 * r.t_s)[:, None]
    r = Recording(t_s=r.t_s, gyro_rad_s=g, meta=r.meta, extra=r.extra)
    meta = dict(
        r.meta,
        gyro_filters=json.dumps(
            [{"kind": "pt1", "cutoff_hz": 100.0, "rate_hz": RATE, "dynamic": False, "header": "gyro_lowpass_hz"}]
        ),
    )
    return Recording(t_s=r.t_s, gyro_rad_s=r.gyro_rad_s, meta=meta, extra=r.extra)


def test_filter_recommendation_stable_across_noise_seeds():
    from gyrocore.flight.preview import recommend_filter

    picks = []
    for seed in (11, 12, 13):
        rec = _flown(seed)
        # the as-flown gyro columns are the raw synthetic gyro here (no prefilter column): the
        # analysis undoes the declared PT1 100 Hz, so hand it the filtered signal it expects
        from gyrocore.flight import filters as F

        g = F.pt1(100.0, RATE).apply(rec.gyro_rad_s)
        rec = Recording(t_s=rec.t_s, gyro_rad_s=g, meta=rec.meta, extra=rec.extra)
        out = recommend_filter(rec)
        r = out["recommended"]
        assert r["motor_noise"] <= out["budget"]["motor_noise"] * (1 + 1e-9)
        assert r["attitude_cost"] <= out["as_flown"]["attitude_cost"] + 1e-12
        picks.append((r["name"]))
        assert r["name"] != "none" and r["delay_ms"] > 0
        # the tracking notch removes the moving line: for the same motor-noise budget it
        # allows a lighter low-pass, so less attitude cost than the best static chain
        rp = out["with_rpm_filter"]
        assert rp is not None and rp["motor_noise"] <= out["budget"]["motor_noise"] * (1 + 1e-9)
        assert rp["attitude_cost"] < r["attitude_cost"] or r["name"] == rp["name"]
        assert set(out["firmware"]) == {"betaflight", "px4", "ardupilot"}
        assert any(
            s.startswith("set gyro_lowpass_type") or s.startswith("set gyro_lpf1_type")
            for s in out["firmware"]["betaflight"]
        )
    assert len(set(picks)) == 1, picks


def test_filter_names_betaflight_parameters_only_for_betaflight_logs():
    """An INAV (or other non-Betaflight) log gets no Betaflight `set` lines and no RPM-filter
    recommendation (that firmware's names and filter were not read): one comment instead."""
    from gyrocore.flight import filters as F
    from gyrocore.flight.preview import recommend_filter

    rec = _flown(11)
    g = F.pt1(100.0, RATE).apply(rec.gyro_rad_s)
    rec = Recording(
        t_s=rec.t_s, gyro_rad_s=g, meta=dict(rec.meta, firmware_name="inav", firmware_version="9.0.1"), extra=rec.extra
    )
    out = recommend_filter(rec)
    bf = out["firmware"]["betaflight"]
    assert len(bf) == 1 and bf[0].startswith("# inav log") and not any(s.startswith("set ") for s in bf)
    assert "rpm_notch" not in out["recommended"] or out["recommended"]["rpm_notch"] is None


def test_filter_cli_on_shared_blackbox(shared_data):
    log = shared_data / "betaflight_blackbox" / "better_tune.BBL"
    if not log.exists():
        pytest.skip("shared blackbox log absent")
    cp = subprocess.run(
        [sys.executable, "-m", "experiments.cli", "filter", str(log), "--json"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert cp.returncode == 0, cp.stderr
    d = json.loads(cp.stdout)
    for k in ("filter", "cutoff_hz", "notches_hz", "attitude_cost", "delay_ms", "motor_noise"):
        assert k in d["recommended"] and k in d["as_flown"]
    # as flown = PT1 90 Hz at 8 kHz + notch 305/205: low-frequency delay 1/(2π·90) = 1.77 ms from
    # the PT1 plus the notch's; the mean over 1–30 Hz sits between 1.8 and 2.5 ms
    assert 1.8 < d["as_flown"]["delay_ms"] < 2.5
    assert d["recommended"]["motor_noise"] <= d["budget"]["motor_noise"] * (1 + 1e-9)
    # Betaflight 3.1.5 CLI names (cli.c of v3.1.5): gyro_lowpass, gyro_notchN_cut
    bf = d["firmware"]["betaflight"]
    assert any(s.startswith("set gyro_lowpass = ") for s in bf) and not any("lpf1" in s for s in bf)
    assert "IMU_GYRO_CUTOFF" in d["firmware"]["px4"] and "INS_GYRO_FILTER" in d["firmware"]["ardupilot"]
    # the article's first-order 30 Hz: 1/(2π·30) = 5.3 ms at DC, less averaged over 1–30 Hz
    assert 3.5 < d["article"]["delay_ms"] < 5.4


def test_firmware_chain_response_matches_betaflight_formulas():
    # PT1 (pt1FilterGain k = ω/(ω+1), ω = 2π·fc·dT): DC group delay (1−k)/k samples
    w = 2 * math.pi * 90.0 / 8000.0
    k = w / (w + 1)
    st = [
        {"kind": "pt1", "cutoff_hz": 90.0, "rate_hz": 8000.0},
        {"kind": "notch", "cutoff_hz": 305.0, "rate_hz": 8000.0, "notch_cutoff_hz": 205.0},
    ]
    r = F.chain_response(st[:1], [0.0])
    assert r.group_delay_s[0] == pytest.approx((1 - k) / k / 8000.0, rel=1e-9)
    # the notch: zero at its centre, −3 dB at Betaflight's 'cutoff' (its Q definition)
    rn = F.chain_response(st[1:], [305.0, 205.0])
    assert rn.magnitude[0] < 1e-9
    # the RBJ Q is an analog-prototype bandwidth: the digital edge moves by the frequency
    # warping of the bilinear map, relative ≈ ω0²/12 with ω0 = 2π·305/8000 (4.8e-3)
    assert rn.magnitude[1] == pytest.approx(1 / math.sqrt(2), rel=(2 * math.pi * 305 / 8000) ** 2 / 12)
    assert F.betaflight_notch_q(305, 205) == pytest.approx(1.22598, rel=1e-5)
    # a clock 1.5 % slow moves the response: the filter runs per sample
    r_slow = F.chain_response(st[:1], [90.0], loop_scale=0.985)
    assert r_slow.magnitude[0] < F.chain_response(st[:1], [90.0]).magnitude[0]


# ---------------------------------------------------------------- simulator side: synthesis and fidelity
def test_synthesized_vibration_reproduces_the_spec_band(res, tmp_path):
    from gyrocore.flight.synthesis import fidelity, synthesize

    p = tmp_path / "spec.json"
    write_spec(res, p, source="synthetic")
    spec = read_spec(p)
    n = int(120 * RATE)
    d = synthesize(spec, n=n, rate_hz=RATE, seed=5, band=3)
    rec = Recording(t_s=np.arange(n) / RATE, gyro_rad_s=d, meta={"source": "synth"})
    sim = analyse(rec)
    fid = fidelity(sim, spec, band=3)
    for a in "xyz":
        lo, hi = fid[a]["band_hz"]
        m = (hi - lo) * sim.nperseg / RATE  # bins compared
        # under equal spectra each bin is in band with p = 0.95; Hann/50 % makes adjacent
        # bins correlated (≈ 2 bins per independent one): 4 SD of a binomial on m/2 bins
        assert fid[a]["in_band_fraction"] >= 0.95 - 4 * math.sqrt(0.95 * 0.05 / (m / 2)), (a, fid[a])
    # and a disturbance of the wrong level is out of band
    bad = Recording(t_s=rec.t_s, gyro_rad_s=3.0 * d, meta={"source": "synth"})
    assert fidelity(analyse(bad), spec, band=3)["y"]["in_band_fraction"] < 0.2


def test_line_following_rotor_speed_is_erpm_with_its_harmonic():
    """With a rotor-speed column (blackbox 4.5+ eRPM → rotor_hz_i) a line at 2× the rotor
    frequency follows ``erpm``, harmonic 2."""
    r = _flight(4)
    u = r.extra["motor_cmd_mean"]
    rotor_hz = (F0 + K_U * u) / 2.0  # the y line is at twice this rotor frequency
    extra = dict(r.extra, **{f"rotor_hz_{i}": rotor_hz for i in range(4)})
    res4 = analyse(Recording(t_s=r.t_s, gyro_rad_s=r.gyro_rad_s, meta=r.meta, extra=extra))
    ln = _line(res4, "y", "erpm")
    assert ln["harmonic"] == 2
