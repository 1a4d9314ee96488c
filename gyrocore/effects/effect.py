"""The effect object and the model inputs every effect reads (the registry's building blocks).

:class:`ModelInputs` holds the signals a measurement depends on (reference rate ω_S, its
derivative, specific force, temperature and its rate, time, attitude); :class:`Effect` is one
registered effect (schema, stage, inputs, forward term, regressors, inverse). The geometry and
polynomial helpers the catalogue's terms share are here too. :mod:`gyrocore.effects.registry`
holds the catalogue and the model functions, :mod:`gyrocore.effects.families` the open families.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np

from gyrocore.errors import GyroInputError

EARTH_RATE_RAD_S = 7.2921150e-5  # WGS-84 Earth rotation rate, rad/s

#: Misalignment angles order: K[0,1], K[0,2], K[1,0], K[1,2], K[2,0], K[2,1].
MISALIGNMENT_ORDER = ("xy", "xz", "yx", "yz", "zx", "zy")
MIS_IDX = ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1))
#: Order of the products f⊗f used by ``g2_sensitivity``.
FF_ORDER = ("xx", "yy", "zz", "xy", "xz", "yz")
FF_IDX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
#: Parameters of the thermal polynomials that are metadata, not fitted.
THERMAL_META = ("t0_c", "temp_min_c", "temp_max_c")

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
        Time since the last power-up (for ``bias_ramp`` and the signal ``t``); defaults to
        ``t_s - t_s[0]``.
    alpha_S_rad_s2 : ndarray, shape (N, 3) or None
        Rate derivative for the ``alpha_*`` signals; default the central difference of the
        rate (:func:`correct` sets a smoothed one, see there).
    """

    t_s: np.ndarray
    omega_S_rad_s: np.ndarray | None = None
    f_S_m_s2: np.ndarray | None = None
    temp_c: np.ndarray | None = None
    q_SW_wxyz: np.ndarray | None = None
    t_since_power_up_s: np.ndarray | None = None
    alpha_S_rad_s2: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(np.asarray(self.t_s).shape[0])

    def since_power_up(self) -> np.ndarray:
        if self.t_since_power_up_s is not None:
            return np.asarray(self.t_since_power_up_s, float)
        t = np.asarray(self.t_s, float)
        return t - t[0]

    def temp_rate_c_s(self, effect: str = "bias_temp_rate") -> np.ndarray:
        """dT/dt by central differences, °C/s, shape (N,) (0 for a single sample)."""
        T = self._need("temp_c", effect)
        if T.shape[0] < 2:
            return np.zeros_like(T)
        return np.gradient(T, np.asarray(self.t_s, float))

    def rate_derivative(self, effect: str = "regressor") -> np.ndarray:
        """dω/dt of ``omega_S_rad_s`` by central differences (one-sided at the ends), rad/s², (N, 3)."""
        w = self._need("omega_S_rad_s", effect)
        return np.gradient(w, np.asarray(self.t_s, float), axis=0)

    def _need(self, name: str, effect: str) -> np.ndarray:
        v = getattr(self, name)
        if v is None:
            col = {"temp_c": "temp_c", "f_S_m_s2": "accel_*", "omega_S_rad_s": "ref_*_rad_s", "q_SW_wxyz": "ref_q*"}[
                name
            ]
            raise GyroInputError(f"effect {effect} needs the {col} column(s), which the data lack")
        return np.asarray(v, float)


# ---------------------------------------------------------------------------- the Effect object
#: Kinds of effect.
KINDS = ("correctable", "output", "stochastic", "physics")
#: Stages of a correctable effect, in the order the model applies them: ``rate`` transforms
#: ω (earth rate, delay), ``k`` adds to the constant K, ``scale`` adds to the rate-dependent
#: diagonal scale d(ω, T) (term d·ω), ``additive`` adds rad/s directly. Output effects:
#: ``filter`` (before the noise) and ``clip`` (after it).
STAGES = ("rate", "k", "scale", "additive", "filter", "clip")
#: Model inputs an effect can need (``ModelInputs`` fields / derived signals).
INPUTS = ("omega", "alpha", "f", "temp", "dtemp", "t", "q")
INPUT_COLUMNS = {
    "omega": "ref_*_rad_s",
    "alpha": "ref_*_rad_s",
    "f": "accel_*",
    "temp": "temp_c",
    "dtemp": "temp_c",
    "q": "ref_q*",
    "t": "t_s",
}


