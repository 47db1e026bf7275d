"""``ppr database build``: a signature database, chunk by chunk, resumable."""

from __future__ import annotations

import contextlib
import json
import shutil
from pathlib import Path

from .. import _outputs
from . import _common as c
from ._help import describe, fields_text, paragraph

NAME = "database build"
DEFAULT_CONFIG = "databases/synthetic_small.toml"
STORE = "database.zarr"
SUMMARY = "database.json"
PARTIAL = ".partial"
SET_EXAMPLE = "grid.size=1"
EXAMPLES = [
    "ppr database build --out out/database",
    "ppr database build --set grid.size=1 --set 'materials=[\"aluminium\"]' --out out/db_small",
    "ppr database build --shard-index 0 --num-shards 2 --out /shared/database",
]


def help_text() -> str:
    import inversion

    return describe(
        "Build a signature database (shapes x attitudes x materials x finishes) chunk by chunk "
        "into --out/database.zarr (zarr v3; opens with xarray.open_zarr(path, "
        "consolidated=False)). The build runs in "
        "--out/database.zarr.partial and is moved to database.zarr only when every chunk is "
        "done and verified: rerunning the same command after an interruption computes only "
        "the missing chunks; with --overwrite the old database stays in place (and a config "
        "error deletes nothing) until the new one is complete. On an existing database.zarr "
        "of the same settings the command verifies every chunk's checksum and recomputes "
        "missing or corrupt chunks in place; a complete, valid one is not rebuilt unless "
        "--overwrite.",
        fields_text(f"Config fields (configs/{DEFAULT_CONFIG})", inversion.DatabaseSpec),
        paragraph(
            "Several hosts: run with --shard-index i --num-shards N against one shared --out "
            "(docs/distributed_builds.md); the builder that finds every chunk done when it "
            "finishes moves the database into place and writes database.json."
        ),
        outputs="database.zarr, database.json (rows, chunks, rows per second).",
        examples=EXAMPLES,
    )


def register(sub) -> None:
    p = sub.add_parser(
        "database", help="signature databases (database build)", formatter_class=c.Formatter
    )
    dsub = p.add_subparsers(dest="database_command", metavar="SUBCOMMAND")
    pb = dsub.add_parser(
        "build",
        help="build or resume a signature database",
        describe=help_text,
        formatter_class=c.Formatter,
    )
    c.add_common(pb, DEFAULT_CONFIG, "out/database", SET_EXAMPLE)
    pb.add_argument(
        "--shard-index",
        type=int,
        default=0,
        help="build only chunks i with i %% num_shards == shard_index (several "
        "processes or hosts sharing one --out)",
    )
    pb.add_argument("--num-shards", type=int, default=1, help="number of cooperating builders")
    pb.set_defaults(func=run, load=load)
    p.set_defaults(func=None, _sub=p)


def load(args):
    import inversion

    path = c.config_path(args, DEFAULT_CONFIG)
    return path, inversion.load_spec(path, c.overrides(args))


def _shards_ok(args) -> None:
    if args.num_shards < 1 or not 0 <= args.shard_index < args.num_shards:
        raise c.CLIError(
            f"--shard-index {args.shard_index} --num-shards {args.num_shards}: need "
            "num_shards >= 1 and 0 <= shard_index < num_shards"
        )


def database_target(spec, sig_fn, out: Path, overwrite: bool, say, shards: int = 1) -> Path | None:
    """Where ``ppr database build`` builds: the existing store itself to repair missing or
    corrupt chunks of the same settings, else ``database.zarr.partial`` (fresh builds and
    ``--overwrite``), committed over the old store only once complete. ``None``: a worker of
    a sharded build finds the database complete (nothing to do)."""
    import inversion

    final, partial = out / STORE, out / (STORE + PARTIAL)
    if final.exists() and not overwrite:
        diffs = inversion.store_differences(spec, final, sig_fn)
        keep = "the old one is kept until the new one is complete"
        if diffs is None:
            raise c.CLIError(
                f"{final} exists and is not a signature database; pass --overwrite to replace "
                f"it ({keep}), or choose another --out"
            )
        if diffs:
            raise c.CLIError(
                f"{final} was built with other settings ({'; '.join(diffs)}); pass --overwrite "
                f"to replace it ({keep}), or choose another --out"
            )
        status = inversion.chunk_status(final, verify=True)
        if not status["missing"] and not status["corrupt"] and shards > 1:
            say(f"ppr database build: {final} is complete; nothing to do for this shard")
            return None
        if not status["missing"] and not status["corrupt"]:
            raise c.CLIError(
                f"{final} already exists and is complete (every chunk matches its checksum); "
                "pass --overwrite to rebuild, or choose another --out"
            )
        say(
            f"ppr database build: {final}: recomputing {len(status['corrupt'])} corrupt and "
            f"{len(status['missing'])} missing chunks"
        )
        return final
    if partial.exists():
        diffs = inversion.store_differences(spec, partial, sig_fn)
        if diffs is None or diffs:
            what = (
                "is not a signature database"
                if diffs is None
                else ("was started with other settings (" + "; ".join(diffs) + ")")
            )
            if not overwrite:
                raise c.CLIError(
                    f"{partial}: an unfinished build that {what}; pass --overwrite to discard "
                    "it, or choose another --out"
                )
            shutil.rmtree(partial)  # an unfinished build, never a result
        else:
            say(f"ppr database build: resuming {partial} (only missing chunks are computed)")
    return partial


