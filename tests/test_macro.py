"""Macro double bounce (ppr/pulse/_macro.py): glossy dihedrals against an independent retro-area
calculation, broad pairs against the exact Lambertian view factor, tessellation independence,
polarization (handedness, roll), convex meshes, the CubeSat's panel-body folds, gradients and
float32.

Cost: every model-BRDF check goes through one compiled macro program per dtype (fixed
capacities ``CAPS``/``NODES``, bins and terms), the gradient check through one forward-mode
program; the Lambertian checks share a cheap stand-in program.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ppr
from ppr.geometry import shapes
from ppr.geometry._mesh import concatenate
from ppr.pulse import _macro
from ppr.pulse._pulse import _macro_jit, lambertian_mueller, stack_materials

N_BINS = 128
WIDTH = 0.02  # 2.56 m gate: holds a 1 m dihedral seen from any direction
CAPS = (64, 128, 8)  # macro triangles, glossy pairs, broad pairs (padded: one program)
NODES = (12, 48)  # broad pairs' points and directions (level <= 2, rule 3, order 4)
AL = complex(0.94, 6.42)  # aluminium at 532 nm (configs/materials.toml)
PEC = complex(1.0, 1000.0)  # near-perfect conductor: |r_s|, |r_p| within 2e-3 of 1


def _dihedral(n=1, a=1.0, length=1.0):
    """90 deg dihedral: face A in z = 0 (y in [0, a], normal +z), face B in y = 0 (z in [0, a],
    normal +y), fold along x (length ``length``), each face ``n x n`` cells; parts a, b and an
    unused third (so that every scene stacks three materials, as the CubeSat's)."""
    p = shapes.plate(length, a, subdivisions=n)
    v = np.asarray(p.vertices) + [0, a / 2, 0]
    face_a = ppr.Mesh(v, p.faces, None, ("a",))
    vb = np.stack([v[:, 0], v[:, 2], v[:, 1]], 1)
    face_b = ppr.Mesh(vb, np.asarray(p.faces)[:, ::-1], None, ("b",))
    m = concatenate([face_a, face_b])
    return ppr.Mesh(m.vertices, m.faces, m.material_ids, ("a", "b", "unused"))


def _retro_dir(phi):
    """Unit direction in the dihedral's cross-section at ``phi`` from its bisector."""
    return np.array([0.0, np.sin(np.pi / 4 + phi), np.cos(np.pi / 4 + phi)])


def _scene(mesh, u, mats, q=(1.0, 0, 0, 0), x_ref=(1.0, 0, 0)):
    return ppr.Scene(
        mesh,
        tuple(mats),
        ppr.Pose(np.asarray(q, float)),
        ppr.Sensor.make(-np.asarray(q_rotate(q, u)), x_ref),
        ppr.Pulse.gaussian(100e-12),
        ppr.RangeBins.centred(WIDTH, N_BINS, 1e6),
        16,
    )


def q_rotate(q, v):
    return np.asarray(ppr.quat_to_matrix(np.asarray(q, float))) @ np.asarray(v)


def _pairs(scene, options=None, dtype=jnp.float64, brdf=ppr.mueller_brdf, glossy=None):
    """Host pairs of ``scene`` at the shared programs' capacities; ``glossy``: every part
    glossy (True) or broad (False) whatever the BRDF (default: by the exponents)."""
    rot = np.asarray(ppr.quat_to_matrix(np.asarray(scene.pose.quaternion, float)))
    u_in = rot.T @ np.asarray(scene.sensor.laser_dir, float)
    u_out = rot.T @ np.asarray(scene.sensor.receiver_dir, float)
    opts = options or _macro.MacroOptions(rule=3)
    m = _macro.part_exponents(scene.materials)
    gl = _macro.glossy_parts(m, brdf, opts.glossy_m) if glossy is None else [glossy] * len(m)
    return _macro.macro_pairs(
        _macro.macro_geometry(scene.mesh, plates=opts.plates),
        ppr.VisibilityCaster(scene.mesh, scene.vis_samples),
        u_in,
        u_out,
        gl,
        m,
        **opts.pair_options(),
        bins=(float(scene.pulse.sigma_range), WIDTH, N_BINS),
        window=0,
        capacities=CAPS,
        node_capacity=NODES,
        mixed=True,
        dtype=dtype,
    )


def _double(scene, options=None, dtype=jnp.float64, brdf=ppr.mueller_brdf):
    """Macro double bounce (4, 4, B) through the shared program."""
    pairs, info = _pairs(scene, options, dtype, brdf)
    p = ppr.double_bounce(scene, dtype=dtype, pairs=pairs, brdf=brdf)
    return np.asarray(p.data), info


def _binned_pulse(r0, sigma):
    """Bin contents of a unit return at one-way range ``r0`` (Gaussian pulse of ``sigma``)."""
    from scipy.stats import norm

    edges = -0.5 * WIDTH * N_BINS + WIDTH * np.arange(N_BINS + 1)
    return np.diff(norm.cdf((edges - r0) / sigma))


def _lobe_reference(n, m, u, normals):
    """Brute-force two-bounce lobe at retro-reflection (:func:`ppr.pulse._macro.two_bounce_lobe`,
    float64), in the frames of ``_scene``'s sensor (x reference projected off ``u``)."""
    x_ref = np.array([1.0, 0, 0]) - u[0] * u
    x_ref /= np.linalg.norm(x_ref)
    return _macro.two_bounce_lobe(*normals, u, u, ppr.Material(n, m), x_ref, x_ref)


# ----------------------------------------------------------------------------- glossy


def test_glossy_dihedral_matches_retro_area_times_two_bounce_lobe():
    """A 1 m aluminium dihedral seen 10 deg off its bisector: its whole double bounce is
    retro-reflected from the area 2 a L sin(45 deg - |phi|) (both orders of the bounces), so
    M = A_retro G with G the two-bounce lobe at retro-reflection, here by brute-force
    quadrature of the BRDF over directions (independent of the Laplace convolution). All 16
    elements agree to the Laplace method's O(1/m) (measured +3.2e-4, +3.1e-5, +3.1e-6 of M00
    for m = 1e3, 1e4, 1e5: within 1/m), depolarization (M00 - M11) included; the return sits
    at the fold's range (corner property: every retro path has the fold's length); the result
    is the same for a finer mesh (plates merged) and, without merging, for 8-triangle faces
    pair by pair (the clipped overlaps tile)."""
    phi = np.radians(10.0)
    u = _retro_dir(phi)
    area = 2 * 1.0 * 1.0 * np.sin(np.pi / 4 - phi)
    n_a, n_b = np.array([0, 0, 1.0]), np.array([0, 1.0, 0])
    for m in (1e3, 1e4, 1e5):
        tol = 1.0 / m  # the Laplace method's O(1/m), 3x the measured error
        mats = [ppr.Material(AL, m)] * 3
        got, info = _double(_scene(_dihedral(), u, mats))
        assert info["glossy"] == 8 and info["broad"] == 0  # 2 x 2 triangles, both orders
        ref = area * _lobe_reference(AL, m, u, (n_a, n_b))
        # every element (diattenuation, retardance, depolarization) to tol of M00
        np.testing.assert_allclose(got.sum(-1), ref, rtol=0, atol=tol * ref[0, 0])
        assert (
            ref[0, 0] - ref[1, 1] > 5 * tol * ref[0, 0]
        )  # the depolarization (~7.5/m) is resolved
        if m == 1e4:
            # the fold passes through the origin: a pulse at range 0, to rounding
            sigma = float(ppr.Pulse.gaussian(100e-12).sigma_range)
            np.testing.assert_allclose(
                got[0, 0], got[0, 0].sum() * _binned_pulse(0.0, sigma), atol=1e-9 * got.max()
            )
            fine, _ = _double(_scene(_dihedral(n=4), u, mats))
            np.testing.assert_allclose(fine, got, rtol=0, atol=1e-12 * got.max())  # rounding
            loose, info2 = _double(
                _scene(_dihedral(n=2), u, mats), _macro.MacroOptions(rule=3, plates=False)
            )
            assert info2["glossy"] > 8  # many triangle pairs, each a clipped overlap
            np.testing.assert_allclose(loose, got, rtol=0, atol=1e-10 * got.max())


# ----------------------------------------------------------------------------- broad


def _squares():
    """Two 0.2 m squares in an L (floor z = 0, x in [0, 0.2]; wall x = 0, z in [0, 0.2])."""
    rot = np.asarray(ppr.quat_to_matrix(ppr.quat_from_axis_angle([0, 1, 0], np.pi / 2)))
    a = shapes.plate(0.2)
    a = ppr.Mesh(np.asarray(a.vertices) + [0.1, 0, 0], a.faces, None, ("floor",))
    b = shapes.plate(0.2)
    b = ppr.Mesh(np.asarray(b.vertices) @ rot.T + [0, 0, 0.1], b.faces, None, ("wall",))
    m = concatenate([a, b])
    return ppr.Mesh(m.vertices, m.faces, m.material_ids, ("floor", "wall", "unused"))


def _square_view_factor():
    """View factor of two unit squares sharing an edge at right angles (Howell, C-14)."""
    w = h = 1.0
    a = w * np.arctan(1 / w) + h * np.arctan(1 / h) - np.hypot(w, h) * np.arctan(1 / np.hypot(w, h))
    s = w * w + h * h
    b = np.log(
        (1 + w * w)
        * (1 + h * h)
        / (1 + s)
        * (w * w * (1 + s) / ((1 + w * w) * s)) ** (w * w)
        * (h * h * (1 + s) / ((1 + h * h) * s)) ** (h * h)
    )
    return (a + b / 4) / (np.pi * w)


def test_broad_pairs_converge_to_the_lambertian_view_factor():
    """Lambertian (1/pi) squares in an L, fully lit and seen: the double bounce is
    (1/pi) A F [cos_in(A) cos_out(B) + cos_in(B) cos_out(A)] with the analytic view factor F.
    The point-to-solid-angle nodes (:func:`ppr.pulse._macro.broad_nodes`) integrate it with errors
    1.6e-3, 8.2e-5, 2.4e-6 for 1, 2, 4 sub-triangles per edge (rule 3, order 16): far faster
    than first order (centroid or area-to-area Gauss rules stop there, at the 1/r^2 of the
    shared edge). Through the kernel (level 2, order 12: 7.9e-5) the profile total agrees,
    and it is reciprocal (laser and receiver swapped) to the same accuracy."""
    ui = np.array([1.0, 0.3, 1.0]) / np.linalg.norm([1.0, 0.3, 1.0])
    uo = np.array([0.7, -0.2, 1.0]) / np.linalg.norm([0.7, -0.2, 1.0])
    expect = (ui[2] * uo[0] + ui[0] * uo[2]) * 0.04 * _square_view_factor() / np.pi
    mesh = _squares()
    geom = _macro.macro_geometry(mesh)
    i, j = geom.candidates.T
    assert len(i) == 8  # two triangles per square, both orders

    def node_sum(level, order):  # the quadrature alone: sum of w (n_I.k) / pi^2
        _, k, w, _ = _macro.broad_nodes(geom.tri[i], geom.tri[j], level, 3, order)
        cos = (geom.normals[i] @ ui) * (geom.normals[j] @ uo)
        return np.einsum("p,pqd,pqdk,pk->", cos, w, k, geom.normals[i]) / np.pi**2

    errs = [abs(node_sum(lv, 16) / expect - 1) for lv in (1, 2, 4)]
    assert errs[2] < 1e-5 and errs[1] < errs[0] / 8 and errs[2] < errs[1] / 8, errs

    def total(u_in, u_out):
        sc = ppr.Scene(
            mesh,
            (ppr.Material(1.5, 10.0),) * 3,
            ppr.Pose(np.array([1.0, 0, 0, 0])),
            ppr.Sensor.make(-u_in, (0, 1.0, 0), receiver_dir=u_out),
            ppr.Pulse.gaussian(100e-12),
            ppr.RangeBins.centred(WIDTH, N_BINS, 1e6),
            4,
        )
        p = ppr.double_bounce(
            sc,
            brdf=lambertian_mueller,
            dtype=jnp.float64,
            options=_macro.MacroOptions(level=2, rule=3, order=12),
        )
        return float(p.total[0, 0])

    assert total(ui, uo) == pytest.approx(expect, rel=2e-4)  # measured 7.9e-5
    assert total(uo, ui) == pytest.approx(expect, rel=2e-4)  # the other surface first


def test_rough_aluminium_dihedral_converges_and_ignores_the_tessellation():
    """m = 20 aluminium (every pair broad): the quadrature levels converge (measured 0.5314,
    0.5245 at levels 1, 2 with rule 3, order 4; 0.5238 at level 4, order 8 in
    bench/bench_macro.py), and a mesh refined from 1 to 4 x 4 cells per face gives the same
    result to rounding (its faces merge into the same plates)."""
    u = _retro_dir(np.radians(10.0))
    mats = [ppr.Material(AL, 20.0)] * 3
    coarse, info = _double(_scene(_dihedral(1), u, mats), _macro.MacroOptions(level=1, rule=3))
    assert info["broad"] == 8 and info["glossy"] == 0
    fine, _ = _double(_scene(_dihedral(4), u, mats), _macro.MacroOptions(level=2, rule=3))
    finer, _ = _double(_scene(_dihedral(1), u, mats), _macro.MacroOptions(level=2, rule=3))
    np.testing.assert_allclose(fine, finer, rtol=0, atol=1e-12 * finer.max())
    c, f = coarse.sum(-1)[0, 0], fine.sum(-1)[0, 0]
    assert abs(c / f - 1) < 0.02, (c, f)  # level 1 against 2: the quadrature's step
    assert abs(f / 0.5238 - 1) < 0.005, f  # the converged value (bench), to level 2's error
    assert fine.sum(-1)[3, 3] > 0.8 * f  # handedness kept at m = 20 too


# ----------------------------------------------------------------------------- polarization


def test_dihedral_keeps_handedness_plate_reverses_it_and_roll_turns_linear_by_two_alpha():
    """Circular polarization: the dihedral's two reflections keep its handedness (M33 > 0),
    one reflection (a plate at normal incidence) reverses it (M33 = -M00). Rolling the
    dihedral by alpha about the line of sight maps M to R(a) M R(a) in the sensor frames
    (the transmitted and received beams travel in opposite senses) exactly, so a near-perfect
    conductor's dihedral (M ~ M00 diag(1, 1, 1, 1)) turns horizontal polarization by 2 alpha."""
    u = _retro_dir(np.radians(10.0))
    al = [ppr.Material(AL, 1e4)] * 3
    m0, _ = _double(_scene(_dihedral(), u, al))
    tot0 = m0.sum(-1)
    assert tot0[3, 3] > 0.85 * tot0[0, 0]
    plate = np.asarray(
        ppr.mueller_brdf(u, u, u, ppr.Material(AL, 1e4), terms=("single",), frame_in=[1.0, 0, 0])
    )
    assert plate[3, 3] == pytest.approx(-plate[0, 0], rel=1e-12)
    pec = [ppr.Material(PEC, 1e4)] * 3
    base, _ = _double(_scene(_dihedral(), u, pec))
    for alpha in (np.radians(15.0), np.radians(35.0)):
        q = np.asarray(ppr.quat_from_axis_angle(u, alpha))  # roll about the line of sight
        for mats, ref in ((al, tot0), (pec, base.sum(-1))):
            got, _ = _double(_scene(_dihedral(), u, mats, q=q))
            rot = np.asarray(ppr.mueller_rotator(np.cos(2 * alpha), np.sin(2 * alpha)))
            tot = got.sum(-1)
            # both frames turn by the same angle (opposite beams): float64 rounding
            assert np.allclose(tot, rot @ ref @ rot, atol=1e-10 * ref[0, 0]) or np.allclose(
                tot, rot.T @ ref @ rot.T, atol=1e-10 * ref[0, 0]
            )
        s_out = tot @ np.array([1.0, 1.0, 0, 0])  # horizontal in
        angle = 0.5 * np.arctan2(s_out[2], s_out[1])
        # the conductor's residual retardance (|r_s|, |r_p| 2e-3 from 1) bends it by ~1e-3
        assert abs(abs(angle) - 2 * alpha) < 5e-3, (angle, alpha)


def test_mirror_image_attitude_gives_the_mirrored_double_bounce():
    """Parity: the dihedral is symmetric under x -> -x (sigma); at the attitude P R sigma (P
    the world mirror through the plane of the line of sight and the sensor's x reference) the
    scene is the mirror image of the one at R, so M' = D M D, D = diag(1, 1, -1, -1), in
    every bin (float64 rounding: the clipped overlaps are mirror images, the visibility is 1)."""
    from scipy.spatial.transform import Rotation

    u = _retro_dir(np.radians(8.0)) + np.array([0.05, 0, 0])
    u /= np.linalg.norm(u)
    align = Rotation.align_vectors([[0, 0, 1.0]], [u])[0].as_matrix()  # body u -> world z
    rot = Rotation.from_rotvec([0, 0, 0.7]).as_matrix() @ align
    sigma, world = np.diag([-1.0, 1.0, 1.0]), np.diag([1.0, -1.0, 1.0])
    mats = [ppr.Material(AL, 1e4)] * 3
    out = []
    for r in (rot, world @ rot @ sigma):
        q = np.asarray(ppr.geometry._rotation.matrix_to_quat(r))
        out.append(_double(_scene(_dihedral(), r.T @ np.array([0, 0, 1.0]), mats, q=q))[0])
    d = np.diag([1.0, 1.0, -1.0, -1.0])
    np.testing.assert_allclose(
        out[1], np.einsum("ij,jkb,kl->ilb", d, out[0], d), rtol=0, atol=1e-10 * out[0].max()
    )
    assert np.abs(out[0][:2, 2:]).max() > 1e-3 * out[0].max()  # the off-block elements differ


# ----------------------------------------------------------------------------- where it applies


def test_convex_meshes_have_no_pairs_and_unchanged_profiles():
    """A convex mesh has no two surfaces facing each other, so its profile is unchanged (to
    the bit) when the double bounce is switched on; the CubeSat with panels is not convex."""
    for mesh in (
        shapes.box((0.1, 0.2, 0.3)),
        shapes.sphere(0.3, subdivisions=2),
        shapes.cylinder(),
    ):
        assert _macro.macro_geometry(mesh).convex
    assert not _macro.macro_geometry(shapes.cubesat_with_panels(3)).convex
    mesh = shapes.box((0.1, 0.2, 0.3))
    sc = ppr.Scene(
        mesh,
        (ppr.Material(1.5, 10.0),),
        ppr.Pose(np.array([0.9, 0.3, -0.2, 0.25]) / np.linalg.norm([0.9, 0.3, -0.2, 0.25])),
        ppr.Sensor.make((0, 0, -1.0)),
        ppr.Pulse.gaussian(100e-12),
        ppr.RangeBins.centred(0.005, 128, 1e6),
        4,
    )
    on = ppr.simulate(sc, brdf=lambertian_mueller, multibounce=True)
    off = ppr.simulate(sc, brdf=lambertian_mueller, multibounce=False)
    np.testing.assert_array_equal(np.asarray(on.data), np.asarray(off.data))
    assert float(on.total[0, 0]) > 0


def test_cubesat_panels_gain_the_dihedral_return_at_the_fold_range():
    """The 3U CubeSat with deployed panels seen along the bisector of a panel's cells (+x) and
    the body side (+y) they meet, 5 deg off it in the fold's cross-section, everything polished
    aluminium (m = 1e4, so the single bounces of these faces, 40 and 50 deg from their normals,
    send nothing back): the dihedral retro-reflects a pulse at the fold's range (one-way, the
    fold point's depth -x.u: every retro path has its length) carrying the retro area
    2 a L sin(45 deg - |phi|) (a = 49 mm of body side in front of the cells, L = 0.34 m: the
    0.3 m panel is long enough for both orders) times the two-bounce lobe at retro-reflection."""
    mesh = shapes.cubesat_with_panels(3, panel_span=0.3)
    phi = np.radians(5.0)
    u = np.array([np.cos(np.pi / 4 - phi), np.sin(np.pi / 4 - phi), 0.0])
    got, info = _double(_scene(mesh, u, [ppr.Material(AL, 1e4)] * 3))
    assert info["glossy"] >= 2  # cells -> body side and back
    fold = np.array([0.001, 0.05, 0.0])  # cells (x = t/2) meet the body side (y = 0.05)
    sigma = float(ppr.Pulse.gaussian(100e-12).sigma_range)
    pulse = _binned_pulse(-fold @ u, sigma)
    np.testing.assert_allclose(got[0, 0], got[0, 0].sum() * pulse, atol=1e-9 * got.max())
    area = 2 * 0.049 * 0.34 * np.sin(np.pi / 4 - phi)
    lobe = _lobe_reference(AL, 1e4, u, (np.array([0, 1.0, 0]), np.array([1.0, 0, 0])))
    # Laplace 1/m and the cells' 1 mm edge strip sampled by 16 points per fan triangle
    np.testing.assert_allclose(got.sum(-1), area * lobe, rtol=0, atol=2e-3 * area * lobe[0, 0])


def test_compacted_pairs_give_the_same_profile():
    """``MacroPairs.compact`` (the sampler's fixed pairs) drops only dead padding: on the
    CubeSat with panels (a random view, all polished aluminium: glossy pairs only; aluminium
    with matte paint on the panels' backs: glossy-broad pairs, whose broad side takes the full
    BRDF) the profile through the compacted pairs equals the padded one to float64 rounding,
    the dead broad slots are gone, and the full-BRDF path is kept exactly when a live pair
    has a broad side. All-matte parts: broad pairs only, the glossy slots go."""
    u = np.array([-0.94988454, -0.31244442, 0.00989135])
    mesh = shapes.cubesat_with_panels(3, panel_span=0.3)
    al, paint = ppr.Material(AL, 1e4), ppr.Material(2.668, 2.0)
    for mats, mixed in (([al] * 3, False), ([al, al, paint], True)):
        sc = _scene(mesh, u, mats)
        pairs, _ = _pairs(sc)
        small = pairs.compact()
        assert pairs.n_glossy == small.n_glossy == 8 and pairs.n_broad == 0
        assert small.g_i.shape == (8,) and small.r_i.shape == (0,) and small.mixed is mixed
        a = np.asarray(ppr.double_bounce(sc, pairs=pairs).data)
        b = np.asarray(ppr.double_bounce(sc, pairs=small).data)
        assert a.max() > 0
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-14 * a.max())
    pairs, _ = _pairs(_scene(mesh, u, [paint] * 3))
    small = pairs.compact()
    assert pairs.n_broad == small.n_broad == 8 and small.g_i.shape == (0,)
    np.testing.assert_array_equal(np.asarray(small.r_w), np.asarray(pairs.r_w))


