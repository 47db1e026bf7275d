# ruff: noqa: E501  (notebook cell sources are kept as written)
"""Write the research notebooks in ``notebooks/`` from the cell sources below (nbformat).

The notebooks are generated, not hand-edited, so they stay reviewable as plain Python here.
Each notebook's first code cell reads ``PPR_SMALL`` (``PPR_SMALL=1``: small grids, short
chains; the test suite runs them that way, ``tests/test_notebooks.py``) and calls
``ppr.compile_cache()`` (the persistent compilation cache of the ``ppr`` command; the tests
switch it off with ``PPR_JAX_CACHE=0``).

    .venv/bin/python scripts/make_notebooks.py                 # write the sources, no outputs
    .venv/bin/python scripts/make_notebooks.py --execute       # write, then run each in full
                                                               # settings and store its outputs
    .venv/bin/python scripts/make_notebooks.py --execute 01 05 # only the notebooks named

Needs ruff (test extra: the written notebooks are fixed and formatted with it); ``--execute``
runs each notebook top to bottom with nbclient on this interpreter's kernel, with JAX's
default compilation, ``PPR_SMALL`` unset and the compilation cache off (``PPR_JAX_CACHE=0``:
the printed timings are a first run's), and stores the outputs (figures included) in the
``.ipynb``, so a reader on GitHub sees them; each notebook's run time is printed.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

OUT = Path(__file__).resolve().parents[1] / "notebooks"

SETUP = '''\
import os, time
SMALL = os.environ.get("PPR_SMALL", "0") == "1"   # small settings (the test suite sets this)
import jax
jax.config.update("jax_enable_x64", True)           # notebooks may enable x64; the library never does
import numpy as np
import matplotlib
if SMALL:
    matplotlib.use("Agg")
import matplotlib.pyplot as plt
import ppr
from pathlib import Path
ROOT = Path(ppr.__file__).resolve().parents[1]       # the repository (configs/, bench/)
ppr.compile_cache()  # compiled programs kept on disk for the next kernel (PPR_JAX_CACHE=0: off)
print("small settings" if SMALL else "full settings", "| jax", jax.__version__, jax.devices())'''


def nb(cells):
    out = new_notebook()
    out.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    out.metadata["language_info"] = {"name": "python"}
    out.cells = [new_markdown_cell(c[3:]) if c.startswith("md:") else new_code_cell(c) for c in cells]
    for i, cell in enumerate(out.cells):  # deterministic ids: regenerating gives no diff
        cell.id = f"cell-{i:02d}"
    return out


# ------------------------------------------------------------------------- 01 BRDF tour
BRDF_TOUR = [
    """md:# A tour of the polarized microfacet BRDF

`ppr.mueller_brdf(k_in, k_out, normal, material)` returns the 4x4 Mueller BRDF (1/sr) of a
rough surface: Blinn-Phong facet normals, Ashikhmin shadowing, the facets' complex Fresnel
reflection as Mueller matrices rotated between the beams' frames and each facet's s/p frame,
plus an energy-conserving depolarizing remainder for light scattered more than once. This
notebook shows (1) Mueller maps over the outgoing hemisphere, (2) how depolarization grows
with roughness and bistatic angle, (3) the Lu-Chipman quantities along a bistatic sweep and
(4) the coherent enhancement peak of the double bounce near exact backscatter. Conventions: `ppr.optics.conventions`; physics notes: `docs/physics.md`.""",
    SETUP,
    """md:## Materials from the library
`configs/materials.toml` holds sourced optical constants at 532 and 1064 nm and finish presets
(Blinn-Phong exponent `m`).""",
    """print(ppr.material_names())
for name in ("aluminium", "gold", "white_paint_tio2", "kapton"):
    mat = ppr.load_material(name, 532e-9)
    print(f"{mat.name:32s} n = {complex(mat.n):.3f}  m = {float(mat.m):g}")""",
    """md:## 1. Mueller maps over the outgoing hemisphere
Incidence 40 deg in the x-z plane; every outgoing direction `k_out` of the upper hemisphere
is drawn at its projected position `(k_out.x, k_out.y)`. Stokes frames: the lab y axis
projected perpendicular to each beam. We jit the BRDF once and evaluate the whole grid in one
call (`terms` is static).""",
    """brdf = jax.jit(ppr.mueller_brdf, static_argnames=("terms",))
N = 41 if SMALL else 121
x, y = np.meshgrid(np.linspace(-1, 1, N), np.linspace(-1, 1, N))
inside = x**2 + y**2 < 0.98
z = np.sqrt(np.clip(1 - x**2 - y**2, 1e-6, None))
k_out = np.stack([x, y, z], -1)
k_out /= np.linalg.norm(k_out, axis=-1, keepdims=True)
th = np.radians(40.0)
k_in = np.array([np.sin(th), 0.0, np.cos(th)])
ey = np.array([0.0, 1.0, 0.0])
def frame(k):
    f = ey - np.sum(ey * k, -1, keepdims=True) * k
    return f / np.linalg.norm(f, axis=-1, keepdims=True)
normal = np.array([0.0, 0.0, 1.0])
mat = ppr.load_material("aluminium", 532e-9, "rough")
t0 = time.perf_counter()
M = np.array(brdf(k_in, k_out, normal, mat, frame_in=frame(k_in), frame_out=frame(k_out)))
print(f"{N*N} directions in {time.perf_counter() - t0:.2f} s (including compilation)")
M[~inside] = np.nan""",
    """fig, axes = plt.subplots(4, 4, figsize=(10, 9.5), constrained_layout=True)
