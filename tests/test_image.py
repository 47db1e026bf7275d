"""``ppr image`` / ``ppr.image._image``: per-pixel Mueller images against closed forms.

A sphere of one material seen along -z: the pixel at image coordinates (u, v) sees the
sphere point with normal ``(u, v, sqrt(1 - u^2 - v^2))`` (radius 1), so its local incidence
angle is known in closed form and every per-pixel quantity must equal ``mueller_brdf``
evaluated at that normal. The faceted icosphere (subdivisions 5, 20480 faces, smooth shading
by barycentric interpolation of vertex normals) sets the tolerances below.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import ppr
from ppr import cli
from ppr.image import _image

BRDF = ppr.mueller_brdf

N_PIX = 48
HALF_WIDTH = 1.1
MAT = {"n_real": 1.5, "n_imag": 0.0, "m": 5.0}
TERMS = ["single"]


def _sphere_config(tmp_path, **render):
    r = {"n_pixels": N_PIX, "half_width_m": HALF_WIDTH, "shading": "smooth", "terms": TERMS,
         "dtype": "float32"}
    r.update(render)
    lines = [
        "[shape]",
        'name = "sphere"',
        "params = { radius = 1.0, subdivisions = 5 }",
        "[materials]",
        f"body = {{ n_real = {MAT['n_real']}, n_imag = {MAT['n_imag']}, m = {MAT['m']} }}",
        "[view]",
        "wavelength_nm = 532.0",
        "line_of_sight = [0.0, 0.0, -1.0]",
        "polarization_reference = [1.0, 0.0, 0.0]",
        "[render]",
    ]
    for k, v in r.items():
        lines.append(f"{k} = {json.dumps(v)}")
    path = tmp_path / "sphere.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def sphere_image(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sphere")
    cfg = _sphere_config(tmp)
    out = tmp / "out"
    assert cli.main(["image", "-q", "--config", str(cfg), "--out", str(out)]) == 0
    with np.load(out / "image.npz") as z:
        data = {k: z[k] for k in z.files}
    return data, out


def test_sphere_writes_outputs(sphere_image):
    _, out = sphere_image
    for name in cli.IMAGE_OUTPUTS:
        assert (out / name).stat().st_size > 0, name
    summary = json.loads((out / "image.json").read_text())
    assert summary["n_pixels"] == [N_PIX, N_PIX]
    assert summary["parts"]["body"]["lit_pixels"] == summary["lit_pixels"] > 0


def test_sphere_disk_edge(sphere_image):
    """Hits fill the disk r < 1: every pixel centre with r < 0.99 hits (the icosphere's
    silhouette lies between R cos(half edge angle) ~ 0.9992 R and R), none with r > 1."""
    d, _ = sphere_image
    uu, vv = np.meshgrid(d["u"], d["v"])
    r = np.hypot(uu, vv)
    hit = d["part"] >= 0
    assert np.all(hit[r < 0.99])
    assert not np.any(hit[r > 1.0])
    assert np.array_equal(d["lit"], hit)  # monostatic: every visible point is lit
    # image axes: columns along +x (frame_rx), rows along receiver_dir x frame_rx = +y, top first
    assert np.all(np.diff(d["u"]) > 0) and np.all(np.diff(d["v"]) < 0)


def test_sphere_incidence_closed_form(sphere_image):
    """cos(theta_in) = sqrt(1 - r^2): interpolated vertex normals of a subdivision-4
    icosphere are within ~2e-3 rad of the true normal, so 5e-3 in the cosine."""
    d, _ = sphere_image
    uu, vv = np.meshgrid(d["u"], d["v"])
    r2 = uu**2 + vv**2
    inside = r2 < 0.97**2
    np.testing.assert_allclose(d["cos_in"][inside], np.sqrt(1 - r2[inside]), atol=5e-3)
    np.testing.assert_allclose(d["cos_out"][inside], d["cos_in"][inside], atol=1e-12)


@pytest.fixture(scope="module")
def reference(sphere_image):
    """float64 mueller_brdf (jitted, one batched call) at the closed-form normal and at the
    image's stored shading normal of every pixel whose centre is inside r < 0.97."""
    import jax

    d, _ = sphere_image
    uu, vv = np.meshgrid(d["u"], d["v"])
    inside = np.hypot(uu, vv) < 0.97
    u, v = uu[inside], vv[inside]
    exact = np.stack([u, v, np.sqrt(1 - u**2 - v**2)], -1)
    stored = d["normal"][inside]
    z = np.array([0.0, 0.0, 1.0])
    x = np.array([1.0, 0.0, 0.0])
    mat = ppr.Material(n=complex(MAT["n_real"], MAT["n_imag"]), m=MAT["m"])
    fn = jax.jit(lambda nrm: BRDF(z, z, nrm, mat, terms=tuple(TERMS), frame_in=x, frame_out=x,
                                  wavelength=532e-9))
    both = np.asarray(fn(np.concatenate([exact, stored])))
    return inside, both[: len(u)], both[len(u):], exact


