"""Posterior files (inversion._posterior): the saved InferenceData holds the samples in the
units its attributes state, walkers as chains, burn-in as warmup; the diagnostics are
ArviZ's own."""

from __future__ import annotations

import dataclasses

import arviz as az
import jax.numpy as jnp
import numpy as np
import pytest

from inversion._mcmc import MCMCResult, _physical_vectors
from inversion._params import Parametrisation, PhysicalParams
from inversion._posterior import GAIN_UNIT, posterior_diagnostics
from ppr import quat_to_matrix
from ppr.geometry import quat_from_rotvec


def _rot(q):
    return np.asarray(quat_to_matrix(np.asarray(q, np.float64)))


def _result(n_steps=40, n_walkers=16, burn_in=12, thin=2):
    """An MCMCResult as sample_posterior assembles it, from a random-walk chain in the solver
    coordinates of a one-material parametrisation with every group free but corr_length
    (a real chain would only add its compilation to this test)."""
    q0 = np.asarray(quat_from_rotvec(jnp.array([0.2, -0.4, 0.3])))
    ref = PhysicalParams(q0, [12.0], [1.3 + 0.4j], range_offset=0.01, gain=2e3)
    par = Parametrisation(ref)
    rng = np.random.default_rng(1)
    theta0 = np.asarray(par.from_physical(ref))
    steps = 0.02 * rng.normal(size=(n_steps, n_walkers, par.size))
    chain = theta0 + np.cumsum(steps, axis=0) + 0.1 * rng.normal(size=(1, n_walkers, par.size))
    phys = np.asarray(_physical_vectors(par, jnp.asarray(chain.reshape(-1, par.size))))
    phys = phys.reshape(chain.shape)
    return MCMCResult(
        chain=chain,
        log_prob=rng.normal(size=(n_steps, n_walkers)),
        samples=phys[burn_in::thin].reshape(-1, par.size),
        labels=par.labels,
        parametrisation=par,
        acceptance_fraction=rng.uniform(0.2, 0.4, n_walkers),
        tau=np.full(par.size, 10.0),
        ess=np.full(par.size, 50.0),
        converged=False,
        burn_in=burn_in,
        thin=thin,
        elapsed_s=0.0,
        physical_chain=phys,
    )


def test_saved_posterior_is_in_physical_units_and_diagnostics_are_arviz(tmp_path):
    post = _result()
    q0 = np.asarray(post.parametrisation.reference.unit_quaternion())
    data = np.random.default_rng(0).poisson(5.0, size=(4, 16)).astype(float)
    path = post.write(tmp_path / "posterior.nc", observed=data)
    idata = az.from_netcdf(path)
    p, par = idata.posterior, post.parametrisation
    assert dict(p.sizes)["chain"] == 16 and dict(p.sizes)["draw"] == (40 - 12) // 2
    assert dict(idata.warmup_posterior.sizes)["draw"] == 6  # burn-in steps 0, 2, ..., 10
    assert p.attrs["burn_in"] == 12 and p.attrs["thin"] == 2
    # every column from the solver chain by the documented maps, independently of the library:
    # degrees of the rotation vector, exp of the log coordinates, softplus of n'', metres
    th = np.swapaxes(post.chain[12::2], 0, 1)  # (walker, draw, P), solver coordinates
    col = {lab: i for i, lab in enumerate(par.theta_labels)}
    expect = {
        "rot_x": np.degrees(th[..., col["rotvec_x"]]),
        "rot_z": np.degrees(th[..., col["rotvec_z"]]),
        "m": np.exp(th[..., col["log_m[0]"]]),
        "n_re": np.exp(th[..., col["log_n_re[0]"]]),
        "n_im": np.logaddexp(th[..., col["softplus_inv_n_im[0]"]], 0.0),
        "range_offset": th[..., col["range_offset/range_scale"]] * par.range_scale,
        "gain": np.exp(th[..., col["log_gain"]]),
    }
    for name, want in expect.items():
        got = p[name].values
        got = got[..., 0] if got.ndim == 3 else got
        np.testing.assert_allclose(got, want, rtol=1e-12, err_msg=name)  # float64 maps
    units = {"rot_x": "deg", "m": "1", "range_offset": "m", "gain": GAIN_UNIT, "los_polar": "deg"}
    for name, unit in units.items():
        assert p[name].attrs["units"] == unit, name
    # the samples of the result are the same draws, flattened step-major
    flat = np.swapaxes(p["gain"].values, 0, 1).reshape(-1)
    np.testing.assert_allclose(flat, post.samples[:, post.labels.index("gain")], rtol=1e-12)
    # the absolute attitude and the body-frame line of sight of a few draws
    quat = p["quaternion"].values
    for w, d in ((0, 0), (5, 3), (15, 13)):
        rv = np.radians([p[k].values[w, d] for k in ("rot_x", "rot_y", "rot_z")])
        qw = np.asarray(quat_from_rotvec(jnp.asarray(rv)))
        # q = exp(w) (x) q0 as a rotation: R(q) = R(exp w) R(q0)
        R = _rot(qw) @ _rot(q0)
        np.testing.assert_allclose(_rot(quat[w, d]), R, atol=1e-12)
        los = R.T @ [0.0, 0.0, 1.0]
        assert p["los_polar"].values[w, d] == pytest.approx(np.degrees(np.arccos(los[2])))
    np.testing.assert_array_equal(idata.observed_data["counts"].values, data)
    # diagnostics: ArviZ's numbers, the same as the MCMCResult reports
    diag = post.diagnostics()
    assert diag == posterior_diagnostics(idata)
    for lab, name, key, fn in (
        ("gain", "gain", "r_hat", lambda: az.rhat(idata)),
        ("m[0]", "m", "ess_bulk", lambda: az.ess(idata, method="bulk")),
        ("n_re[0]", "n_re", "ess_tail", lambda: az.ess(idata, method="tail")),
        ("range_offset [m]", "range_offset", "mcse_mean", lambda: az.mcse(idata)),
    ):
        val = fn()[name].values
        assert diag[lab][key] == float(val if val.ndim == 0 else val[0])


