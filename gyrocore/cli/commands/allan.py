"""``gyroharness allan`` (alias ``gyroharness noise``): noise identification per axis (DESIGN.md).

JSON: ``{"method": "gmwm", "axes": {"x": {"arw_rad_per_sqrt_s": …, "bias_instability_rad_s": …,
"rrw_rad_per_s_sqrt_s": …, "quantization_rad": …, "rate_ramp_rad_s2": …,
"correlated_sigma_rad_s": …, "correlated_tau_c_s": …, "resolved": {…}, "ci95": {…},
"estimate": {…}, "units": {…}, "curve": {…}}, …}, "rate_hz": …, …}``; an unresolved term is
``null``.
"""

from __future__ import annotations

import io
import math

import click
import numpy as np

from gyrocore.cli import emit_json
from gyrocore.noise.spilled import allan_by_axis, t_rows
from gyrocore.readers.large import is_large
from gyrocore.errors import GyroInputError

_ASYMPTOTE = {
    # name: (label, ADEV asymptote as a function of (τ, value))
    "quantization_rad": ("Q", lambda t, v: math.sqrt(3.0) * v / t),
    "arw_rad_per_sqrt_s": ("N", lambda t, v: v / np.sqrt(t)),
    "bias_instability_rad_s": ("B", lambda t, v: math.sqrt(2 * math.log(2) / math.pi) * v * np.ones_like(t)),
    "rrw_rad_per_s_sqrt_s": ("K", lambda t, v: v * np.sqrt(t / 3.0)),
    "rate_ramp_rad_s2": ("R", lambda t, v: v * t / math.sqrt(2.0)),
}
_COLORS = {
    "quantization_rad": "tab:purple",
    "arw_rad_per_sqrt_s": "tab:blue",
    "bias_instability_rad_s": "tab:orange",
    "rrw_rad_per_s_sqrt_s": "tab:green",
    "rate_ramp_rad_s2": "tab:brown",
    "correlated_sigma_rad_s": "tab:pink",
}


def _term_adev(r, name: str, value: float, tt: np.ndarray) -> np.ndarray:
    """ADEV of one term at value ``value`` on a continuous τ grid: the IEEE 952 asymptote, and
    the exact AR(1) Allan variance for the Gauss–Markov term (at the fitted τc)."""
    from gyrocore.noise.avar import gm_avar

    if name == "correlated_sigma_rad_s":
        tc = r.estimate.get("correlated_tau_c_s")
        if not tc or not np.isfinite(tc):
            return np.full_like(tt, np.nan)
        return value * np.sqrt(gm_avar(np.maximum(tt * r.rate_hz, 1.0), 1.0 / r.rate_hz, float(tc)))
    return np.abs(_ASYMPTOTE[name][1](tt, value))


def _label(term: str) -> str:
    return {"correlated_sigma_rad_s": "GM", "correlated_tau_c_s": "GM"}.get(term) or _ASYMPTOTE.get(term, (term,))[0]


def _axes(value: str) -> list[str]:
    axes = [a.strip().lower() for a in value.split(",") if a.strip()]
    bad = [a for a in axes if a not in ("x", "y", "z")]
    if bad or not axes:
        raise GyroInputError(f"--axes takes a comma list of x,y,z, got {value!r}")
    return axes


def _dur(t_s: float) -> str:
    return f"{t_s / 3600:.3g} h" if t_s >= 5400 else (f"{t_s / 60:.3g} min" if t_s >= 90 else f"{t_s:.3g} s")


