r"""Symmetries of a triangle mesh, computed from the mesh itself.

A *symmetry* of a mesh is an orthogonal map ``x -> c + S (x - c)`` (``S`` a 3x3 matrix,
``det S = +1`` a proper rotation, ``-1`` an improper element: mirror plane, rotoreflection or
inversion) about the area centroid ``c`` of the surface that maps the surface onto itself,
**every face's part (material) and outward side included**: a panel whose two sides carry
different materials is not symmetric under the mirror through its own plane, and a box whose
+z face is painted keeps only the symmetries that fix that face. Every isometry of a surface
fixes its area centroid, so centring on ``c`` loses nothing.

**Tolerance.** ``tol`` is relative to the mesh's size ``L``, the largest distance of a vertex
from ``c``: ``S`` is accepted when every point of the transformed surface lies within
``tol * L`` of a point of the surface with the same part whose outward normal points to the
same side (``n . n' > 0``), and every point of the surface within ``tol * L`` of the
transformed surface (a symmetric, part- and side-aware surface distance). The reported
``residual`` is that distance divided by ``L``: exact when ``S`` maps faces onto faces (the
distance is then the largest vertex displacement, an upper bound of the Hausdorff distance
between the two surfaces, found with one nearest-centroid query per face), otherwise the
largest distance of the faces' centroids, corner points and seeded area samples from the
other surface (point-to-triangle distances on KD-tree candidates, with a guard that makes
each distance exact). A mesh that is symmetric only up to a perturbation ``d`` shows the
symmetry at ``tol >~ d / L`` and not below.

**Candidates.** Symmetries are found by verifying candidates, never by assuming a shape
class:

1. The area second moment ``M = int (x - c)(x - c)^T dA`` is invariant under every
   symmetry. If its eigenvalues are distinct, every symmetry maps each eigenvector to
   plus or minus itself: the eight sign matrices in the eigenframe are the only candidates.
2. Otherwise (a symmetric top: one unique axis ``a``; or a spherical top: the cube,
   regular polyhedra, spheres) candidates come from features the symmetries must permute:
   flat regions (faces grouped by part, outward normal and plane; their area, centroid and
   normal do not depend on how a region is triangulated) and vertices. A reference feature
   (or pair of features, or the unique axis and one feature) spanning two directions is
   matched against every feature with the same invariants (distance from ``c``, area,
   part, angles); each match gives a proper and an improper candidate by orthogonal
   Procrustes.
3. The accepted elements are closed under composition: a product that is not yet an element
   is verified and added; :attr:`MeshSymmetry.closed` says whether every product passed
   (always, for exact symmetries; a mesh symmetric only up to ``tol`` can fail it).

Two elements closer than ``tol`` radians (they displace no point by more than ``tol * L``)
are the same element to the tolerance. Candidates are screened on 128 seeded surface points
before the full check.
"""

from __future__ import annotations

import dataclasses
import math
from fractions import Fraction

import numpy as np

__all__ = ["MeshSymmetry", "mesh_symmetries", "symmetry_label"]

_SCREEN_POINTS = 128
_AXIS_NAMES = ("x", "y", "z")


# ----------------------------------------------------------------------------- the result
@dataclasses.dataclass(frozen=True, eq=False)
class MeshSymmetry:
    """The symmetry elements of a mesh (:func:`mesh_symmetries`), or of a named shape class.

    - `matrices`: ``(G, 3, 3)`` orthogonal matrices ``S`` in body axes (identity first, then
      the other proper rotations, then the improper elements); the element maps body point
      ``x`` to ``centre + S (x - centre)``.
    - `residuals`: ``(G,)`` symmetric surface distance of each element, relative to `size`.
    - `centre`: ``(3,)`` body-frame centre (area centroid of the surface), metres.
    - `size`: largest distance of a vertex from `centre`, metres.
    - `tol`: the relative tolerance the elements were accepted at.
    - `closed`: every product of two elements is an element (to `tol`).
    """

    matrices: np.ndarray
    residuals: np.ndarray
    centre: np.ndarray
    size: float
    tol: float
    closed: bool = True

    def __post_init__(self):
        mats = np.asarray(self.matrices, np.float64)
        if mats.ndim != 3 or mats.shape[1:] != (3, 3) or len(mats) == 0:
            raise ValueError(f"MeshSymmetry.matrices must be (G, 3, 3), got {mats.shape}")
        err = np.abs(np.einsum("gji,gjk->gik", mats, mats) - np.eye(3)).max()
        if not err < 1e-6:
            raise ValueError(f"MeshSymmetry.matrices must be orthogonal (|S^T S - I| = {err:.3g})")
        res = np.broadcast_to(np.asarray(self.residuals, np.float64), (len(mats),)).copy()
        object.__setattr__(self, "matrices", mats)
        object.__setattr__(self, "residuals", res)
        object.__setattr__(self, "centre", np.asarray(self.centre, np.float64).reshape(3))

    @classmethod
    def from_matrices(cls, matrices, centre=(0.0, 0.0, 0.0), size: float = 1.0) -> MeshSymmetry:
        """An exact group given by its matrices (e.g. a named shape class); identity first."""
        mats = _sort_elements(np.asarray(matrices, np.float64))
        return cls(mats, np.zeros(len(mats)), np.asarray(centre, np.float64), float(size), 0.0)

    def __len__(self) -> int:
        return len(self.matrices)

    @property
    def determinants(self) -> np.ndarray:
        return np.round(np.linalg.det(self.matrices)).astype(int)

    @property
    def rotations(self) -> np.ndarray:
        """``(G+, 3, 3)`` the proper elements (a group: the rotations the body allows)."""
        return self.matrices[self.determinants > 0]

    @property
    def improper(self) -> np.ndarray:
        """``(G-, 3, 3)`` the improper elements (mirrors, rotoreflections, inversion)."""
        return self.matrices[self.determinants < 0]

    @property
    def labels(self) -> tuple[str, ...]:
        """One label per element, e.g. ``"identity"``, ``"C4 about body +z"``,
        ``"mirror normal to body x"``, ``"S4 about body +z"``, ``"inversion"``."""
        return tuple(symmetry_label(s, self.tol) for s in self.matrices)

    def quaternions(self) -> np.ndarray:
        """``(G+, 4)`` scalar-first unit quaternions of the proper elements (``w >= 0``), in
        the order of :attr:`rotations`."""
        from ._rotation import matrix_to_quat

        return np.stack([matrix_to_quat(r) for r in self.rotations])

    def mirror_normals(self) -> np.ndarray:
        """``(k, 3)`` unit normals of the pure reflections (mirror planes through `centre`)."""
        out = []
        for s in self.improper:
            kind, _, axis = _classify(s, _angle_tol(self.tol))
            if kind == "mirror":
                out.append(axis)
        return np.reshape(np.asarray(out, np.float64), (-1, 3))

    @property
    def point_group(self) -> str:
        """Schoenflies symbol of the elements (``"C1"``, ``"Cs"``, ``"C2v"``, ``"D4h"``,
        ``"Oh"``, ``"Ih"``, ...)."""
        return _point_group(self.matrices, self.tol)

    def summary(self) -> str:
        n_p = len(self.rotations)
        lines = [
            f"point group {self.point_group}: {n_p} proper + {len(self) - n_p} improper "
            f"elements (tol {self.tol:.3g} of size {self.size:.4g} m, centre "
            f"{np.round(self.centre, 6).tolist()} m{'' if self.closed else ', not closed'})"
        ]
        for lab, r in zip(self.labels, self.residuals, strict=True):
            lines.append(f"  {lab:<40s} residual {r:.2g}")
        return "\n".join(lines)

    def transformed(self, rotation, translation=(0.0, 0.0, 0.0)) -> MeshSymmetry:
        """The symmetry of the mesh moved by ``x -> rotation x + translation``: the
        conjugate group ``rotation S rotation^T`` about the moved centre."""
        r = np.asarray(rotation, np.float64)
        mats = np.einsum("ij,gjk,lk->gil", r, self.matrices, r)
        c = r @ self.centre + np.asarray(translation, np.float64)
        return dataclasses.replace(self, matrices=mats, centre=c)


