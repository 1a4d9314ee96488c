"""Simulation speed: simulated seconds per wall second, beside a bare ``mj_step`` loop.

Run: ``python bench/bench_sim.py [--hover-s 20] [--repeat 3]`` (prints one table).

* hover: ``sim.quadrotor.fly_hover`` at physics 1 kHz, gyro 1 kHz, vibration on, with
  (a) the error-free ``PerfectGyro`` (the harness alone), (b) ``sim.gyro.SyntheticGyro``
  (ICM-42688-P preset) with EVERY catalogue effect switched on (the preset's plus overrides
  for the rest), (c) as (b) plus a PT1 30 Hz pipeline (``gyrocore.flight.filters.pt1``); (b) and (c)
  again on the Python reference loop (``fly_hover(compiled=False)``: the loop before
  the compiled kernels of :mod:`sim._fast`, bit-identical results);
* turntable: ``sim.turntable.run_table`` (mujoco.rollout in C, open loop), six mounts x 1 turn
  each way at 180 deg/s;
* bare: a Python loop of ``mujoco.mj_step`` on the same model (hover keyframe / turntable
  at rest), the same number of steps.

Also printed: the wall time of the first flight in the process (numba loading, or on a fresh
checkout compiling, the kernels of :mod:`sim._fast`) and the CPU time of the PT1 pipeline's
``step`` alone (``gyrocore.flight.filters``), the main cost left in (c).

Each figure is the best of ``--repeat`` runs (the machine is shared; best-of is the least
disturbed). Besides wall time, CPU time of this process (``time.process_time``) is shown: on a
loaded machine it is the steadier measure of the same thing. The goal is hover
>= 0.5 x bare.
"""

from __future__ import annotations

import argparse
import math
import platform

import mujoco
import numpy as np
from timing import Clock

from sim.presets import all_effects_overrides


def bare_rate(model: mujoco.MjModel, data: mujoco.MjData, n_steps: int) -> tuple[float, float]:
    step = mujoco.mj_step
    with Clock() as c:
        for _ in range(n_steps):
            step(model, data)
    sim_s = n_steps * model.opt.timestep
    return sim_s / c.wall_s, sim_s / c.cpu_s


def best(fn, repeat: int) -> tuple[float, float]:
    """Best (largest) sim-s per wall-s and per CPU-s over ``repeat`` runs."""
    runs = [fn() for _ in range(repeat)]
    return max(r[0] for r in runs), max(r[1] for r in runs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hover-s", type=float, default=20.0, help="simulated hover seconds per run")
    ap.add_argument("--repeat", type=int, default=3, help="runs per figure (best is kept)")
    args = ap.parse_args()

    from gyrocore.flight.filters import pt1
    from sim.gyro import SyntheticGyro
    from sim.quadrotor import PerfectGyro, fly_hover, load_quadrotor_model
    from sim.turntable import load_table_model, run_table, table_profile_turns

    T = args.hover_s
    rows = []

    def gyro_all():
        return SyntheticGyro("icm42688p", rate_hz=1000.0, seed=1, overrides=all_effects_overrides())

    print(
        f"mujoco {mujoco.__version__}, python {platform.python_version()}, {platform.machine()}; "
        f"best of {args.repeat}; effects on in (b): {', '.join(gyro_all().effects)}"
    )

    m, d = load_quadrotor_model(1e-3)

    def bare_hover():
        mujoco.mj_resetDataKeyframe(m, d, 0)
        return bare_rate(m, d, int(T * 1000))

    def hover(gyro_factory, pipeline_factory, compiled):
        def run():
            g = gyro_factory()
            p = pipeline_factory() if pipeline_factory else None
            with Clock() as c:
                fly_hover(
                    duration_s=T,
                    gyro=g,
                    pipeline=p,
                    vibration=True,
                    physics_rate_hz=1000.0,
                    gyro_rate_hz=1000.0,
                    seed=0,
                    compiled=compiled,
                )
            return T / c.wall_s, T / c.cpu_s

        return run

    # the compiled kernels (sim._fast): loaded from numba's cache, or compiled on a fresh checkout
    with Clock() as c_first:
        fly_hover(duration_s=0.01, gyro=gyro_all(), pipeline=pt1(30.0, 1000.0))
    print(f"first flight in this process (numba kernels compiled or loaded from cache): {c_first.wall_s:.2f} s wall")

    b_h = best(bare_hover, args.repeat)
    for label, gf, pf, compiled in (
        ("hover (a) PerfectGyro", PerfectGyro, None, True),
        ("hover (b) SyntheticGyro, all effects", gyro_all, None, True),
        ("hover (c) (b) + PT1 30 Hz pipeline", gyro_all, lambda: pt1(30.0, 1000.0), True),
        ("hover (b) Python reference loop", gyro_all, None, False),
        ("hover (c) Python reference loop", gyro_all, lambda: pt1(30.0, 1000.0), False),
    ):
        r = best(hover(gf, pf, compiled), args.repeat)
        rows.append((label, r, b_h))

    # the pipeline's own step, alone (gyrocore.flight.filters, called once per gyro sample in (c))
    p = pt1(30.0, 1000.0)
    x = np.zeros((1, 3))[0]
    n_p = 20_000
    with Clock() as c_p:
        for _ in range(n_p):
            p.step(x)
    pipe_us = 1e6 * c_p.cpu_s / n_p

    prof = table_profile_turns(revolutions=1, rates_rad_s=(math.pi,), rest_s=1.0)
    mt, dt_ = load_table_model(1e-3)
    n_tab = int(round(prof.duration_s * 1000)) + 3000

    def bare_table():
        mujoco.mj_resetData(mt, dt_)
        return bare_rate(mt, dt_, n_tab)

    def table():
        with Clock() as c:
            tr = run_table(prof, gyro_rate_hz=1000.0)
        return tr.t_s[-1] / c.wall_s, tr.t_s[-1] / c.cpu_s

    def table_measured():
        with Clock() as c:
            tr = run_table(prof, gyro_rate_hz=1000.0)
            SyntheticGyro("icm42688p", rate_hz=1000.0, seed=1, overrides=all_effects_overrides()).measure(tr)
        return tr.t_s[-1] / c.wall_s, tr.t_s[-1] / c.cpu_s

    b_t = best(bare_table, args.repeat)
    rows.append((f"turntable run_table ({prof.duration_s:.0f} s profile)", best(table, args.repeat), b_t))
    rows.append(("turntable + SyntheticGyro.measure (all effects)", best(table_measured, args.repeat), b_t))

    w = max(len(r[0]) for r in rows)
    print(
        f"{'run':<{w}}  {'sim-s/wall-s':>12}  {'bare':>8}  {'ratio':>5}  |  {'sim-s/CPU-s':>11}  {'bare':>8}  {'ratio':>5}  {'CPU us/step':>11}  {'bare':>6}"
    )
    for label, (rw, rc), (bw, bc) in rows:
        # per 1 ms physics step: microseconds = 1e3 / (sim-s per s)
        print(
            f"{label:<{w}}  {rw:12.1f}  {bw:8.1f}  {rw / bw:5.2f}  |  {rc:11.1f}  {bc:8.1f}  {rc / bc:5.2f}  {1e3 / rc:11.2f}  {1e3 / bc:6.2f}"
        )
    print(f"hover: {T:g} simulated s per run, physics 1 kHz, gyro 1 kHz, vibration on; goal ratio >= 0.5")
    print(f"PT1 pipeline step alone (gyrocore.flight.filters.SosFilter.step): {pipe_us:.2f} CPU us per call")


if __name__ == "__main__":
    main()
