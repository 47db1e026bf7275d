"""Generate ``ppr/data/example_satellite.glb``: a small satellite-like mesh made by the project.

Parts (one named geometry each, so per-part materials can be assigned from a config):

- ``bus``: a 1.0 x 1.0 x 1.4 m box (white paint);
- ``panels``: two deployed solar-panel wings, 2.4 x 0.9 x 0.03 m each, on short yokes
  (cover glass over cells);
- ``mast``: a 1.0 m aluminium mast on the +z face;
- ``dish``: a 0.9 m diameter paraboloid antenna dish (f/D = 0.35) at the top of the mast,
  facing +x (aluminium);
- ``blanket``: a wrinkled thermal-blanket cylinder (radius 0.35 m, length 0.6 m) on the -z
  face (Kapton-on-aluminium MLI), wrinkles from a seeded sum of sinusoids of 0.5-2 cm amplitude.

Units are metres; the body frame has its origin at the bus centre. Run with
``python scripts/make_example_satellite.py`` (deterministic; rewrites the file).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

OUT = Path(__file__).resolve().parents[1] / "ppr" / "data" / "example_satellite.glb"


def bus() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(1.0, 1.0, 1.4))


def panels() -> trimesh.Trimesh:
    parts = []
    for sign in (-1.0, 1.0):
        wing = trimesh.creation.box(extents=(0.9, 2.4, 0.03))
        wing.apply_translation((0.0, sign * (0.5 + 0.25 + 1.2), 0.0))
        yoke = trimesh.creation.box(extents=(0.06, 0.25, 0.06))
        yoke.apply_translation((0.0, sign * (0.5 + 0.125), 0.0))
        parts += [wing, yoke]
    return trimesh.util.concatenate(parts)


def mast() -> trimesh.Trimesh:
    m = trimesh.creation.cylinder(radius=0.03, height=1.0, sections=16)
    m.apply_translation((0.0, 0.0, 0.7 + 0.5))
    return m


def dish(diameter: float = 0.9, f_over_d: float = 0.35, n_r: int = 12, n_t: int = 48):
    """Paraboloid shell x = -r^2 / (4 f) (vertex at the mast top, opening toward +x)."""
    f = f_over_d * diameter
    r = np.linspace(0.0, diameter / 2, n_r + 1)[1:]
    t = np.linspace(0.0, 2 * np.pi, n_t, endpoint=False)
    rr, tt = np.meshgrid(r, t, indexing="ij")
    x = rr**2 / (4 * f)
    y = rr * np.cos(tt)
    z = rr * np.sin(tt)
    verts = np.concatenate([[[0.0, 0.0, 0.0]], np.stack([x, y, z], -1).reshape(-1, 3)])
    faces = []
    for j in range(n_t):  # central fan
        faces.append((0, 1 + j, 1 + (j + 1) % n_t))
    for i in range(n_r - 1):
        for j in range(n_t):
            a = 1 + i * n_t + j
            b = 1 + i * n_t + (j + 1) % n_t
            c = 1 + (i + 1) * n_t + j
            d = 1 + (i + 1) * n_t + (j + 1) % n_t
            faces += [(a, c, d), (a, d, b)]
    shell = trimesh.Trimesh(verts, np.array(faces), process=False)
    # two-sided thin shell: add the back side with reversed winding, offset by 5 mm
    back = trimesh.Trimesh(verts - np.array([0.005, 0, 0]), np.array(faces)[:, ::-1], process=False)
    d = trimesh.util.concatenate([shell, back])
    # the dish opens toward +x: the concave side faces +x
    d.apply_translation((0.05, 0.0, 0.7 + 1.0))
    return d


def blanket(radius: float = 0.35, length: float = 0.6, n_t: int = 96, n_z: int = 24, seed: int = 7):
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 2 * np.pi, n_t, endpoint=False)
    z = np.linspace(0.0, length, n_z + 1)
    tt, zz = np.meshgrid(t, z, indexing="ij")
    dr = np.zeros_like(tt)
    for _ in range(12):  # wrinkles: a seeded sum of sinusoids (0.5-2 cm)
        amp = rng.uniform(0.005, 0.02)
        kt = rng.integers(3, 20)
        kz = rng.uniform(2.0, 12.0)
        ph1, ph2 = rng.uniform(0, 2 * np.pi, 2)
        dr += amp * np.sin(kt * tt + ph1) * np.sin(kz * zz + ph2)
    rr = radius + dr
    verts = np.stack([rr * np.cos(tt), rr * np.sin(tt), -0.7 - zz], -1).reshape(-1, 3)
    faces = []
    for i in range(n_t):
        for j in range(n_z):
            a = i * (n_z + 1) + j
            b = ((i + 1) % n_t) * (n_z + 1) + j
            faces += [(a, b + 1, b), (a, a + 1, b + 1)]  # outward winding
    faces = np.array(faces)
    # end cap at the far end (flat disc)
    centre = len(verts)
    verts = np.concatenate([verts, [[0.0, 0.0, -0.7 - length]]])
    cap = [(centre, ((i + 1) % n_t) * (n_z + 1) + n_z, i * (n_z + 1) + n_z) for i in range(n_t)]
    faces = np.concatenate([faces, np.array(cap)])
    return trimesh.Trimesh(verts, faces, process=False)


def build() -> trimesh.Scene:
    scene = trimesh.Scene()
    for name, geom in (
        ("bus", bus()),
        ("panels", panels()),
        ("mast", mast()),
        ("dish", dish()),
        ("blanket", blanket()),
    ):
        scene.add_geometry(geom, geom_name=name, node_name=name)
    return scene


def main() -> None:
    scene = build()
    OUT.parent.mkdir(parents=True, exist_ok=True)
    scene.export(OUT)
    n = sum(len(g.faces) for g in scene.geometry.values())
    print(f"wrote {OUT} ({n} faces, parts: {', '.join(scene.geometry)})")


if __name__ == "__main__":
    main()
