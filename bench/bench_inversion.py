"""Error against run time of the inversion chain: classifier, + refiner, + MCMC.

Held-out simulated observations (ppr pulse synthesis, PSG/PSA "full" 16 channels, Poisson
noise at a stated SNR, unknown range offset and gain) of several shapes, materials and
finishes at random attitudes (off the database grid). For each observation:

1. classifier only: top-k of the weighted-inner-product classifier against a template bank
   built with the same forward model (Hopf attitude grid, symmetry-reduced);
2. + refiner: Levenberg-Marquardt (optimistix) from the top-k candidates and the best
   candidate of every shape (``Classification.candidates``): every start screened by one
   loose round, the best of each competitive shape polished, shape chosen by the lowest
   deviance, material = nearest library entry to the refined index;
3. + MCMC: emcee around the best refined optimum (short chain), posterior medians, credible
   intervals (coverage of 68% and 95% intervals over the set).

Reports attitude error (deg, modulo the shape's symmetry), relative roughness error, index
error, shape/material accuracy and wall time per observation of each stage (compile time
excluded after a warm-up observation, and reported separately). Writes
``bench/results/inversion_summary.md``, ``inversion_results.json`` and
``inversion_error_vs_time.png``.

Run: ``.venv/bin/python bench/bench_inversion.py [--quick]`` (x64 on; ~5 min on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
# script-level persistent compilation cache: re-runs skip the (minutes-long, on a loaded
# 2-core machine) compilation of the simulator's Jacobian inside the solvers
jax.config.update("jax_compilation_cache_dir", "/tmp/ppr_bench_jax_cache")
jax.config.update("jax_persistent_cache_min_compile_time_secs", 2.0)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ppr  # noqa: E402
from inversion._classifier import (  # noqa: E402
    attitude_error_deg,
    classify,
    line_of_sight_error_deg,
    prepare,
)
from inversion._database import TemplateBank  # noqa: E402
from inversion._grid import (  # noqa: E402
    AttitudeGrid,
    body_mirror_normal,
    los_half_turn,
    mirror_attitude,
    random_quaternions,
    symmetry_group,
)
from inversion._mcmc import ChainTooShortWarning, mcmc_config_from_dict, sample_posterior  # noqa: E402
from inversion._noise import MeasurementModel, NoiseModel, observe  # noqa: E402
from inversion._params import PhysicalParams  # noqa: E402
from inversion._refine import (  # noqa: E402
    PhysicalBounds,
    PoissonCounts,
    SimulatorModel,
    _pure,
    cramer_rao,
    mirror_check,
    refine,
    refine_bounded,
)
from ppr.geometry import quat_multiply  # noqa: E402

# Exact Poisson likelihood for the photo-counts (deviance residuals in the refiner, Poisson
# log-likelihood in the MCMC). Background 1e-3 counts per channel-bin (dark counts).
NOISE = PoissonCounts(background=1e-3)

OUT = Path(__file__).resolve().parent / "results"
# physical box (also the MCMC's uniform index prior); the gain (counts per m^2 sr^-1, the
# simulator returning m^2/sr per bin) is ~1e7-2e10 here, inside the default range
BOUNDS = PhysicalBounds()
NOTES = (
    "Notes: with a monostatic sensor and a single-bounce BRDF the returning microfacets face the "
    "sensor, the Fresnel factor is the normal-incidence scalar and the unknown gain absorbs it: "
    "materials are then indistinguishable in normalized signatures (only the depolarizing terms "
    "of the full BRDF or a bistatic geometry separate them). SNR = sqrt(total signal counts) "
    "(inversion._noise): SNR 30 is ~900 counts over all channels and bins."
)

SHAPES = {
    # name: (mesh factory, symmetry group of the mesh in its body frame)
    "cubesat1u": (lambda: ppr.shapes.cubesat(1), "octahedral"),
    "cubesat3u": (lambda: ppr.shapes.cubesat(3), "dihedral:4"),
    "cylinder": (lambda: ppr.shapes.cylinder(0.06, 0.25, sections=12), "dihedral:12"),
}
MATERIALS = {  # n at 532 nm, docs/physics.md#materials
    "aluminium": 0.94 + 6.42j,
    "gold": 0.54 + 2.23j,
    "silica": 1.461 + 0.0j,
}
FINISHES = {"matte": 8.0, "glossy": 80.0}
N_BINS = 64
BIN_WIDTH = 0.01  # m (67 ps)
PULSE_FWHM = 100e-12
CAPACITY = 64  # every mesh padded to the same capacity: one compilation for all shapes


def choose_brdf(kind="auto"):
    """ppr.mueller_brdf if it imports (``auto``), else / with ``glossy`` the simulator's
    polarizing stand-in (stated in the output)."""
    if kind == "glossy":
        from ppr.pulse import glossy_fresnel_mueller

        return glossy_fresnel_mueller, "glossy_fresnel_mueller (simulator stand-in, --brdf glossy)"
    try:
        from ppr.brdf import mueller_brdf

        return mueller_brdf, "ppr.mueller_brdf"
    except Exception as exc:  # noqa: BLE001
        from ppr.pulse import glossy_fresnel_mueller

        return (
            glossy_fresnel_mueller,
            f"glossy_fresnel_mueller (stand-in; mueller_brdf unavailable: {exc})",
        )


def make_models(brdf, prune=True):
    """The bench's forward models, one per shape (``prune``: :class:`SimulatorModel`'s facet
    pruning, on in the bench; ``bench/bench_prune.py`` measures it against off)."""
    sensor = ppr.Sensor.make()
    pulse = ppr.Pulse.gaussian(PULSE_FWHM)
    bins = ppr.RangeBins.centred(BIN_WIDTH, N_BINS)
    chm = MeasurementModel.preset("full").channel_matrix()
    models = {}
    for name, (factory, _sym) in SHAPES.items():
        mesh = factory()
        mats = tuple(ppr.Material(1.5, 10.0) for _ in mesh.parts)
        scene = ppr.Scene(mesh, mats, ppr.Pose([1.0, 0, 0, 0]), sensor, pulse, bins)
        models[name] = SimulatorModel(
            scene, chm, brdf=brdf, dense=True, capacity=CAPACITY, prune=prune
        )
    return models


@jax.jit
def _batch_expected(kernel, quats, m, n, vis):
    """Noise-free channel profiles for a batch of attitudes/materials (gain 1, no offset)."""
    return jax.vmap(lambda q, mm, nn, v: kernel.expected(_phys(q, mm, nn, 0.0, 1.0), v))(
        quats, m, n, vis
    )


def _phys(q, m, n, off, gain):
    return PhysicalParams(
        jnp.asarray(q, jnp.float64),
        jnp.atleast_1d(jnp.asarray(m, jnp.float64)),
        jnp.atleast_1d(jnp.asarray(n, jnp.complex128)),
        5e-6,
        off,
        gain,
    )


BANK_BATCH = 128
PER_SHAPE = 1  # best candidates of every shape refined (over the whole bank), besides top-k
SCREEN_TOL = 1e-3  # solver tolerance of the screening round
FIXED_INDEX = ("attitude", "m", "range_offset", "gain")  # the material-identifiability fits
POLISH_FACTOR, POLISH_ABS = 1.25, 25.0  # shapes polished: screened deviance <= 1.25 best + 25
NEG_CLIPPED: list = []  # largest negative channel value / max, per simulated observation


def _pad(x):
    """Pad the leading axis to BANK_BATCH by repeating the first row."""
    if len(x) == BANK_BATCH:
        return x
    return np.concatenate([x, np.repeat(x[:1], BANK_BATCH - len(x), axis=0)])


def build_bank(models, grid_size):
    """Template bank (normalized signatures) over shapes x grid attitudes x materials x finishes."""
    sigs, sid, aid, mid, fid, quats, res = [], [], [], [], [], [], []
    mat_names, fin_names = list(MATERIALS), list(FINISHES)
    for s, (name, model) in enumerate(models.items()):
        grid = AttitudeGrid("hopf", grid_size, SHAPES[name][1])
        res.append(grid.resolution_deg)
        vis = np.stack(
            [np.asarray(model.visibility(_phys(q, 1.0, 1.5, 0.0, 1.0))) for q in grid.quats]
        )
        for mi, mname in enumerate(mat_names):
            for fi, fname in enumerate(fin_names):
                g = len(grid.quats)
                outs = []
                for a in range(0, g, BANK_BATCH):  # fixed batch shape: one compilation
                    qb = _pad(grid.quats[a : a + BANK_BATCH])
                    vb = _pad(vis[a : a + BANK_BATCH])
                    o = _batch_expected(
                        _pure(model),
                        jnp.asarray(qb),
                        jnp.full(BANK_BATCH, FINISHES[fname]),
                        jnp.full(BANK_BATCH, MATERIALS[mname], jnp.complex128),
                        jnp.asarray(vb),
                    )
                    outs.append(np.asarray(o)[: min(BANK_BATCH, g - a)])
                out = np.concatenate(outs)
                out = out / np.maximum(out.sum(axis=(1, 2), keepdims=True), 1e-300)
                sigs.append(out.astype(np.float32))
                sid += [s] * g
                aid += list(range(g))
                mid += [mi] * g
                fid += [fi] * g
                quats.append(grid.quats)
    return TemplateBank(
        signatures=np.concatenate(sigs),
        shape_id=np.asarray(sid),
        attitude_id=np.asarray(aid),
        material_id=np.asarray(mid),
        finish_id=np.asarray(fid),
        quat=np.concatenate(quats),
        names={
            "shapes": list(models),
            "materials": mat_names,
            "finishes": fin_names,
            "finish_m": list(FINISHES.values()),
            "symmetry": [SHAPES[k][1] for k in models],
        },
        sensor="",
        resolution_deg=res,
    )


def nearest_material(n) -> int:
    """Index of the library material closest to ``n`` (distance in (n', n'') plane)."""
    cat = np.array(list(MATERIALS.values()))
    return int(np.argmin(np.abs(cat - complex(n))))


def chain_config(steps, moves="stretch", init_scale=0.5):
    """The MCMC benches' sampler: 24 walkers, ``steps`` steps (a third burned in), the
    starting ball at ``init_scale`` (default half) of the Laplace scale, the default priors."""
    return mcmc_config_from_dict(
        {
            "sampler": {
                "n_walkers": 24,
                "n_steps": steps,
                "burn_in": steps // 3,
                "init_scale": init_scale,
                "progress": False,
                "moves": moves,
            },
        }
    )


def z_scores(post, t_eq):
    """(truth - posterior median) / 68 % half-width per parameter, and the 68 % bounds."""
    lo, hi = post.interval(0.68).T
    return (post.truth_vector(t_eq) - post.median()) / np.maximum(0.5 * (hi - lo), 1e-300), lo, hi


def chain_row(case, variant, steps, dt, post, *rest):
    """A result row of the MCMC benches: case, variant, steps, seconds, the largest
    integrated autocorrelation time, the mean acceptance fraction, then ``rest``."""
    tau, acc = float(np.max(post.tau)), float(np.mean(post.acceptance_fraction))
    return (case, variant, steps, dt, tau, acc, *rest)


def truth_equivalents(q_true, sym):
    """Every attitude equivalent to ``q_true`` for a shape of symmetry ``sym``: its images
    ``q g`` under the body's rotations and, when the body has a mirror plane, those of its
    mirror image (``inversion.mirror_attitude``; same range profiles, Mueller ``D M D``),
    and the half turns of all these about the line of sight (``inversion.los_half_turn``:
    identical monostatic data)."""
    g = symmetry_group(sym)
    heads = [np.asarray(q_true, float)]
    normal = body_mirror_normal(sym)
    if normal is not None:
        heads.append(mirror_attitude(q_true, normal))
    out = np.concatenate(
        [
            np.asarray(quat_multiply(jnp.asarray(np.broadcast_to(h, g.shape)), jnp.asarray(g)))
            for h in heads
        ]
    )
    return np.concatenate([out, los_half_turn(out)])


def truth_in_symmetry(q_true, q_est, sym):
    """The equivalent of ``q_true`` (:func:`truth_equivalents`) closest to ``q_est``."""
    cands = truth_equivalents(q_true, sym)
    d = np.abs(cands @ np.asarray(q_est, float))
    return cands[int(np.argmax(d))]


def truth_for_posterior(post, truth, sym):
    """The truth as scored against a posterior: of its equivalents (:func:`truth_equivalents`,
    all giving the same data), the one nearest the posterior in the posterior's own metric
    (Mahalanobis distance of the attitude components from the median, with the samples'
    covariance). The geodesically nearest one (:func:`truth_in_symmetry`) is the wrong choice
    when the roll is unconstrained: a degrees-wide line-of-sight mismatch is then cheaper
    than a tens-of-degrees roll difference, which the posterior does not care about."""
    labels = post.labels
    i = labels.index("rot_x [deg]")
    att = post.samples[:, i : i + 3]
    mu = np.median(att, axis=0)
    prec = np.linalg.pinv(np.cov(att.T))
    best, best_d = None, np.inf
    for q in truth_equivalents(np.asarray(truth.quaternion), sym):
        t = PhysicalParams(q, truth.m, truth.n, truth.corr_length, truth.range_offset, truth.gain)
        x = post.truth_vector(t)[i : i + 3] - mu
        d = float(x @ prec @ x)
        if d < best_d:
            best, best_d = t, d
    return best


def make_observations(models, n_obs, snrs, seed):
    """``n_obs`` held-out truths (shape cycling, random material, finish, off-grid roughness,
    attitude), each observed at every SNR: the rows of different SNRs are paired (same
    truths, same range offset), so error against SNR is not confounded with the draw."""
    rng = np.random.default_rng(seed)
    names = list(models)
    qs = np.asarray(random_quaternions(jax.random.key(seed), n_obs))
    truths = []
    for j in range(n_obs):
        mname = list(MATERIALS)[rng.integers(len(MATERIALS))]
        fname = list(FINISHES)[rng.integers(len(FINISHES))]
        m_true = FINISHES[fname] * math.exp(rng.uniform(-0.3, 0.3))  # off the finish grid
        off = rng.uniform(-3.0, 3.0) * BIN_WIDTH  # unknown range offset, up to 3 bins
        truths.append((names[j % len(names)], mname, fname, m_true, qs[j], off))
    obs = []
    for snr in snrs:
        for j, (shape, mname, fname, m_true, q, off_true) in enumerate(truths):
            model = models[shape]
            # the offset goes into the simulation itself (shifted pulse, then binned), as in
            # the fitted model: NoiseModel's offset rebins the binned profile instead, a
            # smoothing by up to a bin that biased the attitude at high SNR (4 deg at SNR 1000)
            phys = _phys(q, m_true, MATERIALS[mname], off_true, 1.0)
            x = np.asarray(model.expected(phys, model.prepare(phys)))
            # bin-integrated CDF differences can be -1e-17-ish (round-off); observe() wants >= 0
            NEG_CLIPPED.append(float(-x.min() / max(x.max(), 1e-300)) if x.min() < 0 else 0.0)
            x = np.maximum(x, 0.0)
            noise = NoiseModel(snr=float(snr))
            o = observe(x, noise, seed=1000 + j)
            gain_true = float(o.truth["gain"]) * snr**2 / x.sum()
            obs.append(
                dict(
                    data=np.asarray(o.data, np.float64),
                    shape=shape,
                    material=mname,
                    finish=fname,
                    snr=snr,
                    truth=_phys(q, m_true, MATERIALS[mname], off_true, gain_true),
                )
            )
    return obs


def candidate_start(bank, row, shift_bins, data, model):
    q = bank.quat[row]
    m = bank.names["finish_m"][bank.finish_id[row]]
    n = list(MATERIALS.values())[bank.material_id[row]]
    off = float(shift_bins) * BIN_WIDTH
    p = PhysicalParams(q, [m], [n], range_offset=off, gain=1.0)
    x = np.asarray(model.expected(p, model.prepare(p)))
    gain = float(data.sum() / max(x.sum(), 1e-300))
    return PhysicalParams(q, [m], [n], range_offset=off, gain=max(gain, 1e-12))


def _att_errors(truth, q_est, sym, shape_ok):
    """Attitude and line-of-sight errors (deg, modulo the symmetry); NaN for a wrong shape."""
    if not shape_ok:
        return dict(
            att_deg=float("nan"),
            att_sym_deg=float("nan"),
            los_deg=float("nan"),
            los_mirror_deg=float("nan"),
        )
    return dict(
        att_deg=float(attitude_error_deg(truth.quaternion, q_est, sym)[0]),
        # modulo what no monostatic measurement can tell: the half turn about the line of
        # sight (exact for any body) and the mirror image (for bodies with a mirror plane)
        att_sym_deg=float(
            attitude_error_deg(
                truth.quaternion,
                q_est,
                sym,
                mirror=body_mirror_normal(sym) is not None,
                half_turn=True,
            )[0]
        ),
        los_deg=float(line_of_sight_error_deg(truth.quaternion, q_est, sym)[0]),
        # modulo the mirror image too: the part of the error the data can tell at all when the
        # off-block Mueller elements are below the noise (inversion.mirror_check)
        los_mirror_deg=float(line_of_sight_error_deg(truth.quaternion, q_est, sym, mirror=True)[0]),
    )


def _mirror_record(chk):
    return dict(
        mirror_delta=chk.delta_deviance,
        mirror_sep_deg=chk.separation_deg,
        mirror_prob=chk.mirror_probability,
        mirror_ambiguous=chk.ambiguous(),
    )


def _fit_errors(fit, truth, o, sym, shape_ok):
    """Errors of a refined fit against the truth (attitude/LOS, m, n, material), its solver
    verdict and its deviance."""
    return dict(
        success=fit.success,
        shape_ok=shape_ok,
        material_ok=list(MATERIALS)[nearest_material(fit.params.n[0])] == o["material"],
        **_att_errors(truth, np.asarray(fit.params.quaternion), sym, shape_ok),
        m_rel=abs(float(fit.params.m[0]) / float(truth.m[0]) - 1),
        n_err=abs(complex(fit.params.n[0]) - complex(truth.n[0])),
        cost=fit.cost,
    )


def crb_at_truth(model, truth):
    """Cramer-Rao bounds at the truth (Poisson counts, all parameters free): what no estimator
    can beat. Attitude as world rotation components: x, y tilt the line of sight in the body
    frame (LOS bound), z is the roll about it (seen through the polarization alone)."""
    crb = cramer_rao(model, truth, NOISE)
    c = crb.covariance
    i = crb.labels.index("rot_x [deg]")
    return dict(
        att_deg=float(crb.attitude_sigma_deg),
        los_deg=float(np.sqrt(c[i, i] + c[i + 1, i + 1])),
        roll_deg=float(np.sqrt(c[i + 2, i + 2])),
        m_rel=float(crb.sigma[crb.labels.index("m[0]")] / float(truth.m[0])),
        n_re=float(crb.sigma[crb.labels.index("n_re[0]")]),
    )


def run_one(o, models, bank, prep, k, mcmc_cfg, do_mcmc):
    data = o["data"]
    res = {"snr": o["snr"], "shape": o["shape"], "material": o["material"]}
    truth = o["truth"]
    res["crb"] = crb_at_truth(models[o["shape"]], truth)
    sym_of = {name: SHAPES[name][1] for name in models}
    names = list(models)
    # 1. classifier
    t0 = time.perf_counter()
    # top-k overall, plus the best candidate(s) of every shape over the whole bank
    # (Classification.candidates): the classifier's rank is not a likelihood, and a cube's
    # signature, which changes fast with attitude, ranked below 150-500 templates of other
    # shapes while fitting far better once refined. The likelihood chooses the shape.
    cl = classify(prep, data.astype(np.float32), k=len(bank))
    t_cls = time.perf_counter() - t0
    pick = cl.candidates(bank, k=k, per_shape=PER_SHAPE)
    rows = cl.index[0][pick]
    shifts = cl.shift_refined[0][pick]
    best = rows[0]
    res["cls"] = dict(
        time=t_cls,
        shape_ok=names[bank.shape_id[best]] == o["shape"],
        material_ok=list(MATERIALS)[bank.material_id[best]] == o["material"],
        **_att_errors(
            truth, bank.quat[best], sym_of[o["shape"]], names[bank.shape_id[best]] == o["shape"]
        ),
        m_rel=abs(bank.names["finish_m"][bank.finish_id[best]] / float(truth.m[0]) - 1),
        n_err=abs(list(MATERIALS.values())[bank.material_id[best]] - complex(truth.n[0])),
    )
    # 2. refiner. Screening: one loose round (tolerance SCREEN_TOL, the compiled solver's
    # tolerances are traced) from every start of every candidate shape. Polishing: the best
    # screened start of each shape whose screened deviance is within POLISH_FACTOR x best +
    # POLISH_ABS, refined to the full tolerance (the others cannot catch up: polishing lowered
    # the deviance by 0.3-8 % in the diagnostic runs, except a fit that was still descending
    # at 40000, far above).
    t0 = time.perf_counter()
    screened = {}
    for s in sorted(set(bank.shape_id[rows].tolist())):
        model = models[names[s]]
        starts = [
            candidate_start(bank, r, shifts[j], data, model)
            for j, r in enumerate(rows)
            if bank.shape_id[r] == s
        ]
        screened[s] = refine(
            model,
            data,
            starts,
            noise=NOISE,
            max_steps=100,
            rounds=1,
            rtol=SCREEN_TOL,
            atol=SCREEN_TOL,
        )
    best_screen = min(f.cost for f in screened.values())
    fits = {}
    for s, scr in screened.items():
        if not scr.cost <= POLISH_FACTOR * best_screen + POLISH_ABS:
            continue
        model = models[names[s]]
        fits[s] = refine(model, data, [scr.params], noise=NOISE, max_steps=100, rounds=2)
        n0 = complex(fits[s].params.n[0])
        if not (
            BOUNDS.n_re[0] <= n0.real <= BOUNDS.n_re[1]
            and BOUNDS.n_im[0] <= n0.imag <= BOUNDS.n_im[1]
        ):
            # the unbounded LM left the physical index range (the index trades against the
            # unknown gain): redo this shape with the box-bounded L-BFGS-B refiner
            fits[s] = refine_bounded(
                model, data, [scr.starts[0].start], noise=NOISE, bounds=BOUNDS, rounds=3
            )
            res["bounded_fallback"] = res.get("bounded_fallback", 0) + 1
    # the shape with the highest likelihood (lowest deviance; same parameter count for every
    # shape). Not "successful first": a fit that stopped at max_steps still lowered the cost
    # monotonically from its start, and preferring converged fits picked worse shapes.
    s_best = min(fits, key=lambda s: fits[s].cost if np.isfinite(fits[s].cost) else np.inf)
    fit = fits[s_best]
    # the mirror image of the chosen fit: a second mode the local search and the CRB cannot
    # see (same range profiles, only the off-block Mueller elements differ); keep the better
    chk = mirror_check(
        models[names[s_best]],
        data,
        fit,
        sym_of[names[s_best]],
        noise=NOISE,
        max_steps=100,
        rounds=2,
        bounds=BOUNDS,
    )
    fit = chk.best
    t_ref = time.perf_counter() - t0
    shape_ok = names[s_best] == o["shape"]
    res["ref"] = dict(
        time=t_cls + t_ref,
        **_fit_errors(fit, truth, o, sym_of[o["shape"]], shape_ok),
        att_sigma_deg=fit.attitude_sigma_deg,
        reduced_chi2=fit.reduced_chi2,
        n_shapes_refined=len(fits),
        n_shapes_screened=len(screened),
        mirror_swapped=bool(chk.delta_deviance < 0),
        **_mirror_record(chk),
    )
    # diagnostic: the same refiner started at the truth. Its error is what the likelihood and
    # the local solver give without any search; the gap to "ref" is the search's failure
    # (grid resolution, local optima), the gap to "crb" the estimator's inefficiency.
    t0 = time.perf_counter()
    fo = refine(models[o["shape"]], data, [truth], noise=NOISE, max_steps=100, rounds=3)
    t_or = time.perf_counter() - t0
    # does the data itself tell the truth from its mirror image? (no search involved)
    chk_o = mirror_check(
        models[o["shape"]], data, fo, sym_of[o["shape"]], noise=NOISE, max_steps=100, rounds=2
    )
    res["oracle"] = dict(
        time=t_or, **_fit_errors(fo, truth, o, sym_of[o["shape"]], True), **_mirror_record(chk_o)
    )
    # can the data tell the library materials apart at all (no search)? The truth-started fit
    # refined with the index fixed at each library value: the deviance gap from the true
    # material's fit to the best other material's (> 4: likelihood ratio > e^2)
    dev = {}
    for mname, nval in MATERIALS.items():
        p = fo.params
        st = PhysicalParams(p.quaternion, p.m, [nval], p.corr_length, p.range_offset, p.gain)
        dev[mname] = refine(
            models[o["shape"]], data, [st], noise=NOISE, free=FIXED_INDEX, max_steps=100, rounds=2
        ).cost
    res["oracle"]["material_gap"] = (
        min(v for k, v in dev.items() if k != o["material"]) - dev[o["material"]]
    )
    if not do_mcmc:
        return res
    # 3. MCMC around the refined optimum of the chosen shape
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ChainTooShortWarning)
        try:
            post = sample_posterior(models[names[s_best]], data, fit, config=mcmc_cfg, noise=NOISE)
        except ValueError as err:  # e.g. the refined optimum outside the prior's support
            res["mcmc_refused"] = str(err)
            return res
    t_mc = time.perf_counter() - t0
    med = post.median()
    par = post.parametrisation
    labels = post.labels
    # posterior-median attitude: rotation vector (deg) about the refined optimum
    rv = np.radians(med[:3])
    from ppr.geometry import quat_from_rotvec

    q_med = np.asarray(
        quat_multiply(
            quat_from_rotvec(jnp.asarray(rv)), jnp.asarray(par.reference.unit_quaternion())
        )
    )
    m_med = med[labels.index("m[0]")]
    n_med = med[labels.index("n_re[0]")] + 1j * med[labels.index("n_im[0]")]
    cover = {}
    if shape_ok:
        t_eq = truth_for_posterior(post, truth, sym_of[o["shape"]])
        tv = post.truth_vector(t_eq)
        # a truth on a parameter's hard boundary (n'' = 0 for a dielectric) is never inside an
        # equal-tailed interval of a positive parameter: such entries are left out of the
        # coverage (counted separately), not scored as misses
        on_floor = {f"n_im[{i}]" for i, v in enumerate(np.asarray(truth.n)) if abs(v.imag) <= 1e-9}
        for lvl in (0.68, 0.95):
            inside = post.contains(tv, lvl)
            cover[str(lvl)] = {
                lab: bool(v)
                for lab, v in zip(labels, inside, strict=True)
                if lab != "gain" and lab not in on_floor
            }
        res["coverage_skipped_on_boundary"] = sorted(on_floor & set(labels))
    res["mcmc"] = dict(
        time=t_cls + t_ref + t_mc,
        shape_ok=shape_ok,
        material_ok=list(MATERIALS)[nearest_material(n_med)] == o["material"],
        **_att_errors(truth, q_med, sym_of[o["shape"]], shape_ok),
        m_rel=abs(m_med / float(truth.m[0]) - 1),
        n_err=abs(n_med - complex(truth.n[0])),
        acceptance=float(np.mean(post.acceptance_fraction)),
        max_tau=float(np.max(post.tau)),
        min_ess=float(np.min(post.ess)),
        converged=bool(post.converged),
        coverage=cover,
    )
    return res


def summarize(results, stages):
    rows = []
    for snr in sorted({r["snr"] for r in results}):
        sub = [r for r in results if r["snr"] == snr]
        crb = [r["crb"] for r in sub]
        att_b = np.array([c["att_deg"] for c in crb])
        los_b = np.array([c["los_deg"] for c in crb])
        rows.append(
            dict(
                snr=snr,
                stage="crb",
                n=len(crb),
                att_median=float(np.median(att_b)),
                att_le1=float(np.mean(att_b <= 1.0)),
                los_median=float(np.median(los_b)),
                los_le1=float(np.mean(los_b <= 1.0)),
                los_mirror_median=float("nan"),
                att_sym_median=float("nan"),
                mirror_ambiguous=float("nan"),
                roll_median=float(np.median([c["roll_deg"] for c in crb])),
                m_rel_median=float(np.median([c["m_rel"] for c in crb])),
                n_err_median=float(np.median([c["n_re"] for c in crb])),
                shape_acc=float("nan"),
                material_acc=float("nan"),
                both_acc=float("nan"),
                time_median=float("nan"),
            )
        )
        for st in stages:
            rs = [r[st] for r in sub if st in r]
            if not rs:
                continue
            att = np.array([x["att_deg"] for x in rs])
            los = np.array([x["los_deg"] for x in rs])
            los_m = np.array([x["los_mirror_deg"] for x in rs])
            att_s = np.array([x.get("att_sym_deg", np.nan) for x in rs])
            amb = [x["mirror_ambiguous"] for x in rs if "mirror_ambiguous" in x]
            rows.append(
                dict(
                    snr=snr,
                    stage=st,
                    n=len(rs),
                    att_median=float(np.nanmedian(att))
                    if np.any(np.isfinite(att))
                    else float("nan"),
                    att_le1=float(np.mean(np.nan_to_num(att, nan=1e9) <= 1.0)),
                    los_median=float(np.nanmedian(los))
                    if np.any(np.isfinite(los))
                    else float("nan"),
                    los_le1=float(np.mean(np.nan_to_num(los, nan=1e9) <= 1.0)),
                    los_mirror_median=float(np.nanmedian(los_m))
                    if np.any(np.isfinite(los_m))
                    else float("nan"),
                    att_sym_median=float(np.nanmedian(att_s))
                    if np.any(np.isfinite(att_s))
                    else float("nan"),
                    mirror_ambiguous=float(np.mean(amb)) if amb else float("nan"),
                    roll_median=float("nan"),
                    m_rel_median=float(np.median([x["m_rel"] for x in rs])),
                    n_err_median=float(np.median([x["n_err"] for x in rs])),
                    shape_acc=float(np.mean([x["shape_ok"] for x in rs])),
                    material_acc=float(np.mean([x["material_ok"] for x in rs])),
                    both_acc=float(np.mean([x["shape_ok"] and x["material_ok"] for x in rs])),
                    time_median=float(np.median([x["time"] for x in rs])),
                )
            )
    return rows


def coverage(results):
    out = {}
    for lvl in ("0.68", "0.95"):
        hits = tot = 0
        per = {}
        for r in results:
            c = r.get("mcmc", {}).get("coverage", {}).get(lvl)
            if not c:
                continue
            for lab, v in c.items():
                per.setdefault(lab, []).append(v)
                hits += v
                tot += 1
        out[lvl] = dict(
            rate=hits / tot if tot else float("nan"),
            n=tot,
            per_param={k: float(np.mean(v)) for k, v in per.items()},
        )
    return out


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    markers = {"cls": "o", "ref": "s", "mcmc": "^", "oracle": "x"}
    names = {
        "cls": "classifier",
        "ref": "+ refiner",
        "mcmc": "+ MCMC",
        "oracle": "refiner from the truth",
    }
    for ci, snr in enumerate(sorted({r["snr"] for r in rows})):
        col = f"C{ci}"
        sub = [r for r in rows if r["snr"] == snr and r["stage"] != "crb"]
        chain = [r for r in sub if r["stage"] != "oracle"]  # the pipeline's stages, in order
        crb = [r for r in rows if r["snr"] == snr and r["stage"] == "crb"]
        t = [r["time_median"] for r in chain]
        for ax, key in ((axes[0], "att_median"), (axes[1], "los_median")):
            ax.plot(t, [r[key] for r in chain], "-", color=col, alpha=0.5)
            for r in sub:
                ax.scatter(r["time_median"], r[key], marker=markers[r["stage"]], color=col, s=45)
            if crb:
                ax.axhline(crb[0][key], ls="--", color=col, lw=1)
        # hollow: the LOS error counting the mirror image as right (inversion.mirror_check)
        for r in sub:
            axes[1].scatter(
                r["time_median"],
                r["los_mirror_median"],
                marker=markers[r["stage"]],
                facecolors="none" if r["stage"] != "oracle" else col,
                edgecolors=col,
                s=70,
            )
        axes[2].plot(t, [r["both_acc"] for r in chain], "-", color=col, alpha=0.5)
        for r in sub:
            axes[2].scatter(
                r["time_median"],
                r["both_acc"],
                marker=markers[r["stage"]],
                color=col,
                s=45,
                label=f"{names[r['stage']]}, SNR {snr:g}",
            )
    for ax, lab in (
        (axes[0], "attitude error (deg, median, mod symmetry)"),
        (axes[1], "line-of-sight error (deg, median, body frame)"),
    ):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.axhline(1.0, ls=":", color="k")
        ax.set_xlabel("wall time per observation (s, median, after compile)")
        ax.set_ylabel(lab)
    axes[0].set_title("dashed: median Cramer-Rao bound at the truth", fontsize=9)
    axes[1].set_title("hollow: modulo the mirror image too", fontsize=9)
    axes[2].set_xscale("log")
    axes[2].axhline(0.95, ls=":", color="k")
    axes[2].set_xlabel("wall time per observation (s)")
    axes[2].set_ylabel("shape and material right (fraction)")
    axes[2].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny run (smoke test)")
    ap.add_argument("--n-per-snr", type=int, default=6)
    ap.add_argument("--snrs", type=float, nargs="+", default=[30.0, 100.0, 1000.0])
    ap.add_argument("--grid", type=int, default=3, help="Hopf nside of the template bank")
    ap.add_argument("--k", type=int, default=3, help="classifier candidates refined")
    ap.add_argument("--mcmc-steps", type=int, default=300)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--brdf", choices=["auto", "glossy"], default="auto")
    ap.add_argument(
        "--tag", default="", help="suffix of the output files (e.g. _grid5 for a variant run)"
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.n_per_snr, args.snrs, args.grid, args.mcmc_steps = 2, [30.0], 2, 100
    OUT.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    brdf, brdf_name = choose_brdf(args.brdf)
    print(f"BRDF: {brdf_name}", flush=True)
    models = make_models(brdf)
    t0 = time.perf_counter()
    bank = build_bank(models, args.grid)
    t_bank = time.perf_counter() - t0
    prep = prepare(bank)
    print(
        f"bank: {len(bank)} templates ({t_bank:.1f} s incl. compile), resolution "
        f"{[round(r, 1) for r in bank.resolution_deg]} deg",
        flush=True,
    )
    mcmc_cfg = chain_config(args.mcmc_steps)
    obs = make_observations(models, args.n_per_snr, args.snrs, args.seed)
    # warm-up (compilation) on a separate observation, timed separately
    t0 = time.perf_counter()
    # one observation per shape: the pruned models' facet subsets (SimulatorModel(prune=True))
    # have per-shape capacities (8 for the CubeSats, 32 for the cylinder), each compiled once
    for warm in make_observations(models, len(models), [args.snrs[0]], args.seed + 99):
        run_one(warm, models, bank, prep, args.k, mcmc_cfg, True)
    # the bounded fallback compiles on first use: warm it up too (one round, one start)
    refine_bounded(
        models[warm["shape"]], warm["data"], warm["truth"], noise=NOISE, bounds=BOUNDS, rounds=1
    )
    t_compile = time.perf_counter() - t0
    print(f"warm-up (compilation) {t_compile:.1f} s", flush=True)
    results = []
    for i, o in enumerate(obs):
        r = run_one(o, models, bank, prep, args.k, mcmc_cfg, True)
        results.append(r)
        print(
            f"[{i + 1}/{len(obs)}] snr={o['snr']:g} {o['shape']}/{o['material']}: "
            f"cls {r['cls']['att_deg']:.2f} deg ({r['cls']['time'] * 1e3:.0f} ms) | "
            f"ref {r['ref']['att_deg']:.3f} deg ({r['ref']['time']:.2f} s) | "
            + (
                f"mcmc {r['mcmc']['att_deg']:.3f} deg ({r['mcmc']['time']:.2f} s)"
                if "mcmc" in r
                else f"mcmc refused: {r['mcmc_refused'][:80]}"
            ),
            flush=True,
        )
    stages = ("cls", "ref", "mcmc", "oracle")
    rows = summarize(results, stages)
    cov = coverage(results)
    total = time.perf_counter() - t_all
    meta = dict(
        brdf=brdf_name,
        n_templates=len(bank),
        grid_nside=args.grid,
        resolution_deg=bank.resolution_deg,
        shapes=list(SHAPES),
        materials=MATERIALS.__repr__(),
        finishes=FINISHES,
        n_bins=N_BINS,
        bin_width_m=BIN_WIDTH,
        pulse_fwhm_s=PULSE_FWHM,
        channels="full (16)",
        k=args.k,
        mcmc_steps=args.mcmc_steps,
        mcmc_walkers=24,
        bank_build_s=t_bank,
        max_negative_clipped_rel=max(NEG_CLIPPED, default=0.0),
        compile_s=t_compile,
        total_s=total,
        n_obs=len(obs),
        command="python bench/bench_inversion.py "
        + " ".join(sys.argv[1:] if argv is None else argv),
    )
    (OUT / f"inversion_results{args.tag}.json").write_text(
        json.dumps(
            dict(meta=meta, rows=rows, coverage=cov, per_observation=results), indent=1, default=str
        )
    )
    plot(rows, OUT / f"inversion_error_vs_time{args.tag}.png")
    lines = [
        "# Inversion: error against run time",
        "",
        f"Command: `{meta['command']}` (x64). BRDF: {brdf_name}.",
        f"Bank: {len(bank)} templates (shapes {list(SHAPES)} x Hopf nside {args.grid} attitudes, "
        f"covering radius {[round(r, 1) for r in bank.resolution_deg]} deg, symmetry-reduced x "
        f"{len(MATERIALS)} materials x {len(FINISHES)} finishes); built in {t_bank:.1f} s.",
        f"Sensor: monostatic, 532 nm, {PULSE_FWHM * 1e12:.0f} ps FWHM, {N_BINS} bins of "
        f"{BIN_WIDTH * 100:.0f} cm, 16 PSG/PSA channels; noise: Poisson at SNR (total counts = "
        f"SNR^2), range offset up to 3 bins, roughness off the finish grid by up to 30%.",
        f"{len(obs)} held-out observations ({args.n_per_snr} truths, each observed at every "
        f"SNR: the SNR rows are paired); top-{args.k} + the best {PER_SHAPE} candidate(s) of "
        f"every shape (ranked over the whole bank); every start screened by one round at "
        f"solver tolerance {SCREEN_TOL:g}, each shape's best screened start polished (2 rounds, "
        f"tolerance 1e-8) when its screened deviance is within {POLISH_FACTOR} x the best + "
        f"{POLISH_ABS:g}; shape chosen by the lowest deviance; "
        f"MCMC 24 walkers x "
        f"{args.mcmc_steps} steps. Times are medians per observation after a warm-up "
        f"(compilation took {t_compile:.1f} s once). Total run {total:.0f} s.",
        "",
        "Stages: `cls` classifier only, `ref` + refiner, `mcmc` + MCMC (posterior median), "
        "`oracle` the refiner started at the truth (diagnostic: no search; its gap to `ref` is "
        "the search's failure, its gap to `crb` the estimator's), `crb` the bound (below).",
        "The refiner ends with `inversion.mirror_check`: it refines from the mirror image of "
        "the chosen fit (R' = P R sigma: the same range profiles, Mueller D M D) and keeps the "
        "better. `LOS err mod mirror` counts the mirror image's line of sight as right; "
        "`mirror ambiguous` is the fraction of observations whose two modes both keep "
        "posterior probability above 5% (for `oracle`: the check run from the truth-started "
        "fit, i.e. what the data themselves cannot tell, search aside). `att err mod half "
        "turn, mirror` is the attitude error modulo the shape's rotations, the half turn about "
        "the line of sight (`inversion.los_half_turn`: an exact symmetry of any monostatic "
        "measurement) and the mirror image: the part of the attitude the data can tell at all.",
        "",
        "| SNR | stage | n | attitude err median (deg) | att <= 1 deg | LOS err median (deg) | "
        "LOS <= 1 deg | LOS err mod mirror median (deg) | att err mod half turn, mirror "
        "median (deg) | mirror ambiguous | "
        "m rel err median | abs(n err) median | shape acc | material acc | "
        "shape+material | time median (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def f(x, fmt):
        return "-" if np.isnan(x) else ("inf" if np.isinf(x) else format(x, fmt))

    for r in rows:
        lines.append(
            f"| {r['snr']:g} | {r['stage']} | {r['n']} | {f(r['att_median'], '.3g')} | "
            f"{r['att_le1']:.2f} | {f(r['los_median'], '.3g')} | {r['los_le1']:.2f} | "
            f"{f(r['los_mirror_median'], '.3g')} | {f(r['att_sym_median'], '.3g')} | "
            f"{f(r['mirror_ambiguous'], '.2f')} | "
            f"{f(r['m_rel_median'], '.3g')} | {f(r['n_err_median'], '.3g')} | "
            f"{f(r['shape_acc'], '.2f')} | {f(r['material_acc'], '.2f')} | "
            f"{f(r['both_acc'], '.2f')} | {f(r['time_median'], '.3g')} |"
        )
    crb_rows = [r for r in rows if r["stage"] == "crb"]
    lines += [
        "",
        "Rows `crb`: the Cramer-Rao bound at the truth (inverse expected Poisson Fisher "
        "information, all parameters free; `inversion.cramer_rao`), median over the "
        "observations: attitude / LOS columns are 1-sigma bounds (deg), `att <= 1 deg` the "
        "fraction of observations whose bound is below 1 deg, m and n columns the relative "
        "m and absolute n' bounds. The bound scales as 1/SNR (Fisher information is "
        "proportional to the photon count); an infinite bound means an exact symmetry of "
        "the measurement (e.g. the roll about the line of sight of a target whose every "
        "return is a normal-incidence Fresnel reflection, M = R diag(1, 1, -1, -1)).",
    ]
    for r in crb_rows:
        lines.append(
            f"- SNR {r['snr']:g}: median roll bound {f(r['roll_median'], '.3g')} deg; a median "
            f"attitude bound of 1 deg needs SNR ~{f(r['snr'] * r['att_median'], '.3g')}, "
            f"a median LOS bound of 1 deg SNR ~{f(r['snr'] * r['los_median'], '.3g')}."
        )
    lines += [
        "",
        "Material identifiability (no search): the truth-started fit refined with the index "
        "fixed at each library material; the gap is the best other material's deviance minus "
        "the true one's (negative: another material fits better; > 4: a likelihood ratio "
        "above e^2).",
        "",
    ]
    for snr in sorted({r["snr"] for r in results}):
        gaps = np.array([r["oracle"]["material_gap"] for r in results if r["snr"] == snr])
        lines.append(
            f"- SNR {snr:g}: gaps {', '.join(f'{g:.1f}' for g in gaps)}; "
            f"{np.mean(gaps > 4):.2f} of {len(gaps)} identifiable"
        )
    lines += [
        "",
        "Coverage of the MCMC credible intervals (truth inside; all fitted parameters "
        "except gain, observations with the right shape):",
        "",
    ]
    for lvl, c in cov.items():
        per = ", ".join(f"{k}: {v:.2f}" for k, v in c["per_param"].items())
        lines.append(f"- {float(lvl):.0%} intervals: {c['rate']:.2f} of {c['n']} ({per})")
    n_skip = sum(len(r.get("coverage_skipped_on_boundary", [])) for r in results)
    if n_skip:
        lines.append(
            f"- left out: {n_skip} entries whose truth lies on the parameter's hard boundary "
            "(n'' = 0 of a dielectric: never inside an equal-tailed interval of a positive "
            "parameter)"
        )
    n_fb = sum(1 for r in results if r.get("bounded_fallback"))
    if n_fb:
        lines += [
            "",
            f"Refiner: on {n_fb} of {len(results)} observations the Levenberg-Marquardt optimum of "
            "a candidate shape left the physical index box (n' in [0.05, 5], n'' in [0, 15]); "
            "that shape was refined again with the box-bounded L-BFGS-B refiner "
            "(inversion.refine_bounded, jaxopt).",
        ]
    refused = [r["mcmc_refused"] for r in results if "mcmc_refused" in r]
    if refused:
        lines += [
            "",
            f"MCMC refused on {len(refused)} of {len(results)} observations (the refined optimum "
            "outside the prior's support; those rows have no MCMC stage): "
            + "; ".join(x.split(". ")[0] for x in refused),
        ]
    lines += ["", NOTES]
    (OUT / f"inversion_summary{args.tag}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
