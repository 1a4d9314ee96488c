"""Reading a data file: our reader against pandas' C parser on the same file, side by side.

Run: ``nice python bench/bench_read.py [--rows 1000000] [--repeat 3] [--work DIR] [--json]``.

The file is a DESIGN.md data file with all 15 columns (t, gyro, accel, temperature,
reference rate and attitude) written by :func:`gyrocore.data.recording.write_csv_chunks`
(``%.17g``, as every file the project writes). Timed, interleaved, best of ``--repeat``:

``pandas``        ``pandas.read_csv(path, comment="#")`` — the plain C parser into a DataFrame
                  (default float precision; no checks): the reference.
``read_csv``      :func:`gyrocore.data.recording.read_csv`: parse (Arrow C++), column groups, SI
                  units, NaN/backwards-time repairs and every plausibility check (gaps,
                  units, saturation) — what every command does.
``read_csv_raw``  the same with ``checks=False``.
``iter_chunks``   :func:`gyrocore.data.recording.iter_csv_chunks` over the whole file (200 000 rows).
``parquet``       :func:`gyrocore.data.recording.read_parquet` of the same data as Parquet.

The ratio printed is each time over the ``pandas`` time (goal for ``read_csv``: ≤ 1.5).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def make_file(path: Path, rows: int, chunk: int = 200_000) -> None:
    from gyrocore.data.recording import Recording, write_chunks

    rng = np.random.default_rng(0)

    def gen():
        for i0 in range(0, rows, chunk):
            m = min(chunk, rows - i0)
            t = np.arange(i0, i0 + m) / 1000.0
            q = rng.normal(size=(m, 4))
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            yield Recording(
                t_s=t,
                gyro_rad_s=rng.normal(0, 0.01, (m, 3)) + [0.01, -0.02, 0.003],
                accel_m_s2=rng.normal(0, 0.05, (m, 3)) + [0, 0, 9.80665],
                temp_c=25.0 + rng.normal(0, 0.01, m),
                ref_rate_rad_s=rng.normal(0, 0.5, (m, 3)),
                ref_quat_wxyz=q,
                meta={"sensor": "bench_read", "rate_hz": "1000"},
            )

    write_chunks(gen(), path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--work", default=None)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    import pandas as pd

    from gyrocore.data.recording import iter_csv_chunks, read_csv, read_parquet, write_parquet_chunks

    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="bench_read_"))
    work.mkdir(parents=True, exist_ok=True)
    csv = work / "bench_read.csv"
    pq = work / "bench_read.parquet"
    try:
        make_file(csv, a.rows)
        write_parquet_chunks(iter_csv_chunks(csv), pq)

        def chunks():
            n = 0
            for c in iter_csv_chunks(csv):
                n += c.n
            return n

        runs = {
            "pandas": lambda: pd.read_csv(csv, comment="#"),
            "read_csv": lambda: read_csv(csv),
            "read_csv_raw": lambda: read_csv(csv, checks=False),
            "iter_chunks": chunks,
            "parquet": lambda: read_parquet(pq),
        }
        best = {k: math.inf for k in runs}
        cpu = {k: math.inf for k in runs}
        for _ in range(a.repeat):  # interleaved: the load of the shared machine hits every reader alike
            for k, fn in runs.items():
                c0, t0 = time.process_time(), time.perf_counter()
                out = fn()
                dt, dc = time.perf_counter() - t0, time.process_time() - c0
                del out
                best[k] = min(best[k], dt)
                cpu[k] = min(cpu[k], dc)
        # bit-exact check: every value equals Python's correctly rounded float() of its text
        # (on the first 20 000 rows), and the whole file equals pandas' parse
        rec = read_csv(csv)
        df = pd.read_csv(csv, comment="#")
        names = ["t_s", "gyro_x_rad_s", "gyro_y_rad_s", "gyro_z_rad_s"]
        ours = np.column_stack([rec.t_s, rec.gyro_rad_s])
        exact_pandas = bool(np.array_equal(ours, df[names].to_numpy()))
        with open(csv) as fh:
            lines = [ln for ln in fh if not ln.startswith("#")][1:20_001]
        ref = np.array([[float(v) for v in ln.split(",")[:4]] for ln in lines])
        exact = bool(np.array_equal(ours[: len(ref)], ref)) and exact_pandas
        summary = {
            "rows": a.rows,
            "csv_bytes": os.path.getsize(csv),
            "parquet_bytes": os.path.getsize(pq),
            "best_wall_s": best,
            "best_cpu_s": cpu,
            "ratio_to_pandas": {k: best[k] / best["pandas"] for k in runs},
            "bit_exact": exact,
            "load": os.getloadavg(),
        }
    finally:
        if not a.work:
            shutil.rmtree(work, ignore_errors=True)
    if a.json:
        print(json.dumps(summary, indent=1))
    else:
        print(
            f"{a.rows} rows x 15 columns, CSV {summary['csv_bytes'] / 2**20:.0f} MiB, Parquet "
            f"{summary['parquet_bytes'] / 2**20:.0f} MiB; best of {a.repeat}; load {summary['load'][0]:.2f}"
        )
        print(f"{'reader':<14s} {'wall s':>8s} {'CPU s':>8s} {'/ pandas':>9s}")
        for k in runs:
            print(f"{k:<14s} {best[k]:8.3f} {cpu[k]:8.3f} {summary['ratio_to_pandas'][k]:9.2f}")
        print(f"values identical to float() of the text (20 000 rows) and to pandas (all rows): {exact}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
