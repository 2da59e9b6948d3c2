"""Timing helper shared by the benchmarks."""

import time


def best_time(fn, repeats: int) -> float:
    """The fastest of `repeats` calls of `fn`, in seconds (call `block_until_ready` inside)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)
