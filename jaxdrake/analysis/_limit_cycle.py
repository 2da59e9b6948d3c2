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

Both solves run in one jitted `lax.while_loop` (Newton steps with backtracking on |F|), on the
system's parameters held constant. The result is differentiable with respect to them by the
implicit function theorem: one last Newton step is taken from the converged point $z$ (held
constant, as is $DF$), $z^* = z - (DF)^{-1} F(z, p)$, whose derivative is
$dz^*/dp = -(DF)^{-1}\partial F/\partial p$; everything else (the period of a hybrid orbit, the
monodromy matrix, the trajectory) is then evaluated at $z^*$, so that its derivative is the total
one, $\partial g/\partial p + (\partial g/\partial z)\,dz^*/dp$: the period of the rimless
wheel's orbit moves with the slope mostly through the speed on the orbit. Forward mode
(`jax.jacfwd`, `jax.jvp`) by default; `autodiff="reverse"` for `jax.grad` (every output but the
monodromy matrix and the multipliers, whose derivatives are forward-mode only: JAX then names
`while_loop`). First derivatives only: the step holds DF, so a derivative of a derivative
misses terms. In forward mode that step is a `jax.custom_jvp` rule: a call that is not
differentiated returns z* and the period from what the last Newton iteration computed (the
monodromy matrix at z, which differs from z*'s by the residual) and compiles neither the step's
simulation nor its linearization (the rimless wheel's first call 12.3 -> 8.5 s on 2 cores).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..simulation import SimulatedTrajectory, SimulationStatus, simulate
from ..simulation import leaves_to_arrays
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
                atol: float | None = None, max_steps: int = 16384, autodiff: str = "forward") -> LimitCycle:
    """A periodic orbit of `system` (inputs held at 0) near `x_guess`, with period near
    `period_guess` (for a hybrid system, the guess bounds the time searched for the events:
    3 x `period_guess`). `tol`: the Newton residual at which to stop (max norm); `rtol`,
    `atol`, `max_steps`: of the simulations. Defaults follow the float width: 1e-10 and 1e-12
    in float64, 1e-4 and 1e-6 in float32 (JAX's default; it cannot resolve more).
    `autodiff`: how the result is differentiated in the system's parameters (see the module
    doc): `"forward"` (`jax.jacfwd`, `jax.jvp`) or `"reverse"` (`jax.grad`; the monodromy
    matrix and the multipliers stay forward-mode only). Differentiate under `jax.jit` where you
    need a few outputs: an eager `jax.jvp` runs this function's program differentiated as a
    whole, with the tangents of every output, the monodromy's second derivatives through the
    impacts included (the rimless wheel's period: 3.8 s of compiling eager, 1.3 s under
    `jit`, where the unused tangents are dropped). Raises `LimitCycleError` when Newton
    does not converge (outside `jit`; inside, check `result.residual`); for a hybrid system
    called from Python, before Newton's program compiles when the flow from `x_guess` meets too
    few events within 3 x `period_guess` (naming them and when they do come)."""
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
    if autodiff not in ("forward", "reverse"):
        raise ValueError(f"autodiff must be 'forward' or 'reverse', got {autodiff!r}")
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
    if hybrid and not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves((system, x_guess))):
        # a missing event named before Newton's program compiles (~1 s for this check's
        # simulation against ~8 s for the rimless wheel's Newton program)
        _raise_without_events(system, x_guess, float(period_guess), events_per_period, options)
    result = _solve(system, x_guess, jnp.asarray(period_guess, x_guess.dtype), jnp.asarray(tol, x_guess.dtype),
                    max_iterations, events_per_period if hybrid else 0, options, autodiff)
    if isinstance(result.residual, jax.core.Tracer):
        return result
    if not float(result.residual) <= tol:
        raise LimitCycleError(
            f"limit_cycle of {system.name}: Newton's method stopped at residual {float(result.residual):.3g} "
            f"after {int(result.iterations)} iterations (tol {tol:g}); start nearer the orbit, give a "
            "better period_guess, or check that the simulations succeed (simulate from x_guess)")
    # under jax.jvp / jacfwd outside jit the residual is concrete (the Newton loop holds the
    # parameters constant) and the state is not
    if not hybrid and not isinstance(result.state, jax.core.Tracer) and \
            float(jnp.max(jnp.abs(_field(system, result.state)))) < 1e3 * tol:
        raise LimitCycleError(
            f"limit_cycle of {system.name}: Newton's method converged to an equilibrium, "
            f"x = {np.asarray(result.state)}, which is 'periodic' with any period; start on the orbit")
    return result


