"""Benchmark: blackbox parse rate (frames/s) of our reader beside orangebox alone.

For each file, in one run: (1) orangebox 0.4.0's own ``Parser.frames()`` loop over every log of
the file, (2) our frame loop (``gyrocore.readers.blackbox.read_blackbox_logs``: orangebox's decoders +
frame validation), (3) the whole ``read_blackbox`` (decode + SI conversion + metadata). Best of
``--repeat`` wall times, frames/s and the ratio to orangebox alone. Default files: the shared
Betaflight 3.1.5 log, the Betaflight 4.2.0 / INAV 9.0.1 logs of ``../shared/data/blackbox_public``
when present, and the ArduPilot DataFlash fixture (tests/data/dataflash): for a DataFlash file,
(1) pymavlink's DFReader reading every message, (2) pymavlink reading only the messages
``gyrocore.readers.dataflash`` needs, (3) the whole ``read_dataflash`` (IMU stream) — messages/s.

    nice python bench/bench_blackbox.py [FILE ...] [--repeat 3]
"""

from __future__ import annotations

import argparse
import logging
import os
import platform
import time
import warnings
from pathlib import Path

from experiments.datadir import DEFAULT_DATA_DIR, shared_data_dir

DATA = shared_data_dir() or DEFAULT_DATA_DIR  # GYROHARNESS_DATA, else ../shared/data
DEFAULT = [
    DATA / "betaflight_blackbox" / "better_tune.BBL",
    DATA / "blackbox_public" / "LOG00037.BFL",
    DATA / "blackbox_public" / "blackbox_log_2026-02-21_145057.TXT",
    Path(__file__).resolve().parents[1] / "tests" / "data" / "dataflash" / "ArduCopter-4.5.7_00000081_first650k.BIN",
]


def _best(fn, repeat):
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", default=[str(p) for p in DEFAULT if p.exists()])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    import orangebox

    from gyrocore.readers import blackbox as bb

    logging.getLogger("orangebox").setLevel(logging.ERROR)
    print(
        f"python {platform.python_version()}, orangebox {getattr(orangebox, '__version__', bb.ORANGEBOX_VERSION)}; "
        f"load {os.getloadavg()[0]:.2f}; best of {args.repeat}"
    )
    for path in args.files:
        if path.lower().endswith(".bin"):
            _bench_dataflash(path, args.repeat)
            continue
        raised = []

        def ob():
            # orangebox alone; it raises on INAV's end-of-log text ("End of log (disarm reason:N)",
            # atomgomba/orangebox#11): frames up to the raise are counted, the raise reported
            p = orangebox.Parser.load(path)
            n = 0
            raised.clear()
            for li in range(1, p.reader.log_count + 1):
                p.set_log_index(li)
                try:
                    for _ in p.frames():
                        n += 1
                except Exception as exc:  # noqa: BLE001 - reported, not hidden
                    raised.append(f"log {li}: {type(exc).__name__}: {exc}")
            return n

        def ours():
            return sum(lg.data.shape[0] for lg in bb.read_blackbox_logs(path))

        def full():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return bb.read_blackbox(path).n

        t_ob, n_ob = _best(ob, args.repeat)
        t_us, n_us = _best(ours, args.repeat)
        t_full, n_full = _best(full, args.repeat)
        with open(path, "rb") as fh:
            rev = next(
                (
                    ln.split(b":", 1)[1].strip().decode(errors="replace")
                    for ln in fh.read(20000).split(b"\n")
                    if ln.startswith(b"H Firmware revision:")
                ),
                "?",
            )
        print(f"file {Path(path).name} ({os.path.getsize(path) / 2**20:.2f} MiB, {rev})")
        print(
            f"  orangebox Parser.frames : {n_ob:7d} frames {t_ob:6.2f} s  {n_ob / t_ob:9.0f} frames/s  ratio 1.00"
            + (f"  (raised in {len(raised)} log(s): {raised[0]})" if raised else "")
        )
        print(
            f"  gyrocore frame loop     : {n_us:7d} frames {t_us:6.2f} s  {n_us / t_us:9.0f} frames/s  ratio {t_us / t_ob:.2f}"
        )
        print(
            f"  gyrocore read_blackbox  : {n_full:7d} frames {t_full:6.2f} s  {n_full / t_full:9.0f} frames/s  ratio {t_full / t_ob:.2f}"
        )


def _bench_dataflash(path: str, repeat: int) -> None:
    from pymavlink import DFReader

    from gyrocore.readers import dataflash as df

    def count(types):
        log = DFReader.DFReader_binary(path, zero_time_base=False)
        n = 0
        while log.recv_match(type=types) is not None:
            n += 1
        return n

    def full():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return df.read_dataflash(path).n

    t_all, n_all = _best(lambda: count(None), repeat)
    need = ["IMU", "RCOU", "CTUN", "PARM", "MSG", "ISBH"]
    t_need, n_need = _best(lambda: count(need), repeat)
    t_full, n_imu = _best(full, repeat)
    print(f"file {Path(path).name} ({os.path.getsize(path) / 2**20:.2f} MiB, ArduPilot DataFlash)")
    print(f"  pymavlink every message : {n_all:7d} msgs   {t_all:6.2f} s  {n_all / t_all:9.0f} msgs/s  ratio 1.00")
    print(
        f"  pymavlink needed types  : {n_need:7d} msgs   {t_need:6.2f} s  {n_need / t_need:9.0f} msgs/s  ratio {t_need / t_all:.2f}"
    )
    print(
        f"  gyrocore read_dataflash : {n_imu:7d} IMU    {t_full:6.2f} s  {n_need / t_full:9.0f} msgs/s  ratio {t_full / t_all:.2f}"
    )


if __name__ == "__main__":
    main()
