"""The simulation loop: a `LoopState` and the stages that advance it, in the order they run.

One iteration (`Loop.iterate`), like Drake's `Simulator::Step`:

1. `find_ready_transition`: a transition whose guard already holds (after a reset, or at t0)
   fires now, without a step (the notes' semantics: phi <= 0 triggers);
2. `apply_due_updates`: the discrete updates whose sample time has come;
3. `refresh_saturation`: after a breakpoint of the input tape the input may have jumped past a
   limit;
4. `attempt_step`: one solver step of the continuous state towards
   min(t + h, next sample time, next input breakpoint, tf);
5. `locate_event`: if the step is accepted and a guard crossed zero inside it, locate the
   earliest crossing on the dense output and cut the step there;
6. `take_event`: switch a saturation or apply a transition's reset (the ready transition of
   stage 1 or the located one of stage 5: one reset per iteration);
7. `project_onto_constraints` (optional);
8. `adapt_step_size`: accept or reject, the next step size, failures as a status;
9. `record`: the step's dense-output polynomial and the event into the buffers.

The vector field is traced once per program (the solver evaluates its jaxpr at every stage
and picks the initial step size from the first one); discrete updates, resets and outputs have
one call site each; the guards have five (the ready check, both ends of a step in one vmapped
call, the root finder's unrolled and looped iterations, the differentiable Newton step).
"""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp

from ..systems import System
from ..trajectories import NUM_COEFFICIENTS, Trajectory, eval_polynomial
from . import _events as ev
from .._jaxprs import reads_argument
from ._controller import AbstractStepSizeController, advance, carries_low_part, elapsed, least_step, smallest_step
from ._inputs import InputSource
from ._result import SimulatedTrajectory
from ._reverse import run_adjoint, run_reverse
from ._solvers import AbstractSolver, Linearization
from ._status import SimulationStatus


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


class PieceRecord(eqx.Module):
    """The trajectory as it is written: piece i covers (t_start[i], t_end[i]] with
    `coefficients[i]` (NUM_COEFFICIENTS, n) in the normalized time, in hybrid mode `modes[i]`;
    `count` pieces are used (the initial point is piece 0)."""

    t_start: jax.Array
    t_end: jax.Array
    coefficients: jax.Array
    modes: jax.Array
    count: jax.Array


class EventRecord(eqx.Module):
    """The events that fired: time, guard index (the order of `_events`), the mode and the
    state after each; `count` used."""

    times: jax.Array
    indices: jax.Array
    modes: jax.Array
    states: jax.Array
    count: jax.Array


class LoopState(eqx.Module):
    """Everything the loop carries from one iteration to the next."""

    # where the simulation is
    t: jax.Array  # time: t + t_low (`_controller.advance`)
    t_low: jax.Array  # float32: the part of time below t's spacing, so that shorter steps move it; else 0
    x: jax.Array  # state [x_d; x_c] (padded to the largest mode for a hybrid system)
    mode: jax.Array  # active hybrid mode (0 for a plain system)
    saturation: jax.Array  # per input: 0 free, +1 held at u_max, -1 held at u_min
    # step size
    h: jax.Array  # the next step to attempt; NaN until chosen from the first stage
    k0: jax.Array | None  # f(t, x_c) for a first-same-as-last solver (else None)
    k0_valid: jax.Array | None  # False until the first iteration has evaluated k0
    linearization: Linearization | None  # a linearly implicit solver's matrix, for a retry
    # clocks
    samples: jax.Array  # per sample rate, the index k of its next instant k * period
    at_breakpoint: jax.Array  # the last step ended on a breakpoint of the input
    # outcome
    status: jax.Array  # a SimulationStatus
    iterations: jax.Array  # loop iterations so far (bounded by max_steps)
    rejected: jax.Array  # rejected steps so far
    accepted: jax.Array  # accepted steps so far
    pieces: PieceRecord
    events: EventRecord

    def buffers(self):
        """The trajectory buffers (written in place by the loop; their counts are not)."""
        p, e = self.pieces, self.events
        return (p.t_start, p.t_end, p.coefficients, p.modes, e.times, e.indices, e.modes, e.states)

    def buffer_counts(self):
        """Per buffer, the row the next write goes to."""
        return (self.pieces.count,) * 4 + (self.events.count,) * 4


