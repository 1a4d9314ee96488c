"""Python-form test routines for :class:`experiments.calibrators.IsolatedCalibrator`.

``factory(mode)``: ``ok`` (bias = mean of the first 100 samples of the scored recording; params
are a closure, which does not pickle: they must stay in the routine's process), ``hang`` (apply
sleeps 600 s), ``die`` (apply ends the process with exit code 7), ``raise`` (apply raises).
"""

import os
import time

import numpy as np


class Probe:
    def __init__(self, mode="ok"):
        self.mode = mode

    def fit(self, recordings):
        n = len(recordings)
        return lambda: n  # not picklable on purpose

    def apply(self, recording, params):
        assert params() >= 1
        if self.mode == "hang":
            time.sleep(600)
        if self.mode == "die":
            os._exit(7)
        if self.mode == "raise":
            raise RuntimeError("no\nluck")
        g = np.asarray(recording.gyro_rad_s)
        return g - g[:100].mean(axis=0)


def ok():
    return Probe("ok")


def hang():
    return Probe("hang")


def die():
    return Probe("die")


def fails():
    return Probe("raise")
