"""What the benchmarks share: best-of timing, the machine line, the command-line options."""

import argparse
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np


def best_time(fn, repeats: int) -> float:
    """The fastest of `repeats` calls of `fn`, in seconds (call `block_until_ready` inside)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def median_time(fn, repeats: int, warmup: int = 5) -> float:
    """The median of `repeats` warm calls of `fn` (after `warmup` calls), in seconds; `fn`'s
    result is waited for."""
    for _ in range(warmup):
        jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def machine_line() -> str:
    """The processor, JAX's device and version, and the float width, for RESULTS.md."""
    device = jax.devices()[0]
    width = "float64" if jax.config.jax_enable_x64 else "float32"
    return (f"machine: {platform.processor() or platform.machine()}, {device.platform} "
            f"({device.device_kind}), jax {jax.__version__}, {width}")


def argument_parser(doc: str, *, repeats: int, gpu_help: str, batch: int | None = None):
    """--repeats and --gpu (JAX rows only), and --batch when `batch` is given."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    if batch is not None:
        parser.add_argument("--batch", type=int, default=batch)
    parser.add_argument("--repeats", type=int, default=repeats)
    parser.add_argument("--gpu", action="store_true", help=gpu_help)
    return parser


def final_state_or_nan(traj):
    """A simulation's final state, NaN where it failed: a benchmark times the runs that
    failed too, and must not report them as if they had run (see `failures`)."""
    return jnp.where(traj.success, traj.final_state, jnp.nan)


def failures(values) -> int:
    """How many members (rows of `values`) are not finite: failed runs, not to be timed."""
    values = np.atleast_2d(np.asarray(values))  # one final state: one member
    return int(np.sum(~np.isfinite(values.reshape(values.shape[0], -1)).all(axis=1)))


def solver_named(name: str):
    """A solver of `jd.simulate` from a benchmark's command line: its own names, and
    "rosenbrock23/stiff" for `Rosenbrock23(jacobian="stiff")`."""
    import jaxdrake as jd
    return jd.simulation.Rosenbrock23(jacobian="stiff") if name == "rosenbrock23/stiff" else name
