"""Rotations: attitude quaternions, rotation matrices and rotation vectors (the one
implementation used by ``ppr`` and ``inversion``).

Quaternions are ``(w, x, y, z)`` with ``w`` the scalar part and rotate *body* coordinates
into *world* coordinates: ``x_world = R(q) @ x_body + position``. ``q`` and ``-q`` are the
same rotation (the matrix is quadratic in ``q``). Host-side validation
(:func:`check_quaternion`) rejects non-finite quaternions and norms further than
``QUAT_NORM_TOL`` from 1 with a ``ValueError`` naming the field and the value; within the
tolerance the quaternion is normalized (differentiably) inside :func:`quat_to_matrix`.

Each formula is written once and evaluated with either array namespace:

- traceable (JAX; jit, vmap and grad, batched by broadcasting): :func:`quat_to_matrix`,
  :func:`quat_multiply`, :func:`quat_conjugate`, :func:`quat_from_rotvec`,
  :func:`rotvec_from_quat`. They are written out rather than taken from
  ``jax.scipy.spatial.transform.Rotation`` because the inversion differentiates them at the
  identity: the rotation-vector maps use Taylor branches behind a double ``where``, so
  values and gradients stay finite at ``w = 0`` (``Rotation.from_rotvec`` and
  ``as_rotvec`` give NaN gradients there, jax 0.10);
- host (NumPy float64, no JAX dispatch per call; for attitude grids, symmetry groups,
  posterior samples and the image renderer): :func:`quat_to_matrix_host`,
  :func:`quat_multiply_host`, :func:`quat_from_rotvec_host`, :func:`quat_from_axis_angle`,
  :func:`matrix_to_quat`, :func:`quat_angle_deg`.

SciPy's ``Rotation`` would serve the host side too, but its canonical sign at half turns
(first non-zero component positive) differs from :func:`matrix_to_quat`'s (the largest
component positive), which fixes the stored quaternions of symmetry groups.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._safe import safe_norm
from .._types import Array, ArrayLike, Float

__all__ = [
    "QUAT_NORM_TOL",
    "check_quaternion",
    "matrix_to_quat",
    "quat_angle_deg",
    "quat_conjugate",
    "quat_from_axis_angle",
    "quat_from_rotvec",
    "quat_from_rotvec_host",
    "quat_multiply",
    "quat_multiply_host",
    "quat_to_matrix",
    "quat_to_matrix_host",
    "rotvec_from_quat",
]

QUAT_NORM_TOL = 1e-3
"""Largest accepted | |q| - 1 | of a concrete attitude quaternion."""

_CONJ = (1.0, -1.0, -1.0, -1.0)


def check_quaternion(q, name: str = "quaternion", tol: float = QUAT_NORM_TOL) -> np.ndarray:
    """Validate a concrete quaternion (or batch ``(..., 4)``) on the host; return it normalized.

    Raises ``ValueError`` naming ``name`` and the offending value if it is not finite, has
    the wrong shape, or its norm differs from 1 by more than ``tol``.
    """
    a = np.asarray(q, dtype=np.float64)
    if a.ndim < 1 or a.shape[-1] != 4:
        raise ValueError(f"{name} must have shape (..., 4) as (w, x, y, z), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a.tolist()}")
    norm = np.linalg.norm(a, axis=-1)
    bad = np.abs(norm - 1.0) > tol
    if np.any(bad):
        raise ValueError(
            f"{name} must be a unit quaternion (w, x, y, z) within |norm - 1| <= {tol}, "
            f"got {a.tolist()} with norm {norm.tolist()}"
        )
    return a / norm[..., None]


def _matrix(xp, q):
    """Rotation matrix of a *unit* quaternion ``(..., 4)`` in namespace ``xp``."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r00 = 1 - 2 * (y * y + z * z)
    r01 = 2 * (x * y - w * z)
    r02 = 2 * (x * z + w * y)
    r10 = 2 * (x * y + w * z)
    r11 = 1 - 2 * (x * x + z * z)
    r12 = 2 * (y * z - w * x)
    r20 = 2 * (x * z - w * y)
    r21 = 2 * (y * z + w * x)
    r22 = 1 - 2 * (x * x + y * y)
    rows = [xp.stack(r, axis=-1) for r in ((r00, r01, r02), (r10, r11, r12), (r20, r21, r22))]
    return xp.stack(rows, axis=-2)


def _hamilton(xp, q1, q2):
    """Hamilton product ``q1 q2`` in namespace ``xp`` (broadcasts)."""
    w1, x1, y1, z1 = (q1[..., i] for i in range(4))
    w2, x2, y2, z2 = (q2[..., i] for i in range(4))
    return xp.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


# ------------------------------------------------------------------------------ traceable


