"""Per-test compilation log (opt-in): ``PPR_TEST_COMPILE_LOG=path pytest ...`` appends one JSON
line per test to ``path``: wall and CPU seconds of the test (setup, call, teardown), the
seconds spent tracing, lowering and compiling (JAX's ``jax.monitoring`` duration events,
outermost events only), and every program compiled, with a fingerprint of its StableHLO module
(without locations, as in JAX's persistent-cache key) and compile level, so that a summary can
find the programs several tests (or workers) compile (``bench/bench_test_compile.py``). Off by
default: the hooks then cost nothing.

Notebook kernels and subprocesses are separate processes: their compilation shows only in
the wall time of the test that started them.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import threading
import time

EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
}


class CompileLog:
    def __init__(self, path: str) -> None:
        self.path = path
        self.worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        self.depth = 0
        self.local = threading.local()
        self.reset()

    def reset(self) -> None:
        self.sums = {k: 0.0 for k in EVENTS.values()}
        self.programs: list[dict] = []
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        t = os.times()
        self.k0 = t.children_user + t.children_system

    def install(self) -> None:
        import jax
        from jax._src import compiler

        jax.monitoring.register_scalar_listener(self._start)
        jax.monitoring.register_event_duration_secs_listener(self._end)
        jax.monitoring.register_event_listener(self._event)
        original = compiler.compile_or_get_cached

        @functools.wraps(original)
        def wrapped(backend, computation, devices, options, host_callbacks, *args, **kwargs):
            from jax._src import cache_key

            level = jax.config.read("jax_disable_most_optimizations")
            # the module without debug info (locations), as JAX's persistent-cache key has it
            ir = cache_key._canonicalize_ir(computation, cache_key.IgnoreCallbacks.NO)
            h = hashlib.sha1(ir)
            h.update(b"O0" if level else b"O")
            self.local.hit = False
            t = time.perf_counter()
            out = original(backend, computation, devices, options, host_callbacks, *args, **kwargs)
            self.programs.append(
                {
                    "name": str(computation.operation.attributes["sym_name"]).strip('"'),
                    "fp": h.hexdigest()[:16],
                    "s": time.perf_counter() - t,
                    "hit": bool(self.local.hit),
                    "callbacks": len(host_callbacks),
                }
            )
            return out

        compiler.compile_or_get_cached = wrapped

    def _event(self, event: str, **kwargs) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            self.local.hit = True

    def _start(self, event: str, value: float, **kwargs) -> None:
        if event in EVENTS:
            self.depth += 1

    def _end(self, event: str, duration: float, **kwargs) -> None:
        kind = EVENTS.get(event)
        if kind is None:
            return
        self.depth -= 1
        if self.depth == 0:
            self.sums[kind] += duration

    def write(self, nodeid: str) -> None:
        rec = {
            "test": nodeid,
            "worker": self.worker,
            "wall": time.perf_counter() - self.t0,
            "cpu": time.process_time() - self.c0,
            # reaped child processes (CLI subprocesses, notebook kernels)
            "cpu_children": os.times().children_user + os.times().children_system - self.k0,
            **self.sums,
            "programs": self.programs,
        }
        with open(self.path, "a") as f:
            f.write(json.dumps(rec) + "\n")
