r"""Luenberger observers (Drake's `LuenbergerObserver`): the plant's model corrected by its
output error,

$$\dot{\hat x} = f(t, \hat x, u) + L\,(y - g(t, \hat x, u))
  \quad\text{(or } \hat x[n+1] = f_d(t, \hat x, u) + L\,(y - g(t, \hat x, u))\text{)},$$

a system whose input is $[u; y]$ (the plant's input and output) and whose output is $\hat x$.
For a linear plant the error $e = x - \hat x$ obeys $\dot e = (A - LC)\,e$: it decays at the
rate of the eigenvalues of $A - LC$.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..systems import Frame, LinearSystem, System
from ..trajectories import Trajectory
from ._checks import as_matrix, check_plant


def observer_input_frame(plant: System) -> Frame:
    """The frame of an estimator's input $[u; y]$: the plant's input coordinates prefixed
    `u.`, then its output coordinates prefixed `y.`."""
    return Frame(f"{plant.name}InputOutput",
                 tuple(f"u.{c}" for c in plant.input_frame.coordinates)
                 + tuple(f"y.{c}" for c in plant.output_frame.coordinates),
                 generic=plant.input_frame.generic and plant.output_frame.generic)


def estimate_frame(plant: System) -> Frame:
    """The frame of $\\hat x$ as an estimator's state: the plant's state coordinates."""
    frame = plant.state_frame
    return Frame(f"{frame.name}Estimate", frame.coordinates, generic=frame.generic)


class LuenbergerObserver(System):
    r"""$\dot{\hat x} = f(t, \hat x, u) + L(t)(y - g(t, \hat x, u))$ for a continuous plant,
    $\hat x[n+1] = f_d(t, \hat x, u) + L(t)(y - g(t, \hat x, u))$ at the period of a discrete
    one; input $[u; y]$, state and output $\hat x$ (in the plant's state frame, so a state
    feedback such as `lqr(...).controller` can follow it in a cascade).

    **Fields:** `plant` (its nominal model, w = 0 for a stochastic plant) and `gain`: L as an
    (n, p) matrix, or a `Trajectory` of vec L(t) (row-major) for a time-varying gain.
    """

    plant: System
    gain: jax.Array | Trajectory

    def __init__(self, plant: System, gain):
        check_plant(plant, "LuenbergerObserver")
        n, p = plant.num_states, plant.num_outputs
        if isinstance(gain, Trajectory):
            if gain.num_states != n * p:
                raise ValueError(f"LuenbergerObserver: the gain trajectory has {gain.num_states} "
                                 f"coordinates, vec L(t) for {plant.name} needs {n} x {p} = {n * p}")
        else:
            gain = jnp.asarray(as_matrix(gain, "LuenbergerObserver", "L", (n, p),
                                         f"the observer gain of {plant.name}"))
        self.plant, self.gain = plant, gain
        discrete = plant.has_discrete_state
        super().__init__(num_continuous_states=0 if discrete else n,
                         num_discrete_states=n if discrete else 0,
                         num_inputs=plant.num_inputs + p, num_outputs=n,
                         sample_time=plant.sample_time if discrete else None,
                         direct_feedthrough=False,
                         time_invariant=plant.time_invariant and not isinstance(gain, Trajectory),
                         input_frame=observer_input_frame(plant), state_frame=estimate_frame(plant),
                         output_frame=plant.state_frame)

    def gain_at(self, t):
        """L(t), (n, p)."""
        if isinstance(self.gain, Trajectory):
            return self.gain.state(t).reshape(self.plant.num_states, self.plant.num_outputs)
        return self.gain

    def _correction(self, t, x_hat, input_output):
        u, y = jnp.split(input_output, [self.plant.num_inputs])
        return u, self.gain_at(t) @ (y - self.plant.output(t, x_hat, u))

    def dynamics(self, t, x_hat, input_output):
        u, correction = self._correction(t, x_hat, input_output)
        return self.plant.dynamics(t, x_hat, u) + correction

    def update(self, t, x_hat, input_output):
        u, correction = self._correction(t, x_hat, input_output)
        return self.plant.update(t, x_hat, u) + correction

    def output(self, t, x_hat, input_output):
        return x_hat

    def initial_state(self):
        return jnp.asarray(self.plant.initial_state())


def luenberger_observer(system: System, L) -> System:
    r"""The observer of `system` with the constant gain `L` (n, p): input $[u; y]$, output
    $\hat x$. A `LinearSystem` plant gives a `LinearSystem` (continuous, or discrete at the
    plant's period): $A_o = A - LC$, $B_o = [B - LD,\ L]$, $C_o = I$, $D_o = 0$; any other
    plant a `LuenbergerObserver` running the plant's own (nonlinear) model."""
    observer = LuenbergerObserver(system, L)
    if not isinstance(system, LinearSystem):
        return observer
    L = observer.gain
    n = system.num_states
    return LinearSystem(system.A - L @ system.C, jnp.concatenate([system.B - L @ system.D, L], axis=1),
                        jnp.eye(n), jnp.zeros((n, observer.num_inputs)), sample_time=system.sample_time,
                        input_frame=observer.input_frame, state_frame=observer.state_frame,
                        output_frame=observer.output_frame)
