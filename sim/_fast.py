"""Compiled (numba) per-step work of the closed-loop hover (:func:`sim.quadrotor.fly_hover`).

One jitted call per physics step does everything but ``mj_step``: it logs the sensor state,
runs the synthetic gyro (a :class:`sim.gyro.GyroStream`'s effects, or the true rate for
:class:`sim.quadrotor.PerfectGyro`), the cascaded controller (:class:`sim.controller.CascadedController`),
the mixer and the motor commands, and sets the rotor forces for the next physics step.

Every formula is a transcription of the Python reference, operation by operation, in the same
order (no fused multiply-add: numba's default ``fastmath=False`` forbids contraction), so the
results are bit-identical to the Python path:

* rotor forces: ``fly_hover``'s ``rotor_aero`` (Python reference kept in :mod:`sim.quadrotor`);
* gyro: the straight-line code :meth:`sim.gyro.GyroStream._compile` generates (itself
  bit-identical to :mod:`gyrocore.effects.registry`); ``math.cos/sin/sqrt`` and ``np.rint`` compile to
  the same libm calls / IEEE operations Python uses (checked by ``tests/sim/test_hover.py``,
  which compares this path with the Python path and with ``SyntheticGyro.measure``);
* controller: :meth:`CascadedController.update_outer` / :meth:`update_rate`; Python's
  ``min``/``max`` are reproduced exactly (``_pmin``/``_pmax``: first argument unless the second is
  strictly smaller/larger), including signed zeros.

Memory: the kernels take two arrays, ``A`` (int64: addresses of the numpy/MuJoCo arrays they
read and write, and integer settings) and ``W`` (float64: constants and state), so that the
per-call dispatch cost stays small (numba unboxes every array argument). The address slots
and the ``W`` offsets are the module constants below; :func:`build` fills both.

Blocks (bounded memory): the per-sample arrays (logs, times, temperature, noise, gyro output, tables)
hold one block of the flight, rows ``A_K0 … A_K0 + A_NB − 1`` (the times and the ambient one row
more, for the step to ``k + 1``); the kernels index them with ``k − A_K0`` and keep every piece
of state in ``W``/``A``, so a flight cut into blocks is the same flight bit for bit.
:meth:`Kernel.set_block` points ``A`` at the next block's arrays.
"""

from __future__ import annotations

import math

import numpy as np
from numba import carray, njit, types
from numba.core import cgutils
from numba.extending import intrinsic

# ---------------------------------------------------------------------------- A (int64) slots
(
    A_QPOS,
    A_QVEL,
    A_SD,
    A_CTRL,
    A_SDLOG,
    A_REC,
    A_OUTLOG,
    A_GOUT,
    A_NOISE,
    A_TS,
    A_TEMP,
    A_TR,
    A_MAN,
    A_STH,
    A_BTH,
    A_HIST,
    # integers
    A_RQ0,
    A_RV0,
    A_NSD,
    A_SGYRO,
    A_SACC,
    A_SQ,
    A_SPOS,
    A_SVEL,
    A_OUTER_EVERY,
    A_N,
    A_NMAN,
    A_STREAM,
    A_EARTH,
    A_TAU,
    A_STH_P,
    A_ASYM,
    A_NL,
    A_BIAS,
    A_BTH_P,
    A_KTR,
    A_RAMP,
    A_H,
    A_G,
    A_LP,
    A_SAT,
    A_Q,
    A_HCAP,
    A_HLEN,
    A_PREV,
    A_NQPOS,
    A_NQVEL,
    A_NU,
    A_THERM,
    A_AMB,
    A_HEATER,
    A_ARMED,
    # registry family terms of time only, precomputed (rows, 3·A_NFAM) (sim.gyro.GyroStream.family_table)
    A_FAM,
    A_NFAM,
    # the current block: global index of its first sample, rows of its arrays
    A_K0,
    A_NB,
    A_SIZE,
) = range(57)


def _layout(*fields):
    off, out = 0, {}
    for name, size in fields:
        out[name] = off
        off += size
    return out, off


