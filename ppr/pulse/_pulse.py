r"""Facet-sum pulse synthesis: range-resolved Mueller profiles of a posed mesh.

Radiometry
    A plane wave of irradiance ``E0`` (W/m^2 across the beam) from direction ``u_in`` lights a
    flat facet of area ``A`` and normal ``n``; the radiance it sends toward ``u_out`` is
    ``L = f E0 (n . u_in)`` (definition of the BRDF ``f``), and its radiant intensity toward
    the receiver is ``I = L A (n . u_out)``. Summing over facets, the return is described by

        J = sum_f  M_f (n_f . u_in)(n_f . u_out) A_f v_f        [m^2 / sr]

    with ``M_f`` the facet's Mueller BRDF (1/sr; ``k_in = u_in``, ``k_out = u_out``, frames the
    sensor's beam frames) and ``v_f`` its lit-and-visible fraction. ``J`` is the Mueller
    radiant intensity per unit incident irradiance; its M00 is the bistatic radar cross
    section over 4 pi: ``sigma = 4 pi J_00``. The received Stokes energy is
    ``J S_tx E0 A_rx / R_rx^2`` (times pulse energy over beam area, aperture, and the two-way
    atmosphere, dropped by normalized signatures: docs/physics/pulse_and_measurement.md).
    Back-facing facets (``n . u <= COS_MIN`` toward laser or receiver) contribute nothing.

Range-area density of a facet
    The range of a point is its depth along the bisector ``w = (u_in + u_out)/2`` (see
    :mod:`ppr.pulse._scene`). The area of a flat triangle between depths ``z`` and ``z + dz`` is
    piecewise linear in ``z``: the triangular density with vertex depths ``d0 <= d1 <= d2``
    (mode ``d1``), i.e. the linear B-spline ``g(z) = 2 [d0, d1, d2]_t (z - t)_+``.
    Convolved with a Gaussian pulse of range width ``sigma`` its cumulative distribution is
    a second divided difference

        F(x) = [d0, d1, d2]_t  sigma^2 Q((x - t)/sigma),  Q(u) = (u^2 + 1) Phi(u) + u phi(u)

    (``sigma^2 Q = E[(x - t - eps)_+^2]``, ``Q'' = 2 Phi``). Each bin receives ``F(right edge)
    - F(left edge)``: bin-integrated, so the sum over bins is exactly the facet's weight for
    any bin or pulse width. Numerically: ``Q(u) - Q(-u) = u^2 + 1`` gives the mirrored form
    ``F = 1 - [..] Q((t - x)/sigma)`` used right of the facet's mean depth (no large
    cancelling terms); first divided differences closer than ``tau_1`` fall back to a
    midpoint Taylor series, and facets thinner than ``tau`` (in units of sigma; zero-depth
    facets facing the sensor) to the moment expansion
    ``Phi(c) - p2/24 c phi + p3/180 (c^2-1) phi - (p2^2 + 2 p4)/2880 (c^3 - 3c) phi`` about
    the mean. Both branches are double-``where`` guarded: values and gradients stay finite
    for edge-on, two-equal-depth and zero-depth facets.

Windows
    A facet affects only bins within ``NSIG`` sigma of its depth interval. Each facet's CDF is
    evaluated at ``window + 1`` consecutive bin edges starting just before its nearest depth
    (``window`` static, from the longest mesh edge, :func:`window_size`), and the differences
    are scattered into the profile. Past the window the CDF is 1 to ``Phi(-NSIG)`` (1e-12).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._types import Array, ArrayLike, Float, Int
from ..geometry._mesh import MeshArrays, capacity_for, mesh_arrays
from ..geometry._rotation import quat_to_matrix
from ..geometry._visibility import COS_MIN, VisibilityCaster
from ..materials._material import Material, stack_materials
from ..optics.conventions import C_LIGHT, DEFAULT_WAVELENGTH_M
from ._scene import Pose, RangeBins, Scene, Sensor

NSIG = 7.0
"""Half-width of a facet's window beyond its depth interval, in pulse sigmas."""
COVER_NSIG = 3.0
"""The range gate must contain every visible facet's depth interval +- this many sigmas."""
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_INV_SQRT_2 = 1.0 / math.sqrt(2.0)

STOKES_STATES = {
    "H": (1.0, 1.0, 0.0, 0.0),
    "V": (1.0, -1.0, 0.0, 0.0),
    "D": (1.0, 0.0, 1.0, 0.0),
    "A": (1.0, 0.0, -1.0, 0.0),
    "R": (1.0, 0.0, 0.0, -1.0),
    "L": (1.0, 0.0, 0.0, 1.0),
}
"""Named transmitted states (sensor frame): horizontal (x), vertical, +45, -45, right and left
circular. ``"R"`` turns clockwise for an observer looking toward the source (right-circular in
Chipman's, Born & Wolf's and Hecht's naming): ppr's ``S3 = -1``. ``"L"`` is ``S3 = +1``
(IEEE's right-hand circular). See :mod:`ppr.optics.conventions`."""


# ----------------------------------------------------------------------------- closed form


def _phi(u):
    return _INV_SQRT_2PI * jnp.exp(-0.5 * u * u)


def _ncdf(u):
    # one erfc (accurate in the lower tail, absolute accuracy in the upper): cheaper to
    # compile and run than ndtr's two-branch form
    return 0.5 * jax.lax.erfc(-u * _INV_SQRT_2)


@jax.custom_jvp
def _cdf_pdf(u):
    """(Phi(u), phi(u)) with the analytic JVP (phi du, -u phi du): the tangent reuses the
    primal exp instead of differentiating erfc (keeps the gradient's compile small)."""
    return _ncdf(u), _phi(u)


@_cdf_pdf.defjvp
def _cdf_pdf_jvp(primals, tangents):
    (u,), (du,) = primals, tangents
    c, p = _cdf_pdf(u)
    return (c, p), (p * du, -u * p * du)


def _thresholds(dtype) -> tuple[float, float]:
    """(tau, tau_1): thin-facet and close-pair thresholds in units of sigma."""
    if jnp.finfo(dtype).bits <= 32:
        return 0.25, 0.5
    return 0.02, 0.05


_N_TAYLOR = 8


def _q_derivatives(u, cdf, pdf):
    """Q^(k)(u) for k = 1..8: Q' = 2(u Phi + phi), Q'' = 2 Phi, Q^(j+3) = 2 (-1)^j He_j phi."""
    u2 = u * u
    he = [
        1.0,
        u,
        u2 - 1.0,
        u2 * u - 3.0 * u,
        u2 * u2 - 6.0 * u2 + 3.0,
        u2 * u2 * u - 10.0 * u2 * u + 15.0 * u,
    ]
    d = [2.0 * (u * cdf + pdf), 2.0 * cdf]
    d += [2.0 * (-1.0) ** j * he[j] * pdf for j in range(_N_TAYLOR - 2)]
    return d  # d[k-1] = Q^(k)


