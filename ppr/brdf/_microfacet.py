r"""Blinn-Phong microfacet lobe: NDF, lobe averages and Ashikhmin visibility.

Public as :mod:`ppr.microfacet`. All functions broadcast over their arguments, are
``jit``/``vmap``/``grad``-able in ``m`` and ``cos_theta`` (and the directions), and follow the
input float dtype (float32 in, float32 out). ``cos_theta = k . n`` of a unit direction ``k`` in
the upper hemisphere; values outside ``[0, 1]`` are clamped.

Normal distribution (docs/physics/single_bounce.md)
    ``p(h) = (m + 1) / (2 pi) (h . n)^m`` on the upper hemisphere, normalized so that
    ``integral p(h) d omega_h = 1``; ``<h . n> = (m + 1) / (m + 2)``.

The mean projected cosine ``<h . k>+`` (derivation, used by :func:`mean_cosine_plus`)
    Let ``c = k . n``, ``s = sqrt(1 - c^2)``, ``t = h . n``. Integrating ``max(h . k, 0)`` over
    the facet azimuth in closed form gives ``c t`` when the facet faces ``k`` at every azimuth
    (``t >= s``) and ``c t + G(t)`` below the kink ``t = s``, with
    ``pi G = sqrt(s^2 - t^2) - c t atan2(sqrt(s^2 - t^2), c t)`` (the facets facing away).
    So ``<h . k>+ = c <h . n> + int_0^s (m + 1) t^m G(t) dt``. ``G`` vanishes like
    ``(s - t)^{3/2}`` at the kink, which is what spoils plain Gauss-Legendre in ``t`` or in
    ``u = t^(m+1)``. Two integrations by parts (``G' = -(t r / (1 - t^2) + c psi) / pi``,
    ``psi' = -c / (r (1 - t^2))``, ``r = sqrt(s^2 - t^2)``) remove ``psi`` altogether, and
    ``t = s cos(chi)``, ``x = tan(chi)`` then give, with ``M = m + 2``,

    .. math::

        <h.k>_+ = c \frac{m+1}{m+2} + \frac{s^M}{\pi} I, \qquad
        I = \int_0^\infty \frac{s^2 x^2 + (c^2 / M)(1 + x^2)}{c^2 + x^2}
            (1 + x^2)^{-(M+2)/2} dx .

    The integrand is positive (no cancellation), smooth, and has exactly two scales: a
    Lorentzian layer of width ``c`` at ``x = 0`` (the grazing band) and the lobe
    ``(1 + x^2)^{-(M+2)/2}`` of width ``~1/sqrt(M)``. The substitution ``x = c sinh(y)`` maps
    the layer onto ``y ~ 1`` exactly:

    .. math::

        I = c \int_0^\infty \frac{s^2 \sinh^2 y + (1 + c^2 \sinh^2 y) / M}
            {\cosh y \, (1 + c^2 \sinh^2 y)^{(M+2)/2}} dy ,

    an even function of ``y``, analytic in the strip ``|Im y| < pi/2``, decaying like
    ``exp(-(M + 1) y)`` (or faster, Gaussian, for large ``M``). It is truncated at
    ``x = X`` with ``(1 + X^2)^{-(M+1)/2} = exp(-T)`` (T = 28 in float64, 16 in float32) and
    integrated by the trapezoidal rule with a fixed number of nodes (static ``order``), whose
    error for such an integrand falls like ``exp(-pi^2 / h)``: measured 2e-12 relative at 64
    nodes in float64, where Gauss-Legendre in ``y`` needs ~128 (bench/bench_lobe.py).

    Numerics: ``log(s^2)`` is formed to full relative precision (it is multiplied by
    ``M/2 <= 5e5``). Below ``c1 = 1e-5 / sqrt(M)`` (beyond 89.999 deg) the correction is
    continued linearly in ``c`` (the layer is then deep inside the lobe), so the quadrature
    range stays bounded down to ``c = 0``. Where ``s^M / 2`` (an upper bound of the correction)
    is below ``exp(-44)`` (float64; ``exp(-20)`` float32) of ``c <h.n>`` the correction is
    dropped (``jnp.where``, both branches safe), and a batch in which every element is
    dropped skips the quadrature (``lax.cond``). The derivatives in ``m`` and ``c``
    (``jax.custom_jvp``) are the integrals of the differentiated integrand, evaluated by the
    same loop. Checks (tests/test_microfacet.py): an mpmath
    reference at 1e-9, Monte Carlo over the lobe, ``m = 0`` closed form
    ``<h.k>+ = (1 + c) / 4``, ``c = 0`` gives ``I = int_0^{pi/2} cos^M``, ``m -> inf`` gives ``c``.

Visibility (Ashikhmin, Premoze, Shirley 2000)
    ``P(k) = <h . n> (k . n) / <h . k>+`` and
    ``P(k | k') = (1 - f) P(k) P(k') + f min(P(k), P(k'))``, ``f = cos(phi / 2)``, ``phi`` the
    azimuth between the projections of ``k`` and ``k'`` on the surface plane.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Shaped

from .._safe import float_dtype, safe_div, safe_norm, safe_normalize, tiny
from .._types import Array, ArrayLike, Float

__all__ = [
    "ndf",
    "mean_cosine_n",
    "mean_cosine_plus",
    "visibility",
    "joint_visibility",
    "DEFAULT_ORDER",
    "DEFAULT_ORDER_F32",
]

DEFAULT_ORDER = 64
"""Default quadrature order of :func:`mean_cosine_plus` in float64 (bench/bench_lobe.py)."""
DEFAULT_ORDER_F32 = 32
"""Default quadrature order in float32 (bench/bench_lobe.py)."""


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _check_m(m) -> None:
    if _is_concrete(m):
        a = np.asarray(m)
        if not np.all(np.isfinite(a)) or np.any(a < 0):
            raise ValueError(f"m (Blinn-Phong exponent) must be finite and >= 0, got m={a!r}")


def _as(x, dt) -> Array:
    return jnp.asarray(x).astype(dt)


def ndf(m: Shaped[ArrayLike, "..."], cos_h: Shaped[ArrayLike, "..."]) -> Float[Array, "..."]:
    """Blinn-Phong normal distribution ``p(h) = (m + 1) / (2 pi) (h . n)^m`` in 1/sr.

    **Arguments:**

    - `m`: Blinn-Phong exponent (``>= 0``).
    - `cos_h`: ``h . n``, the cosine between the facet normal and the macro normal.

    **Returns:** ``p(h)``, 0 below the horizon (``cos_h < 0``). The power is computed in log
    space, ``exp(m log1p(-(1 - cos_h)))``, so that float32 keeps its precision at ``m = 1e6``;
    at ``cos_h = 0`` exactly, ``0^0 = 1`` (``m = 0``) and ``0^m = 0`` (``m > 0``), with finite
    gradients everywhere.
    """
    _check_m(m)
    dt = float_dtype(m, cos_h)
    m = _as(m, dt)
    ch = _as(cos_h, dt)
    ok = ch > tiny(dt)
    chs = jnp.where(ok, ch, 1.0)
    # log(cos_h) as log1p(-(1 - cos_h)) near the peak (1 - cos_h is exact there), plain log
    # below 1/2 (where 1 - cos_h would round to 1 for tiny cos_h)
    near = chs > 0.5
    log_ch = jnp.where(near, jnp.log1p(-(1.0 - jnp.where(near, chs, 1.0))), jnp.log(chs))
    val = jnp.exp(m * log_ch)
    at_zero = jnp.where(m > 0, 0.0, 1.0)
    pw = jnp.where(ok, val, jnp.where(ch >= 0, at_zero, 0.0))
    return (m + 1.0) / (2.0 * math.pi) * pw


def mean_cosine_n(m: Shaped[ArrayLike, "..."]) -> Float[Array, "..."]:
    """``<h . n> = (m + 1) / (m + 2)``, the mean cosine of the facet normals."""
    _check_m(m)
    dt = float_dtype(m)
    m = _as(m, dt)
    return (m + 1.0) / (m + 2.0)


@functools.cache
def _trapezoid(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes in [0, 1] and weights of the trapezoidal rule for an even integrand on [0, Y].

    (Weights to be multiplied by Y.) For a function analytic in the strip ``|Im y| < pi/2``
    the error decays like ``exp(-pi^2 / h)``, ``h = Y / (order - 1)``.
    """
    x = np.arange(order, dtype=np.float64) / (order - 1)
    w = np.full(order, 1.0 / (order - 1))
    w[0] *= 0.5
    w[-1] *= 0.5
    return x, w


