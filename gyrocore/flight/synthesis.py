"""The simulator side of a vibration spec: a gyro disturbance with the spec's spectrum, and how well a
simulated flight matches it.

A spec (:func:`gyrocore.flight.vibration.write_spec`) holds a flight's raw-domain gyro PSD per
throttle band. :func:`shaped_params` turns one band into the registry effect ``vibration``'s
parameters (``sim.noise.ShapedNoise`` generates it), :func:`synthesize` / :func:`add_vibration`
make a disturbance with that PSD, :func:`fidelity` compares a simulated flight's vibration
(:func:`gyrocore.flight.vibration.analyse`) with the spec band.
"""

from __future__ import annotations

import json
import math
from typing import Sequence

import numpy as np
from scipy import stats

from gyrocore.data.recording import Recording
from gyrocore.errors import GyroInputError
from gyrocore.flight.spectra import AXES, dof
from gyrocore.flight.vibration import HIGHPASS_HZ, VibrationResult

__all__ = ["spec_band", "shaped_params", "synthesize", "add_vibration", "fidelity"]


def spec_band(spec: dict, band: int | str = "middle") -> dict:
    """One band of a vibration spec: an index, or "middle" (the band with the median command)."""
    bands = spec.get("bands") or []
    if not bands:
        raise GyroInputError("vibration spec has no bands")
    if band == "middle":
        return bands[len(bands) // 2]
    try:
        return bands[int(band)]
    except (ValueError, IndexError):
        raise GyroInputError(f"vibration band {band!r}: the spec has bands 0..{len(bands) - 1} (or 'middle')") from None


def shaped_params(
    spec: dict,
    *,
    band: int | str = "middle",
    fmin_hz: float = HIGHPASS_HZ,
    exclude_hz: Sequence[tuple[float, float]] = (),
    subtract_lines: Sequence[tuple[float, dict]] = (),
) -> dict:
    """The shaped part of the registry effect ``vibration`` from one band of a spec.

    Returns ``{"f_hz": (n,), "psd_rad2_s2_hz": (3, n)}`` (the effect's schema, SI): the spec
    band's raw-domain gyro PSD per axis on the spec's grid, set to 0 below ``fmin_hz`` (the
    flight's own motion is not vibration), at and above the spec's reliable limit, in notch
    holes (no value) and inside the ``exclude_hz`` intervals (a line the simulator's physics
    already carries). The grid is cut to [first bin ≥ fmin − one bin, reliable limit + one bin]
    so the zeros at its ends are kept (linear interpolation then falls to 0 within one bin).
    ``subtract_lines``: ``(f_hz, {axis: power (rad/s)²})`` of lines the simulator's physics
    carries: within ± 3 bins of f_hz (a Hann window's main lobe and first side lobes hold > 99.9 %
    of a tone's power) the PSD's excess over the local floor (median of the bins 10..30 away) is
    removed up to the line's power, so the broadband under the line and any power the line
    detector did not attribute to the line (e.g. the line smeared by the throttle moving within
    the band) stay.
    ``sim.noise.ShapedNoise`` generates it; ``simulate --vibration SPEC`` and a preset's
    ``[vibration] spec = ...`` put it into ``SyntheticGyro`` as this effect's parameters.
    """
    b = spec_band(spec, band)
    f_spec = np.asarray(spec["f_hz"], float)
    lim = min(float(spec.get("reconstructed_reliable_below_hz") or f_spec[-1]), f_spec[-1])
    P = np.zeros((3, f_spec.size))
    for j, a in enumerate(AXES):
        s = np.array([np.nan if v is None else v for v in b["psd_rad2_s2_hz"][a]], float)
        S = np.nan_to_num(s, nan=0.0)
        S[(f_spec < fmin_hz) | (f_spec >= lim) | np.isnan(s)] = 0.0
        for lo, hi in exclude_hz:
            S[(f_spec >= lo) & (f_spec <= hi)] = 0.0
        dfs = float(f_spec[1] - f_spec[0])
        for f0, pw in subtract_lines:
            p_line = float(pw.get(a, 0.0)) if isinstance(pw, dict) else float(pw[j])
            if not p_line > 0:
                continue
            k = int(round((float(f0) - f_spec[0]) / dfs))
            side = np.r_[max(k - 30, 0) : max(k - 10, 0), min(k + 11, f_spec.size) : min(k + 31, f_spec.size)]
            floor = float(np.median(S[side])) if side.size else 0.0
            lo_k, hi_k = max(k - 3, 0), min(k + 4, f_spec.size)
            excess = np.maximum(S[lo_k:hi_k] - floor, 0.0)
            tot = float(excess.sum()) * dfs
            if tot > 0:
                S[lo_k:hi_k] -= excess * min(1.0, p_line / tot)
        P[j] = np.maximum(S, 0.0)
    df = float(f_spec[1] - f_spec[0])
    keep = (f_spec >= fmin_hz - 1.01 * df) & (f_spec <= lim + 1.01 * df)
    return {"f_hz": f_spec[keep].copy(), "psd_rad2_s2_hz": P[:, keep].copy()}


def synthesize(
    spec: dict,
    *,
    n: int,
    rate_hz: float,
    seed: int,
    band: int | str = "middle",
    fmin_hz: float = HIGHPASS_HZ,
    exclude_hz: Sequence[tuple[float, float]] = (),
) -> np.ndarray:
    """A gyro vibration disturbance (n, 3), rad/s, whose PSD is the spec band's raw-domain PSD.

    Random-phase synthesis: for each rfft bin k of length n at ``rate_hz``,
    X_k = √(S(f_k)·fs·n/2)·(g₁ + i g₂)/√2 with g ~ N(0, 1), so that the one-sided periodogram
    2|X_k|²/(fs·n) has expectation S(f_k); x = irfft(X). S is the spec's PSD interpolated
    linearly in f; zero below ``fmin_hz`` (the flight's own motion is not vibration), above
    the spec's reliable limit and its Nyquist, and where the spec has no value (notch holes).
    Gaussian: the lines come out as narrow-band noise of the measured power, not as
    phase-coherent sinusoids. ``seed``: ``np.random.default_rng(seed)``. ``exclude_hz``: (lo, hi)
    intervals, Hz, where S is set to 0 (a line the simulator's physics already carries).
    """
    b = spec_band(spec, band)
    f_spec = np.asarray(spec["f_hz"], float)
    lim = min(float(spec.get("reconstructed_reliable_below_hz") or f_spec[-1]), f_spec[-1])
    rng = np.random.default_rng(seed)
    f = np.fft.rfftfreq(n, d=1.0 / rate_hz)
    out = np.empty((n, 3))
    for j, a in enumerate(AXES):
        s = np.array([np.nan if v is None else v for v in b["psd_rad2_s2_hz"][a]], float)
        S = np.interp(f, f_spec, np.nan_to_num(s, nan=0.0), left=0.0, right=0.0)
        S[(f < fmin_hz) | (f >= lim)] = 0.0
        S[np.interp(f, f_spec, np.isnan(s).astype(float)) > 0] = 0.0
        for lo, hi in exclude_hz:
            S[(f >= lo) & (f <= hi)] = 0.0
        amp = np.sqrt(S * rate_hz * n / 2.0)
        X = amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) / math.sqrt(2.0)
        X[0] = 0.0
        if n % 2 == 0:
            X[-1] = 0.0
        out[:, j] = np.fft.irfft(X, n)
    return out


