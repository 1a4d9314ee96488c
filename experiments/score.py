"""Score anyone's calibration: a user's routine beside none, the core and the floor.

For each scenario and simulated unit (the ablation's units: same sensor preset, same instance
seeds, :func:`experiments.montecarlo.instance_seeds`):

1. the scored recording (``run=0``) and the unit's calibration recordings (rate-table run,
   thermal run) are simulated;
2. the user's routine (:mod:`experiments.calibrators`: Python ``module:factory``, a registered
   name, or fit/apply commands) is fitted on the calibration recordings and applied to the
   scored recording — both stripped of their truth (:func:`experiments.calibrators.strip_truth`);
   the truth stays in this process;
3. the corrected gyro is integrated from the true attitude at the end of the power-up still
   window and scored against the truth (RMS attitude error, DESIGN.md "The score"), beside the
   raw gyro (``none``), the core through the same door (``core``, the ablation's ``all`` row,
   same numbers), and the floor (truth + the unit's own noise).

A unit whose routine fails is recorded with a one-line reason; the campaign goes on.
:func:`check_contract` gates a campaign against a contract file (``gyroharness check``).
"""

from __future__ import annotations

import math
import os
import time
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from gyrocore.errors import GyroInputError
from experiments import ablation as A
from experiments.calibrators import (
    calibration_recordings,
    CommandCalibrator,
    CoreCalibrator,
    IsolatedCalibrator,
    load_calibrator,
    REGISTRY,
    RoutineFailure,
    run_routine,
    strip_truth,
)
from experiments.montecarlo import instance_seeds
from experiments.report import md_table, new_figure, save_figure, single_thread_blas
from gyrocore.data.jsonable import to_jsonable
from gyrocore.data.recording import atomic_write_text
from sim import scenarios as S
from sim.scenarios import load_scenario

__all__ = [
    "FORMAT_VERSION",
    "UnitScore",
    "ScoreCampaign",
    "score_unit",
    "score_campaign",
    "scenario_summary",
    "campaign_json",
    "report_markdown",
    "score_figure",
    "Contract",
    "load_contract",
    "check_contract",
    "CheckResult",
    "false_failure_rate",
    "suggest_bound",
    "junit_xml",
]

FORMAT_VERSION = 1
#: Default scenarios of ``gyroharness score``.
DEFAULT_SCENARIOS = ("static", "static_bumped", "turntable", "thermal", "hover", "power_cycles")
DEFAULT_UNITS = 4
#: Error-curve sample points (fractions of the scored duration), as the ablation's.
CURVE_FRACTIONS = tuple(np.round(np.linspace(0.0, 1.0, 21), 3))
ROWS = ("none", "core", "user", "floor")


# ------------------------------------------------------------------------------ one unit
@dataclass(frozen=True)
class UnitScore:
    """One unit in one scenario.

    Attributes
    ----------
    scenario, sensor : str
    instance, seed : int
    rms_deg, final_deg : dict
        ``{row: value}`` for rows ``none``, ``core``, ``user``, ``floor`` (``user`` NaN when
        the routine failed), degrees.
    rms_predicted_deg : float
        The drift prediction's RMS error for the core (NaN where no prediction exists).
    failed : str or None
        One-line reason when the user's routine failed on this unit.
    t_s : list of float
        Curve times since the start of scoring, s.
    curves_deg : dict
        ``{row: list}`` error angle at ``t_s``, degrees.
    """

    scenario: str
    sensor: str
    instance: int
    seed: int
    rms_deg: Mapping[str, float]
    final_deg: Mapping[str, float]
    rms_predicted_deg: float = float("nan")
    failed: str | None = None
    wall_s: float = 0.0
    t_s: tuple = ()
    curves_deg: Mapping[str, tuple] = field(default_factory=dict)

    def ratio(self, to: str) -> float:
        """RMS(user) / RMS(``to``)."""
        d = self.rms_deg.get(to, float("nan"))
        u = self.rms_deg.get("user", float("nan"))
        return u / d if d and math.isfinite(d) and d > 0 else float("nan")


