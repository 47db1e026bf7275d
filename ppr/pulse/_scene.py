r"""Scenes: a posed mesh with materials per part, a sensor, a pulse and range bins.

Geometry (far field, plane waves)
    World coordinates. The object's body frame is rotated into the world by the attitude
    quaternion and shifted by ``position`` (metres, relative to the reference point whose
    one-way range ``reference_range`` is held in float64 on the host and never enters a
    kernel). ``Sensor.laser_dir`` points from the object toward the laser (every facet's
    ``k_in``), ``Sensor.receiver_dir`` from the object toward the receiver (``k_out``);
    monostatic is ``receiver_dir == laser_dir``, a bistatic angle ``beta`` tilts
    ``receiver_dir`` away from ``laser_dir`` by ``beta``. The *line of sight* of configs is the
    propagation direction of the laser, ``-laser_dir``.

Range
    A point ``x`` returns after ``(|L - x| + |R - x|) / c``. In the far field
    ``|L - x| = R_L - x . u_in`` (``u_in = laser_dir``) and likewise for the receiver, so the
    one-way range (``c t / 2``) relative to the reference is

        r(x) = -x . w,    w = (u_in + u_out) / 2,    |w| = cos(beta / 2)

    i.e. the depth along the bisector. A position offset ``p`` shifts every range by ``-p . w``
    and the pulse time offset ``t0`` by ``c t0 / 2``.

Polarization frames
    ``Sensor.frame_tx`` is the x axis of the transmitted beam's Stokes frame (beam travelling
    along ``-laser_dir``), ``Sensor.frame_rx`` the x axis of the received beam's frame (beam
    travelling along ``+receiver_dir``), both in world coordinates and perpendicular to their
    beam; the y axes follow from :mod:`ppr.optics.conventions` (``y = d x x``). By default both are
    the projection of one world reference vector ``x_ref`` ("horizontal" of the sensor).

Pulse
    Gaussian in time with ``sigma_t = sqrt((FWHM / (2 sqrt(2 ln 2)))^2 + jitter^2)`` (receiver
    timing jitter adds in quadrature), in range ``sigma_r = c sigma_t / 2``.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Annotated, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pydantic

from .._config import ConfigError, StrictModel, config_source, load_toml_model
from .._types import Array
from ..geometry._mesh import Mesh, check_mesh, load_mesh
from ..geometry._rotation import check_quaternion
from ..materials._material import Material
from ..optics.conventions import C_LIGHT, DEFAULT_WAVELENGTH_M

FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
UNIT_TOL = 1e-6


def _f(x):
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _unit(v, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite 3-vector, got {np.asarray(v).tolist()}")
    n = np.linalg.norm(a)
    if n == 0:
        raise ValueError(f"{name} must be non-zero, got {a.tolist()}")
    return a / n


def _perp(x_ref: np.ndarray, d: np.ndarray, name: str) -> np.ndarray:
    x = x_ref - np.dot(x_ref, d) * d
    n = np.linalg.norm(x)
    if n < 1e-6:
        raise ValueError(
            f"{name} {x_ref.tolist()} is parallel to the beam direction {d.tolist()}; "
            "the polarization reference must have a component perpendicular to the beam"
        )
    return x / n


class Sensor(eqx.Module):
    """Laser/receiver directions, polarization reference frames and wavelength (see the
    module docstring). Build with :meth:`Sensor.make`.

    ``monostatic`` (static): ``receiver_dir`` equals ``laser_dir`` exactly. Default: derived
    from concrete directions (False for traced ones); ``True`` for concrete unequal directions
    is an error. A monostatic sensor's facets are evaluated with ``k_out`` the same array as
    ``k_in``, which selects the exact-backscatter BRDF kernel (:func:`ppr.mueller_brdf`,
    "Exact backscatter"); being static, the choice survives ``jit`` over the sensor."""

    laser_dir: Array = eqx.field(converter=_f)
    receiver_dir: Array = eqx.field(converter=_f)
    frame_tx: Array = eqx.field(converter=_f)
    frame_rx: Array = eqx.field(converter=_f)
    wavelength: Array = eqx.field(converter=_f, default=DEFAULT_WAVELENGTH_M)
    monostatic: bool | None = eqx.field(static=True, default=None)

    def __post_init__(self):
        if self.monostatic is None:
            a, b = self.laser_dir, self.receiver_dir
            self.monostatic = bool(
                _concrete(a) and _concrete(b) and np.array_equal(np.asarray(a), np.asarray(b))
            )

    def __check_init__(self):
        a, b = self.laser_dir, self.receiver_dir
        if self.monostatic and _concrete(a) and _concrete(b):
            if not np.array_equal(np.asarray(a), np.asarray(b)):
                raise ValueError(
                    "Sensor.monostatic=True needs receiver_dir equal to laser_dir, got "
                    f"laser_dir {np.asarray(a).tolist()}, receiver_dir {np.asarray(b).tolist()}"
                )
        for name in ("laser_dir", "receiver_dir", "frame_tx", "frame_rx"):
            v = getattr(self, name)
            if v.shape[-1:] != (3,):
                raise ValueError(f"Sensor.{name} must have shape (..., 3), got {v.shape}")
            if _concrete(v):
                a = np.asarray(v, np.float64)
                if not np.all(np.isfinite(a)) or np.any(
                    np.abs(np.linalg.norm(a, axis=-1) - 1) > 1e-4
                ):
                    raise ValueError(
                        f"Sensor.{name} must be a finite unit vector, got {a.tolist()}"
                    )
        a, b = self.laser_dir, self.receiver_dir
        if _concrete(a) and _concrete(b):
            cos_b = np.sum(np.asarray(a, np.float64) * np.asarray(b, np.float64), -1)
            if np.any(cos_b <= 0):
                angle = np.degrees(np.arccos(np.clip(np.min(cos_b), -1.0, 1.0)))
                raise ValueError(
                    f"Sensor: the bistatic angle between laser_dir and receiver_dir is "
                    f"{angle:.4g} deg; it must be below 90 deg (as Sensor.make requires: the "
                    "range of a point is measured along their bisector, 0 at 180 deg)"
                )
        for f, d in (("frame_tx", "laser_dir"), ("frame_rx", "receiver_dir")):
            a, b = getattr(self, f), getattr(self, d)
            if _concrete(a) and _concrete(b):
                dot = np.abs(np.sum(np.asarray(a, np.float64) * np.asarray(b, np.float64), -1))
                if np.any(dot > 1e-4):
                    raise ValueError(
                        f"Sensor.{f} must be perpendicular to Sensor.{d}, "
                        f"got |dot| = {dot.tolist()}"
                    )
        if _concrete(self.wavelength):
            wl = np.asarray(self.wavelength)
            if not np.all(np.isfinite(wl)) or np.any(wl <= 0) or np.any(wl > 1e-3):
                raise ValueError(
                    f"Sensor.wavelength must be a positive length in metres (e.g. 532e-9; "
                    f"above 1 mm is taken for nanometres), got {wl!r}"
                )

    @classmethod
    def make(
        cls,
        line_of_sight=(0.0, 0.0, -1.0),
        x_ref=(1.0, 0.0, 0.0),
        *,
        bistatic_angle: float = 0.0,
        bistatic_azimuth: float = 0.0,
        receiver_dir=None,
        wavelength: float = DEFAULT_WAVELENGTH_M,
    ) -> Sensor:
        """Sensor from the laser's line of sight (propagation direction, sensor -> object),
        a polarization reference vector ``x_ref`` (projected perpendicular to each beam), and
        either a bistatic angle (rad; the receiver direction is ``laser_dir`` tilted by it
        toward ``cos(az) x + sin(az) y`` of the transmitted frame) or an explicit
        ``receiver_dir`` (object -> receiver)."""
        u_in = -_unit(line_of_sight, "line_of_sight")
        xr = _unit(x_ref, "x_ref")
        x_tx = _perp(xr, u_in, "x_ref")
        if receiver_dir is not None:
            if bistatic_angle != 0.0:
                raise ValueError("give either bistatic_angle or receiver_dir, not both")
            u_out = _unit(receiver_dir, "receiver_dir")
        else:
            b = float(bistatic_angle)
            if not (np.isfinite(b) and 0.0 <= b < np.pi / 2):
                raise ValueError(f"bistatic_angle must be in [0, pi/2) rad, got {bistatic_angle!r}")
            y_tx = np.cross(-u_in, x_tx)
            az = float(bistatic_azimuth)
            if b == 0.0:
                u_out = u_in.copy()  # exactly monostatic (no renormalization rounding)
            else:
                u_out = np.cos(b) * u_in + np.sin(b) * (np.cos(az) * x_tx + np.sin(az) * y_tx)
                u_out /= np.linalg.norm(u_out)
        if np.dot(u_in, u_out) <= 0:
            raise ValueError(
                f"receiver_dir {u_out.tolist()} is more than 90 deg from the laser direction"
            )
        x_rx = _perp(xr, u_out, "x_ref")
        return cls(u_in, u_out, x_tx, x_rx, wavelength)

    @property
    def bisector(self) -> Array:
        """``w = (laser_dir + receiver_dir) / 2``: range of a point x is ``-x . w``."""
        return 0.5 * (self.laser_dir + self.receiver_dir)


class Pulse(eqx.Module):
    """Gaussian pulse: ``sigma_t`` (s, including receiver jitter) and time offset ``t0`` (s).
    Build with :meth:`Pulse.gaussian`."""

    sigma_t: Array = eqx.field(converter=_f)
    t0: Array = eqx.field(converter=_f, default=0.0)

    def __check_init__(self):
        if _concrete(self.sigma_t):
            s = np.asarray(self.sigma_t)
            if not np.all(np.isfinite(s)) or np.any(s <= 0):
                raise ValueError(f"Pulse.sigma_t must be a positive duration in seconds, got {s!r}")
        if _concrete(self.t0) and not np.all(np.isfinite(np.asarray(self.t0))):
            raise ValueError(f"Pulse.t0 must be finite, got {np.asarray(self.t0)!r}")

    @classmethod
    def gaussian(cls, fwhm: float, jitter: float = 0.0, t0: float = 0.0) -> Pulse:
        """Pulse from its FWHM (s) and the receiver's RMS timing jitter (s)."""
        fw, jt = np.asarray(fwhm, np.float64), np.asarray(jitter, np.float64)
        if not np.all(np.isfinite(fw)) or np.any(fw <= 0):
            raise ValueError(f"pulse fwhm must be a positive duration in seconds, got {fwhm!r}")
        if not np.all(np.isfinite(jt)) or np.any(jt < 0):
            raise ValueError(
                f"pulse jitter must be a non-negative duration in seconds, got {jitter!r}"
            )
        return cls(np.sqrt((fw * FWHM_TO_SIGMA) ** 2 + jt**2), t0)

    @property
    def sigma_range(self) -> Array:
        """Pulse RMS width in one-way range (m): ``c sigma_t / 2``."""
        return 0.5 * C_LIGHT * self.sigma_t