@dataclass(frozen=True, eq=False)
class Effect:
    """One effect of the measurement model (catalogue entry or family instance).

    Attributes
    ----------
    name : str
        Canonical name (``"scale"``, ``"periodic[37.5]"``, ``"regressor[omega_y*omega_z]"``).
    kind : str
        ``"correctable"`` (deterministic, removed by :func:`correct`), ``"output"`` (the
        non-invertible output stage), ``"stochastic"`` (noise; generated by ``sim``,
        identified by ``gyrocore.noise.allan``) or ``"physics"`` (``vibration``).
    schema : mapping
        Parameter name -> shape (``"p"`` = polynomial order chosen by the estimator, ``"n"`` =
        a grid length set by the data, the same for every parameter of the effect), SI
        units in the names.
    stage : str or None
        Where the term enters (:data:`STAGES`).
    inputs : tuple of str
        Model inputs the term needs (:data:`INPUTS`): omega (reference rate), alpha (its
        derivative), f (specific force), temp, dtemp (dT/dt), t (time), q (attitude).
    term : callable or None
        Forward term; signature by stage — ``rate``: ``(pd, inp, t_s, omega) -> omega'``;
        ``k``: ``(pd) -> (3, 3)`` added to K; ``scale``/``additive``:
        ``(pd, inp, omega) -> (N, 3)``; ``filter``/``clip``: ``(pd, y, rate_hz) -> y'``.
    regressors : callable or None
        ``(inp, order, t0_c) -> (column names, A (N, 3, P))``: ∂y/∂θ at zero error (the
        least-squares design); None = not fitted by least squares.
    inverse : callable or None
        For ``rate`` effects: ``(pd, inp, t_s, omega) -> omega`` undoing ``term``. Other
        correctable effects use the generic inverse of :func:`correct`.
    family : str or None
        ``"periodic"``, ``"step"`` or ``"regressor"`` for a family instance.
    arg : object
        The family argument (frequency in Hz, step time in s, or the parsed expression).
    plausible : float
        Largest physically plausible |θ| (SI), for the observability test of ``gyrocore.calib.lsq``.
    defaults : mapping
        Parameter values the simulator uses when an injected term omits them.
    description : str
    priority : int
        Order within a stage (lower first; ties: catalogue order, then family names sorted).
        ``earth_rate`` (−1) is added to ω before the delay of ``time_offset`` is applied.
    """

    name: str
    kind: str
    schema: Mapping[str, tuple]
    stage: str | None = None
    inputs: tuple[str, ...] = ()
    term: Callable | None = None
    regressors: Callable | None = None
    inverse: Callable | None = None
    family: str | None = None
    arg: object = None
    plausible: float = math.inf
    defaults: Mapping[str, object] = field(default_factory=dict)
    description: str = ""
    priority: int = 0

    @property
    def fittable(self) -> bool:
        """Has least-squares regressors (``calibrate`` and the loop can fit it)."""
        return self.regressors is not None

    @property
    def correctable(self) -> bool:
        return self.kind == "correctable"

    @property
    def noisy(self) -> bool:
        """Its regressors are built from measured, noisy inputs (accel, temperature)."""
        return any(i in ("f", "temp", "dtemp") for i in self.inputs)

    @property
    def polynomial(self) -> bool:
        """Has a polynomial parameter of estimator-chosen order (``"p"`` in a shape: the thermal ones)."""
        return any("p" in shape for shape in self.schema.values())

    @property
    def fit_params(self) -> tuple[str, ...]:
        """Parameters estimated by least squares, in design-column order (metadata excluded)."""
        return tuple(k for k in self.schema if k not in THERMAL_META)

    def columns(self) -> list[str]:
        """Data columns the effect needs besides the gyro (``accel``, ``temp_c``, ``ref``...)."""
        out = []
        for i in self.inputs:
            c = {
                "f": "accel",
                "temp": "temp_c",
                "dtemp": "temp_c",
                "omega": "ref_rate",
                "alpha": "ref_rate",
                "q": "ref_attitude",
            }.get(i)
            if c and c not in out:
                out.append(c)
        return out

    def design(self, inp: ModelInputs, *, order: int = 1, t0_c: float | None = None) -> tuple[list[str], np.ndarray]:
        """Regressors ∂y/∂θ, shape (N, 3, P) (see :func:`design`)."""
        if self.regressors is None:
            raise GyroInputError(f"effect {self.name} has no least-squares regressors (it is not fitted by calibrate)")
        return self.regressors(inp, int(order), t0_c)

    def unflatten(self, vec: np.ndarray, order: int = 1) -> dict[str, np.ndarray]:
        """Flat design-order parameter vector -> ``{param: array}`` in schema shapes."""
        vec = np.asarray(vec, float).ravel()
        out, k = {}, 0
        for pname in self.fit_params:
            shp = tuple(int(order) if d == "p" else d for d in self.schema[pname])
            size = int(np.prod(shp)) if shp else 1
            part = vec[k : k + size]
            out[pname] = part.reshape(shp) if shp else np.asarray(float(part[0]))
            k += size
        if k != vec.size:
            raise GyroInputError(f"effect {self.name}: {vec.size} values for {k} parameters")
        return out


