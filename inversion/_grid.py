r"""Deterministic attitude grids on SO(3), their measured resolution and symmetry reduction.

Quaternions are ``(w, x, y, z)`` (scalar first), unit, and ``q`` and ``-q`` are the same
rotation. The distance between two rotations is the geodesic angle
``d(p, q) = 2 arccos |<p, q>|`` (the rotation angle of ``p^-1 q``), in ``[0, pi]``.

Grids
    ``hopf_grid(nside)``: the Hopf-fibration grid of Yershova, Jain, LaValle and Mitchell,
    "Generating uniform incremental grids on SO(3) using the Hopf fibration", IJRR 29 (2010):
    HEALPix pixel centres (``12 nside^2``, ring scheme, Gorski et al. 2005) on the base S^2
    times ``6 nside`` equally spaced points on the S^1 fibre, mapped by

        q = (cos(t/2) cos(p/2), cos(t/2) sin(p/2), sin(t/2) cos(f + p/2), sin(t/2) sin(f + p/2))

    for HEALPix angles ``(t, f)`` and fibre angle ``p``; ``72 nside^3`` rotations (Yershova's
    level ``l`` is ``nside = 2^l``). ``fibonacci_grid(n)``: the super-Fibonacci spiral (Alexa,
    CVPR 2022), a low-discrepancy set of any size.

Resolution
    The *covering radius* ``rho = max_r min_g d(r, g)`` is the stated angular resolution: every
    attitude lies within ``rho`` of a grid point. ``covering_radius`` measures it by Monte Carlo
    (a lower bound that converges from below); ``stated_resolution_deg`` is the calibrated law
    ``rho = C N^(-1/3)`` (N rotations; the Haar volume of a ball of radius ``r`` is
    ``(r - sin r)/pi ~ r^3/(6 pi)``, so ``N^(-1/3)`` scaling is forced), checked against the
    measurement in the tests. Hopf: about 55 deg at 72 rotations, 13.5 deg at 4608, 6.6 deg
    at 36864.

Symmetry
    If a shape maps onto itself under body rotations ``G`` (``q`` and ``q g`` give the same
    signature), grid points ``p`` with ``f(p) = d(p, 1) - min_g d(p, g) <= 2 rho`` are kept.
    ``f`` is 2-Lipschitz and vanishes on the fundamental domain ``D`` (the Voronoi cell of the
    identity among ``G``), so the kept points still cover ``D`` within ``rho`` and therefore all
    of SO(3) modulo ``G``; about ``N / |G|`` points plus a boundary band remain.

    ``G`` is a named class (:func:`symmetry_group`: ``dihedral:n``, ``octahedral``, ...) or the
    group of a mesh computed from the mesh itself (:func:`ppr.mesh_symmetries`, through
    :func:`as_symmetry`): its proper rotations reduce the grid, its improper elements give the
    mirror images (:func:`inversion.candidate_modes`).
"""

from __future__ import annotations

import functools
import hashlib
import math
from collections import OrderedDict

import jax
import jax.numpy as jnp
import numpy as np

import ppr
from ppr.geometry import (
    quat_angle_deg,
    quat_from_axis_angle,
    quat_multiply_host,
    quat_to_matrix_host,
)

# Stated covering radius rho = C * N^(-1/3) radians for a full grid of N rotations. Measured with
# ``covering_radius`` (2e5 Monte Carlo samples): Hopf nside 1..8 gives C = 3.77..4.02, the
# super-Fibonacci spiral N = 72..36864 gives C = 3.81..4.17; the stated constants sit 5% above
# the largest measurement because Monte Carlo approaches the maximum from below.
C_HOPF = 4.2
C_FIBONACCI = 4.3


