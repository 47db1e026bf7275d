"""Roll about the line of sight (inversion._roll): for a monostatic sensor the data are a
degree-2 trigonometric polynomial in twice the roll, so five model calls give the deviance
at every roll exactly; the scan's lowest minimum is the true roll of noise-free data from a
start turned far from it; a bistatic sensor is scanned by direct evaluation."""

from __future__ import annotations

import numpy as np
import pytest

import ppr
from inversion import (
    PhysicalParams,
    PoissonCounts,
    line_of_sight_of,
    los_half_turn,
    roll_scan,
    rolled_about,
)
from inversion._gof import deviance_function

Q_TRUE = np.array([0.9, 0.25, -0.3, 0.2]) / np.linalg.norm([0.9, 0.25, -0.3, 0.2])


def _model(bistatic_angle=0.0):
    from inversion import MeasurementModel, SimulatorModel
    from ppr.pulse import glossy_fresnel_mueller

    mesh = ppr.shapes.cubesat_with_panels(1, panel_span=0.2)
    mats = (ppr.Material(0.94 + 6.4j, 300.0), ppr.Material(1.5, 30.0), ppr.Material(1.8, 5.0))
    scene = ppr.Scene(
        mesh,
        mats,
        ppr.Pose([1.0, 0.0, 0.0, 0.0]),
        ppr.Sensor.make(bistatic_angle=bistatic_angle),
        ppr.Pulse.gaussian(100e-12),
        ppr.RangeBins.centred(0.008, 48),
    )
    chm = MeasurementModel.preset("copol").channel_matrix()
    return SimulatorModel(scene, chm, brdf=glossy_fresnel_mueller, dense=True)


def _truth(gain):
    return PhysicalParams(
        Q_TRUE,
        [300.0, 30.0, 5.0],
        [0.94 + 6.4j, 1.5 + 0j, 1.8 + 0j],
        range_offset=0.004,
        gain=gain,
    )


@pytest.fixture(scope="module")
def mono():
    model = _model()
    return (model, *_observed(model))


def _observed(model, photons=1e6):
    """The truth with the gain giving ``photons`` expected counts, and those counts."""
    unit = _truth(1.0)
    shape = np.asarray(model.expected(unit, model.prepare(unit)), np.float64)
    assert shape.sum() > 0
    return _truth(photons / shape.sum()), shape * (photons / shape.sum())


def test_roll_scan_is_the_exact_deviance_at_every_roll(mono):
    """The five-sample harmonic reconstruction equals the deviance of the model evaluated at
    the turned attitude (with its own visibility) to round-off, at rolls off the sample
    points; the roll keeps the visibility (monostatic), and 180 deg is the identity."""
    model, truth, mu = mono
    data = np.random.default_rng(1).poisson(np.maximum(mu, 0)).astype(float)
    noise = PoissonCounts()
    sc = roll_scan(model, data, truth, noise=noise, n_grid=360)
    assert sc.exact and sc.angles_deg.shape == (360,) and sc.angles_deg[1] == 0.5
    dev = deviance_function(noise)
    for i in (35, 154, 247, 301):  # 17.5, 77, 123.5, 150.5 deg
        p = rolled_about(truth, sc.angles_deg[i], sc.los)
        m = np.asarray(model.expected(p, model.prepare(p)), np.float64) * sc.gain_factor[i]
        np.testing.assert_allclose(sc.deviance[i], dev(data, m), rtol=1e-10)
        # the data do change with the roll (it is not trivially flat)
        assert abs(sc.deviance[i] - sc.deviance[0]) > 1.0
    np.testing.assert_allclose(sc.deviance[0], dev(data, mu * sc.gain_factor[0]), rtol=1e-10)
    p = rolled_about(truth, 180.0, sc.los)
    np.testing.assert_allclose(
        np.asarray(model.expected(p, model.prepare(p))), mu, rtol=1e-9, atol=1e-12 * mu.max()
    )


def test_roll_scan_finds_the_true_roll_from_a_start_turned_away(mono):
    """Noise-free data: from the truth turned by 70 deg about the line of sight, the scan's
    lowest minimum is the turn back (110 deg mod 180) on its 1 deg grid, with the deviance of
    the data against themselves there, and the turned-back attitude is the truth's half turn
    (the same data)."""
    model, truth, mu = mono
    los = line_of_sight_of(model)
    sc = roll_scan(model, mu, rolled_about(truth, 70.0, los))
    best = sc.minima[0]
    assert sc.best_deg == pytest.approx(110.0, abs=1e-9)
    floor = deviance_function(PoissonCounts())(mu, mu)  # the background's own share
    # the deviance sums terms of the size of the counts (1e6 in all): its round-off is
    # ~eps x the total (1.3e-9 seen on one CPU, 1e-8 of this floor of 0.094)
    np.testing.assert_allclose(sc.deviance[best], floor, rtol=1e-8, atol=1e-14 * mu.sum())
    assert np.max(sc.deviance) > 100.0 * floor
    assert np.all(sc.deviance[sc.minima[1:]] > sc.deviance[best])
    q = np.asarray(sc.params(rolled_about(truth, 70.0, sc.los), int(best)).quaternion)
    # 70 + 110 = 180 deg: the truth's half turn about the line of sight (the same data)
    q_half = los_half_turn(Q_TRUE, los)
    assert min(np.linalg.norm(q - q_half), np.linalg.norm(q + q_half)) < 1e-9


def test_bistatic_roll_scan_evaluates_each_roll():
    """A bistatic sensor: no exact harmonic structure; the scan evaluates the model at each
    of its rolls over the full turn (with each roll's visibility), roll 0 being the given
    parameters' own deviance."""
    model = _model(bistatic_angle=0.05)
    truth, mu = _observed(model)
    sc = roll_scan(model, mu, truth, n_direct=8)
    assert not sc.exact and sc.angles_deg.shape == (8,) and sc.angles_deg[-1] == 315.0
    floor = deviance_function(PoissonCounts())(mu, mu)
    assert sc.best_deg == 0.0 and sc.deviance[0] == pytest.approx(floor, rel=1e-8)
    assert np.min(sc.deviance[1:]) > 10.0 * floor
