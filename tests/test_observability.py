"""Observability (inversion._observability): unobservable directions named, finite errors in
the observable subspace, no infinity except for a parameter unobservable on its own."""

from __future__ import annotations

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from inversion._observability import box_edges, observability_from_fisher
from inversion._params import Parametrisation, PhysicalParams
from inversion._refine import PoissonCounts, cramer_rao
from ppr import quat_to_matrix
from ppr._safe import safe_pow
from ppr.geometry import quat_from_rotvec


class LobeProfile(eqx.Module):
    """Unpolarized monostatic range profile of a few facets (sensor along +z): facet ``f``
    returns ``gain A_f (m + 2) cos^m(t_f)`` at depth ``-z(c_f) + range_offset`` (Gaussian
    pulse), ``cos t_f = z(R n_f)``. It depends on the attitude only through the body-frame
    line of sight ``R^T z``, so a roll about the line of sight changes nothing, at any
    attitude: the Fisher matrix is exactly singular there."""

    normals: jax.Array
    centers: jax.Array
    areas: jax.Array
    bins: jax.Array

    def prepare(self, phys):
        return jnp.ones(())

    def expected(self, phys, aux):
        R = quat_to_matrix(phys.quaternion)
        cos = jnp.clip((self.normals @ R.T)[:, 2], 0.0, 1.0)
        depth = -(self.centers @ R.T)[:, 2] + phys.range_offset
        amp = 1e3 * phys.gain * self.areas * (phys.m[0] + 2.0) * safe_pow(cos, phys.m[0])
        prof = jnp.exp(-0.5 * ((self.bins[None, :] - depth[:, None]) / 0.03) ** 2)
        return (amp @ prof)[None, :] * aux


def test_roll_about_the_line_of_sight_is_named_and_nothing_else_is_infinite():
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(5, 3))
    normals[:, 2] = np.abs(normals[:, 2]) + 1.0
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    model = LobeProfile(
        jnp.asarray(normals),
        jnp.asarray(rng.uniform(-0.15, 0.15, (5, 3))),
        jnp.asarray(rng.uniform(0.5, 1.5, 5)),
        jnp.linspace(-0.35, 0.35, 32),
    )
    q = np.asarray(quat_from_rotvec(jnp.array([0.3, -0.2, 0.4])))
    truth = PhysicalParams(q, [10.0], [1.5], range_offset=0.01, gain=2.0)
    free = ("attitude", "m", "range_offset", "gain")
    crb = cramer_rao(model, truth, PoissonCounts(), free=free)
    ob = crb.observability()
    assert len(ob.names) == 1 and ob.names[0].startswith("roll about the line of sight")
    # the roll axis in the body frame is the body-frame line of sight R^T z
    body_los = np.asarray(quat_to_matrix(jnp.asarray(q)))[2]
    np.testing.assert_allclose(ob.unobservable[0].axis_body, body_los, atol=1e-9)
    assert ob.rank == len(ob.labels) - 1
    iz = ob.labels.index("rot_z [deg]")
    assert not ob.observable[iz] and np.isinf(ob.sigma[iz])
    rest = np.delete(ob.sigma, iz)
    assert np.all(np.isfinite(rest)) and np.all(rest > 0)
    assert np.all(np.delete(ob.determined, iz))
    # the other parameters touch no null direction: their subspace sigma is the marginal
    # bound (pseudo-inverse of the plain Fisher matrix; two inverses' round-off: 1e-6)
    np.testing.assert_allclose(rest, np.delete(crb.sigma, iz), rtol=1e-6)
    d = ob.to_dict()
    json.dumps(d, allow_nan=False)  # no Infinity anywhere
    assert d["sigma"][iz] is None and sum(s is None for s in d["sigma"]) == 1
    assert d["unobservable_on_own"] == ["rot_z [deg]"]
    assert "unobservable on its own" in ob.summary()
    assert d["at_bounds"] == {}  # m = 10, gain = 2, offset 1 cm: inside the box
    # a parameter on an edge of the physical box gets no Gaussian sigma: the likelihood is
    # cut there, not curved (a mirror-smooth part at m = 1e6, a dielectric's n'' = 0)
    vals = [2.0, 1e6, 1e-6, 0.05, 1.0, 1e12, 1.5e-9]
    labs = ["rot_x [deg]", "m[0]", "n_im[0]", "n_re[0]", "range_offset [m]", "gain"]
    labs += ["thickness[0] [m]"]  # 1.5 nm: inside the box (lower bound 1 nm)
    assert box_edges(labs, vals) == {
        "m[0]": "at the upper bound 1e+06",
        "n_im[0]": "at the lower bound 0",
        "n_re[0]": "at the lower bound 0.05",
        "range_offset [m]": "at the upper bound 1",
    }
    # a line of sight along x names the same direction a rotation 90 deg from it
    side = crb.observability(line_of_sight=(1.0, 0.0, 0.0))
    assert "90.0 deg from the line of sight" in side.names[0]


