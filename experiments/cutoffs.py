"""Experiment ``cutoffs``: which gyro low-pass (type and cutoff) to fly, judged by attitude.

Closed loop
    The MuJoCo quadrotor (:func:`sim.quadrotor.fly_hover`) hovers with small attitude steps
    and rotor vibration; its rate controller flies on the simulated gyro
    (:class:`sim.gyro.SyntheticGyro`, per-sample stream) through a
    :class:`gyrocore.flight.filters.Pipeline` = power-up bias removal + the filter under test. Scored:
    the true attitude tracking error (true vs commanded attitude, RMS after the first second),
    motor-command noise (RMS of the thrust commands above 20 Hz) and the measured delay of the
    filtered gyro behind the true rate (cross-correlation in 0.2–15 Hz).
Open loop
    The raw gyro of the unfiltered flight is filtered offline; scored: the rate estimation
    error (RMS of filtered − true rate) and the attitude error of integrating it.

The power-up bias is removed with the unit's true turn-on bias (this is a filter study, not a
calibration study: the ablation scores the bias estimate). Every configuration flies the
same sensor instances and rotor phases (paired comparison); medians over instances.
"""

from __future__ import annotations

import math
import multiprocessing
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Sequence

import numpy as np

from gyrocore.attitude import error_angle_rad, integrate_gyro
from gyrocore.flight.filters import AffineCorrection, Pipeline, make_filter

from . import cutoff_grid as G
from experiments.montecarlo import instance_seeds

from .report import ExperimentResult, md_table, new_figure, save_figure, single_thread_blas

__all__ = ["run", "fly_config", "open_loop_scores", "ours_cell_task", "KINDS", "CUTOFFS_HZ", "PRESETS"]

KINDS = ("article", "pt2", "pt3", "biquad", "butter4")
CUTOFFS_HZ = (20.0, 30.0, 45.0, 60.0, 90.0, 130.0, 180.0)
#: A filter may at most multiply the attitude cost of the gyro (excess error) by this.
EXCESS_BUDGET = 2.0
PRESETS = ("icm42688p", "bmi088", "mpu6050")
GYRO_RATE_HZ = 1000.0
SETTLE_S = 1.0
FLIGHT_BAND_HZ = 20.0


def _gyro(preset: str, seed: int, rate_hz: float = GYRO_RATE_HZ):
    from sim.gyro import SyntheticGyro

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return SyntheticGyro(preset, rate_hz=rate_hz, seed=seed)


def _fly(
    preset: str | None,
    seed: int,
    kind: str,
    fc_hz: float,
    duration_s: float,
    steps: bool,
    vehicle: str = "f450",
    rate_hz: float = GYRO_RATE_HZ,
):
    """One closed-loop flight (``preset=None``: a perfect gyro, no filter)."""
    from sim.controller import small_steps
    from sim.quadrotor import PerfectGyro, fly_hover

    n = int(math.floor(duration_s * rate_hz + 1e-9))
    if preset is None:
        gyro, b0, flt = PerfectGyro(), np.zeros(3), make_filter("none", 30.0, rate_hz)
    else:
        g = _gyro(preset, seed, rate_hz)
        gyro, b0, flt = g.stream(n), g.power_up_bias(0), make_filter(kind, fc_hz, rate_hz)
    truth, log = fly_hover(
        duration_s=duration_s,
        gyro=gyro,
        pipeline=Pipeline([AffineCorrection(b0), flt]),
        manoeuvres=small_steps(duration_s) if steps else (),
        vibration=True,
        seed=seed,
        gyro_rate_hz=rate_hz,
        vehicle=vehicle,
    )
    return truth, log, b0, flt


def _crashed(log) -> bool:
    return (not np.all(np.isfinite(log.q_WB_wxyz))) or float(np.max(log.tilt_rad())) > math.radians(60)


