"""The still/motion gate: which windows of a gyro record a still sensor could have produced.

A still sensor reads its bias plus noise; within a short window the bias is constant, so the
window's **sample variance** (mean removed) is the noise's. Per axis i, for a window of n samples
with mean x̄,

    s_i² = 1/(n − 1) · Σ_k (x_ik − x̄_i)²,    ν s_i² / σ_i² ~ χ²(ν) at rest,

with σ_i² the per-sample noise variance and ν = n − 1 for white noise (for coloured noise, e.g.
an on-chip low-pass, Bartlett's effective ν = (n − 1)/(1 + 2 Σ_k (1 − k/n) r_k²), r_k the noise
autocorrelation). A window is **still** when every axis passes

    s_i² ≤ σ_i² · χ²_ν(1 − α_axis) / ν,    α_axis = 1 − (1 − α)^(1/3),

so a window of a still sensor is refused with probability α (``false_reject_rate``, all three
axes together, independent axes). Motion adds its own variance: a rate step h inside the window
adds ≈ h²/4, a ramp a adds (a·dt)² (n² − 1)/12; a constant rotation rate adds none and is not
caught by any gyro-only variance test (``mean_tolerance_rad_s`` adds a test of the window mean
against the still windows' median for that case).

σ² is the record's own unless given (``noise_sigma_rad_s``): the ``noise_quantile`` quantile of
the window variances divided by χ²_ν's (consistent while that fraction of the windows is still),
with ν measured from the autocorrelation of the quiet windows. When fewer than 10 windows exist,
or that estimate is implausibly above the noise of the sample-to-sample differences (smooth
motion in most windows inflates every window variance but barely changes the differences), σ² is
σ_Δ²/2 from the robust (MAD) σ_Δ of the first differences.

``statistic="abs_diff"`` is the seed article's S = Σ_{k=1}^{n−1} |Δ_k| (Δ the first differences):
E S = m σ_Δ √(2/π), Var S = m σ_Δ² (1 − 2/π) + 2(m − 1) σ_Δ² (2/π)(√(1 − ρ²) + ρ asin ρ − 1)
(m = n − 1, ρ = corr(Δ_k, Δ_k+1)); its threshold is the α_axis upper quantile of a gamma law with
that mean and variance. It reacts to high-frequency vibration but is ~50× less sensitive to slow
motion than the variance. ``threshold`` fixes the threshold instead of deriving it (the article's
500 raw counts).

:func:`still_windows` reads the record a block of windows at a time through the one chunk source
(:func:`gyrocore.data.columns.columns_of`: an (N, 3) array or a Recording in memory, views; a
:class:`gyrocore.data.spill.ColumnSpill` on disk): the same arithmetic on the same windows, so a record on disk gets exactly the numbers of the same
record in memory, with memory O(block + one column). Every caller passes its own
:class:`StillGate`: ``calib.bias.StaticBiasCalibrator.still_gate``, ``calib.rotations.STILL_GATE``,
``loop.residual.STILL_GATE``, and the noise analysis's 2-s gate (``noise.allan``).
"""

from __future__ import annotations

import math
from typing import Sequence
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np
import scipy.stats

from gyrocore.errors import GyroInputError, warn_repair

from .checks import robust_diff_sigma
from .columns import columns_of
from .recording import GYRO_COLS

__all__ = [
    "StillGate",
    "StillWindows",
    "still_windows",
    "gate_threshold",
    "robust_diff_noise",
    "abs_diff_moments",
    "runs",
    "windows_touching",
    "still_samples",
    "moving_throughout",
    "NOISE_RATIO_BOUND",
    "MIN_WINDOWS_FOR_QUANTILE",
]

STATISTICS = ("variance", "abs_diff")
#: Fewer windows than this: the noise comes from the first differences, not a window quantile.
MIN_WINDOWS_FOR_QUANTILE = 10
NOISE_RATIO_BOUND = 4.0
"""Largest accepted ratio of the window-variance σ² to the AR(1) prediction from differences."""
#: Bytes of gyro read per block of windows (a fresh array from disk, a view in memory).
BLOCK_BYTES = 4 * 2**20


