"""inversion.invert end to end on the toy facet model of tests/test_refine.py (Blinn-Phong
facets with Fresnel Mueller matrices, 16 PSG x PSA channels; cheap to compile), over a tiny
screening bank of a few attitudes: what the workflow must prove, not the grid search (that
is bench/bench_inversion.py's held-out measurement).

- a box observed at an attitude 6 deg off one of the bank's: the shape (against a cube), the
  attitude and the material are recovered, the mirror image is refit and rejected by the
  off-block channels, the fit is acceptable, and the result is ``reliable``; the posterior
  file holds the physical samples, the JSON has no inf/NaN and no bare ``success``;
- the same data against the cube alone: a model mismatch, ``reliable`` False, the reason
  named and printed first in the summary;
- material probabilities sum to 1 and favour the truth (aluminium against gold and fused
  silica, which the incidence-dependent Fresnel matrices of the facets tell apart);
- a target whose roll about the line of sight no channel sees (the intensity channels
  only): the roll is named unobservable and nothing in the written JSON is inf or NaN;
- a bad MCMC field is refused, naming the field and the value, before the model is called.
"""

from __future__ import annotations

import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_modes import BOX, Q0, _toy
from test_refine import ToyFacetModel

import inversion
import ppr
from inversion import Candidate, PhysicalParams
from ppr.config import ConfigError
from ppr.geometry import quat_from_axis_angle as axis_angle_quat
from ppr.geometry import quat_multiply_host as quat_mul

N_AL = complex(np.asarray(ppr.load_material("aluminium").n))
MATERIALS = ["aluminium", "gold", "fused_silica"]
WIDTH = 0.8 / 63  # the toy's bin width (m): np.linspace(-0.4, 0.4, 64)
_expected = eqx.filter_jit(ToyFacetModel.expected)


def _observe(model, q, *, m=6.0, n=N_AL, gain=5.0, offset=0.012, seed=0):
    truth = PhysicalParams(q, [m], [n], range_offset=offset, gain=gain)
    mu = np.asarray(_expected(model, truth, model.prepare(truth)))
    return truth, np.random.default_rng(seed).poisson(np.maximum(mu, 0.0)).astype(float)


