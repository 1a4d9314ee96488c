"""Fuzz the data-file readers: any bytes must give a Recording, or one-line GyroInputError.

Targets, run on every input (written to a temporary file): ``read_csv``, ``iter_csv_chunks``
(7-row chunks, to cross chunk boundaries), ``read_segments`` (the segments file, current and older
layouts) and the text-format
converters (tomisuarez2, imucal session, imucal annotated, x-io Fusion). A *crash* is any
other exception, or an error message that is empty or spans several lines. Crashing inputs
are saved to ``--crash-dir`` and counted; the run continues.

Engines: ``atheris`` (coverage-guided libFuzzer, ``pip install atheris``) or ``hypothesis``
(random + seed mutations; no extra package). Seeds: small valid files of every format, so
mutations reach the parsing code past the header checks.

Usage::

    python bench/fuzz_reader.py --engine atheris --runs 200000
    python bench/fuzz_reader.py --engine hypothesis --runs 20000

Prints one summary line: engine, inputs tried, crashes, distinct crash sites, seconds.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import tempfile
import time
import traceback
import warnings
from pathlib import Path

SEEDS = [
    b"# sensor: x\n# rate_hz: 100\nt_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n0,0.1,0.2,0.3\n0.01,0.1,0.2,0.3\n0.02,1e-3,-2,3\n",
    b"t_s,gyro_x_deg_s,gyro_y_deg_s,gyro_z_deg_s,accel_x_g,accel_y_g,accel_z_g,temp_c\n0,1,2,3,0,0,1,25\n0.01,1,2,3,0,0,1,25\n0.03,nan,2,3,0,0,1,25\n",
    b"t_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s,ref_qw,ref_qx,ref_qy,ref_qz,ref_x_rad_s,ref_y_rad_s,ref_z_rad_s,flag\n"
    b"0,0,0,0,1,0,0,0,0,0,0,1\n0.005,0,0,0,nan,nan,nan,nan,0,0,0,0\n0.01,4.3633,4.3633,4.3633,1,0,0,0,0,0,0,1\n0.015,4.3633,4.3633,4.3633,1,0,0,0,0,0,0,1\n",
    b't_start_s,t_end_s,kind,angle_x_deg,angle_y_deg,angle_z_deg,label\n0.5,2.5,rotation,720,0,0,"two turns, x"\n'
    b"3,4,still,,,,\n4.5,6,rotation,0,-90.5,1e-3,\n",
    b"t_start_s,t_end_s,axis,angle_deg\n0.5,2.5,x,720\n3,4,z,-360\n",
    b"Fs,100\nLogging Type,1\nInitialization time,-1\nWaiting time,-1\nax,ay,az,gx,gy,gz\n748,244,15708,-480,193,-83\n724,56,14772,-439,189,-56\n",
    b"n_samples,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z\n0,-0.61,-0.30,0.06,10.33,-0.57,0.51\n1,-0.54,-0.36,0.12,10.33,-0.56,0.50\n",
    b"part,samples,acc_x,acc_y,acc_z,gyr_x,gyr_y,gyr_z\nx_a,1,-2052.0,-28.0,-73.0,1.0,0.0,-5.0\nx_p,0,2027.0,-75.0,3.0,5.0,-6.0,-4.0\n",
    b"Time (s),Gyroscope X (deg/s),Gyroscope Y (deg/s),Gyroscope Z (deg/s),Accelerometer X (g),Accelerometer Y (g),"
    b"Accelerometer Z (g),Magnetometer X (uT),Magnetometer Y (uT),Magnetometer Z (uT)\n0,0.01,-0.15,0.10,0.001,-0.02,0.99,15.3,0.43,-41.0\n"
    b"0.01,0.01,-0.33,0.04,0.001,-0.01,0.99,15.3,-0.3,-41.0\n",
]


class Harness:
    """Runs every target on one input and classifies the outcome."""

    def __init__(self, crash_dir: Path) -> None:
        from gyrocore.readers import convert as cv
        from gyrocore.data import recording as rc
        from gyrocore.data.segments import read_segments
        from gyrocore.errors import GyroInputError

        self.GyroInputError = GyroInputError
        self.targets = [
            ("read_csv", rc.read_csv),
            ("iter_csv_chunks", lambda p: list(rc.iter_csv_chunks(p, rows=7))),
            ("read_segments", read_segments),
            ("read_tomisuarez2", cv.read_tomisuarez2),
            ("read_imucal", cv.read_imucal),
            ("read_imucal_annotated", cv.read_imucal_annotated),
            ("read_fusion", cv.read_fusion),
        ]
        self.tmpdir = Path(tempfile.mkdtemp(prefix="fuzz_reader_"))
        self.path = self.tmpdir / "input.csv"
        self.crash_dir = crash_dir
        self.n_inputs = 0
        self.n_crashes = 0
        self.sites: dict[str, int] = {}

    def one(self, data: bytes) -> None:
        self.n_inputs += 1
        self.path.write_bytes(data)
        for name, fn in self.targets:
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    fn(self.path)
            except self.GyroInputError as exc:
                msg = str(exc)
                if not msg or "\n" in msg:
                    self._crash(name, data, f"bad message {msg!r}")
            except Exception as exc:  # noqa: BLE001 — the point is to catch everything
                tb = traceback.extract_tb(exc.__traceback__)[-1]
                self._crash(name, data, f"{type(exc).__name__} at {Path(tb.filename).name}:{tb.lineno}: {exc}")

    def _crash(self, target: str, data: bytes, what: str) -> None:
        self.n_crashes += 1
        site = f"{target}: {what.split(': ')[0]}"
        self.sites[site] = self.sites.get(site, 0) + 1
        if self.sites[site] <= 3:
            self.crash_dir.mkdir(parents=True, exist_ok=True)
            h = hashlib.sha1(data).hexdigest()[:12]
            (self.crash_dir / f"crash-{h}.bin").write_bytes(data)
            print(f"CRASH {target}: {what[:200]}", file=sys.stderr)

    def cleanup(self) -> None:
        import shutil

        shutil.rmtree(self.tmpdir, ignore_errors=True)

    def summary(self, engine: str, seconds: float) -> str:
        return (
            f"fuzz_reader engine={engine} inputs={self.n_inputs} targets_per_input={len(self.targets)} "
            f"crashes={self.n_crashes} distinct_sites={len(self.sites)} seconds={seconds:.0f}"
        )


def run_hypothesis(h: Harness, runs: int, seed: int) -> None:
    from hypothesis import HealthCheck, given, settings, strategies as st
    from hypothesis import seed as hseed

    def mutate(args):
        base, edits = args
        b = bytearray(base)
        for pos, val, kind in edits:
            if not b:
                b.append(val)
                continue
            i = pos % len(b)
            if kind == 0:
                b[i] = val
            elif kind == 1:
                b.insert(i, val)
            elif kind == 2:
                del b[i]
            else:
                b[i:i] = b[i : i + 1 + val % 40]  # duplicate a run (rows, fields)
        return bytes(b)

    edit = st.tuples(st.integers(0, 10**6), st.integers(0, 255), st.integers(0, 3))
    strat = st.one_of(
        st.binary(max_size=600),
        st.tuples(st.sampled_from(SEEDS), st.lists(edit, max_size=12)).map(mutate),
    )

    @hseed(seed)
    @settings(max_examples=runs, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(strat)
    def fuzz(data):
        h.one(data)

    fuzz()


def run_atheris(h: Harness, runs: int, seed: int, t0: float) -> None:
    import atheris

    corpus = h.tmpdir / "corpus"
    corpus.mkdir()
    for i, s in enumerate(SEEDS):
        (corpus / f"seed{i}").write_bytes(s)

    def test_one(data: bytes) -> None:
        h.one(data)
        if h.n_inputs >= runs:
            print(h.summary("atheris", time.time() - t0), flush=True)
            h.cleanup()
            os._exit(0)

    atheris.Setup([sys.argv[0], f"-seed={seed}", "-max_len=2048", str(corpus)], test_one)
    atheris.Fuzz()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--engine", choices=["atheris", "hypothesis"], default="atheris")
    ap.add_argument("--runs", type=int, default=20000, help="inputs to try")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--crash-dir", type=Path, default=Path("out/fuzz_crashes"))
    args = ap.parse_args()
    t0 = time.time()
    if args.engine == "atheris":
        import atheris

        with atheris.instrument_imports():
            import gyrocore.readers.convert  # noqa: F401
            import gyrocore.data.recording  # noqa: F401
        h = Harness(args.crash_dir)
        run_atheris(h, args.runs, args.seed, t0)
    else:
        h = Harness(args.crash_dir)
        try:
            run_hypothesis(h, args.runs, args.seed)
        finally:
            h.cleanup()
        print(h.summary("hypothesis", time.time() - t0), flush=True)


if __name__ == "__main__":
    main()