@dataclass(frozen=True)
class StillGate:
    """Options of the still gate (see the module docstring for the test and its statistic).

    Parameters
    ----------
    window_s : float
        Window length, s (converted with the sample rate: n = round(window_s · rate)).
    window_samples : int, optional
        Window length in samples; overrides ``window_s``.
    false_reject_rate : float
        α: probability that a window of a still sensor is refused (all axes together).
    statistic : {"variance", "abs_diff"}
        The per-window statistic: sample variance s² (χ² test) or the article's Σ|Δ|.
    noise_sigma_rad_s : float or tuple of 3 floats, optional
        Per-sample white-noise σ of the sensor (N·√rate); default: measured from the record.
    noise_quantile : float
        Quantile of the window variances that estimates σ² (that fraction must be still).
    noise_from : {"auto", "windows"}
        Where σ² comes from when not given: ``"auto"`` the window-variance quantile when there are
        ≥ :data:`MIN_WINDOWS_FOR_QUANTILE` windows and it is plausible, else the first differences
        (σ_Δ²/2); ``"windows"`` always the quantile (for callers that exclude the known motion, so
        the windows left are mostly still, and whose sensors' on-chip low-pass makes σ_Δ²/2 too
        small).
    dof : {"measured", "white"}
        ν of a window variance: from the quiet windows' autocorrelation (Bartlett), or n − 1.
    max_lag : int
        Lags of that autocorrelation.
    variance_factor : float
        Multiplies the derived threshold (e.g. 1.5² lets a hand-held pose tremble 1.5 × the
        still noise's standard deviation); 1 keeps the stated false-reject rate.
    threshold : float, optional
        A fixed threshold (units of the statistic) instead of the derived one (α is then not
        the false-reject rate; reported as nan).
    mean_tolerance_rad_s : float, optional
        Also require |window mean − median of the still windows' means| ≤ this (plus
        ``mean_tolerance_sigmas`` × the per-sample σ) on every axis: catches a constant rotation,
        which adds no variance. None: no mean test.
    mean_tolerance_sigmas : float
    """

    window_s: float = 2.0
    window_samples: int | None = None
    false_reject_rate: float = 1e-3
    statistic: str = "variance"
    noise_sigma_rad_s: float | tuple[float, float, float] | None = None
    noise_quantile: float = 0.25
    noise_from: str = "auto"
    dof: str = "measured"
    max_lag: int = 5
    variance_factor: float = 1.0
    threshold: float | None = None
    mean_tolerance_rad_s: float | None = None
    mean_tolerance_sigmas: float = 0.0

    def __post_init__(self) -> None:
        if self.statistic not in STATISTICS:
            raise GyroInputError(f"unknown gate statistic {self.statistic!r}; use abs_diff or variance")
        if not (0.0 < self.false_reject_rate < 1.0):
            raise GyroInputError(f"false_reject_rate must be in (0, 1), got {self.false_reject_rate}")
        if self.window_samples is None and not (self.window_s > 0):
            raise GyroInputError(f"still window must be positive, got {self.window_s} s")
        if self.noise_from not in ("auto", "windows"):
            raise GyroInputError(f"noise_from must be 'auto' or 'windows', got {self.noise_from!r}")
        if self.dof not in ("measured", "white"):
            raise GyroInputError(f"dof must be 'measured' or 'white', got {self.dof!r}")
        if not (0.0 < self.noise_quantile < 1.0):
            raise GyroInputError(f"noise_quantile must be in (0, 1), got {self.noise_quantile}")

    def samples(self, rate_hz: float) -> int:
        """Window length in samples at ``rate_hz``."""
        if self.window_samples is not None:
            return int(self.window_samples)
        return int(round(self.window_s * rate_hz))

    def alpha_axis(self, false_reject_rate: float | None = None) -> float:
        """Per-axis rate 1 − (1 − α)^(1/3)."""
        a = self.false_reject_rate if false_reject_rate is None else float(false_reject_rate)
        return 1.0 - (1.0 - a) ** (1.0 / 3.0)


