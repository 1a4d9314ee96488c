"""Die temperature of the IMU: a first-order thermal model with an optional heater.

Model (one thermal node, the die plus its board neighbourhood), with every heat input written
as the steady-state temperature rise it would cause::

    tau * dT/dt = -(T - T_amb(t)) + dT_self + k_motor * P_motor(t) + R_heater * P_heater(t)

* ``T_amb(t)`` ambient, piecewise linear through ``ThermalSpec.ambient_c`` break points
  (constant, or warm-up / cool-down ramps);
* ``dT_self`` self-heating of the sensor (°C above ambient in steady state);
* ``P_motor`` rotor (aerodynamic) power of a multirotor, W, ``k_motor`` in °C/W;
* ``P_heater`` the heater of a constant-temperature IMU, W, set by a PI controller on the
  die temperature with set point ``HeaterSpec.setpoint_c``, clipped to ``[0, max_power_w]``
  (the approach of temperature-controlled IMUs such as the Pixhawk 4/CUAV IMU heaters).

Discretisation is exact for inputs that are linear in time between samples (ambient: first-
order hold) or constant between samples (motor power, heater power: zero-order hold), with
``a = exp(-h/tau)`` per step ``h``::

    T[k+1] = a T[k] + (1-a) u[k] + (u[k+1]-u[k]) (1 - tau (1-a)/h) + (1-a) z[k]

where ``u`` is ambient plus self-heating and ``z`` the zero-order-held heat inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

from gyrocore.errors import GyroInputError

__all__ = [
    "HeaterSpec",
    "ThermalSpec",
    "ThermalState",
    "TemperatureChunks",
    "ambient_ramps",
    "simulate_temperature",
]


@dataclass(frozen=True)
class HeaterSpec:
    """Heater of a constant-temperature IMU, PI-controlled on the die temperature.

    Parameters
    ----------
    setpoint_c : float
        Die temperature to hold, °C (must be above the ambient plus other heating).
    max_power_w : float
        Heater power limit, W (the PI output is clipped to ``[0, max_power_w]``).
    heater_c_per_w : float
        Steady-state die temperature rise per heater watt, °C/W (thermal resistance).
    closed_loop_time_constant_s : float
        Design time constant of the heater loop, s. The PI places both closed-loop poles at
        ``-1/tau_cl`` (critically damped): the characteristic polynomial of plant
        ``R/(tau s + 1)`` with ``kp + ki/s`` is ``tau s^2 + (1 + kp R) s + ki R``, so
        ``kp = (2 tau/tau_cl - 1)/R`` W/°C and ``ki = tau/(R tau_cl^2)`` W/(°C s). An ambient
        ramp of slope ``r`` leaves the steady error ``r / (ki R) = r tau_cl^2 / tau`` (°C),
        approached monotonically.
    """

    setpoint_c: float = 45.0
    max_power_w: float = 4.0
    heater_c_per_w: float = 10.0
    closed_loop_time_constant_s: float = 10.0

    def gains(self, time_constant_s: float) -> tuple[float, float]:
        """PI gains ``(kp W/°C, ki W/(°C s))`` for a plant of time constant ``time_constant_s``."""
        tau, tcl, r = time_constant_s, self.closed_loop_time_constant_s, self.heater_c_per_w
        kp = max(0.0, 2.0 * tau / tcl - 1.0) / r
        return kp, tau / (r * tcl * tcl)


@dataclass(frozen=True)
class ThermalSpec:
    """First-order thermal model of the sensor die.

    Parameters
    ----------
    time_constant_s : float
        Thermal time constant tau, s (die + board; tens to hundreds of seconds).
    ambient_c : tuple of (t_s, temp_c)
        Ambient temperature break points, piecewise linear, held flat outside (°C).
    self_heating_c : float
        Steady-state rise of the die over ambient from its own dissipation, °C.
    motor_c_per_w : float
        Steady-state rise per watt of rotor power (multirotor motors warming the board), °C/W.
    initial_temp_c : float or None
        Die temperature at power-up (t = first sample); None = ambient at that time.
    heater : HeaterSpec or None
        Constant-temperature IMU heater; None = no heater.
    """

    time_constant_s: float = 120.0
    ambient_c: tuple[tuple[float, float], ...] = ((0.0, 25.0),)
    self_heating_c: float = 0.0
    motor_c_per_w: float = 0.0
    initial_temp_c: float | None = None
    heater: HeaterSpec | None = None

    def __post_init__(self) -> None:
        if not (self.time_constant_s > 0 and math.isfinite(self.time_constant_s)):
            raise GyroInputError(f"thermal time constant must be > 0 s, got {self.time_constant_s}")
        pts = tuple((float(t), float(c)) for t, c in self.ambient_c)
        if not pts:
            raise GyroInputError("thermal ambient_c needs at least one (t_s, temp_c) point")
        if any(b[0] <= a[0] for a, b in zip(pts, pts[1:])):
            raise GyroInputError("thermal ambient_c times must be strictly increasing")
        object.__setattr__(self, "ambient_c", pts)

    @classmethod
    def constant(cls, temp_c: float = 25.0, **kw) -> "ThermalSpec":
        """Constant ambient ``temp_c`` (°C); other fields by keyword."""
        return cls(ambient_c=((0.0, float(temp_c)),), **kw)

    def ambient_at(self, t_s: np.ndarray) -> np.ndarray:
        """Ambient temperature at times ``t_s`` (s), °C, same shape."""
        tp = np.array([p[0] for p in self.ambient_c])
        cp = np.array([p[1] for p in self.ambient_c])
        return np.interp(np.asarray(t_s, dtype=float), tp, cp)


def ambient_ramps(
    *,
    start_c: float,
    peak_c: float,
    start_s: float,
    ramp_s: float,
    hold_s: float,
    end_c: float | None = None,
) -> tuple[tuple[float, float], ...]:
    """Break points of a warm-up / hold / cool-down ambient profile.

    Flat at ``start_c`` until ``start_s``, linear ramp to ``peak_c`` over ``ramp_s``, hold
    ``hold_s``, linear ramp back to ``end_c`` (default ``start_c``) over ``ramp_s``. °C, s.
    """
    if ramp_s <= 0 or hold_s < 0 or start_s < 0:
        raise GyroInputError("ambient ramps need ramp_s > 0, hold_s >= 0, start_s >= 0")
    end = start_c if end_c is None else end_c
    t1 = start_s + ramp_s
    t2 = t1 + hold_s
    pts = [(0.0, start_c)] if start_s > 0 else []
    pts += [(start_s, start_c), (t1, peak_c)]
    if hold_s > 0:
        pts.append((t2, peak_c))
    pts.append((t2 + ramp_s, end))
    return tuple((float(t), float(c)) for t, c in pts)


@dataclass
class ThermalState:
    """Streaming form of the thermal model, one step at a time (closed-loop flight).

    Create with :meth:`start`; call :meth:`step` with the interval and the inputs held over
    it; ``temp_c`` is the die temperature at the current time. Bit-identical to
    :func:`simulate_temperature` on the same samples when used with the same inputs.
    """

    spec: ThermalSpec
    t_s: float
    temp_c: float
    integ_w: float = 0.0
    heater_w: float = 0.0
    _amb_c: float = field(default=0.0, repr=False)

    @classmethod
    def start(cls, spec: ThermalSpec, t0_s: float = 0.0) -> "ThermalState":
        """State at power-up time ``t0_s`` (s)."""
        amb = float(spec.ambient_at(np.array([t0_s]))[0])
        temp = amb if spec.initial_temp_c is None else float(spec.initial_temp_c)
        st = cls(spec=spec, t_s=float(t0_s), temp_c=temp, _amb_c=amb)
        st._update_heater(0.0)
        return st

    def _update_heater(self, h_s: float) -> None:
        heater = self.spec.heater
        if heater is None:
            return
        kp, ki = heater.gains(self.spec.time_constant_s)
        err = heater.setpoint_c - self.temp_c
        integ = self.integ_w + ki * err * h_s
        p = kp * err + integ
        # conditional integration (anti-windup): keep the integral only while not saturated
        if 0.0 <= p <= heater.max_power_w:
            self.integ_w = integ
        self.heater_w = min(max(p, 0.0), heater.max_power_w)

    def step(self, t_next_s: float, *, motor_power_w: float = 0.0, ambient_c: float | None = None) -> float:
        """Advance to ``t_next_s`` (s) with ``motor_power_w`` (W) held; return die temp, °C.

        ``ambient_c`` is the ambient at ``t_next_s`` if the caller has it precomputed (saves
        an interpolation per step); default: from the spec.
        """
        spec = self.spec
        h = t_next_s - self.t_s
        if h <= 0:
            raise GyroInputError("thermal step needs increasing times")
        amb_next = float(spec.ambient_at(np.array([t_next_s]))[0]) if ambient_c is None else float(ambient_c)
        a = math.exp(-h / spec.time_constant_s)
        c1 = 1.0 - spec.time_constant_s * (1.0 - a) / h
        z = spec.motor_c_per_w * motor_power_w
        if spec.heater is not None:
            z += spec.heater.heater_c_per_w * self.heater_w
        u0 = self._amb_c + spec.self_heating_c
        u1 = amb_next + spec.self_heating_c
        self.temp_c = a * self.temp_c + (1.0 - a) * (u0 + z) + (u1 - u0) * c1
        self.t_s = float(t_next_s)
        self._amb_c = amb_next
        self._update_heater(h)
        return self.temp_c


def _rounding_atol(t_first: float, t_last: float) -> float:
    """What the rounding of the times themselves does to their differences: 4 ulp of the largest
    |t|. A clock k/rate is uniform, but its differences vary by an ulp of t, which exceeds
    1e-9 of the interval beyond ~2 h at 1 kHz (ulp(8192 s) = 1.8e-12 s)."""
    return 4.0 * float(np.spacing(max(abs(float(t_first)), abs(float(t_last)))))


def simulate_temperature(t_s: np.ndarray, spec: ThermalSpec, *, motor_power_w: np.ndarray | None = None) -> np.ndarray:
    """Die temperature at the sample times.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Sample times, s, strictly increasing; the first one is the power-up.
    spec : ThermalSpec
        The thermal model.
    motor_power_w : ndarray, shape (N,), optional
        Rotor power at each sample, W, held until the next sample (zero-order hold).

    Returns
    -------
    ndarray, shape (N,)
        Die temperature, °C. Exact for ambient linear between samples and heat inputs
        constant between samples (see the module docstring); without a heater and with a
        uniform sample interval the recursion is evaluated by :func:`scipy.signal.lfilter`.
    """
    t = np.asarray(t_s, dtype=float)
    if t.ndim != 1 or t.size == 0:
        raise GyroInputError("simulate_temperature needs a non-empty 1-D time array")
    n = t.size
    if n > 1 and np.any(np.diff(t) <= 0):
        raise GyroInputError("simulate_temperature needs strictly increasing times")
    p_m = np.zeros(n) if motor_power_w is None else np.asarray(motor_power_w, dtype=float)
    if p_m.shape != (n,):
        raise GyroInputError(f"motor_power_w must have shape ({n},), got {p_m.shape}")
    out = np.empty(n)
    if n == 1:
        st = ThermalState.start(spec, t[0])
        out[0] = st.temp_c
        return out
    h = np.diff(t)
    uniform = np.allclose(h, h[0], rtol=1e-9, atol=_rounding_atol(t[0], t[-1]))
    if spec.heater is None and uniform:
        tau = spec.time_constant_s
        a = math.exp(-h[0] / tau)
        c1 = 1.0 - tau * (1.0 - a) / h[0]
        u = spec.ambient_at(t) + spec.self_heating_c
        z = spec.motor_c_per_w * p_m
        v = (1.0 - a) * (u[:-1] + z[:-1]) + (u[1:] - u[:-1]) * c1
        t0 = u[0] - spec.self_heating_c if spec.initial_temp_c is None else spec.initial_temp_c
        out[0] = t0
        out[1:] = lfilter([1.0], [1.0, -a], v, zi=[a * t0])[0]
        return out
    st = ThermalState.start(spec, t[0])
    out[0] = st.temp_c
    for k in range(1, n):
        out[k] = st.step(t[k], motor_power_w=p_m[k - 1])
    return out


class TemperatureChunks:
    """:func:`simulate_temperature` evaluated in consecutive chunks of sample times (one power-up).

    ``take(t_chunk)`` returns the die temperature at those times, bit-identical to the
    matching rows of ``simulate_temperature(t_all, spec)`` however the times are cut: the
    uniform no-heater path carries the recursion's memory (``lfilter``'s final state) and the
    last input sample; the heater path carries the :class:`ThermalState`.

    Parameters
    ----------
    spec : ThermalSpec
        The thermal model.
    n_total : int, optional
        Number of samples of the whole series, when known (a one-sample series starts from
        :meth:`ThermalState.start`, as :func:`simulate_temperature` does).

    Notes
    -----
    The sample interval is taken from the first two times (as the whole-series path does);
    times after it must stay uniform to rtol 1e-9 plus the rounding of t (the whole-series
    path's test) — sample clocks of the rate table always are. Non-uniform
    times with a heater go through the step loop like the whole-series path.
    """

    def __init__(self, spec: ThermalSpec, *, n_total: int | None = None) -> None:
        self.spec = spec
        self.n_total = n_total
        self.position = 0
        self._state: ThermalState | None = None
        self._a = self._c1 = self._h0 = self._t0 = None
        self._zi = None
        self._u_prev = self._z_prev = self._t_prev = None
        self._p_prev = 0.0

    def take(self, t_s: np.ndarray, *, motor_power_w: np.ndarray | None = None) -> np.ndarray:
        """Die temperature, °C, at the next times ``t_s`` (s, shape (m,))."""
        t = np.asarray(t_s, dtype=float)
        m = t.shape[0]
        if t.ndim != 1:
            raise GyroInputError("TemperatureChunks.take needs a 1-D time array")
        p_m = np.zeros(m) if motor_power_w is None else np.asarray(motor_power_w, dtype=float)
        if p_m.shape != (m,):
            raise GyroInputError(f"motor_power_w must have shape ({m},), got {p_m.shape}")
        if m == 0:
            return np.empty(0)
        spec = self.spec
        first = self.position == 0
        if first and self.n_total == 1:
            self.position += m
            return simulate_temperature(t, spec, motor_power_w=p_m)
        tt = t if first else np.concatenate([[self._t_prev], t])
        if tt.size > 1 and np.any(np.diff(tt) <= 0):
            raise GyroInputError("simulate_temperature needs strictly increasing times")
        if self._h0 is None and tt.size > 1:
            self._h0 = float(tt[1] - tt[0])  # the whole series' first interval
        if tt.size > 1:
            uniform = np.allclose(np.diff(tt), self._h0, rtol=1e-9, atol=_rounding_atol(tt[0], tt[-1]))
        else:
            uniform = True
        out = np.empty(m)
        if spec.heater is None:
            if not uniform:
                raise GyroInputError("TemperatureChunks: sample times must be uniform (no heater)")
            u = spec.ambient_at(t) + spec.self_heating_c
            z = spec.motor_c_per_w * p_m
            if first:  # the power-up sample; the recursion continues from it
                t0 = u[0] - spec.self_heating_c if spec.initial_temp_c is None else spec.initial_temp_c
                out[0] = self._t0 = t0
                uu, zz, rows = u, z, slice(1, m)
            else:
                uu = np.concatenate([[self._u_prev], u])
                zz = np.concatenate([[self._z_prev], z])
                rows = slice(0, m)
            if uu.size > 1:
                if self._a is None:  # first interval known: as the whole-series path, a and c1 from it
                    tau = spec.time_constant_s
                    self._a = math.exp(-self._h0 / tau)
                    self._c1 = 1.0 - tau * (1.0 - self._a) / self._h0
                    self._zi = [self._a * self._t0]
                a, c1 = self._a, self._c1
                v = (1.0 - a) * (uu[:-1] + zz[:-1]) + (uu[1:] - uu[:-1]) * c1
                out[rows], self._zi = lfilter([1.0], [1.0, -a], v, zi=self._zi)
            self._u_prev, self._z_prev = float(u[-1]), float(z[-1])
        else:
            if first:
                self._state = ThermalState.start(spec, t[0])
                out[0] = self._state.temp_c
                k0 = 1
            else:
                k0 = 0
            st = self._state
            for k in range(k0, m):
                out[k] = st.step(t[k], motor_power_w=(p_m[k - 1] if k > 0 else self._p_prev))
            self._p_prev = float(p_m[-1])
        self._t_prev = float(t[-1])
        self.position += m
        return out


class TempRateBlocks:
    """dT/dt of the die temperature on the clock ``t_k = k · (1 / rate_hz)``, block by block.

    ``take(m)`` returns the next m values of
    ``gyrocore.effects.registry.ModelInputs(t_s=t, temp_c=simulate_temperature(t, spec)).temp_rate_c_s()``
    for the whole clock of ``n_total`` samples, bit for bit, however the record is cut
    (the closed-loop gyro's ``bias_temp_rate`` without the whole trajectory). That
    is ``numpy.gradient(T, t)`` (edge_order 1), transcribed: central differences inside —
    the uniform-spacing formula when every difference of the whole clock equals the first
    (numpy's test; checked block by block before the first block), else the non-uniform
    three-point one — and one-sided at the two ends. The temperature comes from
    :class:`TemperatureChunks`, one sample ahead of the block.

    Parameters
    ----------
    spec : ThermalSpec
        The die temperature model (one power-up at t = 0).
    n_total : int
        Samples of the whole record (>= 2).
    rate_hz : float
        Sample rate, Hz.
    """

    _CHECK_ROWS = 1 << 20

    def __init__(self, spec: ThermalSpec, n_total: int, rate_hz: float) -> None:
        self.n = int(n_total)
        if self.n < 2:
            raise GyroInputError("dT/dt needs at least two samples")
        self.dt = 1.0 / float(rate_hz)
        self._temp = TemperatureChunks(spec, n_total=self.n)
        d0 = float(np.arange(1, 2)[0] * self.dt - np.arange(0, 1)[0] * self.dt)
        uniform = True
        for a in range(0, self.n - 1, self._CHECK_ROWS):  # numpy: (diff(t) == diff(t)[0]).all()
            b = min(self.n, a + self._CHECK_ROWS + 1)
            if not np.all(np.diff(self._clock(a, b)) == d0):
                uniform = False
                break
        self._dx0 = d0 if uniform else None
        self.position = 0
        # the last two samples already generated (t, T): the block's left neighbour and one ahead
        self._t = np.empty(0)
        self._T = np.empty(0)
        self._generated = 0

    def _clock(self, a: int, b: int) -> np.ndarray:
        return np.arange(a, b) * self.dt

    def _generate(self, upto: int) -> None:
        """Extend the held window with the temperature of samples up to ``upto`` (exclusive)."""
        if upto > self._generated:
            t = self._clock(self._generated, upto)
            self._t = np.concatenate([self._t, t])
            self._T = np.concatenate([self._T, self._temp.take(t)])
            self._generated = upto

    def take(self, m: int) -> np.ndarray:
        """dT/dt, °C/s, of the next ``m`` samples, shape (m,)."""
        m = int(m)
        k0, k1 = self.position, self.position + m
        if m < 0 or k1 > self.n:
            raise GyroInputError(f"TempRateBlocks.take: {m} samples from {k0} exceed the {self.n} of the record")
        if m == 0:
            return np.empty(0)
        self._generate(min(k1 + 1, self.n))
        w0 = self._generated - self._t.shape[0]  # global index of the held window's row 0
        lo = max(k0 - 1, 0)
        t = self._t[lo - w0 :]
        f = self._T[lo - w0 :]
        out = np.empty(f.shape[0])
        if f.shape[0] > 2:
            if self._dx0 is not None:
                out[1:-1] = (f[2:] - f[:-2]) / (2.0 * self._dx0)
            else:
                dx = np.diff(t)
                dx1 = dx[0:-1]
                dx2 = dx[1:]
                a = -(dx2) / (dx1 * (dx1 + dx2))
                b = (dx2 - dx1) / (dx1 * dx2)
                c = dx1 / (dx2 * (dx1 + dx2))
                out[1:-1] = a * f[:-2] + b * f[1:-1] + c * f[2:]
        if k0 == 0:  # numpy's first-order edges: out[0] = (f[1] − f[0]) / (x[1] − x[0])
            out[0] = (f[1] - f[0]) / (self._dx0 if self._dx0 is not None else t[1] - t[0])
        if k1 == self.n:
            out[-1] = (f[-1] - f[-2]) / (self._dx0 if self._dx0 is not None else t[-1] - t[-2])
        res = out[(k0 - lo) : (k0 - lo) + m].copy()
        # keep the last sample of this block and the one ahead (the next block's neighbours)
        keep = max(k1 - 1, 0)
        self._t = self._t[keep - w0 :].copy()
        self._T = self._T[keep - w0 :].copy()
        self.position = k1
        return res
