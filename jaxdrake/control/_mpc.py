r"""Model-predictive control as discrete systems: linear MPC (a QP per step), nonlinear MPC
(iLQR per step) and sampling MPC (MPPI).

Each controller is a `System` with the sample time Δt of its period: its input is the
plant's state (or an estimate of it), its output the first input of the plan computed at the
last sample. At $t_k = k\Delta t$ it reads $x(t_k)$, solves, and holds $u_0$ on
$(t_k, t_{k+1}]$ (a zero-order hold): a continuous plant in `feedback` sees each command at
once; a discrete plant of the same period updates at $t_k$ from the command of $t_{k-1}$ (the
discrete semantics: all updates at an instant read the outputs before it), which models one
period of computation delay. The plan is kept in the controller's discrete state and, shifted
by one step, starts the next solve (warm start). The discrete state is
$[u_0;\ \text{status};\ \text{plan}]$ (linear MPC keeps the QP's multipliers after the
plan); `status` and `plan` read it back.
"""

from __future__ import annotations

import abc
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..simulation import discrete_step
from ..systems import System, require_plain_system
from ._lqr import check_cost_weights, check_weight_shapes, linearize, operating_point
from ._qp import QPSolution, QPStatus, QPWorkspace, qp_workspace, solve_qp
from ._riccati import solve_discrete_are


class RecedingHorizonController(System):
    """The shared shape of the MPC controllers (abstract): discrete state
    $[u_0; \\text{status}; \\text{plan}]$, output $u_0$, the update run only when due."""

    @abc.abstractmethod
    def update(self, t, x, u):
        ...

    def discrete_update(self, t, x, u, due):
        # the simulator asks at every step; the solve runs only at the samples (a real branch
        # outside vmap, where the cost of the solve matters most)
        return jax.lax.cond(jnp.any(due), lambda: self.update(t, x, u), lambda: x)

    def output(self, t, x, u):
        return x[: self.num_outputs]

    def status(self, x):
        """The code of the last solve, read from the discrete state (batched states too):
        a `QPStatus` for `linear_mpc`, 0 (converged) / 1 (not converged) for
        `nonlinear_mpc`, 0 (finite costs) / 3 (non-finite) for `mppi`."""
        return jnp.asarray(x)[..., self.num_outputs].astype(jnp.int32)

    def plan(self, x):
        """The planned inputs (N, m) kept in the discrete state (absolute values)."""
        return jnp.asarray(x)[..., self.num_outputs + 1:].reshape(*jnp.shape(x)[:-1], -1, self.num_outputs)


# ----- checks shared by the three constructors ----------------------------------------------

def _period(system: System, period, caller: str) -> float:
    if system.has_discrete_state:
        if period is not None and not math.isclose(float(period), system.sample_time, rel_tol=1e-9):
            raise ValueError(f"{caller}: {system.name} is discrete with period {system.sample_time}; "
                             f"period={period} disagrees (leave it out)")
        return system.sample_time
    if period is None:
        raise ValueError(f"{caller}: {system.name} is continuous: give the controller's period= "
                         "(its sample time; the model is discretised with the input held over it)")
    period = float(period)
    if not (period > 0 and math.isfinite(period)):
        raise ValueError(f"{caller}: period must be positive and finite, got {period}")
    return period


def _horizon_steps(horizon, period: float, caller: str) -> int:
    """N = horizon / period, which must be a whole number of periods."""
    steps = float(horizon) / period
    N = round(steps)
    if N < 1 or abs(steps - N) > 1e-9 * max(1.0, steps):
        raise ValueError(f"{caller}: the horizon {horizon} is not a whole number of periods {period} "
                         f"({steps:.6g} periods); use horizon = N * period, e.g. {max(N, 1) * period:g}")
    return N


