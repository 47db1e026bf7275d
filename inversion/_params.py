r"""Inversion parameters: physical values and the unconstrained vector the solvers move.

Physical parameters (:class:`PhysicalParams`) are what the forward model takes and what the
user reads: attitude quaternion, Blinn-Phong exponent ``m``, complex index ``n = n' + i n''``
(one per material slot), surface correlation length, range offset (one-way metres) and
overall gain. Optimistix has no bounded least-squares solver, so the
solvers work on an unconstrained vector ``theta`` (:class:`Parametrisation`):

=================  ==============================  ======================================
group              theta entries                   physical value
=================  ==============================  ======================================
``attitude``       rotation vector ``w`` (rad, 3)  ``q = exp(w) (x) q_ref``
``m``              ``log m``                       ``m = exp(max(., c))`` (> 0)
``n``              ``log n'``, ``u``               ``n' = exp(.)``, ``n'' = softplus(max(u, c))``
``corr_length``    ``log d``                       ``d = exp(.)`` (> 0)
``range_offset``   ``r / range_scale``             ``r`` (metres)
``gain``           ``log g``                       ``g = exp(.)`` (> 0)
``thickness``      ``log t`` per coated slot       ``t = exp(.)`` (metres, > 0)
=================  ==============================  ======================================

``thickness`` is the thickness of one film layer per coated material slot (the slots listed in
``PhysicalParams.thickness_slots``; :class:`~inversion.SimulatorModel` names them and the
layer: the thick layer of a stack that has one, else its outermost).

Quaternions are scalar-first ``(w, x, y, z)``, Hamilton product, active rotation body ->
sensor frame (``v_sensor = q v_body q*``). The attitude perturbation is applied on the left,
i.e. ``w`` is a small rotation expressed in the *sensor* frame about the reference attitude
``q_ref``; near the optimum the covariance of ``w`` is the attitude error (reported in degrees).

The clamps at ``-20.72`` (``m``, ``n''`` = ``1e-9``, physically zero) give a flat region so
that a damped solver stops when the optimum lies on the boundary (a dielectric's ``n'' = 0``);
``from_physical`` maps ``m, n'' < 1e-9`` to ``1e-9``. The refiners lift *starting points*
to ``m, n'' >= 1e-6`` (:func:`lift_start`), where the coordinates still have a gradient.

Only the groups listed in ``free`` enter ``theta``; the others keep the reference's values.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float

from ppr.geometry import quat_conjugate, quat_from_rotvec, quat_multiply, rotvec_from_quat

__all__ = [
    "GROUPS",
    "GAIN_RANGE",
    "BOX_FIELDS",
    "PhysicalParams",
    "Parametrisation",
    "lift_start",
]

GROUPS = ("attitude", "m", "n", "corr_length", "range_offset", "gain", "thickness")
# Default range of the gain (counts per m^2 sr^-1, PhysicalParams.gain) for priors and bounds.
# At the target, a pulse of energy E over a beam of area A_beam gives the fluence E / A_beam;
# the receiver of area A_rx at range R sees the solid angle A_rx / R^2; the detector counts
# eta / (h nu) per joule after the two-way transmission T^2. So
#     gain = E / A_beam * A_rx / R^2 * T^2 * eta / (h nu):
# 10 mJ at 532 nm into a 20 urad beam, a 1 m^2 telescope, 1000 km, T^2 eta = 0.15 gives ~10;
# a laboratory set-up (1 mJ, 0.5 m beam at 10 m, 100 cm^2 aperture, eta = 0.2) ~3e11. The range
# holds both with six decades to spare either way.
GAIN_RANGE = (1e-6, 1e18)
DEFAULT_FREE = ("attitude", "m", "n", "range_offset", "gain")

# Physical values 0 of m and n'' are mapped to these floors by ``from_physical`` (equal to the
# clamps below, so a round trip through theta never moves a point).
N_IMAG_FLOOR = 1e-9
M_FLOOR = 1e-9
# Inside ``to_physical`` the log/softplus coordinates are clamped from below (values ~1e-9,
# physically zero). The flat region makes a damped solver *stop* when the optimum is on the
# boundary (n'' = 0 for a dielectric, m = 0): with a pure softplus/exp map the coordinate
# would run to -inf and the solver never meet its step tolerance.
U_N_IMAG_MIN = -20.72326583694641  # softplus^-1(1e-9) = log(expm1(1e-9))
LOG_M_MIN = -20.72326583694641  # log(1e-9)
# film thicknesses below this (metres, a hundredth of an atomic layer) map to it in theta
THICKNESS_FLOOR = 1e-12


def _softplus(u):
    return jnp.logaddexp(u, 0.0)


def _softplus_inv(x):
    x = jnp.maximum(x, N_IMAG_FLOOR)
    # log(expm1(x)) written to stay accurate for small and large x.
    return x + jnp.log(-jnp.expm1(-x))


class PhysicalParams(eqx.Module):
    """Continuous object parameters in physical units (what the forward model consumes).

    **Fields:**

    - `quaternion`: attitude, scalar-first unit quaternion ``(4,)``, body -> sensor frame.
    - `m`: Blinn-Phong exponent per material slot ``(K,)``.
    - `n`: complex refractive index per material slot ``(K,)``, ``n'' >= 0``.
    - `corr_length`: surface correlation length per material slot ``(K,)``, metres.
    - `range_offset`: one-way range offset, metres (shifts the profile to larger range).
    - `thickness`: thickness (metres, >= 0) of the fitted film layer per material slot
      ``(K,)``; only the slots in `thickness_slots` (static) have one (the others hold 0).
    - `gain`: overall gain, > 0: expected counts per unit of the forward model's profile. For
      :class:`~inversion.SimulatorModel` (``counts = gain x J + background`` with ``J`` the
      bin-integrated Mueller radiant intensity per unit irradiance of :func:`ppr.render`, in
      m^2 sr^-1) it is in **counts per (m^2 sr^-1)**: pulse fluence at the target x receiver
      solid angle x two-way transmission x detector efficiency / photon energy (see
      :data:`GAIN_RANGE` for magnitudes, ~10 for ranging to debris in low orbit, ~1e11 in a
      laboratory).
    """

    quaternion: Float[Array, "4"]
    m: Float[Array, " K"]
    n: Complex[Array, " K"]
    corr_length: Float[Array, " K"]
    range_offset: Float[Array, ""]
    gain: Float[Array, ""]
    thickness: Float[Array, " K"]
    thickness_slots: tuple[int, ...] = eqx.field(static=True, default=())

    def __init__(
        self,
        quaternion,
        m,
        n,
        corr_length=5e-6,
        range_offset=0.0,
        gain=1.0,
        thickness=0.0,
        thickness_slots=(),
    ):
        dt = jnp.result_type(float)
        q = jnp.asarray(quaternion)
        if not jnp.issubdtype(q.dtype, jnp.floating):
            q = q.astype(dt)
        dt = q.dtype
        m = jnp.atleast_1d(jnp.asarray(m, dt))
        cdt = jnp.result_type(dt, jnp.complex64)
        n = jnp.atleast_1d(jnp.asarray(n)).astype(cdt)
        if m.ndim != 1 or m.shape[0] == 0:
            raise ValueError(
                f"PhysicalParams.m must hold one value per material slot (at least one), got "
                f"shape {m.shape}"
            )
        for name, v in (("n", n), ("corr_length", corr_length), ("thickness", thickness)):
            shape = np.shape(v)
            if len(shape) > 1 or (len(shape) == 1 and shape[0] not in (1, m.shape[0])):
                raise ValueError(
                    f"PhysicalParams.{name} has shape {shape} but m has {m.shape[0]} material "
                    f"slot(s): give one value per slot, or one for every slot"
                )
        corr = jnp.broadcast_to(jnp.asarray(corr_length, dt), m.shape)
        self.quaternion = q
        self.m = m
        self.n = jnp.broadcast_to(n, m.shape)
        self.corr_length = corr
        self.range_offset = jnp.asarray(range_offset, dt)
        self.gain = jnp.asarray(gain, dt)
        self.thickness = jnp.broadcast_to(jnp.asarray(thickness, dt), m.shape)
        self.thickness_slots = tuple(int(i) for i in thickness_slots)

    def __check_init__(self):
        concrete = not any(
            isinstance(x, jax.core.Tracer)
            for x in (self.quaternion, self.m, self.n, self.corr_length, self.gain)
        )
        if self.quaternion.shape != (4,):
            raise ValueError(
                f"PhysicalParams.quaternion must have shape (4,), got {self.quaternion.shape}"
            )
        k = int(self.m.shape[0])
        bad = [i for i in self.thickness_slots if not 0 <= i < k]
        if bad or len(set(self.thickness_slots)) != len(self.thickness_slots):
            raise ValueError(
                f"PhysicalParams.thickness_slots must be distinct material slots in [0, {k}), "
                f"got {self.thickness_slots}"
            )
        if not concrete or isinstance(self.thickness, jax.core.Tracer):
            return
        t = np.asarray(self.thickness)
        if not np.all(np.isfinite(t)) or np.any(t < 0):
            raise ValueError(f"PhysicalParams.thickness must be finite and >= 0 metres, got {t!r}")
        q = np.asarray(self.quaternion)
        if not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1.0) > 1e-3:
            raise ValueError(
                "PhysicalParams.quaternion must be a finite unit quaternion (w, x, y, z) within "
                f"|norm - 1| <= 1e-3, got {q.tolist()} with norm {np.linalg.norm(q):.6g}"
            )
        for name in ("m", "corr_length", "range_offset", "gain"):
            a = np.asarray(getattr(self, name))
            if not np.all(np.isfinite(a)):
                raise ValueError(f"PhysicalParams.{name} must be finite, got {a!r}")
        n = np.asarray(self.n)
        if not np.all(np.isfinite(n)) or np.any(n.imag < 0) or np.any(n.real <= 0):
            raise ValueError(f"PhysicalParams.n must be finite with n' > 0 and n'' >= 0, got {n!r}")
        if np.any(np.asarray(self.m) < 0):
            raise ValueError(f"PhysicalParams.m must be >= 0, got {np.asarray(self.m)!r}")
        if np.any(np.asarray(self.gain) <= 0) or np.any(np.asarray(self.corr_length) <= 0):
            raise ValueError(
                "PhysicalParams.gain and corr_length must be > 0, got "
                f"gain={np.asarray(self.gain)!r}, "
                f"corr_length={np.asarray(self.corr_length)!r}"
            )

    @classmethod
    def from_scene(cls, scene, *, range_offset: float = 0.0, gain: float = 1.0):
        """The parameters of a :class:`ppr.Scene`: its pose's attitude and each part's
        material (``m``, ``n``, correlation length); e.g. the truth of a simulated
        observation."""
        mats = scene.materials
        return cls(
            np.asarray(scene.pose.quaternion, np.float64),
            [float(np.asarray(m.m)) for m in mats],
            [complex(np.asarray(m.n)) for m in mats],
            [float(np.asarray(m.corr_length)) for m in mats],
            range_offset=range_offset,
            gain=gain,
        )

    @property
    def n_materials(self) -> int:
        return int(self.m.shape[0])

    def unit_quaternion(self) -> Float[Array, "4"]:
        q = self.quaternion / jnp.linalg.norm(self.quaternion)
        return jnp.where(q[0] < 0, -q, q)


# --------------------------------------------------------------------------- reparametrisation
BOX_FIELDS = ("m", "n_re", "n_im", "corr_length", "range_offset", "gain", "thickness")
"""The physical quantities a :class:`Parametrisation`'s box bounds (columns of its ``box``)."""