def report_text(analysis) -> str:
    """Readable table in SI and datasheet units."""
    from gyrocore.noise.model import to_datasheet_units
    from gyrocore.noise.model import IEEE_TERMS, TERMS

    lines = [
        f"method {getattr(analysis, 'method', 'gmwm')}; "
        f"{analysis.n_samples} samples, {analysis.duration_s:.1f} s sampled, rate {analysis.rate_hz:.6g} Hz"
        + (
            f"; dropped tau {', '.join(f'{t:g}' for t in analysis.dropped_taus_s)} s" if analysis.dropped_taus_s else ""
        ),
        f"{'axis':4} {'term':24} {'value (SI)':>12} {'95% interval (SI)':>27} {'datasheet':>22}",
    ]
    for ax, r in analysis.axes.items():
        terms = r.all_terms()
        for name in TERMS if r.method == "gmwm" else IEEE_TERMS:
            v = terms[name]
            lo, hi = r.interval(name)
            ds, unit = to_datasheet_units(name, v)
            if name == "correlated_tau_c_s":
                if v is None:
                    continue
                lines.append(f"{ax:4} {name:24} {v:12.4e} {f'[{lo:.3e}, {hi:.3e}]':>27} {'':>22}")
                continue
            if v is None:
                ub, unit_u = to_datasheet_units(name, hi)
                lines.append(
                    f"{ax:4} {name:24} {'unresolved':>12} "
                    f"{('< ' + format(hi, '.3e')) if math.isfinite(hi) else 'no bound from this record':>27} "
                    f"{('< ' + format(ub, '.3g') + ' ' + unit_u) if math.isfinite(hi) else '':>22}"
                )
            else:
                lines.append(f"{ax:4} {name:24} {v:12.4e} {f'[{lo:.3e}, {hi:.3e}]':>27} {f'{ds:.4g} {unit}':>22}")
        for name, other in getattr(r, "ambiguous", {}).items():
            lines.append(
                f"{ax:4} {'(' + name + ')':24} fitted {r.estimate.get(name, float('nan')):.3e} but not told "
                f"from {other} (stand-in check): unresolved"
            )
        for name, v in (getattr(r, "not_resolvable", None) or {}).items():
            need = v["needed_s"]
            lines.append(
                f"{ax:4} {'(' + name + ')':24} not resolvable at {_dur(v['record_s'])}: expected z "
                f"{v['expected_z']:.2f} < {v['threshold']:.2f} (z0.99 + z0.9) at its fitted level"
                + (f"; ≈ {_dur(need)} needed" if math.isfinite(need) else "")
            )
        chk = getattr(r, "fit_check", None)
        if chk:
            verdict = "fits" if chk["ok"] else "DOES NOT FIT (terms not to be trusted)"
            first = getattr(r, "fit_from_tau_s", float("nan"))
            lines.append(
                f"{ax:4} {'(model fit)':24} {verdict}: p = {chk['p_value']:.2g}, {chk['misses']} of "
                f"{chk['points']} points outside their 95 % interval"
                + (
                    f"; fitted from tau = {first:.3g} s (sensor low-pass below)"
                    if np.isfinite(first) and first > r.taus_s[0] * (1 + 1e-9)
                    else ""
                )
                + (
                    "; lines removed at " + ", ".join(f"{fq:.4g}" for fq in r.lines_hz) + " Hz"
                    if getattr(r, "lines_hz", ())
                    else ""
                )
            )
        i_min = int(np.argmin(r.adev_rad_s))
        lines.append(
            f"{ax:4} {'(ADEV minimum)':24} {r.adev_rad_s[i_min]:12.4e} {f'at tau = {r.taus_s[i_min]:.4g} s':>27} "
            f"{f'{r.adev_rad_s[i_min] * 180 / math.pi * 3600:.4g} deg/h':>22}"
        )
    return "\n".join(lines)


_RAD_S_TO_DEG_H = 180.0 / math.pi * 3600.0


def _datasheet(term: str, value: float) -> tuple[float, str]:
    """The term in datasheet units for the legend ('' unit when there is none)."""
    from gyrocore.noise.model import to_datasheet_units

    try:
        v, unit = to_datasheet_units(term, value)
    except Exception:  # a term without a datasheet unit
        return float("nan"), ""
    return (v, unit) if unit else (float("nan"), "")


#: terms whose dominance region is shaded (the long-τ terms; Q and N dominate short τ)
_LONG_TAU = ("bias_instability_rad_s", "rrw_rad_per_s_sqrt_s", "rate_ramp_rad_s2", "correlated_sigma_rad_s")


