"""A measured vibration spec, entered through the rotor physics of a vehicle class (issue 16.3).

``gyroharness vibration FLIGHT -o spec.json`` identifies lines whose frequency follows the
throttle (or eRPM): the rotor line. The simulator cannot copy that line's frequency — a
different vehicle spins its rotors at its own speed — but it can give its rotors the imbalance
that puts the *measured line amplitude* into its gyro at the rotor frequency the controller
commands. The response of the rigid body (and of the closed loop, at a fixed frequency) is linear
in the imbalance u (force u Omega²) for given rotor phases, but the four rotors' lines add with
their phases, and those are not fixed: the rotors sit on one frame and are driven by soft speed
servos, so the vibration itself pulls their relative phases (the self-synchronisation of
unbalanced rotors on a common base, Blekhman). Measured here on racing5 (3-s hovers, the line
power summed over axes): flipping single rotors by π does not flip their contribution, and the
line power of one flight scatters over more than a decade with the seeded rotor phases. The
calibration is therefore statistical: the mean line power over ``n_calib`` hovers with seeded,
independent rotor phases at the class's default u, and

    u = u_default x sqrt(P_spec / mean P_sim(u_default))

with P the line power summed over the axes (the spec's ``amplitude_rad_s`` = √(2 P) per axis).
The mean line power of flights with other seeds then matches the spec within the calibration's
Monte Carlo error (relative SE of the mean power, reported); one flight's line scatters around it
(as the real quad's, one draw of its phases).
What the physics cannot give — the real frame's resonances and broadband — stays a shaped
disturbance (:func:`gyrocore.vibration.synthesize`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from gyrocore.errors import GyroInputError

__all__ = ["RotorLine", "rotor_line", "line_amplitude_in_gyro", "vibration_from_spec"]

#: relative frequency tolerance to call two bands' peaks the same line (as gyrocore.vibration's linker, 6 %)
_F_TOL = 0.06


@dataclass(frozen=True)
class RotorLine:
    """The spec's rotor line in one band.

    Attributes
    ----------
    band : int
    frequency_hz : float
        Its frequency in that band on the real vehicle, Hz.
    amplitude_rad_s : dict
        Sinusoid amplitude per axis, rad/s (axes without the line: 0).
    total_rad_s : float
        sqrt(sum of squares over axes), rad/s.
    source : str
        Which spec entries gave it.
    """

    band: int
    frequency_hz: float
    amplitude_rad_s: dict
    total_rad_s: float
    source: str


def _band_index(spec: dict, band) -> int:
    n = len(spec.get("bands") or [])
    if n == 0:
        raise GyroInputError("vibration spec has no bands")
    if band == "middle":
        return n // 2
    try:
        i = int(band)
    except (TypeError, ValueError):
        raise GyroInputError(f"vibration band {band!r}: the spec has bands 0..{n - 1} (or 'middle')") from None
    if not 0 <= i < n:
        raise GyroInputError(f"vibration band {band!r}: the spec has bands 0..{n - 1} (or 'middle')")
    return i


def rotor_line(spec: dict, band="middle") -> RotorLine:
    """The rotor (1st-harmonic) line of a spec in one band.

    The rotor line is the strongest line that follows the throttle or eRPM, is not flagged
    aliased and is not tagged a higher harmonic. Its frequency in the band: its own per-band
    entry, else its law at the band's median. Per axis, the amplitude is that of any line's
    per-band entry in this band within 6 % of that frequency (the same line seen on another
    axis), else — for the line's own axis — its overall amplitude.
    """
    i = _band_index(spec, band)
    lines = spec.get("lines") or []
    cands = [ln for ln in lines if ln.get("follows") in ("throttle", "erpm") and not ln.get("aliased")
             and ln.get("harmonic") in (None, 1)]
    if not cands:
        raise GyroInputError("vibration spec has no line that follows throttle or eRPM (no rotor line to put into the physics)")
    main = max(cands, key=lambda ln: ln["amplitude_rad_s"])
    own = {p["band"]: p for p in main.get("per_band", [])}
    if i in own:
        f = float(own[i]["frequency_hz"])
    else:
        law = main.get("law") or {}
        med = float(spec["bands"][i]["median"])
        f = float(law["hz_at_zero"] + law["hz_per_unit"] * med) if "hz_per_unit" in law else float(main["frequency_hz"])
    amp = {"x": 0.0, "y": 0.0, "z": 0.0}
    used = []
    for ln in lines:
        for p in ln.get("per_band", []):
            if p["band"] == i and abs(p["frequency_hz"] - f) <= _F_TOL * f:
                a = float(p["amplitude_rad_s"])
                if a > amp[ln["axis"]]:
                    amp[ln["axis"]] = a
                    used.append(f"{ln['axis']} {p['frequency_hz']:.0f} Hz")
    if amp[main["axis"]] == 0.0:
        amp[main["axis"]] = float(main["amplitude_rad_s"])
        used.append(f"{main['axis']} overall {main['frequency_hz']:.0f} Hz")
    tot = math.sqrt(sum(a * a for a in amp.values()))
    return RotorLine(band=i, frequency_hz=f, amplitude_rad_s=amp, total_rad_s=tot, source="; ".join(used))


def line_amplitude_in_gyro(omega_rad_s: np.ndarray, rate_hz: float, f_hz: float, *, nperseg: int | None = None) -> np.ndarray:
    """Sinusoid amplitude per axis of the line at ``f_hz`` in a rate signal (N, 3), rad/s.

    Welch (Hann, 1-Hz bins by default); line power = PSD summed over ±3 bins around ``f_hz``
    times the bin width (a Hann window keeps > 99.9 % of a tone's power within ±3 bins), minus the
    median PSD of the neighbouring ±(10..30) bins times 7 bins (the broadband under the line);
    amplitude √(2 P).
    """
    from scipy import signal

    nper = int(nperseg or round(rate_hz))
    f, p = signal.welch(omega_rad_s, fs=rate_hz, nperseg=nper, axis=0)
    df = f[1] - f[0]
    k = int(round(f_hz / df))
    lo, hi = max(k - 3, 0), min(k + 4, f.size)
    side = np.r_[max(k - 30, 0):max(k - 10, 0), min(k + 11, f.size):min(k + 31, f.size)]
    base = np.median(p[side], axis=0) if side.size else 0.0
    pw = np.maximum(p[lo:hi].sum(axis=0) - base * (hi - lo), 0.0) * df
    return np.sqrt(2.0 * pw)


def vibration_from_spec(spec: dict, vehicle="racing5", *, band="middle", seed: int = 0, calib_s: float = 3.0,
                        n_calib: int = 16):
    """The class's :class:`sim.quadrotor.VibrationSpec` with the imbalance set from the spec's rotor line.

    Parameters
    ----------
    spec : dict
        A vibration spec (:func:`gyrocore.vibration.read_spec`).
    vehicle : str or VehicleClass
    band : int or "middle"
    seed : int
        Seeds the calibration hovers' rotor phases (``SeedSequence([seed, 16, j])``).
    calib_s : float
        Calibration hover length, s (the first second is left out).
    n_calib : int
        Calibration hovers averaged (rotor phases seeded by ``SeedSequence([seed, 16, j])``).

    Returns
    -------
    (VibrationSpec, dict)
        The spec for :func:`sim.quadrotor.fly_hover` and what was done (rotor line, calibration
        amplitude, imbalance before/after, commanded rotor frequency).
    """
    from .quadrotor import fly_hover
    from .vehicles import get_vehicle

    veh = get_vehicle(vehicle)
    line = rotor_line(spec, band)
    v0 = veh.vibration
    if not v0.imbalance_kg_m > 0:
        raise GyroInputError(f"vehicle {veh.name} has no default imbalance to calibrate")
    if int(n_calib) < 1:
        raise GyroInputError("n_calib must be >= 1")
    p_axes, f_rots = [], []
    for j in range(int(n_calib)):
        sj = int(np.random.SeedSequence([int(seed), 16, j]).generate_state(1)[0])
        truth, log = fly_hover(duration_s=calib_s, vehicle=veh, vibration=v0, seed=sj)
        k0 = int(round(1.0 * log.rate_hz))
        f_rot = float(np.abs(log.rotor_speed_rad_s[k0:]).mean()) / (2 * math.pi)
        p_axes.append(line_amplitude_in_gyro(truth.omega_S_rad_s[k0:], log.rate_hz, f_rot) ** 2 / 2.0)
        f_rots.append(f_rot)
    p_tot = np.sum(p_axes, axis=1)
    p_se_rel = float(np.std(p_tot, ddof=1) / math.sqrt(len(p_tot)) / np.mean(p_tot)) if len(p_tot) > 1 else float("nan")
    p_mean = np.mean(p_axes, axis=0)  # line power per axis, (rad/s)^2
    a_sim = np.sqrt(2.0 * p_mean)
    tot_sim = float(np.sqrt(np.sum(a_sim**2)))
    if not tot_sim > 0:
        raise GyroInputError(f"vehicle {veh.name}: no rotor line in the calibration hovers")
    f_rot = float(np.mean(f_rots))
    u = v0.imbalance_kg_m * line.total_rad_s / tot_sim
    info = {"vehicle": veh.name, "band": line.band, "real_line_hz": line.frequency_hz,
            "real_line_amplitude_rad_s": line.amplitude_rad_s, "real_line_total_rad_s": line.total_rad_s,
            "real_line_source": line.source, "sim_rotor_hz": f_rot,
            "calibration_amplitude_rad_s": dict(zip("xyz", a_sim.tolist())), "calibration_imbalance_kg_m": v0.imbalance_kg_m,
            "n_calib": int(n_calib), "calibration_power_se_rel": p_se_rel,
            "imbalance_kg_m": u}
    return replace(v0, imbalance_kg_m=u), info
