"""Attitude from gyro: exact, vectorised quaternion integration, error angle, Mahony filter.

Conventions (DESIGN.md): quaternions are ``w, x, y, z`` and rotate S (sensor/body) to W
(world, z up). The body rate ω_S is the rate of S relative to W expressed in S, so the
kinematics are q̇ = ½·q ⊗ (0, ω_S).

Sample-hold convention
----------------------
Each rate sample is held constant over one sample interval and the step is the *exact*
solution of the kinematics for a constant rate::

    q_{k+1} = q_k ⊗ exp(ω·Δt_k / 2),   Δt_k = t_{k+1} − t_k,
    exp((0, v)) = (cos|v|, v/|v|·sin|v|).

Which sample is held over [t_k, t_{k+1}] is the ``hold`` option:

* ``"backward"`` (default): ω = ω_{k+1}, i.e. sample k+1 is the rate over the interval that
  *ends* at its time stamp. This is what a sampled gyro delivers (its ADC and on-chip filter
  average the past, never the future) and it is the convention of the simulator's truth
  (MuJoCo's semi-implicit step: the attitude at t_{k+1} is reached with the velocity reported
  at t_{k+1}). Integrating the simulated true rate this way reproduces the true attitude to
  rounding (max 3e-14 rad on the rate table), where ``"forward"`` is off by ½·Δω·Δt per rate
  change (0.36° on the 360 °/s turntable ramps). ω_0 is not used.
* ``"forward"``: zero-order hold of ω_k over [t_k, t_{k+1}] (ω_{N−1} is not used).

Either way the attitude at t_0 is the given initial attitude.

Vectorisation
-------------
All per-step increment quaternions are computed at once; their running product
P_k = dq_0 ⊗ … ⊗ dq_{k−1} is a prefix product (a scan over an associative operation), done
blockwise: the samples are cut into blocks of ``_BLOCK`` steps, the products inside every
block are formed column by column (``_BLOCK`` vectorised passes over N/_BLOCK blocks), the
block totals are scanned recursively, and each block is left-multiplied by the product of
all earlier blocks (one vectorised pass). Total work ≈ 2–3 quaternion products per sample,
with Python overhead of O(_BLOCK·log_BLOCK N) calls. The result is renormalised.
``bench/bench_attitude.py`` compares it with a per-sample loop.

The floor
---------
With every deterministic error removed the attitude error is the integral of the
stochastic rate noise. Per axis, for white rate noise N (rad/√s, angle random walk), rate
random walk K (rad/s/√s) and a first-order Gauss–Markov bias (σ, τc), the angle variance is
(e.g. Woodman, "An introduction to inertial navigation", UCAM-CL-TR-696, §4; Gelb, Applied
Optimal Estimation, Table 4.4-1)::

    σθ²(t) = N²·t + K²·t³/3 + 2σ²τc²·(t/τc − 1 + exp(−t/τc))

(a constant turn-on bias of known spread σ_b adds σ_b²·t² but is deterministic per power-up
and is counted as an error, not as floor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gyrocore.errors import GyroInputError

__all__ = [
    "AttitudeScore",
    "qmul",
    "qconj",
    "qnormalize",
    "quat_exp_half",
    "quat_from_rotvec",
    "rotvec_from_quat",
    "rotation_matrices",
    "delta_quats",
    "prefix_product",
    "integrate_gyro",
    "integrate_gyro_loop",
    "integrate_gyro_windows",
    "error_angle_rad",
    "tilt_error_rad",
    "score_attitude",
    "mahony",
    "floor_sigma_theta_rad",
    "attitude_rate",
    "rate_error_vs_attitude",
]

_BLOCK = 8  # steps per block of the blockwise prefix product
_CHUNK = 1 << 16  # samples per cache-sized chunk (temporaries reuse memory; ~20 M products/s)


# ------------------------------------------------------------------ quaternion algebra
def qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p ⊗ q of quaternion arrays, shape (..., 4), w first."""
    p = np.asarray(p, float)
    q = np.asarray(q, float)
    return np.stack(_hamilton(np.moveaxis(p, -1, 0), np.moveaxis(q, -1, 0)), axis=-1)


def _qmul_soa(p, q):
    """Hamilton product on component tuples/arrays of shape (4, ...) (struct of arrays)."""
    return np.stack(_hamilton(p, q))


