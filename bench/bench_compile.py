"""Compile-time bench of the ``ppr`` commands: every program each command traces, lowers and
compiles, cold, with a warm persistent cache, and in steady state.

    .venv/bin/python bench/bench_compile.py [--only invert,brdf] [--cold-cache empty|off]
                                            [--set invert:mcmc_steps=200 ...]

Per command (its shipped config; ``--set`` overrides keep the commands small where the
config allows, :data:`COMMANDS`), two fresh processes share one new persistent-cache folder:

- **cold**: the first process, the cache folder empty (every program is compiled; JAX writes
  those that took >= ``jax_persistent_cache_min_compile_time_secs`` to compile and hold no
  host callback). ``--cold-cache off`` runs it with the cache off instead (``PPR_JAX_CACHE=0``)
  and fills the folder in an extra, unrecorded process.
- **warm**: the second process (cache hits; tracing and lowering are never cached).
- **steady**: the same command again inside the warm process (a new ``--out``; ``invert``
  with another observation seed: a later observation of a session). Any program compiled
  here is compiled per call.

For each program (JAX's ``jax.monitoring`` duration events, ``bench/_compile_monitor.py``):
trace, lower and XLA-compile seconds (wall) and the process CPU seconds they took, the
StableHLO bytecode size, host callbacks (never cached), cache hits, and the stage it belongs
to (``invert``: the library calls of ``ppr invert``, :data:`STAGES`). Per process: wall and
CPU time of the command, import time, load average. The machine is shared: wall times are
inflated by the load; CPU seconds, program counts and sizes are not (or much less).

Writes ``bench/results/compile.json`` (all events; ``--only`` replaces that command's entry
and keeps the others) and ``bench/results/compile.md`` (tables of every command in the json);
``--results NAME`` writes ``NAME.json`` / ``NAME.md`` instead (e.g. a before/after pair). The
section "library scripts" (``bench/bench_script_cache.py``: a Python script's cold and warm
start) is kept.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"

# command -> argv after `ppr` (the shipped config is the default of each command); `{db}`
# is the database the `database` entry built (or a setup build)
COMMANDS: dict[str, list[str]] = {
    "brdf": ["brdf"],
    "simulate": ["simulate"],
    "image": ["image", "--set", "render.n_pixels=48"],
    "database": ["database", "build"],
    "classify": ["classify", "--set", "database={db}"],
    "invert": ["invert"],
    "report": ["report"],
}

# extra overrides of the steady-state call (a later observation of an inversion session)
STEADY: dict[str, list[str]] = {"invert": ["--set", "observation.seed=1"]}

# command -> (module, attribute, stage): library calls timed as stages (outermost call wins)
STAGES: dict[str, list[tuple[str, str, str]]] = {
    # the stages of inversion.invert (its Inversion.timings name them the same way)
    "invert": [
        ("ppr.cli", "_simulated_truth", "observe"),
        ("inversion._invert", "screening_bank", "classify"),
        ("inversion._invert", "classify", "classify"),
        ("inversion._invert", "_Refiner.start", "refine"),
        ("inversion._invert", "_Refiner.finish", "refine"),
        ("inversion._invert", "refine_bounded", "refine"),
        ("inversion._invert", "mode_check", "modes"),
        ("inversion._invert", "_index_fit", "index"),
        ("inversion._invert", "fit_goodness_of_fit", "check"),
        ("inversion._invert", "sample_posterior", "mcmc"),
        ("inversion", "cramer_rao", "cramer_rao"),
        ("inversion", "Inversion.write", "write"),
    ],
    "report": [
        ("inversion._report", "bank_in_memory", "bank"),
        ("inversion._report", "_expected", "observe"),
        ("inversion._report", "observe", "observe"),
        ("inversion._report", "prepare", "prepare"),
        ("inversion._report", "classify", "classify"),
        ("inversion._report", "_plots", "plots"),
    ],
    "classify": [
        ("inversion", "make_signature_fn", "bank"),
        ("inversion", "observe", "observe"),
        ("inversion", "prepare", "prepare"),
        ("inversion", "classify", "classify"),
    ],
    "database": [("inversion", "build_database", "build")],
    "simulate": [("ppr", "simulate", "simulate")],
    "image": [("ppr.cli.image", "run_image", "image")],
}

CHILD = r"""
import json, os, sys, time, importlib
t_imp = time.perf_counter(); c_imp = time.process_time()
sys.path.insert(0, sys.argv[3])
from _compile_monitor import Monitor
mon = Monitor()
import jax
mon.install()
import ppr.cli
import inversion
imp = (time.perf_counter() - t_imp, time.process_time() - c_imp)
spec = json.loads(open(sys.argv[1]).read())
targets = []
for mod, attr, stage in spec["stages"]:
    owner = importlib.import_module(mod)
    *path, name = attr.split(".")
    for p in path:
        owner = getattr(owner, p)
    targets.append((owner, name, stage))
