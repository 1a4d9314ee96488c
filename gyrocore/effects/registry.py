"""The effect registry: one measurement model shared by the simulator and the core.

DESIGN.md, "The effect catalogue"::

    omega_meas = Q( sat( D( K(T)·omega(t − τ) + b(T, t) + H·f + G·(f⊗f) + nonlinear(omega) ) + noise ) )

Every effect is one registered :class:`Effect` object — its parameter schema, its forward
term, its least-squares regressors (:meth:`Effect.design`), its inverse where the generic
one does not do, the model inputs it needs, and its kind. The model functions iterate the
registry:

* :func:`deterministic` evaluates the part inside ``D(...)`` (the simulator adds it; the
  core's fits are checked against it).
* :func:`output_stage` applies ``D`` (on-chip low-pass), adds noise, saturates and quantizes.
* :func:`correct` removes fitted deterministic effects from a measurement (the inverse).
* :func:`design` gives, per effect, the derivative of the measurement with respect to that
  effect's parameters (the least-squares regressors used by calibration and the residual loop).

The catalogue (:data:`REGISTRY`, DESIGN.md's 21 names) is closed; three open *families*
describe terms no catalogue names (DESIGN.md "Effects outside the catalogue"). A family
instance's name carries its definition, so it is saved, loaded and injected by name:

* ``periodic[<f_hz>]`` — a_cos·cos(2πf·t_s) + a_sin·sin(2πf·t_s) per axis
  (params ``a_cos_rad_s`` (3,), ``a_sin_rad_s`` (3,));
* ``step[<t_s>]`` — ``size_rad_s`` (3,) added for t_s ≥ the step time;
* ``regressor[<expr>]`` — ``coef`` (3,) times a signal built from the data (:data:`SIGNALS`,
  products ``a*b`` and powers ``a^2``; see :func:`parse_expr`).

:func:`resolve` returns the :class:`Effect` of any name (catalogue or family; family names are
canonicalised, so one term has one name; :func:`family_name` builds one), :func:`catalogue_equivalent`
maps a regressor term that some catalogue effect already contains to that effect's name, and
:func:`expr_values` evaluates a regressor expression on the data. This is the one grammar of the
family terms: the loop's open search and the twin use it.

Parameters are a mapping ``{effect_name: {param_name: ndarray}}`` in SI units (see
:data:`PARAM_SCHEMA`). Stochastic effects (``arw``, ``bias_instability``, ``rrw``,
``correlated``) have parameters here but are generated in ``sim`` and identified by
``gyrocore.noise.allan``. ``vibration`` (kind ``physics``) comes from the hover's rotor physics;
its optional shaped part (``f_hz`` (n,), ``psd_rad2_s2_hz`` (3, n): a measured spectrum,
:func:`gyrocore.flight.synthesis.shaped_params`) is generated in ``sim`` as one more noise term
(``sim.noise.ShapedNoise``), so a spec enters the simulator as every effect does.

Adding a catalogue effect: write its :class:`Effect` below (schema, stage, inputs, term,
regressors) and list it in :data:`_CATALOGUE` — see docs/ARCHITECTURE.md "Add an effect in
one place".
"""

from __future__ import annotations

import math
from dataclasses import replace as _replace
from functools import lru_cache
from typing import Iterable, Mapping

import numpy as np

from gyrocore.effects.effect import (
    EARTH_RATE_RAD_S,
    FF_ORDER,
    MIS_IDX,
    MISALIGNMENT_ORDER,
    THERMAL_META,
    Effect,
    ModelInputs,
    Params,
    clamped_dT,
    diag_design,
    earth_rate_S,
    earth_rate_W,
    ff_products,
    misalignment_matrix,
    poly_dT,
    rows_times,
    time_shift,
)
from gyrocore.effects.families import (
    FAMILIES,
    SIGNALS,
    canonical_expr,
    expr_text,
    expr_values,
    family_parts,
    fmt_float,
    is_family,
    parse_expr,
    parse_float,
    periodic_effect,
    regressor_effect,
    step_effect,
)
from gyrocore.errors import GyroInputError

__all__ = [
    "Effect",
    "REGISTRY",
    "FAMILIES",
    "SIGNALS",
    "resolve",
    "is_family",
    "catalogue_equivalent",
    "parse_expr",
    "canonical_expr",
    "expr_values",
    "canonical_name",
    "family_name",
    "ordered_effects",
    "context_rows",
    "EFFECTS",
    "DETERMINISTIC",
    "CORRECTABLE",
    "STOCHASTIC",
    "NOISE",
    "NOISE_TERMS",
    "is_stochastic",
    "OUTPUT_STAGE",
    "POLYNOMIAL",
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
    "THERMAL_META",
]


