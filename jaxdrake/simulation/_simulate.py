"""`simulate`: one jit-compiled loop for continuous, discrete, mixed and hybrid systems.

Each loop iteration (0) fires a hybrid transition whose guard already holds, (1) applies the
discrete update if the time is a sample time, (2) attempts one solver step of the continuous
state towards min(t + h, next sample time, next input breakpoint, tf), (3) if the step is
accepted and a guard crossed zero inside it, locates the earliest crossing on the dense
output, cuts the step there and switches a saturation or applies a transition's reset,
(4) records the step's dense-output polynomial in the trajectory buffers.

Events are the switching instants of input limits and the transitions of hybrid systems.
While a step is taken each input's saturation mode (free / at u_max / at u_min) and the
hybrid mode are held fixed, so the right-hand side is smooth within a step and the error
estimate is honest; the guards say when a mode must change.

The loop is `equinox.internal.while_loop` with the trajectory as in-place buffers:
`kind="checkpointed"` (recursive checkpointing when reverse-mode differentiated, bounded by
`max_steps`; `autodiff="reverse"`, the default), or `kind="lax"` for `autodiff="forward"`
(`jax.jvp` / `jax.jacfwd`; the checkpointed loop is a custom VJP that forward mode cannot
enter). Step sizes are not differentiated (the gradient is that of the discrete scheme on
its grid); event times are, by the implicit function theorem, so gradients see the shift of
a switching instant and the saltation jump at an impact.
"""
from __future__ import annotations

import enum
from collections.abc import Callable

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np

from ..systems import Diagram, HybridSystem, System
from ..trajectories import Trajectory
from ..trajectories._trajectory import NUM_COEFFICIENTS, eval_polynomial
from ._solvers import AbstractSolver, make_solver


class SimulationStatus(enum.IntEnum):
    """Why a simulation stopped. SUCCESS and STOPPED_BY_RESET are not failures."""

    SUCCESS = 0
    MAX_STEPS_REACHED = 1
    NONFINITE_STATE = 2
    STEP_SIZE_TOO_SMALL = 3
    TOO_MANY_EVENTS = 4
    CONSTRAINT_PROJECTION_FAILED = 5
    STOPPED_BY_RESET = 6  # a reset asked to stop (the notes' status): not a failure


_MESSAGES = {
    SimulationStatus.MAX_STEPS_REACHED: "max_steps was reached before the final time "
                                        "(raise max_steps, or loosen rtol / atol)",
    SimulationStatus.NONFINITE_STATE: "the state became non-finite (NaN or inf)",
    SimulationStatus.STEP_SIZE_TOO_SMALL: "the step size became too small (a singularity, or "
                                          "a stiff system: try solver='rosenbrock23')",
    SimulationStatus.TOO_MANY_EVENTS: "more than max_events events fired (Zeno behaviour or "
                                      "chattering?)",
    SimulationStatus.CONSTRAINT_PROJECTION_FAILED: "no state satisfying the state constraints "
                                                   "phi(x) = 0 was found near x0",
}


class SimulationError(RuntimeError):
    """A simulation ended with a failure status (raised by non-jitted `simulate` calls)."""

    def __init__(self, status: SimulationStatus, message: str):
        super().__init__(message)
        self.status = status


# ----- input sources -------------------------------------------------------------------------


class _InputSource(eqx.Module):
    """u(t) for the loop. A source with breakpoints (an input tape) makes the loop stop a
    step at each one and, within a step, evaluates only the piece the step started in, so a
    jump or kink of the input never falls inside a step."""

    has_breakpoints = False

    def next_breakpoint(self, t):
        return jnp.asarray(jnp.inf, t.dtype)

    def on_step(self, t):
        """u(s) for s in the step starting at t."""
        return self


class _ZeroInput(_InputSource):
    num_inputs: int = eqx.field(static=True)
    dtype: np.dtype = eqx.field(static=True)

    def __call__(self, t):
        return jnp.zeros(self.num_inputs, self.dtype)


class _FunctionInput(_InputSource):
    fn: Callable = eqx.field(static=True)
    num_inputs: int = eqx.field(static=True)

    def __call__(self, t):
        return jnp.reshape(jnp.asarray(self.fn(t), dtype=t.dtype), (self.num_inputs,))


class _TrajectoryInput(_InputSource):
    trajectory: Trajectory
    num_inputs: int = eqx.field(static=True)
    piece: jax.Array | None = None
    has_breakpoints = True

    def __call__(self, t):
        traj = self.trajectory
        y = traj.eval(t) if self.piece is None else traj.eval_piece(self.piece, t)
        return jnp.reshape(y, (self.num_inputs,)).astype(t.dtype)

    def next_breakpoint(self, t):
        ends = self.trajectory.t_end
        valid = (jnp.arange(ends.shape[0]) < self.trajectory.num_segments) & (ends > t)
        return jnp.min(jnp.where(valid, ends, jnp.inf)).astype(t.dtype)

    def on_step(self, t):
        return _TrajectoryInput(self.trajectory, self.num_inputs, self.trajectory.piece_index(t))


