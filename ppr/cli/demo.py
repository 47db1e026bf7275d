"""``ppr demo``: every demo figure (BRDF, double bounce, pulse, a Mueller image)."""

from __future__ import annotations

import time

from . import _common as c
from ._help import paragraph
from .image import DEFAULT_CONFIG as IMAGE_CONFIG
from .image import ImageConfig, image_inputs, run_image, write_image_outputs

NAME = "demo"
SET_EXAMPLE = "'render.terms=[\"single\"]'"
EXAMPLES = [
    "ppr demo --out out/demo",
    "ppr demo --only image,pulse --pixels 96 --out out/demo_quick",
    "ppr demo --only image --set render.n_pixels=64 --set 'render.terms=[\"single\"]'",
]


def _brdf(out):
    from ..plots import brdf_figures

    return brdf_figures(out)


def _double(out):
    from ..plots import double_figures

    return double_figures(out)


def _pulse(out):
    from ..plots import pulse_figures

    return pulse_figures(out)


# (key, label, function writing the figures into a folder); the image is the fourth step
STEPS = [
    ("brdf", "BRDF figures", _brdf),
    ("double", "double-bounce figures", _double),
    ("pulse", "pulse figures", _pulse),
]
KEYS = ("brdf", "double", "pulse", "image")


def help_text() -> str:
    return "\n\n".join(
        [
            paragraph(
                "Write every demo figure into --out: the BRDF figures, the double-bounce "
                "(enhancement peak) figures, the pulse figures and a Mueller image of the "
                "example satellite (configs/cli/image.toml; --set overrides apply to it). The "
                "figures are staged and replace their previous versions together at the end "
                "(the demo always overwrites its own figures; other files in --out are kept)."
            ),
            "Examples:\n" + "\n".join(f"  {e}" for e in EXAMPLES),
        ]
    )


def register(sub) -> None:
    p = sub.add_parser(
        NAME, help="write all demo figures", describe=help_text, formatter_class=c.Formatter
    )
    p.add_argument("--out", "-o", metavar="DIR", default="out/demo", help="output folder")
    p.add_argument("--pixels", type=int, default=160, help="Mueller image size (pixels per side)")
    p.add_argument(
        "--only",
        metavar="STEPS",
        default=None,
        help=f"comma-separated subset of the steps {', '.join(KEYS)} (default: all)",
    )
    p.add_argument(
        "--set",
        "-s",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help="override a field of the Mueller image's config (configs/cli/image.toml), e.g. "
        f"--set {SET_EXAMPLE}",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bars or messages")
    p.set_defaults(func=run, load=load)


def _steps(args) -> tuple[str, ...]:
    if args.only is not None and not args.only.strip():
        # an unset shell variable, not "every step"
        raise c.CLIError(f"--only {args.only!r}: empty; give steps from {', '.join(KEYS)}")
    only = KEYS if args.only is None else tuple(k.strip() for k in args.only.split(","))
    bad = [k for k in only if k not in KEYS]
    if bad:
        raise c.CLIError(
            f"--only {args.only!r}: unknown step {bad[0]!r} (steps: {', '.join(KEYS)})"
        )
    if not 4 <= args.pixels <= 2048:
        raise c.CLIError(f"--pixels {args.pixels}: the image size must lie in [4, 2048] pixels")
    return only


def load(args):
    """The Mueller image's config with ``--pixels`` and the overrides."""
    from .._config import load_toml_model

    path = c.config_path(args, IMAGE_CONFIG)
    return path, load_toml_model(
        ImageConfig, path, {"render.n_pixels": args.pixels, **c.overrides(args)}
    )


def run(args) -> int:
    only = _steps(args)
    cfg_path = cfg = inputs = None
    if "image" in only:  # validate the image's config before drawing anything
        cfg_path, cfg = load(args)
        c.maybe_x64(cfg.render.dtype)
        inputs = image_inputs(cfg, cfg_path)
    done: dict[str, float] = {}
    t_all = time.perf_counter()
    # every figure is staged and the whole set replaces the old one at the end
    with c.outputs(args.out, None, overwrite=True) as staged:
        out = staged.folder
        for key, label, fn in STEPS:
            if key not in only:
                continue
            c.say(args, f"ppr demo: {label} ...")
            t0 = time.perf_counter()
            fn(out)
            done[label] = time.perf_counter() - t0
        if cfg is not None:
            c.say(args, "ppr demo: Mueller image of the example satellite ...")
            t0 = time.perf_counter()
            img = run_image(cfg, cfg_path, progress=c.progress(args), inputs=inputs)
            write_image_outputs(img, cfg, cfg_path, staged, seconds=time.perf_counter() - t0)
            done["Mueller image"] = time.perf_counter() - t0
        summary = {"steps_seconds": done, "total_seconds": time.perf_counter() - t_all}
        c.write_json(out / "demo.json", summary, config=cfg)
        pngs = sorted(p.name for p in out.glob("*.png"))
    c.say(args, f"ppr demo: {len(pngs)} figures in {args.out} ({summary['total_seconds']:.0f} s)")
    return 0