# ---------------------------------------------------------------------------- catalogue terms
def _poly_design(inp: ModelInputs, order: int, t0_c, effect: str, pname: str, rate: bool):
    T = inp._need("temp_c", effect)
    dT = T - (float(np.mean(T)) if t0_c is None else float(t0_c))
    powers = dT[:, None] ** np.arange(1, order + 1)[None, :]  # (N, p)
    n = inp.n
    A = np.zeros((n, 3, 3 * order))
    w = inp._need("omega_S_rad_s", effect) if rate else np.ones((n, 3))
    for i in range(3):
        for k in range(order):
            A[:, i, i * order + k] = powers[:, k] * w[:, i]
    return [f"{pname}[{i},{k}]" for i in range(3) for k in range(order)], A


def _misalignment_design(inp, order, t0_c):
    w = inp._need("omega_S_rad_s", "misalignment")
    A = np.zeros((inp.n, 3, 6))
    for p, (i, j) in enumerate(MIS_IDX):
        A[:, i, p] = w[:, j]
    return [f"m_rad[{p}]" for p in range(6)], A


def _matrix_design(x: np.ndarray, pname: str):
    """Regressors of a 3×J matrix acting on the signals x (N, J): y_i += Σ_j M[i, j]·x_j."""
    J = x.shape[1]
    A = np.zeros((x.shape[0], 3, 3 * J))
    for i in range(3):
        for j in range(J):
            A[:, i, J * i + j] = x[:, j]
    return [f"{pname}[{i},{j}]" for i in range(3) for j in range(J)], A


def _g_design(inp, order, t0_c):
    return _matrix_design(inp._need("f_S_m_s2", "g_sensitivity"), "h_rad_s_per_m_s2")


def _g2_design(inp, order, t0_c):
    return _matrix_design(ff_products(inp._need("f_S_m_s2", "g2_sensitivity")), "g_rad_s_per_m2_s4")


def _time_offset_design(inp, order, t0_c):
    w = inp._need("omega_S_rad_s", "time_offset")
    dw = np.gradient(w, np.asarray(inp.t_s, float), axis=0)
    return ["tau_s"], (-dw)[:, :, None]


def _lowpass(pd, y, rate_hz):
    from scipy import signal

    fc = float(pd["bandwidth_hz"])
    if not 0 < fc < rate_hz / 2:
        raise GyroInputError(f"lowpass bandwidth {fc} Hz must be in (0, {rate_hz / 2}) Hz at {rate_hz} Hz")
    b, a = signal.butter(2, fc, fs=rate_hz)
    z0 = signal.lfilter_zi(b, a)
    return np.stack([signal.lfilter(b, a, y[:, i], zi=z0 * y[0, i])[0] for i in range(3)], axis=1)


def _saturate(pd, y, rate_hz):
    r = float(pd["range_rad_s"])
    return np.clip(y, -r, r)


def _quantize(pd, y, rate_hz):
    q = float(pd["lsb_rad_s"])
    return np.round(y / q) * q


def _earth_inverse(pd, inp, t, omega):
    if inp.q_SW_wxyz is None:
        return omega
    return omega - earth_rate_S(float(pd["latitude_rad"]), float(pd["heading_rad"]), inp.q_SW_wxyz)