_W, W_SIZE = _layout(
    # rotors, motors
    ("RK", 20),
    ("SPIN", 4),
    ("FF", 1),
    ("CT", 1),
    # controller constants
    ("POS_SP", 3),
    ("YAW_SP", 1),
    ("DT", 1),
    ("DT_OUTER", 1),
    ("IL", 1),
    ("ALT_KP", 1),
    ("ALT_KI", 1),
    ("ALT_KD", 1),
    ("XY_KP", 1),
    ("XY_KD", 1),
    ("AMAX", 1),
    ("TMAX", 1),
    ("LIM", 1),
    ("ATT_K", 3),
    ("MASS", 1),
    ("GRAV", 1),
    ("TM", 1),
    ("JKP", 3),
    ("JKI", 3),
    ("JKD", 3),
    ("AINV", 16),
    # gyro constants
    ("K", 9),
    ("EARTH", 3),
    ("TAUV", 1),
    ("ASYMV", 3),
    ("NLV", 3),
    ("BV", 3),
    ("STH_LIM", 3),
    ("BTH_LIM", 3),
    ("KTRV", 3),
    ("RAMPV", 3),
    ("HV", 9),
    ("GV", 18),
    ("LPV", 5),
    ("ZI", 2),
    ("SATV", 1),
    ("LSB", 1),
    ("T_PU", 1),
    # controller state
    ("I_RATE", 3),
    ("I_ALT", 1),
    ("PREV_G", 3),
    ("Q_SP", 4),
    ("RATE_SP", 3),
    ("COLL", 1),
    ("THRUST", 4),
    ("MOT", 4),
    ("OM", 4),
    # gyro state
    ("LPZ", 6),
    ("W_FIRST", 3),
    ("GOUT3", 3),
    # streamed (motor-heated) die temperature: constants, then the ThermalState
    ("TH_TAU", 1),
    ("TH_SELF", 1),
    ("TH_MOTOR", 1),
    ("TH_KC", 1),
    ("TH_TEMP", 1),
    ("TH_T", 1),
    ("TH_AMB", 1),
    # heater PI (sim.thermal.ThermalState._update_heater): constants, then its state
    ("HT_KP", 1),
    ("HT_KI", 1),
    ("HT_SP", 1),
    ("HT_MAXW", 1),
    ("HT_CPW", 1),
    ("HT_INTEG", 1),
    ("HT_W", 1),
    # take-off from the ground (CascadedController arm_at_s, climb_s, z_start_m)
    ("T_ARM", 1),
    ("CLIMB", 1),
    ("Z0", 1),
)
(
    W_RK,
    W_SPIN,
    W_FF,
    W_CT,
    W_POS_SP,
    W_YAW_SP,
    W_DT,
    W_DT_OUTER,
    W_IL,
    W_ALT_KP,
    W_ALT_KI,
    W_ALT_KD,
    W_XY_KP,
    W_XY_KD,
    W_AMAX,
    W_TMAX,
    W_LIM,
    W_ATT_K,
    W_MASS,
    W_GRAV,
    W_TM,
    W_JKP,
    W_JKI,
    W_JKD,
    W_AINV,
    W_K,
    W_EARTH,
    W_TAUV,
    W_ASYMV,
    W_NLV,
    W_BV,
    W_STH_LIM,
    W_BTH_LIM,
    W_KTRV,
    W_RAMPV,
    W_HV,
    W_GV,
    W_LPV,
    W_ZI,
    W_SATV,
    W_LSB,
    W_T_PU,
    W_I_RATE,
    W_I_ALT,
    W_PREV_G,
    W_Q_SP,
    W_RATE_SP,
    W_COLL,
    W_THRUST,
    W_MOT,
    W_OM,
    W_LPZ,
    W_W_FIRST,
    W_GOUT3,
    W_TH_TAU,
    W_TH_SELF,
    W_TH_MOTOR,
    W_TH_KC,
    W_TH_TEMP,
    W_TH_T,
    W_TH_AMB,
    W_HT_KP,
    W_HT_KI,
    W_HT_SP,
    W_HT_MAXW,
    W_HT_CPW,
    W_HT_INTEG,
    W_HT_W,
    W_T_ARM,
    W_CLIMB,
    W_Z0,
) = (_W[_k] for _k in _W)
assert all(globals()["W_" + _k] == _v for _k, _v in _W.items())  # names follow the layout


@intrinsic
def _ptr(typingctx, addr):
    """int64 address -> void pointer (for numba.carray)."""
    sig = types.voidptr(addr)

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], cgutils.voidptr_t)

    return sig, codegen


@njit
def _f1(addr, n):
    return carray(_ptr(addr), (n,), np.float64)


@njit
def _f2(addr, n, m):
    return carray(_ptr(addr), (n, m), np.float64)


@njit
def _pmax(a, b):
    """Python's max(a, b) for floats: a unless b > a."""
    return b if b > a else a


@njit
def _pmin(a, b):
    """Python's min(a, b) for floats: a unless b < a."""
    return b if b < a else a


@njit
def _clamped_poly(coef, p, T, W, lim):
    """Σ_k coef[:, k-1]·dT^k (k = 1..p) with dT = clip(T, W[lim], W[lim+1]) − W[lim+2]: the
    thermal polynomial of gyrocore.effects.registry in the same operation order, per axis."""
    Tc = T
    if Tc < W[lim]:
        Tc = W[lim]
    if Tc > W[lim + 1]:
        Tc = W[lim + 1]
    dT = Tc - W[lim + 2]
    s0 = dT * coef[0, 0]
    s1 = dT * coef[1, 0]
    s2 = dT * coef[2, 0]
    pw = dT
    for kk in range(1, p):
        pw = pw * dT
        s0 = s0 + pw * coef[0, kk]
        s1 = s1 + pw * coef[1, kk]
        s2 = s2 + pw * coef[2, kk]
    return s0, s1, s2


@njit(cache=True)
def _aero(A, W):
    """ctrl[0:16] = rotor forces from the rotors' state now + the held motor commands; W[OM] = rotor speeds."""
    qpos = _f1(A[A_QPOS], A[A_NQPOS])
    qvel = _f1(A[A_QVEL], A[A_NQVEL])
    ctrl = _f1(A[A_CTRL], A[A_NU])
    rq0 = A[A_RQ0]
    rv0 = A[A_RV0]
    for i in range(4):
        p = qpos[rq0 + i]
        w = qvel[rv0 + i]
        W[W_OM + i] = w
        c = math.cos(p)
        s = math.sin(p)
        q = w * w
        r = W_RK + 5 * i
        # thrust c_T w^2 (1 + r cos(2 phi + psi_b)), as rotor_aero in sim.quadrotor
        ctrl[i] = W[r] * q * (1.0 + W[r + 1] * (c * c - s * s) - W[r + 2] * 2.0 * s * c)
        ctrl[4 + 2 * i] = q * (c * W[r + 3] - s * W[r + 4])
        ctrl[5 + 2 * i] = q * (s * W[r + 3] + c * W[r + 4])
    for i in range(4):
        ctrl[12 + i] = W[W_MOT + i]


