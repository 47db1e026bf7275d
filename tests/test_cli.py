"""The ``ppr`` command line: every command end to end on a small config, one-line config
errors with exit status 2, unknown keys, refusing to overwrite. Commands run in-process
(``cli.main([...])``) to share JAX start-up and compilations; one subprocess smoke test."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import ppr
from ppr import cli

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _no_compile_cache(monkeypatch):
    # keep the test process's JAX config untouched (the CLI enables a persistent cache)
    monkeypatch.setenv("PPR_JAX_CACHE", "0")


def run(*argv) -> int:
    try:
        return cli.main([str(a) for a in argv])
    except SystemExit as exc:  # argparse/--help and config errors
        return int(exc.code or 0)


def error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err  # exactly one line
    return err[0]


# ----------------------------------------------------------------------------------- help
def test_help_lists_every_command(capsys):
    assert run("--help") == 0
    text = capsys.readouterr().out
    for cmd in ("demo", "brdf", "image", "simulate", "database", "classify", "invert", "report"):
        assert cmd in text


@pytest.mark.parametrize(
    "cmd, units",
    [
        ("brdf", ["nanometres", "degrees", "1/sr"]),
        ("image", ["microradians", "metres", "1/sr", "[rad]"]),
        ("simulate", ["seconds", "microradians", "metres", "m^2/sr"]),
        ("demo", ["--out"]),
        ("classify", ["bins", "sqrt of expected total counts"]),
        ("invert", ["degrees", "metres", "expected total counts"]),
        ("report", ["bins", "degrees"]),
    ],
)
def test_subcommand_help_explains_units(capsys, cmd, units):
    assert run(cmd, "--help") == 0
    text = " ".join(capsys.readouterr().out.split())  # as read, whatever the wrapping
    for u in units:
        assert u in text, (cmd, u)
    if cmd != "demo":
        for opt in ("--config", "--set", "--out", "--overwrite"):
            assert opt in text


def test_no_command_is_usage_error(capsys):
    assert run() == 2


def _command_modules():
    from ppr.cli import _app

    return _app.COMMANDS


@pytest.mark.parametrize("module", _command_modules(), ids=lambda m: m.NAME)
def test_help_examples_validate_against_their_schemas(module, capsys):
    """Every command line a --help shows (its examples and its --set example) parses and
    its config validates whole against the command's schema (nothing is computed)."""
    from ppr.cli import _app

    parser = _app.build_parser()
    assert run(*module.NAME.split(), "--help") == 0
    text = capsys.readouterr().out
    commands = list(module.EXAMPLES) + [f"ppr {module.NAME} --set {module.SET_EXAMPLE}"]
    for example in module.EXAMPLES:
        assert example in text, example
    assert f"--set {module.SET_EXAMPLE}" in " ".join(text.split())
    for example in commands:
        args = parser.parse_args(shlex.split(example)[1:])
        cfg_path, cfg = args.load(args)
        assert Path(cfg_path).is_file() and cfg is not None, example


def test_version_names_ppr_and_jax(capsys):
    from importlib import metadata

    assert run("--version") == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"ppr {metadata.version('ppr')} (jax {metadata.version('jax')}")


def test_ctrl_c_during_startup_is_one_line_exit_130(capsys, monkeypatch):
    from ppr.cli import _app

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(_app, "build_parser", interrupted)
    assert run("brdf", "--help") == 130
    assert error_line(capsys) == "ppr: interrupted"


OBJ_NAMED = "o {name}\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"


def test_paths_in_a_config_are_relative_to_it_and_set_paths_to_the_cwd(tmp_path, monkeypatch):
    """docs/configs.md: a config's relative paths resolve against its own folder, whatever
    the working folder; a --set path against the working folder."""
    from ppr.cli import _app
    from ppr.cli.image import image_inputs

    there, here = tmp_path / "configs", tmp_path / "work"
    there.mkdir()
    here.mkdir()
    (there / "m.obj").write_text(OBJ_NAMED.format(name="beside_config"))
    (here / "m.obj").write_text(OBJ_NAMED.format(name="in_cwd"))
    cfg = _write(there / "img.toml", 'mesh = "m.obj"\n[materials]\ndefault = "gold"\n')
    monkeypatch.chdir(here)
    parser = _app.build_parser()
    for extra, part in (([], "beside_config"), (["--set", "mesh=m.obj"], "in_cwd")):
        args = parser.parse_args(["image", "-c", str(cfg), *extra])
        mesh = image_inputs(*reversed(args.load(args)))[0]
        assert mesh.parts == (part,), (extra, mesh.parts)


# ---------------------------------------------------------------------------- end to end
def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_brdf_end_to_end(tmp_path):
    cfg = _write(
        tmp_path / "brdf.toml",
        'material = "aluminium/rough"\nterms = ["single"]\nincidence_deg = [0.0, 45.0]\n'
        "bistatic_deg = [0.0, 2.0, 5.0]\n",
    )
    out = tmp_path / "out"
    assert run("brdf", "-q", "-c", cfg, "-o", out) == 0
    with np.load(out / "brdf.npz") as z:
        assert z["mueller"].shape == (2, 3, 4, 4)
        assert np.all(np.isfinite(z["mueller"]))
        assert z["depolarization_index"].shape == (2, 3)
    summary = json.loads((out / "brdf.json").read_text())
    assert summary["n_geometries"] == 6
    # provenance: what ran, with which versions, and the resolved config (defaults filled in)
    prov = summary["provenance"]
    assert prov["command_line"] == ["ppr", "brdf", "-q", "-c", str(cfg), "-o", str(out)]
    assert prov["config"]["wavelength_nm"] == 532.0 and prov["config"]["plane"] == "in"
    assert prov["config"]["incidence_deg"] == [0.0, 45.0]
    import jax

    assert prov["jax"] == jax.__version__ and prov["numpy"] == np.__version__
    assert (out / "brdf.png").stat().st_size > 1000


