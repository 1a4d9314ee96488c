"""The effect catalogue: one measurement model shared by the simulator and the core.

DESIGN.md, "The effect catalogue"::

    omega_meas = Q( sat( D( K(T)·omega(t − τ) + b(T, t) + H·f + G·(f⊗f) + nonlinear(omega) ) + noise ) )

This module is the single place where each effect's formula lives:

* :func:`deterministic` evaluates the part inside ``D(...)`` (the simulator adds it; the
  core's fits are checked against it).
* :func:`output_stage` applies ``D`` (on-chip low-pass), adds noise, saturates and quantizes.
* :func:`correct` removes fitted deterministic effects from a measurement (the inverse).
* :func:`design` gives, per effect, the derivative of the measurement with respect to that
  effect's parameters (the least-squares regressors used by calibration and the residual loop).

Parameters are a mapping ``{effect_name: {param_name: ndarray}}`` in SI units (see
:data:`PARAM_SCHEMA`). Stochastic effects (``arw``, ``bias_instability``, ``rrw``,
``correlated``) have parameters here but are generated in ``sim`` and identified by
``gyrocore.allan``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from .errors import GyroInputError

__all__ = [
    "EFFECTS",
    "DETERMINISTIC",
    "CORRECTABLE",
    "STOCHASTIC",
    "PARAM_SCHEMA",
    "EARTH_RATE_RAD_S",
    "ModelInputs",
    "check_effect_names",
    "validate_params",
    "misalignment_matrix",
    "k_matrix",
    "deterministic",
    "output_stage",
    "correct",
    "design",
    "earth_rate_S",
    "earth_rate_W",
    "article_from_k",
    "k_from_article",
    "FF_ORDER",
    "MISALIGNMENT_ORDER",
]

EARTH_RATE_RAD_S = 7.2921150e-5  # WGS-84 Earth rotation rate, rad/s

#: Canonical effect names, in DESIGN.md order.
EFFECTS: tuple[str, ...] = (
    "bias",
    "bias_thermal",
    "bias_temp_rate",
    "bias_ramp",
    "scale",
    "scale_thermal",
    "scale_asymmetry",
    "scale_nonlinearity",
    "misalignment",
    "g_sensitivity",
    "g2_sensitivity",
    "time_offset",
    "earth_rate",
    "quantization",
    "saturation",
    "lowpass",
    "arw",
    "bias_instability",
    "rrw",
    "correlated",
    "vibration",
)
STOCHASTIC: tuple[str, ...] = ("arw", "bias_instability", "rrw", "correlated")
#: Effects with a deterministic formula (removable by :func:`correct`).
DETERMINISTIC: tuple[str, ...] = tuple(
    e for e in EFFECTS if e not in STOCHASTIC and e not in ("vibration",)
)

#: Deterministic effects that :func:`correct` removes and :func:`design` can regress (all but
#: the non-invertible output stage: quantization, saturation, lowpass).
CORRECTABLE: tuple[str, ...] = tuple(
    e for e in DETERMINISTIC if e not in ("quantization", "saturation", "lowpass")
)

#: Misalignment angles order: K[0,1], K[0,2], K[1,0], K[1,2], K[2,0], K[2,1].
MISALIGNMENT_ORDER = ("xy", "xz", "yx", "yz", "zx", "zy")
_MIS_IDX = ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1))
#: Order of the products f⊗f used by ``g2_sensitivity``.
FF_ORDER = ("xx", "yy", "zz", "xy", "xz", "yz")
_FF_IDX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))

#: Parameter names and shapes per effect (SI units in the names). ``p`` is a polynomial
#: order chosen by the estimator; thermal polynomials are in (T − t0_c) with powers 1..p
#: (the constant term belongs to ``bias`` / ``scale``).
PARAM_SCHEMA: dict[str, dict[str, tuple]] = {
    "bias": {"b_rad_s": (3,)},
    "bias_thermal": {"poly_rad_s": (3, "p"), "t0_c": (), "temp_min_c": (), "temp_max_c": ()},
    "bias_temp_rate": {"k_rad_s_per_c_per_s": (3,)},
    "bias_ramp": {"ramp_rad_s2": (3,)},
    "scale": {"s": (3,)},
    "scale_thermal": {"poly_per_c": (3, "p"), "t0_c": (), "temp_min_c": (), "temp_max_c": ()},
    "scale_asymmetry": {"a": (3,)},
    "scale_nonlinearity": {"s2_s_per_rad": (3,)},
    "misalignment": {"m_rad": (6,)},
    "g_sensitivity": {"h_rad_s_per_m_s2": (3, 3)},
    "g2_sensitivity": {"g_rad_s_per_m2_s4": (3, 6)},
    "time_offset": {"tau_s": ()},
    "earth_rate": {"latitude_rad": (), "heading_rad": ()},
    "quantization": {"lsb_rad_s": ()},
    "saturation": {"range_rad_s": ()},
    "lowpass": {"bandwidth_hz": ()},
    "arw": {"n_rad_per_sqrt_s": (3,)},
    "bias_instability": {"b_rad_s": (3,)},
    "rrw": {"k_rad_s_per_sqrt_s": (3,)},
    "correlated": {"sigma_rad_s": (3,), "tau_c_s": (3,)},
    "vibration": {},
}

Params = Mapping[str, Mapping[str, np.ndarray]]


@dataclass(frozen=True, eq=False)
class ModelInputs:
    """Physical inputs of the measurement model.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Sample times, s.
    omega_S_rad_s : ndarray, shape (N, 3) or None
        True angular rate of S relative to the world frame W, in S, rad/s (for
        :func:`deterministic`/:func:`design`; not needed by :func:`correct`).
    f_S_m_s2 : ndarray, shape (N, 3) or None
        Specific force in S, m/s².
    temp_c : ndarray, shape (N,) or None
        Sensor temperature, °C.
    q_SW_wxyz : ndarray, shape (N, 4) or None
        Attitude S→W (for ``earth_rate``).
    t_since_power_up_s : ndarray, shape (N,) or None
        Time since the last power-up (for ``bias_ramp``); defaults to ``t_s - t_s[0]``.
    """

    t_s: np.ndarray
    omega_S_rad_s: np.ndarray | None = None
    f_S_m_s2: np.ndarray | None = None
    temp_c: np.ndarray | None = None
    q_SW_wxyz: np.ndarray | None = None
    t_since_power_up_s: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(np.asarray(self.t_s).shape[0])

    def since_power_up(self) -> np.ndarray:
        if self.t_since_power_up_s is not None:
            return np.asarray(self.t_since_power_up_s, float)
        t = np.asarray(self.t_s, float)
        return t - t[0]

    def temp_rate_c_s(self) -> np.ndarray:
        """dT/dt by central differences, °C/s, shape (N,)."""
        T = self._need("temp_c", "bias_temp_rate")
        return np.gradient(T, np.asarray(self.t_s, float))

    def _need(self, name: str, effect: str) -> np.ndarray:
        v = getattr(self, name)
        if v is None:
            col = {"temp_c": "temp_c", "f_S_m_s2": "accel_*", "omega_S_rad_s": "ref_*_rad_s",
                   "q_SW_wxyz": "ref_q*"}[name]
            raise GyroInputError(f"effect {effect} needs the {col} column(s), which the data lack")
        return np.asarray(v, float)


# ---------------------------------------------------------------------------- helpers
def check_effect_names(names) -> list[str]:
    """Validate effect names; returns them as a list. Unknown names -> one-line error."""
    out = []
    for n in names:
        n = n.strip()
        if not n:
            continue
        if n not in PARAM_SCHEMA:
            raise GyroInputError(f"unknown effect '{n}'; known effects: {', '.join(EFFECTS)}")
        out.append(n)
    return out


def validate_params(params: Params) -> dict[str, dict[str, np.ndarray]]:
    """Check names and shapes against :data:`PARAM_SCHEMA`; returns float arrays."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for eff, pdict in params.items():
        check_effect_names([eff])
        schema = PARAM_SCHEMA[eff]
        out[eff] = {}
        for pname, shape in schema.items():
            if pname not in pdict:
                raise GyroInputError(f"effect {eff}: missing parameter {pname}")
            v = np.asarray(pdict[pname], float)
            if len(v.shape) != len(shape) or any(
                s != "p" and s != d for s, d in zip(shape, v.shape)
            ):
                raise GyroInputError(f"effect {eff}: parameter {pname} has shape {v.shape}, expected {shape}")
            if not np.all(np.isfinite(v)):
                raise GyroInputError(f"effect {eff}: parameter {pname} is not finite")
            out[eff][pname] = v
        for pname, v in pdict.items():
            if pname not in schema:
                out[eff][pname] = np.asarray(v, float)  # extra info (e.g. turn-on sigma) kept
    return out


