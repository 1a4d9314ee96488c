"""Closed-loop hover flight of the MuJoCo quadrotor, with the simulated gyro in the rate loop.

Per physics step (``physics_rate_hz``):

1. the rotor aerodynamics are set from the rotors' ACTUAL state: thrust ``c_T Omega^2 (1 +
   r cos(2 phi + psi_b))`` (axial blade-pass ripple at twice the rotor frequency) and the 2nd
   imbalance harmonic ``h2 u Omega^2`` (in the rotor plane, turning at 2 Omega); the 1st harmonic is
   the eccentric mass on each rotor (``models/quadrotor.xml``), i.e. pure MuJoCo dynamics;
2. ``mj_step``. Its ``sensordata`` is the state at the START of the step (see
   :mod:`sim.turntable`), so it is logged as sample ``k`` at ``t_k``.

Per gyro sample (every ``m`` physics steps, ``m`` = nearest integer ratio, >= 1; physics is
stepped at ``m`` x the gyro rate): the truth at ``t_k`` goes to ``gyro.step`` (the synthetic
MEMS gyro, or :class:`PerfectGyro`), its output through ``pipeline.step`` (calibration + filter),
into the :class:`sim.controller.CascadedController`, whose rotor speed commands apply from the
next physics step: one physics step of computation delay (1 ms at 1 kHz), as on a flight
controller that runs the loop right after the gyro sample. The attitude/position loops run at
250 Hz (:class:`sim.controller.CascadedController`), the rate loop on every gyro sample.

Speed: with :class:`PerfectGyro` or a :class:`sim.gyro.GyroStream`, everything but ``mj_step`` runs in compiled kernels (:mod:`sim._fast`, numba):
one call per physics step, two around a Python ``pipeline``. They transcribe the Python loop
below operation by operation and give the same flight bit for bit (``tests/sim/test_hover.py``);
``compiled=False`` (:class:`HoverFlight`, :func:`fly_hover`) runs the Python loop (the reference).
"""

from __future__ import annotations

import array
import inspect
import math
from dataclasses import dataclass
from math import cos, sin
from typing import Iterator, Protocol, Sequence

import mujoco
import numpy as np
from scipy import signal

from gyrocore.errors import GyroInputError

from .controller import CascadedController, ControllerGains, Manoeuvre
from .paths import QUADROTOR_XML, model_path
from .thermal import TemperatureChunks, ThermalSpec, ThermalState, simulate_temperature
from .truth import Truth
from .turntable import physics_steps_per_sample
from .vehicles import VibrationSpec

__all__ = [
    "GyroLike",
    "PerfectGyro",
    "FlightLog",
    "HoverFlight",
    "fly_hover",
    "load_quadrotor_model",
    "hover_bare_step_rate",
    "rotor_forces",
    "quat_angle_rad",
    "AttitudeLog",
    "tilt_rad",
    "QUICK_HOVER_S",
    "TAKEOFF_CLIMB_S",
]

#: A quick hover length for tests and smoke runs, s (2 s settling + 8 s of steady hover).
QUICK_HOVER_S = 10.0

#: With a ground phase (``fly_hover(ground_s > 0)``): after arming, the height set point ramps
#: from the ground to the 1-m hover height in this time, s (0.85 m, raised cosine: peak 0.45 m/s).
TAKEOFF_CLIMB_S = 3.0

_IMBALANCE_RADIUS_M = 0.01  # radius of the eccentric masses in models/quadrotor.xml


class GyroLike(Protocol):
    """What ``fly_hover`` needs of a gyro: ``sim.gyro.SyntheticGyro(...).stream(n)`` has it."""

    def step(self, k: int, t_s: float, omega_S: np.ndarray, f_S: np.ndarray, temp_c: float) -> np.ndarray: ...


class PerfectGyro:
    """A gyro without errors: returns the true rate (same protocol as the synthetic gyro stream)."""

    def step(
        self,
        k: int,
        t_s: float,
        omega_S: np.ndarray,
        f_S: np.ndarray,
        temp_c: float,
        q_SW_wxyz: np.ndarray | None = None,
    ) -> np.ndarray:
        """The true rate ``omega_S`` itself (fly_hover passes a view it keeps; no copy needed)."""
        return omega_S


NO_VIBRATION = VibrationSpec(imbalance_kg_m=0.0, harmonic2_ratio=0.0, blade_pass_ripple=0.0)


def quat_angle_rad(q_a_wxyz: np.ndarray, q_b_wxyz: np.ndarray) -> np.ndarray:
    """Angle between two attitude series, rad, shape (N,): 2·arccos|q_a·q_b| (q and −q the same).

    The flights' scores (hover and tracking error, the excess against a perfect-gyro flight) use
    this one formula."""
    d = np.abs(np.einsum("ij,ij->i", q_a_wxyz, q_b_wxyz))
    return 2.0 * np.arccos(np.clip(d, 0.0, 1.0))


def tilt_rad(q_WB_wxyz: np.ndarray) -> np.ndarray:
    """Tilt of the body z axis from the vertical, rad, shape (N,)."""
    q = q_WB_wxyz
    r33 = 1.0 - 2.0 * (q[:, 1] ** 2 + q[:, 2] ** 2)
    return np.arccos(np.clip(r33, -1.0, 1.0))


class AttitudeLog:
    """What every flight log (:class:`FlightLog`, :class:`sim.fw_flight.FwFlightLog`) says about its
    attitude: the sample rate and, from ``q_WB_wxyz`` and ``q_sp_wxyz``, the attitude error and tilt."""

    @property
    def rate_hz(self) -> float:
        return float(1.0 / (self.t_s[1] - self.t_s[0]))

    def attitude_error_rad(self) -> np.ndarray:
        """Angle between true and commanded attitude, rad, shape (N,)."""
        return quat_angle_rad(self.q_WB_wxyz, self.q_sp_wxyz)

    def tilt_rad(self) -> np.ndarray:
        """Tilt of the body z axis from the vertical, rad, shape (N,)."""
        return tilt_rad(self.q_WB_wxyz)


