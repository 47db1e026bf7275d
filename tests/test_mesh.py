"""Meshes, shapes, poses and visibility (host-side geometry of issue 4)."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

import ppr
from ppr import shapes
from ppr.geometry._mesh import capacity_for
from ppr.geometry._rotation import check_quaternion, matrix_to_quat, quat_multiply
from ppr.geometry._visibility import VisibilityCaster, barycentric_samples

# ----------------------------------------------------------------------------- shapes


@pytest.mark.parametrize(
    "mesh, area, volume",
    [
        (shapes.plate(2.0, 0.5, subdivisions=3), 1.0, None),
        (shapes.cubesat(1), 0.06, 1e-3),
        (shapes.cubesat(3), 2 * 0.01 + 4 * 0.034, 0.1 * 0.1 * 0.34),
        (shapes.box((0.2, 0.3, 0.4), max_edge=0.05), 2 * (0.06 + 0.08 + 0.12), 0.024),
    ],
)
def test_flat_shapes_area_volume(mesh, area, volume):
    tm = mesh.to_trimesh()
    # exact geometry: float64 rounding only (vertices may be stored float32 without x64)
    assert tm.area == pytest.approx(area, rel=1e-6)
    if volume is not None:
        assert tm.is_watertight
        assert tm.volume == pytest.approx(volume, rel=1e-6)  # positive: normals point outward


@pytest.mark.parametrize(
    "maker, exact",
    [
        (lambda: shapes.sphere(0.5, subdivisions=4), 4 / 3 * np.pi * 0.125),
        (lambda: shapes.cylinder(0.5, 1.0, sections=128), np.pi * 0.25),
        (lambda: shapes.cone(0.5, 1.0, sections=128), np.pi * 0.25 / 3),
    ],
)
def test_curved_shapes_converge(maker, exact):
    tm = maker().to_trimesh()
    assert tm.is_watertight
    # inscribed polyhedra: volume deficit ~ (edge / radius)^2, below 1 % at these resolutions
    assert tm.volume == pytest.approx(exact, rel=1e-2)
    assert tm.volume < exact


def test_cubesat_with_panels_parts_and_shape():
    m = shapes.cubesat_with_panels(3, panel_span=0.3)
    assert m.parts == ("body", "solar_panel", "panel_back")
    tm = m.to_trimesh()
    mid = np.asarray(m.material_ids)
    area = tm.area_faces
    # solar cells: the two +x panel faces, 0.3 x 0.34 m each
    assert area[mid == 1].sum() == pytest.approx(2 * 0.3 * 0.34, rel=1e-6)
    assert area[mid == 0].sum() == pytest.approx(2 * 0.01 + 4 * 0.034, rel=1e-6)
    assert np.ptp(np.asarray(m.vertices)[:, 1]) == pytest.approx(0.1 + 2 * 0.3, rel=1e-6)
    assert not tm.is_convex  # the panel-body dihedrals are concave


def test_subdivide_keeps_area_and_parts():
    m = shapes.cubesat_with_panels(3)
    s = ppr.subdivide(m, 0.05)
    assert ppr.Mesh.max_edge(s) <= 0.05 + 1e-9
    a0 = m.to_trimesh().area_faces
    a1 = s.to_trimesh().area_faces
    for k in range(3):
        assert a1[np.asarray(s.material_ids) == k].sum() == pytest.approx(
            a0[np.asarray(m.material_ids) == k].sum(), rel=1e-6
        )


def test_face_counts_past_the_budget_are_refused_before_allocating():
    """Count parameters whose shapes would exceed ``MAX_FACES`` are errors naming the
    parameter, the value and the face count (an icosphere of 12 subdivisions, 3.4e8 faces,
    exhausted memory instead); the budget's face counts are the shapes' exact ones, and the
    subdivision's estimate is exact on a box (every face splits the same number of times)."""
    for make, match in (
        (lambda: shapes.sphere(0.25, subdivisions=12), "subdivisions = 12 would make 3.36e"),
        (lambda: shapes.plate(1.0, subdivisions=5000), "subdivisions = 5000 would make 5e"),
        (lambda: shapes.cylinder(0.1, 0.2, sections=10**6), "sections = 1000000 would make 4e"),
        (lambda: shapes.cone(0.1, 0.2, sections=10**7), "sections = 10000000 would make 2e"),
        (lambda: shapes.box((0.1, 0.1, 0.1), max_edge=1e-5), "max_edge = 1e-05 m would make"),
    ):
        with pytest.raises(ValueError, match=match):
            make()
    assert len(shapes.sphere(1.0, subdivisions=3).faces) == 20 * 4**3
    assert len(shapes.plate(1.0, subdivisions=7).faces) == 2 * 7**2
    assert len(shapes.cylinder(0.1, 0.2, sections=9).faces) == 4 * 9
    assert len(shapes.cone(0.1, 0.2, sections=9).faces) == 2 * 9
    # a 0.1 m cube's face diagonals (0.141 m) need 4 halvings to reach 0.01 m: 12 x 4^4
    assert len(shapes.box((0.1, 0.1, 0.1), max_edge=0.01).faces) == 12 * 4**4
    # counts far past the budget are the same error, not an OverflowError
    for make in (
        lambda: shapes.sphere(1.0, subdivisions=600),
        lambda: shapes.plate(1.0, subdivisions=10**200),
    ):
        with pytest.raises(ValueError, match="would make"):
            make()


