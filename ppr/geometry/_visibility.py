"""Macro self-shadowing: per-face lit-and-visible fractions by ray casting (no gradients).

Visibility is piecewise constant in pose, so it is computed on the host with NumPy and
Embree (through trimesh's ``ray_pyembree`` backend, embreex) and handed to the jitted kernel
as a plain array. Everything is done in the *body* frame: the mesh (and Embree's BVH) is
built once and only the two directions change with the pose.

For each face that faces both the laser and the receiver (``n . u > COS_MIN`` for both), a
fixed pattern of ``S = k^2`` barycentric sample points (the centroids of the ``k^2``
congruent sub-triangles of a ``k``-fold edge subdivision, which integrates linear functions
exactly) is tested: a sample counts if a ray from it toward the laser and a ray from it
toward the receiver both escape the mesh. The fraction of samples that count is returned;
back-facing faces get 0 without casting rays. For directions closer than
``SAME_DIRECTION_RAD`` only the laser rays are cast (the shadow of a 1 m object moves by
less than 0.1 mm).
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from ._mesh import Mesh, face_areas_normals

COS_MIN = 1e-6
"""Faces with ``n . u <= COS_MIN`` toward the laser or the receiver are culled (kernel too)."""
SAME_DIRECTION_RAD = 1e-4
RAY_OFFSET_REL = 1e-5
"""Ray origins are lifted off the face by this fraction of the mesh's bounding-box diagonal."""


def barycentric_samples(k: int) -> np.ndarray:
    """``(k^2, 3)`` barycentric weights: centroids of the ``k^2`` sub-triangles."""
    if k < 1:
        raise ValueError(f"sub-sampling level must be >= 1, got {k}")
    pts = []
    for i in range(k):
        for j in range(k - i):
            pts.append(((i + 1 / 3) / k, (j + 1 / 3) / k))  # upward: (i,j),(i+1,j),(i,j+1)
            if i + j <= k - 2:
                pts.append(((i + 2 / 3) / k, (j + 2 / 3) / k))  # downward
    uv = np.asarray(pts)
    return np.stack([1 - uv.sum(1), uv[:, 0], uv[:, 1]], axis=1)


class VisibilityCaster:
    """Host-side ray caster for one mesh (build once, call per pose).

    **Arguments:**

    - `mesh`: the :class:`ppr.Mesh` (body frame).
    - `samples`: barycentric samples per face, a perfect square (default 16).
    - `allow_slow`: if Embree is unavailable, fall back to trimesh's pure-Python ray tracer
      (~1000x slower) with a warning instead of raising.
    """

    def __init__(self, mesh: Mesh, samples: int = 16, *, allow_slow: bool = False):
        import trimesh
        import trimesh.ray

        k = math.isqrt(int(samples))
        if k * k != samples or k < 1:
            raise ValueError(
                f"samples must be a perfect square >= 1 (1, 4, 9, 16, ...), got {samples!r}"
            )
        tri = mesh.triangles()
        # rays in coordinates centred on the mesh (visibility does not depend on where the
        # body origin is): Embree intersects in float32, and a mesh exported far from its
        # origin (a part placed in a vehicle's frame) would otherwise have float32 spacings
        # above the rays' lift off their face and shadow itself (a convex 3U box 70 m off)
        lo, hi = tri.reshape(-1, 3).min(0), tri.reshape(-1, 3).max(0)
        self.centre = 0.5 * (lo + hi)  # body frame; subtract it from points given to _ray
        tri = tri - self.centre
        self.n_faces = tri.shape[0]
        self.samples = samples
        _, self.normals = face_areas_normals(tri)
        bary = barycentric_samples(k)
        diag = float(np.linalg.norm(hi - lo))
        self._offset = RAY_OFFSET_REL * max(diag, 1e-9)
        self.points = np.einsum("sk,fkd->fsd", bary, tri)  # (F, S, 3)
        tm = trimesh.Trimesh(
            vertices=tri.reshape(-1, 3),
            faces=np.arange(3 * self.n_faces).reshape(-1, 3),
            process=False,
        )
        if trimesh.ray.has_embree:
            from trimesh.ray.ray_pyembree import RayMeshIntersector

            self._ray = RayMeshIntersector(tm, scale_to_box=False)
            self.backend = "embree"
        else:
            msg = (
                "Embree (embreex) is not available: trimesh's pure-Python ray tracer is ~1000x "
                "slower. Install embreex, or pass allow_slow=True to accept the fallback."
            )
            if not allow_slow:
                raise RuntimeError(msg)
            warnings.warn(msg, RuntimeWarning, stacklevel=2)
            from trimesh.ray.ray_triangle import RayMeshIntersector

            self._ray = RayMeshIntersector(tm)
            self.backend = "python"

    def _escape(self, faces: np.ndarray, u: np.ndarray) -> np.ndarray:
        """(len(faces), S) bool: rays from the samples of ``faces`` toward ``u`` escape."""
        if len(faces) == 0:
            return np.zeros((0, self.samples), bool)
        pts = self.points[faces] + self._offset * self.normals[faces, None, :]
        origins = pts.reshape(-1, 3)
        dirs = np.broadcast_to(u, origins.shape)
        hit = self._ray.intersects_any(origins, np.ascontiguousarray(dirs))
        return ~np.asarray(hit, bool).reshape(len(faces), self.samples)

    def fractions(self, laser_dir_body, receiver_dir_body=None) -> np.ndarray:
        """``(F,)`` lit-and-visible fraction of every face for body-frame directions (object ->
        laser, object -> receiver)."""
        u_in = np.asarray(laser_dir_body, np.float64)
        u_in = u_in / np.linalg.norm(u_in)
        u_out = u_in if receiver_dir_body is None else np.asarray(receiver_dir_body, np.float64)
        u_out = u_out / np.linalg.norm(u_out)
        front = (self.normals @ u_in > COS_MIN) & (self.normals @ u_out > COS_MIN)
        faces = np.flatnonzero(front)
        ok = self._escape(faces, u_in)
        if np.arccos(np.clip(np.dot(u_in, u_out), -1, 1)) > SAME_DIRECTION_RAD:
            ok &= self._escape(faces, u_out)
        out = np.zeros(self.n_faces)
        out[faces] = ok.mean(axis=1)
        return out
