"""Materials: small immutable pytrees of optical constants and microfacet finish."""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._types import Array, ArrayLike


def _as_complex(x: ArrayLike) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.complexfloating):
        if not jnp.issubdtype(x.dtype, jnp.floating):
            x = x.astype(jnp.result_type(float))
        x = x.astype(jnp.result_type(x.dtype, jnp.complex64))
    return x


def _as_float(x: ArrayLike) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _as_films(films) -> tuple:
    """``((n_1, t_1), ...)`` with complex indices and float thicknesses (arrays)."""
    if films is None:
        return ()
    try:
        layers = tuple(films)
    except TypeError:
        raise ValueError(
            f"Material.films must be a sequence of (n, thickness) pairs, got {films!r}"
        ) from None
    out = []
    for i, layer in enumerate(layers):
        try:
            n, t = layer
        except (TypeError, ValueError):
            raise ValueError(
                f"Material.films[{i}] must be a pair (n, thickness_m), got {layer!r}"
            ) from None
        out.append((_as_complex(n), _as_float(t)))
    return tuple(out)


def _as_opt_float(x):
    return None if x is None else _as_float(x)


class Material(eqx.Module):
    """Optical constants and finish of one surface.

    **Arguments:**

    - `n`: complex refractive index ``n' + i n''`` (``n'' >= 0``; time convention
      ``exp(i(kz - wt))``, see :mod:`ppr.optics.conventions`). Real input is promoted to complex.
    - `m`: Blinn-Phong exponent, ``0 <= m <= 1e6`` (0 is Lambertian-like, large is a mirror).
    - `corr_length`: surface correlation length in metres, sets the width of the coherent
      enhanced-backscatter cone of the double-bounce term (``~ lambda / (4 d)``).
    - `name`: label (static; not traced).
    - `white`: static flag for an *ideal white reflector* (used by the white-furnace test and to
      build the albedo tables): every facet reflects with the Jones matrix of a perfect
      conductor, ``diag(r_s, r_p) = diag(-1, +1)`` in its s/p frames, i.e. Fresnel
      reflectance ``F == 1`` at every angle, no absorption, no diattenuation, no
      depolarization (Mueller ``diag(1, 1, -1, -1)`` per facet, the ``n -> i inf`` limit).
      When ``white`` is set, ``n`` is ignored by the BRDF. Build one with
      :meth:`Material.ideal_white`.

    - `films`: thin-film stack on every facet, ``((n_1, t_1), (n_2, t_2), ...)`` from the
      outermost layer (facing vacuum) inward to the substrate ``n``: complex indices
      (``n'' >= 0``) and thicknesses in metres (``>= 0``; a zero-thickness layer equals no
      layer). The facet's Jones reflection is the stack's (:mod:`ppr.optics._films`,
      ``docs/physics/thin_films.md``) in every BRDF term. ``()`` (default): a bare interface,
      the unchanged program.
    - `wavelength`: metres; required with ``films`` (the layers' phase thickness). Renders
      and BRDF calls check it against their own wavelength.
    - `film_mode`: treatment of a thick layer (fringes in facet angle narrower than the
      microfacet lobe): ``"auto"`` (default: coherent unless a layer is thick by
      :data:`ppr.optics._films.THICK_SPREAD`, then ``"lobe"``), ``"coherent"``, ``"incoherent"``
      (phase-averaged thick layer) or ``"lobe"`` (averaged over the lobe). Static; resolved
      at construction (``"auto"`` needs concrete films, ``m`` and ``wavelength``).
    - `thick_layer`: index of the thick layer (static; default: chosen with the mode).

    Batched materials (leading axes on every field) are allowed; kernels ``vmap`` over them.
    Concrete (non-traced) values are validated at construction with a ``ValueError`` that names
    the field; traced values are checked inside kernels with ``eqx.error_if``.
    """

    n: Array = eqx.field(converter=_as_complex)
    m: Array = eqx.field(converter=_as_float)
    corr_length: Array = eqx.field(converter=_as_float, default=5e-6)
    name: str = eqx.field(static=True, default="")
    white: bool = eqx.field(static=True, default=False)
    films: tuple = eqx.field(converter=_as_films, default=())
    wavelength: Array | None = eqx.field(converter=_as_opt_float, default=None)
    film_mode: str = eqx.field(static=True, default="auto")
    thick_layer: int | None = eqx.field(static=True, default=None)

    def __post_init__(self):
        from ..optics._films import resolve_film_mode  # noqa: PLC0415

        self.films = _as_films(self.films)
        mode, thick = resolve_film_mode(
            self.films,
            None if self.wavelength is None else _as_float(self.wavelength),
            _as_float(self.m),
            self.film_mode,
            self.thick_layer,
        )
        self.film_mode = mode
        self.thick_layer = thick

    def __check_init__(self):
        for field in ("n", "m", "corr_length"):
            v = getattr(self, field)
            if not _is_concrete(v):
                continue
            a = np.asarray(v)
            if not np.all(np.isfinite(a)):
                raise ValueError(f"Material.{field} must be finite, got {a!r}")
        if self.films:
            if self.white:
                raise ValueError(
                    "Material: an ideal white reflector (white=True) has no film stack; "
                    f"got films with {len(self.films)} layers"
                )
            if self.wavelength is None:
                raise ValueError(
                    "Material.wavelength (metres) is required with films (the layers' phase "
                    "thickness), got None"
                )
            if _is_concrete(self.wavelength):
                lam = np.asarray(self.wavelength)
                if not np.all(np.isfinite(lam)) or np.any(lam <= 0) or np.any(lam > 1e-3):
                    raise ValueError(
                        f"Material.wavelength must be in metres (e.g. 532e-9), got {lam!r}"
                    )
            for i, (n, t) in enumerate(self.films):
                if _is_concrete(n):
                    a = np.asarray(n)
                    if not np.all(np.isfinite(a)) or np.any(a.real <= 0) or np.any(a.imag < 0):
                        raise ValueError(
                            f"Material.films[{i}] index must be finite with n' > 0 and "
                            f"n'' >= 0, got {a!r}"
                        )
                if _is_concrete(t):
                    a = np.asarray(t)
                    if not np.all(np.isfinite(a)) or np.any(a < 0):
                        raise ValueError(
                            f"Material.films[{i}] thickness must be finite and >= 0 metres, "
                            f"got {a!r}"
                        )
        if _is_concrete(self.n) and np.any(np.imag(np.asarray(self.n)) < 0):
            raise ValueError(
                f"Material.n must have a non-negative imaginary part (absorbing medium, "
                f"exp(i(kz - wt)) convention), got n={np.asarray(self.n)!r}"
            )
        if _is_concrete(self.n) and np.any(np.real(np.asarray(self.n)) <= 0):
            raise ValueError(
                f"Material.n must have a positive real part, got n={np.asarray(self.n)!r}"
            )
        if _is_concrete(self.m):
            m = np.asarray(self.m)
            if np.any(m < 0) or np.any(m > 1e6 * (1 + 1e-9)):
                raise ValueError(
                    f"Material.m (Blinn-Phong exponent) must lie in [0, 1e6], got m={m!r}"
                )
        if _is_concrete(self.corr_length) and np.any(np.asarray(self.corr_length) <= 0):
            raise ValueError(
                f"Material.corr_length must be > 0 metres, got {np.asarray(self.corr_length)!r}"
            )

    @classmethod
    def ideal_white(cls, m: ArrayLike, corr_length: ArrayLike = 5e-6, name: str = "ideal white"):
        """Ideal white (``F == 1``, non-absorbing, non-polarizing) reflector of roughness ``m``.

        ``n`` is set to ``1 + 0j`` with the same float precision as ``m`` and is ignored.
        """
        m = _as_float(m)
        n = jnp.ones_like(m, dtype=jnp.result_type(m.dtype, jnp.complex64))
        return cls(n=n, m=m, corr_length=corr_length, name=name, white=True)

    @property
    def dtype(self):
        """Real float dtype the material computes in."""
        return jnp.finfo(self.n.dtype).dtype

    @property
    def coated(self) -> bool:
        """The material has a film stack."""
        return bool(self.films)


