r"""Measurement model of a PPR receiver: PSG/PSA channels, photon counting and nuisances.

Channels
    A polarization state generator (PSG) transmits a fully polarized state ``s_g`` (Stokes,
    ``S0 = 1``) and an ideal polarization state analyzer (PSA) passes the state ``u_a`` (unit
    Stokes direction), so the detected intensity of the channel ``(g, a)`` in range bin ``b`` is

        I_ga(b) = 1/2 (1, u_a) . M(b) . s_g

    for the range-resolved Mueller profile ``M(b)`` of the target (sensor frames, see
    :mod:`ppr._conventions`). State names: ``H V D A R L`` (horizontal, vertical, +45, -45,
    right and left circular in Chipman's convention, ``S3 > 0`` is R). Channels are ordered
    generator-major. ``MeasurementModel.preset("full")`` uses ``{H, V, D, R}`` for both PSG and
    PSA: 16 channels that determine the full Mueller matrix (the 16 x 16 system is invertible).

Noise (``NoiseModel``)
    From a noise-free channel profile ``x`` (any units, ``x >= 0``) an observation is drawn as

    1. unknown range offset: a common shift of ``offset`` bins, uniform in
       ``[-max_offset_bins, max_offset_bins]``, applied by exact flux-conserving rebinning of the
       piecewise-constant profile (integer shifts are exact index shifts);
    2. timing jitter: each channel is recorded in its own acquisition, shifted by a further
       independent ``N(0, jitter_bins^2)`` bins (trigger jitter between channels; per-photon
       jitter blurs the expected pulse and belongs to the simulator's pulse shape);
    3. photon counting at a signal-to-noise ratio ``snr``: **definition** -- the expected total
       number of *signal* photo-counts summed over all channels and bins is ``N = snr**2``
       (``snr`` is the SNR of the total-energy measurement under pure Poisson noise). The
       expected counts are ``lam = N x / sum(x)`` plus ``background`` counts per bin;
    4. speckle: the expected signal counts in each (channel, bin) are multiplied by an
       independent ``Gamma(M, 1/M)`` variable, ``M = speckle_cells`` (mean 1, contrast
       ``std/mean = 1/sqrt(M)``); counts are then Poisson (so their variance is
       ``lam + lam^2/M``, negative binomial);
    5. overall gain: the counts are multiplied by an unknown gain, log-uniform in
       ``[gain_min, gain_max]`` (detector conversion / calibration; atmospheric extinction is
       folded into ``snr``).

    ``snr = inf`` switches photon noise off (then the output is ``gain * N``-free, i.e.
    ``gain * x`` shifted), ``speckle_cells = inf`` switches speckle off. Every observation is a
    pure function of its integer seed (``jax.random.key(seed)``).
"""

from __future__ import annotations

import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ppr._types import Array, ArrayLike, Float

STATES: dict[str, tuple[float, float, float, float]] = {
    "H": (1.0, 1.0, 0.0, 0.0),
    "V": (1.0, -1.0, 0.0, 0.0),
    "D": (1.0, 0.0, 1.0, 0.0),
    "A": (1.0, 0.0, -1.0, 0.0),
    "R": (1.0, 0.0, 0.0, 1.0),
    "L": (1.0, 0.0, 0.0, -1.0),
}

PRESETS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "full": (("H", "V", "D", "R"), ("H", "V", "D", "R")),
    "stokes": (("H", "R"), ("H", "V", "D", "R")),
    "copol": (("H",), ("H", "V")),
    "circular": (("R",), ("R", "L")),
}


class MeasurementModel(eqx.Module):
    """Which states are transmitted (PSG) and analyzed (PSA); channel ``k = g * n_psa + a``.

    **Arguments:**

    - `generators`: names of transmitted states (keys of ``STATES``).
    - `analyzers`: names of analyzer states.
    """

    generators: tuple[str, ...] = eqx.field(static=True)
    analyzers: tuple[str, ...] = eqx.field(static=True)

    def __check_init__(self):
        for field in ("generators", "analyzers"):
            names = getattr(self, field)
            if len(names) == 0:
                raise ValueError(f"MeasurementModel.{field} must not be empty")
            bad = [s for s in names if s not in STATES]
            if bad:
                raise ValueError(
                    f"MeasurementModel.{field} has unknown states {bad}; known: {sorted(STATES)}"
                )

    @classmethod
    def preset(cls, name: str) -> MeasurementModel:
        """``"full"`` (16 channels), ``"stokes"`` (8), ``"copol"`` (2), ``"circular"`` (2)."""
        if name not in PRESETS:
            raise ValueError(f"unknown measurement preset {name!r}; known: {sorted(PRESETS)}")
        g, a = PRESETS[name]
        return cls(g, a)

    @property
    def n_channels(self) -> int:
        return len(self.generators) * len(self.analyzers)

    @property
    def channel_names(self) -> tuple[str, ...]:
        return tuple(f"{g}>{a}" for g in self.generators for a in self.analyzers)

    def channel_matrix(self, dtype=np.float64) -> np.ndarray:
        """(n_channels, 4, 4) array ``P`` with ``I_k = sum_ij P[k, i, j] M[i, j]``."""
        rows = []
        for g in self.generators:
            s = np.asarray(STATES[g])
            for a in self.analyzers:
                u = np.asarray(STATES[a])
                rows.append(0.5 * np.outer(u, s))
        return np.stack(rows).astype(dtype)

    def fingerprint(self) -> dict:
        return {"generators": list(self.generators), "analyzers": list(self.analyzers)}