class RangeBins(eqx.Module):
    """Range gate: ``n_bins`` bins of ``width`` metres starting at ``start`` (one-way range
    relative to the float64 host ``reference_range``)."""

    start: Array = eqx.field(converter=_f)
    width: Array = eqx.field(converter=_f)
    n_bins: int = eqx.field(static=True)
    reference_range: float = eqx.field(static=True, default=0.0)

    def __check_init__(self):
        if not isinstance(self.n_bins, int) or self.n_bins < 1:
            raise ValueError(f"RangeBins.n_bins must be a positive int, got {self.n_bins!r}")
        if _concrete(self.width):
            w = np.asarray(self.width)
            if not np.all(np.isfinite(w)) or np.any(w <= 0):
                raise ValueError(f"RangeBins.width must be a positive length in metres, got {w!r}")
        if _concrete(self.start) and not np.all(np.isfinite(np.asarray(self.start))):
            raise ValueError(f"RangeBins.start must be finite, got {np.asarray(self.start)!r}")
        if not math.isfinite(self.reference_range) or self.reference_range < 0:
            raise ValueError(
                f"RangeBins.reference_range must be >= 0 m, got {self.reference_range!r}"
            )

    @classmethod
    def centred(cls, width: float, n_bins: int, reference_range: float = 0.0) -> RangeBins:
        """Bins centred on the reference point."""
        return cls(-0.5 * width * n_bins, width, int(n_bins), float(reference_range))

    def edges(self) -> np.ndarray:
        """Bin edges (m, relative range), host float64."""
        return float(self.start) + float(self.width) * np.arange(self.n_bins + 1)

    def centres(self) -> np.ndarray:
        return float(self.start) + float(self.width) * (np.arange(self.n_bins) + 0.5)