def _hamilton(p, q) -> list:
    """The four components (w, x, y, z) of p ⊗ q from the components of p and q."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return [
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ]


def qconj(q: np.ndarray) -> np.ndarray:
    """Conjugate (= inverse for unit quaternions), shape (..., 4)."""
    q = np.asarray(q, float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def qnormalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternions, shape (..., 4); zero-norm input is a GyroInputError."""
    q = np.asarray(q, float)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n == 0) or not np.all(np.isfinite(n)):
        raise GyroInputError("quaternion with zero or non-finite norm")
    return q / n


def quat_exp_half(v: np.ndarray) -> np.ndarray:
    """exp((0, v)) = (cos|v|, v/|v|·sin|v|) of rotation **half**-vectors v = θ/2, rad, shape
    (..., 3) -> (..., 4) w,x,y,z: the rotation by the rotation vector 2v (the integrator's exact
    step, v = ω·Δt/2). Of a whole rotation vector θ: :func:`quat_from_rotvec`.

    sin(a)/a is evaluated by its series for small |v| so that |v| → 0 is exact.
    """
    v = np.asarray(v, float)
    flat = v.reshape(-1, 3)
    return _dq_soa(flat, np.full(flat.shape[0], 2.0)).T.reshape(v.shape[:-1] + (4,))


def quat_from_rotvec(rotvec_rad: np.ndarray) -> np.ndarray:
    """Unit quaternion w,x,y,z of the rotation vector θ (rad, the **whole** angle: |θ| about
    θ/|θ|), shape (..., 3) -> (..., 4): exp((0, θ/2)) (cf. :func:`quat_exp_half` of θ/2, the
    same rotation by other arithmetic). The attitude filter's error-state exponential."""
    v = np.asarray(rotvec_rad, float)
    a = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * a
    # sin(a/2)/a with its series near 0
    s = np.where(a > 1e-8, np.sin(half) / np.where(a > 1e-8, a, 1.0), 0.5 - a * a / 48.0)
    return np.concatenate([np.cos(half), s * v], axis=-1)