def test_sphere_normals_closed_form(sphere_image, reference):
    """Interpolated vertex normals of the subdivision-4 icosphere are within 3e-3 rad of the
    sphere's normal at the pixel centre (vertex normals are area-weighted face averages)."""
    d, _ = sphere_image
    inside, _, _, exact = reference
    cosang = np.clip(np.sum(d["normal"][inside] * exact, -1), -1, 1)
    assert np.max(np.arccos(cosang)) < 3e-3


def test_sphere_pixels_equal_mueller_brdf(sphere_image, reference):
    """(a) Every pixel inside r < 0.97 equals mueller_brdf at its stored normal (rtol 1e-3 on
    M00, 1e-4 absolute on normalized elements: float32 image vs float64 reference);
    (b) within r < 0.9 it equals mueller_brdf at the closed-form normal (rtol 2e-2: the
    BRDF's log-slope ~m tan(theta) <= 11/rad there times the <= 3e-3 rad normal error;
    normalized elements 1e-2 absolute). Reflectance = M00 cos(theta_in)."""
    d, _ = sphere_image
    inside, ref_exact, ref_stored, exact = reference
    got = d["mueller"][inside]
    np.testing.assert_allclose(got[:, 0, 0], ref_stored[:, 0, 0], rtol=1e-3)
    np.testing.assert_allclose(got / got[:, :1, :1], ref_stored / ref_stored[:, :1, :1],
                               atol=1e-4)
    core = np.hypot(exact[:, 0], exact[:, 1]) < 0.9
    np.testing.assert_allclose(got[core, 0, 0], ref_exact[core, 0, 0], rtol=2e-2)
    np.testing.assert_allclose(got[core] / got[core, :1, :1],
                               ref_exact[core] / ref_exact[core, :1, :1], atol=1e-2)
    refl = d["reflectance"][inside]
    np.testing.assert_allclose(refl, got[:, 0, 0] * d["cos_in"][inside], rtol=1e-12)


def test_sphere_polarimetry_equals_reference(sphere_image, reference):
    """Per-pixel depolarization index, polarizance, diattenuation, retardance equal the
    polarimetry functions applied to mueller_brdf at the closed-form normal (abs 2e-2: the
    normal error above; float32 image), and exactly those of the stored per-pixel matrices."""
    d, _ = sphere_image
    inside, ref, _, _ = reference
    ref_q = _image.polarimetric_maps(ref, np.ones(ref.shape[:-2]))
    for name in _image.QUANTITIES[1:]:
        np.testing.assert_allclose(d[name][inside], ref_q[name], atol=2e-2, err_msg=name)
    again = _image.polarimetric_maps(d["mueller"], np.nan_to_num(d["cos_in"]))
    for name in _image.QUANTITIES[1:]:
        np.testing.assert_allclose(d[name], again[name], atol=1e-12, equal_nan=True)


def test_background_is_nan(sphere_image):
    d, _ = sphere_image
    miss = d["part"] < 0
    assert miss.any()
    assert np.all(np.isnan(d["mueller"][miss]))
    for name in _image.QUANTITIES:
        assert np.all(np.isnan(d[name][miss])), name