def _dd2(u0, u1, u2, g01, g12):
    """[u0, u1, u2] Q for monotonically sorted u, gaps g01 = |u0-u1|, g12 = |u1-u2|.

    Direct divided differences, with Taylor series about the middle point ``u1`` (derivatives
    in closed form from the same Phi, phi) for close pairs (< tau_1) and thin facets (< tau):
    three erfc and three exp per evaluation.
    """
    tau, tau1 = _thresholds(u0.dtype)
    cdf, pdf = zip(*(_cdf_pdf(u) for u in (u0, u1, u2)), strict=True)
    q = [(u * u + 1.0) * c + u * p for u, c, p in zip((u0, u1, u2), cdf, pdf, strict=True)]
    d = _q_derivatives(u1, cdf[1], pdf[1])
    e0 = u0 - u1
    e2 = u2 - u1
    fact = [math.factorial(k) for k in range(_N_TAYLOR + 1)]

    def first(e):  # [u1 + e, u1] Q as a series in e
        return sum(d[k - 1] * e ** (k - 1) / fact[k] for k in range(1, _N_TAYLOR + 1))

    small01 = g01 < tau1
    small12 = g12 < tau1
    dd01 = jnp.where(small01, first(e0), (q[0] - q[1]) / jnp.where(small01, 1.0, u0 - u1))
    dd12 = jnp.where(small12, first(e2), (q[1] - q[2]) / jnp.where(small12, 1.0, u1 - u2))
    thin = (g01 + g12) < tau
    direct = (dd01 - dd12) / jnp.where(thin, 1.0, u0 - u2)
    # [u0, u1, u2] Q = sum_k Q^(k)(u1) / k! h_{k-2}(e0, e2), h complete homogeneous
    h = [jnp.ones_like(e0)]
    for j in range(1, _N_TAYLOR - 1):
        h.append(e0**j + e2 * h[-1])
    series = sum(d[k - 1] * h[k - 2] / fact[k] for k in range(2, _N_TAYLOR + 1))
    return jnp.where(thin, series, direct)


def tent_gaussian_cdf(
    x: Float[ArrayLike, "..."],
    d0: Float[ArrayLike, "..."],
    d1: Float[ArrayLike, "..."],
    d2: Float[ArrayLike, "..."],
    sigma: Float[ArrayLike, "..."],
) -> Float[Array, "..."]:
    """CDF at ``x`` of (triangular density on ``d0 <= d1 <= d2``) convolved with N(0, sigma^2).

    Closed form (module docstring); broadcasts; finite values and gradients for coincident
    depths (``d0 == d1``, ``d1 == d2``, all equal).
    """
    x, d0, d1, d2, sigma = jnp.broadcast_arrays(*map(jnp.asarray, (x, d0, d1, d2, sigma)))
    inv = 1.0 / sigma
    g01 = (d1 - d0) * inv
    g12 = (d2 - d1) * inv
    mean = (d0 + d1 + d2) / 3.0
    left = x <= mean
    sgn = jnp.where(left, 1.0, -1.0)
    u0 = sgn * (x - d0) * inv
    u1 = sgn * (x - d1) * inv
    u2 = sgn * (x - d2) * inv
    val = _dd2(u0, u1, u2, g01, g12)
    return jnp.where(left, val, 1.0 - val)


# ----------------------------------------------------------------------------- stand-in BRDFs


def lambertian_mueller(
    k_in,
    k_out,
    normal,
    material,
    *,
    frame_in=None,
    frame_out=None,
    wavelength=DEFAULT_WAVELENGTH_M,
    terms=None,
):
    """Stand-in BRDF: ideal depolarizing Lambertian ``diag(1, 0, 0, 0) / pi`` (albedo 1),
    same signature as :func:`ppr.mueller_brdf`. For tests and geometry checks."""
    del k_out, material, frame_in, frame_out, wavelength, terms
    batch = jnp.broadcast_shapes(jnp.shape(k_in)[:-1], jnp.shape(normal)[:-1])
    dt = jnp.result_type(k_in, normal)
    m = jnp.zeros((4, 4), dt).at[0, 0].set(1.0 / jnp.pi)
    return jnp.broadcast_to(m, (*batch, 4, 4))


def glossy_fresnel_mueller(
    k_in,
    k_out,
    normal,
    material,
    *,
    frame_in=None,
    frame_out=None,
    wavelength=DEFAULT_WAVELENGTH_M,
    terms=None,
):
    """Stand-in polarizing BRDF for tests and benchmarks (not the model): the Fresnel Mueller
    matrix of the half-vector facet in the beam frames times ``(m + 2)/(2 pi) (h.n)^m / pi``.
    Smooth in attitude, ``m`` and ``n``; no shadowing, no normalization claims."""
    from .._safe import safe_pow  # noqa: PLC0415
    from ..optics._frames import facet_mueller_in_beam_frames  # noqa: PLC0415

    del wavelength, terms
    h = k_in + k_out
    h = h / jnp.linalg.norm(h, axis=-1, keepdims=True)
    cos_h = jnp.sum(h * normal, axis=-1)
    m = material.m
    lobe = (m + 2.0) / (2.0 * jnp.pi) * safe_pow(jnp.clip(cos_h, 0.0, 1.0), m) / jnp.pi
    n = material.n
    if not material.films:
        mm = facet_mueller_in_beam_frames(
            jnp.real(n), jnp.imag(n), k_in, k_out, h, frame_in, frame_out
        )
        return mm * lobe[..., None, None]
    from ..optics._films import films_of  # noqa: PLC0415
    from ..optics._frames import facet_rotated_params, rotated_mueller_flat  # noqa: PLC0415

    batch = jnp.shape(lobe)
    dt = lobe.dtype
    films = films_of(material, dt, batch)
    n_re, n_im = (jnp.broadcast_to(a.astype(dt), batch) for a in (jnp.real(n), jnp.imag(n)))
    flat = rotated_mueller_flat(
        facet_rotated_params(n_re, n_im, k_in, k_out, h, frame_in, frame_out, films=films), lobe
    )
    return jnp.moveaxis(flat, 0, -1).reshape(batch + (4, 4))


