"""Blackbox files damaged the way real dumps are, built from the public logs (../shared/data).

* A dataflash dump cut inside the header of its second log: before, the whole file was refused
  ("log 2: unreadable header (Unknown format code 'd' ...)"); now log 1 is read and log 2 is
  skipped with a warning (asked for by --log-index 2, it stays an error).
* ``looptime:InfinityHz`` (INAV's broken header, FLIGHT_LOGS.md): before, an error; now the loop
  rate is the one the log's own loopIteration count measured, with a warning.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from gyrocore.errors import GyroInputError, RepairWarning
from gyrocore.readers.blackbox import read_blackbox

BF42 = "LOG00037.BFL"
INAV = "blackbox_log_2026-02-21_145057.TXT"
INAV_LOG2_AT = 168_955  # byte offset of the second 'H Product' header (PROVENANCE.md)


def _read(path, **kw):
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        rec = read_blackbox(path, **kw)
    return rec, [str(x.message) for x in w if issubclass(x.category, RepairWarning)]


def test_dump_cut_inside_the_second_header_keeps_the_first_log(shared_data, tmp_path):
    src = (shared_data / "blackbox_public" / INAV).read_bytes()
    p = tmp_path / "cut.TXT"
    p.write_bytes(src[: INAV_LOG2_AT + 2000])  # log 1 whole, log 2 cut 2000 bytes into its header
    rec, msgs = _read(p)
    assert rec.n == 1814  # PROVENANCE: log 1 holds 1,814 frames
    assert any("log 2 of 2: header cut off or unreadable" in m and "skipped" in m for m in msgs), msgs
    with pytest.raises(GyroInputError, match="log 2: unreadable header"):
        _read(p, log_index=2)


@pytest.mark.parametrize(
    "name, field",
    [(BF42, "gyro_rate_hz"), (INAV, "pid_rate_hz")],  # Betaflight: looptime = gyro period; INAV: PID loop
)
def test_looptime_infinityhz_takes_the_measured_loop_rate(shared_data, tmp_path, name, field):
    src = (shared_data / "blackbox_public" / name).read_bytes()
    good = tmp_path / ("good_" + name)
    good.write_bytes(src)
    bad = tmp_path / ("bad_" + name)
    nominal = b"H looptime:125\n" if name == BF42 else b"H looptime:500\n"
    assert nominal in src
    bad.write_bytes(src.replace(nominal, b"H looptime:InfinityHz\n"))
    ref, _ = _read(good, log_index=1)
    rec, msgs = _read(bad, log_index=1)
    assert any("header 'looptime' is 'InfinityHz'" in m and "loopIteration" in m for m in msgs), msgs
    assert np.array_equal(rec.gyro_rad_s, ref.gyro_rad_s)  # the data do not depend on the header's rate
    measured = float(ref.meta["loop_rate_measured_hz"])
    assert float(rec.meta[field]) == pytest.approx(measured, rel=1e-9)
    # the measured loop rate is the nominal one within the clock's few per cent (8 kHz: 7883 Hz;
    # INAV 2 kHz: 1933 Hz)
    assert float(rec.meta[field]) == pytest.approx(float(ref.meta[field]), rel=0.05)


def test_a_log_whose_gyroadc_is_all_zero_says_so(shared_data):
    """INAV 9.0.1's ground logs 1-2 carry gyroADC = 0 in every frame while gyroRaw moves
    (PROVENANCE: both decoders agree). The data file then held zero gyro columns without a word;
    now a warning names the log and where the logged gyro is. Log 3 (gyroADC non-zero) says nothing."""
    src = shared_data / "blackbox_public" / INAV
    rec, msgs = _read(src, log_index=1)
    assert not np.any(rec.gyro_rad_s) and np.any(rec.extra["gyro_prefilter_x_rad_s"])
    assert any("log 1: gyroADC is 0 in every frame" in m and "gyro_prefilter" in m for m in msgs), msgs
    rec3, msgs3 = _read(src, log_index=3)
    assert np.any(rec3.gyro_rad_s) and not any("gyroADC is 0" in m for m in msgs3)
