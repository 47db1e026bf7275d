"""SO(3) grids: HEALPix base, Hopf grid uniformity, covering radius vs stated resolution,
symmetry groups and reduction."""

import numpy as np
import pytest

from inversion._grid import (
    AttitudeGrid,
    _healpix_centres,
    body_mirror_normal,
    covering_radius,
    fibonacci_grid,
    hopf_grid,
    mirror_attitude,
    stated_resolution_deg,
    symmetry_group,
)
from ppr.geometry import quat_angle_deg, quat_multiply_host, quat_to_matrix_host


@pytest.mark.parametrize("nside", [1, 2, 3, 4])
def test_healpix_centres(nside):
    theta, phi = _healpix_centres(nside)
    assert len(theta) == 12 * nside**2
    z = np.cos(theta)
    rings = np.unique(np.round(z, 12))
    assert len(rings) == 4 * nside - 1
    # equal-area pixels: the centres' z are uniform-like -> exact mean 0, and each ring's
    # azimuths are equally spaced, so the centres' vector sum vanishes (1e-12: round-off)
    v = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), z], -1)
    np.testing.assert_allclose(v.sum(0), 0.0, atol=1e-12 * len(v))
    # the polar cap / belt boundary sits at z = 2/3 (Gorski et al. 2005)
    n_cap = 2 * nside * (nside + 1)
    assert np.all(z[:n_cap] >= 2 / 3 - 1e-12) and np.all(z[n_cap:] < 2 / 3 + 1e-12)


@pytest.mark.parametrize("grid", [hopf_grid(2), fibonacci_grid(500)], ids=["hopf", "fibonacci"])
def test_grid_uniform_second_moment(grid):
    # Haar measure: E[q q^T] = I/4 for unit quaternions; the deterministic grids match it to
    # a few percent at these sizes (1.5e-2 absolute)
    m = grid.T @ grid / len(grid)
    np.testing.assert_allclose(m, np.eye(4) / 4, atol=1.5e-2)
    np.testing.assert_allclose(np.linalg.norm(grid, axis=1), 1.0, atol=1e-12)


def test_hopf_size_and_distinct():
    q = hopf_grid(2)
    assert q.shape == (576, 4)
    d = quat_angle_deg(q[:, None], q[None])
    np.fill_diagonal(d, 180.0)
    assert d.min() > 5.0  # no two grid points describe the same rotation


@pytest.mark.parametrize(
    "kind,size,n", [("hopf", 1, 72), ("hopf", 2, 576), ("hopf", 3, 1944), ("fibonacci", 2000, 2000)]
)
def test_covering_radius_matches_stated_resolution(kind, size, n):
    grid = AttitudeGrid(kind, size)
    assert len(grid) == n
    rho = covering_radius(grid.quats, n_samples=60_000, seed=1)
    # Monte Carlo gives a lower bound of the covering radius: it must not exceed the stated
    # one, and the stated one is calibrated to be within 20% of this 6e4-sample measurement
    assert rho <= grid.resolution_deg
    assert rho >= 0.8 * grid.resolution_deg
    assert grid.resolution_deg == pytest.approx(stated_resolution_deg(n, kind))


@pytest.mark.parametrize(
    "name,order", [("none", 1), ("cyclic:3", 3), ("dihedral:4", 8), ("octahedral", 24)]
)
def test_symmetry_groups_close(name, order):
    g = symmetry_group(name)
    assert len(g) == order
    prod = quat_multiply_host(g[:, None], g[None]).reshape(-1, 4)
    d = quat_angle_deg(prod[:, None], g[None]).min(1)
    assert d.max() < 1e-4  # closed under composition (arccos near 1 resolves ~1e-6 deg)


@pytest.mark.parametrize("sym", ["octahedral", "dihedral:4"])
def test_symmetry_reduction_covers_quotient(sym):
    full = AttitudeGrid("hopf", 3)
    red = AttitudeGrid("hopf", 3, sym)
    order = len(red.group)
    assert len(full) / order <= len(red) < len(full) / order * 3.5  # N/|G| plus a boundary band
    rho = covering_radius(red.quats, n_samples=40_000, seed=2, group=red.group)
    assert rho <= red.resolution_deg
    # one representative per orbit: no two kept points are equivalent under the group
    cand = quat_multiply_host(red.quats[:, None], red.group[None])  # (n, G, 4)
    d = quat_angle_deg(cand[:, None, :, :], red.quats[None, :, None, :]).min(-1)
    np.fill_diagonal(d, 180.0)
    assert d.min() > 1e-3


