r"""Signature function backed by the ppr forward model (``ppr.render``).

``PprSignatures(params) -> (batch, n_channels, n_bins)`` for database rows: for each row the
lit-and-visible fractions of the shape's faces are ray cast on the host
(:class:`ppr.VisibilityCaster`, embree; no gradients, piecewise constant in pose), then one
jitted, vmapped call of ``ppr.render`` evaluates every row of the batch with the full Mueller
BRDF (``ppr.mueller_brdf``) projected on the measurement model's channels.

Conventions shared with :mod:`inversion._synthetic`: monostatic sensor looking along world
``-z`` (``ppr.Sensor.make()`` defaults: laser and receiver directions ``+z`` from the object,
polarization reference ``x``), range bins centred on the body origin, pose quaternion body
-> world. Every part of a multi-part mesh gets the row's material and finish (the database
enumerates one material per object); per-part material maps are a possible extension.

The meshes of all shapes are padded to one face capacity (``ppr.mesh_arrays``), so rows of
different shapes share one compiled kernel.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import ppr

from ._noise import MeasurementModel


class PprSignatures:
    """Signature function of the ppr simulator (see module docstring).

    **Arguments:**

    - `shapes`: ``ppr.shapes`` names (``"cubesat"``, ``"cubesat_with_panels"``, ...) or
      ``(name, params)`` pairs, or ready :class:`ppr.Mesh` objects.
    - `materials`: ``ppr.load_material`` names; `finishes`: Blinn-Phong ``m`` per finish id.
    - `measurement`: PSG/PSA channels; `n_bins`, `bin_width_m`, `pulse_fwhm_s`, `wavelength`.
    - `vis_samples`: barycentric samples per face for partial visibility.
    - `brdf`: Mueller BRDF (default ``ppr.mueller_brdf``); `terms`: its terms (default all).
    - `multibounce`: include the macro double bounce between the shapes' surfaces
      (``ppr.simulate``'s switch: ``"auto"`` includes it when some shape has surfaces facing
      each other, i.e. is not convex); `macro_options`: its ``ppr.MacroOptions``.
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
        wavelength: float = ppr.DEFAULT_WAVELENGTH_M,
        vis_samples: int = 4,
        brdf=None,
        terms=None,
        dtype=jnp.float32,
        multibounce="auto",
        macro_options=None,
    ):
        if len(shapes) == 0 or len(materials) == 0 or len(finishes) == 0:
            raise ValueError("PprSignatures needs at least one shape, material and finish")
        meshes = []
        self.shape_names = []
        for s in shapes:
            if isinstance(s, ppr.Mesh):
                meshes.append(s)
                self.shape_names.append("mesh")
            elif isinstance(s, str):
                meshes.append(ppr.shapes.by_name(s))
                self.shape_names.append(s)
            else:
                name, params = s
                meshes.append(ppr.shapes.by_name(name, **dict(params)))
                self.shape_names.append(name)
        self.meshes = meshes
        self.measurement = measurement
        self.n_bins, self.bin_width_m = int(n_bins), float(bin_width_m)
        self.pulse_fwhm_s, self.wavelength = float(pulse_fwhm_s), float(wavelength)
        self.dtype = dtype
        from ppr.geometry import capacity_for, n_normal_groups  # noqa: PLC0415

        cap = max(capacity_for(m.n_faces) for m in meshes)
        # one group capacity for all shapes (their arrays are stacked)
        g_cap = min(
            cap,
            max(capacity_for(n_normal_groups(m)) for m in meshes),
        )
        arrays = [ppr.mesh_arrays(m, cap, dtype, group_capacity=g_cap) for m in meshes]
        self.arrays = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *arrays)
        self.capacity = cap
        self.n_parts = max(len(m.parts) for m in meshes)
        self.casters = [ppr.VisibilityCaster(m, vis_samples) for m in meshes]
        if multibounce not in (True, False, "auto"):
            raise ValueError(f"multibounce must be True, False or 'auto', got {multibounce!r}")
        self.macro_options = macro_options or ppr.MacroOptions()
        geoms = [ppr.macro_geometry(m, plates=self.macro_options.plates) for m in meshes]
        self.multibounce = multibounce is True or (
            multibounce == "auto" and not all(g.convex for g in geoms)
        )
        # padded pair counts grow (one more compilation) only if a row needs more
        self._macro_caps = (max(g.n_macro for g in geoms), 0, 0)
        mats = [ppr.load_material(name, wavelength, dtype=dtype) for name in materials]
        self.materials = tuple(materials)
        self.finishes = tuple(float(f) for f in finishes)
        self._n = jnp.stack([jnp.asarray(m.n) for m in mats])
        self._corr = jnp.stack([jnp.asarray(m.corr_length, dtype) for m in mats])
        self._m = jnp.asarray(self.finishes, dtype)
        # coated library materials: their film stacks aligned over the materials (bare ones
        # become zero-thickness stacks), indexed by material_id like n
        self._films = None
        if any(m.films for m in mats):
            st = ppr.stack_materials(mats)
            self._films = (st.films, jnp.asarray(st.wavelength), st.film_mode, st.thick_layer)
        self.sensor_model = ppr.Sensor.make(wavelength=wavelength)
        self.bins = ppr.RangeBins.centred(self.bin_width_m, self.n_bins)
        pulse = ppr.Pulse.gaussian(self.pulse_fwhm_s)
        self.sigma_r = float(pulse.sigma_range)
        extent = max(float(np.linalg.norm(np.ptp(np.asarray(m.vertices), axis=0))) for m in meshes)
        self.window = ppr.window_size(extent, self.sigma_r, self.bin_width_m, self.n_bins)
        chan = measurement.channel_matrix()  # (C, 4, 4)
        self.projection = jnp.asarray(chan.reshape(len(chan), 16).T, dtype)  # (16, C)
        for f in self.finishes:
            ppr.Material(mats[0].n, f)  # a bad finish raises here, naming Material.m
        if brdf is None or brdf is ppr.mueller_brdf:
            # every material and finish is concrete and checked above, attitudes are
            # normalized in the kernel: without the traced checks' host callback the compiled
            # kernel can come from the persistent compilation cache
            from ppr.brdf import mueller_brdf_unchecked  # noqa: PLC0415

            brdf = mueller_brdf_unchecked
        self.brdf = brdf
        self.terms = None if terms is None else (terms if isinstance(terms, str) else tuple(terms))
        # monostatic sensor: the double term from the exact-backscatter table, chosen here (the
        # sensor is concrete) so that the compiled kernel holds no double-bounce quadrature
        self.terms = ppr.sensor_terms(self.brdf, self.terms, self.sensor_model)
        half = 0.5 * self.bin_width_m * self.n_bins
        if extent / 2 + 6 * self.sigma_r > half:
            raise ValueError(
                f"range window of {2 * half:.3g} m (n_bins x bin_width_m) cannot hold shapes of "
                f"extent {extent:.3g} m plus the pulse; use more or wider bins"
            )

    @classmethod
    def from_spec(cls, spec, measurement: MeasurementModel) -> PprSignatures:
        return cls(
            [(s.name, s.params) for s in spec.shapes],
            list(spec.materials),
            list(spec.finishes.values()),
            measurement,
            n_bins=spec.sensor.n_bins,
            bin_width_m=spec.sensor.bin_width_m,
            pulse_fwhm_s=spec.sensor.pulse_fwhm_s,
        )

    @property
    def n_channels(self) -> int:
        return self.measurement.n_channels

    @property
    def sensor(self) -> dict:
        return {
            # the macro double bounce changes the signatures of non-convex shapes
            "model": "ppr-render-v1+macro" if self.multibounce else "ppr-render-v1",
            "channels": self.measurement.fingerprint(),
            "n_bins": self.n_bins,
            "bin_width_m": self.bin_width_m,
            "pulse_fwhm_s": self.pulse_fwhm_s,
            "wavelength_m": self.wavelength,
        }

    def visibility(self, shape_id: np.ndarray, quat: np.ndarray) -> np.ndarray:
        """(batch, capacity) lit-and-visible fractions, ray cast on the host."""
        quat = np.asarray(quat, np.float64)
        rot = np.asarray(ppr.quat_to_matrix(quat / np.linalg.norm(quat, axis=-1, keepdims=True)))
        u_in = np.asarray(self.sensor_model.laser_dir, np.float64)
        u_out = np.asarray(self.sensor_model.receiver_dir, np.float64)
        out = np.zeros((len(quat), self.capacity))
        for i, (sid, r) in enumerate(zip(np.asarray(shape_id), rot, strict=True)):
            caster = self.casters[int(sid)]
            out[i, : caster.n_faces] = caster.fractions(r.T @ u_in, r.T @ u_out)
        return out

    def macro_pairs(self, shape_id, finish_id, quat):
        """Host: the stacked ``ppr.MacroPairs`` of a batch of rows (every part gets the row's
        finish), or None without the double bounce."""
        if not self.multibounce:
            return None
        from ppr.pulse import batch_pairs  # noqa: PLC0415

        quat = np.asarray(quat, np.float64)
        rot = np.asarray(ppr.quat_to_matrix(quat / np.linalg.norm(quat, axis=-1, keepdims=True)))
        u = np.asarray(self.sensor_model.laser_dir, np.float64)
        dirs = np.einsum("bji,j->bi", rot, u)  # body frame (monostatic)
        pairs = batch_pairs(
            self.meshes,
            self.casters,
            np.asarray(shape_id),
            dirs,
            dirs,
            [self.finishes[int(f)] for f in np.asarray(finish_id)],
            self.brdf,
            self.macro_options,
            capacities=self._macro_caps,
            bins=(self.sigma_r, self.bin_width_m, self.n_bins),
            window=self.n_bins,
            mixed=True,
            dtype=self.dtype,
        )
        self._macro_caps = (
            pairs.tri.shape[1],
            max(self._macro_caps[1], pairs.g_i.shape[1]),
            max(self._macro_caps[2], pairs.r_i.shape[1]),
        )
        return pairs

    def __call__(self, params: dict) -> jax.Array:
        sid = np.asarray(params["shape_id"])
        quat = params["quat"]
        vis = self.visibility(sid, np.asarray(quat))
        macro = self.macro_pairs(sid, params["finish_id"], np.asarray(quat))
        sharding = getattr(quat, "sharding", None)
        args = [params["shape_id"], params["material_id"], params["finish_id"], quat]
        vis = jnp.asarray(vis, self.dtype)
        if sharding is not None and hasattr(sharding, "mesh"):
            vis = jax.device_put(vis, sharding)
        return _batch_render(
            self.arrays,
            *args,
            vis,
            self._n,
            self._m,
            self._corr,
            self.sensor_model,
            jnp.asarray(self.sigma_r, self.dtype),
            jnp.asarray(float(self.bins.start), self.dtype),
            jnp.asarray(self.bin_width_m, self.dtype),
            self.projection,
            n_parts=self.n_parts,
            n_bins=self.n_bins,
            window=self.window,
            brdf=self.brdf,
            terms=self.terms,
            macro=macro,
            films=self._films,
        )


