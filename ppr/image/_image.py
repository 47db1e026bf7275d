"""Per-pixel Mueller images of a mesh at a pose (the source paper's Figure 9).

An orthographic camera looks along the line of sight; one ray per pixel is cast with
trimesh's embree intersector (``trimesh.ray.ray_pyembree``; the pure-Python fallback is about
1000x slower and is refused unless asked for). At each hit the face's normal and material give
the Mueller BRDF :func:`ppr.mueller_brdf` at ``k_in`` = toward the laser and ``k_out`` = toward
the receiver, both expressed in the sensor's polarization frame. Macro shadowing: in exact
monostatic geometry a visible point is lit; with a bistatic offset a shadow ray toward the
laser decides. From the per-pixel Mueller matrices the panels show the total reflectance
``M00 cos(theta_in)`` (the pixel's return per unit projected area, 1/sr) and, from the
Lu-Chipman decomposition, depolarization index, polarizance, diattenuation and retardance.

Geometry conventions are those of :mod:`ppr.pulse._scene` (and :mod:`ppr.optics.conventions`): world
vectors ``laser_dir`` (object -> laser) and ``receiver_dir`` (object -> receiver), Stokes frame
x axes ``frame_tx``/``frame_rx`` of the transmitted and received beams, and the body-to-world
attitude quaternion ``(w, x, y, z)``. The camera is the receiver: image columns run along
``frame_rx``, rows along ``receiver_dir x frame_rx`` (row 0 at the top).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..geometry._mesh import Mesh
from ..geometry._rotation import quat_to_matrix_host
from ..optics.conventions import DEFAULT_WAVELENGTH_M

VecLike = Any  # a 3-vector (or quaternion): list, tuple or array of numbers
EXAMPLE_SATELLITE = Path(__file__).resolve().parents[1] / "data" / "example_satellite.glb"

QUANTITIES = ("reflectance", "depolarization_index", "polarizance", "diattenuation", "retardance")
QUANTITY_LABELS = {
    "reflectance": r"total reflectance $M_{00}\cos\theta_i$ [1/sr]",
    "depolarization_index": "depolarization index (1: none)",
    "polarizance": "polarizance",
    "diattenuation": "diattenuation",
    "retardance": "retardance [rad]",
}


# --------------------------------------------------------------------------- geometry helpers
def _unit(v, name: str) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) < 1e-12:
        raise ValueError(
            f"{name} must be a finite non-zero 3-vector, got {np.asarray(v).tolist()!r}"
        )
    return v / np.linalg.norm(v)


def sensor_axes(to_sensor, sensor_x=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit ``(s, x, y)`` of a beam travelling along ``s``: ``s``, the reference ``sensor_x``
    projected perpendicular to ``s``, and ``y = s x x``. Default ``sensor_x``: world z (world
    x if ``s`` is along z)."""
    s = _unit(to_sensor, "beam direction")
    if sensor_x is None:
        sensor_x = (0.0, 0.0, 1.0) if abs(s[2]) < 0.9 else (1.0, 0.0, 0.0)
    x = _unit(sensor_x, "polarization reference")
    x = x - np.dot(x, s) * s
    if np.linalg.norm(x) < 1e-6:
        raise ValueError(f"polarization reference {list(sensor_x)!r} is parallel to {s.tolist()!r}")
    x /= np.linalg.norm(x)
    return s, x, np.cross(s, x)


def _intersector(vertices: np.ndarray, faces: np.ndarray, allow_slow: bool):
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    try:
        from trimesh.ray import ray_pyembree

        if getattr(ray_pyembree, "RayMeshIntersector", None) is None:  # pragma: no cover
            raise ImportError("embree not available")
        return ray_pyembree.RayMeshIntersector(mesh)
    except (ImportError, ValueError):  # pragma: no cover - depends on the platform
        if not allow_slow:
            raise RuntimeError(
                "trimesh's embree ray intersector (package embreex) is not available; the "
                "pure-Python fallback is ~1000x slower: install embreex or pass allow_slow=True"
            ) from None
        from trimesh.ray import ray_triangle

        return ray_triangle.RayMeshIntersector(mesh)


