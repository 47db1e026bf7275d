"""``ppr invert``: least-squares refinement and MCMC of attitude and materials from one
observation. The workflow is written out here; ``inversion`` supplies the pieces."""

from __future__ import annotations

import time
from typing import Any, Literal

import numpy as np
import pydantic

from .._resources import shipped_config
from . import _common as c
from ._help import describe, fields_text, paragraph

NAME = "invert"
DEFAULT_CONFIG = "cli/invert.toml"
SET_EXAMPLE = "n_starts=2"
EXAMPLES = [
    "ppr invert --out out/invert",
    'ppr invert --set n_starts=2 --set mcmc_steps=300 --set brdf="glossy" --out out/invert_quick',
    "ppr invert --set observation.photons=1e5 --set 'mcmc_set={\"priors.gain.high\" = 1e9}' "
    "--out out/invert_bright",
]


class InvertObservation(c.StrictModel):
    source: str = pydantic.Field(
        "simulate",
        description='"simulate" (from the scene\'s pose and materials) or an .npz with data '
        "(channels, bins)",
    )
    photons: float = pydantic.Field(
        2e4, gt=0.0, description="expected total counts of a simulated observation"
    )
    range_offset_m: float = pydantic.Field(0.003, description="range offset of the simulation")
    seed: c.Seed = 0


class InvertConfig(c.StrictModel):
    """``ppr invert``: least-squares refinement and MCMC of attitude and materials."""

    scene: str = pydantic.Field(
        description="scene config (mesh, sensor, pulse, bins; its pose and materials are the "
        "truth of simulated observations and the reference for the starts)"
    )
    channels: Literal["full", "stokes", "copol", "circular"] = pydantic.Field(
        "copol", description="PSG/PSA preset (below)"
    )
    brdf: Literal["ppr", "glossy"] = pydantic.Field(
        "ppr", description='"ppr" (ppr.mueller_brdf) or "glossy" (a cheap polarizing stand-in)'
    )
    free: list[Literal["attitude", "m", "n", "corr_length", "range_offset", "gain"]] = (
        pydantic.Field(
            ["attitude", "m", "n", "range_offset", "gain"], description="parameter groups fitted"
        )
    )
    solver: Literal["lm", "dogleg", "gauss_newton"] = pydantic.Field(
        "lm", description="least-squares solver (optimistix)"
    )
    likelihood: Literal["poisson", "gaussian"] = pydantic.Field(
        "poisson",
        description='"poisson": exact Poisson likelihood of photo-counts '
        '(inversion.PoissonCounts); "gaussian": Gaussian approximation with variance mu + 1 '
        "(inversion.PoissonNoise) for scaled data",
    )
    n_starts: int = pydantic.Field(4, ge=1, le=64, description="least-squares starts")
    start_perturbation_deg: float = pydantic.Field(
        8.0, ge=0.0, le=180.0, description="starts: the reference attitude rotated this far"
    )
    start_perturbation_frac: float = pydantic.Field(
        0.3, ge=0.0, lt=1.0, description="... and continuous parameters scaled by 1 +- this"
    )
    mcmc: str | None = pydantic.Field(
        "default",
        description='priors + sampler config (configs/inversion/*.toml); "default": the '
        "shipped one; unset: no MCMC",
    )
    mcmc_walkers: int | None = pydantic.Field(None, ge=4, description="overrides the sampler's")
    mcmc_steps: int | None = pydantic.Field(None, ge=10, description="overrides the sampler's")
    mcmc_burn_in: int | None = pydantic.Field(None, ge=0, description="overrides the sampler's")
    mcmc_set: dict[str, Any] = pydantic.Field(
        {},
        description='{"dotted.key" = value} overrides of the MCMC config, e.g. '
        '{"priors.gain.high" = 1e9}',
    )
    mirror_symmetry: str | None = pydantic.Field(
        None,
        description="the shape's symmetry class (dihedral:n, octahedral) to check the mirror "
        "ambiguity: refit from the fit's mirror image (inversion.mirror_check; the mesh must "
        "have the z -> -z mirror plane), keep the better, report both in invert.json",
    )
    observation: InvertObservation = pydantic.Field(
        InvertObservation(), description="the observation to invert"
    )


