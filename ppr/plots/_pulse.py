"""Demo figures of the pulse synthesis: range-resolved Stokes profiles and depolarization.

:func:`pulse_figures` simulates the 3U CubeSat with deployed panels
(``configs/scenes/cubesat3u_panels.toml``: brushed aluminium body, cover-glass solar cells,
white-paint panel backs, 532 nm, 100 ps FWHM pulse with 20 ps jitter, 5 mm bins) with the
full polarized BRDF and saves

- ``pulse_stokes.png``: the received Stokes profiles ``S0..S3`` (sensor frame) for
  transmitted H, V, +45 deg and right-circular (``"R"``: clockwise seen looking toward the
  laser, ``S3 = -1``; :data:`ppr.pulse._pulse.STOKES_STATES`) states, against one-way range
  (bottom axis) and round-trip time (top axis);
- ``pulse_depolarization.png``: the Mueller depolarization index per range bin and the
  degree of polarization of the return for each transmitted state, over the return profile.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def _scene():
    from .._resources import shipped_config
    from ..pulse._scene import load_scene

    return load_scene(shipped_config("scenes/cubesat3u_panels.toml"))


def pulse_figures(out_dir: str | os.PathLike, *, brdf=None, terms=None) -> list[Path]:
    """Simulate the default CubeSat scene and write the two demo PNGs to ``out_dir``.

    Returns the written paths. One compilation of the Mueller profile (the Stokes profiles
    of the four transmitted states are ``M @ s``, identical to ``simulate(states=...)``).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..optics.conventions import C_LIGHT
    from ..pulse._pulse import STOKES_STATES, simulate

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = _scene()
    prof = simulate(scene, brdf=brdf, terms=terms)
    m = np.asarray(prof.data, np.float64)  # (4, 4, B)
    r = np.asarray(prof.range_m)
    names = {"H": "H (0 deg)", "V": "V (90 deg)", "D": "+45 deg", "R": "right circular"}
    stokes = {k: np.einsum("ijb,j->ib", m, np.asarray(STOKES_STATES[k])) for k in names}
    s0max = max(float(s[0].max()) for s in stokes.values())
    sig = m[0, 0] > 1e-3 * m[0, 0].max()
    lo, hi = r[sig].min() - 0.05, r[sig].max() + 0.05
    paths = []

    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True, sharey=True)
    for ax, (k, label) in zip(axes.ravel(), names.items(), strict=True):
        s = stokes[k] / s0max
        for i, lab in enumerate(["S0", "S1", "S2", "S3"]):
            ax.plot(r, s[i], label=lab, lw=1.4)
        ax.axhline(0, color="0.6", lw=0.6)
        ax.set_title(f"transmitted {label}")
        ax.set_xlim(lo, hi)
        top = ax.secondary_xaxis(
            "top", functions=(lambda x: 2e12 * x / C_LIGHT, lambda t: t * C_LIGHT / 2e12)
        )
        top.set_xlabel("round-trip time (ps)", fontsize=8)
    for ax in axes[1]:
        ax.set_xlabel("one-way range relative to reference (m)")
    for ax in axes[:, 0]:
        ax.set_ylabel("Stokes per bin / max S0")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("3U CubeSat with panels: range-resolved received Stokes profiles (sensor frame)")
    fig.tight_layout()
    p = out / "pulse_stokes.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)

    fig, ax = plt.subplots(figsize=(9, 4.5))
    with np.errstate(invalid="ignore", divide="ignore"):
        m00 = m[0, 0]
        di = np.sqrt(np.clip((m**2).sum(axis=(0, 1)) - m00**2, 0, None)) / (np.sqrt(3) * m00)
        ax.plot(r[sig], 1 - di[sig], "k-", lw=2, label="1 - depolarization index (Mueller)")
        for k, label in names.items():
            s = stokes[k]
            dop = np.sqrt(s[1] ** 2 + s[2] ** 2 + s[3] ** 2) / s[0]
            ax.plot(r[sig], 1 - dop[sig], lw=1, label=f"1 - DOP, {label}")
    ax.fill_between(r, 0, m00 / m00.max(), color="0.85", label="return M00 (normalized)")
    ax.set(
        xlim=(lo, hi),
        ylim=(0, 1.05),
        xlabel="one-way range relative to reference (m)",
        ylabel="depolarization",
        title="depolarization vs range",
    )
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    p = out / "pulse_depolarization.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths
