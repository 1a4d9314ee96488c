"""gyrocore: the calibration core of gyroharness (MEMS gyro recordings in, calibration out).

The names users and the experiments need are here; everything else is reached through its
subpackage (docs/ARCHITECTURE.md "Package layout"): ``gyrocore.data`` (the Recording and its
file format), ``gyrocore.readers`` (every input format), ``gyrocore.effects`` (the measurement
model), ``gyrocore.calib`` (least squares, thermal, rotations, bias, budget, parameter file),
``gyrocore.noise`` (Allan deviation, GMWM), ``gyrocore.loop`` (residual, open search, loop),
``gyrocore.flight`` (vibration, firmware filters), ``gyrocore.cli`` (the command line).

``import gyrocore`` is cheap: the names below are loaded on first use (PEP 562), so importing
the package pulls in neither SciPy nor matplotlib nor Dask.
"""

from __future__ import annotations

import importlib
from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("gyroharness")
except PackageNotFoundError:  # pragma: no cover - running from a tree that was never installed
    __version__ = "0+unknown"

#: public name -> module that defines it (attribute of the same name unless given as (module, attr))
_EXPORTS: dict[str, str | tuple[str, str]] = {
    # the recording and its files
    "Recording": "gyrocore.data.recording",
    "read_recording": "gyrocore.data.recording",
    "write_recording": "gyrocore.data.recording",
    "read_csv": "gyrocore.data.recording",
    "write_csv": "gyrocore.data.recording",
    "read_parquet": "gyrocore.data.recording",
    "write_parquet": "gyrocore.data.recording",
    "load_any": "gyrocore.readers.convert",
    # still spans and known rotations, and their file
    "Segment": "gyrocore.data.segments",
    "read_segments": "gyrocore.data.segments",
    "write_segments": "gyrocore.data.segments",
    # the measurement model
    "REGISTRY": "gyrocore.effects.registry",
    "Effect": "gyrocore.effects.registry",
    "resolve": "gyrocore.effects.registry",
    # calibration
    "Calibrator": "gyrocore.calibrator",
    "CalibrationResult": "gyrocore.calib.params",
    "save_params": "gyrocore.calib.params",
    "load_params": "gyrocore.calib.params",
    # noise, loop, attitude, vibration
    "identify_noise": "gyrocore.noise.allan",
    "run_loop": "gyrocore.loop.loop",
    "validate_model": "gyrocore.loop.validate",
    "integrate_gyro": "gyrocore.attitude",
    "analyse_vibration": ("gyrocore.flight.vibration", "analyse"),
    # errors
    "GyroInputError": "gyrocore.errors",
    "UnobservableError": "gyrocore.errors",
    "RepairWarning": "gyrocore.errors",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str):
    try:
        where = _EXPORTS[name]
    except KeyError:
        raise AttributeError(f"module 'gyrocore' has no attribute {name!r}") from None
    mod, attr = where if isinstance(where, tuple) else (where, name)
    value = getattr(importlib.import_module(mod), attr)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
