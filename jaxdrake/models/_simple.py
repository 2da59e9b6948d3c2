"""Small plants of the notes: double integrator, Van der Pol, and the appendix-D examples."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..systems import Frame, LinearSystem, StochasticSystem, System


def DoubleIntegrator() -> LinearSystem:
    r"""The double integrator $\ddot q = u$ as a `LinearSystem`; state $[q, \dot q]$, output the state."""
    state = Frame("DoubleIntegratorState", ("q", "qdot"))
    return LinearSystem([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]],
                        input_frame=Frame("DoubleIntegratorInput", ("u",)),
                        state_frame=state, output_frame=state)


class VanDerPol(System):
    r"""The Van der Pol oscillator (Drake's VanDerPolOscillator), state $[q, \dot q]$:

    $$\ddot q + \mu (q^2 - 1)\dot q + q = 0.$$

    Stiff for large $\mu$ (use `solver="rosenbrock23"`). Output: the state.
    """

    mu: float = 1.0

    def __init__(self, mu=1.0):
        self.mu = mu
        state = Frame("VanDerPolState", ("q", "qdot"))
        super().__init__(num_continuous_states=2, direct_feedthrough=False, time_invariant=True,
                         state_frame=state, output_frame=state)

    def dynamics(self, t, x, u):
        q, qdot = x
        return jnp.stack([qdot, -self.mu * (q**2 - 1) * qdot - q])


class SimpleCTExample(System):
    r"""The notes' simple continuous-time system (D.3.1): $\dot x = -x + x^3$, $y = x$."""

    def __init__(self):
        super().__init__(num_continuous_states=1, num_outputs=1, direct_feedthrough=False,
                         time_invariant=True, output_frame=Frame("SimpleCTOutput", ("x",)))

    def dynamics(self, t, x, u):
        return -x + x**3

    def output(self, t, x, u):
        return x


class SimpleDTExample(System):
    r"""The notes' simple discrete-time system (D.3.1): $x[n+1] = x[n]^3$, $y = x$ (dt = 1)."""

    def __init__(self):
        super().__init__(num_discrete_states=1, num_outputs=1, direct_feedthrough=False,
                         time_invariant=True, sample_time=1.0,
                         output_frame=Frame("SimpleDTOutput", ("x",)))

    def update(self, t, x, u):
        return x**3

    def output(self, t, x, u):
        return x


class SimpleMixedCTDTExample(System):
    r"""The notes' mixed example (D.3.1): $x_1(t + t') = x_1(t)^3$ at $t \in \{0, 1, 2, \dots\}$,
    $t' \in (0, 1]$, and $\dot x_2 = -x_2 + x_2^3$; state $[x_1; x_2]$ (discrete first), $y = x$."""

    def __init__(self):
        state = Frame("SimpleMixedState", ("x1", "x2"))
        super().__init__(num_continuous_states=1, num_discrete_states=1, num_outputs=2,
                         direct_feedthrough=False, time_invariant=True, sample_time=1.0,
                         state_frame=state, output_frame=state)

    def update(self, t, x, u):
        return x[:1] ** 3

    def dynamics(self, t, x, u):
        return -x[1:] + x[1:] ** 3

    def output(self, t, x, u):
        return x


class LinearGaussianExample(StochasticSystem):
    r"""The notes' simple continuous-time stochastic system (D.3.1): $\dot x = -x + w$, $y = x$,
    with w band-limited Gaussian white noise of time constant $\tau$ (default 0.01, as there).

    With w held for $\tau$ at $N(0, 1/\tau)$, the state at the instants $k\tau$ follows
    $x_{k+1} = e^{-\tau} x_k + (1 - e^{-\tau}) w_k$, whose stationary variance
    $\frac{1 - e^{-\tau}}{\tau (1 + e^{-\tau})}$ (`stationary_variance`) tends to 1/2, that
    of the white-noise limit, as $\tau \to 0$.
    """

    def __init__(self, noise_time_constant: float = 0.01):
        super().__init__(num_continuous_states=1, num_noise_inputs=1,
                         noise_time_constant=noise_time_constant, direct_feedthrough=False,
                         time_invariant=True, state_frame=Frame("LinearGaussianState", ("x",)))

    def stochastic_dynamics(self, t, x, u, w):
        return -x + w

    def stationary_variance(self) -> float:
        decay = np.exp(-self.noise_time_constant)
        return float((1 - decay) / (self.noise_time_constant * (1 + decay)))