def test_subdivide_budgets_the_growth_not_the_input(monkeypatch):
    """A mesh already past the face budget that ``max_edge`` leaves alone is returned as
    is; one that it would grow past the budget is refused."""
    m = shapes.sphere(1.0, subdivisions=2)  # 320 faces, edges ~0.3 m
    monkeypatch.setattr(shapes, "MAX_FACES", 100)
    assert len(ppr.subdivide(m, 10.0).faces) == 320
    with pytest.raises(ValueError, match="max_edge = 0.1 m would make"):
        ppr.subdivide(m, 0.1)


def test_shape_errors():
    with pytest.raises(ValueError, match="radius"):
        shapes.sphere(-1.0)
    with pytest.raises(ValueError, match="unknown shape 'torus'"):
        shapes.by_name("torus")
    with pytest.raises(ValueError, match="units"):
        shapes.cubesat(5)


# ----------------------------------------------------------------------------- validation

TRI = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])


def test_fractional_indices_and_repeated_part_names_rejected():
    """A face index 2.5 was silently vertex 2; two parts of one name are one material slot
    named twice."""
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    with pytest.raises(ValueError, match=r"indices must be integers, got 0.5 at \(0, 0\)"):
        ppr.Mesh(TRI, faces + 0.5)
    np.testing.assert_array_equal(ppr.Mesh(TRI, faces * 1.0).faces, faces)
    with pytest.raises(ValueError, match="Mesh.parts names 'a' twice"):
        ppr.Mesh(TRI, faces, np.array([0, 1]), ("a", "a"))


def test_empty_mesh_rejected():
    with pytest.raises(ValueError, match="empty"):
        ppr.Mesh(np.zeros((0, 3)), np.zeros((0, 3), int))


def test_nonfinite_vertices_rejected():
    v = TRI.copy()
    v[2, 1] = np.nan
    with pytest.raises(ValueError, match="vertices must be finite.*vertex 2"):
        ppr.Mesh(v, [[0, 1, 2]])


def test_face_index_out_of_range():
    with pytest.raises(ValueError, match="out of range"):
        ppr.Mesh(TRI, [[0, 1, 7]])
    with pytest.raises(ValueError, match="material_ids out of range"):
        ppr.Mesh(TRI, [[0, 1, 2]], [1], ("body",))


