"""Open search: what the residual still holds once no catalogue effect explains it.

After the catalogue candidates of :mod:`gyrocore.loop.loop`, three detectors describe effects
outside the catalogue (DESIGN.md "Effects outside the catalogue"), each under the loop's
family-wise error control (a weighted Holm/Bonferroni split of α, see :data:`ALPHA_SHARE`):

* **Regressor library** (:func:`library_terms`, :func:`screen_library`): signals built from
  the data — reference rate ``omega_*`` (S, rad/s), its derivative ``alpha_*`` (rad/s²),
  specific force ``f_*`` (m/s²), ``temp_c``, ``dtemp_dt`` (°C/s), ``t`` (s since the start)
  — and their products and squares (degree 2, across axes), each on each gyro axis. A term
  that a catalogue effect already spans (:func:`gyrocore.effects.registry.catalogue_equivalent`: ``omega_y`` on x is
  ``misalignment``, ``f_x*f_z`` is ``g2_sensitivity``, ``t`` is ``bias_ramp`` ...) is not in
  the library: it was tested under its catalogue name; nor is a product that is numerically
  one of its factors on the recording (:func:`collinear_simpler`: ``f_x*t`` in a still log is
  the ramp ``t``). Selection is **forward stepwise on
  the same HAC statistics as the catalogue**: every column is screened by a score (Lagrange
  multiplier) test — the column is projected off the current model (Frisch–Waugh–Lovell),
  its inner product with the residual is referred to its variance under the residual's
  autocovariance model (:func:`gyrocore.calib.covariance.residual_autocov_model`: short lags, a
  Gauss–Markov tail and a flicker/low-frequency component) — with a Bonferroni threshold
  over the library; the winner is then refitted jointly and Wald-tested on the HAC
  covariance exactly as a catalogue candidate, and must pass the blocked out-of-sample guard.
  Why stepwise and not a LASSO path: a LASSO path has no p-value that survives the selection
  (post-selection inference would need the polyhedral lemma under white noise, which these
  residuals are not), whereas the stepwise screen keeps an honest Bonferroni bound over the
  library at every step, with the same coloured-noise statistic the catalogue uses, and the
  refit is unpenalised (no shrinkage bias in the reported coefficient).
* **Narrow-band lines** in the *sample-level* residual: :mod:`gyrocore.loop.lines`.
* **Bias steps**: :mod:`gyrocore.loop.bias_step`.

Each described term is a registered effect family (BRIEFING contract):
``regressor[<expr>]`` (``coef`` (3,)), ``periodic[<f_hz>]`` (``a_cos_rad_s``, ``a_sin_rad_s``
(3,)), ``step[<t_s>]`` (``size_rad_s`` (3,)); their grammar, names, values and regressors are
the registry's (:func:`gyrocore.effects.registry.resolve`, :func:`~gyrocore.effects.registry.family_name`,
:func:`~gyrocore.effects.registry.expr_values`, :func:`~gyrocore.effects.registry.design`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import stats

from gyrocore.calib import covariance
from gyrocore.errors import GyroInputError
from gyrocore.effects import registry as E

from .projection import project_off, weighted_design, weighted_residual

__all__ = [
    "ALPHA_SHARE",
    "Unexplained",
    "collinear_simpler",
    "library_terms",
    "screen_library",
]

#: Share of the family-wise α: the catalogue candidates get one half (split equally among
#: them at each step, Holm), the open search the other half, one sixth of α each for the
#: regressor library (Bonferroni over its terms), lines (over axes and frequencies) and steps.
#: A weighted Bonferroni/Holm split: under the complete null P(any false claim) ≤ Σ shares·α = α.
ALPHA_SHARE = {"catalogue": 0.5, "regressor": 1.0 / 6, "periodic": 1.0 / 6, "step": 1.0 / 6}


# ---------------------------------------------------------------------------- terms
def round_frequency(f_hz: float) -> float:
    """A line's frequency as carried in its name: 1 µHz resolution (a phase error below
    2π·0.5e-6·3600 s = 0.011 rad over an hour)."""
    return round(float(f_hz), 6)


def column_axis(pname: str) -> int:
    """Axis of a family parameter column name (``coef[1]`` -> 1)."""
    return int(pname[pname.index("[") + 1 : pname.index("]")])


def library_terms(inp, *, kind: str, chunks=None) -> list[str]:
    """The degree-≤2 library of terms the data support (see module docstring).

    Rate signals need a time-resolved rate (``rate``/``attitude`` references, not ``still``);
    temperature and specific-force signals need their columns; a signal constant over the
    record (zero rate, constant temperature) is left out. ``chunks`` (optional, long or
    on-disk records): an iterable of (a, b, lo, inputs of lo:hi) windows covering the record
    (:meth:`gyrocore.loop.residual.Residual.iter_inputs`, one neighbour on each side for the
    derivatives); the signals are then checked window by window (same decision: all finite,
    max − min > 0).
    """
    cands = []
    for s in E.SIGNALS:
        if s[:6] in ("omega_", "alpha_") and (kind == "still" or inp.omega_S_rad_s is None):
            continue
        if s.startswith("f_") and inp.f_S_m_s2 is None:
            continue
        if s in ("temp_c", "dtemp_dt") and inp.temp_c is None:
            continue
        cands.append(s)
    avail = []
    if chunks is not None:
        lo_v = {s: np.inf for s in cands}
        hi_v = {s: -np.inf for s in cands}
        bad: set = set()
        for a, b, lo, sub in chunks:
            cache: dict = {}
            for s in cands:
                if s in bad:
                    continue
                try:
                    v = E.expr_values(s, sub, cache=cache)[a - lo : b - lo]
                except GyroInputError:
                    bad.add(s)
                    continue
                if not np.all(np.isfinite(v)):
                    bad.add(s)
                    continue
                lo_v[s] = min(lo_v[s], float(np.min(v)))
                hi_v[s] = max(hi_v[s], float(np.max(v)))
        avail = [s for s in cands if s not in bad and hi_v[s] - lo_v[s] > 0]
    for s in cands if chunks is None else ():
        try:
            v = E.expr_values(s, inp)
        except GyroInputError:
            continue
        if not np.all(np.isfinite(v)) or np.ptp(v) <= 0:
            continue
        avail.append(s)
    terms = list(avail)
    for j, a in enumerate(avail):
        for b in avail[j:]:
            terms.append(E.canonical_expr(f"{a}*{b}"))
    return terms


# ---------------------------------------------------------------------------- findings
@dataclass(frozen=True)
class Unexplained:
    """One effect outside the catalogue, described and added to the model.

    Attributes
    ----------
    kind : {"regressor", "periodic", "step"}
    axis : str
        "x", "y" or "z" (for a step: the axis with the largest size/standard error).
    effect : str
        The registered family instance added to the model (``regressor[omega_x*omega_y]``).
    fields : dict
        The DESIGN.md extra keys: ``term``/``coef`` (regressor, coef in SI per unit of the
        term), ``frequency_hz``/``amplitude_rad_s`` (periodic), ``t_s``/``size_rad_s`` (3,)
        (step).
    evidence : dict
        Test statistic, p-value (log10), threshold, out-of-sample reduction, ...
    residual_rms_before_rad_s, residual_rms_after_rad_s : float
        Window residual RMS (regressor, step) or the sample-level residual RMS of the axis
        (periodic; ``evidence["residual"]`` says which), rad/s.
    attitude_error_before_deg, attitude_error_after_deg : float
    """

    kind: str
    axis: str
    effect: str
    fields: dict
    evidence: dict
    residual_rms_before_rad_s: float
    residual_rms_after_rad_s: float
    attitude_error_before_deg: float = float("nan")
    attitude_error_after_deg: float = float("nan")

    def to_json(self) -> dict:
        d = {"kind": self.kind, "axis": self.axis}
        d.update(self.fields)
        d.update(
            {
                "effect": self.effect,
                "evidence": self.evidence,
                "residual_rms_before_rad_s": self.residual_rms_before_rad_s,
                "residual_rms_after_rad_s": self.residual_rms_after_rad_s,
                "attitude_error_before_deg": self.attitude_error_before_deg,
                "attitude_error_after_deg": self.attitude_error_after_deg,
            }
        )
        return d


# ---------------------------------------------------------------------------- regressor library
def library_windows(res, terms: Sequence[str]) -> np.ndarray:
    """Window regressors of the library: (M, 3, 3·T), column 3·k + i = term k on gyro axis i.

    Computed per term (and in sample chunks for long records without rotation), so at most
    one term's per-sample values are held at once.
    """
    inp = res.inputs
    n, M = inp.n, res.m
    T = len(terms)
    out = np.zeros((M, 3, 3 * T))
    if res.R_GS is None:
        # no rotation: the window operator is a scalar window mean per term
        t = np.asarray(inp.t_s, float)
        dt = np.diff(t)
        need = np.union1d(res.win_start, res.win_stop)
        Cn = np.zeros((need.size, T))
        carry = np.zeros(T)
        # chunks with a one-sample overlap each side (derivatives by central differences), of
        # at most ~32 MB of term values
        chunk = int(max(4096, min(res.chunk, 4_000_000 // max(T, 1))))
        for k0 in range(0, n - 1, chunk):
            k1 = min(k0 + chunk, n - 1)
            lo, hi = max(k0, 0), min(k1 + 2, n)  # samples k0 .. k1+1 (derivative neighbours)
            sub = res.input_rows(lo, hi) if hasattr(res, "input_rows") else _slice_inputs(inp, lo, hi)
            cache: dict = {}
            V = np.empty((k1 - k0, T))
            for j, term in enumerate(terms):
                V[:, j] = E.expr_values(term, sub, cache=cache)[k0 + 1 - lo : k1 + 1 - lo]
            V *= dt[k0:k1, None]
            np.cumsum(V, axis=0, out=V)
            sel = (need > k0) & (need <= k1)
            Cn[sel] = carry + V[need[sel] - k0 - 1]
            carry = carry + V[-1]
        pos = {int(j): r for r, j in enumerate(need)}
        a = Cn[[pos[int(j)] for j in res.win_start]]
        b = Cn[[pos[int(j)] for j in res.win_stop]]
        mean = (b - a) / res.duration_s[:, None]
        for k in range(T):
            for i in range(3):
                out[:, i, 3 * k + i] = mean[:, k]
        return out
    cache = {}
    for k, term in enumerate(terms):
        g = E.expr_values(term, inp, cache=cache)
        A = np.zeros((n, 3, 3))
        for i in range(3):
            A[:, i, i] = g
        out[:, :, 3 * k : 3 * k + 3] = res.window_mean(A)
    return out


def _slice_inputs(inp, lo: int, hi: int):
    def cut(v):
        return None if v is None else np.asarray(v)[lo:hi]

    return E.ModelInputs(
        t_s=np.asarray(inp.t_s)[lo:hi],
        omega_S_rad_s=cut(inp.omega_S_rad_s),
        f_S_m_s2=cut(inp.f_S_m_s2),
        temp_c=cut(inp.temp_c),
        q_SW_wxyz=cut(inp.q_SW_wxyz),
        t_since_power_up_s=inp.since_power_up()[lo:hi],
    )


#: A product term whose window column, projected off the current model, has less than this
#: fraction of its (weighted) norm² outside the span of one of its factors' columns is that
#: factor in disguise on this recording (``f_x*t`` on a still log, where f_x is constant, is
#: a ramp ``t``). With ρ² = 1 − δ the score statistic of the product is
#: z_ab = ρ·z_a + √δ·z_r (z_r ⟂ z_a, N(0, 1) under the null of the rest), so at δ = 0.01 its
#: own direction adds at most 0.1 σ to a score that is ≥ 0.995 of the factor's: any
#: detection of the product is a detection of the factor.
COLLINEAR_DELTA = 0.01


def collinear_simpler(
    res, X0: np.ndarray, sigma: np.ndarray, terms: Sequence[str], Xlib: np.ndarray | None = None
) -> dict:
    """Product terms that are numerically one of their factors on this recording.

    Parameters
    ----------
    res : Residual
    X0 : (M, 3, P) ndarray
        The current model's window design.
    sigma : (3,) ndarray
        Per-axis residual scale (rad/s) of the weighted fit.
    terms : sequence of str
        The library (:func:`library_terms`).
    Xlib : (M, 3, 3·T) ndarray, optional
        :func:`library_windows` of ``terms`` (computed when omitted).

    Returns
    -------
    dict
        ``{(term, axis): simpler_term}`` for every product term on axis ``axis`` whose column,
        projected off X0 (Frisch–Waugh–Lovell, axis weights 1/σ), has a fraction
        1 − ρ² < :data:`COLLINEAR_DELTA` of its norm² outside the span of one factor's column
        (the factor with the largest ρ²). The caller reports such a term as the simpler one
        (or as its catalogue equivalent, :func:`gyrocore.effects.registry.catalogue_equivalent`), never under the
        product's name.
    """
    Xlib = library_windows(res, terms) if Xlib is None else Xlib
    sw = 1.0 / np.maximum(np.asarray(sigma, float), 1e-300)
    Xw = weighted_design(X0, sw)
    pos = {t: k for k, t in enumerate(terms)}
    out = {}
    for k, term in enumerate(terms):
        factors = E.parse_expr(term)
        if sum(k for _, k in factors) < 2:
            continue
        fs = [f for f, _ in factors]
        subs = [(f, pos[f]) for f in fs if f in pos]
        if not subs:
            continue
        for i in range(3):
            cols = [3 * k + i] + [3 * kk + i for _, kk in subs]
            P = project_off(Xw, weighted_design(Xlib[:, :, cols], sw))
            c = P[:, 0]
            nc = float(c @ c)
            if not nc > 0:
                continue
            best, best_r2 = None, 0.0
            for j, (f, _) in enumerate(subs):
                a = P[:, j + 1]
                na = float(a @ a)
                if not na > 0:
                    continue
                r2 = float(a @ c) ** 2 / (na * nc)
                if r2 > best_r2:
                    best, best_r2 = f, r2
            if best is not None and 1.0 - best_r2 < COLLINEAR_DELTA:
                out[(term, i)] = best
    return out


@dataclass(frozen=True)
class LibraryScreen:
    """Best library column by the score test: term, axis, statistic, p-value, columns tested."""

    term: str
    axis: int
    statistic: float
    p_value: float
    log10_p: float
    n_tested: int
    df2: int


def score_tests(X0: np.ndarray, e: np.ndarray, sigma: np.ndarray, C: np.ndarray):
    """Score (LM) tests of single columns C (M, 3, K) added to the model X0 (M, 3, P).

    The residual ``e`` (M, 3) of the weighted fit of X0 (axis weights 1/σ²), each column is
    projected off X0 (Frisch–Waugh–Lovell), z = c⊥ᵀ·W·e, Var(z) = Σ_axes c⊥ᵀ·Γ_axis·c⊥ with
    Γ the HAC autocovariance model of the weighted residual; F = z²/Var(z) ~ F(1, 3M − P).

    Returns F (K,) and the coefficient estimate z / c⊥ᵀc⊥ (K,) (SI per unit of the column).
    """
    M = e.shape[0]
    sw = 1.0 / np.maximum(np.asarray(sigma, float), 1e-300)
    Xw = weighted_design(X0, sw)
    Cw = weighted_design(C, sw)
    ew = weighted_residual(e, sw)
    Cp = project_off(Xw, Cw)
    z = Cp.T @ ew
    gs = covariance.residual_autocov_models(np.stack([e[:, i] * sw[i] for i in range(3)], axis=1))
    var = np.zeros(C.shape[2])
    for i in range(3):
        U = Cp[i * M : (i + 1) * M]
        var += np.einsum("mk,mk->k", U, covariance.autocov_apply(U, gs[i]))
    nrm = np.einsum("rk,rk->k", Cp, Cp)
    with np.errstate(divide="ignore", invalid="ignore"):
        F = np.where(var > 0, z**2 / var, 0.0)
        coef = np.where(nrm > 0, z / nrm, 0.0)
    # columns (nearly) spanned by the model carry nothing to test
    Cn = np.einsum("rk,rk->k", Cw, Cw)
    F = np.where(nrm > 1e-10 * np.maximum(Cn, 1e-300), F, 0.0)
    return F, coef


def screen_library(
    res,
    X0: np.ndarray,
    e: np.ndarray,
    sigma: np.ndarray,
    terms: Sequence[str],
    exclude: set,
    n_params: int,
    Xlib: np.ndarray | None = None,
) -> LibraryScreen | None:
    """Score-test every (term, axis) of the library not excluded; the best one.

    ``exclude`` holds (term, axis) pairs already in the model or equivalent to a catalogue
    effect. The p-value is referred to F(1, 3M − P); the caller compares it with its
    Bonferroni threshold over ``n_tested``.
    """
    cols = [(k, i) for k, term in enumerate(terms) for i in range(3) if (term, i) not in exclude]
    if not cols:
        return None
    Xlib = library_windows(res, terms) if Xlib is None else Xlib
    C = Xlib[:, :, [3 * k + i for k, i in cols]]
    F, _ = score_tests(X0, e, sigma, C)
    df2 = max(3 * res.m - n_params - 1, 1)
    j = int(np.argmax(F))
    lp = float(stats.f.logsf(F[j], 1, df2) / np.log(10))
    if not np.isfinite(lp):
        lp = float(stats.chi2.logsf(F[j], 1) / np.log(10))
    k, i = cols[j]
    return LibraryScreen(
        term=terms[k], axis=i, statistic=float(F[j]), p_value=float(10**lp), log10_p=lp, n_tested=len(cols), df2=df2
    )