# --------------------------------------------------------------------------------- result
@dataclasses.dataclass
class MuellerImage:
    """Per-pixel results. Arrays are ``(H, W, ...)``; pixels without a hit are NaN (part -1).

    - ``mueller``: Mueller BRDF in the sensor frames (1/sr), zero where shadowed;
    - ``cos_in``/``cos_out``: cosines of the laser/receiver directions with the shading normal;
    - ``normal``: shading normal (body frame); ``part``: part index (-1: background);
    - ``lit``: hit and not shadowed; ``u``, ``v``: pixel-centre coordinates (m) along the image
      axes ``x_axis``/``y_axis`` (body frame), ``y`` decreasing with the row index.
    """

    mueller: np.ndarray
    cos_in: np.ndarray
    cos_out: np.ndarray
    normal: np.ndarray
    part: np.ndarray
    lit: np.ndarray
    u: np.ndarray
    v: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    part_names: tuple[str, ...]
    monostatic: bool = True
    quantities: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    def arrays(self) -> dict[str, np.ndarray]:
        out = {
            "mueller": self.mueller,
            "cos_in": self.cos_in,
            "cos_out": self.cos_out,
            "normal": self.normal,
            "part": self.part,
            "lit": self.lit,
            "u": self.u,
            "v": self.v,
            "x_axis": self.x_axis,
            "y_axis": self.y_axis,
            "part_names": np.array(self.part_names),
        }
        out.update(self.quantities)
        return out

    def to_xarray(self, provenance: dict | None = None):
        """The image as a labelled ``xarray.Dataset`` (:func:`ppr.image_dataset`)."""
        from .._labelled import image_dataset  # noqa: PLC0415

        return image_dataset(self, provenance=provenance)


_POLARIMETRY_JIT: dict = {}


def _polarimetry_fn():
    """One jitted function for the four Lu-Chipman quantities (built once per process)."""
    if "fn" not in _POLARIMETRY_JIT:
        import jax

        from ..optics import polarimetry as pol  # noqa: PLC0415

        funcs = {name: getattr(pol, name) for name in QUANTITIES[1:]}

        @jax.jit
        def quantities(M):
            return {name: fn(M) for name, fn in funcs.items()}

        _POLARIMETRY_JIT["fn"] = quantities
    return _POLARIMETRY_JIT["fn"]


def polarimetric_maps(
    mueller: np.ndarray, cos_in: np.ndarray, chunk: int = 8192
) -> dict[str, np.ndarray]:
    """Total reflectance ``M00 cos(theta_in)`` and the Lu-Chipman quantities per pixel.

    Pixels with ``M00 <= 0`` (background, shadow, no reflection) are NaN in the normalized
    quantities (they have no polarization state). Evaluated in padded chunks of ``chunk``
    matrices by one jitted function (one compilation per dtype)."""
    import jax.numpy as jnp

    m00 = mueller[..., 0, 0]
    ok = np.isfinite(m00) & (m00 > 0)
    out = {"reflectance": np.where(np.isfinite(m00), m00 * cos_in, np.nan)}
    flat = mueller[ok]
    if flat.size:
        flat = flat / flat[:, :1, :1]
    for name in QUANTITIES[1:]:
        out[name] = np.full(m00.shape, np.nan)
    if not flat.size:
        return out
    n = len(flat)
    size = chunk
    fn = _polarimetry_fn()
    parts: dict[str, list] = {name: [] for name in QUANTITIES[1:]}
    for a in range(0, n, size):
        block = flat[a : a + size]
        pad = size - len(block)
        if pad:
            block = np.concatenate([block, np.broadcast_to(np.eye(4), (pad, 4, 4))])
        res = fn(jnp.asarray(block))
        for name in parts:
            parts[name].append(np.asarray(res[name], dtype=float)[: size - pad])
    for name in parts:
        out[name][ok] = np.concatenate(parts[name])
    return out


