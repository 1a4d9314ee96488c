"""Predicted attitude drift and its error budget, from the calibration's own uncertainty.

Given a trajectory (true rate, attitude, specific force, temperature), the power-up still
windows whose mean is subtracted as the power-up bias, the calibration's parameter estimates
with their standard errors, and the identified noise, :func:`predict_error` returns the
expected squared attitude error E|ε(t)|² of the integrated, corrected gyro along the
trajectory, split by source (the *error budget*), and the expected RMS and final error.
Pure numpy; no simulator.

Error dynamics (derivation)
---------------------------
Attitude R = R_WS (S → W), Ṙ = R·[ω×]. The integrated estimate R̂ = (I + [ε×])·R with ε
small and expressed in W. Differentiating, with ω̂ = ω + δω the corrected gyro::

    [ε̇×]·R + (I + [ε×])·R·[ω×] = (I + [ε×])·R·[(ω + δω)×]   ⇒   ε̇ = R·δω

(to first order; in S, φ = Rᵀε obeys φ̇ = −ω×φ + δω, the form of the issue). The error angle
scored by :func:`gyrocore.attitude.error_angle_rad` is |ε| to first order, so

    ε(t) = ∫_{t_s}^{t} R(τ)·δω(τ) dτ,       E|ε|² = tr Cov ε   (zero-mean errors).

The corrected rate error has three parts (each linear in its source):

* parameter errors δθ = θ̂ − θ of the fitted effects: the correction removes A(τ)·θ̂ where
  A = ∂y/∂θ (:func:`gyrocore.effects.registry.design` at the true rate, force, temperature), so
  δω = −A(τ)·δθ to first order (K̂⁻¹ ≈ I on an already small error);
* the stochastic noise n(τ) (white, flicker, rate random walk, Gauss–Markov);
* uncorrected deterministic terms d(τ) (an effect present but not corrected; the on-chip
  low-pass, which no correction inverts).

The power-up bias is the mean of the corrected rate over a still window w (true rate 0), so
it removes the window mean of *every* part: δω(τ) = u(τ) − ū_w with u = −A·δθ + n + d, for
the samples of that window's power-up segment. Hence, with P_j(t) = ∫_{seg j ∩ [t_s, t]} R dτ:

    ε(t) = −[∫ R·A dτ − Σ_j P_j(t)·Ā_wj]·δθ  +  [∫ R·n dτ − Σ_j P_j(t)·n̄_wj]  +  (same for d).

The bracket multiplying δθ is the *sensitivity* S(t) (3 × P, rad per unit parameter,
:func:`sensitivity`); a parameter group with covariance Σ contributes tr(S·Σ·Sᵀ). Because the
window mean is subtracted, any constant error cancels exactly (S = 0 for a bias).

Noise (derivation)
------------------
Each noise term is modelled per axis as a linear functional of white noise, started at the
power-up (t = 0 at the start of the recording) as the simulator and the chip do:

* white (ARW) N: Cov of block means z_b = N²/Δ_b δ_bc; quantization adds LSB²/(12·rate) to N²
  (rounding noise, uniform, white);
* bias instability B (IEEE 952: one-sided PSD B²/(π f)): the flicker process started at rest,
  x(t) = (B/√π)∫_0^t (t − s)^(−1/2) dW(s) — the continuous limit of Kasdin & Walter's
  fractional integrator (h_k ≈ 1/√(πk), innovation σ = B; :mod:`sim.noise`);
* rate random walk K: x(t) = K·W(t);
* Gauss–Markov σ, τc: stationary, E x(u)x(v) = σ²e^(−|u−v|/τc).

For a causal kernel h with H(u) = ∫_0^u h, the integrals ξ_b = ∫_b x of two blocks
b = [b0, b1], c = [c0, c1] have Cov = F(b1,c1) − F(b1,c0) − F(b0,c1) + F(b0,c0) with
F(a, c) = ∫_0^min(a,c) H(a − s)·H(c − s) ds, in closed form:

* flicker, H(u) = 2√(u/π): F = (4/π)·[(a + c)/4·√(ac) − d²/8·ln((√a + √c)²/d)], d = |a − c|
  (∫_0^a √(u(u + d)) du, a ≤ c);
* RRW, H(u) = u: F = m²M/2 − m³/6, m = min(a, c), M = max(a, c);
* Gauss–Markov (stationary): Cov = Φ(b1 − c0) + Φ(b0 − c1) − Φ(b1 − c1) − Φ(b0 − c0) with
  Φ(x) = τc²(|x|/τc − 1 + e^(−|x|/τc)) (Φ″ = the kernel).

The trajectory is cut into blocks (edges at the scoring start, every window and power-up
edge, and a uniform grid); ∫_b R·x ≈ P_b·z_b with P_b = ∫_b R (exact for white noise after
the within-block term Σ_k N_k²(Δ_b − |P_b[:,k]|²/Δ_b), added; for the slow terms the error is
the rate's variation within a block times the rotation within it). The quadratic forms are
then exact sums over blocks, including the correlation between a window's mean and the
later noise (a power-up bias also removes part of the slow noise present at power-up). The
*floor* (truth + noise integrated, no window subtraction: DESIGN.md "The score") is the same
sum without the window terms: N²t + K²t³/3 + 2σ²τc²(t/τc − 1 + e^(−t/τc)) for a still sensor
(:func:`gyrocore.attitude.floor_sigma_theta_rad`) plus the flicker term.

Spread
------
ε(T) is Gaussian with covariance C (3×3), so |ε(T)|² is a weighted sum of χ²₁ with the
eigenvalues of C: mean tr C, variance 2·tr C². ``final_sd_rad2`` reports that sd.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from gyrocore.effects import registry as E
from gyrocore.effects.effect import quat_to_R
from gyrocore.errors import GyroInputError
from gyrocore.noise.model import NoiseModel

__all__ = [
    "FORMAT_VERSION",
    "ParameterGroup",
    "Blocks",
    "ErrorPrediction",
    "make_blocks",
    "block_covariance",
    "sensitivity",
    "predict_error",
    "rotation_matrices",
]

FORMAT_VERSION = "1.0"
_NOISE_TERMS = ("arw", "bias_instability", "rrw", "correlated")


# ============================================================================ inputs
@dataclass(frozen=True)
class ParameterGroup:
    """Fitted effects whose errors are propagated together.

    Attributes
    ----------
    name : str
        Budget label (e.g. ``"scale"``, ``"thermal: bias_thermal"``).
    params : dict
        ``{effect: {param: ndarray}}`` estimates (PARAM_SCHEMA form; thermal polynomials give
        the order and ``t0_c``).
    stderr : dict
        Same layout, standard errors (NaN / inf entries are treated as 0 / skipped with a note).
    """

    name: str
    params: Mapping[str, Mapping[str, np.ndarray]]
    stderr: Mapping[str, Mapping[str, np.ndarray]]


# ============================================================================ blocks
@dataclass(frozen=True, eq=False)
class Blocks:
    """Sample-index blocks of a trajectory.

    ``i0``, ``i1`` (M,): sample ranges [i0, i1); ``t0_s``, ``t1_s``: their times since the
    start of the recording (power-up), s; ``scored`` (M,) bool; ``segment`` (M,) power-up
    segment index; ``window`` (M,) index of the still window the block belongs to, −1 if none.
    """

    i0: np.ndarray
    i1: np.ndarray
    t0_s: np.ndarray
    t1_s: np.ndarray
    scored: np.ndarray
    segment: np.ndarray
    window: np.ndarray

    @property
    def dt_s(self) -> np.ndarray:
        return self.t1_s - self.t0_s

    @property
    def m(self) -> int:
        return int(self.i0.size)


def make_blocks(
    t_s: np.ndarray, *, start: int, segments: Sequence[tuple[slice, slice | None]], max_blocks: int = 800
) -> Blocks:
    """Cut [0, N) into blocks: edges at ``start``, every segment and window edge, and a
    uniform grid of about ``max_blocks`` blocks over the scored part. Blocks before
    ``start`` are kept only inside windows.

    Parameters
    ----------
    t_s : ndarray (N,)
        Sample times, s (uniform rate).
    start : int
        First scored sample.
    segments : list of (segment slice, window slice or None)
        Power-up segments and their still windows (:func:`experiments.ablation.powerup_windows`).
    """
    t = np.asarray(t_s, float)
    n = t.size
    if n < 2:
        raise GyroInputError("need at least 2 samples to predict the attitude error")
    dt = float(np.median(np.diff(t)))
    edges = {0, int(start), n}
    for seg, win in segments:
        edges.update([int(seg.start or 0), int(seg.stop if seg.stop is not None else n)])
        if win is not None:
            edges.update([int(win.start), int(win.stop)])
    step = max(1, int(math.ceil((n - start) / max_blocks)))
    edges.update(range(int(start), n, step))
    e = np.array(sorted(x for x in edges if 0 <= x <= n))
    i0, i1 = e[:-1], e[1:]
    keep = i1 > i0
    i0, i1 = i0[keep], i1[keep]
    seg_id = np.full(i0.size, -1)
    win_id = np.full(i0.size, -1)
    for j, (seg, win) in enumerate(segments):
        a, b = int(seg.start or 0), int(seg.stop if seg.stop is not None else n)
        seg_id[(i0 >= a) & (i1 <= b)] = j
        if win is not None:
            win_id[(i0 >= int(win.start)) & (i1 <= int(win.stop))] = j
    scored = i0 >= start
    use = scored | (win_id >= 0)
    i0, i1, seg_id, win_id, scored = i0[use], i1[use], seg_id[use], win_id[use], scored[use]
    t0 = t[i0] - t[0]
    return Blocks(i0=i0, i1=i1, t0_s=t0, t1_s=t0 + (i1 - i0) * dt, scored=scored, segment=seg_id, window=win_id)


# ============================================================================ noise covariances
def _second_difference(F, a0, a1, b0, b1):
    """F(a1, b1) − F(a1, b0) − F(a0, b1) + F(a0, b0) over every pair (rows a, columns b)."""
    if F is _F_flicker:
        kernel = _flicker_kernel()
        if kernel is not None:
            return kernel(*(np.ascontiguousarray(x, dtype=float) for x in (a0, a1, b0, b1)))
    return (
        F(a1[:, None], b1[None, :])
        - F(a1[:, None], b0[None, :])
        - F(a0[:, None], b1[None, :])
        + F(a0[:, None], b0[None, :])
    )


_KERNEL: list = []


def _flicker_kernel():
    """The flicker second difference as one compiled loop (numba), or None without numba.

    The numpy form makes ~15 passes over four M×M temporaries per block covariance (M ≈ 800–1500
    blocks: it was the largest single cost of a calibration with ``covariance="noise_model"``);
    the loop evaluates each entry's four F values in registers. Per entry it performs the same
    IEEE operations in the same order as :func:`_F_flicker` (no fastmath, so no reassociation);
    only ``log`` comes from the C library instead of numpy's vectorised one, which may differ in
    the last bit; the second difference's cancellation turns that into ~4e-11 of the largest
    entry (measured, M = 1500; tests/gyrocore/calib/test_budget.py bounds it at 1e-9).
    """
    if not _KERNEL:
        try:
            import numba
        except ImportError:  # pragma: no cover - numba is a dependency
            _KERNEL.append(None)
            return None
        _KERNEL.append(numba.njit(cache=True)(_flicker_second_difference_loop))
    return _KERNEL[0]


def _flicker_second_difference_loop(a0, a1, b0, b1):
    """Loop form of ``_second_difference(_F_flicker, a0, a1, b0, b1)`` (compiled by :func:`_flicker_kernel`)."""
    sa0, sa1, sb0, sb1 = np.sqrt(a0), np.sqrt(a1), np.sqrt(b0), np.sqrt(b1)
    C = np.empty((a0.size, b0.size))
    for i in range(a0.size):
        for j in range(b0.size):
            acc = 0.0
            for k in range(4):  # + F(a1, b1) − F(a1, b0) − F(a0, b1) + F(a0, b0)
                x, sx = (a1[i], sa1[i]) if k < 2 else (a0[i], sa0[i])
                y, sy = (b1[j], sb1[j]) if k % 2 == 0 else (b0[j], sb0[j])
                d = abs(x - y)
                lg = d * d / 8.0 * math.log((sx + sy) ** 2 / d) if d > 0 else 0.0
                f = (4.0 / math.pi) * ((x + y) / 4.0 * sx * sy - lg)
                acc = acc + f if k == 0 or k == 3 else acc - f
            C[i, j] = acc
    return C


def _F_flicker(a, c):
    # square roots on the unbroadcast vectors (M each, not M²), the M² work in place; the same
    # IEEE operations per entry in the same order as the plain expression
    # (4/π)·((a+c)/4·√a·√c − [d>0]·d²/8·ln((√a+√c)²/d)), d = |a−c|, so bit-identical to it
    sa, sc = np.sqrt(a), np.sqrt(c)
    d = np.abs(a - c)
    pos = d > 0
    lg = sa + sc
    np.square(lg, out=lg)
    np.divide(lg, np.where(pos, d, 1.0), out=lg)
    with np.errstate(divide="ignore", invalid="ignore"):
        np.log(lg, out=lg)
        d *= d
        d /= 8.0
        np.multiply(d, lg, out=lg)
    lg[~pos] = 0.0
    out = a + c
    out /= 4.0
    out *= sa
    out *= sc
    out -= lg
    out *= 4.0 / np.pi
    return out


def _F_rrw(a, c):
    lo, hi = np.minimum(a, c), np.maximum(a, c)
    return lo * lo * hi / 2.0 - lo**3 / 6.0


def block_covariance(blocks: Blocks, term: str, *, tau_c_s: float = np.inf) -> np.ndarray:
    """Covariance of the block means of one unit-level noise term, (M, M), (rad/s)² per unit².

    ``term``: ``"arw"`` (N = 1 rad/√s), ``"bias_instability"`` (B = 1 rad/s), ``"rrw"``
    (K = 1 rad/s/√s) or ``"correlated"`` (σ = 1 rad/s, correlation time ``tau_c_s``). See the
    module docstring for the formulas.
    """
    a0, a1 = blocks.t0_s, blocks.t1_s
    d = blocks.dt_s
    if term == "arw":
        return np.diag(1.0 / d)
    if term == "bias_instability":
        C = _second_difference(_F_flicker, a0, a1, a0, a1)
    elif term == "rrw":
        C = _second_difference(_F_rrw, a0, a1, a0, a1)
    elif term == "correlated":
        tc = float(tau_c_s)

        def phi(x):
            x = np.abs(x)
            return tc * tc * (x / tc - 1.0 + np.exp(-x / tc))

        C = (
            phi(a1[:, None] - a0[None, :])
            + phi(a0[:, None] - a1[None, :])
            - phi(a1[:, None] - a1[None, :])
            - phi(a0[:, None] - a0[None, :])
        )
    else:
        raise GyroInputError(f"unknown noise term {term}")
    C = 0.5 * (C + C.T)
    return C / (d[:, None] * d[None, :])


# ============================================================================ trajectory sums
def rotation_matrices(q_SW_wxyz: np.ndarray) -> np.ndarray:
    """R_WS (S → W) from quaternions w, x, y, z, shape (N, 3, 3)."""
    return quat_to_R(np.asarray(q_SW_wxyz, float))


def _block_sums(x: np.ndarray, blocks: Blocks) -> np.ndarray:
    """Σ over each block's samples of x (N, ...) -> (M, ...)."""
    cs = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)])
    return cs[blocks.i1] - cs[blocks.i0]


