"""Joint least squares over catalogue effects, with honest standard errors.

The measurement model of :mod:`gyrocore.effects.registry`, linearised at zero error, is

    r(t_n) = y(t_n) − ω_ref(t_n) ≈ A(t_n)·θ + e(t_n),       A from ``effects.design``

with ``r`` and ``e`` of shape (N, 3), ``A`` of shape (N, 3, P) and θ the stacked parameters of
the chosen effects. Per-axis effects (bias, scale, ...) are block-diagonal in A; a shared
parameter (``time_offset``) has one column that touches all three axes. The whole 3-axis
problem is solved at once, so cross-axis terms (misalignment, g-sensitivity) and shared terms
are estimated jointly.

Estimation is weighted least squares (axis weights 1/σ_i² from a first pass, times optional
user row weights). Standard errors come from one of three covariances:

* ``"ols"`` — s²·(AᵀWA)⁻¹, right when the residual is white;
* ``"hac"`` — the sandwich (AᵀWA)⁻¹·(AᵀW·Γ·WA)·(AᵀWA)⁻¹ with Γ the Toeplitz
  autocovariance of each axis' residual: sample values at short lags plus a fitted
  exponential (Gauss–Markov) tail (:func:`residual_autocov_model`). Right for coloured
  residuals (on-chip low-pass, Gauss–Markov bias, bias instability over the record), and
  honest even when the correlation time is long, where kernel estimators on the score
  (Newey–West) truncate the tail and understate the error (checked by Monte Carlo in
  tests/gyrocore/calib/test_lsq.py);
* ``"newey_west"`` — the Newey & West (1987) Bartlett-kernel sandwich on the score series,
  AR(1) pre-whitened with the Andrews (1991) plug-in bandwidth (Andrews & Monahan 1992);
* ``"block"`` — batch means over ``n_blocks`` contiguous blocks (cluster-robust by time).

``"auto"`` (the default) runs a Ljung–Box test on the weighted residual and a block-mean
variance test for slow noise (:func:`low_frequency_excess`) and uses ``"hac"`` when either
finds the residual coloured (p < 0.01 / α = 1e-3), ``"ols"`` otherwise; the result says which
(:attr:`LsqFit.cov_kind`) and the Ljung–Box p (:attr:`LsqFit.ljung_box_p`).

Observability: columns are checked in the declared effect order by a rank-revealing
(sequential Gram–Schmidt) test on the column-equilibrated matrix; a column whose part outside
the span of the earlier columns is below ``rank_rtol`` of its norm (a never-rotated axis, f
constant and so collinear with bias, ...) is *unobservable*: it is not fitted (its value is
reported as 0 with an infinite standard error) and it is named in
:attr:`LsqFit.unobservable` as ``"effect.param[index]"``. After the fit, a parameter whose
standard error exceeds its physically plausible magnitude (:data:`PLAUSIBLE_MAGNITUDE`) is
named as well — the data then say nothing that its plausible range did not already say — and
the fit is redone without it (``on_unobservable="drop"``) or :class:`UnobservableError` is
raised (``"raise"``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from scipy import linalg

from gyrocore.effects import registry as E
from gyrocore.errors import GyroInputError, UnobservableError

from .covariance import ljung_box_p, low_frequency_excess, parameter_covariance
from .rows import CHUNK_ROWS, ArrayRows, BlockMeans, BlockRows, RowSource, used_rows, window_ranges

__all__ = ["LsqFit", "build_design", "solve", "fit_effects", "PLAUSIBLE_MAGNITUDE", "NOISY_REGRESSOR_EFFECTS"]

#: Largest physically plausible |θ| per effect, SI (used to call a parameter unobservable when
#: its standard error exceeds it). Generous on purpose: a consumer MEMS gyro is far inside.
PLAUSIBLE_MAGNITUDE: dict[str, float] = {
    # from the registry (gyrocore.effects.registry, Effect.plausible): bias 1 rad/s (57 deg/s),
    # bias_thermal 0.05 rad/s per °C^k, bias_temp_rate 1 rad/s per °C/s, bias_ramp 1e-2 rad/s²,
    # scale 0.5, scale_thermal 0.01 per °C^k, scale_asymmetry 0.2, scale_nonlinearity 0.2 s/rad,
    # misalignment 0.2 rad (11 deg), g_sensitivity 5e-3 rad/s per m/s² (2.8 deg/s/g),
    # g2_sensitivity 1e-3 rad/s per (m/s²)², time_offset 1 s. Family terms: periodic/step
    # 1 rad/s, regressor unbounded (its unit depends on the signal).
    e.name: e.plausible
    for e in E.REGISTRY.values()
    if e.fittable
}


#: Effects whose regressors are built from measured, noisy inputs (accel, temperature).
NOISY_REGRESSOR_EFFECTS: tuple[str, ...] = tuple(e.name for e in E.REGISTRY.values() if e.fittable and e.noisy)


def _plausible(plaus: Mapping[str, float], eff: str) -> float:
    if eff in plaus:
        return plaus[eff]
    try:
        return E.resolve(eff).plausible
    except GyroInputError:
        return np.inf


def _column_effect(name: str) -> str:
    """Effect of a column name ``"effect.param[index]"`` (a family name may hold a '.': periodic[37.5].a_cos_rad_s[0])."""
    if "[" in name.split(".", 1)[0]:
        return name[: name.index("]") + 1]
    return name.split(".", 1)[0]


def _is_noisy(eff: str, noisy_effects) -> bool:
    """A catalogue effect listed in ``noisy_effects``, or a family term built from accel/temperature."""
    return eff in noisy_effects or (E.is_family(eff) and E.resolve(eff).noisy)


@dataclass(frozen=True, eq=False)
class LsqFit:
    """Result of a joint least-squares fit.

    Attributes
    ----------
    theta : ndarray, shape (P,)
        Estimated parameters in SI, in column order; unobservable ones are 0.
    names : tuple of str, length P
        ``"effect.param[index]"`` per column (e.g. ``"scale.s[0]"``).
    slices : dict
        Effect name -> slice into ``theta`` of that effect's columns.
    cov : ndarray, shape (P, P)
        Covariance of ``theta`` (rows/columns of unobservable parameters are NaN off the
        diagonal, +inf on it).
    stderr : ndarray, shape (P,)
        sqrt(diag(cov)); +inf for unobservable parameters.
    cov_kind : str
        ``"ols"``, ``"hac"``, ``"newey_west"`` or ``"block"`` — which covariance ``cov`` is.
    ljung_box_p : float
        p-value of the Ljung–Box whiteness test on the weighted residual (small = coloured).
    hac_bandwidth : float
        Longest lag (samples after ``stride``) of the autocovariance used by ``"hac"`` or the
        Bartlett bandwidth of ``"newey_west"``; NaN otherwise.
    residual_rad_s : ndarray, shape (N, 3)
        r − A·θ on all N input samples (not only the strided ones), rad/s.
    residual_rms_rad_s : ndarray, shape (3,)
        RMS of the residual per axis over the rows used in the fit, rad/s.
    axis_sigma_rad_s : ndarray, shape (3,)
        Per-axis residual standard deviation used for the axis weights, rad/s.
    rank : int
        Number of fitted (observable) columns.
    condition : float
        2-norm condition number of the column-equilibrated, weighted design of the fitted
        columns.
    unobservable : tuple of str
        Names of parameters the data cannot determine (not fitted).
    unobservable_reason : dict
        Name -> one-line reason ("collinear with ...", "stderr ... > plausible ...").
    n_rows : int
        Rows used in the fit (after stride, zero-weight rows and block averaging).
    dof : int
        3·n_rows − rank.
    """

    theta: np.ndarray
    names: tuple[str, ...]
    slices: dict[str, slice]
    cov: np.ndarray
    stderr: np.ndarray
    cov_kind: str
    ljung_box_p: float
    hac_bandwidth: float
    residual_rad_s: np.ndarray
    residual_rms_rad_s: np.ndarray
    axis_sigma_rad_s: np.ndarray
    rank: int
    condition: float
    unobservable: tuple[str, ...]
    unobservable_reason: dict[str, str] = field(default_factory=dict)
    n_rows: int = 0
    dof: int = 0

    def effect_theta(self, effect: str) -> np.ndarray:
        """The flat parameter vector of one effect."""
        return self.theta[self.slices[effect]]

    def effect_stderr(self, effect: str) -> np.ndarray:
        """The flat standard errors of one effect."""
        return self.stderr[self.slices[effect]]

    def observable_mask(self) -> np.ndarray:
        """Boolean (P,): True for fitted columns."""
        bad = set(self.unobservable)
        return np.array([n not in bad for n in self.names])


# ---------------------------------------------------------------------------- design
def build_design(
    effects: Sequence[str],
    inp: E.ModelInputs,
    *,
    orders: Mapping[str, int] | None = None,
    t0_c: float | None = None,
) -> tuple[np.ndarray, list[str], dict[str, slice]]:
    """Stack the regressors of ``effects`` (in the given order).

    Parameters
    ----------
    effects : sequence of str
        Fittable catalogue effects (see :func:`gyrocore.effects.registry.design`).
    inp : ModelInputs
        Physical inputs; ``omega_S_rad_s`` is the reference rate (rad/s, S frame).
    orders : mapping, optional
        Polynomial order per thermal effect (``bias_thermal``, ``scale_thermal``); default 1.
    t0_c : float, optional
        T0 of the thermal polynomials, °C; default the mean of ``inp.temp_c`` (see
        :func:`gyrocore.effects.registry.design`).

    Returns
    -------
    A : ndarray, shape (N, 3, P)
    names : list of str, length P — ``"effect.param[index]"``
    slices : dict effect -> slice
    """
    orders = dict(orders or {})
    blocks, names, slices = [], [], {}
    p0 = 0
    for eff in E.check_effect_names(effects):
        if eff in slices:
            raise GyroInputError(f"effect {eff} listed twice")
        cn, A = E.design(eff, inp, order=int(orders.get(eff, 1)), t0_c=t0_c)
        blocks.append(A)
        names += [f"{eff}.{c}" for c in cn]
        slices[eff] = slice(p0, p0 + A.shape[2])
        p0 += A.shape[2]
    if not blocks:
        raise GyroInputError("no effects to fit")
    return np.concatenate(blocks, axis=2), names, slices


# ---------------------------------------------------------------------------- solver
def _solve_pos(G: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve the symmetric positive (semi-)definite system G x = b.

    Exactly singular G (a candidate's columns collinear with the model's on this record, e.g. a
    companion term that repeats a kept column): SciPy ≥ 1.17 raises ``LinAlgError`` where older
    releases returned a solution with a ``LinAlgWarning``; the minimum-norm least-squares
    solution is then the same fit (the covariance uses ``pinvh`` in any case).
    """
    try:
        return linalg.solve(G, b, assume_a="pos")
    except linalg.LinAlgError:
        return linalg.lstsq(G, b)[0]