_C = "correctable"
#: The catalogue, DESIGN.md order. Each entry is the whole definition of that effect.
_CATALOGUE: tuple[Effect, ...] = (
    Effect(
        "bias",
        _C,
        {"b_rad_s": (3,)},
        "additive",
        (),
        term=lambda pd, inp, w: np.asarray(pd["b_rad_s"], float)[None, :],
        regressors=lambda inp, order, t0: diag_design(np.ones(inp.n)[:, None] * np.ones(3)[None, :], "b_rad_s"),
        plausible=1.0,
        description="constant offset; redrawn at every power-up",
    ),
    Effect(
        "bias_thermal",
        _C,
        {"poly_rad_s": (3, "p"), "t0_c": (), "temp_min_c": (), "temp_max_c": ()},
        "additive",
        ("temp",),
        term=lambda pd, inp, w: poly_dT(
            np.asarray(pd["poly_rad_s"], float), clamped_dT(pd, inp._need("temp_c", "bias_thermal"))
        ),
        regressors=lambda inp, order, t0: _poly_design(inp, order, t0, "bias_thermal", "poly_rad_s", False),
        plausible=0.05,
        description="bias polynomial in T − T0 (clamped to the fitted range)",
    ),
    Effect(
        "bias_temp_rate",
        _C,
        {"k_rad_s_per_c_per_s": (3,)},
        "additive",
        ("dtemp",),
        term=lambda pd, inp, w: inp.temp_rate_c_s()[:, None] * np.asarray(pd["k_rad_s_per_c_per_s"])[None, :],
        regressors=lambda inp, order, t0: diag_design(
            inp.temp_rate_c_s()[:, None] * np.ones(3)[None, :], "k_rad_s_per_c_per_s"
        ),
        plausible=1.0,
        description="bias proportional to dT/dt",
    ),
    Effect(
        "bias_ramp",
        _C,
        {"ramp_rad_s2": (3,)},
        "additive",
        ("t",),
        term=lambda pd, inp, w: inp.since_power_up()[:, None] * np.asarray(pd["ramp_rad_s2"])[None, :],
        regressors=lambda inp, order, t0: diag_design(
            inp.since_power_up()[:, None] * np.ones(3)[None, :], "ramp_rad_s2"
        ),
        plausible=1e-2,
        description="bias linear in time since power-up",
    ),
    Effect(
        "scale",
        _C,
        {"s": (3,)},
        "k",
        ("omega",),
        term=lambda pd: np.diag(np.asarray(pd["s"], float)),
        regressors=lambda inp, order, t0: diag_design(inp._need("omega_S_rad_s", "scale"), "s"),
        plausible=0.5,
        description="scale-factor error K_ii = 1 + s_i",
    ),
    Effect(
        "scale_thermal",
        _C,
        {"poly_per_c": (3, "p"), "t0_c": (), "temp_min_c": (), "temp_max_c": ()},
        "scale",
        ("omega", "temp"),
        term=lambda pd, inp, w: poly_dT(
            np.asarray(pd["poly_per_c"], float), clamped_dT(pd, inp._need("temp_c", "scale_thermal"))
        ),
        regressors=lambda inp, order, t0: _poly_design(inp, order, t0, "scale_thermal", "poly_per_c", True),
        plausible=0.01,
        description="scale polynomial in T − T0",
    ),
    Effect(
        "scale_asymmetry",
        _C,
        {"a": (3,)},
        "scale",
        ("omega",),
        term=lambda pd, inp, w: np.sign(w) * np.asarray(pd["a"])[None, :],
        regressors=lambda inp, order, t0: diag_design(np.abs(inp._need("omega_S_rad_s", "scale_asymmetry")), "a"),
        plausible=0.2,
        description="a_i·sign(ω_i)·ω_i",
    ),
    Effect(
        "scale_nonlinearity",
        _C,
        {"s2_s_per_rad": (3,)},
        "scale",
        ("omega",),
        term=lambda pd, inp, w: np.abs(w) * np.asarray(pd["s2_s_per_rad"])[None, :],
        regressors=lambda inp, order, t0: diag_design(
            (lambda w: w * np.abs(w))(inp._need("omega_S_rad_s", "scale_nonlinearity")), "s2_s_per_rad"
        ),
        plausible=0.2,
        description="s2_i·ω_i·|ω_i|",
    ),
    Effect(
        "misalignment",
        _C,
        {"m_rad": (6,)},
        "k",
        ("omega",),
        term=lambda pd: misalignment_matrix(pd["m_rad"]),
        regressors=_misalignment_design,
        plausible=0.2,
        description="off-diagonal K_ij",
    ),
    Effect(
        "g_sensitivity",
        _C,
        {"h_rad_s_per_m_s2": (3, 3)},
        "additive",
        ("f",),
        term=lambda pd, inp, w: rows_times(inp._need("f_S_m_s2", "g_sensitivity"), np.asarray(pd["h_rad_s_per_m_s2"])),
        regressors=_g_design,
        plausible=5e-3,
        description="H·f",
    ),
    Effect(
        "g2_sensitivity",
        _C,
        {"g_rad_s_per_m2_s4": (3, 6)},
        "additive",
        ("f",),
        term=lambda pd, inp, w: rows_times(
            ff_products(inp._need("f_S_m_s2", "g2_sensitivity")), np.asarray(pd["g_rad_s_per_m2_s4"])
        ),
        regressors=_g2_design,
        plausible=1e-3,
        description="G·(f⊗f)",
    ),
    Effect(
        "time_offset",
        _C,
        {"tau_s": ()},
        "rate",
        ("omega", "alpha"),
        term=lambda pd, inp, t, w: time_shift(t, w, float(pd["tau_s"])),
        inverse=lambda pd, inp, t, w: time_shift(t, w, -float(pd["tau_s"])),
        regressors=_time_offset_design,
        plausible=1.0,
        description="ω(t − τ)",
    ),
    Effect(
        "earth_rate",
        _C,
        {"latitude_rad": (), "heading_rad": ()},
        "rate",
        ("q",),
        term=lambda pd, inp, t, w: (
            w + earth_rate_S(float(pd["latitude_rad"]), float(pd["heading_rad"]), inp._need("q_SW_wxyz", "earth_rate"))
        ),
        inverse=_earth_inverse,
        priority=-1,
        description="Earth's rotation seen by the sensor",
    ),
    Effect("quantization", "output", {"lsb_rad_s": ()}, "clip", term=_quantize, description="output in LSB steps"),
    Effect("saturation", "output", {"range_rad_s": ()}, "clip", term=_saturate, description="clipping at ±range"),
    Effect(
        "lowpass",
        "output",
        {"bandwidth_hz": ()},
        "filter",
        term=_lowpass,
        description="on-chip 2nd-order Butterworth low-pass",
    ),
    Effect("arw", "stochastic", {"n_rad_per_sqrt_s": (3,)}, description="white rate noise"),
    Effect("bias_instability", "stochastic", {"b_rad_s": (3,)}, description="flicker bias noise"),
    Effect("rrw", "stochastic", {"k_rad_s_per_sqrt_s": (3,)}, description="rate random walk"),
    Effect("correlated", "stochastic", {"sigma_rad_s": (3,), "tau_c_s": (3,)}, description="Gauss–Markov bias"),
    Effect(
        "vibration",
        "physics",
        {"f_hz": ("n",), "psd_rad2_s2_hz": (3, "n")},
        description="rotor-driven vibration: from the physics (hover), plus an optional shaped part, a Gaussian "
        "disturbance with the one-sided PSD psd_rad2_s2_hz (per axis, (rad/s)²/Hz) on the grid f_hz "
        "(sim.noise.ShapedNoise; gyrocore.flight.synthesis.shaped_params builds it from a vibration spec)",
    ),
)

