r"""Steady-state Kalman filters (Drake's `SteadyStateKalmanFilter`,
`DiscreteTimeSteadyStateKalmanFilter`; python-control's `lqe`, `dlqe`).

About an operating point $(x_0, u_0)$ the plant's deviations obey

$$\dot x = A x + B u + G w, \qquad y = C x + D u + H w + v$$

(or $x[n+1] = \dots$ for a discrete plant), with $w$ white noise of intensity $W$ and $v$ of
intensity $V$, independent. A deterministic plant has additive process noise ($G = I$,
$H = 0$: $W$ is (n, n)); a `StochasticSystem` has its own noise input $w$ in $f$ and $g$
($G = \partial f / \partial w$, $H = \partial g / \partial w$; $W$ defaults to its convention,
$I$: unit spectral density in continuous time, unit covariance per sample in discrete time),
which correlates process and measurement noise. With $W_x = G W G^T$, $V_y = H W H^T + V$,
$N = G W H^T$ the estimation error covariance $P$ solves the dual of LQR's Riccati equation,

$$A P + P A^T - (P C^T + N) V_y^{-1} (C P + N^T) + W_x = 0, \qquad L = (P C^T + N) V_y^{-1},$$

or, discrete (the predictor form: $P$ is the covariance of $x[n]$ given $y[0..n-1]$),

$$P = A P A^T - (A P C^T + N)(C P C^T + V_y)^{-1}(C P A^T + N^T) + W_x, \quad
  L = (A P C^T + N)(C P C^T + V_y)^{-1}.$$

The observer is `luenberger_observer(system, L)`: the plant's model (linear or not) plus
$L\,(y - \hat y)$.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._numbers import device_array
from ..control import solve_continuous_are, solve_discrete_are
from ..systems import LinearSystem, System
from ._checks import as_matrix, check_covariance, check_plant
from ._observer import luenberger_observer


def noise_jacobians(system: System, t, x, u):
    r"""$(f(t, x, u) - [x \text{ if discrete}], A, B, G, C, D, H)$ at (t, x, u) and w = 0:
    the Jacobians of the dynamics (or update) and the output with respect to x, u and the
    noise w ($G = I$, $H = 0$ for a deterministic plant, whose noise is additive)."""
    discrete = system.has_discrete_state
    num_noise = system.num_noise_inputs
    due = jnp.ones(len(system.sample_times), bool)

    def f(x, u, w):
        full = jnp.concatenate([u, w])
        return system.mode_update(0, t, x, full, due) if discrete else system.mode_dynamics(0, t, x, full)

    def g(x, u, w):
        return system.mode_output(0, t, x, jnp.concatenate([u, w]))

    w = jnp.zeros(num_noise, x.dtype)
    A, B, G = jax.jacfwd(f, argnums=(0, 1, 2))(x, u, w)
    C, D, H = jax.jacfwd(g, argnums=(0, 1, 2))(x, u, w)
    if not system.is_stochastic:
        G, H = jnp.eye(x.shape[0], dtype=x.dtype), jnp.zeros((C.shape[0], x.shape[0]), x.dtype)
    return f(x, u, w) - (x if discrete else 0.0), A, B, G, C, D, H


def noise_intensities(G, H, W, V):
    """(W_x, V_y, N) = (G W G^T, H W H^T + V, G W H^T): the process and measurement noise and
    their cross intensity."""
    return G @ W @ G.T, H @ W @ H.T + V, G @ W @ H.T


@eqx.filter_jit  # compiled once per system structure
def _linear_noise_model(system, t, x, u, W, V):
    """(residual, A, B, C, D, W_x, V_y, N) at the operating point."""
    residual, A, B, G, C, D, H = noise_jacobians(system, t, x, u)
    return (residual, A, B, C, D) + noise_intensities(G, H, W, V)


@functools.partial(jax.jit, static_argnums=5)  # compiled once per (n, p): whatever the noise model
def _kalman_gain(A, C, Wx, Vy, N, discrete: bool):
    """(L, P) by the dual Riccati equation: LQR's for (A^T, C^T, W_x, V_y, N)."""
    if discrete:
        P = solve_discrete_are(A.T, C.T, Wx, Vy, N)
        return jnp.linalg.solve(C @ P @ C.T + Vy, C @ P @ A.T + N.T).T, P
    P = solve_continuous_are(A.T, C.T, Wx, Vy, N)
    return jnp.linalg.solve(Vy, C @ P + N.T).T, P