class Pose(eqx.Module):
    """Attitude quaternion ``(w, x, y, z)`` (body -> world) and position offset (m, world,
    relative to the reference point)."""

    quaternion: Array = eqx.field(converter=_f)
    position: Array = eqx.field(converter=_f, default=(0.0, 0.0, 0.0))

    def __check_init__(self):
        if _concrete(self.quaternion):
            check_quaternion(self.quaternion, "Pose.quaternion")
        if self.position.shape[-1:] != (3,):
            raise ValueError(f"Pose.position must have shape (..., 3), got {self.position.shape}")
        if _concrete(self.position) and not np.all(np.isfinite(np.asarray(self.position))):
            raise ValueError(
                f"Pose.position must be finite, got {np.asarray(self.position).tolist()}"
            )


class Scene(eqx.Module):
    """Everything :func:`ppr.simulate` needs.

    - `mesh`: :class:`ppr.Mesh` (body frame); `materials`: one :class:`ppr.Material` per
      ``mesh.parts`` entry, same order.
    - `pose`, `sensor`, `pulse`, `bins`: see the classes.
    - `vis_samples`: barycentric sample points per face for the visibility fractions
      (a perfect square: 1, 4, 9, 16, ...).
    """

    mesh: Mesh
    materials: tuple[Material, ...]
    pose: Pose
    sensor: Sensor
    pulse: Pulse
    bins: RangeBins
    vis_samples: int = eqx.field(static=True, default=16)

    def __check_init__(self):
        if len(self.materials) != len(self.mesh.parts):
            raise ValueError(
                f"Scene.materials has {len(self.materials)} entries but the mesh has parts "
                f"{self.mesh.parts}: give one Material per part"
            )
        for i, m in enumerate(self.materials):
            if not isinstance(m, Material):
                raise ValueError(
                    f"Scene.materials[{i}] must be a ppr.Material, got {type(m).__name__}"
                )
            lam = m.wavelength
            if m.films and not isinstance(lam, jax.core.Tracer):
                lam_s = float(np.asarray(self.sensor.wavelength))
                if np.any(np.abs(np.asarray(lam, np.float64) - lam_s) > 1e-6 * lam_s):
                    raise ValueError(
                        f"Scene.materials[{i}] (part {self.mesh.parts[i]!r}, "
                        f"{m.name or 'coated'}): its film stack is given at wavelength "
                        f"{np.asarray(lam).ravel()[0]!r} m, the sensor's is {lam_s!r} m"
                    )
        r = math.isqrt(int(self.vis_samples))
        if r * r != self.vis_samples or r < 1:
            raise ValueError(
                f"Scene.vis_samples must be a perfect square >= 1, got {self.vis_samples!r}"
            )


