"""Atomic output folders (ppr/_outputs.py): a failed, interrupted or killed run leaves the
previous result byte-identical; a commit killed between two renames is rolled back by the
next run; no stage or empty folder is left behind."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from ppr import _outputs

ROOT = Path(__file__).resolve().parents[1]
NAMES = ["a.json", "b.npz", "c.txt", "d.png"]  # d.png: optional, not produced by the new run


def folder_bytes(path: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()
    }


def old_result(out: Path) -> dict[str, bytes]:
    out.mkdir(parents=True)
    (out / "a.json").write_text('{"run": "old"}\n')
    (out / "b.npz").write_bytes(b"PK\x05\x06" + b"\0" * 18)  # an empty zip archive
    (out / "c.txt").write_text("old\n")
    (out / "d.png").write_bytes(_outputs.PNG_SIGNATURE + b"old")
    (out / "unrelated.dat").write_text("not an output of this command\n")
    return folder_bytes(out)


def write_new(o: _outputs.Outputs) -> None:
    import zipfile

    o.path("a.json").write_text('{"run": "new"}\n')
    with zipfile.ZipFile(o.path("b.npz"), "w") as z:
        z.writestr("x.npy", b"new")
    o.path("c.txt").write_text("new\n")


def test_failed_run_keeps_old_result_and_leaves_nothing(tmp_path):
    out = tmp_path / "out"
    before = old_result(out)
    for exc in (RuntimeError("bug"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with _outputs.outputs(out, NAMES, True, optional=["d.png"]) as o:
                write_new(o)
                raise exc
        assert folder_bytes(out) == before
        assert not _outputs.stage_folders(out)
    # a required output the command did not write: refused at validation, nothing replaced
    with pytest.raises(RuntimeError, match="did not write its output 'b.npz'"):
        with _outputs.outputs(out, NAMES, True, optional=["d.png"]) as o:
            o.path("a.json").write_text("{}")
    assert folder_bytes(out) == before
    # a truncated JSON fails validation
    with pytest.raises(ValueError):
        with _outputs.outputs(out, ["a.json"], True) as o:
            o.path("a.json").write_text('{"run": ')
    assert folder_bytes(out) == before
    # without --overwrite nothing is touched; with it the new set replaces the old one whole
    with pytest.raises(_outputs.OutputError, match="already exists .*--overwrite"):
        _outputs.Outputs(out, NAMES, False)
    with _outputs.outputs(out, NAMES, True, optional=["d.png"]) as o:
        write_new(o)
    after = folder_bytes(out)
    assert after["a.json"] == b'{"run": "new"}\n' and "d.png" not in after  # stale optional
    assert after["unrelated.dat"] == before["unrelated.dat"]
    assert not _outputs.stage_folders(out)


def test_failed_fresh_run_leaves_no_folder(tmp_path):
    out = tmp_path / "new" / "deeper" / "out"
    with pytest.raises(RuntimeError):
        with _outputs.outputs(out, ["a.json"], False) as o:
            o.path("a.json").write_text("{}")
            raise RuntimeError("bug")
    assert list(tmp_path.iterdir()) == []
    with _outputs.outputs(out, ["a.json"], False) as o:  # a fresh folder appears whole
        o.path("a.json").write_text("{}")
    assert sorted(os.listdir(out)) == ["a.json"]
    assert sorted(os.listdir(out.parent)) == ["out"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(_outputs.OutputError, match="is an existing file"):
        _outputs.Outputs(tmp_path / "file", ["a.json"], True)


# A commit killed (SIGKILL) just before its k-th rename: the journal's own rename is call 0,
# then each old output is moved to the backup and the new one moved in (7 more renames for
# 3 replaced outputs and 1 stale optional one).
KILL_SCRIPT = textwrap.dedent(
    """
    import importlib.util, os, signal, sys, zipfile
    spec = importlib.util.spec_from_file_location("_outputs", sys.argv[1])
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out, kill_at = sys.argv[2], int(sys.argv[3])
    calls = [0]
    real_replace = os.replace

    def replace(src, dst):
        if calls[0] == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)
        calls[0] += 1
        real_replace(src, dst)

    mod.os.replace = replace  # the module's os; os.replace is what the commit renames with
    with mod.outputs(out, {names!r}, True, optional=["d.png"]) as o:
        o.path("a.json").write_text('{{"run": "new"}}')
        with zipfile.ZipFile(o.path("b.npz"), "w") as z:
            z.writestr("x.npy", b"new")
        o.path("c.txt").write_text("new")
    print(calls[0])
    """
)


def test_commit_killed_between_renames_is_rolled_back(tmp_path):
    script = tmp_path / "kill.py"
    script.write_text(KILL_SCRIPT.format(names=NAMES))
    module = ROOT / "ppr" / "_outputs.py"
    n_renames = None
    for kill_at in range(9):  # 8 renames: killed before each, then not at all
        out = tmp_path / f"out{kill_at}"
        before = old_result(out)
        proc = subprocess.run(
            [sys.executable, str(script), str(module), str(out), str(kill_at)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        if proc.returncode == 0:  # ran to the end: the new result, nothing left over
            n_renames = int(proc.stdout)
            assert folder_bytes(out)["c.txt"] == b"new" and "d.png" not in os.listdir(out)
            assert not _outputs.stage_folders(out)
            break
        assert proc.returncode == -9, proc.stderr
        stages = _outputs.stage_folders(out)
        assert len(stages) == 1
        journaled = (stages[0] / _outputs.JOURNAL).exists()
        assert journaled == (kill_at > 0)  # mid-commit: old and new may be mixed until ...
        assert _outputs.recover(out) == stages  # ... the next run rolls the commit back
        assert folder_bytes(out) == before
        assert not _outputs.stage_folders(out)
    assert n_renames == 8, "the kill points did not cover every rename of the commit"