def stack_materials(materials: Sequence[Material], *, multiple: int = 1) -> Material:
    """One batched :class:`Material` (leading axis = part index) from per-part materials.

    Every field is stacked (strongly typed: a weak type would change the jit cache key); the
    static ``name`` becomes ``"stacked"`` (so that names do not retrace programs) and the
    static ``white`` flag is kept. ``white`` selects the BRDF's program (the ideal white
    reflector has no index), so it must be the same for every part: a mix is a
    ``ValueError`` naming the parts. ``multiple``: pad the part axis with copies of the last
    part to a multiple of this (callers with different part counts then share a
    compilation; the padding parts are never indexed).
    """
    mats = list(materials)
    if not mats:
        raise ValueError("stack_materials: need at least one material")
    for i, mat in enumerate(mats):
        if not isinstance(mat, Material):
            raise ValueError(
                f"stack_materials: part {i} is a {type(mat).__name__}, not a ppr.Material"
            )
    white = [bool(mat.white) for mat in mats]
    if any(white) and not all(white):
        idx_w = [i for i, w in enumerate(white) if w]
        idx_r = [i for i, w in enumerate(white) if not w]
        raise ValueError(
            f"stack_materials: parts {idx_w} are ideal white reflectors (Material.ideal_white) "
            f"and parts {idx_r} are not; one batch of parts takes one of the two BRDF "
            "programs: render them in separate calls"
        )
    mats += [mats[-1]] * (-len(mats) % max(int(multiple), 1))

    def st(field):
        a = jnp.stack([jnp.asarray(getattr(mat, field)) for mat in mats])
        return a.astype(a.dtype)

    if not any(mat.films for mat in mats):
        return Material(st("n"), st("m"), st("corr_length"), name="stacked", white=white[0])
    films, lam, mode, thick = _aligned_films(mats)
    return Material(
        st("n"),
        st("m"),
        st("corr_length"),
        name="stacked",
        white=white[0],
        films=films,
        wavelength=lam,
        film_mode=mode,
        thick_layer=thick,
    )


