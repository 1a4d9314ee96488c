"""The synthetic MEMS gyro: truth -> realistic measurement, with the whole effect catalogue.

Measurement model (DESIGN.md, "The effect catalogue")::

    omega_meas = Q( sat( D( K(T)·omega(t − τ) + b(T, t) + H·f + G·(f⊗f) + nonlinear(omega) ) + noise ) )

The formulas live in :mod:`gyrocore.effects.registry` and are used here, not re-implemented:
:func:`gyrocore.effects.registry.deterministic` gives the part inside ``D(...)`` and
:func:`gyrocore.effects.registry.output_stage` applies ``D`` (on-chip low-pass), adds the noise,
saturates and quantizes. This module supplies what the core does not: a drawn sensor
instance (:meth:`sim.presets.SensorSpec.draw_instance`), the turn-on bias redrawn at every
power-up, and the stochastic terms (:mod:`sim.noise`).

Random streams: every effect draws from its own stream
``sim.noise.effect_rng(seed, key)`` with a stable key (``"instance/<effect>"`` for the unit's
parameters, ``"noise/<effect>"`` for the noise realisation, ``"turn_on/<k>"`` for the bias
of power-up k), so adding or removing an effect never changes another's draws.

Two paths:

* :meth:`SyntheticGyro.measure` — batch, for a whole :class:`sim.truth.Truth`. Every
  power-up (``truth.power_up_index``) is a separate run of the chip: its own turn-on bias,
  ``t_since_power_up_s`` restarting, the on-chip filter restarting from steady state.
* :meth:`SyntheticGyro.stream` — :class:`GyroStream`, the per-sample path for closed loop
  (the hover controller reads the gyro every step). Plain float arithmetic in the same order
  as :mod:`gyrocore.effects.registry` (which uses fixed-order elementwise arithmetic for this reason),
  so the stream is bit-identical to :meth:`measure` on the same truth (one power-up).
"""

from __future__ import annotations

import array
import math
from dataclasses import dataclass, field
from typing import Iterable, Iterator, Mapping

import numpy as np
from scipy import signal

from gyrocore.effects.registry import (
    FF_ORDER,
    OUTPUT_STAGE as _CORE_OUTPUT_STAGE,
    PARAM_SCHEMA,
    REGISTRY,
    NOISE,
    NOISE_TERMS,
    ModelInputs,
    check_effect_names,
    context_rows,
    deterministic,
    earth_rate_W,
    k_matrix,
    ordered_effects,
    output_stage,
    resolve,
    validate_params,
)
from gyrocore.errors import GyroInputError

from . import noise as _noise
from .presets import SensorSpec, load_preset
from .thermal import TempRateBlocks
from .truth import Truth

__all__ = ["SyntheticGyro", "GyroOutput", "GyroChunk", "GyroNoise", "GyroStream", "OUTPUT_STAGE", "NOISE_ORDER"]

#: Effects applied by gyrocore.effects.registry.output_stage (not by deterministic()).
OUTPUT_STAGE = ("lowpass", "saturation", "quantization")
#: Order in which the stochastic terms are summed into the noise.
NOISE_ORDER = ("arw", "bias_instability", "rrw", "correlated", "vibration", "arw_lowpass", "arw_student", "angle_white")
_FF_IDX = tuple(("xyz".index(p[0]), "xyz".index(p[1])) for p in FF_ORDER)
#: A lowpass bandwidth at or above this fraction of the rate is repaired (Nyquist).
_LOWPASS_MAX_FRACTION = 0.45
_LOWPASS_REPAIR_FRACTION = 0.25


@dataclass(frozen=True, eq=False)
class GyroOutput:
    """What the synthetic gyro produced for one truth.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Sample times, s.
    gyro_rad_s : ndarray, shape (N, 3)
        The measurement, rad/s, sensor frame S.
    noise_rad_s : ndarray, shape (N, 3)
        The summed stochastic noise that was added inside the output stage (after the
        low-pass, before saturation/quantization), rad/s.
    draws : dict
        What each effect drew: ``bias`` -> ``b_rad_s_per_power_up`` (P, 3), the unit's
        ``b_mean_rad_s``, ``turn_on_sigma_rad_s``, ``power_up_indices``; each stochastic
        effect -> ``mean_rad_s``, ``std_rad_s`` (and ``final_rad_s`` for ``rrw``) of its
        realisation; every other active effect -> the unit's drawn parameters.
    params : dict
        The instance's true parameters (PARAM_SCHEMA form, SI), as used.
    """

    t_s: np.ndarray
    gyro_rad_s: np.ndarray
    noise_rad_s: np.ndarray
    draws: Mapping[str, Mapping[str, np.ndarray]] = field(default_factory=dict)
    params: Mapping[str, Mapping[str, np.ndarray]] = field(default_factory=dict)


def _complete_override(eff: str, given: Mapping, base: Mapping | None, temp_ref_c: float) -> dict:
    """Merge an override into the effect's parameters; shapes broadcast to PARAM_SCHEMA."""
    schema = PARAM_SCHEMA[eff]
    out = {k: np.array(v, float) for k, v in (base or {}).items()}
    for pname, val in given.items():
        if pname not in schema and pname != "turn_on_sigma_rad_s":
            known = ", ".join(list(schema) + (["turn_on_sigma_rad_s"] if eff == "bias" else [])) or "none"
            raise GyroInputError(f"effect {eff} has no parameter '{pname}'; parameters: {known}")
        v = np.asarray(val, float)
        shape = schema.get(pname, (3,))
        if "p" in shape:  # thermal polynomial (3, p): scalar or (3,) means order 1
            if v.ndim == 0:
                v = np.full((3, 1), float(v))
            elif v.ndim == 1 and v.shape[0] == 3:
                v = v[:, None]
            elif v.ndim == 1:
                raise GyroInputError(f"effect {eff}: {pname} needs 3 values per order, got {v.shape[0]}")
        else:
            try:
                v = np.broadcast_to(v, shape).copy()
            except ValueError:
                raise GyroInputError(
                    f"effect {eff}: {pname} has shape {v.shape}, expected {shape} (or a scalar)"
                ) from None
        out[pname] = v
    defaults = {
        "t0_c": temp_ref_c,
        "temp_min_c": -40.0,
        "temp_max_c": 85.0,
        "heading_rad": 0.0,
        **resolve(eff).defaults,
    }  # family terms: unspecified coefficients are 0
    for pname in schema:
        if pname not in out and pname in defaults:
            out[pname] = np.asarray(defaults[pname])
    if eff == "bias" and "turn_on_sigma_rad_s" not in out:
        out["turn_on_sigma_rad_s"] = np.zeros(3)
    missing = [p for p in schema if p not in out]
    if missing:
        raise GyroInputError(
            f"effect {eff} is not in the preset: give {', '.join(missing)} (e.g. --set {eff}.{missing[0]}=...)"
        )
    return out


