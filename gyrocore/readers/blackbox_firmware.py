"""What a blackbox log's header says about the firmware that wrote it.

The firmware and its version (:class:`FirmwareInfo`, :func:`firmware_info`: the Betaflight,
INAV and Cleanflight releases whose source was read, :data:`INAV_READ`,
:data:`CLEANFLIGHT_AS_BETAFLIGHT`), its loop and logged rates (:func:`loop_rates`,
:func:`inav_loop_rates`), its gyro filter chain as flown (:class:`FilterStage`,
:func:`gyro_filter_chain`, :func:`inav_filter_chain`), the name of a ``debug_mode`` index per
release (:func:`debug_mode_name`, :data:`DEBUG_MODE_TABLES`) and what a gyro debug mode holds
(:func:`debug_gyro_meaning`). :mod:`gyrocore.readers.blackbox` decodes the frames and converts
a log with these.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from importlib import resources
from typing import Sequence

from gyrocore.errors import GyroInputError, warn_repair

__all__ = [
    "FirmwareInfo",
    "FilterStage",
    "DebugGyro",
    "firmware_info",
    "loop_rates",
    "inav_loop_rates",
    "gyro_filter_chain",
    "inav_filter_chain",
    "dyn_notch_feature",
    "debug_mode_name",
    "debug_gyro_meaning",
    "notch_q",
    "DEBUG_MODE_TABLES",
    "INAV_READ",
    "CLEANFLIGHT_AS_BETAFLIGHT",
    "NEWEST_KNOWN",
]


def _debug_mode_tables() -> tuple:
    """The release groups of ``betaflight_debug_modes.json`` as (first version, last version, names)."""
    doc = json.loads(resources.files(__package__).joinpath("betaflight_debug_modes.json").read_text(encoding="utf-8"))
    return tuple((tuple(r["first"]), tuple(r["last"]), tuple(r["names"])) for r in doc["releases"])


#: ``debugType_e`` per Betaflight release range: (first version, last version read, names by
#: index), generated from each release tag's src/main/build/debug.h into
#: ``gyrocore/readers/betaflight_debug_modes.json`` (a table, kept as data; read once, here).
DEBUG_MODE_TABLES = _debug_mode_tables()

#: Newest Betaflight release whose source was read for this module.
NEWEST_KNOWN = (2026, 6, 99)


def _version_str(v: Sequence[int]) -> str:
    return ".".join(str(x) for x in v)


def debug_mode_name(version: Sequence[int], index: int) -> str | None:
    """Name of ``debug_mode`` ``index`` in Betaflight ``version`` (None: version not read).

    A version maps to the release group whose tags were read and that holds it (a patch
    release of the same major.minor within the group's range; 2025.12.0, tagged only as
    release candidates whose list equals 2025.12.1's, maps to that group). E.g. (3, 1, 5), 8 →
    ``"NOTCH"``; (3, 2, 5), 8 → ``"GYRO_NOTCH"``; (3, 3, 0), 6 → ``"GYRO_NOTCH"``;
    (4, 3, 0), 6 → ``"GYRO_SCALED"``. An index past the list is ``"index N"``.
    """
    v = tuple(version)
    hit = None
    for lo, hi, names in DEBUG_MODE_TABLES:
        if (lo <= v or lo[:2] == v[:2]) and v <= hi:
            hit = names
    if hit is None:
        return None
    return hit[index] if 0 <= index < len(hit) else f"index {index}"


@dataclass(frozen=True)
class FilterStage:
    """One firmware gyro filter as the firmware runs it.

    Parameters
    ----------
    kind : str
        ``pt1``, ``pt2``, ``pt3``, ``biquad`` (RBJ low-pass, Q = 1/√2), ``notch`` (RBJ notch,
        Q from ``filterGetNotchQ``), ``fir`` (3.1–3.3's FIR option: response not modelled),
        or a dynamic filter: ``dyn_lpf``, ``dyn_notch``, ``rpm_notch`` (cannot be undone).
    cutoff_hz : float
        Cutoff (low-pass) or centre (notch), Hz; for dynamic filters the lower limit.
    rate_hz : float
        Rate the filter runs at (nominal, from the header), Hz.
    header : str
        The header entries it comes from.
    q : float
        Notch Q (NaN otherwise).
    dynamic : bool
        True when the filter moves in flight (its response at each instant is not logged).
    notch_cutoff_hz : float
        Betaflight's notch "cutoff" (lower −3 dB edge) the Q comes from (NaN otherwise).
    """

    kind: str
    cutoff_hz: float
    rate_hz: float
    header: str
    q: float = float("nan")
    dynamic: bool = False
    notch_cutoff_hz: float = float("nan")
    max_hz: float = float("nan")

    def label(self) -> str:
        if self.kind == "notch":
            return f"notch {self.cutoff_hz:g} Hz (cutoff {self.notch_cutoff_hz:g} Hz, Q {self.q:.3f}) @ {self.rate_hz:g} Hz"
        if self.dynamic:
            return f"{self.kind} {self.cutoff_hz:g}-{self.max_hz:g} Hz (dynamic) @ {self.rate_hz:g} Hz"
        return f"{self.kind} {self.cutoff_hz:g} Hz @ {self.rate_hz:g} Hz"

    def to_dict(self) -> dict:
        d = {
            "kind": self.kind,
            "cutoff_hz": self.cutoff_hz,
            "rate_hz": self.rate_hz,
            "dynamic": self.dynamic,
            "header": self.header,
        }
        if self.kind == "notch":
            d["q"] = self.q
            d["notch_cutoff_hz"] = self.notch_cutoff_hz
        if self.dynamic:
            d["max_hz"] = self.max_hz if math.isfinite(self.max_hz) else None
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "FilterStage":
        return cls(
            kind=d["kind"],
            cutoff_hz=float(d["cutoff_hz"]),
            rate_hz=float(d["rate_hz"]),
            header=d.get("header", ""),
            q=float(d.get("q", float("nan"))),
            dynamic=bool(d.get("dynamic", False)),
            notch_cutoff_hz=float(d.get("notch_cutoff_hz", float("nan"))),
            max_hz=float(d["max_hz"]) if d.get("max_hz") is not None else float("nan"),
        )


def notch_q(center_hz: float, cutoff_hz: float) -> float:
    """Betaflight ``filterGetNotchQ``: Q = f0·fc/(f0² − fc²) (3.1's octave form is the same value)."""
    return center_hz * cutoff_hz / (center_hz * center_hz - cutoff_hz * cutoff_hz)


@dataclass(frozen=True)
class FirmwareInfo:
    """Firmware named by the header.

    ``name`` ("betaflight", "inav", "cleanflight"); ``version``: the version whose source gives
    the log's meaning — for Cleanflight the Betaflight release its source equals
    (:data:`CLEANFLIGHT_AS_BETAFLIGHT`), else the firmware's own; ``release``: the firmware's own
    version as the header names it; revision text; blackbox data version.
    """

    name: str
    version: tuple[int, ...]
    revision: str
    data_version: int
    release: tuple[int, ...] | None = None

    @property
    def version_str(self) -> str:
        return _version_str(self.version)

    @property
    def release_str(self) -> str:
        return _version_str(self.release or self.version)

    @property
    def label(self) -> str:
        """E.g. "Betaflight 4.2.0", "INAV 9.0.1", "Cleanflight 2.4.1 (= Betaflight 3.4.1 source)"."""
        if self.name == "cleanflight":
            return f"Cleanflight {self.release_str} (= Betaflight {self.version_str} source)"
        return f"{'INAV' if self.name == 'inav' else 'Betaflight'} {self.version_str}"


_REV = re.compile(
    r"^\s*(Betaflight|INAV|Cleanflight|EmuFlight|Emuflight|Rotorflight|KISS)\s+v?(\d+)\.(\d+)(?:\.(\d+))?", re.I
)


#: INAV releases whose blackbox writer was read (major, minor) → what was read. The source read is
#: the stored iNavFlight/inav revision 00b5622b (a development revision after 9.0.1: it already has
#: the secondary-gyro field gyroRaw2) of src/main/blackbox/blackbox.c, blackbox_fielddefs.h and
#: src/main/sensors/gyro.c; its header writer (``blackboxWriteSysinfo``: every ``H`` key, in
#: order) and main-field list agree line by line with a real INAV 9.0.1 log (tests), so 9.0.x is
#: read; no other INAV release's source was read.
INAV_READ = {(9, 0): "iNavFlight/inav 00b5622b: blackbox/blackbox.c, blackbox/blackbox_fielddefs.h, sensors/gyro.c"}


#: Cleanflight releases read (own version → the Betaflight release whose source it equals).
#: Read in the cleanflight/cleanflight repository: the first-parent commits during which
#: src/main/build/version.h named each version; for each, build/debug.h's debugType_e list is one
#: list over the whole range and equals that Betaflight release's, and blackbox/blackbox.c,
#: sensors/gyro.c (and gyro_filter_impl.c for 4.2) differ from the Betaflight tag only in licence
#: comments, includes and (4.2) a cache-flush state of the header writer. Not read: Cleanflight
#: 1.x (gyro in raw counts), 2.0.0, 2.1.0, 2.3.0 (the debug list changed while that version was
#: current: ambiguous), 2.2.0 and 2.3.1 (debug lists of their own, matching no Betaflight release).
CLEANFLIGHT_AS_BETAFLIGHT = {
    (2, 4, 0): (3, 4, 0),
    (2, 4, 1): (3, 4, 1),
    (2, 5, 0): (3, 5, 0),
    (4, 2, 0): (4, 2, 0),
    (4, 2, 2): (4, 2, 2),
}


def firmware_info(headers: dict, source: str = "") -> FirmwareInfo:
    """Identify the firmware; one-line :class:`GyroInputError` for a firmware/data version not read.

    Read: Betaflight 3.1 … 2026.6 (``gyroADC`` in deg/s, ``gyro_scale`` = 1.0 checked) and INAV
    9.0.x (:data:`INAV_READ`). Betaflight 3.0 and older, other INAV releases, Cleanflight and
    other forks log units/fields/debug lists that were not read here; blackbox data versions
    other than 1 and 2 are unknown.
    """
    dv = headers.get("Data version")
    if dv not in (1, 2):
        raise GyroInputError(f"{source}: blackbox data version {dv!r} is not one this reader knows (1, 2)")
    rev = str(headers.get("Firmware revision", "")).strip()
    ftype = str(headers.get("Firmware type", "")).strip()
    m = _REV.match(rev)
    if not m:
        raise GyroInputError(
            f"{source}: firmware {rev or ftype or 'unnamed'!r} is not one this reader knows "
            f"(Betaflight 3.1–2026.6, INAV 9.0, Cleanflight 2.4/2.5/4.2)"
        )
    name = m.group(1).lower()
    ver = tuple(int(x) for x in m.groups()[1:] if x is not None)
    if len(ver) == 2:
        ver = ver + (0,)
    if name == "inav":
        if ver[:2] not in INAV_READ:
            raise GyroInputError(
                f"{source}: INAV {_version_str(ver)} logs are not read (its blackbox writer and gyro "
                f"units were not checked in that release's source); INAV 9.0.x and Betaflight 3.1–2026.6 are"
            )
        return FirmwareInfo(name=name, version=ver, revision=rev, data_version=int(dv))
    if name == "cleanflight":
        if ver not in CLEANFLIGHT_AS_BETAFLIGHT:
            known = ", ".join(_version_str(v) for v in CLEANFLIGHT_AS_BETAFLIGHT)
            raise GyroInputError(
                f"{source}: Cleanflight {_version_str(ver)} logs are not read (its debug list and gyro "
                f"fields were not matched to a read source); Cleanflight {known} are"
            )
        return FirmwareInfo(
            name=name, version=CLEANFLIGHT_AS_BETAFLIGHT[ver], revision=rev, data_version=int(dv), release=ver
        )
    if name != "betaflight":
        raise GyroInputError(
            f"{source}: {m.group(1)} {_version_str(ver)} logs are not read (units and debug modes of that "
            f"firmware were not checked in its source); Betaflight 3.1–2026.6, INAV 9.0.x and "
            f"Cleanflight 2.4/2.5/4.2 are"
        )
    if ver < (3, 1, 0):
        raise GyroInputError(
            f"{source}: Betaflight {_version_str(ver)} is older than 3.1 (gyro logged in raw counts with a "
            f"per-build gyro_scale); this reader knows Betaflight 3.1–2026.6"
        )
    return FirmwareInfo(name=name, version=ver, revision=rev, data_version=int(dv))


def _h(headers: dict, key: str, default=None):
    return headers.get(key, default)


def _hlist(headers: dict, key: str) -> list:
    v = headers.get(key)
    if v is None:
        return []
    return list(v) if isinstance(v, (list, tuple)) else [v]


def _lpf_kind(fw: FirmwareInfo, type_idx) -> str:
    """lowpassFilterType_e: 0 PT1, 1 BIQUAD, then 2 FIR (3.1–3.3) or 2 PT2, 3 PT3 (4.3+)."""
    t = int(type_idx or 0)
    if t == 0:
        return "pt1"
    if t == 1:
        return "biquad"
    if fw.version >= (4, 3, 0):
        return {2: "pt2", 3: "pt3"}.get(t, f"type{t}")
    return "fir" if t == 2 and fw.version < (3, 4, 0) else f"type{t}"


def _loop_period_us(headers: dict, measured_loop_hz: float | None, loops_per_iteration: float, where: str) -> float:
    """``looptime`` (µs), or — when the header's is not a period (INAV writes "InfinityHz" in
    some builds: FLIGHT_LOGS.md) — the period the log's own ``loopIteration`` count measured
    (``loops_per_iteration`` gyro loops per counted iteration), with a warning."""
    lt = _h(headers, "looptime")
    if isinstance(lt, (int, float)) and lt > 0:
        return float(lt)
    if measured_loop_hz is not None and math.isfinite(measured_loop_hz) and measured_loop_hz > 0:
        period = 1e6 / (float(measured_loop_hz) * loops_per_iteration)
        warn_repair(
            f"{where}header 'looptime' is {lt!r}, not a loop period in µs: the loop rate is taken from the logged "
            f"loopIteration count, {1e6 / period:.6g} Hz"
        )
        return period
    raise GyroInputError(f"{where}header 'looptime' is {lt!r}, not a loop period in µs")


def loop_rates(headers: dict, fw: FirmwareInfo, *, measured_loop_hz: float | None = None, where: str = "") -> dict:
    """Gyro, PID (gyro-filter) and nominal logged rates from the header, Hz.

    3.1–4.1: ``looptime`` is the gyro loop period (gyro.targetLooptime); gyro filters run
    there. 4.2+: ``looptime`` is the gyro sampling period (gyro.sampleLooptime); the gyro
    filters (static notches, LPF1) run at the PID rate = gyro rate / ``pid_process_denom``
    (gyro_init.c: ``biquadFilterInit(..., gyro.targetLooptime, ...)``), LPF2 at the gyro rate
    (it is the downsampling filter). ``P interval`` is "num/denom" (3.1–3.2) or an integer
    count of loops between logged frames (3.3+).
    """
    denom = _h(headers, "pid_process_denom", 1) or 1
    # loopIteration counts PID loops: pid_process_denom gyro loops each
    gyro_hz = 1e6 / _loop_period_us(headers, measured_loop_hz, float(denom), where)
    if fw.version >= (4, 2, 0):
        pid_hz = gyro_hz / float(denom)
        filt_hz, lpf2_hz = pid_hz, gyro_hz
    else:
        pid_hz = gyro_hz / float(denom)
        filt_hz, lpf2_hz = gyro_hz, gyro_hz
    pint = _h(headers, "P interval", 1)
    if isinstance(pint, str) and "/" in pint:
        num, den = (int(x) for x in pint.split("/"))
        log_hz = pid_hz * num / den
    else:
        log_hz = pid_hz / float(pint or 1)
    return {"gyro_hz": gyro_hz, "pid_hz": pid_hz, "filter_hz": filt_hz, "lpf2_hz": lpf2_hz, "log_hz_nominal": log_hz}


def gyro_filter_chain(headers: dict, fw: FirmwareInfo, rates: dict | None = None) -> list[FilterStage]:
    """The firmware's software gyro filters from the header, in the firmware's order.

    Header names per version (blackbox.c of each tag): 3.1–3.3 ``gyro_lowpass_hz`` +
    ``gyro_soft_type``/``gyro_lowpass_type``; 3.4–4.2 adds ``gyro_lowpass2_hz``/``_type``;
    4.0–4.2 ``gyro_lowpass_dyn_hz`` / ``dyn_lpf_gyro_hz``; 4.3+ ``gyro_lpf1_static_hz``,
    ``gyro_lpf1_type``, ``gyro_lpf1_dyn_hz``, ``gyro_lpf2_static_hz``, ``gyro_lpf2_type``;
    all: ``gyro_notch_hz`` / ``gyro_notch_cutoff`` (two static notches, 0 = off); dynamic
    notch (``dyn_notch_*``, 4.3+ ``dyn_notch_count``) and RPM filter (``gyro_rpm_notch_*``
    4.0–4.2, ``rpm_filter_*`` 4.3+, active only with ``dshot_bidir`` = 1).
    Order: 3.1 LPF → notch1 → notch2 (sensors/gyro.c); 3.2+ notches → LPF(s).
    """
    r = loop_rates(headers, fw) if rates is None else rates  # rates: :func:`loop_rates` of this log
    fr, f2 = r["filter_hz"], r["lpf2_hz"]
    # static notches
    hz = _hlist(headers, "gyro_notch_hz")
    cut = _hlist(headers, "gyro_notch_cutoff")
    notches = []
    for i, f0 in enumerate(hz):
        c = cut[i] if i < len(cut) else 0
        if f0 and f0 > 0 and c and 0 < c < f0:
            notches.append(
                FilterStage(
                    "notch",
                    float(f0),
                    fr,
                    f"gyro_notch_hz[{i}], gyro_notch_cutoff[{i}]",
                    q=notch_q(float(f0), float(c)),
                    notch_cutoff_hz=float(c),
                )
            )
    # LPF1
    if fw.version >= (4, 3, 0):
        f1, t1, k1 = _h(headers, "gyro_lpf1_static_hz", 0), _h(headers, "gyro_lpf1_type", 0), "gyro_lpf1_static_hz"
        dyn1 = _hlist(headers, "gyro_lpf1_dyn_hz")
        f2hz, t2, k2 = _h(headers, "gyro_lpf2_static_hz", 0), _h(headers, "gyro_lpf2_type", 0), "gyro_lpf2_static_hz"
    else:
        f1 = _h(headers, "gyro_lowpass_hz", 0)
        t1 = _h(headers, "gyro_lowpass_type", _h(headers, "gyro_soft_type", 0))
        k1 = "gyro_lowpass_hz"
        dyn1 = _hlist(headers, "gyro_lowpass_dyn_hz") or _hlist(headers, "dyn_lpf_gyro_hz")
        f2hz, t2, k2 = _h(headers, "gyro_lowpass2_hz", 0), _h(headers, "gyro_lowpass2_type", 0), "gyro_lowpass2_hz"
    lpfs = []
    if len(dyn1) >= 2 and dyn1[0] and dyn1[0] > 0:
        lpfs.append(
            FilterStage(
                "dyn_lpf",
                float(dyn1[0]),
                fr,
                k1.replace("static_hz", "dyn_hz") if "lpf1" in k1 else "gyro_lowpass_dyn_hz",
                dynamic=True,
                max_hz=float(dyn1[1]),
            )
        )
    elif f1 and f1 > 0:
        lpfs.append(FilterStage(_lpf_kind(fw, t1), float(f1), fr, k1))
    if f2hz and f2hz > 0:
        lpfs.append(FilterStage(_lpf_kind(fw, t2), float(f2hz), f2, k2))
    # dynamic notch / RPM filter
    dyn = []
    count = _h(headers, "dyn_notch_count")
    if (count is not None and count > 0) or (count is None and dyn_notch_feature(headers, fw)):
        dyn.append(
            FilterStage(
                "dyn_notch",
                float(_h(headers, "dyn_notch_min_hz", 0) or 0),
                fr,
                "dyn_notch_*",
                dynamic=True,
                max_hz=float(_h(headers, "dyn_notch_max_hz", 0) or 0),
            )
        )
    harm = _h(headers, "rpm_filter_harmonics", _h(headers, "gyro_rpm_notch_harmonics", 0))
    if harm and _h(headers, "dshot_bidir", 0):
        dyn.append(
            FilterStage(
                "rpm_notch",
                float(_h(headers, "rpm_filter_min_hz", _h(headers, "gyro_rpm_notch_min", 0)) or 0),
                fr,
                "rpm_filter_* / gyro_rpm_notch_*",
                dynamic=True,
                max_hz=float("nan"),
            )
        )
    if fw.version < (3, 2, 0):
        return lpfs + notches
    return dyn + notches + lpfs


#: Betaflight 3.2–4.2 enable the dynamic notch with FEATURE_DYNAMIC_FILTER = 1 << 29
#: (src/main/fc/config.h / feature.h of those tags); 4.3+ log ``dyn_notch_count``.
_FEATURE_DYNAMIC_FILTER = 1 << 29


def dyn_notch_feature(headers: dict, fw: FirmwareInfo) -> bool:
    if not ((3, 2, 0) <= fw.version < (4, 3, 0)):
        return False
    feats = _h(headers, "features", 0)
    return isinstance(feats, int) and bool(feats & _FEATURE_DYNAMIC_FILTER)


def inav_loop_rates(headers: dict, *, measured_loop_hz: float | None = None, where: str = "") -> dict:
    """INAV loop and logged rates from the header, Hz (INAV source read: :data:`INAV_READ`).

    ``looptime`` is ``getLooptime()``: the PID/filter loop period in µs (the gyro task's own
    sampling period is not in the header: ``gyro_hz`` is NaN). ``P interval`` is
    ``rate_num/rate_denom``: one main frame per ``rate_denom/rate_num`` loops.
    """
    pid_hz = 1e6 / _loop_period_us(headers, measured_loop_hz, 1.0, where)
    pint = _h(headers, "P interval", "1/1")
    if isinstance(pint, str) and "/" in pint:
        num, den = (int(x) for x in pint.split("/"))
    else:
        num, den = 1, int(pint or 1)
    return {
        "gyro_hz": float("nan"),
        "pid_hz": pid_hz,
        "filter_hz": pid_hz,
        "lpf2_hz": pid_hz,
        "log_hz_nominal": pid_hz * num / den,
    }


def inav_filter_chain(headers: dict, rates: dict) -> list[FilterStage]:
    """The INAV gyro filters the header names, in the firmware's order (sensors/gyro.c ``gyroFilter``).

    Order after the anti-alias PT1 (not in the header): RPM filter (``rpm_gyro_filter_enabled``,
    dynamic), LULU (not in the header), main LPF = PT1 at ``gyro_lpf_hz`` on the loop period
    (``initGyroFilter``: ``pt1FilterInit(cutoff, looptime)``; off when gyro_filter_mode is OFF,
    moved by the adaptive mode — neither is in the header), dynamic notch (``dynamicGyroNotchMinHz``
    / ``Q`` are logged, its enable flag is not: listed as dynamic), Kalman (not in the header).
    """
    fr = rates["filter_hz"]
    out: list[FilterStage] = []
    if _h(headers, "rpm_gyro_filter_enabled", 0):
        out.append(
            FilterStage(
                "rpm_notch",
                float(_h(headers, "rpm_gyro_min_hz", 0) or 0),
                fr,
                "rpm_gyro_filter_enabled, rpm_gyro_min_hz",
                dynamic=True,
            )
        )
    f_main = _h(headers, "gyro_lpf_hz", 0)
    if isinstance(f_main, (int, float)) and f_main > 0:
        out.append(FilterStage("pt1", float(f_main), fr, "gyro_lpf_hz (INAV main gyro LPF, PT1)"))
    if "dynamicGyroNotchMinHz" in headers:
        out.append(
            FilterStage(
                "dyn_notch",
                float(_h(headers, "dynamicGyroNotchMinHz", 0) or 0),
                fr,
                "dynamicGyroNotchMinHz, dynamicGyroNotchQ (enable flag not logged)",
                dynamic=True,
                max_hz=fr / 2.0,
            )
        )
    return out


@dataclass(frozen=True)
class DebugGyro:
    """What ``debug[0..2]`` holds for the gyro: ``kind`` raw/partly_filtered, filters before it."""

    mode: str
    kind: str
    before: tuple[int, ...]  # indices into the chain of stages the signal has been through
    source: str


def debug_gyro_meaning(fw: FirmwareInfo, mode: str, chain: Sequence[FilterStage]) -> DebugGyro | None:
    """What ``debug[0..2]`` holds, for the gyro debug modes, per Betaflight version.

    Read in src/main/sensors/gyro.c (3.1–4.1) and gyro_filter_impl.* (3.5+):

    * 3.1.x ``DEBUG_GYRO`` (3): scaled gyro before the soft LPF (no software filter);
      ``DEBUG_NOTCH`` (8): after the soft LPF, before the two static notches.
    * 3.2.x–3.3.x ``DEBUG_GYRO_NOTCH`` (8 / 6): "records the unfiltered gyro output";
      ``DEBUG_GYRO`` (3): after the dynamic and static notches, before the LPF.
    * 3.4–4.5 ``DEBUG_GYRO_SCALED`` (6): "the unfiltered, scaled gyro output" (4.2+: the last
      sample of a downsampling group); ``DEBUG_GYRO_FILTERED`` (3): after all filtering (what
      gyroADC holds).
    ``GYRO_RAW`` (sensor counts, not zero-offset nor scaled) is not used: its LSB scale is the
    sensor's, not in the header. All are ``lrintf`` of deg/s: 1 °/s steps.
    """
    v = fw.version
    idx = list(range(len(chain)))
    lpf_idx = [i for i, s in enumerate(chain) if s.kind in ("pt1", "pt2", "pt3", "biquad", "fir", "dyn_lpf")]
    if v < (3, 2, 0):
        if mode == "GYRO":
            return DebugGyro(mode, "raw", (), "sensors/gyro.c 3.1: DEBUG_SET(DEBUG_GYRO) before softLpfFilterApplyFn")
        if mode == "NOTCH":
            return DebugGyro(
                mode,
                "partly_filtered",
                tuple(lpf_idx),
                "sensors/gyro.c 3.1: DEBUG_SET(DEBUG_NOTCH) after the soft LPF, before notchFilter1/2",
            )
        return None
    if v < (3, 4, 0):
        if mode == "GYRO_NOTCH":
            return DebugGyro(
                mode, "raw", (), "sensors/gyro.c 3.2/3.3: DEBUG_GYRO_NOTCH 'records the unfiltered gyro output'"
            )
        if mode == "GYRO":
            return DebugGyro(
                mode,
                "partly_filtered",
                tuple(i for i in idx if i not in lpf_idx),
                "sensors/gyro.c 3.2/3.3: DEBUG_GYRO after dynamic and static notches, before the LPF",
            )
        return None
    if v < (2025, 0, 0):
        if mode == "GYRO_SCALED":
            return DebugGyro(
                mode, "raw", (), "gyro.c / gyro_filter_impl: DEBUG_GYRO_SCALED 'the unfiltered, scaled gyro output'"
            )
        return None
    return None
