r"""Thin-film stacks on microfacets: the facet reflection of a coated surface.

A coated facet is a planar stack: ambient (index 1), films ``1..L`` (outermost first, complex
index ``n_j``, thickness ``t_j``), substrate (index ``n``). Its reflection in the facet's s/p
frames is ``diag(r_s, r_p)`` as for a bare interface (:mod:`ppr.optics._fresnel`), with the same
conventions (time ``exp(-i w t)``, ``Im n >= 0``, Hecht/Born-Wolf signs: a perfect conductor
is ``diag(-1, +1)``). Derivation, conventions and the thick-film criterion:
``docs/physics/thin_films.md``.

Coherent stack (Airy recursion, real arithmetic)
    With ``w_j = sqrt(n_j^2 - sin^2 t)`` (principal branch, ``Im w_j >= 0``; ``w_0 = cos t``),
    the interface ``j -> j+1`` reflects

        r_s = (w_j - w_{j+1}) / (w_j + w_{j+1}),
        r_p = (n_{j+1}^2 w_j - n_j^2 w_{j+1}) / (n_{j+1}^2 w_j + n_j^2 w_{j+1}),

    and from the substrate upward ``R_L = r_{L,L+1}``,
    ``R_{j-1} = (r_{j-1,j} + R_j z_j) / (1 + r_{j-1,j} R_j z_j)``, ``z_j = exp(2 i k0 t_j w_j)``
    (``|z_j| <= 1``: absorbing and evanescent layers decay, never grow), ``r = R_0``.

Thick layers: the lobe average
    A layer whose round-trip phase ``psi = 2 k0 t Re w`` varies over the microfacet lobe by
    more than ``THICK_SPREAD`` (fringes in facet angle narrower than the lobe: tens of
    micrometres of Kapton) is *thick*. The stack splits there into a top part (reflection
    ``r_T`` from above, ``r'_T`` from inside the layer, ``P_T = t_T t'_T``) and the bottom
    part's reflection ``R_B`` seen from inside the layer, so that
    ``r = r_T + A z / (1 - B z)`` with ``A = P_T R_B``, ``B = r'_T R_B``, i.e.
    ``r = sum_k a_k z^k`` (``a_0 = r_T``, ``a_k = A B^(k-1)``). The facet's second moments
    ``G_xy = <r_x r_y^*>`` (``x, y`` in ``s, p``) over the lobe's facet tilts, with the
    interface coefficients at the nominal facet and the phase perturbed, are

        G_xy = sum_q chi(q) C_q^xy z^q,   chi(q) = <exp(i q (psi' - psi))>,

    a Fourier series whose coefficients ``C_q`` are geometric in ``q`` (closed forms below).
    Over the Blinn-Phong lobe the facet tilt is, to leading order in ``1/m``, Gaussian with
    variance ``v = 1/(m+1)`` per axis (``x`` in the plane of incidence, ``y`` across it), and
    ``psi`` is linear in ``u = cos^2 t`` (``w^2 = n^2 - 1 + u``: no stationary point at
    grazing, unlike ``cos t``), slope ``g_u``. Then ``u' - u = 2 c s x + (s^2 - c^2) x^2 -
    c^2 y^2`` is a Gaussian quadratic form and, with ``l = q g_u``,

        chi(q) = exp(-2 l^2 c^2 s^2 v / p_x) / sqrt(p_x p_y),
        p_x = 1 - 2 i l (s^2 - c^2) v,   p_y = 1 + 2 i l c^2 v.

    Modes (``Material.film_mode``): ``"coherent"`` (no average: ``chi = 1``),
    ``"incoherent"`` (a uniformly distributed phase, ``chi(q != 0) = 0``: the incoherent sum
    of the layer's multiple reflections, also right where the source's coherence length is
    below the round-trip path ``2 n t``), ``"lobe"`` (the series above to ``LOBE_TERMS``
    terms, the rest as a geometric tail at ``chi(Q+1)``), ``"auto"`` (coherent unless a layer
    is thick, then ``"lobe"`` for that layer). A thick facet is partially depolarizing:
    its Mueller parameters ``(a, b, c, d)`` come from ``G`` (``a = (G_ss + G_pp)/2``,
    ``b = (G_ss - G_pp)/2``, ``c + i d = G_sp``), and where a Jones chain is needed (the
    double bounce) from two incoherent Jones components with the same ``G``
    (:func:`facet_components`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._safe import safe_atan2, tiny
from .._types import Array
from ._fresnel import _cdiv, complex_sqrt_re, fresnel_amplitudes_re, fresnel_mueller_params

__all__ = [
    "FILM_MODES",
    "Films",
    "LOBE_TERMS",
    "THICK_SPREAD",
    "facet_amplitudes",
    "facet_components",
    "facet_gram",
    "facet_mueller_params",
    "facet_params",
    "films_of",
    "lobe_chi",
    "phase_spread",
    "resolve_film_mode",
    "stack_amplitudes",
    "stack_transmission",
]

FILM_MODES = ("auto", "coherent", "incoherent", "lobe")
"""Values of ``Material.film_mode`` (module docstring)."""

THICK_SPREAD = 0.5 * math.pi
"""A layer is thick when the standard deviation of its round-trip phase over the lobe
(:func:`phase_spread`) exceeds this somewhere in incidence (a quarter fringe per lobe width)."""

LOBE_TERMS = 12
"""Terms of the lobe-averaged Fourier series kept explicitly (``"lobe"`` mode)."""

# --------------------------------------------------------------------------------------------
# complex arithmetic on (re, im) pairs


def _add(a, b):
    return (a[0] + b[0], a[1] + b[1])


def _sub(a, b):
    return (a[0] - b[0], a[1] - b[1])


def _mul(a, b):
    return (a[0] * b[0] - a[1] * b[1], a[0] * b[1] + a[1] * b[0])


def _mulc(a, b):
    """``a b^*``."""
    return (a[0] * b[0] + a[1] * b[1], a[1] * b[0] - a[0] * b[1])


def _conj(a):
    return (a[0], -a[1])


def _div(a, b):
    return _cdiv(a[0], a[1], b[0], b[1])


def _scale(s, a):
    return (s * a[0], s * a[1])


def _abs2(a):
    return a[0] * a[0] + a[1] * a[1]


def _one_minus(a):
    return (1.0 - a[0], -a[1])


def _one_plus(a):
    return (1.0 + a[0], a[1])


# --------------------------------------------------------------------------------------------
# the stack description passed through the kernels


class Films(eqx.Module):
    """The film layers of a facet as the kernels use them: per layer (outermost first) the
    real and imaginary index and ``k0 t = 2 pi t / lambda``, each an array broadcastable
    with the substrate's ``n_re`` (kernels transform them with ``jax.tree.map`` alongside
    it), plus the lobe exponent ``m`` of the thick-layer average. Static: the resolved
    ``mode`` (``"coherent"``, ``"incoherent"`` or ``"lobe"``) and the ``thick`` layer's
    index (-1 when coherent)."""

    n_re: tuple
    n_im: tuple
    kt: tuple
    m: Array
    mode: str = eqx.field(static=True, default="coherent")
    thick: int = eqx.field(static=True, default=-1)

    @property
    def n_layers(self) -> int:
        return len(self.n_re)

    @property
    def coherent(self) -> bool:
        return self.mode == "coherent" or self.thick < 0


def films_of(material, dt, batch=None) -> Films | None:
    """:class:`Films` of a :class:`ppr.Material` in float dtype ``dt`` (None for a bare or
    ideal white material), leaves broadcast to ``batch`` if given."""
    layers = getattr(material, "films", ())
    if not layers or getattr(material, "white", False):
        return None
    lam = jnp.asarray(material.wavelength).astype(dt)
    n_re = tuple(jnp.real(n).astype(dt) for n, _ in layers)
    n_im = tuple(jnp.imag(n).astype(dt) for n, _ in layers)
    kt = tuple((2.0 * math.pi) * jnp.asarray(t).astype(dt) / lam for _, t in layers)
    out = Films(
        n_re,
        n_im,
        kt,
        jnp.asarray(material.m).astype(dt),
        mode=material.film_mode,
        thick=material.thick_layer,
    )
    if batch is not None:
        out = jax.tree.map(lambda a: jnp.broadcast_to(a, batch), out)
    return out


# --------------------------------------------------------------------------------------------
# media and interfaces


def _w(n_re, n_im, c2):
    """``w = sqrt(n^2 - 1 + cos^2)`` (same arithmetic as :mod:`ppr.optics._fresnel`: ``n = 1``
    gives ``w = cos`` exactly)."""
    w2_re = (n_re - 1.0) * (n_re + 1.0) - n_im * n_im + c2
    w2_im = 2.0 * n_re * n_im
    return complex_sqrt_re(w2_re, w2_im)


def _eps(n_re, n_im):
    return (n_re * n_re - n_im * n_im, 2.0 * n_re * n_im)


def _r(eta_a, eta_b):
    """Interface reflection from medium ``a`` into ``b`` for both polarizations at once
    (leading axis: s, p), from the tilted admittances ``eta = (w, w / n^2)``:
    ``r = (eta_a - eta_b) / (eta_a + eta_b)`` (for p this is
    ``(n_b^2 w_a - n_a^2 w_b) / (n_b^2 w_a + n_a^2 w_b)``)."""
    return _div(_sub(eta_a, eta_b), _add(eta_a, eta_b))


def _phase(kt, w):
    """``z = exp(2 i k0 t w)`` (``|z| <= 1`` for ``Im w >= 0``)."""
    mag = jnp.exp(-2.0 * kt * w[1])
    arg = 2.0 * kt * w[0]
    return (mag * jnp.cos(arg), mag * jnp.sin(arg))


def _sp(a):
    """A polarization-independent ``(re, im)`` broadcast against the (s, p) axis."""
    return (a[0][None], a[1][None])


def _media(n_re, n_im, films: Films, cos_t):
    """``(eta, w, kt, cos)``: per medium (ambient, films, substrate) the admittances
    ``eta`` (``(2, ...)``: s, p) and ``w`` (``(...)``), per film ``k0 t``."""
    shape = jnp.broadcast_shapes(
        jnp.shape(n_re), jnp.shape(cos_t), *(jnp.shape(a) for a in jax.tree.leaves(films))
    )
    dt = jnp.result_type(n_re, cos_t)
    b = lambda a: jnp.broadcast_to(jnp.asarray(a, dt), shape)  # noqa: E731
    c = b(cos_t)
    c2 = c * c
    zero = jnp.zeros(shape, dt)
    ws = [(c, zero)]
    etas = [(jnp.stack([c, c]), jnp.stack([zero, zero]))]
    for fr, fi in [*zip(films.n_re, films.n_im, strict=True), (n_re, n_im)]:
        nr, ni = b(fr), b(fi)
        w = _w(nr, ni, c2)
        wp = _div(w, _eps(nr, ni))
        ws.append(w)
        etas.append((jnp.stack([w[0], wp[0]]), jnp.stack([w[1], wp[1]])))
    kt = [b(k) for k in films.kt]
    return etas, ws, kt, c


def _airy_up(etas, ws, kt, top: int):
    """Reflection ``R`` (``(2, ...)``: s, p) seen from medium ``top`` looking down (media
    ``top+1``..), by the Airy recursion from the substrate (module docstring)."""
    last = len(ws) - 1
    R = _r(etas[last - 1], etas[last])
    for j in range(last - 1, top, -1):  # film medium j (1-based), above it medium j - 1
        z = _sp(_phase(kt[j - 1], ws[j]))
        r = _r(etas[j - 1], etas[j])
        zR = _mul(R, z)
        R = _div(_add(r, zR), _one_plus(_mul(r, zR)))
    return R


def _star_down(etas, ws, kt, bottom: int):
    """Top part from the ambient down to medium ``bottom``: ``(r, r', P)`` (reflection from
    above, from below, and ``t t'``; each ``(2, ...)``: s, p), by adding one layer and
    interface at a time (Redheffer star product)."""
    r = _r(etas[0], etas[1])
    rb, P = (-r[0], -r[1]), _one_minus(_mul(r, r))
    for j in range(1, bottom):
        z = _sp(_phase(kt[j - 1], ws[j]))
        ri = _r(etas[j], etas[j + 1])
        Pi = _one_minus(_mul(ri, ri))
        D = _one_minus(_mul(_mul(rb, ri), z))
        r = _add(r, _div(_mul(_mul(P, ri), z), D))
        rb = _sub(_div(_mul(_mul(Pi, rb), z), D), ri)
        P = _div(_mul(_mul(P, Pi), z), _mul(D, D))
    return r, rb, P


# --------------------------------------------------------------------------------------------
# public kernels


def stack_amplitudes(n_re, n_im, films: Films, cos_t):
    """Coherent stack reflection ``(rs_re, rs_im, rp_re, rp_im)`` at facet cosine ``cos_t``
    (Airy recursion; every layer coherent whatever ``films.mode``)."""
    etas, ws, kt, _ = _media(n_re, n_im, films, cos_t)
    R = _airy_up(etas, ws, kt, 0)
    return R[0][0], R[1][0], R[0][1], R[1][1]


def phase_spread(kt, n_re, n_im, m, cos_t):
    """Standard deviation (radians) of a layer's round-trip phase ``psi = 2 k0 t Re w`` over
    the facet tilts of a Blinn-Phong lobe of exponent ``m`` at facet cosine ``cos_t``, with
    ``psi`` linear in ``u = cos^2 t`` (slope ``g_u = k0 t Re(1/w)``) and Gaussian tilts of
    variance ``v = 1/(m+1)`` per axis: ``|g_u| sqrt(4 c^2 s^2 v + 2 ((s^2 - c^2)^2 + c^4) v^2)``
    (module docstring). NumPy or JAX arrays."""
    xp = jnp if any(isinstance(a, jax.Array) for a in (kt, n_re, n_im, m, cos_t)) else np
    c = cos_t
    s2 = 1.0 - c * c
    w2 = (n_re * n_re - n_im * n_im - 1.0 + c * c) + 2j * n_re * n_im
    w = xp.sqrt(w2 + 0j)
    gu = kt * xp.real(w) / xp.maximum(xp.abs(w) ** 2, 1e-30)
    v = 1.0 / (m + 1.0)
    a = s2 - c * c
    return xp.abs(gu) * xp.sqrt(4.0 * c * c * s2 * v + 2.0 * (a * a + c**4) * v * v)


def lobe_chi(q, gu, m, cos_t):
    """``chi(q)`` of the module docstring as ``(re, im)``: the characteristic function of the
    thick layer's phase perturbation over the lobe, with the phase linear in ``u = cos^2 t``
    (``gu = d psi / d u``) and the facet tilt Gaussian (variance ``1/(m+1)`` per axis)."""
    c = cos_t
    s2 = jnp.clip((1.0 - c) * (1.0 + c), 0.0, 1.0)
    var = 1.0 / (m + 1.0)
    lam = q * gu
    # u' - u = 2 c s x + (s^2 - c^2) x^2 - c^2 y^2 for tilts (x in the plane of incidence, y
    # across it): a Gaussian quadratic form, E exp(i lam (u' - u)) in closed form
    a = s2 - c * c
    p1 = (jnp.ones_like(c), -2.0 * lam * a * var)  # 1 - 2 i lam a var
    p2 = (jnp.ones_like(c), 2.0 * lam * c * c * var)  # 1 + 2 i lam c^2 var
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    inv_sqrt = lambda p: _div((one, zero), complex_sqrt_re(p[0], p[1]))  # noqa: E731
    b = 2.0 * lam * c
    e = _div((-(b * b) * s2 * var * 0.5, zero), p1)
    mag = jnp.exp(e[0])
    ez = (mag * jnp.cos(e[1]), mag * jnp.sin(e[1]))
    return _mul(ez, _mul(inv_sqrt(p1), inv_sqrt(p2)))


def _series(chi, w, q_max):
    """``sum_{q=1}^{Q} chi(q) w^(q-1) + chi(Q+1) w^Q / (1 - w)`` with ``chi`` given on a
    trailing axis ``q = 1..Q+1`` and the powers of ``w`` in polar form, vectorized over ``q``
    (one set of operations instead of ``Q``: the unrolled sum made the lobe mode's program
    several times larger)."""
    dt = w[0].dtype
    k = jnp.arange(q_max + 1, dtype=dt)  # powers 0..Q
    a2 = _abs2(w)
    ok = a2 > tiny(dt)
    log_mag = 0.5 * jnp.log(jnp.where(ok, a2, 1.0))
    arg = safe_atan2(w[1], w[0])
    ex = lambda x: x[..., None]  # noqa: E731
    mag = jnp.where(ex(ok), jnp.exp(k * ex(log_mag)), 0.0)
    mag = jnp.where(k == 0, 1.0, mag)
    pw = (mag * jnp.cos(k * ex(arg)), mag * jnp.sin(k * ex(arg)))
    terms = _mul(chi, pw)
    head = (jnp.sum(terms[0][..., :q_max], -1), jnp.sum(terms[1][..., :q_max], -1))
    tail = _div((terms[0][..., q_max], terms[1][..., q_max]), _one_minus(w))
    return _add(head, tail)


def facet_gram(n_re, n_im, cos_t, films: Films | None, *, white: bool = False):
    """Second moments ``(G_ss, G_pp, Re G_sp, Im G_sp)`` of the facet reflection,
    ``G_xy = <r_x r_y^*>`` (the products of the amplitudes for a bare or coherent facet;
    the lobe or phase average of a thick layer otherwise: module docstring)."""
    if white:
        one = jnp.ones_like(cos_t)
        return one, one, -one, jnp.zeros_like(cos_t)
    if films is None or films.coherent:
        if films is None:
            rs_re, rs_im, rp_re, rp_im = fresnel_amplitudes_re(n_re, n_im, cos_t)
        else:
            rs_re, rs_im, rp_re, rp_im = stack_amplitudes(n_re, n_im, films, cos_t)
        rs, rp = (rs_re, rs_im), (rp_re, rp_im)
        sp = _mulc(rs, rp)
        return _abs2(rs), _abs2(rp), sp[0], sp[1]
    etas, ws, kt, c = _media(n_re, n_im, films, cos_t)
    J = films.thick + 1  # medium index of the thick layer
    r_top, rb_top, P_top = _star_down(etas, ws, kt, J)
    RB = _airy_up(etas, ws, kt, J)
    z = _phase(kt[J - 1], ws[J])
    A2 = _mul(P_top, RB)
    B2 = _mul(rb_top, RB)
    # per polarization (s, p) as (re, im) pairs
    pol = lambda x: tuple((x[0][i], x[1][i]) for i in (0, 1))  # noqa: E731
    rT, A, B = pol(r_top), pol(A2), pol(B2)
    # stored once: XLA CPU otherwise fuses the stack into each of the consumers below
    z, rT, A, B = _store_tree((z, rT, A, B))
    z2 = _abs2(z)
    lobe = films.mode == "lobe"
    if lobe:
        # psi = 2 kt Re w, w^2 = n^2 - 1 + u: d psi / d u = kt Re(1 / w) = kt Re(w) / |w|^2
        wJ = ws[J]
        aw = _abs2(wJ)
        aw_s = jnp.where(aw > tiny(aw.dtype), aw, 1.0)
        g = jnp.where(aw > tiny(aw.dtype), kt[J - 1] * wJ[0] / aw_s, 0.0)
        mm = jnp.broadcast_to(films.m, c.shape)
        Q = LOBE_TERMS
        q = jnp.arange(1, Q + 2, dtype=c.dtype)
        chi = lobe_chi(q, g[..., None], mm[..., None], c[..., None])  # (..., Q + 1)
        S = _store_tree([_series(chi, _mul(B[i], z), Q) for i in (0, 1)])

    def pair(x, y):
        # C_0 and, for the lobe, the q != 0 terms (module docstring)
        D0 = _one_minus(_scale(z2, _mulc(B[x], B[y])))
        frac = _div(_scale(z2, _mulc(A[x], A[y])), D0)
        g0 = _add(_mulc(rT[x], rT[y]), frac)
        if not lobe:
            return g0
        # K_x = A_x (rT_y^* + A_y^* B_x |z|^2 / D0); K'_y = A_y^* (rT_x + A_x B_y^* |z|^2 / D0)
        Kx = _mul(A[x], _add(_conj(rT[y]), _div(_scale(z2, _mulc(B[x], A[y])), D0)))
        Ky = _mul(_conj(A[y]), _add(rT[x], _div(_scale(z2, _mulc(A[x], B[y])), D0)))
        plus = _mul(_mul(z, Kx), S[x])
        minus = _mul(_mul(_conj(z), Ky), _conj(S[y]))
        return _add(g0, _add(plus, minus))

    gss = pair(0, 0)
    gpp = pair(1, 1)
    gsp = pair(0, 1)
    return _store_tree((gss[0], gpp[0], gsp[0], gsp[1]))


def _store_tree(tree):
    from ._frames import store  # noqa: PLC0415

    return jax.tree.map(store, tree)


def facet_params(n_re, n_im, cos_t, films: Films | None, *, white: bool = False):
    """Mueller parameters ``(a, b, c, d)`` of the facet (:func:`ppr.optics.fresnel_mueller_params`
    for a bare facet: the same program)."""
    if white:
        one = jnp.ones_like(cos_t)
        return one, jnp.zeros_like(cos_t), -one, jnp.zeros_like(cos_t)
    if films is None:
        return fresnel_mueller_params(n_re, n_im, cos_t)
    gss, gpp, c, d = facet_gram(n_re, n_im, cos_t, films)
    return 0.5 * (gss + gpp), 0.5 * (gss - gpp), c, d


def facet_amplitudes(n_re, n_im, cos_t, films: Films | None, *, white: bool = False):
    """Jones amplitudes ``(rs_re, rs_im, rp_re, rp_im)`` of a bare or coherent facet."""
    if white:
        one = jnp.ones_like(cos_t)
        zero = jnp.zeros_like(cos_t)
        return -one, zero, one, zero
    if films is None:
        return fresnel_amplitudes_re(n_re, n_im, cos_t)
    if not films.coherent:
        raise ValueError("facet_amplitudes: a thick-film facet has no single Jones matrix")
    return stack_amplitudes(n_re, n_im, films, cos_t)


def facet_components(n_re, n_im, cos_t, films: Films):
    """Two Jones components ``((x1, y1), (x2, y2))`` (each amplitude an ``(re, im)`` pair)
    whose incoherent sum has the facet's second moments: ``sum_c x_c y_c^* = G_sp``,
    ``sum |x_c|^2 = G_ss``, ``sum |y_c|^2 = G_pp`` (Cholesky: ``x1 = sqrt(G_ss)``,
    ``y1 = G_sp^* / x1``, ``x2 = 0``, ``y2 = sqrt(G_pp - |G_sp|^2 / G_ss)``). Chains of
    independent facets built from them have the exact second moments of the average."""
    gss, gpp, gr, gi = facet_gram(n_re, n_im, cos_t, films)
    dt = gss.dtype
    ok = gss > tiny(dt)
    x1 = jnp.where(ok, jnp.sqrt(jnp.where(ok, gss, 1.0)), 0.0)
    inv = jnp.where(ok, 1.0 / jnp.where(ok, x1, 1.0), 0.0)
    y1 = (gr * inv, -gi * inv)
    rest = gpp - (gr * gr + gi * gi) * inv * inv
    thr = float(np.finfo(dt).eps) * 1e-2
    okr = rest > thr
    y2 = jnp.where(okr, jnp.sqrt(jnp.where(okr, rest, 1.0)), 0.0)
    zero = jnp.zeros_like(x1)
    return ((x1, zero), y1), ((zero, zero), (y2, zero))


def stack_transmission(n_re, n_im, films: Films, cos_t):
    """Coherent stack amplitudes ``(r_s, r_p, t_s, t_p)`` (each ``(re, im)``) with the
    transmission into the substrate (Born-Wolf amplitude convention: ``t_p`` the ratio of
    the electric-field amplitudes), by the forward star product. The power transmittance
    into a non-absorbing substrate is ``Re(w_sub) / cos t |t|^2`` for both polarizations.
    For tests and the energy balance (docs/physics/thin_films.md)."""
    etas, ws, kt, _ = _media(n_re, n_im, films, cos_t)

    def iface(j):
        # r and t (down), t' (up) from the admittances; for p they are the magnetic-field
        # ratios (the electric one is t_p n_a / n_b, a product that telescopes to 1 / n_sub)
        den = _add(etas[j], etas[j + 1])
        return (
            _div(_sub(etas[j], etas[j + 1]), den),
            _div(_scale(2.0, etas[j]), den),
            _div(_scale(2.0, etas[j + 1]), den),
        )

    last = len(ws) - 1
    r, t, tb = iface(0)
    rb = (-r[0], -r[1])
    for j in range(1, last):
        h = _sp(_phase(0.5 * kt[j - 1], ws[j]))  # exp(i k0 t w): one pass through layer j
        z = _mul(h, h)
        ri, ti, tbi = iface(j)
        D = _one_minus(_mul(_mul(rb, ri), z))
        r_new = _add(r, _div(_mul(_mul(_mul(t, tb), ri), z), D))
        rb = _sub(_div(_mul(_mul(_mul(ti, tbi), rb), z), D), ri)
        t = _div(_mul(_mul(t, ti), h), D)
        tb = _div(_mul(_mul(tbi, tb), h), D)
        r = r_new
    dt = ws[0][0].dtype
    sub = (
        jnp.broadcast_to(jnp.asarray(n_re, dt), t[0].shape[1:]),
        jnp.broadcast_to(jnp.asarray(n_im, dt), t[0].shape[1:]),
    )
    tp = _div((t[0][1], t[1][1]), sub)
    return (r[0][0], r[1][0]), (r[0][1], r[1][1]), (t[0][0], t[1][0]), tp


# --------------------------------------------------------------------------------------------
# the thick-film criterion (host)

_SPREAD_COS = np.linspace(1e-3, 1.0, 400)


def layer_spreads(films, wavelength, m) -> np.ndarray:
    """Host: the largest :func:`phase_spread` of each layer over incidence 0-89.9 deg and over
    the elements of batched fields, ``(L,)`` radians."""
    lam = np.asarray(wavelength, np.float64)
    mm = np.asarray(m, np.float64)
    out = []
    for n, t in films:
        n = np.asarray(n, np.complex128)
        kt = 2.0 * np.pi * np.asarray(t, np.float64) / lam
        kt, nr, ni, mb = np.broadcast_arrays(kt, n.real, n.imag, mm)
        c = _SPREAD_COS.reshape((-1,) + (1,) * kt.ndim)
        s = phase_spread(kt[None], nr[None], ni[None], mb[None], c)
        out.append(float(np.max(s)) if s.size else 0.0)
    return np.asarray(out)


def resolve_film_mode(films, wavelength, m, film_mode, thick_layer) -> tuple[str, int]:
    """``(mode, thick_layer)`` of a material (``Material.film_mode`` is resolved once, at
    construction). ``"auto"``: ``"coherent"`` unless some layer's phase spread over the lobe
    exceeds :data:`THICK_SPREAD`, then ``"lobe"`` on that layer (two thick layers are an
    error: the averaged treatment handles one). ``"lobe"``/``"incoherent"`` without
    ``thick_layer``: the layer of largest spread. Needs concrete values unless both are
    given explicitly."""
    if film_mode not in FILM_MODES:
        raise ValueError(f"Material.film_mode must be one of {FILM_MODES}, got {film_mode!r}")
    if not films:
        return "coherent", -1
    L = len(films)
    if thick_layer is not None:
        thick_layer = int(thick_layer)
        if not (-1 <= thick_layer < L):
            raise ValueError(
                f"Material.thick_layer must index one of the {L} film layers (or be -1), "
                f"got {thick_layer}"
            )
    if film_mode == "coherent" or thick_layer == -1:
        return "coherent", -1
    if film_mode != "auto" and thick_layer is not None:
        return film_mode, thick_layer
    leaves = [wavelength, m] + [a for layer in films for a in layer]
    if any(isinstance(a, jax.core.Tracer) for a in leaves) or wavelength is None:
        raise ValueError(
            f"Material.film_mode={film_mode!r} without thick_layer needs concrete films, m and "
            "wavelength (the thick-layer criterion runs on the host); pass film_mode and "
            "thick_layer explicitly for traced materials"
        )
    spread = layer_spreads(films, wavelength, m)
    if film_mode == "auto":
        thick = [i for i in range(L) if spread[i] > THICK_SPREAD]
        if thick_layer is not None:
            return ("lobe", thick_layer) if thick_layer in thick else ("coherent", -1)
        if not thick:
            return "coherent", -1
        if len(thick) > 1:
            raise ValueError(
                f"Material.films: layers {thick} are all thick (phase spread over the lobe "
                f"{[round(float(spread[i]), 2) for i in thick]} rad > {THICK_SPREAD:.2f}); the "
                "averaged treatment handles one thick layer: pass thick_layer=<index> (the "
                "others stay coherent) or film_mode='coherent'"
            )
        return "lobe", thick[0]
    return film_mode, int(np.argmax(spread))


def facet_mueller_params(material, cos_t):
    """Mueller parameters ``(a, b, c, d)`` of one facet of ``material`` seen at facet cosine
    ``cos_t`` (``M = [[a, b, 0, 0], [b, a, 0, 0], [0, 0, c, d], [0, 0, -d, c]]`` in the facet's
    s/p frames): the bare Fresnel interface, the coherent stack, or the lobe- or
    phase-averaged thick layer of ``material.film_mode``; the ideal white reflector
    ``(1, 0, -1, 0)``. Broadcasts the material's fields against ``cos_t``."""
    dt = jnp.result_type(jnp.finfo(jnp.asarray(material.n).dtype).dtype, cos_t)
    c = jnp.asarray(cos_t, dt)
    n = jnp.asarray(material.n)
    films = films_of(material, dt)
    shape = jnp.broadcast_shapes(n.shape, c.shape, *(jnp.shape(a) for a in jax.tree.leaves(films)))
    b = lambda a: jnp.broadcast_to(jnp.asarray(a).astype(dt), shape)  # noqa: E731
    if films is not None:
        films = jax.tree.map(b, films)
    return facet_params(b(jnp.real(n)), b(jnp.imag(n)), b(c), films, white=material.white)
