"""Signature database: layout, resumability (kill mid-build), corruption detection, device
sharding and bad-input errors."""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from inversion._database import (
    CorruptChunkError,
    IncompleteDatabaseError,
    bank_in_memory,
    build_database,
    chunk_status,
    enumerate_rows,
    load_database,
    spec_from_dict,
)
from ppr._config import ConfigError

ROOT = Path(__file__).resolve().parents[1]

SPEC = {
    "name": "tiny",
    "model": "synthetic",
    "shapes": [
        {"name": "cube", "symmetry": "octahedral"},
        {"name": "box3u", "symmetry": "dihedral:4"},
    ],
    "materials": ["aluminium", "white_paint"],
    "finishes": {"polished": 3000.0, "matte": 5.0},
    "grid": {"kind": "hopf", "size": 1},
    "sensor": {"channels": "stokes", "n_bins": 32, "bin_width_m": 0.02},
    "chunk_rows": 16,
}


def tree_bytes(path: Path) -> dict:
    return {
        str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()
    }


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """One uninterrupted build shared by the tests of this file."""
    path = tmp_path_factory.mktemp("ref") / "db"
    report = build_database(spec_from_dict(SPEC), path, progress=False)
    return path, report


def test_layout_and_rows(reference):
    path, report = reference
    spec = spec_from_dict(SPEC)
    rows = enumerate_rows(spec)
    assert report.n_rows == len(rows["quat"]) and report.computed == list(range(report.n_chunks))
    bank = load_database(path)
    assert bank.signatures.shape == (len(rows["quat"]), 8, 32)
    # energy normalization: every row sums to 1 (float32 storage: 1e-5)
    np.testing.assert_allclose(bank.signatures.sum((1, 2)), 1.0, rtol=1e-5)
    for k in ("shape_id", "attitude_id", "material_id", "finish_id"):
        np.testing.assert_array_equal(getattr(bank, k), rows[k])
    np.testing.assert_array_equal(bank.quat, rows["quat"])
    assert bank.names["materials"] == ["aluminium", "white_paint"]
    # the same rows built in memory give the same signatures (same kernel, same chunking of
    # work is not required: rows are independent; 1e-6 relative covers float32 batch effects)
    mem = bank_in_memory(spec, batch=spec.chunk_rows)
    np.testing.assert_allclose(mem.signatures, bank.signatures, rtol=1e-6, atol=1e-9)
    # a second build call is a no-op
    again = build_database(spec, path, progress=False)
    assert again.computed == [] and len(again.skipped) == report.n_chunks


SCRIPT = textwrap.dedent(
    """
    import sys, time
    from inversion._database import build_database, make_signature_fn, spec_from_dict
    spec = spec_from_dict({spec!r})
    fn = make_signature_fn(spec)

    class Slow:
        sensor, n_channels = fn.sensor, fn.n_channels
        def __call__(self, params):
            out = fn(params)
            out.block_until_ready()
            time.sleep(0.4)
            return out

    build_database(spec, sys.argv[1], Slow(), progress=False)
    """
)


def test_resume_after_kill_is_byte_identical(reference, tmp_path):
    ref_path, ref_report = reference
    path = tmp_path / "db"
    script = tmp_path / "slow_build.py"
    script.write_text(SCRIPT.format(spec=SPEC))
    env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
    proc = subprocess.Popen([sys.executable, str(script), str(path)], env=env, cwd=str(ROOT))
    try:
        deadline = time.time() + 120
        while time.time() < deadline:
            markers = path / "_chunks"
            done = list(markers.glob("[0-9]*.json")) if markers.exists() else []
            if len(done) >= 2 or proc.poll() is not None:
                break
            time.sleep(0.05)
        assert proc.poll() is None, "the build finished before it could be interrupted"
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    status = chunk_status(path)
    n_done = len(status["done"])
    assert 2 <= n_done < ref_report.n_chunks
    with pytest.raises(IncompleteDatabaseError, match="not built"):
        load_database(path)
    report = build_database(spec_from_dict(SPEC), path, progress=False)
    assert report.skipped == status["done"]  # only missing chunks recomputed
    assert sorted(report.computed) == status["missing"]
    assert tree_bytes(path) == tree_bytes(ref_path)