def make_routine(spec: Mapping[str, Any]):
    """A routine from a picklable spec: ``{"calibrator": SPEC}`` or ``{"fit_cmd", "apply_cmd", "timeout_s"}``."""
    if spec.get("calibrator"):
        name = str(spec["calibrator"])
        if name in REGISTRY or not spec.get("isolate", True):
            return load_calibrator(name)
        return IsolatedCalibrator(name, timeout_s=float(spec.get("timeout_s", 120.0)))
    if spec.get("fit_cmd") and spec.get("apply_cmd"):
        return CommandCalibrator(
            fit_cmd=str(spec["fit_cmd"]),
            apply_cmd=str(spec["apply_cmd"]),
            timeout_s=float(spec.get("timeout_s", 120.0)),
        )
    raise GyroInputError("give a calibrator: --calibrator NAME|module:factory, or both --fit-cmd and --apply-cmd")


def validate_spec(spec: Mapping[str, Any]) -> None:
    """Fail early (one line) on a bad calibrator spec: unknown module, bad template."""
    if spec.get("calibrator") and (spec.get("fit_cmd") or spec.get("apply_cmd")):
        raise GyroInputError("give either --calibrator or --fit-cmd/--apply-cmd, not both")
    if bool(spec.get("fit_cmd")) != bool(spec.get("apply_cmd")):
        raise GyroInputError("the command form needs both --fit-cmd and --apply-cmd")
    if spec.get("calibrator"):
        load_calibrator(str(spec["calibrator"]))  # import errors: one line now, not per unit
    else:
        make_routine(spec)


def _predicted_rms_deg(res, core_params, present, still, start: int) -> float:
    """The drift prediction of the core's RMS error (``experiments.ablation.predict_instance``)
    with the noise model the core's calibration identified (not the unit's true noise:
    the same prediction the ablation reports), where it exists; NaN otherwise."""
    fn = getattr(A, "predict_instance", None)
    if fn is None:
        return float("nan")
    try:
        nm = A.identified_noise(core_params, float(res.recording.rate_hz))  # as the ablation predicts
        return float(fn(res, list(core_params.stages), present, still, start, noise=nm).rms_predicted_deg)
    except Exception:  # noqa: BLE001 - the prediction is optional beside the measured score
        return float("nan")


def score_unit(
    scenario: str,
    *,
    routine_spec: Mapping[str, Any],
    sensor: str = "icm42688p",
    seed: int = 0,
    instance: int = 0,
    duration_s: float | None = None,
    quick: bool = True,
    calibration_durations_s: tuple[float | None, float | None] | None = None,
    cache_dir: str | None = None,
) -> UnitScore:
    """Score the user's routine on one unit in one scenario (needs :mod:`sim`).

    ``quick`` uses the quick calibration runs (120-s table, 300-s thermal; the ablation's
    ``--quick``); ``calibration_durations_s`` overrides them (the core's column then uses the
    same shortened runs). ``cache_dir`` caches the core's calibration per unit.
    """
    import warnings

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = S.simulate(scenario, sensor=sensor, duration_s=duration_s, seed=seed, run=0)
    rec, truth, p_true = res.recording, res.truth, res.params_true
    present = A.present_effects(p_true)
    cal_raw = calibration_recordings(sensor, seed, quick=quick, durations_s=calibration_durations_s)
    cal = [strip_truth(r, references=True) for r in cal_raw]
    scored = strip_truth(rec, references=False)
    core_params = A.calibrate_core(
        sensor, seed, present, quick=quick, cache_dir=cache_dir, durations_s=calibration_durations_s
    )
    variants = {
        "none": rec.gyro_rad_s,
        "core": CoreCalibrator(effects=present).apply(scored, core_params),
        "floor": S.floor_gyro(res),
    }
    failed = None
    try:
        variants["user"] = run_routine(make_routine(routine_spec), cal, [scored])[0]
    except RoutineFailure as exc:
        failed = str(exc)
    except GyroInputError as exc:  # a bad template or module: the same for every unit
        failed = str(exc).splitlines()[0]
    still = A.powerup_windows(rec, p_true, bias_bound_rad_s=A.bias_bound_rad_s(sensor))
    start = 0 if still[0][1] is None else int(still[0][1].stop)
    sc = A.score_variants(rec.t_s, truth.q_SW_wxyz, variants, start=start)
    t = rec.t_s[start:] - rec.t_s[start]
    idx = np.clip(np.round(np.asarray(CURVE_FRACTIONS) * (t.size - 1)).astype(int), 0, t.size - 1)
    nan = float("nan")
    return UnitScore(
        scenario=scenario,
        sensor=sensor,
        instance=int(instance),
        seed=int(seed),
        rms_deg={r: (sc[r][0].rms_error_deg if r in sc else nan) for r in ROWS},
        final_deg={r: (sc[r][0].final_error_deg if r in sc else nan) for r in ROWS},
        rms_predicted_deg=_predicted_rms_deg(res, core_params, present, still, start),
        failed=failed,
        wall_s=time.perf_counter() - t0,
        t_s=tuple(float(x) for x in t[idx]),
        curves_deg={r: tuple(float(x) for x in np.degrees(sc[r][1][idx])) for r in ROWS if r in sc},
    )


