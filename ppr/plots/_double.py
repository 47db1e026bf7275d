"""Double-bounce demo figures (``ppr demo``): polarimetry against the bistatic angle with and
without the double term, and the coherent enhancement peak."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ..optics.conventions import DEFAULT_WAVELENGTH_M

__all__ = ["double_figures"]




def double_figures(out_dir: str, *, order: tuple[int, int] = (16, 16)) -> list[str]:
    """Depolarization index, diattenuation and retardance vs bistatic angle 0-10 deg (k at 30
    deg, k' in the plane of incidence) for rough and smooth aluminium and TiO2 white paint,
    single + multiple with and without the double term, and the enhancement peak of the
    double term (co- and cross-polarized, linear and circular). Returns the PNG paths."""
    import os

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..brdf._brdf import mueller_brdf
    from ..brdf.double import double_bounce_term
    from ..optics.polarimetry import depolarization_index, diattenuation, retardance

    os.makedirs(out_dir, exist_ok=True)
    th = math.radians(30.0)
    psi = np.linspace(0.0, math.radians(10.0), 161)
    k = np.stack([np.sin(th) * np.ones_like(psi), 0 * psi, np.cos(th) * np.ones_like(psi)], -1)
    kp = np.stack([np.sin(th + psi), 0 * psi, np.cos(th + psi)], -1)
    z = np.broadcast_to([0.0, 0.0, 1.0], k.shape)
    mats = [
        ("rough Al (m=2)", 0.94 + 6.42j, 2.0),
        ("smooth Al (m=200)", 0.94 + 6.42j, 200.0),
        ("white paint TiO2 (m=1)", 2.67 + 0j, 1.0),
    ]
    deg = np.degrees(psi)
    fig, axes = plt.subplots(3, 3, figsize=(12, 9), sharex=True)
    for col, (lab, n, m) in enumerate(mats):
        mat = _material_of(n, m)
        with_d = mueller_brdf(
            k, kp, z, mat, terms=("single", "double", "multiple"), wavelength=DEFAULT_WAVELENGTH_M
        )
        without = mueller_brdf(
            k, kp, z, mat, terms=("single", "multiple"), wavelength=DEFAULT_WAVELENGTH_M
        )
        for row, (name, fn) in enumerate(
            [
                ("depolarization index", depolarization_index),
                ("diattenuation", diattenuation),
                ("retardance [rad]", retardance),
            ]
        ):
            ax = axes[row, col]
            ax.plot(deg, np.asarray(fn(with_d)), label="single+double+multiple")
            ax.plot(deg, np.asarray(fn(without)), "--", label="single+multiple")
            ax.set_ylabel(name)
            if row == 0:
                ax.set_title(lab)
            if row == 2:
                ax.set_xlabel("bistatic angle [deg]")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    p1 = os.path.join(out_dir, "double_polarimetry_vs_bistatic.png")
    fig.savefig(p1, dpi=110)
    plt.close(fig)

    # enhancement peak of the double term
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    mat = _material_of(0.94 + 6.42j, 2.0)
    fi = np.broadcast_to([0.0, 1.0, 0.0], k.shape)
    coh, inc = (
        np.asarray(
            double_bounce_term(
                *(jnp.asarray(a) for a in (k, kp, z)),
                mat,
                jnp.asarray(fi),
                jnp.asarray(fi),
                order=order,
                coherent=coherent,
            )
        )
        for coherent in (True, False)
    )
    for s_in, s_out, lab in [
        ((1, 1, 0, 0), (1, 1, 0, 0), "linear co-pol"),
        ((1, 1, 0, 0), (1, -1, 0, 0), "linear cross-pol"),
        ((1, 0, 0, 1), (1, 0, 0, 1), "circular, same S3 sign"),
        ((1, 0, 0, 1), (1, 0, 0, -1), "circular, opposite S3 sign"),
    ]:
        so, si = np.asarray(s_out, float), np.asarray(s_in, float)
        ax.plot(deg, (so @ coh @ si) / (so @ inc @ si), label=lab)
    ax.set_xlabel("bistatic angle [deg]")
    ax.set_ylabel("double term: coherent / incoherent")
    ax.set_title("enhanced backscatter, Al m=2, 532 nm, d = 5 um")
    ax.set_xlim(0, 10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    p2 = os.path.join(out_dir, "double_enhancement_peak.png")
    fig.savefig(p2, dpi=110)
    plt.close(fig)
    return [p1, p2]


def _material_of(n, m):
    from ..materials._material import Material

    return Material(n=n, m=m)
