"""The stochastic terms reproduce the IEEE 952 Allan slopes and levels.

Tolerance: the overlapping Allan deviation at averaging factor m is a random variable;
edf·σ̂²/σ² ~ χ²(edf) with the equivalent degrees of freedom of Greenhall & Riley
(allantools.edf_greenhall, NIST SP1065 §5.2). We check that the theoretical IEEE 952 value
lies inside the two-sided 99.9 % chi-square interval around each estimate
(allantools.confidence_interval). With at most 5 τ points per axis and 3 axes per term
the family-wise false-alarm probability is < 1.5 %, and the seeds are fixed, so the test is
deterministic; a wrong level (e.g. a factor √2 or the wrong B↔floor constant, a 41 % or
50 % error) falls far outside intervals that are a few % wide.
"""

from __future__ import annotations

import allantools
import numpy as np
import pytest

from gyrocore.errors import GyroInputError
from sim import noise

CI = 0.999


def _check_allan(x: np.ndarray, rate_hz: float, ms, theory_avar, alpha: int) -> None:
    """Every axis, every m: IEEE 952 theory inside the chi-square CI of the OADEV."""
    n = x.shape[0]
    taus = np.asarray(ms, float) / rate_hz
    for i in range(3):
        tau_out, adev, _, _ = allantools.oadev(x[:, i], rate=rate_hz, data_type="freq", taus=taus)
        assert np.allclose(tau_out, taus)
        for m, tau, dev in zip(ms, tau_out, adev):
            edf = allantools.edf_greenhall(alpha=alpha, d=2, m=int(m), N=n, overlapping=True)
            lo, hi = allantools.confidence_interval(dev, edf, ci=CI)
            th = float(np.sqrt(theory_avar(tau, i)))
            assert lo <= th <= hi, f"axis {i} tau {tau}: theory {th:.4g} not in [{lo:.4g}, {hi:.4g}]"


def test_white_rate_noise_arw_slope_and_level():
    N = np.array([1e-3, 2e-3, 5e-4])  # rad/√s
    rate = 200.0
    x = noise.white_rate_noise(np.random.default_rng(11), 2**17, rate_hz=rate, n_rad_per_sqrt_s=N)
    # per-sample σ = N·√rate (DESIGN.md); sample std has relative s.e. 1/√(2n) = 0.2 %,
    # so 5 s.e. = 1 %.
    assert np.allclose(x.std(axis=0), N * np.sqrt(rate), rtol=5 / np.sqrt(2 * x.shape[0]))
    # IEEE 952 C.1: σ²(τ) = N²/τ (white FM, alpha = 0)
    _check_allan(x, rate, [1, 10, 100, 1000, 5000], lambda tau, i: N[i] ** 2 / tau, alpha=0)


def test_flicker_noise_gives_flat_floor_at_ieee952_level():
    B = np.array([1e-4, 3e-4, 5e-5])  # rad/s
    rate = 100.0
    x = noise.flicker_noise(np.random.default_rng(12), 2**17, rate_hz=rate, b_rad_s=B)
    # IEEE 952 C.2: σ²(τ) = (2 ln2/π)·B², flat (flicker FM, alpha = -1). The pole–zero
    # cascade's exact stationary ADEV is within ±0.1 % of it for m >= 8 (test below), far
    # inside the chi-square intervals; smaller m are not claimed.
    floor = 2 * np.log(2) / np.pi * B**2
    _check_allan(x, rate, [16, 100, 1000, 4000], lambda tau, i: floor[i], alpha=-1)
    assert noise.ALLAN_FLICKER_FACTOR == pytest.approx(np.sqrt(2 * np.log(2) / np.pi))


def test_flicker_level_does_not_depend_on_rate():
    B = 2e-4
    for rate, seed in ((50.0, 1), (1000.0, 2)):
        x = noise.flicker_noise(np.random.default_rng(seed), 2**16, rate_hz=rate, b_rad_s=B)
        _check_allan(x, rate, [32, 512], lambda tau, i: 2 * np.log(2) / np.pi * B**2, alpha=-1)


def test_rate_random_walk_slope_and_level():
    K = np.array([1e-4, 2e-4, 5e-5])  # rad/s/√s
    rate = 50.0
    x = noise.rate_random_walk(np.random.default_rng(13), 2**16, rate_hz=rate, k_rad_s_per_sqrt_s=K)
    # IEEE 952 C.4: σ²(τ) = K²τ/3 (random-walk FM, alpha = -2); the discrete-sum correction
    # is O(1/m²) (< 0.5 % for m >= 10), far inside the CI.
    _check_allan(x, rate, [10, 100, 1000, 5000], lambda tau, i: K[i] ** 2 * tau / 3, alpha=-2)