def _score_task(args: tuple) -> UnitScore:
    scenario, kw = args

    with single_thread_blas():
        return score_unit(scenario, **kw)


# ------------------------------------------------------------------------------ campaign
@dataclass(frozen=True)
class ScoreCampaign:
    """Every unit of every scenario, plus how it was run."""

    calibrator: str
    sensor: str
    seed: int
    units: int
    scenarios: tuple[str, ...]
    durations_s: Mapping[str, float | None]
    quick: bool
    results: tuple[UnitScore, ...]
    wall_s: float
    workers: int
    calibration_s: tuple | None = None
    format_version: int = FORMAT_VERSION

    @property
    def failed(self) -> list[UnitScore]:
        return [u for u in self.results if u.failed]

    def of(self, scenario: str) -> list[UnitScore]:
        return [u for u in self.results if u.scenario == scenario]


def describe_spec(spec: Mapping[str, Any]) -> str:
    if spec.get("calibrator"):
        return str(spec["calibrator"])
    return f"fit: {spec.get('fit_cmd')} | apply: {spec.get('apply_cmd')}"


def score_campaign(
    *,
    routine_spec: Mapping[str, Any],
    scenarios: Sequence[str] = DEFAULT_SCENARIOS,
    sensor: str = "icm42688p",
    units: int = DEFAULT_UNITS,
    seed: int = 0,
    durations_s: Mapping[str, float | None] | None = None,
    quick: bool = True,
    calibration_durations_s: tuple[float | None, float | None] | None = None,
    workers: int | None = 1,
    progress: bool = False,
) -> ScoreCampaign:
    """Score a routine over ``units`` units × ``scenarios`` (worker processes if ``workers`` > 1)."""
    import shutil
    import tempfile

    validate_spec(routine_spec)
    scenarios = tuple(scenarios)
    for sc in scenarios:
        load_scenario(sc)  # one-line error for an unknown scenario before any work
    durations = {sc: (durations_s or {}).get(sc) for sc in scenarios}
    seeds = instance_seeds(int(seed), int(units))
    t0 = time.perf_counter()
    cache = tempfile.mkdtemp(prefix="gyroharness-score-cache-")
    jobs = [
        (
            sc,
            dict(
                routine_spec=dict(routine_spec),
                sensor=sensor,
                seed=s,
                instance=i,
                duration_s=durations[sc],
                quick=quick,
                calibration_durations_s=calibration_durations_s,
                cache_dir=cache,
            ),
        )
        for sc in scenarios
        for i, s in enumerate(seeds)
    ]
    n_workers = max(1, min(int(workers or os.cpu_count() or 1), len(jobs)))
    try:
        if n_workers == 1:
            results = []
            for j in jobs:
                results.append(_score_task(j))
                if progress:
                    u = results[-1]
                    print(
                        f"{u.scenario} unit {u.instance}: "
                        + (
                            f"FAILED {u.failed}"
                            if u.failed
                            else f"user {u.rms_deg['user']:.4g}°, core {u.rms_deg['core']:.4g}°"
                        ),
                        flush=True,
                    )
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            with ProcessPoolExecutor(max_workers=n_workers, mp_context=mp.get_context("spawn")) as ex:
                results = list(ex.map(_score_task, jobs))
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    return ScoreCampaign(
        calibrator=describe_spec(routine_spec),
        sensor=sensor,
        seed=int(seed),
        units=int(units),
        scenarios=scenarios,
        durations_s=durations,
        quick=bool(quick),
        results=tuple(results),
        calibration_s=None if calibration_durations_s is None else tuple(calibration_durations_s),
        wall_s=time.perf_counter() - t0,
        workers=n_workers,
    )


def _med(x) -> float:
    x = np.asarray([v for v in x if math.isfinite(v)], float)
    return float(np.median(x)) if x.size else float("nan")


def _pct(x, q) -> float:
    x = np.asarray([v for v in x if math.isfinite(v)], float)
    return float(np.percentile(x, q)) if x.size else float("nan")


