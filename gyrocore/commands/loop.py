"""``gyroharness loop``: the residual loop (DESIGN.md "Command line", "JSON of loop").

Start from the declared effects, find what the residual still holds, name the effect, add it,
refit, and report the error before and after each step.
"""

from __future__ import annotations

import math
from pathlib import Path

import click

from ..cli import emit_json


def _split(value: str | None) -> list[str] | None:
    if value is None:
        return None
    return [v.strip() for v in value.split(",") if v.strip()]


def _fmt(x: float, unit: str = "", scale: float = 1.0, digits: int = 4) -> str:
    if x is None or not math.isfinite(x):
        return "n/a"
    return f"{x * scale:.{digits}g}{unit}"


def report_text(result) -> str:
    """The readable report of a :class:`gyrocore.loop.LoopResult`."""
    D = 180.0 / math.pi
    lines = [
        f"reference: {result.reference} — {result.description} ({result.n_windows} windows)",
        f"declared: {', '.join(result.declared) or '(none)'}",
        f"residual RMS: {_fmt(result.residual_rms_before_rad_s, ' deg/s', D)} -> "
        f"{_fmt(result.residual_rms_after_rad_s, ' deg/s', D)}; "
        f"attitude error (RMS): {_fmt(result.attitude_error_before_deg, ' deg')} -> "
        f"{_fmt(result.attitude_error_after_deg, ' deg')}",
    ]
    if not result.found:
        lines.append(f"found: nothing significant at family-wise alpha = {result.alpha:g}")
    for k, s in enumerate(result.found, 1):
        e = s.evidence
        lines.append(
            f"step {k}: {s.effect}  F = {e.statistic:.4g} (df {e.df1}, {e.df2}), log10 p = {e.log10_p:.3g} "
            f"< log10 threshold {math.log10(e.threshold):.3g}, out-of-sample RMS {-100 * e.cv_rms_reduction:+.2g} %; residual RMS {_fmt(s.residual_rms_before_rad_s, '', D)} -> "
            f"{_fmt(s.residual_rms_after_rad_s, ' deg/s', D)}, attitude {_fmt(s.attitude_error_before_deg)} -> "
            f"{_fmt(s.attitude_error_after_deg, ' deg')}"
        )
        if e.ambiguous_with:
            lines.append(f"        ambiguous with {', '.join(e.ambiguous_with)} (the data cannot tell them apart)")
        for name, v in e.params.items():
            lines.append(f"        {name} = {v:.4g} ± {e.std_errors.get(name, float('nan')):.2g} (SI)")
    if result.tested:
        top = sorted(result.tested.items(), key=lambda kv: kv[1].log10_p)[:4]
        lines.append("strongest not taken: " + "; ".join(
            f"{c} (log10 p {ev.log10_p:.2g}, threshold {math.log10(ev.threshold):.2g}, out-of-sample RMS {-100 * ev.cv_rms_reduction:+.2g} %)"
            for c, ev in top))
    if result.untestable:
        lines.append("not testable: " + "; ".join(f"{c}: {why}" for c, why in result.untestable.items()))
    rem = result.remaining.summary()
    lines.append(
        f"remaining: Ljung–Box p = {_fmt(rem['ljung_box_p'], '', 1, 3)} ({'white' if rem['white'] else 'not white'}); "
        f"Allan slope per axis {', '.join(_fmt(x, '', 1, 2) for x in rem['allan_slope'])} "
        "(−0.5 white, 0 flicker, +0.5 random walk)"
    )
    for n in result.notes:
        lines.append(f"note: {n}")
    return "\n".join(lines)


@click.command("loop")
@click.argument("path", metavar="FILE", type=click.Path(path_type=str))
@click.option("--effects", "effects", default="bias", show_default=True,
              help="Declared effects (comma-separated catalogue names) the model starts from.")
@click.option("--segments", type=click.Path(path_type=str), default=None,
              help="Segments CSV: still segments and/or known rotations (start_s,stop_s,kind,angle_x/y/z_rad, "
                   "or t_start_s,t_end_s,axis,angle_deg).")
@click.option("--candidates", default=None, help="Effects to trace (default: every traceable effect not declared).")
@click.option("--reference", type=click.Choice(["auto", "rate", "attitude", "still", "angles"]), default="auto",
              show_default=True, help="Which reference to build the residual against.")
@click.option("--window-s", type=float, default=None, help="Observation window length, s.")
@click.option("--alpha", type=float, default=0.01, show_default=True,
              help="Family-wise false-discovery rate over all candidates and steps (Holm).")
@click.option("--thermal-order", type=click.IntRange(1, 3), default=1, show_default=True,
              help="Polynomial order of the thermal candidates.")
@click.option("--min-rms-reduction", type=float, default=0.005, show_default=True,
              help="Practical significance: fraction of the residual RMS a new effect must remove "
                   "(or --min-attitude-reduction of the attitude error); it must also predict the other half "
                   "of the recording (2-fold by time).")
@click.option("--min-attitude-reduction", type=float, default=0.05, show_default=True)
@click.option("--angle-sigma-deg", type=float, default=2.0, show_default=True,
              help="Uncertainty of each known rotation angle (hand: a few degrees; rate table: 0.01).")
@click.option("--axis-sigma-deg", type=float, default=5.0, show_default=True,
              help="Uncertainty of the known rotations' axis (hand: ~5 degrees; rate table: 0.01).")
@click.option("--angle-mode", type=click.Choice(["rotation", "axis"]), default="rotation", show_default=True,
              help="Known rotations: whole rotations (start/end poses known: table, box edge) or only the "
                   "total angle about the axis (free hand turns).")
@click.option("--plot-dir", type=click.Path(path_type=str), default=None,
              help="Write residual-vs-regressor plots (before/after) per found effect here.")
@click.option("--json", "as_json", is_flag=True, default=False, help="Print the JSON result on stdout.")
def command(path, effects, segments, candidates, reference, window_s, alpha, thermal_order, min_rms_reduction,
            min_attitude_reduction, angle_sigma_deg, axis_sigma_deg, angle_mode, plot_dir, as_json):
    """The residual loop on FILE (a data file or any real set `gyroharness convert` reads)."""
    from ..convert import load_with_segments
    from ..loop import run_loop
    from ..residual import read_segments

    conv = load_with_segments(path)
    segs = list(conv.segments)
    if segments:
        segs = read_segments(segments)
    declared = _split(effects) or []
    result = run_loop(
        conv.recording, declared=declared, segments=segs, candidates=_split(candidates), reference=reference,
        window_s=window_s, alpha=alpha, thermal_order=thermal_order, min_rms_reduction=min_rms_reduction,
        min_attitude_reduction=min_attitude_reduction, angle_sigma_deg=angle_sigma_deg,
        axis_sigma_deg=axis_sigma_deg, angle_mode=angle_mode,
    )
    if plot_dir:
        from ..loop import plot_found

        plot_found(result, Path(plot_dir))
    if as_json:
        emit_json(result.to_json())
    else:
        click.echo(report_text(result))