def _sequential_rank(G: np.ndarray, rtol: float) -> tuple[list[int], dict[int, tuple[int, ...]]]:
    """Columns kept in the given order by a rank-revealing sequential test (no pivoting, so
    the declared order decides which of two collinear columns is kept).

    Works on the Gram matrix G = XᵀX of the (weighted) design: with columns equilibrated to
    unit norm, the squared norm of column p's part outside the span of the kept columns is
    the Schur complement G_pp − G_pk·G_kk⁻¹·G_kp; below ``rtol``² the column is dropped.
    (Gram round-off is ~1e-15 here, far below rtol² = 1e-12 for the default rtol.)
    Returns the kept indices and, per dropped index, up to 3 kept columns it is (nearly)
    spanned by.
    """
    P = G.shape[0]
    d = np.sqrt(np.clip(np.diag(G), 0, None))
    good = (d > 0) & np.isfinite(d)
    Gn = G / np.outer(np.where(good, d, 1.0), np.where(good, d, 1.0))
    kept: list[int] = []
    dropped: dict[int, tuple[int, ...]] = {}
    for p in range(P):
        if not good[p]:
            dropped[p] = ()
            continue
        if kept:
            Gkk = Gn[np.ix_(kept, kept)]
            c = _solve_pos(Gkk, Gn[kept, p])
            r2 = float(Gn[p, p] - Gn[p, kept] @ c)
        else:
            c, r2 = np.zeros(0), 1.0
        if r2 < rtol**2:
            big = np.argsort(-np.abs(c))
            dropped[p] = tuple(kept[j] for j in big[:3] if abs(c[j]) > 1e-3 * np.abs(c).max())
            continue
        kept.append(p)
    return kept, dropped