@dataclass(frozen=True, eq=False)
class FlightLog(AttitudeLog):
    """What the flight did, at the gyro sample times.

    Parameters
    ----------
    t_s : ndarray (N,)
        Time, s.
    q_WB_wxyz : ndarray (N, 4)
        True attitude, body to world.
    q_sp_wxyz : ndarray (N, 4)
        Commanded attitude (set point).
    pos_W_m, vel_W_m_s : ndarray (N, 3)
        True position and velocity, world.
    pos_sp_W_m : ndarray (3,)
        Position set point.
    rate_sp_rad_s : ndarray (N, 3)
        Rate set point from the attitude loop, body.
    omega_true_rad_s : ndarray (N, 3)
        True body rate (= Truth.omega_S_rad_s; S = B).
    gyro_meas_rad_s : ndarray (N, 3)
        The gyro as measured (output of ``gyro.step``).
    gyro_filt_rad_s : ndarray (N, 3)
        After the pipeline: what the rate loop used.
    motor_thrust_cmd_n : ndarray (N, 4)
        Rotor thrust commands from the mixer, N.
    rotor_speed_rad_s : ndarray (N, 4)
        Actual rotor speeds (signed), rad/s.
    meta : dict
    """

    t_s: np.ndarray
    q_WB_wxyz: np.ndarray
    q_sp_wxyz: np.ndarray
    pos_W_m: np.ndarray
    vel_W_m_s: np.ndarray
    pos_sp_W_m: np.ndarray
    rate_sp_rad_s: np.ndarray
    omega_true_rad_s: np.ndarray
    gyro_meas_rad_s: np.ndarray
    gyro_filt_rad_s: np.ndarray
    motor_thrust_cmd_n: np.ndarray
    rotor_speed_rad_s: np.ndarray
    meta: dict

    def altitude_error_m(self) -> np.ndarray:
        """Height minus the set point, m, shape (N,)."""
        return self.pos_W_m[:, 2] - self.pos_sp_W_m[2]

    def motor_noise_n(self, *, highpass_hz: float = 20.0, t_from_s: float = 0.0) -> float:
        """RMS of the motor thrust commands above ``highpass_hz`` (mean over motors), N.

        The control action itself lives below a few Hz; what is above ``highpass_hz`` is gyro
        noise and vibration passed to the motors (4th-order Butterworth, zero-phase).
        """
        sos = signal.butter(4, highpass_hz, btype="highpass", fs=self.rate_hz, output="sos")
        x = self.motor_thrust_cmd_n[self.t_s >= t_from_s]
        hp = signal.sosfiltfilt(sos, x, axis=0)
        return float(np.sqrt(np.mean(hp**2)))

    def gyro_delay_s(self, *, band_hz: tuple[float, float] = (0.2, 15.0)) -> float:
        """Delay of the filtered gyro behind the true rate in the flight band, s.

        Both are band-passed (zero-phase) to ``band_hz`` and the lag of the cross-correlation
        peak is refined by a parabola through the three best lags.
        """
        fs = self.rate_hz
        sos = signal.butter(2, band_hz, btype="bandpass", fs=fs, output="sos")
        # axes concatenated with a gap of zeros so no lag mixes two axes
        pad = np.zeros((int(0.1 * fs) + 1, 3))
        a = np.vstack([signal.sosfiltfilt(sos, self.omega_true_rad_s, axis=0), pad]).ravel(order="F")
        b = np.vstack([signal.sosfiltfilt(sos, self.gyro_filt_rad_s, axis=0), pad]).ravel(order="F")
        max_lag = int(0.1 * fs)
        # c[l] = sum_n a[n] b[n + l] (b lags a by l samples), over the three axes
        full = signal.correlate(b, a, mode="full", method="fft")  # lag l at index l + n - 1
        mid = a.size - 1
        lags = np.arange(-max_lag, max_lag + 1)
        c = full[mid - max_lag : mid + max_lag + 1]
        i = int(np.argmax(c))
        frac = 0.0
        if 0 < i < c.size - 1:
            den = c[i - 1] - 2 * c[i] + c[i + 1]
            frac = 0.5 * (c[i - 1] - c[i + 1]) / den if den != 0 else 0.0
        return float((lags[i] + frac) / fs)


def load_quadrotor_model(
    timestep_s: float = 1e-3, *, model_xml: str = QUADROTOR_XML
) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """Compile ``models/<model_xml>`` (default the F450, ``quadrotor.xml``) with the given physics step (s)."""
    model = mujoco.MjModel.from_xml_path(str(model_path(model_xml)))
    model.opt.timestep = timestep_s
    return model, mujoco.MjData(model)


def hover_bare_step_rate(n_steps: int = 20_000) -> float:
    """Simulated seconds per wall second of a bare ``mj_step`` loop on the quadrotor (benchmark)."""
    import time

    model, data = load_quadrotor_model()
    mujoco.mj_resetDataKeyframe(model, data, 0)
    step = mujoco.mj_step
    t0 = time.perf_counter()
    for _ in range(n_steps):
        step(model, data)
    return n_steps * model.opt.timestep / (time.perf_counter() - t0)


