"""One step of the open search inside the loop: the strongest significant description outside the
catalogue among the regressor library, narrow-band lines (sample level, and window level against
an attitude reference) and a bias step (:mod:`gyrocore.loop.search` holds the tests)."""

from __future__ import annotations


import numpy as np

from gyrocore.effects import registry as E
from gyrocore.attitude import rate_error_vs_attitude
from gyrocore.data.recording import Recording
from gyrocore.calib.stream import Rows, SpilledRecording, rows_of
from . import search as S
from .residual import Residual
from .model import split_axis
from .evidence import cv_min, cv_rms
from .scoring import window_line_series

__all__ = ["line_series", "attitude_line_series", "open_step"]


def line_series(
    res: Residual,
    rec: Recording,
    correction: np.ndarray,
    options: S.AttitudeLineOptions | None = None,
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
    t = rec.t_s
    if isinstance(rec, SpilledRecording):
        # from disk (rate reference, finite everywhere: stream._build_spilled): the residual
        # and the motion columns a window at a time
        if res.kind != "rate":  # pragma: no cover
            return None
        ref, acc = rec.ref_rate_rad_s, rec.accel_m_s2

        def x_rows(a, b):
            return rec.gyro_rad_s.rows(a, b) - ref.rows(a, b) - rows_of(correction, a, b)

        def m_rows(a, b):
            return (
                ref.rows(a, b)
                if acc is None
                else np.concatenate([ref.rows(a, b), np.nan_to_num(acc.rows(a, b))], axis=1)
            )

        return (
            Rows(x_rows, rec.n, 3),
            t,
            rec.rate_hz,
            Rows(m_rows, rec.n, 3 if acc is None else 6),
            "sample",
            slice(0, rec.n),
        )
    if res.kind == "rate":
        ref = rec.ref_rate_rad_s
        ok = np.all(np.isfinite(ref), axis=1)
        a, b = _longest_run(ok)
        sl = slice(a, b)
        x = rec.gyro_rad_s[sl] - ref[sl] - correction[sl]
        mot = [ref[sl]]  # (a line of the rate is a line of its derivative too)
        if rec.accel_m_s2 is not None:
            mot.append(np.nan_to_num(rec.accel_m_s2[sl]))
        return x, t[sl], rec.rate_hz, np.concatenate(mot, axis=1), "sample", sl
    if res.kind == "still":
        a_w, b_w = res.win_start, res.win_stop
        cont = np.concatenate([[False], a_w[1:] == b_w[:-1]])
        best, cur, st, bst = 0, 0, 0, 0
        for k in range(res.m):
            if k > 0 and cont[k]:
                cur += 1
            else:
                cur, st = 1, k
            if cur > best:
                best, bst = cur, st
        sl = slice(int(a_w[bst]) + 1, int(b_w[bst + best - 1]) + 1)
        x = rec.gyro_rad_s[sl] - correction[sl]
        mot = np.nan_to_num(rec.accel_m_s2[sl]) if rec.accel_m_s2 is not None else None
        return x, t[sl], rec.rate_hz, mot, "sample", sl
    if res.kind == "attitude":
        return attitude_line_series(rec, correction, options or S.AttitudeLineOptions(), raw=raw)
    return None


def attitude_line_series(
    rec: Recording,
    correction: np.ndarray,
    options: S.AttitudeLineOptions | None = None,
    raw: tuple[Recording, float] | None = None,
):
    """Sample-level residual against a reference attitude, for the line search.

    The reference is differentiated, ω_ref,k = rotvec(R_{k−1}ᵀR_k)/Δt_k, and the residual is
    e_k = rotvec(ΔR_refᵀ·exp((gyro_k − model_k)·Δt_k))/Δt_k
    (:func:`gyrocore.attitude.rate_error_vs_attitude`) on the samples whose reference is
    valid at both ends of a regular interval; those are cut into equal segments
    (:func:`gyrocore.search.even_segments`) that never straddle a dropout. White attitude
    noise σ_q of the reference becomes rate noise of one-sided PSD 8σ_q²·fs·sin²(πf/fs)
    (∝ f² below fs/4): the F-test's local noise estimate carries it, so the test stays
    valid and only loses power where it dominates the gyro's own noise (docs/loop.md §6).
    Needs the reference on the gyro's rows (a reference sampled more slowly than the gyro,
    NaN between its frames, would alias the gyro's lines above its Nyquist frequency onto
    its grid): None otherwise, and the window-level test alone runs.

    ``raw`` = (the recording before the time-offset advance, τ): the gyro is advanced by τ
    with a band-limited interpolator (:func:`gyrocore.loop.search.band_limited_advance`; the
    cubic spline of ``rec`` is kept only within 16 samples of a gap), whose gain stays 1 up to
    0.4·fs where the spline's falls to 0.875 at fs/3. ``options`` (default
    ``AttitudeLineOptions()``): ``segments``, the target number of segments; ``mask_accel``,
    the specific force among the motion columns (off: only the reference's own lines are
    excluded).

    Returns (x (S·L, 3), t (S·L,), fs, motion columns (S·L, 3 or 6), "sample", sample
    indices, L) or None.
    """
    if isinstance(rec, SpilledRecording) or rec.ref_quat_wxyz is None:
        return None
    options = options or S.AttitudeLineOptions()
    t = rec.t_s
    gyro = rec.gyro_rad_s
    if raw is not None and raw[1] != 0.0 and not isinstance(raw[0], SpilledRecording):
        g_bl = S.band_limited_advance(t, raw[0].gyro_rad_s, raw[1])
        gyro = np.where(np.isfinite(g_bl), g_bl, gyro)
    e, w_ref, valid = rate_error_vs_attitude(t, rec.ref_quat_wxyz, gyro - correction)
    ok_q = np.all(np.isfinite(rec.ref_quat_wxyz), axis=1)
    # the reference must be on (nearly) every gyro row where it is tracked: adjacent valid
    # rows are its own consecutive frames (not every 4th row of a 1-kHz gyro)
    if valid.sum() < 0.5 * ok_q.sum():
        return None
    idx, L = S.even_segments(t, valid, n_target=options.segments)
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
    if isinstance(rec, SpilledRecording) or rec.ref_quat_wxyz is None:
        return "not run: no reference attitude in memory; window level only"
    ok = np.all(np.isfinite(rec.ref_quat_wxyz), axis=1)
    d = np.diff(rec.t_s[ok])
    # the frame rate: mean interval between consecutive frames, tracking losses left out
    f_ref = 1.0 / float(np.mean(d[d <= 1.5 * np.median(d)])) if d.size else 0.0
    if ok.sum() and (ok[1:] & ok[:-1]).sum() < 0.5 * ok.sum():
        return (
            f"not run: the reference attitude is on {ok.mean():.1%} of the gyro's rows ({f_ref:.0f} frames/s beside a "
            f"{rec.rate_hz:.0f}-Hz gyro): differentiated on its own frames it would see the gyro only below its Nyquist "
            f"frequency {f_ref / 2:.0f} Hz, and a gyro line above that aliases onto its grid (a line there cannot be "
            "told from the reference); window level only (below 0.5 Hz)"
        )
    return "not run: the reference attitude has no gap-free run of 512 samples; window level only"


def _longest_run(ok: np.ndarray) -> tuple[int, int]:
    m = np.concatenate([[False], ok, [False]]).astype(np.int8)
    d = np.diff(m)
    a, b = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    if a.size == 0:
        return 0, 0
    j = int(np.argmax(b - a))
    return int(a[j]), int(b[j])


def open_step(
    *,
    res,
    rec,
    model,
    model_effects,
    fit,
    e,
    alpha,
    rms_cur,
    att_cur,
    cv_base,
    open_term_test,
    practical,
    step_screen_now,
    ev_dict,
    untestable,
    held,
    tau_acc,
    can_hold,
    open_last,
    line_options=None,
    raw_rec=None,
):
    """One step of the open search: the strongest significant description among the regressor
    library, lines and a bias step, or None. See :mod:`gyrocore.loop.search`.

    Returns (kind, axis, effect name, fields, evidence, held line (axis, f_hz, a_cos, a_sin) or None).
    """
    options = []  # (log10 p − log10 threshold, payload)
    sig = fit.axis_sigma_rad_s if fit is not None else np.maximum(np.std(e, axis=0), 1e-12)
    X0 = model.design(model_effects)[0]
    n_par = fit.rank if fit is not None else 0
    # ---------------- regressor library
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
    if lib is not None:
        thr = alpha * S.ALPHA_SHARE["regressor"] / lib.n_tested
        open_last["regressor"] = {
            "term": lib.term,
            "axis": "xyz"[lib.axis],
            "score_F": lib.statistic,
            "log10_p": lib.log10_p,
            "threshold": thr,
            "n_tested": lib.n_tested,
        }
        if equiv:
            open_last["regressor"]["collinear_with_simpler"] = equiv
        if lib.p_value < thr:
            name = E.family_name("regressor", lib.term)
            ev, _ = open_term_test(f"{name}@{lib.axis}", thr, cv_base)
            open_last["regressor"].update(
                {"wald_log10_p": ev.log10_p, "cv_rms_reduction": ev.cv_rms_reduction, "rms_reduction": ev.rms_reduction}
            )
            if ev.df1 > 0 and ev.p_value < thr and practical(ev):
                evd = ev_dict(ev)
                evd.update(
                    {
                        "score_F": lib.statistic,
                        "score_log10_p": lib.log10_p,
                        "n_tested": lib.n_tested,
                        "residual": "window",
                    }
                )
                options.append(
                    (ev.log10_p - np.log10(thr), ("regressor", lib.axis, name, {"term": lib.term}, evd, None))
                )
    elif not terms:
        open_last["regressor"] = {"skipped": "no signal varies in the data"}
    # ---------------- lines
    thr_line = alpha * S.ALPHA_SHARE["periodic"] / 3.0
    corr = model.correction(fit, model_effects)
    line_options = line_options or S.AttitudeLineOptions()
    raw = (raw_rec(), tau_acc) if (raw_rec is not None and res.kind == "attitude" and tau_acc != 0.0) else None
    ser = line_series(res, rec, corr, line_options, raw) if can_hold else None
    # against an attitude reference both the sample level (differentiated reference) and the
    # window level (below the sample level's lowest frequency) are searched: half of α each
    both = res.kind == "attitude" and ser is not None and ser[0].shape[0] >= 256
    if res.kind == "attitude" and can_hold and not both:
        open_last["periodic_sample_level"] = _sample_level_not_run(rec)
    thr_sample = thr_line / 2 if both else thr_line
    if ser is not None and ser[0].shape[0] >= 256:
        x, tt, fs, mot, level, _ = ser[:6]
        seg_len = ser[6] if len(ser) > 6 else S.segment_length(x.shape[0])
        # (axis, frequency) already removed
        done = [
            (i, E.resolve(n).arg)
            for n, ls in held.items()
            for i in range(3)
            if any(ax == i and (a_ != 0 or b_ != 0) for ax, _, a_, b_ in ls)
        ]
        if res.kind == "attitude":
            # the segments' start times carry the line's phase across them (coherent statistic)
            lines = S.screen_lines(
                x,
                fs,
                ref=mot,
                skip=done,
                seg_max=seg_len,
                seg_start_s=tt[::seg_len],
                statistics=("pooled", "coherent") if line_options.statistic == "both" else (line_options.statistic,),
                mask_level=line_options.mask_level,
                mask_family_wise=True,
            )
        else:
            lines = S.screen_lines(x, fs, ref=mot, skip=done, seg_max=seg_len)
        open_last["periodic"] = [
            {
                "axis": "xyz"[l.axis],
                "frequency_hz": l.frequency_hz,
                "F": l.statistic,
                "log10_p": l.log10_p,
                "threshold": thr_sample,
                "n_freq": l.n_freq,
                "bandwidth_hz": l.bandwidth_hz,
                "masked_by_motion_bins": l.masked_by_motion,
                "level": "sample",
                "statistic": l.test,
            }
            for l in lines
        ]
        for l in lines:
            if l.log10_p >= np.log10(thr_sample):
                continue
            i = l.axis
            # one axis of the sample-level residual at a time (a recording on disk: read and
            # corrected a window at a time into one (n,) array)
            xi = x.axis(i) if isinstance(x, Rows) else x[:, i]
            # ± one bin of the segment grid (fs/L)
            f = S.round_frequency(S.refine_frequency(xi, tt, l.frequency_hz, l.resolution_hz or fs / seg_len))
            cv = S.sinusoid_cv_reduction(xi, tt, f)
            if not cv > 0:
                continue
            name = E.family_name("periodic", f)
            coef, se = S.fit_sinusoid(xi, tt, f)
            a, b = float(coef[0, 0]), float(coef[1, 0])
            before, after = S.sinusoid_rms(xi, tt, f, a, b)
            del xi
            # raw time frame: the residual is of the gyro advanced by tau (time_offset)
            phi = 2 * np.pi * f * tau_acc
            a_raw, b_raw = a * np.cos(phi) - b * np.sin(phi), a * np.sin(phi) + b * np.cos(phi)
            corr_full = (i, f, a_raw, b_raw)  # stream.held_correction
            evd = {
                "statistic": l.statistic,
                "df1": l.df1,
                "df2": l.df2,
                "log10_p": l.log10_p,
                "p_value": 10**l.log10_p,
                "threshold": thr_sample,
                "n_frequencies_tested": l.n_freq,
                "bandwidth_hz": l.bandwidth_hz,
                "grid_frequency_hz": l.frequency_hz,
                "cv_rms_reduction": cv,
                "residual": level,
                "test": "Thomson multitaper harmonic F (NW 4, K 7)"
                + (", phase-coherent across segments" if l.test == "coherent" else ""),
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
            if res.kind == "attitude":
                evd["segments"] = {"n": int(x.shape[0] // seg_len), "length": int(seg_len)}
            options.append((l.log10_p - np.log10(thr_sample), ("periodic", i, name, fields, evd, corr_full)))
    if res.kind == "attitude" and res.m >= 64:
        thr_line = thr_line / 2 if both else thr_line
        x, tt, fs, idx = window_line_series(res, e)
        if x.shape[0] >= 64:
            mot = res.window_mean(np.asarray(res.inputs.omega_S_rad_s, float))[idx]
            done = [
                (ax, E.resolve(base).arg) for base, ax in map(split_axis, model_effects) if base.startswith("periodic[")
            ]
            lines = S.screen_lines(x, fs, ref=mot, skip=done)
            open_last["periodic"] = open_last.get("periodic", []) if both else []
            open_last["periodic"] += [
                {
                    "axis": "xyz"[l.axis],
                    "frequency_hz": l.frequency_hz,
                    "F": l.statistic,
                    "log10_p": l.log10_p,
                    "threshold": thr_line,
                    "n_freq": l.n_freq,
                    "level": "window",
                }
                for l in lines
            ]
            for l in lines:
                if l.log10_p >= np.log10(thr_line):
                    continue
                f = S.round_frequency(S.refine_frequency(x[:, l.axis], tt, l.frequency_hz, 2 * l.bandwidth_hz))
                name = E.family_name("periodic", f)
                ev, _ = open_term_test(f"{name}@{l.axis}", thr_line, cv_base)
                # the harmonic F decided significance; the window refit must hold out of sample
                if ev.df1 > 0 and (ev.cv_rms_reduction > 0 or not np.isfinite(ev.cv_rms_reduction)):
                    evd = ev_dict(ev)
                    evd.update(
                        {
                            "line_F": l.statistic,
                            "line_log10_p": l.log10_p,
                            "threshold": thr_line,
                            "residual": "window",
                            "n_frequencies_tested": l.n_freq,
                        }
                    )
                    a = ev.params.get(f"a_cos_rad_s[{l.axis}]", 0.0)
                    b = ev.params.get(f"a_sin_rad_s[{l.axis}]", 0.0)
                    options.append(
                        (
                            l.log10_p - np.log10(thr_line),
                            (
                                "periodic",
                                l.axis,
                                name,
                                {"frequency_hz": f, "amplitude_rad_s": float(np.hypot(a, b))},
                                evd,
                                None,
                            ),
                        )
                    )
    # ---------------- step
    thr_step = alpha * S.ALPHA_SHARE["step"]
    st = step_screen_now(thr_step)
    if st is not None:
        open_last["step"] = {
            "t_s": st.t_s,
            "sup_statistic": st.statistic,
            "bootstrap_p": st.p_value,
            "threshold": thr_step,
            "n_boot": st.n_boot,
            "n_candidates": st.n_candidates,
        }
        if st.p_value < thr_step:
            name = E.family_name("step", st.t_s)
            if name not in model_effects:
                ev, _ = open_term_test(name, thr_step, cv_base)
                if ev.df1 > 0 and practical(ev):
                    X0c = model.design(model_effects)[0]
                    cv_step = cv_rms(
                        res.y_rad_s, np.concatenate([X0c, model.block(name)[1]], axis=2), min_windows=cv_min(res)
                    )
                    evd = ev_dict(ev)
                    evd.update(
                        {
                            "sup_statistic": st.statistic,
                            "bootstrap_p": st.p_value,
                            "n_boot": st.n_boot,
                            "n_candidates": st.n_candidates,
                            "threshold_step": thr_step,
                            "residual": "window",
                        }
                    )
                    if "bias_ramp" not in model_effects:
                        cv_ramp = cv_rms(
                            res.y_rad_s,
                            np.concatenate([X0c, model.block("bias_ramp")[1]], axis=2),
                            min_windows=cv_min(res),
                        )
                        evd["vs_ramp"] = {
                            "cv_rms_step_rad_s": cv_step,
                            "cv_rms_ramp_rad_s": cv_ramp,
                            "chosen": "step" if cv_step <= cv_ramp else "ramp",
                        }
                    options.append(
                        (np.log10(st.p_value) - np.log10(thr_step), ("step", 0, name, {"t_s": st.t_s}, evd, None))
                    )
    if not options:
        return None
    options.sort(key=lambda o: o[0])
    return options[0][1]