# ----------------------------------------------------------------------------- gradients, dtype


def _macro_total(q, m, pairs, scene, dtype, weights):
    """Weighted sum of the macro profile (stand-in BRDF for the broad sides: a cheap program;
    the glossy pairs' Laplace convolution, Fresnel chain and clipping do not use the BRDF)."""
    mats = stack_materials([ppr.Material(AL, m)] * 3)
    mats = jax.tree_util.tree_map(
        lambda a: a.astype(jnp.result_type(dtype, jnp.complex64) if jnp.iscomplexobj(a) else dtype),
        mats,
    )
    sensor = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), scene.sensor)
    out = _macro_jit(
        pairs,
        ppr.Pose(q.astype(dtype)),
        mats,
        sensor,
        jnp.asarray(float(scene.pulse.sigma_range), dtype),
        jnp.asarray(-0.5 * WIDTH * N_BINS, dtype),
        jnp.asarray(WIDTH, dtype),
        n_bins=N_BINS,
        projection=None,
        brdf=lambertian_mueller,
    )
    return jnp.sum(out * weights.astype(dtype))


def test_gradients_match_finite_differences_and_float32_matches_float64():
    """A dihedral at a general attitude (rolled, tilted): the derivatives of a weighted sum of
    the 16 profiles with respect to the attitude (three tangent directions) and m, glossy
    pairs (m = 3e3: image method, clipped overlaps moving with the pose, Laplace lobes,
    Fresnel chain) and broad pairs (m = 30: quadrature), equal central finite differences with
    the pairs held fixed; float32 agrees with float64."""
    # off the dihedral's cross-section: the image of J's end edges does not fall on I's (where
    # the image method's clipped area has a kink, smoothed in reality by the lobes' spread)
    u = _retro_dir(np.radians(8.0)) + np.array([0.05, 0, 0])
    u /= np.linalg.norm(u)
    q0 = np.asarray(ppr.quat_from_axis_angle(np.array([0.3, -0.2, 1.0]), 0.4))
    w = jnp.asarray(np.random.default_rng(0).normal(size=(16, N_BINS)))
    for m, glossy in ((3e3, True), (30.0, False)):
        scene = _scene(_dihedral(), u, [ppr.Material(AL, m)] * 3, q=q0)
        pairs, info = _pairs(scene, glossy=glossy)
        assert info["glossy" if glossy else "broad"] == 8

        def f(q, mm, pairs=pairs, scene=scene):
            q = q / jnp.linalg.norm(q)  # finite differences leave the unit sphere
            return _macro_total(q, mm, pairs, scene, jnp.float64, w)

        q = jnp.asarray(q0)
        mm = jnp.asarray(m)
        for dq, dm in (
            ([0, 1.0, 0, 0], 0.0),
            ([0, 0, 1.0, 0], 0.0),
            ([0, 0, 0, 1.0], 0.0),
            ([0.0, 0, 0, 0], 1.0),
        ):
            dq, dm = jnp.asarray(dq), jnp.asarray(dm) * m * 1e-2
            val, tan = jax.jvp(f, (q, mm), (dq, dm))
            assert np.isfinite(float(tan))
            h = 1e-6
            fd = (f(q + h * dq, mm + h * dm) - f(q - h * dq, mm - h * dm)) / (2 * h)
            # central differences of a smooth function: truncation h^2, rounding 1e-16 / h
            assert float(tan) == pytest.approx(float(fd), rel=1e-6, abs=1e-8 * abs(float(val)))
        pairs32, _ = _pairs(scene, dtype=jnp.float32, glossy=glossy)
        q32 = jnp.asarray(q0, jnp.float32)
        v32 = _macro_total(q32, jnp.float32(m), pairs32, scene, jnp.float32, w)
        assert v32.dtype == jnp.float32
        # float32 kernel: unit vectors and clipped vertices to 1e-7, lobe widths 1/sqrt(m)
        assert float(v32) == pytest.approx(float(f(q, mm)), rel=2e-4)