class SyntheticGyro:
    """One simulated gyro unit.

    Parameters
    ----------
    spec : SensorSpec or str or path
        Sensor model (a preset name, a TOML path or a :class:`SensorSpec`).
    rate_hz : float, optional
        Output data rate, Hz (default: the preset's).
    seed : int
        Unit seed (>= 0): the instance parameters, the turn-on biases and the noise
        realisations all derive from it, each effect on its own stream.
    run : int
        Run index of this unit (>= 0): run r > 0 is another session of the same unit (same
        instance parameters, fresh turn-on biases and noise; stream keys get ``/run<r>``).
    without : iterable of str
        Effects to switch off (catalogue names).
    overrides : mapping
        ``{effect: {param: value}}`` in SI (PARAM_SCHEMA names). Switches an effect on with
        these values even when the preset has it off; missing parameters come from the
        preset's distribution (if it has one) or from defaults (thermal range −40…85 °C,
        t0 = preset reference, heading 0, turn-on σ 0). Scalars broadcast to the schema
        shape; a thermal polynomial given as 3 values is order 1.

    Attributes
    ----------
    params : dict
        The unit's true parameters (PARAM_SCHEMA form, SI). ``bias.b_rad_s`` is the unit's
        mean bias; each power-up adds N(0, ``turn_on_sigma_rad_s``²).
    rate_hz : float
    seed : int
    spec : SensorSpec
    """

    def __init__(
        self,
        spec: SensorSpec | str,
        *,
        rate_hz: float | None = None,
        seed: int,
        without: Iterable[str] = (),
        overrides: Mapping[str, Mapping[str, object]] | None = None,
        run: int = 0,
    ) -> None:
        self.spec = load_preset(spec)
        self.rate_hz = float(self.spec.rate_hz if rate_hz is None else rate_hz)
        if not (math.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise GyroInputError(f"gyro rate must be > 0 Hz, got {rate_hz}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise GyroInputError(f"seed must be an integer >= 0, got {seed!r}")
        self.seed = int(seed)
        if isinstance(run, bool) or not isinstance(run, (int, np.integer)) or run < 0:
            raise GyroInputError(f"run must be an integer >= 0, got {run!r}")
        self.run = int(run)
        #: notes on adjustments made to the preset (e.g. the DLPF moved below Nyquist)
        self.notes: list[str] = []
        without = check_effect_names(list(without))
        given = dict(overrides or {})
        overrides = {}
        for name, val in given.items():  # canonical names (family terms: periodic[37.50] = periodic[37.5])
            (canon,) = check_effect_names([name])
            if canon in overrides:
                raise GyroInputError(f"effect {canon} is overridden twice ({name!r} is another spelling of it)")
            overrides[canon] = val
        clash = set(without) & set(overrides)
        if clash:
            raise GyroInputError(f"effect {sorted(clash)[0]} is both overridden and switched off")
        include = [e for e in overrides if e not in self.spec.effects and self.spec.distribution(e) is not None]
        params = self.spec.draw_instance(self.seed, include=include)
        if self.spec.shaped_vibration and "vibration" not in overrides:
            params["vibration"] = {k: np.asarray(v, float) for k, v in self.spec.shaped_vibration.items()}
        for eff, given in overrides.items():
            if eff == "vibration":
                # the physics part comes from the hover; an override carries only the shaped part
                # (f_hz, psd_rad2_s2_hz: gyrocore.flight.synthesis.shaped_params), or {} for none
                if not isinstance(given, Mapping):
                    raise GyroInputError("override of vibration must map parameter names to values")
                params[eff] = validate_params({eff: dict(given)})[eff]
                continue
            if not isinstance(given, Mapping):
                raise GyroInputError(f"override of {eff} must map parameter names to values")
            params[eff] = _complete_override(eff, given, params.get(eff), self.spec.temp_ref_c)
        for eff in without:
            params.pop(eff, None)
        if "lowpass" in params and "lowpass" not in overrides:
            fc = float(params["lowpass"]["bandwidth_hz"])
            if fc >= _LOWPASS_MAX_FRACTION * self.rate_hz:
                # as the chips' DLPF tables do when the ODR is lowered: bandwidth ≈ ODR/4
                new = _LOWPASS_REPAIR_FRACTION * self.rate_hz
                self.notes.append(
                    f"lowpass {fc:g} Hz is above 0.45 x the {self.rate_hz:g} Hz output rate; set to {new:g} Hz (rate/4)"
                )
                params["lowpass"] = {"bandwidth_hz": np.asarray(new)}
        self.params = validate_params({e: params[e] for e in ordered_effects(params)})
        self.overridden = tuple(ordered_effects(overrides))
        self.without = tuple(without)

    # ------------------------------------------------------------------ pieces
    def _key(self, key: str) -> str:
        return key if self.run == 0 else f"{key}/run{self.run}"

    @property
    def effects(self) -> tuple[str, ...]:
        """Active effects, model order (catalogue, then registry family terms by name)."""
        return tuple(self.params)

    def power_up_bias(self, index: int) -> np.ndarray:
        """Bias during power-up ``index``, rad/s (3,): mean + N(0, turn-on σ²) from stream ``turn_on/<index>``."""
        if "bias" not in self.params:
            return np.zeros(3)
        pd = self.params["bias"]
        sigma = np.asarray(pd.get("turn_on_sigma_rad_s", np.zeros(3)), float)
        z = _noise.effect_rng(self.seed, self._key(f"turn_on/{int(index)}")).standard_normal(3)
        return pd["b_rad_s"] + z * sigma

    def noise_blocks(self) -> "GyroNoise":
        """The summed stochastic noise as a block generator (:class:`GyroNoise`), from sample 0.

        Each term draws from its own stream ``noise/<effect>`` (:mod:`sim.noise` block
        generators); ``take(m)`` gives the next m samples, bit-identical however the record
        is cut into blocks.
        """
        return GyroNoise(self)

    def noise(self, n_samples: int) -> tuple[np.ndarray, dict[str, dict[str, np.ndarray]]]:
        """The summed stochastic noise for ``n_samples`` samples, rad/s (N, 3), and per-effect summaries.

        Terms are generated from their own streams ``noise/<effect>`` and summed in
        :data:`NOISE_ORDER` (one block of :meth:`noise_blocks`).
        """
        n = int(n_samples)
        total, parts = self.noise_blocks().take(n, parts=True)
        draws: dict[str, dict[str, np.ndarray]] = {}
        for eff, x in parts.items():
            d = {"mean_rad_s": x.mean(axis=0) if n else np.zeros(3), "std_rad_s": x.std(axis=0) if n else np.zeros(3)}
            if eff == "rrw" and n:
                d["final_rad_s"] = x[-1].copy()
            draws[eff] = d
        return total, draws

    def _model_params(self, bias_rad_s: np.ndarray) -> dict:
        """Deterministic + output-stage parameters with the given power-up bias."""
        p = {e: v for e, v in self.params.items() if e not in NOISE}
        if "bias" in p:
            p["bias"] = {"b_rad_s": np.asarray(bias_rad_s, float)}
        return p

    def _check_truth_rate(self, t_s: np.ndarray) -> None:
        if t_s.shape[0] < 2:
            return
        dt = float(np.median(np.diff(t_s)))
        if not dt > 0 or abs(1.0 / dt - self.rate_hz) > 1e-6 * self.rate_hz:
            raise GyroInputError(
                f"truth is sampled at {1.0 / dt if dt > 0 else float('nan'):.6g} Hz but the gyro runs at {self.rate_hz:.6g} Hz"
            )

    # ------------------------------------------------------------------ batch
    def measure(self, truth: Truth) -> GyroOutput:
        """Measure a whole truth (batch path).

        Parameters
        ----------
        truth : sim.truth.Truth
            Truth at the gyro's output times (rate must equal ``rate_hz``).

        Returns
        -------
        GyroOutput
        """
        t = np.asarray(truth.t_s, float)
        n = t.shape[0]
        self._check_truth_rate(t)
        noise_total, draws = self.noise(n)
        pu = np.asarray(truth.power_up_index).astype(int)
        # contiguous runs of one power-up index
        edges = np.flatnonzero(np.diff(pu)) + 1
        starts = np.concatenate([[0], edges]).astype(int)
        stops = np.concatenate([edges, [n]]).astype(int)
        indices = [int(pu[s]) for s in starts] if n else []
        if len(set(indices)) != len(indices):
            raise GyroInputError("truth.power_up_index must not return to an earlier power-up")
        y = np.empty((n, 3))
        biases = {}
        for s0, s1, idx in zip(starts, stops, indices):
            b = self.power_up_bias(idx)
            biases[idx] = b
            sl = slice(s0, s1)
            inp = ModelInputs(
                t_s=t[sl],
                omega_S_rad_s=np.asarray(truth.omega_S_rad_s, float)[sl],
                f_S_m_s2=np.asarray(truth.f_S_m_s2, float)[sl],
                temp_c=np.asarray(truth.temp_c, float)[sl],
                q_SW_wxyz=np.asarray(truth.q_SW_wxyz, float)[sl],
                t_since_power_up_s=np.asarray(truth.t_since_power_up_s, float)[sl],
            )
            p = self._model_params(b)
            x = deterministic(p, inp)
            y[sl] = output_stage(x, p, rate_hz=self.rate_hz, noise_rad_s=noise_total[sl])
        for eff, pd in self.params.items():
            if eff == "bias":
                draws["bias"] = {
                    "b_mean_rad_s": pd["b_rad_s"].copy(),
                    "turn_on_sigma_rad_s": np.asarray(pd.get("turn_on_sigma_rad_s", np.zeros(3))).copy(),
                    "power_up_indices": np.asarray(indices, int),
                    "b_rad_s_per_power_up": np.array([biases[i] for i in indices]).reshape(-1, 3),
                }
            elif eff not in NOISE:
                draws[eff] = {k: np.array(v) for k, v in pd.items()}
        draws = {e: draws[e] for e in ordered_effects(draws)}
        return GyroOutput(t_s=t, gyro_rad_s=y, noise_rad_s=noise_total, draws=draws, params=self.params)

    # ------------------------------------------------------------------ chunked
    def measure_chunks(self, chunks: Iterable[Truth]) -> Iterator["GyroChunk"]:
        """Measure a truth that arrives in consecutive chunks (bounded memory).

        Parameters
        ----------
        chunks : iterable of sim.truth.Truth
            Consecutive pieces of one truth (any lengths, ≥ 0 samples each), in time order.

        Yields
        ------
        GyroChunk
            Consecutive pieces of the measurement. Bit-identical, row for row, to
            :meth:`measure` on the concatenated truth, whatever the chunk lengths: the
            deterministic model is evaluated on each piece with
            :func:`gyrocore.effects.registry.context_rows` neighbour rows on each side (central
            differences, the time-offset shift), clipped to the power-up; the on-chip
            low-pass carries its memory across pieces and restarts from steady state at each
            power-up; the noise comes from :meth:`noise_blocks`. Output lags the input by at
            most the context rows; the buffer holds at most one input chunk plus the context.
        """
        eng = _ChunkedMeasure(self)
        for ch in chunks:
            yield from eng.feed(ch)
        yield from eng.finish()

    # ------------------------------------------------------------------ stream
    def stream(
        self,
        n_samples: int,
        *,
        t_power_up_s: float | None = None,
        t_s: np.ndarray | None = None,
        temp_c: np.ndarray | None = None,
        blocks: bool = False,
        thermal=None,
    ) -> "GyroStream":
        """The per-sample path for closed-loop simulation (one power-up, index 0).

        Parameters
        ----------
        n_samples : int
            Number of samples the run will take (the noise is precomputed for all of them,
            unless ``blocks``).
        t_power_up_s : float, optional
            Power-up time: ``t_since_power_up = t_s − t_power_up_s``; default the first
            step's ``t_s``.
        t_s, temp_c : ndarray, shape (n_samples,), optional
            The whole time base and temperature trajectory, needed only by
            ``bias_temp_rate`` (its dT/dt is a central difference, which looks one sample
            ahead; gyrocore.effects.registry.ModelInputs.temp_rate_c_s).
        blocks : bool
            Bounded memory: noise and output are held one block at a time; the
            caller opens each block with :meth:`GyroStream.next_block` before stepping it.
            The samples are bit-identical to the whole stream's whatever the block sizes.
        thermal : sim.thermal.ThermalSpec, optional
            With ``blocks``: the die temperature model on the clock ``k / rate_hz`` (one
            power-up, no motor heating) from which ``bias_temp_rate``'s dT/dt is computed block
            by block (:class:`sim.thermal.TempRateBlocks`), instead of ``t_s``/``temp_c``.

        Returns
        -------
        GyroStream
        """
        return GyroStream(
            self, int(n_samples), t_power_up_s=t_power_up_s, t_s=t_s, temp_c=temp_c, blocks=blocks, thermal=thermal
        )


@dataclass(frozen=True, eq=False)
class _OneSample(ModelInputs):
    """One sample's model inputs in a stream; dT/dt comes from the precomputed trajectory."""

    temp_rate: float = math.nan

    def temp_rate_c_s(self, effect: str = "bias_temp_rate") -> np.ndarray:
        return np.array([self.temp_rate])


class GyroStream:
    """Per-sample synthetic gyro (see :meth:`SyntheticGyro.stream`).

    ``step(k, t_s, omega_S, f_S, temp_c)`` returns sample k, bit-identical to
    ``SyntheticGyro.measure`` on the same truth. Samples must be stepped in order
    k = 0, 1, …, n−1. The returned array is a read-only view of row k of
    :attr:`gyro_rad_s` (the whole output so far; copy it if you keep it).

    Not supported in closed loop: a leading gyro (``time_offset`` τ < 0, which needs future
    truth), ``regressor`` terms of the rate derivative ``alpha_*`` (a central difference, it
    needs the next sample), and ``bias_temp_rate`` (or a ``dtemp_dt`` term) without the
    temperature trajectory given up front. Registry family terms run through a generic
    per-step call (the batch path's numpy term on a one-sample input); in
    :func:`sim.quadrotor.fly_hover`'s compiled kernels, terms of time alone (periodic, step,
    ``regressor[t]``) are tabulated before the flight (:meth:`family_table`), and a gyro with
    any other family term flies the Python loop.
    """

    def __init__(
        self,
        gyro: SyntheticGyro,
        n_samples: int,
        *,
        t_power_up_s=None,
        t_s=None,
        temp_c=None,
        blocks: bool = False,
        thermal=None,
    ) -> None:
        if n_samples < 1:
            raise GyroInputError(f"n_samples must be >= 1, got {n_samples}")
        self.n = n_samples
        self.rate_hz = gyro.rate_hz
        P = gyro.params
        #: True: noise and output are held one block at a time (:meth:`next_block`)
        self.blocked = bool(blocks)
        self._k_next = 0
        self._t_pu = None if t_power_up_s is None else float(t_power_up_s)
        self.bias_rad_s = gyro.power_up_bias(0)
        if thermal is not None and not self.blocked:
            raise GyroInputError("GyroStream: thermal= goes with blocks=True (else pass t_s= and temp_c=)")
        # dT/dt of the die temperature (bias_temp_rate, dtemp_dt terms): a central difference,
        # one sample ahead; whole (from t_s/temp_c) or block by block (from thermal)
        need_rate = "bias_temp_rate" in P or any(
            "dtemp" in resolve(e).inputs for e in P if resolve(e).family is not None
        )
        self._temp_rate_all = None
        self._temp_rate_blocks = None
        if need_rate and self.blocked and thermal is not None:
            self._temp_rate_blocks = TempRateBlocks(thermal, n_samples, self.rate_hz)
        elif need_rate and t_s is not None and temp_c is not None:
            t_arr, T_arr = np.asarray(t_s, float), np.asarray(temp_c, float)
            if t_arr.shape != (n_samples,) or T_arr.shape != (n_samples,):
                raise GyroInputError(f"stream t_s/temp_c must have shape ({n_samples},)")
            self._temp_rate_all = np.ascontiguousarray(ModelInputs(t_s=t_arr, temp_c=T_arr).temp_rate_c_s())

        # --- earth rate
        self._earth = None
        if "earth_rate" in P:
            self._earth = [
                float(v)
                for v in earth_rate_W(float(P["earth_rate"]["latitude_rad"]), float(P["earth_rate"]["heading_rad"]))
            ]
        # --- time offset (history of the rate after the earth term)
        self._tau = 0.0
        if "time_offset" in P:
            self._tau = float(P["time_offset"]["tau_s"])
            if self._tau < 0:
                raise GyroInputError(
                    "a leading gyro (time_offset tau_s < 0) needs future truth: not possible in closed loop"
                )
        self._hist_t: list[float] = []
        self._hist_w: list[list[float]] = []
        self._hist_len = int(math.ceil(self._tau * self.rate_hz * 1.5)) + 4
        # --- K and scale diag
        K = k_matrix(P)
        self._K = K.tolist()
        self._has_K = True
        self._sth = self._thermal(P, "scale_thermal", "poly_per_c")
        self._asym = P["scale_asymmetry"]["a"].tolist() if "scale_asymmetry" in P else None
        self._nl = P["scale_nonlinearity"]["s2_s_per_rad"].tolist() if "scale_nonlinearity" in P else None
        # --- additive
        self._b = self.bias_rad_s.tolist() if "bias" in P else None
        self._bth = self._thermal(P, "bias_thermal", "poly_rad_s")
        self._ktr = None
        if "bias_temp_rate" in P:
            if self._temp_rate_all is None and self._temp_rate_blocks is None:
                raise GyroInputError(
                    "bias_temp_rate in a stream needs the temperature trajectory: pass t_s= and temp_c= "
                    "(or, with blocks=True, thermal=) to stream()"
                )
            self._ktr = P["bias_temp_rate"]["k_rad_s_per_c_per_s"].tolist()
        self._ramp = P["bias_ramp"]["ramp_rad_s2"].tolist() if "bias_ramp" in P else None
        self._H = P["g_sensitivity"]["h_rad_s_per_m_s2"].tolist() if "g_sensitivity" in P else None
        self._G = P["g2_sensitivity"]["g_rad_s_per_m2_s4"].tolist() if "g2_sensitivity" in P else None
        # --- registry family terms (periodic, step, regressor): one generic per-step call each,
        #     the same numpy term as the batch path on a one-sample input (model order)
        self._fam = [(resolve(e), P[e]) for e in ordered_effects(P) if resolve(e).family is not None]
        for eff, _ in self._fam:
            if "alpha" in eff.inputs:
                raise GyroInputError(
                    f"effect {eff.name} needs the rate derivative (a central difference of "
                    "future truth): not possible in a stream"
                )
            if "dtemp" in eff.inputs and self._temp_rate_all is None and self._temp_rate_blocks is None:
                raise GyroInputError(
                    f"effect {eff.name} in a stream needs the temperature trajectory: "
                    "pass t_s= and temp_c= (or, with blocks=True, thermal=) to stream()"
                )
        # --- output stage
        self._lp = None
        if "lowpass" in P:
            fc = float(P["lowpass"]["bandwidth_hz"])
            if not 0 < fc < self.rate_hz / 2:
                raise GyroInputError(
                    f"lowpass bandwidth {fc} Hz must be in (0, {self.rate_hz / 2}) Hz at {self.rate_hz} Hz"
                )
            b, a = signal.butter(2, fc, fs=self.rate_hz)
            b = b / a[0]
            a = a / a[0]
            self._lp = (float(b[0]), float(b[1]), float(b[2]), float(a[1]), float(a[2]))
            self._lp_zi = signal.lfilter_zi(b, a)
            self._lp_z = None  # per axis [z0, z1], set at the first sample
        self._sat = float(P["saturation"]["range_rad_s"]) if "saturation" in P else None
        self._q = float(P["quantization"]["lsb_rad_s"]) if "quantization" in P else None
        # --- the current block's arrays: the whole run, or none yet (blocks: next_block)
        self._k0 = 0
        self._blk_end = 0
        if self.blocked:
            self._noise_gen = gyro.noise_blocks()
            self.noise_draws = None
            self._set_block(0, np.zeros((0, 3)), None)
        else:
            noise_total, self.noise_draws = gyro.noise(n_samples)
            self._set_block(0, noise_total, self._temp_rate_all)
        #: step(k, t_s, omega_S, f_S, temp_c, q_SW_wxyz=None) -> ndarray (3,), generated code
        self.step = self._compile()

    def _set_block(self, k0: int, noise: np.ndarray, temp_rate: np.ndarray | None) -> None:
        """Make rows k0 … k0 + len(noise) − 1 the current block: its noise, a zeroed output,
        its dT/dt (or None)."""
        m = int(noise.shape[0])
        #: the current block's summed noise, rad/s (m, 3) (the whole run unless ``blocked``)
        self.noise_rad_s = noise
        # flat C doubles (24 B/sample; a list of lists would cost ~150 B/sample)
        self._nz = array.array("d")
        self._nz.frombytes(np.ascontiguousarray(noise, dtype=np.float64).tobytes())
        #: the current block's output, rad/s (m, 3): row j is sample block_start + j
        self.gyro_rad_s = np.zeros((m, 3))
        self._view = self.gyro_rad_s.view()
        self._view.flags.writeable = False
        #: the current block's dT/dt, °C/s (m,), or None (numpy for the compiled kernels, flat doubles per step)
        self._tr = None if temp_rate is None else np.ascontiguousarray(temp_rate, dtype=np.float64)
        self._tr_l = None
        if temp_rate is not None:
            self._tr_l = array.array("d")
            self._tr_l.frombytes(self._tr.tobytes())
        self._k0 = int(k0)
        self._blk_end = int(k0) + m

    @property
    def block_start(self) -> int:
        """Global index of row 0 of :attr:`gyro_rad_s` and :attr:`noise_rad_s`."""
        return self._k0

    def next_block(self, m: int) -> None:
        """Open the next ``m`` samples (``blocks=True``): their noise (the block generators of
        :meth:`SyntheticGyro.noise_blocks`, bit-identical however the run is cut) and dT/dt;
        the previous block's samples must all have been stepped."""
        if not self.blocked:
            raise GyroInputError("GyroStream.next_block: the stream holds the whole run (blocks=False)")
        m = int(m)
        if self._k_next != self._blk_end:
            raise GyroInputError(
                f"GyroStream.next_block: samples {self._k_next}…{self._blk_end - 1} of the block were not stepped"
            )
        if m < 1 or self._blk_end + m > self.n:
            raise GyroInputError(
                f"GyroStream.next_block: {m} samples from {self._blk_end} exceed the {self.n} allocated"
            )
        tr = self._temp_rate_blocks.take(m) if self._temp_rate_blocks is not None else None
        self._set_block(self._blk_end, self._noise_gen.take(m), tr)

    @property
    def families_time_only(self) -> bool:
        """Every family term depends on time alone (periodic, step, regressor[t]): they can be
        tabulated before the flight (:meth:`family_table`), which the compiled hover kernels use."""
        return all(set(eff.inputs) <= {"t"} for eff, _ in self._fam)

    def family_table(self, t_s: np.ndarray, t_power_up_s: float) -> np.ndarray:
        """The time-only family terms on the whole time base, (n, 3·m) in model order.

        The same numpy term as the batch path and :meth:`_family_step` (elementwise, so each
        row has the same bits as the one-sample call)."""
        if not self.families_time_only:
            raise GyroInputError("family_table: a family term depends on more than time")
        t = np.asarray(t_s, float)
        inp = ModelInputs(t_s=t, t_since_power_up_s=t - float(t_power_up_s))
        cols = [np.asarray(eff.term(pd, inp, None), float) for eff, pd in self._fam]
        return np.concatenate(cols, axis=1) if cols else np.zeros((t.shape[0], 0))

    def _family_step(self, eff, pd):
        """Per-step evaluation of one family term: (k, t, w0, w1, w2, f_S, temp_c) -> (u0, u1, u2)."""
        need_f = "f" in eff.inputs
        need_T = "temp" in eff.inputs
        need_rate = "dtemp" in eff.inputs

        def fam(k, t, w0, w1, w2, f_S, temp_c):
            inp = _OneSample(
                t_s=np.array([t]),
                f_S_m_s2=np.asarray(f_S, float).reshape(1, 3) if need_f else None,
                temp_c=np.array([float(temp_c)]) if need_T else None,
                t_since_power_up_s=np.array([t - self._t_pu]),
                temp_rate=float(self._tr_l[k - self._k0]) if need_rate else math.nan,
            )
            u0, u1, u2 = eff.term(pd, inp, np.array([[w0, w1, w2]]))[0].tolist()
            return u0, u1, u2

        return fam

    @staticmethod
    def _thermal(P, eff, pname):
        if eff not in P:
            return None
        pd = P[eff]
        return (
            np.asarray(pd[pname], float).tolist(),
            float(pd["temp_min_c"]),
            float(pd["temp_max_c"]),
            float(pd["t0_c"]),
        )

    def _shifted(self, k: int, t: float, w0: float, w1: float, w2: float) -> tuple[float, float, float]:
        """Push (t, ω) into the history and return ω(t − τ) as np.interp would.

        numpy (compiled_base.c ``arr_interp``): left of the first point -> the first value; on
        a grid point -> its value; else slope·(x − x_j) + y_j with
        slope = (y_{j+1} − y_j)/(x_{j+1} − x_j).
        """
        ht, hw = self._hist_t, self._hist_w
        if k == 0:
            self._w_first = (w0, w1, w2)
        ht.append(t)
        hw.append((w0, w1, w2))
        if len(ht) > self._hist_len:
            del ht[0]
            del hw[0]
        x = t - self._tau
        j = len(ht) - 1
        while j >= 0 and ht[j] > x:
            j -= 1
        if j < 0:
            return self._w_first
        if j == len(ht) - 1 or ht[j] == x:
            return hw[j]
        dx = ht[j + 1] - ht[j]
        xa, xb = hw[j], hw[j + 1]
        u = x - ht[j]
        return ((xb[0] - xa[0]) / dx * u + xa[0], (xb[1] - xa[1]) / dx * u + xa[1], (xb[2] - xa[2]) / dx * u + xa[2])

    def _start(self, k: int, t: float) -> None:
        if k != self._k_next:
            raise GyroInputError(f"GyroStream.step: expected sample {self._k_next}, got {k}")
        if k >= self.n:
            raise GyroInputError(f"GyroStream.step: only {self.n} samples were allocated")
        if k >= self._blk_end:
            raise GyroInputError(f"GyroStream.step: sample {k} is beyond the open block (next_block first)")
        if k == 0 and self._t_pu is None:
            self._t_pu = t

    # ------------------------------------------------------------------ code generation
    def _compile(self):
        """Build ``step`` as straight-line float code for the active effects.

        Each block mirrors one formula of :mod:`gyrocore.effects.registry` operation by operation
        (same operands, same order, no fused multiply-add), which is what makes the stream
        bit-identical to the batch path; the generated source is kept in ``self.step_source``.
        """
        env: dict = {"S": self, "_nd": np.ndarray, "GyroInputError": GyroInputError, "_sqrt": math.sqrt}
        L = [
            "def step(k, t_s, omega_S, f_S, temp_c, q_SW_wxyz=None):",
            "    if k != S._k_next or k >= S._blk_end or k == 0:",
            "        S._start(k, float(t_s))",
            "    S._k_next = k + 1",
            "    t = float(t_s)",
            "    if type(omega_S) is _nd:",
            "        w0, w1, w2 = omega_S.tolist()",
            "    else:",
            "        w0, w1, w2 = omega_S",
            "        w0 = float(w0); w1 = float(w1); w2 = float(w2)",
        ]
        need_T = self._sth is not None or self._bth is not None
        if need_T:
            L.append("    T = float(temp_c)")
        if self._earth is not None:
            env["e0"], env["e1"], env["e2"] = self._earth
            L += [
                "    if q_SW_wxyz is None: raise GyroInputError('earth_rate in a stream needs q_SW_wxyz at every step')",
                "    if type(q_SW_wxyz) is _nd:",
                "        qw, qx, qy, qz = q_SW_wxyz.tolist()",
                "    else:",
                "        qw, qx, qy, qz = q_SW_wxyz",
                "        qw = float(qw); qx = float(qx); qy = float(qy); qz = float(qz)",
                "    nq = _sqrt(qw * qw + qx * qx + qy * qy + qz * qz)",
                "    qw = qw / nq; qx = qx / nq; qy = qy / nq; qz = qz / nq",
                "    r00 = 1 - 2 * (qy * qy + qz * qz); r01 = 2 * (qx * qy - qw * qz); r02 = 2 * (qx * qz + qw * qy)",
                "    r10 = 2 * (qx * qy + qw * qz); r11 = 1 - 2 * (qx * qx + qz * qz); r12 = 2 * (qy * qz - qw * qx)",
                "    r20 = 2 * (qx * qz - qw * qy); r21 = 2 * (qy * qz + qw * qx); r22 = 1 - 2 * (qx * qx + qy * qy)",
                "    w0 = w0 + (r00 * e0 + r10 * e1 + r20 * e2)",
                "    w1 = w1 + (r01 * e0 + r11 * e1 + r21 * e2)",
                "    w2 = w2 + (r02 * e0 + r12 * e1 + r22 * e2)",
            ]
        if self._tau != 0.0:
            L.append("    w0, w1, w2 = S._shifted(k, t, w0, w1, w2)")
        K = self._K
        for i in range(3):
            env[f"K{i}0"], env[f"K{i}1"], env[f"K{i}2"] = K[i]
            L.append(f"    y{i} = w0 * K{i}0 + w1 * K{i}1 + w2 * K{i}2")

        def poly_lines(th, tag, target):
            coef, lo, hi, t0 = th
            env[f"{tag}_lo"], env[f"{tag}_hi"], env[f"{tag}_t0"] = lo, hi, t0
            out = [
                "    Tc = T",
                f"    if Tc < {tag}_lo: Tc = {tag}_lo",
                f"    if Tc > {tag}_hi: Tc = {tag}_hi",
                f"    dT = Tc - {tag}_t0",
            ]
            p = len(coef[0])
            out.append("    pw1 = dT")
            for kk in range(2, p + 1):
                out.append(f"    pw{kk} = pw{kk - 1} * dT")
            for i in range(3):
                terms = []
                for kk in range(p):
                    env[f"{tag}_{i}_{kk}"] = coef[i][kk]
                    terms.append(f"pw{kk + 1} * {tag}_{i}_{kk}")
                out.append(f"    {target}{i} = {target}{i} + ({' + '.join(terms)})")
            return out

        L.append("    d0 = 0.0; d1 = 0.0; d2 = 0.0")
        if self._sth is not None:
            L += poly_lines(self._sth, "sth", "d")
        if self._asym is not None:
            for i in range(3):
                env[f"as{i}"] = self._asym[i]
                L.append(f"    d{i} = d{i} + ((w{i} > 0) - (w{i} < 0)) * as{i}")
        if self._nl is not None:
            for i in range(3):
                env[f"nl{i}"] = self._nl[i]
                L.append(f"    d{i} = d{i} + abs(w{i}) * nl{i}")
        for i in range(3):
            L.append(f"    y{i} = y{i} + d{i} * w{i}")
        L.append("    a0 = 0.0; a1 = 0.0; a2 = 0.0")
        if self._b is not None:
            for i in range(3):
                env[f"b{i}"] = self._b[i]
                L.append(f"    a{i} = a{i} + b{i}")
        if self._bth is not None:
            L += poly_lines(self._bth, "bth", "a")
        if self._ktr is not None:
            L.append("    r = S._tr_l[k - S._k0]")
            for i in range(3):
                env[f"kt{i}"] = self._ktr[i]
                L.append(f"    a{i} = a{i} + r * kt{i}")
        if self._ramp is not None:
            L.append("    ts = t - S._t_pu")
            for i in range(3):
                env[f"rp{i}"] = self._ramp[i]
                L.append(f"    a{i} = a{i} + ts * rp{i}")
        if self._H is not None or self._G is not None:
            L += [
                "    if type(f_S) is _nd:",
                "        f0, f1, f2 = f_S.tolist()",
                "    else:",
                "        f0, f1, f2 = f_S",
                "        f0 = float(f0); f1 = float(f1); f2 = float(f2)",
            ]
        if self._H is not None:
            for i in range(3):
                for j in range(3):
                    env[f"H{i}{j}"] = self._H[i][j]
                L.append(f"    a{i} = a{i} + (f0 * H{i}0 + f1 * H{i}1 + f2 * H{i}2)")
        if self._G is not None:
            for jj, (i, j) in enumerate(_FF_IDX):
                L.append(f"    ff{jj} = f{i} * f{j}")
            for i in range(3):
                for jj in range(6):
                    env[f"G{i}_{jj}"] = self._G[i][jj]
                L.append(f"    a{i} = a{i} + ({' + '.join(f'ff{jj} * G{i}_{jj}' for jj in range(6))})")
        for j, (eff, pd) in enumerate(self._fam):
            env[f"FAM{j}"] = self._family_step(eff, pd)
            L.append(f"    u0, u1, u2 = FAM{j}(k, t, w0, w1, w2, f_S, temp_c)  # {eff.name}")
            for i in range(3):
                L.append(f"    a{i} = a{i} + u{i}")
        for i in range(3):
            L.append(f"    x{i} = y{i} + a{i}")
        if self._lp is not None:
            env["lb0"], env["lb1"], env["lb2"], env["la1"], env["la2"] = self._lp
            env["Z"] = self._lp_state = [0.0] * 6
            env["zi0"], env["zi1"] = (float(v) for v in self._lp_zi)
            L.append("    if k == 0:")
            for i in range(3):
                L.append(f"        Z[{2 * i}] = zi0 * x{i}; Z[{2 * i + 1}] = zi1 * x{i}")
            for i in range(3):
                L += [
                    f"    yn = Z[{2 * i}] + lb0 * x{i}",
                    f"    Z[{2 * i}] = Z[{2 * i + 1}] + x{i} * lb1 - yn * la1",
                    f"    Z[{2 * i + 1}] = x{i} * lb2 - yn * la2",
                    f"    x{i} = yn",
                ]
        # the current block's rows (the whole run unless blocked): row j = sample k0 + j
        L.append("    j = k - S._k0")
        L.append("    NZ = S._nz")
        L.append("    k3 = 3 * j")
        L.append("    x0 = x0 + NZ[k3]; x1 = x1 + NZ[k3 + 1]; x2 = x2 + NZ[k3 + 2]")
        if self._sat is not None:
            env["SAT"], env["NSAT"] = self._sat, -self._sat
            for i in range(3):
                L.append(f"    x{i} = NSAT if x{i} < NSAT else (SAT if x{i} > SAT else x{i})")
        if self._q is not None:
            env["LSB"] = self._q
            L.append("    x0 = round(x0 / LSB) * LSB; x1 = round(x1 / LSB) * LSB; x2 = round(x2 / LSB) * LSB")
        L += ["    row = S.gyro_rad_s[j]", "    row[0] = x0; row[1] = x1; row[2] = x2", "    return S._view[j]"]
        src = "\n".join(L) + "\n"
        exec(compile(src, "<GyroStream.step>", "exec"), env)
        self.step_source = src
        return env["step"]


@dataclass(frozen=True, eq=False)
class GyroChunk:
    """One piece of a chunked measurement (:meth:`SyntheticGyro.measure_chunks`).

    Parameters
    ----------
    start : int
        Index of the first row in the whole record.
    t_s : ndarray, shape (m,)
        Sample times, s.
    gyro_rad_s : ndarray, shape (m, 3)
        The measurement, rad/s, sensor frame S.
    noise_rad_s : ndarray, shape (m, 3)
        The summed stochastic noise of these rows, rad/s.
    power_up_bias_rad_s : dict
        Turn-on bias of every power-up begun so far, {index: (3,)} rad/s.
    truth : sim.truth.Truth
        The truth rows these samples were measured from (same rows; ``meta`` not copied).
    """

    start: int
    t_s: np.ndarray
    gyro_rad_s: np.ndarray
    noise_rad_s: np.ndarray
    power_up_bias_rad_s: Mapping[int, np.ndarray] = field(default_factory=dict)
    truth: Truth | None = None

    @property
    def n(self) -> int:
        return int(self.t_s.shape[0])


class GyroNoise:
    """The summed stochastic noise of one unit as a block generator (:meth:`SyntheticGyro.noise_blocks`)."""

    def __init__(self, gyro: SyntheticGyro) -> None:
        r = gyro.rate_hz
        self.terms: list[tuple[str, object]] = []
        for eff in NOISE_ORDER:
            if eff not in gyro.params:
                continue
            pd = gyro.params[eff]
            rng = _noise.effect_rng(gyro.seed, gyro._key(f"noise/{eff}"))
            if eff == "vibration":
                if "psd_rad2_s2_hz" not in pd:
                    continue  # from the physics alone
                g = _noise.ShapedNoise(rng, _noise.shaped_taps(pd["f_hz"], pd["psd_rad2_s2_hz"], rate_hz=r))
            elif eff in NOISE_TERMS:  # registered noise terms outside the catalogue (gyrocore.effects.registry)
                g = _noise.noise_term_generator(eff, pd, rng, rate_hz=r)
            elif eff == "arw":
                g = _noise.WhiteRateBlocks(rng, rate_hz=r, n_rad_per_sqrt_s=pd["n_rad_per_sqrt_s"])
            elif eff == "bias_instability":
                g = _noise.FlickerBlocks(rng, rate_hz=r, b_rad_s=pd["b_rad_s"])
            elif eff == "rrw":
                g = _noise.RateRandomWalkBlocks(rng, rate_hz=r, k_rad_s_per_sqrt_s=pd["k_rad_s_per_sqrt_s"])
            else:
                g = _noise.GaussMarkovBlocks(rng, rate_hz=r, sigma_rad_s=pd["sigma_rad_s"], tau_c_s=pd["tau_c_s"])
            self.terms.append((eff, g))
        #: samples produced so far
        self.position = 0

    def take(self, m: int, *, parts: bool = False):
        """The next ``m`` samples of the summed noise, rad/s (m, 3); with ``parts=True`` also
        ``{effect: (m, 3)}`` of each term."""
        m = int(m)
        total = np.zeros((m, 3))
        out = {}
        for eff, g in self.terms:
            x = g.take(m)
            total += x
            if parts:
                out[eff] = x
        self.position += m
        return (total, out) if parts else total


_TRUTH_FIELDS = ("t_s", "omega_S_rad_s", "f_S_m_s2", "q_SW_wxyz", "temp_c", "t_since_power_up_s", "power_up_index")


def _lowpass_chunk(pd, y: np.ndarray, rate_hz: float, zi):
    """gyrocore.effects.registry' ``lowpass`` term with its memory carried: (filtered (m, 3), final state).

    ``zi`` None = a power-up: the steady-state start of the core's term (lfilter_zi × first
    sample); the same lfilter calls per axis, so the pieces equal the whole bit for bit."""
    fc = float(pd["bandwidth_hz"])
    if not 0 < fc < rate_hz / 2:
        raise GyroInputError(f"lowpass bandwidth {fc} Hz must be in (0, {rate_hz / 2}) Hz at {rate_hz} Hz")
    b, a = signal.butter(2, fc, fs=rate_hz)
    if zi is None:
        z0 = signal.lfilter_zi(b, a)
        zi = [z0 * y[0, i] for i in range(3)]
    cols, zf = [], []
    for i in range(3):
        yi, zfi = signal.lfilter(b, a, y[:, i], zi=zi[i])
        cols.append(yi)
        zf.append(zfi)
    return np.stack(cols, axis=1), zf


class _ChunkedMeasure:
    """The engine of :meth:`SyntheticGyro.measure_chunks` (see there)."""

    def __init__(self, gyro: SyntheticGyro) -> None:
        self.g = gyro
        self.noise = gyro.noise_blocks()
        self.ctx = context_rows(gyro._model_params(np.zeros(3)), 1.0 / gyro.rate_hz)
        self.buf: dict[str, np.ndarray] | None = None
        self.b0 = 0  # global index of buffer row 0
        self.emit = 0  # next global row to emit
        self.seg_start = 0
        self.seg_index: int | None = None
        self.seen: list[int] = []
        self.biases: dict[int, np.ndarray] = {}
        self.params = None
        self.lp_zi = None
        for name in _CORE_OUTPUT_STAGE:
            if name in gyro.params and REGISTRY[name].stage == "filter" and name != "lowpass":
                raise GyroInputError(f"chunked measurement: the output-stage filter {name} has no carried state")

    def feed(self, truth: Truth):
        new = {k: np.asarray(getattr(truth, k)) for k in _TRUTH_FIELDS}
        if new["t_s"].shape[0] == 0:
            return
        if self.buf is None and self.emit == 0:
            self.g._check_truth_rate(new["t_s"])
        if self.buf is None:
            self.buf = {k: np.array(v, copy=True) for k, v in new.items()}
        else:
            self.buf = {k: np.concatenate([self.buf[k], new[k]]) for k in _TRUTH_FIELDS}
        yield from self._process(final=False)

    def finish(self):
        if self.buf is not None:
            yield from self._process(final=True)

    def _process(self, *, final: bool):
        buf, c = self.buf, self.ctx
        end = self.b0 + buf["t_s"].shape[0]
        pu = buf["power_up_index"]
        while self.emit < end:
            j = self.emit - self.b0
            idx = int(pu[j])
            change = np.flatnonzero(pu[j:] != pu[j])
            closed = change.size > 0 or final
            s1 = self.emit + int(change[0]) if change.size else end
            stop = s1 if closed else min(s1, end - c)
            if stop <= self.emit:
                break
            if self.seg_index != idx:  # a power-up begins at this row
                if idx in self.seen:
                    raise GyroInputError("truth.power_up_index must not return to an earlier power-up")
                self.seen.append(idx)
                self.seg_index, self.seg_start = idx, self.emit
                b = self.g.power_up_bias(idx)
                self.biases[idx] = b
                self.params = self.g._model_params(b)
                self.lp_zi = None
            lo = max(self.seg_start, self.emit - c)
            hi = s1 if closed else end
            hi = min(hi, stop + c)
            a0, a1 = lo - self.b0, hi - self.b0
            inp = ModelInputs(
                t_s=buf["t_s"][a0:a1].astype(float, copy=False),
                omega_S_rad_s=buf["omega_S_rad_s"][a0:a1].astype(float, copy=False),
                f_S_m_s2=buf["f_S_m_s2"][a0:a1].astype(float, copy=False),
                temp_c=buf["temp_c"][a0:a1].astype(float, copy=False),
                q_SW_wxyz=buf["q_SW_wxyz"][a0:a1].astype(float, copy=False),
                t_since_power_up_s=buf["t_since_power_up_s"][a0:a1].astype(float, copy=False),
            )
            x = deterministic(self.params, inp)[self.emit - lo : stop - lo]
            y = self._output(x, stop - self.emit)
            rows = {k: buf[k][j : j + (stop - self.emit)].copy() for k in _TRUTH_FIELDS}
            yield GyroChunk(
                start=self.emit,
                t_s=rows["t_s"].astype(float, copy=False),
                gyro_rad_s=y[0],
                noise_rad_s=y[1],
                power_up_bias_rad_s=dict(self.biases),
                truth=Truth(**rows),
            )
            self.emit = stop
        keep = max(self.b0, self.emit - c)  # rows an unfinished piece may still read
        if keep > self.b0:
            k = keep - self.b0
            self.buf = {kk: v[k:].copy() for kk, v in buf.items()}
            self.b0 = keep

    def _output(self, x: np.ndarray, m: int):
        """gyrocore.effects.registry.output_stage with the low-pass memory carried; returns (y, noise)."""
        p, rate = self.params, self.g.rate_hz
        y = np.asarray(x, float)
        for name in _CORE_OUTPUT_STAGE:
            if REGISTRY[name].stage == "filter" and name in p:
                y, self.lp_zi = _lowpass_chunk(p[name], y, rate, self.lp_zi)
        nz = self.noise.take(m)
        y = y + nz
        for name in _CORE_OUTPUT_STAGE:
            eff = REGISTRY[name]
            if eff.stage == "clip" and name in p:
                y = eff.term(p[name], y, rate)
        return y, nz
