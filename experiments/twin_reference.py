"""The twin's reference: what a real recording says the true motion was (rate, attitude or still
spans), from its columns or its segments file (:func:`reference_of`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from gyrocore.attitude import attitude_rate
from gyrocore.data.recording import Recording
from gyrocore.data.segments import as_segments
from gyrocore.errors import GyroInputError
from gyrocore.data.still import still_samples
from gyrocore.loop.residual import STILL_GATE, choose_reference

DEG = math.pi / 180.0
#: Shortest span of the reference the statistics use, s.
MIN_SPAN_S = 5.0


@dataclass(frozen=True, eq=False)
class Reference:
    """What the twin replays and where its error signal is defined.

    Attributes
    ----------
    kind : str
        ``"rate"``, ``"attitude"`` or ``"still"`` (gyrocore.loop.residual kinds; ``"angles"`` maps
        to ``"still"``: only the still part is replayed).
    omega_S_rad_s : ndarray, shape (N, 3)
        Rate that drives the twin, rad/s, sensor frame (0 on still samples; filled by linear
        interpolation across uncovered samples, which the statistics never use).
    covered : ndarray of bool, shape (N,)
        Samples of the per-sample error signal e = gyro − ω_ref.
    spans : list of (int, int)
        Contiguous covered runs [a, b) of at least :data:`MIN_SPAN_S`.
    q_ref_wxyz : ndarray, shape (N, 4) or None
        Reference attitude (attitude kind only; NaN where lost).
    description : str
    coverage_note : str or None
        The one-line repair warning when the reference does not cover the whole recording.
    """

    kind: str
    omega_S_rad_s: np.ndarray
    covered: np.ndarray
    spans: list
    q_ref_wxyz: np.ndarray | None
    description: str
    coverage_note: str | None = None


def _runs(mask: np.ndarray, min_len: int) -> list[tuple[int, int]]:
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    a, b = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return [(int(x), int(y)) for x, y in zip(a, b) if y - x >= min_len]


def _quat_R(q: np.ndarray):
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q, float)[:, [1, 2, 3, 0]])


def _fill(t: np.ndarray, x: np.ndarray, ok: np.ndarray) -> np.ndarray:
    out = np.array(x, float)
    if ok.all():
        return out
    if not ok.any():
        return np.zeros_like(out)
    for i in range(out.shape[1]):
        out[~ok, i] = np.interp(t[~ok], t[ok], out[ok, i])
    return out


def reference_of(rec: Recording, segments: Sequence = ()) -> Reference:
    """The reference of ``rec`` for the twin (see the module docstring).

    Raises
    ------
    GyroInputError
        No reference at all (no ``ref_*`` columns, no still segments or poses, and the
        recording is not a still log), or a reference that covers less than
        :data:`MIN_SPAN_S` of contiguous samples.
    """
    segs = as_segments(segments)
    t = np.asarray(rec.t_s, float)
    n = rec.n
    fs = rec.rate_hz
    min_len = max(16, int(round(MIN_SPAN_S * fs)))
    try:
        kind = choose_reference(rec, segs)
    except GyroInputError:
        raise GyroInputError(
            "the twin needs a reference: ref_x/y/z_rad_s (a rate), ref_qw/qx/qy/qz (an attitude), still "
            "segments (--segments) or a still recording; this recording has none"
        ) from None
    q_ref = None
    if kind == "rate":
        ref = np.asarray(rec.ref_rate_rad_s, float)
        covered = np.all(np.isfinite(ref), axis=1)
        omega = _fill(t, ref, covered)
        desc = "reference rate (ref_*_rad_s)"
    elif kind == "attitude":
        q_ref = np.asarray(rec.ref_quat_wxyz, float)
        w, valid = attitude_rate(t, q_ref)
        omega = _fill(t, w, valid)
        still = still_samples(rec, STILL_GATE)
        covered = still.copy()
        # a rest must also be a rest of the reference: the attitude changes by < 1° over it
        for a, b in _runs(still, min_len):
            qa, qb = q_ref[a], q_ref[b - 1]
            if np.all(np.isfinite(qa)) and np.all(np.isfinite(qb)):
                ang = np.linalg.norm((_quat_R(qa[None]).inv() * _quat_R(qb[None])).as_rotvec())
                if ang > DEG:
                    covered[a:b] = False
        omega[covered] = 0.0
        desc = (
            "reference attitude (ref_q*): its rate drives the twin; per-sample error signal on the rests "
            "(zero rate), the loop's 1-s window residual on the whole recording"
        )
    else:  # still or angles
        if any(s.kind == "still" for s in segs):
            covered = np.zeros(n, bool)
            for s in segs:
                if s.kind == "still":
                    covered |= (t >= s.t_start_s) & (t <= s.t_end_s)
            how = "still segments"
        elif "static_pose_axis" in rec.extra:
            covered = np.asarray(rec.extra["static_pose_axis"]) != 0
            how = "static poses"
        else:
            covered = still_samples(rec, STILL_GATE)
            how = "motion gate"
        if kind == "angles":
            for s in segs:
                if s.kind == "rotation":
                    covered &= ~((t >= s.t_start_s) & (t <= s.t_end_s))
        omega = np.zeros((n, 3))
        desc = f"still ({how}): zero rate" + (
            "; the known rotations are not replayed (rate profile unknown)" if kind == "angles" else ""
        )
        kind = "still"
    # a margin at each end: the twin's time offset / filters reach across a span's edge into
    # samples whose reference rate is a motion (or, for an optical attitude, its noisy derivative)
    margin = max(8, int(round(0.25 * fs)))
    spans = [(a + margin, b - margin) for a, b in _runs(covered, min_len + 2 * margin)]
    used = np.zeros(n, bool)
    for a, b in spans:
        used[a:b] = True
    if not spans:
        raise GyroInputError(
            f"the reference covers no contiguous stretch of {MIN_SPAN_S:g} s; the twin needs at least one"
        )
    note = None
    if not covered.all() or (q_ref is not None and not np.all(np.isfinite(q_ref))):
        parts = [
            f"reference covers {covered.mean():.0%} of the recording ({len(spans)} span(s) of >= {MIN_SPAN_S:g} s)"
        ]
        if q_ref is not None:
            lost = int((~np.all(np.isfinite(q_ref), axis=1)).sum())
            if lost:
                parts.append(f"{lost} samples of reference attitude lost (windows touching them dropped)")
        note = "; ".join(parts) + ": replicas compared over the covered spans only"
    return Reference(
        kind=kind,
        omega_S_rad_s=omega,
        covered=used,
        spans=spans,
        q_ref_wxyz=q_ref,
        description=desc,
        coverage_note=note,
    )