# ----------------------------------------------------------------------------- bad input


def test_bad_input_is_named():
    mesh = _dihedral()
    u = _retro_dir(0.1)
    sc = _scene(mesh, u, [ppr.Material(AL, 1e4)] * 3)
    with pytest.raises(ValueError, match="multibounce must be True, False or 'auto', got 'yes'"):
        ppr.simulate(sc, multibounce="yes")
    with pytest.raises(ValueError, match=r"capacities \(8, 2, 0\) are smaller than the counts"):
        _macro.pose_pairs(
            mesh,
            ppr.VisibilityCaster(mesh, 4),
            u,
            u,
            [1e4] * 3,
            ppr.mueller_brdf,
            capacities=(8, 2, 0),
        )
    with pytest.raises(ValueError, match="rule must be one of"):
        _macro.triangle_rule(1, 5)
    a, _ = _pairs(sc)
    b, _ = _macro.pose_pairs(mesh, ppr.VisibilityCaster(mesh, 4), u, u, [1e4] * 3, ppr.mueller_brdf)
    with pytest.raises(ValueError, match="build them with the same capacities"):
        ppr.stack_macro_pairs([a, b])
    assert ppr.stack_macro_pairs([a, a]).g_vis.shape == (2, CAPS[1])
    # the image method below its measured range, and knobs that are not counts
    for kw, needle in (
        ({"glossy_m": 1.0}, "glossy_m must be a number >= 100"),
        ({"glossy_m": float("nan")}, "glossy_m must be a number >= 100"),
        ({"order": 0}, "order must be an integer >= 1"),
        ({"samples": -4}, "samples must be an integer >= 1"),
        ({"samples": 10}, "samples must be a perfect square"),
    ):
        with pytest.raises(ValueError, match=needle):
            ppr.MacroOptions(**kw)