def _log_tail(dt) -> float:
    """Truncation: the tail left out of the integral is below ``exp(-T)`` of it."""
    return 28.0 if np.finfo(dt).bits == 64 else 16.0


def _default_order(dt) -> int:
    return DEFAULT_ORDER if np.finfo(dt).bits == 64 else DEFAULT_ORDER_F32


def _c_floor(dt) -> float:
    """A cos_theta below which ``P(k) / (k . n)`` may be taken constant (used by ppr.brdf._brdf).

    Below ``_c_small / sqrt(M)`` (>= 1e-8 in float64) the correction is linear in ``c``, so
    ``P`` is linear in ``c`` to relative ``c / <h.k>+`` (<= 1e-7 at these floors).
    """
    return 1e-10 if np.finfo(dt).bits == 64 else 1e-7


def _c_small(dt) -> float:
    """Below ``c1 = _c_small / sqrt(M)`` the correction is continued linearly in ``c``.

    ``I(c) = I(c1) + (pi/2) ((M-1)/M) (c1 - c) + O(M c1^2)``: the Lorentzian layer of width
    ``c`` is then far inside the lobe (width ``1/sqrt(M)``) and its integral is linear in
    ``c``; the neglected terms are ~``(c1 sqrt(M))^2`` relative; with the default order the
    error at c < c1 (beyond 89.999 deg) is <= 4e-10 in float64 (measured).
    This keeps the quadrature range ``asinh(X / c)`` bounded down to ``c = 0`` exactly.
    """
    return 1e-5 if np.finfo(dt).bits == 64 else 3e-4