def _compiled_path(gyro, n: int, compiled: bool = True) -> bool:
    """Whether :mod:`sim._fast` flies this flight: asked for (``compiled``) and covered
    (PerfectGyro or a fresh, long enough GyroStream; other gyro objects run the Python loop)."""
    if not compiled:
        return False
    try:
        import numba  # noqa: F401
    except ImportError:  # the Python loop gives the same flight, only slower
        return False
    if type(gyro) is PerfectGyro:
        return True
    from .gyro import GyroStream

    # registry family terms: the kernels add those of time alone from a table; others fly the Python loop
    return type(gyro) is GyroStream and gyro._k_next == 0 and gyro.n >= n and gyro.families_time_only


def _fly_compiled(model, data, *, kern, gyro_view, filt, k0: int, k1: int, n: int, m_per: int, bar) -> None:
    """Samples ``k0 … k1 − 1`` of the closed loop, one compiled call per physics step (two around
    a Python pipeline), into the arrays of ``kern``'s current block (:meth:`sim._fast.Kernel.set_block`).

    Same sequence as the Python loop of :class:`HoverFlight`: forces from the rotor state + held
    motor commands, ``mj_step``, log/gyro/controller at the gyro sample, motor commands for the
    next physics step. ``gyro_view`` (block rows, read-only) is the synthetic gyro's output the
    pipeline reads (None: the true rate from the sensor log).
    """
    from . import _fast

    A, W = kern.A, kern.W
    step = mujoco.mj_step
    aero = _fast.aero
    if k0 == 0:
        aero(A, W)  # the first step's forces (later ones are set at the end of each sample)
    extra = range(m_per - 1)
    if filt is None and bar is None and m_per == 1:
        after = _fast.after_step
        for k in range(k0, k1):
            step(model, data)
            after(k, A, W)
        return
    after, gyro_k, control = _fast.after_step, _fast.log_and_gyro, _fast.control
    nd = np.ndarray
    s_g = int(A[_fast.A_SGYRO])
    sd_log = kern._block[2]
    for k in range(k0, k1):
        step(model, data)
        if filt is None:
            after(k, A, W)
        else:
            gyro_k(k, A, W)
            g = gyro_view[k - k0] if gyro_view is not None else sd_log[k - k0, s_g : s_g + 3]
            y = filt(g)
            yl = y.tolist() if type(y) is nd else [float(v) for v in y]
            control(k, A, W, yl[0], yl[1], yl[2])
        for _ in extra:
            step(model, data)
            aero(A, W)
        if bar is not None and (k & 1023) == 0:
            bar.update(min(1024, n - bar.n))


def _set_couple_imbalance(model, hub_moment_kg_m2: float, ss: np.random.SeedSequence, model_xml: str) -> None:
    """Masses of the couple-imbalance pairs (:attr:`VibrationSpec.hub_moment_kg_m2`), each pair turned
    to a seeded phase on its rotor (a 4th child of the flight's SeedSequence, so the other phases are
    unchanged). The model's ``rotor_i_couple_a`` sits at (r, 0, +h) on the rotor, ``_b`` at (−r, 0, −h):
    mass m each gives the couple 2 m r h Omega² and no net force."""
    ids = [
        (
            mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"rotor_{i}_couple_a"),
            mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"rotor_{i}_couple_b"),
        )
        for i in range(1, 5)
    ]
    if any(a < 0 or b < 0 for a, b in ids):
        if hub_moment_kg_m2 > 0:
            raise GyroInputError(
                f"{model_xml} has no couple-imbalance bodies (rotor_i_couple_a/b): hub_moment_kg_m2 needs them"
            )
        return
    (theta,) = (np.random.default_rng(s).uniform(0.0, 2 * math.pi, 4) for s in ss.spawn(1))
    for (a, b), th in zip(ids, theta):
        x, y, h = (float(v) for v in model.body_pos[a])
        r = math.hypot(x, y)
        m = hub_moment_kg_m2 / (2.0 * r * h)
        model.body_pos[a] = (r * math.cos(th), r * math.sin(th), h)
        model.body_pos[b] = (-r * math.cos(th), -r * math.sin(th), -h)
        model.body_mass[a] = m
        model.body_mass[b] = m


def rotor_forces(phi: list, om: list, rotor_k) -> tuple:
    """Rotor forces from the rotors' state: thrust_1..4 then vib2_i_x, vib2_i_y (the model's
    first 12 actuators), for the current rotor angles ``phi`` (rad) and speeds ``om`` (rad/s).

    Thrust c_T w^2 (1 + r cos(2 phi + psi_b)) (blade-pass ripple); the 2nd-harmonic force
    h2 u w^2 at angle phi + psi_h in the rotor frame, i.e. turning at 2 Omega in the body frame.
    ``rotor_k``: per rotor (c_T, r cos psi_b, r sin psi_b, h2 u cos psi_h, h2 u sin psi_h)
    (:attr:`HoverFlight.rotor_k`). Unrolled over the four rotors (this runs every physics step;
    the compiled kernel ``sim._fast.aero`` is the same arithmetic).
    """
    (k_0, k_1, k_2, k_3) = rotor_k
    p0, p1, p2, p3 = phi
    w0, w1, w2, w3 = om
    c0 = cos(p0)
    s0 = sin(p0)
    c1 = cos(p1)
    s1 = sin(p1)  # noqa: E702
    c2 = cos(p2)
    s2 = sin(p2)
    c3 = cos(p3)
    s3 = sin(p3)  # noqa: E702
    q0 = w0 * w0
    q1 = w1 * w1
    q2 = w2 * w2
    q3 = w3 * w3  # noqa: E702
    return (
        k_0[0] * q0 * (1.0 + k_0[1] * (c0 * c0 - s0 * s0) - k_0[2] * 2.0 * s0 * c0),
        k_1[0] * q1 * (1.0 + k_1[1] * (c1 * c1 - s1 * s1) - k_1[2] * 2.0 * s1 * c1),
        k_2[0] * q2 * (1.0 + k_2[1] * (c2 * c2 - s2 * s2) - k_2[2] * 2.0 * s2 * c2),
        k_3[0] * q3 * (1.0 + k_3[1] * (c3 * c3 - s3 * s3) - k_3[2] * 2.0 * s3 * c3),
        q0 * (c0 * k_0[3] - s0 * k_0[4]),
        q0 * (s0 * k_0[3] + c0 * k_0[4]),
        q1 * (c1 * k_1[3] - s1 * k_1[4]),
        q1 * (s1 * k_1[3] + c1 * k_1[4]),
        q2 * (c2 * k_2[3] - s2 * k_2[4]),
        q2 * (s2 * k_2[3] + c2 * k_2[4]),
        q3 * (c3 * k_3[3] - s3 * k_3[4]),
        q3 * (s3 * k_3[3] + c3 * k_3[4]),
    )


