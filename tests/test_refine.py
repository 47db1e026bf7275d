"""Refiners (inversion._refine, _params, _jaxopt_adapter): recovery, gradients, bad input.

The forward model here is a small analytic *toy* with the physical shape of a PPR return
(facets with Blinn-Phong lobes, Fresnel Mueller matrices rotated into the sensor frame,
Gaussian range pulses, 16 PSG x PSA channels, gain and range offset), so the inversion
machinery is tested independently of the pulse simulator; the simulator-backed tests are at
the end (skipped when ``ppr.simulate`` is not available).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from inversion._params import Parametrisation, PhysicalParams
from inversion._refine import (
    GaussianNoise,
    PoissonCounts,
    PoissonNoise,
    check_observation,
    cramer_rao,
    refine,
)
from ppr._safe import safe_div, safe_pow
from ppr.geometry import quat_angle_deg, quat_from_rotvec, quat_multiply, rotvec_from_quat
from ppr.optics._fresnel import fresnel_mueller_params

STATES = np.array([[1, 1, 0, 0], [1, -1, 0, 0], [1, 0, 1, 0], [1, 0, 0, 1]], float)


def quat_to_matrix(q):
    q = q / jnp.linalg.norm(q)
    w, x, y, z = q
    return jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


class ToyFacetModel(eqx.Module):
    """Toy PPR forward model: F flat facets, sensor looking along -z (k toward sensor = +z).

    Facet f (unit normal N_f, centre c_f, area A_f, material slot) returns
    ``A_f vis_f (m+2)/(2 pi) cos^m(theta_f) / 4`` times a Fresnel Mueller matrix at the facet's
    incidence angle rotated by the azimuth of its normal, spread over range as a Gaussian of
    width ``sigma_r`` centred at ``-z(c_f) + range_offset``. Channels: 16 PSG x PSA pairs of
    {H, V, D, R}. Visibility ``vis_f = [cos theta_f > 0]`` is computed on the host (prepare).
    """

    normals: jax.Array
    centers: jax.Array
    areas: jax.Array
    mat_ids: jax.Array
    bins: jax.Array
    photons: float = eqx.field(static=True, default=2e4)
    sigma_r: float = eqx.field(static=True, default=0.03)

    def prepare(self, phys):
        R = np.asarray(quat_to_matrix(jnp.asarray(phys.quaternion)))
        cos = np.asarray(self.normals) @ R.T[:, 2]
        return jnp.asarray((cos > 0).astype(np.float64))

    def expected(self, phys, vis):
        R = quat_to_matrix(phys.quaternion)
        nrm = self.normals @ R.T
        cen = self.centers @ R.T
        cos = jnp.clip(nrm[:, 2], 0.0, 1.0)
        m = phys.m[self.mat_ids]
        n = phys.n[self.mat_ids]
        lobe = (m + 2) / (2 * jnp.pi) * safe_pow(cos, m) / 4
        a, b, c, d = fresnel_mueller_params(jnp.real(n), jnp.imag(n), cos)
        nx, ny = nrm[:, 0], nrm[:, 1]
        rho2 = nx * nx + ny * ny
        c2 = safe_div(nx * nx - ny * ny, rho2, 1.0)
        s2 = safe_div(2 * nx * ny, rho2, 0.0)
        z = jnp.zeros_like(a)
        o = jnp.ones_like(a)
        MF = jnp.stack(
            [
                jnp.stack([a, b, z, z], -1),
                jnp.stack([b, a, z, z], -1),
                jnp.stack([z, z, c, d], -1),
                jnp.stack([z, z, -d, c], -1),
            ],
            -2,
        )
        Rot = jnp.stack(
            [
                jnp.stack([o, z, z, z], -1),
                jnp.stack([z, c2, s2, z], -1),
                jnp.stack([z, -s2, c2, z], -1),
                jnp.stack([z, z, z, o], -1),
            ],
            -2,
        )
        RotT = jnp.swapaxes(Rot, -1, -2)
        M = RotT @ MF @ Rot  # (F, 4, 4)
        amp = self.photons * phys.gain * self.areas * vis * lobe
        r_f = -cen[:, 2] + phys.range_offset
        prof = jnp.exp(-0.5 * ((self.bins[None, :] - r_f[:, None]) / self.sigma_r) ** 2)
        S = jnp.asarray(STATES, M.dtype)
        ch = 0.5 * jnp.einsum("ai,fij,gj->fga", S, M, S).reshape(M.shape[0], 16)
        return jnp.einsum("f,fk,fb->kb", amp, ch, prof)


def make_toy(n_bins=48, seed=0, edge_on=False):
    rng = np.random.default_rng(seed)
    F = 7
    normals = rng.normal(size=(F, 3))
    normals[:, 2] = np.abs(normals[:, 2]) + 0.8
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    if edge_on:
        normals[0] = [1.0, 0.0, 0.0]  # exactly edge-on at the identity attitude
    centers = rng.uniform(-0.2, 0.2, size=(F, 3))
    areas = rng.uniform(0.5, 1.5, size=F)
    mat_ids = np.array([0, 0, 0, 0, 1, 1, 1])
    bins = np.linspace(-0.45, 0.45, n_bins)
    return ToyFacetModel(
        jnp.asarray(normals),
        jnp.asarray(centers),
        jnp.asarray(areas),
        jnp.asarray(mat_ids),
        jnp.asarray(bins),
    )


class TinyModel(eqx.Module):
    """A cheap model (fast to compile) for solver plumbing tests: 12 channels of Fresnel
    Mueller parameters (a, b, c) at 4 incidence angles times a Gaussian pulse whose width
    depends on m, shifted by the range offset, times the gain. Attitude does not enter."""

    bins: jax.Array

    def prepare(self, phys):
        return jnp.ones((), self.bins.dtype)

    def expected(self, phys, aux):
        cos_t = jnp.array([1.0, 0.8, 0.5, 0.2], self.bins.dtype)
        a, b, c, _ = fresnel_mueller_params(jnp.real(phys.n[0]), jnp.imag(phys.n[0]), cos_t)
        amp = jnp.concatenate([a, b, c])
        width = 0.02 * (1.0 + 3.0 / jnp.sqrt(phys.m[0] + 1.0))
        prof = jnp.exp(-0.5 * ((self.bins - phys.range_offset) / width) ** 2)
        return 1e3 * phys.gain * amp[:, None] * prof[None, :] * aux


class TinyCounts(TinyModel):
    """TinyModel with non-negative channels (analyzer intensities ``a +- b``, ``a +- c`` of the
    Fresnel Mueller matrix, 16 channels): expected photo-counts for the Poisson tests."""

    def expected(self, phys, aux):
        cos_t = jnp.array([1.0, 0.8, 0.5, 0.2], self.bins.dtype)
        a, b, c, _ = fresnel_mueller_params(jnp.real(phys.n[0]), jnp.imag(phys.n[0]), cos_t)
        amp = jnp.concatenate([a + b, a - b, a + c, a - c])
        width = 0.02 * (1.0 + 3.0 / jnp.sqrt(phys.m[0] + 1.0))
        prof = jnp.exp(-0.5 * ((self.bins - phys.range_offset) / width) ** 2)
        return 1e3 * phys.gain * amp[:, None] * prof[None, :] * aux


TINY_FREE = ("m", "n", "range_offset", "gain")
TINY_TRUTH = PhysicalParams([1.0, 0, 0, 0], [12.0], [1.3 + 0.4j], range_offset=0.01, gain=2.0)


def tiny_start():
    return PhysicalParams([1.0, 0, 0, 0], [8.0], [1.6 + 0.2j], range_offset=0.0, gain=1.0)


TRUTH = PhysicalParams(
    quaternion=np.array([1.0, 0.0, 0.0, 0.0]),
    m=np.array([6.0, 20.0]),
    n=np.array([1.5 + 0.0j, 1.2 + 5.0j]),
    range_offset=0.012,
    gain=1.3,
)


# All parameters away from boundaries and well constrained (for covariance / coverage checks).
TRUTH_INTERIOR = PhysicalParams(
    quaternion=np.array([1.0, 0.0, 0.0, 0.0]),
    m=np.array([6.0, 20.0]),
    n=np.array([1.5 + 0.5j, 1.2 + 5.0j]),
    range_offset=0.012,
    gain=30.0,
)


def perturbed(truth: PhysicalParams, deg=3.0, seed=1) -> PhysicalParams:
    """A classifier-like start: attitude off by ``deg`` degrees, material and nuisances off."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    q = quat_multiply(
        quat_from_rotvec(jnp.asarray(np.radians(deg) * axis)), truth.unit_quaternion()
    )
    return PhysicalParams(
        q,
        truth.m * np.exp(rng.normal(0, 0.25, truth.m.shape)),
        np.real(truth.n) * 1.1 + 1j * (np.imag(truth.n) * 0.8 + 0.05),
        truth.corr_length,
        truth.range_offset + 0.01,
        truth.gain * 0.7,
    )


