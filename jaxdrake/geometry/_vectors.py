"""Small vector helpers the geometry queries share."""

import jax.numpy as jnp

TINY = 1e-14


def norm_and_direction(v, fallback):
    """(|v|, v / |v|) with `fallback` (a unit vector) as the direction where |v| is ~0,
    differentiable everywhere."""
    sq = jnp.sum(v * v, -1)
    nonzero = sq > TINY * TINY
    safe = jnp.where(nonzero[..., None], v, fallback)
    norm = jnp.sqrt(jnp.sum(safe * safe, -1))
    return jnp.where(nonzero, norm, 0.0), safe / norm[..., None]
