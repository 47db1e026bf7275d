"""Materials: the :class:`Material` pytree (complex index, roughness exponent, correlation
length, optional thin-film stack), :func:`stack_materials` (one batched material per mesh part;
:func:`film_fit_layers` names each part's fitted film layer in it) and the sourced material
library (``configs/materials.toml``: :func:`load_material`, :func:`material_names`,
:func:`finish_names`, :func:`load_library`, :func:`film_entries`)."""

from ._library import film_entries, finish_names, load_library, load_material, material_names
from ._material import Material, film_fit_layers, stack_materials

__all__ = [
    "Material",
    "film_entries",
    "film_fit_layers",
    "finish_names",
    "load_library",
    "load_material",
    "material_names",
    "stack_materials",
]
