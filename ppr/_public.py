"""The public names of :mod:`ppr`, imported together on the first use of any of them
(``ppr/__init__.py`` keeps ``import ppr`` cheap, so the ``ppr`` command starts without JAX)."""


from . import microfacet
from ._resources import shipped_config, shipped_configs_dir
from .brdf._brdf import mueller_brdf
from .brdf._double_table import PSI_MAX as BACKSCATTER_PSI_MAX
from .geometry import shapes
from .geometry._mesh import (
    FaceSubset,
    Mesh,
    MeshArrays,
    check_mesh,
    load_mesh,
    mesh_arrays,
    subdivide,
)
from .geometry._rotation import matrix_to_quat, quat_from_axis_angle, quat_to_matrix
from .geometry._symmetry import MeshSymmetry, mesh_symmetries, symmetry_label
from .geometry._visibility import VisibilityCaster
from .materials._library import load_material, material_names
from .materials._material import Material
from .optics import _polarimetry as polarimetry
from .optics._frames import jones_to_mueller, mueller_rotator
from .optics._fresnel import fresnel_amplitudes, fresnel_mueller_params
from .optics._polarimetry import (
    cloude_eigenvalues,
    degree_of_polarization,
    depolarization_index,
    diattenuation,
    is_realizable,
    lu_chipman,
    polarizance,
    retardance,
)
from .pulse._macro import (
    MacroGeometry,
    MacroOptions,
    MacroPairs,
    macro_geometry,
    macro_pairs,
    stack_macro_pairs,
)
from .pulse._pulse import (
    Profile,
    backscatter_terms,
    double_bounce,
    near_backscatter,
    render,
    sensor_terms,
    simulate,
    stack_materials,
    tent_gaussian_cdf,
    window_size,
)
from .pulse._scene import Pose, Pulse, RangeBins, Scene, Sensor, load_scene, load_sensor

__all__ = [
    "Material",
    "fresnel_amplitudes",
    "fresnel_mueller_params",
    "jones_to_mueller",
    "mueller_rotator",
    "load_material",
    "material_names",
    "polarimetry",
    "cloude_eigenvalues",
    "degree_of_polarization",
    "depolarization_index",
    "diattenuation",
    "is_realizable",
    "lu_chipman",
    "polarizance",
    "retardance",
    "microfacet",
    "mueller_brdf",
    "shapes",
    "Mesh",
    "MeshArrays",
    "FaceSubset",
    "check_mesh",
    "load_mesh",
    "mesh_arrays",
    "subdivide",
    "matrix_to_quat",
    "quat_from_axis_angle",
    "quat_to_matrix",
    "MeshSymmetry",
    "mesh_symmetries",
    "symmetry_label",
    "Pose",
    "Pulse",
    "RangeBins",
    "Scene",
    "Sensor",
    "load_scene",
    "load_sensor",
    "VisibilityCaster",
    "Profile",
    "double_bounce",
    "MacroGeometry",
    "MacroOptions",
    "MacroPairs",
    "macro_geometry",
    "macro_pairs",
    "stack_macro_pairs",
    "render",
    "simulate",
    "backscatter_terms",
    "BACKSCATTER_PSI_MAX",
    "near_backscatter",
    "sensor_terms",
    "stack_materials",
    "tent_gaussian_cdf",
    "window_size",
    "shipped_config",
    "shipped_configs_dir",
]
