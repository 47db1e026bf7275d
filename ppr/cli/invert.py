"""``ppr invert``: one observation -> shape, attitude, materials and how far to believe them.
The workflow is :func:`inversion.invert`; this module reads the config (every field, the MCMC
file included, validated before any computation), simulates or reads the observation and
writes :meth:`inversion.Inversion.write`'s files."""

from __future__ import annotations

import functools
import sys
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pydantic

from .. import _outputs
from .._resources import shipped_config
from . import _common as c
from ._help import describe, fields_text, paragraph

NAME = "invert"
DEFAULT_CONFIG = "cli/invert.toml"
SET_EXAMPLE = "top_k=1"
EXAMPLES = [
    "ppr invert --out out/invert",
    'ppr invert --set top_k=1 --set mcmc_steps=300 --set brdf="glossy" --out out/invert_quick',
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


@functools.cache
def _schema():
    """``ppr invert``'s schema: :class:`inversion.InvertConfig`'s fields (same names, top
    level) plus the scene, channels, BRDF, observation and the MCMC config file."""
    import inversion

    class InvertCommandConfig(inversion.InvertConfig):
        """``ppr invert``: classify, refine, weigh materials and modes, sample (invert)."""

        scene: str = pydantic.Field(
            description="scene config (mesh, sensor, pulse, bins; its pose and materials are "
            "the truth of simulated observations)"
        )
        channels: Literal["full", "stokes", "copol", "circular"] = pydantic.Field(
            "copol", description="PSG/PSA preset (below)"
        )
        brdf: Literal["ppr", "glossy"] = pydantic.Field(
            "ppr", description='"ppr" (ppr.mueller_brdf) or "glossy" (a cheap polarizing stand-in)'
        )
        # priors and sampler (configs/inversion/*.toml); None: no posterior sampling
        mcmc: str | None = pydantic.Field(  # type: ignore[assignment]
            "default",
            description='priors + sampler config (configs/inversion/*.toml); "default": the '
            'shipped one; "none" (or false): no posterior sampling',
        )

        @pydantic.field_validator("mcmc", mode="before")
        @classmethod
        def _no_sampling(cls, v):
            # TOML has no null: "none" or false switch the sampler off (a file named "none"
            # would have to be written "./none")
            if v is False or (isinstance(v, str) and v.strip().lower() == "none"):
                return None
            if v is True:
                raise ValueError('expected a config file, "default", "none" or false')
            return v

        mcmc_walkers: int | None = pydantic.Field(None, ge=4, description="overrides the sampler's")
        mcmc_steps: int | None = pydantic.Field(None, ge=10, description="overrides the sampler's")
        mcmc_burn_in: int | None = pydantic.Field(None, ge=0, description="overrides the sampler's")
        mcmc_set: dict[str, Any] = pydantic.Field(
            {},
            description='{"dotted.key" = value} overrides of the MCMC config, e.g. '
            '{"priors.gain.high" = 1e9}',
        )
        observation: InvertObservation = pydantic.Field(
            InvertObservation(), description="the observation to invert"
        )

    return InvertCommandConfig


# the sampler fields ppr invert sets directly, as written in its config
_MCMC_FIELDS = {"n_walkers": "mcmc_walkers", "n_steps": "mcmc_steps", "burn_in": "mcmc_burn_in"}


def invert_config(cfg, cfg_path: Path, progress: bool):
    """The library config (:class:`inversion.InvertConfig`) of a ``ppr invert`` config, with
    its MCMC file read and the sampler overrides applied: every field validated before any
    computation, errors naming the field as written in ``cfg_path`` (or the MCMC file)."""
    import inversion

    mcfg = None
    if cfg.mcmc is not None:
        mpath = (
            shipped_config("inversion/default.toml")
            if cfg.mcmc == "default"
            else c.resolve_path(cfg.mcmc, cfg_path)
        )
        if not mpath.is_file():
            raise c.ConfigError(f"{cfg_path}: mcmc = {cfg.mcmc!r}: no such file ({mpath})")
        try:
            mcfg = inversion.load_mcmc_config(mpath, cfg.mcmc_set)
        except c.ConfigError as err:
            if not cfg.mcmc_set:
                raise
            # the value may be the user's override, not the MCMC file's: say both
            raise c.ConfigError(
                f"{err} (that file with {cfg_path}'s mcmc_set = {cfg.mcmc_set!r})"
            ) from None
        upd = {k: getattr(cfg, v) for k, v in _MCMC_FIELDS.items() if getattr(cfg, v) is not None}
        samp = {**mcfg.sampler.model_dump(), **upd, "progress": progress}
        try:
            sampler = type(mcfg.sampler).model_validate(samp)
        except pydantic.ValidationError as err:
            parts = []
            for e in err.errors():
                loc = e["loc"][0] if e["loc"] else None
                msg = str(e["msg"]).removeprefix("Value error, ")
                if loc in _MCMC_FIELDS:
                    parts.append(f"{_MCMC_FIELDS[loc]} = {samp[loc]!r}: {msg}")
                else:  # a check across fields (burn-in against steps)
                    parts.append(
                        f"mcmc_burn_in = {samp['burn_in']!r}, mcmc_steps = {samp['n_steps']!r} "
                        f"(with {cfg.mcmc}): {msg}"
                    )
            raise c.ConfigError(f"{cfg_path}: " + "; ".join(parts)) from None
        mcfg = mcfg.model_copy(update={"sampler": sampler})
    lib_fields = set(inversion.InvertConfig.model_fields) - {"mcmc", "progress"}
    data = {k: getattr(cfg, k) for k in lib_fields}
    try:
        return inversion.InvertConfig.model_validate({**data, "mcmc": mcfg, "progress": progress})
    except pydantic.ValidationError as err:  # checks across fields (finishes against priors)
        msg = "; ".join(str(e["msg"]).removeprefix("Value error, ") for e in err.errors())
        raise c.ConfigError(f"{cfg_path}: {msg} (mcmc = {cfg.mcmc!r})") from None


def _simulated_truth(model, scene, photons: float, offset: float, where: str):
    import jax.numpy as jnp

    import inversion

    def counts(offset):
        truth = inversion.PhysicalParams.from_scene(scene, range_offset=offset)
        return truth, np.asarray(model.expected(truth, model.prepare(truth)))

    truth, shape = counts(offset)
    if not float(shape.sum()) > 0.0:
        b = scene.bins
        gate = (float(b.start), float(b.start) + float(b.width) * int(b.n_bins))
        if offset != 0.0 and float(counts(0.0)[1].sum()) > 0.0:
            raise c.ConfigError(
                f"{where}: observation.range_offset_m = {offset!r}: the offset moves the whole "
                f"return out of the range gate [{gate[0]:.4g}, {gate[1]:.4g}] m of the scene's "
                "bins: the simulated observation would hold no signal"
            )
        raise c.ConfigError(
            f"{where}: the scene returns no signal into its range gate [{gate[0]:.4g}, "
            f"{gate[1]:.4g}] m (bins, line of sight and pose): nothing to observe"
        )
    gain = photons / float(shape.sum())
    truth = eqx_replace(truth, gain=jnp.asarray(gain, jnp.float64))
    return truth, shape * gain


def run_invert(cfg, cfg_path: Path, out, overwrite: bool = False, progress: bool = False):
    """``ppr invert`` on a parsed config: validate everything (MCMC included), build the
    scene's forward model, read or simulate the observation, :func:`inversion.invert`,
    :meth:`inversion.Inversion.write` into ``out`` (atomically). Returns the Inversion."""
    import inversion
    import ppr

    lib_cfg = invert_config(cfg, cfg_path, progress)
    ob = cfg.observation
    data, where = None, str(cfg_path)
    if ob.source != "simulate":
        data = c.read_npz(ob.source, cfg_path, "observation.source")["data"]
        where = f"{cfg_path}: observation.source = {ob.source!r}"
    c.maybe_x64("float64")  # inversion runs in float64 (the MCMC needs it)
    scene = ppr.load_scene(c.resolve_path(cfg.scene, cfg_path))
    chm = inversion.MeasurementModel.preset(cfg.channels).channel_matrix()
    brdf = None
    if cfg.brdf == "glossy":
        from ..pulse import glossy_fresnel_mueller as brdf
    model = inversion.SimulatorModel(scene, chm, brdf=brdf, dense=True)
    if data is not None and data.shape != (model.n_channels, model.n_bins):
        raise c.ConfigError(
            f"{where}: data has shape {data.shape}; the scene and channels give "
            f"({model.n_channels} channels, {model.n_bins} bins)"
        )
    _outputs.refuse_existing(out, inversion.INVERT_FILES, overwrite)
    truth = None
    data_file = data is not None
    if data is None:
        truth, expected = _simulated_truth(model, scene, ob.photons, ob.range_offset_m, where)
        # the kernel's roundoff can give -1e-22 counts; anything beyond roundoff is a bug
        if np.min(expected) < -1e-9 * max(float(np.max(expected)), 1e-300):
            raise RuntimeError(
                f"simulated expected counts are negative beyond roundoff "
                f"(min {np.min(expected):.3g}, max {np.max(expected):.3g}); refusing to observe"
            )
        data = np.random.default_rng(ob.seed).poisson(np.maximum(expected, 0.0)).astype(float)
    name = Path(cfg.scene).stem  # the candidate's name: its scene file
    try:
        inv = inversion.invert(data, {name: model}, config=lib_cfg)
    except ValueError as err:
        # the data's own faults (negative counts, no signal) name the file they came from
        msg = str(err)
        if data_file and msg.startswith("observation"):
            raise c.ConfigError(f"{where}: data{msg.removeprefix('observation')}") from None
        raise c.ConfigError(f"{cfg_path}: {msg}") from None
    # the observation as it was used: a file's path, or the simulation's settings
    ob_used = {"source": ob.source} if data_file else ob.model_dump(mode="json")
    extra = {"command": "invert", "config_file": str(cfg_path), "observation": ob_used}
    if truth is not None:
        noise = inversion.PoissonCounts(lib_cfg.background)
        crb = inversion.cramer_rao(model, truth, noise, free=tuple(inv.fit.parametrisation.free))
        ob_crb = crb.observability(line_of_sight=inv.line_of_sight_world)
        extra["truth"] = {
            "quaternion": np.asarray(truth.quaternion),
            "m": np.asarray(truth.m),
            "n": np.asarray(truth.n),
            "range_offset_m": float(truth.range_offset),
            "gain": float(truth.gain),
            "errors": inv.compare(truth, name),
            # what no unbiased estimator can beat (observable subspace; null: unobservable)
            "cramer_rao": {
                "labels": crb.labels,
                "sigma": ob_crb.to_dict()["sigma"],
                "unobservable": ob_crb.names,
            },
        }
    inv.write(out, overwrite=overwrite, extra=extra)
    return inv


def help_text() -> str:
    return describe(
        "Recover shape, attitude, roughness m, material, range offset and gain from one "
        "observation with inversion.invert: screening templates, refinement of the best, "
        "materials weighed by their evidence, every equivalent attitude refit as a mode, the "
        "goodness of fit against the noise, what the data cannot constrain, and posterior "
        "sampling per mode (emcee). The answer says converged (the solver) and reliable (fit "
        "acceptable, modes resolved, chains converged) with the reasons when it is not.",
        fields_text(f"Config fields (configs/{DEFAULT_CONFIG})", _schema()),
        paragraph(
            "channels (PSG/PSA preset; transmitted; analyzed): full (H,V,D,L; H,V,D,L), stokes "
            '(H,L; H,V,D,L), copol (H; H,V), circular (L; L,R). mcmc = "default" is the '
            "shipped configs/inversion/default.toml ([priors.*] and [sampler]); mcmc_walkers, "
            "mcmc_steps and mcmc_burn_in override its sampler, mcmc_set any of its fields."
        ),
        outputs=", ".join(_files()) + " (see docs/cli.md).",
        examples=EXAMPLES,
    )


def _files() -> list[str]:
    import inversion

    return list(inversion.INVERT_FILES)


def register(sub) -> None:
    c.add_command(
        sub,
        sys.modules[__name__],
        "shape, attitude and material of one observation, and how far to believe them",
        "out/invert",
    )


def load(args):
    return c.load_config(args, _schema(), DEFAULT_CONFIG)


def run(args) -> int:
    cfg_path, cfg = load(args)
    if c.progress(args):
        import logging

        logging.basicConfig(level=logging.WARNING, format="%(message)s")
        logging.getLogger("inversion.invert").setLevel(logging.INFO)
    inv = run_invert(cfg, cfg_path, args.out, args.overwrite, c.progress(args))
    c.say(args, inv.summary())
    posts = (
        " and the posterior files (invert_posterior*.nc)" if inv.posteriors else " (no sampling)"
    )
    c.say(args, f"ppr invert: wrote {Path(args.out) / 'invert.json'}{posts}")
    return 0


def eqx_replace(module, **changes):
    import equinox as eqx

    for k, v in changes.items():
        module = eqx.tree_at(lambda m, k=k: getattr(m, k), module, v)
    return module
