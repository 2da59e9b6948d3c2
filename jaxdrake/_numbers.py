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
    return _host_array(values, dtype)


MAX_SCALARS = 1024  # device copies of Python numbers kept (the least recently used dropped)
_SCALARS: OrderedDict = OrderedDict()


def scalar_argument(value: float | int, dtype=None):
    """A Python number as an argument of a compiled call: on a CPU backend, from its second
    use on, one device copy per (value, sign, dtype), kept, so that a call repeated from
    Python (the same tolerances, time span and parameters) transfers nothing (a host number
    costs ~5 us a call); at its first use, and on an accelerator backend (where `simulate` from
    Python runs on the host CPU, see its `device`), a numpy scalar: a sweep that passes each
    value once does not pay a `device_put` (~30-130 us) per value."""
    if jax.default_backend() != "cpu":
        return _host_array(value, dtype)
    # the canonical float64 tells whether 64-bit types are on (also in `jax.enable_x64(...)`)
    key = (type(value), value, math.copysign(1.0, value), dtype, jax.dtypes.canonicalize_dtype(np.float64))
    seen = key in _SCALARS
    kept = _SCALARS.pop(key, None)
    if kept is None and seen:
        with jax.ensure_compile_time_eval():  # a concrete array also while tracing, never a tracer
            kept = jax.device_put(_host_array(value, dtype))
    _SCALARS[key] = kept   # None: seen once
    if len(_SCALARS) > MAX_SCALARS:
        _SCALARS.popitem(last=False)
    return _host_array(value, dtype) if kept is None else kept


def _host_array(values, dtype):
    """`values` as a numpy array of `dtype`, or of the width JAX would give it."""
    array = np.asarray(values, dtype)
    return array.astype(jax.dtypes.canonicalize_dtype(array.dtype), copy=False)
