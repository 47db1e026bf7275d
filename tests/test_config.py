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
    p.write_bytes(b'\xffname = "a"\n')  # another encoding than UTF-8: named, with the byte
    with pytest.raises(ConfigError, match=rf"{p}: not a TOML text file \(not UTF-8: byte 0xff"):
        load_toml_model(Scene, p)


def test_parse_override_types():
    assert parse_override("pulse.fwhm_ps=80") == ("pulse.fwhm_ps", 80)
    assert parse_override("name=abc") == ("name", "abc")
    assert parse_override('name="x y"') == ("name", "x y")
    with pytest.raises(ConfigError):
        parse_override("novalue")


def test_deprecated_key_is_converted_warns_once_and_errors_name_it(tmp_path, monkeypatch):
    """An old spelling in another unit (picoseconds) is read as the SI key (seconds), with
    one warning per key; an error at it names the key and the value as written."""
    from ppr import _config
    from ppr._config import ConfigDeprecationWarning
    from ppr.pulse._scene import PulseConfig

    monkeypatch.setattr(_config, "_WARNED", set())  # whatever warned earlier in this process

    class Sensor(StrictModel):
        pulse: PulseConfig

    new = load_toml_model(Sensor, _write(tmp_path, "[pulse]\nfwhm_s = 100e-12\n"))
    with pytest.warns(ConfigDeprecationWarning, match="'fwhm_ps' is deprecated; write 'fwhm_s'"):
        old = load_toml_model(Sensor, _write(tmp_path, "[pulse]\nfwhm_ps = 100.0\n"))
    assert old.pulse.fwhm_s == pytest.approx(new.pulse.fwhm_s, rel=1e-15)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per key and process: no second warning
        again = load_toml_model(Sensor, _write(tmp_path, "[pulse]\nfwhm_ps = 50.0\n"))
        assert again.pulse.fwhm_s == pytest.approx(50e-12, rel=1e-15)
        p = _write(tmp_path, "[pulse]\nfwhm_ps = -3.0\n")
        with pytest.raises(ConfigError, match=r"pulse.fwhm_ps = -3.0: must be greater than 0"):
            load_toml_model(Sensor, p)
        p = _write(tmp_path, "[pulse]\nfwhm_ps = 3.0\nfwhm_s = 3e-12\n")
        with pytest.raises(ConfigError, match="give fwhm_s or the deprecated fwhm_ps"):
            load_toml_model(Sensor, p)


def test_no_value_reaches_a_number_or_a_switch_by_conversion(tmp_path, monkeypatch):
    """A string or a boolean where a number belongs (``"256"``, ``true`` would become 256 and
    1), a string or a number where true/false belongs (``"no"``, ``1``), and a quoted value
    of a deprecated key in another unit (``width_mm = "5"`` skipped its x 1e-3 and read 5 m)
    are errors naming the field as written and the value; a field that also takes a string
    keeps it, an integer is a number, and an error names the command line's overrides."""
    import typing

    from ppr import _config
    from ppr._config import ConfigDeprecationWarning
    from ppr.pulse._scene import PulseConfig

    monkeypatch.setattr(_config, "_WARNED", set())

    class Run(StrictModel):
        count: int = 1
        scale: float | None = None
        angles: tuple[float, ...] = ()
        capacity: int | typing.Literal["auto"] = "auto"
        mirror: bool = True
        finishes: dict[str, float] = {}
        pair: tuple[float, float] = (1.0, 2.0)
        pulse: PulseConfig | None = None

    cases = [
        ('count = "256"', "count = '256': expected an integer"),
        ("count = true", "count = True: expected an integer"),
        ('scale = "1.5"', "scale = '1.5': expected a number"),
        ("angles = [30.0, true]", r"angles\[1\] = True: expected a number"),
        ('angles = ["30"]', r"angles\[0\] = '30': expected a number"),
        ('mirror = "no"', "mirror = 'no': expected true or false"),
        ("mirror = 1", "mirror = 1: expected true or false"),
        ('[finishes]\nrough = "10"', "finishes.rough = '10': expected a number"),
        ("pair = [0.1]", r"pair = \[0.1\]: too few values \(no value at position 1\)"),
        ('[pulse]\nfwhm_ps = "100"', "pulse.fwhm_ps = '100': expected a number"),
    ]
    for text, needle in cases:
        p = _write(tmp_path, text + "\n")
        # the deprecation warning names the file the key is in
        dep = f"{p}: config key 'fwhm_ps' is deprecated"
        with (
            pytest.warns(ConfigDeprecationWarning, match=dep)
            if "fwhm_ps" in text
            else _no_warning()
        ):
            with pytest.raises(ConfigError, match=f"{p}: {needle}"):
                load_toml_model(Run, p)
    ok = load_toml_model(
        Run, _write(tmp_path, 'count = 3\nscale = 2\nangles = [30, 45.5]\ncapacity = "auto"\n')
    )
    assert (ok.count, ok.scale, ok.angles, ok.capacity) == (3, 2.0, (30.0, 45.5), "auto")
    assert load_toml_model(Run, _write(tmp_path, "capacity = 64\n")).capacity == 64
    p = _write(tmp_path, "count = 3\n")
    with pytest.raises(ConfigError, match=rf'{p} with --set count="4": count = .4.: expected'):
        load_toml_model(Run, p, {"count": "4"})


def _no_warning():
    import contextlib

    return contextlib.nullcontext()


class Shape(StrictModel):
    name: str
    symmetry: str = "none"


class Spec(StrictModel):
    shapes: list[Shape]


def test_override_indexes_a_list_of_tables_as_errors_write_it(tmp_path):
    """``--set shapes[1].symmetry=...`` reaches the second [[shapes]] table (the notation the
    errors use); an index past the list, a dotted key into a list and a bracket that is not
    an index are errors naming the override."""
    p = _write(tmp_path, '[[shapes]]\nname = "a"\n[[shapes]]\nname = "b"\n')
    s = load_toml_model(Spec, p, {"shapes[1].symmetry": "dihedral:4"})
    assert [(x.name, x.symmetry) for x in s.shapes] == [("a", "none"), ("b", "dihedral:4")]
    s = load_toml_model(Spec, p, {"shapes[0]": {"name": "c"}})  # a whole entry replaced
    assert [x.name for x in s.shapes] == ["c", "b"]
    for key, needle in [
        ("shapes[2].symmetry", "'shapes' has 2 entries (indices 0 to 1)"),
        ("shapes.symmetry", "'shapes' is a list: index it (shapes[0].symmetry)"),
        ("shapes[x].symmetry", "'shapes[x]' is not a key"),
        ("shapes[0].symmetry[0]", "'shapes[0].symmetry' is not in the config"),
        ("shapes[0][0]", "'shapes[0]' is a table, not a list"),
        ("missing[0].a", "'missing' is not in the config"),
        ("shapes[1][0].a", "'shapes[1]' is a table, not a list"),
    ]:
        with pytest.raises(ConfigError) as e:
            load_toml_model(Spec, p, {key: "dihedral:4"})
        msg = str(e.value)
        assert str(p) in msg and f"override {key!r}" in msg and needle in msg, msg
    # the error of a value set through an index names it as written
    with pytest.raises(ConfigError) as e:
        load_toml_model(Spec, p, {"shapes[1].colour": 3})
    assert "shapes[1].colour=3" in str(e.value) and "unknown key" in str(e.value)
