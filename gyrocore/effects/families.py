"""The one grammar of the open effect families: ``periodic[<f_hz>]``, ``step[<t_s>]``, ``regressor[<expr>]``.

A family instance's name carries its definition (DESIGN.md "Effects outside the catalogue"):
:func:`parse_expr` reads a regressor expression over :data:`SIGNALS` (products ``a*b``, powers
``a^k``, total degree ≤ :data:`MAX_DEGREE`), :func:`canonical_expr` writes its one name,
:func:`expr_values` evaluates it on the data, and :func:`periodic_effect`, :func:`step_effect`,
:func:`regressor_effect` build the :class:`~gyrocore.effects.effect.Effect` of an instance.
:func:`gyrocore.effects.registry.resolve` resolves any name (catalogue or family) with these.
"""

from __future__ import annotations

import math
import re

import numpy as np

from gyrocore.effects.effect import Effect, ModelInputs, diag_design
from gyrocore.errors import GyroInputError

#: Signal names of ``regressor[<expr>]`` (DESIGN.md "Effects outside the catalogue"), in the
#: canonical order of a product: reference rate ω (S, rad/s), its time derivative α (rad/s²),
#: specific force f (m/s²), temperature (°C), its rate (°C/s), time since power-up (s).
SIGNALS: tuple[str, ...] = (
    "omega_x",
    "omega_y",
    "omega_z",
    "alpha_x",
    "alpha_y",
    "alpha_z",
    "f_x",
    "f_y",
    "f_z",
    "temp_c",
    "dtemp_dt",
    "t",
)
_SIGNAL_INPUT = {"omega": "omega", "alpha": "alpha", "f": "f", "temp_c": "temp", "dtemp_dt": "dtemp", "t": "t"}
#: Highest total degree of a regressor expression.
MAX_DEGREE = 3
_FAMILY_RE = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*\[(.*)\]\s*$", re.S)
_FACTOR_RE = re.compile(r"^([a-z_]+)(?:\^([0-9]+))?$")


def fmt_float(x: float) -> str:
    """Shortest round-trip decimal, never scientific, no trailing '.0' (37.5, 50, 0.001)."""
    s = np.format_float_positional(float(x), trim="-")
    return "0" if s in ("-0", "0") else s


def parse_float(text: str, what: str, name: str) -> float:
    t = text.strip()
    if not re.fullmatch(r"[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?", t):
        raise GyroInputError(f"effect '{name}': {what} must be a decimal number, got '{text}'")
    v = float(t)
    if not math.isfinite(v):
        raise GyroInputError(f"effect '{name}': {what} must be finite, got '{text}'")
    return v


def parse_expr(text: str, *, name: str | None = None) -> tuple[tuple[str, int], ...]:
    """Parse a regressor expression into canonical factors ``((signal, power), ...)``.

    Grammar (strict): ``factor ('*' factor)*`` with ``factor = SIGNAL ['^' k]``, SIGNAL one of
    :data:`SIGNALS`, k an integer ≥ 1, total degree ≤ :data:`MAX_DEGREE`; spaces allowed
    around tokens. Repeated signals are merged (``omega_x*omega_x`` = ``omega_x^2``) and the
    factors sorted in :data:`SIGNALS` order, so one term has one form.

    Raises
    ------
    GyroInputError
        One line naming what is wrong.
    """
    label = name or f"regressor[{text}]"
    parts = [p.strip() for p in str(text).split("*")]
    if not parts or any(not p for p in parts):
        raise GyroInputError(
            f"effect '{label}': expected a product of signals like omega_y*omega_z or f_x^2 "
            f"(signals: {', '.join(SIGNALS)})"
        )
    powers: dict[str, int] = {}
    for p in parts:
        p = re.sub(r"\s*\^\s*", "^", p)
        m = _FACTOR_RE.match(p)
        if not m:
            raise GyroInputError(
                f"effect '{label}': cannot read '{p}' (a signal, optionally ^k; signals: {', '.join(SIGNALS)})"
            )
        sig, k = m.group(1), int(m.group(2) or 1)
        if sig not in SIGNALS:
            raise GyroInputError(f"effect '{label}': unknown signal '{sig}'; signals: {', '.join(SIGNALS)}")
        if k < 1:
            raise GyroInputError(f"effect '{label}': power of {sig} must be >= 1, got {k}")
        powers[sig] = powers.get(sig, 0) + k
    deg = sum(powers.values())
    if deg > MAX_DEGREE:
        raise GyroInputError(f"effect '{label}': degree {deg} > {MAX_DEGREE}")
    return tuple((s, powers[s]) for s in SIGNALS if s in powers)