def test_database_signatures_and_inversion_model_include_the_double_bounce():
    """The signature database's function (inversion.PprSignatures) and the inversion's forward
    model (inversion.SimulatorModel) include the double bounce of a non-convex shape: both
    equal ppr.simulate (which includes it by default) projected on their channels (Lambertian
    stand-in BRDF: every pair broad)."""
    from inversion import PhysicalParams, SimulatorModel
    from inversion._noise import MeasurementModel, measure
    from inversion._ppr_adapter import PprSignatures

    mesh = shapes.cubesat_with_panels(3)
    mm = MeasurementModel.preset("stokes")
    opts = _macro.MacroOptions(order=2, rule=3)
    fn = PprSignatures(
        [mesh],
        ["aluminium"],
        [20.0],
        mm,
        n_bins=48,
        bin_width_m=0.02,
        brdf=lambertian_mueller,
        dtype=jnp.float64,
        macro_options=opts,
    )
    assert fn.multibounce and fn.sensor["model"].endswith("+macro")
    q = np.array([0.3, 0.8, 0.4, 0.33])
    q /= np.linalg.norm(q)
    zero = np.zeros(1, np.int32)
    sig = np.asarray(
        fn({"shape_id": zero, "material_id": zero, "finish_id": zero, "quat": q[None]})
    )
    mat = ppr.load_material("aluminium", 532e-9, dtype=jnp.float64)
    mat = ppr.Material(mat.n, 20.0)
    scene = ppr.Scene(
        mesh,
        (mat,) * 3,
        ppr.Pose(q),
        fn.sensor_model,
        ppr.Pulse.gaussian(fn.pulse_fwhm_s),
        fn.bins,
        vis_samples=4,
    )
    kw = dict(brdf=lambertian_mueller, dtype=jnp.float64, macro_options=opts)
    both = np.asarray(ppr.simulate(scene, **kw).data)  # the double bounce included ("auto")
    ref = np.maximum(np.asarray(measure(mm, jnp.asarray(both))), 0.0)
    # same kernels, same visibility samples; float64 round-off only
    np.testing.assert_allclose(sig[0], ref, rtol=1e-9, atol=1e-12 * ref.max())
    model = SimulatorModel(
        scene, mm.channel_matrix(), brdf=lambertian_mueller, dense=True, macro_options=opts
    )
    phys = PhysicalParams(q, [20.0] * 3, [mat.n] * 3)
    aux = model.prepare(phys)
    assert isinstance(aux, tuple) and aux[1].n_broad > 0  # panel-body pairs at this attitude
    # every pair broad (Lambertian stand-in): no glossy slots, whose dead padding would be
    # evaluated like live pairs; the broad slots at the capacity of their own count
    assert aux[1].g_i.shape == (0,) and aux[1].r_i.shape[0] == _macro._pair_capacity(aux[1].n_broad)
    got = np.asarray(model.expected(phys, aux))
    np.testing.assert_allclose(
        got, np.asarray(measure(mm, jnp.asarray(both))), rtol=1e-9, atol=1e-12 * ref.max()
    )