@dataclass(frozen=True, eq=False)
class StillWindows:
    """The gate's verdict on the non-overlapping windows of a record.

    Window k covers samples ``k·n .. (k+1)·n − 1``; the ``n_samples − W·n`` samples after the
    last whole window are not judged.

    Attributes
    ----------
    still : ndarray of bool, shape (W,)
    statistic : ndarray, shape (W, 3)
        Per-window statistic (``statistic_name``; (rad/s)² for variance, rad/s for abs_diff).
    statistic_name : str
    threshold : ndarray, shape (3,)
    window_samples, n_samples : int
    rate_hz : float
    false_reject_rate : float
        α the threshold was derived for (nan for a fixed threshold).
    sigma_diff_rad_s, diff_corr : ndarray, shape (3,)
        σ_Δ and ρ of the first differences (white-noise values when σ was given).
    sigma2 : ndarray, shape (3,)
        Per-sample noise variance σ² the variance threshold uses, (rad/s)².
    dof : ndarray, shape (3,)
        ν of a window variance.
    noise_note : str
        Why the window-variance noise was not used ('' when it was, or not needed).
    excluded : ndarray of bool, shape (W,)
        Windows the caller excluded (never still, not used for the noise).
    means : ndarray, shape (W, 3)
        Window means, rad/s.
    variance : ndarray, shape (W, 3)
        Window sample variances, (rad/s)² (the statistic itself for ``"variance"``).
    gate : StillGate
        The options that made it.
    """

    still: np.ndarray
    statistic: np.ndarray
    statistic_name: str
    threshold: np.ndarray
    window_samples: int
    n_samples: int
    rate_hz: float
    false_reject_rate: float
    sigma_diff_rad_s: np.ndarray
    diff_corr: np.ndarray
    sigma2: np.ndarray
    dof: np.ndarray
    noise_note: str = ""
    excluded: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    means: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    variance: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    gate: StillGate = StillGate()

    @property
    def n_windows(self) -> int:
        return int(self.still.size)

    @property
    def fraction(self) -> float:
        """Fraction of the windows that are still (nan without windows)."""
        return float(self.still.mean()) if self.still.size else float("nan")

    def still_at(self, false_reject_rate: float) -> np.ndarray:
        """The verdict of the same statistic and noise at another false-reject rate, (W,) bool."""
        thr = gate_threshold(
            replace(self.gate, false_reject_rate=float(false_reject_rate)),
            self.window_samples,
            self.sigma_diff_rad_s,
            self.diff_corr,
            sigma2=self.sigma2,
            dof=self.dof,
        )
        return np.all(self.statistic <= thr[None, :], axis=1) & ~self.excluded

    def sample_mask(self, still: np.ndarray | None = None) -> np.ndarray:
        """Per-sample mask, shape (N,): samples of still windows (the unjudged tail False)."""
        s = self.still if still is None else np.asarray(still, bool)
        out = np.zeros(self.n_samples, bool)
        out[: s.size * self.window_samples] = np.repeat(s, self.window_samples)
        return out


# ---------------------------------------------------------------------------- noise
def robust_diff_noise(x) -> tuple[np.ndarray, np.ndarray]:
    """Robust σ_Δ (std of first differences) and ρ = corr(Δ_k, Δ_k+1) per column.

    σ_Δ = 1.4826·MAD(Δ); Var(x[k+2] − x[k]) = 2σ_Δ²(1 + ρ) gives ρ from the MAD of lag-2
    differences (insensitive to sparse motion). The plain standard deviation when the MAD is 0
    (output quantized more coarsely than its noise). One column at a time, each difference formed
    in place in a fresh copy of the column: memory one column.

    Parameters
    ----------
    x : ndarray, shape (N, 3), a Recording, or a chunk source of its columns (:func:`columns_of`)
        Rate, rad/s, sensor frame S.

    Returns
    -------
    sigma_diff : ndarray, shape (3,)
    rho : ndarray, shape (3,), clipped to [−0.95, 0.95]
    """
    src = columns_of(x)
    if src.n < 4:
        raise GyroInputError(f"need at least 4 samples to estimate the noise, got {src.n}")
    s1, s2 = np.empty(len(GYRO_COLS)), np.empty(len(GYRO_COLS))
    for j, name in enumerate(GYRO_COLS):
        for lag, out in ((1, s1), (2, s2)):
            out[j] = robust_diff_sigma(partial(src.column, name), lag=lag, zero_mad="std")  # a fresh read per call
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(s1 > 0, s2**2 / (2 * s1**2) - 1.0, -0.5)
    return s1, np.clip(rho, -0.95, 0.95)


