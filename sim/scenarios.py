"""Scenarios as data: ``sim/scenarios/<name>.toml`` -> physics truth -> synthetic gyro -> recording.

Each scenario file says what happens to the sensor (rate-table profile or hover flight,
thermal environment, power-ups); :func:`simulate` runs it for one sensor unit and returns a
:class:`SimResult` whose :attr:`SimResult.recording` is the DESIGN.md data file with the
truth in the ``ref_`` columns. Physics comes from the runners of :mod:`sim.turntable`
(:func:`~sim.turntable.run_table`) and :mod:`sim.quadrotor` (:func:`~sim.quadrotor.fly_hover`,
with the gyro in the loop); this module only builds their inputs and does the bookkeeping
(power-up splitting, metadata).

Everything random derives from ``seed`` (and ``run``): the sensor unit's parameters, its
turn-on biases and noise (:class:`sim.gyro.SyntheticGyro`), the bump pattern of
``static_bumped`` and the rotor phases of ``hover``.

Scenario files (see the shipped ones): ``kind`` = ``"table"`` or ``"hover"``, ``duration_s``
(default length; the ``turns`` profile sets its own), optional ``gyro_rate_hz``, and tables
``[table]`` (``profile`` = ``static`` | ``bumped`` | ``turns`` | ``cycle``), ``[bumps]``,
``[power]`` (``cycles``), ``[hover]`` (``vibration``, ``manoeuvres``, ``vehicle``: a class of
:data:`sim.vehicles.VEHICLES`, default ``f450``; ``ground_s``: still on the
ground, gyro on, before the take-off, see :func:`hover_ground_s`) and ``[thermal]``
(:class:`sim.thermal.ThermalSpec` fields; ``ambient_c`` break points or ``ramps`` with
fractions of the duration; optional ``[thermal.heater]``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import Iterable, Mapping

import numpy as np

from gyrocore.data.jsonable import to_jsonable
from gyrocore.effects.registry import canonical_name, resolve, validate_params
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording, concat_recordings

from .gyro import GyroOutput, SyntheticGyro
from .noise import effect_rng
from .presets import load_preset, read_registered_toml
from .truth import Truth
from .controller import small_steps
from .quadrotor import fly_hover, HoverFlight, TAKEOFF_CLIMB_S
from .spec_vibration import spec_injection
from .thermal import ambient_ramps, HeaterSpec, simulate_temperature, TemperatureChunks, ThermalSpec
from .turntable import (
    mount_quat_wxyz,
    run_table,
    stream_table,
    table_profile_static,
    table_profile_turns,
    TableProfile,
    TableSegment,
)
from .vehicles import get_vehicle
from gyrocore.flight.vibration import read_spec

__all__ = [
    "SCENARIOS",
    "SCENARIO_DIR",
    "ScenarioSpec",
    "SimResult",
    "load_scenario",
    "simulate",
    "simulate_stream",
    "SimStream",
    "true_bias_rad_s",
    "floor_gyro",
    "build_table_profile",
    "build_thermal",
    "hover_ground_s",
    "MIN_AIRBORNE_S",
]

SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"
DEG = math.pi / 180.0
_KINDS = ("table", "hover")
_TOP_KEYS = {
    "name",
    "description",
    "kind",
    "duration_s",
    "gyro_rate_hz",
    "table",
    "bumps",
    "power",
    "hover",
    "thermal",
    "vibration",
}


@dataclass(frozen=True)
class ScenarioSpec:
    """A scenario file, parsed (values as in the file; SI units by their names).

    Parameters
    ----------
    name, description : str
    kind : str
        ``"table"`` (rate-table runner) or ``"hover"`` (closed-loop quadrotor).
    duration_s : float or None
        Default duration, s (None: set by the table profile).
    gyro_rate_hz : float or None
        Output rate for this scenario (None: the sensor preset's).
    table, bumps, power, hover, thermal : mapping
        The sections of the file.
    vibration : mapping
        ``[vibration]``: ``spec`` (a vibration spec, ``gyroharness vibration -o``; path relative
        to the TOML), ``band`` (index or ``"middle"``), ``physics`` (hover: the spec's rotor line
        through the vehicle's rotor imbalance): the registry effect ``vibration``
        (:func:`sim.spec_vibration.spec_injection`, as ``simulate --vibration``).
    source : str
        File path.
    """

    name: str
    description: str
    kind: str
    duration_s: float | None
    gyro_rate_hz: float | None
    table: Mapping = field(default_factory=dict)
    bumps: Mapping = field(default_factory=dict)
    power: Mapping = field(default_factory=dict)
    hover: Mapping = field(default_factory=dict)
    thermal: Mapping = field(default_factory=dict)
    source: str = ""
    vibration: Mapping = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class SimResult:
    """One simulated recording and everything true about it.

    Parameters
    ----------
    scenario, sensor : str
    seed, run : int
    recording : gyrocore.data.recording.Recording
        The data file: measured gyro; accel = true specific force (no accelerometer errors
        are simulated); temp = die temperature; ``ref_`` = truth (rate of S in S, attitude
        S→W); extra column ``power_up_index``; ``#`` metadata incl. ``params_true`` (JSON).
    truth : sim.truth.Truth
    params_true : dict
        The unit's true parameters (PARAM_SCHEMA form, SI). ``bias.b_rad_s`` is the bias
        of the first power-up; extras: ``b_mean_rad_s`` (unit mean), ``turn_on_sigma_rad_s``,
        ``b_rad_s_per_power_up`` (P, 3). Stochastic effects carry their levels.
    draws : dict
        What each effect drew (:attr:`sim.gyro.GyroOutput.draws`).
    noise_rad_s : ndarray, shape (N, 3)
        The summed stochastic noise realisation, rad/s.
    flight_log : sim.quadrotor.FlightLog or None
        For ``hover``.
    notes : tuple of str
        Adjustments made (e.g. the DLPF moved below Nyquist, effects the closed loop could
        not carry).
    """

    scenario: str
    sensor: str
    seed: int
    run: int
    recording: Recording
    truth: Truth
    params_true: Mapping
    draws: Mapping
    noise_rad_s: np.ndarray
    flight_log: object | None = None
    notes: tuple[str, ...] = ()


# ---------------------------------------------------------------------------- registry
def _discover() -> Mapping[str, Path]:
    return MappingProxyType({p.stem: p for p in sorted(SCENARIO_DIR.glob("*.toml"))})


#: Registry of the shipped scenarios: name -> TOML path.
SCENARIOS: Mapping[str, Path] = _discover()


def load_scenario(name_or_path: str | Path | ScenarioSpec) -> ScenarioSpec:
    """Parse a scenario by registry name or from a TOML path (one-line errors)."""
    if isinstance(name_or_path, ScenarioSpec):
        return name_or_path
    key = str(name_or_path)
    path, raw = read_registered_toml(key, SCENARIOS, what="scenario", short="scenario")
    unknown = set(raw) - _TOP_KEYS
    if unknown:
        raise GyroInputError(f"scenario {path}: unknown key(s) {', '.join(sorted(unknown))}")
    kind = raw.get("kind", "table")
    if kind not in _KINDS:
        raise GyroInputError(f"scenario {path}: kind must be one of {', '.join(_KINDS)}, got {kind!r}")
    dur = raw.get("duration_s")
    if dur is not None and not (isinstance(dur, (int, float)) and dur > 0):
        raise GyroInputError(f"scenario {path}: duration_s must be > 0")
    rate = raw.get("gyro_rate_hz")
    if rate is not None and not (isinstance(rate, (int, float)) and rate > 0):
        raise GyroInputError(f"scenario {path}: gyro_rate_hz must be > 0")
    table = raw.get("table", {})
    if kind == "table" and table.get("profile") not in ("static", "bumped", "turns", "cycle"):
        raise GyroInputError(f"scenario {path}: [table] profile must be static, bumped, turns or cycle")
    if kind == "table" and table.get("profile") != "turns" and dur is None:
        raise GyroInputError(f"scenario {path}: needs duration_s")
    if kind == "hover" and dur is None:
        raise GyroInputError(f"scenario {path}: needs duration_s")
    veh = raw.get("hover", {}).get("vehicle", "f450")
    if kind == "hover":
        get_vehicle(str(veh))  # an unknown class is one error line at load time
    vsec = raw.get("vibration", {})
    if not isinstance(vsec, Mapping) or set(vsec) - {"spec", "band", "physics"} or ("spec" not in vsec and vsec):
        raise GyroInputError(f'scenario {path}: [vibration] takes spec = "SPEC.json" and optional band, physics')
    if vsec:
        sp = Path(str(vsec["spec"]))
        vsec = dict(vsec, spec=str(sp if sp.is_absolute() else Path(path).resolve().parent / sp))
        if vsec.get("physics") and kind != "hover":
            raise GyroInputError(f'scenario {path}: [vibration] physics = true needs kind = "hover"')
    gs = raw.get("hover", {}).get("ground_s", 0.0)
    if isinstance(gs, bool) or not isinstance(gs, (int, float)) or not (math.isfinite(gs) and gs >= 0):
        raise GyroInputError(f"scenario {path}: [hover] ground_s must be a number >= 0")
    return ScenarioSpec(
        name=str(raw.get("name", path.stem)),
        description=str(raw.get("description", "")),
        kind=kind,
        duration_s=None if dur is None else float(dur),
        gyro_rate_hz=None if rate is None else float(rate),
        table=table,
        bumps=raw.get("bumps", {}),
        power=raw.get("power", {}),
        hover=raw.get("hover", {}),
        thermal=raw.get("thermal", {}),
        source=str(path),
        vibration=vsec,
    )


# ---------------------------------------------------------------------------- builders
def build_thermal(section: Mapping, duration_s: float):
    """:class:`sim.thermal.ThermalSpec` from a ``[thermal]`` section (ramps scale with the duration)."""
    sec = dict(section)
    kw: dict = {}
    for k in ("time_constant_s", "self_heating_c", "motor_c_per_w", "initial_temp_c"):
        if k in sec:
            kw[k] = float(sec.pop(k))
    if "ambient_c" in sec:
        kw["ambient_c"] = tuple((float(t), float(c)) for t, c in sec.pop("ambient_c"))
    if "ramps" in sec:
        r = dict(sec.pop("ramps"))
        try:
            kw["ambient_c"] = ambient_ramps(
                start_c=float(r["start_c"]),
                peak_c=float(r["peak_c"]),
                start_s=float(r["start_frac"]) * duration_s,
                ramp_s=float(r["ramp_frac"]) * duration_s,
                hold_s=float(r.get("hold_frac", 0.0)) * duration_s,
                end_c=None if "end_c" not in r else float(r["end_c"]),
            )
        except KeyError as exc:
            raise GyroInputError(f"[thermal] ramps needs {exc.args[0]}") from None
    if "heater" in sec:
        kw["heater"] = HeaterSpec(**{k: float(v) for k, v in dict(sec.pop("heater")).items()})
    if sec:
        raise GyroInputError(f"[thermal]: unknown key(s) {', '.join(sorted(sec))}")
    return ThermalSpec(**kw)


def _mount(m):
    if isinstance(m, str):
        return m
    if isinstance(m, (list, tuple)) and len(m) == 4:
        return tuple(float(v) for v in m)
    raise GyroInputError(f"mount must be one of +x,-x,+y,-y,+z,-z or a quaternion [w,x,y,z], got {m!r}")


def _segment_from(d: Mapping):
    rate = float(d.get("rate_dps", 0.0)) * DEG
    ramp = float(d.get("ramp_s", 0.5))
    if "revolutions" in d:
        if rate == 0.0:
            raise GyroInputError("a segment with revolutions needs rate_dps != 0")
        dur = float(d["revolutions"]) * 2 * math.pi / abs(rate) + ramp  # angle = rate·(duration − ramp)
    else:
        dur = float(d["duration_s"])
    return TableSegment(mount=_mount(d.get("mount", "+z")), rate_rad_s=rate, duration_s=dur, ramp_s=ramp)


def _turns(t: Mapping, *, revolutions: float, rates, rest_s: float, mounts, repose_s=None, settle_s=None):
    return table_profile_turns(
        mounts=tuple(_mount(m) for m in mounts),
        revolutions=revolutions,
        rates_rad_s=tuple(float(r) * DEG for r in rates),
        directions=tuple(int(d) for d in t.get("directions", (1, -1))),
        rest_s=rest_s,
        ramp_s=float(t.get("ramp_s", 0.5)),
        repose_s=float(t.get("repose_s", 2.0)) if repose_s is None else repose_s,
        settle_s=float(t.get("settle_s", 1.0)) if settle_s is None else settle_s,
    )


def _fit_turns(t: Mapping, duration_s: float | None):
    """The ``turns`` profile, shortened to fit ``duration_s`` if given.

    Reductions in order until one fits: (1) fewer revolutions (down to 1), (2) only the first
    rate, (3) 1-s rests, (4) only the three axis-up mounts (+x, +y, +z: the minimum that
    observes every scale and misalignment), (5) the fastest rate with 0.5-s rests, 1-s
    re-poses and 0.5-s settling, down to a quarter turn. Within the first option that fits,
    the revolutions are the largest multiple of 1/4 turn (at most the file's). Raises if
    even the smallest profile is longer than ``duration_s``.
    """
    mounts = list(t.get("mounts", ("+x", "-x", "+y", "-y", "+z", "-z")))
    rates = list(t.get("rates_dps", (90.0,)))
    rev = float(t.get("revolutions", 5.0))
    rest = float(t.get("rest_s", 2.0))
    full = _turns(t, revolutions=rev, rates=rates, rest_s=rest, mounts=mounts)
    if duration_s is None or full.duration_s <= duration_s:
        return full
    axes = ["+x", "+y", "+z"]
    # (rates, rest, mounts, repose, settle, min revolutions)
    options = [
        (rates, rest, mounts, None, None, 1.0),
        (rates[:1], rest, mounts, None, None, 1.0),
        (rates[:1], min(rest, 1.0), mounts, None, None, 1.0),
        (rates[:1], min(rest, 1.0), axes, None, None, 1.0),
        ([max(rates)], min(rest, 0.5), axes, 1.0, 0.5, 0.25),
    ]

    def prof(r_, rest_, m_, rp, st, n_rev):
        return _turns(t, revolutions=n_rev, rates=r_, rest_s=rest_, mounts=m_, repose_s=rp, settle_s=st)

    for r_, rest_, m_, rp, st, rmin in options:
        low = prof(r_, rest_, m_, rp, st, rmin)
        if low.duration_s <= duration_s:
            quarter = prof(r_, rest_, m_, rp, st, rmin + 0.25).duration_s - low.duration_s
            n_q = int(math.floor((duration_s - low.duration_s) / quarter + 1e-9)) if quarter > 0 else 0
            return prof(r_, rest_, m_, rp, st, min(max(rev, rmin), rmin + 0.25 * n_q))
    small = prof(*options[-1][:5], 0.25)
    raise GyroInputError(
        f"the turntable profile needs at least {small.duration_s:.1f} s (a quarter turn each way about x, y, z); got {duration_s:g} s"
    )


def _bumped(t: Mapping, b: Mapping, duration_s: float, rng: np.random.Generator):
    """Still, a few random handling bumps (table jerks, tilts), then still until the end.

    If the bumps do not leave at least half the run still, fewer bumps are used (at least one).
    """
    from scipy.spatial.transform import Rotation

    base = _mount(t.get("mount", "+z"))
    q_base = mount_quat_wxyz(base)
    start = float(b.get("start_s", 0.3))
    count = int(b.get("count", 5))
    bump_s = float(b.get("duration_s", 0.4))
    max_rate = float(b.get("max_rate_dps", 120.0)) * DEG
    max_tilt = float(b.get("max_tilt_deg", 15.0)) * DEG
    gap = float(b.get("gap_s", 0.3))
    # draw every bump first (the draws do not depend on how many are used)
    draws = [
        (
            rng.uniform(max_rate / 3, max_rate) * rng.choice([-1.0, 1.0]),
            rng.uniform(max_tilt / 3, max_tilt),
            rng.uniform(0, 2 * math.pi),
        )
        for _ in range(max(count, 1))
    ]
    qb = Rotation.from_quat([q_base[1], q_base[2], q_base[3], q_base[0]])

    def segments(k: int) -> list:
        segs = [TableSegment(mount=base, rate_rad_s=0.0, duration_s=start)]
        for i, (r, ang, az) in enumerate(draws[:k]):
            if i % 2 == 0:  # a jerk of the table (yaw), raised-cosine rate
                segs.append(TableSegment(mount=base, rate_rad_s=float(r), duration_s=bump_s, ramp_s=bump_s / 2))
                segs.append(TableSegment(mount=base, rate_rad_s=0.0, duration_s=gap))
            else:  # picked up and tilted about a random horizontal axis, then put back
                tilt = Rotation.from_rotvec(ang * np.array([math.cos(az), math.sin(az), 0.0]))
                x, y, z, w = (tilt * qb).as_quat()
                segs.append(
                    TableSegment(mount=(float(w), float(x), float(y), float(z)), rate_rad_s=0.0, duration_s=gap)
                )
                segs.append(TableSegment(mount=base, rate_rad_s=0.0, duration_s=gap))
        return segs

    k = max(count, 1)
    while True:
        segs = segments(k)
        busy = TableProfile(segments=tuple(segs), repose_s=bump_s, settle_s=0.0).duration_s
        if busy <= 0.5 * duration_s or k == 1:
            break
        k -= 1
    rest = duration_s - busy
    if rest <= 0:
        raise GyroInputError(f"static_bumped needs more than {busy:.1f} s (one bump); got {duration_s:g} s")
    return TableProfile(
        segments=tuple(segs) + (TableSegment(mount=base, rate_rad_s=0.0, duration_s=rest),),
        repose_s=bump_s,
        settle_s=0.0,
    )


def _cycle(t: Mapping, duration_s: float):
    """Repeat the segment pattern while it fits, then stay still until the end."""
    pattern = [_segment_from(d) for d in t.get("segments", ())]
    if not pattern:
        raise GyroInputError("[table] profile = cycle needs [[table.segments]]")
    kw = {"repose_s": float(t.get("repose_s", 2.0)), "settle_s": float(t.get("settle_s", 1.0))}
    segs: list = []
    while True:
        trial = TableProfile(segments=tuple(segs + pattern), **kw)
        if trial.duration_s > duration_s:
            break
        segs += pattern
    if not segs:
        segs = [TableSegment(mount=pattern[0].mount, rate_rad_s=0.0, duration_s=duration_s)]
    rest = duration_s - TableProfile(segments=tuple(segs), **kw).duration_s
    if rest > 1e-9:
        segs.append(TableSegment(mount=segs[-1].mount, rate_rad_s=0.0, duration_s=rest))
    return TableProfile(segments=tuple(segs), **kw)


def build_table_profile(spec: ScenarioSpec, duration_s: float | None, *, seed: int = 0, run: int = 0):
    """The :class:`sim.turntable.TableProfile` of a table scenario."""
    t = spec.table
    prof = t.get("profile")
    if prof == "turns":
        return _fit_turns(t, duration_s)
    assert duration_s is not None
    if prof == "static":
        return table_profile_static(_mount(t.get("mount", "+z")), duration_s)
    if prof == "bumped":
        key = "scenario/bumps" if run == 0 else f"scenario/bumps/run{run}"
        return _bumped(t, spec.bumps, duration_s, effect_rng(seed, key))
    return _cycle(t, duration_s)


def _split_power_ups(truth: Truth, cycles: int, thermal) -> Truth:
    """``cycles`` equal power-ups: index, time since power-up, and a cold die at each start."""
    if cycles < 1:
        raise GyroInputError("[power] cycles must be >= 1")
    n = truth.n
    if n < 2 * cycles:
        raise GyroInputError(f"{cycles} power-ups need at least {2 * cycles} samples")
    idx = (np.arange(n) * cycles) // n
    since = np.empty(n)
    temp = np.empty(n)
    t = truth.t_s
    for k in range(cycles):
        m = idx == k
        since[m] = t[m] - t[m][0]
        temp[m] = simulate_temperature(t[m], thermal)
    return replace(truth, power_up_index=idx, t_since_power_up_s=since, temp_c=temp)


# ---------------------------------------------------------------------------- run
def _params_true(gyro: SyntheticGyro, out: GyroOutput) -> dict:
    return _params_true_from(gyro, out.draws.get("bias"))


def _params_true_from(gyro: SyntheticGyro, bias_draws: Mapping | None) -> dict:
    p = {e: {k: np.array(v) for k, v in pd.items()} for e, pd in gyro.params.items()}
    if "bias" in p:
        d = bias_draws
        per = d["b_rad_s_per_power_up"]
        p["bias"] = {
            "b_rad_s": per[0].copy() if per.size else p["bias"]["b_rad_s"],
            "b_mean_rad_s": d["b_mean_rad_s"],
            "turn_on_sigma_rad_s": d["turn_on_sigma_rad_s"],
            "b_rad_s_per_power_up": per,
        }
    return validate_params(p)


def _recording_meta(
    spec: ScenarioSpec,
    sensor_spec,
    gyro: SyntheticGyro,
    *,
    seed: int,
    run: int,
    rate: float,
    n: int,
    starts: list[float],
    params_true: Mapping,
    notes: list[str],
    truth_meta: Mapping,
    vib_info: Mapping | None = None,
) -> dict:
    """The ``#`` metadata of a simulated recording (shared by :func:`simulate` and :func:`simulate_stream`)."""
    meta = {
        "sensor": sensor_spec.name,
        "sensor_part": sensor_spec.part,
        "scenario": spec.name,
        "scenario_description": spec.description,
        "seed": str(int(seed)),
        "run": str(int(run)),
        "rate_hz": f"{rate:.10g}",
        "duration_s": f"{n / rate:.10g}",
        "effects": ",".join(gyro.effects),
        "overridden": ",".join(gyro.overridden),
        "without": ",".join(gyro.without),
        "accel": "true specific force (no accelerometer errors simulated)",
        "power_up_t_s": json.dumps(starts),
        "params_true": json.dumps(to_jsonable(params_true), separators=(",", ":")),
    }
    if notes:
        meta["notes"] = " | ".join(notes)
    if vib_info is not None:
        meta["vibration_spec"] = str(spec.vibration["spec"])
        meta["vibration_injection"] = json.dumps(vib_info, separators=(",", ":"), default=str)
    for k, v in truth_meta.items():
        meta.setdefault(f"truth_{k}" if k in meta else k, str(v))
    return meta


def _closed_loop_unsupported(gyro: SyntheticGyro, thermal) -> list[str]:
    """Effects a GyroStream cannot carry in closed loop: a leading gyro (needs future truth)
    and ``bias_temp_rate`` when the temperature is not known in advance (motor heating or a
    heater make it depend on the flight). fly_hover passes the attitude, so ``earth_rate`` works.
    Registry family terms: a ``regressor`` of the rate derivative ``alpha_*`` (needs the next
    sample) and one of ``dtemp_dt`` under the same condition as ``bias_temp_rate``."""
    out = []
    if "time_offset" in gyro.params and float(gyro.params["time_offset"]["tau_s"]) < 0:
        out.append("time_offset")
    heated = thermal.heater is not None or thermal.motor_c_per_w != 0.0
    if "bias_temp_rate" in gyro.params and heated:
        out.append("bias_temp_rate")
    for e in gyro.params:
        eff = resolve(e)
        if eff.family is not None and ("alpha" in eff.inputs or "dtemp" in eff.inputs and heated):
            out.append(eff.name)
    return out


def _scenario_vibration(spec: ScenarioSpec, overrides, without, vehicle, hover_vibration, seed):
    """The scenario's ``[vibration]`` spec as the registry effect (and the hover's rotor vibration):
    (overrides, hover_vibration, vib_info); unchanged when the scenario has none or the caller
    overrides or removes ``vibration``."""
    vib_info = None
    if (
        spec.vibration
        and not any(canonical_name(e) == "vibration" for e in (overrides or {}))
        and "vibration" not in [canonical_name(w) for w in without]
    ):
        hv, vib_over, vib_info = spec_injection(
            read_spec(spec.vibration["spec"]),
            band=spec.vibration.get("band", "middle"),
            vehicle=vehicle or str(spec.hover.get("vehicle", "f450")),
            physics=bool(spec.vibration.get("physics", False)),
            seed=int(seed),
        )
        overrides = {**(overrides or {}), **vib_over}
        if hover_vibration is None:
            hover_vibration = hv
    return overrides, hover_vibration, vib_info


#: The chunked path simulates (physics, temperature, gyro) in blocks of at most this many rows
#: (physics steps for the rate table), re-cut to ``chunk_rows``: the working arrays of a block
#: (truth, model terms, noise) cost ~2 kB a row, so 16 384-row blocks added ~30 MiB to the peak
#: of `simulate hover` (measured 279 vs 248 MiB for 2 min at 1 kHz to CSV); the rows are the
#: same for any block size.
SIM_BLOCK_ROWS = 4096


def simulate(
    name: str | ScenarioSpec,
    *,
    sensor: str = "icm42688p",
    duration_s: float | None = None,
    seed: int = 0,
    run: int = 0,
    overrides: Mapping[str, Mapping[str, object]] | None = None,
    without: Iterable[str] = (),
    gyro_rate_hz: float | None = None,
    progress: bool = False,
    vehicle: str | None = None,
    hover_vibration=None,
    chunk_rows: int | None = None,
) -> "SimResult | SimStream":
    """Simulate one scenario with one sensor unit: whole, or chunk by chunk in bounded memory.

    Parameters
    ----------
    name : str or ScenarioSpec
        Scenario name (:data:`SCENARIOS`) or a scenario TOML path.
    sensor : str
        Preset name (:data:`sim.presets.PRESETS`) or a preset TOML path.
    duration_s : float, optional
        Length, s (default: the scenario's). For the ``turns`` profile the profile is
        shortened to fit (see :func:`_fit_turns`); the realised length may be shorter.
    seed : int
        Unit and scenario seed (>= 0).
    run : int
        Session of the same unit (0, 1, ...): same unit parameters, fresh turn-on bias,
        noise, bumps and rotor phases.
    overrides : mapping, optional
        ``{effect: {param: value}}`` in SI, switched on whatever the preset says (the
        calibration is not told: this is how the residual loop is tested).
    without : iterable of str
        Effects switched off (``vibration`` turns the rotor vibration of ``hover`` off).
    gyro_rate_hz : float, optional
        Output rate, Hz (default: the scenario's, else the preset's).
    progress : bool
        tqdm progress bars from the physics runners (stderr).
    vehicle : str, optional
        ``hover``: vehicle class (:data:`sim.vehicles.VEHICLES`), overriding the scenario's
        ``[hover] vehicle`` (default ``f450``).
    hover_vibration : sim.vehicles.VibrationSpec, optional
        ``hover``: rotor vibration instead of the class's default (e.g. from a measured spec,
        :func:`sim.spec_vibration.vibration_from_spec`); ignored when vibration is off.
    chunk_rows : int, optional
        None (default): simulate the whole record in memory and return a :class:`SimResult`
        (truth, noise, draws and flight log as arrays). An int: return a :class:`SimStream`
        whose :meth:`SimStream.chunks` generates the recording chunk by chunk (bounded memory) —
        the rate table (:func:`sim.turntable.stream_table`, ``chunk_rows`` physics steps per
        rollout) or the closed-loop flight (:class:`sim.quadrotor.HoverFlight`, ``chunk_rows``
        gyro samples per block), the die temperature (:class:`sim.thermal.TemperatureChunks`),
        the power-up split and the gyro (:meth:`sim.gyro.SyntheticGyro.measure_chunks`, block
        noise generators) — so the memory does not grow with the duration. The rows equal the
        whole path's bit for bit, whatever ``chunk_rows`` (tested for every registered
        scenario). The simulation itself runs in blocks of at most :data:`SIM_BLOCK_ROWS`
        rows, re-cut to ``chunk_rows`` (a Parquet row group each when written).

    Returns
    -------
    SimResult, or SimStream when ``chunk_rows`` is given
    """
    setup = _Setup(
        name,
        sensor=sensor,
        duration_s=duration_s,
        seed=seed,
        run=run,
        overrides=overrides,
        without=without,
        gyro_rate_hz=gyro_rate_hz,
        progress=progress,
        vehicle=vehicle,
        hover_vibration=hover_vibration,
    )
    if chunk_rows is None:
        return setup.whole()
    if isinstance(chunk_rows, bool) or not isinstance(chunk_rows, (int, np.integer)) or int(chunk_rows) < 1:
        raise GyroInputError(f"chunk_rows must be an integer >= 1, got {chunk_rows!r}")
    return setup.chunked(int(chunk_rows))


def simulate_stream(name: str | ScenarioSpec, *, chunk_rows: int = 16_384, **options) -> "SimStream":
    """``simulate(name, chunk_rows=chunk_rows, **options)``: the recording as a :class:`SimStream`
    of ``chunk_rows``-row chunks (the keyword options are :func:`simulate`'s)."""
    return simulate(name, chunk_rows=chunk_rows, **options)


class _Setup:
    """Everything :func:`simulate` decides before it runs (the scenario, the sensor unit, the
    table profile or the flight, the thermal model, the notes), shared by the whole path
    (:meth:`whole`) and the chunked one (:meth:`chunked`)."""

    def __init__(
        self,
        name,
        *,
        sensor,
        duration_s,
        seed,
        run,
        overrides,
        without,
        gyro_rate_hz,
        progress,
        vehicle,
        hover_vibration,
    ) -> None:
        spec = load_scenario(name)
        sensor_spec = load_preset(sensor)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise GyroInputError(f"seed must be an integer >= 0, got {seed!r}")
        if duration_s is not None and not (math.isfinite(float(duration_s)) and float(duration_s) > 0):
            raise GyroInputError(f"duration must be > 0 s, got {duration_s}")
        self.spec, self.sensor_spec, self.seed, self.run, self.progress = (
            spec,
            sensor_spec,
            int(seed),
            int(run),
            progress,
        )
        self.rate = rate = float(gyro_rate_hz or spec.gyro_rate_hz or sensor_spec.rate_hz)
        dur = float(duration_s) if duration_s is not None else spec.duration_s
        without = list(without)
        overrides, hover_vibration, self.vib_info = _scenario_vibration(
            spec, overrides, without, vehicle, hover_vibration, seed
        )
        self.gyro = gyro = SyntheticGyro(
            sensor_spec, rate_hz=rate, seed=self.seed, run=self.run, without=without, overrides=overrides
        )
        self.notes = list(gyro.notes)
        if spec.kind == "table":
            self.prof = build_table_profile(spec, dur, seed=self.seed, run=self.run)
            self.thermal = build_thermal(spec.thermal, self.prof.duration_s)
            self.cycles = int(spec.power.get("cycles", 1))
            return

        self.dur = dur
        self.thermal = thermal = build_thermal(spec.thermal, dur)
        unsupported = _closed_loop_unsupported(gyro, thermal)
        self.fly_gyro = gyro
        if unsupported:
            self.notes.append(
                f"the controller flew on the gyro without {', '.join(unsupported)} (not possible in closed "
                "loop); the recording has them"
            )
            self.fly_gyro = SyntheticGyro(
                sensor_spec,
                rate_hz=rate,
                seed=self.seed,
                run=self.run,
                without=without + unsupported,
                overrides={e: v for e, v in (overrides or {}).items() if canonical_name(e) not in unsupported},
            )
        ground = hover_ground_s(spec, dur)
        if ground == 0.0 and float(spec.hover.get("ground_s", 0.0)) > 0.0:
            self.notes.append(
                f"no ground phase: {dur:g} s is shorter than ground_s + take-off + {MIN_AIRBORNE_S:g} s of "
                "hover (the flight starts airborne)"
            )
        t_air = ground + (TAKEOFF_CLIMB_S if ground > 0.0 else 0.0)  # manoeuvres after the take-off
        man = (
            tuple(replace(m, t_start_s=m.t_start_s + t_air) for m in small_steps(dur - t_air))
            if spec.hover.get("manoeuvres", True)
            else ()
        )
        vib = bool(spec.hover.get("vibration", True)) and "vibration" not in gyro.without
        if vib and hover_vibration is not None:
            vib = hover_vibration
        #: fly_hover / HoverFlight options (the gyro apart)
        self.flight = dict(
            duration_s=dur,
            vibration=vib,
            manoeuvres=man,
            gyro_rate_hz=rate,
            thermal=thermal,
            seed=self.seed + 1000003 * self.run,
            progress=progress,
            ground_s=ground,
            vehicle=vehicle or str(spec.hover.get("vehicle", "f450")),
        )

    def _meta(self, params_true, n: int, starts: list[float], truth_meta) -> dict:
        return _recording_meta(
            self.spec,
            self.sensor_spec,
            self.gyro,
            seed=self.seed,
            run=self.run,
            rate=self.rate,
            n=n,
            starts=starts,
            params_true=params_true,
            notes=self.notes,
            truth_meta=truth_meta,
            vib_info=self.vib_info,
        )

    # ------------------------------------------------------------------ whole
    def whole(self) -> SimResult:
        """Truth whole (``run_table`` / ``fly_hover``), ``SyntheticGyro.measure``, one :class:`SimResult`."""
        gyro, flight_log = self.gyro, None
        if self.spec.kind == "table":
            truth = run_table(
                self.prof, gyro_rate_hz=self.rate, thermal=self.thermal, seed=self.seed, progress=self.progress
            )
            if self.cycles > 1:
                truth = _split_power_ups(truth, self.cycles, self.thermal)
        else:
            fly_gyro, rate = self.fly_gyro, self.rate
            n = int(math.floor(self.dur * rate + 1e-9))  # fly_hover's sample count
            kw = {}
            if "bias_temp_rate" in fly_gyro.params or any("dtemp" in resolve(e).inputs for e in fly_gyro.params):
                t_all = np.arange(n) * (1.0 / rate)
                kw = {"t_s": t_all, "temp_c": simulate_temperature(t_all, self.thermal)}
            truth, flight_log = fly_hover(gyro=fly_gyro.stream(n, **kw), **self.flight)
        out = gyro.measure(truth)
        params_true = _params_true(gyro, out)
        pu = np.asarray(truth.power_up_index, int)
        starts = [float(truth.t_s[i]) for i in np.flatnonzero(np.concatenate([[True], np.diff(pu) != 0]))]
        meta = self._meta(params_true, truth.n, starts, truth.meta)
        rec = Recording(
            t_s=truth.t_s,
            gyro_rad_s=out.gyro_rad_s,
            accel_m_s2=truth.f_S_m_s2,
            temp_c=truth.temp_c,
            ref_rate_rad_s=truth.omega_S_rad_s,
            ref_quat_wxyz=truth.q_SW_wxyz,
            meta=meta,
            extra={"power_up_index": pu.astype(float)},
        )
        return SimResult(
            scenario=self.spec.name,
            sensor=self.sensor_spec.name,
            seed=self.seed,
            run=self.run,
            recording=rec,
            truth=truth,
            params_true=params_true,
            draws=out.draws,
            noise_rad_s=out.noise_rad_s,
            flight_log=flight_log,
            notes=tuple(self.notes),
        )

    # ------------------------------------------------------------------ chunked
    def chunked(self, chunk_rows: int) -> "SimStream":
        """The truth chunk by chunk (rate table or flight), ``measure_chunks``, one :class:`SimStream`."""
        gyro, rate = self.gyro, self.rate
        block = min(chunk_rows, SIM_BLOCK_ROWS)
        if self.spec.kind == "table":
            table = stream_table(
                self.prof,
                gyro_rate_hz=rate,
                thermal=self.thermal,
                seed=self.seed,
                progress=self.progress,
                chunk_steps=block,
            )
            n, cycles, truth_meta = table.n_samples, self.cycles, table.meta
            if cycles < 1:
                raise GyroInputError("[power] cycles must be >= 1")
            if cycles > 1 and n < 2 * cycles:
                raise GyroInputError(f"{cycles} power-ups need at least {2 * cycles} samples")
            starts_k = [-(-(i * n) // cycles) for i in range(cycles)]
            starts = [float(np.arange(k, k + 1)[0] / rate) for k in starts_k]

            def truths():
                tr = (tr for tr, _ang in table.chunks())
                return _power_cycle_chunks(tr, n, cycles, self.thermal) if cycles > 1 else tr
        else:
            # the flight block by block: a block stream of the gyro in the loop (noise drawn per block)
            flight = HoverFlight(gyro=self.fly_gyro, gyro_blocks=True, **self.flight)
            n, cycles, truth_meta = flight.n, 1, flight.meta
            starts = [float(flight._times(0, 1)[0])]

            def truths():
                return (tr for tr, _log in flight.blocks(block, flight_log=False))

        pd = gyro.params.get("bias")
        bias_draws = None
        if pd is not None:
            bias_draws = {
                "b_mean_rad_s": pd["b_rad_s"].copy(),
                "turn_on_sigma_rad_s": np.asarray(pd.get("turn_on_sigma_rad_s", np.zeros(3))).copy(),
                "power_up_indices": np.arange(cycles),
                "b_rad_s_per_power_up": np.array([gyro.power_up_bias(i) for i in range(cycles)]).reshape(-1, 3),
            }
        params_true = _params_true_from(gyro, bias_draws)
        meta = self._meta(params_true, n, starts, truth_meta)

        def chunks():
            pieces = (
                Recording(
                    t_s=gc.t_s,
                    gyro_rad_s=gc.gyro_rad_s,
                    accel_m_s2=gc.truth.f_S_m_s2,
                    temp_c=gc.truth.temp_c,
                    ref_rate_rad_s=gc.truth.omega_S_rad_s,
                    ref_quat_wxyz=gc.truth.q_SW_wxyz,
                    meta=meta,
                    extra={"power_up_index": np.asarray(gc.truth.power_up_index, int).astype(float)},
                )
                for gc in gyro.measure_chunks(truths())
            )
            yield from _rechunk_recordings(pieces, chunk_rows)

        st = SimStream(
            scenario=self.spec.name,
            sensor=self.sensor_spec.name,
            seed=self.seed,
            run=self.run,
            rate_hz=rate,
            n_samples=n,
            meta=meta,
            params_true=params_true,
            notes=tuple(self.notes),
            bounded=True,
        )
        st._chunks = chunks
        return st


class SimStream:
    """A simulated recording delivered in chunks (bounded memory): ``simulate(..., chunk_rows=N)``.

    Attributes
    ----------
    scenario, sensor : str
    seed, run : int
    rate_hz : float
    n_samples : int
        Rows of the whole recording.
    meta : dict
        The recording's ``#`` metadata (identical to the whole path's, ``params_true`` included).
    params_true : dict
    notes : tuple of str
    bounded : bool
        True: the chunks are generated chunk by chunk (every scenario since the hover flies in
        blocks, :class:`sim.quadrotor.HoverFlight`).

    :meth:`chunks` yields :class:`gyrocore.data.recording.Recording` pieces of at most
    ``chunk_rows`` rows, once; their concatenation equals the whole path's recording bit for bit.
    """

    def __init__(self, **kw) -> None:
        self.__dict__.update(kw)
        self._used = False

    def chunks(self):
        if self._used:
            raise GyroInputError("a SimStream runs once")
        self._used = True
        return self._chunks()


def _rechunk_recordings(pieces, rows: int):
    """Concatenate/cut consecutive Recording pieces into pieces of ``rows`` rows (the last shorter)."""
    held: list[Recording] = []
    count = 0
    for rec in pieces:
        if rec.n == 0:
            continue
        held.append(rec)
        count += rec.n
        while count >= rows:
            whole = held[0] if len(held) == 1 else concat_recordings(held)
            yield whole.slice(0, rows)
            rest = whole.slice(rows, whole.n)
            held = [rest] if rest.n else []
            count = rest.n
    if count:
        yield held[0] if len(held) == 1 else concat_recordings(held)


def _power_cycle_chunks(truths, n: int, cycles: int, thermal):
    """:func:`_split_power_ups` on a truth arriving in chunks (same index, time since power-up and
    cold-start temperature per cycle, bit for bit)."""
    if cycles < 1:
        raise GyroInputError("[power] cycles must be >= 1")
    if n < 2 * cycles:
        raise GyroInputError(f"{cycles} power-ups need at least {2 * cycles} samples")
    starts = [-(-(i * n) // cycles) for i in range(cycles)] + [n]  # first k with k*cycles//n == i
    k0 = 0
    cur, t_first, temp = -1, None, None
    for tr in truths:
        m = tr.n
        k = np.arange(k0, k0 + m)
        idx = (k * cycles) // n
        since = np.empty(m)
        tc = np.empty(m)
        for c in np.unique(idx):
            sel = idx == c
            if c != cur:
                cur = int(c)
                t_first = float(tr.t_s[sel][0])
                temp = TemperatureChunks(thermal, n_total=starts[cur + 1] - starts[cur])
            since[sel] = tr.t_s[sel] - t_first
            tc[sel] = temp.take(tr.t_s[sel])
        yield replace(tr, power_up_index=idx, t_since_power_up_s=since, temp_c=tc)
        k0 += m


#: ``hover``: shortest hover after the take-off for the ground phase to be flown, s.
MIN_AIRBORNE_S = 5.0


def hover_ground_s(spec: ScenarioSpec, duration_s: float) -> float:
    """Time on the ground before take-off for a ``hover`` scenario of ``duration_s``, s.

    ``[hover] ground_s`` when the flight also has room for the take-off
    (:data:`sim.quadrotor.TAKEOFF_CLIMB_S`) and :data:`MIN_AIRBORNE_S` of hover after it; else 0
    (airborne start: short test flights keep the plain hover).
    """
    ground = float(spec.hover.get("ground_s", 0.0))
    if ground > 0.0 and duration_s >= ground + TAKEOFF_CLIMB_S + MIN_AIRBORNE_S:
        return ground
    return 0.0


# ---------------------------------------------------------------------------- helpers for scoring
def true_bias_rad_s(res: SimResult) -> np.ndarray:
    """The true constant bias at every sample (the turn-on draw of its power-up), rad/s, (N, 3)."""
    n = res.truth.n
    if "bias" not in res.params_true:
        return np.zeros((n, 3))
    per = np.asarray(res.params_true["bias"]["b_rad_s_per_power_up"]).reshape(-1, 3)
    idx = np.asarray(res.draws["bias"]["power_up_indices"], int)
    pos = {int(k): i for i, k in enumerate(idx)}
    return per[[pos[int(k)] for k in res.truth.power_up_index]]


def floor_gyro(res: SimResult) -> np.ndarray:
    """The gyro with every deterministic error perfectly removed: truth + the stochastic noise, rad/s (N, 3).

    DESIGN.md "The score": the floor is the integration of this gyro.
    """
    return np.asarray(res.truth.omega_S_rad_s, float) + res.noise_rad_s
