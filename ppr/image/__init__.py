"""Polarimetric images of a mesh: per-pixel Mueller matrices at a pose from an orthographic
camera (embree ray casting), their Lu-Chipman maps and figures.

Public door of the subpackage: :func:`render_mueller_image` (a :class:`ppr.Mesh`, one
material per part) -> :class:`MuellerImage`; :func:`polarimetric_maps`,
:func:`evaluate_mueller`, :func:`sensor_axes`; :func:`plot_mueller_image`,
:func:`plot_mueller_elements`; ``QUANTITIES`` and their labels; ``EXAMPLE_SATELLITE`` (the
shipped example mesh).
"""

from ._image import (
    EXAMPLE_SATELLITE,
    QUANTITIES,
    QUANTITY_LABELS,
    MuellerImage,
    evaluate_mueller,
    plot_mueller_elements,
    plot_mueller_image,
    polarimetric_maps,
    render_mueller_image,
    sensor_axes,
)

__all__ = [
    "EXAMPLE_SATELLITE",
    "MuellerImage",
    "QUANTITIES",
    "QUANTITY_LABELS",
    "evaluate_mueller",
    "plot_mueller_elements",
    "plot_mueller_image",
    "polarimetric_maps",
    "render_mueller_image",
    "sensor_axes",
]
