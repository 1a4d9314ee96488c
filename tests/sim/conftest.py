"""Fixtures for the firmware-in-the-loop tests: the lockstep Betaflight SITL, built once per run."""

from __future__ import annotations

import os
import shutil

import pytest


def _in_ci() -> bool:
    return bool(os.environ.get("CI") or os.environ.get("GYROHARNESS_CI"))


@pytest.fixture(scope="session")
def firmware_binary() -> str:
    """Path of the lockstep SITL (built into the per-user cache on first use).

    Under pytest-xdist every worker calls :func:`sim.firmware.build.ensure_binary`; its lock
    makes one build and the others wait for it. Without a C compiler the tests skip with the
    reason locally, and FAIL in CI (``CI`` or ``GYROHARNESS_CI`` set): CI must build them.
    """
    from sim.firmware.build import ensure_binary

    missing = [t for t in ("gcc", "make") if shutil.which(t) is None]
    if missing:
        msg = f"the firmware tests need {' and '.join(missing)} to build the Betaflight SITL"
        if _in_ci():
            pytest.fail(msg + " (CI must install them: see .ci/run)")
        pytest.skip(msg)
    return ensure_binary().binary
