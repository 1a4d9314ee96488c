"""Experiment ``cutoffs`` flown by the firmware (``gyroharness experiment cutoffs --firmware betaflight``).

The grid of :mod:`experiments.cutoffs` (filter kind x cutoff per sensor preset, plus no filter),
each cell flown twice on the same airframe, gyro instance and rotor phases:

* **firmware**: Betaflight in lockstep (:mod:`sim.fw_flight`): the filter under test is its
  ``gyro_lpf1`` (``article`` -> PT1, the article's first-order filter; ``pt2`` -> PT2, ``pt3`` ->
  PT3, ``biquad`` -> BIQUAD; ``butter4`` has no firmware equivalent and is not flown), every other
  gyro filter off (``gyro_lpf2``, dynamic LPF, dynamic notch, RPM filter), the D-term filters, PIDs,
  feed-forward and mixer at the firmware's defaults. Two flights per cell, as the project's
  experiment: a ``hover`` gives the *hover error* and the *motor noise* (RMS of the four motor
  outputs above 20 Hz, % of full output) and the *D-term noise* (the firmware's D term above 20 Hz,
  its units: 1000 = full motor range); a ``steps`` flight's rate pulses give the *step tracking*
  (RMS attitude error against the pilot's set point), the *excess* (RMS angle between this flight
  and the same flight with a perfect gyro and no gyro filter: what the gyro and its filter cost the
  attitude), the measured *delay* of the firmware's filtered gyro behind the true rate (0.2-15 Hz)
  and the rate step response (rise 10-90 %, overshoot).
* **our controller** (:func:`experiments.cutoffs.ours_cell_task`): the project's cascaded controller,
  same vehicle, same gyro rate, its hover and attitude-step flights, the filter in its pipeline.

Best (both): the quietest motors among the cells whose excess is at most
``experiments.cutoffs.EXCESS_BUDGET`` x the unfiltered cell's. Where the two verdicts differ, the
section says so in a sentence. Instances: Monte Carlo over seeds (:mod:`experiments.montecarlo`:
serial, local processes or a Dask cluster), medians over instances.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np

from sim.quadrotor import quat_angle_rad
from gyrocore.errors import GyroInputError

from experiments.montecarlo import MonteCarloTask, execute, instance_seeds

from . import cutoff_grid as G
from .report import (
    ExperimentResult,
    md_table,
    new_figure,
    save_figure,
    single_thread_blas,
)

__all__ = ["BASE_SETTINGS", "DEFAULT_VEHICLE", "FW_LPF_TYPE", "cell_settings", "fw_cell_task", "run"]

#: the grid's filter kinds as the firmware's gyro_lpf1_type
FW_LPF_TYPE = {"article": "PT1", "pt2": "PT2", "pt3": "PT3", "biquad": "BIQUAD"}
#: every gyro filter but the one under test off (the D-term chain stays at the firmware's defaults)
BASE_SETTINGS = (
    ("gyro_lpf2_static_hz", "0"),
    ("gyro_lpf1_dyn_min_hz", "0"),
    ("dyn_notch_count", "0"),
    ("rpm_filter_harmonics", "0"),
    ("gyro_notch1_hz", "0"),
    ("gyro_notch2_hz", "0"),
)
#: cutoffs of the default firmware grid (five of the project grid's seven), Hz
FW_CUTOFFS_HZ = (30.0, 60.0, 90.0, 130.0, 180.0)
#: Betaflight's defaults are a 5-inch tune
DEFAULT_VEHICLE = "racing5"
LOOP_RATE_HZ = 8000.0
SETTLE_S = 1.0


def cell_settings(kind: str, fc_hz: float) -> list[tuple[str, str]]:
    """The firmware's settings for one grid cell (``kind = "none"``: no gyro low-pass)."""
    s = list(BASE_SETTINGS)
    if kind == "none":
        return s + [("gyro_lpf1_static_hz", "0")]
    if kind not in FW_LPF_TYPE:
        raise GyroInputError(
            f"filter kind {kind!r} has no firmware gyro_lpf1_type (firmware kinds: {', '.join(FW_LPF_TYPE)})"
        )
    return s + [("gyro_lpf1_type", FW_LPF_TYPE[kind]), ("gyro_lpf1_static_hz", str(int(round(fc_hz))))]