def _refuse_constant(sigma_diff: np.ndarray, src) -> None:
    """One error line when a gyro axis never changes (σ_Δ = 0).

    Its output is quantized more coarsely than its noise (INAV logs gyroADC, after a 30-Hz
    low-pass, rounded to 1 deg/s: a quad at rest reads exactly 0 on every axis); no gate, noise or
    bias error can be derived from it.
    """
    flat = [i for i in range(min(3, sigma_diff.size)) if not sigma_diff[i] > 0]
    if flat:
        first = src.block(GYRO_COLS, 0, 1)
        vals = " (" + ", ".join(f"{'xyz'[i]} = {float(first[0, i]):.6g} rad/s" for i in flat) + ")"
        raise GyroInputError(
            f"gyro axis {', '.join('xyz'[i] for i in flat)} never changes over the record{vals}: its output is "
            "quantized more coarsely than its noise (e.g. a filtered gyro rounded to 1 deg/s), so no noise, gate or "
            "bias error can be measured from this record (a finer output is needed)"
        )


def abs_diff_moments(m: int, sigma_diff: np.ndarray, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance of S = Σ_{k=1}^{m} |Δ_k| for Gaussian Δ (σ_Δ, lag-1 correlation ρ)."""
    sd = np.asarray(sigma_diff, float)
    rho = np.asarray(rho, float)
    mean = m * sd * math.sqrt(2.0 / math.pi)
    v1 = sd**2 * (1.0 - 2.0 / math.pi)
    c1 = (2.0 / math.pi) * sd**2 * (np.sqrt(1.0 - rho**2) + rho * np.arcsin(rho) - 1.0)
    var = m * v1 + 2.0 * max(m - 1, 0) * c1
    return mean, var


def _variance_or_abs_threshold(statistic, alpha_axis, n, sigma_diff, rho, sigma2, dof) -> np.ndarray:
    if statistic == "abs_diff":
        mean, var = abs_diff_moments(n - 1, sigma_diff, rho)
        return np.asarray(scipy.stats.gamma.isf(alpha_axis, mean**2 / var, scale=var / mean), float)
    return np.asarray(sigma2, float) * scipy.stats.chi2.isf(alpha_axis, dof) / np.asarray(dof, float)


def gate_threshold(
    gate: StillGate,
    n: int,
    sigma_diff: np.ndarray,
    rho: np.ndarray,
    *,
    sigma2: np.ndarray | None = None,
    dof: np.ndarray | None = None,
) -> np.ndarray:
    """Per-axis threshold (3,) of ``gate`` for windows of n samples.

    variance: σ² χ²_ν(1 − α_axis)/ν × ``variance_factor`` (σ² default σ_Δ²/2, ν default n − 1);
    abs_diff: the gamma-law quantile of Σ|Δ| (module docstring); a fixed ``gate.threshold`` as is.
    """
    if gate.threshold is not None:
        return np.full(3, float(gate.threshold))
    sd = np.asarray(sigma_diff, float)
    s2 = sd**2 / 2.0 if sigma2 is None else np.asarray(sigma2, float)
    nu = np.full(3, float(n - 1)) if dof is None else np.asarray(dof, float)
    thr = _variance_or_abs_threshold(gate.statistic, gate.alpha_axis(), n, sd, rho, s2, nu)
    return thr * (float(gate.variance_factor) if gate.statistic == "variance" else 1.0)


def _check_noise_plausible(sigma2: np.ndarray, sigma_diff: np.ndarray, rho: np.ndarray) -> str:
    """'' when the window-variance σ² is plausible noise, else why not (one phrase).

    For stationary noise σ² = σ_Δ²/(2(1 − r₁)); for AR(1) noise (an on-chip low-pass,
    coefficient φ) r₁ = φ and ρ = −(1 − φ)/2, so σ²/(σ_Δ²/2) = −1/(2ρ) (1 for white noise). ρ is
    clipped to ≤ −0.1 (φ ≤ 0.8) so that motion, which drives the measured ρ towards 0, cannot raise
    the allowance without bound. A still record passes unless σ² exceeds that prediction by
    :data:`NOISE_RATIO_BOUND` = 4: at ≥ 10 windows of ≥ 8 samples the quantile estimate errs by a
    few tens of per cent at most, and the static MPU-6050 and PX4 logs give 0.85…1.5.
    """
    expected = np.asarray(sigma_diff, float) ** 2 / 2.0 * np.maximum(1.0, -1.0 / (2.0 * np.minimum(rho, -0.1)))
    ratio = np.asarray(sigma2, float) / expected
    if not np.any(ratio > NOISE_RATIO_BOUND):
        return ""
    i = int(np.argmax(ratio))
    return (
        f"the window variances imply a noise sigma of {math.degrees(math.sqrt(float(sigma2[i]))):.3g} deg/s on axis "
        f"{'xyz'[i]} but its sample-to-sample differences only {math.degrees(math.sqrt(float(expected[i]))):.3g} "
        f"deg/s (variance ratio {ratio[i]:.3g} > {NOISE_RATIO_BOUND:g})"
    )


def _window_noise(gate: StillGate, n: int, var: np.ndarray, lags: np.ndarray, use: np.ndarray, rho: np.ndarray):
    """σ² (3,) and ν (3,) from the window variances ``var`` (W, 3) of the windows ``use``.

    σ² = q-quantile of the window variances / (χ²_ν(q)/ν); ν = n − 1 (``dof="white"``) or
    (n − 1)/(1 + 2 Σ_k (1 − k/n)(r_k + VIF/n)²) (Bartlett's variance of a sample variance, r_k
    pooled over the windows with s² ≤ 4σ², its demeaning bias −VIF/n added back), two passes.
    ``lags`` (W, L + 1, 3): per-window Σ d_k d_k+l of the demeaned samples, l = 0..L.
    """
    cand = var[use]
    q = gate.noise_quantile
    qv = np.quantile(cand, q, axis=0)
    dof = np.full(3, float(n - 1))
    if gate.dof == "measured":
        L = lags.shape[1] - 1
        for _ in range(2):  # white start, then with the measured correlation
            sigma2 = qv / (scipy.stats.chi2.ppf(q, dof) / dof)
            quiet = use & np.all(var <= 4.0 * sigma2[None, :], axis=1)
            s = lags[quiet].sum(axis=0)  # (L + 1, 3)
            with np.errstate(divide="ignore", invalid="ignore"):
                r = [s[k] / s[0] for k in range(1, L + 1)]
            vif = np.ones(3)
            for _ in range(3):
                vif = 1.0 + sum(2.0 * (1.0 - k / n) * (rk + vif / n) for k, rk in enumerate(r, 1))
            corr = sum(2.0 * (1.0 - k / n) * (rk + vif / n) ** 2 for k, rk in enumerate(r, 1))
            dof = (n - 1) / (1.0 + corr)
    sigma2 = qv / (scipy.stats.chi2.ppf(q, dof) / dof)
    return sigma2, dof


# ---------------------------------------------------------------------------- the gate
def _window_pass(src, n: int, W: int, statistic: str, lag_max: int | None, block_bytes: int):
    """One pass over the windows: statistic (W, 3), variance (W, 3), means (W, 3), and the
    per-window lag products (W, L + 1, 3) when ``lag_max`` is given."""
    stat = np.empty((W, 3))
    var = np.empty((W, 3))
    means = np.empty((W, 3))
    lags = None if lag_max is None else np.zeros((W, lag_max + 1, 3))
    per = max(1, int(block_bytes) // max(1, n * 3 * 8))
    for a in range(0, W, per):
        b = min(a + per, W)
        blk = np.asarray(src.block(GYRO_COLS, a * n, b * n), float).reshape(b - a, n, 3)
        means[a:b] = blk.mean(axis=1)
        var[a:b] = blk.var(axis=1, ddof=1)
        if statistic == "abs_diff":
            stat[a:b] = np.abs(np.diff(blk, axis=1)).sum(axis=1)
        if lags is not None:
            d = blk - means[a:b, None, :]
            lags[a:b, 0] = np.einsum("wnc,wnc->wc", d, d)
            for k in range(1, lag_max + 1):
                lags[a:b, k] = np.einsum("wnc,wnc->wc", d[:, k:], d[:, :-k])
        del blk
    if statistic == "variance":
        stat = var
    return stat, var, means, lags


def still_windows(
    gyro,
    rate_hz: float,
    gate: StillGate = StillGate(),
    *,
    exclude: np.ndarray | None = None,
    block_bytes: int = BLOCK_BYTES,
) -> StillWindows:
    """Judge every whole window of ``gyro`` with ``gate``: the one still/motion gate.

    Parameters
    ----------
    gyro : ndarray (N, 3), a Recording, or a chunk source of its columns
        (:func:`gyrocore.data.columns.columns_of`; a :class:`gyrocore.data.spill.ColumnSpill`
        for a record on disk)
        Rate, rad/s, sensor frame S, evenly spaced at ``rate_hz``; from disk the same numbers
        as in memory, read a block of windows at a time.
    rate_hz : float
    gate : StillGate
    exclude : ndarray of bool, shape (W,), optional
        Windows never still and left out of the noise estimate (e.g. known rotations).
    block_bytes : int
        Gyro bytes per block of windows (memory; the result does not depend on it).

    Returns
    -------
    StillWindows

    Raises
    ------
    GyroInputError
        No sample rate, a window under 8 samples, a record shorter than one window, or an axis
        that never changes.
    """
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise GyroInputError("cannot find still parts: unknown sample rate")
    src = columns_of(gyro)
    n = gate.samples(rate_hz)
    if n < 8:
        raise GyroInputError(f"still window of {n} samples is too short (need >= 8)")
    N = src.n
    W = N // n
    if W < 1:
        raise GyroInputError(f"recording has {N} samples, shorter than one still window of {n} samples")
    excl = np.zeros(W, bool) if exclude is None else np.asarray(exclude, bool)
    if excl.shape != (W,):
        raise GyroInputError(f"exclude must have one entry per window ({W}), got shape {excl.shape}")
    if gate.noise_sigma_rad_s is not None:
        s = np.broadcast_to(np.asarray(gate.noise_sigma_rad_s, float), (3,)).copy()
        if not np.all(s > 0):
            raise GyroInputError("noise_sigma_rad_s must be positive")
        sigma_diff, rho = s * math.sqrt(2.0), np.full(3, -0.5)
    else:
        sigma_diff, rho = robust_diff_noise(src)
        _refuse_constant(sigma_diff, src)
    use = ~excl if np.any(~excl) else np.ones(W, bool)
    quantile = (
        gate.statistic == "variance"
        and gate.threshold is None
        and gate.noise_sigma_rad_s is None
        and (gate.noise_from == "windows" or int(use.sum()) >= MIN_WINDOWS_FOR_QUANTILE)
    )
    L = min(int(gate.max_lag), n - 2) if quantile and gate.dof == "measured" else None
    stat, var, means, lags = _window_pass(src, n, W, gate.statistic, L, block_bytes)
    sigma2, dof, note = sigma_diff**2 / 2.0, np.full(3, float(n - 1)), ""
    if quantile:
        s2q, dofq = _window_noise(gate, n, var, lags if lags is not None else np.zeros((W, 1, 3)), use, rho)
        if gate.noise_from == "windows":  # a quantized axis still at the quantile: the largest σ² of the others
            top = float(np.max(s2q))
            sigma2, dof = np.where(s2q > 0, s2q, top if top > 0 else 1e-30), dofq
        else:
            note = _check_noise_plausible(s2q, sigma_diff, rho)
            if not note:
                sigma2, dof = s2q, dofq
    elif (
        gate.statistic == "variance"
        and gate.threshold is None
        and gate.noise_sigma_rad_s is None
        and np.any(np.abs(rho + 0.5) > 0.1)
    ):
        warn_repair(
            "gyro noise is not white (lag-1 correlation of differences "
            + ", ".join(f"{r:.2f}" for r in rho)
            + ", white = -0.50) and the recording is too short to measure its correlation: "
            "the variance gate's false-reject rate is approximate"
        )
    thr = gate_threshold(gate, n, sigma_diff, rho, sigma2=sigma2, dof=dof)
    still = np.all(stat <= thr[None, :], axis=1) & ~excl
    if gate.mean_tolerance_rad_s is not None and still.any():
        tol = float(gate.mean_tolerance_rad_s) + float(gate.mean_tolerance_sigmas) * np.sqrt(sigma2)
        med = np.median(means[still], axis=0)
        still &= np.all(np.abs(means - med[None, :]) <= tol[None, :], axis=1)
    return StillWindows(
        still=still,
        statistic=stat,
        statistic_name=gate.statistic,
        threshold=thr,
        window_samples=n,
        n_samples=N,
        rate_hz=float(rate_hz),
        false_reject_rate=float("nan") if gate.threshold is not None else gate.false_reject_rate,
        sigma_diff_rad_s=sigma_diff,
        diff_corr=rho,
        sigma2=np.asarray(sigma2, float),
        dof=np.asarray(dof, float),
        noise_note=note,
        excluded=excl,
        means=means,
        variance=var,
        gate=gate,
    )


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Runs of True in a 1-D mask as half-open index ranges [a, b), in order."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]]).astype(np.int8)
    d = np.diff(m)
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def windows_touching(
    t_s: np.ndarray, window_samples: int, spans: Sequence[tuple[float, float]], margin_s: float = 0.0
) -> np.ndarray:
    """Windows (W,) bool that hold a sample of any span [a − margin_s, b + margin_s] (s), e.g. known
    rotations to keep out of :func:`still_windows` (``exclude``)."""
    t = np.asarray(t_s, float)
    n = int(window_samples)
    W = t.shape[0] // n
    hit = np.zeros(t.shape[0], bool)
    for a, b in spans:
        hit |= (t >= a - margin_s) & (t <= b + margin_s)
    return hit[: W * n].reshape(W, n).any(axis=1)


def still_samples(
    recording,
    gate: StillGate,
    *,
    exclude_s: Sequence[tuple[float, float]] = (),
    margin_s: float = 0.0,
    min_windows: int = 2,
) -> np.ndarray:
    """Per-sample still mask (N,) of an in-memory :class:`gyrocore.data.recording.Recording`:
    :func:`still_windows` at its mean rate, the windows touching any span of ``exclude_s``
    (s, widened by ``margin_s``) excluded. All False when the record holds fewer than
    ``min_windows`` windows (too short to judge: the caller says what no still part means)."""
    rate = recording.rate_hz
    if not (math.isfinite(rate) and rate > 0):
        raise GyroInputError("cannot find still parts: unknown sample rate")
    n = gate.samples(rate)
    if recording.n < max(int(min_windows), 1) * max(n, 1):
        return np.zeros(recording.n, bool)
    excl = windows_touching(recording.t_s, n, exclude_s, margin_s) if len(exclude_s) else None
    return still_windows(recording.gyro_rad_s, rate, gate, exclude=excl).sample_mask()


def moving_throughout(recording, gate: StillGate) -> str:
    """'' unless the windows ``gate`` calls still are the quietest part of a record that moves
    throughout; returns why, in one phrase.

    Their noise (the median of their window variances, ≈ σ² for ν ≳ 30) is set against what the
    sample-to-sample differences of the record predict (σ_Δ²/2, raised for an on-chip low-pass
    as in the ``noise_from="auto"`` test); more than :data:`NOISE_RATIO_BOUND` times it is
    motion. A gate with ``noise_from="windows"`` (the rotation calibrations: the known motion
    excluded, the rest mostly still) takes σ² from the window-variance quantile whatever the
    windows hold; a caller that has excluded nothing asks this first, so that a hand-rotated or
    flown record does not yield "still" windows that are its slowest motion (a sunsided rotate-*
    run gave a 15 deg/s "bias"). Still windows of a genuinely still part pass (ratio ≈ 1: the
    static MPU-6050, PX4 and gnss-ins-sim records give 0.85-1.5).
    """
    rate = recording.rate_hz
    n = gate.samples(rate)
    if recording.n < 2 * max(n, 1):
        return ""
    sw = still_windows(recording.gyro_rad_s, rate, gate)
    if not sw.still.any():
        return ""
    return _check_noise_plausible(np.median(sw.variance[sw.still], axis=0), sw.sigma_diff_rad_s, sw.diff_corr)