def test_brdf_geometries_below_the_horizon_are_marked_and_said(tmp_path, capsys):
    """Angles inside the documented bounds whose k_out falls at or below the horizon (a
    cross-plane bistatic angle of 90 deg or more at normal incidence, in-plane 179 deg at 60
    deg): the others are computed, these are NaN with valid = false and the command says so
    on stderr (the cross-plane k_out along the frames' axis raised an internal error)."""
    for plane, inc, bis in (
        ("cross", [0.0, 60.0], [0.0, 90.0, 179.0]),
        ("in", [60.0], [0.0, 179.0]),
    ):
        cfg = _write(
            tmp_path / "brdf.toml",
            f'material = "gold"\nterms = ["single"]\nincidence_deg = {inc}\n'
            f'bistatic_deg = {bis}\nplane = "{plane}"\n',
        )
        out = tmp_path / f"out_{plane}"
        capsys.readouterr()
        assert run("brdf", "-c", cfg, "-o", out) == 0
        err = capsys.readouterr().err
        with np.load(out / "brdf.npz") as z:
            valid, mueller = z["valid"], z["mueller"]
        assert np.all(valid == (z_out(inc, bis, plane) > 1e-12))
        assert np.all(np.isfinite(mueller[valid])) and np.all(np.isnan(mueller[~valid]))
        n_bad = int((~valid).sum())
        assert n_bad > 0 and f"{n_bad} of {valid.size} geometries have k_out at or below" in err
    # 1e-5 deg above the horizon is above it (k.n = 1.7e-7: a 1e-6 cut called it below and
    # wrote NaN), keyed by the incidence as written
    cfg = _write(
        tmp_path / "brdf.toml",
        'material = "aluminium/rough"\nincidence_deg = [89.99999]\nbistatic_deg = [0.0, 0.001]\n',
    )
    capsys.readouterr()
    assert run("brdf", "-c", cfg, "-o", tmp_path / "grazing") == 0
    assert "horizon" not in capsys.readouterr().err
    back = json.loads((tmp_path / "grazing" / "brdf.json").read_text())["backscatter"]
    assert list(back) == ["89.99999"] and back["89.99999"]["M00"] > 0


def z_out(inc, bis, plane):
    """The z component of k_out of ``ppr brdf``'s sweep (normal +z)."""
    from ppr.cli.brdf import brdf_geometry

    return brdf_geometry(inc, bis, plane)[1][..., 2]


def test_image_end_to_end_example_satellite(tmp_path):
    out = tmp_path / "img"
    assert (
        run(
            "image",
            "-q",
            "-o",
            out,
            "--set",
            "render.n_pixels=24",
            "--set",
            'render.terms=["single"]',
        )
        == 0
    )
    for name in cli.IMAGE_OUTPUTS:
        assert (out / name).is_file(), name
    with np.load(out / "image.npz") as z:
        assert z["mueller"].shape == (24, 24, 4, 4)
        assert set(z["part_names"]) == {"bus", "panels", "mast", "dish", "blanket"}
        assert (z["part"] >= 0).sum() > 20
        # the labelled copy: the same numbers, named dimensions, units, provenance
        import xarray as xr

        with xr.open_dataset(out / "image.nc", engine="h5netcdf") as ds:
            np.testing.assert_array_equal(ds["mueller"].values, z["mueller"])
            assert ds["mueller"].dims == ("y", "x", "stokes_out", "stokes_in")
            assert ds["mueller"].attrs["units"] == "1/sr"
            assert ds["retardance"].attrs["units"] == "rad"
            np.testing.assert_array_equal(ds["x"].values, z["u"])
            np.testing.assert_array_equal(ds["y"].values, z["v"])
            assert json.loads(ds.attrs["part_names"]) == list(z["part_names"])
            assert json.loads(ds.attrs["provenance"])["ppr"]
    # no temporary folders left behind
    assert not [p for p in out.iterdir() if p.name.startswith(".ppr-tmp")]


def test_simulate_end_to_end(tmp_path):
    out = tmp_path / "sim"
    assert (
        run(
            "simulate",
            "-q",
            "-o",
            out,
            "--terms",
            "single",
            "--states",
            "H,V",
            "--multibounce",  # plumbing only: the double bounce is tests/test_macro.py's
            "off",
            "--set",
            "visibility.samples_per_face=1",
        )
        == 0
    )
    with np.load(out / "simulate.npz") as z:
        data = z["data"]
        assert data.shape[:2] == (2, 4)
        assert data.shape[-1] == len(z["range_m"])
        assert np.all(np.isfinite(data)) and data[:, 0].sum() > 0
    summary = json.loads((out / "simulate.json").read_text())
    assert summary["kind"] == "stokes" and summary["labels"] == ["H", "V"]
    # the labelled copy (xarray): same numbers, dimensions named, units, time = 2 r / c
    import xarray as xr

    with xr.open_dataset(out / "simulate.nc", engine="h5netcdf") as ds:
        np.testing.assert_array_equal(ds["data"].values, data)
        assert ds["data"].dims == ("state", "stokes_out", "range")
        assert list(ds["state"].values) == ["H", "V"]
        assert ds["data"].attrs["units"] == "m^2/sr" and ds["range"].attrs["units"] == "m"
        np.testing.assert_allclose(
            ds["time_s"].values, 2.0 * ds["range"].values / ppr.C_LIGHT, rtol=1e-15
        )
        assert json.loads(ds.attrs["provenance"])["config"] is not None


def test_demo_runs_and_writes_summary(tmp_path):
    out = tmp_path / "demo"
    assert (
        run(
            "demo",
            "-q",
            "--out",
            out,
            "--pixels",
            "16",
            "--only",
            "image",
            "--set",
            'render.terms=["single"]',
        )
        == 0
    )
    summary = json.loads((out / "demo.json").read_text())
    assert "Mueller image" in summary["steps_seconds"]
    assert (out / "image.png").is_file()


# ------------------------------------------------------------------------ config errors
BAD_CASES = [
    # (config text, field named in the message, bad value named in the message)
    (
        'mesh = "example"\n[render]\nn_pixels = -3\n[materials]\ndefault = "aluminium"\n',
        "render.n_pixels",
        "-3",
    ),
    (
        'mesh = "example"\n[render]\nshading = "phong"\n[materials]\ndefault = "aluminium"\n',
        "render.shading",
        "phong",
    ),
    (
        'mesh = "example"\n[view]\nwavelength_nm = -532.0\n[materials]\ndefault = "aluminium"\n',
        "view.wavelength_nm",
        "-532",
    ),
    (
        'mesh = "example"\n[materials]\nbus = "unobtainium"\ndefault = "aluminium"\n',
        "materials.bus",
        "unobtainium",
    ),
    (
        'mesh = "example"\n[materials]\ndefault = { n_real = 1.5, n_imag = -1.0, m = 5.0 }\n',
        "materials.default.n_imag",
        "-1.0",
    ),
    (
        'mesh = "example"\n[pose]\nquaternion = [2.0, 0.0, 0.0, 0.0]\n[materials]\n'
        'default = "aluminium"\n',
        "pose.quaternion",
        "2.0",
    ),
    (
        'mesh = "example"\n[render]\nn_pixels = nan\n[materials]\ndefault = "aluminium"\n',
        "render.n_pixels",
        "finite",
    ),
    ('mesh = "no_such_file.obj"\n[materials]\ndefault = "aluminium"\n', "mesh", "no_such_file"),
]


