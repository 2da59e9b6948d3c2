"""Which array module a computation on given values should use."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def array_module(*values):
    """numpy for concrete numbers (fast, nothing compiled: building models and programs),
    jax.numpy once a JAX array or tracer is involved (under jit / vmap / grad)."""
    return jnp if any(isinstance(v, jax.Array) for v in values) else np