# --------------------------------------------------------------------------- parameters
def test_params_roundtrip_and_constraints():
    par = Parametrisation(perturbed(TRUTH))
    theta = par.from_physical(TRUTH)
    back = par.to_physical(theta)
    # round trip to float64 rounding (a few ulps through exp/log/softplus/atan2)
    assert quat_angle_deg(back.quaternion, TRUTH.quaternion) < 1e-6
    np.testing.assert_allclose(back.m, TRUTH.m, rtol=1e-12)
    np.testing.assert_allclose(np.real(back.n), np.real(TRUTH.n), rtol=1e-12)
    # n'' = 0 maps to the clamp 1e-9 (documented), others exactly
    np.testing.assert_allclose(np.imag(back.n), [1e-9, 5.0], rtol=1e-9)
    np.testing.assert_allclose([back.range_offset, back.gain], [0.012, 1.3], rtol=1e-12)
    # any theta gives physical values inside the constraints
    rng = np.random.default_rng(0)
    for _ in range(5):
        p = par.to_physical(jnp.asarray(rng.normal(0, 5, par.size)))
        assert (
            np.all(np.asarray(p.m) > 0) and np.all(np.imag(p.n) >= 0) and np.all(np.real(p.n) > 0)
        )
    assert len(par.labels) == par.size == len(par.theta_labels) == 3 + 2 + 4 + 1 + 1
    # what is not an attitude or a set of material slots is refused, not normalised or
    # broadcast (one value for every slot is fine)
    with pytest.raises(ValueError, match=r"unit quaternion .* norm 1.41421"):
        PhysicalParams([1.0, 0.0, 0.0, 1.0], [10.0], [1.5])
    with pytest.raises(ValueError, match=r"n has shape \(2,\) but m has 1 material slot"):
        PhysicalParams([1.0, 0.0, 0.0, 0.0], [10.0], [1.5, 1.6])
    with pytest.raises(ValueError, match=r"at least one"):
        PhysicalParams([1.0, 0.0, 0.0, 0.0], [], [])
    both = PhysicalParams([1.0, 0.0, 0.0, 0.0], [10.0, 20.0], [1.5])
    np.testing.assert_array_equal(both.n, [1.5, 1.5])


def test_rotvec_quaternion_inverse_and_smooth_at_zero():
    rng = np.random.default_rng(3)
    for w in rng.normal(0, 0.8, (5, 3)):  # angles < pi (the log map returns [0, pi])
        np.testing.assert_allclose(
            rotvec_from_quat(quat_from_rotvec(jnp.asarray(w))), w, atol=1e-12
        )
    g = jax.jacfwd(quat_from_rotvec)(jnp.zeros(3))
    np.testing.assert_allclose(g, np.vstack([np.zeros(3), 0.5 * np.eye(3)]), atol=1e-15)
    assert np.all(np.isfinite(jax.jacrev(lambda w: quat_from_rotvec(w).sum())(jnp.zeros(3))))


# --------------------------------------------------------------------------- recovery
def _physical_error(res, truth):
    p = res.params
    return {
        "att_deg": float(quat_angle_deg(p.quaternion, truth.quaternion)),
        "m": np.max(np.abs(np.asarray(p.m) / np.asarray(truth.m) - 1)),
        "n_re": np.max(np.abs(np.real(p.n) - np.real(truth.n))),
        "n_im": np.max(np.abs(np.imag(p.n) - np.imag(truth.n))),
        "off": abs(float(p.range_offset) - float(truth.range_offset)),
        "gain": abs(float(p.gain) / float(truth.gain) - 1),
    }