class _NoisyInput(_InputSource):
    """[u(t); w(t)]: the inputs followed by the noise samples of a stochastic system.

    Noise group g (size n, period tau, scale c) is held constant on [k tau, (k+1) tau) with
    the value c * N(0, I) drawn from fold_in(fold_in(key, g), k): a pure function of the key
    and k, so paths are reproducible and independent across keys. The instants k tau are
    breakpoints: a step never straddles a jump of w, so `on_step` draws the step's samples
    once and every stage of the step reuses them."""

    inputs: _InputSource
    key: jax.Array
    groups: tuple = eqx.field(static=True)
    samples: jax.Array | None = None
    has_breakpoints = True

    def _periods(self, t):
        return jnp.asarray([tau for _, tau, _ in self.groups], t.dtype)

    def _piece(self, t):
        """The index k with k tau <= t < (k+1) tau, exact at the breakpoints (which the loop
        reaches as the same products k * tau)."""
        tau = self._periods(t)
        k = jnp.floor(t / tau)
        k = jnp.where((k + 1) * tau <= t, k + 1, k)
        return jnp.where(k * tau > t, k - 1, k)

    def _draw(self, t):
        pieces = self._piece(t).astype(jnp.int32)
        return jnp.concatenate([c * jax.random.normal(jax.random.fold_in(jax.random.fold_in(self.key, g), pieces[g]),
                                                      (n,), t.dtype)
                                for g, (n, _, c) in enumerate(self.groups)])

    def __call__(self, t):
        w = self._draw(t) if self.samples is None else self.samples.astype(t.dtype)
        return jnp.concatenate([self.inputs(t), w])

    def next_breakpoint(self, t):
        tau = self._periods(t)
        return jnp.minimum(self.inputs.next_breakpoint(t), jnp.min((self._piece(t) + 1) * tau))

    def on_step(self, t):
        return _NoisyInput(self.inputs.on_step(t), self.key, self.groups, self._draw(t))


# ----- input limits as events ----------------------------------------------------------------


def _saturated_input(system, u_raw, saturation):
    """u with each input held at its limit where its saturation mode says so (+1 high, -1 low);
    noise samples after the inputs pass through."""
    if system.input_limits is None:
        return u_raw
    lo, hi = system.input_limits
    nu = system.num_inputs
    u = jnp.where(saturation > 0, hi, jnp.where(saturation < 0, lo, u_raw[:nu]))
    return jnp.concatenate([u, u_raw[nu:]])


def _initial_saturation(system, u_raw):
    if system.input_limits is None:
        return jnp.zeros(system.num_inputs, jnp.int32)
    lo, hi = system.input_limits
    u_raw = u_raw[: system.num_inputs]
    return jnp.where(u_raw >= hi, 1, jnp.where(u_raw <= lo, -1, 0)).astype(jnp.int32)


def _limit_guards(system, u_raw, saturation):
    """Input-limit guards [g_high; g_low] (an event fires when one crosses from < 0 to >= 0).

    Free input: g_high = u - u_max, g_low = u_min - u. Saturated high: g_high = u_max - u
    (leave the limit), g_low inactive; saturated low symmetrically.
    """
    lo, hi = system.input_limits
    u_raw = u_raw[: system.num_inputs]
    inactive = -jnp.ones_like(u_raw)
    g_high = jnp.where(saturation == 0, u_raw - hi, jnp.where(saturation > 0, hi - u_raw, inactive))
    g_low = jnp.where(saturation == 0, lo - u_raw, jnp.where(saturation < 0, u_raw - lo, inactive))
    return jnp.concatenate([g_high, g_low])


def _saturation_after_event(saturation, index, num_inputs):
    i = index % num_inputs
    entering = jnp.where(index < num_inputs, 1, -1)
    return saturation.at[i].set(jnp.where(saturation[i] == 0, entering, 0))


# ----- state constraints ---------------------------------------------------------------------


def project_to_constraints(system: System, x, iterations: int = 20):
    r"""Project x onto the manifold $\phi(x) = 0$ by Gauss-Newton with minimum-norm steps,
    $x \leftarrow x - J^T (J J^T)^{-1} \phi(x)$, $J = \partial\phi/\partial x$ by autodiff."""
    if system.num_state_constraints == 0:
        return x

    def gauss_newton(x, _):
        phi = system.state_constraints(x)
        J = jax.jacfwd(system.state_constraints)(x)
        step = J.T @ jnp.linalg.solve(J @ J.T, phi)
        return x - step, None

    return jax.lax.scan(gauss_newton, x, None, length=iterations)[0]


# ----- the loop ------------------------------------------------------------------------------


def _rms(v):
    return jnp.sqrt(jnp.mean(v * v)) if v.shape[0] else jnp.zeros((), v.dtype)


