"""The EDF of the overlapping Allan variance (gyrocore.noise.avar.power_law_edf) against closed forms."""

import numpy as np
import pytest

from gyrocore.noise import avar as AV

N_SAMPLES = 72_000


def test_power_law_edf_white_rate_first_octave_exact():
    # white rate noise y, m = 1: σ̂² = mean(d²)/2 over the M = n − 1 first differences d_k = y_{k+1} − y_k,
    # Var d² = 8σ⁴, Cov(d_k², d_{k+1}²) = 2·Cov(d_k, d_{k+1})² = 2σ⁴ (lag-one covariance −σ²), so
    # Var Σd² = 12σ⁴M, E Σd² = 2σ²M and edf = 2E²/Var = 2M/3 — exact for Gaussian noise.
    # The spectral integral is on a 64-per-e-fold grid: 0.1 % (measured 1e-5) is its quadrature error.
    n_phase = N_SAMPLES + 1
    assert AV.power_law_edf(0, 1, n_phase) == pytest.approx(2.0 * (N_SAMPLES - 1) / 3.0, rel=1e-3)


def test_power_law_edf_random_walk_rate_first_octave_exact():
    # random-walk rate y_k = Σ w: at m = 1 the first differences d_k = w_{k+1} are independent,
    # so σ̂²(1) is a mean of M = n − 1 independent squares: edf = M exactly
    n_phase = N_SAMPLES + 1
    assert AV.power_law_edf(-2, 1, n_phase) == pytest.approx(N_SAMPLES - 1, rel=1e-3)


@pytest.mark.parametrize("m", [2, 4, 8, 16, 32])
def test_power_law_edf_white_rate_matches_sp1065(m):
    # SP 1065 eq. 47 (white FM, overlapping): [3(N−1)/(2m) − 2(N−2)/N]·4m²/(4m²+5) with N phase
    # points reproduces the exact large-sample value at these m (2M/3 at m = 1 by the derivation
    # above); the 0.5 % is the size of its −2(N−2)/N finite-record term relative to the first
    n = N_SAMPLES
    sp1065 = (3 * (n - 1) / (2 * m) - 2 * (n - 2) / n) * 4 * m * m / (4 * m * m + 5)
    assert AV.power_law_edf(0, m, n + 1) == pytest.approx(sp1065, rel=5e-3)


def test_power_law_edf_last_octaves_are_greenhalls():
    # where the record is short against the filter the finite-sample EDF (Greenhall) is used
    import allantools

    m = 8192
    e = allantools.edf_greenhall(alpha=0, d=2, m=m, N=N_SAMPLES + 1, overlapping=True, modified=False)
    assert AV.power_law_edf(0, m, N_SAMPLES + 1) == pytest.approx(float(e), rel=1e-12)


def test_power_law_edf_monte_carlo_first_octaves():
    # Monte Carlo of white rate noise, n = 4 000 samples, 3 000 records (seeded): the empirical
    # EDF 2E²/Var of σ̂²(m) has a relative SE of √(2/(R−1)) ≈ 2.6 % (the sample variance of R
    # near-normal values); 4 SE = 10 % — tight enough to reject allantools' 17 % excess at m = 1
    # (here 1.17× too) and its 12 % deficit at m = 4
    rng = np.random.default_rng(np.random.SeedSequence(20261128))
    n, reps = 4_000, 3_000
    y = rng.standard_normal((reps, n))
    ph = np.concatenate([np.zeros((reps, 1)), np.cumsum(y, axis=1)], axis=1)
    for m in (1, 4):
        d = ph[:, 2 * m :] - 2 * ph[:, m:-m] + ph[:, : -2 * m]
        s2 = np.mean(d * d, axis=1) / (2 * m * m)
        emp = 2 * s2.mean() ** 2 / s2.var(ddof=1)
        assert emp == pytest.approx(AV.power_law_edf(0, m, n + 1), rel=4 * np.sqrt(2 / (reps - 1)))