def _negligible_log(dt) -> float:
    """log of the relative size below which the correction is dropped (fast path)."""
    return -44.0 if np.finfo(dt).bits == 64 else -20.0


def _correction(m: Array, c: Array, order: int | None) -> Array:
    """``<h.k>+ - c <h.n>`` by the sinh-substituted integral (module docstring).

    ``m``, ``c`` broadcast arrays of one float dtype, ``c`` in ``[0, 1]``.
    """
    dt = c.dtype
    order = _default_order(dt) if order is None else int(order)
    if order < 2:
        raise ValueError(f"order must be >= 2, got order={order}")
    return _correction_jit(m, c, order)


def _prelude(m: Array, c: Array):
    """Per-element quantities of the correction shared by the test and the quadrature."""
    dt = c.dtype
    big_m = m + 2.0
    c1 = _c_small(dt) * jax.lax.rsqrt(big_m)
    c_ok = c > c1
    cq = jnp.where(c_ok, c, c1)
    s2 = (1.0 - cq) * (1.0 + cq)
    s2_ok = s2 > tiny(dt)
    # log(s^2) to full relative precision (it is multiplied by M/2 <= 5e5): log1p(-c^2) for
    # small c, log((1 - c)(1 + c)) near c = 1.
    small_c = cq < 0.5
    log_s2 = jnp.where(
        small_c,
        jnp.log1p(-jnp.where(small_c, cq * cq, 0.0)),
        jnp.log(jnp.where(s2_ok, s2, 1.0)),
    )
    log_s2 = jnp.where(s2_ok, log_s2, -1e4)
    log_sm = 0.5 * big_m * log_s2
    return big_m, c_ok, cq, s2, s2_ok, log_s2, log_sm


def _needed(m: Array, c: Array) -> Array:
    """Where the correction is not negligible: it is <= s^M / 2 (I <= pi/2); it is dropped
    where that is below exp(_negligible_log) of c <h.n>."""
    dt = c.dtype
    big_m, _, _, _, _, _, log_sm = _prelude(m, c)
    base = c * (m + 1.0) / big_m
    log_base = jnp.log(jnp.where(base > tiny(dt), base, tiny(dt)))
    return log_sm - math.log(2.0) > log_base + _negligible_log(dt)


