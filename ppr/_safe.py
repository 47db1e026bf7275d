"""NaN-safe primitives (double-``where`` pattern) shared by every kernel.

Each helper replaces invalid inputs by a harmless value *before* the risky operation and masks
the result afterwards, so that neither the value nor the gradient of the masked branch can be
NaN/inf.  ``jnp.maximum(x, eps)`` alone is not enough: the gradient of the discarded branch
still flows through ``where`` as ``0 * nan = nan``.

Thresholds are dtype-aware (``tiny(dtype)`` rather than ``> 0``): XLA flushes subnormals at
run time but not when folding constants.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._types import Array, ArrayLike


def float_dtype(*xs: ArrayLike):
    """Result float dtype of the arguments (integers promote to the default float)."""
    dt = jnp.result_type(*xs)
    if not jnp.issubdtype(dt, jnp.inexact):
        dt = jnp.result_type(float)
    if jnp.issubdtype(dt, jnp.complexfloating):
        dt = jnp.finfo(dt).dtype
    return dt


def tiny(dtype) -> float:
    """Smallest *normal* positive number of ``dtype`` times a safety factor of 1e3."""
    return float(np.finfo(dtype).tiny) * 1e3


def eps(dtype) -> float:
    return float(np.finfo(dtype).eps)


def safe_sqrt(x: ArrayLike, threshold: float | None = None) -> Array:
    """sqrt(x) with value 0 and gradient 0 for x <= threshold (default: tiny(dtype))."""
    x = jnp.asarray(x)
    t = tiny(float_dtype(x)) if threshold is None else threshold
    ok = x > t
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def safe_div(num: ArrayLike, den: ArrayLike, fill: float = 0.0) -> Array:
    """num / den, ``fill`` (value and zero gradient) where |den| <= tiny(dtype)."""
    num, den = jnp.asarray(num), jnp.asarray(den)
    ok = jnp.abs(den) > tiny(float_dtype(num, den))
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), fill)


def safe_log(x: Array, fill: float = -jnp.inf) -> Array:
    ok = x > tiny(x.dtype)
    return jnp.where(ok, jnp.log(jnp.where(ok, x, 1.0)), fill)


def safe_norm(v: Array, axis: int = -1, keepdims: bool = False) -> Array:
    """Euclidean norm with a finite (zero) gradient at v = 0."""
    sq = jnp.sum(v * v, axis=axis, keepdims=keepdims)
    return safe_sqrt(sq)


def safe_normalize(v: Array, fallback: Array | None = None, axis: int = -1) -> tuple[Array, Array]:
    """Unit vector along ``v`` and a boolean "was valid" mask.

    Where |v| is (numerically) zero the result is ``fallback`` (default: +z) and the gradient
    through ``v`` is zero.
    """
    sq = jnp.sum(v * v, axis=axis, keepdims=True)
    ok = sq > tiny(v.dtype) * 1e3
    if fallback is None:
        fallback = jnp.zeros_like(v).at[..., 2].set(1.0)
    safe_v = jnp.where(ok, v, fallback)
    unit = safe_v / jnp.sqrt(jnp.sum(safe_v * safe_v, axis=axis, keepdims=True))
    return jnp.where(ok, unit, fallback), ok[..., 0]


def safe_pow(base: Array, expo: Array) -> Array:
    """base**expo for base >= 0 computed in log space; 0**0 = 1, 0**m = 0 for m > 0.

    Negative bases are treated as 0 (callers mask below-horizon rows first).
    """
    ok = base > tiny(base.dtype)
    lb = jnp.log(jnp.where(ok, base, 1.0))
    val = jnp.exp(expo * lb)
    zero_val = jnp.where(expo > 0, 0.0, 1.0)
    return jnp.where(ok, val, zero_val)


def safe_atan2(y: Array, x: Array) -> Array:
    """``atan2(y, x)`` whose derivative stays finite when both arguments are tiny.

    The derivative ``(x dy - y dx) / (x^2 + y^2)`` is formed with ``x^2 + y^2``, which
    underflows to 0 in float32 once both are below ~1e-19 (an infinite, then NaN gradient).
    ``atan2`` is invariant under a common positive scale, so both are divided first by
    ``max(|x|, |y|)`` held constant for differentiation; 0 (zero gradient) at ``x = y = 0``.
    """
    x, y = jnp.asarray(x), jnp.asarray(y)
    big = jnp.maximum(jnp.abs(x), jnp.abs(y))
    ok = big > tiny(float_dtype(x, y))
    scale = jax.lax.stop_gradient(jnp.where(ok, big, 1.0))
    return jnp.where(ok, jnp.arctan2(y / scale, x / scale), 0.0)


def safe_atan2_angle(cos_a: Array, sin_a: Array) -> Array:
    """Angle from its cosine and (non-negative) sine: prefer atan2 to arccos."""
    return jnp.arctan2(sin_a, cos_a)


def safe_sin_from_cos(c: Array) -> Array:
    """sqrt(1 - c^2) with a finite gradient at |c| = 1."""
    return safe_sqrt((1.0 - c) * (1.0 + c))