def test_corrupt_chunk_detected_and_recomputed(reference, tmp_path):
    ref_path, _ = reference
    path = tmp_path / "db"
    build_database(spec_from_dict(SPEC), path, progress=False)
    chunk = path / "signatures" / "c" / "1" / "0" / "0"
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF  # flip one byte in the middle of the compressed chunk
    chunk.write_bytes(bytes(data))
    with pytest.raises(CorruptChunkError, match=r"chunks \[1\]"):
        load_database(path)
    assert chunk_status(path)["corrupt"] == [1]
    report = build_database(spec_from_dict(SPEC), path, progress=False)
    assert report.recomputed_corrupt == [1] and report.computed == [1]
    assert tree_bytes(path) == tree_bytes(ref_path)
    # a truncated (half-written) chunk behind a marker is corrupt too
    chunk.write_bytes(chunk.read_bytes()[:10])
    with pytest.raises(CorruptChunkError):
        load_database(path)
    # damaged metadata is named (file and parse error) with what to do, on load and rebuild
    meta = path / "zarr.json"
    meta.write_text(meta.read_text()[:1] + "garbage")
    for call in (
        lambda: load_database(path),
        lambda: build_database(spec_from_dict(SPEC), path, progress=False),
    ):
        with pytest.raises(ValueError) as err:
            call()
        msg = str(err.value)
        assert f"its metadata {meta} cannot be read (JSONDecodeError" in msg, msg
        assert f"remove {path} and build it again" in msg