def test_noise_free_recovery_from_classifier_like_start():
    model = make_toy()
    data = model.expected(TRUTH, model.prepare(TRUTH))
    res = refine(
        model,
        data,
        [perturbed(TRUTH, 4.0, seed=2), perturbed(TRUTH, 2.0, seed=5)],
        noise=PoissonNoise(floor=1.0),
    )
    assert res.success, res.summary()
    assert res.result == "successful" and res.n_steps > 0
    err = _physical_error(res, TRUTH)
    # noise-free data, float64: limited by the solver's step tolerance (rtol=atol=1e-8 on
    # theta) times the conditioning of each direction (n is the least constrained)
    assert err["att_deg"] < 1e-5, err
    assert err["m"] < 1e-6 and err["off"] < 1e-8 and err["gain"] < 1e-7, err
    # n''[0] = 0 is on the boundary, where the data constrain n'' only quadratically
    assert err["n_re"] < 1e-5 and err["n_im"] < 1e-5, err
    assert res.cost < 1e-9  # chi^2 of noise-free data at the optimum (~n''^4 near n'' = 0)
    assert len(res.starts) == 2 and all(s.success for s in res.starts)
    assert np.all(np.isfinite(res.covariance)) and res.covariance.shape == (11, 11)


def test_screening_keeps_the_start_that_reaches_the_global_optimum():
    """``keep=1``: every start runs one loose round, only the lowest-cost one is refined on.
    Three starts 60-80 deg off end in local optima (full multi-start: costs > 1e4); the
    screened run reaches the same optimum as refining every start, in fewer solver steps,
    and reports the others as screened out with their screening costs."""
    model = make_toy()
    data = model.expected(TRUTH, model.prepare(TRUTH))
    starts = [
        perturbed(TRUTH, 70.0, seed=3),
        perturbed(TRUTH, 4.0, seed=2),
        perturbed(TRUTH, 60.0, seed=4),
        perturbed(TRUTH, 80.0, seed=7),
    ]
    noise = PoissonNoise(floor=1.0)
    full = refine(model, data, starts, noise=noise)
    assert [s.index for s in full.starts][0] == 1
    assert all(s.cost > 1e3 for s in full.starts[1:])  # the far starts' local optima
    scr = refine(model, data, starts, noise=noise, keep=1)
    assert scr.success and scr.starts[0].index == 1
    assert quat_angle_deg(scr.params.quaternion, TRUTH.quaternion) < 1e-5
    np.testing.assert_allclose(scr.cost, full.cost, atol=1e-9)
    out = [s for s in scr.starts if s.result == "screened_out"]
    assert sorted(s.index for s in out) == [0, 2, 3]
    assert all(not s.success and s.cost > 1e3 and s.n_rounds == 1 for s in out)
    assert "keep=1" in out[0].message
    assert sum(s.n_steps for s in scr.starts) < sum(s.n_steps for s in full.starts)
    with pytest.raises(ValueError, match="keep=0"):
        refine(model, data, starts, keep=0)
    with pytest.raises(ValueError, match="screen_tol"):
        refine(model, data, starts, keep=1, screen_tol=0.0)


@pytest.mark.parametrize("solver", ["lm", "dogleg"])
def test_solvers_on_tiny_model(solver):
    """LM (default) and Dogleg recover the truth of a cheap model; result codes surfaced."""
    model = TinyModel(jnp.linspace(-0.2, 0.2, 24))
    data = model.expected(TINY_TRUTH, model.prepare(TINY_TRUTH))
    res = refine(
        model,
        data,
        tiny_start(),
        noise=GaussianNoise(jnp.asarray(1.0)),
        free=TINY_FREE,
        solver=solver,
    )
    assert res.success and res.result == "successful", res.summary()
    p = res.params
    # noise-free, float64, well-conditioned: solver step tolerance 1e-8 relative
    np.testing.assert_allclose(np.asarray(p.m), [12.0], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(p.n), [1.3 + 0.4j], rtol=1e-6)
    np.testing.assert_allclose([float(p.range_offset), float(p.gain)], [0.01, 2.0], rtol=1e-6)
    assert res.labels == ["m[0]", "n_re[0]", "n_im[0]", "range_offset [m]", "gain"]


def test_gradients_finite_along_the_path_including_edge_on_facet():
    """Residual Jacobians are finite along a straight path from a start to the optimum, with
    one facet exactly edge-on at the optimum (cos theta = 0 with m > 0: the 0**m guard)."""
    from inversion._refine import _jacobians

    model = make_toy(edge_on=True)
    data = model.expected(TRUTH, model.prepare(TRUTH))
    w = jnp.ones_like(data)
    start = perturbed(TRUTH, 5.0)
    par = Parametrisation(start)
    th0, th1 = par.from_physical(start), par.from_physical(TRUTH)
    for t in np.linspace(0.0, 1.0, 5):
        th = (1 - t) * th0 + t * th1
        aux = model.prepare(par.to_physical(th))
        J, G, _ = _jacobians(model, par, aux, w, data, th)
        assert np.all(np.isfinite(np.asarray(J))) and np.all(np.isfinite(np.asarray(G)))
        assert np.any(np.asarray(J) != 0)
    res = refine(model, data, start)
    assert res.success and np.all(np.isfinite(res.covariance))
    assert quat_angle_deg(res.params.quaternion, TRUTH.quaternion) < 1e-5


def test_forward_jacobian_linearization_equals_autodiff():
    """The solvers' expected counts (inversion._refine._expected_forward_jac: a custom JVP
    applying the forward-mode Jacobian) have the plain function's values, JVP, VJP (the
    transpose optimistix takes) and Jacobian, to rounding; a tangent on anything but theta
    raises instead of being dropped."""
    from inversion._refine import _expected_forward_jac

    model = make_toy()
    start = perturbed(TRUTH, 5.0)
    par = Parametrisation(start)
    th = par.from_physical(start)
    aux = model.prepare(start)

    def plain(t):
        return model.expected(par.to_physical(t), aux)

    def custom(t):
        return _expected_forward_jac(t, par, model, aux)

    dth = jnp.asarray(np.random.default_rng(2).normal(size=th.shape))
    ct = jnp.asarray(np.random.default_rng(3).normal(size=model.bins.shape[:0] + (16, 48)))

    @jax.jit  # one program: eager autodiff of the toy model dispatches hundreds of small ones
    def both(th, dth, ct):
        out = []
        for f, jac in ((plain, jax.jacfwd), (custom, jax.jacrev)):
            y, t = jax.jvp(f, (th,), (dth,))
            out.append((y, t, jax.vjp(f, th)[1](ct)[0], jac(f)(th)))
        return out

    ref, got = both(th, dth, ct)
    for a, b in zip(got, ref, strict=True):  # values, JVP, VJP, Jacobian
        np.testing.assert_allclose(
            np.asarray(a), np.asarray(b), rtol=0, atol=1e-12 * np.abs(np.asarray(b)).max()
        )
    with pytest.raises(NotImplementedError, match="theta only"):
        jax.jvp(
            lambda a: _expected_forward_jac(
                th, par, eqx.tree_at(lambda mo: mo.areas, model, a), aux
            ),
            (model.areas,),
            (jnp.ones_like(model.areas),),
        )


