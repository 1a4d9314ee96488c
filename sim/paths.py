"""Where the MJCF models live.

The ``models/`` folder sits at the top of the repository, next to the ``sim`` package
(``pip install -e .`` keeps it there). ``GYROHARNESS_MODELS`` overrides the location
(e.g. for a non-editable install that ships the models elsewhere).
"""

from __future__ import annotations

import os
from pathlib import Path

from gyrocore.errors import GyroInputError

__all__ = ["models_dir", "model_path", "QUADROTOR_XML", "TURNTABLE_XML"]

QUADROTOR_XML = "quadrotor.xml"
TURNTABLE_XML = "turntable.xml"


def models_dir() -> Path:
    """The folder holding the MJCF files.

    Returns
    -------
    Path
        ``$GYROHARNESS_MODELS`` if set, else ``<repo>/models`` (the parent of this package).
    """
    env = os.environ.get("GYROHARNESS_MODELS")
    path = Path(env) if env else Path(__file__).resolve().parents[1] / "models"
    if not path.is_dir():
        raise GyroInputError(f"models folder not found: {path} (set GYROHARNESS_MODELS)")
    return path


def model_path(name: str) -> Path:
    """Full path of one model file in :func:`models_dir` (e.g. ``"turntable.xml"``)."""
    path = models_dir() / name
    if not path.is_file():
        raise GyroInputError(f"model file not found: {path}")
    return path
