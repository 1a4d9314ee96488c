"""Thermal calibration: polynomial order chosen from the data, PX4 ``TC_G*`` export.

Bias and scale as polynomials of T − T0 (``bias_thermal``, ``scale_thermal`` of the
catalogue; the constant term is ``bias`` / ``scale``). The order is not fixed at 3: for each
thermal effect, orders p = max_order, …, 1 are tested top-down with a Wald test of the
order-p coefficients (3 per effect, one per axis) = 0, using the fit's own covariance — the
autocorrelation-robust one when the residual is coloured, which it is whenever the thermal
model is short of the truth — and the first significant order (p < ``alpha``) is chosen. An
effect whose linear term is not significant either gets order 1 (the user declared it) and
the table says so. T0 (the mean temperature of the fitted data) and the valid range
[min, max] are recorded; ``effects.deterministic``/``correct`` clamp T to that range and
:meth:`gyrocore.calib.params.CalibrationResult.apply` warns how many samples were outside.

PX4's thermal compensation (``src/modules/temperature_compensation``) computes per axis
offset(T) = X0 + X1·dT + X2·dT² + X3·dT³ with dT = clamp(T, TMIN, TMAX) − TREF and
subtracts it from the raw rate (rad/s); PX4 ≤ 1.10 then multiplied by ``TC_G0_SCL_i``.
With the catalogue model y = (1 + s)·ω + b + Σ c_k·dT^k, the export is TREF = T0,
X0 = b, Xk = c_k (k = 1..3), TMIN/TMAX = the valid range, and (legacy) SCL = 1/(1 + s).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from scipy import stats

from gyrocore.effects import registry as E
from . import lsq
from .rows import RowSource
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import atomic_write_text

__all__ = ["THERMAL_EFFECTS", "OrderTest", "select_thermal_orders", "px4_tc_params", "write_px4_params"]

THERMAL_EFFECTS = E.POLYNOMIAL  # ("bias_thermal", "scale_thermal"), from the registry


@dataclass(frozen=True)
class OrderTest:
    """One Wald test of the top-order coefficients of a thermal effect.

    Attributes
    ----------
    effect : str
    order : int
        The polynomial order whose highest coefficients were tested.
    wald : float
        θ_topᵀ·Cov⁻¹·θ_top (χ² with ``dof`` degrees of freedom under H0: they are 0).
    dof : int
    p_value : float
    cov_kind : str
        Which covariance the test used (see :class:`gyrocore.calib.lsq.LsqFit`).
    """

    effect: str
    order: int
    wald: float
    dof: int
    p_value: float
    cov_kind: str


def _top_wald(fit: lsq.LsqFit, effect: str, order: int) -> tuple[float, int]:
    sl = fit.slices[effect]
    names = fit.names[sl]
    idx = [sl.start + j for j, nm in enumerate(names) if nm.endswith(f",{order - 1}]")]
    idx = [i for i in idx if np.isfinite(fit.stderr[i])]
    if not idx:
        return 0.0, 0
    th = fit.theta[idx]
    C = fit.cov[np.ix_(idx, idx)]
    w = float(th @ np.linalg.lstsq(C, th, rcond=None)[0])
    return w, len(idx)


def select_thermal_orders(
    r: np.ndarray,
    inp: E.ModelInputs,
    effects: Sequence[str],
    *,
    max_order: int = 3,
    alpha: float = 0.01,
    fixed: Mapping[str, int] | None = None,
    **solve_options,
) -> tuple[dict[str, int], list[OrderTest]]:
    """Choose the polynomial order of each thermal effect in ``effects`` from the data.

    Parameters
    ----------
    r : ndarray, shape (N, 3), or gyrocore.calib.rows.RowSource
        Measured minus reference rate, rad/s (or a source of it and of the inputs, a window
        at a time: see :func:`gyrocore.calib.lsq.fit_effects`).
    inp : ModelInputs or None
        Needs ``temp_c``; ``omega_S_rad_s`` for ``scale_thermal``. None with a RowSource.
    effects : sequence of str
        The whole model (thermal and other effects are fitted jointly in every test).
    max_order : int
        Highest order tried (≤ 3, the catalogue and PX4 limit).
    alpha : float
        Significance level of each Wald test.
    fixed : mapping, optional
        Orders that are not to be chosen (kept as given).
    **solve_options
        Passed to :func:`gyrocore.calib.lsq.solve` (weights, average, covariance, ...).

    Returns
    -------
    orders : dict effect -> order
    tests : list of OrderTest (every test made, in order)
    """
    if not 1 <= max_order <= 3:
        raise GyroInputError(f"thermal order must be 1, 2 or 3, got {max_order}")
    has_temp = r.has_temp if isinstance(r, RowSource) else inp.temp_c is not None
    if not has_temp:
        raise GyroInputError("thermal effects need the temp_c column, which the data lack")
    orders = {e: max_order for e in effects if e in THERMAL_EFFECTS}
    orders.update({k: int(v) for k, v in (fixed or {}).items()})
    tests: list[OrderTest] = []
    for eff in [e for e in effects if e in THERMAL_EFFECTS and e not in (fixed or {})]:
        chosen = 1
        for p in range(max_order, 0, -1):
            orders[eff] = p
            fit = lsq.fit_effects(r, effects, inp, orders=orders, **solve_options)
            w, dof = _top_wald(fit, eff, p)
            pv = float(stats.chi2.sf(w, dof)) if dof else 1.0
            tests.append(OrderTest(eff, p, w, dof, pv, fit.cov_kind))
            if dof and pv < alpha:
                chosen = p
                break
        orders[eff] = chosen
    return orders, tests


# ---------------------------------------------------------------------------- PX4 export
def px4_tc_params(
    params: Mapping[str, Mapping[str, np.ndarray]], *, instance: int = 0, device_id: int = 0, legacy_scale: bool = False
) -> dict[str, float]:
    """PX4 ``TC_G<instance>_*`` parameters from fitted catalogue parameters.

    Parameters
    ----------
    params : mapping
        Must contain ``bias_thermal`` (order ≤ 3); ``bias`` (X0) and ``scale`` (legacy SCL)
        when fitted.
    instance : int
        PX4 gyro calibration slot (TC_G0..TC_G3).
    device_id : int
        Written to ``TC_G<i>_ID`` (PX4 matches it to the sensor's device id; 0 = fill in).
    legacy_scale : bool
        Also write ``TC_G<i>_SCL_0..2`` = 1/(1 + s) (PX4 ≤ 1.10 only).

    Returns
    -------
    dict name -> value (rad/s, °C)
    """
    if "bias_thermal" not in params:
        raise GyroInputError("PX4 TC_G export needs a bias_thermal fit (calibrate with --effects bias,bias_thermal)")
    if not 0 <= instance <= 3:
        raise GyroInputError(f"PX4 has gyro thermal slots 0..3, not {instance}")
    pd = params["bias_thermal"]
    poly = np.asarray(pd["poly_rad_s"], float)
    if poly.shape[1] > 3:
        raise GyroInputError(f"PX4 takes polynomials up to order 3, this one has order {poly.shape[1]}")
    b = np.asarray(params["bias"]["b_rad_s"], float) if "bias" in params else np.zeros(3)
    g = f"TC_G{instance}_"
    out: dict[str, float] = {f"{g}ID": float(device_id)}
    for i in range(3):
        out[f"{g}X0_{i}"] = float(b[i])
        for k in range(1, 4):
            out[f"{g}X{k}_{i}"] = float(poly[i, k - 1]) if k <= poly.shape[1] else 0.0
    out[f"{g}TREF"] = float(pd["t0_c"])
    out[f"{g}TMIN"] = float(pd["temp_min_c"])
    out[f"{g}TMAX"] = float(pd["temp_max_c"])
    if legacy_scale:
        s = np.asarray(params["scale"]["s"], float) if "scale" in params else np.zeros(3)
        for i in range(3):
            out[f"{g}SCL_{i}"] = float(1.0 / (1.0 + s[i]))
    out["TC_G_ENABLE"] = 1.0
    return out


def write_px4_params(
    path, params: Mapping[str, Mapping[str, np.ndarray]], *, overwrite: bool = False, **options
) -> dict[str, float]:
    """Write :func:`px4_tc_params` as a QGroundControl parameter file (tab separated:
    vehicle id, component id, name, value, MAV_PARAM_TYPE — 9 = REAL32, 6 = INT32),
    atomically. Returns the parameters."""
    p = px4_tc_params(params, **options)
    lines = [
        "# PX4 gyro thermal compensation (gyroharness): offset(T) = X0 + X1 dT + X2 dT^2 + X3 dT^3,",
        "# dT = clamp(T, TMIN, TMAX) - TREF, subtracted from the raw rate in rad/s.",
        "# Vehicle-Id Component-Id Name Value Type",
    ]
    for k, v in p.items():
        if k.endswith("_ID") or k == "TC_G_ENABLE":
            lines.append(f"1\t1\t{k}\t{int(v)}\t6")
        else:
            lines.append(f"1\t1\t{k}\t{v:.9g}\t9")
    if "scale_thermal" in params:
        lines.insert(2, "# NOTE: the fitted scale_thermal has no PX4 parameter and is not exported.")
    if not int(p[f"TC_G{options.get('instance', 0)}_ID"]):
        # PX4's TemperatureCompensation::set_sensor_id_gyro applies slot i only to the gyro whose
        # device id equals TC_G<i>_ID: 0 matches none, the set would be loaded and never used
        lines.insert(
            2,
            f"# NOTE: TC_G{options.get('instance', 0)}_ID is 0 and matches no gyro: set it to your gyro's "
            "device id (CAL_GYRO0_ID) or PX4 will not apply this set.",
        )
    atomic_write_text(path, "\n".join(lines) + "\n", overwrite=overwrite)
    return p