def plot_png(analysis, path: str) -> None:
    """ADEV with 95 % bars, each resolved term's line and 95 % band, the fitted sum, and the τ
    range where each resolved long-τ term dominates shaded; written atomically."""
    from gyrocore.data.recording import atomic_write_bytes

    fig = adev_figure(analysis)
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def adev_figure(analysis):
    """The figure of :func:`plot_png` (one panel per axis). The x-label mentions shading only
    on a panel where a long-τ term's region is shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes = list(analysis.axes.items())
    fig, ax_list = plt.subplots(1, len(axes), figsize=(5.2 * len(axes), 4.4), squeeze=False)
    for plot_ax, (name, r) in zip(ax_list[0], axes):
        tt = np.geomspace(r.taus_s[0], r.taus_s[-1], 200)
        _plot_measured_and_fit(plot_ax, r, tt)
        lo_y = float(np.min(r.adev_ci95_rad_s[:, 0])) / 3
        hi_y = float(np.max(r.adev_ci95_rad_s[:, 1])) * 3
        terms = r.all_terms()
        _plot_unresolved_bounds(plot_ax, r, terms, tt, lo_y, hi_y)
        shaded = _plot_resolved_terms(plot_ax, r, terms, tt)
        _label_panel(plot_ax, name, shaded, lo_y, hi_y)
    fig.tight_layout()
    return fig


def _plot_measured_and_fit(plot_ax, r, tt) -> None:
    """The measured ADEV with its 95 % bars, the sum of the reported terms over the fitted τ
    range, ambiguous stand-ins, narrowband lines and the unfitted short-τ range."""
    t = r.taus_s
    err = np.abs(r.adev_ci95_rad_s.T - r.adev_rad_s[None, :])
    plot_ax.errorbar(t, r.adev_rad_s, yerr=err, fmt="o", ms=3, color="k", capsize=2, label="OADEV, 95 % CI")
    # the solid line is the sum of the REPORTED terms, over the fitted τ range; a
    # stand-in that was fitted but is not reported (ambiguous) shows as the thin grey fit;
    # unresolved terms appear only as their 95 % upper bounds (dotted)
    t0 = r.fit_from_tau_s if np.isfinite(r.fit_from_tau_s) else t[0]
    fitted = t >= t0 * (1 - 1e-9)
    rep = r.reported_adev_rad_s if r.reported_adev_rad_s is not None else r.fit_adev_rad_s
    chk = r.fit_check or {}
    fit_note = (
        ""
        if not chk
        else (f"; fit p = {chk['p_value']:.2g}" if chk["ok"] else f"; MODEL DOES NOT FIT (p = {chk['p_value']:.1g})")
    )
    plot_ax.loglog(t[fitted], rep[fitted], "r-", lw=1.8, label=f"sum of reported terms ({r.method}{fit_note})")
    for k, v in (getattr(r, "ambiguous", None) or {}).items():
        # fitted, needed by the data, but not told from a stand-in: in the sum, named as open
        val = r.estimate.get(k, float("nan"))
        if k in _ASYMPTOTE and np.isfinite(val) and val > 0:
            plot_ax.loglog(
                tt,
                _term_adev(r, k, val, tt),
                "-.",
                lw=1,
                color=_COLORS.get(k, "0.4"),
                label=f"{_label(k)} = {val:.2g} or {_label(v)} (fitted, not told apart: unresolved)",
            )
    if getattr(r, "lines_hz", ()) and r.lines_adev_rad_s is not None:
        plot_ax.loglog(
            t,
            np.sqrt(rep**2 + r.lines_adev_rad_s**2),
            "--",
            color="tab:red",
            lw=0.9,
            alpha=0.7,
            label="with narrowband line(s) at "
            + ", ".join(f"{fq:.3g}" for fq in r.lines_hz)
            + " Hz (not noise, removed before the fit)",
        )
    if np.any(~fitted):
        plot_ax.axvspan(t[0] / 1.2, t0 / np.sqrt(2), color="0.6", alpha=0.15, lw=0)
        plot_ax.loglog(
            t[~fitted],
            rep[~fitted],
            ":",
            color="r",
            lw=1,
            label=f"below tau = {t0:.2g} s: sensor low-pass, not fitted (grey)",
        )


def _plot_unresolved_bounds(plot_ax, r, terms: dict, tt, lo_y: float, hi_y: float) -> None:
    """Each unresolved term's 95 % upper bound (dotted), where it falls inside the panel."""
    for term in ("quantization_rad", "bias_instability_rad_s", "rrw_rad_per_s_sqrt_s", "rate_ramp_rad_s2"):
        if terms[term] is not None or term not in r.model.ci95:
            continue
        ub = r.interval(term)[1]
        if not (np.isfinite(ub) and ub > 0):
            continue
        yb = _term_adev(r, term, ub, tt)
        keep = (yb >= lo_y) & (yb <= hi_y)
        if np.any(keep):
            plot_ax.loglog(
                tt[keep],
                yb[keep],
                ":",
                lw=0.9,
                color=_COLORS[term],
                alpha=0.8,
                label=f"{_ASYMPTOTE[term][0]} < {ub:.2g} (95 % bound, unresolved)",
            )