#: Catalogue name -> :class:`Effect` (DESIGN.md order).
REGISTRY: dict[str, Effect] = {e.name: e for e in _CATALOGUE}

_S = "stochastic"
#: Registered noise terms outside the DESIGN.md catalogue (docs/DESIGN.md "Project notes"): the
#: noise shapes the digital twin finds on real sensors (docs/twin.md). Each is an independent
#: additive noise with its own stream ``noise/<name>`` in the simulator (``sim.gyro``), injected
#: by ``--set`` or a sensor TOML ``[terms."<name>"]`` like a family term; no preset sets them.
_NOISE_TERMS: tuple[Effect, ...] = (
    Effect(
        "arw_lowpass",
        _S,
        {"n_rad_per_sqrt_s": (3,), "bandwidth_hz": ()},
        description="white rate noise of density N (rad/√s, below the corner) generated before the chip's "
        "2nd-order Butterworth low-pass at bandwidth_hz: the filter shapes the noise "
        "(the catalogue's lowpass acts on the signal only; its noise is added after it)",
    ),
    Effect(
        "arw_student",
        _S,
        {"n_rad_per_sqrt_s": (3,), "nu": (3,), "bandwidth_hz": ()},
        defaults={"bandwidth_hz": np.asarray(0.0)},
        description="heavy-tailed white rate noise: Student t with nu > 2 degrees of freedom scaled to the "
        "variance of density N (N²·rate per sample); through the 2nd-order low-pass at "
        "bandwidth_hz when > 0",
    ),
    Effect(
        "angle_white",
        _S,
        {"q_rad": (3,)},
        description="white angle noise (IEEE 952's 'quantization noise' Q, Allan σ² = 3Q²/τ²): an angle "
        "sequence of σ = Q per sample, differentiated (rate = Δθ·rate)",
    ),
)
#: Noise-term name -> :class:`Effect` (registered outside the catalogue; see :data:`_NOISE_TERMS`).
NOISE_TERMS: dict[str, Effect] = {e.name: e for e in _NOISE_TERMS}