class Ready(eqx.Module):
    """Stage 1's decision: whether transition `k` fires at once."""

    fired: jax.Array
    k: jax.Array


class Attempt(eqx.Module):
    """One attempted step, cut at an event if one was located."""

    t_end: jax.Array  # where the step ends (the event time if one was located)
    t_end_low: jax.Array  # and its part below t_end's spacing (`LoopState.t_low`)
    x_end: jax.Array  # the state there, before any reset
    coefficients: jax.Array  # its dense output, [x_d constant; x_c polynomial]
    h_proposed: jax.Array  # the step the controller asked for
    h: jax.Array  # the step attempted (shortened to a stopping point)
    accept: jax.Array
    finite: jax.Array
    h_next: jax.Array  # the controller's next step
    k_last: jax.Array | None  # f at the end of the step (first-same-as-last)
    linearization: Linearization | None  # the matrix the step used (a solver that reuses it)
    priming: jax.Array  # a step of size 0 that only evaluates k0 (first-same-as-last)
    event: jax.Array  # a guard crossed inside the step and was located
    which: jax.Array  # the guard that fired (-1: none)


class Loop(eqx.Module):
    """The loop's fixed inputs and its stages (static structure in static fields)."""

    system: System
    solver: AbstractSolver
    controller: AbstractStepSizeController
    source: InputSource
    tf: jax.Array
    dt_max: jax.Array
    event_tol: jax.Array
    periods: jax.Array | None
    max_steps: int = eqx.field(static=True)
    max_events: int = eqx.field(static=True)
    dense: bool = eqx.field(static=True)
    project: bool = eqx.field(static=True)
    fsal: bool = eqx.field(static=True)
    # the adjoint's step (`_reverse.run_adjoint`): buffers of one row, into which `record`
    # writes the step's piece and event (the caller places them)
    windowed: bool = eqx.field(static=True, default=False)

    # ----- static facts ---------------------------------------------------------------------

    @property
    def reuse_linearization(self):
        """A linearly implicit solver's matrix is kept for the retry of a rejected step where
        the vector field changes only through accepted steps (as for first-same-as-last)."""
        return self.fsal and self.solver.reuses_linearization

    @property
    def num_discrete(self):
        return self.system.num_discrete_states

    @property
    def num_continuous(self):
        return self.system.num_continuous_states

    @property
    def num_limit_guards(self):
        return ev.num_limit_guards(self.system)

    @property
    def num_transitions(self):
        return len(self.system.transitions)

    def next_breakpoint(self, t):
        """The input tape's or the system's next breakpoint after t."""
        return jnp.minimum(self.source.next_breakpoint(t), self.system.next_breakpoint(t).astype(t.dtype))

    # ----- the signals the stages read ------------------------------------------------------

    def input(self, t, saturation, source):
        return ev.saturated_input(self.system, source(t), saturation)

    def guards(self, t, x, mode, saturation, source):
        """All event functions in one vector, in the order of `_events`."""
        u_raw = source(t)
        parts = []
        if self.num_limit_guards:
            parts.append(ev.limit_guards(self.system, u_raw, saturation))
        if self.num_transitions:
            phi = self.system.transition_guards(mode, t, x, ev.saturated_input(self.system, u_raw, saturation))
            parts.append(jnp.where(jnp.isfinite(phi), -phi, -1.0))
        return jnp.concatenate(parts)

    # ----- start ----------------------------------------------------------------------------

    def initial_state(self, t0, x0, h0, status) -> LoopState:
        system, dtype, nx = self.system, x0.dtype, x0.shape[0]
        size = self.max_steps + 1 if self.dense else 1
        inf = jnp.asarray(jnp.inf, dtype)
        mode0 = jnp.asarray(system.initial_mode, jnp.int32)
        first_piece = jnp.zeros((NUM_COEFFICIENTS, nx), dtype).at[0].set(x0)
        pieces = PieceRecord(t_start=jnp.full((size,), inf).at[0].set(t0),
                             t_end=jnp.full((size,), inf).at[0].set(t0),
                             coefficients=jnp.zeros((size, NUM_COEFFICIENTS, nx), dtype).at[0].set(first_piece),
                             modes=jnp.zeros((size,), jnp.int32).at[0].set(mode0), count=jnp.asarray(1))
        m = self.max_events
        events = EventRecord(times=jnp.full((m,), inf), indices=jnp.full((m,), -1, jnp.int32),
                             modes=jnp.full((m,), -1, jnp.int32), states=jnp.zeros((m, nx), dtype),
                             count=jnp.asarray(0))
        return LoopState(
            t=t0, t_low=jnp.zeros_like(t0), x=x0, mode=mode0, saturation=ev.initial_saturation(system, self.source.on_step(t0)(t0)),
            h=jnp.minimum(jnp.asarray(h0, dtype), self.dt_max),
            k0=jnp.zeros(self.num_continuous, dtype) if self.fsal else None,
            k0_valid=jnp.asarray(False) if self.fsal else None,
            linearization=Linearization.none(self.num_continuous, dtype) if self.reuse_linearization else None,
            samples=(jnp.ceil(t0 / self.periods) if self.periods is not None else jnp.zeros((), dtype)),
            at_breakpoint=jnp.asarray(False), status=status, iterations=jnp.asarray(0),
            rejected=jnp.asarray(0), accepted=jnp.asarray(0), pieces=pieces, events=events)


    # ----- the stages, in order -------------------------------------------------------------

    def find_ready_transition(self, s: LoopState) -> tuple[LoopState, Ready]:
        """(1) The lowest-numbered transition whose guard already holds fires at once (one per
        iteration; a chattering system runs into max_events)."""
        if not self.num_transitions:
            return s, Ready(jnp.asarray(False), jnp.asarray(0))
        source = self.source.on_step(s.t)
        ready = self.system.transition_guards(s.mode, s.t, s.x, self.input(s.t, s.saturation, source)) <= 0
        fired = jnp.any(ready) & (s.events.count < self.max_events)
        status = jnp.where(jnp.any(ready) & ~fired, SimulationStatus.TOO_MANY_EVENTS, s.status)
        return dataclasses.replace(s, status=status), Ready(fired, jnp.argmax(ready))

    def apply_due_updates(self, s: LoopState, ready: Ready) -> LoopState:
        """(2) Discrete updates at the sample times {0, dt, 2 dt, ...}: x_d(t+) = f_d(t, x, u),
        each rate counted separately; instants of different rates that agree to rounding
        (3 * 0.1 and 2 * 0.15) are one instant (simultaneous updates, as in exact arithmetic)."""
        if self.periods is None:
            return s
        nd, eps = self.num_discrete, jnp.finfo(s.x.dtype).eps
        instants = s.samples * self.periods
        due = (s.t >= instants - 64 * eps * jnp.abs(instants)) & ~ready.fired
        at_sample = jnp.any(due)
        u = self.input(s.t, s.saturation, self.source.on_step(s.t))
        xd_next = self.system.mode_update(s.mode, s.t, s.x, u, due)
        x = jnp.where(at_sample, jnp.concatenate([xd_next, s.x[nd:]]), s.x)
        status = jnp.where(at_sample & ~jnp.all(jnp.isfinite(x)), SimulationStatus.NONFINITE_STATE, s.status)
        return dataclasses.replace(s, x=x, samples=s.samples + due, status=status)

    def refresh_saturation(self, s: LoopState) -> LoopState:
        """(3) After a breakpoint of an input tape, u may have jumped past a limit."""
        if not self.num_limit_guards:
            return s
        fresh = ev.initial_saturation(self.system, self.source.on_step(s.t)(s.t))
        return dataclasses.replace(s, saturation=jnp.where(s.at_breakpoint, fresh, s.saturation))

    def next_stop(self, s: LoopState):
        """The next time a step must end on: tf, the next breakpoint, the next sample time."""
        target = jnp.minimum(self.tf, self.next_breakpoint(s.t))
        if self.periods is not None:
            target = jnp.minimum(target, jnp.min(s.samples * self.periods))
        return target

    def step_end(self, s: LoopState, k0, target, below_spacing: bool):
        """The proposed step (the controller's initial step from k0 while none is chosen), where
        the step ends, t + h as a pair (`_controller.advance`), snapped onto the next stopping
        point when within rounding, and the step's exact size."""
        h = s.h
        if self.solver.adaptive and self.num_continuous:
            # the first step at least one unit of time's spacing (`least_step`): after it, steps
            # shrink only by rejections, which end the simulation at `smallest_step`
            first = jnp.minimum(self.controller.initial_step(s.t, s.x[self.num_discrete:], k0), self.dt_max)
            h = jnp.where(jnp.isnan(h), jnp.maximum(first, least_step(s.t, low_part=below_spacing)), h)
        if self.system.bounds_steps and self.num_continuous:
            # every attempt, a given first step and a held one too; a fixed step is shortened
            # where the bound is shorter (and takes dt again after it)
            h = jnp.minimum(h, self.step_limit(s.t, s.x))
        t_next, low_next = advance(s.t, s.t_low, h)
        # within rounding of the target: there (a pair's steps may be shorter than t's rounding:
        # stretched by at most 0.1% onto it; else the last step of a float32 dt just below its
        # decimal fell a sliver short of tf)
        rounding = 64 * jnp.finfo(s.t.dtype).eps * jnp.abs(target)
        slack = 1e-6 * h + (jnp.minimum(rounding, 1e-3 * h) if carries_low_part(s.t.dtype) else rounding)
        snap = elapsed(t_next, low_next, target, jnp.zeros_like(target)) <= slack
        t_next, low_next = jnp.where(snap, target, t_next), jnp.where(snap, 0.0, low_next)
        if self.fsal:  # until k0 has been evaluated, a step of size 0 that only does that
            t_next, low_next = jnp.where(s.k0_valid, t_next, s.t), jnp.where(s.k0_valid, low_next, s.t_low)
        return h, t_next, low_next, elapsed(s.t, s.t_low, t_next, low_next)

    def vector_field(self, s: LoopState, source):
        """This step's vector field (`held_vector_field`)."""
        return held_vector_field(self.system, s.mode, s.x[: self.num_discrete], s.saturation, source)

    def steps_below_spacing(self, s: LoopState) -> bool:
        """Whether a step may be shorter than t's spacing (a fact of the traced program): where
        time is a pair (`_controller.carries_low_part`) and the vector field does not read t,
        whose one-number value would stand still through such steps (a pulse narrower than
        t's spacing passed unseen, with SUCCESS); else steps end at one number's floor."""
        if not (carries_low_part(s.t.dtype) and self.num_continuous):
            return False
        return not reads_time(self.vector_field(s, self.source.on_step(s.t)), s.t, s.x[self.num_discrete:])

    def attempt_step(self, s: LoopState, ready: Ready, below_spacing: bool) -> Attempt:
        """(4) One step of the continuous state with the discrete state, the mode and each
        input's saturation held, so the right-hand side is smooth within the step."""
        nd, dtype = self.num_discrete, s.x.dtype
        xd, xc = s.x[:nd], s.x[nd:]
        source = self.source.on_step(s.t)
        target = self.next_stop(s)
        priming = ~s.k0_valid if self.fsal else jnp.asarray(False)
        if self.num_continuous:
            vector_field = self.vector_field(s, source)
            stiff = functools.partial(vector_field, dynamics_of=self.system.stiff_linearization())
            result = self.solver.step(vector_field, s.t, xc, lambda k0: self.step_end(s, k0, target, below_spacing)[3],
                                      s.k0 if self.fsal else None, stiff, s.linearization)
            h_proposed, t_next, low_next, h = self.step_end(s, result.k_first, target, below_spacing)
            xc1, coefficients = result.y1, result.coefficients
            # the error estimate too: a finite y1 whose last stage was NaN (an absurd y1 after an
            # over-long step) has a NaN estimate, which would otherwise grow the step it rejects
            finite = (jnp.all(jnp.isfinite(xc1)) & (True if result.error is None else jnp.all(jnp.isfinite(result.error)))
                      & (jnp.all(jnp.isfinite(coefficients)) if self.dense else True))
            accept, h_next, _ = self.controller.adapt(result.h, xc, xc1, result.error, finite)
            k_last, linearization = result.k_last, result.linearization
        else:
            h_proposed, t_next, low_next, h = self.step_end(s, None, target, below_spacing)
            xc1, coefficients = xc, jnp.zeros((NUM_COEFFICIENTS, 0), dtype)
            finite, accept, h_next, k_last = jnp.asarray(True), jnp.asarray(True), h_proposed, None
            linearization = None
        coefficients_d = jnp.zeros((NUM_COEFFICIENTS, nd), dtype).at[0].set(xd)
        return Attempt(t_end=t_next, t_end_low=low_next, x_end=jnp.concatenate([xd, xc1]),
                       coefficients=jnp.concatenate([coefficients_d, coefficients], axis=1),
                       h_proposed=h_proposed, h=h, accept=accept & ~ready.fired & ~priming,
                       finite=finite, h_next=h_next, k_last=k_last,
                       linearization=linearization if self.reuse_linearization else None, priming=priming,
                       event=jnp.asarray(False), which=jnp.asarray(-1, jnp.int32))

    def locate_event(self, s: LoopState, a: Attempt) -> tuple[LoopState, Attempt]:
        """(5) The earliest guard crossing inside an accepted step, located on the dense output
        (not differentiated), then two differentiable Newton steps on the guard that fired,
        theta <- theta - g / g', so that the event time carries its implicit-function-theorem
        sensitivity (with the reset's Jacobian: the saltation matrix). One step gives the first
        derivative; the second, with g' differentiated too, the second derivative (forward over
        forward mode: the monodromy of a hybrid limit cycle differentiated in a parameter). The
        step is cut there."""
        if not (self.num_limit_guards + self.num_transitions):
            return s, a
        source = self.source.on_step(s.t)
        g_step = lambda tt, xx: self.guards(tt, xx, s.mode, s.saturation, source)  # noqa: E731
        g_start, g_end = jax.vmap(g_step)(jnp.stack([s.t, a.t_end]), jnp.stack([s.x, a.x_end]))
        crossed = a.accept & (g_start < 0) & (g_end >= 0)
        room = s.events.count < self.max_events
        status = jnp.where(jnp.any(crossed) & ~room, SimulationStatus.TOO_MANY_EVENTS, s.status)
        event = jnp.any(crossed) & room

        def cut(a):
            t, h, dtype = s.t, a.h, s.x.dtype
            frozen = jax.lax.stop_gradient((a.coefficients, t, h, g_start, g_end))
            theta_located, which = ev.locate_first_crossing(
                lambda th: g_step(frozen[1] + th * frozen[2], eval_polynomial(frozen[0], th)),
                crossed, frozen[3], frozen[4], frozen[2], self.event_tol)
            g_of = lambda th: g_step(t + th * h, eval_polynomial(a.coefficients, th))[which]  # noqa: E731

            def newton(theta):
                g_val, g_dot = jax.jvp(g_of, (theta,), (jnp.ones((), dtype),))
                return theta - jnp.where(g_dot != 0, g_val / jnp.where(g_dot != 0, g_dot, 1), 0.0)

            theta = jnp.clip(newton(newton(theta_located)), 0.0, 1.0)
            powers = jnp.cumprod(jnp.concatenate([jnp.ones(1, dtype), jnp.full(NUM_COEFFICIENTS - 1, theta)]))
            coefficients = a.coefficients * powers[:, None]
            return coefficients, *advance(t, s.t_low, theta * h), eval_polynomial(coefficients, 1.0), which

        def no_cut(a):
            return a.coefficients, a.t_end, a.t_end_low, a.x_end, jnp.asarray(-1, jnp.int32)

        coefficients, t_end, t_end_low, x_end, which = jax.lax.cond(event, cut, no_cut, a)
        a = dataclasses.replace(a, coefficients=coefficients, t_end=t_end, t_end_low=t_end_low, x_end=x_end,
                                event=event, which=which)
        return dataclasses.replace(s, status=status), a

    def take_event(self, s: LoopState, ready: Ready, a: Attempt):
        """(6) Switch a saturation, or apply a transition's reset x+ = Delta(t, x-, u) (which
        may switch the mode or stop the simulation): the ready transition of stage 1 or the
        transition located in stage 5. Returns (x after, mode after, saturation, stop)."""
        L = self.num_limit_guards
        saturation, x_after, mode_after, stop = s.saturation, a.x_end, s.mode, jnp.asarray(False)
        if L:
            saturation = jnp.where(a.event & (a.which < L),
                                   ev.saturation_after_event(s.saturation, a.which, self.system.num_inputs),
                                   s.saturation)
        if self.num_transitions:
            located = a.event & (a.which >= L)
            k = jnp.where(ready.fired, ready.k, jnp.clip(a.which - L, 0, self.num_transitions - 1))
            t = jnp.where(ready.fired, s.t, a.t_end)
            x = jnp.where(ready.fired, s.x, a.x_end)
            u = self.input(t, saturation, self.source.on_step(s.t))
            x_after, mode_after, stop = jax.lax.cond(
                ready.fired | located, lambda: self.system.apply_transition(s.mode, k, t, x, u),
                lambda: (x, s.mode, jnp.asarray(False)))
        return x_after, mode_after, saturation, stop

    def project_onto_constraints(self, a: Attempt, x_after, took_transition):
        """(7) Optionally pull the end of the step back onto phi(x) = 0, keeping the dense
        output continuous; a state just reset by a transition is left as the reset made it."""
        if not (self.project and self.system.num_state_constraints):
            return a, x_after
        x_projected = project_to_constraints(self.system, a.x_end, iterations=3)
        coefficients = a.coefficients.at[1].add(x_projected - a.x_end)
        a = dataclasses.replace(a, coefficients=coefficients, x_end=x_projected)
        return a, jnp.where(took_transition, x_after, x_projected)

    def step_limit(self, t, x):
        """The system's bound on a step from (t, x) (a contact plant's, so that no body passes
        through a thin geometry unseen), not differentiated: step sizes are held."""
        return jax.lax.stop_gradient(self.system.step_size_bound(t, x))

    def adapt_step_size(self, s: LoopState, ready: Ready, a: Attempt, below_spacing: bool):
        """(8) The next step size and the failures of this attempt (non-finite state, a step
        size that collapsed). Returns (h_next, status)."""
        hold = ready.fired | a.priming
        status = s.status
        if self.solver.adaptive:
            # a step shortened to land on a stopping point does not shrink the next one
            h_next = jnp.where(a.accept & (a.h < a.h_proposed), jnp.maximum(a.h_proposed, a.h_next), a.h_next)
            h_next = jnp.where(hold, s.h, jnp.minimum(h_next, self.dt_max))
            tiny = ~a.accept & ~hold & ~(h_next > smallest_step(s.t, a.finite, low_part=below_spacing))  # a NaN step size too
            status = jnp.where(tiny, jnp.where(a.finite, SimulationStatus.STEP_SIZE_TOO_SMALL,
                                               SimulationStatus.NONFINITE_STATE), status)
        else:
            h_next = s.h
            status = jnp.where(a.finite | hold, status, SimulationStatus.NONFINITE_STATE)
        return h_next, status

    def iterate(self, s: LoopState) -> LoopState:
        if self.system.has_breakpoints:  # the system as this step sees it (its pieces fixed)
            return dataclasses.replace(self, system=self.system.on_step(s.t)).take_one_step(s)
        return self.take_one_step(s)

    def take_one_step(self, s: LoopState) -> LoopState:
        s, ready = self.find_ready_transition(s)
        s = self.apply_due_updates(s, ready)
        s = self.refresh_saturation(s)
        below_spacing = self.steps_below_spacing(s)
        a = self.attempt_step(s, ready, below_spacing)
        s, a = self.locate_event(s, a)
        x_after, mode_after, saturation, stop = self.take_event(s, ready, a)
        took_transition = a.event & (a.which >= self.num_limit_guards)
        a, x_after = self.project_onto_constraints(a, x_after, took_transition)
        h_next, status = self.adapt_step_size(s, ready, a, below_spacing)
        accept = a.accept & SimulationStatus.is_success(status)
        status = jnp.where((accept & stop) | (ready.fired & stop), SimulationStatus.STOPPED_BY_RESET, status)
        return self.record(s, ready, a, accept, x_after, mode_after, saturation, h_next, status)

    def record(self, s: LoopState, ready: Ready, a: Attempt, accept, x_after, mode_after, saturation,
               h_next, status) -> LoopState:
        """(9) The new state, the step's piece and the event into the buffers (written in place,
        under vmap too)."""
        x = jnp.where(ready.fired, x_after, jnp.where(accept, x_after, s.x))
        mode = jnp.where(ready.fired | accept, mode_after, s.mode)
        t, t_low = jnp.where(accept, a.t_end, s.t), jnp.where(accept, a.t_end_low, s.t_low)
        if self.windowed:
            def write(buffer, n, value, pred):
                return buffer.at[0].set(jnp.where(pred, value, buffer[0]))
        else:
            def write(buffer, n, value, pred):
                return buffer.at[n].set(value, pred=pred)
        p = s.pieces
        if self.dense:
            n = p.count
            p = PieceRecord(t_start=write(p.t_start, n, s.t, accept), t_end=write(p.t_end, n, a.t_end, accept),
                            coefficients=write(p.coefficients, n, a.coefficients, accept),
                            modes=write(p.modes, n, s.mode, accept), count=n + accept)
        e = s.events
        if self.num_limit_guards + self.num_transitions:
            recorded = (accept & a.event) | ready.fired
            index = jnp.where(ready.fired, self.num_limit_guards + ready.k, a.which).astype(jnp.int32)
            n = e.count
            e = EventRecord(times=write(e.times, n, jnp.where(ready.fired, s.t, a.t_end), recorded),
                            indices=write(e.indices, n, index, recorded), modes=write(e.modes, n, mode, recorded),
                            states=write(e.states, n, x, recorded), count=n + recorded)
        k0, k0_valid = s.k0, s.k0_valid
        if self.fsal:
            k0 = jnp.where(accept | a.priming, a.k_last, s.k0)
            k0_valid = jnp.asarray(True)
        return LoopState(
            t=t, t_low=t_low, x=x, mode=mode, saturation=saturation, h=jax.lax.stop_gradient(h_next), k0=k0,
            k0_valid=k0_valid, linearization=a.linearization.after(accept) if self.reuse_linearization else None,
            samples=s.samples,
            at_breakpoint=jnp.where(accept, ~a.event & (a.t_end >= self.next_breakpoint(s.t)), s.at_breakpoint),
            status=status, iterations=s.iterations + 1,
            rejected=s.rejected + (~accept & ~ready.fired & ~a.priming), accepted=s.accepted + accept,
            pieces=p, events=e)

    # ----- the whole loop -------------------------------------------------------------------

    def run(self, t0, x0, h0, status, autodiff: str) -> LoopState:
        """The loop from its start to its end, differentiable as `autodiff` says: "forward"
        (the plain loop, for `jax.jvp`), "reverse" (`_reverse.run_reverse`) or "adjoint"
        (`_reverse.run_adjoint`)."""
        if autodiff == "reverse":
            return run_reverse(self, t0, x0, h0, status)
        if autodiff == "adjoint":
            return run_adjoint(self, t0, x0, h0, status)
        return self.run_loop(t0, x0, h0, status)

    def before_tf(self, s: LoopState):
        """Whether time has not reached tf (t itself may round to tf, short of it)."""
        return elapsed(s.t, s.t_low, self.tf, jnp.zeros_like(s.t)) > 0

    def continues(self, s: LoopState):
        """Whether the loop takes another iteration."""
        return (s.status == SimulationStatus.SUCCESS) & self.before_tf(s) & (s.iterations < self.max_steps)

    def run_loop(self, t0, x0, h0, status) -> LoopState:
        return eqxi.while_loop(self.continues, self.iterate, self.initial_state(t0, x0, h0, status),
                               max_steps=self.max_steps, kind="lax", buffers=LoopState.buffers)