M00 = M[..., 0, 0]
for i in range(4):
    for j in range(4):
        ax = axes[i, j]; ax.set_xticks([]); ax.set_yticks([])
        if i == j == 0:
            im = ax.imshow(np.log10(M00), origin="lower", extent=(-1, 1, -1, 1), cmap="inferno")
            ax.set_title("log10 M00 [1/sr]", fontsize=9)
        else:
            im = ax.imshow(M[..., i, j] / M00, origin="lower", extent=(-1, 1, -1, 1),
                           cmap="RdBu_r", vmin=-1, vmax=1)
            ax.set_title(f"M{i}{j}/M00", fontsize=9)
fig.colorbar(im, ax=axes, shrink=0.6, label="normalized element")
fig.suptitle(f"{mat.name}: Mueller BRDF, incidence 40 deg");""",
    """md:The specular lobe (upper right) is polarizing (M01, M10 non-zero: Fresnel diattenuation
of aluminium at oblique facets); away from it the multiple-scattering remainder dominates and
the normalized matrix tends to diag(1, 0, 0, 0): an ideal depolarizer.

## 2. Depolarization vs roughness and bistatic angle
Near-backscatter geometry: incidence 20 deg, receiver tilted in the plane of incidence by the
bistatic angle. The depolarization index is 1 for a non-depolarizing (Jones) matrix and 0 for
an ideal depolarizer.""",
    """# small settings: the shapes of the next cell's call (4 materials x 11 angles), so the two
# cells share one compilation of the BRDF
ms = np.logspace(0, 4, 4 if SMALL else 25)
psi = np.radians(np.linspace(0.0, 10.0, 11 if SMALL else 41))
th = np.radians(20.0)
k_in = np.array([np.sin(th), 0.0, np.cos(th)])
k_out = np.stack([np.sin(th - psi), 0 * psi, np.cos(th - psi)], -1)
fig, axes = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
for ax, name in zip(axes, ("aluminium", "white_paint_tio2"), strict=True):
    base = ppr.load_material(name, 532e-9)
    mats = ppr.Material(n=np.full((len(ms), 1), complex(base.n)), m=ms[:, None])  # batched over m
    Mg = brdf(k_in, k_out[None], normal, mats, frame_in=ey, frame_out=ey)
    di = np.asarray(ppr.depolarization_index(Mg))
    im = ax.pcolormesh(np.degrees(psi), ms, di, vmin=0, vmax=1, shading="auto")
    ax.set_yscale("log"); ax.set_xlabel("bistatic angle [deg]"); ax.set_ylabel("Blinn-Phong m")
    ax.set_title(f"{name}: depolarization index")
fig.colorbar(im, ax=axes, label="depolarization index (1: none)");""",
    """md:Smooth metals stay polarization-preserving until the receiver leaves the specular lobe
(width about `1/sqrt(m)`); the dielectric white paint depolarizes at every roughness because
its multiple-scattering remainder is large (low single-bounce Fresnel reflectance).

## 3. Polarimetric quantities along a bistatic sweep
Diattenuation, polarizance and retardance from the Lu-Chipman decomposition for a few
finishes of aluminium.""",
    """psi = np.radians(np.linspace(0.0, 10.0, 11 if SMALL else 101))
k_out = np.stack([np.sin(th - psi), 0 * psi, np.cos(th - psi)], -1)
finishes = ("polished", "brushed", "rough", "matte")
al = ppr.load_material("aluminium", 532e-9)
m_f = np.array([float(ppr.load_material("aluminium", 532e-9, f).m) for f in finishes])
mats = ppr.Material(n=np.full((len(m_f), 1), complex(al.n)), m=m_f[:, None])  # one batched call
Ms = brdf(k_in, k_out[None], normal, mats, frame_in=ey, frame_out=ey)
lc = jax.jit(ppr.lu_chipman)(Ms)
fig, axes = plt.subplots(1, 4, figsize=(16, 3.6), constrained_layout=True)
for ax, (label, val) in zip(axes, [("M00 [1/sr]", lc.m00), ("diattenuation", lc.diattenuation),
                                   ("polarizance", lc.polarizance), ("retardance [rad]", lc.retardance)], strict=True):
    for i, finish in enumerate(finishes):
        ax.plot(np.degrees(psi), np.asarray(val)[i], label=f"{finish} (m={m_f[i]:g})")
    ax.set_title(label); ax.set_xlabel("bistatic angle [deg]")
axes[0].set_yscale("log"); axes[0].legend(fontsize=8);""",
    """md:## 4. The enhancement peak of the double bounce
