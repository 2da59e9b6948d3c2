"""Compile-time settings: XLA:CPU's emitters (applied when jaxdrake is imported) and, on
request, JAX's persistent compilation cache (`use_compilation_cache`).

XLA's CPU backend (jaxlib 0.10) generates its fused kernels with the newer "fusion
emitters" by default. For the many small kernels of a simulation loop, a rigid-body
recursion or their gradients, the classic emitters compile in about half the time at the
same run time (measured on a 2-core CPU: `jax.jit(plant.dynamics)` of the Panda 1.4 -> 0.5 s,
Solo-12 2.1 -> 0.9 s, Talos 1.9 -> 0.9 s; see `benchmarks/RESULTS.md`). So, when nothing
else chose, jaxdrake asks for the classic emitters through `XLA_FLAGS`.

This only takes effect if jaxdrake is imported before JAX creates its CPU backend (the first
computation), and never overrides a choice already in `XLA_FLAGS`. To keep XLA's default,
set `XLA_FLAGS=--xla_cpu_use_fusion_emitters=true` (or `JAXDRAKE_KEEP_XLA_FLAGS=1`) before
importing jaxdrake. It does not affect GPU or TPU compilation.
"""

from __future__ import annotations

import os
import pathlib

_FLAG = "--xla_cpu_use_fusion_emitters"
# jaxlib versions whose XLA knows the flag: an unknown flag in XLA_FLAGS aborts the process, and
# jaxlib 0.11.2 (the GPU machines') no longer has it (the classic emitters are gone there).
_VERIFIED_JAXLIB = ("0.10.",)


def prefer_fast_cpu_compilation() -> bool:
    """Add `--xla_cpu_use_fusion_emitters=false` to `XLA_FLAGS` unless the user set it, opted
    out, or runs a jaxlib this was not verified on. Returns whether the flag was added."""
    if os.environ.get("JAXDRAKE_KEEP_XLA_FLAGS"):
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    if _FLAG in flags:
        return False
    try:
        from importlib.metadata import version

        jaxlib_version = version("jaxlib")
    except Exception:  # no jaxlib metadata: leave XLA alone
        return False
    if not jaxlib_version.startswith(_VERIFIED_JAXLIB):
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {_FLAG}=false".strip()
    return True


def use_compilation_cache(directory=None) -> pathlib.Path:
    """Keep every compiled program on disk (JAX's persistent compilation cache), so that a new
    process (a restarted notebook kernel, the next run of a script) loads it instead of
    compiling it again; tracing still runs. The acrobot's swing-up by `DirectCollocation` with
    the exact Hessian: first solve in a fresh process 8-10 s, 4.1-4.7 s once the cache holds its
    programs (2-core CPU). `directory`: default `$JAXDRAKE_CACHE`, else
    `~/.cache/jaxdrake/xla`. Sets JAX's global options for the whole process (every program is
    kept, however quick to compile: JAX's default keeps only those that took a second); the
    cache is never pruned, delete the directory to empty it. Returns the directory."""
    import jax

    path = pathlib.Path(directory or os.environ.get("JAXDRAKE_CACHE") or "~/.cache/jaxdrake/xla").expanduser()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
