"""Short flights: every analysed window lands in a throttle band, and the plot shows what there is.

A 17-s Betaflight 4.2 flight (LOG00037.BFL) gave 26 one-second windows; the default 8
equal-count bands held 3-4 windows each and the bands under 4 windows were skipped without a
word: 18 of 26 windows (and the band spectra of 6 of 8 bands) were dropped. The synthetic flight
of test_vibration (a fixed line on x, a throttle-following line on y, white noise; exact
frequencies) is cut to 12 s here: the old code analysed none of its bands and found no line.
"""

from __future__ import annotations

import numpy as np

from gyrocore.flight.spectra import MIN_BAND_WINDOWS
from gyrocore.flight.vibration import analyse, plot_vibration
from tests.gyrocore.flight.test_vibration import A_FIXED, F_FIXED, LEVELS, N_WHITE, RATE, _line


def _short_flight(hold_s: float, seed: int = 5):
    from gyrocore.data.recording import Recording

    rng = np.random.default_rng(seed)
    u = np.repeat(LEVELS, int(hold_s * RATE))
    t = np.arange(u.size) / RATE
    g = rng.normal(0.0, N_WHITE, (u.size, 3))
    g[:, 0] += A_FIXED * np.sin(2 * np.pi * F_FIXED * t + 0.3)
    g[:, 1] += 0.03 * np.sin(2 * np.pi * np.cumsum(100.0 + 400.0 * u) / RATE)
    return Recording(t_s=t, gyro_rad_s=g, meta={"source": "synthetic"}, extra={"motor_cmd_mean": u})


def test_short_flight_uses_every_window_in_fewer_bands():
    res = analyse(_short_flight(1.5))  # 12 s: 8 bands of ~3 windows before
    counts = [b["n_windows"] for b in res.bands]
    assert sum(counts) == res.n_windows, (counts, res.n_windows)
    assert min(counts) >= MIN_BAND_WINDOWS and 3 <= len(counts) < 8
    assert any("throttle band(s) instead of 8" in n for n in res.notes)
    resol = res.to_json()["frequency_resolution_hz"]
    assert abs(_line(res, "x", "fixed")["frequency_hz"] - F_FIXED) <= resol / 2
    _line(res, "y", "throttle")  # the moving line is seen across the bands


def test_too_few_windows_for_a_band_is_said_and_plotted(tmp_path):
    res = analyse(_short_flight(0.25))  # 2 s: 3 windows
    assert res.n_windows < MIN_BAND_WINDOWS and not res.bands
    assert any("no band spectra or lines" in n for n in res.notes)
    assert np.all(np.isfinite(list(res.rms_above_40hz_rad_s.values())))
    png = tmp_path / "v.png"
    plot_vibration(res, png)
    assert png.stat().st_size > 10_000


def test_time_span_outside_the_record_is_named():
    """`vibration --t-from-s 300` on a 129-s flight said "no airborne samples (band variable below
    the airborne threshold everywhere)": the span, not the throttle, was empty."""
    import pytest

    from gyrocore.errors import GyroInputError

    with pytest.raises(GyroInputError, match=r"--t-from-s/--t-to-s select 0 samples; the recording spans t = 0-"):
        analyse(_short_flight(1.5), t_from_s=300.0)
