"""Where the test suite's time goes: per test, seconds compiling (tracing, lowering, XLA)
against the rest, and the programs that several tests compile again.

    .venv/bin/python bench/bench_test_compile.py --run tests/test_double.py [more pytest args]
    .venv/bin/python bench/bench_test_compile.py --log compile_log.jsonl   # summarize a log

``--run`` runs pytest (default ``-n 0``) with ``PPR_TEST_COMPILE_LOG`` set
(``tests/compile_log.py``: one JSON line per test); ``--log`` summarizes an existing log
(e.g. of a whole ``make test`` run with ``PPR_TEST_COMPILE_LOG`` exported). Writes
``bench/results/test_compile.md`` (``--name`` adds a suffix). CPU seconds are the test
process's own (notebook kernels and CLI subprocesses are other processes: their time shows in
the wall column only).

Duplicates: a program (same StableHLO module and compile level) compiled by more than one
test, or more than once by one. Within one process JAX's jit cache keys on the Python
function, so such a repeat is a new function object lowering to the same module (a jit or
lambda made inside the test), a cache cleared in between (the switch to optimized
compilation), or another xdist worker. A persistent compilation cache shared by the session
answers all of them from disk.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent


def summarize(rows: list[dict], title: str) -> str:
    comp = lambda r: r["trace"] + r["lower"] + r["compile"]  # noqa: E731
    wall = sum(r["wall"] for r in rows)
    cpu = sum(r["cpu"] for r in rows)
    c = sum(comp(r) for r in rows)
    progs = [p for r in rows for p in r["programs"]]
    hits = sum(p["hit"] for p in progs)
    by_fp: dict[str, list] = defaultdict(list)
    for r in rows:
        for p in r["programs"]:
            by_fp[p["fp"]].append((r["test"], p))
    dups = {fp: v for fp, v in by_fp.items() if len(v) > 1}
    # what the repeats cost (their own XLA time; cache hits cost their read)
    repeat_s = sum(sum(p["s"] for _, p in v[1:]) for v in dups.values())
    lines = [
        f"# Test compilation: {title}",
        "",
        f"{len(rows)} tests; wall {wall:.0f} s, process CPU {cpu:.0f} s; inside JAX's "
        f"trace/lower/compile events {c:.0f} s ({100 * c / max(wall, 1e-9):.0f} % of wall); "
        f"{len(progs)} programs compiled ({hits} from the persistent cache), "
        f"{len(by_fp)} distinct; {sum(len(v) - 1 for v in dups.values())} repeats of "
        f"{len(dups)} programs costing {repeat_s:.0f} s of XLA time; "
        f"{sum(p['callbacks'] > 0 for p in progs)} programs with host callbacks (never "
        "cached).",
        "",
        "| test | wall s | CPU s | trace / lower / compile s | compile share | programs "
        "(hits) |",
        "|---|---|---|---|---|---|",
    ]
    for r in sorted(rows, key=lambda r: -r["wall"])[:40]:
        n = len(r["programs"])
        h = sum(p["hit"] for p in r["programs"])
        lines.append(
            f"| `{r['test'].removeprefix('tests/')}` | {r['wall']:.1f} | {r['cpu']:.1f} | "
            f"{r['trace']:.1f} / {r['lower']:.1f} / {r['compile']:.1f} | "
            f"{100 * comp(r) / max(r['wall'], 1e-9):.0f} % | {n} ({h}) |"
        )
    mods: dict[str, list] = defaultdict(lambda: [0.0, 0.0, 0.0, 0])
    for r in rows:
        m = mods[r["test"].split("::")[0]]
        m[0] += r["wall"]
        m[1] += r["cpu"]
        m[2] += comp(r)
        m[3] += len(r["programs"])
    lines += ["", "| module | wall s | CPU s | compiling s | programs |", "|---|---|---|---|---|"]
    for k, (w, cp, cc, n) in sorted(mods.items(), key=lambda kv: -kv[1][0]):
        lines.append(f"| `{k}` | {w:.0f} | {cp:.0f} | {cc:.0f} | {n} |")
    lines += [
        "",
        "Programs compiled more than once (largest repeat cost first):",
        "",
        "| program | times | XLA s of the repeats | tests |",
        "|---|---|---|---|",
    ]
    for _, v in sorted(dups.items(), key=lambda kv: -sum(p["s"] for _, p in kv[1][1:]))[:25]:
        tests = sorted({t.split("::")[-1][:40] for t, _ in v})
        lines.append(
            f"| `{v[0][1]['name']}` | {len(v)} | {sum(p['s'] for _, p in v[1:]):.1f} | "
            f"{', '.join(tests[:4])}{' ...' if len(tests) > 4 else ''} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", nargs=argparse.REMAINDER, help="pytest arguments")
    ap.add_argument("--log", help="an existing PPR_TEST_COMPILE_LOG file")
    ap.add_argument("--name", default="", help="suffix of the results file")
    args = ap.parse_args()
    if (args.run is None) == (args.log is None):
        ap.error("give exactly one of --run and --log")
    if args.run is not None:
        log = Path(tempfile.mkdtemp(prefix="ppr_test_compile_")) / "log.jsonl"
        pytest_args = args.run if any(a.startswith("-n") for a in args.run) else [
            *args.run, "-n", "0"]
        env = dict(os.environ, PPR_TEST_COMPILE_LOG=str(log), PYTHONPATH=str(REPO))
        subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                        *pytest_args], env=env, cwd=REPO, check=False)
        title = "pytest " + " ".join(pytest_args)
    else:
        log = Path(args.log)
        title = str(log)
    rows = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    md = summarize(rows, title)
    print(md)
    out = HERE / "results" / f"test_compile{'_' + args.name if args.name else ''}.md"
    out.write_text(md)
    (out.with_suffix(".jsonl")).write_text(log.read_text())


if __name__ == "__main__":
    main()