def measure(
    model: MeasurementModel, mueller: Float[Array, "*batch 4 4 bins"]
) -> Float[Array, "*batch channels bins"]:
    """Noise-free channel profiles from range-resolved Mueller profiles (..., 4, 4, n_bins)."""
    mueller = jnp.asarray(mueller)
    p = jnp.asarray(model.channel_matrix(), dtype=mueller.dtype)
    return jnp.einsum("kij,...ijb->...kb", p, mueller)


def measure_stokes(
    model: MeasurementModel, stokes: Float[Array, "*batch gen 4 bins"]
) -> Float[Array, "*batch channels bins"]:
    """Channel profiles from Stokes profiles of the returns for each transmitted state.

    ``stokes[..., g, :, b]`` is the returned Stokes vector (sensor frame) for the model's
    ``g``-th generator state; the analyzer takes ``1/2 (1, u_a) . S``.
    """
    stokes = jnp.asarray(stokes)
    if stokes.shape[-3] != len(model.generators):
        raise ValueError(
            f"stokes has {stokes.shape[-3]} transmitted states on axis -3, the measurement model "
            f"has {len(model.generators)} generators {model.generators}"
        )
    u = 0.5 * jnp.asarray([STATES[a] for a in model.analyzers], dtype=stokes.dtype)
    out = jnp.einsum("ai,...gib->...gab", u, stokes)
    return out.reshape(*out.shape[:-3], model.n_channels, out.shape[-1])


class NoiseModel(eqx.Module):
    """Noise and nuisance settings of one observation (see the module docstring).

    **Arguments:**

    - `snr`: ``sqrt`` of the expected total signal photo-counts over all channels and bins
      (``inf``: no photon noise).
    - `speckle_cells`: speckle cells per (channel, bin) ``M``; contrast ``1/sqrt(M)``
      (``inf``: no speckle).
    - `jitter_bins`: rms per-channel timing jitter in bins.
    - `max_offset_bins`: unknown common range offset, uniform in ``[-max, max]`` bins.
    - `gain_min`, `gain_max`: overall gain, log-uniform in ``[gain_min, gain_max]``.
    - `background`: expected background counts per (channel, bin).
    """

    snr: float = math.inf
    speckle_cells: float = math.inf
    jitter_bins: float = 0.0
    max_offset_bins: float = 0.0
    gain_min: float = 1.0
    gain_max: float = 1.0
    background: float = 0.0

    def __check_init__(self):
        if not self.snr > 0:
            raise ValueError(f"NoiseModel.snr must be > 0 (or inf), got {self.snr!r}")
        if not self.speckle_cells >= 1:
            raise ValueError(
                f"NoiseModel.speckle_cells must be >= 1 (or inf), got {self.speckle_cells!r}"
            )
        for f in ("jitter_bins", "max_offset_bins", "background"):
            v = getattr(self, f)
            if not (v >= 0 and math.isfinite(v)):
                raise ValueError(f"NoiseModel.{f} must be finite and >= 0, got {v!r}")
        if not (0 < self.gain_min <= self.gain_max < math.inf):
            raise ValueError(
                f"NoiseModel gain range must satisfy 0 < gain_min <= gain_max < inf, "
                f"got ({self.gain_min!r}, {self.gain_max!r})"
            )


def shift_profile(
    x: Float[ArrayLike, "*batch bins"], shift: ArrayLike
) -> Float[Array, "*batch bins"]:
    """Shift a piecewise-constant profile later by ``shift`` bins (flux-conserving rebinning).

    Bin ``b`` of the result collects ``F(b + 1 - shift) - F(b - shift)`` with ``F`` the
    piecewise-linear cumulative of ``x``; flux leaving the window is lost, zeros enter. Integer
    shifts are exact index shifts. ``shift`` broadcasts against ``x.shape[:-1]``.
    """
    x = jnp.asarray(x)
    n = x.shape[-1]
    shift = jnp.broadcast_to(jnp.asarray(shift, dtype=x.dtype), x.shape[:-1])[..., None]
    whole = jnp.floor(shift)
    frac = shift - whole  # in [0, 1): bin b gets (1 - frac) x(b - whole) + frac x(b - whole - 1)
    idx = jnp.arange(n) - whole.astype(jnp.int32)

    def take(i):
        ok = (i >= 0) & (i < n)
        return jnp.where(ok, jnp.take_along_axis(x, jnp.clip(i, 0, n - 1), axis=-1), 0.0)

    a = take(idx)
    return jnp.where(frac > 0, (1 - frac) * a + frac * take(idx - 1), a)