def test_degenerate_faces_error_or_drop():
    m = ppr.Mesh(np.vstack([TRI, [[2.0, 0, 0]]]), [[0, 1, 2], [0, 1, 4]])  # 0, 1, 4 collinear
    with pytest.raises(ValueError, match="1 degenerate .*face 1"):
        ppr.check_mesh(m)
    d = ppr.check_mesh(m, on_degenerate="drop")
    assert d.n_faces == 1
    # degenerate is the face's own shape, not its size: a 0.1 mm facet (area 5e-9 m^2) on a
    # 100 m plate is a face; three collinear points or one point are not, at any scale
    big = ppr.shapes.plate(100.0)
    for pts, bad in (
        ([[0, 0, 1.0], [1e-4, 0, 1.0], [0, 1e-4, 1.0]], False),
        ([[0, 0, 1.0], [1e-4, 0, 1.0], [3e-4, 0, 1.0]], True),
        ([[0, 0, 1.0], [0, 0, 1.0], [0, 0, 1.0]], True),
        ([[0, 0, 1.0], [1e-13, 0, 1.0], [0, 1e-13, 1.0]], True),  # 1e-15 of the mesh
    ):
        both = ppr.shapes.concatenate([big, ppr.Mesh(np.asarray(pts), [[0, 1, 2]])])
        if bad:
            with pytest.raises(ValueError, match=f"face {big.n_faces} "):
                ppr.check_mesh(both)
        else:
            assert ppr.check_mesh(both).n_faces == big.n_faces + 1
    # collinear in the stored precision: float32 rounds three collinear points 6 m from the
    # origin to a 1 mm sliver of height ~1e-7 m (area ~1e-10 of its edge squared, not 1e-12)
    d = np.array([0.48, -0.6, 0.64])
    a = 6.0 * np.array([0.6, 0.0, 0.8])
    pts = np.stack([a, a + 1e-3 * d, a + 2.5e-3 * d]).astype(np.float32)
    box = ppr.shapes.box((0.1, 0.1, 0.1))
    nv = np.asarray(box.vertices).shape[0]
    sliver = ppr.Mesh(
        np.vstack([np.asarray(box.vertices), pts]).astype(np.float32),
        np.vstack([np.asarray(box.faces), [[nv, nv + 1, nv + 2]]]),
    )
    assert np.asarray(sliver.vertices).dtype == np.float32
    with pytest.raises(ValueError, match=f"face {box.n_faces} "):
        ppr.check_mesh(sliver)
    # the same points held in float64 are a real (if thin) face
    assert ppr.check_mesh(ppr.Mesh(np.asarray(sliver.vertices, np.float64), sliver.faces))


def test_duplicate_faces_error_or_drop_but_two_sided_kept():
    dup = ppr.Mesh(TRI, [[0, 1, 2], [1, 2, 0]])  # same face, rotated indices
    with pytest.raises(ValueError, match="1 duplicate faces"):
        ppr.check_mesh(dup)
    assert ppr.check_mesh(dup, on_degenerate="drop").n_faces == 1
    # duplicate positions through different vertex indices
    v = np.vstack([TRI, TRI[:3]])
    with pytest.raises(ValueError, match="duplicate"):
        ppr.check_mesh(ppr.Mesh(v, [[0, 1, 2], [4, 5, 6]]))
    two_sided = ppr.Mesh(TRI, [[0, 1, 2], [0, 2, 1]])
    assert ppr.check_mesh(two_sided).n_faces == 2


def test_mesh_arrays_padding():
    m = shapes.sphere(1.0, subdivisions=2)  # 320 faces
    a = ppr.mesh_arrays(m)
    cap = capacity_for(320)
    assert a.tri.shape == (cap, 3, 3) and cap >= 320 and cap <= 1.25 * 320 + 64
    assert int(a.valid.sum()) == 320
    assert float(a.areas[320:].sum()) == 0.0
    assert float(a.areas.sum()) == pytest.approx(m.to_trimesh().area, rel=1e-9)
    with pytest.raises(ValueError, match="overflow"):
        ppr.mesh_arrays(m, capacity=100)
    assert [capacity_for(n) for n in (1, 64, 65, 1000, 1024, 1025)] == [
        64,
        64,
        80,
        1024,
        1024,
        1280,
    ]


# ----------------------------------------------------------------------------- loading


