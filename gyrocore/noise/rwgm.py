"""Random walk or a Gauss–Markov bias that turns over inside the record?

A rate random walk K and a first-order Gauss–Markov (GM) bias of correlation time τc have the
same Allan-variance slope (+½) for τ ≪ τc; the GM's variance turns over at τ ≈ 1.89 τc and then
falls as 1/τ. When τc lies inside the record the two worlds differ only over the last few
octaves of the Allan variance, where each octave carries 1–5 degrees of freedom: a GM of
τc = 20 s in 10-min records was reported as K on 8–12 % of the held-out axes of the noise study
(docs/noise.md), gnss-ins-sim's "bias drift" (GM, τc = 100 s) at 1 h on 3 of 12. An Allan
check against such a GM (tried first) cannot tell them apart either: it flagged 14 % of the
true-K axes at 1 h while catching 6 of 7 false ones, and its separating power saturates with the
record length, because the turnover always sits in the last octaves.

The Haar (Allan) octaves are not an efficient statistic of the low-frequency shape. The exact
Gaussian likelihood of the record is: this module computes it on **block means** (the record cut
into :data:`N_BLOCKS` equal blocks — at τc ≥ 2 blocks nothing of the low-frequency shape is
lost, and the white noise is the block mean's own variance), differenced so that a random walk
is stationary, with the closed-form autocovariance of each term's block means:

- white rate noise N (rad/√s): block mean variance N²/Δ; differences γ₀ = 2N²/Δ, γ₁ = −N²/Δ;
- white angle noise Q (rad): block mean (u_end − u_start)/Δ; differences are second
  differences of white noise: γ₀ = 6Q²/Δ², γ₁ = −4Q²/Δ², γ₂ = Q²/Δ²;
- rate random walk K (rad/s/√s): differences of block means of a Brownian motion,
  γ₀ = 2K²Δ/3, γ₁ = K²Δ/6 (its Allan variance K²τ/3 = γ₀/2 at τ = Δ);
- Gauss–Markov σ (rad/s), τc (s), covariance σ²e^{−|t|/τc}: block means R₀ = 2σ²τc²/Δ²·(x − 1 +
  e^{−x}), R_k = σ²τc²/Δ²·2(cosh x − 1)·e^{−kx} (x = Δ/τc, k ≥ 1); differences
  γ_k = 2R_k − R_{k−1} − R_{k+1}.

The likelihood of the differences d (length n) under a model is −2 log L = log det Σ + dᵀΣ⁻¹d
(Σ the Toeplitz matrix of γ; Cholesky). The check (:func:`random_walk_check`) fits the random-walk
world (N and Q held at the GMWM values, which the short octaves fix to < 1 %, K free) and the GM
world (σ free, τc free in [2Δ, the cap]) and asks the stand-in question of
:func:`gyrocore.noise.gmwm._ambiguous` (Cox 1961; Vuong 1989): were the GM world as fitted true, the
statistic D = −2 log L_K − (−2 log L_GM) would have mean E = 2·KL(GM‖K*) and variance
V = 2 tr((Σ_K*⁻¹Σ_GM − I)²) (K* = the random walk closest to the GM world); its law is a
generalised χ² (:func:`gchi2_draws`), and K is claimed only when D lies below its 5 % quantile (the
GM world rejected at 5 %, the level of every stand-in check).

**Not applied by default** (``gyrocore.noise.options.NoiseOptions.rw_check`` is False): held out it removed 1 of 9
false K claims for a GM of τc = 20 s in 10-min records and cost 8 of 144 true K at 1–4 h. E is
≈ 7.5–7.9 at every record length — a GM with τc ≈ T/20–T/30 and a random walk differ only over
the last ≈ 2 octaves whatever T is — so this most powerful test has a fixed error pair, and the
two goals cannot both be met for that pair (docs/noise.md, "K for a Gauss–Markov bias").

The cap: τc ≤ τ_max/8 (τ_max the last Allan averaging time): the GM's hump (1.89 τc) then lies
at most at τ_max/4, with ≥ 2 octaves of its 1/τ fall inside the record. A GM whose τc reaches
beyond that *is* a random walk over the record (the nested pair of the selection); this check
only asks whether the data exclude a GM that turns over where the record can see it.

Measured on development seeds (``SeedSequence([s, 4404])``, docs/noise.md, "K for a Gauss–Markov bias"): the
check alone (true N) keeps K on 23/24 N+K axes (1 h, 100 Hz) and lets it pass on 4/24 N+GM axes
(τc = 20 s at the cap, 10 min, 50 Hz); inside :func:`gyrocore.noise.allan.identify_noise`, K claimed
for the GM 33/216 → 21/216 (10 min, 50/100/1000 Hz) and found with K true 171/180 → 162/180
(1 h) — the check costs what the data cannot tell apart. Written by hand: no library offers
the exact likelihood of block means of these processes (statsmodels' ARIMA state space would need
the aggregated GM as an ARMA(1,1) and the random walk as an integrated MA(1), and is not a
dependency).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.stats

#: number of blocks the record is cut into (n − 1 differences enter the likelihood): 256 keeps one
#: likelihood evaluation at a 255×255 Cholesky (< 1 ms; 0.2–0.4 s CPU per axis for the check)
#: while Δ = T/256 stays below the shortest cap the check considers (τ_max/8 ≥ T/32 = 8Δ).
#: (512 blocks: the same decisions on the 12 + 12 development axes of the prototype, 3–5× the time)
N_BLOCKS = 256
#: cap of the GM's τc as a fraction of the last Allan averaging time (see the module docstring)
TC_INSIDE = 1.0 / 8.0
#: one-sided level of the check: the level of every stand-in check (gmwm.ALPHA_STANDIN)
ALPHA = 0.05


@dataclass(frozen=True)
class RandomWalkCheck:
    """Outcome of :func:`random_walk_check` for one axis.

    Attributes
    ----------
    claimed : bool
        True when the GM world is rejected (K stands); False when a GM that turns over inside the
        record explains the data as well (K then reported as ambiguous with the GM).
    d : float
        Observed −2 log L_K − (−2 log L_GM) on the differenced block means.
    expected : float
        Its mean were the fitted GM world true (2·KL).
    sd : float
        Its standard deviation were the fitted GM world true.
    k_rad_s_per_sqrt_s : float
        K of the random-walk world fitted to the block means.
    gm_sigma_rad_s, gm_tau_c_s : float
        σ and τc of the GM world fitted to the block means (τc ≤ ``tau_c_max_s``).
    tau_c_max_s : float
        The cap of τc, s.
    block_s : float
        Block length Δ, s.
    """

    claimed: bool
    d: float
    expected: float
    sd: float
    k_rad_s_per_sqrt_s: float
    gm_sigma_rad_s: float
    gm_tau_c_s: float
    tau_c_max_s: float
    block_s: float


def block_differences(omega_rad_s: np.ndarray, rate_hz: float, *, n_blocks: int = N_BLOCKS) -> tuple[np.ndarray, float]:
    """Differences of the block means of one rate axis.

    Parameters
    ----------
    omega_rad_s : ndarray (n,)
        Rate samples of one axis, rad/s, evenly spaced at ``rate_hz``.
    rate_hz : float
    n_blocks : int

    Returns
    -------
    d : ndarray (n_blocks − 1,)
        Differences of consecutive block means, rad/s (trailing samples that do not fill a block
        are left out).
    block_s : float
        Block length Δ, s.
    """
    x = np.asarray(omega_rad_s, float)
    size = _block_size(x.size, n_blocks)
    nb = x.size // size
    means = x[: nb * size].reshape(nb, size).mean(axis=1)
    return np.diff(means), size / float(rate_hz)


def acov_white(n: int, block_s: float) -> np.ndarray:
    """Autocovariance (lags 0…n−1) of the differenced block means of unit white rate noise (N = 1)."""
    g = np.zeros(n)
    g[0] = 2.0 / block_s
    if n > 1:
        g[1] = -1.0 / block_s
    return g


def acov_angle(n: int, block_s: float) -> np.ndarray:
    """… of unit white angle noise (Q = 1 rad): second differences of white noise over Δ."""
    g = np.zeros(n)
    for k, v in enumerate((6.0, -4.0, 1.0)):
        if k < n:
            g[k] = v / block_s**2
    return g


def acov_rw(n: int, block_s: float) -> np.ndarray:
    """… of a unit rate random walk (K = 1 rad/s/√s)."""
    g = np.zeros(n)
    g[0] = 2.0 * block_s / 3.0
    if n > 1:
        g[1] = block_s / 6.0
    return g


def acov_gm(n: int, block_s: float, tau_c_s: float) -> np.ndarray:
    """… of a unit first-order Gauss–Markov process (σ = 1 rad/s) of correlation time τc."""
    x = block_s / tau_c_s
    k = np.arange(n + 1, dtype=float)
    c = tau_c_s**2 / block_s**2
    R = c * 2.0 * (math.cosh(x) - 1.0) * np.exp(-k * x) if x < 700 else np.zeros(n + 1)
    R[0] = 2.0 * c * (x - 1.0 + math.exp(-x))
    Rm = np.concatenate([[R[1]], R[:-1]])  # R_{k−1}, with R_{−1} = R_1
    return 2.0 * R[:n] - Rm[:n] - R[1 : n + 1]


def _chol(gamma: np.ndarray):
    try:
        return scipy.linalg.cho_factor(scipy.linalg.toeplitz(gamma), lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return None


def neg2_loglik(d: np.ndarray, gamma: np.ndarray) -> float:
    """−2 log L (without the n log 2π constant) of zero-mean Gaussian ``d`` with Toeplitz autocovariance ``gamma``."""
    cf = _chol(gamma)
    if cf is None:
        return float("inf")
    sol = scipy.linalg.cho_solve(cf, d, check_finite=False)
    return float(2.0 * np.sum(np.log(np.diag(cf[0]))) + d @ sol)


def kl2(gamma_p: np.ndarray, gamma_q: np.ndarray) -> tuple[float, float]:
    """2·KL(P‖Q) of two zero-mean Gaussian Toeplitz laws and the variance of the LR statistic under P.

    Returns (tr(Σ_Q⁻¹Σ_P) − n + log det Σ_Q − log det Σ_P, 2 tr((Σ_Q⁻¹Σ_P − I)²)): the mean and
    variance of −2 log L_Q − (−2 log L_P) when the data follow P.
    """
    Sp = scipy.linalg.toeplitz(gamma_p)
    cq, cp = _chol(gamma_q), _chol(gamma_p)
    if cq is None or cp is None:
        return float("inf"), float("inf")
    M = scipy.linalg.cho_solve(cq, Sp, check_finite=False)
    n = gamma_p.size
    mean = float(np.trace(M) - n + 2.0 * np.sum(np.log(np.diag(cq[0]))) - 2.0 * np.sum(np.log(np.diag(cp[0]))))
    A = M - np.eye(n)
    return mean, float(2.0 * np.sum(A * A.T))


#: draws of the generalised χ² laws below (explicit seed: the check and the rule are deterministic)
GCHI2_DRAWS = 20000
GCHI2_SEED = 20261127


def gchi2_draws(gamma_data: np.ndarray, gamma_k: np.ndarray, gamma_g: np.ndarray) -> np.ndarray:
    """Draws of D = −2 log L_K − (−2 log L_GM) when the differences follow ``gamma_data``.

    D = dᵀ(Σ_K⁻¹ − Σ_G⁻¹)d + log det Σ_K − log det Σ_G is a quadratic form of the Gaussian d:
    with L Lᵀ = Σ_data, D = Σ μ_i χ²₁,i + c (μ the eigenvalues of Lᵀ(Σ_K⁻¹ − Σ_G⁻¹)L), a
    generalised χ². Its quantiles are taken from :data:`GCHI2_DRAWS` seeded draws — the normal
    form N(E, V) is far from it: under a random walk D is dominated by a few large μ (seen from
    −0.6 to −79 on 24 axes of one cell), and the normal form's variance put the rule's miss rate
    at 13 % where 0 of 36 axes missed.
    """
    n = gamma_data.size
    T = scipy.linalg.toeplitz
    L = np.linalg.cholesky(T(gamma_data))
    ck, cg = _chol(gamma_k), _chol(gamma_g)
    A = scipy.linalg.cho_solve(ck, L, check_finite=False) - scipy.linalg.cho_solve(cg, L, check_finite=False)
    mu = np.linalg.eigvalsh(L.T @ A)
    c = 2.0 * float(np.sum(np.log(np.diag(ck[0]))) - np.sum(np.log(np.diag(cg[0]))))
    rng = np.random.default_rng(np.random.SeedSequence(GCHI2_SEED))
    out = np.empty(GCHI2_DRAWS)
    step = max(1, 2_000_000 // max(n, 1))
    for a in range(0, GCHI2_DRAWS, step):
        z = rng.standard_normal((min(step, GCHI2_DRAWS - a), n))
        out[a : a + z.shape[0]] = (z * z) @ mu + c
    return out


def _fit_rw(objective, k2_guess: float) -> float:
    """K² minimising ``objective(K²)`` (bounded scalar search in log K²)."""
    lo, hi = math.log(max(k2_guess, 1e-300)) - 25.0, math.log(max(k2_guess, 1e-300)) + 12.0
    r = scipy.optimize.minimize_scalar(
        lambda u: objective(math.exp(u)), bounds=(lo, hi), method="bounded", options={"xatol": 1e-3}
    )
    return math.exp(float(r.x)) if r.fun <= objective(0.0) else 0.0


def _fit_gm(objective, s2_guess: float, tc_lo: float, tc_hi: float) -> tuple[float, float]:
    """(σ², τc) minimising ``objective(σ², τc)``: τc profiled on a log grid and refined, σ² bounded."""

    def prof(tc):
        lo, hi = math.log(max(s2_guess, 1e-300)) - 20.0, math.log(max(s2_guess, 1e-300)) + 10.0
        r = scipy.optimize.minimize_scalar(
            lambda u: objective(math.exp(u), tc), bounds=(lo, hi), method="bounded", options={"xatol": 1e-3}
        )
        return float(r.fun), math.exp(float(r.x))

    grid = np.geomspace(tc_lo, tc_hi, 9) if tc_hi > tc_lo else np.array([tc_lo])
    vals = [prof(float(t)) for t in grid]
    i = int(np.argmin([v[0] for v in vals]))
    best = (vals[i][0], vals[i][1], float(grid[i]))
    if grid.size > 1:
        a, b = math.log(grid[max(i - 1, 0)]), math.log(grid[min(i + 1, grid.size - 1)])
        r = scipy.optimize.minimize_scalar(
            lambda u: prof(math.exp(u))[0], bounds=(a, b), method="bounded", options={"xatol": 0.05}
        )
        if r.fun < best[0]:
            best = (float(r.fun), prof(math.exp(float(r.x)))[1], math.exp(float(r.x)))
    return best[1], best[2]


def tau_c_cap_s(tau_max_s: float) -> float:
    """The largest τc of a GM that turns over inside the record (:data:`TC_INSIDE` × τ_max)."""
    return float(tau_max_s) * TC_INSIDE


def _block_size(n_samples: int, n_blocks: int) -> int:
    """Samples per block (trailing samples that do not fill a block are left out)."""
    return max(1, int(n_samples) // int(n_blocks))


def _setup(n_samples: int, rate_hz: float, tau_max_s: float, n_blocks: int, arw: float, quantization: float):
    """Block geometry and the fixed part of both worlds, or None when the record is too short.

    Returns (n differences, Δ s, τc cap s, τc lower end = 2Δ, unit random-walk autocovariance,
    autocovariance of the white rate + white angle noise held at the GMWM values).
    """
    size = _block_size(n_samples, n_blocks)
    n, block_s = int(n_samples) // size - 1, size / float(rate_hz)
    cap = tau_c_cap_s(tau_max_s)
    if n < 63 or cap < 2.0 * block_s:
        return None
    base = arw**2 * acov_white(n, block_s) + (quantization or 0.0) ** 2 * acov_angle(n, block_s)
    return n, block_s, cap, 2.0 * block_s, acov_rw(n, block_s), base


def _threshold(gam_g: np.ndarray, base: np.ndarray, gk: np.ndarray, k2_guess: float) -> tuple[float, float]:
    """(α quantile of D were the GM world ``gam_g`` true, K*² of the random walk closest to it)."""
    k2s = _fit_rw(lambda v: kl2(gam_g, base + v * gk)[0], k2_guess)
    return float(np.quantile(gchi2_draws(gam_g, base + k2s * gk, gam_g), ALPHA)), k2s


def random_walk_check(
    omega_rad_s: np.ndarray,
    rate_hz: float,
    *,
    arw_rad_per_sqrt_s: float,
    quantization_rad: float = 0.0,
    tau_max_s: float,
    n_blocks: int = N_BLOCKS,
) -> RandomWalkCheck | None:
    """Is a random walk K told from a Gauss–Markov bias that turns over inside the record?

    Parameters
    ----------
    omega_rad_s : ndarray (n,)
        Rate samples of one still axis, rad/s.
    rate_hz : float
    arw_rad_per_sqrt_s, quantization_rad : float
        N and Q of the GMWM fit (held fixed: the short octaves determine them to < 1 %).
    tau_max_s : float
        Last Allan averaging time of the fit, s (sets the τc cap).

    Returns
    -------
    RandomWalkCheck or None
        None when the record is too short for the check (fewer than 64 blocks or the cap below
        two blocks).
    """
    x = np.asarray(omega_rad_s, float)
    got = _setup(x.size, rate_hz, tau_max_s, n_blocks, arw_rad_per_sqrt_s, quantization_rad)
    if got is None:
        return None
    n, block_s, cap, tc_lo, gk, base = got
    d = block_differences(x, rate_hz, n_blocks=n_blocks)[0]
    # scale guesses from the data: the variance of the differences beyond the white part
    excess = max(float(np.mean(d * d)) - base[0], 1e-6 * base[0])
    k2 = _fit_rw(lambda v: neg2_loglik(d, base + v * gk), excess / gk[0])
    s2, tc = _fit_gm(lambda v, t: neg2_loglik(d, base + v * acov_gm(n, block_s, t)), excess, tc_lo, cap)
    gam_k = base + k2 * gk
    gam_g = base + s2 * acov_gm(n, block_s, tc)
    D = neg2_loglik(d, gam_k) - neg2_loglik(d, gam_g)
    if s2 <= 0.0:
        return RandomWalkCheck(True, D, 0.0, 0.0, math.sqrt(k2), 0.0, tc, cap, block_s)
    # the stand-in test: were the GM world true, D would follow a generalised χ² against the random
    # walk closest to it (pseudo-true K*): K claimed below its α quantile
    thr, k2s = _threshold(gam_g, base, gk, k2 if k2 > 0 else excess / gk[0])
    E, V = kl2(gam_g, base + k2s * gk)
    claimed = bool(D < thr)
    return RandomWalkCheck(claimed, D, E, math.sqrt(max(V, 0.0)), math.sqrt(k2), math.sqrt(s2), tc, cap, block_s)


def miss_z(
    *,
    arw_rad_per_sqrt_s: float,
    rrw_rad_per_s_sqrt_s: float,
    quantization_rad: float = 0.0,
    n_samples: int,
    rate_hz: float,
    tau_max_s: float,
    n_blocks: int = N_BLOCKS,
) -> float:
    """The resolvability rule's z for this check with K true (used by :func:`gyrocore.noise.gmwm.expected_z`).

    With the true N, Q, K: G* = the GM world (τc ≤ cap) closest to the truth, K* = the random
    walk closest to G*; threshold t = the α quantile of D under G* (generalised χ²,
    :func:`gchi2_draws`); under the truth D follows the generalised χ² of the truth against G*.
    The miss probability p = P(D ≥ t) is returned as z = Φ⁻¹(1 − p) (∞ when no draw misses).
    """
    got = _setup(n_samples, rate_hz, tau_max_s, n_blocks, arw_rad_per_sqrt_s, quantization_rad)
    if got is None:
        return math.inf
    n, block_s, cap, tc_lo, gk, base = got
    gam_t = base + rrw_rad_per_s_sqrt_s**2 * gk
    s2, tc = _fit_gm(
        lambda v, t: kl2(gam_t, base + v * acov_gm(n, block_s, t))[0], rrw_rad_per_s_sqrt_s**2 * cap, tc_lo, cap
    )
    if s2 <= 0.0:
        return math.inf
    gam_g = base + s2 * acov_gm(n, block_s, tc)
    thr = _threshold(gam_g, base, gk, rrw_rad_per_s_sqrt_s**2)[0]
    # under the truth the data's own fits are ≈ K (the truth) and G*: D's law from the same form
    p_miss = float(np.mean(gchi2_draws(gam_t, gam_t, gam_g) >= thr))
    if p_miss <= 0.0:
        return math.inf
    return float(scipy.stats.norm.isf(p_miss))
