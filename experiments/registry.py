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

__all__ = ["EXPERIMENTS", "TASKS", "get", "get_task", "names"]

EXPERIMENTS: dict[str, str] = {
    "article": "experiments.article:run",
    "ablation": "experiments.ablation:run",
    "cutoffs": "experiments.cutoffs:run",
    "close_the_loop": "experiments.close_the_loop:run",
    "twin": "experiments.twin:run",
    "protocol": "experiments.protocol:run",
    "flight": "experiments.flight:run",
}


#: Monte Carlo task functions (``MonteCarloTask -> TaskResult``) by name, for
#: :func:`experiments.montecarlo.run_campaign`: the runner resolves a name here and never
#: imports an experiment module itself (the experiments import the runner, one way).
TASKS: dict[str, str] = {
    "ablation": "experiments.ablation:ablation_task",
}


def _load(kind: str, name: str, target: str) -> Callable:
    mod, _, fn = target.partition(":")
    try:
        module = importlib.import_module(mod)
    except ImportError as exc:
        raise GyroInputError(f"{kind} {name}: cannot import {mod} ({str(exc).splitlines()[0]})") from exc
    obj = getattr(module, fn, None)
    if not callable(obj):
        raise GyroInputError(f"{kind} {name}: {mod} has no function {fn}")
    return obj


def get_task(name: str) -> Callable:
    """The Monte Carlo task function registered as ``name`` in :data:`TASKS` (imported now)."""
    if name not in TASKS:
        raise GyroInputError(f"unknown Monte Carlo task '{name}'; known: {', '.join(TASKS)}")
    return _load("task", name, TASKS[name])


def names() -> list[str]:
    """Experiment names in report order."""
    return list(EXPERIMENTS)


def get(name: str) -> Callable:
    """The ``run`` function of experiment ``name`` (imported now)."""
    if name not in EXPERIMENTS:
        raise GyroInputError(f"unknown experiment '{name}'; known: {', '.join(EXPERIMENTS)}")
    return _load("experiment", name, EXPERIMENTS[name])
