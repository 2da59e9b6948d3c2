r"""Periodic orbits: limit cycles of continuous systems by shooting, of hybrid systems as
fixed points of the return map through their events (Underactuated, ch. 4 and 13).

Continuous: unknowns $(x_0, T)$ with $\phi_T(x_0) = x_0$ and the phase fixed on the section
through the guess orthogonal to the flow there, $f(x_g)^T (x_0 - x_g) = 0$. Newton's method on

$$\begin{bmatrix} \Phi - I & f(\phi_T(x_0)) \\ f(x_g)^T & 0 \end{bmatrix}
  \begin{bmatrix} \delta x \\ \delta T \end{bmatrix} = -\begin{bmatrix} \phi_T(x_0) - x_0 \\
  f(x_g)^T (x_0 - x_g) \end{bmatrix},$$

$\Phi = \partial\phi_T / \partial x_0$ (the monodromy matrix at convergence) by forward-mode
autodiff through `simulate`. Floquet multipliers: the eigenvalues of $\Phi$ (one is 1, along
the flow).

Hybrid: the return map $P(x)$ takes the state just after an event to the state just after
the `events_per_period`-th next one (through the events' resets, differentiated with the
event times); Newton on $P(x) = x$ with $DP - I$. Its eigenvalues are the return map's
(one is 0 when the event surface is a section: the flow direction is factored out).

Both solves run in one jitted `lax.while_loop` (Newton steps with backtracking on |F|). The result
is differentiable in forward mode (`jax.jacfwd`, `jax.jvp`) with respect to the system's
parameters by the implicit function theorem: one last Newton step is taken from the converged
point held constant, whose derivative is $-(DF)^{-1}\partial F/\partial p$.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..simulation import SimulatedTrajectory, simulate
from ..simulation._inputs import leaves_to_arrays
from ..systems import HybridSystem, System


class LimitCycle(eqx.Module):
    """What `limit_cycle` found: `period`; `state`, a state on the orbit (for a hybrid system,
    just after an event); `monodromy`, the derivative of the flow over one period (of the
    return map, for a hybrid system) at `state`; `floquet_multipliers`, its eigenvalues, largest
    modulus first (the orbit is locally stable when all but the trivial one lie inside the unit
    circle); `trajectory`, one period simulated from `state`; `residual`, the final Newton
    residual (max norm); `iterations`, the Newton steps taken."""

    period: jax.Array
    state: jax.Array
    monodromy: jax.Array
    floquet_multipliers: jax.Array
    trajectory: SimulatedTrajectory
    residual: jax.Array
    iterations: jax.Array


class LimitCycleError(RuntimeError):
    """Newton's method did not converge, or the simulations it needs failed."""


def limit_cycle(system: System, x_guess, period_guess, *, events_per_period: int = 1,
                tol: float | None = None, max_iterations: int = 30, rtol: float | None = None,
                atol: float | None = None, max_steps: int = 16384) -> LimitCycle:
    """A periodic orbit of `system` (inputs held at 0) near `x_guess`, with period near
    `period_guess` (for a hybrid system, the guess bounds the time searched for the events:
    3 x `period_guess`). `tol`: the Newton residual at which to stop (max norm); `rtol`,
    `atol`, `max_steps`: of the simulations. Defaults follow the float width: 1e-10 and 1e-12
    in float64, 1e-4 and 1e-6 in float32 (JAX's default; it cannot resolve more). Raises
    `LimitCycleError` when Newton does not converge (outside `jit`; inside, check
    `result.residual`)."""
    if not isinstance(system, System):
        raise TypeError(f"limit_cycle needs a jaxdrake.System, got {type(system).__name__}")
    hybrid = isinstance(system, HybridSystem)
    if hybrid and not system.transitions:
        raise ValueError(f"{system.name} is hybrid but has no transitions: it has no return map")
    if not hybrid and system.num_discrete_states:
        raise ValueError(f"{system.name} has discrete states; limit_cycle handles continuous and "
                         "hybrid systems")
    if not (isinstance(events_per_period, int) and events_per_period >= 1):
        raise ValueError(f"events_per_period must be a positive int, got {events_per_period!r}")
    x_guess = jnp.asarray(x_guess, jnp.result_type(float))
    if hybrid and x_guess.shape == (system.modes[system.initial_mode].num_states,):
        x_guess = system.pad_state(system.initial_mode, x_guess)
    if x_guess.shape != (system.num_states,):
        raise ValueError(f"x_guess has shape {x_guess.shape}; {system.name} has {system.num_states} states")
    wide = jnp.finfo(x_guess.dtype).bits >= 64
    tol = (1e-10 if wide else 1e-4) if tol is None else tol
    rtol = (1e-12 if wide else 1e-6) if rtol is None else rtol
    atol = (1e-12 if wide else 1e-6) if atol is None else atol
    options = dict(rtol=rtol, atol=atol, max_steps=max_steps)
    system = leaves_to_arrays(system, x_guess.dtype)  # new parameter values: no new compilation
    result = _solve(system, x_guess, jnp.asarray(period_guess, x_guess.dtype), jnp.asarray(tol, x_guess.dtype),
                    max_iterations, events_per_period if hybrid else 0, options)
    if isinstance(result.residual, jax.core.Tracer):
        return result
    if not float(result.residual) <= tol:
        raise LimitCycleError(
            f"limit_cycle of {system.name}: Newton's method stopped at residual {float(result.residual):.3g} "
            f"after {int(result.iterations)} iterations (tol {tol:g}); start nearer the orbit, give a "
            "better period_guess, or check that the simulations succeed (simulate from x_guess)")
    if not hybrid and float(jnp.max(jnp.abs(_field(system, result.state)))) < 1e3 * tol:
        raise LimitCycleError(
            f"limit_cycle of {system.name}: Newton's method converged to an equilibrium, "
            f"x = {np.asarray(result.state)}, which is 'periodic' with any period; start on the orbit")
    return result


