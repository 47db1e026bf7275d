"""``ppr``: the command line of Pulse Polarization Ranging.

A thin layer over the library: every subcommand reads a TOML config (typed schema, unknown
keys are errors; the shipped defaults unless ``--config``), applies ``--set key.sub=value``
overrides, runs the library and writes its outputs (arrays ``.npz``/``.zarr``, a JSON summary
with provenance, PNG plots) into ``--out``. One module per command (``brdf``, ``image``,
``simulate``, ``database``, ``classify``, ``invert``, ``report``, ``demo``); ``_common``
holds config loading, ``--set`` and the path rule (docs/configs.md); ``_help`` generates each
command's help from its schema.

Exit status: 0 on success; 2 for a bad config, a bad override, an input the library rejects
or an output that exists (``--overwrite`` replaces it); 130 on Ctrl-C, 143 on SIGTERM. Errors
are one line on stderr naming the file, the field as the user wrote it and the bad value
(``--debug`` shows the traceback instead). Configs are checked whole before any computation.
Outputs are staged, validated and swapped into ``--out`` as a whole (:mod:`ppr._outputs`):
a failed, interrupted or killed run leaves the previous result as it was.

This module is the entry point (``ppr = "ppr.cli:main"``) and imports nothing heavy: the
parser, JAX and the library are imported inside :func:`main`, so Ctrl-C during start-up is
one line and exit status 130 like any other interruption.
"""

import sys

__all__ = ["main"]


def main(argv=None) -> int:
    """Entry point of the ``ppr`` command. Returns 0 on success; raises ``SystemExit(2)`` with
    a one-line message on stderr for config/usage errors, ``SystemExit(130)`` on Ctrl-C
    (``143`` on SIGTERM) after rolling back the outputs being written."""
    try:
        from ._app import run

        return run(argv)
    except KeyboardInterrupt:  # during start-up; a running command reports its own
        if "--debug" in (sys.argv[1:] if argv is None else [str(a) for a in argv]):
            raise
        print("ppr: interrupted", file=sys.stderr)
        raise SystemExit(130) from None


# names other code reaches through ppr.cli, imported on first use
_LAZY = {
    "IMAGE_OUTPUTS": ("image", "OUTPUTS"),
    "INVERT_OUTPUTS": ("invert", "OUTPUTS"),
    "SIMULATE_OUTPUTS": ("simulate", "OUTPUTS"),
    "CLASSIFY_OUTPUTS": ("classify", "OUTPUTS"),
    "REPORT_OUTPUTS": ("report", "OUTPUTS"),
    "part_mesh_from_ppr_mesh": ("image", "part_mesh_from_ppr_mesh"),
    "run_image": ("image", "run_image"),
    "image_inputs": ("image", "image_inputs"),
    "build_parser": ("_app", "build_parser"),
}


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'ppr.cli' has no attribute {name!r}")
    import importlib

    module, attr = _LAZY[name]
    return getattr(importlib.import_module(f"{__name__}.{module}"), attr)
