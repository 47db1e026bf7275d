r"""A cheap, physically shaped stand-in signature model (convex facet shapes, jittable).

This is *not* the ppr forward model (that is ``ppr.simulate``; see ``inversion._ppr_adapter``);
it exists so that the database, classifier and report can be built and tested with a
signature function that has the right structure and cost profile:

- convex shapes (plate, 1U cube, 3U box, 12-sided cylinder) as lists of flat facets with
  centre, normal, area and in-plane second moment ``S`` (so the depth variance of a facet
  along the line of sight ``k`` is ``k^T R S R^T k``);
- monostatic sensor looking along world ``-z`` (``k = +z`` points from target to sensor),
  Stokes frame x axis along world ``x``; range of a point ``p`` is ``-p . k``; bin ``b`` is
  centred at ``(b + 1/2 - n_bins/2) * bin_width``;
- per visible facet (``cos t = N . k > 0``) three Mueller terms: a mirror-like backscatter
  lobe ``A (m+2)/(8 pi) cos^m t R0 diag(1, 1, -1, -1)`` (Blinn-Phong ``p(h = k)`` over
  ``4 <h.n>``), a roughness-driven dihedral-like double reflection
  ``A cos^2 t g(m) R(-a) F45 F45 R(a)`` (Fresnel Mueller at 45 deg twice, rotated to the
  facet's azimuth ``a`` in the sensor frame: this is what couples attitude into polarization)
  and a depolarizing diffuse term ``A cos^2 t rho_d / pi diag(1, 0, 0, 0)``;
- each facet's contribution is a Gaussian in range (pulse plus facet depth spread)
  integrated exactly over the bins with ``erf``.

Every shape is symmetric under its ``symmetry`` group, so ``q`` and ``q g`` give the same
signature (tested).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ppr import fresnel_mueller_params, quat_to_matrix
from ppr.optics.conventions import C_LIGHT

from ._noise import MeasurementModel

# name: (n_re, n_im, diffuse albedo rho_d); optical constants at 532 nm: docs/physics.md#materials
SYNTHETIC_MATERIALS: dict[str, tuple[float, float, float]] = {
    "aluminium": (0.94, 6.42, 0.03),
    "gold": (0.54, 2.23, 0.03),
    "silica": (1.461, 0.0, 0.02),
    "white_paint": (2.67, 0.0, 0.8),
}

SYNTHETIC_SHAPES = {
    "plate": "dihedral:4",
    "cube": "octahedral",
    "box3u": "dihedral:4",
    "cylinder": "dihedral:12",
}


def _rect(center, e1, e2):
    center, e1, e2 = (np.asarray(v, float) for v in (center, e1, e2))
    n = np.cross(e1, e2)
    area = np.linalg.norm(n)
    s = (np.outer(e1, e1) + np.outer(e2, e2)) / 12.0
    return center, n / area, area, s


def _box(ax, ay, az):
    facets = []
    half = np.array([ax, ay, az]) / 2
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        e1 = np.zeros(3)
        e1[u] = 2 * half[u]
        e2 = np.zeros(3)
        e2[v] = 2 * half[v]
        for sign in (1.0, -1.0):
            c = np.zeros(3)
            c[axis] = sign * half[axis]
            facets.append(_rect(c, e1 if sign > 0 else e2, e2 if sign > 0 else e1))
    return facets


def shape_facets(name: str) -> list:
    """Facets (centre, unit normal, area, second moment) of a synthetic shape (metres)."""
    if name == "plate":  # 0.3 m square panel, 5 mm thick (rims keep edge-on views non-empty)
        return _box(0.3, 0.3, 0.005)
    if name == "cube":
        return _box(0.1, 0.1, 0.1)
    if name == "box3u":
        return _box(0.1, 0.1, 0.34)
    if name == "cylinder":
        n_side, r, h = 12, 0.08, 0.3
        facets = []
        w = 2 * r * math.sin(math.pi / n_side)
        rc = r * math.cos(math.pi / n_side)
        for i in range(n_side):
            phi = 2 * math.pi * i / n_side
            nrm = np.array([math.cos(phi), math.sin(phi), 0.0])
            tang = np.array([-math.sin(phi), math.cos(phi), 0.0])
            facets.append(_rect(rc * nrm, tang * w, [0, 0, h]))
        area = 0.5 * n_side * r * r * math.sin(2 * math.pi / n_side)
        s = r * r / 4 * np.diag([1.0, 1.0, 0.0])
        for sign in (1.0, -1.0):
            facets.append((np.array([0, 0, sign * h / 2]), np.array([0, 0, sign]), area, s))
        return facets
    raise ValueError(f"unknown synthetic shape {name!r}; known: {sorted(SYNTHETIC_SHAPES)}")


class SyntheticSignatures:
    """Signature function ``params -> (batch, n_channels, n_bins)`` of the stand-in model.

    **Arguments:**

    - `shapes`, `materials`: names (ids index these lists); `finishes`: Blinn-Phong ``m``
      per finish id.
    - `measurement`: PSG/PSA channels; `n_bins`, `bin_width_m`: range bins; `pulse_fwhm_s`.

    ``params`` holds int arrays ``shape_id``, ``material_id``, ``finish_id`` (batch,) and
    ``quat`` (batch, 4) (body to world, scalar first). Output dtype follows ``quat``.
    """

    def __init__(
        self,
        shapes,
        materials,
        finishes,
        measurement: MeasurementModel,
        n_bins: int = 64,
        bin_width_m: float = 0.01,
        pulse_fwhm_s: float = 100e-12,
    ):
        if len(shapes) == 0 or len(materials) == 0 or len(finishes) == 0:
            raise ValueError("SyntheticSignatures needs at least one shape, material and finish")
        bad = [m for m in materials if m not in SYNTHETIC_MATERIALS]
        if bad:
            raise ValueError(
                f"unknown synthetic materials {bad}; known: {sorted(SYNTHETIC_MATERIALS)}"
            )
        self.shapes, self.materials = tuple(shapes), tuple(materials)
        self.finishes = tuple(float(m) for m in finishes)
        self.measurement = measurement
        self.n_bins, self.bin_width_m, self.pulse_fwhm_s = (
            int(n_bins),
            float(bin_width_m),
            float(pulse_fwhm_s),
        )
        facets = [shape_facets(s) for s in self.shapes]
        f_max = max(len(f) for f in facets)
        n_s = len(self.shapes)
        self._centre = np.zeros((n_s, f_max, 3))
        self._normal = np.tile([0.0, 0.0, 1.0], (n_s, f_max, 1))
        self._area = np.zeros((n_s, f_max))
        self._moment = np.zeros((n_s, f_max, 3, 3))
        for i, fl in enumerate(facets):
            for j, (c, n, a, s) in enumerate(fl):
                self._centre[i, j], self._normal[i, j], self._area[i, j], self._moment[i, j] = (
                    c,
                    n,
                    a,
                    s,
                )
        self._mat = np.asarray([SYNTHETIC_MATERIALS[m] for m in self.materials])
        self._chan = measurement.channel_matrix()

    @property
    def n_channels(self) -> int:
        return self.measurement.n_channels

    @property
    def sensor(self) -> dict:
        return {
            "model": "synthetic-v1",
            "channels": self.measurement.fingerprint(),
            "n_bins": self.n_bins,
            "bin_width_m": self.bin_width_m,
            "pulse_fwhm_s": self.pulse_fwhm_s,
        }

    def __call__(self, params: dict) -> Float[Array, "batch channels bins"]:
        quat = jnp.asarray(params["quat"])
        dt = quat.dtype if jnp.issubdtype(quat.dtype, jnp.floating) else jnp.result_type(float)
        tables = {
            "centre": self._centre,
            "normal": self._normal,
            "area": self._area,
            "moment": self._moment,
            "mat": self._mat,
            "finish": np.asarray(self.finishes),
            "chan": self._chan,
        }
        tables = {k: jnp.asarray(v, dt) for k, v in tables.items()}
        sigma_r = C_LIGHT * self.pulse_fwhm_s / (2 * math.sqrt(8 * math.log(2))) / 2
        return _kernel_jit(
            params["shape_id"],
            params["material_id"],
            params["finish_id"],
            quat.astype(dt),
            tables,
            jnp.asarray(sigma_r, dt),
            jnp.asarray(self.bin_width_m, dt),
            n_bins=self.n_bins,
        )


def _rot_mueller(c2, s2):
    z, o = jnp.zeros_like(c2), jnp.ones_like(c2)
    return jnp.stack(
        [
            jnp.stack([o, z, z, z], -1),
            jnp.stack([z, c2, s2, z], -1),
            jnp.stack([z, -s2, c2, z], -1),
            jnp.stack([z, z, z, o], -1),
        ],
        -2,
    )


def _synthetic_kernel(shape_id, material_id, finish_id, quat, t, sigma_r, bin_w, *, n_bins):
    def one(sid, mid, fid, q):
        rot = quat_to_matrix(q)
        normal = t["normal"][sid] @ rot.T  # (F, 3) world
        centre = t["centre"][sid] @ rot.T
        area = t["area"][sid]
        kb = rot[2]  # body-frame line of sight: R^T e_z
        var_depth = jnp.einsum("i,fij,j->f", kb, t["moment"][sid], kb)
        cos_t = normal[:, 2]
        vis = (cos_t > 1e-6) & (area > 0)
        ct = jnp.where(vis, cos_t, 0.5)
        n_re, n_im, rho_d = t["mat"][mid]
        m = t["finish"][fid]
        # mirror-like backscatter lobe, Blinn-Phong p(h=k)/(4 <h.n>)
        lobe = (m + 2) / (8 * jnp.pi) * jnp.exp(m * jnp.log(ct))
        a0, _, _, _ = fresnel_mueller_params(n_re, n_im, jnp.ones_like(n_re))
        mirror = jnp.diag(jnp.stack([a0, a0, -a0, -a0]))
        # dihedral-like double reflection at 45 deg, at the facet's azimuth
        a, b, c, d = fresnel_mueller_params(n_re, n_im, jnp.sqrt(0.5) * jnp.ones_like(n_re))
        f45 = jnp.array([[a, b, 0, 0], [b, a, 0, 0], [0, 0, c, d], [0, 0, -d, c]])
        f2 = f45 @ f45
        nx, ny = normal[:, 0], normal[:, 1]
        r2 = jnp.maximum(nx * nx + ny * ny, 1e-30)
        c2, s2 = (nx * nx - ny * ny) / r2, 2 * nx * ny / r2
        dbl = _rot_mueller(c2, -s2) @ f2 @ _rot_mueller(c2, s2)  # (F, 4, 4)
        g_m = 0.3 / (1 + m / 50.0)
        diffuse = jnp.zeros((4, 4), ct.dtype).at[0, 0].set(rho_d / jnp.pi)
        w_lobe = jnp.where(vis, area * lobe, 0.0)
        w_cos2 = jnp.where(vis, area * ct * ct, 0.0)
        mueller = (
            w_lobe[:, None, None] * mirror
            + (w_cos2 * g_m)[:, None, None] * dbl
            + w_cos2[:, None, None] * diffuse
        )
        chan = jnp.einsum("kij,fij->fk", t["chan"], mueller)  # (F, C)
        r = -centre[:, 2]
        sig = jnp.sqrt(sigma_r**2 + var_depth)
        edges = (jnp.arange(n_bins + 1, dtype=ct.dtype) - n_bins / 2) * bin_w
        cdf = 0.5 * (
            1
            + jax.scipy.special.erf((edges[None, :] - r[:, None]) / (jnp.sqrt(2.0) * sig[:, None]))
        )
        prof = cdf[:, 1:] - cdf[:, :-1]  # (F, B)
        return jnp.einsum("fk,fb->kb", chan, prof)

    return jax.vmap(one)(shape_id, material_id, finish_id, quat)


_kernel_jit = jax.jit(_synthetic_kernel, static_argnames=("n_bins",))  # shared compile cache


def point_lobe_signatures(points, normals, quats, n_bins: int = 32) -> np.ndarray:
    """A smooth toy signature model in NumPy (tests and benches of the template fit): point
    scatterers at body positions ``points`` ``(K, 3)`` with unit ``normals``, each returning
    ``1 + cos/2`` (the cosine between its rotated normal and the line of sight +z) at depth
    ``-3 z`` bins from the centre, a Gaussian pulse of 2.5 bins integrated over each bin; two
    channels, the second weighted by ``n_x^2 + 0.1`` (attitude-dependent, as polarization is).
    ``quats`` ``(N, 4)`` body -> sensor, scalar first. Returns ``(N, 2, n_bins)`` profiles
    summing to 1."""
    from scipy.special import erf

    rot = np.asarray(quat_to_matrix(np.asarray(quats, np.float64)), np.float64)
    p = np.einsum("nij,kj->nki", rot, np.asarray(points, np.float64))
    nn = np.einsum("nij,kj->nki", rot, np.asarray(normals, np.float64))
    depth = -3.0 * p[..., 2] + n_bins / 2
    cdf = 0.5 * (1 + erf((np.arange(n_bins + 1) - depth[..., None]) / (2.5 * np.sqrt(2))))
    weight = np.stack([np.ones_like(nn[..., 0]), nn[..., 0] ** 2 + 0.1], -1)
    out = np.einsum("nk,nkc,nkb->ncb", 1.0 + 0.5 * nn[..., 2], weight, np.diff(cdf, axis=-1))
    return out / out.sum(axis=(1, 2), keepdims=True)


def point_lobe_bank(seed: int = 0, nside: int = 3):
    """A toy template bank for the "no template fits" verdict: one point-scatterer shape
    (:func:`point_lobe_signatures`, five points) on a Hopf attitude grid (``nside = 3``:
    1944 attitudes, 19 deg), and a second shape it lacks (five other points, 2.5x further
    out). Returns ``(bank, shape_in, shape_out)``, the shapes as ``(points, normals)``."""
    from ._database import TemplateBank
    from ._grid import hopf_grid

    rng = np.random.default_rng(seed)
    pts_a, pts_b = rng.normal(size=(5, 3)), 2.5 * rng.normal(size=(5, 3))
    nrm = rng.normal(size=(2, 5, 3))
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    grid = hopf_grid(nside)
    ids = np.zeros(len(grid), np.int32)
    bank = TemplateBank(
        signatures=point_lobe_signatures(pts_a, nrm[0], grid).astype(np.float32),
        shape_id=ids,
        attitude_id=np.arange(len(grid), dtype=np.int32),
        material_id=ids,
        finish_id=ids,
        quat=grid,
        names={"shapes": ["a"], "symmetry": ["none"], "finish_m": [1.0]},
        sensor="",
    )
    return bank, (pts_a, nrm[0]), (pts_b, nrm[1])