def _group_design(group: ParameterGroup, inp: E.ModelInputs, sl: slice) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Regressors of a group on samples ``sl``: names, A (n, 3, P), standard errors (P,)."""
    sub = E.ModelInputs(
        t_s=np.asarray(inp.t_s)[sl],
        omega_S_rad_s=None if inp.omega_S_rad_s is None else np.asarray(inp.omega_S_rad_s)[sl],
        f_S_m_s2=None if inp.f_S_m_s2 is None else np.asarray(inp.f_S_m_s2)[sl],
        temp_c=None if inp.temp_c is None else np.asarray(inp.temp_c)[sl],
        q_SW_wxyz=None if inp.q_SW_wxyz is None else np.asarray(inp.q_SW_wxyz)[sl],
        t_since_power_up_s=None if inp.t_since_power_up_s is None else np.asarray(inp.t_since_power_up_s)[sl],
    )
    names, cols, ses = [], [], []
    for eff, pd in group.params.items():
        se_d = group.stderr.get(eff, {})
        if eff in ("bias_thermal", "scale_thermal"):
            key = "poly_rad_s" if eff == "bias_thermal" else "poly_per_c"
            coef = np.asarray(pd[key], float)
            order = coef.shape[1] if coef.ndim == 2 else 1
            nm, A = E.design(eff, sub, order=order, t0_c=float(np.asarray(pd["t0_c"])))
            se = np.asarray(se_d.get(key, np.zeros_like(coef)), float).reshape(-1)
        else:
            nm, A = E.design(eff, sub)
            pname = next(iter(E.PARAM_SCHEMA[eff]))
            se = np.asarray(se_d.get(pname, np.zeros(len(nm))), float).reshape(-1)
        names += [f"{eff}.{x}" for x in nm]
        cols.append(A)
        ses.append(se)
    A = np.concatenate(cols, axis=2) if cols else np.zeros((sub.n, 3, 0))
    se = np.concatenate(ses) if ses else np.zeros(0)
    return names, A, se


def _window_slices(blocks: Blocks, n_windows: int) -> list[np.ndarray]:
    return [np.flatnonzero(blocks.window == j) for j in range(n_windows)]


def _pj(P: np.ndarray, blocks: Blocks, n_seg: int) -> np.ndarray:
    """P_j(t_m) = Σ_{b ≤ m, scored, segment j} P_b: (J, M, 3, 3)."""
    out = np.zeros((n_seg, blocks.m, 3, 3))
    for j in range(n_seg):
        w = (blocks.scored & (blocks.segment == j)).astype(float)
        out[j] = np.cumsum(P * w[:, None, None], axis=0)
    return out


def _sensitivity_from(
    design_fn, n: int, dt: float, R_WS: np.ndarray, blocks: Blocks, n_seg: int, chunk: int = 50_000
) -> np.ndarray:
    """S(t_m) (M, 3, P) for regressors ``design_fn(slice) -> A (n, 3, P)``."""
    Z = Asum = None
    for a in range(0, n, chunk):
        sl = slice(a, min(n, a + chunk))
        A = design_fn(sl)
        RA = np.einsum("nij,njp->nip", R_WS[sl], A)
        lo = np.clip(blocks.i0 - a, 0, sl.stop - a)
        hi = np.clip(blocks.i1 - a, 0, sl.stop - a)
        cs = np.concatenate([np.zeros((1,) + RA.shape[1:]), np.cumsum(RA, axis=0)])
        ca = np.concatenate([np.zeros((1,) + A.shape[1:]), np.cumsum(A, axis=0)])
        z, s = cs[hi] - cs[lo], ca[hi] - ca[lo]
        Z = z if Z is None else Z + z
        Asum = s if Asum is None else Asum + s
    P = _block_sums(R_WS, blocks) * dt
    Pj = _pj(P, blocks, n_seg)
    S = np.cumsum(Z * dt * blocks.scored[:, None, None], axis=0)
    for j, idx in enumerate(_window_slices(blocks, n_seg)):
        if idx.size:
            nsamp = float(np.sum(blocks.i1[idx] - blocks.i0[idx]))
            S = S - np.einsum("mij,jp->mip", Pj[j], Asum[idx].sum(axis=0) / nsamp)
    return S


def sensitivity(
    inp: E.ModelInputs, R_WS: np.ndarray, blocks: Blocks, segments, group: ParameterGroup, *, chunk: int = 50_000
) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Linear sensitivity S(t_m) of the attitude error (W, rad) to each parameter of a group.

    ε(t_m) = −S(t_m)·δθ at the block ends t_m (see the module docstring).

    Parameters
    ----------
    inp : ModelInputs
        True rate, force, temperature of the scored recording.
    R_WS : ndarray (N, 3, 3)
        True attitude (:func:`rotation_matrices`).
    blocks : Blocks
    segments : list of (segment slice, window slice or None)
    group : ParameterGroup

    Returns
    -------
    names : list of str
    S : ndarray, shape (M, 3, P)
        rad per unit of each parameter (SI).
    se : ndarray, shape (P,)
        The group's standard errors in the same order.
    """
    names, _, se = _group_design(group, inp, slice(0, 2))
    dt = float(np.median(np.diff(np.asarray(inp.t_s, float))))
    S = _sensitivity_from(lambda sl: _group_design(group, inp, sl)[1], inp.n, dt, R_WS, blocks, len(segments), chunk)
    return names, S, se


