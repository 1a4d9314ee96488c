"""Gyro low-pass filters: the article's first-order filter, PT1/PT2/PT3, biquads, Butterworth.

Every filter here is a cascade of second-order sections (SOS, scipy.signal's format, rows
``b0 b1 b2 1 a1 a2``) held by one class, :class:`SosFilter`, which gives

* a batch path, :meth:`SosFilter.apply` (``scipy.signal.sosfilt`` over whole arrays, from a
  zero state or from the steady state of the first sample), and
* a streaming path, :meth:`SosFilter.step` / :meth:`SosFilter.reset`, one (3,) sample at a
  time for closed-loop flight, written with exactly the arithmetic of scipy's transposed
  direct form II (``_sosfilt.pyx``), so that it is **bit-identical** to the batch path;
* :meth:`SosFilter.response`: magnitude and group delay at given frequencies
  (``scipy.signal.sosfreqz`` / ``scipy.signal.group_delay``).

The article's filter (§4) ``A = 1/(1 + 1/(2π·T·fc))``, ``y_k = A·x_k + (1−A)·y_{k−1}``, is
Betaflight's PT1 (gain ``ω/(ω+1)``, ω = 2π·fc·T). Its group delay at low frequency is
(1−A)/A samples = 1/(2π·fc) seconds (5.3 ms at 30 Hz = 2.65 samples at 500 Hz).

PT2/PT3 are Betaflight's cascades of 2 or 3 identical PT1 sections whose cutoff is raised by
``1/√(2^(1/n) − 1)`` so the cascade's −3 dB point stays at fc (Betaflight
``src/main/common/filter.c``: ``pt2FilterGain``, ``pt3FilterGain``). Biquads follow R. Bristow-
Johnson's "Audio EQ Cookbook". Butterworth is ``scipy.signal.butter(..., output="sos")``.

:class:`Pipeline` chains stages (a calibration correction, then a filter) behind the same
``step``/``reset``/``apply`` interface; that is what the closed-loop quadrotor consumes.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import signal

from gyrocore.errors import GyroInputError

__all__ = [
    "RpmNotch",
    "loop_scale",
    "article_lpf_coefficient",
    "pt_cutoff_correction",
    "SosFilter",
    "FilterResponse",
    "article_lpf",
    "pt1",
    "pt2",
    "pt3",
    "biquad_lowpass",
    "biquad_notch",
    "butterworth",
    "identity_filter",
    "make_filter",
    "FILTER_KINDS",
    "AffineCorrection",
    "Pipeline",
    "betaflight_notch_q",
    "betaflight_notch",
    "firmware_stage",
    "chain_filters",
    "chain_response",
]


def loop_scale(meta: dict) -> float:
    """Measured / nominal loop rate of a flight log (``loop_rate_measured_hz`` / ``pid_rate_hz``
    of its metadata): the firmware designs its filters for the nominal loop period and they run
    on the real clock. 1 when the header lacks either or the ratio is outside 0.5-2 (implausible)."""
    try:
        ls = float(meta["loop_rate_measured_hz"]) / float(meta["pid_rate_hz"])
    except (KeyError, ValueError, ZeroDivisionError):
        return 1.0
    return ls if np.isfinite(ls) and 0.5 < ls < 2 else 1.0


def _check_fc(fc_hz: float, rate_hz: float) -> None:
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise GyroInputError(f"sample rate must be positive, got {rate_hz} Hz")
    if not (np.isfinite(fc_hz) and 0 < fc_hz < rate_hz / 2):
        raise GyroInputError(
            f"cutoff {fc_hz} Hz must be in (0, {rate_hz / 2:g}) Hz (the Nyquist frequency at {rate_hz:g} Hz)"
        )


def article_lpf_coefficient(fc_hz: float, rate_hz: float) -> float:
    """The article's first-order low-pass coefficient A = 1/(1 + 1/(2π·T·fc)), T = 1/rate_hz.

    0.27378 at fc = 30 Hz, 500 Hz (the article prints 0.2739).
    """
    _check_fc(fc_hz, rate_hz)
    T = 1.0 / rate_hz
    return 1.0 / (1.0 + 1.0 / (2.0 * math.pi * T * fc_hz))


def pt_cutoff_correction(order: int) -> float:
    """Betaflight's PTn cutoff correction 1/√(2^(1/n) − 1) (1 for n=1, 1.5538 for 2, 1.9615 for 3)."""
    return 1.0 / math.sqrt(2.0 ** (1.0 / order) - 1.0)