def scenario_summary(units: Sequence[UnitScore]) -> dict:
    """Medians over units (DESIGN.md keys), the 10th/90th percentiles, the per-unit ratios' medians.

    ``rms_user_deg`` and the ratios are over the units whose routine did not fail.
    """
    ok = [u for u in units if not u.failed]
    out = {
        "rms_user_deg": _med(u.rms_deg["user"] for u in ok),
        "rms_none_deg": _med(u.rms_deg["none"] for u in units),
        "rms_core_deg": _med(u.rms_deg["core"] for u in units),
        "rms_floor_deg": _med(u.rms_deg["floor"] for u in units),
        "failed_units": [{"unit": u.instance, "seed": u.seed, "reason": u.failed} for u in units if u.failed],
    }
    pred = [u.rms_predicted_deg for u in units]
    if any(math.isfinite(p) for p in pred):
        out["rms_predicted_deg"] = _med(pred)
    for r in ROWS:
        vals = [u.rms_deg[r] for u in (ok if r == "user" else units)]
        out[f"rms_{r}_deg_p10"] = _pct(vals, 10)
        out[f"rms_{r}_deg_p90"] = _pct(vals, 90)
    for to in ("floor", "none", "core"):
        out[f"ratio_to_{to}"] = _med(u.ratio(to) for u in ok)
    out["units"] = len(units)
    return out


def campaign_json(c: ScoreCampaign) -> dict:
    """``gyroharness score --json``: DESIGN.md's ``{"scenarios": {NAME: {...}}}`` plus the run's setup."""
    return {
        "format_version": c.format_version,
        "calibrator": c.calibrator,
        "sensor": c.sensor,
        "seed": c.seed,
        "units": c.units,
        "quick": c.quick,
        "calibration_s": None if c.calibration_s is None else list(c.calibration_s),
        "scenarios": {sc: scenario_summary(c.of(sc)) for sc in c.scenarios},
        "per_unit": [
            {
                "scenario": u.scenario,
                "unit": u.instance,
                "seed": u.seed,
                **{f"rms_{r}_deg": u.rms_deg[r] for r in ROWS},
                "failed": u.failed,
            }
            for u in c.results
        ],
        "wall_s": c.wall_s,
        "workers": c.workers,
    }


# ------------------------------------------------------------------------------ report
def score_figure(c: ScoreCampaign, out_dir) -> str:
    """Per-unit RMS attitude error per scenario: none, core, user, floor (log scale)."""
    fig = new_figure(figsize=(max(6.0, 1.3 * len(c.scenarios) + 2), 3.8))
    ax = fig.add_subplot(111)
    colors = {"none": "tab:red", "core": "tab:blue", "user": "tab:green", "floor": "0.4"}
    width = 0.8 / len(ROWS)
    for j, r in enumerate(ROWS):
        for i, sc in enumerate(c.scenarios):
            v = np.array([u.rms_deg[r] for u in c.of(sc)], float)
            v = v[np.isfinite(v) & (v > 0)]
            x = i - 0.4 + (j + 0.5) * width
            if v.size:
                ax.scatter(np.full(v.size, x), v, s=12, color=colors[r], alpha=0.7, label=r if i == 0 else None)
                ax.hlines(np.median(v), x - width / 2, x + width / 2, color=colors[r])
            nf = sum(1 for u in c.of(sc) if u.failed) if r == "user" else 0
            if nf:
                ax.annotate(
                    f"{nf} failed",
                    (x, 1.0),
                    xycoords=("data", "axes fraction"),
                    ha="center",
                    va="top",
                    fontsize=7,
                    color=colors[r],
                    rotation=90,
                )
    ax.set_xticks(range(len(c.scenarios)), c.scenarios, rotation=20)
    ax.set_yscale("log")
    ax.set_ylabel("RMS attitude error, deg")
    ax.set_title(f"{c.calibrator[:70]} — {c.sensor}, {c.units} units (dots: units; bars: medians)", fontsize=9)
    ax.grid(alpha=0.3, which="both", axis="y")
    ax.legend(fontsize=7)
    return save_figure(fig, out_dir, "score")


def _cal_text(c: ScoreCampaign) -> str:
    if c.calibration_s:
        return f"{c.calibration_s[0]:g}-s table and {c.calibration_s[1]:g}-s thermal"
    return "quick (120-s table, 300-s thermal)" if c.quick else "full"