def _aligned_films(mats: list[Material]):
    """The parts' film stacks padded to one layer count with the thick layers (if any) at
    one index, stacked: ``(films, wavelength, mode, thick_layer)``. Padding layers have zero
    thickness, vacuum on top (``r = 0``: exact) or the part's substrate index at the bottom
    (``r = 0``: exact); a part without a thick layer in a thick batch gets a vacuum layer at
    the thick index, where the thick-layer treatment reduces to the coherent stack exactly
    (no multiple reflections in a layer with ``r = 0`` above it). Bare parts become
    zero-thickness stacks (their reflection to rounding)."""
    coated = [i for i, mat in enumerate(mats) if mat.films]
    lams = [float(np.asarray(mats[i].wavelength).reshape(-1)[0]) for i in coated]
    for i, lam in zip(coated, lams, strict=True):
        if abs(lam - lams[0]) > 1e-6 * lams[0]:
            raise ValueError(
                f"stack_materials: coated parts {coated[0]} and {i} have different "
                f"wavelengths ({lams[0]!r} and {lam!r} m); render one wavelength at a time"
            )
    thick_modes = {mats[i].film_mode for i in coated if mats[i].thick_layer >= 0}
    if len(thick_modes) > 1:
        raise ValueError(
            "stack_materials: parts treat their thick film layers differently "
            f"({sorted(thick_modes)} by part: "
            f"{[(i, mats[i].film_mode) for i in coated]}); give them one film_mode"
        )
    mode = thick_modes.pop() if thick_modes else "coherent"
    dt = jnp.result_type(*(jnp.real(mat.n).dtype for mat in mats))
    cdt = jnp.result_type(dt, jnp.complex64)
    T, shifts = _film_shifts(mats)
    layers_of = []
    for mat, shift in zip(mats, shifts, strict=True):
        layers = [(jnp.asarray(n, cdt), jnp.asarray(t, dt)) for n, t in mat.films]
        vac = (jnp.asarray(1.0, cdt), jnp.asarray(0.0, dt))
        layers_of.append([vac] * shift + layers)
    L = max(len(x) for x in layers_of)
    films = []
    for j in range(L):
        ns, ts = [], []
        for mat, layers in zip(mats, layers_of, strict=True):
            n, t = layers[j] if j < len(layers) else (jnp.asarray(mat.n, cdt), jnp.zeros((), dt))
            ns.append(jnp.broadcast_to(n, jnp.shape(mat.m)).astype(cdt))
            ts.append(jnp.broadcast_to(t, jnp.shape(mat.m)).astype(dt))
        films.append((jnp.stack(ns), jnp.stack(ts)))
    lam = jnp.full((len(mats),) + jnp.shape(mats[0].m), lams[0], dt)
    return tuple(films), lam, mode, (T if mode != "coherent" else -1)


def _film_shifts(mats: list[Material]) -> tuple[int, list[int]]:
    """The aligned thick-layer index ``T`` (-1: none) and the vacuum layers each part gets on
    top (:func:`_aligned_films`)."""
    T = max((mat.thick_layer for mat in mats if mat.films), default=-1)
    if T < 0:
        return T, [0] * len(mats)
    return T, [
        T - mat.thick_layer if (mat.films and mat.thick_layer >= 0) else T + 1 for mat in mats
    ]


def film_fit_layers(materials: Sequence[Material]) -> list[int | None]:
    """Per part, the index in :func:`stack_materials`' aligned film stack of the part's
    *fitted* layer (its thick layer if it has one, else its outermost layer; None for a bare
    part): the layer whose thickness the inversion's ``thickness`` parameter sets."""
    mats = list(materials)
    if not any(mat.films for mat in mats):
        return [None] * len(mats)
    _, shifts = _film_shifts(mats)
    return [
        None if not mat.films else shift + max(mat.thick_layer, 0)
        for mat, shift in zip(mats, shifts, strict=True)
    ]
