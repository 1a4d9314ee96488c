"""The integral method's standard errors leave out the known angles' own uncertainty; on a hand
session (imucal's Ferraris, three turns "by hand against a box edge") the report says so."""

from __future__ import annotations

import json

from gyrocore.cli import build_group, run_cli


def _convert_and_calibrate(src, tmp_path, capsys):
    """``convert`` an imucal session with its segments, then ``calibrate --segments`` it (bias,
    scale, misalignment; parameter file p.json); returns the exit status and captured output."""
    g = build_group(["gyrocore.cli.commands"])
    assert (
        run_cli(g, ["convert", str(src), "-o", str(tmp_path / "f.csv"), "--segments-out", str(tmp_path / "s.csv")]) == 0
    )
    capsys.readouterr()
    status = run_cli(
        g,
        [
            "calibrate",
            str(tmp_path / "f.csv"),
            "--segments",
            str(tmp_path / "s.csv"),
            "--effects",
            "bias,scale,misalignment",
            "-o",
            str(tmp_path / "p.json"),
        ],
    )
    return status, capsys.readouterr()


def test_hand_turn_standard_errors_say_what_they_leave_out(shared_data, tmp_path, capsys):
    status, cap = _convert_and_calibrate(
        shared_data / "imucal_ferraris" / "example_ferraris_session.csv", tmp_path, capsys
    )
    out = cap.out
    assert status == 0 and "angles taken as exact" in out
    assert "reads against the reference" not in cap.err  # this session's turns agree with -360 deg
    assert "(integral, 3 known rotations, bias from 6936 still samples," in out  # not "6936 samples"
    assert any("angles taken as exact" in n for n in json.loads((tmp_path / "p.json").read_text())["notes"])


def test_negative_scale_is_called_a_sign_disagreement(shared_data, tmp_path, capsys):
    """imucal's annotated session: its turns integrate positive, the segments carry imucal's
    expected_angle −360°, so the fit gives scale ≈ −200 % (K ≈ −I, as imucal's own snapshot).
    Printed bare, it read as a 200 % sensitivity error; now one warning names the sign."""
    status, cap = _convert_and_calibrate(shared_data / "imucal_ferraris" / "annotated_session.csv", tmp_path, capsys)
    err = cap.err
    assert status == 0 and "reads against the reference" in err
