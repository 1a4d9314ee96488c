"""Report folders: Markdown sections with tables and PNG plots, written atomically.

Every experiment is a ``run(*, out_dir, quick=False, seeds=None, workers=None, **options)``
function that writes its PNG plots into ``out_dir/figures/`` and returns an
:class:`ExperimentResult` holding its Markdown section (figures linked relative to
``out_dir``) and a JSON-able summary. :func:`build_report` runs several experiments into one
folder and :func:`publish_folder` moves a finished folder into place.

Publication policy (``gyroharness run``)
----------------------------------------
Everything is written into a fresh staging folder next to the target (``.<name>.tmp-*``).
Only when every experiment has succeeded is it moved to the target:

* the target does not exist -> renamed into place;
* the target is a previous gyroharness report (it holds the marker file
  ``.gyroharness-report``) -> replaced (old folder renamed aside, new one renamed in, old one
  deleted), so re-running ``gyroharness run`` just refreshes ``out/``;
* the target exists but is not a gyroharness report (and is not empty) -> refused with a
  one-line error unless ``force=True``.

A failed run leaves the previous report untouched and removes its staging folder.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from gyrocore.data.jsonable import to_jsonable
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import atomic_write_text

__all__ = [
    "ExperimentResult",
    "MARKER",
    "md_table",
    "fmt",
    "new_figure",
    "save_figure",
    "publish_folder",
    "staging_folder",
    "build_report",
    "single_thread_blas",
]

MARKER = ".gyroharness-report"
FIG_DIR = "figures"


@dataclass(frozen=True)
class ExperimentResult:
    """What one experiment hands to the report.

    Attributes
    ----------
    name : str
        Registry name (``ablation``, ``cutoffs``, ...).
    title : str
        Section title.
    markdown : str
        Section body (Markdown; figures linked as ``figures/<file>.png``).
    figures : tuple of str
        Figure paths relative to the report folder.
    summary : dict
        JSON-able key figures (for ``--json`` and the tests).
    wall_s : float
        Elapsed time of the experiment, s.
    """

    name: str
    title: str
    markdown: str
    figures: tuple[str, ...] = ()
    summary: Mapping[str, Any] = field(default_factory=dict)
    wall_s: float = float("nan")


def fmt(v: Any, digits: int = 3) -> str:
    """Compact number formatting for tables (NaN/None -> '—')."""
    if v is None:
        return "—"
    if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if not math.isfinite(f):
            return "—"
        if f != 0 and (abs(f) < 10 ** -(digits) or abs(f) >= 10 ** (digits + 3)):
            return f"{f:.{digits - 1}e}"
        return f"{f:.{digits}g}" if abs(f) < 10**digits else f"{f:.0f}"
    return str(v)


def md_table(header: Sequence[str], rows: Sequence[Sequence[Any]], *, digits: int = 3) -> str:
    """A GitHub Markdown table; numbers through :func:`fmt`."""
    out = ["| " + " | ".join(str(h) for h in header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        out.append("| " + " | ".join(fmt(c, digits) if not isinstance(c, str) else c for c in r) + " |")
    return "\n".join(out) + "\n"


def new_figure(*args, **kwargs):
    """A matplotlib Figure on the Agg backend (no display needed, thread-safe: no pyplot)."""
    from matplotlib.figure import Figure

    return Figure(*args, **kwargs)


def save_figure(fig, out_dir: str | os.PathLike, name: str) -> str:
    """Save ``fig`` as ``out_dir/figures/<name>.png`` (atomically); returns the relative path."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    rel = f"{FIG_DIR}/{name}.png"
    path = Path(out_dir) / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    from gyrocore.data.recording import atomic_write_bytes

    atomic_write_bytes(path, buf.getvalue())
    return rel


