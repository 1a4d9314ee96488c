"""The firmware's own gyro filters against the discrete filters at 8 kHz: a gain table.

Run: ``python bench/firmware_filters.py`` (needs the binary: ``gyroharness firmware build``).

White noise (2 rad/s rms, 4 s at 8 kHz, seed 11/12/13) is replayed through the lockstep SITL
(:func:`sim.firmware.replay.replay_gyro`) with one filter on at a time; the gain
|P_xy/P_xx| (Welch, 4096-sample Hann segments) from the int16 input the firmware read to its
filtered gyro (``gyro.gyroADCf``) is printed beside the discrete filter's response
(:mod:`gyrocore.flight.filters`) at 50, 150 and 300 Hz. The same cases, with their tolerance
derivation, are the tests in ``tests/sim/test_firmware_filters.py``.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import csd, sosfreqz, welch

from gyrocore.flight.filters import betaflight_notch, biquad_notch, pt1
from sim.firmware.bridge import GYRO_LSB_PER_RAD_S
from sim.firmware.build import ensure_binary
from sim.firmware.replay import replay_gyro

FS = 8000.0
F = np.array([50.0, 150.0, 300.0])
OFF = (
    "set gyro_lpf1_static_hz = 0",
    "set gyro_lpf1_dyn_min_hz = 0",
    "set gyro_lpf2_static_hz = 0",
    "set dyn_notch_count = 0",
    "set rpm_filter_harmonics = 0",
    "set gyro_notch1_hz = 0",
    "set gyro_notch2_hz = 0",
)


def gain(res, skip=0):
    x = res.gyro_lsb[skip:, 0] / GYRO_LSB_PER_RAD_S
    y = res.fw_gyro_S_rad_s[skip:, 0]
    f, pxy = csd(x, y, fs=FS, nperseg=4096)
    _, pxx = welch(x, fs=FS, nperseg=4096)
    return np.interp(F, f, np.abs(pxy / pxx))


def main() -> None:
    fb = ensure_binary()
    print(
        f"{fb.firmware} {fb.version} lockstep SITL; gains at {', '.join(f'{f:g}' for f in F)} Hz (firmware / discrete model)"
    )
    n = 32000
    rows = []
    w = np.random.default_rng(11).normal(0, 2.0, (n, 3))
    r = replay_gyro(fb.binary, w, settings=(*OFF, "set gyro_lpf1_type = PT1", "set gyro_lpf1_static_hz = 150"))
    rows.append(("PT1 150 Hz (gyro_lpf1)", gain(r), np.abs(sosfreqz(pt1(150, FS).sos, worN=F, fs=FS)[1])))
    w = np.random.default_rng(12).normal(0, 2.0, (n, 3))
    r = replay_gyro(fb.binary, w, settings=(*OFF, "set gyro_notch1_hz = 200", "set gyro_notch1_cutoff = 150"))
    rows.append(
        ("static notch 200/150 Hz", gain(r), np.abs(sosfreqz(betaflight_notch(200, 150, FS).sos, worN=F, fs=FS)[1]))
    )
    t = np.arange(n) / FS
    w = np.random.default_rng(13).normal(0, 0.5, (n, 3))
    w[:, 0] += np.sin(2 * np.pi * 250 * t)
    r = replay_gyro(
        fb.binary,
        w,
        settings=(
            *OFF,
            "set dyn_notch_count = 1",
            "set dyn_notch_q = 300",
            "set dyn_notch_min_hz = 100",
            "set dyn_notch_max_hz = 600",
            "set debug_mode = FFT_FREQ",
        ),
    )
    c = float(np.median(r.debug[4000:, 1]))
    rows.append(
        (
            f"dynamic notch on a 250 Hz tone (centre {c:g} Hz, Q 3)",
            gain(r, 4000),
            np.abs(sosfreqz(biquad_notch(c, FS, q=3.0).sos, worN=F, fs=FS)[1]),
        )
    )
    wid = max(len(x[0]) for x in rows)
    for label, g, h in rows:
        print(f"{label:<{wid}}  " + "  ".join(f"{a:.3f}/{b:.3f} ({100 * (a / b - 1):+.1f} %)" for a, b in zip(g, h)))


if __name__ == "__main__":
    main()