@eqx.filter_jit
def _simulate_core(system: System, solver: AbstractSolver, t0, tf, x0, source, rtol, atol,
                   dt0, dt_max, event_tol, max_steps: int, max_events: int, dense: bool,
                   constraint_projection: bool, autodiff: str):
    dtype = x0.dtype
    nx = x0.shape[0]
    nd, nc, nu = system.num_discrete_states, system.num_continuous_states, system.num_inputs
    num_limit_guards = 2 * nu if (system.input_limits is not None and nu > 0) else 0
    num_transitions = len(system.transitions)
    num_guards = num_limit_guards + num_transitions
    eps = jnp.finfo(dtype).eps
    periods = jnp.asarray(system.sample_times, dtype) if system.sample_times else None

    def u_of(t, saturation, source=source):
        return _saturated_input(system, source(t), saturation)

    def guards(t, x, mode, saturation, source):
        """All event functions in one vector, each firing when it crosses from < 0 to >= 0:
        input limits first, then the transitions out of the active mode as -phi_k."""
        u_raw = source(t)
        parts = []
        if num_limit_guards:
            parts.append(_limit_guards(system, u_raw, saturation))
        if num_transitions:
            phi = system.transition_guards(mode, t, x, _saturated_input(system, u_raw, saturation))
            parts.append(jnp.where(jnp.isfinite(phi), -phi, -1.0))
        return jnp.concatenate(parts)

    def vector_field(xd, mode, saturation, source=source):
        return lambda t, xc: system.mode_dynamics(mode, t, jnp.concatenate([xd, xc]),
                                                  u_of(t, saturation, source))

    status = jnp.asarray(SimulationStatus.SUCCESS, jnp.int32)
    if system.num_state_constraints:
        x0 = project_to_constraints(system, x0)
        residual = jnp.max(jnp.abs(system.state_constraints(x0)))
        status = jnp.where(residual <= jnp.sqrt(eps) * (1 + jnp.max(jnp.abs(x0))), status,
                           SimulationStatus.CONSTRAINT_PROJECTION_FAILED)
    mode0 = jnp.asarray(system.initial_mode, jnp.int32)
    saturation0 = _initial_saturation(system, source.on_step(t0)(t0))

    # Initial step size (Hairer, Norsett & Wanner, *Solving ODEs I*, II.4), or the fixed dt.
    if not solver.adaptive:
        h0 = dt0
    elif dt0 is not None:
        h0 = dt0
    elif nc == 0:
        h0 = tf - t0
    else:
        xd0, xc0 = x0[:nd], x0[nd:]
        f = vector_field(xd0, mode0, saturation0, source.on_step(t0))
        scale = atol + rtol * jnp.abs(xc0)
        f0 = f(t0, xc0)
        d0, d1 = _rms(xc0 / scale), _rms(f0 / scale)
        h_a = jnp.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / jnp.where(d1 > 0, d1, 1))
        f1 = f(t0 + h_a, xc0 + h_a * f0)
        d2 = _rms((f1 - f0) / scale) / h_a
        dmax = jnp.maximum(d1, d2)
        h_b = jnp.where(dmax <= 1e-15, jnp.maximum(1e-6, h_a * 1e-3),
                        (0.01 / jnp.where(dmax > 0, dmax, 1)) ** (1.0 / (solver.error_order + 1)))
        h0 = jax.lax.stop_gradient(jnp.minimum(100 * h_a, h_b))
    h0 = jnp.minimum(jnp.asarray(h0, dtype), dt_max)

    size = max_steps + 1 if dense else 1
    inf = jnp.asarray(jnp.inf, dtype)
    first_piece = jnp.zeros((NUM_COEFFICIENTS, nx), dtype).at[0].set(x0)
    carry = dict(
        t=t0, x=x0, h=h0, mode=mode0, saturation=saturation0,
        sample=jnp.ceil(t0 / periods) if periods is not None else jnp.zeros((), dtype),
        n=jnp.asarray(1), n_events=jnp.asarray(0), iters=jnp.asarray(0),
        rejected=jnp.asarray(0), status=status, at_breakpoint=jnp.asarray(False),
        seg_t0=jnp.full((size,), inf).at[0].set(t0),
        seg_t1=jnp.full((size,), inf).at[0].set(t0),
        seg_c=jnp.zeros((size, NUM_COEFFICIENTS, nx), dtype).at[0].set(first_piece),
        seg_mode=jnp.zeros((size,), jnp.int32).at[0].set(mode0),
        ev_t=jnp.full((max_events,), inf), ev_i=jnp.full((max_events,), -1, jnp.int32),
        ev_mode=jnp.full((max_events,), -1, jnp.int32), ev_x=jnp.zeros((max_events, nx), dtype),
    )
    # First-same-as-last: the solver's last stage is the next step's first, unless something
    # can change the vector field between steps (a discrete update, an event, a projection, a
    # new piece of an input tape): a static fact.
    fsal = (solver.fsal and nc > 0 and nd == 0 and num_guards == 0 and not source.has_breakpoints
            and not (constraint_projection and system.num_state_constraints))
    if fsal:
        carry["f0"] = vector_field(x0[:nd], mode0, saturation0, source)(t0, x0[nd:])

    def cond(c):
        return (c["status"] == SimulationStatus.SUCCESS) & (c["t"] < tf) & (c["iters"] < max_steps)

    def body(c):
        t, x, h, mode, saturation, status = (c["t"], c["x"], c["h"], c["mode"], c["saturation"],
                                             c["status"])
        n_events = c["n_events"]
        step_source = source.on_step(t)

        # (0) a transition whose guard already holds fires at once, without a step (after a
        # reset, or at t0): the notes' semantics, phi <= 0 triggers. One per iteration, the
        # lowest-numbered first; a chattering system runs into max_events. (`lax.cond` skips
        # the reset when nothing fires; under vmap it becomes a select.)
        immediate, k_now = jnp.asarray(False), jnp.asarray(0)
        if num_transitions:
            u_now = u_of(t, saturation, step_source)
            ready = system.transition_guards(mode, t, x, u_now) <= 0
            immediate = jnp.any(ready) & (n_events < max_events)
            status = jnp.where(jnp.any(ready) & ~immediate, SimulationStatus.TOO_MANY_EVENTS, status)
            k_now = jnp.argmax(ready)
            x, mode, stop_now = jax.lax.cond(
                immediate, lambda: system.apply_transition(mode, k_now, t, x, u_now),
                lambda: (x, mode, jnp.asarray(False)))
            status = jnp.where(immediate & stop_now, SimulationStatus.STOPPED_BY_RESET, status)

        # (1) discrete updates at the sample times {0, dt, 2dt, ...}: x_d(t + t') = f_d(t, x, u),
        # each sample time (a multi-rate diagram has several) counted separately.
        sample = c["sample"]
        if periods is not None:
            # sample instants of different rates that agree to rounding (3 * 0.1 and 2 * 0.15)
            # are one instant: those updates are simultaneous, as they are in exact arithmetic
            instants = sample * periods
            due = (t >= instants - 64 * eps * jnp.abs(instants)) & ~immediate
            at_sample = jnp.any(due)
            xd_next = system.mode_update(mode, t, x, u_of(t, saturation, step_source), due)
            x = jnp.where(at_sample, jnp.concatenate([xd_next, x[nd:]]), x)
            sample = sample + due
            status = jnp.where(at_sample & ~jnp.all(jnp.isfinite(x)),
                               SimulationStatus.NONFINITE_STATE, status)
        xd, xc = x[:nd], x[nd:]
        if num_limit_guards:  # after a breakpoint of an input tape, u may have jumped past a limit
            saturation = jnp.where(c["at_breakpoint"], _initial_saturation(system, step_source(t)),
                                   saturation)

        # (2) one step towards the next stopping point (snapping onto it when within rounding):
        # the final time, the next sample time, the next breakpoint of the input.
        breakpoint_ = source.next_breakpoint(t)
        target = jnp.minimum(tf, breakpoint_)
        if periods is not None:
            target = jnp.minimum(target, jnp.min(sample * periods))
        t_next = t + h
        t_next = jnp.where(t_next >= target - (1e-6 * h + 64 * eps * jnp.abs(target)), target, t_next)
        h_eff = t_next - t
        if nc:
            xc1, err, coef, f1 = solver.step(vector_field(xd, mode, saturation, step_source), t, h_eff,
                                             xc, c["f0"] if fsal else None)
        else:
            xc1, err, coef = xc, None, jnp.zeros((NUM_COEFFICIENTS, 0), dtype)
        finite = jnp.all(jnp.isfinite(xc1)) & (jnp.all(jnp.isfinite(coef)) if dense else True)
        if err is not None:
            scale = atol + rtol * jnp.maximum(jnp.abs(xc), jnp.abs(xc1))
            err_norm = jax.lax.stop_gradient(_rms(err / scale))
            accept = finite & (err_norm <= 1)
        else:
            err_norm = jnp.zeros((), dtype)
            accept = finite
        accept = accept & ~immediate
        coef_d = jnp.zeros((NUM_COEFFICIENTS, nd), dtype).at[0].set(xd)
        coef = jnp.concatenate([coef_d, coef], axis=1)
        x1 = jnp.concatenate([xd, xc1])
        t_end, x_end, event, which = t_next, x1, jnp.asarray(False), jnp.asarray(-1, jnp.int32)
        stop = jnp.asarray(False)

        # (3) events: locate the earliest guard crossing inside an accepted step, cut the step
        # there, and switch a saturation or take a transition (reset, new mode).
        x_after, mode_after = x_end, mode
        if num_guards:
            g_step = lambda tt, xx: guards(tt, xx, mode, saturation, step_source)
            crossed = accept & (g_step(t, x) < 0) & (g_step(t_next, x1) >= 0)
            room = n_events < max_events
            status = jnp.where(jnp.any(crossed) & ~room, SimulationStatus.TOO_MANY_EVENTS, status)
            event = jnp.any(crossed) & room

            def handle_event(coef):
                frozen = jax.lax.stop_gradient((coef, t, h_eff))
                theta_located, which = _locate_first_crossing(
                    lambda th: jax.lax.stop_gradient(g_step(frozen[1] + th * frozen[2],
                                                            eval_polynomial(frozen[0], th))),
                    crossed, frozen[2], event_tol)
                # one Newton step on the located root, theta* = theta - g / g', differentiable:
                # the event time moves with parameters and initial state (implicit function
                # theorem; with the reset's Jacobian this is the saltation matrix's jump)
                g_of = lambda th: g_step(t + th * h_eff, eval_polynomial(coef, th))[which]
                g_val, g_dot = jax.jvp(g_of, (theta_located,), (jnp.ones((), dtype),))
                g_dot = jax.lax.stop_gradient(g_dot)
                newton = jnp.where(g_dot != 0, g_val / jnp.where(g_dot != 0, g_dot, 1), 0.0)
                theta = jnp.clip(theta_located - newton, 0.0, 1.0)
                powers = jnp.cumprod(jnp.concatenate([jnp.ones(1, dtype),
                                                      jnp.full(NUM_COEFFICIENTS - 1, theta)]))
                coef = coef * powers[:, None]
                t_end, x_end = t + theta * h_eff, eval_polynomial(coef, 1.0)
                new_saturation, x_after, mode_after, stop = saturation, x_end, mode, jnp.asarray(False)
                if num_limit_guards:
                    new_saturation = jnp.where(which < num_limit_guards,
                                               _saturation_after_event(saturation, which, nu), saturation)
                if num_transitions:
                    k = jnp.clip(which - num_limit_guards, 0, num_transitions - 1)
                    is_transition = which >= num_limit_guards
                    x_reset, mode_reset, stop_reset = system.apply_transition(
                        mode, k, t_end, x_end, u_of(t_end, new_saturation, step_source))
                    x_after = jnp.where(is_transition, x_reset, x_end)
                    mode_after = jnp.where(is_transition, mode_reset, mode)
                    stop = is_transition & stop_reset
                return coef, t_end, x_end, which, new_saturation, x_after, mode_after, stop

            def no_event(coef):
                return (coef, t_next, x1, jnp.asarray(-1, jnp.int32),
                        saturation, x1, mode, jnp.asarray(False))

            coef, t_end, x_end, which, saturation, x_after, mode_after, stop = jax.lax.cond(
                event, handle_event, no_event, coef)

        if constraint_projection and system.num_state_constraints:
            x_projected = project_to_constraints(system, x_end, iterations=3)
            coef = coef.at[1].add(x_projected - x_end)  # keep the dense output continuous
            took_transition = event & (which >= num_limit_guards) if num_transitions else False
            x_after = jnp.where(took_transition, x_after, x_projected)
            x_end = x_projected

        # (4) bookkeeping: step size, status, buffers.
        if solver.adaptive:
            q = solver.error_order + 1
            factor = jnp.where(err_norm > 0, 0.9 * jnp.where(err_norm > 0, err_norm, 1) ** (-1.0 / q), 10.0)
            factor = jnp.where(finite, jnp.clip(factor, 0.2, 10.0), 0.2)
            h_new = jnp.where(accept & (h_eff < h), jnp.maximum(h, h_eff * factor), h_eff * factor)
            h_new = jnp.where(immediate, h, jnp.minimum(h_new, dt_max))
            tiny = ~accept & ~immediate & (h_new <= 16 * eps * jnp.maximum(jnp.abs(t), 1.0))
            status = jnp.where(tiny, jnp.where(finite, SimulationStatus.STEP_SIZE_TOO_SMALL,
                                               SimulationStatus.NONFINITE_STATE), status)
        else:
            h_new = h
            status = jnp.where(finite | immediate, status, SimulationStatus.NONFINITE_STATE)
        ok = (status == SimulationStatus.SUCCESS) | (status == SimulationStatus.STOPPED_BY_RESET)
        accept = accept & ok
        status = jnp.where(accept & stop, SimulationStatus.STOPPED_BY_RESET, status)
        recorded = (accept & event) | immediate

        def write(buffer, index, value, pred):
            return buffer.at[index].set(value, pred=pred)

        n = c["n"]
        out = dict(c, h=jax.lax.stop_gradient(h_new), mode=jnp.where(accept, mode_after, mode),
                   saturation=saturation, sample=sample, status=status,
                   t=jnp.where(accept, t_end, t), x=jnp.where(accept, x_after, x),
                   iters=c["iters"] + 1, rejected=c["rejected"] + (~accept & ~immediate),
                   at_breakpoint=jnp.where(accept, ~event & (t_end >= breakpoint_), c["at_breakpoint"]),
                   n=n + (accept if dense else 0), n_events=n_events + recorded,
                   **({"f0": jnp.where(accept, f1, c["f0"])} if fsal else {}))
        if dense:
            out["seg_t0"] = write(c["seg_t0"], n, t, accept)
            out["seg_t1"] = write(c["seg_t1"], n, t_end, accept)
            out["seg_c"] = write(c["seg_c"], n, coef, accept)
            out["seg_mode"] = write(c["seg_mode"], n, mode, accept)
        if num_guards:
            out["ev_t"] = write(c["ev_t"], n_events, jnp.where(immediate, t, t_end), recorded)
            ev_index = jnp.where(immediate, num_limit_guards + k_now, which).astype(jnp.int32)
            out["ev_i"] = write(c["ev_i"], n_events, ev_index, recorded)
            out["ev_mode"] = write(c["ev_mode"], n_events, out["mode"], recorded)
            out["ev_x"] = write(c["ev_x"], n_events, out["x"], recorded)
        return out

    # Buffers are written in place (under vmap too, where a plain while loop would copy them
    # whole every iteration).
    c = eqxi.while_loop(cond, body, carry, max_steps=max_steps,
                        kind="lax" if autodiff == "forward" else "checkpointed",
                        buffers=lambda c: (c["seg_t0"], c["seg_t1"], c["seg_c"], c["seg_mode"],
                                           c["ev_t"], c["ev_i"], c["ev_mode"], c["ev_x"]))
    status = jnp.where((c["status"] == SimulationStatus.SUCCESS) & (c["t"] < tf),
                       SimulationStatus.MAX_STEPS_REACHED, c["status"])
    seg_t0, seg_t1, seg_c, seg_mode, n = c["seg_t0"], c["seg_t1"], c["seg_c"], c["seg_mode"], c["n"]
    if not dense:  # keep the initial point and the final state only
        last = jnp.zeros((1, NUM_COEFFICIENTS, nx), dtype).at[0, 0].set(c["x"])
        seg_t0 = jnp.concatenate([seg_t0, c["t"][None]])
        seg_t1 = jnp.concatenate([seg_t1, c["t"][None]])
        seg_c, n = jnp.concatenate([seg_c, last]), jnp.asarray(2)
        seg_mode = jnp.concatenate([seg_mode, c["mode"][None]])
    return Trajectory(t_start=seg_t0, t_end=seg_t1, coefficients=seg_c, num_segments=n,
                      t_final=c["t"], status=status, event_times=c["ev_t"],
                      event_indices=c["ev_i"], num_events=c["n_events"],
                      num_rejected_steps=c["rejected"], modes=seg_mode, event_modes=c["ev_mode"],
                      event_states=c["ev_x"], system=system, inputs=source,
                      side="left", dense=dense)


