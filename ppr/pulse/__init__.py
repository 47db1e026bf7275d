"""Range-resolved pulses: scenes, sensors and poses, the facet-sum pulse synthesis and the
macro double bounce between a mesh's surfaces.

Public door of the subpackage: the scene types and loaders, :func:`render` (the pure, jitted
core) and :func:`simulate`, the Stokes/channel projections, the facet BRDF stand-ins
(:func:`lambertian_mueller`, :func:`glossy_fresnel_mueller`), the window sizing, and the
macro double bounce (:mod:`macro`, the host pair builders :func:`macro_pairs`,
:func:`pose_pairs`, :func:`batch_pairs` and the traceable :func:`macro_profile`).
"""

from . import _macro as macro
from ._macro import (
    MacroGeometry,
    MacroOptions,
    MacroPairs,
    batch_pairs,
    glossy_parts,
    macro_geometry,
    macro_pairs,
    macro_profile,
    part_exponents,
    pose_pairs,
    stack_macro_pairs,
)
from ._pulse import (
    COVER_NSIG,
    NSIG,
    STOKES_STATES,
    Profile,
    backscatter_terms,
    channel_projection,
    double_bounce,
    facet_weights,
    glossy_fresnel_mueller,
    lambertian_mueller,
    near_backscatter,
    render,
    sensor_terms,
    simulate,
    single_part,
    stokes_projection,
    tent_gaussian_cdf,
    visible_faces,
    window_size,
)
from ._scene import Pose, Pulse, RangeBins, Scene, Sensor, load_scene, load_sensor

__all__ = [
    "COVER_NSIG",
    "MacroGeometry",
    "MacroOptions",
    "MacroPairs",
    "NSIG",
    "Pose",
    "Profile",
    "Pulse",
    "RangeBins",
    "STOKES_STATES",
    "Scene",
    "Sensor",
    "backscatter_terms",
    "batch_pairs",
    "channel_projection",
    "double_bounce",
    "facet_weights",
    "glossy_fresnel_mueller",
    "glossy_parts",
    "lambertian_mueller",
    "load_scene",
    "load_sensor",
    "macro",
    "macro_geometry",
    "macro_pairs",
    "macro_profile",
    "near_backscatter",
    "part_exponents",
    "pose_pairs",
    "render",
    "sensor_terms",
    "simulate",
    "single_part",
    "stack_macro_pairs",
    "stokes_projection",
    "tent_gaussian_cdf",
    "visible_faces",
    "window_size",
]