# ----------------------------------------------------------------------------- labels
def _rotation_angle_axis(r: np.ndarray) -> tuple[float, np.ndarray]:
    """Angle in [0, pi] and unit axis of a proper rotation (axis sign fixed at angle pi)."""
    c = np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    s = 0.5 * np.linalg.norm(v)
    theta = math.atan2(s, c)
    if theta < 1e-9:
        return 0.0, np.array([0.0, 0.0, 1.0])
    if math.pi - theta > 1e-4:
        return theta, v / (2.0 * s)
    # near a half turn: the axis from the symmetric part (R + I) / 2 = a a^T
    b = 0.5 * (r + np.eye(3))
    axis = b[np.argmax(np.diag(b))]
    axis = axis / np.linalg.norm(axis)
    if np.dot(axis, v) < 0 or (abs(np.dot(axis, v)) < 1e-12 and _first_negative(axis)):
        axis = -axis
    return theta, axis


def _first_negative(a: np.ndarray) -> bool:
    i = int(np.argmax(np.abs(a) > 1e-9))
    return bool(a[i] < 0)


def _angle_tol(tol: float) -> float:
    """Angular tolerance (rad) of the labels of elements accepted at relative ``tol``."""
    return max(1e-6, 4.0 * tol)


def _classify(s: np.ndarray, atol: float = 1e-6) -> tuple[str, float, np.ndarray]:
    """(kind, angle, axis): kind identity / rotation / inversion / mirror / rotoreflection."""
    s = np.asarray(s, np.float64)
    if np.linalg.det(s) > 0:
        theta, axis = _rotation_angle_axis(s)
        return ("identity" if theta < atol else "rotation"), theta, axis
    theta, axis = _rotation_angle_axis(-s)  # S = -R(theta, a) = sigma_a R(theta + pi, a)
    if theta < atol:
        return "inversion", 0.0, axis
    if math.pi - theta < atol:
        if _first_negative(axis):
            axis = -axis
        return "mirror", 0.0, axis
    phi = theta + math.pi  # rotoreflection angle, in (pi, 2 pi): use -axis and 2 pi - phi
    return "rotoreflection", 2 * math.pi - phi, -axis


def _axis_name(axis: np.ndarray, signed: bool, atol: float = 1e-6) -> str:
    a = np.asarray(axis, np.float64)
    i = int(np.argmax(np.abs(a)))
    if abs(abs(a[i]) - 1.0) < atol:
        sign = "+" if a[i] > 0 else "-"
        return f"body {sign if signed else ''}{_AXIS_NAMES[i]}"
    if not signed and _first_negative(a):
        a = -a
    return "body (" + ", ".join(f"{x:.3f}" for x in a + 0.0) + ")"


def _order(angle: float, atol: float = 1e-6) -> tuple[int, int] | None:
    """(n, k): the smallest ``n <= 720`` with ``|angle - 2 pi k / n| <= atol`` for some
    ``k``; None if there is none."""
    n = np.arange(1, 721)
    k = np.rint(angle * n / (2 * math.pi))
    ok = (k > 0) & (np.abs(angle - 2 * math.pi * k / n) <= atol)
    if not ok.any():
        return None
    i = int(np.argmax(ok))
    f = Fraction(int(k[i]), int(n[i]))
    return f.denominator, f.numerator


def symmetry_label(s, tol: float = 0.0) -> str:
    """Label of one orthogonal matrix: ``"identity"``, ``"C4 about body +z"``,
    ``"C5^2 about body (...)"``, ``"C2 about body x"``, ``"mirror normal to body z"``,
    ``"S4 about body +z"``, ``"inversion"``, or a rotation angle in degrees when it is not
    ``2 pi k / n`` for ``n <= 720``. ``tol``: the relative tolerance the element was found
    at (angles and axes are compared to ``max(1e-6, 4 tol)`` rad)."""
    atol = _angle_tol(tol)
    kind, angle, axis = _classify(s, atol)
    if kind in ("identity", "inversion"):
        return kind
    if kind == "mirror":
        return f"mirror normal to {_axis_name(axis, False, atol)}"
    half = abs(angle - math.pi) < atol
    name = _axis_name(axis, not half, atol)
    letter = "C" if kind == "rotation" else "S"
    nk = _order(angle, atol)
    if nk is None:
        what = "rotation" if kind == "rotation" else "rotoreflection"
        return f"{what} by {math.degrees(angle):.4g} deg about {name}"
    n, k = nk
    return f"{letter}{n}{'' if k == 1 else f'^{k}'} about {name}"


