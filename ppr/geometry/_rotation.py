"""Attitude quaternions and rotation matrices.

Quaternions are ``(w, x, y, z)`` with ``w`` the scalar part and rotate *body* coordinates
into *world* coordinates: ``x_world = R(q) @ x_body + position``. ``q`` and ``-q`` are the
same rotation (the matrix is quadratic in ``q``). Host-side validation
(:func:`check_quaternion`) rejects non-finite quaternions and norms further than
``QUAT_NORM_TOL`` from 1 with a ``ValueError`` naming the field and the value; within the
tolerance the quaternion is normalized (differentiably) inside :func:`quat_to_matrix`.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._safe import safe_norm
from .._types import Array, ArrayLike, Float

QUAT_NORM_TOL = 1e-3
"""Largest accepted | |q| - 1 | of a concrete attitude quaternion."""


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


def quat_to_matrix(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix of ``q = (w, x, y, z)``, normalized first (any sign, differentiable)."""
    q = jnp.asarray(q)
    if not jnp.issubdtype(q.dtype, jnp.floating):
        q = q.astype(jnp.result_type(float))
    nrm = safe_norm(q, keepdims=True)
    q = q / jnp.where(nrm > 0, nrm, 1.0)
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
    rows = [jnp.stack(r, axis=-1) for r in ((r00, r01, r02), (r10, r11, r12), (r20, r21, r22))]
    return jnp.stack(rows, axis=-2)


def quat_from_axis_angle(axis, angle: float) -> np.ndarray:
    """Host helper: quaternion of a right-handed rotation by ``angle`` (rad) about ``axis``."""
    a = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(a)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"axis must be a finite non-zero 3-vector, got {a.tolist()}")
    a = a / n
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * a])


def quat_multiply(q1, q2) -> Array:
    """Hamilton product ``q1 * q2`` (apply ``q2`` first, then ``q1``)."""
    q1 = jnp.asarray(q1)
    q2 = jnp.asarray(q2)
    w1, x1, y1, z1 = (q1[..., i] for i in range(4))
    w2, x2, y2, z2 = (q2[..., i] for i in range(4))
    return jnp.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def matrix_to_quat(r) -> np.ndarray:
    """Host helper: quaternion ``(w, x, y, z)`` (w >= 0) of a proper rotation matrix."""
    r = np.asarray(r, dtype=np.float64)
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
