"""Deprecated: ``ppr.demo.brdf_figures`` is ``ppr.plots.brdf_figures``."""

from ._deprecation import warn_deprecated

__all__ = ["brdf_figures"]


def brdf_figures(*args, **kwargs):
    """Deprecated alias of :func:`ppr.plots.brdf_figures`."""
    from .plots import brdf_figures as new

    warn_deprecated("ppr.demo.brdf_figures", "ppr.plots.brdf_figures")
    return new(*args, **kwargs)
