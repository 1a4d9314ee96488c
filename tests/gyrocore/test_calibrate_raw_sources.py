"""`calibrate` on a source as shipped (not converted first): its reader's known rotations, folders.

Before: `calibrate example_ferraris_session.csv --effects bias,scale,misalignment` ignored the
three 360° turns the imucal reader knows and left all nine scale/misalignment parameters
"unobservable"; a recording folder (sunsided, gnss-ins-sim) was refused by the argument type,
and once read, the parameter file's SHA-256 of a folder raised IsADirectoryError.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from gyrocore.data.recording import file_sha256
from tests.gyrocore.test_bad_input import gh


def _params(path):
    return json.loads(path.read_text())["parameters"]


def test_known_rotations_of_the_source_are_used_as_the_segments_file_would_be(capsys, shared_data, tmp_path):
    raw = shared_data / "imucal_ferraris" / "example_ferraris_session.csv"
    eff = "bias,scale,misalignment"
    s, _, err = gh(capsys, "calibrate", raw, "--effects", eff, "-o", tmp_path / "direct.json")
    assert s == 0, err
    assert any("calibrating against the 3 known rotations its reader defines" in ln for ln in err), err
    # the two-step route the docs give: convert with --segments-out, calibrate --segments
    conv, seg = tmp_path / "f.csv", tmp_path / "seg.csv"
    assert gh(capsys, "convert", raw, "-o", conv, "--segments-out", seg)[0] == 0
    s, _, err = gh(capsys, "calibrate", conv, "--segments", seg, "--effects", eff, "-o", tmp_path / "two.json")
    assert s == 0, err
    a, b = _params(tmp_path / "direct.json"), _params(tmp_path / "two.json")
    for e in ("bias", "scale", "misalignment"):
        for k in a[e]:
            # the converted file holds the same samples to %.17g: equal to rounding
            assert np.allclose(a[e][k], b[e][k], rtol=1e-9, atol=1e-12), (e, k)
    # PROVENANCE: raw integrals -371.9, -354.8, -359.2 deg against -360: scale x +3.3 %, y -1.4 %
    # before the bias correction; the fit's scale is in that neighbourhood (hand turns: +-2-5 deg)
    s_fit = np.asarray(a["scale"]["s"])
    assert s_fit[0] > 0.01 and s_fit[1] < -0.005 and abs(s_fit[2]) < 0.01, s_fit


def test_rotations_about_one_axis_are_named_not_used(capsys, shared_data, tmp_path):
    raw = shared_data / "tomisuarez2_mpu6050" / "imu_90_x_rot.csv"
    s, _, err = gh(capsys, "calibrate", raw, "--effects", "bias", "-o", tmp_path / "p.json")
    assert s == 0, err
    assert any("turn about 1 axis/axes; the integral method needs all three" in ln for ln in err), err


def test_folder_recording_is_read_and_hashed(capsys, shared_data, tmp_path):
    folder = shared_data / "gnss_ins_sim_logged_360z" / "bosch"
    out = tmp_path / "p.json"
    s, _, err = gh(capsys, "calibrate", folder, "--effects", "bias", "-o", out)
    assert s == 0, err
    blob = out.read_text()
    assert file_sha256(folder) in blob


def test_folder_digest_follows_its_files(tmp_path):
    d = tmp_path / "rec"
    d.mkdir()
    (d / "a.csv").write_text("1\n")
    (d / "b.csv").write_text("2\n")
    h1 = file_sha256(d)
    (d / "b.csv").write_text("3\n")
    h2 = file_sha256(d)
    (d / "b.csv").rename(d / "c.csv")
    assert len({h1, h2, file_sha256(d)}) == 3
    assert file_sha256(d) != file_sha256(d / "a.csv")
    with pytest.raises(FileNotFoundError):
        file_sha256(tmp_path / "missing")


@pytest.mark.parametrize(
    "rel",
    [
        "sunsided_mpu6050/set-2/rotate-ccw-around-z-pointing-up",  # two hand turns, no still part
        "sunsided_mpu6050/set-1/tilt-sphere",  # tilted about by hand throughout
        "blackbox_public/LOG00037.BFL",  # a 17-s flight
    ],
)
def test_bias_of_a_record_moving_throughout_is_refused(capsys, shared_data, tmp_path, rel):
    """Without a reference the fit is against rate 0 on the still windows; the rotation gate
    (noise from the window-variance quantile) called the slowest motion "still" and gave a bias
    of 14.7 deg/s (rotate-z, residual 24 deg/s), 16 deg/s (tilt-sphere) or 1.7 deg/s (the
    flight). Those windows' variance is 4.3-21 x what the sample-to-sample differences predict;
    refused, one line."""
    s, _, err = gh(capsys, "calibrate", shared_data / rel, "--effects", "bias", "-o", tmp_path / "p.json")
    errors = [ln for ln in err if ln.startswith("error:")]
    assert s != 0 and len(errors) == 1 and "the record moves throughout" in errors[0], err
    assert not (tmp_path / "p.json").exists()


def test_bias_of_still_records_is_unchanged_by_that_test(capsys, shared_data, tmp_path):
    """A still record, and one that is still for only 3 s of 10 (gnss-ins-sim's 360 deg turn),
    keep their fit: their still windows' noise is what the differences predict."""
    from gyrocore.readers.convert import load_any

    rel = "tomisuarez2_mpu6050/imu_static_test.csv"
    s, _, err = gh(capsys, "calibrate", shared_data / rel, "--effects", "bias", "-o", tmp_path / "a.json")
    assert s == 0, err
    b = np.asarray(_params(tmp_path / "a.json")["bias"]["b_rad_s"])
    g = _quiet_load(load_any, shared_data / rel).gyro_rad_s
    # 98 % of the samples are the still windows': the fit (their mean) is the record's mean to
    # well within one standard error sigma/sqrt(N) (1.3-2.0e-5 rad/s); 3 SE
    assert np.all(np.abs(b - g.mean(axis=0)) < 3 * g.std(axis=0) / np.sqrt(g.shape[0])), (b, g.mean(axis=0))
    s, _, err = gh(
        capsys,
        "calibrate",
        shared_data / "gnss_ins_sim_logged_360z" / "bosch",
        "--effects",
        "bias",
        "-o",
        tmp_path / "b.json",
    )
    assert s == 0, err


def _quiet_load(fn, *a):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*a)
