"""Experiment ``twin``: a digital twin of a real sensor.

Replay a real recording through the simulator and show, statistic by statistic, where the
simulated sensor matches the real one and where it does not.

1. **Reference** (:func:`reference_of`): what the data say the true rate was, and where.
   ``ref_*_rad_s`` columns -> that rate; ``ref_q*`` (an attitude) -> the rate of the attitude
   (relative rotation of consecutive samples, backward hold, so integrating it reproduces the
   reference exactly) for driving the twin, plus the still spans of the recording (gyro motion
   gate) as the zero-rate per-sample reference; still segments / poses / a still log -> zero
   rate there. Hand rotations (known angles only) are not replayed: their rate profile is
   unknown. Specific force comes from the accelerometer, temperature from the file.
2. **Identification** (:func:`identify`): the twin's parameters — deterministic terms from the
   residual loop (:func:`gyrocore.loop.loop.run_loop`, declared ``bias``; or a ``--params`` file),
   noise from the Allan analysis of the per-sample error signal on the covered spans after the
   deterministic model (:func:`gyrocore.noise.allan.identify_noise`: N -> ``arw``, B ->
   ``bias_instability``, K -> ``rrw``, a Gauss–Markov term -> ``correlated`` σ, τc; N² less the LSB²/(12·rate) that rounding adds), output
   rate from the timestamps, the LSB from the lattice of first differences
   (:func:`lsb_from_differences`).
3. **Replicas** (:func:`replica_statistics`): N runs of :class:`sim.gyro.SyntheticGyro` driven
   by the reference motion, seeds from ``SeedSequence(seed).spawn(N)``; the same statistics are
   computed on each replica's error signal as on the real one.
4. **Comparison** (:func:`compare`): per statistic a pointwise band from the replicas' order
   statistics and a rank-count test that accounts for the band's own false-out rate and for the
   correlation between bins (see :func:`compare`).
5. **Closing** (:func:`close_twin`): for each failing statistic, the difference is named
   (white angle noise, heavy tails, a spectral line, reference noise) and the matching term is
   added to the twin, then the comparison is repeated ("after").

The statistics (:func:`error_statistics`), all per axis of the sensor frame:

``adev``
    log10 overlapping Allan deviation of the per-sample error signal at octave τ, pooled over
    the covered spans (Σ of squared second differences of the phase over Σ of their count).
``psd``
    log10 Welch PSD (Hann, 256-sample segments, half overlap, averaged over spans), averaged
    in 16 log-spaced frequency bands.
``distribution``
    log10 standard deviation, excess kurtosis and the fraction of samples beyond 4 standard
    deviations of the error signal less its span mean.
``window_acf``
    Autocorrelation at lags 1..5 of the 1-s window means of the error signal (span means
    removed) — the "window residual" of the still / rate reference.
``attitude_residual`` (attitude references only)
    The loop's window residual (:func:`gyrocore.loop.residual.build_residual`, 1-s windows of
    integrated gyro against the reference rotation, windows with tracking loss inside dropped):
    log10 std, excess kurtosis and lag-1, 2, 3 autocorrelation per axis.

Everything here is written by hand except the ADEV kernel's idea (SP 1065 eq. 11), Welch
(:func:`scipy.signal.welch`) and the loop/Allan/simulator of this project.
"""

from __future__ import annotations

import math
import time as _time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from scipy import signal

from gyrocore.effects import registry as E
from gyrocore.errors import GyroInputError, warn_repair
from gyrocore.data.recording import Recording
from gyrocore.data.segments import Segment, as_segments

from .twin_reference import Reference, _quat_R, reference_of
from .twin_stats import (
    WINDOW_S,
    StatLayout,
    _attitude_windows,
    _pooled_adev,
    _span_concat,
    error_statistics,
    layout_for,
)

__all__ = [
    "FORMAT_VERSION",
    "SETS",
    "Reference",
    "TwinModel",
    "Comparison",
    "TwinResult",
    "reference_of",
    "lsb_from_differences",
    "identify",
    "error_statistics",
    "replica_statistics",
    "compare",
    "close_twin",
    "twin",
    "run",
]

FORMAT_VERSION = "1.0"
DEG = math.pi / 180.0
#: Default number of replicas: M = N + 1 = 200 exchangeable series, band k = 5 (p0 = 0.05),
#: smallest attainable p-value 2·(1/200) = 0.01 ≤ α/S = 0.01 (5 statistics, two tests each).
DEFAULT_REPLICAS = 199
#: replicas per set in the standard size of ``gyroharness run``: the fewest for which the
#: two-sided rank band at α = 0.05 exists (k = 1 of 39: the real statistic outside the replicas'
#: [min, max] with probability 2/40 = 0.05 when the twin is right)
STANDARD_REPLICAS = 39
#: Family-wise false-fail rate of the whole twin (Bonferroni over the statistics).
ALPHA = 0.05

#: The real sets of docs/twin.md: (name, path under the data folder).
SETS: tuple[tuple[str, str], ...] = (
    ("BROAD 02 slow rotation", "broad/02_undisturbed_slow_rotation_B.hdf5"),
    ("BROAD 05 slow rotation, breaks", "broad/05_undisturbed_slow_rotation_with_breaks_B.hdf5"),
    ("BROAD 07 fast rotation", "broad/07_undisturbed_fast_rotation_B.hdf5"),
    ("BROAD 09 fast rotation, breaks", "broad/09_undisturbed_fast_rotation_with_breaks_B.hdf5"),
    ("sunsided set-2 static 10 min", "sunsided_mpu6050/set-2/unmoved-with-x-pointing-forward-10min"),
    ("tomisuarez2 static 449 s", "tomisuarez2_mpu6050/example_data_tinit_calc.csv"),
    ("PX4 sample.ulg (still part)", "pyulog_samples/sample.ulg"),
    ("imucal Ferraris session", "imucal_ferraris/example_ferraris_session.csv"),
)