# --------------------------------------------------------------------------- config schema

Vec3 = Annotated[list[float], pydantic.Field(min_length=3, max_length=3)]


def check_sensor_fields(
    line_of_sight,
    polarization_reference,
    receiver_direction=None,
    bistatic_angle_urad=0.0,
    bistatic_azimuth_deg=0.0,
) -> None:
    """The sensor geometry of a config (same field names as configs/sensors/*.toml);
    ``ValueError`` naming the fields and values that :meth:`Sensor.make` would reject."""
    los = np.asarray(line_of_sight, np.float64)
    ref = np.asarray(polarization_reference, np.float64)
    for name, v in (("line_of_sight", los), ("polarization_reference", ref)):
        if np.linalg.norm(v) == 0:
            raise ValueError(f"{name} = {v.tolist()}: must be non-zero")
    d = los / np.linalg.norm(los)
    r = ref / np.linalg.norm(ref)
    if np.linalg.norm(r - np.dot(r, d) * d) < 1e-6:
        raise ValueError(
            f"polarization_reference = {ref.tolist()} is parallel to line_of_sight = "
            f"{los.tolist()}; it needs a component perpendicular to the beam"
        )
    if receiver_direction is not None:
        rd = np.asarray(receiver_direction, np.float64)
        if np.linalg.norm(rd) == 0:
            raise ValueError(f"receiver_direction = {rd.tolist()}: must be non-zero")
        if bistatic_angle_urad != 0.0:
            raise ValueError(
                f"give either bistatic_angle_urad (= {bistatic_angle_urad}) or "
                f"receiver_direction (= {rd.tolist()}), not both"
            )
    try:
        Sensor.make(
            los,
            ref,
            bistatic_angle=bistatic_angle_urad * 1e-6,
            bistatic_azimuth=math.radians(bistatic_azimuth_deg),
            receiver_dir=receiver_direction,
        )
    except ValueError as err:
        msg = (
            str(err)
            .replace("receiver_dir ", "receiver_direction ")
            .replace("x_ref", "polarization_reference")
        )
        raise ValueError(msg) from None


