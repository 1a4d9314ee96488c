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

from functools import partial
from typing import Sequence

import numpy as np

from gyrocore.effects import registry as E
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import Recording
from gyrocore.data.segments import Segment
from . import lines as LN
from . import search as S
from . import source
from .residual import Residual, build_residual
from .search import Unexplained
from .bias_step import screen_step
from .result import Evidence, LoopResult, Step, evidence_dict
from .model import CANDIDATES, Model, advance, fittable, input_check, params_table, with_companion
from .evidence import candidate_test, cv_min, cv_rms, cv_rms_with, rms
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


def loop_residual(res: Residual, rec: Recording, *, declared: Sequence[str], rebuild=None, **options) -> LoopResult:
    """Run the loop on a prepared :class:`~gyrocore.loop.residual.Residual` (see :func:`run_loop`).

    ``rebuild(recording) -> Residual`` (optional) rebuilds the residual from a recording; it
    enables the Gauss–Newton refinement of ``time_offset`` and the sample-level removal of
    narrow-band lines (see :func:`run_loop`). ``options``: ``candidates``, ``alpha``,
    ``thermal_order``, ``min_rms_reduction``, ``min_attitude_reduction``, ``max_steps``,
    ``open_search``, ``seed``, ``attitude_lines`` as :func:`run_loop`, and ``max_open_steps`` (at most this many
    open-search descriptions, default 8).
    """
    run = _LoopRun(res, rec, declared=declared, rebuild=rebuild, **options)
    for _ in range(run.max_steps + run.max_open_steps):
        # the current model's out-of-sample RMS: the base of every candidate's out-of-sample check
        cv_base = cv_rms(run.res.y_rad_s, run.model.design(run.model_effects)[0], min_windows=cv_min(run.res))
        if run.catalogue_step(cv_base):
            continue
        if not run.open_search_step(cv_base):
            break
    return run.result()