#: SI unit of each reported term in the legend
_TERM_UNIT = {
    "quantization_rad": "rad",
    "arw_rad_per_sqrt_s": "rad/√s",
    "bias_instability_rad_s": "rad/s",
    "rrw_rad_per_s_sqrt_s": "rad/s/√s",
    "rate_ramp_rad_s2": "rad/s²",
    "correlated_sigma_rad_s": "rad/s",
}


def _plot_resolved_terms(plot_ax, r, terms: dict, tt) -> list[str]:
    """Each resolved term's line and 95 % band, and the τ range where a long-τ term dominates
    shaded; returns the labels of the shaded terms."""
    from gyrocore.noise.model import TERMS

    shaded = []
    for term in TERMS:
        if term == "correlated_tau_c_s":
            continue
        v = terms[term]
        if v is None:
            continue
        label = {"correlated_sigma_rad_s": "GM"}.get(term) or _ASYMPTOTE[term][0]
        c = _COLORS[term]
        y = _term_adev(r, term, v, tt)
        lo_v, hi_v = r.interval(term)
        plot_ax.fill_between(
            tt, _term_adev(r, term, lo_v, tt), _term_adev(r, term, hi_v, tt), color=c, alpha=0.15, lw=0
        )
        extra = f", tc = {terms['correlated_tau_c_s']:.3g} s" if term == "correlated_sigma_rad_s" else ""
        ds, ds_unit = _datasheet(term, v)
        plot_ax.loglog(
            tt,
            y,
            "--",
            lw=1,
            color=c,
            label=f"{label} = {v:.3g} [{lo_v:.3g}, {hi_v:.3g}] {_TERM_UNIT[term]}{extra}"
            + (f" = {ds:.3g} {ds_unit}" if ds_unit else ""),
        )
        # resolvable region: where this term is the largest of the fitted terms
        others = np.zeros_like(tt)
        for o in TERMS:
            if o in (term, "correlated_tau_c_s") or terms[o] is None:
                continue
            others = np.maximum(others, _term_adev(r, o, terms[o], tt))
        dom = y > others
        if np.any(dom) and term in _LONG_TAU:
            plot_ax.axvspan(tt[dom][0], tt[dom][-1], color=c, alpha=0.07, lw=0)
            shaded.append(label)
    return shaded


def _label_panel(plot_ax, name: str, shaded: list[str], lo_y: float, hi_y: float) -> None:
    """Limits, log axes, labels (deg/h beside rad/s), title, grid and legend of one panel."""
    plot_ax.set_ylim(lo_y, hi_y)
    plot_ax.set_xscale("log")
    plot_ax.set_yscale("log")
    plot_ax.set_xlabel(
        "averaging time tau [s]"
        + (f"; shaded: where {', '.join(shaded)} dominates" if shaded else "; no long-tau term resolved")
    )
    plot_ax.set_ylabel("Allan deviation [rad/s]")
    # the datasheet unit beside the SI one (flight-controller and navigation users read deg/h)
    sec = plot_ax.secondary_yaxis("right", functions=(lambda y: y * _RAD_S_TO_DEG_H, lambda y: y / _RAD_S_TO_DEG_H))
    sec.set_ylabel("[deg/h]")
    plot_ax.set_title(f"gyro {name}")
    plot_ax.grid(True, which="both", alpha=0.3)
    plot_ax.legend(fontsize=6)


