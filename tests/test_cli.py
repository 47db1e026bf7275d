"""The ``ppr`` command line: every command end to end on a small config, one-line config
errors with exit status 2, unknown keys, refusing to overwrite. Commands run in-process
(``cli.main([...])``) to share JAX start-up and compilations; one subprocess smoke test."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ppr import _image, cli

HAVE_BRDF = _image.api("mueller_brdf") is not None
needs_brdf = pytest.mark.skipif(not HAVE_BRDF, reason="ppr.mueller_brdf not available")
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
    for cmd in ("demo", "brdf", "image", "simulate"):
        assert cmd in text


@pytest.mark.parametrize(
    "cmd, units",
    [
        ("brdf", ["nanometres", "degrees", "1/sr"]),
        ("image", ["microradians", "metres", "1/sr", "[rad]"]),
        ("simulate", ["picoseconds", "microradians", "m^2/sr"]),
        ("demo", ["--out"]),
    ],
)
def test_subcommand_help_explains_units(capsys, cmd, units):
    assert run(cmd, "--help") == 0
    text = capsys.readouterr().out
    for u in units:
        assert u in text, (cmd, u)
    if cmd != "demo":
        for opt in ("--config", "--set", "--out", "--overwrite"):
            assert opt in text


def test_no_command_is_usage_error(capsys):
    assert run() == 2


# ---------------------------------------------------------------------------- end to end
def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@needs_brdf
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
    assert (out / "brdf.png").stat().st_size > 1000


@needs_brdf
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
    # no temporary folders left behind
    assert not [p for p in out.iterdir() if p.name.startswith(".ppr-tmp")]


@needs_brdf
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


def test_demo_runs_and_writes_summary(tmp_path):
    out = tmp_path / "demo"
    assert run("demo", "-q", "--out", out, "--pixels", "16", "--only", "image") == 0
    summary = json.loads((out / "demo.json").read_text())
    if HAVE_BRDF:
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
@needs_brdf
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
