"""The calibration result and its parameter file.

:class:`CalibrationResult` is what :class:`gyrocore.calibrator.Calibrator` and the residual loop
return: fitted effects (parameters in :data:`gyrocore.effects.registry.PARAM_SCHEMA` form, SI, with
standard errors) that :meth:`CalibrationResult.apply` removes with
:func:`gyrocore.effects.registry.correct`.

Parameter file (DESIGN.md "Parameter file"): JSON, written atomically, ``format_version``
"1.1"; a file of another major version is refused with a message that says so. 1.1 (a minor
bump: every 1.0 file still reads) may carry family terms of the registry by their canonical
name (``periodic[37.5]``, ``step[12.25]``, ``regressor[omega_y*omega_z]``, see
:func:`gyrocore.effects.registry.resolve`); a name this version does not know is one ``error:`` line
naming it.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from gyrocore.data.jsonable import to_jsonable
from gyrocore.data.recording import Recording, atomic_write_text
from gyrocore.effects import registry as E
from gyrocore.errors import GyroInputError, warn_repair
from gyrocore.noise.model import NoiseModel

__all__ = ["FORMAT_VERSION", "CalibrationResult", "save_params", "load_params", "result_to_dict", "result_from_dict"]

FORMAT_VERSION = "1.1"


def needs_accel(eff: str) -> bool:
    return "f" in E.resolve(eff).inputs


def needs_temp(eff: str) -> bool:
    return any(i in ("temp", "dtemp") for i in E.resolve(eff).inputs)


# ============================================================================ result
@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Fitted catalogue effects, ready to apply or save.

    Attributes
    ----------
    effects : tuple of str
        Fitted effects, in the order given.
    params : dict
        ``{effect: {param: ndarray}}`` in SI (PARAM_SCHEMA names). Unobservable parameters
        are 0 (not corrected).
    stderr : dict
        Same layout; standard errors (NaN where not estimated, e.g. t0_c; +inf for
        unobservable parameters).
    residual_rms_rad_s : ndarray, shape (3,)
        RMS of the fit residual per axis (rad/s); for the integral method, of the still part.
    unobservable : tuple of str
        ``"effect.param[index]"`` names of parameters the data could not determine.
    unobservable_reason : dict
    method : str
        ``"rate_reference"``, ``"still"`` or ``"integral"``.
    covariance : str
        Which covariance the standard errors come from (``ols``, ``hac``, ...; ``integral``).
    sensor : str
    source_file : str or None
        Name of the data file (no folders).
    source_sha256 : str or None
    n_samples : int
        Samples that entered the fit.
    thermal_order : dict
        Chosen polynomial order per thermal effect.
    thermal_tests : tuple
        The order-selection tests (:class:`gyrocore.calib.thermal.OrderTest` as dicts).
    notes : tuple of str
    integral : dict or None
        For the integral method: M, M_stderr, B_rad, C_rad, ... (lists).
    noise_model : dict or None
        The noise model behind ``covariance="noise_model"`` standard errors, per axis (3,):
        ``arw_rad_per_sqrt_s``, ``bias_instability_rad_s``, ``rrw_rad_s_per_sqrt_s``,
        ``gm_sigma_rad_s``, ``gm_tau_c_s`` (inf = no Gauss–Markov term)
        (the terms of a :class:`gyrocore.noise.model.NoiseModel`; :meth:`noise` rebuilds it), and
        ``rate_hz``, the sample rate of the data it describes (its white level includes that
        rate's quantization noise).
    format_version : str
    """

    effects: tuple[str, ...]
    params: dict
    stderr: dict
    residual_rms_rad_s: np.ndarray
    unobservable: tuple[str, ...] = ()
    unobservable_reason: dict = field(default_factory=dict)
    method: str = "rate_reference"
    covariance: str = "ols"
    sensor: str = "unknown"
    source_file: str | None = None
    source_sha256: str | None = None
    n_samples: int = 0
    thermal_order: dict = field(default_factory=dict)
    thermal_tests: tuple = ()
    notes: tuple[str, ...] = ()
    integral: dict | None = None
    noise_model: dict | None = None
    format_version: str = FORMAT_VERSION

    def noise(self):
        """The :class:`gyrocore.noise.model.NoiseModel` of the standard errors, or None."""
        if not self.noise_model:
            return None
        return NoiseModel(
            **{term: np.asarray(self.noise_model[k], float) for k, term in _NOISE_MODEL_KEYS.items()},
            source="parameter file",
        )

    # ------------------------------------------------------------------ apply
    def required_columns(self) -> list[str]:
        """Data columns that :meth:`apply` needs besides the gyro."""
        need = []
        if any(needs_accel(e) for e in self.params):
            need.append("accel")
        if any(needs_temp(e) for e in self.params):
            need.append("temp_c")
        return need

    def apply(
        self,
        recording: Recording,
        *,
        iterations: int = 4,
        power_up_bias: bool = False,
        still_max_s: float = 10.0,
        t_since_power_up_s: np.ndarray | None = None,
    ) -> Recording:
        """Remove the fitted effects from ``recording``'s gyro (rad/s, S frame).

        Temperatures outside the fitted range are clamped to it (``effects.correct``) and
        announced with one :class:`~gyrocore.errors.RepairWarning` giving the count.
        Columns other than the gyro are unchanged.

        Parameters
        ----------
        power_up_bias : bool
            The constant bias is redrawn at every power-up (turn-on repeatability), so a bias
            from another session is off by the turn-on σ. With True, the bias of this
            recording is re-estimated from its still start (the article's §1, gate of
            :func:`gyrocore.calib.bias.startup_still_slice`, up to ``still_max_s``): the mean of
            the corrected rate there is removed. Needs a still start.
        t_since_power_up_s : ndarray, shape (N,), optional
            Time since power-up, s (default ``t_s − t_s[0]``); a chunk of a longer
            recording passes it from the file's first sample (streamed ``apply``).
        """
        for eff in self.params:
            if needs_accel(eff) and recording.accel_m_s2 is None:
                raise GyroInputError(
                    f"the parameters include {eff}, which needs the accel_*_m_s2 columns; the data lack them"
                )
            if needs_temp(eff) and recording.temp_c is None:
                raise GyroInputError(f"the parameters include {eff}, which needs the temp_c column; the data lack it")
        for eff in E.POLYNOMIAL:  # thermal polynomials: clamped to the fitted range
            if eff in self.params:
                pd = self.params[eff]
                lo, hi = float(pd["temp_min_c"]), float(pd["temp_max_c"])
                T = recording.temp_c
                n_out = int(np.sum((T < lo) | (T > hi)))
                if n_out:
                    warn_repair(
                        f"{n_out} of {T.size} samples have a temperature outside the calibrated range "
                        f"{lo:.2f}..{hi:.2f} C; {eff} is held at the range edge there"
                    )
        inp = E.ModelInputs(
            t_s=recording.t_s,
            f_S_m_s2=recording.accel_m_s2,
            temp_c=recording.temp_c,
            t_since_power_up_s=t_since_power_up_s,
        )  # a chunk of a longer file: from the file's start
        omega = E.correct(self.params, recording.gyro_rad_s, inp, iterations=iterations)
        extra_meta = {}
        if power_up_bias:
            from gyrocore.calib.bias import startup_still_slice

            sl = startup_still_slice(recording, max_duration_s=still_max_s)
            if sl is None or sl.stop - sl.start < 8:
                raise GyroInputError(
                    "power-up bias: the recording does not start still, so its bias cannot be re-estimated"
                )
            d = omega[sl].mean(axis=0)
            omega = omega - d[None, :]
            extra_meta["power_up_bias_rad_s"] = " ".join(f"{v:.6g}" for v in d)
            extra_meta["power_up_bias_samples"] = str(sl.stop - sl.start)
        return recording.with_gyro(
            omega,
            **extra_meta,
            calibrated_effects=",".join(self.effects),
            calibration_source=f"{self.source_file or '?'} sha256:{(self.source_sha256 or '?')[:16]}",
        )

    # ------------------------------------------------------------------ article form
    def k_matrix(self) -> np.ndarray:
        """Constant K = I + diag(s) + misalignment (3×3)."""
        return E.k_matrix(self.params)

    def article_form(self) -> dict[str, np.ndarray]:
        """The article's ω = M·diag(1/s)·(ω̂′ − b), ω̂′ = ω̂ − H·a.

        Returns
        -------
        dict with ``M`` (3×3, unit diagonal), ``s`` (3,), ``b_rad_s`` (3,), ``H_rad_s_per_m_s2`` (3×3).
        """
        M, s = E.article_from_k(self.k_matrix())
        b = np.asarray(self.params.get("bias", {}).get("b_rad_s", np.zeros(3)), float)
        H = np.asarray(self.params.get("g_sensitivity", {}).get("h_rad_s_per_m_s2", np.zeros((3, 3))), float)
        return {"M": M, "s": s, "b_rad_s": b, "H_rad_s_per_m_s2": H}

    @staticmethod
    def params_from_article(M, s, b_rad_s=None, H_rad_s_per_m_s2=None) -> dict:
        """Catalogue parameters (bias, scale, misalignment, g_sensitivity) from the article's form."""
        K = E.k_from_article(np.asarray(M, float), np.asarray(s, float))
        out = {
            "scale": {"s": np.diag(K) - 1.0},
            "misalignment": {
                "m_rad": np.array([K["xyz".index(p[0]), "xyz".index(p[1])] for p in E.MISALIGNMENT_ORDER])
            },
        }
        if b_rad_s is not None:
            out["bias"] = {"b_rad_s": np.asarray(b_rad_s, float)}
        if H_rad_s_per_m_s2 is not None:
            out["g_sensitivity"] = {"h_rad_s_per_m_s2": np.asarray(H_rad_s_per_m_s2, float)}
        return out

    def to_dict(self) -> dict:
        """JSON-ready dict (the parameter file)."""
        return result_to_dict(self)