mon.wrap_stages(targets)
runs = []
for i, argv in enumerate(spec["runs"]):
    mon.run = i
    load = open("/proc/loadavg").read().split()[:3]
    w0, c0 = time.perf_counter(), time.process_time()
    rc = ppr.cli.main(argv)
    runs.append(dict(argv=argv, rc=rc, wall=time.perf_counter() - w0,
                     cpu=time.process_time() - c0, load_before=load,
                     load_after=open("/proc/loadavg").read().split()[:3]))
import resource
out = dict(import_wall=imp[0], import_cpu=imp[1], runs=runs, events=mon.events,
           stage_calls=mon.stage_calls,
           max_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
open(sys.argv[2], "w").write(json.dumps(out))
"""


def _child(runs: list[list[str]], stages, env: dict, tmp: Path, tag: str) -> dict:
    spec = tmp / f"{tag}.json"
    res = tmp / f"{tag}.out.json"
    spec.write_text(json.dumps({"runs": runs, "stages": stages}))
    t = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(spec), str(res), str(HERE)],
        env=env,
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"{tag}: exit {proc.returncode}\n{proc.stderr[-4000:]}")
    out = json.loads(res.read_text())
    out["process_wall"] = time.perf_counter() - t
    return out


def _cache_stats(folder: Path) -> dict:
    files = [p for p in folder.rglob("*") if p.is_file()]
    return {"entries": len(files), "bytes": sum(p.stat().st_size for p in files)}


def run_command(name: str, extra: list[str], tmp: Path, cold_cache: str, db: str | None) -> dict:
    argv = [a.replace("{db}", db or "") for a in COMMANDS[name]] + extra
    cache = tmp / f"cache_{name}"
    cache.mkdir()
    env = dict(os.environ, PYTHONPATH=str(REPO), MPLBACKEND="Agg", PPR_JAX_CACHE_DIR=str(cache))
    env.pop("JAX_DISABLE_MOST_OPTIMIZATIONS", None)
    env.pop("PPR_JAX_CACHE", None)
    stages = STAGES.get(name, [])

    def out_args(i: int) -> list[str]:
        return ["--out", str(tmp / f"out_{name}_{i}"), "--quiet"]

    result: dict = {"argv": argv, "cold_cache": cold_cache}
    print(f"[{name}] cold ...", flush=True)
    cold_env = dict(env, PPR_JAX_CACHE="0") if cold_cache == "off" else env
    result["cold"] = _child([argv + out_args(0)], stages, cold_env, tmp, f"{name}_cold")
    if cold_cache == "off":
        _child([argv + out_args(9)], [], env, tmp, f"{name}_prime")
    result["cache_after_cold"] = _cache_stats(cache)
    print(f"[{name}] warm + steady ...", flush=True)
    steady = argv + STEADY.get(name, []) + out_args(2)
    result["warm"] = _child([argv + out_args(1), steady], stages, env, tmp, f"{name}_warm")
    result["load_avg"] = result["warm"]["runs"][-1]["load_after"]
    return result


# ============================================================================ aggregation


def _top(events: list[dict]) -> list[dict]:
    return [e for e in events if e["depth"] == 0]


def _norm(name: str) -> str:
    """Trace events name the function (``f``), lowering and compile events the module
    (``jit(f)``, ``jit_f``)."""
    if name.startswith("jit(") and name.endswith(")"):
        return name[4:-1]
    return name[4:] if name.startswith("jit_") else name


def programs(events: list[dict], run: int) -> dict[tuple[str, str], dict]:
    """(stage, program) -> counts, seconds and sizes of the events of one run."""
    out: dict[tuple[str, str], dict] = defaultdict(
        lambda: dict(n=0, trace=0.0, lower=0.0, compile=0.0, cpu=0.0, hlo_bytes=0,
                     hits=0, callbacks=0, signatures=set())
    )
    for e in events:
        if e["run"] != run:
            continue
        p = out[(e["stage"], _norm(e["name"]))]
        p[e["kind"]] += e["wall"]
        if e["depth"] == 0:
            p["cpu"] += e["cpu"]
        if e["kind"] == "compile":
            p["n"] += 1
            p["hlo_bytes"] += e.get("hlo_bytes", 0)
            p["hits"] += int(e.get("cache_hit", False))
            p["callbacks"] += int(e.get("host_callbacks", 0) > 0)
            if "signature" in e:
                p["signatures"].add(e["signature"])
    return out


def totals(proc: dict, run: int) -> dict:
    ev = [e for e in proc["events"] if e["run"] == run]
    top = _top(ev)
    comp = [e for e in ev if e["kind"] == "compile"]
    r = proc["runs"][run]
    return dict(
        wall=r["wall"],
        cpu=r["cpu"],
        # outermost events only (nested ones are inside their parent's time)
        jax_wall=sum(e["wall"] for e in top),
        jax_cpu=sum(e["cpu"] for e in top),
        trace=sum(e["wall"] for e in ev if e["kind"] == "trace" and e["depth"] == 0),
        lower=sum(e["wall"] for e in ev if e["kind"] == "lower"),
        compile=sum(e["wall"] for e in comp),
        n_compiled=len(comp),
        n_names=len({_norm(e["name"]) for e in comp}),
        n_hits=sum(int(e.get("cache_hit", False)) for e in comp),
        n_callbacks=sum(int(e.get("host_callbacks", 0) > 0) for e in comp),
        hlo_mb=sum(e.get("hlo_bytes", 0) for e in comp) / 1e6,
        load=r["load_before"],
    )


def stage_table(proc: dict, run: int) -> dict[str, dict]:
    st: dict[str, dict] = defaultdict(lambda: dict(wall=0.0, cpu=0.0, jax_wall=0.0,
                                                   jax_cpu=0.0, n=0))
    for c in proc["stage_calls"]:
        if c["run"] == run:
            st[c["stage"]]["wall"] += c["wall"]
            st[c["stage"]]["cpu"] += c["cpu"]
    # the rest of the command's time (its own code, outputs, plots)
    r = proc["runs"][run]
    st["command"]["wall"] = r["wall"] - sum(v["wall"] for k, v in st.items() if k != "command")
    st["command"]["cpu"] = r["cpu"] - sum(v["cpu"] for k, v in st.items() if k != "command")
    for e in _top(proc["events"]):
        if e["run"] == run:
            st[e["stage"]]["jax_wall"] += e["wall"]
            st[e["stage"]]["jax_cpu"] += e["cpu"]
    for e in proc["events"]:
        if e["run"] == run and e["kind"] == "compile":
            st[e["stage"]]["n"] += 1
    return st


def _f(x: float, nd: int = 1) -> str:
    return f"{x:.{nd}f}"


def markdown(all_results: dict) -> str:
    lines = [
        "# Compilation cost of the `ppr` commands",
        "",
        "`.venv/bin/python bench/bench_compile.py [--only NAME,...]` (2-core VM shared with "
        "other jobs: wall seconds are inflated by the load average shown; CPU seconds, "
        "program counts and StableHLO sizes are not). cold: first process, empty persistent "
        "cache; warm: second process on that cache; steady: the command again in the warm "
        "process. `jax` = seconds inside JAX's trace/lower/compile events (outermost "
        "events; wall / process CPU). Programs: XLA compilations (cache reads included).",
        "",
        "| command | load | cold wall / CPU s | cold jax wall / CPU s | trace / lower / "
        "compile s | programs (names) | StableHLO MB | cached entries | warm wall / CPU s "
        "| warm jax s | warm hits / programs | steady wall / CPU s | steady programs |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in all_results.items():
        c = totals(r["cold"], 0)
        w = totals(r["warm"], 0)
        s = totals(r["warm"], 1)
        lines.append(
            f"| {name} | {' '.join(c['load'][:1])} | {_f(c['wall'])} / {_f(c['cpu'])} | "
            f"{_f(c['jax_wall'])} / {_f(c['jax_cpu'])} | {_f(c['trace'])} / {_f(c['lower'])}"
            f" / {_f(c['compile'])} | {c['n_compiled']} ({c['n_names']}) | {_f(c['hlo_mb'])}"
            f" | {r['cache_after_cold']['entries']} | {_f(w['wall'])} / {_f(w['cpu'])} | "
            f"{_f(w['jax_wall'])} | {w['n_hits']} / {w['n_compiled']} | {_f(s['wall'])} / "
            f"{_f(s['cpu'])} | {s['n_compiled']} |"
        )
    for name, r in all_results.items():
        lines += ["", f"## {name}", "", f"`ppr {' '.join(r['argv'])}`; "
                  f"import {_f(r['cold']['import_wall'])} s; peak RSS "
                  f"{r['cold']['max_rss_mb']:.0f} MB (cold)", ""]
        if r.get("note"):
            lines[-1:-1] = ["", r["note"]]
        lines += [
            "| stage | cold wall / CPU s | cold jax wall / CPU s | cold programs | "
            "warm wall / CPU s | warm jax s | steady wall / CPU s | steady programs |",
            "|---|---|---|---|---|---|---|---|",
        ]
        sc, sw, ss = (stage_table(r["cold"], 0), stage_table(r["warm"], 0),
                      stage_table(r["warm"], 1))
        for st in sorted(set(sc) | set(sw) | set(ss), key=lambda k: -sc.get(k, {}).get(
                "jax_wall", 0.0)):
            a, b, d = (x.get(st, dict(wall=0.0, cpu=0.0, jax_wall=0.0, jax_cpu=0.0, n=0))
                       for x in (sc, sw, ss))
            lines.append(
                f"| {st} | {_f(a['wall'])} / {_f(a['cpu'])} | {_f(a['jax_wall'])} / "
                f"{_f(a['jax_cpu'])} | {a['n']} | {_f(b['wall'])} / {_f(b['cpu'])} | "
                f"{_f(b['jax_wall'])} | {_f(d['wall'])} / {_f(d['cpu'])} | {d['n']} |"
            )
        pc, pw, ps = (programs(r["cold"]["events"], 0), programs(r["warm"]["events"], 0),
                      programs(r["warm"]["events"], 1))
        keys = sorted(pc, key=lambda k: -(pc[k]["trace"] + pc[k]["lower"] + pc[k]["compile"]))
        lines += [
            "",
            "| stage | program | compiled (shapes) | trace s | lower s | compile s | CPU s | "
            "StableHLO KB | callbacks | warm: hits / compiled, s | steady compiled |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        shown = keys[:30]
        for k in shown:
            p = pc[k]
            w = pw.get(k, dict(n=0, hits=0, trace=0.0, lower=0.0, compile=0.0))
            s = ps.get(k, dict(n=0))
            lines.append(
                f"| {k[0]} | `{k[1]}` | {p['n']} ({len(p['signatures'])}) | "
                f"{_f(p['trace'], 2)} | {_f(p['lower'], 2)} | {_f(p['compile'], 2)} | "
                f"{_f(p['cpu'], 2)} | {p['hlo_bytes'] / 1e3:.0f} | {p['callbacks']} | "
                f"{w['hits']} / {w['n']}, {_f(w['trace'] + w['lower'] + w['compile'], 2)} | "
                f"{s['n']} |"
            )
        rest = keys[30:]
        if rest:
            tot = sum(pc[k]["trace"] + pc[k]["lower"] + pc[k]["compile"] for k in rest)
            lines.append(
                f"| | {len(rest)} more programs | {sum(pc[k]['n'] for k in rest)} | | | "
                f"{_f(tot, 2)} (all three) | | | | | |"
            )
        new = [k for k in ps if ps[k]["n"] and k not in pw]
        if new:
            lines += ["", "Compiled in the steady-state call only: "
                      + ", ".join(f"`{k[1]}` ({k[0]})" for k in new)]
    return "\n".join(lines) + "\n"


# sections of the results file that other benches write (kept when the tables are rewritten)
KEPT_SECTIONS = ("## library scripts",)  # bench/bench_script_cache.py


def _kept_sections(path: Path) -> str:
    if not path.exists():
        return ""
    text, kept = path.read_text(), []
    for head in KEPT_SECTIONS:
        m = re.search(rf"^{re.escape(head)}\n.*?(?=^## |\Z)", text, re.S | re.M)
        if m:
            kept.append("\n" + m.group(0).rstrip("\n") + "\n")
    return "".join(kept)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=None, help="comma-separated commands " + str(list(COMMANDS)))
    ap.add_argument("--cold-cache", choices=["empty", "off"], default="empty")
    ap.add_argument("--set", action="append", default=[], metavar="CMD:KEY=VALUE",
                    help="extra --set override of one command")
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
    ap.add_argument("--no-write", action="store_true", help="print only")
    ap.add_argument("--results", default="compile", help="results file stem (bench/results/)")
    args = ap.parse_args()
    names = list(COMMANDS) if args.only is None else args.only.split(",")
    for n in names:
        if n not in COMMANDS:
            ap.error(f"--only: unknown command {n!r} (choose from {list(COMMANDS)})")
    extra: dict[str, list[str]] = defaultdict(list)
    for s in args.set:
        cmd, _, kv = s.partition(":")
        extra[cmd] += ["--set", kv]
    tmp = Path(tempfile.mkdtemp(prefix="ppr_bench_compile_"))
    json_path = RESULTS / f"{args.results}.json"
    stored = json.loads(json_path.read_text()) if json_path.exists() else {}
    try:
        db = None
        if "classify" in names:
            if "database" not in names:
                print("[setup] database build (not recorded) ...", flush=True)
                env = dict(os.environ, PYTHONPATH=str(REPO), PPR_JAX_CACHE="0")
                subprocess.run(
                    [sys.executable, "-m", "ppr.cli", "database", "build", "--out",
                     str(tmp / "setup_db"), "--quiet"], env=env, cwd=REPO, check=True)
                db = str(tmp / "setup_db" / "database.zarr")
            else:
                names.remove("database")
                names.insert(names.index("classify"), "database")
        for n in names:
            r = run_command(n, extra[n], tmp, args.cold_cache, db)
            if n == "database":
                db = str(tmp / "out_database_0" / "database.zarr")
            for proc in ("cold", "warm"):
                for i in range(len(r[proc]["runs"])):
                    t = totals(r[proc], i)
                    print(f"  {proc}[{i}]: wall {t['wall']:.1f} s, cpu {t['cpu']:.1f} s, jax "
                          f"{t['jax_wall']:.1f} s, {t['n_compiled']} programs, "
                          f"{t['n_hits']} hits", flush=True)
            stored[n] = r
            if not args.no_write:
                RESULTS.mkdir(exist_ok=True)
                json_path.write_text(json.dumps(stored))
        md = markdown({k: stored[k] for k in COMMANDS if k in stored})
        print(md)
        if not args.no_write:
            md_path = RESULTS / f"{args.results}.md"
            md_path.write_text(md + _kept_sections(md_path))
    finally:
        if not args.keep:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
