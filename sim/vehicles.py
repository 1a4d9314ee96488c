"""Vehicle classes as data: the airframes the closed-loop hover can fly.

Each :class:`VehicleClass` names its MJCF model (``models/*.xml``, whose header comment cites the
source of every constant), the constants the controller needs (:class:`sim.controller.QuadParams`,
the same numbers as the model), its controller gains, its default rotor vibration and its sourced
hover rotor speed. :data:`VEHICLES` is the registry (``sim.quadrotor.fly_hover(vehicle=...)``,
``gyroharness simulate hover --vehicle NAME``, scenario key ``[hover] vehicle``); tests iterate it.

Classes
-------
``f450``
    450-mm quad, 1.4 kg, 10-inch props on 3S (Quan Quan 2017; ``models/quadrotor.xml``). Its
    entries are the former hard-coded defaults (``QuadParams()``, ``ControllerGains()``,
    ``VibrationSpec()``), so its hover is bit for bit what it was.
``racing25``
    The 2.5-inch quad that flew the shared Betaflight log (``models/racing25.xml``: cells and hover
    rotor speed from the log, mass and inertia from a component build-up, c_T = m g / (4 Omega²)),
    physics at 8 kHz (its 327-Hz rotors). Gains from :func:`derive_gains`.
``racing5``
    5-inch racing/freestyle quad, 0.496 kg, 2306 2400-KV motors, 5-inch props on 4S
    (``models/racing5.xml``: Agilicious' 5-inch thrust/torque map and motor time constant,
    mass and inertia from a component build-up). Gains from :func:`derive_gains`.

Gain design rule (:func:`derive_gains`)
---------------------------------------
Rate gains are normalised by the inertia (torque = J x angular acceleration), so the rate loop
is ``L(s) ~ Kp / s`` times the motor lag ``1 / (1 + tau_m s)`` and one sample of delay: its
crossover is ``Kp``. The F450's ``Kp = 15 /s`` with ``tau_m = 20 ms`` gives ``Kp tau_m = 0.3``
(phase margin 90 - atan(0.3) - 0.9 = 72.4 deg). A class keeps that product (same phase margin)
and the F450's ratios: PI zero ``Ki/Kp`` at the same fraction of crossover (``Ki ∝ Kp²``), D
kept (its ratio to P at crossover is ``Kd`` itself), attitude gain the same fraction of the rate
crossover. Yaw: a rotor-speed change reacts on the frame through the motor torque, ``kv / (2
kappa c_T Omega_hover)`` times more than the drag-torque change the mixer assumes at high
frequency (the "yaw coupling", 15.1 on the F450), so the yaw crossover is ``coupling x Kp_yaw``;
it is kept at the F450's ratio to the roll crossover (4.03). Position/altitude loops (omega_n 1-2
rad/s) stay; they sit below the attitude loop of every class here. Applied to the F450's own
constants the rule returns its gains exactly (tested).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from gyrocore.errors import GyroInputError

from .controller import ControllerGains, QuadParams
from .paths import QUADROTOR_XML

__all__ = [
    "VibrationSpec",
    "VehicleClass",
    "VEHICLES",
    "get_vehicle",
    "derive_gains",
    "yaw_coupling",
    "RACING5_XML",
    "RACING25_XML",
]

RACING5_XML = "racing5.xml"
RACING25_XML = "racing25.xml"

# --- the F450 reference of the design rule (models/quadrotor.xml) ---------------------------------
_F450_GAINS = ControllerGains()
_F450_TAU_S = 6e-5 / 0.003  # J_r / kv = 20 ms
_F450_KP_TAU = _F450_GAINS.rate_kp_per_s[0] * _F450_TAU_S  # 0.3


def yaw_coupling(params: QuadParams, hover_rotor_speed_rad_s: float) -> float:
    """High-frequency yaw reaction per unit of the mixer's assumed drag-torque change.

    ``kv / (2 kappa c_T Omega)`` (dimensionless): a thrust change dT asks the rotor speed
    dOmega = dT / (2 c_T Omega); at frequencies above the motor's, the torque that accelerates
    the rotor, kv dOmega, reacts on the frame instead of the drag torque kappa dT.
    """
    return params.motor_kv_n_m_s / (2.0 * params.kappa_m * params.c_t_n_per_rad2_s2 * hover_rotor_speed_rad_s)


_F450_YAW_COUPLING = yaw_coupling(QuadParams(), 557.426)
#: yaw crossover / roll crossover of the F450: coupling x Kp_yaw / Kp_roll = 15.13 x 4 / 15
_F450_YAW_RATIO = _F450_YAW_COUPLING * _F450_GAINS.rate_kp_per_s[2] / _F450_GAINS.rate_kp_per_s[0]


def derive_gains(*, motor_tau_s: float, yaw_coupling_ratio: float) -> ControllerGains:
    """Controller gains by the F450's design rule (module docstring) for a motor lag and yaw coupling.

    Parameters
    ----------
    motor_tau_s : float
        Mechanical time constant of a rotor, ``J_r / kv``, s.
    yaw_coupling_ratio : float
        :func:`yaw_coupling` of the class at its hover rotor speed.

    Returns
    -------
    ControllerGains
        Rate Kp = 0.3 / tau_m (roll, pitch), Ki = 10 (Kp/15)², Kd 0.05, attitude 6 Kp/15; yaw Kp
        such that coupling x Kp_yaw / Kp = 4.03, yaw Ki = 2 (Kp_yaw/4)², yaw attitude 2.5 Kp_yaw/4.
        Everything else as the F450.
    """
    if not (motor_tau_s > 0 and yaw_coupling_ratio > 0):
        raise GyroInputError("derive_gains needs motor_tau_s > 0 and yaw_coupling_ratio > 0")
    g = _F450_GAINS
    kp = _F450_KP_TAU / motor_tau_s
    r = kp / g.rate_kp_per_s[0]
    kp_y = _F450_YAW_RATIO * kp / yaw_coupling_ratio
    ry = kp_y / g.rate_kp_per_s[2]
    return replace(
        g,
        rate_kp_per_s=(kp, kp, kp_y),
        rate_ki_per_s2=(g.rate_ki_per_s2[0] * r * r, g.rate_ki_per_s2[1] * r * r, g.rate_ki_per_s2[2] * ry * ry),
        rate_kd=g.rate_kd,
        att_kp_per_s=(g.att_kp_per_s[0] * r, g.att_kp_per_s[1] * r, g.att_kp_per_s[2] * ry),
    )


@dataclass(frozen=True)
class VibrationSpec:
    """Rotor vibration sources (all reach the IMU only through the rigid-body physics).

    Parameters
    ----------
    imbalance_kg_m : float
        Rotating imbalance u = m r of each rotor, kg m. Force u Omega^2 at the rotor frequency:
        2e-6 kg m (20 mg at the 10 cm prop radius, a poorly balanced hobby prop; ISO 1940 G6.3
        for a 30 g rotor at 5300 rpm is 3.4e-7) gives 0.62 N per rotor in hover.
    harmonic2_ratio : float
        In-plane force at twice the rotor frequency, relative to the imbalance force.
    blade_pass_ripple : float
        Axial thrust ripple at the blade-pass frequency (2 blades: 2 x rotor), fraction of thrust.
    hub_moment_kg_m2 : float
        Rotating once-per-revolution moment in the rotor plane per Omega², kg m² (N m per
        (rad/s)²): the couple (dynamic) unbalance U_c of ISO 21940-11 (mass distributed out of the
        rotor plane; the static unbalance is ``imbalance_kg_m``), and the aerodynamic unbalance of
        a stiff prop (blade-to-blade thrust or pitch difference dT acting at the blades' thrust
        radius r_T: dT r_T, also ∝ Omega²) have this one form. It acts on the frame about the
        body x/y axes, so its line is on roll and pitch, where an in-plane force u Omega² at the
        arm a mostly yaws the frame (moment u Omega² a about z; about x/y only through the rotor
        height above the centre of mass). Built as two point masses on the rotor at ±h above and
        below its plane, opposite each other (``rotor_i_couple_a/b`` in the model): pure MuJoCo
        dynamics, as the static imbalance. Default 0 (the F450 has none).
    """

    imbalance_kg_m: float = 2e-6
    harmonic2_ratio: float = 0.3
    blade_pass_ripple: float = 0.02
    hub_moment_kg_m2: float = 0.0

    def __post_init__(self) -> None:
        if min(self.imbalance_kg_m, self.harmonic2_ratio, self.blade_pass_ripple, self.hub_moment_kg_m2) < 0:
            raise GyroInputError("vibration amplitudes must be >= 0")


@dataclass(frozen=True)
class VehicleClass:
    """One airframe: model file, controller constants and gains, default vibration, sources.

    Parameters
    ----------
    name : str
        Registry key (``--vehicle NAME``).
    description : str
    model_xml : str
        File in ``models/`` (its header comment cites every constant).
    params : QuadParams
        The model's constants as the controller needs them (mass incl. imbalance masses).
    gains : ControllerGains
    vibration : sim.vehicles.VibrationSpec
        Default rotor vibration (``fly_hover(vibration=True)``).
    rotor_spin_inertia_kg_m2 : float
        J_r of one rotor (prop + bell), kg m² (as in the model).
    hover_rotor_speed_rad_s : float
        Sourced hover rotor speed sqrt(m g / (4 c_T)) as written in the model's header and its
        ``hover`` keyframe, rad/s.
    sources : tuple of str
        One line per constant group: where it comes from.
    physics_rate_hz : float
        Physics step rate the class needs, Hz (default 1 kHz; faster rotors need more steps per
        revolution: racing25's 327-Hz rotors fly at 8 kHz, 24 steps per revolution).
    """

    name: str
    description: str
    model_xml: str
    params: QuadParams
    gains: ControllerGains
    vibration: object
    rotor_spin_inertia_kg_m2: float
    hover_rotor_speed_rad_s: float
    sources: tuple[str, ...] = field(default_factory=tuple)
    physics_rate_hz: float = 1000.0

    @property
    def motor_tau_s(self) -> float:
        """Mechanical time constant of a rotor, J_r / kv, s."""
        return self.rotor_spin_inertia_kg_m2 / self.params.motor_kv_n_m_s

    @property
    def hover_rotor_hz(self) -> float:
        """Hover rotor frequency, Hz."""
        return self.hover_rotor_speed_rad_s / (2.0 * math.pi)


def _build() -> dict[str, VehicleClass]:
    f450 = VehicleClass(
        name="f450",
        description="450-mm quad, 1.4 kg, DJI 2212/920KV, 10x4.5 props, 3S (Quan Quan 2017)",
        model_xml=QUADROTOR_XML,
        params=QuadParams(),
        gains=ControllerGains(),
        vibration=VibrationSpec(),
        rotor_spin_inertia_kg_m2=6e-5,
        hover_rotor_speed_rad_s=557.426,
        sources=(
            "mass, inertia, arm, c_T, c_M: Quan Quan, Introduction to Multicopter Design and Control, Springer 2017 (F450)",
            "rotor 30 g, J_r 6e-5 (12 g 10-inch prop m L^2/12), motor tau 20 ms (2212-class, 15-40 ms): models/quadrotor.xml",
        ),
    )
    # racing5: every number as in models/racing5.xml (its header derives them)
    ct, cq = 1.562522e-6, 1.908873e-8
    mass = 0.496 + 4 * 5e-5
    j_r, tau = 8e-6, 0.033
    a = 0.077782
    rp = QuadParams(
        mass_kg=mass,
        inertia_kg_m2=(1.2355e-3, 1.4656e-3, 2.4067e-3),
        c_t_n_per_rad2_s2=ct,
        kappa_m=cq / ct,
        spin=(1, 1, -1, -1),
        rotor_xy_m=((a, -a), (-a, a), (a, a), (-a, -a)),
        motor_kv_n_m_s=j_r / tau,
        max_thrust_n=13.4,
        gravity_m_s2=9.81,
    )
    omega_h = 882.510  # sqrt(m g / (4 c_T)) = sqrt(1.21693 / 1.562522e-6), models/racing5.xml
    racing5 = VehicleClass(
        name="racing5",
        description="5-inch racing quad, 0.50 kg, 2306 2400KV, 5-inch tri-blade props, 4S",
        model_xml=RACING5_XML,
        params=rp,
        gains=derive_gains(motor_tau_s=tau, yaw_coupling_ratio=yaw_coupling(rp, omega_h)),
        vibration=VibrationSpec(imbalance_kg_m=5e-7, harmonic2_ratio=0.3, blade_pass_ripple=0.02),
        rotor_spin_inertia_kg_m2=j_r,
        hover_rotor_speed_rad_s=omega_h,
        sources=(
            "c_T 1.562522e-6, c_Q 1.908873e-8, motor tau 33 ms: agilib (Agilicious, Foehn et al., Sci. Robotics 2022)",
            "mass 0.496 kg, inertia, arm 0.110 m: component build-up (models/racing5.xml header)",
            "J_r 8e-6: 4.5 g 5-inch prop m L^2/12 + 10 g bell ring (estimate)",
            "imbalance 5e-7 kg m: the F450's prop-quality rule scaled to a 4.5 g prop (estimate)",
        ),
    )
    # racing25: the 2.5-inch quad of the shared Betaflight log, every number as in models/racing25.xml
    omega_h25 = 2054.6  # the log's roll rotor line at the hover command (models/racing25.xml header)
    mass25 = 0.1498 + 4 * 6.5e-6
    ct25 = mass25 * 9.81 / (4.0 * omega_h25**2)
    j_r25, tau25 = 5.75e-7, 0.020
    a25 = 0.038891
    p25 = QuadParams(
        mass_kg=mass25,
        inertia_kg_m2=(1.1348e-4, 1.2873e-4, 2.0257e-4),
        c_t_n_per_rad2_s2=ct25,
        kappa_m=0.0061085,
        spin=(1, 1, -1, -1),
        rotor_xy_m=((a25, -a25), (-a25, a25), (a25, a25), (-a25, -a25)),
        motor_kv_n_m_s=j_r25 / tau25,
        max_thrust_n=1.42,
        gravity_m_s2=9.81,
    )
    racing25 = VehicleClass(
        name="racing25",
        description="2.5-inch quad of the shared Betaflight log (CS110), 0.15 kg, 1105-class ~4500KV, 3S",
        model_xml=RACING25_XML,
        params=p25,
        gains=derive_gains(motor_tau_s=tau25, yaw_coupling_ratio=yaw_coupling(p25, omega_h25)),
        vibration=VibrationSpec(
            imbalance_kg_m=6.5e-8, harmonic2_ratio=0.3, blade_pass_ripple=0.02, hub_moment_kg_m2=1.04e-11
        ),
        rotor_spin_inertia_kg_m2=j_r25,
        hover_rotor_speed_rad_s=omega_h25,
        physics_rate_hz=8000.0,
        sources=(
            "3S: the log's vbatref 125 (12.5 V at arming) and vbatLatest (median 11.0 V); hover rotor 327.0 Hz: the "
            "log's roll rotor line law at the hover command 0.21 (models/racing25.xml header)",
            "KV ~4500: the line law at full command, 38,650 rpm = 0.77 x KV x 11.1 V (estimate)",
            "mass 0.150 kg, inertia, 110-mm diagonal: component build-up (estimates, models/racing25.xml header)",
            "c_T = m g / (4 Omega_h^2) = 8.70e-8 (Agilicious 5-inch c_T x (2.5/5)^4 = 9.77e-8); kappa 0.0061 m: "
            "Agilicious' scaled by D",
            "J_r 5.75e-7 (1.2 g prop + 3.5 g bell); motor tau 20 ms: estimate (the F450 model's)",
            "imbalance 6.5e-8 kg m: the F450's prop-quality rule on a 1.2 g prop; hub moment 1.04e-11 kg m^2: a 1 % "
            "blade-to-blade thrust difference at 0.75 R in hover, 0.01 x T/2 x 0.75 R / Omega^2 (estimate); both "
            "are set from a spec by sim.spec_vibration",
        ),
    )
    return {v.name: v for v in (f450, racing5, racing25)}


_REGISTRY: dict[str, VehicleClass] | None = None


def vehicles() -> dict[str, VehicleClass]:
    """The registry {name: VehicleClass} (built on first use)."""
    global _REGISTRY
    if _REGISTRY is None:
        _REGISTRY = _build()
    return _REGISTRY


class _Registry:
    """Mapping view of the registry (``VEHICLES["racing5"]``, iteration in registration order)."""

    def __getitem__(self, name: str) -> VehicleClass:
        return get_vehicle(name)

    def __iter__(self):
        return iter(vehicles())

    def __len__(self) -> int:
        return len(vehicles())

    def __contains__(self, name) -> bool:
        return name in vehicles()

    def keys(self):
        return vehicles().keys()

    def values(self):
        return vehicles().values()

    def items(self):
        return vehicles().items()


VEHICLES = _Registry()


def get_vehicle(vehicle: str | VehicleClass) -> VehicleClass:
    """A class by name (or the class itself); an unknown name is one error line listing the known."""
    if isinstance(vehicle, VehicleClass):
        return vehicle
    reg = vehicles()
    key = str(vehicle).strip().lower()
    if key not in reg:
        raise GyroInputError(f"unknown vehicle class '{vehicle}'; known: {', '.join(reg)}")
    return reg[key]
