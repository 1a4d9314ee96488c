"""Sensor presets: datasheet TOML files -> SI error distributions -> drawn sensor instances.

A preset (``sim/presets/<name>.toml``) is written in datasheet units (°/s, °/s/√Hz, °/h,
°/√h, %, %/°C, °/s/g, LSB/(°/s), Hz) with the datasheet source of each value in a comment.
**This module is the only place where datasheet units are converted to SI** (table
:data:`_KEYS`).

Reading conventions (one rule for every preset):

* ``tol_*`` keys are a datasheet "±X (typ.)" tolerance, read as a ±3σ population bound:
  σ = X/3 (:data:`TOL_SIGMAS`). ``sigma_*`` keys are 1σ values (as Analog Devices gives
  them, or our typical value where a datasheet is silent — the TOML comment says which).
* Noise levels (``arw``, ``bias_instability``, ``rrw``, ``correlated``) and the output
  stage (``quantization``, ``saturation``, ``lowpass``) are the same for every unit.
* ``bias_instability.allan_floor_deg_per_h`` is the Allan-deviation minimum (what datasheets
  and published Allan plots report); IEEE 952's B is floor/√(2 ln2/π) = floor/0.664.
* ``scale_nonlinearity.*_pct_fs`` is the datasheet best-fit-straight-line nonlinearity as a
  fraction of full scale F. For the model error s2·ω·|ω| the minimax straight line through 0
  on [−F, F] leaves a maximum deviation (3 − 2√2)·s2·F² (equal ripple at ω = (√2−1)F and
  ω = F), so s2 = frac / ((3 − 2√2)·F).
* ``enabled = false`` in a section: the level is known but the effect is off unless switched
  on (``SyntheticGyro(..., overrides=...)`` or ``draw_instance(..., include=...)``).
* A section named by a registry family term (``["periodic[37.5]"]``, ``["step[12.25]"]``,
  ``["regressor[omega_y*omega_z]"]``; :func:`gyrocore.effects.registry.resolve`) injects that term with
  fixed values in SI, the parameter names of its schema (``a_cos_rad_s = [0.01, 0, 0]``; a
  scalar means all three axes; missing parameters are 0): the same for every unit. A
  registered noise term outside the catalogue (``[arw_lowpass]``, ``[arw_student]``,
  ``[angle_white]``; :data:`gyrocore.effects.registry.NOISE_TERMS`) is given the same way; every
  parameter is required except ``arw_student.bandwidth_hz`` (default 0 = no low-pass).

A :class:`SensorSpec` holds the SI distributions; :meth:`SensorSpec.draw_instance` draws one
sensor's true parameters in :data:`gyrocore.effects.registry.PARAM_SCHEMA` form, every effect from
its own seeded stream (:func:`sim.noise.effect_rng`).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Iterable, Mapping

import numpy as np

from gyrocore.effects.registry import EFFECTS, NOISE_TERMS, PARAM_SCHEMA, is_family, resolve, validate_params
from gyrocore.errors import GyroInputError

from .noise import ALLAN_FLICKER_FACTOR, effect_rng

__all__ = [
    "SensorSpec",
    "load_preset",
    "all_effects_overrides",
    "PRESETS",
    "PRESET_DIR",
    "TOL_SIGMAS",
    "NL_MINIMAX_FACTOR",
]

PRESET_DIR = Path(__file__).resolve().parent / "presets"
DEG = math.pi / 180.0
G0_M_S2 = 9.80665
#: A datasheet "±X typ." tolerance is read as ±TOL_SIGMAS·σ.
TOL_SIGMAS = 3.0
#: Max deviation of ω|ω| from its minimax line through 0 on [−F, F], in units of F²: 3 − 2√2.
NL_MINIMAX_FACTOR = 3.0 - 2.0 * math.sqrt(2.0)

_T = 1.0 / TOL_SIGMAS
#: (effect, TOML key) -> (SI key, factor). THE datasheet -> SI conversion table.
_KEYS: dict[str, dict[str, tuple[str, float]]] = {
    "bias": {
        "tol_dps": ("b_sigma_rad_s", DEG * _T),
        "sigma_dps": ("b_sigma_rad_s", DEG),
        "sigma_turn_on_dps": ("turn_on_sigma_rad_s", DEG),
    },
    "bias_thermal": {
        "tol_dps_per_c": ("c1_sigma_rad_s_per_c", DEG * _T),
        "sigma_dps_per_c": ("c1_sigma_rad_s_per_c", DEG),
        "tol_dps_per_c2": ("c2_sigma_rad_s_per_c2", DEG * _T),
        "sigma_dps_per_c2": ("c2_sigma_rad_s_per_c2", DEG),
        "temp_min_c": ("temp_min_c", 1.0),
        "temp_max_c": ("temp_max_c", 1.0),
    },
    "bias_temp_rate": {"sigma_dps_per_c_per_s": ("k_sigma_rad_s_per_c_per_s", DEG)},
    "bias_ramp": {"sigma_dps_per_h": ("ramp_sigma_rad_s2", DEG / 3600.0)},
    "scale": {"tol_pct": ("s_sigma", 0.01 * _T), "sigma_pct": ("s_sigma", 0.01)},
    "scale_thermal": {
        "tol_pct_per_c": ("c1_sigma_per_c", 0.01 * _T),
        "sigma_pct_per_c": ("c1_sigma_per_c", 0.01),
        "tol_pct_per_c2": ("c2_sigma_per_c2", 0.01 * _T),
        "sigma_pct_per_c2": ("c2_sigma_per_c2", 0.01),
        "temp_min_c": ("temp_min_c", 1.0),
        "temp_max_c": ("temp_max_c", 1.0),
    },
    "scale_asymmetry": {"tol_pct": ("a_sigma", 0.01 * _T), "sigma_pct": ("a_sigma", 0.01)},
    # converted to s2 (1/(rad/s)) with the full scale in _convert()
    "scale_nonlinearity": {"tol_pct_fs": ("nl_sigma_frac_fs", 0.01 * _T), "sigma_pct_fs": ("nl_sigma_frac_fs", 0.01)},
    "misalignment": {
        "tol_pct": ("m_sigma_rad", 0.01 * _T),  # cross-axis sensitivity 1 % = 0.01 rad
        "sigma_pct": ("m_sigma_rad", 0.01),
        "tol_deg": ("m_sigma_rad", DEG * _T),
        "sigma_deg": ("m_sigma_rad", DEG),
    },
    "g_sensitivity": {
        "tol_dps_per_g": ("h_sigma_rad_s_per_m_s2", DEG / G0_M_S2 * _T),
        "sigma_dps_per_g": ("h_sigma_rad_s_per_m_s2", DEG / G0_M_S2),
    },
    "g2_sensitivity": {"sigma_dps_per_g2": ("g_sigma_rad_s_per_m2_s4", DEG / G0_M_S2**2)},
    "time_offset": {"tau_s": ("tau_s", 1.0)},
    "earth_rate": {"latitude_deg": ("latitude_rad", DEG), "heading_deg": ("heading_rad", DEG)},
    "quantization": {"lsb_dps": ("lsb_rad_s", DEG)},
    "saturation": {"range_dps": ("range_rad_s", DEG)},
    "lowpass": {"bandwidth_hz": ("bandwidth_hz", 1.0)},
    "arw": {
        "density_dps_per_sqrt_hz": ("n_rad_per_sqrt_s", DEG),
        "arw_deg_per_sqrt_h": ("n_rad_per_sqrt_s", DEG / 60.0),  # °/√h = (π/180) rad / √(3600 s)
    },
    "bias_instability": {
        "deg_per_h": ("b_rad_s", DEG / 3600.0),
        "allan_floor_deg_per_h": ("b_rad_s", DEG / 3600.0 / ALLAN_FLICKER_FACTOR),
    },
    "rrw": {"deg_per_h_per_sqrt_h": ("k_rad_s_per_sqrt_s", DEG / 3600.0 / 60.0)},
    "correlated": {"sigma_dps": ("sigma_rad_s", DEG), "tau_c_s": ("tau_c_s", 1.0)},
    "vibration": {},
}
_OUTPUT_KEYS = {"rate_hz", "full_scale_dps", "sensitivity_lsb_per_dps", "temp_ref_c"}
#: SI keys each effect's distribution needs (the rest are optional).
_REQUIRED = {
    "bias": ("b_sigma_rad_s",),
    "bias_thermal": ("c1_sigma_rad_s_per_c",),
    "bias_temp_rate": ("k_sigma_rad_s_per_c_per_s",),
    "bias_ramp": ("ramp_sigma_rad_s2",),
    "scale": ("s_sigma",),
    "scale_thermal": ("c1_sigma_per_c",),
    "scale_asymmetry": ("a_sigma",),
    "scale_nonlinearity": ("s2_sigma_s_per_rad",),
    "misalignment": ("m_sigma_rad",),
    "g_sensitivity": ("h_sigma_rad_s_per_m_s2",),
    "g2_sensitivity": ("g_sigma_rad_s_per_m2_s4",),
    "time_offset": ("tau_s",),
    "earth_rate": ("latitude_rad",),
    "quantization": ("lsb_rad_s",),
    "saturation": ("range_rad_s",),
    "lowpass": ("bandwidth_hz",),
    "arw": ("n_rad_per_sqrt_s",),
    "bias_instability": ("b_rad_s",),
    "rrw": ("k_rad_s_per_sqrt_s",),
    "correlated": ("sigma_rad_s", "tau_c_s"),
    "vibration": (),
}


def _freeze(d: Mapping[str, Mapping[str, float]]) -> Mapping[str, Mapping[str, float]]:
    return MappingProxyType({k: MappingProxyType(dict(v)) for k, v in d.items()})


@dataclass(frozen=True)
class SensorSpec:
    """A sensor model: the population distributions of every error, in SI.

    Parameters
    ----------
    name : str
        Preset name (e.g. ``"icm42688p"``).
    part : str
        Manufacturer part name.
    datasheet : str
        Document the values come from.
    rate_hz : float
        Default output data rate, Hz.
    full_scale_rad_s : float
        Measurement range ±, rad/s.
    lsb_rad_s : float
        Output resolution, rad/s per LSB.
    temp_ref_c : float
        Reference temperature T0 of the thermal polynomials, °C.
    effects : mapping
        ``{effect: {si_key: value}}`` for the effects that are ON. Keys ending in ``_sigma…``
        (or ``*_sigma_*``) are 1σ of a zero-mean normal population; the others are fixed.
    disabled : mapping
        Same, for effects whose level is known but which are off by default.
    source : str
        Path of the TOML file.
    terms : mapping
        Registry family terms with fixed SI parameters ``{canonical name: {param: tuple}}``
        (the same for every unit; see the module docstring).
    shaped_vibration : mapping
        The shaped part of ``vibration`` (``{"f_hz": tuple, "psd_rad2_s2_hz": tuple of 3
        tuples}``, :func:`gyrocore.flight.synthesis.shaped_params`) from a ``[vibration]`` section with
        ``spec = "SPEC.json"`` (path relative to the TOML) and optional ``band`` (index or
        ``"middle"``); empty = none (the physics part alone).
    """

    name: str
    part: str
    datasheet: str
    rate_hz: float
    full_scale_rad_s: float
    lsb_rad_s: float
    temp_ref_c: float
    effects: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    disabled: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    source: str = ""
    terms: Mapping[str, Mapping[str, tuple]] = field(default_factory=dict)
    shaped_vibration: Mapping[str, tuple] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "effects", _freeze(self.effects))
        object.__setattr__(self, "disabled", _freeze(self.disabled))
        object.__setattr__(self, "terms", _freeze(self.terms))

    def distribution(self, effect: str) -> Mapping[str, float] | None:
        """The SI distribution of ``effect`` (on or off), or None if the preset has none."""
        if effect in self.effects:
            return self.effects[effect]
        return self.disabled.get(effect)

    def draw_effect(self, effect: str, seed: int) -> dict[str, np.ndarray]:
        """Draw one effect's true parameters (PARAM_SCHEMA names, SI) from its own stream.

        The stream is ``effect_rng(seed, "instance/<effect>")``: drawing effect X never
        changes the draw of effect Y.
        """
        d = self.distribution(effect)
        if d is None:
            raise GyroInputError(f"preset {self.name} has no level for effect {effect}; give its parameters explicitly")
        rng = effect_rng(seed, f"instance/{effect}")
        t0 = self.temp_ref_c

        def nrm(shape, sigma):
            return rng.standard_normal(shape) * float(sigma)

        def poly(c1, c2):
            cols = [nrm(3, d[c1])]
            if c2 in d:
                cols.append(nrm(3, d[c2]))
            return np.stack(cols, axis=1)

        def trange():
            return {
                "t0_c": np.asarray(t0),
                "temp_min_c": np.asarray(d.get("temp_min_c", -40.0)),
                "temp_max_c": np.asarray(d.get("temp_max_c", 85.0)),
            }

        if effect == "bias":
            return {
                "b_rad_s": nrm(3, d["b_sigma_rad_s"]),
                "turn_on_sigma_rad_s": np.full(3, float(d.get("turn_on_sigma_rad_s", 0.0))),
            }
        if effect == "bias_thermal":
            return {"poly_rad_s": poly("c1_sigma_rad_s_per_c", "c2_sigma_rad_s_per_c2"), **trange()}
        if effect == "bias_temp_rate":
            return {"k_rad_s_per_c_per_s": nrm(3, d["k_sigma_rad_s_per_c_per_s"])}
        if effect == "bias_ramp":
            return {"ramp_rad_s2": nrm(3, d["ramp_sigma_rad_s2"])}
        if effect == "scale":
            return {"s": nrm(3, d["s_sigma"])}
        if effect == "scale_thermal":
            return {"poly_per_c": poly("c1_sigma_per_c", "c2_sigma_per_c2"), **trange()}
        if effect == "scale_asymmetry":
            return {"a": nrm(3, d["a_sigma"])}
        if effect == "scale_nonlinearity":
            return {"s2_s_per_rad": nrm(3, d["s2_sigma_s_per_rad"])}
        if effect == "misalignment":
            return {"m_rad": nrm(6, d["m_sigma_rad"])}
        if effect == "g_sensitivity":
            return {"h_rad_s_per_m_s2": nrm((3, 3), d["h_sigma_rad_s_per_m_s2"])}
        if effect == "g2_sensitivity":
            return {"g_rad_s_per_m2_s4": nrm((3, 6), d["g_sigma_rad_s_per_m2_s4"])}
        if effect == "time_offset":
            return {"tau_s": np.asarray(float(d["tau_s"]))}
        if effect == "earth_rate":
            return {
                "latitude_rad": np.asarray(float(d["latitude_rad"])),
                "heading_rad": np.asarray(float(d.get("heading_rad", 0.0))),
            }
        if effect in ("quantization", "saturation", "lowpass"):
            (k,) = PARAM_SCHEMA[effect]
            return {k: np.asarray(float(d[k]))}
        if effect in ("arw", "bias_instability", "rrw"):
            (k,) = PARAM_SCHEMA[effect]
            return {k: np.full(3, float(d[k]))}
        if effect == "correlated":
            return {"sigma_rad_s": np.full(3, float(d["sigma_rad_s"])), "tau_c_s": np.full(3, float(d["tau_c_s"]))}
        if effect == "vibration":
            return {}
        raise GyroInputError(f"unknown effect '{effect}'")  # pragma: no cover (names checked on load)

    def draw_instance(self, seed: int, *, include: Iterable[str] = ()) -> dict[str, dict[str, np.ndarray]]:
        """Draw one sensor unit: ``{effect: {param: ndarray}}`` in PARAM_SCHEMA form (SI).

        Parameters
        ----------
        seed : int
            Instance seed (>= 0). Each effect uses ``effect_rng(seed, "instance/<effect>")``.
        include : iterable of str
            Effects that are off in the preset (``enabled = false``) to switch on too.

        Returns
        -------
        dict
            Validated parameters. ``bias`` carries the extra ``turn_on_sigma_rad_s`` (3,):
            its ``b_rad_s`` is the unit's mean bias; every power-up adds a fresh
            N(0, turn_on_sigma²) draw (done by :class:`sim.gyro.SyntheticGyro`).
        """
        names = [e for e in EFFECTS if e in self.effects or e in set(include)]
        out = {e: self.draw_effect(e, seed) for e in names if e != "vibration"}
        for e, pd in self.terms.items():  # family terms: fixed values, no draw
            out[e] = {k: np.array(v, float) for k, v in pd.items()}
        return validate_params(out)


# ---------------------------------------------------------------------------- loading
def _convert(raw: Mapping, path: str) -> SensorSpec:
    name = str(raw.get("name") or Path(path).stem)
    out = raw.get("output")
    if not isinstance(out, Mapping):
        raise GyroInputError(f"preset {path}: missing [output] section")
    unknown = set(out) - _OUTPUT_KEYS
    if unknown:
        raise GyroInputError(f"preset {path}: unknown key(s) in [output]: {', '.join(sorted(unknown))}")
    for k in ("rate_hz", "full_scale_dps", "sensitivity_lsb_per_dps"):
        if k not in out:
            raise GyroInputError(f"preset {path}: [output] needs {k}")
        v = out[k]
        if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise GyroInputError(f"preset {path}: [output] {k} must be a positive number, got {v!r}")
    full_rad_s = float(out["full_scale_dps"]) * DEG
    lsb_rad_s = DEG / float(out["sensitivity_lsb_per_dps"])
    on: dict[str, dict[str, float]] = {}
    off: dict[str, dict[str, float]] = {}
    shaped: dict[str, tuple] = {}
    terms: dict[str, dict[str, tuple]] = {}
    for eff, table in raw.items():
        if eff in ("name", "part", "datasheet", "output"):
            continue
        if is_family(eff) or eff in NOISE_TERMS:
            name, pd = _family_section(eff, table, path)
            if name in terms:
                raise GyroInputError(f"preset {path}: [{eff}] is the term {name} given twice")
            if pd is not None:
                terms[name] = pd
            continue
        if eff not in _KEYS:
            raise GyroInputError(f"preset {path}: unknown effect section [{eff}]; known: {', '.join(EFFECTS)}")
        if eff == "vibration" and isinstance(table, Mapping) and "spec" in table:
            shaped = _vibration_section(table, path)
            continue
        if not isinstance(table, Mapping):
            raise GyroInputError(f"preset {path}: [{eff}] must be a table")
        enabled = table.get("enabled", True)
        if not isinstance(enabled, bool):
            raise GyroInputError(f"preset {path}: [{eff}] enabled must be true or false")
        si: dict[str, float] = {}
        for key, val in table.items():
            if key == "enabled":
                continue
            if key not in _KEYS[eff]:
                raise GyroInputError(
                    f"preset {path}: unknown key {key} in [{eff}]; accepted: {', '.join(_KEYS[eff]) or 'none'}"
                )
            if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val):
                raise GyroInputError(f"preset {path}: [{eff}] {key} must be a finite number, got {val!r}")
            si_key, factor = _KEYS[eff][key]
            if si_key in si:
                raise GyroInputError(f"preset {path}: [{eff}] gives {si_key} twice")
            si[si_key] = float(val) * factor
        # defaults from the output section
        if eff == "quantization":
            si.setdefault("lsb_rad_s", lsb_rad_s)
        if eff == "saturation":
            si.setdefault("range_rad_s", full_rad_s)
        if eff == "scale_nonlinearity" and "nl_sigma_frac_fs" in si:
            si["s2_sigma_s_per_rad"] = si.pop("nl_sigma_frac_fs") / (NL_MINIMAX_FACTOR * full_rad_s)
        missing = [k for k in _REQUIRED[eff] if k not in si]
        if missing:
            raise GyroInputError(f"preset {path}: [{eff}] lacks a value for {', '.join(missing)}")
        for k, v in si.items():
            if v < 0 and k not in ("latitude_rad", "heading_rad", "tau_s", "temp_min_c", "temp_max_c"):
                raise GyroInputError(f"preset {path}: [{eff}] {k} must be >= 0")
        (on if enabled else off)[eff] = si
    return SensorSpec(
        name=name,
        part=str(raw.get("part", name)),
        datasheet=str(raw.get("datasheet", "")),
        rate_hz=float(out["rate_hz"]),
        full_scale_rad_s=full_rad_s,
        lsb_rad_s=lsb_rad_s,
        temp_ref_c=float(out.get("temp_ref_c", 25.0)),
        effects=on,
        disabled=off,
        source=str(path),
        terms=terms,
        shaped_vibration=shaped,
    )


def _vibration_section(table: Mapping, path: str) -> dict[str, tuple]:
    """``[vibration] spec = "SPEC.json", band = N|"middle", enabled = bool`` -> the shaped part's SI parameters."""
    from gyrocore.flight.synthesis import shaped_params
    from gyrocore.flight.vibration import read_spec

    unknown = set(table) - {"spec", "band", "enabled"}
    if unknown:
        raise GyroInputError(
            f"preset {path}: unknown key(s) in [vibration]: {', '.join(sorted(unknown))}; accepted: spec, band, enabled"
        )
    enabled = table.get("enabled", True)
    if not isinstance(enabled, bool):
        raise GyroInputError(f"preset {path}: [vibration] enabled must be true or false")
    if not enabled:
        return {}
    sp = Path(str(table["spec"]))
    if not sp.is_absolute():
        sp = Path(path).resolve().parent / sp
    pd = shaped_params(read_spec(sp), band=table.get("band", "middle"))
    return {
        "f_hz": tuple(pd["f_hz"].tolist()),
        "psd_rad2_s2_hz": tuple(tuple(r) for r in pd["psd_rad2_s2_hz"].tolist()),
    }