def _healpix_centres(nside: int) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi) of the ``12 nside^2`` HEALPix ring-scheme pixel centres (Gorski 2005)."""
    npix = 12 * nside * nside
    ncap = 2 * nside * (nside - 1)
    p = np.arange(npix, dtype=np.int64)
    z = np.empty(npix)
    phi = np.empty(npix)
    north = p < ncap
    south = p >= npix - ncap
    eq = ~north & ~south
    # north polar cap
    pn = p[north]
    i = np.floor((1 + np.sqrt(1 + 2 * pn)) / 2).astype(np.int64)
    i = np.where(2 * i * (i - 1) > pn, i - 1, i)  # guard rounding
    j = pn - 2 * i * (i - 1) + 1
    z[north] = 1 - i**2 / (3.0 * nside**2)
    phi[north] = np.pi / (2 * i) * (j - 0.5)
    # equatorial belt
    pe = p[eq] - ncap
    i = pe // (4 * nside) + nside
    j = pe % (4 * nside) + 1
    s = ((i - nside + 1) % 2).astype(float)
    z[eq] = 4.0 / 3.0 - 2.0 * i / (3.0 * nside)
    phi[eq] = np.pi / (2 * nside) * (j - s / 2)
    # south polar cap (mirror of north)
    ps = npix - p[south]
    i = np.floor((1 + np.sqrt(2 * ps - 1)) / 2).astype(np.int64)
    j = 4 * i + 1 - (ps - 2 * i * (i - 1))
    z[south] = -1 + i**2 / (3.0 * nside**2)
    phi[south] = np.pi / (2 * i) * (j - 0.5)
    return np.arccos(np.clip(z, -1, 1)), phi


def hopf_grid(nside: int, n_psi: int | None = None) -> np.ndarray:
    """Hopf-fibration grid: ``(12 nside^2 * n_psi, 4)`` unit quaternions, ``n_psi = 6 nside``."""
    if not isinstance(nside, int | np.integer) or nside < 1:
        raise ValueError(f"nside must be a positive integer, got {nside!r}")
    n_psi = 6 * int(nside) if n_psi is None else int(n_psi)
    if n_psi < 1:
        raise ValueError(f"n_psi must be >= 1, got {n_psi}")
    theta, phi = _healpix_centres(int(nside))
    psi = (np.arange(n_psi) + 0.5) * (2 * np.pi / n_psi)
    t = theta[:, None] / 2
    f = phi[:, None]
    p = psi[None, :] / 2
    q = np.stack(
        np.broadcast_arrays(
            np.cos(t) * np.cos(p),
            np.cos(t) * np.sin(p),
            np.sin(t) * np.cos(f + p),
            np.sin(t) * np.sin(f + p),
        ),
        axis=-1,
    ).reshape(-1, 4)
    return canonical_sign(q)


def fibonacci_grid(n: int) -> np.ndarray:
    """Super-Fibonacci spiral (Alexa 2022): ``n`` low-discrepancy unit quaternions."""
    if not isinstance(n, int | np.integer) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    phi = math.sqrt(2.0)
    psi = 1.533751168755204288118041
    s = np.arange(n) + 0.5
    t = s / n
    r, R = np.sqrt(t), np.sqrt(1 - t)
    a, b = 2 * np.pi * s / phi, 2 * np.pi * s / psi
    q = np.stack([r * np.sin(a), r * np.cos(a), R * np.sin(b), R * np.cos(b)], axis=-1)
    return canonical_sign(q)


def fibonacci_sphere(n: int) -> np.ndarray:
    """``(n, 3)`` unit vectors evenly spread over the sphere (the Fibonacci lattice)."""
    if not isinstance(n, int | np.integer) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5.0**0.5) * i
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def canonical_sign(q: np.ndarray) -> np.ndarray:
    """Flip ``q -> -q`` so that the first non-negligible component is positive."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    idx = np.argmax(np.abs(q) > 1e-12, axis=-1)
    sign = np.sign(np.take_along_axis(q, idx[..., None], axis=-1))
    return q * sign