@pytest.mark.parametrize("text, field, value", BAD_CASES)
def test_bad_config_is_one_line_exit_2(tmp_path, capsys, text, field, value):
    cfg = _write(tmp_path / "bad.toml", text)
    assert run("image", "-q", "-c", cfg, "-o", tmp_path / "out") == 2
    line = error_line(capsys)
    assert str(cfg) in line and field in line and value in line, line
    assert not (tmp_path / "out" / "image.npz").exists()


def test_unknown_key_is_an_error(tmp_path, capsys):
    cfg = _write(
        tmp_path / "typo.toml",
        'mesh = "example"\n[render]\nn_pixel = 32\n[materials]\ndefault = "aluminium"\n',
    )
    assert run("image", "-c", cfg, "-o", tmp_path / "out") == 2
    line = error_line(capsys)
    assert "render.n_pixel" in line and "unknown key" in line and str(cfg) in line


def test_unknown_key_in_brdf_config(tmp_path, capsys):
    cfg = _write(tmp_path / "b.toml", 'material = "aluminium"\nwavelenght_nm = 532.0\n')
    assert run("brdf", "-c", cfg, "-o", tmp_path / "out") == 2
    assert "wavelenght_nm" in error_line(capsys)


def test_bad_override_is_one_line_exit_2(tmp_path, capsys):
    assert run("image", "-o", tmp_path / "o", "--set", "render.n_pixels=many") == 2
    line = error_line(capsys)
    assert "render.n_pixels" in line and "many" in line
    assert run("image", "-o", tmp_path / "o", "--set", "no_equals_sign") == 2
    assert "key=value" in error_line(capsys)


def test_missing_config_file(tmp_path, capsys):
    assert run("brdf", "-c", tmp_path / "nope.toml", "-o", tmp_path / "o") == 2
    assert "nope.toml" in error_line(capsys)


def test_bad_scene_is_one_line_exit_2(tmp_path, capsys):
    scene = ROOT / "configs" / "scenes" / "cubesat3u_panels.toml"
    if not scene.is_file():
        pytest.skip("scene configs not present")
    assert (
        run(
            "simulate",
            "-c",
            scene,
            "-o",
            tmp_path / "o",
            "--set",
            "pose.quaternion=[1.0, 0.0, 0.0]",
        )
        == 2
    )
    line = error_line(capsys)
    assert "pose.quaternion" in line and str(scene) in line


# --------------------------------------------------------------------------- overwriting
def test_refuses_to_overwrite(tmp_path, capsys):
    cfg = _write(
        tmp_path / "brdf.toml",
        'material = "gold"\nterms = ["single"]\nincidence_deg = [10.0]\nbistatic_deg = [0.0]\n',
    )
    out = tmp_path / "out"
    assert run("brdf", "-q", "-c", cfg, "-o", out) == 0
    before = (out / "brdf.npz").read_bytes()
    assert run("brdf", "-q", "-c", cfg, "-o", out, "--set", 'material="silver"') == 2
    line = error_line(capsys)
    assert "already exists" in line and "--overwrite" in line
    assert (out / "brdf.npz").read_bytes() == before
    assert run("brdf", "-q", "-c", cfg, "-o", out, "--set", 'material="silver"', "--overwrite") == 0
    assert json.loads((out / "brdf.json").read_text())["material"]["name"].startswith("silver")


def test_empty_arguments_are_refused_not_defaults(tmp_path, capsys, monkeypatch):
    """An empty --out (an unset shell variable) would write into the working folder and an
    empty --only would run every demo step: both are refused in one line."""
    monkeypatch.chdir(tmp_path)
    assert run("brdf", "-q", "-o", "") == 2
    assert error_line(capsys) == "ppr brdf: error: --out '': empty path; choose a folder"
    assert run("demo", "-q", "--only", " ", "-o", tmp_path / "d") == 2
    assert "--only ' ': empty; give steps from" in error_line(capsys)
    assert list(tmp_path.iterdir()) == []


def test_unwritable_out_is_one_line_naming_it(tmp_path, capsys, monkeypatch):
    """An --out the user cannot write in (a read-only file system: mkdir raises) is refused in
    one line naming --out as written and the reason, with exit status 2 and no folder left
    behind; another write failure later is one line too (exit status 1), not a traceback."""
    import errno
    import pathlib

    cfg = _write(
        tmp_path / "brdf.toml",
        'material = "gold"\nterms = ["single"]\nincidence_deg = [10.0]\nbistatic_deg = [0.0]\n',
    )
    real_mkdir = pathlib.Path.mkdir

    def read_only(self, *args, **kwargs):
        if str(self).startswith(str(tmp_path / "ro")):
            raise PermissionError(errno.EROFS, "Read-only file system", str(self))
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(pathlib.Path, "mkdir", read_only)
    out = tmp_path / "ro" / "deep" / "out"
    assert run("brdf", "-q", "-c", cfg, "-o", out) == 2
    line = error_line(capsys)
    assert line == (
        f"ppr brdf: error: --out {out}: cannot write in {out.parent} (Read-only file system); "
        "choose a folder you can write to"
    ), line
    assert not (tmp_path / "ro").exists()
    monkeypatch.setattr(pathlib.Path, "mkdir", real_mkdir)

    import ppr.cli.brdf as cb

    def disk_full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "o2" / "brdf.npz"))

    monkeypatch.setattr(cb.np, "savez_compressed", disk_full)
    assert run("brdf", "-q", "-c", cfg, "-o", tmp_path / "o2") == 1
    line = error_line(capsys)
    assert "No space left on device" in line and "previous outputs were left" in line, line
    assert not (tmp_path / "o2").exists()