@pytest.mark.parametrize("ext", ["obj", "stl", "ply", "glb"])
def test_load_formats_roundtrip(tmp_path, ext):
    m = shapes.cubesat(3)
    path = tmp_path / f"sat.{ext}"
    m.to_trimesh().export(path)
    got = ppr.load_mesh(path)
    assert got.n_faces == 12
    assert got.to_trimesh().area == pytest.approx(0.156, rel=1e-6)
    got_mm = ppr.load_mesh(path, scale=1e-3)
    assert got_mm.to_trimesh().area == pytest.approx(0.156e-6, rel=1e-6)


def test_load_multipart_glb_names_parts(tmp_path):
    scene = trimesh.Scene()
    scene.add_geometry(shapes.cubesat(1).to_trimesh(), geom_name="bus")
    panel = shapes.plate(0.3).to_trimesh()
    panel.apply_translation([0, 0.3, 0])
    scene.add_geometry(panel, geom_name="wing")
    path = tmp_path / "sat.glb"
    scene.export(path)
    m = ppr.load_mesh(path, part_names={"wing": "solar_panel"})
    assert set(m.parts) == {"bus", "solar_panel"}
    mid = np.asarray(m.material_ids)
    assert (mid == m.parts.index("solar_panel")).sum() == 2


def test_load_errors(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        ppr.load_mesh(tmp_path / "nope.obj")
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\nv 0 1 0\nf 1 2 4\n")
    with pytest.raises(ValueError, match="degenerate"):
        ppr.load_mesh(bad)
    assert ppr.load_mesh(bad, on_degenerate="drop").n_faces == 1
    # the scale is checked itself (0 made every face degenerate, NaN every vertex non-finite)
    for scale in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match=r"load_mesh: scale must be"):
            ppr.load_mesh(bad, scale=scale)


TWO_OBJECTS = """o first
v 0 0 0
v 1 0 0
v 0 1 0
f 1 2 3
o second.panel
v 0 0 1
v 1 0 1
v 0 1 1
f 4 5 6
o second_panel
v 0 0 2
v 1 0 2
v 0 1 2
f 7 8 9
"""


def test_load_never_drops_nonfinite_vertices(tmp_path):
    # trimesh's processing removes a NaN/inf vertex with its faces (3 of 4 faces would
    # survive here); the loader reads without it and names the file, the object and counts
    for bad in ("nan", "inf"):
        path = tmp_path / f"{bad}.obj"
        path.write_text(
            f"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv {bad} 0 0\nf 1 2 3\nf 1 3 4\nf 1 2 4\nf 2 3 5\n"
        )
        with pytest.raises(ValueError) as e:
            ppr.load_mesh(path)
        msg = str(e.value)
        assert str(path) in msg and "1 non-finite" in msg and "used by 1 of its 4 faces" in msg


def test_load_objects_become_parts_named_as_keys(tmp_path):
    path = tmp_path / "two.obj"
    path.write_text(TWO_OBJECTS)
    m = ppr.load_mesh(path)
    # three objects, three parts; dots would split --set keys, so they become "_"; the
    # clash that makes with the third object's name gets a suffix instead of a merge
    assert sorted(m.parts) == ["first", "second_panel", "second_panel_2"]
    assert np.bincount(np.asarray(m.material_ids)).tolist() == [1, 1, 1]
    with pytest.raises(ValueError, match="part_names.frist: .* has no object 'frist'"):
        ppr.load_mesh(path, part_names={"frist": "body"})
    renamed = ppr.load_mesh(path, part_names={"second.panel": "wing", "first": "body"})
    assert sorted(renamed.parts) == ["body", "second_panel", "wing"]
    # a GLB scene whose two nodes instance one geometry: two parts, both placed
    scene = trimesh.Scene()
    box = shapes.cubesat(1).to_trimesh()
    scene.add_geometry(box, geom_name="unit", node_name="left")
    scene.add_geometry(
        box,
        geom_name="unit",
        node_name="right",
        transform=trimesh.transformations.translation_matrix([1, 0, 0]),
    )
    scene.export(tmp_path / "pair.glb")
    g = ppr.load_mesh(tmp_path / "pair.glb")
    assert sorted(g.parts) == ["left", "right"] and g.n_faces == 24
    x = np.asarray(g.vertices)[:, 0]
    assert x.min() == pytest.approx(-0.05) and x.max() == pytest.approx(1.05)
    # a lone object is named after the file, without its extension
    box.export(tmp_path / "bus.v2.stl")
    assert ppr.load_mesh(tmp_path / "bus.v2.stl").parts == ("bus_v2",)