def test_covariance_matches_scatter_of_noisy_fits():
    """(J^T J)^-1 in physical units agrees with the spread of fits over noise realisations."""
    model = make_toy()
    mu = model.expected(TRUTH_INTERIOR, model.prepare(TRUTH_INTERIOR))
    noise = PoissonNoise(floor=1.0)
    sig = np.sqrt(np.asarray(noise.variance(mu)))
    vecs, covs = [], []
    rng = np.random.default_rng(11)
    par0 = Parametrisation(TRUTH_INTERIOR)
    for _ in range(12):
        d = np.asarray(mu) + sig * rng.normal(size=mu.shape)
        res = refine(model, d, TRUTH_INTERIOR, noise=noise, rounds=2)
        assert res.success
        th = par0.from_physical(res.params)
        vecs.append(np.asarray(par0.physical_vector(th)))
        covs.append(res.covariance)
    vecs = np.array(vecs)
    pred = np.sqrt(np.diag(np.mean(covs, axis=0)))
    emp = vecs.std(axis=0, ddof=1)
    ratio = emp / pred
    # 12 samples: the sample std has ~21% relative scatter; allow a factor 2 either way
    assert np.all((ratio > 0.45) & (ratio < 2.0)), ratio


def test_failure_is_reported_not_silent():
    model = make_toy()
    data = model.expected(TRUTH, model.prepare(TRUTH))
    # zero tolerances: the step criterion can never be met, the solver runs out of steps
    res = refine(model, data, perturbed(TRUTH, 10.0), rtol=0.0, atol=0.0, max_steps=200, rounds=1)
    assert not res.success
    assert res.result == "nonlinear_max_steps_reached"
    assert "maximum number of steps" in res.message
    assert "success=False" in res.summary()


# --------------------------------------------------------------------------- Poisson counts
def _deviance_mp(k, lam):
    """Reference deviance residual, sign(k - lam) sqrt(2 (lam - k + k log(k/lam))), 40 digits."""
    import mpmath

    with mpmath.workdps(40):
        k, lam = mpmath.mpf(float(k)), mpmath.mpf(float(lam))
        d = 2 * (lam - k + (k * mpmath.log(k / lam) if k > 0 else 0))
        return float(mpmath.sign(k - lam) * mpmath.sqrt(d)), float(d)


def test_poisson_deviance_residuals_against_mpmath_and_finite_gradients():
    """Deviance residuals (values to 1e-12 of sqrt(k)-scale, incl. lam ~ k where the naive
    form cancels) and sum(r^2) = -2 (log L - log L_saturated) with the exact Poisson
    log-likelihood (mpmath log-gamma); finite gradients at k = 0, lam = k, mu = 0."""
    import mpmath

    from inversion._refine import PoissonCounts

    b = 1e-3
    noise = PoissonCounts(background=b)
    k = np.array([0, 0, 0, 1, 1, 1, 3, 3, 7, 7, 50, 50, 2000, 2000], float)
    mu = np.array(
        [
            0,
            1e-9,
            2,
            1 - b,
            1e-6,
            1 + 3e-5,
            3 * (1 + 2e-4) - b,
            10,
            7 * (1 + 5e-5),
            7 * (1 - 1e-3),
            49.9,
            0.5,
            2000 * (1 + 1e-6),
            1900.0,
        ]
    )
    r = np.asarray(noise.residuals(jnp.asarray(k), jnp.asarray(mu)))
    ref = np.array([_deviance_mp(ki, mi + b)[0] for ki, mi in zip(k, mu, strict=True)])
    assert np.all(np.abs(r - ref) <= 1e-12 * np.sqrt(1 + k)), np.abs(r - ref) / np.sqrt(1 + k)
    # exact log-likelihood, and deviance = -2 (log L(lam) - log L(lam = k))
    ll = float(noise.log_likelihood(jnp.asarray(k), jnp.asarray(mu)))
    with mpmath.workdps(40):
        ll_ref = sum(
            ki * mpmath.log(mpmath.mpf(mi) + b) - (mpmath.mpf(mi) + b) - mpmath.loggamma(ki + 1)
            for ki, mi in zip(k, mu, strict=True)
        )
        ll_sat = sum(
            (ki * mpmath.log(ki) - ki if ki > 0 else 0) - mpmath.loggamma(ki + 1) for ki in k
        )
    assert abs(ll - float(ll_ref)) < 1e-10 * abs(float(ll_ref))
    assert abs(np.sum(r**2) - float(-2 * (ll_ref - ll_sat))) < 1e-9 * np.sum(r**2)
    # gradients in mu: finite everywhere, and equal to central differences where smooth
    g = np.asarray(jax.vmap(jax.grad(lambda m_, k_: noise.residuals(k_, m_)))(mu, k))
    assert np.all(np.isfinite(g)), g
    h = 1e-7 * np.maximum(mu, 1.0)
    fd = (
        np.asarray(noise.residuals(jnp.asarray(k), jnp.asarray(mu + h)))
        - np.asarray(noise.residuals(jnp.asarray(k), jnp.asarray(mu - h)))
    ) / (2 * h)
    smooth = mu > 1e-3
    np.testing.assert_allclose(g[smooth], fd[smooth], rtol=1e-5, atol=1e-8)
    # float32: finite, and agrees with float64 to 1e-4 relative of sqrt(k)-scale
    r32 = np.asarray(noise.residuals(jnp.asarray(k, jnp.float32), jnp.asarray(mu, jnp.float32)))
    assert np.all(np.isfinite(r32))
    assert np.all(np.abs(r32 - ref) <= 2e-4 * np.sqrt(1 + k)), np.abs(r32 - ref) / np.sqrt(1 + k)