# ============================================================================ prediction
@dataclass(frozen=True, eq=False)
class ErrorPrediction:
    """Predicted attitude error of a corrected gyro along a trajectory.

    Attributes
    ----------
    t_s : ndarray (M,)
        Times since the start of scoring (block ends), s.
    var_rad2 : dict
        ``{component: ndarray (M,)}``: each source's contribution to E|ε(t)|², rad².
        Components: ``noise:<term>`` (the noise term with the power-up window subtraction),
        ``param:<group>`` (a parameter group's standard errors), ``uncorrected:<effect>``
        (a deterministic term left in the gyro), ``stale bias`` (a segment without a still
        window, corrected with a stale bias).
    floor_var_rad2 : dict
        ``{noise term: ndarray (M,)}``: the floor (noise integrated without window subtraction).
    predicted : tuple of str
        Components that make up the prediction for a calibration that does what it claims
        (all but ``uncorrected:`` effects the calibration should have corrected).
    final_cov_rad2 : ndarray (3, 3)
        Covariance of ε at the last time (predicted components).
    notes : tuple of str
    """

    t_s: np.ndarray
    var_rad2: Mapping[str, np.ndarray]
    floor_var_rad2: Mapping[str, np.ndarray]
    predicted: tuple[str, ...]
    final_cov_rad2: np.ndarray
    notes: tuple[str, ...] = ()
    format_version: str = FORMAT_VERSION

    def _mean(self, v: np.ndarray) -> float:
        t = np.concatenate([[0.0], self.t_s])
        y = np.concatenate([[0.0], v])
        T = t[-1] - t[0]
        return float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(t)) / T) if T > 0 else float(v[-1])

    def total_var_rad2(self, components: Sequence[str] | None = None) -> np.ndarray:
        comps = self.predicted if components is None else components
        out = np.zeros_like(self.t_s)
        for c in comps:
            out = out + self.var_rad2[c]
        return out

    @property
    def rms_predicted_deg(self) -> float:
        """sqrt(time mean of E|ε|²) of the predicted components, degrees."""
        return math.degrees(math.sqrt(max(self._mean(self.total_var_rad2()), 0.0)))

    @property
    def final_predicted_deg(self) -> float:
        """sqrt(E|ε(T)|²), degrees."""
        return math.degrees(math.sqrt(max(float(self.total_var_rad2()[-1]), 0.0)))

    @property
    def rms_with_uncorrected_deg(self) -> float:
        return math.degrees(math.sqrt(max(self._mean(self.total_var_rad2(list(self.var_rad2))), 0.0)))

    @property
    def rms_floor_deg(self) -> float:
        v = sum(self.floor_var_rad2.values()) if self.floor_var_rad2 else np.zeros_like(self.t_s)
        return math.degrees(math.sqrt(max(self._mean(np.asarray(v)), 0.0)))

    @property
    def final_floor_deg(self) -> float:
        v = sum(self.floor_var_rad2.values()) if self.floor_var_rad2 else np.zeros_like(self.t_s)
        return math.degrees(math.sqrt(max(float(np.asarray(v)[-1]), 0.0)))

    @property
    def final_sd_rad2(self) -> float:
        """sd of |ε(T)|²: √(2·tr C²) (Gaussian ε, covariance C)."""
        C = self.final_cov_rad2
        return float(math.sqrt(2.0 * np.trace(C @ C)))

    def budget_deg(self, *, rms: bool = True) -> dict[str, float]:
        """Each component's share as a signed RMS-equivalent angle, degrees:
        sign(v)·sqrt(|v|) of its time-mean (``rms``) or final variance. The squares add up to
        the total. ``powerup window`` = noise with the window subtraction − the floor (the
        power-up bias's own noise; negative where it removes more slow noise than it adds)."""
        comps: dict[str, np.ndarray] = {}
        win = np.zeros_like(self.t_s)
        for k, v in self.var_rad2.items():
            if k.startswith("noise:"):
                term = k[len("noise:") :]
                fl = self.floor_var_rad2.get(term, np.zeros_like(v))
                comps[f"floor:{term}"] = fl
                win = win + (v - fl)
            else:
                comps[k] = v
        if any(k.startswith("noise:") for k in self.var_rad2):
            comps["powerup window"] = win
        out = {}
        for k, v in comps.items():
            x = self._mean(v) if rms else float(v[-1])
            out[k] = math.copysign(math.degrees(math.sqrt(abs(x))), x)
        return out


