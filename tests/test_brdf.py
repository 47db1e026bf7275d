"""Physics and numerics of the assembled Mueller BRDF (ppr.brdf._brdf, issue 2).

References are independent of the kernel: closed forms (monostatic backscatter), the
reciprocity theorem (derived below), Cloude realizability, limits (mirror at large m,
near-Lambertian at m = 0), an AoS reassembly from the public pieces of ppr.brdf._microfacet and
ppr.optics._frames, finite differences, loops vs vmap.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ppr
from ppr.brdf import albedo as _albedo
from ppr.brdf._brdf import mueller_brdf
from ppr.brdf._microfacet import joint_visibility, mean_cosine_n, ndf, visibility
from ppr.materials._material import Material
from ppr.optics._frames import default_frame, facet_mueller_in_beam_frames, jones_to_mueller
from ppr.optics.polarimetry import cloude_eigenvalues

Z = np.array([0.0, 0.0, 1.0])

# The core model of this file (issue 2): single bounce + multiple-scattering remainder. Tests
# of numerics and machinery (float32, JVP, vmap, validation) run on it; the default terms add
# the double bounce, whose own float32, reciprocity and realizability tests are in
# tests/test_double.py (compiling the double term costs ~10 s per distinct jit, so it is not
# repeated here). Stiff and grazing geometry of every term: tests/test_grazing.py.
CORE = ("single", "multiple")


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _dir(theta, phi):
    return np.stack(
        [
            np.sin(theta) * np.cos(phi),
            np.sin(theta) * np.sin(phi),
            np.cos(theta) * np.ones_like(phi),
        ],
        axis=-1,
    )


def _random_upper(rng, n, min_cos=0.02):
    mu = rng.uniform(min_cos, 1.0, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    return _dir(np.arccos(mu), phi)


def _random_perp(rng, k):
    a = rng.normal(size=k.shape)
    a = a - np.sum(a * k, -1, keepdims=True) * k
    return _unit(a)


def _random_materials(rng, n):
    """Batched materials: metals, dielectrics, n = 1, roughness over the full range."""
    m = 10.0 ** rng.uniform(-3, 6, n)
    m[:3] = [0.0, 1.0, 1e6]
    kind = rng.integers(0, 3, n)
    n_re = np.where(kind == 0, rng.uniform(0.1, 2.0, n), rng.uniform(1.0, 3.0, n))
    n_im = np.where(
        kind == 0, rng.uniform(2.0, 10.0, n), np.where(kind == 1, 0.0, rng.uniform(0, 0.5, n))
    )
    return Material(n=n_re + 1j * n_im, m=m)


_brdf_jit = jax.jit(
    lambda ki, ko, nr, mat, fi, fo: mueller_brdf(ki, ko, nr, mat, frame_in=fi, frame_out=fo)
)


# ----------------------------------------------------------------------------- reciprocity


def test_reciprocity_transform_of_jones_transpose():
    """Derivation check. Reciprocity (Saxon) for the scattering dyadic: S(k_in -> k_out) seen
    from the reversed path is S^T. With reversed-path frames x_in' = x_out, x_out' = x_in the
    y axes flip (y = d x x with d reversed), so J_rev = D J^T D, D = diag(1, -1). In the
    Stokes convention of ppr.optics.conventions, Mueller(J^T) = diag(1,1,1,-1) M^T diag(1,1,1,-1)
    and Mueller(D X D) = diag(1,1,-1,-1) Mueller(X) diag(1,1,-1,-1), so
    M_rev = Q M^T Q with Q = diag(1, 1, -1, 1). Checked here on random Jones matrices."""
    rng = np.random.default_rng(0)
    J = rng.normal(size=(20, 2, 2)) + 1j * rng.normal(size=(20, 2, 2))
    D = np.diag([1.0, -1.0])
    J_rev = D @ np.swapaxes(J, -1, -2) @ D
    M = np.asarray(jones_to_mueller(jnp.asarray(J)))
    M_rev = np.asarray(jones_to_mueller(jnp.asarray(J_rev)))
    Q = np.diag([1.0, 1.0, -1.0, 1.0])
    np.testing.assert_allclose(M_rev, Q @ np.swapaxes(M, -1, -2) @ Q, atol=1e-12)


def test_reciprocity_random_geometries_and_materials():
    rng = np.random.default_rng(1)
    n = 256
    ki, ko = _random_upper(rng, n), _random_upper(rng, n)
    xi, xo = _random_perp(rng, ki), _random_perp(rng, ko)
    mat = _random_materials(rng, n)
    M = np.asarray(_brdf_jit(ki, ko, Z, mat, xi, xo))
    M_rev = np.asarray(_brdf_jit(ko, ki, Z, mat, xo, xi))
    Q = np.diag([1.0, 1.0, -1.0, 1.0])
    expect = Q @ np.swapaxes(M, -1, -2) @ Q
    scale = np.max(np.abs(M), axis=(-2, -1), keepdims=True) + 1e-300
    # rounding only: the kernel is symmetric except for the order of floating-point ops
    np.testing.assert_allclose(M_rev / scale, expect / scale, atol=1e-10)
    assert np.all(M[..., 0, 0] >= 0)


# ----------------------------------------------------------------------------- realizability


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_realizable_random(dtype):
    rng = np.random.default_rng(2)
    n = 512
    ki, ko = _random_upper(rng, n, 1e-3), _random_upper(rng, n, 1e-3)
    ko[:16] = ki[:16]  # exact backscatter
    mat = _random_materials(rng, n)
    cdt = jnp.complex64 if dtype == jnp.float32 else jnp.complex128
    mat = Material(n=jnp.asarray(mat.n, cdt), m=jnp.asarray(mat.m, dtype))
    M = mueller_brdf(
        jnp.asarray(ki, dtype), jnp.asarray(ko, dtype), jnp.asarray(Z, dtype), mat, terms=CORE
    )
    assert M.dtype == dtype
    w = np.asarray(cloude_eigenvalues(M.astype(jnp.float64)))
    m00 = np.asarray(M[..., 0, 0], np.float64)
    # eigenvalues of a sum of rank-1 coherency matrices; rounding of the 4x4 entries
    tol = 1e-10 if dtype == jnp.float64 else 2e-6
    # float32 flushes entries below its normal range (1.2e-38) to 0: a glossy single term of
    # 1.7e-35 /sr (m = 1329, 57 deg -> 17 deg, where the multiple-scattering remainder is
    # ~1e-60 and no longer masks it) loses its smallest entries, eigenvalue -2.5e-39
    floor = 0.0 if dtype == jnp.float64 else 16 * float(np.finfo(np.float32).tiny)
    assert np.all(w[..., -1] >= -(tol * m00 + floor)), np.min(w[..., -1] - (-tol * m00))


# ----------------------------------------------------------------------------- components


def test_single_term_equals_assembly_of_public_pieces():
    """Single term = ndf(h.n) P(k|k') / (4 <h.n> (k.n)(k'.n)) x facet Mueller in the beam
    frames, each piece from the public functions of ppr.brdf._microfacet / ppr.optics._frames
    (AoS)."""
    rng = np.random.default_rng(3)
    n = 200
    ki, ko = _random_upper(rng, n), _random_upper(rng, n)
    mat = _random_materials(rng, n)
    M = np.asarray(mueller_brdf(ki, ko, Z, mat, terms=("single",)))
    h = _unit(ki + ko)

    @jax.jit  # the reference in one program (eager, its pieces compile op by op)
    def reference(ki, ko, h, m, n):
        xi, xo = default_frame(-ki, Z), default_frame(ko, Z)
        p = ndf(m, h @ Z)
        pk = joint_visibility(m, ki, ko, Z, order=256)
        scal = p * pk / (4 * mean_cosine_n(m) * (ki @ Z) * (ko @ Z))
        F = facet_mueller_in_beam_frames(jnp.real(n), jnp.imag(n), ki, ko, h, xi, xo)
        return scal[..., None, None] * F

    ref = np.asarray(reference(ki, ko, h, mat.m, mat.n))
    scale = np.max(np.abs(ref), axis=(-2, -1), keepdims=True) + 1e-300
    # visibility order 64 vs 256 (2e-14) and (h.n)^m via |h - n|^2 vs 1 - h.n (m up to 1e6:
    # relative 1e6 * 1e-16 / (1 - h.n)); 1e-9 covers both
    np.testing.assert_allclose(M / scale, ref / scale, atol=1e-9)


@pytest.mark.parametrize("n_index", [1.5, 0.94 + 6.42j, 0.2 + 7j])
@pytest.mark.parametrize("m", [0.0, 1.0, 100.0, 1e4])
def test_monostatic_backscatter_closed_form(n_index, m):
    """k_out = k_in: h = k, every facet at normal incidence, P(k|k) = P(k):
    M = p(k) P(k) |r0|^2 diag(1, 1, -1, -1) / (4 <h.n> (k.n)^2), r0 = (n - 1)/(n + 1).
    The default frames at backscatter are x_out = -x_in (y_out = y_in): a mirror at normal
    incidence maps (E_x, E_y) -> (E_x, -E_y) there, hence diag(1, 1, -1, -1)."""
    theta = np.deg2rad([0.0, 20.0, 50.0, 80.0])
    k = _dir(theta, np.full_like(theta, 0.3))
    mat = Material(n=n_index, m=m)
    M = np.asarray(mueller_brdf(k, k, Z, mat, terms=("single",)))
    mu = np.cos(theta)
    r0 = abs((n_index - 1) / (n_index + 1)) ** 2
    p = (m + 1) / (2 * np.pi) * mu**m
    P = np.asarray(visibility(m, mu, order=256))
    hn = (m + 1) / (m + 2)
    f = p * P * r0 / (4 * hn * mu**2)
    ref = f[:, None, None] * np.diag([1.0, 1.0, -1.0, -1.0])
    np.testing.assert_allclose(M, ref, rtol=1e-9, atol=1e-12 * np.max(f))


# ----------------------------------------------------------------------------- limits


def _lobe_integral(mat, theta_in, n_phi=32, n_w=16):
    """int M(k_in, k_out) (k_out.n) d omega_out by the half-vector quadrature of _albedo."""
    k_in, k_out, wt = _albedo.albedo_nodes(float(mat.m), np.cos(theta_in), n_phi, n_w)
    k_spec = np.array([-k_in[0], -k_in[1], k_in[2]])
    # one fixed frame per beam, valid over the whole narrow lobe: project the specular one
    xo = np.asarray(default_frame(k_spec, Z))
    xo = _unit(xo - np.sum(xo * k_out, -1, keepdims=True) * k_out)
    xi = np.asarray(default_frame(-k_in, Z))
    # the nodes cover phi_h in [0, pi] with weights doubled for the mirror half; only M00 is
    # mirror-symmetric, so evaluate the mirrored nodes too and average
    flip = np.array([1.0, -1.0, 1.0])
    kw = dict(frame_in=xi, terms=CORE)
    M = np.asarray(mueller_brdf(k_in, k_out, Z, mat, frame_out=xo, **kw))
    Mf = np.asarray(mueller_brdf(k_in, k_out * flip, Z, mat, frame_out=xo * flip, **kw))
    return 0.5 * np.einsum("q,qij->ij", wt, M + Mf), k_in, k_spec, xi


@pytest.mark.parametrize("m", [1e5, 1e6])
@pytest.mark.parametrize("n_index", [1.5, 0.94 + 6.42j])
def test_large_m_reproduces_mirror(m, n_index):
    for theta in np.deg2rad([10.0, 45.0, 70.0]):
        mat = Material(n=n_index, m=m)
        integral, k_in, k_spec, xi = _lobe_integral(mat, theta)
        F = np.asarray(
            facet_mueller_in_beam_frames(
                np.real(n_index), np.imag(n_index), k_in, k_spec, Z, xi, default_frame(k_spec, Z)
            )
        )
        # Fresnel varies across the lobe (width ~1/sqrt(m) <= 3e-3 rad) and the remainder is
        # O(1e-6) here: 1e-3 of the mirror's M00
        np.testing.assert_allclose(integral, F, atol=1e-3 * F[0, 0])


def test_m0_near_lambertian():
    """m = 0 (white: single + multiple): the BRDF is smooth and within a factor band of the
    Lambertian 1/pi for outgoing zenith <= 60 deg at incidences <= 60 deg. Measured range of
    pi f: [0.93, 1.48]; asserted band [0.85, 1.6] (APS at m = 0 is 'Lambertian-like', not
    Lambertian: the single term rises toward the back-scatter direction)."""
    th_o, ph_o = np.meshgrid(np.deg2rad(np.linspace(0, 60, 13)), np.linspace(0, np.pi, 13))
    ko = _dir(th_o.ravel(), ph_o.ravel())
    vals = []
    for th_i in np.deg2rad([0.0, 30.0, 60.0]):
        ki = _dir(np.array(th_i), np.array(0.0))
        M = mueller_brdf(ki, ko, Z, Material.ideal_white(0.0))
        vals.append(np.asarray(M[:, 0, 0]) * np.pi)
    vals = np.concatenate(vals)
    assert 0.85 <= vals.min() and vals.max() <= 1.6, (vals.min(), vals.max())
    # no jumps: samples 5 deg (zenith) / 15 deg (azimuth) apart differ by < 35 % (measured
    # 31 %, on the rise toward back-scatter)
    grid = vals.reshape(3, 13, 13)
    assert np.max(np.abs(np.diff(grid, axis=-1)) / grid[..., 1:]) < 0.35
    assert np.max(np.abs(np.diff(grid, axis=-2)) / grid[:, 1:]) < 0.35


# stiff and grazing cases (finite values and gradients): tests/test_grazing.py


def test_float32_matches_float64():
    """Float32 vs float64, 2000 random geometries and materials (m <= 1e4).

    Single term: relative error per element (floor 1e-30 /sr: far lobe tails at m ~ 1e4 fall
    below float32's normal range), measured 4.1e-5; float32 rounding of directions (1e-7)
    amplified by the lobe exponent m (1 - h.n ~ 1/m): ~ m * 1e-7 * |h - n| <~ 1e-4 at m = 1e4.
    Core total (single + remainder): the remainder's deficit D(m, mu) is a Catmull-Rom blend of
    table nodes spanning many decades, so where D ~ 1e-9 sits next to nodes of 1e-2 float32
    leaves ~1e-9 absolute, i.e. a large *relative* error of a negligible value (measured 8.7e-3
    at M00 = 1.6e-18 /sr). Relative to max(|M|, 1e-12 /sr) (12 decades below a Lambertian
    surface) the measured error is 2.3e-4."""
    rng = np.random.default_rng(5)
    n = 2000
    ki, ko = _random_upper(rng, n, 0.05), _random_upper(rng, n, 0.05)
    mat = _random_materials(rng, n)
    mat = Material(n=mat.n, m=np.minimum(mat.m, 1e4))
    mat32 = Material(n=jnp.asarray(mat.n, jnp.complex64), m=jnp.asarray(mat.m, jnp.float32))
    a32 = [jnp.asarray(a, jnp.float32) for a in (ki, ko, Z)]
    for terms, floor, tol in [(("single",), 1e-30, 1e-4), (CORE, 1e-12, 5e-4)]:
        M64 = np.asarray(mueller_brdf(ki, ko, Z, mat, terms=terms))
        M32 = mueller_brdf(*a32, mat32, terms=terms)
        assert M32.dtype == jnp.float32
        scale = np.maximum(np.max(np.abs(M64), axis=(-2, -1), keepdims=True), floor)
        err = np.max(np.abs(np.asarray(M32, np.float64) - M64) / scale)
        assert err < tol, (terms, err)


def test_jvp_matches_central_differences():
    rng = np.random.default_rng(6)

    def f(p):
        th_i, th_o, ph_o, log_m, n_re, n_im = p
        ki = jnp.stack([jnp.sin(th_i), 0.0 * th_i, jnp.cos(th_i)])
        ko = jnp.stack(
            [jnp.sin(th_o) * jnp.cos(ph_o), jnp.sin(th_o) * jnp.sin(ph_o), jnp.cos(th_o)]
        )
        mat = Material(n=n_re + 1j * n_im, m=jnp.exp(log_m))
        return mueller_brdf(ki, ko, jnp.asarray(Z), mat, terms=CORE).ravel()

    f_jit = jax.jit(f)
    jvp = jax.jit(lambda p, t: jax.jvp(f, (p,), (t,))[1])
    for p in [
        [0.3, 1.0, 2.0, np.log(10.0), 1.5, 0.01],
        [1.2, 0.8, 3.0, np.log(300.0), 0.94, 6.42],
        [0.7, 1.45, 1.0, np.log(0.5), 0.2, 7.0],
        [1.5, 1.5, 0.4, np.log(3e3), 2.6, 0.1],
    ]:
        p = jnp.asarray(p)
        t = jnp.asarray(rng.normal(size=6))
        h = 1e-6
        fd = (f_jit(p + h * t) - f_jit(p - h * t)) / (2 * h)
        an = jvp(p, t)
        scale = float(jnp.max(jnp.abs(an))) + 1e-300
        # central differences: O(h^2) truncation + rounding eps/h ~ 1e-10 relative
        np.testing.assert_allclose(np.asarray(an) / scale, np.asarray(fd) / scale, atol=1e-6)


def test_vmap_equals_loop_and_broadcasting():
    rng = np.random.default_rng(7)
    ki, ko = _random_upper(rng, 6), _random_upper(rng, 6)
    ms = np.array([0.0, 0.5, 10.0, 1e3, 1e5, 1e6])
    ns = np.array([1.5, 0.94 + 6.42j, 1.0, 2.6, 0.54 + 2.23j, 1.46])
    batched = np.asarray(mueller_brdf(ki, ko, Z, Material(n=ns, m=ms), terms=CORE))
    vm = jax.jit(
        jax.vmap(  # jitted: the vmapped trace in one program, not op by op
            lambda a, b, m, n: mueller_brdf(a, b, jnp.asarray(Z), Material(n=n, m=m), terms=CORE)
        )
    )
    vmapped = np.asarray(vm(jnp.asarray(ki), jnp.asarray(ko), jnp.asarray(ms), jnp.asarray(ns)))
    loop = np.stack(
        [
            np.asarray(mueller_brdf(ki[i], ko[i], Z, Material(n=ns[i], m=ms[i]), terms=CORE))
            for i in range(6)
        ]
    )
    np.testing.assert_allclose(batched, loop, rtol=1e-12, atol=0)
    np.testing.assert_allclose(vmapped, loop, rtol=1e-12, atol=0)
    # broadcasting: (3, 1, 3) x (1, 4, 3) -> (3, 4, 4, 4)
    out = mueller_brdf(ki[:3, None], ko[None, :4], Z, Material(n=1.5, m=10.0), terms=CORE)
    assert out.shape == (3, 4, 4, 4)
    # eager calls are padded to a bucket (ppr.brdf._brdf.eager_bucket; the comparisons with the
    # traced vmap above check the padded results): (2, 6) is another shape of 12 rows, so
    # it reuses the program of (3, 4)
    from ppr.brdf._brdf import _brdf_core

    n0 = _brdf_core._cache_size()
    out26 = mueller_brdf(ki[:2, None], ko[None, :6], Z, Material(n=1.5, m=10.0), terms=CORE)
    assert _brdf_core._cache_size() == n0
    np.testing.assert_allclose(np.asarray(out26)[:, :4], np.asarray(out)[:2], rtol=1e-13)
    np.testing.assert_allclose(
        np.asarray(out[1, 2]),
        np.asarray(mueller_brdf(ki[1], ko[2], Z, Material(n=1.5, m=10.0), terms=CORE)),
        rtol=1e-12,
    )


def test_eager_bucket_sizes():
    """Eager calls pad their flattened batch to ppr.brdf._brdf.eager_bucket(n): at least n, at most
    25 % more above 8 rows (the padded results are checked against the traced path in
    test_vmap_equals_loop_and_broadcasting)."""
    from ppr.brdf._brdf import eager_bucket

    assert [eager_bucket(n) for n in (1, 8, 9, 17, 100, 4096, 4097)] == [
        8,
        8,
        10,
        20,
        112,
        4096,
        5120,
    ]
    assert eager_bucket(0) is None
    sizes = [eager_bucket(n) for n in range(1, 100_000)]
    assert all(n <= b <= max(8, 1.25 * n) for n, b in enumerate(sizes, 1))
    assert len(set(sizes)) == 56  # 4 programs per factor of 2 in batch size


def test_terms_add_up_and_registry_errors():
    rng = np.random.default_rng(8)
    ki, ko = _random_upper(rng, 10), _random_upper(rng, 10)
    mat = Material(n=0.94 + 6.42j, m=3.0)
    names = ppr.brdf._brdf.implemented_terms()

    @jax.jit  # one compilation for the full model and every term alone
    def full_and_parts(ki, ko):
        full = mueller_brdf(ki, ko, jnp.asarray(Z), mat)
        return full, sum(mueller_brdf(ki, ko, jnp.asarray(Z), mat, terms=(t,)) for t in names)

    full, parts = full_and_parts(jnp.asarray(ki), jnp.asarray(ko))
    np.testing.assert_allclose(np.asarray(full), np.asarray(parts), rtol=1e-13)
    with pytest.raises(ValueError, match="terms"):
        mueller_brdf(ki, ko, Z, mat, terms=("singel",))
    if "double" not in ppr.brdf._brdf.implemented_terms():
        with pytest.raises(NotImplementedError, match="double"):
            mueller_brdf(ki, ko, Z, mat, terms=("double",))
    # the multiple term is depolarizing: only M00
    Mm = np.asarray(mueller_brdf(ki, ko, Z, mat, terms="multiple"))
    assert np.all(Mm[..., 0, 0] > 0) and np.all(Mm.reshape(10, 16)[:, 1:] == 0)


def test_export():
    assert ppr.mueller_brdf is mueller_brdf


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(k_in=[0.0, 0.0, 1.0, 0.0]), "k_in"),
        (dict(k_out=[[0.0, 1.0]]), "k_out"),
        (dict(normal=[0.0, 0.0, 2.0]), "normal"),
        (dict(k_in=[0.0, 0.0, np.nan]), "k_in"),
        (dict(k_out=[0.0, 0.6, -0.8]), "k_out"),
        (dict(k_in=[0.0, 0.0, 1.01]), "k_in"),
        (dict(frame_in=[0.0, 0.0, 1.0]), "frame_in"),
        (dict(frame_out=[1.0, 1.0, 0.0]), "frame_out"),
        (
            dict(k_in=np.zeros((2, 3)) + [0, 0, 1.0], k_out=np.zeros((3, 3)) + [0, 0, 1.0]),
            "broadcast",
        ),
    ],
)
def test_bad_directions_raise_naming_argument(kwargs, name):
    args = dict(k_in=[0.0, 0.0, 1.0], k_out=[0.6, 0.0, 0.8], normal=[0.0, 0.0, 1.0])
    args.update(kwargs)
    frames = {k: args.pop(k) for k in ("frame_in", "frame_out") if k in args}
    with pytest.raises(ValueError, match=name):
        mueller_brdf(args["k_in"], args["k_out"], args["normal"], Material(n=1.5, m=10.0), **frames)


# equinox's runtime check surfaces as EquinoxRuntimeError, or, depending on the jax version and
# the thread the callback runs on, wrapped in XLA's ValueError / jax.errors.JaxRuntimeError;
# the message (matched below) names the offending field in every case.
_RUNTIME_ERRORS = (eqx.EquinoxRuntimeError, ValueError, jax.errors.JaxRuntimeError)


def test_wavelength_not_in_metres_raises():
    """A NaN, non-positive or nanometre wavelength (the coherent backscatter peak and film
    phases scale with it) is refused by the BRDF and the sensor, not computed."""
    k = _unit([0.2, 0.0, 1.0])
    for bad in (np.nan, 0.0, -532e-9, 532.0):
        with pytest.raises(ValueError, match="wavelength must be a finite length in metres"):
            mueller_brdf(k, k, jnp.asarray(Z), Material(n=1.5, m=10.0), wavelength=bad)
    with pytest.raises(ValueError, match=r"Sensor.wavelength .* nanometres"):
        ppr.Sensor.make(wavelength=532.0)
    assert np.isfinite(
        np.asarray(mueller_brdf(k, k, jnp.asarray(Z), Material(n=1.5, m=10.0), wavelength=1064e-9))
    ).all()


def test_bad_material_raises():
    with pytest.raises(ValueError, match="m"):
        Material(n=1.5, m=-1.0)
    with pytest.raises(ValueError, match="imaginary"):
        Material(n=1.5 - 0.1j, m=1.0)
    with pytest.raises(ValueError, match="finite"):
        Material(n=np.nan, m=1.0)

    # traced materials get checked inside the kernel (eqx.error_if)
    @jax.jit
    def f(m, n_im):
        mat = Material(n=1.5 + 1j * n_im, m=m)
        return mueller_brdf(jnp.asarray(Z), _unit([0.2, 0.0, 1.0]), jnp.asarray(Z), mat, terms=CORE)

    assert np.all(np.isfinite(np.asarray(f(1.0, 0.0))))
    # under jax.jit the equinox error surfaces as EquinoxRuntimeError or XLA's ValueError
    with pytest.raises(_RUNTIME_ERRORS, match="material.m"):
        f(-1.0, 0.0)
    with pytest.raises(_RUNTIME_ERRORS, match="material.n"):
        f(1.0, -0.5)

    @jax.jit
    def g(k):
        return mueller_brdf(k, jnp.asarray(Z), jnp.asarray(Z), Material(n=1.5, m=1.0), terms=CORE)

    with pytest.raises(_RUNTIME_ERRORS, match="k_in"):
        g(jnp.asarray([0.0, 0.6, -0.8]))


def test_unchecked_variant_same_values_no_host_callback():
    """``mueller_brdf_unchecked`` (the inversion's kernels: inputs valid by construction)
    returns the checked BRDF's values (to round-off), its compiled program holds no host
    callback (so JAX's persistent compilation cache can store it: programs with one are never
    written), and concrete bad input still raises."""
    import re

    from ppr.brdf._brdf import mueller_brdf_unchecked

    rng = np.random.default_rng(5)
    k, kp = rng.normal(size=(2, 64, 3))
    k[:, 2], kp[:, 2] = np.abs(k[:, 2]) + 0.1, np.abs(kp[:, 2]) + 0.1  # upper hemisphere
    k, kp = (jnp.asarray(a / np.linalg.norm(a, axis=1, keepdims=True)) for a in (k, kp))
    mat = Material(n=jnp.asarray(0.94 + 6.42j), m=jnp.asarray(rng.uniform(0.5, 50.0, 64)))
    out = {}
    for name, fn in (("checked", mueller_brdf), ("unchecked", mueller_brdf_unchecked)):
        f = jax.jit(lambda a, b, mt, fn=fn: fn(a, b, jnp.asarray(Z), mt, terms=CORE))
        calls = set(re.findall(r"custom_call @(\w+)", f.lower(k, kp, mat).as_text()))
        out[name] = (np.asarray(f(k, kp, mat)), any("callback" in c for c in calls))
    # round-off only: the checks' reductions change how XLA fuses the kernel
    np.testing.assert_allclose(out["unchecked"][0], out["checked"][0], rtol=1e-12, atol=1e-15)
    assert out["checked"][1] and not out["unchecked"][1]
    with pytest.raises(ValueError, match="k_in"):
        mueller_brdf_unchecked(np.array([0.0, 0.6, -0.8]), Z, Z, Material(n=1.5, m=1.0))


def test_grazing_is_zero_with_finite_gradient():
    def f(k):
        mat = Material(n=1.5, m=0.0)
        return jnp.sum(mueller_brdf(k, _unit([0.3, 0.2, 1.0]), jnp.asarray(Z), mat, terms=CORE))

    f_and_grad = jax.jit(jax.value_and_grad(f))  # the double term's grazing rows: test_double
    k = jnp.asarray([1.0, 0.0, 0.0])
    val, grad = f_and_grad(k)
    assert float(val) == 0.0
    assert np.all(np.isfinite(np.asarray(grad)))
    # slightly below the horizon but within HORIZON_TOL counts as grazing
    val2, grad2 = f_and_grad(jnp.asarray(_unit([1.0, 0.0, -1e-6])))
    assert float(val2) == 0.0
    assert np.all(np.isfinite(np.asarray(grad2)))


def test_white_material_is_perfect_conductor_facets():
    """Ideal white: facet Mueller = diag(1,1,-1,-1) in its s/p frames, i.e. the n -> i inf
    limit of a metal; compare with n = 1 + 1e6 i (|r|^2 = 1 - O(1e-6))."""
    rng = np.random.default_rng(9)
    ki, ko = _random_upper(rng, 50), _random_upper(rng, 50)
    Mw = np.asarray(mueller_brdf(ki, ko, Z, Material.ideal_white(20.0), terms="single"))
    Mc = np.asarray(mueller_brdf(ki, ko, Z, Material(n=1 + 1e6j, m=20.0), terms="single"))
    scale = np.max(np.abs(Mw), axis=(-2, -1), keepdims=True) + 1e-300
    np.testing.assert_allclose(Mc / scale, Mw / scale, atol=1e-5)
    assert math.isclose(float(ppr.brdf._brdf.fresnel_average(Material.ideal_white(1.0))), 1.0)


@pytest.mark.parametrize("dtype, tol", [(np.float32, 2e-5), (np.float64, 1e-12)])
def test_one_material_fast_paths_match_per_element(dtype, tol):
    """A scalar material takes the per-material fast paths (float32: P(k) from the tabulated
    correction; both dtypes: the albedo deficit interpolated in m once). They must agree with
    the same material broadcast per element (quadrature, 2-D table), relative to each
    matrix's M00: float64 to rounding; float32 to 2e-5, the float32 rounding of the deficit
    interpolation summed in the other order where the depolarizing remainder dominates
    (measured 6e-6; the visibility table alone agrees to ~1e-6)."""
    rng = np.random.default_rng(21)
    n = 512
    ki = _random_upper(rng, n, min_cos=1e-4).astype(dtype)
    ko = _random_upper(rng, n, min_cos=1e-4).astype(dtype)
    cdt = np.complex64 if dtype == np.float32 else np.complex128
    f = jax.jit(
        lambda ki, ko, mat: mueller_brdf(ki, ko, Z.astype(dtype), mat, terms=("single", "multiple"))
    )
    for n_idx, m in ((0.94 + 6.42j, 300.0), (1.46 + 0j, 3.0), (2.67 + 0j, 0.3)):
        one = Material(n=jnp.asarray(n_idx, cdt), m=jnp.asarray(m, dtype))
        per = Material(n=jnp.full(n, n_idx, cdt), m=jnp.full(n, m, dtype))
        a = np.asarray(f(ki, ko, one), np.float64)
        b = np.asarray(f(ki, ko, per), np.float64)
        scale = np.maximum(np.abs(b[:, :1, :1]), 1e-30)
        np.testing.assert_allclose(a / scale, b / scale, rtol=0, atol=tol, err_msg=f"m = {m}")


def test_derivative_in_m_at_zero_is_the_one_sided_limit():
    """``m = 0`` is a bound a fit can sit on: there the gradient of every term (single, the
    multiple-scattering remainder's table, the double term's backscatter table and its
    quadrature) is the one-sided derivative into ``m > 0``, the limit of the difference
    quotients (the tables' clamp at their first node split the gradient of a tie in half and
    the lobe's ``m log cos`` was masked at ``m = 0``: AD gave 0.082 for 0.057 on the sum)."""
    k = np.array([math.sin(0.5), 0.0, math.cos(0.5)])
    kp = np.array([math.sin(-0.2), 0.1, math.cos(0.2)])
    kp /= np.linalg.norm(kp)
    nrm = jnp.asarray([0.0, 0.0, 1.0])
    # monostatic: the tables (the double term's quadrature, off backscatter, was right: not
    # compiled here, it is the costly branch)
    cases = [(k, k, t) for t in ("single", "multiple", "double")]
    cases += [(k, kp, t) for t in ("single", "multiple")]

    def f(m):
        mat = ppr.Material(0.94 + 6.42j, m)
        return jnp.stack(
            [
                mueller_brdf(jnp.asarray(a), jnp.asarray(b), nrm, mat, terms=(t,))[0, 0]
                for a, b, t in cases
            ]
        )

    # one program: values and forward-mode derivatives (the suite pays one compilation)
    value_and_slope = jax.jit(lambda m: jax.jvp(f, (m,), (jnp.ones_like(m),)))
    f0, g0 = (np.asarray(a) for a in value_and_slope(jnp.asarray(0.0)))
    h = 1e-7
    fd = (np.asarray(value_and_slope(jnp.asarray(h))[0]) - f0) / h
    np.testing.assert_allclose(g0, fd, rtol=1e-5)
    assert np.all(np.abs(g0) > 1e-3)  # every term moves with m there