def _quadrature(m: Array, c: Array, order: int, partials: bool):
    """The correction (and, if ``partials``, d/dm and d/dc) by the quadrature, every element."""
    dt = c.dtype
    big_m, c_ok, cq, s2, s2_ok, log_s2, log_sm = _prelude(m, c)
    inv_s2 = jnp.where(s2_ok, 1.0 / jnp.where(s2_ok, s2, 1.0), 0.0)
    s2 = jnp.where(s2_ok, s2, 0.0)
    n_out = 3 if partials else 1
    # truncation in x = c sinh y: (1 + X^2)^{-(M+1)/2} = exp(-T)
    x_max = jnp.sqrt(jnp.expm1(2.0 * _log_tail(dt) / (big_m + 1.0)))
    y_max = jnp.arcsinh(x_max / cq)
    c2 = cq * cq
    inv_m = 1.0 / big_m
    half_m2 = 0.5 * (big_m + 2.0)
    h = y_max / (order - 1)

    def node(j, acc):
        # trapezoid on the even integrand over [0, y_max]: half weight at both ends
        e = jnp.exp(h * j.astype(dt))
        ei = 1.0 / e
        sh = 0.5 * (e - ei)
        sh2 = sh * sh
        q = c2 * sh2
        log1p_q = jnp.log1p(q)
        num = s2 * sh2 + (1.0 + q) * inv_m
        wj = jnp.where((j == 0) | (j == order - 1), 0.5, 1.0).astype(dt)
        ew = wj * (2.0 / (e + ei)) * jnp.exp(log_sm - half_m2 * log1p_q)
        out = (acc[0] + ew * num,)
        if partials:
            # d/dM and d/dc of num * exp(L), L = (M/2) log s2 - ((M+2)/2) log1p(q)
            d_num_m = -(1.0 + q) * inv_m * inv_m
            d_l_m = 0.5 * (log_s2 - log1p_q)
            d_num_c = -2.0 * cq * sh2 * (1.0 - inv_m)
            d_l_c = -big_m * cq * inv_s2 - 2.0 * half_m2 * cq * sh2 / (1.0 + q)
            out = out + (
                acc[1] + ew * (d_num_m + num * d_l_m),
                acc[2] + ew * (d_num_c + num * d_l_c),
            )
        return out

    if cq.size * order <= NODE_AXIS_MAX and (NODE_AXIS_PARTIALS or not partials):
        # small batches: all nodes at once on a leading node axis (XLA CPU pays a few us per
        # loop iteration, which dominates a batch of a few hundred elements)
        j = jnp.arange(order).reshape((order,) + (1,) * cq.ndim)
        acc = tuple(jnp.sum(t, axis=0) for t in node(j, (0.0,) * n_out))
    else:
        # A loop over the nodes keeps the compiled program small (an unrolled sum took
        # minutes to compile under grad) and the intermediates at the batch shape.
        acc = jax.lax.fori_loop(0, order, node, (jnp.zeros_like(cq),) * n_out)
    scale = h / math.pi
    # linear continuation below c1 (see _c_small); s^M(c) = s^M(c1) to 5e-11 there
    dc_lin = cq - c
    sm = jnp.exp(log_sm)
    slope = 0.5 * (1.0 - inv_m)
    out = (cq * acc[0] * scale + sm * slope * dc_lin,)
    if partials:
        d_m = cq * acc[1] * scale + sm * (0.5 * log_s2 * slope + 0.5 * inv_m * inv_m) * dc_lin
        d_c = jnp.where(c_ok, (acc[0] + cq * acc[2]) * scale, -sm * slope)
        out = out + (d_m, d_c)
    return out


NODE_AXIS_MAX = 2**18
"""Value-only calls with ``size * order`` up to this sum the quadrature's nodes on a node axis
(one fused sum) instead of looping over the nodes (:func:`_quadrature`): 1.1-2.5x faster
for 64-4096 elements in float64 (bench/bench_lobe.py, "Small batches"); the MCMC's
log-probability (a few facets per walker) spends most of its time here."""
NODE_AXIS_PARTIALS = False
"""Also sum the custom-JVP partials on a node axis: no consistent gain (bench/bench_lobe.py,
three runs: 0.7-1.5x the loop's time, the loop faster at 256-512 elements every time), so
off: gradients keep the loop the refiner was tuned with."""

COMPACT_MIN = 4096
"""Batches of at least this many elements evaluate the quadrature only on the elements that
need it (:func:`_correction_impl`); smaller ones on all (a gather costs more than it saves
there). Measured in bench/bench_brdf.py."""
COMPACT_FRACTIONS = (1 / 16, 1 / 4, 1 / 2)
"""Static capacities (fractions of the batch) of the compacted quadrature."""


