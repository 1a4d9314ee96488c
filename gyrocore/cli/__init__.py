"""The ``gyroharness`` command line: core subcommands (no simulator needed).

Contract (DESIGN.md "Command line"): every subcommand takes ``--json`` and then prints only
JSON on stdout; bad input exits non-zero with one ``error: ...`` line on stderr; repairs are
one ``warning: ...`` line each on stderr.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import math
import os
import pkgutil
import sys
import warnings
from typing import Any, Mapping, Sequence

import click
import numpy as np

from gyrocore.errors import GyroInputError

__all__ = ["build_group", "run_cli", "emit_json", "to_jsonable", "WORKER_ENV", "worker_environment"]


def to_jsonable(obj: Any) -> Any:
    """Convert numpy types / dataclasses to JSON-compatible values (NaN -> None)."""
    import dataclasses

    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return None if not math.isfinite(f) else f
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    return obj


#: Thread counts for spawned worker processes (Monte Carlo, batch): one BLAS/OpenMP thread each,
#: so that N workers on N cores do not oversubscribe (as Dask's nanny does).
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@contextlib.contextmanager
def worker_environment(defaults: Mapping[str, str] = WORKER_ENV):
    """Set the unset variables of ``defaults`` in os.environ for the duration of the block."""
    added = [k for k in defaults if k not in os.environ]
    for k in added:
        os.environ[k] = defaults[k]
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


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
        rv = group.main(
            args=list(argv) if argv is not None else None, prog_name="gyroharness", standalone_mode=False
        )
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