def _plates():
    """A 2 m plate at z = 0 and a 0.4 m plate hovering at z = 0.5 (two parts)."""
    big = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    small = np.array([[-0.2, -0.2, 0.5], [0.2, -0.2, 0.5], [0.2, 0.2, 0.5], [-0.2, 0.2, 0.5]])
    verts = np.concatenate([big, small])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    return ppr.Mesh(verts, faces, np.array([0, 0, 1, 1]), ("ground", "top"))


def test_bistatic_shadow_ray():
    """Laser tilted by beta toward +x (receiver along +z): the hovering plate's shadow on the
    ground is its footprint shifted by -0.5 tan(beta) in x; the monostatic image has none."""
    beta = 0.5
    mesh = _plates()
    mats = [ppr.Material(n=1.5, m=5.0)] * 2
    laser = np.array([np.sin(beta), 0.0, np.cos(beta)])
    kw = dict(receiver_dir=(0, 0, 1), frame_tx=(0, 1, 0), frame_rx=(0, 1, 0), n_pixels=40,
              half_width=1.0, terms=("single",), dtype=np.float32)
    img = _image.render_mueller_image(mesh, mats, laser_dir=laser, **kw)
    # image columns along frame_rx = +y, rows along z x y = -x (top first)
    uu, vv = np.meshgrid(img.u, img.v)
    y, x = uu, -vv
    ground = img.part == 0
    shift = 0.5 * np.tan(beta)
    in_shadow = (np.abs(x + shift) < 0.2 - 0.03) & (np.abs(y) < 0.2 - 0.03)
    clear = (np.abs(x + shift) > 0.2 + 0.03) | (np.abs(y) > 0.2 + 0.03)
    assert in_shadow.sum() > 10
    assert not np.any(img.lit[ground & in_shadow])
    assert np.all(img.lit[ground & clear])
    assert np.all(img.mueller[ground & in_shadow] == 0.0)
    mono = _image.render_mueller_image(mesh, mats, laser_dir=(0, 0, 1), **kw)
    assert np.array_equal(mono.lit, mono.part >= 0)


def test_no_ray_hits_gives_an_empty_image():
    """Plates seen exactly edge-on from beside them: no ray hits, and the image is empty
    (NaN Mueller, part -1, nothing lit) with the dtypes of a hit image, not an error."""
    mesh = _plates()
    mats = [ppr.Material(n=1.5, m=5.0)] * 2
    kw = dict(receiver_dir=(1, 0, 0), frame_tx=(0, 0, 1), frame_rx=(0, 0, 1), n_pixels=8,
              half_width=0.1, terms=("single",), dtype=np.float32)
    img = _image.render_mueller_image(mesh, mats, laser_dir=(1, 0, 0), **kw)
    assert img.part.dtype.kind == "i" and img.lit.dtype == bool
    assert np.all(img.part == -1) and not img.lit.any()
    assert np.all(np.isnan(img.mueller)) and np.all(np.isnan(img.cos_in))
    assert img.normal.shape == (8, 8, 3)


def test_render_input_errors():
    mesh = _plates()
    mats = [ppr.Material(n=1.5, m=5.0)] * 2
    with pytest.raises(ValueError, match="one material per part"):
        _image.render_mueller_image(mesh, mats[:1], laser_dir=(0, 0, 1))
    with pytest.raises(ValueError, match="laser_dir"):
        _image.render_mueller_image(mesh, mats, laser_dir=(0, 0, np.nan))
    with pytest.raises(ValueError, match="shading"):
        _image.render_mueller_image(mesh, mats, laser_dir=(0, 0, 1), shading="phong")


def test_deprecated_part_mesh_adapter_warns_once():
    """``ppr.cli.part_mesh_from_ppr_mesh`` (the image renderer now takes a ``ppr.Mesh``) is a
    deprecated no-op for one release: one warning per process, the mesh handed back."""
    from ppr._deprecation import _WARNED, PprDeprecationWarning

    _WARNED.discard("ppr.cli.part_mesh_from_ppr_mesh")
    mesh = _plates()
    with pytest.warns(PprDeprecationWarning, match="part_mesh_from_ppr_mesh") as rec:
        first = cli.part_mesh_from_ppr_mesh(mesh, smooth=True)
        second = cli.part_mesh_from_ppr_mesh(mesh)
    assert first is mesh and second is mesh
    assert len(rec) == 1