OUTPUTS = [
    "invert.json",
    "invert_chain.npz",
    "invert_posterior.nc",
    "invert_fit.png",
    "invert_corner.png",
]


def help_text() -> str:
    return describe(
        "Recover attitude, roughness m, complex index n, range offset and gain from one "
        "observation: multi-start least squares (optimistix Levenberg-Marquardt), the "
        "goodness of fit and what the data constrain, then posterior sampling (emcee, "
        "vmapped log-probability) with priors from an MCMC config.",
        fields_text(f"Config fields (configs/{DEFAULT_CONFIG})", InvertConfig),
        paragraph(
            "channels (PSG/PSA preset; transmitted; analyzed): full (H,V,D,L; H,V,D,L), stokes "
            "(H,L; H,V,D,L), copol (H; H,V), circular (L; L,R); R/L: right/left circular, "
            "clockwise/counterclockwise seen looking into the beam. The MCMC config "
            "(configs/inversion/*.toml) holds [priors.*] and [sampler]; mcmc_walkers, "
            "mcmc_steps and mcmc_burn_in override its sampler, mcmc_set any of its fields."
        ),
        outputs="invert.json (fit, result codes, attitude error, goodness of fit, "
        "observability, credible intervals, ArviZ diagnostics), invert_chain.npz (physical "
        "samples with walker and draw axes), invert_posterior.nc (ArviZ InferenceData, "
        "netCDF), invert_fit.png, invert_corner.png.",
        examples=EXAMPLES,
    )


def register(sub) -> None:
    p = sub.add_parser(
        NAME,
        help="least-squares + MCMC inversion of one observation",
        describe=help_text,
        formatter_class=c.Formatter,
    )
    c.add_common(p, DEFAULT_CONFIG, "out/invert", SET_EXAMPLE)
    p.set_defaults(func=run, load=load)


def load(args):
    return c.load_config(args, InvertConfig, DEFAULT_CONFIG)


