"""Report section ``flight``: a real Betaflight blackbox log, its vibration and its gyro filter.

Where a pilot starts: the shared flight log with an *unfiltered* gyro (Betaflight 4.2.0,
``debug_mode`` GYRO_SCALED: the gyro before the firmware's filters, ../shared/data/blackbox_public/
LOG00037.BFL; the older ../shared/data/betaflight_blackbox/better_tune.BBL logs its gyro after a
90 Hz PT1 and is the fallback), read by the project's reader (:func:`gyrocore.readers.convert.load_any`),

1. its vibration per throttle band (:func:`gyrocore.flight.vibration.analyse`: 1-s Hann windows binned by
   the mean motor command; RMS above 40 Hz per band and axis with its 95 % interval from the
   windows' spread; the lines and how they follow throttle), plotted;
2. the gyro filter recommendation in Betaflight parameter names beside what was flown
   (:func:`gyrocore.flight.preview.recommend_filter`: every candidate chain previewed on the flight's own
   unfiltered spectrum, the least attitude cost under the as-flown chain's motor noise);
3. the firmware-in-the-loop cutoff comparison (the same cutoff grid flown by Betaflight's own
   filters and PID in lockstep) when the SITL binary is built — :func:`firmware_part`, the hook:
   it only *looks* for the binary (``sim.firmware.build.find_binary``, never builds it) and runs the
   firmware experiment (``experiments.cutoffs.run(firmware="betaflight")``) if it is there; otherwise it says how
   to build it (``gyroharness firmware build``).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from experiments import firmware_filter as F
from experiments.cutoffs import run as cutoffs_run
from experiments.datadir import shared_data_dir
from gyrocore.flight.preview import recommend_filter
from gyrocore.flight.vibration import analyse, plot_vibration
from gyrocore.readers.convert import load_any
from sim.firmware import build

from .report import ExperimentResult, md_table, new_figure, save_figure

__all__ = ["FLIGHT_LOGS", "find_flight_log", "firmware_filter_part", "firmware_part", "run"]

#: Candidate logs under the shared data folder, in order of preference: the first whose analysed
#: signal is the unfiltered gyro ("raw") is used.
FLIGHT_LOGS = ("blackbox_public/LOG00037.BFL", "betaflight_blackbox/better_tune.BBL")
DEG = 180.0 / math.pi
#: the build command the report names when the firmware binary is absent
BUILD_HINT = "gyroharness firmware build"


def find_flight_log(data_dir: Path | None):
    """The first log of :data:`FLIGHT_LOGS` with an unfiltered gyro: (path, Recording, VibrationResult).

    Falls back to the first readable log (its filtered gyro, the static filters undone) when none is
    unfiltered; None when no log is present.
    """
    first = None
    for rel in FLIGHT_LOGS:
        p = None if data_dir is None else Path(data_dir) / rel
        if p is None or not p.is_file():
            continue
        rec = load_any(str(p))
        res = analyse(rec)
        if res.signal == "raw":
            return p, rec, res
        first = first or (p, rec, res)
    return first


#: firmware experiment options per report size. Lockstep Betaflight flies at ~3x real time on
#: one core and every cell is flown twice (its filter, and the perfect-gyro reference), so the
#: standard report (5 min of CPU in all) flies a reduced grid — one preset, one unit, the PT1
#: (Betaflight's default gyro_lpf1 type; the article's first-order filter) at three cutoffs
#: spanning the grid, beside no filter (measured: 51 s of CPU with PT2 as well); --full flies
#: the whole grid
FIRMWARE_SIZES: dict[str, dict[str, Any]] = {
    "quick": {"quick": True},
    "standard": {"presets": ("icm42688p",), "seeds": 1, "kinds": ("article",), "cutoffs": (45.0, 90.0, 180.0)},
    "full": {},
}


def firmware_part(
    out_dir: Path,
    *,
    size: str = "standard",
    workers: int | None = None,
    find_binary: Callable | None = None,
    firmware_run: Callable | None = None,
) -> tuple[str, tuple, dict]:
    """The firmware-in-the-loop cutoff comparison, or the line saying how to get it.

    Looks for the built Betaflight SITL binary with ``sim.firmware.build.find_binary()`` (which
    never builds) and, if it is there, runs
    ``experiments.cutoffs.run(firmware="betaflight", out_dir=..., binary=...)`` at the report's size (:data:`FIRMWARE_SIZES`). ``find_binary`` / ``firmware_run`` override the
    two for tests.

    Returns
    -------
    markdown : str
    figures : tuple of str
    summary : dict
        ``{"built": bool, ...}``; with the firmware experiment's summary under ``"cutoffs"``.
    """
    fb = (find_binary or build.find_binary)()
    if fb is None:
        return (
            "Firmware-in-the-loop cutoff comparison: not run — the Betaflight SITL binary is not built; "
            f"build it with `{BUILD_HINT}` and run again to add it here.",
            (),
            {"built": False},
        )
    fw_run = firmware_run or _firmware_cutoffs
    binary = getattr(fb, "binary", fb)
    version = getattr(fb, "version", "")
    r = fw_run(out_dir=out_dir, workers=workers, binary=binary, **FIRMWARE_SIZES.get(size, {}))
    md = (
        f"### Firmware in the loop: {r.title}\n\nBetaflight {version} SITL in lockstep (`{binary}`), "
        f"`gyroharness experiment cutoffs --firmware betaflight` at this report's size.\n\n{r.markdown.strip()}"
    )
    return md, tuple(r.figures), {"built": True, "binary": str(binary), "version": version, "cutoffs": r.summary}


#: the log whose whole tune the firmware flies in the filter-closed-loop part (its airframe class is
#: known: the racing25 vehicle's rotor-line law was fitted to it; see docs/firmware.md)
FIRMWARE_FILTER_LOG = "betaflight_blackbox/better_tune.BBL"
#: filter-closed-loop --firmware options per report size: every candidate chain is flown twice per
#: seed (vibrating and vibration-free) at 8 kHz, minutes of CPU, so only the research size flies it
FIRMWARE_FILTER_SIZES: dict[str, dict[str, Any] | None] = {
    "quick": None,
    "standard": None,
    "full": {"seeds": (0, 1), "duration_s": 4.0},
}


def firmware_filter_part(
    data_dir: Path | None,
    *,
    size: str = "standard",
    workers: int | None = None,
    find_binary: Callable | None = None,
    filter_run: Callable | None = None,
) -> tuple[str, dict]:
    """The pilot's whole tune and each candidate gyro filter chain flown by the firmware
    (``gyroharness filter-closed-loop LOG --firmware betaflight``) on :data:`FIRMWARE_FILTER_LOG`, at
    the research size only (:data:`FIRMWARE_FILTER_SIZES`); otherwise the line that runs it.

    Returns
    -------
    markdown : str
    summary : dict
        ``{"run": bool, ...}``; with the recommendation, the as-flown row and the seeds when flown.
    """
    log = None if data_dir is None else Path(data_dir) / FIRMWARE_FILTER_LOG
    cmd = f"`gyroharness filter-closed-loop {log or FIRMWARE_FILTER_LOG} --firmware betaflight`"
    opts = FIRMWARE_FILTER_SIZES.get(size)
    if log is None or not log.is_file():
        return f"Candidate filter chains flown by the firmware: not run — {FIRMWARE_FILTER_LOG} not found.", {
            "run": False
        }
    if opts is None:
        return (
            f"Candidate filter chains flown by the firmware with the pilot's whole tune: flown at the research "
            f"size (`gyroharness run --full`), or on its own with {cmd}.",
            {"run": False, "command": cmd.strip("`")},
        )
    fb = (find_binary or build.find_binary)()
    if fb is None:
        return (
            f"Candidate filter chains flown by the firmware: not run — the Betaflight SITL binary is not built; "
            f"build it with `{BUILD_HINT}`.",
            {"run": False},
        )
    fn = filter_run or F.run
    out = fn(flight=str(log), binary=getattr(fb, "binary", fb), workers=workers or 1, **opts)
    md = (
        f"### Firmware in the loop: the pilot's tune and candidate filter chains\n\n{cmd} at this report's size "
        f"(seeds {list(opts['seeds'])}, {opts['duration_s']:g}-s flights).\n\n{F.format_table(out)}\n"
    )
    summ = {
        "run": True,
        "flight": FIRMWARE_FILTER_LOG,
        "firmware": out["firmware"],
        "recommended": out["recommended"],
        "as_flown": out["as_flown"],
        "stable": out["stable"],
        "seeds": out["seeds"],
    }
    return md, summ


def _firmware_cutoffs(**kw) -> ExperimentResult:
    """``gyroharness experiment cutoffs --firmware betaflight``: the cutoffs experiment's own entry,
    which hands the firmware experiment its grid and our controller's cell task."""
    return cutoffs_run(firmware="betaflight", **kw)


