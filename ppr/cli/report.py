"""``ppr report``: the classifier's evaluation on held-out simulated observations."""

from __future__ import annotations

import json
import sys
from typing import Annotated, Literal

import pydantic

from . import _common as c
from ._help import describe, fields_text
from .database import load_bank

NAME = "report"
DEFAULT_CONFIG = "cli/report.toml"
SET_EXAMPLE = "n_obs=8"
EXAMPLES = [
    "ppr report --out out/report",
    "ppr report --set n_obs=8 --set 'snrs=[30.0]' --set 'grid_sizes=[1]' --out out/report_quick",
    "ppr report --set database_path=out/database/database.zarr --out out/report_built",
]
OUTPUTS = [
    "report.json",
    "report.md",
    "accuracy_vs_snr.png",
    "attitude_vs_snr.png",
    "attitude_vs_resolution.png",
    "confusion_shape.png",
    "confusion_material.png",
    "confusion_finish.png",
]


class ReportConfig(c.StrictModel):
    """``ppr report``: classifier evaluation on held-out simulated observations."""

    database: str = pydantic.Field(
        description="database spec (configs/databases/*.toml); the bank is built in memory"
    )
    database_path: str | None = pydantic.Field(
        None, description="a built database (.zarr) to use as the bank instead"
    )
    snrs: c.NonEmpty[c.PositiveFloat] = pydantic.Field(
        [10.0, 30.0, 100.0, 300.0], description="sqrt of expected total signal counts"
    )
    grid_sizes: c.NonEmpty[Annotated[int, pydantic.Field(ge=1, le=16)]] = pydantic.Field(
        [1, 2, 3], description="Hopf nside of the attitude-resolution sweep"
    )
    n_obs: int = pydantic.Field(32, ge=1, description="held-out observations per SNR")
    weight_kinds: c.NonEmpty[Literal["uniform", "channel", "range", "fisher"]] = pydantic.Field(
        ["uniform", "channel", "range", "fisher"], description="weight designs compared"
    )
    speckle_cells: float = pydantic.Field(
        50.0, ge=1.0, description="speckle contrast 1/sqrt(cells)"
    )
    jitter_bins: float = pydantic.Field(0.2, ge=0.0, description="rms timing jitter")
    max_offset_bins: float = pydantic.Field(4.0, ge=0.0, description="unknown range offset")
    gain_range: tuple[c.PositiveFloat, c.PositiveFloat] = pydantic.Field(
        (0.1, 10.0), description="unknown gain, log-uniform in [low, high]"
    )
    seed: c.Seed = 0
    top_k: int = pydantic.Field(5, ge=1, description="candidates per observation")

    @pydantic.field_validator("gain_range")
    @classmethod
    def _gain_order(cls, v):
        if v[0] > v[1]:
            raise ValueError("must be [low, high] with low <= high")
        return v


def help_text() -> str:
    return describe(
        "Evaluate the classifier on held-out simulated observations (random attitudes off the "
        "grid, random shape/material/finish, Poisson noise at each SNR, speckle, jitter, range "
        "offset and gain): accuracy and attitude error (degrees) per weight design against "
        "SNR and database angular resolution, confusion matrices, time per classification.",
        fields_text(f"Config fields (configs/{DEFAULT_CONFIG})", ReportConfig),
        outputs="report.json, report.md, accuracy_vs_snr.png, attitude_vs_snr.png, "
        "attitude_vs_resolution.png, confusion_{shape,material,finish}.png.",
        examples=EXAMPLES,
    )


def register(sub) -> None:
    c.add_command(sub, sys.modules[__name__], "classifier evaluation report", "out/report")


def load(args):
    return c.load_config(args, ReportConfig, DEFAULT_CONFIG)


def run(args) -> int:
    import inversion

    cfg_path, cfg = load(args)
    spec_path = c.resolve_path(cfg.database, cfg_path)
    try:
        spec = inversion.load_spec(spec_path)
        inversion.make_signature_fn(spec)  # names the model knows
    except ValueError as err:
        raise c.ConfigError(f"{cfg_path}: database = {cfg.database!r}: {c.one_line(err)}") from None
    bank = None
    if cfg.database_path is not None:
        bank = load_bank(cfg.database_path, cfg_path, "database_path")
    with c.outputs(args.out, OUTPUTS, args.overwrite) as out:
        inversion.evaluate(
            spec,
            out.folder,
            snrs=tuple(cfg.snrs),
            grid_sizes=tuple(cfg.grid_sizes),
            n_obs=cfg.n_obs,
            weight_kinds=tuple(cfg.weight_kinds),
            speckle_cells=cfg.speckle_cells,
            jitter_bins=cfg.jitter_bins,
            max_offset_bins=cfg.max_offset_bins,
            gain_range=tuple(cfg.gain_range),
            seed=cfg.seed,
            bank=bank,
            k=cfg.top_k,
        )
        # the report's JSON gains the provenance every ppr output records
        report = out.path("report.json")
        c.write_json(report, json.loads(report.read_text()), config=cfg)
    c.say(args, f"ppr report: wrote {args.out}/report.md and plots")
    return 0