def _angle_rms_deg(qa, qb, mask):
    return float(np.degrees(np.sqrt(np.mean(quat_angle_rad(qa[mask], qb[mask]) ** 2))))


def _opt(task, name, default=None):
    return dict(task.options).get(name, default)


def fw_cell_task(task):
    """Monte Carlo task (:mod:`experiments.montecarlo`): every cell of one (preset, instance) flown
    by the firmware; metrics ``"<cell>|<metric>"``."""
    with single_thread_blas():
        return _fw_cells(task)


def _fw_cells(task):
    from experiments.firmware_fly import fly
    from experiments.montecarlo import TaskResult
    from sim.fw_flight import FwFlightOptions

    kinds, cutoffs = _opt(task, "kinds"), _opt(task, "cutoffs")
    vehicle, binary = _opt(task, "vehicle", DEFAULT_VEHICLE), _opt(task, "binary")
    dur = float(task.duration_s)
    base = FwFlightOptions(
        scenario="steps",
        vehicle=vehicle,
        duration_s=dur,
        seed=int(task.seed),
        sensor=task.sensor,
        loop_rate_hz=LOOP_RATE_HZ,
        settle_s=SETTLE_S,
    )
    ref, _ = fly(replace(base, sensor=None), cell_settings("none", 0.0), binary=binary)
    metrics: dict[str, float] = {}
    nan = float("nan")
    for kind, fc in G.cells(kinds, cutoffs):
        sets = cell_settings(kind, fc)
        hov, _ = fly(replace(base, scenario="hover"), sets, binary=binary)
        stp, _ = fly(base, sets, binary=binary)
        sh, ss = hov.scores(SETTLE_S), stp.scores(SETTLE_S)
        after = stp.t_s >= SETTLE_S
        ok = not (sh["crashed"] or ss["crashed"] or ref.crashed())
        m = {
            "hover_att_rms_deg": sh["hover_att_rms_deg"] if ok else nan,
            "motor_noise_pct": 100.0 * sh["motor_noise_above_20hz"] if ok else nan,
            "dterm_noise": sh["dterm_noise_above_20hz"] if ok and sh["dterm_noise_above_20hz"] is not None else nan,
            "step_track_rms_deg": ss["step_track_rms_deg"] if ok else nan,
            "excess_deg": _angle_rms_deg(stp.q_WB_wxyz, ref.q_WB_wxyz, after) if ok else nan,
            "delay_ms": ss["gyro_delay_ms"] if ok else nan,
            "rise_ms": ss["step_rise_ms"] if ok else nan,
            "overshoot_pct": ss["step_overshoot_pct"] if ok else nan,
            "crashed": float(not ok),
        }
        lab = G.label(kind, fc)
        for k, v in m.items():
            metrics[f"{lab}|{k}"] = float(v)
    return TaskResult.from_task(task, metrics)


def _medians(results, cells, keys):
    out = {}
    for kind, fc in cells:
        lab = G.label(kind, fc)
        out[lab] = {}
        for k in keys:
            out[lab][k] = G.finite_median(r.metrics_dict.get(f"{lab}|{k}", np.nan) for r in results)
    return out


def _disagreement(p, fw_best, ours_best, fw, ours, budget) -> str:
    if fw_best == ours_best:
        return f"Both pick **{fw_best}** for {p}."
    parts = [f"For {p} they disagree: the firmware picks **{fw_best}**, our controller **{ours_best}**."]
    if fw_best in ours and ours_best in fw:
        a, b = fw[fw_best], fw[ours_best]
        parts.append(
            f" Flown by the firmware, {ours_best} costs excess {b['excess_deg']:.4f}° at motor noise "
            f"{b['motor_noise_pct']:.3f} % against {a['excess_deg']:.4f}° / {a['motor_noise_pct']:.3f} % for "
            f"{fw_best} (budget {budget * fw['none']['excess_deg']:.4f}°); by our controller "
            f"{fw_best} costs {ours[fw_best]['excess_deg']:.4f}° / {ours[fw_best]['motor_noise_n']:.4f} N against "
            f"{ours[ours_best]['excess_deg']:.4f}° / {ours[ours_best]['motor_noise_n']:.4f} N "
            f"(budget {budget * ours['none']['excess_deg']:.4f}°)."
        )
    return "".join(parts)


