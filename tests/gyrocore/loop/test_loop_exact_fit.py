"""The residual loop on three hand turns (sunsided set-1, the docs' integral-method session):
with bias declared, misalignment's 6 parameters leave none of the 9 window residuals free. The
F-test's residual dof was floored at 1, so the exact fit read as F ~ 1e26 and the loop 'found'
a misalignment of 6 rad with attitude error 40 deg -> 1e-12 deg."""

from __future__ import annotations

import json

from gyrocore.cli import build_group, run_cli


def test_exactly_determined_candidate_is_not_testable(shared_data, tmp_path, capsys):
    g = build_group(["gyrocore.cli.commands"])
    s = shared_data / "sunsided_mpu6050" / "set-1"
    rot, seg = tmp_path / "rot.csv", tmp_path / "seg.csv"
    assert (
        run_cli(
            g,
            [
                "convert",
                str(s / "rotate-360ccw-around-x-pointing-forward"),
                "--append",
                str(s / "rotate-360ccw-around-y-pointing-left"),
                "--append",
                str(s / "rotate-360ccw-around-z-pointing-up"),
                "-o",
                str(rot),
                "--segments-out",
                str(seg),
            ],
        )
        == 0
    )
    capsys.readouterr()
    status = run_cli(g, ["loop", str(rot), "--segments", str(seg), "--effects", "bias", "--json"])
    j = json.loads(capsys.readouterr().out)
    assert status == 0
    assert all(f["evidence"]["df2"] >= 1 for f in j["found"])
    assert "misalignment" not in [f["effect"] for f in j["found"]]
    assert j["attitude_error_after_deg"] > 1.0  # nothing is fitted to zero
