"""Scene configs (TOML schema), sensor geometry, pulse and range-bin parameters."""

import math

import numpy as np
import pytest

import ppr
from ppr._config import ConfigError
from ppr.optics.conventions import C_LIGHT
from ppr.pulse._scene import FWHM_TO_SIGMA

SCENES = "configs/scenes"


def _write(tmp_path, text, name="scene.toml", sensor=True):
    if sensor:
        (tmp_path / "s.toml").write_text(
            "wavelength_nm = 1064.0\n[pulse]\nfwhm_s = 50e-12\n[bins]\nwidth_m = 4e-3\n"
            "count = 200\n"
        )
    p = tmp_path / name
    p.write_text(text)
    return p


BASE = """sensor = "s"
[shape]
name = "cubesat_with_panels"
params = {{ units = 3 }}
[materials]
body = {{ n_real = 0.94, n_imag = 6.42, m = 200.0 }}
solar_panel = {{ n_real = 1.46, m = 2000.0 }}
panel_back = {{ n_real = 2.6, m = 5.0 }}
[pose]
quaternion = {q}
"""


@pytest.mark.parametrize("name", ["cubesat3u_panels.toml", "sphere_lambert.toml"])
def test_shipped_scenes_load(name):
    sc = ppr.load_scene(f"{SCENES}/{name}")
    assert len(sc.materials) == len(sc.mesh.parts)
    assert sc.bins.n_bins == 256 and sc.bins.reference_range == pytest.approx(1e6)
    assert float(sc.sensor.wavelength) == pytest.approx(532e-9)
    # 100 ps FWHM and 20 ps jitter add in quadrature
    sig = math.hypot(100e-12 * FWHM_TO_SIGMA, 20e-12)
    assert float(sc.pulse.sigma_t) == pytest.approx(sig, rel=1e-6)
    assert float(sc.pulse.sigma_range) == pytest.approx(0.5 * C_LIGHT * sig, rel=1e-6)


def test_sensor_file_with_aberration_angle():
    sensor, pulse, bins = ppr.load_sensor("configs/sensors/leo_aberration_1064.toml")
    ang = np.arccos(
        np.clip(
            np.dot(np.asarray(sensor.laser_dir, float), np.asarray(sensor.receiver_dir, float)),
            -1,
            1,
        )
    )
    assert ang == pytest.approx(50e-6, rel=1e-3)  # arccos of float32 directions near 1: 1e-3
    assert bins.reference_range == pytest.approx(8e5)


def test_sensor_geometry():
    s = ppr.Sensor.make((0, 0, -1.0), (1.0, 1.0, 0.0), bistatic_angle=0.1, bistatic_azimuth=0.0)
    u_in, u_out = np.asarray(s.laser_dir, float), np.asarray(s.receiver_dir, float)
    np.testing.assert_allclose(u_in, [0, 0, 1], atol=1e-7)
    assert np.dot(u_in, u_out) == pytest.approx(np.cos(0.1), rel=1e-6)
    # receiver tilted toward the transmitted frame's x axis (azimuth 0)
    x_tx = np.asarray(s.frame_tx, float)
    np.testing.assert_allclose(x_tx, np.array([1, 1, 0]) / np.sqrt(2), atol=1e-7)
    assert np.dot(u_out, x_tx) == pytest.approx(np.sin(0.1), rel=1e-6)
    assert abs(np.dot(np.asarray(s.frame_rx, float), u_out)) < 1e-7
    # bisector length cos(beta/2)
    assert np.linalg.norm(np.asarray(s.bisector, float)) == pytest.approx(np.cos(0.05), rel=1e-6)
    with pytest.raises(ValueError, match="parallel to the beam"):
        ppr.Sensor.make((0, 0, -1.0), (0, 0, 1.0))
    with pytest.raises(ValueError, match="either bistatic_angle or receiver_dir"):
        ppr.Sensor.make(receiver_dir=(0, 0.1, 1.0), bistatic_angle=0.1)
    with pytest.raises(ValueError, match="perpendicular"):
        ppr.Sensor([0, 0, 1.0], [0, 0, 1.0], [0, 0.6, 0.8], [1.0, 0, 0])
    # the constructor refuses what Sensor.make refuses: a bistatic angle of 90 deg or more
    for u_out, deg in (([1.0, 0, 0], "90"), ([0.6, 0, -0.8], "143.1"), ([0, 0, -1.0], "180")):
        with pytest.raises(ValueError, match=rf"bistatic angle .* is {deg} deg; it must be below"):
            ppr.Sensor([0, 0, 1.0], u_out, [1.0, 0, 0], [0, 1.0, 0])


