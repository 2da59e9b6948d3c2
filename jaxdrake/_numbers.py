"""Which array module a computation on given values should use, and host numbers to arrays."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def array_module(*values):
    """numpy for concrete numbers (fast, nothing compiled: building models and programs),
    jax.numpy once a JAX array or tracer is involved (under jit / vmap / grad)."""
    return jnp if any(isinstance(v, jax.Array) for v in values) else np


def device_array(values, dtype=None):
    """`values` as a JAX array: host numbers through `jax.device_put`, which compiles nothing
    (`jnp.asarray` of a numpy array compiles a staging program per new shape, ~10-25 ms each
    in a fresh process); JAX arrays and tracers through `jnp.asarray`."""
    if isinstance(values, jax.Array):
        return jnp.asarray(values, dtype)
    return jax.device_put(np.asarray(values, dtype))


def call_argument(values, dtype=None):
    """`values` as an argument of a compiled call: host numbers as numpy arrays (the call
    transfers them with its other arguments, no `device_put` each) of the width JAX would give
    them (float32 without `jax_enable_x64`), JAX arrays and tracers through `jnp.asarray`."""
    if isinstance(values, jax.Array):
        return values if dtype is None or values.dtype == dtype else jnp.asarray(values, dtype)
    values = np.asarray(values, dtype)
    return values.astype(jax.dtypes.canonicalize_dtype(values.dtype), copy=False)