def box_array(bounds=None) -> Array:
    """``(2, len(BOX_FIELDS))`` array of a physical box: row 0 the low, row 1 the high bounds.

    ``bounds``: ``None`` (unbounded: -inf / +inf), an object with the fields of
    :data:`BOX_FIELDS` as ``(low, high)`` pairs (:class:`inversion.PhysicalBounds`), or such
    an array (returned as is)."""
    if bounds is None:
        inf = np.full(len(BOX_FIELDS), np.inf)
        return jnp.asarray(np.stack([-inf, inf]), jnp.result_type(float))
    if isinstance(bounds, (jax.Array, np.ndarray)):
        if bounds.shape != (2, len(BOX_FIELDS)):
            raise ValueError(
                f"Parametrisation bounds: a box array has shape (2, {len(BOX_FIELDS)}) "
                f"(low / high of {BOX_FIELDS}), got {bounds.shape}"
            )
        return bounds
    rows = np.asarray([tuple(getattr(bounds, f)) for f in BOX_FIELDS], np.float64).T
    return jnp.asarray(rows, jnp.result_type(float))


def group_sizes(reference: PhysicalParams) -> dict[str, int]:
    """Number of solver coordinates of each parameter group for ``reference``'s materials."""
    k = reference.n_materials
    return {
        "attitude": 3,
        "m": k,
        "n": 2 * k,
        "corr_length": k,
        "range_offset": 1,
        "gain": 1,
        "thickness": len(reference.thickness_slots),
    }