Two-bounce paths and their reversed partners add in amplitude near exact backscatter
(coherent backscatter). The model writes the double term as `(1 - gamma) M_inc + gamma M_coh`
with the coherence `gamma(psi) = exp(-ln 2 |k_out - k_in|^2 / psi_h^2)`,
`psi_h = lambda / (4 d)` (d: the material's correlation length). At exact backscatter every
two-facet path is coplanar and its reversed partner has the same Jones matrix, so *every*
channel of the double term (co- and cross-polarized, linear and circular) is exactly twice
its incoherent part; away from `psi = 0` the factor follows `1 + gamma(psi)` in both channels
(left). Right: the channels themselves. Their incoherent parts are of the same order here
(the double bounce depolarizes) and vary with `psi` on the scale of the facet lobe, so a
channel divided by its own value at 5 deg (where `gamma` is already below 1e-3) is not the
enhancement factor. Transmitted H; co-pol = analyzer H, cross-pol = analyzer V (frame vector:
the lab y axis, perpendicular to the plane of incidence).""",
    """from ppr.brdf.double import coherence_factor, double_bounce_term
psi = np.radians(np.linspace(0.0, 5.0, 11 if SMALL else 101))
th = np.radians(30.0)
k_out = np.stack([np.sin(th - psi), 0 * psi, np.cos(th - psi)], -1)
k_in = np.broadcast_to(np.array([np.sin(th), 0.0, np.cos(th)]), k_out.shape)
nrm, e = np.broadcast_to(normal, k_out.shape), np.broadcast_to(ey, k_out.shape)
mat = ppr.load_material("aluminium", 532e-9, "rough")
# the full double term and its incoherent part from one compiled program
both = jax.jit(lambda *a: (double_bounce_term(*a, wavelength=532e-9), double_bounce_term(*a, coherent=False)))
M_all, M_inc = (np.asarray(M) for M in both(k_in, k_out, nrm, mat, e, e))
gamma = np.asarray(coherence_factor(k_in, k_out, 532e-9, mat.corr_length))
def co(M): return 0.5 * (M[:, 0, 0] + M[:, 0, 1] + M[:, 1, 0] + M[:, 1, 1])
def cross(M): return 0.5 * (M[:, 0, 0] + M[:, 0, 1] - M[:, 1, 0] - M[:, 1, 1])
deg = np.degrees(psi)
fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(12, 3.6), constrained_layout=True)
ax0.plot(deg, co(M_all) / co(M_inc), label="co-pol (H -> H)")
ax0.plot(deg, cross(M_all) / cross(M_inc), "--", label="cross-pol (H -> V)")
ax0.plot(deg, 1 + gamma, "k:", label="1 + gamma(psi)")
ax0.set_ylabel("double term / its incoherent part")
for f, lab, c in ((co, "co-pol", "C0"), (cross, "cross-pol", "C1")):
    ax1.plot(deg, f(M_all), color=c, label=f"{lab}")
    ax1.plot(deg, f(M_inc), "--", color=c, label=f"{lab}, incoherent part")
ax1.set_ylabel("double term [1/sr]")
for ax in (ax0, ax1):
    ax.set_xlabel("bistatic angle [deg]"); ax.legend(fontsize=8)
fig.suptitle(f"{mat.name}, corr. length {float(mat.corr_length) * 1e6:g} um, incidence 30 deg")
print("enhancement at 0 deg: co-pol", co(M_all)[0] / co(M_inc)[0], " cross-pol", cross(M_all)[0] / cross(M_inc)[0])""",
]

# ------------------------------------------------------------ 02 CubeSat simulation
CUBESAT = [
    """md:# PPR simulation of a 3U CubeSat with deployed panels

The scene file `configs/scenes/cubesat3u_panels.toml` names the shape, a material per mesh
part, the attitude and a sensor file (`configs/sensors/default.toml`: 532 nm, 100 ps FWHM
pulse, 20 ps jitter, 5 mm range bins). `ppr.simulate(scene)` returns the range-resolved
Mueller profile: each lit and visible triangle contributes its Mueller BRDF times its
projected area, spread over its range interval by the exact triangle range-area density
convolved with the Gaussian pulse. The same command line: `ppr simulate`.""",
    SETUP,
    """scene = ppr.load_scene(ROOT / "configs/scenes/cubesat3u_panels.toml")
print("parts:", scene.mesh.parts, "| faces:", scene.mesh.n_faces)
print("materials:", [f"{complex(m.n):.3g}, m={float(m.m):g}" for m in scene.materials])
print("line of sight (laser propagation):", -np.asarray(scene.sensor.laser_dir))
print("bins:", scene.bins.n_bins, "x", float(scene.bins.width) * 1e3, "mm")""",
    """md:## The Mueller profile
`data` has shape (4, 4, bins), in m^2/sr per bin, sensor frames. The range axis is the
one-way range relative to the reference point.""",
    """t0 = time.perf_counter()
prof = ppr.simulate(scene)
M = np.asarray(prof.data); r = np.asarray(prof.range_m)
print(f"simulate: {time.perf_counter() - t0:.2f} s (first call includes compilation)")
sel = M[0, 0] > 1e-6 * M[0, 0].max()
lo, hi = r[sel].min() - 0.05, r[sel].max() + 0.05
fig, axes = plt.subplots(4, 4, figsize=(12, 8), sharex=True, constrained_layout=True)
for i in range(4):
    for j in range(4):
        ax = axes[i, j]
        if i == j == 0:
            ax.plot(r, M[0, 0]); ax.set_title("M00 [m^2/sr per bin]", fontsize=9)
        else:
            with np.errstate(invalid="ignore", divide="ignore"):
                ax.plot(r, np.where(sel, M[i, j] / M[0, 0], np.nan))
            ax.set_ylim(-1.05, 1.05); ax.set_title(f"M{i}{j}/M00", fontsize=9)
        ax.set_xlim(lo, hi)
for ax in axes[-1]:
    ax.set_xlabel("range [m]")""",
    """md:## The panel-body folds: the macro double bounce
