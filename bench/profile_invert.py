"""Where a steady-state ``ppr invert`` spends its time: stages, compiled programs, host code.

Runs the shipped ``ppr invert`` config (``configs/cli/invert.toml``; ``--set`` overrides as
on the command line, default ``mcmc="none"``: the refinement stages) twice in one process
(the first call compiles), profiles the second with ``cProfile`` and prints its stage
timings (``Inversion.timings``), the seconds spent inside compiled programs (equinox's and
JAX's jit dispatch, which waits for the result) against the rest (host code), and the calls
ranked by cumulative time.

Run: ``.venv/bin/python bench/profile_invert.py [--set KEY=VALUE ...] [--top 30]``. Prints
only; writes nothing (outputs go to a temporary folder).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--top", type=int, default=30)
    args = ap.parse_args(argv)
    from ppr._config import load_toml_model, parse_override
    from ppr.cli import invert as cli_invert

    overrides = {"mcmc": "none"}
    overrides.update(dict(parse_override(s) for s in args.set))
    cfg_path = ROOT / "configs" / "cli" / "invert.toml"
    cfg = load_toml_model(cli_invert._schema(), cfg_path, overrides)
    prof = cProfile.Profile()
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(2):
            t0 = time.perf_counter()
            if k == 1:
                prof.enable()
            inv = cli_invert.run_invert(cfg, cfg_path, Path(tmp) / f"out{k}")
            if k == 1:
                prof.disable()
            stages = ", ".join(f"{a} {b:.2f}" for a, b in inv.timings.items())
            label = "first (compiles)" if k == 0 else "second (steady)"
            print(f"{label}: {time.perf_counter() - t0:.1f} s wall; stages (s): {stages}")
    stats = pstats.Stats(prof)
    total = stats.total_tt
    compiled = sum(
        v[2]  # total time inside the function itself: the dispatch blocks on the program
        for (fname, _, func), v in stats.stats.items()
        if ("equinox" in fname and func == "_call") or ("pjit" in fname and "cpp_pjit" in func)
    )
    print(
        f"second call: {total:.1f} s profiled, {compiled:.1f} s inside compiled programs "
        f"({100 * compiled / total:.0f} %), the rest host code"
    )
    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("cumulative").print_stats(args.top)
    print(buf.getvalue())


if __name__ == "__main__":
    main()
