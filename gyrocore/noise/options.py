"""Options of the noise identification, passed in (never module state)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["NoiseOptions", "DEFAULT_NOISE_OPTIONS"]


@dataclass(frozen=True)
class NoiseOptions:
    """How :func:`gyrocore.noise.allan.identify_noise` and :func:`gyrocore.noise.gmwm.fit_noise`
    decide (defaults = the project's rule).

    Parameters
    ----------
    robust_ci : bool
        Intervals of selected long-τ terms widened to cover an unselected confounder the data
        cannot exclude (:func:`gyrocore.noise.gmwm._robust_ends`). Default True; False gives the
        intervals conditional on the selected model alone.
    rw_check : bool
        A claimed rate random walk K must also reject a Gauss–Markov bias that turns over inside
        the record, on the exact likelihood of the block means (:mod:`gyrocore.noise.rwgm`):
        applied per axis by ``identify_noise`` and counted by
        :func:`gyrocore.noise.gmwm.expected_z`. **Default False**: held out (seed 20261124,
        6 replicates × 3 axes per cell) it turned 1 of 9 false K claims for a GM of τc = 20 s in
        10-min records into "ambiguous" and 8 true K at 1–4 h as well — the test's
        noncentrality is ≈ 7.5 at every record length (docs/noise.md), so it costs K a fixed
        share at any length.
    """

    robust_ci: bool = True
    rw_check: bool = False


DEFAULT_NOISE_OPTIONS = NoiseOptions()
