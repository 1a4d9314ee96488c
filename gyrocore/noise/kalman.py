"""Kalman filters that track the gyro bias online on the identified noise model.

Two filters, both on ``filterpy.kalman.KalmanFilter`` (the linear algebra), fed with a noise
model identified by :mod:`gyrocore.noise.allan` (or given by hand):

(a) :class:`StillBiasTracker` — sensor at rest: measurement ``gyro = bias + white noise``
    (per-sample variance r = N²·rate, DESIGN.md density convention), bias as a random walk
    (q = K²·dt) or a turn-on constant plus a first-order Gauss–Markov process
    (φ = e^(−dt/τc), q = σ²(1 − φ²)).
    Its steady-state error variance is the discrete Riccati solution
    (:func:`steady_state_variance`, scipy.linalg.solve_discrete_are).
(b) :class:`AttitudeBiasTracker` — moving sensor with a reference attitude (e.g. motion
    capture, a star tracker, a rate table's encoder): a multiplicative error-state filter
    (MEKF; Lefferts, Markley & Shuster 1982; Markley & Crassidis 2014 §7.2) with state
    δx = (δθ, δb): true attitude q = q̂ ⊗ Exp(δθ) (body/sensor frame), true bias b = b̂ + δb,

        δθ̇ = −[ω̂×] δθ − δb − n_N,   δḃ = n_K,   ω̂ = ω_meas − b̂,

    measurement z = Log(q̂⁻¹ ⊗ q_ref) = δθ + v (σ_ref per axis), reset after each update.

:func:`kf_predict` / :func:`kf_update` are the same steps as pure, batched numpy functions
(leading batch dimensions), used for fast Monte Carlo and checked against filterpy in tests.
Quaternions are ``w, x, y, z``, rotating S to W (DESIGN.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from gyrocore.attitude import qmul, quat_from_rotvec, rotvec_from_quat
from gyrocore.errors import GyroInputError, warn_repair

from .model import NoiseModel

__all__ = [
    "tracking_model",
    "kf_predict",
    "kf_update",
    "steady_state_variance",
    "StillBiasTracker",
    "AttitudeBiasTracker",
    "BiasTrack",
]

# First-order Gauss–Markov: ADEV peak ≈ 0.6178 σ at τ ≈ 1.89 τc; flicker floor = 0.6643 B.
_GM_PEAK = 0.6178
_GM_TAU = 1.89
_B_FLOOR = math.sqrt(2 * math.log(2) / math.pi)


# ---------------------------------------------------------------------------- pure steps
def kf_predict(x: np.ndarray, P: np.ndarray, F: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kalman prediction x⁻ = F x, P⁻ = F P Fᵀ + Q, batched over leading dimensions.

    x : (..., n); P : (..., n, n); F, Q : (n, n) or (..., n, n).
    """
    x = np.einsum("...ij,...j->...i", F, x)
    P = F @ P @ np.swapaxes(F, -1, -2) + Q
    return x, P


