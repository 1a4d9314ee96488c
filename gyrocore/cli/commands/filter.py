"""``gyroharness filter FILE``: choose the gyro filter from the pilot's own spectrum (DESIGN.md).

JSON: ``{"recommended": {"filter", "cutoff_hz", "notches_hz", "attitude_cost", "delay_ms",
"motor_noise", ...}, "as_flown": {same keys}, "firmware": {"betaflight": ["set …", ...],
"px4": {...}, "ardupilot": {...}}, "defaults": {...}, "article": {...}, "pareto": [...], ...}``.
The recommendation is :func:`gyrocore.flight.preview.recommend_filter`; this module parses, plots
and prints.
"""

from __future__ import annotations

import math
import os

import click
import numpy as np

from gyrocore.cli import emit_json
from gyrocore.errors import GyroInputError, warn_repair
from gyrocore.flight.preview import recommend_filter


def plot_filter(out: dict, path: str) -> None:
    """Gyro PSD after the recommended, as-flown, default and article chains, (°/s)²/Hz, one scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gyrocore.data.recording import atomic_open

    res = out["_res"]
    rows = {r["name"]: r for r in out["_rows"]}
    f = res.f_hz
    conv = (180 / math.pi) ** 2
    show = [("none", "k", "before firmware filters")]
    show.append((out["recommended"]["name"], "tab:green", "recommended"))
    if out["as_flown"]:
        show.append(("as flown", "tab:blue", "as flown"))
    show += [
        ("betaflight 4.x default (static part)", "tab:orange", None),
        ("px4 default IMU_GYRO_CUTOFF 40", "tab:purple", None),
        ("article 1st-order 30 Hz", "tab:red", None),
    ]
    fig, axs = plt.subplots(1, 3, figsize=(15, 4.5), constrained_layout=True)
    for j, a in enumerate("xyz"):
        ax = axs[j]
        for name, col, lab in show:
            if name in rows:
                r = rows[name]
                rec_name = out["recommended"]["name"]
                same = (
                    lab == "as flown" and rec_name in rows and np.allclose(rows[rec_name]["psd_after"], r["psd_after"])
                )
                ax.semilogy(
                    f,
                    r["psd_after"][:, j] * conv,
                    color=col,
                    lw=0.8,
                    ls="--" if same else "-",
                    label=f"{lab or name}{' (= recommended)' if same else ''}: {r['delay_ms']:.2f} ms, "
                    f"motor noise {r['motor_noise']:.0f} rad/s^2",
                )
        if res.reliable_below_hz < f[-1]:
            ax.axvspan(
                res.reliable_below_hz,
                f[-1],
                color="0.85",
                zorder=0,
                label=f"above {res.reliable_below_hz:.0f} Hz: folded from above the logged Nyquist (unreliable)",
            )
        ax.set_title(f"gyro {a}")
        ax.set_xlabel("frequency, Hz")
        ax.set_ylabel("PSD, (deg/s)^2/Hz")
        ax.set_ylim(1e-6, None)
        if j == 0:
            ax.legend(fontsize=6)
    fig.suptitle(
        f"{os.path.basename(str(out.get('file', '')))}: the flight's gyro spectrum ({res.signal} signal) "
        f"after each candidate filter chain",
        fontsize=9,
    )
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)


@click.command("filter")
@click.argument("path", metavar="FILE", type=click.Path(path_type=str))
@click.option(
    "--loop-hz",
    type=float,
    default=None,
    help="Rate the gyro filters run at (default: the log header's, else the data rate).",
)
@click.option("--window-s", type=float, default=1.0, show_default=True, help="Spectral window, s.")
@click.option("--signal", "use", type=click.Choice(["auto", "prefilter", "gyro"]), default="auto", show_default=True)
@click.option("--log-index", type=int, default=None, help="blackbox: only this log of the file.")
@click.option("--plot", default=None, type=click.Path(path_type=str), help="PNG of the spectra after the chains.")
@click.option("--force", is_flag=True, default=False, help="Overwrite an existing plot.")
@click.option("--json", "as_json", is_flag=True, default=False, help="Print the JSON result on stdout.")
def command(path, loop_hz, window_s, use, log_index, plot, force, as_json):
    """Recommend a gyro filter from a flight's own spectrum, beside what was flown and the firmware defaults."""
    from gyrocore.readers.convert import detect_format, load_any
    from gyrocore.data.recording import read_csv

    if plot and os.path.exists(plot) and not force:
        raise GyroInputError(f"{plot} exists; pass --force to overwrite it")
    fmt = detect_format(path)
    if log_index is not None and fmt != "blackbox":
        raise GyroInputError("--log-index applies to blackbox logs only")
    rec = (
        load_any(path, format="blackbox", log_index=log_index)
        if fmt == "blackbox"
        else (read_csv(path) if fmt == "csv" else load_any(path))
    )
    from .vibration import batch_hint

    with batch_hint(rec, path):
        out = recommend_filter(rec, loop_hz=loop_hz, window_s=window_s, use=use)
    for w in out["_res"].warnings:
        warn_repair(w)
    out["file"] = path
    if plot:
        plot_filter(out, plot)
        out["plot"] = plot
    out = {k: v for k, v in out.items() if not k.startswith("_")}
    if as_json:
        emit_json(out)
        return
    r = out["recommended"]
    click.echo(
        f"recommended: {r['name']}: attitude cost {r['attitude_cost']:.3f} deg, delay {r['delay_ms']:.2f} ms, "
        f"motor noise {r['motor_noise']:.0f} rad/s^2 (budget {out['budget']['motor_noise']:.0f}, {out['budget']['from']})"
    )
    if out["as_flown"]:
        a = out["as_flown"]
        click.echo(
            f"as flown:    {a['name']}: attitude cost {a['attitude_cost']:.3f} deg, delay {a['delay_ms']:.2f} ms, motor noise {a['motor_noise']:.0f}"
        )
    for k, d in out["defaults"].items():
        click.echo(
            f"{k}: {d['name']}: cost {d['attitude_cost']:.3f} deg, delay {d['delay_ms']:.2f} ms, motor noise {d['motor_noise']:.0f}"
        )
    a = out["article"]
    click.echo(
        f"article:     {a['name']}: cost {a['attitude_cost']:.3f} deg, delay {a['delay_ms']:.2f} ms, motor noise {a['motor_noise']:.0f}"
    )
    click.echo("betaflight CLI:")
    for line in out["firmware"]["betaflight"]:
        click.echo("  " + line)
    click.echo("px4: " + ", ".join(f"{k} {v}" for k, v in out["firmware"]["px4"].items()))
    click.echo("ardupilot: " + ", ".join(f"{k} {v}" for k, v in out["firmware"]["ardupilot"].items()))
    for n in out.get("notes", []):  # the caveats (signal already filtered, dynamic filters not modelled)
        click.echo(f"note: {n}")