def _default_brdf():
    try:
        from ..brdf._brdf import mueller_brdf  # noqa: PLC0415
    except ImportError as exc:  # pragma: no cover - until the BRDF lands
        raise RuntimeError("ppr.mueller_brdf is not available; pass brdf=...") from exc
    return mueller_brdf


# ----------------------------------------------------------------------------- kernel


def window_size(max_depth_extent: float, sigma_r: float, width: float, n_bins: int) -> int:
    """Static number of bins per facet window (multiple of 8; capped at ``n_bins``, which is
    the dense evaluation)."""
    k = math.ceil((max_depth_extent + 2 * NSIG * sigma_r) / width) + 2
    k = 8 * math.ceil(k / 8)
    return int(min(k, n_bins))


def stokes_projection(states: Float[ArrayLike, "S 4"]) -> np.ndarray:
    """``(16, 4 S)`` matrix mapping flattened Mueller rows to Stokes outputs ``M @ s`` of each
    transmitted state ``s`` (column ``4 s + i`` is output component ``i`` of state ``s``)."""
    st = np.asarray(states, np.float64)
    p = np.zeros((16, 4 * len(st)))
    for s, vec in enumerate(st):
        for i in range(4):
            for j in range(4):
                p[4 * i + j, 4 * s + i] = vec[j]
    return p


def channel_projection(channels: Sequence[tuple[int, int]]) -> np.ndarray:
    """``(16, C)`` matrix selecting Mueller elements ``(i, j)``."""
    p = np.zeros((16, len(channels)))
    for c, (i, j) in enumerate(channels):
        p[4 * i + j, c] = 1.0
    return p


def facet_weights(
    arrays: MeshArrays,
    vis: Float[Array, " F"],
    rot: Float[Array, "3 3"],
    materials: Material,
    sensor: Sensor,
    *,
    projection: Float[Array, "16 C"] | None,
    brdf: Callable,
    terms=None,
    part: int | None = None,
) -> tuple[Float[Array, "F C"], Array]:
    """Per-facet weights ``M_f (n.u_in)(n.u_out) A_f v_f`` projected to the output channels,
    and the body-frame bisector. Everything is evaluated in the body frame (the BRDF is
    rotation covariant), so only four 3-vectors are rotated per pose. ``part`` (static): the
    one part every real facet belongs to, if known (:func:`single_part`); its material is then
    passed unbatched, which lets the BRDF take its one-material paths."""
    rt = rot.T
    u_in = rt @ sensor.laser_dir
    # a monostatic sensor: k_out is the same array as k_in (the BRDF's exact-backscatter
    # kernel, and XLA shares the work of the two directions)
    u_out = u_in if sensor.monostatic else rt @ sensor.receiver_dir
    x_tx = rt @ sensor.frame_tx
    x_rx = rt @ sensor.frame_rx
    nrm = arrays.normals
    cos_in = nrm @ u_in
    cos_out = nrm @ u_out
    front = (cos_in > COS_MIN) & (cos_out > COS_MIN) & arrays.valid & (vis > 0)
    w = 0.5 * (u_in + u_out)
    w_unit = w / jnp.linalg.norm(w)
    f_count = nrm.shape[0]
    grouped = arrays.group_normals.shape[0] < f_count
    if grouped:
        # one BRDF per (normal, part) group (MeshArrays): faces of a group share the normal
        # bit for bit, so their Mueller matrices are identical
        g_nrm, g_mid = arrays.group_normals, arrays.group_material_ids
        g_front = (g_nrm @ u_in > COS_MIN) & (g_nrm @ u_out > COS_MIN)
    else:
        g_nrm, g_mid, g_front = nrm, arrays.material_ids, front
    # double where: masked normals become the bisector before the BRDF
    safe_n = jnp.where(g_front[:, None], g_nrm, w_unit[None, :])
    if part is not None or jnp.shape(materials.m)[:1] == (1,):
        # one material for every facet: unbatched, so that the BRDF's per-material work
        # (tables of the visibility and of the double term) is done once, not per facet
        mat = jax.tree_util.tree_map(lambda a: a[part or 0], materials)
    else:
        mat = jax.tree_util.tree_map(lambda a: a[g_mid], materials)
    count = g_nrm.shape[0]
    k_in = jnp.broadcast_to(u_in, (count, 3))
    k_out = k_in if sensor.monostatic else jnp.broadcast_to(u_out, (count, 3))

    def call(t):
        return brdf(
            k_in,
            k_out,
            safe_n,
            mat,
            frame_in=jnp.broadcast_to(x_tx, (count, 3)),
            frame_out=jnp.broadcast_to(x_rx, (count, 3)),
            wavelength=sensor.wavelength,
            terms=t,
        )

    bs = backscatter_terms(brdf, terms)
    if bs is None:
        m = call(terms)
    elif sensor.monostatic:
        m = call(bs)
    else:
        # one decision per sensor (unbatched under vmap over poses, unlike the per-facet
        # directions): the exact-backscatter table of the double term, or its quadrature
        near = near_backscatter(sensor.laser_dir, sensor.receiver_dir)
        m = jax.lax.cond(near, lambda _: call(bs), lambda _: call(terms), None)
    m = m.reshape(count, 16)
    m = jnp.where(g_front[:, None], m, 0.0)
    wch = m if projection is None else m @ projection.astype(m.dtype)
    if grouped:
        wch = wch[arrays.normal_group]
    g = jnp.where(front, cos_in * cos_out * arrays.areas * vis, 0.0)
    return jnp.where(front[:, None], wch, 0.0) * g[:, None], w


def backscatter_terms(brdf: Callable, terms) -> tuple[str, ...] | None:
    """``terms`` for :func:`ppr.mueller_brdf` with its double term taken from the
    exact-backscatter table (``"double:backscatter"``, :mod:`ppr.brdf.double_table`), or None when
    that changes nothing (another BRDF, or no double term). ``"auto"`` keeps the double term
    at backscatter: from the table it costs little, and leaving it out was only a saving."""
    from ..brdf._brdf import (  # noqa: PLC0415
        _resolve_terms,
        implemented_terms,
        mueller_brdf,
        mueller_brdf_unchecked,
    )

    if brdf is not mueller_brdf and brdf is not mueller_brdf_unchecked:
        return None
    names = implemented_terms() if terms is None or terms == "auto" else _resolve_terms(terms)
    if "double" not in names:
        return None
    return tuple("double:backscatter" if t == "double" else t for t in names)


def near_backscatter(laser_dir: Array, receiver_dir: Array) -> Array:
    """The sensor's bistatic angle is within the backscatter table's ``PSI_MAX``."""
    from ..brdf.double_table import near_backscatter as near  # noqa: PLC0415

    return near(laser_dir, receiver_dir)