def _bank_attitudes(q_true, seed=3):
    """Five random attitudes and one 6 deg from the truth."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(5, 4))
    near = quat_mul(axis_angle_quat([0.3, -0.5, 0.8], math.radians(6.0)), q_true)
    return np.vstack([q / np.linalg.norm(q, axis=1, keepdims=True), near])


@pytest.fixture(scope="module")
def box_case():
    box_mesh, cube_mesh = ppr.shapes.box(BOX), ppr.shapes.box((0.2, 0.2, 0.2))
    cands = [
        Candidate("box", _toy(box_mesh), symmetry=box_mesh, bin_width_m=WIDTH),
        Candidate("cube", _toy(cube_mesh), symmetry=cube_mesh, bin_width_m=WIDTH),
    ]
    truth, data = _observe(cands[0].model, Q0)
    mats = {m: complex(np.asarray(ppr.load_material(m).n)) for m in MATERIALS}
    bank = inversion.screening_bank(cands, mats, {"rough": 6.0}, attitudes=_bank_attitudes(Q0))
    return cands, truth, data, bank


CONFIG = {"materials": MATERIALS, "top_k": 2, "free": ["attitude", "m", "range_offset", "gain"]}
SHORT_CHAIN = {"sampler": {"n_walkers": 16, "n_steps": 60, "burn_in": 20, "progress": False}}


def test_invert_recovers_box_attitude_material_and_is_reliable(box_case, tmp_path):
    cands, truth, data, bank = box_case
    inv = inversion.invert(data, cands, config=CONFIG, bank=bank)
    # shape and attitude: the box, its line of sight within a degree (modulo its rotations)
    assert inv.shape == "box" and inv.shape_probabilities["box"] > 0.99, inv.summary()
    err = inv.compare(truth, "box")
    assert err["los_error_deg"] < 1.0 and err["attitude_error_deg"] < 2.0, err
    # the mirror image was refit, and the off-block channels reject it
    assert inv.modes[0].kind == "fit" and [m.kind for m in inv.modes[1:]] == ["mirror"]
    assert inv.modes[1].weight < 1e-6, inv.summary()
    # material probabilities: a distribution favouring the truth
    probs = inv.material_probabilities[0]
    assert set(probs) == set(MATERIALS) and abs(sum(probs.values()) - 1.0) < 1e-12
    assert inv.material == ("aluminium",) and probs["aluminium"] > 0.9, probs
    # each library material's row is that material's optimum: no worse than a refit of it
    # started at the truth's attitude, m and offset (the gain scaled by the data's total; a
    # dielectric's reflectance is ~25x below aluminium's, which the row's start must absorb)
    noise = inversion.PoissonCounts(background=inversion.InvertConfig().background)
    for row in inv.materials[0]:
        start = PhysicalParams(Q0, truth.m, [row.n], range_offset=truth.range_offset, gain=1.0)
        mu = np.asarray(_expected(cands[0].model, start, cands[0].model.prepare(start)))
        start = PhysicalParams(
            Q0, truth.m, [row.n], range_offset=truth.range_offset, gain=data.sum() / mu.sum()
        )
        ref = inversion.refine(
            cands[0].model, data, [start], noise=noise, free=CONFIG["free"], rounds=3
        )
        assert row.fit.cost <= ref.cost * (1 + 1e-6), (row.name, row.fit.cost, ref.cost)
    # acceptable fit, converged solver, one mode: reliable, with no reasons
    assert not inv.goodness_of_fit.model_mismatch and inv.converged
    assert inv.reliable and inv.reasons == (), inv.summary()
    assert inv.summary().startswith("RELIABLE")

    # the same with a posterior: a 60-step chain has not converged, which is the one reason
    # (the same compiled programs: only the sampler's are new)
    inv = inversion.invert(data, cands, config={**CONFIG, "mcmc": SHORT_CHAIN}, bank=bank)
    assert inv.converged and not inv.reliable and len(inv.reasons) == 1, inv.reasons
    assert inv.reasons[0].startswith("posterior of mode 0") and "not converged" in inv.reasons[0]
    # files: JSON without inf/NaN or a bare success, the posterior in physical units
    written = inv.write(tmp_path / "out")
    assert {"invert.json", "invert_fit.npz", "invert_posterior.nc"} <= {p.name for p in written}
    d = json.loads((tmp_path / "out" / "invert.json").read_text())
    assert d["reliable"] is False and d["converged"] is True and d["reasons"] == list(inv.reasons)
    assert '"success"' not in json.dumps(d)
    assert d["goodness_of_fit"]["model_mismatch"] is False
    # the posterior over the sampled modes, in the JSON: weights and ordered intervals
    pm = d["posterior_over_modes"]
    assert abs(sum(pm["weights"]) - 1.0) < 1e-12
    for lab in ("gain", "range_offset [m]"):
        v = pm["intervals"][lab]
        assert v["95"][0] <= v["68"][0] <= v["median"] <= v["68"][1] <= v["95"][1], v
    # the posterior over the sampled modes: the mirror image weighs < 1e-6, so its intervals
    # are mode 0's (to the resampling error of 2e4 draws)
    mix = inv.mixture
    assert mix.weights.sum() == pytest.approx(1.0, abs=1e-12) and mix.weights[0] > 0.999
    post0 = inv.modes[0].posterior
    for lab in ("gain", "range_offset [m]"):
        lo, hi = post0.interval(0.68)[post0.labels.index(lab)]
        np.testing.assert_allclose(mix.interval(lab, 0.68), [lo, hi], atol=0.05 * (hi - lo))
    import arviz as az

    idata = az.from_netcdf(tmp_path / "out" / "invert_posterior.nc")
    post = inv.modes[0].posterior
    np.testing.assert_allclose(
        idata.posterior["gain"].values,
        np.swapaxes(post.physical_chain[post.burn_in :, :, post.labels.index("gain")], 0, 1),
        rtol=1e-12,
    )


def test_out_of_bank_target_is_a_model_mismatch(box_case):
    """The box's data against the cube alone: no parameter values fit, and the result says
    so first."""
    cands, truth, data, bank = box_case
    cube_bank = inversion.screening_bank(
        cands[1:],
        {m: complex(np.asarray(ppr.load_material(m).n)) for m in MATERIALS},
        {"rough": 6.0},
        attitudes=_bank_attitudes(Q0),
    )
    inv = inversion.invert(data, cands[1:], config=CONFIG, bank=cube_bank)
    assert inv.goodness_of_fit.model_mismatch and inv.goodness_of_fit.p_value < 1e-6
    assert not inv.reliable and inv.reasons[0].startswith("model mismatch"), inv.reasons
    assert "or an optimum the search missed" in inv.reasons[0], inv.reasons
    assert inv.summary().startswith("NOT RELIABLE: model mismatch")
    assert "MODEL MISMATCH" in inv.summary()


def test_a_missed_optimum_is_searched_for_before_a_mismatch_is_reported(box_case, monkeypatch):
    """A screening that starts only from the worst-ranked template (a search that missed the
    optimum: its screened deviance is a model mismatch) goes on to the next templates in rank
    order while the best screened fit is a mismatch, and stops at the first acceptable one;
    with ``escalate = 0`` it screens the one start. A good first pick screens nothing more."""
    from inversion import _invert

    cands, truth, data, bank = box_case
    inv0 = inversion.invert(data, cands, config={**CONFIG, "escalate": 0}, bank=bank)
    inv1 = inversion.invert(data, cands, config={**CONFIG, "escalate": 12}, bank=bank)
    assert [s.n_starts for s in inv1.shapes] == [s.n_starts for s in inv0.shapes]

    worst = lambda cls, bank_, top_k, per_shape: _invert._ranked_rows(cls, bank_)[-1:]  # noqa: E731
    monkeypatch.setattr(_invert, "_pick_rows", worst)
    cfg = {**CONFIG, "top_k": 1, "per_shape": 0, "face_on": 0}  # the escalation alone
    inv = inversion.invert(data, cands, config={**cfg, "escalate": 0}, bank=bank)
    assert sum(s.n_starts for s in inv.shapes) == 1
    gof = inversion.goodness_of_fit(
        data,
        np.asarray(_expected(cands[0].model, truth, cands[0].model.prepare(truth))),
        inversion.PoissonCounts(1e-3),
        n_params=6,
    )
    assert inv.shapes[0].screened_deviance > gof.expected + 10 * gof.std  # a missed optimum
    inv = inversion.invert(data, cands, config={**cfg, "escalate": 12}, bank=bank)
    n = sum(s.n_starts for s in inv.shapes)
    assert 1 < n < 12, n  # went on, and stopped before the end of the ranking
    box = next(s for s in inv.shapes if s.name == "box")
    assert box.screened_deviance < gof.expected + 4 * gof.std, inv.summary()
    assert not inv.goodness_of_fit.model_mismatch and inv.shape == "box"
    assert inv.compare(truth, "box")["los_error_deg"] < 1.0


def test_other_optima_find_the_basin_a_wrong_fit_missed_and_invent_none(box_case):
    """The search for other optima (``_other_optima``: roll-scanned lines of sight over the
    sphere at the fit's materials, the best screened) from a converged fit in a wrong basin
    (polished from 100 deg off the truth: its deviance far above the truth's null
    distribution) finds the truth's basin, and the mode check refits it from its own
    parameters into the most probable mode, at the true line of sight with an acceptable
    goodness of fit. From the converged fit at the truth it adds no mode: every other basin
    (the mirror image, which the off-block channels reject) is more than ``OTHER_DELTA``
    worse."""
    from inversion import _invert
    from inversion._modes import candidate_modes

    cands, truth, data, bank = box_case
    model = cands[0].model
    cfg = inversion.InvertConfig(**CONFIG)
    noise = _invert._noise_of(cfg)
    free = ("attitude", "m", "range_offset", "gain")
    ref = _invert._Refiner(model, noise, data, free, cfg)
    sym = cands[0].mode_symmetry(cfg.symmetry, cfg.near_tol)
    mu = np.asarray(_expected(model, truth, model.prepare(truth)))
    null = inversion.goodness_of_fit(data, mu, noise, n_params=6)

    wrong = quat_mul(axis_angle_quat([1.0, 0.0, 0.0], math.radians(100.0)), Q0)
    off = ref.polish(_invert._with(truth, quaternion=jnp.asarray(wrong)))
    assert off.cost > null.expected + 10 * null.std  # a wrong basin, converged
    assert inversion.line_of_sight_error_deg(np.asarray(Q0), off.params.quaternion)[0] > 10.0
    geo = {"los": (0.0, 0.0, 1.0), "half_turn_exact": True}
    modes = candidate_modes(np.asarray(off.params.quaternion), sym, **geo)
    found = _invert._other_optima(ref, data, off, sym, modes, True, cfg)
    assert found and all(m.kind == "other optimum" and m.start is not None for m in found)
    chk = inversion.mode_check(
        model, data, off, sym, noise=noise, modes=modes + found, **geo, max_steps=cfg.max_steps
    )
    best = max(chk.modes, key=lambda m: m.weight)
    assert best.mode.kind == "other optimum" and best.weight > 0.99, chk
    los_err = inversion.line_of_sight_error_deg(np.asarray(Q0), best.fit.params.quaternion, sym)
    assert los_err[0] < 1.0, los_err
    mu = np.asarray(_expected(model, best.fit.params, model.prepare(best.fit.params)))
    assert not inversion.goodness_of_fit(data, mu, noise, n_params=6).model_mismatch

    fit = ref.polish(truth)
    modes = candidate_modes(np.asarray(fit.params.quaternion), sym, **geo)
    assert _invert._other_optima(ref, data, fit, sym, modes, True, cfg) == []
    # a named symmetry class (a string) is accepted like a mesh's group
    assert _invert._other_optima(ref, data, fit, "dihedral:2", modes, True, cfg) == []


class _IntensityOnly(eqx.Module):
    """The toy's H and V channels summed (``2 M_00``): blind to the polarization frame, so
    the roll about the line of sight changes nothing."""

    toy: ToyFacetModel

    def prepare(self, phys):
        return self.toy.prepare(phys)

    def expected(self, phys, aux):
        return jnp.sum(self.toy.expected(phys, aux)[jnp.array([0, 1, 4, 5])], 0, keepdims=True)


def test_unobservable_roll_is_named_and_json_has_no_inf(tmp_path):
    box_mesh = ppr.shapes.box(BOX)
    model = _IntensityOnly(_toy(box_mesh))
    truth = PhysicalParams(Q0, [6.0], [N_AL], range_offset=0.012, gain=5.0)
    mu = np.asarray(eqx.filter_jit(_IntensityOnly.expected)(model, truth, model.prepare(truth)))
    data = np.random.default_rng(1).poisson(np.maximum(mu, 0.0)).astype(float)
    cand = Candidate("box", model, symmetry=box_mesh, bin_width_m=WIDTH)
    mats = {m: complex(np.asarray(ppr.load_material(m).n)) for m in MATERIALS}
    bank = inversion.screening_bank([cand], mats, {"rough": 6.0}, attitudes=_bank_attitudes(Q0))
    inv = inversion.invert(data, [cand], config=CONFIG, bank=bank)
    assert any("roll about the line of sight" in n for n in inv.observability.names)
    # a roll the data do not see: the observable-subspace sigmas are finite except for a
    # parameter unobservable on its own, which the JSON writes as null next to its name
    inv.write(tmp_path / "roll")
    text = (tmp_path / "roll" / "invert.json").read_text()
    d = json.loads(text)  # strict JSON: Infinity/NaN would not parse with allow_nan=False
    json.dumps(d, allow_nan=False)
    ob = d["observability"]
    nulls = [lab for lab, s in zip(ob["labels"], ob["sigma"], strict=True) if s is None]
    assert nulls == ob["unobservable_on_own"]
    assert "Infinity" not in text and "NaN" not in text


class _Untouchable(eqx.Module):
    """A forward model that must not be called (validation happens first)."""

    def prepare(self, phys):  # pragma: no cover - reaching it is the failure
        raise AssertionError("the model was called before the config was validated")

    def expected(self, phys, aux):  # pragma: no cover
        raise AssertionError("the model was called before the config was validated")


@pytest.mark.parametrize(
    "config, words",
    [
        (
            {"mcmc": {"sampler": {"n_walkers": 2}}},
            ["mcmc.sampler.n_walkers = 2", "greater than or equal to 4"],
        ),
        ({"mcmc": {"sampler": {"n_steps": 100, "burn_in": 200}}}, ["burn_in (200)", "n_steps"]),
        ({"mcmc": {"priors": {"m": {"kind": "uniform", "low": 5.0}}}}, ["mcmc.priors.m"]),
        ({"top_k": 0}, ["top_k = 0"]),
        ({"materials": ["aluminium", "unobtainium"]}, ["materials[1] = 'unobtainium'"]),
        ({"symmetry": "dihedral"}, ["symmetry = 'dihedral'"]),
        # a Hopf grid grows as 72 size^3: size 4096 would need petabytes, found when built
        ({"grid": {"size": 4096}}, ["grid.size = 4096", "4.95e+12 attitudes", "lower grid.size"]),
        # a named order whose group closure would run for hours: refused before it is built
        ({"symmetry": "dihedral:100000000"}, ["symmetry = 'dihedral:100000000'", "above 64"]),
        # an inline index outside the refiner's box would be moved into it
        (
            {"materials": [{"name": "x", "n_real": 1e300, "n_imag": 0.1}]},
            ["materials[0].n_real = 1e+300", "outside [0.05, 5]"],
        ),
        (
            {"materials": [{"name": "x", "n_real": 1.5, "n_imag": -0.1}]},
            ["materials[0].n_imag = -0.1", "outside [0, 15]"],
        ),
        # the refiner moves log m: a finish at m = 0 cannot move, one outside the m prior's
        # support gives fits the sampler refuses (found after the whole refinement)
        ({"finishes": {"rough": 0.0}}, ["finishes.rough = 0.0", "greater than 0"]),
        (
            {"finishes": {"rough": 1e-6}, "mcmc": {}},
            ["finishes.rough = 1e-06", "support [0.001, 1e+06] of mcmc.priors.m"],
        ),
        # an inline index named like a listed library material would replace it
        (
            {"materials": [{"name": "gold", "n_real": 1.5, "n_imag": 0.0}, "gold"]},
            ["materials = ", "the name 'gold' is given twice"],
        ),
    ],
)
def test_config_is_validated_before_any_computation(config, words):
    data = np.ones((16, 64))
    with pytest.raises(ConfigError) as err:
        inversion.invert(data, {"box": _Untouchable()}, config=config)
    msg = str(err.value)
    assert len(msg.splitlines()) == 1
    for w in words:
        assert w in msg, msg


@pytest.mark.parametrize(
    "observation, kwargs, words",
    [
        # complex data: the imaginary part would be lost by a cast (also inside an Observation)
        (np.ones((16, 64)) + 1j, {}, ["complex", "imaginary part"]),
        (
            inversion.Observation(data=np.ones((16, 64)) + 0j, sensor=""),
            {},
            ["complex", "imaginary part"],
        ),
        (
            inversion.Observation(data=np.full((16, 64), np.nan), sensor=""),
            {},
            ["1024 non-finite", "first at index (0, 0)"],
        ),
        (np.zeros((16, 64)), {}, ["all 1024 values are 0", "no signal"]),
        (np.full((16, 64), 1e300), {}, ["value 1e+300 at index (0, 0)", "2^53"]),
        ([[1.0, 2.0], [3.0]], {}, ["observation: not a (channels, bins) array"]),
        (
            np.ones((16, 64)) * np.r_[1.0, -2.0, np.ones(62)],
            {},
            ["negative", "(0, 1): -2.0", 'set likelihood = "gaussian"'],
        ),
        (np.ones((16, 64)), {"noise": "poisson"}, ["noise: expected a noise model", "str"]),
        (np.ones((16, 64)), {"candidates": {"box": 3}}, ["candidates['box'] is int"]),
    ],
    ids=[
        "complex",
        "observation-complex",
        "observation-nan",
        "zero",
        "huge",
        "ragged",
        "negative",
        "noise",
        "candidate",
    ],
)
def test_bad_observation_or_argument_is_named_before_any_computation(observation, kwargs, words):
    """Data the likelihood cannot take, or would take only after a silent cast, are refused
    by name (with the first offending position and value) before a model is called: the
    Poisson deviance has no signal to fit in all-zero counts (the fit would wander to the
    edge of the gain and range boxes and call that converged), and counts above 2^53 are not
    exact in float64 and overflow the refiner's normal equations."""
    cands = kwargs.pop("candidates", {"box": _Untouchable()})
    with pytest.raises(ValueError) as err:
        inversion.invert(observation, cands, config={"materials": ["gold"]}, **kwargs)
    msg = str(err.value)
    for w in words:
        assert w in msg, msg


def test_candidates_or_a_bank_of_other_sensor_settings_are_refused():
    """Two candidates whose range bins differ (1 cm and 5 cm: the same counts mean different
    depths), or a screening bank built from models of other settings, were accepted without
    a word; refused naming the setting, before any model runs."""
    from ppr.pulse import glossy_fresnel_mueller

    def cube(width, fwhm=100e-12):
        scene = ppr.Scene(
            ppr.shapes.cubesat(1),
            (ppr.Material(1.5, 10.0),),
            ppr.Pose([1.0, 0.0, 0.0, 0.0]),
            ppr.Sensor.make(),
            ppr.Pulse.gaussian(fwhm),
            ppr.RangeBins.centred(width, 32),
        )
        chm = inversion.MeasurementModel.preset("copol").channel_matrix()
        return inversion.SimulatorModel(scene, chm, brdf=glossy_fresnel_mueller, dense=True)

    data = np.ones((2, 32))
    fine, coarse, slow = cube(0.01), cube(0.05), cube(0.01, 400e-12)
    with pytest.raises(ValueError, match=r"candidate 'b': bins.width_m = 0.05 differs from"):
        inversion.invert(data, {"a": fine, "b": coarse}, config={"mcmc": None})
    with pytest.raises(ValueError, match=r"candidate 'b': pulse.sigma_t_s = .* differs from"):
        inversion.invert(data, {"a": fine, "b": slow}, config={"mcmc": None})
    bank = inversion.screening_bank(
        {"a": coarse}, {"gold": 0.2 + 7j}, {"rough": 10.0}, grid={"size": 1}
    )
    assert bank.names["model_sensor"]["bins.width_m"] == [0.05]
    with pytest.raises(
        ValueError, match=r"candidate 'a': bins.width_m = 0.01 differs from the bank"
    ):
        inversion.invert(data, {"a": fine}, config={"mcmc": None}, bank=bank)
    # a model built before x64 was switched on holds float32 arrays: refused by name too
    with jax.enable_x64(False):
        f32 = cube(0.01)
    with pytest.raises(ValueError, match="candidate 'a' holds float32 arrays"):
        inversion.invert(data, {"a": f32}, config={"mcmc": None})


def test_float32_is_refused_before_any_computation():
    """Without x64 the point fit ran in float32 unannounced (only the sampler refused it):
    the observability named other directions (a roll at +-692 deg in the 'observable'
    subspace) and a goodness-of-fit test was dropped. Refused by name, like the sampler."""
    with jax.enable_x64(False), pytest.raises(ValueError, match="needs float64: enable x64"):
        inversion.invert(np.ones((16, 64)), {"box": _Untouchable()}, config={"mcmc": None})


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"symmetry": "weird"}, ["Candidate 'box': symmetry = 'weird'", "unknown symmetry"]),
        ({"bin_width_m": -0.01}, ["Candidate 'box': bin_width_m = -0.01", "> 0"]),
        ({"bin_width_m": math.nan}, ["bin_width_m = nan"]),
        ({"model": None}, ["Candidate 'box': model is NoneType"]),
        ({"name": ""}, ["name must be a non-empty string"]),
    ],
)
def test_candidate_fields_are_checked_when_made(kwargs, words):
    """A candidate's symmetry name, bin width and model are checked when it is made, not
    where the screening bank first uses them."""
    args = {"name": "box", "model": _Untouchable(), **kwargs}
    with pytest.raises(ValueError) as err:
        Candidate(**args)
    for w in words:
        assert w in str(err.value), str(err.value)


