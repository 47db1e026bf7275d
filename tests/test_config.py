"""Config loading: errors name file, field and value; unknown keys and NaN are rejected."""

import pytest

from ppr._config import ConfigError, StrictModel, load_toml_model, parse_override


class Pulse(StrictModel):
    fwhm_ps: float
    wavelength_nm: float = 532.0


class Scene(StrictModel):
    name: str
    pulse: Pulse


def _write(tmp_path, text):
    p = tmp_path / "scene.toml"
    p.write_text(text)
    return p


def test_valid_config_and_override(tmp_path):
    p = _write(tmp_path, 'name = "a"\n[pulse]\nfwhm_ps = 100.0\n')
    s = load_toml_model(Scene, p, {"pulse.fwhm_ps": 80.0})
    assert s.pulse.fwhm_ps == 80.0 and s.pulse.wavelength_nm == 532.0


@pytest.mark.parametrize(
    "text, needle",
    [
        ('name = "a"\n[pulse]\nfwhm_ps = 100.0\ncolour = 3\n', "pulse.colour = 3: unknown key"),
        ('name = "a"\n[pulse]\nfwhm_ps = nan\n', "pulse.fwhm_ps = nan: not finite"),
        ('name = "a"\n[pulse]\nfwhm_ps = "fast"\n', "pulse.fwhm_ps = 'fast': expected a number"),
        ('name = "a"\n', "pulse: required field missing"),
    ],
)
def test_errors_name_file_field_value(tmp_path, text, needle):
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError) as e:
        load_toml_model(Scene, p)
    msg = str(e.value)
    assert "\n" not in msg
    assert str(p) in msg and needle in msg, msg


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="no such config file"):
        load_toml_model(Scene, tmp_path / "nope.toml")
    p = _write(tmp_path, "name = \n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_toml_model(Scene, p)


def test_parse_override_types():
    assert parse_override("pulse.fwhm_ps=80") == ("pulse.fwhm_ps", 80)
    assert parse_override("name=abc") == ("name", "abc")
    assert parse_override('name="x y"') == ("name", "x y")
    with pytest.raises(ConfigError):
        parse_override("novalue")