def _bound(value, default, size: int, label: str, caller: str):
    """`value` (default `default`) as a vector of `size`, from a scalar or `size` entries."""
    value = jnp.asarray(default if value is None else value, float)
    if value.size not in (1, size):
        raise ValueError(f"{caller}: {label} must be a scalar or have {size} entries")
    value = jnp.broadcast_to(value.reshape(()) if value.size == 1 else value.reshape(size), (size,))
    if not isinstance(value, jax.core.Tracer) and np.any(np.isnan(np.asarray(value))):
        raise ValueError(f"{caller}: {label} has NaN entries (use ±inf for no bound)")
    return value


def _bounds(lower, upper, size, default, label, caller):
    lo = _bound(lower, default[0], size, f"{label}_lower", caller)
    hi = _bound(upper, default[1], size, f"{label}_upper", caller)
    if not any(isinstance(v, jax.core.Tracer) for v in (lo, hi)) and np.any(np.asarray(lo) > np.asarray(hi)):
        raise ValueError(f"{caller}: {label}_lower must not exceed {label}_upper, got {lo} and {hi}")
    return lo, hi


def _input_limits(system: System):
    if system.input_limits is None:
        return (-jnp.inf, jnp.inf)
    return system.input_limits


def _controller_frames(system: System):
    """A controller reads the plant's state and writes the plant's input."""
    return dict(input_frame=system.state_frame, output_frame=system.input_frame)


# ----- linear MPC ---------------------------------------------------------------------------

def zero_order_hold(A, B, period):
    r"""The exact discretisation of $\dot x = Ax + Bu$ with u held over `period` T:
    $A_d = e^{AT}$, $B_d = \int_0^T e^{As} ds\, B$, both read from
    $\exp\left(\begin{bmatrix} A & B \\ 0 & 0 \end{bmatrix} T\right)$."""
    n, m = B.shape
    M = jnp.zeros((n + m, n + m), A.dtype).at[:n, :n].set(A).at[:n, n:].set(B)
    E = jax.scipy.linalg.expm(M * period)
    return E[:n, :n], E[:n, n:]


def _condensed(A, B, Q, R, Qf, N: int):
    r"""The condensed MPC QP: with $X = [x_1; \dots; x_N] = \Phi x_0 + \Gamma U$,
    $J = \sum_{k<N} x_k^T Q x_k + u_k^T R u_k + x_N^T Q_f x_N = \tfrac12 U^T P U + x_0^T F^T U + \text{const}$:
    (P, F, Φ, Γ)."""
    n, m = B.shape
    powers = jax.lax.scan(lambda Ak, _: (A @ Ak, Ak), jnp.eye(n, dtype=A.dtype), None, length=N + 1)[1]
    Phi = powers[1:].reshape(N * n, n)
    k, j = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")  # block (k, j): A^(k-j) B for j <= k
    blocks = jnp.where(jnp.asarray(j <= k)[:, :, None, None], powers[np.maximum(k - j, 0)] @ B, 0.0)
    Gamma = blocks.transpose(0, 2, 1, 3).reshape(N * n, N * m)
    weights = jnp.concatenate([jnp.broadcast_to(Q, (N - 1, n, n)), Qf[None]])
    QGamma = jnp.einsum("kab,kbj->kaj", weights, Gamma.reshape(N, n, N * m)).reshape(N * n, N * m)
    P = 2 * (Gamma.T @ QGamma + jnp.kron(jnp.eye(N, dtype=A.dtype), R))
    F = 2 * QGamma.T @ Phi
    return (P + P.T) / 2, F, Phi, Gamma