def test_padded_broad_slots_change_nothing_and_dead_ones_are_skipped_exactly():
    """The inversion model pads its broad pair slots to a fixed capacity (one compiled program
    for every pose and roughness); the broad block sits under a ``lax.cond`` on any live
    point. Padded slots (16 instead of 8) and a block whose points are all dead (the cond's
    skip branch) give the same counts and the same forward-mode Jacobian as the compact
    layout (no broad slots at all), to float64 round-off, with no NaN."""
    import dataclasses

    from inversion import PhysicalParams, SimulatorModel
    from inversion._noise import MeasurementModel

    mesh = shapes.cubesat_with_panels(3)
    opts = _macro.MacroOptions(order=2, rule=3)
    q = np.array([0.3, 0.8, 0.4, 0.33])
    q /= np.linalg.norm(q)
    mat = ppr.Material(0.94 + 6.42j, 20.0)
    scene = ppr.Scene(
        mesh,
        (mat,) * 3,
        ppr.Pose(q),
        ppr.Sensor.make(),
        ppr.Pulse.gaussian(100e-12),
        ppr.RangeBins.centred(0.02, 48),
        vis_samples=4,
    )
    chm = MeasurementModel.preset("copol").channel_matrix()
    model = SimulatorModel(scene, chm, brdf=lambertian_mueller, dense=True, macro_options=opts)
    phys = PhysicalParams(q, [20.0] * 3, [mat.n] * 3, range_offset=0.001, gain=1.0)
    vis, pairs = model.prepare(phys)
    assert pairs.n_broad > 0 and pairs.r_i.shape[0] == 8

    def padded(p, cap):
        extra = cap - p.r_i.shape[0]

        def pad(a, fill=0.0):
            widths = [(0, extra)] + [(0, 0)] * (a.ndim - 1)
            return jnp.pad(a, widths, constant_values=fill)

        return dataclasses.replace(
            p,
            r_i=pad(p.r_i, 0),
            r_j=pad(p.r_j, 0),
            r_x=pad(p.r_x),
            r_k=pad(p.r_k, 1.0),
            r_w=pad(p.r_w),
            r_t=pad(p.r_t),
        )

    def counts_and_jac(p):
        def f(g):
            return model.expected(dataclasses.replace(phys, gain=g[0], m=g[1:]), (vis, p))

        x = jnp.concatenate([jnp.ones(1), jnp.asarray(phys.m)])
        return np.asarray(f(x)), np.asarray(jax.jacfwd(f)(x))

    live, live_j = counts_and_jac(pairs)
    pad, pad_j = counts_and_jac(padded(pairs, 16))
    np.testing.assert_allclose(pad, live, rtol=1e-12, atol=1e-14 * live.max())
    np.testing.assert_allclose(pad_j, live_j, rtol=1e-12, atol=1e-14 * np.abs(live_j).max())
    # every broad point dead: the cond skips the block; equal to no broad slots at all
    dead = dataclasses.replace(pairs, r_w=jnp.zeros_like(pairs.r_w))
    none = dataclasses.replace(
        dead.compact(),
        g_i=dead.g_i,
        g_j=dead.g_j,
        g_kind=dead.g_kind,
        g_vis=dead.g_vis,
        mixed=dead.mixed,
    )
    assert none.r_i.shape[0] == 0
    got, got_j = counts_and_jac(dead)
    ref, ref_j = counts_and_jac(none)
    assert np.all(np.isfinite(got_j)) and np.all(np.isfinite(got))
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-14 * ref.max())
    np.testing.assert_allclose(got_j, ref_j, rtol=1e-12, atol=1e-14 * np.abs(ref_j).max())
    # and the broad pairs mattered where they were live
    assert np.abs(live - ref).max() > 1e-3 * live.max()


