"""Single-axis rate table in MuJoCo: the truth for rotation and static calibration.

The table (``models/turntable.xml``) turns about the world vertical; the IMU fixture on it is
mounted with one sensor axis up or down (``"+x" ... "-z"``) or at any tilt quaternion. A
:class:`TableProfile` is a list of :class:`TableSegment` (mount, table rate, duration, ramps);
between segments with different mounts the fixture turns to the new mount about one axis
(a smooth rotation of ``repose_s`` then ``settle_s`` at rest) — a real motion, in the truth.

Timing. After ``mj_step`` MuJoCo's ``sensordata`` holds the sensors evaluated in that step's
forward pass, i.e. at the state at the START of the step. The runner (via
:func:`mujoco.rollout.rollout`, which has the same semantics as ``mj_step``) therefore labels the
sensordata of physics step ``i`` with ``t_i = i * dt`` — gyro, accelerometer and attitude all
come from the same forward pass at ``t_i``. The gyro samples at its own rate: physics runs at
the integer multiple ``m`` of the gyro rate nearest the requested physics rate (at least 1x;
e.g. gyro 8 kHz with physics 1 kHz requested -> physics at 8 kHz), and gyro sample ``k`` is the
state at physics step ``k*m`` exactly (no interpolation). The realised physics rate is in
``Truth.meta["physics_rate_hz"]``.

Exactness. The table servo is an integrated-velocity servo: its activation integrates the
commanded rate, so with the per-step command ``(theta(t_{i+1}) - theta(t_i)) / dt`` the activation
equals the commanded angle ``theta(t_i)`` to rounding, and the PD loop settles the hinge on it.
MuJoCo's semi-implicit Euler advances the attitude with the new velocity, so the quaternion
finite difference over ``[t_i, t_{i+1}]`` equals the rate at ``t_{i+1}``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Sequence

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout
from scipy.spatial.transform import Rotation

from gyrocore.errors import GyroInputError

from .paths import TURNTABLE_XML, model_path
from .thermal import TemperatureChunks, ThermalSpec
from .truth import Truth

__all__ = [
    "MOUNTS",
    "mount_quat_wxyz",
    "TableSegment",
    "TableProfile",
    "TableRun",
    "table_profile_static",
    "table_profile_turns",
    "table_profile_quick",
    "run_table",
    "run_table_detailed",
    "stream_table",
    "TableStream",
    "load_table_model",
    "physics_steps_per_sample",
]

_HALF_PI = 0.5 * math.pi
# Rotation table -> sensor mount (rotation vector in the table frame T, z up), chosen so that
# the named sensor axis points up: e.g. "+x": R_y(-pi/2) maps S x onto T z.
_MOUNT_ROTVEC = {
    "+z": (0.0, 0.0, 0.0),
    "-z": (math.pi, 0.0, 0.0),
    "+x": (0.0, -_HALF_PI, 0.0),
    "-x": (0.0, _HALF_PI, 0.0),
    "+y": (_HALF_PI, 0.0, 0.0),
    "-y": (-_HALF_PI, 0.0, 0.0),
}
MOUNTS: tuple[str, ...] = ("+x", "-x", "+y", "-y", "+z", "-z")

Mount = str | tuple[float, float, float, float]


def _wxyz_to_rot(q: Sequence[float]) -> Rotation:
    return Rotation.from_quat([q[1], q[2], q[3], q[0]])


def _rot_to_wxyz(r: Rotation) -> np.ndarray:
    x, y, z, w = r.as_quat()
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


def mount_quat_wxyz(mount: Mount) -> np.ndarray:
    """Quaternion (w, x, y, z) of the sensor frame S in the table-top frame T.

    Parameters
    ----------
    mount : str or 4-tuple
        One of :data:`MOUNTS` (which sensor axis points up), or a unit quaternion (w, x, y, z)
        rotating S to T (arbitrary tilt; normalised here).
    """
    if isinstance(mount, str):
        if mount not in _MOUNT_ROTVEC:
            raise GyroInputError(f"unknown mount {mount!r}; use one of {', '.join(MOUNTS)} or a quaternion")
        return _rot_to_wxyz(Rotation.from_rotvec(_MOUNT_ROTVEC[mount]))
    q = np.asarray(mount, dtype=float)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-9:
        raise GyroInputError(f"mount quaternion must be 4 finite numbers (w,x,y,z), got {mount!r}")
    return q / np.linalg.norm(q)


def _mount_label(mount: Mount) -> str:
    if isinstance(mount, str):
        return mount
    return "q(" + ",".join(f"{v:.6g}" for v in mount_quat_wxyz(mount)) + ")"


@dataclass(frozen=True)
class TableSegment:
    """One segment of a table run: a mount held while the table turns (or rests).

    Parameters
    ----------
    mount : str or tuple
        Mount of the IMU fixture (see :func:`mount_quat_wxyz`).
    rate_rad_s : float
        Table rate during the hold, rad/s about world +z (sign = direction); 0 = at rest.
    duration_s : float
        Duration, s, ramps included. The table starts and ends the segment at rest.
    ramp_s : float
        Duration of each of the acceleration and deceleration ramps, s. The ramps are
        raised-cosine in rate (continuous acceleration); each contributes ``rate*ramp_s/2``,
        so the commanded angle is ``rate * (duration_s - ramp_s)``.
    """

    mount: Mount
    rate_rad_s: float = 0.0
    duration_s: float = 1.0
    ramp_s: float = 0.5

    def __post_init__(self) -> None:
        mount_quat_wxyz(self.mount)  # validates
        if isinstance(self.mount, (list, np.ndarray)):
            object.__setattr__(self, "mount", tuple(float(v) for v in self.mount))
        if not (self.duration_s > 0 and math.isfinite(self.duration_s)):
            raise GyroInputError(f"segment duration must be > 0 s, got {self.duration_s}")
        if not math.isfinite(self.rate_rad_s):
            raise GyroInputError("segment rate must be finite")
        if self.rate_rad_s != 0.0 and not (0 < self.ramp_s and 2 * self.ramp_s <= self.duration_s):
            raise GyroInputError(
                f"segment needs 0 < ramp_s <= duration_s/2 (ramp {self.ramp_s} s, duration {self.duration_s} s)"
            )

    @property
    def angle_rad(self) -> float:
        """Commanded table angle over the segment, rad (signed)."""
        if self.rate_rad_s == 0.0:
            return 0.0
        return self.rate_rad_s * (self.duration_s - self.ramp_s)

    def theta_rad(self, tau_s: np.ndarray) -> np.ndarray:
        """Commanded table angle at segment time ``tau_s`` (s, clipped to the segment), rad."""
        tau = np.clip(np.asarray(tau_s, dtype=float), 0.0, self.duration_s)
        r, ta, T = self.rate_rad_s, self.ramp_s, self.duration_s
        if r == 0.0:
            return np.zeros_like(tau)

        def ramp_area(x: np.ndarray) -> np.ndarray:  # integral of (1-cos(pi x/ta))/2 from 0 to x
            return 0.5 * x - ta / (2 * math.pi) * np.sin(math.pi * x / ta)

        up = ramp_area(np.minimum(tau, ta))
        hold = np.clip(tau - ta, 0.0, T - 2 * ta)
        x_dn = np.clip(tau - (T - ta), 0.0, ta)
        down = x_dn - ramp_area(x_dn)  # integral of (1+cos(pi x/ta))/2
        return r * (up + hold + down)


@dataclass(frozen=True)
class TableProfile:
    """A table run: segments, plus how the fixture moves between mounts.

    Parameters
    ----------
    segments : tuple of TableSegment
    repose_s : float
        Duration of the fixture's rotation to a new mount, s (raised-cosine rate profile).
    settle_s : float
        Rest after a re-pose before the next segment starts, s.
    """

    segments: tuple[TableSegment, ...]
    repose_s: float = 2.0
    settle_s: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "segments", tuple(self.segments))
        if not self.segments:
            raise GyroInputError("a table profile needs at least one segment")
        if self.repose_s <= 0 or self.settle_s < 0:
            raise GyroInputError("table profile needs repose_s > 0 and settle_s >= 0")

    @property
    def duration_s(self) -> float:
        """Total duration including re-poses, s (before rounding to physics steps)."""
        total = 0.0
        prev = None
        for seg in self.segments:
            q = mount_quat_wxyz(seg.mount)
            if prev is not None and not _same_rotation(prev, q):
                total += self.repose_s + self.settle_s
            total += seg.duration_s
            prev = q
        return total


def _same_rotation(q1: np.ndarray, q2: np.ndarray) -> bool:
    return abs(float(np.dot(q1, q2))) > 1.0 - 1e-15


def table_profile_static(mount: Mount = "+z", duration_s: float = 60.0) -> TableProfile:
    """The IMU at rest on the table in one mount for ``duration_s`` seconds."""
    return TableProfile(segments=(TableSegment(mount=mount, rate_rad_s=0.0, duration_s=duration_s),))


def table_profile_turns(
    *,
    mounts: Sequence[Mount] = MOUNTS,
    revolutions: float = 5.0,
    rates_rad_s: Sequence[float] = (math.radians(90.0),),
    directions: Sequence[int] = (+1, -1),
    rest_s: float = 2.0,
    ramp_s: float = 0.5,
    repose_s: float = 2.0,
    settle_s: float = 1.0,
) -> TableProfile:
    """Each mount in turn: ``revolutions`` turns at each rate, in each direction, rests between.

    The article's "rotate each axis 5 turns" generalised: for every mount, a rest of
    ``rest_s`` (static reference), then for every rate and direction one segment turning exactly
    ``revolutions * 2*pi`` rad followed by ``rest_s`` at rest.

    Parameters
    ----------
    mounts : sequence of str or quaternion
        Mounts (default all six axis-up/down positions).
    revolutions : float
        Turns per segment.
    rates_rad_s : sequence of float
        Hold rates, rad/s (> 0).
    directions : sequence of int
        +1 (counter-clockwise about world z) and/or -1.
    rest_s, ramp_s, repose_s, settle_s : float
        Rest between segments, ramp duration, fixture re-pose and settle durations, s.
    """
    if revolutions <= 0 or not rates_rad_s or any(r <= 0 for r in rates_rad_s):
        raise GyroInputError("table_profile_turns needs revolutions > 0 and rates > 0 rad/s")
    if any(d not in (1, -1) for d in directions) or not directions:
        raise GyroInputError("directions must be +1 and/or -1")
    if rest_s <= 0:
        raise GyroInputError("rest_s must be > 0 s")
    angle = 2.0 * math.pi * revolutions
    segs: list[TableSegment] = []
    for mount in mounts:
        segs.append(TableSegment(mount=mount, rate_rad_s=0.0, duration_s=rest_s))
        for rate in rates_rad_s:
            ramp = min(ramp_s, 0.5 * angle / rate)
            for d in directions:
                segs.append(TableSegment(mount=mount, rate_rad_s=d * rate, duration_s=angle / rate + ramp, ramp_s=ramp))
                segs.append(TableSegment(mount=mount, rate_rad_s=0.0, duration_s=rest_s))
    return TableProfile(segments=tuple(segs), repose_s=repose_s, settle_s=settle_s)


def table_profile_quick() -> TableProfile:
    """A short profile for tests and smoke runs (~14 s): mounts +z and -x, one turn each way at
    180 deg/s, 1 s rests, one re-pose."""
    return table_profile_turns(mounts=("+z", "-x"), revolutions=1.0, rates_rad_s=(math.pi,), rest_s=1.0)


@dataclass(frozen=True, eq=False)
class TableRun:
    """A table run with its bookkeeping.

    Parameters
    ----------
    truth : Truth
        Truth at the gyro sample times.
    phases : tuple of dict
        One entry per phase in time order: ``kind`` ("segment" or "repose"), ``t_start_s``,
        ``t_end_s`` (commanded motion ends; the servo settles after), ``mount`` label,
        ``rate_rad_s``, ``angle_rad`` (commanded table angle for segments, fixture angle for re-poses),
        ``axis_S`` for re-poses (unit rotation axis in S).
    table_angle_rad : ndarray, shape (N,)
        Table hinge angle at the gyro samples (unwrapped), rad.
    """

    truth: Truth
    phases: tuple[dict, ...]
    table_angle_rad: np.ndarray


def physics_steps_per_sample(gyro_rate_hz: float, physics_rate_hz: float) -> int:
    """Physics steps per gyro sample: the integer multiple nearest the requested ratio, >= 1."""
    if not (gyro_rate_hz > 0 and physics_rate_hz > 0):
        raise GyroInputError("gyro and physics rates must be > 0 Hz")
    return max(1, int(round(physics_rate_hz / gyro_rate_hz)))


def load_table_model(timestep_s: float = 1e-3) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """Compile ``models/turntable.xml`` with the given physics step (s)."""
    model = mujoco.MjModel.from_xml_path(str(model_path(TURNTABLE_XML)))
    model.opt.timestep = timestep_s
    return model, mujoco.MjData(model)


def _raised_cosine_angle(tau: np.ndarray, duration: float, angle: float) -> np.ndarray:
    """Angle reached at time tau of a raised-cosine rate profile moving ``angle`` in ``duration``."""
    x = np.clip(tau, 0.0, duration) / duration
    return angle * (x - np.sin(2 * math.pi * x) / (2 * math.pi))


class TableStream:
    """A table run delivered in chunks of gyro samples (bounded memory; :func:`stream_table`).

    Attributes
    ----------
    n_samples : int
        Gyro samples of the whole run.
    phases : tuple of dict
        The phase bookkeeping (see :class:`TableRun`), known before the run.
    meta : dict
        The truth metadata (see :func:`run_table`).
    physics_rate_hz : float

    :meth:`chunks` runs the physics once (the model is stepped in place) and yields
    ``(Truth, table_angle_rad)`` pieces in time order; their concatenation equals
    :func:`run_table_detailed` bit for bit, whatever ``chunk_steps`` (``mujoco.rollout`` from the
    full physics state is exact across cuts; tested).
    """

    def __init__(
        self,
        profile: TableProfile,
        *,
        gyro_rate_hz: float,
        physics_rate_hz: float,
        thermal: ThermalSpec | None,
        seed: int,
        progress: bool,
        chunk_steps: int,
    ) -> None:
        if int(chunk_steps) < 1:
            raise GyroInputError("chunk_steps must be >= 1")
        self.profile = profile
        self.gyro_rate_hz = float(gyro_rate_hz)
        self.m_per = physics_steps_per_sample(gyro_rate_hz, physics_rate_hz)
        self.physics_rate_hz = phys_hz = gyro_rate_hz * self.m_per
        self.dt = dt = 1.0 / phys_hz
        self.thermal = thermal if thermal is not None else ThermalSpec.constant(25.0)
        self.progress = progress
        self.chunk_steps = int(chunk_steps)
        self.model, self.data = model, _data = load_table_model(dt)
        self._ids = {
            "fixture": mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "fixture"),
            "repose": mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "fixture_repose"),
            "act_fix": mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, "fixture_servo"),
            "act_table": mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, "table_servo"),
        }

        def sens_slice(name: str) -> slice:
            sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name)
            a = model.sensor_adr[sid]
            return slice(a, a + model.sensor_dim[sid])

        self._sens = tuple(sens_slice(n) for n in ("imu_gyro", "imu_accel", "imu_quat", "table_angle"))
        # ---- the phases (their controls are built chunk by chunk in chunks())
        phases: list[dict] = []
        plan: list[tuple] = []  # kind, nsteps, angle function of the step time, repose axis
        step0 = 0
        q_cur = mount_quat_wxyz(profile.segments[0].mount)
        for seg in profile.segments:
            q_new = mount_quat_wxyz(seg.mount)
            if not _same_rotation(q_cur, q_new):
                r_rel = _wxyz_to_rot(q_cur).inv() * _wxyz_to_rot(q_new)  # rotation in the fixture frame
                rotvec = r_rel.as_rotvec()
                ang = float(np.linalg.norm(rotvec))
                axis = rotvec / ang
                n = int(math.ceil((profile.repose_s + profile.settle_s) * phys_hz - 1e-9))
                plan.append(("repose", n, (lambda tk, _a=ang: _raised_cosine_angle(tk, profile.repose_s, _a)), axis))
                phases.append(
                    {
                        "kind": "repose",
                        "t_start_s": step0 * dt,
                        "t_end_s": step0 * dt + profile.repose_s,
                        "mount": _mount_label(seg.mount),
                        "rate_rad_s": 0.0,
                        "angle_rad": ang,
                        "axis_S": [float(v) for v in axis],
                    }
                )
                step0 += n
                q_cur = q_new
            n = int(math.ceil(seg.duration_s * phys_hz - 1e-9))
            plan.append(("segment", n, seg.theta_rad, None))
            phases.append(
                {
                    "kind": "segment",
                    "t_start_s": step0 * dt,
                    "t_end_s": step0 * dt + seg.duration_s,
                    "mount": _mount_label(seg.mount),
                    "rate_rad_s": float(seg.rate_rad_s),
                    "angle_rad": float(seg.angle_rad),
                }
            )
            step0 += n
        self._plan = plan
        self.phases = tuple(phases)
        self.total_steps = step0
        self.n_samples = step0 // self.m_per
        if self.n_samples < 1:
            raise GyroInputError("table profile shorter than one gyro sample")
        self.meta = {
            "model": TURNTABLE_XML,
            "runner": "sim.turntable.run_table",
            "physics_rate_hz": f"{phys_hz:.10g}",
            "gyro_rate_hz": f"{gyro_rate_hz:.10g}",
            "seed": str(seed),
            "table_phases": json.dumps(phases, separators=(",", ":")),
        }
        self._used = False

    def chunks(self):
        """Run the physics; yield ``(Truth, table_angle_rad)`` pieces of at most ``chunk_steps`` physics steps."""
        if self._used:
            raise GyroInputError("a TableStream runs once")
        self._used = True
        model, data, ids, dt, m_per = self.model, self.data, self._ids, self.dt, self.m_per
        s_gyro, s_acc, s_quat, s_ang = self._sens
        fixture_id, repose_jid = ids["fixture"], ids["repose"]
        q_adr_fix = model.jnt_qposadr[repose_jid]
        act_fix = ids["act_fix"]
        model.body_quat[fixture_id] = mount_quat_wxyz(self.profile.segments[0].mount)
        mujoco.mj_resetData(model, data)
        mujoco.mj_forward(model, data)
        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        state = np.empty(mujoco.mj_stateSize(model, spec))
        mujoco.mj_getState(model, data, state, spec)
        temp = TemperatureChunks(self.thermal, n_total=self.n_samples)
        n_samples = self.n_samples
        bar = None
        if self.progress:
            from tqdm import tqdm

            bar = tqdm(total=self.total_steps * dt, unit="sim-s", desc="rate table", leave=False)
        step = 0
        try:
            for kind, n, angle, axis in self._plan:
                act = act_fix if kind == "repose" else ids["act_table"]
                if kind == "repose":
                    # Bake the fixture hinge's current angle into the fixture mount, then point the hinge
                    # along the new re-pose axis (pose and servo error unchanged; hinge at rest).
                    mujoco.mj_setState(model, data, state, spec)
                    phi = float(data.qpos[q_adr_fix])
                    r_mount = _wxyz_to_rot(model.body_quat[fixture_id]) * Rotation.from_rotvec(
                        phi * model.jnt_axis[repose_jid]
                    )
                    model.body_quat[fixture_id] = _rot_to_wxyz(r_mount)
                    data.qpos[q_adr_fix] = 0.0
                    data.act[act_fix] -= phi
                    model.jnt_axis[repose_jid] = axis
                    mujoco.mj_forward(model, data)
                    mujoco.mj_getState(model, data, state, spec)
                for c0 in range(0, n, self.chunk_steps):
                    c1 = min(n, c0 + self.chunk_steps)
                    # the per-step command: the same elementwise arithmetic as on the whole phase
                    tk = np.arange(c0, c1 + 1) * dt
                    ctrl = np.zeros((c1 - c0, model.nu))
                    ctrl[:, act] = np.diff(angle(tk)) / dt
                    st, sd = mj_rollout.rollout(model, data, state, ctrl)
                    st, sd = st[0], sd[0]
                    state = st[-1].copy()
                    del st
                    # global step indices step+c0 .. step+c1-1; keep those that are multiples of m_per
                    first = (-(step + c0)) % m_per
                    rows = sd[first::m_per]
                    k0 = (step + c0 + first) // m_per
                    k1 = min(n_samples, k0 + rows.shape[0])
                    rows = rows[: k1 - k0]
                    if bar is not None:
                        bar.update((c1 - c0) * dt)
                    if k1 <= k0:
                        continue
                    t_s = np.arange(k0, k1) / self.gyro_rate_hz
                    truth = Truth(
                        t_s=t_s,
                        omega_S_rad_s=np.ascontiguousarray(rows[:, s_gyro]),
                        f_S_m_s2=np.ascontiguousarray(rows[:, s_acc]),
                        q_SW_wxyz=np.ascontiguousarray(rows[:, s_quat]),
                        temp_c=temp.take(t_s),
                        t_since_power_up_s=t_s.copy(),
                        power_up_index=np.zeros(k1 - k0, dtype=int),
                        meta=self.meta,
                    )
                    yield truth, np.ascontiguousarray(rows[:, s_ang]).ravel()
                step += n
        finally:
            if bar is not None:
                bar.close()


def stream_table(
    profile: TableProfile,
    *,
    gyro_rate_hz: float,
    physics_rate_hz: float = 1000.0,
    thermal: ThermalSpec | None = None,
    seed: int = 0,
    progress: bool = False,
    chunk_steps: int = 65_536,
) -> TableStream:
    """The table run of :func:`run_table` as a :class:`TableStream` (chunks of at most
    ``chunk_steps`` physics steps; bit-identical to the whole run)."""
    return TableStream(
        profile,
        gyro_rate_hz=gyro_rate_hz,
        physics_rate_hz=physics_rate_hz,
        thermal=thermal,
        seed=seed,
        progress=progress,
        chunk_steps=chunk_steps,
    )


def run_table_detailed(
    profile: TableProfile,
    *,
    gyro_rate_hz: float,
    physics_rate_hz: float = 1000.0,
    thermal: ThermalSpec | None = None,
    seed: int = 0,
    progress: bool = False,
    chunk_steps: int = 200_000,
) -> TableRun:
    """Run a table profile; see :func:`run_table` (this also returns the phase bookkeeping)."""
    ts = stream_table(
        profile,
        gyro_rate_hz=gyro_rate_hz,
        physics_rate_hz=physics_rate_hz,
        thermal=thermal,
        seed=seed,
        progress=progress,
        chunk_steps=chunk_steps,
    )
    n_samples = ts.n_samples
    omega = np.empty((n_samples, 3))
    f_S = np.empty((n_samples, 3))
    quat = np.empty((n_samples, 4))
    temp_c = np.empty(n_samples)
    table_ang = np.empty(n_samples)
    k = 0
    for tr, ang in ts.chunks():
        k1 = k + tr.n
        omega[k:k1] = tr.omega_S_rad_s
        f_S[k:k1] = tr.f_S_m_s2
        quat[k:k1] = tr.q_SW_wxyz
        temp_c[k:k1] = tr.temp_c
        table_ang[k:k1] = ang
        k = k1
    t_s = np.arange(n_samples) / gyro_rate_hz
    truth = Truth(
        t_s=t_s,
        omega_S_rad_s=omega,
        f_S_m_s2=f_S,
        q_SW_wxyz=quat,
        temp_c=temp_c,
        t_since_power_up_s=t_s.copy(),
        power_up_index=np.zeros(n_samples, dtype=int),
        meta=ts.meta,
    )
    return TableRun(truth=truth, phases=ts.phases, table_angle_rad=table_ang)


def run_table(
    profile: TableProfile,
    *,
    gyro_rate_hz: float,
    physics_rate_hz: float = 1000.0,
    thermal: ThermalSpec | None = None,
    seed: int = 0,
    progress: bool = False,
) -> Truth:
    """Run the rate table through ``profile`` and return the truth at the gyro sample times.

    Parameters
    ----------
    profile : TableProfile
        Segments (mount, rate, duration, ramps) and re-pose timing.
    gyro_rate_hz : float
        Gyro output rate, Hz (100 Hz - 8 kHz typical).
    physics_rate_hz : float
        Requested physics rate, Hz; the realised rate is the nearest integer multiple of the
        gyro rate (>= 1x), see the module docstring.
    thermal : ThermalSpec, optional
        Die temperature model (no motor heating on the table); default constant 25 °C.
    seed : int
        Recorded in ``meta``; the table run itself is deterministic (nothing random in it).
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    Truth
        Rate of S in S (rad/s), specific force in S (m/s²), attitude S->W (w,x,y,z),
        temperature, time since power-up (one power-up). ``meta["table_phases"]`` is a JSON
        list of the phases (start/end times, mount, commanded angle) for rotation calibration.
    """
    return run_table_detailed(
        profile,
        gyro_rate_hz=gyro_rate_hz,
        physics_rate_hz=physics_rate_hz,
        thermal=thermal,
        seed=seed,
        progress=progress,
    ).truth