_ROOT_ITERATIONS = 6  # safeguarded Newton from a secant start: ~4 suffice for smooth guards


def _locate_first_crossing(guard_fn, crossed, h, tol):
    """The earliest crossing in theta in [0, 1] among the crossed guards, and which guard it is.

    It is the root of G(theta) = max over crossed guards of g_i(theta) (G < 0 at 0, G >= 0 at
    1), found by Newton's method safeguarded with bisection: the bracket [lo, hi] keeps
    G(lo) < 0 <= G(hi), and a Newton iterate outside it is replaced by the midpoint. It stops
    when the last update or the bracket is below `tol` in time: a few iterations for smooth
    guards, where bisection alone needs ~30 (which under vmap every member pays whenever any
    member has an event). Ties go to the lowest index.
    `guard_fn(theta)` gives all guards; not differentiated (see the Newton step in the loop)."""
    def G(theta):
        return jnp.max(jnp.where(crossed, guard_fn(theta), -jnp.inf))

    g0, g1 = G(jnp.zeros((), h.dtype)), G(jnp.ones((), h.dtype))
    secant = jnp.clip(-g0 / jnp.where(g1 > g0, g1 - g0, 1.0), 0.0, 1.0)

    def iterate(state):
        lo, hi, theta, done = state
        g, dg = jax.jvp(G, (theta,), (jnp.ones_like(theta),))
        lo, hi = jnp.where(g >= 0, lo, theta), jnp.where(g >= 0, theta, hi)
        newton = theta - g / jnp.where(dg != 0, dg, 1.0)
        new = jnp.where((dg != 0) & (newton > lo) & (newton < hi), newton, (lo + hi) / 2)
        converged = done | (jnp.abs(new - theta) * h <= tol) | ((hi - lo) * h <= tol)
        return lo, hi, jnp.where(done, theta, new), converged

    state = (jnp.zeros_like(secant), jnp.ones_like(secant), secant, ~jnp.any(crossed))
    # The first iterations unrolled (a nested while loop costs a device-host round trip per
    # iteration on a GPU), then a loop for the rare hard case (a kink of an and-guard near
    # the root sends Newton to bisection), bounded.
    for _ in range(_ROOT_ITERATIONS):
        state = iterate(state)
    state = jax.lax.while_loop(lambda s: ~s[3] & (s[1] - s[0] > 0), iterate, state)
    theta = state[2]
    which = jnp.argmax(jnp.where(crossed, guard_fn(theta), -jnp.inf)).astype(jnp.int32)
    return theta, which