def test_index_fisher_scoring_follows_the_reflectance_ridge_to_the_noise_free_optimum():
    """The continuous-index stage (Fisher scoring with ``n`` free) on a glossy box (m = 20)
    seen 8 deg off face-on: the return is nearly a normal-incidence Fresnel reflection, so
    the gain absorbs the reflectance along a curved ridge in (n', n'', gain). Noise-free
    counts ``d = mu(truth) + background`` put the Poisson deviance's minimum exactly at 0
    (aluminium). Started like ``invert`` does, at another metal's index (gold, silver) with
    the gain matching the total counts, it must reach that minimum (deviance below its 1e-3
    stopping tolerance) and say converged. Zig-zagging across the ridge (unsheared steps,
    the damping relaxed tenfold after every accepted step) ended 12 steps later at deviance
    1.2 from gold, and called deviance 0.11 from silver converged."""
    from inversion._invert import InvertConfig, _index_fit, _Refiner

    model = _toy(ppr.shapes.box(BOX))
    q = np.asarray(axis_angle_quat([1.0, 0.3, 0.0], math.radians(8.0)))
    m, bg = 20.0, 1e-3
    truth = PhysicalParams(q, [m], [N_AL], range_offset=0.012, gain=5.0)
    mu = np.asarray(_expected(model, truth, model.prepare(truth)), np.float64)
    cfg = InvertConfig(free=["attitude", "m", "n", "range_offset", "gain"], background=bg)
    free = tuple(cfg.free)
    refiner = _Refiner(model, inversion.PoissonCounts(background=bg), mu + bg, free, cfg)
    for name in ("gold", "silver"):
        n0 = complex(np.asarray(ppr.load_material(name).n))
        unit = PhysicalParams(q, [m], [n0], range_offset=0.012, gain=1.0)
        gain = mu.sum() / float(np.asarray(_expected(model, unit, model.prepare(unit))).sum())
        start = PhysicalParams(q, [m], [n0], range_offset=0.012, gain=gain)
        fit = _index_fit(refiner, refiner.at(start), free, cfg)
        assert fit.success, (name, fit.message, fit.cost)
        assert fit.cost < 1e-3, (name, fit.cost, complex(np.asarray(fit.params.n)[0]))


