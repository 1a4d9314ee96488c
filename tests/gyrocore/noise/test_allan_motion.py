"""Noise identification of a record that holds some motion (a new user's logs).

A log that is still for most of its length but handled at the start (PX4 sample.ulg: ~8 s in the
hand, then 59 s on the bench) or between poses (IMU-TK's multi-pose session) used to pass the
motion gate (it refused only records with more than half their windows moving) and its Allan
variance was analysed whole: ARW 59 deg/sqrt(h) for an MPU6000 whose still part gives 0.1.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from gyrocore.noise import allan as AL
from gyrocore.cli import build_group, run_cli
from gyrocore.readers.convert import load_any
from gyrocore.data.recording import Recording, write_csv

RATE = 200.0


def _gh(capsys, *argv):
    status = run_cli(build_group(["gyrocore.cli.commands"]), list(argv))
    out, err = capsys.readouterr()
    return status, out, err


def _white(rng, n, sigma):
    return sigma * rng.standard_normal((n, 3))


def _assert_n_near(res, n_true):
    """N on each axis within 3.4 of its standard errors of the truth (SE from the 95 % interval,
    half-width / 1.96): two-sided 6.7e-4 per axis, ≤ 2e-3 for the three (a bare 95 % interval
    per axis would fail one test run in seven)."""
    for a in "xyz":
        lo, hi = res.axes[a].interval("arw_rad_per_sqrt_s")
        se = (hi - lo) / (2 * 1.96)
        z = (res.axes[a].all_terms()["arw_rad_per_sqrt_s"] - n_true) / se
        assert abs(z) < 3.4, (a, z)


def test_handled_start_and_end_are_cut_and_n_matches_the_still_part():
    """Motion (a 30 deg/s hand turn) in the first 20 s and the last 10 s of a 300-s white-noise
    record: the analysis runs on the still stretch and N is within its standard errors of the truth."""
    rng = np.random.default_rng(11)
    n = int(300 * RATE)
    t = np.arange(n) / RATE
    sigma = 2e-3  # rad/s per sample -> N = sigma / sqrt(rate)
    g = _white(rng, n, sigma)
    hand = np.deg2rad(30.0) * np.sin(2 * np.pi * 0.4 * t)
    moving = (t < 20.0) | (t > 290.0)
    g[moving, 0] += hand[moving]
    g[moving, 2] -= 0.5 * hand[moving]
    rec = Recording(t_s=t, gyro_rad_s=g)
    with pytest.warns(
        UserWarning, match=r"motion in \d+ of \d+ 2-s windows.*noise identified on the longest still stretch"
    ):
        res = AL.allan_analysis(rec, check_static=True)
    lo_s, hi_s = res.analysed_span_s
    assert 20.0 <= lo_s <= 24.5 and 285.5 <= hi_s <= 290.0  # one margin window at each end
    _assert_n_near(res, sigma / math.sqrt(RATE))
    assert res.to_json()["analysed_span_s"] == [lo_s, hi_s]


def test_still_record_with_a_false_reject_is_analysed_whole():
    """A still record is never cut: the number of rejected windows is what the gate's
    false-reject rate (1e-3 per window) explains, so the whole record is used, no warning."""
    rng = np.random.default_rng(3)
    n = int(600 * RATE)
    rec = Recording(t_s=np.arange(n) / RATE, gyro_rad_s=_white(rng, n, 1e-3))
    sp = AL.analysed_span(rec.gyro_rad_s, RATE)
    assert not sp.cut and (sp.start, sp.stop) == (0, n)
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = AL.allan_analysis(rec, check_static=True)
    assert not [w for w in caught if "motion" in str(w.message)]
    assert res.analysed_span_s is None and res.n_samples == n


def test_px4_sample_ulg_noise_from_its_still_part(shared_data, tmp_path, capsys):
    """PX4 sample.ulg (PROVENANCE: handheld ~8 s, then ~59 s stationary): `noise` on the converted
    log must give the numbers of its still part, not of the hand motion.

    Reference: the same analysis on the rows t >= 10 s cut by hand. The automatic stretch starts
    at the first still window after the motion (+ one margin window), so the two analyse nearly
    the same samples: their N agree to well inside N's 95 % interval (≈ ±3 %)."""
    rec = load_any(shared_data / "pyulog_samples" / "sample.ulg")
    p = tmp_path / "px4.csv"
    write_csv(rec, p)
    status, out, err = _gh(capsys, "noise", str(p), "--json")
    assert status == 0, err
    assert "noise identified on the longest still stretch" in err
    j = json.loads(out)
    assert j["analysed_span_s"][0] > 7.0
    cut = rec.slice(int(np.searchsorted(rec.t_s, 10.0)), rec.n)
    ref = AL.allan_analysis(cut)
    for a in "xyz":
        got = j["axes"][a]["arw_rad_per_sqrt_s"]
        lo, hi = ref.axes[a].interval("arw_rad_per_sqrt_s")
        # (the old code: 1.7e-2 rad/sqrt(s) on x, 59 deg/sqrt(h) — 500x the still part's)
        assert lo <= got <= hi, (a, lo, got, hi)
    # --t-from-s gives the user's own cut, with no warning
    status, out2, err2 = _gh(capsys, "noise", str(p), "--json", "--t-from-s", "10")
    assert status == 0 and "motion" not in err2
    j2 = json.loads(out2)
    assert j2["axes"]["x"]["arw_rad_per_sqrt_s"] == pytest.approx(
        ref.axes["x"].all_terms()["arw_rad_per_sqrt_s"], rel=1e-12
    )