def quat_to_matrix(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix of ``q = (w, x, y, z)``, normalized first (any sign, differentiable)."""
    q = jnp.asarray(q)
    if not jnp.issubdtype(q.dtype, jnp.floating):
        q = q.astype(jnp.result_type(float))
    nrm = safe_norm(q, keepdims=True)
    q = q / jnp.where(nrm > 0, nrm, 1.0)
    return _matrix(jnp, q)


def quat_multiply(q1: Float[ArrayLike, "*#b 4"], q2: Float[ArrayLike, "*#b 4"]) -> Array:
    """Hamilton product ``q1 q2`` (apply ``q2`` first, then ``q1``); broadcasts."""
    return _hamilton(jnp, jnp.asarray(q1), jnp.asarray(q2))


def quat_conjugate(q: Float[ArrayLike, "*b 4"]) -> Array:
    """``(w, -x, -y, -z)``: the inverse rotation of a unit quaternion."""
    q = jnp.asarray(q)
    return q * jnp.asarray(_CONJ, q.dtype)


def _from_rotvec(xp, w):
    """``exp(w/2)`` of rotation vectors ``w (..., 3)`` in namespace ``xp``."""
    a2 = xp.sum(w * w, axis=-1)
    small = a2 < 1e-12
    a = xp.sqrt(xp.where(small, 1.0, a2))
    half = 0.5 * a
    # sin(a/2)/a and cos(a/2) with Taylor branches at a -> 0 (double where: finite gradients).
    s_big = xp.sin(half) / a
    s_small = 0.5 - a2 / 48.0
    c_big = xp.cos(half)
    c_small = 1.0 - a2 / 8.0
    s = xp.where(small, s_small, s_big)
    c = xp.where(small, c_small, c_big)
    return xp.concatenate([c[..., None], s[..., None] * w], axis=-1)


def quat_from_rotvec(w: Float[ArrayLike, "*b 3"]) -> Float[Array, "*b 4"]:
    """Unit quaternion ``exp(w/2)`` of a rotation vector (radians); smooth at ``w = 0``."""
    return _from_rotvec(jnp, jnp.asarray(w))


def rotvec_from_quat(q: Float[ArrayLike, "*b 4"]) -> Float[Array, "*b 3"]:
    """Rotation vector (radians, angle in [0, pi]) of a quaternion (sign and norm ignored)."""
    q = jnp.asarray(q)
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    q = jnp.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    sv2 = jnp.sum(v * v, axis=-1)
    small = sv2 < 1e-24
    sv = jnp.sqrt(jnp.where(small, 1.0, sv2))
    angle = 2.0 * jnp.arctan2(sv, q[..., 0])
    factor = jnp.where(small, 2.0 / q[..., 0], angle / sv)
    return factor[..., None] * v


# ------------------------------------------------------------------------------ host (NumPy)


def quat_to_matrix_host(q) -> np.ndarray:
    """Host rotation matrices ``(..., 3, 3)`` (float64) of quaternions ``(..., 4)``, normalized
    first (either sign): :func:`quat_to_matrix` without a JAX dispatch per call. A quaternion
    that is not finite or has zero norm is a ``ValueError`` naming it."""
    a = np.asarray(q, dtype=np.float64)
    if a.ndim < 1 or a.shape[-1] != 4 or not np.all(np.isfinite(a)):
        raise ValueError(
            f"quaternion must be finite numbers (w, x, y, z), shape (..., 4); got "
            f"{np.asarray(q).tolist()!r}"
        )
    nrm = np.linalg.norm(a, axis=-1, keepdims=True)
    if np.any(nrm < 1e-12):
        raise ValueError(f"quaternion has zero norm: {np.asarray(q).tolist()!r}")
    return _matrix(np, a / nrm)


def quat_from_rotvec_host(w) -> np.ndarray:
    """Host :func:`quat_from_rotvec` (float64): ``exp(w/2)`` of rotation vectors ``(..., 3)``."""
    return _from_rotvec(np, np.asarray(w, np.float64))


def quat_multiply_host(q1, q2) -> np.ndarray:
    """Host Hamilton product ``q1 q2`` (float64; apply ``q2`` first); broadcasts."""
    return _hamilton(np, np.asarray(q1, np.float64), np.asarray(q2, np.float64))


def quat_from_axis_angle(axis, angle: float) -> np.ndarray:
    """Host helper: quaternion of a right-handed rotation by ``angle`` (rad) about ``axis``."""
    a = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(a)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"axis must be a finite non-zero 3-vector, got {a.tolist()}")
    a = a / n
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * a])


def matrix_to_quat(r) -> np.ndarray:
    """Host helper: quaternion ``(w, x, y, z)`` (w >= 0) of a proper rotation matrix
    (Shepperd's method: the largest of ``w, x, y, z`` from the diagonal, the rest from the
    off-diagonal sums and differences)."""
    r = np.asarray(r, dtype=np.float64)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise ValueError(f"rotation matrix must be finite with shape (3, 3), got {r.tolist()!r}")
    tr = np.trace(r)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q if q[0] >= 0 else -q


def quat_angle_deg(q1: ArrayLike, q2: ArrayLike) -> np.ndarray | float:
    """Angle (degrees) of the rotation taking ``q1`` to ``q2`` (sign-invariant, accurate near 0);
    broadcasts."""
    q1 = np.asarray(q1, float)
    q2 = np.asarray(q2, float)
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    q2 = q2 / np.linalg.norm(q2, axis=-1, keepdims=True)
    d = quat_multiply_host(q2, q1 * np.asarray(_CONJ))
    ang = np.degrees(2.0 * np.arctan2(np.linalg.norm(d[..., 1:], axis=-1), np.abs(d[..., 0])))
    return float(ang) if np.ndim(ang) == 0 else ang
