"""Closed-loop hover: holds attitude and altitude with vibration; the pipeline changes the flight."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from gyrocore.flight.filters import pt1
from sim.controller import Manoeuvre, QuadParams, small_steps
from sim.vehicles import VibrationSpec
from sim.quadrotor import fly_hover
from sim.thermal import ThermalSpec, simulate_temperature

QP = QuadParams()
# hover rotor speed sqrt(m g / (4 c_T)) = 557.5 rad/s -> rotor line at 88.73 Hz
F_ROTOR_HZ = math.sqrt(QP.mass_kg * QP.gravity_m_s2 / (4 * QP.c_t_n_per_rad2_s2)) / (2 * math.pi)
DURATION_S = 8.0
SETTLE_S = 2.0


@pytest.fixture(scope="module")
def hover_vib():
    return fly_hover(duration_s=DURATION_S, vibration=True, seed=3)


@pytest.fixture(scope="module")
def hover_vib_pt1():
    return fly_hover(duration_s=DURATION_S, vibration=True, seed=3, pipeline=pt1(30.0, 1000.0))


def test_hover_holds_attitude_and_altitude_with_vibration(hover_vib):
    truth, log = hover_vib
    k0 = int(SETTLE_S * 1000)
    # Bounds. The vibration forces are the imbalance u Omega^2 = 2e-6 * 557.5^2 = 0.62 N per
    # rotor (+30 % at 2 Omega). Their torques on the frame: in-plane forces at the rotor hubs
    # (lever 0.225 m about z, 0.04 m about x/y): at most 4 * 0.62 * 1.3 * 0.225 = 0.73 N m in
    # yaw -> 0.73 / 0.0366 / Omega^2 = 6.4e-5 rad of attitude ripple, 4 * 0.81 * 0.04 / 0.0211
    # / Omega^2 = 2e-5 rad in roll/pitch. The closed loop adds its own response to that ripple
    # (rate loop |L| < 0.2 at 89 Hz). Bound 0.1 deg = 1.7e-3 rad: > 25 x the forced ripple, and
    # 50 x tighter than the 5 deg manoeuvre steps: a controller that does not hold hover fails.
    assert np.degrees(log.attitude_error_rad()[k0:]).max() < 0.1
    assert np.degrees(log.tilt_rad()[k0:]).max() < 0.1
    # Altitude: axial ripple 2 % of thrust at 177 Hz -> 4 * 0.069 N / 1.4 kg / (2 pi 177)^2 =
    # 1.6e-7 m; the loop itself settles from rest in ~2 s (omega_n = 2 rad/s). Bound 5 mm,
    # position 1 cm (horizontal loop omega_n 1 rad/s, lateral vibration amplitude
    # 4 * 0.62 / 1.4 / Omega^2 = 5.7e-6 m).
    assert np.abs(log.altitude_error_m()[k0:]).max() < 5e-3
    assert np.abs(log.pos_W_m[k0:, :2] - log.pos_sp_W_m[:2]).max() < 1e-2
    # truth is internally consistent with the log (S = B on this model)
    np.testing.assert_array_equal(truth.omega_S_rad_s, log.omega_true_rad_s)
    assert truth.n == int(DURATION_S * 1000)


def test_vibration_reaches_the_sensor_at_the_rotor_lines(hover_vib):
    truth, _ = hover_vib
    k0 = int(SETTLE_S * 1000)
    f, p_acc = signal.welch(truth.f_S_m_s2[k0:, :2], fs=1000.0, nperseg=4096, axis=0)
    p = p_acc.sum(axis=1)
    band = f > 20.0
    f_peak = f[band][np.argmax(p[band])]
    # dominant lateral-acceleration line = the rotor frequency (bin width 0.24 Hz; the hover
    # speed varies by < 0.1 % while holding)
    assert abs(f_peak - F_ROTOR_HZ) < 0.5
    # the second harmonic (in-plane force at 2 Omega) is present: >100x the floor between lines
    i2 = np.argmin(np.abs(f - 2 * F_ROTOR_HZ))
    i_mid = np.argmin(np.abs(f - 1.5 * F_ROTOR_HZ))
    assert p[i2 - 2 : i2 + 3].max() > 100 * p[i_mid]
    # the gyro truth sees the rotor line too (torques from the imbalance)
    fg, pg = signal.welch(truth.omega_S_rad_s[k0:], fs=1000.0, nperseg=4096, axis=0)
    assert abs(fg[band][np.argmax(pg[band].sum(axis=1))] - F_ROTOR_HZ) < 0.5


def test_without_vibration_no_high_frequency():
    truth, log = fly_hover(duration_s=4.0, vibration=False)
    sos = signal.butter(4, 20.0, btype="highpass", fs=1000.0, output="sos")
    hf = signal.sosfiltfilt(sos, truth.f_S_m_s2[2000:], axis=0)
    # nothing excites the frame above 20 Hz: only rounding and the settled control loop
    assert np.sqrt(np.mean(hf**2)) < 1e-4
    assert np.degrees(log.attitude_error_rad()[2000:]).max() < 1e-3


def test_filter_in_the_pipeline_changes_the_flight(hover_vib, hover_vib_pt1):
    _, raw = hover_vib
    _, lp = hover_vib_pt1
    filt = pt1(30.0, 1000.0)
    h = filt.response(np.array([F_ROTOR_HZ, 2 * F_ROTOR_HZ])).magnitude  # ~0.32, ~0.17
    k0 = int(SETTLE_S * 1000)
    sos = signal.butter(4, 60.0, btype="highpass", fs=1000.0, output="sos")
    meas_hf = signal.sosfiltfilt(sos, lp.gyro_meas_rad_s[k0:], axis=0).std(axis=0)
    filt_hf = signal.sosfiltfilt(sos, lp.gyro_filt_rad_s[k0:], axis=0).std(axis=0)
    # the rate loop sees the filtered gyro: above 60 Hz the content is the 1x and 2x rotor
    # lines, so the filtered/measured ratio lies between the PT1 gains at 2x and at 1x
    ratio = filt_hf / meas_hf
    assert np.all(ratio > 0.95 * h[1]) and np.all(ratio < 1.05 * h[0])
    # without a filter the rate loop sees the raw gyro
    np.testing.assert_array_equal(raw.gyro_filt_rad_s, raw.gyro_meas_rad_s)
    # motor-command noise: the rate loop's high-frequency path is linear in the filtered gyro
    # (P and D terms; the integrator and the outer loops are negligible above 20 Hz), so the
    # PT1 scales it by at most |H(88.7 Hz)| = 0.32 for a fixed vibration. The vibration
    # itself is fed back through the motors (mostly the yaw reaction of the rotor speed
    # servos, loop gain ~15 Kp_yaw / omega = 0.11 at 89 Hz), which can raise it by up to
    # 1/(1 - 0.11) = 1.12 x per pass; bound 0.32 * 1.12 ~ 0.36, asserted with margin at 0.5.
    assert lp.motor_noise_n(t_from_s=SETTLE_S) < 0.5 * raw.motor_noise_n(t_from_s=SETTLE_S)


def test_filter_delay_seen_by_the_rate_loop():
    man = small_steps(5.0)
    _, raw = fly_hover(duration_s=5.0, manoeuvres=man)
    _, lp = fly_hover(duration_s=5.0, manoeuvres=man, pipeline=pt1(30.0, 1000.0))
    # PT1 group delay at low frequency: (1-A)/A samples = 1/(2 pi fc) = 5.31 ms at 30 Hz (the
    # manoeuvre band, < 15 Hz, is well below fc: the delay there is within 3 % of that).
    # Cross-correlation peak with parabolic refinement resolves ~0.1 sample; allow 0.5 ms.
    assert abs(raw.gyro_delay_s()) < 0.5e-3
    assert lp.gyro_delay_s() == pytest.approx(1 / (2 * math.pi * 30.0), abs=0.5e-3)
    # and the flight differs: in the steps the body rate reaches ~0.5 rad/s, so a 5 ms later
    # reaction moves the attitude by ~2.5e-3 rad; require 1e-3 rad
    assert np.abs(lp.attitude_error_rad() - raw.attitude_error_rad()).max() > 1e-3


def test_manoeuvres_are_flown():
    man = (
        Manoeuvre(t_start_s=1.0, duration_s=1.5, roll_rad=math.radians(5.0)),
        Manoeuvre(t_start_s=3.0, duration_s=1.5, yaw_rad=math.radians(15.0)),
    )
    _, log = fly_hover(duration_s=5.0, vibration=True, manoeuvres=man)
    q = log.q_WB_wxyz
    roll = np.degrees(np.arctan2(2 * (q[:, 0] * q[:, 1] + q[:, 2] * q[:, 3]), 1 - 2 * (q[:, 1] ** 2 + q[:, 2] ** 2)))
    yaw = np.degrees(np.arctan2(2 * (q[:, 0] * q[:, 3] + q[:, 1] * q[:, 2]), 1 - 2 * (q[:, 2] ** 2 + q[:, 3] ** 2)))
    # attitude loop time constant 1/6 s (roll) and 1/2.5 s (yaw): within 0.35 s of the roll step
    # the roll is past 3 deg (1 - exp(-0.35*6) = 88 % of the command, minus the position loop's
    # pull-back); the yaw reaches 80 % of 15 deg within 1 s (1 - exp(-2.5) = 92 %)
    assert roll[int(1.35 * 1000)] > 3.0
    assert yaw[int(4.0 * 1000)] > 12.0
    # tracking error shrinks again after each step
    assert np.degrees(log.attitude_error_rad()[int(2.4 * 1000)]) < 2.0


def test_same_seed_same_flight_and_gyro_rate_below_physics():
    a, la = fly_hover(duration_s=1.0, seed=5, gyro_rate_hz=500.0)
    b, lb = fly_hover(duration_s=1.0, seed=5, gyro_rate_hz=500.0)
    np.testing.assert_array_equal(a.omega_S_rad_s, b.omega_S_rad_s)
    np.testing.assert_array_equal(la.motor_thrust_cmd_n, lb.motor_thrust_cmd_n)
    assert a.n == 500 and a.meta["physics_rate_hz"] == "1000"
    c, _ = fly_hover(duration_s=1.0, seed=6, gyro_rate_hz=500.0)
    assert not np.array_equal(a.f_S_m_s2, c.f_S_m_s2)  # other rotor phases


def test_custom_vibration_scales_the_imbalance_line():
    # the 1x line is the eccentric masses' centrifugal force u Omega^2: doubling u doubles it
    k0 = 1000
    amps = []
    for u in (1e-6, 2e-6):
        truth, _ = fly_hover(
            duration_s=3.0,
            seed=2,
            vibration=VibrationSpec(imbalance_kg_m=u, harmonic2_ratio=0.0, blade_pass_ripple=0.0),
        )
        x = truth.f_S_m_s2[k0:, :2]
        n = x.shape[0]
        w = np.hanning(n)[:, None]
        spec = np.abs(np.fft.rfft((x - x.mean(0)) * w, axis=0)).sum(axis=1)
        f = np.fft.rfftfreq(n, 1e-3)
        amps.append(spec[np.abs(f - F_ROTOR_HZ) < 1.0].max())
    # linear in u (the loop response to the ripple is linear too); 5 % for the leakage of the
    # slowly varying rotor speed
    assert amps[1] / amps[0] == pytest.approx(2.0, rel=0.05)


def test_truth_timing_rate_matches_attitude(hover_vib):
    # sample k is the state at t_k (sensordata after mj_step = start of the step). MuJoCo's
    # semi-implicit Euler advances the free joint's attitude by exp(dt * omega(k+1)) in the body
    # frame (S = B here), so the quaternion finite difference over [t_k, t_k+1] equals the
    # truth rate of sample k+1 to rounding (quaternion normalisation ~1e-16 / dt), and differs
    # from sample k by the vibration's rate change per step (~1e-3 rad/s).
    from scipy.spatial.transform import Rotation

    truth, _ = hover_vib
    r = Rotation.from_quat(truth.q_SW_wxyz[:, [1, 2, 3, 0]])
    w_fd = (r[:-1].inv() * r[1:]).as_rotvec() / 1e-3
    err_next = np.abs(w_fd - truth.omega_S_rad_s[1:]).max()
    err_same = np.abs(w_fd - truth.omega_S_rad_s[:-1]).max()
    assert err_next < 1e-9
    assert err_same > 1e4 * err_next


def test_motor_heating_streams_like_the_batch_model():
    spec = ThermalSpec(time_constant_s=5.0, ambient_c=((0.0, 20.0),), motor_c_per_w=0.05, self_heating_c=1.0)
    truth, log = fly_hover(duration_s=3.0, thermal=spec)
    # rotor (aerodynamic) power kappa c_T |Omega|^3 summed over the rotors, held per sample:
    p_w = QP.kappa_m * QP.c_t_n_per_rad2_s2 * np.sum(np.abs(log.rotor_speed_rad_s) ** 3, axis=1)
    # ~123 W in hover -> steady rise 6.2 °C + 1 °C self-heating; the closed-loop stream and the
    # batch recursion are the same exact discretisation: equal to rounding
    np.testing.assert_allclose(truth.temp_c, simulate_temperature(truth.t_s, spec, motor_power_w=p_w), atol=1e-9)
    assert 120.0 < p_w.mean() < 126.0
    expect_end = 20.0 + (1.0 + 0.05 * p_w.mean()) * (1 - math.exp(-truth.t_s[-1] / 5.0))
    assert truth.temp_c[-1] == pytest.approx(expect_end, abs=0.05)


def test_synthetic_gyro_in_the_loop_sees_the_truth_at_its_samples():
    # The closed loop feeds sample k's truth to the stream; the batch path on the recorded truth
    # must give the very same measurement (sim.gyro promises stream == batch bit for bit), so
    # any mislabelled sample (off by one step) or wrong frame would show here.
    from sim.gyro import SyntheticGyro

    truth, log = fly_hover(duration_s=1.5, gyro=SyntheticGyro("icm42688p", rate_hz=1000.0, seed=4))
    batch = SyntheticGyro("icm42688p", rate_hz=1000.0, seed=4).measure(truth)
    np.testing.assert_array_equal(batch.gyro_rad_s, log.gyro_meas_rad_s)
    assert not np.array_equal(log.gyro_meas_rad_s, log.omega_true_rad_s)


@pytest.mark.parametrize("gyro_rate_hz", [100.0, 4000.0])
def test_hover_at_low_and_high_gyro_rates(gyro_rate_hz):
    # 100 Hz: physics 1 kHz, 10 steps per sample (the 89 Hz rotor line aliases to 11 Hz in the
    # gyro; the loop still holds); 4 kHz: physics stepped at 4 kHz. Same bounds as at 1 kHz.
    truth, log = fly_hover(duration_s=3.0, gyro_rate_hz=gyro_rate_hz)
    k0 = int(SETTLE_S * gyro_rate_hz)
    assert truth.meta["physics_rate_hz"] == f"{max(1000.0, gyro_rate_hz):g}"
    assert truth.n == int(3.0 * gyro_rate_hz)
    assert np.degrees(log.attitude_error_rad()[k0:]).max() < 0.1
    assert np.abs(log.altitude_error_m()[k0:]).max() < 5e-3


def _unnamed_elements(model) -> list[str]:
    import mujoco

    out = []
    for objtype, count in (
        (mujoco.mjtObj.mjOBJ_BODY, model.nbody),
        (mujoco.mjtObj.mjOBJ_JOINT, model.njnt),
        (mujoco.mjtObj.mjOBJ_GEOM, model.ngeom),
        (mujoco.mjtObj.mjOBJ_SITE, model.nsite),
        (mujoco.mjtObj.mjOBJ_ACTUATOR, model.nu),
        (mujoco.mjtObj.mjOBJ_SENSOR, model.nsensor),
    ):
        start = 1 if objtype == mujoco.mjtObj.mjOBJ_BODY else 0  # body 0 is the world
        out += [f"{objtype.name}[{i}]" for i in range(start, count) if not mujoco.mj_id2name(model, objtype, i)]
    return out


def test_quadrotor_model_matches_its_sources():
    import mujoco

    from sim.paths import model_path
    from sim.quadrotor import load_quadrotor_model

    model, data = load_quadrotor_model()
    assert _unnamed_elements(model) == []
    assert all(model.sensor_noise == 0.0)  # every sensor error comes from sim.gyro
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    m_full = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, m_full)
    # Quan (2017) F450: 1.4 kg, J = diag(0.0211, 0.0219, 0.0366) kg m^2. The model adds the
    # 4 x 0.2 g imbalance masses (0.8 g) and their 1 cm offsets: within 0.1 % / 0.5 %.
    assert m_full[0, 0] == pytest.approx(1.4, rel=1e-3)
    np.testing.assert_allclose(np.diag(m_full[3:6, 3:6]), [0.0211, 0.0219, 0.0366], rtol=5e-3)
    # products of inertia only from the imbalance masses: <= 4 m_u (d/sqrt2 + r) z_rotor
    # = 4 * 2e-4 * 0.17 * 0.04 = 5.4e-6 kg m^2 (0.03 % of Jxx)
    assert np.abs(m_full[3:6, 3:6] - np.diag(np.diag(m_full[3:6, 3:6]))).max() < 5.5e-6
    # centre of mass at the frame origin (designed so): within the imbalance masses' 0.06 mm
    assert np.abs(data.subtree_com[1] - data.xpos[1]).max() < 1e-4
    # hover keyframe: four thrusts carry the weight
    assert data.ctrl[:4].sum() == pytest.approx(QP.mass_kg * QP.gravity_m_s2, rel=1e-3)
    # the scene includes the model
    assert "quadrotor.xml" in model_path("scene_quadrotor.xml").read_text()
    assert mujoco.MjModel.from_xml_path(str(model_path("scene_quadrotor.xml"))).nu == model.nu


# ---------------------------------------------------------------- compiled path (sim._fast)
def _all_effects_gyro(rate_hz: float, without: tuple = ()):
    """ICM-42688-P with every catalogue effect on (as bench/bench_sim.py's hover (b)), less ``without``."""
    from sim.gyro import SyntheticGyro
    from sim.presets import all_effects_overrides

    return SyntheticGyro("icm42688p", rate_hz=rate_hz, seed=1, overrides=all_effects_overrides(without))


def _bits(x) -> np.ndarray:
    """The IEEE bit patterns (so -0.0 != 0.0 and NaN payloads count)."""
    return np.ascontiguousarray(x, dtype=np.float64).view(np.uint64)


def _assert_same_flight(a, b) -> None:
    (ta, la), (tb, lb) = a, b
    for f in ("omega_S_rad_s", "f_S_m_s2", "q_SW_wxyz", "temp_c"):
        np.testing.assert_array_equal(_bits(getattr(ta, f)), _bits(getattr(tb, f)), err_msg=f)
    for f in (
        "q_WB_wxyz",
        "q_sp_wxyz",
        "pos_W_m",
        "vel_W_m_s",
        "rate_sp_rad_s",
        "gyro_meas_rad_s",
        "gyro_filt_rad_s",
        "motor_thrust_cmd_n",
        "rotor_speed_rad_s",
    ):
        np.testing.assert_array_equal(_bits(getattr(la, f)), _bits(getattr(lb, f)), err_msg=f)
    assert la.meta == lb.meta


CASES = [
    "all_effects_pt1_manoeuvres",
    "perfect_gyro_500hz",
    "preset_no_pipeline",
    "motor_heating",
    "heater",
    "ground_all_effects_pt1",
    "ground_preset_no_pipeline_500hz",
    "family_terms_of_time",
]


def _flight(case: str, **kw):
    """The flights the compiled/Python and block tests compare (``kw``: e.g. ``block_samples``)."""
    from sim.gyro import SyntheticGyro

    if case == "all_effects_pt1_manoeuvres":
        return fly_hover(
            duration_s=1.2,
            seed=2,
            gyro=_all_effects_gyro(1000.0),
            pipeline=pt1(30.0, 1000.0),
            manoeuvres=(Manoeuvre(0.2, 0.6, roll_rad=0.05, yaw_rad=0.1),),
            **kw,
        )
    if case == "ground_all_effects_pt1":  # disarmed on the floor (contact), arming, take-off ramp; motor heating
        spec = ThermalSpec(time_constant_s=0.5, ambient_c=((0.0, 20.0),), motor_c_per_w=0.05)
        return fly_hover(
            duration_s=1.6,
            ground_s=0.5,
            seed=2,
            gyro=_all_effects_gyro(1000.0, without=("bias_temp_rate",)),
            pipeline=pt1(30.0, 1000.0),
            thermal=spec,
            manoeuvres=(Manoeuvre(1.0, 0.4, roll_rad=0.05, yaw_rad=0.1),),
            **kw,
        )
    if case == "ground_preset_no_pipeline_500hz":  # kernel entry without a pipeline, m = 2
        return fly_hover(
            duration_s=1.5,
            ground_s=0.3,
            seed=4,
            gyro_rate_hz=500.0,
            gyro=SyntheticGyro("icm42688p", rate_hz=500.0, seed=4),
            **kw,
        )
    if case == "family_terms_of_time":  # registry terms of time alone: tabulated for the kernels
        g = SyntheticGyro("icm42688p", rate_hz=1000.0, seed=7, overrides=FAMILY_OF_TIME)
        return fly_hover(duration_s=1.0, seed=7, gyro=g, pipeline=pt1(30.0, 1000.0), **kw)
    if case == "perfect_gyro_500hz":
        return fly_hover(duration_s=1.0, seed=5, gyro_rate_hz=500.0, manoeuvres=small_steps(1.0), **kw)
    if case == "motor_heating":  # the die temperature streamed from the rotor power, thermal effects on
        spec = ThermalSpec(
            time_constant_s=0.5, ambient_c=((0.0, 20.0), (1.0, 22.0)), motor_c_per_w=0.05, self_heating_c=1.0
        )
        g = SyntheticGyro(
            "icm42688p",
            rate_hz=1000.0,
            seed=3,
            overrides={"bias_thermal": {"poly_rad_s": [[1e-4, 2e-6]] * 3}, "scale_thermal": {"poly_per_c": [1e-4] * 3}},
        )
        return fly_hover(duration_s=1.0, seed=6, gyro=g, thermal=spec, **kw)
    if case == "heater":  # PI heater to 23 °C, saturating at first (anti-windup), plus motor heating
        from sim.thermal import HeaterSpec

        spec = ThermalSpec(
            time_constant_s=0.5,
            ambient_c=((0.0, 20.0),),
            motor_c_per_w=0.01,
            heater=HeaterSpec(setpoint_c=23.0, max_power_w=2.0, heater_c_per_w=2.0, closed_loop_time_constant_s=0.2),
        )
        return fly_hover(
            duration_s=1.0, seed=6, gyro=_all_effects_gyro(1000.0, without=("bias_temp_rate",)), thermal=spec, **kw
        )
    if case == "temp_rate_ramp":  # bias_temp_rate on a warming die (no motor heating): dT/dt block by block
        spec = ThermalSpec(time_constant_s=0.3, ambient_c=((0.0, 20.0), (0.6, 30.0)), self_heating_c=1.0)
        return fly_hover(
            duration_s=1.0, seed=9, gyro=_all_effects_gyro(1000.0), thermal=spec, pipeline=pt1(30.0, 1000.0), **kw
        )
    assert case == "preset_no_pipeline"
    return fly_hover(duration_s=1.0, seed=4, gyro=SyntheticGyro("icm42688p", rate_hz=1000.0, seed=4), **kw)


@pytest.mark.parametrize("case", CASES)
def test_compiled_loop_is_the_python_loop_bit_for_bit(case, monkeypatch):
    # sim._fast transcribes rotor forces, GyroStream's generated code and the controller
    # operation by operation (libm cos/sin, IEEE sqrt, no FMA): the flights must agree in every
    # bit (incl. signed zeros), for the three kernel entries (with/without pipeline, m = 2
    # physics steps per sample) and every gyro effect (time offset, earth rate, temperature
    # rate, thermal polynomials, low-pass, saturation, quantization).
    import sim.quadrotor as Q

    calls = []
    compiled = Q._fly_compiled
    monkeypatch.setattr(Q, "_fly_compiled", lambda *a, **kw: calls.append(1) or compiled(*a, **kw))
    fast = _flight(case)
    assert calls == [1]  # the compiled path did fly
    slow = _flight(case, compiled=False)
    assert calls == [1]
    _assert_same_flight(fast, slow)


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("case", CASES + ["temp_rate_ramp"])
def test_flight_in_blocks_is_the_whole_flight_bit_for_bit(case, compiled):
    # HoverFlight carries every state across blocks (MuJoCo, controller incl. the
    # outer-loop row a block starts inside, motor commands, die temperature, the gyro's noise
    # generators, delay history, low-pass, dT/dt) and nothing indexes the whole flight: cut into
    # blocks of 997 samples (one cut) or 7 (cuts at every phase of the 4-sample outer loop, and
    # of the 2 physics steps per sample at 500 Hz) the flight is the same in every bit.
    whole = _flight(case, compiled=compiled)
    for b in (997, 7):
        _assert_same_flight(_flight(case, block_samples=b, compiled=compiled), whole)


def test_hover_flight_blocks_hold_one_block():
    # the blocks are pieces of the flight (sample times, sizes), a SyntheticGyro is opened as a
    # block stream (its arrays hold one block), and a flight runs once
    from gyrocore.errors import GyroInputError
    from sim.gyro import SyntheticGyro
    from sim.quadrotor import HoverFlight

    fl = HoverFlight(duration_s=0.5, gyro=SyntheticGyro("icm42688p", rate_hz=1000.0, seed=1), seed=1)
    sizes = []
    for tr, log in fl.blocks(120):
        assert tr.t_s[0] == sum(sizes) * 1e-3 and log.gyro_meas_rad_s.shape == (tr.n, 3)
        assert fl.gyro.blocked and fl.gyro.gyro_rad_s.shape == (tr.n, 3)
        sizes.append(tr.n)
    assert sizes == [120, 120, 120, 120, 20] and fl.gyro._k_next == 500
    with pytest.raises(GyroInputError, match="flies once"):
        next(fl.blocks(10))
    with pytest.raises(GyroInputError, match="block_samples"):
        next(HoverFlight(duration_s=0.1).blocks(0))


FAMILY_OF_TIME = {
    "periodic[37.5]": {"a_cos_rad_s": [0.01, 0.0, -0.004], "a_sin_rad_s": [0.0, 0.003, 0.0]},
    "step[0.4]": {"size_rad_s": [0.02, 0.0, 0.0]},
    "regressor[t]": {"coef": [0.0, 1e-3, 0.0]},
}


@pytest.mark.parametrize("extra", [{}, {"regressor[omega_x*f_z]": {"coef": [0.0, 1e-3, 0.0]}}])
def test_family_terms_in_the_loop_are_the_batch_measurement(extra, monkeypatch):
    # time-only family terms ride the compiled kernels (a table built before the flight); a term
    # of the rate or the specific force sends the flight to the Python loop (generic per-step
    # call). Either way the controller's gyro is SyntheticGyro.measure on the flight's truth.
    import sim.quadrotor as Q
    from sim.gyro import SyntheticGyro

    calls = []
    compiled = Q._fly_compiled
    monkeypatch.setattr(Q, "_fly_compiled", lambda *a, **kw: calls.append(1) or compiled(*a, **kw))
    ov = {**FAMILY_OF_TIME, **extra}
    stream = SyntheticGyro("icm42688p", rate_hz=1000.0, seed=8, overrides=ov).stream(800)
    truth, log = fly_hover(duration_s=0.8, gyro=stream, seed=8)
    assert calls == ([] if extra else [1])
    want = SyntheticGyro("icm42688p", rate_hz=1000.0, seed=8, overrides=ov).measure(truth).gyro_rad_s
    np.testing.assert_array_equal(want, log.gyro_meas_rad_s)
    np.testing.assert_array_equal(stream.gyro_rad_s, log.gyro_meas_rad_s)


def test_compiled_all_effects_gyro_is_the_batch_measurement():
    # The compiled gyro against SyntheticGyro.measure on the flight's own truth: every effect
    # on, the same measurement (value equality: the batch path's np.round may give -0.0 where
    # the stream's round() gives +0.0). The stream object is left as its own step() leaves it.
    g = _all_effects_gyro(1000.0)
    stream = g.stream(1000, t_s=np.arange(1000) / 1000.0, temp_c=np.full(1000, 25.0))
    truth, log = fly_hover(duration_s=1.0, gyro=stream, seed=1)
    np.testing.assert_array_equal(_all_effects_gyro(1000.0).measure(truth).gyro_rad_s, log.gyro_meas_rad_s)
    np.testing.assert_array_equal(stream.gyro_rad_s, log.gyro_meas_rad_s)
    assert stream._k_next == 1000


# ---------------------------------------------------------------- ground phase (power-up still, take-off)
GROUND_S = 3.0


@pytest.fixture(scope="module")
def from_ground():
    from sim.quadrotor import TAKEOFF_CLIMB_S

    dur = GROUND_S + TAKEOFF_CLIMB_S + SETTLE_S + 3.0
    return fly_hover(duration_s=dur, ground_s=GROUND_S, vibration=True, seed=3, manoeuvres=()), dur


def test_ground_phase_is_still_with_gravity_only(from_ground):
    (truth, log), _ = from_ground
    g = truth.t_s < GROUND_S
    assert g.sum() == int(GROUND_S * 1000)
    # Rotors stopped, motors off (controller disarmed): no thrust, no vibration source.
    assert np.all(log.motor_thrust_cmd_n[g] == 0.0)
    assert np.abs(log.rotor_speed_rad_s[g]).max() < 1e-6
    # Contact micro-motion on the four feet (soft contact settling from the keyframe, 0.1 mm
    # penetration): measured < 1.1e-6 rad/s. Bound 2e-6 rad/s: 1/14 of the ICM-42688-P's
    # bias resolution over the ground phase, N / sqrt(T) = 0.0028 deg/s/sqrt(Hz) * (pi/180)
    # / sqrt(3 s) = 2.8e-5 rad/s, so a static calibration sees a still sensor.
    assert np.linalg.norm(truth.omega_S_rad_s[g], axis=1).max() < 2e-6
    # Specific force = gravity only, +z in S (S = B, level on the ground): the settling
    # transient is measured < 6e-5 m/s^2; bound 1e-3 m/s^2 (= 0.1 mrad of tilt to the
    # accelerometer, far below any still-detector threshold).
    np.testing.assert_allclose(
        truth.f_S_m_s2[g], np.broadcast_to([0.0, 0.0, QP.gravity_m_s2], truth.f_S_m_s2[g].shape), rtol=0, atol=1e-3
    )
    assert np.degrees(log.tilt_rad()[g]).max() < 1e-3  # level on four equal feet
    # the gyro is powered up from t = 0, on the ground
    np.testing.assert_array_equal(truth.t_since_power_up_s, truth.t_s)
    assert truth.meta["ground_s"] == "3"


def test_takes_off_and_holds_hover_after_the_ground_phase(from_ground):
    from sim.quadrotor import TAKEOFF_CLIMB_S

    (truth, log), dur = from_ground
    z = log.pos_W_m[:, 2]
    assert z[0] < 0.2 and log.pos_sp_W_m[2] == 1.0  # starts on its 15-cm feet, climbs to 1 m
    # spools up right after arming: thrust commanded from the first outer update at >= GROUND_S
    assert log.motor_thrust_cmd_n[int(GROUND_S * 1000) + 4].sum() > 0.5 * QP.mass_kg * QP.gravity_m_s2
    # The same bounds as the airborne start (test_hover_holds_attitude_and_altitude_with_vibration,
    # derivations there), SETTLE_S after the climb ends: the ramp is a raised cosine with
    # velocity and acceleration fed forward, so it ends at the set point at rest.
    k0 = int((GROUND_S + TAKEOFF_CLIMB_S + SETTLE_S) * 1000)
    assert k0 < truth.n - 2000
    assert np.degrees(log.attitude_error_rad()[k0:]).max() < 0.1
    assert np.degrees(log.tilt_rad()[k0:]).max() < 0.1
    assert np.abs(log.altitude_error_m()[k0:]).max() < 5e-3
    assert np.abs(log.pos_W_m[k0:, :2] - log.pos_sp_W_m[:2]).max() < 1e-2
    # and it is flying: the rotor line is back in the truth (hover speed, 88.7 Hz)
    assert abs(np.abs(log.rotor_speed_rad_s[k0:]).mean() / (2 * math.pi) - F_ROTOR_HZ) < 0.5


def test_ground_s_is_checked():
    from gyrocore.errors import GyroInputError

    for bad in (-1.0, 2.0, 3.0, float("nan")):
        with pytest.raises(GyroInputError, match="ground_s"):
            fly_hover(duration_s=2.0, ground_s=bad)


def test_kernels_warm_up_in_a_child_process():
    # `simulate hover` of >= 1e6 samples first compiles/loads the numba cache in a child process
    # (compiling keeps ~50 MiB of LLVM memory in the process that does it); the child must work
    # from the test's sys.path
    from sim._fast import warm_cache_in_child

    assert warm_cache_in_child()
