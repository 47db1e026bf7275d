"""Weighted-inner-product classifier: exactness at grid points, invariances, FFT against a
direct reference, low-rank certificate, weight designs, bad input, evaluation report."""

import json
import math

import numpy as np
import pytest

from inversion._classifier import (
    ATTRIBUTES,
    WEIGHT_KINDS,
    attitude_error_deg,
    classify,
    design_weights,
    prepare,
    score_pair,
)
from inversion._database import bank_in_memory, spec_from_dict
from inversion._grid import symmetry_group
from inversion._noise import NoiseModel, Observation, observe, shift_profile
from ppr.geometry import quat_multiply_host

SPEC = {
    "name": "clf",
    "shapes": [
        {"name": "cube", "symmetry": "octahedral"},
        {"name": "box3u", "symmetry": "dihedral:4"},
        {"name": "cylinder", "symmetry": "dihedral:12"},
    ],
    "materials": ["aluminium", "white_paint", "silica"],
    "finishes": {"polished": 3000.0, "brushed": 100.0, "matte": 5.0},
    "grid": {"kind": "hopf", "size": 1},
    "sensor": {"channels": "full", "n_bins": 48, "bin_width_m": 0.01},
    "chunk_rows": 256,
}


@pytest.fixture(scope="module")
def bank():
    return bank_in_memory(spec_from_dict(SPEC), batch=256)


@pytest.fixture(scope="module")
def exact(bank):
    return prepare(bank, design_weights(bank, "fisher", "shape"), chunk=512)