def rotvec_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation vector θ (rad, the whole angle; shortest: w ≥ 0) of unit quaternions w,x,y,z,
    shape (..., 4) -> (..., 3): the inverse of :func:`quat_from_rotvec`."""
    q = np.asarray(q, float)
    q = np.where(q[..., :1] < 0, -q, q)
    w = np.clip(q[..., :1], -1.0, 1.0)
    v = q[..., 1:]
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    ang = 2.0 * np.arctan2(n, w)
    f = np.where(n > 1e-12, ang / np.where(n > 1e-12, n, 1.0), 2.0 / np.maximum(w, 1e-300))
    return f * v


def rotation_matrices(q_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrices R (..., 3, 3) of quaternions w,x,y,z (..., 4) (normalised first;
    scipy's ``Rotation``): for q_SW, R_WS maps S coordinates into W."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q_wxyz, float), scalar_first=True).as_matrix()


# ------------------------------------------------------------------ integration
def _check_rates(t_s, omega_S_rad_s):
    t = np.asarray(t_s, float)
    w = np.asarray(omega_S_rad_s, float)
    if t.ndim != 1 or w.shape != (t.shape[0], 3):
        raise GyroInputError(f"gyro has shape {w.shape} but time has shape {t.shape}; expected (N, 3) and (N,)")
    if t.shape[0] < 1:
        raise GyroInputError("no samples to integrate")
    if t.shape[0] > 1 and not np.all(np.diff(t) > 0):
        raise GyroInputError("time stamps must increase strictly to integrate the gyro")
    if not np.all(np.isfinite(w)):
        raise GyroInputError("gyro rates contain NaN or inf; cannot integrate")
    return t, w


def _dq_soa(omega_S_rad_s: np.ndarray, dt_s: np.ndarray) -> np.ndarray:
    """exp(ω_k·Δt_k/2) as a (4, M) struct of arrays; ω (M, 3), Δt (M,)."""
    h = 0.5 * dt_s
    vx = omega_S_rad_s[:, 0] * h
    vy = omega_S_rad_s[:, 1] * h
    vz = omega_S_rad_s[:, 2] * h
    a = np.sqrt(vx * vx + vy * vy + vz * vz)
    out = np.empty((4, a.shape[0]))
    np.cos(a, out=out[0])
    small = a < 1e-4
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.sin(a) / a
    # sin(a)/a = 1 − a²/6 + a⁴/120 − …: the 3-term series is exact to < 1e-22 for a < 1e-4
    a2 = a[small] ** 2
    s[small] = 1.0 - a2 / 6.0 + a2 * a2 / 120.0
    np.multiply(vx, s, out=out[1])
    np.multiply(vy, s, out=out[2])
    np.multiply(vz, s, out=out[3])
    return out


def _held(w: np.ndarray, hold: str) -> np.ndarray:
    """The N−1 rate samples held over the N−1 intervals (see the module docstring)."""
    if hold == "backward":
        return w[1:]
    if hold == "forward":
        return w[:-1]
    raise GyroInputError(f"hold must be 'backward' or 'forward', got {hold!r}")


def delta_quats(t_s: np.ndarray, omega_S_rad_s: np.ndarray, *, hold: str = "backward") -> np.ndarray:
    """Per-step increments dq_k = exp(ω·Δt_k/2) over [t_k, t_{k+1}], k = 0..N−2, shape (N−1, 4)."""
    t, w = _check_rates(t_s, omega_S_rad_s)
    return _dq_soa(_held(w, hold), np.diff(t)).T


def prefix_product(dq: np.ndarray) -> np.ndarray:
    """Running products P_k = dq_0 ⊗ dq_1 ⊗ … ⊗ dq_k, shape (M, 4) -> (M, 4).

    Blockwise scan (see module docstring); exact up to floating-point re-association.
    """
    dq = np.asarray(dq, float)
    m = dq.shape[0]
    if m == 0:
        return dq.copy()
    return _prefix_soa(np.ascontiguousarray(dq.T)).T


def _prefix_soa(d: np.ndarray) -> np.ndarray:
    """Prefix product on a (4, M) struct-of-arrays quaternion sequence."""
    m = d.shape[1]
    B = _BLOCK
    if m <= B:
        out = d.copy()
        for j in range(1, m):
            out[:, j] = _qmul_soa(out[:, j - 1], out[:, j])
        return out
    nb = -(-m // B)
    pad = nb * B - m
    if pad:
        ident = np.zeros((4, pad))
        ident[0] = 1.0
        d = np.concatenate([d, ident], axis=1)
    # x[c, j, i] = element j of block i
    x = np.ascontiguousarray(d.reshape(4, nb, B).transpose(0, 2, 1))
    for j in range(1, B):
        x[:, j] = _qmul_soa(x[:, j - 1], x[:, j])
    totals = _prefix_soa(np.ascontiguousarray(x[:, B - 1]))  # (4, nb) prefix over blocks
    off = np.empty_like(totals)
    off[:, 0] = (1.0, 0.0, 0.0, 0.0)
    off[:, 1:] = totals[:, :-1]
    x = _qmul_soa(off[:, None, :], x)  # broadcast over j
    return x.transpose(0, 2, 1).reshape(4, nb * B)[:, :m]


def integrate_gyro(
    t_s: np.ndarray,
    omega_S_rad_s: np.ndarray,
    *,
    q0_wxyz: np.ndarray | None = None,
    hold: str = "backward",
) -> np.ndarray:
    """Attitude from body rates, exact constant-rate steps, vectorised.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Sample times, s, strictly increasing.
    omega_S_rad_s : ndarray, shape (N, 3)
        Rate of S relative to W, in S, rad/s.
    q0_wxyz : ndarray, shape (4,), optional
        Initial attitude S→W (default identity).
    hold : {"backward", "forward"}
        Which sample is held over [t_k, t_{k+1}]: ω_{k+1} (default) or ω_k (module docstring).

    Returns
    -------
    q_SW_wxyz : ndarray, shape (N, 4)
        Unit quaternions, q_0 = q0, q_{k+1} = q_k ⊗ exp(ω·Δt_k/2).
    """
    t, w = _check_rates(t_s, omega_S_rad_s)
    q0 = np.array([1.0, 0.0, 0.0, 0.0]) if q0_wxyz is None else qnormalize(np.asarray(q0_wxyz, float).reshape(4))
    n = t.shape[0]
    out = np.empty((4, n))
    out[:, 0] = q0
    carry = q0.copy()
    dt = np.diff(t)
    wh = _held(w, hold)
    # Cache-sized chunks: within each, increments and their prefix product; the running
    # attitude at the end of a chunk is carried into the next.
    for s0 in range(0, n - 1, _CHUNK):
        s1 = min(s0 + _CHUNK, n - 1)
        P = _prefix_soa(_dq_soa(wh[s0:s1], dt[s0:s1]))
        out[:, s0 + 1 : s1 + 1] = _qmul_soa(carry[:, None], P)
        carry = out[:, s1] / math.sqrt(float(np.dot(out[:, s1], out[:, s1])))
    out /= np.sqrt(np.einsum("ij,ij->j", out, out))[None, :]
    return out.T


def integrate_gyro_windows(
    t_s: np.ndarray,
    rate_rows,
    windows,
    *,
    q0_wxyz: np.ndarray | None = None,
):
    """:func:`integrate_gyro` (backward hold) of a rate read a window of rows at a time, the
    attitude carried across the windows.

    Each window after the first starts from the previous window's last attitude and last rate
    sample, so the backward-hold step across the cut is taken once (with the previous window's
    last rate prepended, the step into the window's first sample is that of the whole record).

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Sample times, s, strictly increasing (in memory).
    rate_rows : callable
        ``rate_rows(lo, hi)`` -> rows lo:hi of the rate of S relative to W, in S, rad/s,
        shape (hi − lo, 3).
    windows : iterable of (int, int)
        Consecutive row ranges [lo, hi) covering the record in order.
    q0_wxyz : ndarray, shape (4,), optional
        Initial attitude S→W (default identity).

    Yields
    ------
    lo, hi : int
        The window.
    q_SW_wxyz : ndarray, shape (hi − lo, 4)
        The attitude on rows lo:hi, w,x,y,z.
    """
    q_carry = w_last = None
    for lo, hi in windows:
        w = rate_rows(lo, hi)
        if q_carry is None:
            q = integrate_gyro(t_s[lo:hi], w, q0_wxyz=q0_wxyz, hold="backward")
        else:
            q = integrate_gyro(t_s[lo - 1 : hi], np.vstack([w_last, w]), q0_wxyz=q_carry, hold="backward")[1:]
        yield lo, hi, q
        q_carry, w_last = q[-1], w[-1:]


def _exp_step(qw: float, qx: float, qy: float, qz: float, hx: float, hy: float, hz: float):
    """q ⊗ exp(h) renormalised, on plain floats (h = ω·dt/2, rad): the per-sample step of the
    reference loop and of the Mahony filter (scalar code: faster than numpy on one quaternion)."""
    a = math.sqrt(hx * hx + hy * hy + hz * hz)
    s = math.sin(a) / a if a > 1e-300 else 1.0
    dw, dx, dy, dz = math.cos(a), hx * s, hy * s, hz * s
    qw, qx, qy, qz = (
        qw * dw - qx * dx - qy * dy - qz * dz,
        qw * dx + qx * dw + qy * dz - qz * dy,
        qw * dy - qx * dz + qy * dw + qz * dx,
        qw * dz + qx * dy - qy * dx + qz * dw,
    )
    nrm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    return qw / nrm, qx / nrm, qy / nrm, qz / nrm


def integrate_gyro_loop(
    t_s: np.ndarray,
    omega_S_rad_s: np.ndarray,
    *,
    q0_wxyz: np.ndarray | None = None,
    hold: str = "backward",
) -> np.ndarray:
    """Reference per-sample loop of :func:`integrate_gyro` (same convention; slow, for tests/bench).

    Each step multiplies by the exact exponential and renormalises.
    """
    t, w = _check_rates(t_s, omega_S_rad_s)
    q = [1.0, 0.0, 0.0, 0.0] if q0_wxyz is None else list(qnormalize(np.asarray(q0_wxyz, float).reshape(4)))
    n = t.shape[0]
    out = np.empty((n, 4))
    out[0] = q
    qw, qx, qy, qz = q
    tl = t.tolist()
    wl = _held(w, hold).tolist()
    for k in range(n - 1):
        dt = tl[k + 1] - tl[k]
        vx, vy, vz = (c * 0.5 * dt for c in wl[k])
        qw, qx, qy, qz = _exp_step(qw, qx, qy, qz, vx, vy, vz)
        out[k + 1] = (qw, qx, qy, qz)
    return out


# ------------------------------------------------------------------ errors and score
def error_angle_rad(q_est_wxyz: np.ndarray, q_true_wxyz: np.ndarray) -> np.ndarray:
    """Rotation angle between estimated and true attitude, rad, shape (N,).

    q_err = q_true⁻¹ ⊗ q_est, angle = 2·atan2(|vec(q_err)|, |w(q_err)|) ∈ [0, π]
    (the |w| makes q and −q equal). Rows with NaN truth give NaN.
    """
    qe = qmul(qconj(np.asarray(q_true_wxyz, float)), np.asarray(q_est_wxyz, float))
    return 2.0 * np.arctan2(np.linalg.norm(qe[..., 1:], axis=-1), np.abs(qe[..., 0]))


def _up_in_S(q_wxyz: np.ndarray) -> np.ndarray:
    """W's z axis (up) expressed in S: third row of R_WS, shape (N, 3)."""
    w, x, y, z = np.moveaxis(np.asarray(q_wxyz, float), -1, 0)
    return np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1)


