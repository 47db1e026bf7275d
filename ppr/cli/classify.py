"""``ppr classify``: top-k database candidates for observations."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import pydantic

from .. import _outputs
from . import _common as c
from ._help import describe, fields_text
from .database import load_bank

NAME = "classify"
DEFAULT_CONFIG = "cli/classify.toml"
OUTPUTS = ["classify.json", "classify.npz", "classify.png"]
SET_EXAMPLE = "database=out/database/database.zarr"
EXAMPLES = [
    "ppr classify --set database=out/database/database.zarr --out out/classify",
    "ppr classify --set database=out/database/database.zarr --set noise.snr=100 "
    '--set attribute="material" --out out/classify_material',
    "ppr classify --set database=out/database/database.zarr "
    "--set observations=out/classify/classify.npz --out out/classify_again",
]


def _finite_or_inf(v: float | str) -> float:
    return float("inf") if v in ("inf", float("inf")) else float(v)


class NoiseConfig(c.StrictModel):
    """Noise of simulated observations (inversion.NoiseModel); "inf" switches a term off."""

    snr: Annotated[float, pydantic.Field(gt=0.0)] | Literal["inf"] = pydantic.Field(
        30.0, description='sqrt of expected total counts; "inf": no photon noise'
    )
    speckle_cells: Annotated[float, pydantic.Field(ge=1.0)] | Literal["inf"] = pydantic.Field(
        50.0, description='speckle contrast 1/sqrt(cells); "inf": none'
    )
    jitter_bins: float = pydantic.Field(0.2, ge=0.0, description="rms per-channel timing jitter")
    max_offset_bins: float = pydantic.Field(
        3.0, ge=0.0, description="unknown range offset, uniform in [-max, max]"
    )
    gain_min: float = pydantic.Field(
        0.1, gt=0.0, description="unknown overall gain, log-uniform in [gain_min, gain_max]"
    )
    gain_max: float = pydantic.Field(10.0, gt=0.0)

    @pydantic.model_validator(mode="after")
    def _gains(self):
        if self.gain_min > self.gain_max:
            raise ValueError(
                f"gain_min = {self.gain_min} exceeds gain_max = {self.gain_max} (the gain is "
                "drawn log-uniformly between them)"
            )
        return self

    def model(self):
        import inversion

        return inversion.NoiseModel(
            snr=_finite_or_inf(self.snr),
            speckle_cells=_finite_or_inf(self.speckle_cells),
            jitter_bins=self.jitter_bins,
            max_offset_bins=self.max_offset_bins,
            gain_min=self.gain_min,
            gain_max=self.gain_max,
        )


class ClassifyConfig(c.StrictModel):
    """``ppr classify``: top-k database candidates for observations."""

    database: str | None = pydantic.Field(
        None, description="a built database (.zarr, from `ppr database build`); no default"
    )
    observations: str = pydantic.Field(
        "simulate",
        description='"simulate" (held-out noisy observations at random attitudes, from the '
        "database's own signature model) or an .npz with data (N, channels, bins)",
    )
    attribute: Literal["shape", "material", "finish", "attitude"] = pydantic.Field(
        "shape", description="what the weights are tuned for"
    )
    weights: Literal["uniform", "channel", "range", "fisher"] = pydantic.Field(
        "fisher", description="weight design"
    )
    top_k: int = pydantic.Field(5, ge=1, le=1000, description="candidates per observation")
    max_shift_bins: int | None = pydantic.Field(
        None, ge=0, description="range shift searched (default: the classifier's)"
    )
    n_simulated: int = pydantic.Field(16, ge=1, le=100_000, description="simulated observations")
    seed: c.Seed = 0
    noise: NoiseConfig = pydantic.Field(
        NoiseConfig(), description="noise of simulated observations"
    )


def help_text() -> str:
    return describe(
        "Classify observations against a built database: weighted inner product maximized "
        "over the unknown range shift (FFT), top-k candidates with scores, shifts (bins) and "
        "their shape, material, finish and attitude quaternion.",
        fields_text(f"Config fields (configs/{DEFAULT_CONFIG})", ClassifyConfig),
        outputs="classify.json (candidates, accuracy if simulated, ms per observation), "
        "classify.npz, classify.png.",
        examples=EXAMPLES,
    )


def register(sub) -> None:
    c.add_command(
        sub, sys.modules[__name__], "top-k database candidates for observations", "out/classify"
    )


def load(args):
    cfg_path, cfg = c.load_config(args, ClassifyConfig, DEFAULT_CONFIG)
    if cfg.database is None:
        raise c.ConfigError(
            f"{cfg_path}: database: not given; pass the database to classify against, e.g. "
            "--set database=out/database/database.zarr (what `ppr database build` writes)"
        )
    return cfg_path, cfg


def read_observations(cfg, cfg_path: Path, bank) -> tuple[np.ndarray, str]:
    """Observations ``(N, channels, bins)`` from an .npz file, checked against the bank."""
    where = f"{cfg_path}: observations = {cfg.observations!r}"
    arrays = c.read_npz(cfg.observations, cfg_path, "observations", optional=("sensor",))
    data = arrays["data"]
    sensor = str(arrays["sensor"]) if "sensor" in arrays else bank.sensor
    if data.ndim == 2:
        data = data[None]
    want = (bank.n_channels, bank.n_bins)
    if data.ndim != 3 or data.shape[1:] != want or len(data) == 0:
        raise c.ConfigError(
            f"{where}: data has shape {data.shape}; this database needs (N, {want[0]} channels, "
            f"{want[1]} bins) or ({want[0]}, {want[1]})"
        )
    # classify computes in float32 (JAX's default): larger values would become inf
    big = np.abs(data) > np.finfo(np.float32).max
    if big.any():
        first = tuple(int(i) for i in np.argwhere(big)[0])
        raise c.ConfigError(
            f"{where}: data value {float(data[first]):g} at index {first} overflows float32, "
            "the precision classify computes in; rescale the data"
        )
    # ... and an observation whose values are all below tiny / eps (float32's normal range
    # with its 24 bits of precision) would come out as 0 or a few denormal digits ("no
    # return"): refused, not reported as empty
    f32 = np.finfo(np.float32)
    peak = np.max(np.abs(np.nan_to_num(data, nan=0.0)), axis=(1, 2))
    small = (peak > 0) & (peak < f32.tiny / f32.eps)
    if small.any():
        i = int(np.argmax(small))
        raise c.ConfigError(
            f"{where}: observation {i}'s largest value {float(peak[i]):g} is too small for "
            f"float32, the precision classify computes in, to keep its digits (below "
            f"{float(f32.tiny / f32.eps):.3g}; float32's smallest normal is "
            f"{float(f32.tiny):.3g}); rescale the data"
        )
    return data, sensor


def simulated_observations(cfg, dbp: Path, bank, noise):
    """``cfg.n_simulated`` noisy observations of random rows of the database's own model:
    random shape, material and finish, Haar-random attitude (off the grid)."""
    import jax.numpy as jnp
    import zarr
    from scipy.spatial.transform import Rotation

    import inversion

    spec = inversion.spec_from_dict(
        dict(zarr.open_group(str(dbp), mode="r").attrs["spec"]), str(dbp)
    )
    sig_fn = inversion.make_signature_fn(spec)
    rng = np.random.default_rng(cfg.seed)
    n = cfg.n_simulated
    quat = Rotation.random(n, random_state=rng).as_quat(scalar_first=True)
    truth = {
        "shape_id": rng.integers(0, len(spec.shapes), n).astype(np.int32),
        "material_id": rng.integers(0, len(spec.materials), n).astype(np.int32),
        "finish_id": rng.integers(0, len(spec.finishes), n).astype(np.int32),
        "attitude_id": np.zeros(n, np.int32),
        "quat": quat,
    }
    clean = np.asarray(sig_fn({k: jnp.asarray(v) for k, v in truth.items()}), np.float64)
    data = np.stack(
        [
            np.asarray(inversion.observe(x, noise, seed=cfg.seed + i, sensor=bank.sensor).data)
            for i, x in enumerate(clean)
        ]
    )
    return data, truth


def run(args) -> int:
    import inversion

    from ..plots import plot_classification

    cfg_path, cfg = load(args)
    dbp = c.resolve_path(cfg.database, cfg_path)
    bank = load_bank(cfg.database, cfg_path, "database")
    if cfg.max_shift_bins is not None and cfg.max_shift_bins > bank.n_bins - 1:
        raise c.ConfigError(
            f"{cfg_path}: max_shift_bins = {cfg.max_shift_bins}: at most n_bins - 1 = "
            f"{bank.n_bins - 1} for this database"
        )
    noise = cfg.noise.model()
    data = truth = None
    sensor = bank.sensor
    if cfg.observations != "simulate":
        data, sensor = read_observations(cfg, cfg_path, bank)
    _outputs.refuse_existing(args.out, OUTPUTS, args.overwrite)
    if cfg.observations == "simulate":
        data, truth = simulated_observations(cfg, dbp, bank, noise)
    obs = [inversion.Observation(data=d, sensor=sensor) for d in data]
    with c.outputs(args.out, OUTPUTS, args.overwrite) as out:
        w = inversion.design_weights(bank, cfg.weights, cfg.attribute)
        prep = inversion.prepare(bank, w)
        if cfg.top_k > len(bank):  # what was asked for is not what is returned: said
            print(
                f"ppr classify: top_k = {cfg.top_k} is more than the database's {len(bank)} "
                f"templates: every template is a candidate ({len(bank)} per observation)",
                file=sys.stderr,
            )
        try:
            res = inversion.classify(
                prep, obs, k=min(cfg.top_k, len(bank)), max_shift=cfg.max_shift_bins
            )
        except ValueError as err:
            raise c.ConfigError(f"{cfg_path}: observations: {err}") from None
        names = bank.names
        cands = []
        for i in range(len(data)):
            rows = []
            for j, r in enumerate(res.index[i]):
                rows.append(
                    {
                        "row": int(r),
                        "score": float(res.score[i, j]),
                        "shift_bins": float(res.shift_refined[i, j]),
                        "shape": names["shapes"][bank.shape_id[r]],
                        "material": names["materials"][bank.material_id[r]],
                        "finish": names["finishes"][bank.finish_id[r]],
                        "quaternion": bank.quat[r],
                    }
                )
            cands.append(rows)
        summary = {
            "command": "classify",
            "config_file": str(cfg_path),
            "database": str(dbp),
            "n_templates": len(bank),
            "n_observations": len(data),
            "seconds": res.seconds,
            "ms_per_observation": 1e3 * res.seconds / len(data),
            "candidates": cands,
            # frames without a positive value hold no return: their candidates are arbitrary
            "no_signal": [int(i) for i in np.flatnonzero(res.no_signal)],
        }
        if res.no_signal.any():
            print(
                f"ppr classify: observations {summary['no_signal']} have no positive value (no "
                "return): their candidates are arbitrary (classify.json 'no_signal')",
                file=sys.stderr,
            )
        if truth is not None:
            best = res.best(bank)
            summary["accuracy"] = {
                a: float(np.mean(best[f"{a}_id"] == truth[f"{a}_id"]))
                for a in ("shape", "material", "finish")
            }
        c.write_json(out.path("classify.json"), summary, config=cfg)
        extra = {f"truth_{k}": v for k, v in (truth or {}).items()}
        np.savez_compressed(
            out.path("classify.npz"),
            data=data,
            sensor=np.array(sensor),
            index=res.index,
            score=res.score,
            shift=res.shift_refined,
            no_signal=res.no_signal,
            **extra,
        )
        plot_classification(
            out.path("classify.png"), data, bank.signatures, res.index, res.shift, res.score
        )
    c.wrote(args, NAME, OUTPUTS)
    return 0