def fly_config(
    preset: str,
    seed: int,
    kind: str,
    fc_hz: float,
    duration_s: float,
    ref_steps=None,
    *,
    vehicle: str = "f450",
    rate_hz: float = GYRO_RATE_HZ,
):
    """Closed-loop metrics of one configuration: a hover flight and a step flight.

    Returns (metrics dict, step-flight Truth, step-flight FlightLog, true power-up bias).
    ``ref_steps`` is the FlightLog of the perfect-gyro step flight (same rotor phases) for the
    excess tracking error. ``vehicle``/``rate_hz``: the airframe and the gyro (= rate loop) rate.
    """
    nan = float("nan")
    _, hov, _, flt = _fly(preset, seed, kind, fc_hz, duration_s, steps=False, vehicle=vehicle, rate_hz=rate_hz)
    truth, stp, b0, _ = _fly(preset, seed, kind, fc_hz, duration_s, steps=True, vehicle=vehicle, rate_hz=rate_hz)
    keep_h = hov.t_s >= SETTLE_S
    keep_s = stp.t_s >= SETTLE_S
    ok_h, ok_s = not _crashed(hov), not _crashed(stp)
    m = {
        "hover_att_rms_deg": float(np.degrees(np.sqrt(np.mean(hov.attitude_error_rad()[keep_h] ** 2))))
        if ok_h
        else nan,
        "motor_noise_n": hov.motor_noise_n(t_from_s=SETTLE_S) if ok_h else nan,
        "step_track_rms_deg": float(np.degrees(np.sqrt(np.mean(stp.attitude_error_rad()[keep_s] ** 2))))
        if ok_s
        else nan,
        "excess_deg": nan,
        "delay_ms": 1e3 * stp.gyro_delay_s() if ok_s else nan,
        "filter_delay_ms": 1e3 * flt.delay_s(0.0),
        "crashed": float(not (ok_h and ok_s)),
    }
    if ref_steps is not None and ok_s:
        e = error_angle_rad(stp.q_WB_wxyz[keep_s], ref_steps.q_WB_wxyz[keep_s])
        m["excess_deg"] = float(np.degrees(np.sqrt(np.mean(e**2))))
    return m, truth, stp, b0


def open_loop_scores(truth, gyro_meas_rad_s: np.ndarray, b0: np.ndarray, kind: str, fc_hz: float) -> dict:
    """Offline filter of a raw gyro, scored against the truth.

    ``rate_err_rms_deg_s``: RMS |filtered − true rate|, where the true rate is taken in the
    flight band (zero-phase 4th-order Butterworth at 20 Hz: the rigid-body motion the
    controller should see; rotor vibration above it is real motion but not wanted);
    ``att_err_rms_deg``: RMS attitude error of integrating the filtered gyro from the truth.
    """
    from scipy import signal

    flt = make_filter(kind, fc_hz, GYRO_RATE_HZ)
    w = flt.apply(np.asarray(gyro_meas_rad_s, float) - b0)
    sos = signal.butter(4, FLIGHT_BAND_HZ, fs=GYRO_RATE_HZ, output="sos")
    w_band = signal.sosfiltfilt(sos, truth.omega_S_rad_s, axis=0)
    keep = truth.t_s >= SETTLE_S
    rate_err = np.degrees(np.sqrt(np.mean(np.sum((w - w_band)[keep] ** 2, axis=1))))
    i0 = int(np.argmax(keep))
    q = integrate_gyro(truth.t_s[i0:], w[i0:], q0_wxyz=truth.q_SW_wxyz[i0])
    att = np.degrees(error_angle_rad(q, truth.q_SW_wxyz[i0:]))
    return {"rate_err_rms_deg_s": float(rate_err), "att_err_rms_deg": float(np.sqrt(np.mean(att**2)))}


def _task(args):
    """All configurations for one (preset, seed): closed-loop flights + open-loop on the raw flight."""
    with single_thread_blas():
        return _task_inner(args)


def _task_inner(args):
    preset, seed, kinds, cutoffs, duration_s = args
    _, ref, _, _ = _fly(None, seed, "none", 30.0, duration_s, steps=True)
    out = []
    raw = None
    for kind, fc in G.cells(kinds, cutoffs):
        m, truth, log, b0 = fly_config(preset, seed, kind, fc if kind != "none" else 30.0, duration_s, ref_steps=ref)
        if kind == "none":
            raw = (truth, log.gyro_meas_rad_s.copy(), b0)
        out.append({"preset": preset, "seed": seed, "kind": kind, "fc_hz": fc, **m})
    truth, gm, b0 = raw
    for row in out:
        row.update(open_loop_scores(truth, gm, b0, row["kind"], row["fc_hz"] if row["kind"] != "none" else 30.0))
    return out