def test_imutk_multipose_session_uses_its_initial_static_phase(shared_data, tmp_path, capsys):
    """IMU-TK's Xsens session: 50 s static, then ~37 hand-placed poses (45 % of the windows move).
    PROVENANCE: ADEV(1 s) ≈ 0.025 deg/s, i.e. N ≈ 0.025 deg/s/sqrt(Hz) = 4.4e-4 rad/sqrt(s) when white
    noise dominates at 1 s; the identified N must be within 20 % of it (the 1-s ADEV also holds a
    little of the other terms and PROVENANCE rounds to two digits), not the 0.019–0.031 rad/sqrt(s)
    of the whole session."""
    rec = load_any(shared_data / "imu_tk_xsens" / "xsens_gyro.mat")
    p = tmp_path / "xsens.csv"
    write_csv(rec, p)
    status, out, err = _gh(capsys, "noise", str(p), "--json")
    assert status == 0, err
    j = json.loads(out)
    assert j["analysed_span_s"][1] <= 51.0
    n_ref = np.deg2rad(0.025)
    for a in "xyz":
        assert j["axes"][a]["arw_rad_per_sqrt_s"] == pytest.approx(n_ref, rel=0.2)


def test_mostly_moving_record_is_refused_naming_its_longest_still_stretch(tmp_path, capsys):
    rng = np.random.default_rng(5)
    n = int(150 * RATE)
    t = np.arange(n) / RATE
    g = _white(rng, n, 2e-3)
    g[:, 1] += 0.5 * np.sin(2 * np.pi * 0.5 * t) * (t % 40 < 30)
    p = tmp_path / "moving.csv"
    write_csv(Recording(t_s=t, gyro_rad_s=g), p)
    status, _o, err = _gh(capsys, "noise", str(p))
    assert status == 2 and err.startswith("error: recording is not static: the motion gate rejects")
    assert "longest still stretch" in err and "--t-from-s" in err and len(err.strip().splitlines()) == 1


def test_batch_allan_cuts_a_moving_start(tmp_path, capsys):
    """`batch allan` runs the same gate as `allan` (it ran none: a handled file entered the
    fleet table with its motion in the ARW)."""
    rng = np.random.default_rng(8)
    n = int(200 * RATE)
    t = np.arange(n) / RATE
    sigma = 2e-3
    g = _white(rng, n, sigma)
    g[t < 15.0, 0] += np.deg2rad(40.0) * np.sin(2 * np.pi * 0.3 * t[t < 15.0])
    write_csv(Recording(t_s=t, gyro_rad_s=g), tmp_path / "a.csv")
    status, out, err = _gh(
        capsys, "batch", "allan", str(tmp_path / "a.csv"), "-o", str(tmp_path / "fleet.csv"), "--workers", "0", "--json"
    )
    assert status == 0, err
    import pandas as pd

    row = pd.read_csv(tmp_path / "fleet.csv").iloc[0]
    assert "noise identified on the longest still stretch" in row["warnings"]
    assert row["arw_x_rad_per_sqrt_s"] == pytest.approx(sigma / math.sqrt(RATE), rel=0.05)  # N's 95 % CI ≈ ±2 %