# ------------------------------------------------------------------------------ subprocess
def test_subprocess_smoke(tmp_path):
    """The installed entry point's module runs in a fresh interpreter; a config error gives
    exit status 2 and one line on stderr."""
    bad = _write(tmp_path / "bad.toml", 'material = "aluminium"\nplane = "diagonal"\n')
    env = dict(os.environ, PPR_JAX_CACHE="0", JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, "-m", "ppr.cli", "brdf", "-c", str(bad), "-o", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "plane" in lines[0] and "diagonal" in lines[0]
    ok = subprocess.run(
        [sys.executable, "-m", "ppr.cli", "--help"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert ok.returncode == 0 and "simulate" in ok.stdout
    # the entry point is light: importing it (and `ppr --version`) loads neither JAX nor the
    # library, so Ctrl-C during start-up is caught by main() like any interruption
    light = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys, ppr.cli; assert 'jax' not in sys.modules, 'jax imported'; "
            "sys.argv = ['ppr', '--version']; ppr.cli.main()",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert light.returncode == 0 and light.stdout.startswith("ppr "), light.stderr


# ------------------------------------------------------------------------- inversion side
SMALL_DB = """name = "tiny"
model = "synthetic"
materials = ["aluminium", "white_paint"]
chunk_rows = 64
[finishes]
polished = 3000.0
matte = 5.0
[[shapes]]
name = "cube"
symmetry = "octahedral"
[[shapes]]
name = "box3u"
symmetry = "dihedral:4"
[grid]
kind = "hopf"
size = 1
[sensor]
channels = "copol"
n_bins = 32
bin_width_m = 0.01
"""


@pytest.fixture(scope="module")
def tiny_db(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("db")
    spec = _write(tmp / "tiny.toml", SMALL_DB)
    out = tmp / "out"
    assert run("database", "build", "-q", "-c", spec, "-o", out) == 0
    return spec, out


def test_database_build_and_refuse(tiny_db, capsys):
    spec, out = tiny_db
    summary = json.loads((out / "database.json").read_text())
    assert summary["complete"] and summary["n_rows"] > 0 and summary["missing_chunks"] == 0
    assert (out / "database.zarr" / "zarr.json").is_file()
    capsys.readouterr()
    assert run("database", "build", "-q", "-c", spec, "-o", out) == 2
    assert "already exists" in error_line(capsys)


def test_database_without_subcommand_is_usage_error(capsys):
    assert run("database") == 2


def test_classify_end_to_end(tiny_db, tmp_path):
    _, db = tiny_db
    cfg = _write(
        tmp_path / "c.toml",
        f'database = "{db / "database.zarr"}"\nn_simulated = 6\ntop_k = 3\n[noise]\nsnr = 100.0\n',
    )
    out = tmp_path / "cls"
    assert run("classify", "-q", "-c", cfg, "-o", out) == 0
    summary = json.loads((out / "classify.json").read_text())
    assert summary["n_observations"] == 6 and len(summary["candidates"][0]) == 3
    assert set(summary["accuracy"]) == {"shape", "material", "finish"}
    with np.load(out / "classify.npz") as z:
        assert z["index"].shape == (6, 3)
    # the observations written by one run classify again from the file
    cfg2 = _write(
        tmp_path / "c2.toml",
        f'database = "{db / "database.zarr"}"\nobservations = "{out / "classify.npz"}"\n',
    )
    assert run("classify", "-q", "-c", cfg2, "-o", tmp_path / "cls2") == 0
    # an empty frame (no return) is flagged in place, not classified silently
    with np.load(out / "classify.npz") as z:
        data = z["data"].copy()
        assert not z["no_signal"].any()
    data[2] = 0.0
    np.savez(tmp_path / "empty.npz", data=data)
    cfg3 = _write(
        tmp_path / "c3.toml",
        f'database = "{db / "database.zarr"}"\nobservations = "{tmp_path / "empty.npz"}"\n',
    )
    assert run("classify", "-q", "-c", cfg3, "-o", tmp_path / "cls3") == 0
    assert json.loads((tmp_path / "cls3" / "classify.json").read_text())["no_signal"] == [2]


def test_classify_figure_with_best_scores_ulps_apart(tmp_path):
    """Best scores a few float32 ulps apart (copies of one observation with 1e-4 noise):
    the figure is drawn (numpy's histogram refused 20 bins over that width, and classify
    wrote nothing)."""
    from ppr import plots

    score = np.float32([[0.9999], [0.99990004], [0.9999001]])
    data = np.ones((3, 2, 8))
    sig = np.ones((1, 2, 8)) / 16.0
    zeros = np.zeros((3, 1))
    plots.plot_classification(tmp_path / "c.png", data, sig, zeros.astype(int), zeros, score)
    assert (tmp_path / "c.png").stat().st_size > 1000


def test_classify_top_k_beyond_the_database_is_said(tiny_db, tmp_path, capsys):
    """top_k above the database's template count returns every template, and says so."""
    _, db = tiny_db
    cfg = _write(
        tmp_path / "c.toml",
        f'database = "{db / "database.zarr"}"\nn_simulated = 2\ntop_k = 1000\n',
    )
    capsys.readouterr()
    assert run("classify", "-q", "-c", cfg, "-o", tmp_path / "cls") == 0
    n = json.loads((tmp_path / "cls" / "classify.json").read_text())["n_templates"]
    assert f"top_k = 1000 is more than the database's {n} templates" in capsys.readouterr().err


def test_classify_missing_database(tmp_path, capsys):
    cfg = _write(tmp_path / "c.toml", 'database = "nowhere.zarr"\n')
    assert run("classify", "-c", cfg, "-o", tmp_path / "o") == 2
    line = error_line(capsys)
    assert "database" in line and "nowhere.zarr" in line


def test_report_end_to_end(tiny_db, tmp_path):
    spec, _ = tiny_db
    cfg = _write(
        tmp_path / "r.toml",
        f'database = "{spec}"\nsnrs = [30.0]\ngrid_sizes = [1]\nn_obs = 4\n'
        'weight_kinds = ["uniform", "fisher"]\n',
    )
    out = tmp_path / "rep"
    assert run("report", "-q", "-c", cfg, "-o", out) == 0
    assert json.loads((out / "report.json").read_text())
    assert (out / "report.md").stat().st_size > 0
    assert (out / "accuracy_vs_snr.png").is_file()


INV_SENSOR = """wavelength_nm = 532.0
line_of_sight = [0.0, 0.0, -1.0]
polarization_reference = [1.0, 0.0, 0.0]
[pulse]
fwhm_s = 100e-12
[bins]
width_m = 0.01
count = 32
"""
INV_SCENE = """sensor = "sensor.toml"
[shape]
name = "cubesat"
params = { units = 1 }
[materials]
body = { n_real = 1.5, n_imag = 0.05, m = 10.0 }
[pose]
quaternion = [0.9317252, 0.2504638, 0.2003711, 0.1703154]
[visibility]
samples_per_face = 1
"""


def test_invert_simulated_return_outside_the_gate_names_the_offset(tmp_path, capsys):
    """A simulated observation whose range offset moves the whole return out of the bins is
    refused naming the offset and the gate (it was 'all values are 0 (no signal)')."""
    _write(tmp_path / "sensor.toml", INV_SENSOR)
    _write(tmp_path / "scene.toml", INV_SCENE)
    text = 'scene = "scene.toml"\nbrdf = "glossy"\nmcmc = "none"\n'
    cfg = _write(tmp_path / "inv.toml", text + "[observation]\nrange_offset_m = 5.0\n")
    out = tmp_path / "out"
    assert run("invert", "-q", "-c", cfg, "-o", out) == 2
    line = error_line(capsys)
    assert line.startswith(f"ppr invert: error: {cfg}: observation.range_offset_m = 5.0: ")
    assert "out of the range gate [-0.16, 0.16] m" in line, line
    assert not out.exists()


def test_invert_end_to_end(tmp_path, capsys):
    """``ppr invert`` is config + inversion.invert + Inversion.write: the JSON separates
    converged from reliable with the reasons (a 20-step chain has not converged; the glossy
    stand-in's copolarized returns cannot tell the cube from its mirror image), the posterior
    file is ArviZ netCDF in physical units, no inf/NaN anywhere, errors against the
    simulated truth; bad MCMC settings are refused by name before any computation."""
    _write(tmp_path / "sensor.toml", INV_SENSOR)
    _write(tmp_path / "scene.toml", INV_SCENE)
    mcmc = ROOT / "configs" / "inversion" / "default.toml"
    cfg = _write(
        tmp_path / "inv.toml",
        f'scene = "scene.toml"\nbrdf = "glossy"\nmcmc = "{mcmc}"\n'
        "mcmc_walkers = 16\nmcmc_steps = 20\nmcmc_burn_in = 5\n"
        'materials = ["aluminium", "fused_silica"]\ntop_k = 2\n[grid]\nsize = 2\n',
    )
    out = tmp_path / "inv"
    assert run("invert", "-q", "-c", cfg, "-o", out) == 0
    for name in ("invert.json", "invert_fit.npz", "invert_posterior.nc", "invert_fit.png"):
        assert (out / name).is_file(), name
    text = (out / "invert.json").read_text()
    assert "Infinity" not in text and "NaN" not in text and '"success"' not in text
    summary = json.loads(text)
    assert summary["converged"] in (True, False) and summary["reliable"] is False
    assert any("not converged" in r for r in summary["reasons"]), summary["reasons"]
    # the glossy stand-in: the mirror image of the cube fits as well (weight about 1/2)
    mirror = [m for m in summary["modes"] if m["kind"] == "mirror"]
    assert mirror and abs(mirror[0]["weight"] - 0.5) < 0.05, summary["modes"]
    assert any("attitude modes not resolved" in r for r in summary["reasons"])
    gof = summary["goodness_of_fit"]
    assert gof["statistic"] == "poisson_deviance" and 0 <= gof["p_value"] <= 1
    assert abs(gof["deviance"] - summary["fit"]["deviance"]) < 1e-6 * gof["deviance"]
    # the deviance and the marginal tests, combined (Bonferroni) into the reported p-value
    comps = gof["components"]
    assert [c["name"] for c in comps][:2] == ["all values", "range profile"], comps
    assert gof["p_value"] == min(1.0, len(comps) * min(c["p_value"] for c in comps))
    obs = summary["observability"]
    nulls = [lab for lab, sg in zip(obs["labels"], obs["sigma"], strict=True) if sg is None]
    assert nulls == obs["unobservable_on_own"]
    probs = summary["material_probabilities"][0]["probabilities"]
    assert set(probs) == {"aluminium", "fused_silica"} and abs(sum(probs.values()) - 1) < 1e-9
    err = summary["truth"]["errors"]
    assert err["los_error_mod_mirror_deg"] <= err["los_error_deg"] + 1e-9
    crb = summary["truth"]["cramer_rao"]
    assert len(crb["sigma"]) == len(crb["labels"])
    # the posterior file: ArviZ InferenceData in physical units, the JSON quotes it
    import arviz as az

    idata = az.from_netcdf(out / "invert_posterior.nc")
    post = summary["modes"][0]["posterior"]
    assert summary["modes"][0]["posterior"]["file"] == "invert_posterior.nc"
    i_gain = post["labels"].index("gain")
    np.testing.assert_allclose(
        float(np.median(idata.posterior["gain"].values)), post["median"][i_gain], rtol=1e-12
    )
    assert idata.posterior.attrs["burn_in"] == 5 and idata.posterior.sizes["chain"] == 16
    # bad MCMC settings: refused by name before any computation (no output folder)
    for extra, words in (
        (["--set", "mcmc_steps=5"], ["mcmc_steps = 5"]),
        (["--set", "mcmc_burn_in=50"], ["mcmc_burn_in = 50", "mcmc_steps = 20"]),
        (["--set", 'mcmc_set={"sampler.n_walkers"=2}'], ["sampler.n_walkers = 2"]),
        (["--set", "top_k=0"], ["top_k = 0"]),
    ):
        capsys.readouterr()
        assert run("invert", "-q", "-c", cfg, "-o", tmp_path / "bad", *extra) == 2
        line = error_line(capsys)
        for w in words:
            assert w in line, line
        assert not (tmp_path / "bad").exists()


def test_invert_mcmc_none_switches_the_sampler_off(tmp_path, capsys):
    """TOML has no null: ``mcmc = "none"`` (any case) or ``false``, in the file or by --set,
    give the library config no sampler; ``true`` is refused by name."""
    from ppr._config import load_toml_model
    from ppr.cli import invert as ci

    for text, over in (
        ('mcmc = "none"', {}),
        ("mcmc = false", {}),
        ("", {"mcmc": "None"}),
        ("", {"mcmc": False}),
    ):
        path = _write(tmp_path / "inv.toml", f'scene = "scene.toml"\n{text}\n')
        cfg = load_toml_model(ci._schema(), path, over)
        assert cfg.mcmc is None
        assert ci.invert_config(cfg, path, False).mcmc is None
    import argparse

    from ppr.cli._common import overrides

    assert overrides(argparse.Namespace(set=["mcmc=none"])) == {"mcmc": "none"}
    path = _write(tmp_path / "inv.toml", 'scene = "scene.toml"\nmcmc = true\n')
    assert run("invert", "-q", "-c", path, "-o", tmp_path / "out") == 2
    line = error_line(capsys)
    assert "mcmc = true" in line.lower() and "none" in line, line
    assert not (tmp_path / "out").exists()


def _obs_files(folder: Path) -> None:
    """Observation files a user might hand ``ppr invert`` by mistake (2 channels x 32 bins:
    the copol preset on INV_SENSOR)."""
    good = np.random.default_rng(0).poisson(3.0, size=(2, 32)).astype(float)
    neg, nan = good.copy(), good.copy()
    neg[0, 3], nan[1, 5] = -2.0, np.nan
    for name, arr in {
        "nodata": {"counts": good},
        "shape": {"data": np.ones(64)},
        "str": {"data": np.full((2, 32), "1")},
        "complex": {"data": good + 0j},
        "bool": {"data": good > 2},
        "nan": {"data": nan},
        "neg": {"data": neg},
        "zero": {"data": np.zeros((2, 32))},
    }.items():
        np.savez(folder / f"{name}.npz", **arr)
    np.save(folder / "plain.npy", good)
    (folder / "text.npz").write_text("1 2 3")
    (folder / "trunc.npz").write_bytes((folder / "neg.npz").read_bytes()[:100])
    (folder / "adir.npz").mkdir()
    import zipfile

    with zipfile.ZipFile(folder / "member.npz", "w") as z:  # a member not in .npy format
        z.writestr("data.npy", b"garbage")


# (observation file, what the one line must name besides the config file and the field):
# refused before any computation, nothing cast or dropped silently
BAD_OBSERVATIONS = [
    ("missing.npz", ["no such file"]),
    ("adir.npz", ["is a folder, not an .npz file"]),
    ("plain.npy", ["a single .npy array, not an .npz archive", "np.savez(path, data=array)"]),
    ("text.npz", ["not a NumPy .npz file (no zip header)"]),
    ("trunc.npz", ["not a NumPy .npz file"]),
    ("nodata.npz", ["no 'data' array (it has counts)"]),
    ("member.npz", ["array 'data' cannot be read", "data.npy is not a .npy array"]),
    ("shape.npz", ["data has shape (64,)", "(2 channels, 32 bins)"]),
    ("str.npz", ["data has dtype <U1 (strings)"]),
    ("complex.npz", ["data has dtype complex128", "imaginary part"]),
    ("bool.npz", ["data has dtype bool"]),
    ("nan.npz", ["1 NaN/inf value(s), first at index (1, 5) = nan"]),
    ("neg.npz", ["photo-counts >= 0", "first at (0, 3): -2.0"]),
    ("zero.npz", ["all 64 values are 0 (no signal)"]),
]


def test_invert_bad_observation_file_is_one_line_naming_it(tmp_path, capsys):
    """``observation.source``: every faulty file is refused in one line naming the config
    file, the field as written and the file, with the fault (the dtype, the first NaN or
    negative count and its position), before any computation and with no --out folder."""
    _write(tmp_path / "sensor.toml", INV_SENSOR)
    _write(tmp_path / "scene.toml", INV_SCENE)
    _obs_files(tmp_path)
    cfg = _write(tmp_path / "inv.toml", 'scene = "scene.toml"\nbrdf = "glossy"\nmcmc = "none"\n')
    out = tmp_path / "out"
    for name, needles in BAD_OBSERVATIONS:
        text = 'scene = "scene.toml"\nbrdf = "glossy"\nmcmc = "none"\n'
        text += f'[observation]\nsource = "{name}"\n'
        _write(cfg, text)
        capsys.readouterr()
        assert run("invert", "-q", "-c", cfg, "-o", out) == 2, name
        line = error_line(capsys)
        assert line.startswith(f"ppr invert: error: {cfg}: observation.source = '{name}': ")
        for needle in needles:
            assert needle in line, (needle, line)
        assert not out.exists()


def test_invert_failed_or_interrupted_keeps_the_previous_result(tmp_path, capsys, monkeypatch):
    """``ppr invert --overwrite`` that fails or is stopped once the inversion has started
    (after every check passed) leaves the previous result file for file."""
    import signal
    import time

    import inversion
    import inversion._invert as inv_mod

    _write(tmp_path / "sensor.toml", INV_SENSOR)
    _write(tmp_path / "scene.toml", INV_SCENE)
    # a file observation: no simulation to compile before the inversion starts
    np.savez(tmp_path / "obs.npz", data=np.ones((2, 32)))
    cfg = _write(
        tmp_path / "inv.toml",
        'scene = "scene.toml"\nbrdf = "glossy"\nmcmc = "none"\n[observation]\nsource = "obs.npz"\n',
    )
    out = tmp_path / "out"
    out.mkdir()
    for name in inversion.INVERT_FILES:
        (out / name).write_text(f"previous {name}")
    before = {p.name: p.read_text() for p in out.iterdir()}

    def ctrl_c(*args, **kwargs):
        raise KeyboardInterrupt

    def sigterm(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler raises first

    def fails(*args, **kwargs):
        raise RuntimeError("a failure inside the inversion")

    for fake, code in ((ctrl_c, 130), (sigterm, 143), (fails, None)):
        monkeypatch.setattr(inv_mod, "screening_bank", fake)  # the first stage after checks
        capsys.readouterr()
        if code is None:
            with pytest.raises(RuntimeError, match="a failure inside"):
                run("invert", "-q", "-c", cfg, "-o", out, "--overwrite")
        else:
            assert run("invert", "-q", "-c", cfg, "-o", out, "--overwrite") == code
            assert "previous outputs were left as they were" in error_line(capsys)
        assert {p.name: p.read_text() for p in out.iterdir()} == before


# ------------------------------------------------------- bad inputs, interruptions (issue 28)
NAN_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv nan 0 0\nf 1 2 3\nf 1 3 4\nf 1 2 4\nf 2 3 5\n"
CORRUPT_STL = b"solid x\nfacet normal 0 0 1\n outer loop\n vertex 0 0 \xff\xfe junk"
BRDF_OK = 'material = "gold"\nterms = ["single"]\nincidence_deg = [10.0]\nbistatic_deg = [0.0]\n'
IMG_OK = 'mesh = "example"\n[materials]\ndefault = "aluminium"\n'
CLS = 'database = "{db}"\nn_simulated = 2\n'

# (command, config text or None for the command's default, extra arguments, what the one
# line must name besides the config file: the field as written and the bad value). Every
# case must fail before any computation and leave no --out folder.
BAD_INPUTS = [
    ("brdf", BRDF_OK, ["--set", "incidence_deg=[]"], ["incidence_deg = []", "must not be empty"]),
    (
        "brdf",
        BRDF_OK,
        ["--set", "bistatic_deg={start=0.0,stop=1.0,num=0}"],
        ["bistatic_deg.num = 0"],
    ),
    ("brdf", BRDF_OK, ["--set", "terms=[]"], ["terms = []", "must not be empty"]),
    ("brdf", BRDF_OK, ["--set", 'terms=["single","single"]'], ["terms = ", "listed twice"]),
    ("brdf", BRDF_OK, ["--set", "material=3"], ["material = 3", "a string or a table"]),
    ("brdf", BRDF_OK, ["--set", "wavelength_nm=inf"], ["wavelength_nm = inf", "not finite"]),
    ("brdf", BRDF_OK, ["--set", "=3"], ["--set '=3'", "empty key"]),
    (
        "image",
        IMG_OK
        + "[view]\nline_of_sight = [0.0, 0.0, -1.0]\npolarization_reference = [0.0, 0.0, 2.0]\n",
        [],
        ["view: polarization_reference = [0.0, 0.0, 2.0]", "line_of_sight"],
    ),
    (
        "image",
        'mesh = "nan.obj"\n[materials]\ndefault = "gold"\n',
        [],
        ["mesh = 'nan.obj'", "non-finite"],
    ),
    (
        "image",
        'mesh = "bad.stl"\n[materials]\ndefault = "gold"\n',
        [],
        ["bad.stl", "not a valid STL"],
    ),
    (
        "image",
        'mesh = "x.3ds"\n[materials]\ndefault = "gold"\n',
        [],
        ["x.3ds", "unsupported format"],
    ),
    ("image", 'scene = "nope.toml"\n', [], ["scene = 'nope.toml'", "no such scene file"]),
    (
        "image",
        IMG_OK,
        ["--set", "materials.default.x=1"],
        ["override 'materials.default.x'", "'materials.default' is 'aluminium', not a table"],
    ),
    (
        "simulate",
        'sensor = "default"\nmesh = "nan.obj"\n[materials]\nnan = "gold"\n',
        [],
        ["mesh", "nan.obj", "non-finite"],
    ),
    ("simulate", None, ["--states", "H,Q"], ["--states 'H,Q'", "'Q'"]),
    ("simulate", None, ["--terms", "single,quad"], ["--terms 'single,quad'", "'quad'"]),
    ("simulate", None, ["--states", "H,V,H"], ["--states 'H,V,H'", "'H' is listed twice"]),
    (
        "database build",
        SMALL_DB,
        ["--set", "shapes[9].symmetry='none'"],
        ["override 'shapes[9].symmetry'", "'shapes' has"],
    ),
    (
        "database build",
        SMALL_DB,
        ["--set", 'materials=["aluminium", "unobtainium"]'],
        ["materials[1] = 'unobtainium'"],
    ),
    ("database build", SMALL_DB, ["--set", 'model="foo"'], ["model = 'foo'"]),
    ("database build", SMALL_DB, ["--set", 'sensor.channels="foo"'], ["sensor.channels = 'foo'"]),
    (
        "database build",
        SMALL_DB.replace('symmetry = "octahedral"', 'symmetry = "weird"'),
        [],
        ["shapes[0].symmetry = 'weird'"],
    ),
    ("database build", SMALL_DB, ["--num-shards", "0"], ["--num-shards 0"]),
    ("classify", CLS + "[noise]\nsnr = 0.0\n", [], ["noise.snr = 0.0"]),
    ("classify", CLS + "seed = -1\n", [], ["seed = -1"]),
    ("classify", CLS + "[noise]\ngain_min = 10.0\ngain_max = 0.1\n", [], ["gain_min = 10.0"]),
    ("classify", CLS + "max_shift_bins = 1000\n", [], ["max_shift_bins = 1000"]),
    ("classify", CLS + 'observations = "bad.stl"\n', [], ["observations = 'bad.stl'", ".npz"]),
    (
        "classify",
        CLS + 'observations = "plain.npy"\n',
        [],
        ["observations = 'plain.npy'", "a single .npy array, not an .npz archive"],
    ),
    (
        "classify",
        CLS + 'observations = "huge.npz"\n',
        [],
        ["observations = 'huge.npz'", "data value 1e+300 at index (0, 0, 0) overflows float32"],
    ),
    (
        "classify",
        CLS + 'observations = "tiny.npz"\n',
        [],
        ["observations = 'tiny.npz'", "observation 0's largest value 1e-300 is too small for"],
    ),
    (
        "classify",
        CLS + 'observations = "complex.npz"\n',
        [],
        ["observations = 'complex.npz'", "dtype complex128", "imaginary part"],
    ),
    (
        "classify",
        'database = "nowhere.zarr"\n',
        [],
        ["database = 'nowhere.zarr'", "does not exist"],
    ),
    ("report", 'database = "{spec}"\nsnrs = []\n', [], ["snrs = []", "must not be empty"]),
    ("report", 'database = "{spec}"\nsnrs = [30.0, 30.0]\n', [], ["30.0 is listed twice"]),
    ("report", 'database = "{spec}"\ngain_range = [10.0, 0.1]\n', [], ["gain_range = [10.0, 0.1]"]),
    ("report", 'database = "nope.toml"\n', [], ["database = 'nope.toml'", "no such config file"]),
    ("demo", None, ["--only", "image", "--pixels", "2"], ["--pixels 2"]),
    (
        "invert",
        None,
        ["--set", "finishes={rough=1e-6}"],
        ["finishes.rough = 1e-06", "support [0.001, 1e+06] of mcmc.priors.m", "mcmc = 'default'"],
    ),
    (
        "invert",
        None,
        ["--set", 'materials=[{name="x",n_real=1e300,n_imag=0.1}]'],
        ["materials[0].n_real = 1e+300", "outside [0.05, 5]"],
    ),
    ("invert", None, ["--set", 'symmetry="dihedral:100000000"'], ["order above 64"]),
]


@pytest.mark.parametrize(
    "command, text, extra, needles",
    BAD_INPUTS,
    ids=[f"{c[0]}-{i}" for i, c in enumerate(BAD_INPUTS)],
)
def test_bad_input_is_one_line_exit_2(tiny_db, tmp_path, capsys, command, text, extra, needles):
    spec, db = tiny_db
    (tmp_path / "nan.obj").write_text(NAN_OBJ)
    (tmp_path / "bad.stl").write_bytes(CORRUPT_STL)
    (tmp_path / "x.3ds").write_bytes(b"3ds")
    np.save(tmp_path / "plain.npy", np.ones((2, 32)))
    np.savez(tmp_path / "complex.npz", data=np.ones((2, 32)) + 1j)
    np.savez(tmp_path / "huge.npz", data=np.full((2, 32), 1e300))
    np.savez(tmp_path / "tiny.npz", data=np.full((2, 32), 1e-300))
    argv = command.split()
    if text is not None:
        cfg = _write(tmp_path / "cfg.toml", text.format(db=db / "database.zarr", spec=spec))
        argv += ["-c", cfg]
    out = tmp_path / "out"
    capsys.readouterr()
    assert run(*argv, "-q", "-o", out, *extra) == 2
    line = error_line(capsys)
    assert line.startswith(f"ppr {command}: error: ") and "Traceback" not in line
    if text is not None and not any(n.startswith("--") for n in needles):
        assert str(cfg) in line, line
    for needle in needles:
        assert needle in line, (needle, line)
    assert not out.exists()


DEGEN_OBJ = "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\nv 0 1 0\nf 1 2 4\n"


def test_image_mesh_table_takes_the_degenerate_face_hint(tmp_path, capsys):
    """``ppr image`` on a mesh with a zero-area face says how to drop it in the config's own
    notation, and the mesh table it names (as in scene configs) is accepted: the face is
    dropped, the other kept."""
    from ppr.cli import image

    (tmp_path / "degen.obj").write_text(DEGEN_OBJ)
    cfg = _write(tmp_path / "img.toml", 'mesh = "degen.obj"\n[materials]\ndefault = "gold"\n')
    assert run("image", "-q", "-c", cfg, "-o", tmp_path / "out") == 2
    line = error_line(capsys)
    assert "1 degenerate (zero-area) faces" in line
    assert 'mesh = {path = "...", on_degenerate = "drop"}' in line, line
    text = 'mesh = {path = "degen.obj", on_degenerate = "drop"}\n[materials]\ndefault = "gold"\n'
    _write(cfg, text)
    from ppr.config import read_toml

    mesh = image.image_inputs(image.ImageConfig.model_validate(read_toml(cfg)), cfg)[0]
    assert mesh.n_faces == 1
    _write(cfg, text.replace('"drop"', '"keep"'))
    assert run("image", "-q", "-c", cfg, "-o", tmp_path / "out") == 2
    assert "mesh.on_degenerate = 'keep'" in error_line(capsys)


def test_out_is_a_file(tmp_path, capsys):
    cfg = _write(tmp_path / "b.toml", BRDF_OK)
    (tmp_path / "taken").write_text("a file")
    assert run("brdf", "-q", "-c", cfg, "-o", tmp_path / "taken") == 2
    line = error_line(capsys)
    assert f"--out {tmp_path / 'taken'}: is an existing file" in line
    assert (tmp_path / "taken").read_text() == "a file"


def test_ctrl_c_and_sigterm_keep_previous_outputs(tmp_path, capsys, monkeypatch):
    import signal
    import time

    from ppr.image import _image

    cfg = _write(tmp_path / "b.toml", BRDF_OK)
    out = tmp_path / "out"
    out.mkdir()
    for name in ("brdf.npz", "brdf.json", "brdf.png"):
        (out / name).write_text(f"previous {name}")

    def ctrl_c(*args, **kwargs):
        raise KeyboardInterrupt

    def sigterm(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler raises first

    for fake, code, word in ((ctrl_c, 130, "interrupted"), (sigterm, 143, "terminated")):
        monkeypatch.setattr(_image, "evaluate_mueller", fake)
        capsys.readouterr()
        assert run("brdf", "-q", "-c", cfg, "-o", out, "--overwrite") == code
        assert error_line(capsys) == f"ppr brdf: {word}; previous outputs were left as they were"
        assert sorted(os.listdir(out)) == ["brdf.json", "brdf.npz", "brdf.png"]
        assert (out / "brdf.npz").read_text() == "previous brdf.npz"
    assert signal.getsignal(signal.SIGTERM) is not None  # restored, not left raising


def store_bytes(path: Path, skip: str = "\0") -> dict[str, bytes]:
    return {
        str(p.relative_to(path)): p.read_bytes()
        for p in sorted(path.rglob("*"))
        if p.is_file() and not str(p.relative_to(path)).startswith(skip)
    }


def test_failed_or_interrupted_overwrite_keeps_the_database(tiny_db, tmp_path, capsys, monkeypatch):
    import shutil

    import inversion._database as D

    spec, built = tiny_db
    out = tmp_path / "db"
    shutil.copytree(built, out)
    before = store_bytes(out)
    # a typo with --overwrite: refused before anything is touched (issue 28, item 1)
    bad = 'materials=["unobtainium"]'
    assert run("database", "build", "-q", "-c", spec, "-o", out, "--overwrite", "--set", bad) == 2
    assert store_bytes(out) == before
    # --overwrite with new settings builds beside the old store; interrupted, the old stays
    new = ["--set", 'materials=["white_paint", "aluminium"]']
    real, calls, stop = D.evaluate_rows, [], [1]

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) == stop[0]:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(D, "evaluate_rows", interrupted)
    # a fresh build interrupted before its first chunk leaves no folder behind
    fresh = tmp_path / "fresh" / "db"
    assert run("database", "build", "-q", "-c", spec, "-o", fresh, *new) == 130
    assert not (tmp_path / "fresh").exists()
    calls.clear()
    stop[0] = 2
    capsys.readouterr()
    assert run("database", "build", "-q", "-c", spec, "-o", out, "--overwrite", *new) == 130
    assert "interrupted; rerun the same command to resume" in error_line(capsys)
    assert store_bytes(out, skip="database.zarr.partial") == before
    assert (out / "database.zarr.partial" / "_chunks" / "000000.json").is_file()
    monkeypatch.setattr(D, "evaluate_rows", real)
    # rerun: resumes the staged build, then swaps it in whole
    assert run("database", "build", "-q", "-c", spec, "-o", out, "--overwrite", *new) == 0
    assert sorted(os.listdir(out)) == ["database.json", "database.zarr"]
    summary = json.loads((out / "database.json").read_text())
    assert summary["complete"] and summary["skipped_chunks"] == 1
    assert summary["computed_chunks"] == summary["n_chunks"] - 1
    import inversion

    assert inversion.load_database(out / "database.zarr").names["materials"] == [
        "white_paint",
        "aluminium",
    ]


def test_corrupt_chunk_is_repaired_by_the_command_classify_names(tiny_db, tmp_path, capsys):
    import shlex
    import shutil

    spec, built = tiny_db
    out = tmp_path / "db"
    shutil.copytree(built, out)
    store = out / "database.zarr"
    reference = store_bytes(store)
    chunk = sorted(p for p in (store / "signatures" / "c").rglob("*") if p.is_file())[1]
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    cfg = _write(tmp_path / "c.toml", f'database = "{store}"\n')
    capsys.readouterr()
    assert run("classify", "-q", "-c", cfg, "-o", tmp_path / "cls") == 2
    line = error_line(capsys)
    assert "chunks [1] do not match their checksums" in line
    advice = line.split("rerun `")[1].split("`")[0]
    assert advice == f"ppr database build -c {Path(spec).resolve()} -o {out}"
    assert run(*shlex.split(advice)[1:], "-q") == 0  # the advice works as written
    assert store_bytes(store) == reference  # equal to the uninterrupted build, byte for byte
    assert json.loads((out / "database.json").read_text())["recomputed_corrupt"] == [1]
    capsys.readouterr()
    assert run(*shlex.split(advice)[1:], "-q") == 2  # now complete: refused
    assert "already exists and is complete" in error_line(capsys)