@dataclass(frozen=True)
class FilterResponse:
    """Frequency response of a filter.

    Attributes
    ----------
    f_hz : ndarray, shape (M,)
        Frequencies, Hz.
    magnitude : ndarray, shape (M,)
        |H(f)| (linear).
    group_delay_s : ndarray, shape (M,)
        Group delay, s (−dφ/dω).
    """

    f_hz: np.ndarray
    magnitude: np.ndarray
    group_delay_s: np.ndarray


class SosFilter:
    """A digital filter as second-order sections, for batch and streaming use on (N, 3) data.

    Parameters
    ----------
    sos : ndarray, shape (S, 6)
        Sections ``b0 b1 b2 a0 a1 a2`` with a0 = 1 (scipy.signal's format).
    rate_hz : float
        Sample rate the coefficients were designed for, Hz.
    name : str
        Label, e.g. ``"pt2 30 Hz"``.
    cutoff_hz : float
        Nominal cutoff, Hz (NaN for the identity).
    start : {"zero", "steady"}
        Initial state: ``"zero"`` (output starts from 0) or ``"steady"`` (as if the first
        sample had been applied forever: no start transient; ``scipy.signal.sosfilt_zi``).
    n_channels : int
        Channels of the streaming path (3 for a gyro).
    """

    def __init__(
        self,
        sos,
        *,
        rate_hz: float,
        name: str,
        cutoff_hz: float = float("nan"),
        start: str = "steady",
        n_channels: int = 3,
    ) -> None:
        sos = np.atleast_2d(np.asarray(sos, float))
        if sos.ndim != 2 or sos.shape[1] != 6 or sos.shape[0] < 1:
            raise GyroInputError(f"sos must have shape (S, 6), got {sos.shape}")
        if not np.allclose(sos[:, 3], 1.0):
            sos = sos / sos[:, 3:4]
        if start not in ("zero", "steady"):
            raise GyroInputError(f"start must be 'zero' or 'steady', got {start!r}")
        self.sos = sos
        self.rate_hz = float(rate_hz)
        self.name = name
        self.cutoff_hz = float(cutoff_hz)
        self.start = start
        self.n_channels = int(n_channels)
        self._zi_unit = signal.sosfilt_zi(sos) if sos.shape[0] else np.zeros((0, 2))  # (S, 2)
        self._rows = [tuple(float(c) for c in row) for row in sos]
        self.reset()

    # ------------------------------------------------------------ batch
    def initial_state(self, x0: np.ndarray) -> np.ndarray:
        """State (S, 2, C) for a first sample ``x0`` (C,) under this filter's ``start`` rule."""
        x0 = np.asarray(x0, float)
        if self.start == "zero":
            return np.zeros((self.sos.shape[0], 2) + x0.shape)
        return self._zi_unit[:, :, None] * x0[None, None, :] if x0.ndim else self._zi_unit * x0

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Filter whole arrays along axis 0 (``scipy.signal.sosfilt``); x (N,) or (N, C)."""
        x = np.asarray(x, float)
        if x.shape[0] == 0:
            return x.copy()
        zi = self.initial_state(x[0])
        y, _ = signal.sosfilt(self.sos, x, axis=0, zi=zi)
        return y

    # ------------------------------------------------------------ streaming
    def reset(self) -> None:
        """Forget the state; the next :meth:`step` starts as :meth:`apply` does."""
        self._z = None

    def step(self, x: np.ndarray) -> np.ndarray:
        """Filter one sample x (C,) -> (C,); bit-identical to :meth:`apply` on the stream so far.

        Transposed direct form II per section, the operation order of scipy's ``_sosfilt``.
        Plain Python floats per channel (no numpy temporaries): a numpy expression on a
        3-vector costs more than the arithmetic; this is the closed-loop hover hot path
        (float arithmetic is the same IEEE double arithmetic, so the results are unchanged).
        """
        if type(x) is np.ndarray and x.ndim == 1 and x.dtype == np.float64:
            v = x
        else:
            v = np.array(x, dtype=float)
            if v.ndim != 1:
                return self._step_array(v)
        vals = v.tolist()
        if self._z is None:
            self._z = self.initial_state(v).copy()
            # per section: [z0 of each channel..., z1 of each channel...]
            self._zl = [list(self._z[k, 0]) + list(self._z[k, 1]) for k in range(self._z.shape[0])]
        C = len(vals)
        for zk, (b0, b1, b2, _a0, a1, a2) in zip(self._zl, self._rows):
            for c in range(C):
                xc = vals[c]
                vc = b0 * xc + zk[c]
                zk[c] = b1 * xc - a1 * vc + zk[C + c]
                zk[C + c] = b2 * xc - a2 * vc
                vals[c] = vc
        return np.array(vals)

    def _step_array(self, v: np.ndarray) -> np.ndarray:
        """:meth:`step` for a scalar channel (numpy arithmetic)."""
        if self._z is None:
            self._z = self.initial_state(v).copy()
        z = self._z
        for s, (b0, b1, b2, _a0, a1, a2) in enumerate(self._rows):
            xc = v
            v = b0 * xc + z[s, 0]
            z[s, 0] = b1 * xc - a1 * v + z[s, 1]
            z[s, 1] = b2 * xc - a2 * v
        return v

    __call__ = step

    # ------------------------------------------------------------ analysis
    def response(self, f_hz) -> FilterResponse:
        """Magnitude and group delay at frequencies ``f_hz`` (Hz), via scipy.signal."""
        f = np.atleast_1d(np.asarray(f_hz, float))
        _, h = signal.sosfreqz(self.sos, worN=f, fs=self.rate_hz)
        b, a = signal.sos2tf(self.sos)
        with warnings.catch_warnings():  # at a notch's zero the group delay is singular
            warnings.simplefilter("ignore", UserWarning)
            _, gd = signal.group_delay((b, a), w=f, fs=self.rate_hz)
        return FilterResponse(f_hz=f, magnitude=np.abs(h), group_delay_s=np.asarray(gd) / self.rate_hz)

    def delay_s(self, f_hz: float = 0.0) -> float:
        """Group delay at ``f_hz`` (default DC, the low-frequency delay), s."""
        return float(self.response([f_hz]).group_delay_s[0])

    def magnitude(self, f_hz: float) -> float:
        """|H| at ``f_hz``."""
        return float(self.response([f_hz]).magnitude[0])

    def __repr__(self) -> str:
        return f"SosFilter({self.name!r}, rate_hz={self.rate_hz:g}, sections={self.sos.shape[0]})"


# ---------------------------------------------------------------- constructors
def _first_order_row(k: float) -> list[float]:
    """y_k = k·x_k + (1 − k)·y_{k−1} as an SOS row."""
    return [k, 0.0, 0.0, 1.0, k - 1.0, 0.0]


def article_lpf(fc_hz: float, rate_hz: float, *, start: str = "steady") -> SosFilter:
    """The article's first-order low-pass, A = 1/(1 + 1/(2π·T·fc)) (same as Betaflight PT1)."""
    A = article_lpf_coefficient(fc_hz, rate_hz)
    return SosFilter(
        [_first_order_row(A)], rate_hz=rate_hz, name=f"article 1st-order {fc_hz:g} Hz", cutoff_hz=fc_hz, start=start
    )


