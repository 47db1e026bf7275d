"""ppr: Pulse Polarization Ranging in JAX.

Polarized microfacet BRDF (Blinn-Phong normals, Ashikhmin shadowing, complex Fresnel as
Mueller matrices, double bounce with coherent enhanced backscatter, depolarizing multiple
scattering) and facet-sum pulse synthesis over triangle meshes.

Conventions (directions, frames, Stokes handedness, complex index sign, units) are fixed in
:mod:`ppr._conventions`. The library never enables ``jax_enable_x64``; dtypes follow inputs.
"""

from ._material import Material
from ._fresnel import fresnel_amplitudes, fresnel_mueller_params
from ._frames import jones_to_mueller, mueller_rotator
from . import microfacet

__all__ = ["Material", "fresnel_amplitudes", "fresnel_mueller_params", "jones_to_mueller", "mueller_rotator"]
__version__ = "0.1.0"