@njit(cache=True)
def _log_and_gyro(k, A, W):
    """Log sensordata as sample k, run the gyro; the gyro output lands in W[GOUT3:GOUT3+3]."""
    nsd = A[A_NSD]
    sd = _f1(A[A_SD], nsd)
    nb = A[A_NB]
    kb = k - A[A_K0]  # row of sample k in the block's arrays
    sdlog = _f2(A[A_SDLOG], nb, nsd)
    for j in range(nsd):
        sdlog[kb, j] = sd[j]
    if A[A_THERM] != 0:
        _f1(A[A_TEMP], nb)[kb] = W[W_TH_TEMP]  # die temperature at t_k
    sg = A[A_SGYRO]
    w0 = sd[sg]
    w1 = sd[sg + 1]
    w2 = sd[sg + 2]
    if A[A_STREAM] == 0:
        W[W_GOUT3] = w0
        W[W_GOUT3 + 1] = w1
        W[W_GOUT3 + 2] = w2
        return
    # ---- the synthetic gyro: GyroStream._compile's code, block by block
    t = _f1(A[A_TS], nb + 1)[kb]
    if A[A_EARTH] != 0:
        sq = A[A_SQ]
        qw = sd[sq]
        qx = sd[sq + 1]
        qy = sd[sq + 2]
        qz = sd[sq + 3]
        nq = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw = qw / nq
        qx = qx / nq
        qy = qy / nq
        qz = qz / nq
        r00 = 1 - 2 * (qy * qy + qz * qz)
        r01 = 2 * (qx * qy - qw * qz)
        r02 = 2 * (qx * qz + qw * qy)
        r10 = 2 * (qx * qy + qw * qz)
        r11 = 1 - 2 * (qx * qx + qz * qz)
        r12 = 2 * (qy * qz - qw * qx)
        r20 = 2 * (qx * qz - qw * qy)
        r21 = 2 * (qy * qz + qw * qx)
        r22 = 1 - 2 * (qx * qx + qy * qy)
        e0 = W[W_EARTH]
        e1 = W[W_EARTH + 1]
        e2 = W[W_EARTH + 2]
        w0 = w0 + (r00 * e0 + r10 * e1 + r20 * e2)
        w1 = w1 + (r01 * e0 + r11 * e1 + r21 * e2)
        w2 = w2 + (r02 * e0 + r12 * e1 + r22 * e2)
    if A[A_TAU] != 0:
        # GyroStream._shifted: history window, then np.interp at t - tau
        cap = A[A_HCAP]
        hist = _f2(A[A_HIST], cap, 4)  # t, w0, w1, w2
        if k == 0:
            W[W_W_FIRST] = w0
            W[W_W_FIRST + 1] = w1
            W[W_W_FIRST + 2] = w2
        hl = A[A_HLEN]
        if hl == cap:
            for i in range(cap - 1):
                for c in range(4):
                    hist[i, c] = hist[i + 1, c]
            hl -= 1
        hist[hl, 0] = t
        hist[hl, 1] = w0
        hist[hl, 2] = w1
        hist[hl, 3] = w2
        hl += 1
        A[A_HLEN] = hl
        x = t - W[W_TAUV]
        j = hl - 1
        while j >= 0 and hist[j, 0] > x:
            j -= 1
        if j < 0:
            w0 = W[W_W_FIRST]
            w1 = W[W_W_FIRST + 1]
            w2 = W[W_W_FIRST + 2]
        elif j == hl - 1 or hist[j, 0] == x:
            w0 = hist[j, 1]
            w1 = hist[j, 2]
            w2 = hist[j, 3]
        else:
            dx = hist[j + 1, 0] - hist[j, 0]
            u = x - hist[j, 0]
            w0 = (hist[j + 1, 1] - hist[j, 1]) / dx * u + hist[j, 1]
            w1 = (hist[j + 1, 2] - hist[j, 2]) / dx * u + hist[j, 2]
            w2 = (hist[j + 1, 3] - hist[j, 3]) / dx * u + hist[j, 3]
    K = W_K
    y0 = w0 * W[K] + w1 * W[K + 1] + w2 * W[K + 2]
    y1 = w0 * W[K + 3] + w1 * W[K + 4] + w2 * W[K + 5]
    y2 = w0 * W[K + 6] + w1 * W[K + 7] + w2 * W[K + 8]
    T = 0.0
    if A[A_STH_P] > 0 or A[A_BTH_P] > 0:
        T = _f1(A[A_TEMP], nb)[kb]
    d0 = 0.0
    d1 = 0.0
    d2 = 0.0
    p = A[A_STH_P]
    if p > 0:
        s0, s1, s2 = _clamped_poly(_f2(A[A_STH], 3, p), p, T, W, W_STH_LIM)
        d0 = d0 + s0
        d1 = d1 + s1
        d2 = d2 + s2
    if A[A_ASYM] != 0:
        d0 = d0 + ((w0 > 0) - (w0 < 0)) * W[W_ASYMV]
        d1 = d1 + ((w1 > 0) - (w1 < 0)) * W[W_ASYMV + 1]
        d2 = d2 + ((w2 > 0) - (w2 < 0)) * W[W_ASYMV + 2]
    if A[A_NL] != 0:
        d0 = d0 + abs(w0) * W[W_NLV]
        d1 = d1 + abs(w1) * W[W_NLV + 1]
        d2 = d2 + abs(w2) * W[W_NLV + 2]
    y0 = y0 + d0 * w0
    y1 = y1 + d1 * w1
    y2 = y2 + d2 * w2
    a0 = 0.0
    a1 = 0.0
    a2 = 0.0
    if A[A_BIAS] != 0:
        a0 = a0 + W[W_BV]
        a1 = a1 + W[W_BV + 1]
        a2 = a2 + W[W_BV + 2]
    p = A[A_BTH_P]
    if p > 0:
        s0, s1, s2 = _clamped_poly(_f2(A[A_BTH], 3, p), p, T, W, W_BTH_LIM)
        a0 = a0 + s0
        a1 = a1 + s1
        a2 = a2 + s2
    if A[A_KTR] != 0:
        r = _f1(A[A_TR], nb)[kb]
        a0 = a0 + r * W[W_KTRV]
        a1 = a1 + r * W[W_KTRV + 1]
        a2 = a2 + r * W[W_KTRV + 2]
    if A[A_RAMP] != 0:
        ts = t - W[W_T_PU]
        a0 = a0 + ts * W[W_RAMPV]
        a1 = a1 + ts * W[W_RAMPV + 1]
        a2 = a2 + ts * W[W_RAMPV + 2]
    sa = A[A_SACC]
    f0 = sd[sa]
    f1 = sd[sa + 1]
    f2 = sd[sa + 2]
    if A[A_H] != 0:
        H = W_HV
        a0 = a0 + (f0 * W[H] + f1 * W[H + 1] + f2 * W[H + 2])
        a1 = a1 + (f0 * W[H + 3] + f1 * W[H + 4] + f2 * W[H + 5])
        a2 = a2 + (f0 * W[H + 6] + f1 * W[H + 7] + f2 * W[H + 8])
    if A[A_G] != 0:
        # FF_ORDER = xx, yy, zz, xy, xz, yz (gyrocore.effects.registry), checked in build()
        ff0 = f0 * f0
        ff1 = f1 * f1
        ff2 = f2 * f2
        ff3 = f0 * f1
        ff4 = f0 * f2
        ff5 = f1 * f2
        G = W_GV
        a0 = a0 + (ff0 * W[G] + ff1 * W[G + 1] + ff2 * W[G + 2] + ff3 * W[G + 3] + ff4 * W[G + 4] + ff5 * W[G + 5])
        a1 = a1 + (
            ff0 * W[G + 6] + ff1 * W[G + 7] + ff2 * W[G + 8] + ff3 * W[G + 9] + ff4 * W[G + 10] + ff5 * W[G + 11]
        )
        a2 = a2 + (
            ff0 * W[G + 12] + ff1 * W[G + 13] + ff2 * W[G + 14] + ff3 * W[G + 15] + ff4 * W[G + 16] + ff5 * W[G + 17]
        )
    m = A[A_NFAM]
    if m > 0:
        # registry family terms (gyrocore.effects.registry: periodic, step, regressor[t]), each added
        # in model order as GyroStream's generic per-step call adds it
        fam = _f2(A[A_FAM], nb, 3 * m)
        for j in range(m):
            a0 = a0 + fam[kb, 3 * j]
            a1 = a1 + fam[kb, 3 * j + 1]
            a2 = a2 + fam[kb, 3 * j + 2]
    x0 = y0 + a0
    x1 = y1 + a1
    x2 = y2 + a2
    if A[A_LP] != 0:
        Z = W_LPZ
        lb0 = W[W_LPV]
        lb1 = W[W_LPV + 1]
        lb2 = W[W_LPV + 2]
        la1 = W[W_LPV + 3]
        la2 = W[W_LPV + 4]
        if k == 0:
            W[Z] = W[W_ZI] * x0
            W[Z + 1] = W[W_ZI + 1] * x0
            W[Z + 2] = W[W_ZI] * x1
            W[Z + 3] = W[W_ZI + 1] * x1
            W[Z + 4] = W[W_ZI] * x2
            W[Z + 5] = W[W_ZI + 1] * x2
        yn = W[Z] + lb0 * x0
        W[Z] = W[Z + 1] + x0 * lb1 - yn * la1
        W[Z + 1] = x0 * lb2 - yn * la2
        x0 = yn
        yn = W[Z + 2] + lb0 * x1
        W[Z + 2] = W[Z + 3] + x1 * lb1 - yn * la1
        W[Z + 3] = x1 * lb2 - yn * la2
        x1 = yn
        yn = W[Z + 4] + lb0 * x2
        W[Z + 4] = W[Z + 5] + x2 * lb1 - yn * la1
        W[Z + 5] = x2 * lb2 - yn * la2
        x2 = yn
    nz = _f2(A[A_NOISE], nb, 3)
    x0 = x0 + nz[kb, 0]
    x1 = x1 + nz[kb, 1]
    x2 = x2 + nz[kb, 2]
    if A[A_SAT] != 0:
        S = W[W_SATV]
        NS = -S
        x0 = NS if x0 < NS else (S if x0 > S else x0)
        x1 = NS if x1 < NS else (S if x1 > S else x1)
        x2 = NS if x2 < NS else (S if x2 > S else x2)
    if A[A_Q] != 0:
        L = W[W_LSB]
        # Python's round() -> int: half to even as np.rint, and an int has no -0 (hence + 0.0)
        x0 = (np.rint(x0 / L) + 0.0) * L
        x1 = (np.rint(x1 / L) + 0.0) * L
        x2 = (np.rint(x2 / L) + 0.0) * L
    gout = _f2(A[A_GOUT], nb, 3)
    gout[kb, 0] = x0
    gout[kb, 1] = x1
    gout[kb, 2] = x2
    W[W_GOUT3] = x0
    W[W_GOUT3 + 1] = x1
    W[W_GOUT3 + 2] = x2


