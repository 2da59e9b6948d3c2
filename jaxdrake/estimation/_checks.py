"""What every estimator checks at construction: the plant it observes and the covariances it is
given (shapes, symmetry, definiteness), each refusal naming the remedy."""

from __future__ import annotations

import jax
import numpy as np

from .._numbers import array_module
from ..systems import System


def check_plant(system, caller: str, *, stochastic: bool = True) -> None:
    """A named error unless `system` is an initialised, non-hybrid `System` whose states are all
    continuous or all discrete at one sample time (and deterministic, unless `stochastic`)."""
    if not isinstance(system, System):
        raise TypeError(f"{caller} needs a jaxdrake.System, got {type(system).__name__}")
    if system.state_frame is None:
        raise TypeError(f"{system.name} was not initialised as a System: its __init__ must call "
                        "super().__init__(...) to declare its sizes")
    if system.is_hybrid:
        raise ValueError(f"{caller}: {system.name} is hybrid; estimate one mode (or the nominal "
                         "system) instead")
    if system.has_continuous_state and system.has_discrete_state:
        raise ValueError(f"{caller}: {system.name} mixes continuous and discrete states; estimate "
                         "a plain continuous or discrete model")
    if system.has_discrete_state and system.sample_time is None:
        raise ValueError(f"{caller}: {system.name} has several sample times; estimate a "
                         "single-rate model")
    if system.is_stochastic and not stochastic:
        raise ValueError(f"{caller}: {system.name} is stochastic, but {caller} models additive "
                         "noise: give the deterministic model and the noise covariances W, V "
                         "(for x+ = f(x, u) + G w, W = G G^T)")


def as_matrix(M, caller: str, label: str, shape: tuple[int, int], meaning: str):
    """M as a (numpy, or JAX when traced) float matrix of `shape`; a scalar is a 1x1 matrix."""
    xp = array_module(M)
    M = xp.atleast_2d(xp.asarray(M, dtype=float))
    if M.shape != shape:
        raise ValueError(f"{caller}: {label} ({meaning}) must have shape {shape}, got {M.shape}")
    return M


def check_covariance(caller: str, label: str, M, *, definite: bool, meaning: str) -> None:
    """Refuse a matrix that cannot be a covariance: non-finite, not symmetric, or with a
    negative eigenvalue (`definite`: any eigenvalue <= 0). Traced matrices are not checked."""
    if isinstance(M, jax.core.Tracer) or M.size == 0:
        return
    M = np.asarray(M, float)
    if not np.all(np.isfinite(M)):
        raise ValueError(f"{caller}: {label} ({meaning}) has non-finite entries")
    scale = max(1.0, float(np.abs(M).max()))
    if not np.allclose(M, M.T, rtol=1e-10, atol=1e-12 * scale):
        raise ValueError(f"{caller}: {label} ({meaning}) must be symmetric (use ({label} + {label}.T) / 2)")
    least = float(np.linalg.eigvalsh(M).min())
    if definite and least <= 1e-14 * scale:
        raise ValueError(f"{caller}: {label} ({meaning}) must be positive definite (its least "
                         f"eigenvalue is {least:.3g}): every measurement needs some noise; add a "
                         "small variance to its diagonal")
    if least < -1e-10 * scale:
        raise ValueError(f"{caller}: {label} ({meaning}) must be positive semidefinite (its least "
                         f"eigenvalue is {least:.3g}): a covariance has no negative variance; build "
                         "it as G @ G.T or a diagonal of variances")
