"""What every reader shares: the :class:`Converted` result (a recording and its known-rotation
segments, :class:`gyrocore.data.segments.Segment`), timing diagnostics, and the helpers that
record repairs in the metadata.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gyrocore.errors import GyroInputError, warn_repair
from gyrocore.data.checks import gap_threshold_s
from gyrocore.data.recording import Recording
from gyrocore.data.segments import Segment


__all__ = [
    "Converted",
    "TimingReport",
    "timing_report",
    "retime_uniform",
    "motion_span",
    "frame_consistency",
]


# ============================================================================ converted
@dataclass(frozen=True)
class Converted:
    """A converted recording and its known-reference segments (:class:`gyrocore.data.segments.Segment`)."""

    recording: Recording
    segments: tuple[Segment, ...] = ()
    format: str = ""


# ============================================================================ timing
@dataclass(frozen=True)
class TimingReport:
    """Sample-interval statistics of a time column.

    Attributes
    ----------
    median_dt_s, mean_dt_s, max_dt_s : float
        Median, mean ((N−1)/duration) and largest interval, s.
    n_gaps : int
        Intervals longer than ``gap_factor`` × median (dropped samples, when not bursty).
    bursty : bool
        Host receive times: the median interval is under half the mean one and the longest
        interval is over 4 × the mean (samples arrive in bursts, e.g. USB/serial buffering).
    """

    median_dt_s: float
    mean_dt_s: float
    max_dt_s: float
    n_gaps: int
    bursty: bool


def timing_report(t_s: np.ndarray, *, gap_factor: float = 1.5) -> TimingReport:
    """Classify the intervals of ``t_s`` (strictly increasing, s).

    A dropped sample makes an interval ≈ 2 × the nominal one; ``gap_factor = 1.5`` sits half
    way, so jitter up to ±50 % of the interval is not counted as a gap.
    """
    d = np.diff(np.asarray(t_s, float))
    if d.size == 0:
        return TimingReport(float("nan"), float("nan"), float("nan"), 0, False)
    med = float(np.median(d))
    mean = float((t_s[-1] - t_s[0]) / d.size)
    mx = float(d.max())
    bursty = bool(med < 0.5 * mean and mx > 4.0 * mean)
    # beyond the jitter of a host clock too (long intervals mirrored by short ones are no gaps)
    n_gaps = int(np.count_nonzero(d > max(gap_factor * med, gap_threshold_s(d, med)))) if med > 0 else 0
    return TimingReport(med, mean, mx, n_gaps, bursty)


def retime_uniform(t_s: np.ndarray) -> np.ndarray:
    """Uniform grid with the same start, end and count: rate (N−1)/duration."""
    t_s = np.asarray(t_s, float)
    n = t_s.size
    if n < 2:
        return t_s.copy()
    return t_s[0] + np.arange(n) * ((t_s[-1] - t_s[0]) / (n - 1))


def motion_span(
    t_s: np.ndarray,
    omega_rad_s: np.ndarray,
    *,
    threshold_rad_s: float = np.deg2rad(10.0),
    pad_s: float = 0.5,
    window_s: float = 0.5,
) -> tuple[float, float]:
    """First and last time |ω − b| exceeds ``threshold_rad_s``, padded by ``pad_s``.

    ``b`` is the mean rate over the quietest ``window_s`` window (smallest summed standard
    deviation), i.e. the bias seen while the hand held the board still. Used to place a
    known-rotation segment around the actual motion of a hand rotation, so that the still
    parts before and after stay outside the segment (they can give the bias).
    """
    t_s = np.asarray(t_s, float)
    n = t_s.size
    rate = (n - 1) / (t_s[-1] - t_s[0]) if n > 1 and t_s[-1] > t_s[0] else 1.0
    k = max(2, int(round(window_s * rate)))
    if n >= 2 * k:
        starts = np.arange(0, n - k + 1, max(1, k // 4))
        sd = np.array([omega_rad_s[i : i + k].std(axis=0).sum() for i in starts])
        i0 = int(starts[int(np.argmin(sd))])
        b = omega_rad_s[i0 : i0 + k].mean(axis=0)
    else:
        b = np.median(omega_rad_s, axis=0)
    dev = np.linalg.norm(omega_rad_s - b, axis=1)
    idx = np.flatnonzero(dev > threshold_rad_s)
    if idx.size == 0:
        return float(t_s[0]), float(t_s[-1])
    return max(float(t_s[0]), float(t_s[idx[0]]) - pad_s), min(float(t_s[-1]), float(t_s[idx[-1]]) + pad_s)


def frame_consistency(rec: Recording, *, window: int = 21) -> float:
    """Correlation between d f/dt and −ω × f (kinematic check of the gyro/accel axes).

    For a sensor moved by hand, the specific force f is nearly constant in the world frame,
    so in the sensor frame df/dt ≈ −ω × f. With gyro and accelerometer in one right-handed
    frame the correlation is positive (≈ +0.4…+0.95 for hand motion); a flipped axis in one
    of them makes it negative or near zero. Uses Savitzky–Golay smoothing over ``window``
    samples and the sample index with dt = 1/rate (robust to bursty host timestamps).
    """
    from scipy.signal import savgol_filter

    if rec.accel_m_s2 is None or rec.n < window + 2:
        return float("nan")
    dt = 1.0 / rec.rate_hz
    w = savgol_filter(rec.gyro_rad_s - np.median(rec.gyro_rad_s, axis=0), window, 2, axis=0)
    f = savgol_filter(rec.accel_m_s2, window, 2, axis=0)
    df = savgol_filter(rec.accel_m_s2, window, 2, deriv=1, delta=dt, axis=0)
    pred = -np.cross(w, f)
    den = math.sqrt(float(np.sum(pred**2) * np.sum(df**2)))
    return float(np.sum(pred * df) / den) if den > 0 else float("nan")


# ============================================================================ helpers
class _Repairs:
    """Collects repairs: each is warned once and listed in the ``repairs`` metadata line."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.items: list[str] = []

    def add(self, message: str) -> None:
        self.items.append(message)
        warn_repair(f"{self.source}: {message}", stacklevel=3)

    def note(self, message: str) -> None:
        """A change that is part of the documented conversion (listed, not warned)."""
        self.items.append(message)

    def meta(self) -> str:
        return "; ".join(self.items) if self.items else "none"


