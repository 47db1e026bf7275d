r"""The assembled polarized microfacet Mueller BRDF and its term registry.

``mueller_brdf(k_in, k_out, normal, material)`` returns the 4x4 Mueller BRDF in 1/sr mapping
the incident Stokes vector (frame of the beam travelling along ``-k_in``, x axis
``frame_in``) to the outgoing one (beam along ``+k_out``, x axis ``frame_out``); directions
point away from the surface (:mod:`ppr.optics.conventions`). It is the sum of named terms:

``"single"`` (:func:`single_bounce_term`)
    Ashikhmin, Premoze & Shirley 2000 with the facet Fresnel Mueller matrix,

        f = p(h) P(k|k') F_M(k.h) / (4 <h.n> (k.n)(k'.n)),

    ``h = (k_in + k_out)/|k_in + k_out|``, Blinn-Phong ``p(h) = (m+1)/(2 pi) (h.n)^m`` and
    Ashikhmin visibility (:mod:`ppr.brdf._microfacet`), ``F_M`` the facet's Fresnel Mueller matrix
    in the beam frames (:func:`ppr.optics._frames.facet_mueller_in_beam_frames`). The paper's eq. 4
    drops the 4 and ``(k'.n)``; docs/physics/single_bounce.md restores them.

``"double"``
    The double-bounce term of ``ppr/brdf/double.py`` (quadrature over the first facet's normal),
    from the material-independent exact-backscatter tables of ``ppr/brdf/double_table.py``
    wherever the whole batch is within ``ppr.BACKSCATTER_PSI_MAX`` (1e-3 rad) of
    backscatter (``"double:backscatter"`` forces the tables).

``"multiple"`` (:func:`multiple_scattering_term`)
    Depolarizing remainder of the explicit terms (docs/physics/multiple_scattering.md),

        f_ms = F_add c D(k) D(k') diag(1, 0, 0, 0),  c = 1 / (pi D_avg),
        D = 1 - E,  D_avg = 1 - E_avg = 2 int_0^1 D(mu) mu dmu,

    ``E(m, mu)`` the white-surface (``F == 1``) directional albedo of the model's explicit terms
    (:func:`explicit_terms`; tables of ``log D`` in :mod:`ppr.brdf.albedo`), so that explicit +
    multiple has a white-furnace albedo of 1 (to within the tables' closure budget of the double
    term's quadrature error, 3e-4). ``F_add = F_avg^2 E_avg / (1 - F_avg D_avg)`` (Kulla &
    Conty 2017) with ``F_avg = 2 int_0^1 F(mu) mu dmu`` the cosine-weighted hemispherical
    average of the unpolarized Fresnel reflectance, by fixed 32-point Gauss-Legendre
    (differentiable in ``n``); ``F_add = 1`` for the ideal white reflector.

Terms are components of *one* model: the remainder always completes the full set of
explicit terms, whichever subset the caller asks for, so that the requested terms add up.

Validation (concrete inputs raise ``ValueError`` naming the argument; traced inputs: one
``eqx.branched_error_if`` on the result raises the first failing check's message, so no
result is returned): directions must have shape ``(..., 3)``, be finite, have
``| |k| - 1 | <= UNIT_TOL = 1e-3`` (then they are renormalized), and lie in the upper
hemisphere up to ``k.n >= -HORIZON_TOL = -1e-5`` (``k.n`` in ``[-1e-5, 0]`` is treated as
grazing). Frames must be finite, unit within ``UNIT_TOL`` and perpendicular to their beam
within ``|x.k| <= UNIT_TOL`` (then re-orthonormalized). Material: finite, ``m >= 0``,
``Im n >= 0``. Exactly grazing directions (``k.n <= GRAZING``, about ``1e-30`` in float32 and
``2e-300`` in float64) give 0 with zero (finite) gradients.

Eager calls (all inputs concrete): the checks run on the host side of one small jitted
program per input shape, and the batch is flattened and padded to a bucket size
(:func:`eager_bucket`: 8, then 4 sizes per factor of 2, at most 25 % padding) by repeating its
last row, so the BRDF program itself is compiled once per bucket, dtype, term set and material
layout, not once per batch shape (an eager call on a new shape in the same bucket costs
~0.1-1 s of compilation, not 3-15 s). Calls inside a caller's ``jit``/``vmap``/``grad`` are
traced as they are, unpadded.

Exact backscatter: when ``k_out`` is ``k_in`` (the same array or tracer, or concrete arrays
with equal entries; a monostatic :class:`ppr.Sensor` renders this way), the terms
``"single"``, ``"double"`` and ``"multiple"`` take a dedicated kernel (:func:`_mono_core`):
with ``h = k`` every term is a function of ``k.n`` in the shared frames ``normalize(n x k)``,
the double term comes from the exact-backscatter table, and one rotation maps to the caller's
frames (none for the default frames). Same model, other algebra: equal to the general kernel
to rounding (tests/test_monostatic.py), 5-7x faster at one material in float32
(bench/bench_double_table.py). Equal directions given as different traced arrays take the
general kernel.

Reciprocity (tests/test_brdf.py): with the reversed beams' frames chosen as
``frame_in' = frame_out`` and ``frame_out' = frame_in``,
``M(k_out -> k_in) = Q M(k_in -> k_out)^T Q`` with ``Q = diag(1, 1, -1, 1)`` (the reversed
path has Jones matrix ``D J^T D``, ``D = diag(1, -1)``, because the reversed beams' y axes
flip; derivation in the test).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._safe import float_dtype, tiny
from .._types import Array, Float
from ..materials._material import Material
from ..optics._films import facet_params, films_of
from ..optics._frames import (
    _default_frame3,
    _neg3,
    _stack3,
    facet_rotated_params,
    rotated_mueller_flat,
    store,
)
from ..optics._fresnel import fresnel_mueller_params
from ..optics.conventions import DEFAULT_WAVELENGTH_M
from . import albedo as _albedo
from ._microfacet import mean_cosine_n, visibility_over_cos, visibility_over_cos_one_material
from .double import AUTO_M_MAX, AUTO_PSI_MAX
from .double_table import (
    PSI_MAX,
    backscatter_local,
    double_backscatter_44,
    double_backscatter_term,
    double_bounce_term_auto,
    double_term_dispatch,
    near_backscatter,
    rotate_local,
)

__all__ = [
    "EXPLICIT_TERMS",
    "HORIZON_TOL",
    "TERMS",
    "UNIT_TOL",
    "explicit_terms",
    "fresnel_average",
    "implemented_terms",
    "mueller_brdf",
    "multiple_scattering_term",
    "single_bounce_term",
]

UNIT_TOL = 1e-3
"""Allowed relative deviation of a direction (or frame vector) from unit length."""
HORIZON_TOL = 1e-5
"""Directions with ``k.n < -HORIZON_TOL`` are rejected as below the surface."""


def _grazing(dt) -> float:
    """``k.n`` at or below which a direction counts as exactly grazing (BRDF = 0)."""
    return tiny(dt) * 1e8  # 1.2e-30 (f32), 2.2e-300 (f64)


def _dot(a: Array, b: Array) -> Array:
    return jnp.sum(a * b, axis=-1)


# ---------------------------------------------------------------------------------------
# structure-of-arrays kernels (vectors are tuples of three (...,) arrays; docs/DESIGN.md)

Vec = tuple[Array, Array, Array]


def _split(v: Array) -> Vec:
    return (v[..., 0], v[..., 1], v[..., 2])


def _d3(a: Vec, b: Vec) -> Array:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _geometry3(ki: Vec, ko: Vec, nr: Vec):
    """Cosines, validity mask and safe (masked) directions and half vector, SoA."""
    dt = ki[0].dtype
    ci = _d3(ki, nr)
    co = _d3(ko, nr)
    valid = (ci > _grazing(dt)) & (co > _grazing(dt))
    ki_s = tuple(jnp.where(valid, a, b) for a, b in zip(ki, nr, strict=True))
    ko_s = tuple(jnp.where(valid, a, b) for a, b in zip(ko, nr, strict=True))
    ci_s = jnp.where(valid, ci, 1.0)
    co_s = jnp.where(valid, co, 1.0)
    # half vector: scale by the largest component first (|k_in + k_out|^2 underflows in
    # float32 when both are grazing, ~1e-20, and opposite); h.n = (ci + co) / |.| > 0
    hs = tuple(a + b for a, b in zip(ki_s, ko_s, strict=True))
    big = jnp.maximum(jnp.maximum(jnp.abs(hs[0]), jnp.abs(hs[1])), jnp.abs(hs[2]))
    # the scale is a constant for differentiation (h does not depend on it): its own
    # derivative, -c / big^2, underflows big^2 to 0 in float32 at k.n ~ 1e-20 (inf, then NaN)
    big = jax.lax.stop_gradient(jnp.where(big > 0, big, 1.0))
    hs = tuple(c / big for c in hs)
    inv = 1.0 / jnp.sqrt(_d3(hs, hs))
    h = tuple(c * inv for c in hs)
    return valid, ki_s, ko_s, ci_s, co_s, h


def _log_lobe3(m: Array, h: Vec, nr: Vec) -> Array:
    """``m log(h.n)`` accurate in float32 at m = 1e6: ``1 - h.n = |h - n|^2 / 2`` from the
    difference vector (docs/physics/numerics.md), not from a rounded ``h.n``; 0 at m = 0."""
    d = tuple(a - b for a, b in zip(h, nr, strict=True))
    one_minus = 0.5 * _d3(d, d)
    hn = _d3(h, nr)
    small = one_minus < 0.5
    lp_small = jnp.log1p(-jnp.where(small, one_minus, 0.0))
    hn_ok = hn > tiny(hn.dtype)
    lp_big = jnp.log(jnp.where(hn_ok, hn, 1.0))
    lp = jnp.where(small, lp_small, lp_big)
    # lp is finite (log of a clamped cosine), so m * lp is 0 at m = 0 with d/dm = lp there (a
    # where on m > 0 gave d/dm = 0 at m = 0)
    return m * lp


def _azimuth_factor3(ki: Vec, ko: Vec, nr: Vec, ci: Array, co: Array) -> Array:
    """``f = cos(phi/2) = |u + u'| / 2`` of the unit surface projections (1 where one is along
    the normal), as in :func:`ppr.brdf._microfacet.joint_visibility`."""
    dt = ci.dtype
    ti = tuple(a - ci * b for a, b in zip(ki, nr, strict=True))
    to = tuple(a - co * b for a, b in zip(ko, nr, strict=True))
    qi, qo = _d3(ti, ti), _d3(to, to)
    # projections below |t|^2 = eps: the direction is along the normal, where P = 1 and f does
    # not enter the joint visibility; a ~tiny threshold let the tangent of 1/sqrt(q) (q^-1.5)
    # overflow in float32 for q ~ 1e-32
    thr = float(np.finfo(dt).eps)
    ok = (qi > thr) & (qo > thr)
    ri = 1.0 / jnp.sqrt(jnp.where(ok, qi, 1.0))
    ro = 1.0 / jnp.sqrt(jnp.where(ok, qo, 1.0))
    u = tuple(a * ri + b * ro for a, b in zip(ti, to, strict=True))
    q = _d3(u, u)
    q_ok = ok & (q > tiny(dt) * 1e6)
    f = 0.5 * jnp.sqrt(jnp.where(q_ok, q, 1.0))
    f = jnp.where(q_ok, f, jnp.where(ok, 0.0, 1.0))
    return jnp.clip(f, 0.0, 1.0)


def _c_cap(dt) -> float:
    """Cosine at which the ``1 / (k.n)`` divergence of the BRDF toward grazing backscatter
    (Ashikhmin's joint visibility ``P(k|k) = P(k) ~ k.n`` over ``(k.n)^2``) is held: ``1e2
    sqrt(tiny)``, 1.1e-17 in float32 (1.5e-152 in float64), where the derivative ``1 / c^2``
    (9e33) still leaves float32 room for the other factors. Below it the factor keeps its
    value at the cap; a float32 cosine that small is below the rounding of ``k.n`` itself
    (~6e-8) unless the direction was built exactly."""
    return float(np.sqrt(np.finfo(dt).tiny)) * 1e2


def _log_capped(c: Array) -> Array:
    """``log(max(c, _c_cap))`` (``c`` positive where used)."""
    return jnp.log(jnp.maximum(c, _c_cap(c.dtype)))


def _visibility_over_cos(m: Array, m0, c: Array) -> Array:
    """``V = P(k) / (k.n)``, finite down to ``k.n -> 0`` (ppr.brdf._microfacet continues
    ``<h.k>+`` linearly below its smallest resolved cosine). One material in float32: from a
    per-call table over the incidence (as accurate as the float32 quadrature, 3.4x faster;
    ppr.brdf._microfacet)."""
    if m0 is not None and jnp.ndim(m0) == 0 and np.finfo(c.dtype).bits == 32:
        return visibility_over_cos_one_material(m0, c)
    return visibility_over_cos(m, c)


def _single_scalar3(ki, ko, nr, m, m0=None):
    """``p(h) P(k|k') / (4 <h.n> (k.n)(k'.n))`` (0 where invalid) and the safe geometry.

    The joint visibility divided by ``(k.n)(k'.n)`` is formed as
    ``(1 - f) V V' + f min(V / (k'.n), V' / (k.n))`` with ``V = P(k) / (k.n)`` finite, so no
    product of two small cosines is ever formed (float32 underflow near ``k.n ~ 1e-20``). It
    equals ``ppr.brdf._microfacet.joint_visibility / ((k.n)(k'.n))`` (tests/test_brdf.py).
    """
    dt = ki[0].dtype
    valid, ki_s, ko_s, ci, co, h = _geometry3(ki, ko, nr)
    vi, vo = _visibility_over_cos(m, m0, ci), _visibility_over_cos(m, m0, co)
    f = _azimuth_factor3(ki_s, ko_s, nr, ci, co)
    # min(P, P') / (ci co) = min(V / co, V' / ci) in log space: XLA's algebraic simplifier
    # rewrites a / b / c as a / (b * c), which underflows in float32 at ci, co ~ 1e-20. The
    # factor diverges like 1 / (k.n) toward grazing backscatter (f = 1) for small m; its
    # cosine is held at _c_cap so that it and its derivative (1 / c^2) stay in range
    lci, lco = _log_capped(ci), _log_capped(co)
    t = tiny(dt)
    log_min = jnp.minimum(jnp.log(jnp.maximum(vi, t)) - lco, jnp.log(jnp.maximum(vo, t)) - lci)
    g = (1.0 - f) * vi * vo + f * jnp.exp(log_min)
    log_p = jnp.log((m + 1.0) / (2.0 * math.pi)) + _log_lobe3(m, h, nr)
    scal = jnp.exp(log_p) * g / (4.0 * mean_cosine_n(m))
    return jnp.where(valid, scal, 0.0), ki_s, ko_s, h


def _single_flat(
    ki, ko, nr, m, n_re, n_im, x_in, x_out, white: bool, add_m00=None, m0=None, films=None
) -> Array:
    """Single-bounce term (plus ``add_m00`` on M00) as ``(16, ...)`` (row-major entries on a
    leading axis); ``m0`` the material's own (unbroadcast) exponent; ``films`` the facets'
    film stack (:class:`ppr.optics._films.Films`, broadcast like ``n_re``) or None."""
    scal, ki_s, ko_s, h = _single_scalar3(ki, ko, nr, m, m0)
    # R(b) F R(a) of the facet; the ideal white reflector (perfect conductor,
    # diag(r_s, r_p) = diag(-1, 1)) has Fresnel parameters (a, b, c, d) = (1, 0, -1, 0)
    params = facet_rotated_params(n_re, n_im, ki_s, ko_s, h, x_in, x_out, white=white, films=films)
    return rotated_mueller_flat(params, scal, add_m00)


def _multiple_m00(ki, ko, nr, material: Material, m: Array) -> Array:
    """The multiple-scattering remainder's only non-zero entry, ``M00`` (module docstring):
    ``F_add / pi * exp(log D(k) + log D(k') - log D_avg)``, one ``exp`` of the tabulated logs
    (positive, no product of two small deficits formed, no clamp; ``k' = k`` given as the same
    array interpolates one deficit)."""
    dt = ki[0].dtype
    table = _albedo.load_table(explicit_terms())
    ci = _d3(ki, nr)
    co = ci if ko is ki else _d3(ko, nr)
    g = _grazing(dt)
    valid = (ci > g) & (co > g)
    m_mat = material.m.astype(dt)
    la = _albedo.log_deficit_avg(table, m_mat)  # material shape only (cheap)
    d_avg = jnp.exp(la)
    f_avg = fresnel_average(material, dt)
    f_add = f_avg * f_avg * (1.0 - d_avg) / (1.0 - f_avg * d_avg)
    if jnp.ndim(m_mat) == 0:
        # one material: the table's m-interpolation done once (ppr.brdf.albedo)
        def log_deficit(mu):
            return _albedo.log_deficit_one_material(table, m_mat, mu)
    else:

        def log_deficit(mu):
            return _albedo.log_deficit(table, m, mu)

    li = log_deficit(jnp.where(valid, ci, 1.0))
    lo = li if ko is ki else log_deficit(jnp.where(valid, co, 1.0))
    val = jnp.broadcast_to(f_add / math.pi, m.shape) * jnp.exp(
        li + lo - jnp.broadcast_to(la, m.shape)
    )
    return jnp.where(valid, val, 0.0)


def _unflatten(flat: Array) -> Array:
    """``(16, ...)`` -> ``(..., 4, 4)`` (one transposing copy)."""
    return jnp.moveaxis(flat, 0, -1).reshape(flat.shape[1:] + (4, 4))


_F_AVG_ORDER = 32


def fresnel_average(material: Material, dtype=None) -> Array:
    """``F_avg = 2 int_0^1 F(mu) mu dmu``, cosine-weighted hemispherical average of the
    unpolarized Fresnel reflectance (32-point Gauss-Legendre; 1 for the ideal white
    reflector). Shape of ``material.n``."""
    dt = material.dtype if dtype is None else dtype
    if material.white:
        return jnp.ones(jnp.shape(material.n), dt)
    x, w = np.polynomial.legendre.leggauss(_F_AVG_ORDER)
    mu = jnp.asarray(0.5 * (x + 1.0), dt)
    wt = jnp.asarray(w, dt)  # 0.5 (interval) * 2 (definition) = 1
    n_re = jnp.real(material.n).astype(dt)[..., None]
    n_im = jnp.imag(material.n).astype(dt)[..., None]
    films = films_of(material, dt)
    if films is None:
        a, _, _, _ = fresnel_mueller_params(n_re, n_im, mu)
        return jnp.sum(a * mu * wt, axis=-1)
    shape = jnp.broadcast_shapes(
        jnp.shape(material.n), *(jnp.shape(x) for x in jax.tree.leaves(films))
    )
    films = jax.tree.map(lambda a: jnp.broadcast_to(a, shape)[..., None], films)
    n_re, n_im = (jnp.broadcast_to(a[..., 0], shape)[..., None] for a in (n_re, n_im))
    a, _, _, _ = facet_params(n_re, n_im, mu, films)
    return jnp.sum(a * mu * wt, axis=-1)


# ---------------------------------------------------------------------------------------
# exact monostatic backscatter (k_out is k_in)

MONO_TERMS = frozenset({"single", "multiple", "double", "double:backscatter"})
"""Terms the exact-backscatter kernel :func:`_mono_core` evaluates (``"double:auto"`` takes
the general kernel, with ``k_out`` the same array as ``k_in``)."""

# diag(1, 1, -1, -1) and e_00 as row-major (16,) patterns
_DIAG_MIRROR = np.diag([1.0, 1.0, 0.0, 0.0]).reshape(16)
_DIAG_CROSS = np.diag([0.0, 0.0, 1.0, 1.0]).reshape(16)
_E00 = np.eye(16)[0]


def _mono_core(k_in, normal, material, frame_in, frame_out, wavelength, names) -> Array:
    """The BRDF at exact backscatter ``k_out = k_in`` in the shared frames ``e = normalize(n x
    k)`` of the beams (input along ``-k``, output along ``+k``), then one rotation into the
    caller's frames (none for the default frames, which are ``-e`` and ``e``: a half turn).

    In those frames, with ``h = k`` every term is a function of ``c = k.n`` alone:

    - single: the facet is seen at normal incidence, ``F_M = [[a, b, 0, 0], [b, a, 0, 0],
      [0, 0, c, d], [0, 0, -d, c]]`` at ``cos = 1`` (``b = d = 0``, ``c = -a``: the mirror's
      ``diag(1, 1, -1, -1)``), times ``p(k) P(k) / (4 <h.n> c^2)`` (the joint visibility of
      identical directions is ``P(k)``; azimuth factor 1);
    - multiple: ``F_add D(c)^2 / (pi D_avg)`` on ``M00``, one deficit instead of two;
    - double: the exact-backscatter table (:func:`ppr.brdf.double_table.backscatter_local`) with
      the coherent enhancement ``1 + gamma(0) = 2``.

    Same model as the general kernel (:func:`_brdf_core` with separate ``k_in`` and ``k_out``
    arrays); the two agree to rounding (tests/test_brdf.py::test_monostatic_kernel_*)."""
    del wavelength  # gamma(0) = 1 for every wavelength and correlation length
    dt = k_in.dtype
    batch = k_in.shape[:-1]
    ki, nr = _split(k_in), _split(normal)
    m, n_re, n_im = _material_batch(material, batch, dt)
    m0 = material.m.astype(dt)
    c = _d3(ki, nr)
    valid = c > _grazing(dt)
    c_s = jnp.where(valid, c, 1.0)
    mirror = None  # coefficient of diag(1, 1, 0, 0), (...,)
    cross = None  # coefficient of diag(0, 0, 1, 1)
    m00 = None
    if "single" in names:
        v = _visibility_over_cos(m, m0, c_s)
        # p(h) P(k) / c^2 = p V / c in log space (float32: c ~ 1e-20 at grazing), its 1 / c
        # held at _c_cap as in the general kernel
        log_s = (
            jnp.log((m + 1.0) / (2.0 * math.pi))
            + _log_lobe3(m, ki, nr)
            + jnp.log(jnp.maximum(v, tiny(dt)))
            - _log_capped(c_s)
        )
        scal = jnp.where(valid, jnp.exp(log_s) / (4.0 * mean_cosine_n(m)), 0.0)
        if material.white:
            a0, c0 = 1.0, -1.0
        elif material.films:
            one = jnp.ones((), dt)
            a0, _, c0, _ = facet_params(
                jnp.real(material.n).astype(dt),
                jnp.imag(material.n).astype(dt),
                one,
                films_of(material, dt),
            )
        else:
            one = jnp.ones((), dt)
            a0, _, c0, _ = fresnel_mueller_params(
                jnp.real(material.n).astype(dt), jnp.imag(material.n).astype(dt), one
            )
        mirror, cross = scal * a0, scal * c0
    if "multiple" in names:
        m00 = _multiple_m00(ki, ki, nr, material, m)
    out = None
    if "double" in names or "double:backscatter" in names:
        out = backscatter_local(ki, nr, material, m, dt, batch, 2.0)[0]
    cols = []
    pats = []
    for coef, pat in ((mirror, _DIAG_MIRROR), (cross, _DIAG_CROSS), (m00, _E00)):
        if coef is not None:
            cols.append(jnp.broadcast_to(coef, batch))
            pats.append(pat)
    if cols:
        # the diagonal terms as one (..., 3) @ (3, 16) dot: XLA CPU stores its result (written
        # as broadcast products, the frame rotation re-computed them per entry: 1.4-2.5x
        # slower with frames, measured)
        diag = jnp.stack(cols, axis=-1) @ jnp.asarray(np.stack(pats), dt)
        out = diag if out is None else out + diag
    e = _default_frame3(ki, nr)
    if frame_in is None and frame_out is None:
        return jnp.where(valid[..., None], out, 0.0).reshape(batch + (4, 4))
    fi = _neg3(e) if frame_in is None else _split(frame_in)
    fo = e if frame_out is None else _split(frame_out)
    return rotate_local(out, valid, e, e, ki, ki, fi, fo)


# ---------------------------------------------------------------------------------------
# terms (registry contract, docs/DESIGN.md: arrays (..., 3) in, (..., 4, 4) out)


def _material_batch(material: Material, batch, dt):
    m = jnp.broadcast_to(material.m.astype(dt), batch)
    n = jnp.broadcast_to(material.n, batch)
    return m, jnp.real(n).astype(dt), jnp.imag(n).astype(dt)


def single_bounce_term(
    k_in: Float[Array, "*b 3"],
    k_out: Float[Array, "*b 3"],
    normal: Float[Array, "*b 3"],
    material: Material,
    frame_in: Float[Array, "*b 3"],
    frame_out: Float[Array, "*b 3"],
    *,
    wavelength: float | Array = DEFAULT_WAVELENGTH_M,
) -> Float[Array, "*b 4 4"]:
    """Single-bounce APS term (module docstring). Inputs broadcast, unit and validated
    (by :func:`mueller_brdf`); ``material`` fields broadcast against the batch shape."""
    del wavelength
    dt = k_in.dtype
    batch = k_in.shape[:-1]
    m, n_re, n_im = _material_batch(material, batch, dt)
    flat = _single_flat(
        _split(k_in),
        _split(k_out),
        _split(normal),
        m,
        n_re,
        n_im,
        _split(frame_in),
        _split(frame_out),
        material.white,
        m0=material.m.astype(dt),
        films=films_of(material, dt, batch),
    )
    return _unflatten(flat)


def multiple_scattering_term(
    k_in: Float[Array, "*b 3"],
    k_out: Float[Array, "*b 3"],
    normal: Float[Array, "*b 3"],
    material: Material,
    frame_in: Float[Array, "*b 3"],
    frame_out: Float[Array, "*b 3"],
    *,
    wavelength: float | Array = DEFAULT_WAVELENGTH_M,
) -> Float[Array, "*b 4 4"]:
    """Depolarizing multiple-scattering remainder (module docstring), ``diag(f_ms, 0, 0, 0)``."""
    del wavelength, frame_in, frame_out
    dt = k_in.dtype
    batch = k_in.shape[:-1]
    m, _, _ = _material_batch(material, batch, dt)
    f = _multiple_m00(_split(k_in), _split(k_out), _split(normal), material, m)
    flat = jnp.zeros((16,) + batch, dt).at[0].set(f)
    return _unflatten(flat)


def _double_term(
    k_in, k_out, normal, material, frame_in, frame_out, *, wavelength=DEFAULT_WAVELENGTH_M
):
    return double_term_dispatch(
        k_in, k_out, normal, material, frame_in, frame_out, wavelength=wavelength
    )


def _double_backscatter_term(
    k_in, k_out, normal, material, frame_in, frame_out, *, wavelength=DEFAULT_WAVELENGTH_M
):
    return double_backscatter_term(
        k_in, k_out, normal, material, frame_in, frame_out, wavelength=wavelength
    )


# the quadrature branch of the dispatch, decided when the term is named
_double_quadrature_term = functools.partial(double_term_dispatch, branch="quadrature")


def _double_auto_term(
    k_in, k_out, normal, material, frame_in, frame_out, *, wavelength=DEFAULT_WAVELENGTH_M
):
    return double_bounce_term_auto(
        k_in, k_out, normal, material, frame_in, frame_out, wavelength=wavelength
    )


TermFn = Callable[..., Array]

TERMS: dict[str, TermFn] = {
    "single": single_bounce_term,
    "double": _double_term,
    "multiple": multiple_scattering_term,
    "double:backscatter": _double_backscatter_term,
    "double:quadrature": _double_quadrature_term,
}
"""Term registry: name -> ``term(k_in, k_out, normal, material, frame_in, frame_out, *,
wavelength) -> (..., 4, 4)`` (contract in docs/DESIGN.md). ``"double"`` uses the
exact-backscatter table of :mod:`ppr.brdf.double_table` when every element of the batch is
within ``PSI_MAX`` (1e-3 rad) of backscatter and the quadrature otherwise;
``"double:backscatter"`` forces the table (inputs beyond ``PSI_MAX`` are an error): a
caller that knows its geometry is monostatic (``ppr.render`` for a monostatic sensor) uses it
to keep the quadrature out of the compiled program; ``"double:quadrature"`` forces the
quadrature (any geometry, exact at backscatter too): a caller whose geometry is known to be
bistatic (``ppr.render`` for a bistatic sensor beyond ``PSI_MAX``) or mixed uses it to keep the
table branch, and its ``lax.cond``, out of a traced program (a ``lax.cond`` compiles and
differentiates both branches: the gradient of a bistatic batch traces 3-4x faster without it,
docs/benchmarks.md "Compilation")."""

EXPLICIT_TERMS = ("single", "double")
"""Terms computed explicitly; ``"multiple"`` is the white-furnace remainder of those
implemented (:func:`explicit_terms`)."""


def _is_implemented(name: str) -> bool:
    return name in TERMS


def implemented_terms() -> tuple[str, ...]:
    """Names of the terms available now (the default of ``mueller_brdf(terms=None)``)."""
    return tuple(t for t in ("single", "double", "multiple") if _is_implemented(t))


def explicit_terms() -> tuple[str, ...]:
    """Explicit terms of the model whose white albedo the ``"multiple"`` remainder completes
    (``("double", "single")``)."""
    return tuple(sorted(t for t in EXPLICIT_TERMS if _is_implemented(t)))


def _resolve_terms(terms) -> tuple[str, ...]:
    if terms is None:
        return implemented_terms()
    if isinstance(terms, str):
        if terms == "auto":
            # the double term is kept only where its measured contribution exceeds the rule's
            # tolerance (ppr/brdf/double.py: AUTO_TOL, AUTO_M_MAX; docs/double_bounce_table.md)
            return tuple("double:auto" if t == "double" else t for t in implemented_terms())
        terms = (terms,)
    terms = tuple(terms)
    if len(terms) == 0:
        raise ValueError("terms must name at least one term, got ()")
    for t in terms:
        if t not in TERMS:
            raise ValueError(f"terms: unknown term {t!r}; choose from {tuple(TERMS)} or 'auto'")
    if len(set(terms)) != len(terms):
        raise ValueError(f"terms: duplicate names in {terms!r}")
    doubles = [t for t in terms if t in ("double", "double:backscatter", "double:quadrature")]
    if len(doubles) > 1:
        raise ValueError(
            f"terms: {' and '.join(map(repr, doubles))} are the same term, got {terms!r}"
        )
    return terms


# ---------------------------------------------------------------------------------------
# validation


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _as_vec(name: str, x, dt=None) -> Array:
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise ValueError(f"{name} must be real, got dtype {x.dtype}")
    if x.ndim < 1 or x.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got shape {x.shape}")
    if dt is not None:
        x = x.astype(dt)
    return x


def _check(name: str, x: Array, bad: Array, msg: str, errors: list | None = None) -> Array:
    """Raise (concrete) when ``bad`` is anywhere true; traced: append ``(any(bad), message)``
    to ``errors`` (attached to the result by :func:`_attach_errors`), or attach
    ``eqx.error_if`` to ``x`` when no list is given."""
    if _is_concrete(x) and _is_concrete(bad):
        b = np.asarray(bad)
        if np.any(b):
            idx = tuple(int(i) for i in np.argwhere(b)[0]) if b.ndim else ()
            raise ValueError(f"{name}: {msg} (first offending index {idx})")
        return x
    if errors is not None:
        errors.append((jnp.any(bad), f"{name}: {msg}"))
        return x
    return eqx.error_if(x, jnp.any(bad), f"{name}: {msg}")


def _attach_errors(out: Array, errors: list) -> Array:
    """One ``eqx.branched_error_if`` on the result for the traced input checks: the first
    failing check's message is raised and no result is returned. Gating the *inputs*
    instead (an ``error_if`` on ``k_in`` depending on a reduction over the batch) made the
    whole BRDF ~1.7x slower on XLA CPU (measured, 250k evaluations)."""
    if not errors:
        return out
    preds = jnp.stack([b for b, _ in errors])
    return eqx.branched_error_if(out, jnp.any(preds), jnp.argmax(preds), [m for _, m in errors])


def _norm3(k: Array) -> Array:
    """``|k|`` of a ``(..., 3)`` array by component arithmetic (a trailing-axis reduction ran
    ~5x slower on XLA CPU)."""
    return jnp.sqrt(k[..., 0] * k[..., 0] + k[..., 1] * k[..., 1] + k[..., 2] * k[..., 2])


def _validate_direction(
    name: str, k: Array, normal: Array | None, errors: list | None = None
) -> Array:
    finite = jnp.isfinite(k[..., 0]) & jnp.isfinite(k[..., 1]) & jnp.isfinite(k[..., 2])
    k = _check(name, k, ~finite, "must be finite", errors)
    norm = _norm3(k)
    k = _check(
        name,
        k,
        jnp.abs(norm - 1.0) > UNIT_TOL,
        f"must be unit vectors (| |k| - 1 | <= {UNIT_TOL}), got |k| = "
        + (f"{np.asarray(norm).ravel()[:4]}" if _is_concrete(norm) else "(traced)"),
        errors,
    )
    inv = 1.0 / jnp.where(norm > 0.5, norm, 1.0)
    k = _stack3(tuple(k[..., i] * inv for i in range(3)))
    if normal is not None:
        c = _d3(_split(k), _split(normal))
        k = _check(
            name,
            k,
            c < -HORIZON_TOL,
            f"points below the surface (k.normal < -{HORIZON_TOL}); directions point away "
            "from the surface (ppr.optics.conventions)",
            errors,
        )
    return k


def _validate_frame(name: str, x: Array, d: Array, errors: list | None = None) -> Array:
    finite = jnp.isfinite(x[..., 0]) & jnp.isfinite(x[..., 1]) & jnp.isfinite(x[..., 2])
    x = _check(name, x, ~finite, "must be finite", errors)
    norm = _norm3(x)
    x = _check(
        name, x, jnp.abs(norm - 1.0) > UNIT_TOL, f"must be unit (tolerance {UNIT_TOL})", errors
    )
    x3, d3 = _split(x), _split(d)
    xd = _d3(x3, d3)
    x = _check(
        name,
        x,
        jnp.abs(xd) > UNIT_TOL,
        f"must be perpendicular to its beam direction (|x.k| <= {UNIT_TOL})",
        errors,
    )
    x3 = tuple(a - xd * b for a, b in zip(_split(x), d3, strict=True))
    inv = 1.0 / jnp.sqrt(_d3(x3, x3))
    return _stack3(tuple(a * inv for a in x3))


def _validate_material(material: Material, errors: list | None = None) -> Material:
    if not isinstance(material, Material):
        raise ValueError(f"material must be a ppr.Material, got {type(material).__name__}")
    m = material.m
    n = material.n
    m = _check("material.m", m, ~jnp.isfinite(m), "must be finite", errors)
    m = _check("material.m", m, m < 0, "Blinn-Phong exponent must be >= 0", errors)
    if not material.white:
        n = _check("material.n", n, ~jnp.isfinite(n), "must be finite", errors)
        n = _check(
            "material.n",
            n,
            jnp.imag(n) < 0,
            "imaginary part must be >= 0 (absorbing medium, exp(i(kz - wt)) convention)",
            errors,
        )
    out = eqx.tree_at(lambda mt: (mt.m, mt.n), material, (m, n))
    if not material.films:
        return out
    films = []
    for i, (fn, ft) in enumerate(material.films):
        name = f"material.films[{i}]"
        fn = _check(name, fn, ~jnp.isfinite(fn), "index must be finite", errors)
        fn = _check(name, fn, jnp.imag(fn) < 0, "index must have n'' >= 0", errors)
        fn = _check(name, fn, jnp.real(fn) <= 0, "index must have n' > 0", errors)
        ft = _check(name, ft, ~(ft >= 0), "thickness must be finite and >= 0 metres", errors)
        ft = _check(name, ft, ~jnp.isfinite(ft), "thickness must be finite", errors)
        films.append((fn, ft))
    lam = material.wavelength
    lam = _check("material.wavelength", lam, ~(lam > 0), "must be > 0 metres", errors)
    return eqx.tree_at(lambda mt: (mt.films, mt.wavelength), out, (tuple(films), lam))


# ---------------------------------------------------------------------------------------
# public API


def mueller_brdf(
    k_in: Any,
    k_out: Any,
    normal: Any,
    material: Material,
    *,
    terms: tuple[str, ...] | str | None = None,
    frame_in: Any = None,
    frame_out: Any = None,
    wavelength: float | Array = DEFAULT_WAVELENGTH_M,
    traced_checks: bool = True,
) -> Float[Array, "... 4 4"]:
    """Polarized microfacet Mueller BRDF (1/sr), ``S_out = M @ S_in``.

    **Arguments:**

    - `k_in`: unit direction from the surface toward the source, ``(..., 3)`` (array-like;
      shapes are checked here, with errors naming the argument, not by the annotation).
    - `k_out`: unit direction from the surface toward the receiver, ``(..., 3)``; exact
      monostatic backscatter is ``k_out == k_in``: pass the same array for the
      exact-backscatter kernel (module docstring, "Exact backscatter").
    - `normal`: unit macro-surface normal, ``(..., 3)``.
    - `material`: :class:`ppr.Material` (fields may carry batch axes that broadcast with the
      directions' batch shape).
    - `terms`: names from ``"single"``, ``"double"``, ``"multiple"`` (default: all implemented),
      or ``"auto"``; ``"double:backscatter"`` is the double term from the exact-backscatter
      table only (bistatic angle <= ``ppr.BACKSCATTER_PSI_MAX`` = 1e-3 rad, else an error),
      ``"double:quadrature"`` from the quadrature only (any geometry; a traced call then
      compiles no table branch; :data:`TERMS`).
      ``"multiple"`` is always the remainder of the model's full set of explicit terms.
    - `frame_in`: x axis of the incident beam's Stokes frame (beam along ``-k_in``); default
      :func:`ppr.optics._frames.default_frame` (the s direction ``normal x d``).
    - `frame_out`: x axis of the outgoing beam's Stokes frame (beam along ``+k_out``); same
      default.
    - `wavelength`: metres (used by the double-bounce coherence).
    - `traced_checks`: attach the checks of *traced* inputs to the result (module docstring,
      "Validation"). Concrete inputs are always checked. ``False`` is for kernels whose
      inputs are valid by construction (:func:`mueller_brdf_unchecked`): the checks are an
      ``equinox`` host callback, and JAX does not store programs with host callbacks in its
      persistent compilation cache.

    **Returns:** ``(..., 4, 4)`` in the common float dtype of the directions and the material.
    Validation and tolerances: see the module docstring.

    Model: Ashikhmin, Premoze & Shirley (2000) single bounce with facet Fresnel Mueller
    matrices, plus the energy-conserving depolarizing remainder (Kulla & Conty 2017).
    """
    names = _resolve_terms(terms)
    if not isinstance(material, Material):
        raise ValueError(f"material must be a ppr.Material, got {type(material).__name__}")
    mono = _same_direction(k_in, k_out)
    dt = float_dtype(
        jnp.asarray(k_in), jnp.asarray(k_out), jnp.asarray(normal), material.m, material.n
    )
    k_in = _as_vec("k_in", k_in)
    k_out = _as_vec("k_out", k_out)
    normal = _as_vec("normal", normal)
    shapes = {"k_in": k_in.shape, "k_out": k_out.shape, "normal": normal.shape}
    if frame_in is not None:
        frame_in = _as_vec("frame_in", frame_in)
        shapes["frame_in"] = frame_in.shape
    if frame_out is not None:
        frame_out = _as_vec("frame_out", frame_out)
        shapes["frame_out"] = frame_out.shape
    try:
        batch = jnp.broadcast_shapes(*(s[:-1] for s in shapes.values()))
    except ValueError as err:
        raise ValueError(
            f"k_in, k_out, normal, frames: batch shapes do not broadcast: {shapes}"
        ) from err
    try:
        batch = jnp.broadcast_shapes(
            batch, *(jnp.shape(a) for a in jax.tree.leaves(material) if jnp.ndim(a) > 0)
        )
    except ValueError as err:
        raise ValueError(
            f"material: field shapes m {jnp.shape(material.m)}, n {jnp.shape(material.n)} "
            f"(and film layers) do not broadcast with the directions' batch shape {batch}"
        ) from err
    if _is_concrete(wavelength):
        w = np.asarray(wavelength, np.float64)
        if not np.all(np.isfinite(w)) or np.any(w <= 0) or np.any(w > 1e-3):
            # the coherent backscatter peak and film phases scale with it: NaN, 0 or
            # nanometres would give NaN or a silently wrong BRDF
            raise ValueError(
                f"wavelength must be a finite length in metres (e.g. 532e-9), got "
                f"{w.ravel()[:4].tolist()}"
            )
    _check_film_wavelength(material, wavelength)
    inputs = (k_in, k_out, normal, frame_in, frame_out, material)
    static = dict(names=names, dt=np.dtype(dt).name, batch=tuple(batch))
    if all(_is_concrete(x) for x in jax.tree_util.tree_leaves((inputs, wavelength))):
        # concrete inputs: the checks and the normalization in one jitted program per shape
        # (as eager jnp ops they compiled 20-45 one-op programs, 0.5-1.2 s, on every new
        # shape); a failing check is re-run eagerly, which raises with the details. The
        # batch is flattened and padded to a bucket size (module docstring, "Eager calls"),
        # so the BRDF itself compiles once per bucket, not once per batch shape
        size = eager_bucket(math.prod(batch)) if np.ndim(wavelength) == 0 else None
        prepared, bad = _prepare_jit(*inputs, **static, size=size)
        if np.any(np.asarray(bad)):
            _prepare(*inputs, **static, errors=None)
        out = _brdf_core(
            *prepared[:3],
            prepared[5],
            *prepared[3:5],
            wavelength,
            names=_double_branch_on_host(names, prepared[0], prepared[1], prepared[5].m),
            mono=mono,
        )
        return out if size is None else _unpad_jit(out, batch=tuple(batch))
    else:
        errors: list = []  # traced checks, attached to the result (_attach_errors)
        k_in, k_out, normal, frame_in, frame_out, material = _prepare(
            *inputs, **static, errors=errors
        )
    out = _brdf_core(
        k_in, k_out, normal, material, frame_in, frame_out, wavelength, names=names, mono=mono
    )
    return _attach_errors(out, errors) if traced_checks else out


def _check_film_wavelength(material: Material, wavelength) -> None:
    """A coated material's layers were given at ``material.wavelength``; a concrete BRDF
    wavelength must match it (within 1e-6 relative)."""
    if not material.films or not (_is_concrete(wavelength) and _is_concrete(material.wavelength)):
        return
    lam = np.asarray(material.wavelength, np.float64)
    w = np.asarray(wavelength, np.float64)
    if np.any(np.abs(lam - w) > 1e-6 * np.abs(w)):
        raise ValueError(
            f"material.wavelength = {lam.ravel()[:4]} m (its film stack) differs from the "
            f"BRDF's wavelength = {w.ravel()[:4]} m; build the material at the wavelength "
            "it is rendered at (ppr.load_material(name, wavelength))"
        )


def _same_direction(k_in, k_out) -> bool:
    """``k_out`` is exactly ``k_in``: the same object (array or tracer), or concrete arrays of
    one shape with equal entries (module docstring, "Exact backscatter")."""
    if k_out is k_in:
        return True
    if not (_is_concrete(k_in) and _is_concrete(k_out)):
        return False
    a, b = np.asarray(k_in), np.asarray(k_out)
    return a.shape == b.shape and a.dtype == b.dtype and bool(np.array_equal(a, b))


def _double_branch_on_host(names: tuple[str, ...], k_in, k_out, m) -> tuple[str, ...]:
    """``names`` with the double term's run-time decisions taken on the host, for concrete
    (prepared) inputs: ``"double:auto"`` is dropped where no element needs it
    (:func:`ppr.brdf.double.double_needed`), and ``"double"`` becomes the backscatter table
    (``"double:backscatter"``) when every element is within ``PSI_MAX`` of backscatter, else
    the quadrature (``"double:quadrature"``, internal). The same choices as the traced
    ``lax.cond``s of :func:`ppr.brdf.double_table.double_term_dispatch` and
    :func:`ppr.brdf.double.double_bounce_term_auto`, in NumPy on the same arrays, so the compiled
    program holds only the branch this call takes (a ``lax.cond`` compiles both)."""
    if "double" not in names and "double:auto" not in names:
        return names
    dk = np.asarray(k_out) - np.asarray(k_in)
    q2 = dk[..., 0] * dk[..., 0] + dk[..., 1] * dk[..., 1] + dk[..., 2] * dk[..., 2]
    near = bool(np.all(q2 <= (2.0 * math.sin(0.5 * PSI_MAX)) ** 2))
    out = []
    for t in names:
        if t == "double:auto":
            far = np.sum(dk * dk, axis=-1) > (2.0 * math.sin(0.5 * AUTO_PSI_MAX)) ** 2
            if not np.any((np.asarray(m) < AUTO_M_MAX) | far):
                continue
            t = "double"
        if t == "double":
            t = "double:backscatter" if near else "double:quadrature"
        out.append(t)
    return tuple(out) if out else names


EAGER_MIN_BUCKET = 8
"""Smallest padded batch of an eager :func:`mueller_brdf` call (:func:`eager_bucket`)."""


def eager_bucket(n: int) -> int | None:
    """Padded batch size of an eager call with ``n`` evaluations: the smallest of
    ``EAGER_MIN_BUCKET`` and ``{4, 5, 6, 7} * 2^j`` that holds ``n`` (at most 25 % padding
    above 8, about 4 compiled programs per factor of 2 in batch size); ``None`` (no padding)
    for an empty batch."""
    if n <= 0:
        return None
    if n <= EAGER_MIN_BUCKET:
        return EAGER_MIN_BUCKET
    j = max((n - 1).bit_length() - 3, 0)  # n <= 8 * 2^j
    for f in (4, 5, 6, 7, 8):
        if f << j >= n:
            return f << j
    raise AssertionError(n)  # unreachable: 8 * 2^j >= n


@functools.partial(jax.jit, static_argnames=("batch",))
def _unpad_jit(out, *, batch):
    n = math.prod(batch)
    return out[:n].reshape(batch + out.shape[1:])


def _prepare(k_in, k_out, normal, frame_in, frame_out, material, *, names, dt, batch, errors):
    """Checks, casts, normalizes and broadcasts :func:`mueller_brdf`'s inputs (shapes already
    checked). Concrete inputs with ``errors=None`` raise on the first failing check; traced
    ones append ``(any(bad), message)`` to ``errors``."""
    material = _validate_material(material, errors)
    k_in, k_out, normal = (x.astype(dt) for x in (k_in, k_out, normal))
    normal = _validate_direction("normal", normal, None, errors)
    k_in = _validate_direction("k_in", k_in, normal, errors)
    k_out = _validate_direction("k_out", k_out, normal, errors)
    if "double:backscatter" in names:
        k_out = _check(
            "k_out",
            k_out,
            ~near_backscatter(k_in, k_out),
            f'terms "double:backscatter" needs a bistatic angle <= PSI_MAX = {PSI_MAX} rad '
            '(use "double")',
            errors,
        )
    k_in = jnp.broadcast_to(k_in, batch + (3,))
    k_out = jnp.broadcast_to(k_out, batch + (3,))
    normal = jnp.broadcast_to(normal, batch + (3,))
    if frame_in is not None:
        frame_in = _validate_frame(
            "frame_in", jnp.broadcast_to(frame_in.astype(dt), batch + (3,)), k_in, errors
        )
    if frame_out is not None:
        frame_out = _validate_frame(
            "frame_out", jnp.broadcast_to(frame_out.astype(dt), batch + (3,)), k_out, errors
        )
    cdt = jnp.result_type(dt, jnp.complex64)
    material = eqx.tree_at(
        lambda mt: (mt.m, mt.n), material, (material.m.astype(dt), material.n.astype(cdt))
    )
    if material.films:
        material = eqx.tree_at(
            lambda mt: (mt.films, mt.wavelength),
            material,
            (
                tuple((n.astype(cdt), t.astype(dt)) for n, t in material.films),
                material.wavelength.astype(dt),
            ),
        )
    return k_in, k_out, normal, frame_in, frame_out, material


@functools.partial(jax.jit, static_argnames=("names", "dt", "batch", "size"))
def _prepare_jit(k_in, k_out, normal, frame_in, frame_out, material, *, names, dt, batch, size):
    """:func:`_prepare` of concrete inputs as one program: the prepared inputs and the
    checks' flags (the caller raises, re-running :func:`_prepare` eagerly for the message).
    With ``size``, the batch is flattened and padded to ``size`` rows by repeating the last
    one (valid inputs: the padding rows are computed and dropped); material fields without
    batch axes stay scalars (the one-material paths)."""
    errors: list = []
    out = _prepare(
        k_in,
        k_out,
        normal,
        frame_in,
        frame_out,
        material,
        names=names,
        dt=dt,
        batch=batch,
        errors=errors,
    )
    bad = jnp.stack([b for b, _ in errors]) if errors else jnp.zeros((0,), bool)
    if size is None:
        return out, bad
    n = math.prod(batch)

    def flat(x, tail):
        x = jnp.broadcast_to(x, batch + tail).reshape((n,) + tail)
        return jnp.concatenate([x, jnp.broadcast_to(x[-1:], (size - n,) + tail)])

    *vecs, material = out
    vecs = [None if v is None else flat(v, (3,)) for v in vecs]
    # every material leaf (m, n, corr_length, film layers, wavelength) with batch axes
    material = jax.tree.map(lambda a: a if jnp.ndim(a) == 0 else flat(a, ()), material)
    return (*vecs, material), bad


def mueller_brdf_unchecked(
    k_in: Any, k_out: Any, normal: Any, material: Material, **kwargs
) -> Float[Array, "... 4 4"]:
    """:func:`mueller_brdf` with ``traced_checks=False``: for kernels whose traced inputs are
    valid by construction (the inversion's forward model: attitudes normalized, ``m = e^x``,
    ``n'' = softplus(.)``, directions from a validated sensor and mesh). Its compiled
    programs hold no host callback, so JAX's persistent compilation cache can store them
    (the ``ppr`` CLI turns that cache on). Concrete inputs are still checked."""
    return mueller_brdf(k_in, k_out, normal, material, traced_checks=False, **kwargs)


@functools.partial(jax.jit, static_argnames=("names", "mono"))
def _brdf_core(
    k_in, k_out, normal, material, frame_in, frame_out, wavelength, *, names, mono=False
):
    """Validated, broadcast inputs -> (..., 4, 4); jitted so that eager calls are fast too.
    ``mono``: ``k_out`` is ``k_in`` (exact backscatter; :func:`_mono_core` for its terms,
    else the general kernel on one array, whose duplicated work XLA then shares)."""
    if mono:
        if set(names) <= MONO_TERMS:
            return _mono_core(k_in, normal, material, frame_in, frame_out, wavelength, names)
        k_out = k_in
    dt = k_in.dtype
    batch = k_in.shape[:-1]
    ki, ko, nr = _split(k_in), _split(k_out), _split(normal)
    # frames in component form (trailing-axis-3 arithmetic is ~15x slower on XLA CPU)
    fi = _default_frame3(_neg3(ki), nr) if frame_in is None else _split(frame_in)
    fo = _default_frame3(ko, nr) if frame_out is None else _split(frame_out)
    flat = None  # (16, ...) of the single and multiple terms
    out = None
    m, n_re, n_im = _material_batch(material, batch, dt)
    f_ms = _multiple_m00(ki, ko, nr, material, m) if "multiple" in names else None
    if "single" in names:
        flat = _single_flat(
            ki,
            ko,
            nr,
            m,
            n_re,
            n_im,
            fi,
            fo,
            material.white,
            f_ms,
            material.m.astype(dt),
            films_of(material, dt, batch),
        )
    elif f_ms is not None:
        flat = jnp.zeros((16,) + batch, dt).at[0].set(f_ms)
    if "double:backscatter" in names:
        out = double_backscatter_44(
            k_in, k_out, normal, material, fi, fo, wavelength=wavelength
        ).astype(dt)
    for name in names:
        if name in ("double", "double:quadrature"):
            # frames passed as components (see double_term_dispatch); "double:quadrature":
            # the branch decided on the host (_double_branch_on_host)
            branch = "quadrature" if name == "double:quadrature" else None
            t = double_term_dispatch(
                k_in, k_out, normal, material, fi, fo, wavelength=wavelength, branch=branch
            )
            out = t if out is None else out + t
        elif name not in ("single", "multiple", "double:backscatter"):
            fn = _double_auto_term if name == "double:auto" else TERMS[name]
            t = fn(k_in, k_out, normal, material, _stack3(fi), _stack3(fo), wavelength=wavelength)
            out = t if out is None else out + t
    if flat is not None:
        r = _unflatten(flat)
        if out is not None:
            # the double term stored before the sum: XLA CPU otherwise fuses its rotation into
            # the transposing copy of the other terms (2.6 -> 4.2 M evals/s float32)
            out = store(out)
        out = r if out is None else out + r
    return out