# ----- the public entry point ----------------------------------------------------------------


def simulate(system: System, tspan, x0=None, *, inputs=None, key=None, solver="dopri5", rtol=1e-6,
             atol=1e-9, dt=None, max_step_size=None, max_steps: int = 4096,
             max_events: int = 256, event_tol=1e-10, dense: bool = True,
             constraint_projection: bool = False, autodiff: str = "reverse",
             throw: bool = True) -> Trajectory:
    """Simulate a system over `tspan = (t0, tf)` (the notes' `simulate(sys, [t0 tf], x0)`).

    **Arguments:**

    - `system`: a `jaxdrake.System`.
    - `tspan`: `(t0, tf)` with t0 < tf.
    - `x0`: initial state, shape (num_states,) (a scalar for one state); None takes
      `system.initial_state()`. With state constraints it is first projected onto phi(x) = 0.
    - `inputs`: a `Trajectory` (input tape) or a function of time returning u(t); None means
      u = 0, as in the notes. Input limits of the system saturate it.
    - `key`: a JAX PRNG key, for a stochastic system (required then, refused otherwise): the
      noise path is a function of the key alone; `jax.vmap` over keys gives a Monte-Carlo batch.
    - `solver`: `"dopri5"` (adaptive, default), `"rosenbrock23"` (adaptive, for stiff
      systems), `"rk4"`, `"midpoint"` or `"euler"` (fixed step `dt`), or a solver instance.
    - `rtol`, `atol`: tolerances of the adaptive solvers; `dt`: the fixed step (or the first
      step of an adaptive one); `max_step_size`: an upper bound on steps.
    - `max_steps`: the bound on loop iterations (accepted + rejected steps) and the size of
      the trajectory buffers; `max_events`: the bound on events (Zeno protection).
    - `event_tol`: the time tolerance to which event instants are located.
    - `dense`: keep the dense output (else only the final state, for big batches).
    - `constraint_projection`: project the state onto phi(x) = 0 after every step.
    - `autodiff`: `"reverse"` (default; `jax.grad` works, through a checkpointed loop) or
      `"forward"` (`jax.jvp` / `jax.jacfwd` work, `jax.grad` does not).
    - `throw`: outside `jit` / `vmap`, raise `SimulationError` on failure; inside, the
      status is on the result (`traj.status`, `traj.success`) either way.

    **Returns:** a `Trajectory`.
    """
    if not isinstance(system, System):
        raise TypeError(f"simulate needs a jaxdrake.System, got {type(system).__name__}")
    solver = make_solver(solver)
    try:
        t0, tf = tspan
    except (TypeError, ValueError):
        raise ValueError(f"tspan must be a pair (t0, tf), got {tspan!r}") from None
    dtype = jnp.result_type(float)
    if x0 is None:
        x0 = system.initial_state()
    x0 = jnp.asarray(x0)
    dtype = x0.dtype if jnp.issubdtype(x0.dtype, jnp.floating) else dtype
    x0 = x0.astype(dtype)
    nx = system.num_states
    if x0.shape == () and nx == 1:
        x0 = x0.reshape(1)
    if isinstance(system, HybridSystem):  # x0 may be given in the initial mode's own layout
        n_initial = system.modes[system.initial_mode].num_states
        if x0.shape == () and n_initial == 1:
            x0 = x0.reshape(1)
        if x0.shape == (n_initial,) and n_initial != nx:
            x0 = system.pad_state(system.initial_mode, x0)
    if x0.shape != (nx,):
        raise ValueError(f"x0 has shape {x0.shape}, but {system.name}'s state frame "
                         f"{system.state_frame} needs shape ({nx},)")
    t0, tf = jnp.asarray(t0, dtype), jnp.asarray(tf, dtype)
    if _concrete(t0, tf) and not (np.isfinite(t0) and np.isfinite(tf) and tf > t0):
        raise ValueError(f"tspan must be finite with t0 < tf, got ({float(t0)}, {float(tf)})")
    if _concrete(x0) and not np.all(np.isfinite(x0)):
        raise ValueError(f"x0 is not finite: {x0}")
    source = _make_source(system, inputs, t0, dtype)
    if system.is_stochastic:
        if key is None:
            raise ValueError(f"{system.name} is stochastic (noise inputs {system.noise_groups}): "
                             "simulate needs a PRNG key, e.g. key=jax.random.key(0)")
        source = _NoisyInput(source, key, system.noise_groups)
    elif key is not None:
        raise ValueError(f"a key was given, but {system.name} is deterministic (it has no noise inputs)")
    _check_system_shapes(system, t0, x0, source)
    if not solver.adaptive and dt is None:
        raise ValueError(f"the fixed-step solver {type(solver).__name__} needs a step size dt")
    for name, v in (("rtol", rtol), ("atol", atol), ("dt", dt), ("max_step_size", max_step_size),
                    ("event_tol", event_tol)):
        if v is not None and _concrete(v) and not float(v) > 0:
            raise ValueError(f"{name} must be positive, got {v}")
    if autodiff not in ("reverse", "forward"):
        raise ValueError(f"autodiff must be 'reverse' or 'forward', got {autodiff!r}")
    if not (isinstance(max_steps, int) and max_steps > 0):
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}")

    arr = lambda v: None if v is None else jnp.asarray(v, dtype)
    system = _leaves_to_arrays(system, dtype)
    traj = _simulate_core(system, solver, t0, tf, x0, source, arr(rtol), arr(atol), arr(dt),
                          arr(jnp.inf if max_step_size is None else max_step_size),
                          arr(event_tol), max_steps, max_events, dense, constraint_projection,
                          autodiff)
    if throw and _concrete(traj.status) and not bool(traj.success):
        status = SimulationStatus(int(traj.status))
        raise SimulationError(status, f"simulating {system.name} over [{float(t0)}, {float(tf)}] "
                                      f"stopped at t = {float(traj.t_final)!r}: {_MESSAGES[status]}")
    return traj