#: Canonical effect names, in DESIGN.md order.
EFFECTS: tuple[str, ...] = tuple(REGISTRY)
STOCHASTIC: tuple[str, ...] = tuple(e.name for e in _CATALOGUE if e.kind == "stochastic")
#: Every registered noise term: the catalogue's (:data:`STOCHASTIC`) and :data:`NOISE_TERMS`.
NOISE: tuple[str, ...] = STOCHASTIC + tuple(NOISE_TERMS)
#: Effects with a deterministic formula (correctable + output stage).
DETERMINISTIC: tuple[str, ...] = tuple(e.name for e in _CATALOGUE if e.kind in ("correctable", "output"))
#: Deterministic effects that :func:`correct` removes and :func:`design` can regress (all but
#: the non-invertible output stage: quantization, saturation, lowpass).
CORRECTABLE: tuple[str, ...] = tuple(e.name for e in _CATALOGUE if e.kind == "correctable")
#: Effects with a polynomial of estimator-chosen order (in T − t0_c, clamped to the fitted range).
POLYNOMIAL: tuple[str, ...] = tuple(e.name for e in _CATALOGUE if e.polynomial)
#: The output stage in the order it is applied (filter, then noise, then clip).
OUTPUT_STAGE: tuple[str, ...] = ("lowpass", "saturation", "quantization")


def _unknown(name: str) -> GyroInputError:
    return GyroInputError(
        f"unknown effect '{name}'; known effects: {', '.join(EFFECTS)}; "
        f"noise terms: {', '.join(NOISE_TERMS)}; families: periodic[<f_hz>], step[<t_s>], regressor[<expr>]"
    )


@lru_cache(maxsize=4096)
def _family_effect(name: str) -> Effect:
    parts = family_parts(name)
    if parts is None:
        raise _unknown(name)
    fam, arg = parts
    if fam == "periodic":
        f = parse_float(arg, "the frequency (Hz)", name)
        if not f > 0:
            raise GyroInputError(f"effect '{name}': the frequency must be > 0 Hz, got {arg.strip()}")
        return periodic_effect(f"periodic[{fmt_float(f)}]", f)
    if fam == "step":
        t = parse_float(arg, "the step time (s)", name)
        return step_effect(f"step[{fmt_float(t)}]", t)
    factors = parse_expr(arg, name=name)
    return regressor_effect(f"regressor[{expr_text(factors)}]", factors)


def resolve(name: str) -> Effect:
    """The :class:`Effect` of a catalogue name or a family instance name.

    Family names are canonicalised (``periodic[37.50]`` -> ``periodic[37.5]``,
    ``regressor[omega_z*omega_y]`` -> ``regressor[omega_y*omega_z]``); the returned effect's
    ``name`` is the canonical one. Unknown names or bad arguments -> one-line
    :class:`~gyrocore.errors.GyroInputError`.
    """
    if not isinstance(name, str):
        raise GyroInputError(f"effect name must be a string, got {name!r}")
    e = REGISTRY.get(name)
    if e is not None:
        return e
    key = name.strip()
    if key in REGISTRY:
        return REGISTRY[key]
    if key in NOISE_TERMS:
        return NOISE_TERMS[key]
    return _family_effect(key)


def is_stochastic(name: str) -> bool:
    """Whether ``name`` is a registered noise term (catalogue or :data:`NOISE_TERMS`)."""
    try:
        return resolve(name).kind == "stochastic"
    except GyroInputError:
        return False


def canonical_name(name: str) -> str:
    """The one name of an effect (see :func:`resolve`)."""
    return resolve(name).name


def family_name(family: str, arg: float | str) -> str:
    """The canonical name of a family instance from its argument: ``family_name("periodic", 37.5)``
    -> ``"periodic[37.5]"``, ``family_name("step", 9.47)`` -> ``"step[9.47]"``,
    ``family_name("regressor", "omega_z*omega_y")`` -> ``"regressor[omega_y*omega_z]"``. A number
    is written as the shortest decimal that reads back to it (never an exponent)."""
    text = arg if isinstance(arg, str) else fmt_float(arg)
    return canonical_name(f"{family}[{text}]")


