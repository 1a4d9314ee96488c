"""Still-gyro noise generators written independently of ``sim/`` (a second implementation to check the first).

The noise identification (``gyrocore/noise/gmwm.py``) was studied on the simulator's own generators
(``sim/noise.py``).  These are the generators *other people* use, re-written here from their
published description (no code copied), so that the estimator is held against noise it was not
built beside.  Every function returns one axis of angular rate in rad/s, shape (n,), and takes an
explicit ``numpy.random.Generator``.

Conventions (IEEE Std 952-1997, Annex C; two-sided rate PSD S(f), Allan variance
σ²(τ) = 4∫₀^∞ S(f) sin⁴(πfτ)/(πfτ)² df):

- white rate noise N [rad/√s]: S = N², per-sample σ = N·√fs, σ²(τ) = N²/τ;
- rate random walk K [rad/s/√s]: S = K²/(2πf)², σ²(τ) = K²τ/3;
- flicker ("bias instability") B [rad/s]: S = B²/(2πf), σ²(τ) → (2 ln2/π)B², so the flat
  minimum of the ADEV is 0.664·B;
- first-order Gauss–Markov σ [rad/s], τc [s]: stationary variance σ², ADEV maximum 0.6178·σ at
  τ ≈ 1.89·τc (it is *not* flicker: it rises as √τ below τc and falls as 1/√τ above).
"""

from __future__ import annotations

import contextlib
import math

import numpy as np

#: B from the flat ADEV minimum: σ_min = √(2 ln2/π)·B = 0.6643·B (IEEE 952, C.4).
FLICKER_FLOOR = math.sqrt(2.0 * math.log(2.0) / math.pi)


def white(n: int, fs_hz: float, N: float, rng: np.random.Generator) -> np.ndarray:
    """White rate noise of density N [rad/√s]: per-sample σ = N·√fs (the ``σ_n/√Δt`` of the
    Kalibr wiki "IMU Noise Model", OpenVINS' simulator, gnss-ins-sim's ``arw/sqrt(dt)``)."""
    return N * math.sqrt(fs_hz) * rng.standard_normal(n)


def random_walk(n: int, fs_hz: float, K: float, rng: np.random.Generator) -> np.ndarray:
    """Rate random walk K [rad/s/√s] as the Kalibr wiki / OpenVINS discrete bias:
    b[k+1] = b[k] + K·√Δt·w[k], b[0] = 0 (a cumulative sum)."""
    return np.cumsum(K * math.sqrt(1.0 / fs_hz) * rng.standard_normal(n))


@contextlib.contextmanager
def _numpy_global_seed(rng: np.random.Generator):
    """allantools' generators draw from numpy's global RandomState: seed it from ``rng`` and
    restore it afterwards (the seed stays explicit and the caller's state is not disturbed)."""
    state = np.random.get_state()
    np.random.seed(int(rng.integers(0, 2**32 - 1)))
    try:
        yield
    finally:
        np.random.set_state(state)


def flicker_allantools(n: int, fs_hz: float, B: float, rng: np.random.Generator) -> np.ndarray:
    """Flicker rate noise by ``allantools.noise_kasdin.Noise`` (Kasdin & Walter 1992, the
    library's power-law generator), used on the rate series with b = −1 (a 1/f series).

    Its one-sided PSD is S₁(f) = 2·qd·(2π)^b·τ0^(b+1)·f^b (``phase_psd_from_qd``) = qd/(π f) for
    b = −1; IEEE 952's two-sided S = B²/(2πf) is the one-sided B²/(πf), so qd = B²."""
    from allantools.noise_kasdin import Noise

    with _numpy_global_seed(rng):
        g = Noise(nr=n, qd=B * B, b=-1)
        g.generateNoise()
        return np.asarray(g.time_series, dtype=float)[:n]


def flicker_voss_allantools(n: int, B_unused: float, rng: np.random.Generator, depth: int = 80) -> np.ndarray:
    """``allantools.noise.pink`` (Voss–McCartney, unnormalised) — kept to show what it is: its
    row index wraps at ``depth``, so with the default depth 80 only rows 0–6 are ever redrawn and
    the series is 1/f only up to ~2⁷ samples (white beyond); no B can be stated for it."""
    import allantools.noise as an

    with _numpy_global_seed(rng):
        return an.pink(n, depth=depth)