def _sparse_counts(model, phys, seed):
    mu = np.asarray(model.expected(phys, model.prepare(phys)))
    # a + c = 0 at normal incidence up to round-off (-1e-18)
    return np.random.default_rng(seed).poisson(np.maximum(mu, 0.0)).astype(float), mu


def test_poisson_counts_refiner_is_the_maximum_likelihood_estimate():
    """Sparse counts (~0.5 count per channel-bin): with only the gain free the Poisson MLE has
    the closed form sum(k) / sum(t) (t the gain-1 profile, background -> 0); the refiner with
    PoissonCounts finds it to 1e-7. The Gaussian approximation with a variance floor of 1
    (PoissonNoise) does not: its weights are nearly uniform where counts are sparse."""
    from inversion._refine import PoissonCounts

    model = TinyCounts(jnp.linspace(-0.2, 0.2, 24))
    truth = PhysicalParams([1.0, 0, 0, 0], [12.0], [1.3 + 0.4j], range_offset=0.01, gain=0.02)
    data, _ = _sparse_counts(model, truth, seed=3)
    assert 20 < data.sum() < 500 and np.mean(data == 0) > 0.5
    start = PhysicalParams([1.0, 0, 0, 0], [12.0], [1.3 + 0.4j], range_offset=0.01, gain=0.05)
    unit = PhysicalParams([1.0, 0, 0, 0], [12.0], [1.3 + 0.4j], range_offset=0.01, gain=1.0)
    t = np.asarray(model.expected(unit, model.prepare(unit)))
    g_mle = data.sum() / t.sum()
    res = refine(model, data, start, noise=PoissonCounts(background=1e-12), free=("gain",))
    assert res.success, res.summary()
    assert abs(float(res.params.gain) / g_mle - 1) < 1e-7
    # the Cramer-Rao bound of a Poisson scale: sigma_g = g / sqrt(expected counts)
    from inversion._refine import cramer_rao

    crb = cramer_rao(model, truth, PoissonCounts(background=1e-12), free=("gain",))
    n_exp = float(truth.gain) * t.sum()
    assert abs(crb.sigma[0] / (float(truth.gain) / np.sqrt(n_exp)) - 1) < 1e-6
    res_g = refine(model, data, start, noise=PoissonNoise(floor=1.0), free=("gain",))
    assert abs(float(res_g.params.gain) / g_mle - 1) > 1e-3  # a different (non-ML) estimate


def test_poisson_counts_covariance_matches_scatter_on_sparse_counts():
    """On sparse Poisson counts (~300 photons in 384 channel-bins) the Fisher covariance
    at the optimum agrees with the scatter of the maximum-likelihood fits over realisations."""
    from inversion._refine import PoissonCounts

    model = TinyCounts(jnp.linspace(-0.2, 0.2, 24))
    truth = PhysicalParams([1.0, 0, 0, 0], [12.0], [1.3 + 0.4j], range_offset=0.01, gain=0.02)
    noise = PoissonCounts()
    free = ("m", "range_offset", "gain")  # n is poorly determined by ~300 photons
    par0 = Parametrisation(truth, free)
    vecs, sig = [], []
    for seed in range(24):
        data, _ = _sparse_counts(model, truth, seed=100 + seed)
        res = refine(model, data, truth, noise=noise, free=free, rounds=1)
        assert res.success, res.summary()
        vecs.append(np.asarray(par0.physical_vector(par0.from_physical(res.params))))
        sig.append(res.sigma)
    ratio = np.std(vecs, axis=0, ddof=1) / np.median(sig, axis=0)
    # 24 samples: sample std scatter ~15%; low counts add skew: a factor 1.6 either way
    assert np.all((ratio > 0.6) & (ratio < 1.6)), ratio


def test_unconstrained_direction_has_infinite_variance_not_zero():
    """TinyCounts does not depend on the attitude at all: the Fisher matrix is singular along
    the three rotation directions. Their bounds must be infinite (a pseudo-inverse alone would
    report 0), while the constrained parameters keep the bound of the attitude-free fit."""
    from inversion._refine import PoissonCounts, cramer_rao

    model = TinyCounts(jnp.linspace(-0.2, 0.2, 24))
    truth = PhysicalParams([1.0, 0, 0, 0], [12.0], [1.3 + 0.4j], range_offset=0.01, gain=0.02)
    full = cramer_rao(model, truth, PoissonCounts(), free=("attitude",) + TINY_FREE)
    part = cramer_rao(model, truth, PoissonCounts(), free=TINY_FREE)
    assert np.all(np.isinf(full.sigma[:3])) and full.attitude_sigma_deg == np.inf
    assert np.all(np.isfinite(part.sigma)) and np.all(part.sigma > 0)
    np.testing.assert_allclose(full.sigma[3:], part.sigma, rtol=1e-6)


def test_poisson_counts_bad_input():
    from inversion._refine import PoissonCounts

    with pytest.raises(ValueError, match="background"):
        PoissonCounts(background=0.0)
    with pytest.raises(ValueError, match="background"):
        PoissonCounts(background=float("nan"))
    model = TinyCounts(jnp.linspace(-0.2, 0.2, 24))
    data = np.array(model.expected(TINY_TRUTH, model.prepare(TINY_TRUTH)))
    data[2, 5] = -1.0
    with pytest.raises(ValueError, match=r"PoissonCounts.*negative.*\(2, 5\)"):
        refine(model, data, tiny_start(), noise=PoissonCounts(), free=TINY_FREE)


# --------------------------------------------------------------------------- bad input
def test_bad_inputs_name_the_problem():
    model = make_toy()
    data = np.asarray(model.expected(TRUTH, model.prepare(TRUTH)))
    with pytest.raises(ValueError, match="range bins"):
        refine(model, data[:, :40], TRUTH)
    with pytest.raises(ValueError, match="shape"):
        refine(model, data[:8], TRUTH)
    bad = data.copy()
    bad[3, 7] = np.nan
    with pytest.raises(ValueError, match=r"non-finite.*\(3, 7\)"):
        refine(model, bad, TRUTH)
    with pytest.raises(ValueError, match="starts is empty"):
        refine(model, data, [])
    with pytest.raises(ValueError, match="solver="):
        refine(model, data, TRUTH, solver="newton")
    with pytest.raises(ValueError, match="unknown group"):
        Parametrisation(TRUTH, free=("attitude", "colour"))
    with pytest.raises(ValueError, match="no parameter group is free"):  # was an IndexError
        refine(model, data, TRUTH, free=())
    with pytest.raises(ValueError, match="n' > 0"):
        PhysicalParams([1, 0, 0, 0], 5.0, -1.5 + 0j)
    with pytest.raises(ValueError, match="shape"):
        check_observation(np.zeros((16, 48, 1)), (16, 48))