def catalogue_equivalent(term: str, axis) -> str | None:
    """The catalogue effect that already contains a regressor term on ``axis``, or None.

    Parameters
    ----------
    term : str
        A regressor expression (``"omega_x"``, ``"f_y*f_z"``) or a ``regressor[...]`` name.
        ``periodic``/``step`` names have no catalogue equivalent (None).
    axis : {"x", "y", "z"} or {0, 1, 2}
        The measurement axis the term enters.

    Returns
    -------
    str or None
        The effect one of whose design columns (with its constant companion: ``bias`` for the
        thermal bias polynomial, ``scale`` for the thermal scale polynomial) is exactly the
        term on that axis: ``scale`` (ω_i on axis i), ``misalignment`` (ω_j, j ≠ i),
        ``g_sensitivity`` (f_j), ``g2_sensitivity`` (f_j·f_k), ``bias_thermal`` (T, T², T³:
        the polynomial in T − T0), ``scale_thermal`` (ω_i·T, ω_i·T² on axis i),
        ``bias_temp_rate`` (dT/dt), ``bias_ramp`` (t); else None. Not equivalent:
        ``alpha_i`` alone (a per-axis delay; the catalogue's ``time_offset`` is one τ shared
        by the three axes, a single column across them) and ``omega_i^2`` (even in ω;
        ``scale_nonlinearity``'s ω|ω| is odd).
    """
    i = (
        axis
        if isinstance(axis, (int, np.integer))
        else "xyz".index(str(axis))
        if str(axis) in ("x", "y", "z")
        else None
    )
    if i is None or not 0 <= int(i) <= 2:
        raise GyroInputError(f"axis must be x, y, z or 0..2, got {axis!r}")
    ax = "xyz"[int(i)]
    if is_family(term):
        eff = resolve(term)
        if eff.family != "regressor":
            return None
        factors = eff.arg
    elif isinstance(term, str) and term.strip() in REGISTRY:
        return None
    else:
        factors = parse_expr(term)
    d = dict(factors)
    deg = sum(d.values())
    sigs = set(d)
    if deg == 1:
        (s,) = sigs
        if s.startswith("omega_"):
            return "scale" if s[-1] == ax else "misalignment"
        if s.startswith("alpha_"):
            return None
        if s.startswith("f_"):
            return "g_sensitivity"
        return {"temp_c": "bias_thermal", "dtemp_dt": "bias_temp_rate", "t": "bias_ramp"}[s]
    if all(s.startswith("f_") for s in sigs) and deg == 2:
        return "g2_sensitivity"
    if sigs == {"temp_c"}:
        return "bias_thermal"
    if sigs == {f"omega_{ax}", "temp_c"} and d[f"omega_{ax}"] == 1:
        return "scale_thermal"
    return None


def ordered_effects(names: Iterable[str]) -> list[str]:
    """Canonical names in model order: catalogue (DESIGN.md order), then family terms sorted."""
    names = [canonical_name(n) for n in names]
    cat = [e for e in EFFECTS if e in names]
    return cat + sorted(n for n in dict.fromkeys(names) if n not in REGISTRY)


class _SchemaView(dict):
    """``PARAM_SCHEMA``: catalogue name -> schema; family names resolve on lookup."""

    def __missing__(self, key):
        try:
            return dict(resolve(key).schema)
        except GyroInputError:
            raise KeyError(key) from None

    def __contains__(self, key) -> bool:
        if dict.__contains__(self, key):
            return True
        try:
            resolve(key)
        except (GyroInputError, TypeError):
            return False
        return True

    def get(self, key, default=None):
        try:
            return self[key]
        except KeyError:
            return default


#: Parameter names and shapes per effect (SI units in the names). ``p`` is a polynomial
#: order chosen by the estimator; thermal polynomials are in (T − t0_c) with powers 1..p
#: (the constant term belongs to ``bias`` / ``scale``). Iterates the catalogue; family names
#: (``periodic[37.5]``...) are looked up through :func:`resolve`.
PARAM_SCHEMA: dict[str, dict[str, tuple]] = _SchemaView({e.name: dict(e.schema) for e in _CATALOGUE})


# ---------------------------------------------------------------------------- names, parameters
def check_effect_names(names) -> list[str]:
    """Validate effect names; returns their canonical names as a list. Unknown -> one-line error."""
    out = []
    for n in names:
        if not isinstance(n, str):
            raise GyroInputError(f"effect name must be a string, got {n!r}")
        n = n.strip()
        if not n:
            continue
        out.append(canonical_name(n))
    return out