def report_markdown(c: ScoreCampaign, figure: str | None = None, check: "CheckResult | None" = None) -> str:
    """The report section: one table per run, failures listed, the plot linked."""
    rows = []
    have_pred = False
    for sc in c.scenarios:
        s = scenario_summary(c.of(sc))
        have_pred |= "rms_predicted_deg" in s
        rows.append(
            (
                sc,
                s["units"],
                len(s["failed_units"]),
                s["rms_none_deg"],
                s["rms_core_deg"],
                s["rms_user_deg"],
                f"{s['rms_user_deg_p10']:.3g}–{s['rms_user_deg_p90']:.3g}",
                s["rms_floor_deg"],
                s.get("rms_predicted_deg", float("nan")),
                s["ratio_to_floor"],
                s["ratio_to_core"],
            )
        )
    hdr = [
        "scenario",
        "units",
        "failed",
        "none, °",
        "core, °",
        "user, °",
        "user p10–p90, °",
        "floor, °",
        "predicted (core), °",
        "user/floor",
        "user/core",
    ]
    if not have_pred:
        hdr = hdr[:8] + hdr[9:]
        rows = [r[:8] + r[9:] for r in rows]
    md = [
        f"## Score: {c.calibrator}\n",
        f"Sensor {c.sensor}, {c.units} units per scenario (campaign seed {c.seed}, the ablation's units), "
        f"{_cal_text(c)} calibration runs. RMS attitude error against the truth, median over units, "
        "integrated from the true attitude at the end of the power-up still window: no correction, the "
        "gyroharness core through the same door, the user's routine, the floor (truth + the unit's own noise). "
        "Ratios are medians of per-unit ratios.\n",
        md_table(hdr, rows),
    ]
    fails = [u for u in c.results if u.failed]
    if fails:
        md.append("\nFailed units:\n")
        md += [f"- {u.scenario} unit {u.instance} (seed {u.seed}): {u.failed}" for u in fails]
    if figure:
        md.append(f"\n![score]({figure})\n")
    if check is not None:
        md.append("\n### Contract\n")
        md.append(check.markdown())
    md.append(f"\nWall time {c.wall_s:.1f} s on {c.workers} worker(s).\n")
    return "\n".join(md)


def write_report(c: ScoreCampaign, out_dir, check: "CheckResult | None" = None) -> Path:
    """``out_dir/score.md`` + ``figures/score.png`` + ``score.json`` (atomic writes)."""
    import json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fig = score_figure(c, out)
    atomic_write_text(out / "score.md", report_markdown(c, fig, check))
    data = campaign_json(c)
    if check is not None:
        data["check"] = check.to_json()
    atomic_write_text(out / "score.json", json.dumps(to_jsonable(data), indent=1, allow_nan=True) + "\n")
    return out / "score.md"


# ------------------------------------------------------------------------------ the contract (CI gate)
BOUND_KEYS = ("max_rms_deg", "max_ratio_to_floor", "max_ratio_to_none", "max_ratio_to_core")
_METRIC_OF = {
    "max_rms_deg": ("rms_user_deg", "RMS error", "°"),
    "max_ratio_to_floor": ("ratio_to_floor", "RMS/floor", ""),
    "max_ratio_to_none": ("ratio_to_none", "RMS/none", ""),
    "max_ratio_to_core": ("ratio_to_core", "RMS/core", ""),
}


@dataclass(frozen=True)
class Contract:
    """A contract file (TOML).

    ::

        sensor = "icm42688p"       # preset (default icm42688p)
        units = 4                  # units per scenario (default 4)
        seed = 0                   # campaign seed (default 0): fixed units, a deterministic gate
        calibration = "quick"      # "quick" (120-s table, 300-s thermal) or "full"
        calibration_s = [40, 60]   # optional: other (table, thermal) durations, s
        timeout_s = 120            # per routine step
        [calibrator]               # optional; the command line overrides it
        fit_cmd = "./cal fit {params} {inputs}"
        apply_cmd = "./cal apply {params} {input} {output}"
        # or: python = "module:factory"
        [scenario.static]
        duration_s = 30            # optional (the scenario's default otherwise)
        max_rms_deg = 0.5          # any of the four bounds, each on the median over units
        max_ratio_to_floor = 4.0
        max_ratio_to_none = 0.5
        max_ratio_to_core = 2.0
    """

    path: str
    sensor: str
    units: int
    seed: int
    quick: bool
    timeout_s: float
    calibration_s: tuple[float, float] | None
    calibrator: Mapping[str, str]
    scenarios: Mapping[str, Mapping[str, float]]
    durations_s: Mapping[str, float | None]


