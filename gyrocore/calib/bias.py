"""Power-up (static) gyro bias with a motion gate — the seed article's §1, made range-independent.

The article averages 200 samples at rest and refuses while moving: per axis it sums
Σ|g[k] − g[k−1]| over the window and rejects when any axis exceeds 500 raw counts. A fixed
count threshold depends on the range setting: at ±250 °/s an MPU-6050 at rest already sums
≈ 2200–3300 counts per 200 samples, so that gate never lets it calibrate (shown on the
tomisuarez2 static set in the tests and docs/noise.md).

Here the threshold is derived from the sensor's own noise for a stated false-reject rate
at rest α (probability that a window of a still sensor is rejected, all axes together):

- ``statistic="abs_diff"`` (the article's statistic). With first differences Δ of
  stationary Gaussian noise (σ_Δ² = Var Δ, ρ = corr(Δ_k, Δ_k+1), −1/2 for white noise),
  S = Σ_{k=1}^{m}|Δ_k| (m = n − 1) has
  E S = m σ_Δ √(2/π),
  Var S = m σ_Δ² (1 − 2/π) + 2 (m − 1) σ_Δ² (2/π)(√(1−ρ²) + ρ asin ρ − 1)
  (bivariate half-normal covariance; lags ≥ 2 neglected, exact for white noise).
  The threshold is the upper α_axis quantile of a gamma law with that mean and variance
  (the Gaussian quantile under-covers: S is right-skewed; the gamma law is slightly
  conservative, measured 2.7e-4 for a nominal 3.3e-4 at n = 200).
- ``statistic="variance"``: (n − 1) s²/σ² ~ χ²(n − 1) at rest under white noise (exact).

α_axis = 1 − (1 − α)^(1/3) (independent axes). σ_Δ and ρ are estimated robustly from the
whole recording (MAD of lag-1 and lag-2 differences, insensitive to sparse motion) unless the
sensor's white-noise σ (or density N, σ = N √rate) is given. The result states the smallest
motion that the gate catches half of the time: a rate step inside the window and a rate ramp
(constant angular acceleration) over it. A constant rotation rate cannot be told from bias by a
gyro alone and is not caught by any gyro-only gate.

Rules: ``"mean"`` (the article), ``"median"`` (PX4-like, robust to spikes), ``"converge"``
(ArduPilot-like: consecutive window means until they agree within a tolerance),
``"article"`` (the article's fixed raw-count threshold, for comparison).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import scipy.optimize
import scipy.stats

from gyrocore.errors import GyroInputError, warn_repair
from gyrocore.data.columns import columns_of
from gyrocore.data.recording import GYRO_COLS, Recording
from gyrocore.data.still import StillGate, abs_diff_moments, gate_threshold, still_windows

__all__ = [
    "StaticBiasCalibrator",
    "StaticBiasResult",
    "startup_still_slice",
    "FORMAT_VERSION",
]

FORMAT_VERSION = "1.0"
RULES = ("mean", "median", "converge", "article")
STATISTICS = ("abs_diff", "variance")


@dataclass(frozen=True, eq=False)
class StaticBiasResult:
    """Static bias estimate and what the motion gate did.

    Attributes
    ----------
    bias_rad_s : ndarray, shape (3,)
        Bias per sensor axis, rad/s.
    bias_se_rad_s : ndarray, shape (3,)
        Standard error: σ√VIF/√n (mean), √(π/2)·σ√VIF/√n (median), with VIF the variance
        inflation of the window mean from the noise autocorrelation (1 for white noise).
    rule, statistic : str
    window_start_index, window_samples : int
        First sample and length of the data that made the estimate (two windows for
        ``"converge"``).
    window_start_s, window_s : float
        The same in seconds (window_s = samples / mean rate).
    n_rejected_windows : int
        Windows refused before the accepted one.
    n_windows_total, n_windows_still : int
        Windows in the recording and how many of them pass the gate.
    false_reject_rate : float
        Stated probability that a window of a still sensor is refused (all axes), nan for
        ``"article"`` (not derived).
    threshold : ndarray, shape (3,)
        Per-axis gate threshold, in ``threshold_units``.
    threshold_units : str
        ``"rad/s"`` (sum of |Δ|, abs_diff), ``"(rad/s)^2"`` (variance) or ``"rad/s"`` for the
        converge tolerance (Mahalanobis radius of the mean difference, see notes).
    noise_sigma_rad_s : ndarray, shape (3,)
        Per-sample white-noise σ used (σ_Δ/√2).
    diff_corr : ndarray, shape (3,)
        ρ = corr(Δ_k, Δ_k+1) used (−0.5 for white noise).
    vif : ndarray, shape (3,)
        Variance inflation factor of the window mean.
    min_step_rad_s : ndarray, shape (3,)
        Smallest rate step inside a window detected with 50 % probability.
    min_ramp_rad_s2 : ndarray, shape (3,)
        Smallest constant angular acceleration over a window detected with 50 % probability.
    units : str
    format_version : str
    """

    bias_rad_s: np.ndarray
    bias_se_rad_s: np.ndarray
    rule: str
    statistic: str
    window_start_index: int
    window_samples: int
    window_start_s: float
    window_s: float
    n_rejected_windows: int
    n_windows_total: int
    n_windows_still: int
    false_reject_rate: float
    threshold: np.ndarray
    threshold_units: str
    noise_sigma_rad_s: np.ndarray
    diff_corr: np.ndarray
    vif: np.ndarray
    min_step_rad_s: np.ndarray
    min_ramp_rad_s2: np.ndarray
    units: str = "rad/s"
    format_version: str = FORMAT_VERSION


# ---------------------------------------------------------------------------- pure helpers
def _folded_mean(mu: float, s: float) -> float:
    """E|X| for X ~ N(mu, s²)."""
    return s * math.sqrt(2 / math.pi) * math.exp(-mu * mu / (2 * s * s)) + mu * (1 - 2 * scipy.stats.norm.cdf(-mu / s))


def _solve_increasing(f, target: float, hi0: float) -> float:
    """Smallest x ≥ 0 with f(x) = target, f increasing; nan if not reachable."""
    if f(0.0) >= target:
        return 0.0
    hi = hi0
    for _ in range(200):
        if f(hi) >= target:
            break
        hi *= 2
    else:
        return float("nan")
    return float(scipy.optimize.brentq(lambda x: f(x) - target, 0.0, hi, xtol=hi * 1e-10))


#: Records larger than this (bytes of the (N, 3) gyro) have their per-window statistics
#: computed a block of windows at a time (memory O(block) instead of several copies of the
#: record); smaller records take the whole-array path unchanged.
_BLOCK_BYTES = 32 * 2**20


def _blocks(W: int, n: int, width: int, block_bytes: int | None = None):
    """Window ranges [a, b) of about ``block_bytes`` (default _BLOCK_BYTES) each (one range
    when the record is small)."""
    block_bytes = _BLOCK_BYTES if block_bytes is None else int(block_bytes)
    per = max(1, block_bytes // max(1, n * width * 8))
    if W * n * width * 8 <= block_bytes:
        per = max(W, 1)
    return [(a, min(a + per, W)) for a in range(0, W, per)]


class GyroWindows:
    """Non-overlapping windows of n samples of the gyro of a chunk source
    (:mod:`gyrocore.data.columns`: a recording in memory or its columns on disk), shape (W, n, 3)
    like ``x[:W*n].reshape(W, n, 3)``, read a block of windows at a time (:meth:`block`, blocks
    of the source's ``block_bytes``); the window statistics of this module take it in place
    of an in-memory array and do the same arithmetic on the same blocks."""

    def __init__(self, cols, n: int) -> None:
        self.cols = cols
        self.shape = (cols.n // n, n, 3)
        self.block_bytes = cols.block_bytes

    def block(self, a: int, b: int) -> np.ndarray:
        """Windows a:b, shape (b − a, n, 3) (a view in memory, a fresh array from disk)."""
        n = self.shape[1]
        return self.cols.block(GYRO_COLS, a * n, b * n).reshape(b - a, n, 3)

    def __getitem__(self, k: int) -> np.ndarray:
        return self.block(k, k + 1)[0]


def _wblock(xw, a: int, b: int) -> np.ndarray:
    return xw[a:b] if isinstance(xw, np.ndarray) else xw.block(a, b)


def _lag_sums(xw, sel: np.ndarray, L: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """c0 and the lag-k cross sums of the demeaned selected windows, block by block."""
    W, n, C = xw.shape
    c0 = np.zeros(C)
    ck = [np.zeros(C) for _ in range(L)]
    for a, b in _blocks(W, n, C, getattr(xw, "block_bytes", None)):
        s = sel[a:b]
        if not s.any():
            continue
        blk = _wblock(xw, a, b)[s]
        d = blk - blk.mean(axis=1, keepdims=True)
        del blk
        c0 = c0 + np.einsum("wnc,wnc->c", d, d)
        for k in range(1, L + 1):
            ck[k - 1] = ck[k - 1] + np.einsum("wnc,wnc->c", d[:, k:], d[:, :-k])
    return c0, ck


def _vif(xw: np.ndarray, max_lag: int, sel: np.ndarray | None = None) -> np.ndarray:
    """Variance inflation of a window mean from the pooled autocorrelation of still windows.

    xw : (W, n, 3) windows, of which ``sel`` (bool (W,), default all) are the still ones. VIF = 1 + 2 Σ_{k=1}^{L} (1 − k/n) r_k, with r_k pooled over
    the windows after removing each window's mean; the O(1/n) bias of demeaned
    autocorrelations (E r_k ≈ −VIF/n) is added back by a fixed-point iteration.
    """
    W, n, _ = xw.shape
    L = min(max_lag, n - 2)
    c0, ck = _lag_sums(xw, np.ones(W, bool) if sel is None else sel, L)
    r = [c / c0 for c in ck]
    vif = np.ones(xw.shape[2])
    for _ in range(3):  # demeaning bias of r_k is −VIF/n: fixed-point correction
        vif = 1.0 + sum(2.0 * (1.0 - k / n) * (r[k - 1] + vif / n) for k in range(1, L + 1))
    return np.maximum(vif, 0.05)


# ---------------------------------------------------------------------------- calibrator
class StaticBiasCalibrator:
    """Static bias with a motion gate, refusing while moving and retrying on the next window.

    Parameters
    ----------
    window_samples : int, default 200
        Samples per window (the article: 200).
    window_s : float, optional
        Window length in seconds (converted with the mean sample rate); overrides
        ``window_samples``.
    false_reject_rate : float, default 1e-3
        Probability that a window of a still sensor is refused (all three axes together).
    rule : {"mean", "median", "converge", "article"}
        ``"mean"``: mean of the first still window (the article); ``"median"``: its median
        (PX4-like, robust to spikes); ``"converge"``: consecutive window means until two agree
        within the tolerance (ArduPilot-like), bias = their average; ``"article"``: mean with
        the article's fixed gate Σ|Δ| > ``article_threshold_counts`` × ``lsb_rad_s``.
    statistic : {"variance", "abs_diff"}
        Gate statistic for "mean"/"median" (see module docstring). ``"variance"`` (default)
        is ~50× more sensitive to slow motion than the article's Σ|Δ| at the same false-reject
        rate (one step changes one difference but the whole window's variance); ``"abs_diff"``
        reacts to high-frequency vibration.
    max_retries : int, optional
        Windows to try after the first; None = until the recording ends.
    noise_sigma_rad_s : float or array (3,), optional
        Per-sample white-noise σ of the sensor (e.g. N·√rate from an Allan analysis or the
        datasheet). Default: estimated robustly from the recording itself.
    lsb_rad_s : float, optional
        Size of one raw count in rad/s (``"article"`` rule; e.g. (1/131)°/s at ±250 °/s).
    article_threshold_counts : float, default 500
    converge_tolerance_rad_s : float, optional
        ``"converge"`` tolerance on |mean_k − mean_k−1| (Euclidean norm). Default: derived —
        accept when Σ_i d_i²/(2 s_i²) < χ²₃ quantile at 1 − α (s_i² = σ_i² VIF_i / n).
    max_lag : int, default 5
        Lags used for the variance inflation factor.
    correlation : {"auto", "white"}
        "auto" estimates the VIF from the still windows; "white" sets VIF = 1.
    """

    def __init__(
        self,
        *,
        window_samples: int = 200,
        window_s: float | None = None,
        false_reject_rate: float = 1e-3,
        rule: str = "mean",
        statistic: str = "variance",
        max_retries: int | None = None,
        noise_sigma_rad_s: float | np.ndarray | None = None,
        lsb_rad_s: float | None = None,
        article_threshold_counts: float = 500.0,
        converge_tolerance_rad_s: float | None = None,
        max_lag: int = 5,
        correlation: str = "auto",
    ) -> None:
        if rule not in RULES:
            raise GyroInputError(f"unknown bias rule {rule!r}; use one of {', '.join(RULES)}")
        if statistic not in STATISTICS:
            raise GyroInputError(f"unknown gate statistic {statistic!r}; use abs_diff or variance")
        if not (0.0 < false_reject_rate < 1.0):
            raise GyroInputError(f"false_reject_rate must be in (0, 1), got {false_reject_rate}")
        if window_s is None and int(window_samples) < 8:
            raise GyroInputError(f"window must have at least 8 samples, got {window_samples}")
        if rule == "article" and not (lsb_rad_s and lsb_rad_s > 0):
            raise GyroInputError("the article rule needs the raw count size lsb_rad_s (e.g. --lsb-dps 0.0076336)")
        if correlation not in ("auto", "white"):
            raise GyroInputError(f"correlation must be 'auto' or 'white', got {correlation!r}")
        self.window_samples = int(window_samples)
        self.window_s = window_s
        self.false_reject_rate = float(false_reject_rate)
        self.rule = rule
        self.statistic = statistic
        self.max_retries = max_retries
        self.noise_sigma_rad_s = noise_sigma_rad_s
        self.lsb_rad_s = lsb_rad_s
        self.article_threshold_counts = float(article_threshold_counts)
        self.converge_tolerance_rad_s = converge_tolerance_rad_s
        self.max_lag = int(max_lag)
        self.correlation = correlation

    # ------------------------------------------------------------------ gate
    def still_gate(self, n: int, statistic: str | None = None) -> StillGate:
        """The options of the one still gate (:mod:`gyrocore.data.still`) for windows of n samples:
        this calibrator's statistic (the article's Σ|Δ| with its fixed threshold for ``"article"``),
        false-reject rate, noise σ and autocorrelation lags."""
        article = self.rule == "article"
        sigma = self.noise_sigma_rad_s
        return StillGate(
            window_samples=int(n),
            false_reject_rate=self.false_reject_rate,
            statistic="abs_diff" if article else (statistic or self.statistic),
            noise_sigma_rad_s=None
            if sigma is None
            else tuple(np.broadcast_to(np.asarray(sigma, float), (3,)).tolist()),
            max_lag=self.max_lag,
            threshold=self.article_threshold_counts * float(self.lsb_rad_s) if article else None,
        )

    def gate(
        self,
        n: int,
        sigma_diff: np.ndarray,
        rho: np.ndarray,
        dt_s: float,
        *,
        sigma2: np.ndarray | None = None,
        dof: np.ndarray | None = None,
    ):
        """Threshold (3,), its units, α used, min step (3,) and min ramp (3,) for windows of n.

        For the variance statistic, ``sigma2`` (per-sample variance) and ``dof`` (effective
        degrees of freedom of a window variance) default to the white-noise values
        σ_Δ²/2 and n − 1.

        Returns
        -------
        threshold, units, alpha, min_step_rad_s, min_ramp_rad_s2
        """
        alpha_axis = 1.0 - (1.0 - self.false_reject_rate) ** (1.0 / 3.0)
        m = n - 1
        step = np.full(3, np.nan)
        ramp = np.full(3, np.nan)
        if self.rule == "converge":
            return None, "", self.false_reject_rate, step, ramp
        thr = gate_threshold(self.still_gate(n), n, sigma_diff, rho, sigma2=sigma2, dof=dof)
        if self.rule == "article" or self.statistic == "abs_diff":
            mean, var = abs_diff_moments(m, sigma_diff, rho)
            alpha = float("nan") if self.rule == "article" else self.false_reject_rate
            for i in range(3):
                sd = float(sigma_diff[i])
                base = sd * math.sqrt(2 / math.pi)
                # a step h changes one difference: E S = mean + E|N(h, σΔ²)| − E|N(0, σΔ²)|
                step[i] = _solve_increasing(lambda h: mean[i] + _folded_mean(h, sd) - base, thr[i], sd)
                # a ramp a shifts every difference by a·dt: E S = m·E|N(a dt, σΔ²)|
                ramp[i] = _solve_increasing(lambda a: m * _folded_mean(a * dt_s, sd), thr[i], sd / dt_s)
            return thr, "rad/s (sum of |diff| over the window)", alpha, step, ramp
        sigma2 = sigma_diff**2 / 2.0 if sigma2 is None else np.asarray(sigma2, float)
        dof = np.full(3, float(m)) if dof is None else np.asarray(dof, float)
        for i in range(3):
            s2, nu = float(sigma2[i]), float(dof[i])
            q = scipy.stats.chi2.isf(alpha_axis, nu)
            # (ν/σ²)·s² ~ χ²(ν) at rest; a deterministic motion adds the noncentrality
            # λ = Σ(x − x̄)²/σ² · ν/m: step at mid-window Σ = n h²/4, ramp (a dt)² n(n²−1)/12
            det = lambda lam: scipy.stats.ncx2.sf(q, nu, lam * nu / m)  # noqa: E731
            step[i] = _solve_increasing(lambda h: det(n * h * h / (4 * s2)), 0.5, math.sqrt(s2))
            ramp[i] = _solve_increasing(
                lambda a: det((a * dt_s) ** 2 * n * (n * n - 1) / 12 / s2), 0.5, math.sqrt(s2) / (n * dt_s)
            )
        return thr, "(rad/s)^2 (window variance)", self.false_reject_rate, step, ramp

    # ------------------------------------------------------------------ fit
    def fit(self, recording) -> StaticBiasResult:
        """Estimate the static bias of ``recording`` (gyro rad/s, sensor frame S).

        ``recording``: a :class:`Recording`, or the columns of one held on disk (a
        :class:`gyrocore.data.spill.ColumnSpill`). Either is read through the chunk source of
        :mod:`gyrocore.data.columns` a block of windows at a time (views of memory; fresh small
        reads from disk) and the robust noise one gyro column at a time: memory O(one column)
        + O(W) window statistics, the same numbers in memory and from disk.

        Raises
        ------
        GyroInputError
            Recording shorter than one window (two for "converge"), or motion detected in
            every window tried (one line, with the threshold and how many windows were tried).
        """
        cols = columns_of(recording)
        # what _result reads (the rate, the start time): t with a zero-stride stand-in gyro
        head = Recording(t_s=cols.t_s, gyro_rad_s=np.broadcast_to(0.0, (cols.n, 3)), meta=cols.meta)

        return self._fit(head, cols.n, head.rate_hz, cols, lambda n: GyroWindows(cols, n))

    def _fit(self, recording, N: int, rate: float, cols, windows) -> StaticBiasResult:
        if not (math.isfinite(rate) and rate > 0):
            raise GyroInputError("static bias needs a sample rate (at least 2 timestamps)")
        dt = 1.0 / rate
        n = int(round(self.window_s * rate)) if self.window_s is not None else self.window_samples
        if n < 8:
            raise GyroInputError(f"window of {n} samples is too short (need >= 8)")
        W = N // n
        need = 2 if self.rule == "converge" else 1
        if W < need:
            raise GyroInputError(f"recording has {N} samples, shorter than {need} window(s) of {n} samples")
        # the one still gate; "converge" takes σ and the VIF from the windows the (default)
        # variance gate calls still, so that motion cannot inflate them
        gate = self.still_gate(n, "variance" if self.rule == "converge" else None)
        sw = still_windows(cols, rate, gate, block_bytes=cols.block_bytes)
        sigma_diff, rho = sw.sigma_diff_rad_s, sw.diff_corr
        xw = windows(n)  # the gyro's (W, n, 3) windows (GyroWindows), for the VIF and the chosen window
        inflated = sw.noise_note  # why the window variances were not used (motion in most windows), else ""
        thr, units, alpha, step, ramp = self.gate(n, sigma_diff, rho, dt, sigma2=sw.sigma2, dof=sw.dof)
        still = sw.still
        n_still = int(still.sum())
        if inflated and n_still:
            warn_repair(
                "motion in most windows: " + inflated + "; the gate uses the noise of the sample-to-sample "
                "differences instead"
            )
        if self.correlation == "white" or n_still == 0:
            vif = np.ones(3)
        else:
            vif = _vif(xw, self.max_lag, still)
        # per-sample σ of the data (pooled within-window variance of the still windows; for
        # coloured noise σ_Δ/√2 is not the marginal σ)
        if self.noise_sigma_rad_s is not None:
            sigma = sigma_diff / math.sqrt(2.0)
        else:
            sigma = np.sqrt((sw.variance[still] if n_still else sw.variance).mean(axis=0))
        last = W if self.max_retries is None else min(W, 1 + int(self.max_retries) + (need - 1))
        common = dict(recording=recording, n=n, W=W, last=last, n_still=n_still, sigma=sigma, rho=rho, vif=vif)
        if self.rule == "converge":
            return self._fit_converge(sw.means, dt=dt, inflated=inflated, alpha=alpha, **common)
        return self._fit_first_still(
            xw, still, sigma_diff, inflated=inflated, alpha=alpha, thr=thr, units=units, step=step, ramp=ramp, **common
        )

    def _fit_converge(self, means, *, recording, n, W, last, n_still, sigma, rho, vif, dt, inflated, alpha):
        """The "converge" rule: the first two consecutive window means that agree (Mahalanobis
        tolerance from the noise, or a given tolerance); their average is the bias."""
        s_mean2 = sigma**2 * vif / n
        if self.converge_tolerance_rad_s is None:
            q3 = scipy.stats.chi2.isf(self.false_reject_rate, 3)
            ok = lambda d: float(np.sum(d * d / (2 * s_mean2))) <= q3  # noqa: E731
            thr = np.sqrt(2 * s_mean2 * q3)
            units = "rad/s (per-axis scale of the derived Mahalanobis tolerance on mean differences)"
        else:
            tol = float(self.converge_tolerance_rad_s)
            ok = lambda d: float(np.linalg.norm(d)) < tol  # noqa: E731
            thr = np.full(3, tol)
            units = "rad/s (tolerance on |mean difference|)"
            alpha = float("nan")
        # 50 % detection, approx: a step h at a window boundary moves the difference by h;
        # a ramp a moves it by a·n·dt.
        step = thr.copy()
        ramp = thr / (n * dt)
        for k in range(1, last):
            if ok(means[k] - means[k - 1]):
                bias = 0.5 * (means[k] + means[k - 1])
                se = sigma * np.sqrt(vif / (2 * n))
                return self._result(
                    bias,
                    se,
                    recording,
                    (k - 1) * n,
                    2 * n,
                    k - 1,
                    W,
                    n_still,
                    alpha,
                    thr,
                    units,
                    sigma,
                    rho,
                    vif,
                    step,
                    ramp,
                )
        raise GyroInputError(
            f"motion detected throughout: no two consecutive {n}-sample window means agreed "
            f"within tolerance over {last} windows"
            + (f"; {inflated}: the recording moves smoothly the whole time" if inflated else "")
        )

    def _fit_first_still(
        self,
        xw,
        still,
        sigma_diff,
        *,
        recording,
        n,
        W,
        last,
        n_still,
        sigma,
        rho,
        vif,
        inflated,
        alpha,
        thr,
        units,
        step,
        ramp,
    ):
        """The first still window's mean (or median) is the bias; one error line when every
        window tried moves."""
        for k in range(last):
            if still[k]:
                w = xw[k]
                if self.rule == "median":
                    bias = np.median(w, axis=0)
                    se = math.sqrt(math.pi / 2) * sigma * np.sqrt(vif / n)
                else:
                    bias = w.mean(axis=0)
                    se = sigma * np.sqrt(vif / n)
                return self._result(
                    bias, se, recording, k * n, n, k, W, n_still, alpha, thr, units, sigma, rho, vif, step, ramp
                )
        if self.rule == "article":
            rest = abs_diff_moments(n - 1, sigma_diff, rho)[0] / float(self.lsb_rad_s)
            raise GyroInputError(
                f"motion detected throughout: all {last} windows of {n} samples rejected (article rule: "
                f"sum|diff| > {self.article_threshold_counts:g} counts; a still sensor with this noise sums "
                f"~{', '.join(f'{v:.0f}' for v in rest)} counts per axis)"
            )
        if inflated:
            raise GyroInputError(
                f"motion detected throughout: all {last} windows of {n} samples rejected; {inflated}: the recording "
                f"moves smoothly the whole time; if it is really still, give the sensor's noise (--noise-dps)"
            )
        raise GyroInputError(
            f"motion detected throughout: all {last} windows of {n} samples rejected "
            f"({self.rule} rule, {self.statistic} gate, threshold {np.array2string(thr, precision=4)} "
            f"{units.split(' (')[0]}, false-reject rate {self.false_reject_rate:g})"
        )

    def _result(self, bias, se, rec, start, length, n_rej, W, n_still, alpha, thr, units, sigma, rho, vif, step, ramp):
        rate = rec.rate_hz
        return StaticBiasResult(
            bias_rad_s=np.asarray(bias, float),
            bias_se_rad_s=np.asarray(se, float),
            rule=self.rule,
            statistic="mean_difference"
            if self.rule == "converge"
            else ("abs_diff" if self.rule == "article" else self.statistic),
            window_start_index=int(start),
            window_samples=int(length),
            window_start_s=float(rec.t_s[start] - rec.t_s[0]),
            window_s=float(length / rate),
            n_rejected_windows=int(n_rej),
            n_windows_total=int(W),
            n_windows_still=int(n_still),
            false_reject_rate=float(alpha),
            threshold=np.asarray(thr, float),
            threshold_units=units,
            noise_sigma_rad_s=np.asarray(sigma, float),
            diff_corr=np.asarray(rho, float),
            vif=np.asarray(vif, float),
            min_step_rad_s=np.asarray(step, float),
            min_ramp_rad_s2=np.asarray(ramp, float),
        )


def startup_still_slice(
    recording: Recording,
    *,
    max_duration_s: float = 10.0,
    window_samples: int = 200,
    false_reject_rate: float = 1e-3,
    statistic: str = "variance",
    noise_sigma_rad_s: float | np.ndarray | None = None,
    noise_quantile: float = 0.1,
) -> slice | None:
    """The still stretch at the start of a recording: consecutive gate-accepted windows.

    Windows of ``window_samples`` from sample 0 are tested with the gate of
    :class:`StaticBiasCalibrator` (same threshold, same false-reject rate); the slice ends
    at the first moving window or after ``max_duration_s``. ``None`` if the first window
    already moves (or the recording is shorter than a window).

    The noise σ is estimated from the whole recording unless given: the ``noise_quantile``
    quantile of the window variances (so at least that fraction of the recording must be
    still, e.g. 10 %); pass the sensor's σ (N·√rate) for flight logs that are mostly moving.
    """
    x = np.asarray(recording.gyro_rad_s, float)
    rate = recording.rate_hz
    n = int(window_samples)
    if x.shape[0] < n or not (math.isfinite(rate) and rate > 0):
        return None
    gate = StaticBiasCalibrator(
        window_samples=n, false_reject_rate=false_reject_rate, statistic=statistic, noise_sigma_rad_s=noise_sigma_rad_s
    ).still_gate(n)
    still = still_windows(x, rate, replace(gate, noise_quantile=noise_quantile)).still
    W_max = max(1, min(still.size, int(math.floor(max_duration_s * rate / n))))
    still = still[:W_max]
    if not still[0]:
        return None
    k = int(np.argmin(still)) if not still.all() else W_max
    return slice(0, k * n)