def _ptn(order: int, fc_hz: float, rate_hz: float, start: str) -> SosFilter:
    _check_fc(fc_hz, rate_hz)
    fc_sec = fc_hz * pt_cutoff_correction(order)
    if fc_sec >= rate_hz / 2:
        raise GyroInputError(
            f"PT{order} at {fc_hz} Hz needs sections at {fc_sec:.1f} Hz, above Nyquist at {rate_hz:g} Hz"
        )
    w = 2.0 * math.pi * fc_sec / rate_hz
    k = w / (w + 1.0)
    return SosFilter(
        [_first_order_row(k)] * order, rate_hz=rate_hz, name=f"pt{order} {fc_hz:g} Hz", cutoff_hz=fc_hz, start=start
    )


def pt1(fc_hz: float, rate_hz: float, *, start: str = "steady") -> SosFilter:
    """Betaflight PT1: one first-order section, gain ω/(ω+1), ω = 2π·fc/rate."""
    return _ptn(1, fc_hz, rate_hz, start)


def pt2(fc_hz: float, rate_hz: float, *, start: str = "steady") -> SosFilter:
    """Betaflight PT2: two PT1 sections at fc·1.5538 (−3 dB of the cascade at fc)."""
    return _ptn(2, fc_hz, rate_hz, start)