def test_noise_free_grid_points_exact(bank, exact):
    rng = np.random.default_rng(0)
    rows = rng.choice(len(bank), 40, replace=False)
    shifts = rng.integers(-4, 5, len(rows))
    gains = 10 ** rng.uniform(-3, 3, len(rows))
    x = gains[:, None, None] * np.asarray(
        shift_profile(bank.signatures[rows], shifts[:, None].astype(np.float32))
    )
    res = classify(exact, x, k=3)
    # score 1 at the true row (float32 spectra: 2e-5), right integer shift
    np.testing.assert_allclose(res.score[:, 0], 1.0, atol=2e-5)
    # another row ranks first only in a tie: the true row is among the 3 best, with the best
    # score to float32 rounding (measured gap <= 1.8e-7). Symmetric attitudes, and one cube /
    # 3U box pair, render the same signature up to the rounding of the facet sums: 4e-7 of the
    # peak with the default compilation, 2e-5 compiled unoptimized as in the test suite
    # (tests/compile_level.py), so comparing the signatures themselves would be fragile.
    hit = res.index == rows[:, None]
    assert np.all(hit.any(axis=1))
    true_score = np.max(np.where(hit, res.score, -np.inf), axis=1)
    np.testing.assert_allclose(true_score, res.score[:, 0], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(res.shift[:, 0], shifts)
    assert np.all(res.certified)


def test_invariant_to_gain_and_offset(bank, exact):
    y = bank.signatures[17]
    base = classify(exact, y, k=5)
    moved = classify(exact, 123.4 * np.asarray(shift_profile(y, 3.0)), k=5)
    np.testing.assert_array_equal(base.index, moved.index)
    # float32 FFT round-off only (1e-5)
    np.testing.assert_allclose(base.score, moved.score, atol=1e-5)
    np.testing.assert_array_equal(moved.shift[:, 0] - base.shift[:, 0], [3])


def test_fft_scores_match_direct_reference(bank):
    rng = np.random.default_rng(1)
    w = rng.uniform(0.1, 2.0, (bank.n_channels, bank.n_bins)).astype(np.float32)
    prep = prepare(bank, w, chunk=512)
    x = rng.random((bank.n_channels, bank.n_bins)) * (bank.signatures[5] > 1e-4)
    res = classify(prep, x, k=4)
    for i, s, lag in zip(res.index[0], res.score[0], res.shift[0], strict=True):
        direct = [
            score_pair(x, bank.signatures[i], w, k) for k in range(-(bank.n_bins - 1), bank.n_bins)
        ]
        # FFT in float32 against float64 direct sums: 1e-5
        assert s == pytest.approx(max(direct), abs=1e-5)
        assert s == pytest.approx(score_pair(x, bank.signatures[i], w, int(lag)), abs=1e-5)
    # the best template really is the best over the whole bank (brute force on all rows)
    brute = [
        max(score_pair(x, y, w, k) for k in range(-6, 7))
        for y in bank.signatures[:: max(1, len(bank) // 60)]
    ]
    assert res.score[0, 0] >= max(brute) - 1e-5


def test_low_rank_matches_exact_on_noisy_observations(bank, exact):
    lowrank = prepare(bank, exact.weights, chunk=512, rank=96)
    noise = NoiseModel(
        snr=100.0, speckle_cells=20.0, max_offset_bins=3.0, gain_min=0.5, gain_max=2.0
    )
    sensor = bank.sensor
    obs = [
        observe(bank.signatures[r].astype(np.float64), noise, seed=int(r), sensor=sensor)
        for r in (3, 50, 200)
    ]
    a = classify(exact, obs, k=3)
    b = classify(lowrank, obs, k=3, n_candidates=64)
    np.testing.assert_array_equal(a.index[:, 0], b.index[:, 0])
    np.testing.assert_allclose(a.score, b.score, atol=1e-5)  # certified or exhaustive: exact
    assert b.certified.dtype == bool


def test_weight_designs(bank):
    for kind in WEIGHT_KINDS:
        for att in ATTRIBUTES:
            w = design_weights(bank, kind, att)
            assert w.shape == (bank.n_channels, bank.n_bins) and np.all(w > 0)
            assert w.mean() == pytest.approx(1.0, rel=0.01)
    # Fisher ratio against a direct per-feature computation on one feature
    w = design_weights(bank, "fisher", "material", floor=0.0, eps_rel=0.0)
    x = bank.signatures.reshape(len(bank), -1).astype(np.float64)
    lab = bank.material_id
    j = int(np.argmax(x.var(0)))
    mu = x[:, j].mean()
    between = sum((lab == c).sum() * (x[lab == c, j].mean() - mu) ** 2 for c in np.unique(lab))
    within = sum(((x[lab == c, j] - x[lab == c, j].mean()) ** 2).sum() for c in np.unique(lab))
    ratio = (between / within) / np.mean(w.ravel() * 0 + 1)
    full = w.ravel()
    # the design is scaled to mean 1: compare ratios of two features instead
    k = int(np.argsort(x.var(0))[-2])
    mu_k = x[:, k].mean()
    b_k = sum((lab == c).sum() * (x[lab == c, k].mean() - mu_k) ** 2 for c in np.unique(lab))
    w_k = sum(((x[lab == c, k] - x[lab == c, k].mean()) ** 2).sum() for c in np.unique(lab))
    assert full[j] / full[k] == pytest.approx(ratio / (b_k / w_k), rel=1e-5)


def test_attitude_error_modulo_symmetry():
    g = symmetry_group("octahedral")
    q = np.array([0.9, 0.1, -0.3, 0.2])
    q /= np.linalg.norm(q)
    equivalent = quat_multiply_host(q, g[7])
    assert attitude_error_deg(q, equivalent, "octahedral")[0] == pytest.approx(0.0, abs=1e-4)
    assert attitude_error_deg(q, equivalent, "none")[0] > 10


def test_bad_input(bank, exact):
    other = Observation(
        data=bank.signatures[0], sensor=json.dumps({"model": "other", "n_bins": 48})
    )
    with pytest.raises(ValueError, match="other sensor settings"):
        classify(exact, other)
    with pytest.raises(ValueError, match="n_bins=40"):
        classify(exact, np.ones((bank.n_channels, 40)))
    with pytest.raises(ValueError, match="channels"):
        classify(exact, np.ones((3, bank.n_bins)))
    with pytest.raises(ValueError, match="non-finite"):
        classify(exact, np.full((bank.n_channels, bank.n_bins), np.nan))
    with pytest.raises(ValueError, match="max_shift"):
        classify(exact, bank.signatures[0], max_shift=100)
    empty = type(bank)(**{**bank.__dict__, "signatures": bank.signatures[:0]})
    with pytest.raises(ValueError, match="empty"):
        prepare(empty)
    with pytest.raises(ValueError, match="weights have shape"):
        prepare(bank, np.ones((2, 2)))


def test_evaluate_report_smoke(tmp_path):
    from inversion._report import evaluate

    spec = spec_from_dict(dict(SPEC, shapes=SPEC["shapes"][:2], materials=SPEC["materials"][:2]))
    res = evaluate(
        spec,
        tmp_path,
        snrs=(1e4,),
        grid_sizes=(1,),
        n_obs=6,
        weight_kinds=("uniform", "fisher"),
        seed=3,
        plots=True,
    )
    for name in (
        "report.json",
        "report.md",
        "accuracy_vs_snr.png",
        "attitude_vs_resolution.png",
        "confusion_shape.png",
        "confusion_material.png",
        "confusion_finish.png",
    ):
        assert (tmp_path / name).stat().st_size > 0, name
    data = json.loads((tmp_path / "report.json").read_text())
    assert set(data["best_weight"]) == set(ATTRIBUTES)
    assert np.asarray(data["confusion"]["shape"]).sum() == 6
    acc = data["by_weight"]["fisher"]["shape"]["10000.0"]["shape_acc"]
    assert 0.0 <= acc <= 1.0 and res["timing"]["n_templates"] > 0


def test_ppr_adapter_matches_simulate():
    """The database's ppr signature function equals ppr.simulate projected on the channels."""
    import jax.numpy as jnp

    import ppr
    from inversion._noise import MeasurementModel, measure
    from inversion._ppr_adapter import PprSignatures
    from ppr.pulse._pulse import lambertian_mueller

    mm = MeasurementModel.preset("stokes")
    fn = PprSignatures(
        ["cubesat"],
        ["aluminium"],
        [300.0],
        mm,
        n_bins=48,
        bin_width_m=0.01,
        brdf=lambertian_mueller,
        dtype=jnp.float64,
    )
    q = np.array([[0.9, 0.2, -0.3, 0.1], [0.5, 0.5, 0.5, 0.5]])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    sig = np.asarray(
        fn(
            {
                "shape_id": np.zeros(2, np.int32),
                "material_id": np.zeros(2, np.int32),
                "finish_id": np.zeros(2, np.int32),
                "quat": q,
            }
        )
    )
    mat = ppr.load_material("aluminium", 532e-9, dtype=jnp.float64)
    for i in range(2):
        scene = ppr.Scene(
            fn.meshes[0],
            (mat,),
            ppr.Pose(q[i]),
            fn.sensor_model,
            ppr.Pulse.gaussian(fn.pulse_fwhm_s),
            fn.bins,
            vis_samples=4,
        )
        prof = ppr.simulate(scene, brdf=lambertian_mueller, dtype=jnp.float64)
        ref = np.asarray(measure(mm, jnp.asarray(prof.data)))
        # same kernel, same visibility samples; float64 round-off only
        np.testing.assert_allclose(sig[i], np.maximum(ref, 0.0), rtol=1e-9, atol=1e-12 * ref.max())


def test_candidates_cover_every_shape(bank, exact):
    """``Classification.candidates``: the top k plus each shape's best ``per_shape`` columns,
    in rank order and without repeats; a classification cut too short to hold a shape's
    candidates is refused rather than silently missing that shape."""
    x = bank.signatures[int(np.flatnonzero(bank.shape_id == 0)[3])]
    full = classify(exact, x, k=len(bank))
    sid = bank.shape_id[full.index[0]]
    cols = full.candidates(bank, k=2, per_shape=2)
    assert list(cols) == sorted(set(cols)) and {0, 1} <= set(cols)
    for s in np.unique(bank.shape_id):
        first = np.flatnonzero(sid == s)[:2]
        assert set(first) <= set(cols)  # each shape's two best ranks are in
    # nothing else: the union of top-2 and the per-shape ranks
    want = {0, 1} | {int(c) for s in np.unique(bank.shape_id) for c in np.flatnonzero(sid == s)[:2]}
    assert set(cols) == want
    assert list(full.candidates(bank, k=0, per_shape=0)) == []
    # a truncated classification that misses a shape: clear error naming it
    short = classify(exact, x, k=1)
    missing = sorted(set(np.unique(bank.shape_id)) - set(bank.shape_id[short.index[0]]))
    assert len(missing) == 2
    name = bank.names["shapes"][missing[0]]
    with pytest.raises(ValueError, match=f"shape '{name}'.*larger k"):
        short.candidates(bank, k=1, per_shape=1)
    with pytest.raises(ValueError, match="per_shape=-1"):
        full.candidates(bank, per_shape=-1)
    with pytest.raises(ValueError, match="obs=1"):
        full.candidates(bank, obs=1)


def test_line_of_sight_error_about_another_sensor_direction():
    """With the sensor along another world direction ``k`` (``los=k``), a turn of the
    attitude about ``k`` keeps the body-frame line of sight (error 0) and a tilt away from it
    by 30 deg shows as 30 deg; the default ``+z`` is ``los=(0, 0, 1)``."""
    from inversion._classifier import line_of_sight_error_deg
    from ppr.geometry import quat_from_axis_angle

    def quat_mul(a, b):
        return quat_multiply_host(np.asarray(a), np.asarray(b))

    rng = np.random.default_rng(7)
    q = rng.normal(size=(4, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    k = np.array([0.6, -0.0, 0.8])
    turn = np.stack([quat_from_axis_angle(k, a) for a in (0.3, 1.1, 2.0, -2.5)])
    tilt = quat_from_axis_angle(np.cross(k, [0.0, 1.0, 0.0]), math.radians(30.0))
    for i in range(4):
        rolled = quat_mul(turn[i], q[i])  # world-side turn about k
        assert line_of_sight_error_deg(q[i], rolled, los=k)[0] < 1e-5
        assert line_of_sight_error_deg(q[i], rolled)[0] > 1.0  # about +z it is a tilt
        np.testing.assert_allclose(
            line_of_sight_error_deg(q[i], quat_mul(tilt, q[i]), los=k), 30.0, atol=1e-6
        )
    np.testing.assert_allclose(
        line_of_sight_error_deg(q, q[::-1], los=(0.0, 0.0, 1.0)),
        line_of_sight_error_deg(q, q[::-1]),
        atol=1e-9,
    )


def test_half_turn_about_line_of_sight_in_attitude_errors():
    """``los_half_turn`` is ``C2(z) q``: an involution (up to sign), 180 deg from ``q``, with
    the same body-frame line of sight; ``attitude_error_deg(half_turn=True)`` counts it as
    the same attitude, ``line_of_sight_error_deg`` never sees it."""
    from inversion import los_half_turn
    from inversion._classifier import line_of_sight_error_deg
    from ppr.geometry import quat_angle_deg

    rng = np.random.default_rng(4)
    q = rng.normal(size=(5, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    h = los_half_turn(q)
    np.testing.assert_allclose(np.abs(np.sum(los_half_turn(h) * q, axis=1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(quat_angle_deg(q, h), 180.0, atol=1e-6)
    np.testing.assert_allclose(attitude_error_deg(q, h, "none"), 180.0, atol=1e-6)
    np.testing.assert_allclose(attitude_error_deg(q, h, "none", half_turn=True), 0.0, atol=1e-5)
    np.testing.assert_allclose(line_of_sight_error_deg(q, h, "none"), 0.0, atol=1e-5)
    # with the mirror too: the half turn of the mirror image is equivalent as well
    from inversion import mirror_attitude

    hm = los_half_turn(mirror_attitude(q, [0.0, 0.0, 1.0]))
    assert np.all(attitude_error_deg(q, hm, "dihedral:4", mirror=True) > 1.0)
    np.testing.assert_allclose(
        attitude_error_deg(q, hm, "dihedral:4", mirror=True, half_turn=True), 0.0, atol=1e-5
    )
    with pytest.raises(ValueError, match="unit 3-vector"):
        los_half_turn(q, los=(0.0, 0.0, 2.0))


def test_flags_an_observation_that_no_template_fits():
    """A bank of one toy shape on a 19 deg attitude grid (Hopf, 1944 templates): its
    observations at random attitudes (off the grid), sub-bin offsets and 1e4 or 1e6
    photo-counts fit within the bank's resolution; a shape the bank lacks (another, longer
    point set) is flagged (5 of 6 attitudes; at the sixth it mimics the bank within a grid
    spacing). Without the resolution allowance the bank's own shape at 1e6 counts would be
    flagged: there the grid error, not the noise, dominates."""
    from inversion._refine import PoissonCounts
    from inversion._synthetic import point_lobe_bank, point_lobe_signatures

    bank, shape_in, shape_out = point_lobe_bank()
    rng = np.random.default_rng(0)
    prep = prepare(bank)
    q = rng.normal(size=(12, 4))
    y = np.concatenate(
        [point_lobe_signatures(*shape_in, q[:6]), point_lobe_signatures(*shape_out, q[6:])]
    )
    y = shift_profile(y, rng.uniform(-2, 2, (12, 1)))
    noise = PoissonCounts(background=1e-3)
    for counts in (1e4, 1e6):
        x = rng.poisson(counts * y + 1e-3).astype(np.float64)
        res = classify(prep, x, k=3, noise=noise)
        assert not res.no_template_fits[:6].any(), [f.summary() for f in res.fit[:6]]
        assert res.no_template_fits[6:].sum() >= 5, [f.summary() for f in res.fit[6:]]
        assert all(f.allowance > 0 and f.n_params == 2 for f in res.fit)
    strict = classify(prep, x, k=3, noise=noise, resolution_scale=0.0)
    assert strict.no_template_fits[:6].all(), [f.summary() for f in strict.fit[:6]]
    assert classify(prep, x, k=3).fit is None  # no noise model, no verdict


def test_empty_frame_is_flagged_and_leaves_the_batch_unchanged(bank, exact):
    """A frame with no positive value holds no return (every channel is an intensity):
    flagged, in place, and the other observations' candidates are those they get alone."""
    y = np.asarray(bank.signatures[[5, 40]], np.float64) * 1e3
    batch = np.stack([y[0], np.zeros_like(y[0]), y[1], -np.abs(y[1])])
    res = classify(exact, batch, k=3)
    np.testing.assert_array_equal(res.no_signal, [False, True, False, True])
    alone = classify(exact, y, k=3)
    np.testing.assert_array_equal(res.index[[0, 2]], alone.index)
    np.testing.assert_allclose(res.score[[0, 2]], alone.score, atol=1e-6)
    assert np.all(np.isfinite(res.score))  # the empty frames score 0, not NaN