def solve(
    r: np.ndarray,
    A: np.ndarray,
    names: Sequence[str],
    slices: Mapping[str, slice],
    *,
    weights: np.ndarray | None = None,
    stride: int = 1,
    average: int = 1,
    t_s: np.ndarray | None = None,
    **options,
) -> LsqFit:
    """Solve r ≈ A·θ jointly over the three axes.

    Parameters
    ----------
    r : ndarray, shape (N, 3)
        Left-hand side, usually measured minus reference rate, rad/s (S frame).
    A : ndarray, shape (N, 3, P)
        Regressors (see :func:`build_design`).
    names : sequence of str, length P
        Column names ``"effect.param[index]"``.
    slices : mapping effect -> slice
    weights : ndarray, shape (N,) or (N, 3), optional
        Non-negative row weights (0 excludes a sample, e.g. a transient). Multiplied by the
        axis weights 1/σ_i² when ``axis_weighting``.
    stride : int
        Use every ``stride``-th sample (downsampling for speed; the covariance is computed
        on the same rows and stays honest through the HAC/block estimator).
    average : int
        Fit weighted block means of ``average`` consecutive rows (after ``stride``) instead
        of the rows: exact for the linear model, keeps nearly all the information of slow
        regressors and cuts memory/time; residual RMS is still reported on all samples
        (:class:`gyrocore.calib.rows.BlockMeans`, the reduction :func:`fit_effects` makes
        window by window).
    t_s : ndarray, shape (N,), optional
        Sample times, s since the power-up (flicker and random walk start there); needed by
        ``covariance="noise_model"``.
    **options
        Options of the solver on the rows (:func:`_solve_rows`): ``covariance`` ({"auto",
        "ols", "hac", "newey_west", "block", "noise_model"}, see the module docstring),
        ``axis_weighting`` (two-step feasible WLS: weight axis i by 1/σ̂_i² from a first
        unweighted pass; default True), ``n_blocks`` (blocks of ``"block"``, 30),
        ``rank_rtol`` (relative residual norm below which a column counts as spanned by
        earlier ones, 1e-6), ``on_unobservable`` ({"drop", "raise"}), ``plausible``
        (overrides of :data:`PLAUSIBLE_MAGNITUDE`), ``hac_bandwidth`` (fixed Bartlett
        bandwidth of ``"newey_west"``), ``min_excitation_snr`` (columns built from measured
        inputs: the RMS of the column's part independent of the other columns over its
        first-difference noise level must reach this, else the parameter is unobservable;
        5 → errors-in-variables attenuation below 4 %), ``noisy_effects`` (effects whose
        regressors come from measured inputs), ``noise_model`` (the gyro's noise,
        :class:`gyrocore.noise.model.NoiseModel`, for ``covariance="noise_model"``: the
        sandwich (AᵀWA)⁻¹·(Σ_i U_iᵀ C_i U_i)·(AᵀWA)⁻¹, U = W·A,
        :func:`gyrocore.calib.covariance.noise_model_meat`).

    Returns
    -------
    LsqFit
    """
    r_all = np.asarray(r, float)
    A_all = np.asarray(A, float)
    N, P = r_all.shape[0], A_all.shape[2]
    if r_all.shape != (N, 3) or A_all.shape[:2] != (N, 3):
        raise GyroInputError(f"lsq: r has shape {r_all.shape}, A has shape {A_all.shape}; expected (N,3) and (N,3,P)")
    if len(names) != P:
        raise GyroInputError(f"lsq: {len(names)} names for {P} columns")
    _check_options(options, t_s)
    w_all, keep = used_rows(N, weights, stride)
    if not np.all(np.isfinite(r_all)) or not np.all(np.isfinite(A_all)):
        raise GyroInputError("lsq: non-finite values in the data or regressors")
    times = _row_times(options, t_s)
    blocks = BlockMeans(w_all, keep, average, with_times=times is not None, dt_s=times[1] if times else np.nan)
    rows = blocks.rows_in(0, N)  # one window: the whole record
    blocks.add(0, rows, r_all[rows], A_all[rows], None if times is None else times[0][rows])
    fit = _solve_rows(blocks.result(), names, slices, dt_s=times[1] if times else np.nan, **options)
    resid = r_all - np.einsum("nip,p->ni", A_all, fit.theta)
    return dataclasses.replace(fit, residual_rad_s=resid, residual_rms_rad_s=_weighted_rms(resid, w_all, keep))