def _band_figure(res, out_dir: Path) -> str:
    """RMS above 40 Hz per throttle band and axis, °/s, with the 95 % intervals."""
    fig = new_figure(figsize=(7.5, 4.0))
    ax = fig.add_subplot(1, 1, 1)
    med = np.array([b["median"] for b in res.bands])
    for j, (a, col) in enumerate(zip("xyz", ("tab:blue", "tab:orange", "tab:green"))):
        y = np.array([b["rms_above_40hz_rad_s"][a] for b in res.bands]) * DEG
        lo = np.array([b["rms_above_40hz_interval_rad_s"][a][0] for b in res.bands]) * DEG
        hi = np.array([b["rms_above_40hz_interval_rad_s"][a][1] for b in res.bands]) * DEG
        x = med + (j - 1) * 0.0015
        ax.errorbar(x, y, yerr=[y - lo, hi - y], fmt="o-", color=col, capsize=3, lw=1, ms=4, label=f"gyro {a}")
    ax.set_xlabel("throttle band (median mean motor command, 0-1)")
    ax.set_ylabel("RMS above 40 Hz, deg/s (95 % interval)")
    ax.set_title(
        "vibration per throttle band (unfiltered gyro)"
        if res.signal == "raw"
        else f"vibration per throttle band ({res.signal} signal, static filters undone)",
        fontsize=9,
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, out_dir, "flight_vibration_bands")