def test_bad_grid_input():
    with pytest.raises(ValueError, match="nside"):
        hopf_grid(0)
    with pytest.raises(ValueError, match="symmetry group"):
        symmetry_group("icosahedral")
    with pytest.raises(ValueError, match="grid kind"):
        AttitudeGrid("random", 3)
    with pytest.raises(ValueError, match="empty grid"):
        covering_radius(np.zeros((0, 4)))


def _matrix(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_mirror_attitude_is_world_mirror_times_body_mirror():
    """R' = P R sigma (two reflections: proper), batched; its body line of sight is sigma v;
    applying it twice gives R back; arbitrary mirror normals."""
    rng = np.random.default_rng(3)
    q = rng.normal(size=(20, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    for s, w in (([0, 0, 1.0], [0, 1.0, 0]), (rng.normal(size=3), rng.normal(size=3))):
        s, w = np.asarray(s) / np.linalg.norm(s), np.asarray(w) / np.linalg.norm(w)
        qm = mirror_attitude(q, s, w)
        sigma, world = np.eye(3) - 2 * np.outer(s, s), np.eye(3) - 2 * np.outer(w, w)
        for a, b in zip(q, qm, strict=True):
            np.testing.assert_allclose(_matrix(b), world @ _matrix(a) @ sigma, atol=1e-14)
        back = mirror_attitude(qm, s, w)
        assert np.all(quat_angle_deg(back, q) < 1e-5)
    # body line of sight (world +z seen from the body) is mirrored by sigma_h: z -> -z
    v, vm = _matrix(q[0])[2], _matrix(mirror_attitude(q[0]))[2]
    np.testing.assert_allclose(vm, v * [1, 1, -1], atol=1e-14)


def test_mirror_errors_and_normals():
    from inversion._classifier import attitude_error_deg, line_of_sight_error_deg

    assert np.array_equal(body_mirror_normal("dihedral:4"), [0, 0, 1])
    assert np.array_equal(body_mirror_normal("octahedral"), [0, 0, 1])
    assert body_mirror_normal("cyclic:3") is None and body_mirror_normal("none") is None
    q = np.array([0.9, 0.2, -0.3, 0.25])
    q /= np.linalg.norm(q)
    qm = mirror_attitude(q)
    # the mirror image's line of sight is a different direction modulo the rotations ...
    assert line_of_sight_error_deg(q, qm, "dihedral:4")[0] > 5.0
    assert attitude_error_deg(q, qm, "dihedral:4")[0] > 5.0
    # ... and the same one modulo the mirror too
    assert line_of_sight_error_deg(q, qm, "dihedral:4", mirror=True)[0] < 1e-5
    assert attitude_error_deg(q, qm, "dihedral:4", mirror=True)[0] < 1e-5
    with pytest.raises(ValueError, match="mirror=True needs"):
        line_of_sight_error_deg(q, qm, "cyclic:3", mirror=True)
    with pytest.raises(ValueError, match="body_normal"):
        mirror_attitude(q, [0, 0, 2.0])
    with pytest.raises(ValueError, match="symmetry group"):
        body_mirror_normal("icosahedral")


def test_mesh_has_mirror_on_the_shapes_the_named_classes_stand_for():
    """The z -> -z plane is a mirror of the box, CubeSat and prism meshes the dihedral and
    octahedral classes stand for, as a surface (their triangulations are not symmetric) and
    as a vertex set; a tilted plane is not, nor is z -> -z of a cone."""
    import ppr
    from inversion._grid import mesh_has_mirror

    for mesh in (ppr.shapes.cubesat(1), ppr.shapes.cubesat(3), ppr.shapes.cylinder(0.06, 0.25)):
        for m in (mesh, mesh.vertices):
            assert mesh_has_mirror(m, body_mirror_normal("dihedral:4"))
            assert not mesh_has_mirror(m, [0.0, 0.6, 0.8])
    assert not mesh_has_mirror(ppr.shapes.cone(0.1, 0.2), [0.0, 0.0, 1.0])
    # panels (in the body's y-z plane) with solar cells on one side and paint on the other:
    # the vertex set is symmetric through the panels' plane, the parts are not
    panels = ppr.shapes.cubesat_with_panels(3)
    assert mesh_has_mirror(panels.vertices, [1.0, 0.0, 0.0])
    assert not mesh_has_mirror(panels, [1.0, 0.0, 0.0])
    assert mesh_has_mirror(panels, [0.0, 0.0, 1.0]) and mesh_has_mirror(panels, [0.0, 1.0, 0.0])
    with pytest.raises(ValueError, match="vertices"):
        mesh_has_mirror(np.zeros((0, 3)), [0.0, 0.0, 1.0])


def test_grid_and_database_take_a_mesh_group():
    """The attitude grid reduced by a 3U CubeSat's own group (D4h, computed from the mesh) is
    the grid reduced by the named class that stands for it (dihedral:4); a database shape
    with symmetry = "auto" (model ppr) gets that grid and records the group's 8 rotations;
    the synthetic model, which has no mesh, refuses "auto" when the spec is read."""
    import ppr
    from inversion._database import _names, grids_for, spec_from_dict

    mesh = ppr.shapes.cubesat(3)
    by_mesh = AttitudeGrid("hopf", 2, mesh)
    by_name = AttitudeGrid("hopf", 2, "dihedral:4")
    assert by_mesh.describe()["symmetry"] == "mesh:D4h"
    np.testing.assert_array_equal(by_mesh.quats, by_name.quats)
    spec = {
        "name": "t",
        "model": "ppr",
        "shapes": [{"name": "cubesat", "symmetry": "auto", "params": {"units": 3}}],
        "materials": ["aluminium"],
        "finishes": {"rough": 10.0},
        "grid": {"size": 2},
    }
    (grid,) = grids_for(spec_from_dict(spec))
    np.testing.assert_array_equal(grid.quats, by_name.quats)
    assert len(_names(spec_from_dict(spec))["symmetry_group"][0]) == 8
    spec["model"] = "synthetic"
    spec["shapes"] = [{"name": "box3u", "symmetry": "auto"}]
    with pytest.raises(ValueError, match=r"shapes\[0\]\.symmetry = 'auto': .* needs model = 'ppr'"):
        spec_from_dict(spec)


def test_face_on_attitudes_turn_each_side_class_to_the_sensor():
    """Each attitude takes one side's outward normal exactly onto the line of sight; sides
    the mesh's rotations map onto each other are one class (a 3U CubeSat: its four long sides
    one class, its two ends another; a cube: one), largest side area first; a box of three
    different sides has three classes (opposite sides swapped by its half turns), cut at
    ``max_classes``."""
    import ppr
    from inversion._grid import face_on_attitudes

    los = np.array([0.3, -0.2, 0.93])
    los /= np.linalg.norm(los)
    cases = [
        (ppr.shapes.box((0.1, 0.1, 0.34)), [(1, 0, 0), (0, 0, 1)]),  # long side, then end
        (ppr.shapes.box((0.1, 0.1, 0.1)), [(1, 0, 0)]),
        (ppr.shapes.box((0.1, 0.2, 0.34)), [(1, 0, 0), (0, 1, 0), (0, 0, 1)]),
    ]
    for mesh, axes in cases:
        q = face_on_attitudes(mesh, los, max_classes=6)
        rot = quat_to_matrix_host(q)
        body_los = np.einsum("kji,j->ki", rot, los)  # R^T los: the side facing the sensor
        # each one a side normal (up to its sign: the outward one of either of a pair)
        got = [tuple(np.abs(np.round(v, 9))) for v in body_los]
        assert sorted(got) == sorted(tuple(map(float, a)) for a in axes), (got, axes)
        # largest side area first: the box's sides are 0.1 x 0.34 > 0.1 x 0.1 (3U)
        if len(axes) == 2:
            assert got[0] == (1.0, 0.0, 0.0) or got[0] == (0.0, 1.0, 0.0)
    # the box of three sides: its largest (0.2 x 0.34, normal x) first, cut at max_classes
    q = face_on_attitudes(cases[2][0], los, max_classes=6)
    assert abs(abs((quat_to_matrix_host(q[0]).T @ los)[0]) - 1.0) < 1e-9
    assert len(face_on_attitudes(cases[2][0], los, max_classes=2)) == 2
