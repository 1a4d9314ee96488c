"""Host-clock jitter is not a gap (gyrocore.data.checks.gap_threshold_s).

A logger that stamps samples on receipt (an Arduino read over serial, a phone app) gives
intervals T + e_{i+1} − e_i: long ones mirrored by short ones. Before, every interval above
1.5 × median was a "gap": ±4 ms of jitter at 100 Hz gave 666 "gaps" in tomisuarez2's 100-s
static log and `noise` ran at the rate of "the intervals without gaps", 104.5 Hz instead of
100 (N 2 % low, silently). Now they are jitter (a warning says so), the rate is the mean
rate, and a real pause in a jittered log is still a gap.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from gyrocore.data.checks import gap_threshold_s
from gyrocore.data.recording import read_csv
from gyrocore.errors import RepairWarning
from gyrocore.readers.common import timing_report
from tests.gyrocore.test_bad_input import gh

T_S = 0.01  # 100 Hz
N = 10_000


def _jittered(seed: int, sigma_s: float, n: int = N) -> np.ndarray:
    """Receipt times of an even 100-Hz stream, iid Gaussian latency of σ (sorted: a host
    receives in order)."""
    rng = np.random.default_rng(seed)
    return np.sort(np.arange(n) * T_S + 0.02 + rng.normal(0.0, sigma_s, n))


def test_clean_clock_keeps_one_and_a_half_median():
    t = np.arange(N) * T_S
    t[5000:] += 3 * T_S  # three samples lost
    d = np.diff(t)
    assert gap_threshold_s(d, float(np.median(d))) == pytest.approx(1.5 * T_S)
    assert timing_report(t).n_gaps == 1


def test_gaussian_jitter_is_no_gap_but_a_pause_is():
    # σ = 2 ms: intervals σ·√2 = 2.83 ms about 10 ms; P(d > 1.5 T) = P(z > 1.77) = 3.8 % → ~380
    # "gaps" under the old rule. Threshold T + 2·(T − q_0.001) ≈ T + 2·3.09·2.83 ms = 27.5 ms:
    # P(z > 6.2) ≈ 3e-10 per interval, none expected in 10⁴ (the seed only picks one draw)
    t = _jittered(1, 0.002)
    d = np.diff(t)
    assert np.count_nonzero(d > 1.5 * np.median(d)) > 200  # the old rule's false gaps
    assert timing_report(t).n_gaps == 0
    t2 = t.copy()
    t2[6000:] += 30.0  # a 30-s pause
    assert timing_report(t2).n_gaps == 1


def _write(path, t, gyro):
    body = "\n".join(",".join(f"{float(v)!r}" for v in (a, *g)) for a, g in zip(t, gyro))
    path.write_text("t_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n" + body + "\n")
    return path


def test_read_csv_says_jitter_not_gaps(tmp_path):
    rng = np.random.default_rng(2)
    t = _jittered(3, 0.002, 2000)
    p = _write(tmp_path / "j.csv", t, rng.normal(0, 1e-3, (t.size, 3)))
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always", RepairWarning)
        read_csv(p)
    msgs = " | ".join(str(x.message) for x in w)
    assert "timestamps jitter" in msgs and "gaps longer" not in msgs, msgs


def test_noise_rate_of_a_jittered_log_is_the_mean_rate(capsys, tmp_path):
    """The same white noise on a uniform grid and on jittered receipt times: same rate, same N."""
    rng = np.random.default_rng(4)
    gyro = rng.normal(0.0, 2e-3, (N, 3))  # white: N = σ/√rate = 2e-4 rad/√s
    t_even = np.arange(N) * T_S
    t_jit = t_even + 0.02 + np.random.default_rng(5).uniform(-0.004, 0.004, N)
    t_jit.sort()  # ±4 ms uniform latency: intervals 2-18 ms, the old rule's 104.5 Hz
    out = {}
    for name, t in (("even", t_even), ("jit", t_jit)):
        s, o, err = gh(capsys, "noise", _write(tmp_path / f"{name}.csv", t, gyro), "--json", "--method", "adev")
        assert s == 0, err
        out[name] = json.loads(o)
    # mean rate (N−1)/duration: the latency's end points move it by ≤ 8 ms over 100 s (8e-5)
    assert out["jit"]["rate_hz"] == pytest.approx(100.0, rel=1e-4)
    for ax in "xyz":
        a, b = (out[k]["axes"][ax]["arw_rad_per_sqrt_s"] for k in ("even", "jit"))
        assert b == pytest.approx(a, rel=1e-4)  # same samples, rates equal to 1e-4: N ∝ 1/√rate


@pytest.mark.parametrize("tick_s", [0.015625, 0.02])  # Windows' 64-Hz clock; a 20-ms host stamp
def test_coarse_clock_keeps_every_sample(capsys, tmp_path, tick_s):
    """A 100-Hz stream stamped by a clock that ticks every 15.6 or 20 ms repeats a third to a
    half of its stamps. Dropping the repeats (the rule for a time that repeats) lost those
    samples and put `noise` at 64 or 50 Hz with N 25-41 % high; now every row is kept on a
    uniform grid at the mean rate, and N is the evenly stamped file's."""
    rng = np.random.default_rng(6)
    gyro = rng.normal(0.0, 2e-3, (N, 3))
    t_even = np.arange(N) * T_S
    t_coarse = np.floor(t_even / tick_s) * tick_s
    assert np.count_nonzero(np.diff(t_coarse) == 0) > 0.3 * N
    with pytest.warns(RepairWarning, match=r"timestamps repeat the previous one .*all rows kept, on a uniform grid"):
        rec = read_csv(_write(tmp_path / "coarse.csv", t_coarse, gyro))
    assert rec.n == N and np.array_equal(rec.gyro_rad_s, gyro)
    # the grid spans first to last stamp: the last is floored by < one tick, rate off by < tick/T
    assert rec.rate_hz == pytest.approx(100.0, rel=tick_s / (N * T_S))
    out = {}
    for name, t in (("even", t_even), ("coarse", t_coarse)):
        s, o, err = gh(capsys, "noise", _write(tmp_path / f"{name}.csv", t, gyro), "--json", "--method", "adev")
        assert s == 0, err
        out[name] = json.loads(o)
    for ax in "xyz":
        a, b = (out[k]["axes"][ax]["arw_rad_per_sqrt_s"] for k in ("even", "coarse"))
        assert b == pytest.approx(a, rel=1e-3)  # same samples; rate within tick/T = 2e-4: N ∝ 1/√rate


def test_rows_written_twice_are_still_dropped(tmp_path):
    """A repeated time with the same gyro values is a row written twice, not a coarse clock."""
    t = np.arange(300) * T_S
    gyro = np.random.default_rng(7).normal(0, 1e-3, (300, 3))
    idx = np.sort(np.concatenate([np.arange(300), np.arange(0, 300, 10)]))  # every 10th row twice
    with pytest.warns(RepairWarning, match="dropped 30 rows whose timestamp goes backwards or repeats"):
        rec = read_csv(_write(tmp_path / "twice.csv", t[idx], gyro[idx]))
    assert rec.n == 300 and np.array_equal(rec.t_s, t)