def _flown_settings(meta: dict) -> list[str]:
    """The gyro filter settings of the log header, as ``name = value`` (what was flown)."""
    try:
        h = json.loads(meta.get("header_filters", "{}"))
    except ValueError:
        return []
    keys = [
        k
        for k in h
        if k.startswith(
            (
                "gyro_lowpass",
                "gyro_notch",
                "dyn_notch",
                "gyro_rpm",
                "dshot_bidir",
                "rpm_filter",
                "dyn_lpf_gyro",
                "gyro_lpf",
            )
        )
    ]
    return [f"{k} = {','.join(str(x) for x in h[k]) if isinstance(h[k], list) else h[k]}" for k in keys]


def _chain_row(label: str, row: dict | None) -> tuple:
    if not row:
        return (label, "—", "—", "—", "—", "—")
    notches = ", ".join(f"{f:g}" for f in row.get("notches_hz") or []) or "none"
    return (label, row["name"], notches, row["delay_ms"], row["motor_noise"], row["attitude_cost"])


def run(
    *,
    out_dir,
    quick: bool = False,
    size: str | None = None,
    workers: int | None = None,
    data_dir: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    find_binary: Callable | None = None,
    firmware_run: Callable | None = None,
    **_ignored,
) -> ExperimentResult:
    """The flight section (module docstring) into ``out_dir``."""
    t0 = time.perf_counter()
    size = size or ("quick" if quick else "full")
    out_dir = Path(out_dir)
    steps = 4

    def tick(k):
        if progress is not None:
            progress(k, steps)

    tick(0)
    ddir = Path(data_dir) if data_dir is not None else shared_data_dir()
    found = find_flight_log(ddir)
    tick(1)
    md: list[str] = []
    figures: list[str] = []
    summary: dict[str, Any] = {}
    if found is None:
        md.append(
            f"No flight log found under {ddir} (looked for {', '.join(FLIGHT_LOGS)}): "
            "`gyroharness vibration YOUR_LOG.BBL` and `gyroharness filter YOUR_LOG.BBL` run the same analysis "
            "on your own log."
        )
    else:
        path, rec, res = found
        figures += _vibration_figures(path, rec, res, out_dir)
        tick(2)
        fj = recommend_filter(rec)
        tick(3)
        flown = _flown_settings(rec.meta)
        md += _vibration_markdown(path, rec, res, figures)
        md += _filter_markdown(fj, flown)
        summary = _log_summary(path, rec, res, fj, flown)
    fw_md, fw_figs, fw_sum = firmware_part(
        out_dir, size=size, workers=workers, find_binary=find_binary, firmware_run=firmware_run
    )
    md.append(fw_md)
    figures += list(fw_figs)
    summary["firmware_in_the_loop"] = fw_sum
    ff_md, ff_sum = firmware_filter_part(ddir, size=size, workers=workers, find_binary=find_binary)
    md.append(ff_md)
    summary["firmware_filter_closed_loop"] = ff_sum
    tick(4)
    return ExperimentResult(
        name="flight",
        title="A real flight: vibration and gyro filter",
        markdown="\n".join(md),
        figures=tuple(figures),
        summary=summary,
        wall_s=time.perf_counter() - t0,
    )