def test_attitude_rhat_ignores_the_half_turn_and_sees_an_unmixed_roll():
    """``invert`` judges the attitude modulo the half turn about the line of sight ``k``:
    the body-frame line of sight and the doubled roll. Walkers hold a roll of 20 deg
    (+-3 deg per draw) or its half turn, 200 deg, and share the tilt noise: the
    rotation-vector components jump by the half turn between walkers (R-hat >> 1.1), the
    five judged quantities are i.i.d. across walkers (R-hat < 1.02; ``R = exp(phi k) exp(t)
    R_ref``: ``R^T k = R_ref^T exp(-t) k``, ``2 phi`` unchanged by ``phi -> phi + pi``).
    Walkers each stuck at their own roll (uniform over the circle) are not mixed: the
    doubled roll's R-hat shows it, the line of sight's does not care. The line of sight is
    the posterior file's ``los_polar``/``los_azimuth``."""
    from inversion import attitude_rhat
    from inversion._mcmc import _rotvec_host
    from ppr.geometry import quat_from_rotvec_host, quat_multiply_host

    res = _result(n_steps=400, n_walkers=16, burn_in=0, thin=1)
    rng = np.random.default_rng(4)
    k = np.array([0.3, -0.2, 0.93])
    k /= np.linalg.norm(k)
    i = res.labels.index("rot_x [deg]")

    def with_roll(phi):
        tilt = 0.01 * rng.normal(size=(400, 16, 3))
        tilt -= (tilt @ k)[..., None] * k  # perpendicular to the line of sight
        q = quat_multiply_host(quat_from_rotvec_host(phi * k), quat_from_rotvec_host(tilt))
        phys = np.array(res.physical_chain, copy=True)
        # rotation vectors about the reference: R = exp(w) R_ref, exp(w) = exp(phi k) exp(t)
        phys[..., i : i + 3] = np.degrees(_rotvec_host(q))
        return dataclasses.replace(res, physical_chain=phys)

    half = np.radians(20.0 + 180.0 * (np.arange(16) % 2))[None, :, None]
    split = with_roll(half + np.radians(3.0) * rng.normal(size=(400, 16, 1)))
    judged = attitude_rhat(split, k)
    assert set(judged) == {"los_x", "los_y", "los_z", "roll_cos2", "roll_sin2"}
    assert max(judged.values()) < 1.02, judged
    phys = split.physical_chain
    rot = [float(az.rhat(np.ascontiguousarray(phys[..., i + j].T))) for j in range(3)]
    assert max(rot) > 1.5, rot
    post = split.to_inference_data(line_of_sight=k).posterior
    th, ph = np.radians(post["los_polar"].values), np.radians(post["los_azimuth"].values)
    v = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    ref = {f"los_{c}": float(az.rhat(np.ascontiguousarray(v[..., j]))) for j, c in enumerate("xyz")}
    assert {c: judged[c] for c in ref} == pytest.approx(ref, rel=1e-5)

    stuck = attitude_rhat(with_roll(rng.uniform(-np.pi, np.pi, size=(1, 16, 1))), k)
    assert max(stuck["los_x"], stuck["los_y"], stuck["los_z"]) < 1.02, stuck
    assert max(stuck["roll_cos2"], stuck["roll_sin2"]) > 1.5, stuck


def test_material_indicator_rhat_shows_walkers_that_do_not_share_the_materials():
    """``invert`` judges a library-sampled index by each material's indicator R-hat: walkers
    each stuck in their own material (half in one, half in another) give R-hat >> 1.1;
    walkers drawing the material independently at every step give ~1; a material below 5 %
    of the draws is not judged."""
    from inversion._invert import _material_rhat

    res = _result(n_steps=400, n_walkers=16, burn_in=0, thin=1)
    lib = {"aluminium": 0.94 + 6.42j, "silver": 0.054 + 3.43j, "gold": 0.47 + 2.4j}
    n = np.array(list(lib.values()))
    i_re, i_im = res.labels.index("n_re[0]"), res.labels.index("n_im[0]")
    rng = np.random.default_rng(2)

    def with_materials(which):
        phys = np.array(res.physical_chain, copy=True)
        phys[..., i_re], phys[..., i_im] = n[which].real, n[which].imag
        return dataclasses.replace(res, physical_chain=phys)

    stuck = np.broadcast_to(np.arange(16) % 2, (400, 16))
    r = _material_rhat(with_materials(stuck), lib)
    assert set(r) == {"material[0] = aluminium", "material[0] = silver"}
    assert min(r.values()) == np.inf, r  # no walker ever switches: never mixed
    # every walker in the one material all along: agreement, not a failure to mix
    r = _material_rhat(with_materials(np.zeros((400, 16), int)), lib)
    assert r == {"material[0] = aluminium": 1.0}, r
    # walkers that switch once, half of them at the start: R-hat finite and >> 1.1
    once = np.where(np.arange(400)[:, None] < 40 * (1 + np.arange(16) % 8), np.arange(16) % 2, 2)
    r = _material_rhat(with_materials(once), lib)
    assert all(np.isfinite(v) for v in r.values()) and max(r.values()) > 1.5, r
    mixed = rng.choice(3, p=[0.6, 0.38, 0.02], size=(400, 16))
    r = _material_rhat(with_materials(mixed), lib)
    assert set(r) == {"material[0] = aluminium", "material[0] = silver"}
    assert max(r.values()) < 1.02, r