def sensor_terms(brdf: Callable, terms, sensor: Sensor):
    """``terms`` for a *concrete* sensor: :func:`backscatter_terms` when its bistatic angle is
    within the backscatter table's ``PSI_MAX`` (monostatic PPR), else the double term by
    quadrature only (``"double:quadrature"``), ``terms`` unchanged for a traced sensor,
    another BRDF or ``"auto"`` beyond ``PSI_MAX``. Callers that jit over the sensor
    (:class:`inversion.SimulatorModel`, the database's signature function) call it once
    outside, so that their compiled programs hold one branch of the double term, not a
    ``lax.cond`` of the table and the quadrature (both compiled and, under a Jacobian, both
    differentiated). The quadrature is valid at any geometry; the table within ``PSI_MAX``,
    where the concrete sensor was checked to be."""
    bs = backscatter_terms(brdf, terms)
    dirs = (sensor.laser_dir, sensor.receiver_dir)
    if bs is not None and sensor.monostatic:
        return bs
    if bs is None or any(isinstance(a, jax.core.Tracer) for a in dirs):
        return terms
    if _near_np(*dirs):
        return bs
    return _quadrature_terms(terms, bs)


def _quadrature_terms(terms, bs: tuple[str, ...]):
    """``bs`` (:func:`backscatter_terms` of ``terms``) with the double term by quadrature, for
    a geometry beyond ``PSI_MAX``; ``terms`` unchanged when it is ``"auto"`` (whose double
    term is dropped at run time where it cannot matter: that saving is kept)."""
    if terms == "auto":
        return terms
    return tuple("double:quadrature" if t == "double:backscatter" else t for t in bs)


def _near_np(laser_dir, receiver_dir) -> bool:
    """:func:`near_backscatter` of concrete directions in NumPy (jnp ops would be staged
    into an enclosing jit trace)."""
    from ..brdf.double_table import PSI_MAX  # noqa: PLC0415

    dk = np.asarray(receiver_dir, np.float64) - np.asarray(laser_dir, np.float64)
    return bool(np.sum(dk * dk) <= (2.0 * math.sin(0.5 * PSI_MAX)) ** 2)


def render(
    arrays: MeshArrays,
    vis: Float[Array, " F"],
    pose: Pose,
    materials: Material,
    sensor: Sensor,
    sigma_r: Float[ArrayLike, ""],
    start: Float[ArrayLike, ""],
    width: Float[ArrayLike, ""],
    *,
    n_bins: int,
    window: int,
    projection: Float[Array, "16 C"] | None = None,
    brdf: Callable = lambertian_mueller,
    terms=None,
    faces: Int[Array, " Fc"] | None = None,
    macro=None,
) -> Float[Array, "C B"]:
    """Pure jitted core: bin-integrated range profiles ``(C, n_bins)`` (m^2/sr per bin).

    **Arguments:**

    - `arrays`: :class:`ppr.MeshArrays` (padded body-frame mesh).
    - `vis`: ``(F,)`` lit-and-visible fractions (:class:`ppr.VisibilityCaster`, host).
    - `pose`: :class:`ppr.Pose` (traced; differentiable).
    - `materials`: batched :class:`ppr.Material`, one entry per part (:func:`stack_materials`),
      or a single entry shared by every part (cheaper: see :func:`facet_weights`).
    - `sensor`: :class:`ppr.Sensor`.
    - `sigma_r`: pulse RMS width in range (m), ``c sigma_t / 2``, including jitter; add a
      time offset ``t0`` through ``start`` (``start - c t0 / 2``).
    - `start`, `width`: first bin edge and bin width (m, relative range).
    - `n_bins`, `window` (static): bin count; bins per facet window (:func:`window_size`).
    - `projection`: ``(16, C)`` output channels (None: all 16 Mueller elements, row-major).
    - `brdf` (static): Mueller BRDF with the signature of :func:`ppr.mueller_brdf`.
    - `faces`: optional ``(Fc,)`` indices of the facets to keep (pruning: back-facing and
      invisible facets left out, :func:`visible_faces`); padding indices must point at
      facets with ``vis == 0``. The result is the same; the cost scales with ``Fc``.
    - `macro`: optional :class:`ppr.MacroPairs` (host: the first item of
      :func:`ppr.macro_pairs` at this pose): adds the macro double bounce between the object's
      surfaces (:mod:`ppr.pulse._macro`).

    Facets deeper than the window lose the part of their return beyond it: choose
    ``window`` from the longest edge (``simulate`` does). Python scalars are converted to
    arrays here, so new values never recompile.
    """
    dt = arrays.tri.dtype
    part = single_part(arrays)
    if faces is not None:
        arrays, vis = _take_faces(arrays, vis, faces)
    brdf = _unchecked_if_concrete(brdf, materials, pose)
    # decided here for a concrete sensor, so that the compiled program holds the table only
    # (facet_weights decides by lax.cond when the sensor is traced)
    terms = sensor_terms(brdf, terms, sensor)
    return _render_jit(
        arrays,
        vis,
        pose,
        materials,
        sensor,
        jnp.asarray(sigma_r, dt),
        jnp.asarray(start, dt),
        jnp.asarray(width, dt),
        n_bins=int(n_bins),
        window=int(window),
        projection=projection,
        brdf=brdf,
        terms=terms,
        part=part,
        macro=macro,
    )


def _unchecked_if_concrete(brdf: Callable, materials: Material, pose: Pose) -> Callable:
    """:func:`ppr.brdf._brdf.mueller_brdf_unchecked` in place of :func:`ppr.mueller_brdf` when the
    materials and the pose are concrete. The BRDF's inputs are then valid by construction:
    ``Material`` and ``Pose`` check concrete values when built, the sensor's directions and
    frames are validated unit vectors rotated by a normalized quaternion, mesh normals are
    unit and back-facing facets get the bisector. Without the traced checks' host callback
    the render's program can go to the persistent compilation cache. Traced materials or
    poses (a caller's ``jit`` or ``grad``) keep the checks."""
    from ..brdf._brdf import _validate_material, mueller_brdf, mueller_brdf_unchecked  # noqa: PLC0415

    if brdf is not mueller_brdf:
        return brdf
    leaves = jax.tree_util.tree_leaves((materials, pose))
    if any(isinstance(a, jax.core.Tracer) for a in leaves):
        return brdf
    # the same checks on the host (a Material or Pose edited with eqx.tree_at skips its own)
    _validate_material(materials)
    for name in ("quaternion", "position"):
        if not np.all(np.isfinite(np.asarray(getattr(pose, name)))):
            raise ValueError(f"pose.{name} must be finite, got {np.asarray(getattr(pose, name))}")
    return mueller_brdf_unchecked


