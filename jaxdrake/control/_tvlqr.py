r"""Finite-horizon, time-varying LQR along a nominal trajectory (Underactuated ch. 8;
Drake's `FiniteHorizonLinearQuadraticRegulator`).

About a nominal $x_0(t), u_0(t)$ on $[t_0, t_f]$ the deviations obey
$\dot{\tilde x} = A(t)\tilde x + B(t)\tilde u$ with $A, B$ the Jacobians of $f$ along the
nominal. The cost $\tilde x(t_f)^T Q_f \tilde x(t_f) + \int \tilde x^T Q \tilde x +
\tilde u^T R \tilde u + 2\tilde x^T N \tilde u\,dt$ has the cost-to-go $\tilde x^T S(t) \tilde x$,

$$-\dot S = Q + S A + A^T S - (S B + N) R^{-1} (B^T S + N^T),\qquad S(t_f) = Q_f,$$

integrated backward by `simulate` (in the reversed time $\tau = t_f - t$), and the gain
$K(t) = R^{-1}(B^T S + N^T)$; the controller is $u = u_0(t) - K(t)(x - x_0(t))$.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..simulation import SimulatedTrajectory, simulate
from ..systems import System
from ..trajectories import Trajectory
from ._lqr import check_cost_weights

def nominal_at(nominal, t):
    """A nominal signal at time t: a `Trajectory` (its state) or a constant array."""
    return nominal.state(t) if isinstance(nominal, (Trajectory, SimulatedTrajectory)) else nominal


def _jacobians(plant, t, x_nominal, u_nominal):
    x0, u0 = nominal_at(x_nominal, t), nominal_at(u_nominal, t)
    return jax.jacfwd(plant.dynamics, argnums=(1, 2))(t, x0, u0)


def _riccati_rhs(tau, s, u, params):
    """d vec(S) / d tau in the reversed time tau = t_f - t."""
    plant, x_nominal, u_nominal, Q, R, N, tf = params
    n = Q.shape[0]
    S = s.reshape(n, n)  # symmetric: S(tf) is, and so is every derivative below
    A, B = _jacobians(plant, tf - tau, x_nominal, u_nominal)
    SBN = S @ B + N
    dS = Q + S @ A + A.T @ S - SBN @ jnp.linalg.solve(R, SBN.T)
    return ((dS + dS.T) / 2).reshape(-1)


def _tracking_output(t, _, plant_state, params):
    K, x_nominal, u_nominal = params
    gain = K.state(t).reshape(-1, plant_state.shape[0])
    return nominal_at(u_nominal, t) - gain @ (plant_state - nominal_at(x_nominal, t))


class FiniteHorizonLQRResult(eqx.Module):
    """`S_trajectory` (vec S(t), row-major), `K_trajectory` (vec K(t)), the nominal, and the
    `controller` $u = u_0(t) - K(t)(x - x_0(t))$; `S(t)`, `K(t)` give the matrices."""

    S_trajectory: Trajectory
    K_trajectory: Trajectory
    x_nominal: object
    u_nominal: object
    controller: System
    num_states: int = eqx.field(static=True)

    def S(self, t):
        n = self.num_states
        return self.S_trajectory.state(t).reshape(jnp.shape(t) + (n, n))

    def K(self, t):
        n = self.num_states
        return self.K_trajectory.state(t).reshape(jnp.shape(t) + (-1, n))


@eqx.filter_jit  # compiled once per structure: a second call costs milliseconds
def _cost_to_go_and_gain(backward, system, x_nominal, u_nominal, R, N, tf):
    """S(t) from the backward solution of tau = tf - t, and K(t) = R^-1 (B^T S + N^T) as
    quartic pieces through the exact gain (K(t) is not polynomial)."""
    S = backward.reversed_in_time(tf)
    n = system.num_states

    def gain_at(t, s):
        _, B = _jacobians(system, t, x_nominal, u_nominal)
        return jnp.linalg.solve(R, B.T @ s.reshape(n, n) + N.T).reshape(-1)

    return S, S.interpolate(gain_at)


def _as_nominal(value, size, label, name):
    if isinstance(value, (Trajectory, SimulatedTrajectory)):
        if value.num_states != size:
            raise ValueError(f"finite_horizon_lqr: the nominal {label} trajectory has {value.num_states} "
                             f"coordinates, {name} needs {size}")
        return value
    return jnp.zeros(size) if value is None else jnp.asarray(value, float).reshape(size)


def finite_horizon_lqr(system: System, Q, R, tspan, *, Qf=None, x_nominal=None, u_nominal=None,
                       N=None, rtol=1e-8, atol=1e-10, max_steps: int = 4096) -> FiniteHorizonLQRResult:
    """The time-varying LQR of a continuous `system` on `tspan = (t0, tf)` about a nominal
    state and input (each a `Trajectory` — simulated, from samples, or from trajectory
    optimization — or a constant array; default the origin and u = 0). `Qf` is the final
    cost (default zero). The Riccati ODE is integrated backward with `simulate` at
    `rtol`/`atol`; differentiable with respect to Q, R, Qf and the plant's parameters."""
    if not isinstance(system, System):
        raise TypeError(f"finite_horizon_lqr needs a jaxdrake.System, got {type(system).__name__}")
    if system.has_discrete_state or system.is_hybrid or system.is_stochastic:
        raise ValueError(f"finite_horizon_lqr: {system.name} must be a continuous, deterministic, "
                         "non-hybrid system (linearize a mode or the nominal system)")
    n, m = system.num_states, system.num_inputs
    t0, tf = (jnp.asarray(t, float) for t in tspan)
    Q, R = jnp.atleast_2d(jnp.asarray(Q, float)), jnp.atleast_2d(jnp.asarray(R, float))
    Qf = jnp.zeros((n, n)) if Qf is None else jnp.atleast_2d(jnp.asarray(Qf, float))
    N = jnp.zeros((n, m)) if N is None else jnp.asarray(N, float).reshape(n, m)
    for label, M, size in (("Q", Q, n), ("R", R, m), ("Qf", Qf, n)):
        if M.shape != (size, size):
            raise ValueError(f"finite_horizon_lqr: {label} must be ({size}, {size}) for {system.name}, got {M.shape}")
    check_cost_weights("finite_horizon_lqr", Q, R, N, Qf)
    x_nominal = _as_nominal(x_nominal, n, "state", system.name)
    u_nominal = _as_nominal(u_nominal, m, "input", system.name)

    riccati = System.from_functions(_riccati_rhs, num_states=n * n,
                                    params=(system, x_nominal, u_nominal, Q, R, N, tf),
                                    time_invariant=False)
    backward = simulate(riccati, (0.0, tf - t0), ((Qf + Qf.T) / 2).reshape(-1),
                        rtol=rtol, atol=atol, max_steps=max_steps)
    S, K = _cost_to_go_and_gain(backward.state_trajectory, system, x_nominal, u_nominal, R, N, tf)
    controller = System.from_functions(
        output=_tracking_output, num_states=0, num_inputs=n, num_outputs=m,
        params=(K, x_nominal, u_nominal), time_invariant=False,
        input_frame=system.state_frame, output_frame=system.input_frame)
    return FiniteHorizonLQRResult(S, K, x_nominal, u_nominal, controller, n)