# --------------------------------------------------------------------------- jaxopt adapter
def test_jaxopt_version_pinned():
    """The L-BFGS-B adapter is tested with these jaxopt versions (archived upstream)."""
    import warnings

    from inversion._jaxopt_adapter import JAXOPT_TESTED, jaxopt_version

    assert jaxopt_version() in JAXOPT_TESTED, (
        f"jaxopt {jaxopt_version()} is not in the tested set {JAXOPT_TESTED}: re-run "
        "tests/test_refine.py and update JAXOPT_TESTED, or swap the adapter's backend"
    )
    with warnings.catch_warnings():  # importing the adapter must not leak jaxopt's warning
        warnings.simplefilter("error")
        import importlib

        import inversion._jaxopt_adapter as ad

        importlib.reload(ad)


def test_bounded_refine_recovers_truth_and_respects_bounds():
    from inversion._refine import PhysicalBounds, refine_bounded

    model = TinyModel(jnp.linspace(-0.2, 0.2, 24))
    data = model.expected(TINY_TRUTH, model.prepare(TINY_TRUTH))
    noise = GaussianNoise(jnp.asarray(1.0))
    res = refine_bounded(model, data, tiny_start(), noise=noise, free=TINY_FREE)
    assert res.method == "lbfgsb_jaxopt" and res.success, res.summary()
    p = res.params
    # L-BFGS-B stops on the projected gradient of the normalised chi^2 (tol 1e-7): looser
    # than the LM step tolerance
    np.testing.assert_allclose(np.asarray(p.m), [12.0], rtol=1e-3)
    np.testing.assert_allclose(np.asarray(p.n), [1.3 + 0.4j], rtol=1e-3)
    np.testing.assert_allclose([float(p.range_offset), float(p.gain)], [0.01, 2.0], rtol=1e-3)
    # a box that excludes the truth (n' <= 1.2 < 1.3): ends on the bound and says so
    tight = PhysicalBounds(n_re=(0.5, 1.2))
    res2 = refine_bounded(model, data, tiny_start(), noise=noise, free=TINY_FREE, bounds=tight)
    nre = float(np.real(np.asarray(res2.params.n))[0])
    assert 0.5 <= nre <= 1.2
    assert abs(nre - 1.2) < 1e-9, res2.summary()
    assert res2.cost > 1.0  # the truth is outside the box: the fit cannot be exact
    if res2.success:
        assert "at bounds: n_re[0]" in res2.message
    with pytest.raises(ValueError, match="n_re"):
        PhysicalBounds(n_re=(2.0, 1.0))
    # an unbounded optimum outside the box is named in outside_bounds() and the summary
    import dataclasses

    assert res.outside_bounds() == [] and res2.outside_bounds(tight) == []
    far = dataclasses.replace(
        res,
        params=PhysicalParams([1.0, 0, 0, 0], [12.0], [7.3 + 0.4j], range_offset=0.01, gain=2.0),
    )
    assert far.outside_bounds() == ["n_re[0] = 7.3 outside [0.05, 5]"]
    assert "outside the physical box (refit with refine_bounded)" in far.summary()
    # mirror_check(bounds=): the mirror refit stays in the box (the solver's clamped
    # parametrisation) and ends on the bound the unbounded one crosses
    from inversion._refine import mirror_check

    fit = refine(model, data, tiny_start(), noise=noise, free=TINY_FREE)
    free_chk = mirror_check(model, data, fit, "dihedral:4", noise=noise)
    assert free_chk.mirror.outside_bounds(tight)
    chk = mirror_check(model, data, fit, "dihedral:4", noise=noise, bounds=tight)
    assert chk.mirror.outside_bounds(tight) == []
    assert abs(float(np.real(np.asarray(chk.mirror.params.n))[0]) - 1.2) < 1e-9
    assert chk.delta_deviance > 1.0 and chk.best is fit  # the boxed mirror fits worse

    # refine(bounds=): the Levenberg-Marquardt solver kept in the box by its clamped
    # parametrisation reaches L-BFGS-B's constrained optimum (on the bound n' = 1.2, the other
    # parameters at their conditional optimum: the same point by two unrelated methods)
    lm = refine(model, data, tiny_start(), noise=noise, free=TINY_FREE, bounds=tight)
    assert lm.method == "levenberg_marquardt" and lm.success, lm.summary()
    assert float(np.real(np.asarray(lm.params.n))[0]) == 1.2  # exactly on the bound
    assert "at bounds: n_re[0]" in lm.message and lm.outside_bounds(tight) == []
    np.testing.assert_allclose(lm.cost, res2.cost, rtol=1e-9)
    for a, b in [(lm.params.m, res2.params.m), (lm.params.n, res2.params.n)]:
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6)
    np.testing.assert_allclose(float(lm.params.gain), float(res2.params.gain), rtol=1e-6)
    # an optimum inside the box: the box changes nothing (the clamp is the identity there)
    inside = refine(model, data, tiny_start(), noise=noise, free=TINY_FREE, bounds=PhysicalBounds())
    assert inside.n_steps == fit.n_steps and inside.cost == fit.cost
    np.testing.assert_array_equal(np.asarray(inside.theta), np.asarray(fit.theta))


# --------------------------------------------------------------------------- ppr simulator
def _simulator_model(n_bins=32):
    import ppr
    from inversion._noise import MeasurementModel
    from inversion._refine import SimulatorModel
    from ppr.pulse._pulse import glossy_fresnel_mueller

    mesh = ppr.shapes.cubesat(1)  # 0.1 m cube, 12 faces
    scene = ppr.Scene(
        mesh,
        (ppr.Material(1.5, 10.0),),
        ppr.Pose([1.0, 0.0, 0.0, 0.0]),
        ppr.Sensor.make(),  # monostatic, line of sight -z
        ppr.Pulse.gaussian(100e-12),
        ppr.RangeBins.centred(0.01, n_bins),
    )
    chm = MeasurementModel.preset("copol").channel_matrix()
    # the simulator's polarizing stand-in BRDF: smooth in attitude, m and n, cheap to compile
    return SimulatorModel(scene, chm, brdf=glossy_fresnel_mueller, dense=True)


