"""ArduPilot batch-sampler stream as a new user runs it: `convert --stream batch`, then
`vibration` — no 'bursty timestamps, use --retime' advice (retiming would join the windows), and
the default 1-s window names the window length that fits."""

from __future__ import annotations

import warnings
from pathlib import Path

from gyrocore.cli import build_group, run_cli
from gyrocore.data.recording import read_csv

BIN = Path(__file__).resolve().parents[1] / "data" / "dataflash" / "ArduCopter-4.5.7_00000081_first650k.BIN"


def test_batch_stream_file_reads_without_retime_advice_and_vibration_names_the_window(tmp_path, capsys):
    g = build_group(["gyrocore.cli.commands"])
    out = tmp_path / "isb.csv"
    assert run_cli(g, ["convert", str(BIN), "--stream", "batch", "-o", str(out)]) == 0
    capsys.readouterr()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read_csv(out)
    assert not [w for w in caught if "retime" in str(w.message) or "gaps" in str(w.message)]
    status = run_cli(g, ["vibration", str(out)])
    err = capsys.readouterr().err
    assert status == 2 and "use --window-s 0.15" in err
    assert run_cli(g, ["vibration", str(out), "--window-s", "0.15"]) == 0


def test_the_raw_log_points_to_its_batch_stream(capsys):
    """`vibration LOG.BIN` / `filter LOG.BIN` read the IMU messages (25 Hz in this log) and said
    only "use a longer --window-s", which cannot reach the motor lines; the error now names the
    batch sampler's stream and the commands that read it."""
    g = build_group(["gyrocore.cli.commands"])
    for cmd in ("vibration", "filter"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            status = run_cli(g, [cmd, str(BIN)])
        err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("error:")]
        assert status == 2 and len(err) == 1, err
        assert "logged at 25 Hz" in err[0] and "--stream batch -o isb.csv" in err[0], err[0]