class PulseConfig(StrictModel):
    fwhm_s: float = pydantic.Field(gt=0, description="full width at half maximum, e.g. 100e-12")
    jitter_s: float = pydantic.Field(default=0.0, ge=0, description="rms receiver jitter")
    renamed = {"fwhm_ps": ("fwhm_s", 1e-12), "jitter_ps": ("jitter_s", 1e-12)}


class BinsConfig(StrictModel):
    width_m: float = pydantic.Field(gt=0, description="bin width (one-way range), e.g. 0.005")
    count: int = pydantic.Field(gt=0, le=1_000_000, description="number of bins")
    start_m: float | None = pydantic.Field(
        None, description="range of the first bin's edge (default: centred on the reference)"
    )
    renamed = {"width_mm": ("width_m", 1e-3)}


class SensorConfig(StrictModel):
    """``configs/sensors/*.toml``."""

    wavelength_nm: float = pydantic.Field(gt=0, lt=1e6, description="laser wavelength")
    line_of_sight: Vec3 = pydantic.Field(
        [0.0, 0.0, -1.0], description="laser propagation direction (sensor -> object, world)"
    )
    polarization_reference: Vec3 = pydantic.Field(
        [1.0, 0.0, 0.0], description="sensor x axis (world), projected per beam"
    )
    bistatic_angle_urad: float = pydantic.Field(
        default=0.0, ge=0, lt=1.5e6, description="angle between laser and receiver directions"
    )
    bistatic_azimuth_deg: float = pydantic.Field(0.0, description="azimuth of that offset")
    receiver_direction: Vec3 | None = pydantic.Field(
        None, description="receiver direction instead of bistatic_angle_urad (world)"
    )
    reference_range_km: float = pydantic.Field(
        default=1000.0, ge=0, description="range of the body origin (time zero of the bins)"
    )
    pulse: PulseConfig = pydantic.Field(description="Gaussian pulse")
    bins: BinsConfig = pydantic.Field(description="range bins")

    @pydantic.model_validator(mode="after")
    def _geometry(self):
        check_sensor_fields(
            self.line_of_sight,
            self.polarization_reference,
            self.receiver_direction,
            self.bistatic_angle_urad,
            self.bistatic_azimuth_deg,
        )
        return self


class ShapeConfig(StrictModel):
    name: str = pydantic.Field(description="a ppr.shapes name (sphere, cubesat, ...)")
    params: dict[str, float | int | str | list[float]] = pydantic.Field(
        {}, description="its parameters (metres)"
    )


class MeshFileConfig(StrictModel):
    path: str = pydantic.Field(description='a mesh file trimesh reads (mesh = "file" also works)')
    scale: float = pydantic.Field(default=1.0, gt=0, description="file units -> metres")
    on_degenerate: Literal["error", "drop"] = pydantic.Field(
        "error", description="zero-area faces: an error, or dropped"
    )
    part_names: dict[str, str] = pydantic.Field({}, description="rename parts: file -> config")


class InlineFilm(StrictModel):
    n_real: float = pydantic.Field(gt=0)
    n_imag: float = pydantic.Field(default=0.0, ge=0)
    thickness_m: float = pydantic.Field(ge=0, le=1e-2)


