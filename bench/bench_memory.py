"""Memory: a one-hour 1 kHz recording processed end to end; peak RSS per stage.

Run: ``nice python bench/bench_memory.py [--duration-s 3600] [--rate-hz 1000] [--work DIR] [--json]``.

The recording (3.6 M samples, 15 columns: t, gyro, accel, temperature, reference rate and
attitude) is a still, level sensor warming up from 25 °C to 45 °C (τ = 10 min) with a
constant and thermal bias (:func:`gyrocore.effects.registry.deterministic`) and white rate noise from
an explicit ``np.random.Generator``. Every stage runs in its own subprocess; its peak
resident set size is that process's ``ru_maxrss`` from ``os.wait4`` (Linux: KiB), so the
figures are per stage, not cumulative. Stages:

``baseline``      python + numpy + ``gyrocore.data.recording`` only (the floor of every other figure)
``simulate``      ``gyroharness simulate thermal --duration-s 3600 --rate-hz 1000`` (MuJoCo rate
                  table + thermal model + synthetic gyro with every noise term, generated and
                  written chunk by chunk: sim.scenarios.simulate_stream)
``simulate_parquet`` the same to a Parquet file
``simulate_long`` the same for ``--long-duration-s`` (e.g. 36000: ten hours) to Parquet, run once
                  (not at the compare length): completes, and its peak tells bounded from O(N)
``simulate_<scenario>``, ``simulate_<scenario>_parquet`` the same for every registered scenario
                  (``sim/scenarios/*.toml``: hover, power_cycles, static, static_bumped, thermal,
                  turntable — the closed-loop hover flown block by block), to CSV /
                  Parquet; ``turntable`` is its own profile's length whatever the duration
``simulate_hover_long`` hover for ``--long-duration-s`` to Parquet, run once
``synth``         generate and write the CSV chunk by chunk (``write_csv_chunks``)
``read_whole``    ``read_csv`` of the whole file (the path every CLI command takes)
``read_chunks``   ``iter_csv_chunks`` with per-axis running sums (streaming)
``allan``         gyro columns gathered from chunks, ``allan_analysis`` on 3 × 3.6 M samples
``calibrate``     columns gathered from chunks, ``Calibrator(effects=bias,bias_thermal).fit``
``apply``         per chunk: remove the fitted effects, write the corrected CSV (streaming)
``attitude``      per chunk: ``integrate_gyro`` carried across chunks, error angle vs the
                  reference attitude, running final/RMS/max (streaming)
``cli_*``         every command that reads a recording, through ``gyroharness``: ``convert``
                  (to Parquet, streamed), ``bias`` (windows read back from disk a block at a
                  time), ``allan`` (one axis at a time), ``calibrate`` (fitted from disk a
                  window at a time), ``apply`` (streamed), ``loop`` (spilled; the residual loop
                  reads it back a window at a time: gyrocore.calib.stream.SpilledRecording)
``cli_loop_long`` ``loop`` on the synthetic recording of ``--long-duration-s`` (e.g. 36000: ten hours),
                  written to Parquet in ``WORK/long/`` first; ``--loop-args`` adds options (e.g.
                  ``--no-open-search``); run once: completes, and its peak
``imports_*``     only the modules that command loads (``gyrocore.cli`` + its modules + the
                  reader): what the command costs before it reads anything

``--format parquet`` writes and processes ``one_hour.parquet`` instead of the CSV (much faster to
generate at ten hours: no text formatting).

Every stage is run at two lengths (``--compare-duration-s``, default 10 min, and the full
hour); the growth of its peak between them, in bytes per sample, tells a *streaming* stage
(≈ 0: memory bounded by the chunk size, whatever the length) from one that holds whole
columns (O(N): e.g. 3 gyro columns = 24 B/sample at least).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

G_M_S2 = 9.80665
CHUNK_ROWS = 100_000
SEED = 0
# Still sensor: constant and thermal bias (order 2 in T − 25 °C), white noise density N.
B_RAD_S = np.array([0.010, -0.007, 0.004])
POLY_RAD_S = np.array([[2e-4, -3e-6], [-1.5e-4, 2e-6], [1e-4, 4e-6]])  # per °C, per °C²
N_RAD_PER_SQRT_S = 2e-4
T0_C = 25.0


#: Effects fitted by the calibrate stages, per source recording.
EFFECTS = {"synth": ("bias", "bias_thermal"), "sim": ("bias", "bias_thermal", "scale", "scale_thermal", "misalignment")}


def _temp_c(t_s: np.ndarray) -> np.ndarray:
    return T0_C + 20.0 * (1.0 - np.exp(-t_s / 600.0))


def _true_params() -> dict:
    return {
        "bias": {"b_rad_s": B_RAD_S},
        "bias_thermal": {"poly_rad_s": POLY_RAD_S, "t0_c": T0_C, "temp_min_c": -40.0, "temp_max_c": 85.0},
    }


# ---------------------------------------------------------------------------- stages (child side)
def stage_baseline(a) -> dict:
    import gyrocore.data.recording  # noqa: F401  (python + numpy + the data file module)

    return {}


def _chunks(a):
    from gyrocore.effects import registry as E
    from gyrocore.data.recording import Recording

    n = int(round(a.duration_s * a.rate_hz))
    n_chunks = math.ceil(n / CHUNK_ROWS)
    seeds = np.random.SeedSequence(SEED).spawn(n_chunks)
    sigma = N_RAD_PER_SQRT_S * math.sqrt(a.rate_hz)
    params = _true_params()
    for k in range(n_chunks):
        i0, i1 = k * CHUNK_ROWS, min(n, (k + 1) * CHUNK_ROWS)
        rng = np.random.default_rng(seeds[k])
        m = i1 - i0
        t = np.arange(i0, i1) / a.rate_hz
        T = _temp_c(t)
        zeros = np.zeros((m, 3))
        f = np.tile([0.0, 0.0, G_M_S2], (m, 1))
        inp = E.ModelInputs(t_s=t, omega_S_rad_s=zeros, f_S_m_s2=f, temp_c=T)
        gyro = E.deterministic(params, inp) + rng.normal(0.0, sigma, (m, 3))
        accel = f + rng.normal(0.0, 0.02, (m, 3))
        q = np.tile([1.0, 0.0, 0.0, 0.0], (m, 1))
        yield Recording(
            t_s=t,
            gyro_rad_s=gyro,
            accel_m_s2=accel,
            temp_c=T + rng.normal(0, 0.01, m),
            ref_rate_rad_s=zeros,
            ref_quat_wxyz=q,
            meta={"sensor": "bench_memory", "scenario": "static_thermal", "rate_hz": str(a.rate_hz)},
        )


def stage_synth(a) -> dict:
    from gyrocore.data.recording import write_chunks

    n = write_chunks(_chunks(a), a.csv)  # CSV or Parquet by the file name (--format)
    return {"rows": n, "csv_bytes": os.path.getsize(a.csv)}


#: What each command imports when it runs (``gyrocore.cli`` and the command modules are
#: loaded by every command; pyarrow.csv by every reader).
IMPORTS = {
    "imports_convert": ["gyrocore.readers.convert", "gyrocore.data.recording", "pyarrow.csv", "pyarrow.parquet"],
    "imports_bias": ["gyrocore.calib.bias", "gyrocore.readers.convert", "gyrocore.data.recording", "pyarrow.csv"],
    "imports_allan": ["gyrocore.noise.allan", "gyrocore.noise.gmwm", "gyrocore.data.recording", "pyarrow.csv"],
    "imports_calibrate": [
        "gyrocore.calibrator",
        "gyrocore.calib.lsq",
        "gyrocore.calib.thermal",
        "gyrocore.calib.stream",
        "gyrocore.readers.convert",
        "pyarrow.csv",
    ],
    "imports_apply": ["gyrocore.calibrator", "gyrocore.data.recording", "pyarrow.csv"],
    "imports_loop": [
        "gyrocore.loop.loop",
        "gyrocore.loop.search",
        "gyrocore.loop.lines",
        "gyrocore.loop.residual",
        "gyrocore.calibrator",
        "gyrocore.calib.lsq",
        "gyrocore.data.recording",
        "pyarrow.csv",
    ],
}


def _stage_imports(name):
    def run(a) -> dict:
        import importlib

        import experiments.cli  # noqa: F401  (gyrocore.cli, click)
        from gyrocore.cli import build_group

        build_group(["experiments.commands"])  # imports every command module, as `gyroharness` does
        for m in IMPORTS[name]:
            importlib.import_module(m)
        return {"modules": IMPORTS[name]}

    return run


def stage_read_whole(a) -> dict:
    from gyrocore.data.recording import read_recording

    rec = read_recording(a.csv)
    return {"rows": rec.n}


def stage_read_chunks(a) -> dict:
    from gyrocore.data.recording import iter_chunks

    n, s = 0, np.zeros(3)
    for ch in iter_chunks(a.csv, rows=CHUNK_ROWS):
        n += ch.n
        s += ch.gyro_rad_s.sum(axis=0)
    return {"rows": n, "mean_gyro_rad_s": (s / n).tolist()}


def _gather(a, *, full: bool):
    """The recording from chunks, keeping only the columns a stage needs (no text held).

    The columns are preallocated for the known length and filled chunk by chunk, so the
    gather peaks at the columns themselves (not at chunk lists plus their concatenation)."""
    from gyrocore.data.recording import Recording, iter_chunks

    n = int(round(a.duration_s * a.rate_hz))
    shapes = {"t": (n,), "g": (n, 3)}
    if full:
        shapes.update({"a": (n, 3), "T": (n,), "r": (n, 3)})
    cat = {k: np.empty(s) for k, s in shapes.items()}
    i0 = 0
    meta = {}
    for ch in iter_chunks(a.csv, rows=CHUNK_ROWS):
        i1 = i0 + ch.n
        if i1 > n:
            raise SystemExit(f"{a.csv}: more than the expected {n} rows")
        cat["t"][i0:i1] = ch.t_s
        cat["g"][i0:i1] = ch.gyro_rad_s
        if full:
            cat["a"][i0:i1] = ch.accel_m_s2
            cat["T"][i0:i1] = ch.temp_c
            cat["r"][i0:i1] = ch.ref_rate_rad_s
        meta = ch.meta
        i0 = i1
    if i0 != n:
        raise SystemExit(f"{a.csv}: {i0} rows, expected {n}")
    return Recording(
        t_s=cat["t"],
        gyro_rad_s=cat["g"],
        accel_m_s2=cat.get("a"),
        temp_c=cat.get("T"),
        ref_rate_rad_s=cat.get("r"),
        meta=meta,
    )


def stage_allan(a) -> dict:
    from gyrocore.noise.allan import allan_analysis

    res = allan_analysis(_gather(a, full=False))
    return {"arw_rad_per_sqrt_s": {k: v.all_terms()["arw_rad_per_sqrt_s"] for k, v in res.axes.items()}}


def stage_calibrate(a) -> dict:
    from gyrocore.calibrator import Calibrator
    from gyrocore.calib.params import save_params

    rec = _gather(a, full=True)
    res = Calibrator(effects=EFFECTS[a.source]).fit(rec)
    save_params(res, a.params)
    return {
        "effects": list(res.effects),
        "bias_rad_s": np.asarray(res.params["bias"]["b_rad_s"]).tolist(),
        "thermal_order": {k: int(v) for k, v in res.thermal_order.items()},
        "residual_rms_rad_s": np.asarray(res.residual_rms_rad_s).tolist(),
    }


def stage_apply(a) -> dict:
    import warnings

    from gyrocore.calib.params import load_params
    from gyrocore.data.recording import iter_chunks, write_chunks

    cal = load_params(a.params)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # per-chunk range notes
        n = write_chunks((cal.apply(ch) for ch in iter_chunks(a.csv, rows=CHUNK_ROWS)), a.corrected)
    return {"rows": n}


def stage_attitude(a) -> dict:
    """Streaming score of the corrected file: integrate each chunk from the attitude carried
    over from the previous one (the chunk starts at the previous chunk's last sample, so the
    zero-order-hold step across the boundary is included exactly once)."""
    from gyrocore.attitude import error_angle_rad, integrate_gyro
    from gyrocore.data.recording import iter_chunks

    q_carry = t_last = w_last = None
    n = 0
    sum_sq = 0.0
    err_max = 0.0
    err_final = math.nan
    t_first = None
    path = a.corrected if os.path.exists(a.corrected) else a.csv  # raw when apply did not run
    for ch in iter_chunks(path, rows=CHUNK_ROWS):
        t, w, q_ref = ch.t_s, ch.gyro_rad_s, ch.ref_quat_wxyz
        if q_carry is None:
            q = integrate_gyro(t, w, q0_wxyz=q_ref[0])
            t_first = float(t[0])
        else:
            q = integrate_gyro(np.r_[t_last, t], np.vstack([w_last, w]), q0_wxyz=q_carry)[1:]
        e = error_angle_rad(q, q_ref)
        sum_sq += float(np.sum(e * e))
        err_max = max(err_max, float(np.max(e)))
        err_final = float(e[-1])
        n += e.size
        q_carry, t_last, w_last = q[-1], t[-1:], w[-1:]
    dur = float(t_last[0] - t_first)
    return {
        "scored_file": os.path.basename(path),
        "rows": n,
        "final_error_deg": math.degrees(err_final),
        "rms_error_deg": math.degrees(math.sqrt(sum_sq / n)),
        "max_error_deg": math.degrees(err_max),
        "drift_deg_per_min": math.degrees(err_final) / (dur / 60.0),
    }


STAGES = {
    "baseline": stage_baseline,
    "synth": stage_synth,
    "read_whole": stage_read_whole,
    "read_chunks": stage_read_chunks,
    "allan": stage_allan,
    "calibrate": stage_calibrate,
    "apply": stage_apply,
    "attitude": stage_attitude,
    **{k: _stage_imports(k) for k in IMPORTS},
}
STREAMING = {"baseline", "synth", "read_chunks", "apply", "attitude", *IMPORTS}
#: How each command holds the recording.
CLI_DESIGN = {
    "cli_convert": "CLI, streamed (chunks)",
    "cli_bias": "CLI, spilled; windows read back a block at a time",
    "cli_allan": "CLI, one axis at a time",
    "cli_calibrate": "CLI, spilled; fitted a window at a time",
    "cli_apply": "CLI, streamed (chunks + context)",
    "cli_loop": "CLI, spilled; residual loop a window at a time",
    "cli_loop_long": "CLI, spilled; residual loop a window at a time (--long-duration-s, Parquet)",
}


# ---------------------------------------------------------------------------- parent side
def _run_child(argv: list[str]) -> tuple[int, float, int, str]:
    """Run ``argv``; return (exit status, wall s, peak RSS in bytes, stdout); its CPU seconds
    (user + system) in ``_run_child.cpu_s``."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        p = subprocess.Popen(argv, stdout=out, stderr=err)
        _pid, status, ru = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t0
        out.seek(0)
        err.seek(0)
        text = out.read().decode()
        if p.returncode != 0:
            tail = err.read().decode().strip().splitlines()[-3:]
            text = " | ".join(tail)
    _run_child.cpu_s = float(ru.ru_utime + ru.ru_stime)
    return p.returncode, wall, int(ru.ru_maxrss) * 1024, text