def _concrete(*values) -> bool:
    return not any(isinstance(v, jax.core.Tracer) for v in jax.tree.leaves(values))


def _leaves_to_arrays(tree, dtype):
    """Python floats and numpy arrays in a system become JAX arrays: traced, not static, so
    changing a parameter's value does not recompile."""
    def convert(v):
        if isinstance(v, float) or (isinstance(v, np.ndarray) and np.issubdtype(v.dtype, np.floating)):
            return jnp.asarray(v, dtype)
        if isinstance(v, jax.Array) and jnp.issubdtype(v.dtype, jnp.floating):
            return v.astype(dtype)
        return v
    return jax.tree.map(convert, tree)


def _make_source(system, inputs, t0, dtype):
    nu = system.num_inputs
    if inputs is None:
        return _ZeroInput(nu, np.dtype(dtype))
    if nu == 0:
        raise ValueError(f"{system.name} has no inputs, but inputs were given")
    if isinstance(inputs, Trajectory):
        source = _TrajectoryInput(_leaves_to_arrays(inputs, dtype), nu)
    elif callable(inputs):
        source = _FunctionInput(inputs, nu)
    else:
        raise TypeError(f"inputs must be a Trajectory or a function of time, got {type(inputs).__name__}")
    raw = inputs.eval if isinstance(inputs, Trajectory) else inputs
    try:
        shape = jax.eval_shape(raw, t0).shape
    except Exception as e:
        raise ValueError(f"evaluating the inputs at t0 failed: {e}") from e
    if shape not in ((nu,), ()) or (shape == () and nu != 1):
        raise ValueError(f"inputs(t) returns shape {shape}, but {system.name}'s input frame "
                         f"{system.input_frame} needs shape ({nu},)")
    return source