def _family_section(eff: str, table, path: str):
    """A registry family term's section -> (canonical name, {param: tuple} or None if disabled)."""
    try:
        effect = resolve(eff)
    except GyroInputError as exc:
        raise GyroInputError(f"preset {path}: [{eff}]: {exc}") from None
    if not isinstance(table, Mapping):
        raise GyroInputError(f"preset {path}: [{eff}] must be a table")
    enabled = table.get("enabled", True)
    if not isinstance(enabled, bool):
        raise GyroInputError(f"preset {path}: [{eff}] enabled must be true or false")
    pd: dict[str, tuple] = {}
    for key, val in table.items():
        if key == "enabled":
            continue
        if key not in effect.schema:
            raise GyroInputError(
                f"preset {path}: unknown key {key} in [{eff}]; accepted: {', '.join(effect.schema)} (SI)"
            )
        vals = val if isinstance(val, list) else [val]
        if any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in vals):
            raise GyroInputError(f"preset {path}: [{eff}] {key} must be a finite number or a list of 3, got {val!r}")
        try:
            arr = np.broadcast_to(
                np.asarray(vals if isinstance(val, list) else float(val), float), effect.schema[key]
            ).copy()
        except ValueError:
            raise GyroInputError(
                f"preset {path}: [{eff}] {key} needs shape {effect.schema[key]} (or a scalar)"
            ) from None
        pd[key] = tuple(arr.tolist()) if arr.ndim else float(arr)
    for key, d in effect.defaults.items():
        d = np.asarray(d, float)
        pd.setdefault(key, tuple(d.tolist()) if d.ndim else float(d))
    return effect.name, (pd if enabled else None)


