"""Benchmark: blackbox parse rate (frames/s) of our reader beside orangebox alone (issue 16 item 6).

Same file, same run: (1) orangebox 0.4.0's own ``Parser.frames()`` loop, (2) our frame loop
(``gyrocore.blackbox.read_blackbox_logs``: orangebox's decoders + frame validation), (3) the whole
``read_blackbox`` (decode + SI conversion + metadata). Best of ``--repeat`` wall times, frames/s
and the ratio to orangebox alone.

    nice python bench/bench_blackbox.py [FILE.BBL] [--repeat 3]
"""

from __future__ import annotations

import argparse
import logging
import os
import platform
import time
import warnings
from pathlib import Path

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "betaflight_blackbox" / "better_tune.BBL"


def _best(fn, repeat):
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file", nargs="?", default=str(DEFAULT))
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    import orangebox

    from gyrocore import blackbox as bb

    logging.getLogger("orangebox").setLevel(logging.ERROR)

    def ob():
        p = orangebox.Parser.load(args.file)
        return sum(1 for _ in p.frames())

    def ours():
        return sum(lg.data.shape[0] for lg in bb.read_blackbox_logs(args.file))

    def full():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return bb.read_blackbox(args.file).n

    t_ob, n_ob = _best(ob, args.repeat)
    t_us, n_us = _best(ours, args.repeat)
    t_full, n_full = _best(full, args.repeat)
    print(f"file {args.file} ({os.path.getsize(args.file) / 2**20:.2f} MiB); python {platform.python_version()}, "
          f"orangebox {orangebox.__version__ if hasattr(orangebox, '__version__') else bb.ORANGEBOX_VERSION}; "
          f"load {os.getloadavg()[0]:.2f}; best of {args.repeat}")
    print(f"orangebox Parser.frames : {n_ob:7d} frames {t_ob:6.2f} s  {n_ob / t_ob:9.0f} frames/s  ratio 1.00")
    print(f"gyrocore frame loop     : {n_us:7d} frames {t_us:6.2f} s  {n_us / t_us:9.0f} frames/s  ratio {t_us / t_ob:.2f}")
    print(f"gyrocore read_blackbox  : {n_full:7d} frames {t_full:6.2f} s  {n_full / t_full:9.0f} frames/s  ratio {t_full / t_ob:.2f}")


if __name__ == "__main__":
    main()