def _point_group(mats: np.ndarray, tol: float = 0.0) -> str:
    atol = _angle_tol(tol)
    proper = [m for m in mats if np.linalg.det(m) > 0]
    improper = [m for m in mats if np.linalg.det(m) < 0]
    axes: dict[int, list[np.ndarray]] = {}
    for r in proper:
        theta, axis = _rotation_angle_axis(r)
        if theta < atol:
            continue
        nk = _order(theta, atol)
        n = nk[0] if nk else 0
        lst = axes.setdefault(n, [])
        if all(abs(abs(np.dot(axis, a)) - 1) > atol for a in lst):
            lst.append(axis)
    n_max = max(axes, default=1)
    high = sum(len(v) for n, v in axes.items() if n >= 3)
    n_p = len(proper)
    if high > 1 and n_p in (12, 24, 60):
        base = {12: "T", 24: "O", 60: "I"}[n_p]
    elif n_p == 2 * n_max and n_max >= 2 and (n_max > 2 or len(axes.get(2, [])) == 3):
        base = f"D{n_max}"
    else:
        base = f"C{n_max}"
    if not improper:
        return base
    kinds = [_classify(s, atol) for s in improper]
    has_inv = any(k == "inversion" for k, _, _ in kinds)
    mirrors = [a for k, _, a in kinds if k == "mirror"]
    if base == "T":
        return "Th" if has_inv else "Td"
    if base in ("O", "I"):
        return base + "h"
    if base == "C1":
        return "Ci" if has_inv else "Cs"
    principal = axes[n_max][0] if n_max >= 2 else np.array([0.0, 0.0, 1.0])
    horizontal = any(abs(abs(np.dot(m, principal)) - 1) < atol for m in mirrors)
    if base.startswith("C"):
        if horizontal:
            return f"C{n_max}h"
        if mirrors:
            return f"C{n_max}v"
        return f"S{2 * n_max}"
    if n_max == 2:
        return "D2h" if has_inv else "D2d"
    return f"D{n_max}h" if horizontal else f"D{n_max}d"


def _sort_elements(mats: np.ndarray, residuals: np.ndarray | None = None, tol: float = 0.0):
    """Identity first, then proper rotations by (order, label), then improper ones."""
    atol = _angle_tol(tol)
    rank = {"identity": 0, "rotation": 1, "inversion": 2, "mirror": 3, "rotoreflection": 4}
    keys = []
    for s in mats:
        kind, angle, _ = _classify(s, atol)
        nk = _order(angle, atol) if angle > 0 else (1, 1)
        keys.append((rank[kind], -(nk[0] if nk else 10**6), symmetry_label(s, tol)))
    order = sorted(range(len(mats)), key=keys.__getitem__)
    if residuals is None:
        return mats[order]
    return mats[order], np.asarray(residuals)[order]


# ----------------------------------------------------------------------------- geometry
def _segment(vv, vd, dd):
    """(squared distance, parameter) of a point ``v`` to the segment from the origin along
    ``d``, from ``vv = v.v``, ``vd = v.d``, ``dd = d.d``."""
    t = np.clip(vd / np.maximum(dd, 1e-300), 0.0, 1.0)
    return vv - 2 * t * vd + t * t * dd, t


class _Faces:
    """Per-face constants of the point-to-triangle distance (corner ``a``, edges ``e0``,
    ``e1``, unit normal, Gram entries)."""

    def __init__(self, tri: np.ndarray):
        self.a = tri[:, 0]
        self.e0 = tri[:, 1] - tri[:, 0]
        self.e1 = tri[:, 2] - tri[:, 0]
        n = np.cross(self.e0, self.e1)
        nn = np.linalg.norm(n, axis=1)
        self.n = n / np.where(nn > 0, nn, 1.0)[:, None]
        self.d00 = np.einsum("fi,fi->f", self.e0, self.e0)
        self.d01 = np.einsum("fi,fi->f", self.e0, self.e1)
        self.d11 = np.einsum("fi,fi->f", self.e1, self.e1)
        den = self.d00 * self.d11 - self.d01**2
        self.inv_den = np.where(den > 0, 1.0 / np.where(den > 0, den, 1.0), 0.0)

    def closest(self, p: np.ndarray, idx: np.ndarray, points: bool = False):
        """Distance of points ``p (..., 3)`` to faces ``idx (...)`` (same leading shape), and
        with ``points`` the closest points of the faces."""
        a, e0, e1 = self.a[idx], self.e0[idx], self.e1[idx]
        v = p - a
        vv = np.einsum("...i,...i->...", v, v)
        d20 = np.einsum("...i,...i->...", v, e0)
        d21 = np.einsum("...i,...i->...", v, e1)
        vn = np.einsum("...i,...i->...", v, self.n[idx])
        d00, d01, d11 = self.d00[idx], self.d01[idx], self.d11[idx]
        u = (d11 * d20 - d01 * d21) * self.inv_den[idx]
        w = (d00 * d21 - d01 * d20) * self.inv_den[idx]
        inside = (u >= 0) & (w >= 0) & (u + w <= 1) & (self.inv_den[idx] > 0)

        s0, t0 = _segment(vv, d20, d00)  # a -> b
        s1, t1 = _segment(vv, d21, d11)  # a -> c
        s2, t2 = _segment(vv - 2 * d20 + d00, d21 - d20 - d01 + d00, d11 - 2 * d01 + d00)  # b -> c
        edge = np.minimum(np.minimum(s0, s1), s2)
        dist = np.where(inside, np.abs(vn), np.sqrt(np.maximum(edge, 0.0)))
        if not points:
            return dist
        on_edge = np.where(
            (s0 <= s1)[..., None] & (s0 <= s2)[..., None],
            a + t0[..., None] * e0,
            np.where(
                (s1 <= s2)[..., None], a + t1[..., None] * e1, a + e0 + t2[..., None] * (e1 - e0)
            ),
        )
        q = np.where(inside[..., None], p - vn[..., None] * self.n[idx], on_edge)
        return dist, q