def pt3(fc_hz: float, rate_hz: float, *, start: str = "steady") -> SosFilter:
    """Betaflight PT3: three PT1 sections at fc·1.9615 (−3 dB of the cascade at fc)."""
    return _ptn(3, fc_hz, rate_hz, start)


def _rbj(kind: str, f0_hz: float, rate_hz: float, q: float) -> list[float]:
    _check_fc(f0_hz, rate_hz)
    if not q > 0:
        raise GyroInputError(f"biquad Q must be positive, got {q}")
    w0 = 2.0 * math.pi * f0_hz / rate_hz
    c, alpha = math.cos(w0), math.sin(w0) / (2.0 * q)
    if kind == "lowpass":
        b = [(1 - c) / 2, 1 - c, (1 - c) / 2]
    else:  # notch
        b = [1.0, -2 * c, 1.0]
    a0 = 1 + alpha
    return [b[0] / a0, b[1] / a0, b[2] / a0, 1.0, -2 * c / a0, (1 - alpha) / a0]


def biquad_lowpass(fc_hz: float, rate_hz: float, *, q: float = 1 / math.sqrt(2), start: str = "steady") -> SosFilter:
    """RBJ cookbook biquad low-pass (Q = 1/√2: 2nd-order Butterworth, Betaflight's default)."""
    return SosFilter(
        [_rbj("lowpass", fc_hz, rate_hz, q)], rate_hz=rate_hz, name=f"biquad {fc_hz:g} Hz", cutoff_hz=fc_hz, start=start
    )


def biquad_notch(f0_hz: float, rate_hz: float, *, q: float = 3.0, start: str = "steady") -> SosFilter:
    """RBJ cookbook notch at ``f0_hz`` (bandwidth f0/Q)."""
    return SosFilter(
        [_rbj("notch", f0_hz, rate_hz, q)],
        rate_hz=rate_hz,
        name=f"notch {f0_hz:g} Hz Q{q:g}",
        cutoff_hz=f0_hz,
        start=start,
    )


def butterworth(fc_hz: float, rate_hz: float, *, order: int = 2, start: str = "steady") -> SosFilter:
    """Butterworth low-pass of ``order`` via ``scipy.signal.butter(..., output='sos')``."""
    _check_fc(fc_hz, rate_hz)
    if not 1 <= int(order) <= 10:
        raise GyroInputError(f"Butterworth order must be 1..10, got {order}")
    sos = signal.butter(int(order), fc_hz, fs=rate_hz, output="sos")
    return SosFilter(sos, rate_hz=rate_hz, name=f"butter{order} {fc_hz:g} Hz", cutoff_hz=fc_hz, start=start)


def identity_filter(rate_hz: float) -> SosFilter:
    """No filtering (one pass-through section), for 'unfiltered' rows."""
    return SosFilter([[1.0, 0, 0, 1.0, 0, 0]], rate_hz=rate_hz, name="none", start="zero")


