"""``gyroharness loop``: the residual loop (DESIGN.md "Command line", "JSON of loop").

Start from the declared effects, find what the residual still holds, name the effect, add it,
refit, and report the error before and after each step.
"""

from __future__ import annotations

import math
from pathlib import Path

import click

from gyrocore.cli import emit_json
from gyrocore.readers.large import is_large


def _split(value: str | None) -> list[str] | None:
    if value is None:
        return None
    return [v.strip() for v in value.split(",") if v.strip()]


def _fmt(x: float, unit: str = "", scale: float = 1.0, digits: int = 4) -> str:
    if x is None or not math.isfinite(x):
        return "n/a"
    return f"{x * scale:.{digits}g}{unit}"


D = 180.0 / math.pi


def report_text(result) -> str:
    """The readable report of a :class:`gyrocore.loop.result.LoopResult`."""
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
    for u in result.unexplained:
        ev = u.evidence
        what = {
            "regressor": lambda f: f"term {f['term']}, coef {f['coef']:.4g} (SI)",
            "periodic": lambda f: f"{f['frequency_hz']:.6g} Hz, amplitude {f['amplitude_rad_s'] * D:.4g} deg/s",
            "step": lambda f: (
                f"at t = {f['t_s']:.6g} s, size [{', '.join(f'{v * D:.4g}' for v in f['size_rad_s'])}] deg/s"
            ),
        }[u.kind](u.fields)
        lines.append(
            f"unexplained: {u.kind} on axis {u.axis}: {what}; log10 p = {ev.get('log10_p', float('nan')):.3g} "
            f"< log10 threshold {math.log10(ev['threshold']):.3g}; residual RMS "
            f"{_fmt(u.residual_rms_before_rad_s, '', D)} -> {_fmt(u.residual_rms_after_rad_s, ' deg/s', D)} "
            f"({ev.get('residual', 'window')} level); added as {u.effect}"
        )
    if result.tested:
        top = sorted(result.tested.items(), key=lambda kv: kv[1].log10_p)[:4]
        lines.append(
            "strongest not taken: "
            + "; ".join(
                f"{c} (log10 p {ev.log10_p:.2g}, threshold {math.log10(ev.threshold):.2g}, out-of-sample RMS {-100 * ev.cv_rms_reduction:+.2g} %)"
                for c, ev in top
            )
        )
    if result.untestable:
        lines.append("not testable: " + "; ".join(f"{c}: {why}" for c, why in result.untestable.items()))
    rem = result.remaining.summary()
    lines.append(
        f"remaining: Ljung–Box p = {_fmt(rem['ljung_box_p'], '', 1, 3)} ({'white' if rem['white'] else 'not white'}); "
        f"Allan slope per axis {', '.join(_fmt(x, '', 1, 2) for x in rem['allan_slope'])} "
        "(−0.5 white, 0 flicker, +0.5 random walk)"
    )
    os_ = result.open_search
    if os_ and not result.unexplained:
        parts = []
        if "regressor" in os_ and "term" in os_["regressor"]:
            g = os_["regressor"]
            parts.append(
                f"best library term {g['term']} on {g['axis']} (log10 p {g['log10_p']:.2g}, threshold "
                f"{math.log10(g['threshold']):.2g}, {g['n_tested']} tested)"
            )
        if os_.get("periodic"):
            g = min(os_["periodic"], key=lambda d: d["log10_p"])
            parts.append(
                f"strongest line {g['frequency_hz']:.4g} Hz on {g['axis']} (log10 p {g['log10_p']:.2g}, "
                f"threshold {math.log10(g['threshold']):.2g})"
            )
        if "step" in os_:
            g = os_["step"]
            parts.append(
                f"best step at {g['t_s']:.5g} s (bootstrap p {g['bootstrap_p']:.2g}, threshold {g['threshold']:.2g})"
            )
        if parts:
            lines.append("open search, nothing significant: " + "; ".join(parts))
    for n in result.notes:
        lines.append(f"note: {n}")
    return "\n".join(lines)


