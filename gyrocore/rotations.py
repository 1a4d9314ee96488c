"""Rotation calibration: still parts, the article's integral method M = C·B⁻¹, its worked numbers.

Rate-table least squares (K, bias, g-sensitivity against reference rates) is
:class:`gyrocore.model.Calibrator` with those effects; this module covers the case where only
total rotation angles are known (hand or table turns with a known count), the seed article's
§5:

    on a level table rotate about each axis; B = integrated bias-free outputs (column j =
    rotation about axis j), C = the known angles; C = M·B, so M = C·B⁻¹.

In the catalogue model y = K·ω + b + noise, integrating a segment k gives
B[:, k] = ∫(y − b) dt = K·c_k + noise, with c_k the known rotation vector, so K = B·C⁻¹ and
the article's M (which maps integrated outputs to true angles) is K⁻¹ = C·B⁻¹. With more than
three segments (e.g. + and − turns about each axis) K̂ = B·C⁺ (least squares, C exact,
B noisy).

Standard errors: each integral carries the noise ∫e dt, variance n_k·dt²·σ²_LR (σ²_LR the
long-run variance of the still residual: white noise N² per second, i.e. ARW·√T, plus any
correlated part), and the bias error δb·T_k shared by all segments; both are propagated to K
and M to first order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import stats

from .errors import GyroInputError, warn_repair
from .recording import Recording

__all__ = [
    "IntegralResult",
    "still_mask",
    "integral_calibration",
    "article_worked_example",
    "ARTICLE_B_RAD",
    "ARTICLE_M_PRINTED",
    "segments_from_any",
]

AXES = ("x", "y", "z")

#: The article's integrated outputs B (rad), §5 (column j = rotation about axis j).
ARTICLE_B_RAD = np.array(
    [
        [64.3986, -0.034, 0.141],
        [-0.201, 64.7262, 0.023],
        [0.2379, 0.8250, 64.1897],
    ]
)
#: The article's printed result M.
ARTICLE_M_PRINTED = np.array(
    [
        [0.9754, -0.0135, 0.0214],
        [-0.0117, 0.9841, 0.0023],
        [0.0231, 0.107, 0.9851],
    ]
)


# ---------------------------------------------------------------------------- segments
def segments_from_any(segments) -> list:
    """Segments as ``gyrocore.convert.Segment`` (t_start_s, t_end_s, axis, angle_deg).

    Accepts a path to a segments CSV (``t_start_s,t_end_s,axis,angle_deg``) or a sequence of
    objects/tuples with those four fields.
    """
    from .convert import Segment, read_segments_csv

    if isinstance(segments, (str, bytes)) or hasattr(segments, "__fspath__"):
        return read_segments_csv(segments)
    out = []
    for s in segments:
        if isinstance(s, Segment):
            out.append(s)
        elif hasattr(s, "t_start_s"):
            out.append(Segment(float(s.t_start_s), float(s.t_end_s), str(s.axis), float(s.angle_deg)))
        else:
            t0, t1, ax, ang = s
            out.append(Segment(float(t0), float(t1), str(ax), float(ang)))
    for s in out:
        if s.axis not in AXES:
            raise GyroInputError(f"segment axis must be x, y or z, got {s.axis!r}")
        if not s.t_end_s > s.t_start_s:
            raise GyroInputError(f"segment {s.t_start_s}..{s.t_end_s} s is empty")
    return out


# ---------------------------------------------------------------------------- still parts
def still_mask(
    recording: Recording,
    *,
    window_s: float = 1.0,
    false_reject_rate: float = 1e-3,
    exclude: Sequence[tuple[float, float]] = (),
    margin_s: float = 0.5,
) -> np.ndarray:
    """Samples that belong to still windows, shape (N,) bool.

    The recording is cut into windows of ``window_s``; a window is still when, on every axis,
    its sample variance s² passes the χ² test (n−1)·s²/σ² ≤ χ²_{n−1}(1 − α_axis), with
    α_axis = 1 − (1 − α)^(1/3) and α = ``false_reject_rate``. The still-noise variance σ² is
    estimated from the data as the lower quartile of the window variances divided by the
    lower quartile of χ²_{n−1}/(n−1) — consistent as long as a quarter of the windows are
    still, and it includes coloured noise up to the window length (an on-chip low-pass makes
    first-difference estimates too small). Spans in ``exclude`` (e.g. the rotation segments)
    widened by ``margin_s`` are never still. A constant rotation rate has no variance and is
    not caught by any gyro-only test; the segments file must cover every rotation.
    """
    x = np.asarray(recording.gyro_rad_s, float)
    t = recording.t_s
    N = x.shape[0]
    rate = recording.rate_hz
    if not (math.isfinite(rate) and rate > 0):
        raise GyroInputError("cannot find still parts: unknown sample rate")
    n = max(8, int(round(window_s * rate)))
    mask = np.zeros(N, bool)
    if N < 2 * n:
        raise GyroInputError(f"recording too short ({N} samples) for still windows of {n} samples")
    nw = N // n
    xw = x[: nw * n].reshape(nw, n, 3)
    var = xw.var(axis=1, ddof=1)  # (nw, 3)
    excl = np.zeros(N, bool)
    for a, b in exclude:
        excl |= (t >= a - margin_s) & (t <= b + margin_s)
    win_excl = excl[: nw * n].reshape(nw, n).any(axis=1)
    cand = var[~win_excl] if np.any(~win_excl) else var
    q25 = stats.chi2.ppf(0.25, n - 1) / (n - 1)
    sigma2 = np.quantile(cand, 0.25, axis=0) / q25
    sigma2 = np.where(sigma2 > 0, sigma2, np.max(sigma2) if np.max(sigma2) > 0 else 1e-30)
    a_axis = 1.0 - (1.0 - false_reject_rate) ** (1.0 / 3.0)
    thr = sigma2 * stats.chi2.ppf(1.0 - a_axis, n - 1) / (n - 1)
    still_w = np.all(var <= thr[None, :], axis=1) & ~win_excl
    mask[: nw * n] = np.repeat(still_w, n)
    return mask


# ---------------------------------------------------------------------------- integral method
@dataclass(frozen=True, eq=False)
class IntegralResult:
    """Result of the integral (known-angle) calibration.

    Attributes
    ----------
    M : ndarray, shape (3, 3)
        The article's matrix: true angles = M · integrated bias-free outputs (M = K⁻¹).
    M_stderr : ndarray, shape (3, 3)
    K : ndarray, shape (3, 3)
        Catalogue K (y = K·ω + b): K = I + diag(s) + misalignment.
    K_stderr : ndarray, shape (3, 3)
    bias_rad_s, bias_stderr_rad_s : ndarray, shape (3,)
        Bias from the still parts, rad/s, and its standard error (long-run variance).
    B_rad : ndarray, shape (3, K)
        Integrated bias-free outputs per segment, rad.
    C_rad : ndarray, shape (3, K)
        Known rotation vectors per segment, rad.
    angle_residual_rad : ndarray, shape (3, K)
        C − M·B (zero when K = 3).
    noise_lr_rad2_s : ndarray, shape (3,)
        Long-run noise variance of the still residual, (rad/s)²·s (= N² for white noise).
    n_still : int
        Still samples used for the bias.
    segment_duration_s : ndarray, shape (K,)
    still_rms_rad_s : ndarray, shape (3,)
        RMS of the still samples about the bias, rad/s.
    """

    M: np.ndarray
    M_stderr: np.ndarray
    K: np.ndarray
    K_stderr: np.ndarray
    bias_rad_s: np.ndarray
    bias_stderr_rad_s: np.ndarray
    B_rad: np.ndarray
    C_rad: np.ndarray
    angle_residual_rad: np.ndarray
    noise_lr_rad2_s: np.ndarray
    n_still: int
    segment_duration_s: np.ndarray
    still_rms_rad_s: np.ndarray

    @property
    def scale(self) -> np.ndarray:
        """s_i = K_ii − 1 (catalogue ``scale``)."""
        return np.diag(self.K) - 1.0

    @property
    def scale_stderr(self) -> np.ndarray:
        return np.diag(self.K_stderr).copy()

    @property
    def misalignment_rad(self) -> np.ndarray:
        """K off-diagonals in ``effects.MISALIGNMENT_ORDER`` (catalogue ``misalignment``)."""
        from .effects import MISALIGNMENT_ORDER

        return np.array([self.K["xyz".index(p[0]), "xyz".index(p[1])] for p in MISALIGNMENT_ORDER])

    @property
    def misalignment_stderr_rad(self) -> np.ndarray:
        from .effects import MISALIGNMENT_ORDER

        return np.array([self.K_stderr["xyz".index(p[0]), "xyz".index(p[1])] for p in MISALIGNMENT_ORDER])


def _long_run_var(e: np.ndarray) -> float:
    """σ²_LR = γ(0) + 2Σγ(l) of one still residual series (model of gyrocore.lsq)."""
    from .lsq import residual_autocov_model

    g = residual_autocov_model(e)
    return float(max(g[0] + 2.0 * g[1:].sum(), g[0]))


def integral_calibration(
    recording: Recording,
    segments,
    *,
    still: np.ndarray | None = None,
    window_s: float = 1.0,
    false_reject_rate: float = 1e-3,
    margin_s: float = 0.5,
    h_rad_s_per_m_s2: np.ndarray | None = None,
) -> IntegralResult:
    """The article's integral method, generalised to any number of known-angle segments.

    Parameters
    ----------
    recording : Recording
        Gyro in rad/s, sensor frame S.
    segments : path or sequence
        Known rotations (``t_start_s, t_end_s, axis, angle_deg``); each segment must contain
        the whole motion (still at both ends) and the three axes must all be turned.
    still : ndarray of bool, shape (N,), optional
        Samples to take the bias from; default :func:`still_mask` outside the segments.
    h_rad_s_per_m_s2 : ndarray, shape (3, 3), optional
        A known g-sensitivity H (e.g. fitted on the still poses): H·f is removed from the
        gyro before the bias is taken and before integrating (as imucal's Ferraris does).

    Returns
    -------
    IntegralResult
    """
    segs = segments_from_any(segments)
    if not segs:
        raise GyroInputError("integral method: the segments file lists no rotations")
    t = recording.t_s
    y = recording.gyro_rad_s
    if still is None:
        still = still_mask(recording, window_s=window_s, false_reject_rate=false_reject_rate,
                           exclude=[(s.t_start_s, s.t_end_s) for s in segs], margin_s=margin_s)
    still = np.asarray(still, bool)
    n_still = int(still.sum())
    if n_still < 10:
        raise GyroInputError("integral method: no still part found to take the bias from (need still data outside the segments)")
    dt = float(np.median(np.diff(t)))
    if h_rad_s_per_m_s2 is not None:
        if recording.accel_m_s2 is None:
            raise GyroInputError("g-sensitivity removal needs the accel_*_m_s2 columns, which the data lack")
        y = y - recording.accel_m_s2 @ np.asarray(h_rad_s_per_m_s2, float).T
    b = y[still].mean(axis=0)
    # long-run variance from each contiguous still stretch's residual (stretch means removed
    # would hide drift; use one mean, the bias, as the model does)
    e = y[still] - b
    lr = np.array([_long_run_var(e[:, i]) for i in range(3)])  # (rad/s)² per sample, long-run
    se_b = np.sqrt(lr / n_still)
    nseg = len(segs)
    B = np.zeros((3, nseg))
    C = np.zeros((3, nseg))
    T = np.zeros(nseg)
    nk = np.zeros(nseg)
    for k, s in enumerate(segs):
        m = (t >= s.t_start_s) & (t <= s.t_end_s)
        if m.sum() < 2:
            raise GyroInputError(f"segment {s.t_start_s}..{s.t_end_s} s holds fewer than 2 samples of the recording")
        tk = t[m]
        B[:, k] = np.trapezoid(y[m] - b, tk, axis=0)
        T[k] = tk[-1] - tk[0]
        nk[k] = m.sum()
        C["xyz".index(s.axis), k] = math.radians(s.angle_deg)
    if np.linalg.matrix_rank(C) < 3:
        turned = sorted({s.axis for s in segs})
        raise GyroInputError(
            f"integral method: rotations about {', '.join(turned)} only; K and M need turns about all three axes"
        )
    Cp = np.linalg.pinv(C)  # (nseg, 3)
    K = B @ Cp
    M = np.linalg.inv(K)
    # covariance of K (rows independent across axes): row i = B_i·C⁺,
    # cov(B_i) = diag(n_k dt² σ²_LR,i) + T Tᵀ se_b,i²
    cov_K = np.zeros((9, 9))
    for i in range(3):
        Sig = np.diag(nk * dt**2 * lr[i]) + np.outer(T, T) * se_b[i] ** 2
        cov_K[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = Cp.T @ Sig @ Cp
    J = -np.kron(M, M.T)  # vec_r(dM) = −(M ⊗ Mᵀ) vec_r(dK)
    cov_M = J @ cov_K @ J.T
    return IntegralResult(
        M=M,
        M_stderr=np.sqrt(np.diag(cov_M)).reshape(3, 3),
        K=K,
        K_stderr=np.sqrt(np.diag(cov_K)).reshape(3, 3),
        bias_rad_s=b,
        bias_stderr_rad_s=se_b,
        B_rad=B,
        C_rad=C,
        angle_residual_rad=C - M @ B,
        noise_lr_rad2_s=lr * dt,
        n_still=n_still,
        segment_duration_s=T,
        still_rms_rad_s=np.sqrt(np.mean(e**2, axis=0)),
    )


# ---------------------------------------------------------------------------- the article's numbers
def article_worked_example() -> dict[str, object]:
    """Recompute the article's §5 numbers from its printed B (see /work/shared/ARTICLE.md).

    Returns
    -------
    dict with
        ``B_rad`` — the article's B;
        ``turns_on_diagonal`` — diag(B)/2π (≈ 10.25, 10.30, 10.22: about 10 turns, not 5);
        ``M_C_10pi`` — 10π·B⁻¹, the article's stated C = 10π·I (5 turns): ≈ 0.488·I;
        ``M_C_20pi`` — 20π·B⁻¹ (10 turns): diagonal 0.9756, 0.9707, 0.9788;
        ``M_printed`` — the article's printed M;
        ``M_printed_minus_C_20pi`` — the disagreement (|…| up to 0.119, at M[2,1]);
        ``five_turns_deg`` — 1800 (not the article's 3600);
        ``scale_3600_over_3500`` — 1.0286 (the article says ≈ 1.02).
    """
    B = ARTICLE_B_RAD
    Binv = np.linalg.inv(B)
    M10 = 10 * np.pi * Binv
    M20 = 20 * np.pi * Binv
    return {
        "B_rad": B.copy(),
        "turns_on_diagonal": np.diag(B) / (2 * np.pi),
        "M_C_10pi": M10,
        "M_C_20pi": M20,
        "M_printed": ARTICLE_M_PRINTED.copy(),
        "M_printed_minus_C_20pi": ARTICLE_M_PRINTED - M20,
        "five_turns_deg": 5 * 360.0,
        "scale_3600_over_3500": 3600.0 / 3500.0,
    }