def evaluate_mueller(
    k_in: np.ndarray,
    k_out: np.ndarray,
    normal: np.ndarray,
    frame_in: np.ndarray,
    frame_out: np.ndarray,
    materials: Sequence,
    material_idx: np.ndarray,
    *,
    terms="auto",
    wavelength: float = DEFAULT_WAVELENGTH_M,
    dtype=np.float32,
    chunk: int = 8192,
    progress: bool = False,
    desc: str = "Mueller BRDF",
) -> np.ndarray:
    """:func:`ppr.mueller_brdf` over ``N`` rows (``(N, 3)`` arrays; row ``i`` uses
    ``materials[material_idx[i]]``) in padded chunks of ``chunk`` rows, so every caller with
    the same (terms, dtype, chunk) shares one compilation of the BRDF's jitted core. The
    inputs are checked on the host, chunk by chunk (a bad row raises ``ValueError`` naming
    the argument); the compiled program holds no host callback and can come from the
    persistent compilation cache. Returns ``(N, 4, 4)`` float64 (1/sr)."""
    import jax
    import jax.numpy as jnp
    from tqdm.auto import tqdm

    n = len(material_idx)
    out = np.empty((n, 4, 4))
    if n == 0:
        return out
    from ..brdf._brdf import mueller_brdf  # noqa: PLC0415
    from ..materials._material import stack_materials  # noqa: PLC0415

    arrays = [np.asarray(a, float) for a in (k_in, k_out, normal, frame_in, frame_out)]
    names = _host_terms(terms, arrays[0], arrays[1])
    # padded to 8 parts: meshes with different part counts share a compilation
    mats = stack_materials([_cast_material(m, dtype) for m in materials], multiple=8)
    idx_all = np.asarray(material_idx, np.int32)

    def evaluate(ki, ko, nr, fi, fo, idx, mats):
        # eager call on concrete chunks: the input checks run on the host (a bad row raises
        # here, naming the argument) and the jitted core holds no host callback, so its
        # program goes to the persistent compilation cache (``ppr`` CLI)
        mat = jax.tree_util.tree_map(lambda a: a[idx], mats)
        return mueller_brdf(
            ki, ko, nr, mat, terms=names, frame_in=fi, frame_out=fo, wavelength=wavelength
        )

    for a in tqdm(range(0, n, chunk), desc=desc, unit="chunk", disable=not progress):
        b = min(a + chunk, n)
        pad = chunk - (b - a)

        def block(x, pad=pad, a=a, b=b):
            x = x[a:b]
            if pad:
                x = np.concatenate([x, np.broadcast_to(x[:1], (pad, *x.shape[1:]))])
            return x

        res = evaluate(
            *(jnp.asarray(block(x), dtype) for x in arrays), jnp.asarray(block(idx_all)), mats
        )
        out[a:b] = np.asarray(res, dtype=float)[: b - a]
    return out


def _host_terms(terms, k_in: np.ndarray, k_out: np.ndarray):
    """``terms`` with the double term taken from the exact-backscatter table when every row
    is within its ``PSI_MAX`` of backscatter (a monostatic sensor), else from its quadrature
    (``"double:quadrature"``; ``"auto"`` unchanged), decided here on the host as
    :func:`ppr.pulse._pulse.sensor_terms` does for ``ppr.render``: the run-time dispatch would
    pick the same branch, but its compiled program also holds the other one (the table with
    the quadrature: about 3x the compilation time)."""
    from ..brdf._brdf import mueller_brdf  # noqa: PLC0415
    from ..brdf.double_table import PSI_MAX  # noqa: PLC0415
    from ..pulse._pulse import _quadrature_terms, backscatter_terms  # noqa: PLC0415

    bs = backscatter_terms(mueller_brdf, terms)
    if bs is None:
        return terms
    dk = k_out - k_in
    if np.all(np.sum(dk * dk, axis=-1) <= (2.0 * np.sin(0.5 * PSI_MAX)) ** 2):
        return bs
    return _quadrature_terms(terms, bs)


def _host_mesh(mesh, smooth: bool):
    """``(vertices float64, faces int64, part ids, part names, vertex normals or None)`` of a
    :class:`ppr.Mesh` on the host; vertex normals (trimesh's area-weighted) if ``smooth``."""
    verts = np.asarray(mesh.vertices, float)
    faces = np.asarray(mesh.faces, np.int64)
    vn = None
    if smooth:
        import trimesh

        vn = np.asarray(trimesh.Trimesh(verts, faces, process=False).vertex_normals, float)
    return verts, faces, np.asarray(mesh.material_ids, np.int64), tuple(mesh.parts), vn


