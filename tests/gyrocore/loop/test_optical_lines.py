"""Lines under an optical attitude reference: the reference differentiated,
the sample-level residual, the pooled harmonic F on gap-free segments, a line the gyro
carries and the reference lacks described as periodic[f], one both carry not reported."""

import numpy as np
import pytest

from experiments.optical_lines import (
    DEG,
    RATE_HZ,
    line_z,
    optical_recording,
    residual_psd,
    taper_efficiency,
    trial,
)
from gyrocore.loop import lines as LN
from gyrocore.attitude import attitude_rate, integrate_gyro, rate_error_vs_attitude
from gyrocore.loop.loop import run_loop
from gyrocore.loop.model import advance
from gyrocore.loop.open_step import attitude_line_series
from gyrocore.loop.validate import split_halves, validate_model


def test_attitude_rate_inverts_the_integration_and_skips_dropouts():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.003, 0.005, 500))
    w = rng.normal(0.0, 2.0, (500, 3))
    q = integrate_gyro(t, w)
    q[100:110] = np.nan
    w_ref, ok = attitude_rate(t, q)
    assert not ok[0] and not ok[100:111].any() and ok[111:].all()
    np.testing.assert_allclose(w_ref[ok], w[ok], atol=1e-9)  # exact inverse (backward hold)
    d = np.array([0.01, -0.02, 0.015])
    e, w2, ok2 = rate_error_vs_attitude(t, q, w + d)
    # rotvec(exp(−a)·exp(a + dΔt))/Δt = J(a)·d with J = I − ½[a]× + O(|a|²), a = ωΔt: the
    # error differs from d by at most ½|a|·|d| (+ second order) — here |a| ≲ 0.04 rad
    a = np.linalg.norm(w * np.diff(t, prepend=np.nan)[:, None], axis=1)
    dev = np.linalg.norm(e - d, axis=1)
    assert np.all(dev[ok2] <= 0.5 * a[ok2] * np.linalg.norm(d) * 1.05 + 1e-12)
    assert np.abs(np.mean(e[ok2], axis=0) - d).max() < 1e-4  # the cross terms average out
    assert np.isnan(e[~ok2]).all()


