"""Rate table truth: commanded revolutions, rate/attitude consistency, mounts, timing."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gyrocore.errors import GyroInputError
from sim.turntable import (
    MOUNTS,
    TableSegment,
    mount_quat_wxyz,
    run_table,
    run_table_detailed,
    table_profile_static,
    table_profile_turns,
)

G_M_S2 = 9.81  # the model's gravity


def _rot(q_wxyz: np.ndarray) -> Rotation:
    return Rotation.from_quat(q_wxyz[..., [1, 2, 3, 0]])


@pytest.fixture(scope="module")
def turns_run():
    # two turns each way at pi rad/s on three mounts (two re-poses): ~40 s of table, ~0.2 s wall
    prof = table_profile_turns(mounts=("+z", "-x", "+y"), revolutions=2, rates_rad_s=(math.pi,), rest_s=1.0)
    return run_table_detailed(prof, gyro_rate_hz=1000.0)


def test_truth_integrates_to_commanded_revolutions(turns_run):
    tr, dt = turns_run.truth, 1e-3
    up_S = _rot(tr.q_SW_wxyz).inv().apply([0.0, 0.0, 1.0])
    w_up = np.einsum("ij,ij->i", tr.omega_S_rad_s, up_S)
    phases = turns_run.phases
    checked = 0
    for i, ph in enumerate(phases):
        if ph["kind"] != "segment" or ph["angle_rad"] == 0.0:
            continue
        # window: the turning segment and the rest after it (servo settled: exp(-omega_n t)
        # with omega_n = 62.8 rad/s over 1 s of rest is ~1e-27)
        k0 = int(round(ph["t_start_s"] / dt))
        k1 = int(round(phases[i + 1]["t_end_s"] / dt)) - 1
        # MuJoCo's semi-implicit Euler: attitude(k+1) = attitude(k) advanced by dt*omega(k+1);
        # the rectangle sum over omega(k0+1..k1) is the exact discrete rotation. The tolerance
        # 1e-6 rad is the requirement; rounding over ~5e3 steps is ~1e-12 rad.
        integ = np.sum(w_up[k0 + 1 : k1 + 1]) * dt
        assert abs(integ - ph["angle_rad"]) < 1e-6
        assert abs(abs(ph["angle_rad"]) - 2 * 2 * math.pi) < 1e-12
        # the table hinge itself turned the commanded angle
        assert abs(turns_run.table_angle_rad[k1] - turns_run.table_angle_rad[k0] - ph["angle_rad"]) < 1e-6
        checked += 1
    assert checked == 6


def test_truth_rate_consistent_with_attitude(turns_run):
    tr, dt = turns_run.truth, 1e-3
    r = _rot(tr.q_SW_wxyz)
    w_fd = (r[:-1].inv() * r[1:]).as_rotvec() / dt  # body-frame rate over [t_k, t_k+1]
    err = np.abs(w_fd - tr.omega_S_rad_s[1:]).max(axis=1)
    # One joint moving: the step rotation is exactly exp(dt*omega(k+1)) (semi-implicit Euler),
    # so FD equals omega(k+1) to rounding (quaternion normalisation ~1e-16/dt ~ 1e-13 rad/s).
    # Two joints moving (re-pose, table reacting): the composed step rotation differs from
    # exp(dt*(w1+w2)) by dt^2/2 |w1 x w2|, a rate error <= dt/2 |w|^2 (|w| <= pi rad/s here).
    bound = 0.5 * dt * np.linalg.norm(tr.omega_S_rad_s[1:], axis=1) ** 2 + 1e-9
    assert np.all(err <= bound)
    # and it is NOT the rate at t_k (the sample timing matters): during the ramps they differ
    err_k = np.abs(w_fd - tr.omega_S_rad_s[:-1]).max()
    assert err_k > 1e3 * err.max()
    seg = [p for p in turns_run.phases if p["kind"] == "segment"]
    k_in = np.concatenate([np.arange(int(p["t_start_s"] / dt) + 1, int(p["t_end_s"] / dt) - 1) for p in seg])
    # inside segments only the table moves (the stiff fixture clamp deflects < 1e-8 rad, see the
    # model): the composed-rotation term dt/2*|w_table|*|w_clamp| is < 1e-9 rad/s
    assert err[k_in - 1].max() < 1e-9


@pytest.mark.parametrize("mount", MOUNTS)
def test_static_mounts_point_axis_up(mount):
    tr = run_table(table_profile_static(mount, 0.2), gyro_rate_hz=500.0)
    axis = "xyz".index(mount[1])
    sign = 1.0 if mount[0] == "+" else -1.0
    expect = np.zeros(3)
    expect[axis] = sign * G_M_S2
    # at rest: specific force = +g on the up axis (exact in the rigid model, rounding only)
    np.testing.assert_allclose(tr.f_S_m_s2, np.broadcast_to(expect, tr.f_S_m_s2.shape), atol=1e-9)
    np.testing.assert_allclose(tr.omega_S_rad_s, 0.0, atol=1e-12)
    up_W = _rot(tr.q_SW_wxyz).apply(np.eye(3)[axis] * sign)
    np.testing.assert_allclose(up_W, np.broadcast_to([0, 0, 1.0], up_W.shape), atol=1e-12)
    assert tr.n == 100 and np.allclose(np.diff(tr.t_s), 1 / 500.0)


def test_tilt_quaternion_mount_and_constant_rate():
    q = Rotation.from_rotvec([0.3, -0.2, 0.1])
    q_wxyz = tuple(np.roll(q.as_quat(), 1))
    seg = TableSegment(mount=q_wxyz, rate_rad_s=2.0, duration_s=2.0, ramp_s=0.5)
    from sim.turntable import TableProfile

    tr = run_table(TableProfile(segments=(seg,)), gyro_rate_hz=1000.0)
    k = 1000  # mid-hold (t = 1 s, hold from 0.5 to 1.5 s) — servo settled to ~exp(-31)
    # table rate 2 rad/s about world z, seen in S: R_TS^T z * 2
    expect = q.inv().apply([0, 0, 2.0])
    np.testing.assert_allclose(tr.omega_S_rad_s[k], expect, atol=1e-9)
    np.testing.assert_allclose(tr.f_S_m_s2[k], q.inv().apply([0, 0, G_M_S2]), atol=1e-9)


def test_gyro_faster_than_physics_steps_physics_at_multiple():
    prof = table_profile_turns(mounts=("+z",), revolutions=0.25, rates_rad_s=(math.pi,), directions=(1,), rest_s=0.2)
    tr = run_table(prof, gyro_rate_hz=4000.0, physics_rate_hz=1000.0)
    assert tr.meta["physics_rate_hz"] == "4000"
    assert np.allclose(np.diff(tr.t_s), 1 / 4000.0)
    phases = json.loads(tr.meta["table_phases"])
    assert phases[1]["angle_rad"] == pytest.approx(math.pi / 2, abs=1e-15)
    w_up = tr.omega_S_rad_s[:, 2]
    assert abs(np.sum(w_up[1:]) / 4000.0 - math.pi / 2) < 1e-6


def test_bad_mount_is_one_line_error():
    with pytest.raises(GyroInputError):
        mount_quat_wxyz("+w")
    with pytest.raises(GyroInputError):
        TableSegment(mount="+z", rate_rad_s=1.0, duration_s=0.5, ramp_s=0.5)


def test_table_model_named_and_scene_includes_it():
    import mujoco

    from sim.paths import model_path
    from sim.turntable import load_table_model

    model, _ = load_table_model()
    unnamed = []
    for objtype, count in (
        (mujoco.mjtObj.mjOBJ_BODY, model.nbody),
        (mujoco.mjtObj.mjOBJ_JOINT, model.njnt),
        (mujoco.mjtObj.mjOBJ_GEOM, model.ngeom),
        (mujoco.mjtObj.mjOBJ_SITE, model.nsite),
        (mujoco.mjtObj.mjOBJ_ACTUATOR, model.nu),
        (mujoco.mjtObj.mjOBJ_SENSOR, model.nsensor),
    ):
        start = 1 if objtype == mujoco.mjtObj.mjOBJ_BODY else 0
        unnamed += [i for i in range(start, count) if not mujoco.mj_id2name(model, objtype, i)]
    assert unnamed == []
    assert all(model.sensor_noise == 0.0)
    for name in ("imu_gyro", "imu_accel"):
        assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name) >= 0
    assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "imu") >= 0
    assert "turntable.xml" in model_path("scene_turntable.xml").read_text()
    assert mujoco.MjModel.from_xml_path(str(model_path("scene_turntable.xml"))).nu == model.nu