def test_pulse_and_bins_validation():
    p = ppr.Pulse.gaussian(100e-12, 30e-12)
    assert float(p.sigma_t) == pytest.approx(math.hypot(100e-12 / 2.3548200450309493, 30e-12))
    with pytest.raises(ValueError, match="jitter"):
        ppr.Pulse.gaussian(100e-12, -1e-12)
    with pytest.raises(ValueError, match="fwhm"):
        ppr.Pulse.gaussian(float("nan"))
    b = ppr.RangeBins.centred(0.01, 10, 5e5)
    np.testing.assert_allclose(b.edges(), np.linspace(-0.05, 0.05, 11))
    with pytest.raises(ValueError, match="width"):
        ppr.RangeBins(0.0, -0.01, 10)
    with pytest.raises(ValueError, match="n_bins"):
        ppr.RangeBins(0.0, 0.01, 0)


def test_scene_from_written_config(tmp_path):
    p = _write(tmp_path, BASE.format(q="[0.0, 0.0, 0.0, -1.0]"))
    sc = ppr.load_scene(p)
    assert sc.mesh.parts == ("body", "solar_panel", "panel_back")
    assert float(sc.sensor.wavelength) == pytest.approx(1064e-9)
    assert float(sc.bins.width) == pytest.approx(4e-3)
    assert sc.materials[0].n == pytest.approx(0.94 + 6.42j)


@pytest.mark.parametrize(
    "text, match",
    [
        (BASE.format(q="[1.0, 0.0, 0.0, 0.0]") + "colour = 3\n", r"colour = 3: unknown key"),
        (BASE.format(q="[1.0, 0.0, 0.5, 0.0]"), r"pose.quaternion must be a unit quaternion.*norm"),
        (BASE.format(q="[nan, 0.0, 0.0, 0.0]"), r"pose.quaternion.*not finite"),
        (BASE.format(q="[1.0, 0.0, 0.0]"), r"pose.quaternion"),
        (
            BASE.format(q="[1.0, 0.0, 0.0, 0.0]").replace("panel_back = ", "panel_bak = "),
            r"no material for mesh parts \['panel_back'\]",
        ),
        (
            BASE.format(q="[1.0, 0.0, 0.0, 0.0]").replace("cubesat_with_panels", "donut"),
            r"unknown shape 'donut'",
        ),
        (
            BASE.format(q="[1.0, 0.0, 0.0, 0.0]").replace('sensor = "s"', 'sensor = "nope"'),
            r"sensor = 'nope': no such sensor",
        ),
        (
            BASE.format(q="[1.0, 0.0, 0.0, 0.0]").replace("m = 5.0", "m = -5.0"),
            r"materials.panel_back.*m = -5.0",
        ),
        (
            BASE.format(q="[1.0, 0.0, 0.0, 0.0]").replace(
                "body = { n_real = 0.94, n_imag = 6.42, m = 200.0 }", 'body = "unobtainium"'
            ),
            r"unobtainium",
        ),
    ],
)
def test_config_errors_name_file_field_value(tmp_path, text, match):
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError, match=match) as err:
        ppr.load_scene(p)
    assert str(p) in str(err.value)


def test_sensor_config_errors(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(
        "wavelength_nm = 532.0\n[pulse]\nfwhm_s = 0.0\n[bins]\nwidth_m = 4e-3\ncount = 200\n"
    )
    with pytest.raises(ConfigError, match=r"pulse.fwhm_s = 0.0"):
        ppr.load_sensor(bad)
    bad.write_text(
        "wavelength_nm = 532.0\n[pulse]\nfwhm_s = 10e-12\n[bins]\nwidth_m = 4e-3\ncount = 0\n"
    )
    with pytest.raises(ConfigError, match=r"bins.count = 0"):
        ppr.load_sensor(bad)
    # a sensor field overridden on a scene (`ppr simulate --set bins.width_m=...`) says where
    # it lives instead of "unknown key"
    scene = ppr.shipped_config("scenes/cubesat3u_panels.toml")
    with pytest.raises(ConfigError, match=r"bins.width_m is a field of the sensor file"):
        ppr.load_scene(scene, {"bins.width_m": 0.01})


def test_mesh_file_scene(tmp_path):
    mesh = ppr.shapes.cubesat(1)
    mesh.to_trimesh().export(tmp_path / "bus.stl")
    text = """sensor = "s"
[mesh]
path = "bus.stl"
scale = 1000.0
part_names = { bus = "body" }
[materials]
body = { n_real = 1.5, m = 10.0 }
"""
    p = _write(tmp_path, text)
    sc = ppr.load_scene(p)  # an STL's one part is named after the file without extension
    assert sc.mesh.parts == ("body",)
    assert sc.mesh.to_trimesh().area == pytest.approx(0.06e6, rel=1e-6)
    p = _write(tmp_path, text.replace("{ bus = ", '{ "bus.stl" = '))  # the name in the file
    assert ppr.load_scene(p).mesh.parts == ("body",)
    p = _write(tmp_path, text.replace("{ bus = ", "{ bsu = "))
    with pytest.raises(ConfigError, match=r"part_names.bsu: .* has no object 'bsu'"):
        ppr.load_scene(p)