def test_material_stage_polishes_every_refit_that_can_matter(monkeypatch):
    """The material stage's polish rule (``_polish_material_fits``): a local refit within the
    log-evidence window of the best is polished, and so is an unconverged one however far
    behind; a converged one far behind is not; a polish that ends worse is rejected; a polish
    that lowers the best brings a refit newly inside the window in on the next pass; the
    current fit (not a local refit) is never touched; an unconverged refit whose deviance
    decrement cannot bring it into the window is not polished (unknown decrement: it is)."""
    from types import SimpleNamespace as NS

    import inversion._invert as inv_mod

    monkeypatch.setattr(inv_mod, "MATERIAL_POLISH_WINDOW", 10.0)
    monkeypatch.setattr(inv_mod, "log_evidence", lambda f, priors=None: f.lz)

    def fit(name, cost, lz, success=True, decrement=None):
        return NS(name=name, cost=cost, lz=lz, success=success, params=name, decrement=decrement)

    # what a polish of each local refit returns (keyed by the refit's params = its name); a
    # polish lowers the deviance, its log evidence moves either way
    polished = {
        "near": fit("near*", 99.0, -5.0),
        "far": fit("far*", 0.0, 0.0),  # would win, but a converged far refit is not polished
        "stuck": fit("stuck*", 50.0, -3.0),  # unconverged, far behind: polished
        "worse": fit("worse*", 120.0, 5.0),  # the polish ended higher: rejected
        "best": fit("best*", 4.0, -6.0),  # the polish lowers the best's evidence ...
        "edge": fit("edge*", 30.0, -2.5),  # ... which brings this one into the window
        "hopeless": fit("hopeless*", 0.0, 0.0),  # never asked for: see below
    }
    calls = []

    class Refiner:
        def polish(self, params):
            calls.append(params)
            return polished[params]

    # first pass: top 0, window [-10, 0]; after it the top is stuck*'s -3: window [-13, -3]
    fits = [
        fit("current", 40.0, -20.0),  # the current fit: never polished
        fit("near", 100.0, -1.0),
        fit("far", 500.0, -15.0),
        fit("stuck", 900.0, -30.0, success=False),
        fit("worse", 110.0, -4.0),
        fit("best", 5.0, 0.0),
        fit("edge", 31.0, -12.0),
        # unconverged, but its whole decrement (3) plus the Occam slack (5) leaves it at
        # -14, outside every window of the passes (the lowest: [-13, -3])
        fit("hopeless", 80.0, -22.0, success=False, decrement=3.0),
    ]
    lz = [f.lz for f in fits]
    local = [False] + [True] * 7
    inv_mod._polish_material_fits(Refiner(), fits, lz, local, None)
    assert sorted(calls) == sorted(["near", "stuck", "worse", "best", "edge"])
    assert [f.name for f in fits] == [
        "current",
        "near*",
        "far",
        "stuck*",
        "worse",
        "best*",
        "edge*",
        "hopeless",
    ]
    assert lz == [f.lz for f in fits]


