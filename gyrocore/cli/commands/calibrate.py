"""``gyroharness calibrate``: fit catalogue effects against the references in a data file."""

from __future__ import annotations

import math
import os
import warnings

import click
import numpy as np

from gyrocore.cli import emit_json
from gyrocore.readers.large import is_large

D = 180.0 / math.pi


def _fmt(v, scale=1.0, p=5) -> str:
    a = np.atleast_1d(np.asarray(v, float)) * scale
    return "[" + ", ".join("—" if not np.isfinite(x) else f"{x:.{p}g}" for x in a.ravel()) + "]"


def report_text(res, params_path: str, px4_path: str | None) -> str:
    if res.method == "integral" and res.integral is not None:
        # n_samples of the integral method is the still samples the bias came from (0 with a bias
        # from outside the data): say what it counts
        nseg = int(np.asarray(res.integral.get("C_rad", np.zeros((3, 0)))).shape[1])
        what = (
            f"{nseg} known rotations, bias from {res.n_samples} still samples"
            if res.n_samples
            else f"{nseg} known rotations, bias from outside the data"
        )
    else:
        what = f"{res.n_samples} samples"
    lines = [
        f"calibrated {', '.join(res.effects)} on {res.source_file} ({res.method}, {what}, "
        f"standard errors: {res.covariance})",
    ]
    for eff, pd in res.params.items():
        for name, v in pd.items():
            se = res.stderr.get(eff, {}).get(name)
            se_txt = "" if se is None or not np.any(np.isfinite(se)) else f"  ± {_fmt(se, 1.0, 2)}"
            lines.append(f"  {eff}.{name} = {_fmt(v)}{se_txt}")
    if res.method == "integral" and not res.n_samples:
        lines.append("residual RMS: none (no still samples in this file; the bias came from outside it)")
    else:
        lines.append(f"residual RMS {_fmt(res.residual_rms_rad_s, D, 4)} deg/s")
    if res.thermal_order:
        lines.append(
            "thermal order " + ", ".join(f"{k}: {v}" for k, v in res.thermal_order.items()) + " (chosen from the data)"
            if res.thermal_tests
            else "thermal order " + ", ".join(f"{k}: {v}" for k, v in res.thermal_order.items())
        )
    if res.unobservable:
        lines.append(f"UNOBSERVABLE (not fitted, left uncorrected): {len(res.unobservable)} parameter(s)")
        for u in res.unobservable:
            lines.append(f"  {u}: {res.unobservable_reason.get(u, '')}")
    for n in res.notes:
        lines.append(f"note: {n}")
    if res.integral is not None:
        M = np.asarray(res.integral["M"])
        lines.append("article form M = C·B⁻¹ (true angle = M · integrated bias-free output):")
        for row in M:
            lines.append("  " + "  ".join(f"{x:+.5f}" for x in row))
    lines.append(f"wrote {params_path}" + (f" and {px4_path}" if px4_path else ""))
    return "\n".join(lines)


def _three(text: str, what: str) -> np.ndarray:
    from gyrocore.errors import GyroInputError

    try:
        v = np.array([float(x) for x in str(text).split(",")])
    except ValueError:
        v = np.array([])
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise GyroInputError(f"{what} needs three comma-separated numbers x,y,z, got {text!r}")
    return v


def external_bias(bias_from: str | None, bias_dps: str | None, bias_se_dps: str, arw_dps_rt_hz: float):
    """The external bias of ``--bias-from`` / ``--bias-dps`` (None when neither is given).

    ``--bias-from``: :class:`gyrocore.calib.bias.StaticBiasCalibrator` (default gate, first still
    window) on the static recording → bias, standard error and long-run noise.
    ``--bias-dps``: the given bias, standard error and white-noise density (N² per second).
    """
    from gyrocore.errors import GyroInputError

    if bias_from and bias_dps:
        raise GyroInputError("give --bias-from or --bias-dps, not both")
    if bias_from:
        from gyrocore.calib.bias import StaticBiasCalibrator
        from gyrocore.data.recording import read_recording

        return StaticBiasCalibrator().fit(read_recording(bias_from, columns=()))
    if bias_dps:
        if not (math.isfinite(arw_dps_rt_hz) and arw_dps_rt_hz >= 0):
            raise GyroInputError(f"--arw-dps-rt-hz must be >= 0, got {arw_dps_rt_hz}")
        se = _three(bias_se_dps, "--bias-se-dps")
        if np.any(se < 0):
            raise GyroInputError("--bias-se-dps must be >= 0")
        return {
            "bias_rad_s": _three(bias_dps, "--bias-dps") / D,
            "bias_stderr_rad_s": se / D,
            "noise_lr_rad2_s": np.full(3, (arw_dps_rt_hz / D) ** 2),
        }
    return None