def _rows_times(x: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``x @ M.T`` per sample in a fixed order, without BLAS: Σ_j x[:, j]·M[:, j], j = 0, 1, …

    BLAS kernels (FMA, blocking) round differently from build to build; this elementwise
    form gives the same bits on every machine, and a per-sample scalar implementation
    (``sim.gyro.GyroStream``) that accumulates in the same order reproduces it exactly.
    x (N, J), M (I, J) -> (N, I).
    """
    out = x[:, 0:1] * M[None, :, 0]
    for j in range(1, M.shape[1]):
        out = out + x[:, j : j + 1] * M[None, :, j]
    return out


def _poly(coef: np.ndarray, dT: np.ndarray) -> np.ndarray:
    """Σ_k coef[:, k-1]·dT^k for k = 1..p; coef (3, p), dT (N,) -> (N, 3).

    Powers by repeated multiplication (dT, dT·dT, dT·dT·dT, …), summed in order k = 1..p.
    """
    p = coef.shape[1]
    powers = np.empty((dT.shape[0], p))
    pw = dT
    for k in range(p):
        if k:
            pw = pw * dT
        powers[:, k] = pw
    return _rows_times(powers, coef)


def _clamped_dT(pd: Mapping[str, np.ndarray], T: np.ndarray) -> np.ndarray:
    lo, hi = float(pd["temp_min_c"]), float(pd["temp_max_c"])
    return np.clip(T, lo, hi) - float(pd["t0_c"])


def misalignment_matrix(m_rad: np.ndarray) -> np.ndarray:
    """Off-diagonal 3×3 matrix from the 6 misalignment angles (MISALIGNMENT_ORDER)."""
    M = np.zeros((3, 3))
    for (i, j), v in zip(_MIS_IDX, np.asarray(m_rad, float)):
        M[i, j] = v
    return M


def k_matrix(params: Params) -> np.ndarray:
    """Constant part of K: I + diag(s) + misalignment, 3×3."""
    K = np.eye(3)
    if "scale" in params:
        K = K + np.diag(np.asarray(params["scale"]["s"], float))
    if "misalignment" in params:
        K = K + misalignment_matrix(params["misalignment"]["m_rad"])
    return K


def _ff(f: np.ndarray) -> np.ndarray:
    return np.stack([f[:, i] * f[:, j] for i, j in _FF_IDX], axis=1)


def _quat_to_R(q: np.ndarray) -> np.ndarray:
    nq = np.sqrt(q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2] + q[:, 3] * q[:, 3])
    q = q / nq[:, None]
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def earth_rate_S(latitude_rad: float, heading_rad: float, q_SW_wxyz: np.ndarray) -> np.ndarray:
    """Earth's rotation seen in S, rad/s, shape (N, 3).

    W is East-North-Up rotated about Up by ``heading_rad`` (W's x axis points
    ``heading_rad`` counter-clockwise from East). In ENU the Earth rate is
    Ω·(0, cos φ, sin φ).
    """
    w_W = earth_rate_W(latitude_rad, heading_rad)
    R_WS = _quat_to_R(np.asarray(q_SW_wxyz, float))  # S -> W
    # ω_S[:, i] = Σ_j R_WS[:, j, i]·ω_W[j], summed in order j = 0, 1, 2 (no BLAS/einsum)
    return R_WS[:, 0, :] * w_W[0] + R_WS[:, 1, :] * w_W[1] + R_WS[:, 2, :] * w_W[2]


def earth_rate_W(latitude_rad: float, heading_rad: float) -> np.ndarray:
    """Earth's rotation in W, rad/s, shape (3,) (W = ENU rotated by ``heading_rad`` about Up)."""
    w_enu = EARTH_RATE_RAD_S * np.array([0.0, np.cos(latitude_rad), np.sin(latitude_rad)])
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    R_ENU_W = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return R_ENU_W.T @ w_enu


def _shift(t: np.ndarray, x: np.ndarray, tau_s: float) -> np.ndarray:
    """x(t − τ) by linear interpolation (edges held), x shape (N, 3)."""
    if tau_s == 0.0:
        return x
    return np.stack([np.interp(t - tau_s, t, x[:, i]) for i in range(x.shape[1])], axis=1)


# ---------------------------------------------------------------------------- forward
def _additive(params: Params, inp: ModelInputs) -> np.ndarray:
    """Rate-independent terms: b(T, t) + H·f + G·(f⊗f), shape (N, 3)."""
    n = inp.n
    out = np.zeros((n, 3))
    if "bias" in params:
        out += np.asarray(params["bias"]["b_rad_s"], float)[None, :]
    if "bias_thermal" in params:
        pd = params["bias_thermal"]
        out += _poly(np.asarray(pd["poly_rad_s"], float), _clamped_dT(pd, inp._need("temp_c", "bias_thermal")))
    if "bias_temp_rate" in params:
        out += inp.temp_rate_c_s()[:, None] * np.asarray(params["bias_temp_rate"]["k_rad_s_per_c_per_s"])[None, :]
    if "bias_ramp" in params:
        out += inp.since_power_up()[:, None] * np.asarray(params["bias_ramp"]["ramp_rad_s2"])[None, :]
    if "g_sensitivity" in params:
        out += _rows_times(inp._need("f_S_m_s2", "g_sensitivity"), np.asarray(params["g_sensitivity"]["h_rad_s_per_m_s2"]))
    if "g2_sensitivity" in params:
        f = inp._need("f_S_m_s2", "g2_sensitivity")
        out += _rows_times(_ff(f), np.asarray(params["g2_sensitivity"]["g_rad_s_per_m2_s4"]))
    return out


def _scale_diag(params: Params, inp: ModelInputs, omega: np.ndarray) -> np.ndarray:
    """Rate- and temperature-dependent diagonal scale error (beyond I), shape (N, 3)."""
    d = np.zeros_like(omega)
    if "scale_thermal" in params:
        pd = params["scale_thermal"]
        d += _poly(np.asarray(pd["poly_per_c"], float), _clamped_dT(pd, inp._need("temp_c", "scale_thermal")))
    if "scale_asymmetry" in params:
        d += np.sign(omega) * np.asarray(params["scale_asymmetry"]["a"])[None, :]
    if "scale_nonlinearity" in params:
        d += np.abs(omega) * np.asarray(params["scale_nonlinearity"]["s2_s_per_rad"])[None, :]
    return d


def deterministic(params: Params, inp: ModelInputs) -> np.ndarray:
    """The deterministic measurement before the output stage, rad/s, shape (N, 3).

    K(T)·ω(t − τ) + b(T, t) + H·f + G·(f⊗f) + nonlinear(ω), with ω the inertial rate
    (world-relative truth plus ``earth_rate`` when present). ``scale_asymmetry`` is
    a_i·sign(ω_i)·ω_i and ``scale_nonlinearity`` is s2_i·ω_i·|ω_i| (DESIGN.md table).
    """
    params = validate_params(params)
    omega = inp._need("omega_S_rad_s", "deterministic model").copy()
    t = np.asarray(inp.t_s, float)
    if "earth_rate" in params:
        pd = params["earth_rate"]
        omega = omega + earth_rate_S(float(pd["latitude_rad"]), float(pd["heading_rad"]),
                                     inp._need("q_SW_wxyz", "earth_rate"))
    if "time_offset" in params:
        omega = _shift(t, omega, float(params["time_offset"]["tau_s"]))
    K = k_matrix(params)
    y = _rows_times(omega, K) + _scale_diag(params, inp, omega) * omega
    return y + _additive(params, inp)


def output_stage(
    x: np.ndarray,
    params: Params,
    *,
    rate_hz: float,
    noise_rad_s: np.ndarray | None = None,
    zi: np.ndarray | None = None,
) -> np.ndarray:
    """Q(sat(D(x) + noise)): on-chip low-pass, noise, saturation, quantization.

    ``lowpass`` is a 2nd-order Butterworth (scipy.signal.butter) at ``bandwidth_hz``, run
    causally from a steady-state start (scipy.signal.lfilter_zi). ``quantization`` rounds to
    the nearest LSB; ``saturation`` clips to ±range.
    """
    from scipy import signal

    y = np.asarray(x, float)
    if "lowpass" in params:
        fc = float(params["lowpass"]["bandwidth_hz"])
        if not 0 < fc < rate_hz / 2:
            raise GyroInputError(f"lowpass bandwidth {fc} Hz must be in (0, {rate_hz / 2}) Hz at {rate_hz} Hz")
        b, a = signal.butter(2, fc, fs=rate_hz)
        z0 = signal.lfilter_zi(b, a)
        y = np.stack([signal.lfilter(b, a, y[:, i], zi=z0 * y[0, i])[0] for i in range(3)], axis=1)
    if noise_rad_s is not None:
        y = y + noise_rad_s
    if "saturation" in params:
        r = float(params["saturation"]["range_rad_s"])
        y = np.clip(y, -r, r)
    if "quantization" in params:
        q = float(params["quantization"]["lsb_rad_s"])
        y = np.round(y / q) * q
    return y


# ---------------------------------------------------------------------------- inverse
def correct(params: Params, gyro_rad_s: np.ndarray, inp: ModelInputs, *, iterations: int = 4) -> np.ndarray:
    """Remove the deterministic effects in ``params`` from a measurement.

    Returns the estimated world-relative rate ω, rad/s, shape (N, 3) — the inverse of
    :func:`deterministic` (``earth_rate`` is subtracted when present and the attitude is
    known). The rate-dependent scale terms are inverted by fixed-point iteration, which
    converges because they are small (|a|, |s2·ω| ≪ 1). ``quantization``, ``saturation`` and
    ``lowpass`` are not invertible and are ignored; stochastic effects are not removed.
    """
    params = validate_params(params)
    y = np.asarray(gyro_rad_s, float)
    z = y - _additive(params, inp)
    Kinv = np.linalg.inv(k_matrix(params))
    omega = z @ Kinv.T
    has_nl = any(e in params for e in ("scale_thermal", "scale_asymmetry", "scale_nonlinearity"))
    if has_nl:
        for _ in range(iterations):
            omega = (z - _scale_diag(params, inp, omega) * omega) @ Kinv.T
    t = np.asarray(inp.t_s, float)
    if "time_offset" in params:
        omega = _shift(t, omega, -float(params["time_offset"]["tau_s"]))
    if "earth_rate" in params and inp.q_SW_wxyz is not None:
        pd = params["earth_rate"]
        omega = omega - earth_rate_S(float(pd["latitude_rad"]), float(pd["heading_rad"]), inp.q_SW_wxyz)
    return omega


# ---------------------------------------------------------------------------- regressors
def design(effect: str, inp: ModelInputs, *, order: int = 1,
           t0_c: float | None = None) -> tuple[list[str], np.ndarray]:
    """Regressors of one effect: ∂(measurement)/∂(parameters), linearised at zero error.

    Parameters
    ----------
    effect : str
        Catalogue name of a fittable deterministic effect.
    inp : ModelInputs
        Needs ``omega_S_rad_s`` (the reference rate) for rate-dependent effects.
    order : int
        Polynomial order for ``bias_thermal`` / ``scale_thermal`` (powers 1..order of T − T0,
        with T0 = ``inp`` mean temperature; the caller stores T0).
    t0_c : float, optional
        T0 of the thermal polynomials, °C; default the mean of ``inp.temp_c``. Pass the
        whole record's mean when building the design of a slice of it (chunked fits).

    Returns
    -------
    names : list of str
        ``"<param>[<index>]"`` for each column, in the order of the flattened parameter.
    A : ndarray, shape (N, 3, P)
        A[n, i, p] = ∂y_i(t_n)/∂θ_p, so that y − ω_ref ≈ A·θ.
    """
    n = inp.n
    if effect in ("bias", "bias_ramp", "bias_temp_rate", "scale", "scale_asymmetry", "scale_nonlinearity"):
        if effect == "bias":
            g = np.ones(n)[:, None] * np.ones(3)[None, :]
            pname = "b_rad_s"
        elif effect == "bias_ramp":
            g = inp.since_power_up()[:, None] * np.ones(3)[None, :]
            pname = "ramp_rad_s2"
        elif effect == "bias_temp_rate":
            g = inp.temp_rate_c_s()[:, None] * np.ones(3)[None, :]
            pname = "k_rad_s_per_c_per_s"
        else:
            w = inp._need("omega_S_rad_s", effect)
            g = {"scale": w, "scale_asymmetry": np.abs(w), "scale_nonlinearity": w * np.abs(w)}[effect]
            pname = {"scale": "s", "scale_asymmetry": "a", "scale_nonlinearity": "s2_s_per_rad"}[effect]
        A = np.zeros((n, 3, 3))
        for i in range(3):
            A[:, i, i] = g[:, i]
        return [f"{pname}[{i}]" for i in range(3)], A
    if effect in ("bias_thermal", "scale_thermal"):
        T = inp._need("temp_c", effect)
        dT = T - (float(np.mean(T)) if t0_c is None else float(t0_c))
        powers = dT[:, None] ** np.arange(1, order + 1)[None, :]  # (N, p)
        A = np.zeros((n, 3, 3 * order))
        w = inp._need("omega_S_rad_s", effect) if effect == "scale_thermal" else np.ones((n, 3))
        for i in range(3):
            for k in range(order):
                A[:, i, i * order + k] = powers[:, k] * w[:, i]
        pname = "poly_rad_s" if effect == "bias_thermal" else "poly_per_c"
        return [f"{pname}[{i},{k}]" for i in range(3) for k in range(order)], A
    if effect == "misalignment":
        w = inp._need("omega_S_rad_s", effect)
        A = np.zeros((n, 3, 6))
        for p, (i, j) in enumerate(_MIS_IDX):
            A[:, i, p] = w[:, j]
        return [f"m_rad[{p}]" for p in range(6)], A
    if effect == "g_sensitivity":
        f = inp._need("f_S_m_s2", effect)
        A = np.zeros((n, 3, 9))
        for i in range(3):
            for j in range(3):
                A[:, i, 3 * i + j] = f[:, j]
        return [f"h_rad_s_per_m_s2[{i},{j}]" for i in range(3) for j in range(3)], A
    if effect == "g2_sensitivity":
        ff = _ff(inp._need("f_S_m_s2", effect))
        A = np.zeros((n, 3, 18))
        for i in range(3):
            for j in range(6):
                A[:, i, 6 * i + j] = ff[:, j]
        return [f"g_rad_s_per_m2_s4[{i},{j}]" for i in range(3) for j in range(6)], A
    if effect == "time_offset":
        w = inp._need("omega_S_rad_s", effect)
        dw = np.gradient(w, np.asarray(inp.t_s, float), axis=0)
        return ["tau_s"], (-dw)[:, :, None]
    raise GyroInputError(f"effect {effect} has no least-squares regressors (it is not fitted by calibrate)")


# ---------------------------------------------------------------------------- article form
def article_from_k(K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Convert K to the article's form K⁻¹ = M·diag(1/s).

    The split is not unique; we fix it by giving M a unit diagonal:
    s_i = 1 / (K⁻¹)_ii and M = K⁻¹·diag(s).

    Returns
    -------
    M : ndarray, shape (3, 3)
        Non-orthogonality (mounting) matrix, unit diagonal.
    s : ndarray, shape (3,)
        Scale factors (dimensionless, ≈ 1).
    """
    Kinv = np.linalg.inv(np.asarray(K, float))
    s = 1.0 / np.diag(Kinv)
    return Kinv * s[None, :], s


def k_from_article(M: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Inverse of :func:`article_from_k`: K = (M·diag(1/s))⁻¹."""
    return np.linalg.inv(np.asarray(M, float) @ np.diag(1.0 / np.asarray(s, float)))
