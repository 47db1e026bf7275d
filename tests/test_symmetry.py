"""Mesh symmetries found from the mesh itself (ppr.mesh_symmetries): known point groups,
conjugation under rigid motions, near symmetries at a tolerance, materials and outward
sides breaking symmetry, and the point-to-surface distance the verification rests on,
checked against trimesh's independent closest-point code. NumPy only (no JAX programs)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

import ppr
from ppr.geometry._symmetry import _Faces

ROT = trimesh.transformations.euler_matrix(0.3, -1.1, 2.0)[:3, :3]
SHIFT = np.array([1.0, -2.0, 0.5])


def _prism():
    """Regular triangular prism (circumradius 0.1 m, height 0.3 m): D3h."""
    return ppr.shapes.cylinder(0.1, 0.3, sections=3)


def _hull():
    """Convex hull of 30 random points: no symmetry."""
    tm = trimesh.convex.convex_hull(np.random.default_rng(0).normal(size=(30, 3)))
    return ppr.Mesh(tm.vertices, tm.faces)


def _moved(mesh, rot=ROT, shift=SHIFT):
    v = np.asarray(mesh.vertices, np.float64) @ rot.T + shift
    return ppr.Mesh(v, mesh.faces, mesh.material_ids, mesh.parts)


def _independent_residual(mesh, sym, s, n=400):
    """Largest distance of surface samples mapped by ``s`` (about the group's centre) from
    the surface, by trimesh's closest-point query (rtree, no orientation or parts)."""
    tm = mesh.to_trimesh()
    pts, _ = trimesh.sample.sample_surface(tm, n, seed=1)
    mapped = (pts - sym.centre) @ s.T + sym.centre
    _, dist, _ = trimesh.proximity.closest_point(tm, mapped)
    return float(dist.max()) / sym.size


def test_point_triangle_distance_and_closest_point_match_trimesh():
    """The vectorized point-to-triangle distance and closest point equal trimesh's for random
    triangles (including slivers) and points inside, outside and beyond the edges."""
    rng = np.random.default_rng(3)
    tri = rng.normal(size=(40, 3, 3))
    tri[:5, 2] = tri[:5, 0] + 1e-3 * (tri[:5, 1] - tri[:5, 0])  # slivers
    pts = 2.0 * rng.normal(size=(200, 3))
    faces = _Faces(tri)
    idx = np.broadcast_to(np.arange(len(tri)), (len(pts), len(tri)))
    dist, close = faces.closest(pts[:, None, :], idx, points=True)
    ref = np.stack(
        [trimesh.triangles.closest_point(tri, np.repeat(p[None], len(tri), 0)) for p in pts]
    )
    # float64 geometry: both codes agree to rounding of O(1) coordinates
    np.testing.assert_allclose(close, ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        dist, np.linalg.norm(ref - pts[:, None], axis=-1), rtol=0, atol=1e-12
    )


@pytest.mark.parametrize(
    "name, make, group, n_proper, n_improper",
    [
        ("box with three different sides", lambda: ppr.shapes.box((0.1, 0.2, 0.3)), "D2h", 4, 4),
        ("cube", lambda: ppr.shapes.box((0.1, 0.1, 0.1)), "Oh", 24, 24),
        ("regular triangular prism", _prism, "D3h", 6, 6),
        ("asymmetric hull", _hull, "C1", 1, 0),
    ],
)
def test_known_groups_and_their_conjugates(name, make, group, n_proper, n_improper):
    """The elements found are the mesh's point group (counted and named), form a group
    (closed: every product is an element), each maps the surface onto itself by trimesh's
    independent distance, and a rotated and translated copy has the conjugate group
    ``R G R^T`` about the moved centre."""
    mesh = make()
    sym = ppr.mesh_symmetries(mesh)
    assert sym.point_group == group, (name, sym.summary())
    assert (len(sym.rotations), len(sym.improper)) == (n_proper, n_improper), sym.summary()
    assert sym.closed and np.allclose(sym.matrices[0], np.eye(3)) and sym.labels[0] == "identity"
    g = sym.matrices.reshape(-1, 9)
    prod = np.einsum("aij,bjk->abik", sym.matrices, sym.matrices).reshape(-1, 9)
    # products of float64 matrices built from float32 vertices: equal to 1e-6
    assert np.abs(prod[:, None] - g[None]).max(-1).min(1).max() < 1e-6
    for s in sym.matrices[1:]:
        # sampled in float32 vertex rounding: an exact symmetry maps the surface to 1e-6
        assert _independent_residual(mesh, sym, s) < 1e-6, sym.labels
    moved = ppr.mesh_symmetries(_moved(mesh))
    conj = sym.transformed(ROT, SHIFT)
    assert moved.point_group == group and len(moved) == len(sym)
    # the moved float32 vertices are rounded at |v| ~ 2 m: 1e-6 m of a 0.1 m body, 1e-5
    d = np.abs(conj.matrices.reshape(-1, 1, 9) - moved.matrices.reshape(1, -1, 9)).max(-1)
    assert d.min(axis=1).max() < 1e-5 and d.min(axis=0).max() < 1e-5
    np.testing.assert_allclose(moved.centre, conj.centre, rtol=0, atol=1e-6)


def test_a_missing_element_is_far_from_a_symmetry():
    """The verification is not vacuous: the quarter turn a square box has is far from a
    symmetry of a box with three different sides (trimesh's distance, 10% of the size)."""
    box = ppr.shapes.box((0.1, 0.2, 0.3))
    sym = ppr.mesh_symmetries(box)
    c4 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert _independent_residual(box, sym, c4) > 0.1
    assert not any(np.allclose(s, c4) for s in sym.matrices)


def test_symmetric_only_up_to_a_tolerance():
    """A prism with one vertex moved by 1e-3 of its size: no element but the identity at
    tol 1e-4; all 12 of D3h at tol 1e-2, with residuals of the perturbation's order."""
    mesh = _prism()
    v = np.asarray(mesh.vertices, np.float64).copy()
    size = ppr.mesh_symmetries(mesh).size
    i = int(np.argmax(v[:, 2] + v[:, 0]))
    v[i] += np.array([1.0, 0.5, 0.2]) / np.linalg.norm([1.0, 0.5, 0.2]) * 1e-3 * size
    near = ppr.Mesh(v, mesh.faces)
    tight = ppr.mesh_symmetries(near, tol=1e-4)
    assert len(tight) == 1 and tight.point_group == "C1", tight.summary()
    loose = ppr.mesh_symmetries(near, tol=1e-2)
    assert loose.point_group == "D3h" and len(loose) == 12 and loose.closed, loose.summary()
    # the moved vertex is 1e-3 of the size away from its images: residuals up to ~1e-3
    assert 1e-4 < loose.residuals[1:].max() < 2e-3, loose.summary()


def test_materials_and_outward_sides_break_symmetry():
    """A cube whose +z face is another part keeps only the elements that fix that face
    (C4v about +z); ignoring parts gives Oh back. A one-sided rectangular plate is not
    symmetric under the mirror through its own plane (its outward side flips): C2v."""
    cube = ppr.shapes.box((0.1, 0.1, 0.1))
    tri = cube.triangles()
    up = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2] > 0
    painted = ppr.Mesh(cube.vertices, cube.faces, up.astype(np.int32), ("body", "paint"))
    sym = ppr.mesh_symmetries(painted)
    assert sym.point_group == "C4v" and len(sym) == 8, sym.summary()
    assert "C4 about body +z" in sym.labels
    for s in sym.matrices:
        np.testing.assert_allclose(s @ [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], atol=1e-9)
    assert len(ppr.mesh_symmetries(painted, materials=False)) == 48
    plate = ppr.mesh_symmetries(ppr.shapes.plate(1.0, 0.5))
    assert plate.point_group == "C2v" and "mirror normal to body z" not in plate.labels