def test_material_probabilities_are_averaged_over_unresolved_shapes():
    """P(material) = sum_s P(s) P(material | s) / sum_s P(s) over the shapes kept: a shape
    read with probability 0.6 whose table says gold 0.9, and one with 0.4 saying aluminium
    0.95, give gold 0.6 x 0.9 + 0.4 x 0.05 = 0.56 (normalised over 1.0), the rows' fits and
    evidences those of the chosen shape."""
    import dataclasses

    import inversion._invert as inv_mod

    @dataclasses.dataclass(frozen=True)
    class Row:  # MaterialFit's fields that the average reads or keeps
        name: str
        fit: str
        log_evidence: float
        probability: float

    def rows(probs):
        return [
            [Row(name, f"fit-{name}", -float(k), p) for k, (name, p) in enumerate(probs.items())]
        ]

    best = rows({"gold": 0.9, "aluminium": 0.1})
    other = rows({"gold": 0.05, "aluminium": 0.95})
    (mixed,) = inv_mod._shape_averaged(best, 0.6, [(0.4, other)])
    got = {r.name: r.probability for r in mixed}
    assert got == pytest.approx({"gold": 0.56, "aluminium": 0.44}, abs=1e-15)
    assert [r.fit for r in mixed] == ["fit-gold", "fit-aluminium"]
    assert [r.log_evidence for r in mixed] == [r.log_evidence for r in best[0]]
    # kept shapes below total probability 1 (a third shape dropped): renormalised
    (mixed,) = inv_mod._shape_averaged(best, 0.3, [(0.2, other)])
    assert sum(r.probability for r in mixed) == pytest.approx(1.0, abs=1e-15)


