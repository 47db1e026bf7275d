"""ppr: Pulse Polarization Ranging in JAX.

Polarized microfacet BRDF (Blinn-Phong normals, Ashikhmin shadowing, complex Fresnel as
Mueller matrices, double bounce with coherent enhanced backscatter, depolarizing multiple
scattering) and facet-sum pulse synthesis over triangle meshes.

Conventions (directions, frames, Stokes handedness, complex index sign, units) are fixed in
:mod:`ppr.optics.conventions`. The library never enables ``jax_enable_x64``; dtypes follow inputs.
Importing ppr never changes JAX's config: ``ppr.compile_cache()`` opts a script or notebook in
to the persistent compilation cache the ``ppr`` command uses.
"""

__version__ = "0.1.0"


def _load_public():
    import importlib

    return importlib.import_module("ppr._public")


# public names served without JAX (module, attribute; None: the module itself)
_LIGHT = {
    "config": ("ppr.config", None),
    "compile_cache": ("ppr._compile_cache", "compile_cache"),
    "shipped_config": ("ppr._resources", "shipped_config"),
    "shipped_configs_dir": ("ppr._resources", "shipped_configs_dir"),
}


def __getattr__(name: str):
    # The public names live in ppr._public; importing it imports JAX and the library, so it
    # happens on their first use, not on `import ppr` (the `ppr` command's entry stays light).
    if name.startswith("_") and name != "__all__":
        raise AttributeError(f"module 'ppr' has no attribute {name!r}")
    if name in _LIGHT:
        import importlib

        module, attr = _LIGHT[name]
        mod = importlib.import_module(module)
        return mod if attr is None else getattr(mod, attr)
    public = _load_public()
    names = getattr(public, "__all__", None)  # None while ppr._public itself imports
    if names is None or (name != "__all__" and name not in names):
        raise AttributeError(f"module 'ppr' has no attribute {name!r}")
    globals().update({n: getattr(public, n) for n in names})
    globals()["__all__"] = list(names)
    return globals()[name]


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_load_public().__all__))
