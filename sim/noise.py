"""Stochastic gyro error terms (IEEE Std 952-1997, Annex C), as pure generator functions.

Every function takes an explicit :class:`numpy.random.Generator` and returns the noise of
three independent axes, rad/s, shape ``(n_samples, 3)``, sampled at ``rate_hz``. The
levels follow the Allan-variance terms of DESIGN.md / IEEE 952::

    σ²(τ) = N²/τ  +  (2 ln2/π)·B²  +  K²·τ/3          (+ the Gauss–Markov hump)

* :func:`white_rate_noise` — angle random walk, N in rad/√s (= rad/s/√Hz); per-sample
  σ = N·√rate_hz, so that the Allan variance of the averaged rate is N²/τ.
* :func:`flicker_noise` — bias instability, B in rad/s. A 1/f (flicker) process made with
  Kasdin & Walter's fractional-differencing filter (Kasdin & Walter 1992, "Discrete simulation
  of power law noise", Proc. IEEE FCS; Kasdin 1995, Proc. IEEE 83(5) eq. 115–116): white
  noise of variance Q filtered by (1 − z⁻¹)^(−α/2), α = 1. A single Gauss–Markov process
  does not give the flat Allan floor; this does.
* :func:`rate_random_walk` — K in rad/s/√s: the rate performs a random walk with
  increments of σ = K·√dt.
* :func:`gauss_markov` — first-order Gauss–Markov (exponentially correlated) bias, σ in
  rad/s and correlation time τc in s, discretised exactly: x[k+1] = φ·x[k] + σ·√(1−φ²)·w[k]
  with φ = exp(−dt/τc), started from its stationary distribution.

Quantization noise is not generated here: it is the output rounding in
:func:`gyrocore.effects.output_stage`.

Calibration of the flicker level
--------------------------------
IEEE 952 (C.2) writes the bias-instability rate PSD in its "4∫" convention as
S(f) = (B²/2π)·(1/f), i.e. one-sided S₁(f) = B²/(π f) = h₋₁/f with h₋₁ = B²/π, whose Allan
variance is the constant 2 ln2·h₋₁ = (2 ln2/π)·B² (Barnes et al. 1971, NBS TN 394). The
Kasdin–Walter sequence has one-sided PSD S₁(f) = 2Qτ₀ / |2 sin(π f τ₀)|^α (Kasdin 1995
eq. 116), which for α = 1 and f ≪ 1/τ₀ is Q/(π f). Matching gives Q = B²: the innovation
standard deviation equals B, whatever the sample rate.
"""

from __future__ import annotations

import numpy as np
from scipy import signal

from gyrocore.errors import GyroInputError

__all__ = [
    "white_rate_noise",
    "flicker_noise",
    "rate_random_walk",
    "gauss_markov",
    "kasdin_walter_coefficients",
    "ALLAN_FLICKER_FACTOR",
    "stable_key_int",
    "effect_rng",
]

#: σ_Allan / B for bias instability: sqrt(2 ln2 / π) ≈ 0.6643 (IEEE 952 Table C.1).
ALLAN_FLICKER_FACTOR = float(np.sqrt(2.0 * np.log(2.0) / np.pi))


def _per_axis(value, name: str) -> np.ndarray:
    v = np.broadcast_to(np.asarray(value, dtype=float), (3,)).copy()
    if not np.all(np.isfinite(v)) or np.any(v < 0):
        raise GyroInputError(f"{name} must be finite and >= 0 per axis, got {v.tolist()}")
    return v


def _check(n_samples: int, rate_hz: float) -> tuple[int, float]:
    n = int(n_samples)
    if n < 0:
        raise GyroInputError(f"n_samples must be >= 0, got {n_samples}")
    r = float(rate_hz)
    if not (np.isfinite(r) and r > 0):
        raise GyroInputError(f"rate_hz must be > 0, got {rate_hz}")
    return n, r


def white_rate_noise(
    rng: np.random.Generator, n_samples: int, *, rate_hz: float, n_rad_per_sqrt_s
) -> np.ndarray:
    """White rate noise (angle random walk).

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness (the caller owns the seed).
    n_samples : int
        Number of output samples.
    rate_hz : float
        Sample rate, Hz.
    n_rad_per_sqrt_s : float or array_like, shape (3,)
        ARW coefficient N per axis, rad/√s (= rad/s/√Hz).

    Returns
    -------
    ndarray, shape (n_samples, 3)
        Rate noise, rad/s, per-sample σ = N·√rate_hz (DESIGN.md noise-density convention),
        so that σ²_Allan(τ) = N²/τ (IEEE 952 C.1).
    """
    n, r = _check(n_samples, rate_hz)
    N = _per_axis(n_rad_per_sqrt_s, "n_rad_per_sqrt_s")
    return rng.standard_normal((n, 3)) * (N * np.sqrt(r))[None, :]


def kasdin_walter_coefficients(n: int, alpha: float) -> np.ndarray:
    """Impulse response of (1 − z⁻¹)^(−α/2): h₀ = 1, h_k = h_{k−1}·(k − 1 + α/2)/k.

    Kasdin 1995, Proc. IEEE 83(5), eq. 115. Shape (n,).
    """
    k = np.arange(1, n, dtype=float)
    return np.concatenate([[1.0], np.cumprod((k - 1.0 + alpha / 2.0) / k)])