def test_one_turn_in_a_long_still_log_is_not_taken_for_a_false_reject():
    """A single 2-s hand turn in the middle of a 10-min still log: one rejected window of 300 is
    what the 1e-3 gate's false rejects explain (P ≈ 0.26), but not the strict gate's (3e-4); the
    longer still half is analysed and N is within its standard errors of the truth."""
    rng = np.random.default_rng(21)
    n = int(600 * RATE)
    t = np.arange(n) / RATE
    sigma = 1e-3
    g = _white(rng, n, sigma)
    turn = (t >= 250.0) & (t < 252.0)
    g[turn, 2] += np.deg2rad(90.0) * np.sin(np.pi * (t[turn] - 250.0) / 2.0) ** 2
    with pytest.warns(UserWarning, match="noise identified on the longest still stretch"):
        res = AL.allan_analysis(Recording(t_s=t, gyro_rad_s=g), check_static=True)
    assert res.analysed_span_s[0] >= 252.0
    _assert_n_near(res, sigma / math.sqrt(RATE))


def test_short_flight_log_is_refused(tmp_path, capsys):
    """ArduCopter's IMU stream at 25 Hz, 12.7 s of flight (tests/data/dataflash): fewer than ten
    2-s windows used to skip the gate, and the flight's motion was identified as noise."""
    from pathlib import Path

    src = Path(__file__).resolve().parents[2] / "data" / "dataflash" / "ArduCopter-4.5.7_00000081_first650k.BIN"
    p = tmp_path / "df.csv"
    write_csv(load_any(src), p)
    status, _o, err = _gh(capsys, "noise", str(p))
    assert status == 2 and "recording is not static" in err


def test_paused_log_uses_the_rate_of_its_samples_not_the_wall_span(shared_data, tmp_path, capsys):
    """tomisuarez2's 449-s still log with a 300-s pause in the middle (a logger stopped, two
    recordings appended): the Allan time base was the mean rate (N-1)/duration = 60 Hz, and N came
    out 29 % high (sqrt(750/449)) with only a warning. Now the rate of the intervals without gaps
    (100 Hz): the same N as the log without the pause."""
    rec = load_any(shared_data / "tomisuarez2_mpu6050" / "example_data_tinit_calc.csv")
    ref = AL.allan_analysis(rec)
    t = rec.t_s.copy()
    t[t.size // 2 :] += 300.0
    p = tmp_path / "paused.csv"
    write_csv(Recording(t_s=t, gyro_rad_s=rec.gyro_rad_s), p)
    status, out, err = _gh(capsys, "noise", str(p), "--json")
    assert status == 0 and "gap" in err
    j = json.loads(out)
    assert j["rate_hz"] == pytest.approx(100.0, rel=1e-9)
    for a in "xyz":
        assert j["axes"][a]["arw_rad_per_sqrt_s"] == pytest.approx(
            ref.axes[a].all_terms()["arw_rad_per_sqrt_s"], rel=1e-9
        )


def test_gyro_only_file_in_deg_s_labelled_rad_s_warns(shared_data, tmp_path, capsys):
    """A gyro-only still log whose deg/s numbers sit under rad/s headers: the reader's unit check
    needs accel columns to know the sensor is at rest, so `noise` reported N 57x too large
    (tomisuarez2: 25.7 deg/sqrt(h) for 0.45) without a word; the motion gate now says it is at
    rest, and a per-sample noise above 0.05 rad/s there gets one warning."""
    rec = load_any(shared_data / "tomisuarez2_mpu6050" / "example_data_tinit_calc.csv")
    p = tmp_path / "degs.csv"
    write_csv(Recording(t_s=rec.t_s, gyro_rad_s=np.rad2deg(rec.gyro_rad_s)), p)
    status, _o, err = _gh(capsys, "noise", str(p))
    assert status == 0 and "is it deg/s labelled rad/s" in err
    status, _o, err = _gh(capsys, "bias", str(p))  # the same check on the bias window
    assert status == 0 and "is it deg/s labelled rad/s" in err
    q = tmp_path / "rads.csv"
    write_csv(Recording(t_s=rec.t_s, gyro_rad_s=rec.gyro_rad_s), q)
    for cmd in ("noise", "bias"):
        status, _o, err = _gh(capsys, cmd, str(q))
        assert status == 0 and "labelled rad/s" not in err