def fit_effects(
    r: np.ndarray,
    effects: Sequence[str],
    inp: E.ModelInputs,
    *,
    orders: Mapping[str, int] | None = None,
    chunk_rows: int | None = CHUNK_ROWS,
    keep_residual: bool = True,
    overwrite_r: bool = False,
    residual_sink=None,
    weights: np.ndarray | None = None,
    stride: int = 1,
    average: int = 1,
    t_s: np.ndarray | None = None,
    **options,
) -> LsqFit:
    """Fit the linearised ``effects`` to r = y − ω_ref jointly (see :func:`solve`), a window
    at a time: memory O(window·P + N/``average``·P) whatever the record's length.

    Two passes over windows of rows (:func:`gyrocore.calib.rows.window_ranges`): the first
    builds the design of each window (with one row of overlap each side for the time
    derivatives of ``time_offset``/``bias_temp_rate``; the thermal T0 and the power-up time of
    the whole record) and adds its used rows to the weighted block means
    (:class:`gyrocore.calib.rows.BlockMeans`) that :func:`_solve_rows` fits; the second computes
    the full-resolution residual r − A·θ and its RMS window by window. A record in memory and
    one on disk (a :class:`gyrocore.calib.rows.RowSource`) take this same path.

    Parameters
    ----------
    r : ndarray, shape (N, 3), or RowSource
        Measured minus reference rate, rad/s, S frame; or a :class:`gyrocore.calib.rows.RowSource`
        that gives r and the model inputs a window at a time (``inp`` is then unused).
    effects : sequence of str
        Catalogue effects with regressors (``effects.design``); the order matters for the
        observability test (an earlier effect keeps a column that a later one duplicates).
    inp : ModelInputs
        ``omega_S_rad_s`` = reference rate; ``f_S_m_s2``/``temp_c`` when the effects need them.
    orders : mapping, optional
        Thermal polynomial orders.
    chunk_rows : int or None
        Window length, rows (a record of at most four windows is one window); None: one
        window. The windows change only the order of the float additions of a block that
        straddles two of them (see :class:`gyrocore.calib.rows.BlockMeans`).
    keep_residual : bool
        False: the result's ``residual_rad_s`` is empty, shape (0, 3) (its RMS is still
        computed), so a fit whose residual is not used (e.g. an order test) holds no
        (N, 3) array.
    overwrite_r : bool
        Write the residual into ``r`` (a float64 (N, 3) array the caller no longer needs)
        and return it as ``residual_rad_s``, saving one (N, 3) array — like scipy's
        ``overwrite_a``.
    residual_sink : callable, optional
        ``residual_sink(a, b, e)`` receives the full-resolution residual of rows a:b
        (shape (b − a, 3), rad/s) window by window, e.g. to write it to disk instead of
        holding (N, 3) in memory.
    weights, stride, average, t_s
        As in :func:`solve`; without ``t_s`` a noise-model covariance takes the source's
        times from its first sample and their mean spacing.
    **options
        Options of the solver (see :func:`solve`).
    """
    src = r if isinstance(r, RowSource) else ArrayRows(r, inp)
    N = src.n
    _check_options(options, t_s, need_times=False)
    w_all, keep = used_rows(N, weights, stride)
    times = _row_times(options, t_s, src)
    t0_c = src.temp_mean_c() if src.has_temp else None
    windows = window_ranges(N, chunk_rows)
    blocks = BlockMeans(w_all, keep, average, with_times=times is not None, dt_s=times[1] if times else np.nan)
    names = slices = None
    for a, b in windows:  # pass 1: the block means
        rows = blocks.rows_in(a, b)
        if rows.size == 0:
            if blocks.done:
                break
            continue
        A, names, slices = _window_design(effects, src, orders, t0_c, a, b, N)
        rw = _finite_rows(src, a, b)
        blocks.add(a, rows, rw[rows], A[rows], None if times is None else times[0](a, b)[rows])
        del A, rw
        if blocks.done:
            break
    fit = _solve_rows(blocks.result(), names, slices, dt_s=times[1] if times else np.nan, **options)
    del blocks
    # pass 2: the residual r − A·θ at full resolution and its RMS over the used rows
    r_arr = src.r if isinstance(src, ArrayRows) else None
    if not keep_residual:
        resid = np.zeros((0, 3))
    elif overwrite_r and r_arr is not None and r_arr is r and r_arr.flags.writeable:
        resid = r_arr  # window a:b reads only r[a:b] before it is overwritten
    else:
        resid = np.empty((N, 3))
    num, den = np.zeros(3), np.zeros(3)
    for a, b in windows:
        A, _, _ = _window_design(effects, src, orders, t0_c, a, b, N)
        e = src.r_rows(a, b) - np.einsum("nip,p->ni", A, fit.theta)
        del A
        if keep_residual:
            resid[a:b] = e
        if residual_sink is not None:
            residual_sink(a, b, e)
        sel = keep[a:b]
        wu = w_all[a:b][sel]
        num += np.sum(wu * e[sel] ** 2, axis=0)
        den += np.sum(wu, axis=0)
    return dataclasses.replace(fit, residual_rad_s=resid, residual_rms_rad_s=np.sqrt(num / np.maximum(den, 1e-300)))


