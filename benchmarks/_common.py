"""What the benchmarks share: best-of timing, the machine line, the command-line options."""

import argparse
import platform
import time

import jax


def best_time(fn, repeats: int) -> float:
    """The fastest of `repeats` calls of `fn`, in seconds (call `block_until_ready` inside)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


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
