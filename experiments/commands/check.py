"""``gyroharness check --contract FILE.toml``: the CI gate on a calibration routine."""

from __future__ import annotations

import click

from gyrocore.cli import emit_json

from .score import routine_options, spec_from

__all__ = ["command"]


@click.command("check")
@click.option(
    "--contract",
    "contract_path",
    required=True,
    type=click.Path(dir_okay=False),
    help="Contract file (TOML): bounds per scenario, units, seed (docs/score.md).",
)
@routine_options
@click.option("--units", type=click.IntRange(min=1), default=None, help="Override the contract's units.")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Override the contract's campaign seed.")
@click.option(
    "--junit",
    "junit_path",
    default=None,
    type=click.Path(dir_okay=False),
    help="Also write JUnit XML here (one test case per bound and per failed unit).",
)
@click.option(
    "--out",
    "out_dir",
    default=None,
    type=click.Path(file_okay=False),
    help="Also write the score report (score.md, score.json, figures/) here.",
)
@click.option(
    "--suggest",
    "suggest_rate",
    type=click.FloatRange(min=0, max=1, min_open=True, max_open=True),
    default=None,
    help="Also print bounds with this false-failure rate (median of the contract's units) from this run's spread.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the JSON verdict on stdout.")
def command(
    contract_path,
    calibrator,
    fit_cmd,
    apply_cmd,
    timeout_s,
    workers,
    units,
    seed,
    junit_path,
    out_dir,
    suggest_rate,
    as_json,
):
    """Run the contract's scenarios for a routine and check every bound.

    Exit status 0 when every bound holds and no unit failed; 1 with one line per broken bound
    and per failed unit; 2 for bad input (contract, template, module).
    """
    from experiments import score as SC
    from gyrocore.data.recording import atomic_write_text

    contract = SC.load_contract(contract_path)
    res = SC.check_contract(
        contract,
        routine_spec=spec_from(calibrator, fit_cmd, apply_cmd, timeout_s),
        workers=workers,
        units=units,
        seed=seed,
    )
    if junit_path:
        atomic_write_text(junit_path, SC.junit_xml(res))
    if out_dir:
        SC.write_report(res.campaign, out_dir, res)
    sugg = SC.suggestions(res, suggest_rate) if suggest_rate else None
    if as_json:
        d = res.to_json()
        d["scenarios"] = SC.campaign_json(res.campaign)["scenarios"]
        if sugg is not None:
            d["suggested_bounds"] = sugg
        emit_json(d)
    else:
        for line in res.lines():
            click.echo(line)
        n_broken = sum(1 for c in res.checks if not c.passed)
        click.echo(
            f"contract {contract_path}: "
            + ("passed" if res.passed else "FAILED")
            + f" ({len(res.checks) - n_broken} of {len(res.checks)} bounds hold"
            + (f", {len(res.failed_units)} unit(s) failed" if res.failed_units else "")
            + ")"
        )
        if sugg is not None:
            click.echo(
                f"# bounds with false-failure rate {suggest_rate:g} for the median of {contract.units} fresh "
                f"units (from the spread of this run's {res.campaign.units} units, seed {res.campaign.seed}):"
            )
            for sc, b in sugg.items():
                click.echo(f"[scenario.{sc}]")
                for k, v in b.items():
                    click.echo(f"{k} = {v:.4g}")
    return 0 if res.passed else 1