@functools.partial(jax.jit, static_argnames=("period", "N", "rows_u", "rows_x", "qp_options"))
@jax.default_matmul_precision("highest")
def _linear_mpc_data(A, B, Q, R, Qf, x0, u0, bounds, *, period, N, rows_u, rows_x, qp_options):
    """Everything `LinearMPC` keeps, in one compiled program: the model discretised (when
    `period` is given), the terminal cost (the DARE's when Qf is None), the condensed QP on the
    given constraint rows and its workspace."""
    if period is not None:
        A, B = zero_order_hold(A, B, period)
    if Qf is None:
        Qf = solve_discrete_are(A, B, Q, R)
    n, m = B.shape
    u_lo, u_hi, x_lo, x_hi = bounds
    P, F, Phi, Gamma = _condensed(A, B, Q, R, Qf, N)
    rows_u, rows_x = np.asarray(rows_u, int), np.asarray(rows_x, int)
    A_qp = jnp.concatenate([jnp.eye(N * m, dtype=A.dtype)[rows_u], Gamma[rows_x]])
    lower = jnp.concatenate([jnp.tile(u_lo - u0, N)[rows_u], jnp.tile(x_lo - x0, N)[rows_x]])
    upper = jnp.concatenate([jnp.tile(u_hi - u0, N)[rows_u], jnp.tile(x_hi - x0, N)[rows_x]])
    bound_shift = jnp.concatenate([jnp.zeros((len(rows_u), n), A.dtype), Phi[rows_x]])
    return qp_workspace(P, A_qp, **dict(qp_options)), F, bound_shift, lower, upper, Qf


class LinearMPC(RecedingHorizonController):
    r"""Linear MPC (see `linear_mpc`): each sample solves the QP of the plant's state, warm
    started from the previous plan shifted by one step."""

    workspace: QPWorkspace
    linear_term: jax.Array        # F: q = F (x - x0)
    bound_shift: jax.Array        # G: the constraints' bounds move by -G (x - x0)
    lower: jax.Array
    upper: jax.Array
    input_bounds: tuple[jax.Array, jax.Array]
    x0: jax.Array
    u0: jax.Array
    horizon_steps: int = eqx.field(static=True)
    rows_per_step: tuple[int, int] = eqx.field(static=True)  # (input rows, state rows) per step

    def __init__(self, workspace, linear_term, bound_shift, lower, upper, input_bounds, x0, u0, horizon_steps,
                 rows_per_step, sample_time, frames):
        self.workspace, self.linear_term, self.bound_shift = workspace, linear_term, bound_shift
        self.lower, self.upper, self.input_bounds, self.x0, self.u0 = lower, upper, input_bounds, x0, u0
        self.horizon_steps, self.rows_per_step = int(horizon_steps), tuple(rows_per_step)
        m = u0.shape[0]
        super().__init__(num_discrete_states=m + 1 + horizon_steps * m + lower.shape[0],
                         num_inputs=x0.shape[0], num_outputs=m, sample_time=sample_time,
                         direct_feedthrough=False, time_invariant=True, **frames)

    def plan(self, x):
        """The planned inputs (N, m) kept in the discrete state (absolute values)."""
        m, N = self.num_outputs, self.horizon_steps
        x = jnp.asarray(x)
        return x[..., m + 1: m + 1 + N * m].reshape(*x.shape[:-1], N, m) + self.u0

    def initial_state(self):
        return jnp.zeros(self.num_states).at[: self.num_outputs].set(self.u0)

    def qp(self, state):
        """(P, q, A, lower, upper) of the QP solved at the plant state `state`, over the input
        deviations $U = [u_0 - u^*; \\dots; u_{N-1} - u^*]$ (what the tests give OSQP)."""
        dx = jnp.asarray(state) - self.x0
        with jax.default_matmul_precision("highest"):  # as the QP solver
            shift, q = self.bound_shift @ dx, self.linear_term @ dx
        return (self.workspace.P, q, self.workspace.A, self.lower - shift, self.upper - shift)

    def solve(self, state, warm_x=None, warm_y=None) -> QPSolution:
        """The `QPSolution` at the plant state `state` (deviation variables, see `qp`)."""
        _, q, _, lower, upper = self.qp(state)
        return solve_qp(self.workspace, q, lower, upper, warm_x, warm_y)

    def update(self, t, x, u):
        m, N = self.num_outputs, self.horizon_steps
        U = x[m + 1: m + 1 + N * m].reshape(N, m)
        y = x[m + 1 + N * m:]
        rows_u, rows_x = self.rows_per_step
        y_u, y_x = y[: N * rows_u].reshape(N, rows_u), y[N * rows_u:].reshape(N, rows_x)
        shift = lambda v, last: jnp.concatenate([v[1:], last]).reshape(-1)  # noqa: E731
        warm_x = shift(U, U[-1:])
        warm_y = jnp.concatenate([shift(y_u, jnp.zeros_like(y_u[:1])), shift(y_x, jnp.zeros_like(y_x[:1]))])
        solution = self.solve(u, warm_x, warm_y)
        failed = (solution.status == QPStatus.PRIMAL_INFEASIBLE) | (solution.status == QPStatus.NONFINITE)
        plan = jnp.where(failed, 0.0, solution.x)  # a diverged dual is no warm start
        first = jnp.clip(self.u0 + solution.x[:m], *self.input_bounds)  # a last iterate may be outside
        first = jnp.where(jnp.isfinite(first), first, self.u0)
        return jnp.concatenate([first, solution.status[None].astype(x.dtype), plan,
                                jnp.where(failed, 0.0, solution.y)])