def _vibration_figures(path: Path, rec, res, out_dir: Path) -> list[str]:
    """The spectra per throttle band and the RMS per band (paths relative to ``out_dir``)."""
    rel = f"{path.parent.name}/{path.name}"
    fig_rel = "figures/flight_vibration.png"
    (out_dir / "figures").mkdir(parents=True, exist_ok=True)
    plot_vibration(
        res, out_dir / fig_rel, title=f"{rel}: {rec.meta.get('firmware', '')}, gyro spectrum per throttle band"
    )
    return [fig_rel, _band_figure(res, out_dir)]


def _vibration_markdown(path: Path, rec, res, figures: list[str]) -> list[str]:
    """The log, the analysed signal and its vibration per throttle band, with the lines."""
    rel = f"{path.parent.name}/{path.name}"
    meta = rec.meta
    airborne_s = res.n_windows * res.nperseg / res.rate_hz
    sig = (
        "the unfiltered gyro (" + json.loads(meta["gyro_prefilter"])["source"].split(";")[0] + ")"
        if res.signal == "raw" and "gyro_prefilter" in meta
        else f"the {res.signal} gyro with the static firmware filters undone"
    )
    md = [
        f"`{rel}` ({meta.get('firmware', '?')}, craft {meta.get('craft_name', '?')}; "
        f"{rec.n} samples at {res.rate_hz:.0f} Hz, {rec.t_s[-1] - rec.t_s[0]:.1f} s): read with the project's "
        f"blackbox reader; analysed signal: {sig}. Vibration: {res.n_windows} airborne windows of "
        f"{res.nperseg / res.rate_hz:g} s ({airborne_s:.0f} s), Hann, binned into {len(res.bands)} throttle bands of "
        "equal window count by the mean motor command. Each band's RMS above 40 Hz carries a 95 % interval from "
        "the spread of its windows (`gyrocore.flight.vibration.analyse`); spectra above "
        f"{res.reliable_below_hz:.0f} Hz are folded from above the logged Nyquist and not used. Commands: "
        f"`gyroharness vibration {path} --plot v.png`, `gyroharness filter {path} --json`.\n"
    ]
    rows = []
    for b in res.bands:
        r = b["rms_above_40hz_rad_s"]
        iv = b["rms_above_40hz_interval_rad_s"]
        rows.append(
            (
                f"{b['throttle'][0]:.3f}–{b['throttle'][1]:.3f}",
                b["n_windows"],
                *(f"{r[a] * DEG:.2f} [{iv[a][0] * DEG:.2f}, {iv[a][1] * DEG:.2f}]" for a in "xyz"),
            )
        )
    whole = res.rms_above_40hz_rad_s
    wiv = res.rms_above_40hz_interval_rad_s
    rows.append(
        (
            "whole flight",
            res.n_windows,
            *(f"{whole[a] * DEG:.2f} [{wiv[a][0] * DEG:.2f}, {wiv[a][1] * DEG:.2f}]" for a in "xyz"),
        )
    )
    md.append("#### Vibration per throttle band\n")
    md.append(md_table(["motor command band", "windows", "x, °/s RMS > 40 Hz [95 %]", "y", "z"], rows))
    if res.lines:
        lrows = [
            (
                ln["axis"],
                ln["frequency_hz"],
                ln["amplitude_rad_s"] * DEG,
                ln["follows"],
                "yes" if ln.get("aliased") else "no",
            )
            for ln in res.lines[:8]
        ]
        md.append(
            "Lines (largest first): axis, frequency at the median throttle, amplitude, and what it follows "
            "(a throttle-linked line is a rotor line).\n"
        )
        md.append(md_table(["axis", "Hz", "amplitude °/s", "follows", "aliased"], lrows))
    md.append(f"![vibration per throttle band]({figures[1]})\n\n![spectra per throttle band]({figures[0]})\n")
    return md