def rebuild_command(db: Path) -> str:
    """The ``ppr database build`` command that built ``db`` (from its database.json)."""
    import shlex

    folder = db.parent
    cmd = ["ppr", "database", "build"]
    try:
        info = json.loads((folder / SUMMARY).read_text())
        cmd += ["-c", info["config_file"]]
        for key, value in (info.get("overrides") or {}).items():
            cmd += ["--set", f"{key}={json.dumps(value)}"]
    except (OSError, ValueError, KeyError, TypeError):
        cmd += ["-c", "<its database config>"]
    cmd += ["-o", str(folder)]
    return " ".join(shlex.quote(a) if not a.startswith("<") else a for a in cmd)


def database_error_hint(db: Path, err: Exception) -> str:
    """A load error of ``db`` with the command that finishes or repairs it."""
    import inversion

    msg = c.one_line(err)
    if isinstance(err, inversion.CorruptChunkError | inversion.IncompleteDatabaseError):
        msg = msg.split("; rerun build_database")[0]
        return f"{msg}; rerun `{rebuild_command(db)}` to recompute them"
    partial = db.with_name(db.name + PARTIAL)
    if not db.exists() and partial.exists():
        return (
            f"{db} does not exist; an unfinished build is at {partial}: rerun "
            f"`{rebuild_command(db)}` to finish it"
        )
    return msg


def load_bank(value: str, cfg_path: Path, field: str):
    """``inversion.load_database`` of the config's ``field = value``, with errors naming them
    and, for unfinished or corrupt databases, the ``ppr database build`` command that
    completes them."""
    import inversion

    dbp = c.resolve_path(value, cfg_path)
    try:
        return inversion.load_database(dbp)
    except (ValueError, OSError) as err:
        hint = database_error_hint(dbp, err)
        raise c.ConfigError(f"{cfg_path}: {field} = {value!r}: {hint}") from None


def _summary(args, cfg_path, db, report, status) -> dict:
    return {
        "command": "database build",
        "config_file": str(Path(cfg_path).resolve()),
        "overrides": c.overrides(args),
        "path": str(db),
        "n_rows": report.n_rows,
        "n_chunks": report.n_chunks,
        "computed_chunks": len(report.computed),
        "skipped_chunks": len(report.skipped),
        "recomputed_corrupt": report.recomputed_corrupt,
        "missing_chunks": len(status["missing"]),
        "complete": not status["missing"],
        "seconds": report.seconds,
        "rows_per_second": report.rows_per_second,
        "n_devices": report.n_devices,
        "shard": [args.shard_index, args.num_shards],
    }


def _validate_store(path: Path) -> None:
    import inversion

    if not path.is_dir():
        raise FileNotFoundError(f"{path} does not exist")
    status = inversion.chunk_status(path, verify=False)
    if status["missing"]:  # pragma: no cover - the command checks before committing
        raise RuntimeError(f"{path}: {len(status['missing'])} chunks missing; not committed")


def run(args) -> int:
    import inversion

    from .._config import config_source

    cfg_path, spec = load(args)
    _shards_ok(args)
    try:
        sig_fn = inversion.make_signature_fn(spec)
    except ValueError as err:
        src = config_source(cfg_path, c.overrides(args))
        raise c.ConfigError(f"{src}: {c.one_line(err)}") from None
    out = _outputs.check_out_folder(args.out)
    _outputs.recover(out)
    target = database_target(
        spec, sig_fn, out, args.overwrite, lambda m: c.say(args, m), args.num_shards
    )
    if target is None:
        return 0
    made = [p for p in (out, *out.parents) if not p.exists()]
    args._interrupt_note = f"rerun the same command to resume {target}"
    try:
        report = inversion.build_database(
            spec,
            target,
            sig_fn,
            progress=c.progress(args),
            shard_index=args.shard_index,
            num_shards=args.num_shards,
        )
    except BaseException:
        _drop_empty_build(target, made)
        raise
    status = inversion.chunk_status(target, verify=False)  # the build verified every chunk
    final = out / STORE
    if status["missing"]:  # other shards still building
        c.say(
            args,
            f"ppr database build: shard {args.shard_index}/{args.num_shards} done "
            f"({len(report.computed)} chunks computed); {len(status['missing'])} chunks of other "
            f"shards missing in {target}: the builder that finishes last moves it to {final}",
        )
        return 0
    summary = _summary(args, cfg_path, final, report, status)
    names = [SUMMARY] if target == final else [STORE, SUMMARY]
    try:
        with c.outputs(out, names, overwrite=True, validators={STORE: _validate_store}) as o:
            if target != final:
                o.adopt(STORE, target)
            c.write_json(o.path(SUMMARY), summary, config=spec)
    except FileNotFoundError:
        if target.exists() or not final.exists():
            raise
        c.say(args, f"ppr database build: another builder moved {target} to {final} first")
        return 0
    c.say(
        args,
        f"ppr database build: {final} ({report.n_rows} rows, {len(report.computed)} chunks "
        f"computed, {len(report.skipped)} already done)",
    )
    return 0


def _drop_empty_build(target: Path, made: list[Path]) -> None:
    """After a failed build: remove a staged store without one finished chunk, and the
    folders made for it (a store with finished chunks is kept for resuming)."""
    if target.name.endswith(PARTIAL) and target.is_dir():
        chunks = target / "_chunks"
        if not (chunks.is_dir() and any(chunks.glob("[0-9]*.json"))):  # a chunk marker
            shutil.rmtree(target, ignore_errors=True)
    for p in made:  # innermost first
        with contextlib.suppress(OSError):
            p.rmdir()
