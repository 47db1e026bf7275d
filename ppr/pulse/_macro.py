r"""Macro double bounce: light reflected by one part of the object onto another before it
returns (a solar panel and the body side it meets at right angles, a dish and its mast).

Physics and derivations: ``docs/physics/macro_double_bounce.md``. In short, per unit
incident irradiance the return of the ordered pair (first bounce on surface ``I``, second on
``J``) is

    J_IJ = int_I dA (n_I.u_in) int_(Omega_J(x)) M_J(-k -> u_out) M_I(u_in -> k)
                                               (n_I.k)(n_J.u_out) d omega_k          (1)

``Omega_J(x)`` the directions from ``x`` that reach ``J`` unoccluded, ``M`` the Mueller BRDFs
in beam frames (the intermediate beam's frame is ``perpendicular_unit(k)`` and cancels), the
path lit at ``x`` and seen at its end. Pairs are summed incoherently (the enhanced
backscatter of macroscopic paths is lost at the separations of centimetres, see the notes).

Surfaces
    Coplanar, connected faces of one part are merged into *plates* (:func:`macro_geometry`):
    a plate whose faces exactly tile their convex hull is re-triangulated as a fan over the
    hull, so that a subdivided panel is two triangles again and the result does not depend
    on the tessellation; any other plate keeps its faces. The *macro triangles* are the
    surfaces ``I``, ``J`` of (1).

Glossy pairs: image method with convolved lobes
    For a part with ``m >= GLOSSY_M_MIN`` (and the model BRDF, :func:`ppr.mueller_brdf`) the
    single-bounce lobe ``D(h) = (m + 2)/(2 pi) (h.n)^m`` confines ``k`` to within a few
    ``2/sqrt(m)`` of the specular direction. Each lobe is a near-Gaussian in ``k`` (in-plane
    variance ``4/(m+2)``, out-of-plane ``4 c^2/(m+2)``, ``c`` the cosine of incidence: the
    Gaussian with the lobe's peak and its exact integral ``Lambda = 4 c``); the product of the
    two is again Gaussian (Laplace's method), centred on ``k*``, with integral
    ``Lambda_1 Lambda_2 N(Delta; 0, C_1 + C_2)`` (``Delta`` the mismatch of the two specular
    directions). The slowly varying factors (Fresnel Jones chain, shadowing, cosines) are
    averaged over the product at 3 x 3 Gauss-Hermite points (which keeps the depolarization
    by the varying planes of incidence), and the area integral becomes the exact area of the
    region of ``I`` whose ray along ``k*`` lands on ``J`` (``I`` clipped by the parallel
    projection of ``J``), times its sampled visibility. Relative error ``~0.3/m`` (a 90 deg
    aluminium dihedral against brute-force quadrature, tests/test_macro.py), plus the light
    that the lobes' spread carries past the edges, ``O(sigma^2)`` in the lobe width except
    where the image of an edge falls on an edge. A pair with one glossy and one broad side
    (``m < GLOSSY_M_MIN`` or another BRDF) takes ``k*`` from the glossy lobe and the broad
    side's full BRDF over it. The range of a point of that region is affine in its position,
    so each fan triangle of the clipped polygon is a range tent (the closed form of
    :mod:`ppr.pulse._pulse`).

Broad pairs: point-to-solid-angle quadrature
    Both sides broad: (1) with Gauss points on ``I`` (:func:`triangle_rule`: ``level^2``
    sub-triangles with a ``rule``-point symmetric rule) and, from each, ``3 order^2``
    directions over the solid angle of ``J`` in polar coordinates about its nearest point
    (:func:`broad_nodes`), whose measure stays bounded where ``I`` and ``J`` meet (a fold);
    visibility per node by ray casting; each node's path placed at its range with the
    Gaussian pulse. The Lambertian view factor of two squares at right angles converges at
    second order in the sub-triangle size (tests/test_macro.py).

Visibility (host, no gradients): the same Embree caster as the single bounce: a glossy pair's
fraction is the share of sample points of its overlap polygon that are lit, reach ``J``
unoccluded along ``k*`` and whose landing point is seen by the receiver; a broad pair's is
per node. Everything pose-dependent in the kernel (directions, ``k*``, clipping, lobe
widths, Fresnel) is differentiable in the pose, ``m`` and ``n``.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
import numbers

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._types import Array
from ..geometry._mesh import Mesh, capacity_for, face_areas_normals
from ..geometry._visibility import COS_MIN, VisibilityCaster, barycentric_samples

__all__ = [
    "DEFAULT_TERMS",
    "GLOSSY_M_MIN",
    "LOBE_CUT",
    "MacroGeometry",
    "MacroOptions",
    "MacroPairs",
    "broad_nodes",
    "glossy_parts",
    "macro_geometry",
    "macro_pairs",
    "macro_profile",
    "pose_pairs",
    "stack_macro_pairs",
    "batch_pairs",
    "triangle_rule",
]

GLOSSY_M_MIN = 100.0
"""Parts with ``m >= GLOSSY_M_MIN`` are glossy (image method); below, broad (quadrature)."""
LOBE_CUT = 30.0
"""Glossy pairs whose lobe mismatch ``Delta^T (C_1 + C_2)^-1 Delta`` exceeds this are skipped:
their lobe overlap is below ``exp(-LOBE_CUT / 2) = 3e-7`` of its peak."""
KIND_GG, KIND_GB, KIND_BG = 0, 1, 2
"""Glossy pair kinds: both glossy; first glossy, second broad; first broad, second glossy."""
_K = 8  # vertex slots of a clipped polygon (a triangle clipped by 4 half-planes has <= 7)
_FAN = _K - 2
DEFAULT_TERMS = ("single", "multiple")
"""BRDF terms of the macro-bounce evaluations (the micro double term's quadrature costs
~50 us per evaluation and adds little to a macro path; measured in bench/bench_macro.py)."""


# ----------------------------------------------------------------------------- quadrature


_DUNAVANT = {
    1: ([(1 / 3, 1 / 3, 1 / 3)], [1.0]),
    3: ([(2 / 3, 1 / 6, 1 / 6)], [1 / 3]),
    6: (
        [
            (0.108103018168070, 0.445948490915965, 0.445948490915965),
            (0.816847572980459, 0.091576213509771, 0.091576213509771),
        ],
        [0.223381589678011, 0.109951743655322],
    ),
    7: (
        [
            (1 / 3, 1 / 3, 1 / 3),
            (0.059715871789770, 0.470142064105115, 0.470142064105115),
            (0.797426985353087, 0.101286507323456, 0.101286507323456),
        ],
        [0.225, 0.132394152788506, 0.125939180544827],
    ),
}
"""Symmetric triangle rules (Dunavant 1985): points (orbit generators) and weights summing
to 1; degree 1, 2, 4 and 5 for 1, 3, 6 and 7 points."""


def _local_rule(rule: int) -> tuple[np.ndarray, np.ndarray]:
    if rule not in _DUNAVANT:
        raise ValueError(f"rule must be one of {sorted(_DUNAVANT)} points, got {rule!r}")
    gens, wts = _DUNAVANT[rule]
    pts, ws = [], []
    for g, w in zip(gens, wts, strict=True):
        orbit = {tuple(np.roll(g, s)) for s in range(3)} if len(set(g)) > 1 else {tuple(g)}
        for p in sorted(orbit):
            pts.append(p)
            ws.append(w)
    return np.asarray(pts), np.asarray(ws) / np.sum(ws)


@functools.cache
def _sub_triangles(level: int) -> np.ndarray:
    """``(level^2, 3, 3)`` barycentric vertices of the congruent sub-triangles of a triangle
    whose edges are split in ``level`` (counter-clockwise like the parent)."""
    if int(level) < 1:
        raise ValueError(f"level must be >= 1, got {level!r}")
    n = int(level)
    subs = []
    for i in range(n):
        for j in range(n - i):
            a = np.array([1 - (i + j) / n, i / n, j / n])
            b = np.array([1 - (i + j + 1) / n, (i + 1) / n, j / n])
            c = np.array([1 - (i + j + 1) / n, i / n, (j + 1) / n])
            subs.append((a, b, c))
            if i + j <= n - 2:
                d = np.array([1 - (i + j + 2) / n, (i + 1) / n, (j + 1) / n])
                subs.append((b, d, c))
    return np.stack([np.stack(t) for t in subs])


@functools.cache
def triangle_rule(level: int = 2, rule: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """``(bary (Q, 3), weights (Q,))`` of a composite rule on a triangle: ``level^2``
    congruent sub-triangles (edges split in ``level``), each with the symmetric ``rule``-point
    Dunavant rule (1, 3, 6 or 7 points; degree 1, 2, 4, 5). Weights sum to 1."""
    local, local_w = _local_rule(rule)
    subs = _sub_triangles(level)
    bary = np.einsum("lk,skv->slv", local, subs).reshape(-1, 3)
    return bary, np.tile(local_w, len(subs)) / len(subs)


def _closest_on_triangle(f, tri):
    """Closest points of triangles ``tri (..., 3, 3)`` to points ``f (..., 3)`` in their
    planes (host)."""
    best = None
    dist = None
    e0, e1 = tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :]
    # inside: barycentric coordinates of f all >= 0
    d = f - tri[..., 0, :]
    g00, g01, g11 = (e0 * e0).sum(-1), (e0 * e1).sum(-1), (e1 * e1).sum(-1)
    b0, b1 = (d * e0).sum(-1), (d * e1).sum(-1)
    den = g00 * g11 - g01 * g01
    v = (g11 * b0 - g01 * b1) / den
    w = (g00 * b1 - g01 * b0) / den
    inside = (v >= 0) & (w >= 0) & (v + w <= 1)
    for a_, b_ in ((0, 1), (1, 2), (2, 0)):
        a, b = tri[..., a_, :], tri[..., b_, :]
        ab = b - a
        s = np.clip(((f - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0.0, 1.0)
        c = a + s[..., None] * ab
        dd = ((f - c) ** 2).sum(-1)
        if best is None:
            best, dist = c, dd
        else:
            better = dd < dist
            best = np.where(better[..., None], c, best)
            dist = np.where(better, dd, dist)
    return np.where(inside[..., None], f, best)


def broad_nodes(tri_i, tri_j, level: int, rule: int, order: int):
    """Host: quadrature nodes of broad pairs ``(I, J)`` (``tri (P, 3, 3)`` each): points
    ``x (P, Q, 3)`` of :func:`triangle_rule` on ``I``, and from each point the directions
    ``k (P, Q, Q', 3)`` toward ``J`` with weights ``w (P, Q, Q')`` (area weight of ``x`` times
    solid angle) and distances ``t (P, Q, Q')`` to ``J``; ``Q' = 3 order^2``.

    The solid angle of ``J`` seen from ``x`` is integrated in polar coordinates about ``C``,
    the point of ``J`` closest to the foot of ``x`` on ``J``'s plane: ``J`` splits into the
    three triangles ``(C, v_a, v_b)`` (none negative, ``J`` being convex), each with
    Gauss-Legendre nodes in the angle ``theta`` about ``C`` and in ``psi`` with
    ``rho = h_C tan psi`` (``h_C = |x - C|``), so that ``d omega = h rho d rho d theta / r^3``
    stays bounded as ``x`` approaches ``J`` (the ``1 / r^2`` of the point-to-point kernel,
    which limits plain area-to-area Gauss rules to first order at a shared edge, is
    absorbed by the substitution)."""
    bary, wq = triangle_rule(level, rule)
    xg, wg = np.polynomial.legendre.leggauss(int(order))
    cr_i = np.cross(tri_i[:, 1] - tri_i[:, 0], tri_i[:, 2] - tri_i[:, 0])
    area = 0.5 * np.linalg.norm(cr_i, axis=1)
    x = np.einsum("qk,pkd->pqd", bary, tri_i)  # (P, Q, 3)
    wx = area[:, None] * wq[None, :]
    cr_j = np.cross(tri_j[:, 1] - tri_j[:, 0], tri_j[:, 2] - tri_j[:, 0])
    n_j = cr_j / np.linalg.norm(cr_j, axis=1, keepdims=True)
    tj = tri_j[:, None]  # (P, 1, 3, 3)
    nj = n_j[:, None, :]
    h = ((x - tj[:, :, 0]) * nj).sum(-1)  # (P, Q) height above J's plane
    foot = x - h[..., None] * nj
    c = _closest_on_triangle(foot, np.broadcast_to(tj, x.shape[:2] + (3, 3)))
    hc = np.linalg.norm(x - c, axis=-1)  # (P, Q)
    e1 = tri_j[:, 1] - tri_j[:, 0]
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(n_j, e1)
    ks, ws, ts = [], [], []
    for a_, b_ in ((0, 1), (1, 2), (2, 0)):
        va = tj[:, :, a_] - c  # (P, Q, 3)
        vb = tj[:, :, b_] - c
        a2 = np.stack([(va * e1[:, None]).sum(-1), (va * e2[:, None]).sum(-1)], -1)
        b2 = np.stack([(vb * e1[:, None]).sum(-1), (vb * e2[:, None]).sum(-1)], -1)
        crs = a2[..., 0] * b2[..., 1] - a2[..., 1] * b2[..., 0]
        dth = np.arctan2(crs, (a2 * b2).sum(-1))  # >= 0 for C in J (counter-clockwise)
        tha = np.arctan2(a2[..., 1], a2[..., 0])
        th = tha[..., None] + 0.5 * dth[..., None] * (xg + 1.0)  # (P, Q, n)
        wth = 0.5 * dth[..., None] * wg
        u = np.stack([np.cos(th), np.sin(th)], -1)  # (P, Q, n, 2)
        ba = (b2 - a2)[..., None, :]
        den = u[..., 0] * ba[..., 1] - u[..., 1] * ba[..., 0]
        ok = (crs[..., None] > 1e-14 * np.maximum(hc, 1e-9)[..., None] ** 2) & (np.abs(den) > 0)
        rho_e = np.where(ok, crs[..., None] / np.where(ok, den, 1.0), 0.0)
        psi_e = np.arctan2(rho_e, hc[..., None])  # (P, Q, n)
        psi = 0.5 * psi_e[..., None] * (xg + 1.0)  # (P, Q, n, n)
        wpsi = 0.5 * psi_e[..., None] * wg
        rho = hc[..., None, None] * np.tan(psi)
        drho = hc[..., None, None] / np.cos(psi) ** 2
        dirp = u[..., 0, None] * e1[:, None, None, :] + u[..., 1, None] * e2[:, None, None, :]
        y = c[:, :, None, None, :] + rho[..., None] * dirp[:, :, :, None, :]
        d = y - x[:, :, None, None, :]
        r = np.linalg.norm(d, axis=-1)
        r_s = np.maximum(r, 1e-300)
        dom = h[..., None, None] * rho * drho / r_s**3
        w = np.where(ok[..., None], dom * wth[..., None] * wpsi, 0.0)
        ks.append((d / r_s[..., None]).reshape(d.shape[:2] + (-1, 3)))
        ws.append(w.reshape(w.shape[:2] + (-1,)))
        ts.append(r.reshape(r.shape[:2] + (-1,)))
    k = np.concatenate(ks, axis=2)
    w = np.concatenate(ws, axis=2) * wx[..., None]
    w = np.where(h[..., None] > 0, w, 0.0)
    return x, k, w, np.concatenate(ts, axis=2)


# ----------------------------------------------------------------------------- geometry (host)


@dataclasses.dataclass(frozen=True, eq=False)
class MacroGeometry:
    """Host description of a mesh's surfaces for the macro double bounce (body frame).

    - `tri`: ``(M, 3, 3)`` macro triangles; `normals` ``(M, 3)``, `areas` ``(M,)``,
      `part` ``(M,)`` part index, `plate` ``(M,)`` plate index.
    - `candidates`: ``(K, 2)`` ordered pairs ``(I, J)`` that face each other (some point of
      ``J`` in front of ``I``'s plane and vice versa); none for a convex mesh.
    - `diameter`: longest edge of a macro triangle (m).
    - `n_faces`: faces of the source mesh; `merged`: plates were merged.
    """

    tri: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    part: np.ndarray
    plate: np.ndarray
    candidates: np.ndarray
    diameter: float
    n_faces: int
    merged: bool
    cache: dict = dataclasses.field(default_factory=dict, repr=False)

    @property
    def n_macro(self) -> int:
        return int(self.tri.shape[0])

    @property
    def convex(self) -> bool:
        """No two surfaces face each other: the macro double bounce is exactly zero."""
        return len(self.candidates) == 0


def _plane_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def _plates(tri, area, nrm, part, scale):
    """Plate label per face: same part, same plane (normals and offsets equal to ~1e-9),
    connected through shared vertex positions."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = len(tri)
    off = np.einsum("fk,fk->f", nrm, tri[:, 0])
    key = np.concatenate(
        [
            part[:, None].astype(np.int64),
            np.round(nrm * 1e9).astype(np.int64),
            np.round(off / (scale * 1e-9)).astype(np.int64)[:, None],
        ],
        axis=1,
    )
    _, group = np.unique(key, axis=0, return_inverse=True)
    group = group.reshape(-1)
    vkey = np.round(tri.reshape(-1, 3) / (scale * 1e-9)).astype(np.int64)
    vkey = np.concatenate([np.repeat(group, 3)[:, None], vkey], axis=1)
    _, vid = np.unique(vkey, axis=0, return_inverse=True)
    vid = vid.reshape(-1)
    nv = int(vid.max()) + 1
    rows = np.repeat(np.arange(f), 3)
    adj = coo_matrix((np.ones(3 * f), (rows, f + vid)), shape=(f + nv, f + nv))
    _, lab = connected_components(adj, directed=False)
    _, plate = np.unique(lab[:f], return_inverse=True)
    return plate.reshape(-1)


def _fan_of_hull(tri_faces, normal, total_area):
    """Fan triangles over the convex hull of a plate's vertices if the faces tile it exactly
    (areas equal to 1e-9), else None."""
    from scipy.spatial import ConvexHull, QhullError

    pts = np.unique(tri_faces.reshape(-1, 3), axis=0)
    if len(pts) < 3:
        return None
    e1, e2 = _plane_basis(normal)
    uv = np.stack([pts @ e1, pts @ e2], axis=1)
    try:
        hull = ConvexHull(uv)
    except QhullError:
        return None
    if abs(hull.volume - total_area) > 1e-9 * total_area:
        return None
    v = pts[hull.vertices]  # counter-clockwise in (e1, e2), i.e. about +normal
    return np.stack([np.repeat(v[:1], len(v) - 2, 0), v[1:-1], v[2:]], axis=1)


def _facing(tri, nrm, scale, chunk=2048):
    """Ordered pairs (I, J) with some vertex of J strictly in front of I's plane and some
    vertex of I strictly in front of J's plane (pose independent).

    Both surfaces of such a pair have some vertex of the mesh in front of their plane, so the
    pairs are searched among those surfaces only: one matrix product of the planes with the
    mesh's vertices finds them (none for a convex mesh: a 20480-face sphere in ~1 s instead of
    the quadratic search's 80 s and 2.2 GB)."""
    m = len(tri)
    tol = 1e-9 * scale
    off = np.einsum("mk,mk->m", nrm, tri[:, 0])
    verts = np.unique(tri.reshape(-1, 3), axis=0)
    above = np.zeros(m, bool)
    step = max(1, (1 << 22) // max(len(verts), 1))  # <= 32 MB of heights at a time
    for s in range(0, m, step):
        a = slice(s, min(m, s + step))
        above[a] = (nrm[a] @ verts.T - off[a, None]).max(1) > tol
    idx = np.flatnonzero(above)
    if len(idx) == 0:
        return np.zeros((0, 2), np.int32)
    tri, nrm, off = tri[idx], nrm[idx], off[idx]
    k = len(idx)
    chunk = max(1, min(chunk, (1 << 22) // (3 * k)))  # <= 32 MB per height table
    # h[a, b] = max over the vertices of b of their height above a's plane
    out = []
    for s in range(0, k, chunk):
        a = slice(s, min(k, s + chunk))
        h_ab = np.einsum("ak,bvk->abv", nrm[a], tri).max(-1) - off[a, None]  # (A, K)
        h_ba = np.einsum("bk,avk->abv", nrm, tri[a]).max(-1) - off[None, :]  # (A, K)
        ii, jj = np.nonzero((h_ab > tol) & (h_ba > tol))
        out.append(np.stack([idx[ii + s], idx[jj]], 1))
    pairs = np.concatenate(out) if out else np.zeros((0, 2), np.int64)
    return pairs.astype(np.int32)


def macro_geometry(mesh: Mesh, *, plates: bool = True) -> MacroGeometry:
    """Host: the macro triangles of ``mesh`` and their facing pairs (module docstring).

    ``plates=False`` keeps every face as its own surface (the result is the same up to the
    quadrature of broad pairs; the cost grows with the face count). Cached per mesh."""
    tri = mesh.triangles()
    key = (
        hashlib.sha1(np.ascontiguousarray(tri).tobytes()).hexdigest(),
        hashlib.sha1(np.asarray(mesh.material_ids).tobytes()).hexdigest(),
        bool(plates),
    )
    return _macro_geometry_cached(key, tri, np.asarray(mesh.material_ids), bool(plates))


def _macro_geometry_cached(key, tri, part, plates):
    hit = _GEOMETRY_CACHE.get(key)
    if hit is None:
        hit = _build_geometry(tri, part, plates)
        if len(_GEOMETRY_CACHE) >= 16:
            _GEOMETRY_CACHE.pop(next(iter(_GEOMETRY_CACHE)))
        _GEOMETRY_CACHE[key] = hit
    return hit


_GEOMETRY_CACHE: dict = {}


def _build_geometry(tri, part, plates):
    area, nrm = face_areas_normals(tri)
    ok = area > 0
    tri, area, nrm, part = tri[ok], area[ok], nrm[ok], part[ok]
    pts = tri.reshape(-1, 3)
    scale = max(float(np.linalg.norm(pts.max(0) - pts.min(0))), 1e-12)
    out_t, out_p, out_plate = [], [], []
    if plates:
        plate = _plates(tri, area, nrm, part, scale)
        for p in range(int(plate.max()) + 1):
            sel = np.flatnonzero(plate == p)
            fan = None
            if len(sel) > 1:
                fan = _fan_of_hull(tri[sel], nrm[sel[0]], float(area[sel].sum()))
            t = tri[sel] if fan is None else fan
            out_t.append(t)
            out_p.append(np.full(len(t), part[sel[0]]))
            out_plate.append(np.full(len(t), p))
        mt = np.concatenate(out_t)
        mp = np.concatenate(out_p)
        mplate = np.concatenate(out_plate)
    else:
        mt, mp, mplate = tri, part, np.arange(len(tri))
    ma, mn = face_areas_normals(mt)
    # a fan triangle of collinear points carries nothing (ppr.check_mesh's shape test: a
    # small real facet on a large mesh stays)
    longest = np.linalg.norm(mt - np.roll(mt, 1, axis=1), axis=-1).max(-1)
    keep = ma > 1e-12 * longest * longest
    mt, mp, mplate, ma, mn = mt[keep], mp[keep], mplate[keep], ma[keep], mn[keep]
    cand = _facing(mt, mn, scale)
    cand = cand[mplate[cand[:, 0]] != mplate[cand[:, 1]]]
    edge = np.linalg.norm(mt - np.roll(mt, 1, axis=1), axis=-1)
    return MacroGeometry(
        tri=mt,
        normals=mn,
        areas=ma,
        part=mp.astype(np.int32),
        plate=mplate.astype(np.int32),
        candidates=cand,
        diameter=float(edge.max()) if len(edge) else 0.0,
        n_faces=len(tri),
        merged=plates,
    )


# ----------------------------------------------------------------------------- shared math
# written for both NumPy (host pair selection) and jax.numpy (kernel): ``xp`` is the module


def _dot(xp, a, b):
    return xp.sum(a * b, axis=-1)


def _cross(xp, a, b):
    return xp.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def _unit(xp, v, fallback):
    """``v / |v|`` with ``fallback`` where ``|v|^2`` is below 1e-30 (double where)."""
    q = _dot(xp, v, v)
    ok = q > 1e-30
    inv = 1.0 / xp.sqrt(xp.where(ok, q, 1.0))
    return xp.where(ok[..., None], v * inv[..., None], fallback)


def _perp(xp, d):
    """A unit vector perpendicular to unit ``d`` (as :func:`ppr.optics.perpendicular_unit`)."""
    use_y = xp.abs(d[..., 0]) > 0.9
    z = xp.zeros_like(d[..., 0])
    v = xp.stack(
        [
            xp.where(use_y, -d[..., 2], z),
            xp.where(use_y, z, d[..., 2]),
            xp.where(use_y, d[..., 0], -d[..., 1]),
        ],
        axis=-1,
    )
    return v / xp.sqrt(xp.maximum(_dot(xp, v, v), 0.1))[..., None]


def _lobe_cov(xp, u, n, m):
    """``(3, 3)`` covariance of a Blinn-Phong lobe in the reflected direction about its
    specular direction: ``4/(m+2) [P_perp(k_s) - (u x n)(u x n)^T]`` (the Gaussian with the
    lobe's peak ``(m + 2)/(2 pi)`` and integral ``4 c``)."""
    c = _dot(xp, u, n)
    ks = 2.0 * c[..., None] * n - u
    a = _cross(xp, u, n)
    eye = xp.eye(3, dtype=u.dtype)
    p = eye - ks[..., :, None] * ks[..., None, :] - a[..., :, None] * a[..., None, :]
    return (4.0 / (m + 2.0))[..., None, None] * p, ks, c


def specular_solution(xp, n_i, n_j, u_in, u_out, m_i, m_j, kind):
    """Laplace solution of a glossy pair: ``(k*, lambda, q)`` with ``k*`` the direction of the
    light from ``I`` to ``J``, ``lambda`` the integral of the lobe product (GG:
    ``Lambda_1 Lambda_2 N(Delta; 0, Sigma)``; GB: ``Lambda_1``; BG: ``Lambda_2``) and ``q`` the
    mismatch ``Delta^T Sigma^-1 Delta`` (0 for GB, BG). Batched over a leading axis."""
    c1_mat, ks1, c1 = _lobe_cov(xp, u_in, n_i, m_i)
    c2_mat, kr2, c2 = _lobe_cov(xp, u_out, n_j, m_j)
    ks2 = -kr2  # propagation direction arriving at J
    lam1 = 4.0 * c1  # int D(h(k)) d omega_k = int D(h) 4 (u.h) d omega_h = 4 c (exact)
    lam2 = 4.0 * c2
    gg = kind == KIND_GG
    kbar = xp.where(
        gg[..., None],
        _unit(xp, ks1 + ks2, ks1),
        xp.where((kind == KIND_GB)[..., None], ks1, ks2),
    )
    ea = _perp(xp, kbar)
    eb = _cross(xp, kbar, ea)

    def proj2(cm):
        ca = xp.einsum("...ij,...j->...i", cm, ea)
        cb = xp.einsum("...ij,...j->...i", cm, eb)
        return _dot(xp, ea, ca), _dot(xp, ea, cb), _dot(xp, eb, cb)

    a1, b1, d1 = proj2(c1_mat)
    a2, b2, d2 = proj2(c2_mat)
    sa, sb, sd = a1 + a2, b1 + b2, d1 + d2
    det = sa * sd - sb * sb
    tiny = 1e-300 if u_in.dtype == np.float64 else 1e-37
    det_ok = det > tiny
    det_s = xp.where(det_ok, det, 1.0)
    dv = ks1 - ks2
    da, db = _dot(xp, dv, ea), _dot(xp, dv, eb)
    ia, ib, id_ = sd / det_s, -sb / det_s, sa / det_s  # Sigma^-1
    q = da * (ia * da + ib * db) + db * (ib * da + id_ * db)
    q = xp.where(det_ok & gg, q, 0.0)
    q_s = xp.minimum(q, 200.0)
    gauss = xp.exp(-0.5 * q_s) / (2.0 * math.pi * xp.sqrt(det_s))
    lam = xp.where(
        gg, lam1 * lam2 * xp.where(det_ok, gauss, 0.0), xp.where(kind == KIND_GB, lam1, lam2)
    )
    # mean of the lobe product: mu2 + C2 Sigma^-1 Delta (tangent coordinates about kbar)
    m2a, m2b = _dot(xp, ks2 - kbar, ea), _dot(xp, ks2 - kbar, eb)
    ta, tb = ia * da + ib * db, ib * da + id_ * db
    mua = m2a + a2 * ta + b2 * tb
    mub = m2b + b2 * ta + d2 * tb
    kstar = _unit(xp, kbar + mua[..., None] * ea + mub[..., None] * eb, kbar)
    kstar = xp.where(gg[..., None], kstar, kbar)
    # covariance of k under the lobe product (GG: C1 - C1 Sigma^-1 C1 = (C1^-1 + C2^-1)^-1;
    # GB: C1; BG: C2), as its Cholesky factor in the tangent basis (ea, eb)
    s_a = a1 * ia + b1 * ib
    s_b = a1 * ib + b1 * id_
    t_a = b1 * ia + d1 * ib
    t_b = b1 * ib + d1 * id_
    pa = xp.where(gg, a1 - (s_a * a1 + s_b * b1), xp.where(kind == KIND_GB, a1, a2))
    pb = xp.where(gg, b1 - (s_a * b1 + s_b * d1), xp.where(kind == KIND_GB, b1, b2))
    pd = xp.where(gg, d1 - (t_a * b1 + t_b * d1), xp.where(kind == KIND_GB, d1, d2))
    l11 = xp.sqrt(xp.maximum(pa, 0.0))
    l21 = xp.where(l11 > 0, pb / xp.where(l11 > 0, l11, 1.0), 0.0)
    l22 = xp.sqrt(xp.maximum(pd - l21 * l21, 0.0))
    chol = (ea * l11[..., None] + eb * l21[..., None], eb * l22[..., None])
    return kstar, lam, q, chol


_SIGMA_Z = np.array([-math.sqrt(3.0), 0.0, math.sqrt(3.0)])
_SIGMA_W = np.array([1.0, 4.0, 1.0]) / 6.0
SIGMA_POINTS = np.stack(np.meshgrid(_SIGMA_Z, _SIGMA_Z, indexing="ij"), -1).reshape(-1, 2)
SIGMA_WEIGHTS = np.outer(_SIGMA_W, _SIGMA_W).reshape(-1)
"""Gauss-Hermite rule (3 x 3 points) for the average of the slowly varying factors (Fresnel
chain, shadowing, cosines) over the lobe product: exact for polynomials of degree 5 in each
tangent coordinate, so the depolarization of the varying planes of incidence across the
lobe (``O(1/m)``) is kept."""


def _clip(xp, poly, cnt, a, c):
    """Sutherland-Hodgman: convex polygons ``(P, K, 2)`` with ``cnt`` vertices clipped to
    ``a . x + c >= 0``; fixed ``K`` slots, compacted by a one-hot product (differentiable in
    the vertices; a crossing's parameter is guarded by a double where)."""
    p_, k = poly.shape[0], poly.shape[1]
    idx = xp.arange(k)
    live = idx[None, :] < cnt[:, None]
    nxt = xp.where(idx[None, :] + 1 < cnt[:, None], idx[None, :] + 1, 0)
    q = xp.take_along_axis(poly, xp.broadcast_to(nxt[..., None], (p_, k, 2)), axis=1)
    d0 = _dot(xp, poly, a[:, None, :]) + c[:, None]
    d1 = _dot(xp, q, a[:, None, :]) + c[:, None]
    in0, in1 = d0 >= 0, d1 >= 0
    cross = live & (in0 != in1)
    den = xp.where(cross, d0 - d1, 1.0)
    s = xp.where(cross, d0 / den, 0.0)
    x = poly + s[..., None] * (q - poly)
    cand = xp.stack([poly, x], axis=2).reshape(p_, 2 * k, 2)
    keep = xp.stack([live & in0, cross], axis=2).reshape(p_, 2 * k)
    pos = xp.cumsum(keep.astype(np.int32), axis=1) - 1
    onehot = (pos[:, :, None] == idx[None, None, :]) & keep[:, :, None]
    out = xp.einsum("psk,psd->pkd", onehot.astype(poly.dtype), cand)
    return out, xp.minimum(xp.sum(keep.astype(np.int32), axis=1), k).astype(np.int32)


def overlap_fans(xp, tri_i, n_i, tri_j, n_j, kstar):
    """The region of triangle ``I`` whose ray along ``kstar`` lands on triangle ``J`` (in front
    of ``J``'s plane): ``(fans (P, 6, 3, 3), areas (P, 6), t_fans (P, 6, 3))`` - the fan
    triangles of the clipped polygon in 3D, their areas (0 for unused fans) and each vertex's
    distance along ``kstar`` to ``J``'s plane. Needs ``n_i . kstar > 0 > n_j . kstar``."""
    p_ = tri_i.shape[0]
    dt = tri_i.dtype
    o = tri_i[:, 0]
    e1 = _unit(xp, tri_i[:, 1] - o, _perp(xp, n_i))
    e2 = _cross(xp, n_i, e1)

    def to2(x):
        r = x - o[:, None, :]
        return xp.stack([_dot(xp, r, e1[:, None]), _dot(xp, r, e2[:, None])], axis=-1)

    cik = _dot(xp, n_i, kstar)
    cik_s = xp.where(cik > 1e-12, cik, 1.0)
    ty = _dot(xp, tri_j - o[:, None, :], n_i[:, None, :]) / cik_s[:, None]
    pj = to2(tri_j - ty[..., None] * kstar[:, None, :])  # (P, 3, 2) projected J
    sub = to2(tri_i)
    poly = xp.concatenate([sub, xp.zeros((p_, _K - 3, 2), dt)], axis=1)
    cnt = xp.full((p_,), 3, dtype=np.int32)
    orient = (pj[:, 1, 0] - pj[:, 0, 0]) * (pj[:, 2, 1] - pj[:, 0, 1]) - (
        pj[:, 1, 1] - pj[:, 0, 1]
    ) * (pj[:, 2, 0] - pj[:, 0, 0])
    sgn = xp.where(orient > 0, 1.0, -1.0)
    flat = xp.abs(orient) <= 1e-24
    planes_a, planes_c = [], []
    for e in range(3):
        pa, pb = pj[:, e], pj[:, (e + 1) % 3]
        ed = pb - pa
        a = sgn[:, None] * xp.stack([-ed[:, 1], ed[:, 0]], axis=-1)
        c = -_dot(xp, a, pa)
        planes_a.append(xp.where(flat[:, None], 0.0, a))
        planes_c.append(xp.where(flat, -1.0, c))  # J edge-on to k*: empty
    # in front of J's plane: n_j . (x - y0) >= 0
    planes_a.append(xp.stack([_dot(xp, n_j, e1), _dot(xp, n_j, e2)], axis=-1))
    planes_c.append(_dot(xp, n_j, o - tri_j[:, 0]))
    if xp is np:
        for a, c in zip(planes_a, planes_c, strict=True):
            poly, cnt = _clip(xp, poly, cnt, a, c)
    else:
        # one compiled clipping step, scanned over the four half-planes

        def step(carry, ac):
            return _clip(xp, *carry, *ac), None

        (poly, cnt), _ = jax.lax.scan(step, (poly, cnt), (xp.stack(planes_a), xp.stack(planes_c)))
    v0 = poly[:, :1]
    va, vb = poly[:, 1:-1], poly[:, 2:]
    ar = 0.5 * (
        (va[..., 0] - v0[..., 0]) * (vb[..., 1] - v0[..., 1])
        - (va[..., 1] - v0[..., 1]) * (vb[..., 0] - v0[..., 0])
    )
    use = xp.arange(_FAN)[None, :] + 2 < cnt[:, None]
    ar = xp.where(use, xp.maximum(ar, 0.0), 0.0)
    p3 = o[:, None, :] + poly[..., :1] * e1[:, None, :] + poly[..., 1:] * e2[:, None, :]
    fans = xp.stack(
        [xp.broadcast_to(p3[:, :1], (p_, _FAN, 3)), p3[:, 1:-1], p3[:, 2:]], axis=2
    )  # (P, FAN, 3, 3)
    cjk = _dot(xp, n_j, kstar)
    cjk_s = xp.where(cjk < -1e-12, cjk, -1.0)
    t = _dot(xp, tri_j[:, None, None, 0, :] - fans, n_j[:, None, None, :]) / cjk_s[:, None, None]
    return fans, ar, t


# ----------------------------------------------------------------------------- pairs (host)


class MacroPairs(eqx.Module):
    """Kernel inputs of the macro double bounce at one pose (host-built by
    :func:`macro_pairs`; stack several along a leading axis for ``vmap``).

    - `tri` ``(Mc, 3, 3)``, `normals` ``(Mc, 3)``, `part` ``(Mc,)``: macro triangles (body
      frame, padded).
    - `g_i`, `g_j`, `g_kind`, `g_vis` ``(Pg,)``: glossy pairs (first and second surface, kind
      ``KIND_GG``/``GB``/``BG``, visibility fraction; padding has ``g_vis = 0``).
    - `r_i`, `r_j` ``(Pr,)``: broad pairs; `r_x` ``(Pr, Q, 3)``, `r_k` ``(Pr, Q, Q', 3)``,
      `r_w` ``(Pr, Q, Q')``, `r_t` ``(Pr, Q, Q')``: their quadrature nodes
      (:func:`broad_nodes`; body frame, pose independent), the weights times the visibility of
      each path (0 for padding).
    - static: `window` and `point_window` (bins per
      glossy and per broad range item, :func:`ppr.window_size`; 0: every bin), `terms` (BRDF
      terms of the evaluations), `mixed` (some glossy pair has a broad side: the full BRDF
      is evaluated for the glossy pairs too).
    """

    tri: Array
    normals: Array
    part: Array
    g_i: Array
    g_j: Array
    g_kind: Array
    g_vis: Array
    r_i: Array
    r_j: Array
    r_x: Array
    r_k: Array
    r_w: Array
    r_t: Array
    window: int = eqx.field(static=True, default=0)
    point_window: int = eqx.field(static=True, default=0)
    mixed: bool = eqx.field(static=True, default=True)
    terms: tuple = eqx.field(static=True, default=DEFAULT_TERMS)

    @property
    def n_glossy(self) -> int:
        return int(np.sum(np.asarray(self.g_vis) > 0))

    @property
    def n_broad(self) -> int:
        return int(np.sum(np.any(np.asarray(self.r_w) > 0, axis=(-1, -2))))

    def compact(self) -> MacroPairs:
        """Host: the same pairs with the padding no live entry needs dropped, for a program
        that will only ever see these pairs (a sampler's fixed pairs): the glossy and the broad
        slots cut to the capacity of their live count (0 when none is live: the kernel then
        leaves that path out), and `mixed` recomputed from the live glossy pairs. The profile
        is unchanged (padding carries zero weight); its cost is not: dead broad slots still
        cost their BRDF evaluations (bench/results/walker_cost.md). Works on one pose or a
        stacked batch (cut to the largest live count of its rows)."""
        g_live = np.asarray(self.g_vis) > 0
        r_live = np.any(np.asarray(self.r_w) > 0, axis=(-1, -2))

        def keep(live):
            counts = np.sum(live, axis=-1).reshape(-1)  # (zero slots: counts of 0)
            n = int(counts.max()) if counts.size else 0
            # live slots come first (_pack); anything live beyond the cut would be lost
            if np.any(live[..., n:]):
                raise ValueError("MacroPairs.compact: live slots are not a prefix (not packed)")
            return min(_pair_capacity(n), live.shape[-1])

        cg, cr = keep(g_live), keep(r_live)
        kinds = np.asarray(self.g_kind)[g_live]
        return dataclasses.replace(
            self,
            g_i=self.g_i[..., :cg],
            g_j=self.g_j[..., :cg],
            g_kind=self.g_kind[..., :cg],
            g_vis=self.g_vis[..., :cg],
            r_i=self.r_i[..., :cr],
            r_j=self.r_j[..., :cr],
            r_x=self.r_x[..., :cr, :, :],
            r_k=self.r_k[..., :cr, :, :, :],
            r_w=self.r_w[..., :cr, :, :],
            r_t=self.r_t[..., :cr, :, :],
            mixed=bool(self.mixed and np.any(kinds != KIND_GG)),
        )


def _pair_capacity(n: int) -> int:
    """Padded count: 0 for none (the kernel then leaves that path out), else the next power
    of two from 8 up to 64, then :func:`ppr.geometry._mesh.capacity_for`."""
    n = int(n)
    if n <= 0:
        return 0
    return max(8, 1 << (n - 1).bit_length()) if n <= 64 else capacity_for(n)


def _escape(caster: VisibilityCaster, pts, nrm, u):
    """Rays from ``pts`` (lifted along ``nrm``) toward ``u`` escape the mesh."""
    if len(pts) == 0:
        return np.zeros(0, bool)
    org = pts - caster.centre + caster._offset * nrm  # the caster's centred coordinates
    hit = caster._ray.intersects_any(org, np.ascontiguousarray(np.broadcast_to(u, org.shape)))
    return ~np.asarray(hit, bool)


def _clear(caster: VisibilityCaster, pts, nrm, targets):
    """The segment from ``pts`` (lifted along ``nrm``) to ``targets`` meets no surface before
    it (hits within 1e-6 of its length, or the caster's offset, of the end count as the end)."""
    if len(pts) == 0:
        return np.zeros(0, bool)
    org = pts - caster.centre + caster._offset * nrm  # the caster's centred coordinates
    d = targets - caster.centre - org
    dist = np.linalg.norm(d, axis=1)
    dirs = d / np.maximum(dist, 1e-300)[:, None]
    loc, ray, _ = caster._ray.intersects_location(org, dirs, multiple_hits=False)
    first = np.full(len(org), np.inf)
    if len(ray):
        first[ray] = np.linalg.norm(loc - org[ray], axis=1)
    return first >= dist - np.maximum(1e-6 * dist, 2.0 * caster._offset)


def _cached_nodes(g: MacroGeometry, ib, jb, level, rule, order):
    """:func:`broad_nodes` of the pairs ``(ib, jb)`` (pose independent: cached on ``g``)."""
    cache = g.cache.setdefault(("nodes", level, rule, order), {})
    missing = [(a, b) for a, b in zip(ib.tolist(), jb.tolist(), strict=True) if (a, b) not in cache]
    if missing:
        a, b = np.asarray(missing).T
        new = broad_nodes(g.tri[a], g.tri[b], level, rule, order)
        for n, key in enumerate(missing):
            cache[key] = tuple(v[n] for v in new)
    rows = [cache[(a, b)] for a, b in zip(ib.tolist(), jb.tolist(), strict=True)]
    return tuple(np.stack([r[c] for r in rows]) for c in range(4))


def macro_pairs(
    geometry: MacroGeometry,
    caster: VisibilityCaster,
    laser_dir_body,
    receiver_dir_body,
    glossy_parts,
    m_parts,
    *,
    level: int = 1,
    rule: int = 6,
    order: int = 4,
    samples: int = 16,
    bins: tuple[float, float, int] | None = None,
    terms: tuple = DEFAULT_TERMS,
    window: int | None = None,
    capacities: tuple[int, int, int] | None = None,
    node_capacity: tuple[int, int] | None = None,
    mixed: bool | None = None,
    dtype=None,
) -> tuple[MacroPairs, dict]:
    """Host: the pairs of ``geometry`` that can send light from the laser to the receiver at
    one pose (body-frame directions), with their visibility (module docstring), and a host
    summary: counts, glossy pairs cut by ``LOBE_CUT`` and the body-frame one-way range
    interval ``(lo, hi)`` of the kept paths (None if none).

    **Arguments:**

    - `geometry`: :func:`macro_geometry` of the mesh; `caster`: its
      :class:`ppr.VisibilityCaster`.
    - `glossy_parts`: ``(n_parts,)`` bool, parts treated by the image method
      (:func:`glossy_parts`); `m_parts`: their Blinn-Phong exponents (for the pruning).
    - `level`, `rule`, `order`: quadrature of broad pairs (:func:`broad_nodes`: points of
      :func:`triangle_rule` on the first surface, ``3 order^2`` directions toward the second).
    - `samples`: visibility samples per fan triangle of a glossy pair's overlap (a square).
    - `bins`: ``(sigma_r, bin_width, n_bins)`` of the render, to size the static range
      windows (default: every bin, the dense evaluation); `window`: the glossy items' window
      instead (fixed across poses).
    - `capacities`: ``(macro triangles, glossy pairs, broad pairs)`` padding (default: the
      next bucket of each count); fixed values let several poses share one program, as do
      `node_capacity` (points and directions per broad pair) and `mixed` (evaluate the full
      BRDF for glossy pairs whether or not one has a broad side).
    - `terms`: BRDF terms of the evaluations (default :data:`DEFAULT_TERMS`).
    """
    sel = _select_pairs(
        geometry,
        caster,
        laser_dir_body,
        receiver_dir_body,
        glossy_parts,
        m_parts,
        level=level,
        rule=rule,
        order=order,
        samples=samples,
    )
    return _pack(
        geometry,
        sel,
        bins=bins,
        terms=terms,
        window=window,
        capacities=capacities,
        node_capacity=node_capacity,
        mixed=mixed,
        dtype=dtype,
    )


def _select_pairs(
    g: MacroGeometry,
    caster: VisibilityCaster,
    laser_dir_body,
    receiver_dir_body,
    glossy_parts,
    m_parts,
    *,
    level: int,
    rule: int,
    order: int,
    samples: int,
) -> dict:
    """Host: the pairs that pass a pose's tests, their kinds, visibility and nodes (the
    selection :func:`_pack` pads), with the summary of :func:`macro_pairs`."""
    u_in = np.asarray(laser_dir_body, np.float64)
    u_in = u_in / np.linalg.norm(u_in)
    u_out = np.asarray(receiver_dir_body, np.float64)
    u_out = u_out / np.linalg.norm(u_out)
    gl = np.asarray(glossy_parts, bool)
    mp = np.asarray(m_parts, np.float64)
    cand = g.candidates
    if len(cand):
        i, j = cand[:, 0], cand[:, 1]
        ok = (g.normals[i] @ u_in > COS_MIN) & (g.normals[j] @ u_out > COS_MIN)
        i, j = i[ok], j[ok]
    else:
        i = j = np.zeros(0, np.int32)
    gi, gj = gl[g.part[i]], gl[g.part[j]]
    glossy = gi | gj
    gsel = [], [], [], []
    extent = 0.0
    span_lo, span_hi = np.inf, -np.inf
    n_cut = 0
    ii, jj = i[glossy], j[glossy]
    if len(ii):
        kind = np.where(gi[glossy] & gj[glossy], KIND_GG, np.where(gi[glossy], KIND_GB, KIND_BG))
        n_i, n_j = g.normals[ii], g.normals[jj]
        ub_in = np.broadcast_to(u_in, n_i.shape)
        ub_out = np.broadcast_to(u_out, n_i.shape)
        kstar, _, q, _ = specular_solution(
            np, n_i, n_j, ub_in, ub_out, mp[g.part[ii]], mp[g.part[jj]], kind
        )
        ok = (
            (np.einsum("pk,pk->p", n_i, kstar) > COS_MIN)
            & (np.einsum("pk,pk->p", n_j, kstar) < -COS_MIN)
            & (q <= LOBE_CUT)
        )
        n_cut = int(np.sum(q > LOBE_CUT))
        ii, jj, kind, kstar = ii[ok], jj[ok], kind[ok], kstar[ok]
        fans, ar, t = overlap_fans(np, g.tri[ii], g.normals[ii], g.tri[jj], g.normals[jj], kstar)
        has = ar.sum(1) > 1e-12 * max(g.diameter, 1e-9) ** 2
        bary = barycentric_samples(math.isqrt(int(samples)))
        ns = len(bary)
        keep = np.flatnonzero(has)
        if len(keep):
            # every sample of every kept pair in three batched ray casts
            x = np.einsum("sk,pfkd->pfsd", bary, fans[keep]).reshape(-1, 3)
            tt = np.einsum("sk,pfk->pfs", bary, t[keep]).reshape(-1)
            ks = np.repeat(kstar[keep], _FAN * ns, axis=0)
            y = x + tt[:, None] * ks
            ni = np.repeat(g.normals[ii[keep]], _FAN * ns, axis=0)
            nj = np.repeat(g.normals[jj[keep]], _FAN * ns, axis=0)
            wts = np.repeat((ar[keep] / ar[keep].sum(1, keepdims=True)).reshape(-1), ns) / ns
            live = wts > 0
            good = np.zeros(len(x), bool)
            sel = np.flatnonzero(live)
            ok1 = _escape(caster, x[sel], ni[sel], u_in)
            sel = sel[ok1]
            ok2 = _clear(caster, x[sel], ni[sel], y[sel])
            sel = sel[ok2]
            ok3 = _escape(caster, y[sel], nj[sel], u_out)
            good[sel[ok3]] = True
            vis = (wts * good).reshape(len(keep), -1).sum(1)
            dep = (-fans[keep] @ (u_in + u_out)) + t[keep] * (1.0 - kstar[keep] @ u_out)[
                :, None, None
            ]
            used = ar[keep][..., None] > 0
            span = np.where(used, dep, -np.inf).max((1, 2)) - np.where(used, dep, np.inf).min(
                (1, 2)
            )
            for n, p in enumerate(keep):
                if vis[n] > 0:
                    gsel[0].append(ii[p])
                    gsel[1].append(jj[p])
                    gsel[2].append(kind[p])
                    gsel[3].append(float(vis[n]))
                    extent = max(extent, 0.5 * float(span[n]))
                    span_lo = min(span_lo, 0.5 * float(np.where(used[n], dep[n], np.inf).min()))
                    span_hi = max(span_hi, 0.5 * float(np.where(used[n], dep[n], -np.inf).max()))
    # broad pairs: visibility per (point of I, direction toward J) node
    bary_q, _ = triangle_rule(level, rule)
    nq, nd = len(bary_q), 3 * int(order) ** 2
    rsel_i, rsel_j, rsel = [], [], []
    ib, jb = i[~glossy], j[~glossy]
    if len(ib):
        x, kd, wd, td = _cached_nodes(g, ib, jb, level, rule, order)
        na, nb = g.normals[ib], g.normals[jb]
        ok = (
            (wd > 0)
            & (np.einsum("pqdk,pk->pqd", kd, na) > COS_MIN)
            & (np.einsum("pqdk,pk->pqd", kd, nb) < -COS_MIN)
        )
        lit = _escape(caster, x.reshape(-1, 3), np.repeat(na, nq, axis=0), u_in).reshape(
            len(ib), nq
        )
        ok &= lit[:, :, None]
        sel = np.flatnonzero(ok.reshape(-1))
        xs = np.broadcast_to(x[:, :, None, :], kd.shape).reshape(-1, 3)[sel]
        ys = xs + (td.reshape(-1)[sel])[:, None] * kd.reshape(-1, 3)[sel]
        na_s = np.broadcast_to(na[:, None, None, :], kd.shape).reshape(-1, 3)[sel]
        nb_s = np.broadcast_to(nb[:, None, None, :], kd.shape).reshape(-1, 3)[sel]
        good = _clear(caster, xs, na_s, ys)
        good[good] = _escape(caster, ys[good], nb_s[good], u_out)
        vis = np.zeros(ok.size)
        vis[sel[good]] = 1.0
        vis = vis.reshape(ok.shape)
        if len(sel) and good.any():
            rr = 0.5 * (-(xs[good] @ u_in) + np.linalg.norm(ys[good] - xs[good], axis=1))
            rr -= 0.5 * (ys[good] @ u_out)
            span_lo, span_hi = min(span_lo, float(rr.min())), max(span_hi, float(rr.max()))
        for n in np.flatnonzero(vis.any((1, 2))):
            rsel_i.append(ib[n])
            rsel_j.append(jb[n])
            rsel.append((x[n], kd[n], wd[n] * vis[n], td[n]))
    sel = {
        "gsel": gsel,
        "rsel": (rsel_i, rsel_j, rsel),
        "nq": nq,
        "nd": nd,
        "extent": extent,
        "info": {
            "glossy": len(gsel[0]),
            "broad": len(rsel_i),
            "lobe_cut": n_cut,
            "range": (span_lo, span_hi) if span_lo <= span_hi else None,
        },
    }
    return sel


def _pack(
    g: MacroGeometry,
    sel: dict,
    *,
    bins=None,
    terms=DEFAULT_TERMS,
    window=None,
    capacities=None,
    node_capacity=None,
    mixed=None,
    dtype=None,
) -> tuple[MacroPairs, dict]:
    """Pad a host selection (:func:`_select_pairs`) into :class:`MacroPairs`."""
    gsel = sel["gsel"]
    rsel_i, rsel_j, rsel = sel["rsel"]
    nq, nd, extent = sel["nq"], sel["nd"], sel["extent"]
    n_m, n_g, n_r = g.n_macro, len(gsel[0]), len(rsel_i)
    if capacities is None:
        capacities = (max(8, _pair_capacity(n_m)), _pair_capacity(n_g), _pair_capacity(n_r))
    c_m, c_g, c_r = (int(c) for c in capacities)
    if c_m < n_m or c_g < n_g or c_r < n_r:
        raise ValueError(
            f"macro_pairs: capacities {capacities} are smaller than the counts "
            f"(macro triangles {n_m}, glossy pairs {n_g}, broad pairs {n_r})"
        )
    dt = jnp.result_type(float) if dtype is None else dtype
    tri = np.zeros((c_m, 3, 3))
    tri[:n_m] = g.tri
    tri[n_m:] = np.eye(3)  # a unit triangle of normal (1,1,1)/sqrt 3: finite padding
    nrm = np.zeros((c_m, 3))
    nrm[:n_m] = g.normals
    nrm[n_m:] = 1.0 / math.sqrt(3.0)
    part = np.zeros(c_m, np.int32)
    part[:n_m] = g.part

    def pad(v, cap, fill=0):
        out = np.full(cap, fill, dtype=np.asarray(v).dtype if len(v) else np.int32)
        out[: len(v)] = v
        return out

    # padding pairs (0, 1): two distinct surfaces, zero visibility (finite, zero weight)
    other = 1 if c_m > 1 else 0
    g_i = pad(np.asarray(gsel[0], np.int32), c_g, 0)
    g_j = pad(np.asarray(gsel[1], np.int32), c_g, other)
    g_kind = pad(np.asarray(gsel[2], np.int32), c_g, KIND_GB)
    g_vis = np.zeros(c_g)
    g_vis[:n_g] = gsel[3]
    r_i = pad(np.asarray(rsel_i, np.int32), c_r, 0)
    r_j = pad(np.asarray(rsel_j, np.int32), c_r, other)
    cq, cd = (nq, nd) if node_capacity is None else (int(c) for c in node_capacity)
    if cq < nq or cd < nd:
        raise ValueError(
            f"macro_pairs: node_capacity {node_capacity} is smaller than the broad pairs' "
            f"nodes ({nq} points, {nd} directions)"
        )
    r_x = np.zeros((c_r, cq, 3))
    r_k = np.zeros((c_r, cq, cd, 3))
    r_k[..., 2] = 1.0
    r_w = np.zeros((c_r, cq, cd))
    r_t = np.zeros((c_r, cq, cd))
    for n, (xx, kk, ww, tt) in enumerate(rsel):
        r_x[n, :nq], r_k[n, :nq, :nd], r_w[n, :nq, :nd], r_t[n, :nq, :nd] = xx, kk, ww, tt
    point_window = 0
    if bins is not None:
        from ._pulse import window_size  # noqa: PLC0415

        sig, wid, nb = float(bins[0]), float(bins[1]), int(bins[2])
        # glossy: the largest range extent of a kept overlap, to the next power of two
        if window is None:
            window = window_size(extent, sig, wid, nb)
            window = min(1 << (window - 1).bit_length(), nb)
        point_window = window_size(0.0, sig, wid, nb)
    window = 0 if window is None else int(window)
    pairs = MacroPairs(
        tri=jnp.asarray(tri, dt),
        normals=jnp.asarray(nrm, dt),
        part=jnp.asarray(part, jnp.int32),
        g_i=jnp.asarray(g_i, jnp.int32),
        g_j=jnp.asarray(g_j, jnp.int32),
        g_kind=jnp.asarray(g_kind, jnp.int32),
        g_vis=jnp.asarray(g_vis, dt),
        r_i=jnp.asarray(r_i, jnp.int32),
        r_j=jnp.asarray(r_j, jnp.int32),
        r_x=jnp.asarray(r_x, dt),
        r_k=jnp.asarray(r_k, dt),
        r_w=jnp.asarray(r_w, dt),
        r_t=jnp.asarray(r_t, dt),
        window=int(window),
        point_window=int(point_window),
        mixed=bool(np.any(g_kind[:n_g] != KIND_GG)) if mixed is None else bool(mixed),
        terms=tuple(terms),
    )
    return pairs, dict(sel["info"])


def stack_macro_pairs(pairs: list[MacroPairs]) -> MacroPairs:
    """Stack the pairs of several poses along a new leading axis (for ``vmap``): built with
    the same ``capacities`` and ``terms``; the static windows become the largest."""
    if not pairs:
        raise ValueError("stack_macro_pairs: no pairs given")
    shapes = {tuple(a.shape for a in jax.tree_util.tree_leaves(p)) for p in pairs}
    if len(shapes) != 1 or len({p.terms for p in pairs}) != 1:
        raise ValueError(
            "stack_macro_pairs: the pairs differ in shapes or terms; build them with the same "
            "capacities= and terms="
        )
    fields = {
        f.name: jnp.stack([getattr(p, f.name) for p in pairs])
        for f in dataclasses.fields(MacroPairs)
        if not f.metadata.get("static", False)
    }
    return MacroPairs(
        **fields,
        window=max(p.window for p in pairs),
        point_window=max(p.point_window for p in pairs),
        mixed=any(p.mixed for p in pairs),
        terms=pairs[0].terms,
    )


def glossy_parts(m_parts, brdf, glossy_m: float = GLOSSY_M_MIN) -> np.ndarray:
    """Host: ``(n_parts,)`` bool, parts whose lobe the image method treats: the model BRDF
    (:func:`ppr.mueller_brdf`; another BRDF's lobe is unknown, so all its pairs take the
    quadrature) and ``m >= glossy_m``."""
    from ..brdf._brdf import mueller_brdf, mueller_brdf_unchecked  # noqa: PLC0415

    m = np.atleast_1d(np.asarray(m_parts, np.float64))
    if brdf is not mueller_brdf and brdf is not mueller_brdf_unchecked:
        return np.zeros(m.shape, bool)
    return m >= glossy_m


def part_exponents(materials) -> np.ndarray:
    """Host: ``(n_parts,)`` Blinn-Phong exponents of per-part or stacked concrete materials."""
    if isinstance(materials, list | tuple):
        return np.asarray([float(np.asarray(mt.m)) for mt in materials])
    return np.atleast_1d(np.asarray(materials.m, np.float64))


@dataclasses.dataclass(frozen=True)
class MacroOptions:
    """Knobs of the macro double bounce (accuracy against cost: bench/bench_macro.py).

    - `plates`: merge coplanar faces into plates (:func:`macro_geometry`).
    - `level`, `rule`, `order`: broad pairs' quadrature (:func:`broad_nodes`).
    - `samples`: visibility samples per fan triangle of a glossy pair's overlap (a perfect
      square).
    - `glossy_m`: parts with ``m >= glossy_m`` take the image method (at least
      :data:`GLOSSY_M_MIN`: below it the Laplace approximation of the lobes fails: on a 1 m
      aluminium dihedral 10 deg off its bisector the image method gives +16 % at m = 10 and
      +98 % at m = 1 against the broad quadrature, which converges there; a larger value sends
      more parts through the quadrature).
    - `terms`: BRDF terms of the macro-bounce evaluations.
    """

    plates: bool = True
    level: int = 1
    rule: int = 6
    order: int = 4
    samples: int = 16
    glossy_m: float = GLOSSY_M_MIN
    terms: tuple = DEFAULT_TERMS

    def __post_init__(self):
        for name in ("level", "rule", "order", "samples"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1:
                raise ValueError(f"MacroOptions.{name} must be an integer >= 1, got {v!r}")
        if math.isqrt(self.samples) ** 2 != self.samples:
            raise ValueError(
                "MacroOptions.samples must be a perfect square (1, 4, 9, 16, ...: a k-fold "
                f"subdivision of each fan triangle), got {self.samples!r}"
            )
        g = self.glossy_m
        if isinstance(g, bool) or not isinstance(g, numbers.Real) or not g >= GLOSSY_M_MIN:
            raise ValueError(
                f"MacroOptions.glossy_m must be a number >= {GLOSSY_M_MIN:g} (the image method "
                f"is measured from m = {GLOSSY_M_MIN:g} up; below it the lobes' Laplace "
                f"approximation fails), got {g!r}"
            )

    def pair_options(self) -> dict:
        return dict(
            level=self.level,
            rule=self.rule,
            order=self.order,
            samples=self.samples,
            terms=tuple(self.terms),
        )


def pose_pairs(
    mesh: Mesh,
    caster: VisibilityCaster,
    laser_dir_body,
    receiver_dir_body,
    m_parts,
    brdf,
    options: MacroOptions | None = None,
    **kwargs,
) -> tuple[MacroPairs, dict]:
    """Host: :func:`macro_pairs` of ``mesh`` at one pose from the parts' exponents and the
    BRDF (glossy parts by :func:`glossy_parts`), and its summary
    (``info["convex"]``: the mesh has no facing surfaces at all)."""
    opt = MacroOptions() if options is None else options
    geom = macro_geometry(mesh, plates=opt.plates)
    mp = np.broadcast_to(np.asarray(m_parts, np.float64), (len(mesh.parts),))
    pairs, info = macro_pairs(
        geom,
        caster,
        laser_dir_body,
        receiver_dir_body,
        glossy_parts(mp, brdf, opt.glossy_m),
        mp,
        **{**opt.pair_options(), **kwargs},
    )
    info["convex"] = geom.convex
    return pairs, info


def batch_pairs(
    meshes,
    casters,
    shape_ids,
    laser_dirs_body,
    receiver_dirs_body,
    m_parts,
    brdf,
    options: MacroOptions | None = None,
    *,
    capacities: tuple[int, int, int] = (8, 0, 0),
    **kwargs,
) -> MacroPairs:
    """Host: the :class:`MacroPairs` of a batch of rows (``shape_ids`` into ``meshes`` and
    ``casters``, body-frame directions and per-part exponents per row), padded to common
    capacities (at least ``capacities``, so that a fixed value gives every batch the same
    shapes unless a row needs more) and stacked for ``vmap``."""
    opt = MacroOptions() if options is None else options
    unknown = set(kwargs) - {"bins", "dtype", "node_capacity", "mixed", "window"}
    if unknown:
        raise TypeError(f"batch_pairs: unexpected keyword arguments {sorted(unknown)}")
    sels, geoms = [], []
    for sid, ui, uo, mp in zip(
        shape_ids, laser_dirs_body, receiver_dirs_body, m_parts, strict=True
    ):
        mesh = meshes[int(sid)]
        geom = macro_geometry(mesh, plates=opt.plates)
        mpv = np.broadcast_to(np.asarray(mp, np.float64), (len(mesh.parts),))
        sels.append(
            _select_pairs(
                geom,
                casters[int(sid)],
                ui,
                uo,
                glossy_parts(mpv, brdf, opt.glossy_m),
                mpv,
                level=opt.level,
                rule=opt.rule,
                order=opt.order,
                samples=opt.samples,
            )
        )
        geoms.append(geom)
    need = (
        max(g.n_macro for g in geoms),
        max(len(s_["gsel"][0]) for s_ in sels),
        max(len(s_["rsel"][0]) for s_ in sels),
    )
    caps = tuple(max(int(c), _pair_capacity(n)) for c, n in zip(capacities, need, strict=True))
    window = kwargs.get("window")
    if window is None and kwargs.get("bins") is not None:
        from ._pulse import window_size  # noqa: PLC0415

        sig, wid, nb = kwargs["bins"]
        ext = max(s_["extent"] for s_ in sels)
        window = min(1 << (window_size(ext, sig, wid, int(nb)) - 1).bit_length(), int(nb))
    pack = {k: v for k, v in kwargs.items() if k in ("bins", "dtype", "node_capacity", "mixed")}
    rows = [
        _pack(g, s_, capacities=caps, window=window, terms=tuple(opt.terms), **pack)[0]
        for g, s_ in zip(geoms, sels, strict=True)
    ]
    return stack_macro_pairs(rows)


def gnomonic_grid(center, span: float, n: int):
    """Host: ``(k (n^2, 3), weights (n^2,))``: unit directions on an ``n x n`` grid of the
    plane tangent to the unit ``center`` (coordinates in ``[-span, span]``), with the
    trapezoid weights of the solid angle (``d omega = dA / r^3``)."""
    e1 = np.cross(center, [1.0, 0, 0] if abs(center[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(center, e1)
    x = np.linspace(-span, span, int(n))
    gx, gy = np.meshgrid(x, x, indexing="ij")
    v = center + gx[..., None] * e1 + gy[..., None] * e2
    r = np.linalg.norm(v, axis=-1).reshape(-1)
    return v.reshape(-1, 3) / r[:, None], (x[1] - x[0]) ** 2 / r**3


def two_bounce_lobe(n_i, n_j, u_in, u_out, material, frame_in, frame_out, *, span=7.0, n=121):
    """Host reference (float64, brute force): the two-bounce lobe
    ``int M_J(-k -> u_out) M_I(u_in -> k) (n_I.k)(n_J.u_out) d omega_k`` of the single-bounce
    BRDF over a gnomonic grid of ``+-span`` lobe widths ``2/sqrt(m)`` about ``I``'s specular
    direction (directions below either surface dropped): what the Laplace convolution of the
    glossy pairs approximates, by another method (tests/test_macro.py, bench/bench_macro.py)."""
    from ..brdf._brdf import mueller_brdf  # noqa: PLC0415
    from ..optics._frames import perpendicular_unit  # noqa: PLC0415

    n_i, n_j, u_in, u_out = (np.asarray(v, np.float64) for v in (n_i, n_j, u_in, u_out))
    ks = 2 * (u_in @ n_i) * n_i - u_in
    k, w = gnomonic_grid(ks, span * 2.0 / math.sqrt(float(material.m)), n)
    ok = (k @ n_i > 1e-6) & (k @ n_j < -1e-6)
    k = np.where(ok[:, None], k, ks)
    xk = np.asarray(perpendicular_unit(jnp.asarray(k)))
    one = ("single",)
    b = np.broadcast_to
    m1 = np.asarray(
        mueller_brdf(
            b(u_in, k.shape),
            k,
            b(n_i, k.shape),
            material,
            terms=one,
            frame_in=b(frame_in, k.shape),
            frame_out=xk,
        )
    )
    m2 = np.asarray(
        mueller_brdf(
            -k,
            b(u_out, k.shape),
            b(n_j, k.shape),
            material,
            terms=one,
            frame_in=xk,
            frame_out=b(frame_out, k.shape),
        )
    )
    return np.einsum("pij,pjk,p->ik", m2, m1, np.where(ok, (k @ n_i) * (u_out @ n_j) * w, 0.0))


# ----------------------------------------------------------------------------- kernel


def _visibility_gaussian(m, c):
    """Ashikhmin's ``P(k) = <h.n> c / <h.k>+`` with ``<h.k>+`` of a near-Gaussian lobe:
    ``h.k ~ mu + s Z``, ``mu = c <h.n>``, ``s^2 = (1 - c^2)/(m + 3)`` (the variance of a facet
    normal's component along ``k``'s azimuth), so ``<h.k>+ = mu Phi(mu/s) + s phi(mu/s)``. For
    the glossy lobes of the image method (``m >= GLOSSY_M_MIN``) it differs from the
    quadrature of :func:`ppr.microfacet.visibility` at ``O(1/m)`` near grazing only, and it
    compiles to a few operations."""
    dt = c.dtype
    mu = c * (m + 1.0) / (m + 2.0)
    s2 = jnp.maximum(1.0 - c * c, 0.0) / (m + 3.0)
    ok = s2 > 1e-30
    s = jnp.sqrt(jnp.where(ok, s2, 1.0))
    z = mu / s
    den = mu * 0.5 * jax.lax.erfc(-z * (1.0 / math.sqrt(2.0))) + s * jnp.exp(
        -0.5 * z * z
    ) / math.sqrt(2.0 * math.pi)
    den_ok = ok & (den > 1e-30)
    p = mu / jnp.where(den_ok, den, 1.0)
    return jnp.clip(jnp.where(den_ok, p, jnp.where(ok, 0.0, 1.0)), 0.0, 1.0).astype(dt)


def _specular_factor(k_in, k_out, normal, m, n_re, n_im, x_in, x_out, white, films=None):
    """``F_M(k_in -> k_out) P(k|k') / (4 (k.n)(k'.n))`` as ``(16, P)``: the single-bounce term
    without its lobe ``D(h)`` (as :func:`ppr.brdf._brdf._single_scalar3`, shadowing from
    :func:`_visibility_gaussian`)."""
    from .._safe import tiny  # noqa: PLC0415
    from ..brdf._brdf import _azimuth_factor3, _geometry3, _split  # noqa: PLC0415
    from ..optics._frames import facet_rotated_params, rotated_mueller_flat  # noqa: PLC0415

    ki, ko, nr = _split(k_in), _split(k_out), _split(normal)
    dt = k_in.dtype
    valid, ki_s, ko_s, ci, co, h = _geometry3(ki, ko, nr)
    vi = _visibility_gaussian(m, ci) / ci
    vo = _visibility_gaussian(m, co) / co
    f = _azimuth_factor3(ki_s, ko_s, nr, ci, co)
    t = tiny(dt)
    lci, lco = jnp.log(ci), jnp.log(co)
    log_min = jnp.minimum(jnp.log(jnp.maximum(vi, t)) - lco, jnp.log(jnp.maximum(vo, t)) - lci)
    g = (1.0 - f) * vi * vo + f * jnp.exp(log_min)
    scal = jnp.where(valid, 0.25 * g, 0.0)
    params = facet_rotated_params(
        n_re, n_im, ki_s, ko_s, h, _split(x_in), _split(x_out), white=white, films=films
    )
    return rotated_mueller_flat(params, scal)


def _to44(flat):
    return jnp.moveaxis(flat, 0, -1).reshape(flat.shape[1:] + (4, 4))


def macro_profile(
    pairs: MacroPairs,
    rot,
    position,
    materials,
    sensor,
    sigma,
    start,
    width,
    *,
    n_bins: int,
    projection,
    brdf,
):
    """Traceable: the macro double bounce ``(C, n_bins)`` (m^2/sr per bin) at the body-to-world
    rotation ``rot`` (module docstring). ``materials``: stacked per part (as
    :func:`ppr.render`); ``brdf``: the render's BRDF (broad sides). Two ``brdf`` calls: the
    broad sides of the glossy pairs, and both bounces of the broad point pairs under a
    ``lax.cond`` on any live point (padded broad slots cost nothing at run time outside
    ``vmap``, so a model can pad them to a fixed capacity and compile once)."""
    from ._pulse import _tent_profile  # noqa: PLC0415

    dt = pairs.tri.dtype
    rt = rot.T
    u_in = rt @ sensor.laser_dir.astype(dt)
    u_out = rt @ sensor.receiver_dir.astype(dt)
    x_tx = rt @ sensor.frame_tx.astype(dt)
    x_rx = rt @ sensor.frame_rx.astype(dt)
    w_body = 0.5 * (u_in + u_out)
    shift = jnp.dot(position.astype(dt), rot @ w_body)
    white = materials.white
    one = jnp.shape(materials.m)[:1] == (1,)  # one material shared by every part

    def mat(parts, shape=None):
        ids = jnp.zeros_like(parts) if one else parts
        if shape is None:
            return jax.tree_util.tree_map(lambda a: a[ids], materials)
        return jax.tree_util.tree_map(
            lambda a: jnp.broadcast_to(a[ids].reshape(ids.shape + (1,) * (len(shape) - 1)), shape),
            materials,
        )

    # BRDF requests (k_in, k_out, normal, material, frame_in, frame_out), flat batches
    requests = []
    n_g = pairs.g_i.shape[0]
    n_r = pairs.r_i.shape[0]
    pieces = []
    if n_g:
        ti, tj = pairs.tri[pairs.g_i], pairs.tri[pairs.g_j]
        ni, nj = pairs.normals[pairs.g_i], pairs.normals[pairs.g_j]
        mi, mj = mat(pairs.part[pairs.g_i]), mat(pairs.part[pairs.g_j])
        kind = pairs.g_kind
        ub_in = jnp.broadcast_to(u_in, (n_g, 3))
        ub_out = jnp.broadcast_to(u_out, (n_g, 3))
        kstar, lam, _, (c1, c2) = specular_solution(
            jnp, ni, nj, ub_in, ub_out, mi.m.astype(dt), mj.m.astype(dt), kind
        )
        live_g = (
            (pairs.g_vis > 0)
            & (jnp.sum(ni * kstar, -1) > COS_MIN)
            & (jnp.sum(nj * kstar, -1) < -COS_MIN)
        )
        # double where: dead pairs get a harmless direction (normal of I) and zero weight
        kstar = jnp.where(live_g[:, None], kstar, ni)
        nj_g = jnp.where(live_g[:, None], nj, -ni)
        # the slowly varying factors averaged over the lobe product at its sigma points
        n_s = len(SIGMA_WEIGHTS)
        z = jnp.asarray(SIGMA_POINTS, dt)
        ks = kstar[:, None] + z[None, :, :1] * c1[:, None] + z[None, :, 1:] * c2[:, None]
        ks = _unit(jnp, ks, kstar[:, None]).reshape(-1, 3)  # (P S, 3)

        def rep(a):
            return jnp.repeat(a, n_s, axis=0)

        ni_s, nj_s = rep(ni), rep(nj_g)
        live_s = rep(live_g) & (jnp.sum(ni_s * ks, -1) > COS_MIN)
        live_s &= jnp.sum(nj_s * ks, -1) < -COS_MIN
        ks = jnp.where(live_s[:, None], ks, ni_s)
        nj_s = jnp.where(live_s[:, None], nj_s, -ni_s)
        xk_g = _perp(jnp, ks)
        n_gs = n_g * n_s
        fr_tx = jnp.broadcast_to(x_tx, (n_gs, 3))
        fr_rx = jnp.broadcast_to(x_rx, (n_gs, 3))
        ub_in_s = jnp.broadcast_to(u_in, (n_gs, 3))
        ub_out_s = jnp.broadcast_to(u_out, (n_gs, 3))
        cat = lambda a, b: jnp.concatenate([a, b])  # noqa: E731
        mij = jax.tree_util.tree_map(lambda a, b: cat(rep(a), rep(b)), mi, mj)
        g_args = (cat(ub_in_s, -ks), cat(ks, ub_out_s), cat(ni_s, nj_s), mij)
        g_frames = (cat(fr_tx, xk_g), cat(xk_g, fr_rx))
        from ..optics._films import films_of  # noqa: PLC0415

        spec = _to44(
            _specular_factor(
                *g_args[:3],
                mij.m.astype(dt),
                jnp.real(mij.n).astype(dt),
                jnp.imag(mij.n).astype(dt),
                *g_frames,
                white,
                films_of(mij, dt),
            )
        )
        if pairs.mixed:
            requests.append((*g_args, *g_frames))
    full = None
    if requests:
        cat_all = lambda *xs: jnp.concatenate(xs)  # noqa: E731
        ki_, ko_, nr_, mt_, fi_, fo_ = (
            jax.tree_util.tree_map(cat_all, *[rq[c] for rq in requests]) for c in range(6)
        )
        full = brdf(
            ki_,
            ko_,
            nr_,
            mt_,
            frame_in=fi_,
            frame_out=fo_,
            wavelength=sensor.wavelength,
            terms=pairs.terms,
        )
    if n_g:
        first, second = spec[:n_gs], spec[n_gs:]
        if pairs.mixed:
            fg = full[: 2 * n_gs]
            kind_s = jnp.repeat(kind, n_s)
            first = jnp.where((kind_s == KIND_BG)[:, None, None], fg[:n_gs], first)
            second = jnp.where((kind_s == KIND_GB)[:, None, None], fg[n_gs:], second)
        wsig = jnp.tile(jnp.asarray(SIGMA_WEIGHTS, dt), n_g)
        wsig = jnp.where(live_s, wsig * jnp.sum(ni_s * ks, -1), 0.0)
        chain = ((second @ first).reshape(n_g, n_s, 16) * wsig.reshape(n_g, n_s, 1)).sum(1)
        wgt = jnp.where(live_g, (ni @ u_in) * (nj_g @ u_out) * lam * pairs.g_vis, 0.0)
        m44 = chain * wgt[:, None]
        w = m44 if projection is None else m44 @ projection.astype(dt)
        fans, ar, t = overlap_fans(jnp, ti, ni, tj, nj_g, kstar)
        # range of a point x of I: one-way path laser -> x -> x + t k* -> receiver
        depth = (
            0.5
            * (
                -jnp.einsum("pfvk,k->pfv", fans, u_in + u_out)
                + t * (1.0 - kstar @ u_out)[:, None, None]
            )
            - shift
        )
        wf = (w[:, None, :] * ar[..., None]).reshape(n_g * _FAN, -1)
        pieces.append((wf, depth.reshape(n_g * _FAN, 3), pairs.window))
    out = None
    for w, depth, window in pieces:
        prof = _tent_profile(w, depth, sigma, start, width, n_bins=n_bins, window=window)
        out = prof if out is None else out + prof
    if n_r:
        # the broad point pairs in their own BRDF call, skipped at run time when no point is
        # live: a model pads its broad slots to a fixed capacity (one compiled program for
        # every pose and roughness), and dead slots then cost nothing outside vmap
        geo = dict(u_in=u_in, u_out=u_out, x_tx=x_tx, x_rx=x_rx, shift=shift, mat=mat)
        bins = dict(sensor=sensor, sigma=sigma, start=start, width=width, n_bins=n_bins)
        live_r, prof_r = _broad_pairs_profile(pairs, geo, bins, projection, brdf, dt)
        c = 16 if projection is None else projection.shape[1]
        prof = jax.lax.cond(jnp.any(live_r), prof_r, lambda: jnp.zeros((c, n_bins), dt))
        out = prof if out is None else out + prof
    if out is None:
        c = 16 if projection is None else projection.shape[1]
        out = jnp.zeros((c, n_bins), dt)
    return out


def _broad_pairs_profile(pairs, geo: dict, bins: dict, projection, brdf, dt):
    """The broad point pairs of :func:`macro_profile`: ``(live (R Q Q',), profile())``, the
    profile a thunk (its BRDF call is only traced where the caller's ``cond`` takes it)."""
    from ._pulse import _tent_profile  # noqa: PLC0415

    u_in, u_out, x_tx, x_rx, shift, mat = (
        geo[k] for k in ("u_in", "u_out", "x_tx", "x_rx", "shift", "mat")
    )
    sensor, n_bins = bins["sensor"], bins["n_bins"]
    n_r = pairs.r_i.shape[0]
    rni, rnj = pairs.normals[pairs.r_i], pairs.normals[pairs.r_j]
    nq, nd = pairs.r_k.shape[1], pairs.r_k.shape[2]
    shape = (n_r, nq, nd)
    k0 = pairs.r_k.reshape(-1, 3)  # (R Q Q', 3)
    nib = jnp.broadcast_to(rni[:, None, None, :], shape + (3,)).reshape(-1, 3)
    njb = jnp.broadcast_to(rnj[:, None, None, :], shape + (3,)).reshape(-1, 3)
    live_r = (pairs.r_w.reshape(-1) > 0) & (jnp.sum(nib * k0, -1) > COS_MIN)
    live_r &= jnp.sum(njb * k0, -1) < -COS_MIN

    def profile():
        k = jnp.where(live_r[:, None], k0, nib)
        nj_r = jnp.where(live_r[:, None], njb, -nib)
        xk_r = _perp(jnp, k)
        cat = lambda a, b: jnp.concatenate([a, b])  # noqa: E731
        n_pts = k.shape[0]
        mir = mat(pairs.part[pairs.r_i], shape)
        mjr = mat(pairs.part[pairs.r_j], shape)
        m_r = jax.tree_util.tree_map(lambda a, b: cat(a.reshape(-1), b.reshape(-1)), mir, mjr)
        fr = brdf(
            cat(jnp.broadcast_to(u_in, (n_pts, 3)), -k),
            cat(k, jnp.broadcast_to(u_out, (n_pts, 3))),
            cat(nib, nj_r),
            m_r,
            frame_in=cat(jnp.broadcast_to(x_tx, (n_pts, 3)), xk_r),
            frame_out=cat(xk_r, jnp.broadcast_to(x_rx, (n_pts, 3))),
            wavelength=sensor.wavelength,
            terms=pairs.terms,
        )
        m1, m2 = fr[:n_pts], fr[n_pts:]
        g = (rni @ u_in)[:, None, None] * pairs.r_w
        g = jnp.where(live_r, g.reshape(-1) * jnp.sum(nib * k, -1) * (nj_r @ u_out), 0.0)
        m44 = (m2 @ m1).reshape(-1, 16) * g[:, None]
        w = m44 if projection is None else m44 @ projection.astype(dt)
        # one-way path laser -> x -> x + t k -> receiver
        y = pairs.r_x[:, :, None, :] + pairs.r_t[..., None] * pairs.r_k
        depth = 0.5 * (-(pairs.r_x @ u_in)[:, :, None] + pairs.r_t - (y @ u_out)) - shift
        depth = jnp.broadcast_to(depth.reshape(-1)[:, None], (n_pts, 3))
        # in the kernel's dtype, as the skip branch (a complex128 index under x64 would
        # otherwise promote a float32 model's profile)
        return _tent_profile(
            w,
            depth,
            bins["sigma"],
            bins["start"],
            bins["width"],
            n_bins=n_bins,
            window=pairs.point_window,
        ).astype(dt)

    return live_r, profile
