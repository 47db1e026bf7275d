"""Files shipped with ppr: the default configs (CLI commands, scenes, sensors, databases,
inversion settings, the material library) and the example meshes.

The repository keeps the configs in its top-level ``configs/`` folder; a wheel carries a copy
of that folder inside the package, as ``ppr/data/configs`` (``pyproject.toml``:
``force-include``). :func:`shipped_config` finds them through :mod:`importlib.resources`, so
ppr behaves the same from any working folder, installed or run from a checkout.

Paths written *inside* a config are relative to that config file (docs/configs.md).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["shipped_config", "shipped_configs_dir"]


def shipped_configs_dir() -> Path:
    """The folder of the shipped configs: ``ppr/data/configs`` in an installed wheel, the
    repository's ``configs/`` in a source checkout (an editable install)."""
    packaged = resources.files("ppr").joinpath("data", "configs")
    if packaged.is_dir():
        return Path(str(packaged))
    checkout = Path(__file__).resolve().parent.parent / "configs"
    if (checkout / "scenes").is_dir():
        return checkout
    raise FileNotFoundError(
        f"ppr's shipped configs are missing: neither {packaged} (installed wheel) nor "
        f"{checkout} (source checkout) exists; reinstall ppr"
    )


def shipped_config(relative: str) -> Path:
    """Path of a shipped config, e.g. ``shipped_config("scenes/cubesat3u_panels.toml")``.

    ``relative`` is a path under the configs folder (``cli/``, ``scenes/``, ``sensors/``,
    ``databases/``, ``inversion/``, ``materials.toml``); ``FileNotFoundError`` lists the
    files of that folder when it does not exist."""
    root = shipped_configs_dir()
    path = root / relative
    if not path.is_file():
        folder = path.parent
        known = (
            sorted(str(p.relative_to(root)) for p in folder.glob("*.toml"))
            if folder.is_dir()
            else []
        )
        hint = f"; shipped: {', '.join(known)}" if known else ""
        raise FileNotFoundError(f"no shipped config {relative!r} (in {root}){hint}")
    return path
