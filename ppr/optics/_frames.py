r"""Beam frames, frame rotations, Jones -> Mueller, and a facet's Fresnel reflection expressed
in the incident/outgoing beam frames.

Conventions (:mod:`ppr.optics.conventions`): a beam travelling along ``d`` carries a right-handed
frame ``(x, y = d x x, d)``. Rotating the frame vector by ``a`` (right-handed about ``d``)
maps Stokes vectors by ``R(a) = [[1,0,0,0],[0,C,S,0],[0,-S,C,0],[0,0,0,1]]`` with
``C = cos 2a, S = sin 2a``, and Jones vectors by ``[[cos a, sin a], [-sin a, cos a]]``.

A facet with normal ``h`` reflecting the beam travelling along ``-k_in`` into the beam along
``+k_out`` has its own s/p frames: ``s = normalize(k_in x k_out)`` (shared), ``p = d x s`` per
beam; in those frames its Jones matrix is ``diag(r_s, r_p)`` (:mod:`ppr.optics._fresnel`). The
result
does not depend on the sign of ``s``. At exact backscatter (``k_out = k_in``) and exact forward
geometry (``k_out = -k_in``) ``s`` is undefined, but so is the dependence on it (normal
incidence: ``r_s = -r_p``; grazing: ``r_s = r_p``, ``d_in = d_out``): any ``s`` perpendicular
to ``k_in`` gives the same matrix, and the fallback below keeps values and gradients finite.

The array-valued public functions (:func:`default_frame`, :func:`mueller_rotator`,
:func:`jones_to_mueller`, :func:`facet_jones_in_beam_frames`,
:func:`facet_mueller_in_beam_frames`) are ``jax.jit``-wrapped, as in :mod:`ppr.optics._fresnel`.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from .._safe import float_dtype, safe_div
from .._types import Array, ArrayLike, Complex, Float
from ._fresnel import fresnel_amplitudes_re, fresnel_mueller_params, jax_complex

__all__ = [
    "A_STOKES",
    "default_frame",
    "facet_jones_in_beam_frames",
    "facet_jones_in_beam_frames_re",
    "facet_jones_rows",
    "facet_mueller_in_beam_frames",
    "facet_mueller_rows",
    "facet_rotated_params",
    "rotated_mueller_flat",
    "jones_rotator",
    "jones_to_mueller",
    "materialize",
    "rotate_mueller_flat",
    "rotate_mueller_44",
    "store",
    "mueller_from_params",
    "mueller_rotator",
    "perpendicular_unit",
    "rotation_cos_sin",
    "rotation_cos_sin_2a",
]

# S = A (E (x) E^*): the Stokes definitions of ppr.optics.conventions (S3 = -2 Im(E_x E_y^*))
A_STOKES = np.array([[1, 0, 0, 1], [1, 0, 0, -1], [0, 1, 1, 0], [0, 1j, -1j, 0]], np.complex128)
_A_STOKES_INV = np.linalg.inv(A_STOKES)

FLike = Float[ArrayLike, "..."]
VLike = Float[ArrayLike, "... 3"]


def _dot(a: Array, b: Array) -> Array:
    return jnp.sum(a * b, axis=-1)


def _stack3(v) -> Array:
    """Three ``(...,)`` components -> ``(..., 3)``, stacked on a leading axis and moved:
    stacking directly on a trailing axis ran ~2x slower on XLA CPU (docs/DESIGN.md)."""
    return jnp.moveaxis(jnp.stack(v, axis=0), 0, -1)


def _perp3_any(d: "Vec") -> "Vec":
    """SoA :func:`perpendicular_unit` for any (not necessarily unit) ``d``; ``+z`` for d = 0."""
    dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    use_y = jnp.abs(d[0]) > 0.9 * jnp.sqrt(dd)
    # d x e_x = (0, d_z, -d_y); d x e_y = (-d_z, 0, d_x)
    z = jnp.zeros_like(d[0])
    v = (jnp.where(use_y, -d[2], z), jnp.where(use_y, z, d[2]), jnp.where(use_y, d[0], -d[1]))
    sq = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    ok = sq > jnp.finfo(sq.dtype).tiny * 1e3
    inv = 1.0 / jnp.sqrt(jnp.where(ok, sq, 1.0))
    one = jnp.ones_like(sq)
    return (
        jnp.where(ok, v[0] * inv, z),
        jnp.where(ok, v[1] * inv, z),
        jnp.where(ok, v[2] * inv, one),
    )


def perpendicular_unit(d: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """A deterministic unit vector perpendicular to ``d`` (piecewise smooth, finite gradient).

    ``normalize(d x e)`` with ``e = e_x`` unless ``|d_x| > 0.9 |d|``, then ``e = e_y``
    (``|d x e| >= 0.43 |d|`` by construction; ``+z`` only for ``d = 0``). Component
    arithmetic: reductions over a trailing axis of 3 ran ~15x slower on XLA CPU.
    """
    d = jnp.asarray(d)
    return _stack3(_perp3_any(_split(d)))


def _default_frame3(d: "Vec", normal: "Vec") -> "Vec":
    """SoA :func:`default_frame`."""
    fb = _perp3_any(d)
    cr = _cross3(normal, d)
    sq = _dot3(cr, cr)
    # threshold |normal x d|^2 > eps (not tiny): nearly parallel inputs would otherwise give a
    # rounding-dominated direction and gradients ~1/|normal x d|
    ok = sq > jnp.finfo(sq.dtype).eps
    inv = 1.0 / jnp.sqrt(jnp.where(ok, sq, 1.0))
    return tuple(jnp.where(ok, c * inv, f) for c, f in zip(cr, fb, strict=True))


@jax.jit
def default_frame(d: VLike, normal: VLike) -> Float[Array, "... 3"]:
    """Frame vector (x axis) of a beam travelling along ``d``: the s direction
    ``normalize(normal x d)``; where ``d`` is parallel to ``normal`` (no plane of incidence)
    the deterministic :func:`perpendicular_unit` of ``d`` (gradient through ``d x normal``
    is zero there)."""
    dt = float_dtype(d, normal)
    d = jnp.asarray(d, dt)
    normal = jnp.asarray(normal, dt)
    d, normal = jnp.broadcast_arrays(d, normal)
    return _stack3(_default_frame3(_split(d), _split(normal)))


def rotation_cos_sin(
    x_from: Float[ArrayLike, "... 3"], x_to: Float[ArrayLike, "... 3"], d: Float[ArrayLike, "... 3"]
) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """``(cos a, sin a)`` of the rotation about ``d`` (right-handed) taking ``x_from`` to ``x_to``.

    ``cos a = x_from . x_to``, ``sin a = d . (x_from x x_to)``, renormalized so that
    ``cos^2 + sin^2 = 1`` (identity where both vanish). Sign-unambiguous, so it is the right
    input for Jones rotations (coherent sums need the sign).
    """
    x_from = jnp.asarray(x_from)
    x_to = jnp.asarray(x_to)
    d = jnp.asarray(d)
    c = _dot(x_from, x_to)
    s = _dot(d, jnp.cross(x_from, x_to))
    r2 = c * c + s * s
    ok = r2 > jnp.finfo(r2.dtype).tiny * 1e6
    inv = 1.0 / jnp.sqrt(jnp.where(ok, r2, 1.0))
    return jnp.where(ok, c * inv, 1.0), jnp.where(ok, s * inv, 0.0)


def rotation_cos_sin_2a(
    x_from: Float[ArrayLike, "... 3"], x_to: Float[ArrayLike, "... 3"], d: Float[ArrayLike, "... 3"]
) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """``(cos 2a, sin 2a)`` of the rotation about ``d`` taking frame vector ``x_from`` to
    ``x_to`` (no arccos; from dot and cross products, identity where undefined)."""
    x_from = jnp.asarray(x_from)
    x_to = jnp.asarray(x_to)
    d = jnp.asarray(d)
    c = _dot(x_from, x_to)
    s = _dot(d, jnp.cross(x_from, x_to))
    r2 = c * c + s * s
    return safe_div(c * c - s * s, r2, fill=1.0), safe_div(2.0 * c * s, r2, fill=0.0)


@jax.jit
def mueller_rotator(c2: FLike, s2: FLike) -> Float[Array, "... 4 4"]:
    """Stokes rotator ``[[1,0,0,0],[0,c2,s2,0],[0,-s2,c2,0],[0,0,0,1]]`` (frame rotation by
    ``a`` with ``c2 = cos 2a``, ``s2 = sin 2a``)."""
    c2, s2 = jnp.broadcast_arrays(jnp.asarray(c2), jnp.asarray(s2))
    dt = float_dtype(c2, s2)
    c2, s2 = c2.astype(dt), s2.astype(dt)
    o, z = jnp.ones_like(c2), jnp.zeros_like(c2)
    rows = [[o, z, z, z], [z, c2, s2, z], [z, -s2, c2, z], [z, z, z, o]]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def jones_rotator(c: FLike, s: FLike) -> Float[Array, "... 2 2"]:
    """Jones frame rotator ``[[c, s], [-s, c]]`` (``c = cos a``, ``s = sin a``)."""
    c, s = jnp.broadcast_arrays(jnp.asarray(c), jnp.asarray(s))
    return jnp.stack([jnp.stack([c, s], -1), jnp.stack([-s, c], -1)], -2)


def mueller_from_params(a: FLike, b: FLike, c: FLike, d: FLike) -> Float[Array, "... 4 4"]:
    """``[[a,b,0,0],[b,a,0,0],[0,0,c,d],[0,0,-d,c]]`` (Fresnel Mueller matrix in s/p frames)."""
    a, b, c, d = jnp.broadcast_arrays(*(jnp.asarray(v) for v in (a, b, c, d)))
    z = jnp.zeros_like(a)
    rows = [[a, b, z, z], [b, a, z, z], [z, z, c, d], [z, z, -d, c]]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


@jax.jit
def jones_to_mueller(J: Complex[ArrayLike, "... 2 2"]) -> Float[Array, "... 4 4"]:
    """Mueller matrix ``A (J (x) J^*) A^{-1}`` of a (batched) 2x2 complex Jones matrix."""
    J = jnp.asarray(J)
    if not jnp.issubdtype(J.dtype, jnp.complexfloating):
        J = J.astype(jnp.result_type(float_dtype(J), jnp.complex64))
    A = jnp.asarray(A_STOKES, J.dtype)
    Ainv = jnp.asarray(_A_STOKES_INV, J.dtype)
    K = jnp.einsum("...ij,...kl->...ikjl", J, jnp.conj(J))
    K = K.reshape(J.shape[:-2] + (4, 4))
    M = A @ K @ Ainv
    return jnp.real(M)


# ---------------------------------------------------------------- facet helpers (SoA)
# Internally vectors are tuples of three (...,) component arrays: reductions over a trailing
# axis of length 3 ran ~10x slower than component arithmetic on XLA CPU (docs/DESIGN.md).

Vec = tuple[Array, Array, Array]


def _split(v) -> Vec:
    if isinstance(v, tuple | list):
        return tuple(v)  # type: ignore[return-value]
    return (v[..., 0], v[..., 1], v[..., 2])


def _dot3(a: Vec, b: Vec) -> Array:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross3(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _neg3(a: Vec) -> Vec:
    return (-a[0], -a[1], -a[2])


def _perp3(d: Vec) -> Vec:
    """SoA version of :func:`perpendicular_unit` (d unit)."""
    use_y = jnp.abs(d[0]) > 0.9
    # d x e_x = (0, d_z, -d_y); d x e_y = (-d_z, 0, d_x)
    z = jnp.zeros_like(d[0])
    v = (jnp.where(use_y, -d[2], z), jnp.where(use_y, z, d[2]), jnp.where(use_y, d[0], -d[1]))
    inv = 1.0 / jnp.sqrt(jnp.maximum(_dot3(v, v), 0.1))  # |v|^2 >= 0.19 for unit d
    return (v[0] * inv, v[1] * inv, v[2] * inv)


def _facet_frames3(k_in: Vec, k_out: Vec) -> tuple[Vec, Vec, Vec]:
    """Shared s vector and per-beam p vectors (p = d x s), with a safe fallback for s."""
    fb = _perp3(k_in)
    cr = _cross3(k_in, k_out)
    sq = _dot3(cr, cr)
    # fallback inside |k_in x k_out|^2 <= eps: near backscatter the matrix depends on s only at
    # O(|k_in x k_out|^2) (r_s + r_p = O(t^2)), so the switch costs ~eps in value and keeps
    # gradients ~ rounding / |k_in x k_out| small; near forward geometry the dependence is
    # O(|k_in x k_out|) (degenerate half vector, masked by callers)
    ok = sq > jnp.finfo(sq.dtype).eps
    inv = 1.0 / jnp.sqrt(jnp.where(ok, sq, 1.0))
    s = tuple(jnp.where(ok, c * inv, f) for c, f in zip(cr, fb, strict=True))
    p_in = _cross3(_neg3(k_in), s)
    p_out = _cross3(k_out, s)
    return s, p_in, p_out


def _prep3(n_re, n_im, k_in, k_out, h, x_in, x_out):
    vecs = [
        _split(v) if isinstance(v, tuple | list) else _split(jnp.asarray(v))
        for v in (k_in, k_out, h, x_in, x_out)
    ]
    leaves = [c for v in vecs for c in v]
    dt = float_dtype(n_re, n_im, *leaves)
    leaves = jnp.broadcast_arrays(*(jnp.asarray(c, dt) for c in leaves))
    k_in, k_out, h, x_in, x_out = (tuple(leaves[3 * i : 3 * i + 3]) for i in range(5))
    cos_t = jnp.clip(_dot3(k_in, h), 0.0, 1.0)
    n_re = jnp.asarray(n_re, dt)
    n_im = jnp.asarray(n_im, dt)
    return n_re, n_im, k_in, k_out, x_in, x_out, cos_t


def facet_jones_rows(n_re, n_im, k_in, k_out, h, x_in, x_out):
    """Structure-of-arrays Jones matrix: ``((j11, j12), (j21, j22))`` each as ``(re, im)``.

    Same arguments as :func:`facet_jones_in_beam_frames`; vectors may be ``(..., 3)`` arrays
    or tuples of three component arrays (fastest).
    """
    n_re, n_im, k_in, k_out, x_in, x_out, cos_t = _prep3(n_re, n_im, k_in, k_out, h, x_in, x_out)
    rs_re, rs_im, rp_re, rp_im = fresnel_amplitudes_re(n_re, n_im, cos_t)
    s, p_in, p_out = _facet_frames3(k_in, k_out)
    y_in = _cross3(_neg3(k_in), x_in)
    y_out = _cross3(k_out, x_out)
    # components in the new basis are dot products: E_s = E.s, E_p = E.p_in
    # J = P_out diag(rs, rp) P_in, P_in = [[s.x_in, s.y_in], [p_in.x_in, p_in.y_in]],
    # P_out = [[x_out.s, x_out.p_out], [y_out.s, y_out.p_out]]
    a11, a12 = _dot3(s, x_in), _dot3(s, y_in)
    a21, a22 = _dot3(p_in, x_in), _dot3(p_in, y_in)
    b11, b12 = _dot3(x_out, s), _dot3(x_out, p_out)
    b21, b22 = _dot3(y_out, s), _dot3(y_out, p_out)

    def entry(bs, bp, as_, ap):
        return (bs * rs_re * as_ + bp * rp_re * ap, bs * rs_im * as_ + bp * rp_im * ap)

    return (
        (entry(b11, b12, a11, a21), entry(b11, b12, a12, a22)),
        (entry(b21, b22, a11, a21), entry(b21, b22, a12, a22)),
    )


def facet_jones_in_beam_frames_re(
    n_re: FLike, n_im: FLike, k_in: VLike, k_out: VLike, h: VLike, x_in: VLike, x_out: VLike
) -> tuple[Float[Array, "... 2 2"], Float[Array, "... 2 2"]]:
    """Real and imaginary parts of :func:`facet_jones_in_beam_frames`."""
    rows = jax.lax.optimization_barrier(facet_jones_rows(n_re, n_im, k_in, k_out, h, x_in, x_out))

    def mat(part):
        flat = [e[part] for r in rows for e in r]
        return jnp.stack(flat, axis=-1).reshape(flat[0].shape + (2, 2))

    return mat(0), mat(1)


@jax.jit
def facet_jones_in_beam_frames(
    n_re: FLike, n_im: FLike, k_in: VLike, k_out: VLike, h: VLike, x_in: VLike, x_out: VLike
) -> Complex[Array, "... 2 2"]:
    """Complex 2x2 Jones matrix of a facet's Fresnel reflection in the beam frames.

    **Arguments:**

    - `n_re`, `n_im`: complex index of the facet (``n_im >= 0``).
    - `k_in`, `k_out`: unit directions away from the surface (toward source / receiver).
    - `h`: facet normal (unit); the angle of incidence is ``cos t = clip(k_in . h, 0, 1)``.
      The caller guarantees ``k_out`` is the mirror of ``k_in`` about ``h`` (e.g. ``h`` is
      the half vector); only ``k_in . h`` and the s/p geometry of ``(k_in, k_out)`` are used.
    - `x_in`: frame vector of the incident beam (travelling along ``-k_in``), unit, ``_|_ k_in``.
    - `x_out`: frame vector of the outgoing beam (travelling along ``+k_out``), unit,
      ``_|_ k_out``.

    **Returns:** ``J`` with ``E_out = J @ E_in`` (Jones components in the beam frames). The
    overall sign is unambiguous (no angle-doubling), as a coherent sum of paths requires.
    """
    re, im = facet_jones_in_beam_frames_re(n_re, n_im, k_in, k_out, h, x_in, x_out)
    return jax_complex(re, im)


def facet_rotated_params(
    n_re, n_im, k_in, k_out, h, x_in, x_out, *, white: bool = False, films=None
):
    """``(a, b, c, d, Ca, Sa, Cb, Sb)``: the facet's Fresnel Mueller parameters
    (:func:`ppr.optics._fresnel.fresnel_mueller_params`; the ideal white reflector ``(1, 0, -1, 0)``
    if ``white``; the film stack's, :func:`ppr.optics._films.facet_params`, for ``films``, a
    :class:`ppr.optics._films.Films` broadcastable with ``n_re``) and ``cos 2a, sin 2a, cos 2b,
    sin 2b`` of the rotations ``x_in -> s`` about ``-k_in`` and ``s -> x_out`` about
    ``+k_out``. Arguments as in :func:`facet_mueller_in_beam_frames`; vectors ``(..., 3)`` or
    SoA tuples."""
    n_re, n_im, k_in, k_out, x_in, x_out, cos_t = _prep3(n_re, n_im, k_in, k_out, h, x_in, x_out)
    if white:
        one = jnp.ones_like(cos_t)
        a, b, c, d = one, jnp.zeros_like(cos_t), -one, jnp.zeros_like(cos_t)
    elif films is not None:
        from ._films import facet_params  # noqa: PLC0415

        a, b, c, d = facet_params(n_re, n_im, cos_t, films)
    else:
        a, b, c, d = fresnel_mueller_params(n_re, n_im, cos_t)
    s, _, p_out = _facet_frames3(k_in, k_out)
    y_in = _cross3(_neg3(k_in), x_in)
    # rotation x_in -> s about -k_in: cos = s.x_in, sin = s.y_in ; s -> x_out about k_out:
    # cos = x_out.s, sin = x_out.p_out ; frames are orthonormal so no renormalization needed
    ca, sa = _dot3(s, x_in), _dot3(s, y_in)
    cb, sb = _dot3(x_out, s), _dot3(x_out, p_out)
    return a, b, c, d, ca * ca - sa * sa, 2.0 * ca * sa, cb * cb - sb * sb, 2.0 * cb * sb


# R(b) F R(a) = sum over 18 monomials p q r (p in a, b, c, d; q in 1, Ca, Sa; r in 1, Cb, Sb)
# with constant coefficients: entry (i, j) -> [(coefficient, p, q, r), ...]
_ROTATED_ENTRIES = {
    (0, 0): [(1, "a", "1", "1")],
    (0, 1): [(1, "b", "Ca", "1")],
    (0, 2): [(1, "b", "Sa", "1")],
    (1, 0): [(1, "b", "1", "Cb")],
    (1, 1): [(1, "a", "Ca", "Cb"), (-1, "c", "Sa", "Sb")],
    (1, 2): [(1, "a", "Sa", "Cb"), (1, "c", "Ca", "Sb")],
    (1, 3): [(1, "d", "1", "Sb")],
    (2, 0): [(-1, "b", "1", "Sb")],
    (2, 1): [(-1, "a", "Ca", "Sb"), (-1, "c", "Sa", "Cb")],
    (2, 2): [(-1, "a", "Sa", "Sb"), (1, "c", "Ca", "Cb")],
    (2, 3): [(1, "d", "1", "Cb")],
    (3, 1): [(1, "d", "Sa", "1")],
    (3, 2): [(-1, "d", "Ca", "1")],
    (3, 3): [(1, "c", "1", "1")],
}
_MONOMIALS = sorted({(p, q, r) for v in _ROTATED_ENTRIES.values() for _, p, q, r in v})
_ROTATED_COEF = np.zeros((16, len(_MONOMIALS)))
for (_i, _j), _terms in _ROTATED_ENTRIES.items():
    for _c, _p, _q, _r in _terms:
        _ROTATED_COEF[4 * _i + _j, _MONOMIALS.index((_p, _q, _r))] += _c


def rotated_mueller_flat(params, scale=None, add_m00=None) -> Array:
    """``scale * R(b) F R(a)`` (plus ``add_m00`` on the ``M00`` entry) as a ``(16, ...)``
    array (row-major entries on a *leading* axis) from :func:`facet_rotated_params`.

    Formed as a constant ``(16, 18)`` matrix times the 18 monomials ``p q r``: the product
    is a dot, whose operand XLA CPU materializes once. Written as 16 expressions, XLA CPU
    re-computed the shared Fresnel and frame arithmetic inside each output's fusion
    (``optimization_barrier`` is stripped before fusion on CPU): measured 1.7-2x slower
    (bench/bench_brdf.py).
    """
    a, b, c, d, Ca, Sa, Cb, Sb = params
    if scale is not None:
        a, b, c, d = (scale * v for v in (a, b, c, d))
    v = {"a": a, "b": b, "c": c, "d": d, "Ca": Ca, "Sa": Sa, "Cb": Cb, "Sb": Sb}

    def mono(p, q, r):
        x = v[p]
        if q != "1":
            x = x * v[q]
        if r != "1":
            x = x * v[r]
        return x

    shape = jnp.broadcast_shapes(*(jnp.shape(x) for x in params))
    cols = [mono(*t) for t in _MONOMIALS]
    coef = _ROTATED_COEF
    if add_m00 is not None:
        # one more monomial with coefficient 1 on M00 (a separate add on the stacked
        # result ran 2x slower: XLA CPU copied the whole (16, ...) array)
        shape = jnp.broadcast_shapes(shape, jnp.shape(add_m00))
        cols.append(add_m00)
        coef = np.concatenate([coef, np.eye(16)[:, :1]], axis=1)
    X = jnp.stack([jnp.broadcast_to(x, shape) for x in cols], axis=0)
    coef = jnp.asarray(coef, X.dtype)
    return jnp.tensordot(coef, X, axes=1, precision=jax.lax.Precision.HIGHEST)


def store(x: Array, width: int = 8) -> Array:
    """``x`` computed once and stored, for consumers that XLA CPU would otherwise each
    re-compute it in (it fuses elementwise producers into every consumer, and strips
    ``lax.optimization_barrier`` before fusion). Formed as ``x`` reshaped to rows of
    ``k = gcd(x.size, width)`` entries times a ``k x k`` identity built at run time (from an
    iota, so XLA neither folds it nor rewrites the dot into elementwise work, as it does a
    ``(..., 1) @ [[1]]`` dot or a dot with a literal constant): exact for finite values
    (``x * 1`` plus exact zeros; a non-finite entry spreads NaN to its row of ``k``, so callers
    pass guarded values). A size with ``k = 1`` is returned as is. Unlike
    :func:`materialize` there is no stacking, which XLA CPU runs as a scalar concatenate
    loop."""
    x = jnp.asarray(x)
    k = math.gcd(x.size, width)
    if k < 2:
        return x
    y = jnp.matmul(
        x.reshape(x.size // k, k), jnp.eye(k, dtype=x.dtype), precision=jax.lax.Precision.HIGHEST
    )
    return y.reshape(x.shape)


def materialize(*xs: Array) -> tuple[Array, ...]:
    """The arrays ``xs`` (one shape and dtype) computed once and stored, for consumers that
    XLA CPU would otherwise each re-compute them in (it fuses elementwise producers into
    every consumer, and strips ``lax.optimization_barrier`` before fusion). Formed as a dot
    with the identity, whose operand XLA materializes: exact for finite values (``x * 1``
    plus exact zeros; a non-finite entry would spread NaN to its row, so callers pass
    guarded values). Costly for expensive producers: XLA CPU builds the stacked operand in a
    concatenate fusion that runs as a scalar loop evaluating each column's producers per
    element (see :func:`rotate_mueller_flat`)."""
    x = jnp.stack(xs, axis=-1)
    y = jnp.matmul(x, jnp.eye(len(xs), dtype=x.dtype), precision=jax.lax.Precision.HIGHEST)
    return tuple(y[..., i] for i in range(len(xs)))


def _rotation_monomials():
    """``R(c_out, s_out) M R(c_in, s_in)`` as a constant map of the 36 monomials
    ``M_kl p q`` (``p`` in ``1, c_in, s_in``; ``q`` in ``1, c_out, s_out``)."""

    def rot(c, s):
        return np.array([[1, 0, 0, 0], [0, c, s, 0], [0, -s, c, 0], [0, 0, 0, 1]], float)

    parts = [rot(0, 0), rot(1, 0) - rot(0, 0), rot(0, 1) - rot(0, 0)]  # 1, c, s
    mons, cols = [], []
    for k in range(4):
        for l_ in range(4):
            for p in range(3):
                for q in range(3):
                    col = np.einsum("i,j->ij", parts[q][:, k], parts[p][l_, :]).reshape(16)
                    if np.any(col):
                        mons.append((4 * k + l_, p, q))
                        cols.append(col)
    return tuple(mons), np.stack(cols, axis=1)


_ROT_MONOMIALS, _ROT_COEF = _rotation_monomials()


def rotate_mueller_44(M: Array, c_in: Array, s_in: Array, c_out: Array, s_out: Array) -> Array:
    """``R(c_out, s_out) M R(c_in, s_in)`` (:func:`mueller_rotator`, ``c = cos 2a``,
    ``s = sin 2a``) of Mueller matrices ``(..., 4, 4)``, in that layout.

    ``M R`` keeps columns 0 and 3 and mixes 1 and 2: ``M * [1, c, c, 1] + M[..., ::-1] * s
    [0, -1, 1, 0]`` (the reversed columns bring column 2 to 1 and 1 to 2); ``R M`` does the
    same on the rows. Only broadcasts of per-element scalars against constant ``(4, 4)``
    patterns and two reversals: XLA CPU vectorizes it along the trailing entries, 3.3x faster
    than :func:`rotate_mueller_flat` followed by the transposing copy to ``(..., 4, 4)``
    (17 against 56 ns per matrix, 250k float32)."""
    dt = M.dtype
    one_c = jnp.asarray(np.tile([1.0, 0.0, 0.0, 1.0], (4, 1)), dt)
    mid_c = jnp.asarray(np.tile([0.0, 1.0, 1.0, 0.0], (4, 1)), dt)
    sgn_c = jnp.asarray(np.tile([0.0, -1.0, 1.0, 0.0], (4, 1)), dt)
    c_in, s_in, c_out, s_out = (
        jnp.asarray(x, dt)[..., None, None] for x in (c_in, s_in, c_out, s_out)
    )
    Y = M * (one_c + c_in * mid_c) + M[..., ::-1] * (s_in * sgn_c)
    return Y * (one_c.T + c_out * mid_c.T) + Y[..., ::-1, :] * (s_out * (-sgn_c.T))


def rotate_mueller_flat(M16: Array, c_in: Array, s_in: Array, c_out: Array, s_out: Array) -> Array:
    """``R(c_out, s_out) M R(c_in, s_in)`` (:func:`mueller_rotator`, ``c = cos 2a``,
    ``s = sin 2a``) of row-major Mueller matrices given and returned as ``(16, ...)``.

    A constant ``(16, 36)`` map of the monomials ``M_kl p q`` applied by one dot, with
    ``M`` materialized first (an identity dot): written entry by entry,
    XLA CPU re-computed the producers of ``M`` (table gathers, envelopes) inside each of the
    16 outputs (measured 3.5x slower for the double-bounce table term)."""
    dt = M16.dtype
    # (the entries as the rows of one (..., 16) @ eye dot: stacking 16 slices instead ran
    # 3.5x slower)
    Mt = jnp.moveaxis(M16, 0, -1)
    Mt = jnp.matmul(Mt, jnp.eye(16, dtype=dt), precision=jax.lax.Precision.HIGHEST)
    M = jnp.moveaxis(Mt, -1, 0)
    # the angles are not materialized: XLA CPU fuses them into each monomial (re-computed,
    # but vectorized). Stacking them into one (..., 4) operand of an identity dot made XLA
    # build it in a concatenate fusion that ran as a scalar loop: 320 of the double table
    # term's 510 ns per evaluation (profiled, 250k evaluations, float32). A per-array
    # (..., 1) @ [[1]] dot is simplified away by XLA
    c_in, s_in, c_out, s_out = jnp.broadcast_arrays(c_in, s_in, c_out, s_out)
    f_in = (None, c_in, s_in)
    f_out = (None, c_out, s_out)
    shape = M[0].shape

    def mono(e, p, q):
        x = M[e]
        if p:
            x = x * f_in[p]
        if q:
            x = x * f_out[q]
        return jnp.broadcast_to(x, shape)

    X = jnp.stack([mono(*t) for t in _ROT_MONOMIALS], axis=0)
    return jnp.tensordot(jnp.asarray(_ROT_COEF, dt), X, axes=1, precision=jax.lax.Precision.HIGHEST)


def facet_mueller_rows(n_re, n_im, k_in, k_out, h, x_in, x_out):
    """Structure-of-arrays facet Mueller matrix: a tuple of 4 rows of 4 ``(...,)`` arrays.

    Same arguments and meaning as :func:`facet_mueller_in_beam_frames`; vectors may be
    ``(..., 3)`` arrays or tuples of three component arrays (no trailing-axis reductions).
    Large batches that need the whole matrix are faster through
    :func:`rotated_mueller_flat` (one dot instead of 16 fusions).
    """
    a, b, c, d, Ca, Sa, Cb, Sb = facet_rotated_params(n_re, n_im, k_in, k_out, h, x_in, x_out)
    z = jnp.zeros_like(a)
    return (
        (a, b * Ca, b * Sa, z),
        (Cb * b, Cb * a * Ca - Sb * c * Sa, Cb * a * Sa + Sb * c * Ca, Sb * d),
        (-Sb * b, -Sb * a * Ca - Cb * c * Sa, -Sb * a * Sa + Cb * c * Ca, Cb * d),
        (z, d * Sa, -d * Ca, c),
    )


@jax.jit
def facet_mueller_in_beam_frames(
    n_re: FLike, n_im: FLike, k_in: VLike, k_out: VLike, h: VLike, x_in: VLike, x_out: VLike
) -> Float[Array, "... 4 4"]:
    """Mueller matrix of a facet's Fresnel reflection in the beam frames (arguments as in
    :func:`facet_jones_in_beam_frames`): ``R(b) F R(a)``, ``a`` rotating ``x_in`` to ``s``
    about ``-k_in``, ``F`` from :func:`ppr.optics._fresnel.fresnel_mueller_params`, ``b`` rotating
    ``s`` to ``x_out`` about ``+k_out``. Unitless (multiply by the BRDF's scalar factors).
    """
    flat = rotated_mueller_flat(facet_rotated_params(n_re, n_im, k_in, k_out, h, x_in, x_out))
    return jnp.moveaxis(flat, 0, -1).reshape(flat.shape[1:] + (4, 4))