def held_vector_field(system, mode, xd, saturation, inputs):
    r"""$\dot x_c = f(t, x_c)$ with the discrete state `xd`, the `mode` and each input's
    `saturation` held (`dynamics_of`: the system whose dynamics, e.g. its stiff linearization)."""
    def f(t, xc, dynamics_of=system):
        u = ev.saturated_input(system, inputs(t), saturation)
        return dynamics_of.mode_dynamics(mode, t, jnp.concatenate([xd, xc]), u)
    return f


def reads_time(field, t, xc) -> bool:
    """Whether the vector field `field(t, xc)` reads t: where it does, float32 steps keep one
    number's floor (`Loop.steps_below_spacing`)."""
    return reads_argument(field, (t, xc), 0)


def vector_field_reads_time(system, source, t0, x0) -> bool:
    """`reads_time` of the system's vector field with its inputs, at its initial mode and
    saturation (for the advice of a float32 run whose steps became too small)."""
    nd, inputs = system.num_discrete_states, source.on_step(t0)
    field = held_vector_field(system, system.initial_mode, x0[:nd], ev.initial_saturation(system, inputs(t0)), inputs)
    return reads_time(field, t0, x0[nd:])


def initial_status(system, source, t0, tf, x0):
    """The failures visible before the first step (inside `jit`, where they cannot raise): a
    time span that is not finite with t0 < tf, a non-finite x0 or u(t0), a NaN parameter."""
    parameters = [jnp.any(jnp.isnan(leaf)) for leaf in jax.tree.leaves(eqx.filter(system, eqx.is_inexact_array))]
    failures = [(~(jnp.isfinite(t0) & jnp.isfinite(tf) & (tf > t0)), SimulationStatus.INVALID_TIME_SPAN),
                (~jnp.all(jnp.isfinite(x0)), SimulationStatus.NONFINITE_INITIAL_STATE),
                (~jnp.all(jnp.isfinite(source(t0))), SimulationStatus.NONFINITE_INPUT),
                (jnp.any(jnp.stack(parameters)) if parameters else jnp.asarray(False),
                 SimulationStatus.NAN_PARAMETER)]
    status = jnp.asarray(int(SimulationStatus.SUCCESS), jnp.int32)
    for failed, failure in reversed(failures):  # the first failure in the list wins
        status = jnp.where(failed, jnp.asarray(int(failure), jnp.int32), status)
    return status


