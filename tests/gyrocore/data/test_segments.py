"""The one Segment and the one segments file (gyrocore.data.segments)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

import gyrocore
from gyrocore.data.segments import SEGMENTS_HEADER, Segment, as_segments, read_segments, write_segments
from gyrocore.errors import GyroInputError, RepairWarning


def test_about_axis_and_still():
    s = Segment.about_axis(1.0, 2.5, "y", -360.0, label="hand")
    assert s.kind == "rotation" and s.angle_S_deg == (0.0, -360.0, 0.0) and s.axis == "y" and s.label == "hand"
    # the SI vector is math.radians of the degrees given, component by component (as numpy's)
    assert s.angle_S_rad == (0.0, math.radians(-360.0), 0.0)
    assert s.angle_S_rad[1] == np.radians(-360.0)
    q = Segment.still(3.0, 4.0)
    assert q.kind == "still" and q.angle_S_deg is None and q.angle_S_rad is None and q.axis is None
    oblique = Segment(0.0, 1.0, "rotation", (90.0, 90.0, 0.0))
    assert oblique.axis is None
    assert s.shifted(10.0) == Segment.about_axis(11.0, 12.5, "y", -360.0, label="hand")


@pytest.mark.parametrize(
    "args, match",
    [
        ((1.0, 2.0, "x", 720.0), "kind must be"),  # the older one-axis positional form
        ((2.0, 1.0, "still"), "t_start_s < t_end_s"),
        ((1.0, float("nan"), "still"), "t_start_s < t_end_s"),
        ((1.0, 2.0, "rotation"), "needs its angle"),
        ((1.0, 2.0, "rotation", (1.0, 2.0)), "3 finite numbers"),
        ((1.0, 2.0, "rotation", (1.0, float("inf"), 0.0)), "3 finite numbers"),
        ((1.0, 2.0, "still", (0.0, 0.0, 0.0)), "has no rotation angle"),
        (("a", 2.0, "still"), "must be numbers"),
    ],
)
def test_segment_validation(args, match):
    with pytest.raises(GyroInputError, match=match):
        Segment(*args)


def test_about_axis_bad_axis():
    with pytest.raises(GyroInputError, match="axis must be x, y or z"):
        Segment.about_axis(1.0, 2.0, "w", 90.0)


def test_file_round_trip_exact(tmp_path):
    segs = [
        Segment.about_axis(1.0, 2.5, "x", 720.0, label='two turns, "README"'),
        Segment.still(3.0, 4.0),
        Segment(4.1, 5.0, "rotation", (0.1, -1e-7, 359.999999999), "oblique"),
        Segment.about_axis(0.1 + 0.2, 7.0, "z", -360.0),
    ]
    p = tmp_path / "s.csv"
    write_segments(segs, p)
    assert p.read_text().splitlines()[0] == ",".join(SEGMENTS_HEADER)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the current layout is read without a warning
        back = read_segments(p)
    assert back == segs  # bit-exact: repr of every float
    assert as_segments(p) == segs and as_segments(str(p)) == segs and as_segments(segs) == segs
    assert as_segments(None) == []


def test_label_column_optional_and_comments(tmp_path):
    p = tmp_path / "s.csv"
    p.write_text(
        "# hand turns\nt_start_s,t_end_s,kind,angle_x_deg,angle_y_deg,angle_z_deg\n\n1,2,rotation,0,0,90\n3,4,still,,,\n5,6,still,0,0,0\n"
    )
    s = read_segments(p)
    assert s == [Segment.about_axis(1, 2, "z", 90.0), Segment.still(3, 4), Segment.still(5, 6)]


def test_older_one_axis_layout_read_with_a_warning(tmp_path):
    p = tmp_path / "old.csv"
    p.write_text("t_start_s,t_end_s,axis,angle_deg\n1.0,5.0,y,-360\n6,7,x,720\n")
    with pytest.warns(RepairWarning, match="older segments layout t_start_s,t_end_s,axis,angle_deg"):
        s = read_segments(p)
    assert s == [Segment.about_axis(1.0, 5.0, "y", -360.0), Segment.about_axis(6.0, 7.0, "x", 720.0)]
    p.write_text("t_start_s,t_end_s,axis,angle_deg\n1,2,w,90\n")
    with pytest.warns(RepairWarning), pytest.raises(GyroInputError, match="line 2: segment axis must be x, y or z"):
        read_segments(p)


def test_older_loop_layout_read_with_a_warning(tmp_path):
    p = tmp_path / "old.csv"
    p.write_text("start_s,stop_s,kind,angle_x_deg,angle_y_deg,angle_z_deg\n1,5,rotation,720,0,0\n6,9,still,,,\n")
    with pytest.warns(RepairWarning, match="older segments layout start_s,stop_s,kind"):
        s = read_segments(p)
    assert s == [Segment.about_axis(1.0, 5.0, "x", 720.0), Segment.still(6.0, 9.0)]
    p.write_text("start_s,stop_s,kind,angle_x_rad,angle_y_rad,angle_z_rad\n1,5,rotation,0,-6.283185307179586,0\n")
    with pytest.warns(RepairWarning, match="converted from rad to deg"):
        s = read_segments(p)
    # rad -> deg -> rad: equal to a rounding error of the last bit
    assert s[0].angle_S_rad[1] == pytest.approx(-2 * np.pi, rel=4e-16)
    p.write_text("start_s,stop_s,kind\n0,20,still\n")
    with pytest.warns(RepairWarning):
        assert read_segments(p) == [Segment.still(0.0, 20.0)]
    p.write_text("start_s,stop_s,kind\n1,2,rotation\n")
    with pytest.warns(RepairWarning), pytest.raises(GyroInputError, match="line 2: rotation segments need"):
        read_segments(p)


@pytest.mark.parametrize(
    "text, match",
    [
        ("", "empty segments file"),
        ("# only a comment\n", "empty segments file"),
        ("a,b,c\n1,2,3\n", "header must be"),
        (",".join(SEGMENTS_HEADER) + "\n1,2,rotation,90,0\n", "line 2: expected at least 6 values"),
        (",".join(SEGMENTS_HEADER) + "\n1,2,rotation,90,,0\n", "line 2: a rotation segment needs all three angles"),
        (",".join(SEGMENTS_HEADER) + "\n1,2,still,90,0,0\n", "line 2: a still segment has no rotation angle"),
        (",".join(SEGMENTS_HEADER) + "\n1,2,turn,90,0,0\n", "line 2: segment kind must be"),
        (",".join(SEGMENTS_HEADER) + "\n1,x,still,,,\n", "line 2: not a valid segment"),
        (",".join(SEGMENTS_HEADER) + "\n2,1,still,,,\n", "line 2: segment 2.0..1.0 s"),
    ],
)
def test_bad_files_are_one_line_errors(tmp_path, text, match):
    p = tmp_path / "s.csv"
    p.write_text(text)
    with pytest.raises(GyroInputError, match=match) as exc:
        read_segments(p)
    assert "\n" not in str(exc.value)


def test_missing_file_and_bad_items(tmp_path):
    with pytest.raises(GyroInputError, match="no such segments file"):
        read_segments(tmp_path / "nope.csv")
    with pytest.raises(GyroInputError, match="not a segment"):
        as_segments([(1.0, 2.0, "x", 90.0)])


def test_write_is_atomic_and_respects_overwrite(tmp_path):
    p = tmp_path / "s.csv"
    write_segments([Segment.still(0, 1)], p)
    with pytest.raises(GyroInputError):
        write_segments([Segment.still(0, 2)], p, overwrite=False)
    assert read_segments(p) == [Segment.still(0, 1)]
    assert [f.name for f in tmp_path.iterdir()] == ["s.csv"]  # no temporary left behind


def test_public_api():
    assert gyrocore.Segment is Segment
    assert gyrocore.read_segments is read_segments and gyrocore.write_segments is write_segments
