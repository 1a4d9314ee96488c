"""Data files as a new user writes them: time in ms/us/ns, other separators, pandas Parquet,
a BOM, Windows line ends, columns in another order with extra ones."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from gyrocore.cli import build_group, run_cli
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import read_csv, read_recording

RATE = 200.0
N = 4000


def _gh(capsys, *argv):
    status = run_cli(build_group(["gyrocore.cli.commands"]), list(argv))
    out, err = capsys.readouterr()
    return status, out, err


@pytest.fixture()
def frame():
    rng = np.random.default_rng(4)
    t = np.arange(N) / RATE
    g = 2e-3 * rng.standard_normal((N, 3)) + [0.01, -0.02, 0.005]
    a = np.tile([0.0, 0.0, 9.81], (N, 1)) + 0.02 * rng.standard_normal((N, 3))
    return pd.DataFrame(
        {
            "t_s": t,
            **{f"gyro_{c}_rad_s": g[:, i] for i, c in enumerate("xyz")},
            **{f"accel_{c}_m_s2": a[:, i] for i, c in enumerate("xyz")},
        }
    )


@pytest.mark.parametrize("col, factor", [("t_ms", 1e3), ("t_us", 1e6), ("t_ns", 1e9)])
@pytest.mark.parametrize("kind", ["csv", "parquet"])
def test_time_in_ms_us_ns_columns(tmp_path, frame, col, factor, kind):
    """A counter column t_ms / t_us / t_ns (integers, as loggers write them; pandas Parquet with
    its index) reads as seconds: the same times as t_s to the counter's resolution."""
    d = frame.rename(columns={"t_s": col})
    d[col] = np.round(frame["t_s"].to_numpy() * factor).astype(np.int64)
    p = tmp_path / f"f.{kind}"
    d.to_csv(p, index=False) if kind == "csv" else d.to_parquet(p)
    rec = read_recording(p)
    np.testing.assert_allclose(rec.t_s, frame["t_s"].to_numpy(), rtol=0, atol=0.5 / factor)
    assert rec.rate_hz == pytest.approx(RATE, rel=1e-9)


def test_seconds_column_holding_a_counter_is_refused_not_a_traceback(tmp_path, frame, capsys):
    """t_s filled with microseconds: `noise` used to end in a ZeroDivisionError traceback (and a
    millisecond counter silently gave a noise density sqrt(1000) off); now one error line."""
    for factor, unit in ((1e6, "us"), (1e3, "ms")):
        d = frame.copy()
        d["t_s"] = np.round(d["t_s"] * factor).astype(np.int64)
        p = tmp_path / f"counter_{unit}.csv"
        d.to_csv(p, index=False)
        status, _out, err = _gh(capsys, "noise", str(p))
        assert status == 2 and err.startswith("error: ") and len(err.strip().splitlines()) == 1, err
        assert "t_ms, t_us or t_ns" in err and "Traceback" not in err


def test_millisecond_counter_at_1khz_labelled_seconds_warns(tmp_path):
    t_ms = np.arange(3000)  # a 1 kHz logger's millis(): dt = 1 "s" if read as seconds
    g = 1e-3 * np.random.default_rng(1).standard_normal((3000, 3))
    p = tmp_path / "millis.csv"
    pd.DataFrame({"t_s": t_ms, "gyro_x_rad_s": g[:, 0], "gyro_y_rad_s": g[:, 1], "gyro_z_rad_s": g[:, 2]}).to_csv(
        p, index=False
    )
    with pytest.warns(UserWarning, match="rename the column t_ms"):
        read_csv(p)


def test_two_time_columns_is_an_error(tmp_path, frame):
    d = frame.assign(t_ms=frame["t_s"] * 1e3)
    p = tmp_path / "two.csv"
    d.to_csv(p, index=False)
    with pytest.raises(GyroInputError, match="several time columns"):
        read_csv(p)


@pytest.mark.parametrize("sep, name", [(";", "';'"), ("\t", "tab")])
def test_other_separator_is_named_in_the_error(tmp_path, frame, capsys, sep, name):
    p = tmp_path / "semi.csv"
    frame.to_csv(p, index=False, sep=sep)
    status, _o, err = _gh(capsys, "bias", str(p))
    assert status == 2 and f"separated by {name}" in err and len(err.strip().splitlines()) == 1


def test_bom_crlf_reordered_extra_columns_and_pandas_parquet_read_the_same(tmp_path, frame, capsys):
    """What a spreadsheet or pandas writes: a UTF-8 BOM, CRLF line ends, the columns in another
    order with a text column and a temperature, Parquet with the pandas index — all give the
    bias of the plain file, bit for bit."""
    plain = tmp_path / "plain.csv"
    frame.to_csv(plain, index=False)
    variants = {"bom.csv": dict(encoding="utf-8-sig"), "crlf.csv": dict(lineterminator="\r\n")}
    for name, kw in variants.items():
        frame.to_csv(tmp_path / name, index=False, **kw)
    cols = list(frame.columns)
    frame.assign(temp_c=25.0)[["temp_c", cols[3], "t_s", cols[1], cols[2], *cols[4:]]].to_csv(
        tmp_path / "order.csv", index=False
    )
    frame.to_parquet(tmp_path / "pandas.parquet")  # with pandas' index metadata
    frame.set_index("t_s").to_parquet(tmp_path / "pandas_idx.parquet")  # t_s stored as the index
    ref = None
    for name in ["plain.csv", *variants, "order.csv", "pandas.parquet", "pandas_idx.parquet"]:
        status, out, err = _gh(capsys, "bias", str(tmp_path / name), "--json")
        assert status == 0, (name, err)
        b = json.loads(out)["bias_rad_s"]
        ref = ref or b
        assert b == ref, name


def test_quoted_header_pandas_index_and_trailing_comma(tmp_path, frame, capsys):
    """R's write.csv and MATLAB quote the header; pandas' to_csv() writes its index as a first
    column with no name; some loggers end every line with a comma. Each used to be refused
    ('missing required column t_s', 'empty column name in header'); now read, the unnamed column
    kept as an extra column with a warning, and the bias is the plain file's."""
    import csv

    frame.to_csv(tmp_path / "plain.csv", index=False)
    frame.to_csv(tmp_path / "quoted.csv", index=False, quoting=csv.QUOTE_NONNUMERIC)
    frame.to_csv(tmp_path / "index.csv")
    lines = (tmp_path / "plain.csv").read_text().splitlines()
    (tmp_path / "trailing.csv").write_text("".join(line + ",\n" for line in lines))
    status, out, _e = _gh(capsys, "bias", str(tmp_path / "plain.csv"), "--json")
    ref = json.loads(out)["bias_rad_s"]
    for name in ("quoted.csv", "index.csv", "trailing.csv"):
        status, out, err = _gh(capsys, "bias", str(tmp_path / name), "--json")
        assert status == 0, (name, err)
        assert json.loads(out)["bias_rad_s"] == ref, name
        if name != "quoted.csv":
            assert "without a name" in err


def test_parquet_datetime_time_column_error_says_how_to_store_it(tmp_path, frame):
    d = frame.copy()
    d["t_s"] = pd.to_datetime(d["t_s"], unit="s")
    p = tmp_path / "dt.parquet"
    d.to_parquet(p)
    with pytest.raises(GyroInputError, match=r"not numeric \(timestamp\[ns\]\); store the time as numbers"):
        read_recording(p)