class Parametrisation(eqx.Module):
    """Map between the unconstrained solver vector ``theta`` and :class:`PhysicalParams`.

    **Arguments:**

    - `reference`: physical parameters giving the reference attitude ``q_ref`` (``theta``'s
      rotation vector is measured from it) and the values of the groups that are not free.
    - `free`: names from :data:`GROUPS` that are fitted (static; order in ``theta`` follows
      :data:`GROUPS`). Default: everything but ``corr_length``.
    - `range_scale`: metres per unit of the range-offset entry of ``theta`` (keeps all entries
      O(1) for the damped solvers; default 1 cm).

    ``to_physical`` / ``from_physical`` are jittable and differentiable. ``physical_vector``
    gives a flat vector in user units (attitude as a rotation vector in *degrees* about
    ``q_ref``, ``m``, ``n'``, ``n''``, corr. length in metres, range offset in metres, gain);
    ``labels`` names its entries; covariances are reported in that vector's coordinates.
    - `bounds`: an optional physical box (an object with the fields of :data:`BOX_FIELDS`
      as ``(low, high)`` pairs, e.g. :class:`inversion.PhysicalBounds`, or the ``(2, 7)``
      array :attr:`box`). ``to_physical`` clamps each free group's physical values into it
      (``clip``: identity inside, a flat region outside), so an unbounded solver stays in the
      box and a parameter whose optimum lies beyond a bound stops on it, the way the floors of
      ``m`` and ``n''`` work. Unbounded by default (infinite box: ``to_physical`` is then
      the same function). The box is a traced array: bounded and unbounded fits share one
      compiled solver.
    """

    reference: PhysicalParams
    free: tuple[str, ...] = eqx.field(static=True, default=DEFAULT_FREE)
    range_scale: float = eqx.field(static=True, default=0.01)
    # (2, len(BOX_FIELDS)) physical box, rows low / high; +-inf where unbounded. Always an
    # array (never None), so a bounded and an unbounded parametrisation share every program
    box: Array = None  # type: ignore[assignment]

    def __init__(self, reference, free=DEFAULT_FREE, range_scale=0.01, bounds=None):
        self.reference = reference
        self.free = free
        self.range_scale = range_scale
        self.box = box_array(bounds)

    def __check_init__(self):
        if not self.free:
            raise ValueError(f"free: no parameter group is free; name at least one of {GROUPS}")
        bad = [g for g in self.free if g not in GROUPS]
        if bad:
            raise ValueError(f"Parametrisation.free: unknown group(s) {bad}; known: {GROUPS}")
        if len(set(self.free)) != len(self.free):
            raise ValueError(f"Parametrisation.free has duplicates: {self.free}")
        if not self.range_scale > 0:
            raise ValueError(f"Parametrisation.range_scale must be > 0, got {self.range_scale}")

    # -- layout
    @property
    def ordered_free(self) -> tuple[str, ...]:
        return tuple(g for g in GROUPS if g in self.free)

    def _sizes(self) -> dict[str, int]:
        return group_sizes(self.reference)

    @property
    def size(self) -> int:
        s = self._sizes()
        return sum(s[g] for g in self.ordered_free)

    @property
    def labels(self) -> list[str]:
        """Names (with units) of the entries of :meth:`physical_vector` / the covariance."""
        k = self.reference.n_materials
        out: list[str] = []
        for g in self.ordered_free:
            if g == "attitude":
                out += ["rot_x [deg]", "rot_y [deg]", "rot_z [deg]"]
            elif g == "m":
                out += [f"m[{i}]" for i in range(k)]
            elif g == "n":
                out += [f"n_re[{i}]" for i in range(k)] + [f"n_im[{i}]" for i in range(k)]
            elif g == "corr_length":
                out += [f"corr_length[{i}] [m]" for i in range(k)]
            elif g == "range_offset":
                out += ["range_offset [m]"]
            elif g == "gain":
                out += ["gain"]
            elif g == "thickness":
                out += [f"thickness[{i}] [m]" for i in self.reference.thickness_slots]
        return out

    @property
    def theta_labels(self) -> list[str]:
        k = self.reference.n_materials
        out: list[str] = []
        for g in self.ordered_free:
            if g == "attitude":
                out += ["rotvec_x", "rotvec_y", "rotvec_z"]
            elif g == "m":
                out += [f"log_m[{i}]" for i in range(k)]
            elif g == "n":
                out += [f"log_n_re[{i}]" for i in range(k)] + [
                    f"softplus_inv_n_im[{i}]" for i in range(k)
                ]
            elif g == "corr_length":
                out += [f"log_corr_length[{i}]" for i in range(k)]
            elif g == "range_offset":
                out += ["range_offset/range_scale"]
            elif g == "gain":
                out += ["log_gain"]
            elif g == "thickness":
                out += [f"log_thickness[{i}]" for i in self.reference.thickness_slots]
        return out

    def _split(self, theta: Array) -> dict[str, Array]:
        sizes = self._sizes()
        out, i = {}, 0
        for g in self.ordered_free:
            out[g] = theta[i : i + sizes[g]]
            i += sizes[g]
        return out

    # -- maps
    def to_physical(self, theta: Float[Array, " P"]) -> PhysicalParams:
        """Physical parameters of an unconstrained vector (jittable, differentiable)."""
        ref = self.reference
        parts = self._split(theta)
        k = ref.n_materials
        box = jnp.asarray(self.box).astype(theta.dtype)

        def clip(x, field):  # into the box (identity when unbounded)
            j = BOX_FIELDS.index(field)
            return jnp.clip(x, box[0, j], box[1, j])

        q = ref.unit_quaternion().astype(theta.dtype)
        if "attitude" in parts:
            q = quat_multiply(quat_from_rotvec(parts["attitude"]), q)
        m = (
            clip(jnp.exp(jnp.maximum(parts["m"], LOG_M_MIN)), "m")
            if "m" in parts
            else ref.m.astype(theta.dtype)
        )
        if "n" in parts:
            n_re = clip(jnp.exp(parts["n"][:k]), "n_re")
            n_im = clip(_softplus(jnp.maximum(parts["n"][k:], U_N_IMAG_MIN)), "n_im")
            n = jax.lax.complex(n_re, n_im)
        else:
            n = ref.n
        corr = (
            clip(jnp.exp(parts["corr_length"]), "corr_length")
            if "corr_length" in parts
            else ref.corr_length
        )
        off = (
            clip(parts["range_offset"][0] * self.range_scale, "range_offset")
            if "range_offset" in parts
            else ref.range_offset
        )
        gain = clip(jnp.exp(parts["gain"][0]), "gain") if "gain" in parts else ref.gain
        thick = ref.thickness.astype(theta.dtype)
        if "thickness" in parts and ref.thickness_slots:
            thick = thick.at[jnp.asarray(ref.thickness_slots)].set(
                clip(jnp.exp(parts["thickness"]), "thickness")
            )
        return PhysicalParams(q, m, n, corr, off, gain, thick, ref.thickness_slots)

    def from_physical(self, phys: PhysicalParams) -> Float[Array, " P"]:
        """Unconstrained vector of physical parameters (``m = 0`` and ``n'' = 0`` are mapped to
        the floors ``1e-6`` of their log/softplus coordinates)."""
        ref = self.reference
        pieces = []
        dt = phys.m.dtype
        for g in self.ordered_free:
            if g == "attitude":
                q_ref = ref.unit_quaternion().astype(dt)
                dq = quat_multiply(phys.unit_quaternion(), quat_conjugate(q_ref))
                pieces.append(rotvec_from_quat(dq))
            elif g == "m":
                pieces.append(jnp.log(jnp.maximum(phys.m, M_FLOOR)))
            elif g == "n":
                pieces.append(jnp.log(jnp.real(phys.n)))
                pieces.append(_softplus_inv(jnp.imag(phys.n)))
            elif g == "corr_length":
                pieces.append(jnp.log(phys.corr_length))
            elif g == "range_offset":
                pieces.append(jnp.reshape(phys.range_offset / self.range_scale, (1,)))
            elif g == "gain":
                pieces.append(jnp.reshape(jnp.log(phys.gain), (1,)))
            elif g == "thickness":
                t = phys.thickness[jnp.asarray(ref.thickness_slots, jnp.int32)]
                pieces.append(jnp.log(jnp.maximum(t, THICKNESS_FLOOR)))
        return jnp.concatenate([jnp.asarray(p, dt) for p in pieces])

    def physical_vector(self, theta: Float[Array, " P"]) -> Float[Array, " P"]:
        """Flat vector in user units (see :attr:`labels`) of ``theta`` (differentiable)."""
        parts = self._split(theta)
        phys = self.to_physical(theta)
        k = self.reference.n_materials
        pieces = []
        for g in self.ordered_free:
            if g == "attitude":
                pieces.append(jnp.degrees(parts["attitude"]))
            elif g == "m":
                pieces.append(phys.m)
            elif g == "n":
                pieces.append(jnp.real(phys.n)[:k])
                pieces.append(jnp.imag(phys.n)[:k])
            elif g == "corr_length":
                pieces.append(phys.corr_length)
            elif g == "range_offset":
                pieces.append(jnp.reshape(phys.range_offset, (1,)))
            elif g == "gain":
                pieces.append(jnp.reshape(phys.gain, (1,)))
            elif g == "thickness":
                slots = jnp.asarray(self.reference.thickness_slots, jnp.int32)
                pieces.append(phys.thickness[slots])
        return jnp.concatenate(pieces)

    def recentred(self, phys: PhysicalParams) -> Parametrisation:
        """Same layout with the reference moved to ``phys`` (so its rotation vector is 0)."""
        return Parametrisation(phys, self.free, self.range_scale, self.box)

    def with_reference(self, phys: PhysicalParams) -> Parametrisation:
        return self.recentred(phys)


def lift_start(phys: PhysicalParams, floor: float = 1e-6) -> PhysicalParams:
    """``phys`` with ``m`` and ``n''`` raised to at least ``floor`` (a start off the clamp)."""
    n = jnp.asarray(phys.n)
    n = jax.lax.complex(jnp.real(n), jnp.maximum(jnp.imag(n), floor))
    return PhysicalParams(
        phys.quaternion,
        jnp.maximum(phys.m, floor),
        n,
        phys.corr_length,
        phys.range_offset,
        phys.gain,
        phys.thickness,
        phys.thickness_slots,
    )
