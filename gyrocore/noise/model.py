"""The gyro's noise model: one type for every estimator, filter and budget of the project.

:class:`NoiseModel` holds, per sensor axis, the IEEE Std 952 terms and one first-order
Gauss–Markov bias (DESIGN.md "Units and frames"; the catalogue's ``arw``, ``bias_instability``,
``rrw``, ``correlated`` and ``quantization``), with their 95 % intervals and "resolved" flags when
an estimator identified them (:func:`gyrocore.noise.allan.identify_noise` returns results that
carry one). The Allan variance of the model, σ²(τ) = 3Q²/τ² + N²/τ + (2 ln2/π)B² + K²τ/3 + R²τ²/2
+ the Gauss–Markov hump (its exact discrete form, :func:`gyrocore.noise.avar.term_avar`), its
spectrum, and the discrete-time bias process a Kalman filter propagates are methods of the model.

Users: the identification (:mod:`gyrocore.noise.allan`), the bias trackers
(:mod:`gyrocore.noise.kalman`), the attitude-error budget and the noise-model covariance of the
least squares (:mod:`gyrocore.calib.budget`, :func:`gyrocore.calib.lsq.noise_model_meat`), the
parameter file's ``noise_model`` (:mod:`gyrocore.calib.params`) and the protocol experiment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from gyrocore.errors import GyroInputError

from .avar import LINEAR, spectrum, term_avar

__all__ = ["NoiseModel", "TERMS", "IEEE_TERMS", "TERM_UNITS", "model_value", "to_datasheet_units"]

RAD2DEG = 180.0 / math.pi

#: The IEEE 952 terms (DESIGN.md JSON of ``allan``), in the order of the estimators' coefficients.
IEEE_TERMS = (
    "quantization_rad",
    "arw_rad_per_sqrt_s",
    "bias_instability_rad_s",
    "rrw_rad_per_s_sqrt_s",
    "rate_ramp_rad_s2",
)
#: Every term of the model: the IEEE terms and the Gauss–Markov pair (``correlated``).
TERMS = IEEE_TERMS + ("correlated_sigma_rad_s", "correlated_tau_c_s")
TERM_UNITS = {
    "correlated_sigma_rad_s": "rad/s",
    "correlated_tau_c_s": "s",
    "quantization_rad": "rad",
    "arw_rad_per_sqrt_s": "rad/s/sqrt(Hz) = rad/sqrt(s)",
    "bias_instability_rad_s": "rad/s",
    "rrw_rad_per_s_sqrt_s": "rad/s/sqrt(s) = rad/s^2/sqrt(Hz)",
    "rate_ramp_rad_s2": "rad/s^2",
}
_TAU = "correlated_tau_c_s"


def to_datasheet_units(name: str, value: float | None) -> tuple[float | None, str]:
    """Convert an IEEE 952 term from SI to the datasheet unit engineers use.

    N: deg/√h (×180/π×60); B: deg/h; K: deg/h/√h (×180/π×3600×60); R: deg/h²; Q: arcsec.
    """
    if value is None:
        return None, ""
    f = {
        "quantization_rad": (RAD2DEG * 3600.0, "arcsec"),
        "arw_rad_per_sqrt_s": (RAD2DEG * 60.0, "deg/sqrt(h)"),
        "bias_instability_rad_s": (RAD2DEG * 3600.0, "deg/h"),
        "rrw_rad_per_s_sqrt_s": (RAD2DEG * 3600.0 * 60.0, "deg/h/sqrt(h)"),
        "rate_ramp_rad_s2": (RAD2DEG * 3600.0**2, "deg/h^2"),
        "correlated_sigma_rad_s": (RAD2DEG * 3600.0, "deg/h"),
        "correlated_tau_c_s": (1.0, "s"),
    }[name]
    return value * f[0], f[1]


def model_value(
    name: str, reported: float | None, ambiguous: Mapping[str, str], estimate: Mapping[str, float]
) -> float:
    """The value a noise *model* takes for one identified term of one axis.

    The resolved value; for a term fitted but *ambiguous* (the GMWM stand-in check: e.g. flicker
    and a Gauss–Markov term fit equally well) its fitted estimate — the slow noise is there, only
    its name is uncertain, and dropping it made the budget's standard errors too small; else 0
    (τc: inf, no Gauss–Markov term)."""
    absent = math.inf if name == _TAU else 0.0
    if reported is not None:
        return float(reported)
    key = "correlated_sigma_rad_s" if name == _TAU else name
    v = estimate.get(name)
    if key in ambiguous and v is not None and np.isfinite(v) and v > 0:
        return float(v)
    return absent


@dataclass(frozen=True, eq=False)
class NoiseModel:
    """Stochastic noise of a gyro, per sensor axis (S frame); every value an array of shape (k,).

    Attributes
    ----------
    arw_rad_per_sqrt_s : ndarray (k,)
        White rate noise density N, rad/s/√Hz = rad/√s; per-sample σ = N·√rate.
    bias_instability_rad_s : ndarray (k,)
        Bias instability (flicker) B, rad/s (IEEE 952: Allan floor 0.664·B).
    rrw_rad_per_s_sqrt_s : ndarray (k,)
        Rate random walk K, rad/s/√s.
    correlated_sigma_rad_s, correlated_tau_c_s : ndarray (k,)
        First-order Gauss–Markov bias: σ, rad/s, and correlation time τc, s (σ = 0, τc = inf: none).
    rate_ramp_rad_s2 : ndarray (k,)
        Rate ramp R, rad/s².
    quantization_rad : ndarray (k,)
        Angle quantization Q (white angle noise), rad.
    quantization_lsb_rad_s : float
        Output LSB of the rate, rad/s (the catalogue's ``quantization`` effect; 0: none): adds
        white rate noise of variance LSB²/12 per sample, i.e. LSB²/(12·rate) to N².
    ci95 : dict of str -> ndarray (k, 2)
        95 % interval of each term an estimator identified ([0, upper bound] when unresolved).
    resolved : dict of str -> ndarray (k,) of bool
        Which identified terms the data resolved (an unresolved term is ``null`` in the JSON; its
        value here is 0, or its fitted estimate when it was fitted but not told from a stand-in).
    axes : tuple of str
        Axis names, default ``("x", "y", "z")``.
    source : str
        Where the numbers come from.
    """

    arw_rad_per_sqrt_s: np.ndarray
    bias_instability_rad_s: np.ndarray = 0.0
    rrw_rad_per_s_sqrt_s: np.ndarray = 0.0
    correlated_sigma_rad_s: np.ndarray = 0.0
    correlated_tau_c_s: np.ndarray = math.inf
    rate_ramp_rad_s2: np.ndarray = 0.0
    quantization_rad: np.ndarray = 0.0
    quantization_lsb_rad_s: float = 0.0
    ci95: Mapping[str, np.ndarray] = field(default_factory=dict)
    resolved: Mapping[str, np.ndarray] = field(default_factory=dict)
    axes: tuple[str, ...] = ("x", "y", "z")
    source: str = "given"

    def __post_init__(self) -> None:
        k = len(self.axes)
        for name in TERMS:
            v = np.asarray(getattr(self, name), float)
            if v.ndim > 1 or (v.ndim == 1 and v.size not in (1, k)):
                raise GyroInputError(f"{name}: one value or one per axis ({k}), got shape {v.shape}")
            v = np.broadcast_to(v, (k,)).copy()
            if np.any(np.isnan(v)) or np.any(v < 0) or (name != _TAU and not np.all(np.isfinite(v))):
                raise GyroInputError(f"{name} must be finite and >= 0")
            if name == _TAU and np.any(v <= 0):
                raise GyroInputError("correlated_tau_c_s must be > 0")
            v.setflags(write=False)
            object.__setattr__(self, name, v)
        if not (math.isfinite(self.quantization_lsb_rad_s) and self.quantization_lsb_rad_s >= 0):
            raise GyroInputError("quantization_lsb_rad_s must be finite and >= 0")
        object.__setattr__(
            self, "ci95", {n: np.broadcast_to(np.asarray(v, float), (k, 2)) for n, v in dict(self.ci95).items()}
        )
        object.__setattr__(
            self, "resolved", {n: np.broadcast_to(np.asarray(v, bool), (k,)) for n, v in dict(self.resolved).items()}
        )

    @classmethod
    def from_params(cls, params: Mapping[str, Mapping[str, np.ndarray]]) -> "NoiseModel":
        """From catalogue parameters (``arw``, ``bias_instability``, ``rrw``, ``correlated``,
        ``quantization``: the simulator's truth, a preset); absent terms are zero."""

        def v(eff, name, default=0.0):
            if eff not in params:
                return np.full(3, default)
            return np.broadcast_to(np.asarray(params[eff][name], float), (3,)).copy()

        lsb = float(np.asarray(params["quantization"]["lsb_rad_s"])) if "quantization" in params else 0.0
        return cls(
            arw_rad_per_sqrt_s=v("arw", "n_rad_per_sqrt_s"),
            bias_instability_rad_s=v("bias_instability", "b_rad_s"),
            rrw_rad_per_s_sqrt_s=v("rrw", "k_rad_s_per_sqrt_s"),
            correlated_sigma_rad_s=v("correlated", "sigma_rad_s"),
            correlated_tau_c_s=v("correlated", "tau_c_s", np.inf),
            quantization_lsb_rad_s=lsb,
            source="catalogue parameters",
        )

    @classmethod
    def identified(
        cls,
        axis: str,
        terms: Mapping[str, float | None],
        ci95: Mapping[str, tuple[float, float]],
        ambiguous: Mapping[str, str],
        estimate: Mapping[str, float],
        names: Sequence[str] | None = None,
    ) -> "NoiseModel":
        """The one-axis model of an estimator's identification: each term's model value
        (:func:`model_value`), the 95 % intervals and resolved flags of the ``names`` it identified
        (default: the terms with an interval, in :data:`TERMS` order)."""
        names = [k for k in TERMS if k in ci95] if names is None else list(names)
        return cls(
            **{k: model_value(k, terms.get(k), ambiguous, estimate) for k in TERMS},
            ci95={k: [ci95[k]] for k in names},
            resolved={k: [terms.get(k) is not None] for k in names},
            axes=(axis,),
            source="identified",
        )

    # ------------------------------------------------------------------ views
    def reported(self, name: str) -> list[float | None]:
        """Per axis: the value where the estimator resolved the term, else ``None`` (DESIGN.md JSON:
        a term the data cannot resolve is null, not a guess). A model given by hand (no
        ``resolved`` flags) reports every value."""
        v = getattr(self, name)
        if not self.resolved:
            return [float(x) for x in v]
        r = self.resolved.get(name)
        return [float(x) if (r is not None and r[j]) else None for j, x in enumerate(v)]

    def axis(self, a: str) -> "NoiseModel":
        """The model of one axis."""
        i = self.axes.index(a)
        return NoiseModel(
            **{n: getattr(self, n)[i : i + 1] for n in TERMS},
            quantization_lsb_rad_s=self.quantization_lsb_rad_s,
            ci95={n: v[i : i + 1] for n, v in self.ci95.items()},
            resolved={n: v[i : i + 1] for n, v in self.resolved.items()},
            axes=(a,),
            source=self.source,
        )

    @classmethod
    def stack(cls, models: Sequence["NoiseModel"], *, source: str | None = None) -> "NoiseModel":
        """One model of the axes of several (each axis once, in order)."""
        if not models:
            raise GyroInputError("no noise model to stack")
        axes = tuple(a for m in models for a in m.axes)
        names = [n for n in models[0].ci95 if all(n in m.ci95 for m in models)]
        rnames = [n for n in models[0].resolved if all(n in m.resolved for m in models)]
        return cls(
            **{n: np.concatenate([getattr(m, n) for m in models]) for n in TERMS},
            quantization_lsb_rad_s=max(m.quantization_lsb_rad_s for m in models),
            ci95={n: np.concatenate([m.ci95[n] for m in models]) for n in names},
            resolved={n: np.concatenate([m.resolved[n] for m in models]) for n in rnames},
            axes=axes,
            source=models[0].source if source is None else source,
        )

    def complete(self, axes: Sequence[str] = ("x", "y", "z")) -> "NoiseModel":
        """The model on ``axes``; an axis it lacks takes the mean of the others (τc: the mean of
        the present ones, inf when any is inf). Intervals and flags are dropped when an axis is filled."""
        axes = tuple(axes)
        if self.axes == axes:
            return self
        have = [a for a in axes if a in self.axes]
        if not have:
            raise GyroInputError("identified noise model has no axis")
        vals = {}
        for n in TERMS:
            v = getattr(self, n)
            fill = float(np.mean(v))
            vals[n] = np.array([v[self.axes.index(a)] if a in self.axes else fill for a in axes])
        return NoiseModel(**vals, quantization_lsb_rad_s=self.quantization_lsb_rad_s, axes=axes, source=self.source)

    def mean_terms(self) -> dict[str, float | None]:
        """Axis means of N, B, K and the Gauss–Markov pair (over the axes that have one; τc None
        when none does): one axis' terms, as :func:`gyrocore.noise.gmwm.expected_z` takes them."""
        sig = self.correlated_sigma_rad_s
        tau = self.correlated_tau_c_s
        has = (sig > 0) & np.isfinite(tau)
        return {
            "arw_rad_per_sqrt_s": float(np.mean(self.arw_rad_per_sqrt_s)),
            "bias_instability_rad_s": float(np.mean(self.bias_instability_rad_s)),
            "rrw_rad_per_s_sqrt_s": float(np.mean(self.rrw_rad_per_s_sqrt_s)),
            "correlated_sigma_rad_s": float(np.mean(sig[has])) if has.any() else 0.0,
            "correlated_tau_c_s": float(np.mean(tau[has])) if has.any() else None,
        }

    # ------------------------------------------------------------------ what it implies
    def white_var_rad2_s(self, rate_hz: float) -> np.ndarray:
        """White rate noise level N² + LSB²/(12·rate) per axis, rad²/s (the quantization of the
        output at ``rate_hz`` counted as white rate noise)."""
        return self.arw_rad_per_sqrt_s**2 + self.quantization_lsb_rad_s**2 / (12.0 * rate_hz)

    def _coef(self, i: int) -> np.ndarray:
        """Variance-scale coefficients (Q², N², B², K², R², σ²) of axis i (:data:`LINEAR` order)."""
        return np.array([float(getattr(self, n)[i]) ** 2 for n in LINEAR])

    def _tau(self, i: int) -> float | None:
        t = float(self.correlated_tau_c_s[i])
        return t if (math.isfinite(t) and self.correlated_sigma_rad_s[i] > 0) else None

    def avar(self, taus_s: np.ndarray, rate_hz: float) -> np.ndarray:
        """Allan variance of the model at averaging times ``taus_s`` (whole multiples of 1/rate),
        (rad/s)², shape (k, M): the exact discrete form of each term at ``rate_hz``
        (:func:`gyrocore.noise.avar.term_avar`; → the IEEE 952 asymptotes at long τ)."""
        m = np.rint(np.asarray(taus_s, float) * rate_hz).astype(np.int64)
        if np.any(m < 1):
            raise GyroInputError("Allan variance of the model: every tau must be at least one sample")
        return np.stack([term_avar(m, rate_hz, tau_c_s=self._tau(i)) @ self._coef(i) for i in range(len(self.axes))])

    def psd(self, f_hz: np.ndarray, rate_hz: float) -> np.ndarray:
        """Two-sided power spectral density of the sampled model at ``f_hz`` (0 < f ≤ rate/2),
        (rad/s)²/Hz, shape (k, F): N² (white), B²/(2π f) (flicker), K²/(2π f)² (random walk),
        (2π f)²Q² (white angle), the AR(1) Lorentzian — each in its discrete form at
        ``rate_hz`` (the spectrum behind :func:`gyrocore.noise.avar.avar_covariance`). The ramp
        R is a trend, not in the spectrum."""
        nu = np.asarray(f_hz, float) / rate_hz
        if np.any(nu <= 0) or np.any(nu > 0.5):
            raise GyroInputError("PSD of the model: frequencies must lie in (0, rate/2]")
        return np.stack([spectrum(nu, rate_hz, self._coef(i), self._tau(i)) / rate_hz for i in range(len(self.axes))])

    def bias_process(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The bias as a first-order discrete process over ``dt_s``: b_{k+1} = φ·b_k + w, Var w = q.

        Per axis: a Gauss–Markov bias where σ > 0 (φ = e^(−dt/τc), q = σ²(1 − φ²)), else a random
        walk with K (φ = 1, q = K²·dt; K = 0: a constant bias). One state per axis, as the Kalman
        trackers carry it (a Gauss–Markov term replaces the random walk)."""
        gm = (self.correlated_sigma_rad_s > 0) & np.isfinite(self.correlated_tau_c_s)
        with np.errstate(divide="ignore", invalid="ignore"):
            phi_gm = np.exp(-dt_s / np.where(gm, self.correlated_tau_c_s, 1.0))
        phi = np.where(gm, phi_gm, 1.0)
        q = np.where(gm, self.correlated_sigma_rad_s**2 * (1.0 - phi_gm**2), self.rrw_rad_per_s_sqrt_s**2 * dt_s)
        return phi, q