@click.command("calibrate")
@click.argument("file", type=click.Path())  # a data file or any source `convert` reads (folders too)
@click.option(
    "--effects", "effects", required=True, help="comma-separated catalogue effects, e.g. bias,scale,misalignment"
)
@click.option(
    "-o", "--output", "output", required=True, type=click.Path(dir_okay=False), help="parameter file (JSON) to write"
)
@click.option(
    "--segments",
    type=click.Path(dir_okay=False),
    default=None,
    help="segments file of known rotations (t_start_s,t_end_s,kind,angle_x_deg,angle_y_deg,angle_z_deg) "
    "-> the integral method M = C·B⁻¹",
)
@click.option(
    "--bias-from",
    type=click.Path(dir_okay=False),
    default=None,
    help="integral method: take the bias (and its standard error, and the noise) from this static recording "
    "of the same session (gyrocore.calib.bias.StaticBiasCalibrator) — for turns without a still part",
)
@click.option("--bias-dps", default=None, help="integral method: the bias x,y,z in deg/s, known from elsewhere")
@click.option(
    "--bias-se-dps", default="0,0,0", show_default=True, help="with --bias-dps: its standard error x,y,z, deg/s"
)
@click.option(
    "--arw-dps-rt-hz",
    type=float,
    default=0.0,
    show_default=True,
    help="with --bias-dps: white rate noise density N, deg/s/sqrt(Hz), for the noise of each integral",
)
@click.option(
    "--angle-sigma-deg",
    type=float,
    default=0.0,
    show_default=True,
    help="integral method: uncertainty of each known rotation's angle, deg (a turn by hand: 2-5), "
    "propagated into the standard errors",
)
@click.option(
    "--axis-sigma-deg",
    type=float,
    default=0.0,
    show_default=True,
    help="integral method: uncertainty of each known rotation's axis direction, deg (by hand: ~5)",
)
@click.option(
    "--poses",
    is_flag=True,
    help="multi-pose method (Tedaldi et al. 2014, IMU-TK): bias, scale, misalignment from the turns between "
    "still poses, each pose's gravity direction (accel) as the reference; no rate reference needed",
)
@click.option(
    "--pose-std-factor",
    type=float,
    default=5.0,
    show_default=True,
    help="with --poses: a still pose may scatter up to this many times the rest noise (hand-held poses tremble: 10)",
)
@click.option("--thermal-order", default="auto", show_default=True, help="auto (chosen from the data, up to 3) or 1..3")
@click.option(
    "--covariance",
    type=click.Choice(["auto", "ols", "hac", "newey_west", "block", "noise_model"]),
    default="auto",
    show_default=True,
    help="standard errors: auto switches to hac when the residual is coloured; noise_model: sandwich with "
    "the noise model identified (GMWM) on the fit residual",
)
@click.option(
    "--ramp-margin-s",
    type=click.FloatRange(min=0.0),
    default=0.0,
    show_default=True,
    help="leave out samples within this time of a reference-rate change (the gyro filter's transient)",
)
@click.option(
    "--px4-params",
    type=click.Path(dir_okay=False),
    default=None,
    help="also write PX4 TC_G0_* thermal parameters (QGC .params) — needs bias_thermal",
)
@click.option(
    "--px4-device-id",
    type=click.IntRange(min=1),
    default=None,
    help="with --px4-params: TC_G0_ID, the gyro's PX4 device id (CAL_GYRO0_ID in the vehicle's parameters); "
    "PX4 applies the TC_G0 set only to the gyro with that id",
)
@click.option("--sensor", default=None, help="sensor name for the parameter file (default: file metadata)")
@click.option("--force", is_flag=True, help="overwrite existing output files")
@click.option("--json", "as_json", is_flag=True, help="print JSON only (the parameter file's content)")
def command(
    file,
    effects,
    output,
    segments,
    bias_from,
    bias_dps,
    bias_se_dps,
    arw_dps_rt_hz,
    angle_sigma_deg,
    axis_sigma_deg,
    poses,
    pose_std_factor,
    thermal_order,
    covariance,
    ramp_margin_s,
    px4_params,
    px4_device_id,
    sensor,
    force,
    as_json,
):
    """Fit the named effects against the references in FILE (reference rates, a reference
    attitude, known-angle segments, or still parts) and write the parameter file."""
    from gyrocore.effects.registry import check_effect_names
    from gyrocore.errors import GyroInputError
    from gyrocore.calibrator import Calibrator

    names = check_effect_names(effects.split(","))
    for p in [output] + ([px4_params] if px4_params else []):
        if os.path.exists(p) and not force:
            raise GyroInputError(f"{p} exists; pass --force to overwrite it")
    if thermal_order != "auto":
        try:
            thermal_order = int(thermal_order)
        except ValueError:
            raise GyroInputError(f"--thermal-order must be auto or 1..3, got {thermal_order!r}") from None
    if px4_device_id is not None and not px4_params:
        raise GyroInputError("--px4-device-id goes with --px4-params")
    if px4_params and "bias_thermal" not in names:
        raise GyroInputError(
            "--px4-params needs bias_thermal among the effects (PX4 TC_G is a bias polynomial of temperature)"
        )
    if (bias_from or bias_dps) and not segments:
        raise GyroInputError("--bias-from/--bias-dps are for the integral method: give --segments too")
    ext = external_bias(bias_from, bias_dps, bias_se_dps, arw_dps_rt_hz)
    if poses and segments:
        raise GyroInputError("--poses and --segments are two methods: give one")
    if not segments and not poses and is_large(file, "calibrate", need=("ref_rate",)):
        # a long data file with reference rates: spilled to per-column files and fitted a
        # window at a time (the least-squares method's one path); the same fit as in memory
        import tempfile

        from gyrocore.data.spill import spill_columns

        cal = Calibrator(
            effects=names,
            thermal_order=thermal_order,
            covariance=covariance,
            sensor=sensor,
            ramp_margin_s=ramp_margin_s,
        )
        with tempfile.TemporaryDirectory(prefix="gyroharness_calibrate_") as tmp:
            store = spill_columns(file, tmp, accel=True, groups=("temp", "ref_rate"))
            res = cal.fit(store, source_path=file)
        _warn_unobservable(res)
        _write_and_report(res, output, px4_params, as_json, px4_device_id=px4_device_id)
        return
    rec, segments = _read_with_known_rotations(file, segments, poses)
    # (a reference attitude and no reference rate: Calibrator.fit fits against the attitude)
    if (angle_sigma_deg or axis_sigma_deg) and not segments:
        raise GyroInputError("--angle-sigma-deg/--axis-sigma-deg are for the integral method: give --segments too")
    cal = Calibrator(
        effects=names,
        thermal_order=thermal_order,
        segments=segments,
        covariance=covariance,
        sensor=sensor,
        external_bias=ext,
        ramp_margin_s=ramp_margin_s,
        angle_sigma_deg=angle_sigma_deg,
        axis_sigma_deg=axis_sigma_deg,
        poses=poses,
        pose_std_factor=pose_std_factor,
    )
    res = cal.fit(rec, source_path=file)
    if segments and res.integral is not None and not (angle_sigma_deg or axis_sigma_deg):
        from dataclasses import replace

        # the integral method's covariance propagates gyro noise and bias (rotations.integral_calibration);
        # the known angles enter as exact unless their uncertainty is given
        res = replace(
            res,
            notes=tuple(res.notes)
            + (
                "standard errors: gyro noise and bias only, the segments' angles taken as exact; a turn by hand "
                "(±2-5 deg over 360-720 deg, 0.3-1.4 %) is far less certain than the scale SEs above: give "
                "--angle-sigma-deg/--axis-sigma-deg to include it",
            ),
        )
    _warn_unobservable(res)
    _write_and_report(res, output, px4_params, as_json, px4_device_id=px4_device_id)