@pytest.mark.parametrize("rate_hz", [10.0, 1000.0])
def test_gauss_markov_exact_discretisation(rate_hz):
    sigma = np.array([1e-3, 2e-3, 5e-4])
    tau_c = np.array([0.1, 1.0, 0.5])
    n = 2**17
    x = noise.gauss_markov(np.random.default_rng(14), n, rate_hz=rate_hz, sigma_rad_s=sigma, tau_c_s=tau_c)
    phi = np.exp(-1.0 / (rate_hz * tau_c))
    for i in range(3):
        xi = x[:, i]
        # Stationary variance σ²: for an AR(1) sequence the sample variance has
        # var(s²) ≈ (2σ⁴/n)·(1+φ²)/(1−φ²) (Bartlett); 5 standard errors.
        se_var = np.sqrt(2 * sigma[i] ** 4 / n * (1 + phi[i] ** 2) / (1 - phi[i] ** 2))
        assert abs(xi.var() - sigma[i] ** 2) < 5 * se_var
        # Lag-1 correlation = exp(−dt/τc) exactly, at any rate; the estimate's s.e. is
        # sqrt((1−φ²)/n) (Box & Jenkins), 5 s.e.
        r1 = np.dot(xi[1:] - xi.mean(), xi[:-1] - xi.mean()) / np.dot(xi - xi.mean(), xi - xi.mean())
        assert abs(r1 - phi[i]) < 5 * np.sqrt((1 - phi[i] ** 2) / n) + 1.0 / n


def test_same_generator_state_same_noise_and_bad_input():
    a = noise.white_rate_noise(np.random.default_rng(5), 100, rate_hz=100.0, n_rad_per_sqrt_s=1e-3)
    b = noise.white_rate_noise(np.random.default_rng(5), 100, rate_hz=100.0, n_rad_per_sqrt_s=1e-3)
    assert np.array_equal(a, b)
    with pytest.raises(GyroInputError):
        noise.white_rate_noise(np.random.default_rng(5), 10, rate_hz=0.0, n_rad_per_sqrt_s=1e-3)
    with pytest.raises(GyroInputError):
        noise.gauss_markov(np.random.default_rng(5), 10, rate_hz=10.0, sigma_rad_s=1.0, tau_c_s=0.0)
    with pytest.raises(GyroInputError):
        noise.flicker_noise(np.random.default_rng(5), 10, rate_hz=10.0, b_rad_s=-1.0)


# ---------------------------------------------------------------- block generation (bounded memory)
def _blocks(make, sizes, n):
    g = make()
    out, k = [], 0
    while sum(len(o) for o in out) < n:
        m = min(sizes[k % len(sizes)], n - sum(len(o) for o in out))
        out.append(g.take(m))
        k += 1
    return np.concatenate(out)


GENERATORS = {
    "arw": lambda: noise.WhiteRateBlocks(
        np.random.default_rng(21), rate_hz=1000.0, n_rad_per_sqrt_s=[1e-3, 2e-3, 5e-4]
    ),
    "flicker": lambda: noise.FlickerBlocks(np.random.default_rng(22), rate_hz=1000.0, b_rad_s=[1e-4, 3e-4, 5e-5]),
    "rrw": lambda: noise.RateRandomWalkBlocks(
        np.random.default_rng(23), rate_hz=1000.0, k_rad_s_per_sqrt_s=[1e-4, 2e-4, 5e-5]
    ),
    "gm": lambda: noise.GaussMarkovBlocks(
        np.random.default_rng(24), rate_hz=1000.0, sigma_rad_s=[1e-3, 2e-3, 5e-4], tau_c_s=[0.1, 1.0, 30.0]
    ),
    # registered noise terms outside the catalogue (gyrocore.effects.registry.NOISE_TERMS)
    "arw_lowpass": lambda: noise.LowpassWhiteNoise(
        np.random.default_rng(25), rate_hz=1000.0, n_rad_per_sqrt_s=[1e-3, 2e-3, 5e-4], bandwidth_hz=90.0
    ),
    "arw_student": lambda: noise.LowpassWhiteNoise(
        np.random.default_rng(26),
        rate_hz=1000.0,
        n_rad_per_sqrt_s=[1e-3, 2e-3, 5e-4],
        bandwidth_hz=90.0,
        nu=[5.0, 6.0, 30.0],
    ),
    "angle_white": lambda: noise.AngleWhiteNoise(np.random.default_rng(27), rate_hz=1000.0, q_rad=[1e-5, 2e-5, 3e-6]),
    # the shaped vibration (fixed internal FFT blocks, served in the caller's blocks)
    "shaped": lambda: noise.ShapedNoise(
        np.random.default_rng(28),
        noise.shaped_taps(
            50.0 + np.arange(60.0), np.vstack([np.full(60, 1e-4), np.full(60, 2e-4), np.zeros(60)]), rate_hz=1000.0
        ),
    ),
}


