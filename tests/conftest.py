"""Tests run in float64 ("float64 for truth"); float32 is tested explicitly."""

import os

# The suite is compile-bound: LLVM's expensive optimisation passes cost ~11% of its CPU time
# (tests/test_hybrid.py: 104 -> 93 CPU-s) and change no result (no fast-math: the same IEEE
# operations, scheduled with less effort). Set before JAX starts its CPU backend; inherited by
# the example scripts and node processes the tests start. A user's XLA_FLAGS still wins.
# Only on the jaxlib this was measured with (an unknown flag aborts the process).
from importlib.metadata import version  # noqa: E402

if version("jaxlib").startswith("0.10.") and "xla_llvm_disable_expensive_passes" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_llvm_disable_expensive_passes=true".strip()

import jax  # noqa: E402
import matplotlib  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
matplotlib.use("Agg")


@pytest.fixture(autouse=True, scope="session")
def _one_compilation_cache_per_run(tmp_path_factory):
    """The run's workers share one JAX persistent compilation cache (fresh per run: under
    pytest's base temporary directory, which pytest prunes): a program compiled by one test
    file (or worker) is loaded by the next that builds the same one, also after
    `_free_compiled_programs` dropped the in-memory caches. Programs that compiled in 0.3 s or
    more only. Measured on 2 cores: 63 of ~490 such programs were loaded instead of compiled,
    the suite 11:58 -> 11:06 (590 passed both ways). An entry read while the other worker
    writes it fails to decompress, and JAX then warns and compiles."""
    base = tmp_path_factory.getbasetemp()
    directory = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "jax-compilation-cache"
    directory.mkdir(exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(directory))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.3)
    yield


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    import matplotlib.pyplot as plt
    plt.close("all")


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    # One pytest process compiles thousands of XLA programs; without this, a full run on the
    # 2-core CI machine aborted inside XLA's compiler near the end (each test file passes on
    # its own). Dropping the compilation caches between files keeps the process small.
    yield
    jax.clear_caches()
    import gc
    gc.collect()


def pytest_collection_modifyitems(config, items):
    """The example scripts and notebooks (the suite's longest pole: their own processes, run
    side by side) first, so that they overlap the rest of the suite."""
    items.sort(key=lambda item: item.module.__name__ != "test_examples")  # a stable sort