@eqx.filter_jit
def _solve(system, x_guess, period_guess, tol, max_iterations, events, options, autodiff):
    """The Newton loop on the parameters held constant, then the implicit-function step and
    what is evaluated at its result (see the module doc). `residual(z, system, guess,
    autodiff)` is (F, T), simulated in that autodiff mode; `linearize(z, system, guess)` is
    (F, DF, monodromy, dT/dz, T), differentiated in z by `jacfwd` (forward mode); `guess` is
    (x_guess, period_guess), passed, not closed over (`_at_the_orbit`'s derivative rule traces
    them again)."""
    n = x_guess.shape[0]
    guess = (x_guess, period_guess)

    if events:
        def residual(z, system, guess, autodiff="forward"):
            x_next, t_next = _return_map(system, z, 3 * guess[1], events, options, autodiff)
            return x_next - z, t_next

        def linearize(z, system, guess):
            def P(x):
                out = _return_map(system, x, 3 * guess[1], events, options)
                return out, out
            (DP, dT), (x_next, t_next) = jax.jacfwd(P, has_aux=True)(z)
            return x_next - z, DP - jnp.eye(n, dtype=z.dtype), DP, dT, t_next
        z0 = x_guess
    else:
        def residual(z, system, guess, autodiff="forward"):
            x, T = z[:n], z[n]
            F = jnp.concatenate([_flow(system, x, T, options, autodiff) - x,
                                 jnp.atleast_1d(_field(system, guess[0]) @ (x - guess[0]))])
            return jnp.where(T > 0, F, jnp.nan), T

        def linearize(z, system, guess):
            x, T = z[:n], z[n]
            def flow(x_):
                x_end = _flow(system, x_, T, options)
                return x_end, x_end
            Phi, x_end = jax.jacfwd(flow, has_aux=True)(x)
            section = _field(system, guess[0])  # the phase condition's plane, through the guess
            F = jnp.concatenate([x_end - x, jnp.atleast_1d(section @ (x - guess[0]))])
            top = jnp.concatenate([Phi - jnp.eye(n, dtype=x.dtype), _field(system, x_end)[:, None]], 1)
            DF = jnp.concatenate([top, jnp.concatenate([section, jnp.zeros(1, x.dtype)])[None]], 0)
            return jnp.where(T > 0, F, jnp.nan), DF, Phi, jnp.zeros(n + 1, x.dtype).at[n].set(1), T
        z0 = jnp.concatenate([x_guess, period_guess[None]])

    held = jax.tree_util.tree_map(lambda a: jax.lax.stop_gradient(a) if eqx.is_array(a) else a, system)
    m = z0.shape[0]

    def newton(carry):
        """One Newton step from z, backtracking on |F| (the first of 1, 1/2, 1/4, ... that
        decreases it); the point is linearized once, where it is tried. The first call only
        linearizes at z0 (k = 0: no step yet)."""
        z, linearized, k = carry
        F, DF = linearized[:2]
        size = jnp.max(jnp.abs(F))
        step = jnp.where(k == 0, 0.0, jnp.linalg.solve(DF, -jnp.where(k == 0, 0.0, F)))

        def try_next(trial):
            _, j, _ = trial
            z_try = z + 0.5 ** j * step
            return z_try, j + 1, (z_try, linearize(z_try, held, guess))

        def worse(trial):
            _, j, (_, (F_try, *_)) = trial
            decreased = jnp.max(jnp.abs(F_try)) < (1 - 1e-4 * 2 * 0.5 ** (j - 1)) * size
            return (j == 0) | ((k > 0) & ~decreased & (j < 13))

        start = (z, jnp.asarray(0), (z, linearized))
        _, _, (z_new, linearized_new) = jax.lax.while_loop(worse, try_next, start)
        return z_new, linearized_new, k + 1

    def keep_going(carry):
        _, (F, *_), k = carry
        return (jnp.max(jnp.abs(F)) > tol) & (k <= max_iterations)

    z0 = jax.lax.stop_gradient(z0)
    # (F, DF, monodromy, dT/dz, T) at z, before any step: nothing known (F infinite)
    unknown = (jnp.full(m, jnp.inf, z0.dtype), jnp.eye(m, dtype=z0.dtype), jnp.zeros((n, n), z0.dtype),
               jnp.zeros(m, z0.dtype), jnp.zeros((), z0.dtype))
    z, linearized, evaluations = jax.lax.while_loop(keep_going, newton, (z0, unknown, 0))
    z, linearized = jax.lax.stop_gradient((z, linearized))
    F = linearized[0]
    if autodiff == "forward":
        state, period, monodromy = _at_the_orbit(residual, linearize, n, system, guess, z, linearized)
    else:
        # The implicit-function step (see the module doc), evaluated with the parameters'
        # reverse-mode derivative: F and T through `simulate(..., autodiff)`.
        F, T = residual(z, system, guess, autodiff)
        z_star = z - jnp.linalg.solve(linearized[1], F)
        state, period = z_star[:n], T + linearized[3] @ (z_star - z)  # continuous: T = z[n], dT = e_n
        monodromy = linearize(z_star, system, guess)[2]  # forward mode (jacfwd in z)
    multipliers = jnp.linalg.eigvals(monodromy)
    multipliers = multipliers[jnp.argsort(-jnp.abs(multipliers))]
    trajectory = simulate(system, (0.0, period), state, throw=False, autodiff=autodiff, **options)
    return LimitCycle(period=period, state=state, monodromy=monodromy, floquet_multipliers=multipliers,
                      trajectory=trajectory, residual=jnp.max(jnp.abs(F)), iterations=evaluations - 1)