def _param(free, **kw):
    ref = PhysicalParams([1.0, 0, 0, 0], [kw.get("m", 20.0)], [kw.get("n", 1.4 + 0.1j)], gain=3.0)
    return Parametrisation(ref, free)


def test_trade_offs_own_axis_nulls_and_near_degeneracy_are_named():
    rng = np.random.default_rng(1)
    par = _param(("m", "n", "range_offset", "gain"))
    labels = par.theta_labels
    assert labels == [
        "log_m[0]",
        "log_n_re[0]",
        "softplus_inv_n_im[0]",
        "range_offset/range_scale",
        "log_gain",
    ]
    # the data see gain x m^2 (columns of log m and log gain in ratio 2:1), n'' not at all
    base = rng.normal(size=(40, 3))
    J = np.stack([2 * base[:, 0], base[:, 1], np.zeros(40), base[:, 2], base[:, 0]], 1)
    ob = observability_from_fisher(J.T @ J, par)
    names = ob.names
    assert names[0] == "n_im[0]" and not ob.observable[labels.index("softplus_inv_n_im[0]")]
    trade = names[1]
    assert "gain" in trade and "m[0]" in trade
    loads = ob.unobservable[1].loadings
    assert -loads["log_m[0]"] / loads["log_gain"] == pytest.approx(0.5, rel=1e-9)  # v ~ (1, -2)
    assert "the data fix m[0] x gain^-0.5" in trade or "the data fix gain x m[0]^2" in trade
    assert ob.rank == 3
    assert np.isfinite(ob.sigma_of("gain")) and not ob.determined[par.labels.index("gain")]
    assert ob.determined[par.labels.index("n_re[0]")]
    # a near-degeneracy (columns 1 - 1e-12 correlated) is a null direction at the default
    # rtol 1e-8 and an observable one at 1e-14
    J2 = np.stack(
        [
            base[:, 0],
            base[:, 0] + 1e-6 * rng.normal(size=40),
            base[:, 1],
            base[:, 2],
            rng.normal(size=40),
        ],
        1,
    )
    assert observability_from_fisher(J2.T @ J2, par).rank == 4
    assert observability_from_fisher(J2.T @ J2, par, rtol=1e-14).rank == 5
    # a dielectric fitted on the floor of n'' (1e-9, flat coordinate): no local information,
    # said so
    floor = _param(("m", "n", "range_offset", "gain"), n=1.5 + 0.0j)
    J3 = J.copy()
    J3[:, 0] = base[:, 0] + base[:, 1] ** 2
    named = observability_from_fisher(J3.T @ J3, floor).names
    assert named == ["n_im[0] (at its lower bound 0: no local information)"]
    with pytest.raises(ValueError, match="does not match"):
        observability_from_fisher(np.eye(3), par)


def test_two_null_directions_led_by_one_parameter_get_distinct_names():
    """A fit at the roughness ceiling has two null directions both led by ``m[0]`` (alone,
    and with a few % of the gain and an index): named once each, the second by all of its
    physical components, so the summary never lists one name twice."""
    from inversion._observability import UnobservableDirection, _distinct_names

    a = UnobservableDirection("m[0]", {"log_m[0]": 1.0}, {"m[0]": 1.0}, 0.0)
    b = UnobservableDirection(
        "m[0]", {"log_m[0]": 0.99}, {"m[0]": 0.99, "gain": -0.08, "n_im[0]": 0.05}, 1e-10
    )
    c = UnobservableDirection("m[0]", {"log_m[0]": 1.0}, {"m[0]": 1.0}, 0.0)
    names = [d.name for d in _distinct_names([a, b, c])]
    assert names == ["m[0]", "m[0] vs gain vs n_im[0]", "m[0] (direction 2)"], names
    assert len(set(names)) == 3