@pytest.mark.parametrize("tilt_deg, m", [(0.5, 300.0), (2.0, 50.0)])
def test_materials_the_data_cannot_tell_apart_are_not_ruled_out(tilt_deg, m):
    """A glossy box seen nearly face-on returns one normal-incidence glint: aluminium, gold
    and fused silica differ there by their reflectance, which the gain absorbs, and (to second
    order in the tilt) by their diattenuation. Their fits reach the same deviance (within 2),
    so none may be ruled out. Each material's refit stops somewhere of its own on the flat
    ridge of roughness against tilt and gain, where the point Laplace estimate varies by many
    units of log evidence (measured here before the carry: gold 11 below aluminium at equal
    deviance, fused silica -inf; probabilities 1, 0, 0); the evidence taken also at the best
    optimum carried over (``_carry_best_optimum``) gives each at least 0.05. The carried
    estimate is never below the material's own, and each is a Laplace estimate at a real
    point: its log evidence is at most the best's plus what the deviance and the Occam
    factor of that point allow (checked by recomputing it)."""
    import inversion._invert as inv_mod

    box = ppr.shapes.box(BOX)
    cand = Candidate("box", _toy(box), symmetry=box, bin_width_m=WIDTH)
    q = np.asarray(axis_angle_quat([1.0, 0.3, 0.0], math.radians(tilt_deg)))
    _, data = _observe(cand.model, q, m=m, gain=5.0, seed=1)
    mats = {k: complex(np.asarray(ppr.load_material(k).n)) for k in MATERIALS}
    near = quat_mul(axis_angle_quat([0.3, -0.5, 0.8], math.radians(6.0)), q)
    bank = inversion.screening_bank(
        [cand], mats, {"rough": 6.0, "glossy": 100.0}, attitudes=np.vstack([q, near])
    )
    cfg = dict(CONFIG, mcmc=None)
    rows = inversion.invert(data, [cand], config=cfg, bank=bank).materials[0]
    d_min = min(r.fit.cost for r in rows)
    assert all(r.fit.cost <= d_min + 2.0 for r in rows), [r.fit.cost for r in rows]
    probs = {r.name: r.probability for r in rows}
    assert min(probs.values()) >= 0.05, probs
    assert sum(probs.values()) == pytest.approx(1.0, abs=1e-12)
    refiner = inv_mod._Refiner(
        cand.model, inversion.PoissonCounts(), data, tuple(cfg["free"]), inv_mod._as_config(cfg)
    )
    for r in rows:
        own = inv_mod.log_evidence(r.fit)
        assert r.log_evidence >= own or not math.isfinite(own)
        if r.evidence_at is not None:  # the carried estimate, recomputed at its point
            src = next(x for x in rows if x.name == r.evidence_at)
            base = src.fit.params
            p = inv_mod._gain_profiled(refiner, inv_mod._with(base, n=np.array([r.n])))
            assert inv_mod.log_evidence(refiner.at(p)) == pytest.approx(r.log_evidence, abs=1e-6)
            # carried from the best of the materials' own optima
            assert src.evidence_at is None
            own = [x.log_evidence for x in rows if x.evidence_at is None]
            assert src.log_evidence >= max(own)
            # the row's fit is the carried point itself
            assert r.fit.params.gain == pytest.approx(float(np.asarray(p.gain)), rel=1e-12)