Light that meets two surfaces of the satellite before it returns (a panel and the body side
it meets at a right angle) is part of `ppr.simulate`'s profile by default
(`multibounce="auto"`: included wherever two surfaces face each other; a convex mesh has
none). `ppr.double_bounce(scene)` returns that part alone: a 90 deg fold retro-reflects, so
over a wide range of attitudes it comes back at the fold's range (docs/physics/macro_double_bounce.md).""",
    """dbl = np.asarray(ppr.double_bounce(scene).data)
print(f"double bounce: {dbl[0, 0].sum() / M[0, 0].sum():.2%} of the M00 energy at this attitude")
fig, ax = plt.subplots(figsize=(8, 3.2))
ax.plot(r, M[0, 0], label="total (single + double)")
ax.plot(r, dbl[0, 0], label="double bounce")
ax.set_xlim(lo, hi); ax.set_xlabel("range [m]"); ax.set_ylabel("M00 per bin"); ax.legend();""",
    """md:## Stokes profiles and the degree of polarization
For transmitted horizontal (H) and right-circular (R: clockwise for an observer looking
toward the laser, `S3 = -1` in ppr's Stokes sign; see `docs/physics/conventions.md`) light:
the return's degree of polarization per range bin. Facets of different parts (body, panels) sit at different ranges,
so the polarization changes along the pulse: that is the PPR signal.""",
    """st = ppr.simulate(scene, states=["H", "R"])
S = np.asarray(st.data)                      # (2 states, 4 Stokes, bins)
fig, axes = plt.subplots(1, 2, figsize=(11, 3.6), constrained_layout=True)
for k, lab in enumerate(st.labels):
    with np.errstate(invalid="ignore", divide="ignore"):
        dop = np.sqrt((S[k, 1:] ** 2).sum(0)) / S[k, 0]
    axes[0].plot(r, S[k, 0], label=f"{lab}: S0")
    axes[1].plot(r, np.where(sel, dop, np.nan), label=lab)
axes[0].set_xlim(lo, hi); axes[1].set_xlim(lo, hi)
axes[0].set_xlabel("range [m]"); axes[1].set_xlabel("range [m]")
axes[1].set_ylabel("degree of polarization"); axes[0].legend(); axes[1].legend();""",
    """md:## Energy is conserved across bin widths
The time integral of the return does not depend on the bin width (closed-form bin
integrals, no centroid sampling).""",
    """import equinox as eqx
widths = [0.005, 0.01] if SMALL else [0.005, 0.0075, 0.01, 0.02]
for w in widths:
    bins = ppr.RangeBins.centred(w, scene.bins.n_bins, float(scene.bins.reference_range))
    sc = eqx.tree_at(lambda s: s.bins, scene, bins)
    total = float(np.asarray(ppr.simulate(sc, channels=[(0, 0)]).data).sum())
    print(f"bin width {w*1e3:5.1f} mm: total M00 energy {total:.6e} m^2/sr")""",
    """md:## Attitude changes the signature
Rotating the CubeSat about the line of sight leaves M00 unchanged (up to the polarization
frame), but tilting it changes both the range profile and the polarization.""",
    """from ppr.geometry import quat_from_axis_angle, quat_multiply
q0 = np.asarray(scene.pose.quaternion)
fig, ax = plt.subplots(figsize=(8, 3.6))
for deg in ([0, 20] if SMALL else [0, 10, 20, 40]):
    dq = quat_from_axis_angle([0, 1, 0], np.radians(deg))
    q = np.asarray(quat_multiply(dq, q0))
    sc = eqx.tree_at(lambda s: s.pose, scene, ppr.Pose(q, scene.pose.position))
    ax.plot(r, np.asarray(ppr.simulate(sc, channels=[(0, 0)]).data)[0], label=f"tilt {deg} deg")
ax.set_xlim(lo, hi); ax.set_xlabel("range [m]"); ax.set_ylabel("M00 per bin"); ax.legend();""",
    """md:## A Mueller image of the same scene
`ppr image` renders what each pixel of the satellite contributes (orthographic view from the
receiver): the range profile above is the sum of these pixels along lines of constant range.""",
    """from ppr.image import QUANTITY_LABELS, render_mueller_image
img = render_mueller_image(
    scene.mesh, scene.materials,
    laser_dir=np.asarray(scene.sensor.laser_dir), receiver_dir=np.asarray(scene.sensor.receiver_dir),
    frame_tx=np.asarray(scene.sensor.frame_tx), frame_rx=np.asarray(scene.sensor.frame_rx),
    quaternion=np.asarray(scene.pose.quaternion), n_pixels=48 if SMALL else 160)
fig, axes = plt.subplots(1, 3, figsize=(13, 4), constrained_layout=True)
for ax, q in zip(axes, ("reflectance", "depolarization_index", "retardance"), strict=True):
    im = ax.imshow(img.quantities[q]); ax.set_title(QUANTITY_LABELS[q]); fig.colorbar(im, ax=ax)""",
]

