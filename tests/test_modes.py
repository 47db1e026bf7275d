"""Equivalent and near-equivalent attitudes (inversion._modes) and the attitude-error
helpers over a mesh's own group: zero error between equivalent attitudes, the named classes
and the meshes they stand for agree, the candidate modes of a box at known poses, and the
data of the toy facet model at every exactly equivalent attitude (range offset moved with an
off-centre body) are those of the fit, while the mirror image differs only off the block."""

from __future__ import annotations

import equinox as eqx
import numpy as np
import pytest
import trimesh
from test_refine import ToyFacetModel

import ppr
from inversion import (
    PhysicalParams,
    attitude_error_deg,
    candidate_modes,
    equivalent_attitudes,
    line_of_sight_error_deg,
    mirror_attitude,
)
from ppr.geometry import quat_multiply_host, quat_to_matrix_host

_expected = eqx.filter_jit(ToyFacetModel.expected)  # one program per toy shape


def _data(model, q, shift=0.0):
    """Toy data at attitude ``q`` (m 10, n 1.5 + 0.1i, gain 1), range offset 0.01 + shift."""
    p = PhysicalParams(q, [10.0], [1.5 + 0.1j], range_offset=0.01 + shift, gain=1.0)
    return np.asarray(_expected(model, p, model.prepare(p)))


Q0 = np.array([0.86, 0.31, -0.22, 0.35]) / np.linalg.norm([0.86, 0.31, -0.22, 0.35])
BOX = (0.1, 0.2, 0.3)


