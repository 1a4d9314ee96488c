"""Registry of experiments run by ``gyroharness run`` / ``gyroharness experiment NAME``.

Each entry maps a name to ``"module:function"``; the module is imported only when the
experiment runs (so the CLI starts fast and a broken experiment does not break the others'
``--help``). The function has the signature::

    run(*, out_dir: pathlib.Path, quick: bool = False, seeds: int | None = None,
        workers: int | None = None) -> experiments.report.ExperimentResult

To add an experiment, add one line to :data:`EXPERIMENTS` (order = order in the report).
"""

from __future__ import annotations

import importlib
from typing import Callable

from gyrocore.errors import GyroInputError

__all__ = ["EXPERIMENTS", "get", "names"]

EXPERIMENTS: dict[str, str] = {
    "article": "experiments.article:run",
    "ablation": "experiments.ablation:run",
    "cutoffs": "experiments.cutoffs:run",
    "close_the_loop": "experiments.close_the_loop:run",
}


def names() -> list[str]:
    """Experiment names in report order."""
    return list(EXPERIMENTS)


def get(name: str) -> Callable:
    """The ``run`` function of experiment ``name`` (imported now)."""
    if name not in EXPERIMENTS:
        raise GyroInputError(f"unknown experiment '{name}'; known: {', '.join(EXPERIMENTS)}")
    mod, _, fn = EXPERIMENTS[name].partition(":")
    try:
        module = importlib.import_module(mod)
    except ImportError as exc:
        raise GyroInputError(f"experiment {name}: cannot import {mod} ({str(exc).splitlines()[0]})") from exc
    run = getattr(module, fn, None)
    if not callable(run):
        raise GyroInputError(f"experiment {name}: {mod} has no function {fn}")
    return run