# ------------------------------------------------------------ 03 classifier evaluation
CLASSIFIER = [
    """md:# Classifier evaluation: which weights recover which attribute?

The classifier compares an observed PPR vector `x` (channels x range bins) with every
template `y` of a signature database by the weighted inner product
`s = <x, W y> / (|x|_W |y|_W)`, maximized over the unknown range shift by FFT correlation.
This notebook builds a small database in memory (the database spec format of
`configs/databases/`; a fast stand-in signature model so it runs in seconds), draws held-out
noisy observations **off the attitude grid**, and measures shape / material / finish accuracy
and attitude error for each weight design, against SNR. The command-line version writes the
same numbers to disk: `ppr database build`, `ppr classify`, `ppr report`.""",
    SETUP,
    """from inversion import (WEIGHT_KINDS, NoiseModel, attitude_error_deg, bank_in_memory, classify,
                       design_weights, make_signature_fn, observe, prepare, random_quaternions,
                       spec_from_dict)

spec = spec_from_dict({
    "name": "notebook",
    "shapes": [{"name": "cube", "symmetry": "octahedral"}, {"name": "box3u", "symmetry": "dihedral:4"},
               {"name": "cylinder", "symmetry": "dihedral:12"}],
    "materials": ["aluminium", "white_paint", "silica"],
    "finishes": {"polished": 3000.0, "brushed": 100.0, "matte": 5.0},
    "grid": {"kind": "hopf", "size": 1 if SMALL else 2},
    "sensor": {"channels": "full", "n_bins": 48, "bin_width_m": 0.01},
    "chunk_rows": 256,
}, "notebook")
t0 = time.perf_counter()
bank = bank_in_memory(spec, batch=256)
print(f"{len(bank)} templates, {bank.n_channels} channels x {bank.n_bins} bins,"
      f" built in {time.perf_counter() - t0:.1f} s; grid resolution {bank.resolution_deg} deg")""",
    """md:## Held-out observations
Random attitudes (uniform on SO(3), not on the grid), random shape/material/finish, photon
noise at a given SNR, speckle, a random range offset of up to 3 bins and an unknown gain.""",
    """import jax.numpy as jnp
sig_fn = make_signature_fn(spec)
n_obs = 24 if SMALL else 200
rng = np.random.default_rng(1)
truth = {
    "shape_id": rng.integers(0, len(spec.shapes), n_obs).astype(np.int32),
    "material_id": rng.integers(0, len(spec.materials), n_obs).astype(np.int32),
    "finish_id": rng.integers(0, len(spec.finishes), n_obs).astype(np.int32),
    "attitude_id": np.zeros(n_obs, np.int32),
    "quat": np.asarray(random_quaternions(jax.random.key(7), n_obs)),
}
clean = np.asarray(sig_fn({k: jnp.asarray(v) for k, v in truth.items()}))
print("clean signatures:", clean.shape)

def draw(snr, seed0=0):
    noise = NoiseModel(snr=snr, speckle_cells=50.0, max_offset_bins=3.0, gain_min=0.1, gain_max=10.0)
    return np.stack([np.asarray(observe(c, noise, seed=seed0 + i, sensor=bank.sensor).data)
                     for i, c in enumerate(clean)])""",
    """md:## Accuracy per weight design and attribute""",
    """obs = draw(30.0)
rows = []
for kind in WEIGHT_KINDS:
    for att in ("shape", "material", "finish"):
        prep = prepare(bank, design_weights(bank, kind, att), chunk=512)
        res = classify(prep, obs, k=1)
        best = res.best(bank)
        acc = np.mean(best[f"{att}_id"] == truth[f"{att}_id"])
        rows.append((kind, att, acc, 1e3 * res.seconds / n_obs))
print(f"{'weights':8s} {'attribute':9s} accuracy  ms/obs")
for kind, att, acc, ms in rows:
    print(f"{kind:8s} {att:9s} {acc:8.2f} {ms:7.2f}")""",
    """md:## Accuracy and attitude error against SNR (Fisher weights for the shape)""",
    """prep = prepare(bank, design_weights(bank, "fisher", "shape"), chunk=512)
snrs = [10.0, 30.0, 100.0] if SMALL else [5.0, 10.0, 20.0, 30.0, 50.0, 100.0, 300.0]
acc = {a: [] for a in ("shape", "material", "finish")}
att_err = []
for snr in snrs:
    best = classify(prep, draw(snr, seed0=1000), k=1).best(bank)
    for a in acc:
        acc[a].append(np.mean(best[f"{a}_id"] == truth[f"{a}_id"]))
    ok = best["shape_id"] == truth["shape_id"]
    err = [attitude_error_deg(truth["quat"][i], best["quat"][i], spec.shapes[truth["shape_id"][i]].symmetry)
           for i in np.nonzero(ok)[0]]
    att_err.append(np.median(np.concatenate([np.atleast_1d(e) for e in err])) if err else np.nan)
fig, axes = plt.subplots(1, 2, figsize=(11, 3.6), constrained_layout=True)
for a, v in acc.items():
    axes[0].semilogx(snrs, v, "o-", label=a)
axes[0].set_xlabel("SNR"); axes[0].set_ylabel("accuracy"); axes[0].legend()
axes[1].semilogx(snrs, att_err, "o-"); axes[1].set_xlabel("SNR")
axes[1].set_ylabel("median attitude error [deg]")
axes[1].axhline(bank.resolution_deg[0], ls=":", c="k", label="grid resolution"); axes[1].legend();""",
    """md:## Confusion matrix of the shape at SNR 30""",
    """best = classify(prep, draw(30.0, seed0=2000), k=1).best(bank)
ns = len(spec.shapes)
cm = np.zeros((ns, ns), int)
np.add.at(cm, (truth["shape_id"], best["shape_id"]), 1)
fig, ax = plt.subplots(figsize=(4, 3.6))
ax.imshow(cm, cmap="Blues")
names = [s.name for s in spec.shapes]
ax.set_xticks(range(ns), names); ax.set_yticks(range(ns), names)
ax.set_xlabel("classified"); ax.set_ylabel("true")
for i in range(ns):
    for j in range(ns):
        ax.text(j, i, cm[i, j], ha="center", va="center")""",
]

