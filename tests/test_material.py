"""Material pytree validation and the sourced material library (configs/materials.toml)."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from ppr import Material
from ppr._config import ConfigError
from ppr.materials._library import (
    finish_names,
    index_entry,
    load_library,
    load_material,
    material_names,
)
from ppr.optics._fresnel import fresnel_mueller_params

REQUIRED = ["aluminium", "gold", "silver", "fused_silica", "white_paint_tio2", "kapton"]


# ------------------------------------------------------------------ Material pytree


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(n=1.5 - 0.1j, m=10.0), "n"),
        (dict(n=1.5, m=-1.0), "m"),
        (dict(n=1.5, m=2e6), "m"),
        (dict(n=complex("nan"), m=1.0), "n"),
        (dict(n=1.5, m=float("inf")), "m"),
        (dict(n=1.5, m=1.0, corr_length=0.0), "corr_length"),
        (dict(n=-1.5, m=1.0), "n"),
    ],
)
def test_material_rejects_bad_values(kwargs, field):
    with pytest.raises(ValueError, match=field):
        Material(**kwargs)


def test_material_promotes_and_batches():
    mat = Material(n=jnp.array([1.5, 2.0]), m=jnp.array([1.0, 1e6]))
    assert jnp.issubdtype(mat.n.dtype, jnp.complexfloating) and mat.n.shape == (2,)
    assert mat.dtype == np.float64


# ------------------------------------------------------------------------- library


def _sellmeier(l_um, B, C):
    l2 = l_um * l_um
    return math.sqrt(1 + sum(b * l2 / (l2 - c) for b, c in zip(B, C, strict=True)))


def test_required_materials_load_everywhere():
    names = material_names()
    for r in REQUIRED:
        assert r in names
    for name in names:
        for wl in (532e-9, 1064e-9):
            e = index_entry(name, wl)
            assert len(e.source) > 10
            for fin in finish_names():
                mat = load_material(name, wl, fin)
                assert complex(mat.n) == pytest.approx(complex(e.n, e.k), abs=0)
                assert name in mat.name and fin in mat.name


def test_metal_values_match_physics_notes():
    # docs/physics.md#materials (refractiveindex.info compilations), copied exactly
    expected = {
        ("aluminium", 532e-9): 0.94 + 6.42j,
        ("aluminium", 1064e-9): 1.38 + 10.25j,
        ("gold", 532e-9): 0.54 + 2.23j,
        ("gold", 1064e-9): 0.26 + 6.97j,
        ("silver", 532e-9): 0.054 + 3.43j,
        ("silver", 1064e-9): 0.040 + 7.61j,
    }
    for (name, wl), n in expected.items():
        e = index_entry(name, wl)
        assert complex(e.n, e.k) == n


def test_dielectrics_match_dispersion_formulas():
    # independent Sellmeier evaluations; library stores 4 significant decimals (rounding 5e-5)
    silica = ([0.6961663, 0.4079426, 0.8974794], [0.0684043**2, 0.1162414**2, 9.896161**2])
    bk7 = ([1.03961212, 0.231792344, 1.01046945], [0.00600069867, 0.0200179144, 103.560653])
    for wl in (0.532, 1.064):
        assert index_entry("fused_silica", wl * 1e-6).n == pytest.approx(
            _sellmeier(wl, *silica), abs=6e-5
        )
        assert index_entry("cover_glass", wl * 1e-6).n == pytest.approx(
            _sellmeier(wl, *bk7), abs=6e-5
        )
        # rutile ordinary ray, Devore (1951): n^2 = 5.913 + 0.2441 / (l^2 - 0.0803)
        n_rutile = math.sqrt(5.913 + 0.2441 / (wl * wl - 0.0803))
        assert index_entry("white_paint_tio2", wl * 1e-6).n == pytest.approx(n_rutile, abs=6e-4)
    # docs/physics.md#materials: fused silica 1.461 / 1.450, rutile about 2.67 / 2.48
    assert index_entry("fused_silica", 532e-9).n == pytest.approx(1.461, abs=5e-4)
    assert index_entry("fused_silica", 1064e-9).n == pytest.approx(1.450, abs=5e-4)


def test_normal_incidence_reflectance_is_plausible():
    # closed form ((n-1)^2 + k^2)/((n+1)^2 + k^2) against the Fresnel kernel, and sane ranges
    for name in material_names():
        for wl in (532e-9, 1064e-9):
            e = index_entry(name, wl)
            R = ((e.n - 1) ** 2 + e.k**2) / ((e.n + 1) ** 2 + e.k**2)
            a, _, _, _ = fresnel_mueller_params(e.n, e.k, 1.0)
            assert float(a) == pytest.approx(R, rel=1e-12)
            if e.k > 1:
                assert 0.6 < R < 1.0  # metals
            elif e.n > 3.0:
                assert 0.3 < R < 0.45  # semiconductors (silicon: n ~ 4.1 at 532 nm, R ~ 0.37)
            else:
                assert 0.03 < R < 0.25  # glasses, polymer, rutile, silicon nitride


def test_defaults_and_dtype():
    mat = load_material("aluminium")
    assert "@532nm" in mat.name and "brushed" in mat.name
    assert load_material("gold", 1064.0000001e-9).name.endswith("@1064nm")
    m32 = load_material("silver", dtype=jnp.float32)
    assert m32.m.dtype == jnp.float32 and m32.n.dtype == jnp.complex64
    m64 = load_material("silver", dtype=jnp.float64)
    assert m64.n.dtype == jnp.complex128


def test_unknown_name_wavelength_finish():
    with pytest.raises(ValueError, match="available: .*aluminium"):
        load_material("unobtainium")
    with pytest.raises(ValueError, match="532e-9, 1064e-9"):
        load_material("gold", 633e-9)
    with pytest.raises(ValueError, match="metres"):
        load_material("gold", 532)
    with pytest.raises(ValueError, match="available: .*polished"):
        load_material("gold", finish="shiny")


GOOD = """
[finishes.rough]
m = 10.0
corr_length = 5e-6
[materials.x]
default_finish = "rough"
[[materials.x.index]]
wavelength_nm = 532.0
n = 1.5
k = 0.0
source = "test value"
"""


@pytest.mark.parametrize(
    "old, new, needle",
    [
        ("k = 0.0", "k = -0.1", "k = -0.1"),
        ("n = 1.5", "n = nan", "not finite"),
        ("m = 10.0", "m = 10.0\nroughness = 3", "roughness"),
        ('default_finish = "rough"', 'default_finish = "silky"', "silky"),
        ('source = "test value"', "", "source"),
        ("k = 0.0\n", 'k = 0.0\nsource2 = "x"\n', "source2"),
        (
            'source = "test value"',
            'source = "test value"\n[[materials.x.index]]\nwavelength_nm = 532.2\nn = 1.6\nk = 0'
            '\nsource = "dup"',
            "duplicate wavelength",
        ),
    ],
)
def test_bad_library_file(tmp_path, old, new, needle):
    p = tmp_path / "lib.toml"
    p.write_text(GOOD)
    assert load_material("x", path=p).name == "x/rough@532nm"
    bad = tmp_path / "bad.toml"
    bad.write_text(GOOD.replace(old, new))
    with pytest.raises(ConfigError) as err:
        load_library(bad)
    msg = str(err.value)
    assert str(bad) in msg and needle in msg and "\n" not in msg


def test_stack_materials_keeps_the_white_flag_and_rejects_mixtures():
    """``stack_materials`` (the one implementation behind ``simulate``, ``double_bounce`` and
    the image tools) stacks every field, keeps the static ``white`` flag, pads to a
    multiple on request, and refuses to mix the ideal white reflector with real materials
    (one batch takes one BRDF program), naming the parts."""
    from ppr import stack_materials

    white = stack_materials([Material.ideal_white(3.0), Material.ideal_white(50.0, 1e-5)])
    assert white.white and np.asarray(white.m).tolist() == [3.0, 50.0]
    assert np.asarray(white.corr_length).tolist() == [5e-6, 1e-5]
    real = stack_materials([Material(1.5, 2.0), Material(0.94 + 6.42j, 7.0)], multiple=8)
    assert not real.white and real.m.shape == (8,) and real.n.dtype == np.complex128
    np.testing.assert_array_equal(np.asarray(real.m), [2.0, 7.0] + [7.0] * 6)
    with pytest.raises(ValueError, match=r"parts \[1\] are ideal white .* parts \[0, 2\]"):
        stack_materials([Material(1.5, 2.0), Material.ideal_white(3.0), Material(2.0, 1.0)])
