"""The data a calibration reads and writes: :class:`~gyrocore.data.recording.Recording`, its CSV/Parquet
file format, atomic writes and column spilling; :class:`~gyrocore.data.segments.Segment` (still spans
and known rotations) and the segments file."""
