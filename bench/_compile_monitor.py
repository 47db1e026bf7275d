"""Records every program JAX traces, lowers and compiles in this process (imported by
``bench/bench_compile.py``'s child processes).

Sources, all of them JAX's own:

- ``jax.monitoring`` duration events ``/jax/core/compile/jaxpr_trace_duration`` (tracing a
  jitted function), ``.../jaxpr_to_mlir_module_duration`` (lowering to StableHLO) and
  ``.../backend_compile_duration`` (XLA compilation, or the persistent-cache read that
  replaces it), each with the function or module name. JAX announces each of them at its start
  with a ``record_scalar`` of the same event name: the start hook takes the process CPU time
  and the stage, the end hook the wall duration and the CPU time spent.
- ``jax._src.compiler.compile_or_get_cached`` (wrapped): the StableHLO module handed to XLA,
  its bytecode size (load-independent), the argument types of its ``main`` function, the
  number of host callbacks (programs with host callbacks are never written to the persistent
  cache) and whether the persistent cache answered (``/jax/compilation_cache/cache_hits``).

Events can nest (an eager op run while tracing an outer function compiles its own program):
each event carries its nesting depth, and totals use the outermost ones only.

Stages: :func:`wrap_stages` wraps named functions (e.g. ``inversion.refine``); an event belongs
to the outermost wrapped call running when it starts (``"command"`` outside all of them).
"""

from __future__ import annotations

import functools
import threading
import time

EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
}


class Monitor:
    def __init__(self) -> None:
        self.events: list[dict] = []
        self.stage_calls: list[dict] = []
        self.run = 0
        self._stage: list[str] = []
        self._open: dict[tuple[str, str], list[dict]] = {}
        self._depth = 0
        self._extra: dict | None = None
        self._hit = threading.local()
        self.t0 = time.perf_counter()

    # ------------------------------------------------------------------ listeners
    def install(self) -> None:
        from jax import monitoring
        from jax._src import compiler

        monitoring.register_scalar_listener(self._on_start)
        monitoring.register_event_duration_secs_listener(self._on_end)
        monitoring.register_event_listener(self._on_event)
        original = compiler.compile_or_get_cached

        @functools.wraps(original)
        def wrapped(backend, computation, devices, compile_options, host_callbacks, *a, **k):
            extra = _module_facts(computation)
            extra["host_callbacks"] = len(host_callbacks)
            self._hit.value = False
            out = original(backend, computation, devices, compile_options, host_callbacks, *a, **k)
            extra["cache_hit"] = bool(self._hit.value)
            self._extra = extra
            return out

        compiler.compile_or_get_cached = wrapped

    def _on_event(self, event: str, **kwargs) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            self._hit.value = True

    def _on_start(self, event: str, value: float, **kwargs) -> None:
        kind = EVENTS.get(event)
        if kind is None:
            return
        rec = {
            "kind": kind,
            "name": str(kwargs.get("fun_name", "?")),
            "stage": self._stage[0] if self._stage else "command",
            "run": self.run,
            "depth": self._depth,
            "t_start": time.perf_counter() - self.t0,
            "_cpu0": time.process_time(),
        }
        self._depth += 1
        self._open.setdefault((kind, rec["name"]), []).append(rec)

    def _on_end(self, event: str, duration: float, **kwargs) -> None:
        kind = EVENTS.get(event)
        if kind is None:
            return
        stack = self._open.get((kind, str(kwargs.get("fun_name", "?"))))
        if not stack:
            return
        rec = stack.pop()
        self._depth -= 1
        rec["wall"] = float(duration)
        rec["cpu"] = time.process_time() - rec.pop("_cpu0")
        if kind == "compile" and self._extra is not None:
            rec.update(self._extra)
            self._extra = None
        self.events.append(rec)

    # ------------------------------------------------------------------ stages
    def wrap_stages(self, targets: list[tuple[object, str, str]]) -> None:
        """``(owner, attribute, stage name)``: replace ``owner.attribute`` by a wrapper that
        marks its outermost calls as the stage and records their wall and CPU time."""
        for owner, attr, stage in targets:
            fn = getattr(owner, attr, None)
            if fn is None:
                continue
            setattr(owner, attr, self._stage_wrapper(fn, stage))

    def _stage_wrapper(self, fn, stage: str):
        mon = self

        @functools.wraps(fn)
        def inner(*args, **kwargs):
            if mon._stage:
                return fn(*args, **kwargs)
            mon._stage.append(stage)
            w0, c0 = time.perf_counter(), time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                mon._stage.pop()
                mon.stage_calls.append(
                    {
                        "stage": stage,
                        "run": mon.run,
                        "wall": time.perf_counter() - w0,
                        "cpu": time.process_time() - c0,
                    }
                )

        return inner


def _module_facts(computation) -> dict:
    """StableHLO bytecode size and the ``main`` function's type of a module about to be
    compiled (cheap: serialization is what the cache key costs anyway)."""
    facts: dict = {}
    try:
        from jax._src.interpreters import mlir

        facts["hlo_bytes"] = len(mlir.module_to_bytecode(computation))
    except Exception:  # noqa: BLE001 - a fact we could not get is left out
        pass
    try:
        for op in computation.body.operations:
            if op.operation.name == "func.func" and str(
                op.attributes["sym_name"]
            ).strip('"') == "main":
                facts["signature"] = str(op.attributes["function_type"])[:400]
                break
    except Exception:  # noqa: BLE001
        pass
    return facts
