"""Fleet analysis: one analysis over many recordings, on Dask, and the fleet's statistics.

:func:`run_batch` runs ``bias``, ``allan``, ``calibrate`` or ``loop`` on every data file of a
list, in local worker processes (a Dask ``LocalCluster``, one single-threaded worker per core
by default) or on a running cluster, and writes one results table (one row per file: ``file``,
``sha256`` of the input, ``command``, ``options``, every headline number in SI units,
``warnings``, ``error``, ``outliers``) and a summary plot of the fleet's distribution of each
headline number. ``gyroharness batch`` (:mod:`gyrocore.cli.commands.batch`) is its command line.

A file that fails is a row with its one-line error; the others complete. Rerunning with the
same table skips the files whose input hash already has a result for the same command and
options (failed rows are retried).

Outliers: robust z-score ``0.6745·(x − median)/MAD`` of each headline number over the
fleet's successful rows, ``|z| > 3.5`` (Iglewicz & Hoaglin, *How to Detect and Handle
Outliers*, ASQC 1993: the modified z-score; 0.6745 = Φ⁻¹(0.75) makes MAD/0.6745 the
standard deviation of a normal sample, and 3.5 flags a normal sample's value with
probability ≈ 5e-4). Needs ≥ 5 successful files; a number with MAD = 0 flags nothing.
"""

from __future__ import annotations

import contextlib
import glob
import io
import json
import math
import os
import warnings
from pathlib import Path
from typing import Mapping

import numpy as np

from gyrocore.errors import GyroInputError
from gyrocore.calib.bias import StaticBiasCalibrator
from gyrocore.calib.params import save_params
from gyrocore.calibrator import Calibrator
from gyrocore.data.recording import atomic_write_bytes, file_sha256
from gyrocore.effects.registry import check_effect_names
from gyrocore.loop.loop import run_loop
from gyrocore.noise.allan import allan_analysis
from gyrocore.readers.convert import load_with_segments, read_any

__all__ = [
    "WORKER_ENV",
    "worker_environment",
    "COMMANDS",
    "run_batch",
    "run_one",
    "find_inputs",
    "robust_z",
    "mark_outliers",
    "plot_fleet",
    "read_table",
    "write_table",
    "execute",
    "default_workers",
]


#: Thread counts for spawned worker processes (Monte Carlo, batch): one BLAS/OpenMP thread each,
#: so that N workers on N cores do not oversubscribe (as Dask's nanny does).
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@contextlib.contextmanager
def worker_environment(defaults: Mapping[str, str] = WORKER_ENV):
    """Set the unset variables of ``defaults`` in os.environ for the duration of the block."""
    added = [k for k in defaults if k not in os.environ]
    for k in added:
        os.environ[k] = defaults[k]
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


#: Commands the batch runs.
COMMANDS = ("bias", "allan", "calibrate", "loop")
#: Largest exit status (shells keep 8 bits; 126+ mean "not executable"/signals).
MAX_EXIT = 100
#: Robust z-score above which a file is named an outlier (Iglewicz & Hoaglin 1993).
OUTLIER_Z = 3.5
#: Fewest successful files for the outlier test (a median and MAD of fewer are not robust).
MIN_FLEET = 5
#: Data-file suffixes picked up from a folder.
DATA_SUFFIXES = (".csv", ".parquet", ".pq")
#: Environment of local workers: one BLAS/OpenMP thread each (K workers on K cores).
AX = ("x", "y", "z")


# ------------------------------------------------------------------ one file (runs on a worker)
def _vec(prefix: str, v, suffix: str) -> dict:
    a = np.atleast_1d(np.asarray(v, float)).ravel()
    if a.size == 1:
        return {f"{prefix}{suffix}": float(a[0])}
    if a.size == 3:
        return {f"{prefix}_{AX[i]}{suffix}": float(a[i]) for i in range(3)}
    return {f"{prefix}[{i}]{suffix}": float(a[i]) for i in range(a.size)}


def _num(x) -> float:
    return float("nan") if x is None else float(x)


def headline_bias(path: str, options: dict) -> dict:
    rec = read_any(path, columns=())  # as `gyroharness bias`: a data file or any source `convert` reads
    r = StaticBiasCalibrator().fit(rec)
    out = {"n_samples": rec.n, "duration_s": rec.duration_s, "rate_hz": rec.rate_hz}
    out.update(_vec("bias", r.bias_rad_s, "_rad_s"))
    out.update(_vec("bias_se", r.bias_se_rad_s, "_rad_s"))
    out.update(_vec("noise_sigma", r.noise_sigma_rad_s, "_rad_s"))
    out["window_start_s"] = float(r.window_start_s)
    return out