class Observation(eqx.Module):
    """A simulated (or measured) observation: channel profiles plus what produced them.

    `data` is (n_channels, n_bins); `sensor` the canonical JSON fingerprint of the sensor
    settings (must match the database's); `seed` the integer the noise was drawn from; `truth`
    holds the drawn nuisances (gain, offset_bins, channel_offsets_bins) for evaluation.
    """

    data: ArrayLike = eqx.field(converter=jnp.asarray)
    sensor: str = eqx.field(static=True)
    seed: int = eqx.field(static=True, default=-1)
    truth: dict = eqx.field(default_factory=dict)


@jax.jit
def _draw(key, x, p):
    """One observation; ``p`` holds the noise settings as traced scalars (one compilation
    per input shape and dtype: switched-off effects are computed and discarded)."""
    dtype = x.dtype
    k_off, k_jit, k_gain, k_spk, k_poi = jax.random.split(key, 5)
    n_ch = x.shape[0]
    offset = jax.random.uniform(k_off, (), dtype, -1.0, 1.0) * p["max_offset_bins"]
    ch_off = p["jitter_bins"] * jax.random.normal(k_jit, (n_ch,), dtype)
    gain = jnp.exp(jax.random.uniform(k_gain, (), dtype, p["log_gain_min"], p["log_gain_max"]))
    y = shift_profile(x, offset + ch_off)
    m = jnp.where(p["speckle"], p["speckle_cells"], 1.0)
    speckle = jnp.where(p["speckle"], jax.random.gamma(k_spk, m, y.shape, dtype) / m, 1.0)
    lam = jnp.where(p["poisson"], p["n_signal"] * y / jnp.sum(x), y) * speckle
    lam = lam + jnp.where(p["poisson"], p["background"], 0.0)
    counts = jax.random.poisson(k_poi, jnp.where(p["poisson"], lam, 0.0), y.shape).astype(dtype)
    y = jnp.where(p["poisson"], counts, lam)
    return gain * y, {"gain": gain, "offset_bins": offset, "channel_offsets_bins": ch_off}


def _noise_params(noise: NoiseModel, dtype) -> dict:
    poisson = math.isfinite(noise.snr)
    speckle = math.isfinite(noise.speckle_cells)
    vals = {
        "poisson": poisson,
        "speckle": speckle,
        "n_signal": noise.snr**2 if poisson else 1.0,
        "speckle_cells": noise.speckle_cells if speckle else 1.0,
        "background": noise.background,
        "jitter_bins": noise.jitter_bins,
        "max_offset_bins": noise.max_offset_bins,
        "log_gain_min": math.log(noise.gain_min),
        "log_gain_max": math.log(noise.gain_max),
    }
    return {
        k: jnp.asarray(v) if isinstance(v, bool) else jnp.asarray(v, dtype) for k, v in vals.items()
    }


def observe(
    expected: ArrayLike,
    noise: NoiseModel,
    seed: int,
    sensor: str | dict = "",
) -> Observation:
    """Draw one noisy observation from noise-free channel profiles ``expected`` (C, B).

    Reproducible: the same ``seed`` gives the same observation. ``sensor`` is the sensor
    fingerprint (dict or canonical JSON) of the model that produced ``expected``.
    """
    x = jnp.asarray(expected)
    if x.ndim != 2:
        raise ValueError(f"expected must be (n_channels, n_bins), got shape {x.shape}")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    xn = np.asarray(x)
    if not np.all(np.isfinite(xn)) or np.any(xn < 0) or not np.sum(xn) > 0:
        raise ValueError("expected must be finite, non-negative and not all zero")
    if not isinstance(seed, int | np.integer):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    data, truth = _draw(jax.random.key(int(seed)), x, _noise_params(noise, x.dtype))
    return Observation(data=data, sensor=canonical_sensor(sensor), seed=int(seed), truth=truth)


def canonical_sensor(sensor: str | dict) -> str:
    """Canonical JSON string of a sensor-settings dict (sorted keys, floats as repr)."""
    if isinstance(sensor, str):
        if sensor == "":
            return ""
        sensor = json.loads(sensor)
    return json.dumps(sensor, sort_keys=True, separators=(",", ":"))
