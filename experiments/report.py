"""Report folders: Markdown sections with tables and PNG plots, written atomically.

Every experiment is a ``run(*, out_dir, quick=False, seeds=None, workers=None, **options)``
function that writes its PNG plots into ``out_dir/figures/`` and returns an
:class:`ExperimentResult` holding its Markdown section (figures linked relative to
``out_dir``) and a JSON-able summary. :func:`build_report` runs several experiments into one
folder and :func:`publish_folder` moves a finished folder into place.

Publication policy (``gyroharness run``)
----------------------------------------
Everything is written into a fresh staging folder next to the target (``.<name>.tmp-*``); each
section, as soon as it has finished, as ``sections/<name>.md`` and ``sections/<name>.json``
(atomically). Only when every section has succeeded is the folder moved to the target:

* the target does not exist -> renamed into place;
* the target is a previous gyroharness report (it holds the marker file
  ``.gyroharness-report``) -> replaced (old folder renamed aside, new one renamed in, old one
  deleted), so re-running ``gyroharness run`` just refreshes ``out/``;
* the target exists but is not a gyroharness report (and is not empty) -> refused with a
  one-line error unless ``force=True``.

A run where a section failed (the others still run) or that was interrupted (Ctrl-C) leaves the
previous report untouched; its finished sections, with a ``report.md`` naming what failed and
what did not run, are moved to ``<target>.incomplete`` (:class:`ReportIncomplete` says where).
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
from gyrocore.data.recording import atomic_write_bytes

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
    "cpu_seconds",
    "SectionStatus",
    "ReportIncomplete",
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
        if f != 0 and (abs(f) < 10**-(digits) or abs(f) >= 10 ** (digits + 3)):
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


def cpu_seconds() -> float:
    """CPU time (user + system) of this process and its waited-for children, s.

    Worker processes of a section (the Monte Carlo pools) are joined before the section returns,
    so their time is in ``RUSAGE_CHILDREN`` by then: the difference across a section is its
    whole CPU cost, which on a shared machine is the figure to compare (wall time depends on
    the load)."""
    import resource

    me, ch = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + ch.ru_utime + ch.ru_stime


@dataclass(frozen=True)
class SectionStatus:
    """How one section of a report run ended.

    Attributes
    ----------
    name : str
        Registry name.
    state : str
        ``"done"``, ``"failed"``, ``"interrupted"`` or ``"not run"``.
    wall_s, cpu_s : float
        Elapsed and CPU (user + system, children included) time of the section, s (NaN if not run).
    error : str
        One line: why it failed (empty when done / not run).
    """

    name: str
    state: str
    wall_s: float = float("nan")
    cpu_s: float = float("nan")
    error: str = ""


class ReportIncomplete(GyroInputError):
    """A report run that did not finish every section (a failure or an interrupt).

    The finished sections were kept in :attr:`partial` (a report folder of its own, with a
    status table); the previous report at the target was not touched.
    """

    def __init__(self, message: str, *, partial: Path | None, statuses: Sequence[SectionStatus], interrupted: bool):
        super().__init__(message)
        self.partial = partial
        self.statuses = tuple(statuses)
        self.interrupted = interrupted


SECTIONS_DIR = "sections"
INCOMPLETE_SUFFIX = ".incomplete"


def _one_line(exc: BaseException) -> str:
    msg = str(exc).splitlines()[0] if str(exc) else ""
    if isinstance(exc, GyroInputError):
        return msg
    return f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__


def _write_section(stage: Path, r: ExperimentResult, cpu_s: float) -> None:
    """The finished section as ``sections/<name>.md`` + ``.json`` (each written atomically)."""
    d = stage / SECTIONS_DIR
    d.mkdir(exist_ok=True)
    atomic_write_text(d / f"{r.name}.md", f"## {r.title}\n\n{r.markdown.strip()}\n")
    atomic_write_text(
        d / f"{r.name}.json",
        json.dumps(
            to_jsonable(
                {
                    "name": r.name,
                    "title": r.title,
                    "wall_s": r.wall_s,
                    "cpu_s": cpu_s,
                    "figures": list(r.figures),
                    "summary": r.summary,
                }
            ),
            indent=2,
            allow_nan=False,
        ),
    )


def _anchor(title: str) -> str:
    a = title.lower().replace(" ", "-")
    return "".join(c for c in a if c.isalnum() or c in "-_")


def _assemble(
    stage: Path,
    results: Sequence[ExperimentResult],
    statuses: Sequence[SectionStatus],
    *,
    title: str,
    preamble: str,
    total_wall_s: float,
    total_cpu_s: float,
    sections: Sequence[str] | None = None,
) -> None:
    """report.md (contents with each section's time and state, then the sections) and summary.json.

    ``sections[i]`` is the name of the section that produced ``results[i]`` (a section may name its
    result otherwise: ``cutoffs`` flown by the firmware is ``cutoffs_firmware``); default: the
    results' own names.
    """
    sections = [r.name for r in results] if sections is None else list(sections)
    by = dict(zip(sections, results))
    cpu_of = {s.name: s.cpu_s for s in statuses}
    complete = all(s.state == "done" for s in statuses)
    parts = [f"# {title}\n", preamble.strip() + "\n" if preamble else ""]
    if not complete:
        parts.append(
            "**Incomplete run**: "
            + "; ".join(
                f"`{s.name}` {s.state}" + (f" ({s.error})" if s.error else "") for s in statuses if s.state != "done"
            )
            + ". The finished sections follow.\n"
        )
    parts.append("## Contents\n")
    for s in statuses:
        r = by.get(s.name)
        if r is not None:
            parts.append(f"- [{r.title}](#{_anchor(r.title)}) — `{r.name}`, {s.wall_s:.1f} s wall, {s.cpu_s:.1f} s CPU")
        else:
            parts.append(f"- `{s.name}` — {s.state}" + (f": {s.error}" if s.error else ""))
    parts.append(
        f"\nTotal {total_wall_s:.1f} s wall, {total_cpu_s:.1f} s CPU (user + system, worker processes included).\n"
    )
    for r in results:
        parts.append(f"## {r.title}\n\n{r.markdown.strip()}\n")
    atomic_write_text(stage / "report.md", "\n".join(parts))
    doc = {
        "complete": complete,
        "wall_s": total_wall_s,
        "cpu_s": total_cpu_s,
        "sections": {
            s.name: {"state": s.state, "wall_s": s.wall_s, "cpu_s": s.cpu_s, "error": s.error} for s in statuses
        },
        "experiments": {
            r.name: {
                "title": r.title,
                "wall_s": r.wall_s,
                "cpu_s": by_cpu,
                "figures": list(r.figures),
                "summary": r.summary,
            }
            for r, by_cpu in ((r, cpu_of.get(sec, float("nan"))) for sec, r in zip(sections, results))
        },
    }
    atomic_write_text(stage / "summary.json", json.dumps(to_jsonable(doc), indent=2, allow_nan=False))


def _keep_partial(stage: Path, target: Path) -> Path:
    """Move an incomplete staging folder to ``<target>.incomplete`` (replacing an earlier incomplete
    report there); if that name is taken by something else, the staging folder stays where it is."""
    dest = target.with_name(target.name + INCOMPLETE_SUFFIX)
    (stage / MARKER).write_text("incomplete gyroharness report folder; `gyroharness run` replaces it\n")
    try:
        if dest.exists():
            if not (dest.is_dir() and (dest / MARKER).exists()):
                return stage
            aside = Path(tempfile.mkdtemp(prefix=f".{dest.name}.old-", dir=dest.parent))
            os.replace(dest, aside / "old")
            os.replace(stage, dest)
            shutil.rmtree(aside, ignore_errors=True)
        else:
            os.replace(stage, dest)
    except OSError:
        return stage
    return dest


def build_report(
    experiments: Sequence[tuple[str, Callable[..., ExperimentResult]]],
    out: str | os.PathLike,
    *,
    force: bool = False,
    title: str = "gyroharness report",
    preamble: str = "",
    on_start: Callable[[str], Callable[[int, int], None] | None] | None = None,
    on_done: Callable[[SectionStatus], None] | None = None,
    **options: Any,
) -> tuple[Path, list[ExperimentResult]]:
    """Run ``experiments`` (name, run) into one report folder; publish it at ``out``.

    Each section runs in turn into a staging folder beside ``out``; a finished section is
    written there at once (``sections/<name>.md`` and ``.json``, each atomically). When every
    section is done the folder is published at ``out`` (:func:`publish_folder`). A section that
    fails is recorded (one line) and the next ones still run; a Ctrl-C stops at once. Either way
    the staging folder, with a ``report.md`` of the finished sections and a status line for the
    others, is moved to ``<out>.incomplete`` and :class:`ReportIncomplete` is raised; the
    previous report at ``out`` is left as it was.

    Parameters
    ----------
    on_start : callable, optional
        Called with the section name before it runs; may return a progress callable
        ``(done, total) -> None`` that is passed to the section as ``progress``.
    on_done : callable, optional
        Called with the section's :class:`SectionStatus` when it ends.
    **options
        Passed to every section's ``run``.

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
    statuses: list[SectionStatus] = []
    result_sections: list[str] = []
    t0, c0 = time.perf_counter(), cpu_seconds()
    interrupted = False
    try:
        for name, fn in experiments:
            if interrupted:
                statuses.append(SectionStatus(name, "not run"))
                continue
            t1, c1 = time.perf_counter(), cpu_seconds()
            # an interrupt anywhere in a section's turn (its progress bar, its run, the writing of its
            # files) interrupts that section; the finished ones are kept either way
            try:
                prog = on_start(name) if on_start is not None else None
                kw = dict(options)
                if prog is not None:
                    kw["progress"] = prog
                try:
                    r = fn(out_dir=stage, **kw)
                except KeyboardInterrupt:
                    raise
                except Exception as exc:  # noqa: BLE001 - recorded as one line naming the section
                    st = SectionStatus(name, "failed", time.perf_counter() - t1, cpu_seconds() - c1, _one_line(exc))
                else:
                    wall, cpu = time.perf_counter() - t1, cpu_seconds() - c1
                    if r.wall_s != r.wall_s:  # NaN: fill in
                        from dataclasses import replace

                        r = replace(r, wall_s=wall)
                    _write_section(stage, r, cpu)
                    results.append(r)
                    result_sections.append(name)
                    st = SectionStatus(name, "done", wall, cpu)
            except KeyboardInterrupt:
                interrupted = True
                wall, cpu = time.perf_counter() - t1, cpu_seconds() - c1
                finished = bool(result_sections) and result_sections[-1] == name  # its files are written
                st = SectionStatus(name, "done" if finished else "interrupted", wall, cpu)
            statuses.append(st)
            if on_done is not None:
                on_done(st)
        total_wall, total_cpu = time.perf_counter() - t0, cpu_seconds() - c0
        _assemble(
            stage,
            results,
            statuses,
            title=title,
            preamble=preamble,
            total_wall_s=total_wall,
            total_cpu_s=total_cpu,
            sections=result_sections,
        )
        bad = [s for s in statuses if s.state != "done"]
        if not bad:
            publish_folder(stage, target, force=force)
            stale = target.with_name(target.name + INCOMPLETE_SUFFIX)
            if (stale / MARKER).exists():
                shutil.rmtree(stale, ignore_errors=True)
            return target, results
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    partial = _keep_partial(stage, target)
    failed = [s for s in bad if s.state in ("failed", "interrupted")]
    head = "; ".join(f"section {s.name} {s.state}" + (f": {s.error}" if s.error else "") for s in failed)
    not_run = [s.name for s in bad if s.state == "not run"]
    done = [s.name for s in statuses if s.state == "done"]
    msg = (
        head
        + (f"; not run: {', '.join(not_run)}" if not_run else "")
        + f"; finished sections ({', '.join(done) or 'none'}) kept in {partial}"
        + (f"; the previous report in {target} is unchanged" if target.exists() else "")
    )
    raise ReportIncomplete(msg, partial=partial, statuses=statuses, interrupted=interrupted)