def headline_allan(path: str, options: dict) -> dict:
    rec = read_any(path, columns=())  # as `gyroharness allan`
    # the motion gate as `gyroharness allan` runs it: a record with motion is cut to its
    # longest still stretch (warning) or refused (one error line, the row marked failed)
    res = allan_analysis(rec, check_static=True)
    out = {"n_samples": res.n_samples, "duration_s": res.duration_s, "rate_hz": rec.rate_hz}
    for ax, r in res.axes.items():
        t = r.all_terms()
        out[f"arw_{ax}_rad_per_sqrt_s"] = _num(t["arw_rad_per_sqrt_s"])
        out[f"bias_instability_{ax}_rad_s"] = _num(t["bias_instability_rad_s"])
        out[f"rrw_{ax}_rad_per_s_sqrt_s"] = _num(t["rrw_rad_per_s_sqrt_s"])
        out[f"quantization_{ax}_rad"] = _num(t["quantization_rad"])
        out[f"rate_ramp_{ax}_rad_s2"] = _num(t["rate_ramp_rad_s2"])
    return out


def headline_calibrate(path: str, options: dict) -> dict:
    names = check_effect_names(options.get("effects", "bias").split(","))
    rec = read_any(path)  # as `gyroharness calibrate`: a data file or any set `convert` reads (BROAD .hdf5, ...)
    res = Calibrator(effects=names).fit(rec, source_path=path)
    if options.get("params_dir"):
        save_params(res, Path(options["params_dir"]) / f"{Path(path).stem}.params.json", overwrite=True)
    out = {"n_samples": rec.n, "duration_s": rec.duration_s, "rate_hz": rec.rate_hz}
    for eff, pd in res.params.items():
        for pname, v in pd.items():
            if np.asarray(v).dtype.kind not in "fi":
                continue
            out.update(_vec(f"{eff}.{pname}", v, ""))
            se = res.stderr.get(eff, {}).get(pname)
            if se is not None:
                out.update(_vec(f"{eff}.{pname}", np.asarray(se, float), "_se"))
    out.update(_vec("residual_rms", res.residual_rms_rad_s, "_rad_s"))
    out["unobservable"] = ";".join(res.unobservable)
    return out


def headline_loop(path: str, options: dict) -> dict:
    conv = load_with_segments(path)
    declared = [e for e in options.get("effects", "bias").split(",") if e]
    r = run_loop(conv.recording, declared=declared, segments=list(conv.segments))
    found = [s.effect for s in r.found]
    out = {
        "n_samples": conv.recording.n,
        "duration_s": conv.recording.duration_s,
        "found": ";".join(found),
        "n_found": len(found),
        "residual_rms_before_rad_s": _num(r.residual_rms_before_rad_s),
        "residual_rms_after_rad_s": _num(r.residual_rms_after_rad_s),
        "attitude_error_before_deg": _num(r.attitude_error_before_deg),
        "attitude_error_after_deg": _num(r.attitude_error_after_deg),
    }
    for s in r.found:
        for name, v in s.evidence.params.items():
            out[f"{s.effect}.{name}"] = _num(v)
    return out


HEADLINE = {"bias": headline_bias, "allan": headline_allan, "calibrate": headline_calibrate, "loop": headline_loop}

#: The headline numbers the fleet summary (plot, outliers) is about, per command: a
#: prefix/suffix match on the table's columns.
FLEET_METRICS = {
    "bias": (
        "bias_x_rad_s",
        "bias_y_rad_s",
        "bias_z_rad_s",
        "noise_sigma_x_rad_s",
        "noise_sigma_y_rad_s",
        "noise_sigma_z_rad_s",
    ),
    "allan": tuple(f"{t}_{a}_{u}" for t, u in (("arw", "rad_per_sqrt_s"), ("bias_instability", "rad_s")) for a in AX),
    "calibrate": None,  # every fitted parameter value (not the standard errors) and the residual RMS
    "loop": ("n_found", "residual_rms_after_rad_s", "attitude_error_after_deg"),
}