#: The metrics of a firmware cell and of our controller's cell (medians over the instances).
_FW_KEYS = (
    "hover_att_rms_deg",
    "motor_noise_pct",
    "step_track_rms_deg",
    "excess_deg",
    "delay_ms",
    "rise_ms",
    "overshoot_pct",
    "dterm_noise",
    "crashed",
)
_OURS_KEYS = ("hover_att_rms_deg", "motor_noise_n", "step_track_rms_deg", "excess_deg", "delay_ms", "crashed")


def run(
    *,
    out_dir,
    grid: dict,
    ours_task,
    quick: bool = False,
    seeds: int | None = None,
    workers: int | None = None,
    presets: Sequence[str] | None = None,
    duration_s: float | None = None,
    seed: int = 0,
    vehicle: str = DEFAULT_VEHICLE,
    kinds: Sequence[str] | None = None,
    cutoffs: Sequence[float] | None = None,
    scheduler: str | None = None,
    binary=None,
    with_ours: bool = True,
    **_ignored,
) -> ExperimentResult:
    """The cutoffs grid flown by the firmware, beside our controller's verdict (module docstring).

    ``grid``: the project experiment's ``kinds``, ``cutoffs``, ``presets`` and ``excess_budget``;
    ``ours_task``: its Monte Carlo task that flies one (preset, instance) with our controller
    (:func:`experiments.cutoffs.ours_cell_task`). :func:`experiments.cutoffs.run` passes both.
    """
    KINDS, PRESETS = grid["kinds"], grid["presets"]
    EXCESS_BUDGET = float(grid["excess_budget"])
    from experiments.firmware_fly import _record_of
    from sim.firmware.build import FirmwareBinary, ensure_binary
    from sim.vehicles import get_vehicle

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    get_vehicle(vehicle)
    kinds = tuple(kinds or (("article", "pt2") if quick else tuple(k for k in KINDS if k in FW_LPF_TYPE)))
    bad = [k for k in kinds if k not in FW_LPF_TYPE]
    if bad:
        raise GyroInputError(
            f"filter kind {bad[0]!r} has no firmware equivalent (firmware kinds: {', '.join(FW_LPF_TYPE)})"
        )
    # every firmware cell is two 8-kHz flights through a second process (~0.5 CPU s per simulated s):
    # the default grid is the project's at five of its cutoffs, on two presets, one instance
    cutoffs = tuple(float(c) for c in (cutoffs or ((30.0, 90.0) if quick else FW_CUTOFFS_HZ)))
    presets = tuple(presets or (PRESETS[:1] if quick else PRESETS[:2]))
    n_inst = seeds or 1
    dur = float(duration_s or (3.0 if quick else 4.0))
    fb = binary if isinstance(binary, FirmwareBinary) else (ensure_binary() if binary is None else _record_of(binary))
    binary = fb.binary if fb is not None else str(binary)
    version = f"{fb.firmware} {fb.version}" if fb is not None else "betaflight"
    opts = (("kinds", kinds), ("cutoffs", cutoffs), ("vehicle", vehicle), ("binary", binary))
    res_fw, res_ours, backend, nw = _fly_cells(
        presets, instance_seeds(seed, n_inst), dur, opts, ours_task if with_ours else None, workers, scheduler
    )
    cells = G.cells(kinds, cutoffs)
    veh = get_vehicle(vehicle)
    md = [
        f"**Flown by {version}** (lockstep SITL, one firmware loop per gyro sample at {LOOP_RATE_HZ:g} Hz) on the "
        f"`{vehicle}` airframe ({veh.description}); beside it the project's own cascaded controller on the same "
        f"airframe and gyro rate. {dur:g} s flights, {n_inst} sensor instance(s) per preset (medians; every cell flies "
        "the same instances and rotor phases; Monte Carlo backend "
        f"{backend}, {nw} worker(s)). Firmware cells: gyro_lpf1 = the filter under test (article → PT1, pt2 → PT2, "
        "pt3 → PT3, biquad → BIQUAD; butter4 has no firmware equivalent), every other gyro filter off (lpf2, dynamic "
        "LPF, dynamic notch, RPM), D-term filters, PIDs and feed-forward at the firmware's defaults. Two flights per "
        "cell: a hover (hover error; motor noise = RMS of the motor outputs above 20 Hz, % of full output; D-term "
        "noise = the firmware's D term above 20 Hz, 1000 = full motor range) and a `steps` flight, rate pulses "
        "(±115 °/s on roll, pitch, yaw): step tracking, excess (RMS angle to the same "
        "flight with a perfect gyro and no gyro filter), measured gyro delay, rise and overshoot of the rate steps. "
        f"Best = the quietest motors among the cells whose excess is at most {EXCESS_BUDGET:g}× the unfiltered cell's.\n"
    ]
    summary = {
        "firmware": version,
        "vehicle": vehicle,
        "loop_rate_hz": LOOP_RATE_HZ,
        "duration_s": dur,
        "instances": n_inst,
        "presets": {},
    }
    figs = []
    for p in presets:
        fw = _medians([r for r in res_fw if r.sensor == p], cells, _FW_KEYS)
        ours = _medians([r for r in res_ours if r.sensor == p], cells, _OURS_KEYS) if with_ours else {}
        summary["presets"][p] = _preset_summary(fw, ours, EXCESS_BUDGET, with_ours=with_ours)
        md += _preset_markdown(p, fw, ours, summary["presets"][p], cells, version, EXCESS_BUDGET, with_ours=with_ours)
        figs.append(_preset_figure(p, fw, ours, kinds, cutoffs, version, vehicle, out_dir, with_ours=with_ours))
        md.append(f"![cutoffs on the firmware {p}]({figs[-1]})\n")
    line = "; ".join(
        f"{p}: firmware {v['firmware_best']}, ours {v['ours_best']}" for p, v in summary["presets"].items()
    )
    md.insert(
        1,
        f"**Best filter per preset (quietest motors at ≤ {EXCESS_BUDGET:g}× the raw gyro's attitude cost):** {line}.\n",
    )
    return ExperimentResult(
        name="cutoffs_firmware",
        title=f"Filter cutoffs flown by the firmware ({version})",
        markdown="\n".join(md),
        figures=tuple(figs),
        summary=summary,
        wall_s=time.perf_counter() - t0,
    )