# ------------------------------------------------------------ 04 inversion with MCMC
INVERSION = [
    """md:# Pose and material inversion: one call, and how far to believe it

From a noisy PPR observation of a CubeSat we recover the attitude, the roughness `m`, the
material, the range offset and the gain with one library call, `inversion.invert`: it
classifies the observation against templates of the candidate shapes, refines screened
starts (Levenberg-Marquardt, optimistix), weighs every library material by its evidence,
refits every equivalent attitude (mirror image, near symmetries), tests the fit against its
noise, names what the data cannot constrain and samples the posterior (emcee) of each mode.
The answer comes with `converged` (the solver) and `reliable` (fit acceptable, modes resolved,
chains converged) and the reasons when it is not. In small mode the forward model uses the
simulator's cheap polarizing stand-in BRDF (`glossy_fresnel_mueller`, smooth in attitude, m
and n) and a short chain, so the notebook runs in the test suite; set `PPR_SMALL=0` for the
full BRDF and a longer chain.""",
    SETUP,
    """import inversion
from ppr.pulse import glossy_fresnel_mueller

n_bins = 32
scene = ppr.Scene(ppr.shapes.cubesat(1), (ppr.Material(1.5, 10.0),), ppr.Pose([1.0, 0, 0, 0]),
                  ppr.Sensor.make(), ppr.Pulse.gaussian(100e-12), ppr.RangeBins.centred(0.01, n_bins))
channels = inversion.MeasurementModel.preset("copol").channel_matrix()
model = inversion.SimulatorModel(scene, channels, brdf=glossy_fresnel_mueller if SMALL else None, dense=True)
q_true = np.array([0.93, 0.25, 0.2, 0.17]); q_true /= np.linalg.norm(q_true)
n_true = complex(np.asarray(ppr.load_material("fused_silica").n))
unit = inversion.PhysicalParams(q_true, [20.0], [n_true], range_offset=0.003, gain=1.0)
# the simulator returns m^2/sr per bin: the gain (optics, range, detector; counts per
# m^2 sr^-1) sets the counts, here 2e5 expected in all
gain = 2e5 / float(np.asarray(model.expected(unit, model.prepare(unit))).sum())
truth = inversion.PhysicalParams(q_true, [20.0], [n_true], range_offset=0.003, gain=gain)
expected = np.asarray(model.expected(truth, model.prepare(truth)))
rng = np.random.default_rng(0)
data = rng.poisson(np.maximum(expected, 0.0)).astype(float)   # round-off below 0 set to 0
print("channels x bins:", data.shape, "| total counts:", data.sum())""",
    """md:## One call
The candidate is the cube's forward model (a mapping `name -> model`; several shapes, or a
template bank with `bank=`, work the same way). The config is validated whole, the MCMC
settings included, before anything is computed: a typo in `mcmc` costs nothing. Priors and
sampler settings come from `configs/inversion/default.toml` (the file `ppr invert` reads),
shortened in small mode. Stage timings go to the `inversion.invert` logger.""",
    """import logging
logging.basicConfig(level=logging.WARNING)
logging.getLogger("inversion.invert").setLevel(logging.INFO)
mcmc = inversion.load_mcmc_config(ROOT / "configs/inversion/default.toml")
steps = dict(n_walkers=16, n_steps=150, burn_in=50) if SMALL else dict(n_walkers=32, n_steps=2000, burn_in=500)
mcmc = mcmc.model_copy(update={"sampler": mcmc.sampler.model_copy(update={**steps, "progress": False})})
config = {
    "materials": ["aluminium", "gold", "fused_silica", "kapton"],
    "finishes": {"rough": 10.0, "glossy": 60.0},
    "grid": {"size": 2},
    "mcmc": mcmc,
}
t0 = time.perf_counter()
inv = inversion.invert(data, {"cube": model}, config=config)
print(f"invert: {time.perf_counter() - t0:.1f} s")
print()
print(inv.summary())""",
    """md:## Reading the verdict
- **Goodness of fit**: the deviance against its exact null distribution (per-bin Poisson
  moments, the fitted degrees of freedom removed): a `MODEL MISMATCH` would mean the best fit
  found does not explain the data (a shape or material the candidates lack, or an optimum
  the search missed after `escalate` extra batches of templates).
- **Modes**: the cube has mirror planes. At the attitude `P R sigma` (`P` the world mirror
  through the line of sight and the x polarization reference) the scene is the exact mirror
  image of the one at `R`: the same range profiles and Mueller profiles `D M D`,
  `D = diag(1, 1, -1, -1)`. Only the off-block Mueller elements tell the two apart and these
  co-polarized channels measure none of them: the mirror image is refit and comes out with
  half the posterior weight. A local bound (the Cramer-Rao bound, a curvature) cannot show
  this; the result is therefore not `reliable` although the solver converged.
- **Materials**: with a monostatic sensor the returning facets face the sensor, the Fresnel
  factor is the normal-incidence scalar and the unknown gain absorbs it: the probabilities
  are spread over the materials rather than a confident wrong index. The continuous index is
  reported only where the data determine it.
- **Observability**: the directions the data do not constrain are named (the roll about the
  line of sight when every return is a normal-incidence reflection; the index against the
  gain), and the uncertainties are given in the observable subspace, finite.""",
    """print("converged:", inv.converged, "| reliable:", inv.reliable)
for r in inv.reasons:
    print("  reason:", r)
print("material probabilities:", inv.material_probabilities[0])
print("mode weights:", np.round(inv.mode_weights, 3), [m.label for m in inv.modes])
print("unobservable:", inv.observability.names)""",
    """md:## Against the truth and the Cramer-Rao bound
`Inversion.compare` measures the errors against a known truth modulo the cube's exact
symmetry (and, for the line of sight, modulo the mirror image the data cannot tell).
`inversion.cramer_rao` is the bound no unbiased estimator can beat at the truth, reported in
the observable subspace.""",
    """err = inv.compare(truth, "cube")
print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in err.items() if k != "z"})
crb = inversion.cramer_rao(model, truth, inversion.PoissonCounts(), free=tuple(inv.fit.parametrisation.free))
ob_crb = crb.observability()
print("unobservable at the truth:", ob_crb.names)
i = ob_crb.labels.index("rot_x [deg]")
los_sigma = float(np.hypot(ob_crb.sigma[i], ob_crb.sigma[i + 1]))
print(f"line-of-sight error {err['los_error_mod_mirror_deg']:.3g} deg modulo the mirror image; "
      f"Cramer-Rao bound {los_sigma:.3g} deg")""",
    """md:## The posterior
One emcee chain per mode with real weight, in physical units as ArviZ `InferenceData`
(walkers as chains, the burn-in kept as warm-up) with R-hat, bulk and tail ESS and MCSE from
ArviZ. `Inversion.write(folder)` writes `invert.json` (no inf/NaN), the posterior netCDF of
each sampled mode and the fit, atomically.""",
    """import arviz as az
import tempfile
idata = inv.posterior
print(az.summary(idata, var_names=["m", "range_offset", "gain", "los_polar", "los_azimuth"]))
with tempfile.TemporaryDirectory() as d:
    written = inv.write(Path(d) / "inversion")
    print("wrote", sorted(p.name for p in written))
    if not SMALL:
        from IPython.display import Image, display
        display(Image(filename=str(Path(d) / "inversion" / "invert_corner.png")))""",
]

