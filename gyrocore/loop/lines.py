"""Narrow-band lines: the open search's line tests on the sample-level residual.

One of the three detectors of :mod:`gyrocore.loop.search` (its share of α is
``search.ALPHA_SHARE["periodic"]``).

**Narrow-band lines** (:func:`harmonic_f_test`, :func:`screen_lines`) in the
*sample-level* residual (window means would hide them): Thomson's (1982) multitaper
harmonic F-test, F(f) = (K − 1)·|μ̂(f)|²·Σ_k U_k(0)² / Σ_k |Y_k(f) − μ̂(f)·U_k(0)|²
~ F(2, 2K − 2) for a line in noise whose spectrum is smooth over ±W — the local
comparison makes it valid under coloured noise (flicker, random walk, Gauss–Markov,
the on-chip low-pass). Long records are cut into segments (≤ 65536 samples) whose
eigencoefficients are pooled, F ~ F(2S, 2S(K − 1)). The p-value is Bonferroni over the
frequencies tested; frequencies below 10·W (where 1/f noise is not smooth over the band)
and bins where the reference motion itself (rate, its derivative, specific force) has a
line are not tested — a line the motion explains is a motion-coupled error, not a new
effect. The frequency is refined by maximising the periodogram of the whole residual, the
amplitude fitted by least squares (cos/sin) at that frequency.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import signal as _signal
from scipy import stats

from gyrocore.errors import GyroInputError

__all__ = [
    "harmonic_f_test",
    "coherent_harmonic_f",
    "AttitudeLineOptions",
    "screen_lines",
    "fit_sinusoid",
    "refine_frequency",
    "reference_on_rows",
]

_SEG_MAX = 65536


#: Largest (K, nf, C) complex spectrum :func:`harmonic_f_test` forms at once (bytes); beyond
#: it the columns are transformed one at a time (memory, not numbers: each column's
#: statistics are computed by the same operations).
_FFT_BATCH_BYTES = 16 * 2**20
#: Series longer than this (samples) are summed in chunks of this length by the line fits
#: (:func:`refine_frequency`, :func:`fit_sinusoid`, :func:`sinusoid_cv_reduction`,
#: :func:`sinusoid_rms`): the per-sample cos/sin/design temporaries stay bounded; shorter
#: series take the whole-array arithmetic.
LINE_CHUNK = 1 << 18


def _spans(n: int):
    for a in range(0, n, LINE_CHUNK):
        yield a, min(a + LINE_CHUNK, n)


def segment_length(n: int, seg_max: int = _SEG_MAX) -> int:
    """Length of the equal segments :func:`harmonic_f_test` cuts n samples into."""
    return n // int(np.ceil(n / seg_max))


@dataclass(frozen=True, eq=False)
class HarmonicF:
    """Pooled multitaper harmonic F-test on a grid (see :func:`harmonic_f_test`)."""

    freq_hz: np.ndarray
    F: np.ndarray  # (F,) or (F, C)
    df1: int
    df2: int
    bandwidth_hz: float  # W
    amplitude: np.ndarray  # 2|μ̂| pooled (RMS over segments), same shape as F
    #: local noise power per real degree of freedom, Σ_s Σ_k |Y_sk − μ̂_s U_k(0)|² / df2 (the F
    #: denominator), same shape as F
    noise: np.ndarray | None = None


def harmonic_f_test(
    x: np.ndarray, fs: float, *, nw: float = 4.0, k: int | None = None, seg_max: int = _SEG_MAX, pad: int = 4
) -> HarmonicF:
    """Thomson's harmonic F-test for a sinusoid in coloured noise, per column of x.

    Parameters
    ----------
    x : ndarray, shape (N,) or (N, C)
        Evenly sampled series (mean removed per segment).
    fs : float
        Sample rate, Hz.
    nw : float
        Time-bandwidth product (W = nw·fs/L for segments of L samples).
    k : int, optional
        Number of Slepian tapers, default 2·nw − 1.
    pad : int
        Zero-padding factor of the FFT grid. The F statistic of a line between two grid
        frequencies saturates (the offset eigencoefficient pattern leaks into the
        denominator), so the grid is ``pad`` times finer than 1/L; a Bonferroni bound over the
        padded grid is then conservative.
    seg_max : int
        Longest segment; longer series are cut into S equal segments whose statistics are
        pooled: F = [Σ_s |μ̂_s|²ΣU²/2S] / [Σ_s Σ_k |Y_sk − μ̂_s U_k|² / (2S(K−1))] ~ F(2S, 2S(K−1)).

    Returns
    -------
    HarmonicF
        On the rfft grid of one segment (DC excluded).

    References
    ----------
    D. J. Thomson, "Spectrum estimation and harmonic analysis", Proc. IEEE 70 (1982) 1055–1096, §XIII.
    """
    from gyrocore.calib.stream import Rows

    if not isinstance(x, Rows):  # a lazy (N, C) series is read one segment at a time
        x = np.asarray(x, float)
    squeeze = x.ndim == 1
    if squeeze:
        x = x[:, None]
    N, C = x.shape
    K = int(k or max(1, int(2 * nw - 1)))
    S = int(np.ceil(N / seg_max))
    L = N // S
    tapers = _signal.windows.dpss(L, nw, K)  # (K, L), unit energy
    U0 = tapers.sum(axis=1)  # U_k(0)
    sU2 = float(np.sum(U0**2))
    nfft = int(pad) * L
    nf = nfft // 2 + 1
    num = np.zeros((nf, C))
    den = np.zeros((nf, C))
    amp2 = np.zeros((nf, C))
    # long segments are transformed one column at a time (the (K, nf, C) spectra of 6 motion
    # columns of 65 536 samples are ~0.2 GB; the statistics of each column are independent)
    cols = [slice(0, C)] if K * nf * C * 16 <= _FFT_BATCH_BYTES else [slice(c, c + 1) for c in range(C)]
    # work arrays reused for every segment and column (the same operations with out=: no
    # allocation per segment — with allocations served by mmap, stream.bounded_heap, each would
    # be page-faulted anew)
    nc = cols[0].stop - cols[0].start
    prod = np.empty((K, L, nc))
    Y = np.empty((K, nf, nc), dtype=complex)
    r2 = np.empty((K, nf, nc))
    for s in range(S):
        seg = np.asarray(x[s * L : (s + 1) * L], float)
        seg = seg - seg.mean(axis=0)
        for cs in cols:
            np.multiply(tapers[:, :, None], seg[None, :, cs], out=prod)
            np.fft.rfft(prod, n=nfft, axis=1, out=Y)  # (K, nf, C)
            mu = np.einsum("k,kfc->fc", U0, Y) / sU2
            for k_ in range(K):  # the residual eigencoefficients, in place
                Y[k_] -= mu * U0[k_]
            np.abs(Y, out=r2)
            np.square(r2, out=r2)
            num[:, cs] += np.abs(mu) ** 2 * sU2
            den[:, cs] += np.sum(r2, axis=0)
            amp2[:, cs] += 4 * np.abs(mu) ** 2
    del prod, Y, r2
    df1, df2 = 2 * S, 2 * S * (K - 1)
    # F = (num/df1)/(den/df2) where den > 0, else 0 — in place (the same divisions)
    ok = den > 0
    num /= df1
    den /= df2
    np.divide(num, den, out=num, where=ok)
    num[~ok] = 0.0
    F = num
    del ok
    f = np.fft.rfftfreq(nfft, 1.0 / fs)
    F, f, amp, den = F[1:], f[1:], np.sqrt(amp2[1:] / S), den[1:]
    if squeeze:
        F, amp, den = F[:, 0], amp[:, 0], den[:, 0]
    return HarmonicF(freq_hz=f, F=F, df1=df1, df2=df2, bandwidth_hz=nw * fs / L, amplitude=amp, noise=den)


def coherent_harmonic_f(
    x: np.ndarray,
    fs: float,
    seg_start_s: np.ndarray,
    *,
    nw: float = 4.0,
    k: int | None = None,
    pad: int = 4,
    pooled: HarmonicF | None = None,
) -> HarmonicF:
    """Harmonic F-test of one sinusoid, phase-coherent across S equal segments cut from one record.

    A line of fixed frequency, amplitude and phase (what a ``periodic[f]`` term is),
    (A/2)e^{i(2πft + φ)} + c.c., has in segment s starting at t_s the eigencoefficient mean
    μ_s(f) = μ·e^{i2πf t_s}: the segments' estimates μ̂_s (:func:`harmonic_f_test`) are
    combined with their phases, μ̂(f) = (1/S) Σ_s μ̂_s(f)·e^{−i2πf(t_s − t_0)}, on a grid ``pad`` times finer than 1/T_span
    (T_span from the first segment's start to the last one's end). Against the same local
    noise estimate as the pooled test (each segment's eigencoefficient residuals, 2S(K − 1)
    degrees of freedom, independent of the μ̂_s):

        F = S·|μ̂|²·ΣU_k(0)² / 2 / (Σ_s Σ_k |Y_sk − μ̂_s U_k(0)|² / (2S(K − 1))) ~ F(2, 2S(K − 1); λ)

    with the same noncentrality λ = (A/σ_A)² as the pooled F(2S, 2S(K − 1)) — the line's
    whole strength in 2 numerator degrees of freedom instead of 2S. At √λ = 10 and a
    Bonferroni level of 1e-9 over the fine grid this has power ≈ 0.999 (the pooled test with
    S = 17: ≈ 0.9; scipy.stats.ncf). A line whose frequency wanders by more than 1/T_span
    loses coherence: the pooled test (which :func:`screen_lines` runs beside this one) keeps it.

    μ̂_s is linear in the segment, μ̂_s(f) = Σ_n h_n x_n e^{−i2πfn/fs} with
    h = Σ_k U_k(0)·v_k/ΣU_k(0)²: one FFT per segment and column. The local noise of the
    pooled test is taken at the nearest frequency of its grid (pad·L points: within 1/(2·pad)
    of a Rayleigh bin 1/L of the line, where the noise spectrum is smooth over ±W by the test's
    assumption).

    Parameters
    ----------
    x : ndarray, shape (S·L, C)
        The S segments of L samples, one after the other (:func:`even_segments`).
    fs : float
        Sample rate, Hz.
    seg_start_s : ndarray, shape (S,)
        Time of each segment's first sample, s.
    pooled : HarmonicF, optional
        :func:`harmonic_f_test` (x, fs, nw=nw, seg_max=L) if already computed.

    Returns
    -------
    HarmonicF
        On the fine grid (DC excluded); df1 = 2; amplitude 2|μ̂|, rad/s.
    """
    x = np.asarray(x, float)
    squeeze = x.ndim == 1
    if squeeze:
        x = x[:, None]
    t0 = np.asarray(seg_start_s, float)
    S = t0.shape[0]
    N, C = x.shape
    L = N // S
    K = int(k or max(1, int(2 * nw - 1)))
    if pooled is None:
        pooled = harmonic_f_test(x, fs, nw=nw, k=K, seg_max=L, pad=pad)
    tapers = _signal.windows.dpss(L, nw, K)
    U0 = tapers.sum(axis=1)
    sU2 = float(np.sum(U0**2))
    h = U0 @ tapers / sU2  # (L,)
    span = float(t0[-1] - t0[0]) + L / fs
    from scipy.fft import next_fast_len

    nfft = next_fast_len(int(pad * np.ceil(span * fs)))
    f = np.fft.rfftfreq(nfft, 1.0 / fs)
    acc = np.zeros((f.size, C), complex)
    for s in range(S):
        seg = x[s * L : (s + 1) * L]
        M = np.fft.rfft(h[:, None] * (seg - seg.mean(axis=0)), n=nfft, axis=0)
        M *= np.exp(-2j * np.pi * f * (t0[s] - t0[0]))[:, None]
        acc += M
    acc /= S
    num = np.abs(acc) ** 2 * (S * sU2 / 2.0)
    amp = 2 * np.abs(acc)
    del acc
    noise = pooled.noise if pooled.noise.ndim == 2 else pooled.noise[:, None]
    # nearest frequency of the pooled grid (its DC dropped: index 0 is fs/(pad·L))
    step = pooled.freq_hz[0]
    j = np.clip(np.rint(f / step).astype(int) - 1, 0, noise.shape[0] - 1)
    den = noise[j]
    F = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
    F, amp, den, f = F[1:], amp[1:], den[1:], f[1:]
    if squeeze:
        F, amp, den = F[:, 0], amp[:, 0], den[:, 0]
    return HarmonicF(freq_hz=f, F=F, df1=2, df2=pooled.df2, bandwidth_hz=pooled.bandwidth_hz, amplitude=amp, noise=den)


@dataclass(frozen=True)
class LineScreen:
    axis: int
    frequency_hz: float
    statistic: float
    df1: int
    df2: int
    log10_p: float  # Bonferroni over the frequencies tested
    n_freq: int
    bandwidth_hz: float
    masked_by_motion: int
    #: "pooled" (:func:`harmonic_f_test`) or "coherent" (:func:`coherent_harmonic_f`): the
    #: statistic whose Bonferroni p-value was the smaller
    test: str = "pooled"
    #: half-width of the frequency refinement around ``frequency_hz`` (one bin of its grid's
    #: resolution: fs/L pooled, 1/T_span coherent), Hz
    resolution_hz: float = 0.0


@dataclass(frozen=True)
class AttitudeLineOptions:
    """The sample-level line test against a differentiated reference attitude.

    Attributes
    ----------
    segments : int
        Target number of equal gap-free segments (:func:`even_segments` ``n_target``).
    statistic : {"coherent", "pooled", "both"}
        The line test: phase-coherent across the segments (:func:`coherent_harmonic_f`,
        F(2, 2S(K − 1)): a stable line needs √λ ≈ 8.5 for 99 % power), the segments' pooled
        statistic (F(2S, 2S(K − 1)): √λ ≈ 11–12 with 8–18 segments), or both with α split in
        halves. A ``periodic[f]`` term is one phase-stable sinusoid over the record: narrow-band
        energy whose phase wanders between segments (what only the pooled statistic sees) is
        not one — its fitted amplitude is within its standard error.
    mask_level : float
        Probability that a given frequency is masked by the differentiated reference's noise
        alone (:func:`_motion_mask` ``family_wise``: Bonferroni over the reference's bins
        within ±2W and its columns).
    mask_accel : bool
        Mask lines of the specific force too. Off: an accelerometer shares the vibration of a
        vibrating attachment (the very line the gyro carries and the optical reference lacks);
        the reference's own lines are what the test must exclude.
    """

    segments: int = 8
    statistic: str = "coherent"
    mask_level: float = 1e-3
    mask_accel: bool = False

    def __post_init__(self):
        if self.statistic not in ("coherent", "pooled", "both"):
            raise GyroInputError(f"line statistic must be coherent, pooled or both, not {self.statistic!r}")
        if self.segments < 1:
            raise GyroInputError(f"line segments must be >= 1, not {self.segments}")
        if not 0.0 < self.mask_level < 1.0:
            raise GyroInputError(f"line mask level must be in (0, 1), not {self.mask_level}")


def _motion_mask(
    ref: np.ndarray | None,
    fs: float,
    f: np.ndarray,
    W: float,
    *,
    p_mask: float = 1e-4,
    seg_max: int = _SEG_MAX,
    family_wise: bool = False,
) -> np.ndarray:
    """Bins within ±2W of a line in any reference-motion column: p < p_mask per bin, or with
    ``family_wise`` p < p_mask/(bins within ±2W × columns) — Bonferroni over the motion bins
    that can mask one frequency, so that P(a given frequency is masked by the motion's noise
    alone) ≤ p_mask. (Per bin, a frequency is masked by noise with probability ≈
    p_mask·64·C: 2 % at p_mask = 1e-4 with the 64 padded bins of ±2W and 3 columns — a line the
    motion lacks lost on one record in 50.) A line of the motion that leaks into the residual
    is at least as significant in the motion column as in the residual, where the line test's
    own level is far lower still: the local level masks it."""
    mask = np.zeros(f.size, bool)
    if ref is None or int(np.prod(ref.shape)) == 0:
        return mask
    from gyrocore.calib.stream import Rows

    n_r = ref.shape[0]
    C = ref.shape[1] if len(ref.shape) == 2 else 1
    L = segment_length(n_r, seg_max)
    if C > 1 and 7 * (2 * L + 1) * C * 16 > _FFT_BATCH_BYTES:
        # long records: one motion column per test (harmonic_f_test transforms them one at a
        # time anyway — the same numbers — and its accumulators are then (nf, 1), not (nf, 6))
        if isinstance(ref, Rows):
            cols = [Rows(lambda a, b, c=c: ref.rows(a, b)[:, c : c + 1], n_r, 1) for c in range(C)]
        else:
            cols = [ref[:, c : c + 1] for c in range(C)]
    else:
        cols = [ref]
    hit = None
    for col in cols:
        h = harmonic_f_test(col, fs, seg_max=seg_max)
        Fm = h.F if h.F.ndim == 2 else h.F[:, None]
        if hit is None:
            hit = np.zeros(Fm.shape[0], bool)
        # the padded motion bins within ±2·max(W, W_m) of one frequency: 4·nw·pad·max(1, W/W_m)
        n_local = 4 * 4.0 * 4 * max(1.0, W / h.bandwidth_hz)
        level = p_mask / (n_local * C) if family_wise else p_mask
        for c in range(Fm.shape[1]):  # one column at a time (scipy's temporaries of 6 columns × 2¹⁷ bins)
            hit |= stats.f.sf(Fm[:, c], h.df1, h.df2) < level
        del Fm
    # the reference also must carry power there: a line of the motion, not of its noise
    fl = h.freq_hz[hit]
    for f0 in fl:
        mask |= np.abs(f - f0) <= 2 * max(W, h.bandwidth_hz)
    return mask


def _motion_mask_coherent(
    ref: np.ndarray | None, fs: float, seg_start_s: np.ndarray, f: np.ndarray, W: float, *, p_mask: float = 1e-3
) -> np.ndarray:
    """Bins of the coherent grid ``f`` within ±2W of a phase-stable line of any reference-motion
    column (:func:`coherent_harmonic_f` on the same segments and grid), at a level Bonferroni
    over the grid's bins within ±2W and the columns: P(a given frequency masked by the motion's
    noise alone) ≤ ``p_mask``. A line of the reference that leaks into the residual is at
    least as strong in the reference (a reference-only line: the same line; a motion line the
    gyro shares: ≥ 1/0.36 of its residual, |1 − sinc(f/fs)| ≤ 0.36 below fs/2 − 2W) and is
    measured there by the same statistic, so it is masked wherever the residual's test could
    see it; a noise peak of the pooled statistic 1.4 Hz away no longer hides a line."""
    mask = np.zeros(f.size, bool)
    if ref is None or int(np.prod(ref.shape)) == 0:
        return mask
    r = np.asarray(ref, float)
    if r.ndim == 1:
        r = r[:, None]
    C = r.shape[1]
    hm = coherent_harmonic_f(r, fs, seg_start_s)
    df = float(hm.freq_hz[1] - hm.freq_hz[0])
    k = int(np.ceil(2 * max(W, hm.bandwidth_hz) / df))
    level = np.log(p_mask / ((2 * k + 1) * C))
    hit = np.zeros(hm.freq_hz.size, bool)
    for c in range(C):
        hit |= stats.f.logsf(hm.F[:, c], hm.df1, hm.df2) < level
    if not hit.any():
        return mask
    from scipy.ndimage import binary_dilation

    near = binary_dilation(hit, structure=np.ones(2 * k + 1, bool))
    # the same grid as the residual's (same segments, fs, pad): index by frequency
    j = np.clip(np.rint(f / df).astype(int) - 1, 0, near.size - 1)
    return near[j]


def screen_lines(
    x: np.ndarray,
    fs: float,
    *,
    ref: np.ndarray | None = None,
    f_min_hz: float | None = None,
    nw: float = 4.0,
    skip: Sequence[tuple[int, float]] = (),
    seg_max: int = _SEG_MAX,
    seg_start_s: np.ndarray | None = None,
    statistics: Sequence[str] = ("pooled",),
    mask_level: float = 1e-4,
    mask_family_wise: bool = False,
) -> list[LineScreen]:
    """Strongest line per axis of x (N, 3) and its Bonferroni p-value over frequencies.

    Frequencies below ``f_min_hz`` (default 10·W) and bins within ±2W of a line of the
    reference motion ``ref`` (N, R) are not tested; neither are (axis, frequency) pairs in
    ``skip`` (lines already in the model, ±2W). ``seg_max``: segment length of
    :func:`harmonic_f_test` (a series of S equal segments of L samples cut from separate runs,
    :func:`even_segments`, is passed with ``seg_max = L``: no segment straddles a gap).
    ``statistics``: ``"pooled"`` (:func:`harmonic_f_test`) and/or ``"coherent"``
    (:func:`coherent_harmonic_f`, needs ``seg_start_s`` (S,), the segments' start times); with
    both, each axis reports the one with the smaller Bonferroni p, doubled (α split in halves
    between the two families).
    ``mask_level``, ``mask_family_wise``: the motion mask's level (:func:`_motion_mask`).
    """
    h = harmonic_f_test(x, fs, nw=nw, seg_max=seg_max)
    W = h.bandwidth_hz
    fmin = 10 * W if f_min_hz is None else max(f_min_hz, 2 * W)
    grids = []
    if "pooled" in statistics or seg_start_s is None or len(seg_start_s) < 2:
        grids.append(("pooled", h, fs / segment_length(x.shape[0], seg_max)))
    if "coherent" in statistics and seg_start_s is not None and len(seg_start_s) > 1:
        hc = coherent_harmonic_f(x, fs, seg_start_s, nw=nw, pooled=h)
        grids.append(("coherent", hc, 2 * (hc.freq_hz[1] - hc.freq_hz[0])))
    # the motion mask of each grid: the coherent grid's from the motion's own coherent statistic
    # (a phase-stable line of the reference is seen there with the power the residual's test
    # has), the pooled grid's from the pooled statistic
    masks = []
    for name, g, _ in grids:
        if name == "coherent" and mask_family_wise:
            masks.append(_motion_mask_coherent(ref, fs, seg_start_s, g.freq_hz, W, p_mask=mask_level))
        else:
            masks.append(
                _motion_mask(ref, fs, g.freq_hz, W, seg_max=seg_max, p_mask=mask_level, family_wise=mask_family_wise)
            )
    out = []
    for i in range(x.shape[1]):
        best = None
        for (name, g, res_hz), mm in zip(grids, masks):
            f = g.freq_hz
            ok = (f >= fmin) & (f <= 0.5 * fs - 2 * W)
            oki = ok & ~mm
            for ax, f0 in skip:
                if ax == i:
                    oki &= np.abs(f - f0) > 2 * W
            n = int(oki.sum())
            if n == 0:
                continue
            Fi = np.where(oki, g.F[:, i], -np.inf)
            j = int(np.argmax(Fi))
            lp1 = float(stats.f.logsf(Fi[j], g.df1, g.df2) / np.log(10))
            cand = LineScreen(
                axis=i,
                frequency_hz=float(f[j]),
                statistic=float(Fi[j]),
                df1=g.df1,
                df2=g.df2,
                log10_p=min(0.0, lp1 + np.log10(n) + np.log10(len(grids))),
                n_freq=n,
                bandwidth_hz=W,
                masked_by_motion=int((ok & mm).sum()),
                test=name,
                resolution_hz=float(res_hz),
            )
            if best is None or cand.log10_p < best.log10_p:
                best = cand
        if best is not None:
            out.append(best)
    return out


def even_segments(
    t: np.ndarray,
    valid: np.ndarray,
    *,
    n_target: int = 8,
    min_len: int = 512,
    seg_max: int = _SEG_MAX,
    dt_tol: float = 0.5,
) -> tuple[np.ndarray, int]:
    """Equal, evenly sampled segments of a series with gaps, for a pooled harmonic F-test.

    A sample k belongs to a run when it is valid and Δt_k = t_k − t_{k−1} is within
    ``dt_tol``·Δt̄ of the median interval (a dropped frame, a timing glitch or a NaN ends a
    run: the F-test's tapers assume even sampling, and interpolating across a gap would put
    invented data under them). Segments of one length L are cut from the runs; the series of
    their samples, concatenated, gives :func:`harmonic_f_test` with ``seg_max = L`` exactly
    these segments. L: the longest of a geometric ladder from min(total/n_target, seg_max)
    down to ``min_len`` whose segments cover ≥ 75 % of the valid samples (else the one covering
    most). Pooling S ≈ n_target segments is also the test's best power for a line of given
    noncentrality: the pooled F(2S, 2S(K−1)) needs a line of √λ ≈ 11.6 standard errors for
    99 % power at a Bonferroni level of 3e-8 with S = 8, against 26 for S = 1 (F(2, 12)
    has a heavy tail; scipy.stats.ncf, docs/loop.md §6).

    Parameters
    ----------
    t : ndarray, shape (N,)
        Sample times, s.
    valid : ndarray, shape (N,), bool

    Returns
    -------
    idx : ndarray of int, shape (S·L,)
        Sample indices, segment after segment (empty when no segment of ``min_len`` fits).
    L : int
        Segment length, samples.
    """
    t = np.asarray(t, float)
    ok = np.asarray(valid, bool).copy()
    if t.shape[0] < 2 or ok.sum() < min_len:
        return np.zeros(0, int), 0
    dt = np.diff(t)
    dt_med = float(np.median(dt[ok[1:]])) if ok[1:].any() else float(np.median(dt))
    ok[1:] &= np.abs(dt - dt_med) <= dt_tol * dt_med
    ok[0] = False  # the first sample has no interval before it
    m = np.concatenate([[0], ok.astype(np.int8), [0]])
    d = np.diff(m)
    a, b = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    runs = b - a
    total = int(runs.sum())
    if total < min_len:
        return np.zeros(0, int), 0
    L0 = int(min(max(total // n_target, min_len), seg_max))
    ladder = []
    L = L0
    while L >= min_len:
        ladder.append(L)
        L = int(L * 0.8)
    cover = [int(np.sum((runs // L_) * L_)) for L_ in ladder]
    good = [L_ for L_, c in zip(ladder, cover) if c >= 0.75 * total]
    L = good[0] if good else ladder[int(np.argmax(cover))]
    if max(cover) == 0:
        return np.zeros(0, int), 0
    idx = [np.arange(a_ + j * L, a_ + (j + 1) * L) for a_, r in zip(a, runs) for j in range(r // L)]
    return np.concatenate(idx), L


def _regular_frame_times(tf: np.ndarray, row_s: float) -> np.ndarray:
    """Frame stamps ``tf`` (F,) s put on the straight line t₀ + n_k·Δ they were rounded from, when
    every stamp is within 0.75·``row_s`` of it (:func:`reference_on_rows`); else ``tf``."""
    d = np.diff(tf)
    reg = d <= 1.5 * np.median(d)
    if tf.size < 3 or not reg.any():
        return tf
    dt = float(d[reg].mean())  # the mean interval: the median is a whole number of rows
    t0 = float(tf[0])
    for _ in range(3):
        n_k = np.rint((tf - t0) / dt)
        A = np.column_stack([np.ones_like(n_k), n_k])
        (t0, dt), *_ = np.linalg.lstsq(A, tf, rcond=None)
    n_k = np.rint((tf - t0) / dt)
    fit = t0 + n_k * dt
    if np.all(np.diff(n_k) >= 1) and float(np.max(np.abs(tf - fit))) <= 0.75 * row_s:
        return fit
    return tf


def reference_on_rows(t_s: np.ndarray, q_wxyz: np.ndarray) -> tuple[np.ndarray, float]:
    """A reference attitude sampled more slowly than the gyro, put on every gyro row.

    A tracker at 100–240 Hz beside a gyro at 400 Hz–1 kHz reaches a recording in one of three
    ways: on the row nearest each of its frames (NaN between), held (each frame repeated on the
    rows until the next one: exact repeats), or already interpolated. The first two are not
    differentiable row by row: NaN rows leave no consecutive valid pair, and a held reference
    differentiates into a pulse train — the whole frame's rotation on one row, zero on the
    others — whose images of the motion and of the reference noise at every multiple of the
    frame rate fill the band up to the gyro's Nyquist frequency with noise the F-test must
    then beat. Here the *frames* (finite rows that are not an exact repeat of the previous
    finite row, up to sign) are interpolated onto the rows by slerp between consecutive frames
    (shortest path, so a sign flip q → −q between frames is no rotation), the rate between two
    frames constant: its content above the frame rate's Nyquist frequency is only the images
    of what lies below it, which the reference's own line mask excludes. Never across a
    dropout: rows between frames more than 1.5 median frame intervals apart stay NaN, as do
    rows before the first frame and after the last.

    **Frame times.** A tracker's frames stamped on the gyro's rows carry the rows' rounding:
    at 120 Hz beside 1 kHz the intervals run 8, 8, 9 rows, a stamp error of period 3 frames, so
    the slerped rate carries ω·δ_k at 40 Hz and its multiples (± the motion's frequencies) — lines
    of the reference, masked with ±2W about them (a quarter of the band above 60 Hz on a
    tumbling record). A tracker's own clock is regular: when every frame stamp lies within 0.75
    row of a straight line t₀ + n_k·Δ in the frame count n_k (dropped frames skip counts), the
    frames are put at the line's times; otherwise (an irregular tracker, a clock that wanders by
    more than a row) the stamps are used as they are.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Gyro row times, s.
    q_wxyz : ndarray, shape (N, 4)
        Reference attitude S→W, w,x,y,z (NaN: no frame on that row).

    Returns
    -------
    q_wxyz : ndarray, shape (N, 4)
        The input itself when the frames are on at least half the rows (nothing to do), else
        the interpolated reference.
    frame_rate_hz : float
        The frames' rate (1 / median frame interval); the rows' rate when unchanged.
    """
    from scipy.spatial.transform import Rotation, Slerp

    t = np.asarray(t_s, float)
    q = np.asarray(q_wxyz, float)
    ok = np.all(np.isfinite(q), axis=1)
    fin = np.flatnonzero(ok)
    rows_hz = 1.0 / float(np.median(np.diff(t))) if t.size > 1 else 0.0
    if fin.size < 2:
        return q, rows_hz
    repeat = np.all(q[fin[1:]] == q[fin[:-1]], axis=1) | np.all(q[fin[1:]] == -q[fin[:-1]], axis=1)
    frames = np.concatenate([fin[:1], fin[1:][~repeat]])
    # frames on at least half the rows they span: the reference is on the gyro's rows already
    if frames.size >= 0.5 * (fin[-1] - fin[0] + 1) or frames.size < 2:
        return q, rows_hz
    # ... and consecutive frames a row apart for the most part (a noise-free reference that is
    # exactly still for a spell repeats itself without being slower than the gyro)
    if np.median(np.diff(t[frames])) < 1.5 / rows_hz:
        return q, rows_hz
    tf = _regular_frame_times(t[frames], float(np.median(np.diff(t))))
    d_f = np.diff(tf)
    d_med = float(np.median(d_f))
    out = np.full_like(q, np.nan)
    inside = (t >= tf[0]) & (t <= tf[-1])
    j = np.clip(np.searchsorted(tf, t, side="right") - 1, 0, frames.size - 2)
    use = inside & (d_f[j] <= 1.5 * d_med)
    if use.any():
        s = Slerp(tf, Rotation.from_quat(q[frames][:, [1, 2, 3, 0]]))
        out[use] = s(t[use]).as_quat()[:, [3, 0, 1, 2]]
    return out, 1.0 / d_med


def band_limited_advance(
    t: np.ndarray, x: np.ndarray, tau_s: float, *, half_width: int = 16, beta: float = 8.0, dt_tol: float = 0.5
) -> np.ndarray:
    """x(t_k + τ) by Kaiser-windowed sinc interpolation on the evenly sampled runs of t.

    A cubic spline shifted by a fraction of a sample is a low-pass: by half a sample its gain
    is 0.996 / 0.97 / 0.875 / 0.58 at 0.17 / 0.25 / 0.33 / 0.42·fs, which takes a line near the
    Nyquist frequency down with it while the reference's noise beside it stays (the line test
    loses that factor of its √λ, and the fitted amplitude is that much short). The windowed
    sinc (2·``half_width`` taps, Kaiser β = 8) has gain 1 ± 1e-4 up to 0.4·fs (0.94 at
    0.45·fs) at every fraction. The taps must lie in one run of intervals within ``dt_tol``
    of the median (the segments' own rule, :func:`even_segments`): NaN elsewhere (within
    ``half_width`` samples of a gap, a NaN, or an end) — the caller falls back there.

    Parameters
    ----------
    t : ndarray, shape (N,)
        Sample times, s.
    x : ndarray, shape (N, C)
    tau_s : float
        Advance, s (x'(t) = x(t + τ)).

    Returns
    -------
    ndarray, shape (N, C)
    """
    t = np.asarray(t, float)
    x = np.asarray(x, float)
    N = t.shape[0]
    out = np.full(x.shape, np.nan)
    if N < 2 * half_width + 2:
        return out
    dt = np.diff(t)
    dt_med = float(np.median(dt))
    brk = np.flatnonzero(np.abs(dt - dt_med) > dt_tol * dt_med) + 1  # a run starts at each
    starts = np.concatenate([[0], brk])
    stops = np.concatenate([brk, [N]])
    d = tau_s / dt_med
    n0 = int(np.floor(d))
    frac = d - n0
    j = np.arange(-half_width + 1, half_width + 1)
    xp = j - frac  # tap positions relative to the interpolation point, samples
    h = np.sinc(xp) * np.i0(beta * np.sqrt(np.clip(1 - (xp / half_width) ** 2, 0, None))) / np.i0(beta)
    h /= h.sum()  # unit gain at DC
    M = half_width
    for a, b in zip(starts, stops):
        if b - a < 2 * M:
            continue
        # c[m] = Σ_i h[i]·x[a + m + i]: the value at row k = a + m + M − 1 − n0
        c = np.stack([np.correlate(x[a:b, col], h, mode="valid") for col in range(x.shape[1])], axis=1)
        k = a + np.arange(c.shape[0]) + M - 1 - n0
        keep = (k >= a) & (k < b)
        out[k[keep]] = c[keep]
    return out


def refine_frequency(x: np.ndarray, t: np.ndarray, f0: float, half_width_hz: float) -> float:
    """The frequency in f0 ± half_width maximising the periodogram |Σ x e^{−i2πft}|² of x (N,).

    Grid search (≥ 64 points over the interval, ≈ 16 per Fourier bin 1/T) then a bounded
    scalar refinement (scipy.optimize.minimize_scalar).
    """
    from scipy.optimize import minimize_scalar

    x = np.asarray(x, float) - np.mean(x)
    tt = np.asarray(t, float) - t[0]

    def power(f):
        if x.shape[0] <= LINE_CHUNK:
            ph = 2 * np.pi * f * tt
            return -(np.dot(x, np.cos(ph)) ** 2 + np.dot(x, np.sin(ph)) ** 2)
        c = s_ = 0.0
        for a, b in _spans(x.shape[0]):
            ph = 2 * np.pi * f * tt[a:b]
            c += np.dot(x[a:b], np.cos(ph))
            s_ += np.dot(x[a:b], np.sin(ph))
        return -(c**2 + s_**2)

    T = max(tt[-1], 1e-9)
    npts = int(min(max(64, 16 * 2 * half_width_hz * T), 2000))
    grid = np.linspace(max(f0 - half_width_hz, 1e-9), f0 + half_width_hz, npts)
    vals = np.array([power(f) for f in grid])
    j = int(np.argmin(vals))
    step = grid[1] - grid[0]
    r = minimize_scalar(
        power,
        bounds=(grid[max(j - 1, 0)], grid[min(j + 1, npts - 1)]),
        method="bounded",
        options={"xatol": step * 1e-3},
    )
    return float(r.x) if r.fun <= vals[j] else float(grid[j])


def fit_sinusoid(x: np.ndarray, t: np.ndarray, f_hz: float, *, X_window=None) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares a_cos, a_sin of a·cos(2πf t) + b·sin(2πf t) (+ constant) per column of x.

    ``X_window`` (M, 2) replaces the cos/sin columns when x is a window-mean series (the
    window operator applied to them). Returns (coef (2, C), standard errors (2, C), OLS).
    """
    x = np.asarray(x, float)
    if x.ndim == 1:
        x = x[:, None]
    if X_window is None and x.shape[0] > LINE_CHUNK:
        # normal equations summed a chunk at a time (B = [cos, sin, 1] over many periods is
        # well conditioned: cond(BᵀB) ≈ 2, so squaring it costs nothing at float64)
        t = np.asarray(t, float)
        G = np.zeros((3, 3))
        g = np.zeros((3, x.shape[1]))
        for a, b in _spans(x.shape[0]):
            ph = 2 * np.pi * f_hz * t[a:b]
            B = np.stack([np.cos(ph), np.sin(ph), np.ones_like(ph)], axis=1)
            G += B.T @ B
            g += B.T @ x[a:b]
        th = np.linalg.solve(G, g)
        rss = np.zeros(x.shape[1])
        for a, b in _spans(x.shape[0]):
            ph = 2 * np.pi * f_hz * t[a:b]
            B = np.stack([np.cos(ph), np.sin(ph), np.ones_like(ph)], axis=1)
            rss += np.sum((x[a:b] - B @ th) ** 2, axis=0)
        s2 = rss / max(x.shape[0] - 3, 1)
        cov = np.linalg.pinv(G)
        return th[:2], np.sqrt(np.outer(np.diag(cov)[:2], s2))
    if X_window is None:
        ph = 2 * np.pi * f_hz * np.asarray(t, float)
        B = np.stack([np.cos(ph), np.sin(ph), np.ones_like(ph)], axis=1)
    else:
        B = np.column_stack([X_window, np.ones(X_window.shape[0])])
    th, *_ = np.linalg.lstsq(B, x, rcond=None)
    r = x - B @ th
    s2 = np.sum(r**2, axis=0) / max(x.shape[0] - 3, 1)
    cov = np.linalg.pinv(B.T @ B)
    se = np.sqrt(np.outer(np.diag(cov)[:2], s2))
    return th[:2], se


def sinusoid_cv_reduction(x: np.ndarray, t: np.ndarray, f_hz: float, *, n_blocks: int = 10) -> float:
    """1 − RMS(predicted out of sample)/RMS(x − mean) of a sinusoid fitted on alternate blocks
    of time and predicted on the others (2-fold blocked, the loop's guard), x (N,)."""
    x = np.asarray(x, float)
    N = x.shape[0]
    if N > LINE_CHUNK:
        return _sinusoid_cv_chunked(x, np.asarray(t, float), f_hz, n_blocks)
    fold = (np.arange(N) * n_blocks // N) % 2 == 0
    ph = 2 * np.pi * f_hz * np.asarray(t, float)
    B = np.stack([np.cos(ph), np.sin(ph), np.ones_like(ph)], axis=1)
    Bo = B[:, 2:]
    err, err0 = [], []
    for tr, te in ((fold, ~fold), (~fold, fold)):
        th, *_ = np.linalg.lstsq(B[tr], x[tr], rcond=None)
        th0, *_ = np.linalg.lstsq(Bo[tr], x[tr], rcond=None)
        err.append(x[te] - B[te] @ th)
        err0.append(x[te] - Bo[te] @ th0)
    r1 = np.sqrt(np.mean(np.concatenate(err) ** 2))
    r0 = np.sqrt(np.mean(np.concatenate(err0) ** 2))
    return float(1.0 - r1 / r0) if r0 > 0 else 0.0


def _sinusoid_cv_chunked(x: np.ndarray, t: np.ndarray, f_hz: float, n_blocks: int) -> float:
    """:func:`sinusoid_cv_reduction` of a long series by normal equations summed a chunk at a
    time (per fold: the sinusoid + constant and the constant alone)."""
    N = x.shape[0]
    G = np.zeros((2, 3, 3))
    g = np.zeros((2, 3))

    def parts(a, b):
        ph = 2 * np.pi * f_hz * t[a:b]
        B = np.stack([np.cos(ph), np.sin(ph), np.ones_like(ph)], axis=1)
        fold = (np.arange(a, b) * n_blocks // N) % 2 == 0
        return B, fold

    for a, b in _spans(N):
        B, fold = parts(a, b)
        for k, sel in enumerate((fold, ~fold)):
            G[k] += B[sel].T @ B[sel]
            g[k] += B[sel].T @ x[a:b][sel]
    th = [np.linalg.lstsq(G[k], g[k], rcond=None)[0] for k in range(2)]
    th0 = [g[k][2] / G[k][2, 2] if G[k][2, 2] > 0 else 0.0 for k in range(2)]
    e2 = e02 = 0.0
    for a, b in _spans(N):
        B, fold = parts(a, b)
        for k, te in ((0, ~fold), (1, fold)):  # fitted on fold k, scored on the other
            e2 += float(np.sum((x[a:b][te] - B[te] @ th[k]) ** 2))
            e02 += float(np.sum((x[a:b][te] - th0[k]) ** 2))
    r1, r0 = np.sqrt(e2 / N), np.sqrt(e02 / N)
    return float(1.0 - r1 / r0) if r0 > 0 else 0.0


def sinusoid_rms(x: np.ndarray, t: np.ndarray, f_hz: float, a: float, b: float) -> tuple[float, float]:
    """RMS about the mean of x (N,) before and after removing a·cos(2πft) + b·sin(2πft)."""
    x = np.asarray(x, float)
    t = np.asarray(t, float)
    if x.shape[0] <= LINE_CHUNK:
        before = float(np.sqrt(np.mean((x - x.mean()) ** 2)))
        ph = 2 * np.pi * f_hz * t
        xa = x - a * np.cos(ph) - b * np.sin(ph)
        return before, float(np.sqrt(np.mean((xa - xa.mean()) ** 2)))
    N = x.shape[0]

    def after(a_, b_):
        s = 0.0
        for p, q in _spans(N):
            ph = 2 * np.pi * f_hz * t[p:q]
            s += float(np.sum(x[p:q] - a_ * np.cos(ph) - b_ * np.sin(ph)))
        m = s / N
        s2 = 0.0
        for p, q in _spans(N):
            ph = 2 * np.pi * f_hz * t[p:q]
            s2 += float(np.sum((x[p:q] - a_ * np.cos(ph) - b_ * np.sin(ph) - m) ** 2))
        return float(np.sqrt(s2 / N))

    return after(0.0, 0.0), after(a, b)