def test_even_segments_never_straddle_a_gap():
    t = np.arange(3000) / 200.0
    t[1500:] += 0.02  # a timestamp gap (4 frames dropped)
    ok = np.ones(3000, bool)
    ok[700:720] = False  # tracking lost
    idx, L = LN.even_segments(t, ok, n_target=4, min_len=128)
    assert idx.size % L == 0 and idx.size >= 0.75 * 2980
    for s in range(idx.size // L):
        seg = idx[s * L : (s + 1) * L]
        assert np.all(np.diff(seg) == 1) and ok[seg].all()
        assert np.allclose(np.diff(t[seg]), 1 / 200.0)
        assert seg[0] > 0 and not (seg[0] <= 1500 <= seg[-1] and seg[0] != 1500)


def test_reference_noise_psd_matches_the_derivation():
    # 8 σ_q² fs sin²(πf/fs): the white attitude noise differenced, measured by Welch
    from scipy import signal

    rng = np.random.default_rng(1)
    fs, sq = 240.0, 0.001
    eps = rng.normal(0.0, sq, 2**18)
    f, P = signal.welch(np.diff(eps) * fs, fs=fs, nperseg=1024)
    pred = residual_psd(f, rate_hz=fs, sigma_q_rad=sq, arw_rad_per_sqrt_s=0.0)
    sel = (f > 5) & (f < 115)
    # Welch with 512 segments of 1024 (50 % overlap, Hann): relative σ of each bin ≈ 1/√(≈ 470)
    # ≈ 0.046; over the band the mean ratio is within 2 %
    assert abs(np.mean(P[sel] / pred[sel]) - 1) < 0.02


# seeds 0-5 at z ∈ [10, 10.5]: z = A/σ_A, σ_A² = S(f)/(T_eff·ΣU²/L) on the loop's own segments —
# the noncentrality √λ of its harmonic F (experiments/optical_lines.py). The phase-coherent
# F(2, 12S), S ≈ 15-18, at the Bonferroni level α/6/3/2 over ≈ 23 000 fine frequencies (1.2e-8
# per frequency: F_c ≈ 20, i.e. √(2F_c) ≈ 6.3σ) has power 0.9998 at √λ = 10, 0.9995 with the
# worst grid offset (1/8 of 1/T: √λ·0.974) (scipy.stats.ncf). Every seed must be described.
@pytest.mark.parametrize("seed", range(6))
def test_gyro_line_absent_from_the_reference_is_described(seed):
    tr = trial(seed, z_range=(10.0, 10.5))
    assert tr.z >= 10.0
    assert tr.described, tr
    # within the record's frequency resolution 1/T (T ≈ 60 s); the Cramér–Rao σ_f at z = 10 is
    # √6/(2π·z·T) ≈ 7e-4 Hz
    assert abs(tr.f_found_hz - tr.f_hz) <= 1.0 / 60.0
    assert tr.others == ()


def test_line_amplitude_removed_and_scored_on_the_held_out_half():
    f, amp = 40.5366, 1.455 * DEG
    rec = optical_recording(seed=3, line_axis=0, line_hz=f, line_amp_rad_s=amp)
    first, second = split_halves(rec)
    r = run_loop(first, declared=["bias", "time_offset"], candidates=["bias_ramp"])
    (u,) = r.unexplained
    assert u.kind == "periodic" and u.axis == "x"
    assert u.evidence["residual"] == "sample" and u.evidence["segments"]["n"] >= 4
    # amplitude within 5 σ_A of the truth (σ_A from the derivation, on the half record)
    sA = amp / line_z(
        amp,
        f,
        u.evidence["segments"]["n"] * u.evidence["segments"]["length"] / RATE_HZ,
        u.evidence["segments"]["length"],
    )
    assert abs(u.fields["amplitude_rad_s"] - amp) < 5 * sA
    from gyrocore.loop.validate import loop_parameters

    p_after, _ = loop_parameters(r, first)
    base = run_loop(first, declared=["bias", "time_offset"], candidates=[], open_search=False)
    p_before, _ = loop_parameters(base, first)
    v = validate_model(second, params_after=p_after, params_before=p_before, reference="attitude")
    (pv,) = v["periodic"]
    before, after = pv["amplitude_before_rad_s"][0], pv["amplitude_after_rad_s"][0]
    se = pv["amplitude_std_error_after_rad_s"][0]
    assert abs(before - amp) < 5 * se  # the line is in the held-out half ...
    # ... and removed from it up to the frequency's extrapolation: the half-record estimate's
    # σ_f ≈ √6/(2π·z·T/2) carried over the next 30 s leaves ≤ 2π·σ_f·30 s·A ≈ 0.3·A at 1σ (z ≈ 7)
    assert after < 0.5 * before


def test_line_the_reference_also_carries_is_not_reported():
    # a rotation at 47.3 Hz of 0.5 rad/s: in the truth, so in the gyro and the reference. The
    # point-sampled gyro against the reference's interval-mean rate leaves part of it in the
    # residual (|1 − sinc(fΔt)| after the half-frame advance), which the motion mask excludes
    rec = optical_recording(seed=1, shared_hz=47.3, shared_amp_rad_s=0.5)
    r = run_loop(rec, declared=["bias", "time_offset"], candidates=["bias_ramp"])
    assert not [u for u in r.unexplained if u.kind == "periodic"]
    per = [p for p in r.open_search["periodic"] if p["level"] == "sample"]
    assert per and all(p["masked_by_motion_bins"] > 0 for p in per)
    # control: the same residual screened without the motion mask has the line, far past the
    # threshold — so the test above can fail
    tau = r.params["time_offset"]["tau_s"][0]
    x, tt, fs, mot, _, _, L = attitude_line_series(advance(rec, tau), np.zeros((rec.n, 3)), LN.AttitudeLineOptions())
    bare = LN.screen_lines(x, fs, seg_max=L)
    assert bare[0].axis == 0 and abs(bare[0].frequency_hz - 47.3) < 0.5
    assert bare[0].log10_p < np.log10(per[0]["threshold"]) - 3


def test_null_optical_recording_reports_no_line():
    r = run_loop(optical_recording(seed=7), declared=["bias", "time_offset"], candidates=["bias_ramp"])
    assert r.unexplained == ()
    assert any(p["level"] == "sample" for p in r.open_search["periodic"])


def test_taper_efficiency_is_near_one():
    # ΣU_k(0)² over the 7 tapers of NW = 4 captures nearly all of a constant's energy
    assert 0.95 < taper_efficiency(2048) <= 1.0


def _segmented_noise(rng, S, L, gap_max, C=1):
    """S segments of L white samples (fs = 1) whose starts are separated by random gaps."""
    starts = np.cumsum(np.concatenate([[0], L + rng.integers(1, gap_max, S - 1)])).astype(float)
    return rng.normal(size=(S * L, C)), starts


def test_coherent_f_is_f_2_12s_under_the_null_and_noncentral_f_with_a_line():
    # 150 draws of 6 segments of 512 white samples with random gaps; 15 frequencies 3W apart per
    # draw (W = 4/512: nearly independent). The null F must be F(2, 72); with a line of λ = 100
    # placed on the fine grid it must be noncentral F(2, 72; 100). KS at the 1e-3 level:
    # D < 1.95/√n (n = 2250: 0.041; n = 150: 0.16) — the coherent statistic is exact, not
    # approximate, so the test holds at any seed
    from scipy import stats

    rng = np.random.default_rng(11)
    S_, L = 6, 512
    W = 4.0 / L
    Fnull, Fline = [], []
    for _ in range(150):
        x, t0 = _segmented_noise(rng, S_, L, 300)
        h = LN.coherent_harmonic_f(x, 1.0, t0)
        df = h.freq_hz[1] - h.freq_hz[0]
        js = [int(round(f / df)) - 1 for f in np.arange(0.06, 0.44, 3 * W)[:15]]
        Fnull += list(h.F[js, 0])
        # a line of amplitude A on a fine-grid frequency: λ = A²·ΣU²·S/(2·σ²) with fs = 1
        f0 = h.freq_hz[js[5]]
        tt = np.concatenate([t0[s] + np.arange(L) for s in range(S_)])
        from experiments.optical_lines import taper_efficiency

        A = 10.0 / np.sqrt(taper_efficiency(L) * L * S_ / 2.0)
        xl = x + A * np.cos(2 * np.pi * f0 * tt + rng.uniform(0, 2 * np.pi))[:, None]
        Fline.append(LN.coherent_harmonic_f(xl, 1.0, t0).F[js[5], 0])
    assert h.df1 == 2 and h.df2 == 12 * S_
    assert stats.kstest(Fnull, stats.f(2, 12 * S_).cdf).statistic < 1.95 / np.sqrt(len(Fnull))
    assert stats.kstest(Fline, stats.ncf(2, 12 * S_, 100.0).cdf).statistic < 1.95 / np.sqrt(len(Fline))
    # the pooled statistic of the same data has the same λ in 2S numerator degrees of freedom
    hp = LN.harmonic_f_test(xl, 1.0, seg_max=L)
    assert hp.df1 == 2 * S_


def test_reference_mask_level_is_per_frequency():
    # white "reference motion", 3 columns of 8 × 1024: the per-bin level 1e-4 masks a frequency
    # with probability ≈ 1 − (1 − 1e-4)^(64·3) ≈ 1.9 % (64 padded bins in ±2W); the per-frequency
    # level 1e-3 (Bonferroni over those bins and columns) at most 0.1 %. Masks come in chunks of
    # 64 bins of 2048: over 30 draws the per-frequency level gives Poisson(≤ 0.94) chunks
    # (P(≥ 6) < 1e-3), the per-bin level ≈ 19 (P(< 8) < 1e-3)
    from gyrocore.loop.lines import _motion_mask

    L = 1024
    f = np.fft.rfftfreq(4 * L, 1.0)[1:]
    chunks = {False: 0.0, True: 0.0}
    for seed in range(30):
        m = np.random.default_rng([seed, 7]).normal(size=(8 * L, 3))
        for fw, lev in ((False, 1e-4), (True, 1e-3)):
            chunks[fw] += _motion_mask(m, 1.0, f, 4.0 / L, p_mask=lev, seg_max=L, family_wise=fw).sum() / 64
    assert chunks[True] < 6 and chunks[False] >= 8


def test_coherent_reference_mask_level_is_per_frequency():
    # the same with the coherent statistic of the reference on its fine grid: Bonferroni over
    # the fine bins within ±2W and the columns, P(a frequency masked by noise) ≤ 1e-3; a mask is
    # ≥ 4W/(fs/2) = 3.1 % of the band here, so the bound allows a masked fraction ≤ 1e-3 on
    # average: over 30 draws ≤ 5 hit draws (Poisson(≤ 0.97), P(≥ 6) < 1e-3)
    from gyrocore.loop.lines import _motion_mask_coherent

    L, S_ = 1024, 8
    hits = 0
    for seed in range(30):
        rng = np.random.default_rng([seed, 7])
        m, starts = _segmented_noise(rng, S_, L, 300, C=3)
        f = LN.coherent_harmonic_f(m[:, :1], 1.0, starts).freq_hz
        hits += bool(_motion_mask_coherent(m, 1.0, starts, f, 4.0 / L, p_mask=1e-3).any())
    assert hits <= 5


def test_line_only_the_reference_carries_is_not_reported():
    # a 55-Hz oscillation of the reference alone (marker jitter, an artefact of the tracker):
    # −line in the residual at √λ ≈ 12, the same line in the differentiated reference — masked
    from dataclasses import replace

    from gyrocore.attitude import qmul

    rec = optical_recording(seed=4)
    ser = attitude_line_series(rec, np.zeros((rec.n, 3)), LN.AttitudeLineOptions())
    f = 55.3
    A = 12.0 / line_z(1.0, f, ser[5].size / RATE_HZ, ser[6])
    th = A / (2 * np.pi * f) * np.sin(2 * np.pi * f * rec.t_s)  # rotation about x of rate A·cos
    dq = np.column_stack([np.cos(th / 2), np.sin(th / 2), np.zeros(rec.n), np.zeros(rec.n)])
    rec2 = replace(rec, ref_quat_wxyz=qmul(rec.ref_quat_wxyz, dq))
    r = run_loop(rec2, declared=["bias", "time_offset"], candidates=["bias_ramp"])
    assert not [u for u in r.unexplained if u.kind == "periodic"]
    # control: unmasked, the residual has it far past the threshold
    x, tt, fs, mot, _, _, L = attitude_line_series(rec2, np.zeros((rec.n, 3)), LN.AttitudeLineOptions())
    bare = LN.screen_lines(x, fs, seg_max=L, seg_start_s=tt[::L], statistics=("coherent",))
    assert bare[0].axis == 0 and abs(bare[0].frequency_hz - f) < 0.05 and bare[0].log10_p < np.log10(2.8e-4) - 3


def test_band_limited_advance_keeps_a_line_near_nyquist():
    from scipy.interpolate import CubicSpline

    fs = 240.0
    t = np.arange(6000) / fs
    t[3000:] += 2 / fs  # a timestamp gap: NaN within 16 samples of it
    tau = -0.48 / fs
    for f in (20.0, 80.0, 96.0):  # ≤ 0.4·fs: Kaiser-sinc gain 1 ± 1e-4 (its design)
        x = np.cos(2 * np.pi * f * t)[:, None]
        y = LN.band_limited_advance(t, x, tau)[:, 0]
        ok = np.isfinite(y)
        assert ok.sum() >= 6000 - 4 * 16 and not ok[2990:3010].any()
        assert np.abs(y[ok] - np.cos(2 * np.pi * f * (t[ok] + tau))).max() < 1e-3
    # the cubic spline the loop's time-offset advance uses: gain ≈ 0.88 at fs/3 (control)
    x = np.cos(2 * np.pi * 80.0 * t[:3000])
    ys = CubicSpline(t[:3000], x)(t[:3000] + tau)[200:-200]
    assert np.sqrt(2 * np.mean(ys**2)) < 0.9


def test_accelerometer_sharing_the_line_does_not_mask_it():
    # a vibrating attachment: the gyro's 40.5-Hz line and a 2 m/s² line of the specific force at
    # the same frequency; the optical reference lacks both. Only the reference's lines are
    # excluded: described; with the specific force among the masking columns it is lost (control)
    from dataclasses import replace

    f, amp = 40.5366, 1.455 * DEG
    rec = optical_recording(seed=3, line_axis=0, line_hz=f, line_amp_rad_s=amp)
    acc = np.zeros((rec.n, 3))
    acc[:, 2] = 9.81 + 2.0 * np.cos(2 * np.pi * f * rec.t_s)
    rec = replace(rec, accel_m_s2=acc)
    r = run_loop(rec, declared=["bias", "time_offset"], candidates=["bias_ramp"])
    assert [u.axis for u in r.unexplained if u.kind == "periodic"] == ["x"]
    r2 = run_loop(
        rec,
        declared=["bias", "time_offset"],
        candidates=["bias_ramp"],
        attitude_lines=LN.AttitudeLineOptions(mask_accel=True),
    )
    assert not [u for u in r2.unexplained if u.kind == "periodic"]


def test_attitude_line_options_are_passed_in_and_checked():
    from gyrocore.errors import GyroInputError

    rec = optical_recording(seed=3, line_axis=0, line_hz=40.5366, line_amp_rad_s=1.455 * DEG)
    r = run_loop(
        rec,
        declared=["bias", "time_offset"],
        candidates=["bias_ramp"],
        attitude_lines=LN.AttitudeLineOptions(segments=3),
    )
    (u,) = r.unexplained
    assert u.evidence["segments"]["n"] < 15  # default (8, dropouts): 15-18 segments of ≈ 570
    assert "phase-coherent" in u.evidence["test"]
    for bad in ({"statistic": "best"}, {"segments": 0}, {"mask_level": 0.0}):
        with pytest.raises(GyroInputError):
            LN.AttitudeLineOptions(**bad)


def test_reference_on_rows_slerps_frames_and_stops_at_dropouts():
    # a 120-Hz reference beside a 1-kHz gyro, NaN between frames and held: the same frames, put on
    # the rows by slerp (the rate between two frames constant), NaN across a dropout, a sign flip
    # between frames no rotation
    from experiments.optical_lines import slow_reference_recording

    kw = dict(seed=5, duration_s=6.0, gaps=2, sign_flips=True)
    rec_nan = slow_reference_recording(fill="nan", **kw)
    rec_hold = slow_reference_recording(fill="hold", **kw)
    q_nan, f_nan = LN.reference_on_rows(rec_nan.t_s, rec_nan.ref_quat_wxyz)
    q_hold, f_hold = LN.reference_on_rows(rec_hold.t_s, rec_hold.ref_quat_wxyz)
    # the tracker's rate from its frame grid (the stamps' median interval would say 8 rows, 125 Hz)
    assert abs(f_nan - 120.0) < 1e-3 and f_hold == f_nan
    ok = np.isfinite(q_nan[:, 0])
    assert np.array_equal(ok, np.isfinite(q_hold[:, 0])) and np.allclose(q_nan[ok], q_hold[ok])
    # no sign flip turns into a 2π rotation: the rate stays that of the tumbling (≲ 2.4 rad/s)
    w, valid = attitude_rate(rec_nan.t_s, q_nan)
    assert valid.mean() > 0.9 and np.nanmax(np.abs(w)) < 5.0
    fr = np.isfinite(rec_nan.ref_quat_wxyz[:, 0])
    fi = np.flatnonzero(fr)
    # a dropout (> 1.5 frame intervals between frames) stays NaN: nothing invented across it
    big = np.flatnonzero(np.diff(fi) > 1.5 * 8.34)
    assert big.size >= 2 and all(not ok[fi[k] + 1 : fi[k + 1]].any() for k in big)
    # a reference already on the rows is returned as it is
    rec = optical_recording(seed=1, duration_s=5.0)
    q, f = LN.reference_on_rows(rec.t_s, rec.ref_quat_wxyz)
    assert q is rec.ref_quat_wxyz


def test_frame_stamps_rounded_to_rows_are_put_back_on_the_trackers_grid():
    # 120-Hz frames stamped on a 1-kHz gyro's rows (rounded: 8, 8, 9 rows), frames dropped: the
    # straight line in the frame count recovers the tracker's times to rounding; stamps that wander
    # by more than a row (an irregular tracker) are kept as they are
    from gyrocore.loop.lines import _regular_frame_times

    rng = np.random.default_rng(4)
    t_true = 0.0123 + np.arange(2000) / 120.0
    keep = np.ones(t_true.size, bool)
    keep[[50, 51, 52, 700, 1400, 1401]] = False
    stamps = np.rint(t_true[keep] * 1000.0) / 1000.0
    err = _regular_frame_times(stamps, 1e-3) - t_true[keep]
    # the line's end-to-end error from a least-squares fit of N stamps with rounding noise
    # σ = row/√12: ≈ σ·√(12/N) = row/√N = 22 µs here; allowed 4× that, ≪ the ±500 µs rounding it
    # removes (measured: 1.4 µs). A constant offset remains, the mean of the rounding over the
    # 3-frame pattern, |·| ≤ row/(2·3) (a time offset, the loop's to fit)
    assert np.ptp(err) < 4e-3 / np.sqrt(stamps.size) and abs(err.mean()) <= 1e-3 / 6
    assert np.max(np.abs(stamps - t_true[keep])) > 3e-4  # control: the stamps were 0.33 ms off
    wander = stamps + rng.integers(-3, 4, stamps.size) * 1e-3
    assert np.array_equal(_regular_frame_times(wander, 1e-3), wander)


# NaN between frames and held give the same slerped reference (test above): one of each
@pytest.mark.parametrize(("fill", "line_hz"), [("hold", 40.3), ("nan", 300.3)])
def test_reference_slower_than_the_gyro_finds_the_gyro_line(fill, line_hz):
    # a 120-Hz tracker beside a 1-kHz gyro (NaN between frames or each frame held, frame
    # exposures jittered ±0.5 ms, dropped frames, q or −q per frame) with a 3 °/s gyro line below /
    # above the tracker's Nyquist frequency (60 Hz). Slerped onto the rows, the reference carries
    # neither. The residual's PSD (experiments.optical_lines.residual_psd, ref_rate_hz=120: the
    # reference's differenced noise held over each frame) is 1.35e-4 (rad/s)²/Hz at 40 Hz and
    # 4.3e-6 at 300 Hz (sinc² of the hold); stamp jitter adds ≈ 27 % (σ_eq = ω_rms·J/√3 ≈ 2.7e-4
    # rad beside σ_q = 5.2e-4). σ_A = √(S/T_eff), T_eff ≈ 50 s: 0.11 °/s at 40 Hz, 0.019 °/s at
    # 300 Hz, so 3 °/s is ≈ 28σ / 150σ (the test's threshold ≈ 6.3σ). Before: the sample level was
    # not run on a NaN-between-frames reference (nothing found), and a held one was
    # differentiated into a pulse train (a 0.3 °/s line at 300 Hz, ≈ 15σ here, missed).
    from experiments.optical_lines import slow_reference_recording

    rec = slow_reference_recording(
        seed=2,
        line_axis=0,
        line_hz=line_hz,
        line_amp_rad_s=3.0 * DEG,
        fill=fill,
        frame_jitter_s=5e-4,
        gaps=5,
        sign_flips=True,
    )
    r = run_loop(rec, declared=["bias", "time_offset"], candidates=["bias_ramp"])
    assert "periodic_sample_level" not in r.open_search
    (u,) = [u for u in r.unexplained if u.kind == "periodic"]
    assert u.axis == "x" and abs(u.fields["frequency_hz"] - line_hz) <= 1.0 / 60.0
    assert r.unexplained == (u,)


def test_slow_reference_images_are_not_reported():
    # no line: the slerped reference's rate is a staircase, whose images of the tumbling motion
    # at k·120 ± (0.1-1.5) Hz are in the residual; they are lines of the reference, masked. Control:
    # unmasked, the residual's strongest line is such an image, far past the threshold.
    from experiments.optical_lines import slow_reference_recording

    rec = slow_reference_recording(seed=3, fill="hold", frame_jitter_s=5e-4, gaps=5, sign_flips=True)
    r = run_loop(rec, declared=["bias", "time_offset"], candidates=["bias_ramp"])
    assert r.unexplained == ()
    x, tt, fs, mot, _, _, L = attitude_line_series(rec, np.zeros((rec.n, 3)), LN.AttitudeLineOptions())
    bare = LN.screen_lines(x, fs, seg_max=L, seg_start_s=tt[::L], statistics=("coherent",))
    near = [b for b in bare if min(abs(b.frequency_hz - k * 120.0) for k in (1, 2, 3, 4)) < 2.0]
    assert near and min(b.log10_p for b in near) < np.log10(2.8e-4) - 3, bare


def test_quaternion_sign_flips_change_nothing():
    # q and −q per frame at random: the same attitude, so the same loop result to rounding
    rec = optical_recording(seed=3, line_axis=1, line_hz=47.3, line_amp_rad_s=2.0 * DEG)
    flip = optical_recording(seed=3, line_axis=1, line_hz=47.3, line_amp_rad_s=2.0 * DEG, sign_flips=True)
    ok = np.isfinite(rec.ref_quat_wxyz[:, 0])
    assert (np.sign(flip.ref_quat_wxyz[ok, 0]) != np.sign(rec.ref_quat_wxyz[ok, 0])).mean() > 0.4
    r0 = run_loop(rec, declared=["bias", "time_offset"], candidates=["bias_ramp"])
    r1 = run_loop(flip, declared=["bias", "time_offset"], candidates=["bias_ramp"])
    assert [u.effect for u in r1.unexplained] == [u.effect for u in r0.unexplained] != []
    assert np.isclose(
        r1.unexplained[0].fields["amplitude_rad_s"], r0.unexplained[0].fields["amplitude_rad_s"], rtol=1e-6
    )


def test_cli_line_options(tmp_path):
    import json

    from click.testing import CliRunner

    from gyrocore.cli.commands.loop import command as loop_command
    from gyrocore.data.recording import write_csv

    rec = optical_recording(seed=3, line_axis=0, line_hz=40.5366, line_amp_rad_s=1.455 * DEG)
    f = tmp_path / "optical.csv"
    write_csv(rec, f)
    args = [str(f), "--effects", "bias,time_offset", "--candidates", "bias_ramp", "--json"]
    out = CliRunner().invoke(loop_command, args + ["--line-statistic", "pooled", "--line-segments", "4"])
    assert out.exit_code == 0, out.output
    (u,) = json.loads(out.stdout)["unexplained"]
    assert u["kind"] == "periodic" and u["axis"] == "x" and abs(u["frequency_hz"] - 40.5366) < 1 / 60
    assert "phase-coherent" not in u["evidence"]["test"] and u["evidence"]["df1"] > 2
    bad = CliRunner().invoke(loop_command, args + ["--line-statistic", "best"])
    assert bad.exit_code != 0 and "best" in bad.output


@pytest.mark.slow
def test_every_line_at_10_sigma_is_described_and_nulls_stay_clean():
    # 30 seeds at √λ ∈ [10, 11]: the coherent test's power there is ≥ 0.9995 per seed (see the
    # six-seed test above), so all 30 are described with probability ≥ 0.985; 20 nulls: the
    # lines' share of α at the sample level is α/6/2 = 8.3e-4 per record over the 3 axes, so P(any
    # false line in 20) ≤ 0.017
    for seed in range(200, 230):
        tr = trial(seed, z_range=(10.0, 11.0))
        assert tr.described and abs(tr.f_found_hz - tr.f_hz) <= 1.0 / 60.0 and tr.others == (), tr
    for seed in range(300, 320):
        r = run_loop(optical_recording(seed=seed), declared=["bias", "time_offset"], candidates=["bias_ramp"])
        assert r.unexplained == (), seed


@pytest.mark.slow
def test_slower_reference_lines_at_10_sigma_are_described_and_nulls_stay_clean():
    # a 120-Hz tracker beside a 1-kHz gyro (slow-nan: jitter, dropped frames, sign flips), lines at
    # 70-400 Hz at √λ ∈ [10, 11] on the measured PSD: outside the reference's own lines' masks the
    # coherent test's power is ≥ 0.9995 per seed (see the six-seed test above), so all of 12 are
    # described with probability ≥ 0.99. A line within ±(1.5 Hz + 2W) of k·120 Hz may be masked
    # (the slerped reference's images of the 0.1-1.5-Hz tumbling; W = 4·fs/L): then it must not be
    # reported elsewhere either. 8 nulls: ≤ 8.3e-4 false lines per record (α/6/2), P(any) ≤ 0.007.
    from experiments.optical_lines import SCENARIOS

    make, kw, _ = SCENARIOS["slow-nan"]
    for seed in range(1100, 1112):
        tr = trial(seed, z_range=(10.0, 11.0), scenario="slow-nan")
        if not tr.described:
            ser = attitude_line_series(make(seed=seed, **kw), np.zeros((60000, 3)), LN.AttitudeLineOptions())
            W = 4.0 * ser[2] / ser[6]
            assert min(abs(tr.f_hz - k * 120.0) for k in range(1, 5)) <= 1.5 + 2 * W, tr
        else:
            assert abs(tr.f_found_hz - tr.f_hz) <= 1.0 / 60.0, tr
        assert tr.others == (), tr
    for seed in range(1150, 1158):
        r = run_loop(make(seed=seed, **kw), declared=["bias", "time_offset"], candidates=["bias_ramp"])
        assert r.unexplained == (), seed
