"""Optics: Fresnel reflection, beam frames and Mueller/Jones rotations, polarimetric
decompositions, and the conventions every module follows (:mod:`ppr.optics.conventions`).

Public door of the subpackage: the Fresnel coefficients, a facet's reflection with a thin-film
stack (:func:`facet_mueller_params`, ``docs/physics/thin_films.md``), the frame and rotation
helpers, the
facet-reflection kernels in beam frames (array-of-structures and structure-of-arrays forms,
the fast monomial and ``(..., 4, 4)`` assemblies), :mod:`polarimetry`, :data:`C_LIGHT` and
:data:`DEFAULT_WAVELENGTH_M`.
"""

from . import conventions, polarimetry
from ._films import facet_mueller_params
from ._frames import (
    A_STOKES,
    default_frame,
    facet_jones_in_beam_frames,
    facet_mueller_in_beam_frames,
    facet_mueller_rows,
    facet_rotated_params,
    jones_rotator,
    jones_to_mueller,
    mueller_from_params,
    mueller_rotator,
    perpendicular_unit,
    rotate_mueller_44,
    rotate_mueller_flat,
    rotated_mueller_flat,
    rotation_cos_sin,
    rotation_cos_sin_2a,
)
from ._fresnel import fresnel_amplitudes, fresnel_amplitudes_re, fresnel_mueller_params
from .conventions import C_LIGHT, DEFAULT_WAVELENGTH_M

__all__ = [
    "A_STOKES",
    "C_LIGHT",
    "DEFAULT_WAVELENGTH_M",
    "conventions",
    "default_frame",
    "facet_jones_in_beam_frames",
    "facet_mueller_params",
    "facet_mueller_in_beam_frames",
    "facet_mueller_rows",
    "facet_rotated_params",
    "fresnel_amplitudes",
    "fresnel_amplitudes_re",
    "fresnel_mueller_params",
    "jones_rotator",
    "jones_to_mueller",
    "mueller_from_params",
    "mueller_rotator",
    "perpendicular_unit",
    "polarimetry",
    "rotate_mueller_44",
    "rotate_mueller_flat",
    "rotated_mueller_flat",
    "rotation_cos_sin",
    "rotation_cos_sin_2a",
]