#: Filter kinds accepted by :func:`make_filter`.
FILTER_KINDS = ("none", "article", "pt1", "pt2", "pt3", "biquad", "butter2", "butter4")


def make_filter(kind: str, fc_hz: float, rate_hz: float, *, start: str = "steady") -> SosFilter:
    """Filter by name (:data:`FILTER_KINDS`) and cutoff."""
    if kind == "none":
        return identity_filter(rate_hz)
    if kind == "article":
        return article_lpf(fc_hz, rate_hz, start=start)
    if kind in ("pt1", "pt2", "pt3"):
        return _ptn(int(kind[2]), fc_hz, rate_hz, start)
    if kind == "biquad":
        return biquad_lowpass(fc_hz, rate_hz, start=start)
    if kind.startswith("butter") and kind[6:].isdigit():
        return butterworth(fc_hz, rate_hz, order=int(kind[6:]), start=start)
    raise GyroInputError(f"unknown filter '{kind}'; known: {', '.join(FILTER_KINDS)}")


# ---------------------------------------------------------------- pipeline
class AffineCorrection:
    """Per-sample calibration stage ω = K⁻¹·(y − b) (constant bias, scale, misalignment).

    Parameters
    ----------
    b_rad_s : ndarray, shape (3,)
        Bias to remove, rad/s (sensor frame).
    K : ndarray, shape (3, 3), optional
        Scale/misalignment matrix of the measurement model (gyrocore.effects.registry.k_matrix);
        identity by default.
    """

    def __init__(self, b_rad_s=(0.0, 0.0, 0.0), K=None) -> None:
        self.b_rad_s = np.asarray(b_rad_s, float).reshape(3)
        self.K_inv = np.eye(3) if K is None else np.linalg.inv(np.asarray(K, float).reshape(3, 3))

    @classmethod
    def from_params(cls, params) -> "AffineCorrection":
        """From a parameter mapping ``{effect: {param: array}}`` (uses bias, scale, misalignment)."""
        from gyrocore.effects.registry import k_matrix

        b = np.asarray(params["bias"]["b_rad_s"], float) if "bias" in params else np.zeros(3)
        return cls(b, k_matrix(params))

    def reset(self) -> None:
        """Stateless; present for the stage interface."""

    def step(self, x: np.ndarray) -> np.ndarray:
        """Correct one sample, (3,) -> (3,)."""
        d = np.asarray(x, float) - self.b_rad_s
        Ki = self.K_inv
        return d[0] * Ki[:, 0] + d[1] * Ki[:, 1] + d[2] * Ki[:, 2]

    __call__ = step

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Correct (N, 3) samples; the same elementwise arithmetic as :meth:`step` (bit-identical)."""
        d = np.asarray(x, float) - self.b_rad_s
        Ki = self.K_inv
        return d[:, 0:1] * Ki[:, 0] + d[:, 1:2] * Ki[:, 1] + d[:, 2:3] * Ki[:, 2]


class Pipeline:
    """Stages applied in order (e.g. ``Pipeline([AffineCorrection(b), pt2(80, 1000)])``).

    Each stage has ``step(x (3,)) -> (3,)`` and ``reset()``; stages with ``apply`` are used by
    the batch path. ``pipeline.step(x)`` (or ``pipeline(x)``) is the closed-loop interface.
    """

    def __init__(self, stages: Sequence) -> None:
        self.stages = list(stages)
        for s in self.stages:
            if not callable(getattr(s, "step", None)):
                raise GyroInputError(f"pipeline stage {s!r} has no step(x) method")

    @property
    def name(self) -> str:
        return " -> ".join(getattr(s, "name", type(s).__name__) for s in self.stages) or "none"

    def reset(self) -> None:
        for s in self.stages:
            if hasattr(s, "reset"):
                s.reset()

    def step(self, x: np.ndarray) -> np.ndarray:
        v = np.asarray(x, float)
        for s in self.stages:
            v = s.step(v)
        return v

    __call__ = step

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Batch path: each stage's ``apply`` in turn (fresh state)."""
        v = np.asarray(x, float)
        for s in self.stages:
            v = s.apply(v) if hasattr(s, "apply") else np.stack([s.step(r) for r in v])
        return v

    def delay_s(self, f_hz: float = 0.0) -> float:
        """Sum of the filter stages' group delays at ``f_hz``, s."""
        return float(sum(s.delay_s(f_hz) for s in self.stages if hasattr(s, "delay_s")))