def _filter_markdown(fj: dict, flown: list) -> list[str]:
    """The gyro filter recommendation (:func:`recommend_filter`'s JSON) beside what was flown."""
    md = ["#### Gyro filter: recommendation beside what was flown\n"]
    md.append(
        "Each candidate chain is built as the firmware runs it (coefficients at the "
        f"{fj['filter_rate_hz']:g} Hz filter rate) and applied to this flight's spectrum before the filters: "
        "*delay* = mean group delay 1–30 Hz, *motor noise* = RMS of the filtered gyro's derivative above 40 Hz "
        "(what the D term passes to the motors, rad/s²), *attitude cost* = the delay times the flight-band rate "
        "combined with the vibration jitter (degrees). Recommended: the least attitude cost whose motor noise "
        f"stays within the budget ({fj['budget']['from']}: {fj['budget']['motor_noise']:.0f} rad/s²). "
        "An open-loop spectral model on one flight: deterministic given the log (no sampling interval); "
        "the spectrum itself carries the per-band intervals above.\n"
    )
    crow = [_chain_row("recommended", fj["recommended"]), _chain_row("as flown (static part)", fj["as_flown"])]
    crow += [_chain_row(k.replace("_", " "), v) for k, v in fj["defaults"].items()]
    if fj.get("with_rpm_filter"):
        crow.append(_chain_row("best with RPM filter", fj["with_rpm_filter"]))
    md.append(md_table(["chain", "filters", "notches Hz", "delay ms", "motor noise rad/s²", "attitude cost °"], crow))
    md.append("Betaflight settings — flown (log header) | recommended (`set` lines for the CLI):\n")
    md.append(
        "```\n# flown\n"
        + "\n".join(flown or ["(header has no gyro filter settings)"])
        + "\n\n# recommended\n"
        + "\n".join(fj["firmware"]["betaflight"])
        + "\n```\n"
    )
    md.append(f"PX4: `{json.dumps(fj['firmware']['px4'])}`; ArduPilot: `{json.dumps(fj['firmware']['ardupilot'])}`.\n")
    notes = [n for n in fj["notes"] if not n.startswith("open-loop spectral")]
    if notes:
        md.append("Notes: " + " ".join(f"({i + 1}) {n}." for i, n in enumerate(notes)) + "\n")
    return md


def _log_summary(path: Path, rec, res, fj: dict, flown: list) -> dict[str, Any]:
    whole = res.rms_above_40hz_rad_s
    return {
        "log": f"{path.parent.name}/{path.name}",
        "signal": res.signal,
        "firmware": rec.meta.get("firmware"),
        "bands": len(res.bands),
        "windows": res.n_windows,
        "rms_above_40hz_deg_s": {a: whole[a] * DEG for a in "xyz"},
        "band_rms_above_40hz_deg_s": [{a: b["rms_above_40hz_rad_s"][a] * DEG for a in "xyz"} for b in res.bands],
        "recommended": fj["recommended"]["name"],
        "as_flown": fj["as_flown"]["name"] if fj["as_flown"] else None,
        "betaflight_set": fj["firmware"]["betaflight"],
        "flown_settings": flown,
    }