# ------------------------------------------------------------ 05 validation
VALIDATION = [
    """md:# Validation: the model beside its references

Every number here is computed from an independent reference written in this notebook:
closed forms (Fresnel at normal incidence and the Brewster angle, mirror limit),
quadrature (the lobe average `<h.k>+` by adaptive integration), Monte Carlo (directional
albedo: the white-furnace test), symmetry (reciprocity), and the measured error-vs-run-time
curves of the benchmarks in `bench/results/`.""",
    SETUP,
    """md:## 1. Fresnel: closed forms
Normal incidence `R = ((n-1)/(n+1))^2` (glass: 0.04), `r_p = 0` at Brewster's angle
`atan(n)` (56.31 deg for n = 1.5), and the full complex coefficients against the Hecht form
written out here.""",
    """n = 1.5
rs, rp = ppr.fresnel_amplitudes(n + 0j, 1.0)
print("normal incidence |r|^2:", abs(complex(rs))**2, "reference", ((n - 1) / (n + 1))**2)
tb = np.arctan(n)
rs, rp = ppr.fresnel_amplitudes(n + 0j, np.cos(tb))
print(f"Brewster {np.degrees(tb):.2f} deg: |r_p| = {abs(complex(rp)):.2e}")
t = np.radians(np.linspace(0, 89.9, 200))
for nc in (1.5 + 0j, 0.94 + 6.42j, 0.054 + 3.43j):
    c = np.cos(t); s2 = 1 - c**2; root = np.sqrt(nc**2 - s2)
    ref_s = (c - root) / (c + root); ref_p = (nc**2 * c - root) / (nc**2 * c + root)
    got_s, got_p = (np.asarray(v) for v in ppr.fresnel_amplitudes(nc, c))
    print(f"n = {nc}: max |r_s - ref| = {np.abs(got_s - ref_s).max():.1e}, "
          f"max |r_p - ref| = {np.abs(got_p - ref_p).max():.1e}")""",
    """md:## 2. The lobe average `<h.k>+` against adaptive quadrature
`<h.k>+ = integral over the hemisphere of max(h.k, 0) p(h) (h.n) dh` with the Blinn-Phong
density `p(h) = (m+1)/(2 pi) (h.n)^m` -- integrated here with scipy's adaptive `dblquad`
in (theta_h, phi_h) and compared with `ppr.microfacet.mean_cosine_plus`. Away from grazing
it equals `(k.n) <h.n>` exactly; near grazing it is larger.""",
    """from scipy.integrate import dblquad
def reference(m, theta):
    k = np.array([np.sin(theta), 0.0, np.cos(theta)])
    def f(ph, th):
        h = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
        return (h @ k) * (m + 1) / (2 * np.pi) * np.cos(th) ** m * np.sin(th)
    def phi_max(th):   # h.k > 0 for |phi| < phi_max: integrate the smooth part only (no kink)
        s, c = np.sin(th) * np.sin(theta), np.cos(th) * np.cos(theta)
        if s < 1e-300:
            return np.pi if c > 0 else 0.0
        return np.arccos(np.clip(-c / s, -1.0, 1.0))
    width = min(np.pi / 2, 12 / np.sqrt(m + 1))   # the lobe: integrate where it lives
    val, _ = dblquad(f, 0, width, 0, phi_max, epsabs=1e-13, epsrel=1e-10)
    return 2 * val   # phi in [-phi_max, phi_max]: twice [0, phi_max]
cases = [(1.0, 30.0), (10.0, 60.0), (100.0, 85.0)] if SMALL else \\
        [(m, t) for m in (0.5, 1.0, 10.0, 100.0, 1000.0) for t in (0.0, 45.0, 80.0, 88.0, 89.9)]
print(f"{'m':>7s} {'theta':>6s} {'ppr':>14s} {'quadrature':>14s} {'rel err':>9s}")
for m, tdeg in cases:
    got = float(ppr.microfacet.mean_cosine_plus(m, np.cos(np.radians(tdeg))))
    ref = reference(m, np.radians(tdeg))
    print(f"{m:7g} {tdeg:6.1f} {got:14.10f} {ref:14.10f} {abs(got - ref) / ref:9.1e}")""",
    """md:## 3. White furnace by Monte Carlo
For an ideal white (non-absorbing, F = 1) surface the directional albedo
`E(k_in) = integral M00(k_in, k_out) (k_out.n) dk_out` must be 1 at every incidence and
roughness. Estimated here by uniform hemisphere sampling (standard error printed).""",
    """brdf = jax.jit(ppr.mueller_brdf)
rng = np.random.default_rng(0)
n_mc = 20_000 if SMALL else 400_000
u1, u2 = rng.random(n_mc), rng.random(n_mc)
z = u1; r = np.sqrt(1 - z**2); ph = 2 * np.pi * u2
k_out = np.stack([r * np.cos(ph), r * np.sin(ph), z], -1)       # uniform on the hemisphere
normal = np.array([0.0, 0.0, 1.0])
for m in ([1.0, 10.0] if SMALL else [0.5, 1.0, 10.0, 100.0]):
    white = ppr.Material.ideal_white(m)
    for tdeg in (0.0, 60.0):
        th = np.radians(tdeg); k_in = np.array([np.sin(th), 0.0, np.cos(th)])
        g = np.asarray(brdf(k_in, k_out, normal, white)[..., 0, 0]) * z * 2 * np.pi
        se = g.std() / np.sqrt(n_mc)
        print(f"m = {m:5g}, incidence {tdeg:4.0f} deg: E = {g.mean():.4f} +- {se:.4f}")""",
    """md:## 4. Reciprocity
`M(k_in, k_out)` equals the reciprocal transform of `M(k_out, k_in)`: for the scalar part,
`M00(k_in, k_out) = M00(k_out, k_in)` exactly.""",
    """rng = np.random.default_rng(3)
def hemi(n):
    v = rng.normal(size=(n, 3)); v[:, 2] = np.abs(v[:, 2]) + 0.05
    return v / np.linalg.norm(v, axis=1, keepdims=True)
a, b = hemi(2000), hemi(2000)
mat = ppr.load_material("gold", 532e-9, "rough")
f_ab = np.asarray(brdf(a, b, normal, mat)[..., 0, 0]); f_ba = np.asarray(brdf(b, a, normal, mat)[..., 0, 0])
print("max relative reciprocity error of M00:", np.max(np.abs(f_ab - f_ba) / np.maximum(f_ab, 1e-300)))""",
    """md:## 5. Error against run time (benchmarks)
The benchmark scripts (`bench/bench_*.py`, `make bench`) write Markdown tables and PNG plots
to `bench/results/`; they are shown here as committed (rerun `make bench` to regenerate).""",
    """from IPython.display import Image, Markdown, display
results = sorted((ROOT / "bench" / "results").glob("*")) if (ROOT / "bench" / "results").exists() else []
if not results:
    print("no benchmark results committed yet: run `make bench`")
for p in results:
    if p.suffix == ".md":
        display(Markdown(f"### {p.name}\\n\\n" + p.read_text()))
    elif p.suffix == ".png" and not SMALL:
        display(Image(filename=str(p)))
print(len(results), "result files")""",
]