def run(args) -> int:
    import warnings

    import jax.numpy as jnp

    import inversion
    import ppr

    from ..geometry import quat_angle_deg, quat_from_rotvec_host, quat_multiply_host
    from ..plots import plot_fit

    cfg_path, cfg = load(args)
    c.maybe_x64("float64")  # the inversion runs in float64 (docs/DESIGN.md)
    scene = ppr.load_scene(c.resolve_path(cfg.scene, cfg_path))
    chm = inversion.MeasurementModel.preset(cfg.channels).channel_matrix()
    brdf = None
    if cfg.brdf == "glossy":
        from ..pulse._pulse import glossy_fresnel_mueller as brdf
    model = inversion.SimulatorModel(scene, chm, brdf=brdf, dense=True)
    mats = scene.materials
    truth = inversion.PhysicalParams(
        np.asarray(scene.pose.quaternion, np.float64),
        [float(np.asarray(m.m)) for m in mats],
        [complex(np.asarray(m.n)) for m in mats],
        [float(np.asarray(m.corr_length)) for m in mats],
        range_offset=cfg.observation.range_offset_m,
        gain=1.0,
    )
    ob = cfg.observation
    if ob.source == "simulate":
        shape = np.asarray(model.expected(truth, model.prepare(truth)))
        gain = ob.photons / max(float(shape.sum()), 1e-300)
        truth = eqx_replace(truth, gain=jnp.asarray(gain, jnp.float64))
        expected = shape * gain
        # the kernel's roundoff can give -1e-22 counts; anything beyond roundoff is a bug
        if np.min(expected) < -1e-9 * max(float(np.max(expected)), 1e-300):
            raise RuntimeError(
                f"simulated expected counts are negative beyond roundoff "
                f"(min {np.min(expected):.3g}, max {np.max(expected):.3g}); refusing to observe"
            )
        expected = np.maximum(expected, 0.0)
        data = np.random.default_rng(ob.seed).poisson(expected).astype(np.float64)
    else:
        path = c.resolve_path(ob.source, cfg_path)
        if not path.is_file():
            raise c.ConfigError(f"{cfg_path}: observation.source = {ob.source!r}: no such file")
        with np.load(path) as z:
            data = np.asarray(z["data"], np.float64)
        truth = None
    # starts: the reference (truth or scene) perturbed, as the classifier's candidates would be
    ref = (
        truth
        if truth is not None
        else inversion.PhysicalParams(
            np.asarray(scene.pose.quaternion, np.float64),
            [float(np.asarray(m.m)) for m in mats],
            [complex(np.asarray(m.n)) for m in mats],
            gain=max(float(data.sum()), 1.0),
        )
    )
    rng = np.random.default_rng(ob.seed + 1)
    starts = []
    for _ in range(cfg.n_starts):
        w = rng.normal(size=3)
        w *= np.radians(cfg.start_perturbation_deg) / max(np.linalg.norm(w), 1e-12)
        q = quat_multiply_host(quat_from_rotvec_host(w), np.asarray(ref.quaternion))
        f = 1.0 + cfg.start_perturbation_frac * rng.uniform(-1, 1, 4)
        starts.append(
            inversion.PhysicalParams(
                q,
                np.asarray(ref.m) * f[0],
                np.asarray(ref.n).real * f[1] + 1j * np.asarray(ref.n).imag * f[2],
                np.asarray(ref.corr_length),
                range_offset=0.0,
                gain=float(ref.gain) * f[3],
            )
        )
    noise = inversion.PoissonCounts() if cfg.likelihood == "poisson" else inversion.PoissonNoise()
    if cfg.mirror_symmetry is not None:
        try:
            normal = inversion.body_mirror_normal(cfg.mirror_symmetry)
        except ValueError as err:
            raise c.ConfigError(f"{cfg_path}: mirror_symmetry: {err}") from None
        if normal is None:
            raise c.ConfigError(
                f"{cfg_path}: mirror_symmetry = {cfg.mirror_symmetry!r} implies no mirror plane "
                "(use dihedral:n or octahedral, or leave it out)"
            )
        if not inversion.mesh_has_mirror(scene.mesh, normal):
            raise c.ConfigError(
                f"{cfg_path}: mirror_symmetry = {cfg.mirror_symmetry!r}: the scene's mesh has "
                f"no mirror plane with normal {normal.tolist()} through the body origin"
            )
    optional = ["invert_corner.png", "invert_posterior.nc"]  # written with an MCMC config
    with c.outputs(args.out, OUTPUTS, args.overwrite, optional=optional) as out:
        t0 = time.perf_counter()
        try:
            fit = inversion.refine(
                model, data, starts, free=tuple(cfg.free), solver=cfg.solver, noise=noise
            )
        except ValueError as err:
            raise c.ConfigError(f"{cfg_path}: {err}") from None
        mirror = None
        if cfg.mirror_symmetry is not None:
            # the second mode no local fit or bound sees: refit from the mirror image, keep
            # the better, report both
            chk = inversion.mirror_check(
                model, data, fit, cfg.mirror_symmetry, noise=noise, solver=cfg.solver
            )
            mirror = {
                "delta_deviance": chk.delta_deviance,
                "separation_deg": chk.separation_deg,
                "mirror_probability": chk.mirror_probability,
                "ambiguous": chk.ambiguous(),
                "swapped": bool(chk.delta_deviance < 0),
                "mirror_quaternion": np.asarray(chk.mirror.params.unit_quaternion()),
                "summary": chk.summary(),
            }
            fit = chk.best
        t_fit = time.perf_counter() - t0
        # the fit against its noise (exact null distribution of the deviance), and what the
        # data constrain (named unobservable directions; finite uncertainties otherwise)
        los = inversion.line_of_sight_of(model)
        gof = inversion.fit_goodness_of_fit(model, data, fit, noise)
        obs_fit = fit.observability(line_of_sight=los)
        c.say(args, f"ppr invert: {gof.summary()}")
        if obs_fit.unobservable:
            c.say(args, "ppr invert: unobservable: " + "; ".join(obs_fit.names))
        summary = {
            "command": "invert",
            "config_file": str(cfg_path),
            "n_channels": int(data.shape[0]),
            "n_bins": int(data.shape[1]),
            "refine": {
                "success": fit.success,
                "result": fit.result,
                "message": fit.message,
                "cost": fit.cost,
                "reduced_chi2": fit.reduced_chi2
                if not callable(fit.reduced_chi2)
                else fit.reduced_chi2(),
                "seconds": t_fit,
                "labels": fit.labels,
                "quaternion": np.asarray(fit.params.unit_quaternion()),
                "m": np.asarray(fit.params.m),
                "n": np.asarray(fit.params.n),
                "range_offset_m": float(fit.params.range_offset),
                "gain": float(fit.params.gain),
                "starts": [{"result": st.result, "cost": st.cost} for st in fit.starts]
                if hasattr(fit.starts[0], "result")
                else len(fit.starts),
                "sigma": obs_fit.to_dict()["sigma"],
            },
            "goodness_of_fit": gof.to_dict(),
            "observability": obs_fit.to_dict(),
        }
        if mirror is not None:
            summary["mirror_check"] = mirror
        if truth is not None:
            summary["truth"] = {
                "quaternion": np.asarray(truth.quaternion),
                "m": np.asarray(truth.m),
                "n": np.asarray(truth.n),
                "range_offset_m": float(truth.range_offset),
                "gain": float(truth.gain),
            }
            # geodesic angle to the true attitude, not reduced by the shape's symmetry group
            summary["refine"]["attitude_error_deg"] = float(
                quat_angle_deg(fit.params.unit_quaternion(), truth.quaternion)
            )
            if cfg.mirror_symmetry is not None:
                # modulo the shape's rotations, and the line of sight also modulo its mirror
                q_fit = np.asarray(fit.params.unit_quaternion())
                q_true = np.asarray(truth.quaternion)
                sym = cfg.mirror_symmetry
                summary["refine"]["attitude_error_mod_symmetry_deg"] = float(
                    inversion.attitude_error_deg(q_true, q_fit, sym)[0]
                )
                summary["refine"]["los_error_deg"] = float(
                    inversion.line_of_sight_error_deg(q_true, q_fit, sym)[0]
                )
                summary["refine"]["los_error_mod_mirror_deg"] = float(
                    inversion.line_of_sight_error_deg(q_true, q_fit, sym, mirror=True)[0]
                )
            # what no unbiased estimator can beat on these data (infinite: an exact symmetry)
            crb = inversion.cramer_rao(model, truth, noise, free=tuple(cfg.free))
            obs_crb = crb.observability(line_of_sight=los)
            summary["cramer_rao"] = {
                "labels": crb.labels,
                # in the observable subspace: null only for a parameter unobservable on its own
                "sigma": obs_crb.to_dict()["sigma"],
                "unobservable": obs_crb.names,
                "condition": crb.condition,
            }
        chain = {}
        post = None
        if cfg.mcmc is not None:
            mcmc_path = (
                shipped_config("inversion/default.toml")
                if cfg.mcmc == "default"
                else c.resolve_path(cfg.mcmc, cfg_path)
            )
            mcfg = inversion.load_mcmc_config(mcmc_path, cfg.mcmc_set)
            upd = {
                k: v
                for k, v in (
                    ("n_walkers", cfg.mcmc_walkers),
                    ("n_steps", cfg.mcmc_steps),
                    ("burn_in", cfg.mcmc_burn_in),
                )
                if v is not None
            }
            upd["progress"] = c.progress(args)
            samp = validate_sub(
                type(mcfg.sampler), {**mcfg.sampler.model_dump(), **upd}, cfg_path, "mcmc"
            )
            mcfg = mcfg.model_copy(update={"sampler": samp})
            t1 = time.perf_counter()
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", inversion.ChainTooShortWarning)
                try:
                    post = inversion.sample_posterior(
                        model, data, fit.params, config=mcfg, free=tuple(cfg.free), noise=noise
                    )
                    # an ambiguous mirror check: the posterior has a second mode the chain
                    # cannot reach; sample it too (inversion.sample_modes' weighting)
                    post_m = None
                    if mirror is not None and mirror["ambiguous"]:
                        other = chk.fit if chk.delta_deviance < 0 else chk.mirror
                        post_m = inversion.sample_posterior(
                            model,
                            data,
                            other.params,
                            config=mcfg,
                            free=tuple(cfg.free),
                            noise=noise,
                        )
                except ValueError as err:
                    raise c.ConfigError(f"{cfg_path}: mcmc: {err}") from None
            lo68, hi68 = post.interval(0.68).T
            lo95, hi95 = post.interval(0.95).T
            post.write(out.path("invert_posterior.nc"), line_of_sight=los, observed=data)
            # R-hat, bulk/tail ESS and MCSE from ArviZ (walkers as chains), as in the file
            diag = post.diagnostics()
            summary["mcmc"] = {
                "seconds": time.perf_counter() - t1,
                "labels": post.labels,
                "median": post.median(),
                "interval68": np.stack([lo68, hi68], -1),
                "interval95": np.stack([lo95, hi95], -1),
                "acceptance_fraction": float(np.mean(post.acceptance_fraction)),
                "tau": post.tau,
                **{
                    key: [diag[lab][key] for lab in post.labels]
                    for key in ("r_hat", "ess_bulk", "ess_tail", "mcse_mean", "mcse_sd")
                },
                "burn_in": post.burn_in,
                "thin": post.thin,
                "converged": bool(post.converged),
                "warnings": [str(w.message) for w in caught],
            }
            if truth is not None:
                tv = post.truth_vector(truth)
                summary["mcmc"]["truth_vector"] = tv
                summary["mcmc"]["truth_in_95"] = post.contains(tv, 0.95)
            if post_m is not None:
                # the other mirror image's mode: its probability (equal volumes), the
                # quaternion it is centred on, and its intervals (attitude relative to it)
                p_other = min(mirror["mirror_probability"], 1.0 - mirror["mirror_probability"])
                lo68m, hi68m = post_m.interval(0.68).T
                lo95m, hi95m = post_m.interval(0.95).T
                summary["mcmc"]["mode_probability"] = 1.0 - p_other
                summary["mcmc"]["mirror_mode"] = {
                    "probability": p_other,
                    "quaternion": np.asarray(other.params.unit_quaternion()),
                    "median": post_m.median(),
                    "interval68": np.stack([lo68m, hi68m], -1),
                    "interval95": np.stack([lo95m, hi95m], -1),
                    "acceptance_fraction": float(np.mean(post_m.acceptance_fraction)),
                    "tau": post_m.tau,
                    "converged": bool(post_m.converged),
                }
            chain = _chain_arrays(post)
            if post_m is not None:
                chain.update({f"mirror_{k}": v for k, v in _chain_arrays(post_m).items()})
            post.corner_plot(out.path("invert_corner.png"), truth=truth)
        c.write_json(out.path("invert.json"), summary, config=cfg)
        np.savez_compressed(out.path("invert_chain.npz"), data=data, **chain)
        fitted = np.asarray(model.expected(fit.params, model.prepare(fit.params)))
        plot_fit(out.path("invert_fit.png"), data, fitted)
    c.wrote(args, NAME, OUTPUTS)
    return 0


def _chain_arrays(post) -> dict:
    """The npz view of a posterior, every array in the units its labels state: ``samples``
    ``(walkers, draws after burn-in, P)`` and ``warmup`` (the burn-in) in physical units
    (``labels``), the log posterior, the solver-coordinate chain under its own labels."""
    b, t = post.burn_in, post.thin
    par = post.parametrisation
    return {
        "samples": np.swapaxes(post.physical_chain[b::t], 0, 1),
        "warmup": np.swapaxes(post.physical_chain[:b:t], 0, 1),
        "labels": np.array(post.labels),
        "log_prob": np.swapaxes(post.log_prob[b::t], 0, 1),
        "burn_in": np.array(b),
        "thin": np.array(t),
        "reference_quaternion": np.asarray(par.reference.unit_quaternion()),
        "chain_theta": np.swapaxes(post.chain, 0, 1),
        "theta_labels": np.array(par.theta_labels),
    }


def eqx_replace(module, **changes):
    import equinox as eqx

    for k, v in changes.items():
        module = eqx.tree_at(lambda m, k=k: getattr(m, k), module, v)
    return module


def validate_sub(model, data, cfg_path, field):
    return c.sub_model(model, data, cfg_path, field)
