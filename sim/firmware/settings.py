"""Firmware settings as Betaflight CLI lines: from ``--set K=V``, a ``diff`` file or a log header.

Every function returns CLI lines for :class:`~sim.firmware.bridge.BetaflightSITL` (which applies
them in order; ``skip_unknown`` decides whether a name this firmware lacks is an error). Enum
settings may carry the lookup index a blackbox header logs (``gyro_lpf1_type = 0``): the bridge
asks the firmware for the allowed names and uses the one at that index.

The blackbox header of a pilot's log (Betaflight 3.1 … 4.x) is translated to the SITL's 4.6.0
names: PIDs, feedforward and D-max (D-min before 4.5), rates, TPA, the gyro filter chain (static
and dynamic low-passes, static notches, dynamic notch, RPM filter), the D-term filters, and the
PID loop rate (``pid_process_denom`` so the PID runs at the log's PID rate on the SITL's 8 kHz
gyro). What is not translated is listed in the returned notes (the caller prints them).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

from gyrocore.errors import GyroInputError

__all__ = ["FirmwareSettings", "parse_set_args", "settings_from_diff", "settings_from_blackbox", "settings_from_file"]

_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
_AXES = ("roll", "pitch", "yaw")


@dataclass(frozen=True)
class FirmwareSettings:
    """CLI lines and where they came from.

    Attributes
    ----------
    lines : tuple of str
        Betaflight CLI lines in order.
    source : str
        ``"--set"``, ``"diff FILE"`` or ``"blackbox FILE (Betaflight X.Y.Z)"``.
    notes : tuple of str
        What was not carried over, and why (one line each).
    lenient : bool
        True for files from another board: names this SITL lacks are skipped (with a warning).
    """

    lines: tuple[str, ...]
    source: str
    notes: tuple[str, ...] = field(default=())
    lenient: bool = False


def parse_set_args(pairs: Sequence[str]) -> FirmwareSettings:
    """``["gyro_lpf1_static_hz=150", ...]`` → ``set gyro_lpf1_static_hz = 150`` lines (strict)."""
    lines = []
    for p in pairs:
        if "=" not in p:
            raise GyroInputError(
                f"--set {p!r}: expected NAME=VALUE (a Betaflight setting, e.g. gyro_lpf1_static_hz=150)"
            )
        k, v = (s.strip() for s in p.split("=", 1))
        if not _NAME.match(k) or not v:
            raise GyroInputError(f"--set {p!r}: expected NAME=VALUE with a lower-case setting name")
        lines.append(f"set {k} = {v}")
    return FirmwareSettings(tuple(lines), "--set")


#: CLI commands of a ``diff``/``dump`` that configure flight behaviour (kept); board- and
#: hardware-specific ones (resource, timer, dma, serial, board_name, mcu_id, …) are dropped.
_DIFF_KEEP = ("set ", "feature ", "aux ", "profile ", "rateprofile ", "adjrange ", "rxrange ")
_DIFF_DROP_SET = re.compile(
    r"^set\s+(osd_|vtx_|serialrx_|gyro_\d_|acc_\d_|mag_|baro_|blackbox_device|"
    r"motor_pwm_protocol|motor_pwm_rate|dshot_burst|dshot_bitbang|gyro_to_use|"
    r"gyro_hardware_lpf|align_board|current_meter|battery_meter|ibata_|vbat_|"
    r"pinio_|ledstrip_|beeper_|name\b|craft_name|pilot_name|display_name)"
)


def settings_from_diff(path: str | os.PathLike) -> FirmwareSettings:
    """The flight-relevant lines of a Betaflight ``diff`` (or ``diff all``/``dump``) file."""
    p = Path(path)
    try:
        text = p.read_text(errors="replace")
    except OSError as exc:
        raise GyroInputError(f"{path}: {exc.strerror or exc}") from None
    lines, dropped = [], 0
    for raw in text.splitlines():
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        low = s.lower()
        if low.startswith(_DIFF_KEEP) and not _DIFF_DROP_SET.match(low):
            lines.append(s)
        else:
            dropped += 1
    if not lines:
        raise GyroInputError(f"{path}: no 'set'/'feature'/'aux'/'profile' lines: not a Betaflight diff")
    notes = (
        (
            f"{dropped} board/hardware line(s) of the diff not applied (resources, serial, OSD, "
            f"motor protocol, batch/save …)",
        )
        if dropped
        else ()
    )
    return FirmwareSettings(tuple(lines), f"diff {p.name}", notes, lenient=True)


def _first(h: dict, *keys):
    for k in keys:
        if k in h and h[k] is not None:
            return h[k]
    return None


def _as_list(v) -> list | None:
    if v is None:
        return None
    if isinstance(v, (list, tuple)):
        return list(v)
    if isinstance(v, str) and "," in v:
        return [int(x) if re.fullmatch(r"-?\d+", x.strip()) else x.strip() for x in v.split(",")]
    return [v]


def settings_from_blackbox(path: str | os.PathLike, *, log_index: int | None = None) -> FirmwareSettings:
    """The pilot's tune from a Betaflight blackbox log header, as 4.6.0 CLI lines.

    Parameters
    ----------
    path : path
        .bbl/.bfl/.txt blackbox file (read with :func:`gyrocore.readers.blackbox.read_blackbox_logs`).
    log_index : int or None
        1-based log of the file (default: the first).
    """
    from gyrocore.readers.blackbox import read_blackbox_logs
    from gyrocore.readers.blackbox_firmware import firmware_info, loop_rates

    p = Path(path)
    logs = read_blackbox_logs(p, log_index=log_index)
    if not logs:
        raise GyroInputError(f"{path}: no log in the file")
    h = logs[0].headers
    fw = firmware_info(h, p.name)
    if fw.name == "inav":
        raise GyroInputError(f"{path}: an INAV log; its settings do not map onto Betaflight")
    v = fw.version
    out: list[str] = []
    notes: list[str] = []

    def put(name: str, value) -> None:
        if value is None:
            return
        out.append(f"set {name} = {value}")

    # --- PID loop rate: the SITL's gyro is 8 kHz; run the PID at the log's PID rate
    rates = loop_rates(h, fw)
    gyro_hz, pid_hz = float(rates.get("gyro_hz", float("nan"))), float(rates.get("pid_hz", float("nan")))
    if pid_hz == pid_hz and pid_hz > 0:
        denom = 8000.0 / pid_hz
        if abs(denom - round(denom)) < 1e-6 and 1 <= round(denom) <= 16:
            put("pid_process_denom", int(round(denom)))
        else:
            notes.append(f"PID rate {pid_hz:g} Hz is not 8 kHz / an integer: pid_process_denom left at 1")
    if gyro_hz == gyro_hz and abs(gyro_hz - 8000.0) > 1:
        notes.append(
            f"the log's gyro ran at {gyro_hz:g} Hz; the SITL's virtual gyro runs at 8 kHz (filters run at 8 kHz)"
        )

    # --- PIDs, D-min/D-max, feedforward
    pids = {ax: _as_list(h.get(f"{ax}PID")) for ax in _AXES}
    dmin = _as_list(h.get("d_min")) if v < (4, 5, 0) else None
    dmax = _as_list(h.get("d_max")) if v >= (4, 5, 0) else None
    for i, ax in enumerate(_AXES):
        pid = pids[ax]
        if not pid or len(pid) < 3:
            continue
        put(f"p_{ax}", pid[0])
        put(f"i_{ax}", pid[1])
        d = pid[2]
        if dmin is not None and i < len(dmin):
            # before 4.5 "D" was the maximum and d_min the base; 4.5+ has d (base) and d_max
            if 0 < dmin[i] < d:
                put(f"d_{ax}", dmin[i])
                put(f"d_max_{ax}", d)
            else:
                put(f"d_{ax}", d)
                put(f"d_max_{ax}", 0)
        else:
            put(f"d_{ax}", d)
            if dmax is not None and i < len(dmax):
                put(f"d_max_{ax}", dmax[i])
        if len(pid) >= 4 and v >= (4, 3, 0):
            put(f"f_{ax}", pid[3])
    ff = _as_list(_first(h, "ff_weight", "feedforward_weight"))
    if ff:
        for i, ax in enumerate(_AXES[: len(ff)]):
            put(f"f_{ax}", ff[i])
    if v >= (4, 5, 0):
        put("d_max_gain", h.get("d_max_gain"))
        put("d_max_advance", h.get("d_max_advance"))
    elif dmin is not None:
        put("d_max_gain", h.get("d_min_gain"))
        put("d_max_advance", h.get("d_min_advance"))

    # --- rates
    for key, fmt in (
        ("rc_rates", "{}_rc_rate"),
        ("rc_expo", "{}_expo"),
        ("rates", "{}_srate"),
        ("rate_limits", "{}_rate_limit"),
    ):
        vals = _as_list(h.get(key))
        if vals and len(vals) == 3:
            for ax, val in zip(_AXES, vals):
                put(fmt.format(ax), val)
    if "rc_rates" not in h and "rcRate" in h:  # 3.1-3.2 headers: roll/pitch shared, yaw separate
        for ax, rk, ek in (
            ("roll", "rcRate", "rcExpo"),
            ("pitch", "rcRate", "rcExpo"),
            ("yaw", "rcYawRate", "rcYawExpo"),
        ):
            put(f"{ax}_rc_rate", h.get(rk))
            put(f"{ax}_expo", h.get(ek))
    put("rates_type", h.get("rates_type"))
    for k in ("thr_mid", "thr_expo", "tpa_rate", "tpa_breakpoint"):
        put(k, h.get(k))

    # --- gyro filters (names changed in 4.3)
    put("gyro_lpf1_type", _first(h, "gyro_lpf1_type", "gyro_lowpass_type", "gyro_soft_type"))
    put("gyro_lpf1_static_hz", _first(h, "gyro_lpf1_static_hz", "gyro_lowpass_hz"))
    dyn = _as_list(_first(h, "gyro_lpf1_dyn_hz", "gyro_lowpass_dyn_hz", "dyn_lpf_gyro_hz"))
    if dyn and len(dyn) >= 2:
        put("gyro_lpf1_dyn_min_hz", dyn[0])
        put("gyro_lpf1_dyn_max_hz", dyn[1])
    elif v >= (3, 1, 0):
        put("gyro_lpf1_dyn_min_hz", 0)  # no dynamic LPF in this log: keep it off
    put("gyro_lpf1_dyn_expo", h.get("gyro_lpf1_dyn_expo"))
    put("gyro_lpf2_type", _first(h, "gyro_lpf2_type", "gyro_lowpass2_type"))
    put("gyro_lpf2_static_hz", _first(h, "gyro_lpf2_static_hz", "gyro_lowpass2_hz"))
    if _first(h, "gyro_lpf2_static_hz", "gyro_lowpass2_hz") is None:
        put("gyro_lpf2_static_hz", 0)
    nh, nc = _as_list(h.get("gyro_notch_hz")), _as_list(h.get("gyro_notch_cutoff"))
    for i in (0, 1):
        put(f"gyro_notch{i + 1}_hz", nh[i] if nh and i < len(nh) else 0)
        if nc and i < len(nc):
            put(f"gyro_notch{i + 1}_cutoff", nc[i])
    # dynamic notch: 4.3+ logs its count; 4.2 has 1 notch (2 when dyn_notch_width_percent > 0)
    # when the DYNAMIC_FILTER feature is on; older ones had a different analyser: off
    count = h.get("dyn_notch_count")
    if count is None:
        from gyrocore.readers.blackbox_firmware import dyn_notch_feature

        if v >= (4, 2, 0) and dyn_notch_feature(h, fw):
            count = 2 if (h.get("dyn_notch_width_percent") or 0) > 0 else 1
        else:
            count = 0
            if dyn_notch_feature(h, fw):
                notes.append(
                    f"Betaflight {fw.version_str}'s dynamic notch (a different analyser) is not "
                    f"reproduced: dynamic notch off"
                )
    put("dyn_notch_count", count)
    for k in ("dyn_notch_q", "dyn_notch_min_hz", "dyn_notch_max_hz"):
        put(k, h.get(k))
    # RPM filter: active only with bidirectional DShot
    harm = _first(h, "rpm_filter_harmonics", "gyro_rpm_notch_harmonics")
    if not h.get("dshot_bidir"):
        harm = 0
    put("rpm_filter_harmonics", harm if harm is not None else 0)
    put("rpm_filter_q", _first(h, "rpm_filter_q", "gyro_rpm_notch_q"))
    put("rpm_filter_min_hz", _first(h, "rpm_filter_min_hz", "gyro_rpm_notch_min"))
    put("rpm_filter_lpf_hz", _first(h, "rpm_filter_lpf_hz", "rpm_notch_lpf"))
    put("rpm_filter_fade_range_hz", h.get("rpm_filter_fade_range_hz"))
    w = _as_list(h.get("rpm_filter_weights"))
    if w:
        put("rpm_filter_weights", ",".join(str(x) for x in w))
    put("motor_poles", h.get("motor_poles"))

    # --- D-term filters
    put("dterm_lpf1_type", _first(h, "dterm_lpf1_type", "dterm_filter_type"))
    put("dterm_lpf1_static_hz", _first(h, "dterm_lpf1_static_hz", "dterm_lowpass_hz", "dterm_lpf_hz"))
    ddyn = _as_list(_first(h, "dterm_lpf1_dyn_hz", "dterm_lowpass_dyn_hz", "dyn_lpf_dterm_hz"))
    if ddyn and len(ddyn) >= 2:
        put("dterm_lpf1_dyn_min_hz", ddyn[0])
        put("dterm_lpf1_dyn_max_hz", ddyn[1])
    else:
        put("dterm_lpf1_dyn_min_hz", 0)
    put("dterm_lpf1_dyn_expo", h.get("dterm_lpf1_dyn_expo"))
    put("dterm_lpf2_type", _first(h, "dterm_lpf2_type", "dterm_filter2_type"))
    d2 = _first(h, "dterm_lpf2_static_hz", "dterm_lowpass2_hz")
    put("dterm_lpf2_static_hz", d2 if d2 is not None else 0)
    put("dterm_notch_hz", h.get("dterm_notch_hz"))
    put("dterm_notch_cutoff", h.get("dterm_notch_cutoff"))
    put("yaw_lowpass_hz", _first(h, "yaw_lowpass_hz", "yaw_lpf_hz"))

    # --- loop behaviour with the same meaning across 4.x
    if v >= (4, 3, 0):
        for k in (
            "iterm_relax",
            "iterm_relax_type",
            "iterm_relax_cutoff",
            "iterm_windup",
            "anti_gravity_gain",
            "anti_gravity_cutoff_hz",
            "anti_gravity_p_gain",
            "abs_control_gain",
            "pidsum_limit",
            "pidsum_limit_yaw",
            "acc_limit",
            "acc_limit_yaw",
            "feedforward_transition",
            "feedforward_averaging",
            "feedforward_smooth_factor",
            "feedforward_jitter_factor",
            "feedforward_boost",
            "feedforward_max_rate_limit",
            "motor_idle",
            "thrust_linearization",
            "throttle_boost",
            "throttle_boost_cutoff",
            "motor_output_limit",
            "tpa_mode",
            "tpa_low_rate",
            "tpa_low_breakpoint",
            "tpa_low_always",
        ):
            put(k, h.get(k))
    else:
        notes.append(
            f"Betaflight {fw.version_str}: I-term relax, anti-gravity, feedforward shaping and idle "
            f"(scales changed in 4.3) left at the 4.6.0 defaults; PIDs, rates and filters carried over"
        )
    return FirmwareSettings(tuple(out), f"blackbox {p.name} ({fw.label})", tuple(notes), lenient=True)


def settings_from_file(path: str | os.PathLike) -> FirmwareSettings:
    """A blackbox log (by content) or else a CLI ``diff`` file."""
    from gyrocore.readers.blackbox import is_blackbox

    if not Path(path).exists():
        raise GyroInputError(f"{path}: no such file")
    if is_blackbox(path):
        return settings_from_blackbox(path)
    return settings_from_diff(path)
