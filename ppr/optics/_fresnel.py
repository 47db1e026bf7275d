r"""Complex Fresnel reflection coefficients, in real arithmetic with NaN-safe gradients.

Conventions (see :mod:`ppr.optics.conventions`): time dependence ``exp(i(kz - wt))``, absorbing
media have ``Im n >= 0``, Hecht/Born-Wolf form

    r_s = (cos t - w) / (cos t + w),   r_p = (n^2 cos t - w) / (n^2 cos t + w),
    w = sqrt(n^2 - sin^2 t)   (principal branch, Im w >= 0 for Im n >= 0),

in the s/p frames of :mod:`ppr.optics.conventions` (``p = d x s`` for each beam), so that a perfect
conductor is ``diag(-1, +1)`` and normal incidence gives ``r_s = -r_p = -(n-1)/(n+1)``.

The Mueller matrix of the Jones matrix ``diag(r_s, r_p)`` is

    M = [[a, b, 0, 0], [b, a, 0, 0], [0, 0, c, d], [0, 0, -d, c]]
    a = (|r_s|^2 + |r_p|^2)/2,  b = (|r_s|^2 - |r_p|^2)/2,
    c = Re(r_s r_p^*),          d = +Im(r_s r_p^*)

(the sign of ``d`` follows from ``M = A (J (x) J^*) A^{-1}`` with S3 = -2 Im(E_x E_y^*); it is
pinned by a test against :func:`ppr.optics._frames.jones_to_mueller`).

Everything is written with explicit real and imaginary parts (2-3x faster than complex dtypes
on XLA CPU, docs/DESIGN.md). The complex square root uses the cancellation-free form
``t = sqrt((|Re z| + |z|)/2)`` (:func:`complex_sqrt_re`), guarded by double ``where`` at
``z = 0`` (``n = 1`` at grazing, or a real ``n < 1`` at its critical angle), so values and
gradients are finite for all ``0 <= cos t <= 1``, real or complex ``n``.

The public entry points (:func:`fresnel_amplitudes`, :func:`fresnel_mueller_params`) are
``jax.jit``-wrapped: an eager call runs one compiled program per input shape and dtype instead
of dispatching each operation; under a caller's ``jit`` they are inlined.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._safe import float_dtype, tiny
from .._types import Array, ArrayLike, Complex, Float

__all__ = [
    "complex_sqrt_re",
    "fresnel_amplitudes",
    "fresnel_amplitudes_re",
    "fresnel_mueller_params",
]


def complex_sqrt_re(re: Array, im: Array) -> tuple[Array, Array]:
    """Principal square root of ``re + i im`` as ``(u, v)``, NaN-safe value and gradient.

    Uses ``t = sqrt((|re| + |z|)/2)``; for ``re >= 0``: ``u = t, v = im/(2t)``; for ``re < 0``:
    ``v = sign(im) t, u = |im|/(2t)`` (no cancellation). At ``z = 0`` returns 0 with a zero
    gradient (the true derivative is infinite there). ``sign(0)`` is taken as ``+1`` so a
    negative real argument gives ``+i sqrt(|re|)`` (principal branch, Im >= 0).
    """
    dt = re.dtype
    sq = re * re + im * im
    ok = sq > tiny(dt) * 1e6
    re_s = jnp.where(ok, re, 1.0)
    im_s = jnp.where(ok, im, 0.0)
    mod = jnp.sqrt(re_s * re_s + im_s * im_s)
    t = jnp.sqrt(0.5 * (jnp.abs(re_s) + mod))
    half_over_t = 0.5 / t
    sgn = jnp.where(im_s >= 0, 1.0, -1.0).astype(dt)
    pos = re_s >= 0
    u = jnp.where(pos, t, jnp.abs(im_s) * half_over_t)
    v = jnp.where(pos, im_s * half_over_t, sgn * t)
    zero = jnp.zeros((), dt)
    return jnp.where(ok, u, zero), jnp.where(ok, v, zero)


def _cdiv(a: Array, b: Array, c: Array, d: Array) -> tuple[Array, Array]:
    """(a + ib) / (c + id) with value 0 and zero gradient where |c + id| is ~0.

    All four are divided first by ``max(|c|, |d|)``, held constant for differentiation (the
    quotient does not depend on it): the derivative of a quotient is formed with its
    denominator squared, and ``|c + id|^4`` underflowed in float32 (an infinite, then NaN
    gradient) for a facet seen at grazing incidence with ``n = 1`` (``c + id ~ 1e-20``).
    """
    big = jnp.maximum(jnp.abs(c), jnp.abs(d))
    ok = big > tiny(big.dtype) * 1e3
    scale = jax.lax.stop_gradient(jnp.where(ok, big, 1.0))
    a, b, c, d = a / scale, b / scale, c / scale, d / scale
    den = c * c + d * d  # in [1, 2] where ok
    den_s = jnp.where(ok, den, 1.0)
    re = (a * c + b * d) / den_s
    im = (b * c - a * d) / den_s
    return jnp.where(ok, re, 0.0), jnp.where(ok, im, 0.0)


def _broadcast_real(n_re: ArrayLike, n_im: ArrayLike, cos_t: ArrayLike):
    dt = float_dtype(n_re, n_im, cos_t)
    n_re = jnp.asarray(n_re, dt)
    n_im = jnp.asarray(n_im, dt)
    cos_t = jnp.asarray(cos_t, dt)
    return jnp.broadcast_arrays(n_re, n_im, cos_t)


def fresnel_amplitudes_re(
    n_re: Float[ArrayLike, "..."], n_im: Float[ArrayLike, "..."], cos_t: Float[ArrayLike, "..."]
) -> tuple[Float[Array, "..."], Float[Array, "..."], Float[Array, "..."], Float[Array, "..."]]:
    """Fresnel amplitudes as real arrays ``(rs_re, rs_im, rp_re, rp_im)``.

    **Arguments:**

    - `n_re`, `n_im`: real and imaginary part of the complex index (``n_im >= 0``).
    - `cos_t`: cosine of the angle of incidence on the facet, in ``[0, 1]`` (not clipped here).

    Broadcasts its arguments; dtype is the common float dtype.
    """
    n_re, n_im, cos_t = _broadcast_real(n_re, n_im, cos_t)
    # n^2 = (n_re^2 - n_im^2) + 2i n_re n_im ; w^2 = n^2 - sin^2 = n^2 - 1 + cos^2
    n2_re = n_re * n_re - n_im * n_im
    n2_im = 2.0 * n_re * n_im
    # (n_re - 1)(n_re + 1) keeps w^2 = cos^2 exact for n = 1 (no reflection at any angle)
    w2_re = (n_re - 1.0) * (n_re + 1.0) - n_im * n_im + cos_t * cos_t
    w2_im = n2_im
    w_re, w_im = complex_sqrt_re(w2_re, w2_im)
    rs_re, rs_im = _cdiv(cos_t - w_re, -w_im, cos_t + w_re, w_im)
    a_re, a_im = n2_re * cos_t, n2_im * cos_t
    rp_re, rp_im = _cdiv(a_re - w_re, a_im - w_im, a_re + w_re, a_im + w_im)
    return rs_re, rs_im, rp_re, rp_im


@jax.jit
def fresnel_amplitudes(
    n: Complex[ArrayLike, "..."] | Float[ArrayLike, "..."], cos_t: Float[ArrayLike, "..."]
) -> tuple[Complex[Array, "..."], Complex[Array, "..."]]:
    """Complex Fresnel reflection amplitudes ``(r_s, r_p)`` (Hecht form, principal branch).

    **Arguments:**

    - `n`: complex refractive index ``n' + i n''`` with ``n'' >= 0`` (real input allowed).
    - `cos_t`: cosine of the angle of incidence, ``0 <= cos_t <= 1``.

    **Returns:** ``(r_s, r_p)`` complex, broadcast shape. ``n = 1`` gives 0; grazing
    incidence (``cos_t = 0``) gives ``r_s = r_p = -1`` for ``n != 1``.
    """
    n = jnp.asarray(n)
    n_re, n_im = jnp.real(n), jnp.imag(n)
    rs_re, rs_im, rp_re, rp_im = fresnel_amplitudes_re(n_re, n_im, cos_t)
    return jax_complex(rs_re, rs_im), jax_complex(rp_re, rp_im)


def jax_complex(re: Array, im: Array) -> Array:
    """``re + i im`` in the complex dtype matching the float dtype of ``re``."""
    cdt = jnp.result_type(re.dtype, jnp.complex64)
    return re.astype(cdt) + 1j * im.astype(cdt)


@jax.jit
def fresnel_mueller_params(
    n_re: Float[ArrayLike, "..."], n_im: Float[ArrayLike, "..."], cos_t: Float[ArrayLike, "..."]
) -> tuple[Float[Array, "..."], Float[Array, "..."], Float[Array, "..."], Float[Array, "..."]]:
    """Parameters ``(a, b, c, d)`` of the Fresnel Mueller matrix in the facet's s/p frames.

    ``M = [[a, b, 0, 0], [b, a, 0, 0], [0, 0, c, d], [0, 0, -d, c]]`` with
    ``a = (|r_s|^2 + |r_p|^2)/2`` (the unpolarized reflectance), ``b = (|r_s|^2 - |r_p|^2)/2``,
    ``c = Re(r_s r_p^*)``, ``d = Im(r_s r_p^*)``. Real arithmetic, NaN-safe gradients in
    ``n_re``, ``n_im`` and ``cos_t`` on ``[0, 1]``.
    """
    rs_re, rs_im, rp_re, rp_im = fresnel_amplitudes_re(n_re, n_im, cos_t)
    rs2 = rs_re * rs_re + rs_im * rs_im
    rp2 = rp_re * rp_re + rp_im * rp_im
    a = 0.5 * (rs2 + rp2)
    b = 0.5 * (rs2 - rp2)
    # r_s r_p^* = (rs_re + i rs_im)(rp_re - i rp_im)
    c = rs_re * rp_re + rs_im * rp_im
    d = rs_im * rp_re - rs_re * rp_im
    return a, b, c, d
