"""The residual loop: find what the model still leaves, name the effect, add it, refit.

Start from the declared effects, fit them jointly to the residual of
:mod:`gyrocore.loop.residual` (whatever reference the data offer), then repeat:

1. **Trace.** For every catalogue effect not yet in the model (each through its physical
   regressors from :func:`gyrocore.effects.registry.design`, integrated over the observation windows),
   refit the model plus that candidate jointly (:func:`gyrocore.calib.lsq.solve`) and test
   "candidate parameters = 0" with a Wald statistic on a **HAC** covariance — ``lsq``'s
   ``"hac"``: the sandwich with each axis' residual autocovariance (short-lag sample values
   plus a fitted Gauss–Markov tail), so that coloured residuals (on-chip low-pass, bias
   instability, rate random walk, an optical reference's noise) do not pass for a signal —
   referred to F(q, M − P) (q candidate parameters, M windows, P fitted parameters) — and,
   as a second test that must reject too, with the covariance implied by a white + random-walk
   noise model identified on the residual's Allan variance (:func:`gyrocore.loop.evidence._model_wald`): the HAC's
   slow component is added only when significant, and slowly varying regressors (time, a
   warm-up temperature) then pass Gauss–Markov / random-walk wander for a signal. With a
   known-angle reference the fit is weighted by the known uncertainties (OLS covariance).
2. **Select with false-discovery control.** Forward selection with Holm-type step-down
   thresholds: at a step with K testable candidates the smallest p-value must be below α/K
   (Holm 1979), so the family-wise error over candidates and steps stays ≤ α. The winner must
   also be of practical size: it must cut the window residual RMS by ``min_rms_reduction`` or
   the attitude error by ``min_attitude_reduction``, and it must hold *out of sample*: the
   model plus the candidate, refitted on every other tenth of the recording, must predict the
   remaining tenths better than the model alone, and vice versa (2-fold blocked; in-sample
   with fewer than 40 windows or a known-angle reference). Where a fold cannot identify the
   joint model (a rate table turning one axis and one sense at a time) the candidate's own
   columns, fitted to the current residual, must predict it instead. It must also predict
   across the two contiguous halves (fitted on one, scored on the other; no verdict where a
   half cannot identify it). This guards against HAC's optimism on short, strongly coloured
   residuals: a ramp fitted to one stretch of wander does not predict the next.
3. **Collinearity.** Every other candidate that also passes is tested again in the presence of
   the winner and vice versa; if neither adds anything once the other is in (e.g.
   ``bias_ramp`` vs ``bias_thermal`` when the temperature rises linearly in time) the step
   reports them as *ambiguous* (``evidence["ambiguous_with"]``); the winner stays the one
   with the strongest evidence (smallest p-value, which accounts for the number of
   parameters) unless another is within one decade of p, in which case the simpler effect is
   taken (fewer parameters, then the lower-order, more common one: earlier in
   :data:`gyrocore.loop.model.CANDIDATES`). A candidate contained in the winner that explains the same residual
   replaces it (parsimony). A thermal candidate is tested on top of its constant companion
   (:data:`gyrocore.loop.model.COMPANION`) and added with it.
4. **Add and refit** everything jointly, record the error before and after (windowed residual
   RMS, attitude error), and repeat until nothing significant is left. ``time_offset`` is
   re-linearised (Gauss–Newton): the gyro is advanced by the estimate (cubic spline) and the
   residual rebuilt, until the correction is below 1 µs — the first-order regressor −τ·dω/dt
   leaves a second-order term τ²/2·d²ω/dt² that fast motion would otherwise pass to scale-like
   candidates.

What remains is described by a Ljung–Box whiteness test, a Welch spectrum and the Allan
deviation of the final window residual (:class:`Remaining`).

The attitude error is always in-sample (the parameters are fitted on the same recording);
it is the integrated corrected gyro against the reference attitude (``rate``/``attitude``),
the integrated angle inside still segments (``still``), or the per-segment angle error
(``angles``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from gyrocore.effects import registry as E
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording
from gyrocore.calib.stream import SpilledRecording, held_correction
from gyrocore.data.segments import Segment
from . import search as S
from .residual import Residual, build_residual
from .search import Unexplained
from .result import Evidence, LoopResult, Step
from .model import CANDIDATES, Model, advance, fittable, input_check, params_table, with_companion
from .evidence import candidate_test, cv_min, cv_rms, rms
from .scoring import attitude_error_deg, describe_remaining
from .open_step import open_step

__all__ = ["run_loop", "loop_residual"]


def _single_thread():
    """Limit BLAS to one thread: the fits are small (≤ 1500 windows × 40 columns), and on a
    loaded machine threaded BLAS is up to 50× slower than one thread."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional
        import contextlib

        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


