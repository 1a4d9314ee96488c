"""A measured vibration spec, entered through the rotor physics of a vehicle class.

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
disturbance (:func:`gyrocore.flight.synthesis.synthesize`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from gyrocore.errors import GyroInputError

__all__ = [
    "RotorLine",
    "carried_bands",
    "line_amplitude_in_gyro",
    "line_exclusion_hz",
    "rotor_line",
    "spec_injection",
    "vibration_from_spec",
]

#: relative frequency tolerance to call two bands' peaks the same line (as gyrocore.flight.vibration's linker, 6 %)
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
    cands = [
        ln
        for ln in lines
        if ln.get("follows") in ("throttle", "erpm") and not ln.get("aliased") and ln.get("harmonic") in (None, 1)
    ]
    if not cands:
        bands = [b for b in (spec.get("bands") or []) if len(b.get("throttle") or ()) == 2]
        why = ""
        if bands:
            lo = min(float(b["throttle"][0]) for b in bands)
            hi = max(float(b["throttle"][1]) for b in bands)
            erpm = any("rotor_hz_median" in b for b in bands)
            why = (
                f": its {len(bands)} band(s) span motor command {lo:.2f}-{hi:.2f}"
                + ("" if erpm else " and the log has no rotor speed (eRPM)")
                + (
                    "; a flight that holds one throttle (a hover) gives no throttle law: use a log with "
                    "throttle changes" + ("" if erpm else " or with eRPM (bidirectional DShot telemetry)")
                    if hi - lo < 0.2
                    else ""
                )
            )
        raise GyroInputError(
            "vibration spec has no line that follows throttle or eRPM (no rotor line to put into the physics)" + why
        )
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


def line_amplitude_in_gyro(
    omega_rad_s: np.ndarray, rate_hz: float, f_hz: float, *, nperseg: int | None = None
) -> np.ndarray:
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
    side = np.r_[max(k - 30, 0) : max(k - 10, 0), min(k + 11, f.size) : min(k + 31, f.size)]
    base = np.median(p[side], axis=0) if side.size else 0.0
    pw = np.maximum(p[lo:hi].sum(axis=0) - base * (hi - lo), 0.0) * df
    return np.sqrt(2.0 * pw)


_CALIB_CACHE: dict = {}


def _calibration_powers(veh, vib, *, seed: int, tag: int, calib_s: float, n_calib: int):
    """Line power per axis (n_calib, 3), (rad/s)², and the mean rotor frequency of seeded hovers with ``vib``.

    Deterministic in its arguments (seeded hovers), so a registered class's results are kept for
    the process (the calibration bases do not depend on the spec: one per class, not one per band).
    """
    from .vehicles import VEHICLES

    key = (veh.name, vib, int(seed), int(tag), float(calib_s), int(n_calib))
    cacheable = veh.name in VEHICLES and VEHICLES[veh.name] is veh
    if cacheable and key in _CALIB_CACHE:
        p, f = _CALIB_CACHE[key]
        return p.copy(), f
    out = _calibration_powers_uncached(veh, vib, seed=seed, tag=tag, calib_s=calib_s, n_calib=n_calib)
    if cacheable:
        _CALIB_CACHE[key] = (out[0].copy(), out[1])
    return out


def _calibration_powers_uncached(veh, vib, *, seed: int, tag: int, calib_s: float, n_calib: int):
    from .quadrotor import fly_hover

    p_axes, f_rots = [], []
    for j in range(int(n_calib)):
        sj = int(np.random.SeedSequence([int(seed), tag, j]).generate_state(1)[0])
        truth, log = fly_hover(duration_s=calib_s, vehicle=veh, vibration=vib, seed=sj)
        k0 = int(round(1.0 * log.rate_hz))
        f_rot = float(np.abs(log.rotor_speed_rad_s[k0:]).mean()) / (2 * math.pi)
        p_axes.append(line_amplitude_in_gyro(truth.omega_S_rad_s[k0:], log.rate_hz, f_rot) ** 2 / 2.0)
        f_rots.append(f_rot)
    return np.asarray(p_axes), float(np.mean(f_rots))


def vibration_from_spec(
    spec: dict, vehicle="racing5", *, band="middle", seed: int = 0, calib_s: float = 3.0, n_calib: int = 32
):
    """The class's :class:`sim.vehicles.VibrationSpec` with its rotor unbalance set from the spec's rotor line.

    Two physical sources put a line at the rotor frequency, and they load different axes:
    the static unbalance u (an in-plane force u Omega² at the arm: mostly yaw) and the hub
    moment U (couple and aerodynamic unbalance, a moment U Omega² in the rotor plane: roll and
    pitch; :class:`sim.vehicles.VibrationSpec`). Their line powers add in the mean over the
    rotors' independent random phases (the cross terms average out), and each is ∝ its source
    squared, so with the mean per-axis powers of ``n_calib`` seeded hovers at the class's
    reference u0 alone (A) and at a reference U0 alone (B),

        P_xy = α A_xy + β B_xy,   P_z = α A_z + β B_z,   u = u0 √α,  U = U0 √β,

    solved for α, β ≥ 0 in relative terms (non-negative least squares on the two rows divided by
    their targets; exact when both are positive) against the spec band's per-axis line powers
    P_xy = (a_x² + a_y²)/2, P_z = a_z²/2. Then α is rescaled by the yaw power measured at that
    solution (``n_calib`` more hovers): the vibration pulls the rotors' relative phases and with
    them the static unbalance's yaw sum (see the code).

    Parameters
    ----------
    spec : dict
        A vibration spec (:func:`gyrocore.flight.vibration.read_spec`).
    vehicle : str or VehicleClass
    band : int or "middle"
    seed : int
        Seeds the calibration hovers' rotor phases (``SeedSequence([seed, 16 or 17, j])``).
    calib_s : float
        Calibration hover length, s (the first second is left out).
    n_calib : int
        Calibration hovers per source.

    Returns
    -------
    (VibrationSpec, dict)
        The spec for :func:`sim.quadrotor.fly_hover` and what was done (rotor line, the two
        calibration bases, u and U, commanded rotor frequency, relative SE of the mean powers).
    """
    from scipy.optimize import nnls

    from .vehicles import get_vehicle

    veh = get_vehicle(vehicle)
    line = rotor_line(spec, band)
    v0 = veh.vibration
    if not v0.imbalance_kg_m > 0:
        raise GyroInputError(f"vehicle {veh.name} has no default imbalance to calibrate")
    if int(n_calib) < 1:
        raise GyroInputError("n_calib must be >= 1")
    u0 = v0.imbalance_kg_m
    hub0 = v0.hub_moment_kg_m2 if v0.hub_moment_kg_m2 > 0 else u0 * 0.01
    pa, f_a = _calibration_powers(
        veh, replace(v0, hub_moment_kg_m2=0.0), seed=seed, tag=16, calib_s=calib_s, n_calib=n_calib
    )
    has_hub = True
    try:
        pb, f_b = _calibration_powers(
            veh,
            replace(v0, imbalance_kg_m=0.0, hub_moment_kg_m2=hub0),
            seed=seed,
            tag=17,
            calib_s=calib_s,
            n_calib=n_calib,
        )
    except GyroInputError:  # a model without couple-imbalance bodies (the F450): static unbalance alone
        has_hub, pb = False, np.zeros_like(pa)
    a = line.amplitude_rad_s
    target = np.array([(a["x"] ** 2 + a["y"] ** 2) / 2.0, a["z"] ** 2 / 2.0])
    A = np.array([pa[:, 0:2].sum(axis=1).mean(), pa[:, 2].mean()])
    B = np.array([pb[:, 0:2].sum(axis=1).mean(), pb[:, 2].mean()])
    if not (A.sum() > 0):
        raise GyroInputError(f"vehicle {veh.name}: no rotor line in the calibration hovers")
    w = 1.0 / np.maximum(target, 1e-3 * target.max())  # relative residuals; an absent axis still counts
    M = np.column_stack([A, B]) * w[:, None]
    coef, _ = nnls(M, target * w)
    alpha, beta = float(coef[0]), float(coef[1])
    # Stage 2, yaw at the operating point: the static unbalance's yaw line is a sum of four rotor
    # phasors, and the vibration itself pulls the rotors' relative phases (self-synchronisation on
    # the common frame; a large hub moment more so), so the yaw power per unit α measured with the
    # static unbalance alone (A_z) is not the one at the solution. Fly ``n_calib`` more hovers at
    # the solution (u1, U1) and rescale α by target / measured yaw power there. Measured (32 hovers
    # per source, 32 check hovers, band 0 of the shared log): racing25's yaw came out 1.30x its
    # target from the linear solve alone.
    a_z_op = None
    if has_hub and alpha > 0 and beta > 0 and target[1] > 0:
        pz, _ = _calibration_powers(
            veh,
            replace(v0, imbalance_kg_m=u0 * math.sqrt(alpha), hub_moment_kg_m2=hub0 * math.sqrt(beta)),
            seed=seed,
            tag=18,
            calib_s=calib_s,
            n_calib=n_calib,
        )
        a_z_op = float(pz[:, 2].mean()) - beta * B[1]
        if a_z_op > 0:
            alpha = alpha * target[1] / a_z_op
    u, hub = u0 * math.sqrt(alpha), hub0 * math.sqrt(beta)

    def se_rel(p):
        tot = p.sum(axis=1)
        return (
            float(np.std(tot, ddof=1) / math.sqrt(tot.size) / np.mean(tot))
            if tot.size > 1 and np.mean(tot) > 0
            else float("nan")
        )

    pred = alpha * A + beta * B
    info = {
        "vehicle": veh.name,
        "band": line.band,
        "real_line_hz": line.frequency_hz,
        "real_line_amplitude_rad_s": line.amplitude_rad_s,
        "real_line_total_rad_s": line.total_rad_s,
        "real_line_source": line.source,
        "sim_rotor_hz": f_a,
        "calibration_power_xy_z_static": A.tolist(),
        "calibration_power_xy_z_hub": B.tolist(),
        "calibration_imbalance_kg_m": u0,
        "calibration_hub_moment_kg_m2": hub0 if has_hub else 0.0,
        "target_power_xy_z": target.tolist(),
        "fitted_power_xy_z": pred.tolist(),
        "calibration_power_z_at_stage1_solution": a_z_op,
        "n_calib": int(n_calib),
        "calibration_power_se_rel": max(se_rel(pa), se_rel(pb) if has_hub else 0.0),
        "imbalance_kg_m": u,
        "hub_moment_kg_m2": hub,
        "model_has_hub_moment": has_hub,
    }
    return replace(v0, imbalance_kg_m=u, hub_moment_kg_m2=hub), info


def line_exclusion_hz(spec: dict, line_hz: float) -> tuple[tuple[float, float], ...]:
    """± max(3 spec bins, 6 %) around a line the physics carries (the line linker's tolerance):
    the interval the shaped part leaves out so the line is not in the gyro twice."""
    df = float(spec["f_hz"][1]) - float(spec["f_hz"][0])
    half = max(3 * df, _F_TOL * float(line_hz))
    return ((float(line_hz) - half, float(line_hz) + half),)


def carried_bands(spec_band: dict, shaped: dict) -> list[dict]:
    """How much of each energy band of a spec band (format 1.1, ``energy_bands``) the shaped part
    carries: its power over the band's extent on the band's axis, (rad/s)², against the spec's.

    The shaped part is the spec band's PSD (the generator reproduces the grid sum exactly), so a
    band below the spec's reliable limit is carried whole (ratio 1 up to the ± half-bin at the
    edges); the part of a band above that limit is not generated (the shaped part stops there),
    and a rotor line the physics carries is taken out of it only up to its own power.
    """
    f = np.asarray(shaped["f_hz"], float)
    if f.size < 2:
        return []
    df = float(f[1] - f[0])
    out = []
    for e in spec_band.get("energy_bands") or []:
        j = "xyz".index(e["axis"])
        inb = (f >= e["extent_hz"][0]) & (f <= e["extent_hz"][1])
        carried = float(np.sum(np.asarray(shaped["psd_rad2_s2_hz"])[j, inb]) * df)
        out.append(
            {
                "axis": e["axis"],
                "centre_hz": e["centre_hz"],
                "extent_hz": e["extent_hz"],
                "spec_power_rad2_s2": e["power_rad2_s2"],
                "shaped_power_rad2_s2": carried,
                "carried_fraction": carried / e["power_rad2_s2"] if e["power_rad2_s2"] else None,
            }
        )
    return out


def spec_injection(
    spec: dict,
    *,
    band="middle",
    vehicle=None,
    physics: bool = False,
    seed: int = 0,
    n_calib: int = 32,
    calib_s: float = 2.0,
) -> tuple[object, dict, dict]:
    """How a vibration spec enters a simulation: the one path of ``simulate --vibration SPEC
    [--vibration-physics]``, a scenario's ``[vibration]`` section and the experiments.

    Returns ``(hover_vibration, overrides, info)``: ``hover_vibration`` is a
    :class:`sim.vehicles.VibrationSpec` for the rotor physics (``physics=True``: the spec's
    rotor line through :func:`vibration_from_spec`) or None (the class's default);
    ``overrides`` = ``{"vibration": shaped part}`` for :class:`sim.gyro.SyntheticGyro` (the
    registry effect ``vibration``'s parameters, :func:`gyrocore.flight.synthesis.shaped_params`, without
    the rotor line when the physics carries it); ``info`` for the recording's metadata.
    """
    from gyrocore.flight.synthesis import shaped_params, spec_band

    b = spec_band(spec, band)  # a bad band is one error line before anything runs
    hover_vib, sub, info = (
        None,
        (),
        {
            "spec": str(spec.get("source", "")),
            "band": band,
            "band_throttle": b.get("throttle"),
            "band_median": b.get("median"),
        },
    )
    if physics:
        if vehicle is None:
            raise GyroInputError("the spec's rotor line through the physics needs a hover vehicle class")
        hover_vib, pinfo = vibration_from_spec(
            spec, vehicle, band=band, seed=int(seed), n_calib=n_calib, calib_s=calib_s
        )
        # the physics carries the rotor line's power (at the vehicle's own rotor speed): take that
        # power, per axis, out of the shaped part at the real line; the broadband under it stays
        sub = ((pinfo["real_line_hz"], {a: v * v / 2.0 for a, v in pinfo["real_line_amplitude_rad_s"].items()}),)
        info["physics"] = pinfo
    shaped = shaped_params(spec, band=band, subtract_lines=sub)
    info["energy_bands"] = carried_bands(b, shaped)
    info["shaped"] = (
        "registry effect vibration, shaped part: Gaussian disturbance with the spec band's PSD above 40 Hz"
        + (f", without the rotor line's power at {sub[0][0]:.1f} Hz (carried by the physics)" if sub else "")
        + "; added in the gyro's noise stage (sim.noise.ShapedNoise), so a closed loop flies on it"
    )
    return hover_vib, {"vibration": shaped}, info
