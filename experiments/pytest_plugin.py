"""pytest plugin: gate a calibration routine from your own test suite (``gyroharness check``).

Installed with gyroharness (entry point ``pytest11: gyroharness``); load it explicitly with
``-p experiments.pytest_plugin`` where the package is not installed. It offers one fixture::

    def test_my_calibration_holds_its_contract(gyroharness_check):
        gyroharness_check("ci/gyro_contract.toml",
                          fit_cmd="./build/cal fit {params} {inputs}",
                          apply_cmd="./build/cal apply {params} {input} {output}")

The call runs the contract's campaign (:func:`experiments.score.check_contract`) and fails the
test with one line per broken bound or failed unit; it returns the
:class:`experiments.score.CheckResult` when every bound holds. ``--gyroharness-workers N`` sets
the worker processes (default 1); ``--gyroharness-junit FILE`` also writes the JUnit XML.
Nothing is imported from gyroharness until the fixture is used.
"""

from __future__ import annotations

import pytest


def pytest_addoption(parser):
    group = parser.getgroup("gyroharness", "gyroharness calibration contract")
    group.addoption(
        "--gyroharness-workers",
        type=int,
        default=1,
        help="worker processes for the gyroharness_check fixture (default 1)",
    )
    group.addoption("--gyroharness-junit", default=None, help="also write the gate's JUnit XML to this file")


@pytest.fixture
def gyroharness_check(request):
    """``check(contract, *, calibrator=None, fit_cmd=None, apply_cmd=None, timeout_s=None, units=None,
    expect_pass=True)`` → :class:`experiments.score.CheckResult`; fails the test when the verdict
    differs from ``expect_pass`` (one line per broken bound / failed unit in the message)."""
    workers = request.config.getoption("--gyroharness-workers")
    junit = request.config.getoption("--gyroharness-junit")

    def check(contract, *, calibrator=None, fit_cmd=None, apply_cmd=None, timeout_s=None, units=None, expect_pass=True):
        from experiments import score as SC
        from gyrocore.data.recording import atomic_write_text

        spec = {k: v for k, v in {"calibrator": calibrator, "fit_cmd": fit_cmd, "apply_cmd": apply_cmd}.items() if v}
        if timeout_s is not None:
            spec["timeout_s"] = float(timeout_s)
        res = SC.check_contract(str(contract), routine_spec=spec, workers=workers, units=units)
        if junit:
            atomic_write_text(junit, SC.junit_xml(res))
        if res.passed != bool(expect_pass):
            lines = res.lines() or ["every bound holds"]
            verdict = "broke" if not res.passed else "held (expected to fail)"
            pytest.fail(f"gyroharness contract {contract} {verdict}:\n" + "\n".join(lines), pytrace=False)
        return res

    return check