def load_contract(path) -> Contract:
    """Read and validate a contract file; one-line :class:`GyroInputError` on any problem."""
    p = Path(path)
    if not p.is_file():
        raise GyroInputError(f"{path}: no such contract file")
    try:
        d = tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise GyroInputError(f"{path}: not a valid TOML file ({str(exc).splitlines()[0]})") from None
    known = {"sensor", "units", "seed", "calibration", "calibration_s", "timeout_s", "calibrator", "scenario"}
    extra = set(d) - known
    if extra:
        raise GyroInputError(f"{path}: unknown key(s) {', '.join(sorted(extra))}; known: {', '.join(sorted(known))}")
    scen = d.get("scenario")
    if not isinstance(scen, dict) or not scen:
        raise GyroInputError(f"{path}: no [scenario.NAME] section with bounds")
    bounds, durations = {}, {}
    for name, b in scen.items():
        if not isinstance(b, dict):
            raise GyroInputError(f"{path}: scenario.{name} must be a table of bounds")
        bad = set(b) - set(BOUND_KEYS) - {"duration_s"}
        if bad:
            raise GyroInputError(
                f"{path}: scenario.{name}: unknown key(s) {', '.join(sorted(bad))}; "
                f"bounds are {', '.join(BOUND_KEYS)} (and duration_s)"
            )
        bb = {}
        for k in BOUND_KEYS:
            if k in b:
                v = b[k]
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
                    raise GyroInputError(f"{path}: scenario.{name}.{k} must be a positive number, got {v!r}")
                bb[k] = float(v)
        if not bb:
            raise GyroInputError(f"{path}: scenario.{name} has no bound ({', '.join(BOUND_KEYS)})")
        bounds[name] = bb
        dur = b.get("duration_s")
        if dur is not None and (isinstance(dur, bool) or not isinstance(dur, (int, float)) or not dur > 0):
            raise GyroInputError(f"{path}: scenario.{name}.duration_s must be a positive number, got {dur!r}")
        durations[name] = None if dur is None else float(dur)
    units = d.get("units", DEFAULT_UNITS)
    seed = d.get("seed", 0)
    for k, v in (("units", units), ("seed", seed)):
        if isinstance(v, bool) or not isinstance(v, int) or v < (1 if k == "units" else 0):
            raise GyroInputError(f"{path}: {k} must be an integer >= {1 if k == 'units' else 0}, got {v!r}")
    cal = d.get("calibration", "quick")
    if cal not in ("quick", "full"):
        raise GyroInputError(f'{path}: calibration must be "quick" or "full", got {cal!r}')
    cal_s = d.get("calibration_s")
    if cal_s is not None and not (
        isinstance(cal_s, list)
        and len(cal_s) == 2
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in cal_s)
    ):
        raise GyroInputError(f"{path}: calibration_s must be [table_s, thermal_s], got {cal_s!r}")
    c = d.get("calibrator", {}) or {}
    if not isinstance(c, dict) or set(c) - {"fit_cmd", "apply_cmd", "python"}:
        raise GyroInputError(f"{path}: [calibrator] takes fit_cmd and apply_cmd, or python")
    spec = {"calibrator": c.get("python"), "fit_cmd": c.get("fit_cmd"), "apply_cmd": c.get("apply_cmd")}
    timeout = d.get("timeout_s", 120.0)
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not timeout > 0:
        raise GyroInputError(f"{path}: timeout_s must be a positive number, got {timeout!r}")
    return Contract(
        path=str(path),
        sensor=str(d.get("sensor", "icm42688p")),
        units=int(units),
        seed=int(seed),
        quick=(cal == "quick"),
        timeout_s=float(timeout),
        calibration_s=None if cal_s is None else (float(cal_s[0]), float(cal_s[1])),
        calibrator={k: v for k, v in spec.items() if v},
        scenarios=bounds,
        durations_s=durations,
    )


def _binom_tail(n: int, p: float, k_min: int) -> float:
    return float(sum(math.comb(n, k) * p**k * (1 - p) ** (n - k) for k in range(k_min, n + 1)))


def _median_exceed_k(n: int) -> int:
    """The median of n values exceeds B if at least this many values exceed B (even n: the
    conservative ⌈n/2⌉ — the midpoint of the two middle values may exceed B with one of them)."""
    return n // 2 + 1 if n % 2 else n // 2