@njit(cache=True)
def _outer(k, A, W):
    """CascadedController.update_outer at t_k on the true state (sensordata), op by op."""
    sd = _f1(A[A_SD], A[A_NSD])
    t_s = _f1(A[A_TS], A[A_NB] + 1)[k - A[A_K0]]
    sp = A[A_SPOS]
    sv = A[A_SVEL]
    sq = A[A_SQ]
    t_arm = W[W_T_ARM]
    if t_s < t_arm:  # on the ground, disarmed: nothing runs (the log keeps the held set points)
        A[A_ARMED] = 0
        _log_outer(k, A, W)
        return
    A[A_ARMED] = 1
    dt = W[W_DT_OUTER]
    grav = W[W_GRAV]
    il = W[W_IL]
    z_sp = W[W_POS_SP + 2]
    climbing = t_s < t_arm + W[W_CLIMB]
    vz_sp = 0.0
    az_sp = 0.0
    if climbing:
        u = math.pi * (t_s - t_arm) / W[W_CLIMB]
        half = 0.5 * (z_sp - W[W_Z0])
        w = math.pi / W[W_CLIMB]
        vz_sp = half * w * math.sin(u)
        az_sp = half * w * w * math.cos(u)
        z_sp = W[W_Z0] + half * (1.0 - math.cos(u))
    ez = z_sp - sd[sp + 2]
    W[W_I_ALT] = _pmin(_pmax(W[W_I_ALT] + ez * dt, -il), il)
    if climbing:
        az = az_sp + W[W_ALT_KP] * ez + W[W_ALT_KI] * W[W_I_ALT] - W[W_ALT_KD] * (sd[sv + 2] - vz_sp)
    else:
        az = W[W_ALT_KP] * ez + W[W_ALT_KI] * W[W_I_ALT] - W[W_ALT_KD] * sd[sv + 2]
    ax = W[W_XY_KP] * (W[W_POS_SP] - sd[sp]) - W[W_XY_KD] * sd[sv]
    ay = W[W_XY_KP] * (W[W_POS_SP + 1] - sd[sp + 1]) - W[W_XY_KD] * sd[sv + 1]
    amax = W[W_AMAX]
    ax = _pmin(_pmax(ax, -amax), amax)
    ay = _pmin(_pmax(ay, -amax), amax)
    d_roll = 0.0
    d_pitch = 0.0
    d_yaw = 0.0
    nman = A[A_NMAN]
    if nman > 0:
        man = _f2(A[A_MAN], nman, 5)
        for i in range(nman):
            if man[i, 0] <= t_s < man[i, 0] + man[i, 1]:
                d_roll += man[i, 2]
                d_pitch += man[i, 3]
                d_yaw += man[i, 4]
    yaw = W[W_YAW_SP] + d_yaw
    cy = math.cos(yaw)
    sy = math.sin(yaw)
    tmax = W[W_TMAX]
    pitch = _pmin(_pmax((ax * cy + ay * sy) / grav + d_pitch, -tmax), tmax)
    roll = _pmin(_pmax(-(-ax * sy + ay * cy) / grav + d_roll, -tmax), tmax)
    # _quat_from_euler_zyx(yaw, pitch, roll)
    ccy = math.cos(0.5 * yaw)
    ssy = math.sin(0.5 * yaw)
    ccp = math.cos(0.5 * pitch)
    ssp = math.sin(0.5 * pitch)
    ccr = math.cos(0.5 * roll)
    ssr = math.sin(0.5 * roll)
    bw = ccr * ccp * ccy + ssr * ssp * ssy
    bx = ssr * ccp * ccy - ccr * ssp * ssy
    by = ccr * ssp * ccy + ssr * ccp * ssy
    bz = ccr * ccp * ssy - ssr * ssp * ccy
    W[W_Q_SP] = bw
    W[W_Q_SP + 1] = bx
    W[W_Q_SP + 2] = by
    W[W_Q_SP + 3] = bz
    qw = sd[sq]
    qx = sd[sq + 1]
    qy = sd[sq + 2]
    qz = sd[sq + 3]
    # _quat_mul((qw, -qx, -qy, -qz), q_sp)
    aw = qw
    ax_ = -qx
    ay_ = -qy
    az_ = -qz
    e0 = aw * bw - ax_ * bx - ay_ * by - az_ * bz
    e1 = aw * bx + ax_ * bw + ay_ * bz - az_ * by
    e2 = aw * by - ax_ * bz + ay_ * bw + az_ * bx
    e3 = aw * bz + ax_ * by - ay_ * bx + az_ * bw
    sgn = 2.0 if e0 >= 0.0 else -2.0
    lim = W[W_LIM]
    W[W_RATE_SP] = _pmin(_pmax(W[W_ATT_K] * sgn * e1, -lim), lim)
    W[W_RATE_SP + 1] = _pmin(_pmax(W[W_ATT_K + 1] * sgn * e2, -lim), lim)
    W[W_RATE_SP + 2] = _pmin(_pmax(W[W_ATT_K + 2] * sgn * e3, -lim), lim)
    r33 = 1.0 - 2.0 * (qx * qx + qy * qy)
    W[W_COLL] = W[W_MASS] * (grav + az) / _pmax(r33, 0.5)
    _log_outer(k, A, W)