def add_vibration(
    rec: Recording, spec: dict, *, seed: int, band: int | str = "middle", exclude_hz: Sequence[tuple[float, float]] = ()
) -> Recording:
    """``rec`` with :func:`synthesize`'s disturbance added to its gyro (open loop: the truth and
    any controller that flew the recording did not see it); metadata says so. ``exclude_hz`` as
    :func:`synthesize`."""
    d = synthesize(spec, n=rec.n, rate_hz=rec.rate_hz, seed=seed, band=band, exclude_hz=exclude_hz)
    b = spec_band(spec, band)
    return rec.with_gyro(
        rec.gyro_rad_s + d,
        vibration_spec=str(spec.get("source", "")),
        vibration_band=json.dumps({"throttle": b.get("throttle"), "median": b.get("median")}),
        vibration_injection="shaped Gaussian disturbance added to the measured gyro (open loop), seed "
        f"{seed}; PSD of the spec band above {HIGHPASS_HZ:g} Hz"
        + (f", without {', '.join(f'{lo:g}-{hi:g} Hz' for lo, hi in exclude_hz)}" if exclude_hz else ""),
    )


def fidelity(sim: VibrationResult, spec: dict, *, band: int | str = "middle", fmin_hz: float = HIGHPASS_HZ) -> dict:
    """In-band fraction: bins (fmin .. min(Nyquists, reliable limit)) where the simulated gyro's
    PSD is statistically indistinguishable from the real flight's band PSD.

    Under equal spectra the ratio of two averaged periodograms is F(ν_sim, ν_real)-distributed
    (ν from each one's window count, :func:`dof`); a bin is in band when the ratio lies in the
    central 95 % of that F distribution, so a perfect match gives 0.95 on average.
    Also returns the median ratio (sim/real) and the RMS above fmin of both.
    """
    b = spec_band(spec, band)
    f_r = np.asarray(spec["f_hz"], float)
    lim = min(float(spec.get("reconstructed_reliable_below_hz") or f_r[-1]), f_r[-1], sim.f_hz[-1])
    nu_r = dof(int(b["n_windows"]))
    nu_s = dof(int(sim.n_windows))
    lo_q, hi_q = stats.f.ppf([0.025, 0.975], nu_s, nu_r)
    out = {}
    fs = sim.f_hz
    sel = (fs >= fmin_hz) & (fs < lim)
    for j, a in enumerate(AXES):
        real = np.array([np.nan if v is None else v for v in b["psd_rad2_s2_hz"][a]], float)
        R = np.interp(fs[sel], f_r, real)
        S = sim.mean_psd[sel, j]
        ok = np.isfinite(R) & np.isfinite(S) & (R > 0)
        ratio = S[ok] / R[ok]
        dfr = fs[1] - fs[0]
        out[a] = {
            "in_band_fraction": float(np.mean((ratio >= lo_q) & (ratio <= hi_q))) if ok.any() else float("nan"),
            "median_ratio_sim_to_real": float(np.median(ratio)) if ok.any() else float("nan"),
            "rms_sim_rad_s": float(np.sqrt(np.nansum(S) * dfr)),
            "rms_real_rad_s": float(np.sqrt(np.nansum(R) * dfr)),
            "band_hz": [fmin_hz, float(lim)],
        }
    return out