def _fly_cells(presets, instances, dur: float, opts: tuple, ours_task, workers, scheduler):
    """Every cell of every (preset, instance) flown by the firmware and, with ``ours_task``, by our
    controller on the same airframe and gyro rate: (firmware results, ours, backend, workers)."""
    tasks_fw = [
        MonteCarloTask(index=i, scenario="cutoffs-firmware", sensor=p, instance=j, seed=s, duration_s=dur, options=opts)
        for i, (p, (j, s)) in enumerate((p, js) for p in presets for js in enumerate(instances))
    ]
    n_work = 1 if workers is None else int(workers)
    res_fw, backend, nw = execute(fw_cell_task, tasks_fw, workers=n_work, scheduler=scheduler)
    res_ours = []
    if ours_task is not None:
        tasks_o = [
            MonteCarloTask(
                index=t.index,
                scenario="cutoffs-ours",
                sensor=t.sensor,
                instance=t.instance,
                seed=t.seed,
                duration_s=dur,
                options=opts[:3] + (("rate_hz", LOOP_RATE_HZ),),
            )
            for t in tasks_fw
        ]
        res_ours, _, _ = execute(ours_task, tasks_o, workers=n_work, scheduler=scheduler)
    return res_fw, res_ours, backend, nw


def _preset_summary(fw: dict, ours: dict, budget: float, *, with_ours: bool) -> dict:
    """Each side's best cell and least attitude cost (the cutoffs rule), and whether they agree."""
    fw_best, fw_least = G.best_within_budget(fw, "motor_noise_pct", budget)
    ours_best, ours_least = G.best_within_budget(ours, "motor_noise_n", budget) if with_ours else (None, None)
    return {
        "firmware_best": fw_best,
        "firmware_least_attitude_cost": fw_least,
        "ours_best": ours_best,
        "ours_least_attitude_cost": ours_least,
        "agree": fw_best == ours_best,
        "firmware": fw,
        "ours": ours,
    }


