"""The residual: what the measurement still holds against whatever reference the data offer.

Every reference is reduced to the same form, a series of **observation windows** m = 1..M,
each [t_a, t_b] with a residual mean rate error y_m (rad/s, sensor frame at t_b) and a linear
operator that maps any per-sample regressor A(t) (N, 3, P) of :func:`gyrocore.effects.registry.design`
to the window regressor

    X_m = (1/T_m) Σ_{k=a}^{b−1} R_{b←k+1} · A_{k+1} · Δt_k,        T_m = t_b − t_a,

so that the linearised measurement model r(t) = y(t) − ω(t) ≈ A(t)·θ + e(t) becomes
y_m ≈ X_m·θ + ε_m, exactly (the operator is linear). Sample k+1 is the rate over
[t_k, t_{k+1}] (backward hold, the convention of :func:`gyrocore.attitude.integrate_gyro`,
used explicitly here).

Reference kinds
---------------
``"rate"``
    Reference rates (``ref_*_rad_s``): r_k = y_k − ω_ref,k, windows are short contiguous blocks
    (block means; no rotation, R = I). Windows with a NaN reference are dropped.
``"attitude"``
    Reference attitude (``ref_q*``; NaN where tracking was lost). The optical attitude is
    *not* differentiated: for each window with a valid reference at both ends, the gyro is
    integrated over the window and compared with the reference relative rotation,

        E_m = (R_a^T R_b)^T · ΔR̂_{a→b},    y_m = rotvec(E_m) / T_m,

    which to first order is the window mean of R_{b←k}·(ω_meas − ω_true) (the error rotation
    expressed in S at t_b). R_{b←k} comes from the gyro's own integration within the window
    (its error is second order). The regressors' rate is the gyro itself, low-passed
    (errors-in-variables effect is second order for small errors).
``"still"``
    Still segments (true rate 0 relative to W): r_k = y_k, windows are blocks inside the
    segments. Earth rate is then a candidate only when the attitude is known.
``"angles"``
    Known rotation segments (e.g. "two turns about x", a turntable's N revolutions): the
    window is the whole segment and, as for ``"attitude"``, the gyro's rotation over it is
    compared with the known rotation exp(φ_m) (φ_m the rotation vector in S):
    y_m = rotvec(exp(φ_m)ᵀ·ΔR̂_m)/T_m. Comparing rotations (not ∫ω dt) makes the residual
    independent of the path — wobble and coning of a hand rotation — and for whole turns of
    the axis direction as well. Still windows outside the segments (still segments, a
    ``static_pose_axis`` column or a motion gate) are added; they pin the bias. With
    ``angle_mode="axis"`` (free hand turns: start and end poses unknown) only the total angle
    about the axis is used, y_m = (∫ω dt − φ_m)/T_m with zero weight across the axis.

Segments
--------
Still intervals and known rotations are :class:`gyrocore.data.segments.Segment` (the segments
file: :func:`gyrocore.data.segments.read_segments`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy import signal
from scipy.spatial.transform import Rotation

from gyrocore.effects import registry as E
from gyrocore.attitude import integrate_gyro, rotation_matrices
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording
from gyrocore.data.segments import Segment, as_segments
from gyrocore.data.still import StillGate, still_samples
from gyrocore.calib.stream import NotStreamable, Rows, rows_of
from . import source

__all__ = [
    "REFERENCE_KINDS",
    "Residual",
    "STILL_GATE",
    "build_residual",
    "choose_reference",
    "earth_rate_design",
]

REFERENCE_KINDS = ("rate", "attitude", "still", "angles")

#: The still gate (:func:`gyrocore.data.still.still_windows`) that finds a rate-0 reference in the
#: data: 0.5-s windows; σ² from the 10 % quantile of the window variances (at least a tenth of the
#: record still); a window is still when its variance is under 4 × the χ²_{n−1} quantile at α =
#: 10⁻³ (a hand-held rest may tremble 2 × the sensor's σ: it averages out of the rate-0 residual)
#: and its mean within 0.5 °/s + 3σ of the still windows' median (a constant turn adds no variance;
#: 0.5 °/s allows a turn-on bias drift).
STILL_GATE = StillGate(
    window_s=0.5,
    noise_from="windows",
    noise_quantile=0.1,
    dof="white",
    variance_factor=4.0,
    mean_tolerance_rad_s=float(np.radians(0.5)),
    mean_tolerance_sigmas=3.0,
)

#: Target number of observation windows for the rate/still kinds (block means).
_TARGET_WINDOWS = 1500
#: Recordings longer than this are regressed in chunks of this many samples (memory).
CHUNK_SAMPLES = 200_000
#: Effects whose regressor at a sample depends only on that sample's inputs.
_POINTWISE = frozenset(
    {
        "bias",
        "bias_ramp",
        "scale",
        "scale_asymmetry",
        "scale_nonlinearity",
        "misalignment",
        "g_sensitivity",
        "g2_sensitivity",
        "earth_rate",
    }
)


def is_pointwise(effect: str) -> bool:
    """True when an effect's regressor at a sample depends only on that sample's inputs (so its
    regressors can be built chunk by chunk). Family terms: steps and lines are; a library term
    is unless it holds a derivative (``alpha_*``, ``dtemp_dt``)."""
    if effect in _POINTWISE:
        return True
    if not E.is_family(effect):
        return False
    eff = E.resolve(effect)
    return eff.family != "regressor" or not {"alpha", "dtemp"} & set(eff.inputs)


def earth_rate_design(R_WS: np.ndarray) -> tuple[list[str], np.ndarray]:
    """Regressors of the Earth rate as an unknown constant vector Ω_W in a fixed frame W.

    ω_earth,S(t) = R_WS(t)ᵀ·Ω_W, so A[n, i, k] = R_WS[n, k, i]. Latitude and heading follow
    from Ω_W (|Ω_W| must be the Earth rate): sin φ = Ω_up/|Ω|.

    Parameters
    ----------
    R_WS : ndarray, shape (N, 3, 3)
        Attitude S→W.

    Returns
    -------
    names : list of str (3)
    A : ndarray, shape (N, 3, 3)
    """
    return [f"omega_W_rad_s[{k}]" for k in range(3)], np.transpose(R_WS, (0, 2, 1)).copy()


@dataclass(frozen=True, eq=False)
class Residual:
    """A residual series over observation windows, with what is needed to regress it.

    Attributes
    ----------
    kind : str
        One of :data:`REFERENCE_KINDS`.
    y_rad_s : ndarray, shape (M, 3)
        Residual mean rate error per window, rad/s, S frame (at the window end for
        ``"attitude"``), before any correction.
    win_start, win_stop : ndarray of int, shape (M,)
        Sample indices a, b of each window (b exclusive of its own hold interval).
    t_mid_s : ndarray, shape (M,)
        Window centre times, s.
    inputs : ModelInputs
        Per-sample inputs of the regressors (N samples): reference (or proxy) rate, specific
        force, temperature, time, attitude when known.
    R_GS : ndarray, shape (N, 3, 3) or None
        Gyro-integrated attitude in an arbitrary fixed frame G (for the window rotation
        R_{b←k} = R_GS[b]ᵀ·R_GS[k]); None means R = I.
    R_WS : ndarray, shape (N, 3, 3) or None
        Attitude S→W for the Earth-rate regressors (None: Earth rate not testable).
    gyro_rad_s : ndarray, shape (N, 3)
        The measurement.
    description : str
        What the reference is, one line.
    notes : tuple of str
        Repairs and caveats (windows dropped, outliers, ...).
    is_rotation : ndarray of bool, shape (M,) or None
        ``"angles"``: True for the known-rotation windows (the others are still windows).
    angle_sigma_rad : float
        ``"angles"``: standard uncertainty of each known angle, rad (hand rotations: a few
        degrees); the rotation windows are weighted by it.
    axis_sigma_rad : float
        ``"angles"``: uncertainty of the rotation axis direction, rad (a hand rotation "about
        x" wobbles by a few degrees, so the cross-axis components of ∫ω dt are uncertain by
        |φ|·sin(axis σ)).
    angle_S_rad : ndarray, shape (M, 3) or None
        ``"angles"``: the known rotation vector of each window (zeros for still windows).
    angle_mode : str
        ``"angles"``: ``"rotation"`` (start and end attitudes related by the known rotation:
        rate table, turns against a box edge) or ``"axis"`` (only the total angle about the
        axis is known: free hand turns).
    """

    kind: str
    y_rad_s: np.ndarray
    win_start: np.ndarray
    win_stop: np.ndarray
    t_mid_s: np.ndarray
    inputs: E.ModelInputs
    R_GS: np.ndarray | None
    R_WS: np.ndarray | None
    gyro_rad_s: np.ndarray
    description: str
    notes: tuple[str, ...] = ()
    is_rotation: np.ndarray | None = None
    angle_sigma_rad: float = float("nan")
    axis_sigma_rad: float = float("nan")
    angle_S_rad: np.ndarray | None = None
    angle_mode: str = "rotation"
    chunk_rows: int = 0
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def m(self) -> int:
        """Number of observation windows."""
        return int(self.y_rad_s.shape[0])

    @property
    def duration_s(self) -> np.ndarray:
        """Window lengths T_m, s, shape (M,)."""
        t = np.asarray(self.inputs.t_s, float)
        return t[self.win_stop] - t[self.win_start]

    # ---------------------------------------------------------------- per-sample data a window at a time
    @property
    def chunk(self) -> int:
        """Rows per window of the chunked (bounded-memory) paths."""
        return int(self.chunk_rows or CHUNK_SAMPLES)

    @property
    def lazy(self) -> bool:
        """True when the per-sample data are read from disk a window at a time
        (:class:`gyrocore.calib.stream.SpilledRecording`): every per-sample pass is then chunked."""
        return isinstance(self.gyro_rad_s, Rows)

    def chunked(self) -> bool:
        """Whether per-sample passes go window by window (long or lazy records)."""
        return self.lazy or self.inputs.n > self.chunk

    def input_rows(self, lo: int, hi: int) -> E.ModelInputs:
        """Model inputs of samples lo:hi (time since power-up counted from the record's start)."""
        inp = self.inputs
        t = np.asarray(inp.t_s)
        sp = rows_of(inp.t_since_power_up_s, lo, hi) if inp.t_since_power_up_s is not None else t[lo:hi] - t[0]
        return E.ModelInputs(
            t_s=t[lo:hi],
            omega_S_rad_s=rows_of(inp.omega_S_rad_s, lo, hi),
            f_S_m_s2=rows_of(inp.f_S_m_s2, lo, hi),
            temp_c=rows_of(inp.temp_c, lo, hi),
            q_SW_wxyz=rows_of(inp.q_SW_wxyz, lo, hi),
            t_since_power_up_s=sp,
        )

    def temp_mean_c(self) -> float | None:
        """Mean temperature of the record, °C (the T0 of the thermal regressors), or None."""
        if self.inputs.temp_c is None:
            return None
        if "temp_mean" not in self._cache:
            self._cache["temp_mean"] = float(np.mean(np.asarray(self.inputs.temp_c, float)))
        return self._cache["temp_mean"]

    def design_rows(self, effect: str, a: int, b: int, *, order: int = 1) -> tuple[list[str], np.ndarray]:
        """Per-sample regressors of samples a:b, (names, A (b − a, 3, P)), NaN-free — equal to
        rows a:b of the whole record's: built on a:b plus one neighbour on each side (central
        differences: ``time_offset``, ``bias_temp_rate``, ``alpha_*``), thermal polynomials
        about the whole record's mean temperature."""
        n = self.inputs.n
        lo, hi = (a, b) if is_pointwise(effect) else (max(a - 1, 0), min(b + 1, n))
        inp = self.input_rows(lo, hi)
        if effect == "earth_rate":
            if self.R_WS is None:
                raise GyroInputError("earth_rate needs the attitude (ref_q* or reference rates)")
            names, A = earth_rate_design(rows_of(self.R_WS, lo, hi))
        elif effect in ("bias_thermal", "scale_thermal"):
            names, A = E.design(effect, inp, order=order, t0_c=self.temp_mean_c())
        else:
            names, A = E.design(effect, inp, order=order)
        A = A[a - lo : a - lo + (b - a)]
        if not np.all(np.isfinite(A)):
            A = np.nan_to_num(A, nan=0.0, posinf=0.0, neginf=0.0)
        return names, A

    def iter_inputs(self, *, context: int = 1):
        """Windows of the record: (a, b, lo, inputs of lo:hi) with lo:hi = a:b plus ``context``
        samples on each side (trim with ``[a − lo : b − lo]``)."""
        n = self.inputs.n
        for a in range(0, n, self.chunk):
            b = min(a + self.chunk, n)
            lo, hi = max(a - context, 0), min(b + context, n)
            yield a, b, lo, self.input_rows(lo, hi)

    # ---------------------------------------------------------------- regressors
    def sample_design(self, effect: str, *, order: int = 1, rows: slice | None = None) -> tuple[list[str], np.ndarray]:
        """Per-sample regressors of one effect, (names, A (N, 3, P)); NaN-free; not cached.

        ``rows`` (point-wise effects only, see :meth:`regressors`) restricts them to a slice of
        the samples.
        """
        if rows is not None:
            if not is_pointwise(effect):
                raise ValueError(f"{effect} is not point-wise; its regressors need all samples")
            lo, hi, _ = rows.indices(self.inputs.n)
            return self.design_rows(effect, lo, hi, order=order)
        inp = self.inputs
        if self.lazy:
            return self.design_rows(effect, 0, inp.n, order=order)
        if effect == "earth_rate":
            if self.R_WS is None:
                raise GyroInputError("earth_rate needs the attitude (ref_q* or reference rates)")
            names, A = earth_rate_design(self.R_WS)
        else:
            names, A = E.design(effect, inp, order=order)
        if not np.all(np.isfinite(A)):
            A = np.nan_to_num(A, nan=0.0, posinf=0.0, neginf=0.0)
        return names, A

    def sample_correction(self, effect: str, theta: np.ndarray, *, order: int = 1) -> np.ndarray:
        """Σ_p A[:, :, p]·θ_p for one effect, rad/s, (N, 3) — in chunks for long recordings."""
        n = self.inputs.n
        th = np.asarray(theta, float)
        if not self.chunked():
            return np.einsum("nip,p->ni", self.sample_design(effect, order=order)[1], th)
        out = np.empty((n, 3))
        for s0 in range(0, n, self.chunk):
            s1 = min(s0 + self.chunk, n)
            out[s0:s1] = np.einsum("nip,p->ni", self.design_rows(effect, s0, s1, order=order)[1], th)
        return out

    def correction_rows(self, terms) -> Rows:
        """Σ_e A_e·θ_e as a lazy (N, 3) :class:`~gyrocore.calib.stream.Rows`, ``terms`` a list of
        (effect, θ, order): rows computed a window at a time (rows a:b equal the whole record's)."""
        terms = [(e, np.asarray(th, float), int(o)) for e, th, o in terms]

        def fn(a, b):
            c = np.zeros((b - a, 3))
            for e, th, o in terms:
                c += np.einsum("nip,p->ni", self.design_rows(e, a, b, order=o)[1], th)
            return c

        return Rows(fn, self.inputs.n, 3)

    def window_mean(self, Z: np.ndarray) -> np.ndarray:
        """Apply the window operator to per-sample values.

        Parameters
        ----------
        Z : ndarray, shape (N, 3) or (N, 3, P)
            Per-sample quantity in S (rad/s or regressor units).

        Returns
        -------
        ndarray, shape (M, 3) or (M, 3, P)
            (1/T_m) Σ_{k=a}^{b−1} R_{b←k+1}·Z_{k+1}·Δt_k (backward hold).
        """
        if isinstance(Z, Rows):
            squeeze = Z.ndim == 2

            def fn(a, b):
                z = np.asarray(Z.rows(a, b), float)
                return z[:, :, None] if squeeze else z

            D = self._window_sums(fn)
            return D[:, :, 0] if squeeze else D
        Z = np.asarray(Z, float)
        squeeze = Z.ndim == 2
        if squeeze:
            Z = Z[:, :, None]
        t = np.asarray(self.inputs.t_s, float)
        dt = np.diff(t)
        # backward hold (gyrocore.attitude.integrate_gyro's convention): sample k+1 is the
        # rate over [t_k, t_{k+1}]
        if self.R_GS is not None:
            Zg = np.einsum("nij,njp->nip", self.R_GS[1:], Z[1:])
        else:
            Zg = Z[1:]
        C = np.concatenate([np.zeros((1,) + Zg.shape[1:]), np.cumsum(Zg * dt[:, None, None], axis=0)])
        D = C[self.win_stop] - C[self.win_start]
        if self.R_GS is not None:
            D = np.einsum("mji,mjp->mip", self.R_GS[self.win_stop], D)
        D = D / self.duration_s[:, None, None]
        return D[:, :, 0] if squeeze else D

    def regressors(self, effect: str, *, order: int = 1) -> tuple[list[str], np.ndarray]:
        """Window regressors of one effect: (names, X (M, 3, P)).

        Long recordings (more than :data:`CHUNK_SAMPLES` samples, or read from disk) are
        processed in chunks (:meth:`design_rows`: one neighbour sample on each side for the
        central differences, thermal polynomials about the whole record's mean temperature),
        so that the per-sample regressors (N, 3, P) — 1.3 GB for ``g2_sensitivity`` over an
        hour at 1 kHz — are never held at once; the result is the same to rounding.
        """
        key = ("w", effect, order)
        if key not in self._cache:
            if self.chunked():
                self._cache[key] = self._chunked_regressors(effect, order)
            else:
                names, A = self.sample_design(effect, order=order)
                self._cache[key] = (names, self.window_mean(A))
        return self._cache[key]

    def _window_sums(self, rows_fn) -> np.ndarray:
        """The window operator applied window by window: ``rows_fn(a, b)`` gives the per-sample
        values of samples a:b, (b − a, 3, P); returns (M, 3, P). Running sums are carried
        across windows (C_j = Σ_{k<j} R[k+1]·A[k+1]·Δt_k), so the result equals the whole-array
        :meth:`window_mean` (bit for bit with one window)."""
        n = self.inputs.n
        t = np.asarray(self.inputs.t_s, float)
        need = np.union1d(self.win_start, self.win_stop)
        C_need: dict[int, np.ndarray] = {}
        carry = None
        # chunk of k in [k0, k1) uses samples k0+1 .. k1
        for k0 in range(0, n - 1, self.chunk):
            k1 = min(k0 + self.chunk, n - 1)
            A = rows_fn(k0 + 1, k1 + 1)
            if self.R_GS is not None:
                A = np.einsum("nij,njp->nip", rows_of(self.R_GS, k0 + 1, k1 + 1), A)
            A = A * np.diff(t[k0 : k1 + 1])[:, None, None]
            np.cumsum(A, axis=0, out=A)
            if carry is None:
                carry = np.zeros(A.shape[1:])
                C_need[0] = carry.copy()
            for j in need[(need > k0) & (need <= k1)]:
                C_need[int(j)] = carry + A[j - k0 - 1]
            carry = carry + A[-1]
        a = np.stack([C_need[int(j)] for j in self.win_start])
        b = np.stack([C_need[int(j)] for j in self.win_stop])
        D = b - a
        if self.R_GS is not None:
            D = np.einsum("mji,mjp->mip", np.asarray(self.R_GS)[self.win_stop], D)
        return D / self.duration_s[:, None, None]

    def _chunked_regressors(self, effect: str, order: int) -> tuple[list[str], np.ndarray]:
        names: list = []

        def fn(a, b):
            nm, A = self.design_rows(effect, a, b, order=order)
            names[:] = nm
            return A

        D = self._window_sums(fn)
        return list(names), D


# ---------------------------------------------------------------------------- builders
def _blocks(mask: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Contiguous windows of ``block`` hold intervals inside runs of True in ``mask`` (N,).

    A window [a, b] needs mask[a..b] all True (samples a+1..b are held over it; a too, as a
    margin).
    """
    starts, stops = [], []
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    run_a = np.flatnonzero(d == 1)
    run_b = np.flatnonzero(d == -1)  # exclusive
    for a, b in zip(run_a, run_b):
        last = b - 1  # last sample of the run (inclusive): it is held over the window's end
        k = a
        while k + block <= last:
            starts.append(k)
            stops.append(k + block)
            k += block
    return np.asarray(starts, int), np.asarray(stops, int)


def _smooth(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Zero-phase low-pass of a proxy rate at min(0.1·fs, 20 Hz) (regressor inputs only)."""
    fs = (t.shape[0] - 1) / (t[-1] - t[0])
    fc = min(0.1 * fs, 20.0)
    if t.shape[0] < 30 or not 0 < fc < fs / 2:
        return x
    sos = signal.butter(2, fc, fs=fs, output="sos")
    return signal.sosfiltfilt(sos, x, axis=0)


def _fill_nan_rows(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    ok = np.all(np.isfinite(x), axis=1)
    if ok.all() or not ok.any():
        return x
    return np.stack([np.interp(t, t[ok], x[ok, i]) for i in range(x.shape[1])], axis=1)


def choose_reference(rec: Recording, segments: Sequence[Segment] | None = None) -> str:
    """The best reference the data offer: rate > attitude > angles > still.

    Without reference columns or segments, a recording that a motion gate finds ≥ 80 % still
    (or that has a ``static_pose_axis`` column) is taken as ``"still"``.
    """
    segs = as_segments(segments)
    if rec.ref_rate_rad_s is not None and np.isfinite(rec.ref_rate_rad_s).any():
        return "rate"
    if rec.ref_quat_wxyz is not None and np.isfinite(rec.ref_quat_wxyz).all(axis=1).sum() >= 2:
        return "attitude"
    if any(s.kind == "rotation" for s in segs):
        return "angles"
    if any(s.kind == "still" for s in segs):
        return "still"
    if "static_pose_axis" in rec.extra or (rec.n > 100 and still_samples(rec, STILL_GATE).mean() >= 0.8):
        return "still"
    raise GyroInputError(
        "no reference in the data: need ref_*_rad_s, ref_q* columns, or a segments file (--segments) "
        "with still or rotation segments"
    )


def _segment_mask(t: np.ndarray, segs: Sequence[Segment], kind: str) -> np.ndarray:
    m = np.zeros(t.shape[0], bool)
    for s in segs:
        if s.kind == kind:
            m |= (t >= s.t_start_s) & (t <= s.t_end_s)
    return m


def build_residual(
    rec: Recording,
    *,
    reference: str = "auto",
    segments: Sequence[Segment] | None = None,
    window_s: float | None = None,
    outlier_mad: float = 20.0,
    angle_sigma_deg: float = 2.0,
    axis_sigma_deg: float = 5.0,
    angle_mode: str = "rotation",
) -> Residual:
    """Build the residual of ``rec`` against its reference.

    Parameters
    ----------
    rec : Recording
    reference : {"auto", "rate", "attitude", "still", "angles"}
        Which reference to use; ``"auto"`` picks :func:`choose_reference`.
    segments : sequence of Segment, optional
        Still / known-rotation segments (needed for ``"still"`` unless the whole recording
        is declared still by passing ``reference="still"`` without segments, and for
        ``"angles"``).
    window_s : float, optional
        Window length, s. Default: blocks giving ≈ 1500 windows (≥ 2 samples) for
        ``"rate"``/``"still"``; 1 s for ``"attitude"``.
    outlier_mad : float
        ``"attitude"`` only: windows whose |y| exceeds median + ``outlier_mad``·1.4826·MAD are
        dropped as reference glitches (marker swaps) and counted in ``notes``.
    angle_sigma_deg : float
        ``"angles"`` only: standard uncertainty of each known rotation angle, degrees (2° for
        rotations by hand against a box edge; 0.01° for a rate table).
    axis_sigma_deg : float
        ``"angles"`` only: uncertainty of the rotation axis, degrees (5° by hand; 0.01° on a
        rate table).
    angle_mode : {"rotation", "axis"}
        ``"angles"`` only: compare whole rotations (start/end poses known) or only the total
        angle about the axis (free hand turns).

    Returns
    -------
    Residual
    """
    segs = as_segments(segments)
    src = source.of(rec)
    if src.on_disk:
        _check_streamable(rec, reference, segs)
        kind = "rate"
    else:
        kind = choose_reference(rec, segs) if reference == "auto" else reference
    if kind not in REFERENCE_KINDS:
        raise GyroInputError(f"unknown reference '{reference}' ({', '.join(REFERENCE_KINDS)}, auto)")
    if rec.n < 3:
        raise GyroInputError("too few samples for a residual")
    if kind == "rate":
        return _rate_residual(src, window_s)
    if kind == "still":
        return _still_residual(rec, segs, window_s)
    if kind == "attitude":
        return _attitude_residual(rec, window_s, outlier_mad)
    return _angles_residual(rec, segs, window_s, angle_sigma_deg, axis_sigma_deg, angle_mode)


def _n_block(rec: Recording, window_s: float | None) -> int:
    """Samples per block-mean window: ``window_s`` at the sample rate, else ≈ :data:`_TARGET_WINDOWS`
    windows of at least 2 samples."""
    if window_s is not None:
        return max(1, int(round(window_s * rec.rate_hz)))
    return max(2, int(np.ceil(rec.n / _TARGET_WINDOWS)))


def _check_streamable(rec, reference: str, segs: Sequence[Segment]) -> None:
    """What a recording on disk (:class:`gyrocore.calib.stream.SpilledRecording`) can be built
    against: the ``rate`` reference without segments and without NaN rows in the reference rate.
    Raises :class:`gyrocore.calib.stream.NotStreamable` for what only a recording in memory offers
    (the motion gate, the attitude reference's integration, the filled NaN rows all need the whole
    record): the caller reads the file whole instead."""
    if segs or reference not in ("auto", "rate"):
        raise NotStreamable("only the rate reference without segments is built from disk")
    if rec.ref_rate_rad_s is None:
        if reference == "rate":
            raise GyroInputError("reference 'rate' needs the ref_x/y/z_rad_s columns")
        raise NotStreamable("no reference rate")
    if rec.n < 3:
        raise GyroInputError("too few samples for a residual")
    if not rec.all_finite("ref_rate"):
        raise NotStreamable("NaN rows in the reference rate")


def _rate_residual(src, window_s: float | None) -> Residual:
    """``"rate"``: block means of r = y − ω_ref over the runs of samples with a finite reference,
    a window of rows at a time (:mod:`gyrocore.loop.source`: a recording in memory is one window)."""
    rec = src.rec
    if rec.ref_rate_rad_s is None:
        raise GyroInputError("reference 'rate' needs the ref_x/y/z_rad_s columns")
    t = rec.t_s
    ref = rec.ref_rate_rad_s
    ok = src.finite_rows(ref)
    if ok.sum() < 3:
        raise GyroInputError("the reference rate is NaN almost everywhere")
    notes = []
    if not ok.all():
        notes.append(f"{int((~ok).sum())} samples with NaN reference rate excluded")
    # the regressors' rate: NaN rows filled (in memory only: a recording on disk has none)
    omega = ref if ok.all() else _fill_nan_rows(t, ref)
    a, b = _blocks(ok, _n_block(rec, window_s))
    # S->W from ref_q*, else the reference rate integrated (W' = S at t0, a fixed frame)
    R_WS = src.rotations(src.reference_attitude(omega))

    def r_rows(lo, hi):
        r = rows_of(rec.gyro_rad_s, lo, hi) - rows_of(omega, lo, hi)
        return np.where(np.isfinite(r), r, 0.0)

    desc = "reference rate (ref_*_rad_s), block means"
    r = src.per_sample(r_rows, 3)
    return _block_means_residual("rate", rec, r, omega, a, b, R_WS, desc, notes, chunk_rows=src.chunk_rows)


def _still_residual(rec: Recording, segs: Sequence[Segment], window_s: float | None) -> Residual:
    """``"still"``: block means of the gyro (true rate 0) inside the still samples."""
    t, gyro = rec.t_s, rec.gyro_rad_s
    if segs:
        mask = _segment_mask(t, segs, "still")
        if not mask.any():
            raise GyroInputError("no still segment covers any sample")
        desc = f"{sum(s.kind == 'still' for s in segs)} still segment(s): true rate 0"
    elif "static_pose_axis" in rec.extra:
        mask = rec.extra["static_pose_axis"] != 0
        desc = "static poses (static_pose_axis column): true rate 0"
    else:
        mask = still_samples(rec, STILL_GATE)
        desc = f"still samples found by a motion gate ({mask.mean():.0%} of the recording): true rate 0"
    a, b = _blocks(mask, _n_block(rec, window_s))
    q_ref = rec.ref_quat_wxyz
    R_WS = rotation_matrices(q_ref) if q_ref is not None and np.all(np.isfinite(q_ref)) else None
    r = np.where(np.isfinite(gyro), gyro, 0.0)
    return _block_means_residual("still", rec, r, np.zeros((rec.n, 3)), a, b, R_WS, desc, [])


def _block_means_residual(kind, rec, r, omega, a, b, R_WS, desc: str, notes: list, chunk_rows: int = 0) -> Residual:
    """The residual of block-mean windows [a, b): y = the window means of r (finite per-sample
    values, an array or :class:`~gyrocore.calib.stream.Rows`); no rotation within a window."""
    if a.size < 3:
        raise GyroInputError(f"fewer than 3 observation windows for reference '{kind}'")
    t = rec.t_s
    inputs = E.ModelInputs(t_s=t, omega_S_rad_s=omega, f_S_m_s2=rec.accel_m_s2, temp_c=rec.temp_c, q_SW_wxyz=None)
    kw = dict(
        kind=kind,
        win_start=a,
        win_stop=b,
        t_mid_s=0.5 * (t[a] + t[b]),
        inputs=inputs,
        R_GS=None,
        R_WS=R_WS,
        gyro_rad_s=rec.gyro_rad_s,
        description=desc,
        notes=tuple(notes),
        chunk_rows=chunk_rows,
    )
    y = Residual(y_rad_s=np.zeros((a.size, 3)), **kw).window_mean(r)
    return Residual(y_rad_s=y, **kw)


def _attitude_residual(rec: Recording, window_s: float | None, outlier_mad: float) -> Residual:
    """``"attitude"``: windows of the integrated gyro's rotation against the reference rotation."""
    t, n, fs, gyro = rec.t_s, rec.n, rec.rate_hz, rec.gyro_rad_s
    q_ref = rec.ref_quat_wxyz
    if q_ref is None:
        raise GyroInputError("reference 'attitude' needs the ref_qw/qx/qy/qz columns")
    ok = np.all(np.isfinite(q_ref), axis=1)
    L = max(2, int(round((window_s or 1.0) * fs)))
    idx = np.arange(0, n - L, L)
    a_all, b_all = idx, idx + L
    keep = ok[a_all] & ok[b_all]
    a, b = a_all[keep], b_all[keep]
    if a.size < 3:
        raise GyroInputError("fewer than 3 windows with a valid reference attitude at both ends")
    notes = []
    n_lost = int((~keep).sum())
    if n_lost:
        notes.append(f"{n_lost} of {keep.size} windows dropped: reference attitude NaN at an end")
    q_hat = integrate_gyro(t, gyro, hold="backward")
    R_GS = rotation_matrices(q_hat)
    R_ref = np.full((n, 3, 3), np.nan)
    R_ref[ok] = rotation_matrices(q_ref[ok])
    # E = (R_a^T R_b)^T · (R̂_a^T R̂_b)
    rel_ref = np.einsum("mji,mjk->mik", R_ref[a], R_ref[b])
    rel_hat = np.einsum("mji,mjk->mik", R_GS[a], R_GS[b])
    Em = np.einsum("mji,mjk->mik", rel_ref, rel_hat)
    T = t[b] - t[a]
    y = Rotation.from_matrix(Em).as_rotvec() / T[:, None]
    # attitude S->W per sample: anchored at the latest valid reference sample
    vi = np.flatnonzero(ok)
    anchor = vi[np.clip(np.searchsorted(vi, np.arange(n), side="right") - 1, 0, None)]
    R_WS = np.einsum("nij,nkj,nkl->nil", R_ref[anchor], R_GS[anchor], R_GS)
    omega = _smooth(t, gyro)
    desc = f"reference attitude (ref_q*), {L / fs:.3g} s windows of integrated gyro vs reference rotation"
    # glitches of the optical reference (marker swaps): robust outlier rejection
    nrm = np.linalg.norm(y, axis=1)
    med = float(np.median(nrm))
    mad = float(np.median(np.abs(nrm - med))) * 1.4826
    if mad > 0 and outlier_mad > 0:
        good = nrm <= med + outlier_mad * mad
        if (~good).any():
            notes.append(
                f"{int((~good).sum())} windows dropped as reference glitches (|residual| > median + {outlier_mad:g}·MAD)"
            )
        a, b, y = a[good], b[good], y[good]
    inputs = E.ModelInputs(t_s=t, omega_S_rad_s=omega, f_S_m_s2=rec.accel_m_s2, temp_c=rec.temp_c, q_SW_wxyz=None)
    return Residual(
        kind="attitude",
        y_rad_s=y,
        win_start=a,
        win_stop=b,
        t_mid_s=0.5 * (t[a] + t[b]),
        inputs=inputs,
        R_GS=R_GS,
        R_WS=R_WS,
        gyro_rad_s=gyro,
        description=desc,
        notes=tuple(notes),
    )


def _angles_residual(
    rec: Recording,
    segs: Sequence[Segment],
    window_s: float | None,
    angle_sigma_deg: float,
    axis_sigma_deg: float,
    angle_mode: str,
) -> Residual:
    """``"angles"``: each known rotation segment is one window (its gyro rotation against the
    known rotation, or the angle about its axis), with still windows outside the rotations."""
    t, n, fs, gyro = rec.t_s, rec.n, rec.rate_hz, rec.gyro_rad_s
    rots = [s for s in segs if s.kind == "rotation"]
    if not rots:
        raise GyroInputError("reference 'angles' needs rotation segments (--segments)")
    a, b, phi = _rotation_windows(t, rots)
    n_rot = a.size
    # still windows outside the rotations: they pin the bias (and g-sensitivity across poses)
    in_rot = np.zeros(n, bool)
    for ia, ib in zip(a, b):
        in_rot[ia : ib + 1] = True
    if any(s.kind == "still" for s in segs):
        still = _segment_mask(t, segs, "still")
        how = "still segments"
    elif "static_pose_axis" in rec.extra:
        still = rec.extra["static_pose_axis"] != 0
        how = "static poses"
    else:
        still = still_samples(rec, STILL_GATE)
        how = "motion gate"
    still &= ~in_rot
    sa, sb = _blocks(still, max(2, int(round((window_s or 0.5) * fs))))
    if n_rot + sa.size < 2:
        raise GyroInputError(
            "reference too poor: one known rotation and no still part give only 3 numbers "
            "(record still periods before/after, or several rotations)"
        )
    phi_all = np.vstack([phi, np.zeros((sa.size, 3))])
    a, b = np.concatenate([a, sa]), np.concatenate([b, sb])
    omega = _smooth(t, gyro)
    omega[still] = 0.0
    # a first bias from the still windows is removed before integrating, so that the error
    # rotation of each known rotation stays small (first order); it is added back below
    b0 = gyro[still].mean(axis=0) if still.any() else np.zeros(3)
    if angle_mode not in ("rotation", "axis"):
        raise GyroInputError(f"angle mode must be 'rotation' or 'axis', not '{angle_mode}'")
    R_GS = rotation_matrices(integrate_gyro(t, gyro - b0, hold="backward")) if angle_mode == "rotation" else None
    inputs = E.ModelInputs(t_s=t, omega_S_rad_s=omega, f_S_m_s2=rec.accel_m_s2, temp_c=rec.temp_c)
    how_compared = (
        "integrated gyro rotation vs known rotation"
        if angle_mode == "rotation"
        else "integrated angle about each axis vs known angle"
    )
    kw = dict(
        kind="angles",
        win_start=a,
        win_stop=b,
        t_mid_s=0.5 * (t[a] + t[b]),
        inputs=inputs,
        R_GS=R_GS,
        R_WS=None,
        gyro_rad_s=gyro,
        description=f"{n_rot} known rotation(s): {how_compared}; {sa.size} still windows ({how})",
    )
    y, note = _angle_errors(Residual(y_rad_s=np.zeros((a.size, 3)), notes=(), **kw), phi_all, n_rot, b0, angle_mode)
    return Residual(
        y_rad_s=y,
        notes=(note,),
        is_rotation=np.arange(a.size) < n_rot,
        angle_sigma_rad=np.radians(angle_sigma_deg),
        axis_sigma_rad=np.radians(axis_sigma_deg),
        angle_S_rad=phi_all,
        angle_mode=angle_mode,
        **kw,
    )


def _rotation_windows(t: np.ndarray, rots: Sequence[Segment]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample indices (a, b) of each known rotation segment and its rotation vector (K, 3), rad."""
    a_l, b_l, phi = [], [], []
    for s in rots:
        ia = int(np.searchsorted(t, s.t_start_s, side="left"))
        ib = int(np.searchsorted(t, s.t_end_s, side="right")) - 1
        if ib - ia < 2:
            raise GyroInputError(f"rotation segment {s.t_start_s}..{s.t_end_s} s covers fewer than 3 samples")
        a_l.append(ia)
        b_l.append(ib)
        phi.append(s.angle_S_rad)
    return np.asarray(a_l), np.asarray(b_l), np.asarray(phi, float)


def _angle_errors(res: Residual, phi_all: np.ndarray, n_rot: int, b0: np.ndarray, angle_mode: str):
    """The ``"angles"`` residual y (M, 3) of the windows of ``res`` (the first ``n_rot`` are the
    known rotations, the others still) and the note that says how the rotations were compared."""
    a, b = res.win_start, res.win_stop
    gyro = res.gyro_rad_s
    T = res.duration_s
    y = res.window_mean(gyro)  # still windows: the mean rate (true rate 0)
    if angle_mode == "rotation":
        # rotation windows: E = exp(φ)ᵀ·(R̂_aᵀ·R̂_b) — compared as rotations, so the path (wobble,
        # coning of a hand rotation) does not matter, only the start and end attitudes
        ra, rb = a[:n_rot], b[:n_rot]
        rel_hat = np.einsum("mji,mjk->mik", res.R_GS[ra], res.R_GS[rb])
        Rk = Rotation.from_rotvec(phi_all[:n_rot]).as_matrix()
        Em = np.einsum("mji,mjk->mik", Rk, rel_hat)
        b0_win = res.window_mean(np.broadcast_to(b0, gyro.shape).copy())
        y[:n_rot] = Rotation.from_matrix(Em).as_rotvec() / T[:n_rot, None] + b0_win[:n_rot]
        return y, (
            "known rotations are compared as rotations (start vs end attitude); by hand they are "
            "good to a few degrees (see angle_sigma/axis_sigma)"
        )
    # only the total angle about the axis is known (hand turns whose start and end
    # poses differ): ∫ω dt along the axis; the cross-axis components get zero weight
    y[:n_rot] = y[:n_rot] - phi_all[:n_rot] / T[:n_rot, None]
    return y, (
        "angle mode 'axis': only the total angle about each rotation axis is used "
        "(∫ω dt along the axis; the start and end poses are not assumed known)"
    )
