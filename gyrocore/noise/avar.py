"""The Allan variance of each noise term and the covariance of its estimates (the GMWM's engine).

Terms, in the order of the linear coefficient vector :data:`LINEAR` (variance scale):
quantization Q (white angle noise), white rate N, flicker B (the Kasdin–Walter α = 1 process of
:mod:`sim.noise`, its exact discrete Allan variance integrated numerically), rate random walk K
(discrete: K²τ/3 + K²τ0²/(6τ)), rate ramp R, and one first-order Gauss–Markov term (σ, τc) with
the exact AR(1) Allan variance (:func:`term_avar`, method ``"gmwm"``); or the IEEE 952 continuous
asymptotes 3Q²/τ² + N²/τ + (2 ln2/π)B² + K²τ/3 + R²τ²/2 (method ``"adev"``, no GM). The
averaging factors are the octaves m = 1, 2, 4, … ≤ (n−1)/2 (:func:`scales`).

Covariance of the Allan-variance estimates
------------------------------------------
Var σ̂²_j = 2σ_j⁴/edf_j with the EDF of the power law that has the local log–log slope of the
fitted model at τ_j (:func:`power_law_edf`: the exact large-sample EDF where the record is long
against the filter, Greenhall's finite-sample EDF at the last octaves where edf ≈ 1–5), times the
mixture's spectral EDF over the pure law's where terms share an octave. The correlation between scales is the
large-sample Gaussian form (Percival & Walden eq. 308 generalised to two scales):
Cov(σ̂²_i, σ̂²_j) ∝ ∫|H_i(ν)|²|H_j(ν)|² S(ν)² dν / max(M_i, M_j), with |H_m(ν)|² =
4 sin⁴(πmν)/(m² sin²(πν)) the Haar (Allan) filter, S the model's two-sided spectrum (white
N²·f_s, flicker B²/|2 sin πν|, random walk K²τ0/(4 sin²πν), white angle 4Q²f_s² sin²πν,
AR(1) σ²(1−φ²)/|1−φe^{−2πiν}|²) and M_j = n − 2m_j terms. Integrated on a log-spaced ν grid
(64 points per e-fold); where a filter oscillates faster than the grid, sin⁴ is replaced by
its average (3/8; products of two such by their exact averages 35/128, 7/64, 9/64).
"""

from __future__ import annotations

import functools
import math
from typing import Mapping

import numpy as np

__all__ = [
    "LINEAR",
    "scales",
    "term_avar",
    "flicker_avar_factor",
    "gm_avar",
    "model_avar",
    "avar_covariance",
    "power_law_edf",
    "base_method",
    "spectrum",
]

#: Coefficient names, in the order of the linear coefficient vector (variance scale):
#: Q² (rad²), N² (rad²/s), B² (rad²/s²), K² (rad²/s³), R² (rad²/s⁴), σ_GM² (rad²/s²).
LINEAR = (
    "quantization_rad",
    "arw_rad_per_sqrt_s",
    "bias_instability_rad_s",
    "rrw_rad_per_s_sqrt_s",
    "rate_ramp_rad_s2",
    "correlated_sigma_rad_s",
)
_B_FACTOR = 2.0 * math.log(2.0) / math.pi
#: prior SD (in units of the Kasdin-minus-asymptote shape) of the flicker's Allan-variance shape
#: at the first octaves (:func:`avar_covariance`): the conventions span θ = −1.1 (averaged
#: continuous 1/f: the simulator's cascade) … 0 (point-sampled Kasdin–Walter: the model), so
#: s = 1.5 keeps either within 1σ of the model and costs N at most the information of one
#: shape direction
_FLICKER_SHAPE_SD = 1.5


def scales(n_samples: int, *, max_m: int | None = None) -> np.ndarray:
    """Octave factors m = 1, 2, 4, … ≤ (n−1)/2 (or ``max_m``): the whole Haar-scale range."""
    top = (n_samples - 1) // 2 if max_m is None else min(int(max_m), (n_samples - 1) // 2)
    if top < 1:
        return np.zeros(0, np.int64)
    return 2 ** np.arange(int(math.floor(math.log2(top))) + 1, dtype=np.int64)