def false_failure_rate(values: Sequence[float], bound: float, n_units: int) -> float:
    """Probability that the median over ``n_units`` fresh units exceeds ``bound``.

    As the accuracy contract does (docs/accuracy.md): log x over units is modelled as normal,
    with mean and sd from the Monte Carlo ``values`` (plug-in). A unit exceeds B with
    p = Φ(−(ln B − m)/s); the median of n units exceeds B when ⌈(n+1)/2⌉ of them do (odd n;
    ⌈n/2⌉ for even n, conservative): a binomial tail in p. NaN with fewer than 3 values.
    """
    from scipy.stats import norm

    x = np.asarray([v for v in values if math.isfinite(v) and v > 0], float)
    if x.size < 3:
        return float("nan")
    lx = np.log(x)
    m, s = float(lx.mean()), float(lx.std(ddof=1))
    if s == 0:
        return 0.0 if math.log(bound) >= m else 1.0
    p = float(norm.sf((math.log(bound) - m) / s))
    return _binom_tail(int(n_units), p, _median_exceed_k(int(n_units)))


def suggest_bound(values: Sequence[float], n_units: int, rate: float) -> float:
    """The bound whose :func:`false_failure_rate` for ``n_units`` units is ``rate``."""
    from scipy.optimize import brentq
    from scipy.stats import norm

    x = np.asarray([v for v in values if math.isfinite(v) and v > 0], float)
    if x.size < 3:
        return float("nan")
    lx = np.log(x)
    m, s = float(lx.mean()), float(lx.std(ddof=1))
    k = _median_exceed_k(int(n_units))
    p = brentq(lambda q: _binom_tail(int(n_units), q, k) - rate, 1e-300, 1.0 - 1e-15)
    return float(math.exp(m + s * norm.isf(p)))


@dataclass(frozen=True)
class BoundCheck:
    scenario: str
    bound: str
    limit: float
    value: float
    passed: bool
    false_failure_rate: float

    def line(self) -> str:
        metric, label, unit = _METRIC_OF[self.bound]
        return (
            f"{self.scenario}: {label} {self.value:.4g}{unit} > {self.bound} {self.limit:.4g}{unit} (median over units)"
        )


@dataclass(frozen=True)
class CheckResult:
    """The gate's verdict: every bound checked, every failed unit."""

    contract: str
    checks: tuple[BoundCheck, ...]
    failed_units: tuple[tuple[str, int, int, str], ...]
    campaign: ScoreCampaign | None = None
    contract_units: int | None = None

    @property
    def passed(self) -> bool:
        return all(c.passed for c in self.checks) and not self.failed_units

    def lines(self) -> list[str]:
        """One line per broken bound and per failed unit."""
        out = [f"{sc}: unit {i} (seed {s}) failed: {why}" for sc, i, s, why in self.failed_units]
        return out + [c.line() for c in self.checks if not c.passed]

    def markdown(self) -> str:
        rows = [
            (
                c.scenario,
                c.bound,
                c.limit,
                c.value,
                "pass" if c.passed else "**FAIL**",
                f"{c.false_failure_rate:.2g}" if math.isfinite(c.false_failure_rate) else "n/a",
            )
            for c in self.checks
        ]
        verdict = "PASSED" if self.passed else "FAILED"
        return (
            f"Contract `{self.contract}`: **{verdict}**.\n\n"
            + md_table(
                ["scenario", "bound", "limit", "median over units", "verdict", "false-failure rate (fresh units)"], rows
            )
            + "\nFalse-failure rate: probability that the median over as many fresh units exceeds the bound if "
            "the routine is as measured here (log-normal over units, plug-in mean/sd; see docs/score.md). With "
            "the contract's fixed seed the gate itself is deterministic.\n"
        )

    def to_json(self) -> dict:
        return {
            "contract": self.contract,
            "passed": self.passed,
            "lines": self.lines(),
            "checks": [asdict(c) for c in self.checks],
            "failed_units": [
                {"scenario": sc, "unit": i, "seed": s, "reason": why} for sc, i, s, why in self.failed_units
            ],
        }


