"""Lines under an optical attitude reference (part 1): synthetic recordings and the
Monte Carlo of the loop's sample-level line search against a differentiated attitude.

A motion-capture-like recording: rows at the optical rate (the gyro resampled to it, as
BROAD), timestamps jittered by ±1/20 of a frame, a few frames dropped (timestamp gaps) and
tracking lost in a few runs (NaN attitude, ≈ 3 %), white attitude noise σ_q per axis on the
reference, white gyro noise N, a gyro bias, and optionally a vibration line the gyro carries
and the reference lacks (``line_axis``, ``line_hz``, ``line_amp_rad_s``) and a line of the
motion itself that both see (``shared_hz``, ``shared_amp_rad_s``).

The line's strength is its noncentrality in the harmonic F statistic the loop uses
(``line_z``): z = A/σ_A with σ_A² = (ΣU_k(0)²/L)⁻¹·S(f)/T_eff, the standard error of each
quadrature of the line's complex amplitude estimate μ̂ (Thomson's, combined phase-coherently
over the segments), S(f) the one-sided noise PSD of the residual at f — the gyro's 2N² plus the
differentiated reference's 8σ_q²·fs·sin²(πf/fs) — and T_eff the duration of the segments
tested: the loop's own segments (``attitude_line_series`` on the recording without the line),
so z is the σ of the test's statistic. (2|μ̂_s|²ΣU²/(S fs/2) is χ²₂(λ_s) per segment with
λ_s = A²ΣU²/(S·fs); over the segments λ = z², the noncentrality of the coherent F(2, 12S; λ)
the loop decides with, and of the pooled F(2S, 12S; λ).) ``slow_reference_recording``: a
reference slower than the gyro (120 Hz beside 1 kHz; NaN between frames or held, frame jitter,
dropped frames, sign flips), which the loop slerps onto the gyro's rows; ``SCENARIOS`` /
``--reference``: the study's reference scenarios.

Command: ``python -m experiments.optical_lines --seeds 20`` (a table of described lines per
seed; ``--null``: no line, what the loop reports); docs/loop.md §6.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np
from scipy import signal

from gyrocore.attitude import integrate_gyro
from gyrocore.data.recording import Recording
from gyrocore.loop.lines import AttitudeLineOptions

DEG = np.pi / 180.0

#: Defaults: an OptiTrack-like reference (σ_q 0.03° per axis at 240 Hz) and a consumer MEMS
#: gyro (N 0.005 °/s/√Hz).
SIGMA_Q_RAD = 0.03 * DEG
ARW_RAD_PER_SQRT_S = 0.005 * DEG
RATE_HZ = 240.0
_SUB = 20  # fine integration steps per frame


def residual_psd(
    f_hz,
    *,
    rate_hz: float = RATE_HZ,
    sigma_q_rad: float = SIGMA_Q_RAD,
    arw_rad_per_sqrt_s: float = ARW_RAD_PER_SQRT_S,
    ref_rate_hz: float | None = None,
):
    """One-sided PSD of the sample-level residual gyro − d/dt(reference), (rad/s)²/Hz.

    White attitude noise ε_k (σ_q per axis) differenced, (ε_k − ε_{k−1})/Δt: |1 − e^{−i2πfΔt}|²
    = 4 sin²(πfΔt) times the white PSD 2σ_q²Δt, over Δt²: 8σ_q²·fs·sin²(πf/fs) (≈ 8π²σ_q²f²/fs,
    ∝ f², well below fs/4); plus the gyro's white 2N².

    A reference at ``ref_rate_hz`` = f_r below the rows' ``rate_hz`` (slerped onto the rows,
    :func:`gyrocore.loop.lines.reference_on_rows`): its differenced noise, 8σ_q²·f_r·sin²(πf/f_r),
    is held over each frame interval (the rate between two slerped frames is constant), a
    zero-order hold of gain sinc²(f/f_r): 8σ_q²·f_r·sin⁴(πf/f_r)/(πf/f_r)², folded at the rows'
    rate (images at |f + m·fs|, |m| ≤ 4). Zero at every multiple of f_r, and ∝ 1/f² above f_r/2.
    """
    f = np.asarray(f_hz, float)
    if ref_rate_hz is None or ref_rate_hz >= rate_hz:
        return 8 * sigma_q_rad**2 * rate_hz * np.sin(np.pi * f / rate_hz) ** 2 + 2 * arw_rad_per_sqrt_s**2
    fr = float(ref_rate_hz)
    ref = np.zeros_like(f)
    for m in range(-4, 5):
        x = np.abs(f + m * rate_hz) / fr
        ref += 8 * sigma_q_rad**2 * fr * np.sin(np.pi * x) ** 2 * np.sinc(x) ** 2
    return ref + 2 * arw_rad_per_sqrt_s**2


def taper_efficiency(L: int, nw: float = 4.0) -> float:
    """ΣU_k(0)²/L of the K = 2NW − 1 unit-energy Slepian tapers of length L (≈ 1)."""
    K = int(2 * nw - 1)
    v = signal.windows.dpss(L, nw, K)
    return float(np.sum(v.sum(axis=1) ** 2) / L)


def line_z(amp_rad_s: float, f_hz: float, t_eff_s: float, L: int, **psd) -> float:
    """Noncentrality √λ of a line of amplitude ``amp_rad_s`` in the pooled harmonic F (module doc)."""
    return float(amp_rad_s * np.sqrt(taper_efficiency(L) * t_eff_s / residual_psd(f_hz, **psd)))


def optical_recording(
    *,
    seed: int,
    duration_s: float = 60.0,
    rate_hz: float = RATE_HZ,
    sigma_q_rad: float = SIGMA_Q_RAD,
    arw_rad_per_sqrt_s: float = ARW_RAD_PER_SQRT_S,
    line_axis: int = 0,
    line_hz: float = 0.0,
    line_amp_rad_s: float = 0.0,
    shared_hz: float = 0.0,
    shared_amp_rad_s: float = 0.0,
    bias_rad_s=(0.004, -0.003, 0.002),
    dropouts: bool = True,
    sign_flips: bool = False,
) -> Recording:
    """A gyro beside a motion-capture attitude (module docstring). Rows at ``rate_hz``.

    The gyro is a point sample of the true rate at each row's time (plus bias, line, noise),
    the reference the true attitude (integrated on a 20× finer grid) times exp(ε), ε ~ N(0, σ_q²)
    per axis. The shared line is a rotation of the body about x (rate amplitude
    ``shared_amp_rad_s``): in the truth, so in both.
    """
    rng = np.random.default_rng(seed)
    n_fine = round(duration_s * rate_hz * _SUB)
    t_fine = np.arange(n_fine + 1) / (rate_hz * _SUB)
    freqs = rng.uniform(0.1, 1.5, (3, 3))
    phases = rng.uniform(0, 2 * np.pi, (3, 3))
    amps = rng.uniform(0.3, 0.8, (3, 3))

    def omega(t):
        w = np.stack(
            [
                np.sum(amps[i][:, None] * np.sin(2 * np.pi * freqs[i][:, None] * t[None] + phases[i][:, None]), axis=0)
                for i in range(3)
            ],
            axis=1,
        )
        if shared_amp_rad_s:
            w[:, 0] += shared_amp_rad_s * np.cos(2 * np.pi * shared_hz * t + 0.3)
        return w

    # the attitude: the rate at the fine steps' midpoints held over each step (error O(dt³))
    w_mid = omega(t_fine - 0.5 / (rate_hz * _SUB))
    q_fine = integrate_gyro(t_fine, w_mid)
    # frame k at fine index SUB·k + jitter (±1 fine step), a few frames dropped
    k_idx = np.arange(1, int(duration_s * rate_hz) - 1) * _SUB + rng.integers(-1, 2, int(duration_s * rate_hz) - 2)
    keep = np.ones(k_idx.size, bool)
    if dropouts:
        for _ in range(5):  # dropped frames: timestamp gaps of 1-3 frames
            a = int(rng.integers(100, k_idx.size - 100))
            keep[a : a + int(rng.integers(1, 4))] = False
    k_idx = k_idx[keep]
    t = t_fine[k_idx]
    q = q_fine[k_idx]
    n = t.shape[0]
    # reference noise: q ⊗ exp(ε/2)
    eps = rng.normal(0.0, sigma_q_rad, (n, 3))
    ang = np.linalg.norm(eps, axis=1)
    half = 0.5 * ang
    s_ = np.where(ang > 0, np.sin(half) / np.where(ang > 0, ang, 1), 0.5)
    dq = np.column_stack([np.cos(half), eps * s_[:, None]])
    from gyrocore.attitude import qmul, qnormalize

    q_ref = qnormalize(qmul(q, dq))
    if dropouts:  # tracking lost: ≈ 3 % of the frames in runs of 10-100
        lost = 0
        while lost < 0.03 * n:
            a = int(rng.integers(0, n - 100))
            m = int(rng.integers(10, 101))
            q_ref[a : a + m] = np.nan
            lost += m
    if sign_flips:  # q and −q are one attitude: a tracker may hand out either, frame by frame
        q_ref[np.random.default_rng([seed, 7]).random(n) < 0.5] *= -1.0
    gyro = omega(t) + np.asarray(bias_rad_s, float)
    if line_amp_rad_s:
        gyro[:, line_axis] += line_amp_rad_s * np.cos(2 * np.pi * line_hz * t + 1.1)
    gyro += rng.normal(0.0, arw_rad_per_sqrt_s * np.sqrt(rate_hz), gyro.shape)
    return Recording(
        t_s=t - t[0], gyro_rad_s=gyro, ref_quat_wxyz=q_ref, meta={"scenario": "optical_lines", "seed": str(seed)}
    )


def slow_reference_recording(
    *,
    seed: int,
    duration_s: float = 60.0,
    gyro_rate_hz: float = 1000.0,
    ref_rate_hz: float = 120.0,
    sigma_q_rad: float = SIGMA_Q_RAD,
    arw_rad_per_sqrt_s: float = ARW_RAD_PER_SQRT_S,
    line_axis: int = 0,
    line_hz: float = 0.0,
    line_amp_rad_s: float = 0.0,
    bias_rad_s=(0.004, -0.003, 0.002),
    fill: str = "nan",
    frame_jitter_s: float = 0.0,
    gaps: int = 0,
    sign_flips: bool = False,
) -> Recording:
    """A gyro at ``gyro_rate_hz`` beside an optical attitude at ``ref_rate_hz`` (slower): rows
    at the gyro's rate, the reference on the row nearest each of its frames (frame intervals of
    ⌊fs/f_ref⌋ or ⌈fs/f_ref⌉ rows, as a tracker stamped on the IMU's clock), tracking lost in
    ≈ 3 % of the frames. Motion, noise and line as :func:`optical_recording`.

    ``fill``: the rows between frames NaN (``"nan"``) or each frame held until the next
    (``"hold"``, NaN through a tracking loss). ``frame_jitter_s``: each frame's exposure is
    uniform within ±this of its nominal time (the frame rows stay where they are: irregular
    spacing is rounded to rows, the rest is stamp error). ``gaps``: that many runs of 2–6
    dropped frames (17–50 ms at 120 Hz), NaN. ``sign_flips``: each frame's quaternion is −q
    with probability ½.
    """
    from gyrocore.attitude import qmul, qnormalize

    rng = np.random.default_rng([seed, 120])
    sub = 4
    n = int(duration_s * gyro_rate_hz)
    t_fine = np.arange(n * sub + 1) / (gyro_rate_hz * sub)
    freqs = rng.uniform(0.1, 1.5, (3, 3))
    phases = rng.uniform(0, 2 * np.pi, (3, 3))
    amps = rng.uniform(0.3, 0.8, (3, 3))

    def omega(t):
        return np.stack(
            [
                np.sum(amps[i][:, None] * np.sin(2 * np.pi * freqs[i][:, None] * t[None] + phases[i][:, None]), axis=0)
                for i in range(3)
            ],
            axis=1,
        )

    q_fine = integrate_gyro(t_fine, omega(t_fine - 0.5 / (gyro_rate_hz * sub)))
    rows = np.arange(n) * sub
    t = t_fine[rows]
    t_nom = np.arange(0, duration_s, 1.0 / ref_rate_hz)
    frames, first = np.unique(np.rint(t_nom * gyro_rate_hz).astype(int), return_index=True)
    t_nom = t_nom[first][frames < n - 1]
    frames = frames[frames < n - 1]
    eps = rng.normal(0.0, sigma_q_rad, (frames.size, 3))
    ang = np.linalg.norm(eps, axis=1)
    s_ = np.where(ang > 0, np.sin(0.5 * ang) / np.where(ang > 0, ang, 1), 0.5)
    # the exposure: nominal time (plus jitter) on the fine grid
    t_exp = t_nom + (rng.uniform(-frame_jitter_s, frame_jitter_s, frames.size) if frame_jitter_s else 0.0)
    i_exp = np.clip(np.rint(t_exp * gyro_rate_hz * sub).astype(int), 0, n * sub)
    q_frames = qnormalize(qmul(q_fine[i_exp], np.column_stack([np.cos(0.5 * ang), eps * s_[:, None]])))
    lost = 0
    while lost < 0.03 * frames.size:
        a = int(rng.integers(0, frames.size - 100))
        m = int(rng.integers(10, 101))
        q_frames[a : a + m] = np.nan
        lost += m
    for _ in range(gaps):
        a = int(rng.integers(100, frames.size - 100))
        q_frames[a : a + int(rng.integers(2, 7))] = np.nan
    if sign_flips:
        q_frames[rng.random(frames.size) < 0.5] *= -1.0
    q_ref = np.full((n, 4), np.nan)
    q_ref[frames] = q_frames
    if fill == "hold":  # each frame repeated until the next one (NaN frames held as NaN)
        j = np.searchsorted(frames, np.arange(n), side="right") - 1
        q_ref = np.where((j >= 0)[:, None], q_frames[np.clip(j, 0, None)], np.nan)
    elif fill != "nan":
        raise ValueError(f"fill must be 'nan' or 'hold', not {fill!r}")
    gyro = omega(t) + np.asarray(bias_rad_s, float)
    if line_amp_rad_s:
        gyro[:, line_axis] += line_amp_rad_s * np.cos(2 * np.pi * line_hz * t + 1.1)
    gyro += rng.normal(0.0, arw_rad_per_sqrt_s * np.sqrt(gyro_rate_hz), gyro.shape)
    return Recording(
        t_s=t, gyro_rad_s=gyro, ref_quat_wxyz=q_ref, meta={"scenario": "optical_lines_slow_ref", "seed": str(seed)}
    )


@dataclass(frozen=True)
class LineTrial:
    seed: int
    axis: int
    f_hz: float
    amp_rad_s: float
    z: float
    described: bool
    f_found_hz: float | None
    others: tuple
    amp_found_rad_s: float | None = None


#: The reference scenarios of the study: generator keywords, the line's frequency band (Hz).
#: ``optical``: the 240-Hz reference on the rows (docs/loop.md §6); ``optical-flips``: the same
#: with q or −q per frame; ``slow-nan`` / ``slow-hold``: a 120-Hz reference beside a 1-kHz gyro,
#: on the row nearest each frame (NaN between) or held until the next frame, frame exposures
#: jittered ±0.5 ms, 5 runs of 2–6 dropped frames, q or −q per frame; the line above the
#: reference's Nyquist frequency (60 Hz), below 0.4× the gyro's rate.
SCENARIOS = {
    "optical": (optical_recording, {}, (20.0, 80.0)),
    "optical-flips": (optical_recording, {"sign_flips": True}, (20.0, 80.0)),
    "slow-nan": (
        slow_reference_recording,
        {"fill": "nan", "frame_jitter_s": 5e-4, "gaps": 5, "sign_flips": True},
        (70.0, 400.0),
    ),
    "slow-hold": (
        slow_reference_recording,
        {"fill": "hold", "frame_jitter_s": 5e-4, "gaps": 5, "sign_flips": True},
        (70.0, 400.0),
    ),
}


def trial(
    seed: int,
    *,
    z_range=(6.0, 16.0),
    duration_s: float = 60.0,
    declared=("bias", "time_offset"),
    candidates=("bias_ramp",),
    options: AttitudeLineOptions | None = None,
    scenario: str = "optical",
) -> LineTrial:
    """One seed: a gyro line at a frequency in the scenario's band (:data:`SCENARIOS`; 20–80 Hz
    for ``optical``) of strength z ∈ ``z_range`` (drawn), run through the loop (declared
    ``bias``, ``time_offset``: the point-sampled gyro leads the reference's interval-mean rate by
    half a frame).

    z is the line's noncentrality on the loop's own segments: ``optical`` from the theoretical
    PSD (:func:`residual_psd`); the other scenarios from the measured one — Welch of the loop's
    residual on the recording without the line (each segment, Hann 2048, averaged), the median
    over ±2 Hz of the line — since stamp jitter adds motion-dependent noise the formula leaves out.
    """
    from gyrocore.loop.loop import run_loop
    from gyrocore.loop.open_step import attitude_line_series

    make, kw, band = SCENARIOS[scenario]
    opts = options or AttitudeLineOptions()
    rng = np.random.default_rng([seed, 25])
    axis = int(rng.integers(0, 3))
    f = float(rng.uniform(*band))
    z = float(rng.uniform(*z_range))
    # T_eff and L of the segments the loop's test runs on (its own series, on the recording
    # without the line: same seed, same times and dropouts)
    base = make(seed=seed, duration_s=duration_s, **kw)
    ser = attitude_line_series(base, np.zeros((base.n, 3)), opts)
    idx, L, fs = ser[5], ser[6], ser[2]
    t_eff = idx.size / fs
    if scenario == "optical":
        amp = z / line_z(1.0, f, t_eff, L)
    else:
        segs = ser[0][:, axis].reshape(-1, L)
        f_w, P = signal.welch(segs, fs=fs, nperseg=min(L, 2048), axis=-1)
        S = float(np.median(P.mean(axis=0)[np.abs(f_w - f) <= 2.0]))
        amp = z / np.sqrt(taper_efficiency(L) * t_eff / S)
    rec = make(seed=seed, duration_s=duration_s, line_axis=axis, line_hz=f, line_amp_rad_s=amp, **kw)
    r = run_loop(rec, declared=list(declared), candidates=list(candidates), attitude_lines=opts)
    hit = [
        u
        for u in r.unexplained
        if u.kind == "periodic"
        and u.axis == "xyz"[axis]
        and abs(u.fields["frequency_hz"] - f) <= 1.0 / (rec.t_s[-1] - rec.t_s[0])
    ]
    others = tuple(u.effect + "@" + u.axis for u in r.unexplained if all(u is not h for h in hit)) + tuple(
        s.effect for s in r.found
    )
    return LineTrial(
        seed=seed,
        axis=axis,
        f_hz=f,
        amp_rad_s=amp,
        z=z,
        described=bool(hit),
        f_found_hz=float(hit[0].fields["frequency_hz"]) if hit else None,
        others=others,
        amp_found_rad_s=float(hit[0].fields["amplitude_rad_s"]) if hit else None,
    )


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--seed-start", type=int, default=0)
    ap.add_argument("--z-min", type=float, default=6.0)
    ap.add_argument("--z-max", type=float, default=16.0)
    ap.add_argument("--null", action="store_true", help="no line: print what the loop reports on each seed")
    ap.add_argument("--reference", choices=sorted(SCENARIOS), default="optical", help="the reference scenario")
    a = ap.parse_args(argv)
    if a.null:
        from gyrocore.loop.loop import run_loop

        print("seed reported strongest_sample_line(axis,Hz,log10p) threshold_log10")
        for s in range(a.seed_start, a.seed_start + a.seeds):
            make, kw, _ = SCENARIOS[a.reference]
            r = run_loop(make(seed=s, **kw), declared=["bias", "time_offset"], candidates=["bias_ramp"])
            per = [p for p in r.open_search.get("periodic", []) if p.get("level") == "sample"]
            best = min(per, key=lambda p: p["log10_p"]) if per else None
            print(
                s,
                ",".join(u.effect + "@" + u.axis for u in r.unexplained) + ",".join(x.effect for x in r.found) or "-",
                (best["axis"], round(best["frequency_hz"], 3), round(best["log10_p"], 2)) if best else "-",
                round(float(np.log10(best["threshold"])), 2) if best else "-",
                flush=True,
            )
        return
    print("seed axis f_hz amp_deg_s z described f_found_hz amp_found/amp others")
    for s in range(a.seed_start, a.seed_start + a.seeds):
        tr = trial(s, z_range=(a.z_min, a.z_max), scenario=a.reference)
        print(
            f"{tr.seed} {'xyz'[tr.axis]} {tr.f_hz:.4f} {tr.amp_rad_s / DEG:.4g} {tr.z:.2f} {tr.described} "
            f"{tr.f_found_hz if tr.f_found_hz is None else round(tr.f_found_hz, 4)} "
            f"{'-' if tr.amp_found_rad_s is None else round(tr.amp_found_rad_s / tr.amp_rad_s, 3)} "
            f"{','.join(tr.others) or '-'}",
            flush=True,
        )


if __name__ == "__main__":
    main()