NOTEBOOKS = {
    "01_brdf_tour.ipynb": BRDF_TOUR,
    "02_cubesat_simulation.ipynb": CUBESAT,
    "03_classifier_evaluation.ipynb": CLASSIFIER,
    "04_inversion_mcmc.ipynb": INVERSION,
    "05_validation.ipynb": VALIDATION,
}


def execute(path: Path, timeout: float = 3600.0) -> float:
    """Run the notebook at ``path`` in full settings and store its outputs; seconds taken."""
    import nbclient

    # full settings, JAX's default compilation, matplotlib's inline backend (figures stored);
    # the compilation cache off, so the stored timings are a first run's (compilation included)
    keys = ("PPR_SMALL", "JAX_DISABLE_MOST_OPTIMIZATIONS", "MPLBACKEND", "PPR_JAX_CACHE")
    env_keep = {k: os.environ.get(k) for k in keys}
    for k in keys:
        os.environ.pop(k, None)
    os.environ["PPR_JAX_CACHE"] = "0"
    try:
        book = nbformat.read(path, as_version=4)
        t0 = time.perf_counter()
        nbclient.NotebookClient(
            book, timeout=timeout, kernel_name="python3",
            resources={"metadata": {"path": str(path.parent)}},
        ).execute()
        nbformat.write(book, path)
        return time.perf_counter() - t0
    finally:
        for k, v in env_keep.items():
            if v is not None:
                os.environ[k] = v
            else:
                os.environ.pop(k, None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--execute", nargs="*", metavar="PREFIX", default=None,
                    help="run the notebooks (all, or those whose names start with a PREFIX) "
                    "in full settings and store their outputs")
    args = ap.parse_args()
    OUT.mkdir(exist_ok=True)
    paths = []
    for name, cells in NOTEBOOKS.items():
        nbformat.write(nb(cells), OUT / name)
        paths.append(str(OUT / name))
    # the written notebooks in the project's ruff style (pyproject.toml): sorted imports, one
    # statement per line, wrapped lines; what ruff cannot fix is fixed in the sources above
    ruff = [sys.executable, "-m", "ruff"]
    subprocess.run([*ruff, "check", "--fix", "--quiet", *paths], check=False)
    subprocess.run([*ruff, "format", "--quiet", *paths], check=True)
    subprocess.run([*ruff, "check", *paths], check=True)
    for p in paths:
        print("wrote", p)
    if args.execute is not None:
        for p in map(Path, paths):
            if args.execute and not any(p.name.startswith(x) for x in args.execute):
                continue
            print(f"executed {p.name} in {execute(p):.0f} s (outputs stored)", flush=True)


if __name__ == "__main__":
    main()
