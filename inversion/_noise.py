r"""Measurement model of a PPR receiver: PSG/PSA channels, photon counting and nuisances.

Channels
    A polarization state generator (PSG) transmits a fully polarized state ``s_g`` (Stokes,
    ``S0 = 1``) and an ideal polarization state analyzer (PSA) passes the state ``u_a`` (unit
    Stokes direction), so the detected intensity of the channel ``(g, a)`` in range bin ``b`` is

        I_ga(b) = 1/2 (1, u_a) . M(b) . s_g

    for the range-resolved Mueller profile ``M(b)`` of the target (sensor frames, see
    :mod:`ppr.optics.conventions`). State names: ``H V D A R L`` (horizontal, vertical, +45, -45,
    right and left circular), the names of ``ppr.pulse.STOKES_STATES``: ``R`` turns clockwise
    for an observer looking toward the source (Chipman's, Born & Wolf's and Hecht's
    right-circular), ppr's ``S3 = -1``; ``L`` is ``S3 = +1``. Channels are ordered
    generator-major. ``MeasurementModel.preset("full")`` uses ``{H, V, D, L}`` for both PSG and
    PSA: 16 channels that determine the full Mueller matrix (the 16 x 16 system is invertible).
    The presets' circular state is ``L`` (``S3 = +1``).

Noise (``NoiseModel``)
    From a noise-free channel profile ``x`` (any units, ``x >= 0`` up to rounding, see
    :data:`ROUNDING_ULPS`) an observation is drawn as

    1. unknown range offset: a common shift of ``offset`` bins, uniform in
       ``[-max_offset_bins, max_offset_bins]``, applied by exact flux-conserving rebinning of the
       piecewise-constant profile (integer shifts are exact index shifts). A fractional shift
       of the *binned* profile is not the binned profile of the shifted return: it smooths by
       up to a bin. A model that shifts the return before binning (``SimulatorModel``'s
       ``range_offset``) then fits a biased attitude at high SNR; for such studies put the
       offset into the simulation and leave ``max_offset_bins = 0``;
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
from jaxtyping import Array, ArrayLike, Float

STATES: dict[str, tuple[float, float, float, float]] = {
    "H": (1.0, 1.0, 0.0, 0.0),
    "V": (1.0, -1.0, 0.0, 0.0),
    "D": (1.0, 0.0, 1.0, 0.0),
    "A": (1.0, 0.0, -1.0, 0.0),
    "R": (1.0, 0.0, 0.0, -1.0),
    "L": (1.0, 0.0, 0.0, 1.0),
}

PRESETS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "full": (("H", "V", "D", "L"), ("H", "V", "D", "L")),
    "stokes": (("H", "L"), ("H", "V", "D", "L")),
    "copol": (("H",), ("H", "V")),
    "circular": (("L",), ("L", "R")),
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
        """``"full"`` (16 channels: H, V, D, L transmitted and analyzed), ``"stokes"`` (8: H, L
        transmitted; H, V, D, L analyzed), ``"copol"`` (2: H; H, V), ``"circular"`` (2: L;
        L, R). Names: :data:`STATES`."""
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
) -> Float[ArrayLike, "*batch bins"]:
    """Shift a piecewise-constant profile later by ``shift`` bins (flux-conserving rebinning).

    Bin ``b`` of the result collects ``F(b + 1 - shift) - F(b - shift)`` with ``F`` the
    piecewise-linear cumulative of ``x``; flux leaving the window is lost, zeros enter. Integer
    shifts are exact index shifts. ``shift`` broadcasts against ``x.shape[:-1]``. NumPy
    inputs give a NumPy result (host-side fits call it thousands of times); any JAX input
    (or a tracer) a JAX one.
    """
    xp = jnp if any(isinstance(a, jax.Array) for a in (x, shift)) else np
    return _shift_profile(x, shift, xp)


def _shift_profile(x, shift, xp):
    """:func:`shift_profile` with the array namespace given (unannotated: host-side fits call
    it in loops, where a runtime type check would cost more than the shift)."""
    x = xp.asarray(x)
    if not xp.issubdtype(x.dtype, xp.floating):
        x = x.astype(jnp.result_type(float))
    n = x.shape[-1]
    shift = xp.broadcast_to(xp.asarray(shift, dtype=x.dtype), x.shape[:-1])[..., None]
    whole = xp.floor(shift)
    frac = shift - whole  # in [0, 1): bin b gets (1 - frac) x(b - whole) + frac x(b - whole - 1)
    idx = xp.arange(n) - whole.astype(xp.int32)
    a = _take(x, idx, xp)
    return xp.where(frac > 0, (1 - frac) * a + frac * _take(x, idx - 1, xp), a)


def _take(x, i, xp):
    """``x[..., i]`` with zeros outside ``[0, n)`` (module level: no closure per call)."""
    n = x.shape[-1]
    ok = (i >= 0) & (i < n)
    return xp.where(ok, xp.take_along_axis(x, xp.clip(i, 0, n - 1), axis=-1), 0.0)


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


# Samplers with a fixed number of vectorized proposals (no while loops): they compile in about
# a second where jax.random.gamma / poisson take 7 s each on this machine. The probability
# that every proposal of an element is rejected is below 1e-10 (stated per sampler); such an
# element falls back to the mean-matched value (a bias far below any statistical test here).
_GAMMA_TRIES = 8  # Marsaglia-Tsang acceptance >= 0.95 for shape >= 1: 0.05^8 < 4e-11
_POISSON_TRIES = 16  # PTRS acceptance > 0.85 for lam >= 10: 0.15^16 < 7e-14
_POISSON_SMALL = 10.0  # below: inversion over _POISSON_TERMS terms (P(X >= 48 | lam < 10) < 1e-15)
_POISSON_TERMS = 48


def _normal(u1, u2):
    """Standard normals from two uniforms on (0, 1] (Box-Muller)."""
    return jnp.sqrt(-2.0 * jnp.log(u1)) * jnp.cos(2.0 * jnp.pi * u2)


def _gamma(a, u):
    """Gamma(a, 1) samples (Marsaglia and Tsang 2000; a < 1 via Gamma(a + 1) U^(1/a)).

    ``u``: (3 _GAMMA_TRIES + 1, *a.shape) uniforms on (0, 1]."""
    t = _GAMMA_TRIES
    boost = a < 1
    a1 = jnp.where(boost, a + 1, a)
    d = a1 - 1.0 / 3.0
    c = 1.0 / jnp.sqrt(9.0 * d)
    x = _normal(u[:t], u[t : 2 * t])
    v = (1 + c * x) ** 3
    pos = v > 0
    logv = jnp.log(jnp.where(pos, v, 1.0))
    accept = pos & (jnp.log(u[2 * t : 3 * t]) < 0.5 * x * x + d - d * v + d * logv)
    first = jnp.argmax(accept, axis=0)
    val = jnp.take_along_axis(d * v, first[None], axis=0)[0]
    val = jnp.where(jnp.any(accept, axis=0), val, d)
    return jnp.where(boost, val * jnp.exp(jnp.log(u[3 * t]) / jnp.where(boost, a, 1.0)), val)


def _poisson(lam, u):
    """Poisson(lam) counts: inversion for lam < 10, PTRS (Hormann 1993) above.

    ``u``: (2 _POISSON_TRIES + 1, *lam.shape) uniforms on (0, 1]."""
    dtype = lam.dtype
    t = _POISSON_TRIES
    shape = lam.shape
    # small lam: count CDF steps below a uniform
    ls = jnp.minimum(lam, _POISSON_SMALL)
    kk = jnp.arange(_POISSON_TERMS, dtype=dtype).reshape((-1,) + (1,) * len(shape))
    logls = jnp.log(jnp.maximum(ls, jnp.finfo(dtype).tiny))
    cdf = jnp.cumsum(jnp.exp(-ls + kk * logls - jax.scipy.special.gammaln(kk + 1)), axis=0)
    small = jnp.sum(u[2 * t][None] > cdf, axis=0).astype(dtype)
    small = jnp.where(ls > 0, small, 0.0)
    # large lam: transformed rejection with squeeze
    lb = jnp.maximum(lam, _POISSON_SMALL)
    slam = jnp.sqrt(lb)
    loglam = jnp.log(lb)
    b = 0.931 + 2.53 * slam
    a = -0.059 + 0.02483 * b
    inv_alpha = 1.1239 + 1.1328 / (b - 3.4)
    vr = 0.9277 - 3.6224 / (b - 2)
    uu = u[:t] - 0.5
    v = u[t : 2 * t]
    ush = 0.5 - jnp.abs(uu)
    kf = jnp.floor((2 * a / ush + b) * uu + lb + 0.43)
    quick = (ush >= 0.07) & (v <= vr)
    bad = (kf < 0) | ((ush < 0.013) & (v > ush))
    lhs = jnp.log(v) + jnp.log(inv_alpha) - jnp.log(a / (ush * ush) + b)
    rhs = -lb + kf * loglam - jax.scipy.special.gammaln(jnp.maximum(kf, 0.0) + 1)
    accept = quick | (~bad & (lhs <= rhs))
    first = jnp.argmax(accept, axis=0)
    large = jnp.take_along_axis(kf, first[None], axis=0)[0]
    large = jnp.where(jnp.any(accept, axis=0), large, jnp.round(lb))
    return jnp.where(lam < _POISSON_SMALL, small, large)


@jax.jit
def _draw(key, x, p):
    """One observation; ``p`` holds the noise settings as traced scalars (one compilation
    per input shape and dtype: switched-off effects are computed and discarded). All
    randomness comes from one ``jax.random.uniform`` call (one PRNG kernel to compile)."""
    dtype = x.dtype
    n_ch = x.shape[0]
    n_g, n_p = 3 * _GAMMA_TRIES + 1, 2 * _POISSON_TRIES + 1
    total = 2 + 2 * n_ch + (n_g + n_p) * x.size
    u = jax.random.uniform(key, (total,), dtype, minval=jnp.finfo(dtype).tiny, maxval=1.0)
    u = jnp.minimum(u, 1.0)
    offset = (2 * u[0] - 1) * p["max_offset_bins"]
    gain = jnp.exp(p["log_gain_min"] + u[1] * (p["log_gain_max"] - p["log_gain_min"]))
    ch_off = p["jitter_bins"] * _normal(u[2 : 2 + n_ch], u[2 + n_ch : 2 + 2 * n_ch])
    rest = u[2 + 2 * n_ch :]
    u_g = rest[: n_g * x.size].reshape(n_g, *x.shape)
    u_p = rest[n_g * x.size :].reshape(n_p, *x.shape)
    y = shift_profile(x, offset + ch_off)
    m = jnp.where(p["speckle"], p["speckle_cells"], 1.0)
    speckle = jnp.where(
        p["speckle"], _gamma(jnp.broadcast_to(m, y.shape).astype(dtype), u_g) / m, 1.0
    )
    lam = jnp.where(p["poisson"], p["n_signal"] * y / jnp.sum(x), y) * speckle
    lam = lam + jnp.where(p["poisson"], p["background"], 0.0)
    counts = _poisson(jnp.where(p["poisson"], lam, 0.0), u_p)
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


ROUNDING_ULPS: float = 16.0
"""Negative values of an expected channel profile down to ``-ROUNDING_ULPS * eps * peak``
(``eps`` of float32, ``peak`` the profile's largest value) are rounding, not signal: a
channel is the sum ``1/2 (1, u_a) . M . s_g`` of 16 products, and where the return is fully
polarized across the analyzer (a crossed channel) the exact value 0 comes out as +-(a
fraction of ``eps * peak``) depending on how the compiler orders and contracts the sum
(measured: down to -0.2 ``eps * peak``). float32's ``eps`` whatever the profile's dtype: a
profile computed in float32 (ppr's fast path) and handed over in float64 keeps float32's
rounding. :func:`observe` takes them as 0; anything more negative is an error."""


def _checked_intensities(x: Array) -> Array:
    """``x`` (C, B) with rounding-level negatives set to 0 (:data:`ROUNDING_ULPS`); a clear
    error for non-finite values, real negatives or an all-zero profile."""
    xn = np.asarray(x)
    bad = ~np.isfinite(xn)
    if bad.any():
        c, b = np.argwhere(bad)[0]
        raise ValueError(
            f"expected has {int(bad.sum())} non-finite values (first {xn[c, b]} at channel "
            f"{c}, bin {b}): channel profiles must be finite"
        )
    peak = float(xn.max()) if xn.size else 0.0
    if not peak > 0:
        raise ValueError(
            f"expected has no positive value (largest {peak:.6g}): nothing to observe"
        )
    floor = -ROUNDING_ULPS * float(np.finfo(np.float32).eps) * peak
    if np.any(xn < floor):
        c, b = np.unravel_index(np.argmin(xn), xn.shape)
        raise ValueError(
            f"expected has negative values down to {xn[c, b]:.6g} at channel {c}, bin {b} "
            f"(peak {peak:.6g}): channel profiles are intensities, >= 0 up to rounding "
            f"({floor:.3g})"
        )
    return jnp.maximum(x, 0.0)


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
    x = _checked_intensities(x)
    if not isinstance(noise, NoiseModel):
        raise TypeError(
            f"observe: noise must be an inversion.NoiseModel (the observation's noise "
            f"recipe: snr, speckle, jitter, offset, gain), got {type(noise).__name__}; "
            "PoissonCounts and the other likelihoods are what a fit assumes, not a recipe"
        )
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    if not 0 <= int(seed) < 2**63:
        raise ValueError(f"seed must be in [0, 2^63), got {seed!r}")
    data, truth = _draw(jax.random.key(int(seed)), x, _noise_params(noise, x.dtype))
    return Observation(data=data, sensor=canonical_sensor(sensor), seed=int(seed), truth=truth)


def canonical_sensor(sensor: str | dict) -> str:
    """Canonical JSON string of a sensor-settings dict (sorted keys, floats as repr)."""
    if isinstance(sensor, str):
        if sensor == "":
            return ""
        sensor = json.loads(sensor)
    return json.dumps(sensor, sort_keys=True, separators=(",", ":"))