_MIN_ATTITUDE_DEG = 1e-3
_TAU_ITERATIONS = 4
_TAU_TOL_S = 1e-6


def loop_residual(
    res: Residual,
    rec: Recording,
    *,
    declared: Sequence[str],
    candidates: Sequence[str] | None = None,
    alpha: float = 0.01,
    thermal_order: int = 1,
    min_rms_reduction: float = 0.005,
    min_attitude_reduction: float = 0.05,
    max_steps: int = 8,
    rebuild=None,
    open_search: bool = True,
    max_open_steps: int = 8,
    seed: int = 0,
    attitude_lines: S.AttitudeLineOptions | None = None,
) -> LoopResult:
    """Run the loop on a prepared :class:`~gyrocore.loop.residual.Residual` (see :func:`run_loop`).

    ``rebuild(recording) -> Residual`` (optional) rebuilds the residual from a recording; it
    enables the Gauss–Newton refinement of ``time_offset`` and the sample-level removal of
    narrow-band lines (see :func:`run_loop`).
    """
    declared = E.check_effect_names(declared)
    notes = list(res.notes)
    ignored = [d for d in declared if not fittable(d)]
    if ignored:
        notes.append(f"declared effects without linear regressors are not fitted: {', '.join(ignored)}")
    model_effects = [d for d in declared if fittable(d)]
    if candidates is None:
        cand_all = [c for c in CANDIDATES if c not in declared]
    else:
        cand_all = [c for c in E.check_effect_names(candidates) if c not in declared]
        bad = [c for c in cand_all if c not in CANDIDATES]
        if bad:
            raise GyroInputError(f"the loop cannot trace {', '.join(bad)} (no linear regressors)")
    orders = {"bias_thermal": thermal_order, "scale_thermal": thermal_order}
    model = Model(res, orders)
    untestable: dict[str, str] = {}
    for c in list(cand_all) + list(model_effects):
        why = input_check(res, c)
        if why is None:
            try:
                model.block(c)
            except GyroInputError as exc:
                why = str(exc)
        if why is not None:
            if c in model_effects:
                raise GyroInputError(f"declared effect {c} cannot be fitted here: {why}")
            untestable[c] = why
    cands = [c for c in cand_all if c not in untestable]
    do_open = bool(open_search) and res.kind != "angles"
    if open_search and not do_open:
        notes.append(
            "open search not run: a known-angle reference has a few rotation windows, too few to "
            "describe effects outside the catalogue"
        )
    # family-wise error: a weighted Bonferroni/Holm split of alpha between the catalogue and the
    # three open-search kinds (search.ALPHA_SHARE); without the open search the catalogue has all of it
    alpha_cat = alpha * (S.ALPHA_SHARE["catalogue"] if do_open else 1.0)
    rng = np.random.default_rng(seed)

    rec0 = rec
    tau_acc = 0.0
    # sample-level line terms removed from the gyro (raw time frame): name -> [(axis, f_hz,
    # a_cos, a_sin), ...]; the correction is stream.held_correction (on the fly for a spill)
    held: dict[str, list] = {}
    held_params: dict[str, dict] = {}

    def base_rec():
        if not held:
            return rec0
        if isinstance(rec0, SpilledRecording):
            return rec0.with_ops(held=held, tau_s=0.0)
        from dataclasses import replace

        return replace(rec0, gyro_rad_s=rec0.gyro_rad_s - held_correction(rec0.t_s, held))

    def refit(res, model, rec, tau_acc, force_rebuild=False):
        """Joint fit; with time_offset in the model, re-linearise around its estimate."""
        if force_rebuild:
            rb = base_rec()
            rec = advance(rb, tau_acc) if tau_acc != 0.0 else rb
            res = rebuild(rec)
            model = Model(res, orders)
        fit, e = model.fit(model_effects)
        if rebuild is None or "time_offset" not in model_effects or res.kind not in ("rate", "attitude"):
            return res, model, rec, tau_acc, fit, e
        for _ in range(_TAU_ITERATIONS):
            d = float(fit.effect_theta("time_offset")[0])
            if not np.isfinite(d) or abs(d) < _TAU_TOL_S:
                break
            tau_acc += d
            rec = advance(base_rec(), tau_acc)
            res = rebuild(rec)
            model = Model(res, orders)
            fit, e = model.fit(model_effects)
        return res, model, rec, tau_acc, fit, e

    res, model, rec, tau_acc, fit, e = refit(res, model, rec, tau_acc)
    history = [e]
    rms0 = rms(e)
    att0 = attitude_error_deg(res, rec, model.correction(fit, model_effects))
    rms_cur, att_cur = rms0, att0
    steps: list[Step] = []
    unexplained: list[Unexplained] = []
    last_tests: dict[str, Evidence] = {}
    open_last: dict = {}
    n_cat = 0

    def practical(ev: Evidence) -> bool:
        # out of sample (2-fold blocked): an effect fitted to coloured noise does not
        # predict the other folds; and of a size that matters, in the residual or in the
        # attitude
        size = ev.rms_reduction >= min_rms_reduction or (
            np.isfinite(ev.attitude_reduction) and ev.attitude_reduction >= min_attitude_reduction
        )
        held_ = ev.cv_rms_reduction > 0 or not np.isfinite(ev.cv_rms_reduction)
        if res.kind == "angles" and np.isfinite(ev.attitude_reduction):
            # the known angles are the reference: an effect that makes them worse by more
            # than a quarter of their uncertainty is refuted
            worse_deg = -ev.attitude_reduction * att_cur
            held_ = held_ and worse_deg <= 0.25 * np.degrees(res.angle_sigma_rad)
        return held_ and size

    def with_attitude(ev: Evidence, f, added: list[str]) -> Evidence:
        att = attitude_error_deg(res, rec, model.correction(f, model_effects + added))
        att_red = 1.0 - att / att_cur if att_cur > _MIN_ATTITUDE_DEG else float("nan")
        return Evidence(**{**ev.__dict__, "attitude_reduction": att_red})

    def open_term_test(name: str, thr: float, cv_base: float):
        """Full joint refit + HAC Wald test of an open term (as a catalogue candidate)."""
        ev, f = candidate_test(model, model_effects, name, thr, rms_cur, e, cv_base)
        if ev.df1 > 0 and ev.p_value < thr:
            ev = with_attitude(ev, f, [name])
        return ev, f

    def step_screen_now(thr_step: float):
        X0 = model.design(model_effects)[0]
        sig = fit.axis_sigma_rad_s if fit is not None else np.maximum(np.std(e, axis=0), 1e-12)
        return S.screen_step(res, X0, e, sig, threshold=thr_step, rng=rng)

    def add_open(
        kind: str,
        axis: int,
        name: str,
        fields: dict,
        evidence: dict,
        before: float,
        after: float,
        att_b: float,
        att_a: float,
    ) -> None:
        unexplained.append(
            Unexplained(
                kind=kind,
                axis="xyz"[axis],
                effect=name,
                fields=fields,
                evidence=evidence,
                residual_rms_before_rad_s=before,
                residual_rms_after_rad_s=after,
                attitude_error_before_deg=att_b,
                attitude_error_after_deg=att_a,
            )
        )

    def ev_dict(ev: Evidence) -> dict:
        return {
            "statistic": ev.statistic,
            "df1": ev.df1,
            "df2": ev.df2,
            "p_value": ev.p_value,
            "log10_p": ev.log10_p,
            "threshold": ev.threshold,
            "cv_rms_reduction": ev.cv_rms_reduction,
            "rms_reduction": ev.rms_reduction,
            "attitude_reduction": ev.attitude_reduction,
            "params": ev.params,
            "std_errors": ev.std_errors,
            "hac_log10_p": ev.hac_log10_p,
            "model_log10_p": ev.model_log10_p,
        }

    for _ in range(max_steps + max_open_steps):
        remaining = [c for c in cands if c not in model_effects]
        cv_base = cv_rms(res.y_rad_s, model.design(model_effects)[0], min_windows=cv_min(res))
        sig: list[str] = []
        evs: dict[str, Evidence] = {}
        if remaining and n_cat < max_steps:
            trial = {c: candidate_test(model, model_effects, c, 0.0, rms_cur, e, cv_base) for c in remaining}
            testable = [c for c in remaining if trial[c][0].df1 > 0]
            for c in remaining:
                if c not in testable:
                    untestable[c] = "not observable given the model: " + ", ".join(trial[c][0].unobservable)
            if testable:
                thr = alpha_cat / len(testable)
                for c in testable:
                    ev, f = trial[c]
                    ev = Evidence(**{**ev.__dict__, "threshold": thr})
                    if ev.p_value < thr:
                        ev = with_attitude(ev, f, with_companion(model_effects, c))
                    evs[c] = ev
                sig = [c for c in testable if evs[c].p_value < thr and practical(evs[c])]
                last_tests = evs
        if sig:
            sig.sort(key=lambda c: (evs[c].log10_p, -evs[c].statistic))
            best = sig[0]
            ambiguous, nested = [], []
            thr = evs[best].threshold
            for r in sig[1:]:
                ev_b, _ = candidate_test(model, model_effects + with_companion(model_effects, r), best, thr, rms_cur)
                ev_r, _ = candidate_test(model, model_effects + with_companion(model_effects, best), r, thr, rms_cur)
                if ev_r.df1 == 0 and ev_b.df1 > 0 and not ev_b.significant:
                    nested.append(r)  # r is contained in best and best adds nothing to it
                elif not ev_b.significant and not ev_r.significant:
                    ambiguous.append(r)
            if nested:  # parsimony: the smaller effect that explains the same residual
                best = min(nested, key=lambda c: (evs[c].log10_p, -evs[c].statistic))
                ambiguous = [c for c in ambiguous if c != best]
            if ambiguous:
                # evidence decides when it differs by ≥ 1 decade of p; otherwise (a tie the data
                # cannot break) the simpler effect: fewer parameters, then the lower-order, more
                # common one (earlier in CANDIDATES)
                pool = [best] + ambiguous
                close = [c for c in pool if evs[c].log10_p <= evs[best].log10_p + 1.0]
                pick = min(close, key=lambda c: (evs[c].df1, CANDIDATES.index(c)))
                ambiguous = [c for c in pool if c != pick]
                best = pick
            if best == "bias_ramp" and do_open:
                # step vs ramp: a bias step also correlates with time; model comparison decides
                thr_step = alpha * S.ALPHA_SHARE["step"]
                st = step_screen_now(thr_step)
                if st is not None and st.p_value < thr_step:
                    name = E.family_name("step", st.t_s)
                    ev_s, f_s = open_term_test(name, thr_step, cv_base)
                    X0 = model.design(model_effects)[0]
                    cv_step = cv_rms(
                        res.y_rad_s, np.concatenate([X0, model.block(name)[1]], axis=2), min_windows=cv_min(res)
                    )
                    cv_ramp = cv_rms(
                        res.y_rad_s, np.concatenate([X0, model.block("bias_ramp")[1]], axis=2), min_windows=cv_min(res)
                    )
                    if cv_step < cv_ramp and ev_s.df1 > 0 and practical(ev_s):
                        model_effects.append(name)
                        res, model, rec, tau_acc, fit, e = refit(res, model, rec, tau_acc)
                        rms_new = rms(e)
                        att_new = attitude_error_deg(res, rec, model.correction(fit, model_effects))
                        size = np.array([fit.effect_theta(name)[i] for i in range(3)])
                        se = np.array([fit.effect_stderr(name)[i] for i in range(3)])
                        ax = int(np.argmax(np.abs(size) / np.where(se > 0, se, np.inf)))
                        evd = ev_dict(ev_s)
                        evd.update(
                            {
                                "sup_statistic": st.statistic,
                                "bootstrap_p": st.p_value,
                                "n_boot": st.n_boot,
                                "n_candidates": st.n_candidates,
                                "log10_p_step": st.log10_p,
                                "threshold_step": thr_step,
                                "vs_ramp": {
                                    "cv_rms_step_rad_s": cv_step,
                                    "cv_rms_ramp_rad_s": cv_ramp,
                                    "chosen": "step",
                                },
                                "size_std_errors_rad_s": se,
                            }
                        )
                        add_open(
                            "step",
                            ax,
                            name,
                            {"t_s": st.t_s, "size_rad_s": size},
                            evd,
                            rms_cur,
                            rms_new,
                            att_cur,
                            att_new,
                        )
                        notes.append(
                            f"a bias step at t = {st.t_s:.6g} s explains the residual better than "
                            f"bias_ramp (out-of-sample RMS {cv_step:.3g} vs {cv_ramp:.3g} rad/s)"
                        )
                        history.append(e)
                        rms_cur, att_cur = rms_new, att_new
                        last_tests = {}
                        continue
            # `best` has the strongest evidence (smallest p-value, which accounts for its number
            # of parameters); the ambiguous ones are reported with it.
            model_effects.extend(with_companion(model_effects, best))
            res, model, rec, tau_acc, fit, e = refit(res, model, rec, tau_acc)
            history.append(e)
            rms_new = rms(e)
            att_new = attitude_error_deg(res, rec, model.correction(fit, model_effects))
            evb = evs[best]
            steps.append(
                Step(
                    effect=best,
                    evidence=Evidence(**{**evb.__dict__, "ambiguous_with": tuple(ambiguous)}),
                    residual_rms_before_rad_s=rms_cur,
                    residual_rms_after_rad_s=rms_new,
                    attitude_error_before_deg=att_cur,
                    attitude_error_after_deg=att_new,
                )
            )
            n_cat += 1
            last_tests = {}
            rms_cur, att_cur = rms_new, att_new
            continue
        # ------------------------------------------------------------ open search
        if not do_open or len(unexplained) >= max_open_steps:
            break
        took = open_step(
            res=res,
            rec=rec,
            model=model,
            model_effects=model_effects,
            fit=fit,
            e=e,
            alpha=alpha,
            rms_cur=rms_cur,
            att_cur=att_cur,
            cv_base=cv_base,
            open_term_test=open_term_test,
            practical=practical,
            step_screen_now=step_screen_now,
            ev_dict=ev_dict,
            untestable=untestable,
            held=held,
            tau_acc=tau_acc,
            can_hold=rebuild is not None,
            open_last=open_last,
            line_options=attitude_lines or S.AttitudeLineOptions(),
            raw_rec=base_rec,
        )
        if took is None:
            break
        kind, axis, name, fields, evd, held_corr = took
        if held_corr is not None:
            # a sample-level line: removed from the gyro (raw time frame), residual rebuilt
            x_before = evd.pop("_sample_rms_before")
            held.setdefault(name, []).append(held_corr)
            hp = held_params.setdefault(name, {})
            for k_, v_ in evd.pop("_params").items():
                hp[k_] = v_
            res, model, rec, tau_acc, fit, e = refit(res, model, rec, tau_acc, force_rebuild=True)
            x_after = evd.pop("_sample_rms_after")
            rms_new = rms(e)
            att_new = attitude_error_deg(res, rec, model.correction(fit, model_effects))
            evd["window_residual_rms_before_rad_s"] = rms_cur
            evd["window_residual_rms_after_rad_s"] = rms_new
            add_open(kind, axis, name, fields, evd, x_before, x_after, att_cur, att_new)
        else:
            model_effects.append(name if axis is None or kind == "step" else f"{name}@{axis}")
            res, model, rec, tau_acc, fit, e = refit(res, model, rec, tau_acc)
            rms_new = rms(e)
            att_new = attitude_error_deg(res, rec, model.correction(fit, model_effects))
            if kind == "step":
                size = np.array(fit.effect_theta(name), float)
                se = np.array(fit.effect_stderr(name), float)
                fields = dict(fields, size_rad_s=size)
                evd["size_std_errors_rad_s"] = se
                axis = int(np.argmax(np.abs(size) / np.where(se > 0, se, np.inf)))
            elif kind == "regressor":
                fields = dict(fields, coef=float(fit.effect_theta(f"{name}@{axis}")[0]))
            add_open(kind, axis, name, fields, evd, rms_cur, rms_new, att_cur, att_new)
        history.append(e)
        rms_cur, att_cur = rms_new, att_new
    found = [s.effect for s in steps]
    params = params_table(fit, model_effects)
    for name, hp in held_params.items():
        params[name] = {k: [float(v[0]), float(v[1])] for k, v in hp.items()}
    if tau_acc != 0.0 and "time_offset" in params:
        v, se = params["time_offset"]["tau_s"]
        params["time_offset"]["tau_s"] = [tau_acc + v, se]
        notes.append(
            f"time_offset re-linearised (Gauss-Newton): the gyro was advanced by {tau_acc:.6g} s and "
            "the fit repeated; tau_s is the total"
        )
    t0_c = res.temp_mean_c()
    return LoopResult(
        declared=tuple(declared),
        found=tuple(steps),
        reference=res.kind,
        description=res.description,
        residual_rms_before_rad_s=rms0,
        residual_rms_after_rad_s=rms_cur,
        attitude_error_before_deg=att0,
        attitude_error_after_deg=att_cur,
        params=params,
        tested={c: ev for c, ev in last_tests.items() if c not in found},
        untestable=untestable,
        remaining=describe_remaining(res, e),
        notes=tuple(notes),
        n_windows=res.m,
        alpha=alpha,
        residual=res,
        history=tuple(history),
        unexplained=tuple(unexplained),
        open_search=open_last,
        t0_c=t0_c,
    )