def _noise_var(
    blocks: Blocks,
    P: np.ndarray,
    Pj: np.ndarray,
    wins: list[np.ndarray],
    C: np.ndarray,
    levels2: np.ndarray,
    *,
    white: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """E|ε(t_m)|² of one noise term (with windows) and of its floor (without); and the
    final 3×3 covariance. ``C`` unit block-mean covariance, ``levels2`` (3,) per-axis level²."""
    M = blocks.m
    sc = blocks.scored.astype(float)
    Ps = P * sc[:, None, None]
    d = blocks.dt_s
    # T1: Σ_k L_k² Σ_{b,c ≤ m} (P_b[:,k]·P_c[:,k]) C(b,c)
    G = np.einsum("bik,cik,k->bc", Ps, Ps, levels2, optimize=True) * C
    r = np.tril(G).sum(axis=1)
    T1 = np.cumsum(2.0 * r - np.diag(G))
    if white:  # within-block rotation: ∫_b |R[:,k]|² = Δ_b exactly
        corr = (levels2[None, :] * (d[:, None] - np.einsum("bik,bik->bk", Ps, Ps) / d[:, None])) * sc[:, None]
        T1 = T1 + np.cumsum(corr.sum(axis=1))
    floor = T1.copy()
    total = T1.copy()
    # window weights: ξ_j = Σ_{b ∈ j} w_b z_b, w_b = Δ_b / T_wj
    wv = []
    for idx in wins:
        w = np.zeros(M)
        if idx.size:
            w[idx] = d[idx] / d[idx].sum()
        wv.append(w)
    J = len(wins)
    # cross terms  −2 Σ_j Σ_k L_k² P_j(t_m)[:,k]·Y_j(m)[:,k],  Y_j(m) = Σ_{b ≤ m} P_b c_j(b)
    for j in range(J):
        if not wins[j].size:
            continue
        cj = C @ wv[j]  # Cov(z_b, ξ_j)
        Y = np.cumsum(Ps * cj[:, None, None], axis=0)  # (M, 3, 3)
        total = total - 2.0 * np.einsum("mik,mik,k->m", Pj[j], Y, levels2)
        for jj in range(J):
            if not wins[jj].size:
                continue
            cw = float(wv[j] @ C @ wv[jj])
            total = total + cw * np.einsum("mik,mik,k->m", Pj[j], Pj[jj], levels2)
    # final covariance (3×3): weights W_b = P_b·scored − Σ_j P_j(T) w_j(b)
    W = Ps.copy()
    for j in range(J):
        if wins[j].size:
            W = W - Pj[j][-1][None, :, :] * wv[j][:, None, None]
    cov = np.einsum("bik,cjk,k,bc->ij", W, W, levels2, C, optimize=True)
    if white:  # within-block rotation term (its trace, spread isotropically)
        cov = cov + np.eye(3) * float(corr.sum()) / 3.0
    return total, floor, cov


def predict_error(
    inp: E.ModelInputs,
    *,
    start: int,
    segments: Sequence[tuple[slice, slice | None]],
    noise: NoiseModel,
    groups: Sequence[ParameterGroup] = (),
    uncorrected: Mapping[str, np.ndarray] | None = None,
    expected_uncorrected: Sequence[str] = (),
    stale_bias_sigma_rad_s: np.ndarray | None = None,
    exact_error_rad: Mapping[str, np.ndarray] | None = None,
    floor_exact_error_rad: Mapping[str, np.ndarray] | None = None,
    max_blocks: int = 800,
) -> ErrorPrediction:
    """Predict the attitude error of the corrected gyro along a trajectory.

    Parameters
    ----------
    inp : ModelInputs
        The scored recording's inputs with the *true* rate ``omega_S_rad_s`` (S, rad/s), the
        true attitude ``q_SW_wxyz``, specific force (S, m/s²) and temperature (°C), shape (N, ·).
        Sample times from the power-up (flicker and RRW start there).
    start : int
        First scored sample (integration starts there from the true attitude).
    segments : list of (segment slice, window slice or None)
        Power-up segments and the still window whose mean is subtracted in each.
    noise : NoiseModel
    groups : sequence of ParameterGroup
        Fitted effects with standard errors (independent groups; diagonal covariance).
    uncorrected : dict, optional
        ``{label: δω (N, 3) rad/s}``: deterministic rate errors left in the corrected gyro
        (e.g. an effect the calibration did not estimate, the on-chip low-pass).
    expected_uncorrected : sequence of str
        Labels of ``uncorrected`` that belong to the prediction (irreducible terms, e.g. the
        low-pass); the others are reported but not predicted.
    stale_bias_sigma_rad_s : ndarray (3,), optional
        σ of the bias error in segments without a still window (turn-on repeatability).
    exact_error_rad : dict, optional
        ``{label: ndarray (N − start,)}``: deterministic error-angle series computed exactly
        (e.g. the integration of the true rate plus the low-pass error by the scorer's own
        integrator): |e|² enters the prediction as component ``label`` (zero-mean random
        errors add to it in expectation, ε = e + random).
    floor_exact_error_rad : dict, optional
        The same for the floor (e.g. the integrator's error on the true rate alone).
    max_blocks : int
        Block grid size (accuracy vs time: the quadratic forms cost O(M²)).

    Returns
    -------
    ErrorPrediction
    """
    t = np.asarray(inp.t_s, float)
    n = t.size
    if inp.q_SW_wxyz is None:
        raise GyroInputError("predict_error needs the true attitude q_SW_wxyz")
    if not 0 <= start < n - 1:
        raise GyroInputError(f"scoring start {start} outside the recording (N = {n})")
    dt = float(np.median(np.diff(t)))
    rate = 1.0 / dt
    blocks = make_blocks(t, start=start, segments=segments, max_blocks=max_blocks)
    R = rotation_matrices(inp.q_SW_wxyz)
    P = _block_sums(R, blocks) * dt
    J = len(segments)
    Pj = _pj(P, blocks, J)
    wins = _window_slices(blocks, J)
    sc = blocks.scored
    t_m = blocks.t1_s[sc] - blocks.t0_s[sc][0]
    var: dict[str, np.ndarray] = {}
    floor: dict[str, np.ndarray] = {}
    notes: list[str] = []
    cov_final = np.zeros((3, 3))
    levels = {
        "arw": noise.white_var_rad2_s(rate),
        "bias_instability": np.asarray(noise.bias_instability_rad_s, float) ** 2,
        "rrw": np.asarray(noise.rrw_rad_per_s_sqrt_s, float) ** 2,
    }
    for term, L2 in levels.items():
        if not np.any(L2 > 0):
            continue
        C = block_covariance(blocks, term)
        tot, fl, cov = _noise_var(blocks, P, Pj, wins, C, L2, white=(term == "arw"))
        var[f"noise:{term}"] = tot[sc]
        floor[term] = fl[sc]
        cov_final += cov
    gs, gt = np.asarray(noise.correlated_sigma_rad_s, float), np.asarray(noise.correlated_tau_c_s, float)
    if np.any(gs > 0):
        tot = np.zeros(blocks.m)
        fl = np.zeros(blocks.m)
        for k in range(3):  # per-axis correlation time
            if gs[k] <= 0:
                continue
            L2 = np.zeros(3)
            L2[k] = gs[k] ** 2
            C = block_covariance(blocks, "correlated", tau_c_s=float(gt[k]))
            a, b, cov = _noise_var(blocks, P, Pj, wins, C, L2, white=False)
            tot, fl, cov_final = tot + a, fl + b, cov_final + cov
        var["noise:correlated"] = tot[sc]
        floor["correlated"] = fl[sc]
    for g in groups:
        names, S, se = sensitivity(inp, R, blocks, segments, g)
        se = np.where(np.isfinite(se), se, 0.0)
        v = np.einsum("mip,p->m", S**2, se**2)
        var[f"param:{g.name}"] = v[sc]
        cov_final += np.einsum("ip,jp,p->ij", S[-1], S[-1], se**2)
    for label, dw in (uncorrected or {}).items():
        dw = np.asarray(dw, float)
        e = _sensitivity_from(lambda sl, dw=dw: dw[sl][:, :, None], n, dt, R, blocks, J)[:, :, 0]
        var[f"uncorrected:{label}"] = np.sum(e * e, axis=1)[sc]
        if label in expected_uncorrected:
            cov_final += np.outer(e[-1], e[-1])
    if stale_bias_sigma_rad_s is not None:
        sb2 = np.asarray(stale_bias_sigma_rad_s, float) ** 2
        v = np.zeros(blocks.m)
        for j, (_, win) in enumerate(segments):
            if win is None:
                v = v + np.einsum("mik,k->m", Pj[j] ** 2, sb2)
        if np.any(v > 0):
            var["stale bias"] = v[sc]
            notes.append("segments without a still window: bias from the calibration run (turn-on repeatability)")
    at = blocks.i1[sc] - 1 - start
    for label, e in (exact_error_rad or {}).items():
        var[label] = np.asarray(e, float)[at] ** 2
    for label, e in (floor_exact_error_rad or {}).items():
        floor[label] = np.asarray(e, float)[at] ** 2
    predicted = tuple(
        k for k in var if not k.startswith("uncorrected:") or k[len("uncorrected:") :] in expected_uncorrected
    )
    return ErrorPrediction(
        t_s=t_m, var_rad2=var, floor_var_rad2=floor, predicted=predicted, final_cov_rad2=cov_final, notes=tuple(notes)
    )