# ---------------------------------------------------------------------------- the steps
def _check_options(options: dict, t_s, *, need_times: bool = True) -> None:
    """One ``error:`` line for solver options that cannot be used."""
    covariance = options.get("covariance", "auto")
    if covariance not in ("auto", "ols", "hac", "newey_west", "block", "noise_model"):
        raise GyroInputError(f"unknown covariance '{covariance}' (auto, ols, hac, newey_west, block, noise_model)")
    if covariance == "noise_model" and (options.get("noise_model") is None or (need_times and t_s is None)):
        raise GyroInputError("covariance 'noise_model' needs the noise model and the sample times")
    if options.get("on_unobservable", "drop") not in ("drop", "raise"):
        raise GyroInputError(f"on_unobservable must be 'drop' or 'raise', not '{options['on_unobservable']}'")


def _row_times(options: dict, t_s, src: RowSource | None = None):
    """For ``covariance="noise_model"``: (the rows' times, s since the power-up, and the sample
    spacing dt_s) — ``t_s`` (N,) and the median of its steps; without ``t_s`` the source's
    times from its first sample and their mean spacing. A reader ``(a, b) -> times of rows
    a:b`` when ``src`` is given, else the (N,) array. None for the other covariances."""
    if options.get("covariance") != "noise_model":
        return None
    if t_s is not None:
        t_arr = np.asarray(t_s, float)
        n = src.n if src is not None else t_arr.size
        if t_arr.shape != (n,):
            raise GyroInputError(f"lsq: t_s has shape {t_arr.shape}, expected ({n},)")
        dt_s = float(np.median(np.diff(t_arr))) if t_arr.size > 1 else float("nan")
        return (t_arr if src is None else (lambda a, b: t_arr[a:b])), dt_s
    t_first = float(src.t_rows(0, 1)[0])
    dt_s = (float(src.t_rows(src.n - 1, src.n)[0]) - t_first) / max(src.n - 1, 1)
    return (lambda a, b: src.t_rows(a, b) - t_first), dt_s