def validation_text(v: dict) -> str:
    D = 180.0 / math.pi
    return (
        f"validation on {v['file']} ({v['reference']}, {v['n_windows']} windows; bias {v['bias']}): "
        f"residual RMS {_fmt(v['residual_rms_before_rad_s'], '', D)} (declared model) -> "
        f"{_fmt(v['residual_rms_after_rad_s'], ' deg/s', D)} (final model); attitude error "
        f"{_fmt(v['attitude_error_before_deg'])} -> {_fmt(v['attitude_error_after_deg'], ' deg')}"
        + "".join(_line_validation_text(p) for p in v.get("periodic", ()))
    )


def _line_validation_text(p: dict) -> str:
    D = 180.0 / math.pi
    i = max(range(3), key=lambda k: p["amplitude_before_rad_s"][k])
    return (
        f"; {p['effect']} on {'xyz'[i]}: sample-level line amplitude {p['amplitude_before_rad_s'][i] * D:.4g} -> "
        f"{p['amplitude_after_rad_s'][i] * D:.4g} ± {p['amplitude_std_error_after_rad_s'][i] * D:.2g} deg/s"
    )


@click.command("loop")
@click.argument("path", metavar="FILE", type=click.Path(path_type=str))
@click.option(
    "--effects",
    "effects",
    default="bias",
    show_default=True,
    help="Declared effects (comma-separated catalogue names) the model starts from.",
)
@click.option(
    "--segments",
    type=click.Path(path_type=str),
    default=None,
    help="Segments file: still segments and/or known rotations "
    "(t_start_s,t_end_s,kind,angle_x_deg,angle_y_deg,angle_z_deg; gyrocore.data.segments).",
)
@click.option("--candidates", default=None, help="Effects to trace (default: every traceable effect not declared).")
@click.option(
    "--reference",
    type=click.Choice(["auto", "rate", "attitude", "still", "angles"]),
    default="auto",
    show_default=True,
    help="Which reference to build the residual against.",
)
@click.option("--window-s", type=float, default=None, help="Observation window length, s.")
@click.option(
    "--alpha",
    type=float,
    default=0.01,
    show_default=True,
    help="Family-wise false-discovery rate over all candidates and steps (Holm).",
)
@click.option(
    "--thermal-order",
    type=click.IntRange(1, 3),
    default=1,
    show_default=True,
    help="Polynomial order of the thermal candidates.",
)
@click.option(
    "--min-rms-reduction",
    type=float,
    default=0.005,
    show_default=True,
    help="Practical significance: fraction of the residual RMS a new effect must remove "
    "(or --min-attitude-reduction of the attitude error); it must also predict the other half "
    "of the recording (2-fold by time).",
)
@click.option("--min-attitude-reduction", type=float, default=0.05, show_default=True)
@click.option(
    "--angle-sigma-deg",
    type=float,
    default=2.0,
    show_default=True,
    help="Uncertainty of each known rotation angle (hand: a few degrees; rate table: 0.01).",
)
@click.option(
    "--axis-sigma-deg",
    type=float,
    default=5.0,
    show_default=True,
    help="Uncertainty of the known rotations' axis (hand: ~5 degrees; rate table: 0.01).",
)
@click.option(
    "--angle-mode",
    type=click.Choice(["rotation", "axis"]),
    default="rotation",
    show_default=True,
    help="Known rotations: whole rotations (start/end poses known: table, box edge) or only the "
    "total angle about the axis (free hand turns).",
)
@click.option(
    "--plot-dir",
    type=click.Path(path_type=str),
    default=None,
    help="Write residual-vs-regressor plots (before/after) per found effect here.",
)
@click.option(
    "--open-search/--no-open-search",
    default=True,
    show_default=True,
    help="After the catalogue, describe what is still significant outside it (regressor library, "
    "narrow-band lines, bias steps); alpha is split between the catalogue and the open search.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the step test's bootstrap.")
