"""BRDF demo figures (``ppr demo`` writes them with the double-bounce, pulse and image ones)."""

from __future__ import annotations

import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..optics.conventions import DEFAULT_WAVELENGTH_M

__all__ = ["brdf_figures"]

ROUGHNESSES = (10.0, 1000.0)
INCIDENCE_DEG = 30.0


def _materials(wavelength: float):
    from ..materials._library import load_material, material_names

    return [(name, load_material(name, wavelength)) for name in material_names()]


def brdf_figures(out_dir, wavelength: float = DEFAULT_WAVELENGTH_M) -> list[str]:
    """Write PNG figures of total reflectance (M00), depolarization index and diattenuation
    of :func:`ppr.mueller_brdf` (single + multiple) for the library materials at two
    roughnesses: (1) against the bistatic angle (0 to 60 deg, receiver rotated away from the
    source in the plane of incidence) at 30 deg incidence, (2) against incidence (0 to 85 deg)
    in monostatic backscatter and in the specular direction. Returns the file paths."""
    from ..brdf._brdf import mueller_brdf
    from ..materials._material import Material
    from ..optics.polarimetry import depolarization_index, diattenuation
    from . import brdf_quantity_figure

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mats = _materials(wavelength)
    z = jnp.asarray([0.0, 0.0, 1.0], jnp.float32)

    @jax.jit
    def quantities(k_in, k_out, n, m):
        M = mueller_brdf(k_in, k_out, z, Material(n=n, m=m))
        return M[..., 0, 0], depolarization_index(M), diattenuation(M)

    def evaluate(k_in, k_out):
        res = {}
        for name, mat in mats:
            vals = [quantities(k_in, k_out, jnp.asarray(mat.n, jnp.complex64), jnp.float32(m))
                    for m in ROUGHNESSES]
            res[name] = [np.stack([np.asarray(v[q]) for v in vals]) for q in range(3)]
        return res

    def direction(theta_deg):
        t = np.deg2rad(np.asarray(theta_deg, np.float64))
        return jnp.asarray(np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], -1), jnp.float32)

    columns = [f"m = {m:g}" for m in ROUGHNESSES]
    qlabels = ("M00 (1/sr)", "depolarization index", "diattenuation")
    paths = []

    # (1) bistatic angle at fixed incidence: receiver zenith = incidence - psi (through normal)
    psi = np.linspace(0.0, 60.0, 121)
    k_in = direction(np.full_like(psi, INCIDENCE_DEG))
    k_out = direction(INCIDENCE_DEG - psi)
    res = evaluate(k_in, k_out)
    panels = [(ql, {n: res[n][q] for n, _ in mats}) for q, ql in enumerate(qlabels)]
    fig = brdf_quantity_figure(
        psi, panels, xlabel="bistatic angle (deg)", columns=columns,
        title=f"Mueller BRDF vs bistatic angle, incidence {INCIDENCE_DEG:g} deg, "
              f"{wavelength * 1e9:.0f} nm (single + multiple)",
    )
    p = os.path.join(out, "brdf_vs_bistatic.png")
    fig.savefig(p, dpi=100)
    paths.append(p)

    # (2) incidence: monostatic backscatter and specular
    inc = np.linspace(0.0, 85.0, 86)
    k_in = direction(inc)
    for label, k_out in (("backscatter", k_in), ("specular", direction(-inc))):
        res = evaluate(k_in, k_out)
        panels = [(ql, {n: res[n][q] for n, _ in mats}) for q, ql in enumerate(qlabels)]
        fig = brdf_quantity_figure(
            inc, panels, xlabel="incidence (deg)", columns=columns,
            title=f"Mueller BRDF vs incidence, {label}, {wavelength * 1e9:.0f} nm "
                  "(single + multiple)",
        )
        p = os.path.join(out, f"brdf_vs_incidence_{label}.png")
        fig.savefig(p, dpi=100)
        paths.append(p)
    import matplotlib.pyplot as plt

    plt.close("all")
    return paths