def test_two_devices_subprocess(reference, tmp_path):
    ref_path, _ = reference
    path = tmp_path / "db2"
    code = textwrap.dedent(
        f"""
        import jax, json, sys
        from inversion._database import build_database, spec_from_dict, evaluate_rows, device_mesh
        from inversion._database import make_signature_fn, enumerate_rows
        spec = spec_from_dict({SPEC!r})
        assert len(jax.devices()) == 2, jax.devices()
        rep = build_database(spec, sys.argv[1], progress=False)
        fn = make_signature_fn(spec)
        rows = {{k: v[:16] for k, v in enumerate_rows(spec).items()}}
        import numpy as np
        mesh = device_mesh()
        from jax.sharding import NamedSharding, PartitionSpec
        shard = NamedSharding(mesh, PartitionSpec("rows"))
        q = jax.device_put(rows["quat"].astype("float32"), shard)
        out = fn(dict(rows, quat=q))
        n_out = len(out.sharding.device_set)
        print(json.dumps({{"n_devices": rep.n_devices, "out_devices": n_out}}))
        """
    )
    env = dict(
        os.environ,
        PYTHONPATH=str(ROOT),
        JAX_PLATFORMS="cpu",
        XLA_FLAGS="--xla_force_host_platform_device_count=2",
    )
    res = subprocess.run(
        [sys.executable, "-c", code, str(path)],
        env=env,
        cwd=str(ROOT),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    import json

    info = json.loads(res.stdout.strip().splitlines()[-1])
    assert info == {"n_devices": 2, "out_devices": 2}
    two, one = load_database(path), load_database(ref_path)
    # rows are independent, so sharding over two devices changes nothing beyond float32
    # rounding: XLA may fuse, order and vectorize the per-device program differently, and the
    # lobe power cos^m amplifies a direction's rounding by m (m = 3000 here; the single term's
    # documented float32 precision is 5e-4 of the largest entry, docs/physics/numerics.md).
    # Measured with jax 0.10.2: 3.4e-6 of the row's peak with the MLIR emitters, 2.5e-4 with
    # the suite's legacy ones (tests/compile_level.py). A row computed wrongly or twice would
    # differ by O(1) of its peak.
    a, b = np.asarray(two.signatures), np.asarray(one.signatures)
    peak = np.abs(b).max(axis=(1, 2), keepdims=True)
    assert np.all(peak > 0)
    assert np.all(np.abs(a - b) <= 5e-4 * peak), float((np.abs(a - b) / peak).max())


def test_bad_inputs(reference, tmp_path):
    ref_path, _ = reference
    other = dict(SPEC, finishes={"polished": 1000.0, "matte": 5.0})
    with pytest.raises(ValueError, match="other settings"):
        build_database(spec_from_dict(other), ref_path, progress=False)
    with pytest.raises(ConfigError, match="materials"):
        spec_from_dict(dict(SPEC, materials=[]))
    # an entry twice would build its rows twice (one template counted as two)
    with pytest.raises(ConfigError, match=r"entries \[0\] and \[1\] are the same 'aluminium'"):
        spec_from_dict(dict(SPEC, materials=["aluminium", "aluminium"]))
    with pytest.raises(ConfigError, match=r"entries \[0\] and \[2\] are the same shape 'cube'"):
        spec_from_dict(dict(SPEC, shapes=[*SPEC["shapes"], SPEC["shapes"][0]]))
    with pytest.raises(ConfigError, match="shapes"):
        spec_from_dict(dict(SPEC, shapes=[]))
    with pytest.raises(ConfigError, match="finishes"):
        spec_from_dict(dict(SPEC, finishes={}))
    with pytest.raises(ConfigError, match="size"):
        spec_from_dict(dict(SPEC, grid={"kind": "hopf", "size": 0}))
    with pytest.raises(ValueError, match="not a signature database"):
        load_database(tmp_path)
    with pytest.raises(ConfigError, match=r"shapes\[0\].name = 'torus': not a shape of model"):
        spec_from_dict(dict(SPEC, shapes=[{"name": "torus"}]))
    # a sensor that sees nothing (every template zero) is refused, not written as zeros
    from inversion._database import make_signature_fn

    class Dark:
        def __init__(self, fn):
            self.fn = fn

        def __getattr__(self, name):
            return getattr(self.fn, name)

        def __call__(self, params):
            return 0.0 * self.fn(params)

    spec = spec_from_dict(SPEC)
    with pytest.raises(ValueError, match=r"every signature of chunk 0 \(rows 0-15\) is zero"):
        build_database(spec, tmp_path / "dark", Dark(make_signature_fn(spec)), progress=False)
    assert chunk_status(tmp_path / "dark", verify=False)["done"] == []


def test_declared_symmetry_must_be_the_shapes():
    """The grid is reduced by a shape's declared class: one the mesh does not have (a 3U
    CubeSat declared cyclic:7) would merge attitudes with different signatures, so it is
    refused naming the rotation; the shipped spec's classes are the meshes' own (geometry
    only: a template has one material on every part)."""
    from inversion._database import grids_for, load_spec

    bad = dict(
        SPEC,
        model="ppr",
        materials=["aluminium"],
        shapes=[{"name": "cubesat", "params": {"units": 3}, "symmetry": "cyclic:7"}],
    )
    from inversion._database import make_signature_fn

    for call in (grids_for, make_signature_fn):  # before a store is made, and for the grid
        with pytest.raises(
            ValueError,
            match=r"shapes\[0\].symmetry = 'cyclic:7': shape 'cubesat' is "
            r"not symmetric under its 51.43 deg rotation about \[0.0, 0.0, 1.0\]",
        ):
            call(spec_from_dict(bad))
    assert len(grids_for(load_spec(ROOT / "configs" / "databases" / "ppr_cubesat.toml"))) == 2


@pytest.mark.parametrize("name", ["synthetic_small", "ppr_cubesat"])
def test_shipped_specs_parse(name):
    from inversion._database import load_spec

    spec = load_spec(ROOT / "configs" / "databases" / f"{name}.toml")
    rows = enumerate_rows(spec)
    assert len(rows["quat"]) > 0 and spec.sensor.n_bins >= 64


def test_opens_as_labelled_data_with_xarray(reference):
    """The store is labelled data: xarray opens it with named dimensions, units and the
    label names, and its values are the bank's (rows normalized to 1)."""
    import xarray as xr

    path, _ = reference
    bank = load_database(path)
    ds = xr.open_zarr(path, consolidated=False)
    assert ds["signatures"].dims == ("row", "channel", "bin")
    assert ds["quat"].dims == ("row", "quaternion_component")
    for key in ("energy", "shape_id", "attitude_id", "material_id", "finish_id"):
        assert ds[key].dims == ("row",), key
    assert ds.sizes["row"] == len(bank) and ds.sizes["bin"] == SPEC["sensor"]["n_bins"]
    assert ds["signatures"].attrs["units"] == "1" and ds["quat"].attrs["units"] == "1"
    assert ds["signatures"].attrs["bin_width_m"] == SPEC["sensor"]["bin_width_m"]
    np.testing.assert_array_equal(ds["signatures"].values, bank.signatures)
    np.testing.assert_allclose(ds["signatures"].sum(("channel", "bin")), 1.0, rtol=1e-5)
    # the label indices decode to the names through CF flag attributes
    for key, names in (("shape_id", "shapes"), ("material_id", "materials")):
        attrs = ds[key].attrs
        assert attrs["flag_meanings"].split() == bank.names[names]
        assert attrs["flag_values"] == list(range(len(bank.names[names])))
    assert ds.attrs["spec"]["name"] == "tiny"  # the group's attributes come along
