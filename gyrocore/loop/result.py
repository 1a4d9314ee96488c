"""What the residual loop reports: the evidence for each effect, the steps, what remains, the result."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .residual import Residual

__all__ = ["FORMAT_VERSION", "Evidence", "Step", "Remaining", "LoopResult", "evidence_dict"]


FORMAT_VERSION = "1.0"


@dataclass(frozen=True)
class Evidence:
    """Why an effect was (or was not) taken.

    Attributes
    ----------
    statistic : float
        Wald statistic / q on the HAC covariance (an F statistic).
    df1, df2 : int
        q (testable candidate parameters) and M − P.
    p_value : float
        P(F(df1, df2) > statistic).
    log10_p : float
        log10 of the p-value (finite where the p-value underflows).
    threshold : float
        Holm threshold α/K at this step.
    params : dict
        ``"param[index]"`` -> estimate, SI.
    std_errors : dict
        ``"param[index]"`` -> HAC standard error, SI.
    unobservable : tuple of str
        Candidate parameters the data cannot determine (not tested).
    rms_reduction : float
        1 − RMS(after)/RMS(before) of the window residual.
    attitude_reduction : float
        1 − error(after)/error(before) (NaN if no attitude error is defined).
    hac_bandwidth : float
        Bartlett bandwidth in windows.
    ambiguous_with : tuple of str
        Candidates that explain the same residual (see module docstring).
    hac_log10_p, model_log10_p : float
        log10 p of the two Wald tests the candidate must pass (:func:`gyrocore.loop.evidence._model_wald`): on the
        HAC covariance (F reference) and on the covariance implied by a white + random-walk +
        Gauss–Markov noise model identified on the residual (χ² reference). ``p_value`` /
        ``log10_p`` are the larger of the two (both must reject); NaN where the model-based
        test does not apply (known-angle references, fewer than 64 windows).
    cv_rms_reduction : float
        1 − RMS(with)/RMS(without the candidate) of the window residual predicted out of
        sample (2-fold blocked in time; see the module docstring); NaN when no fold split
        can identify the candidate (no verdict).
    """

    statistic: float
    df1: int
    df2: int
    p_value: float
    log10_p: float
    threshold: float
    params: dict
    std_errors: dict
    unobservable: tuple[str, ...]
    rms_reduction: float
    attitude_reduction: float
    hac_bandwidth: float
    ambiguous_with: tuple[str, ...] = ()
    cv_rms_reduction: float = float("nan")
    hac_log10_p: float = float("nan")
    model_log10_p: float = float("nan")

    @property
    def significant(self) -> bool:
        return self.df1 > 0 and self.p_value < self.threshold

    def to_json(self) -> dict:
        """The DESIGN.md JSON of the evidence (``found[i].evidence``, ``not_taken``)."""
        return {
            "statistic": self.statistic,
            "df1": self.df1,
            "df2": self.df2,
            "p_value": self.p_value,
            "log10_p": self.log10_p,
            "threshold": self.threshold,
            "params": self.params,
            "std_errors": self.std_errors,
            "unobservable": list(self.unobservable),
            "rms_reduction": self.rms_reduction,
            "attitude_reduction": self.attitude_reduction,
            "hac_bandwidth_windows": self.hac_bandwidth,
            "ambiguous_with": list(self.ambiguous_with),
            "cv_rms_reduction": self.cv_rms_reduction,
            "hac_log10_p": self.hac_log10_p,
            "model_log10_p": self.model_log10_p,
        }


#: The evidence keys an open-search description carries (``unexplained[i].evidence``), in order.
_OPEN_EVIDENCE_KEYS = (
    "statistic",
    "df1",
    "df2",
    "p_value",
    "log10_p",
    "threshold",
    "cv_rms_reduction",
    "rms_reduction",
    "attitude_reduction",
    "params",
    "std_errors",
    "hac_log10_p",
    "model_log10_p",
)


def evidence_dict(ev: Evidence) -> dict:
    """The evidence of an open-search term refitted with the model (its Wald tests and sizes)."""
    full = ev.to_json()
    return {k: full[k] for k in _OPEN_EVIDENCE_KEYS}


@dataclass(frozen=True)
class Step:
    """One loop step: the effect added and the error before and after."""

    effect: str
    evidence: Evidence
    residual_rms_before_rad_s: float
    residual_rms_after_rad_s: float
    attitude_error_before_deg: float
    attitude_error_after_deg: float


@dataclass(frozen=True, eq=False)
class Remaining:
    """What the final residual still holds.

    The Ljung–Box test uses all windows; the Welch spectrum and the Allan deviation use the
    longest run of evenly spaced windows (empty when it is shorter than 17 windows).

    Attributes
    ----------
    ljung_box_p : float
        Ljung–Box p-value over 3 axes (small = not white).
    window_s : float
        Median window length, s (the residual's sample interval for the spectrum/Allan).
    welch_freq_hz : ndarray, shape (F,)
    welch_psd : ndarray, shape (F, 3)
        One-sided PSD of the window residual, (rad/s)²/Hz.
    allan_tau_s : ndarray, shape (K,)
    allan_adev_rad_s : ndarray, shape (K, 3)
    allan_slope : ndarray, shape (3,)
        Log-log slope of the Allan deviation (−½ white, 0 flicker, +½ RRW, +1 ramp).
    """

    ljung_box_p: float
    window_s: float
    welch_freq_hz: np.ndarray
    welch_psd: np.ndarray
    allan_tau_s: np.ndarray
    allan_adev_rad_s: np.ndarray
    allan_slope: np.ndarray

    def summary(self) -> dict:
        """JSON-friendly summary."""
        return {
            "ljung_box_p": self.ljung_box_p,
            "white": bool(np.isfinite(self.ljung_box_p) and self.ljung_box_p >= 0.01),
            "window_s": self.window_s,
            "welch_peak_hz": [
                float(self.welch_freq_hz[1:][np.argmax(self.welch_psd[1:, i])]) if self.welch_freq_hz.size > 2 else None
                for i in range(3)
            ],
            "allan_tau_s": self.allan_tau_s,
            "allan_adev_rad_s": self.allan_adev_rad_s,
            "allan_slope": self.allan_slope,
        }


@dataclass(frozen=True, eq=False)
class LoopResult:
    """Result of :func:`run_loop` (JSON: :meth:`to_json`, DESIGN.md "JSON of loop").

    Attributes
    ----------
    declared : tuple of str
    found : tuple of Step
    reference : str
        Reference kind used.
    description : str
        The reference, one line.
    residual_rms_before_rad_s, residual_rms_after_rad_s : float
        RMS over windows and axes of the window residual with the declared model only / with
        declared + found, rad/s.
    attitude_error_before_deg, attitude_error_after_deg : float
        RMS attitude error (see module docstring), deg; NaN when not defined.
    params : dict
        Final joint fit: effect -> {"param[index]": [value, stderr]}, SI.
    tested : dict
        Last step's evidence of every candidate not taken.
    untestable : dict
        Candidate -> reason (missing column, not observable).
    remaining : Remaining
    notes : tuple of str
    n_windows : int
    alpha : float
    residual : Residual
        The residual the loop worked on (window regressors, for plots).
    history : tuple of ndarray, each (M, 3)
        Window residual with the declared model, then after each catalogue step, rad/s.
    unexplained : tuple of gyrocore.loop.search.Unexplained
        Effects outside the catalogue described by the open search (DESIGN.md
        "Effects outside the catalogue"), in the order they were added.
    open_search : dict
        What the open search tested last (the strongest candidate of each kind, not taken),
        or why it did not run.
    t0_c : float or None
        Reference temperature of the thermal polynomials (mean temperature), °C.
    """

    declared: tuple[str, ...]
    found: tuple[Step, ...]
    reference: str
    description: str
    residual_rms_before_rad_s: float
    residual_rms_after_rad_s: float
    attitude_error_before_deg: float
    attitude_error_after_deg: float
    params: dict
    tested: dict
    untestable: dict
    remaining: Remaining
    notes: tuple[str, ...]
    n_windows: int
    alpha: float = 0.01
    format_version: str = FORMAT_VERSION
    residual: Residual | None = field(default=None, repr=False)
    history: tuple = field(default=(), repr=False)
    unexplained: tuple = ()
    open_search: dict = field(default_factory=dict)
    t0_c: float | None = None

    @property
    def found_effects(self) -> list[str]:
        return [s.effect for s in self.found]

    def to_json(self) -> dict:
        """The DESIGN.md JSON (plus extra keys)."""

        return {
            "format_version": self.format_version,
            "declared": list(self.declared),
            "found": [
                {
                    "effect": s.effect,
                    "evidence": s.evidence.to_json(),
                    "residual_rms_before_rad_s": s.residual_rms_before_rad_s,
                    "residual_rms_after_rad_s": s.residual_rms_after_rad_s,
                    "attitude_error_before_deg": s.attitude_error_before_deg,
                    "attitude_error_after_deg": s.attitude_error_after_deg,
                }
                for s in self.found
            ],
            "residual_rms_before_rad_s": self.residual_rms_before_rad_s,
            "residual_rms_after_rad_s": self.residual_rms_after_rad_s,
            "attitude_error_before_deg": self.attitude_error_before_deg,
            "attitude_error_after_deg": self.attitude_error_after_deg,
            "reference": self.reference,
            "reference_description": self.description,
            "n_windows": self.n_windows,
            "alpha": self.alpha,
            "params": self.params,
            "not_taken": {k: v.to_json() for k, v in self.tested.items()},
            "untestable": dict(self.untestable),
            "unexplained": [u.to_json() for u in self.unexplained],
            "open_search": self.open_search,
            "remaining": self.remaining.summary(),
            "notes": list(self.notes),
        }