def test_simulator_refuses_material_slots_that_are_not_its_parts():
    """Parameters with two material slots for a one-part mesh were fitted (phantom m[1],
    n[1] reported as unobservable): refused by name before anything runs."""
    model = _simulator_model()
    two = PhysicalParams([1.0, 0.0, 0.0, 0.0], [10.0, 3.0], [1.5, 1.5], gain=1e3)
    with pytest.raises(ValueError, match="2 material slots .* 1 part \\(body\\)"):
        model.prepare(two)
    with pytest.raises(ValueError, match="one material per part"):
        refine(model, np.ones((2, 32)), two)


def test_a_start_that_predicts_no_signal_is_not_a_success():
    """A start whose range offset puts the object outside the range window predicts 0 in
    every bin: the gradient is 0 and the solver stopped at once, reported as a success (with
    a reduced chi-square of 1e8). It is reported as no_signal, not converged."""
    model = _simulator_model()
    q = np.array([0.93, 0.25, 0.2, 0.17]) / np.linalg.norm([0.93, 0.25, 0.2, 0.17])
    truth = PhysicalParams(q, [10.0], [1.5], range_offset=0.002, gain=1e4)
    data = np.asarray(model.expected(truth, model.prepare(truth)))
    far = PhysicalParams(truth.quaternion, [10.0], [1.5], range_offset=5.0, gain=1e4)
    res = refine(model, data, far, free=("attitude", "m", "gain"))
    assert not res.success and res.result == "no_signal", (res.result, res.message)
    assert "predicts no signal" in res.message


def test_sigma_of_a_free_extinction_near_its_floor_is_infinite():
    """A dielectric (extinction 0) fitted with n free: the data do not constrain n_im,
    fitted as its logarithm near the floor, where the covariance keeps it finite; its sigma
    was ~1e-32 at the bound (Cramer-Rao) and ~1e-23 after a refit, claiming an exact value
    where the observability names it unobservable. Both report inf; a constrained
    parameter (the range offset) keeps its finite bound."""
    model = _simulator_model()
    q = np.array([0.93, 0.25, 0.2, 0.17]) / np.linalg.norm([0.93, 0.25, 0.2, 0.17])
    truth = PhysicalParams(q, [20.0], [1.45], range_offset=0.003, gain=1e4)
    crb = cramer_rao(model, truth, PoissonCounts())
    sig = dict(zip(crb.labels, crb.sigma, strict=True))
    assert sig["n_im[0]"] == np.inf
    assert "n_im[0]" in " ".join(crb.observability().names)
    assert 0 < sig["range_offset [m]"] < np.inf
    data = np.asarray(model.expected(truth, model.prepare(truth)))
    fit = refine(model, data, truth)
    assert dict(zip(fit.labels, fit.sigma, strict=True))["n_im[0]"] == np.inf


def test_simulator_jacobian_finite_with_edge_on_faces():
    """ppr-backed residual Jacobians are finite along a path that starts with four faces of a
    cube exactly edge-on (identity attitude, line of sight along -z) and tilts them into view;
    the attitude columns are non-zero once the tilt is on (the profile depends on attitude)."""
    from inversion._refine import _jacobians, _pure

    model = _simulator_model()
    truth = PhysicalParams([1.0, 0.0, 0.0, 0.0], [10.0], [1.5 + 0.1j], range_offset=0.002, gain=1e3)
    par = Parametrisation(truth)
    data = model.expected(truth, model.prepare(truth))
    assert data.shape == (2, 32) and np.all(np.isfinite(np.asarray(data)))
    w = jnp.ones_like(data)
    th0 = par.from_physical(truth)
    for deg in (0.0, 1e-6, 3.0):
        th = th0.at[0].set(np.radians(deg)).at[1].set(np.radians(0.7 * deg))
        aux = model.prepare(par.to_physical(th))
        J, G, chi2 = _jacobians(_pure(model), par, aux, w, data, th)
        J = np.asarray(J)
        assert np.all(np.isfinite(J)) and np.isfinite(float(chi2)), deg
        if deg > 1.0:
            assert np.any(J[:, :3] != 0)


def test_pruned_simulator_matches_the_whole_mesh():
    """SimulatorModel(prune=True) (the default) renders only the facets lit and visible at
    the round's pose (a ppr.FaceSubset: at most 6 of a cube's 12 facets, padded to 8, against
    64 padded facets): its expected counts and residual Jacobian are those of the unpruned
    model (bench/bench_prune.py compares the refined fits and chains on the inversion
    bench's observations)."""
    import ppr
    from inversion._refine import _jacobians, _pure

    pruned = _simulator_model()
    whole = _simulator_model()
    whole.prune = False
    assert pruned.prune and pruned.subset_capacities() == (8, 8)
    q = np.array([0.86, 0.31, -0.22, 0.35])
    q = q / np.linalg.norm(q)
    truth = PhysicalParams(q, [10.0], [1.5 + 0.1j], range_offset=0.002, gain=1e3)
    aux_p, aux_w = pruned.prepare(truth), whole.prepare(truth)
    assert isinstance(aux_p, ppr.FaceSubset) and aux_p.n_faces == 8
    assert int(np.sum(np.asarray(aux_w) > 0)) == 6 and aux_w.shape == (64,)
    mu_p, mu_w = (np.asarray(m.expected(truth, a)) for m, a in ((pruned, aux_p), (whole, aux_w)))
    np.testing.assert_allclose(mu_p, mu_w, rtol=0, atol=1e-13 * mu_w.max())
    par = Parametrisation(truth)
    th = par.from_physical(truth)
    w = jnp.ones_like(jnp.asarray(mu_w))
    jp, jw = (
        np.asarray(_jacobians(_pure(m), par, a, w, jnp.asarray(mu_w), th)[0])
        for m, a in ((pruned, aux_p), (whole, aux_w))
    )
    assert np.abs(jw[:, :3]).max() > 0
    np.testing.assert_allclose(jp, jw, rtol=0, atol=1e-12 * np.abs(jw).max())