def flicker_noise(
    rng: np.random.Generator, n_samples: int, *, rate_hz: float, b_rad_s
) -> np.ndarray:
    """Bias instability as flicker (1/f) rate noise with a flat Allan floor.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    n_samples : int
        Number of output samples.
    rate_hz : float
        Sample rate, Hz (the level does not depend on it; kept for a uniform signature).
    b_rad_s : float or array_like, shape (3,)
        Bias-instability coefficient B per axis, rad/s (IEEE 952). The Allan deviation floor
        is B·sqrt(2 ln2/π) ≈ 0.664·B.

    Returns
    -------
    ndarray, shape (n_samples, 3)
        Flicker rate noise, rad/s: white noise of σ = B filtered by Kasdin & Walter's
        α = 1 fractional integrator (see the module docstring for the level). The process
        starts at rest at the first sample (the filter has no pre-history).
    """
    n, _ = _check(n_samples, rate_hz)
    B = _per_axis(b_rad_s, "b_rad_s")
    if n == 0:
        return np.zeros((0, 3))
    w = rng.standard_normal((n, 3)) * B[None, :]
    h = kasdin_walter_coefficients(n, 1.0)
    return signal.fftconvolve(w, h[:, None], mode="full", axes=0)[:n]


def rate_random_walk(
    rng: np.random.Generator, n_samples: int, *, rate_hz: float, k_rad_s_per_sqrt_s
) -> np.ndarray:
    """Rate random walk.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    n_samples : int
        Number of output samples.
    rate_hz : float
        Sample rate, Hz.
    k_rad_s_per_sqrt_s : float or array_like, shape (3,)
        RRW coefficient K per axis, rad/s/√s.

    Returns
    -------
    ndarray, shape (n_samples, 3)
        Random walk of the rate, rad/s: cumulative sum of independent increments of
        σ = K·√dt (the first sample already carries one increment), so that
        σ²_Allan(τ) = K²τ/3 (IEEE 952 C.4) up to a discretisation term O(dt/τ).
    """
    n, r = _check(n_samples, rate_hz)
    K = _per_axis(k_rad_s_per_sqrt_s, "k_rad_s_per_sqrt_s")
    return np.cumsum(rng.standard_normal((n, 3)) * (K * np.sqrt(1.0 / r))[None, :], axis=0)


def gauss_markov(
    rng: np.random.Generator, n_samples: int, *, rate_hz: float, sigma_rad_s, tau_c_s
) -> np.ndarray:
    """First-order Gauss–Markov (exponentially correlated) bias, exact discretisation.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    n_samples : int
        Number of output samples.
    rate_hz : float
        Sample rate, Hz.
    sigma_rad_s : float or array_like, shape (3,)
        Stationary standard deviation per axis, rad/s.
    tau_c_s : float or array_like, shape (3,)
        Correlation time per axis, s (> 0).

    Returns
    -------
    ndarray, shape (n_samples, 3)
        x[0] ~ N(0, σ²) (stationary start); x[k] = φ·x[k−1] + σ·√(1−φ²)·w[k],
        φ = exp(−dt/τc): the exact sampling of dx/dt = −x/τc + white noise, so that
        E[x[k]x[k+m]] = σ²·exp(−m·dt/τc) at every sample rate.
    """
    n, r = _check(n_samples, rate_hz)
    sigma = _per_axis(sigma_rad_s, "sigma_rad_s")
    tau = np.broadcast_to(np.asarray(tau_c_s, dtype=float), (3,))
    if not np.all(np.isfinite(tau)) or np.any(tau <= 0):
        raise GyroInputError(f"tau_c_s must be finite and > 0 per axis, got {tau.tolist()}")
    w = rng.standard_normal((n, 3))
    out = np.empty((n, 3))
    if n == 0:
        return out
    for i in range(3):
        phi = float(np.exp(-1.0 / (r * tau[i])))
        u = w[:, i] * (sigma[i] * np.sqrt(1.0 - phi * phi))
        u[0] = w[0, i] * sigma[i]
        out[:, i] = signal.lfilter([1.0], [1.0, -phi], u)
    return out


def stable_key_int(key: str) -> int:
    """A stable 32-bit integer for a string key (first 4 bytes of its SHA-256).

    Python's ``hash`` is salted per process; this is not, so a stream derived from it is
    the same in every run and on every machine.
    """
    import hashlib

    return int.from_bytes(hashlib.sha256(key.encode("utf-8")).digest()[:4], "little")


def effect_rng(seed: int, key: str) -> np.random.Generator:
    """The random stream of one effect: ``SeedSequence(seed, spawn_key=(stable_key_int(key),))``.

    Each effect draws from its own stream, derived from the seed and a stable per-effect key
    (not from a spawn order), so adding or removing one effect leaves the others' draws
    unchanged.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or int(seed) < 0:
        raise GyroInputError(f"seed must be an integer >= 0, got {seed!r}")
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(int(seed), spawn_key=(stable_key_int(key),))))
