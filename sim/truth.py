"""Ground truth handed from the MuJoCo runners to the synthetic gyro."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

__all__ = ["Truth"]


@dataclass(frozen=True, eq=False)
class Truth:
    """Truth at the gyro's output sample times.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Sample times, s (the gyro's own output clock).
    omega_S_rad_s : ndarray, shape (N, 3)
        True angular rate of S relative to W, expressed in S, rad/s.
    f_S_m_s2 : ndarray, shape (N, 3)
        True specific force at the IMU site, in S, m/s² (+9.81 on the up axis at rest).
    q_SW_wxyz : ndarray, shape (N, 4)
        True attitude, unit quaternion (w, x, y, z) rotating S to W.
    temp_c : ndarray, shape (N,)
        Sensor die temperature, °C (from :mod:`sim.thermal`).
    t_since_power_up_s : ndarray, shape (N,)
        Time since the last power-up, s (resets in ``power_cycles``).
    power_up_index : ndarray of int, shape (N,)
        Which power-up each sample belongs to (0, 1, ...); the turn-on bias is redrawn per index.
    meta : mapping
        Scenario description (name, model file, physics rate, ...), written as ``#`` metadata.
    """

    t_s: np.ndarray
    omega_S_rad_s: np.ndarray
    f_S_m_s2: np.ndarray
    q_SW_wxyz: np.ndarray
    temp_c: np.ndarray
    t_since_power_up_s: np.ndarray
    power_up_index: np.ndarray
    meta: Mapping[str, str] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.t_s.shape[0])
