"""The loop's window design weighted per axis, and columns projected off the model.

The open search's score (Lagrange multiplier) tests — the regressor screen and the product
collinearity check of :mod:`gyrocore.loop.search`, the bias-step test of
:mod:`gyrocore.loop.bias_step` — work on the window regressors (M, 3, P) of
:mod:`gyrocore.loop.residual` with axis weights √w_i = 1/σ_i, flattened axis-major into
(3M, P) (:func:`weighted_design`, :func:`weighted_residual`), and project the tested columns
off the current model (Frisch–Waugh–Lovell, :func:`project_off`). Their variance under the
residual's autocovariance model is :func:`gyrocore.calib.covariance.autocov_apply`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["weighted_design", "weighted_residual", "project_off"]

#: Columns per block when :func:`project_off` works in place (memory only: a (R, 64) temporary).
_BLOCK_COLUMNS = 64


def weighted_design(X: np.ndarray, sw: np.ndarray) -> np.ndarray:
    """Window design (M, 3, P) × per-axis √w (3,) -> (3M, P), rows axis-major (axis i's M rows
    × √w_i)."""
    return np.concatenate([X[:, i, :] * sw[i] for i in range(3)], axis=0)


def weighted_residual(e: np.ndarray, sw: np.ndarray) -> np.ndarray:
    """Window residual (M, 3), rad/s, × per-axis √w (3,) -> (3M,), axis-major like
    :func:`weighted_design`."""
    return np.concatenate([e[:, i] * sw[i] for i in range(3)])


def project_off(Xw: np.ndarray, C: np.ndarray, *, overwrite: bool = False) -> np.ndarray:
    """C minus its least-squares projection on the columns of Xw (both (R, ·)); ``overwrite``:
    in place in C (a temporary of the caller's: one (R, ·) array fewer, the same numbers)."""
    if Xw.shape[1] == 0:
        return C
    Q, Rr = np.linalg.qr(Xw, mode="reduced")
    keep = np.abs(np.diag(Rr)) > 1e-10 * max(np.abs(np.diag(Rr)).max(), 1e-300)
    Q = Q[:, keep]
    if overwrite:  # in blocks of columns: a (R, 64) temporary instead of (R, ·)
        for c in range(0, C.shape[1], _BLOCK_COLUMNS):
            blk = C[:, c : c + _BLOCK_COLUMNS]
            blk -= Q @ (Q.T @ blk)
        return C
    return C - Q @ (Q.T @ C)
