"""Segments: spans of a recording with a known reference, and the one segments file.

A :class:`Segment` is either **still** (true rate 0 relative to the world frame W) or a known
**rotation** of the sensor frame S over the span, given as its rotation vector in S (degrees;
a turn about one sensor axis is the special case with one non-zero component, made by
:meth:`Segment.about_axis`). Readers produce them (the public research sets' documented turns),
the integral calibration method (:mod:`gyrocore.calib.rotations`) and the loop's ``angles`` and
``still`` references (:mod:`gyrocore.loop.residual`) consume them.

The segments file (CSV, UTF-8; blank and ``#`` lines ignored; written by
:func:`write_segments`, read by :func:`read_segments`)::

    t_start_s,t_end_s,kind,angle_x_deg,angle_y_deg,angle_z_deg,label
    1.25,9.5,rotation,720.0,0.0,0.0,two CCW 360 deg turns about x (README)
    10.0,14.0,still,,,,

``kind`` is ``still`` or ``rotation``; the three angles are the rotation vector in S, degrees,
right-hand positive (empty for a still segment); ``label`` (optional column, free text) says
where the segment comes from. Two older layouts are still read, with a warning that says what
was converted: ``t_start_s,t_end_s,axis,angle_deg`` (one axis per row, written by
``gyroharness convert --segments-out`` before) and ``start_s,stop_s,kind[,angle_x/y/z_rad|_deg]``
(the loop's segments file before).
"""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass, replace
from typing import Iterable, Sequence

from gyrocore.errors import GyroInputError, warn_repair
from gyrocore.data.recording import atomic_write_text

__all__ = [
    "SEGMENT_KINDS",
    "SEGMENTS_HEADER",
    "Segment",
    "read_segments",
    "write_segments",
    "as_segments",
]

SEGMENT_KINDS = ("still", "rotation")
#: The header of the segments file (``label`` may be left out when reading).
SEGMENTS_HEADER = ("t_start_s", "t_end_s", "kind", "angle_x_deg", "angle_y_deg", "angle_z_deg", "label")
_AXES = ("x", "y", "z")


