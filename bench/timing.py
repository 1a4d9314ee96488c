"""Timing shared by the benches: wall and CPU seconds of a block."""

from __future__ import annotations

import time

import psutil


class Clock:
    """Wall (perf_counter) and CPU seconds of a block: this process's (process_time), plus a
    child process's (``child_pid``, e.g. the firmware SITL; psutil) when given."""

    def __init__(self, child_pid: int | None = None):
        self.child = psutil.Process(child_pid) if child_pid else None

    def _cpu(self) -> float:
        c = time.process_time()
        if self.child is not None:
            t = self.child.cpu_times()
            c += t.user + t.system
        return c

    def __enter__(self):
        self.w0, self.c0 = time.perf_counter(), self._cpu()
        return self

    def __exit__(self, *exc):
        self.wall_s = time.perf_counter() - self.w0
        self.cpu_s = self._cpu() - self.c0
