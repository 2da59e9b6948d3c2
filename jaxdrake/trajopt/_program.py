r"""Trajectory optimization programs: direct transcription, direct collocation and shooting.

All three put the state $x_k$ and input $u_k$ at knots $t_k = k\,T/(N-1)$, $k = 0..N-1$, among
the decision variables, with the duration $T$ (optionally free) and system parameters $p$
(optionally free); they differ in the constraint tying $x_{k+1}$ to $x_k$:

- transcription: $x_{k+1} = \Phi_h(t_k, x_k, u_k)$ — one step of an explicit rule (Euler,
  midpoint, RK4) with $u$ held, or the discrete update of a discrete system;
- Hermite-Simpson collocation (Drake's `DirectCollocation`): cubic states through
  $(x_k, f_k)$, $(x_{k+1}, f_{k+1})$ and first-order-hold inputs, with
  $x_{k+1} - x_k = \tfrac h6 (f_k + 4 f_c + f_{k+1})$,
  $x_c = \tfrac12(x_k + x_{k+1}) + \tfrac h8 (f_k - f_{k+1})$, $u_c = \tfrac12 (u_k + u_{k+1})$;
- multiple shooting: $x_{k+1} = $ `simulate`$(x_k, u_k \to u_{k+1})$ at the simulator's
  tolerance, derivatives by forward-mode through the simulation.

Every cost and constraint is local to a knot, a segment or the two ends (see `_nlp.py`), so
the constraint Jacobian and the Lagrangian Hessian are sparse and assembled from small
autodiff blocks.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse.linalg

from .._numbers import device_array
from ..simulation import FIXED_STEP_RULES, discrete_step, simulate
from ..systems import System
from ..systems import require_plain_system
from ..trajectories import Trajectory
from ._nlp import NonlinearProgram, SolverResult, Term, resolve_solver, solve
from .._status import Reported
from ._status import SolverStatus


class TrajectoryOptimizationResult(eqx.Module, Reported):
    """A solved trajectory program, on the host (the solve is IPOPT's or SciPy's):

    - `states`, `inputs`: `Trajectory` objects (cubic / first-order hold for collocation, the
      rule's own hold for transcription); `times`, `knot_states`, `knot_inputs` their knots;
    - `duration`, `parameters` (None without free parameters), `max_defect` (the largest
      dynamic defect);
    - the solver's report: `status` (a `SolverStatus`; `success` and `message` from it),
      `cost`, `constraint_violation`, `iterations`, `solve_time` (s), `solver` (its name),
      `log` (per iteration) and `z` (the decision vector, for `initial_guess=`)."""

    states: Trajectory
    inputs: Trajectory
    times: np.ndarray
    knot_states: np.ndarray
    knot_inputs: np.ndarray
    duration: float
    parameters: np.ndarray | None
    max_defect: float
    status: SolverStatus
    cost: float
    constraint_violation: float
    iterations: int
    solve_time: float
    solver: str
    log: list
    z: np.ndarray
    status_type = SolverStatus

    def __repr__(self):
        return (f"TrajectoryOptimizationResult(success={self.success}, message={self.message!r}, "
                f"cost={self.cost:.6g}, duration={self.duration:.6g}, iterations={self.iterations}, "
                f"max_defect={self.max_defect:.2e}, solve_time={self.solve_time:.3f} s)")


def _split(v, sizes):
    out, start = [], 0
    for size in sizes:
        out.append(v[start: start + size])
        start += size
    return out


def _vector(value, size, label):
    value = np.asarray(value, float)
    if value.ndim == 0:
        value = np.full(size, float(value))
    if value.shape != (size,):
        raise ValueError(f"{label} must have shape ({size},), got {value.shape}")
    return value


class _TrajectoryProgram:
    """What transcription, collocation and shooting share: the decision layout, bounds, costs,
    constraints, the initial guess and the solve."""

    method = ""

    def __init__(self, system, num_time_samples: int, *, duration=None, parameters=None,
                 parameter_bounds=None):
        if parameters is not None:
            if not callable(system) or isinstance(system, System):
                raise TypeError("with `parameters`, pass `system` as a function p -> System")
            self._p0 = np.atleast_1d(np.asarray(parameters, float))
            self._make_system = system
            with jax.enable_x64(True):
                system = system(jnp.asarray(self._p0))
        else:
            self._p0 = np.zeros(0)
            self._make_system = None
        require_plain_system(system, type(self).__name__,
                             "optimize a deterministic system (one mode of a hybrid one)")
        if not isinstance(num_time_samples, (int, np.integer)) or num_time_samples < 2:
            raise ValueError(f"num_time_samples must be an int >= 2, got {num_time_samples!r}")
        self.system = system
        self.num_time_samples = N = int(num_time_samples)
        self.num_states, self.num_inputs = n, m = system.num_states, system.num_inputs
        self.num_parameters = len(self._p0)
        self._duration_bounds = self._check_duration(duration)
        self.free_duration = self._duration_bounds[0] != self._duration_bounds[1]
        self.num_globals = int(self.free_duration) + self.num_parameters
        self.num_variables = N * (n + m) + self.num_globals
        self._lower = np.full(self.num_variables, -np.inf)
        self._upper = np.full(self.num_variables, np.inf)
        if self.free_duration:
            self._lower[self._globals[0]], self._upper[self._globals[0]] = self._duration_bounds
        if self.num_parameters:
            lo, hi = parameter_bounds if parameter_bounds is not None else (-np.inf, np.inf)
            self._lower[self._globals[int(self.free_duration):]] = _vector(lo, self.num_parameters, "parameter lower bound")
            self._upper[self._globals[int(self.free_duration):]] = _vector(hi, self.num_parameters, "parameter upper bound")
        if system.input_limits is not None:
            self.add_input_bounds(*system.input_limits)
        self._costs, self._constraints = [], []
        self._add_dynamics()
        self._nlp = None

    # ----- layout ---------------------------------------------------------------------------

    def _check_duration(self, duration):
        if self.system.has_discrete_state:
            fixed = (self.num_time_samples - 1) * self.system.sample_time
            if duration is not None and not np.isclose(np.asarray(duration, float), fixed).all():
                raise ValueError(f"{self.system.name} is discrete (period {self.system.sample_time}): "
                                 f"the duration is (N - 1) * period = {fixed}, not {duration}")
            return fixed, fixed
        if duration is None:
            raise ValueError("give the duration T (a number) or its bounds (T_min, T_max) to make it free")
        lo, hi = (duration, duration) if np.ndim(duration) == 0 else tuple(duration)
        lo, hi = float(lo), float(hi)
        if not (0 < lo <= hi < np.inf):
            raise ValueError(f"duration bounds must satisfy 0 < T_min <= T_max < inf, got ({lo}, {hi})")
        return lo, hi

    @property
    def _globals(self):
        return np.arange(self.num_variables - self.num_globals, self.num_variables)

    def _state_index(self, k):
        return np.arange(k * self.num_states, (k + 1) * self.num_states)

    def _input_index(self, k):
        start = self.num_time_samples * self.num_states + k * self.num_inputs
        return np.arange(start, start + self.num_inputs)

    def _knot_index(self, k):
        return np.concatenate([self._state_index(k), self._input_index(k)])

    def _unpack_globals(self, g):
        """(T, h, system) from the global decision variables."""
        T = g[0] if self.free_duration else self._duration_bounds[0]
        p = g[int(self.free_duration):]
        system = self._make_system(p) if self._make_system is not None else self.system
        return T, T / (self.num_time_samples - 1), system

    def _knot_term(self, name, fn, knots, lower=None, upper=None):
        """fn(t, x, u, h, system) at each knot in `knots`."""
        n, m = self.num_states, self.num_inputs
        knots = np.asarray(knots)
        idx = np.stack([np.concatenate([self._knot_index(k), self._globals]) for k in knots])

        def term(v, i):
            x, u, g = _split(v, (n, m, self.num_globals))
            T, h, system = self._unpack_globals(g)
            return jnp.atleast_1d(fn(jnp.asarray(knots)[i] * h, x, u, h, system))

        return Term(name, term, idx, lower, upper)

    def _segment_term(self, name, fn, lower=None, upper=None):
        """fn(t_k, x_k, u_k, x_{k+1}, u_{k+1}, h, system) on every segment."""
        n, m = self.num_states, self.num_inputs
        idx = np.stack([np.concatenate([self._knot_index(k), self._knot_index(k + 1), self._globals])
                        for k in range(self.num_time_samples - 1)])

        def term(v, k):
            x0, u0, x1, u1, g = _split(v, (n, m, n, m, self.num_globals))
            T, h, system = self._unpack_globals(g)
            return jnp.atleast_1d(fn(k * h, x0, u0, x1, u1, h, system))

        return Term(name, term, idx, lower, upper)

    def _ends_term(self, name, fn, lower=None, upper=None):
        """fn(x_0, x_N, T, p) once."""
        n = self.num_states
        idx = np.concatenate([self._state_index(0), self._state_index(self.num_time_samples - 1),
                              self._globals])[None]

        def term(v, k):
            x0, xf, g = _split(v, (n, n, self.num_globals))
            T, _, _ = self._unpack_globals(g)
            return jnp.atleast_1d(fn(x0, xf, T, g[int(self.free_duration):]))

        return Term(name, term, idx, lower, upper)

    def _add(self, term, kind):
        (self._costs if kind == "cost" else self._constraints).append(term)
        self._nlp = None

    # ----- the user's costs and constraints -------------------------------------------------

    def add_running_cost(self, fn: Callable):
        r"""Add $\int_0^T \ell(t, x, u)\,dt$ with `fn(t, x, u) -> scalar`, by the method's
        quadrature (for collocation its `quadrature`: Simpson's rule on the cubic, or Drake's
        trapezoid on the knots; the rule's rectangle for transcription; the simulation itself
        for shooting)."""
        self._add(self._running_cost_term(fn), "cost")
        return self

    def add_final_cost(self, fn: Callable):
        """Add `fn(T, x_final) -> scalar`."""
        self._add(self._ends_term("final cost", lambda x0, xf, T, p: fn(T, xf)), "cost")
        return self

    def add_duration_cost(self, weight: float = 1.0):
        """Add `weight * T` (minimum time; needs a free duration)."""
        if not self.free_duration:
            raise ValueError("add_duration_cost needs a free duration: pass duration=(T_min, T_max)")
        self._add(self._ends_term("duration cost", lambda x0, xf, T, p: weight * T), "cost")
        return self

    def add_parameter_cost(self, fn: Callable):
        """Add `fn(p) -> scalar` on the free parameters."""
        if not self.num_parameters:
            raise ValueError("add_parameter_cost needs parameters=... at construction")
        self._add(self._ends_term("parameter cost", lambda x0, xf, T, p: fn(p)), "cost")
        return self

    def _set_knot_bounds(self, index, lower, upper, label):
        lower, upper = _vector(lower, len(index), label + " lower"), _vector(upper, len(index), label + " upper")
        bad = np.flatnonzero(lower > upper)
        if len(bad):
            raise ValueError(f"{label}: lower bound {lower[bad[0]]} > upper bound {upper[bad[0]]} "
                             f"at coordinate {bad[0]}")
        self._lower[index] = np.maximum(self._lower[index], lower)
        self._upper[index] = np.minimum(self._upper[index], upper)
        clash = np.flatnonzero(self._lower[index] > self._upper[index])
        if len(clash):
            raise ValueError(f"{label} contradict earlier bounds at coordinate {clash[0]}: "
                             f"[{self._lower[index][clash[0]]}, {self._upper[index][clash[0]]}] is empty")
        self._nlp = None

    def _fix(self, k, value, label):
        value = _vector(value, self.num_states, label)
        free = np.isnan(value)
        index = self._state_index(k)[~free]
        self._set_knot_bounds(index, value[~free], value[~free], label)

    def set_initial_state(self, x0):
        """Fix x(0) (NaN entries stay free)."""
        self._fix(0, x0, "initial state")
        return self

    def set_final_state(self, xf):
        """Fix x(T) (NaN entries stay free)."""
        self._fix(self.num_time_samples - 1, xf, "final state")
        return self

    def add_state_bounds(self, lower, upper, knots=None):
        """lower <= x_k <= upper at `knots` (default all)."""
        knots = range(self.num_time_samples) if knots is None else knots
        for k in knots:
            self._set_knot_bounds(self._state_index(k), lower, upper, f"state bounds at knot {k}")
        return self

    def add_input_bounds(self, lower, upper):
        """lower <= u_k <= upper at every knot (the system's input limits are added already)."""
        for k in range(self.num_time_samples):
            self._set_knot_bounds(self._input_index(k), lower, upper, f"input bounds at knot {k}")
        return self

    def add_path_constraint(self, fn: Callable, lower, upper):
        """lower <= fn(t, x, u) <= upper at every knot."""
        lower, upper = np.atleast_1d(np.asarray(lower, float)), np.atleast_1d(np.asarray(upper, float))
        if np.any(lower > upper):
            raise ValueError(f"path constraint: lower {lower} > upper {upper}")
        term = self._knot_term("path constraint", lambda t, x, u, h, s: fn(t, x, u),
                               range(self.num_time_samples), lower, upper)
        self._add(term, "constraint")
        return self

    def add_boundary_constraint(self, fn: Callable, lower, upper):
        """lower <= fn(x_0, x_final) <= upper."""
        lower, upper = np.atleast_1d(np.asarray(lower, float)), np.atleast_1d(np.asarray(upper, float))
        if np.any(lower > upper):
            raise ValueError(f"boundary constraint: lower {lower} > upper {upper}")
        self._add(self._ends_term("boundary constraint", lambda x0, xf, T, p: fn(x0, xf), lower, upper),
                  "constraint")
        return self

    def add_periodicity(self, indices=None, offset=0.0):
        """x_final[i] = x_0[i] + offset[i] for i in `indices` (default all states)."""
        indices = np.arange(self.num_states) if indices is None else np.atleast_1d(indices)
        offset = np.broadcast_to(np.asarray(offset, float), indices.shape)
        return self.add_boundary_constraint(lambda x0, xf: xf[indices] - x0[indices] - offset,
                                            np.zeros(len(indices)), np.zeros(len(indices)))

    # ----- the program and its solution -----------------------------------------------------

    @property
    def nlp(self) -> NonlinearProgram:
        """The sparse nonlinear program (compiled on first use, again after a change)."""
        if self._nlp is None:
            if not self._costs:
                raise ValueError("the program has no cost: add a running, final or duration cost")
            self._nlp = NonlinearProgram(self.num_variables, self._costs, self._constraints,
                                         self._lower, self._upper)
        return self._nlp

    def initial_guess(self, states=None, inputs=None, duration=None, parameters=None) -> np.ndarray:
        """The decision vector for a guess: `states` / `inputs` each a `Trajectory`, a function
        of time, an array of knot values ((N, n) / (N, m)) or None (states: the straight line
        between the fixed initial and final states; inputs: zero), clipped into the bounds.
        With neither `states` nor `inputs`, the straight line then takes one step toward the
        dynamics (`toward_dynamics`), as `solve` does."""
        z = self._interpolated_guess(states, inputs, duration, parameters)
        if states is None and inputs is None:
            z = self.toward_dynamics(z)
        return z

    def _interpolated_guess(self, states, inputs, duration, parameters) -> np.ndarray:
        """`initial_guess` before the step toward the dynamics."""
        N, n, m = self.num_time_samples, self.num_states, self.num_inputs
        T = float(duration) if duration is not None else (
            self._duration_bounds[0] if not self.free_duration else float(np.mean(self._duration_bounds)))
        times = np.linspace(0.0, T, N)
        x0 = np.where(self._lower[self._state_index(0)] == self._upper[self._state_index(0)],
                      self._lower[self._state_index(0)], 0.0)
        xf_index = self._state_index(N - 1)
        xf = np.where(self._lower[xf_index] == self._upper[xf_index], self._lower[xf_index], x0)
        line = x0 + np.linspace(0, 1, N)[:, None] * (xf - x0)
        X = self._guess_values(states, times, (N, n), line, "states")
        U = self._guess_values(inputs, times, (N, m), np.zeros((N, m)), "inputs")
        z = np.concatenate([X.ravel(), U.ravel()])
        if self.free_duration:
            z = np.append(z, T)
        if self.num_parameters:
            z = np.append(z, self._p0 if parameters is None else _vector(parameters, self.num_parameters, "parameters"))
        z = np.clip(z, self._lower, self._upper)
        if not np.all(np.isfinite(z)):
            raise ValueError("the initial guess has non-finite values")
        return z

    def toward_dynamics(self, z, *, exact_hessian: bool | None = None) -> np.ndarray:
        r"""One Gauss-Newton step from the decision vector z toward the dynamics: the least
        change $\delta$ of the free knot states and inputs (the duration and parameters kept)
        with $c(z) + J \delta = 0$ for the dynamic defects c (LSQR's least-norm solution),
        clipped into the bounds, and kept only where it lowers $|c|$ (else z itself).

        A straight line in state space is no trajectory of a mechanical system (its angles
        move while its velocities stay at the endpoints' values, with zero input), and IPOPT
        started there can stop at a point of locally least infeasibility (the notes' pendulum
        swing-up with a free duration); the step puts velocities and inputs in line with the
        motion (the pendulum's defects fall 3.4-fold). Where the linearization misleads (the
        acrobot's and the cart-pole's swing-ups: the step raises the defects), the line stays.
        (`exact_hessian`: which compiled Jacobian program to use, the one the solve uses.)"""
        exact = (self._hessian_approximation == "exact") if exact_hessian is None else exact_hessian
        z = np.asarray(z, float)
        rows = (self.num_time_samples - 1) * self.num_states  # the dynamics term comes first
        defects = self.nlp.constraint_values(z)[:rows]
        knots = self.num_variables - self.num_globals
        free = np.flatnonzero(self._lower[:knots] < self._upper[:knots])
        jacobian = self.nlp.jacobian(z, for_hessian=exact)[:rows][:, free]
        step = scipy.sparse.linalg.lsqr(jacobian, -defects, atol=1e-12, btol=1e-12)[0]
        moved = z.copy()
        moved[free] += step
        moved = np.clip(moved, self._lower, self._upper)
        lower = np.linalg.norm(self.nlp.constraint_values(moved)[:rows]) < np.linalg.norm(defects)
        return moved if lower else z  # a NaN norm compares False

    @staticmethod
    def _guess_values(spec, times, shape, default, label):
        if spec is None:
            return default
        if isinstance(spec, Trajectory):
            values = np.asarray(spec.state(jnp.asarray(times)))
        elif callable(spec):
            values = np.stack([np.asarray(spec(t), float).reshape(shape[1]) for t in times])
        else:
            values = np.asarray(spec, float)
        if values.shape != shape:
            raise ValueError(f"initial guess for the {label} must give shape {shape}, got {values.shape}")
        return values

    def solve(self, states=None, inputs=None, duration=None, parameters=None, *, solver="auto",
              tol=1e-8, max_iterations=3000, hessian=None, progress=True, verbose=False,
              options=None, initial_guess=None) -> TrajectoryOptimizationResult:
        """Solve from a guess (see `initial_guess`: by default the straight line between the
        fixed initial and final states, one step toward the dynamics; or pass a decision vector
        as `initial_guess`) with `solver` ("auto": IPOPT if available, else SciPy's trust-constr;
        "ipopt"; "scipy"). `hessian`: "exact" (the sparse autodiff Lagrangian Hessian; default
        for transcription and collocation) or "limited-memory" (IPOPT's L-BFGS, as Drake runs
        IPOPT; compiles faster, more iterations). `progress`: a progress bar of the iterations (drawn once the solve has run 2 s);
        `verbose` the solver's own log.
        Never raises on a failed solve: check `result.success` and `result.message`."""
        z0 = (self._interpolated_guess(states, inputs, duration, parameters) if initial_guess is None
              else np.asarray(initial_guess, float))
        if z0.shape != (self.num_variables,):
            raise ValueError(f"initial_guess must have shape ({self.num_variables},), got {z0.shape}")
        kwargs = dict(tol=tol, max_iterations=max_iterations, progress=progress, verbose=verbose,
                      options=options)
        hessian = self._hessian_approximation if hessian is None else hessian
        if hessian not in ("exact", "limited-memory"):
            raise ValueError(f"hessian must be 'exact' or 'limited-memory', got {hessian!r}")
        solver = resolve_solver(solver)
        if hessian != "exact":
            if solver == "scipy":
                raise ValueError("the SciPy solver needs hessian='exact'")
            kwargs["hessian"] = hessian
        self.nlp.compile_for_solver(z0, exact_hessian=hessian == "exact", also=(lambda: self._solution(z0),))
        if initial_guess is None and states is None and inputs is None:
            z0 = self.toward_dynamics(z0, exact_hessian=hessian == "exact")
        return self._result(solve(self.nlp, z0, solver, **kwargs))

    _hessian_approximation = "exact"

    def _result(self, result: SolverResult) -> TrajectoryOptimizationResult:
        report = {field.name: getattr(result, field.name) for field in dataclasses.fields(result)}
        return TrajectoryOptimizationResult(**self._solution(result.z), **report)

    def _solution(self, z) -> dict:
        """The trajectories and knot values of the decision vector z (all but the solver's report)."""
        N, n, m = self.num_time_samples, self.num_states, self.num_inputs
        X, U = z[: N * n].reshape(N, n), z[N * n: N * (n + m)].reshape(N, m)
        g = z[N * (n + m):]
        T = float(g[0]) if self.free_duration else self._duration_bounds[0]
        p = g[int(self.free_duration):] if self.num_parameters else None
        times = np.linspace(0.0, T, N)
        defects = self.nlp.constraint_values(z)[: (N - 1) * n]  # the dynamics term comes first
        with jax.enable_x64(True):
            states, inputs = self._reconstruct(times, X, U, g)
        # in the session's own precision (float32 unless x64 is on): arrays made under the x64
        # context would not mix with the user's (a simulation with the inputs as its tape)
        states, inputs = jax.tree.map(lambda a: device_array(np.asarray(a)), (states, inputs))
        return dict(states=states, inputs=inputs, times=times, knot_states=X, knot_inputs=U, duration=T,
                    parameters=p, max_defect=float(np.max(np.abs(defects))))

    def _add_dynamics(self):
        term = self._segment_term(f"{self.method} defects", self._defect,
                                  np.zeros(self.num_states), np.zeros(self.num_states))
        self._dynamics_term = dataclasses.replace(term, size=self.num_states, **self._defect_derivatives())
        self._constraints.append(self._dynamics_term)

    def _defect_derivatives(self) -> dict:
        """The defect term's own `jacobian` / `hessian` where its structure gives them; none
        (autodiff of the defect) by default."""
        return {}


def _knots_then_midpoints(evaluate, V, t0, h, n):
    r"""`evaluate(times, W) -> (F, ...)` (F: f at the rows of W, then anything else) at the knots
    of K consecutive segments (rows of V = [w_k; w_{k+1}], $w = (x, u)$, starting at times
    t0), each knot once (segment k's end is segment k+1's start), then at the midpoints
    $w_c = (x_c, u_c)$, $x_c = \tfrac12(x_k + x_{k+1}) + \tfrac h8 (f_k - f_{k+1})$,
    $u_c = \tfrac12(u_k + u_{k+1})$, which need the knots' f first. A two-step loop, so the
    traced program holds ONE copy of `evaluate` (the vector field or its derivatives), at half
    the compile time of two; K + 1 evaluations per step (the midpoints' step repeats its last).
    Returns the knots' outputs (K + 1 rows), the midpoints' (K rows) and W_c."""
    L = V.shape[1] // 2

    def step(points, _):
        t, W = points
        out = evaluate(t, W)
        F = out[0]
        Wc = jnp.concatenate([(W[:-1, :n] + W[1:, :n]) / 2 + h / 8 * (F[:-1] - F[1:]),
                              (W[:-1, n:] + W[1:, n:]) / 2], axis=1)
        tc = t[:-1] + h / 2
        return (jnp.concatenate([tc, tc[-1:]]), jnp.concatenate([Wc, Wc[-1:]])), (out, Wc)

    t0 = jnp.asarray(t0, V.dtype)
    start = (jnp.concatenate([t0, t0[-1:] + h]), jnp.concatenate([V[:, :L], V[-1:, L:2 * L]]))
    _, (out, Wc) = jax.lax.scan(step, start, length=2)
    return jax.tree.map(lambda a: a[0], out), jax.tree.map(lambda a: a[1][:-1], out), Wc[0]


def _dynamics_at(system, n):
    """(times, W) -> (f at each row of W,): the `evaluate` of `_knots_then_midpoints`."""
    return lambda times, W: (jax.vmap(system.dynamics)(times, W[:, :n], W[:, n:]),)


def _reads_state(fn, n, m) -> bool:
    """Whether `fn(t, x, u)`'s traced program references x at all (conservatively: any use)."""
    with jax.enable_x64(True):
        closed = jax.make_jaxpr(fn)(0.0, np.zeros(n), np.zeros(m))
    x = closed.jaxpr.invars[1]
    return x in closed.jaxpr.outvars or any(x in eqn.invars for eqn in closed.jaxpr.eqns)


def _hermite_simpson_batched(system, n, m, h):
    r"""The Hermite-Simpson defects of all N - 1 segments at once (a batched `Term`: every knot's
    vector field evaluated once, not once per segment touching it), with their Jacobian and
    Lagrangian Hessian blocks by the chain rule around ONE traced copy of f's derivatives:
    $c = x_1 - x_0 - \tfrac h6 (f_0 + 4 f_c + f_1)$, $x_c = \tfrac12(x_0 + x_1) + \tfrac h8 (f_0 - f_1)$,
    $u_c = \tfrac12 (u_0 + u_1)$, over v = [w_0; w_1], $w_j = (x_j, u_j)$:
    $\partial c = [-I\,0\,I\,0] - \tfrac h6 (J_0 P_0 + J_1 P_1 + 4 J_c\, \partial w_c)$,
    $\nabla^2 (\lambda\cdot c) = -\tfrac h6 \big(P_0^T \nabla^2(\mu_0\cdot f)(w_0) P_0
    + P_1^T \nabla^2(\mu_1\cdot f)(w_1) P_1 + 4\, \partial w_c^T \nabla^2(\lambda\cdot f)(w_c)\, \partial w_c\big)$
    with $g = (\partial f/\partial x)(w_c)^T \lambda$, $\mu_{0,1} = \lambda \pm \tfrac h2 g$.
    (Autodiff of a per-segment defect traces f's derivatives for the knots and again for the
    midpoint, and evaluates every inner knot twice.)"""
    L = n + m
    eye_n, eye_m = np.eye(n), np.eye(m)
    plain = np.concatenate([-eye_n, np.zeros((n, m)), eye_n, np.zeros((n, m))], axis=1)
    average = np.concatenate([np.concatenate([eye_n, np.zeros((n, m)), eye_n, np.zeros((n, m))], axis=1),
                              np.concatenate([np.zeros((m, n)), eye_m, np.zeros((m, n)), eye_m], axis=1)]) / 2

    def f(t, w):
        return system.dynamics(t, w[:n], w[n:])

    def value_and_jacobian(t, w):  # (f, its Jacobian): f traced once
        J, value = jax.jacfwd(lambda w: (lambda y: (y, y))(f(t, w)), has_aux=True)(w)
        return value, J

    def value_jacobian_tensor(t, w):  # (f, its Jacobian, its second-derivative tensor)
        T, (value, J) = jax.jacfwd(lambda w: (lambda y, J: (J, (y, J)))(*value_and_jacobian(t, w)),
                                   has_aux=True)(w)
        return value, J, T

    def midpoint_jacobians(J):  # d w_c / d v per segment, (K, L, 2L), from the knots' (K + 1, n, L)
        dx = h / 8 * jnp.concatenate([J[:-1], -J[1:]], axis=2)
        return average + jnp.concatenate([dx, jnp.zeros((dx.shape[0], m, 2 * L), dx.dtype)], axis=1)

    def defects(V, ks):
        (F,), (Fc,), _ = _knots_then_midpoints(_dynamics_at(system, n), V, ks * h, h, n)
        return V[:, L:L + n] - V[:, :n] - h / 6 * (F[:-1] + 4 * Fc + F[1:])

    def curvature(V, ks):  # the Jacobian blocks, and what the Hessian needs besides lam
        (_, J, T), (_, Jc, Tc), _ = _knots_then_midpoints(jax.vmap(value_jacobian_tensor), V, ks * h, h, n)
        Dc = midpoint_jacobians(J)
        return jacobian_from(J, Jc, Dc), (T, Jc, Tc, Dc)

    def jacobian_from(J, Jc, Dc):
        return plain - h / 6 * (jnp.concatenate([J[:-1], J[1:]], axis=2) + 4 * Jc @ Dc)

    def jacobian(V, ks):
        (_, J), (_, Jc), _ = _knots_then_midpoints(jax.vmap(value_and_jacobian), V, ks * h, h, n)
        return jacobian_from(J, Jc, midpoint_jacobians(J))

    def hessian_from(curvature, lam):
        T, Jc, Tc, Dc = curvature
        g = jnp.einsum("kij,ki->kj", Jc[:, :, :n], lam)
        H0 = jnp.einsum("ki,kijl->kjl", lam + h / 2 * g, T[:-1])
        H1 = jnp.einsum("ki,kijl->kjl", lam - h / 2 * g, T[1:])
        zero = jnp.zeros_like(H0)
        knots = jnp.concatenate([jnp.concatenate([H0, zero], 2), jnp.concatenate([zero, H1], 2)], 1)
        middle = jnp.einsum("kai,kab,kbj->kij", Dc, jnp.einsum("ki,kijl->kjl", lam, Tc), Dc)
        return -h / 6 * (knots + 4 * middle)

    return {"fn": defects, "jacobian": jacobian, "curvature": curvature, "hessian_from": hessian_from,
            "batched": True}


class DirectCollocation(_TrajectoryProgram):
    r"""Direct collocation with Hermite-Simpson's rule (Drake's `DirectCollocation`): cubic
    state segments matching $f$ at the knots, first-order-hold inputs, the dynamics enforced
    at each segment's midpoint. Running costs are integrated segment by segment by
    `quadrature`:

    - "simpson" (default): $\tfrac h6 (\ell_k + 4 \ell_c + \ell_{k+1})$ on the Hermite cubic
      and the first-order-hold input (at the collocation's midpoint $x_c$, $u_c$), exact for a
      quadratic-in-u cost of a linear input;
    - "trapezoid": $\tfrac h2 (\ell_k + \ell_{k+1})$ on the knots, as Drake's
      `AddRunningCost` (then the program and its objective are Drake's with equal time steps).

    ```python
    prog = DirectCollocation(DoubleIntegrator(), 21, duration=2.0)
    prog.set_initial_state([1, 0]).set_final_state([0, 0]).add_running_cost(lambda t, x, u: u @ u)
    result = prog.solve()          # result.states, result.inputs are Trajectory objects
    ```
    """

    method = "Hermite-Simpson"

    def __init__(self, system, num_time_samples, *, duration=None, quadrature: str = "simpson",
                 parameters=None, parameter_bounds=None):
        if isinstance(system, System) and system.has_discrete_state:
            raise ValueError(f"DirectCollocation needs a continuous system; {system.name} is discrete "
                             "(use DirectTranscription)")
        if quadrature not in ("simpson", "trapezoid"):
            raise ValueError(f"unknown quadrature {quadrature!r}; use 'simpson' or 'trapezoid' (Drake's)")
        self.quadrature = quadrature
        super().__init__(system, num_time_samples, duration=duration, parameters=parameters,
                         parameter_bounds=parameter_bounds)

    def _defect(self, t, x0, u0, x1, u1, h, system):
        (F,), (fc,), _ = _knots_then_midpoints(_dynamics_at(system, self.num_states),
                                               jnp.concatenate([x0, u0, x1, u1])[None], jnp.atleast_1d(t), h,
                                               self.num_states)
        return x1 - x0 - h / 6 * (F[0] + 4 * fc[0] + F[1])

    def _defect_derivatives(self):
        if self.num_globals:  # a free duration or free parameters: autodiff of the defect
            return {}
        return _hermite_simpson_batched(self.system, self.num_states, self.num_inputs,
                                        self._duration_bounds[0] / (self.num_time_samples - 1))

    def _running_cost_term(self, fn):
        if self.quadrature == "trapezoid":
            return self._segment_term("running cost", lambda t, x0, u0, x1, u1, h, system:
                                      h / 2 * (fn(t, x0, u0) + fn(t + h, x1, u1)))
        reads_state = _reads_state(fn, self.num_states, self.num_inputs)

        def simpson(t, x0, u0, x1, u1, h, system):
            n = self.num_states
            if reads_state:
                _, _, Wc = _knots_then_midpoints(_dynamics_at(system, n), jnp.concatenate([x0, u0, x1, u1])[None],
                                                 jnp.atleast_1d(t), h, n)
                xc, uc = Wc[0, :n], Wc[0, n:]
            else:  # the midpoint state costs dynamics evaluations, and fn ignores it
                xc, uc = (x0 + x1) / 2, (u0 + u1) / 2
            return h / 6 * (fn(t, x0, u0) + 4 * fn(t + h / 2, xc, uc) + fn(t + h, x1, u1))

        return self._segment_term("running cost", simpson)

    @functools.cached_property
    def _cubic_pieces(self):
        """Every segment's Hermite cubic (pieces, 5, n) in the normalized time, from the knots
        and their derivatives: one program, compiled once per trajectory program."""
        def pieces(g, times, X, U):
            F = jax.vmap(self._unpack_globals(g)[2].dynamics)(times, X, U)
            h = times[1] - times[0]
            x0, x1, f0, f1 = X[:-1], X[1:], h * F[:-1], h * F[1:]
            zero = jnp.zeros_like(x0)
            return jnp.stack([x0, f0, 3 * (x1 - x0) - 2 * f0 - f1, 2 * (x0 - x1) + f0 + f1, zero], axis=1)

        return jax.jit(pieces)

    def _reconstruct(self, times, X, U, g):
        states = Trajectory.from_pieces(times[:-1], times[1:], self._cubic_pieces(g, times, X, U))
        return states, Trajectory.from_samples(times, U, "linear")


class DirectTranscription(_TrajectoryProgram):
    r"""Direct transcription (Drake's `DirectTranscription`): $x_{k+1} = x_k + \dots$ one step of
    an explicit `rule` ("euler", "midpoint", "rk4") with the input held (zero-order hold) for a
    continuous system, or $x_{k+1} = f_d(t_k, x_k, u_k)$ for a discrete one (then the time step
    is its period). Running cost $\sum_{k<N-1} h\,\ell(t_k, x_k, u_k)$."""

    method = "transcription"

    def __init__(self, system, num_time_samples, *, duration=None, rule: str = "euler",
                 parameters=None, parameter_bounds=None):
        if rule not in FIXED_STEP_RULES:
            raise ValueError(f"unknown rule {rule!r}; use one of {FIXED_STEP_RULES}")
        self.rule = rule
        super().__init__(system, num_time_samples, duration=duration, parameters=parameters,
                         parameter_bounds=parameter_bounds)

    def _defect(self, t, x0, u0, x1, u1, h, system):
        return x1 - discrete_step(system, t, x0, u0, h, self.rule)

    def _running_cost_term(self, fn):
        return self._knot_term("running cost", lambda t, x, u, h, s: h * fn(t, x, u),
                               range(self.num_time_samples - 1))

    def _reconstruct(self, times, X, U, g):
        hold = "zoh" if self.system.has_discrete_state else "linear"
        return Trajectory.from_samples(times, X, hold), Trajectory.from_samples(times, U, "zoh")


class MultipleShooting(_TrajectoryProgram):
    r"""Multiple shooting through `simulate`: $x_{k+1} = \phi(t_{k+1}; t_k, x_k, u)$ with the
    input a first-order hold between $u_k$ and $u_{k+1}$, integrated by the adaptive simulator
    at `rtol`/`atol` and differentiated in forward mode through it. The running cost is
    integrated along the same simulation (an extra quadrature state). Each segment is a short
    simulation, so unstable systems stay tractable (Bock & Plitt 1984); with
    `num_time_samples=2` it is single shooting of one FOH segment. The Lagrangian Hessian is
    approximated by L-BFGS (second derivatives through a simulation are not worth their cost)."""

    method = "multiple shooting"
    _hessian_approximation = "limited-memory"

    def __init__(self, system, num_time_samples, *, duration=None, rtol=1e-8, atol=1e-10,
                 max_steps=256, parameters=None, parameter_bounds=None):
        if isinstance(system, System) and system.has_discrete_state:
            raise ValueError(f"MultipleShooting needs a continuous system; {system.name} is discrete "
                             "(use DirectTranscription)")
        self.rtol, self.atol, self.max_steps = rtol, atol, max_steps
        super().__init__(system, num_time_samples, duration=duration, parameters=parameters,
                         parameter_bounds=parameter_bounds)

    def _simulate_segment(self, t, x0, u0, u1, h, system, cost=None, dense=False):
        """The segment's simulation from (t, x0) over h with the input going linearly from u0
        to u1; with `cost`, the system carries the running cost as one more state."""
        foh = lambda s: u0 + (s - t) / h * (u1 - u0)  # noqa: E731
        inputs = foh
        if cost is not None:
            n, plant = self.num_states, system
            system = System.from_functions(
                lambda s, z, _: jnp.append(plant.dynamics(s, z[:n], foh(s)), cost(s, z[:n], foh(s))),
                num_states=n + 1)
            x0, inputs = jnp.append(x0, 0.0), None
        return simulate(system, (t, t + h), x0, inputs=inputs, rtol=self.rtol, atol=self.atol, dense=dense,
                        autodiff="forward", max_steps=self.max_steps, throw=False)

    def _defect(self, t, x0, u0, x1, u1, h, system):
        return x1 - self._simulate_segment(t, x0, u0, u1, h, system).final_state

    def _running_cost_term(self, fn):
        n = self.num_states
        return self._segment_term(
            "running cost", lambda t, x0, u0, x1, u1, h, system:
            self._simulate_segment(t, x0, u0, u1, h, system, cost=fn).final_state[n])

    @functools.cached_property
    def _segment_samples(self):
        """Compiled once: each segment's own simulation sampled at 8 points, so an unstable
        plant is not re-integrated across the whole horizon."""
        def sample(g, t, h, x, u0, u1, s):
            return self._simulate_segment(t, x, u0, u1, h, self._unpack_globals(g)[2], dense=True).state(s)

        return jax.jit(jax.vmap(sample, (None, 0, None, 0, 0, 0, 0)))

    def _reconstruct(self, times, X, U, g):
        h = times[1] - times[0]
        samples = times[:-1, None] + np.linspace(0.0, 1.0, 9)[None, :-1] * h
        values = self._segment_samples(g, times[:-1], h, X[:-1], U[:-1], U[1:], samples)
        states = Trajectory.from_samples(np.append(samples.ravel(), times[-1]),
                                         jnp.concatenate([values.reshape(-1, self.num_states), X[-1:]]), "linear")
        return states, Trajectory.from_samples(times, U, "linear")
