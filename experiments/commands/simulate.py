"""``gyroharness simulate``: write a simulated recording (the DESIGN.md data file)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import click
import numpy as np

from gyrocore.cli import emit_json
from gyrocore.errors import GyroInputError


def parse_set(items) -> dict[str, dict[str, np.ndarray]]:
    """``effect.param=value`` items -> ``{effect: {param: ndarray}}`` (SI, PARAM_SCHEMA names).

    Values are a number or a comma list; a list fills the parameter's shape row-major
    (e.g. 9 values for ``g_sensitivity.h_rad_s_per_m_s2``; 3·p values for a thermal
    polynomial ``(3, p)``). A single number broadcasts. The effect may be a registry family
    term, e.g. ``periodic[37.5].a_cos_rad_s=0.01,0,0`` (its name is canonicalised; the
    parameters it does not set are 0).
    """
    import re

    from gyrocore.effects.registry import PARAM_SCHEMA, check_effect_names

    out: dict[str, dict[str, np.ndarray]] = {}
    for item in items:
        key, _, text = item.partition("=")
        m = re.match(r"^\s*([^.\[\]=]+\[[^\]]*\]|[^.\[\]=]+)\s*\.\s*([^.]+?)\s*$", key) if _ else None
        if m is None:
            raise GyroInputError(
                f"--set expects effect.param=value (e.g. scale.s=0.01 or "
                f"periodic[37.5].a_cos_rad_s=0.01,0,0), got '{item}'"
            )
        (eff,) = check_effect_names([m.group(1)])
        pname = m.group(2)
        schema = PARAM_SCHEMA[eff]
        extra = ("turn_on_sigma_rad_s",) if eff == "bias" else ()
        if pname not in schema and pname not in extra:
            known = ", ".join(list(schema) + list(extra)) or "none"
            raise GyroInputError(f"effect {eff} has no parameter '{pname}'; parameters: {known}")
        try:
            vals = [float(v) for v in text.split(",") if v.strip() != ""]
        except ValueError:
            raise GyroInputError(f"--set {key}: '{text}' is not a number or a comma list of numbers") from None
        if not vals or not all(math.isfinite(v) for v in vals):
            raise GyroInputError(f"--set {key}: needs finite number(s), got '{text}'")
        shape = schema.get(pname, (3,))
        if len(vals) == 1:
            v = np.asarray(vals[0])
        elif "p" in shape:
            if len(vals) % 3:
                raise GyroInputError(
                    f"--set {key}: a thermal polynomial needs 3·p values (axis-major), got {len(vals)}"
                )
            v = np.asarray(vals).reshape(3, len(vals) // 3)
        else:
            size = int(np.prod(shape)) if shape else 1
            if len(vals) != size:
                raise GyroInputError(f"--set {key}: needs 1 or {size} values, got {len(vals)}")
            v = np.asarray(vals).reshape(shape)
        out.setdefault(eff, {})[pname] = v
    return out


#: Hover runs of at least this many samples compile the numba kernels in a child process first
#: (sim._fast.warm_cache_in_child: ~2 s with a warm cache; one million samples = 17 min at 1 kHz,
#: where the bounded-memory budget starts to matter).
_WARM_IN_CHILD_SAMPLES = 1_000_000


@click.command("simulate")
@click.argument("scenario")
@click.option(
    "-o",
    "--output",
    "output",
    required=True,
    type=click.Path(dir_okay=False),
    help="Data file to write (.parquet: Parquet, else CSV).",
)
@click.option(
    "--sensor",
    default="icm42688p",
    show_default=True,
    metavar="PRESET|FILE.toml",
    help="Sensor preset name or preset TOML file.",
)
@click.option("--duration-s", type=float, default=None, help="Length in seconds (default: the scenario's).")
@click.option("--seed", type=int, default=0, show_default=True, help="Sensor-unit and scenario seed (>= 0).")
@click.option(
    "--run",
    type=int,
    default=0,
    show_default=True,
    help="Session of the same unit: same parameters, new turn-on bias and noise.",
)
@click.option("--rate-hz", type=float, default=None, help="Gyro output rate, Hz (default: scenario, else preset).")
@click.option(
    "--set",
    "sets",
    multiple=True,
    metavar="EFFECT.PARAM=VALUE",
    help="Put an effect in with these SI values (even if the preset has it off); repeatable. "
    "VALUE is a number or a comma list, e.g. --set scale.s=0.01,0.02,-0.01. EFFECT may be a "
    "term outside the catalogue: --set 'periodic[37.5].a_cos_rad_s=0.01,0,0', "
    "'step[12.25].size_rad_s=2e-3,0,0', 'regressor[omega_y*omega_z].coef=1e-3,0,0'",
)
@click.option(
    "--without", "without", multiple=True, metavar="EFFECT", help="Switch an effect off; repeatable or comma-separated."
)
@click.option(
    "--vibration",
    "vibration_spec",
    default=None,
    type=click.Path(dir_okay=False),
    help="Vibration spec (gyroharness vibration -o): its band's measured gyro PSD enters as the registry effect "
    "`vibration` (shaped part, in the gyro's noise stage; a hover flies on it in closed loop).",
)
@click.option("--vibration-band", default="middle", show_default=True, help="Spec band: index or 'middle'.")
@click.option(
    "--vibration-physics",
    is_flag=True,
    help="hover + --vibration: the spec's rotor line enters through the rotor imbalance of the vehicle class "
    "(closed loop, at the commanded rotor speed; sim/spec_vibration.py) and only the rest of the spectrum "
    "(broadband, frame) is added as the shaped disturbance.",
)
@click.option(
    "--vehicle",
    default=None,
    metavar="CLASS",
    help="hover: vehicle class (f450, racing5; sim/vehicles.py), overriding the scenario's [hover] vehicle.",
)
@click.option(
    "--chunk-rows",
    type=click.IntRange(min=1),
    default=16_384,
    show_default=True,
    help="Rows generated and written per chunk (memory does not grow with --duration-s; the file is the "
    "same for any value).",
)
@click.option("--force", is_flag=True, help="Overwrite an existing output file.")
@click.option(
    "--progress/--no-progress",
    default=None,
    help="Progress bar on stderr (default: for long runs when stderr is a terminal).",
)
@click.option("--json", "as_json", is_flag=True, help="Print a JSON summary on stdout.")
def command(
    scenario,
    output,
    sensor,
    duration_s,
    seed,
    run,
    rate_hz,
    sets,
    without,
    vibration_spec,
    vibration_band,
    vibration_physics,
    vehicle,
    chunk_rows,
    force,
    progress,
    as_json,
):
    """Simulate SCENARIO with one sensor unit and write the recording (truth in the ref_ columns).

    Scenarios: static, static_bumped, turntable, thermal, hover, power_cycles (or a
    scenario TOML file). Effect and parameter names are those of the effect catalogue
    (DESIGN.md), values in SI units.
    """
    from gyrocore.effects.registry import check_effect_names
    from gyrocore.data.recording import file_sha256, write_chunks
    from sim import presets as P
    from sim import scenarios as S

    out = Path(output)
    if out.exists() and not force:
        raise GyroInputError(f"{out} exists; pass --force to overwrite it")
    if seed < 0 or run < 0:
        raise GyroInputError("--seed and --run must be >= 0")
    if rate_hz is not None and not (math.isfinite(rate_hz) and rate_hz > 0):
        raise GyroInputError(f"--rate-hz must be > 0, got {rate_hz}")
    if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
        raise GyroInputError(f"--duration-s must be > 0, got {duration_s}")
    spec = S.load_scenario(scenario)
    if vehicle is not None:
        from sim.vehicles import get_vehicle

        if spec.kind != "hover":
            raise GyroInputError(f"--vehicle applies to hover scenarios; {spec.name} is a {spec.kind} scenario")
        vehicle = get_vehicle(vehicle).name
    sensor_spec = P.load_preset(sensor)
    hover_vib, vib_over, vib_info = None, {}, None
    if vibration_physics and (not vibration_spec or spec.kind != "hover"):
        raise GyroInputError("--vibration-physics needs --vibration SPEC and a hover scenario")
    if vibration_spec:
        from gyrocore.flight.vibration import read_spec
        from sim.spec_vibration import spec_injection

        # the spec enters as the registry effect `vibration` (its shaped part, in the gyro's
        # noise stage: a hover's controller flies on it), and with --vibration-physics its rotor line
        # through the vehicle's rotor imbalance
        veh_name = vehicle or str(spec.hover.get("vehicle", "f450"))
        hover_vib, vib_over, vib_info = spec_injection(
            read_spec(vibration_spec), band=vibration_band, vehicle=veh_name, physics=vibration_physics, seed=int(seed)
        )
    wo = check_effect_names([w for item in without for w in item.split(",")])
    overrides = parse_set(sets)
    if vib_over:
        if "vibration" in overrides:
            raise GyroInputError("--vibration and --set vibration.* both give the shaped vibration; use one")
        overrides.update(vib_over)
    if progress is None:
        rate = rate_hz or spec.gyro_rate_hz or sensor_spec.rate_hz
        dur = duration_s or spec.duration_s or 300.0
        progress = sys.stderr.isatty() and (dur * rate > 200_000 or spec.kind == "hover" and dur * rate > 20_000)
    # every scenario generated and written chunk by chunk in bounded memory (the rate table
    # and the closed-loop hover flight alike); the same rows as the whole path S.simulate(...)
    # (16 384-row chunks; Parquet: one row group each, whose ~13 kB of metadata pyarrow's writer keeps
    # until the footer: +30 MiB per 1000 groups, measured — larger chunks cost more than they save)
    if spec.kind == "hover":
        rate = rate_hz or spec.gyro_rate_hz or sensor_spec.rate_hz
        if (duration_s or spec.duration_s or 0.0) * rate >= _WARM_IN_CHILD_SAMPLES:
            # the hover kernels compiled in a child (a cold numba cache costs this process ~50 MiB)
            from sim._fast import warm_cache_in_child

            warm_cache_in_child()
    res = S.simulate(
        spec,
        sensor=sensor_spec,
        duration_s=duration_s,
        seed=seed,
        run=run,
        overrides=overrides,
        without=wo,
        gyro_rate_hz=rate_hz,
        progress=bool(progress),
        vehicle=vehicle,
        hover_vibration=hover_vib,
        chunk_rows=chunk_rows,
    )
    meta = dict(res.meta)
    if vib_info is not None:
        import json as _json

        meta.update(
            vibration_spec=str(vibration_spec),
            vibration_injection=_json.dumps(vib_info, separators=(",", ":"), default=str),
        )
    n_samples = write_chunks(res.chunks(), out, overwrite=force, meta=meta)
    power_ups = len(json.loads(meta["power_up_t_s"]))
    summary = {
        "path": str(out),
        "sha256": file_sha256(out),
        "scenario": res.scenario,
        "sensor": res.sensor,
        "seed": res.seed,
        "run": res.run,
        "rate_hz": float(meta["rate_hz"]),
        "n_samples": n_samples,
        "duration_s": n_samples / float(meta["rate_hz"]),
        "power_ups": power_ups,
        "effects": meta["effects"].split(",") if meta["effects"] else [],
        "overridden": meta["overridden"].split(",") if meta["overridden"] else [],
        "without": meta["without"].split(",") if meta["without"] else [],
        "notes": list(res.notes),
        "params_true": res.params_true,
    }
    if as_json:
        emit_json(summary)
        return
    for note in res.notes:
        click.echo(f"note: {note}", err=True)
    click.echo(
        f"wrote {out}: scenario {res.scenario}, sensor {res.sensor}, seed {res.seed}"
        + (f", run {res.run}" if res.run else "")
        + f", {n_samples} samples at {summary['rate_hz']:g} Hz ({summary['duration_s']:g} s), "
        + f"{summary['power_ups']} power-up(s)"
    )
    click.echo(f"effects: {', '.join(summary['effects']) or 'none'}")