@njit(cache=True)
def _log_outer(k, A, W):
    """Outer log row of sample k: q_sp (4), rate_sp (3); the block's log starts at the row of its first sample."""
    oe = A[A_OUTER_EVERY]
    k0 = A[A_K0]
    outlog = _f2(A[A_OUTLOG], (k0 + A[A_NB] - 1) // oe - k0 // oe + 1, 7)
    row = k // oe - k0 // oe
    for i in range(4):
        outlog[row, i] = W[W_Q_SP + i]
    for i in range(3):
        outlog[row, 4 + i] = W[W_RATE_SP + i]


@njit(cache=True)
def _rate_mix_motor(k, A, W, g0, g1, g2):
    """CascadedController.update_rate on the filtered gyro, mixer, log, motor commands, next forces."""
    if A[A_ARMED] == 0:  # disarmed (on the ground): thrusts 0, integrators and derivative memory untouched
        _mix_motor(k, A, W, g0, g1, g2, False, 0.0, 0.0, 0.0)
    else:
        _rate_pid_mix_motor(k, A, W, g0, g1, g2)


@njit(cache=True)
def _rate_pid_mix_motor(k, A, W, g0, g1, g2):
    """Armed: CascadedController.update_rate's PID, then the mixer."""
    dt = W[W_DT]
    il = W[W_IL]
    e0 = W[W_RATE_SP] - g0
    e1 = W[W_RATE_SP + 1] - g1
    e2 = W[W_RATE_SP + 2] - g2
    i0 = W[W_I_RATE] + e0 * dt
    i1 = W[W_I_RATE + 1] + e1 * dt
    i2 = W[W_I_RATE + 2] + e2 * dt
    i0 = il if i0 > il else (-il if i0 < -il else i0)
    i1 = il if i1 > il else (-il if i1 < -il else i1)
    i2 = il if i2 > il else (-il if i2 < -il else i2)
    W[W_I_RATE] = i0
    W[W_I_RATE + 1] = i1
    W[W_I_RATE + 2] = i2
    if A[A_PREV] == 0:
        p0 = g0
        p1 = g1
        p2 = g2
        A[A_PREV] = 1
    else:
        p0 = W[W_PREV_G]
        p1 = W[W_PREV_G + 1]
        p2 = W[W_PREV_G + 2]
    t0 = W[W_JKP] * e0 + W[W_JKI] * i0 - W[W_JKD] * (g0 - p0)
    t1 = W[W_JKP + 1] * e1 + W[W_JKI + 1] * i1 - W[W_JKD + 1] * (g1 - p1)
    t2 = W[W_JKP + 2] * e2 + W[W_JKI + 2] * i2 - W[W_JKD + 2] * (g2 - p2)
    W[W_PREV_G] = g0
    W[W_PREV_G + 1] = g1
    W[W_PREV_G + 2] = g2
    _mix_motor(k, A, W, g0, g1, g2, True, t0, t1, t2)


@njit(cache=True)
def _mix_motor(k, A, W, g0, g1, g2, armed, t0, t1, t2):
    """Log, mixer (thrusts 0 when not armed), motor commands, streamed die temperature."""
    c = W[W_COLL]
    tm = W[W_TM]
    nb = A[A_NB]
    kb = k - A[A_K0]
    rec = _f2(A[A_REC], nb, 14)
    rec[kb, 0] = W[W_GOUT3]
    rec[kb, 1] = W[W_GOUT3 + 1]
    rec[kb, 2] = W[W_GOUT3 + 2]
    rec[kb, 3] = g0
    rec[kb, 4] = g1
    rec[kb, 5] = g2
    ct = W[W_CT]
    ff = W[W_FF]
    for i in range(4):
        a = W_AINV + 4 * i
        if armed:
            ti = W[a] * c + W[a + 1] * t0 + W[a + 2] * t1 + W[a + 3] * t2
            ti = tm if ti > tm else (0.0 if ti < 0.0 else ti)
        else:
            ti = 0.0
        W[W_THRUST + i] = ti
        rec[kb, 6 + i] = ti
        rec[kb, 10 + i] = W[W_OM + i]  # rotor speeds at the start of this physics step
        W[W_MOT + i] = W[W_SPIN + i] * (math.sqrt(ti / ct) + ff * ti)
    if A[A_THERM] != 0 and k + 1 < A[A_N]:
        # rotor power kappa c_T sum |Omega|^3 over this step -> sim.thermal.ThermalState.step
        s = 0.0
        for i in range(4):
            s = s + math.pow(abs(W[W_OM + i]), 3.0)  # Python's float ** 3 is C pow(x, 3.0)
        p_w = W[W_TH_KC] * s
        t_next = _f1(A[A_TS], nb + 1)[kb + 1]
        amb_next = _f1(A[A_AMB], nb + 1)[kb + 1]
        tau = W[W_TH_TAU]
        h = t_next - W[W_TH_T]
        a = math.exp(-h / tau)
        c1 = 1.0 - tau * (1.0 - a) / h
        z = W[W_TH_MOTOR] * p_w
        if A[A_HEATER] != 0:
            z += W[W_HT_CPW] * W[W_HT_W]
        u0 = W[W_TH_AMB] + W[W_TH_SELF]
        u1 = amb_next + W[W_TH_SELF]
        W[W_TH_TEMP] = a * W[W_TH_TEMP] + (1.0 - a) * (u0 + z) + (u1 - u0) * c1
        W[W_TH_T] = t_next
        W[W_TH_AMB] = amb_next
        if A[A_HEATER] != 0:
            maxw = W[W_HT_MAXW]
            err = W[W_HT_SP] - W[W_TH_TEMP]
            integ = W[W_HT_INTEG] + W[W_HT_KI] * err * h
            p = W[W_HT_KP] * err + integ
            if 0.0 <= p <= maxw:  # conditional integration (anti-windup)
                W[W_HT_INTEG] = integ
            W[W_HT_W] = _pmin(_pmax(p, 0.0), maxw)


@njit(cache=True)
def control(k, A, W, y0, y1, y2):
    """With a pipeline, part 2: outer loops when due, rate loop on the filtered gyro y, next forces."""
    if k % A[A_OUTER_EVERY] == 0:
        _outer(k, A, W)
    _rate_mix_motor(k, A, W, y0, y1, y2)
    _aero(A, W)


@njit(cache=True)
def after_step(k, A, W):
    """After the (first) mj_step of gyro sample k, without a pipeline: log, gyro, control, next forces."""
    _log_and_gyro(k, A, W)
    control(k, A, W, W[W_GOUT3], W[W_GOUT3 + 1], W[W_GOUT3 + 2])


#: With a pipeline, part 1: log sample k and run the gyro (output in the gyro log row k).
log_and_gyro = _log_and_gyro


aero = _aero


class Kernel:
    """The compiled per-step work of one flight: the ``A``/``W`` arrays and what they point into.

    Build with :func:`build`, then :meth:`set_block` before each block of samples; keeps every
    array it hands out by address alive (the flight's for its life, a block's until the next).
    """

    def __init__(self, A: np.ndarray, W: np.ndarray, keep: list) -> None:
        self.A, self.W, self._keep = A, W, keep
        self._block: list = []

    def set_block(
        self,
        k0: int,
        *,
        t_s: np.ndarray,
        temp_c: np.ndarray,
        sd_log: np.ndarray,
        outer_log: np.ndarray,
        rec: np.ndarray,
        ambient_c: np.ndarray | None = None,
        gyro_out: np.ndarray | None = None,
        noise: np.ndarray | None = None,
        temp_rate: np.ndarray | None = None,
        family: np.ndarray | None = None,
    ) -> None:
        """Point the kernels at the arrays of samples ``k0 … k0 + m − 1``.

        Parameters
        ----------
        k0 : int
            Global index of the block's first sample.
        t_s : ndarray (m + 1,)
            Sample times of the block and of the sample after it, s.
        temp_c : ndarray (m,)
            Die temperature, °C (written by the kernels when the temperature is streamed).
        sd_log : ndarray (m, nsensordata); rec : ndarray (m, 14)
            Logs, written in place.
        outer_log : ndarray ((k0 + m − 1) // outer_every − k0 // outer_every + 1, 7)
            Outer-loop log from the row of sample k0 (a row begun in the previous block is
            rewritten only at its next update: fill it from there).
        ambient_c : ndarray (m + 1,), optional
            Ambient at the block's times and the next, °C (streamed temperature).
        gyro_out, noise : ndarray (m, 3), optional
            The synthetic gyro's output rows and summed noise rows (with a stream).
        temp_rate : ndarray (m,), optional
            dT/dt, °C/s (``bias_temp_rate``).
        family : ndarray (m, 3·nfam), optional
            The time-only family terms' table.
        """
        A = self.A
        m = int(temp_c.shape[0])
        oe = int(A[A_OUTER_EVERY])
        checks = [
            (t_s, (m + 1,)),
            (temp_c, (m,)),
            (sd_log, (m, int(A[A_NSD]))),
            (rec, (m, 14)),
            (outer_log, ((k0 + m - 1) // oe - k0 // oe + 1, 7)),
        ]
        if A[A_THERM] != 0:
            checks.append((ambient_c, (m + 1,)))
        if A[A_STREAM] != 0:
            checks += [(gyro_out, (m, 3)), (noise, (m, 3))]
        if A[A_KTR] != 0:
            checks.append((temp_rate, (m,)))
        if A[A_NFAM] > 0:
            checks.append((family, (m, 3 * int(A[A_NFAM]))))
        for arr, shape in checks:
            if arr is None or arr.shape != shape:
                raise ValueError(f"kernel block array of shape {None if arr is None else arr.shape}, expected {shape}")
        A[A_K0], A[A_NB] = int(k0), m
        A[A_TS], A[A_TEMP], A[A_SDLOG], A[A_REC], A[A_OUTLOG] = (
            _addr(x) for x in (t_s, temp_c, sd_log, rec, outer_log)
        )
        block = [t_s, temp_c, sd_log, rec, outer_log]
        for arr, slot in ((ambient_c, A_AMB), (gyro_out, A_GOUT), (noise, A_NOISE), (temp_rate, A_TR), (family, A_FAM)):
            if arr is not None and arr.size:
                A[slot] = _addr(arr)
                block.append(arr)
        self._block = block


def _addr(a: np.ndarray) -> int:
    if not (a.dtype == np.float64 and a.flags.c_contiguous):
        raise ValueError("kernel arrays must be C-contiguous float64")
    return int(a.ctypes.data)


def build(
    *,
    data,
    rq0: int,
    rv0: int,
    sens: dict,
    rotor_k,
    spin,
    ff: float,
    ct: float,
    ctl,
    n: int,
    t_power_up_s: float,
    stream=None,
    thermal=None,
    kappa_ct: float = 0.0,
) -> Kernel:
    """Fill the kernel arrays for one flight (the per-sample arrays: :meth:`Kernel.set_block`).

    Parameters
    ----------
    data : mujoco.MjData
        Its qpos, qvel, sensordata and ctrl are read/written in place.
    rq0, rv0 : int
        qpos / qvel address of rotor 1's spin joint (rotors 1..4 follow).
    sens : dict
        sensordata addresses: gyro, acc, quat, pos, vel.
    rotor_k : sequence of 4 x 5 floats
        Per rotor: c_T, ripple cos(psi_b), ripple sin(psi_b), h2 u cos(psi_h), h2 u sin(psi_h).
    spin : 4 ints; ff : float; ct : float
        Rotor spin signs, drag-torque feed-forward kappa/kv (s), thrust coefficient.
    ctl : sim.controller.CascadedController
        Freshly reset controller (constants and initial state are copied).
    n : int
        Gyro samples of the whole flight.
    t_power_up_s : float
        The gyro's power-up time (the first sample's), s, unless the stream has its own.
    stream : sim.gyro.GyroStream, optional
        The synthetic gyro (None: the true rate, PerfectGyro).
    thermal : sim.thermal.ThermalState, optional
        Streamed die temperature (motor heating, heater): its state at t_0; the block's
        ``temp_c`` is then written, sample by sample, from the block's ``ambient_c``;
        ``kappa_ct`` = kappa c_T, rotor power per |Omega|^3, W s^3.
    """
    from gyrocore.effects.registry import FF_ORDER

    n = int(n)
    A = np.zeros(A_SIZE, dtype=np.int64)
    W = np.zeros(W_SIZE)
    keep: list = []
    A[A_QPOS], A[A_QVEL], A[A_SD], A[A_CTRL] = (_addr(x) for x in (data.qpos, data.qvel, data.sensordata, data.ctrl))
    A[A_NQPOS], A[A_NQVEL], A[A_NSD], A[A_NU] = data.qpos.size, data.qvel.size, data.sensordata.size, data.ctrl.size
    A[A_RQ0], A[A_RV0], A[A_N] = rq0, rv0, n
    A[A_SGYRO], A[A_SACC], A[A_SQ], A[A_SPOS], A[A_SVEL] = (sens[x] for x in ("gyro", "acc", "quat", "pos", "vel"))
    A[A_OUTER_EVERY] = ctl.outer_every
    W[W_RK : W_RK + 20] = np.asarray(rotor_k, float).ravel()
    W[W_SPIN : W_SPIN + 4] = spin
    W[W_FF], W[W_CT] = ff, ct
    W[W_MOT : W_MOT + 4] = data.ctrl[12:16]
    # --- controller
    g, p = ctl.g, ctl.p
    W[W_POS_SP : W_POS_SP + 3] = ctl.pos_sp
    W[W_YAW_SP], W[W_DT], W[W_DT_OUTER], W[W_IL] = ctl.yaw_sp, ctl.dt, ctl.dt_outer, g.integrator_limit
    W[W_ALT_KP], W[W_ALT_KI], W[W_ALT_KD] = g.alt_kp_per_s2, g.alt_ki_per_s3, g.alt_kd_per_s
    W[W_XY_KP], W[W_XY_KD], W[W_AMAX], W[W_TMAX] = g.xy_kp_per_s2, g.xy_kd_per_s, g.max_horiz_accel_m_s2, g.max_tilt_rad
    W[W_LIM] = g.rate_limit_rad_s
    W[W_ATT_K : W_ATT_K + 3] = g.att_kp_per_s
    W[W_MASS], W[W_GRAV], W[W_TM] = p.mass_kg, p.gravity_m_s2, p.max_thrust_n
    W[W_JKP : W_JKP + 3], W[W_JKI : W_JKI + 3], W[W_JKD : W_JKD + 3] = ctl._jkp, ctl._jki, ctl._jkd
    W[W_AINV : W_AINV + 16] = np.asarray(ctl.alloc_inv, float).ravel()
    W[W_I_RATE : W_I_RATE + 3], W[W_I_ALT] = ctl.i_rate, ctl.i_alt
    if ctl.prev_gyro is not None:
        W[W_PREV_G : W_PREV_G + 3] = ctl.prev_gyro
        A[A_PREV] = 1
    W[W_Q_SP : W_Q_SP + 4], W[W_RATE_SP : W_RATE_SP + 3] = ctl.q_sp, ctl.rate_sp
    W[W_COLL], W[W_THRUST : W_THRUST + 4] = ctl.collective_n, ctl.thrust_cmd
    W[W_T_ARM], W[W_CLIMB], W[W_Z0] = ctl.arm_at_s, ctl.climb_s, ctl.z_start_m
    A[A_ARMED] = 1 if ctl.armed else 0
    if thermal is not None:
        A[A_THERM] = 1
        W[W_TH_TAU], W[W_TH_SELF], W[W_TH_MOTOR] = (
            thermal.spec.time_constant_s,
            thermal.spec.self_heating_c,
            thermal.spec.motor_c_per_w,
        )
        W[W_TH_KC], W[W_TH_TEMP], W[W_TH_T], W[W_TH_AMB] = kappa_ct, thermal.temp_c, thermal.t_s, thermal._amb_c
        ht = thermal.spec.heater
        if ht is not None:
            A[A_HEATER] = 1
            W[W_HT_KP], W[W_HT_KI] = ht.gains(thermal.spec.time_constant_s)
            W[W_HT_SP], W[W_HT_MAXW], W[W_HT_CPW] = ht.setpoint_c, ht.max_power_w, ht.heater_c_per_w
            W[W_HT_INTEG], W[W_HT_W] = thermal.integ_w, thermal.heater_w
    man = np.array(
        [(m.t_start_s, m.duration_s, m.roll_rad, m.pitch_rad, m.yaw_rad) for m in ctl.manoeuvres], float
    ).reshape(-1, 5)
    keep.append(man)
    A[A_NMAN] = man.shape[0]
    A[A_MAN] = _addr(man) if man.shape[0] else 0
    # --- gyro
    if stream is not None:
        S = stream
        if tuple(FF_ORDER) != ("xx", "yy", "zz", "xy", "xz", "yz"):
            raise ValueError("gyrocore.effects.registry.FF_ORDER changed: update sim._fast")
        A[A_STREAM] = 1
        keep.append(S)
        W[W_T_PU] = S._t_pu if S._t_pu is not None else float(t_power_up_s)
        if S._earth is not None:
            A[A_EARTH] = 1
            W[W_EARTH : W_EARTH + 3] = S._earth
        if S._tau != 0.0:
            A[A_TAU] = 1
            W[W_TAUV] = S._tau
            hist = np.zeros((S._hist_len, 4))
            keep.append(hist)
            A[A_HIST], A[A_HCAP], A[A_HLEN] = _addr(hist), S._hist_len, 0
        W[W_K : W_K + 9] = np.asarray(S._K, float).ravel()
        for th, flag, coef_slot, lim in ((S._sth, A_STH_P, A_STH, W_STH_LIM), (S._bth, A_BTH_P, A_BTH, W_BTH_LIM)):
            if th is not None:
                coef, lo, hi, t0 = th
                c = np.ascontiguousarray(np.asarray(coef, float).reshape(3, -1))
                keep.append(c)
                A[flag], A[coef_slot] = c.shape[1], _addr(c)
                W[lim : lim + 3] = (lo, hi, t0)
        for val, flag, slot, size in (
            (S._asym, A_ASYM, W_ASYMV, 3),
            (S._nl, A_NL, W_NLV, 3),
            (S._b, A_BIAS, W_BV, 3),
            (S._ktr, A_KTR, W_KTRV, 3),
            (S._ramp, A_RAMP, W_RAMPV, 3),
            (S._H, A_H, W_HV, 9),
            (S._G, A_G, W_GV, 18),
        ):
            if val is not None:
                A[flag] = 1
                W[slot : slot + size] = np.asarray(val, float).ravel()
        if S._lp is not None:
            A[A_LP] = 1
            W[W_LPV : W_LPV + 5] = S._lp
            W[W_ZI : W_ZI + 2] = [float(v) for v in S._lp_zi]
        if S._fam:
            A[A_NFAM] = len(S._fam)
        if S._sat is not None:
            A[A_SAT], W[W_SATV] = 1, S._sat
        if S._q is not None:
            A[A_Q], W[W_LSB] = 1, S._q
    return Kernel(A, W, keep)


def warm_cache_in_child(timeout_s: float = 600.0) -> bool:
    """Compile (or just load) the kernels' numba cache in a child process.

    The process that compiles the kernels keeps ~50 MiB of LLVM memory resident afterwards
    (measured: one second of hover peaks at 291 MiB with a cold cache, 237 MiB warm); a long
    `simulate hover` calls this first, so that it only loads the cache. Two tiny flights reach
    every entry point (``after_step``; ``log_and_gyro``/``control``/``aero`` with a pipeline and
    two physics steps per sample). Returns whether the child succeeded; on failure (e.g. an
    unwritable cache) the caller simply compiles in-process, as before.
    """
    import os
    import subprocess
    import sys

    code = (
        "from sim.quadrotor import fly_hover\n"
        "fly_hover(duration_s=0.01)\n"
        "fly_hover(duration_s=0.02, gyro_rate_hz=500.0, pipeline=lambda g: g)\n"
    )
    try:
        # the child resolves `sim` as this process does (its sys.path as PYTHONPATH)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
        r = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, timeout=timeout_s, env=env, cwd=os.getcwd()
        )
    except (OSError, subprocess.SubprocessError):
        return False
    return r.returncode == 0
