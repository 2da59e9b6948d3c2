r"""Stochastic systems (notes, D.3.1): dynamics driven by Gaussian white noise.

$$\dot x_c = f_c(t, x, u, w), \qquad x_d^+ = f_d(t, x, u, w), \qquad y = g(t, x, u, w).$$

Continuous-time white noise is approximated, as in the notes, by *band-limited* white noise
with time constant $\tau$: $w$ is held constant on $[k\tau, (k+1)\tau)$ with independent values
$w_k \sim N(0, I/\tau)$ (a spectral density of $I$, like Simulink's band-limited white noise
block). A purely discrete system gets i.i.d. $w[n] \sim N(0, I)$, one per sample. The samples
are drawn from an explicit JAX PRNG key given to `simulate(..., key=key)`, as a function of
(key, k) only: a key always gives the same path, and `jax.vmap` over keys gives Monte-Carlo
batches.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._system import Functions, System, infer_num_outputs


class StochasticSystem(System):
    """A system with noise inputs w (the notes' `StochasticDrakeSystem`).

    Subclass it and override `stochastic_dynamics(t, x, u, w)` (continuous),
    `stochastic_update(t, x, u, w)` (discrete) and `stochastic_output(t, x, u, w)` (default
    y = x); or use `StochasticSystem.from_functions`. The deterministic methods `dynamics`,
    `update` and `output` are the nominal system, with w = 0 (for linearization).

    **Arguments** (keyword), besides those of `System`:

    - `num_noise_inputs`: the size of w.
    - `noise_time_constant`: $\\tau$ of the band-limited white noise (needed with continuous
      states; the notes' example uses 0.01). A discrete-only system draws one w per sample.
    """

    def __init__(self, *, num_noise_inputs: int, noise_time_constant: float | None = None, **kwargs):
        name = type(self).__name__
        if not isinstance(num_noise_inputs, (int, np.integer)) or num_noise_inputs < 1:
            raise ValueError(f"{name}: num_noise_inputs must be a positive int, got {num_noise_inputs!r}")
        continuous = kwargs.get("num_continuous_states", 0) > 0
        if continuous:
            if noise_time_constant is None or not (float(noise_time_constant) > 0
                                                   and np.isfinite(noise_time_constant)):
                raise ValueError(f"{name}: continuous-time noise needs a positive noise_time_constant "
                                 f"(the band-limit of w), got {noise_time_constant!r}")
            tau = float(noise_time_constant)
            group = (num_noise_inputs, tau, 1.0 / np.sqrt(tau))
        else:
            tau = kwargs.get("sample_time") or 1.0
            if noise_time_constant is not None and float(noise_time_constant) != float(tau):
                raise ValueError(f"{name}: a discrete-time system draws one noise sample per sample "
                                 f"time ({tau}); noise_time_constant={noise_time_constant} differs")
            group = (num_noise_inputs, float(tau), 1.0)
        super().__init__(noise_groups=(group,), **kwargs)

    @property
    def noise_time_constant(self) -> float:
        return self.noise_groups[0][1]

    # ----- the methods a system writer overrides ---------------------------------------------

    def stochastic_dynamics(self, t, x, u, w):
        raise NotImplementedError(f"{self.name} has continuous states but does not define "
                                  "stochastic_dynamics()")

    def stochastic_update(self, t, x, u, w):
        raise NotImplementedError(f"{self.name} has discrete states but does not define "
                                  "stochastic_update()")

    def stochastic_output(self, t, x, u, w):
        return System.output(self, t, x, u)

    # ----- the nominal (w = 0) system, and the simulator's view with w ----------------------

    def _zero_noise(self, x):
        return jnp.zeros(self.num_noise_inputs, jnp.asarray(x).dtype)

    def dynamics(self, t, x, u):
        return self.stochastic_dynamics(t, x, u, self._zero_noise(x))

    def update(self, t, x, u):
        return self.stochastic_update(t, x, u, self._zero_noise(x))

    def output(self, t, x, u):
        return self.stochastic_output(t, x, u, self._zero_noise(x))

    def _split(self, u):
        return u[: self.num_inputs], u[self.num_inputs:]

    def mode_dynamics(self, mode, t, x, u):
        return self.stochastic_dynamics(t, x, *self._split(u))

    def mode_update(self, mode, t, x, u, due):
        return self.stochastic_update(t, x, *self._split(u))

    def mode_output(self, mode, t, x, u):
        return self.stochastic_output(t, x, *self._split(u))

    @classmethod
    def from_functions(cls, dynamics: Callable | None = None, update: Callable | None = None,
                       output: Callable | None = None, *, num_states: int, num_noise_inputs: int,
                       num_inputs: int = 0, params: Any = None, initial_state: Any = None,
                       **kwargs) -> "FunctionStochasticSystem":
        """Build a stochastic system from functions `f(t, x, u, w)` (or `f(t, x, u, w, params)`):
        `dynamics` makes it continuous, `update` (with `sample_time`) discrete. The number of
        outputs is that of `output`'s result, as for `System.from_functions`."""
        if (dynamics is None) == (update is None):
            raise ValueError("StochasticSystem.from_functions needs exactly one of dynamics "
                             "(continuous) or update (discrete)")
        discrete = update is not None
        return FunctionStochasticSystem(
            dynamics, update, output, params=params, initial_state=initial_state,
            num_continuous_states=0 if discrete else num_states,
            num_discrete_states=num_states if discrete else 0, num_inputs=num_inputs,
            num_noise_inputs=num_noise_inputs, **kwargs)


class FunctionStochasticSystem(StochasticSystem):
    """A stochastic system from plain functions (see `StochasticSystem.from_functions`)."""

    functions: Functions

    def __init__(self, dynamics_fn=None, update_fn=None, output_fn=None, *, params=None,
                 initial_state=None, **kwargs):
        self.functions = Functions(dynamics_fn, update_fn, output_fn, params, initial_state)
        n = kwargs.get("num_noise_inputs")
        if isinstance(n, (int, np.integer)) and n > 0:  # else StochasticSystem names the problem
            kwargs = infer_num_outputs(self.functions, kwargs, jax.ShapeDtypeStruct((n,), jnp.zeros(()).dtype))
        super().__init__(**kwargs)

    def stochastic_dynamics(self, t, x, u, w):
        return self.functions.call(self.functions.dynamics, t, x, u, w)

    def stochastic_update(self, t, x, u, w):
        return self.functions.call(self.functions.update, t, x, u, w)

    def stochastic_output(self, t, x, u, w):
        if self.functions.output is None:
            return super().stochastic_output(t, x, u, w)
        return self.functions.call(self.functions.output, t, x, u, w)

    def initial_state(self):
        return super().initial_state() if self.functions.x0 is None else self.functions.x0