@pytest.mark.parametrize("term", list(GENERATORS))
@pytest.mark.parametrize("sizes", [(997,), (4096,), (1, 3, 1000)])
def test_blocks_bit_identical_across_block_sizes(term, sizes):
    n = 20_011
    whole = GENERATORS[term]().take(n)
    assert np.array_equal(_blocks(GENERATORS[term], sizes, n), whole)


def test_functions_are_one_block():
    """The plain functions are the generators in one block; ARW, RRW and Gauss–Markov draw
    exactly what the whole-record functions drew before blocks (only the flicker changed)."""
    x = noise.gauss_markov(
        np.random.default_rng(24), 5000, rate_hz=1000.0, sigma_rad_s=[1e-3, 2e-3, 5e-4], tau_c_s=[0.1, 1.0, 30.0]
    )
    assert np.array_equal(x, GENERATORS["gm"]().take(5000))
    # the pre-block Gauss–Markov: lfilter over the whole record with a stationary first sample
    w = np.random.default_rng(24).standard_normal((5000, 3))
    sig, tau = np.array([1e-3, 2e-3, 5e-4]), np.array([0.1, 1.0, 30.0])
    for i in range(3):
        phi = np.exp(-1.0 / (1000.0 * tau[i]))
        u = w[:, i] * (sig[i] * np.sqrt(1 - phi * phi))
        u[0] = w[0, i] * sig[i]
        from scipy.signal import lfilter

        assert np.array_equal(x[:, i], lfilter([1.0], [1.0, -phi], u))
    k = noise.rate_random_walk(np.random.default_rng(23), 5000, rate_hz=1000.0, k_rad_s_per_sqrt_s=[1e-4, 2e-4, 5e-5])
    inc = np.random.default_rng(23).standard_normal((5000, 3)) * (np.array([1e-4, 2e-4, 5e-5]) * np.sqrt(1e-3))
    assert np.array_equal(k, np.cumsum(inc, axis=0))


@pytest.mark.parametrize("rate_hz", [100.0, 1000.0, 8000.0])
def test_flicker_design_band(rate_hz):
    """The band the generator claims (sim/noise.py docstring), from the digital filter's exact
    response — a design check, no randomness: one-sided PSD within ±1 % of B²/(πf) from
    FLICKER_BAND_LO_HZ to rate/20, and the stationary Allan deviation (exact integral over
    the PSD, σ²(m) = 2∫S₁(f)·sin⁴(πfmτ₀)/(m·sin(πfτ₀))² df) within ±0.3 % of B·√(2 ln2/π)
    at m = 8 and ±0.1 % for m >= 16 up to τ = 1e5 s."""
    from scipy import signal

    sos = noise.flicker_sos(rate_hz)
    f = np.logspace(np.log10(noise.FLICKER_BAND_LO_HZ), np.log10(rate_hz / 20), 3000)
    _, h = signal.sosfreqz(sos, worN=f, fs=rate_hz)
    s1 = (2.0 / rate_hz) * np.abs(h) ** 2  # B = 1, unit-variance input per sample
    rel = s1 * np.pi * f
    assert np.all(np.abs(rel - 1) < 0.01), (rel.min(), rel.max())
    fg = np.logspace(-10, np.log10(rate_hz / 2), 400_000)
    _, hg = signal.sosfreqz(sos, worN=fg, fs=rate_hz)
    sg = (2.0 / rate_hz) * np.abs(hg) ** 2
    ms = [8, 16, 100, 10_000] + [int(t * rate_hz) for t in (100.0, 1e4, 1e5)]
    for m in ms:
        x = np.pi * fg * m / rate_hz
        avar = np.trapezoid(2 * sg * np.sin(x) ** 4 / (m * np.sin(np.pi * fg / rate_hz)) ** 2, fg)
        tol = 3e-3 if m < 16 else 1e-3
        assert abs(np.sqrt(avar) / noise.ALLAN_FLICKER_FACTOR - 1) < tol, (
            m,
            np.sqrt(avar) / noise.ALLAN_FLICKER_FACTOR,
        )


def test_flicker_floor_over_long_tau_in_blocks():
    """Generated in blocks of 4096 at 10 Hz for 2^18 samples (7.3 h): the flat floor holds from
    m = 8 to τ = 1638 s (m = 16384), IEEE 952 inside each 99.9 % chi-square interval (Greenhall
    EDF for flicker FM, alpha = -1; 4 τ × 3 axes, family-wise false alarm < 1.2 %, fixed seed)."""
    B = np.array([2e-5, 1e-4, 5e-4])
    rate = 10.0
    n = 2**18
    x = _blocks(lambda: noise.FlickerBlocks(np.random.default_rng(31), rate_hz=rate, b_rad_s=B), (4096,), n)
    floor = 2 * np.log(2) / np.pi * B**2
    _check_allan(x, rate, [8, 128, 2048, 16384], lambda tau, i: floor[i], alpha=-1)