def validate_params(params: Params) -> dict[str, dict[str, np.ndarray]]:
    """Check names and shapes against the registry; returns float arrays under canonical names."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for eff_name, pdict in params.items():
        effect = resolve(eff_name)
        eff = effect.name
        if eff in out:
            raise GyroInputError(f"effect {eff} is given twice ({eff_name!r} is another spelling of it)")
        schema = effect.schema
        out[eff] = {}
        if effect.kind == "physics" and not pdict:
            continue  # vibration from the physics alone: no shaped part
        for pname, shape in schema.items():
            if pname not in pdict:
                raise GyroInputError(f"effect {eff}: missing parameter {pname}")
            v = np.asarray(pdict[pname], float)
            if len(v.shape) != len(shape) or any(s not in ("p", "n") and s != d for s, d in zip(shape, v.shape)):
                raise GyroInputError(f"effect {eff}: parameter {pname} has shape {v.shape}, expected {shape}")
            if not np.all(np.isfinite(v)):
                raise GyroInputError(f"effect {eff}: parameter {pname} is not finite")
            out[eff][pname] = v
        n_lens = {d for pn, sh in schema.items() for s, d in zip(sh, out[eff][pn].shape) if s == "n"}
        if len(n_lens) > 1:
            raise GyroInputError(f"effect {eff}: the parameters' 'n' dimensions differ ({sorted(n_lens)})")
        for pname, v in pdict.items():
            if pname not in schema:
                out[eff][pname] = np.asarray(v, float)  # extra info (e.g. turn-on sigma) kept
    return out


def _order_key(name: str) -> tuple:
    return (EFFECTS.index(name), "") if name in REGISTRY else (len(EFFECTS), name)


def _stage(params: Params, stage: str) -> list[tuple[Effect, Mapping]]:
    """(effect, its parameters) of the given stage, in model order (catalogue, then families by name)."""
    found = [(resolve(k), pd) for k, pd in params.items()]
    found = [(e, pd) for e, pd in found if e.stage == stage]
    return sorted(found, key=lambda ep: (ep[0].priority, _order_key(ep[0].name)))


def k_matrix(params: Params) -> np.ndarray:
    """Constant part of K: I + diag(s) + misalignment, 3×3."""
    K = np.eye(3)
    for eff, pd in _stage(params, "k"):
        K = K + eff.term(pd)
    return K


# ---------------------------------------------------------------------------- forward
def _additive(params: Params, inp: ModelInputs, omega: np.ndarray | None = None, *, which: str = "all") -> np.ndarray:
    """Additive terms b(T, t) + H·f + G·(f⊗f) + family terms, shape (N, 3).

    ``which``: ``"all"``, ``"static"`` (terms that do not depend on ω) or ``"rate"`` (those
    that do: regressors of ω or α, evaluated at ``omega``).
    """
    out = np.zeros((inp.n, 3))
    for eff, pd in _stage(params, "additive"):
        dyn = "omega" in eff.inputs or "alpha" in eff.inputs
        if which == "static" and dyn or which == "rate" and not dyn:
            continue
        out += eff.term(pd, inp, omega)
    return out


def _has_rate_additive(params: Params) -> bool:
    return any("omega" in e.inputs or "alpha" in e.inputs for e, _ in _stage(params, "additive"))


def _scale_diag(params: Params, inp: ModelInputs, omega: np.ndarray) -> np.ndarray:
    """Rate- and temperature-dependent diagonal scale error (beyond I), shape (N, 3)."""
    d = np.zeros_like(omega)
    for eff, pd in _stage(params, "scale"):
        d += eff.term(pd, inp, omega)
    return d


def deterministic(params: Params, inp: ModelInputs) -> np.ndarray:
    """The deterministic measurement before the output stage, rad/s, shape (N, 3).

    K(T)·ω(t − τ) + b(T, t) + H·f + G·(f⊗f) + nonlinear(ω) + family terms, with ω the
    inertial rate (world-relative truth plus ``earth_rate`` when present). ``scale_asymmetry``
    is a_i·sign(ω_i)·ω_i and ``scale_nonlinearity`` is s2_i·ω_i·|ω_i| (DESIGN.md table).
    Family terms that depend on the rate see the same ω as K (after Earth rate and delay).
    """
    params = validate_params(params)
    omega = inp._need("omega_S_rad_s", "deterministic model").copy()
    t = np.asarray(inp.t_s, float)
    for eff, pd in _stage(params, "rate"):
        omega = eff.term(pd, inp, t, omega)
    K = k_matrix(params)
    y = rows_times(omega, K) + _scale_diag(params, inp, omega) * omega
    return y + _additive(params, inp, omega)


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
    the nearest LSB; ``saturation`` clips to ±range. Order: :data:`OUTPUT_STAGE`, the noise
    added after the ``filter`` stage.
    """
    y = np.asarray(x, float)
    for name in OUTPUT_STAGE:
        eff = REGISTRY[name]
        if eff.stage == "filter" and name in params:
            y = eff.term(params[name], y, rate_hz)
    if noise_rad_s is not None:
        y = y + noise_rad_s
    for name in OUTPUT_STAGE:
        eff = REGISTRY[name]
        if eff.stage == "clip" and name in params:
            y = eff.term(params[name], y, rate_hz)
    return y


# ---------------------------------------------------------------------------- inverse
#: Half-window of the Savitzky–Golay rate derivative used by :func:`correct` for ``alpha_*`` terms, s.
ALPHA_HALF_WINDOW_S = 0.01


def _alpha_half_rows(dt_s: float) -> int:
    return max(2, int(round(ALPHA_HALF_WINDOW_S / dt_s)))