@click.option(
    "--line-segments",
    type=int,
    default=8,
    show_default=True,
    help="Against a reference attitude: target number of gap-free segments of the sample-level line test.",
)
@click.option(
    "--line-statistic",
    type=click.Choice(["coherent", "pooled", "both"]),
    default="coherent",
    show_default=True,
    help="Against a reference attitude: the line test's statistic — phase-coherent across the segments "
    "(a periodic[f] term), pooled over them, or both (alpha split).",
)
@click.option(
    "-o",
    "--output",
    "output",
    type=click.Path(dir_okay=False, path_type=str),
    default=None,
    help="Write the final model as a parameter file (readable by apply).",
)
@click.option(
    "--validate",
    "validate",
    type=click.Path(path_type=str),
    default=None,
    help="Score the final model (and the declared model fitted on FILE) on this other recording.",
)
@click.option(
    "--validate-segments",
    type=click.Path(path_type=str),
    default=None,
    help="Segments CSV of the --validate recording.",
)
@click.option(
    "--validate-split",
    is_flag=True,
    help="Fit on the first half of FILE and score on the second half (long logs without a second file).",
)
@click.option("--force", is_flag=True, help="Overwrite an existing -o file.")
@click.option("--json", "as_json", is_flag=True, default=False, help="Print the JSON result on stdout.")
def command(
    path,
    effects,
    segments,
    candidates,
    reference,
    window_s,
    alpha,
    thermal_order,
    min_rms_reduction,
    min_attitude_reduction,
    angle_sigma_deg,
    axis_sigma_deg,
    angle_mode,
    plot_dir,
    open_search,
    seed,
    line_segments,
    line_statistic,
    output,
    validate,
    validate_segments,
    validate_split,
    force,
    as_json,
):
    """The residual loop on FILE (a data file or any real set `gyroharness convert` reads)."""
    import os

    from gyrocore.errors import GyroInputError
    from gyrocore.loop.loop import run_loop
    from gyrocore.loop.lines import AttitudeLineOptions

    if output and os.path.exists(output) and not force:
        raise GyroInputError(f"{output} exists; pass --force to overwrite it")
    declared = _split(effects) or []
    search = dict(
        declared=declared,
        candidates=_split(candidates),
        min_rms_reduction=min_rms_reduction,
        min_attitude_reduction=min_attitude_reduction,
        open_search=open_search,
        seed=seed,
    )
    model = dict(
        reference=reference,
        window_s=window_s,
        alpha=alpha,
        thermal_order=thermal_order,
        angle_sigma_deg=angle_sigma_deg,
        axis_sigma_deg=axis_sigma_deg,
        angle_mode=angle_mode,
    )
    finish = dict(path=path, output=output, plot_dir=plot_dir, thermal_order=thermal_order, as_json=as_json)
    if (
        not segments
        and not validate
        and not validate_split
        and reference in ("auto", "rate")
        and is_large(path, "loop", need=("ref_rate",))
        and _run_spilled(path, search, model, finish)
    ):
        return
    conv, segs, val_conv, validate = _fit_and_validation(path, segments, validate, validate_split)
    opts = dict(
        attitude_lines=AttitudeLineOptions(segments=line_segments, statistic=line_statistic),
        segments=segs,
        **model,
    )
    result = run_loop(conv.recording, **search, **opts)
    extra: dict = {}
    if validate_split:
        extra["fitted_on"] = f"{path} (first half, t < {conv.recording.t_s[-1]:.6g} s)"
    if validate:
        extra["validation"] = validation(
            result,
            conv.recording,
            val_conv,
            declared=declared,
            opts=opts,
            validate=validate,
            validate_segments=validate_segments,
        )
    _finish(
        result,
        conv.recording,
        **finish,
        extra=extra,
        extra_text=validation_text(extra["validation"]) if validate else None,
    )


def _run_spilled(path, search: dict, model: dict, finish: dict) -> bool:
    """Loop a long data file with reference rates a window at a time: spilled to per-column
    files (gyrocore.calib.stream.SpilledRecording); the same loop, bounded memory. False when
    the recording needs what only the in-memory path does (NaN rows in the reference)."""
    import tempfile

    from gyrocore.calib.stream import NotStreamable, SpilledRecording, bounded_heap, release_memory
    from gyrocore.data.spill import spill_columns
    from gyrocore.effects.registry import check_effect_names
    from gyrocore.loop.loop import run_loop

    check_effect_names(search["declared"])  # a misspelt effect is one error line before a long spill
    if search["candidates"]:
        check_effect_names(search["candidates"])

    bounded_heap()  # freed window arrays go back to the system (see there)
    with tempfile.TemporaryDirectory(prefix="gyroharness_loop_") as tmp:
        store = spill_columns(path, tmp, accel=True, groups=("temp", "ref_rate", "ref_quat"))
        release_memory()
        try:
            result = run_loop(SpilledRecording(store), **search, **model)
        except NotStreamable:
            return False
        _finish(result, SpilledRecording(store), **finish)
        return True


