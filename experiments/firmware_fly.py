"""``gyroharness firmware fly``: one closed-loop flight with the firmware in the loop, scored
(the flight itself is :func:`sim.fw_flight.fly_firmware`).

The firmware is booted with the settings (CLI ``set`` lines, a ``diff`` file or a blackbox log's
header, through the bridge), armed (boot and arming before t = 0, not scored), and flies the
scenario; the flight is written as a data file and scored (:meth:`sim.fw_flight.FwFlightLog.scores`).
"""

from __future__ import annotations

import math
import os
from dataclasses import replace
from typing import Mapping, Sequence

from gyrocore.errors import GyroInputError
from gyrocore.data.recording import write_csv
from gyrocore.flight.vibration import read_spec
from sim.firmware.bridge import BetaflightSITL
from sim.firmware.build import ensure_binary, find_binary, FirmwareBinary
from sim.firmware.settings import settings_from_file
from sim.fw_flight import fly_firmware, FwFlightOptions, RateProfile, to_recording
from sim.gyro import SyntheticGyro
from sim.spec_vibration import spec_injection
from sim.vehicles import get_vehicle

__all__ = ["BOOT_MAX_S", "FIRMWARES", "boot_still_source", "fly", "run", "settings_dict"]

FIRMWARES = ("betaflight",)


def settings_dict(settings: Sequence[tuple[str, str]] | Mapping[str, str]) -> dict[str, str]:
    """``{name: value}`` (lower-case names, last one wins) of settings given as pairs or a mapping."""
    items = settings.items() if isinstance(settings, Mapping) else settings
    return {str(k).strip().lower(): str(v).strip() for k, v in items}


def _flight_options(opts, settings: Mapping[str, str]):
    """``opts`` with the pilot's view of the firmware's settings: its rate curve, idle, min_check."""
    s = settings_dict(settings)
    try:
        idle = float(s.get("dshot_idle_value", "550")) / 10000.0
        mincheck = int(float(s.get("min_check", "1050")))
    except ValueError as exc:
        raise GyroInputError(f"firmware setting not a number: {exc}") from None
    return replace(opts, rates=RateProfile.from_settings(s), idle_fraction=idle, mincheck_us=mincheck)


def _lines(settings) -> list[str]:
    """CLI lines (``set NAME = VALUE``, or a line as given: ``aux …``, ``feature …``)."""
    if isinstance(settings, Mapping):
        settings = list(settings.items())
    out = []
    for x in settings:
        if isinstance(x, str):
            out.append(x.strip())
        else:
            k, v = x
            out.append(f"set {str(k).strip()} = {str(v).strip()}")
    return [x for x in out if x]


def _pairs(lines: Sequence[str]) -> dict[str, str]:
    """``{name: value}`` of the ``set`` lines (last one wins)."""
    out = {}
    for ln in lines:
        s = ln.strip()
        if s.lower().startswith("set "):
            s = s[4:]
        elif "=" not in s or s.split(None, 1)[0].lower() in ("aux", "feature", "profile", "rateprofile", "map"):
            continue
        k, _, v = s.partition("=")
        out[k.strip().lower()] = v.strip()
    return out


def boot_still_source(opts):
    """The still vehicle's gyro during the firmware's boot (its motion-gated gyro calibration):
    the same sensor unit and power-up as the flight (same turn-on bias), specific force (0, 0, g),
    25 °C; None for a perfect gyro."""
    if opts.sensor is None:
        return None
    import numpy as np

    g = SyntheticGyro(
        opts.sensor,
        rate_hz=opts.loop_rate_hz,
        seed=opts.seed,
        overrides={k: v for k, v in dict(opts.gyro_overrides or {}).items() if k != "vibration"} or None,
    )
    n = int(round(BOOT_MAX_S * opts.loop_rate_hz))
    st = g.stream(n)
    zero, f = np.zeros(3), np.array([0.0, 0.0, 9.80665])
    dt = 1.0 / opts.loop_rate_hz

    def still(k):
        return st.step(k, k * dt, zero, f, 25.0).copy(), f

    return still


#: simulated-time limit of the firmware's boot (gyro calibration and arming), s
BOOT_MAX_S = 20.0