def evaluate(contract: Contract, campaign: ScoreCampaign) -> CheckResult:
    """Check a campaign against a contract's bounds."""
    checks = []
    for sc, bounds in contract.scenarios.items():
        units = campaign.of(sc)
        ok = [u for u in units if not u.failed]
        s = scenario_summary(units)
        for k, limit in bounds.items():
            metric = _METRIC_OF[k][0]
            value = s[metric]
            per_unit = [u.rms_deg["user"] if k == "max_rms_deg" else u.ratio(metric[len("ratio_to_") :]) for u in ok]
            passed = bool(math.isfinite(value) and value <= limit)
            checks.append(BoundCheck(sc, k, limit, value, passed, false_failure_rate(per_unit, limit, contract.units)))
    failed = tuple((u.scenario, u.instance, u.seed, u.failed) for u in campaign.results if u.failed)
    return CheckResult(
        contract=contract.path,
        checks=tuple(checks),
        failed_units=failed,
        campaign=campaign,
        contract_units=contract.units,
    )


def check_contract(
    contract,
    *,
    routine_spec: Mapping[str, Any] | None = None,
    workers: int | None = 1,
    units: int | None = None,
    seed: int | None = None,
    progress: bool = False,
) -> CheckResult:
    """Run the contract's campaign for a routine and check every bound (``gyroharness check``).

    ``routine_spec`` (``{"calibrator": …}`` or ``{"fit_cmd": …, "apply_cmd": …}``) overrides the
    contract's ``[calibrator]``; ``units`` and ``seed`` override the contract's (e.g. to derive
    bounds on more units, and other ones, than the gate uses: :func:`suggestions`).
    """
    c = contract if isinstance(contract, Contract) else load_contract(contract)
    spec = dict(routine_spec or {})
    spec = {k: v for k, v in spec.items() if v} or dict(c.calibrator)
    if not spec:
        raise GyroInputError(
            f"{c.path}: no calibrator: give --calibrator or --fit-cmd/--apply-cmd, or a [calibrator] section"
        )
    spec.setdefault("timeout_s", c.timeout_s)
    camp = score_campaign(
        routine_spec=spec,
        scenarios=tuple(c.scenarios),
        sensor=c.sensor,
        units=units or c.units,
        seed=c.seed if seed is None else int(seed),
        durations_s=c.durations_s,
        quick=c.quick,
        calibration_durations_s=c.calibration_s,
        workers=workers,
        progress=progress,
    )
    return evaluate(c, camp)


def junit_xml(result: CheckResult) -> str:
    """JUnit XML: one test case per bound and one per failed unit (CI systems display it)."""
    import xml.etree.ElementTree as ET

    cases = []
    for c in result.checks:
        cases.append(
            (
                f"{c.scenario}.{c.bound}",
                None if c.passed else c.line(),
                f"median {c.value:.6g} vs limit {c.limit:.6g}; false-failure rate {c.false_failure_rate:.3g}",
            )
        )
    for sc, i, s, why in result.failed_units:
        cases.append((f"{sc}.unit{i}", f"{sc}: unit {i} (seed {s}) failed: {why}", ""))
    n_fail = sum(1 for _, f, _ in cases if f)
    wall = result.campaign.wall_s if result.campaign else 0.0
    suite = ET.Element(
        "testsuite",
        name="gyroharness-check",
        tests=str(len(cases)),
        failures=str(n_fail),
        errors="0",
        skipped="0",
        time=f"{wall:.3f}",
    )
    for name, failure, info in cases:
        tc = ET.SubElement(
            suite, "testcase", classname=f"gyroharness.{Path(result.contract).stem}", name=name, time="0"
        )
        if failure:
            f = ET.SubElement(tc, "failure", message=failure, type="BoundBroken")
            f.text = failure
        if info:
            so = ET.SubElement(tc, "system-out")
            so.text = info
    root = ET.Element("testsuites", name="gyroharness", tests=str(len(cases)), failures=str(n_fail))
    root.append(suite)
    return ET.tostring(root, encoding="unicode", xml_declaration=True) + "\n"


def suggestions(result: CheckResult, rate: float) -> dict:
    """Per scenario and bound of the contract, the limit with false-failure ``rate`` (:func:`suggest_bound`)
    for the median over the *contract's* number of units, from the spread of this run's units
    (run more, and other, units than the gate: ``check --units 16 --seed 1 --suggest 1e-3``)."""
    camp = result.campaign
    n = result.contract_units or camp.units
    out: dict = {}
    for c in result.checks:
        ok = [u for u in camp.of(c.scenario) if not u.failed]
        metric = _METRIC_OF[c.bound][0]
        vals = [u.rms_deg["user"] if c.bound == "max_rms_deg" else u.ratio(metric[len("ratio_to_") :]) for u in ok]
        out.setdefault(c.scenario, {})[c.bound] = suggest_bound(vals, n, rate)
    return out
