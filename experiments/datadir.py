"""Where the real measured recordings are: the one data-folder finder of the harness."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["DEFAULT_DATA_DIR", "shared_data_dir"]

#: The folder beside the checkout (``<repo>/../shared/data``, INDEX.md and PROVENANCE.md there).
DEFAULT_DATA_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def shared_data_dir() -> Path | None:
    """The real-data folder: env ``GYROHARNESS_DATA`` when set, else :data:`DEFAULT_DATA_DIR`;
    None when that folder does not exist (callers skip the real sets)."""
    env = os.environ.get("GYROHARNESS_DATA")
    p = Path(env) if env else DEFAULT_DATA_DIR
    return p if p.is_dir() else None