def single_part(arrays: MeshArrays) -> int | None:
    """The part index shared by every real face of ``arrays`` when the arrays are concrete
    (host check), else None. A one-part mesh then renders with its material unbatched (the
    BRDF's one-material fast paths) even when the scene lists materials for more parts."""
    if isinstance(arrays.material_ids, jax.core.Tracer) or isinstance(
        arrays.valid, jax.core.Tracer
    ):
        return None
    ids = np.unique(np.asarray(arrays.material_ids)[np.asarray(arrays.valid)])
    return int(ids[0]) if len(ids) == 1 else None


def _take_faces(arrays, vis, faces):
    return arrays.take_faces(faces), vis[faces]


def visible_faces(vis: np.ndarray, capacity: int | None = None) -> np.ndarray:
    """Host helper: indices of the facets with ``vis > 0`` padded (with a ``vis == 0`` facet,
    or facet 0 if there is none) to ``capacity`` (default :func:`ppr.geometry._mesh.capacity_for`),
    for ``render(..., faces=...)``; batches of poses share one capacity."""
    vis = np.asarray(vis)
    idx = np.flatnonzero(vis > 0)
    cap = capacity_for(max(len(idx), 1)) if capacity is None else int(capacity)
    if cap < len(idx):
        raise ValueError(f"capacity {cap} < {len(idx)} visible facets (overflow)")
    zero = np.flatnonzero(vis <= 0)
    pad = zero[0] if len(zero) else 0
    if not len(zero) and cap > len(idx):
        raise ValueError("every facet is visible: no vis == 0 facet to pad with; use faces=None")
    return np.concatenate([idx, np.full(cap - len(idx), pad)]).astype(np.int32)


def _sort3(a: Array, b: Array, c: Array) -> tuple[Array, Array, Array]:
    """Ascending order of three arrays by a compare-and-swap network of selects: the values
    and the tangents of ``jnp.sort`` on a trailing axis of 3 (a permutation: each output
    carries exactly one input's tangent), which XLA CPU runs ~100x slower (1.3 ms per pose at
    6k facets). ``jnp.minimum``/``maximum`` would not do: they split the tangent at ties, and
    nested they lose part of it (three equal depths: measured wrong attitude gradients)."""

    def swap(x, y):
        le = x <= y
        return jnp.where(le, x, y), jnp.where(le, y, x)

    a, b = swap(a, b)
    b, c = swap(b, c)
    a, b = swap(a, b)
    return a, b, c


@eqx.filter_jit
def _render_jit(
    arrays,
    vis,
    pose,
    materials,
    sensor,
    sigma_r,
    start,
    width,
    *,
    n_bins,
    window,
    projection,
    brdf,
    terms,
    part=None,
    macro=None,
):
    dt = arrays.tri.dtype
    rot = quat_to_matrix(pose.quaternion.astype(dt))
    wch, w_body = facet_weights(
        arrays,
        vis,
        rot,
        materials,
        sensor,
        projection=projection,
        brdf=brdf,
        terms=terms,
        part=part,
    )
    w_world = rot @ w_body
    depth = -(arrays.tri @ w_body) - jnp.dot(pose.position.astype(dt), w_world)  # (F, 3)
    out = _tent_profile(wch, depth, sigma_r, start, width, n_bins=n_bins, window=window)
    if macro is not None:
        from ._macro import macro_profile  # noqa: PLC0415

        out = out + macro_profile(
            macro,
            rot,
            pose.position,
            materials,
            sensor,
            jnp.asarray(sigma_r, dt),
            jnp.asarray(start, dt),
            jnp.asarray(width, dt),
            n_bins=n_bins,
            projection=projection,
            brdf=brdf,
        )
    return out


def _tent_profile(wch, depth, sigma_r, start, width, *, n_bins: int, window: int) -> Array:
    """``(C, n_bins)`` profile of range items: weights ``wch (N, C)`` spread over triangular
    range densities with vertex depths ``depth (N, 3)`` (a point item repeats its depth),
    convolved with the Gaussian pulse and bin-integrated (module docstring). ``window``
    (static): bins per item (``<= 0`` or ``>= n_bins``: every bin)."""
    dt = wch.dtype
    sigma = jnp.asarray(sigma_r, dt)
    start = jnp.asarray(start, dt)
    width = jnp.asarray(width, dt)
    dense = window <= 0 or window >= n_bins
    d0, d1, d2 = _sort3(depth[:, 0:1], depth[:, 1:2], depth[:, 2:3])
    if dense:
        j0 = jnp.zeros(d0.shape, jnp.int32)
        k = n_bins
    else:
        first = jax.lax.stop_gradient((d0 - NSIG * sigma - start) / width)
        j0 = jnp.floor(first).astype(jnp.int32)
        k = window
    j = j0 + jnp.arange(k + 1, dtype=jnp.int32)[None, :]  # (F, k+1) edge indices
    edges = start + j.astype(dt) * width
    cdf = tent_gaussian_cdf(edges, d0, d1, d2, sigma)
    # (F, k) bin contents of each facet (unit weight). The differences go through a matmul
    # with the (k+1, k) difference matrix: its exact 0/+-1 coefficients round like a plain
    # subtraction, and it keeps XLA CPU from fusing the erfc chain into a sliced consumer
    # that does not vectorize (measured 8-14x slower than materializing the CDF)
    diff = jnp.eye(k + 1, k, -1, dtype=dt) - jnp.eye(k + 1, k, dtype=dt)
    dcdf = cdf @ diff
    if dense:
        return wch.T @ dcdf
    return _place(wch, dcdf, j0, n_bins)


def _place_plain(wch: Array, dcdf: Array, j0: Array, n_bins: int) -> Array:
    """``(C, n_bins)`` profile: each facet's window ``dcdf[f]`` placed at bins ``j0[f] + t``,
    weighted by ``wch[f]``. The window goes into its row of a dense ``(F, n_bins)`` matrix by
    a gather (window offset of every bin), then one matmul with the weights: on XLA CPU this
    ran ~2x faster than a 1-D scatter-add, ~10x faster than a 2-D one, and faster than
    select-based block placements (measured)."""
    k = dcdf.shape[1]
    off = jnp.arange(n_bins, dtype=jnp.int32)[None, :] - j0  # (F, n_bins)
    inside = (off >= 0) & (off < k)
    dense = jnp.where(inside, jnp.take_along_axis(dcdf, jnp.clip(off, 0, k - 1), axis=1), 0.0)
    return wch.T @ dense