def test_load_refuses_a_closed_object_facing_inward(tmp_path):
    """A closed box written with every face wound clockwise (normals inward) is refused,
    naming the object (it rendered as an all-zero return), from OBJ and from STL (three
    vertices per face: checked with coincident vertices merged); so is an inward box beside
    an outward one. The same box wound outward, an open inward plate and an outward shell
    around an inward cavity load; a node mirrored by its transform (the usual way to model
    a symmetric panel in glTF) loads with its winding reversed, so its faces point outward
    (it rendered as zero before)."""
    import trimesh

    box = trimesh.creation.box(extents=(0.1, 0.2, 0.3))
    inward = trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False)
    for ext in ("obj", "stl"):
        inward.export(tmp_path / f"inward.{ext}")
        with pytest.raises(ValueError, match=r"object 'inward' has a closed body whose faces"):
            ppr.load_mesh(tmp_path / f"inward.{ext}")
    box.export(tmp_path / "outward.obj")
    assert len(ppr.load_mesh(tmp_path / "outward.obj").faces) == 12
    plate = trimesh.Trimesh(box.vertices, box.faces[:2, ::-1], process=False)
    plate.export(tmp_path / "plate.obj")
    assert len(ppr.load_mesh(tmp_path / "plate.obj").faces) == 2
    small = inward.copy()
    small.apply_scale(0.5)  # an inward box inside the outward one: a cavity
    shell = trimesh.util.concatenate([box, small])
    shell.export(tmp_path / "shell.obj")
    assert len(ppr.load_mesh(tmp_path / "shell.obj").faces) == 24
    beside = small.copy()
    beside.apply_translation((1.0, 0.0, 0.0))
    trimesh.util.concatenate([box, beside]).export(tmp_path / "beside.obj")
    with pytest.raises(ValueError, match="closed body whose faces point inward"):
        ppr.load_mesh(tmp_path / "beside.obj")
    scene = trimesh.Scene()
    scene.add_geometry(
        box, node_name="left", transform=trimesh.transformations.translation_matrix((-0.5, 0, 0))
    )
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    mirror[0, 3] = 0.5
    scene.add_geometry(box, node_name="right", transform=mirror)
    scene.export(tmp_path / "panels.glb")
    mesh = ppr.load_mesh(tmp_path / "panels.glb")
    assert set(mesh.parts) == {"left", "right"}
    for k in range(2):
        sel = np.asarray(mesh.material_ids) == k
        part = trimesh.Trimesh(mesh.vertices, np.asarray(mesh.faces)[sel], process=False)
        part.merge_vertices()
        assert part.volume == pytest.approx(0.1 * 0.2 * 0.3, rel=1e-6)  # outward (float32 file)


def test_load_unreadable_files(tmp_path):
    stl = tmp_path / "broken.stl"
    stl.write_bytes(b"solid x\nfacet normal 0 0 1\n outer loop\n vertex 0 0 \xff\xfe junk")
    with pytest.raises(ValueError, match=r"broken.stl' is not a valid STL file"):
        ppr.load_mesh(stl)
    xyz = tmp_path / "points.xyz"
    xyz.write_text("0 0 0\n")
    with pytest.raises(ValueError, match=r"unsupported format '.xyz'; supported: .obj"):
        ppr.load_mesh(xyz)


# ----------------------------------------------------------------------------- pose