def tilt_error_rad(q_est_wxyz: np.ndarray, q_true_wxyz: np.ndarray) -> np.ndarray:
    """Tilt (roll/pitch) error: angle between estimated and true 'up' in S, rad, shape (N,).

    Heading error does not count (an accelerometer cannot see it).
    """
    a = _up_in_S(q_est_wxyz)
    b = _up_in_S(q_true_wxyz)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


@dataclass(frozen=True)
class AttitudeScore:
    """Attitude error summary against the truth (DESIGN.md "The score").

    Attributes
    ----------
    final_error_deg : float
        Error angle at the last sample, degrees.
    rms_error_deg : float
        Root mean square of the error angle over all samples, degrees.
    max_error_deg : float
        Largest error angle, degrees.
    drift_deg_per_min : float
        final_error_deg / duration in minutes (mean drift rate over the run).
    duration_s : float
        Scored time span, s.
    n_samples : int
        Number of scored samples (finite truth).
    """

    final_error_deg: float
    rms_error_deg: float
    max_error_deg: float
    drift_deg_per_min: float
    duration_s: float
    n_samples: int


def score_attitude(t_s: np.ndarray, error_rad: np.ndarray) -> AttitudeScore:
    """Summarise an error-angle series (rad, shape (N,)) as an :class:`AttitudeScore`.

    Samples with NaN error (truth missing) are skipped.
    """
    t = np.asarray(t_s, float)
    e = np.asarray(error_rad, float)
    ok = np.isfinite(e)
    if ok.sum() < 2:
        raise GyroInputError("fewer than 2 samples with a reference attitude; cannot score")
    t, e = t[ok], np.degrees(e[ok])
    dur = float(t[-1] - t[0])
    return AttitudeScore(
        final_error_deg=float(e[-1]),
        rms_error_deg=float(np.sqrt(np.mean(e * e))),
        max_error_deg=float(np.max(e)),
        drift_deg_per_min=float(e[-1] / (dur / 60.0)) if dur > 0 else float("nan"),
        duration_s=dur,
        n_samples=int(e.size),
    )


