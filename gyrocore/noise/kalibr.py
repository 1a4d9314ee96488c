"""Kalibr's ``imu.yaml`` from a noise identification (noise density = N, random walk = K)."""

from __future__ import annotations

from typing import Mapping

from gyrocore.errors import GyroInputError

from .allan import AllanAnalysis, AllanResult

__all__ = ["kalibr_imu_yaml"]


def _kalibr_value(r: Mapping[str, AllanResult], name: str) -> tuple[float, bool]:
    """Largest axis value of a term (conservative scalar); (value, is_upper_bound)."""
    vals, upper = [], False
    for res in r.values():
        v = res.all_terms()[name]
        if v is None:
            v = res.interval(name)[1]
            upper = True
        vals.append(v)
    return float(max(vals)), upper


def kalibr_imu_yaml(analysis: AllanAnalysis, *, rostopic: str = "/imu0", inflate: float = 1.0) -> str:
    """Kalibr ``imu.yaml`` text from an Allan analysis.

    Kalibr's ``gyroscope_noise_density`` is the white-noise density N (rad/s/√Hz = rad/√s),
    the ``gyroscope_random_walk`` is the rate random walk K (rad/s²/√Hz = rad/s/√s) — NOT the
    bias instability B (rad/s), a common confusion. Kalibr takes one scalar per sensor; we
    write the largest axis. An unresolved K is replaced by the upper end of its 95 % interval
    (said in a comment). Kalibr's wiki recommends inflating static Allan values for motion
    (e.g. ×10 on the random walks); ``inflate`` multiplies every value and is recorded.
    """
    g = analysis.axes
    if not g:
        raise GyroInputError("no gyro axes in the Allan analysis")
    nd, nd_up = _kalibr_value(g, "arw_rad_per_sqrt_s")
    rw, rw_up = _kalibr_value(g, "rrw_rad_per_s_sqrt_s")
    lines = [
        "# Kalibr IMU noise model, written by gyroharness (gyrocore.noise.allan) from a static recording",
        f"# {analysis.n_samples} samples, {analysis.duration_s:.1f} s, mean rate {analysis.rate_hz:.6g} Hz; "
        f"values = largest axis of {','.join(g)}",
        f"# inflation factor applied to every value below: {inflate:g} "
        "(Kalibr recommends inflating static Allan values for dynamic use)",
        "#",
        "# gyroscope_noise_density = white rate noise N (Allan 1/sqrt(tau) slope at tau = 1 s)",
        "#   units rad/s/sqrt(Hz) = rad/sqrt(s)  (angle random walk; x 180/pi x 60 -> deg/sqrt(h))",
        "# gyroscope_random_walk  = rate random walk K (Allan +1/2 slope, read at tau = 3 s)",
        "#   units rad/s^2/sqrt(Hz) = rad/s/sqrt(s)  -- NOT the bias instability (rad/s, the flat floor)",
    ]
    if rw_up:
        lines.append("# gyroscope_random_walk: K not resolved by the data; the value is its 95 % upper bound")
    if nd_up:
        lines.append("# gyroscope_noise_density: N not resolved by the data; the value is its 95 % upper bound")
    if analysis.accel:
        and_, and_up = _kalibr_value(analysis.accel, "arw_rad_per_sqrt_s")
        arw, arw_up = _kalibr_value(analysis.accel, "rrw_rad_per_s_sqrt_s")
        lines += [
            "# accelerometer_noise_density: white noise, m/s^2/sqrt(Hz); accelerometer_random_walk: m/s^3/sqrt(Hz)",
        ]
        if and_up or arw_up:
            lines.append("# an accelerometer value not resolved by the data is its 95 % upper bound")
        lines += [
            f"accelerometer_noise_density: {and_ * inflate:.6e}",
            f"accelerometer_random_walk: {arw * inflate:.6e}",
        ]
    else:
        lines.append("# accelerometer_* not written: the recording has no accelerometer analysis (Kalibr needs them)")
    lines += [
        f"gyroscope_noise_density: {nd * inflate:.6e}",
        f"gyroscope_random_walk: {rw * inflate:.6e}",
        f"rostopic: {rostopic}",
        f"update_rate: {analysis.rate_hz:.6g}",
        "",
    ]
    return "\n".join(lines)