# ---------------------------------------------------------------------------- term variances
@functools.lru_cache(maxsize=256)
def flicker_avar_factor(m: int) -> float:
    """Allan variance of unit Kasdin–Walter flicker (α = 1, innovation σ = 1) at factor m.

    (2/(π m²)) ∫₀^{π/2} sin⁴(mx)/sin³(x) dx (two-sided spectrum 1/|2 sin πν| through the
    Haar filter); → 2 ln2/π for m → ∞ with an O(ln m/m²) correction, used beyond m = 4096.
    """
    m = int(m)
    if m > 4096:
        return _B_FACTOR
    # ∫ sin⁴(mx)(1/sin³x − 1/x³) dx numerically + m²∫₀^{mπ/2} sin⁴u/u³ du in closed-ish form
    n_pts = max(4001, 200 * m + 1)
    x = np.linspace(0.0, math.pi / 2, n_pts)
    x[0] = 1e-300
    s4 = np.sin(m * x) ** 4
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        g = np.where(x > 1e-3, 1.0 / np.sin(x) ** 3 - 1.0 / x**3, 0.5 / x + 17.0 * x / 120.0)
    g[0] = 0.0
    part1 = float(np.trapezoid(s4 * g, x))
    U = m * math.pi / 2
    u = np.linspace(1e-9, U, max(20001, 400 * m + 1))
    part2 = m * m * float(np.trapezoid(np.sin(u) ** 4 / u**3, u))
    return 2.0 / (math.pi * m * m) * (part1 + part2)


def gm_avar(m: np.ndarray, dt_s: float, tau_c_s: float) -> np.ndarray:
    """Allan variance of a unit-variance AR(1) with φ = exp(−dt/τc) at factors m (exact, discrete).

    AVAR = Var(ȳ_m) − Cov(ȳ₁, ȳ₂): Var(ȳ_m) = [m + 2φ(m(1−φ) − (1−φᵐ))/(1−φ)²]/m²,
    Cov = φ(1−φᵐ)²/((1−φ)² m²).
    """
    m = np.asarray(m, float)
    a = dt_s / tau_c_s
    omp = -math.expm1(-a)  # 1 − φ
    phi = 1.0 - omp
    ompm = -np.expm1(-a * m)  # 1 − φ^m
    var = (m + 2.0 * phi * (m * omp - ompm) / omp**2) / m**2
    cov = phi * ompm**2 / (omp**2 * m**2)
    return np.maximum(var - cov, 0.0)


def term_avar(m: np.ndarray, rate_hz: float, *, method: str = "gmwm", tau_c_s: float | None = None) -> np.ndarray:
    """Design matrix: Allan variance of each unit term at factors m; shape (M, 6).

    Columns Q², N², B², K², R², σ_GM² (units so that AVAR = A @ c in rad²/s²). ``method``
    "gmwm": exact discrete forms; "adev": IEEE 952 continuous asymptotes (GM column zero).
    """
    A = _base_design(tuple(int(v) for v in np.asarray(m).ravel()), float(rate_hz), method).copy()
    if base_method(method) != "adev" and tau_c_s is not None:
        A[:, 5] = gm_avar(np.asarray(m, float), 1.0 / rate_hz, tau_c_s)
    return A


@functools.lru_cache(maxsize=256)
def _base_design(m_key: tuple[int, ...], rate_hz: float, method: str) -> np.ndarray:
    m = np.array(m_key, float)
    dt = 1.0 / rate_hz
    t = m * dt
    A = np.zeros((m.size, 6))
    # "+lp": above the sensor's low-pass, white rate noise through any filter with unit
    # DC gain has σ² = N²/τ − κN²/τ² (+ terms that vanish beyond the filter's impulse response): the
    # first column is then that signed deficit, −3/τ² (coefficient ≥ 0), instead of white angle
    # noise 3Q²/τ² — the two have one signature, so Q is not identified beside a low-pass
    A[:, 0] = (-3.0 if method.endswith("+lp") else 3.0) / t**2
    A[:, 1] = 1.0 / t
    A[:, 4] = t**2 / 2.0
    if base_method(method) == "adev":
        A[:, 2] = _B_FACTOR
        A[:, 3] = t / 3.0
    else:
        A[:, 2] = [flicker_avar_factor(int(v)) for v in m]
        A[:, 3] = t / 3.0 + dt * dt / (6.0 * t)
    A.setflags(write=False)
    return A


def base_method(method: str) -> str:
    """The estimator of a method name: "gmwm" or "adev" (a "+lp" suffix marks a low-pass)."""
    return method.split("+", 1)[0]


def model_avar(m: np.ndarray, rate_hz: float, terms: Mapping[str, float | None], *, method: str = "gmwm") -> np.ndarray:
    """Allan variance of a set of terms (SI values, None/absent = 0) at factors m."""
    tc = terms.get("correlated_tau_c_s")
    A = term_avar(m, rate_hz, method=method, tau_c_s=tc if tc else None)
    c = np.array([(terms.get(k) or 0.0) ** 2 for k in LINEAR])
    return A @ c