def run_loop(
    rec: Recording,
    *,
    declared: Sequence[str],
    segments: Sequence[Segment] | None = None,
    candidates: Sequence[str] | None = None,
    reference: str = "auto",
    window_s: float | None = None,
    alpha: float = 0.01,
    thermal_order: int = 1,
    min_rms_reduction: float = 0.005,
    min_attitude_reduction: float = 0.05,
    max_steps: int = 8,
    angle_sigma_deg: float = 2.0,
    axis_sigma_deg: float = 5.0,
    angle_mode: str = "rotation",
    open_search: bool = True,
    seed: int = 0,
    attitude_lines: S.AttitudeLineOptions | None = None,
) -> LoopResult:
    """Close the loop on one recording.

    Parameters
    ----------
    rec : Recording
        Measured or simulated data with some reference (``ref_*_rad_s``, ``ref_q*``) or
        ``segments``.
    declared : sequence of str
        Effects already in the model (fitted jointly from the start).
    segments : sequence of Segment, optional
        Still / known-rotation segments (see :mod:`gyrocore.loop.residual`).
    candidates : sequence of str, optional
        Effects to trace (default: every :data:`gyrocore.loop.model.CANDIDATES` entry not declared).
    reference : {"auto", "rate", "attitude", "still", "angles"}
    window_s : float, optional
        Observation window length, s (default: see :func:`gyrocore.loop.residual.build_residual`).
    alpha : float
        Family-wise error rate over all candidates and steps (Holm).
    thermal_order : int
        Polynomial order of the thermal candidates.
    min_rms_reduction, min_attitude_reduction : float
        Practical significance: a winner must cut the window residual RMS or the attitude
        error by at least these fractions, and must predict the other half of the recording
        (see the module docstring).
    max_steps : int
        At most this many effects are added.
    angle_sigma_deg, axis_sigma_deg : float
        Uncertainty of each known rotation angle and of its axis (``"angles"`` reference),
        degrees.
    angle_mode : {"rotation", "axis"}
        Known rotations: whole rotations (start/end poses known) or the total angle about the
        axis only (free hand turns); see :func:`gyrocore.loop.residual.build_residual`.

    open_search : bool
        After the catalogue, describe what is still significant outside it (regressor
        library, narrow-band lines, bias steps: :mod:`gyrocore.loop.search`); α is then split
        between the catalogue (½) and the three open kinds (⅙ each).
    seed : int
        Seed of the step test's parametric bootstrap.
    attitude_lines : gyrocore.loop.search.AttitudeLineOptions, optional
        The sample-level line test against a reference attitude (segments, its statistic,
        the reference's line mask); default ``AttitudeLineOptions()``.

    Returns
    -------
    LoopResult
    """
    if not 0 < alpha < 1:
        raise GyroInputError(f"alpha must be in (0, 1), not {alpha}")
    with _single_thread():
        res = build_residual(
            rec,
            reference=reference,
            segments=segments,
            window_s=window_s,
            angle_sigma_deg=angle_sigma_deg,
            axis_sigma_deg=axis_sigma_deg,
            angle_mode=angle_mode,
        )

        def rebuild(r: Recording) -> Residual:
            return build_residual(
                r,
                reference=res.kind,
                segments=segments,
                window_s=window_s,
                angle_sigma_deg=angle_sigma_deg,
                axis_sigma_deg=axis_sigma_deg,
                angle_mode=angle_mode,
            )

        return loop_residual(
            res,
            rec,
            declared=declared,
            candidates=candidates,
            alpha=alpha,
            thermal_order=thermal_order,
            rebuild=rebuild,
            min_rms_reduction=min_rms_reduction,
            min_attitude_reduction=min_attitude_reduction,
            max_steps=max_steps,
            open_search=open_search,
            seed=seed,
            attitude_lines=attitude_lines,
        )
