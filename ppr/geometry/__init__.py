"""Geometry: triangle meshes and their kernel arrays, rotations, parametric shapes, mesh
symmetries and ray-cast visibility.

Public door of the subpackage (the names :mod:`inversion`, the notebooks and the benches use):
:class:`Mesh` and its loaders, :class:`MeshArrays` / :class:`FaceSubset` with their static
capacities (:func:`capacity_for`, :func:`subset_capacity`, :func:`n_normal_groups`),
:func:`face_areas_normals`, :func:`concatenate`; the rotation functions of
:mod:`ppr.geometry._rotation` (traceable and host); :mod:`shapes`; :func:`mesh_symmetries`;
:class:`VisibilityCaster`.
"""

from . import shapes
from ._mesh import (
    FaceSubset,
    Mesh,
    MeshArrays,
    capacity_for,
    check_mesh,
    concatenate,
    face_areas_normals,
    load_mesh,
    mesh_arrays,
    n_normal_groups,
    subdivide,
    subset_capacity,
)
from ._rotation import (
    QUAT_NORM_TOL,
    check_quaternion,
    matrix_to_quat,
    quat_angle_deg,
    quat_conjugate,
    quat_from_axis_angle,
    quat_from_rotvec,
    quat_from_rotvec_host,
    quat_multiply,
    quat_multiply_host,
    quat_to_matrix,
    quat_to_matrix_host,
    rotvec_from_quat,
)
from ._symmetry import MeshSymmetry, mesh_symmetries, symmetry_label
from ._visibility import VisibilityCaster

__all__ = [
    "FaceSubset",
    "Mesh",
    "MeshArrays",
    "MeshSymmetry",
    "QUAT_NORM_TOL",
    "VisibilityCaster",
    "capacity_for",
    "check_mesh",
    "check_quaternion",
    "concatenate",
    "face_areas_normals",
    "load_mesh",
    "matrix_to_quat",
    "mesh_arrays",
    "mesh_symmetries",
    "n_normal_groups",
    "quat_angle_deg",
    "quat_conjugate",
    "quat_from_axis_angle",
    "quat_from_rotvec",
    "quat_from_rotvec_host",
    "quat_multiply",
    "quat_multiply_host",
    "quat_to_matrix",
    "quat_to_matrix_host",
    "rotvec_from_quat",
    "shapes",
    "subdivide",
    "subset_capacity",
    "symmetry_label",
]
