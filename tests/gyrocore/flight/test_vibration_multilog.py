"""A blackbox file holding several logs flown with different gyro filters (a new user's file:
Betaflight appends every arm to the same flash): `vibration` and `filter` used to undo the first
log's filter chain on every log's spectrum, silently."""

from __future__ import annotations

import json

import pytest

from gyrocore.cli import build_group, run_cli


def _gh(capsys, *argv):
    status = run_cli(build_group(["gyrocore.cli.commands"]), list(argv))
    out, err = capsys.readouterr()
    return status, out, err


@pytest.fixture()
def two_logs(shared_data, tmp_path):
    """better_tune.BBL's header + first 400 kB, twice; the second log's PT1 set to 60 Hz (the
    header line a pilot changes between two packs)."""
    b = (shared_data / "betaflight_blackbox" / "better_tune.BBL").read_bytes()[:400_000]
    assert b.count(b"H gyro_lowpass_hz:90") == 1
    p = tmp_path / "two.BBL"
    p.write_bytes(b + b.replace(b"H gyro_lowpass_hz:90", b"H gyro_lowpass_hz:60", 1))
    return p


def test_logs_with_different_filters_are_refused_then_read_one_at_a_time(two_logs, capsys):
    for cmd in ("vibration", "filter"):
        status, _o, err = _gh(capsys, cmd, str(two_logs))
        last = err.strip().splitlines()[-1]
        assert status == 2 and last.startswith("error: ") and "--log-index" in last, err
        assert "log 1: pt1 90 Hz" in last and "log 2: pt1 60 Hz" in last
    status, out, err = _gh(capsys, "vibration", str(two_logs), "--log-index", "2", "--json")
    assert status == 0, err
    j = json.loads(out)
    undone = [f for f in j["filters_before"] if f.get("undone")]
    assert [(f["kind"], f["cutoff_hz"]) for f in undone] == [("pt1", 60.0)]
