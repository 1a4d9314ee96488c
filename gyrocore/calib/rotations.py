"""Rotation calibration: still parts, the article's integral method M = C·B⁻¹, its worked numbers.

Rate-table least squares (K, bias, g-sensitivity against reference rates) is
:class:`gyrocore.calibrator.Calibrator` with those effects; this module covers the case where only
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
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from gyrocore.errors import GyroInputError, warn_repair
from gyrocore.data.recording import Recording
from gyrocore.data.segments import Segment, as_segments
from gyrocore.data.still import StillGate, still_samples

from .covariance import residual_autocov_model

__all__ = [
    "IntegralResult",
    "STILL_GATE",
    "integral_calibration",
    "article_worked_example",
    "ARTICLE_B_RAD",
    "ARTICLE_M_PRINTED",
    "segments_from_any",
    "GravityPoseResult",
    "gravity_pose_calibration",
]

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
def segments_from_any(segments) -> list[Segment]:
    """The known rotations the integral method uses, from a segments file path or a sequence of
    :class:`gyrocore.data.segments.Segment`.

    Raises
    ------
    GyroInputError
        An unreadable file, an item that is not a Segment, or a still segment (the integral
        method takes its bias from the still parts it finds outside the rotations, or from an
        external bias; it does not take still spans).
    """
    segs = as_segments(segments)
    still = [s for s in segs if s.kind != "rotation"]
    if still:
        s = still[0]
        raise GyroInputError(
            f"integral method: segment {s.t_start_s}..{s.t_end_s} s is still; the method takes known rotations "
            "only (its bias comes from the still parts outside them, or --bias-from / --bias-dps)"
        )
    return segs


# ---------------------------------------------------------------------------- still parts
#: The still gate of the rotation calibrations (:func:`gyrocore.data.still.still_windows`): window
#: variance against its χ²_{n−1} quantile, σ² always from the lower quartile of the window variances
#: outside the known rotations (most of what is left is still, and it includes coloured noise up to
#: the window length: an on-chip low-pass makes first-difference estimates too small), ν = n − 1.
#: ``variance_factor`` = f² lets a hand-held "still" pose tremble f × the still noise (the gravity
#: direction is steady although the hand trembles). A constant rotation rate has no variance and is
#: not caught by any gyro-only test: the segments file must cover every rotation.
STILL_GATE = StillGate(window_s=1.0, false_reject_rate=1e-3, noise_from="windows", dof="white")


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
        Bias from the still parts, rad/s, and its standard error (long-run variance); or the
        external bias and standard error that were given (then ``n_still`` may be 0).
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
        from gyrocore.effects.registry import MISALIGNMENT_ORDER

        return np.array([self.K["xyz".index(p[0]), "xyz".index(p[1])] for p in MISALIGNMENT_ORDER])

    @property
    def misalignment_stderr_rad(self) -> np.ndarray:
        from gyrocore.effects.registry import MISALIGNMENT_ORDER

        return np.array([self.K_stderr["xyz".index(p[0]), "xyz".index(p[1])] for p in MISALIGNMENT_ORDER])


def _vec3(what: str, v, *, positive: bool = False) -> np.ndarray:
    a = np.broadcast_to(np.asarray(v, float), (3,)).copy() if np.ndim(v) == 0 else np.asarray(v, float)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or (positive and not np.all(a >= 0)):
        raise GyroInputError(
            f"integral method: {what} must be 3 finite{' non-negative' if positive else ''} numbers, got {v!r}"
        )
    return a


def _long_run_var(e: np.ndarray) -> float:
    """σ²_LR = γ(0) + 2Σγ(l) of one still residual series (model of gyrocore.calib.covariance)."""
    g = residual_autocov_model(e)
    return float(max(g[0] + 2.0 * g[1:].sum(), g[0]))


def _segment_integrals(t, y, b, segs):
    """Per segment k: B[:, k] the integral of y − b over it (rad), C[:, k] its known rotation
    vector (rad), T[k] its duration (s) and nk[k] its sample count."""
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
        C[:, k] = s.angle_S_rad
    return B, C, T, nk


def _k_covariance(K, C, Cp, T, nk, *, dt: float, lr, se_b, angle_sigma_rad: float, axis_sigma_rad: float):
    """Covariance of vec_r(K) (9×9): rows independent across axes, row i = B_i·C⁺ with
    cov(B_i) = diag(n_k dt² σ²_LR,i) + T Tᵀ se_b,i²; plus the known angles' and axes'
    uncertainty to first order (see :func:`integral_calibration`)."""
    cov_K = np.zeros((9, 9))
    for i in range(3):
        Sig = np.diag(nk * dt**2 * lr[i]) + np.outer(T, T) * se_b[i] ** 2
        cov_K[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = Cp.T @ Sig @ Cp
    sa, sx = float(angle_sigma_rad), float(axis_sigma_rad)
    if not (math.isfinite(sa) and sa >= 0 and math.isfinite(sx) and sx >= 0):
        raise GyroInputError(f"angle/axis uncertainty must be >= 0, got {angle_sigma_rad}, {axis_sigma_rad}")
    if sa > 0 or sx > 0:
        for k in range(C.shape[1]):
            theta = float(np.linalg.norm(C[:, k]))
            a = C[:, k] / theta if theta > 0 else np.zeros(3)
            P = np.outer(a, a)
            Sk = sa**2 * P + (theta * sx) ** 2 * (np.eye(3) - P)
            cov_K += np.kron(K @ Sk @ K.T, np.outer(Cp[k], Cp[k]))
    return cov_K


def integral_calibration(
    recording: Recording,
    segments,
    *,
    still: np.ndarray | None = None,
    window_s: float = 1.0,
    false_reject_rate: float = 1e-3,
    margin_s: float = 0.5,
    h_rad_s_per_m_s2: np.ndarray | None = None,
    bias_rad_s: np.ndarray | None = None,
    bias_stderr_rad_s: np.ndarray | None = None,
    noise_lr_rad2_s: np.ndarray | None = None,
    angle_sigma_rad: float = 0.0,
    axis_sigma_rad: float = 0.0,
) -> IntegralResult:
    """The article's integral method, generalised to any number of known-angle segments.

    Parameters
    ----------
    recording : Recording
        Gyro in rad/s, sensor frame S.
    segments : path or sequence
        Known rotations (a segments file or :class:`gyrocore.data.segments.Segment` rows, any
        rotation vector); each segment must contain the whole motion (still at both ends) and
        the rotation vectors must span all three axes.
    still : ndarray of bool, shape (N,), optional
        Samples to take the bias from; default :data:`STILL_GATE` outside the segments.
    h_rad_s_per_m_s2 : ndarray, shape (3, 3), optional
        A known g-sensitivity H (e.g. fitted on the still poses): H·f is removed from the
        gyro before the bias is taken and before integrating (as imucal's Ferraris does).
    bias_rad_s : ndarray, shape (3,), optional
        External bias, rad/s (e.g. :class:`gyrocore.calib.bias.StaticBiasCalibrator` on a static
        recording of the same session), for recordings without a still part (hand turns
        that start and end moving). Then ``still`` is not searched and
        ``bias_stderr_rad_s`` and ``noise_lr_rad2_s`` are required.
    bias_stderr_rad_s : ndarray, shape (3,), optional
        Its standard error, rad/s; enters every integral as δb·T_k (shared by the segments).
    noise_lr_rad2_s : ndarray, shape (3,), optional
        Long-run noise variance of the gyro, (rad/s)²·s (= N² for white noise; σ²·VIF/rate
        from a static fit), for the noise of each integral, n_k·dt²·σ²_LR.
    angle_sigma_rad, axis_sigma_rad : float
        Standard deviation of each known rotation's angle (rad) and of its axis direction (rad,
        per orthogonal component): a turn by hand is good to a few degrees. Propagated into K's
        covariance to first order: the true angle vector c_k = C[:, k] + δc_k with
        cov(δc_k) = σ_θ² a aᵀ + θ_k² σ_φ² (I − a aᵀ) (a = the segment's axis), and K = B·C⁺ gives
        dK = −K·δC·C⁺ (B's part outside C's row space is the fit residual, left out), i.e.
        cov(vec_r dK) += Σ_k (K Σ_k Kᵀ) ⊗ (C⁺[k] C⁺[k]ᵀ). 0 (default): the angles are exact.

    Returns
    -------
    IntegralResult
    """
    segs = segments_from_any(segments)
    if not segs:
        raise GyroInputError("integral method: the segments file lists no rotations")
    t = recording.t_s
    y = recording.gyro_rad_s
    dt = float(np.median(np.diff(t)))
    external = bias_rad_s is not None
    if external:
        if bias_stderr_rad_s is None or noise_lr_rad2_s is None:
            raise GyroInputError("integral method: an external bias needs its standard error and the noise level too")
        b = _vec3("bias", bias_rad_s)
        se_b = _vec3("bias standard error", bias_stderr_rad_s, positive=True)
        lr = _vec3("long-run noise variance", noise_lr_rad2_s, positive=True) / dt  # (rad/s)² per sample
        still = np.zeros(t.size, bool) if still is None else np.asarray(still, bool)
    elif still is None:
        still = still_samples(
            recording,
            replace(STILL_GATE, window_s=window_s, false_reject_rate=false_reject_rate),
            exclude_s=[(s.t_start_s, s.t_end_s) for s in segs],
            margin_s=margin_s,
        )
    still = np.asarray(still, bool)
    n_still = int(still.sum())
    if not external and n_still < 10:
        raise GyroInputError(
            "integral method: no still part found to take the bias from (need still data outside the segments, "
            "or an external bias: --bias-from STATIC.csv / --bias-dps)"
        )
    if h_rad_s_per_m_s2 is not None:
        if recording.accel_m_s2 is None:
            raise GyroInputError("g-sensitivity removal needs the accel_*_m_s2 columns, which the data lack")
        y = y - recording.accel_m_s2 @ np.asarray(h_rad_s_per_m_s2, float).T
    if external:
        e = y[still] - b if n_still else np.full((1, 3), np.nan)
    else:
        b = y[still].mean(axis=0)
        # long-run variance from each contiguous still stretch's residual (stretch means removed
        # would hide drift; use one mean, the bias, as the model does)
        e = y[still] - b
        lr = np.array([_long_run_var(e[:, i]) for i in range(3)])  # (rad/s)² per sample, long-run
        se_b = np.sqrt(lr / n_still)
    B, C, T, nk = _segment_integrals(t, y, b, segs)
    if np.linalg.matrix_rank(C) < 3:
        turned = sorted({s.axis or "an oblique axis" for s in segs})
        raise GyroInputError(
            f"integral method: rotations about {', '.join(turned)} only; K and M need turns about all three axes"
        )
    Cp = np.linalg.pinv(C)  # (nseg, 3)
    K = B @ Cp
    M = np.linalg.inv(K)
    # covariance of K (rows independent across axes): row i = B_i·C⁺,
    # cov(B_i) = diag(n_k dt² σ²_LR,i) + T Tᵀ se_b,i²
    cov_K = _k_covariance(
        K, C, Cp, T, nk, dt=dt, lr=lr, se_b=se_b, angle_sigma_rad=angle_sigma_rad, axis_sigma_rad=axis_sigma_rad
    )
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


# ---------------------------------------------------------------------------- gravity poses
@dataclass(frozen=True, eq=False)
class GravityPoseResult:
    """Multi-pose calibration against gravity directions (Tedaldi et al. 2014, gyro part).

    Attributes
    ----------
    K, K_stderr : ndarray, shape (3, 3)
        Catalogue K (y − b = K·ω) and its standard errors (from the Jacobian, scaled by the
        residual variance — they include the pose-direction noise and hand-motion model error,
        not the first-pose bias error, whose effect σ_b·T per motion is usually far smaller).
    M : ndarray, shape (3, 3)
        K⁻¹ (ω = M·(y − b)).
    bias_rad_s, bias_stderr_rad_s : ndarray, shape (3,)
        Bias from the first still pose (Tedaldi's initialisation interval).
    intervals : ndarray, shape (P, 2)
        Sample index ranges [start, stop) of the still poses used.
    residual_rad : ndarray, shape (U, 3)
        Gravity-direction misfit after each used motion (unit-vector difference ≈ angle, rad).
    n_motions_saturated : int
        Motions dropped because the gyro clipped during them.
    rms_residual_rad : float
    condition : float
        Condition number of the Jacobian (large: some rotation axis not exercised).
    """

    K: np.ndarray
    K_stderr: np.ndarray
    M: np.ndarray
    bias_rad_s: np.ndarray
    bias_stderr_rad_s: np.ndarray
    intervals: np.ndarray
    residual_rad: np.ndarray
    rms_residual_rad: float
    condition: float
    n_motions_saturated: int = 0


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def gravity_pose_calibration(
    recording: Recording,
    *,
    still: np.ndarray | None = None,
    intervals: Sequence[tuple[int, int]] | None = None,
    window_s: float = 0.5,
    min_pose_s: float = 1.0,
    false_reject_rate: float = 1e-3,
    pose_std_factor: float = 5.0,
    bias_from: str = "first",
) -> GravityPoseResult:
    """K from the rotations between still poses, with gravity as the attitude reference.

    Between consecutive still poses k and k+1 the bias-free, corrected gyro
    ω = M·(y − b) is integrated (:func:`gyrocore.attitude.integrate_gyro`) to the rotation
    R_k; the measured gravity direction of pose k, carried through R_k, must match that of
    pose k+1: u_{k+1} = R_kᵀ·u_k. M (9 entries) is fitted by Levenberg–Marquardt
    (scipy.optimize.least_squares) over all transitions; K = M⁻¹. Rotations about the
    vertical leave gravity unchanged and carry no information — the poses must tilt the
    sensor about every axis. The accelerometer is used uncalibrated (direction only).

    Parameters
    ----------
    recording : Recording
        Gyro (rad/s) and accel (m/s²), sensor frame S.
    still : ndarray of bool, shape (N,), optional
        Still samples (default :data:`STILL_GATE` with ``window_s``).
    intervals : sequence of (start, stop), optional
        Still poses as sample ranges (overrides ``still``), e.g. the authors' own list.
    min_pose_s : float
        Shortest still run accepted as a pose.
    pose_std_factor : float
        A pose window may have up to this many times the still-noise standard deviation
        (hand-held poses tremble; only the mean gravity direction is used).
    bias_from : {"first", "all"}
        Bias from the first pose (Tedaldi's initialisation) or from all poses.
    """
    if recording.accel_m_s2 is None:
        raise GyroInputError("multi-pose calibration needs the accel_*_m_s2 columns (gravity is the reference)")
    if bias_from not in ("first", "all"):
        raise GyroInputError(f"bias_from must be 'first' or 'all', not {bias_from!r}")
    y = recording.gyro_rad_s
    f = recording.accel_m_s2
    runs = _pose_runs(recording, still, intervals, window_s, min_pose_s, false_reject_rate, pose_std_factor)
    if bias_from == "first":
        a, b_ = runs[0]
        e0 = y[a:b_]
    else:
        e0 = np.vstack([y[a:b_] for a, b_ in runs])
    bias = e0.mean(axis=0)
    lr = np.array([_long_run_var(e0[:, i] - bias[i]) for i in range(3)])
    se_b = np.sqrt(lr / e0.shape[0])
    u = np.array([f[a:b_].mean(axis=0) for a, b_ in runs])
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    moves, n_sat = _usable_moves(y, runs, pose_std_factor)
    sol = _fit_gravity_moves(recording.t_s, y - bias, u, moves)
    M = sol.x.reshape(3, 3)
    J = sol.jac
    m = J.shape[0]
    dof = max(m - 9, 1)
    s2 = 2.0 * sol.cost / dof
    sv = np.linalg.svd(J, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    cov_M = s2 * np.linalg.pinv(J.T @ J)
    K = np.linalg.inv(M)
    Jk = -np.kron(K, K.T)
    cov_K = Jk @ cov_M @ Jk.T
    r = sol.fun.reshape(-1, 3)
    return GravityPoseResult(
        K=K,
        K_stderr=np.sqrt(np.clip(np.diag(cov_K), 0, None)).reshape(3, 3),
        M=M,
        bias_rad_s=bias,
        bias_stderr_rad_s=se_b,
        intervals=np.array(runs),
        residual_rad=r,
        rms_residual_rad=float(np.sqrt(np.mean(r**2))),
        condition=cond,
        n_motions_saturated=n_sat,
    )


def _pose_runs(recording, still, intervals, window_s, min_pose_s, false_reject_rate, pose_std_factor):
    """The still poses as sorted sample ranges ``[(start, stop)]`` (at least 4): the given
    ``intervals``, else the runs of ``still`` (default the still gate) of at least ``min_pose_s``."""
    if intervals is None:
        if still is None:
            still = still_samples(
                recording,
                replace(
                    STILL_GATE,
                    window_s=window_s,
                    false_reject_rate=false_reject_rate,
                    variance_factor=float(pose_std_factor) ** 2,
                ),
            )
        runs = [(a, b) for a, b in _runs(np.asarray(still, bool)) if (b - a) >= min_pose_s * recording.rate_hz]
    else:
        runs = [(int(a), int(b)) for a, b in intervals]
    if len(runs) < 4:
        raise GyroInputError(f"multi-pose calibration: found {len(runs)} still poses, need at least 4")
    return sorted(runs)


def _usable_moves(y: np.ndarray, runs, pose_std_factor: float):
    """The motions between consecutive poses ``[(k, start, stop)]`` that can be integrated
    (none passes through a clipped gyro sample), and how many were dropped for clipping."""
    moves_all = [(k, runs[k][1] - 1, runs[k + 1][0] + 1) for k in range(len(runs) - 1)]
    # a motion through a clipped (saturated) sample cannot be integrated: drop it
    absy = np.abs(y)
    top = absy.max(axis=0)
    clipped = np.any(
        (absy >= top[None, :] * (1 - 1e-9)) & (np.sum(absy >= top * (1 - 1e-9), axis=0) >= 3)[None, :], axis=1
    )
    moves = [(k, a, b_) for k, a, b_ in moves_all if not clipped[a:b_].any()]
    n_sat = len(moves_all) - len(moves)
    if n_sat:
        warn_repair(
            f"multi-pose calibration: {n_sat} of {len(moves_all)} motions pass through clipped (saturated) gyro samples and are not used"
        )
    if 3 * len(moves) < 12:
        raise GyroInputError(
            f"multi-pose calibration: only {len(moves)} usable motions between poses, need at least 4 "
            f"({len(runs)} still poses found at {pose_std_factor:g}x the rest noise; hand-held poses "
            "tremble: a larger factor, calibrate --pose-std-factor 10, admits them)"
        )
    return moves, n_sat


def _fit_gravity_moves(t: np.ndarray, yb: np.ndarray, u: np.ndarray, moves):
    """Levenberg–Marquardt fit of M (the ``least_squares`` solution, x = M row-major) so that
    each motion's integrated rotation R carries pose k's gravity direction ``u[k]`` to
    ``u[k+1] = Rᵀ·u[k]``; ``yb`` is the bias-free gyro, rad/s."""
    from scipy.optimize import least_squares

    from gyrocore.attitude import integrate_gyro

    def rot_of(M, a, b_):
        q = integrate_gyro(t[a:b_], yb[a:b_] @ M.T)[-1]
        w, x, yy, z = q
        return np.array(
            [
                [1 - 2 * (yy * yy + z * z), 2 * (x * yy - w * z), 2 * (x * z + w * yy)],
                [2 * (x * yy + w * z), 1 - 2 * (x * x + z * z), 2 * (yy * z - w * x)],
                [2 * (x * z - w * yy), 2 * (yy * z + w * x), 1 - 2 * (x * x + yy * yy)],
            ]
        )

    def resid(p):
        M = p.reshape(3, 3)
        out = np.empty((len(moves), 3))
        for j, (k, a, b_) in enumerate(moves):
            R = rot_of(M, a, b_)
            out[j] = u[k + 1] - R.T @ u[k]
        return out.ravel()

    return least_squares(resid, np.eye(3).ravel(), method="lm", x_scale=np.full(9, 0.01))
