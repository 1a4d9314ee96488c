"""``gyroharness filter-closed-loop FLIGHT``: the gyro filter chosen by flying the candidates in the
simulator with the flight's own vibration (:mod:`experiments.flight_filter`).

JSON keys as ``gyroharness filter`` (DESIGN.md "Flight logs and vibration"): ``recommended``,
``as_flown``, ``defaults`` ({filter, cutoff_hz, notches_hz, attitude_cost, delay_ms, motor_noise}),
``firmware`` (Betaflight ``set`` lines, PX4 ``IMU_GYRO_CUTOFF``, ArduPilot ``INS_GYRO_FILTER``);
plus ``picks_per_seed``, ``stable`` and every chain's scores (mean and SD over the seeds).
"""

from __future__ import annotations

import click

from gyrocore.cli import emit_json
from gyrocore.errors import GyroInputError


@click.command("filter-closed-loop")
@click.argument("path", metavar="FLIGHT", type=click.Path(path_type=str))
@click.option("--vehicle", default="racing25", show_default=True, help="Vehicle class flown (sim/vehicles.py).")
@click.option(
    "--seeds", type=int, default=3, show_default=True, help="Noise seeds (gyro noise, rotor phases, shaped draw)."
)
@click.option("--duration-s", type=float, default=8.0, show_default=True, help="Length of each flight, s.")
@click.option(
    "--band", default="middle", show_default=True, help="Throttle band of the flight's spec: index or 'middle'."
)
@click.option(
    "--firmware",
    type=click.Choice(["betaflight"]),
    default=None,
    help="Fly the candidates with the firmware in the loop (lockstep SITL, `gyroharness firmware build` first): "
    "the pilot's whole tune from the log's header, each candidate as set lines over it.",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="--firmware: local worker processes for the seeds (Monte Carlo).",
)
@click.option("--scheduler", default=None, help="--firmware: a Dask scheduler address for the seeds.")
@click.option("--json", "as_json", is_flag=True, help="Print the JSON result on stdout.")
def command(path, vehicle, seeds, duration_s, band, firmware, workers, scheduler, as_json):
    """Fly every candidate gyro filter chain with FLIGHT's vibration and recommend one, stable across seeds."""
    from experiments.flight_filter import print_table, run
    from sim.vehicles import get_vehicle

    get_vehicle(vehicle)  # an unknown class is one error line
    if seeds < 1:
        raise GyroInputError("--seeds must be >= 1")
    if not duration_s >= 3.0:
        raise GyroInputError("--duration-s must be >= 3 (1 s settling + the attitude steps)")
    if firmware is not None:
        from experiments import firmware_filter as F

        out = F.run(
            flight=path,
            vehicle=vehicle,
            seeds=tuple(range(seeds)),
            duration_s=duration_s,
            band=band,
            workers=workers,
            scheduler=scheduler,
        )
        if as_json:
            emit_json(out)
        else:
            F.print_table(out)
        return
    out = run(flight=path, vehicle=vehicle, seeds=tuple(range(seeds)), duration_s=duration_s, band=band)
    if as_json:
        emit_json({k: v for k, v in out.items() if k != "per_seed"})
        return
    print_table(out)