@functools.cache
def _place_mapped(n_bins: int):
    """:func:`_place_plain` whose ``vmap`` rule loops over the mapped axis (``lax.map``): XLA
    CPU ran the batched gather 3x slower per pose than the unbatched one (vmap over 8 poses of
    6k facets: 3.6 -> 1.3 ms per pose for the placement)."""

    @jax.custom_batching.custom_vmap
    def f(wch, dcdf, j0):
        return _place_plain(wch, dcdf, j0, n_bins)

    @f.def_vmap
    def _rule(axis_size, in_batched, wch, dcdf, j0):
        args = tuple(
            a if b else jnp.broadcast_to(a, (axis_size,) + a.shape)
            for a, b in zip((wch, dcdf, j0), in_batched, strict=True)
        )
        return jax.lax.map(lambda t: f(*t), args), True

    return f


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def _place(wch: Array, dcdf: Array, j0: Array, n_bins: int) -> Array:
    return _place_mapped(n_bins)(wch, dcdf, j0)


@_place.defjvp
def _place_jvp(n_bins, primals, tangents):
    # bilinear in (wch, dcdf); the tangent uses the plain (transposable) form
    wch, dcdf, j0 = primals
    dw, dd, _ = tangents
    out = _place(wch, dcdf, j0, n_bins)
    return out, _place_plain(dw, dcdf, j0, n_bins) + _place_plain(wch, dd, j0, n_bins)


# ----------------------------------------------------------------------------- macro double bounce


@eqx.filter_jit
def _macro_jit(pairs, pose, materials, sensor, sigma, start, width, *, n_bins, projection, brdf):
    from ._macro import macro_profile  # noqa: PLC0415

    dt = pairs.tri.dtype
    rot = quat_to_matrix(pose.quaternion.astype(dt))
    return macro_profile(
        pairs,
        rot,
        pose.position,
        materials,
        sensor,
        sigma,
        start,
        width,
        n_bins=n_bins,
        projection=projection,
        brdf=brdf,
    )


def _scene_macro(scene: Scene, pairs, mats, brdf, dt) -> Array:
    """``(16, n_bins)`` macro double bounce of ``scene`` (concrete pose and pulse) from host
    pairs and materials stacked in ``dt``."""
    cast = lambda t: jax.tree_util.tree_map(lambda a: jnp.asarray(a, dt), t)  # noqa: E731
    bins, pulse = scene.bins, scene.pulse
    shift = 0.5 * C_LIGHT * float(pulse.t0)
    return _macro_jit(
        pairs,
        cast(scene.pose),
        mats,
        cast(scene.sensor),
        jnp.asarray(0.5 * C_LIGHT * float(pulse.sigma_t), dt),
        jnp.asarray(float(bins.start) - shift, dt),
        jnp.asarray(bins.width, dt),
        n_bins=bins.n_bins,
        projection=None,
        brdf=_unchecked_if_concrete(brdf, mats, scene.pose),
    )


def double_bounce(
    scene: Scene,
    *,
    brdf: Callable | None = None,
    dtype=None,
    options=None,
    pairs=None,
) -> Profile:
    """The macro double bounce alone (:mod:`ppr.pulse._macro`): light reflected by one surface of
    the object onto another (a panel against the body) before it returns, summed
    incoherently, as a Mueller :class:`Profile` (what ``simulate(multibounce=True)`` adds to
    the single bounce).

    **Arguments:**

    - `brdf`: Mueller BRDF (default :func:`ppr.mueller_brdf`); glossy parts
      (``m >= options.glossy_m``) take the image method only with the model BRDF.
    - `dtype`: kernel float dtype.
    - `options`: :class:`ppr.MacroOptions` (accuracy knobs).
    - `pairs`: ready :class:`ppr.MacroPairs` at the scene's pose (default: built here).

    Glossy pairs: the Laplace convolution of the two lobes over the exact clipped overlap
    (relative error ~``0.3/m`` on a 90 deg aluminium dihedral, tests/test_macro.py); broad
    pairs converge with the quadrature knobs (bench/bench_macro.py). No gradients through the
    pair selection and visibility (host, like the single bounce's)."""
    from ._macro import part_exponents, pose_pairs  # noqa: PLC0415

    brdf = _default_brdf() if brdf is None else brdf
    mesh, sensor, bins, pulse, pose = scene.mesh, scene.sensor, scene.bins, scene.pulse, scene.pose
    for x, what in ((pose.quaternion, "pose"), (pulse.sigma_t, "pulse")):
        _check_concrete(x, what)
    rot = np.asarray(quat_to_matrix(np.asarray(pose.quaternion, np.float64)))
    dt = jnp.result_type(float) if dtype is None else dtype
    sigma_r = 0.5 * C_LIGHT * float(pulse.sigma_t)
    if pairs is None:
        caster = VisibilityCaster(mesh, scene.vis_samples)
        pairs, _ = pose_pairs(
            mesh,
            caster,
            rot.T @ np.asarray(sensor.laser_dir, np.float64),
            rot.T @ np.asarray(sensor.receiver_dir, np.float64),
            part_exponents(scene.materials),
            brdf,
            options,
            bins=(sigma_r, float(bins.width), bins.n_bins),
            dtype=dt,
        )
    mats = stack_materials(scene.materials)
    mats = jax.tree_util.tree_map(
        lambda a: a.astype(jnp.result_type(dt, jnp.complex64) if jnp.iscomplexobj(a) else dt), mats
    )
    out = _scene_macro(scene, pairs, mats, brdf, dt)
    centres = bins.centres()
    return Profile(
        data=out.reshape(4, 4, bins.n_bins),
        range_m=jnp.asarray(centres),
        time_s=jnp.asarray(2.0 * centres / C_LIGHT),
        edges_m=jnp.asarray(bins.edges()),
        visibility=jnp.zeros(mesh.n_faces),
        reference_range_m=float(bins.reference_range),
        kind="mueller",
        labels=("double",),
    )


# ----------------------------------------------------------------------------- wrapper