def _correction_impl(m: Array, c: Array, order: int, partials: bool):
    """Value (and, if ``partials``, d/dm and d/dc) of the correction.

    The derivatives are those of the exact integral, differentiated under the integral sign
    in ``y`` and evaluated by the same quadrature (the truncation point moves with ``c`` but
    the integrand is negligible there). Only the elements where the correction is not
    negligible (:func:`_needed`) pay for the quadrature: a batch with none skips it; a batch
    of at least :data:`COMPACT_MIN` elements gathers the needed ones into the smallest
    static capacity of :data:`COMPACT_FRACTIONS` that holds them (``lax.switch``), runs the
    quadrature there and scatters back. The others are exactly 0 with zero derivatives, as
    with ``where``. (XLA CPU pays ~5 us per loop iteration, so the quadrature needs a large
    batch to be efficient: one gather into a static size, not a loop over small blocks.)
    """
    n_out = 3 if partials else 1
    needed = _needed(m, c)
    zeros = (jnp.zeros_like(c),) * n_out

    def full(_):
        return tuple(jnp.where(needed, v, 0.0) for v in _quadrature(m, c, order, partials))

    size = c.size
    caps = sorted({int(math.ceil(f * size)) for f in COMPACT_FRACTIONS if f * size >= 256})
    if size < COMPACT_MIN or not caps:
        return jax.lax.cond(jnp.any(needed), full, lambda _: zeros, None)

    mf, cf, nf = m.reshape(-1), c.reshape(-1), needed.reshape(-1)
    pos = jnp.cumsum(nf.astype(jnp.int32)) - 1
    count = pos[-1] + 1

    def compact(cap):
        def run(_):
            # indices of the needed elements in order, padded with `size` (out of range)
            idx = jnp.full((cap,), size, jnp.int32)
            idx = idx.at[jnp.where(nf, pos, cap)].set(
                jnp.arange(size, dtype=jnp.int32), mode="drop"
            )
            ok = idx < size
            safe = jnp.where(ok, idx, 0)
            vals = _quadrature(mf[safe], cf[safe], order, partials)
            dest = jnp.where(ok, idx, size)
            return tuple(
                jnp.zeros_like(cf).at[dest].set(v, mode="drop").reshape(c.shape) for v in vals
            )

        return run

    branches = [lambda _: zeros] + [compact(k) for k in caps] + [full]
    # branch 0: none needed; then the smallest capacity >= count; last: all
    which = jnp.where(count == 0, 0, 1 + jnp.searchsorted(jnp.asarray(caps), count))
    return jax.lax.switch(which, branches, None)


@functools.cache
def _correction_batched(order: int, partials: bool):
    """:func:`_correction_impl` with a ``vmap`` rule that folds the mapped axis into the
    batch: the function is elementwise, and under plain ``vmap`` its ``lax.switch`` on the
    number of needed elements would become a select that runs every branch."""

    @jax.custom_batching.custom_vmap
    def f(m, c):
        return _correction_impl(m, c, order, partials)

    @f.def_vmap
    def _rule(axis_size, in_batched, m, c):
        bm, bc = in_batched
        m = m if bm else jnp.broadcast_to(m, (axis_size,) + jnp.shape(m))
        c = c if bc else jnp.broadcast_to(c, (axis_size,) + jnp.shape(c))
        m, c = jnp.broadcast_arrays(m, c)
        out = f(m, c)
        return out, tuple(True for _ in out)

    return f


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _correction_cjvp(m: Array, c: Array, order: int) -> Array:
    return _correction_batched(order, False)(m, c)[0]


@_correction_cjvp.defjvp
def _correction_jvp(order, primals, tangents):
    m, c = primals
    tm, tc = tangents
    val, d_m, d_c = _correction_batched(order, True)(m, c)
    return val, d_m * tm + d_c * tc


# jit the loop once per shape/dtype/order, so that eager calls do not recompile the loop
_correction_jit = jax.jit(_correction_cjvp, static_argnums=(2,))


# ---------------------------------------------------------------------------------------
# one material per batch: the correction tabulated in c once per call (float32 BRDF path)

