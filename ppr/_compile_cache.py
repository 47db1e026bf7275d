"""The persistent XLA compilation cache, switched on by one call (standard library until it is
on; then JAX's config). Importing ppr never changes JAX's config: a program (the ``ppr``
command) or a user's script or notebook opts in with :func:`compile_cache`."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["compile_cache"]


def _default_folder() -> Path:
    """``$PPR_JAX_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/ppr/jax`` (``~/.cache/ppr/jax``)."""
    env = os.environ.get("PPR_JAX_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "ppr" / "jax"


def _check_folder(folder: Path, what: str) -> None:
    if folder.exists() and not folder.is_dir():
        raise ValueError(
            f"{what}{str(folder)!r} exists and is not a folder (the compilation cache is a "
            "folder of compiled programs; give a new or existing folder)"
        )


def compile_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Keep every program JAX compiles in a folder on disk, so that a new process (the next run
    of a script, a restarted notebook kernel) reads it back instead of compiling it again
    (tracing and lowering still run; XLA's compilation, most of a first ``inversion.refine``,
    does not).

    Call it once at the start of a script or notebook, before the first computation (programs
    compiled earlier in the process are not written); the ``ppr`` command line calls it for
    every command. Returns the folder in use, or ``None``
    when the cache is switched off.

    - ``PPR_JAX_CACHE=0`` switches it off (and nothing is changed; ``1`` or unset: on), so a
      script's cache can be turned off without editing it (the test suite does).
    - The folder: ``path`` if given, else ``$PPR_JAX_CACHE_DIR``, else
      ``~/.cache/ppr/jax`` (``$XDG_CACHE_HOME/ppr/jax``); created by JAX on the first write.
    - A folder already set in JAX's config (``jax.config.update("jax_compilation_cache_dir",
      ...)``, ``JAX_COMPILATION_CACHE_DIR``) is kept and returned: JAX reads its folder once
      per process. A different ``path`` is then an error.
    - Every program is written, also those compiling in under a second (JAX's default keeps
      only those above 1 s; a refine or a command compiles dozens of small programs), unless
      ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS`` is set.

    JAX never writes programs holding host callbacks; the library's checked entry points
    check concrete inputs on the host and compile programs without them. A cache folder is
    trusted code: do not share it with users you do not trust (JAX's warning). Removing the
    folder is always safe (everything is compiled again).
    """
    if path is not None:
        if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
            raise ValueError(f"compile_cache: path must be a folder path, got {path!r}")
        _check_folder(Path(path).expanduser(), "compile_cache: path=")
    switch = os.environ.get("PPR_JAX_CACHE", "").strip()
    if switch not in ("", "0", "1"):
        raise ValueError(f"PPR_JAX_CACHE={switch!r}: use 0 (cache off) or 1 (on)")
    if switch == "0":
        return None
    import jax

    current = jax.config.jax_compilation_cache_dir
    if current:
        if path is not None and Path(path).expanduser().resolve() != Path(current).resolve():
            raise ValueError(
                f"compile_cache: path {os.fspath(path)!r}: JAX's compilation cache folder is "
                f"already {current!r} in this process (jax_compilation_cache_dir); JAX reads "
                "it once, so call compile_cache before any other setting of it"
            )
        return Path(current)
    if path is not None:
        folder = Path(path).expanduser().absolute()
    else:
        folder = _default_folder().absolute()
        env = bool(os.environ.get("PPR_JAX_CACHE_DIR"))
        _check_folder(folder, "PPR_JAX_CACHE_DIR=" if env else "compile_cache: default folder ")
    jax.config.update("jax_compilation_cache_dir", str(folder))
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return folder