def test_mirror_check_finds_the_parity_ambiguity_and_its_breaking():
    """A 3U CubeSat (mirror plane z -> -z) of rough aluminium, monostatic, noise-free counts
    (1e7), with the double-bounce term alone (it carries the off-block Mueller elements; one
    term keeps the compilation short). Its mirror image P R sigma is an exact parity image: the same
    range profiles and Mueller profiles D M D, D = diag(1, 1, -1, -1)
    (tests/test_pulse.py). (1) A polarimeter that measures only the block-diagonal Mueller
    elements cannot tell the two apart: delta deviance 0, probability 1/2, and a second mode
    degrees away modulo the rotations, nowhere modulo the mirror. (2) The 16 PSG/PSA channels
    see the off-block elements the rough surface's double bounces give, and reject the
    image. (3) inversion.mode_check from the mesh's own group (D4h) finds the same two modes
    and weights. (4) Near symmetries of a nearly symmetric CubeSat are refit modes with
    real weight (same compiled programs: the same face count and channels)."""
    import ppr
    from inversion._classifier import line_of_sight_error_deg
    from inversion._modes import candidate_modes
    from inversion._noise import MeasurementModel
    from inversion._refine import PoissonCounts, SimulatorModel, mirror_check, mode_check

    scene = ppr.Scene(
        ppr.shapes.cubesat(3),
        (ppr.Material(1.5, 10.0),),
        ppr.Pose([1.0, 0.0, 0.0, 0.0]),
        ppr.Sensor.make(),
        ppr.Pulse.gaussian(100e-12),
        ppr.RangeBins.centred(0.012, 32),
    )
    full = MeasurementModel.preset("full").channel_matrix()
    block = np.array(full)
    block[:, :2, 2:] = 0.0  # the same channels, blind to the off-block elements
    block[:, 2:, :2] = 0.0
    q = np.array([0.86, 0.31, -0.22, 0.35])
    q /= np.linalg.norm(q)
    noise = PoissonCounts(background=1e-3)
    checks, modes = {}, {}

    def fit_to(mesh, chm):
        model = SimulatorModel(
            eqx.tree_at(lambda s: s.mesh, scene, mesh), chm, dense=True, terms=("double",)
        )
        truth = PhysicalParams(q, [4.0], [0.94 + 6.42j], range_offset=0.003, gain=1.0)
        x = np.asarray(model.expected(truth, model.prepare(truth)))
        truth = PhysicalParams(q, [4.0], [0.94 + 6.42j], range_offset=0.003, gain=1e7 / x.sum())
        data = np.maximum(np.asarray(model.expected(truth, model.prepare(truth))), 0.0)
        # 5 steps from the truth, as the checks below: one compilation for all
        return model, data, refine(model, data, [truth], noise=noise, max_steps=5, rounds=1)

    for name, chm in (("block", block), ("full", full)):
        model, data, fit = fit_to(scene.mesh, chm)
        assert fit.cost < 1.0
        assert line_of_sight_error_deg(q, np.asarray(fit.params.quaternion), "dihedral:4")[0] < 0.1
        # a few steps only: with 16 channels the solver would walk from the image back to the
        # fit's own mode (the check then reports separation 0: no second mode either)
        checks[name] = mirror_check(
            model, data, fit, "dihedral:4", noise=noise, max_steps=5, rounds=1
        )
        if name == "block":  # the same from the mesh's own group (D4h): refit and weighted
            group = ppr.mesh_symmetries(scene.mesh)
            modes[name] = mode_check(model, data, fit, group, noise=noise, max_steps=5, rounds=1)

    exact = checks["block"]
    q_fit, q_mir = (np.asarray(r.params.quaternion) for r in (exact.fit, exact.mirror))
    assert exact.separation_deg > 5.0  # a distinct mode, not the fit again
    assert line_of_sight_error_deg(q_fit, q_mir, "dihedral:4", mirror=True)[0] < 0.05
    assert abs(exact.delta_deviance) < 1e-6
    assert abs(exact.mirror_probability - 0.5) < 1e-6 and exact.ambiguous()
    assert "ambiguous" in exact.summary()

    broken = checks["full"]
    assert broken.delta_deviance > 50.0
    assert broken.mirror_probability < 1e-10 and not broken.ambiguous()
    assert broken.best is broken.fit
    with pytest.raises(ValueError, match="implies no mirror plane"):
        mirror_check(model, data, broken.fit, "cyclic:4", noise=noise)

    # mode_check generalizes mirror_check: the same two modes and weights (its mirror start
    # is another element's image, the same mode modulo the rotations)
    mc = modes["block"]
    assert [m.label for m in mc.modes] == ["fit", "mirror image"], mc.summary()
    img = mc.modes[1]
    assert abs(img.delta_deviance - exact.delta_deviance) < 1e-6
    assert abs(img.weight - exact.mirror_probability) < 1e-6
    q_a, q_b = (np.asarray(r.params.quaternion) for r in (exact.mirror, img.fit))
    assert line_of_sight_error_deg(q_a, q_b, mesh=scene.mesh)[0] < 0.05
    assert mc.ambiguous() and len(mc.fits()) == 2

    # a nearly symmetric CubeSat: its +x face widened by 2e-4 of the size (C2v about x, D4h
    # to 2e-4). At the mesh's exact group the near quarter and half turns are not even
    # candidates; at tol 1e-2 they are refit: optima far from the fit whose deviance excess
    # (~ (asymmetry x SNR)^2, tests/test_modes.py) is below 2 at 1e7 counts, so they keep
    # real posterior weight: the ambiguity a local fit and its Cramer-Rao bound cannot show
    v = np.asarray(scene.mesh.vertices, np.float64).copy()
    plus = v[:, 0] > 0
    v[plus, 1] += np.sign(v[plus, 1]) * 2e-4 * 0.18
    near = ppr.Mesh(v, scene.mesh.faces)
    model, data, fit = fit_to(near, block)
    q_fit = np.asarray(fit.params.quaternion)
    assert [m.kind for m in candidate_modes(q_fit, near)] == ["fit", "mirror"]
    cands = candidate_modes(q_fit, ppr.mesh_symmetries(near, tol=1e-2), mirror=False)
    assert [m.kind for m in cands] == ["fit"] + ["near symmetry"] * 3
    # refit the fit and the first near mode (the half turn about body y): one more solve
    loose = mode_check(model, data, fit, near, modes=cands[:2], noise=noise, max_steps=5, rounds=1)
    nm = loose.modes[1]
    assert nm.label.startswith("near symmetry: C2 about body y"), loose.summary()
    assert nm.duplicate_of is None and nm.separation_deg > 45.0, loose.summary()
    assert 0.0 < nm.delta_deviance < 2.0 and nm.weight > 0.1 and loose.ambiguous(), loose.summary()