# ------------------------------------------------------------------ Mahony
def mahony(
    t_s: np.ndarray,
    omega_S_rad_s: np.ndarray,
    accel_S_m_s2: np.ndarray,
    *,
    q0_wxyz: np.ndarray | None = None,
    kp_per_s: float = 1.0,
    ki_per_s2: float = 0.0,
    accel_gate_m_s2: float | None = 2.0,
    g_m_s2: float = 9.80665,
    hold: str = "backward",
) -> tuple[np.ndarray, np.ndarray]:
    """Mahony explicit complementary filter (Mahony, Hamel & Pflimlin, IEEE TAC 53(5), 2008).

    The accelerometer's specific force f_S (≈ +g·up at rest) is compared with the predicted up
    direction v̂ = R_SW·e_z; the error e = f̂ × v̂ drives a proportional correction and an
    integral bias estimate::

        b̂ ← b̂ − ki·e·Δt ;  ω_c = ω − b̂ + kp·e ;  q ← q ⊗ exp(ω_c·Δt/2)

    (exact exponential step, same sample-hold convention as :func:`integrate_gyro`; the
    accelerometer sample paired with the held gyro sample is used for the correction).
    Samples with | |f| − g | > ``accel_gate_m_s2`` (manoeuvres) get no correction.
    Inherently sequential: a plain-float Python loop (~1 µs-scale per sample).

    Parameters
    ----------
    t_s : ndarray, shape (N,)
    omega_S_rad_s : ndarray, shape (N, 3)
        Gyro in S, rad/s.
    accel_S_m_s2 : ndarray, shape (N, 3)
        Specific force in S, m/s².
    kp_per_s, ki_per_s2 : float
        Proportional gain (1/s; tilt time constant ≈ 1/kp) and integral gain (1/s²).

    Returns
    -------
    q_SW_wxyz : ndarray, shape (N, 4)
    bias_hat_rad_s : ndarray, shape (N, 3)
        The integral term's gyro bias estimate (in S) at each sample.
    """
    t, w = _check_rates(t_s, omega_S_rad_s)
    f = np.asarray(accel_S_m_s2, float)
    if f.shape != w.shape:
        raise GyroInputError(f"accel has shape {f.shape}, expected {w.shape}")
    q = (1.0, 0.0, 0.0, 0.0) if q0_wxyz is None else tuple(qnormalize(np.asarray(q0_wxyz, float).reshape(4)))
    n = t.shape[0]
    out = np.empty((n, 4))
    bout = np.zeros((n, 3))
    out[0] = q
    qw, qx, qy, qz = q
    bx = by = bz = 0.0
    fn = np.linalg.norm(f, axis=1)
    use = np.isfinite(fn) & (fn > 0)
    if accel_gate_m_s2 is not None:
        use &= np.abs(fn - g_m_s2) <= accel_gate_m_s2
    fu = np.where(use[:, None], f / np.where(fn > 0, fn, 1.0)[:, None], 0.0)
    tl, wl, fl, ul = t.tolist(), _held(w, hold).tolist(), _held(fu, hold).tolist(), _held(use, hold).tolist()
    for k in range(n - 1):
        dt = tl[k + 1] - tl[k]
        ox, oy, oz = wl[k]
        if ul[k]:
            ax, ay, az = fl[k]
            # predicted up in S
            vx = 2 * (qx * qz - qw * qy)
            vy = 2 * (qy * qz + qw * qx)
            vz = 1 - 2 * (qx * qx + qy * qy)
            ex, ey, ez = ay * vz - az * vy, az * vx - ax * vz, ax * vy - ay * vx
            if ki_per_s2:
                bx -= ki_per_s2 * ex * dt
                by -= ki_per_s2 * ey * dt
                bz -= ki_per_s2 * ez * dt
            ox, oy, oz = ox - bx + kp_per_s * ex, oy - by + kp_per_s * ey, oz - bz + kp_per_s * ez
        else:
            ox, oy, oz = ox - bx, oy - by, oz - bz
        hx, hy, hz = 0.5 * dt * ox, 0.5 * dt * oy, 0.5 * dt * oz
        qw, qx, qy, qz = _exp_step(qw, qx, qy, qz, hx, hy, hz)
        out[k + 1] = (qw, qx, qy, qz)
        bout[k + 1] = (bx, by, bz)
    return out, bout


