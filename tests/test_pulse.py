"""Facet-sum pulse synthesis: closed forms, energy, invariances, occlusion, gradients.

Most tests use stand-in BRDFs (Lambertian ``diag(1,0,0,0)/pi``, or a smooth polarizing
Fresnel-lobe stand-in) so that the geometry and the range kernel are checked against
closed forms independent of the microfacet model; one test runs the real ``mueller_brdf``.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, stats

import ppr
from ppr import shapes
from ppr.optics.conventions import C_LIGHT
from ppr.pulse._pulse import (
    STOKES_STATES,
    glossy_fresnel_mueller,
    lambertian_mueller,
    render,
    stack_materials,
    tent_gaussian_cdf,
    visible_faces,
    window_size,
)

MAT = ppr.Material(1.5 + 0.0j, 10.0)
SIGMA_R = 0.5 * C_LIGHT * 100e-12 / 2.3548200450309493  # 100 ps FWHM in range (m)


def _scene(
    mesh,
    q=(1.0, 0, 0, 0),
    *,
    sensor=None,
    width=0.005,
    n_bins=256,
    fwhm=100e-12,
    jitter=0.0,
    materials=None,
    position=(0.0, 0, 0),
    samples=16,
):
    return ppr.Scene(
        mesh,
        tuple(materials or [MAT] * len(mesh.parts)),
        ppr.Pose(np.asarray(q, float), position),
        sensor or ppr.Sensor.make((0, 0, -1.0)),
        ppr.Pulse.gaussian(fwhm, jitter),
        ppr.RangeBins.centred(width, n_bins, 1e6),
        samples,
    )


def _p1(y):
    return y * stats.norm.cdf(y) + stats.norm.pdf(y)


# ----------------------------------------------------------------------------- closed form


def _cdf_reference(x, d0, d1, d2, s):
    """Quadrature of (triangular density) x Phi((x - z)/s) (independent of the closed form)."""
    if d2 - d0 < 1e-13:
        return stats.norm.cdf((x - d0) / s)

    def g(z):
        if z < d1:
            return 2 * (z - d0) / ((d2 - d0) * (d1 - d0)) if d1 > d0 else 0.0
        return 2 * (d2 - z) / ((d2 - d0) * (d2 - d1)) if d2 > d1 else 0.0

    return integrate.quad(
        lambda z: g(z) * stats.norm.cdf((x - z) / s),
        d0,
        d2,
        points=[d1],
        epsabs=1e-14,
        epsrel=1e-13,
        limit=200,
    )[0]


def test_tent_cdf_matches_quadrature_f64_f32():
    rng = np.random.default_rng(0)
    rows = []
    for case in range(80):
        s = 10 ** rng.uniform(-3, 0)
        d = np.sort(rng.normal(size=3) * 10 ** rng.uniform(-4, 0.5))
        if case % 5 == 0:
            d[1] = d[0]  # two vertices at the same depth
        if case % 7 == 0:
            d[2] = d[1]
        if case % 11 == 0:
            d[:] = d[0]  # zero-depth facet facing the sensor
        x = rng.uniform(d[0] - 6 * s, d[2] + 6 * s)
        rows.append((x, *d, s, _cdf_reference(x, *d, s)))
    a = np.asarray(rows)
    got64 = np.asarray(tent_gaussian_cdf(*(a[:, i] for i in range(5))))
    # float64: quadrature accuracy ~1e-13, closed form branches ~1e-13 (measured 2e-13)
    np.testing.assert_allclose(got64, a[:, 5], atol=2e-12)
    got32 = np.asarray(tent_gaussian_cdf(*(a[:, i].astype(np.float32) for i in range(5))))
    # float32: rounding of the inputs (x - d)/s plus branch truncation ~1e-6; 3e-5 covers
    # the worst measured case (cancellation in the first divided differences)
    np.testing.assert_allclose(got32, a[:, 5], atol=3e-5)
    assert got32.dtype == np.float32


@jax.jit
def _tent_value_grad_jvp(d, x, v):
    f = lambda dd: tent_gaussian_cdf(x, dd[0], dd[1], dd[2], 0.01)  # noqa: E731
    val, g = jax.value_and_grad(f)(d)
    h = 1e-7
    fd = (f(d + h * v) - f(d - h * v)) / (2 * h)
    return val, g, g @ v, fd


def test_tent_cdf_gradients_finite_and_match_fd():
    ds = [
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 0.02],
        [0.0, 0.02, 0.02],
        [-0.01, 0.005, 0.03],
        [0.0, 1e-9, 2e-9],
        [0.0, 0.0005, 0.04],
    ]
    v = jnp.array([0.3, -0.5, 0.8])
    for d in ds:
        for x in (-0.02, 0.004, 0.01, 0.05):
            _, g, jvp, fd = _tent_value_grad_jvp(jnp.asarray(d), x, v)
            assert np.all(np.isfinite(np.asarray(g)))
            # central differences in float64: truncation ~h^2 (third derivative) ~ 1e-8 rel.
            np.testing.assert_allclose(float(jvp), float(fd), rtol=1e-6, atol=1e-7)
    g32 = jax.jit(
        jax.grad(
            lambda dd: tent_gaussian_cdf(jnp.float32(0.01), dd[0], dd[1], dd[2], jnp.float32(0.01))
        )
    )
    for d in ds:
        assert np.all(np.isfinite(np.asarray(g32(jnp.asarray(d, jnp.float32)))))


# ----------------------------------------------------------------------------- analytic scenes


def test_tilted_plate_profile_mean_variance():
    th = np.radians(35.0)
    width = 0.004
    sc = _scene(
        shapes.plate(1.0, subdivisions=2),
        ppr.quat_from_axis_angle([1, 0, 0], th),
        width=width,
        n_bins=384,
    )
    p = ppr.simulate(sc, brdf=lambertian_mueller)
    prof = np.asarray(p.data[0, 0])
    sig = float(sc.pulse.sigma_range)
    s = np.sin(th)  # depth of a point (x, y cos th, y sin th) is -y sin th: uniform on [-s/2, s/2]

    def u_cdf(x):
        return sig / s * (_p1((x + s / 2) / sig) - _p1((x - s / 2) / sig))

    e = np.asarray(p.edges_m)
    expect = np.cos(th) ** 2 / np.pi * np.diff(u_cdf(e))
    # closed form vs closed form: float64 rounding only
    # window truncated at NSIG = 7 sigma: Phi(-7) ~ 1e-12 of the facet weight
    np.testing.assert_allclose(prof, expect, atol=1e-11 * expect.max())
    assert prof.sum() == pytest.approx(np.cos(th) ** 2 / np.pi, rel=1e-12)
    r = np.asarray(p.range_m)
    mean = (prof * r).sum() / prof.sum()
    var = (prof * (r - mean) ** 2).sum() / prof.sum()
    assert mean == pytest.approx(0.0, abs=1e-12)
    # uniform + Gaussian variances, plus Sheppard's h^2/12 for bin-centre moments (exact to
    # ~exp(-2 pi^2 sigma^2 / h^2) for a Gaussian-smoothed density)
    assert var == pytest.approx(s**2 / 12 + sig**2 + width**2 / 12, rel=1e-10)


def _sphere_reference(edges, a, sig):
    """Lambertian sphere, monostatic: area-weighted cos^2/pi density 2 r^2 / a on [-a, 0]."""
    r = np.linspace(-a, 0.0, 20001)
    rho = 2 * r**2 / a
    cdf = np.array([integrate.simpson(rho * stats.norm.cdf((x - r) / sig), x=r) for x in edges])
    return np.diff(cdf)


def test_sphere_lambertian_profile_converges():
    a = 0.3
    errs = []
    ref = None
    for sub in (1, 2, 3):
        sc = _scene(shapes.sphere(a, subdivisions=sub), width=0.005, n_bins=256)
        p = ppr.simulate(sc, brdf=lambertian_mueller)
        prof = np.asarray(p.data[0, 0])
        if ref is None:
            ref = _sphere_reference(np.asarray(p.edges_m), a, float(sc.pulse.sigma_range))
            assert ref.sum() == pytest.approx(2 * a**2 / 3, rel=1e-6)
        errs.append(np.abs(prof - ref).sum() / ref.sum())
    # inscribed icosphere: O(edge^2) errors, edge halves per level -> ratio ~4; ask for > 2.5
    assert errs[0] / errs[1] > 2.5 and errs[1] / errs[2] > 2.5, errs
    assert errs[2] < 0.02, errs


def test_box_face_on_and_edge_on():
    """A cube seen along a face normal: only that face counts (the four side faces are exactly
    edge-on); its profile is the bin-integrated Gaussian at depth -0.05 m."""
    sc = _scene(shapes.cubesat(1), width=0.003, n_bins=128)
    p = ppr.simulate(sc, brdf=lambertian_mueller)
    prof = np.asarray(p.data[0, 0])
    sig = float(sc.pulse.sigma_range)
    e = np.asarray(p.edges_m)
    expect = 0.01 / np.pi * np.diff(stats.norm.cdf((e + 0.05) / sig))
    np.testing.assert_allclose(prof, expect, atol=1e-14)
    # rotated 45 deg about y: two faces at 45 deg, each deeper than the pulse; total is
    # 2 * A cos^2(45) / pi and the depth interval is [-0.0707, 0.0]
    q = ppr.quat_from_axis_angle([0, 1, 0], np.pi / 4)
    p = ppr.simulate(_scene(shapes.cubesat(1), q, width=0.003, n_bins=128), brdf=lambertian_mueller)
    assert float(p.total[0, 0]) == pytest.approx(2 * 0.01 * 0.5 / np.pi, rel=1e-12)
    r = np.asarray(p.range_m)
    prof = np.asarray(p.data[0, 0])
    assert (prof * r).sum() / prof.sum() == pytest.approx(-0.05 * np.sqrt(2) / 2, rel=1e-9)


# ----------------------------------------------------------------------------- energy


def test_energy_independent_of_bins_and_pulse():
    mesh = shapes.cubesat_with_panels(3)
    q = np.array([0.9, 0.3, -0.2, 0.25])
    q /= np.linalg.norm(q)
    rot = np.asarray(ppr.quat_to_matrix(q))
    u = rot.T @ np.array([0, 0, 1.0])
    vis = ppr.VisibilityCaster(mesh, 16).fractions(u)
    arrays = ppr.mesh_arrays(mesh)
    vis_p = jnp.asarray(np.concatenate([vis, np.zeros(arrays.valid.shape[0] - mesh.n_faces)]))
    totals = []
    n = 512  # dense window (= n_bins): one compilation for every bin and pulse width
    mats, sensor = stack_materials([MAT] * 3), ppr.Sensor.make((0, 0, -1.0))

    def kw(width, sig):
        return dict(brdf=lambertian_mueller, n_bins=n, width=width, window=n, sigma_r=sig)

    for width, fwhm in ((0.004, 30e-12), (0.005, 100e-12), (0.011, 300e-12), (0.05, 100e-12)):
        sig = 0.5 * C_LIGHT * fwhm / 2.3548200450309493
        out = _profile(jnp.asarray(q), mats, arrays, vis_p, sensor, **kw(width, sig))
        totals.append(float(out[0].sum()))
    # pruning back-facing/invisible facets (render(faces=...)) changes nothing
    n_vis = int((np.asarray(vis_p) > 0).sum())
    faces = jnp.asarray(visible_faces(np.asarray(vis_p), capacity=n_vis + 1))
    assert n_vis + 1 < vis_p.shape[0] // 2  # more than half of the slots pruned
    pruned = _profile(jnp.asarray(q), mats, arrays, vis_p, sensor, faces=faces, **kw(width, sig))
    np.testing.assert_allclose(np.asarray(pruned), np.asarray(out), atol=1e-15)
    tri = mesh.triangles()
    cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cr, axis=1)
    c = np.clip((cr / (2 * area[:, None])) @ u, 0, None)
    facet_sum = (c * c * area * vis).sum() / np.pi
    # every facet's bin contents telescope to its weight: float64 rounding only
    np.testing.assert_allclose(totals, facet_sum, rtol=1e-12)
    assert ((vis > 0) & (vis < 1)).any()  # partial self-shadowing present in this pose


def test_windowed_equals_dense_for_deep_facets():
    """Facets much deeper than the pulse and the bins (a 1 m plate at 60 deg, 2 mm bins)."""
    mesh = shapes.plate(1.0, subdivisions=4)
    arrays = ppr.mesh_arrays(mesh)
    q = jnp.asarray(ppr.quat_from_axis_angle([1, 1, 0], np.radians(60)))
    vis = jnp.asarray(arrays.valid, float)
    sensor = ppr.Sensor.make((0, 0, -1.0))
    mats = stack_materials([MAT])
    kw = dict(n_bins=640, brdf=lambertian_mueller)
    k = window_size(mesh.max_edge(), SIGMA_R, 0.002, 640)
    assert k < 640
    a = render(arrays, vis, ppr.Pose(q), mats, sensor, SIGMA_R, -0.64, 0.002, window=k, **kw)
    b = render(arrays, vis, ppr.Pose(q), mats, sensor, SIGMA_R, -0.64, 0.002, window=640, **kw)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-15)


# ----------------------------------------------------------------------------- invariances


def _random_rotation(seed):
    q = np.random.default_rng(seed).normal(size=4)
    return q / np.linalg.norm(q)


def test_joint_rotation_of_object_and_sensor_leaves_profile_unchanged():
    mesh = shapes.cubesat_with_panels(3)
    mats = [ppr.Material(0.94 + 6.42j, 50.0), ppr.Material(1.46, 400.0), ppr.Material(2.6, 3.0)]
    q0 = _random_rotation(3)
    sensor0 = ppr.Sensor.make(
        (0.2, -0.1, -1.0), (1.0, 0.3, 0.0), bistatic_angle=0.05, bistatic_azimuth=0.7
    )
    p0 = ppr.simulate(
        _scene(mesh, q0, sensor=sensor0, materials=mats),
        brdf=glossy_fresnel_mueller,
        multibounce=False,
    )
    g = _random_rotation(4)
    rg = np.asarray(ppr.quat_to_matrix(g))
    sensor1 = ppr.Sensor(
        *(
            rg @ np.asarray(getattr(sensor0, f))
            for f in ("laser_dir", "receiver_dir", "frame_tx", "frame_rx")
        ),
        532e-9,
    )
    q1 = np.asarray(ppr.geometry._rotation.quat_multiply(g, q0))
    p1 = ppr.simulate(
        _scene(mesh, q1, sensor=sensor1, materials=mats),
        brdf=glossy_fresnel_mueller,
        multibounce=False,
    )
    d0, d1 = np.asarray(p0.data), np.asarray(p1.data)
    assert np.abs(d0[1:, 1:]).max() > 1e-3 * np.abs(d0[0, 0]).max()  # polarizing: frames matter
    # same facets, same visibility (ray casts in the body frame), float64 rounding
    np.testing.assert_allclose(d1, d0, atol=1e-12 * np.abs(d0).max())


@pytest.mark.parametrize(
    "mesh_fn, mat",
    [
        (lambda: shapes.cubesat(3), ppr.Material(0.94 + 6.42j, 5.0)),  # rough aluminium
        (lambda: shapes.cylinder(0.06, 0.25, sections=12), ppr.Material(1.46, 3.0)),  # silica
        # non-convex, self-shadowing, three parts; subdivided so that partly shadowed faces
        # are small (on the 36-face mesh the per-face visibility weighting alone breaks the
        # parity by ~14% of the peak: docs/limits.md)
        (lambda: shapes.cubesat_with_panels(3, max_edge=0.05), None),
    ],
    ids=["cubesat3u-aluminium", "cylinder-silica", "panels-subdivided"],
)
def test_mirror_image_scene_gives_mirrored_mueller_profile(mesh_fn, mat):
    """Parity of the whole forward model (full BRDF: single, double, multiple). A body with a
    mirror plane sigma (here z -> -z) at attitude P R sigma, with P the world mirror through
    the plane holding the line of sight and the sensor's x reference, is the mirror image of
    the scene at R. Mirroring flips U and V: M' = D M D, D = diag(1, 1, -1, -1), in every bin,
    exactly. The range profile of M00 is then identical, and only the off-block elements
    (M02, M03, M12, ...) can tell the two attitudes apart: the mirror ambiguity of the
    inversion (inversion.mirror_attitude)."""
    mesh = mesh_fn()
    sigma, world = np.diag([1.0, 1.0, -1.0]), np.diag([1.0, -1.0, 1.0])
    from inversion import mesh_has_mirror

    assert mesh_has_mirror(mesh, sigma[2])  # as a surface, parts included
    q = _random_rotation(11)
    q_mirror = ppr.matrix_to_quat(world @ np.asarray(ppr.quat_to_matrix(q)) @ sigma)
    mats = (
        [mat]
        if mat is not None
        else [ppr.Material(0.94 + 6.42j, 40.0), ppr.Material(1.5, 300.0), ppr.Material(2.6, 3.0)]
    )
    scenes = [_scene(mesh, qq, materials=mats, width=0.01, n_bins=64) for qq in (q, q_mirror)]
    # single bounce (the double bounce's parity: tests/test_macro.py)
    m0, m1 = (np.asarray(ppr.simulate(s, multibounce=False).data) for s in scenes)
    d = np.diag([1.0, 1.0, -1.0, -1.0])
    scale = np.abs(m0).max()
    # convex: exact. Self-shadowing: a partly lit face is weighted by its ray-sampled lit
    # fraction, and the mirror image's faces are sampled at mirrored points only where the
    # triangulation is mirror-symmetric: ~1e-4 of the peak here (docs/limits.md)
    tol = 1e-12 if mat is not None else 3e-4
    np.testing.assert_allclose(
        m1, np.einsum("ij,jkb,kl->ilb", d, m0, d), rtol=0, atol=tol * scale
    )  # not a trivial identity: the attitudes differ and the off-block elements do not vanish
    r0, r1 = (np.asarray(ppr.quat_to_matrix(qq)) for qq in (q, q_mirror))
    assert np.abs(r1[2] - r0[2]).max() > 0.1  # the body-frame lines of sight differ
    assert np.abs(m0[:2, 2:]).max() > 1e-4 * scale


def test_half_turn_about_line_of_sight_is_exact_for_monostatic_data():
    """A half turn of the scene about the line of sight keeps every depth and rotates the
    sensor's polarization frame by 180 deg, the identity on Stokes vectors: the monostatic
    Mueller profiles at ``C2(los) R`` and ``R`` are identical in all 16 elements, for any body
    (here non-convex and self-shadowing, three materials, full BRDF). This attitude ambiguity
    is exact, unlike the mirror image it needs no body symmetry, and it keeps the body-frame
    line of sight (inversion.los_half_turn). A quarter turn, or a bistatic receiver, breaks
    it (the check is not vacuous)."""
    from inversion import los_half_turn
    from ppr.geometry import quat_from_rotvec, quat_multiply

    mesh = shapes.cubesat_with_panels(3)
    mats = [ppr.Material(0.94 + 6.42j, 5.0), ppr.Material(1.5, 300.0), ppr.Material(2.6, 3.0)]
    q = _random_rotation(21)
    q_half = los_half_turn(q)  # sensor line of sight: world z
    quarter = np.asarray(
        quat_multiply(quat_from_rotvec(jnp.asarray([0, 0, np.pi / 2])), jnp.asarray(q))
    )

    def sim(qq, sensor=None, terms=None):
        sc = _scene(mesh, qq, sensor=sensor, materials=mats, width=0.01, n_bins=64)
        return np.asarray(ppr.simulate(sc, terms=terms, multibounce=False).data)

    m0, m1, m4 = sim(q), sim(q_half), sim(quarter)
    scale = np.abs(m0).max()
    np.testing.assert_allclose(m1, m0, rtol=0, atol=1e-12 * scale)
    assert np.abs(m0[:2, 2:]).max() > 1e-4 * scale  # off-block elements present
    assert np.abs(m4 - m0).max() > 1e-3 * scale  # a quarter turn is seen
    # bistatic: the single term alone already breaks the symmetry (and keeps the double
    # term's general quadrature, a 20 s compilation, out of this test)
    bi = ppr.Sensor.make((0, 0, -1.0), bistatic_angle=0.3, bistatic_azimuth=0.4)
    b0, b1 = sim(q, bi, ("single", "multiple")), sim(q_half, bi, ("single", "multiple"))
    assert np.abs(b1 - b0).max() > 1e-3 * np.abs(b0).max()


def test_range_offset_shifts_profile_exactly():
    mesh = shapes.cubesat_with_panels(3)
    q = _random_rotation(5)
    width = 0.005
    base = ppr.simulate(_scene(mesh, q, width=width), brdf=lambertian_mueller)
    w = np.array([0, 0, 1.0])  # monostatic bisector for line of sight -z
    k = 7
    moved = ppr.simulate(
        _scene(mesh, q, width=width, position=-k * width * w), brdf=lambertian_mueller
    )
    a, b = np.asarray(base.data[0, 0]), np.asarray(moved.data[0, 0])
    np.testing.assert_allclose(b[k:], a[:-k], atol=1e-12 * a.max())
    # a pulse time offset t0 is the same as a range offset c t0 / 2
    sc = _scene(mesh, q, width=width)
    sc = eqx.tree_at(lambda s: s.pulse, sc, ppr.Pulse(sc.pulse.sigma_t, 2 * k * width / C_LIGHT))
    c = np.asarray(ppr.simulate(sc, brdf=lambertian_mueller).data[0, 0])
    np.testing.assert_allclose(c, b, atol=1e-12 * a.max())


# ----------------------------------------------------------------------------- occlusion


def _stack(front_offset, back_sub=4):
    front = shapes.plate(1.0, part="front")
    front = ppr.Mesh(
        np.asarray(front.vertices) + [front_offset, 0, 0.2], front.faces, None, ("front",)
    )
    back = shapes.plate(1.0, subdivisions=back_sub, part="back")
    return ppr.geometry._mesh.concatenate([front, back]), front, back


def test_hidden_plate_contributes_nothing_and_half_hidden_half():
    both, front, back = _stack(0.0)
    p_both = ppr.simulate(_scene(both), brdf=lambertian_mueller)
    p_front = ppr.simulate(_scene(front, materials=[MAT]), brdf=lambertian_mueller)
    # identical facets up to summation order
    np.testing.assert_allclose(
        np.asarray(p_both.data),
        np.asarray(p_front.data),
        atol=1e-11 * float(np.abs(p_front.data).max()),
    )
    both, front, back = _stack(0.5)
    p_both = ppr.simulate(_scene(both), brdf=lambertian_mueller)
    p_front = ppr.simulate(_scene(front, materials=[MAT]), brdf=lambertian_mueller)
    p_back = ppr.simulate(_scene(back, materials=[MAT]), brdf=lambertian_mueller)
    back_part = np.asarray(p_both.data - p_front.data)[0, 0]
    # the shadow edge falls on cell boundaries: exactly half of the back plate remains
    # windows differ between the scenes: tails beyond NSIG = 7 sigma (Phi(-7) ~ 1e-12) differ
    np.testing.assert_allclose(
        back_part,
        0.5 * np.asarray(p_back.data[0, 0]),
        atol=1e-11 * float(np.abs(p_front.data).max()),
    )


def test_pruning_and_channel_selection_agree():
    mesh = shapes.cubesat_with_panels(3)
    mats = [ppr.Material(0.94 + 6.42j, 50.0), ppr.Material(1.46, 400.0), ppr.Material(2.6, 3.0)]
    sc = _scene(
        mesh,
        _random_rotation(8),
        materials=mats,
        sensor=ppr.Sensor.make((0, 0, -1.0), bistatic_angle=0.02),
    )
    full = ppr.simulate(sc, brdf=glossy_fresnel_mueller, multibounce=False)
    unpruned = ppr.simulate(sc, brdf=glossy_fresnel_mueller, prune=False, multibounce=False)
    # pruning drops only zero-weight facets: identical up to summation order
    np.testing.assert_allclose(np.asarray(unpruned.data), np.asarray(full.data), atol=1e-15)
    st = ppr.simulate(
        sc, brdf=glossy_fresnel_mueller, states=["H", "V", "D", "R"], multibounce=False
    )
    m = np.asarray(full.data)
    for i, name in enumerate(st.labels):
        expect = np.einsum("ijb,j->ib", m, np.asarray(STOKES_STATES[name]))
        np.testing.assert_allclose(np.asarray(st.data[i]), expect, atol=1e-15)
    ch = ppr.simulate(
        sc, brdf=glossy_fresnel_mueller, channels=[(0, 0), (3, 3), (1, 2)], multibounce=False
    )
    np.testing.assert_allclose(np.asarray(ch.data), m[[0, 3, 1], [0, 3, 2]], atol=1e-15)
    assert full.range_m.shape == (256,) and full.time_s[1] - full.time_s[0] == pytest.approx(
        2 * 0.005 / C_LIGHT
    )


# ----------------------------------------------------------------------------- gradients


N_BINS, WIDTH, WINDOW = 192, 0.006, 96  # shared by the gradient tests: one compilation


def _render_setup(mesh, q, materials, sensor):
    """Padded arrays (capacity 64) and host visibility for ``render`` at a fixed pose."""
    arrays = ppr.mesh_arrays(mesh, capacity=64)
    rot = np.asarray(ppr.quat_to_matrix(q))
    caster = ppr.VisibilityCaster(mesh, 9)
    vis = caster.fractions(
        rot.T @ np.asarray(sensor.laser_dir), rot.T @ np.asarray(sensor.receiver_dir)
    )
    vis = jnp.asarray(np.concatenate([vis, np.zeros(64 - mesh.n_faces)]))
    assert window_size(mesh.max_edge(), SIGMA_R, WIDTH, N_BINS) <= WINDOW
    mats = list(materials) + [materials[0]] * (3 - len(materials))  # always 3 parts
    return arrays, vis, stack_materials(mats)


def _profile(
    q,
    mats,
    arrays,
    vis,
    sensor,
    *,
    brdf=glossy_fresnel_mueller,
    n_bins=N_BINS,
    width=WIDTH,
    window=WINDOW,
    faces=None,
    sigma_r=SIGMA_R,
):
    """``render`` at attitude ``q`` on bins centred on the body origin (defaults: the shared
    gradient-test settings and the polarizing stand-in BRDF)."""
    return render(
        arrays,
        vis,
        ppr.Pose(q),
        mats,
        sensor,
        sigma_r,
        -0.5 * width * n_bins,
        width,
        n_bins=n_bins,
        window=window,
        brdf=brdf,
        faces=faces,
    )


def _loss_fn(q, mats, arrays, vis, sensor, wts):
    return jnp.sum(_profile(q, mats, arrays, vis, sensor) * wts)


_loss_grad = eqx.filter_jit(jax.value_and_grad(_loss_fn, argnums=(0, 1)))


def _loss(*args):  # finite differences reuse the gradient's compilation
    return _loss_grad(*args)[0]


WTS = jnp.asarray(np.random.default_rng(0).normal(size=(16, N_BINS)))


def test_gradients_attitude_and_material_match_fd():
    mesh = shapes.cubesat_with_panels(3)
    mats = [ppr.Material(0.94 + 6.42j, 50.0), ppr.Material(1.46, 40.0), ppr.Material(2.6, 3.0)]
    sensor = ppr.Sensor.make((0, 0, -1.0), bistatic_angle=0.03)
    q = jnp.asarray(_random_rotation(11))
    arrays, vis, stacked = _render_setup(mesh, q, mats, sensor)
    args = (arrays, vis, sensor, WTS)
    _, (gq, gm) = _loss_grad(q, stacked, *args)
    assert np.all(np.isfinite(np.asarray(gq)))
    h = 1e-6
    # attitude: directional derivative along a random direction in quaternion space
    v = jnp.asarray(np.random.default_rng(1).normal(size=4))
    fd = (_loss(q + h * v, stacked, *args) - _loss(q - h * v, stacked, *args)) / (2 * h)
    # central FD in float64 (visibility held fixed): truncation ~h^2, rounding ~1e-10
    np.testing.assert_allclose(float(gq @ v), float(fd), rtol=1e-6)
    # roughness and complex index of every part
    for field, dv in (("m", 1.0), ("n", 1.0 + 0.0j), ("n", 1.0j)):
        tan = jnp.zeros_like(getattr(stacked, field)).at[:].set(dv)
        get = lambda s, f=field: getattr(s, f)  # noqa: E731
        plus = eqx.tree_at(get, stacked, get(stacked) + h * tan)
        minus = eqx.tree_at(get, stacked, get(stacked) - h * tan)
        fd = (_loss(q, plus, *args) - _loss(q, minus, *args)) / (2 * h)
        # JAX's gradient of a real loss w.r.t. complex z is df/dx - i df/dy: Re(g t) is the
        # directional derivative
        an = float(np.real(np.sum(np.asarray(getattr(gm, field)) * np.asarray(tan))))
        np.testing.assert_allclose(an, float(fd), rtol=1e-6, atol=1e-12)


def test_gradients_finite_edge_on_and_equal_depths():
    """Cube face-on (four faces exactly edge-on, front vertex pairs at equal depths) and a plate
    exactly edge-on: values and attitude gradients finite; FD agrees at the cube."""
    sensor = ppr.Sensor.make((0, 0, -1.0))
    for mesh, q in (
        (shapes.cubesat(1), jnp.array([1.0, 0, 0, 0])),
        (
            shapes.plate(0.5, subdivisions=2),
            jnp.asarray(ppr.quat_from_axis_angle([1, 0, 0], np.pi / 2)),
        ),
    ):
        arrays, vis, stacked = _render_setup(mesh, q, [MAT], sensor)
        args = (arrays, vis, sensor, WTS)
        val, (g, _) = _loss_grad(q, stacked, *args)
        assert np.isfinite(float(val)) and np.all(np.isfinite(np.asarray(g)))
        if mesh.n_faces == 12:
            v = jnp.array([0.1, 0.4, -0.3, 0.2])
            fd = (_loss(q + 1e-6 * v, stacked, *args) - _loss(q - 1e-6 * v, stacked, *args)) / 2e-6
            np.testing.assert_allclose(float(g @ v), float(fd), rtol=1e-5, atol=1e-9)


def test_one_part_mesh_takes_the_one_material_path():
    """A one-part mesh rendered with materials listed for three parts uses its part's material
    unbatched (the BRDF's one-material fast paths: tabulated visibility, folded double table)
    and agrees with the per-element path; float32, full BRDF at backscatter."""
    from ppr.brdf._brdf import mueller_brdf
    from ppr.pulse._pulse import _render_jit, single_part

    mesh = shapes.sphere(0.3, subdivisions=2)
    arrays = ppr.mesh_arrays(mesh, dtype=jnp.float32)
    assert single_part(arrays) == 0
    assert single_part(ppr.mesh_arrays(shapes.cubesat_with_panels(3))) is None
    mats = stack_materials(
        [ppr.Material(0.94 + 6.42j, 30.0), ppr.Material(1.46, 2000.0), ppr.Material(2.67, 5.0)]
    )
    mats = jax.tree_util.tree_map(
        lambda a: a.astype(jnp.complex64 if jnp.iscomplexobj(a) else jnp.float32), mats
    )
    sensor = jax.tree_util.tree_map(
        lambda a: jnp.asarray(a, jnp.float32), ppr.Sensor.make((0.1, 0.0, -1.0))
    )
    vis = arrays.valid.astype(jnp.float32)
    q = jnp.asarray(_random_rotation(2), jnp.float32)
    args = (arrays, vis, ppr.Pose(q), mats, sensor)
    kw = dict(n_bins=256, window=32, projection=None, brdf=mueller_brdf)
    rng = (jnp.float32(SIGMA_R), jnp.float32(-0.64), jnp.float32(0.005))
    fast = render(*args, *rng, **kw)
    terms = ppr.pulse._pulse.sensor_terms(mueller_brdf, None, sensor)
    per_element = _render_jit(*args, *rng, **kw, terms=terms, part=None)
    scale = float(jnp.abs(per_element[0]).max())
    np.testing.assert_allclose(np.asarray(fast), np.asarray(per_element), atol=2e-5 * scale)
    assert float(jnp.abs(fast[1:]).max()) > 1e-3 * scale  # polarizing


def test_sort3_equals_jnp_sort_values_and_tangents_at_ties():
    """The select network that orders facet depths is a permutation: values and tangents as
    jnp.sort, including two and three equal depths (where min/max would split tangents)."""
    from ppr.pulse._pulse import _sort3

    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 3))
    x[:50, 1] = x[:50, 0]  # pairs
    x[50:100] = x[50:100, :1]  # triples
    x[100:120, 2] = x[100:120, 1]
    t = rng.normal(size=x.shape)

    def net(v):
        return jnp.concatenate(_sort3(v[:, 0:1], v[:, 1:2], v[:, 2:3]), axis=1)

    (v1, t1), (v2, t2) = (
        jax.jvp(f, (jnp.asarray(x),), (jnp.asarray(t),))
        for f in (net, lambda v: jnp.sort(v, axis=-1))
    )
    np.testing.assert_array_equal(np.asarray(v1), np.asarray(v2))
    # tangents: a permutation of the inputs' (ties may be ordered differently), same sum
    np.testing.assert_allclose(np.asarray(t1).sum(1), t.sum(1), rtol=1e-14)
    np.testing.assert_array_equal(np.sort(np.asarray(t1), 1), np.sort(np.asarray(t2), 1))
    untied = slice(120, 200)
    np.testing.assert_array_equal(np.asarray(t1)[untied], np.asarray(t2)[untied])


def test_zero_area_and_duplicate_faces_stay_finite():
    mesh = shapes.plate(0.5, subdivisions=2)
    sensor = ppr.Sensor.make((0, 0, -1.0))
    q = jnp.asarray(_random_rotation(2))
    arrays, vis, stacked = _render_setup(mesh, q, [MAT], sensor)
    tri = np.array(arrays.tri)
    tri[2] = tri[0]  # duplicate face
    tri[3] = np.array([[0.1, 0.1, 0.0]] * 3)  # zero-area face, fallback normal +z
    arrays = eqx.tree_at(
        lambda a: (a.tri, a.valid, a.areas),
        arrays,
        (
            jnp.asarray(tri),
            arrays.valid.at[2:4].set(True),
            arrays.areas.at[2].set(arrays.areas[0]).at[3].set(0.0),
        ),
    )
    vis = vis.at[2:4].set(1.0)
    val, (g, gm) = _loss_grad(q, stacked, arrays, vis, sensor, WTS)
    assert np.isfinite(float(val))
    assert np.all(np.isfinite(np.asarray(g))) and np.all(np.isfinite(np.asarray(gm.m)))


# ----------------------------------------------------------------------------- jit / vmap / dtype


def test_no_retrace_for_new_poses_materials_and_vmap_matches_loop():
    mesh = shapes.cubesat_with_panels(3)
    mats = [ppr.Material(0.94 + 6.42j, 50.0), ppr.Material(1.46, 400.0), ppr.Material(2.6, 3.0)]
    sensor = ppr.Sensor.make((0, 0, -1.0))
    arrays, vis, stacked = _render_setup(mesh, jnp.asarray(_random_rotation(1)), mats, sensor)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def g(qq, mm):
        return _profile(qq, mm, arrays, vis, sensor)

    outs = [g(jnp.asarray(_random_rotation(s)), stacked) for s in range(3)]
    mats2 = eqx.tree_at(lambda s: s.m, stacked, stacked.m * 2)
    g(jnp.asarray(_random_rotation(9)), mats2)
    qs = jnp.asarray(np.stack([_random_rotation(s) for s in range(3)]))
    batched = jax.vmap(lambda qq: _profile(qq, stacked, arrays, vis, sensor))(qs)
    # vmap vs single calls: same ops, float64 rounding
    np.testing.assert_allclose(
        np.asarray(batched),
        np.stack([np.asarray(o) for o in outs]),
        atol=1e-14 * float(np.abs(batched).max()),
    )


def test_float32_in_float32_out():
    sc = _scene(shapes.cubesat_with_panels(3), _random_rotation(6))
    p64 = ppr.simulate(sc, brdf=glossy_fresnel_mueller, multibounce=False)
    p32 = ppr.simulate(sc, brdf=glossy_fresnel_mueller, dtype=jnp.float32, multibounce=False)
    assert p32.data.dtype == jnp.float32
    scale = float(np.abs(p64.data).max())
    # float32 kernel: depths/sigma ~ 1e2 with eps 1e-7 plus closed-form branch error ~3e-5
    np.testing.assert_allclose(np.asarray(p32.data), np.asarray(p64.data), atol=1e-4 * scale)


# ----------------------------------------------------------------------------- bad input


def test_bad_inputs_raise_before_computing():
    mesh = shapes.cubesat_with_panels(3)
    with pytest.raises(ValueError, match="do not cover the visible object") as err:
        ppr.simulate(_scene(mesh, width=0.001, n_bins=100), brdf=lambertian_mueller)
    assert "millimetres" not in str(err.value)  # 0.34 m deep in a 0.1 m window: no unit hint
    # the same CubeSat read from a file in millimetres, turned: hundreds of metres deep, a
    # hint at the mesh's scale
    mm = ppr.Mesh(np.asarray(mesh.vertices) * 1000.0, mesh.faces, mesh.material_ids, mesh.parts)
    with pytest.raises(ValueError, match=r"\d m deep along the line of sight: .* mesh.scale"):
        ppr.simulate(_scene(mm, _random_rotation(6)), brdf=lambertian_mueller)
    with pytest.raises(ValueError, match="fwhm must be a positive"):
        ppr.Pulse.gaussian(0.0)
    with pytest.raises(ValueError, match="fwhm must be a positive"):
        ppr.Pulse.gaussian(-1e-12)
    with pytest.raises(ValueError, match="unknown transmitted state"):
        ppr.simulate(_scene(mesh), brdf=lambertian_mueller, states=["H", "Q"])
    # Stokes rows that are not light: over-polarized, zero, negative power
    for row, dop in (([1.0, 2.0, 0.0, 0.0], "2"), ([0.0] * 4, "inf"), ([-1.0, 0, 0, 0], "inf")):
        with pytest.raises(ValueError, match=rf"states\[1\] = .*degree of polarization {dop}"):
            states = np.asarray([[1.0, 1, 0, 0], row], np.float64)
            ppr.simulate(_scene(mesh), brdf=lambertian_mueller, states=states)
    with pytest.raises(ValueError, match="visibility must be"):
        ppr.simulate(_scene(mesh), brdf=lambertian_mueller, visibility=np.ones(3))
    with pytest.raises(ValueError, match="one Material per part"):
        _scene(mesh, materials=[MAT])
    sc = _scene(mesh)
    with pytest.raises(ValueError, match="needs a concrete pose"):
        jax.jit(
            lambda q: (
                ppr.simulate(
                    eqx.tree_at(lambda s: s.pose.quaternion, sc, q), brdf=lambertian_mueller
                ).data
            )
        )(jnp.array([1.0, 0, 0, 0]))


def test_real_brdf_wiring_energy_and_frames():
    """Default BRDF (ppr.mueller_brdf): the time-integrated Mueller profile equals the facet sum
    of mueller_brdf(k_in = laser, k_out = receiver, facet normal, frames = sensor frames)
    times cos_in cos_out A v, computed here directly in world coordinates. Single-bounce term
    only (the polarizing one; keeps the two compilations of the BRDF affordable)."""
    from ppr.brdf._brdf import mueller_brdf

    mesh = shapes.cubesat_with_panels(3)
    mats = [ppr.Material(0.94 + 6.42j, 200.0), ppr.Material(1.46, 2000.0), ppr.Material(2.67, 5.0)]
    sensor = ppr.Sensor.make((0.1, 0.0, -1.0), (1.0, 0.2, 0.0), bistatic_angle=0.02)
    q = _random_rotation(21)
    terms = ("single",)
    p = ppr.simulate(
        _scene(mesh, q, sensor=sensor, materials=mats),
        dtype=jnp.float32,
        terms=terms,
        multibounce=False,
    )
    assert p.data.dtype == jnp.float32
    tot = np.asarray(p.total, np.float64)
    rot = np.asarray(ppr.quat_to_matrix(q))
    tri = mesh.triangles() @ rot.T
    cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cr, axis=1)
    nrm = cr / (2 * area[:, None])
    vis = np.asarray(p.visibility)
    keep = vis > 0
    u_in, u_out = (
        np.asarray(getattr(sensor, f), np.float64) for f in ("laser_dir", "receiver_dir")
    )
    mid = np.asarray(mesh.material_ids)[keep]
    stacked = stack_materials(mats)
    mat_f = jax.tree_util.tree_map(
        lambda a: a[mid].astype(jnp.complex64 if jnp.iscomplexobj(a) else jnp.float32), stacked
    )
    k = int(keep.sum())

    def f32(v):
        return np.ascontiguousarray(np.broadcast_to(v, (k, 3)), np.float32)

    brdf = jax.jit(functools.partial(mueller_brdf, terms=terms))
    m = np.asarray(
        brdf(
            f32(u_in),
            f32(u_out),
            f32(nrm[keep]),
            mat_f,
            frame_in=f32(np.asarray(sensor.frame_tx, np.float64)),
            frame_out=f32(np.asarray(sensor.frame_rx, np.float64)),
        ),
        np.float64,
    )
    g = (nrm[keep] @ u_in) * (nrm[keep] @ u_out) * area[keep] * vis[keep]
    expect = np.einsum("fij,f->ij", m, g)
    # both float32: body-frame kernel vs world-frame direct call, rounding of the rotated
    # directions propagates through sharp lobes (m = 2000): 2e-4 of M00
    np.testing.assert_allclose(tot, expect, atol=2e-4 * expect[0, 0])
    d = np.asarray(p.data, np.float64)
    assert np.all(d[0, 0] >= -1e-6 * d[0, 0].max())
    assert np.all(np.abs(d) <= d[0, 0][None, None, :] * (1 + 1e-3) + 1e-6 * d[0, 0].max())


def test_concrete_render_drops_the_traced_checks_and_checks_on_the_host():
    """``render`` with concrete materials and pose (``ppr.simulate``) swaps ``ppr.mueller_brdf``
    for its unchecked variant, whose program holds no host callback and so can come from the
    persistent compilation cache (values: test_real_brdf_wiring_energy_and_frames, which goes
    through that path). The checks then run on the host: a material edited past its own
    checks (``eqx.tree_at``) or a non-finite pose still raise, naming the field. Traced
    materials or poses keep the traced checks."""
    from ppr.brdf._brdf import mueller_brdf, mueller_brdf_unchecked
    from ppr.pulse._pulse import _unchecked_if_concrete

    mats = stack_materials([ppr.Material(0.94 + 6.42j, 20.0), ppr.Material(1.46, 3.0)])
    pose = ppr.Pose(_random_rotation(4))
    assert _unchecked_if_concrete(mueller_brdf, mats, pose) is mueller_brdf_unchecked
    assert _unchecked_if_concrete(glossy_fresnel_mueller, mats, pose) is glossy_fresnel_mueller
    seen = []

    def traced(m, q):
        seen.append(_unchecked_if_concrete(mueller_brdf, m, ppr.Pose(q)))
        return q

    jax.jit(traced)(mats, pose.quaternion)
    jax.jit(lambda q: traced(mats, q))(pose.quaternion)
    assert seen == [mueller_brdf, mueller_brdf]
    bad_m = eqx.tree_at(lambda m: m.m, mats, jnp.asarray([20.0, -1.0]))
    with pytest.raises(ValueError, match="material.m"):
        _unchecked_if_concrete(mueller_brdf, bad_m, pose)
    bad_n = eqx.tree_at(lambda m: m.n, mats, jnp.asarray([0.94 - 6.42j, 1.46 + 0j]))
    with pytest.raises(ValueError, match="material.n"):
        _unchecked_if_concrete(mueller_brdf, bad_n, pose)
    bad_q = eqx.tree_at(lambda p: p.quaternion, pose, jnp.asarray([np.nan, 0.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="pose.quaternion"):
        _unchecked_if_concrete(mueller_brdf, mats, bad_q)


def test_normal_groups_change_nothing_values_and_gradients():
    """The BRDF evaluated once per (normal, part) group (MeshArrays.normal_group) gives the same
    profile as one BRDF per facet (real mueller_brdf, default terms at backscatter: single +
    tabulated double + multiple; three materials; pruned facets; float64) and the same
    gradients in attitude, roughness and index (polarizing stand-in BRDF)."""
    from ppr.brdf._brdf import mueller_brdf

    mesh = shapes.cubesat_with_panels(3, max_edge=0.1)
    grouped = ppr.mesh_arrays(mesh)
    flat = ppr.mesh_arrays(mesh, group=False)
    # ~500 faces, 12 distinct (normal, part) pairs; each face's group normal is its own, bitwise
    cap = flat.normals.shape[0]
    assert mesh.n_faces > 400 and ppr.geometry._mesh.n_normal_groups(mesh) == 12
    assert grouped.group_normals.shape == (64, 3) and flat.group_normals.shape == (cap, 3)
    g_of = np.asarray(grouped.normal_group)[: mesh.n_faces]
    np.testing.assert_array_equal(
        np.asarray(grouped.group_normals)[g_of], np.asarray(grouped.normals)[: mesh.n_faces]
    )
    np.testing.assert_array_equal(
        np.asarray(grouped.group_material_ids)[g_of], np.asarray(mesh.material_ids)
    )
    q = _random_rotation(5)
    sensor = ppr.Sensor.make((0.1, 0.0, -1.0), (1.0, 0.2, 0.0))
    rot = np.asarray(ppr.quat_to_matrix(q))
    vis = ppr.VisibilityCaster(mesh, 4).fractions(rot.T @ np.asarray(sensor.laser_dir))
    vis = jnp.asarray(np.concatenate([vis, np.zeros(cap - mesh.n_faces)]))
    faces = jnp.asarray(visible_faces(np.asarray(vis)))
    assert faces.shape[0] > 64  # the grouped path is taken (G = 64 < pruned facet count)
    mats = stack_materials(
        [ppr.Material(0.94 + 6.42j, 200.0), ppr.Material(1.46, 2000.0), ppr.Material(2.67, 5.0)]
    )

    kw = dict(n_bins=256, width=0.005, window=window_size(mesh.max_edge(), SIGMA_R, 0.005, 256))

    def profile(arrays, q, mats, brdf=mueller_brdf):
        return _profile(q, mats, arrays, vis, sensor, brdf=brdf, faces=faces, **kw)

    wts = jnp.asarray(np.random.default_rng(0).normal(size=(16, 256)))

    def loss(q, m, n, arrays):  # the polarizing stand-in: new here is the gather's adjoint
        mt = eqx.tree_at(lambda t: (t.m, t.n), mats, (m, n))
        return jnp.sum(wts * profile(arrays, q, mt, glossy_fresnel_mueller))

    qj = jnp.asarray(q)
    a, b = (np.asarray(profile(x, qj, mats)) for x in (grouped, flat))
    assert np.abs(a[1:]).max() > 1e-3 * np.abs(a[0]).max()  # polarizing
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-13 * np.abs(b).max())
    grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))
    ga, gb = (grad(qj, mats.m, mats.n, x) for x in (grouped, flat))
    for x, y in zip(ga, gb, strict=True):
        assert np.all(np.isfinite(np.asarray(x)))
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-10, atol=1e-14)


def test_face_subset_renders_the_full_mesh_values_and_gradients():
    """A FaceSubset (the facets lit and visible at one pose, padded to a small capacity)
    renders what the whole padded mesh renders at that visibility: subdivided non-convex
    CubeSat with panels (~500 facets in 12 normal groups, partly hidden facets with fractions
    in (0, 1)), three materials, a bistatic polarizing BRDF (the stand-in: what is new here
    is the gathering of facets and group tables, BRDF-agnostic; the real mueller_brdf on
    grouped, pruned facets is test_normal_groups_change_nothing_values_and_gradients),
    values and gradients in attitude, roughness and index. The subset keeps the per-group
    BRDF; from ungrouped arrays (one group per facet) it has none, and renders the same."""
    mesh = shapes.cubesat_with_panels(3, max_edge=0.1)
    arrays = ppr.mesh_arrays(mesh)
    cap = arrays.normals.shape[0]
    q = _random_rotation(11)
    sensor = ppr.Sensor.make((0.1, 0.0, -1.0), (1.0, 0.2, 0.0))
    rot = np.asarray(ppr.quat_to_matrix(q))
    vis = ppr.VisibilityCaster(mesh, 4).fractions(rot.T @ np.asarray(sensor.laser_dir))
    vis = jnp.asarray(np.concatenate([vis, np.zeros(cap - mesh.n_faces)]))
    n_lit = int(np.sum(np.asarray(vis) > 0))
    assert np.any((np.asarray(vis) > 0) & (np.asarray(vis) < 1))  # partial occlusion
    sub = ppr.FaceSubset.of(arrays, vis)
    assert n_lit <= sub.n_faces < 2 * n_lit and sub.n_faces < cap
    assert sub.groups.shape[0] < sub.n_faces  # grouped path
    mats = stack_materials(
        [ppr.Material(0.94 + 6.42j, 200.0), ppr.Material(1.46, 2000.0), ppr.Material(2.67, 5.0)]
    )
    kw = dict(n_bins=128, width=0.01, window=128)

    def profile(q, mats, subset, brdf=glossy_fresnel_mueller, arrays=arrays):
        a, v = (subset.apply(arrays), subset.vis) if subset is not None else (arrays, vis)
        return _profile(q, mats, a, v, sensor, brdf=brdf, **kw)

    qj = jnp.asarray(q)
    full, part = (np.asarray(profile(qj, mats, x)) for x in (None, sub))
    assert np.abs(full[1:]).max() > 1e-3 * np.abs(full[0]).max()  # polarizing
    np.testing.assert_allclose(part, full, rtol=0, atol=1e-13 * np.abs(full).max())
    wts = jnp.asarray(np.random.default_rng(1).normal(size=(16, 128)))

    def loss(q, m, n, subset):
        mt = eqx.tree_at(lambda t: (t.m, t.n), mats, (m, n))
        return jnp.sum(wts * profile(q, mt, subset))

    grad = jax.grad(loss, argnums=(0, 1, 2))
    ga, gb = grad(qj, mats.m, mats.n, None), grad(qj, mats.m, mats.n, sub)
    for x, y in zip(gb, ga, strict=True):
        assert np.all(np.isfinite(np.asarray(x))) and np.abs(np.asarray(y)).max() > 0
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-10, atol=1e-14)
    flat = ppr.mesh_arrays(mesh, group=False)
    sub_flat = ppr.FaceSubset.of(flat, vis)
    assert sub_flat.groups.shape[0] == sub_flat.n_faces  # one group per facet
    np.testing.assert_allclose(
        np.asarray(profile(qj, mats, sub_flat, arrays=flat)),
        full,
        rtol=0,
        atol=1e-13 * np.abs(full).max(),
    )


def test_face_subset_bad_input():
    arrays = ppr.mesh_arrays(shapes.cubesat(1))
    vis = np.zeros(64)
    vis[:6] = 1.0
    with pytest.raises(ValueError, match="vis must be finite with shape"):
        ppr.FaceSubset.of(arrays, vis[:12])
    bad = vis.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="vis must be finite with shape"):
        ppr.FaceSubset.of(arrays, bad)
    with pytest.raises(ValueError, match="capacity 4 is smaller than the 6 visible facets"):
        ppr.FaceSubset.of(arrays, vis, capacity=4)
    sub = ppr.FaceSubset.of(arrays, vis)
    assert sub.n_faces == 8 and np.asarray(sub.vis)[6:].max() == 0.0


def test_ideal_white_plate_monostatic_return_and_double_bounce_flag():
    """A plate of ``Material.ideal_white(m)`` at normal incidence, monostatic, through
    ``simulate`` and the real BRDF. The single bounce at exact backscatter off a facet seen
    at normal incidence is ``p(n) P(k) F / (4 <h.n> (k.n)^2)`` with the Blinn-Phong density
    ``p(n) = (m + 1) / (2 pi)``, ``P(k) = 1`` (no shadowing at normal incidence), ``F = 1``
    (the ideal white reflector) and ``<h.n> = (m + 1) / (m + 2)``: ``(m + 2) / (8 pi)`` per
    sr. The renderer weights a facet by ``(n.u_in)(n.u_out) A = A`` and spreads it with a
    bin-integrated unit-area pulse (bins covering +-50 sigma: sum 1), so the time-integrated
    M00 is ``(m + 2) / (8 pi) A``. At m = 1000 the other terms vanish: the double term at
    backscatter needs two facets tilted ~45 deg (weight ~2^-m, 0 beyond the table's
    M_MAX = 200) and the multiple-scattering remainder ``~ D(mu = 1)^2`` is far below
    1e-20 of it. The facet is a perfect mirror: no depolarization, ``|M_ii| = M00``.

    ``double_bounce`` gets the flag too: with a stand-in BRDF that is Lambertian for a white
    material and 0 otherwise, a white dihedral returns exactly what the Lambertian stand-in
    returns (before, stacking dropped the flag and both paths rendered 0)."""
    from ppr.pulse._pulse import double_bounce

    m, side = 1000.0, 0.5
    mesh = shapes.plate(side)
    white = ppr.Material.ideal_white(m)
    p = ppr.simulate(_scene(mesh, materials=[white], width=0.002, n_bins=256, samples=4))
    expect = (m + 2.0) / (8.0 * np.pi) * side * side
    total = np.asarray(p.total)
    # float64 rounding of the lobe, the visibility ratio and the bin sums
    assert total[0, 0] == pytest.approx(expect, rel=1e-12)
    np.testing.assert_allclose(np.abs(np.diag(total)), expect, rtol=1e-12)
    np.testing.assert_allclose(total - np.diag(np.diag(total)), 0.0, atol=1e-12 * expect)

    def white_lambertian(k_in, k_out, normal, material, **kw):
        return lambertian_mueller(k_in, k_out, normal, material, **kw) * float(material.white)

    rot = np.asarray(ppr.quat_to_matrix(ppr.quat_from_axis_angle([0, 1, 0], np.pi / 2)))
    a = shapes.plate(0.2, subdivisions=2)
    a = ppr.Mesh(np.asarray(a.vertices) + [0.1, 0, 0], a.faces, None, ("floor",))
    b = shapes.plate(0.2, subdivisions=2)
    b = ppr.Mesh(np.asarray(b.vertices) @ rot.T + [0, 0, 0.1], b.faces, None, ("wall",))
    dihedral = ppr.geometry._mesh.concatenate([a, b])
    sensor = ppr.Sensor.make(-np.array([1.0, 0.3, 1.0]) / np.linalg.norm([1.0, 0.3, 1.0]))
    scene = _scene(dihedral, sensor=sensor, materials=[white, white], samples=4)
    got = double_bounce(scene, brdf=white_lambertian)
    ref = double_bounce(scene, brdf=lambertian_mueller)
    assert float(ref.total[0, 0]) > 0
    np.testing.assert_array_equal(np.asarray(got.data), np.asarray(ref.data))
