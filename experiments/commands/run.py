"""``gyroharness run``: the main job — every experiment into one report folder."""

from __future__ import annotations

import sys
import time

import click

from gyrocore.cli import emit_json

__all__ = ["command", "ESTIMATE_CPU_S"]

#: CPU seconds (user + system, workers included) each section took at each size on the project's
#: 2-core machine (`gyroharness run [--quick|--full] --json`, its ``cpu_s`` per section; docs/
#: experiments.md "The main job"). Shown beside each progress bar as the a-priori estimate; the
#: bar's own ETA takes over once the section reports steps. (The flight section's firmware grid at
#: the quick and full sizes is an extrapolation from the standard one, not a measurement.)
ESTIMATE_CPU_S: dict[str, dict[str, float]] = {
    "quick": {
        "article": 1,
        "ablation": 46,
        "cutoffs": 2,
        "close_the_loop": 7,
        "twin": 14,
        "protocol": 35,
        "flight": 30,
    },
    "standard": {
        "article": 1,
        "ablation": 100,
        "cutoffs": 19,
        "close_the_loop": 11,
        "twin": 57,
        "protocol": 42,
        "flight": 30,
    },
    "full": {
        "article": 1,
        "ablation": 511,
        "cutoffs": 160,
        "close_the_loop": 11,
        "twin": 490,
        "protocol": 278,
        "flight": 600,
    },
}


class _Bars:
    """One tqdm line per section on stderr: steps the section reports, elapsed, ETA, and the a-priori
    estimate; the section's CPU time when it ends."""

    def __init__(self, size: str, enabled: bool):
        self.size, self.enabled, self.bar = size, enabled, None

    def start(self, name: str):
        if not self.enabled:
            return None
        from tqdm import tqdm

        est = ESTIMATE_CPU_S.get(self.size, {}).get(name)
        desc = f"{name:<15s}" + (f" (~{est:.0f} s CPU)" if est else "")
        self.bar = tqdm(
            total=1,
            desc=desc,
            file=sys.stderr,
            leave=True,
            dynamic_ncols=True,
            unit="step",
            bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}]{postfix}",
        )

        def progress(done: int, total: int, bar=self.bar) -> None:
            bar.total = max(int(total), 1)
            bar.n = min(int(done), bar.total)
            bar.refresh()

        return progress

    def done(self, st) -> None:
        if self.bar is None:
            return
        if st.state == "done":
            self.bar.n = self.bar.total
        self.bar.set_postfix_str(f"{st.state}, {st.cpu_s:.0f} s CPU" if st.state == "done" else st.state, refresh=False)
        self.bar.close()
        self.bar = None


@click.command("run")
@click.option(
    "--out",
    "out_dir",
    default="out",
    show_default=True,
    type=click.Path(file_okay=False),
    help="Report folder (Markdown report.md + figures/*.png + summary.json + sections/).",
)
@click.option("--quick", is_flag=True, help="Smoke run: short recordings, few sensor instances (~2 min).")
@click.option("--full", is_flag=True, help="Research size: every campaign at its full size (~20 min of CPU).")
@click.option(
    "--seeds",
    type=click.IntRange(min=1),
    default=None,
    help="Sensor instances per scenario in the Monte Carlo parts (default: the size's own).",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=None,
    help="Worker processes for the Monte Carlo parts (default: all cores).",
)
@click.option("--only", default=None, help="Comma-separated subset of sections (default: all).")
@click.option(
    "--force",
    is_flag=True,
    help="Replace --out even if it is not a previous gyroharness report. A previous report is always replaced.",
)
@click.option("--no-progress", is_flag=True, help="No progress bars on stderr.")
@click.option("--json", "as_json", is_flag=True, help="Print a JSON summary on stdout.")
def command(out_dir, quick, full, seeds, workers, only, force, no_progress, as_json):
    """Run every section (article, ablation, cutoffs, close_the_loop, twin, protocol, flight) into one
    report folder: about 5 minutes of CPU by default, each section sized so its stated intervals
    hold; --full for the research-size campaigns, --quick for a smoke run.

    The report is built in a staging folder, each finished section saved there at once, and moved
    into place only when every section succeeded: re-running replaces a previous report in OUT
    atomically; a folder that is not a gyroharness report is refused unless --force. A failing
    section is named in one line (the others still run); Ctrl-C stops. Either way the finished
    sections are kept in OUT.incomplete and the previous report in OUT stays as it was.
    """
    from experiments import registry
    from experiments.report import ReportIncomplete, build_report

    if quick and full:
        raise click.UsageError("--quick and --full exclude each other")
    size = "quick" if quick else ("full" if full else "standard")
    names = registry.names()
    if only:
        names = [n.strip() for n in only.split(",") if n.strip()]
    exps = [(n, registry.get(n)) for n in names]
    bars = _Bars(size, enabled=not no_progress)
    flag = {"quick": " --quick", "full": " --full", "standard": ""}[size]
    t0 = time.perf_counter()
    try:
        path, results = build_report(
            exps,
            out_dir,
            force=force,
            on_start=bars.start,
            on_done=bars.done,
            quick=quick,
            size=size,
            seeds=seeds,
            workers=workers,
            preamble=(
                f"Generated by `gyroharness run{flag}" + (f" --seeds {seeds}" if seeds else "") + "`. "
                "Units: degrees for attitude errors, deg/min for drift rates, Hz for cutoffs, ms for delays. "
                "Each section states its units or replicas and the interval its figures carry."
            ),
        )
    except ReportIncomplete as exc:
        if exc.interrupted:
            click.echo(f"error: interrupted: {exc}", err=True)
            click.get_current_context().exit(130)
        raise
    wall = time.perf_counter() - t0
    import json

    doc = json.loads((path / "summary.json").read_text())
    if as_json:
        emit_json(
            {
                "out": str(path),
                "size": size,
                "wall_s": wall,
                "cpu_s": doc["cpu_s"],
                "experiments": {
                    r.name: {
                        "wall_s": r.wall_s,
                        "cpu_s": doc["sections"][r.name]["cpu_s"],
                        "figures": list(r.figures),
                        "summary": r.summary,
                    }
                    for r in results
                },
            }
        )
    else:
        for r in results:
            click.echo(
                f"{r.name:16s} {r.wall_s:7.1f} s wall {doc['sections'][r.name]['cpu_s']:7.1f} s CPU  "
                f"{len(r.figures)} figures"
            )
        click.echo(f"report: {path / 'report.md'}  ({wall:.1f} s wall, {doc['cpu_s']:.1f} s CPU)")
    if not no_progress:
        click.echo(f"total: {wall:.0f} s wall, {doc['cpu_s']:.0f} s CPU; report in {path}", err=True)
    return 0