def _check_system_shapes(system, t0, x0, source):
    """Trace each method once (shapes only) so that a wrong shape is a named Python error."""
    if isinstance(system, HybridSystem):
        _check_hybrid_shapes(system, t0, x0, source)
        return
    if isinstance(system, Diagram):
        _check_diagram_shapes(system, t0, x0, source)
        return
    u = jax.ShapeDtypeStruct((system.num_inputs,), x0.dtype)
    expected = [("output", system.output, system.num_outputs, (t0, x0, u))]
    if system.num_continuous_states:
        expected.append(("dynamics", system.dynamics, system.num_continuous_states, (t0, x0, u)))
    if system.num_discrete_states:
        expected.append(("update", system.update, system.num_discrete_states, (t0, x0, u)))
    if system.num_state_constraints:
        expected.append(("state_constraints", system.state_constraints,
                         system.num_state_constraints, (x0,)))
    for name, method, size, args in expected:
        try:
            out = jax.eval_shape(method, *args)
        except NotImplementedError:
            raise
        except Exception as e:
            raise ValueError(f"{system.name}.{name} failed on a state of shape {x0.shape} and an "
                             f"input of shape ({system.num_inputs},): {type(e).__name__}: {e}") from e
        if getattr(out, "shape", None) != (size,):
            raise ValueError(f"{system.name}.{name} returned shape {getattr(out, 'shape', type(out))}, "
                             f"expected ({size},)")