def diag_design(g: np.ndarray, pname: str) -> tuple[list[str], np.ndarray]:
    """Per-axis regressor g (N, 3) on the diagonal: A[:, i, i] = g[:, i]."""
    n = g.shape[0]
    A = np.zeros((n, 3, 3))
    for i in range(3):
        A[:, i, i] = g[:, i]
    return [f"{pname}[{i}]" for i in range(3)], A


# ---------------------------------------------------------------------------- helpers
def rows_times(x: np.ndarray, M: np.ndarray) -> np.ndarray:
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


def poly_dT(coef: np.ndarray, dT: np.ndarray) -> np.ndarray:
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
    return rows_times(powers, coef)


def clamped_dT(pd: Mapping[str, np.ndarray], T: np.ndarray) -> np.ndarray:
    lo, hi = float(pd["temp_min_c"]), float(pd["temp_max_c"])
    return np.clip(T, lo, hi) - float(pd["t0_c"])


def misalignment_matrix(m_rad: np.ndarray) -> np.ndarray:
    """Off-diagonal 3×3 matrix from the 6 misalignment angles (MISALIGNMENT_ORDER)."""
    M = np.zeros((3, 3))
    for (i, j), v in zip(MIS_IDX, np.asarray(m_rad, float)):
        M[i, j] = v
    return M


def ff_products(f: np.ndarray) -> np.ndarray:
    return np.stack([f[:, i] * f[:, j] for i, j in FF_IDX], axis=1)


def quat_to_R(q: np.ndarray) -> np.ndarray:
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
    R_WS = quat_to_R(np.asarray(q_SW_wxyz, float))  # S -> W
    # ω_S[:, i] = Σ_j R_WS[:, j, i]·ω_W[j], summed in order j = 0, 1, 2 (no BLAS/einsum)
    return R_WS[:, 0, :] * w_W[0] + R_WS[:, 1, :] * w_W[1] + R_WS[:, 2, :] * w_W[2]


def earth_rate_W(latitude_rad: float, heading_rad: float) -> np.ndarray:
    """Earth's rotation in W, rad/s, shape (3,) (W = ENU rotated by ``heading_rad`` about Up)."""
    w_enu = EARTH_RATE_RAD_S * np.array([0.0, np.cos(latitude_rad), np.sin(latitude_rad)])
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    R_ENU_W = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return R_ENU_W.T @ w_enu


def time_shift(t: np.ndarray, x: np.ndarray, tau_s: float) -> np.ndarray:
    """x(t − τ) by linear interpolation (edges held), x shape (N, 3)."""
    if tau_s == 0.0:
        return x
    return np.stack([np.interp(t - tau_s, t, x[:, i]) for i in range(x.shape[1])], axis=1)
