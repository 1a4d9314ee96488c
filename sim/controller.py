"""Cascaded flight controller for the quadrotor: position/altitude -> attitude -> rate -> mixer.

Structure (PX4-like, all loops at the gyro output rate):

* loop rates: rate loop on every gyro sample, attitude/position loops at 250 Hz (PX4-like);
* altitude: PID on the true height (a perfect height estimate) -> vertical acceleration;
* horizontal position hold: PD on the true position -> horizontal acceleration -> tilt set
  point (small-angle, in the yaw frame), plus the manoeuvre offsets (roll, pitch, yaw steps);
* attitude: quaternion error ``q_e = q^-1 q_sp`` -> rate set point ``K_att * 2 sign(w) vec(q_e)``
  (body frame) on the true attitude (a perfect attitude estimate: the study object is the
  gyro in the rate loop, not the estimator);
* rate: PID per body axis on the **measured, pipeline-filtered gyro**, D on the measurement
  (``-Kd d(omega_meas)/dt``, no extra D filter: the pipeline is the only gyro filter, so a
  filter choice changes the motor commands);
* mixer: the exact inverse of the quad-X allocation (thrust, roll/pitch/yaw torques) -> four
  rotor thrusts, clipped to ``[0, T_max]``; then rotor speed commands ``sqrt(T/c_T)`` with
  the drag-torque feed-forward of the motor speed servo.

Gains are normalised by the inertia (torque = J * angular acceleration), see
:class:`ControllerGains`. Rate loop: with motor lag tau_m = 20 ms, ``Kp = 15 /s`` crosses over at
~15 rad/s with ~73 deg phase margin (90 - atan(15*0.02) - 1 ms delay); attitude ``6 /s`` sits
below it; altitude omega_n = 2 rad/s, horizontal omega_n = 1 rad/s (damping ~0.75).
Yaw is gentler (rate Kp 4 /s): a yaw command changes rotor speeds, and the motor torque that
accelerates the rotors reacts on the frame at first kv / (2 kappa c_T Omega) ~ 15 times more than
the steady drag-torque change the mixer assumes (kv = 0.003 N m s, hover Omega = 557 rad/s), so the
high-frequency yaw loop gain is ~15 Kp / omega (crossover ~60 rad/s, |L| ~ 0.1 at the 89 Hz
rotor line).

Everything per sample is plain Python float arithmetic (no per-step numpy allocations).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gyrocore.errors import GyroInputError

__all__ = ["ControllerGains", "QuadParams", "Manoeuvre", "small_steps", "CascadedController"]


@dataclass(frozen=True)
class QuadParams:
    """Vehicle constants the controller needs (from ``models/quadrotor.xml``'s comments).

    Parameters
    ----------
    mass_kg : float
    inertia_kg_m2 : tuple of 3 floats
        Principal inertia about body x, y, z, kg m².
    arm_xy_m : float
        Rotor offset along body x and y (d/√2), m.
    c_t_n_per_rad2_s2 : float
        Thrust coefficient, N/(rad/s)².
    kappa_m : float
        Yaw torque per newton of thrust (c_M/c_T), m.
    spin : tuple of 4 ints
        Rotor spin, +1 CCW seen from above (rotors 1..4, PX4 quad-X order).
    rotor_xy_m : tuple of 4 (x, y)
        Rotor positions, m.
    motor_kv_n_m_s : float
        Speed-servo gain of the motor, N m per rad/s.
    max_thrust_n : float
        Thrust limit per rotor, N (about 8.5 N for a 2212/920KV with a 10x4.5 prop on 3S).
    gravity_m_s2 : float
    """

    mass_kg: float = 1.4008
    inertia_kg_m2: tuple[float, float, float] = (0.0211, 0.0219, 0.0366)
    c_t_n_per_rad2_s2: float = 1.105e-5
    kappa_m: float = 0.0161
    spin: tuple[int, int, int, int] = (1, 1, -1, -1)
    rotor_xy_m: tuple[tuple[float, float], ...] = (
        (0.159099, -0.159099),
        (-0.159099, 0.159099),
        (0.159099, 0.159099),
        (-0.159099, -0.159099),
    )
    motor_kv_n_m_s: float = 0.003
    max_thrust_n: float = 8.5
    gravity_m_s2: float = 9.81

    def allocation(self) -> np.ndarray:
        """Matrix A (4x4): [T, tau_x, tau_y, tau_z] = A @ rotor thrusts (N, N m)."""
        a = np.zeros((4, 4))
        for i, ((x, y), s) in enumerate(zip(self.rotor_xy_m, self.spin)):
            a[:, i] = (1.0, y, -x, -s * self.kappa_m)
        return a


@dataclass(frozen=True)
class ControllerGains:
    """Gains, normalised by mass or inertia (units in the names).

    ``rate_kp_per_s`` etc. map rate error (rad/s) to angular acceleration (rad/s²): torque =
    J * (kp e + ki ∫e − kd dω/dt).
    """

    rate_kp_per_s: tuple[float, float, float] = (15.0, 15.0, 4.0)
    rate_ki_per_s2: tuple[float, float, float] = (10.0, 10.0, 2.0)
    rate_kd: tuple[float, float, float] = (0.05, 0.05, 0.0)
    att_kp_per_s: tuple[float, float, float] = (6.0, 6.0, 2.5)
    rate_limit_rad_s: float = 3.5
    alt_kp_per_s2: float = 4.0
    alt_ki_per_s3: float = 1.0
    alt_kd_per_s: float = 3.0
    xy_kp_per_s2: float = 1.0
    xy_kd_per_s: float = 1.5
    max_horiz_accel_m_s2: float = 2.0
    max_tilt_rad: float = math.radians(20.0)
    integrator_limit: float = 5.0


@dataclass(frozen=True)
class Manoeuvre:
    """An attitude offset added to the hover set point for a while.

    Parameters
    ----------
    t_start_s, duration_s : float
        When and how long, s.
    roll_rad, pitch_rad, yaw_rad : float
        Offsets, rad (roll/pitch about body axes at the set point, yaw about world z).
    """

    t_start_s: float
    duration_s: float
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0


def small_steps(
    duration_s: float, *, angle_rad: float = math.radians(5.0), yaw_rad: float = math.radians(15.0)
) -> tuple[Manoeuvre, ...]:
    """A sequence of small steps fitted into ``duration_s``: roll +, roll −, pitch +, pitch −, yaw.

    The first 20 % of the flight is plain hover; each step lasts 1/10 of the flight (max 2 s).
    """
    if duration_s <= 0:
        raise GyroInputError("duration_s must be > 0")
    step = min(2.0, 0.1 * duration_s)
    t0 = 0.2 * duration_s
    offs = [(angle_rad, 0, 0), (-angle_rad, 0, 0), (0, angle_rad, 0), (0, -angle_rad, 0), (0, 0, yaw_rad)]
    return tuple(
        Manoeuvre(t_start_s=t0 + 1.5 * i * step, duration_s=step, roll_rad=r, pitch_rad=p, yaw_rad=y)
        for i, (r, p, y) in enumerate(offs)
    )


def _quat_mul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def _quat_from_euler_zyx(yaw, pitch, roll):
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


class CascadedController:
    """Position/altitude -> attitude (outer, ``outer_rate_hz``) and rate PID -> mixer (every gyro sample).

    As in PX4, the rate loop runs on every gyro sample and the attitude/position loops at a
    lower rate (default 250 Hz), holding their outputs (rate set point, collective thrust) in
    between. Call :meth:`update_outer` when due (:meth:`outer_due`), then :meth:`update_rate`.

    Parameters
    ----------
    params : QuadParams
    gains : ControllerGains
    dt_s : float
        Rate-loop period (the gyro output period), s.
    pos_sp_W_m : tuple of 3 floats
        Hover position set point, world, m.
    yaw_sp_rad : float
        Hover heading, rad.
    manoeuvres : sequence of Manoeuvre
    outer_rate_hz : float
        Rate of the attitude/position loops, Hz; they run every ``round(rate/outer)`` samples (>= 1).
    arm_at_s : float
        Take-off from the ground: the controller is DISARMED (all rotor thrusts 0, loops and
        integrators idle) before ``arm_at_s``, s; it arms at the first outer-loop update at or
        after it. Default 0: armed from the start (airborne).
    climb_s : float
        After arming, the height set point ramps from ``z_start_m`` to ``pos_sp_W_m[2]`` over
        ``climb_s`` s (raised cosine: zero climb rate at both ends, peak ``pi/2`` x the mean),
        with the ramp's climb rate and vertical acceleration fed forward (velocity set point of
        the altitude D term, acceleration added); 0 = no ramp.
    z_start_m : float
        Start of the height ramp (the height on the ground), m.
    """

    def __init__(
        self,
        params: QuadParams,
        gains: ControllerGains,
        *,
        dt_s: float,
        pos_sp_W_m=(0.0, 0.0, 1.0),
        yaw_sp_rad: float = 0.0,
        manoeuvres=(),
        outer_rate_hz: float = 250.0,
        arm_at_s: float = 0.0,
        climb_s: float = 0.0,
        z_start_m: float = 0.0,
    ) -> None:
        if not dt_s > 0 or not outer_rate_hz > 0:
            raise GyroInputError("controller dt_s and outer_rate_hz must be > 0")
        if not (math.isfinite(arm_at_s) and arm_at_s >= 0 and math.isfinite(climb_s) and climb_s >= 0):
            raise GyroInputError("controller arm_at_s and climb_s must be finite and >= 0")
        self.arm_at_s, self.climb_s, self.z_start_m = float(arm_at_s), float(climb_s), float(z_start_m)
        self.p, self.g, self.dt = params, gains, float(dt_s)
        self.outer_every = max(1, int(round(1.0 / (dt_s * outer_rate_hz))))
        self.dt_outer = self.outer_every * self.dt
        self.pos_sp = tuple(float(v) for v in pos_sp_W_m)
        self.yaw_sp = float(yaw_sp_rad)
        self.manoeuvres = tuple(sorted(manoeuvres, key=lambda m: m.t_start_s))
        self.alloc_inv = [tuple(r) for r in np.linalg.inv(params.allocation()).tolist()]
        J = params.inertia_kg_m2
        # rate-loop constants folded: torque = J (kp e + ki I) - J kd/dt (g - g_prev)
        self._jkp = tuple(J[a] * gains.rate_kp_per_s[a] for a in range(3))
        self._jki = tuple(J[a] * gains.rate_ki_per_s2[a] for a in range(3))
        self._jkd = tuple(J[a] * gains.rate_kd[a] / self.dt for a in range(3))
        self.reset()

    def reset(self) -> None:
        """Zero the integrators and the derivative memory; hover thrust."""
        self.i_rate = [0.0, 0.0, 0.0]
        self.i_alt = 0.0
        self.prev_gyro = None
        self.q_sp = (1.0, 0.0, 0.0, 0.0)
        self.rate_sp = (0.0, 0.0, 0.0)
        self.collective_n = self.p.mass_kg * self.p.gravity_m_s2
        self.thrust_cmd = [self.collective_n / 4.0] * 4
        self.armed = self.arm_at_s <= 0.0

    def outer_due(self, k: int) -> bool:
        """Whether the outer loops run at gyro sample ``k``."""
        return k % self.outer_every == 0

    def offsets(self, t_s: float) -> tuple[float, float, float]:
        """Manoeuvre offsets (roll, pitch, yaw) active at ``t_s``, rad."""
        r = p = y = 0.0
        for m in self.manoeuvres:
            if m.t_start_s <= t_s < m.t_start_s + m.duration_s:
                r += m.roll_rad
                p += m.pitch_rad
                y += m.yaw_rad
        return r, p, y

    def update_outer(self, t_s: float, pos_W, vel_W, q_WB) -> None:
        """Altitude, position and attitude loops (true state) -> rate set point, collective.

        Parameters
        ----------
        t_s : float
            Time, s.
        pos_W, vel_W : sequence of 3 floats
            True position (m) and velocity (m/s), world.
        q_WB : sequence of 4 floats
            True attitude (w, x, y, z), body to world.
        """
        if t_s < self.arm_at_s:  # on the ground, disarmed: nothing runs
            self.armed = False
            return
        self.armed = True
        p, g, dt = self.p, self.g, self.dt_outer
        grav = p.gravity_m_s2
        z_sp = self.pos_sp[2]
        climbing = t_s < self.arm_at_s + self.climb_s
        if climbing:  # take-off: raised-cosine ramp from the ground to the hover height (v = 0 at both ends)
            u = math.pi * (t_s - self.arm_at_s) / self.climb_s
            half = 0.5 * (z_sp - self.z_start_m)
            w = math.pi / self.climb_s
            vz_sp = half * w * math.sin(u)
            az_sp = half * w * w * math.cos(u)
            z_sp = self.z_start_m + half * (1.0 - math.cos(u))
        ez = z_sp - pos_W[2]
        self.i_alt = min(max(self.i_alt + ez * dt, -g.integrator_limit), g.integrator_limit)
        if climbing:
            az = az_sp + g.alt_kp_per_s2 * ez + g.alt_ki_per_s3 * self.i_alt - g.alt_kd_per_s * (vel_W[2] - vz_sp)
        else:
            az = g.alt_kp_per_s2 * ez + g.alt_ki_per_s3 * self.i_alt - g.alt_kd_per_s * vel_W[2]
        ax = g.xy_kp_per_s2 * (self.pos_sp[0] - pos_W[0]) - g.xy_kd_per_s * vel_W[0]
        ay = g.xy_kp_per_s2 * (self.pos_sp[1] - pos_W[1]) - g.xy_kd_per_s * vel_W[1]
        amax = g.max_horiz_accel_m_s2
        ax = min(max(ax, -amax), amax)
        ay = min(max(ay, -amax), amax)
        d_roll, d_pitch, d_yaw = self.offsets(t_s)
        yaw = self.yaw_sp + d_yaw
        cy, sy = math.cos(yaw), math.sin(yaw)
        tmax = g.max_tilt_rad
        pitch = min(max((ax * cy + ay * sy) / grav + d_pitch, -tmax), tmax)
        roll = min(max(-(-ax * sy + ay * cy) / grav + d_roll, -tmax), tmax)
        q_sp = _quat_from_euler_zyx(yaw, pitch, roll)
        self.q_sp = q_sp
        qw, qx, qy, qz = q_WB
        qe = _quat_mul((qw, -qx, -qy, -qz), q_sp)
        sgn = 2.0 if qe[0] >= 0.0 else -2.0
        lim = g.rate_limit_rad_s
        k = g.att_kp_per_s
        self.rate_sp = (
            min(max(k[0] * sgn * qe[1], -lim), lim),
            min(max(k[1] * sgn * qe[2], -lim), lim),
            min(max(k[2] * sgn * qe[3], -lim), lim),
        )
        r33 = 1.0 - 2.0 * (qx * qx + qy * qy)
        self.collective_n = p.mass_kg * (grav + az) / max(r33, 0.5)

    def update_rate(self, g0: float, g1: float, g2: float) -> list[float]:
        """Rate PID on the measured, filtered body rate (rad/s) and the mixer.

        Returns
        -------
        list of 4 floats
            Rotor thrust commands, N (the same list object as ``self.thrust_cmd``); all 0 while
            disarmed (integrators and derivative memory untouched).
        """
        if not self.armed:
            out = self.thrust_cmd
            out[0] = out[1] = out[2] = out[3] = 0.0
            return out
        dt = self.dt
        il = self.g.integrator_limit
        r0, r1, r2 = self.rate_sp
        e0, e1, e2 = r0 - g0, r1 - g1, r2 - g2
        i0, i1, i2 = self.i_rate
        i0 += e0 * dt
        i1 += e1 * dt
        i2 += e2 * dt
        i0 = il if i0 > il else (-il if i0 < -il else i0)
        i1 = il if i1 > il else (-il if i1 < -il else i1)
        i2 = il if i2 > il else (-il if i2 < -il else i2)
        self.i_rate = [i0, i1, i2]
        prev = self.prev_gyro
        if prev is None:
            prev = (g0, g1, g2)
        jkp, jki, jkd = self._jkp, self._jki, self._jkd
        t0 = jkp[0] * e0 + jki[0] * i0 - jkd[0] * (g0 - prev[0])
        t1 = jkp[1] * e1 + jki[1] * i1 - jkd[1] * (g1 - prev[1])
        t2 = jkp[2] * e2 + jki[2] * i2 - jkd[2] * (g2 - prev[2])
        self.prev_gyro = (g0, g1, g2)
        c = self.collective_n
        tm = self.p.max_thrust_n
        out = self.thrust_cmd
        for i, (a0, a1, a2, a3) in enumerate(self.alloc_inv):
            ti = a0 * c + a1 * t0 + a2 * t1 + a3 * t2
            out[i] = tm if ti > tm else (0.0 if ti < 0.0 else ti)
        return out

    def update(self, k: int, t_s: float, pos_W, vel_W, q_WB, gyro_B) -> list[float]:
        """Both loops for sample ``k`` (outer only when due). Returns the rotor thrusts, N."""
        if self.outer_due(k):
            self.update_outer(t_s, pos_W, vel_W, q_WB)
        return self.update_rate(gyro_B[0], gyro_B[1], gyro_B[2])