class InlineMaterial(StrictModel):
    n_real: float = pydantic.Field(gt=0)
    n_imag: float = pydantic.Field(default=0.0, ge=0)
    m: float = pydantic.Field(ge=0, le=1e6)
    corr_length_m: float = pydantic.Field(default=5e-6, gt=0)
    films: list[InlineFilm] = []
    film_mode: Literal["auto", "coherent", "incoherent", "lobe"] = "auto"


class PoseConfig(StrictModel):
    quaternion: Annotated[list[float], pydantic.Field(min_length=4, max_length=4)] = pydantic.Field(
        [1.0, 0, 0, 0], description="body -> world, [w, x, y, z], unit norm"
    )
    position_m: Vec3 = pydantic.Field([0.0, 0.0, 0.0], description="body origin (world)")


class VisibilityConfig(StrictModel):
    samples_per_face: int = pydantic.Field(
        default=16, ge=1, le=4096, description="visibility rays per face (a perfect square)"
    )


class SceneConfig(StrictModel):
    """``configs/scenes/*.toml``: exactly one of ``shape`` / ``mesh``; ``materials`` maps
    every mesh part to a library material (``"name"`` or ``"name/finish"``, see
    :func:`ppr.load_material`) or an inline material; ``sensor`` is a sensor file relative
    to the scene file, or the name of a shipped sensor (``configs/sensors/``)."""

    sensor: str = pydantic.Field(
        description="a sensor file relative to the scene file (.toml may be left out), or a "
        'shipped sensor\'s name ("default", "leo_aberration_1064")'
    )
    shape: ShapeConfig | None = pydantic.Field(
        None, description="a parametric shape; exactly one of [shape] and [mesh]"
    )
    mesh: MeshFileConfig | None = pydantic.Field(None, description="a mesh file")
    materials: dict[str, str | InlineMaterial] = pydantic.Field(
        description='mesh part -> library material ("name" or "name/finish", '
        "configs/materials.toml) or inline {n_real, n_imag, m, corr_length_m}"
    )
    pose: PoseConfig = pydantic.Field(PoseConfig(), description="attitude and position")
    visibility: VisibilityConfig = pydantic.Field(
        VisibilityConfig(), description="macro shadowing (embree rays)"
    )

    @pydantic.field_validator("mesh", mode="before")
    @classmethod
    def _mesh_path(cls, v):
        return {"path": v} if isinstance(v, str) else v  # mesh = "file" is [mesh] path = "file"

    @pydantic.model_validator(mode="after")
    def _one_geometry(self):
        if (self.shape is None) == (self.mesh is None):
            raise ValueError("give exactly one of [shape] and [mesh]")
        return self


def _material_from_config(spec, wavelength: float, where: str) -> Material:
    if isinstance(spec, InlineMaterial):
        films = tuple((complex(f.n_real, f.n_imag), f.thickness_m) for f in spec.films)
        try:
            return Material(
                complex(spec.n_real, spec.n_imag),
                spec.m,
                spec.corr_length_m,
                name="inline",
                films=films,
                wavelength=wavelength if films else None,
                film_mode=spec.film_mode,
            )
        except ValueError as exc:
            raise ConfigError(f"{where}: {exc}") from None
    from ..materials._library import load_material  # noqa: PLC0415

    name, slash, finish = spec.partition("/")
    try:
        return load_material(name, wavelength, finish=finish if slash else None)
    except (KeyError, ValueError) as exc:
        raise ConfigError(f"{where} = {spec!r}: {exc}") from None


def _find_sensor(name: str, scene_path: Path) -> Path:
    """``sensor = name``: a file relative to the scene file (``.toml`` may be left out), else
    a shipped sensor (``configs/sensors/<name>.toml``, :func:`ppr.shipped_config`)."""
    p = Path(name).expanduser()
    if not p.is_absolute():
        p = scene_path.parent / p
    cands = [p, p.with_name(p.name + ".toml")]
    if "/" not in name and "\\" not in name:
        from .._resources import shipped_configs_dir  # noqa: PLC0415

        cands.append(shipped_configs_dir() / "sensors" / f"{name}.toml")
    for c in cands:
        if c.is_file():
            return c
    looked = ", ".join(str(c) for c in cands)
    raise ConfigError(
        f"{scene_path}: sensor = {name!r}: no such sensor config (looked for {looked})"
    )