def _fit_and_validation(path, segments, validate, validate_split):
    """The recording to fit (with its segments) and the one to validate on.

    Returns ``(conv, segs, val_conv, validate)``: ``val_conv`` is None without validation;
    with ``--validate-split`` the fit is FILE's first half, the validation its second, and
    ``validate`` becomes the label of that half.
    """
    from gyrocore.data.segments import read_segments
    from gyrocore.errors import GyroInputError
    from gyrocore.readers.convert import load_with_segments

    conv = load_with_segments(path)
    segs = list(conv.segments)
    if segments:
        segs = read_segments(segments)
    val_conv = None
    if validate and validate_split:
        raise GyroInputError("give --validate OTHER or --validate-split, not both")
    if validate_split:
        from gyrocore.loop.validate import split_halves
        from gyrocore.readers.common import Converted

        if segs:
            raise GyroInputError(
                "--validate-split cuts a recording in time; known-rotation segments would be cut too "
                "(use --validate OTHER)"
            )
        first, second = split_halves(conv.recording)
        conv = Converted(recording=first, segments=())
        val_conv = Converted(recording=second, segments=())
        validate = f"{path} (second half, t >= {second.t_s[0]:.6g} s)"
    elif validate:
        from gyrocore.loop.validate import check_compatible

        val_conv = load_with_segments(validate)
        check_compatible(conv.recording, val_conv.recording, fit_name=path, val_name=validate)
    return conv, segs, val_conv, validate


def _finish(result, rec, *, path, output, plot_dir, thermal_order, as_json, extra=None, extra_text=None) -> None:
    """Parameter file, plots and report of a loop run (in memory or on a recording held on
    disk); ``extra`` keys go into the JSON after the result's, ``extra_text`` (the validation's
    report) is printed after the loop's report."""
    payload = result.to_json()
    payload.update(extra or {})
    if output:
        from gyrocore.loop.validate import loop_calibration
        from gyrocore.calib.params import save_params

        save_params(
            loop_calibration(result, rec, source_path=path, thermal_order=thermal_order), output, overwrite=True
        )
        payload["params_file"] = output
    if plot_dir:
        from gyrocore.loop.plots import plot_found

        plot_found(result, Path(plot_dir))
    if as_json:
        emit_json(payload)
    else:
        click.echo(report_text(result))
        if extra_text:
            click.echo(extra_text)
        if output:
            click.echo(f"wrote {output}")


def validation(result, rec_fit, val_conv, *, declared, opts, validate, validate_segments=None) -> dict:
    """The ``validation`` block: the final model and the declared model fitted on FILE, scored
    on the other recording (:func:`gyrocore.loop.validate.validate_model`)."""
    from gyrocore.errors import GyroInputError
    from gyrocore.loop.loop import run_loop
    from gyrocore.loop.validate import loop_parameters, validate_model
    from gyrocore.data.segments import read_segments

    base = run_loop(rec_fit, declared=declared, candidates=[], open_search=False, **opts)
    p_before, _ = loop_parameters(base, rec_fit, thermal_order=opts.get("thermal_order", 1))
    p_after, _ = loop_parameters(result, rec_fit, thermal_order=opts.get("thermal_order", 1))
    vsegs = read_segments(validate_segments) if validate_segments else list(val_conv.segments)
    try:
        v = validate_model(
            val_conv.recording,
            params_after=p_after,
            params_before=p_before,
            segments=vsegs,
            window_s=opts.get("window_s"),
        )
    except GyroInputError as exc:
        raise GyroInputError(f"--validate {validate}: {exc}") from None
    return {"file": validate, **v}