def kf_update(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Kalman update with the Joseph form, batched over leading dimensions.

    Returns x⁺, P⁺, innovation y = z − Hx, innovation covariance S = HPHᵀ + R.
    """
    y = z - np.einsum("...ij,...j->...i", H, x)
    Ht = np.swapaxes(H, -1, -2)
    S = H @ P @ Ht + R
    K = np.swapaxes(np.linalg.solve(S, H @ np.swapaxes(P, -1, -2)), -1, -2)  # P Hᵀ S⁻¹
    x = x + np.einsum("...ij,...j->...i", K, y)
    n = P.shape[-1]
    IKH = np.eye(n) - K @ H
    P = IKH @ P @ np.swapaxes(IKH, -1, -2) + K @ R @ np.swapaxes(K, -1, -2)
    return x, P, y, S


def steady_state_variance(phi: float, q: float, r: float) -> tuple[float, float]:
    """Scalar steady state of x_{k+1} = φ x_k + w (Var q), z = x + v (Var r).

    Returns (P⁻, P⁺): the prior from the discrete algebraic Riccati equation
    P⁻ = φ² P⁻ r/(P⁻ + r) + q (scipy.linalg.solve_discrete_are) and the posterior
    P⁺ = P⁻ r/(P⁻ + r).
    """
    if q <= 0:
        return 0.0, 0.0
    Pm = float(
        scipy.linalg.solve_discrete_are(np.array([[phi]]), np.array([[1.0]]), np.array([[q]]), np.array([[r]]))[0, 0]
    )
    return Pm, Pm * r / (Pm + r)


# ---------------------------------------------------------------------------- noise model
def tracking_model(analysis) -> NoiseModel:
    """The noise model a bias tracker runs on, from an identification of axes x, y, z.

    ``analysis``: a :class:`gyrocore.noise.allan.AllanAnalysis` (or a dict axis → AllanResult).
    N is required (resolved on every axis). The bias process: random walk with K where K is
    resolved on every axis; else the identified first-order Gauss–Markov term where it is
    resolved on every axis; else a Gauss–Markov process matched to the bias-instability floor
    (σ = 0.6643 B / 0.6178, τc = τ(ADEV minimum)/1.89) where B is resolved or fitted but
    ambiguous with a Gauss–Markov term (the model's value of B); else a random walk with K at
    the upper end of its 95 % interval (what the data cannot exclude).
    """
    axes = getattr(analysis, "axes", analysis)
    if set(axes) != {"x", "y", "z"}:
        raise GyroInputError("bias tracking needs the Allan terms of all three axes x, y, z")
    res = [axes[a] for a in ("x", "y", "z")]
    rep = [r.all_terms() for r in res]
    N = []
    for r, t in zip(res, rep):
        if t["arw_rad_per_sqrt_s"] is None:
            raise GyroInputError(f"angle random walk N of axis {r.axis} not resolved; cannot set the measurement noise")
        N.append(t["arw_rad_per_sqrt_s"])
    K = [t["rrw_rad_per_s_sqrt_s"] for t in rep]
    if all(k is not None for k in K):
        return NoiseModel(np.array(N), rrw_rad_per_s_sqrt_s=np.array(K), source="allan: N, K")
    gs = [t["correlated_sigma_rad_s"] for t in rep]
    gt = [t["correlated_tau_c_s"] for t in rep]
    if all(v is not None for v in gs) and all(v is not None for v in gt):
        return NoiseModel(
            np.array(N),
            correlated_sigma_rad_s=np.array(gs, float),
            correlated_tau_c_s=np.array(gt, float),
            source="noise: N, Gauss-Markov (identified)",
        )
    # a flicker floor fitted but not told from a Gauss–Markov term (``ambiguous``) has its fitted
    # value in the model: either way a Gauss–Markov process matched to the floor is the model to track
    B = np.array([float(r.model.bias_instability_rad_s[0]) for r in res])
    if np.all(B > 0):
        sig = B * _B_FLOOR / _GM_PEAK
        tau = np.array([r.taus_s[int(np.argmin(r.adev_rad_s))] / _GM_TAU for r in res])
        return NoiseModel(
            np.array(N), correlated_sigma_rad_s=sig, correlated_tau_c_s=tau, source="allan: N, B -> Gauss-Markov"
        )
    Kub = np.array([k if k is not None else r.interval("rrw_rad_per_s_sqrt_s")[1] for k, r in zip(K, res)])
    warn_repair(
        "rate random walk K not resolved on every axis: bias tracked as a random walk with K at its 95 % upper bound"
    )
    return NoiseModel(np.array(N), rrw_rad_per_s_sqrt_s=Kub, source="allan: N, K (upper bound where unresolved)")


def _check_tracking(model: NoiseModel) -> None:
    if model.axes != ("x", "y", "z"):
        raise GyroInputError("bias tracking needs the noise model of the three axes x, y, z")
    if np.any(model.arw_rad_per_sqrt_s <= 0):
        raise GyroInputError("arw_rad_per_sqrt_s must be > 0 (the measurement noise)")


def _gauss_markov(model: NoiseModel) -> bool:
    """Does the model's bias carry a Gauss–Markov term (tracked as its own state)?"""
    return bool(np.any(model.correlated_sigma_rad_s > 0))


@dataclass(frozen=True, eq=False)
class BiasTrack:
    """Output of a tracker run.

    bias_rad_s : (N, 3) posterior bias estimate after each sample, rad/s.
    bias_sigma_rad_s : (N, 3) its standard deviation from the filter's P.
    quat_wxyz : (N, 4) or None — attitude estimate (S→W) of the attitude filter.
    """

    bias_rad_s: np.ndarray
    bias_sigma_rad_s: np.ndarray
    quat_wxyz: np.ndarray | None = None


# ---------------------------------------------------------------------------- (a) still
class StillBiasTracker:
    """Online bias of a still gyro, filterpy KalmanFilter, z = gyro = b + v (r = N²·rate).

    Random-walk model: x = b (3,), b_k+1 = b_k + w (q = K²·dt).
    Gauss–Markov model: the bias is a turn-on constant plus a zero-mean Gauss–Markov part,
    x = (c, g) (6,), c_k+1 = c_k, g_k+1 = φ g_k + w, b = c + g. (A Gauss–Markov state alone
    would pull the estimate of a several-°/s turn-on bias towards zero.)

    Parameters
    ----------
    model : NoiseModel
        Of axes x, y, z (:func:`tracking_model`); N > 0.
    rate_hz : float
        Sample rate.
    bias0_rad_s : array (3,)
        Initial bias estimate (e.g. 0 or the last calibration).
    bias0_sigma_rad_s : float or array (3,)
        Its standard deviation (turn-on repeatability).
    """

    def __init__(self, model: NoiseModel, *, rate_hz: float, bias0_rad_s=0.0, bias0_sigma_rad_s=0.1) -> None:
        from filterpy.kalman import KalmanFilter

        _check_tracking(model)
        if not (rate_hz > 0):
            raise GyroInputError(f"rate_hz must be > 0, got {rate_hz}")
        self.model = model
        self.rate_hz = float(rate_hz)
        dt = 1.0 / self.rate_hz
        phi, q = model.bias_process(dt)
        self.phi, self.q = phi, q
        self.r = model.arw_rad_per_sqrt_s**2 * self.rate_hz
        b0 = np.broadcast_to(np.asarray(bias0_rad_s, float), (3,)).copy()
        s0 = np.broadcast_to(np.asarray(bias0_sigma_rad_s, float), (3,)) ** 2
        if _gauss_markov(model):
            kf = KalmanFilter(dim_x=6, dim_z=3)
            kf.x = np.concatenate([b0, np.zeros(3)])
            kf.P = np.diag(np.concatenate([s0, model.correlated_sigma_rad_s**2]))
            kf.F = np.diag(np.concatenate([np.ones(3), phi]))
            kf.Q = np.diag(np.concatenate([np.zeros(3), q]))
            kf.H = np.hstack([np.eye(3), np.eye(3)])
            self._S = np.hstack([np.eye(3), np.eye(3)])  # b = c + g
        else:
            kf = KalmanFilter(dim_x=3, dim_z=3)
            kf.x = b0
            kf.P = np.diag(s0)
            kf.F = np.diag(phi)
            kf.Q = np.diag(q)
            kf.H = np.eye(3)
            self._S = np.eye(3)
        kf.R = np.diag(self.r)
        self.kf = kf

    @property
    def bias_rad_s(self) -> np.ndarray:
        return self._S @ np.asarray(self.kf.x, float).reshape(-1)

    @property
    def bias_sigma_rad_s(self) -> np.ndarray:
        return np.sqrt(np.diag(self._S @ self.kf.P @ self._S.T))

    def step(self, gyro_rad_s: np.ndarray) -> np.ndarray:
        """One sample (3,) in rad/s; returns the posterior bias (3,)."""
        self.kf.predict()
        self.kf.update(np.asarray(gyro_rad_s, float))
        return self.bias_rad_s

    def run(self, gyro_rad_s: np.ndarray) -> BiasTrack:
        """Filter a whole still recording (N, 3)."""
        g = np.asarray(gyro_rad_s, float)
        b = np.empty_like(g)
        s = np.empty_like(g)
        for k in range(g.shape[0]):
            b[k] = self.step(g[k])
            s[k] = self.bias_sigma_rad_s
        return BiasTrack(bias_rad_s=b, bias_sigma_rad_s=s)

    def steady_state_sigma(self) -> np.ndarray:
        """Posterior steady-state standard deviation per axis (Riccati), rad/s.

        For the Gauss–Markov model this is the limit once the turn-on constant is learned
        (its variance decays like 1/time): the scalar Riccati solution of the g part.
        """
        return np.array(
            [
                math.sqrt(steady_state_variance(float(p), float(q), float(r))[1])
                for p, q, r in zip(self.phi, self.q, self.r)
            ]
        )


def _skew(w: np.ndarray) -> np.ndarray:
    x, y, z = w
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _rodrigues(phi: np.ndarray) -> np.ndarray:
    """exp([φ×]) = I + (sin θ/θ)[φ×] + ((1 − cos θ)/θ²)[φ×]², θ = |φ| (rotation matrix)."""
    th = float(np.linalg.norm(phi))
    S = _skew(phi)
    if th < 1e-6:
        a, c = 1.0 - th * th / 6.0, 0.5 - th * th / 24.0
    else:
        a, c = math.sin(th) / th, (1.0 - math.cos(th)) / (th * th)
    return np.eye(3) + a * S + c * (S @ S)


# ---------------------------------------------------------------------------- (b) attitude
class AttitudeBiasTracker:
    """Gyro bias with a reference attitude: MEKF on δx = (δθ, δb), filterpy KalmanFilter.

    Parameters
    ----------
    model : NoiseModel
        Of axes x, y, z (:func:`tracking_model`); N (rad/√s) drives the attitude error, K (or Gauss–Markov) the bias.
    ref_sigma_rad : float
        Standard deviation of the reference attitude per axis (rad, small angle).
    q0_wxyz : array (4,)
        Initial attitude S→W (e.g. the first reference sample).
    bias0_rad_s, bias0_sigma_rad_s, att0_sigma_rad :
        Initial bias, its σ, initial attitude σ.
    """

    def __init__(
        self,
        model: NoiseModel,
        *,
        ref_sigma_rad: float,
        q0_wxyz=(1.0, 0.0, 0.0, 0.0),
        bias0_rad_s=0.0,
        bias0_sigma_rad_s=0.1,
        att0_sigma_rad=0.01,
    ) -> None:
        from filterpy.kalman import KalmanFilter

        _check_tracking(model)
        if not (ref_sigma_rad > 0):
            raise GyroInputError(f"ref_sigma_rad must be > 0, got {ref_sigma_rad}")
        self.model = model
        q0 = np.asarray(q0_wxyz, float)
        self.q = q0 / np.linalg.norm(q0)
        self.b = np.broadcast_to(np.asarray(bias0_rad_s, float), (3,)).copy()
        kf = KalmanFilter(dim_x=6, dim_z=3)
        kf.x = np.zeros(6)
        kf.P = np.diag(
            np.concatenate(
                [
                    np.broadcast_to(att0_sigma_rad, (3,)) ** 2,
                    np.broadcast_to(np.asarray(bias0_sigma_rad_s, float), (3,)) ** 2,
                ]
            )
        )
        kf.H = np.hstack([np.eye(3), np.zeros((3, 3))])
        kf.R = np.eye(3) * ref_sigma_rad**2
        self.kf = kf

    def _FQ(self, omega_hat: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        N2 = self.model.arw_rad_per_sqrt_s**2
        F = np.eye(6)
        # exact attitude-error transition for constant ω̂ over dt: R(ω̂ dt)ᵀ ≈ I − [ω̂×]dt + …
        F[:3, :3] = _rodrigues(-omega_hat * dt)
        F[:3, 3:] = -np.eye(3) * dt
        Q = np.zeros((6, 6))
        # Gauss–Markov bias: tracked as a random walk with the same short-term diffusion
        # K² = 2σ²/τc (keeps the turn-on constant; conservative beyond τc).
        m = self.model
        K2 = 2.0 * m.correlated_sigma_rad_s**2 / m.correlated_tau_c_s if _gauss_markov(m) else m.rrw_rad_per_s_sqrt_s**2
        # Farrenkopf's discrete noise of the (angle, random-walk bias) pair
        Q[:3, :3] = np.diag(N2 * dt + K2 * dt**3 / 3.0)
        Q[:3, 3:] = Q[3:, :3] = np.diag(-K2 * dt**2 / 2.0)
        Q[3:, 3:] = np.diag(K2 * dt)
        return F, Q

    def predict(self, gyro_rad_s: np.ndarray, dt_s: float) -> None:
        """Propagate with one gyro sample (3,) over dt_s."""
        omega_hat = np.asarray(gyro_rad_s, float) - self.b
        F, Q = self._FQ(omega_hat, dt_s)
        self.kf.predict(F=F, Q=Q)
        self.q = qmul(self.q, quat_from_rotvec(omega_hat * dt_s))
        self.q /= np.linalg.norm(self.q)

    def update(self, q_ref_wxyz: np.ndarray) -> None:
        """Fuse one reference attitude (4,), then move the error into q̂, b̂ and reset it."""
        z = rotvec_from_quat(qmul(self.q * np.array([1.0, -1.0, -1.0, -1.0]), np.asarray(q_ref_wxyz, float)))
        self.kf.update(z)
        dx = np.array(self.kf.x, float).reshape(6)
        self.q = qmul(self.q, quat_from_rotvec(dx[:3]))
        self.q /= np.linalg.norm(self.q)
        self.b = self.b + dx[3:]
        self.kf.x = np.zeros(6)

    def run(
        self, t_s: np.ndarray, gyro_rad_s: np.ndarray, q_ref_wxyz: np.ndarray | None, *, update_every: int = 1
    ) -> BiasTrack:
        """Filter a recording: gyro (N, 3) rad/s, reference (N, 4) w,x,y,z S→W (NaN rows skipped).

        Sample k propagates over [t_k, t_k+1) with gyro k (zero-order hold) and is then
        corrected with the reference at t_k+1 when k+1 is a multiple of ``update_every``.
        """
        t = np.asarray(t_s, float)
        g = np.asarray(gyro_rad_s, float)
        n = g.shape[0]
        b = np.full((n, 3), np.nan)
        s = np.full((n, 3), np.nan)
        qs = np.full((n, 4), np.nan)
        b[0], s[0], qs[0] = self.b, np.sqrt(np.diag(self.kf.P)[3:]), self.q
        for k in range(n - 1):
            self.predict(g[k], float(t[k + 1] - t[k]))
            if q_ref_wxyz is not None and (k + 1) % update_every == 0 and np.all(np.isfinite(q_ref_wxyz[k + 1])):
                self.update(q_ref_wxyz[k + 1])
            b[k + 1] = self.b
            s[k + 1] = np.sqrt(np.diag(self.kf.P)[3:])
            qs[k + 1] = self.q
        return BiasTrack(bias_rad_s=b, bias_sigma_rad_s=s, quat_wxyz=qs)

    @property
    def bias_sigma_rad_s(self) -> np.ndarray:
        return np.sqrt(np.diag(self.kf.P)[3:])