TABLE_NODES = {32: 256, 64: 1024}
"""Nodes of the per-material table of the correction (:func:`visibility_one_material`) per
float width: max relative error of ``P(k)`` against the float64 quadrature 1.0e-6 in float32
(the float32 quadrature's own: 1.1e-6) and 5.5e-10 in float64 (error against size and speed
in bench/bench_lobe.py)."""


def _table_c_hi(m0: Array) -> Array:
    """Upper end of the table: beyond it the correction is below ``exp(-54) / 2`` of 1
    (``s^M <= exp(-M c^2 / 2)``), far below the drop rule of :func:`_needed`."""
    return jnp.minimum(1.0, jnp.sqrt(2.0 * 54.0 / (m0 + 2.0)))


def _half_angle(c: Array) -> Array:
    """``w = tan(v / 2)`` of ``v = asin(c)``, the table variable, as ``c / (1 + sqrt(1 - c^2))``
    (one sqrt and one divide: ``jnp.arcsin`` lowers to an ``atan2`` that XLA CPU does not
    vectorize, 17 ns per element against 0.7)."""
    return c / (1.0 + jnp.sqrt((1.0 - c) * (1.0 + c)))


def _correction_nodes(m0: Array, n_nodes: int, order: int):
    """Correction and its partials d/dm, d/dc at ``n_nodes`` points equispaced in
    ``w = tan(v / 2)``, ``v = asin(c)``, over ``[0, w(c_hi)]``, by the quadrature. ``w`` is
    ``c / 2`` near grazing (full float32 relative precision where large-``m`` corrections vary
    fast) and a smooth function of the incidence angle near normal incidence, where the
    correction has a ``sqrt(1 - c)`` term for small ``m`` that a grid in ``c`` resolves only to
    O(h^1/2) (measured 1.5e-4 at m = 0, 512 nodes; a grid in the incidence angle lost 1e-4 in
    float32 at m = 1e6). ``dc/dw = 2 (1 - w^2) / (1 + w^2)^2``."""
    dt = m0.dtype
    w_hi = _half_angle(_table_c_hi(m0))
    w = w_hi * jnp.linspace(0.0, 1.0, n_nodes, dtype=dt)
    w2 = w * w
    cn = jnp.clip(2.0 * w / (1.0 + w2), 0.0, 1.0)
    dc_dw = 2.0 * (1.0 - w2) / ((1.0 + w2) * (1.0 + w2))
    val, d_m, d_c = _quadrature(jnp.broadcast_to(m0, cn.shape), cn, order, True)
    return w_hi, dc_dw, val, d_m, d_c


def _hermite(x, step, val, der, n_nodes):
    """Cubic Hermite interpolation at ``x`` on nodes ``j step`` (values and derivatives),
    0 beyond the last node.

    The cubic of each interval is formed once, as four ``(n_nodes - 1,)`` columns of monomial
    coefficients stored by a dot with the identity, and gathered per query. XLA CPU otherwise
    fuses the table's elementwise producers (the node arithmetic) into each gather and
    recomputes them per query (bench/profile_brdf.py); four column gathers run 2.5x faster
    than one gather of a row of four."""
    dt = x.dtype
    s = jnp.clip(x / step, 0.0, n_nodes - 1.0)
    i = jnp.clip(jnp.floor(s), 0, n_nodes - 2).astype(jnp.int32)
    t = s - i.astype(dt)
    f0, f1 = val[:-1], val[1:]
    d0, d1 = der[:-1] * step, der[1:] * step
    df = f1 - f0
    coef = jnp.stack([f0, d0, 3.0 * df - 2.0 * d0 - d1, d0 + d1 - 2.0 * df], axis=0)
    coef = jnp.matmul(jnp.eye(4, dtype=dt), coef, precision=jax.lax.Precision.HIGHEST)
    c0, c1, c2, c3 = (jnp.take(coef[k], i, mode="clip") for k in range(4))
    p = ((c3 * t + c2) * t + c1) * t + c0
    inside = x <= step * (n_nodes - 1)
    return jnp.where(inside, p, 0.0)