# ---------------------------------------------------------------------------- covariance
_GRID_PER_EFOLD = 64


@functools.lru_cache(maxsize=64)
def _grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Log-spaced ν grid (cycles/sample) from 1/(64 n) to 1/2 and its trapezoid weights."""
    lo = 1.0 / (64.0 * n)
    k = int(math.ceil(_GRID_PER_EFOLD * math.log(0.5 / lo)))
    nu = np.geomspace(lo, 0.5, k + 1)
    w = np.zeros_like(nu)
    d = np.diff(nu)
    w[:-1] += d / 2
    w[1:] += d / 2
    w[0] += lo  # the sliver (0, lo): integrand taken constant
    return nu, w


@functools.lru_cache(maxsize=64)
def _filters(m_key: tuple[int, ...], n: int):
    """sin⁴(π m ν) on the grid, exact where resolved and its mean 3/8 elsewhere; flags."""
    nu, w = _grid(n)
    dnu = np.gradient(nu)
    m = np.array(m_key, float)[:, None]
    fast = m * dnu[None, :] > 0.25
    s4 = np.where(fast, 0.375, np.sin(np.pi * m * nu[None, :]) ** 4)
    return s4, fast


@functools.lru_cache(maxsize=64)
def _pair_factor(m_key: tuple[int, ...]) -> np.ndarray:
    mm = np.array(m_key, float)
    ratio = mm[:, None] / mm[None, :]
    ratio = np.maximum(ratio, 1.0 / ratio)
    return np.where(
        np.isclose(ratio, 1.0), (35 / 128) / (9 / 64), np.where(np.isclose(ratio, 2.0), (7 / 64) / (9 / 64), 1.0)
    )


def spectrum(nu: np.ndarray, rate_hz: float, c: np.ndarray, tau_c_s: float | None) -> np.ndarray:
    """Two-sided spectrum (rad²/s² per cycle/sample) of the stochastic terms c = (Q², N², B², K², R², σ²)."""
    s = np.sin(np.pi * nu)
    S = c[1] * rate_hz + c[0] * rate_hz**2 * 4.0 * s * s + c[2] / (2.0 * s) + c[3] / rate_hz / (4.0 * s * s)
    if tau_c_s and c[5] > 0:
        phi = math.exp(-1.0 / (rate_hz * tau_c_s))
        S = S + c[5] * (1.0 - phi * phi) / (1.0 + phi * phi - 2.0 * phi * np.cos(2.0 * np.pi * nu))
    return S


def _alpha_of_slope(mu: np.ndarray) -> np.ndarray:
    """Power-law α (S ∝ f^α) with the Allan-variance slope μ (AVAR ∝ τ^μ): α = −μ − 1, μ ≤ −1.5 → α = 2."""
    a = np.rint(np.clip(-mu - 1.0, -2.0, 1.0)).astype(int)
    return np.where(mu <= -1.5, 2, np.where(a == 1, 0, a))


#: the large-sample (1/M) form of the EDF holds where the record is long against the filter: the
#: lag-correlation of the Allan filter output spans < 2m terms, and with M ≥ 64·m terms the
#: finite-M correction is below 0.5 % (Greenhall's finite-sample values over the spectral ones at
#: n = 72 000: 1.001 at M/m ≈ 1100, 1.004 at 140, 1.007 at 70, 1.015 at 35, all four laws)
_LARGE_SAMPLE_M_PER_FACTOR = 64


@functools.lru_cache(maxsize=8192)
def power_law_edf(alpha: int, m: int, n_phase: int) -> float:
    """Equivalent degrees of freedom of the overlapping Allan variance at factor m of a power law
    S_y ∝ f^α (α = −2 random-walk rate K, −1 flicker B, 0 white rate N, 2 white angle Q) on
    ``n_phase`` phase points; at least 1.

    Where the record is long against the filter (M = n_phase − 2m ≥ 64·m terms): the exact
    large-sample EDF, 2σ⁴M/∫|H_m|⁴S² dν (Percival & Walden eq. 308; :func:`_pure_spec_edf`).
    At the longer factors: Greenhall's finite-sample EDF (Greenhall & Riley 2003,
    ``allantools.edf_greenhall``; SP 1065 eq. 47, the white-rate approximation, where it fails).

    Why not Greenhall's everywhere: ``allantools.edf_greenhall`` (2024.06) is wrong at the first
    octaves for α ≤ 0 (its summation branch, 3m ≤ 100). At n = 72 000: white rate noise, m = 1,
    it gives 56 347 where the exact value is 2(n − 1)/3 = 48 000 (the first differences have
    lag-one correlation −½, their squares ¼: Var σ̂² = 3σ⁴/M) — Monte Carlo 47 445 ± 1 061
    (4 000 records); m = 4: 22 148 vs exact 25 041, MC 25 299 ± 566; random-walk rate, m = 1:
    54 926 where the first differences of a random walk's rate are white, so σ̂²(1) is a mean
    of M independent squares and edf = M = 71 999 (MC 68 151 ± 1 760). The 17 % excess at
    m = 1, the octave with the most samples, made N's interval 4 % too narrow.
    """
    n = int(n_phase) - 1
    big_m = int(n_phase) - 2 * int(m)
    if int(alpha) in _ALPHAS and big_m >= _LARGE_SAMPLE_M_PER_FACTOR * int(m):
        row = int(np.searchsorted(_ALPHAS, int(alpha)))
        return max(float(_pure_spec_edf((int(m),), n)[row, 0]) * big_m, 1.0)
    import allantools

    try:
        e = float(
            allantools.edf_greenhall(alpha=int(alpha), d=2, m=int(m), N=int(n_phase), overlapping=True, modified=False)
        )
    except Exception:  # pragma: no cover
        e = float("nan")
    if not math.isfinite(e) or e <= 0:
        e = (3 * (n - 1) / (2 * m) - 2 * (n - 2) / n) * 4 * m * m / (4 * m * m + 5)
    return max(e, 1.0)


_ALPHAS = np.array([-2, -1, 0, 2])


@functools.lru_cache(maxsize=64)
def _pure_spec_edf(m_key: tuple[int, ...], n: int) -> np.ndarray:
    """edf_spec (without the 1/M factor, as in :func:`avar_covariance`) of each pure power law
    α = −2 (K), −1 (B), 0 (N), 2 (Q) at factors m; shape (4, M). Scale-free, so unit levels
    at rate 1 Hz."""
    nu, w = _grid(n)
    s4, fast = _filters(m_key, n)
    sn2 = np.sin(np.pi * nu) ** 2
    mm = np.array(m_key, float)[:, None]
    H2 = 4.0 * s4 / (mm**2 * sn2[None, :])
    pf = np.diag(_pair_factor(m_key))[:, None]
    out = np.empty((4, len(m_key)))
    for k, idx in enumerate((3, 2, 1, 0)):  # K, B, N, Q columns of the coefficient vector
        c = np.zeros(6)
        c[idx] = 1.0
        G = H2 * spectrum(nu, 1.0, c, None)[None, :]
        d = (G * G * w[None, :]).sum(axis=1) + (np.where(fast, G, 0.0) ** 2 * w[None, :]).sum(axis=1) * (pf[:, 0] - 1.0)
        lv = (G * w[None, :]).sum(axis=1)
        out[k] = 2.0 * lv**2 / np.maximum(d, np.finfo(float).tiny)
    out.setflags(write=False)
    return out


def avar_covariance(
    m: np.ndarray,
    n_samples: int,
    rate_hz: float,
    c: np.ndarray,
    tau_c_s: float | None,
    model: np.ndarray,
    *,
    method: str = "gmwm",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Covariance (M, M) of the overlapping AVAR estimates under the model; also edf (M,), α (M,).

    Diagonal 2·model²/edf (:func:`power_law_edf` of the local power law of the model, corrected
    for mixtures); correlation
    from the spectral integral of the module docstring, including the finite-M factor
    √(min(M_i, M_j)/max(M_i, M_j)).
    """
    m = np.asarray(m, np.int64)
    key = tuple(int(v) for v in m)
    nu, w = _grid(int(n_samples))
    s4, fast = _filters(key, int(n_samples))
    sn2 = np.sin(np.pi * nu) ** 2
    mm = m.astype(float)[:, None]
    H2 = 4.0 * s4 / (mm**2 * sn2[None, :])  # |H_m|², averaged where fast
    cc = np.where(np.asarray(c) > 0, c, 0.0)
    if method.endswith("+lp"):  # the low-pass deficit is no spectral term of its own
        cc = cc.copy()
        cc[0] = 0.0
    if not np.any(cc[:4] > 0) and not cc[5] > 0:
        cc = cc.copy()
        cc[1] = 1.0
    S = spectrum(nu, rate_hz, cc, tau_c_s)
    G = H2 * S[None, :]
    C = (G * w[None, :]) @ G.T
    # products of two fast-oscillating sin⁴ terms: replace (3/8)² by their exact mean
    # (35/128 for equal m, 7/64 for m_j = 2 m_i, 9/64 otherwise)
    Gf = np.where(fast, G, 0.0)
    C = C + ((Gf * w[None, :]) @ Gf.T) * (_pair_factor(key) - 1.0)
    lvl = (G * w[None, :]).sum(axis=1)  # the model's AVAR from the same integral
    d = np.sqrt(np.diag(C))
    R = C / np.outer(d, d)
    Mt = (n_samples - 2 * m).astype(float)
    R = R * np.sqrt(np.minimum.outer(Mt, Mt) / np.maximum.outer(Mt, Mt))
    np.fill_diagonal(R, 1.0)
    # EDF from the local slope of the model
    lt = np.log(m.astype(float))
    lm = np.log(np.maximum(model, np.finfo(float).tiny))
    mu = np.gradient(lm, lt) if m.size > 1 else np.array([-1.0])
    alpha = _alpha_of_slope(mu)
    edf = np.array([power_law_edf(int(a), int(v), int(n_samples) + 1) for a, v in zip(alpha, m)])
    # Mixtures: power_law_edf is that of ONE power law; where two terms share an
    # octave (white angle Q and white rate N over m = 1…3Q²f_s/N² at 1 kHz) Var σ̂² is not
    # that law's. The large-sample variance Var σ̂²_j ≈ 2∫|H_j|⁴S² dν / M_j (Percival & Walden
    # eq. 308; the diagonal of C above) gives edf_spec = 2σ⁴_j M_j / ∫|H_j|⁴S² (exact for a
    # pure law where M ≫ m: 2(n−1)/3 for white rate noise at m = 1; not at the last octaves).
    # The EDF used is the pure law's times the mixture's edf_spec over the pure law's edf_spec
    # at the same m: unchanged for a pure law, Greenhall's finite-M form kept at the last
    # octaves, the mixture's variance in the shared octaves (white-PM EDF ≈ n/2 at m = 64
    # became 3.5× too large with Q + N at 1 kHz: N's interval covered 62–79 %).
    e_mix = 2.0 * lvl**2 / np.maximum(np.diag(C), np.finfo(float).tiny)
    e_pure = _pure_spec_edf(key, int(n_samples))
    ratio = e_mix / e_pure[np.searchsorted(_ALPHAS, alpha), np.arange(m.size)]
    edf = np.maximum(edf * np.where(np.isfinite(ratio) & (ratio > 0), ratio, 1.0), 1.0)
    sd = np.sqrt(2.0 / edf) * model
    try:  # positive definite (the usual case): no eigen-decomposition needed
        np.linalg.cholesky(R - 1e-9 * np.eye(R.shape[0]))
    except np.linalg.LinAlgError:
        w_, V = np.linalg.eigh(R)
        R = (V * np.maximum(w_, 1e-9)) @ V.T
        dd = np.sqrt(np.diag(R))
        R = R / np.outer(dd, dd)
    C = R * np.outer(sd, sd)
    if cc[2] > 0 and _FLICKER_SHAPE_SD > 0:
        # the flicker's Allan variance at the first octaves is a convention of how the
        # 1/f process reaches the sample rate, not a property of B: point-sampled 1/f up to
        # Nyquist (Kasdin–Walter, this model's column) is 1.44× the IEEE asymptote at m = 1,
        # 1.15× at 2, 1.05× at 4; continuous 1/f averaged over each sample interval (a sensor's
        # decimation; the simulator's cascade within 0.04 of it) has the asymptote at every m.
        # Where flicker is a notable share of σ² at the first octaves — and these carry the
        # most samples — the difference biased N (−0.4 % = 2 SE, N covered 60–80 % with a 5-octave
        # plateau at 20 Hz) and fed a false Q. Model uncertainty: a shape error
        # θ·B²·v(m), v = the Kasdin factor − 2 ln2/π, θ ~ N(0, s²), added to the covariance
        # (rank one, fully correlated across octaves) and to the EDF as its variance share.
        v = np.array([flicker_avar_factor(int(q)) for q in m]) - _B_FACTOR
        u = _FLICKER_SHAPE_SD * cc[2] * v
        C = C + np.outer(u, u)
        edf = np.maximum(2.0 * model**2 / np.diag(C), 1.0)
    return C, edf, alpha