@eqx.filter_jit
def _solve(system, x_guess, period_guess, tol, max_iterations, events, options):
    """The Newton loop, then the implicit-function step and the orbit (see the module doc)."""
    n = x_guess.shape[0]

    if events:
        def residual(z, system):
            return _return_map(system, z, 3 * period_guess, events, options)[0] - z

        def residual_and_jacobian(z, system=system):
            def P(x):
                x_next, period = _return_map(system, x, 3 * period_guess, events, options)
                return x_next, (x_next, period)
            DP, (x_next, period) = jax.jacfwd(P, has_aux=True)(z)
            return x_next - z, DP - jnp.eye(n, dtype=z.dtype), period, DP
        z0 = x_guess
    else:
        section = _field(system, x_guess)

        def residual(z, system):
            x, T = z[:n], z[n]
            F = jnp.concatenate([_flow(system, x, T, options) - x, jnp.atleast_1d(section @ (x - x_guess))])
            return jnp.where(T > 0, F, jnp.nan)

        def residual_and_jacobian(z, system=system):
            x, T = z[:n], z[n]
            def flow(x_):
                x_end = _flow(system, x_, T, options)
                return x_end, x_end
            Phi, x_end = jax.jacfwd(flow, has_aux=True)(x)
            F = jnp.concatenate([x_end - x, jnp.atleast_1d(section @ (x - x_guess))])
            top = jnp.concatenate([Phi - jnp.eye(n, dtype=x.dtype), _field(system, x_end)[:, None]], 1)
            DF = jnp.concatenate([top, jnp.concatenate([section, jnp.zeros(1, x.dtype)])[None]], 0)
            return F, DF, T, Phi
        z0 = jnp.concatenate([x_guess, period_guess[None]])

    held = jax.tree_util.tree_map(lambda a: jax.lax.stop_gradient(a) if eqx.is_array(a) else a, system)

    def newton(carry):  # on the parameters held constant: derivatives come from the last step
        z, _, k = carry
        F, DF, _, _ = residual_and_jacobian(z, held)
        size = jnp.max(jnp.abs(F))
        step = jnp.linalg.solve(DF, -F)

        def halve(trial):  # backtracking: the first of 1, 1/2, 1/4, ... that decreases |F|
            alpha, _, _, j = trial
            z_try = z + alpha * step
            return alpha / 2, z_try, jnp.max(jnp.abs(residual(z_try, held))), j + 1

        def worse(trial):
            alpha, _, size_try, j = trial
            return ~(size_try < (1 - 1e-4 * 2 * alpha) * size) & (j < 12)

        _, z_new, _, _ = jax.lax.while_loop(worse, halve, (jnp.asarray(1.0, z.dtype), z, jnp.inf, 0))
        z_new = jnp.where(jnp.all(jnp.isfinite(z_new)), z_new, z)
        return z_new, size, k + 1

    def keep_going(carry):
        _, residual, k = carry
        return (residual > tol) & (k < max_iterations)

    z, _, iterations = jax.lax.while_loop(keep_going, newton, (jax.lax.stop_gradient(z0), jnp.inf, 0))
    z = jax.lax.stop_gradient(z)
    F, DF, period, monodromy = residual_and_jacobian(z)
    z = z - jnp.linalg.solve(jax.lax.stop_gradient(DF), F)  # the implicit-function step
    state = z[:n]
    period = period if events else z[n]
    multipliers = jnp.linalg.eigvals(monodromy)
    multipliers = multipliers[jnp.argsort(-jnp.abs(multipliers))]
    trajectory = simulate(system, (0.0, period), state, throw=False, autodiff="forward", **options)
    return LimitCycle(period=period, state=state, monodromy=monodromy, floquet_multipliers=multipliers,
                      trajectory=trajectory, residual=jnp.max(jnp.abs(F)), iterations=iterations)


def _field(system, x):
    return system.dynamics(0.0, x, jnp.zeros(system.num_inputs, x.dtype))


def _flow(system, x0, T, options):
    """phi_T(x0); NaN when the simulation failed (Newton then stops with a large residual)."""
    traj = simulate(system, (0.0, T), x0, dense=False, autodiff="forward", throw=False, **options)
    return jnp.where(traj.success, traj.final_state, jnp.nan)


def _return_map(system, x0, horizon, events, options):
    """(state just after the `events`-th event from x0, its time); NaN without that many."""
    traj = simulate(system, (0.0, horizon), x0, dense=False, autodiff="forward", throw=False,
                    max_events=max(events, 8), **options)
    ok = traj.num_events >= events
    return (jnp.where(ok, traj.event_states[events - 1], jnp.nan),
            jnp.where(ok, traj.event_times[events - 1], jnp.nan))
