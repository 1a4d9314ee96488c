"""A real log's unfiltered gyro replayed through the firmware with the log's own settings, against
the log's own filtered gyro: rms above 40 Hz per axis.

Run: ``python bench/firmware_replay_log.py [LOG]`` (default ../shared/data/blackbox_public/LOG00037.BFL;
needs the binary: ``gyroharness firmware build``). Runs ``gyroharness firmware replay LOG -o TMP``
(the log's header as settings, its throttle stick, armed) and compares at the log's rows.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.signal import butter, sosfiltfilt

from gyrocore.data.recording import read_recording
from gyrocore.readers.blackbox import read_blackbox

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    log_path = (
        Path(sys.argv[1]) if len(sys.argv) > 1 else REPO.parent / "shared" / "data" / "blackbox_public" / "LOG00037.BFL"
    )
    with tempfile.TemporaryDirectory() as tmp:
        out_path = Path(tmp) / "fw.csv"
        r = subprocess.run(
            [sys.executable, "-m", "experiments.cli", "firmware", "replay", str(log_path), "-o", str(out_path)],
            cwd=REPO,
            capture_output=True,
            text=True,
            env={**os.environ, "PYTHONPATH": str(REPO)},
            check=False,
        )
        sys.stderr.write(r.stderr)
        if r.returncode != 0:
            sys.exit(r.returncode)
        out = read_recording(out_path)
    log = read_blackbox(log_path)
    t_log, t_fw = log.t_s - log.t_s[0], out.t_s - out.t_s[0]
    idx = np.clip(np.searchsorted(t_fw, t_log), 0, t_fw.size - 1)
    sos = butter(4, 40.0, "highpass", fs=log.rate_hz, output="sos")

    def hp_rms_deg(x):
        return float(np.degrees(np.sqrt(np.mean(sosfiltfilt(sos, x) ** 2))))

    print(
        f"{log_path.name}: {out.meta.get('firmware')} replay vs the log's own filtered gyro (gyroADC), "
        f"rms above 40 Hz, deg/s, at the log's {log.rate_hz:.0f} Hz rows"
    )
    print(f"{'axis':<4}  {'unfiltered':>10}  {'log filtered':>12}  {'firmware replay':>15}  {'ratio':>5}")
    for i, a in enumerate("xyz"):
        pre = hp_rms_deg(log.extra[f"gyro_prefilter_{a}_rad_s"])
        lg = hp_rms_deg(log.gyro_rad_s[:, i])
        fw = hp_rms_deg(out.extra[f"fw_gyro_{a}_rad_s"][idx])
        print(f"{a:<4}  {pre:10.2f}  {lg:12.2f}  {fw:15.2f}  {fw / lg:5.2f}")


if __name__ == "__main__":
    main()