def test_decrement_predicts_the_deviance_a_fisher_scoring_step_removes(box_case):
    """``RefineResult.decrement`` (``g^T F^+ g``, g the score in the solver coordinates):
    ~0 at the maximum-likelihood fit, and off it the deviance drop to second order: at points
    0.5-2 sd (of the fit's own covariance) away along each coordinate, the decrement equals
    ``D(point) - D(fit)`` to within the third-order terms (10 % here), and it never
    exceeds what a polish from the point then actually removes by more than that."""
    import inversion._invert as inv_mod

    cands, truth, data, _ = box_case
    cfg = inv_mod._as_config(CONFIG)
    ref = inv_mod._Refiner(cands[0].model, inversion.PoissonCounts(), data, tuple(cfg.free), cfg)
    best = ref.polish(truth)
    assert best.success
    assert best.decrement < 1e-6 * max(1.0, best.cost), best.decrement
    sd = np.sqrt(np.diag(best.covariance_theta))
    checked = 0
    for i in range(len(best.theta)):
        if not np.isfinite(sd[i]) or sd[i] == 0:
            continue
        for k in (0.5, 2.0):
            th = np.array(best.theta, np.float64)
            th[i] += k * sd[i]
            phys = inv_mod._to_physical(best.parametrisation, jnp.asarray(th))
            at = ref.at(phys)
            rise = at.cost - best.cost
            assert at.decrement == pytest.approx(rise, rel=0.1, abs=1e-3), (i, k, rise)
            checked += 1
    assert checked >= 8