def random_quaternions(key, n: int, dtype=jnp.float64) -> jax.Array:
    """``n`` Haar-uniform unit quaternions (normalized Gaussian 4-vectors)."""
    q = jax.random.normal(key, (n, 4), dtype)
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def body_mirror_normal(symmetry) -> np.ndarray | None:
    """Unit normal of a mirror plane the shape has, or ``None`` if it has none.

    The named classes of :func:`symmetry_group` are those of ``ppr.shapes``: ``dihedral:n``
    stands for an n-sided prism or a square box (point group D_nh) and ``octahedral`` for
    the cube (O_h); both have the mirror ``z -> -z`` (normal ``(0, 0, 1)``). ``cyclic:n`` and
    ``none`` imply no mirror. A :class:`ppr.MeshSymmetry` or :class:`ppr.Mesh` gives the
    normal of its first mirror plane (:meth:`ppr.MeshSymmetry.mirror_normals`). A body's
    mirror symmetry gives the measurement a second, improper ambiguity besides its
    rotations: see :func:`mirror_attitude`.
    """
    if not isinstance(symmetry, str):
        normals = as_symmetry(symmetry).mirror_normals()
        return normals[0] if len(normals) else None
    symmetry_group(symmetry)  # validates the name
    if symmetry.split(":")[0] in ("dihedral", "octahedral"):
        return np.array([0.0, 0.0, 1.0])
    return None


_MESH_GROUPS: OrderedDict = OrderedDict()


@functools.lru_cache(maxsize=64)
def _named_symmetry(name: str) -> ppr.MeshSymmetry:
    rot = quat_to_matrix_host(symmetry_group(name))
    mats = [rot]
    if body_mirror_normal(name) is not None:
        mats.append(np.einsum("ij,gjk->gik", np.diag([1.0, 1.0, -1.0]), rot))
    return ppr.MeshSymmetry.from_matrices(np.concatenate(mats))


def _mesh_digest(mesh, tol: float) -> str:
    h = hashlib.blake2b(digest_size=16)
    for a in (mesh.vertices, mesh.faces, mesh.material_ids):
        a = np.ascontiguousarray(np.asarray(a))
        h.update(str((a.dtype, a.shape)).encode())
        h.update(a.tobytes())
    h.update(repr((mesh.parts, float(tol))).encode())
    return h.hexdigest()


def as_symmetry(symmetry, *, tol: float = 1e-6) -> ppr.MeshSymmetry:
    """A shape's symmetry as a :class:`ppr.MeshSymmetry` (proper and improper elements).

    ``symmetry``: a named class of :func:`symmetry_group` (``"dihedral:4"``: its rotations,
    and for ``dihedral:n`` and ``octahedral`` the same rotations times the mirror
    ``z -> -z``, i.e. D_nh and O_h about the body origin); a :class:`ppr.MeshSymmetry`
    (returned as is); a :class:`ppr.Mesh` (:func:`ppr.mesh_symmetries` at ``tol``, cached per
    mesh content and tolerance); or a ``(G, 4)`` array of quaternions (rotations only).
    """
    if isinstance(symmetry, ppr.MeshSymmetry):
        return symmetry
    if isinstance(symmetry, ppr.Mesh):
        key = _mesh_digest(symmetry, tol)
        if key not in _MESH_GROUPS:
            _MESH_GROUPS[key] = ppr.mesh_symmetries(symmetry, tol=tol)
            while len(_MESH_GROUPS) > 32:
                _MESH_GROUPS.popitem(last=False)
        _MESH_GROUPS.move_to_end(key)
        return _MESH_GROUPS[key]
    if isinstance(symmetry, str):
        return _named_symmetry(symmetry)
    q = np.asarray(symmetry, np.float64)
    if q.ndim != 2 or q.shape[1] != 4 or len(q) == 0:
        raise ValueError(
            "symmetry must be a class name, a ppr.MeshSymmetry, a ppr.Mesh or (G, 4) "
            f"quaternions, got {type(symmetry).__name__} of shape {q.shape}"
        )
    return ppr.MeshSymmetry.from_matrices(quat_to_matrix_host(q))