def run_one(command: str, path: str, sha256: str, options: dict) -> dict:
    """One file: the command's headline numbers, or its one-line error. Never raises."""
    import time

    row = {"file": path, "sha256": sha256, "command": command, "options": json.dumps(options, sort_keys=True)}
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            row.update(HEADLINE[command](path, options))
            row["error"] = ""
        except GyroInputError as exc:
            row["error"] = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        except MemoryError:
            row["error"] = "out of memory"
        except Exception as exc:  # a bug or an unexpected file: a row, not the end of the batch
            msg = str(exc).splitlines()[0] if str(exc) else ""
            row["error"] = f"{type(exc).__name__}: {msg}"
    row["warnings"] = " | ".join(
        dict.fromkeys(str(w.message).replace("\n", " ") for w in caught if issubclass(w.category, UserWarning))
    )
    row["wall_s"] = time.perf_counter() - t0
    return row


# ------------------------------------------------------------------ inputs
def find_inputs(spec: str) -> list[str]:
    """Data files of a folder (recursively, by suffix) or of a glob pattern, sorted."""
    p = Path(spec)
    if p.is_dir():
        files = [str(f) for f in sorted(p.rglob("*")) if f.is_file() and f.suffix.lower() in DATA_SUFFIXES]
        if not files:
            raise GyroInputError(f"{spec}: no data files (*.csv, *.parquet) in this folder")
        return files
    if any(c in spec for c in "*?["):
        files = sorted(f for f in glob.glob(spec, recursive=True) if os.path.isfile(f))
        if not files:
            raise GyroInputError(f"{spec}: the pattern matches no file")
        return files
    if p.is_file():
        return [str(p)]
    raise GyroInputError(f"{spec}: no such folder, file or pattern")


def _hash(path: str) -> str:
    try:
        return file_sha256(path)
    except OSError as exc:
        return f"unreadable: {exc.strerror or type(exc).__name__}"


# ------------------------------------------------------------------ fleet summary
def robust_z(x: np.ndarray) -> np.ndarray:
    """Modified z-score 0.6745·(x − median)/MAD (NaN where x is NaN or MAD = 0)."""
    x = np.asarray(x, float)
    ok = np.isfinite(x)
    z = np.full(x.shape, np.nan)
    if ok.sum() < MIN_FLEET:
        return z
    med = float(np.median(x[ok]))
    mad = float(np.median(np.abs(x[ok] - med)))
    if mad > 0:
        z[ok] = 0.6745 * (x[ok] - med) / mad
    return z


def fleet_metrics(command: str, columns) -> list[str]:
    want = FLEET_METRICS[command]
    if want is None:
        return [c for c in columns if "." in c and not c.endswith("_se") and not c.startswith("options")] + [
            c for c in columns if c.startswith("residual_rms_")
        ]
    return [c for c in want if c in columns]


def mark_outliers(df, command: str) -> list[dict]:
    """Fill the ``outliers`` column; returns [{file, metric, value, z}]."""
    ok = df["error"].fillna("") == ""
    found = []
    flags = {i: [] for i in df.index}
    for m in fleet_metrics(command, df.columns):
        x = np.asarray(df.loc[ok, m], dtype=float) if m in df else np.array([])
        z = robust_z(x)
        for i, zi, xi in zip(df.index[ok], z, x):
            if np.isfinite(zi) and abs(zi) > OUTLIER_Z:
                flags[i].append(m)
                found.append({"file": df.at[i, "file"], "metric": m, "value": float(xi), "z": float(zi)})
    df["outliers"] = [";".join(flags[i]) for i in df.index]
    return found