def flicker_fft(n: int, fs_hz: float, B: float, rng: np.random.Generator) -> np.ndarray:
    """Flicker rate noise by shaping a random spectrum (Timmer & König 1995, A&A 300:707; the
    ``time_series_from_psd`` approach of gnss-ins-sim's ``pathgen``): complex Gaussian DFT
    coefficients with E|X_k|² = n·fs·S₁(f_k)/2 for the one-sided target S₁(f) = B²/(π f), zero at
    DC and made real at Nyquist, inverse real FFT.  The series is periodic with period n (no
    padding, as these tools do), so power below 1/T is absent."""
    f = np.fft.rfftfreq(n, d=1.0 / fs_hz)
    s1 = np.zeros_like(f)
    s1[1:] = B * B / (math.pi * f[1:])
    amp = np.sqrt(n * fs_hz * s1 / 2.0)
    X = amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) / math.sqrt(2.0)
    if n % 2 == 0:  # Nyquist bin of a real series is real: same expected power
        X[-1] = amp[-1] * rng.standard_normal()
    return np.fft.irfft(X, n)


def gauss_markov_gnss_ins_sim(
    n: int, fs_hz: float, sigma: float, tau_c_s: float, rng: np.random.Generator
) -> np.ndarray:
    """First-order Gauss–Markov "bias drift/instability" as gnss-ins-sim's ``bias_drift``
    (Aceinna/gnss-ins-sim, ``gnss_ins_sim/pathgen/pathgen.py``): x[0] = 0,
    x[k] = a·x[k−1] + b·w[k−1] with a = 1 − 1/(fs·τc) and b = σ·√(1 − exp(−2/(fs·τc))) — σ is the
    stationary std that the tool calls the bias "drift"/"stability".  Started at 0, not in its
    stationary law (so are theirs)."""
    from scipy.signal import lfilter

    a = 1.0 - 1.0 / (fs_hz * tau_c_s)
    b = sigma * math.sqrt(1.0 - math.exp(-2.0 / (fs_hz * tau_c_s)))
    w = rng.standard_normal(n)
    x = lfilter([0.0, b], [1.0, -a], w)  # x[k] = a x[k-1] + b w[k-1], x[0] = 0
    return x


def gm_stationary_sigma(sigma: float, tau_c_s: float, fs_hz: float) -> float:
    """Stationary std of :func:`gauss_markov_gnss_ins_sim` (a ≠ exp(−Δt/τc)):
    b²/(1 − a²), slightly below σ (by ≈ Δt/(4τc))."""
    a = 1.0 - 1.0 / (fs_hz * tau_c_s)
    b = sigma * math.sqrt(1.0 - math.exp(-2.0 / (fs_hz * tau_c_s)))
    return b / math.sqrt(1.0 - a * a)


def quantize_lsb(omega_rad_s: np.ndarray, lsb_per_dps: float) -> np.ndarray:
    """Round to integer counts of a digital gyro (e.g. MPU-6050 ±250 °/s: 131 LSB/(°/s)); returns
    int64 counts.  Rounding adds white *rate* noise of variance LSB²/12 per sample when the noise
    spans several LSB (density LSB/√(12·fs)), not an angle-quantization Q term."""
    return np.rint(np.degrees(omega_rad_s) * lsb_per_dps).astype(np.int64)


def gm_avar(tau_s: np.ndarray, sigma: float, tau_c_s: float) -> np.ndarray:
    """Continuous-time Allan variance of a stationary first-order GM (IEEE 952 C.6 / Jerath et
    al.): σ²τc/τ²·(2τ/τc·... ) in the closed form (σ²τc²/τ²)(2τ/τc − 3 + 4e^{−τ/τc} − e^{−2τ/τc})."""
    x = np.asarray(tau_s, float) / tau_c_s
    return sigma**2 / x**2 * (2 * x - 3 + 4 * np.exp(-x) - np.exp(-2 * x))


def adev_floor_B(taus_s: np.ndarray, adev: np.ndarray) -> tuple[float, float]:
    """The textbook read-out of bias instability: B = min ADEV / 0.664, and the τ of that
    minimum (IEEE 952 C.4; what a user computes from an ADEV plot)."""
    i = int(np.nanargmin(adev))
    return float(adev[i] / FLICKER_FLOOR), float(taus_s[i])