@dataclass(frozen=True)
class Segment:
    """A span of a recording with a known reference: still, or a known rotation.

    Parameters
    ----------
    t_start_s, t_end_s : float
        Span on the recording's time axis, s (``t_end_s > t_start_s``, both finite).
    kind : {"still", "rotation"}
        ``"still"``: the true rate is 0 relative to W over the span. ``"rotation"``: the
        sensor frame S turns by ``angle_S_deg`` over the span.
    angle_S_deg : tuple of 3 floats or None
        Rotations only: the rotation vector of S over the span, expressed in S, degrees
        (e.g. (720, 0, 0): two turns about +x, right-hand positive). None for still spans.
    label : str
        Where the segment comes from (free text, kept in the segments file).

    Raises
    ------
    GyroInputError
        Unknown kind, an empty or non-finite span, a rotation without a finite 3-vector, or a
        still span with one.
    """

    t_start_s: float
    t_end_s: float
    kind: str
    angle_S_deg: tuple[float, float, float] | None = None
    label: str = ""

    def __post_init__(self) -> None:
        if self.kind not in SEGMENT_KINDS:
            raise GyroInputError(
                f"segment kind must be 'still' or 'rotation', not {self.kind!r} (a turn about one sensor axis: "
                "Segment.about_axis)"
            )
        try:
            t0, t1 = float(self.t_start_s), float(self.t_end_s)
        except (TypeError, ValueError):
            raise GyroInputError(f"segment times must be numbers, got {self.t_start_s!r}..{self.t_end_s!r}") from None
        if not (math.isfinite(t0) and math.isfinite(t1) and t1 > t0):
            raise GyroInputError(f"segment {t0}..{t1} s: need finite t_start_s < t_end_s")
        object.__setattr__(self, "t_start_s", t0)
        object.__setattr__(self, "t_end_s", t1)
        if self.kind == "still":
            if self.angle_S_deg is not None:
                raise GyroInputError(f"segment {t0}..{t1} s: a still segment has no rotation angle")
        else:
            if self.angle_S_deg is None:
                raise GyroInputError(f"segment {t0}..{t1} s: a rotation segment needs its angle (angle_x/y/z_deg)")
            try:
                v = tuple(float(x) for x in self.angle_S_deg)
            except (TypeError, ValueError):
                raise GyroInputError(
                    f"segment {t0}..{t1} s: angle must be 3 numbers, got {self.angle_S_deg!r}"
                ) from None
            if len(v) != 3 or not all(math.isfinite(x) for x in v):
                raise GyroInputError(f"segment {t0}..{t1} s: angle must be 3 finite numbers, got {self.angle_S_deg!r}")
            object.__setattr__(self, "angle_S_deg", v)
        object.__setattr__(self, "label", str(self.label))

    @classmethod
    def about_axis(cls, t_start_s: float, t_end_s: float, axis: str, angle_deg: float, label: str = "") -> "Segment":
        """A rotation by ``angle_deg`` (degrees, right-hand positive) about the sensor axis
        ``axis`` (``"x"``, ``"y"`` or ``"z"``)."""
        if axis not in _AXES:
            raise GyroInputError(f"segment axis must be x, y or z, got {axis!r}")
        v = [0.0, 0.0, 0.0]
        v[_AXES.index(axis)] = float(angle_deg)
        return cls(t_start_s, t_end_s, "rotation", tuple(v), label)

    @classmethod
    def still(cls, t_start_s: float, t_end_s: float, label: str = "") -> "Segment":
        """A still span (true rate 0 relative to W)."""
        return cls(t_start_s, t_end_s, "still", None, label)

    @property
    def angle_S_rad(self) -> tuple[float, float, float] | None:
        """The rotation vector in S, rad (None for a still segment)."""
        if self.angle_S_deg is None:
            return None
        return tuple(math.radians(x) for x in self.angle_S_deg)

    @property
    def axis(self) -> str | None:
        """The sensor axis a rotation turns about when its vector lies along one (``"x"``,
        ``"y"``, ``"z"``); None for still segments and rotations about an oblique axis."""
        if self.angle_S_deg is None:
            return None
        nz = [a for a, x in zip(_AXES, self.angle_S_deg) if x != 0.0]
        return nz[0] if len(nz) == 1 else None

    def shifted(self, dt_s: float) -> "Segment":
        """The same segment with its span moved by ``dt_s`` seconds."""
        return replace(self, t_start_s=self.t_start_s + dt_s, t_end_s=self.t_end_s + dt_s)


def as_segments(segments: str | os.PathLike | Iterable[Segment] | None) -> list[Segment]:
    """A list of :class:`Segment` from a segments file path or a sequence of segments
    (None: no segments).

    Raises
    ------
    GyroInputError
        The file cannot be read (see :func:`read_segments`) or an item is not a Segment.
    """
    if segments is None:
        return []
    if isinstance(segments, (str, bytes)) or hasattr(segments, "__fspath__"):
        return read_segments(os.fsdecode(segments))
    out = list(segments)
    for s in out:
        if not isinstance(s, Segment):
            raise GyroInputError(f"not a segment: {s!r} (use gyrocore.data.segments.Segment)")
    return out


