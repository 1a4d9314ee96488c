"""Closed-loop flight with flight-controller firmware in the loop.

The MuJoCo vehicle (:mod:`sim.vehicles`) flies on a real firmware's gyro filters, PID loop and
mixer (:class:`sim.firmware.BetaflightSITL`, lockstep: one firmware loop per gyro sample). Per
firmware loop (``loop_rate_hz``, 8 kHz by default; physics at an integer multiple >= 1 of it):

1. rotor forces from the rotors' actual state (:func:`sim.quadrotor.rotor_forces`: thrust with
   blade-pass ripple, 2nd imbalance harmonic; 1st harmonic and hub moment are MuJoCo masses), the
   held rotor-speed commands, ``mj_step``; the sensors give the state at ``t_k``;
2. the synthetic MEMS gyro (:class:`sim.gyro.SyntheticGyro` at the loop rate, its whole effect
   catalogue and the spec's shaped vibration) turns the true rate into the measured one;
3. the pilot (:class:`Pilot`, 250 Hz: the altitude/position/attitude loops of
   :class:`sim.controller.CascadedController` on the true state) turns its rate set point into
   sticks through the inverse of the firmware's own rate curve (:class:`RateProfile`) and its
   collective thrust into a throttle stick (:class:`MotorLaw`);
4. one firmware step: gyro (the firmware applies its own int16 scaling, 16.4 LSB per deg/s),
   specific force, attitude, the rotor speeds (as bidirectional-DShot telemetry would give them
   to the RPM filter) and the sticks in; four motor outputs out;
5. the motor outputs set the rotor-speed commands of the next physics step (:class:`MotorLaw`),
   through the vehicle's speed servo (motor time constant ``J_r / kv``) and the drag-torque
   feed-forward the hover runner uses.

Motor order. Betaflight's quad-X numbers its motors 1 rear-right, 2 front-right, 3 rear-left,
4 front-left (its ``mixerQuadX``); the models number their rotors PX4-style 1 front-right,
2 rear-left, 3 front-left, 4 rear-right. Both spin front-right and rear-left counter-clockwise
seen from above (Betaflight's default, ``yaw_motors_reversed = OFF``). :data:`ROTOR_OF_BF_MOTOR`
maps one to the other; the data file's ``motor_1..4`` are in Betaflight's order (metadata
``motor_order``).

Sticks. Betaflight's rate frame is the body frame FLU here for roll and pitch (roll stick right =
right roll = +x; pitch stick forward = nose down = +y) and yaw stick right = nose right = −z
(its ``rcCommand[YAW]`` is the stick negated, ``yaw_control_reversed = OFF``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Mapping, Protocol, Sequence

import numpy as np
from scipy import signal

from gyrocore.errors import GyroInputError

from .quadrotor import AttitudeLog

__all__ = [
    "BF_MOTOR_NAMES",
    "ROTOR_OF_BF_MOTOR",
    "SCENARIOS",
    "FwFlightLog",
    "FwFlightOptions",
    "MotorLaw",
    "Pilot",
    "RateProfile",
    "RatePulse",
    "fly_firmware",
    "motor_law",
    "rate_pulses",
]

#: Betaflight quad-X motor positions, motors 1..4
BF_MOTOR_NAMES = ("rear-right", "front-right", "rear-left", "front-left")
#: the model's rotor index (0-based, PX4 order FR, RL, FL, RR) of Betaflight motor j (0-based)
ROTOR_OF_BF_MOTOR = (3, 0, 1, 2)
#: Betaflight motor index (0-based) of the model's rotor i
BF_MOTOR_OF_ROTOR = (1, 2, 3, 0)

#: scenario name -> description (``gyroharness firmware fly SCENARIO``)
SCENARIOS = {
    "hover": "steady hover at 1 m, no manoeuvres",
    "steps": "hover, then rate steps: on roll, pitch and yaw in turn a pulse of +R then one of -R (R = 2 rad/s, "
    "up to 0.15 s each: the attitude set point ramps with it and comes back level)",
}

#: firmware stick range, us (Betaflight PWM_RANGE_MIN/MAX, midrc)
_STICK_MIN_US, _STICK_MID_US, _STICK_MAX_US = 1000, 1500, 2000


# ----------------------------------------------------------------------------- motors
@dataclass(frozen=True)
class MotorLaw:
    """Steady rotor speed for a firmware motor command (the ESC + motor + prop in one law).

    ``u`` is the firmware's motor command as a fraction of its motor output range (0 at the idle
    output, 1 at full: Betaflight's ``motorOutput`` low..high, what its blackbox logs as
    ``motor[i]``); the steady rotor speed is affine in it, ``Omega = omega_idle + (omega_full -
    omega_idle) u``. A disarmed (or stopped) motor is 0.

    Parameters
    ----------
    omega_idle_rad_s, omega_full_rad_s : float
        Steady rotor speed at u = 0 and u = 1, rad/s.
    source : str
        Where the law comes from.
    """

    omega_idle_rad_s: float
    omega_full_rad_s: float
    source: str

    def speed_rad_s(self, u: float) -> float:
        """Steady rotor speed for command ``u`` (0..1 of the output range), rad/s."""
        return self.omega_idle_rad_s + (self.omega_full_rad_s - self.omega_idle_rad_s) * u

    def command_for_speed(self, omega_rad_s: float) -> float:
        """The command u whose steady speed is ``omega_rad_s`` (not clipped)."""
        return (omega_rad_s - self.omega_idle_rad_s) / (self.omega_full_rad_s - self.omega_idle_rad_s)


def motor_law(vehicle, idle_fraction: float) -> MotorLaw:
    """The motor law of a vehicle class (:class:`MotorLaw`).

    ``racing25`` (the quad of the shared Betaflight log): the log's own rotor line law,
    f = 242.5 + 401.6 u Hz (``gyroharness vibration`` on better_tune.BBL, u the mean motor command
    as a fraction of ``motorOutput``; models/racing25.xml). Other classes have no measured law:
    the rotor speed is taken proportional to the ESC output (duty) ``idle + (1 - idle) u``, full
    output at the class's maximum thrust, Omega_max = sqrt(T_max / c_T) (an estimate: a loaded
    motor's speed is close to proportional to its voltage).

    Parameters
    ----------
    vehicle : str or VehicleClass
    idle_fraction : float
        The firmware's idle output as a fraction of full output (Betaflight
        ``dshot_idle_value`` / 10000), used by the proportional law.
    """
    from .vehicles import get_vehicle

    veh = get_vehicle(vehicle)
    if veh.name == "racing25":
        two_pi = 2.0 * math.pi
        return MotorLaw(
            two_pi * 242.5,
            two_pi * (242.5 + 401.6),
            "the log's rotor line law f = 242.5 + 401.6 u Hz (models/racing25.xml)",
        )
    p = veh.params
    w_max = math.sqrt(p.max_thrust_n / p.c_t_n_per_rad2_s2)
    i = float(idle_fraction)
    return MotorLaw(
        w_max * i,
        w_max,
        f"rotor speed proportional to the ESC output, {w_max:.1f} rad/s at full output "
        f"(sqrt(T_max / c_T), T_max {p.max_thrust_n:g} N; estimate), idle {100 * i:g} %",
    )


# ----------------------------------------------------------------------------- rates
#: Betaflight's rate types in its lookup order (cli/settings.c lookupTableRatesType)
_RATES_TYPES = ("BETAFLIGHT", "RACEFLIGHT", "KISS", "ACTUAL", "QUICK")
_AXES = ("roll", "pitch", "yaw")


@dataclass(frozen=True)
class RateProfile:
    """The firmware's stick-to-rate curve (Betaflight ``fc/rc.c``, ``applyRates``), per axis.

    Fields carry Betaflight's CLI values (``rates_type``, ``roll_rc_rate`` …, ``roll_expo`` …,
    ``roll_srate`` …, ``quickrates_rc_expo``, ``roll_rate_limit`` …); the defaults are
    Betaflight 4.6's (ACTUAL, centre 70 deg/s, max 670 deg/s, no expo).
    """

    rates_type: str = "ACTUAL"
    rc_rate: tuple[int, int, int] = (7, 7, 7)
    expo: tuple[int, int, int] = (0, 0, 0)
    srate: tuple[int, int, int] = (67, 67, 67)
    rate_limit: tuple[int, int, int] = (1998, 1998, 1998)
    quick_rc_expo: bool = False

    def __post_init__(self) -> None:
        if self.rates_type not in _RATES_TYPES:
            raise GyroInputError(f"rates_type {self.rates_type!r}: one of {', '.join(_RATES_TYPES)}")

    @classmethod
    def from_settings(cls, settings: Mapping[str, str] | Sequence[tuple[str, str]]) -> RateProfile:
        """The profile from firmware settings (CLI names; missing ones keep their defaults)."""
        s = {
            str(k).strip().lower(): str(v).strip()
            for k, v in (settings.items() if isinstance(settings, Mapping) else settings)
        }
        d = cls()

        def trio(fmt, default):
            out = []
            for a, dv in zip(_AXES, default):
                v = s.get(fmt.format(a))
                try:
                    out.append(dv if v is None else int(float(v)))
                except ValueError:
                    raise GyroInputError(f"setting {fmt.format(a)} = {v!r}: not a number") from None
            return tuple(out)

        rt = s.get("rates_type", d.rates_type).upper()
        if rt.isdigit():  # a log header gives the lookup index (Betaflight's lookupTableRatesType order)
            if int(rt) >= len(_RATES_TYPES):
                raise GyroInputError(
                    f"rates_type index {rt}: Betaflight has {len(_RATES_TYPES)} ({', '.join(_RATES_TYPES)})"
                )
            rt = _RATES_TYPES[int(rt)]
        return cls(
            rates_type=rt,
            rc_rate=trio("{}_rc_rate", d.rc_rate),
            expo=trio("{}_expo", d.expo),
            srate=trio("{}_srate", d.srate),
            rate_limit=trio("{}_rate_limit", d.rate_limit),
            quick_rc_expo=s.get("quickrates_rc_expo", "OFF").upper() in ("ON", "1"),
        )

    def rate_deg_s(self, axis: int, d: float) -> float:
        """Rate set point (deg/s) for stick deflection ``d`` in [-1, 1] on ``axis`` (0 roll, 1 pitch,
        2 yaw), as the firmware computes it (before its sign conventions and RC smoothing)."""
        x, ax = float(d), abs(float(d))
        rc, ex, sr = self.rc_rate[axis], self.expo[axis], self.srate[axis]
        t = self.rates_type
        if t == "BETAFLIGHT":
            if ex:
                e = ex / 100.0
                x = x * ax**3 * e + x * (1 - e)
            r = rc / 100.0
            if r > 2.0:
                r += 14.54 * (r - 2.0)
            rate = 200.0 * r * x
            if sr:
                rate *= 1.0 / min(max(1.0 - ax * sr / 100.0, 0.01), 1.0)
        elif t == "RACEFLIGHT":
            x = (1.0 + 0.01 * ex * (x * x - 1.0)) * x
            rate = 10.0 * rc * x * (1 + ax * sr * 0.01)
        elif t == "KISS":
            use = 1.0 / min(max(1.0 - ax * sr / 100.0, 0.01), 1.0)
            c = ex / 100.0
            rate = min(max(2000.0 * use * (x**3 * c + x * (1 - c)) * rc / 1000.0, -1998.0), 1998.0)
        elif t == "ACTUAL":
            e = ex / 100.0
            ef = ax * (x**5 * e + x * (1 - e))
            centre = rc * 10.0
            rate = x * centre + max(0.0, sr * 10.0 - centre) * ef
        else:  # QUICK
            rcr = rc * 2
            mx = max(sr * 10, rcr)
            e = ex / 100.0
            sf = (mx / rcr - 1) / (mx / rcr)
            if self.quick_rc_expo:
                curve = x**3 * e + x * (1 - e)
                rate = min(max(curve * rcr / min(max(1.0 - ax * sf, 0.01), 1.0), -1998.0), 1998.0)
            else:
                curve = ax**3 * e + ax * (1 - e)
                rate = min(max(x * rcr / min(max(1.0 - curve * sf, 0.01), 1.0), -1998.0), 1998.0)
        lim = float(self.rate_limit[axis])
        return min(max(rate, -lim), lim)

    def deflection(self, axis: int, rate_deg_s: float) -> float:
        """The stick deflection in [-1, 1] whose rate is ``rate_deg_s`` (the curve is odd and
        monotone: bisection to 1e-9; a rate beyond the curve's maximum gives full deflection)."""
        r = float(rate_deg_s)
        if r == 0.0:
            return 0.0
        sgn, r = (1.0, r) if r > 0 else (-1.0, -r)
        if self.rate_deg_s(axis, 1.0) <= r:
            return sgn
        lo, hi = 0.0, 1.0
        for _ in range(34):
            mid = 0.5 * (lo + hi)
            if self.rate_deg_s(axis, mid) < r:
                lo = mid
            else:
                hi = mid
        return sgn * 0.5 * (lo + hi)


# ----------------------------------------------------------------------------- scenario
@dataclass(frozen=True)
class RatePulse:
    """A rate step the pilot flies: ``rate_rad_s`` about body ``axis`` (0 x, 1 y, 2 z) for
    ``duration_s`` from ``t_start_s``; the attitude set point ramps with it (roll/pitch about the
    body axes at the set point, yaw about world z). During the pulse the stick on its axis is the
    pulse alone (the firmware sees a clean rate step); after it, the attitude loop takes up the
    angle the vehicle lagged behind the ramp."""

    t_start_s: float
    duration_s: float
    axis: int
    rate_rad_s: float


#: rate of the scenario's rate pulses, rad/s (115 deg/s: a brisk but ordinary acro input)
STEP_RATE_RAD_S = 2.0
#: longest pulse, s (2 rad/s x 0.15 s = 17 deg of tilt, inside the pilot's 20 deg tilt limit)
STEP_MAX_S = 0.15


def rate_pulses(duration_s: float, settle_s: float) -> tuple[RatePulse, ...]:
    """The ``steps`` scenario: hover until ``t0 = max(settle_s + 0.5, settle_s + 0.4 (duration_s -
    settle_s))``, then six equal slots (roll +, roll -, pitch +, pitch -, yaw +, yaw -), each a
    pulse of ``min(0.15 s, 0.4 slot)`` then level hover."""
    t0 = max(settle_s + 0.5, settle_s + 0.4 * (duration_s - settle_s))
    slot = (duration_s - t0) / 6.0
    if slot < 0.1:
        raise GyroInputError(f"the steps scenario needs at least {t0 + 0.6:g} s (settling, hover, six rate pulses)")
    tau = min(STEP_MAX_S, 0.4 * slot)
    out = []
    for i, (ax, sgn) in enumerate(((0, 1), (0, -1), (1, 1), (1, -1), (2, 1), (2, -1))):
        out.append(RatePulse(t0 + i * slot, tau, ax, sgn * STEP_RATE_RAD_S))
    return tuple(out)


def _pulse_controller(base_cls):
    """A :class:`sim.controller.CascadedController` whose manoeuvre offsets are the integral of
    rate pulses (the attitude set point ramps with the commanded rate)."""

    class PulseController(base_cls):
        def __init__(self, *a, pulses=(), **kw):
            super().__init__(*a, **kw)
            self.pulses = tuple(pulses)

        def offsets(self, t_s: float) -> tuple[float, float, float]:
            off = [0.0, 0.0, 0.0]
            for p in self.pulses:
                if t_s > p.t_start_s:
                    off[p.axis] += p.rate_rad_s * min(t_s - p.t_start_s, p.duration_s)
            return off[0], off[1], off[2]

        def rate_ff(self, t_s: float) -> tuple[float, float, float]:
            """The pulses active at ``t_s`` (body rate feed-forward), rad/s."""
            ff = [0.0, 0.0, 0.0]
            for p in self.pulses:
                if p.t_start_s <= t_s < p.t_start_s + p.duration_s:
                    ff[p.axis] += p.rate_rad_s
            return ff[0], ff[1], ff[2]

    return PulseController


# ----------------------------------------------------------------------------- pilot
class Pilot:
    """The pilot: the hover runner's outer loops on the true state, flying the firmware's sticks.

    Parameters
    ----------
    ctl : sim.controller.CascadedController
        Its altitude/position/attitude loops (:meth:`~sim.controller.CascadedController.update_outer`)
        give the body rate set point (FLU, rad/s) and the collective thrust (N); its rate loop is
        not used (the firmware's is).
    rates : RateProfile
    law : MotorLaw
    c_t : float
        Thrust coefficient, N/(rad/s)^2.
    mincheck_us : int
        The firmware's ``min_check``: its throttle command is (stick - min_check) / (2000 -
        min_check) of the motor output range (Betaflight ``rc.c``, linear ``thr_mid``/``thr_expo``
        defaults); the altitude loop's integrator takes up what this feed-forward misses (throttle
        expo, TPA, battery sag are not modelled here).
    """

    def __init__(self, ctl, rates: RateProfile, law: MotorLaw, c_t: float, *, mincheck_us: int = 1050) -> None:
        self.ctl, self.rates, self.law, self.c_t = ctl, rates, law, float(c_t)
        self.mincheck_us = int(mincheck_us)
        self.rate_sp = (0.0, 0.0, 0.0)

    def sticks(self, t_s: float) -> tuple[int, int, int, int]:
        """(throttle, roll, pitch, yaw) in us for the controller's current rate set point (plus the
        rate pulses active at ``t_s``) and collective thrust. Also sets :attr:`rate_sp`."""
        ff = self.ctl.rate_ff(t_s) if hasattr(self.ctl, "rate_ff") else (0.0, 0.0, 0.0)
        # on an axis with a pulse the stick is the pulse alone (a clean stick step, as a pilot's);
        # the attitude loop takes up what the vehicle lagged once the pulse is over
        wx, wy, wz = (b if b != 0.0 else a for a, b in zip(self.ctl.rate_sp, ff))
        self.rate_sp = (wx, wy, wz)
        r = self.rates
        deg = 180.0 / math.pi
        d = (r.deflection(0, wx * deg), r.deflection(1, wy * deg), r.deflection(2, -wz * deg))
        t_rotor = max(self.ctl.collective_n / 4.0, 0.0)
        u = min(max(self.law.command_for_speed(math.sqrt(t_rotor / self.c_t)), 0.0), 1.0)
        thr = self.mincheck_us + (_STICK_MAX_US - self.mincheck_us) * u
        return (int(round(thr)),) + tuple(int(round(_STICK_MID_US + 500.0 * x)) for x in d)


# ----------------------------------------------------------------------------- the flight
class FirmwareLike(Protocol):
    """What the flight needs of the firmware (:class:`sim.firmware.BetaflightSITL`, booted and armed)."""

    def step(self, omega_S_rad_s, accel_S_m_s2, q_WB_wxyz, rotor_rad_s, rc): ...


@dataclass(frozen=True)
class FwFlightOptions:
    """One firmware flight.

    Parameters
    ----------
    scenario : str
        :data:`SCENARIOS` key.
    vehicle : str
        :data:`sim.vehicles.VEHICLES` key.
    duration_s : float
        Scored flight time, s (the firmware's boot and arming are before t = 0, not counted).
    seed : int
        Sensor instance and noise, rotor phases.
    sensor : str or None
        Sensor preset (``sim/presets``) or TOML path; None: a perfect gyro (the true rate; the
        firmware's int16 scaling still applies).
    loop_rate_hz : float
        The firmware's gyro/PID loop rate (one firmware step per gyro sample), Hz.
    vibration : bool or sim.quadrotor.VibrationSpec
        Rotor vibration through the physics (True: the class's default).
    gyro_overrides : mapping, optional
        Overrides of the synthetic gyro (``{"vibration": shaped part}`` from a spec).
    idle_fraction : float
        The firmware's idle output as a fraction of full output (motor law of classes without a
        measured one).
    settle_s : float
        Start of the scored hover, s.
    hover_command : float, optional
        Hover at this motor command u (0..1 of the output range) instead of the class's own: a
        payload at the centre of mass makes the weight 4 c_T Omega(u)^2 (inertia unchanged), so the
        rotors spin where a log's throttle band had them (its rotor line, RPM filter, dynamic
        notch and dynamic LPF at that throttle). Default: the class's weight.
    """

    scenario: str = "hover"
    vehicle: str = "racing25"
    duration_s: float = 3.0
    seed: int = 0
    sensor: str | None = "icm42688p"
    loop_rate_hz: float = 8000.0
    vibration: object = True
    gyro_overrides: Mapping | None = None
    idle_fraction: float = 0.055
    settle_s: float = 1.0
    mincheck_us: int = 1050
    rates: RateProfile = field(default_factory=RateProfile)
    hover_command: float | None = None

    def __post_init__(self) -> None:
        if self.scenario not in SCENARIOS:
            raise GyroInputError(f"unknown firmware flight scenario {self.scenario!r}; known: {', '.join(SCENARIOS)}")
        if not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise GyroInputError(f"--duration-s must be > 0, got {self.duration_s}")
        if not (0.0 <= self.settle_s < self.duration_s):
            raise GyroInputError(f"settle_s must be in [0, duration_s), got {self.settle_s}")
        if not (self.loop_rate_hz > 0 and math.isfinite(self.loop_rate_hz)):
            raise GyroInputError(f"loop rate must be > 0 Hz, got {self.loop_rate_hz}")


@dataclass(frozen=True, eq=False)
class FwFlightLog(AttitudeLog):
    """A firmware flight at the firmware loop's samples (N rows).

    Frames: S = B (FLU); W world (z up). Motor columns in Betaflight's motor order.

    Parameters
    ----------
    t_s : (N,)
    omega_true_rad_s, f_S_m_s2 : (N, 3)
        True rate of S in S, true specific force in S.
    q_WB_wxyz, q_sp_wxyz : (N, 4)
        True and commanded attitude (body to world).
    pos_W_m, vel_W_m_s : (N, 3)
    gyro_meas_rad_s : (N, 3)
        The synthetic gyro as sent to the firmware (before its int16 scaling).
    fw_gyro_rad_s : (N, 3)
        The firmware's filtered gyro (its PID input), S, rad/s.
    fw_dterm_rad_s : (N, 3) or None
        The firmware's D-term input (the gyro after its D-term filters), S, rad/s, or None.
    fw_pid_d : (N, 3) or None
        The firmware's D term (``pidData[].D``, roll/pitch/yaw, its own units: 1000 = full motor
        range), or None.
    fw_setpoint_rad_s : (N, 3) or None
        The firmware's rate set point (after its RC smoothing), S, rad/s, or None.
    motors : (N, 4)
        Motor outputs 0..1 of full output, Betaflight order.
    rotor_speed_rad_s : (N, 4)
        True rotor speeds (magnitude), Betaflight order.
    rate_sp_rad_s : (N, 3)
        The pilot's body rate set point (FLU).
    sticks_us : (N, 4)
        Throttle, roll, pitch, yaw sticks sent, us.
    temp_c : (N,)
    manoeuvres : tuple of RatePulse
    meta : dict
    wall_s : float
        Wall time of the flight loop, s (not written to the data file).
    """

    t_s: np.ndarray
    omega_true_rad_s: np.ndarray
    f_S_m_s2: np.ndarray
    q_WB_wxyz: np.ndarray
    q_sp_wxyz: np.ndarray
    pos_W_m: np.ndarray
    vel_W_m_s: np.ndarray
    gyro_meas_rad_s: np.ndarray
    fw_gyro_rad_s: np.ndarray
    fw_dterm_rad_s: np.ndarray | None
    fw_pid_d: np.ndarray | None
    fw_setpoint_rad_s: np.ndarray | None
    motors: np.ndarray
    rotor_speed_rad_s: np.ndarray
    rate_sp_rad_s: np.ndarray
    sticks_us: np.ndarray
    temp_c: np.ndarray
    manoeuvres: tuple
    meta: dict
    wall_s: float = float("nan")

    def crashed(self) -> bool:
        """Non-finite state or a tilt beyond 60 deg (the pilot's steps are 5 deg)."""
        return (not np.all(np.isfinite(self.q_WB_wxyz))) or float(np.max(self.tilt_rad())) > math.radians(60.0)

    def hover_mask(self, settle_s: float) -> np.ndarray:
        """Samples of steady hover: after ``settle_s``, before the first manoeuvre."""
        end = min((m.t_start_s for m in self.manoeuvres), default=math.inf)
        return (self.t_s >= settle_s) & (self.t_s < end)

    def highpass_rms(self, x: np.ndarray, mask: np.ndarray, *, highpass_hz: float = 20.0) -> float:
        """RMS above ``highpass_hz`` (4th-order Butterworth, zero-phase over the whole flight,
        then restricted to ``mask``), mean over columns in quadrature (RMS of all columns)."""
        sos = signal.butter(4, highpass_hz, btype="highpass", fs=self.rate_hz, output="sos")
        hp = signal.sosfiltfilt(sos, np.asarray(x, float), axis=0)[mask]
        return float(np.sqrt(np.mean(hp**2))) if hp.size else float("nan")

    def gyro_delay_s(self) -> float:
        """Delay of the firmware's filtered gyro behind the true rate in 0.2-15 Hz, s (the
        cross-correlation of :meth:`sim.quadrotor.FlightLog.gyro_delay_s`)."""
        from types import SimpleNamespace

        from .quadrotor import FlightLog

        view = SimpleNamespace(
            rate_hz=self.rate_hz, omega_true_rad_s=self.omega_true_rad_s, gyro_filt_rad_s=self.fw_gyro_rad_s
        )
        return FlightLog.gyro_delay_s(view)

    def step_responses(self) -> list[dict]:
        """Per rate pulse (:class:`RatePulse`): the rate step response of its axis.

        The response is the true body rate on the pulse's axis divided by the pulse's rate, over
        the pulse. Rise time: time to 90 % minus time to 10 %; overshoot: the peak above 1, in %;
        tracking error: RMS of (response - 1) over the pulse's second half, in %.
        """
        out = []
        dt = 1.0 / self.rate_hz
        for p in self.manoeuvres:
            i0 = int(np.searchsorted(self.t_s, p.t_start_s))
            i1 = int(np.searchsorted(self.t_s, p.t_start_s + p.duration_s))
            if i1 - i0 < 10:
                continue
            r = self.omega_true_rad_s[i0:i1, p.axis] / p.rate_rad_s
            k10 = np.flatnonzero(r >= 0.1)
            k90 = np.flatnonzero(r >= 0.9)
            rise = float((k90[0] - k10[0]) * dt) if k10.size and k90.size else float("nan")
            half = r[r.size // 2 :]
            out.append(
                {
                    "axis": _AXES[p.axis],
                    "t_start_s": p.t_start_s,
                    "rate_deg_s": math.degrees(p.rate_rad_s),
                    "rise_s": rise,
                    "overshoot_pct": float(100.0 * max(np.max(r) - 1.0, 0.0)),
                    "tracking_error_pct": float(100.0 * np.sqrt(np.mean((half - 1.0) ** 2))),
                }
            )
        return out

    def scores(self, settle_s: float) -> dict:
        """The flight's figures (JSON of ``gyroharness firmware fly``; units in the names)."""
        nan = float("nan")
        if self.crashed():
            return {"crashed": True}
        hov = self.hover_mask(settle_s)
        err = np.degrees(self.attitude_error_rad())
        after = self.t_s >= settle_s
        steps_mask = after & ~hov
        out = {
            "crashed": False,
            "hover_att_rms_deg": float(np.sqrt(np.mean(err[hov] ** 2))) if hov.any() else nan,
            "hover_att_max_deg": float(np.max(err[hov])) if hov.any() else nan,
            "step_track_rms_deg": float(np.sqrt(np.mean(err[steps_mask] ** 2))) if steps_mask.any() else None,
            "motor_noise_above_20hz": self.highpass_rms(self.motors, hov if hov.any() else after),
            # the cross-correlation needs motion in the flight band: steps only
            "gyro_delay_ms": 1e3 * self.gyro_delay_s() if self.manoeuvres else None,
            "fw_gyro_noise_above_20hz_rad_s": self.highpass_rms(self.fw_gyro_rad_s, hov if hov.any() else after),
            "raw_gyro_noise_above_20hz_rad_s": self.highpass_rms(self.gyro_meas_rad_s, hov if hov.any() else after),
            "dterm_noise_above_20hz": (
                self.highpass_rms(self.fw_pid_d, hov if hov.any() else after) if self.fw_pid_d is not None else None
            ),
            "dterm_input_noise_above_20hz_rad_s": (
                self.highpass_rms(self.fw_dterm_rad_s, hov if hov.any() else after)
                if self.fw_dterm_rad_s is not None
                else None
            ),
            "mean_motor": float(np.mean(self.motors[after])),
            "altitude_error_rms_m": float(np.sqrt(np.mean((self.pos_W_m[after, 2] - 1.0) ** 2))),
        }
        sr = self.step_responses()
        if sr:
            out["steps"] = sr
            rp = [s for s in sr if s["axis"] != "yaw"]  # roll and pitch: the axes a gyro filter shapes
            rises = [s["rise_s"] for s in rp if np.isfinite(s["rise_s"])]
            out["step_rise_ms"] = 1e3 * float(np.median(rises)) if rises else nan
            out["step_overshoot_pct"] = float(np.median([s["overshoot_pct"] for s in rp])) if rp else nan
        return out


def _settings_value(settings, name: str, default: str) -> str:
    for k, v in settings.items() if isinstance(settings, Mapping) else settings:
        if str(k).strip().lower() == name:
            return str(v).strip()
    return default


class _SetupOnly:
    """The gyro given to :class:`sim.quadrotor.HoverFlight` when it only sets the flight up (its
    model, vibration, rotor phases, pilot): not a ``PerfectGyro``, so no compiled kernel is built."""

    def step(self, k, t_s, omega_S, f_S, temp_c):
        return omega_S


def _add_payload(model, data, hf, veh, law, u: float):
    """Make the vehicle hover at motor command ``u`` (``FwFlightOptions.hover_command``): the frame
    body carries the extra mass (inertia unchanged), the rotors start at the new hover speed.
    Returns the pilot's :class:`sim.controller.QuadParams` with the new mass."""
    from dataclasses import replace as _replace

    import mujoco

    if not 0.0 < u <= 1.0:
        raise GyroInputError(f"hover command must be in (0, 1], got {u}")
    p = veh.params
    om = law.speed_rad_s(u)
    m_new = 4.0 * p.c_t_n_per_rad2_s2 * om * om / p.gravity_m_s2
    m_old = float(mujoco.mj_getTotalmass(model))
    if m_new < 0.5 * m_old:
        raise GyroInputError(
            f"hover command {u:g} is below the {veh.name}'s own hover: it would need a lighter vehicle"
        )
    fid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "frame")
    model.body_mass[fid] += m_new - m_old
    mujoco.mj_setConst(model, data)
    rv0 = hf.rv0
    data.qvel[rv0 : rv0 + 4] = [s * om for s in hf.spin]
    t = p.c_t_n_per_rad2_s2 * om * om
    data.ctrl[0:4] = t
    data.ctrl[12:16] = [s * (om + hf.ff * t) for s in hf.spin]
    mujoco.mj_forward(model, data)
    return _replace(p, mass_kg=m_new)


def fly_firmware(opts: FwFlightOptions, fw: FirmwareLike, *, fw_meta: Mapping[str, str] | None = None) -> FwFlightLog:
    """Fly ``opts`` with the firmware ``fw`` (booted and armed) in the loop (module docstring).

    Returns the flight log; the same options and firmware settings give the same log bit for bit
    (every random draw is seeded; the firmware runs in lockstep).
    """
    import mujoco

    from .controller import CascadedController
    from .gyro import SyntheticGyro
    from .quadrotor import HoverFlight, rotor_forces
    from .thermal import ThermalSpec, simulate_temperature
    from .vehicles import get_vehicle

    veh = get_vehicle(opts.vehicle)
    rate = float(opts.loop_rate_hz)
    pulses = rate_pulses(opts.duration_s, opts.settle_s) if opts.scenario == "steps" else ()
    # the physics at an integer multiple >= 1 of the loop rate, at least the class's own rate
    phys = max(float(veh.physics_rate_hz), rate)
    hf = HoverFlight(
        duration_s=opts.duration_s,
        gyro=_SetupOnly(),
        vibration=opts.vibration,
        physics_rate_hz=phys,
        gyro_rate_hz=rate,
        seed=opts.seed,
        vehicle=veh,
    )
    n, m_per = hf.n, hf.m_per
    model, data = hf.model, hf.data
    t_all = np.arange(n) / rate
    th = ThermalSpec.constant(25.0)
    temp = simulate_temperature(t_all, th)
    if opts.sensor is None:

        def gstep(k, t_s, omega_S, f_S, temp_c):
            return omega_S
    else:
        g = SyntheticGyro(opts.sensor, rate_hz=rate, seed=opts.seed, overrides=dict(opts.gyro_overrides or {}) or None)
        gstep = g.stream(n, t_s=t_all, temp_c=temp).step
    law = motor_law(veh, opts.idle_fraction)
    params = veh.params
    if opts.hover_command is not None:
        params = _add_payload(model, data, hf, veh, law, float(opts.hover_command))
    # the pilot: the hover runner's outer loops (same constants as HoverFlight's own) flying the pulses
    ctl = _pulse_controller(CascadedController)(
        params, veh.gains, dt_s=1.0 / rate, pos_sp_W_m=tuple(data.qpos[0:3].tolist()), yaw_sp_rad=0.0, pulses=pulses
    )
    pilot = Pilot(ctl, opts.rates, law, params.c_t_n_per_rad2_s2, mincheck_us=opts.mincheck_us)
    spin, ff, ct = hf.spin, hf.ff, hf.ct
    rotor_k = hf.rotor_k
    rq0, rv0 = hf.rq0, hf.rv0
    s = hf.sens
    s_g, s_a, s_q, s_p, s_v = s["gyro"], s["acc"], s["quat"], s["pos"], s["vel"]
    qpos, qvel, ctrl, sd = data.qpos, data.qvel, data.ctrl, data.sensordata
    step = mujoco.mj_step
    idle = float(opts.idle_fraction)

    sd_log = np.empty((n, model.nsensordata))
    gyro_log = np.empty((n, 3))
    fwg = np.empty((n, 3))
    fwd = np.full((n, 3), np.nan)
    fwp = np.full((n, 3), np.nan)
    fws = np.full((n, 3), np.nan)
    mot = np.empty((n, 4))
    rot = np.empty((n, 4))
    rsp = np.empty((n, 3))
    qsp = np.empty((n, 4))
    stk = np.empty((n, 4))
    mot_cmd = tuple(data.ctrl[12:16].tolist())  # the hover keyframe's commands until the first firmware reply
    sticks = pilot.sticks(0.0)
    have_dterm = None
    oe = ctl.outer_every
    t0 = time.perf_counter()
    for k in range(n):
        om = qvel[rv0 : rv0 + 4].tolist()
        ctrl[:] = rotor_forces(qpos[rq0 : rq0 + 4].tolist(), om, rotor_k) + mot_cmd
        step(model, data)
        row = sd_log[k]
        row[:] = sd  # the state at t_k (MuJoCo's sensors are computed at the start of the step)
        tk = float(t_all[k])
        gm = gstep(k, tk, row[s_g : s_g + 3], row[s_a : s_a + 3], float(temp[k]))
        gyro_log[k] = gm
        if k % oe == 0:
            rl = row.tolist()
            ctl.update_outer(tk, rl[s_p : s_p + 3], rl[s_v : s_v + 3], rl[s_q : s_q + 4])
            sticks = pilot.sticks(tk)
        w = [abs(v) for v in qvel[rv0 : rv0 + 4].tolist()]  # rotor speeds after this step, as telemetry reports them
        rpm_bf = [w[ROTOR_OF_BF_MOTOR[j]] for j in range(4)]
        rep = fw.step(
            np.array(gm, float), row[s_a : s_a + 3].copy(), row[s_q : s_q + 4].copy(), np.array(rpm_bf), sticks
        )
        v = [float(x) for x in rep.motors]
        mot[k] = v
        rot[k] = rpm_bf
        fwg[k] = rep.fw_gyro_S_rad_s
        dterm = getattr(rep, "fw_dterm_S_rad_s", None)
        if dterm is not None:
            fwd[k] = dterm
            fwp[k] = rep.pid_rpy[2]
            fws[k] = rep.setpoint_S_rad_s
            have_dterm = True
        rsp[k] = pilot.rate_sp
        qsp[k] = ctl.q_sp
        stk[k] = sticks
        # motor outputs -> rotor speed commands (the hover runner's servo law: speed + drag feed-forward)
        cmds = []
        for i in range(4):
            vi = v[BF_MOTOR_OF_ROTOR[i]]
            if vi <= 0.0:
                om_ss = 0.0
            else:
                u = min(max((vi - idle) / (1.0 - idle), 0.0), 1.0)
                om_ss = law.speed_rad_s(u)
            cmds.append(spin[i] * (om_ss + ff * ct * om_ss * om_ss))
        mot_cmd = tuple(cmds)
        for _ in range(m_per - 1):
            ctrl[:] = rotor_forces(qpos[rq0 : rq0 + 4].tolist(), qvel[rv0 : rv0 + 4].tolist(), rotor_k) + mot_cmd
            step(model, data)
    wall = time.perf_counter() - t0
    meta = dict(hf.meta)
    meta.update(
        {
            "runner": "sim.fw_flight.fly_firmware",
            "manoeuvres": f"{len(pulses)} rate pulses" if pulses else "0",
            "scenario": opts.scenario,
            "sensor": opts.sensor or "perfect (the true rate)",
            "loop_rate_hz": f"{rate:.10g}",
            "gyro": "SyntheticGyro",
            "pipeline": "firmware",
            "motor_order": "betaflight quad-X: "
            + ", ".join(f"motor_{j + 1} {nm}" for j, nm in enumerate(BF_MOTOR_NAMES)),
            "motor_law": law.source,
            "motor_idle_fraction": f"{idle:g}",
            **(
                {"hover_command": f"{opts.hover_command:g} (payload: weight 4 c_T Omega(u)^2)"}
                if opts.hover_command is not None
                else {}
            ),
            "pilot": "sim.controller.CascadedController outer loops (250 Hz) on the true state; sticks by the inverse "
            f"of the firmware's {opts.rates.rates_type} rate curve",
        }
    )
    meta.update(dict(fw_meta or {}))
    return FwFlightLog(
        t_s=t_all,
        omega_true_rad_s=sd_log[:, s_g : s_g + 3].copy(),
        f_S_m_s2=sd_log[:, s_a : s_a + 3].copy(),
        q_WB_wxyz=sd_log[:, s_q : s_q + 4].copy(),
        q_sp_wxyz=qsp,
        pos_W_m=sd_log[:, s_p : s_p + 3].copy(),
        vel_W_m_s=sd_log[:, s_v : s_v + 3].copy(),
        gyro_meas_rad_s=gyro_log,
        fw_gyro_rad_s=fwg,
        fw_dterm_rad_s=fwd if have_dterm else None,
        fw_pid_d=fwp if have_dterm else None,
        fw_setpoint_rad_s=fws if have_dterm else None,
        motors=mot,
        rotor_speed_rad_s=rot,
        rate_sp_rad_s=rsp,
        sticks_us=stk,
        temp_c=temp,
        manoeuvres=pulses,
        meta=meta,
        wall_s=wall,
    )


def to_recording(log: FwFlightLog):
    """The flight as a DESIGN.md data file (:class:`gyrocore.recording.Recording`): the synthetic
    gyro, the truth in ``ref_*``, specific force, temperature, and the firmware's view."""
    from gyrocore.data.recording import Recording

    extra = {}
    for i, a in enumerate("xyz"):
        extra[f"fw_gyro_{a}_rad_s"] = log.fw_gyro_rad_s[:, i]
    if log.fw_dterm_rad_s is not None:
        for i, a in enumerate("xyz"):
            extra[f"fw_dterm_{a}_rad_s"] = log.fw_dterm_rad_s[:, i]
        for i, a in enumerate(("roll", "pitch", "yaw")):
            extra[f"fw_pid_d_{a}"] = log.fw_pid_d[:, i]
        for i, a in enumerate("xyz"):
            extra[f"fw_setpoint_{a}_rad_s"] = log.fw_setpoint_rad_s[:, i]
    for j in range(4):
        extra[f"motor_{j + 1}"] = log.motors[:, j]
    for j in range(4):
        extra[f"rotor_{j + 1}_rad_s"] = log.rotor_speed_rad_s[:, j]
    for i, a in enumerate("xyz"):
        extra[f"rate_sp_{a}_rad_s"] = log.rate_sp_rad_s[:, i]
    for i, a in enumerate("wxyz"):
        extra[f"att_sp_q{a}"] = log.q_sp_wxyz[:, i]
    for i, a in enumerate(("throttle", "roll", "pitch", "yaw")):
        extra[f"rc_{a}_us"] = log.sticks_us[:, i]
    for i, a in enumerate("xyz"):
        extra[f"pos_{a}_m"] = log.pos_W_m[:, i]
    meta = dict(log.meta)
    meta["columns_firmware"] = (
        "fw_gyro_*_rad_s: the firmware's filtered gyro (PID input), S; fw_dterm_*_rad_s: the gyro "
        "after its D-term filters (D input), S; fw_pid_d_*: its D term (1000 = full motor range); "
        "fw_setpoint_*_rad_s: its rate set point, S; motor_1..4: outputs 0-1 "
        "(motor_order); rotor_1..4_rad_s: true rotor speeds, same order; rate_sp_*: the pilot's "
        "body rate set point; att_sp_q*: its attitude set point; rc_*_us: sticks sent"
    )
    return Recording(
        t_s=log.t_s,
        gyro_rad_s=log.gyro_meas_rad_s,
        accel_m_s2=log.f_S_m_s2,
        temp_c=log.temp_c,
        ref_rate_rad_s=log.omega_true_rad_s,
        ref_quat_wxyz=log.q_WB_wxyz,
        meta=meta,
        extra=extra,
    )