# ---------------------------------------------------------------- firmware chains
def betaflight_notch_q(center_hz: float, cutoff_hz: float) -> float:
    """Betaflight ``filterGetNotchQ`` (src/main/common/filter.c): Q = f0·fc/(f0² − fc²).

    ``cutoff_hz`` is the lower −3 dB edge the pilot sets (``gyro_notch1_cutoff``); 3.1's
    octave form ``√(2^o)/(2^o − 1)``, o = 2·log2(f0/fc), is algebraically the same value.
    """
    if not (0 < cutoff_hz < center_hz):
        raise GyroInputError(f"notch cutoff {cutoff_hz} Hz must be in (0, centre {center_hz} Hz)")
    return center_hz * cutoff_hz / (center_hz * center_hz - cutoff_hz * cutoff_hz)


def betaflight_notch(center_hz: float, cutoff_hz: float, rate_hz: float, *, start: str = "steady") -> SosFilter:
    """Betaflight's static gyro notch: RBJ biquad notch (``biquadFilterInit(..., FILTER_NOTCH)``)
    at ``center_hz`` with Q from :func:`betaflight_notch_q`, run at ``rate_hz``."""
    q = betaflight_notch_q(center_hz, cutoff_hz)
    f = biquad_notch(center_hz, rate_hz, q=q, start=start)
    f.name = f"notch {center_hz:g}/{cutoff_hz:g} Hz"
    return f


def firmware_stage(stage: dict, *, loop_scale: float = 1.0, start: str = "steady") -> SosFilter | None:
    """One static firmware gyro stage (dict of ``gyrocore.readers.blackbox_firmware.FilterStage.to_dict``) as an SosFilter.

    The coefficients are Betaflight's (``pt1FilterGain`` k = ω/(ω+1), ω = 2π·fc·dT;
    PT2/PT3 with the cutoff correction; RBJ biquad low-pass Q = 1/√2; RBJ notch) for the
    nominal loop period ``dT = 1/rate_hz``; the filter then runs on the real clock
    (``rate_hz·loop_scale``), which is how its response is evaluated at physical frequencies.
    ``butter2``/``butter4``/``article`` kinds are accepted for other firmware (PX4's 2nd-order
    Butterworth, ArduPilot's LowPassFilter2p = 2nd-order Butterworth biquad, the article's
    first-order filter). Dynamic stages (dyn_notch, rpm_notch, dyn_lpf) and FIR return None.
    """
    kind = stage["kind"]
    fc = float(stage["cutoff_hz"])
    rate = float(stage["rate_hz"])
    if stage.get("dynamic") or kind in ("fir", "dyn_notch", "rpm_notch", "dyn_lpf"):
        return None
    if kind == "notch":
        q = (
            float(stage["q"])
            if "q" in stage and stage["q"] == stage["q"]
            else betaflight_notch_q(fc, float(stage["notch_cutoff_hz"]))
        )
        flt = biquad_notch(fc, rate, q=q, start=start)
    else:
        flt = make_filter(kind, fc, rate, start=start)
    if loop_scale != 1.0:
        flt = SosFilter(flt.sos, rate_hz=rate * loop_scale, name=flt.name, cutoff_hz=fc, start=start)
    return flt


def chain_filters(stages: Sequence[dict], *, loop_scale: float = 1.0) -> list[SosFilter]:
    """The static stages of a firmware chain as SosFilters (dynamic ones skipped)."""
    out = []
    for s in stages:
        f = firmware_stage(s, loop_scale=loop_scale)
        if f is not None:
            out.append(f)
    return out


