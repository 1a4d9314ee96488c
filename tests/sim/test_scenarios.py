"""Scenarios: every registered scenario runs, is reproducible per seed, and does what it says."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from gyrocore.data.jsonable import to_jsonable
from gyrocore.effects.registry import EFFECTS
from gyrocore.errors import GyroInputError
from gyrocore.data.recording import read_csv, write_csv
from sim import scenarios as S

ALL_BUT_VIB = [e for e in EFFECTS if e != "vibration"]
# short, cheap versions of every scenario (duration s, gyro rate Hz)
SHORT = {
    "static": (3.0, 200.0),
    "static_bumped": (6.0, 200.0),
    "turntable": (45.0, 100.0),
    "thermal": (120.0, 50.0),
    "hover": (1.5, 500.0),
    "power_cycles": (4.0, 200.0),
}


def test_registry_has_the_required_scenarios():
    assert set(SHORT) <= set(S.SCENARIOS)


@pytest.mark.parametrize("name", sorted(S.SCENARIOS))
def test_every_scenario_runs_and_records_the_truth(name):
    dur, rate = SHORT.get(name, (5.0, 200.0))
    res = S.simulate(name, duration_s=dur, gyro_rate_hz=rate, seed=3)
    rec, tr = res.recording, res.truth
    assert rec.n == tr.n and rec.n > 0
    assert rec.duration_s <= dur + 1e-9
    assert np.array_equal(rec.ref_rate_rad_s, tr.omega_S_rad_s)
    assert np.array_equal(rec.ref_quat_wxyz, tr.q_SW_wxyz)
    assert np.array_equal(rec.temp_c, tr.temp_c) and np.array_equal(rec.accel_m_s2, tr.f_S_m_s2)
    assert np.all(np.isfinite(rec.gyro_rad_s))
    for k in ("sensor", "scenario", "seed", "rate_hz", "params_true", "effects"):
        assert k in rec.meta
    assert rec.meta["scenario"] == name and float(rec.meta["rate_hz"]) == rate
    pt = json.loads(rec.meta["params_true"])
    assert set(pt) == set(res.params_true)
    assert np.allclose(pt["scale"]["s"], res.params_true["scale"]["s"], rtol=0, atol=0)
    # the recording is the batch measurement of the truth with the unit's parameters
    assert not np.array_equal(rec.gyro_rad_s, tr.omega_S_rad_s)


def test_same_seed_bit_identical_file(tmp_path):
    a = S.simulate("static_bumped", duration_s=7.0, gyro_rate_hz=200.0, seed=4)
    b = S.simulate("static_bumped", duration_s=7.0, gyro_rate_hz=200.0, seed=4)
    c = S.simulate("static_bumped", duration_s=7.0, gyro_rate_hz=200.0, seed=5)
    write_csv(a.recording, tmp_path / "a.csv")
    write_csv(b.recording, tmp_path / "b.csv")
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()
    assert not np.array_equal(a.recording.gyro_rad_s, c.recording.gyro_rad_s)
    # different bumps for a different seed
    assert not np.array_equal(a.truth.omega_S_rad_s, c.truth.omega_S_rad_s)
    back = read_csv(tmp_path / "a.csv")
    assert np.array_equal(back.gyro_rad_s, a.recording.gyro_rad_s)


def test_power_cycles_redraw_turn_on_bias_and_restart_cold():
    sig = 0.01
    res = S.simulate(
        "power_cycles",
        duration_s=5.0,
        gyro_rate_hz=200.0,
        seed=2,
        without=[e for e in ALL_BUT_VIB if e != "bias"],
        overrides={"bias": {"turn_on_sigma_rad_s": sig}},
    )
    tr = res.truth
    pu = tr.power_up_index
    assert list(np.unique(pu)) == [0, 1, 2, 3, 4]
    per = res.params_true["bias"]["b_rad_s_per_power_up"]
    assert per.shape == (5, 3)
    err = res.recording.gyro_rad_s - tr.omega_S_rad_s
    for k in range(5):
        m = pu == k
        assert np.allclose(err[m], per[k], rtol=1e-12, atol=1e-15)
        assert tr.t_since_power_up_s[m][0] == 0.0
        assert tr.temp_c[m][0] == pytest.approx(25.0)  # cold start at ambient
        assert tr.temp_c[m][-1] > tr.temp_c[m][0]  # then self-heating
    # the turn-on draws differ between power-ups by ~σ: all pairwise differences non-zero
    assert np.all(np.abs(np.diff(per, axis=0)) > 0)
    assert np.allclose(S.true_bias_rad_s(res), per[pu])
    assert json.loads(res.recording.meta["power_up_t_s"]) == pytest.approx([0.0, 1.0, 2.0, 3.0, 4.0])


def test_static_bumped_moves_first_then_is_still():
    res = S.simulate("static_bumped", duration_s=10.0, gyro_rate_hz=200.0, seed=1)
    w = np.linalg.norm(res.truth.omega_S_rad_s, axis=1)
    t = res.truth.t_s
    moving = w > 0.05
    assert moving.any() and t[moving][0] < 1.0 and t[moving][-1] < 6.0
    assert np.all(w[t > 7.0] < 1e-6)


def test_turntable_profile_fits_duration_with_exact_turns():
    res = S.simulate("turntable", duration_s=45.0, gyro_rate_hz=100.0, seed=0, without=ALL_BUT_VIB)
    phases = json.loads(res.recording.meta["table_phases"])
    turns = [p for p in phases if p["kind"] == "segment" and p["rate_rad_s"] != 0.0]
    mounts = {p["mount"] for p in turns}
    assert {"+x", "+y", "+z"} <= mounts
    rev = abs(turns[0]["angle_rad"]) / (2 * math.pi)
    assert rev >= 1.0 and abs(rev * 4 - round(rev * 4)) < 1e-12  # multiple of 1/4 turn
    assert sorted({math.copysign(1, p["rate_rad_s"]) for p in turns}) == [-1.0, 1.0]
    full = S.build_table_profile(S.load_scenario("turntable"), None)
    assert full.duration_s > 300  # the full run: 6 mounts, 5 turns each way at 2 rates
    # shortest form: x, y, z up, quarter turns each way at the fastest rate
    short = S.build_table_profile(S.load_scenario("turntable"), 20.0)
    assert short.duration_s <= 20.0 and {seg.mount for seg in short.segments} == {"+x", "+y", "+z"}
    with pytest.raises(GyroInputError, match="at least"):
        S.simulate("turntable", duration_s=8.0)


def test_thermal_ramps_up_and_down_with_motion_and_rest():
    res = S.simulate("thermal", duration_s=300.0, gyro_rate_hz=20.0, seed=0)
    T = res.truth.temp_c
    assert T.max() > T[0] + 15 and T[-1] < T.max() - 10
    w = np.linalg.norm(res.truth.omega_S_rad_s, axis=1)
    assert np.mean(w > 0.5) > 0.1 and np.mean(w < 1e-6) > 0.1
    assert "lowpass" in " ".join(res.notes)  # the 250 Hz DLPF cannot run at 20 Hz


def test_hover_gyro_in_the_loop_is_the_recording():
    res = S.simulate("hover", duration_s=1.5, gyro_rate_hz=500.0, seed=0)
    log = res.flight_log
    # what the controller read (GyroStream) is bit-identical to the batch recording
    assert np.array_equal(log.gyro_meas_rad_s, res.recording.gyro_rad_s)
    # rotor vibration reaches the truth: a line at the rotor frequency (imbalance, 1st
    # harmonic) that the same flight without vibration does not have
    from sim.controller import small_steps
    from sim.quadrotor import fly_hover

    calm, calm_log = fly_hover(duration_s=1.5, vibration=False, manoeuvres=small_steps(1.5), gyro_rate_hz=500.0, seed=0)

    def rotor_line(truth, flight):  # Hann-windowed periodogram of the last second, ±5 Hz around f_rotor
        f_rot = np.abs(flight.rotor_speed_rad_s[-500:]).mean() / (2 * np.pi)
        w = truth.omega_S_rad_s[-500:] - truth.omega_S_rad_s[-500:].mean(axis=0)
        spec = (np.abs(np.fft.rfft(w * np.hanning(500)[:, None], axis=0)) ** 2).sum(axis=1)
        f = np.fft.rfftfreq(500, 1 / 500.0)
        assert 30 < f_rot < 240  # hover rotor speed of a 450-mm quad, below Nyquist here
        return spec[np.abs(f - f_rot) < 5].sum()

    assert rotor_line(res.truth, log) > 30 * rotor_line(calm, calm_log)
    # earth rate rides in the loop (fly_hover passes the attitude); a temperature-rate bias
    # cannot (motor heating makes dT/dt depend on the flight): flown without, recorded with
    r2 = S.simulate(
        "hover", duration_s=0.5, gyro_rate_hz=500.0, seed=0, overrides={"earth_rate": {}, "bias_temp_rate": {}}
    )
    assert "earth_rate" in r2.params_true and "bias_temp_rate" in r2.params_true
    assert any("bias_temp_rate" in n for n in r2.notes) and not any("earth_rate" in n for n in r2.notes)
    assert not np.array_equal(r2.flight_log.gyro_meas_rad_s, r2.recording.gyro_rad_s)
    r3 = S.simulate("hover", duration_s=0.5, gyro_rate_hz=500.0, seed=0, overrides={"earth_rate": {}})
    assert np.array_equal(r3.flight_log.gyro_meas_rad_s, r3.recording.gyro_rad_s)


def test_overrides_reach_the_recording_and_floor():
    res = S.simulate(
        "static",
        duration_s=2.0,
        gyro_rate_hz=200.0,
        seed=0,
        overrides={"bias_ramp": {"ramp_rad_s2": [1e-3, 0, 0]}},
        without=["quantization"],
    )
    assert "bias_ramp" in res.params_true and res.recording.meta["overridden"] == "bias_ramp"
    assert "quantization" not in res.params_true and "quantization" in res.recording.meta["without"]
    assert np.array_equal(S.floor_gyro(res), res.truth.omega_S_rad_s + res.noise_rad_s)


def test_run_is_a_new_session():
    a = S.simulate("static", duration_s=1.0, gyro_rate_hz=200.0, seed=6)
    b = S.simulate("static", duration_s=1.0, gyro_rate_hz=200.0, seed=6, run=1)
    assert np.array_equal(a.params_true["scale"]["s"], b.params_true["scale"]["s"])
    assert not np.array_equal(a.params_true["bias"]["b_rad_s"], b.params_true["bias"]["b_rad_s"])


def test_bad_scenario_files(tmp_path):
    p = tmp_path / "x.toml"
    p.write_text('kind = "boat"\nduration_s = 1\n', encoding="utf-8")
    with pytest.raises(GyroInputError, match="kind"):
        S.load_scenario(str(p))
    p.write_text('kind = "table"\nduration_s = 1\nwarp = 1\n[table]\nprofile = "static"\n', encoding="utf-8")
    with pytest.raises(GyroInputError, match="unknown key"):
        S.load_scenario(str(p))
    p.write_text('kind = "table"\nduration_s = 2\n[table]\nprofile = "static"\n[thermal]\nfoo = 1\n', encoding="utf-8")
    with pytest.raises(GyroInputError, match="thermal"):
        S.simulate(str(p), gyro_rate_hz=100.0)
    with pytest.raises(GyroInputError, match="unknown scenario"):
        S.simulate("nope")
    p.write_text('kind = "hover"\nduration_s = 20\n[hover]\nground_s = -1\n', encoding="utf-8")
    with pytest.raises(GyroInputError, match="ground_s"):
        S.load_scenario(str(p))


def test_hover_powers_up_on_the_ground_and_the_static_bias_calibration_finds_it():
    from gyrocore.calib.bias import StaticBiasCalibrator
    from sim.quadrotor import TAKEOFF_CLIMB_S

    spec = S.load_scenario("hover")
    ground = float(spec.hover["ground_s"])
    dur = ground + TAKEOFF_CLIMB_S + S.MIN_AIRBORNE_S  # shortest flight with the ground phase
    assert S.hover_ground_s(spec, dur) == ground and S.hover_ground_s(spec, dur - 0.1) == 0.0
    # g-sensitivity (H g ~ 3e-4 rad/s here, 4 sigma) and the thermal bias add their own static
    # offsets on the ground: off, so that the still window measures the turn-on bias alone
    res = S.simulate("hover", duration_s=dur, gyro_rate_hz=500.0, seed=0, without=["g_sensitivity", "bias_thermal"])
    assert res.recording.meta["ground_s"] == f"{ground:g}"
    t = res.truth.t_s
    on_ground = t < ground
    assert np.linalg.norm(res.truth.omega_S_rad_s[on_ground], axis=1).max() < 2e-6  # bound: tests/sim/test_hover.py
    assert res.flight_log.pos_W_m[-1, 2] > 0.9  # took off
    # the manoeuvres come after the take-off: no rate set point beyond the hover loops' before
    rate_sp_deg_s = np.degrees(np.abs(res.flight_log.rate_sp_rad_s[t < ground + TAKEOFF_CLIMB_S])).max()
    assert rate_sp_deg_s < 1.0, rate_sp_deg_s
    fit = StaticBiasCalibrator().fit(res.recording)
    # the first still window lies in the ground phase
    assert fit.window_start_s + fit.window_s <= ground
    # Turn-on bias within 4 standard errors per axis: bias_se = sigma VIF / sqrt(n) of the
    # window mean (ARW 0.0028 deg/s/sqrt(Hz) over 0.4 s: 7.7e-5 rad/s); P(|z| > 4) = 6e-5 per axis.
    b_true = S.true_bias_rad_s(res)[0]
    assert np.all(np.abs(fit.bias_rad_s - b_true) < 4.0 * fit.bias_se_rad_s)
    # a short flight has no room for the ground phase: airborne start, said in the notes
    short = S.simulate("hover", duration_s=1.0, gyro_rate_hz=500.0, seed=0)
    assert "ground_s" not in short.recording.meta and any("no ground phase" in n for n in short.notes)


# ---------------------------------------------------------------- chunked simulation (bounded memory)
#: Short runs of every registered scenario for the chunked == whole test (a scenario added later
#: without an entry runs at its own duration, at most 30 s).
CHUNKED_RUNS = {
    "static": dict(duration_s=20.0, seed=1),
    "static_bumped": dict(duration_s=20.0, seed=3, run=1),
    "power_cycles": dict(duration_s=30.0, seed=2),
    "thermal": dict(duration_s=200.0, gyro_rate_hz=200.0),
    "turntable": dict(
        duration_s=90.0, sensor="adis16448", overrides={"time_offset": {"tau_s": -0.003}, "rrw": {}, "correlated": {}}
    ),
    # 16 s: the ground phase (5 s), take-off (3 s) and the manoeuvres are flown
    "hover": dict(duration_s=16.0, seed=5, run=1),
}


def _short(name: str) -> dict:
    if name in CHUNKED_RUNS:
        return CHUNKED_RUNS[name]
    return dict(duration_s=min(S.load_scenario(name).duration_s or 30.0, 30.0))


def _assert_chunked_is_whole(name, kw, chunk_rows):
    from gyrocore.data.recording import concat_recordings

    res = S.simulate(name, **kw)
    st = S.simulate(name, chunk_rows=chunk_rows, **kw)
    assert st.bounded and st.meta == res.recording.meta and st.n_samples == res.recording.n
    assert st.notes == res.notes and json.dumps(to_jsonable(st.params_true)) == json.dumps(to_jsonable(res.params_true))
    recs = list(st.chunks())
    assert max(r.n for r in recs) <= chunk_rows
    rec = concat_recordings(recs)
    a = res.recording
    for f in ("t_s", "gyro_rad_s", "accel_m_s2", "temp_c", "ref_rate_rad_s", "ref_quat_wxyz"):
        assert np.array_equal(getattr(rec, f).view(np.uint64), np.asarray(getattr(a, f), float).view(np.uint64)), f
    assert np.array_equal(rec.extra["power_up_index"], a.extra["power_up_index"])
    with pytest.raises(GyroInputError):
        st.chunks()


@pytest.mark.parametrize("name", sorted(S.SCENARIOS))
@pytest.mark.parametrize("chunk_rows", [997, 4096])
def test_chunked_equals_whole_bit_for_bit(name, chunk_rows):
    """simulate(chunk_rows=...) (physics — rate table or closed-loop flight —, temperature,
    power-ups, gyro and noise all in chunks) gives the recording of the whole path bit for bit
    and the same metadata, whatever the chunk size, for every registered scenario."""
    _assert_chunked_is_whole(name, _short(name), chunk_rows)


def test_chunked_hover_with_temperature_rate_and_a_leading_gyro(tmp_path):
    """A hover without motor heating flies bias_temp_rate (its dT/dt block by block,
    sim.thermal.TempRateBlocks); a leading time offset is left out of the loop and put in the
    recording (a note); both paths agree bit for bit."""
    toml = tmp_path / "warm_hover.toml"
    toml.write_text(
        'kind = "hover"\nduration_s = 3.0\n[hover]\nvibration = true\n'
        "[thermal]\ntime_constant_s = 1.0\nambient_c = [[0.0, 20.0], [2.0, 35.0]]\n"
    )
    deg = math.pi / 180.0
    kw = dict(seed=2, overrides={"bias_temp_rate": {"k_rad_s_per_c_per_s": 0.01 * deg}, "rrw": {}})
    res = S.simulate(str(toml), **kw)
    assert "bias_temp_rate" in res.params_true and not res.notes
    _assert_chunked_is_whole(str(toml), kw, 700)
    lead = dict(kw, overrides={**kw["overrides"], "time_offset": {"tau_s": -0.002}})
    assert any("without time_offset" in n for n in S.simulate(str(toml), chunk_rows=500, **lead).notes)
    _assert_chunked_is_whole(str(toml), lead, 500)


def test_simulate_stream_is_simulate_with_chunk_rows():
    # one entry point: simulate_stream(name, chunk_rows=N, **options) is simulate(name, chunk_rows=N, **options)
    from gyrocore.data.recording import concat_recordings

    a = concat_recordings(list(S.simulate_stream("static", duration_s=3.0, chunk_rows=500).chunks()))
    b = concat_recordings(list(S.simulate("static", duration_s=3.0, chunk_rows=1000).chunks()))
    assert np.array_equal(a.gyro_rad_s, b.gyro_rad_s)
    for bad in (0, -3, 2.5, True):
        with pytest.raises(GyroInputError, match="chunk_rows"):
            S.simulate("static", duration_s=3.0, chunk_rows=bad)


@pytest.mark.parametrize(
    "name, kw",
    [("static", dict(duration_s=2.0, gyro_rate_hz=200.0)), ("power_cycles", dict(duration_s=3.0, gyro_rate_hz=100.0))],
)
def test_stream_with_one_row_chunks(name, kw):
    """Chunks shorter than the physics-to-gyro ratio (one physics step per rollout, most with no
    gyro sample) and single-sample temperature chunks still give simulate()'s rows."""
    from gyrocore.data.recording import concat_recordings

    a = S.simulate(name, **kw).recording
    rec = concat_recordings(list(S.simulate_stream(name, chunk_rows=1, **kw).chunks()))
    for f in ("t_s", "gyro_rad_s", "accel_m_s2", "temp_c", "ref_rate_rad_s", "ref_quat_wxyz"):
        assert np.array_equal(getattr(rec, f), getattr(a, f)), f