def _preset_markdown(p, fw, ours, summ, cells, version, budget, *, with_ours: bool) -> list[str]:
    """The preset's table (firmware, then ours) and the two verdicts."""
    rows = []
    for kind, fc in cells:
        lab = G.label(kind, fc)
        f = fw[lab]
        row = [
            lab,
            f["hover_att_rms_deg"],
            f["motor_noise_pct"],
            f["dterm_noise"],
            f["step_track_rms_deg"],
            f["excess_deg"],
            f["delay_ms"],
            f["rise_ms"],
            f["overshoot_pct"],
        ]
        if with_ours:
            o = ours[lab]
            row += [o["hover_att_rms_deg"], o["motor_noise_n"], o["excess_deg"], o["delay_ms"]]
        rows.append(tuple(row))
    head = [
        "filter",
        "fw hover error, °",
        "fw motor noise, %",
        "fw D-term noise",
        "fw step tracking, °",
        "fw excess, °",
        "fw delay, ms",
        "fw rise, ms",
        "fw overshoot, %",
    ]
    if with_ours:
        head += ["ours hover error, °", "ours motor noise, N", "ours excess, °", "ours delay, ms"]
    fw_best, ours_best = summ["firmware_best"], summ["ours_best"]
    return [
        f"### {p} ({version})\n",
        md_table(head, rows),
        f"\nFirmware's best for **{p}**: **{fw_best}** (least attitude cost: {summ['firmware_least_attitude_cost']}); "
        f"our controller's: **{ours_best}** (least attitude cost: {summ['ours_least_attitude_cost']}). "
        + (_disagreement(p, fw_best, ours_best, fw, ours, budget) if with_ours else "")
        + "\n",
    ]


def _preset_figure(p, fw, ours, kinds, cutoffs, version, vehicle, out_dir, *, with_ours: bool) -> str:
    """Excess error, firmware motor noise and measured delay against the cutoff, firmware and ours."""
    fig = new_figure(figsize=(11, 3.4))
    plots = (
        ("excess_deg", "excess attitude error, °"),
        ("motor_noise_pct", "fw motor noise > 20 Hz, %"),
        ("delay_ms", "measured gyro delay, ms"),
    )
    axs = [fig.add_subplot(1, len(plots), i + 1) for i in range(len(plots))]
    for kind in kinds:
        for ax, (key, _) in zip(axs, plots):
            ax.plot(cutoffs, [fw[G.label(kind, c)][key] for c in cutoffs], marker="o", ms=3, label=f"fw {kind}")
            if with_ours and key in ("excess_deg", "delay_ms"):
                ax.plot(
                    cutoffs,
                    [ours[G.label(kind, c)][key] for c in cutoffs],
                    ls="--",
                    marker="x",
                    ms=3,
                    label=f"ours {kind}",
                )
    for ax, (key, lab) in zip(axs, plots):
        ax.axhline(fw["none"][key], color="k", ls=":", lw=1, label="fw none")
        ax.set_xscale("log")
        ax.set_xlabel("cutoff, Hz")
        ax.set_ylabel(lab, fontsize=8)
        ax.grid(alpha=0.3)
    axs[0].legend(fontsize=6)
    fig.suptitle(f"{p}: gyro low-pass flown by {version} ({vehicle})")
    fig.tight_layout()
    return save_figure(fig, out_dir, f"cutoffs_firmware_{p}")