class HoverFlight:
    """A closed-loop hover flight, flown block by block in bounded memory.

    The flight: hover at 1 m (plus manoeuvres) for ``duration_s``. With ``ground_s > 0`` it
    starts on the ground (keyframe ``ground``: resting on its four feet on the floor, contact on,
    rotors stopped): the gyro is powered up from t = 0 and sees a still IMU (specific force =
    gravity only, rate = contact micro-motion, < 2e-6 rad/s) while the controller is disarmed
    (thrusts 0) until ``ground_s``; then it arms, the rotors spool up and the height set point
    ramps to 1 m over :data:`TAKEOFF_CLIMB_S`; manoeuvres are flown at their own times
    (schedule them after take-off). :func:`fly_hover` returns it whole.

    The constructor sets the flight up (model, vibration, controller, gyro, thermal model);
    :meth:`blocks` flies it, yielding consecutive pieces ``(Truth, FlightLog)`` of at most
    ``block_samples`` gyro samples. Everything that evolves — the MuJoCo state, the controller
    (integrators, set points, derivative memory, the outer-loop log row a block starts inside),
    the held motor commands, the die temperature, the gyro stream (noise generators, low-pass
    and delay memory, dT/dt) — is carried from block to block, and nothing indexes the whole
    flight, so the pieces concatenated are the whole flight bit for bit whatever the block size
    (tested, compiled and Python paths). A :class:`sim.gyro.SyntheticGyro` given as ``gyro`` is
    opened as a block stream (``stream(n, blocks=True)``: noise generated block by block); a
    :class:`sim.gyro.GyroStream` opened whole is used as it is (its arrays hold the flight).

    Parameters
    ----------
    duration_s : float
        Flight time, s.
    gyro : object with ``.step(k, t_s, omega_S (3,), f_S (3,), temp_c) -> (3,)``, optional
        The simulated gyro in the loop (``sim.gyro.SyntheticGyro(...).stream(n)``, or the
        ``SyntheticGyro`` itself: its stream is then opened here over the flight's time base
        and temperature); default :class:`PerfectGyro`. Called once per gyro sample, k = 0, 1, ...
    pipeline : object with ``.step(x (3,)) -> (3,)`` or a callable, optional
        Calibration + filter between the gyro and the rate loop (e.g.
        ``gyrocore.flight.filters.Pipeline``); None = the raw gyro.
    manoeuvres : sequence of Manoeuvre
        Attitude steps on top of hover (see :func:`sim.controller.small_steps`).
    vibration : bool or VibrationSpec
        True = the vehicle class's default vibration (the F450's: :class:`VibrationSpec`
        defaults), False = none.
    physics_rate_hz, gyro_rate_hz : float
        Requested physics rate (default: the vehicle class's, 1 kHz for the F450) and gyro
        output rate, Hz; physics runs at the nearest integer multiple (>= 1) of the gyro rate
        (see the module docstring).
    thermal : ThermalSpec, optional
        Die temperature; with ``motor_c_per_w`` the rotor power ``c_M Omega^3`` heats it.
        Default constant 25 °C.
    seed : int
        Seeds the rotor phases (imbalance, harmonic and blade-pass phases).
    progress : bool
        tqdm progress bar.
    gains : ControllerGains, optional
    ground_s : float
        Time on the ground before take-off, s (0 <= ground_s < duration_s); default 0: the
        flight starts airborne, in hover (keyframe ``hover``).
    vehicle : str or sim.vehicles.VehicleClass
        Airframe (:data:`sim.vehicles.VEHICLES`: ``f450``, ``racing5``): its model, controller
        constants, gains (unless ``gains`` is given) and default vibration.
    gyro_blocks : bool
        Open a ``SyntheticGyro`` given as ``gyro`` as a block stream (default; False: one
        whole-flight stream).
    compiled : bool
        Fly with the compiled per-step kernels (:mod:`sim._fast`) where they cover the flight
        (default); False: the Python reference loop (the same flight bit for bit, slower).

    Attributes
    ----------
    n : int
        Gyro samples of the flight.
    meta : dict
        The flight's metadata (:attr:`sim.truth.Truth.meta`).
    gyro : object
        The gyro flown (the stream opened here for a ``SyntheticGyro``).
    """

    def __init__(
        self,
        *,
        duration_s: float,
        gyro: GyroLike | None = None,
        pipeline=None,
        manoeuvres: Sequence[Manoeuvre] = (),
        vibration: bool | VibrationSpec = True,
        physics_rate_hz: float | None = None,
        gyro_rate_hz: float = 1000.0,
        thermal: ThermalSpec | None = None,
        seed: int = 0,
        progress: bool = False,
        gains: ControllerGains | None = None,
        ground_s: float = 0.0,
        vehicle: str | object = "f450",
        gyro_blocks: bool = True,
        compiled: bool = True,
    ) -> None:
        if not (duration_s > 0 and math.isfinite(duration_s)):
            raise GyroInputError(f"duration_s must be > 0, got {duration_s}")
        if not (math.isfinite(ground_s) and 0.0 <= ground_s < duration_s):
            raise GyroInputError(f"ground_s must be >= 0 and shorter than the flight, got {ground_s}")
        from .vehicles import get_vehicle

        veh = get_vehicle(vehicle)
        vib = veh.vibration if vibration is True else (NO_VIBRATION if vibration is False else vibration)
        if not isinstance(vib, VibrationSpec):
            raise GyroInputError("vibration must be True, False or a VibrationSpec")
        if physics_rate_hz is None:
            physics_rate_hz = veh.physics_rate_hz
        m_per = physics_steps_per_sample(gyro_rate_hz, physics_rate_hz)
        phys_hz = gyro_rate_hz * m_per
        dt = 1.0 / phys_hz
        self.dt_c = 1.0 / gyro_rate_hz
        n = int(math.floor(duration_s * gyro_rate_hz + 1e-9))
        if n < 2:
            raise GyroInputError("flight shorter than two gyro samples")
        self.n, self.m_per = n, m_per

        model, data = load_quadrotor_model(dt, model_xml=veh.model_xml)
        self.model, self.data = model, data
        qp = veh.params
        gains = gains or veh.gains
        # --- vibration set-up: imbalance masses, phases -------------------------------------------
        for i in range(1, 5):
            bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"rotor_{i}_imbalance")
            model.body_mass[bid] = vib.imbalance_kg_m / _IMBALANCE_RADIUS_M
        ss = np.random.SeedSequence(seed)
        rng_rotor, rng_h2, rng_bp = (np.random.default_rng(s) for s in ss.spawn(3))
        _set_couple_imbalance(model, vib.hub_moment_kg_m2, ss, veh.model_xml)
        mujoco.mj_setConst(model, data)
        phi0 = rng_rotor.uniform(0.0, 2 * math.pi, 4)
        psi_h2 = rng_h2.uniform(0.0, 2 * math.pi, 4)
        psi_bp = rng_bp.uniform(0.0, 2 * math.pi, 4)
        key_hover = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "hover")
        if ground_s > 0.0:
            # on the floor: contact on (the feet and the ground plane are the only colliding geoms)
            model.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
            mujoco.mj_resetDataKeyframe(model, data, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "ground"))
        else:
            mujoco.mj_resetDataKeyframe(model, data, key_hover)
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "rotor_1_spin")
        rq0, rv0 = int(model.jnt_qposadr[jid]), int(model.jnt_dofadr[jid])
        self.rq0, self.rv0 = rq0, rv0
        data.qpos[rq0 : rq0 + 4] = phi0
        mujoco.mj_forward(model, data)
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, i) for i in range(model.nu)]
        expect = (
            [f"thrust_{i}" for i in range(1, 5)]
            + [f"vib2_{i}_{a}" for i in range(1, 5) for a in "xy"]
            + [f"motor_{i}" for i in range(1, 5)]
        )
        if names != expect:
            raise GyroInputError("quadrotor.xml actuator order changed (thrust_1..4, vib2_*_x/y, motor_1..4)")

        def sens(name: str) -> int:
            return int(model.sensor_adr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name)])

        self.sens = {
            k: sens(x)
            for k, x in (
                ("gyro", "imu_gyro"),
                ("acc", "imu_accel"),
                ("quat", "imu_quat"),
                ("pos", "body_pos"),
                ("vel", "body_linvel"),
            )
        }
        self.nsd = model.nsensordata

        # --- per-step constants (Python floats: cheaper than numpy for 4 rotors) ----------------
        ct = qp.c_t_n_per_rad2_s2
        r_bp = vib.blade_pass_ripple
        h2u = vib.harmonic2_ratio * vib.imbalance_kg_m
        # per rotor: c_T, ripple*cos(psi_b), ripple*sin(psi_b), h2*u*cos(psi_h), h2*u*sin(psi_h)
        self.rotor_k = tuple(
            (ct, r_bp * math.cos(pb), r_bp * math.sin(pb), h2u * math.cos(ph), h2u * math.sin(ph))
            for pb, ph in zip(psi_bp, psi_h2)
        )
        self.ct, self.spin, self.ff, self.kappa = ct, qp.spin, qp.kappa_m / qp.motor_kv_n_m_s, qp.kappa_m

        # --- gyro, pipeline, thermal, controller ----------------------------------------------------
        gyro = gyro if gyro is not None else PerfectGyro()
        if pipeline is None:
            filt = None
        elif hasattr(pipeline, "step"):
            filt = pipeline.step
            # an RPM filter in the pipeline follows the simulator's rotor speeds (as Betaflight's from eRPM)
            rpm_cbs = [
                s.set_rotor_hz
                for s in ([pipeline] + list(getattr(pipeline, "stages", ())))
                if callable(getattr(s, "set_rotor_hz", None))
            ]
            if rpm_cbs:
                inner = filt
                qv = data.qvel
                two_pi = 2.0 * math.pi

                def filt(g, _inner=inner, _cbs=tuple(rpm_cbs)):
                    hz = [abs(w) / two_pi for w in qv[rv0 : rv0 + 4].tolist()]  # rotor speeds after this physics step
                    for cb in _cbs:
                        cb(hz)
                    return _inner(g)
        elif callable(pipeline):
            filt = pipeline
        else:
            raise GyroInputError("pipeline must have .step(x) or be callable")
        self.filt = filt
        th_spec = thermal if thermal is not None else ThermalSpec.constant(25.0)
        self.th_spec = th_spec
        self.stream_thermal = th_spec.heater is not None or th_spec.motor_c_per_w != 0.0
        if self.stream_thermal:
            self.th_state = ThermalState.start(th_spec, 0.0)
            self._temp_chunks = None
        else:
            self.th_state = None
            self._temp_chunks = TemperatureChunks(th_spec, n_total=n)

        if not hasattr(gyro, "step") and hasattr(gyro, "stream"):
            # a sim.gyro.SyntheticGyro: open its per-sample stream over this flight's time base
            if gyro_blocks:
                gyro = gyro.stream(n, blocks=True, thermal=None if self.stream_thermal else th_spec)
            else:  # the whole-flight stream (fly_hover in one block: whole-flight arrays)
                t_all = self._times(0, n)
                gyro = gyro.stream(
                    n, t_s=t_all, temp_c=None if self.stream_thermal else simulate_temperature(t_all, th_spec)
                )
        if not hasattr(gyro, "step"):
            raise GyroInputError("gyro must have .step(k, t_s, omega_S, f_S, temp_c) (or .stream(n))")
        self.gyro = gyro
        from .gyro import GyroStream

        self._gstream = gyro if type(gyro) is GyroStream else None
        # gyros that model the earth rate need the attitude: pass it when step() takes it
        try:
            self.pass_q = "q_SW_wxyz" in inspect.signature(gyro.step).parameters
        except (TypeError, ValueError):
            self.pass_q = False
        s_pos = self.sens["pos"]
        if ground_s > 0.0:
            ctl = CascadedController(
                qp,
                gains,
                dt_s=self.dt_c,
                pos_sp_W_m=tuple(model.key_qpos[key_hover, 0:3].tolist()),
                yaw_sp_rad=0.0,
                manoeuvres=manoeuvres,
                arm_at_s=float(ground_s),
                climb_s=TAKEOFF_CLIMB_S,
                z_start_m=float(data.sensordata[s_pos + 2]),
            )
        else:
            ctl = CascadedController(
                qp, gains, dt_s=self.dt_c, pos_sp_W_m=tuple(data.qpos[0:3]), yaw_sp_rad=0.0, manoeuvres=manoeuvres
            )
        self.ctl = ctl
        self.outer_every = ctl.outer_every
        self.progress = progress
        self.mot_cmd = tuple(data.ctrl[12:16].tolist())  # the keyframe's motor commands until the first update
        self.fast = _compiled_path(gyro, n, compiled)
        self.kern = None
        if self.fast:
            from . import _fast

            self.kern = _fast.build(
                data=data,
                rq0=rq0,
                rv0=rv0,
                sens=self.sens,
                rotor_k=self.rotor_k,
                spin=self.spin,
                ff=self.ff,
                ct=ct,
                ctl=ctl,
                n=n,
                t_power_up_s=float(self._times(0, 1)[0]),
                stream=self._gstream,
                thermal=self.th_state,
                kappa_ct=self.kappa * ct,
            )
        self.meta = {
            "model": veh.model_xml,
            "vehicle": veh.name,
            "runner": "sim.quadrotor.fly_hover",
            "physics_rate_hz": f"{phys_hz:.10g}",
            "gyro_rate_hz": f"{gyro_rate_hz:.10g}",
            "seed": str(seed),
            "vibration": f"imbalance_kg_m={vib.imbalance_kg_m:g},harmonic2_ratio={vib.harmonic2_ratio:g},blade_pass_ripple={vib.blade_pass_ripple:g}"
            + (f",hub_moment_kg_m2={vib.hub_moment_kg_m2:g}" if vib.hub_moment_kg_m2 > 0 else ""),
            "manoeuvres": str(len(tuple(manoeuvres))),
            "gyro": type(gyro).__name__,
            "pipeline": type(pipeline).__name__ if pipeline is not None else "none",
        }
        if ground_s > 0.0:
            self.meta["ground_s"] = f"{ground_s:.10g}"
            self.meta["takeoff_climb_s"] = f"{TAKEOFF_CLIMB_S:.10g}"
        self._outer_last = None  # the outer-log row the next block may start inside
        self._k = 0  # next sample to fly
        self._started = False

    def _times(self, k0: int, k1: int) -> np.ndarray:
        """Gyro sample times t_k = k · dt, s, for k0 ≤ k < k1 (the elements of ``np.arange(n) * dt``)."""
        return np.arange(k0, k1) * self.dt_c

    def blocks(
        self, block_samples: int | None = None, *, flight_log: bool = True
    ) -> Iterator[tuple[Truth, FlightLog | None]]:
        """Fly the flight; yield ``(Truth, FlightLog)`` for each block of at most ``block_samples``
        consecutive gyro samples (default: the whole flight in one block). Runs once.

        ``flight_log=False`` yields ``(Truth, None)`` (the log's 17 columns are not built).
        Memory: one block of logs (the sensor state, 14 + 7 log columns, the gyro's noise and
        output: ≈ 0.4 kB per sample), whatever the flight's length.
        """
        if self._started:
            raise GyroInputError("a HoverFlight flies once")
        self._started = True
        n = self.n
        b = n if block_samples is None else int(block_samples)
        if b < 1:
            raise GyroInputError(f"block_samples must be >= 1, got {block_samples}")
        bar = None
        if self.progress:
            from tqdm import tqdm

            bar = tqdm(total=n, unit="sample", desc="hover", leave=False, mininterval=0.5)
        try:
            for k0 in range(0, n, b):
                yield self._block(k0, min(n, k0 + b), bar, flight_log)
        finally:
            if bar is not None:
                bar.close()

    def _block(self, k0: int, k1: int, bar, flight_log: bool = True) -> tuple[Truth, FlightLog | None]:
        """Fly samples k0 … k1 − 1 (the next ones) and return their truth and log."""
        if k0 != self._k:
            raise GyroInputError(f"HoverFlight: block from {k0}, expected {self._k}")
        m = k1 - k0
        n, oe = self.n, self.outer_every
        t_b = self._times(k0, k1 + 1)  # the block's times and the next sample's (thermal step to k + 1)
        amb = self.th_spec.ambient_at(t_b) if self.stream_thermal else None
        temp = np.empty(m) if self.stream_thermal else self._temp_chunks.take(t_b[:m])
        sd_log = np.empty((m, self.nsd))
        outer_log = np.empty(((k1 - 1) // oe - k0 // oe + 1, 7))  # q_sp (4), rate_sp (3) from the row of k0
        if k0 % oe:
            outer_log[0] = self._outer_last  # begun in the previous block, rewritten at its next update
        st = self._gstream
        if st is not None and st.blocked:
            st.next_block(m)
        if self.fast:
            gout = noise = tr = fam = gview = None
            if st is not None:
                j0 = k0 - st.block_start
                gout, gview = st.gyro_rad_s[j0 : j0 + m], st._view[j0 : j0 + m]
                noise = np.ascontiguousarray(st.noise_rad_s[j0 : j0 + m], dtype=np.float64)
                tr = None if st._tr is None else st._tr[j0 : j0 + m]
                if st._fam:
                    from . import _fast

                    fam = np.ascontiguousarray(st.family_table(t_b[:m], float(self.kern.W[_fast.W_T_PU])))
            rec = np.empty((m, 14))
            self.kern.set_block(
                k0,
                t_s=t_b,
                temp_c=temp,
                sd_log=sd_log,
                outer_log=outer_log,
                rec=rec,
                ambient_c=amb,
                gyro_out=gout,
                noise=noise,
                temp_rate=tr,
                family=fam,
            )
            _fly_compiled(
                self.model,
                self.data,
                kern=self.kern,
                gyro_view=gview,
                filt=self.filt,
                k0=k0,
                k1=k1,
                n=n,
                m_per=self.m_per,
                bar=bar,
            )
            if st is not None:
                from . import _fast

                # leave the stream as its own step() would have: samples up to k1 taken
                W = self.kern.W
                st._k_next = k1
                if st._t_pu is None:
                    st._t_pu = float(self._times(0, 1)[0])
                if st._lp is not None:
                    st._lp_state[:] = W[_fast.W_LPZ : _fast.W_LPZ + 6].tolist()
        else:
            rec = self._fly_python(k0, k1, t_b, temp, amb, sd_log, outer_log, bar)
        self._outer_last = outer_log[-1].copy()
        self._k = k1
        return self._pieces(k0, k1, t_b[:m], temp, sd_log, outer_log, rec, flight_log)

    def _fly_python(self, k0, k1, t_b, temp, amb, sd_log, outer_log, bar) -> np.ndarray:
        """The Python reference loop over samples k0 … k1 − 1 (operation for operation what the
        compiled kernels do); returns the per-sample record (m, 14)."""
        model, data, ctl, n = self.model, self.data, self.ctl, self.n
        qpos, qvel, ctrl, sensordata = data.qpos, data.qvel, data.ctrl, data.sensordata
        rq0, rv0 = self.rq0, self.rv0
        rq1, rv1 = rq0 + 4, rv0 + 4
        step = mujoco.mj_step
        sqrt = math.sqrt
        rotor_k = self.rotor_k

        def rotor_aero(om: list) -> tuple:
            """Rotor forces from the rotors' state now (:func:`rotor_forces`)."""
            return rotor_forces(qpos[rq0:rq1].tolist(), om, rotor_k)

        s = self.sens
        s_gyro, s_acc, s_q, s_pos, s_vel = s["gyro"], s["acc"], s["quat"], s["pos"], s["vel"]
        sg1, sa1, sq1, sp1, sv1 = s_gyro + 3, s_acc + 3, s_q + 4, s_pos + 3, s_vel + 3
        gstep, filt, pass_q = self.gyro.step, self.filt, self.pass_q
        update_rate = ctl.update_rate
        outer_every = self.outer_every
        r0 = k0 // outer_every
        nd = np.ndarray
        extra_steps = range(self.m_per - 1)
        stream_thermal, th_state, kappa, ct = self.stream_thermal, self.th_state, self.kappa, self.ct
        spin, ff = self.spin, self.ff
        t_l = t_b.tolist()
        amb_l = amb.tolist() if stream_thermal else None
        temp_l = None if stream_thermal else temp.tolist()
        rec_arr = array.array("d")  # per sample: gyro meas (3), gyro filtered (3), thrust cmd (4), rotor speed (4)
        rec_extend = rec_arr.extend
        mot_cmd = self.mot_cmd
        for k in range(k0, k1):
            j = k - k0
            om = qvel[rv0:rv1].tolist()
            ctrl[:] = rotor_aero(om) + mot_cmd
            step(model, data)
            row = sd_log[j]
            row[:] = sensordata  # the state at t_k (start of this step)
            if stream_thermal:
                tc = th_state.temp_c
                temp[j] = tc
            else:
                tc = temp_l[j]
            tk = t_l[j]
            if pass_q:
                g = gstep(k, tk, row[s_gyro:sg1], row[s_acc:sa1], tc, q_SW_wxyz=row[s_q:sq1])
            else:
                g = gstep(k, tk, row[s_gyro:sg1], row[s_acc:sa1], tc)
            y = filt(g) if filt is not None else g
            if k % outer_every == 0:
                rl = row.tolist()
                ctl.update_outer(tk, rl[s_pos:sp1], rl[s_vel:sv1], rl[s_q:sq1])
                outer_log[k // outer_every - r0] = ctl.q_sp + ctl.rate_sp
            gl = g.tolist() if type(g) is nd else [float(v) for v in g]
            yl = y.tolist() if type(y) is nd else [float(v) for v in y]
            thrust = update_rate(yl[0], yl[1], yl[2])
            rec_extend(gl + yl + thrust + om)
            mot_cmd = tuple([sp * (sqrt(t / ct) + ff * t) for sp, t in zip(spin, thrust)])
            if stream_thermal and k + 1 < n:
                p_w = kappa * ct * sum(abs(w) ** 3 for w in om)
                th_state.step(t_l[j + 1], motor_power_w=p_w, ambient_c=amb_l[j + 1])
            for _ in extra_steps:
                ctrl[:] = rotor_aero(qvel[rv0:rv1].tolist()) + mot_cmd
                step(model, data)
            if bar is not None and (k & 1023) == 0:
                bar.update(min(1024, n - bar.n))
        self.mot_cmd = mot_cmd
        return np.frombuffer(rec_arr, dtype=np.float64).reshape(k1 - k0, 14).copy()

    def _pieces(self, k0, k1, t_s, temp, sd_log, outer_log, rec, flight_log=True) -> tuple[Truth, FlightLog | None]:
        m = k1 - k0
        s = self.sens
        oe = self.outer_every
        idx_outer = np.arange(k0, k1) // oe - k0 // oe
        s_gyro, s_acc, s_q, s_pos, s_vel = s["gyro"], s["acc"], s["quat"], s["pos"], s["vel"]
        omega = sd_log[:, s_gyro : s_gyro + 3].copy()
        truth = Truth(
            t_s=t_s,
            omega_S_rad_s=omega,
            f_S_m_s2=sd_log[:, s_acc : s_acc + 3].copy(),
            q_SW_wxyz=sd_log[:, s_q : s_q + 4].copy(),
            temp_c=temp,
            t_since_power_up_s=t_s.copy(),
            power_up_index=np.zeros(m, dtype=int),
            meta=dict(self.meta),
        )
        if not flight_log:
            return truth, None
        log = FlightLog(
            t_s=t_s,
            q_WB_wxyz=sd_log[:, s_q : s_q + 4].copy(),
            q_sp_wxyz=outer_log[idx_outer, 0:4],
            pos_W_m=sd_log[:, s_pos : s_pos + 3].copy(),
            vel_W_m_s=sd_log[:, s_vel : s_vel + 3].copy(),
            pos_sp_W_m=np.array(self.ctl.pos_sp),
            rate_sp_rad_s=outer_log[idx_outer, 4:7],
            omega_true_rad_s=omega,
            gyro_meas_rad_s=rec[:, 0:3],
            gyro_filt_rad_s=rec[:, 3:6],
            motor_thrust_cmd_n=rec[:, 6:10],
            rotor_speed_rad_s=rec[:, 10:14],
            meta=dict(self.meta),
        )
        return truth, log


def _concat_flight(pieces: list[tuple[Truth, FlightLog]]) -> tuple[Truth, FlightLog]:
    """One (Truth, FlightLog) from consecutive blocks (the flight's omega shared by both, as flown whole)."""
    if len(pieces) == 1:
        return pieces[0]
    ts, ls = [p[0] for p in pieces], [p[1] for p in pieces]

    def cat(objs, name):
        return np.concatenate([getattr(o, name) for o in objs])

    t_s = cat(ts, "t_s")
    omega = cat(ts, "omega_S_rad_s")
    truth = Truth(
        t_s=t_s,
        omega_S_rad_s=omega,
        f_S_m_s2=cat(ts, "f_S_m_s2"),
        q_SW_wxyz=cat(ts, "q_SW_wxyz"),
        temp_c=cat(ts, "temp_c"),
        t_since_power_up_s=cat(ts, "t_since_power_up_s"),
        power_up_index=cat(ts, "power_up_index"),
        meta=ts[0].meta,
    )
    log = FlightLog(
        t_s=t_s,
        omega_true_rad_s=omega,
        pos_sp_W_m=ls[-1].pos_sp_W_m,
        meta=ls[0].meta,
        **{
            f: cat(ls, f)
            for f in (
                "q_WB_wxyz",
                "q_sp_wxyz",
                "pos_W_m",
                "vel_W_m_s",
                "rate_sp_rad_s",
                "gyro_meas_rad_s",
                "gyro_filt_rad_s",
                "motor_thrust_cmd_n",
                "rotor_speed_rad_s",
            )
        },
    )
    return truth, log


def fly_hover(*, block_samples: int | None = None, **options) -> tuple[Truth, FlightLog]:
    """Fly the quadrotor in closed loop: hover at 1 m (plus manoeuvres) for ``duration_s``.

    ``options`` are :class:`HoverFlight`'s (``duration_s``, ``gyro``, ``pipeline``,
    ``manoeuvres``, ``vibration``, ``physics_rate_hz``, ``gyro_rate_hz``, ``thermal``, ``seed``,
    ``progress``, ``gains``, ``ground_s``, ``vehicle``, ``compiled``: see there); the whole flight is returned.

    Parameters
    ----------
    block_samples : int, optional
        Fly in blocks of this many gyro samples (:meth:`HoverFlight.blocks`) and concatenate:
        the same flight bit for bit (a ``SyntheticGyro`` then draws its noise block by block).
        Default: one block. For bounded memory iterate :meth:`HoverFlight.blocks` instead.

    Returns
    -------
    (Truth, FlightLog)
        Truth at the gyro samples (rate of S in S, specific force in S, attitude S->W,
        temperature, ...) and the flight log.
    """
    flight = HoverFlight(gyro_blocks=block_samples is not None, **options)
    return _concat_flight(list(flight.blocks(block_samples)))
