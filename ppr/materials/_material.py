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

    Batched materials (leading axes on every field) are allowed; kernels ``vmap`` over them.
    Concrete (non-traced) values are validated at construction with a ``ValueError`` that names
    the field; traced values are checked inside kernels with ``eqx.error_if``.
    """

    n: Array = eqx.field(converter=_as_complex)
    m: Array = eqx.field(converter=_as_float)
    corr_length: Array = eqx.field(converter=_as_float, default=5e-6)
    name: str = eqx.field(static=True, default="")
    white: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        for field in ("n", "m", "corr_length"):
            v = getattr(self, field)
            if not _is_concrete(v):
                continue
            a = np.asarray(v)
            if not np.all(np.isfinite(a)):
                raise ValueError(f"Material.{field} must be finite, got {a!r}")
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

    return Material(st("n"), st("m"), st("corr_length"), name="stacked", white=white[0])