def _split_long(tri: np.ndarray, normals: np.ndarray, max_edge: float):
    """Bisect the longest edge of every triangle longer than ``max_edge`` until none is: the
    same surface in smaller pieces, so that nearest-centroid queries stay local."""
    out_t, out_n = [], []
    for _ in range(64):
        e = np.linalg.norm(tri - np.roll(tri, -1, axis=1), axis=-1)  # edge i: v_i -> v_i+1
        j = np.argmax(e, axis=1)
        long = e[np.arange(len(tri)), j] > max_edge
        out_t.append(tri[~long])
        out_n.append(normals[~long])
        if not long.any():
            break
        t, n, j = tri[long], normals[long], j[long]
        r = np.arange(len(t))
        a, b, c = t[r, j], t[r, (j + 1) % 3], t[r, (j + 2) % 3]
        m = 0.5 * (a + b)
        tri = np.concatenate([np.stack([a, m, c], 1), np.stack([m, b, c], 1)])
        normals = np.concatenate([n, n])
    return np.concatenate(out_t), np.concatenate(out_n)


class _Surface:
    """Faces of a mesh grouped by part, with KD-trees on their centroids, for distances from
    points (with outward normals and parts) to the part- and side-compatible surface: faces
    of the same part whose outward normal makes an angle below 90 deg with the point's."""

    _PAIRS = 1 << 20  # point-face pairs per chunk of the exact search

    def __init__(self, tri, normals, parts, max_edge: float, k: int = 4):
        from scipy.spatial import cKDTree

        self.groups = {}
        for p in np.unique(parts):
            sel = np.flatnonzero(parts == p)
            t, nrm = _split_long(tri[sel], normals[sel], max_edge)
            cen = t.mean(axis=1)
            rmax = float(np.linalg.norm(t - cen[:, None], axis=-1).max())
            self.groups[int(p)] = (cKDTree(cen), _Faces(t), nrm, rmax, len(t))
        self.k = k

    def _refine(self, part, idx, x, n, best, q, limit):
        """Exact distances (in place in ``best``, closest points in ``q`` if not None) of
        the points ``idx``: every face whose centroid lies within ``min(best, limit) +
        rmax``, in chunks of at most ``_PAIRS`` point-face pairs."""
        tree, faces, fn, rmax, _ = self.groups[part]
        radius = np.minimum(best[idx], limit) + rmax
        lists = tree.query_ball_point(x[idx], radius)
        counts = np.fromiter((len(a) for a in lists), int, len(lists))
        start = 0
        while start < len(idx):
            csum = np.cumsum(counts[start:])
            stop = start + max(1, int(np.searchsorted(csum, self._PAIRS, side="right")))
            rows = np.repeat(idx[start:stop], counts[start:stop])
            if len(rows):
                cols = np.concatenate([np.asarray(a, int) for a in lists[start:stop]])
                r = faces.closest(x[rows], cols, q is not None)
                dist = r[0] if q is not None else r
                dist = np.where(np.einsum("ni,ni->n", fn[cols], n[rows]) > 0, dist, np.inf)
                if q is not None:
                    order = np.lexsort((dist, rows))
                    rows_s, dist_s = rows[order], dist[order]
                    first = np.r_[True, rows_s[1:] != rows_s[:-1]]
                    better = dist_s[first] < best[rows_s[first]]
                    tgt = rows_s[first][better]
                    best[tgt] = dist_s[first][better]
                    q[tgt] = r[1][order][first][better]
                else:
                    np.minimum.at(best, rows, dist)
            start = stop

    def query(self, pts, nrm, parts, limit: float, exact: bool, points: bool = False):
        """Distance of each point to the compatible surface (and with ``points`` the closest
        points; ``inf`` and NaN where no compatible face lies within ``limit``).

        Distances start as upper bounds (the best of the ``k`` faces with the nearest
        centroids) and are made exact where it matters: where a bound exceeds ``limit``
        (a face further out might still lie within ``limit``) and, with ``exact``, in
        decreasing order of the bounds until none left exceeds the largest exact distance
        or ``1e-3 limit``: the maximum over the points is then exact to ``1e-3 limit``."""
        out = np.full(len(pts), np.inf)
        close = np.full((len(pts), 3), np.nan) if points else None
        for p, (tree, faces, fn, rmax, n_faces) in self.groups.items():
            sel = np.flatnonzero(parts == p)
            if len(sel) == 0:
                continue
            x, n = pts[sel], nrm[sel]
            k = min(self.k, n_faces)
            dd, ii = tree.query(x, k)
            dd, ii = dd.reshape(len(x), k), ii.reshape(len(x), k)
            ok = np.einsum("nki,ni->nk", fn[ii], n) > 0
            res = faces.closest(x[:, None, :], ii, points)
            d = np.where(ok, res[0] if points else res, np.inf)
            j = np.argmin(d, axis=1)
            best = d[np.arange(len(x)), j]
            q = res[1][np.arange(len(x)), j] if points else None

            if k < n_faces:
                # a face outside the k nearest centroids is at least dd_k - rmax away
                sure = best <= dd[:, -1] - rmax
                over = np.flatnonzero(~sure & (best > limit))
                if len(over):
                    self._refine(p, over, x, n, best, q, limit)
                    sure[over] = True
                if exact:
                    done = best[sure]
                    current = float(done.max()) if len(done) else 0.0
                    rest = np.flatnonzero(~sure)
                    rest = rest[np.argsort(-best[rest])]
                    for i in range(0, len(rest), 64):
                        batch = rest[i : i + 64]
                        batch = batch[best[batch] > max(current, 1e-3 * limit)]
                        if len(batch) == 0:
                            break
                        self._refine(p, batch, x, n, best, q, limit)
                        current = max(current, float(best[batch].max()))
            out[sel] = best
            if points:
                close[sel] = q
        return (out, close) if points else out