def run_simulation(system, solver, controller, source, t0, tf, x0, h0, dt_max, event_tol, max_steps: int,
                   max_events: int, dense: bool, constraint_projection: bool, autodiff: str) -> SimulatedTrajectory:
    """Project x0 onto the state constraints, run the loop, and package the trajectory."""
    dtype, eps = x0.dtype, jnp.finfo(x0.dtype).eps
    status = initial_status(system, source, t0, tf, x0)
    if system.num_state_constraints:
        x0 = project_to_constraints(system, x0)
        residual = jnp.max(jnp.abs(system.state_constraints(x0)))
        status = jnp.where(residual <= jnp.sqrt(eps) * (1 + jnp.max(jnp.abs(x0))), status,
                           SimulationStatus.CONSTRAINT_PROJECTION_FAILED)
    nc = system.num_continuous_states
    num_guards = ev.num_limit_guards(system) + len(system.transitions)
    # First same as last: the solver's last stage is the next step's first, unless something
    # can change the vector field between steps (a discrete update, an event, a projection, a
    # new piece of an input tape): a static fact.
    fsal = (solver.fsal and nc > 0 and system.num_discrete_states == 0 and num_guards == 0
            and not source.has_breakpoints and not system.has_breakpoints and not (constraint_projection and system.num_state_constraints))
    periods = jnp.asarray(system.sample_times, dtype) if system.sample_times else None
    loop = Loop(system, solver, controller, source, tf, dt_max, event_tol, periods, max_steps, max_events,
                dense, constraint_projection, fsal)
    s = loop.run(t0, x0, h0, status, autodiff)
    status = jnp.where((s.status == SimulationStatus.SUCCESS) & loop.before_tf(s), SimulationStatus.MAX_STEPS_REACHED,
                       s.status)
    p = s.pieces
    t_start, t_end, coefficients, modes, count = p.t_start, p.t_end, p.coefficients, p.modes, p.count
    if not dense:  # keep the initial point and the final state only
        last = jnp.zeros((1, NUM_COEFFICIENTS, x0.shape[0]), dtype).at[0, 0].set(s.x)
        t_start = jnp.concatenate([t_start, s.t[None]])
        t_end = jnp.concatenate([t_end, s.t[None]])
        coefficients, count = jnp.concatenate([coefficients, last]), jnp.asarray(2)
        modes = jnp.concatenate([modes, s.mode[None]])
    e = s.events
    return SimulatedTrajectory(
        state_trajectory=Trajectory(t_start, t_end, coefficients, count, side="left"), modes=modes,
        t_final=s.t, status=status, event_times=e.times, event_indices=e.indices, event_modes=e.modes,
        event_states=e.states, num_events=e.count, num_rejected_steps=s.rejected,
        num_accepted_steps=s.accepted, system=system,
        inputs=source, dense=dense)