def require_stable_estimator(caller: str, system: System, A, C, L, P) -> None:
    """A ValueError unless P is finite and A - L C stable: the Riccati equation has a
    stabilising solution only when (A, C) is detectable (every mode that does not decay is
    seen by C) and the noise excites every mode on the stability boundary. The poles that did
    not move inside are the undetectable modes (output injection cannot move them)."""
    A, C, L, P = (np.asarray(M) for M in (A, C, L, P))
    discrete = system.has_discrete_state
    finite = np.all(np.isfinite(L)) and np.all(np.isfinite(P))
    poles = np.linalg.eigvals(A - L @ C) if finite else np.linalg.eigvals(A)
    unstable = poles[np.abs(poles) >= 1] if discrete else poles[poles.real >= 0]
    if finite and not unstable.size:
        return
    boundary = "unit circle" if discrete else "imaginary axis"
    raise ValueError(
        f"{caller}: the pair (A, C) of {system.name} is not detectable, or the noise misses a mode "
        f"on the {boundary}: the estimator's poles {np.round(unstable, 6)} do not decay (an "
        f"{'unstable or marginal' if finite else ''} mode that the output y does not see). Measure "
        "more of the state (rows of C), check the operating point, or give every state process "
        "noise (W > 0).")


class KalmanFilterResult(NamedTuple):
    """`L` (gain), `P` (steady-state error covariance), the `linearization` (A, B, C, D), and
    the `observer` system: input $[u; y]$, output $\\hat x$."""

    L: jax.Array
    P: jax.Array
    linearization: LinearSystem
    observer: System


def kalman_filter(system: System, W=None, V=None, x0=None, u0=None, *,
                  check_equilibrium: bool = True, tolerance: float = 1e-6) -> KalmanFilterResult:
    """The steady-state Kalman filter of `system` about (x0, u0) (default: the origin, u = 0),
    continuous or discrete to match the system (see the module doc for the noise model).

    **Arguments:**

    - `W`: the process noise intensity: (n, n) for additive noise on the state of a
      deterministic plant; (k, k) for a `StochasticSystem`'s noise input w (default I, the
      intensity `simulate` draws). Positive semidefinite.
    - `V`: the measurement noise intensity (p, p), positive definite (for a stochastic plant
      it adds to $H W H^T$, may be left out when that is positive definite).
    - `check_equilibrium`, `tolerance`: as for `linearize`: (x0, u0) must be a fixed point.

    **Returns:** a `KalmanFilterResult`. Differentiable with respect to W, V and the plant's
    parameters (the Riccati solvers are).
    """
    caller = "kalman_filter"
    check_plant(system, caller)
    n, m, p, k = system.num_states, system.num_inputs, system.num_outputs, system.num_noise_inputs
    stochastic = system.is_stochastic
    if not stochastic and (W is None or V is None):
        raise ValueError(f"{caller}: {system.name} is deterministic: give W, the covariance of the "
                         f"process noise on its {n} states, and V, that of the noise on its {p} outputs "
                         "(or model the noise in a StochasticSystem)")
    W = np.eye(k) if W is None else as_matrix(W, caller, "W", (k, k) if stochastic else (n, n),
                                              "the process noise intensity")
    V = np.zeros((p, p)) if V is None else as_matrix(V, caller, "V", (p, p), "the measurement noise intensity")
    check_covariance(caller, "W", W, definite=False, meaning="the process noise intensity")
    if not stochastic:
        check_covariance(caller, "V", V, definite=True, meaning="the measurement noise intensity")
    x0 = jnp.zeros(n) if x0 is None else jnp.asarray(x0, float).reshape(n)
    u0 = jnp.zeros(m) if u0 is None else jnp.asarray(u0, float).reshape(m)
    residual, A, B, C, D, Wx, Vy, N = _linear_noise_model(system, device_array(0.0, float), x0, u0, W, V)
    if check_equilibrium and not isinstance(residual, jax.core.Tracer):
        worst = float(np.max(np.abs(np.asarray(residual)))) if residual.size else 0.0
        if worst > tolerance:
            raise ValueError(f"{caller}: ({x0}, {u0}) is not an equilibrium of {system.name}: the "
                             f"{'update moves x by' if system.has_discrete_state else 'derivative is'} up to "
                             f"{worst:.3g} (pass check_equilibrium=False to linearize anyway)")
    if stochastic:
        check_covariance(caller, "V", V, definite=False, meaning="the measurement noise intensity")
        check_covariance(caller, "H W H^T + V", Vy, definite=True,
                         meaning=f"the noise on the outputs of {system.name}, H = dg/dw")
    discrete = system.has_discrete_state
    L, P = _kalman_gain(A, C, Wx, Vy, N, discrete)
    if not isinstance(L, jax.core.Tracer):
        require_stable_estimator(caller, system, A, C, L, P)
    linearization = LinearSystem(A, B.reshape(n, m), C, D.reshape(p, m),
                                 sample_time=system.sample_time if discrete else None,
                                 input_frame=system.input_frame, state_frame=system.state_frame,
                                 output_frame=system.output_frame)
    return KalmanFilterResult(L, P, linearization, luenberger_observer(system, L))
