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

import math

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
    "shaped_taps",
    "ShapedNoise",
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


# ---------------------------------------------------------------------------- shaped (vibration) noise
def shaped_taps(f_hz, psd_rad2_s2_hz, *, rate_hz: float, grid_hz: float | None = None) -> np.ndarray:
    """FIR taps (L, 3) whose output, driven by unit white noise, has the one-sided PSD ``psd``.

    Frequency-sampling design (no window): the amplitude A(f_k) = √(S(f_k)·fs/2) on the grid
    f_k = k·fs/L (S interpolated linearly in f from ``f_hz``, 0 outside it), zero phase,
    ``irfft`` of length L and rolled by L/2 (linear phase). For unit white input the output's
    one-sided PSD is (2/fs)·|H(f)|², which equals S(f_k) at every grid frequency, and its variance
    is Σh² = (1/L)·Σ_k |A_k|² = Σ_k S(f_k)·fs/L ≈ ∫S df exactly on the grid (Parseval); between
    grid points |H|² interpolates (Dirichlet kernel), so any average over ≥ 2 grid spacings
    (a Welch bin of the spec's resolution) has the spec's expectation.

    Parameters
    ----------
    f_hz : array_like, shape (n,)
        Increasing frequency grid of the PSD, Hz.
    psd_rad2_s2_hz : array_like, shape (3, n)
        One-sided PSD per axis, (rad/s)²/Hz (≥ 0).
    rate_hz : float
        Sample rate of the generated noise, Hz.
    grid_hz : float, optional
        Design grid spacing fs/L, Hz; default half the smallest spacing of ``f_hz`` (so a spec
        bin holds two grid points).

    Returns
    -------
    ndarray, shape (L, 3)
    """
    f = np.asarray(f_hz, float)
    S = np.asarray(psd_rad2_s2_hz, float)
    r = float(rate_hz)
    if f.ndim != 1 or f.size < 2 or S.shape != (3, f.size) or not np.all(np.diff(f) > 0):
        raise GyroInputError(f"shaped vibration: f_hz must be an increasing grid (n,) and psd (3, n); got {f.shape}, {S.shape}")
    if not (np.all(np.isfinite(S)) and np.all(S >= 0)):
        raise GyroInputError("shaped vibration: psd_rad2_s2_hz must be finite and >= 0")
    if not (np.isfinite(r) and r > 0):
        raise GyroInputError(f"rate_hz must be > 0, got {rate_hz}")
    df = float(grid_hz) if grid_hz is not None else float(np.min(np.diff(f))) / 2.0
    L = max(int(math.ceil(r / df)), 8)
    fk = np.fft.rfftfreq(L, d=1.0 / r)
    taps = np.empty((L, 3))
    for j in range(3):
        Sk = np.interp(fk, f, S[j], left=0.0, right=0.0)
        A = np.sqrt(Sk * r / 2.0)
        taps[:, j] = np.roll(np.fft.irfft(A, L), L // 2)
    return taps


class ShapedNoise:
    """Gaussian noise (n, 3) through FIR taps, generated in fixed internal blocks (block-friendly).

    White noise is drawn from ``rng`` in fixed blocks of B samples (``standard_normal((B, 3))``,
    one after the other), each block is FFT-convolved with the taps and overlap-added (the tail
    of L − 1 samples carried to the next block), and :meth:`next` serves the caller's chunks from
    that stream. So ``next(n1); next(n2)`` returns exactly the bits of ``next(n1 + n2)`` whatever
    the chunking. The first L − 1 outputs (the filter filling up) are dropped: the noise is
    stationary from its first sample.

    Parameters
    ----------
    rng : numpy.random.Generator
    taps : ndarray, shape (L, 3)
        :func:`shaped_taps`.
    block : int, optional
        Internal block length (default max(4 L, 8192)); part of the definition of the stream
        (another block length gives another realisation).
    """

    def __init__(self, rng: np.random.Generator, taps: np.ndarray, *, block: int | None = None) -> None:
        from scipy import fft as _fft

        self._rng = rng
        h = np.asarray(taps, float)
        if h.ndim != 2 or h.shape[1] != 3 or h.shape[0] < 1:
            raise GyroInputError(f"ShapedNoise taps must have shape (L, 3), got {h.shape}")
        self.L = int(h.shape[0])
        self.B = int(block) if block is not None else max(4 * self.L, 8192)
        self._nfft = _fft.next_fast_len(self.B + self.L - 1, real=True)
        self._H = np.fft.rfft(h, self._nfft, axis=0)
        self._tail = np.zeros((self.L - 1, 3))
        self._chunks: list[np.ndarray] = []
        self._have = 0
        first = self._block()
        self._push(first[self.L - 1:])

    def _block(self) -> np.ndarray:
        w = self._rng.standard_normal((self.B, 3))
        y = np.fft.irfft(np.fft.rfft(w, self._nfft, axis=0) * self._H, self._nfft, axis=0)[: self.B + self.L - 1]
        y[: self.L - 1] += self._tail
        self._tail = y[self.B:].copy()
        return y[: self.B]

    def _push(self, x: np.ndarray) -> None:
        if x.shape[0]:
            self._chunks.append(x)
            self._have += x.shape[0]

    def next(self, n_samples: int) -> np.ndarray:
        """The next ``n_samples`` samples, rad/s, shape (n, 3)."""
        n = int(n_samples)
        if n < 0:
            raise GyroInputError(f"n_samples must be >= 0, got {n_samples}")
        while self._have < n:
            self._push(self._block())
        buf = np.concatenate(self._chunks, axis=0) if len(self._chunks) > 1 else (self._chunks[0] if self._chunks else np.zeros((0, 3)))
        out, rest = buf[:n].copy(), buf[n:]
        self._chunks = [rest] if rest.shape[0] else []
        self._have = rest.shape[0]
        return out
