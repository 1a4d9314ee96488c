"""Stochastic gyro error terms (IEEE Std 952-1997, Annex C), generated in blocks.

Every term is a *block generator*: created with an explicit :class:`numpy.random.Generator`
and its levels, then asked for consecutive blocks of samples with ``take(m)``; the state
(filter memories, the random walk's last value, the position in the random stream) is
carried from one block to the next, so the samples do not depend on how the record is cut:
``take(997)`` then ``take(4096)`` gives, bit for bit, the first 5093 samples of
``take(5093)`` (tested for every term). A long record therefore never needs its whole noise
in memory. The plain functions (:func:`white_rate_noise`, ...) are one ``take(n)``.

Each term returns the noise of three independent axes, rad/s, shape ``(m, 3)``, sampled at
``rate_hz``. The levels follow the Allan-variance terms of DESIGN.md / IEEE 952::

    σ²(τ) = N²/τ  +  (2 ln2/π)·B²  +  K²·τ/3          (+ the Gauss–Markov hump)

* :class:`WhiteRateBlocks` — angle random walk, N in rad/√s (= rad/s/√Hz); per-sample
  σ = N·√rate_hz, so that the Allan variance of the averaged rate is N²/τ.
* :class:`FlickerBlocks` — bias instability, B in rad/s: white noise through a cascade of
  first-order pole–zero sections (a filter bank approximating 1/f; see "Flicker" below).
* :class:`RateRandomWalkBlocks` — K in rad/s/√s: the rate performs a random walk with
  increments of σ = K·√dt.
* :class:`GaussMarkovBlocks` — first-order Gauss–Markov (exponentially correlated) bias, σ
  in rad/s and correlation time τc in s, discretised exactly: x[k+1] = φ·x[k] + σ·√(1−φ²)·w[k]
  with φ = exp(−dt/τc), started from its stationary distribution.

Quantization noise is not generated here: it is the output rounding in
:func:`gyrocore.effects.registry.output_stage`.

Flicker (bias instability)
--------------------------
IEEE 952 (C.2) writes the bias-instability rate PSD in its "4∫" convention as
S(f) = (B²/2π)·(1/f), i.e. one-sided S₁(f) = B²/(π f) = h₋₁/f with h₋₁ = B²/π, whose Allan
variance is the constant 2 ln2·h₋₁ = (2 ln2/π)·B² (Barnes et al. 1971, NBS TN 394).

A 1/f spectrum has no finite-order rational form, and the exact fractional integrator of
Kasdin & Walter (1992) used before (an FFT convolution with an impulse response as long as
the record) needs the whole record at once. Here 1/f is approximated over a stated band by
a cascade of first-order analog sections (s + 2π z_i)/(s + 2π p_i) with poles p_i spaced
geometrically, :data:`FLICKER_SECTIONS_PER_DECADE` per decade (ratio r = 10^(1/2)), and each
zero z_i = p_i·√r half-way (in log f) to the next pole: between a pole and its zero the
magnitude falls at −20 dB/decade, between a zero and the next pole it is flat, on average
−10 dB/decade, i.e. |H|² ∝ 1/f (Keshner 1982, Proc. IEEE 70(3); Corsini & Saletti 1988,
IEEE Trans. Instrum. Meas. 37(4)). The lowest pole is :data:`FLICKER_F_LO_HZ`, the sections
go up to rate/4; each is discretised by the bilinear transform with its corner frequencies
pre-warped (so the digital corners are where they are designed), and the cascade runs in
:func:`scipy.signal.sosfilt` with its section memories carried between blocks (started at
rest, as Kasdin–Walter's was: the process is switched on at the first sample). One unit
normal per sample and axis drives it, times B; the gain is set so that the geometric mean of
f·S₁(f) over 10⁻⁵ Hz … rate/40 is B²/π exactly.

Band claimed, from the digital filter's exact response (``scipy.signal.sosfreqz``, checked
in tests/sim/test_noise.py): S₁(f) is within ±1 % of B²/(π f) for
:data:`FLICKER_BAND_LO_HZ` ≤ f ≤ rate/20 (±0.2 % up to rate/40; the ripple of two sections
per decade is ±0.1 %), and the Allan deviation of the stationary process, from the exact PSD
(σ²(m) = 2∫S₁(f)·sin⁴(πfmτ₀)/(m sin(πfτ₀))² df), is within ±0.1 % of B·√(2 ln2/π) for
averaging factors m ≥ 16 up to τ = 10⁵ s, ±0.3 % at m = 8 (−0.5 … −3 % at m = 2…4 and
−2 … −18 % at m = 1, depending on the rate: there the white ARW dominates every real gyro). Above rate/4 the spectrum flattens (the last
zero) and rolls off towards Nyquist; below 10⁻⁷ Hz it is flat.
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
    "LowpassWhiteNoise",
    "AngleWhiteNoise",
    "noise_term_generator",
    "WhiteRateBlocks",
    "FlickerBlocks",
    "RateRandomWalkBlocks",
    "GaussMarkovBlocks",
    "flicker_sos",
    "kasdin_walter_coefficients",
    "kasdin_walter_flicker",
    "ALLAN_FLICKER_FACTOR",
    "FLICKER_F_LO_HZ",
    "FLICKER_BAND_LO_HZ",
    "FLICKER_SECTIONS_PER_DECADE",
    "stable_key_int",
    "effect_rng",
    "shaped_taps",
    "ShapedNoise",
]

#: σ_Allan / B for bias instability: sqrt(2 ln2 / π) ≈ 0.6643 (IEEE 952 Table C.1).
ALLAN_FLICKER_FACTOR = float(np.sqrt(2.0 * np.log(2.0) / np.pi))
#: Lowest pole of the flicker cascade, Hz (below it the spectrum is flat).
FLICKER_F_LO_HZ = 1e-7
#: Lowest frequency of the claimed 1/f band, Hz (a decade above the lowest pole).
FLICKER_BAND_LO_HZ = 1e-6
#: Sections of the flicker cascade per decade of frequency (ripple ±0.1 % in PSD).
FLICKER_SECTIONS_PER_DECADE = 2
#: Highest zero of the flicker cascade as a fraction of the sample rate.
_FLICKER_TOP_FRACTION = 0.25


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


class _Blocks:
    """Common part of the block generators: the stream, the position, ``take``."""

    def __init__(self, rng: np.random.Generator, rate_hz: float) -> None:
        if not isinstance(rng, np.random.Generator):
            raise GyroInputError("the noise needs an explicit numpy.random.Generator")
        _, self.rate_hz = _check(0, rate_hz)
        self.rng = rng
        #: samples produced so far
        self.position = 0

    def take(self, m: int) -> np.ndarray:
        """The next ``m`` samples, rad/s, shape (m, 3) (state carried to the next call)."""
        m, _ = _check(m, self.rate_hz)
        out = self._take(m)
        self.position += m
        return out

    def _take(self, m: int) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError


class WhiteRateBlocks(_Blocks):
    """White rate noise (angle random walk) in blocks.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness (the caller owns the seed).
    rate_hz : float
        Sample rate, Hz.
    n_rad_per_sqrt_s : float or array_like, shape (3,)
        ARW coefficient N per axis, rad/√s (= rad/s/√Hz). Per-sample σ = N·√rate_hz
        (DESIGN.md noise-density convention), so that σ²_Allan(τ) = N²/τ (IEEE 952 C.1).
    """

    def __init__(self, rng, *, rate_hz: float, n_rad_per_sqrt_s) -> None:
        super().__init__(rng, rate_hz)
        self._sigma = (_per_axis(n_rad_per_sqrt_s, "n_rad_per_sqrt_s") * np.sqrt(self.rate_hz))[None, :]

    def _take(self, m):
        # Generator.standard_normal fills row-major from one stream: blocks (a, 3) then (b, 3)
        # draw exactly the numbers of one (a + b, 3) call
        return self.rng.standard_normal((m, 3)) * self._sigma


def flicker_sos(rate_hz: float) -> np.ndarray:
    """Second-order sections of the 1/f cascade at ``rate_hz`` (unit-B gain), shape (n_sections, 6).

    Analog sections (s + 2πz_i)/(s + 2πp_i), p_i = FLICKER_F_LO_HZ·r^i, z_i = p_i·√r,
    r = 10^(1/FLICKER_SECTIONS_PER_DECADE), up to the first zero at or above rate/4; bilinear
    transform with pre-warped corners (ω = 2·rate·tan(π f/rate)). The overall gain makes
    f·S₁(f) = 1/π (geometric mean over 10⁻⁵ Hz … rate/40) for white input of unit variance
    per sample, i.e. S₁(f) = B²/(π f) for input of standard deviation B (module docstring).
    """
    _, rate = _check(0, rate_hz)
    r = 10.0 ** (1.0 / FLICKER_SECTIONS_PER_DECADE)
    top = _FLICKER_TOP_FRACTION * rate
    if top <= 10.0 * FLICKER_F_LO_HZ:
        raise GyroInputError(f"flicker noise needs a rate above {40 * FLICKER_F_LO_HZ:g} Hz, got {rate:g} Hz")
    poles = []
    f = FLICKER_F_LO_HZ
    while True:
        poles.append(f)
        if f * np.sqrt(r) >= top:
            break
        f *= r
    p_hz = np.asarray(poles)
    z_hz = p_hz * np.sqrt(r)
    c = 2.0 * rate
    wp = c * np.tan(np.pi * np.minimum(p_hz, 0.49 * rate) / rate)
    wz = c * np.tan(np.pi * np.minimum(z_hz, 0.49 * rate) / rate)
    # bilinear transform of (s + wz)/(s + wp): k·(1 − zd z⁻¹)/(1 − pd z⁻¹)
    k = (c + wz) / (c + wp)
    sos = np.zeros((p_hz.size, 6))
    sos[:, 0] = k
    sos[:, 1] = -k * (c - wz) / (c + wz)
    sos[:, 3] = 1.0
    sos[:, 4] = -(c - wp) / (c + wp)
    # level: one-sided PSD of unit-variance white input through H is (2/rate)|H|²; want 1/(πf)
    f_grid = np.logspace(-5.0, np.log10(rate / 40.0), 2001)
    _, h = signal.sosfreqz(sos, worN=f_grid, fs=rate)
    level = float(np.exp(np.mean(np.log(f_grid * np.abs(h) ** 2 * (2.0 / rate) * np.pi))))
    sos[0, :3] /= np.sqrt(level)
    return sos


class FlickerBlocks(_Blocks):
    """Bias instability as flicker (1/f) rate noise, in blocks (module docstring, "Flicker").

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    rate_hz : float
        Sample rate, Hz (the level does not depend on it).
    b_rad_s : float or array_like, shape (3,)
        Bias-instability coefficient B per axis, rad/s (IEEE 952). The Allan deviation floor
        is B·sqrt(2 ln2/π) ≈ 0.664·B for averaging times from 16 samples to 10⁵ s (±0.1 %; ±0.3 % at 8);
        the PSD is B²/(π f) within ±1 % from 10⁻⁶ Hz to rate/20.

    Notes
    -----
    White noise of σ = B through :func:`flicker_sos` (``scipy.signal.sosfilt``, section
    memories carried between blocks, started at rest at the first sample).
    """

    def __init__(self, rng, *, rate_hz: float, b_rad_s) -> None:
        super().__init__(rng, rate_hz)
        self._b = _per_axis(b_rad_s, "b_rad_s")[None, :]
        self.sos = flicker_sos(self.rate_hz)
        self._zi = np.zeros((self.sos.shape[0], 2, 3))

    def _take(self, m):
        w = self.rng.standard_normal((m, 3)) * self._b
        if m == 0:
            return w
        y, self._zi = signal.sosfilt(self.sos, w, axis=0, zi=self._zi)
        return y


class RateRandomWalkBlocks(_Blocks):
    """Rate random walk in blocks.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    rate_hz : float
        Sample rate, Hz.
    k_rad_s_per_sqrt_s : float or array_like, shape (3,)
        RRW coefficient K per axis, rad/s/√s: cumulative sum of independent increments of
        σ = K·√dt (the first sample already carries one increment), so that
        σ²_Allan(τ) = K²τ/3 (IEEE 952 C.4) up to a discretisation term O(dt/τ).
    """

    def __init__(self, rng, *, rate_hz: float, k_rad_s_per_sqrt_s) -> None:
        super().__init__(rng, rate_hz)
        self._step = (_per_axis(k_rad_s_per_sqrt_s, "k_rad_s_per_sqrt_s") * np.sqrt(1.0 / self.rate_hz))[None, :]
        self._last = None  # (1, 3): the walk's value at the previous sample

    def _take(self, m):
        inc = self.rng.standard_normal((m, 3)) * self._step
        if m == 0:
            return inc
        if self._last is None:
            out = np.cumsum(inc, axis=0)
        else:  # the sequential sum continued: last + inc[0], (last + inc[0]) + inc[1], ...
            out = np.cumsum(np.concatenate([self._last, inc]), axis=0)[1:]
        self._last = out[-1:].copy()
        return out


class GaussMarkovBlocks(_Blocks):
    """First-order Gauss–Markov (exponentially correlated) bias in blocks, exact discretisation.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    rate_hz : float
        Sample rate, Hz.
    sigma_rad_s : float or array_like, shape (3,)
        Stationary standard deviation per axis, rad/s.
    tau_c_s : float or array_like, shape (3,)
        Correlation time per axis, s (> 0).

    Notes
    -----
    x[0] ~ N(0, σ²) (stationary start); x[k] = φ·x[k−1] + σ·√(1−φ²)·w[k], φ = exp(−dt/τc):
    the exact sampling of dx/dt = −x/τc + white noise, so that E[x[k]x[k+m]] = σ²·exp(−m·dt/τc)
    at every sample rate. The recursion runs in :func:`scipy.signal.lfilter` with its memory
    carried between blocks.
    """

    def __init__(self, rng, *, rate_hz: float, sigma_rad_s, tau_c_s) -> None:
        super().__init__(rng, rate_hz)
        self._sigma = _per_axis(sigma_rad_s, "sigma_rad_s")
        tau = np.broadcast_to(np.asarray(tau_c_s, dtype=float), (3,))
        if not np.all(np.isfinite(tau)) or np.any(tau <= 0):
            raise GyroInputError(f"tau_c_s must be finite and > 0 per axis, got {tau.tolist()}")
        self._phi = [float(np.exp(-1.0 / (self.rate_hz * tau[i]))) for i in range(3)]
        self._zi = [np.zeros(1) for _ in range(3)]

    def _take(self, m):
        w = self.rng.standard_normal((m, 3))
        out = np.empty((m, 3))
        if m == 0:
            return out
        first = self.position == 0
        for i in range(3):
            phi = self._phi[i]
            u = w[:, i] * (self._sigma[i] * np.sqrt(1.0 - phi * phi))
            if first:
                u[0] = w[0, i] * self._sigma[i]
            out[:, i], self._zi[i] = signal.lfilter([1.0], [1.0, -phi], u, zi=self._zi[i])
        return out


def white_rate_noise(rng: np.random.Generator, n_samples: int, *, rate_hz: float, n_rad_per_sqrt_s) -> np.ndarray:
    """White rate noise (angle random walk), ``n_samples`` × 3, rad/s: :class:`WhiteRateBlocks` in one block."""
    n, _ = _check(n_samples, rate_hz)
    return WhiteRateBlocks(rng, rate_hz=rate_hz, n_rad_per_sqrt_s=n_rad_per_sqrt_s).take(n)


def kasdin_walter_coefficients(n: int, alpha: float) -> np.ndarray:
    """Impulse response of (1 − z⁻¹)^(−α/2): h₀ = 1, h_k = h_{k−1}·(k − 1 + α/2)/k.

    Kasdin 1995, Proc. IEEE 83(5), eq. 115. Shape (n,). (The exact fractional integrator of
    :func:`kasdin_walter_flicker`; the simulator's flicker runs in blocks instead.)
    """
    k = np.arange(1, n, dtype=float)
    return np.concatenate([[1.0], np.cumprod((k - 1.0 + alpha / 2.0) / k)])


def kasdin_walter_flicker(rng: np.random.Generator, n_samples: int, *, rate_hz: float, b_rad_s) -> np.ndarray:
    """The exact discrete flicker process of Kasdin & Walter (whole record, FFT convolution).

    Reference only (tests of models that assume this discretisation, e.g. the GMWM's exact
    discrete flicker AVAR, :func:`gyrocore.noise.avar.flicker_avar_factor`); the simulator uses
    :class:`FlickerBlocks`, which equals it in Allan deviation within 0.3 % for m ≥ 8 and in
    impulse response within 0.2 % for lags ≥ 100 samples, but is lower at m < 8 (this process
    is 1.44× the IEEE asymptote in AVAR at m = 1; :class:`FlickerBlocks` 0.68–0.96×, depending
    on the rate). White noise of σ = B filtered by (1 − z⁻¹)^(−1/2) (Kasdin 1995 eq. 115–116:
    one-sided PSD B²/(π f) for f ≪ rate), started at rest; memory O(n): not for long records.
    """
    n, _ = _check(n_samples, rate_hz)
    B = _per_axis(b_rad_s, "b_rad_s")
    if n == 0:
        return np.zeros((0, 3))
    w = rng.standard_normal((n, 3)) * B[None, :]
    h = kasdin_walter_coefficients(n, 1.0)
    return signal.fftconvolve(w, h[:, None], mode="full", axes=0)[:n]


def flicker_noise(rng: np.random.Generator, n_samples: int, *, rate_hz: float, b_rad_s) -> np.ndarray:
    """Bias instability as flicker (1/f) rate noise, ``n_samples`` × 3, rad/s: :class:`FlickerBlocks` in one block.

    B per axis in rad/s (IEEE 952); Allan floor B·sqrt(2 ln2/π) ≈ 0.664·B over the band of
    :class:`FlickerBlocks`.
    """
    n, _ = _check(n_samples, rate_hz)
    return FlickerBlocks(rng, rate_hz=rate_hz, b_rad_s=b_rad_s).take(n)


def rate_random_walk(rng: np.random.Generator, n_samples: int, *, rate_hz: float, k_rad_s_per_sqrt_s) -> np.ndarray:
    """Rate random walk, ``n_samples`` × 3, rad/s: :class:`RateRandomWalkBlocks` in one block."""
    n, _ = _check(n_samples, rate_hz)
    return RateRandomWalkBlocks(rng, rate_hz=rate_hz, k_rad_s_per_sqrt_s=k_rad_s_per_sqrt_s).take(n)


def gauss_markov(rng: np.random.Generator, n_samples: int, *, rate_hz: float, sigma_rad_s, tau_c_s) -> np.ndarray:
    """First-order Gauss–Markov bias, ``n_samples`` × 3, rad/s: :class:`GaussMarkovBlocks` in one block."""
    n, _ = _check(n_samples, rate_hz)
    return GaussMarkovBlocks(rng, rate_hz=rate_hz, sigma_rad_s=sigma_rad_s, tau_c_s=tau_c_s).take(n)


class LowpassWhiteNoise(_Blocks):
    """White rate noise generated *before* a 2nd-order Butterworth low-pass (``arw_lowpass``,
    ``arw_student``; :data:`gyrocore.effects.registry.NOISE_TERMS`): the chip's digital low-pass shapes
    its own noise. Block generator (:class:`_Blocks`): draws consumed in row-major (m, 3) order,
    the filter state carried between blocks (scipy.signal.lfilter with ``zi``), so any sequence
    of :meth:`take` equals one call for the total, bit for bit.

    Parameters
    ----------
    rng : numpy.random.Generator
        The term's own stream.
    rate_hz : float
        Sample rate, Hz.
    n_rad_per_sqrt_s : float or array_like, shape (3,)
        Density N per axis, rad/√s: per-sample σ = N·√rate_hz before the filter, so the
        low-frequency density (and the long-τ Allan variance N²/τ) is N — unit DC gain.
    bandwidth_hz : float
        Corner of the 2nd-order Butterworth (scipy.signal.butter(2, f, fs=rate)), 0 < f <
        rate/2; 0 = no filter.
    nu : float or array_like, shape (3,), optional
        Student-t degrees of freedom per axis (> 2): draws t_ν·√((ν − 2)/ν) (unit variance,
        excess kurtosis 6/(ν − 4) for ν > 4). None = Gaussian.

    The filter starts in steady state for the first sample (lfilter_zi × the first draw), as the
    catalogue's ``lowpass`` does for the signal.
    """

    def __init__(self, rng, *, rate_hz: float, n_rad_per_sqrt_s, bandwidth_hz: float = 0.0, nu=None) -> None:
        super().__init__(rng, rate_hz)
        r = self.rate_hz
        self._scale = _per_axis(n_rad_per_sqrt_s, "n_rad_per_sqrt_s") * np.sqrt(r)
        fc = float(bandwidth_hz)
        if not np.isfinite(fc) or fc < 0 or fc >= r / 2:
            raise GyroInputError(
                f"noise low-pass bandwidth_hz must be 0 (none) or in (0, {r / 2:g}) Hz at {r:g} Hz, got {fc:g}"
            )
        self._ba = signal.butter(2, fc, fs=r) if fc > 0 else None
        self._zi = None
        if nu is None:
            self._nu = None
        else:
            v = np.broadcast_to(np.asarray(nu, float), (3,)).copy()
            if not np.all(np.isfinite(v)) or np.any(v <= 2):
                raise GyroInputError(
                    f"nu (Student-t degrees of freedom) must be finite and > 2 per axis, got {v.tolist()}"
                )
            self._nu = v

    def _take(self, m):
        if m == 0:
            return np.zeros((0, 3))
        if self._nu is None:
            z = self.rng.standard_normal((m, 3))
        else:
            z = self.rng.standard_t(np.broadcast_to(self._nu, (m, 3))) * np.sqrt((self._nu - 2.0) / self._nu)[None, :]
        x = z * self._scale[None, :]
        if self._ba is None:
            return x
        b, a = self._ba
        if self._zi is None:
            self._zi = signal.lfilter_zi(b, a)[:, None] * x[:1]
        y, self._zi = signal.lfilter(b, a, x, axis=0, zi=self._zi)
        return y


class AngleWhiteNoise(_Blocks):
    """White angle noise (``angle_white``; IEEE 952's "quantization noise" Q): an angle sequence
    θ_k of σ = Q per sample and axis seen as the rate (θ_{k+1} − θ_k)·rate_hz, so that
    σ²_Allan(τ) = 3Q²/τ² (IEEE 952 C.1). Block generator (the last angle carried)."""

    def __init__(self, rng, *, rate_hz: float, q_rad) -> None:
        super().__init__(rng, rate_hz)
        self._q = _per_axis(q_rad, "q_rad")
        self._last = None

    def _take(self, m):
        if m == 0:
            return np.zeros((0, 3))
        if self._last is None:
            self._last = self.rng.standard_normal((1, 3)) * self._q[None, :]
        th = self.rng.standard_normal((m, 3)) * self._q[None, :]
        out = np.diff(np.concatenate([self._last, th]), axis=0) * self.rate_hz
        self._last = th[-1:]
        return out


def noise_term_generator(name: str, pd, rng: np.random.Generator, *, rate_hz: float) -> _Blocks:
    """The block generator of a registered noise term outside the catalogue
    (:data:`gyrocore.effects.registry.NOISE_TERMS`) from its parameters ``pd``."""
    if name == "arw_lowpass":
        return LowpassWhiteNoise(
            rng, rate_hz=rate_hz, n_rad_per_sqrt_s=pd["n_rad_per_sqrt_s"], bandwidth_hz=float(pd["bandwidth_hz"])
        )
    if name == "arw_student":
        return LowpassWhiteNoise(
            rng,
            rate_hz=rate_hz,
            n_rad_per_sqrt_s=pd["n_rad_per_sqrt_s"],
            bandwidth_hz=float(pd.get("bandwidth_hz", 0.0)),
            nu=pd["nu"],
        )
    if name == "angle_white":
        return AngleWhiteNoise(rng, rate_hz=rate_hz, q_rad=pd["q_rad"])
    raise GyroInputError(f"no noise generator for '{name}'")


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
        raise GyroInputError(
            f"shaped vibration: f_hz must be an increasing grid (n,) and psd (3, n); got {f.shape}, {S.shape}"
        )
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
        self._push(first[self.L - 1 :])

    def _block(self) -> np.ndarray:
        w = self._rng.standard_normal((self.B, 3))
        y = np.fft.irfft(np.fft.rfft(w, self._nfft, axis=0) * self._H, self._nfft, axis=0)[: self.B + self.L - 1]
        y[: self.L - 1] += self._tail
        self._tail = y[self.B :].copy()
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
        buf = (
            np.concatenate(self._chunks, axis=0)
            if len(self._chunks) > 1
            else (self._chunks[0] if self._chunks else np.zeros((0, 3)))
        )
        out, rest = buf[:n].copy(), buf[n:]
        self._chunks = [rest] if rest.shape[0] else []
        self._have = rest.shape[0]
        return out

    #: the block-generator name of :meth:`next` (sim.gyro.GyroNoise calls ``take`` on every term)
    take = next