def test_quaternion_matches_scipy_and_sign():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(20, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    r = np.asarray(ppr.quat_to_matrix(q))
    ref = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy is (x, y, z, w)
    np.testing.assert_allclose(r, ref, atol=1e-12)  # float64 rounding
    np.testing.assert_allclose(np.asarray(ppr.quat_to_matrix(-q)), r, atol=1e-15)
    for i in range(3):
        np.testing.assert_allclose(np.abs(matrix_to_quat(r[i])), np.abs(q[i]), atol=1e-12)
    q12 = np.asarray(quat_multiply(q[0], q[1]))
    np.testing.assert_allclose(np.asarray(ppr.quat_to_matrix(q12)), r[0] @ r[1], atol=1e-12)


def test_rotation_host_and_traceable_forms_agree():
    """The host (NumPy) and traceable (JAX) forms of each rotation formula agree to float64
    rounding, and each is the closed form: R(exp(w/2)) is Rodrigues' matrix of the rotation
    vector w, R(q1 q2) = R(q1) R(q2), and the angle between q1 and q2 is the angle of
    R(q1)^T R(q2), ``acos((tr - 1) / 2)``, down to 1e-7 deg where that acos has lost all
    digits (the atan2 form stays accurate)."""
    from ppr.geometry import (
        quat_angle_deg,
        quat_from_rotvec,
        quat_from_rotvec_host,
        quat_multiply_host,
        quat_to_matrix_host,
    )

    rng = np.random.default_rng(7)
    q = rng.normal(size=(50, 4))
    r = quat_to_matrix_host(q)
    np.testing.assert_allclose(r, np.asarray(ppr.quat_to_matrix(q)), atol=1e-15)
    q12 = quat_multiply_host(q[:25], q[25:])
    np.testing.assert_allclose(quat_to_matrix_host(q12), r[:25] @ r[25:], atol=1e-14)
    np.testing.assert_allclose(q12, np.asarray(quat_multiply(q[:25], q[25:])), atol=1e-15)
    w = rng.normal(size=(50, 3)) * rng.uniform(0, 3, (50, 1))
    w[0] = 0.0
    w[1] = [1e-9, -2e-9, 0.5e-9]
    qw = quat_from_rotvec_host(w)
    np.testing.assert_allclose(qw, np.asarray(quat_from_rotvec(w)), atol=1e-15)
    a = np.linalg.norm(w, axis=1)
    k = np.where(a[:, None] > 0, w / np.where(a > 0, a, 1.0)[:, None], 0.0)
    z = np.zeros(len(k))
    kx = np.stack(  # the cross-product matrix [k]x
        [
            np.stack([z, -k[:, 2], k[:, 1]], -1),
            np.stack([k[:, 2], z, -k[:, 0]], -1),
            np.stack([-k[:, 1], k[:, 0], z], -1),
        ],
        -2,
    )
    rod = np.eye(3) + np.sin(a)[:, None, None] * kx + (1 - np.cos(a))[:, None, None] * (kx @ kx)
    np.testing.assert_allclose(quat_to_matrix_host(qw), rod, atol=1e-14)
    rel = np.einsum("nji,njk->nik", r[:25], r[25:])
    tr = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    np.testing.assert_allclose(quat_angle_deg(q[:25], q[25:]), np.degrees(np.arccos(tr)), atol=1e-6)
    tiny = quat_multiply_host(quat_from_rotvec_host([0.0, 0.0, np.radians(1e-7)]), q[2])
    np.testing.assert_allclose(quat_angle_deg(q[2], tiny), 1e-7, rtol=1e-6)


def test_quaternion_validation():
    with pytest.raises(ValueError, match=r"Pose.quaternion must be a unit quaternion.*norm 2.0"):
        ppr.Pose([2.0, 0, 0, 0])
    with pytest.raises(ValueError, match="must be finite"):
        check_quaternion([np.nan, 0, 0, 1])
    with pytest.raises(ValueError, match="shape"):
        check_quaternion([1.0, 0, 0])
    # within tolerance: normalized, either sign
    np.testing.assert_allclose(check_quaternion([-1.0005, 0, 0, 0]), [-1, 0, 0, 0])


# ----------------------------------------------------------------------------- visibility


def test_barycentric_samples_integrate_linear_exactly():
    for k in (1, 2, 3, 5):
        b = barycentric_samples(k)
        assert b.shape == (k * k, 3)
        np.testing.assert_allclose(b.sum(1), 1.0)
        np.testing.assert_allclose(b.mean(0), [1 / 3] * 3, atol=1e-15)  # centroid
        assert (b > 0).all()


def _two_plates(offset_x):
    """Front plate (1 x 1 at z = 1) and back plate (1 x 1 at z = 0, 4x4 subdivided)."""
    front = shapes.plate(1.0, part="front")
    front = ppr.Mesh(np.asarray(front.vertices) + [offset_x, 0, 1.0], front.faces, None, ("front",))
    back = shapes.plate(1.0, subdivisions=4, part="back")
    return ppr.geometry._mesh.concatenate([front, back])


def test_hidden_plate_gets_zero_and_half_hidden_half():
    caster = VisibilityCaster(_two_plates(0.0), 16)
    assert caster.backend == "embree"
    f = caster.fractions([0, 0, 1.0])
    np.testing.assert_array_equal(f[:2], 1.0)
    np.testing.assert_array_equal(f[2:], 0.0)
    # front plate shifted by half its width: half of the back plate (its 4x4 cells split on
    # the cell boundary x = 0) is lit
    f = VisibilityCaster(_two_plates(0.5), 16).fractions([0, 0, 1.0])
    back = f[2:]
    area = 1.0 / 32
    assert back.sum() * area == pytest.approx(0.5, abs=1e-12)
    # oblique (monostatic) view along (0.3, 0, 1): the front plate hides x in [-0.8, 0.2] of
    # the back plate, leaving 0.3 m^2 lit; the shadow edge x = 0.2 cuts a column of cells,
    # which the 8 x 8 sub-triangle pattern resolves to within its spacing (tolerance 0.01)
    caster = VisibilityCaster(_two_plates(0.0), 64)
    f = caster.fractions([0.3, 0, 1.0])
    assert f[2:].sum() * area == pytest.approx(0.3, abs=0.01)
    assert ((f[2:] > 0) & (f[2:] < 1)).any()  # partial facets
    # receiver straight above: every lit point of the back plate is hidden from it
    f = caster.fractions([0.3, 0, 1.0], [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(f[2:], 0.0)


def test_back_faces_culled_and_self_shadowing_panels():
    m = shapes.cubesat_with_panels(3)
    caster = VisibilityCaster(m, 9)
    u = np.array([1.0, 1.0, 0.2])
    f = caster.fractions(u)
    tri = m.triangles()
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (f[n @ u <= 0] == 0).all()
    # the body's +y face is partly shadowed by the +y panel's front (light from +x+y)
    mid = np.asarray(m.material_ids)
    body_py = (mid == 0) & (n[:, 1] > 0.5 * np.linalg.norm(n, axis=1))
    assert 0.0 < f[body_py].mean() < 1.0


def test_visibility_rejects_non_square_samples():
    with pytest.raises(ValueError, match="perfect square"):
        VisibilityCaster(shapes.plate(), 10)


@pytest.mark.parametrize(
    "name, params, needle",
    [
        ("sphere", {"subdivisions": 1.9}, "subdivisions must be an integer >= 0, got 1.9"),
        ("sphere", {"subdivisions": -2}, "subdivisions must be an integer >= 0, got -2"),
        ("cylinder", {"sections": 2}, "sections must be an integer >= 3, got 2"),
        ("cone", {"sections": True}, "sections must be an integer >= 3, got True"),
        ("cylinder", {"radius": "0.25"}, "radius must be a positive finite length"),
        ("plate", {"subdivisions": 0}, "subdivisions must be an integer >= 1, got 0"),
    ],
)
def test_shape_parameters_are_refused_not_truncated(name, params, needle):
    """A fractional, boolean or too small count (a 1.9-times subdivided sphere was silently
    80 faces, a 2-sided cylinder a flat sliver) or a quoted length is an error naming it.
    (Under the suite's runtime type checks a wrong type is caught by its annotation first:
    that message names the parameter and the value too.)"""
    ((key, value),) = params.items()
    with pytest.raises(ValueError) as err:
        shapes.by_name(name, **params)
    msg = str(err.value)
    assert needle in msg or (f"'{key}'" in msg and f"Actual value: {value!r}" in msg), msg
