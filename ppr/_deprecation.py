"""Deprecated public names: each still works for one release and warns once per process."""

from __future__ import annotations

import warnings

__all__ = ["PprDeprecationWarning", "warn_deprecated"]


class PprDeprecationWarning(FutureWarning):
    """A deprecated public name of ppr was used (shown once per name and process)."""


_WARNED: set[str] = set()


def warn_deprecated(old: str, new: str, *, stacklevel: int = 3) -> None:
    """Warn once that ``old`` is deprecated in favour of ``new``."""
    if old in _WARNED:
        return
    _WARNED.add(old)
    warnings.warn(
        f"{old} is deprecated and will be removed in the next release; use {new}",
        PprDeprecationWarning,
        stacklevel=stacklevel,
    )