def _discover() -> Mapping[str, Path]:
    return MappingProxyType({p.stem: p for p in sorted(PRESET_DIR.glob("*.toml"))})


#: Registry of the shipped presets: name -> TOML path.
PRESETS: Mapping[str, Path] = _discover()
_CACHE: dict[str, SensorSpec] = {}


def read_registered_toml(key: str, registry: Mapping[str, Path], *, what: str, short: str) -> tuple[Path, dict]:
    """Resolve ``key`` as a registry name or a ``.toml`` path and parse it (one-line errors).

    Shared by the sensor presets and the scenarios: both are TOML data registered by name.
    """
    if key in registry:
        path = registry[key]
    else:
        path = Path(key)
        if path.suffix != ".toml" or not path.is_file():
            raise GyroInputError(f"unknown {what} '{key}'; known: {', '.join(registry)} (or a .toml file)")
    try:
        return path, tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise GyroInputError(f"{short} {path}: cannot read ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise GyroInputError(f"{short} {path}: not valid TOML ({str(exc).splitlines()[0]})") from None


def load_preset(name_or_path: str | Path | SensorSpec) -> SensorSpec:
    """Load a preset by registry name (``"icm42688p"``) or from a TOML file path.

    Raises
    ------
    GyroInputError
        Unknown name, unreadable file, or a file that breaks the preset format (one line).
    """
    if isinstance(name_or_path, SensorSpec):
        return name_or_path
    key = str(name_or_path)
    if key in _CACHE:
        return _CACHE[key]
    path, raw = read_registered_toml(key, PRESETS, what="sensor preset", short="preset")
    spec = _convert(raw, str(path))
    if key in PRESETS:  # registry files are cached; a user's file is re-read every time
        _CACHE[key] = spec
    return spec


def all_effects_overrides(without: tuple[str, ...] = ()) -> dict[str, dict]:
    """SI overrides (``SyntheticGyro(..., overrides=...)``) that switch on the catalogue effects
    the ICM-42688-P preset leaves off, at representative levels, so a gyro flies every effect
    (the benches' and the compiled-path tests' "all effects" gyro); ``without``: effects left off.
    """
    deg = math.pi / 180.0
    overrides = {
        "bias_temp_rate": {"k_rad_s_per_c_per_s": 0.01 * deg},
        "bias_ramp": {"ramp_rad_s2": 1e-6},
        "scale_asymmetry": {"a": 1e-3},
        "g2_sensitivity": {"g_rad_s_per_m2_s4": 1e-6},
        "time_offset": {"tau_s": 2e-4},
        "earth_rate": {"latitude_rad": 48.0 * deg, "heading_rad": 0.0},
        "rrw": {"k_rad_s_per_sqrt_s": 1e-5},
        "correlated": {"sigma_rad_s": 0.005 * deg, "tau_c_s": 30.0},
    }
    return {e: v for e, v in overrides.items() if e not in without}