#: Registered scenarios (the TOML files of sim/scenarios; read without importing sim).
SCENARIO_NAMES = sorted(p.stem for p in (Path(__file__).resolve().parent.parent / "sim" / "scenarios").glob("*.toml"))


def _run_stages(a, duration_s: float, work: Path, names: list[str], *, quiet: bool) -> list[dict]:
    """Every stage at one recording length; rows with peak RSS and wall time."""
    n = int(round(duration_s * a.rate_hz))
    csv_path = Path(a.csv)  # one_hour.csv, or one_hour.parquet with --format parquet
    # the checkout this script belongs to (PYTHONPATH), not whatever `gyroharness` is installed
    exe = [sys.executable, "-m", "experiments.cli"]
    common = [
        "--duration-s",
        str(duration_s),
        "--rate-hz",
        str(a.rate_hz),
        "--work",
        str(work),
        "--source",
        a.source,
        "--format",
        a.format,
    ]
    sim_path = csv_path if a.source == "sim" else work / "sim_thermal.csv"
    cli = {
        "simulate": [
            *exe,
            "simulate",
            "thermal",
            "--duration-s",
            str(duration_s),
            "--rate-hz",
            str(a.rate_hz),
            "--seed",
            str(SEED),
            "-o",
            str(sim_path),
            "--force",
            "--no-progress",
            "--json",
        ],
        "simulate_parquet": [
            *exe,
            "simulate",
            "thermal",
            "--duration-s",
            str(duration_s),
            "--rate-hz",
            str(a.rate_hz),
            "--seed",
            str(SEED),
            "-o",
            str(work / "sim_thermal.parquet"),
            "--force",
            "--no-progress",
            "--json",
        ],
        "simulate_long": [
            *exe,
            "simulate",
            "thermal",
            "--duration-s",
            str(a.long_duration_s),
            "--rate-hz",
            str(a.rate_hz),
            "--seed",
            str(SEED),
            "-o",
            str(work / "sim_thermal_long.parquet"),
            "--force",
            "--no-progress",
            "--json",
        ],
        "simulate_hover_long": [
            *exe,
            "simulate",
            "hover",
            "--duration-s",
            str(a.long_duration_s),
            "--rate-hz",
            str(a.rate_hz),
            "--seed",
            str(SEED),
            "-o",
            str(work / "sim_hover_long.parquet"),
            "--force",
            "--no-progress",
            "--json",
        ],
        **{
            f"simulate_{sc}{suf}": [
                *exe,
                "simulate",
                sc,
                "--duration-s",
                str(duration_s),
                "--rate-hz",
                str(a.rate_hz),
                "--seed",
                str(SEED),
                "-o",
                str(work / f"scn_{sc}{ext}"),
                "--force",
                "--no-progress",
                "--json",
            ]
            for sc in SCENARIO_NAMES
            for suf, ext in (("", ".csv"), ("_parquet", ".parquet"))
        },
        "cli_convert": [*exe, "convert", str(csv_path), "-o", str(work / "cli_converted.parquet"), "--force", "--json"],
        "cli_bias": [*exe, "bias", str(csv_path), "--json"],
        "cli_loop": [*exe, "loop", str(csv_path), "--effects", ",".join(EFFECTS[a.source]), "--json"],
        "cli_allan": [*exe, "allan", str(csv_path), "--json"],
        "cli_calibrate": [
            *exe,
            "calibrate",
            str(csv_path),
            "--effects",
            ",".join(EFFECTS[a.source]),
            "-o",
            str(work / "cli_params.json"),
            "--force",
            "--json",
        ],
        "cli_apply": [
            *exe,
            "apply",
            str(csv_path),
            "--params",
            str(work / "cli_params.json"),
            "-o",
            str(work / "cli_corrected.csv"),
            "--force",
            "--json",
        ],
    }
    rows = []
    for name in names:
        if name == "synth" and a.source == "sim":
            continue
        long = name in ("simulate_long", "simulate_hover_long", "cli_loop_long")
        if long and (not a.long_duration_s or duration_s != a.duration_s):
            continue  # once, at its own length
        if name == "cli_loop_long":
            # the synthetic recording of --long-duration-s, to Parquet (WORK/long/, kept for reruns)
            long_dir = work / "long"
            long_dir.mkdir(exist_ok=True)
            long_file = long_dir / "one_hour.parquet"
            if not long_file.exists():
                rc, _, _, out = _run_child(
                    [
                        sys.executable,
                        __file__,
                        "--stage",
                        "synth",
                        "--duration-s",
                        str(a.long_duration_s),
                        "--rate-hz",
                        str(a.rate_hz),
                        "--work",
                        str(long_dir),
                        "--format",
                        "parquet",
                    ]
                )
                if rc != 0:
                    raise SystemExit(f"cli_loop_long: writing the long recording failed: {out}")
            cli[name] = [
                *exe,
                "loop",
                str(long_file),
                "--effects",
                ",".join(EFFECTS["synth"]),
                "--json",
                *getattr(a, "loop_args", "").split(),
            ]
        argv_c = cli.get(name) or [sys.executable, __file__, "--stage", name, *common]
        rc, wall, rss, out = _run_child(argv_c)
        info = {}
        if rc == 0 and name in STAGES:
            info = json.loads(out.strip().splitlines()[-1])
        elif rc == 0 and name.startswith("simulate"):
            doc = json.loads(out)
            info = {k: doc.get(k) for k in ("n_samples", "rate_hz", "duration_s", "effects")}
        elif rc == 0 and name.startswith("cli_loop"):
            doc = json.loads(out)
            info = {
                "found": [f["effect"] for f in doc["found"]],
                "unexplained": [u["effect"] for u in doc["unexplained"]],
                "n_windows": doc["n_windows"],
            }
        if name.startswith("simulate") and name != "simulate":
            # the files of the other simulate stages are not read again (1 h at 1 kHz: 1.1 GB of CSV)
            Path(cli[name][cli[name].index("-o") + 1]).unlink(missing_ok=True)
        samples = int(round(a.long_duration_s * a.rate_hz)) if long else n
        if rc == 0 and isinstance(info, dict) and info.get("n_samples"):
            samples = int(info["n_samples"])  # turntable: its profile's own length
        rows.append(
            {
                "stage": name,
                "samples": samples,
                "exit": rc,
                "wall_s": wall,
                "cpu_s": _run_child.cpu_s,
                "peak_rss_bytes": rss,
                "result": info if rc == 0 else out,
            }
        )
        if not quiet:
            print(
                f"  [{samples / a.rate_hz:g} s] {name:<22s} exit {rc}  wall {wall:7.1f} s  CPU {_run_child.cpu_s:7.1f} s  peak RSS {rss / 2**20:8.1f} MiB"
                + ("" if rc == 0 else f"  FAILED: {out[:300]}"),
                flush=True,
            )
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration-s", type=float, default=3600.0)
    ap.add_argument(
        "--compare-duration-s",
        type=float,
        default=600.0,
        help="a shorter run of every stage; the peak's growth between the two lengths, per "
        "sample, tells streaming (≈ 0) from whole-column stages (0 = skip)",
    )
    ap.add_argument("--rate-hz", type=float, default=1000.0)
    ap.add_argument(
        "--long-duration-s",
        type=float,
        default=0.0,
        help="stage simulate_long: simulate this long to Parquet once (e.g. 36000; 0 = skip)",
    )
    ap.add_argument(
        "--loop-args",
        default="",
        help="extra options of the cli_loop_long stage, e.g. '--no-open-search' (catalogue only)",
    )
    ap.add_argument("--work", default=None, help="folder for the CSV files (default: a temporary folder, removed)")
    ap.add_argument(
        "--stages",
        default="baseline,simulate,"
        + ",".join(list(STAGES)[1:])
        + ",cli_convert,cli_bias,cli_allan,cli_calibrate,cli_apply,cli_loop",
    )
    ap.add_argument(
        "--source",
        choices=("synth", "sim"),
        default="synth",
        help="recording processed by the later stages: 'synth' (still, thermal; default) or "
        "'sim' (the simulated thermal rate-table run of the 'simulate' stage)",
    )
    ap.add_argument(
        "--format",
        choices=("csv", "parquet"),
        default="csv",
        help="data file the stages write and read (parquet: no text formatting, for long runs)",
    )
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--stage", help=argparse.SUPPRESS)  # child mode
    a = ap.parse_args(argv)
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="bench_memory_"))
    a.csv = str(work / ("one_hour.parquet" if a.format == "parquet" else "one_hour.csv"))
    a.params = str(work / "params.json")
    a.corrected = str(work / "corrected.csv")
    if a.stage:  # child: run one stage, print its JSON
        print(json.dumps(STAGES[a.stage](a)))
        return 0

    work.mkdir(parents=True, exist_ok=True)
    names = [s.strip() for s in a.stages.split(",") if s.strip()]
    n = int(round(a.duration_s * a.rate_hz))
    try:
        small = []
        if a.compare_duration_s and a.compare_duration_s < a.duration_s:
            small = _run_stages(a, a.compare_duration_s, work, names, quiet=a.json)
        big = _run_stages(a, a.duration_s, work, names, quiet=a.json)
        csv_bytes = os.path.getsize(a.csv) if os.path.exists(a.csv) else None
    finally:
        if not a.work:
            shutil.rmtree(work, ignore_errors=True)
    by_small = {r["stage"]: r for r in small}
    base = next((r["peak_rss_bytes"] for r in big if r["stage"] == "baseline"), 0)
    for r in big:
        r["above_baseline_bytes"] = r["peak_rss_bytes"] - base
        s = by_small.get(r["stage"])
        if s is not None and s["exit"] == 0 and r["exit"] == 0:
            if r["samples"] != s["samples"]:
                r["growth_bytes_per_sample"] = (r["peak_rss_bytes"] - s["peak_rss_bytes"]) / (
                    r["samples"] - s["samples"]
                )
    summary = {
        "samples": n,
        "rate_hz": a.rate_hz,
        "duration_s": a.duration_s,
        "compare_duration_s": a.compare_duration_s or None,
        "data_float64_bytes": n * 15 * 8,
        "csv_bytes": csv_bytes,
        "chunk_rows": CHUNK_ROWS,
        "stages": big,
        "stages_short": small,
    }
    if a.json:
        print(json.dumps(summary, indent=1))
    else:
        print(
            f"{n} samples ({a.duration_s:g} s at {a.rate_hz:g} Hz); 15 float64 columns = {n * 120 / 2**20:.0f} MiB"
            + (f"; CSV {csv_bytes / 2**20:.0f} MiB" if csv_bytes else "")
            + f"; chunks of {CHUNK_ROWS} rows"
        )
        print(f"{'stage':<22s} {'peak RSS MiB':>12s} {'growth B/sample':>16s}  {'wall s':>7s}  {'CPU s':>7s}  design")
        for r in big:
            g = r.get("growth_bytes_per_sample")
            design = (
                CLI_DESIGN.get(r["stage"], "CLI")
                if r["stage"].startswith("cli_")
                else (f"CLI, chunked ({r['samples']} samples)")
                if r["stage"].startswith("simulate")
                else ("streaming" if r["stage"] in STREAMING else "whole columns")
            )
            print(
                f"{r['stage']:<22s} {r['peak_rss_bytes'] / 2**20:12.1f} {'' if g is None else f'{g:16.1f}'}"
                f"  {r['wall_s']:7.1f}  {r['cpu_s']:7.1f}  {design}" + ("" if r["exit"] == 0 else "  FAILED")
            )
    return 0 if all(r["exit"] == 0 for r in big + small) else 1


if __name__ == "__main__":
    sys.exit(main())
