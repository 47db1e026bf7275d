"""Test configuration: float64 references, warnings are errors (see pyproject)."""

import os
import shutil
import tempfile

os.environ.setdefault("MPLBACKEND", "Agg")
# Hermetic compilation: `ppr.cli.main` enables a persistent XLA cache in ~/.cache/ppr/jax
# unless PPR_JAX_CACHE=0, and JAX config is process-wide. A test that calls the CLI would
# otherwise switch the cache on for the rest of its worker, and later tests would time (and
# run) against executables left by earlier runs, not against what a clean checkout compiles.
os.environ["PPR_JAX_CACHE"] = "0"
# Compile unoptimized (tests/compile_level.py), here and in the subprocesses and notebook
# kernels the tests start; tests marked `optimized` run with JAX's defaults.
os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1"
from compile_level import SUITE_XLA_FLAGS  # noqa: E402  (imports jax: after the line above)

# ... and with XLA:CPU's legacy kernel emitters (tests/compile_level.py, SUITE_XLA_FLAGS): the
# same HLO, generated 3-4x faster; process-wide, so the subprocesses and notebook kernels
# inherit it through the environment.
os.environ["XLA_FLAGS"] = " ".join(
    [f for f in os.environ.get("XLA_FLAGS", "").split() if f not in SUITE_XLA_FLAGS]
    + list(SUITE_XLA_FLAGS)
)
# PPR_TEST_JAX_CACHE=1: one persistent compilation cache per test session, in a new temporary
# folder (hermetic: every run starts empty, as a clean checkout does, and the folder is removed
# at the end), shared through the environment by the xdist workers, the notebook kernels and the
# CLI subprocesses, so that a program one of them compiled is read from disk by the others. JAX
# keys an entry on the location-free StableHLO module and the compile options (unoptimized and
# optimized builds stay apart); every program is written (minimum compile time 0). Off by
# default: the repeats it answers are few and small in the modules measured (2 workers on
# tests/test_double_table.py: 1 of 112 programs compiled by both, CPU 73.8 s off, 76.8 s on;
# notebook 02 with the CLI's simulate and image tests: 52 of 77 programs read from the cache,
# all small ones, CPU 37.7 s off, 35.5 s on; load 12-15): the costly programs differ in shape.
_SESSION_CACHE = None
if os.environ.get("PPR_TEST_JAX_CACHE", "0") == "1":
    if "PPR_TEST_JAX_CACHE_DIR" not in os.environ:  # the session's first process
        _SESSION_CACHE = tempfile.mkdtemp(prefix="ppr-test-jax-cache-")
        os.environ["PPR_TEST_JAX_CACHE_DIR"] = _SESSION_CACHE
    os.environ["JAX_COMPILATION_CACHE_DIR"] = os.environ["PPR_TEST_JAX_CACHE_DIR"]
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
else:
    os.environ.pop("JAX_COMPILATION_CACHE_DIR", None)

import jax  # noqa: E402
import pytest  # noqa: E402
from compile_level import DEFAULT, UNOPTIMIZED, apply  # noqa: E402, I001
from compile_log import CompileLog  # noqa: E402

jax.config.update("jax_enable_x64", True)
apply(UNOPTIMIZED)

# per-test compilation log, opt-in (tests/compile_log.py)
_LOG = CompileLog(os.environ["PPR_TEST_COMPILE_LOG"]) if os.environ.get(
    "PPR_TEST_COMPILE_LOG"
) else None
if _LOG is not None:
    _LOG.install()


def pytest_unconfigure(config):
    if _SESSION_CACHE is not None:
        shutil.rmtree(_SESSION_CACHE, ignore_errors=True)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    if _LOG is not None:
        _LOG.reset()
    yield
    if _LOG is not None:
        _LOG.write(item.nodeid)


_optimized = [False]  # the worker's current setting


@pytest.fixture(autouse=True)
def _compile_level(request):
    """Tests marked ``optimized`` (their cost is running, not compiling) compile with JAX's
    default optimization; every other test compiles unoptimized. JAX's jit cache does not key
    on the switch, so switching to the defaults drops the worker's (unoptimized) executables
    first, or the test would reuse any that an earlier test compiled for the same program.
    Switching back keeps the optimized ones: reusing them costs nothing."""
    marked = request.node.get_closest_marker("optimized") is not None
    if marked and not _optimized[0]:
        jax.clear_caches()
        apply(DEFAULT)
    elif not marked and _optimized[0]:
        apply(UNOPTIMIZED)
    _optimized[0] = marked
    yield


# The slowest tests (seconds of one worker, `--durations`, 2026-12-02) run first, so that the
# two xdist workers share them from the start instead of one worker finishing a long test
# alone at the end (xdist's "load" scheduler hands out the collected order round-robin).
SLOW_FIRST = (
    "test_grazing.py::test_grazing_and_stiff_geometry_finite_values_and_gradients_float32_matches_float64",
    "test_notebooks.py::test_notebook_runs[04_inversion_mcmc]",  # 92
    "test_cli.py::test_invert_end_to_end",  # 79
    "test_notebooks.py::test_notebook_runs[01_brdf_tour]",  # 74
    "test_notebooks.py::test_notebook_runs[05_validation]",  # 70
    "test_refine.py::test_mirror_check_finds_the_parity_ambiguity_and_its_breaking",  # 57
    "test_notebooks.py::test_notebook_runs[02_cubesat_simulation]",  # 54
    "test_pulse.py::test_normal_groups_change_nothing_values_and_gradients",  # 49
    "test_double.py::test_auto_rule_skips_only_where_negligible",  # 38
    "test_double.py::test_white_albedo_matches_process_monte_carlo",  # 37
    "test_pulse.py::test_face_subset_renders_the_full_mesh_values_and_gradients",  # 35
    "test_refine.py::test_noise_free_recovery_from_classifier_like_start",  # 32
    "test_furnace.py::test_white_furnace_all_terms",  # 32
    "test_compile_level.py::test_unoptimized_compilation_gives_the_same_values_and_gradients",
    "test_invert.py::test_invert_recovers_box_attitude_material_and_is_reliable",  # ~27 (load 5)
    "test_notebooks.py::test_notebook_runs[03_classifier_evaluation]",  # 27
)


def pytest_collection_modifyitems(config, items):
    def rank(item):
        for i, name in enumerate(SLOW_FIRST):
            if item.nodeid.endswith(name) or f"{name}[" in item.nodeid:
                return i
        return len(SLOW_FIRST)

    items.sort(key=rank)  # stable: the rest keeps its order
