"""The one rule for "this data file is too large to analyse in memory".

A CSV/Parquet data file is *large* for an analysis when its estimated rows
(:func:`gyrocore.data.recording.file_layout`: the Parquet row count, or the CSV size over its
mean line length) times the analysis' in-memory bytes per row exceed :data:`LARGE_FILE_BYTES`.
A large file is analysed from disk (spilled columns read back a window or an axis at a time),
with the same numbers as in memory (tests/gyrocore/calib/test_stream.py, test_lowmem.py,
test_loop_stream.py compare the two paths bit for bit); only the memory differs.
"""

from __future__ import annotations

import os

from gyrocore.data.recording import file_layout

from .convert import detect_format

__all__ = ["LARGE_FILE_BYTES", "BYTES_PER_ROW", "is_large"]

#: Working set an in-memory analysis may hold, bytes.
LARGE_FILE_BYTES = 64 * 2**20

#: In-memory bytes per data row of each analysis (float64 = 8 B):
#: ``allan`` t and three gyro axes (4 × 8 = 32; from disk it holds t and one axis);
#: ``bias`` the record and its window statistics (64: 1 048 576 rows, as the million rows the
#: bias command streamed above before);
#: ``calibrate`` / ``loop`` the least-squares design, three axes × up to ~20 regressor columns
#: (512: 131 072 rows).
BYTES_PER_ROW = {"allan": 32, "bias": 64, "calibrate": 512, "loop": 512}


def is_large(path: str | os.PathLike, analysis: str, *, need: tuple[str, ...] = ()) -> bool:
    """True when ``path`` is a CSV/Parquet data file, holds the column groups ``need``
    (e.g. ``("ref_rate",)``) and is too large for ``analysis`` (a key of :data:`BYTES_PER_ROW`)
    in memory."""
    if not os.path.isfile(path) or detect_format(path) not in ("csv", "parquet"):
        return False
    groups, est_rows = file_layout(path)
    return all(g in groups for g in need) and est_rows * BYTES_PER_ROW[analysis] > LARGE_FILE_BYTES