def test_visibility_does_not_depend_on_where_the_body_origin_is():
    """Moving every vertex 1 km from the body origin (a part exported in a vehicle's frame)
    changes no lit-and-visible fraction and no macro pair's visibility: the rays are cast in
    coordinates centred on the mesh (Embree intersects in float32; with rays lifted 4 um off
    their faces in body coordinates, a convex 3U box 70 m off shadowed itself, 1 km off it
    vanished)."""
    mesh = shapes.cubesat_with_panels(3, panel_span=0.3)
    far = ppr.Mesh(
        np.asarray(mesh.vertices, np.float64) + 1e3 * np.array([1.0, 1.0, 1.0]) / np.sqrt(3),
        mesh.faces,
        mesh.material_ids,
        mesh.parts,
    )
    u = np.array([0.3, -0.4, 0.866])
    u /= np.linalg.norm(u)
    near_f = ppr.VisibilityCaster(mesh, 16).fractions(u)
    far_f = ppr.VisibilityCaster(far, 16).fractions(u)
    assert near_f.max() == 1.0
    np.testing.assert_array_equal(far_f, near_f)
    # a convex box: every face toward u fully lit and visible
    box = shapes.box((0.1, 0.1, 0.34))
    off = ppr.Mesh(np.asarray(box.vertices, np.float64) + 1e3, box.faces)
    f = ppr.VisibilityCaster(off, 16).fractions(u)
    front = np.asarray(ppr.mesh_arrays(off).normals)[: box.n_faces] @ u > 1e-6
    assert np.all(f[front] == 1.0) and np.all(f[~front] == 0.0)
    # the macro pairs' visibility: the panel-body dihedral seen along its bisector
    phi = np.radians(5.0)
    v = np.array([np.cos(np.pi / 4 - phi), np.sin(np.pi / 4 - phi), 0.0])
    mats = [ppr.Material(AL, 1e4)] * 3
    (p0, i0), (p1, i1) = (_pairs(_scene(m, v, mats)) for m in (mesh, far))
    assert i0["glossy"] >= 2
    assert {k: v for k, v in i0.items() if k != "range"} == {
        k: v for k, v in i1.items() if k != "range"
    }
    np.testing.assert_allclose(np.asarray(p1.g_vis), np.asarray(p0.g_vis), rtol=1e-12, atol=0)
    np.testing.assert_allclose(np.asarray(p1.r_w), np.asarray(p0.r_w), rtol=1e-9, atol=0)


def test_facing_pairs_equal_their_definition_and_convex_meshes_have_none():
    """The facing pairs (searched among the surfaces with some vertex in front of their
    plane) are exactly the ordered pairs of the definition, checked pair by pair on the
    panelled 3U's faces and a concave L; a 1280-face sphere has none."""
    for mesh in (shapes.cubesat_with_panels(3, panel_span=0.3), _dihedral(2)):
        tri = mesh.triangles()
        area, nrm = ppr.geometry._mesh.face_areas_normals(tri)
        scale = float(np.linalg.norm(np.ptp(tri.reshape(-1, 3), axis=0)))
        got = {tuple(p) for p in _macro._facing(tri, nrm, scale).tolist()}
        off = np.einsum("mk,mk->m", nrm, tri[:, 0])
        h = np.einsum("ak,bvk->abv", nrm, tri).max(-1) - off[:, None]  # (I, J)
        tol = 1e-9 * scale
        want = {(i, j) for i, j in zip(*np.nonzero((h > tol) & (h.T > tol)), strict=True)}
        assert got == want and len(want) > 0
    sphere = shapes.sphere(0.5, subdivisions=3)
    assert _macro.macro_geometry(sphere, plates=False).convex
