"""The filter-cutoff grid shared by the cutoffs experiment and its firmware-flown twin.

Its cells (no filter, then every kind × cutoff), their labels, the median of a metric over the
instances, and the choice rule: the quietest motors among the cells whose attitude cost (the
excess error against a perfect-gyro flight) is at most ``budget`` × the unfiltered cell's.
:mod:`experiments.cutoffs` flies it with our controller, :mod:`experiments.firmware_cutoffs`
with the firmware.
"""

from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np

__all__ = ["cells", "label", "finite_median", "best_within_budget"]


def cells(kinds: Sequence[str], cutoffs: Sequence[float]) -> list[tuple[str, float]]:
    """``("none", nan)`` then every ``(kind, cutoff_hz)`` of the grid."""
    return [("none", float("nan"))] + [(k, float(fc)) for k in kinds for fc in cutoffs]


def label(kind: str, fc: float) -> str:
    """A cell's name: ``"none"`` or ``"<kind> <fc> Hz"``."""
    return "none" if kind == "none" else f"{kind} {fc:g} Hz"


def finite_median(values: Iterable[float]) -> float:
    """Median of the finite values (NaN when there is none)."""
    v = np.array(list(values), float)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else float("nan")


def best_within_budget(stats: dict, noise_key: str, budget: float) -> tuple[str | None, str | None]:
    """(best, least attitude cost) of ``stats`` ({cell label: {"excess_deg", noise_key, ...}}).

    best = the quietest motors (``noise_key``) among the cells whose ``excess_deg`` is at most
    ``budget`` × the ``"none"`` cell's; least attitude cost = the smallest finite ``excess_deg``.
    None where no cell qualifies.
    """
    lim = budget * stats["none"]["excess_deg"]
    ok = {
        k: v
        for k, v in stats.items()
        if np.isfinite(v["excess_deg"]) and v["excess_deg"] <= lim and np.isfinite(v[noise_key])
    }
    best = min(ok, key=lambda k: ok[k][noise_key]) if ok else None
    finite = {k: v for k, v in stats.items() if np.isfinite(v["excess_deg"])}
    least = min(finite, key=lambda k: finite[k]["excess_deg"]) if finite else None
    return best, least