def ours_cell_task(task):
    """Monte Carlo task (:mod:`experiments.montecarlo`): every cell of one (preset, instance) flown by
    our controller (:func:`fly_config`) on the vehicle and gyro rate of ``task.options`` (``vehicle``,
    ``rate_hz``, ``kinds``, ``cutoffs``); metrics ``"<cell>|<metric>"``. The firmware side of
    ``run(firmware=...)`` flies the same cells (:mod:`experiments.firmware_cutoffs`)."""
    from experiments.montecarlo import TaskResult

    o = dict(task.options)
    vehicle, rate = o["vehicle"], float(o.get("rate_hz", 8000.0))
    dur = float(task.duration_s)
    with single_thread_blas():
        _, ref, _, _ = _fly(None, int(task.seed), "none", 30.0, dur, steps=True, vehicle=vehicle, rate_hz=rate)
        metrics = {}
        for kind, fc in G.cells(o["kinds"], o["cutoffs"]):
            m, _, _, _ = fly_config(
                task.sensor,
                int(task.seed),
                kind,
                fc if kind != "none" else 30.0,
                dur,
                ref_steps=ref,
                vehicle=vehicle,
                rate_hz=rate,
            )
            lab = G.label(kind, fc)
            for k in ("hover_att_rms_deg", "motor_noise_n", "step_track_rms_deg", "excess_deg", "delay_ms", "crashed"):
                metrics[f"{lab}|{k}"] = float(m[k])
    return TaskResult.from_task(task, metrics)


def run(
    *,
    out_dir,
    quick: bool = False,
    seeds: int | None = None,
    workers: int | None = None,
    presets: Sequence[str] | None = None,
    duration_s: float | None = None,
    seed: int = 0,
    firmware: str | None = None,
    size: str | None = None,
    **options,
) -> ExperimentResult:
    """Sweep filter type × cutoff per sensor preset; write plots into ``out_dir``; return the section.

    ``firmware="betaflight"``: the grid flown by the firmware in the loop, beside our controller's
    verdict on the same airframe (:func:`experiments.firmware_cutoffs.run`; ``options`` go there:
    ``vehicle``, ``kinds``, ``cutoffs``, ``scheduler``, ``binary``).
    """
    if firmware is not None:
        if firmware != "betaflight":
            from gyrocore.errors import GyroInputError

            raise GyroInputError(f"--firmware {firmware!r}: the firmware in the loop is betaflight")
        from .firmware_cutoffs import run as run_firmware

        grid = {"kinds": KINDS, "cutoffs": CUTOFFS_HZ, "presets": PRESETS, "excess_budget": EXCESS_BUDGET}
        return run_firmware(
            out_dir=out_dir,
            grid=grid,
            ours_task=ours_cell_task,
            quick=quick,
            seeds=seeds,
            workers=workers,
            presets=presets,
            duration_s=duration_s,
            seed=seed,
            **options,
        )
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    size = size or ("quick" if quick else "full")
    quick = size == "quick"
    kinds = ("article", "pt2") if quick else KINDS
    cutoffs = (30.0, 90.0) if quick else CUTOFFS_HZ
    presets = tuple(presets or (PRESETS[:1] if quick else PRESETS))
    n_inst = seeds or (1 if size in ("quick", "standard") else 2)
    dur = duration_s or (3.0 if size in ("quick", "standard") else 6.0)
    rows = _fly_grid(presets, instance_seeds(seed, n_inst), kinds, cutoffs, dur, workers=workers)

    md = [
        f"Gyro at {GYRO_RATE_HZ:g} Hz, rotor vibration on, {dur:g} s flights, {n_inst} sensor instance(s) per "
        "preset (medians; every configuration flies the same instances and rotor phases). Closed loop, two flights "
        "per configuration: **hover** (no manoeuvres): RMS attitude error against the set point (noise and "
        "vibration jitter) and *motor noise* = RMS of the thrust commands above 20 Hz; **steps** (5° roll/pitch, "
        "15° yaw): RMS tracking error against the commanded attitude, the *excess* error = RMS angle between this "
        "flight and the same flight with a perfect unfiltered gyro (what the gyro and its filter cost), and the "
        "measured *delay* of the filtered gyro behind the true rate (0.2–15 Hz), beside the filter's own DC "
        f"group delay. Open loop (raw gyro of the unfiltered step flight, filtered offline): *rate error* = RMS of "
        f"filtered − true rate in the flight band (true rate zero-phase low-passed at {FLIGHT_BAND_HZ:g} Hz); "
        "*attitude error* = RMS error of integrating the filtered gyro. (A lower step-tracking RMS under heavy "
        "filtering is not better control: the delayed rate feedback weakens the damping, the response gets faster "
        "and overshoots; the excess error against the perfect-gyro flight measures that cost.) Best = the quietest motors among the filters whose attitude cost (excess error) is at most "
        f"{EXCESS_BUDGET:g}× that of the raw gyro.\n"
    ]
    figs = []
    summary: dict = {"presets": {}}
    for p in presets:
        stats = _preset_stats([r for r in rows if r["preset"] == p], kinds, cutoffs)
        summary["presets"][p] = _preset_summary(stats)
        md += _preset_markdown(p, stats, summary["presets"][p])
        figs.append(_preset_figure(p, stats, kinds, cutoffs, out_dir))
        md.append(f"![cutoffs {p}]({figs[-1]})\n")
    best_line = "; ".join(f"{p}: {v['best']}" for p, v in summary["presets"].items())
    md.insert(
        1,
        f"**Best filter per preset (quietest motors at ≤ {EXCESS_BUDGET:g}× the raw gyro's attitude cost):** {best_line}.\n",
    )
    return ExperimentResult(
        name="cutoffs",
        title="Filter cutoffs compared by attitude",
        markdown="\n".join(md),
        figures=tuple(figs),
        summary=summary,
        wall_s=time.perf_counter() - t0,
    )