# ------------------------------------------------------------------ floor theory
def floor_sigma_theta_rad(
    t_s: np.ndarray,
    *,
    arw_rad_per_sqrt_s: np.ndarray | float = 0.0,
    rrw_rad_s_per_sqrt_s: np.ndarray | float = 0.0,
    gm_sigma_rad_s: np.ndarray | float = 0.0,
    gm_tau_c_s: np.ndarray | float = np.inf,
) -> np.ndarray:
    """Per-axis standard deviation of the integrated angle from stochastic noise, rad.

    σθ²(t) = N²·t + K²·t³/3 + 2σ²τc²·(t/τc − 1 + e^(−t/τc))  (see module docstring).

    Parameters
    ----------
    t_s : ndarray, shape (M,)
        Time since the start of integration, s (≥ 0).
    arw_rad_per_sqrt_s, rrw_rad_s_per_sqrt_s, gm_sigma_rad_s, gm_tau_c_s : float or ndarray (3,)
        Noise terms per axis (scalars broadcast to 3 axes).

    Returns
    -------
    ndarray, shape (M, 3)
        σθ per axis. The expected squared 3-D error angle is the row sum of squares.
    """
    t = np.asarray(t_s, float)[:, None]
    N = np.broadcast_to(np.asarray(arw_rad_per_sqrt_s, float), (3,))[None, :]
    K = np.broadcast_to(np.asarray(rrw_rad_s_per_sqrt_s, float), (3,))[None, :]
    sg = np.broadcast_to(np.asarray(gm_sigma_rad_s, float), (3,))[None, :]
    tc = np.broadcast_to(np.asarray(gm_tau_c_s, float), (3,))[None, :]
    var = N**2 * t + K**2 * t**3 / 3.0
    with np.errstate(invalid="ignore", over="ignore"):
        x = t / tc
        gm = np.where(np.isfinite(tc) & (sg > 0), 2 * sg**2 * tc**2 * (x - 1 + np.exp(-x)), 0.0)
        # small-x series avoids cancellation: x − 1 + e^(−x) ≈ x²/2 − x³/6
        small = x < 1e-4
        gm = np.where(small & (sg > 0), 2 * sg**2 * tc**2 * (x**2 / 2 - x**3 / 6), gm)
    return np.sqrt(var + gm)