def _read_with_known_rotations(file, segments, poses):
    """The recording, and the segments the integral method uses: ``--segments`` when given; else
    the known rotations of a source whose reader defines them (imucal's x/y/z_rot, a joined
    sunsided session), when they turn about all three axes (what the method needs) — said in one
    warning; a source with turns about fewer axes keeps its other references, and the warning
    says how to use the turns."""
    from gyrocore.readers.convert import detect_format, load_with_segments, read_any

    if segments or poses or detect_format(file) in ("csv", "parquet"):
        return read_any(file), segments  # a data file, or the user chose the method
    conv = load_with_segments(file)
    turns = [sg for sg in conv.segments if sg.kind == "rotation"]
    if not turns:
        return conv.recording, segments
    axes = {int(np.argmax(np.abs(sg.angle_S_deg))) for sg in turns}
    what = "; ".join(sg.label or f"{sg.t_start_s:g}-{sg.t_end_s:g} s" for sg in turns)
    if len(axes) == 3:
        warnings.warn(
            f"{conv.format}: calibrating against the {len(turns)} known rotations its reader defines ({what}), "
            f"the integral method (--segments FILE or --poses chooses otherwise)",
            UserWarning,
            stacklevel=2,
        )
        return conv.recording, list(turns)
    warnings.warn(
        f"{conv.format}: its known rotations ({what}) turn about {len(axes)} axis/axes; the integral method needs "
        f"all three, so they are not used (join a session's turns: gyroharness convert ... --append ... "
        f"--segments-out SEG.csv, then calibrate --segments SEG.csv)",
        UserWarning,
        stacklevel=2,
    )
    return conv.recording, segments