def mesh_has_mirror(mesh, normal, rtol: float = 1e-9) -> bool:
    """Whether the plane through the body origin with unit ``normal`` is a mirror plane of a
    mesh, within ``rtol`` of the mesh's size. A check to run before trusting
    :func:`mirror_attitude` for a mesh.

    ``mesh``: a ``ppr.Mesh``, compared as a surface (the triangulation need not be
    symmetric): faces are grouped by part, outward normal and plane offset, and every group's
    area and first and second area moments must equal those of the reflected group, so a
    panel with different materials on its two sides is not mirror-symmetric through its own
    plane. Or ``(V, 3)`` vertices: the vertex set alone.
    """
    from scipy.spatial import cKDTree

    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    has_faces = hasattr(mesh, "faces") and hasattr(mesh, "vertices")
    v = np.asarray(mesh.vertices if has_faces else mesh, np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"mesh_has_mirror: vertices must be (V, 3), got {v.shape}")
    size = max(float(np.ptp(v, axis=0).max()), 1e-300)
    refl = np.eye(3) - 2.0 * np.outer(n, n)
    if not has_faces:
        dist, _ = cKDTree(v).query(v @ refl)
        return bool(np.max(dist) <= rtol * size)
    return _surface_moments(v, mesh, refl, rtol, size)


def _surface_moments(v, mesh, refl, rtol, size) -> bool:
    """Compare the (part, normal, plane)-grouped area moments of a mesh and its reflection."""
    tri = v[np.asarray(mesh.faces)]
    parts = np.asarray(mesh.material_ids)

    def groups(t):
        cr = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        area = 0.5 * np.linalg.norm(cr, axis=-1)
        nrm = cr / np.maximum(2.0 * area, 1e-300)[:, None]
        offset = np.einsum("fi,fi->f", nrm, t[:, 0]) / size
        ssum = t.sum(axis=1)
        # int x dA = A c; int x x^T dA = A/12 (sum_i v_i v_i^T + s s^T), s = v0 + v1 + v2
        m1 = area[:, None] * ssum / 3.0
        m2 = (area / 12.0)[:, None, None] * (
            np.einsum("fki,fkj->fij", t, t) + np.einsum("fi,fj->fij", ssum, ssum)
        )
        out = {}
        for f in range(len(t)):
            if area[f] <= 0:
                continue
            key = (int(parts[f]), *np.round(nrm[f], 6), round(float(offset[f]), 6))
            a, b, c = out.get(key, (0.0, 0.0, 0.0))
            out[key] = (a + area[f], b + m1[f], c + m2[f])
        return out

    mine = groups(tri)
    theirs = groups((tri @ refl)[:, ::-1])  # a reflection reverses the winding: flip it back
    if set(mine) != set(theirs):
        return False
    tol = rtol * 10
    for key, (a, m1, m2) in mine.items():
        a2, m1b, m2b = theirs[key]
        if (
            abs(a - a2) > tol * size**2
            or np.abs(m1 - m1b).max() > tol * size**3
            or np.abs(m2 - m2b).max() > tol * size**4
        ):
            return False
    return True


