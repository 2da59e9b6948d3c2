r"""The time-varying (Kalman-Bucy) filter along a nominal trajectory: the dual of
`finite_horizon_lqr`.

About a nominal $x_0(t), u_0(t)$ on $[t_0, t_f]$ the deviations obey $\dot x = A(t) x + B(t) u
+ G(t) w$, $y = C(t) x + D(t) u + H(t) w + v$ (the noise model of `kalman_filter`). The error
covariance runs forward from its initial value,

$$\dot P = A P + P A^T - (P C^T + N) V_y^{-1} (C P + N^T) + W_x, \qquad P(t_0) = P_0,$$

integrated by `simulate`, and the gain is $L(t) = (P C^T + N) V_y^{-1}$; the observer is a
`LuenbergerObserver` with that gain, $\dot{\hat x} = f(t, \hat x, u) + L(t)(y - g(t, \hat x, u))$.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..control import nominal_at
from ..simulation import SimulatedTrajectory, simulate
from ..systems import System
from ..trajectories import Trajectory
from ._checks import as_matrix, check_covariance, check_plant
from ._kalman import noise_intensities, noise_jacobians
from ._observer import LuenbergerObserver


def _as_nominal(value, size, label, name):
    if isinstance(value, (Trajectory, SimulatedTrajectory)):
        if value.num_states != size:
            raise ValueError(f"time_varying_kalman_filter: the nominal {label} trajectory has "
                             f"{value.num_states} coordinates, {name} needs {size}")
        return value
    return jnp.zeros(size) if value is None else jnp.asarray(value, float).reshape(size)


def _noise_model_along(plant, t, x_nominal, u_nominal, W, V):
    """(A, C, W_x, V_y, N) at time t on the nominal."""
    _, A, _, G, C, _, H = noise_jacobians(plant, t, nominal_at(x_nominal, t), nominal_at(u_nominal, t))
    return (A, C) + noise_intensities(G, H, W, V)


def _riccati_rhs(t, p, u, params):
    """d vec(P) / dt."""
    plant, x_nominal, u_nominal, W, V = params
    n = plant.num_states
    P = p.reshape(n, n)  # symmetric: P(t0) is, and so is every derivative below
    A, C, Wx, Vy, N = _noise_model_along(plant, t, x_nominal, u_nominal, W, V)
    PCN = P @ C.T + N
    dP = A @ P + P @ A.T - PCN @ jnp.linalg.solve(Vy, PCN.T) + Wx
    return ((dP + dP.T) / 2).reshape(-1)


class TimeVaryingKalmanFilterResult(eqx.Module):
    """`P_trajectory` (vec P(t), row-major), `L_trajectory` (vec L(t)), the nominal, and the
    `observer` (input $[u; y]$, output $\\hat x$); `P(t)`, `L(t)` give the matrices."""

    P_trajectory: Trajectory
    L_trajectory: Trajectory
    x_nominal: object
    u_nominal: object
    observer: System
    num_states: int = eqx.field(static=True)

    def P(self, t):
        n = self.num_states
        return self.P_trajectory.state(t).reshape(jnp.shape(t) + (n, n))

    def L(self, t):
        n = self.num_states
        return self.L_trajectory.state(t).reshape(jnp.shape(t) + (n, -1))


@eqx.filter_jit  # compiled once per structure: a second call costs milliseconds
def _gain_trajectory(P, plant, x_nominal, u_nominal, W, V):
    """L(t) = (P C^T + N) V_y^-1 as quartic pieces through the exact gain on P's pieces."""
    n = plant.num_states

    def gain_at(t, p):
        _, C, _, Vy, N = _noise_model_along(plant, t, x_nominal, u_nominal, W, V)
        return jnp.linalg.solve(Vy, C @ p.reshape(n, n) + N.T).T.reshape(-1)

    return P.interpolate(gain_at)


def time_varying_kalman_filter(system: System, W, V, tspan, *, P0=None, x_nominal=None, u_nominal=None,
                               rtol=1e-8, atol=1e-10, max_steps: int = 4096) -> TimeVaryingKalmanFilterResult:
    """The time-varying Kalman filter of a continuous `system` on `tspan = (t0, tf)` about a
    nominal state and input (each a `Trajectory` -- simulated, from samples, or from trajectory
    optimization -- or a constant array; default the origin and u = 0). `W`, `V` as for
    `kalman_filter` (for a `StochasticSystem`, None takes its own noise: W = I, V = 0); `P0`
    the initial error covariance (default zero: x(t0) known). The Riccati ODE is integrated
    forward with `simulate` at `rtol`/`atol`; differentiable with respect to W, V, P0 and the
    plant's parameters."""
    caller = "time_varying_kalman_filter"
    check_plant(system, caller)
    if system.has_discrete_state:
        raise ValueError(f"{caller}: {system.name} must be continuous (a discrete plant's "
                         "time-varying filter is the ExtendedKalmanFilter)")
    n, m, p, k = system.num_states, system.num_inputs, system.num_outputs, system.num_noise_inputs
    stochastic = system.is_stochastic
    if not stochastic and (W is None or V is None):
        raise ValueError(f"{caller}: {system.name} is deterministic: give W (n, n) and V (p, p), "
                         "the process and measurement noise intensities")
    W = np.eye(k) if W is None else as_matrix(W, caller, "W", (k, k) if stochastic else (n, n),
                                              "the process noise intensity")
    V = np.zeros((p, p)) if V is None else as_matrix(V, caller, "V", (p, p), "the measurement noise intensity")
    P0 = np.zeros((n, n)) if P0 is None else as_matrix(P0, caller, "P0", (n, n), "the initial error covariance")
    check_covariance(caller, "W", W, definite=False, meaning="the process noise intensity")
    check_covariance(caller, "V", V, definite=not stochastic, meaning="the measurement noise intensity")
    check_covariance(caller, "P0", P0, definite=False, meaning="the initial error covariance")
    x_nominal = _as_nominal(x_nominal, n, "state", system.name)
    u_nominal = _as_nominal(u_nominal, m, "input", system.name)
    W, V, P0 = (jnp.asarray(M, float) for M in (W, V, P0))
    t0, tf = tspan

    riccati = System.from_functions(_riccati_rhs, num_states=n * n,
                                    params=(system, x_nominal, u_nominal, W, V), time_invariant=False)
    forward = simulate(riccati, (t0, tf), ((P0 + P0.T) / 2).reshape(-1), rtol=rtol, atol=atol,
                       max_steps=max_steps)
    P = forward.state_trajectory
    L = _gain_trajectory(P, system, x_nominal, u_nominal, W, V)
    return TimeVaryingKalmanFilterResult(P, L, x_nominal, u_nominal, LuenbergerObserver(system, L), n)