def render_mueller_image(
    mesh: Mesh,
    materials: Sequence,
    *,
    laser_dir: VecLike,
    receiver_dir: VecLike | None = None,
    frame_tx: VecLike | None = None,
    frame_rx: VecLike | None = None,
    quaternion: VecLike = (1.0, 0.0, 0.0, 0.0),
    n_pixels: int = 128,
    half_width: float | None = None,
    wavelength: float = DEFAULT_WAVELENGTH_M,
    terms="auto",
    shading: str = "flat",
    chunk: int = 8192,
    dtype=np.float32,
    progress: bool = False,
    allow_slow: bool = False,
) -> MuellerImage:
    """Render the per-pixel Mueller BRDF of ``mesh`` (one material per part) at a pose.

    Directions and frames are world vectors as in :class:`ppr.Sensor` (see
    :mod:`ppr.pulse._scene`): the camera is the receiver, looking along ``-receiver_dir``.
    Faces are two-sided here (the side facing the camera is shaded), unlike
    :func:`ppr.simulate`, whose faces return light only on their outward side.

    **Arguments:**

    - `mesh`: :class:`ppr.Mesh` in the body frame (metres).
    - `materials`: one :class:`ppr.Material` per ``mesh.parts`` entry.
    - `laser_dir`: unit vector from the object toward the laser (every pixel's ``k_in``).
    - `receiver_dir`: unit vector from the object toward the receiver (``k_out``); default
      ``laser_dir`` (monostatic: every visible point is lit). Otherwise a shadow ray toward
      the laser decides whether a visible point is lit.
    - `frame_tx`, `frame_rx`: x axes of the transmitted (along ``-laser_dir``) and received
      (along ``+receiver_dir``) beams' Stokes frames; default world z projected (world x if a
      beam is along z). The image's columns run along ``frame_rx`` and its rows along
      ``receiver_dir x frame_rx`` (up).
    - `quaternion`: body-to-world attitude ``(w, x, y, z)``.
    - `n_pixels`: image is ``n_pixels x n_pixels``.
    - `half_width`: half the field of view (m); default: the mesh's bounding radius x 1.05.
    - `wavelength`: metres. `terms`: BRDF terms (``"auto"``, ``None`` for all, or names).
    - `shading`: ``"flat"`` (face normals) or ``"smooth"`` (barycentric interpolation of the
      mesh's area-weighted vertex normals).
    - `chunk`: pixels per BRDF call (fixed, padded: one compilation).
    - `dtype`: float dtype of the BRDF evaluation (float32 default).

    **Returns:** a :class:`MuellerImage` with the polarimetric maps in ``quantities``.
    """

    if len(materials) != len(mesh.parts):
        raise ValueError(
            f"need one material per part {list(mesh.parts)}, got {len(materials)} materials"
        )
    if shading not in ("flat", "smooth"):
        raise ValueError(f"shading must be 'flat' or 'smooth', got {shading!r}")
    if not (isinstance(n_pixels, int | np.integer) and 1 <= n_pixels <= 4096):
        raise ValueError(f"n_pixels must be an integer in [1, 4096], got {n_pixels!r}")

    # Work in the body frame: rotate the sensor directions by R^T.
    q = np.asarray(quaternion, dtype=float)
    if q.shape != (4,):
        raise ValueError(f"quaternion must be 4 numbers (w, x, y, z), got {q.tolist()!r}")
    rot = quat_to_matrix_host(q)
    u_in = _unit(laser_dir, "laser_dir")
    u_out = u_in if receiver_dir is None else _unit(receiver_dir, "receiver_dir")
    if np.dot(u_in, u_out) <= 0:
        raise ValueError("receiver_dir is more than 90 deg from laser_dir")
    monostatic = bool(np.allclose(u_in, u_out, rtol=0.0, atol=1e-12))
    _, x_tx_w, _ = sensor_axes(u_in, frame_tx)
    s_w, x_w, y_w = sensor_axes(u_out, frame_rx)
    s, x_ax, y_ax = rot.T @ s_w, rot.T @ x_w, rot.T @ y_w
    s_tx = rot.T @ u_in
    # Stokes frame x axes of the transmitted beam (travelling along -s_tx) and the received
    # one (travelling along +s), body frame.
    x_in = rot.T @ x_tx_w
    x_out = x_ax

    verts, faces, part_ids, part_names, vertex_normals = _host_mesh(mesh, shading == "smooth")
    centre = 0.5 * (verts.min(0) + verts.max(0))
    radius = float(np.max(np.linalg.norm(verts - centre, axis=1)))
    hw = 1.05 * radius if half_width is None else float(half_width)
    if not (np.isfinite(hw) and hw > 0):
        raise ValueError(f"half_width must be > 0 metres, got {half_width!r}")
    step = 2 * hw / n_pixels
    u = (np.arange(n_pixels) + 0.5) * step - hw
    v = hw - (np.arange(n_pixels) + 0.5) * step
    uu, vv = np.meshgrid(u, v)  # (H, W): rows along -y, columns along +x
    c_uv = centre - np.dot(centre, s) * s
    far = float(np.dot(centre, s)) + 2 * radius + 1.0
    origins = c_uv[None] + uu.reshape(-1, 1) * x_ax + vv.reshape(-1, 1) * y_ax + far * s
    dirs = np.broadcast_to(-s, origins.shape)

    inter = _intersector(verts, faces, allow_slow)
    tri, ray, loc = inter.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
    # (integer indices even when no ray hits: an empty result may come back as floats)
    tri, ray = np.asarray(tri, np.int64), np.asarray(ray, np.int64)
    loc = np.asarray(loc, np.float64).reshape(-1, 3)

    tris = verts[faces[tri]]
    fn = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    # two-sided surfaces: the side facing the receiver is the one seen
    flip = np.sum(fn * s, axis=1) < 0
    fn[flip] *= -1
    if shading == "smooth":
        import trimesh

        bary = trimesh.triangles.points_to_barycentric(tris, loc)
        vn = vertex_normals[faces[tri]]
        nrm = np.einsum("ij,ijk->ik", bary, vn)
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        nrm[flip] *= -1
    else:
        nrm = fn

    lit = np.ones(len(tri), dtype=bool)
    if not monostatic and len(tri):
        eps = 1e-5 * max(radius, 1e-3)
        sh_orig = loc + eps * fn
        lit = ~np.asarray(inter.intersects_any(sh_orig, np.broadcast_to(s_tx, sh_orig.shape)))
    cos_in_hit = np.sum(nrm * s_tx, axis=1)
    cos_out_hit = np.sum(nrm * s, axis=1)
    lit &= (cos_in_hit > 0) & (cos_out_hit > 0)

    n_pix = n_pixels * n_pixels
    mueller = np.full((n_pix, 4, 4), np.nan)
    pid = part_ids[tri]
    sel = np.nonzero(lit)[0]
    mueller[ray] = 0.0
    if len(sel):
        n_sel = len(sel)
        mueller[ray[sel]] = evaluate_mueller(
            np.broadcast_to(s_tx, (n_sel, 3)),
            np.broadcast_to(s, (n_sel, 3)),
            nrm[sel],
            np.broadcast_to(x_in, (n_sel, 3)),
            np.broadcast_to(x_out, (n_sel, 3)),
            materials,
            pid[sel],
            terms=terms,
            wavelength=wavelength,
            dtype=dtype,
            chunk=chunk,
            progress=progress,
        )

    def to_img(vals, fill, shape=(), dtype=None):
        # the dtype is given where no ray may hit (an empty `vals` has no meaningful one)
        dt = np.asarray(vals).dtype if dtype is None else dtype
        img = np.full((n_pix, *shape), fill, dtype=dt)
        img[ray] = vals
        return img.reshape(n_pixels, n_pixels, *shape)

    cos_in = to_img(cos_in_hit, np.nan, dtype=mueller.dtype)
    result = MuellerImage(
        mueller=mueller.reshape(n_pixels, n_pixels, 4, 4),
        cos_in=cos_in,
        cos_out=to_img(cos_out_hit, np.nan, dtype=mueller.dtype),
        normal=to_img(nrm, np.nan, (3,), dtype=mueller.dtype),
        part=to_img(pid, -1, dtype=np.int64),
        lit=to_img(lit, False, dtype=bool),
        u=u,
        v=v,
        x_axis=x_ax,
        y_axis=y_ax,
        part_names=part_names,
        monostatic=monostatic,
    )
    result.quantities = polarimetric_maps(result.mueller, np.where(result.lit, cos_in, 0.0))
    return result