@pytest.mark.parametrize(
    "make, group, order",
    [
        (lambda: ppr.shapes.plate(), "C4v", 8),
        (lambda: ppr.shapes.cubesat(3), "D4h", 16),
        (lambda: ppr.shapes.cylinder(sections=8), "D8h", 32),
        (lambda: ppr.shapes.cone(sections=8), "C8v", 16),
        (lambda: ppr.shapes.sphere(subdivisions=1), "Ih", 120),
        (lambda: ppr.shapes.cubesat_with_panels(), "C2v", 4),
        (lambda: ppr.load_mesh(ppr.__path__[0] + "/data/example_satellite.glb"), "C1", 1),
    ],
)
def test_library_shapes(make, group, order):
    """The library's shapes: a one-sided square plate, a 3U CubeSat, an 8-sided cylinder and
    cone, an icosphere, a CubeSat with panels whose solar cells face +x (so no mirror x),
    and the example satellite (no symmetry at the default tolerance: its mirror through
    y = 0 holds to 2% of its size only)."""
    sym = ppr.mesh_symmetries(make())
    assert (sym.point_group, len(sym)) == (group, order), sym.summary()
    assert sym.closed and sym.residuals.max() < 1e-6


def test_labels():
    """Labels name the element: rotation order and power, axis (signed unless a half
    turn), mirror normal, rotoreflection, inversion."""

    def rot(axis, angle):
        return trimesh.transformations.rotation_matrix(angle, axis)[:3, :3]

    assert ppr.symmetry_label(np.eye(3)) == "identity"
    assert ppr.symmetry_label(-np.eye(3)) == "inversion"
    assert ppr.symmetry_label(rot([0, 0, 1], math.pi / 2)) == "C4 about body +z"
    assert ppr.symmetry_label(rot([0, 0, 1], -math.pi / 2)) == "C4 about body -z"
    assert ppr.symmetry_label(rot([1, 0, 0], math.pi)) == "C2 about body x"
    assert ppr.symmetry_label(rot([1, 1, 1], 2 * math.pi / 3)) == (
        "C3 about body (0.577, 0.577, 0.577)"
    )
    assert ppr.symmetry_label(rot([0, 1, 0], 4 * math.pi / 5)) == "C5^2 about body +y"
    assert ppr.symmetry_label(np.diag([1.0, -1.0, 1.0])) == "mirror normal to body y"
    s4 = np.diag([1.0, 1.0, -1.0]) @ rot([0, 0, 1], math.pi / 2)
    assert ppr.symmetry_label(s4) == "S4 about body +z"
    assert ppr.symmetry_label(rot([0, 0, 1], 0.5)) == "rotation by 28.65 deg about body +z"


def test_bad_input_is_named():
    box = ppr.shapes.box((0.1, 0.2, 0.3))
    with pytest.raises(ValueError, match="tol must lie in"):
        ppr.mesh_symmetries(box, tol=0.0)
    with pytest.raises(ValueError, match="n_samples must be >= 1"):
        ppr.mesh_symmetries(box, n_samples=0)
    with pytest.raises(ValueError, match="orthogonal"):
        ppr.MeshSymmetry(np.ones((1, 3, 3)), np.zeros(1), np.zeros(3), 1.0, 0.0)
