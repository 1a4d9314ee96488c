"""`filter-closed-loop` on a hover log without eRPM says why no rotor line exists.

Betaflight 4.2 LOG00037.BFL (17-s hover, motor command 0.29-0.38, no eRPM logged) was refused
with "vibration spec has no line that follows throttle or eRPM" and nothing a pilot could act on.
"""

from __future__ import annotations

import pytest

from gyrocore.errors import GyroInputError
from sim.spec_vibration import rotor_line


def _spec(lo, hi, erpm=False):
    bands = []
    for i in range(3):
        a, b = lo + (hi - lo) * i / 3, lo + (hi - lo) * (i + 1) / 3
        bands.append({"throttle": [a, b], "median": (a + b) / 2, **({"rotor_hz_median": 500.0} if erpm else {})})
    return {
        "bands": bands,
        "lines": [{"axis": "y", "frequency_hz": 47.0, "follows": "fixed", "amplitude_rad_s": 0.005}],
    }


def test_hover_without_erpm_names_the_throttle_span_and_erpm():
    with pytest.raises(
        GyroInputError,
        match=r"span motor command 0\.29-0\.38 and the log has no rotor speed \(eRPM\); "
        r"a flight that holds one throttle \(a hover\) gives no throttle law",
    ):
        rotor_line(_spec(0.29, 0.38))


def test_wide_throttle_with_erpm_is_not_called_a_hover():
    with pytest.raises(GyroInputError) as e:
        rotor_line(_spec(0.2, 0.7, erpm=True))
    assert "hover" not in str(e.value) and "no rotor speed" not in str(e.value)