@eqx.filter_jit
def _batch_render(
    arrays,
    shape_id,
    material_id,
    finish_id,
    quat,
    vis,
    n_tab,
    m_tab,
    corr_tab,
    sensor,
    sigma_r,
    start,
    width,
    projection,
    *,
    n_parts,
    n_bins,
    window,
    brdf,
    terms=None,
    macro=None,
    films=None,
):
    dt = arrays.tri.dtype

    def one(sid, mid, fid, q, v, mac):
        arr = jax.tree_util.tree_map(lambda a: a[sid], arrays)
        # one entry shared by every part (ppr.render): per-material work done once per row
        mat = ppr.Material(n_tab[mid][None], m_tab[fid][None], corr_tab[mid][None])
        if films is not None:
            layers, lam, mode, thick = films
            mat = ppr.Material(
                mat.n,
                mat.m,
                mat.corr_length,
                films=tuple((fn[mid][None], ft[mid][None].astype(dt)) for fn, ft in layers),
                wavelength=lam[mid][None].astype(dt),
                film_mode=mode,
                thick_layer=thick,
            )
        pose = ppr.Pose(q.astype(dt), jnp.zeros(3, dt))
        return ppr.render(
            arr,
            v,
            pose,
            mat,
            sensor,
            sigma_r,
            start,
            width,
            n_bins=n_bins,
            window=window,
            projection=projection,
            brdf=brdf,
            terms=terms,
            macro=mac,
        )

    out = jax.vmap(one)(shape_id, material_id, finish_id, quat, vis, macro)
    return jnp.maximum(out, 0.0)  # channel intensities; clip round-off below zero
