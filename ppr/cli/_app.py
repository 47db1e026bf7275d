"""The ``ppr`` parser and the run loop: one-line errors, exit statuses, the compilation
cache, Ctrl-C and SIGTERM rolling back the outputs being written."""

from __future__ import annotations

import contextlib
import sys
import warnings
from collections.abc import Sequence

import pydantic

from . import _common as c
from . import brdf, classify, database, demo, image, invert, report, simulate
from ._help import paragraph

COMMANDS = (demo, brdf, image, simulate, database, classify, invert, report)


def version_text() -> str:
    """``ppr X (jax Y, jaxlib Z, numpy W, Python V)`` from the installed distributions'
    metadata (nothing imported, so ``ppr --version`` is instant)."""
    from importlib import metadata

    def ver(dist: str) -> str:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return "not installed"

    deps = ", ".join(f"{d} {ver(d)}" for d in ("jax", "jaxlib", "numpy"))
    return f"ppr {ver('ppr')} ({deps}, Python {sys.version.split()[0]})"


def build_parser() -> c.Parser:
    parser = c.Parser(
        prog="ppr",
        description=paragraph(
            "Pulse Polarization Ranging: polarized microfacet BRDF, pulse synthesis and "
            "inversion. Every command reads a TOML config (the shipped defaults, or --config), "
            "accepts --set overrides and writes its results into --out. `ppr COMMAND --help` "
            "lists every config field with its default and unit."
        ),
        formatter_class=c.Formatter,
        epilog=paragraph(
            "Exit status: 0 success; 2 bad config/override/input or existing output; 130 "
            "interrupted (Ctrl-C), 143 terminated. A failed or interrupted run leaves the "
            "previous outputs in --out as they were."
        ),
    )
    parser.add_argument(
        "--debug", action="store_true", help="show tracebacks instead of one-line errors"
    )
    parser.add_argument(
        "--version", action="version", version=version_text(), help="ppr and JAX versions"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command in COMMANDS:
        command.register(sub)
    return parser


def enable_compile_cache() -> None:
    """The persistent XLA compilation cache for repeated ``ppr`` runs
    (:func:`ppr.compile_cache`: ``~/.cache/ppr/jax``, ``PPR_JAX_CACHE=0`` off,
    ``PPR_JAX_CACHE_DIR`` moves it, every program written). The CLI is a program, so it may set
    JAX config; the library never does on its own.

    JAX never persists executables with host callbacks, so the programs the commands run check
    their inputs on the host and carry none (:class:`inversion.SimulatorModel` renders with the
    unchecked BRDF)."""
    from .._compile_cache import compile_cache

    compile_cache()


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that outputs are rolled back as on Ctrl-C."""


@contextlib.contextmanager
def _sigterm_raises():
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _command_name(args) -> str:
    sub = getattr(args, "database_command", None)
    return f"{args.command} {sub}" if sub else str(args.command)


USER_ERRORS = (c.ConfigError, c.CLIError, ValueError, pydantic.ValidationError)


_WARNING_PREFIX = ["ppr"]  # the running command, for the warning lines below


def _config_warnings_as_lines(name: str) -> None:
    """A config's deprecation warnings as one line each (``ppr simulate: warning: <file>:
    config key 'fwhm_ps' is deprecated; ...``), not Python's two-line warning format."""
    from .._config import ConfigDeprecationWarning

    _WARNING_PREFIX[0] = f"ppr {name}"
    shown = warnings.showwarning
    if getattr(shown, "_ppr_lines", False):
        return

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, ConfigDeprecationWarning):
            out = sys.stderr if file is None else file
            print(f"{_WARNING_PREFIX[0]}: warning: {message}", file=out)
        else:
            shown(message, category, filename, lineno, file, line)

    show._ppr_lines = True
    warnings.showwarning = show


def run(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` and run the command (see :func:`ppr.cli.main`)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        (getattr(args, "_sub", None) or parser).print_help(sys.stderr)
        raise SystemExit(2)
    c.COMMAND_LINE = ["ppr", *(sys.argv[1:] if argv is None else [str(a) for a in argv])]
    name = _command_name(args)
    _config_warnings_as_lines(name)
    try:
        with _sigterm_raises():
            enable_compile_cache()
            return int(args.func(args) or 0)
    except KeyboardInterrupt as err:
        if args.debug:
            raise
        what = "terminated" if isinstance(err, Terminated) else "interrupted"
        note = getattr(args, "_interrupt_note", None) or "previous outputs were left as they were"
        print(f"ppr {name}: {what}; {note}", file=sys.stderr)
        raise SystemExit(143 if isinstance(err, Terminated) else 130) from None
    except USER_ERRORS as err:
        if args.debug:
            raise
        print(f"ppr {name}: error: {c.one_line(err)}", file=sys.stderr)
        raise SystemExit(2) from None
    except OSError as err:
        # a folder that cannot be written (--out on a read-only or special file system), a
        # full disk: one line naming the path, not a traceback
        if args.debug:
            raise
        what = err.strerror or c.one_line(err)
        where = f": {err.filename}" if err.filename else ""
        print(
            f"ppr {name}: error: {what}{where} (previous outputs were left as they were)",
            file=sys.stderr,
        )
        raise SystemExit(1) from None