def single_thread_blas():
    """Context manager limiting BLAS to one thread (threadpoolctl, if installed).

    The experiments do many small matrix products ((N, 3) @ (3, 3)); a multi-threaded
    OpenBLAS on a shared 2-core machine makes each one ~40× slower than single-threaded
    (measured: 0.23 s vs 5 ms for 150 000 rows). Parallelism comes from worker processes.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional
        import contextlib

        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


# ------------------------------------------------------------------ folders
def staging_folder(target: str | os.PathLike) -> Path:
    """A new empty staging folder beside ``target`` (same file system, so rename is atomic)."""
    target = Path(target).resolve()
    target.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))


def publish_folder(staging: str | os.PathLike, target: str | os.PathLike, *, force: bool = False) -> None:
    """Move a finished ``staging`` folder to ``target`` under the policy of the module docstring."""
    staging, target = Path(staging), Path(target).resolve()
    (staging / MARKER).write_text("gyroharness report folder; `gyroharness run` replaces it\n")
    if target.exists():
        if not target.is_dir():
            raise GyroInputError(f"{target} exists and is not a folder; choose another --out")
        is_report = (target / MARKER).exists()
        if not is_report and any(target.iterdir()) and not force:
            raise GyroInputError(f"{target} exists and is not a gyroharness report; pass --force to replace it")
        aside = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
        os.replace(target, aside / "old")
        try:
            os.replace(staging, target)
        except BaseException:
            os.replace(aside / "old", target)
            raise
        shutil.rmtree(aside, ignore_errors=True)
    else:
        os.replace(staging, target)


def build_report(
    experiments: Sequence[tuple[str, Callable[..., ExperimentResult]]],
    out: str | os.PathLike,
    *,
    force: bool = False,
    title: str = "gyroharness report",
    preamble: str = "",
    on_start: Callable[[str], None] | None = None,
    **options: Any,
) -> tuple[Path, list[ExperimentResult]]:
    """Run ``experiments`` (name, run) into one report folder; publish it at ``out``.

    Any failing experiment aborts the whole report with a one-line
    :class:`GyroInputError` naming it; the previous report is left untouched.

    Returns
    -------
    path : Path
        The published folder.
    results : list of ExperimentResult
    """
    target = Path(out).resolve()
    if target.exists() and not target.is_dir():
        raise GyroInputError(f"{target} exists and is not a folder; choose another --out")
    if target.exists() and not (target / MARKER).exists() and any(target.iterdir()) and not force:
        raise GyroInputError(f"{target} exists and is not a gyroharness report; pass --force to replace it")
    stage = staging_folder(target)
    results: list[ExperimentResult] = []
    t0 = time.perf_counter()
    try:
        for name, fn in experiments:
            if on_start is not None:
                on_start(name)
            t1 = time.perf_counter()
            try:
                r = fn(out_dir=stage, **options)
            except GyroInputError as exc:
                raise GyroInputError(f"experiment {name} failed: {str(exc).splitlines()[0]}") from exc
            except Exception as exc:  # noqa: BLE001 - re-raised as one line naming the experiment
                msg = str(exc).splitlines()[0] if str(exc) else ""
                raise GyroInputError(f"experiment {name} failed: {type(exc).__name__}: {msg}") from exc
            if r.wall_s != r.wall_s:  # NaN: fill in
                from dataclasses import replace

                r = replace(r, wall_s=time.perf_counter() - t1)
            results.append(r)
        total = time.perf_counter() - t0
        parts = [f"# {title}\n", preamble.strip() + "\n" if preamble else ""]
        parts.append("## Contents\n")
        for r in results:
            anchor = r.title.lower().replace(" ", "-")
            anchor = "".join(c for c in anchor if c.isalnum() or c in "-_")
            parts.append(f"- [{r.title}](#{anchor}) — `{r.name}`, {r.wall_s:.1f} s")
        parts.append(f"\nTotal wall time {total:.1f} s.\n")
        for r in results:
            parts.append(f"## {r.title}\n\n{r.markdown.strip()}\n")
        atomic_write_text(stage / "report.md", "\n".join(parts))
        atomic_write_text(
            stage / "summary.json",
            json.dumps(to_jsonable({"wall_s": total, "experiments": {r.name: {"title": r.title, "wall_s": r.wall_s,
                                                                                "figures": list(r.figures),
                                                                                "summary": r.summary}
                                                                       for r in results}}),
                       indent=2, allow_nan=False),
        )
        publish_folder(stage, target, force=force)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return target, results
