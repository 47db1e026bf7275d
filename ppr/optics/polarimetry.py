r"""Polarimetric quantities of (batched) 4x4 Mueller matrices.

- :func:`lu_chipman`: polar decomposition ``M = M_Delta @ M_R @ M_D`` (Lu and Chipman,
  J. Opt. Soc. Am. A 13, 1106 (1996)) with diattenuation, polarizance, retardance and
  depolarization power.
- :func:`depolarization_index`: Gil-Bernabeu ``DI = sqrt((sum M_ij^2 - M00^2) / (3 M00^2))``
  (1 for non-depolarizing, 0 for the ideal depolarizer).
- :func:`degree_of_polarization`: DOP of ``M @ s_in``.
- :func:`cloude_eigenvalues`, :func:`is_realizable`: eigenvalues of the Cloude coherency
  matrix ``H = 1/4 sum_ij M_ij sigma_i (x) sigma_j^*`` (Pauli matrices in the Stokes order of
  :mod:`ppr.optics.conventions`: ``sigma_1 = diag(1,-1)``, ``sigma_2 = sigma_x``,
  ``sigma_3 = sigma_y``), ``trace H = M00``; M is a convex sum of Jones-Mueller matrices
  (physically realizable) iff they are all >= 0.

Everything is batched over leading axes and jit-able. The polar step uses a scaled Newton
iteration (Higham) with closed-form 3x3 inverses instead of an eigendecomposition, so
gradients stay finite at degenerate singular values (pure retarders, diagonal depolarizers);
they are zeroed where a quantity is undefined (no light, ``D = 1``, singular ``m'``), which the
result marks in ``valid`` / ``singular``.

Every public function is ``jax.jit``-wrapped: eager calls run one compiled program per input
shape and dtype instead of dispatching dozens of operations one by one (``lu_chipman`` on 300
float64 matrices: first call 6.0 -> 1.3 s, later calls 301 -> 0.6 ms). Under a caller's
``jit`` they are inlined.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._safe import eps, safe_div, safe_sin_from_cos, safe_sqrt, tiny
from .._types import Array, ArrayLike, Bool, Float

__all__ = [
    "LuChipman",
    "cloude_eigenvalues",
    "coherency_matrix",
    "degree_of_polarization",
    "depolarization_index",
    "diattenuation",
    "is_realizable",
    "lu_chipman",
    "polarizance",
    "retardance",
]

MuellerLike = Float[ArrayLike, "... 4 4"]

_NEWTON_STEPS = 12


class LuChipman(NamedTuple):
    """Result of :func:`lu_chipman` (all batched over the leading axes of ``M``).

    - `m00`: transmittance / reflectance ``M00`` for unpolarized light.
    - `diattenuation`, `diattenuation_vector`: ``D = |M[0, 1:]| / M00`` and the vector.
    - `polarizance`, `polarizance_vector`: ``P = |M[1:, 0]| / M00`` and the vector.
    - `retardance`: total retardance ``R`` in radians, ``[0, pi]``.
    - `retardance_vector`: ``R`` times the unit fast axis on the Poincare sphere.
    - `linear_retardance`: ``delta`` (rad) of ``M_R = M_LR(delta) M_CR(psi)``.
    - `optical_rotation`: ``psi`` (rad) with ``M_CR(psi) = mueller_rotator(cos 2psi, sin 2psi)``
      (a rotation of the S1-S2 plane by ``2 psi``); circular retardance is ``2 psi``.
    - `depolarization_power`: ``Delta = 1 - |tr m_Delta| / 3`` (0: none, 1: ideal depolarizer).
    - `M_D`, `M_R`, `M_Delta`: the factors, ``M = M_Delta @ M_R @ M_D`` (``M_D`` carries M00).
    - `valid`: False where ``M00 <= 0`` (no light; quantities are 0, factors identity).
    - `singular`: True where ``m'`` is (numerically) singular, e.g. an ideal depolarizer or
      an ideal polarizer (``D = 1``, where ``M_D`` itself is singular): the decomposition is
      then not unique; ``M_R = I`` is reported (retardance 0) and ``M_Delta = M'``.
    """

    m00: Array
    diattenuation: Array
    diattenuation_vector: Array
    polarizance: Array
    polarizance_vector: Array
    retardance: Array
    retardance_vector: Array
    linear_retardance: Array
    optical_rotation: Array
    depolarization_power: Array
    M_D: Array
    M_R: Array
    M_Delta: Array
    valid: Array
    singular: Array


def _as_mueller(M: ArrayLike) -> Array:
    M = jnp.asarray(M)
    if not jnp.issubdtype(M.dtype, jnp.floating):
        M = M.astype(jnp.result_type(float))
    if M.shape[-2:] != (4, 4):
        raise ValueError(f"M must have shape (..., 4, 4), got {M.shape}")
    return M


def _normalized(M: Array) -> tuple[Array, Array, Array]:
    """(M / M00 with identity where there is no light, M00, valid)."""
    m00 = M[..., 0, 0]
    scale = jnp.max(jnp.abs(M), axis=(-2, -1))
    valid = m00 > jnp.maximum(tiny(M.dtype) * 1e3, 10 * eps(M.dtype) * scale)
    safe = jnp.where(valid, m00, 1.0)
    eye = jnp.eye(4, dtype=M.dtype)
    Mn = jnp.where(valid[..., None, None], M / safe[..., None, None], eye)
    return Mn, m00, valid


def _cof_det3(X: Array) -> tuple[Array, Array]:
    """Cofactor matrix and determinant of 3x3 matrices (inv(X)^T = cof / det)."""
    r0, r1, r2 = X[..., 0, :], X[..., 1, :], X[..., 2, :]
    cof = jnp.stack([jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)], axis=-2)
    det = jnp.sum(r0 * cof[..., 0, :], axis=-1)
    return cof, det


def _polar_orthogonal(X: Array) -> Array:
    """Orthogonal factor Q of X = Q S (S symmetric positive), scaled Newton, X nonsingular."""

    def step(_, X):
        cof, det = _cof_det3(X)
        Xit = cof / det[..., None, None]
        nx = jnp.sqrt(jnp.sum(X * X, axis=(-2, -1)))
        ni = jnp.sqrt(jnp.sum(Xit * Xit, axis=(-2, -1)))
        g = jnp.sqrt(ni / nx)[..., None, None]
        return 0.5 * (g * X + Xit / g)

    # static trip count: lowered to a scan, so reverse-mode works and the graph stays small
    return jax.lax.fori_loop(0, _NEWTON_STEPS, step, X)


@jax.jit
def lu_chipman(M: MuellerLike) -> LuChipman:
    """Lu-Chipman polar decomposition ``M = M_Delta @ M_R @ M_D`` of (batched) Mueller matrices.

    **Arguments:**

    - `M`: ``(..., 4, 4)`` real Mueller matrices (any positive scale; ``M00 = 0`` allowed).

    **Returns:** a :class:`LuChipman` named tuple. Reference: S.-Y. Lu and R. A. Chipman,
    "Interpretation of Mueller matrices based on polar decomposition", JOSA A 13 (1996).
    """
    M = _as_mueller(M)
    dt = M.dtype
    Mn, m00, valid = _normalized(M)
    Dv = Mn[..., 0, 1:]
    Pv = Mn[..., 1:, 0]
    m = Mn[..., 1:, 1:]
    D2 = jnp.sum(Dv * Dv, axis=-1)
    D = safe_sqrt(D2)
    P = safe_sqrt(jnp.sum(Pv * Pv, axis=-1))
    # diattenuator: m_D = a I + D D^T / (1 + a), a = sqrt(1 - D^2); inverse
    # m_D^{-1} = I / a - D D^T / (a (1 + a)). Clamp a away from 0 (ideal polarizer, D = 1).
    a_floor = jnp.sqrt(eps(dt))
    a_raw = safe_sqrt(1.0 - D2)
    a = jnp.where(a_raw > a_floor, a_raw, a_floor)
    eye3 = jnp.eye(3, dtype=dt)
    DDt = Dv[..., :, None] * Dv[..., None, :]
    a_ = a[..., None, None]
    m_D = a_ * eye3 + DDt / (1.0 + a_)
    m_D_inv = eye3 / a_ - DDt / (a_ * (1.0 + a_))
    # M' = M M_D^{-1} = [[1, 0], [P_Delta, m']]
    P_Delta = (Pv - jnp.einsum("...ij,...j->...i", m, Dv)) / (a * a)[..., None]
    m_prime = (m - P_Delta[..., :, None] * Dv[..., None, :]) @ m_D_inv
    # polar decomposition m' = m_Delta m_R with det(m_R) = +1
    _, det_mp = _cof_det3(m_prime)
    scale = jnp.sum(m_prime * m_prime, axis=(-2, -1)) / 3.0
    singular = ~(jnp.abs(det_mp) > eps(dt) ** 0.75 * jnp.maximum(scale, 1.0) ** 1.5)
    X0 = jnp.where(singular[..., None, None], eye3, m_prime)
    Q = _polar_orthogonal(X0)
    sgn = jnp.where(det_mp < 0, -1.0, 1.0).astype(dt)[..., None, None]
    m_R = jnp.where(singular[..., None, None], eye3, sgn * Q)
    m_Delta = m_prime @ jnp.swapaxes(m_R, -1, -2)
    m_Delta = 0.5 * (m_Delta + jnp.swapaxes(m_Delta, -1, -2))
    # retardance from the rotation m_R: cos R = (tr - 1)/2, 2 sin R = |antisymmetric part|
    tr = m_R[..., 0, 0] + m_R[..., 1, 1] + m_R[..., 2, 2]
    axis = jnp.stack(
        [m_R[..., 1, 2] - m_R[..., 2, 1], m_R[..., 2, 0] - m_R[..., 0, 2],
         m_R[..., 0, 1] - m_R[..., 1, 0]], axis=-1
    )
    two_sin = safe_sqrt(jnp.sum(axis * axis, axis=-1))
    R = jnp.arctan2(0.5 * two_sin, 0.5 * (tr - 1.0))
    R_vec = axis * safe_div(R, two_sin)[..., None]
    # linear retardance / optical rotation (Lu-Chipman eqs. for M_R = M_LR M_CR)
    q = jnp.sqrt((m_R[..., 0, 0] + m_R[..., 1, 1]) ** 2 + (m_R[..., 1, 0] - m_R[..., 0, 1]) ** 2
                 + tiny(dt))
    cos_lin = jnp.clip(q - 1.0, -1.0, 1.0)
    lin = jnp.arctan2(safe_sin_from_cos(cos_lin), cos_lin)
    psi = 0.5 * jnp.arctan2(m_R[..., 0, 1] - m_R[..., 1, 0], m_R[..., 0, 0] + m_R[..., 1, 1])
    depol = 1.0 - jnp.abs(m_Delta[..., 0, 0] + m_Delta[..., 1, 1] + m_Delta[..., 2, 2]) / 3.0

    def block(top_left, row, col, inner):
        top = jnp.concatenate([top_left[..., None, None], row[..., None, :]], axis=-1)
        bot = jnp.concatenate([col[..., :, None], inner], axis=-1)
        return jnp.concatenate([top, bot], axis=-2)

    one = jnp.ones_like(m00)
    z3 = jnp.zeros_like(Dv)
    M_D = block(one, Dv, Dv, m_D) * jnp.where(valid, m00, 0.0)[..., None, None]
    M_R = block(one, z3, z3, m_R)
    M_Delta = block(one, z3, P_Delta, m_Delta)
    zero = jnp.zeros_like(m00)
    v = valid
    return LuChipman(
        m00=m00,
        diattenuation=jnp.where(v, D, zero),
        diattenuation_vector=jnp.where(v[..., None], Dv, 0.0),
        polarizance=jnp.where(v, P, zero),
        polarizance_vector=jnp.where(v[..., None], Pv, 0.0),
        retardance=jnp.where(v, R, zero),
        retardance_vector=jnp.where(v[..., None], R_vec, 0.0),
        linear_retardance=jnp.where(v, lin, zero),
        optical_rotation=jnp.where(v, psi, zero),
        depolarization_power=jnp.where(v, depol, zero),
        M_D=M_D,
        M_R=M_R,
        M_Delta=M_Delta,
        valid=valid,
        singular=singular & valid,
    )


@jax.jit
def diattenuation(M: MuellerLike) -> Float[Array, "..."]:
    """Diattenuation ``D = sqrt(M01^2 + M02^2 + M03^2) / M00`` (0 where ``M00 = 0``)."""
    Mn, _, valid = _normalized(_as_mueller(M))
    return jnp.where(valid, safe_sqrt(jnp.sum(Mn[..., 0, 1:] ** 2, axis=-1)), 0.0)


@jax.jit
def polarizance(M: MuellerLike) -> Float[Array, "..."]:
    """Polarizance ``P = sqrt(M10^2 + M20^2 + M30^2) / M00`` (0 where ``M00 = 0``)."""
    Mn, _, valid = _normalized(_as_mueller(M))
    return jnp.where(valid, safe_sqrt(jnp.sum(Mn[..., 1:, 0] ** 2, axis=-1)), 0.0)


@jax.jit
def retardance(M: MuellerLike) -> Float[Array, "..."]:
    """Total retardance (rad) of the Lu-Chipman retarder factor."""
    return lu_chipman(M).retardance


@jax.jit
def depolarization_index(M: MuellerLike) -> Float[Array, "..."]:
    """Gil-Bernabeu depolarization index ``sqrt((sum M_ij^2 - M00^2) / (3 M00^2))``.

    1 for a non-depolarizing (Jones-derived) matrix, 0 for the ideal depolarizer, 0 where
    ``M00 = 0``. (Despite the name, larger means *less* depolarizing.)
    """
    Mn, _, valid = _normalized(_as_mueller(M))
    s = jnp.sum(Mn * Mn, axis=(-2, -1)) - 1.0
    return jnp.where(valid, safe_sqrt(s / 3.0), 0.0)


@jax.jit
def degree_of_polarization(
    M: MuellerLike, s_in: Float[ArrayLike, "... 4"]
) -> Float[Array, "..."]:
    """Degree of polarization ``|S_out[1:]| / S_out[0]`` of ``S_out = M @ s_in``
    (0 where ``S_out[0] = 0``)."""
    M = _as_mueller(M)
    S = jnp.einsum("...ij,...j->...i", M, jnp.asarray(s_in, M.dtype))
    pol = safe_sqrt(jnp.sum(S[..., 1:] ** 2, axis=-1))
    return safe_div(pol, jnp.where(S[..., 0] > 0, S[..., 0], 0.0))


_PAULI = np.array(
    [[[1, 0], [0, 1]], [[1, 0], [0, -1]], [[0, 1], [1, 0]], [[0, -1j], [1j, 0]]], np.complex128
)
# basis B[i, j] = sigma_i (x) conj(sigma_j), 4x4 each
_COHERENCY_BASIS = np.einsum("iab,jcd->ijacbd", _PAULI, np.conj(_PAULI)).reshape(4, 4, 4, 4)


@jax.jit
def coherency_matrix(M: MuellerLike) -> Array:
    """Cloude coherency matrix ``H = 1/4 sum_ij M_ij sigma_i (x) sigma_j^*`` (Hermitian 4x4,
    ``trace H = M00``; rank one for a Jones-derived M)."""
    M = _as_mueller(M)
    cdt = jnp.result_type(M.dtype, jnp.complex64)
    B = jnp.asarray(_COHERENCY_BASIS, cdt)
    return 0.25 * jnp.einsum("...ij,ijab->...ab", M.astype(cdt), B)


@jax.jit
def cloude_eigenvalues(M: MuellerLike) -> Float[Array, "... 4"]:
    """Real eigenvalues of the coherency matrix, sorted in descending order (sum = M00).

    All >= 0 iff M is physically realizable (a convex sum of Jones-Mueller matrices); a
    non-depolarizing M has exactly one non-zero eigenvalue, equal to M00.
    """
    H = coherency_matrix(M)
    H = 0.5 * (H + jnp.conj(jnp.swapaxes(H, -1, -2)))
    w = jnp.linalg.eigvalsh(H)
    return w[..., ::-1]


@jax.jit
def is_realizable(M: MuellerLike, tol: float = 1e-6) -> Bool[Array, "..."]:
    """True where every Cloude eigenvalue is ``>= -tol * max(M00, |M|_max)``."""
    M = _as_mueller(M)
    w = cloude_eigenvalues(M)
    scale = jnp.maximum(M[..., 0, 0], jnp.max(jnp.abs(M), axis=(-2, -1)))
    return w[..., -1] >= -tol * scale