def expr_text(factors: tuple[tuple[str, int], ...]) -> str:
    return "*".join(s if k == 1 else f"{s}^{k}" for s, k in factors)


def canonical_expr(text: str) -> str:
    """The one form of a regressor expression: ``"omega_z*omega_y"`` -> ``"omega_y*omega_z"``,
    ``"f_x*f_x"`` -> ``"f_x^2"`` (see :func:`parse_expr`)."""
    return expr_text(parse_expr(text))


def _signal(sig: str, inp: ModelInputs, omega: np.ndarray | None, effect: str) -> np.ndarray:
    """Value of one signal, shape (N,). ``omega`` (N, 3) overrides ``inp.omega_S_rad_s``.
    The derivatives (``alpha_*``, ``dtemp_dt``) of a single sample are 0."""
    one = inp.n < 2
    if sig.startswith(("omega_", "alpha_")):
        j = "xyz".index(sig[-1])
        if sig.startswith("alpha_") and inp.alpha_S_rad_s2 is not None:
            return np.asarray(inp.alpha_S_rad_s2, float)[:, j]
        w = inp._need("omega_S_rad_s", effect) if omega is None else omega
        if sig.startswith("omega_"):
            return w[:, j]
        return np.zeros(inp.n) if one else np.gradient(w[:, j], np.asarray(inp.t_s, float))
    if sig.startswith("f_"):
        return inp._need("f_S_m_s2", effect)[:, "xyz".index(sig[-1])]
    if sig == "temp_c":
        return inp._need("temp_c", effect)
    if sig == "dtemp_dt":
        # the inputs' own rate: a stream's one-sample inputs carry it from the temperature trajectory
        return inp.temp_rate_c_s(effect)
    if sig == "t":
        return inp.since_power_up()
    raise GyroInputError(f"unknown signal {sig}")  # pragma: no cover (parse_expr checks)


def _expr_value(factors, inp: ModelInputs, omega, effect: str, cache: dict | None = None) -> np.ndarray:
    """Π signal^k, shape (N,), by repeated multiplication in canonical order; ``cache`` (a dict
    kept by the caller for one ``inp``) holds each signal's values once."""
    g = None
    for sig, k in factors:
        if cache is None:
            s = _signal(sig, inp, omega, effect)
        elif sig in cache:
            s = cache[sig]
        else:
            s = cache[sig] = _signal(sig, inp, omega, effect)
        pw = s
        for _ in range(k - 1):
            pw = pw * s
        g = pw if g is None else g * pw
    return np.asarray(g, float)


def expr_values(expr: str, inp: ModelInputs, *, cache: dict | None = None) -> np.ndarray:
    """Per-sample value of a regressor expression (``"omega_y*omega_z"``, ``"t"``), shape (N,),
    in the SI units of its signals: the signal ``g`` of ``regressor[expr]``.

    Parameters
    ----------
    expr : str
        A regressor expression (:func:`parse_expr`).
    inp : ModelInputs
    cache : dict, optional
        Signal values already computed on ``inp`` (filled in here; pass one dict per ``inp``
        when evaluating many expressions on the same inputs).

    Raises
    ------
    GyroInputError
        A bad expression, or a signal whose input ``inp`` lacks.
    """
    return _expr_value(parse_expr(expr), inp, None, f"regressor[{expr}]", cache)


