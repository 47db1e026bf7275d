r"""Double-bounce term of the polarized microfacet BRDF, with coherent enhanced backscatter.

This is the paper's eq. 13 (``f_double``) derived from the same microfacet statistics as the
single-bounce term (docs/physics/double_bounce.md), with the visibility of eq. 17 replaced (see
"Two-facet visibility") and the Jones chain of eqs. 15-16 generalized to non-coplanar paths.

Notation
    Directions point away from the surface (:mod:`ppr.optics.conventions`): ``k`` toward the
    source, ``k'`` toward the receiver, ``n`` the macro normal, ``c = k.n``, ``c' = k'.n``.
    ``p(h) = (m+1)/(2 pi) (h.n)^m`` is the Blinn-Phong *area-fraction* density of facet normals
    (``int p = 1``); ``<h.n> = (m+1)/(m+2)``; ``<h.u>+ = int p(h) max(h.u, 0) d omega_h``
    (``ppr.microfacet.mean_cosine_plus``); ``P(u) = <h.n> (u.n) / <h.u>+`` (Ashikhmin).

The path and its change of variables
    Light arriving along ``-k`` hits a first facet of normal ``h1`` (lit only if
    ``h1.k > 0``) and leaves it along the mirror direction

        d1 = 2 (k.h1) h1 - k        (direction of *propagation* after bounce 1).

    The second facet reflects the beam arriving along ``d1`` into ``k'``, so its normal is the
    half vector between the reversed first-bounce direction ``-d1`` and ``k'``:

        h2 = normalize(k' - d1),    cos t2 = h2.k' = h2.(-d1) = |k' - d1| / 2,
        cos t1 = h1.k.

    h2 is a function of h1 (for fixed k, k'): the double term is a 2-D integral over h1.

Derivation of the weight (Smith-type, uncorrelated facets)
    Per unit macro area and unit incident irradiance ``E = L (k.n) d omega``:

    1. the power landing on lit facets with normal in ``d omega_h1`` is
       ``p(h1) (h1.k) P(k) / (<h.n> c) d omega_h1`` (facet area per macro area is
       ``1 / <h.n>``; integrated over h1 it is exactly 1);
    2. the beam leaving along ``d1`` is blocked (meets a second facet) with probability
       ``B(d1) = 1`` if ``d1.n <= 0`` (it heads into the surface) and ``1 - P(d1)`` if it heads
       up (a grazing-up ray can still meet a slope); every path with ``B = 0`` is impossible;
    3. the facet it meets has the visible-normal density ``p(h2) (h2.w)+ / <h.w>+`` with
       ``w = -d1`` (pointing back along the ray); the mirror map ``h2 -> k'`` has
       ``d omega_k' = 4 (h2.w) d omega_h2``, so the density of the outgoing direction is
       ``p(h2) / (4 <h.w>+)``;
    4. the beam leaving facet 2 escapes toward the receiver with probability ``P(k')``
       (times the correlation factors of "Two-facet visibility" below).

    Radiance over irradiance, divided by ``c'``, gives

        f_double = P(k) P(k') / (<h.n> c c') int d omega_h1 p(h1) (h1.k)+ p(h2)
                   B(d1) / (4 <h.(-d1)>+) F2(h1, h2).

    Since ``<(-x)+> = <x+> - <x>`` and ``<h.u> = (u.n) <h.n>``, one has for an upward ``u``
    ``1 - P(u) = <h.(-u)>+ / <h.u>+``; hence for *either* sign of ``d1.n``

        B(d1) / <h.(-d1)>+ = 1 / <h.u1>+,    u1 = the upward one of +-d1, i.e.
        1 / mean_cosine_plus(m, |d1.n|),

    which is finite, smooth across the horizon and even in ``d1 -> -d1``. With
    ``P(k) / c = <h.n> / <h.k>+`` no ``1 / (k.n)`` remains (finite at grazing, float32-safe):

        f_double = <h.n> / (<h.k>+ <h.k'>+)
                   int d omega_h1 p(h1) (h1.k)+ p(h2) / (4 <h.u1>+) F2.            (D)

    In the symmetric variable ``d1`` (``d omega_d1 = 4 (h1.k) d omega_h1``) the measure is
    ``p(h1) p(h2) d omega_d1 / (16 <h.u1>+)``; swapping ``k <-> k'`` maps ``d1 -> -d1`` and
    ``h1 <-> h2``, so (D) is reciprocal by construction (tested).

Two-facet visibility (paper eq. 17, corrected)
    The paper's ``P2 = (P(k) - P(k|d))(P(k) - P(k|-d)) / (1 - P(k|-d))`` (``d`` the direction
    from facet 1 to facet 2) fails its own limit: for a ray going straight down
    (``-d = n``) ``P(k|n) = P(k)`` makes ``P2 = 0``, yet such a ray always meets a second facet.
    Its first factor, ``P(k) - P(k|d1)`` = "lit from k and blocked along d1" with Ashikhmin's
    joint visibility (eq. 6), is right, and it is what makes the model conserve energy: the
    flux entering the second bounce is then exactly ``1 - E_single`` (the single term's
    escaping flux is the same integral with ``P(k|d1)``), so single + double can never exceed
    1 (with the uncorrelated ``P(k) (1 - P(d1))`` instead, a measured ``E_single + E_double``
    reached 1.15 at m = 0, grazing). The second factor and the denominator of eq. 17 are
    replaced by the symmetric counterpart at the exit, which restores reciprocity:

        P2 = P(k) B(d1) rho(k, d1) P(k') rho(k', -d1),
        rho(a, d) = (P(a) - P(a|d)) / (P(a) (1 - P(d)))  for d heading up, 1 otherwise,

    ``0 <= rho <= 1`` (since ``P(a|d) >= P(a) P(d)``); ``P(k) B(d1) rho(k, d1) = P(k) -
    P(k|d1)``. Limits: rays heading down are always blocked (``P(d1) = 0``, ``rho = 1``);
    rays heading straight up never (``B = 0``); ``P2 -> 0`` at grazing ``k`` or ``k'``; a ray
    leaving at the azimuth of ``k`` and at least as high is never blocked (``f = 1``,
    ``P(k|d1) = P(k)``), as in Ashikhmin's model. The weight of (D) below is multiplied by
    ``rho(k, d1) rho(k', -d1)``.

Jones chain (general non-coplanar path)
    Facet i has its own s/p frames (:mod:`ppr.optics._frames`): ``s1 = normalize(k x d1)``,
    ``p_in1 = -k x s1``, ``p_out1 = d1 x s1``; ``s2 = normalize(-d1 x k')``, ``p_in2 = d1 x s2``,
    ``p_out2 = k' x s2``. With beam frames ``(x_in, y_in = -k x x_in)`` and
    ``(x_out, y_out = k' x x_out)``

        J_f = P_out2 diag(r_s(t2), r_p(t2)) C_12 diag(r_s(t1), r_p(t1)) P_in1,
        P_in1 = [[s1.x_in, s1.y_in], [p_in1.x_in, p_in1.y_in]],
        C_12  = [[s2.s1, s2.p_out1], [p_in2.s1, p_in2.p_out1]]      (rotation between the
                                                                     two planes of incidence)
        P_out2 = [[x_out.s2, x_out.p_out2], [y_out.s2, y_out.p_out2]].

    ``F2 = A (J_f (x) J_f^*) A^-1`` (Mueller). At exact backscatter every double path is
    coplanar (``h2`` is proportional to ``k - (k.h1) h1``, in the plane of ``k`` and ``h1``, and
    ``h1.h2 = 0``: the paper's eq. 14), ``C_12 = +-1`` and ``J_f`` is ``diag(rs1 rs2, rp1 rp2)``
    in the path's s/p frame: the paper's eqs. 15-16 (the two sign flips of its eq. 10
    cancel in the product). Depolarization comes from averaging paths whose planes have
    different azimuths about ``k``, and, off backscatter, from ``C_12`` rotating between
    non-coplanar planes of incidence.

Coherent enhanced backscatter
    The path through the same two facets in the opposite order has, by reciprocity (3-D
    scattering dyadic ``S_reverse = S^T``) and in beam frames sharing one frame vector
    ``x_in = x_out = e`` (``e _|_ k, k'``; ``e = normalize(k x k')``), the Jones matrix

        J_r = Q J_f^T Q,    Q = diag(1, -1).

    The two paths add in amplitude with the phase ``q.(r2 - r1)``, ``q = (2 pi / lambda)(k' - k)``
    in this direction convention. Averaged over the facet separation, a fraction ``gamma`` of
    the pairs interferes fully and the rest adds in intensity; per integration point

        K = (1 - gamma) J_f (x) J_f^* + gamma (1/2) (J_f + J_r) (x) (J_f + J_r)^*,
        M_double = A <K> A^-1

    (the 1/2 because each unordered pair appears twice in the integral: at backscatter the
    reversed path is the integration point ``-d1``, where the weight is the same). Both parts
    are positive semi-definite coherencies, so ``M_double`` is realizable for every
    ``0 <= gamma <= 1`` and every geometry (a per-path cross term ``J_f (x) J_r^*`` alone would
    not be, off backscatter). At backscatter, summing a node with its partner gives
    ``M_inc + (gamma/2) A <J_f (x) J_r^* + J_r (x) J_f^*> A^-1``, the textbook form.

    Because ``J_r`` is a fixed signed permutation of ``J_f``'s entries, the coherent part is a
    fixed linear map of the incoherent coherency sum: ``M = (1 - gamma) M_inc + gamma M_coh``
    with ``M_coh`` a constant 16 x 16 map of the same 16 accumulated reals (no second Jones
    chain per node). At ``psi = 0`` every path is coplanar, ``J_r = J_f`` exactly, and
    *every* channel (co- and cross-polarized, linear and circular) of the double term is
    enhanced by exactly 2; off backscatter ``J_r != J_f`` (the cross-polarized elements lose
    correlation first) and ``gamma`` decays.

    Coherence factor (Gaussian cone, 2-D Gaussian distribution of the transverse separation
    of the bounce points; ``|k' - k| = 2 sin(psi / 2)``, no arccos):

        gamma(psi) = exp(-ln 2 |k' - k|^2 / psi_h^2),   psi_h = lambda / (4 d),

    so ``gamma(0) = 1`` and ``gamma(psi_h) = 1/2`` (half width at half maximum ``psi_h``, the
    cone width of docs/physics/double_bounce.md), ``d = material.corr_length``: 5 um at 532 nm gives
    ``psi_h = 1.5 deg``. Differentiable in ``psi``, ``lambda`` and ``d``. Macroscopic dihedrals
    (d of cm) must be summed incoherently by the caller (``gamma ~ 0``).

Quadrature (static order)
    (D) is a 2-D integral over h1 whose integrand carries two lobes, ``p(h1)`` and ``p(h2)``.
    A rule adapted to ``p(h1)`` alone misses the ``p(h2)`` lobe when it sits in the tail of
    ``p(h1)`` (grazing incidence: steep first facets feeding a flat second facet), so the
    integral is split by the balance weights ``p1 / (p1 + p2)`` and ``p2 / (p1 + p2)``; the
    first part is integrated over h1, the second over h2 (the reciprocal parametrization:
    swap ``k <-> k'``, ``d1 -> -d1``), each with a rule adapted to its own lobe:
    ``u = cos^(m+1) t`` (uniform lobe weight, ``p(h) d omega_h = du dphi / (2 pi)``,
    ``cos t = exp(log(u)/(m+1))``, ``1 - cos t = -expm1(log(u)/(m+1))``).

    Panels in ``t`` (per azimuth, closed form): with ``h1 = (sin t cos phi, sin t sin phi,
    cos t)`` about n (``phi`` from the projection of k), ``d1.n = R cos(2t - alpha)``,
    ``R = sqrt(c^2 + s^2 cos^2 phi)``, ``alpha = atan2(s cos phi, c)``. So the shadow boundary
    ``h1.k = 0`` is ``t_max = min(pi/2, pi/2 + alpha)``, the horizon of the first-bounce ray
    (``d1.n = 0``, where the blocking and the visibility correlation change form) is
    ``t_0 = alpha/2 + pi/4``, and the second facet faces away (``h2.n = c' - d1.n <= 0``,
    ``p(h2) = 0``; a jump of the integrand at m = 0) for ``|2t - alpha| < acos(c'/R)``. The
    nonzero part is the union of at most three intervals ``[0, t_a]``, ``[t_b, t_0]``,
    ``[t_0, t_max]``, each a Gauss-Legendre panel in ``u`` with ``n_u`` nodes.
    Azimuth: four quarter panels with ends at ``phi = 0, pi/2, pi, 3pi/2``; in each, the
    nodes are Gauss-Legendre in ``log(delta + lambda)``, ``delta`` the distance to
    ``phi = +-pi/2``, ``lambda = c (1 + sqrt(m+1)/4) / s``: near grazing the paths that go
    below the horizon come from a thin band of azimuths around ``+-pi/2`` (:func:`_phi_nodes`).
    Total ``2 * 3 n_u * n_phi`` path evaluations (216 at the default (3, 12), against 192 for
    the former single-panel (8, 12) rule).

    The former rule (one ``u`` panel ``[u_min, 1]``, plain GL in ``phi``, and a ``<h.u>+``
    interpolant on a fixed ``c`` range, see :func:`_mcp_interpolant`) overshot near grazing:
    ``E_single + E_double`` = 1.016 at m = 1e4, 89 deg and 1.001 at m = 1e3, 89 deg (white,
    float64), against exactly ``<= 1`` for the integral. Measured now (white, half-vector
    rule over k', float64): the default-order ``E_double`` is within 3% (at worst 1e-2
    absolute, m = 0 near grazing, where it is *below* the converged value) of order (24, 64),
    and ``E_single + E_double <= 0.9995`` on m in [0, 1e5] x [0, 89 deg]
    (tests/test_furnace.py). The inner ``<h.u1>+`` uses a short fixed rule
    (:func:`_mean_cosine_plus_fast`, :func:`_mcp_interpolant`).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._safe import float_dtype, safe_atan2, safe_sqrt, tiny
from .._types import Array, ArrayLike, Complex, Float
from ..optics._frames import A_STOKES, mueller_rotator, perpendicular_unit, rotation_cos_sin_2a
from ..optics._fresnel import fresnel_amplitudes_re
from ..optics.conventions import DEFAULT_WAVELENGTH_M

__all__ = [
    "DEFAULT_ORDER",
    "INNER_ORDER",
    "coherence_factor",
    "double_bounce_term",
    "double_path_jones",
    "double_bounce_incoherent",
]

DEFAULT_ORDER: tuple[int, int] = (3, 12)
"""Default ``(n_u, n_phi)`` of each half of the quadrature: ``n_u`` Gauss-Legendre nodes in
each of the three ``u`` panels, ``n_phi`` azimuths (module docstring, "Quadrature")."""

INNER_ORDER: int = 16
"""Nodes of the ``<h.u>+`` quadrature at each of the CHEB_DEGREE + 1 Chebyshev nodes."""

_LN2 = math.log(2.0)

DOUBLE_THICK_MODE: str = "incoherent"
"""Treatment of a thick film layer at the facets of the double bounce's quadrature: the
phase-averaged (incoherent) facet whatever the material's ``film_mode``. The double term
matters for rough surfaces (``m`` below ~30), where a thick layer's fringes average out over
the lobe except within a few degrees of normal facet incidence, and its paths meet facets
tilted ~45 deg; the lobe series at every node of the quadrature cost ~10x the bare term
(measured difference to the lobe treatment: bench/results/films.md)."""


# --------------------------------------------------------------------------------------------
# small structure-of-arrays vector helpers (tuples of 3 arrays: XLA fuses them well)


def _sdot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _scross(a, b):
    return (
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    )


def _sscale(s, a):
    return (s * a[0], s * a[1], s * a[2])


def _sneg(a):
    return (-a[0], -a[1], -a[2])


def _snormalize(v, fallback, thr):
    """normalize(v) where |v|^2 > thr, else ``fallback`` (zero gradient through v there).

    ``thr`` must keep the derivative of ``v / |v|`` (``|v|^-3`` inside ``rsqrt``'s tangent)
    finite: at least ``eps^2`` (``|v|`` at rounding level). A threshold near ``tiny`` let
    ``|v|^2 ~ 1e-34`` through in float32 (a cross product of nearly parallel unit vectors
    with a 1e-16 out-of-plane component) and ``rsqrt``'s tangent overflowed to inf, then NaN.
    """
    sq = _sdot(v, v)
    ok = sq > thr
    inv = jax.lax.rsqrt(jnp.where(ok, sq, 1.0))
    return tuple(jnp.where(ok, vi * inv, fi) for vi, fi in zip(v, fallback, strict=True)), ok


def _split(v):
    return (v[..., 0], v[..., 1], v[..., 2])


# --------------------------------------------------------------------------------------------
# constant linear maps: coherency sums -> Mueller, and the reciprocal-path interference map

# j = (J11, J12, J21, J22); K_{(i k),(j l)} = J_ij J*_kl ; M = A K A^-1.
# H_{ab} = sum w j_a j_b^* is stored as 16 reals:
#   diag |j_a|^2 (4), then Re and Im of H_ab for a < b (6 + 6).
_PAIRS = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]


def _h_from_reals(h16: np.ndarray) -> np.ndarray:
    H = np.zeros((4, 4), complex)
    for a in range(4):
        H[a, a] = h16[a]
    for p, (a, b) in enumerate(_PAIRS):
        H[a, b] = h16[4 + p] + 1j * h16[10 + p]
        H[b, a] = np.conj(H[a, b])
    return H


def _mueller_of_h(H: np.ndarray) -> np.ndarray:
    # index of j: a = 2 i + j for J_ij ; K[(i,k),(j,l)] = H[(i,j),(k,l)]
    K = np.zeros((4, 4), complex)
    for i in range(2):
        for j in range(2):
            for k in range(2):
                for l_ in range(2):
                    K[2 * i + k, 2 * j + l_] = H[2 * i + j, 2 * k + l_]
    A = np.asarray(A_STOKES)
    return A @ K @ np.linalg.inv(A)


# reversed path: J_r = Q J^T Q, Q = diag(1,-1): (J11, J12, J21, J22) -> (J11, -J21, -J12, J22)
_L = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], float)


@functools.cache
def _linear_maps() -> tuple[np.ndarray, np.ndarray]:
    """(G_inc, G_coh): 16 x 16 real maps from the 16 coherency reals to the Mueller elements
    (row-major) of ``sum w J_f (x) J_f^*`` and of the fully coherent pair
    ``sum w (1/2) (J_f + J_r) (x) (J_f + J_r)^*``."""
    g_inc = np.zeros((16, 16))
    g_coh = np.zeros((16, 16))
    IL = np.eye(4) + _L
    for col in range(16):
        e = np.zeros(16)
        e[col] = 1.0
        H = _h_from_reals(e)
        g_inc[:, col] = _mueller_of_h(H).real.ravel()
        g_coh[:, col] = _mueller_of_h(0.5 * IL @ H @ IL.T).real.ravel()
    return g_inc, g_coh


# --------------------------------------------------------------------------------------------
# public pieces


def coherence_factor(
    k_in: Float[ArrayLike, "... 3"],
    k_out: Float[ArrayLike, "... 3"],
    wavelength: Float[ArrayLike, "..."] | float,
    corr_length: Float[ArrayLike, "..."] | float,
) -> Float[Array, "..."]:
    """Coherence ``gamma(psi) = exp(-ln2 |k' - k|^2 / psi_h^2)``, ``psi_h = lambda / (4 d)``.

    ``|k' - k| = 2 sin(psi/2)`` with ``psi`` the bistatic angle; ``gamma(0) = 1``,
    ``gamma(psi_h) ~= 1/2``. Smooth in all arguments.
    """
    dt = float_dtype(k_in, k_out, wavelength, corr_length)
    k_in = jnp.asarray(k_in, dt)
    k_out = jnp.asarray(k_out, dt)
    dk = k_out - k_in
    # component by component: a last-axis jnp.sum became a reduction fusion that made the
    # table term 6x slower on XLA CPU (measured)
    q2 = dk[..., 0] * dk[..., 0] + dk[..., 1] * dk[..., 1] + dk[..., 2] * dk[..., 2]
    psi_h = jnp.asarray(wavelength, dt) / (4.0 * jnp.asarray(corr_length, dt))
    return jnp.exp(-_LN2 * q2 / (psi_h * psi_h))


def _fresnel(n_re, n_im, cos_t, white: bool):
    if white:
        one = jnp.ones_like(cos_t)
        zero = jnp.zeros_like(cos_t)
        # ideal white: lossless, perfect-conductor-like facet, |r_s| = |r_p| = 1
        return -one, zero, one, zero
    return fresnel_amplitudes_re(n_re, n_im, cos_t)


def _path_jones(k, kp, d1, e, n_re, n_im, white, thr, probe=None, films=None):
    """Jones chain of the path k -> facet 1 -> d1 -> facet 2 -> k' in frames x_in = x_out = e
    (SoA tuples). Returns the J entries as (re, im) pairs for 11, 12, 21, 22.

    ``probe`` (static, for the backscatter tables of :mod:`ppr.brdf.double_table`): ``"s"`` or
    ``"p"`` replaces the Fresnel amplitudes by ``(r_s, r_p) = (1, 0)`` or ``(0, 1)`` at facet 1
    and ``(1, 1)`` at facet 2, so that ``J = a J_s + b J_p`` (``a = r_s1 r_s2``,
    ``b = r_p1 r_p2``) wherever the chain is coplanar (``C_12`` diagonal: exact backscatter).

    ``films`` (:class:`ppr.optics._films.Films`, broadcast like ``n_re``): coated facets. A thick
    (lobe- or phase-averaged) facet is partially depolarizing: it is the incoherent sum of two
    Jones components (:func:`ppr.optics._films.facet_components`), and the chain returns the four
    component pairs of the two facets concatenated along the last (node) axis, so that the
    caller's coherency sum over that axis (weights tiled four times) has the exact second
    moments of independent averaged facets.
    """
    # cos t1 = |k + d1| / 2, cos t2 = |k' - d1| / 2 (both mirror geometries)
    a1 = tuple(x + y for x, y in zip(k, d1, strict=True))
    a2 = tuple(x - y for x, y in zip(kp, d1, strict=True))
    c1 = jnp.clip(0.5 * safe_sqrt(_sdot(a1, a1)), 0.0, 1.0)
    c2 = jnp.clip(0.5 * safe_sqrt(_sdot(a2, a2)), 0.0, 1.0)
    combos = None
    if probe is None and films is not None:
        from ..optics._films import Films, facet_amplitudes, facet_components  # noqa: PLC0415

        fx = jax.tree.map(lambda a: a[..., None], films)
        if not films.coherent and films.mode != DOUBLE_THICK_MODE:
            fx = Films(
                fx.n_re, fx.n_im, fx.kt, fx.m, mode=DOUBLE_THICK_MODE, thick=films.thick
            )
        cc = jnp.stack([c1, c2], -1)
        if films.coherent:
            both = facet_amplitudes(n_re[..., None], n_im[..., None], cc, fx)
            rs1r, rs1i, rp1r, rp1i = (r[..., 0] for r in both)
            rs2r, rs2i, rp2r, rp2i = (r[..., 1] for r in both)
        else:
            comp = facet_components(n_re[..., None], n_im[..., None], cc, fx)
            # comp[c] = (x, y) amplitudes of component c at both facets (last axis 2)
            amp = [
                tuple((x[0][..., f], x[1][..., f], y[0][..., f], y[1][..., f]) for x, y in comp)
                for f in (0, 1)
            ]
            combos = [(amp[0][i], amp[1][j]) for i in (0, 1) for j in (0, 1)]
    elif probe is None:
        # both facets in one Fresnel evaluation (half its traced program: compile time)
        both = _fresnel(n_re[..., None], n_im[..., None], jnp.stack([c1, c2], -1), white)
        rs1r, rs1i, rp1r, rp1i = (r[..., 0] for r in both)
        rs2r, rs2i, rp2r, rp2i = (r[..., 1] for r in both)
    else:
        one, zero = jnp.ones_like(c1), jnp.zeros_like(c1)
        rs2r, rs2i, rp2r, rp2i = one, zero, one, zero
        if probe == "s":
            rs1r, rs1i, rp1r, rp1i = one, zero, zero, zero
        else:
            rs1r, rs1i, rp1r, rp1i = zero, zero, one, zero
    # facet s/p frames; fallbacks (normal incidence on a facet) use e, which is _|_ k and k'.
    # The fallback takes over below |s|^2 = eps (not ~tiny): at normal incidence on a facet
    # r_p = -r_s and the facet's operator does not depend on s; near it the dependence is
    # O(|s|^2) (r_s + r_p = O(t^2)), so the switch costs ~eps in value, and the gradient
    # through s (~ rounding / |s|) stays small, as in ppr.optics._frames._facet_frames3
    ceps = float(np.finfo(k[0].dtype).eps)
    s1, _ = _snormalize(_scross(k, d1), e, ceps)
    p_in1 = _scross(_sneg(k), s1)
    p_out1 = _scross(d1, s1)
    s2, _ = _snormalize(_scross(_sneg(d1), kp), e, ceps)
    p_in2 = _scross(d1, s2)
    p_out2 = _scross(kp, s2)
    y_in = _scross(_sneg(k), e)
    y_out = _scross(kp, e)
    # P_in1
    a11, a12 = _sdot(s1, e), _sdot(s1, y_in)
    a21, a22 = _sdot(p_in1, e), _sdot(p_in1, y_in)
    # C_12
    c11, c12 = _sdot(s2, s1), _sdot(s2, p_out1)
    c21, c22 = _sdot(p_in2, s1), _sdot(p_in2, p_out1)
    # P_out2
    b11, b12 = _sdot(e, s2), _sdot(e, p_out2)
    b21, b22 = _sdot(y_out, s2), _sdot(y_out, p_out2)

    def lin(p, q, u, w):  # p*u + q*w for real p, q and complex u, w
        return (p * u[0] + q * w[0], p * u[1] + q * w[1])

    def cmul(r, u):  # (r_re + i r_im) * u
        return (r[0] * u[0] - r[1] * u[1], r[0] * u[1] + r[1] * u[0])

    def chain(rs1r, rs1i, rp1r, rp1i, rs2r, rs2i, rp2r, rp2i):
        # X = diag(rs1, rp1) P_in1 (complex rows)
        x11 = (rs1r * a11, rs1i * a11)
        x12 = (rs1r * a12, rs1i * a12)
        x21 = (rp1r * a21, rp1i * a21)
        x22 = (rp1r * a22, rp1i * a22)
        # Y = C_12 X
        y11 = lin(c11, c12, x11, x21)
        y12 = lin(c11, c12, x12, x22)
        y21 = lin(c21, c22, x11, x21)
        y22 = lin(c21, c22, x12, x22)
        # Z = diag(rs2, rp2) Y
        z11 = cmul((rs2r, rs2i), y11)
        z12 = cmul((rs2r, rs2i), y12)
        z21 = cmul((rp2r, rp2i), y21)
        z22 = cmul((rp2r, rp2i), y22)
        # J = P_out2 Z
        j11 = lin(b11, b12, z11, z21)
        j12 = lin(b11, b12, z12, z22)
        j21 = lin(b21, b22, z11, z21)
        j22 = lin(b21, b22, z12, z22)
        return (j11, j12, j21, j22)

    if combos is None:
        return chain(rs1r, rs1i, rp1r, rp1i, rs2r, rs2i, rp2r, rp2i)
    parts = [chain(*f1, *f2) for f1, f2 in combos]
    cat = lambda *xs: jnp.concatenate(xs, axis=-1)  # noqa: E731
    return tuple(
        tuple(cat(*(p[a][ri] for p in parts)) for ri in (0, 1)) for a in range(4)
    )


def _common_frame(k, kp, normal, dt):
    """e = normalize(k x k') (_|_ both), or near backscatter a vector _|_ k (array form)."""
    cr = jnp.cross(k, kp)
    sq = jnp.sum(cr * cr, axis=-1, keepdims=True)
    ok = sq > jnp.finfo(dt).eps
    e1 = cr / jnp.sqrt(jnp.where(ok, sq, 1.0))
    # fallback: s direction of the plane of incidence of k, or any _|_ k
    cr2 = jnp.cross(normal, k)
    sq2 = jnp.sum(cr2 * cr2, axis=-1, keepdims=True)
    ok2 = sq2 > jnp.finfo(dt).eps
    e2 = jnp.where(ok2, cr2 / jnp.sqrt(jnp.where(ok2, sq2, 1.0)), perpendicular_unit(k))
    return jnp.where(ok, e1, e2)


def _tangent_frame(k, normal, dt):
    t = k - jnp.sum(k * normal, axis=-1, keepdims=True) * normal
    sq = jnp.sum(t * t, axis=-1, keepdims=True)
    ok = sq > jnp.finfo(dt).eps
    t1 = jnp.where(ok, t / jnp.sqrt(jnp.where(ok, sq, 1.0)), perpendicular_unit(normal))
    t2 = jnp.cross(normal, t1)
    return t1, t2


def _tilt_nodes(m: Array, order: int, dt):
    """Gauss-Legendre nodes ``b`` (..., order) on ``[0, bmax]``, ``bmax = min(pi/2,
    7/sqrt(m+1))`` (``cos^m`` < e^-24 beyond), with ``bmax`` and the weights on [0, 1]."""
    x, w = np.polynomial.legendre.leggauss(order)
    x = jnp.asarray(0.5 * (x + 1.0), dt)
    w = jnp.asarray(0.5 * w, dt)
    bmax = jnp.minimum(0.5 * math.pi, 7.0 * jax.lax.rsqrt(m + 1.0))
    return bmax[..., None] * x, bmax, w


def _mean_cosine_plus_fast(m: Array, c: Array, order: int) -> Array:
    """``<h.u>+`` for ``u.n = c`` by a short fixed rule (inner weight of the h1 quadrature).

    ``<h.u>+ = c <h.n> + (m+1) s^(m+2) / pi int_0^(pi/2) cos^m b sin b
    [sin b - c cos b atan2(sin b, c cos b)] db`` (``s^2 = 1 - c^2``; from the azimuthal closed
    form of ``ppr.brdf._microfacet`` with ``t = s cos b``): smooth in ``b``, truncated at
    ``b = min(pi/2, 7/sqrt(m+1))`` (``cos^m`` < e^-24 beyond), Gauss-Legendre with ``order``
    nodes. Relative error (vs ``ppr.microfacet.mean_cosine_plus`` at order 256): 8 nodes
    <= 8e-4 for m in [0, 1e4] (worst at non-integer m < 1, ``cos^m`` at ``b = pi/2``).
    """
    dt = c.dtype
    b, bmax, w = _tilt_nodes(m, order, dt)
    cb, sb = jnp.cos(b), jnp.sin(b)
    cc = c[..., None]
    mm = m[..., None]
    sh = jnp.sin(0.5 * b)
    lcb = jnp.log1p(-2.0 * sh * sh)  # log cos b, accurate at b ~ 1e-3 (m = 1e6) in float32
    f = jnp.exp(mm * lcb) * sb * (sb - cc * cb * jnp.arctan2(sb, cc * cb))
    s2 = jnp.clip((1.0 - c) * (1.0 + c), 0.0, 1.0)
    ok = s2 > tiny(dt) * 1e3
    log_s2 = jnp.log(jnp.where(ok, s2, 1.0))
    sm2 = jnp.where(ok, jnp.exp(0.5 * (m + 2.0) * log_s2), 0.0)
    excess = (m + 1.0) / math.pi * sm2 * bmax * jnp.sum(w * f, axis=-1)
    return c * (m + 1.0) / (m + 2.0) + excess


CHEB_DEGREE = 8
"""Degree of the Chebyshev interpolant in ``c`` of ``<h.u>+`` used per quadrature node."""

CHEB_RANGE = 7.0
"""The interpolant covers ``c`` in ``[0, c_max]``, ``c_max = min(1, CHEB_RANGE / sqrt(m + 1))``;
beyond, ``s^(m+2) <= exp(-CHEB_RANGE^2 / 2) = 2e-11`` and ``g`` is held at ``g(c_max)``."""

CHEB_WARP = 0.5
"""``c = c_max ((1 - a) y + a y^2)``, ``y`` in [0, 1] the Chebyshev variable: more nodes near
``c = 0``, where ``g`` has a ``c^2 log c`` term (finite slope: ``dc/dy > 0`` everywhere)."""


@functools.cache
def _cheb(deg: int):
    """Chebyshev nodes ``x_j`` on [-1, 1] and the matrix taking values at them to coefficients."""
    j = np.arange(deg + 1)
    x = np.cos(np.pi * (j + 0.5) / (deg + 1))
    T = np.cos(np.outer(np.arange(deg + 1), np.arccos(x)))  # T_i(x_j)
    C = 2.0 / (deg + 1) * T
    C[0] *= 0.5
    return x, C


def _excess_shape(m: Array, c: Array, order: int) -> Array:
    """``g(m, c)`` with ``<h.u>+ = c <h.n> + s^(m+2) g`` (see :func:`_mean_cosine_plus_fast`)."""
    dt = c.dtype
    b, bmax, w = _tilt_nodes(m, order, dt)
    cb, sb = jnp.cos(b), jnp.sin(b)
    sh = jnp.sin(0.5 * b)
    lcb = jnp.log1p(-2.0 * sh * sh)
    cc = c[..., None]
    f = jnp.exp(m[..., None] * lcb) * sb * (sb - cc * cb * jnp.arctan2(sb, cc * cb))
    return (m + 1.0) / math.pi * bmax * jnp.sum(w * f, axis=-1)


def _cheb_cmax(m: Array) -> Array:
    return jnp.minimum(1.0, CHEB_RANGE * jax.lax.rsqrt(m + 1.0))


def _mcp_interpolant(m: Array, order: int):
    """Per-element Chebyshev coefficients (..., deg+1) of ``g(m, c)`` on ``c`` in
    ``[0, c_max(m)]`` in the warped variable ``y`` (:data:`CHEB_RANGE`, :data:`CHEB_WARP`).

    ``g`` varies on the scale ``c ~ 1/sqrt(m)`` (the grazing band), so the interval shrinks
    with m; an interpolant on the fixed ``c`` in [0, 1] (before) underestimated ``<h.u>+``
    at grazing by 10% at m = 1e3 and 46% at m = 1e4 (hence ``P(k)`` and the double term too
    large there: ``E_single + E_double`` = 1.016 at m = 1e4, 89 deg). Relative error of the
    resulting ``<h.u>+`` vs ``ppr.microfacet.mean_cosine_plus`` (order 256), max over
    ``c`` in [0, 1]: 2.2e-4 at m = 0.3 (the inner rule's ``cos^m`` endpoint), <= 1.5e-5 for
    m in [1, 10], 3e-6 at m = 30, <= 2.8e-5 for m in [100, 1e6]
    (tests/test_double.py::test_inner_mean_cosine_interpolant_against_quadrature).
    """
    dt = m.dtype
    x, C = _cheb(CHEB_DEGREE)
    y = 0.5 * (x + 1.0)
    yc = jnp.asarray((1.0 - CHEB_WARP) * y + CHEB_WARP * y * y, dt)
    cn = _cheb_cmax(m)[..., None] * yc
    g = _excess_shape(m[..., None], cn, order)
    return g @ jnp.asarray(C, dt).T


def _mcp_eval(coef: Array, m: Array, c: Array) -> Array:
    """``<h.u>+`` at ``u.n = c`` from the coefficients (Clenshaw); shapes broadcast."""
    dt = c.dtype
    q = jnp.minimum(c / _cheb_cmax(m), 1.0)
    a = CHEB_WARP
    # inverse of q = (1 - a) y + a y^2 (the sqrt argument is >= (1 - a)^2: smooth)
    y = 2.0 * q / ((1.0 - a) + jnp.sqrt((1.0 - a) ** 2 + 4.0 * a * q))
    x = 2.0 * y - 1.0
    deg = coef.shape[-1] - 1
    b1 = jnp.zeros_like(x)
    b2 = jnp.zeros_like(x)
    for i in range(deg, 0, -1):
        b1, b2 = 2.0 * x * b1 - b2 + coef[..., i], b1
    g = x * b1 - b2 + coef[..., 0]
    s2 = jnp.clip((1.0 - c) * (1.0 + c), 0.0, 1.0)
    ok = s2 > tiny(dt) * 1e3
    sm2 = jnp.where(ok, jnp.exp(0.5 * (m + 2.0) * jnp.log(jnp.where(ok, s2, 1.0))), 0.0)
    return c * (m + 1.0) / (m + 2.0) + sm2 * g


PHI_SCALE = (1.0, 0.25)
"""``(A, B)`` of the azimuth map's scale ``lambda = c (A + B sqrt(m + 1)) / s`` (see
:func:`_phi_nodes`)."""


@functools.cache
def _nodes(n_u: int, n_phi: int):
    """Gauss-Legendre nodes/weights on [0, 1] for u (per panel) and for the azimuth variable
    (per quarter panel, ``max(n_phi // 4, 1)`` nodes)."""
    x, w = np.polynomial.legendre.leggauss(n_u)
    nq = max(n_phi // 4, 1)
    xp, wp = np.polynomial.legendre.leggauss(nq)
    return 0.5 * (x + 1.0), 0.5 * w, 0.5 * (xp + 1.0), 0.5 * wp


def _phi_nodes(c, s, m, tp, wp):
    """Azimuth nodes ``(cos phi, sin phi, weight / (2 pi))``, shapes ``(..., 4 nq)``.

    Four quarter panels with ends at ``phi = 0, pi/2, pi, 3pi/2`` (the plane of incidence and
    the shadow-boundary kink ``phi = +-pi/2`` are panel ends). In each, with ``delta`` the
    distance to the nearest ``+-pi/2``, ``log(delta + lambda)`` is uniform:
    ``delta = lambda expm1(t log1p(pi / (2 lambda)))``. The lit facets that send the beam
    below the horizon (``t`` in ``[t_max / 2, t_max]``, ``tan t_max = c / (s sin delta)``)
    enter the lobe (``t ~ 1/sqrt(m)``) only for ``sin delta`` below about
    ``c sqrt(m) / s``: near grazing that is a thin band around ``+-pi/2``, which plain
    Gauss-Legendre in ``phi`` misses; ``lambda -> inf`` (normal incidence) is plain GL.
    """
    ex = lambda a: a[..., None]  # noqa: E731
    a, b = PHI_SCALE
    ok = s > 1e-6 * c
    lam = jnp.where(ok, c * (a + b * jnp.sqrt(m + 1.0)) / jnp.where(ok, s, 1.0), 1e6)
    lam = jnp.minimum(lam, 1e6)
    # L = log1p(pi / (2 lam)); for lam < 1 as log(lam + pi/2) - log(lam): the quotient's
    # derivative is formed with lam^2, which underflows in float32 at k.n ~ 1e-20 (inf, NaN)
    small = lam < 1.0
    lam_s = jnp.where(small, lam, 1.0)
    L = jnp.where(
        small,
        jnp.log(lam_s + 0.5 * math.pi) - jnp.log(lam_s),
        jnp.log1p(0.5 * math.pi / jnp.where(small, 1.0, lam)),
    )
    d = ex(lam) * jnp.expm1(ex(L) * tp)  # (..., nq)
    wd = ex(L) * (d + ex(lam)) * wp / (2.0 * math.pi)
    sd, cd = jnp.sin(d), jnp.cos(d)
    cph = jnp.concatenate([sd, -sd, -sd, sd], axis=-1)
    sph = jnp.concatenate([cd, cd, -cd, -cd], axis=-1)
    wph = jnp.concatenate([wd, wd, wd, wd], axis=-1)
    return cph, sph, wph


def _log_cos_pow(m, ts, thr):
    """``cos^(m+1) t`` for each ``t`` in ``ts`` (in [0, pi/2]); 0 at ``cos t <= thr`` (double
    where: no ``log(0)`` in the gradient). ``log cos t = log1p(-2 sin^2(t/2))``: accurate for
    the small angles of m = 1e6 in float32."""
    out = []
    for t in ts:
        sh = jnp.sin(0.5 * t)
        ct = jnp.cos(t)
        ok = ct > thr
        small = t < 1.0  # log1p form near 0, log(cos t) near pi/2 (where 2 sh^2 rounds to 1)
        lg_s = jnp.log1p(jnp.where(small, -2.0 * sh * sh, 0.0))
        lg_l = jnp.log(jnp.where(ok & ~small, ct, 1.0))
        lg = jnp.where(small, lg_s, lg_l)
        out.append(jnp.where(ok, jnp.exp((m + 1.0) * lg), 0.0))
    return out


def _lobe_pow(m, h, nq, hn, thr):
    """(h.n)^m from |h - n|^2 (float32-accurate near h = n), 0 for h.n <= thr."""
    dv = tuple(a - b for a, b in zip(h, nq, strict=True))
    q2 = _sdot(dv, dv)
    ok = hn > thr
    lg = jnp.log1p(-0.5 * jnp.clip(jnp.where(ok, q2, 0.0), 0.0, 1.999))
    return jnp.where(ok, jnp.exp(m * lg), 0.0), ok, m * lg


def _azimuth_f(a, d, nq, thr):
    """Ashikhmin's f(phi) = cos(phi / 2) = |u_a + u_d| / 2 (unit projections on the surface
    plane); 1 where a projection vanishes (SoA tuples)."""
    pa = tuple(x - _sdot(a, nq) * y for x, y in zip(a, nq, strict=True))
    pd = tuple(x - _sdot(d, nq) * y for x, y in zip(d, nq, strict=True))
    fb = tuple(jnp.zeros_like(pd[0]) for _ in range(3))
    # below |projection|^2 = eps the direction is along the normal, where P = 1 and f does
    # not enter the joint visibility (and an eps threshold keeps d(v/|v|) finite, see
    # _snormalize)
    ceps = float(np.finfo(pa[0].dtype).eps)
    ua, oka = _snormalize(pa, fb, max(thr * 1e6, ceps))
    ud, okd = _snormalize(pd, fb, max(thr * 1e6, ceps))
    sm = tuple(x + y for x, y in zip(ua, ud, strict=True))
    f = 0.5 * safe_sqrt(jnp.clip(_sdot(sm, sm), 0.0, 4.0))
    return jnp.where(oka & okd, jnp.clip(f, 0.0, 1.0), 1.0)


def _rho(p_a, p_d, f):
    """(P(a) - P(a|d)) / (P(a) (1 - P(d))) in [0, 1] with the Ashikhmin joint visibility
    P(a|d) = (1 - f) P(a) P(d) + f min(P(a), P(d)); 1 where undefined (P(a) = 0 or P(d) = 1,
    where the factor it multiplies vanishes anyway)."""
    joint = (1.0 - f) * p_a * p_d + f * jnp.minimum(p_a, p_d)
    num = p_a - joint
    den = p_a * (1.0 - p_d)
    ok = den > 1e-30
    # both divided first by den held constant for differentiation: the quotient's derivative
    # is otherwise formed with den^2, which underflows in float32 at grazing (P(a) ~ k.n)
    s = jax.lax.stop_gradient(jnp.where(ok, den, 1.0))
    return jnp.where(ok, jnp.clip((num / s) / jnp.where(ok, den / s, 1.0), 0.0, 1.0), 1.0)


def _accumulate(
    k, kp, normal, e, m, n_re, n_im, *, order, inner_order, white, coef=None, films=None
):
    """Balance-weighted sum of the h1- and h2-parametrized halves (module docstring).

    Both halves are one traced computation on inputs stacked along a new leading axis of 2
    (the h2 half is the h1 half with ``k`` and ``k'`` swapped and its Jones chain reversed:
    :func:`_half_paths` with an array ``reverse``): the same arithmetic as two calls, half
    the program, so half the XLA compilation time of the quadrature."""
    if coef is None:
        coef = _mcp_interpolant(m, inner_order)
    two = lambda a: jnp.broadcast_to(a, (2,) + jnp.shape(a))  # noqa: E731
    rev = jnp.array([False, True]).reshape((2,) + (1,) * (k.ndim - 1))
    w, J, _ = _half_paths(
        jnp.stack([k, kp]),
        jnp.stack([kp, k]),
        two(normal),
        two(e),
        two(m),
        two(n_re),
        two(n_im),
        reverse=rev,
        order=order,
        coef=two(coef),
        white=white,
        films=None if films is None else jax.tree.map(two, films),
    )
    return _coherency_sums(w, J, axes=(0, -1))


def _accumulate_half(k, kp, normal, e, m, n_re, n_im, *, reverse, order, coef, white):
    """16 coherency reals of sum_nodes w * vec(J_f) vec(J_f)^† for eq. (D) without its
    prefactor (:func:`_half_paths` gives the nodes). Returns (..., 16)."""
    w, J, _ = _half_paths(
        k, kp, normal, e, m, n_re, n_im, reverse=reverse, order=order, coef=coef, white=white
    )
    return _coherency_sums(w, J, axes=-1)


def _coherency_sums(w, J, axes):
    """``sum w vec(J) vec(J)^†`` over the node axes: 16 reals (4 |j_a|^2, then Re and Im of
    the 6 ``j_a j_b^*``), stacked last."""
    # materialize the Jones entries once: without the barrier XLA fuses the whole chain into
    # each of the 16 reductions below (16x the work, measured)
    w, J = jax.lax.optimization_barrier((w, J))
    re = [J[a][0] for a in range(4)]
    im = [J[a][1] for a in range(4)]
    out = [jnp.sum(w * (re[a] * re[a] + im[a] * im[a]), axis=axes) for a in range(4)]
    cross_re, cross_im = [], []
    for a, b in _PAIRS:
        # j_a j_b^*
        cross_re.append(jnp.sum(w * (re[a] * re[b] + im[a] * im[b]), axis=axes))
        cross_im.append(jnp.sum(w * (im[a] * re[b] - re[a] * im[b]), axis=axes))
    return jnp.stack(out + cross_re + cross_im, axis=-1)


def _half_paths(
    k, kp, normal, e, m, n_re, n_im, *, reverse, order, coef, white, probe=None, films=None
):
    """Nodes of one half of the quadrature: weights ``w`` (..., N), Jones entries ``J`` (4
    (re, im) pairs of (..., N)) and ``cos t`` at the path's first facet in its
    parametrization (..., N). ``sum w vec(J) vec(J)^†`` is eq. (D) without its prefactor
    (module docstring, "Quadrature"); ``probe``: :func:`_path_jones`.

    h1 = (sin t cos phi, sin t sin phi, cos t) about n, phi from the projection of k. Lit facets
    (h1.k > 0) are exactly ``t < t_max(phi)``, ``tan t_max = c / (s max(-cos phi, 0))``, so
    the lobe variable u = cos^(m+1) t runs over [u_min(phi), 1], u_min = cos^(m+1) t_max:
    the shadow boundary is a panel end, not a kink inside the rule. Arrays: k, kp, normal, e
    (..., 3); m, n_re, n_im (...).
    """
    dt = k.dtype
    thr = tiny(dt) * 1e3
    n_u, n_phi = order
    t, wt, tp, wp = (jnp.asarray(a, dt) for a in _nodes(n_u, n_phi))
    ex = lambda a: a[..., None]  # noqa: E731
    c = jnp.clip(jnp.sum(k * normal, axis=-1), 0.0, 1.0)
    s = safe_sqrt(jnp.clip((1.0 - c) * (1.0 + c), 0.0, 1.0))
    cp = jnp.clip(jnp.sum(kp * normal, axis=-1), 0.0, 1.0)
    cph, sph, wph = _phi_nodes(c, s, m, tp, wp)  # (..., P)
    # panel ends in t (module docstring, "Quadrature"): d1.n = R cos(2t - alpha),
    # R = sqrt(c^2 + s^2 cos^2 phi), alpha = atan2(s cos phi, c) in [-pi/2, pi/2]
    scp = ex(s) * cph  # (..., P)
    alpha = safe_atan2(scp, ex(c))
    R2 = ex(c) ** 2 + scp**2
    t_max = jnp.minimum(0.5 * math.pi, 0.5 * math.pi + alpha)  # shadow boundary h1.k = 0
    t_0 = 0.5 * alpha + 0.25 * math.pi  # horizon of d1 (d1.n = 0)
    # h2.n = k'.n - d1.n > 0 fails for |2t - alpha| < beta, beta = acos(c' / R) (if c' < R)
    beta = safe_atan2(safe_sqrt(jnp.clip(R2 - ex(cp) ** 2, 0.0, None)), ex(cp))
    t_a = jnp.clip(0.5 * (alpha - beta), 0.0, t_0)
    t_b = jnp.clip(0.5 * (alpha + beta), 0.0, t_0)
    lc = _log_cos_pow(ex(m), (t_a, t_b, t_0, t_max), thr)  # u = cos^(m+1) t at the ends
    u_a, u_b, u_0, u_mx = lc
    one = jnp.ones_like(u_a)
    lo = jnp.stack([u_a, u_0, u_mx], axis=-1)  # (..., P, 3): panels A, B, C in u
    hi = jnp.stack([one, u_b, u_0], axis=-1)
    u = lo[..., None] + (hi - lo)[..., None] * t  # (..., P, 3, U)
    wq = ex(ex(wph)) * (hi - lo)[..., None] * wt
    P, U = cph.shape[-1], 3 * t.shape[0]
    batch = k.shape[:-1]
    u = u.reshape(batch + (P * U,))
    wq = wq.reshape(batch + (P * U,))
    cphq = jnp.repeat(cph, U, axis=-1)
    sphq = jnp.repeat(sph, U, axis=-1)
    mq = ex(m)
    logu = jnp.log(jnp.where(u > thr, u, thr))
    a_n = mq + 1.0
    cos_t = jnp.exp(logu / a_n)
    one_m = -jnp.expm1(logu / a_n)
    sin_t = safe_sqrt(jnp.clip(one_m * (1.0 + cos_t), 0.0, None))
    t1, t2 = _tangent_frame(k, normal, dt)
    h1 = tuple(
        sin_t * cphq * ex(t1[..., i]) + sin_t * sphq * ex(t2[..., i]) + cos_t * ex(normal[..., i])
        for i in range(3)
    )
    kq = tuple(ex(k[..., i]) for i in range(3))
    kpq = tuple(ex(kp[..., i]) for i in range(3))
    nq = tuple(ex(normal[..., i]) for i in range(3))
    eq = tuple(ex(e[..., i]) for i in range(3))
    c1 = jnp.clip(_sdot(kq, h1), 0.0, 1.0)
    d1 = tuple(2.0 * c1 * hi - ki for hi, ki in zip(h1, kq, strict=True))
    fb = (jnp.zeros_like(c1), jnp.zeros_like(c1), jnp.ones_like(c1))
    # |k' - d1| below rounding (eps) has no direction (and keeps d(v/|v|) finite: _snormalize)
    h2, ok2 = _snormalize(
        tuple(a - b for a, b in zip(kpq, d1, strict=True)), fb, float(np.finfo(dt).eps) ** 2
    )
    p2, v2, log_p2 = _lobe_pow(mq, h2, nq, _sdot(h2, nq), thr)
    # balance weight p1 / (p1 + p2) (the other half, parametrized by h2, carries p2 / (p1+p2));
    # p1 = cos^m t = u^(m / (m+1)) up to the common (m+1)/(2 pi). As a logistic function of
    # log p1 - log p2: no underflowing (p1 + p2)^2 in the gradient where both are tiny
    log_p1 = mq * logu / a_n
    bal = jax.nn.sigmoid(log_p1 - jnp.where(v2, log_p2, -1e30))
    valid = ok2 & v2 & (c1 > 0.0)
    dn = _sdot(d1, nq)
    ca = jnp.clip(_sdot(kq, nq), 0.0, 1.0)
    cb = jnp.clip(_sdot(kpq, nq), 0.0, 1.0)
    # <h.u>+ at |d1.n| (per node) and at k.n, k'.n (per element) in one Chebyshev evaluation:
    # each evaluation is an unrolled recurrence, and the three separate ones were a fifth of
    # the traced program (compile time)
    nn = dn.shape[-1]
    mcp = _mcp_eval(coef[..., None, :], mq, jnp.concatenate([jnp.abs(dn), ca, cb], axis=-1))
    inner, mcp_a, mcp_b = mcp[..., :nn], mcp[..., nn : nn + 1], mcp[..., nn + 1 :]
    # shadowing-blocking correlation (module docstring, "Two-facet visibility"):
    # rho(k, d1) rho(k', -d1), each in [0, 1]
    hn = (mq + 1.0) / (mq + 2.0)
    p_d = jnp.clip(hn * jnp.abs(dn) / inner, 0.0, 1.0)  # P(+-d1) of the upward one
    p_a = jnp.clip(hn * ca / mcp_a, 0.0, 1.0)
    p_b = jnp.clip(hn * cb / mcp_b, 0.0, 1.0)
    up = dn > 0.0
    # the one factor that is not 1: rho(k, d1) where d1 heads up, rho(k', -d1) where it heads
    # down (one evaluation on the selected arguments, not two)
    a_up = tuple(jnp.where(up, x, y) for x, y in zip(kq, kpq, strict=True))
    d_up = tuple(jnp.where(up, x, -x) for x in d1)
    rho = _rho(jnp.where(up, p_a, p_b), p_d, _azimuth_f(a_up, d_up, nq, thr))
    w = jnp.where(
        valid, wq * bal * rho * c1 * ((mq + 1.0) / (2.0 * math.pi)) * p2 / (4.0 * inner), 0.0
    )
    fq = None if films is None else jax.tree.map(ex, films)
    if isinstance(reverse, bool):
        if reverse:  # parametrized by the second facet: the forward path is k' -> ... -> k
            J = _path_jones(
                kpq, kq, _sneg(d1), eq, ex(n_re), ex(n_im), white, thr, probe, films=fq
            )
        else:
            J = _path_jones(kq, kpq, d1, eq, ex(n_re), ex(n_im), white, thr, probe, films=fq)
    else:  # per element (both halves in one batch, :func:`_accumulate`)
        rq = ex(reverse)
        first = tuple(jnp.where(rq, b, a) for a, b in zip(kq, kpq, strict=True))
        second = tuple(jnp.where(rq, a, b) for a, b in zip(kq, kpq, strict=True))
        d = tuple(jnp.where(rq, -x, x) for x in d1)
        J = _path_jones(first, second, d, eq, ex(n_re), ex(n_im), white, thr, probe, films=fq)
    reps = J[0][0].shape[-1] // w.shape[-1]
    if reps > 1:  # thick-film facets: four Jones component pairs per node (_path_jones)
        w = jnp.concatenate([w] * reps, axis=-1)
    return w, J, c1


def _broadcast_inputs(k_in, k_out, normal, material, frame_in, frame_out):
    n = jnp.asarray(material.n)
    dt = float_dtype(k_in, k_out, normal, frame_in, frame_out, material.m, n)
    arrs = [jnp.asarray(a, dt) for a in (k_in, k_out, normal, frame_in, frame_out)]
    batch = jnp.broadcast_shapes(*(a.shape[:-1] for a in arrs), jnp.shape(material.m), n.shape)
    arrs = [jnp.broadcast_to(a, batch + (3,)) for a in arrs]
    m = jnp.broadcast_to(jnp.asarray(material.m, dt), batch)
    n_re = jnp.broadcast_to(jnp.real(n).astype(dt), batch)
    n_im = jnp.broadcast_to(jnp.imag(n).astype(dt), batch)
    return (*arrs, m, n_re, n_im, dt, batch)


def _mueller_e_frames(
    k, kp, normal, e, m, n_re, n_im, gamma, *, order, inner_order, white, films=None
):
    """(..., 16) row-major Mueller matrix of the double term in the common frames e."""
    dt = k.dtype
    coef = _mcp_interpolant(m, inner_order)
    h16 = _accumulate(
        k,
        kp,
        normal,
        e,
        m,
        n_re,
        n_im,
        order=order,
        inner_order=inner_order,
        white=white,
        coef=coef,
        films=films,
    )
    g_inc, g_x = (jnp.asarray(g, dt) for g in _linear_maps())
    m_inc = h16 @ g_inc.T
    m_coh = h16 @ g_x.T
    c = jnp.clip(jnp.sum(k * normal, axis=-1), 0.0, 1.0)
    cp = jnp.clip(jnp.sum(kp * normal, axis=-1), 0.0, 1.0)
    hn = (m + 1.0) / (m + 2.0)
    mcp = _mcp_eval(coef[..., None, :], m[..., None], jnp.stack([c, cp], axis=-1))
    pref = hn / (mcp[..., 0] * mcp[..., 1])
    g = gamma[..., None]
    return pref[..., None] * ((1.0 - g) * m_inc + g * m_coh)


def _to_user_frames(M16, k, kp, e, frame_in, frame_out):
    batch = M16.shape[:-1]
    M = M16.reshape(batch + (4, 4))
    # S_e = R(a_in) S_user_in, a_in rotates frame_in -> e about -k;
    # S_user_out = R(a_out) S_e_out, a_out rotates e -> frame_out about +k'
    c_in, s_in = rotation_cos_sin_2a(frame_in, e, -k)
    c_out, s_out = rotation_cos_sin_2a(e, frame_out, kp)
    return mueller_rotator(c_out, s_out) @ M @ mueller_rotator(c_in, s_in)


def double_bounce_term(
    k_in: Float[Array, "*batch 3"],
    k_out: Float[Array, "*batch 3"],
    normal: Float[Array, "*batch 3"],
    material,
    frame_in: Float[Array, "*batch 3"],
    frame_out: Float[Array, "*batch 3"],
    *,
    wavelength: float | Float[ArrayLike, "..."] = DEFAULT_WAVELENGTH_M,
    order: tuple[int, int] = DEFAULT_ORDER,
    inner_order: int = INNER_ORDER,
    coherent: bool = True,
) -> Float[Array, "*batch 4 4"]:
    """Double-bounce Mueller BRDF (1/sr), incoherent sum plus coherent backscatter.

    **Arguments:** the term signature of :mod:`ppr.brdf._brdf` (``k_in``, ``k_out``, ``normal``
    unit ``(..., 3)``; ``frame_in`` the x axis of the incident beam (travelling along
    ``-k_in``), ``frame_out`` of the outgoing beam (along ``+k_out``); ``material`` a
    :class:`ppr.Material`), plus static ``order = (n_u, n_phi)``, ``inner_order`` and
    ``coherent`` (False drops the enhanced-backscatter interference, e.g. for macroscopic
    dihedrals or white-albedo tables).

    **Returns:** ``(..., 4, 4)`` Mueller BRDF of the two-facet paths (module docstring,
    eq. (D)), in the given beam frames. Paths and weights: module docstring.
    """
    k, kp, nrm, f_in, f_out, m, n_re, n_im, dt, batch = _broadcast_inputs(
        k_in, k_out, normal, material, frame_in, frame_out
    )
    # exactly grazing rows (k.n or k'.n <= ~tiny): the BRDF is 0 there (P = 0); replace them by
    # harmless directions before the kernel (double where: zero value, zero gradient)
    g = tiny(dt) * 1e8
    valid = (jnp.sum(k * nrm, -1) > g) & (jnp.sum(kp * nrm, -1) > g)
    v3 = valid[..., None]
    fb = perpendicular_unit(nrm)
    k = jnp.where(v3, k, nrm)
    kp = jnp.where(v3, kp, nrm)
    f_in = jnp.where(v3, f_in, fb)
    f_out = jnp.where(v3, f_out, fb)
    e = _common_frame(k, kp, nrm, dt)
    if coherent:
        gamma = jnp.broadcast_to(
            coherence_factor(k, kp, wavelength, material.corr_length).astype(dt), batch
        )
    else:
        gamma = jnp.zeros(batch, dt)
    white = bool(getattr(material, "white", False))
    from ..optics._films import films_of  # noqa: PLC0415

    M16 = _mueller_e_frames(
        k,
        kp,
        nrm,
        e,
        m,
        n_re,
        n_im,
        gamma,
        order=order,
        inner_order=inner_order,
        white=white,
        films=films_of(material, dt, batch),
    )
    return jnp.where(v3[..., None], _to_user_frames(M16, k, kp, e, f_in, f_out), 0.0)


def double_bounce_incoherent(
    k_in: Float[Array, "*batch 3"],
    k_out: Float[Array, "*batch 3"],
    normal: Float[Array, "*batch 3"],
    material,
    frame_in: Float[Array, "*batch 3"],
    frame_out: Float[Array, "*batch 3"],
    *,
    wavelength: float = DEFAULT_WAVELENGTH_M,
    order: tuple[int, int] = DEFAULT_ORDER,
) -> Float[Array, "*batch 4 4"]:
    """:func:`double_bounce_term` without the coherent interference (``gamma = 0``)."""
    return double_bounce_term(
        k_in,
        k_out,
        normal,
        material,
        frame_in,
        frame_out,
        wavelength=wavelength,
        order=order,
        coherent=False,
    )


def double_path_jones(
    n: Complex[ArrayLike, "..."] | Float[ArrayLike, "..."],
    k_in: Float[ArrayLike, "... 3"],
    h1: Float[ArrayLike, "... 3"],
    k_out: Float[ArrayLike, "... 3"],
    frame: Float[ArrayLike, "... 3"],
) -> Complex[Array, "... 2 2"]:
    """Jones matrix of one double-bounce path ``k_in -> h1 -> h2 -> k_out`` (module docstring).

    ``frame`` is the shared frame vector ``x_in = x_out`` (must be perpendicular to both
    ``k_in`` and ``k_out``). ``h2 = normalize(k_out - d1)``. For tests and figures.
    """
    n = jnp.asarray(n)
    dt = float_dtype(k_in, h1, k_out, frame, jnp.real(n))
    k, h, kp, e = (jnp.asarray(a, dt) for a in (k_in, h1, k_out, frame))
    k, h, kp, e = jnp.broadcast_arrays(k, h, kp, e)
    n_re = jnp.broadcast_to(jnp.real(n).astype(dt), k.shape[:-1])
    n_im = jnp.broadcast_to(jnp.imag(n).astype(dt), k.shape[:-1])
    d1 = 2.0 * jnp.sum(k * h, axis=-1, keepdims=True) * h - k
    J = _path_jones(_split(k), _split(kp), _split(d1), _split(e), n_re, n_im, False, tiny(dt) * 1e3)
    cdt = jnp.result_type(dt, jnp.complex64)
    ent = [a[0].astype(cdt) + 1j * a[1].astype(cdt) for a in J]
    return jnp.stack([jnp.stack(ent[:2], -1), jnp.stack(ent[2:], -1)], -2)


# --------------------------------------------------------------------------------------------
# terms="auto": skip the double term where it does not matter (measured rule)

AUTO_TOL = 1e-3
"""Tolerance of ``terms="auto"``: the double term is left out where its measured relative
contribution to M00 and to the depolarization index of the full BRDF is below this."""

AUTO_M_MAX = 30.0
"""Blinn-Phong exponent from which the double term's contribution stays below ``AUTO_TOL`` at
every geometry measured with a bistatic angle up to ``AUTO_PSI_MAX`` (incidence 0-80 deg,
any bistatic azimuth; aluminium, TiO2, fused silica): docs/double_bounce_table.md
(scripts/double_table.py --matter). Near backscatter a double path needs two facets tilted
~45 deg, weighted ``cos^m(45 deg)^2 = 2^-m``: 1e-9 at m = 30."""

AUTO_PSI_MAX = math.radians(30.0)
"""Largest bistatic angle covered by the measured rule; beyond it the term is always kept
(near-specular geometries with rough-ish surfaces can carry a large double contribution)."""


def double_needed(
    m: Float[ArrayLike, "..."], k_in: Float[ArrayLike, "... 3"], k_out: Float[ArrayLike, "... 3"]
) -> Array:
    """Per-element rule of ``terms="auto"``: keep the double term unless ``m >= AUTO_M_MAX``
    and the bistatic angle is at most ``AUTO_PSI_MAX`` (``|k' - k| = 2 sin(psi/2)``)."""
    dk = jnp.asarray(k_out) - jnp.asarray(k_in)
    far = jnp.sum(dk * dk, axis=-1) > (2.0 * math.sin(0.5 * AUTO_PSI_MAX)) ** 2
    return (jnp.asarray(m) < AUTO_M_MAX) | far