def noise_model_dict(nm, rate_hz: float) -> dict | None:
    """The parameter file's ``noise_model`` entry of a :class:`~gyrocore.noise.model.NoiseModel`
    (its N, B, K and Gauss–Markov pair per axis; ``rate_hz`` the rate of the data it describes)."""
    if nm is None:
        return None
    out: dict = {
        k: np.broadcast_to(np.asarray(getattr(nm, term), float), (3,)).copy() for k, term in _NOISE_MODEL_KEYS.items()
    }
    out["rate_hz"] = float(rate_hz)
    return out


# ============================================================================ parameter file
def result_to_dict(res: CalibrationResult) -> dict:
    """The parameter file as a dict (DESIGN.md "Parameter file")."""
    art = (
        res.article_form() if any(e in res.params for e in ("scale", "misalignment", "bias", "g_sensitivity")) else None
    )
    d = {
        "format_version": res.format_version,
        "sensor": res.sensor,
        "effects": list(res.effects),
        "parameters": {e: {k: to_jsonable(v) for k, v in pd.items()} for e, pd in res.params.items()},
        "standard_errors": {e: {k: to_jsonable(v) for k, v in pd.items()} for e, pd in res.stderr.items()},
        "residual_rms_rad_s": to_jsonable(res.residual_rms_rad_s),
        "unobservable": list(res.unobservable),
        "unobservable_reason": dict(res.unobservable_reason),
        "method": res.method,
        "covariance": res.covariance,
        "n_samples": int(res.n_samples),
        "thermal_order": dict(res.thermal_order),
        "thermal_tests": to_jsonable(list(res.thermal_tests)),
        "notes": list(res.notes),
        "source": {"file": res.source_file, "sha256": res.source_sha256},
        "article_form": to_jsonable(art) if art is not None else None,
        "integral": to_jsonable(res.integral) if res.integral is not None else None,
        "noise_model": (
            {
                k: (
                    [None if not np.isfinite(x) else float(x) for x in np.asarray(v, float).reshape(-1)]
                    if k != "rate_hz"
                    else float(v)
                )
                for k, v in res.noise_model.items()
            }
            if res.noise_model
            else None
        ),
        "created_utc": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "units": "SI: rad, s, m/s^2, degC; parameter names carry their unit",
    }
    return d


