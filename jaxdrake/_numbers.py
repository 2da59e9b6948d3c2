"""Which array module a computation on given values should use, and host numbers to arrays."""

from __future__ import annotations

import math
from collections import OrderedDict

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
    """`values` as an argument of a compiled call, of the width JAX would give it (float32
    without `jax_enable_x64`): a Python number through `scalar_argument`, other host numbers
    as numpy arrays (the call transfers them with its other arguments, no `device_put` each),
    JAX arrays and tracers through `jnp.asarray`."""
    if isinstance(values, jax.Array):
        return values if dtype is None or values.dtype == dtype else jnp.asarray(values, dtype)
    if type(values) is float or type(values) is int:
        return scalar_argument(values, dtype)
    values = np.asarray(values, dtype)
    return values.astype(jax.dtypes.canonicalize_dtype(values.dtype), copy=False)


MAX_SCALARS = 1024  # device copies of Python numbers kept (the least recently used dropped)
_SCALARS: OrderedDict = OrderedDict()


def scalar_argument(value: float | int, dtype=None):
    """A Python number as an argument of a compiled call: on a CPU backend one device copy per
    (value, sign, dtype), kept, so that a call repeated from Python (the same tolerances, time
    span and parameters) transfers nothing (each host number costs ~5 us a call); elsewhere a
    numpy scalar (`simulate` from Python then runs on the host CPU, see its `device`)."""
    if jax.default_backend() != "cpu":
        array = np.asarray(value, dtype)
        return array.astype(jax.dtypes.canonicalize_dtype(array.dtype), copy=False)
    # the canonical float64 tells whether 64-bit types are on (also in `jax.enable_x64(...)`)
    key = (type(value), value, math.copysign(1.0, value), dtype, jax.dtypes.canonicalize_dtype(np.float64))
    try:
        device = _SCALARS.pop(key)
    except KeyError:
        array = np.asarray(value, dtype)
        with jax.ensure_compile_time_eval():  # a concrete array also while tracing, never a tracer
            device = jax.device_put(array.astype(jax.dtypes.canonicalize_dtype(array.dtype), copy=False))
    _SCALARS[key] = device
    if len(_SCALARS) > MAX_SCALARS:
        _SCALARS.popitem(last=False)
    return device