def _warn_sign(res) -> None:
    """A scale below −50 % (K_ii = 1 + s < 0.5, typically ≈ −1) is not a sensitivity error: the
    axis reads against the reference (a flipped axis, or the known angles' sign convention — imucal's
    expected_angle −360° on turns that integrate positive); say so in one warning line."""
    s = res.params.get("scale", {}).get("s")
    if s is None:
        return
    s = np.asarray(s, float)
    bad = [f"{'xyz'[i]} {100 * v:+.0f} %" for i, v in enumerate(s) if np.isfinite(v) and v < -0.5]
    if bad:
        warnings.warn(
            f"scale {', '.join(bad)}: K_ii = 1 + s is negative, i.e. the axis reads against the reference — a flipped "
            f"axis or the reference's sign convention (segments' angle signs, frame), not a sensitivity error",
            UserWarning,
            stacklevel=3,
        )


def _warn_unobservable(res) -> None:
    _warn_sign(res)
    if res.unobservable:
        # one line on stderr (the CLI prints "warning: ..."); stdout (and --json) unchanged
        warnings.warn(
            f"{len(res.unobservable)} parameter(s) unobservable from this data, not fitted and left uncorrected: "
            + ", ".join(res.unobservable),
            UserWarning,
            stacklevel=3,
        )


def _write_and_report(res, output, px4_params, as_json: bool, *, px4_device_id: int | None = None) -> None:
    """Write the parameter file (and PX4 TC_G parameters), then print the report or the JSON."""
    from gyrocore.calib.params import result_to_dict, save_params

    save_params(res, output, overwrite=True)
    if px4_params:
        from gyrocore.calib.thermal import write_px4_params

        write_px4_params(px4_params, res.params, overwrite=True, device_id=px4_device_id or 0)
        if not px4_device_id:
            warnings.warn(
                f"{px4_params}: TC_G0_ID is 0, which matches no gyro: PX4 will not apply these parameters "
                "until TC_G0_ID is your gyro's device id (CAL_GYRO0_ID; or calibrate --px4-device-id ID)",
                UserWarning,
                stacklevel=2,
            )
    if as_json:
        emit_json(result_to_dict(res))
    else:
        click.echo(report_text(res, output, px4_params))