def _check_diagram_shapes(system, t0, x0, source):
    """Each subsystem as a system of its own, then the wiring (frame conversions)."""
    for i, sub in enumerate(system.subsystems):
        _check_system_shapes(sub, t0, system.subsystem_state(i, x0), source)
    u = jax.ShapeDtypeStruct((system.num_inputs + system.num_noise_inputs,), x0.dtype)
    mode = jnp.asarray(system.initial_mode, jnp.int32)
    try:
        out = jax.eval_shape(lambda x, u: system.mode_output(mode, t0, x, u), x0, u)
    except Exception as e:
        raise ValueError(f"evaluating the signals of diagram {system.name} failed (a frame "
                         f"conversion returning the wrong shape?): {type(e).__name__}: {e}") from e
    if out.shape != (system.num_outputs,):
        raise ValueError(f"diagram {system.name}'s output has shape {out.shape}, expected "
                         f"({system.num_outputs},)")


def _check_hybrid_shapes(system, t0, x0, source):
    """Each mode as a system of its own, then every guard (a scalar) and reset (the target
    mode's state, or a pair (state, stop))."""
    u = jax.ShapeDtypeStruct((system.num_inputs,), x0.dtype)
    for i, mode in enumerate(system.modes):
        _check_system_shapes(mode, t0, system.mode_state(i, x0), source)
    for k, tr in enumerate(system.transitions):
        label = f"{system.name} transition {k}" + (f" ({tr.name})" if tr.name else "")
        x_src = jax.ShapeDtypeStruct((system.modes[tr.source].num_states,), x0.dtype)
        try:
            g = jax.eval_shape(lambda x, u: tr.guard(system, t0, x, u), x_src, u)
            out = jax.eval_shape(lambda x, u: tr.reset(system, t0, x, u), x_src, u)
        except Exception as e:
            raise ValueError(f"{label}: the guard or reset failed on a state of shape "
                             f"{x_src.shape}: {type(e).__name__}: {e}") from e
        if getattr(g, "shape", None) not in ((), (1,)):
            raise ValueError(f"{label}: the guard must return a scalar, got shape "
                             f"{getattr(g, 'shape', type(g))}")
        x_plus = out[0] if isinstance(out, tuple) else out
        n_target = system.modes[tr.target].num_states
        if getattr(x_plus, "shape", None) != (n_target,):
            raise ValueError(f"{label}: the reset must return the target mode's state, shape "
                             f"({n_target},), got {getattr(x_plus, 'shape', type(x_plus))}")
