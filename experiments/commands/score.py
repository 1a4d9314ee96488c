"""``gyroharness score``: a user's calibration routine beside none, the core and the floor."""

from __future__ import annotations

import click

from gyrocore.cli import emit_json

__all__ = ["command", "routine_options", "spec_from"]


def routine_options(f):
    """The calibrator options shared by ``score`` and ``check``."""
    for opt in reversed(
        [
            click.option(
                "--calibrator",
                default=None,
                help="Python routine: a registered name (core, article, px4, ardupilot) or module:factory.",
            ),
            click.option(
                "--fit-cmd",
                default=None,
                help='Fit command template, e.g. "./cal fit {params} {inputs}" (run without a shell).',
            ),
            click.option(
                "--apply-cmd",
                default=None,
                help='Apply command template, e.g. "./cal apply {params} {input} {output}".',
            ),
            click.option(
                "--timeout-s",
                type=click.FloatRange(min=0, min_open=True),
                default=None,
                help="Timeout of each command step, s (default 120, or the contract's).",
            ),
            click.option(
                "--workers", type=click.IntRange(min=1), default=None, help="Worker processes (default: all cores)."
            ),
        ]
    ):
        f = opt(f)
    return f


def spec_from(calibrator, fit_cmd, apply_cmd, timeout_s) -> dict:
    spec = {"calibrator": calibrator, "fit_cmd": fit_cmd, "apply_cmd": apply_cmd}
    spec = {k: v for k, v in spec.items() if v}
    if timeout_s is not None:
        spec["timeout_s"] = float(timeout_s)
    return spec


@click.command("score")
@routine_options
@click.option("--scenarios", default=None, help="Comma-separated scenarios (default: all six).")
@click.option("--sensor", default="icm42688p", show_default=True, help="Sensor preset or TOML file.")
@click.option("--units", type=click.IntRange(min=1), default=4, show_default=True, help="Units per scenario.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Campaign seed.")
@click.option(
    "--duration-s",
    type=click.FloatRange(min=0, min_open=True),
    default=None,
    help="Scored duration of every scenario, s (default: each scenario's own).",
)
@click.option(
    "--calibration",
    type=click.Choice(["quick", "full"]),
    default="quick",
    show_default=True,
    help="Calibration runs: quick (120-s table, 300-s thermal) or the scenarios' full ones.",
)
@click.option(
    "--calibration-s",
    default=None,
    metavar="TABLE,THERMAL",
    help="Durations of the calibration runs, s (overrides --calibration), e.g. 40,60.",
)
@click.option(
    "--out",
    "out_dir",
    default=None,
    type=click.Path(file_okay=False),
    help="Write score.md, score.json and figures/score.png here.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the JSON result on stdout.")
def command(
    calibrator,
    fit_cmd,
    apply_cmd,
    timeout_s,
    workers,
    scenarios,
    sensor,
    units,
    seed,
    duration_s,
    calibration,
    calibration_s,
    out_dir,
    as_json,
):
    """Score a calibration routine: attitude error after its corrections, per scenario and unit.

    Exit status 0 when the routine ran on every unit, 1 when it failed on any (each failed unit
    gets a one-line reason), 2 for bad input.
    """
    from experiments import score as SC

    spec = spec_from(calibrator, fit_cmd, apply_cmd, timeout_s)
    scen = tuple(s.strip() for s in scenarios.split(",") if s.strip()) if scenarios else SC.DEFAULT_SCENARIOS
    cal_s = None
    if calibration_s:
        try:
            cal_s = tuple(float(x) for x in calibration_s.split(","))
            if len(cal_s) != 2 or not all(x > 0 for x in cal_s):
                raise ValueError
        except ValueError:
            raise click.BadParameter(
                f"expected TABLE,THERMAL seconds, got {calibration_s!r}", param_hint="--calibration-s"
            ) from None
    camp = SC.score_campaign(
        routine_spec=spec,
        scenarios=scen,
        sensor=sensor,
        units=units,
        seed=seed,
        durations_s={s: duration_s for s in scen},
        quick=(calibration == "quick"),
        calibration_durations_s=cal_s,
        workers=workers,
        progress=False,
    )
    report = SC.write_report(camp, out_dir) if out_dir else None
    if as_json:
        d = SC.campaign_json(camp)
        if report:
            d["report"] = str(report)
        emit_json(d)
    else:
        for sc in scen:
            s = SC.scenario_summary(camp.of(sc))
            click.echo(
                f"{sc}: user {s['rms_user_deg']:.4g}°  core {s['rms_core_deg']:.4g}°  none "
                f"{s['rms_none_deg']:.4g}°  floor {s['rms_floor_deg']:.4g}°  (RMS, median of {s['units']} units"
                + (f", {len(s['failed_units'])} failed" if s["failed_units"] else "")
                + ")"
            )
        for u in camp.failed:
            click.echo(f"failed: {u.scenario} unit {u.instance} (seed {u.seed}): {u.failed}")
        if report:
            click.echo(f"report: {report}")
    return 1 if camp.failed else 0