def _arr(v, *, null=np.nan):
    if v is None:
        return np.asarray(null, float)
    a = np.asarray(v, dtype=object)
    return np.asarray(np.where(a == None, null, a), dtype=float)  # noqa: E711


def result_from_dict(d: Mapping, *, where: str = "parameter file") -> CalibrationResult:
    """Inverse of :func:`result_to_dict` (validates names, shapes and the format version)."""
    if not isinstance(d, Mapping):
        raise GyroInputError(f"{where}: not a gyroharness parameter file (top level is not an object)")
    ver = d.get("format_version")
    if not isinstance(ver, str) or not ver:
        raise GyroInputError(f"{where}: not a gyroharness parameter file (no format_version)")
    major = ver.split(".")[0]
    if major != FORMAT_VERSION.split(".")[0]:
        raise GyroInputError(
            f"{where}: parameter file format_version {ver} is not supported; this gyroharness reads {FORMAT_VERSION.split('.')[0]}.x"
        )
    try:
        given = [str(n) for n in d["effects"]]
        effects = tuple(E.check_effect_names(given))  # canonical names (a 1.0 file: catalogue only)
        if len(set(effects)) != len(effects):
            raise GyroInputError("an effect is listed twice")
        raw = d["parameters"]
        params = {e: {k: _arr(v) for k, v in raw[g].items()} for g, e in zip(given, effects)}
        params = E.validate_params(params)
        se_raw = d.get("standard_errors") or {}
        stderr = {e: {k: _arr(v, null=np.inf) for k, v in se_raw.get(g, {}).items()} for g, e in zip(given, effects)}
        rms = _arr(d.get("residual_rms_rad_s"))
    except GyroInputError as exc:
        raise GyroInputError(f"{where}: {exc}") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise GyroInputError(
            f"{where}: malformed parameter file ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        ) from None
    src = d.get("source") or {}
    return CalibrationResult(
        effects=effects,
        params=params,
        stderr=stderr,
        residual_rms_rad_s=rms,
        unobservable=tuple(d.get("unobservable") or ()),
        unobservable_reason=dict(d.get("unobservable_reason") or {}),
        method=str(d.get("method", "")),
        covariance=str(d.get("covariance", "")),
        sensor=str(d.get("sensor", "unknown")),
        source_file=src.get("file"),
        source_sha256=src.get("sha256"),
        n_samples=int(d.get("n_samples") or 0),
        thermal_order=dict(d.get("thermal_order") or {}),
        thermal_tests=tuple(d.get("thermal_tests") or ()),
        notes=tuple(d.get("notes") or ()),
        integral=d.get("integral"),
        noise_model=_noise_model_from(d.get("noise_model"), where),
        format_version=ver,
    )


#: The parameter file's ``noise_model`` keys (DESIGN.md "Parameter file") and the
#: :class:`~gyrocore.noise.model.NoiseModel` term each one holds.
_NOISE_MODEL_KEYS = {
    "arw_rad_per_sqrt_s": "arw_rad_per_sqrt_s",
    "bias_instability_rad_s": "bias_instability_rad_s",
    "rrw_rad_s_per_sqrt_s": "rrw_rad_per_s_sqrt_s",
    "gm_sigma_rad_s": "correlated_sigma_rad_s",
    "gm_tau_c_s": "correlated_tau_c_s",
}


def _noise_model_from(d, where: str) -> dict | None:
    """The optional ``noise_model`` entry of a parameter file (null τc = inf)."""
    if not d:
        return None
    try:
        out = {k: _arr(d[k], null=np.inf if k == "gm_tau_c_s" else 0.0).reshape(3) for k in _NOISE_MODEL_KEYS}
        out["rate_hz"] = float(d.get("rate_hz") or np.nan)
    except (KeyError, TypeError, ValueError):
        raise GyroInputError(
            f"{where}: malformed noise_model entry (needs {', '.join(_NOISE_MODEL_KEYS)}, 3 values each)"
        ) from None
    return out


def save_params(result: CalibrationResult, path: str | os.PathLike, *, overwrite: bool = True) -> None:
    """Write the parameter file (JSON, atomically)."""
    text = json.dumps(result_to_dict(result), indent=2, allow_nan=False)
    atomic_write_text(path, text + "\n", overwrite=overwrite)


def load_params(path: str | os.PathLike) -> CalibrationResult:
    """Read a parameter file; a corrupt file or another major version -> one-line error."""
    path = str(path)
    if not os.path.isfile(path):
        raise GyroInputError(f"{path}: no such parameter file")
    try:
        with open(path, encoding="utf-8") as fh:
            d = json.load(fh)
    except UnicodeDecodeError:
        raise GyroInputError(f"{path}: not a parameter file (not UTF-8 text)") from None
    except json.JSONDecodeError as exc:
        raise GyroInputError(f"{path}: not a parameter file (JSON error at line {exc.lineno}: {exc.msg})") from None
    return result_from_dict(d, where=path)