# ============================================================================ identification
def lsb_from_differences(gyro_rad_s: np.ndarray, *, tol: float = 0.01, min_fraction: float = 0.99) -> float | None:
    """Output resolution from the lattice of first differences, rad/s; None if not quantized.

    The smallest non-zero |Δ| common to the axes is the candidate LSB q (the histogram of
    differences has its first non-zero bin at q); it is accepted when at least
    ``min_fraction`` of the differences up to 5 q are integer multiples of q within
    ``tol``·q — float data (averaged or filtered output) fail this and get no quantization.
    """
    d = np.diff(np.asarray(gyro_rad_s, float), axis=0).ravel()
    d = np.abs(d[np.isfinite(d)])
    # differences below 1e-9 of the typical step are float round-off of equal values
    nz = d[d > 1e-9 * max(float(np.median(d)), 1e-300)]
    if nz.size < 100:
        return None
    # candidate: the most frequent of the smallest differences (robust to a stray tiny one)
    small = np.sort(nz)[: max(10, nz.size // 1000)]
    q = float(np.median(small))
    if not q > 0:
        return None
    # only small steps are checked: on calibrated output (scale/misalignment applied in float)
    # the lattice is slightly skewed, so a step of 1000 LSB lands off it while 1–5 LSB do not
    r = d[d <= 5.5 * q] / q
    if r.size < 100:
        return None
    frac = float(np.mean(np.abs(r - np.round(r)) < tol))
    return q if frac >= min_fraction else None


@dataclass(frozen=True, eq=False)
class TwinModel:
    """The twin's parameters.

    Attributes
    ----------
    rate_hz : float
        Output rate, Hz (mean rate of the recording; the twin runs on a uniform clock).
    params : dict
        ``{effect: {param: ndarray}}`` (PARAM_SCHEMA names, SI) handed to
        :class:`sim.gyro.SyntheticGyro` as overrides: deterministic terms, noise, quantization.
    extra : dict
        Terms of the *reference*, not of the sensor, added by the twin (:func:`_extra_noise`):
        ``reference_angle_noise`` {``sigma_rad`` (3,)}: white noise on the replicas' reference
        attitude (attitude references). The sensor's noise shapes the closing finds are
        registered simulator terms in ``params`` (``arw_lowpass``, ``arw_student``,
        ``angle_white``; :data:`gyrocore.effects.registry.NOISE_TERMS`).
    sources : dict
        effect -> where its value came from.
    notes : tuple of str
    """

    rate_hz: float
    params: Mapping[str, Mapping[str, np.ndarray]]
    extra: Mapping[str, Mapping[str, np.ndarray]] = field(default_factory=dict)
    sources: Mapping[str, str] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    format_version: str = FORMAT_VERSION

    def to_json(self) -> dict:
        def js(pd):
            return {k: np.asarray(v).tolist() for k, v in pd.items()}

        return {
            "rate_hz": self.rate_hz,
            "params": {e: js(p) for e, p in self.params.items()},
            "extra": {e: js(p) for e, p in self.extra.items()},
            "sources": dict(self.sources),
            "notes": list(self.notes),
            "format_version": self.format_version,
        }


_DETERMINISTIC_SKIP = {"bias_thermal", "scale_thermal"}  # need t0/range the loop table lacks


def _loop_params(table: Mapping) -> dict:
    """LoopResult.params (``{effect: {"name[i]": [value, se]}}``) -> PARAM_SCHEMA arrays."""
    out = {}
    for eff, entries in table.items():
        schema = _schema(eff)
        if schema is None or eff in _DETERMINISTIC_SKIP or eff == "earth_rate":
            continue
        arrs: dict[str, np.ndarray] = {}
        for key, (val, _se) in entries.items():
            name, _, idx = key.partition("[")
            if name not in schema:
                continue
            shape = schema[name]
            a = arrs.setdefault(name, np.zeros(shape))
            v = float(val) if np.isfinite(val) else 0.0
            if idx:
                ij = tuple(int(x) for x in idx.rstrip("]").split(","))
                a[ij] = v
            else:
                arrs[name] = np.asarray(v)
        if set(arrs) == set(schema):
            out[eff] = arrs
    return out


def _simulated_by_sim(name: str) -> bool:
    """True when the effect registry knows ``name`` (catalogue effect, noise term or family
    instance), so SyntheticGyro injects it."""
    try:
        E.resolve(name)
        return True
    except GyroInputError:
        return False


def _deterministic(det: Mapping, inp) -> np.ndarray:
    """:func:`gyrocore.effects.registry.deterministic` of ``det`` (rad/s, (N, 3))."""
    return E.deterministic(dict(det), inp) if det else np.array(inp.omega_S_rad_s, float)


def _schema(name: str):
    """Parameter schema of a catalogue effect or a family instance such as ``periodic[37.5]`` /
    ``step[9.47]`` (the registry's); None when the registry does not know the name."""
    if name in E.PARAM_SCHEMA:
        return E.PARAM_SCHEMA[name]
    try:
        return dict(E.resolve(name).schema)
    except GyroInputError:  # an unknown name is simply not replayed
        return None


def _inputs(rec: Recording, ref: Reference, rate_hz: float):
    from gyrocore.effects.registry import ModelInputs

    n = rec.n
    # uniform clock at the mean rate, from the recording's first time stamp (the loop's family
    # terms, periodic[f] and step[t_s], use absolute time)
    t = float(rec.t_s[0]) + np.arange(n) / rate_hz
    f = rec.accel_m_s2 if rec.accel_m_s2 is not None else np.tile([0.0, 0.0, 9.80665], (n, 1))
    temp = rec.temp_c if rec.temp_c is not None else np.full(n, 25.0)
    return ModelInputs(
        t_s=t,
        omega_S_rad_s=ref.omega_S_rad_s,
        f_S_m_s2=np.asarray(f, float),
        temp_c=np.asarray(temp, float),
        q_SW_wxyz=np.tile([1.0, 0, 0, 0], (n, 1)),
    )


def identify(
    rec: Recording, ref: Reference, *, segments: Sequence = (), params_file: str | None = None, loop_result=None
) -> TwinModel:
    """Identify the twin of ``rec`` (see the module docstring, step 2).

    Parameters
    ----------
    rec : Recording
    ref : Reference
    segments : sequence of Segment
        Passed to the loop.
    params_file : str, optional
        A gyroharness parameter file: its effects replace the loop's deterministic terms; its
        noise / quantization effects (if any) replace the identified ones.
    loop_result : LoopResult, optional
        A loop already run on ``rec`` (saves the run).
    """
    from gyrocore.noise.allan import identify_noise

    rate = float(rec.rate_hz)
    notes: list[str] = []
    sources: dict[str, str] = {}
    params: dict[str, dict[str, np.ndarray]] = {}
    given: dict = {}
    if params_file is not None:
        from gyrocore.calib.params import load_params

        given = {e: dict(p) for e, p in load_params(params_file).params.items()}
    det_given = {
        e: p for e, p in given.items() if not E.is_stochastic(e) and e not in ("quantization", "saturation", "lowpass")
    }
    if det_given:
        params.update(det_given)
        for e in det_given:
            sources[e] = f"parameter file {Path(params_file).name}"
    else:
        if loop_result is None:
            from gyrocore.loop.loop import run_loop

            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                loop_result = run_loop(rec, declared=["bias"], segments=list(segments))
        lp = _loop_params(loop_result.params)
        params.update(lp)
        found = list(loop_result.found_effects) + [u.effect for u in getattr(loop_result, "unexplained", ())]
        for e in lp:
            sources[e] = "residual loop (declared bias" + (f"; found {', '.join(found)}" if found else "") + ")"
        skipped = [e for e in loop_result.params if e not in lp]
        if skipped:
            notes.append(f"loop terms not replayed: {', '.join(skipped)}")
    # quantization from the data
    if "quantization" in given:
        params["quantization"] = given["quantization"]
        sources["quantization"] = "parameter file"
        lsb = float(given["quantization"]["lsb_rad_s"])
    else:
        lsb = lsb_from_differences(rec.gyro_rad_s)
        if lsb is not None:
            params["quantization"] = {"lsb_rad_s": np.asarray(lsb)}
            sources["quantization"] = f"lattice of first differences: LSB {lsb / DEG:.5g} °/s"
        else:
            sources["quantization"] = "none: the differences are not on a lattice (float output)"
    notes.append(
        "no on-chip low-pass in the twin: the simulator adds its noise after the DLPF, which would shape "
        "only the motion; its delay is the loop's time_offset where one was found"
    )
    # noise: Allan of the per-sample error signal after the deterministic model, covered spans
    noise_given = {e: p for e, p in given.items() if E.is_stochastic(e)}
    if noise_given:
        params.update(noise_given)
        for e in noise_given:
            sources[e] = "parameter file"
    else:
        inp = _inputs(rec, ref, rate)
        det = {e: p for e, p in params.items() if e not in ("quantization",)}
        e_sig = rec.gyro_rad_s - _deterministic(det, inp)
        x = _span_concat(e_sig, ref.spans)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            # the project's noise identification (the default GMWM with Gauss–Markov
            # terms); the spans are joined, so the motion gate is off (the error signal is
            # what is left after the deterministic model, not a still recording)
            an = identify_noise(x, rate_hz=rate, check_static=False)
        N = np.zeros(3)
        B = np.zeros(3)
        K = np.zeros(3)
        Q = np.zeros(3)
        GMs = np.zeros(3)
        GMt = np.ones(3)
        for i, a in enumerate("xyz"):
            t = an.axes[a].all_terms()  # the resolved terms (None: unresolved)
            N[i] = t["arw_rad_per_sqrt_s"] or 0.0
            B[i] = t["bias_instability_rad_s"] or 0.0
            K[i] = t["rrw_rad_per_s_sqrt_s"] or 0.0
            Q[i] = t["quantization_rad"] or 0.0
            if t["correlated_sigma_rad_s"] is not None and t["correlated_tau_c_s"]:
                GMs[i] = t["correlated_sigma_rad_s"]
                GMt[i] = t["correlated_tau_c_s"]
        if lsb is not None:
            n2 = N**2 - lsb**2 / (12.0 * rate)
            if np.any(n2 <= 0):
                notes.append("white noise at or below the LSB rounding noise on some axis: arw set to 0 there")
            N = np.sqrt(np.clip(n2, 0.0, None))
        params["arw"] = {"n_rad_per_sqrt_s": N}
        sources["arw"] = "identify_noise N of the covered spans" + (
            " (less LSB²/12 of rounding)" if lsb is not None else ""
        )
        if np.any(B > 0):
            params["bias_instability"] = {"b_rad_s": B}
            sources["bias_instability"] = "identify_noise B (unresolved axes 0)"
        if np.any(K > 0):
            params["rrw"] = {"k_rad_s_per_sqrt_s": K}
            sources["rrw"] = "identify_noise K (unresolved axes 0)"
        if np.any(GMs > 0):
            params["correlated"] = {"sigma_rad_s": GMs, "tau_c_s": GMt}
            sources["correlated"] = "identified Gauss–Markov σ, τc (unresolved axes σ = 0)"
        if np.any(Q > 0):
            notes.append(
                "Allan resolves white angle noise Q = "
                + ", ".join(f"{q:.3g}" for q in Q)
                + " rad, which the catalogue simulator does not carry"
            )
    return TwinModel(rate_hz=rate, params=params, sources=sources, notes=tuple(notes))


# ============================================================================ statistics
def model_error(model: "TwinModel", rec: Recording, ref: Reference) -> np.ndarray:
    """The twin's deterministic sensor error at the reference inputs, det(ω_ref) − ω_ref, rad/s (N, 3).

    The error signal of the real recording and of every replica is the measurement less
    det(ω_ref) (the loop's residual form): what is left is what the noise model must explain.
    """
    det = {
        e: p
        for e, p in model.params.items()
        if not E.is_stochastic(e) and e not in ("quantization", "saturation", "lowpass")
    }
    return _deterministic(det, _inputs(rec, ref, model.rate_hz)) - ref.omega_S_rad_s


# ============================================================================ replicas
def _spec(rate_hz: float):
    from sim.presets import SensorSpec

    return SensorSpec(
        name="twin",
        part="digital twin",
        datasheet="identified from data",
        rate_hz=rate_hz,
        full_scale_rad_s=1e6,
        lsb_rad_s=1e-9,
        temp_ref_c=25.0,
        effects={},
        disabled={},
    )


def _truth(rec: Recording, ref: Reference, rate_hz: float):
    from sim.truth import Truth

    inp = _inputs(rec, ref, rate_hz)
    n = rec.n
    return Truth(
        t_s=inp.t_s,
        omega_S_rad_s=ref.omega_S_rad_s,
        f_S_m_s2=inp.f_S_m_s2,
        q_SW_wxyz=inp.q_SW_wxyz,
        temp_c=inp.temp_c,
        t_since_power_up_s=inp.t_s - inp.t_s[0],
        power_up_index=np.zeros(n, int),
    )


def _extra_noise(model: TwinModel, rng_seed: int, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """The twin's own terms (:attr:`TwinModel.extra`) for one replica: (rate noise (N, 3) rad/s,
    reference angle noise (N, 3) rad or None)."""
    from sim.noise import effect_rng

    n = int(np.asarray(t_s).shape[0])
    extra = np.zeros((n, 3))
    ref_noise = None
    if "reference_angle_noise" in model.extra:
        s = np.asarray(model.extra["reference_angle_noise"]["sigma_rad"], float)
        ref_noise = effect_rng(rng_seed, "twin/reference_angle_noise").standard_normal((n, 3)) * s[None, :]
    if model.extra.get("periodic"):
        t = np.asarray(t_s, float)
        for fz, c in model.extra["periodic"].items():
            c = np.asarray(c, float)
            w = 2 * np.pi * float(fz) * t
            extra += np.cos(w)[:, None] * c[0][None, :] + np.sin(w)[:, None] * c[1][None, :]
    return extra, ref_noise


def _replica(model: TwinModel, truth, seed: int) -> tuple[np.ndarray, np.ndarray | None]:
    """One replica: the simulator (:class:`sim.gyro.SyntheticGyro`) with the twin's parameters —
    deterministic terms, catalogue noise and the registered noise terms the closing adds
    (``arw_lowpass``, ``arw_student``, ``angle_white``: :data:`gyrocore.effects.registry.NOISE_TERMS`) —
    plus the twin's reference terms (:func:`_extra_noise`)."""
    from sim.gyro import SyntheticGyro

    params = {e: dict(p) for e, p in model.params.items() if _simulated_by_sim(e)}
    g = SyntheticGyro(_spec(model.rate_hz), rate_hz=model.rate_hz, seed=seed, overrides=params)
    extra, ref_noise = _extra_noise(model, seed, truth.t_s)
    if np.any(extra):
        # legacy line terms join the simulator's own noise before quantization: re-run the output
        # stage with them (same order as sim.gyro: deterministic, DLPF, + noise, saturate, quantize)
        from gyrocore.effects.registry import deterministic, output_stage, ModelInputs

        noise, _ = g.noise(truth.n)
        p = g._model_params(g.power_up_bias(0))
        inp = ModelInputs(
            t_s=truth.t_s,
            omega_S_rad_s=truth.omega_S_rad_s,
            f_S_m_s2=truth.f_S_m_s2,
            temp_c=truth.temp_c,
            q_SW_wxyz=truth.q_SW_wxyz,
            t_since_power_up_s=truth.t_since_power_up_s,
        )
        y = output_stage(deterministic(p, inp), p, rate_hz=model.rate_hz, noise_rad_s=noise + extra)
        return y, ref_noise
    return g.measure(truth).gyro_rad_s, ref_noise


def shaped_white_noise_terms(N: np.ndarray, *, fc_hz: float = float("inf"), nu=None) -> dict:
    """The registered noise term that carries white rate noise of density N (rad/√s, (3,))
    through the chip's low-pass at ``fc_hz`` (∞ = none) with Student-t draws of ν (None =
    Gaussian): ``{"arw": …}``, ``{"arw_lowpass": …}`` or ``{"arw_student": …}``
    (:data:`gyrocore.effects.registry.NOISE_TERMS`)."""
    N = np.asarray(N, float)
    fc = float(fc_hz)
    if nu is not None:
        return {
            "arw_student": {
                "n_rad_per_sqrt_s": N,
                "nu": np.asarray(nu, float),
                "bandwidth_hz": np.asarray(fc if np.isfinite(fc) else 0.0),
            }
        }
    if np.isfinite(fc):
        return {"arw_lowpass": {"n_rad_per_sqrt_s": N, "bandwidth_hz": np.asarray(fc)}}
    return {"arw": {"n_rad_per_sqrt_s": N}}


_WHITE_TERMS = ("arw", "arw_lowpass", "arw_student")


def _white_term(params: Mapping) -> tuple[np.ndarray | None, float, np.ndarray | None]:
    """(N, fc, ν) of the white rate noise term in ``params`` (whichever of :data:`_WHITE_TERMS`)."""
    for e in _WHITE_TERMS:
        if e in params:
            pd = params[e]
            fc = float(pd.get("bandwidth_hz", 0.0)) if e != "arw" else 0.0
            return (
                np.asarray(pd["n_rad_per_sqrt_s"], float),
                fc if fc > 0 else float("inf"),
                np.asarray(pd["nu"], float) if "nu" in pd else None,
            )
    return None, float("inf"), None


def replica_statistics(
    model: TwinModel,
    rec: Recording,
    ref: Reference,
    layout: StatLayout,
    *,
    n_replicas: int,
    seed: int,
    det_err: np.ndarray | None = None,
) -> list[dict]:
    """Statistics of ``n_replicas`` replicas, seeds ``SeedSequence(seed).spawn(n_replicas)``.

    ``det_err`` (default: :func:`model_error` of ``model``) is what is taken off every error
    signal; the closing step keeps the one of the model as given, so that the real error signal
    is the same before and after and a term added by the closing is simulated, not subtracted.
    """
    truth = _truth(rec, ref, model.rate_hz)
    if det_err is None:
        det_err = model_error(model, rec, ref)
    children = np.random.SeedSequence(seed).spawn(n_replicas)
    out = []
    R_ref = None
    if layout.att_windows is not None:
        # the replicas' reference is the motion that drove them (zero on the rests, the
        # attitude's own rate elsewhere): a perfect reference; the real one's noise is what the
        # closing step may add (reference_angle_noise)
        from gyrocore.attitude import integrate_gyro

        R_ref = _quat_R(integrate_gyro(truth.t_s, ref.omega_S_rad_s, hold="backward"))
    for ch in children:
        s = int(ch.generate_state(1, dtype=np.uint32)[0])
        y, ref_noise = _replica(model, truth, s)
        e = y - ref.omega_S_rad_s - det_err
        att = None
        if R_ref is not None:
            Rr = R_ref
            if ref_noise is not None:
                from scipy.spatial.transform import Rotation

                Rr = R_ref * Rotation.from_rotvec(ref_noise)
            a, b = layout.att_windows
            att = _attitude_windows(y - det_err, truth.t_s, Rr, a, b)
        out.append(error_statistics(e, ref.spans, layout, att_resid=att))
    return out


# ============================================================================ comparison
@dataclass(frozen=True, eq=False)
class Comparison:
    """Real statistics against the replicas' band.

    Attributes
    ----------
    real : dict name -> ndarray (3, J)
    lo, hi, median : dict name -> ndarray (3, J)
        Pointwise band [x_(k), x_(N+1−k)] of the N replicas and their median.
    out : dict name -> ndarray of bool (3, J)
        Real value outside the band (NaN bins never count).
    in_band_fraction, p_value : dict name -> float
    passed : dict name -> bool
    twin_distance : float
        Mean over statistics of the fraction of bins outside the band.
    null_out_rate : float
        2k/(N+1): the exact pointwise false-out rate of the band under "the twin is right".
    k, n_replicas : int
    alpha_per_statistic : float
    """

    real: dict
    lo: dict
    hi: dict
    median: dict
    out: dict
    in_band_fraction: dict
    p_value: dict
    passed: dict
    twin_distance: float
    null_out_rate: float
    k: int
    n_replicas: int
    alpha_per_statistic: float

    def to_json(self) -> dict:
        return {
            "twin_distance": self.twin_distance,
            "null_out_rate": self.null_out_rate,
            "statistics": {
                n: {
                    "in_band_fraction": self.in_band_fraction[n],
                    "pass": bool(self.passed[n]),
                    "p_value": self.p_value[n],
                    "n_bins": int(np.isfinite(self.real[n]).sum()),
                }
                for n in self.real
            },
        }


def compare(real: dict, reps: Sequence[dict], *, alpha: float = ALPHA, seed: int = 0) -> Comparison:
    """Per-statistic band, out-fraction and rank-count test.

    With N replicas and M = N + 1, the band of a bin is [x_(k), x_(N+1−k)] of the replicas'
    values, k = max(1, ⌊0.025·M⌋). If the twin is right, the real series and the N replicas
    are exchangeable, so the real value falls outside with probability exactly 2k/M per bin
    (ranks among M are uniform). The bins of one statistic are correlated (neighbouring τ and
    frequencies share data), so the number of out-bins C has no binomial law; but C of any of
    the M series, computed the same way against the other N, has the same distribution: the
    real value is outside [x_(k), x_(N+1−k)] of the replicas iff its rank among all M is ≤ k
    or ≥ M + 1 − k. The p-value is (number of series with C ≥ C_real)/M (the real one
    included) — a permutation test, exact for any correlation between bins. A statistic passes
    when p > α/S (Bonferroni over the S statistics: the whole twin false-fails with
    probability ≤ α).
    """
    names = list(real)
    N = len(reps)
    M = N + 1
    k = max(1, int(math.floor(0.025 * M)))
    S = len(names)
    a_stat = alpha / S
    res = {key: {} for key in ("lo", "hi", "median", "out", "frac", "p", "pass")}
    for nm in names:
        r = np.asarray(real[nm], float)
        X = np.stack([np.asarray(rp[nm], float) for rp in reps])  # (N, 3, J)
        allv = np.concatenate([r[None], X])  # (M, 3, J)
        finite = np.all(np.isfinite(allv), axis=0)
        # each series against the band of the other N (leave-one-out order statistics): with
        # continuous values this is "rank <= k or >= M + 1 - k"; a value tied with the band's
        # edge is inside (quantized statistics, e.g. a tail count of 0 everywhere)
        v = np.where(finite[None], allv, 0.0)
        order = np.argsort(v, axis=0, kind="stable")
        Xs = np.take_along_axis(v, order, axis=0)
        pos = np.empty_like(order)
        np.put_along_axis(pos, order, np.arange(M)[:, None, None] * np.ones_like(order), axis=0)
        lo_s = np.where(pos > k - 1, Xs[k - 1][None], Xs[k][None])
        hi_s = np.where(pos < M - k, Xs[M - k][None], Xs[M - k - 1][None])
        out_all = ((v < lo_s) | (v > hi_s)) & finite[None]
        C = out_all.reshape(M, -1).sum(axis=1)
        nb = int(finite.sum())
        # max-type statistic: the largest robust z of a series over the bins, with the median
        # and MAD taken over all M series (a symmetric function: exchangeability is kept)
        med = np.median(v, axis=0)
        mad = 1.4826 * np.median(np.abs(v - med[None]), axis=0)
        z = np.abs(v - med[None]) / np.maximum(mad, 1e-12 * (np.abs(med) + 1e-30))[None]
        Tmax = np.where(finite[None], z, 0.0).reshape(M, -1).max(axis=1)
        p_count = float(np.mean(C >= C[0])) if nb else 1.0
        p_max = float(np.mean(Tmax >= Tmax[0])) if nb else 1.0
        p = min(1.0, 2.0 * min(p_count, p_max))
        Xs = np.sort(X, axis=0)
        res["lo"][nm] = Xs[k - 1]
        res["hi"][nm] = Xs[N - k]
        res["median"][nm] = np.median(X, axis=0)
        res["out"][nm] = out_all[0]
        res["frac"][nm] = 1.0 - (C[0] / nb if nb else 0.0)
        res["p"][nm] = p
        res["pass"][nm] = p > a_stat
    dist = float(np.mean([1.0 - res["frac"][nm] for nm in names]))
    return Comparison(
        real=dict(real),
        lo=res["lo"],
        hi=res["hi"],
        median=res["median"],
        out=res["out"],
        in_band_fraction=res["frac"],
        p_value=res["p"],
        passed=res["pass"],
        twin_distance=dist,
        null_out_rate=2.0 * k / M,
        k=k,
        n_replicas=N,
        alpha_per_statistic=a_stat,
    )


# ============================================================================ closing
def _lines(e: np.ndarray, spans, rate: float) -> list[float]:
    """Narrow-band lines of the real error signal: Welch bins 30× above the local median
    (31-bin median filter), then each frequency refined by least squares (the amplitude of a
    sinusoid fitted on the covered spans, maximised on a grid ±1 Welch bin)."""
    nper = min(4096, max(256, 2 ** int(np.floor(np.log2(max(b - a for a, b in spans) / 4)))))
    acc, w = None, 0
    for a, b in spans:
        if b - a >= nper:
            f, P = signal.welch(e[a:b], fs=rate, nperseg=nper, axis=0)
            acc = P if acc is None else acc + P
            w += 1
    if acc is None:
        return []
    P = acc / w
    med = np.stack([signal.medfilt(P[:, i], 31) for i in range(3)], axis=1)
    peak = np.max(P / np.maximum(med, 1e-300), axis=1)
    cand = np.flatnonzero((peak > 30.0) & (f > 2 * rate / nper) & (f < 0.49 * rate))
    idx = np.concatenate([np.arange(a, b) for a, b in spans])
    t = idx / rate
    x = e[idx] - e[idx].mean(axis=0)
    out: list[float] = []
    for c in cand:  # local maxima only
        if not (peak[c] >= peak[max(c - 1, 0)] and peak[c] >= peak[min(c + 1, len(peak) - 1)]):
            continue
        df = rate / nper
        grid = np.linspace(f[c] - df, f[c] + df, 81)
        power = [np.sum(np.abs(np.exp(-2j * np.pi * fz * t) @ x) ** 2) for fz in grid]
        out.append(float(grid[int(np.argmax(power))]))
    return out[:5]


def _avar_columns(m: np.ndarray, rate: float, fc_hz: float) -> np.ndarray:
    """AVAR per unit coefficient (J, 4) at m samples: [white through a 2nd-order Butterworth at
    fc (N²), white angle (Q²), flicker floor (B²), rate random walk (K²)].

    Discrete AVAR from the one-sided PSD S(f) of the rate:
    σ²(m) = ½ ∫₀^{fs/2} S(f)·4 sin²(πfmτ₀)·[sin(πfmτ₀)/(m sin(πfτ₀))]² df (difference of two
    adjacent m-sample means). White rate: S = 2N²|H(f)|²; white angle of σ = Q: S = 2Q²·fs·4
    sin²(πf/fs). Flicker: its IEEE 952 floor (2 ln2/π)B²; random walk: K²τ/3.
    """
    tau0 = 1.0 / rate
    f = np.geomspace(rate * 1e-8, rate / 2, 20000)
    x = np.pi * f * tau0
    cols = np.zeros((m.size, 4))
    if np.isfinite(fc_hz):
        b, a = signal.butter(2, fc_hz, fs=rate)
        _, h = signal.freqz(b, a, worN=f, fs=rate)
        H2 = np.abs(h) ** 2
    else:
        H2 = np.ones_like(f)
    for j, mm in enumerate(m):
        kern = 2.0 * np.sin(mm * x) ** 2 * (np.sin(mm * x) / (mm * np.sin(x))) ** 2  # ½·4 = 2
        cols[j, 0] = np.trapezoid(2.0 * H2 * kern, f)
        cols[j, 1] = np.trapezoid(2.0 * rate * 4.0 * np.sin(x) ** 2 * kern, f)
    tau = m * tau0
    cols[:, 2] = 2.0 * np.log(2.0) / np.pi
    cols[:, 3] = tau / 3.0
    return cols


def fit_noise_family(e: np.ndarray, spans, rate: float, *, lsb_rad_s: float = 0.0) -> dict:
    """Noise model over an extended family fitted to the real ADEV (closing step).

    Family: white rate noise through a 2nd-order low-pass at fc (fc = ∞: no filter; grid of
    25 values 0.03–0.45·rate), white angle noise Q, flicker B, random walk K; the LSB's
    rounding noise (LSB²/12 per sample, white, after any filter) is known and subtracted.
    Coefficients ≥ 0 by NNLS on relative errors, fc shared by the axes (one chip filter),
    chosen by the smallest summed squared relative error. Returns {"fc_hz", "N", "Q", "B", "K"}
    (arrays (3,), fc a float, inf when unfiltered fits best).
    """
    from scipy.optimize import nnls

    longest = max(b - a for a, b in spans)
    m = 2 ** np.arange(0, 40)
    m = m[m <= longest // 5]
    av = _pooled_adev(e, spans, m, rate) ** 2  # (3, J)
    av_fit = av - (lsb_rad_s**2 / 12.0) / m[None, :]
    # weights: relative variance of an overlapping AVAR estimate ≈ 1/edf, edf ≈ (n − 2m)/m
    # for white-type noise (SP 1065 Table 5 order of magnitude) — short τ are far more precise
    n_cov = sum(b - a for a, b in spans)
    w = np.sqrt(np.clip((n_cov - 2 * m) / m, 1.0, None))
    best = None
    for fc in [np.inf] + list(np.geomspace(0.03 * rate, 0.45 * rate, 25)):
        G = _avar_columns(m, rate, fc)
        cost, coefs = 0.0, []
        for i in range(3):
            a = np.clip(av_fit[i], 1e-30, None)
            c, rn = nnls(G * (w / a)[:, None], w)
            cost += rn**2
            coefs.append(c)
        if best is None or cost < best[0] - 1e-12:
            best = (cost, fc, np.array(coefs))
    _, fc, C = best
    return {
        "fc_hz": float(fc),
        "N": np.sqrt(C[:, 0]),
        "Q": np.sqrt(C[:, 1]),
        "B": np.sqrt(C[:, 2]),
        "K": np.sqrt(C[:, 3]),
        "cost": float(best[0]),
    }


def close_twin(model: TwinModel, rec: Recording, ref: Reference, cmp: Comparison) -> tuple[TwinModel, list[str]]:
    """Add to the twin what its failing statistics point at; returns (new model, what was added).

    * ``adev``/``psd`` fail with the real ADEV above the band at the shortest τ and the Allan
      fit resolving a white-angle term Q (slope −1, a PSD rising as f²): ``angle_white`` with
      that Q (Allan: σ² = 3Q²/τ², a white angle sequence of σ = Q).
    * ``distribution`` fails with the real excess kurtosis above the band: heavy-tailed white
      noise, Student t with ν = 4 + 6/κ (excess kurtosis of t_ν is 6/(ν − 4)), κ the excess
      kurtosis the white part must carry: κ_e·(σ_e²/σ_w²)² with σ_w² = N²·rate.
    * ``psd`` fails and the real spectrum holds narrow lines: ``periodic[f]`` per line,
      coefficients by least squares on the covered spans.
    * ``attitude_residual`` fails with a negative lag-1 autocorrelation of the window
      residual: white noise on the reference attitude (optical noise), σ_θ² = −cov₁·T²
      (a white angle noise θ at the window ends gives y_m = (θ_b − θ_a)/T, lag-1 covariance
      −σ_θ²/T²). This is a term of the *reference*, not of the sensor.
    """
    added: list[str] = []
    params = {e: dict(p) for e, p in model.params.items()}
    extra = {e: dict(p) for e, p in model.extra.items()}
    sources = dict(model.sources)
    rate = model.rate_hz
    inp = _inputs(rec, ref, rate)
    det = {e: p for e, p in params.items() if not E.is_stochastic(e) and e != "quantization"}
    e_sig = rec.gyro_rad_s - _deterministic(det, inp)
    x = _span_concat(e_sig, ref.spans)
    failed = {n for n, ok in cmp.passed.items() if not ok}
    lines_found = False
    if "psd" in failed:
        lines = _lines(e_sig, ref.spans, rate)
        lines_found = bool(lines)
        if lines:
            t = inp.t_s
            extra["periodic"] = {}
            for fz in lines:
                cov = np.zeros(rec.n, bool)
                for a, b in ref.spans:
                    cov[a:b] = True
                A = np.column_stack(
                    [np.cos(2 * np.pi * fz * t[cov]), np.sin(2 * np.pi * fz * t[cov]), np.ones(cov.sum())]
                )
                coef, *_ = np.linalg.lstsq(A, e_sig[cov], rcond=None)
                fam = E.canonical_name(f"periodic[{fz:.6g}]")
                if _schema(fam) is not None:  # the effect registry simulates it
                    params[fam] = {"a_cos_rad_s": coef[0], "a_sin_rad_s": coef[1]}
                    sources[fam] = "closing: a line of the real PSD, least squares on the covered spans"
                else:
                    extra["periodic"][f"{fz:.6g}"] = coef[:2]  # (2, 3): a_cos, a_sin per axis
                e_sig = e_sig - (
                    np.cos(2 * np.pi * fz * t)[:, None] * coef[0][None, :]
                    + np.sin(2 * np.pi * fz * t)[:, None] * coef[1][None, :]
                )
                added.append(
                    f"line periodic[{fz:.4g}] amplitude "
                    + ", ".join(f"{np.hypot(*coef[:2, i]):.3g}" for i in range(3))
                    + " rad/s"
                )
        x = _span_concat(e_sig, ref.spans)
    if failed & {"adev", "window_acf"} or ("psd" in failed and not lines_found):
        lsb = float(params["quantization"]["lsb_rad_s"]) if "quantization" in params else 0.0
        fit = fit_noise_family(e_sig, ref.spans, rate, lsb_rad_s=lsb)
        old = {
            k: np.asarray(v.get(list(v)[0]), float)
            for k, v in params.items()
            if k in ("arw", "bias_instability", "rrw")
        }
        for eff in ("arw", "bias_instability", "rrw", "angle_white") + _WHITE_TERMS:
            params.pop(eff, None)
        # the white part through the registry: arw, or arw_lowpass when the chip's filter shapes it
        white = shaped_white_noise_terms(fit["N"], fc_hz=fit["fc_hz"])
        params.update(white)
        if np.any(fit["B"] > 0):
            params["bias_instability"] = {"b_rad_s": fit["B"]}
        if np.any(fit["K"] > 0):
            params["rrw"] = {"k_rad_s_per_sqrt_s": fit["K"]}
        for k in ("bias_instability", "rrw", *white):
            sources[k] = "noise refit over the extended family (ADEV of the covered spans)"
        what = []
        if np.isfinite(fit["fc_hz"]):
            sources["arw_lowpass"] = (
                "noise refit: the white noise passes a 2nd-order low-pass (registered term arw_lowpass)"
            )
            what.append(
                f"white noise through a 2nd-order low-pass at {fit['fc_hz']:.3g} Hz (coloured noise; arw_lowpass)"
            )
        if np.any(fit["Q"] > 0):
            params["angle_white"] = {"q_rad": fit["Q"]}
            sources["angle_white"] = "noise refit: white angle noise (Allan Q; registered term angle_white)"
            what.append("white angle noise Q = " + ", ".join(f"{q:.3g}" for q in fit["Q"]) + " rad")
        ob = old.get("bias_instability", np.zeros(3))
        if np.any(np.abs(fit["B"] - ob) > 0.2 * np.maximum(ob, 1e-12)):
            what.append(
                "bias instability B "
                + ", ".join(f"{a:.2g}" for a in ob)
                + " -> "
                + ", ".join(f"{b:.2g}" for b in fit["B"])
                + " rad/s"
            )
        if what:
            added.append("noise refit: " + "; ".join(what))
    if "distribution" in failed:
        ku = cmp.real["distribution"][:, 1]
        hi = cmp.hi["distribution"][:, 1]
        N, fc_w, _ = _white_term(params)
        if np.any(ku > hi) and N is not None:
            sd2 = x.var(axis=0)
            w2 = N**2 * rate
            kw = np.where(ku > hi, ku * (sd2 / np.maximum(w2, 1e-300)) ** 2, 0.0)
            nu = np.where(kw > 0, 4.0 + 6.0 / np.maximum(kw, 1e-6), 1e6)
            nu = np.clip(nu, 4.05, 1e6)
            for e in _WHITE_TERMS:
                params.pop(e, None)
            params.update(shaped_white_noise_terms(N, fc_hz=fc_w, nu=nu))
            sources["arw_student"] = "Student-t white noise, ν from the excess kurtosis (registered term arw_student)"
            added.append("heavy-tailed white noise, Student t ν = " + ", ".join(f"{v:.3g}" for v in nu))
    if "attitude_residual" in failed and ref.q_ref_wxyz is not None:
        ac1 = cmp.real["attitude_residual"][:, 2]
        sd = 10 ** cmp.real["attitude_residual"][:, 0]
        T = WINDOW_S
        cov1 = np.where(ac1 < 0, -ac1 * sd**2, 0.0)
        sig = np.sqrt(cov1) * T
        if np.any(sig > 0):
            extra["reference_angle_noise"] = {"sigma_rad": sig}
            sources["reference_angle_noise"] = "lag-1 autocovariance of the window residual (reference term)"
            added.append(
                "reference (optical) angle noise σθ = "
                + ", ".join(f"{s / DEG:.3g}" for s in sig)
                + "° per sample — a term of the reference, not the sensor"
            )
    new = replace(model, params=params, extra=extra, sources=sources)
    return new, added


# ============================================================================ the whole twin
@dataclass(frozen=True, eq=False)
class TwinResult:
    """Result of :func:`twin` (JSON: :meth:`to_json`)."""

    file: str
    reference: Reference
    model: TwinModel
    before: Comparison
    after: Comparison | None
    model_after: TwinModel | None
    added: tuple[str, ...]
    layout: StatLayout
    wall_s: float
    format_version: str = FORMAT_VERSION

    def to_json(self) -> dict:
        d = self.before.to_json()
        d.update(
            {
                "format_version": self.format_version,
                "file": self.file,
                "reference": self.reference.kind,
                "reference_description": self.reference.description,
                "n_replicas": self.before.n_replicas,
                "band_k": self.before.k,
                "alpha_per_statistic": self.before.alpha_per_statistic,
                "model": self.model.to_json(),
                "added": list(self.added),
                "wall_s": self.wall_s,
            }
        )
        if self.after is not None:
            d["after"] = self.after.to_json()
            # the closing is adopted only when it brings the twin closer to the real sensor
            d["after"]["accepted"] = bool(self.after.twin_distance < self.before.twin_distance)
            d["model_after"] = self.model_after.to_json()
        return d


def _real_stats(rec: Recording, ref: Reference, layout: StatLayout, model: TwinModel) -> dict:
    det_err = model_error(model, rec, ref)
    e = rec.gyro_rad_s - ref.omega_S_rad_s - det_err
    att = None
    if layout.att_windows is not None:
        q = np.where(np.all(np.isfinite(ref.q_ref_wxyz), axis=1)[:, None], ref.q_ref_wxyz, [1.0, 0, 0, 0])
        a, b = layout.att_windows
        att = _attitude_windows(rec.gyro_rad_s - det_err, np.arange(rec.n) / rec.rate_hz, _quat_R(q), a, b)
    return error_statistics(e, ref.spans, layout, att_resid=att)


def twin(
    rec: Recording,
    *,
    segments: Sequence = (),
    params_file: str | None = None,
    n_replicas: int = DEFAULT_REPLICAS,
    seed: int = 0,
    close: bool = True,
    alpha: float = ALPHA,
    model: TwinModel | None = None,
    file: str = "",
) -> TwinResult:
    """Build, replay and compare the twin of ``rec``; close it when ``close``.

    Parameters
    ----------
    rec : Recording
    segments : sequence of Segment
    params_file : str, optional
        Parameter file of the declared model (else the loop identifies it).
    n_replicas : int
        N (≥ 19). With α = 0.05 over 5 statistics, N ≥ 199 is needed for a fail to be possible
        at all (smallest p-value 1/(N+1)).
    seed : int
        Root of the replicas' seeds.
    close : bool
        Run the closing step and the "after" comparison.
    model : TwinModel, optional
        Use this model instead of identifying one (tests: the true parameters).
    """
    t0 = _time.perf_counter()
    if n_replicas < 19:
        raise GyroInputError(f"--replicas must be >= 19 (a 95 % band needs k >= 1 of N + 1 >= 20), got {n_replicas}")
    ref = reference_of(rec, segments)
    if ref.coverage_note:
        warn_repair(ref.coverage_note)
    if model is None:
        model = identify(rec, ref, segments=segments, params_file=params_file)
    layout = layout_for(ref, model.rate_hz, rec.n)
    real = _real_stats(rec, ref, layout, model)
    reps = replica_statistics(model, rec, ref, layout, n_replicas=n_replicas, seed=seed)
    before = compare(real, reps, alpha=alpha, seed=seed)
    after = model_after = None
    added: list[str] = []
    if close and not all(before.passed.values()):
        model_after, added = close_twin(model, rec, ref, before)
        if added:
            reps2 = replica_statistics(
                model_after,
                rec,
                ref,
                layout,
                n_replicas=n_replicas,
                seed=seed + 1,
                det_err=model_error(model, rec, ref),
            )
            after = compare(real, reps2, alpha=alpha, seed=seed + 1)
        else:
            model_after = None
    return TwinResult(
        file=file,
        reference=ref,
        model=model,
        before=before,
        after=after,
        model_after=model_after,
        added=tuple(added),
        layout=layout,
        wall_s=_time.perf_counter() - t0,
    )


# ============================================================================ plots and run
def plot_twin(result: TwinResult, out_dir, *, prefix: str = "twin") -> list[str]:
    """One PNG per statistic, ``out_dir/figures/<prefix>_<statistic>.png``: real (black) against the
    replicas' band (grey: as given; blue: after). Returns the paths relative to ``out_dir``."""
    from experiments.report import new_figure, save_figure

    paths = []
    for nm in result.before.real:
        x, xlabel = result.layout.x(nm)
        fig = new_figure(figsize=(12, 3.4))
        axs = fig.subplots(1, 3)
        rel = nm in ("adev", "psd")  # plotted relative to the replicas' median (the bands are narrow)
        for i, ax in enumerate(axs):
            c = result.before
            base = c.median[nm][i] if rel else 0.0
            ax.fill_between(
                x, c.lo[nm][i] - base, c.hi[nm][i] - base, color="0.75", label=f"twin as given, {c.n_replicas} replicas"
            )
            if result.after is not None:
                ax.fill_between(
                    x,
                    result.after.lo[nm][i] - base,
                    result.after.hi[nm][i] - base,
                    color="tab:blue",
                    alpha=0.3,
                    label="twin after closing",
                )
            ax.plot(x, c.real[nm][i] - base, "k.-", label="real")
            o = c.out[nm][i]
            ax.plot(np.asarray(x)[o], (c.real[nm][i] - base)[o], "rx", label="outside band")
            if nm in ("adev", "psd"):
                ax.set_xscale("log")
            ax.set_title(f"{nm}, axis {'xyz'[i]}")
            ax.set_xlabel(xlabel)
        axs[0].set_ylabel(
            {
                "adev": "log10(ADEV / median of replicas as given)",
                "psd": "log10(PSD / median of replicas as given)",
            }.get(nm, "value")
        )
        axs[-1].legend(fontsize=7)
        paths.append(save_figure(fig, out_dir, f"{prefix}_{nm}"))
    return paths


def load_recording(path, *, retime: bool | None = None):
    """(Recording, segments) of a data file or a real set (gyrocore.readers.convert.load_with_segments)."""
    from gyrocore.readers.convert import load_with_segments

    c = load_with_segments(path)
    return c.recording, list(c.segments)


def _cell(c: Comparison | None) -> str:
    if c is None:
        return "—"
    return ", ".join(f"{n} {'in' if c.passed[n] else '**out**'} ({c.in_band_fraction[n]:.2f})" for n in c.real)


def _row(name: str, cmd: str, r: TwinResult, h: dict | None = None) -> list:
    hb = h.get("_before") if h else None
    ha = h.get("_after") if h else None
    held = (
        "—"
        if not h
        else (
            h["error"]
            if h.get("error")
            else f"{hb.twin_distance:.3f} → {ha.twin_distance:.3f}"
            if ha is not None
            else f"{hb.twin_distance:.3f}"
        )
    )
    return [
        name,
        held,
        _cell(r.before),
        f"{r.before.twin_distance:.3f}",
        "; ".join(r.added) or "nothing",
        _cell(r.after),
        f"{r.after.twin_distance:.3f}" if r.after is not None else "—",
        f"`{cmd}`",
    ]


#: ``--quick``: two small sets only.
#: the standard size of ``gyroharness run``: one set per source (BROAD, sunsided, tomisuarez2,
#: PX4, imucal); --full adds BROAD 05, 07 and 09
STANDARD_SETS = (
    "BROAD 02 slow rotation",
    "sunsided set-2 static 10 min",
    "tomisuarez2 static 449 s",
    "PX4 sample.ulg (still part)",
    "imucal Ferraris session",
)
QUICK_SETS = ("tomisuarez2 static 449 s", "imucal Ferraris session")


def run(
    *,
    out_dir,
    quick: bool = False,
    seeds: int | None = None,
    workers: int | None = None,
    data_dir: str | None = None,
    replicas: int | None = None,
    names: Sequence[str] | None = None,
    seed: int = 0,
    do_holdout: bool = True,
    size: str | None = None,
    progress=None,
    **_ignored,
):
    """The twin on every real set of :data:`SETS` found under ``data_dir`` (one setting for all).

    ``quick``: 39 replicas on :data:`QUICK_SETS` only; ``size="standard"`` (``gyroharness run``):
    :data:`STANDARD_REPLICAS` on :data:`STANDARD_SETS`; full: :data:`DEFAULT_REPLICAS`. Sets whose files are
    absent are skipped.
    """
    size = size or ("quick" if quick else "full")
    quick = size == "quick"
    if names is None and quick:
        names = QUICK_SETS
    elif names is None and size == "standard":
        names = STANDARD_SETS
    if data_dir is None:
        from experiments.datadir import DEFAULT_DATA_DIR, shared_data_dir

        data_dir = shared_data_dir() or DEFAULT_DATA_DIR  # GYROHARNESS_DATA, else beside the checkout
    from experiments.report import ExperimentResult, md_table
    from gyrocore.data.recording import atomic_write_text

    t_start = _time.time()
    out = Path(out_dir)
    n_rep = replicas or (39 if quick else STANDARD_REPLICAS if size == "standard" else DEFAULT_REPLICAS)
    rows, figures, summary = [], [], {}
    todo = [(name, rel) for name, rel in SETS if (names is None or name in names) and (Path(data_dir) / rel).exists()]
    for i, (name, rel) in enumerate(todo):
        if progress is not None:
            progress(i, len(todo))
        p = Path(data_dir) / rel
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rec, segs = load_recording(p)
            r = twin(rec, segments=segs, n_replicas=n_rep, seed=seed, file=str(p))
            h = holdout(rec, segments=segs, n_replicas=n_rep, seed=seed) if do_holdout else None
        slug = "".join(ch if ch.isalnum() else "_" for ch in name.lower()).strip("_")
        figures += plot_twin(r, out, prefix=f"twin_{slug}")
        rows.append(_row(name, f"gyroharness twin {rel} --replicas {n_rep} -o out/twin_{slug} --json", r, h))
        summary[name] = r.to_json()
        if h is not None:
            summary[name]["holdout"] = {k: v for k, v in h.items() if not k.startswith("_")}
    if not rows:
        md = [f"No real set found under {data_dir}: nothing to twin."]
        return ExperimentResult(
            name="twin",
            title="Digital twin of the real sensors",
            markdown="\n".join(md),
            figures=(),
            summary={},
            wall_s=_time.time() - t_start,
        )
    k_band = max(1, int(0.025 * (n_rep + 1)))
    md = [
        f"Replicas: {n_rep} per set, seed {seed}; band k = {k_band}: a real statistic outside the k-th smallest "
        f"to k-th largest replica has probability {2 * k_band}/{n_rep + 1} = {2 * k_band / (n_rep + 1):.3f} when the "
        f"twin is right (rank test, two-sided 95 % band); α = {ALPHA} family-wise over the statistics."
        + (
            " `gyroharness run --full` uses 199 replicas (finer p-values, more power)."
            if n_rep < DEFAULT_REPLICAS
            else ""
        ),
        "",
        md_table(
            [
                "set",
                "held out: distance given → after",
                "statistics as given (in-band fraction)",
                "distance",
                "added",
                "after",
                "distance after",
                "command",
            ],
            rows,
        ),
    ]
    text = "\n".join(md)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "twin.md", "## Digital twin\n\n" + text + "\n")
    return ExperimentResult(
        name="twin",
        title="Digital twin of the real sensors",
        markdown=text,
        figures=tuple(figures),
        summary=summary,
        wall_s=_time.time() - t_start,
    )


def summary_text(r: TwinResult) -> str:
    """Readable summary of a :class:`TwinResult` (the CLI's default output)."""
    lines = [
        f"reference: {r.reference.kind} — {r.reference.description}",
        "twin: " + "; ".join(f"{e}: {s}" for e, s in r.model.sources.items()),
    ]
    for label, c in (("as given", r.before), ("after", r.after)):
        if c is None:
            continue
        lines.append(
            f"{label}: twin distance {c.twin_distance:.3f} (null {c.null_out_rate:.3f}, {c.n_replicas} replicas, "
            f"k = {c.k}, α per statistic {c.alpha_per_statistic:.3g})"
        )
        for n in c.real:
            lines.append(
                f"  {n:18s} in band {c.in_band_fraction[n]:.2f}  p = {c.p_value[n]:.3g}  "
                + ("pass" if c.passed[n] else "FAIL")
            )
    if r.added:
        lines.append("added: " + "; ".join(r.added))
    for n in r.model.notes:
        lines.append(f"note: {n}")
    return "\n".join(lines)


def markdown(r: TwinResult, figures: Sequence[str] = ()) -> str:
    """Markdown section of one twin (the CLI's twin.md)."""
    from experiments.report import md_table

    rows = []
    for n in r.before.real:
        a = r.after
        rows.append(
            [
                n,
                f"{r.before.in_band_fraction[n]:.2f}",
                f"{r.before.p_value[n]:.3g}",
                "pass" if r.before.passed[n] else "**fail**",
                f"{a.in_band_fraction[n]:.2f}" if a else "—",
                f"{a.p_value[n]:.3g}" if a else "—",
                ("pass" if a.passed[n] else "**fail**") if a else "—",
            ]
        )
    md = [
        f"# Twin of {r.file}",
        "",
        f"Reference: {r.reference.kind} — {r.reference.description}.",
        "",
        "Twin parameters: " + "; ".join(f"`{e}` from {s}" for e, s in r.model.sources.items()) + ".",
        "",
        md_table(["statistic", "in band (given)", "p", "verdict", "in band (after)", "p", "verdict"], rows),
        "",
        f"Twin distance {r.before.twin_distance:.3f} as given"
        + (f", {r.after.twin_distance:.3f} after adding: {'; '.join(r.added)}" if r.after else "")
        + f" (null level {r.before.null_out_rate:.3f} = 2k/(N+1), N = {r.before.n_replicas}).",
        "",
    ]
    md += [f"![{Path(f).stem}]({f})" for f in figures]
    return "\n".join(md)


def preset_claim(
    rec: Recording,
    *,
    segments: Sequence = (),
    preset: str = "mpu6050",
    n_replicas: int = DEFAULT_REPLICAS,
    seed: int = 0,
    model: TwinModel | None = None,
    alpha: float = ALPHA,
) -> dict:
    """Is the preset's noise a claim the real sensor supports?

    The identified twin of ``rec`` with its noise terms (``arw``, ``bias_instability``,
    ``rrw``) replaced by the preset's values (the datasheet's density, the preset's Allan
    floor), compared with the real recording like the twin itself. Returns
    ``{"preset": …, "terms": {effect: values}, "comparison": Comparison.to_json(), "twin":
    Comparison.to_json(), "real_over_preset_adev_tau0": (3,)}``: the preset's terms sit inside
    the twin's band when the comparison passes.
    """
    from sim.presets import load_preset

    spec = load_preset(preset)
    ref = reference_of(rec, segments)
    if model is None:
        model = identify(rec, ref, segments=segments)
    params = {
        e: dict(p)
        for e, p in model.params.items()
        if e not in ("bias_instability", "rrw", "angle_white") + _WHITE_TERMS
    }
    terms = {}
    for eff in ("arw", "bias_instability", "rrw"):
        if eff in spec.effects:
            params[eff] = spec.draw_effect(eff, 0)
            terms[eff] = {k: np.asarray(v).tolist() for k, v in params[eff].items()}
    pm = replace(model, params=params, extra={}, sources={**model.sources, **{e: f"preset {preset}" for e in terms}})
    layout = layout_for(ref, model.rate_hz, rec.n)
    real = _real_stats(rec, ref, layout, model)
    c_preset = compare(real, replica_statistics(pm, rec, ref, layout, n_replicas=n_replicas, seed=seed), alpha=alpha)
    c_twin = compare(real, replica_statistics(model, rec, ref, layout, n_replicas=n_replicas, seed=seed), alpha=alpha)
    ratio = 10 ** (c_preset.real["adev"][:, 0] - c_preset.median["adev"][:, 0])
    return {
        "preset": preset,
        "terms": terms,
        "comparison": c_preset.to_json(),
        "twin": c_twin.to_json(),
        "real_over_preset_adev_tau0": ratio,
    }


def holdout(
    rec: Recording, *, segments: Sequence = (), n_replicas: int = DEFAULT_REPLICAS, seed: int = 0, alpha: float = ALPHA
) -> dict:
    """The held-out figure: the noise model and the closing terms are identified on the first
    half of the recording and compared with the second half.

    The deterministic terms (bias, ramp, steps, …) are per-session nuisance and are identified
    on the second half itself (the loop); the noise terms (``arw``, ``bias_instability``,
    ``rrw``), the LSB and the closing terms (:attr:`TwinModel.extra` and lines) come from the
    first half only. Returns ``{"before": Comparison.to_json() | None, "after": … | None,
    "added": [...], "error": str | None}`` for the second half.
    """
    n = rec.n
    rec_a, rec_b = rec.slice(0, n // 2), rec.slice(n // 2, n)

    def cut(r: Recording) -> list:
        t0, t1 = float(r.t_s[0]), float(r.t_s[-1])
        out = []
        for s in as_segments(segments):
            if s.kind == "rotation":
                if s.t_start_s >= t0 and s.t_end_s <= t1:
                    out.append(s)
            elif min(s.t_end_s, t1) - max(s.t_start_s, t0) > 0:
                out.append(Segment.still(max(s.t_start_s, t0), min(s.t_end_s, t1), s.label))
        return out

    seg_a, seg_b = cut(rec_a), cut(rec_b)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ra = twin(rec_a, segments=seg_a, n_replicas=n_replicas, seed=seed, alpha=alpha)
            ref_b = reference_of(rec_b, seg_b)
            mb = identify(rec_b, ref_b, segments=seg_b)
    except GyroInputError as exc:
        return {"before": None, "after": None, "added": [], "error": str(exc)}
    noise_keys = set(("bias_instability", "rrw", "quantization", "angle_white") + _WHITE_TERMS)

    def transplant(src: TwinModel) -> TwinModel:
        det = {e: p for e, p in mb.params.items() if e not in noise_keys}
        noise = {e: p for e, p in src.params.items() if e in noise_keys}
        lines = {e: p for e, p in src.params.items() if e.startswith("periodic[") and e not in mb.params}
        return replace(
            mb,
            params={**det, **noise, **lines},
            extra=dict(src.extra),
            sources={**mb.sources, **{e: "first half" for e in noise}},
        )

    layout = layout_for(ref_b, mb.rate_hz, rec_b.n)
    given = transplant(ra.model)
    real = _real_stats(rec_b, ref_b, layout, given)
    det_err = model_error(given, rec_b, ref_b)
    before = compare(
        real,
        replica_statistics(given, rec_b, ref_b, layout, n_replicas=n_replicas, seed=seed + 2, det_err=det_err),
        alpha=alpha,
    )
    after = None
    if ra.model_after is not None:
        after = compare(
            real,
            replica_statistics(
                transplant(ra.model_after), rec_b, ref_b, layout, n_replicas=n_replicas, seed=seed + 3, det_err=det_err
            ),
            alpha=alpha,
        )
    return {
        "before": before.to_json(),
        "after": after.to_json() if after else None,
        "added": list(ra.added),
        "error": None,
        "_before": before,
        "_after": after,
    }