def sensor_from_config(
    cfg: SensorConfig, source: str = "sensor"
) -> tuple[Sensor, Pulse, RangeBins]:
    try:
        sensor = Sensor.make(
            cfg.line_of_sight,
            cfg.polarization_reference,
            bistatic_angle=cfg.bistatic_angle_urad * 1e-6,
            bistatic_azimuth=math.radians(cfg.bistatic_azimuth_deg),
            receiver_dir=cfg.receiver_direction,
            wavelength=cfg.wavelength_nm * 1e-9,
        )
    except ValueError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    pulse = Pulse.gaussian(cfg.pulse.fwhm_s, cfg.pulse.jitter_s)
    width = cfg.bins.width_m
    start = -0.5 * width * cfg.bins.count if cfg.bins.start_m is None else cfg.bins.start_m
    bins = RangeBins(start, width, cfg.bins.count, cfg.reference_range_km * 1e3)
    return sensor, pulse, bins


def load_sensor(path: str | os.PathLike) -> tuple[Sensor, Pulse, RangeBins]:
    """Read ``configs/sensors/*.toml`` -> ``(Sensor, Pulse, RangeBins)``."""
    return sensor_from_config(load_toml_model(SensorConfig, path), str(path))


def load_scene(path: str | os.PathLike, overrides: dict | None = None) -> Scene:
    """Read a scene TOML (``configs/scenes/*.toml``) into a :class:`Scene`.

    Errors (:class:`ppr._config.ConfigError`, a ``ValueError``) name the file, the field and
    the value: unknown keys, NaN, bad shapes, unknown shape or material names, mesh parts
    without a material, non-unit quaternions.
    """
    from ..geometry import shapes  # noqa: PLC0415

    path = Path(path)
    sensor_keys = [k for k in (overrides or {}) if k.split(".")[0] in SensorConfig.model_fields]
    if sensor_keys:
        # the sensor's fields live in its own file, which the scene names
        raise ConfigError(
            f"{config_source(path, overrides)}: {sensor_keys[0]} is a field of the sensor "
            "file the scene names (sensor = ...), not of the scene: copy that file (e.g. "
            'configs/sensors/default.toml), change it there and set sensor = "<its path>"'
        )
    cfg = load_toml_model(SceneConfig, path, overrides)
    src = config_source(path, overrides)
    spath = _find_sensor(cfg.sensor, path)
    sensor, pulse, bins = load_sensor(spath)
    try:
        if cfg.shape is not None:
            mesh = shapes.by_name(cfg.shape.name, **cfg.shape.params)
        else:
            mpath = Path(cfg.mesh.path)
            if not mpath.is_absolute():
                mpath = path.parent / mpath
            mesh = load_mesh(
                mpath,
                scale=cfg.mesh.scale,
                on_degenerate=cfg.mesh.on_degenerate,
                part_names=cfg.mesh.part_names,
            )
    except ValueError as exc:
        raise ConfigError(f"{src}: {'shape' if cfg.shape else 'mesh'}: {exc}") from None
    missing = [p for p in mesh.parts if p not in cfg.materials]
    if missing:
        raise ConfigError(
            f"{src}: materials: no material for mesh parts {missing} (parts are {list(mesh.parts)})"
        )
    extra = [k for k in cfg.materials if k not in mesh.parts]
    if extra:
        raise ConfigError(f"{src}: materials: {extra} are not parts of the mesh {list(mesh.parts)}")
    wl = float(sensor.wavelength)
    mats = tuple(
        _material_from_config(cfg.materials[p], wl, f"{src}: materials.{p}") for p in mesh.parts
    )
    try:
        q = check_quaternion(cfg.pose.quaternion, "pose.quaternion")
    except ValueError as exc:
        raise ConfigError(f"{src}: {exc}") from None
    pose = Pose(q, cfg.pose.position_m)
    r = math.isqrt(cfg.visibility.samples_per_face)
    if r * r != cfg.visibility.samples_per_face:
        raise ConfigError(
            f"{src}: visibility.samples_per_face = {cfg.visibility.samples_per_face}: must be a "
            "perfect square (1, 4, 9, 16, ...)"
        )
    return Scene(
        check_mesh(mesh, name=str(path)),
        mats,
        pose,
        sensor,
        pulse,
        bins,
        cfg.visibility.samples_per_face,
    )