def linear_mpc(system: System, Q, R, horizon, *, period=None, x0=None, u0=None, input_lower=None,
               input_upper=None, state_lower=None, state_upper=None, terminal_cost=None,
               check_equilibrium: bool = True, **qp_options) -> LinearMPC:
    r"""Linear model-predictive control of `system` about (x0, u0) (default: the origin, u = 0),
    a discrete system with the period Δt (Drake's `LinearModelPredictiveController`, with
    constraints and a terminal cost). Each sample solves

    $$\min_{u_0..u_{N-1}} \sum_{k=0}^{N-1} \tilde x_k^T Q \tilde x_k + \tilde u_k^T R \tilde u_k
      + \tilde x_N^T Q_f \tilde x_N \quad\text{s.t.}\quad \tilde x_{k+1} = A_d \tilde x_k + B_d \tilde u_k,\ 
      \tilde x_0 = x(t_k) - x_0,$$

    $u_{lo} \le u_k \le u_{hi}$ ($k < N$), $x_{lo} \le x_k \le x_{hi}$ ($1 \le k \le N$), with
    $\tilde x = x - x_0$, $\tilde u = u - u_0$ and N = horizon / Δt steps, condensed to a QP
    over the inputs (`_qp.py`: ADMM on a factorization made once, here, then polished).

    **Arguments:**

    - `system`: a `LinearSystem`, or any plain system linearized at (x0, u0) as `lqr` does;
      a continuous one is discretised exactly with the input held over `period` (ZOH, `expm`).
    - `Q` (n, n) ⪰ 0, `R` (m, m) ≻ 0: Drake's cost convention ($x^T Q x + u^T R u$ per step,
      no ½).
    - `horizon`: the prediction horizon in seconds, a whole number N ≥ 1 of periods.
    - `period`: the sample time (required for a continuous system; a discrete one's own).
    - `input_lower` / `input_upper` (absolute u; default the system's input limits),
      `state_lower` / `state_upper` (absolute x; ±inf for a free coordinate): box constraints.
    - `terminal_cost`: $Q_f$; default the DARE solution of $(A_d, B_d, Q, R)$ (the infinite
      horizon's cost-to-go: with no active constraint, the controller is the LQR).
    - `qp_options`: `rho`, `sigma`, `tolerance`, `max_iterations` of `qp_workspace`.

    **Returns:** a `LinearMPC` system (input: the plant's state; output: its input; `solve`,
    `qp`, `plan`, `status` to look inside). Differentiable with respect to Q, R, Qf, the
    model and the bounds. Drake's controller, for comparison, has no constraints, no terminal
    cost, and a horizon of N + 1 samples for our N steps.
    """
    caller = "linear_mpc"
    require_plain_system(system, caller, "linearize a mode (or the nominal deterministic system) instead")
    n, m = system.num_states, system.num_inputs
    if m == 0 or n == 0:
        raise ValueError(f"{caller}: {system.name} needs states and inputs to be controlled")
    dt = _period(system, period, caller)
    N = _horizon_steps(horizon, dt, caller)
    x0, u0 = operating_point(caller, system, jnp.zeros(n) if x0 is None else jnp.asarray(x0, float),
                             jnp.zeros(m) if u0 is None else jnp.asarray(u0, float))
    Q, R = jnp.atleast_2d(jnp.asarray(Q, float)), jnp.atleast_2d(jnp.asarray(R, float))
    check_weight_shapes(caller, system, Q, R)
    if terminal_cost is not None:
        terminal_cost = jnp.atleast_2d(jnp.asarray(terminal_cost, float))
        if terminal_cost.shape != (n, n):
            raise ValueError(f"{caller}: terminal_cost must be ({n}, {n}), got {terminal_cost.shape}")
    check_cost_weights(caller, Q, R, Qf=terminal_cost)
    lin = linearize(system, x0, u0, check_equilibrium=check_equilibrium)
    u_lo, u_hi = _bounds(input_lower, input_upper, m, _input_limits(system), "input", caller)
    x_lo, x_hi = _bounds(state_lower, state_upper, n, (-jnp.inf, jnp.inf), "state", caller)
    rows_u, rows_x = _constraint_rows(u_lo, u_hi, N), _constraint_rows(x_lo, x_hi, N)
    workspace, F, bound_shift, lower, upper, terminal_cost = _linear_mpc_data(
        lin.A, lin.B, Q, R, terminal_cost, x0, u0, (u_lo, u_hi, x_lo, x_hi),
        period=None if lin.is_discrete else dt, N=N, rows_u=rows_u, rows_x=rows_x,
        qp_options=tuple(sorted(qp_options.items())))
    if not isinstance(terminal_cost, jax.core.Tracer) and not np.all(np.isfinite(terminal_cost)):
        raise ValueError(f"{caller}: the DARE of {system.name} (period {dt}) has no stabilising solution, so "
                         "there is no default terminal cost: give terminal_cost= (e.g. Q), or check "
                         "that (A, B) is stabilisable")
    return LinearMPC(workspace, F, bound_shift, lower, upper, (u_lo, u_hi), x0, u0, N,
                     (len(rows_u) // N, len(rows_x) // N), dt, _controller_frames(system))


def _constraint_rows(lower, upper, N: int) -> tuple[int, ...]:
    """The rows of the stacked bounds (N blocks) that constrain anything: the coordinates with
    a finite bound (every coordinate, when one is; all of them for traced bounds)."""
    size = lower.shape[0]
    traced = isinstance(lower, jax.core.Tracer) or isinstance(upper, jax.core.Tracer)
    bounded = traced or np.isfinite(np.asarray(lower)).any() or np.isfinite(np.asarray(upper)).any()
    coords = np.arange(size) if traced else np.flatnonzero(np.isfinite(np.asarray(lower)) | np.isfinite(np.asarray(upper)))
    return tuple(int(k * size + i) for k in range(N) for i in coords) if bounded else ()


# ----- nonlinear MPC and MPPI: the plant's own (RK4-stepped) model -----------------------------

def _check_costs(system: System, running_cost, final_cost, caller: str):
    """Named errors for cost functions that do not return a scalar (traced once, on shapes)."""
    t, x, u = (jax.ShapeDtypeStruct(shape, jnp.zeros(()).dtype) for shape in ((), (system.num_states,),
                                                                              (system.num_inputs,)))
    for label, fn, args in (("running_cost(t, x, u)", running_cost, (t, x, u)), ("final_cost(x)", final_cost, (x,))):
        if fn is None:
            continue
        if not callable(fn):
            raise TypeError(f"{caller}: {label.split('(')[0]} must be a function {label} -> scalar")
        shape = jax.eval_shape(fn, *args).shape
        if shape != ():
            raise ValueError(f"{caller}: {label} must return a scalar, got shape {shape}")


def _sampled_controller_setup(system, running_cost, final_cost, horizon, period, input_lower, input_upper,
                              caller):
    """(period, N, input bounds) after the checks shared by `nonlinear_mpc` and `mppi`."""
    require_plain_system(system, caller, "control a deterministic system (one mode of a hybrid one)")
    if system.num_inputs == 0:
        raise ValueError(f"{caller}: {system.name} has no inputs to control")
    dt = _period(system, period, caller)
    N = _horizon_steps(horizon, dt, caller)
    _check_costs(system, running_cost, final_cost, caller)
    bounds = _bounds(input_lower, input_upper, system.num_inputs, _input_limits(system), "input", caller)
    return dt, N, bounds


def _finite_plan(plan, bounds):
    """(whether `plan` is finite, the plan or, if not, zeros clipped into the bounds)."""
    finite = jnp.all(jnp.isfinite(plan))
    return finite, jnp.where(finite, plan, jnp.clip(jnp.zeros_like(plan), *bounds))


class _PlanController(RecedingHorizonController):
    """A controller whose discrete state is exactly $[u_0; \\text{status}; \\text{plan}]$
    (iLQR, MPPI); subclasses hold `plant`, `input_bounds`, `horizon_steps` and `period`."""

    def _declare_plan_state(self):
        m = self.plant.num_inputs
        super().__init__(num_discrete_states=m + 1 + self.horizon_steps * m, num_inputs=self.plant.num_states,
                         num_outputs=m, sample_time=self.period, direct_feedthrough=False,
                         **_controller_frames(self.plant))

    def initial_state(self):
        """The plan u = 0 clipped into the bounds."""
        m, N = self.num_outputs, self.horizon_steps
        plan = jnp.broadcast_to(jnp.clip(jnp.zeros(m), *self.input_bounds), (N, m))
        return jnp.concatenate([plan[0], jnp.zeros(1), plan.reshape(-1)])


class NonlinearMPC(_PlanController):
    """Nonlinear MPC by iLQR (see `nonlinear_mpc`)."""

    plant: System
    input_bounds: tuple[jax.Array, jax.Array]
    running_cost: object = eqx.field(static=True)
    final_cost: object = eqx.field(static=True)
    horizon_steps: int = eqx.field(static=True)
    period: float = eqx.field(static=True)
    max_iterations: int = eqx.field(static=True)
    tolerance: float = eqx.field(static=True)

    def __init__(self, plant, running_cost, final_cost, input_bounds, horizon_steps, period, max_iterations,
                 tolerance):
        self.plant, self.running_cost, self.final_cost = plant, running_cost, final_cost
        self.input_bounds, self.horizon_steps, self.period = input_bounds, int(horizon_steps), float(period)
        self.max_iterations, self.tolerance = int(max_iterations), float(tolerance)
        self._declare_plan_state()

    def update(self, t, x, u):
        from ..trajopt import ilqr  # imported on first use, as `import jaxdrake` keeps trajopt (IPOPT) lazy

        U = self.plan(x)
        guess = jnp.concatenate([U[1:], U[-1:]])  # the last plan, one step on
        result = ilqr(self.plant, u, guess, self.period, self.running_cost, self.final_cost,
                      input_bounds=self.input_bounds, max_iterations=self.max_iterations, tol=self.tolerance)
        finite, plan = _finite_plan(result.knot_inputs, self.input_bounds)
        status = jnp.where(finite, jnp.where(result.success, 0, 1), QPStatus.NONFINITE)
        return jnp.concatenate([plan[0], status[None].astype(x.dtype), plan.reshape(-1)])


def nonlinear_mpc(system: System, running_cost, horizon, *, final_cost=None, period=None, input_lower=None,
                  input_upper=None, max_iterations: int = 10, tolerance: float = 1e-6) -> NonlinearMPC:
    r"""Nonlinear model-predictive control by iLQR/DDP (`jd.trajopt.ilqr`): each sample minimizes

    $$\sum_{k=0}^{N-1} \Delta t\, \ell(t_k, x_k, u_k) + \ell_f(x_N), \qquad x_{k+1} = \Phi_{\Delta t}(x_k, u_k),
      \quad x_0 = x(t), \quad u_{lo} \le u_k \le u_{hi},$$

    over N = horizon / Δt steps of the plant itself (one RK4 step per period, or a discrete
    plant's update; $t_k = k \Delta t$ on the horizon's own clock), starting from the previous
    plan shifted by one step, for at most `max_iterations` iLQR iterations (a real-time
    budget: the plan improves from sample to sample).

    **Arguments:** `system` (a plain, deterministic system), `running_cost(t, x, u)`,
    `final_cost(x)` (scalars; the same functions each call: they key the compiled program),
    `horizon` (seconds, a whole number of periods), `period` (required for a continuous
    system), input bounds (default the system's limits), `tolerance` (relative cost change).

    **Returns:** a `NonlinearMPC` system; its `status` is 0 when iLQR converged, 1 when the
    iteration budget ran out first (the improved plan is used all the same).
    """
    dt, N, bounds = _sampled_controller_setup(system, running_cost, final_cost, horizon, period, input_lower,
                                              input_upper, "nonlinear_mpc")
    if not (isinstance(max_iterations, (int, np.integer)) and max_iterations >= 1):
        raise ValueError(f"nonlinear_mpc: max_iterations must be a positive int, got {max_iterations!r}")
    return NonlinearMPC(system, running_cost, final_cost, bounds, N, dt, max_iterations, tolerance)


def rollout_cost(system: System, running_cost, final_cost, x0, inputs, period):
    r"""$\sum_k \Delta t\, \ell(t_k, x_k, u_k) + \ell_f(x_N)$ along the plant's own steps from x0
    under `inputs` (N, m) (one RK4 step per period, or a discrete plant's update), as iLQR
    counts it."""
    h = jnp.asarray(period, x0.dtype)

    def step(carry, k_u):
        x, cost = carry
        k, u = k_u
        t = k * h
        return (discrete_step(system, t, x, u, h, "rk4"), cost + h * running_cost(t, x, u)), None

    steps = jnp.arange(inputs.shape[0], dtype=x0.dtype)
    (xN, cost), _ = jax.lax.scan(step, (x0, jnp.zeros((), x0.dtype)), (steps, inputs))
    return cost + (0.0 if final_cost is None else final_cost(xN))


class MPPI(_PlanController):
    """Sampling MPC, MPPI (see `mppi`)."""

    plant: System
    input_bounds: tuple[jax.Array, jax.Array]
    noise_std: jax.Array
    temperature: jax.Array
    key_data: jax.Array
    running_cost: object = eqx.field(static=True)
    final_cost: object = eqx.field(static=True)
    horizon_steps: int = eqx.field(static=True)
    period: float = eqx.field(static=True)
    num_samples: int = eqx.field(static=True)

    def __init__(self, plant, running_cost, final_cost, input_bounds, noise_std, temperature, key_data,
                 horizon_steps, period, num_samples):
        self.plant, self.running_cost, self.final_cost = plant, running_cost, final_cost
        self.input_bounds, self.noise_std, self.temperature, self.key_data = input_bounds, noise_std, temperature, key_data
        self.horizon_steps, self.period, self.num_samples = int(horizon_steps), float(period), int(num_samples)
        self._declare_plan_state()

    def update(self, t, x, u):
        N, m, K = self.horizon_steps, self.num_outputs, self.num_samples
        U = self.plan(x)
        nominal = jnp.concatenate([U[1:], U[-1:]])
        # sample k's noise is a function of the key and the sample index alone
        key = jax.random.fold_in(jax.random.wrap_key_data(self.key_data), jnp.round(t / self.period).astype(jnp.int32))
        noise = self.noise_std * jax.random.normal(key, (K, N, m), x.dtype)
        candidates = jnp.clip(nominal + noise.at[0].set(0.0), *self.input_bounds)  # the nominal competes too
        costs = jax.vmap(lambda V: rollout_cost(self.plant, self.running_cost, self.final_cost, u, V,
                                                self.period))(candidates)
        costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
        best = jnp.min(costs)
        weights = jax.nn.softmax(-(costs - jnp.where(jnp.isfinite(best), best, 0.0)) / self.temperature)
        plan = jnp.where(jnp.isfinite(best), jnp.einsum("k,knm->nm", weights, candidates), jnp.nan)
        finite, plan = _finite_plan(plan, self.input_bounds)
        status = jnp.where(finite, 0, QPStatus.NONFINITE)
        return jnp.concatenate([plan[0], status[None].astype(x.dtype), plan.reshape(-1)])


def mppi(system: System, running_cost, horizon, *, key, final_cost=None, period=None, num_samples: int = 1024,
         noise_std=1.0, temperature=1.0, input_lower=None, input_upper=None) -> MPPI:
    r"""Sampling MPC: model-predictive path integral control (Williams, Aldrich & Theodorou,
    *Model predictive path integral control*, 2017). Each sample draws K input sequences
    $V^{(i)} = \mathrm{clip}(\bar U + \varepsilon^{(i)})$, $\varepsilon \sim N(0, \sigma^2)$
    around the previous plan $\bar U$ shifted by one step (candidate 0 is $\bar U$ itself),
    rolls them out on the plant (all at once, `vmap`), scores each by the cost $S_i$ that
    `rollout_cost` (and iLQR) uses, and plans the weighted mean

    $$U = \sum_i w_i V^{(i)}, \qquad w_i \propto \exp(-(S_i - \min_j S_j) / \lambda).$$

    The input cost is that of the running cost on the sampled inputs (no separate
    $\lambda u^T \Sigma^{-1} \varepsilon$ term). The noise at a sample is a function of `key`
    and the sample's index $t / \Delta t$ alone, so a simulation is reproducible and a batch
    over keys is a Monte-Carlo batch.

    **Arguments:** `system`, `running_cost(t, x, u)`, `final_cost(x)`, `horizon`, `period`
    as for `nonlinear_mpc`; `key` a JAX PRNG key; `num_samples` K; `noise_std` σ (scalar or
    per input); `temperature` λ > 0 (in cost units); input bounds (default the system's limits).

    **Returns:** an `MPPI` system; its `status` is 3 when every rollout's cost was non-finite
    (the plan then falls back to zero clipped into the bounds).
    """
    dt, N, bounds = _sampled_controller_setup(system, running_cost, final_cost, horizon, period, input_lower,
                                              input_upper, "mppi")
    m = system.num_inputs
    if not (isinstance(num_samples, (int, np.integer)) and num_samples >= 2):
        raise ValueError(f"mppi: num_samples must be an int >= 2, got {num_samples!r}")
    noise_std = _bound(noise_std, None, m, "noise_std", "mppi")
    temperature = jnp.asarray(temperature, float)
    for label, v in (("noise_std", noise_std), ("temperature", temperature)):
        if not isinstance(v, jax.core.Tracer) and not np.all(np.asarray(v) > 0):
            raise ValueError(f"mppi: {label} must be positive, got {v}")
    key = jnp.asarray(key)
    key_data = jax.random.key_data(key) if jnp.issubdtype(key.dtype, jax.dtypes.prng_key) else key
    if key_data.dtype != jnp.uint32:
        raise TypeError(f"mppi: key must be a JAX PRNG key (jax.random.key(0)), got {key.dtype}")
    return MPPI(system, running_cost, final_cost, bounds, noise_std, temperature, key_data, N, dt, num_samples)