def periodic_effect(name: str, f_hz: float) -> Effect:
    w = 2.0 * math.pi * f_hz

    def cs(inp):
        ph = w * np.asarray(inp.t_s, float)
        return np.cos(ph), np.sin(ph)

    def term(pd, inp, omega):
        c, s = cs(inp)
        return (
            c[:, None] * np.asarray(pd["a_cos_rad_s"], float)[None, :]
            + s[:, None] * np.asarray(pd["a_sin_rad_s"], float)[None, :]
        )

    def regs(inp, order, t0):
        c, s = cs(inp)
        A = np.zeros((inp.n, 3, 6))
        for i in range(3):
            A[:, i, i] = c
            A[:, i, 3 + i] = s
        return [f"a_cos_rad_s[{i}]" for i in range(3)] + [f"a_sin_rad_s[{i}]" for i in range(3)], A

    return Effect(
        name,
        "correctable",
        {"a_cos_rad_s": (3,), "a_sin_rad_s": (3,)},
        "additive",
        ("t",),
        term=term,
        regressors=regs,
        family="periodic",
        arg=f_hz,
        plausible=1.0,
        defaults={"a_cos_rad_s": np.zeros(3), "a_sin_rad_s": np.zeros(3)},
        description=f"a_cos·cos(2π·{fmt_float(f_hz)} Hz·t_s) + a_sin·sin(…) per axis",
    )


def step_effect(name: str, t_step_s: float) -> Effect:
    def g(inp):
        return (np.asarray(inp.t_s, float) >= t_step_s).astype(float)

    def term(pd, inp, omega):
        return g(inp)[:, None] * np.asarray(pd["size_rad_s"], float)[None, :]

    return Effect(
        name,
        "correctable",
        {"size_rad_s": (3,)},
        "additive",
        ("t",),
        term=term,
        regressors=lambda inp, order, t0: diag_design(g(inp)[:, None] * np.ones(3)[None, :], "size_rad_s"),
        family="step",
        arg=t_step_s,
        plausible=1.0,
        defaults={"size_rad_s": np.zeros(3)},
        description=f"bias step of size_rad_s at t_s ≥ {fmt_float(t_step_s)} s",
    )


def regressor_effect(name: str, factors) -> Effect:
    inputs = tuple(
        dict.fromkeys(_SIGNAL_INPUT[s.rsplit("_", 1)[0] if s[-2:] in ("_x", "_y", "_z") else s] for s, _ in factors)
    )

    def term(pd, inp, omega):
        return _expr_value(factors, inp, omega, name)[:, None] * np.asarray(pd["coef"], float)[None, :]

    def regs(inp, order, t0):
        g = _expr_value(factors, inp, None, name)
        return diag_design(g[:, None] * np.ones(3)[None, :], "coef")

    return Effect(
        name,
        "correctable",
        {"coef": (3,)},
        "additive",
        inputs,
        term=term,
        regressors=regs,
        family="regressor",
        arg=factors,
        defaults={"coef": np.zeros(3)},
        description=f"coef (rad/s per unit) × {expr_text(factors)} per axis",
    )


#: Open families: family name -> (argument parser -> canonical text and value, Effect factory).
FAMILIES: dict[str, str] = {
    "periodic": "periodic[<f_hz>]: a_cos_rad_s (3,), a_sin_rad_s (3,)",
    "step": "step[<t_s>]: size_rad_s (3,)",
    "regressor": "regressor[<expr>]: coef (3,); expr over " + ", ".join(SIGNALS) + " with * and ^k",
}


def family_parts(name: str):
    m = _FAMILY_RE.match(name)
    if not m or m.group(1) not in FAMILIES:
        return None
    return m.group(1), m.group(2)


def is_family(name: str) -> bool:
    """Whether ``name`` has the form of a family instance (``periodic[...]`` etc.)."""
    return isinstance(name, str) and family_parts(name) is not None