def write_segments(segments: Sequence[Segment], path: str | os.PathLike, *, overwrite: bool = True) -> None:
    """Write the segments file (header :data:`SEGMENTS_HEADER`) atomically.

    Times and angles are written as Python's shortest exact decimal (``repr``), so
    :func:`read_segments` gives back equal segments.
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(SEGMENTS_HEADER)
    for s in segments:
        ang = ("", "", "") if s.angle_S_deg is None else tuple(repr(x) for x in s.angle_S_deg)
        w.writerow((repr(s.t_start_s), repr(s.t_end_s), s.kind, *ang, s.label))
    atomic_write_text(path, buf.getvalue(), overwrite=overwrite)


def read_segments(path: str | os.PathLike) -> list[Segment]:
    """Read a segments file (module docstring); the two older layouts are converted with a
    warning that says so.

    Raises
    ------
    GyroInputError
        No such file, no header, an unknown header, or a row that is not a valid segment
        (the message names the line).
    """
    path = os.fsdecode(path)
    if not os.path.isfile(path):
        raise GyroInputError(f"{path}: no such segments file")
    with open(path, newline="", encoding="utf-8", errors="replace") as fh:
        numbered = [(i, line) for i, line in enumerate(fh, 1) if line.strip() and not line.lstrip().startswith("#")]
    if not numbered:
        raise GyroInputError(f"{path}: empty segments file")
    rows = []
    for ln, line in numbered:  # one line, one row: a label never spans lines
        try:
            rows.append((ln, [c.strip() for c in next(csv.reader([line.rstrip("\r\n")]))]))
        except (csv.Error, StopIteration):
            raise GyroInputError(f"{path}: line {ln}: not a CSV row") from None
    head, body = rows[0][1], rows[1:]
    if head[:6] == list(SEGMENTS_HEADER[:6]):
        parse = _row_current
    elif head[:4] == ["t_start_s", "t_end_s", "axis", "angle_deg"]:
        parse = _row_one_axis
        warn_repair(
            f"{path}: older segments layout t_start_s,t_end_s,axis,angle_deg read as rotations about one sensor "
            f"axis each; the segments file is now {','.join(SEGMENTS_HEADER)}"
        )
    elif {"start_s", "stop_s", "kind"} <= set(head):
        parse = _row_loop(head, path)
        warn_repair(
            f"{path}: older segments layout start_s,stop_s,kind[,angle_*] read as t_start_s,t_end_s,kind"
            + (" with the angles converted from rad to deg" if "angle_x_rad" in head else "")
            + f"; the segments file is now {','.join(SEGMENTS_HEADER)}"
        )
    else:
        raise GyroInputError(f"{path}: the segments file's header must be {','.join(SEGMENTS_HEADER)}")
    out: list[Segment] = []
    for ln, r in body:
        try:
            out.append(parse(r))
        except GyroInputError as exc:
            raise GyroInputError(f"{path}: line {ln}: {exc}") from None
        except (ValueError, IndexError):
            raise GyroInputError(
                f"{path}: line {ln}: not a valid segment (a value is missing or not a number)"
            ) from None
    return out


def _angles(cells: Sequence[str], kind: str, factor: float = 1.0) -> tuple[float, float, float] | None:
    """The rotation vector of a row in degrees; empty (or all-zero) cells on a still row."""
    if kind not in SEGMENT_KINDS:
        raise GyroInputError(f"segment kind must be 'still' or 'rotation', not {kind!r}")
    if kind == "still":
        if any(c and float(c) != 0.0 for c in cells):
            raise GyroInputError("a still segment has no rotation angle")
        return None
    if any(not c for c in cells):
        raise GyroInputError("a rotation segment needs all three angles")
    return tuple(float(c) * factor for c in cells)


def _row_current(r: list[str]) -> Segment:
    if len(r) < 6:
        raise GyroInputError(f"expected at least 6 values, got {len(r)}")
    kind = r[2]
    label = r[6] if len(r) > 6 else ""
    return Segment(float(r[0]), float(r[1]), kind, _angles(r[3:6], kind), label)


def _row_one_axis(r: list[str]) -> Segment:
    if len(r) < 4:
        raise GyroInputError(f"expected 4 values, got {len(r)}")
    return Segment.about_axis(float(r[0]), float(r[1]), r[2], float(r[3]))


def _row_loop(head: list[str], path: str):
    """Row parser of the loop's older layout ``start_s,stop_s,kind[,angle_x/y/z_rad|_deg]``."""
    ix = {h: i for i, h in enumerate(head)}
    if all(f"angle_{a}_deg" in ix for a in _AXES):
        cols, factor = [ix[f"angle_{a}_deg"] for a in _AXES], 1.0
    elif all(f"angle_{a}_rad" in ix for a in _AXES):
        cols, factor = [ix[f"angle_{a}_rad"] for a in _AXES], 180.0 / math.pi
    else:
        cols, factor = None, 1.0

    def parse(r: list[str]) -> Segment:
        kind = r[ix["kind"]]
        if kind == "rotation" and cols is None:
            raise GyroInputError("rotation segments need angle_x/y/z_deg (or _rad) columns")
        cells = [r[i] if i < len(r) else "" for i in cols] if cols is not None else ["", "", ""]
        return Segment(float(r[ix["start_s"]]), float(r[ix["stop_s"]]), kind, _angles(cells, kind, factor))

    return parse
