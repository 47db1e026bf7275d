"""Deprecated: ``ppr.plots_pulse.pulse_figures`` is ``ppr.plots.pulse_figures``."""

from ._deprecation import warn_deprecated

__all__ = ["pulse_figures"]


def pulse_figures(*args, **kwargs):
    """Deprecated alias of :func:`ppr.plots.pulse_figures`."""
    from .plots import pulse_figures as new

    warn_deprecated("ppr.plots_pulse.pulse_figures", "ppr.plots.pulse_figures")
    return new(*args, **kwargs)