def _one_material_parts(m0, c, n_nodes, order, partials):
    w_hi, dc_dw, val, d_m, d_c = _correction_nodes(m0, n_nodes, order)
    step = w_hi / (n_nodes - 1)
    x = _half_angle(c)  # the query's w
    out = _hermite(x, step, val, dc_dw * d_c, n_nodes)
    if not partials:
        return out
    # the partials, interpolated (their w-derivatives by central differences)
    dm = _hermite(x, step, d_m, jnp.gradient(d_m, step), n_nodes)
    dc = _hermite(x, step, d_c, jnp.gradient(d_c, step), n_nodes)
    return out, dm, dc


@functools.partial(jax.custom_jvp, nondiff_argnums=(2, 3))
def _correction_one_material(m0: Array, c: Array, n_nodes: int, order: int) -> Array:
    return _one_material_parts(m0, c, n_nodes, order, False)


@_correction_one_material.defjvp
def _correction_one_material_jvp(n_nodes, order, primals, tangents):
    m0, c = primals
    tm, tc = tangents
    out, dm, dc = _one_material_parts(m0, c, n_nodes, order, True)
    return out, dm * tm + dc * tc


def visibility_one_material(
    m0: Shaped[ArrayLike, ""], cos_theta: Shaped[ArrayLike, "..."], *, n_nodes: int | None = None
) -> Float[Array, "..."]:
    """:func:`visibility` for one ``m`` shared by the whole batch, from a table of the
    ``<h.k>+`` correction over ``cos_theta`` built per call (``n_nodes`` quadrature
    evaluations, default :data:`TABLE_NODES` by dtype) and cubic Hermite interpolation (values and
    ``c``-derivatives at the nodes): a few operations per element instead of a quadrature.
    Differentiable in ``m0`` and ``cos_theta``. Its error against the quadrature is measured
    in bench/bench_lobe.py and tested in tests/test_microfacet.py; ``ppr.mueller_brdf`` uses
    it in float32 (the quadrature in float64)."""
    _check_m(m0)
    dt = float_dtype(m0, cos_theta)
    m0 = _as(m0, dt)
    if m0.ndim != 0:
        raise ValueError(f"m0 must be a scalar (one material), got shape {m0.shape}")
    c = jnp.clip(_as(cos_theta, dt), 0.0, 1.0)
    n = TABLE_NODES[np.finfo(dt).bits] if n_nodes is None else int(n_nodes)
    if n < 4:
        raise ValueError(f"n_nodes must be >= 4, got n_nodes={n}")
    base = c * (m0 + 1.0) / (m0 + 2.0)
    corr = _correction_one_material(m0, c, n, _default_order(dt))
    return jnp.clip(safe_div(base, base + corr, fill=1.0), 0.0, 1.0)


def _over_cos(m: Array, c: Array, corr: Array) -> Array:
    """``P(k) / (k . n) = <h.n> / <h.k>+ = <h.n> / (c <h.n> + corr)``: no division by ``c``
    (finite with a finite derivative down to ``c = 0``, where ``<h.k>+ > 0``)."""
    hn = (m + 1.0) / (m + 2.0)
    return safe_div(hn, c * hn + corr, fill=0.0)


def visibility_over_cos(m: Array, c: Array, *, order: int | None = None) -> Array:
    """``P(k) / (k . n)`` (:func:`visibility` over the cosine) as ``<h.n> / <h.k>+``.

    Dividing ``P`` by ``c`` instead gives the same value, but the derivative of a quotient is
    formed with ``c^2``, which underflows in float32 below ``c ~ 1e-19`` (an infinite, then NaN
    gradient). ``m``, ``c``: arrays of one float dtype, ``c`` in ``[0, 1]``."""
    m, c = jnp.broadcast_arrays(m, c)
    return _over_cos(m, c, _correction(m, c, order))


def visibility_over_cos_one_material(m0: Array, c: Array) -> Array:
    """:func:`visibility_over_cos` for one scalar ``m0`` (the per-call table of
    :func:`visibility_one_material`)."""
    n = TABLE_NODES[np.finfo(c.dtype).bits]
    return _over_cos(m0, c, _correction_one_material(m0, c, n, _default_order(c.dtype)))