def fly(opts, settings=(), *, lenient=(), binary=None, step_timeout_s: float | None = None):
    """Boot the firmware with ``settings``, fly ``opts`` (:class:`sim.fw_flight.FwFlightOptions`).

    ``settings``: CLI lines or (name, value) pairs, applied last; a name the firmware does not have
    is an error. ``lenient``: lines from a log header or a diff (applied first; names this SITL
    lacks are skipped with a warning). ``binary``: a
    :class:`sim.firmware.build.FirmwareBinary`, a path, or None (the cached build, built if missing).
    Returns ``(FwFlightLog, info)``; ``info`` has ``firmware`` (name and version), ``settings``
    (the ``set`` lines applied), ``boot`` (the firmware's boot: simulated s, its gyro-calibration
    bias estimate against the unit's true turn-on bias) and ``sim_s_per_wall_s`` of the flight loop.
    """
    lines, soft = _lines(settings), _lines(lenient)
    fb = binary if isinstance(binary, FirmwareBinary) else (ensure_binary() if binary is None else _record_of(binary))
    path = fb.binary if fb is not None else str(binary)
    label = f"{fb.firmware} {fb.version}" if fb is not None else "betaflight"
    opts = _flight_options(opts, _pairs(soft + lines))
    kw = {} if step_timeout_s is None else {"step_timeout_s": step_timeout_s}
    with BetaflightSITL(path, settings=lines, lenient_settings=soft, loop_rate_hz=opts.loop_rate_hz, **kw) as fw:
        rep = fw.boot(boot_still_source(opts), max_boot_s=BOOT_MAX_S)
        meta = {
            "firmware": label,
            "firmware_settings": "; ".join(soft + lines) or "defaults",
            "firmware_boot_s": f"{rep.sim_s:.6g}",
        }
        log = fly_firmware(opts, fw, fw_meta=meta)
        skipped = list(fw.skipped_settings)
    boot = {
        "sim_s": rep.sim_s,
        "calibration_steps": rep.calibration_steps,
        "fw_gyro_bias_estimate_rad_s": [float(x) for x in rep.gyro_bias_S_rad_s],
    }
    if opts.sensor is not None:
        b0 = SyntheticGyro(opts.sensor, rate_hz=opts.loop_rate_hz, seed=opts.seed).power_up_bias(0)
        boot["true_turn_on_bias_rad_s"] = [float(x) for x in b0]
        boot["bias_estimate_error_rad_s"] = [float(a - b) for a, b in zip(rep.gyro_bias_S_rad_s, b0)]
    info = {
        "firmware": label,
        "settings": soft + lines,
        "skipped_settings": skipped,
        "boot": boot,
        "sim_s_per_wall_s": float(opts.duration_s / log.wall_s) if log.wall_s > 0 else math.nan,
    }
    return log, info


def _record_of(path):
    """The build record (name, version) of a binary given by its path, when it is the cached build."""
    from pathlib import Path

    fb = find_binary()
    return fb if fb is not None and Path(fb.binary).resolve() == Path(str(path)).resolve() else None


def run(
    *,
    scenario: str,
    out: str | os.PathLike,
    vehicle: str = "racing25",
    settings=(),
    settings_from=None,
    vibration_spec=None,
    band="middle",
    sensor: str = "icm42688p",
    seed: int = 0,
    duration_s: float = 3.0,
    loop_rate_hz: float = 8000.0,
    n_calib: int = 16,
    binary=None,
) -> dict:
    """The ``fly`` command: fly, write ``out`` (data file), return the JSON dict."""
    get_vehicle(vehicle)  # an unknown class is one error line before the firmware starts
    soft = settings_lines_from(settings_from)
    over, hover_vib, vib_info = None, True, None
    if vibration_spec is not None:
        hv, over, vib_info = spec_injection(
            read_spec(vibration_spec), band=band, vehicle=vehicle, physics=True, seed=int(seed), n_calib=n_calib
        )
        hover_vib = hv if hv is not None else True
    opts = FwFlightOptions(
        scenario=scenario,
        vehicle=vehicle,
        duration_s=float(duration_s),
        seed=int(seed),
        sensor=sensor,
        loop_rate_hz=float(loop_rate_hz),
        vibration=hover_vib,
        gyro_overrides=over,
    )
    log, info = fly(opts, settings, lenient=soft, binary=binary)
    rec = to_recording(log)
    if vib_info is not None:
        rec.meta["vibration_spec"] = f"{vib_info.get('spec', '')} band {band}"
    write_csv(rec, out)
    scores = log.scores(opts.settle_s)
    return {
        "out": str(out),
        "scenario": scenario,
        "vehicle": vehicle,
        "sensor": sensor,
        "seed": int(seed),
        "duration_s": float(duration_s),
        "loop_rate_hz": float(loop_rate_hz),
        **info,
        **scores,
        "units": {
            "motor_noise_above_20hz": "fraction of full motor output (RMS above 20 Hz, hover)",
            "hover_att_rms_deg": "deg, true vs commanded attitude over the steady hover",
            "step_rise_ms": "ms, 10-90 % of the rate steps (roll/pitch median)",
            "dterm_noise_above_20hz": "the bridge's D-term unit, RMS above 20 Hz in hover",
        },
    }


def settings_lines_from(settings_from) -> list[str]:
    """CLI lines from a blackbox log's header or a ``diff`` file (empty when None), through the
    bridge's translation to the SITL's names (:func:`sim.firmware.settings.settings_from_file`);
    what it could not carry over is warned about, one line each."""
    if settings_from is None:
        return []
    import warnings

    fs = settings_from_file(settings_from)
    for note in fs.notes:
        warnings.warn(f"{fs.source}: {note}", stacklevel=2)
    return list(fs.lines)