def _rotations(q_wxyz: np.ndarray):
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q_wxyz, float), scalar_first=True)


def attitude_rate(t_s: np.ndarray, q_wxyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rate of an attitude series, backward hold: ω_k = rotvec(R_{k−1}ᵀ R_k)/Δt_k (S frame).

    Integrating these rates with :func:`integrate_gyro` (backward hold) reproduces the
    attitude at every sample.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Sample times, s, strictly increasing.
    q_wxyz : ndarray, shape (N, 4)
        Attitude S→W, w, x, y, z; rows with a NaN (tracking lost) are invalid.

    Returns
    -------
    omega_S_rad_s : ndarray, shape (N, 3)
        Mean rate over (t_{k−1}, t_k], rad/s, sensor frame; NaN where either end is invalid
        and at k = 0.
    valid : ndarray, shape (N,), bool
    """
    q = np.asarray(q_wxyz, float)
    n = q.shape[0]
    ok = np.all(np.isfinite(q), axis=1)
    R = _rotations(np.where(ok[:, None], q, np.array([1.0, 0.0, 0.0, 0.0])))
    dt = np.diff(np.asarray(t_s, float))
    w = np.full((n, 3), np.nan)
    if n > 1:
        w[1:] = (R[:-1].inv() * R[1:]).as_rotvec() / dt[:, None]
    valid = np.zeros(n, bool)
    valid[1:] = ok[1:] & ok[:-1]
    w[~valid] = np.nan
    return w, valid


def rate_error_vs_attitude(
    t_s: np.ndarray, q_wxyz: np.ndarray, omega_S_rad_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample-level rate error of a gyro against a reference attitude.

    e_k = rotvec(ΔR_kᵀ·exp(ω_k·Δt_k))/Δt_k with ΔR_k = R_{k−1}ᵀR_k the reference's increment
    over (t_{k−1}, t_k] and ω_k the gyro sample held over it (backward hold, as
    :func:`integrate_gyro`): the rate error over one interval, exact in the rotation (no
    small-angle difference of rotation vectors), ≈ ω_k − ω_ref,k for small errors.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
    q_wxyz : ndarray, shape (N, 4)
        Reference attitude S→W (NaN rows: tracking lost).
    omega_S_rad_s : ndarray, shape (N, 3)
        Gyro (corrected), rad/s, sensor frame.

    Returns
    -------
    error_rad_s : ndarray, shape (N, 3)
        NaN where the reference increment is not defined.
    omega_ref_rad_s : ndarray, shape (N, 3)
        The reference rate (:func:`attitude_rate`).
    valid : ndarray, shape (N,), bool
    """
    w_ref, valid = attitude_rate(t_s, q_wxyz)
    g = np.asarray(omega_S_rad_s, float)
    valid = valid & np.all(np.isfinite(g), axis=1)
    e = np.full(g.shape, np.nan)
    if valid.any():
        from scipy.spatial.transform import Rotation

        dt = np.diff(np.asarray(t_s, float))
        k = np.flatnonzero(valid)
        dR = Rotation.from_rotvec(w_ref[k] * dt[k - 1][:, None])
        G = Rotation.from_rotvec(g[k] * dt[k - 1][:, None])
        e[k] = (dR.inv() * G).as_rotvec() / dt[k - 1][:, None]
    w_ref = np.where(valid[:, None], w_ref, np.nan)
    return e, w_ref, valid