class Profile(eqx.Module):
    """Range-resolved result of :func:`simulate`.

    - `data`: ``(4, 4, B)`` Mueller profiles (``kind="mueller"``), ``(S, 4, B)`` Stokes
      profiles per transmitted state (``kind="stokes"``, states named by `labels`) or
      ``(C, B)`` selected Mueller elements (``kind="channels"``). Units m^2/sr per bin
      (bin-integrated, module docstring), sensor frames.
    - `range_m`: ``(B,)`` bin centres, one-way range relative to `reference_range_m`.
    - `time_s`: ``(B,)`` round-trip time of the bin centres relative to the reference's
      return, ``2 r / c``.
    - `edges_m`: ``(B + 1,)`` bin edges (m).
    - `visibility`: ``(F,)`` per-face lit-and-visible fractions used.
    """

    data: Array
    range_m: Array
    time_s: Array
    edges_m: Array
    visibility: Array
    reference_range_m: float = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    labels: tuple = eqx.field(static=True)

    @property
    def total(self) -> Array:
        """Time integral of the return (sum over bins)."""
        return jnp.sum(self.data, axis=-1)

    def to_xarray(self, provenance: dict | None = None):
        """The profile as a labelled ``xarray.Dataset`` (:func:`ppr.profile_dataset`)."""
        from .._labelled import profile_dataset  # noqa: PLC0415

        return profile_dataset(self, provenance=provenance)


def _check_concrete(x, what):
    if isinstance(x, jax.core.Tracer):
        raise ValueError(
            f"simulate() needs a concrete {what} to cast visibility rays; inside jit/grad/vmap "
            "pass visibility=... (host-computed) or call ppr.render directly"
        )


def _simulate_macro(scene, caster, rot, brdf, multibounce, options, dt, offset):
    """Host part of :func:`simulate`'s macro double bounce: ``(MacroPairs or None, range
    interval of its paths or None)`` (``offset``: the position and pulse shift of ranges)."""
    if multibounce is False:
        return None, None
    from ._macro import MacroOptions, macro_geometry, part_exponents, pose_pairs  # noqa: PLC0415

    mesh, sensor = scene.mesh, scene.sensor
    opt = MacroOptions() if options is None else options
    if multibounce == "auto" and macro_geometry(mesh, plates=opt.plates).convex:
        return None, None  # no facing surfaces: exactly zero
    if caster is None:
        caster = VisibilityCaster(mesh, scene.vis_samples)
    u_in = rot.T @ np.asarray(sensor.laser_dir, np.float64)
    u_out = rot.T @ np.asarray(sensor.receiver_dir, np.float64)
    pairs, info = pose_pairs(
        mesh,
        caster,
        u_in,
        u_out,
        part_exponents(scene.materials),
        brdf,
        opt,
        dtype=dt,  # every bin (no static windows): one program for any bins and poses
    )
    if multibounce == "auto" and info["glossy"] + info["broad"] == 0:
        return None, None
    span = info["range"]
    return pairs, None if span is None else (span[0] - offset, span[1] - offset)