def test_log_evidence_occam_factor_is_exact_at_a_glint_condition_number(box_case):
    """``log_evidence``'s Occam factor ``1/2 log det(I + S F S)`` from the singular values of
    ``R S`` (``RefineResult.jacobian_r``) where ``F = J^T J`` has condition ~1e20 (a glint
    pins one tilt, another direction is unobservable): exact to 1e-9 against the closed form
    ``sum log(1 + sigma_i^2)`` of a Jacobian built with those singular values, to the
    round-off of the largest singular value. Formed as ``J^T J``, the small eigenvalues are
    round-off of the largest (~1e4 here) and the estimate is off by units."""
    import dataclasses

    import inversion._invert as inv_mod

    cands, truth, data, _ = box_case
    cfg = inv_mod._as_config(CONFIG)
    ref = inv_mod._Refiner(cands[0].model, inversion.PoissonCounts(), data, tuple(cfg.free), cfg)
    fit = ref.polish(truth)
    s = inv_mod.prior_scales(fit.parametrisation, None)
    p = len(s)
    rng = np.random.default_rng(7)
    u, _ = np.linalg.qr(rng.normal(size=(200, p)))
    v, _ = np.linalg.qr(rng.normal(size=(p, p)))
    sig = np.array([1e10, 3.0, 0.5, 1e-3, 0.0, 2.0, 7.0][:p])
    jac = (u * sig) @ v.T / s[None, :]  # J S = U diag(sig) V^T
    exact = -0.5 * fit.cost - 0.5 * float(np.sum(np.log1p(sig**2)))
    f2 = dataclasses.replace(fit, fisher_theta=jac.T @ jac, jacobian_r=np.linalg.qr(jac, mode="r"))
    # to round-off of the largest singular value (1e-16 x 1e10) in the others
    assert inv_mod.log_evidence(f2) == pytest.approx(exact, rel=0.0, abs=1e-6)
    f_only = dataclasses.replace(f2, jacobian_r=None)  # the eigenvalues of I + S J^T J S
    assert abs(inv_mod.log_evidence(f_only) - exact) > 1.0  # measured: 7.3 units off
    # a fit's own R factor gives its own Fisher matrix's determinant (well conditioned here)
    f3 = dataclasses.replace(fit, jacobian_r=None)
    assert inv_mod.log_evidence(fit) == pytest.approx(inv_mod.log_evidence(f3), abs=1e-8)
