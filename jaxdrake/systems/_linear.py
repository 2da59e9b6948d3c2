"""Linear time-invariant systems."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._frame import Frame
from ._system import System


class LinearSystem(System):
    r"""A linear time-invariant system, continuous or discrete.

    $$\dot x = A x + B u \quad\text{(or } x[n+1] = A x[n] + B u[n] \text{ with a sample time)},
      \qquad y = C x + D u.$$

    A, B, C, D are pytree leaves (differentiable); their shapes fix the sizes. Missing C
    means y = x; missing D means zero. `direct_feedthrough` is True when D is not all zeros
    (decided at construction from D's value, so D must not be a tracer then).

    **Arguments:**

    - `A` (n, n), `B` (n, m) or None for no input, `C` (p, n), `D` (p, m).
    - `sample_time`: None for continuous time, else the period of the discrete update.
    - frames and `input_limits` as for `System`.
    """

    A: jax.Array
    B: jax.Array
    C: jax.Array
    D: jax.Array

    def __init__(self, A, B=None, C=None, D=None, *, sample_time: float | None = None,
                 input_limits=None, input_frame: Frame | None = None,
                 state_frame: Frame | None = None, output_frame: Frame | None = None):
        A = jnp.atleast_2d(jnp.asarray(A, dtype=float))
        n = A.shape[0]
        if A.shape != (n, n):
            raise ValueError(f"LinearSystem: A must be square, got shape {A.shape}")
        B = jnp.zeros((n, 0)) if B is None else jnp.asarray(B, dtype=float)
        if B.ndim == 1 and B.shape[0] == n:
            B = B[:, None]  # a single input given as a vector
        if B.ndim != 2 or B.shape[0] != n:
            raise ValueError(f"LinearSystem: B must have shape ({n}, m), got {B.shape}")
        m = B.shape[1]
        C = jnp.eye(n) if C is None else jnp.atleast_2d(jnp.asarray(C, dtype=float))
        if C.ndim != 2 or C.shape[1] != n:
            raise ValueError(f"LinearSystem: C must have shape (p, {n}), got {C.shape}")
        p = C.shape[0]
        D = jnp.zeros((p, m)) if D is None else jnp.asarray(D, dtype=float)
        if D.size == p * m:
            D = D.reshape(p, m)
        if D.shape != (p, m):
            raise ValueError(f"LinearSystem: D must have shape ({p}, {m}), got {D.shape}")
        self.A, self.B, self.C, self.D = A, B, C, D
        discrete = sample_time is not None
        feedthrough = isinstance(D, jax.core.Tracer) or bool(np.any(np.asarray(D) != 0))
        super().__init__(num_continuous_states=0 if discrete else n,
                         num_discrete_states=n if discrete else 0, num_inputs=m, num_outputs=p,
                         sample_time=sample_time, direct_feedthrough=feedthrough,
                         time_invariant=True, input_limits=input_limits, input_frame=input_frame,
                         state_frame=state_frame, output_frame=output_frame)

    @property
    def is_discrete(self) -> bool:
        return self.sample_time is not None

    def dynamics(self, t, x, u):
        return self.A @ x + self.B @ u

    def update(self, t, x, u):
        return self.A @ x + self.B @ u

    def output(self, t, x, u):
        return self.C @ x + self.D @ u