def _meta(source: str, fmt: str, sensor: str, rate_hz: float, repairs: _Repairs, **more: str) -> dict[str, str]:
    m = {
        "source": source,
        "format": fmt,
        "sensor": sensor,
        "rate_hz": f"{rate_hz:.6g}",
        "units": "SI (rad/s, m/s^2, degC, s)",
    }
    m.update({k: str(v) for k, v in more.items()})
    m["repairs"] = repairs.meta()
    return m


def _require_file(path: Path, what: str) -> None:
    if not path.exists():
        raise GyroInputError(f"{path}: no such file ({what})")
    if path.is_dir():
        raise GyroInputError(f"{path}: is a directory, expected {what}")


def _positive(name: str, value: float) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise GyroInputError(f"{name} must be a positive number, got {value!r}")
    return v


def _check_finite(rec_source: str, arrays: dict[str, np.ndarray], repairs: _Repairs) -> np.ndarray:
    """Mask of rows whose listed arrays are all finite; drop the rest with a repair note."""
    keep = None
    for a in arrays.values():
        ok = np.all(np.isfinite(a.reshape(a.shape[0], -1)), axis=1)
        keep = ok if keep is None else keep & ok
    assert keep is not None
    n_bad = int((~keep).sum())
    if n_bad:
        repairs.add(f"dropped {n_bad} rows with NaN/inf samples")
    return keep


def _h5(path: Path):
    import h5py

    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise GyroInputError(f"{path}: not an HDF5 / MATLAB v7.3 file ({str(exc).splitlines()[0]})") from None


# ============================================================================ generic text
def _loadtxt(path: Path, *, skiprows: int, ncols: int, delimiter: str | None = ",") -> np.ndarray:
    """Numeric table with one-line errors naming the line and column of a bad value."""
    _require_file(path, "data file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data = np.loadtxt(path, delimiter=delimiter, skiprows=skiprows, ndmin=2, dtype=float)
    except (ValueError, UnicodeDecodeError):
        from gyrocore.data.csvtext import locate_bad_value

        raise GyroInputError(locate_bad_value(str(path), skiprows=skiprows, delimiter=delimiter)) from None
    if data.size == 0:
        raise GyroInputError(f"{path}: header only, no samples")
    if data.shape[1] != ncols:
        raise GyroInputError(f"{path}: rows have {data.shape[1]} values, expected {ncols}")
    return data
