"""Lockstep Betaflight speed: simulated seconds per wall second at 8 kHz, beside the bare physics.

Run: ``python bench/bench_firmware.py [--sim-s 2] [--repeat 3]`` (prints one table; needs the
binary: ``gyroharness firmware build``).

All rows step at 8 kHz (the firmware's loop rate: one packet per gyro sample), the same number
of steps, in one process:

* bare: a Python loop of ``mujoco.mj_step`` on the F450 quadrotor at 8 kHz (hover keyframe);
* physics + gyro: the same plus the synthetic gyro (``sim.gyro.SyntheticGyro``, ICM-42688-P
  preset with EVERY catalogue effect switched on, as ``bench_sim.py``) stepped per sample
  (``GyroStream.step``) on the true body rate and specific force;
* firmware alone: :meth:`sim.firmware.bridge.BetaflightSITL.step` on a still gyro (one
  gyro/filter/PID/mixer pass of the real firmware + the bridge's packing), and ``step_raw``
  (the packet exchange without the reply's conversion);
* closed loop: physics + gyro + firmware, the firmware's motor outputs setting the four rotor
  thrusts (thrust = T_max · throttle², T_max = 2.5 × hover thrust), armed, throttle stick at
  mid, the firmware's default 4.6.0 tune and filters (RPM filter fed the rotor speeds).

CPU time is this process's plus the SITL process's (``psutil``): the loop is ping-pong, so on
an unloaded core CPU ≈ wall; on a shared machine the CPU figure is the steadier one. Each figure
is the best of ``--repeat`` runs. Goal: closed loop ≥ 2 simulated s per wall s.
"""

from __future__ import annotations

import argparse
import platform

import mujoco
import numpy as np
import psutil
from timing import Clock

from sim.presets import all_effects_overrides

RATE_HZ = 8000.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim-s", type=float, default=2.0, help="simulated seconds per run")
    ap.add_argument("--repeat", type=int, default=3, help="runs per figure (best is kept)")
    args = ap.parse_args()

    from sim.firmware.bridge import BF_FROM_PX4, PX4_FROM_BF, BetaflightSITL
    from sim.firmware.build import ensure_binary
    from sim.gyro import SyntheticGyro
    from sim.quadrotor import load_quadrotor_model

    fb = ensure_binary()
    n = int(round(args.sim_s * RATE_HZ))
    T = n / RATE_HZ
    m, d = load_quadrotor_model(1.0 / RATE_HZ)
    g0 = 9.80665
    mass = float(np.sum(m.body_mass))
    t_hover = mass * g0 / 4.0
    t_max = 2.5 * t_hover
    print(
        f"{fb.firmware} {fb.version} lockstep SITL ({fb.binary}); mujoco {mujoco.__version__}, "
        f"python {platform.python_version()}, {platform.machine()}; {n} steps at 8 kHz per run, best of {args.repeat}"
    )

    def reset():
        mujoco.mj_resetDataKeyframe(m, d, 0)
        mujoco.mj_forward(m, d)

    def gyro_stream():
        g = SyntheticGyro("icm42688p", rate_hz=RATE_HZ, seed=1, overrides=all_effects_overrides())
        t = np.arange(n) / RATE_HZ
        return g, g.stream(n, t_s=t, temp_c=np.full(n, 35.0))

    def truth():
        # body rate (free joint: qvel[3:6] in the body frame), specific force from gravity
        # (third row of R_WB: world z in body axes), q_SW; plain floats (per-step cost)
        w = d.qvel[3:6].tolist()
        x = d.xmat[1].tolist()
        f = (x[6] * g0, x[7] * g0, x[8] * g0)
        q = d.qpos[3:7].tolist()
        return w, f, (q[0], -q[1], -q[2], -q[3])

    def bare():
        reset()
        with Clock() as c:
            for _ in range(n):
                mujoco.mj_step(m, d)
        return c

    def physics_gyro():
        reset()
        _, s = gyro_stream()
        with Clock() as c:
            for k in range(n):
                mujoco.mj_step(m, d)
                w, f, qsw = truth()
                s.step(k, k / RATE_HZ, w, f, 35.0, qsw)
        return c

    def firmware_only(raw: bool):
        def run():
            with BetaflightSITL(fb.binary) as fc:
                fc.boot()
                with Clock(fc.pid) as c:
                    if raw:
                        for _ in range(n):
                            fc.step_raw((0, 0, 0))
                    else:
                        for _ in range(n):
                            fc.step((0.0, 0.0, 0.0))
            return c

        return run

    def closed_loop():
        reset()
        _, s = gyro_stream()
        with BetaflightSITL(fb.binary) as fc:
            fc.boot()
            rc = (1500, 1500, 1500, 1500)
            with Clock(fc.pid) as c:
                ctrl = d.ctrl
                px4 = PX4_FROM_BF.tolist()
                bf = BF_FROM_PX4.tolist()
                rotor = [0.0, 0.0, 0.0, 0.0]
                for k in range(n):
                    mujoco.mj_step(m, d)
                    w, f, qsw = truth()
                    g = s.step(k, k / RATE_HZ, w, f, 35.0, qsw)
                    # rotor speed ~ 900 rad/s x throttle: an RPM-filter input, Betaflight order
                    r = fc.step(g, f, (qsw[0], -qsw[1], -qsw[2], -qsw[3]), [rotor[i] for i in bf], rc=rc)
                    mot = r.motors.tolist()
                    thr = [mot[i] for i in px4]
                    rotor = [900.0 * t for t in thr]
                    ctrl[:4] = [t_max * t * t for t in thr]
        return c

    rows = []
    b = min((bare() for _ in range(args.repeat)), key=lambda c: c.wall_s)
    for label, fn in (
        ("physics + gyro (all effects)", physics_gyro),
        ("firmware alone: step()", firmware_only(False)),
        ("firmware alone: step_raw()", firmware_only(True)),
        ("closed loop: physics + gyro + firmware", closed_loop),
    ):
        cs = [fn() for _ in range(args.repeat)]
        rows.append((label, min(cs, key=lambda c: c.wall_s), min(cs, key=lambda c: c.cpu_s)))
    w = max(len(r[0]) for r in rows + [("bare mj_step",)])
    print(
        f"{'run (8 kHz)':<{w}}  {'sim-s/wall-s':>12}  {'x bare':>6}  {'us/step':>8}  |  {'sim-s/CPU-s':>11}  {'us/step':>8}"
    )
    print(
        f"{'bare mj_step':<{w}}  {T / b.wall_s:12.2f}  {1.0:6.2f}  {1e6 * b.wall_s / n:8.1f}  |  "
        f"{T / b.cpu_s:11.2f}  {1e6 * b.cpu_s / n:8.1f}"
    )
    for label, cw, cc in rows:
        print(
            f"{label:<{w}}  {T / cw.wall_s:12.2f}  {b.wall_s / cw.wall_s:6.2f}  {1e6 * cw.wall_s / n:8.1f}  |  "
            f"{T / cc.cpu_s:11.2f}  {1e6 * cc.cpu_s / n:8.1f}"
        )
    print(
        f"load average {', '.join(f'{x:.1f}' for x in psutil.getloadavg())} on {psutil.cpu_count()} CPUs; "
        f"goal: closed loop >= 2 simulated s per wall s"
    )


if __name__ == "__main__":
    main()