#: The per-configuration metrics the section reports (medians over the instances).
_KEYS = (
    "hover_att_rms_deg",
    "motor_noise_n",
    "step_track_rms_deg",
    "excess_deg",
    "delay_ms",
    "filter_delay_ms",
    "rate_err_rms_deg_s",
    "att_err_rms_deg",
    "crashed",
)


def _fly_grid(presets, instances, kinds, cutoffs, duration_s: float, *, workers: int | None) -> list[dict]:
    """Every configuration flown for every (preset, instance): one row per flight pair (:func:`_task`)."""
    jobs = [(p, s, kinds, cutoffs, duration_s) for p in presets for s in instances]
    n_work = 1 if workers == 1 or len(jobs) == 1 else (workers or None)
    if n_work == 1:
        results = [_task(j) for j in jobs]
    else:
        with ProcessPoolExecutor(max_workers=n_work, mp_context=multiprocessing.get_context("spawn")) as pool:
            results = list(pool.map(_task, jobs))
    return [r for chunk in results for r in chunk]


def _preset_stats(pr: list[dict], kinds, cutoffs) -> dict:
    """{configuration label: {metric: median over the instances}} of one preset's rows."""
    stats = {}
    for kind, fc in G.cells(kinds, cutoffs):
        rr = [r for r in pr if r["kind"] == kind and (kind == "none" or r["fc_hz"] == fc)]
        stats[G.label(kind, fc)] = {k: G.finite_median(r[k] for r in rr) for k in _KEYS}
    return stats


def _preset_summary(stats: dict) -> dict:
    """The preset's best filter (quietest motors within EXCESS_BUDGET × the raw gyro's attitude
    cost), its least attitude cost, and the raw gyro's and the article's figures."""
    best, quiet = G.best_within_budget(stats, "motor_noise_n", EXCESS_BUDGET)
    art = stats.get("article 30 Hz")
    return {
        "best": best,
        "least_attitude_cost": quiet,
        "best_excess_deg": stats[best]["excess_deg"] if best else None,
        "best_motor_noise_n": stats[best]["motor_noise_n"] if best else None,
        "none_step_track_rms_deg": stats["none"]["step_track_rms_deg"],
        "none_excess_deg": stats["none"]["excess_deg"],
        "none_motor_noise_n": stats["none"]["motor_noise_n"],
        "article30_step_track_rms_deg": art["step_track_rms_deg"] if art else None,
        "article30_motor_noise_n": art["motor_noise_n"] if art else None,
        "article30_delay_samples": art["filter_delay_ms"] * GYRO_RATE_HZ / 1e3 if art else None,
        "best_open_loop_rate": min(stats, key=lambda k: stats[k]["rate_err_rms_deg_s"]),
    }


