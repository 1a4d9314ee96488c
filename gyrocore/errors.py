"""Errors and warnings that reach the user as one line.

Every user-facing failure in gyrocore raises :class:`GyroInputError` (or a subclass) with a
single-line message; the CLI prints ``error: <message>`` on stderr and exits with status 2.
Repairs made to input data are announced with :class:`RepairWarning` (one line each).
"""

from __future__ import annotations

import warnings

__all__ = ["GyroInputError", "UnobservableError", "RepairWarning", "warn_repair"]


class GyroInputError(ValueError):
    """Bad input (file, column, flag, parameter file). The message is one line."""


class UnobservableError(GyroInputError):
    """The data cannot observe a requested parameter; the message names it."""


class RepairWarning(UserWarning):
    """Input was repaired (rows dropped, units converted, ...); the message says what."""


def warn_repair(message: str, *, stacklevel: int = 2) -> None:
    """Emit a one-line :class:`RepairWarning`."""
    warnings.warn(message.replace("\n", " "), RepairWarning, stacklevel=stacklevel + 1)