def _finite_rows(src: RowSource, a: int, b: int) -> np.ndarray:
    """r on rows a:b of a source, refused when not finite."""
    rw = src.r_rows(a, b)
    if not isinstance(src, ArrayRows) and not np.all(np.isfinite(rw)):  # ArrayRows checked it whole
        raise GyroInputError("lsq: non-finite values in the data or regressors")
    return rw


def _window_design(effects, src: RowSource, orders, t0_c, a: int, b: int, n: int):
    """Design rows a:b of the whole record, built on a:b plus one neighbour each side (so
    central differences at the window edges equal those of the whole record)."""
    lo, hi = max(a - 1, 0), min(b + 1, n)
    A, names, slices = build_design(effects, src.inputs(lo, hi), orders=orders, t0_c=t0_c)
    A = A[a - lo : a - lo + (b - a)]
    if not np.all(np.isfinite(A)):
        raise GyroInputError("lsq: non-finite values in the data or regressors")
    return A, names, slices


def _weighted_rms(e: np.ndarray, w_all: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """RMS per axis of the residual over the used rows, weighted, rad/s (3,)."""
    eu, wu = e[keep], w_all[keep]
    return np.sqrt(np.sum(wu * eu**2, axis=0) / np.maximum(np.sum(wu, axis=0), 1e-300))


def _solve_rows(
    rows: BlockRows,
    names: Sequence[str],
    slices: Mapping[str, slice],
    *,
    dt_s: float = float("nan"),
    covariance: str = "auto",
    axis_weighting: bool = True,
    n_blocks: int = 30,
    rank_rtol: float = 1e-6,
    on_unobservable: str = "drop",
    plausible: Mapping[str, float] | None = None,
    hac_bandwidth: float | None = None,
    min_excitation_snr: float = 5.0,
    noisy_effects: Sequence[str] = NOISY_REGRESSOR_EFFECTS,
    noise_model=None,
) -> LsqFit:
    """The fit of the rows (block means) and its covariance; the result's residual is that of
    the rows (the callers replace it by the full-resolution one).

    Steps: the observable columns (:func:`_observable_columns`); then, until no standard error
    exceeds its plausible magnitude: the weighted fit (:func:`_weighted_fit`), the covariance
    kind (:func:`_covariance_kind`) and the parameter covariance
    (:func:`gyrocore.calib.covariance.parameter_covariance`); the parameters too wide are
    dropped (:func:`_too_wide`) and the fit redone."""
    r_, A_, w_ = rows.r, rows.A, rows.w
    n, P = r_.shape[0], A_.shape[2]
    plaus = dict(PLAUSIBLE_MAGNITUDE)
    plaus.update(plausible or {})
    rows_t = None if rows.t0_s is None else (rows.t0_s, rows.t1_s, rows.n_eff)
    kept, dropped, reasons = _observable_columns(
        A_, w_, names, rank_rtol=rank_rtol, noisy_effects=noisy_effects, min_excitation_snr=min_excitation_snr
    )
    for _attempt in range(P + 1):
        th, e, W, sigma = _weighted_fit(A_, r_, kept, w_, axis_weighting)
        Ak = A_[:, :, kept]
        bread, cond = _bread(Ak, W)
        ew = e * np.sqrt(W)
        kind, lb_p = _covariance_kind(covariance, ew, W)
        dof = max(int(np.sum(W > 0)) - len(kept), 1)
        cov_k, L = parameter_covariance(
            kind,
            Ak,
            W,
            e,
            ew,
            bread,
            n=n,
            dof=dof,
            rows_t=rows_t,
            noise_model=noise_model,
            dt_s=dt_s,
            hac_bandwidth=hac_bandwidth,
            n_blocks=n_blocks,
        )
        too_wide = _too_wide(cov_k, kept, names, plaus, reasons)
        if not too_wide:
            break
        kept = [p for p in kept if p not in too_wide]
        if not kept:
            break
    unobs = tuple(names[p] for p in range(P) if p not in kept)
    if unobs and on_unobservable == "raise":
        raise UnobservableError("unobservable parameters: " + "; ".join(f"{u} ({reasons.get(u, '')})" for u in unobs))
    theta = np.zeros(P)
    cov = np.full((P, P), np.nan)
    if kept:
        theta[kept] = th
        cov[np.ix_(kept, kept)] = cov_k
    for p in range(P):
        if p not in kept:
            cov[p, p] = np.inf
    return LsqFit(
        theta=theta,
        names=tuple(names),
        slices=dict(slices),
        cov=cov,
        stderr=np.sqrt(np.diag(cov)),
        cov_kind=kind,
        ljung_box_p=float(lb_p),
        hac_bandwidth=L,
        residual_rad_s=e,
        residual_rms_rad_s=np.zeros(3),
        axis_sigma_rad_s=np.asarray(sigma, float),
        rank=len(kept),
        condition=cond if kept else float("inf"),
        unobservable=unobs,
        unobservable_reason={u: reasons.get(u, "") for u in unobs},
        n_rows=int(n),
        dof=int(dof),
    )


def _weighted_fit(A_, r_, kept: list[int], w_, axis_weighting: bool):
    """θ of the kept columns, the rows' residual e, the weights W used and the axis σ:
    weighted least squares, then (``axis_weighting``) again with the axes weighted by
    1/σ̂_i² of the first pass (feasible WLS)."""
    th = _wls(A_, r_, kept, w_)
    e = r_ - np.einsum("nip,p->ni", A_[:, :, kept], th)
    if not axis_weighting:
        return th, e, w_, np.ones(3)
    sigma = _axis_sigma(r_, e, w_)
    W = w_ / sigma[None, :] ** 2
    th = _wls(A_, r_, kept, W)
    return th, r_ - np.einsum("nip,p->ni", A_[:, :, kept], th), W, sigma


def _bread(Ak, W) -> tuple[np.ndarray, float]:
    """(AᵀWA)⁻¹ of the kept columns (pseudo-inverse of the column-equilibrated matrix) and the
    2-norm condition number of the equilibrated, weighted design."""
    XtX = np.einsum("nip,ni,niq->pq", Ak, W, Ak, optimize=True)
    cn = np.sqrt(np.diag(XtX))
    cn[cn == 0] = 1.0
    XtX_s = XtX / np.outer(cn, cn)
    ev = np.linalg.eigvalsh(XtX_s)
    cond = float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float("inf")
    return linalg.pinvh(XtX_s) / np.outer(cn, cn), cond


def _covariance_kind(covariance: str, ew, W) -> tuple[str, float]:
    """The covariance used and the Ljung–Box p of the weighted residual ``ew``: ``"auto"`` is
    ``"hac"`` when the residual is coloured (Ljung–Box p < 0.01, or slow noise by
    :func:`gyrocore.calib.covariance.low_frequency_excess`), else ``"ols"``."""
    lb_p = ljung_box_p(ew)
    if covariance != "auto":
        return covariance, lb_p
    coloured = (np.isfinite(lb_p) and lb_p < 0.01) or any(low_frequency_excess(ew[:, i][W[:, i] > 0]) for i in range(3))
    return ("hac" if coloured else "ols"), lb_p


def _too_wide(cov_k, kept: list[int], names, plaus, reasons: dict) -> set[int]:
    """Kept columns whose standard error exceeds their plausible magnitude (their reason
    recorded in ``reasons``)."""
    se_k = np.sqrt(np.clip(np.diag(cov_k), 0, None))
    wide = set()
    for j, p in enumerate(kept):
        eff = _column_effect(names[p])
        if se_k[j] > _plausible(plaus, eff):
            reasons[names[p]] = (
                f"standard error {se_k[j]:.3g} exceeds the plausible magnitude {_plausible(plaus, eff):.3g} (too little excitation)"
            )
            wide.add(p)
    return wide


def _observable_columns(A_, w_, names, *, rank_rtol: float, noisy_effects, min_excitation_snr: float):
    """Columns that can be fitted: (kept column indices, {dropped: the columns it is not
    separable from}, {column name: why it was dropped})."""
    # sequential rank test on the (unweighted-by-axis) design
    G_all = np.einsum("nip,ni,niq->pq", A_, w_, A_, optimize=True)
    kept, dropped = _sequential_rank(G_all, rank_rtol)
    reasons: dict[str, str] = {}
    for p, by in dropped.items():
        if by:
            reasons[names[p]] = "not separable from " + ", ".join(names[j] for j in by)
        else:
            reasons[names[p]] = "regressor is zero in the data (no excitation)"

    # columns built from measured inputs (accel, temperature): their independent part must
    # stand above the input's own noise, else the fit is to noise (errors in variables)
    noisy_idx = [p for p in kept if _is_noisy(_column_effect(names[p]), noisy_effects)]
    if noisy_idx and min_excitation_snr > 0:
        sw = np.sqrt(w_)
        drop_noisy = []
        Gk = G_all[np.ix_(kept, kept)]
        for p in noisy_idx:
            j = kept.index(p)
            oth = [q for q in range(len(kept)) if q != j]
            R = A_[:, :, p] * sw
            if oth:
                c = linalg.lstsq(Gk[np.ix_(oth, oth)], Gk[oth, j])[0]
                R = R - np.einsum("nip,p->ni", A_[:, :, [kept[q] for q in oth]], c) * sw
            exc2 = float(np.mean(R**2))
            noise2 = float(np.mean(np.diff(R, axis=0) ** 2)) / 2.0
            snr = np.sqrt(exc2 / noise2) if noise2 > 0 else np.inf
            if snr < min_excitation_snr:
                drop_noisy.append(p)
                reasons[names[p]] = (
                    f"its regressor varies only at the level of its own measurement noise "
                    f"(excitation/noise {snr:.2g} < {min_excitation_snr:g})"
                )
        kept = [p for p in kept if p not in drop_noisy]
    return kept, dropped, reasons


def _wls(A_, r_, cols: list[int], w: np.ndarray) -> np.ndarray:
    """Weighted least squares of r_ on the columns ``cols``: the normal equations of the
    column-equilibrated problem (the columns passed the rank test, so cond² stays far from 1/eps)."""
    Ac = A_[:, :, cols]
    G = np.einsum("nip,ni,niq->pq", Ac, w, Ac, optimize=True)
    b = np.einsum("nip,ni,ni->p", Ac, w, r_, optimize=True)
    cn = np.sqrt(np.diag(G))
    cn[cn == 0] = 1.0
    return _solve_pos(G / np.outer(cn, cn), b / cn) / cn


def _axis_sigma(r_, e, w_) -> np.ndarray:
    """Per-axis residual σ̂ of a first pass, for the axis weights 1/σ̂² (feasible WLS)."""
    sig = np.sqrt(np.sum(w_ * e**2, axis=0) / np.maximum(np.sum(w_ > 0, axis=0), 1))
    # an exact fit (noise-free data) has nothing to weight: unit weights; otherwise a
    # relative floor keeps an exactly fitted axis from getting an infinite weight
    smax = float(sig.max())
    # ... and so is a residual at the rounding level of the data (64 eps·max|r|) or
    # below 1e-100 rad/s (no instrument's noise; 1/σ² of the 1e-9 floor then stays
    # below 1e218, no overflow: hypothesis found b = 1.4e-146 rad/s, σ ~ 1e-150)
    exact = smax <= max(64.0 * np.finfo(float).eps * float(np.max(np.abs(r_), initial=0.0)), 1e-100)
    return np.ones(3) if smax == 0.0 or exact else np.maximum(sig, 1e-9 * smax)


#: Window length of the chunked design in :func:`fit_effects` (rows); records longer than
