"""The loop's model: the effects it can trace, their stacked window regressors and joint fit, and
which candidates the data can test.

:class:`Model` stacks the window regressors of :class:`gyrocore.loop.residual.Residual` for a
list of effects (a family term may be restricted to one axis: ``"regressor[..]@0"``) and fits
them jointly with :func:`gyrocore.calib.lsq.solve`; :func:`advance` applies a time offset
exactly (the gyro advanced by a cubic spline).
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from gyrocore.effects import registry as E
from gyrocore.calib import lsq
from gyrocore.data.recording import Recording
from . import source
from .residual import Residual
from .search import column_axis

__all__ = [
    "CANDIDATES",
    "FITTABLE",
    "COMPANION",
    "Model",
    "advance",
    "fittable",
    "split_axis",
    "with_companion",
    "params_table",
    "input_check",
]


#: Effects the loop can trace (each has linear regressors).
CANDIDATES: tuple[str, ...] = E.CORRECTABLE
FITTABLE = CANDIDATES

#: A thermal polynomial in (T − T0) with T0 ≠ the recording's mean temperature also shifts
#: the constant term, which belongs to ``bias``/``scale``: a thermal candidate is tested on top
#: of its constant companion (the test asks for more than a constant) and, when taken, is added
#: together with it.
COMPANION = {"bias_thermal": "bias", "scale_thermal": "scale"}


class Model:
    """Stacked window regressors of a list of effects."""

    def __init__(self, res: Residual, orders: Mapping[str, int]):
        self.res = res
        self.orders = dict(orders)

    def block(self, effect: str) -> tuple[list[str], np.ndarray]:
        base, axis = split_axis(effect)
        names, X = self.res.regressors(base, order=self.orders.get(base, 1))
        if axis is None:
            return names, X
        cols = [p for p, n in enumerate(names) if column_axis(n) == axis]
        return [names[p] for p in cols], X[:, :, cols]

    def design(self, effects: Sequence[str]):
        cols, names, slices, p0 = [], [], {}, 0
        for e in effects:
            n, X = self.block(e)
            cols.append(X)
            names += [f"{e}.{c}" for c in n]
            slices[e] = slice(p0, p0 + X.shape[2])
            p0 += X.shape[2]
        if not cols:
            return np.zeros((self.res.m, 3, 0)), [], {}
        return np.concatenate(cols, axis=2), names, slices

    def fit(self, effects: Sequence[str]):
        """Joint fit; returns (LsqFit or None, window residual (M,3), theta per effect)."""
        y = self.res.y_rad_s
        if not effects:
            return None, y.copy()
        X, names, slices = self.design(effects)
        with np.errstate(invalid="ignore"):  # a negative HAC variance comes back as NaN = not testable
            if self.res.kind == "angles":
                # a few known angles among still windows: weighted least squares with the known
                # angle uncertainty on the rotation windows and the still windows' own scatter;
                # the covariance is s²(AᵀWA)⁻¹ (s² ≈ 1 when the weights are right)
                f = lsq.solve(
                    y,
                    X,
                    names,
                    slices,
                    weights=self.angle_weights(),
                    covariance="ols",
                    axis_weighting=False,
                    on_unobservable="drop",
                    min_excitation_snr=0.0,
                )
            else:
                f = lsq.solve(y, X, names, slices, covariance="hac", on_unobservable="drop", min_excitation_snr=0.0)
        return f, f.residual_rad_s

    def angle_weights(self) -> np.ndarray:
        """Row weights 1/σ² for the ``angles`` residual, (M, 3)."""
        if "angle_w" not in self.__dict__:
            res = self.res
            rot = res.is_rotation
            T = res.duration_s
            w = np.ones((res.m, 3))
            still = ~rot
            if still.sum() >= 3:
                sd = np.std(res.y_rad_s[still], axis=0, ddof=1)
                w[still] = 1.0 / np.maximum(sd, 1e-12) ** 2
            # per component: σ_i² = σ_angle²·u_i² + σ_across²·(1 − u_i²), u = φ/|φ|; an axis
            # error δ moves exp(φ) by 2|sin(φ/2)|·δ across the axis (nothing for whole turns):
            # σ_across = max(σ_angle, 2|sin(φ/2)|·σ_axis) (exact for rotations about a sensor axis)
            phi = res.angle_S_rad[rot] if res.angle_S_rad is not None else np.zeros((rot.sum(), 3))
            ang = np.linalg.norm(phi, axis=1)
            u2 = np.where(ang[:, None] > 0, (phi / np.where(ang > 0, ang, 1.0)[:, None]) ** 2, 1.0 / 3)
            s_across = np.maximum(res.angle_sigma_rad, 2 * np.abs(np.sin(ang / 2)) * res.axis_sigma_rad)
            if res.angle_mode == "axis":  # nothing known across the axis
                s_across = np.full_like(s_across, 1e6)
            var = res.angle_sigma_rad**2 * u2 + s_across[:, None] ** 2 * (1 - u2)
            w[rot] = T[rot, None] ** 2 / var
            self.angle_w = w
        return self.angle_w

    def correction(self, fit, effects: Sequence[str]) -> np.ndarray:
        """Per-sample correction Σ A_e·θ_e, rad/s, (N, 3)."""
        terms = []
        for e in effects if fit is not None else ():
            base, axis = split_axis(e)
            th = fit.effect_theta(e)
            if axis is not None:  # one axis of a family term: the other columns are 0
                names = self.res.regressors(base, order=1)[0]
                full = np.zeros(len(names))
                full[[p for p, n in enumerate(names) if column_axis(n) == axis]] = th
                th = full
            terms.append((base, th, self.orders.get(base, 1)))
        if self.res.lazy:
            # a recording on disk: the correction is computed a window at a time where it is used
            return self.res.correction_rows(terms)
        c = np.zeros((self.res.inputs.n, 3))
        for base, th, order in terms:
            c += self.res.sample_correction(base, th, order=order)
        return c


def advance(rec: Recording, tau_s: float) -> Recording:
    """The recording with the gyro advanced by τ: gyro'(t) = gyro(t + τ) (cubic spline, ends
    held), which undoes a lag τ of the gyro behind the reference exactly (no linearisation); a
    recording on disk is advanced a window at a time as it is read (:mod:`gyrocore.loop.source`)."""
    return source.of(rec).advance(tau_s)


def fittable(effect: str) -> bool:
    """A declared effect the loop fits: a catalogue effect with linear regressors, or a
    registered family term (``periodic[..]``, ``step[..]``, ``regressor[..]``)."""
    if effect in FITTABLE:
        return True
    return "[" in effect and bool(getattr(E.resolve(effect), "fittable", False))


def split_axis(effect: str) -> tuple[str, int | None]:
    """Internal name of one axis of a family term, ``"regressor[omega_x*omega_y]@0"`` ->
    (``"regressor[omega_x*omega_y]"``, 0); other names -> (name, None)."""
    if "@" in effect:
        base, ax = effect.rsplit("@", 1)
        return base, int(ax)
    return effect, None


def with_companion(current: Sequence[str], cand: str) -> list[str]:
    comp = COMPANION.get(cand)
    return [comp, cand] if comp is not None and comp not in current else [cand]


def params_table(fit, effects) -> dict:
    out = {}
    if fit is None:
        return out
    for e in effects:
        sl = fit.slices[e]
        base, _ = split_axis(e)
        out.setdefault(base, {}).update(
            {
                fit.names[p].rsplit(".", 1)[1]: [float(fit.theta[p]), float(fit.stderr[p])]
                for p in range(sl.start, sl.stop)
            }
        )
        if e == "earth_rate":
            om = fit.theta[sl]
            mag = float(np.linalg.norm(om))
            out[e]["magnitude_rad_s"] = [mag, float("nan")]
            if mag > 0:
                out[e]["latitude_rad_if_W_is_up"] = [float(np.arcsin(np.clip(om[2] / mag, -1, 1))), float("nan")]
    return out


#: Still references: g-sensitivity needs poses whose specific force differs by at least this
#: much (m/s², ≈ 0.2 g) on some axis; within one pose, changes of f mean motion, not a signal.
_MIN_POSE_CHANGE_M_S2 = 2.0


def _n_poses(f: np.ndarray, tol_m_s2: float = _MIN_POSE_CHANGE_M_S2) -> int:
    """Number of distinct static poses among window-mean specific forces f (M, 3): greedy
    clustering, a new pose when f is farther than ``tol_m_s2`` from every known pose."""
    centres: list[np.ndarray] = []
    for v in f:
        if all(np.linalg.norm(v - c) > tol_m_s2 for c in centres):
            centres.append(v)
    return len(centres)


def input_check(res: Residual, effect: str) -> str | None:
    """Reason why a candidate cannot be tested on these data, or None."""
    inp = res.inputs
    needs = {
        "bias_thermal": "temp",
        "bias_temp_rate": "temp",
        "scale_thermal": "temp",
        "g_sensitivity": "accel",
        "g2_sensitivity": "accel",
    }.get(effect)
    if needs == "temp" and inp.temp_c is None:
        return "no temp_c column"
    if needs == "accel" and inp.f_S_m_s2 is None:
        return "no accel columns"
    if needs == "accel" and res.kind in ("still", "angles"):
        f = res.window_mean(np.nan_to_num(np.asarray(inp.f_S_m_s2, float)))
        rot = res.is_rotation if res.is_rotation is not None else np.zeros(res.m, bool)
        fs = f[~rot]
        poses = _n_poses(fs)
        if poses < 2:
            return (
                "one static pose: the specific force hardly changes, so g-sensitivity is a bias here "
                "(and small changes of f mean the sensor moved)"
            )
        if poses < 3:
            return (
                "two static poses: a bias change between them (drift, warm-up) explains the same step; "
                "g-sensitivity needs three or more poses"
            )
    if effect == "earth_rate" and res.R_WS is None:
        return "no attitude to resolve the Earth rate (it is a bias in a fixed pose)"
    if effect == "time_offset" and res.kind == "angles":
        return "known angles carry no timing: a lag between gyro and reference needs a time-resolved reference"
    if (
        effect in ("scale", "scale_thermal", "scale_asymmetry", "scale_nonlinearity", "misalignment", "time_offset")
        and res.kind == "still"
    ):
        return "still data: the true rate is zero, rate-proportional errors are invisible"
    return None
