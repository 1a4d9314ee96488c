"""``gyroharness firmware fly SCENARIO``: the MuJoCo vehicle flown by the firmware in lockstep
(:mod:`experiments.firmware_fly`, :mod:`sim.fw_flight`)."""

from __future__ import annotations

import click

from gyrocore.cli import emit_json

__all__ = ["command", "fidelity_command"]


@click.command("fly")
@click.argument("scenario", metavar="SCENARIO")
@click.option("--vehicle", default="racing25", show_default=True, help="Vehicle class (sim/vehicles.py).")
@click.option(
    "--set",
    "sets",
    multiple=True,
    metavar="NAME=VALUE",
    help="Firmware setting, its own CLI name (repeatable): --set gyro_lpf1_static_hz=150.",
)
@click.option(
    "--settings-from",
    type=click.Path(dir_okay=False),
    default=None,
    help="A blackbox log (its header) or a Betaflight `diff` file: the pilot's whole tune, applied first.",
)
@click.option(
    "--vibration",
    "vibration_spec",
    type=click.Path(dir_okay=False),
    default=None,
    help="Vibration spec (gyroharness vibration LOG -o SPEC): its rotor line through the rotors' unbalance, the "
    "rest of its band as the gyro's shaped vibration.",
)
@click.option("--vibration-band", default="middle", show_default=True, help="Spec band: index or 'middle'.")
@click.option("--sensor", default="icm42688p", show_default=True, help="Sensor preset or TOML file.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option(
    "--duration-s",
    type=float,
    default=3.0,
    show_default=True,
    help="Scored flight time, s (boot and arming are before it).",
)
@click.option("-o", "--out", "output", required=True, type=click.Path(dir_okay=False), help="Data file to write.")
@click.option("--json", "as_json", is_flag=True, help="Print the JSON result on stdout.")
def command(
    scenario, vehicle, sets, settings_from, vibration_spec, vibration_band, sensor, seed, duration_s, output, as_json
):
    """Fly SCENARIO (hover, steps) with the firmware's filters, PID and mixer in the loop; write OUT.

    OUT: the data file with the truth (ref_*), the synthetic gyro, the firmware's filtered gyro
    (fw_gyro_*_rad_s) and D-term input, motor outputs motor_1..4 (Betaflight order), rotor speeds,
    the pilot's set points and sticks. JSON: attitude error (hover, steps), motor-output noise above
    20 Hz, D-term noise, rate step rise/overshoot, the firmware's version and settings,
    sim_s_per_wall_s.
    """
    from experiments.firmware_fly import run
    from gyrocore.errors import GyroInputError
    from sim.fw_flight import SCENARIOS

    if scenario not in SCENARIOS:
        raise GyroInputError(f"unknown firmware flight scenario {scenario!r}; known: {', '.join(SCENARIOS)}")
    settings = []
    for s in sets:
        if "=" not in s:
            raise GyroInputError(f"--set {s!r}: expected NAME=VALUE")
        k, _, v = s.partition("=")
        settings.append((k.strip(), v.strip()))
    out = run(
        scenario=scenario,
        out=output,
        vehicle=vehicle,
        settings=settings,
        settings_from=settings_from,
        vibration_spec=vibration_spec,
        band=vibration_band,
        sensor=sensor,
        seed=seed,
        duration_s=duration_s,
    )
    if as_json:
        emit_json(out)
        return
    click.echo(
        f"{out['firmware']} flew {scenario} on {vehicle} for {duration_s:g} s "
        f"({out['sim_s_per_wall_s']:.2f} simulated s per wall s): {output}"
    )
    if out.get("crashed"):
        click.echo("crashed (tilt beyond 60 deg or a non-finite state)")
        return
    click.echo(
        f"hover attitude error RMS {out['hover_att_rms_deg']:.4f} deg; motor noise above 20 Hz "
        f"{100 * out['motor_noise_above_20hz']:.3f} % of full output"
    )
    if out.get("step_rise_ms") is not None and "steps" in out:
        click.echo(
            f"rate steps: rise {out['step_rise_ms']:.1f} ms, overshoot {out['step_overshoot_pct']:.1f} %; "
            f"attitude tracking RMS {out['step_track_rms_deg']:.3f} deg"
        )


@click.command("fidelity")
@click.argument("log", metavar="LOG", type=click.Path(dir_okay=False))
@click.option("--vehicle", default="racing25", show_default=True, help="Vehicle class standing in for the log's quad.")
@click.option("--bands", default=None, help="Comma-separated throttle band indices (default: all).")
@click.option("--duration-s", type=float, default=5.0, show_default=True, help="Hover per band, s (1 s settling).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--at-band-throttle", is_flag=True, help="Fly each band at its own motor command (a payload).")
@click.option(
    "--inject-to-nyquist",
    is_flag=True,
    help="Inject the band's spectrum up to the logged Nyquist (past the spec's reliable limit).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the JSON result on stdout.")
def fidelity_command(log, vehicle, bands, duration_s, seed, at_band_throttle, inject_to_nyquist, as_json):
    """The firmware's filtered gyro in simulated flight against LOG's own filtered gyro, per throttle band.

    The vibration spec comes from LOG's first half (its unfiltered gyro); the simulated hovers fly LOG's
    tune with it; held out = against the second half. Per axis: RMS above 40 Hz and the in-band fraction.
    """
    from experiments.firmware_fidelity import run, summary_table
    from gyrocore.errors import GyroInputError
    from sim.vehicles import get_vehicle

    get_vehicle(vehicle)
    try:
        sel = None if bands is None else {int(x) for x in bands.split(",")}
    except ValueError:
        raise GyroInputError(f"--bands {bands!r}: expected comma-separated integers") from None
    out = run(
        flight=log,
        vehicle=vehicle,
        seed=seed,
        duration_s=duration_s,
        bands=sel,
        at_band_throttle=at_band_throttle,
        inject_to_nyquist=inject_to_nyquist,
    )
    if as_json:
        emit_json(out)
        return
    click.echo(
        f"{out['flight']} flown by {out['firmware']} on {vehicle} ({len(out['settings_applied'])} settings from "
        f"its header); held out = the second half (t >= {out['t_split_s']:.1f} s)"
    )
    click.echo(summary_table(out))
