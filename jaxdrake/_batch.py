"""`run_batch`: a per-member function over a batch of any size, in chunks that fit in memory,
spread over devices.

Results gathered to this host from this process's devices: each device drains its own queue of
slices in its own thread, so a device never waits for another's slowest member (two H200s,
10^7 pendulum simulations: 1.92x one device, against 1.78x when every chunk was one program
over both). Results left on the devices, or devices of several processes
(`jax.distributed.initialize()` first; every process calls it with the same arguments and the
global devices): every chunk is one program sharded over all of them (JAX's `NamedSharding`
over a "batch" mesh axis), each process holds its own shards, and gathered results are
exchanged between processes (tests/test_distributed.py). Either way one program is compiled
per chunk shape (the last chunk is padded with copies of the batch's last member and trimmed),
and each is dispatched before its predecessor's results are copied back, so the devices are
not idle while results come back.
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._progress import progress_bar


def run_batch(fn, inputs, *, chunk_size: int | None = None, devices=None, progress: bool = True,
              gather: bool = True):
    """`jax.vmap(fn)(inputs)`, computed chunk by chunk and sharded across `devices`.

    - `fn`: a function of one member (a pytree of arrays) returning a pytree of arrays.
    - `inputs`: a pytree whose leaves share a leading batch axis of size B.
    - `chunk_size`: members per chunk (rounded up to a multiple of the number of devices);
      default: as many as fit in a quarter of the devices' free memory (`default_chunk_size`),
      at most the whole batch.
    - `devices`: default `jax.local_devices()`; `progress`: a progress bar over chunks (tqdm; drawn once the work has run 2 s).
      Several processes (`jax.distributed`): every one calls `run_batch` with the same `fn`,
      `inputs` and `jax.devices()`.
    - `gather`: return NumPy arrays on the host (device memory holds one chunk at a time; with
      several processes every one receives the whole batch); False keeps the results on the
      devices, sharded along the batch axis (each process holds its own shards).

    Returns once the results are computed. A process of a distributed run that dies while
    results are exchanged makes the others raise `ConnectionError`, not wait for it.

    The compiled program is kept per (`fn`, devices): pass the same function object (not a new
    lambda) to call again without compiling."""
    leaves, treedef = jax.tree.flatten(inputs)
    if not leaves:
        raise ValueError("run_batch: `inputs` has no arrays to map over")
    sizes = {np.shape(leaf)[0] if np.ndim(leaf) else None for leaf in leaves}
    if len(sizes) != 1 or None in sizes:
        raise ValueError(f"run_batch: every leaf of `inputs` needs the same leading batch axis, "
                         f"got leading sizes {sorted(sizes, key=str)}")
    size = sizes.pop()
    if size == 0:
        raise ValueError("run_batch: the batch is empty")
    devices = tuple(jax.local_devices() if devices is None else devices)
    count = len(devices)
    member = jax.tree.unflatten(treedef, [jax.ShapeDtypeStruct(np.shape(leaf)[1:], jnp.result_type(leaf))
                                          for leaf in leaves])
    chunk = default_chunk_size(fn, member, devices) if chunk_size is None else int(chunk_size)
    if chunk < 1:
        raise ValueError(f"run_batch: chunk_size must be a positive int, got {chunk_size}")
    chunk = -(-min(chunk, size) // count) * count  # a multiple of the device count
    with _failures_named(fn, member, chunk):
        if gather and _one_process(devices):
            result = _per_device_queues(fn, leaves, treedef, size, chunk // count, devices, progress)
        else:
            result = _sharded_chunks(fn, leaves, treedef, size, chunk, devices, progress, gather)
    return result


def _per_device_queues(fn, leaves, treedef, size, piece, devices, progress):
    """Results to this host from this process's devices: each device runs its own queue of
    `piece`-member slices in its own thread (one program, `vmap(fn)`, for every slice; the
    last slice padded), taking the next slice as soon as its previous one is dispatched, so no
    device waits for another's slowest member. Slices run where they are taken, results land
    in place: the same values as one `vmap` (each member's computation is its own)."""
    starts = list(range(0, size, piece))
    taken = iter(enumerate(starts))
    lock, failed = threading.Lock(), []
    results = [None] * len(starts)
    bar = progress_bar(progress, len(starts), "batch", "chunk")
    # JAX's context managers (`jax.enable_x64(...)`, `jax.default_matmul_precision(...)`) are
    # thread-local: the workers place and trace under the caller's
    x64, precision = jax.config.jax_enable_x64, jax.config.jax_default_matmul_precision

    def collect(index, out, used):
        results[index] = jax.tree.map(lambda a: np.asarray(a)[:used], out)
        if bar:
            with lock:
                bar.update(1)

    def drain(device):
        program, pending = _device_program(fn, device), None
        try:
            with jax.enable_x64(x64), jax.default_matmul_precision(precision):
                while not failed:
                    with lock:
                        index, start = next(taken, (None, None))
                    if index is None:
                        break
                    stop = min(start + piece, size)
                    slice_ = jax.device_put(_members(leaves, treedef, start, stop, piece), device)
                    out = program(slice_)  # dispatched; runs while the previous slice is copied back
                    if pending is not None:
                        collect(*pending)
                    pending = (index, out, stop - start)
                if pending is not None:
                    collect(*pending)
        except BaseException as error:  # noqa: BLE001 -- re-raised in the caller's thread
            failed.append(error)

    workers = [threading.Thread(target=drain, args=(device,), daemon=True) for device in devices]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    if bar:
        bar.close()
    if failed:
        raise failed[0]
    return jax.tree.map(lambda *parts: np.concatenate(parts), *results)


def _sharded_chunks(fn, leaves, treedef, size, chunk, devices, progress, gather):
    """Every chunk one program over all `devices` (several processes, or results left on the
    devices): dispatched ahead of the host copies of its predecessor's results."""
    mapped, sharding = _program(fn, devices)
    starts = range(0, size, chunk)
    bar = progress_bar(progress, len(starts), "batch", "chunk")
    pending, results = None, []
    for start in starts:
        stop = min(start + chunk, size)
        piece = jax.device_put(_members(leaves, treedef, start, stop, chunk), sharding)
        out = mapped(piece)  # dispatched; runs while the previous chunk is copied back
        if pending is not None:
            results.append(_collect(*pending, gather))
            if bar:
                bar.update(1)
        pending = (out, stop - start)
    results.append(_collect(*pending, gather))
    if gather:
        result = jax.tree.map(lambda *parts: np.concatenate(parts), *results)
    else:
        result = jax.block_until_ready(jax.tree.map(
            lambda *parts: jnp.concatenate(parts) if len(parts) > 1 else parts[0], *results))
    if bar:
        bar.update(1)
        bar.close()
    return result


MEMORY_FACTOR = 3  # a member's live memory over its inputs, outputs and largest value (copies)


def member_bytes(fn, member) -> int:
    """Estimated device memory of one member: `MEMORY_FACTOR` x (its inputs + its outputs +
    the largest value computed on the way, e.g. a simulation's trajectory buffers), from the
    traced program without running it; kept per function and shapes."""
    leaves, treedef = jax.tree.flatten(member)
    return _member_bytes(fn, treedef, tuple(leaves))


@functools.lru_cache(maxsize=64)
def _member_bytes(fn, treedef, leaves) -> int:
    closed = jax.make_jaxpr(lambda m: fn(m))(jax.tree.unflatten(treedef, leaves))
    ends = sum(_bytes(v.aval) for v in (*closed.jaxpr.invars, *closed.jaxpr.outvars))
    return MEMORY_FACTOR * max(ends + _largest_value(closed.jaxpr), 1)


def _bytes(aval) -> int:
    return int(np.prod(getattr(aval, "shape", ()))) * np.dtype(getattr(aval, "dtype", np.uint8)).itemsize


def _largest_value(jaxpr) -> int:
    """Bytes of the largest array any equation of `jaxpr` (or of its sub-programs) makes."""
    largest = 0
    for eqn in jaxpr.eqns:
        largest = max([largest, *(_bytes(v.aval) for v in eqn.outvars)])
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            largest = max(largest, _largest_value(sub))
    return largest


def free_memory(device) -> int:
    """Bytes free on `device` (its allocator's limit minus use; on the CPU the host's
    available memory)."""
    stats = device.memory_stats()
    if stats and "bytes_limit" in stats:
        return int(stats["bytes_limit"] - stats.get("bytes_in_use", 0))
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def default_chunk_size(fn, member, devices) -> int:
    """Members per chunk that fit in a quarter of the least free memory of `devices`, per
    device (at least one per device). `devices` of several processes: each measures its own,
    and all take the least (every process must run the same chunks)."""
    here = [d for d in devices if d.process_index == jax.process_index()]
    per_device = min(free_memory(d) for d in here) // 4 // member_bytes(fn, member)
    if len(here) < len(devices):
        per_device = multihost_utils.process_allgather(np.int64(per_device)).min()
    return max(int(per_device), 1) * len(devices)


# What XLA's errors say when a collective's peer process has died: Gloo (CPU) and the
# distributed runtime's health check.
LOST_PEER = ("closed by peer", "reset by peer", "heartbeat timeout", "stopped sending heartbeats")


@contextlib.contextmanager
def _failures_named(fn, member, chunk):
    """Re-raise XLA's bare errors as named ones: RESOURCE_EXHAUSTED as a MemoryError naming the
    remedies; a lost peer of a distributed run as a ConnectionError."""
    try:
        yield
    except jax.errors.JaxRuntimeError as error:
        text = str(error)
        if "RESOURCE_EXHAUSTED" in text:
            raise MemoryError(f"run_batch: a chunk of {chunk} members did not fit in device memory (about "
                              f"{member_bytes(fn, member):,} bytes per member, estimated): pass a smaller "
                              "chunk_size, or return less per member (simulate(..., dense=False) keeps only "
                              "the final state)") from error
        if jax.process_count() > 1 and any(sign in text for sign in LOST_PEER):
            raise ConnectionError(f"run_batch: another process of this distributed run (this is process "
                                  f"{jax.process_index()} of {jax.process_count()}) died while results were "
                                  f"exchanged ({text.splitlines()[0]}); a process cannot rejoin a "
                                  "jax.distributed run: start every process again") from error
        raise


@functools.lru_cache(maxsize=64)
def _program(fn, devices):
    """The jitted, sharded `vmap(fn)` for these devices (kept: one compilation per chunk shape).
    On several devices each runs `vmap(fn)` on its own slice (`shard_map`): a loop inside `fn`
    (an adaptive simulation's `while`) then stops per device, without the all-reduce of its
    condition across devices that one global program needs every iteration."""
    sharding = batch_sharding(devices)
    mapped = jax.vmap(fn)
    if len(devices) > 1:  # check_vma=False: the event search's custom_vmap has no replication rule
        mapped = jax.shard_map(mapped, mesh=sharding.mesh, in_specs=sharding.spec, out_specs=sharding.spec,
                               check_vma=False)
    return jax.jit(mapped, in_shardings=sharding, out_shardings=sharding), sharding


def batch_sharding(devices) -> NamedSharding:
    """Arrays split along their first axis across `devices` (a one-axis "batch" mesh)."""
    return NamedSharding(Mesh(np.asarray(devices), ("batch",)), PartitionSpec("batch"))


def padded(x, chunk):
    """x (n, ...) with its last row repeated up to `chunk` rows."""
    missing = chunk - x.shape[0]
    if missing == 0:
        return x
    tail = jnp.repeat(x[-1:], missing, axis=0) if isinstance(x, jax.Array) else np.repeat(x[-1:], missing, axis=0)
    return (jnp if isinstance(x, jax.Array) else np).concatenate([x, tail])


def _members(leaves, treedef, start, stop, length):
    """Members start..stop of the inputs, padded to `length` (device arrays stay where they
    are, the rest become NumPy)."""
    return jax.tree.unflatten(treedef, [padded(leaf[start:stop] if isinstance(leaf, jax.Array)
                                               else np.asarray(leaf[start:stop]), length) for leaf in leaves])


@functools.lru_cache(maxsize=64)
def _device_program(fn, device):
    """`jit(vmap(fn))` on `device` (kept per function and device). An accelerator writes the
    results to pinned host memory itself: a separate copy would share the device-to-host queue
    with the next slice's loop, whose condition is read back every iteration, and stall it
    (two H200s, 10^7 pendulums in slices of 10^6: 0.68 s against 0.74 s on one device)."""
    kind = None if device.platform == "cpu" else "pinned_host"
    return jax.jit(jax.vmap(fn), out_shardings=jax.sharding.SingleDeviceSharding(device, memory_kind=kind))


def _one_process(devices) -> bool:
    return all(d.process_index == jax.process_index() for d in devices)


def _collect(out, used, gather):
    """A chunk's first `used` results: NumPy arrays of the whole chunk on this host (from every
    process, by an all-gather over JAX's collectives, where the chunk spans several), or the
    sharded arrays."""
    if gather:
        return jax.tree.map(lambda a: np.asarray(a if a.is_fully_addressable
                                                 else multihost_utils.process_allgather(a, tiled=True))[:used], out)
    return jax.tree.map(lambda a: a[:used] if used < a.shape[0] else a, out)