def context_rows(params: Params, dt_s: float, *, iterations: int = 4) -> int:
    """Neighbour rows :func:`correct` reads on each side of a sample (for chunked correction).

    Central differences reach 1 row, the time-offset shift |τ|/dt rows, and every fixed-point
    iteration over an ``alpha_*`` term one Savitzky–Golay half-window more.
    """
    reach = 2
    for e, pd in params.items():
        eff = resolve(e)
        if eff.name == "time_offset":
            reach += int(math.ceil(abs(float(np.asarray(pd["tau_s"]))) / dt_s)) + 1
        if "alpha" in eff.inputs and eff.stage == "additive":
            reach += (int(iterations) + 1) * (_alpha_half_rows(dt_s) + 1)
    return reach


def _smooth_derivative(t: np.ndarray, w: np.ndarray) -> np.ndarray:
    """dω/dt of a measured rate (N, 3): quadratic Savitzky–Golay derivative (scipy), ±ALPHA_HALF_WINDOW_S.

    The half-width m (samples) comes from the median step; the derivative per sample is
    divided by the local step.
    """
    from scipy.signal import savgol_filter

    n = w.shape[0]
    if n < 5:
        return np.gradient(w, t, axis=0) if n > 1 else np.zeros_like(w)
    dt = float(np.median(np.diff(t)))
    m = _alpha_half_rows(dt)
    win = min(2 * m + 1, n if n % 2 else n - 1)
    # derivative per sample, divided by the local step (central difference of t): the same
    # value for a sample whatever chunk of the record it is computed in
    return savgol_filter(w, win, 2, deriv=1, delta=1.0, axis=0, mode="interp") / np.gradient(t)[:, None]


def correct(params: Params, gyro_rad_s: np.ndarray, inp: ModelInputs, *, iterations: int = 4) -> np.ndarray:
    """Remove the deterministic effects in ``params`` from a measurement.

    Returns the estimated world-relative rate ω, rad/s, shape (N, 3) — the inverse of
    :func:`deterministic` (``earth_rate`` is subtracted when present and the attitude is
    known). Generic inverse: the additive terms that do not depend on ω are subtracted, K is
    inverted, and the rate-dependent terms (scale_thermal/asymmetry/nonlinearity and
    family regressors of ω or α, evaluated at the current estimate) by fixed-point iteration,
    which converges because they are small (|a|, |s2·ω| ≪ 1). A term of the rate derivative
    (``alpha_*``) is evaluated from the estimate's Savitzky–Golay derivative (quadratic, ±10 ms
    half-window, at least ±2 samples; :data:`ALPHA_HALF_WINDOW_S`), because the central
    difference of a measured rate amplifies its noise by √2/dt: with white noise σ the
    derivative's sd is σ/dt·√(3/(m(m+1)(2m+1))) for half-width m (0.036·σ/dt at m = 10).
    ``rate``-stage effects
    (time_offset, earth_rate) use their own inverse, in reverse order. ``quantization``,
    ``saturation`` and ``lowpass`` are not invertible and are ignored; stochastic effects
    are not removed.
    """
    params = validate_params(params)
    y = np.asarray(gyro_rad_s, float)
    rate_add = _has_rate_additive(params)
    if rate_add and any("alpha" in e.inputs for e, _ in _stage(params, "additive")):
        base_inp = inp

        def inp_at(w):
            return _replace(base_inp, alpha_S_rad_s2=_smooth_derivative(np.asarray(base_inp.t_s, float), w))
    else:

        def inp_at(w):
            return inp

    z = y - (_additive(params, inp, which="static") if rate_add else _additive(params, inp))
    Kinv = np.linalg.inv(k_matrix(params))
    omega = z @ Kinv.T
    if rate_add:
        for _ in range(iterations):
            omega = (
                z - _scale_diag(params, inp, omega) * omega - _additive(params, inp_at(omega), omega, which="rate")
            ) @ Kinv.T
    elif _stage(params, "scale"):
        for _ in range(iterations):
            omega = (z - _scale_diag(params, inp, omega) * omega) @ Kinv.T
    t = np.asarray(inp.t_s, float)
    for eff, pd in reversed(_stage(params, "rate")):
        omega = eff.inverse(pd, inp, t, omega)
    return omega


# ---------------------------------------------------------------------------- regressors
def design(effect: str, inp: ModelInputs, *, order: int = 1, t0_c: float | None = None) -> tuple[list[str], np.ndarray]:
    """Regressors of one effect: ∂(measurement)/∂(parameters), linearised at zero error.

    Parameters
    ----------
    effect : str
        Name of a fittable deterministic effect (catalogue or family; :func:`resolve`).
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
    return resolve(effect).design(inp, order=order, t0_c=t0_c)


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
