"""The one rule for "this data file is too large to analyse in memory".

A CSV/Parquet data file is *large* for an analysis when its in-memory working set — the
estimated rows (:func:`gyrocore.data.recording.file_layout`: the Parquet row count, or the CSV
size over its mean line length) times the analysis' bytes per row (:class:`MemoryRule`: a
fixed part, plus a part per column of the file) — exceeds the analysis' budget or its fraction
of the available memory. A large file is analysed from disk (spilled columns read back a
window or an axis at a time, or converted chunk by chunk), with the same numbers as in memory
(tests/gyrocore/calib/test_stream.py, test_lowmem.py, test_loop_stream.py compare the two
paths); only the memory differs.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from gyrocore.data import recording as _recording

from .convert import detect_format

__all__ = ["LARGE_FILE_BYTES", "MemoryRule", "RULES", "is_large"]

#: Working set an in-memory analysis may hold, bytes.
LARGE_FILE_BYTES = 64 * 2**20


@dataclass(frozen=True)
class MemoryRule:
    """The in-memory working set of one analysis and the memory it may take.

    Attributes
    ----------
    bytes_per_row : float
        In-memory bytes per data row, whatever the file's columns.
    bytes_per_value : float
        Plus these bytes per value of the file (rows × its columns): a whole read.
    budget_bytes : float
        Largest working set, bytes.
    available_fraction : float, optional
        ... and at most this fraction of the available memory (None: the budget alone).
    """

    bytes_per_row: float = 0.0
    bytes_per_value: float = 0.0
    budget_bytes: float = LARGE_FILE_BYTES
    available_fraction: float | None = None


#: The rule of each analysis (float64 = 8 B):
#: ``allan`` t and three gyro axes (4 × 8 = 32; from disk it holds t and one axis);
#: ``bias`` the record and its window statistics (64: 1 048 576 rows);
#: ``calibrate`` / ``loop`` the least-squares design, three axes × up to ~20 regressor columns
#: (512: 131 072 rows);
#: ``convert`` a whole read of every column (32 B per value, the reader's measured cost,
#: ``recording._BYTES_PER_VALUE``), at most 160 MiB or 5 % of the available memory (≈ 96 MiB of
#: CSV text, or 1/30 of the memory in CSV bytes, at ~22 B of text per value): above it the file
#: is converted chunk by chunk (the per-row repairs, not the whole-series checks).
RULES: dict[str, MemoryRule] = {
    "allan": MemoryRule(bytes_per_row=32),
    "bias": MemoryRule(bytes_per_row=64),
    "calibrate": MemoryRule(bytes_per_row=512),
    "loop": MemoryRule(bytes_per_row=512),
    "convert": MemoryRule(
        bytes_per_value=_recording._BYTES_PER_VALUE, budget_bytes=160 * 2**20, available_fraction=0.05
    ),
}


def is_large(path: str | os.PathLike, analysis: str | MemoryRule, *, need: tuple[str, ...] = ()) -> bool:
    """True when ``path`` is a CSV/Parquet data file, holds the column groups ``need``
    (e.g. ``("ref_rate",)``) and is too large for ``analysis`` (a key of :data:`RULES`, or a
    :class:`MemoryRule`) in memory."""
    if not os.path.isfile(path) or detect_format(path) not in ("csv", "parquet"):
        return False
    rule = RULES[analysis] if isinstance(analysis, str) else analysis
    groups, est_rows, n_columns = _recording.file_layout(path)
    if not all(g in groups for g in need):
        return False
    need_bytes = est_rows * (rule.bytes_per_row + rule.bytes_per_value * n_columns)
    if need_bytes > rule.budget_bytes:
        return True
    return (
        rule.available_fraction is not None
        and need_bytes > rule.available_fraction * _recording._available_memory_bytes()
    )