def mirror_attitude(q, body_normal=(0.0, 0.0, 1.0), world_normal=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Attitude of the mirror image of the scene: ``R' = P R sigma`` (batched over ``q``).

    ``sigma = I - 2 s s^T`` is a mirror symmetry of the body (normal ``s`` in body axes, e.g.
    :func:`body_mirror_normal`), ``P = I - 2 w w^T`` the world mirror through the plane that
    holds the line of sight and the sensor's x polarization reference (normal ``w``; world
    ``+y`` for the canonical sensor looking along ``-z`` with x reference ``+x``). ``R'`` is a
    proper rotation, and the scene at ``R'`` is the mirror image of the scene at ``R``: the
    same range profile of every facet, and Mueller profiles ``M' = D M D`` with
    ``D = diag(1, 1, -1, -1)`` (U and V change sign; ``tests/test_pulse.py`` checks this on
    the full forward model to 1e-12). Only the off-block elements ``M02, M03, M12, M13`` and
    their transposes tell ``R`` and ``R'`` apart, and they vanish when every return is a
    normal-incidence reflection (glossy targets), so the two attitudes are then exactly
    indistinguishable. In body axes the line of sight of ``R'`` is ``sigma v``.

    With ``P = -C2(w)`` and ``sigma = -C2(s)`` (``C2`` the half turn) ``R' = C2(w) R C2(s)``,
    i.e. the quaternion ``(0, w) q (0, s)``.
    """
    s = np.asarray(body_normal, np.float64)
    w = np.asarray(world_normal, np.float64)
    for name, v in (("body_normal", s), ("world_normal", w)):
        if v.shape != (3,) or not np.all(np.isfinite(v)) or abs(np.linalg.norm(v) - 1) > 1e-6:
            raise ValueError(f"mirror_attitude: {name} must be a unit 3-vector, got {v.tolist()}")
    q = np.asarray(q, np.float64)
    pure_w, pure_s = np.concatenate([[0.0], w]), np.concatenate([[0.0], s])
    out = quat_multiply_host(quat_multiply_host(pure_w, q), pure_s)
    return canonical_sign(out)


def los_half_turn(q, los=(0.0, 0.0, 1.0)) -> np.ndarray:
    """The attitude turned by 180 deg about the world line of sight: ``C2(los) (x) q``.

    An exact symmetry of every monostatic measurement, whatever the body: the turn keeps
    every depth along the line of sight, and it rotates the sensor's polarization frame by
    180 deg, which is the identity on Stokes vectors (the frame rotation of a Mueller matrix
    goes with twice the angle). So ``q`` and its half turn give identical data in every
    channel and bin (``tests/test_pulse.py``); only a bistatic receiver, off the line of
    sight, breaks it. Unlike the mirror image, the half turn keeps the line of sight in the
    body frame. ``los``: the world line of sight (``+z`` for the canonical sensor).
    """
    a = np.asarray(los, np.float64)
    if a.shape != (3,) or not np.isclose(np.linalg.norm(a), 1.0, atol=1e-9):
        raise ValueError(f"los_half_turn: los must be a unit 3-vector, got {a.tolist()}")
    q = np.asarray(q, np.float64)
    pure_a = np.broadcast_to(np.concatenate([[0.0], a]), q.shape)
    return canonical_sign(quat_multiply_host(pure_a, q))


# largest order n of a named class cyclic:n / dihedral:n (the group is built by closure,
# quadratic in its size: dihedral:360 takes about a minute)
MAX_NAMED_ORDER = 64


def symmetry_group(name) -> np.ndarray:
    """Rotation group of a shape as ``(|G|, 4)`` quaternions (identity first).

    ``"none"``; ``"cyclic:n"`` (n-fold about body z); ``"dihedral:n"`` (plus n two-fold axes in
    the xy plane: an n-sided prism, ``dihedral:4`` a square box like a 3U CubeSat,
    ``dihedral:2`` a general cuboid); ``"octahedral"`` (cube, 24 rotations). Or the proper
    rotations of a :class:`ppr.MeshSymmetry` or of a :class:`ppr.Mesh`'s own symmetry
    (:func:`as_symmetry`).
    """
    if isinstance(name, ppr.MeshSymmetry | ppr.Mesh):
        return canonical_sign(as_symmetry(name).quaternions())
    if not isinstance(name, str):
        raise ValueError(
            f"symmetry_group: expected a class name, ppr.MeshSymmetry or ppr.Mesh, got {name!r}"
        )
    if name == "none":
        gens = []
    elif name.startswith("cyclic:") or name.startswith("dihedral:"):
        kind, _, n = name.partition(":")
        try:
            n = int(n)
        except ValueError:
            raise ValueError(f"symmetry group {name!r}: order must be an integer") from None
        if n < 1:
            raise ValueError(f"symmetry group {name!r}: order must be >= 1")
        if n > MAX_NAMED_ORDER:
            raise ValueError(
                f"symmetry group {name!r}: order above {MAX_NAMED_ORDER}; a rounder shape's "
                "own group comes from its mesh (symmetry = 'auto')"
            )
        gens = [quat_from_axis_angle([0, 0, 1], 2 * math.pi / n)]
        if kind == "dihedral":
            gens.append(quat_from_axis_angle([1, 0, 0], math.pi))
    elif name == "octahedral":
        gens = [
            quat_from_axis_angle([1, 0, 0], math.pi / 2),
            quat_from_axis_angle([0, 0, 1], math.pi / 2),
        ]
    else:
        raise ValueError(
            f"unknown symmetry group {name!r}; use none, cyclic:n, dihedral:n or octahedral"
        )
    group = [np.array([1.0, 0, 0, 0])]
    frontier = list(group)
    while frontier:
        new = []
        for g in frontier:
            for h in gens:
                c = canonical_sign(quat_multiply_host(g, h))
                if min(quat_angle_deg(c, e) for e in group) > 1e-4:
                    group.append(c)
                    new.append(c)
        frontier = new
        if len(group) > 1000:
            raise ValueError(f"symmetry group {name!r} did not close")
    return np.stack(group)


def reduce_by_symmetry(quats: np.ndarray, group: np.ndarray, rho_deg: float) -> np.ndarray:
    """Indices of grid points kept after reduction by ``group`` (see module docstring)."""
    quats = np.asarray(quats)
    group = np.asarray(group)
    if len(group) == 1:
        return np.arange(len(quats))
    d = quat_angle_deg(quats[:, None, :], group[None, :, :])  # d(p, g)
    f = d[:, 0] - d.min(axis=1)
    keep = np.nonzero(f <= 2 * rho_deg + 1e-9)[0]
    # drop exact duplicates modulo G (grids can be invariant under some g): one per orbit
    orbit = canonical_sign(quat_multiply_host(quats[keep][:, None, :], group[None, :, :]))
    key = np.round(orbit, 8) + 0.0  # +0.0 folds -0.0
    reps = [max(map(tuple, row)) for row in key]  # lexicographic max: same for the whole orbit
    _, first = np.unique(np.asarray(reps), axis=0, return_index=True)
    return keep[np.sort(first)]


def covering_radius(
    quats,
    n_samples: int = 100_000,
    seed: int = 0,
    group: np.ndarray | None = None,
    chunk: int = 4096,
) -> float:
    """Monte Carlo estimate (degrees) of ``max_r min_{p, g} d(r, p g)`` over Haar samples ``r``.

    A lower bound on the true covering radius that tightens with ``n_samples``. With a
    ``group``, distances are taken modulo the symmetry (``p g`` for every ``g``).
    """
    grid = np.asarray(quats, dtype=np.float64)
    if len(grid) == 0:
        raise ValueError("covering_radius: empty grid")
    if group is not None and len(group) > 1:
        grid = quat_multiply_host(grid[:, None, :], np.asarray(group)[None, :, :]).reshape(-1, 4)
    g = jnp.asarray(grid, jnp.float32)
    samples = random_quaternions(jax.random.key(seed), n_samples, jnp.float32)

    @jax.jit
    def best(s):
        return jnp.max(jnp.abs(s @ g.T), axis=1)

    worst = 1.0
    for i in range(0, n_samples, chunk):
        s = samples[i : i + chunk]
        worst = min(worst, float(jnp.min(best(s))))
    return float(np.degrees(2 * np.arccos(np.clip(worst, 0.0, 1.0))))


def stated_resolution_deg(n_points: int, kind: str = "hopf") -> float:
    """Stated covering radius (degrees) of a full ``kind`` grid of ``n_points`` rotations."""
    c = {"hopf": C_HOPF, "fibonacci": C_FIBONACCI}[kind]
    return float(np.degrees(c * n_points ** (-1.0 / 3.0)))


def nside_for_resolution(resolution_deg: float) -> int:
    """Smallest Hopf ``nside`` whose stated resolution is at most ``resolution_deg``."""
    if not resolution_deg > 0:
        raise ValueError(f"resolution_deg must be > 0, got {resolution_deg!r}")
    n = 1
    while stated_resolution_deg(72 * n**3) > resolution_deg:
        n += 1
    return n


class AttitudeGrid:
    """An attitude grid with its stated resolution, optionally reduced by a symmetry group.

    Not a pytree: a host-side description used to enumerate database rows.
    """

    def __init__(self, kind: str = "hopf", size: int = 1, symmetry="none"):
        """``symmetry``: a class name of :func:`symmetry_group`, a :class:`ppr.MeshSymmetry`
        or a :class:`ppr.Mesh` (its own group, :func:`as_symmetry`); its rotations reduce
        the grid."""
        if kind == "hopf":
            full = hopf_grid(int(size))
        elif kind == "fibonacci":
            full = fibonacci_grid(int(size))
        else:
            raise ValueError(f"unknown grid kind {kind!r}; use 'hopf' or 'fibonacci'")
        self.kind, self.size = kind, int(size)
        if isinstance(symmetry, str):
            self.symmetry = symmetry
        else:
            symmetry = as_symmetry(symmetry)
            self.symmetry = f"mesh:{symmetry.point_group}"
        self.resolution_deg = stated_resolution_deg(len(full), kind)
        self.group = symmetry_group(symmetry)
        keep = reduce_by_symmetry(full, self.group, self.resolution_deg)
        self.quats = full[keep]
        self.full_size = len(full)

    def __len__(self) -> int:
        return len(self.quats)

    def describe(self) -> dict:
        return {
            "kind": self.kind,
            "size": self.size,
            "symmetry": self.symmetry,
            "n_full": self.full_size,
            "n": len(self),
            "resolution_deg": self.resolution_deg,
        }


def face_on_attitudes(mesh, los, *, symmetry=None, max_classes: int = 3) -> np.ndarray:
    """Attitudes ``(K, 4)`` that turn each of a mesh's largest flat sides to face ``los``.

    A glossy side returns a glint only within a lobe ``~1/sqrt(m)`` rad of face-on (6 deg at
    ``m = 90``), narrower than a screening grid's spacing, and the cosine score of a template
    cannot tell that glint from another shape's smaller side with the gain absorbing the
    area (a 3U's long side 5 deg off face-on read as a 1U at SNR 1000, the 3U's screened
    starts 77 deviance units behind). The sides: the mesh's triangles grouped by normal
    (to 1e-6), their areas summed, one side per class of normals mapped onto each other by
    the proper rotations of ``symmetry`` (default :func:`as_symmetry` of the mesh; elements
    with residual above 1e-6 ignored), the ``max_classes`` classes of largest side area
    first. Each attitude is the smallest rotation taking the side's outward normal to the
    world direction ``los`` (toward the sensor); the roll about ``los`` is left to the
    caller (a roll scan). Host NumPy; quaternions ``(w, x, y, z)``."""
    if max_classes <= 0:
        return np.zeros((0, 4))
    tri = np.asarray(mesh.triangles(), np.float64)
    cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    dbl = np.linalg.norm(cr, axis=1)
    ok = dbl > 0
    nrm = cr[ok] / dbl[ok, None]
    area = 0.5 * dbl[ok]
    key, inv = np.unique(np.round(nrm, 6), axis=0, return_inverse=True)
    inv = inv.ravel()
    side_area = np.bincount(inv, weights=area, minlength=len(key))
    side_nrm = np.zeros((len(key), 3))
    np.add.at(side_nrm, inv, nrm * area[:, None])
    side_nrm /= np.linalg.norm(side_nrm, axis=1, keepdims=True)
    sym = as_symmetry(mesh if symmetry is None else symmetry)
    mats = np.asarray(sym.matrices, np.float64)
    proper = (np.linalg.det(mats) > 0) & (np.asarray(sym.residuals) <= 1e-6)
    rots = mats[proper]
    los = np.asarray(los, np.float64)
    los = los / np.linalg.norm(los)
    out, seen = [], np.zeros(len(key), bool)
    for i in np.argsort(-side_area, kind="stable"):
        if seen[i]:
            continue
        images = side_nrm[i] @ np.transpose(rots, (0, 2, 1))  # S n for every rotation S
        same = np.any(np.linalg.norm(images[:, None, :] - side_nrm[None], axis=-1) < 1e-5, 0)
        seen |= same
        seen[i] = True
        n = side_nrm[i]
        axis = np.cross(n, los)
        s, c = np.linalg.norm(axis), float(n @ los)
        if s < 1e-12:  # parallel: no turn; antiparallel: a half turn about any perpendicular
            if c > 0:
                out.append(np.array([1.0, 0.0, 0.0, 0.0]))
                continue
            axis = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
            s = 0.0
        out.append(quat_from_axis_angle(axis, math.atan2(s, c)))
        if len(out) >= max_classes:
            break
    return np.asarray(out, np.float64).reshape(-1, 4)