def _preset_markdown(p: str, stats: dict, summ: dict) -> list[str]:
    """The preset's table, its best filter and the article's advice against it."""
    table = [
        (
            label,
            v["hover_att_rms_deg"],
            v["motor_noise_n"],
            v["step_track_rms_deg"],
            v["excess_deg"],
            v["delay_ms"],
            v["filter_delay_ms"],
            v["filter_delay_ms"] * GYRO_RATE_HZ / 1e3,
            v["rate_err_rms_deg_s"],
            v["att_err_rms_deg"],
        )
        for label, v in stats.items()
    ]
    md = [f"### {p}\n"]
    md.append(
        md_table(
            [
                "filter",
                "hover error, °",
                "motor noise, N",
                "step tracking, °",
                "excess, °",
                "delay, ms",
                "filter delay, ms",
                "filter delay, samples",
                "rate error, °/s",
                "attitude error, °",
            ],
            table,
        )
    )
    best, quiet = summ["best"], summ["least_attitude_cost"]
    n0 = stats["none"]
    if best:
        b = stats[best]
        md.append(
            f"\nBest for **{p}**: **{best}** — motor noise {b['motor_noise_n']:.4f} N "
            f"({n0['motor_noise_n'] / b['motor_noise_n']:.1f}× quieter than unfiltered), excess attitude error "
            f"{b['excess_deg']:.4f}° (unfiltered {n0['excess_deg']:.4f}°), measured delay {b['delay_ms']:.2f} ms. "
            f"Least attitude cost: **{quiet}** ({stats[quiet]['excess_deg']:.4f}°). Hover attitude error "
            f"barely depends on the filter ({min(v['hover_att_rms_deg'] for v in stats.values()):.4f}–"
            f"{max(v['hover_att_rms_deg'] for v in stats.values()):.4f}°): vibration moves the airframe "
            "itself; the filter decides motor noise and delay."
        )
    art = stats.get("article 30 Hz")
    if art:
        d_samp = art["filter_delay_ms"] * GYRO_RATE_HZ / 1e3
        md.append(
            f" The article's advice, first-order 30 Hz: excess {art['excess_deg']:.4f}° "
            f"({art['excess_deg'] / n0['excess_deg']:.1f}× the raw gyro's), motor noise "
            f"{art['motor_noise_n']:.4f} N, filter delay {art['filter_delay_ms']:.2f} ms = {d_samp:.1f} samples at "
            f"{GYRO_RATE_HZ:g} Hz — {'over' if d_samp > 1 else 'within'} its one-sample budget (a first-order "
            f"filter meets that budget only for fc ≥ {GYRO_RATE_HZ / (2 * math.pi):.0f} Hz at this rate)."
        )
    md.append("\n")
    return md


def _preset_figure(p: str, stats: dict, kinds, cutoffs, out_dir) -> str:
    """Excess error, motor noise, measured delay and open-loop rate error against the cutoff, per kind."""
    fig = new_figure(figsize=(11, 3.4))
    plots = (
        ("excess_deg", "closed-loop excess attitude error, °"),
        ("motor_noise_n", "motor noise > 20 Hz, N"),
        ("delay_ms", "measured gyro delay, ms"),
        ("rate_err_rms_deg_s", "open-loop rate error, °/s"),
    )
    axs = [fig.add_subplot(1, len(plots), i + 1) for i in range(len(plots))]
    for kind in kinds:
        for ax, (key, _) in zip(axs, plots):
            ys = [stats[f"{kind} {fc:g} Hz"][key] for fc in cutoffs]
            ax.plot(cutoffs, ys, marker="o", ms=3, label=kind)
    for ax, (key, lab) in zip(axs, plots):
        ax.axhline(stats["none"][key], color="k", ls=":", lw=1, label="none")
        ax.set_xscale("log")
        ax.set_xticks(list(cutoffs))
        ax.set_xticklabels([f"{c:g}" for c in cutoffs], fontsize=7)
        ax.minorticks_off()
        ax.set_xlabel("cutoff, Hz")
        ax.set_ylabel(lab, fontsize=8)
        ax.grid(alpha=0.3)
    axs[0].legend(fontsize=7)
    fig.suptitle(f"{p}: filter type and cutoff")
    fig.tight_layout()
    return save_figure(fig, out_dir, f"cutoffs_{p}")