class _LoopRun:
    """The loop between its steps: the residual and model, their joint fit, what was found.

    The first joint fit of the declared effects is made on construction; each step adds one
    effect (:meth:`catalogue_step`, :meth:`open_search_step`) and refits everything.
    """

    def __init__(
        self,
        res: Residual,
        rec: Recording,
        *,
        declared: Sequence[str],
        rebuild=None,
        candidates: Sequence[str] | None = None,
        alpha: float = 0.01,
        thermal_order: int = 1,
        min_rms_reduction: float = 0.005,
        min_attitude_reduction: float = 0.05,
        max_steps: int = 8,
        open_search: bool = True,
        max_open_steps: int = 8,
        seed: int = 0,
        attitude_lines: LN.AttitudeLineOptions | None = None,
    ) -> None:
        self.declared = E.check_effect_names(declared)
        self.notes = list(res.notes)
        self.alpha = alpha
        self.min_rms_reduction = min_rms_reduction
        self.min_attitude_reduction = min_attitude_reduction
        self.max_steps = max_steps
        self.max_open_steps = max_open_steps
        self.rebuild = rebuild
        self.can_hold = rebuild is not None
        self.line_options = attitude_lines or LN.AttitudeLineOptions()
        self.orders = {"bias_thermal": thermal_order, "scale_thermal": thermal_order}
        self.model = Model(res, self.orders)
        self.model_effects, self.cands, self.untestable = self._effects_and_candidates(res, candidates)
        self.do_open = bool(open_search) and res.kind != "angles"
        if open_search and not self.do_open:
            self.notes.append(
                "open search not run: a known-angle reference has a few rotation windows, too few to "
                "describe effects outside the catalogue"
            )
        # family-wise error: a weighted Bonferroni/Holm split of alpha between the catalogue and the
        # three open-search kinds (search.ALPHA_SHARE); without the open search the catalogue has all of it
        self.alpha_cat = alpha * (S.ALPHA_SHARE["catalogue"] if self.do_open else 1.0)
        self.rng = np.random.default_rng(seed)
        self.rec0 = rec
        self.res, self.rec, self.tau_acc = res, rec, 0.0
        # sample-level line terms removed from the gyro (raw time frame): name -> [(axis, f_hz,
        # a_cos, a_sin), ...]; the correction is stream.held_correction (on the fly for a spill)
        self.held: dict[str, list] = {}
        self.held_params: dict[str, dict] = {}
        self.refit()
        self.history = [self.e]
        self.rms0 = rms(self.e)
        self.att0 = self.attitude_error()
        self.rms_cur, self.att_cur = self.rms0, self.att0
        self.steps: list[Step] = []
        self.unexplained: list[Unexplained] = []
        self.last_tests: dict[str, Evidence] = {}
        self.open_last: dict = {}
        self.n_cat = 0

    def _effects_and_candidates(self, res: Residual, candidates) -> tuple[list[str], list[str], dict[str, str]]:
        """The declared effects the loop fits, the candidates it can test here and why the others
        cannot be (a declared effect that cannot be fitted is an error)."""
        declared = self.declared
        ignored = [d for d in declared if not fittable(d)]
        if ignored:
            self.notes.append(f"declared effects without linear regressors are not fitted: {', '.join(ignored)}")
        model_effects = [d for d in declared if fittable(d)]
        if candidates is None:
            cand_all = [c for c in CANDIDATES if c not in declared]
        else:
            cand_all = [c for c in E.check_effect_names(candidates) if c not in declared]
            bad = [c for c in cand_all if c not in CANDIDATES]
            if bad:
                raise GyroInputError(f"the loop cannot trace {', '.join(bad)} (no linear regressors)")
        untestable: dict[str, str] = {}
        for c in list(cand_all) + list(model_effects):
            why = input_check(res, c)
            if why is None:
                try:
                    self.model.block(c)
                except GyroInputError as exc:
                    why = str(exc)
            if why is not None:
                if c in model_effects:
                    raise GyroInputError(f"declared effect {c} cannot be fitted here: {why}")
                untestable[c] = why
        return model_effects, [c for c in cand_all if c not in untestable], untestable

    # ---------------------------------------------------------------- the fit and its scores
    def base_rec(self) -> Recording:
        """The recording with the held lines removed from the gyro (before any time-offset advance)."""
        if not self.held:
            return self.rec0
        return source.of(self.rec0).without_lines(self.held)

    def refit(self, force_rebuild: bool = False) -> None:
        """Joint fit; with time_offset in the model, re-linearise around its estimate.

        ``force_rebuild``: rebuild the residual first (a line was removed from the gyro)."""
        if force_rebuild:
            rb = self.base_rec()
            self.rec = advance(rb, self.tau_acc) if self.tau_acc != 0.0 else rb
            self._rebuild()
        self.fit, self.e = self.model.fit(self.model_effects)
        if self.rebuild is None or "time_offset" not in self.model_effects or self.res.kind not in ("rate", "attitude"):
            return
        for _ in range(_TAU_ITERATIONS):
            d = float(self.fit.effect_theta("time_offset")[0])
            if not np.isfinite(d) or abs(d) < _TAU_TOL_S:
                break
            self.tau_acc += d
            self.rec = advance(self.base_rec(), self.tau_acc)
            self._rebuild()
            self.fit, self.e = self.model.fit(self.model_effects)

    def _rebuild(self) -> None:
        self.res = self.rebuild(self.rec)
        self.model = Model(self.res, self.orders)

    def attitude_error(self, fit=None, effects: Sequence[str] | None = None) -> float:
        """Attitude error of the model (default: the current fit of the current effects), deg."""
        if effects is None:
            fit, effects = self.fit, self.model_effects
        return attitude_error_deg(self.res, self.rec, self.model.correction(fit, effects))

    def practical(self, ev: Evidence) -> bool:
        """Out of sample (2-fold blocked: an effect fitted to coloured noise does not predict the
        other folds) and of a size that matters, in the residual or in the attitude."""
        size = ev.rms_reduction >= self.min_rms_reduction or (
            np.isfinite(ev.attitude_reduction) and ev.attitude_reduction >= self.min_attitude_reduction
        )
        held_ = ev.cv_rms_reduction > 0 or not np.isfinite(ev.cv_rms_reduction)
        if self.res.kind == "angles" and np.isfinite(ev.attitude_reduction):
            # the known angles are the reference: an effect that makes them worse by more
            # than a quarter of their uncertainty is refuted
            worse_deg = -ev.attitude_reduction * self.att_cur
            held_ = held_ and worse_deg <= 0.25 * np.degrees(self.res.angle_sigma_rad)
        return held_ and size

    def with_attitude(self, ev: Evidence, f, added: list[str]) -> Evidence:
        """The evidence with the attitude reduction of the model plus ``added`` (fitted as ``f``)."""
        att = self.attitude_error(f, self.model_effects + added)
        att_red = 1.0 - att / self.att_cur if self.att_cur > _MIN_ATTITUDE_DEG else float("nan")
        return Evidence(**{**ev.__dict__, "attitude_reduction": att_red})

    def open_term_test(self, name: str, thr: float, cv_base: float):
        """Full joint refit + HAC Wald test of an open term (as a catalogue candidate)."""
        ev, f = candidate_test(self.model, self.model_effects, name, thr, self.rms_cur, self.e, cv_base)
        if ev.df1 > 0 and ev.p_value < thr:
            ev = self.with_attitude(ev, f, [name])
        return ev, f

    def step_screen_now(self, thr_step: float):
        """The bias-step scan of the current window residual (:func:`gyrocore.loop.bias_step.screen_step`)."""
        X0 = self.model.design(self.model_effects)[0]
        sig = self.fit.axis_sigma_rad_s if self.fit is not None else np.maximum(np.std(self.e, axis=0), 1e-12)
        return screen_step(self.res, X0, self.e, sig, threshold=thr_step, rng=self.rng)

    def _advanced(self, rms_new: float, att_new: float) -> None:
        """Record the refitted residual as the start of the next step."""
        self.history.append(self.e)
        self.rms_cur, self.att_cur = rms_new, att_new

    # ---------------------------------------------------------------- the catalogue step
    def catalogue_step(self, cv_base: float) -> bool:
        """Test every catalogue candidate not yet in the model and add the winner (or a bias step
        that predicts better than the ramp that won). False when none is significant."""
        sig, evs = self._test_catalogue(cv_base)
        if not sig:
            return False
        best, ambiguous = self._winner(sig, evs)
        if best == "bias_ramp" and self.do_open and self._step_instead_of_ramp(cv_base):
            return True
        # `best` has the strongest evidence (smallest p-value, which accounts for its number
        # of parameters); the ambiguous ones are reported with it.
        self.model_effects.extend(with_companion(self.model_effects, best))
        self.refit()
        rms_new = rms(self.e)
        att_new = self.attitude_error()
        self.steps.append(
            Step(
                effect=best,
                evidence=Evidence(**{**evs[best].__dict__, "ambiguous_with": tuple(ambiguous)}),
                residual_rms_before_rad_s=self.rms_cur,
                residual_rms_after_rad_s=rms_new,
                attitude_error_before_deg=self.att_cur,
                attitude_error_after_deg=att_new,
            )
        )
        self.n_cat += 1
        self.last_tests = {}
        self._advanced(rms_new, att_new)
        return True

    def _test_catalogue(self, cv_base: float) -> tuple[list[str], dict[str, Evidence]]:
        """Each remaining candidate's evidence at the Holm threshold α/K, and the candidates that
        pass it and are of practical size."""
        remaining = [c for c in self.cands if c not in self.model_effects]
        if not remaining or self.n_cat >= self.max_steps:
            return [], {}
        trial = {
            c: candidate_test(self.model, self.model_effects, c, 0.0, self.rms_cur, self.e, cv_base) for c in remaining
        }
        testable = [c for c in remaining if trial[c][0].df1 > 0]
        for c in remaining:
            if c not in testable:
                self.untestable[c] = "not observable given the model: " + ", ".join(trial[c][0].unobservable)
        if not testable:
            return [], {}
        thr = self.alpha_cat / len(testable)
        evs: dict[str, Evidence] = {}
        for c in testable:
            ev, f = trial[c]
            ev = Evidence(**{**ev.__dict__, "threshold": thr})
            if ev.p_value < thr:
                ev = self.with_attitude(ev, f, with_companion(self.model_effects, c))
            evs[c] = ev
        self.last_tests = evs
        return [c for c in testable if evs[c].p_value < thr and self.practical(evs[c])], evs

    def _winner(self, sig: list[str], evs: dict[str, Evidence]) -> tuple[str, list[str]]:
        """The winner among the significant candidates and those it is ambiguous with (see the
        module docstring, step 3)."""
        sig.sort(key=lambda c: (evs[c].log10_p, -evs[c].statistic))
        best = sig[0]
        ambiguous, nested = [], []
        thr = evs[best].threshold
        for r in sig[1:]:
            with_r = self.model_effects + with_companion(self.model_effects, r)
            with_best = self.model_effects + with_companion(self.model_effects, best)
            ev_b, _ = candidate_test(self.model, with_r, best, thr, self.rms_cur)
            ev_r, _ = candidate_test(self.model, with_best, r, thr, self.rms_cur)
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
        return best, ambiguous

    def _step_instead_of_ramp(self, cv_base: float) -> bool:
        """Step vs ramp: a bias step also correlates with time; when a significant step predicts
        out of sample better than the ramp, it is added instead (as an open-search description)."""
        thr_step = self.alpha * S.ALPHA_SHARE["step"]
        st = self.step_screen_now(thr_step)
        if st is None or not st.p_value < thr_step:
            return False
        name = E.family_name("step", st.t_s)
        ev_s, _ = self.open_term_test(name, thr_step, cv_base)
        cv_step = cv_rms_with(self.model, self.model_effects, name)
        cv_ramp = cv_rms_with(self.model, self.model_effects, "bias_ramp")
        if not (cv_step < cv_ramp and ev_s.df1 > 0 and self.practical(ev_s)):
            return False
        self.model_effects.append(name)
        self.refit()
        rms_new = rms(self.e)
        att_new = self.attitude_error()
        size = np.array([self.fit.effect_theta(name)[i] for i in range(3)])
        se = np.array([self.fit.effect_stderr(name)[i] for i in range(3)])
        ax = int(np.argmax(np.abs(size) / np.where(se > 0, se, np.inf)))
        evd = evidence_dict(ev_s)
        evd.update(
            {
                **st.evidence(),
                "log10_p_step": st.log10_p,
                "threshold_step": thr_step,
                "vs_ramp": {"cv_rms_step_rad_s": cv_step, "cv_rms_ramp_rad_s": cv_ramp, "chosen": "step"},
                "size_std_errors_rad_s": se,
            }
        )
        self._add_open("step", ax, name, {"t_s": st.t_s, "size_rad_s": size}, evd, self.rms_cur, rms_new, att_new)
        self.notes.append(
            f"a bias step at t = {st.t_s:.6g} s explains the residual better than "
            f"bias_ramp (out-of-sample RMS {cv_step:.3g} vs {cv_ramp:.3g} rad/s)"
        )
        self.last_tests = {}
        self._advanced(rms_new, att_new)
        return True

    # ---------------------------------------------------------------- the open search
    def open_search_step(self, cv_base: float) -> bool:
        """Add the strongest description outside the catalogue (:func:`gyrocore.loop.open_step.open_step`).
        False when the open search does not run, is spent or finds nothing."""
        if not self.do_open or len(self.unexplained) >= self.max_open_steps:
            return False
        took = open_step(self, cv_base)
        if took is None:
            return False
        kind, axis, name, fields, evd, held_corr = took
        if held_corr is not None:
            self._hold_line(kind, axis, name, fields, evd, held_corr)
        else:
            self._add_open_term(kind, axis, name, fields, evd)
        return True

    def _hold_line(self, kind: str, axis: int, name: str, fields: dict, evd: dict, held_corr: tuple) -> None:
        """A sample-level line: removed from the gyro (raw time frame), the residual rebuilt."""
        x_before = evd.pop("_sample_rms_before")
        self.held.setdefault(name, []).append(held_corr)
        hp = self.held_params.setdefault(name, {})
        for k_, v_ in evd.pop("_params").items():
            hp[k_] = v_
        self.refit(force_rebuild=True)
        x_after = evd.pop("_sample_rms_after")
        rms_new = rms(self.e)
        att_new = self.attitude_error()
        evd["window_residual_rms_before_rad_s"] = self.rms_cur
        evd["window_residual_rms_after_rad_s"] = rms_new
        self._add_open(kind, axis, name, fields, evd, x_before, x_after, att_new)
        self._advanced(rms_new, att_new)

    def _add_open_term(self, kind: str, axis: int, name: str, fields: dict, evd: dict) -> None:
        """A window-level open term (regressor on one axis, line on one axis, bias step) added to
        the model and refitted with it."""
        self.model_effects.append(name if axis is None or kind == "step" else f"{name}@{axis}")
        self.refit()
        rms_new = rms(self.e)
        att_new = self.attitude_error()
        if kind == "step":
            size = np.array(self.fit.effect_theta(name), float)
            se = np.array(self.fit.effect_stderr(name), float)
            fields = dict(fields, size_rad_s=size)
            evd["size_std_errors_rad_s"] = se
            axis = int(np.argmax(np.abs(size) / np.where(se > 0, se, np.inf)))
        elif kind == "regressor":
            fields = dict(fields, coef=float(self.fit.effect_theta(f"{name}@{axis}")[0]))
        self._add_open(kind, axis, name, fields, evd, self.rms_cur, rms_new, att_new)
        self._advanced(rms_new, att_new)

    def _add_open(self, kind, axis, name, fields, evidence, before, after, att_after) -> None:
        self.unexplained.append(
            Unexplained(
                kind=kind,
                axis="xyz"[axis],
                effect=name,
                fields=fields,
                evidence=evidence,
                residual_rms_before_rad_s=before,
                residual_rms_after_rad_s=after,
                attitude_error_before_deg=self.att_cur,
                attitude_error_after_deg=att_after,
            )
        )

    # ---------------------------------------------------------------- the result
    def result(self) -> LoopResult:
        found = [s.effect for s in self.steps]
        params = params_table(self.fit, self.model_effects)
        for name, hp in self.held_params.items():
            params[name] = {k: [float(v[0]), float(v[1])] for k, v in hp.items()}
        if self.tau_acc != 0.0 and "time_offset" in params:
            v, se = params["time_offset"]["tau_s"]
            params["time_offset"]["tau_s"] = [self.tau_acc + v, se]
            self.notes.append(
                f"time_offset re-linearised (Gauss-Newton): the gyro was advanced by {self.tau_acc:.6g} s and "
                "the fit repeated; tau_s is the total"
            )
        t0_c = self.res.temp_mean_c()
        return LoopResult(
            declared=tuple(self.declared),
            found=tuple(self.steps),
            reference=self.res.kind,
            description=self.res.description,
            residual_rms_before_rad_s=self.rms0,
            residual_rms_after_rad_s=self.rms_cur,
            attitude_error_before_deg=self.att0,
            attitude_error_after_deg=self.att_cur,
            params=params,
            tested={c: ev for c, ev in self.last_tests.items() if c not in found},
            untestable=self.untestable,
            remaining=describe_remaining(self.res, self.e),
            notes=tuple(self.notes),
            n_windows=self.res.m,
            alpha=self.alpha,
            residual=self.res,
            history=tuple(self.history),
            unexplained=tuple(self.unexplained),
            open_search=self.open_last,
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
    attitude_lines: LN.AttitudeLineOptions | None = None,
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
    attitude_lines : gyrocore.loop.lines.AttitudeLineOptions, optional
        The sample-level line test against a reference attitude (segments, its statistic,
        the reference's line mask); default ``AttitudeLineOptions()``.

    Returns
    -------
    LoopResult
    """
    if not 0 < alpha < 1:
        raise GyroInputError(f"alpha must be in (0, 1), not {alpha}")
    with _single_thread():
        build = partial(
            build_residual,
            segments=segments,
            window_s=window_s,
            angle_sigma_deg=angle_sigma_deg,
            axis_sigma_deg=axis_sigma_deg,
            angle_mode=angle_mode,
        )
        res = build(rec, reference=reference)

        def rebuild(r: Recording) -> Residual:
            return build(r, reference=res.kind)  # the reference resolved on the first build

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