def chain_response(stages: Sequence[dict], f_hz, *, loop_scale: float = 1.0) -> FilterResponse:
    """Magnitude (product) and group delay (sum) of a firmware chain's static stages at ``f_hz``.

    Stages may run at different rates (Betaflight 4.2+: LPF2 at the gyro rate, the rest at
    the PID rate); a cascade's magnitude multiplies and its group delay adds.
    """
    f = np.atleast_1d(np.asarray(f_hz, float))
    mag = np.ones_like(f)
    gd = np.zeros_like(f)
    for flt in chain_filters(stages, loop_scale=loop_scale):
        r = flt.response(f)
        mag *= r.magnitude
        gd += r.group_delay_s
    return FilterResponse(f_hz=f, magnitude=mag, group_delay_s=gd)


class RpmNotch:
    """Betaflight's RPM filter: an RBJ biquad notch per rotor and harmonic, tracking rotor speed.

    As Betaflight 4.x ``rpm_filter.c`` (``rpm_filter_harmonics`` 3, ``rpm_filter_q`` 500 = Q 5,
    ``rpm_filter_min_hz`` 100): for each rotor i and harmonic h = 1..``harmonics`` a notch at
    h·f_i, clamped below at ``min_hz``, coefficients recomputed whenever the rotor frequencies
    are updated (the firmware does it from eRPM every loop); a notch at or above 0.48·rate is
    switched off (the firmware fades it out near Nyquist). Direct form II transposed per axis.

    ``set_rotor_hz(f (n_rotors,))`` before ``step``; ``sim.quadrotor.fly_hover`` calls it on
    every gyro sample with the simulator's rotor speeds (|Ω|/2π after the physics step) when
    the pipeline (or a stage) has it.

    Parameters
    ----------
    rate_hz : float
        Sample rate, Hz.
    q : float
    harmonics : int
    min_hz : float
    """

    def __init__(self, rate_hz: float, *, q: float = 5.0, harmonics: int = 3, min_hz: float = 100.0) -> None:
        if not (rate_hz > 0 and q > 0 and int(harmonics) >= 1 and min_hz >= 0):
            raise GyroInputError("RpmNotch needs rate_hz > 0, q > 0, harmonics >= 1, min_hz >= 0")
        self.rate_hz, self.q, self.harmonics, self.min_hz = float(rate_hz), float(q), int(harmonics), float(min_hz)
        self.name = f"rpm notch x{self.harmonics} Q{self.q:g}"
        self._coef: list = []
        self._z: list = []

    def reset(self) -> None:
        self._z = [[0.0] * 6 for _ in self._coef]

    def set_rotor_hz(self, rotor_hz) -> None:
        """Retune to these rotor frequencies (Hz, one per rotor); filter states are kept."""
        coef = []
        for f in rotor_hz:
            for h in range(1, self.harmonics + 1):
                fc = max(abs(float(f)) * h, self.min_hz)
                if fc >= 0.48 * self.rate_hz:
                    continue
                w0 = 2.0 * math.pi * fc / self.rate_hz
                alpha = math.sin(w0) / (2.0 * self.q)
                a0 = 1.0 + alpha
                c = -2.0 * math.cos(w0) / a0
                coef.append((1.0 / a0, c, 1.0 / a0, c, (1.0 - alpha) / a0))
        if len(coef) != len(self._coef):
            self._z = [[0.0] * 6 for _ in coef]
        self._coef = coef

    def step(self, x) -> np.ndarray:
        v = [float(x[0]), float(x[1]), float(x[2])]
        for (b0, b1, b2, a1, a2), z in zip(self._coef, self._z):
            for j in range(3):
                xin = v[j]
                y = b0 * xin + z[2 * j]
                z[2 * j] = b1 * xin - a1 * y + z[2 * j + 1]
                z[2 * j + 1] = b2 * xin - a2 * y
                v[j] = y
        return np.array(v)
