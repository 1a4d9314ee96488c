"""Plots of the loop: the window residual against each found effect's regressor, before and after."""

from __future__ import annotations


import numpy as np

from gyrocore.calib.stream import Rows
from .result import LoopResult

__all__ = ["plot_found"]


_NATURAL = {
    "bias_ramp": ("time since start, s", lambda r: np.repeat(r.t_mid_s[:, None] - r.inputs.t_s[0], 3, axis=1)),
    "bias_thermal": (
        "temperature, °C",
        lambda r: np.repeat(
            r.window_mean(np.repeat(np.asarray(r.inputs.temp_c, float)[:, None], 3, axis=1))[:, :1], 3, axis=1
        ),
    ),
    "bias_temp_rate": (
        "dT/dt, °C/s",
        lambda r: np.repeat(r.window_mean(np.repeat(r.inputs.temp_rate_c_s()[:, None], 3, axis=1))[:, :1], 3, axis=1),
    ),
    "scale": ("reference rate, rad/s", lambda r: r.window_mean(_as_rows(r.inputs.omega_S_rad_s))),
    "scale_asymmetry": ("reference rate, rad/s", lambda r: r.window_mean(_as_rows(r.inputs.omega_S_rad_s))),
    "scale_nonlinearity": ("reference rate, rad/s", lambda r: r.window_mean(_as_rows(r.inputs.omega_S_rad_s))),
    "time_offset": (
        "rate derivative dω/dt, rad/s²",
        lambda r: r.window_mean(
            np.gradient(np.asarray(r.inputs.omega_S_rad_s, float), np.asarray(r.inputs.t_s, float), axis=0)
        ),
    ),
}


def _as_rows(v):
    return v if isinstance(v, Rows) else np.asarray(v, float)


def plot_found(result: LoopResult, out_dir, *, max_points: int = 4000, prefix: str = "loop") -> list:
    """Residual against the found effect's regressor, before and after each step (PNG per step).

    The x axis is the effect's physical variable where it has one per axis (time, T, dT/dt,
    rate, rate derivative) and otherwise the effect's fitted contribution X·θ (a partial
    residual plot: before the step the residual follows the 1:1 line, after it is flat).

    Returns the list of written paths.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from pathlib import Path

    from gyrocore.data.recording import atomic_write_bytes
    import io

    out = Path(out_dir)
    res = result.residual
    paths = []
    if res is None:
        return paths
    D = 180.0 / np.pi
    rng = np.random.default_rng(0)  # subsampling of points only
    idx = np.arange(res.m) if res.m <= max_points else np.sort(rng.choice(res.m, max_points, replace=False))
    for k, step in enumerate(result.found):
        before, after = result.history[k], result.history[k + 1]
        eff = step.effect
        if before.shape != after.shape or before.shape[0] != res.m:
            continue  # the windows changed (re-linearised time offset dropped a glitch window)
        if eff in _NATURAL:
            xlabel, fx = _NATURAL[eff]
            x = fx(res)
        else:
            names, X = res.regressors(eff, order=1) if eff not in ("bias_thermal", "scale_thermal") else (None, None)
            th = np.array(
                [
                    step.evidence.params[n]
                    for n in step.evidence.params
                    if not n.startswith("bias.") and not n.startswith("scale.")
                ]
            )
            if X is not None and X.shape[2] == th.size:
                x = np.einsum("mip,p->mi", X, th) * D
                xlabel = f"fitted {eff} contribution X·θ, deg/s"
            else:
                x = np.repeat(res.t_mid_s[:, None], 3, axis=1)
                xlabel = "time, s"
        fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), sharey=True)
        for i, ax in enumerate(axes):
            ax.plot(x[idx, i], before[idx, i] * D, ".", ms=2, alpha=0.5, label="before")
            ax.plot(x[idx, i], after[idx, i] * D, ".", ms=2, alpha=0.5, label="after")
            ax.set_title(f"axis {'xyz'[i]}")
            ax.set_xlabel(xlabel)
            ax.grid(True, alpha=0.3)
        axes[0].set_ylabel(f"window residual, deg/s ({res.kind})")
        axes[0].legend(loc="best", markerscale=4)
        ev = step.evidence
        fig.suptitle(
            f"step {k + 1}: {eff} (F = {ev.statistic:.3g}, log10 p = {ev.log10_p:.3g}); "
            f"RMS {step.residual_rms_before_rad_s * D:.3g} -> {step.residual_rms_after_rad_s * D:.3g} deg/s"
        )
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=90)
        plt.close(fig)
        p = out / f"{prefix}_step{k + 1}_{eff}.png"
        atomic_write_bytes(p, buf.getvalue())
        paths.append(p)
    return paths