def mean_cosine_plus(
    m: Shaped[ArrayLike, "..."], cos_theta: Shaped[ArrayLike, "..."], *, order: int | None = None
) -> Float[Array, "..."]:
    """``<h . k>+``: mean over the Blinn-Phong lobe of ``max(h . k, 0)``, ``cos_theta = k . n``.

    **Arguments:**

    - `m`: Blinn-Phong exponent, ``0 <= m <= 1e6``.
    - `cos_theta`: ``k . n`` (clamped to ``[0, 1]``).
    - `order`: number of quadrature nodes (static Python int); default ``DEFAULT_ORDER``
      (64) in float64 and ``DEFAULT_ORDER_F32`` (32) in float32.

    **Returns:** ``<h . k>+ >= (k . n) <h . n>``, equal to it away from grazing. Relative
    error below 1e-9 in float64 for incidence up to 89.999 deg (tests/test_microfacet.py).
    """
    _check_m(m)
    dt = float_dtype(m, cos_theta)
    m = _as(m, dt)
    c = jnp.clip(_as(cos_theta, dt), 0.0, 1.0)
    m, c = jnp.broadcast_arrays(m, c)
    base = c * (m + 1.0) / (m + 2.0)
    return base + _correction(m, c, order)


def _visibility(m: Array, c: Array, order: int | None) -> Array:
    base = c * (m + 1.0) / (m + 2.0)
    den = base + _correction(m, c, order)
    return jnp.clip(safe_div(base, den, fill=1.0), 0.0, 1.0)


def visibility(
    m: Shaped[ArrayLike, "..."], cos_theta: Shaped[ArrayLike, "..."], *, order: int | None = None
) -> Float[Array, "..."]:
    """Ashikhmin shadowing ``P(k) = <h . n> (k . n) / <h . k>+`` in ``[0, 1]``.

    ``P = 1`` at normal incidence and away from grazing; ``P -> 0`` linearly (finite gradient)
    as ``cos_theta -> 0``.
    """
    _check_m(m)
    dt = float_dtype(m, cos_theta)
    m = _as(m, dt)
    c = jnp.clip(_as(cos_theta, dt), 0.0, 1.0)
    m, c = jnp.broadcast_arrays(m, c)
    return _visibility(m, c, order)


def joint_visibility(
    m: Shaped[ArrayLike, "..."],
    k_in: Shaped[ArrayLike, "... 3"],
    k_out: Shaped[ArrayLike, "... 3"],
    normal: Shaped[ArrayLike, "... 3"],
    *,
    order: int | None = None,
) -> Float[Array, "..."]:
    """Joint visibility ``P(k|k') = (1 - f) P(k) P(k') + f min(P(k), P(k'))``.

    **Arguments:**

    - `m`: Blinn-Phong exponent, shape broadcastable with the batch shape.
    - `k_in`, `k_out`: unit directions away from the surface, ``(..., 3)``.
    - `normal`: unit macro normal, ``(..., 3)``.

    ``f = cos(phi / 2)`` with ``phi`` in ``[0, pi]`` the azimuth between the projections of the
    two directions on the surface plane, evaluated as ``|u + u'| / 2`` (``u``, ``u'`` the unit
    projections), which has a finite gradient also at ``phi = pi``. When either direction is
    along the normal its projection vanishes and ``phi = 0`` (``f = 1``) is used; there
    ``P = 1`` for that direction so the choice does not change the value. Symmetric in
    ``k_in <-> k_out``.
    """
    _check_m(m)
    dt = float_dtype(m, k_in, k_out, normal)
    m = _as(m, dt)
    ki = _as(k_in, dt)
    ko = _as(k_out, dt)
    n = _as(normal, dt)
    ci = jnp.clip(jnp.sum(ki * n, axis=-1), 0.0, 1.0)
    co = jnp.clip(jnp.sum(ko * n, axis=-1), 0.0, 1.0)
    ti = ki - jnp.sum(ki * n, axis=-1, keepdims=True) * n
    to = ko - jnp.sum(ko * n, axis=-1, keepdims=True) * n
    ui, ok_i = safe_normalize(ti)
    uo, ok_o = safe_normalize(to)
    f = jnp.where(ok_i & ok_o, 0.5 * safe_norm(ui + uo), 1.0)
    f = jnp.clip(f, 0.0, 1.0)
    m, ci, co = jnp.broadcast_arrays(m, ci, co)
    # one quadrature call for both directions (one loop in the compiled program)
    p2 = _visibility(jnp.stack([m, m]), jnp.stack([ci, co]), order)
    pi, po = p2[0], p2[1]
    return (1.0 - f) * (pi * po) + f * jnp.minimum(pi, po)
