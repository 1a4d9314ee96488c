"""The ``gyroharness`` command line: core subcommands (no simulator needed).

Contract (DESIGN.md "Command line"): every subcommand takes ``--json`` and then prints only
JSON on stdout; bad input exits non-zero with one ``error: ...`` line on stderr; repairs are
one ``warning: ...`` line each on stderr.
"""

from __future__ import annotations

import importlib
import json
import pkgutil
import sys
import warnings
from typing import Any, Sequence

import click

from gyrocore.data.jsonable import to_jsonable
from gyrocore.errors import GyroInputError

__all__ = ["build_group", "run_cli", "emit_json"]


def emit_json(obj: Any) -> None:
    """Print ``obj`` as JSON on stdout (the only thing a ``--json`` run prints there)."""
    click.echo(json.dumps(to_jsonable(obj), indent=2, allow_nan=False))


def _add_package_commands(group: click.Group, package: str) -> None:
    pkg = importlib.import_module(package)
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{package}.{info.name}")
        cmd = getattr(mod, "command", None)
        if isinstance(cmd, click.Command):
            group.add_command(cmd)


def build_group(extra_packages: Sequence[str] = ()) -> click.Group:
    """The click group with every core command plus those of ``extra_packages``."""

    @click.group(context_settings={"help_option_names": ["-h", "--help"]})
    @click.version_option(package_name="gyroharness")
    def gyroharness() -> None:
        """Simulation-driven validation harness for MEMS gyro calibration."""

    _add_package_commands(gyroharness, "gyrocore.cli.commands")
    for p in extra_packages:
        _add_package_commands(gyroharness, p)
    return gyroharness


def _showwarning(message, category, filename, lineno, file=None, line=None):  # noqa: ARG001
    text = str(message).splitlines()[0] if str(message) else category.__name__
    print(f"warning: {text}", file=sys.stderr)


def run_cli(group: click.Group, argv: Sequence[str] | None = None) -> int:
    """Run ``group`` with one-line errors; returns the exit status."""
    warnings.showwarning = _showwarning
    warnings.simplefilter("default")
    try:
        from threadpoolctl import threadpool_limits

        # One BLAS thread: our linear algebra is many small products and solves, where
        # OpenBLAS threads only contend (measured 40x slower (N,3)@(3,3) on a loaded 2-core box).
        threadpool_limits(limits=1, user_api="blas")
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency
        pass
    try:
        rv = group.main(args=list(argv) if argv is not None else None, prog_name="gyroharness", standalone_mode=False)
        return int(rv) if isinstance(rv, int) else 0
    except click.exceptions.Exit as exc:
        return int(exc.exit_code)
    except click.exceptions.Abort:
        print("error: aborted", file=sys.stderr)
        return 130
    except click.UsageError as exc:
        hint = f" (see '{exc.ctx.command_path} --help')" if exc.ctx is not None else ""
        print(f"error: {exc.format_message().splitlines()[0]}{hint}", file=sys.stderr)
        return 2
    except click.ClickException as exc:
        print(f"error: {exc.format_message().splitlines()[0]}", file=sys.stderr)
        return exc.exit_code or 1
    except GyroInputError as exc:
        print(f"error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted; no partial output was written", file=sys.stderr)
        return 130
    except (OSError, MemoryError) as exc:
        print(f"error: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}", file=sys.stderr)
        return 1


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point for the core-only CLI (no simulator commands)."""
    sys.exit(run_cli(build_group(), argv))