def _at_the_orbit(residual, linearize, n, system, guess, z, linearized):
    """(state, period, monodromy) at the converged Newton point z with what the loop computed
    there (`linearized`: F, DF, monodromy, dT/dz and T at z, parameters held constant), through
    the implicit-function step $z^* = z - (DF)^{-1} F(z, p)$. Differentiated in the parameters
    (forward mode) by the rule below, which evaluates F and the monodromy at $z^*$ with their
    derivatives in p (the total derivative: through z* as well as directly through p); a call
    that is not differentiated compiles neither (two simulations' worth of program)."""
    params, static = eqx.partition(system, eqx.is_array)

    @jax.custom_jvp
    def at_the_orbit(params, guess, z, linearized):
        F, DF, monodromy, dT, T = linearized
        z_star = z - jnp.linalg.solve(DF, F)
        return z_star[:n], T + dT @ (z_star - z), monodromy  # the monodromy at z: |z* - z| ~ the residual

    @at_the_orbit.defjvp
    def derivative(primals, tangents):
        params, guess, z, (_, DF, _, dT, _) = primals   # z and what the loop computed are held constant
        params_dot, guess_dot = tangents[:2]
        at = lambda p: eqx.combine(p, static)  # noqa: E731
        (F, T), (F_dot, T_dot) = jax.jvp(lambda p, g: residual(z, at(p), g), (params, guess), (params_dot, guess_dot))
        z_star, z_star_dot = z - jnp.linalg.solve(DF, F), -jnp.linalg.solve(DF, F_dot)
        monodromy, monodromy_dot = jax.jvp(lambda z_, p, g: linearize(z_, at(p), g)[2], (z_star, params, guess),
                                           (z_star_dot, params_dot, guess_dot))
        return ((z_star[:n], T + dT @ (z_star - z), monodromy),
                (z_star_dot[:n], T_dot + dT @ z_star_dot, monodromy_dot))

    return at_the_orbit(params, guess, z, linearized)


def _field(system, x):
    return system.dynamics(0.0, x, jnp.zeros(system.num_inputs, x.dtype))


def _flow(system, x0, T, options, autodiff="forward"):
    """phi_T(x0); NaN when the simulation failed (Newton then stops with a large residual)."""
    traj = simulate(system, (0.0, T), x0, dense=False, autodiff=autodiff, throw=False, **options)
    return jnp.where(traj.success, traj.final_state, jnp.nan)


def _return_map(system, x0, horizon, events, options, autodiff="forward"):
    """(state just after the `events`-th event from x0, its time); NaN without that many."""
    traj = simulate(system, (0.0, horizon), x0, dense=False, autodiff=autodiff, throw=False,
                    max_events=max(events, 8), **options)
    ok = traj.num_events >= events
    return (jnp.where(ok, traj.event_states[events - 1], jnp.nan),
            jnp.where(ok, traj.event_times[events - 1], jnp.nan))


def _raise_without_events(system, x_guess, period_guess, events, options):
    """If the flow from x_guess meets fewer than `events` events within 3 x period_guess (the
    horizon of the return map), say so, with the time at which they do come (if they do within
    30 x period_guess); otherwise return."""
    horizon = 3 * period_guess
    traj = simulate(system, (0.0, 10 * horizon), x_guess, dense=False, throw=False,
                    max_events=max(events, 8), **options)
    times = np.asarray(traj.event_times)[: int(traj.num_events)]
    found = int(np.sum(times <= horizon))
    if found >= events:
        return
    names = ", ".join(repr(tr.name) if tr.name else f"transition {k}" for k, tr in enumerate(system.transitions))
    if len(times) >= events:
        remedy = (f"event {events} comes at t = {times[events - 1]:.6g}: give a period_guess near the "
                  "time between events")
    else:
        remedy = (f"none came within {10 * horizon:.6g} s either (simulation status "
                  f"{SimulationStatus(int(traj.status)).name}): start from a state whose flow reaches a guard")
    raise LimitCycleError(
        f"limit_cycle of {system.name}: the return map needs {events} event{'s' * (events > 1)} (of "
        f"{names}) within 3 x period_guess = {horizon:.6g} s of x_guess, but simulating from x_guess "
        f"found {found}; {remedy}")
