"""A short fuzz run of the readers (bench/fuzz_reader.py, hypothesis engine) must find no crash.

The long runs (atheris, 10^5 inputs) are in bench/; this keeps a few hundred mutated inputs
of every seed format in the default suite so a regression in a reader shows up at once.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import warnings

from gyrocore.errors import RepairWarning

BENCH = Path(__file__).resolve().parents[2] / "bench" / "fuzz_reader.py"


def _load():
    spec = importlib.util.spec_from_file_location("fuzz_reader", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_seeds_are_valid_inputs(tmp_path):
    """Each seed is accepted by the reader it was written for (so mutations start deep)."""
    from gyrocore.readers import convert as cv
    from gyrocore.data import recording as rc
    from gyrocore.data.segments import read_segments

    fz = _load()
    readers = [
        rc.read_csv,
        rc.read_csv,
        rc.read_csv,
        read_segments,
        read_segments,
        cv.read_tomisuarez2,
        cv.read_imucal,
        cv.read_imucal_annotated,
        cv.read_fusion,
    ]
    assert len(readers) == len(fz.SEEDS)
    for i, (seed, reader) in enumerate(zip(fz.SEEDS, readers)):
        p = tmp_path / f"seed{i}.csv"
        p.write_bytes(seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RepairWarning)  # seed 1: a NaN row; seed 4: an older segments layout
            rec = reader(p)
        assert rec is not None


def test_short_fuzz_run_finds_no_crash(tmp_path):
    fz = _load()
    h = fz.Harness(tmp_path / "crashes")
    try:
        fz.run_hypothesis(h, runs=300, seed=12345)
    finally:
        h.cleanup()
    assert h.n_inputs >= 250  # hypothesis may stop a little early on duplicates
    assert h.n_crashes == 0, h.sites