#: Files whose t + gyro columns would exceed this are analysed one axis at a time
@click.command("allan")
@click.argument("file", type=click.Path())  # a data file or any source `convert` reads (folders too)
@click.option(
    "--plot", "plot", type=click.Path(dir_okay=False), default=None, help="write a PNG of the deviation and fit"
)
@click.option("--json", "as_json", is_flag=True, help="print JSON only")
@click.option("--kalibr-yaml", type=click.Path(dir_okay=False), default=None, help="write Kalibr imu.yaml")
@click.option("--axes", "axes", default="x,y,z", show_default=True, help="comma list of axes")
@click.option(
    "--max-tau-s",
    type=float,
    default=None,
    help="largest averaging time, s (default: half the record; adev_legacy: a quarter)",
)
@click.option(
    "--kalibr-inflate", type=float, default=1.0, show_default=True, help="factor applied to the Kalibr values"
)
@click.option("--engine", type=click.Choice(["fast", "allantools"]), default="fast", show_default=True)
@click.option(
    "--method",
    type=click.Choice(["gmwm", "adev", "adev_legacy"]),
    default="gmwm",
    show_default=True,
    help="gmwm: wavelet-variance fit with Gauss-Markov terms (default); adev: IEEE 952 joint ADEV fit; "
    "adev_legacy: the earlier fit (tau <= T/4, backward elimination), the noise study's baseline",
)
@click.option(
    "--no-static-check",
    is_flag=True,
    help="skip the motion gate (by default a record with motion is cut to its longest still stretch, "
    "with a warning, or refused)",
)
@click.option("--t-from-s", type=float, default=None, help="analyse only t >= this, s (e.g. the still part of a log)")
@click.option("--t-to-s", type=float, default=None, help="analyse only t < this, s")
def command(
    file, plot, as_json, kalibr_yaml, axes, max_tau_s, kalibr_inflate, engine, method, no_static_check, t_from_s, t_to_s
):
    """Noise identification per axis of a still recording: Allan deviation and the terms Q, N, B, K, R and a
    Gauss-Markov bias (sigma, tau_c), each with its 95 % interval (null = not resolved)."""
    from gyrocore.noise.allan import allan_analysis
    from gyrocore.noise.kalibr import kalibr_imu_yaml
    from gyrocore.data.recording import atomic_write_text
    from gyrocore.readers.convert import read_any

    if is_large(file, "allan"):
        # long files: one axis at a time (memory); the motion gate loads the three axes once
        res = allan_by_axis(
            file,
            axes=_axes(axes),
            max_tau_s=max_tau_s,
            kalibr=kalibr_yaml is not None,
            engine=engine,
            method=method,
            check_static=not no_static_check,
            t_from_s=t_from_s,
            t_to_s=t_to_s,
        )
    else:
        # only the columns the analysis needs (t, gyro; accel for Kalibr)
        # a data file: only the columns the analysis needs; any other source `convert` reads
        # (a ULog, a blackbox, a tomisuarez2 CSV, a sunsided folder, ...) through its reader
        rec = read_any(file, columns=("accel",) if kalibr_yaml is not None else ())
        if t_from_s is not None or t_to_s is not None:
            rec = rec.slice(*t_rows(rec.t_s, t_from_s, t_to_s))
        want_accel = kalibr_yaml is not None and rec.accel_m_s2 is not None
        res = allan_analysis(
            rec,
            axes=_axes(axes),
            max_tau_s=max_tau_s,
            accel=want_accel,
            engine=engine,
            method=method,
            check_static=not no_static_check,
        )
    if plot:
        plot_png(res, plot)
    if kalibr_yaml:
        atomic_write_text(kalibr_yaml, kalibr_imu_yaml(res, inflate=kalibr_inflate))
    if as_json:
        emit_json(res.to_json())
    else:
        click.echo(report_text(res))