def _random_quats(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _hull():
    tm = trimesh.convex.convex_hull(np.random.default_rng(0).normal(size=(30, 3)))
    return ppr.Mesh(tm.vertices, tm.faces)


def test_attitude_error_is_zero_between_equivalent_attitudes():
    """Every exactly equivalent attitude of a box (its 4 rotations, with and without the half
    turn about the line of sight) is 0 deg from the fit modulo the box's own group, and so is
    every mirror image ``P R S`` modulo the mirror; without ``mirror`` the image is degrees
    away. The line of sight in the body frame is the same for all of them."""
    box = ppr.shapes.box(BOX)
    sym = ppr.mesh_symmetries(box)
    for q in _random_quats(4):
        eq = equivalent_attitudes(q, box)
        assert len(eq) == 8 and eq[0].label == "fit"
        qs = np.stack([m.quaternion for m in eq])
        # arccos near 1: the geodesic is resolved to ~1e-6 deg
        assert (
            attitude_error_deg(np.repeat(q[None], 8, 0), qs, mesh=box, half_turn=True).max() < 1e-5
        )
        assert line_of_sight_error_deg(np.repeat(q[None], 8, 0), qs, mesh=box).max() < 1e-5
        plain = [m.quaternion for m in eq if m.world == "identity"]
        assert attitude_error_deg(np.repeat(q[None], 4, 0), np.stack(plain), mesh=box).max() < 1e-5
        # the mirror images through every improper element (world mirror normal +y)
        r = quat_to_matrix_host(q)
        p = np.diag([1.0, -1.0, 1.0])
        for s in sym.improper:
            qm = ppr.matrix_to_quat(p @ r @ s)
            assert attitude_error_deg(q, qm, mesh=box, mirror=True)[0] < 1e-5
            assert attitude_error_deg(q, qm, mesh=box)[0] > 1.0


def test_named_classes_and_their_meshes_agree():
    """``dihedral:4`` and a 3U CubeSat's own group (D4h), ``octahedral`` and a cube's (Oh):
    the same attitude and line-of-sight errors, with and without the mirror."""
    pairs = [("dihedral:4", ppr.shapes.cubesat(3)), ("octahedral", ppr.shapes.box((0.1,) * 3))]
    a, b = _random_quats(20, 1), _random_quats(20, 2)
    for name, mesh in pairs:
        for mirror in (False, True):
            np.testing.assert_allclose(
                attitude_error_deg(a, b, name, mirror=mirror),
                attitude_error_deg(a, b, mesh=mesh, mirror=mirror),
                rtol=0,
                atol=1e-9,
            )
            np.testing.assert_allclose(
                line_of_sight_error_deg(a, b, name, mirror=mirror),
                line_of_sight_error_deg(a, b, mesh=mesh, mirror=mirror),
                rtol=0,
                atol=1e-9,
            )
    with pytest.raises(ValueError, match="either symmetry"):
        attitude_error_deg(a, b, "dihedral:4", mesh=pairs[0][1])
    with pytest.raises(ValueError, match="needs a symmetry with a mirror plane"):
        attitude_error_deg(a, b, mesh=_hull(), mirror=True)


def test_candidate_modes_of_a_box_at_known_poses():
    """A box (D2h) at the identity looks along its own +z, which lies in two of its mirror
    planes: the mirror image is the fit itself, and the half turn about the line of sight is
    the body's C2 about z: one mode, four distinct equivalent attitudes. At a generic pose:
    the fit and its mirror image (the mirror image of a named class, modulo the rotations),
    four modes when the half turn is not exact (bistatic), the fit alone without the mirror.
    A cube has 48 equivalent attitudes at a generic pose."""
    box = ppr.shapes.box(BOX)
    ident = np.array([1.0, 0.0, 0.0, 0.0])
    assert [m.label for m in candidate_modes(ident, box)] == ["fit"]
    assert len(equivalent_attitudes(ident, box)) == 4
    modes = candidate_modes(Q0, box)
    assert [m.label for m in modes] == ["fit", "mirror image"]
    assert [m.kind for m in modes] == ["fit", "mirror"] and not modes[1].exact
    ref = mirror_attitude(Q0, (0.0, 0.0, 1.0))
    assert attitude_error_deg(ref, modes[1].quaternion, "dihedral:2")[0] < 1e-5
    bistatic = candidate_modes(Q0, box, half_turn_exact=False)
    assert [m.label for m in bistatic] == [
        "fit",
        "half turn about the line of sight",
        "mirror image",
        "mirror image turned about the line of sight",
    ]
    assert [m.label for m in candidate_modes(Q0, box, mirror=False)] == ["fit"]
    cube = ppr.shapes.box((0.1, 0.1, 0.1))
    assert len(equivalent_attitudes(Q0, cube)) == 48
    assert [m.label for m in candidate_modes(Q0, cube)] == ["fit", "mirror image"]


def test_near_symmetries_are_modes_only_at_their_tolerance():
    """A box whose +x face is widened by 1e-3 of its size keeps C2v about x exactly; the
    elements that swap its x faces hold to ~1e-3 only: at tol 1e-2 they add one near-symmetry
    mode (C2 about y, and C2 about z, the same mode modulo C2 about x) and one near mirror
    image; at the default tolerance they are not modes."""
    near = _tapered_box(1e-3)
    exact = ppr.mesh_symmetries(near)
    assert exact.point_group == "C2v", exact.summary()
    assert [m.label for m in candidate_modes(Q0, near)] == ["fit", "mirror image"]
    loose = ppr.mesh_symmetries(near, tol=1e-2)
    assert loose.point_group == "D2h", loose.summary()
    modes = candidate_modes(Q0, loose)
    assert [m.kind for m in modes] == ["fit", "mirror", "near symmetry", "near mirror"]
    assert modes[2].label.startswith("near symmetry: C2 about body y (residual")
    assert not any(m.exact for m in modes[1:])
    assert [m.label for m in candidate_modes(Q0, loose, near=False)] == ["fit", "mirror image"]


def _tapered_box(frac, shift=(0.0, 0.0, 0.0)):
    """A box (BOX) whose +x face is widened in y by ``frac`` of the box's size on each side
    (a slight frustum: C2v about x, D2h to ``frac``), then shifted."""
    box = ppr.shapes.box(BOX)
    v = np.asarray(box.vertices, np.float64).copy()
    size = 0.5 * np.linalg.norm(BOX)
    plus = v[:, 0] > 0
    v[plus, 1] += np.sign(v[plus, 1]) * frac * size
    return ppr.Mesh(v + np.asarray(shift), box.faces)


def _toy(mesh, n_bins=64):
    """The toy facet model of tests/test_refine.py on a mesh's flat sides (one facet per side:
    area-weighted centre, total area), so that any triangulation gives the same facets."""
    tri = mesh.triangles()
    cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cr, axis=1)
    nrm = cr / (2 * area[:, None])
    key = np.round(nrm, 6)
    _, side = np.unique(key, axis=0, return_inverse=True)
    side = side.ravel()
    k = side.max() + 1
    a = np.bincount(side, area, k)
    cen = (
        np.stack([np.bincount(side, area * tri.mean(1)[:, i], k) for i in range(3)], 1) / a[:, None]
    )
    n = np.stack([np.bincount(side, nrm[:, i], k) for i in range(3)], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return ToyFacetModel(
        normals=n,
        centers=cen,
        areas=a / a.max(),
        mat_ids=np.zeros(k, np.int32),
        bins=np.linspace(-0.4, 0.4, n_bins),
        sigma_r=0.01,
    )


def test_exact_modes_give_the_fits_data_and_the_mirror_differs_off_the_block():
    """Physics of the modes on the toy facet model (Blinn-Phong facets with Fresnel Mueller
    matrices, 16 PSG x PSA channels) of a box moved off the body origin: at every exactly
    equivalent attitude, with the range offset moved by the mode's ``range_shift``, the data
    are the fit's in every channel and bin (to rounding); without the shift they are not. At
    the mirror image the four channels whose states are H or V (blind to the off-block
    Mueller elements) equal the fit's, the others do not. An attitude 10 deg away differs."""
    mesh = _tapered_box(0.0, shift=(0.03, -0.02, 0.05))
    model = _toy(mesh)

    def data(q, shift=0.0):
        return _data(model, q, shift)

    ref = data(Q0)
    scale = np.abs(ref).max()
    eq = equivalent_attitudes(Q0, mesh)
    assert len(eq) == 8 and max(abs(m.range_shift) for m in eq) > 0.02
    for m in eq:
        # float64 facet sums: identical to rounding
        np.testing.assert_allclose(
            data(m.quaternion, m.range_shift), ref, rtol=0, atol=1e-12 * scale
        )
    moved = [m for m in eq if abs(m.range_shift) > 0.02]
    assert np.abs(data(moved[0].quaternion) - ref).max() > 0.1 * scale
    modes = candidate_modes(Q0, mesh)
    img = data(modes[1].quaternion, modes[1].range_shift).reshape(4, 4, -1)  # (PSG, PSA, bin)
    hv = np.ix_([0, 1], [0, 1])
    np.testing.assert_allclose(img[hv], ref.reshape(4, 4, -1)[hv], rtol=0, atol=1e-12 * scale)
    assert np.abs(img - ref.reshape(4, 4, -1)).max() > 1e-3 * scale
    off = ppr.quat_from_axis_angle([0.3, 0.8, 0.1], np.radians(10.0))
    assert np.abs(data(quat_multiply_host(off, Q0)) - ref).max() > 0.01 * scale


def test_near_mode_mismatch_grows_as_the_square_of_the_asymmetry():
    """On the toy facet model of a box tapered by ``frac`` of its size, the data at the near
    mode (the fit's attitude mapped by the near C2 about y, with its range shift) differ
    from the fit's by a squared error that grows as ``frac^2`` (the data are smooth in the
    geometry): 9x for a 3x taper, within 10%; at an exact equivalent the error is 0."""
    chi2 = []
    for frac in (1e-3, 3e-3):
        mesh = _tapered_box(frac)
        model = _toy(mesh)
        ref = _data(model, Q0)
        modes = candidate_modes(Q0, ppr.mesh_symmetries(mesh, tol=1e-2))
        near = [m for m in modes if m.kind == "near symmetry"]
        assert len(near) == 1
        diff = _data(model, near[0].quaternion, near[0].range_shift) - ref
        chi2.append(float(np.sum(diff**2)))
        exact = equivalent_attitudes(Q0, mesh)[1]
        diff = _data(model, exact.quaternion, exact.range_shift) - ref
        assert np.sum(diff**2) < 1e-20 * chi2[-1]
    # first order in frac: chi^2 ratio 9 up to the second-order term (3 frac ~ 1e-2)
    assert abs(chi2[1] / chi2[0] / 9.0 - 1.0) < 0.1, chi2
