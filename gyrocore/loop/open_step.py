"""One step of the open search inside the loop: the strongest significant description outside the
catalogue among the regressor library, narrow-band lines (sample level, and window level against
an attitude reference) and a bias step (:mod:`gyrocore.loop.search` holds the tests)."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from gyrocore.effects import registry as E
from gyrocore.attitude import rate_error_vs_attitude
from gyrocore.data.recording import Recording
from gyrocore.calib.stream import rows_of
from . import lines as LN
from . import search as S
from . import source
from .residual import Residual
from .evidence import cv_rms_with
from .model import Model, split_axis
from .result import Evidence, evidence_dict
from .scoring import longest_chain, window_line_series

__all__ = ["line_series", "attitude_line_series", "open_step"]


def line_series(
    res: Residual,
    rec: Recording,
    correction: np.ndarray,
    options: LN.AttitudeLineOptions | None = None,
    raw: tuple[Recording, float] | None = None,
):
    """The series the line search runs on: (x (n, 3), t (n,), fs, reference motion (n, R) or
    None, level, sample slice or None).

    ``rate``: the sample-level residual gyro − ω_ref − model (longest run with a finite
    reference); ``still``: gyro − model over the longest contiguous run of still windows;
    ``attitude``: the residual against the differentiated reference on equal gap-free
    segments (:func:`attitude_line_series`; ``options``, ``raw`` are passed to it), or None
    when the reference is not on the gyro's rows.
    """
    if res.kind == "rate":
        return _rate_line_series(rec, correction)
    t = rec.t_s
    if res.kind == "still":
        a_w, b_w = res.win_start, res.win_stop
        bst, best = longest_chain(np.concatenate([[False], a_w[1:] == b_w[:-1]]))
        sl = slice(int(a_w[bst]) + 1, int(b_w[bst + best - 1]) + 1)
        x = rec.gyro_rad_s[sl] - correction[sl]
        mot = np.nan_to_num(rec.accel_m_s2[sl]) if rec.accel_m_s2 is not None else None
        return x, t[sl], rec.rate_hz, mot, "sample", sl
    if res.kind == "attitude":
        return attitude_line_series(rec, correction, options or LN.AttitudeLineOptions(), raw=raw)
    return None


def _rate_line_series(rec, correction):
    """``rate``: gyro − ω_ref − model over the longest run with a finite reference, the reference
    rate (a line of the rate is a line of its derivative too) and the specific force as motion
    columns; a window of rows at a time (:mod:`gyrocore.loop.source`: in memory, one window)."""
    src = source.of(rec)
    ref, acc = rec.ref_rate_rad_s, rec.accel_m_s2
    a, b = _longest_run(src.finite_rows(ref))

    def x_rows(lo, hi):
        return rows_of(rec.gyro_rad_s, lo, hi) - rows_of(ref, lo, hi) - rows_of(correction, lo, hi)

    def m_rows(lo, hi):
        mot = [rows_of(ref, lo, hi)]
        if acc is not None:
            mot.append(np.nan_to_num(rows_of(acc, lo, hi)))
        return np.concatenate(mot, axis=1)

    x = src.per_sample(x_rows, 3, a, b)
    mot = src.per_sample(m_rows, 3 if acc is None else 6, a, b)
    return x, rec.t_s[a:b], rec.rate_hz, mot, "sample", slice(a, b)


def attitude_line_series(
    rec: Recording,
    correction: np.ndarray,
    options: LN.AttitudeLineOptions | None = None,
    raw: tuple[Recording, float] | None = None,
):
    """Sample-level residual against a reference attitude, for the line search.

    The reference is differentiated, ω_ref,k = rotvec(R_{k−1}ᵀR_k)/Δt_k, and the residual is
    e_k = rotvec(ΔR_refᵀ·exp((gyro_k − model_k)·Δt_k))/Δt_k
    (:func:`gyrocore.attitude.rate_error_vs_attitude`) on the samples whose reference is
    valid at both ends of a regular interval; those are cut into equal segments
    (:func:`gyrocore.loop.lines.even_segments`) that never straddle a dropout. White attitude
    noise σ_q of the reference becomes rate noise of one-sided PSD 8σ_q²·fs·sin²(πf/fs)
    (∝ f² below fs/4): the F-test's local noise estimate carries it, so the test stays
    valid and only loses power where it dominates the gyro's own noise (docs/loop.md §6).
    A reference sampled more slowly than the gyro (NaN between its frames, or each frame held)
    is first slerped onto the gyro's rows (:func:`gyrocore.loop.lines.reference_on_rows`): the
    residual is then on the gyro's grid, a gyro line above the reference's Nyquist frequency is
    in it and not in the reference, and the reference's images of its own content at multiples
    of its frame rate are its own lines, masked. None without a gap-free run of 512 samples.

    ``raw`` = (the recording before the time-offset advance, τ): the gyro is advanced by τ
    with a band-limited interpolator (:func:`gyrocore.loop.lines.band_limited_advance`; the
    cubic spline of ``rec`` is kept only within 16 samples of a gap), whose gain stays 1 up to
    0.4·fs where the spline's falls to 0.875 at fs/3. ``options`` (default
    ``AttitudeLineOptions()``): ``segments``, the target number of segments; ``mask_accel``,
    the specific force among the motion columns (off: only the reference's own lines are
    excluded). A recording on disk has only the rate reference (:func:`build_residual` refuses
    the others), so this reads a recording in memory.

    Returns (x (S·L, 3), t (S·L,), fs, motion columns (S·L, 3 or 6), "sample", sample
    indices, L) or None.
    """
    if rec.ref_quat_wxyz is None:
        return None
    options = options or LN.AttitudeLineOptions()
    t = rec.t_s
    gyro = rec.gyro_rad_s
    if raw is not None and raw[1] != 0.0:
        g_bl = LN.band_limited_advance(t, raw[0].gyro_rad_s, raw[1])
        gyro = np.where(np.isfinite(g_bl), g_bl, gyro)
    # a reference slower than the gyro (NaN between its frames, or each frame held) is put on
    # every row by slerp between its frames: a gyro line above its Nyquist frequency is then in
    # the residual and not in the reference, and the reference's images of its own content at
    # multiples of its frame rate are lines of the reference, masked below
    q_ref, _ = LN.reference_on_rows(t, rec.ref_quat_wxyz)
    e, w_ref, valid = rate_error_vs_attitude(t, q_ref, gyro - correction)
    ok_q = np.all(np.isfinite(q_ref), axis=1)
    # the reference must be on (nearly) every gyro row where it is tracked: adjacent valid
    # rows are its own consecutive frames (not every 4th row of a 1-kHz gyro)
    if valid.sum() < 0.5 * ok_q.sum():
        return None
    idx, L = LN.even_segments(t, valid, n_target=options.segments)
    if idx.size == 0:
        return None
    tt = t[idx]
    fs = 1.0 / float(np.median(np.diff(t)[idx[1:] - 1]))
    mot = [w_ref[idx]]
    if options.mask_accel and rec.accel_m_s2 is not None:
        mot.append(np.nan_to_num(rec.accel_m_s2[idx]))
    return e[idx], tt, fs, np.concatenate(mot, axis=1), "sample", idx, L


def _sample_level_not_run(rec: Recording) -> str:
    """Why the sample-level line test did not run against a reference attitude (JSON note)."""
    if source.of(rec).on_disk or rec.ref_quat_wxyz is None:
        return "not run: no reference attitude in memory; window level only"
    return (
        "not run: the reference attitude (a slower one slerped onto the gyro's rows between its frames) has no "
        "gap-free run of 512 samples; window level only"
    )


def _longest_run(ok: np.ndarray) -> tuple[int, int]:
    m = np.concatenate([[False], ok, [False]]).astype(np.int8)
    d = np.diff(m)
    a, b = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    if a.size == 0:
        return 0, 0
    j = int(np.argmax(b - a))
    return int(a[j]), int(b[j])


class LoopState(Protocol):
    """What an open step reads of the loop between steps (``gyrocore.loop.loop._LoopRun``)."""

    res: Residual
    rec: Recording
    model: Model
    model_effects: list[str]
    fit: object  # gyrocore.calib.lsq's fit of model_effects, or None without effects
    e: np.ndarray  # window residual of that fit, (M, 3) rad/s
    alpha: float
    tau_acc: float  # time offset the gyro is advanced by, s
    held: dict  # sample-level lines removed from the gyro: name -> [(axis, f_hz, a_cos, a_sin), ...]
    open_last: dict  # what the open search tested last (written here)
    can_hold: bool  # whether the residual can be rebuilt (sample-level lines can be removed)
    line_options: LN.AttitudeLineOptions  # the sample-level line test against a reference attitude

    def base_rec(self) -> Recording: ...

    def open_term_test(self, name: str, thr: float, cv_base: float) -> tuple[Evidence, object]: ...

    def practical(self, ev: Evidence) -> bool: ...

    def step_screen_now(self, thr_step: float): ...


def open_step(run: LoopState, cv_base: float):
    """One step of the open search: the strongest significant description among the regressor
    library, lines and a bias step, or None. See :mod:`gyrocore.loop.search`.

    ``cv_base`` is the current model's out-of-sample RMS (:func:`gyrocore.loop.evidence.cv_rms`);
    what each kind tested is left in ``run.open_last``.

    Returns (kind, axis, effect name, fields, evidence, held line (axis, f_hz, a_cos, a_sin) or None).
    """
    # each option: (log10 p − log10 threshold, payload); the strongest against its own threshold wins
    options = _regressor_options(run, cv_base) + _line_options(run, cv_base) + _step_options(run, cv_base)
    if not options:
        return None
    options.sort(key=lambda o: o[0])
    return options[0][1]


def _regressor_options(run: LoopState, cv_base: float) -> list:
    """The regressor library: the strongest product term on one axis, refitted with the model."""
    res, fit, e, model_effects = run.res, run.fit, run.e, run.model_effects
    sig = fit.axis_sigma_rad_s if fit is not None else np.maximum(np.std(e, axis=0), 1e-12)
    X0 = run.model.design(model_effects)[0]
    n_par = fit.rank if fit is not None else 0
    terms = S.library_terms(res.inputs, kind=res.kind, chunks=(res.iter_inputs(context=1) if res.chunked() else None))
    exclude = set()
    for term in terms:
        for i in range(3):
            eq = E.catalogue_equivalent(term, i)
            if eq is not None or f"regressor[{term}]@{i}" in model_effects:
                exclude.add((term, i))
    Xlib = S.library_windows(res, terms) if terms else None
    # a product that is numerically one of its factors on this recording (f_x*t in a still
    # log is a ramp t) is that factor: screened under the factor's own name, or, when the
    # factor is a catalogue term, already tested (and kept or refused) as that effect
    equiv = {}
    if terms:
        for (term, i), simple in S.collinear_simpler(res, X0, sig, terms, Xlib).items():
            if (term, i) in exclude:
                continue
            exclude.add((term, i))
            cat = E.catalogue_equivalent(simple, i)
            equiv[f"{term}@{'xyz'[i]}"] = (
                f"{cat} (tested in the catalogue step)" if cat is not None else f"regressor[{simple}]"
            )
    lib = S.screen_library(res, X0, e, sig, terms, exclude, n_par, Xlib) if terms else None
    if lib is None:
        if not terms:
            run.open_last["regressor"] = {"skipped": "no signal varies in the data"}
        return []
    thr = run.alpha * S.ALPHA_SHARE["regressor"] / lib.n_tested
    run.open_last["regressor"] = {
        "term": lib.term,
        "axis": "xyz"[lib.axis],
        "score_F": lib.statistic,
        "log10_p": lib.log10_p,
        "threshold": thr,
        "n_tested": lib.n_tested,
    }
    if equiv:
        run.open_last["regressor"]["collinear_with_simpler"] = equiv
    if not lib.p_value < thr:
        return []
    name = E.family_name("regressor", lib.term)
    ev, _ = run.open_term_test(f"{name}@{lib.axis}", thr, cv_base)
    run.open_last["regressor"].update(
        {"wald_log10_p": ev.log10_p, "cv_rms_reduction": ev.cv_rms_reduction, "rms_reduction": ev.rms_reduction}
    )
    if not (ev.df1 > 0 and ev.p_value < thr and run.practical(ev)):
        return []
    evd = evidence_dict(ev)
    evd.update({"score_F": lib.statistic, "score_log10_p": lib.log10_p, "n_tested": lib.n_tested, "residual": "window"})
    return [(ev.log10_p - np.log10(thr), ("regressor", lib.axis, name, {"term": lib.term}, evd, None))]


def _line_options(run: LoopState, cv_base: float) -> list:
    """Narrow-band lines: on the sample-level residual where there is one, and against an
    attitude reference also on the window residual (below the sample level's lowest frequency)."""
    res = run.res
    thr_line = run.alpha * S.ALPHA_SHARE["periodic"] / 3.0
    corr = run.model.correction(run.fit, run.model_effects)
    # against an attitude reference the gyro is advanced by a band-limited interpolator from the
    # recording before the time-offset advance
    raw = (run.base_rec(), run.tau_acc) if (res.kind == "attitude" and run.tau_acc != 0.0) else None
    ser = line_series(res, run.rec, corr, run.line_options, raw) if run.can_hold else None
    # against an attitude reference both levels are searched: half of α each
    both = res.kind == "attitude" and ser is not None and ser[0].shape[0] >= 256
    if res.kind == "attitude" and run.can_hold and not both:
        run.open_last["periodic_sample_level"] = _sample_level_not_run(run.rec)
    thr_level = thr_line / 2 if both else thr_line
    options = []
    if ser is not None and ser[0].shape[0] >= 256:
        options += _sample_line_options(run, ser, thr_level)
    if res.kind == "attitude" and res.m >= 64:
        options += _window_line_options(run, cv_base, thr_level, both)
    return options


def _line_row(line, threshold: float, level: str) -> dict:
    """What the open search reports of one screened line (``open_search["periodic"]``)."""
    row = {
        "axis": "xyz"[line.axis],
        "frequency_hz": line.frequency_hz,
        "F": line.statistic,
        "log10_p": line.log10_p,
        "threshold": threshold,
        "n_freq": line.n_freq,
    }
    if level == "sample":
        row.update(bandwidth_hz=line.bandwidth_hz, masked_by_motion_bins=line.masked_by_motion)
    row["level"] = level
    if level == "sample":
        row["statistic"] = line.test
    return row


def _sample_line_options(run: LoopState, ser: tuple, thr: float) -> list:
    """Lines of the sample-level residual ``ser`` (:func:`line_series`), each fitted as a sinusoid
    to be removed from the gyro (raw time frame)."""
    x, tt, fs, mot, level, _ = ser[:6]
    seg_len = ser[6] if len(ser) > 6 else LN.segment_length(x.shape[0])
    # (axis, frequency) already removed
    done = [
        (i, E.resolve(n).arg)
        for n, ls in run.held.items()
        for i in range(3)
        if any(ax == i and (a_ != 0 or b_ != 0) for ax, _, a_, b_ in ls)
    ]
    if run.res.kind == "attitude":
        # the segments' start times carry the line's phase across them (coherent statistic)
        opts = run.line_options
        lines = LN.screen_lines(
            x,
            fs,
            ref=mot,
            skip=done,
            seg_max=seg_len,
            seg_start_s=tt[::seg_len],
            statistics=("pooled", "coherent") if opts.statistic == "both" else (opts.statistic,),
            mask_level=opts.mask_level,
            mask_family_wise=True,
        )
    else:
        lines = LN.screen_lines(x, fs, ref=mot, skip=done, seg_max=seg_len)
    run.open_last["periodic"] = [_line_row(line, thr, "sample") for line in lines]
    options = []
    for line in lines:
        if line.log10_p >= np.log10(thr):
            continue
        opt = _sample_line_option(line, x, tt, fs, seg_len, thr, level, run.tau_acc, run.res.kind == "attitude")
        if opt is not None:
            options.append(opt)
    return options


def _sample_line_option(line, x, tt, fs, seg_len, thr, level, tau_acc, attitude):
    """One significant sample-level line refined, checked out of sample and fitted: its option, or
    None when the fit does not predict the held-out part."""
    i = line.axis
    # one axis of the sample-level residual at a time (a recording on disk: read and corrected a
    # window at a time into one (n,) array)
    xi = source.column(x, i)
    # ± one bin of the segment grid (fs/L)
    f = S.round_frequency(LN.refine_frequency(xi, tt, line.frequency_hz, line.resolution_hz or fs / seg_len))
    cv = LN.sinusoid_cv_reduction(xi, tt, f)
    if not cv > 0:
        return None
    name = E.family_name("periodic", f)
    coef, se = LN.fit_sinusoid(xi, tt, f)
    a, b = float(coef[0, 0]), float(coef[1, 0])
    before, after = LN.sinusoid_rms(xi, tt, f, a, b)
    # raw time frame: the residual is of the gyro advanced by tau (time_offset)
    phi = 2 * np.pi * f * tau_acc
    a_raw, b_raw = a * np.cos(phi) - b * np.sin(phi), a * np.sin(phi) + b * np.cos(phi)
    corr_full = (i, f, a_raw, b_raw)  # stream.held_correction
    evd = {
        "statistic": line.statistic,
        "df1": line.df1,
        "df2": line.df2,
        "log10_p": line.log10_p,
        "p_value": 10**line.log10_p,
        "threshold": thr,
        "n_frequencies_tested": line.n_freq,
        "bandwidth_hz": line.bandwidth_hz,
        "grid_frequency_hz": line.frequency_hz,
        "cv_rms_reduction": cv,
        "residual": level,
        "test": "Thomson multitaper harmonic F (NW 4, K 7)"
        + (", phase-coherent across segments" if line.test == "coherent" else ""),
        "params": {f"a_cos_rad_s[{i}]": a_raw, f"a_sin_rad_s[{i}]": b_raw},
        "std_errors": {f"a_cos_rad_s[{i}]": float(se[0, 0]), f"a_sin_rad_s[{i}]": float(se[1, 0])},
        "_sample_rms_before": before,
        "_sample_rms_after": after,
        "_params": {
            f"a_cos_rad_s[{i}]": (a_raw, float(se[0, 0])),
            f"a_sin_rad_s[{i}]": (b_raw, float(se[1, 0])),
        },
    }
    fields = {"frequency_hz": f, "amplitude_rad_s": float(np.hypot(a, b))}
    if attitude:
        evd["segments"] = {"n": int(x.shape[0] // seg_len), "length": int(seg_len)}
    return (line.log10_p - np.log10(thr), ("periodic", i, name, fields, evd, corr_full))


def _window_line_options(run: LoopState, cv_base: float, thr: float, both: bool) -> list:
    """Lines of the window residual (attitude reference), each refitted with the model as a
    ``periodic[f]`` term on its axis."""
    res = run.res
    x, tt, fs, idx = window_line_series(res, run.e)
    if x.shape[0] < 64:
        return []
    mot = res.window_mean(np.asarray(res.inputs.omega_S_rad_s, float))[idx]
    done = [
        (ax, E.resolve(base).arg) for base, ax in map(split_axis, run.model_effects) if base.startswith("periodic[")
    ]
    lines = LN.screen_lines(x, fs, ref=mot, skip=done)
    run.open_last["periodic"] = (run.open_last.get("periodic", []) if both else []) + [
        _line_row(line, thr, "window") for line in lines
    ]
    options = []
    for line in lines:
        if line.log10_p >= np.log10(thr):
            continue
        f = S.round_frequency(LN.refine_frequency(x[:, line.axis], tt, line.frequency_hz, 2 * line.bandwidth_hz))
        name = E.family_name("periodic", f)
        ev, _ = run.open_term_test(f"{name}@{line.axis}", thr, cv_base)
        # the harmonic F decided significance; the window refit must hold out of sample
        if not (ev.df1 > 0 and (ev.cv_rms_reduction > 0 or not np.isfinite(ev.cv_rms_reduction))):
            continue
        evd = evidence_dict(ev)
        evd.update(
            {
                "line_F": line.statistic,
                "line_log10_p": line.log10_p,
                "threshold": thr,
                "residual": "window",
                "n_frequencies_tested": line.n_freq,
            }
        )
        a = ev.params.get(f"a_cos_rad_s[{line.axis}]", 0.0)
        b = ev.params.get(f"a_sin_rad_s[{line.axis}]", 0.0)
        fields = {"frequency_hz": f, "amplitude_rad_s": float(np.hypot(a, b))}
        options.append((line.log10_p - np.log10(thr), ("periodic", line.axis, name, fields, evd, None)))
    return options


def _step_options(run: LoopState, cv_base: float) -> list:
    """A bias step (sup-F scan with a parametric bootstrap), refitted with the model and compared
    out of sample with a ramp."""
    thr_step = run.alpha * S.ALPHA_SHARE["step"]
    st = run.step_screen_now(thr_step)
    if st is None:
        return []
    run.open_last["step"] = {
        "t_s": st.t_s,
        "sup_statistic": st.statistic,
        "bootstrap_p": st.p_value,
        "threshold": thr_step,
        "n_boot": st.n_boot,
        "n_candidates": st.n_candidates,
    }
    if not st.p_value < thr_step:
        return []
    name = E.family_name("step", st.t_s)
    if name in run.model_effects:
        return []
    ev, _ = run.open_term_test(name, thr_step, cv_base)
    if not (ev.df1 > 0 and run.practical(ev)):
        return []
    cv_step = cv_rms_with(run.model, run.model_effects, name)
    evd = evidence_dict(ev)
    evd.update(
        {
            **st.evidence(),
            "threshold_step": thr_step,
            "residual": "window",
        }
    )
    if "bias_ramp" not in run.model_effects:
        cv_ramp = cv_rms_with(run.model, run.model_effects, "bias_ramp")
        evd["vs_ramp"] = {
            "cv_rms_step_rad_s": cv_step,
            "cv_rms_ramp_rad_s": cv_ramp,
            "chosen": "step" if cv_step <= cv_ramp else "ramp",
        }
    return [(np.log10(st.p_value) - np.log10(thr_step), ("step", 0, name, {"t_s": st.t_s}, evd, None))]
