"""``ppr.compile_cache()``: a script that calls it compiles a program once across processes.

Fresh interpreters (``sys.executable -c``) share one temporary cache folder: the first compiles
a small float64 Fresnel program and writes it (every program is written, also one compiling in
milliseconds), the second reads it back (JAX's ``/jax/compilation_cache/cache_hits`` event) and
computes the same values; with ``PPR_JAX_CACHE=0`` a process neither reads nor writes the
folder. In this process the suite keeps the cache off (tests/conftest.py), so only argument
checks that fail before JAX's config is touched run here."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import ppr

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import ppr
from ppr.optics import fresnel_mueller_params

folder = ppr.compile_cache()
hits = []
jax.monitoring.register_event_listener(
    lambda event, **kw: hits.append(1) if event == "/jax/compilation_cache/cache_hits" else None)
cos_t = np.linspace(0.05, 1.0, int(sys.argv[1]))   # the shape: one program per length
a, b, c, d = jax.jit(fresnel_mueller_params)(1.2, 7.0, cos_t)   # aluminium-like n = 1.2 + 7i
print(json.dumps(dict(folder=None if folder is None else str(folder), hits=len(hits),
                      jax_dir=jax.config.jax_compilation_cache_dir,
                      values=[np.asarray(x).tolist() for x in (a, b, c, d)])))
"""


def _start(env: dict, points: int = 7) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", CHILD, str(points)], env=env, cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _result(proc: subprocess.Popen) -> dict:
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    return json.loads(out.strip().splitlines()[-1])


def _entries(folder: Path) -> list[str]:
    if not folder.exists():
        return []
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))


def test_second_process_reads_the_first_ones_programs_and_off_means_off(tmp_path):
    folder = tmp_path / "jax-cache"
    env = {k: v for k, v in os.environ.items()
           if k not in ("PPR_JAX_CACHE", "JAX_COMPILATION_CACHE_DIR",
                        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS")}
    env.update(PYTHONPATH=os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]),
               PPR_JAX_CACHE_DIR=str(folder), JAX_PLATFORMS="cpu")

    cold = _result(_start(env))
    assert cold["folder"] == str(folder) == cold["jax_dir"]
    assert cold["hits"] == 0
    written = _entries(folder)
    assert written, "the cold process wrote no program (minimum compile time must be 0)"

    # then two processes side by side: one with the cache, one with it switched off
    warm_proc = _start(env)
    # off: the folder holds the 7-point program, yet nothing is read, and the 5-point program
    # (a new one, which the cold process shows an enabled cache writes) is not written
    off = _result(_start(dict(env, PPR_JAX_CACHE="0"), points=5))
    warm = _result(warm_proc)
    assert warm["folder"] == str(folder)
    assert warm["hits"] >= 1
    assert _entries(folder) == written  # read, nothing new compiled
    # the executable read from disk computes what the compiled one did, bit for bit
    assert warm["values"] == cold["values"]
    # and it is the Fresnel reflectance: normal incidence R = |(n-1)/(n+1)|^2 = a, b = 0
    n = 1.2 + 7.0j
    assert cold["values"][0][-1] == pytest.approx(abs((n - 1) / (n + 1)) ** 2, rel=1e-12)
    assert cold["values"][1][-1] == pytest.approx(0.0, abs=1e-12)

    assert off["folder"] is None and off["jax_dir"] is None
    assert off["hits"] == 0
    assert _entries(folder) == written
    for v_off, v_cold in zip(off["values"], cold["values"], strict=True):  # shared end points
        assert [v_off[0], v_off[-1]] == pytest.approx([v_cold[0], v_cold[-1]], rel=1e-14)


def test_bad_folder_and_switch_are_errors_naming_the_value(tmp_path, monkeypatch):
    file = tmp_path / "not_a_folder"
    file.write_text("x")
    with pytest.raises(ValueError, match=r"path='.*not_a_folder' exists and is not a folder"):
        ppr.compile_cache(file)
    monkeypatch.setenv("PPR_JAX_CACHE", "off")
    with pytest.raises(ValueError, match=r"PPR_JAX_CACHE='off': use 0 .* or 1"):
        ppr.compile_cache()
