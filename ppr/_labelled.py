"""Results as labelled arrays: :func:`profile_dataset` and :func:`image_dataset` turn a
:class:`ppr.Profile` (range profiles) and a :class:`ppr.MuellerImage` into ``xarray.Dataset``s
with named dimensions, coordinates and a ``units`` attribute on every variable, so that
``xarray.open_dataset("simulate.nc")`` gives a researcher the same numbers with their
meaning. The ``ppr simulate`` and ``ppr image`` commands write them as netCDF
(``simulate.nc``, ``image.nc``; engine ``h5netcdf``).

Conventions: Mueller matrices ``M[out, in]`` act on Stokes vectors ``S_out = M @ S_in`` in
the sensor's beam frames (docs/physics/conventions.md); ranges are one-way, relative to the
profile's reference range; times are round trip.
"""

from __future__ import annotations

import json

import numpy as np

STOKES = ["I", "Q", "U", "V"]


def _xr():
    try:
        import xarray as xr  # noqa: PLC0415
    except ImportError as err:  # pragma: no cover - xarray is a dependency
        raise ImportError("labelled outputs need xarray (pip install xarray)") from err
    return xr


def _provenance_attrs(provenance: dict | None) -> dict:
    """netCDF attributes hold strings and numbers: the provenance record as one JSON string."""
    if provenance is None:
        from ._outputs import provenance as make  # noqa: PLC0415

        provenance = make()
    return {"provenance": json.dumps(provenance, default=str)}


def profile_dataset(profile, *, provenance: dict | None = None):
    """``xarray.Dataset`` of a :class:`ppr.Profile` (the result of :func:`ppr.simulate`).

    Variables: ``data`` in m^2/sr per bin (bin-integrated), with dimensions
    ``(stokes_out, stokes_in, range)`` for ``kind="mueller"``, ``(state, stokes_out, range)``
    for ``"stokes"`` and ``(channel, range)`` for ``"channels"``; ``visibility`` per face
    (lit-and-visible fraction, 1); ``range_edges_m`` (``edge``). Coordinates: ``range`` (bin
    centres, m one-way, relative to ``reference_range_m``), ``time_s`` along ``range`` (s,
    round trip), and the Stokes, state or channel labels. Attributes: ``kind``,
    ``reference_range_m``, ``provenance`` (JSON: versions, time, command line)."""
    xr = _xr()
    data = np.asarray(profile.data, float)
    labels = [str(x) for x in profile.labels]
    if profile.kind == "mueller":
        dims = ("stokes_out", "stokes_in", "range")
        coords = {"stokes_out": STOKES, "stokes_in": STOKES}
    elif profile.kind == "stokes":
        dims = ("state", "stokes_out", "range")
        coords = {"state": labels, "stokes_out": STOKES}
    else:
        dims = ("channel", "range")
        coords = {"channel": labels}
    rng = np.asarray(profile.range_m, float)
    coords["range"] = ("range", rng, {"units": "m", "long_name": "one-way range, bin centre"})
    coords["time_s"] = (
        "range",
        np.asarray(profile.time_s, float),
        {"units": "s", "long_name": "round-trip time of the bin centre"},
    )
    ds = xr.Dataset(
        {
            "data": (
                dims,
                data,
                {"units": "m^2/sr", "long_name": "bin-integrated return (per bin)"},
            ),
            "visibility": (
                ("face",),
                np.asarray(profile.visibility, float),
                {"units": "1", "long_name": "lit-and-visible fraction of each face"},
            ),
            "range_edges_m": (
                ("edge",),
                np.asarray(profile.edges_m, float),
                {"units": "m", "long_name": "one-way range of the bin edges"},
            ),
        },
        coords=coords,
        attrs={
            "kind": profile.kind,
            "reference_range_m": float(profile.reference_range_m),
            "conventions": "S_out = M @ S_in in the sensor's beam frames; ranges one-way",
            **_provenance_attrs(provenance),
        },
    )
    return ds


_IMAGE_UNITS = {
    "reflectance": "1/sr",
    "depolarization_index": "1",
    "polarizance": "1",
    "diattenuation": "1",
    "retardance": "rad",
}


def image_dataset(image, *, provenance: dict | None = None):
    """``xarray.Dataset`` of a :class:`ppr.MuellerImage` (the result of
    :func:`ppr.mueller_image`).

    Dimensions ``y`` (rows, image-plane coordinate ``v`` decreasing) and ``x`` (columns,
    ``u``), coordinates in metres along the image axes (``x_axis``, ``y_axis`` attributes, body
    frame); ``mueller`` ``(y, x, stokes_out, stokes_in)`` in 1/sr (NaN off the object, 0 where
    shadowed), ``cos_in``, ``cos_out``, ``normal`` ``(y, x, xyz)``, ``part`` (index into the
    ``part_names`` attribute, -1 off the object), ``lit``, and the polarimetric maps (units
    per map: reflectance 1/sr, retardance rad, the others 1)."""
    xr = _xr()
    u = np.asarray(image.u, float)
    v = np.asarray(image.v, float)
    u1 = u[0] if u.ndim == 2 else u
    v1 = v[:, 0] if v.ndim == 2 else v
    yx = ("y", "x")
    data = {
        "mueller": (
            yx + ("stokes_out", "stokes_in"),
            np.asarray(image.mueller, float),
            {"units": "1/sr", "long_name": "Mueller BRDF in the sensor frames"},
        ),
        "cos_in": (yx, np.asarray(image.cos_in, float), {"units": "1"}),
        "cos_out": (yx, np.asarray(image.cos_out, float), {"units": "1"}),
        "normal": (
            yx + ("xyz",),
            np.asarray(image.normal, float),
            {"units": "1", "long_name": "shading normal, body frame"},
        ),
        "part": (yx, np.asarray(image.part).astype(np.int32), {"units": "1"}),
        "lit": (yx, np.asarray(image.lit).astype(np.int8), {"units": "1"}),
    }
    for name, val in image.quantities.items():
        data[name] = (yx, np.asarray(val, float), {"units": _IMAGE_UNITS.get(name, "1")})
    return xr.Dataset(
        data,
        coords={
            "y": ("y", v1, {"units": "m", "long_name": "image-plane coordinate along y_axis"}),
            "x": ("x", u1, {"units": "m", "long_name": "image-plane coordinate along x_axis"}),
            "stokes_out": STOKES,
            "stokes_in": STOKES,
            "xyz": ["x", "y", "z"],
        },
        attrs={
            "part_names": json.dumps(list(image.part_names)),
            "x_axis": np.asarray(image.x_axis, float),
            "y_axis": np.asarray(image.y_axis, float),
            "monostatic": int(bool(image.monostatic)),
            **_provenance_attrs(provenance),
        },
    )