def plot_fleet(df, command: str, path: str) -> None:
    """Strip plot of each headline number over the fleet; outliers red and named."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = df["error"].fillna("") == ""
    metrics = [
        m for m in fleet_metrics(command, df.columns) if np.isfinite(np.asarray(df.loc[ok, m], dtype=float)).any()
    ][:12]  # unresolved everywhere: no panel
    extra = command == "loop"
    n = max(len(metrics) + (1 if extra else 0), 1)
    ncol = min(3, n)
    nrow = math.ceil(n / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.6 * ncol, 3.4 * nrow), squeeze=False)
    rng = np.random.default_rng(0)  # jitter only
    k = 0
    for m in metrics:
        ax = axes.flat[k]
        k += 1
        x = np.asarray(df.loc[ok, m], dtype=float)
        files = list(df.loc[ok, "file"])
        z = robust_z(x)
        out = np.isfinite(z) & (np.abs(z) > OUTLIER_Z)
        jit = rng.uniform(-0.15, 0.15, x.size)
        ax.scatter(jit[~out], x[~out], s=14, color="k", alpha=0.7, label=f"{int(np.isfinite(x).sum())} files")
        if out.any():
            ax.scatter(jit[out], x[out], s=22, color="r", label=f"outlier (|robust z| > {OUTLIER_Z:g})")
            for j in np.flatnonzero(out):
                ax.annotate(
                    Path(files[j]).stem,
                    (jit[j], x[j]),
                    fontsize=7,
                    color="r",
                    xytext=(4, 0),
                    textcoords="offset points",
                )
        fin = x[np.isfinite(x)]
        if fin.size:
            med = float(np.median(fin))
            ax.axhline(med, color="b", lw=0.8, ls="--", label=f"median {med:.3g}")
        if fin.size and np.all(fin > 0) and fin.max() > 3 * fin.min():
            ax.set_yscale("log")  # noise levels: a log scale shows the fleet and its outliers at once
        ax.set_xlim(-0.6, 0.6)
        ax.set_xticks([])
        ax.set_title(m, fontsize=9)
        ax.legend(fontsize=6)
        ax.grid(True, alpha=0.3)
    if extra:  # found-effect distribution
        ax = axes.flat[k]
        k += 1
        names = [e for s in df.loc[ok, "found"].fillna("") for e in str(s).split(";") if e]
        uniq, cnt = np.unique(names, return_counts=True) if names else (np.array([]), np.array([]))
        ax.bar(range(len(uniq)), cnt, color="0.4")
        ax.set_xticks(range(len(uniq)), uniq, rotation=45, ha="right", fontsize=7)
        ax.set_title(f"effects found ({int(ok.sum())} files)", fontsize=9)
    for j in range(k, nrow * ncol):
        axes.flat[j].axis("off")
    n_fail = int((~ok).sum())
    fig.suptitle(
        f"gyroharness batch {command}: {int(ok.sum())} files" + (f", {n_fail} failed" if n_fail else ""), fontsize=10
    )
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


# ------------------------------------------------------------------ table
def read_table(path: str):
    import pandas as pd

    if not os.path.exists(path):
        return None
    try:
        if path.lower().endswith((".parquet", ".pq")):
            return pd.read_parquet(path)
        return pd.read_csv(path, keep_default_na=False, na_values=[""], dtype={"error": str, "sha256": str})
    except Exception as exc:  # a table we cannot read is not silently replaced
        raise GyroInputError(
            f"{path}: existing results table is unreadable ({str(exc).splitlines()[0][:120]}); "
            f"move it away or pass --no-resume"
        ) from None


def write_table(df, path: str) -> None:
    """CSV or Parquet by name; atomic (a full disk leaves the old table, one error line)."""
    try:
        if path.lower().endswith((".parquet", ".pq")):
            buf = io.BytesIO()
            df.to_parquet(buf, index=False)
            data = buf.getvalue()
        else:
            data = df.to_csv(index=False, lineterminator="\n").encode("utf-8")
        atomic_write_bytes(path, data)
    except OSError as exc:
        raise GyroInputError(
            f"{path}: cannot write the results table ({exc.strerror or exc}); "
            f"nothing was written, the previous table (if any) is unchanged"
        ) from None


# ------------------------------------------------------------------ execution
def execute(
    tasks: list[tuple], *, workers: int, scheduler: str | None, progress: bool = False
) -> tuple[list[dict], dict]:
    """Run ``run_one(*task)`` for every task; rows in task order, and backend info.

    ``scheduler``: address of a running Dask scheduler; else a ``LocalCluster`` of
    ``workers`` single-threaded worker processes; ``workers=0``: in this process (no Dask).
    A task whose worker dies (out of memory, killed) becomes a row with that error.
    """
    import sys

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(tasks), unit="file", file=sys.stderr)

    def tick(r):
        if bar is not None:
            bar.update(1)
        return r

    try:
        if scheduler is None and workers == 0:
            return [tick(run_one(*t)) for t in tasks], {"backend": "serial", "workers": 0}
        return _execute_dask(tasks, workers, scheduler, tick)
    finally:
        if bar is not None:
            bar.close()


def _execute_dask(tasks, workers, scheduler, tick):
    import logging

    from dask.distributed import Client, LocalCluster, as_completed

    cluster = None
    if scheduler is None:
        with worker_environment():  # workers are spawned now and read their thread counts at start-up
            cluster = LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                silence_logs=logging.ERROR,
            )
        client = Client(cluster, set_as_default=False)
    else:
        try:
            client = Client(scheduler, timeout="20s", set_as_default=False)
        except (OSError, TimeoutError) as exc:
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise GyroInputError(f"cannot connect to the Dask scheduler at {scheduler}: {msg}") from None
    try:
        n_workers = len(client.scheduler_info().get("workers", {}))
        futures = [client.submit(run_one, *t, pure=False) for t in tasks]
        index = {f.key: i for i, f in enumerate(futures)}
        rows: list[dict | None] = [None] * len(tasks)
        for fut in as_completed(futures, loop=client.loop):
            i = index[fut.key]
            try:
                rows[i] = tick(fut.result())
            except Exception as exc:  # the worker died (KilledWorker) or could not run the task
                command, path, sha, options = tasks[i]
                msg = str(exc).splitlines()[0] if str(exc) else ""
                rows[i] = tick(
                    {
                        "file": path,
                        "sha256": sha,
                        "command": command,
                        "options": json.dumps(options, sort_keys=True),
                        "error": f"worker failed: {type(exc).__name__}: {msg}"[:300],
                        "warnings": "",
                    }
                )
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return rows, {"backend": "dask-local" if scheduler is None else "dask", "workers": n_workers}


def run_batch(
    command: str,
    inputs: list[str],
    *,
    table: str,
    plot: str | None,
    options: dict,
    workers: int,
    scheduler: str | None,
    resume: bool = True,
    progress: bool = False,
) -> dict:
    """The batch: hash, skip what the table already has, run the rest, write table and plot."""
    import pandas as pd

    if command not in COMMANDS:
        raise GyroInputError(f"batch runs {', '.join(COMMANDS)}; got {command!r}")
    opt_key = json.dumps(options, sort_keys=True)
    hashes = [_hash(f) for f in inputs]
    old = read_table(table) if resume else None
    keep_old = None
    done: set[tuple[str, str]] = set()
    if old is not None and len(old):
        for col in ("sha256", "command", "options", "error", "file"):
            if col not in old.columns:
                raise GyroInputError(
                    f"{table}: not a batch results table (no column {col!r}); move it away or pass --no-resume"
                )
        good = (old["error"].fillna("") == "") & (old["command"] == command) & (old["options"] == opt_key)
        done = set(old.loc[good, "sha256"].astype(str))
        # keep the successful rows (of any command/options); files rerun now replace their old failed rows
        keep_old = old[(old["error"].fillna("") == "") | ~old["file"].isin(inputs)]
    tasks = [(command, f, h, options) for f, h in zip(inputs, hashes) if h not in done]
    unreadable = [t for t in tasks if t[2].startswith("unreadable")]
    tasks = [t for t in tasks if not t[2].startswith("unreadable")]
    rows, info = (
        execute(tasks, workers=workers, scheduler=scheduler, progress=progress)
        if tasks
        else ([], {"backend": "none", "workers": 0})
    )
    for command_, f, h, o in unreadable:
        rows.append(
            {"file": f, "sha256": "", "command": command_, "options": opt_key, "error": f"{f}: {h}", "warnings": ""}
        )
    new = pd.DataFrame(rows)
    if keep_old is not None and len(keep_old):
        new_files = set(new["file"]) if len(new) else set()
        keep_old = keep_old[~keep_old["file"].isin(new_files)]
        df = pd.concat([keep_old.drop(columns=["outliers"], errors="ignore"), new], ignore_index=True, sort=False)
    else:
        df = new
    if not len(df):
        raise GyroInputError("no results to write")
    if "error" not in df:
        df["error"] = ""
    df["error"] = df["error"].fillna("")
    front = ["file", "sha256", "command", "options", "error", "warnings"]
    df = df[[c for c in front if c in df.columns] + [c for c in df.columns if c not in front]]
    this = df["command"] == command
    outliers = mark_outliers(df.loc[this].copy(), command)
    df["outliers"] = ""
    for o in outliers:
        i = df.index[this & (df["file"] == o["file"])]
        df.loc[i, "outliers"] = [";".join(filter(None, [str(v), o["metric"]])) for v in df.loc[i, "outliers"]]
    write_table(df, table)
    if plot:
        plot_fleet(df.loc[this], command, plot)
    failed = df.loc[this & (df["error"] != "") & df["file"].isin(inputs), ["file", "error"]]
    return {
        "command": command,
        "options": options,
        "table": table,
        "plot": plot,
        "n_inputs": len(inputs),
        "n_run": len(tasks) + len(unreadable),
        "n_skipped": len(inputs) - len(tasks) - len(unreadable),
        "n_failed": int(len(failed)),
        "failed": failed.to_dict("records"),
        "outliers": outliers,
        "backend": info["backend"],
        "workers": info["workers"],
    }


def default_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)