def simulate(
    scene: Scene,
    *,
    states: Sequence[str] | Float[ArrayLike, "S 4"] | None = None,
    channels: Sequence[tuple[int, int]] | None = None,
    visibility: Float[ArrayLike, " F"] | None = None,
    brdf: Callable | None = None,
    terms=None,
    prune: bool = True,
    dtype=None,
    multibounce: bool | str = "auto",
    macro_options=None,
) -> Profile:
    """Simulate the range-resolved return of ``scene``.

    **Arguments:**

    - `scene`: :class:`ppr.Scene`.
    - `states`: transmitted Stokes states (names from ``STOKES_STATES`` or ``(S, 4)`` rows):
      return Stokes profiles ``(S, 4, B)``. Default: the full Mueller profile ``(4, 4, B)``.
    - `channels`: Mueller elements ``[(i, j), ...]`` to compute (``(C, B)``), instead.
    - `visibility`: ``(F,)`` lit-and-visible fractions; default: ray-cast at the scene's pose
      (needs concrete pose values).
    - `brdf`: Mueller BRDF callable (default :func:`ppr.mueller_brdf`); `terms` passed to it.
    - `prune`: drop back-facing and invisible facets before the kernel (same result).
    - `dtype`: kernel float dtype (default: the default float, float32 unless x64 is on).
    - `multibounce`: add the macro double bounce between the object's surfaces
      (:mod:`ppr.pulse._macro`; e.g. solar panels against the body). ``"auto"`` (default) leaves it
      out exactly where it is zero: no two surfaces of the mesh face each other (a convex
      mesh), or none of the facing pairs is lit, seen and, for glossy pairs, within
      ``LOBE_CUT`` of sending light to the receiver (the skipped lobe overlaps are below
      ``exp(-LOBE_CUT / 2)`` of their peak). ``True`` always evaluates it, ``False`` never.
    - `macro_options`: :class:`ppr.MacroOptions` (accuracy knobs of the double bounce).

    Faces are one-sided: a face returns light only to the side its outward normal points to
    (counter-clockwise seen from outside); a thin sheet seen from both sides needs two
    back-to-back faces (:func:`ppr.check_mesh` keeps them). ``ppr.image.render_mueller_image``
    shades either side of a face (docs/limits.md).

    Raises ``ValueError`` (before computing anything) if the range gate does not contain every
    visible facet's depth interval +- ``COVER_NSIG`` pulse sigmas (and the double-bounce
    paths' ranges when they are included).
    """
    if multibounce not in (True, False, "auto"):
        raise ValueError(f"multibounce must be True, False or 'auto', got {multibounce!r}")
    if states is not None and channels is not None:
        raise ValueError("give states or channels, not both")
    brdf = _default_brdf() if brdf is None else brdf
    mesh, sensor, bins, pulse, pose = scene.mesh, scene.sensor, scene.bins, scene.pulse, scene.pose
    for x, what in ((pose.quaternion, "pose"), (pose.position, "pose"), (pulse.sigma_t, "pulse")):
        _check_concrete(x, what)
    rot = np.asarray(quat_to_matrix(np.asarray(pose.quaternion, np.float64)))
    u_in = np.asarray(sensor.laser_dir, np.float64)
    u_out = np.asarray(sensor.receiver_dir, np.float64)
    caster = None
    if visibility is None:
        caster = VisibilityCaster(mesh, scene.vis_samples)
        vis = caster.fractions(rot.T @ u_in, rot.T @ u_out)
    else:
        vis = np.asarray(visibility, np.float64)
        if (
            vis.shape != (mesh.n_faces,)
            or not np.all(np.isfinite(vis))
            or np.any(vis < 0)
            or np.any(vis > 1)
        ):
            raise ValueError(
                f"visibility must be ({mesh.n_faces},) fractions in [0, 1], got shape {vis.shape}"
            )
    # projection / labels
    if states is not None:
        names = [s if isinstance(s, str) else None for s in states]
        if all(isinstance(s, str) for s in states):
            bad = [s for s in states if s not in STOKES_STATES]
            if bad:
                raise ValueError(
                    f"unknown transmitted state(s) {bad}; known: {sorted(STOKES_STATES)}"
                )
            svec = np.asarray([STOKES_STATES[s] for s in states])
            labels = tuple(names)
        else:
            svec = np.asarray(states, np.float64)
            if svec.ndim != 2 or svec.shape[1] != 4 or not np.all(np.isfinite(svec)):
                raise ValueError(f"states must be names or (S, 4) Stokes rows, got {svec.tolist()}")
            # a physical (partially) polarized state: S0 > 0 and |S1, S2, S3| <= S0
            dop = np.linalg.norm(svec[:, 1:], axis=1)
            bad = np.flatnonzero(~(svec[:, 0] > 0) | (dop > svec[:, 0] * (1 + 1e-9)))
            if bad.size:
                i = int(bad[0])
                raise ValueError(
                    f"states[{i}] = {svec[i].tolist()}: not a Stokes vector of light (needs S0 > 0 "
                    f"and sqrt(S1^2 + S2^2 + S3^2) <= S0; degree of polarization "
                    f"{dop[i] / svec[i, 0] if svec[i, 0] > 0 else float('inf'):.3g})"
                )
            labels = tuple(str(list(r)) for r in svec)
        proj = stokes_projection(svec)
        kind, out_shape = "stokes", (len(svec), 4)
    elif channels is not None:
        chans = [tuple(int(v) for v in c) for c in channels]
        if not chans or any(len(c) != 2 or not (0 <= c[0] < 4 and 0 <= c[1] < 4) for c in chans):
            raise ValueError(f"channels must be (i, j) pairs with 0 <= i, j < 4, got {channels!r}")
        proj = channel_projection(chans)
        kind, out_shape, labels = "channels", (len(chans),), tuple(chans)
    else:
        proj = None
        kind, out_shape, labels = "mueller", (4, 4), ()
    # geometry on the host: coverage check and window size
    tri = mesh.triangles()
    w = 0.5 * (u_in + u_out)
    pos = np.asarray(pose.position, np.float64)
    sigma_r = 0.5 * C_LIGHT * float(pulse.sigma_t)
    shift = 0.5 * C_LIGHT * float(pulse.t0)
    depth = -(tri @ rot.T @ w) - pos @ w + shift
    keep = vis > 0 if prune else np.ones(mesh.n_faces, bool)
    edges = bins.edges()
    dt = jnp.result_type(float) if dtype is None else dtype
    macro, span = _simulate_macro(
        scene, caster, rot, brdf, multibounce, macro_options, dt, pos @ w - shift
    )
    spans = [] if span is None else [span]
    if np.any(vis > 0):
        spans.append((depth[vis > 0].min(), depth[vis > 0].max()))
    if spans:
        lo = min(a for a, _ in spans) - COVER_NSIG * sigma_r
        hi = max(b for _, b in spans) + COVER_NSIG * sigma_r
        if lo < edges[0] or hi > edges[-1]:
            span_m = float(hi - lo) - 2 * COVER_NSIG * sigma_r
            hint = ""
            if span_m > 100 * (edges[-1] - edges[0]):
                # an object hundreds of times the window: a mesh in mm or cm read as metres?
                hint = (
                    f"; the object is {span_m:.4g} m deep along the line of sight: if its file "
                    "is in millimetres or centimetres, set the mesh's scale (e.g. "
                    "mesh.scale = 0.001)"
                )
            raise ValueError(
                f"range bins [{edges[0]:.4g}, {edges[-1]:.4g}] m do not cover the visible object "
                f"[{lo:.4g}, {hi:.4g}] m (depth +- {COVER_NSIG:g} pulse sigmas); widen or move "
                f"the bins (start, width, count){hint}"
            )
    if not keep.any():
        keep = np.zeros(mesh.n_faces, bool)
        keep[0] = True  # a zero-weight facet keeps the shapes valid (vis = 0)
    from ..geometry._mesh import Mesh  # noqa: PLC0415

    sub = Mesh(
        mesh.vertices, np.asarray(mesh.faces)[keep], np.asarray(mesh.material_ids)[keep], mesh.parts
    )
    arrays = mesh_arrays(sub, capacity_for(int(keep.sum())), dt)
    vis_k = np.zeros(arrays.valid.shape[0])
    vis_k[: int(keep.sum())] = vis[keep]
    max_ext = float(np.ptp(depth[keep], axis=1).max())
    # window from the mesh's longest edge (pose independent, so new poses reuse the
    # compilation as long as the pruned facet count stays in the same capacity bucket)
    max_edge = float(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1).max())
    window = window_size(
        max(max_edge * float(np.linalg.norm(w)), max_ext), sigma_r, float(bins.width), bins.n_bins
    )
    mats = stack_materials(scene.materials)
    mats = jax.tree_util.tree_map(
        lambda a: a.astype(jnp.result_type(dt, jnp.complex64) if jnp.iscomplexobj(a) else dt), mats
    )
    cast = lambda t: jax.tree_util.tree_map(lambda a: jnp.asarray(a, dt), t)  # noqa: E731
    out = render(
        arrays,
        jnp.asarray(vis_k, dt),
        cast(pose),
        mats,
        cast(sensor),
        jnp.asarray(sigma_r, dt),
        jnp.asarray(float(bins.start) - shift, dt),
        jnp.asarray(bins.width, dt),
        n_bins=bins.n_bins,
        window=window,
        projection=None if proj is None else jnp.asarray(proj, dt),
        brdf=brdf,
        terms=terms,
    )
    if macro is not None:
        # the double bounce as its own program, all 16 elements, projected here: simulate
        # calls that differ in states, channels or bin width share its compilation
        m16 = _scene_macro(scene, macro, mats, brdf, dt)
        out = out + (m16 if proj is None else jnp.asarray(proj, dt).T @ m16)
    data = out.reshape(*out_shape, bins.n_bins)
    centres = bins.centres()
    return Profile(
        data=data,
        range_m=jnp.asarray(centres),
        time_s=jnp.asarray(2.0 * centres / C_LIGHT),
        edges_m=jnp.asarray(edges),
        visibility=jnp.asarray(vis),
        reference_range_m=float(bins.reference_range),
        kind=kind,
        labels=labels,
    )


__all__ = [
    "NSIG",
    "Profile",
    "STOKES_STATES",
    "channel_projection",
    "double_bounce",
    "facet_weights",
    "glossy_fresnel_mueller",
    "lambertian_mueller",
    "render",
    "simulate",
    "sensor_terms",
    "stack_materials",
    "stokes_projection",
    "tent_gaussian_cdf",
    "visible_faces",
    "window_size",
]

_ = RangeBins  # re-exported type used in annotations of callers