@dataclasses.dataclass
class _Prepared:
    tri: np.ndarray  # (F, 3, 3) relative to the centre
    normals: np.ndarray
    areas: np.ndarray
    parts: np.ndarray
    centre: np.ndarray
    size: float
    surface: _Surface
    points: np.ndarray  # verification points (relative), normals, parts
    point_normals: np.ndarray
    point_parts: np.ndarray
    screen: np.ndarray  # indices of the screening points
    centroid_tree: object  # KD-tree on (face centroid, part) for the face-matching path
    face_keys: np.ndarray
    screen_faces: np.ndarray  # a few faces tried before matching all of them
    verts: np.ndarray  # (V, 3) distinct vertex positions (relative to the centre)
    vertex_tree: object  # KD-tree on them
    face_verts: np.ndarray  # (F, 3) indices into verts
    face_codes: np.ndarray  # sorted codes of the faces' vertex sets (with the part)
    face_order: np.ndarray  # face index of each sorted code


def _prepare(mesh, materials: bool, n_samples: int, seed: int, max_points: int) -> _Prepared:
    from scipy.spatial import cKDTree

    from ._mesh import face_areas_normals

    tri = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)]
    area, normal = face_areas_normals(tri)
    keep = area > 0
    if not keep.any():
        raise ValueError("mesh_symmetries: the mesh has no face of non-zero area")
    tri, area, normal = tri[keep], area[keep], normal[keep]
    parts = np.asarray(mesh.material_ids)[keep] if materials else np.zeros(len(tri), int)
    parts = parts.astype(int)
    cen = tri.mean(axis=1)
    centre = (area[:, None] * cen).sum(0) / area.sum()
    tri = tri - centre
    cen = cen - centre
    size = float(np.linalg.norm(tri.reshape(-1, 3), axis=1).max())
    edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1).max(axis=1)
    if not size > 0:
        raise ValueError("mesh_symmetries: the mesh has zero size")
    rng = np.random.default_rng(seed)
    # verification points: the seeded area samples (the first _SCREEN_POINTS screen the
    # candidates), then the centroid and three interior points near the corners of every
    # face, or of a seeded subset of max_points / 4 faces
    n_rand = max(int(n_samples), _SCREEN_POINTS)
    f = rng.choice(len(tri), size=n_rand, p=area / area.sum())
    r1, r2 = rng.random(n_rand), rng.random(n_rand)
    s = np.sqrt(r1)
    rand = (
        (1 - s)[:, None] * tri[f, 0]
        + (s * (1 - r2))[:, None] * tri[f, 1]
        + (s * r2)[:, None] * tri[f, 2]
    )
    sub = np.arange(len(tri))
    if 4 * len(tri) > max_points:
        sub = np.sort(rng.choice(len(tri), size=max(max_points // 4, 1), replace=False))
    bary = np.array([[1 / 3, 1 / 3, 1 / 3], [0.6, 0.2, 0.2], [0.2, 0.6, 0.2], [0.2, 0.2, 0.6]])
    corner = np.einsum("kj,fji->fki", bary, tri[sub]).reshape(-1, 3)
    pts = np.concatenate([rand, corner])
    pn = np.concatenate([normal[f], np.repeat(normal[sub], 4, axis=0)])
    pp = np.concatenate([parts[f], np.repeat(parts[sub], 4)])
    screen = np.arange(_SCREEN_POINTS)
    keys = np.concatenate([cen, 1e3 * size * parts[:, None].astype(np.float64)], axis=1)
    verts, face_verts = np.unique(tri.reshape(-1, 3), axis=0, return_inverse=True)
    face_verts = face_verts.reshape(-1, 3)
    codes = _face_codes(face_verts, parts, len(verts))
    order = np.argsort(codes, kind="stable")
    return _Prepared(
        tri,
        normal,
        area,
        parts,
        centre,
        size,
        _Surface(tri, normal, parts, max(size / 16, float(np.median(edges)))),
        pts,
        pn,
        pp,
        screen,
        cKDTree(keys),
        keys,
        np.sort(rng.choice(len(tri), size=min(len(tri), 256), replace=False)),
        verts,
        cKDTree(verts),
        face_verts,
        codes[order],
        order,
    )


def _face_codes(face_verts: np.ndarray, parts: np.ndarray, n_verts: int) -> np.ndarray:
    """One integer per face: its sorted vertex indices and its part (orientation-free)."""
    f = np.sort(face_verts, axis=1).astype(np.int64)
    n = np.int64(n_verts)
    return ((f[:, 0] * n + f[:, 1]) * n + f[:, 2]) * np.int64(parts.max() + 1) + parts


def _vertex_match_residual(prep: _Prepared, s: np.ndarray, thr: float) -> float:
    """Largest vertex displacement if ``s`` permutes the distinct vertices (each moved within
    ``thr`` of another, one to one) and thereby maps every face onto a face with the same
    vertices, part and side; ``inf`` otherwise. A permutation of the faces maps the surface
    onto itself both ways, so one direction suffices."""
    d, j = prep.vertex_tree.query(prep.verts @ s.T, 1)
    if d.max() > thr or len(np.unique(j)) != len(j):
        return math.inf
    codes = _face_codes(j[prep.face_verts], prep.parts, len(prep.verts))
    pos = np.searchsorted(prep.face_codes, codes)
    pos = np.minimum(pos, len(codes) - 1)
    if not np.array_equal(prep.face_codes[pos], codes):
        return math.inf
    image = prep.face_order[pos]
    if np.any(np.einsum("fi,fi->f", prep.normals @ s.T, prep.normals[image]) <= 0.5):
        return math.inf
    return float(d.max())


def _face_match_residual(prep: _Prepared, s: np.ndarray, faces=None) -> float:
    """Largest vertex displacement if ``s`` maps every face (of ``faces``, default all) onto
    a face of the same part and side (the nearest compatible centroid, among the four
    nearest where the nearest is not compatible); ``inf`` if some face has no image."""
    t = prep.tri if faces is None else prep.tri[faces]
    nrm = (prep.normals if faces is None else prep.normals[faces]) @ s.T
    part = prep.face_keys[:, 3:] if faces is None else prep.face_keys[faces, 3:]
    t = t @ s.T
    keys = np.concatenate([t.mean(axis=1), part], axis=1)
    _, j = prep.centroid_tree.query(keys, 1)
    side = np.einsum("fi,fi->f", nrm, prep.normals[j]) > 0.5
    if not side.all():  # back-to-back faces: look further
        k = min(4, len(prep.tri))
        bad = np.flatnonzero(~side)
        dist, jj = prep.centroid_tree.query(keys[bad], k)
        dist, jj = dist.reshape(len(bad), k), jj.reshape(len(bad), k)
        ok = np.einsum("fi,fki->fk", nrm[bad], prep.normals[jj]) > 0.5
        pick = np.argmin(np.where(ok, dist, np.inf), axis=1)
        if not np.all(ok[np.arange(len(bad)), pick]):
            return math.inf
        j[bad] = jj[np.arange(len(bad)), pick]
    other = prep.tri[j]
    best = np.full(len(t), np.inf)
    for perm in ((0, 1, 2), (1, 2, 0), (2, 0, 1), (0, 2, 1), (2, 1, 0), (1, 0, 2)):
        d = np.einsum("fvi,fvi->fv", t - other[:, perm], t - other[:, perm]).max(axis=1)
        best = np.minimum(best, d)
    return float(np.sqrt(best.max()))


def _surface_residual(prep: _Prepared, s: np.ndarray, limit: float, idx=None, exact=False):
    """Largest distance of the points mapped by ``s`` and by ``s^T`` from the surface."""
    pts, nrm, parts = prep.points, prep.point_normals, prep.point_parts
    if idx is not None:
        pts, nrm, parts = pts[idx], nrm[idx], parts[idx]
    worst = 0.0
    for m in (s, s.T):
        d = prep.surface.query(pts @ m.T, nrm @ m.T, parts, limit, exact)
        worst = max(worst, float(d.max()))
        if worst > limit:
            return worst
    return worst


def _icp(prep: _Prepared, s: np.ndarray, reach: float, iters: int = 12) -> np.ndarray:
    """Refine an approximate symmetry: orthogonal Procrustes (determinant kept) of the
    screening points onto their closest compatible surface points, both ways (``S x ~ y``
    and ``S^T x ~ y'``), iterated; points further than ``reach`` are left out."""
    x, n, parts = (a[prep.screen] for a in (prep.points, prep.point_normals, prep.point_parts))
    det = 1 if np.linalg.det(s) > 0 else -1
    for _ in range(iters):
        d1, y1 = prep.surface.query(x @ s.T, n @ s.T, parts, reach, False, points=True)
        d2, y2 = prep.surface.query(x @ s, n @ s, parts, reach, False, points=True)
        ok1, ok2 = d1 <= reach, d2 <= reach
        if ok1.sum() + ok2.sum() < 3:
            return s
        u = np.concatenate([x[ok1], y2[ok2]])
        v = np.concatenate([y1[ok1], x[ok2]])
        new = _procrustes(u, v, det)
        if np.abs(new - s).max() < 1e-13:
            return new
        s = new
    return s


def _verified(prep: _Prepared, s: np.ndarray, thr: float) -> float:
    """Absolute residual (metres; ``inf`` when rejected) of an element that passed the
    screen: a vertex permutation, else face matching, else surface distances from every
    verification point."""
    r = _vertex_match_residual(prep, s, thr)
    if r <= thr:
        return r
    few = prep.screen_faces
    if max(_face_match_residual(prep, s, few), _face_match_residual(prep, s.T, few)) <= thr:
        r = max(_face_match_residual(prep, s), _face_match_residual(prep, s.T))
        if r <= thr:
            return r
    r = _surface_residual(prep, s, thr, exact=True)
    return r if r <= thr else math.inf


def _reach(prep: _Prepared, thr: float) -> float:
    """Distance within which an approximate element is refined by :func:`_icp`:
    ``max(10 tol, 0.02) size``, at most ``0.1 size``."""
    return min(0.1, max(10 * thr / prep.size, 0.02)) * prep.size


# ----------------------------------------------------------------------------- candidates
def _procrustes(u: np.ndarray, v: np.ndarray, det: int) -> np.ndarray:
    """Orthogonal ``S`` with ``det S = det`` minimizing ``sum |S u_i - v_i|^2`` (rows)."""
    h = u.T @ v
    w, _, zt = np.linalg.svd(h)
    d = np.eye(3)
    d[2, 2] = det * np.sign(np.linalg.det(zt.T @ w.T) or 1.0)
    return zt.T @ d @ w.T


def _moment_frame(prep: _Prepared):
    """Eigenvalues and eigenvectors (columns) of the area second moment about the centre."""
    t = prep.tri
    ssum = t.sum(axis=1)
    m2 = (prep.areas / 12.0)[:, None, None] * (
        np.einsum("fki,fkj->fij", t, t) + np.einsum("fi,fj->fij", ssum, ssum)
    )
    return np.linalg.eigh(m2.sum(0))


def _regions(prep: _Prepared, eps: float):
    """Flat regions: faces grouped by part, outward normal and plane offset (within eps).
    Returns positions (area centroids), normals, and invariants (k, m)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = prep.normals
    cen = prep.tri.mean(axis=1)
    off = np.einsum("fi,fi->f", n, cen) / prep.size
    keys = np.concatenate([n, off[:, None], 1e3 * prep.parts[:, None]], axis=1)
    # faces in one cell of side eps belong together; cells closer than eps (through the
    # cell diagonal) are then joined: few pairs even when thousands of faces are coplanar
    _, cell = np.unique(np.floor(keys / eps).astype(np.int64), axis=0, return_inverse=True)
    cell = cell.ravel()
    n_cells = cell.max() + 1
    rep = np.zeros((n_cells, keys.shape[1]))
    rep[cell] = keys
    pairs = cKDTree(rep).query_pairs(
        eps * (1 + 2 * math.sqrt(keys.shape[1])), output_type="ndarray"
    )
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n_cells, n_cells))
    _, cell_label = connected_components(g, directed=False)
    label = cell_label[cell]
    k = label.max() + 1
    a = np.bincount(label, prep.areas, k)
    pos = (
        np.stack([np.bincount(label, prep.areas * cen[:, i], k) for i in range(3)], 1) / a[:, None]
    )
    nrm = np.stack([np.bincount(label, prep.areas * n[:, i], k) for i in range(3)], 1)
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    part = np.zeros(k)
    part[label] = prep.parts
    return pos / prep.size, nrm, np.stack([np.sqrt(a) / prep.size, 1e3 * part], 1)


def _classes(inv: np.ndarray, tol: float, p: float = 2.0) -> np.ndarray:
    """Labels of features whose invariants agree within ``tol`` (connected components)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(inv).query_pairs(tol, p=p, output_type="ndarray")
    n = len(inv)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)[1]


def _span2(vs) -> bool:
    """Whether the vectors ``vs`` span two directions (second singular value > 0.2)."""
    if len(vs) < 2:
        return False
    m = np.asarray(vs)
    sv = np.linalg.svd(m / np.linalg.norm(m, axis=1, keepdims=True), compute_uv=False)
    return bool(sv[1] > 0.2)


def _feature_candidates(pos, nrm, inv, tol, axis=None, max_candidates=20000) -> list:
    """Candidates mapping a reference (feature, feature pair, or the unique axis and a
    feature) onto every feature (pair) with the same invariants."""
    from scipy.spatial import cKDTree

    r = np.linalg.norm(pos, axis=1)
    pn = np.einsum("ki,ki->k", pos, nrm)
    has_n = np.linalg.norm(nrm, axis=1) > 0.5
    full_inv = np.concatenate([inv, r[:, None], pn[:, None], has_n[:, None] * 10.0], axis=1)
    # a feature's class: the features whose invariants lie within tol of its own (a ball,
    # not connected components, which chain at loose tolerances)
    tree = cKDTree(full_inv)
    count = tree.query_ball_point(full_inv, tol, return_length=True)
    # vectors each feature carries (position if off-centre, normal if any)
    vecs = [
        [v for v, ok in ((pos[i], r[i] > 0.05), (nrm[i], has_n[i])) if ok] for i in range(len(pos))
    ]

    usable = [i for i in range(len(pos)) if vecs[i]]
    if not usable:
        return []
    order = sorted(usable, key=lambda i: (count[i], -inv[i, 0], -r[i]))
    out = []
    if axis is not None:
        # symmetric top: every symmetry maps the axis to +-itself; one off-axis feature
        b = next((i for i in order if _span2([axis, *vecs[i]])), None)
        if b is None or count[b] > max_candidates // 4:
            return []
        u = np.concatenate([axis[None], np.stack(vecs[b])])
        for j in tree.query_ball_point(full_inv[b], tol):
            vj = np.stack(vecs[j])
            if len(vj) != len(vecs[b]):
                continue
            for sa in (1.0, -1.0):
                v = np.concatenate([sa * axis[None], vj])
                for det in (1, -1):
                    out.append(_procrustes(u, v, det))
        return out
    a = order[0]
    if _span2(vecs[a]):
        u = np.stack(vecs[a])
        for j in tree.query_ball_point(full_inv[a], tol):
            if len(vecs[j]) == len(vecs[a]):
                for det in (1, -1):
                    out.append(_procrustes(u, np.stack(vecs[j]), det))
        return out
    # a pair: the reference and the feature of the smallest class spanning two directions
    b = next((i for i in order if i != a and _span2([*vecs[a], *vecs[i]])), None)
    if b is None or count[a] * count[b] > max_candidates:
        return []
    u = np.concatenate([np.stack(vecs[a]), np.stack(vecs[b])])
    ma = [j for j in tree.query_ball_point(full_inv[a], tol) if len(vecs[j]) == len(vecs[a])]
    mb = np.asarray(
        [k for k in tree.query_ball_point(full_inv[b], tol) if len(vecs[k]) == len(vecs[b])], int
    )
    first_b = np.asarray([vecs[k][0] for k in mb]).reshape(-1, 3)
    ref = float(np.dot(vecs[a][0], vecs[b][0]))
    for j in ma:
        vj = np.stack(vecs[j])
        fit = np.abs(first_b @ vj[0] - ref) <= 4 * tol
        for k in mb[fit]:
            if k == j:
                continue
            v = np.concatenate([vj, np.stack(vecs[k])])
            for det in (1, -1):
                s = _procrustes(u, v, det)
                if np.abs(u @ s.T - v).max() <= 8 * tol + 1e-9:
                    out.append(s)
    return out


def _candidates(prep: _Prepared, tol: float) -> list:
    evals, evecs = _moment_frame(prep)
    scale = max(float(evals.sum()), 1e-300)
    gap = max(20 * tol, 1e-7) * scale
    d01, d12 = evals[1] - evals[0], evals[2] - evals[1]
    out = [np.eye(3)]
    for signs in np.array(np.meshgrid([1, -1], [1, -1], [1, -1])).T.reshape(-1, 3):
        out.append(evecs @ np.diag(signs) @ evecs.T)
    if d01 > gap and d12 > gap:
        return out
    axis = None
    if d01 > gap:
        axis = evecs[:, 0]
    elif d12 > gap:
        axis = evecs[:, 2]
    ftol = max(4 * tol, 1e-7)
    for eps in sorted({1e-9, min(max(4 * tol, 1e-9), 1e-2)}):
        pos, nrm, inv = _regions(prep, eps)
        out += _feature_candidates(pos, nrm, inv, ftol, axis)
    v = np.unique(np.round(prep.tri.reshape(-1, 3) / prep.size, 12), axis=0)
    out += _feature_candidates(v, np.zeros_like(v), np.zeros((len(v), 1)), ftol, axis)
    return out


def _dedupe(mats, tol_angle: float) -> np.ndarray:
    """One representative of every set of matrices closer than ``tol_angle`` (entrywise)."""
    arr = np.asarray(mats, np.float64).reshape(-1, 9)
    if len(arr) == 0:
        return arr.reshape(0, 3, 3)
    lab = _classes(arr, tol_angle, p=np.inf)
    _, first = np.unique(lab, return_index=True)
    return arr[np.sort(first)].reshape(-1, 3, 3)


class _ElementSet:
    """Matrices with a vectorized 'is any within tol_angle (entrywise)' test."""

    def __init__(self, tol_angle: float):
        self.tol = tol_angle
        self.items = np.zeros((0, 3, 3))
        self._tree = None

    def add(self, s):
        self.items = np.concatenate([self.items, np.asarray(s)[None]])
        self._tree = None

    def contains(self, mats) -> np.ndarray:
        from scipy.spatial import cKDTree

        mats = np.asarray(mats).reshape(-1, 9)
        if len(self.items) == 0:
            return np.zeros(len(mats), bool)
        if self._tree is None:
            self._tree = cKDTree(self.items.reshape(-1, 9))
        d, _ = self._tree.query(mats, 1, p=np.inf, distance_upper_bound=2 * self.tol)
        return d <= self.tol


def _consider(mats, prep, thr, same, tested, accepted, residuals) -> None:
    """Verify the untested candidates ``mats`` and add the accepted ones to ``accepted`` with
    their relative residuals. Candidates that pass the screen (a few surface points within
    ``thr``) are verified first; then those within :func:`_reach` of a symmetry and not near
    an accepted element are refined by :func:`_icp`, screened again and verified."""
    near = []
    for s in _dedupe(mats, same):
        if tested.contains(s)[0]:
            continue
        tested.add(s)
        # most wrong candidates miss already on 16 points; the rest are screened on all
        r = _surface_residual(prep, s, thr, prep.screen[:16])
        if r <= thr:
            r = _surface_residual(prep, s, thr, prep.screen)
        if r > thr:
            near.append(s)
            continue
        r = _verified(prep, s, thr)
        if r <= thr and not accepted.contains(s)[0]:
            accepted.add(s)
            residuals.append(r / prep.size)
    reach = _reach(prep, thr)
    for s in near:
        # an element this close to an accepted one would be refined back onto it
        if (
            len(accepted.items)
            and np.abs(accepted.items - s).max(axis=(1, 2)).min() < reach / prep.size
        ):
            continue
        if _surface_residual(prep, s, reach, prep.screen) > reach:
            continue
        s = _icp(prep, s, reach)
        if accepted.contains(s)[0] or _surface_residual(prep, s, thr, prep.screen) > thr:
            continue
        r = _verified(prep, s, thr)
        if r <= thr:
            accepted.add(s)
            residuals.append(r / prep.size)


# ----------------------------------------------------------------------------- entry point
def mesh_symmetries(
    mesh,
    *,
    tol: float = 1e-6,
    materials: bool = True,
    n_samples: int = 512,
    max_points: int = 8192,
    seed: int = 0,
) -> MeshSymmetry:
    """The symmetry elements of a mesh, found from the mesh itself (see the module docstring).

    **Arguments:**

    - `mesh`: a :class:`ppr.Mesh`.
    - `tol`: relative tolerance (fraction of the mesh's size, the largest distance of a
      vertex from the area centroid). The default accepts exact symmetries up to the
      rounding of vertex coordinates; a loose value (``1e-3``) also finds elements that the
      mesh has only approximately. It is raised to at least ``8 eps |v|_max / size``
      (``eps`` of the vertices' dtype, ``|v|_max`` their largest coordinate): float32
      vertices far from the origin are not more precise than that; the tolerance used is
      :attr:`MeshSymmetry.tol`.
    - `materials`: compare parts (a symmetry must map each face onto faces of the same part);
      ``False`` compares the geometry alone.
    - `n_samples`, `max_points`, `seed`: the verification points are `n_samples` seeded
      area samples plus the centroid and three interior points of every face, or of a
      seeded subset of ``max_points / 4`` faces of a larger mesh (faces that an element
      maps onto faces are all checked anyway, see the module docstring).

    **Returns:** a :class:`MeshSymmetry` (identity first; ``len`` the group order).
    """
    if not (isinstance(tol, int | float) and math.isfinite(tol) and 0 < tol < 0.5):
        raise ValueError(f"mesh_symmetries: tol must lie in (0, 0.5), got {tol!r}")
    if int(n_samples) < 1:
        raise ValueError(f"mesh_symmetries: n_samples must be >= 1, got {n_samples!r}")
    prep = _prepare(mesh, materials, int(n_samples), int(seed), int(max_points))
    v = np.asarray(mesh.vertices)
    eps = np.finfo(v.dtype if np.issubdtype(v.dtype, np.floating) else np.float64).eps
    tol = max(float(tol), 8 * eps * float(np.abs(v).max()) / prep.size)
    thr = tol * prep.size
    same = max(4 * tol, 1e-9)  # entrywise: elements this close move no point by > ~tol * size
    accepted, residuals = _ElementSet(same), []
    tested = _ElementSet(same)

    _consider([np.eye(3)], prep, thr, same, tested, accepted, residuals)
    _consider(_candidates(prep, tol), prep, thr, same, tested, accepted, residuals)
    closed = True
    for _ in range(8):  # closure under composition
        g = accepted.items
        prod = np.einsum("aij,bjk->abik", g, g).reshape(-1, 3, 3)
        new = prod[~accepted.contains(prod)]
        if len(new) == 0:
            break
        n_before = len(g)
        _consider(new, prep, thr, same, tested, accepted, residuals)
        if len(accepted.items) == n_before:
            closed = False
            break
    else:
        closed = False
    if not accepted.contains(np.eye(3))[0]:
        raise ValueError(
            f"mesh_symmetries: the identity failed its own check at tol={tol!r}; the mesh may "
            "have overlapping faces of different parts or sides"
        )
    mats, res = _sort_elements(accepted.items, np.asarray(residuals), tol)
    return MeshSymmetry(mats, res, prep.centre, prep.size, float(tol), closed)
