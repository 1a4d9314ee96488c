"""Work spread over processes: the thread environment of spawned workers."""

from __future__ import annotations

import contextlib
import os
from typing import Mapping

__all__ = ["WORKER_ENV", "worker_environment"]


#: Thread counts for spawned worker processes (Monte Carlo, batch): one BLAS/OpenMP thread each,
#: so that N workers on N cores do not oversubscribe (as Dask's nanny does).
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@contextlib.contextmanager
def worker_environment(defaults: Mapping[str, str] = WORKER_ENV):
    """Set the unset variables of ``defaults`` in os.environ for the duration of the block."""
    added = [k for k in defaults if k not in os.environ]
    for k in added:
        os.environ[k] = defaults[k]
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)
