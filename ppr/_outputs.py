"""Atomic output folders: a command's results appear whole or not at all.

Every file (or directory, e.g. a zarr store) a ``ppr`` command writes into its ``--out``
folder is first written into a private *stage* folder on the same file system, validated,
and only then moved into place:

- ``--out`` does not exist yet: the stage is a hidden sibling ``.<name>.ppr-stage-...``
  and the commit is one ``rename`` of the whole staged folder to ``--out``.
- ``--out`` exists: the stage is ``--out/.ppr-stage-...`` and the commit is a *journaled*
  sequence of renames. The journal (``journal.json`` in the stage, written atomically
  before the first rename) lists every move ``src -> dst`` with a backup path for what
  ``dst`` held. Each old output is renamed to its backup, then the new one renamed into
  place; deleting the journal is the commit point, after which the backups are removed.

A failed run (an exception, Ctrl-C, SIGTERM) discards its stage, rolling back a commit it
had started, so the previous result is left exactly as it was. A run killed outright
(SIGKILL, power loss) leaves its stage behind: the next command writing to the same
``--out`` (or :func:`recover`) finds stages whose owner process is dead and rolls back
any journaled commit by undoing the moves in reverse order (each undo is a rename guarded
by existence checks, so rolling back is itself safe to interrupt and repeat). Until then,
a ``.ppr-stage-*`` folder holding a ``journal.json`` marks ``--out`` as mid-commit. Stages
are named ``<host>-<pid>-<token>``; stages of other hosts are left alone.

Outputs named but not produced by a run (an optional plot) are moved to the backup too,
so a result never mixes files of two runs. ``--overwrite`` only allows replacing; nothing
is deleted before the new result is complete and validated.

This module uses the standard library only (no JAX), so it is cheap to import.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import glob
import json
import os
import platform
import secrets
import shutil
import socket
import sys
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path

STAGE_MARK = ".ppr-stage-"
JOURNAL = "journal.json"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class OutputError(ValueError):
    """A user-facing problem with an output location (exists, is a file, ...)."""


# ------------------------------------------------------------------------------ helpers
def owner_tag() -> str:
    """``<host>-<pid>``: who owns a stage folder (host names may contain '-')."""
    return f"{socket.gethostname()}-{os.getpid()}"


def _parse_owner(stage: Path) -> tuple[str, int] | None:
    tail = stage.name.split(STAGE_MARK, 1)[-1]  # <host>-<pid>-<token>
    host_pid, _, _token = tail.rpartition("-")
    host, _, pid = host_pid.rpartition("-")
    try:
        return host, int(pid)
    except ValueError:
        return None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _owner_dead(stage: Path) -> bool:
    owner = _parse_owner(stage)
    if owner is None:
        return False
    host, pid = owner
    return host == socket.gethostname() and pid != os.getpid() and not _pid_alive(pid)


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` via a temporary sibling, fsync and rename."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{owner_tag()}-{secrets.token_hex(4)}")
    try:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif os.path.lexists(path):
        path.unlink()


def check_out_folder(out: str | os.PathLike, flag: str = "--out") -> Path:
    """``out`` as a Path; an error naming ``flag`` if it is empty (an unset shell variable
    would write into the working folder), or it or a parent is not a folder."""
    if not os.fspath(out).strip():
        raise OutputError(f"{flag} {os.fspath(out)!r}: empty path; choose a folder")
    out = Path(out)
    for p in (out, *out.parents):
        if os.path.lexists(p) and not p.is_dir():
            what = "" if p == out else f" (its parent {p} is a file)"
            raise OutputError(
                f"{flag} {out}: is an existing file{what}, not a folder; choose a folder"
            )
    return out


def refuse_existing(out: str | os.PathLike, names: Sequence[str], overwrite: bool) -> None:
    """An :class:`OutputError` if ``out`` is not a folder, or holds one of ``names`` and
    ``overwrite`` is false (commands call it before any long computation)."""
    out = check_out_folder(out)
    existing = [n for n in names if os.path.lexists(out / n)]
    if existing and not overwrite:
        more = f" (and {len(existing) - 1} more outputs)" if len(existing) > 1 else ""
        raise OutputError(
            f"{out / existing[0]} already exists{more}; pass --overwrite to replace, or "
            "choose another --out"
        )


# ----------------------------------------------------------------------- journaled swap
def swap_in(moves: Sequence[tuple[Path | None, Path]], stage: Path) -> None:
    """Move each ``src`` to ``dst`` as one transaction journaled in ``stage``.

    ``src = None`` removes ``dst``. Every ``src`` must exist. Old ``dst`` entries go to
    ``stage/old/``; the journal is deleted once every move is done (the commit point) and
    the backups after that. On an exception the moves done so far are undone."""
    missing = [str(s) for s, _ in moves if s is not None and not os.path.lexists(s)]
    if missing:
        raise FileNotFoundError(f"nothing to commit: {missing[0]} does not exist")
    old = stage / "old"
    old.mkdir(exist_ok=True)
    plan = [
        [None if s is None else str(s), str(d), str(old / f"{i:03d}-{Path(d).name}")]
        for i, (s, d) in enumerate(moves)
    ]
    atomic_write_text(stage / JOURNAL, json.dumps({"owner": owner_tag(), "moves": plan}))
    try:
        for src, dst, bak in plan:
            if os.path.lexists(dst):
                os.replace(dst, bak)
            if src is not None:
                os.replace(src, dst)
        for d in {Path(dst).parent for _, dst, _ in plan}:
            _fsync_dir(d)
    except BaseException:
        roll_back(stage)
        raise
    (stage / JOURNAL).unlink()  # commit point
    _fsync_dir(stage)
    shutil.rmtree(old, ignore_errors=True)


def roll_back(stage: Path) -> bool:
    """Undo the journaled moves of ``stage`` (if it has a journal); returns whether it had
    one. Idempotent: safe to interrupt and call again."""
    journal = stage / JOURNAL
    if not journal.exists():
        return False
    plan = json.loads(journal.read_text())["moves"]
    for src, dst, bak in reversed(plan):
        if src is not None and not os.path.lexists(src) and os.path.lexists(dst):
            os.replace(dst, src)  # the new entry had been moved in: move it back
        if os.path.lexists(bak):
            if os.path.lexists(dst):  # pragma: no cover - someone wrote dst meanwhile
                raise OutputError(
                    f"cannot restore {dst} from {bak}: {dst} was written by another process; "
                    "resolve by hand"
                )
            os.replace(bak, dst)
    journal.unlink()
    _fsync_dir(stage)
    return True


def stage_folders(out: Path) -> list[Path]:
    """Stage folders that belong to ``out`` (inside it, or hidden siblings of it)."""
    out = Path(out)
    found = []
    if out.is_dir():
        found += [Path(p) for p in glob.glob(str(out / f"{STAGE_MARK}*"))]
    if out.name:
        pattern = glob.escape(str(out.parent / f".{out.name}")) + f"{STAGE_MARK}*"
        found += [Path(p) for p in glob.glob(pattern)]
    return [p for p in found if p.is_dir()]


def recover(out: str | os.PathLike) -> list[Path]:
    """Roll back interrupted commits into ``out`` by dead processes of this host and remove
    their stage folders; returns the stages handled."""
    handled = []
    for stage in stage_folders(Path(out)):
        if _owner_dead(stage):
            roll_back(stage)
            shutil.rmtree(stage, ignore_errors=True)
            handled.append(stage)
    return handled


# ------------------------------------------------------------------------ provenance
def provenance(config=None, command_line: Sequence[str] | None = None) -> dict:
    """What made an output, for its JSON sidecar: the ppr, JAX, jaxlib, NumPy and Python
    versions (from the installed distributions' metadata), the command line, the time (UTC,
    ISO 8601) and the resolved ``config`` (JSON values)."""
    from importlib import metadata

    def version(dist: str) -> str | None:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return None

    return {
        "ppr": version("ppr"),
        "jax": version("jax"),
        "jaxlib": version("jaxlib"),
        "numpy": version("numpy"),
        "python": platform.python_version(),
        "command_line": list(sys.argv if command_line is None else command_line),
        "time_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "config": config,
    }


# ------------------------------------------------------------------------ validation
def _validate_file(path: Path) -> None:
    """Cheap structural checks of a finished output (catches truncated writes)."""
    if path.is_dir():
        return
    if path.stat().st_size == 0:
        raise RuntimeError(f"output {path.name} is empty")
    suffix = path.suffix.lower()
    if suffix == ".json":
        json.loads(path.read_text())
    elif suffix == ".npz":
        import zipfile

        with zipfile.ZipFile(path) as z:
            if not z.namelist():
                raise RuntimeError(f"output {path.name} holds no arrays")
    elif suffix == ".png":
        with open(path, "rb") as f:
            if f.read(8) != PNG_SIGNATURE:
                raise RuntimeError(f"output {path.name} is not a PNG file")


# ------------------------------------------------------------------------ output folder
class Outputs:
    """The outputs one command writes into ``out`` (see the module docstring).

    - `names`: the outputs (file or folder names in ``out``); ``None``: whatever the command
      writes into :attr:`folder` (always replacing, as ``ppr demo`` does).
    - `overwrite`: allow replacing existing outputs (refused otherwise, before any work).
    - `optional`: names the command may not produce.
    - `validators`: ``name -> callable(path)`` run on the staged output before the commit.
    """

    def __init__(
        self,
        out: str | os.PathLike,
        names: Sequence[str] | None,
        overwrite: bool,
        *,
        optional: Iterable[str] = (),
        validators: Mapping[str, Callable[[Path], None]] | None = None,
    ):
        self.out = check_out_folder(out)
        self.names = None if names is None else list(names)
        self.optional = set(optional)
        self.validators = dict(validators or {})
        recover(self.out)
        if self.names is not None:
            refuse_existing(self.out, self.names, overwrite)
        self._created: list[Path] = []
        token = f"{owner_tag()}-{secrets.token_hex(4)}"
        try:
            if self.out.is_dir():
                self.stage = self.out / f"{STAGE_MARK}{token}"
            else:
                self._make_parents(self.out.parent)
                self.stage = self.out.parent / f".{self.out.name}{STAGE_MARK}{token}"
            (self.stage / "new").mkdir(parents=True)
        except OSError as err:  # a read-only or special file system: a user error, one line
            for p in reversed(self._created):  # the parents this call made, if any
                with contextlib.suppress(OSError):
                    p.rmdir()
            where = self.out if self.out.is_dir() else self.out.parent
            raise ValueError(
                f"--out {os.fspath(out)}: cannot write in {where} "
                f"({err.strerror or err}); choose a folder you can write to"
            ) from None
        self._adopted: dict[str, Path] = {}
        self.written: list[Path] = []

    def _make_parents(self, folder: Path) -> None:
        missing = [p for p in (folder, *folder.parents) if not p.exists()]
        for p in reversed(missing):
            p.mkdir()
            self._created.append(p)

    @property
    def folder(self) -> Path:
        """Where the command writes its outputs (the stage)."""
        return self.stage / "new"

    def path(self, name: str) -> Path:
        if self.names is not None and name not in self.names:  # pragma: no cover - a bug
            raise KeyError(f"output {name!r} not declared")
        return self.folder / name

    def adopt(self, name: str, path: str | os.PathLike) -> None:
        """Make the existing ``path`` (outside the stage, on the same file system) the output
        ``name``: the commit moves it into place, a roll-back moves it back to ``path``
        (``ppr database build`` adopts its finished ``database.zarr.partial``)."""
        self.path(name)  # declared?
        self._adopted[name] = Path(path)

    def _source(self, name: str) -> Path:
        return self._adopted.get(name, self.folder / name)

    def _produced(self) -> list[str]:
        present = sorted(set(os.listdir(self.folder)) | set(self._adopted))
        if self.names is None:
            return present
        missing = [n for n in self.names if n not in present and n not in self.optional]
        if missing:
            raise RuntimeError(f"the command did not write its output {missing[0]!r}")
        undeclared = [n for n in present if n not in self.names]
        if undeclared:  # would be lost with the stage: a bug in the command's output list
            raise RuntimeError(f"the command wrote {undeclared[0]!r}, not among its outputs")
        return [n for n in self.names if n in present]

    def commit(self) -> list[Path]:
        """Validate the staged outputs and move them into place (see the module docstring)."""
        produced = self._produced()
        for name in produced:
            check = self.validators.get(name, _validate_file)
            check(self._source(name))
        if not self.out.exists() and not self._adopted:
            try:
                os.rename(self.folder, self.out)
                _fsync_dir(self.out.parent)
                moved = True
            except OSError as err:  # created meanwhile by someone else: journaled swap
                if err.errno not in (errno.EEXIST, errno.ENOTEMPTY):
                    raise
                moved = False
            if moved:
                shutil.rmtree(self.stage, ignore_errors=True)
                self.written = [self.out / n for n in produced]
                return self.written
        self.out.mkdir(exist_ok=True)
        moves: list[tuple[Path | None, Path]] = [(self._source(n), self.out / n) for n in produced]
        stale = [] if self.names is None else [n for n in self.names if n not in produced]
        moves += [(None, self.out / n) for n in stale if os.path.lexists(self.out / n)]
        swap_in(moves, self.stage)
        shutil.rmtree(self.stage, ignore_errors=True)
        self.written = [self.out / n for n in produced]
        return self.written

    def discard(self) -> None:
        """Drop the stage (rolling back a commit in progress) and folders made for it."""
        if self.stage.exists():
            roll_back(self.stage)
            shutil.rmtree(self.stage, ignore_errors=True)
        for p in reversed(self._created):
            with contextlib.suppress(OSError):
                p.rmdir()  # only if empty


@contextlib.contextmanager
def outputs(
    out: str | os.PathLike, names: Sequence[str] | None, overwrite: bool, **kwargs
) -> Iterator[Outputs]:
    """Context manager around :class:`Outputs`: commit on success, discard on any exception
    (including ``KeyboardInterrupt``)."""
    o = Outputs(out, names, overwrite, **kwargs)
    try:
        yield o
        o.commit()
    except BaseException:
        o.discard()
        raise