def _cast_material(mat, dtype):
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    cdtype = jnp.complex64 if np.dtype(dtype) == np.float32 else jnp.complex128

    def cast(x):
        if not eqx.is_array(x):
            return x
        if jnp.issubdtype(x.dtype, jnp.complexfloating):
            return x.astype(cdtype)
        if jnp.issubdtype(x.dtype, jnp.floating):
            return x.astype(dtype)
        return x

    return jax.tree_util.tree_map(cast, mat)


# ------------------------------------------------------------------------------- plotting
def plot_mueller_image(img: MuellerImage, path: str | Path, title: str = "") -> Path:
    """Write the five panels (reflectance, depolarization index, polarizance, diattenuation,
    retardance) with colour bars to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    du = img.u[1] - img.u[0] if len(img.u) > 1 else 1.0
    extent = (img.u[0] - du / 2, img.u[-1] + du / 2, img.v[-1] - du / 2, img.v[0] + du / 2)
    fig, axes = plt.subplots(1, 5, figsize=(20, 4.2))
    fig.subplots_adjust(left=0.04, right=0.98, bottom=0.13, top=0.84, wspace=0.35)
    for ax, name in zip(axes, QUANTITIES, strict=True):
        data = img.quantities[name]
        if name == "reflectance":
            from matplotlib.colors import LogNorm

            finite = data[np.isfinite(data) & (data > 0)]
            vmax = float(finite.max()) if finite.size else 1.0
            cmap = plt.get_cmap("inferno").with_extremes(under="black")
            kw = {"norm": LogNorm(vmin=vmax * 1e-4, vmax=vmax), "cmap": cmap}
        elif name == "retardance":
            kw = {"vmin": 0.0, "vmax": np.pi, "cmap": "magma"}
        else:
            kw = {"vmin": 0.0, "vmax": 1.0, "cmap": "viridis"}
        ax.set_facecolor("0.85")
        im = ax.imshow(
            np.ma.masked_invalid(data), extent=extent, origin="upper", interpolation="nearest", **kw
        )
        ax.set_title(QUANTITY_LABELS[name], fontsize=10)
        ax.set_xlabel("image x [m]")
        ax.set_ylabel("image y [m]")
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
    if title:
        fig.suptitle(title)
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_mueller_elements(img: MuellerImage, path: str | Path, title: str = "") -> Path:
    """Write the Mueller image as a 4x4 grid: ``M00`` (1/sr) and the normalized elements
    ``M_ij / M00`` (one shared colour bar, -1..1)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    m = img.mueller
    m00 = m[..., 0, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        norm = np.where((m00 > 0)[..., None, None], m / m00[..., None, None], np.nan)
    fig, axes = plt.subplots(4, 4, figsize=(10, 9.2))
    fig.subplots_adjust(left=0.02, right=0.86, bottom=0.02, top=0.92, wspace=0.05, hspace=0.15)
    im_n = im_0 = None
    for i in range(4):
        for j in range(4):
            ax = axes[i, j]
            ax.set_facecolor("0.85")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == j == 0:
                finite = m00[np.isfinite(m00) & (m00 > 0)]
                vmax = float(np.percentile(finite, 99)) if finite.size else 1.0
                im_0 = ax.imshow(
                    np.ma.masked_invalid(m00),
                    vmin=0,
                    vmax=vmax,
                    cmap="inferno",
                    interpolation="nearest",
                )
                ax.set_title(r"$M_{00}$ [1/sr]", fontsize=9)
            else:
                im_n = ax.imshow(
                    np.ma.masked_invalid(norm[..., i, j]),
                    vmin=-1,
                    vmax=1,
                    cmap="RdBu_r",
                    interpolation="nearest",
                )
                ax.set_title(rf"$M_{{{i}{j}}}/M_{{00}}$", fontsize=9)
    fig.colorbar(im_n, cax=fig.add_axes([0.89, 0.1, 0.02, 0.55]), label=r"$M_{ij}/M_{00}$")
    fig.colorbar(im_0, cax=fig.add_axes([0.89, 0.72, 0.02, 0.2]), label=r"$M_{00}$ [1/sr]")
    if title:
        fig.suptitle(title)
    path = Path(path)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path
