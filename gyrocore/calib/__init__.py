"""Deterministic calibration: least squares, thermal polynomials, rotations, static bias, the error
budget, and the bounded-memory row sources the fits read."""
