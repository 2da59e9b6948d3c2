r"""A batched, JAX-native trajectory optimizer: augmented-Lagrangian iLQR.

For the discretized dynamics $x_{k+1} = \Phi(t_k, x_k, u_k)$ (an RK4 step with the input held,
or a discrete system's update) it minimizes
$$J = \sum_{k=0}^{N-1} h\,\ell(t_k, x_k, u_k) + \ell_f(x_N)$$
subject to $u_{min} \le u_k \le u_{max}$ and optionally $x_N = x_{goal}$. The input bounds
are kept exactly by box-constrained iLQR (Tassa, Mansard & Todorov 2014): each backward step
solves the box QP $\min_{\delta u} \tfrac12 \delta u^T Q_{uu} \delta u + Q_u^T \delta u$,
$u_{min} - u \le \delta u \le u_{max} - u$, by projected Newton, and the feedback acts on the
free inputs only; the forward pass clamps. The goal enters an augmented Lagrangian (as ALTRO,
Howell, Jackson & Manchester 2019), whose unconstrained problems are solved by differential
dynamic programming: iLQR's backward pass (Li & Todorov 2004) plus the dynamics' curvature
$V_x' \cdot \nabla^2 \Phi$ (the full DDP expansion: the step's second-derivative tensors
evaluated for all steps at once, off the sequential path, and contracted with $V_x$ inside the
backward scan), with Levenberg-Marquardt regularization of the value Hessian and
a backtracking line search (Tassa, Erez & Todorov 2012); the multiplier and the penalty are
updated between inner solves. The curvature term matters once the goal's multiplier is large:
without it, the Gauss-Newton model crawls (pendulum swing-ups: 553 iterations for the slowest
of 64, against 46 with it). Every loop is a `lax.while_loop` and every derivative comes from JAX,
so `jax.vmap` over initial states, goals or parameters solves many problems at once (all
members run until the last has finished). It returns a status, never raises inside `jit`.

The stages, module-level functions over an `ILQRProblem` (what every stage reads), in the order
they run: one loop over `ILQRState` (`iteration`, while `running`), each step a `ddp_iteration`
(`backward_pass`: the gains, from `expand_steps`' local models, one `backward_step` per knot;
`line_search`: a `forward_pass` per step length; `update_regularization`;
`subproblem_converged`) and, where that ended the current subproblem, `update_multiplier`
(then `start_subproblem` for the next one, if `keep_going`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..simulation import discrete_step
from ..systems import System
from ..systems import require_plain_system
from ..trajectories import Trajectory
from ._status import ILQRStatus, messages

_ALPHAS = 0.5 ** np.arange(10)
_FRESH_REGULARIZATION = 1e-6  # rho at the start of each subproblem
_BOX_QP_ITERATIONS = 8  # projected Newton steps per box QP, at most (m + 1: exact in one when m = 1)


def box_qp(H, g, lower, upper, x0):
    r"""Projected Newton for $\min \tfrac12 x^T H x + g^T x$, lower <= x <= upper (H > 0):
    (x, free, the Cholesky factor of H on the free set, identity elsewhere). An index is
    clamped when it sits on a bound its gradient pushes against; each step solves on the free
    set and backtracks (Armijo) along the projected path."""
    m = g.shape[0]
    eye = jnp.eye(m, dtype=H.dtype)
    q = lambda x: 0.5 * x @ H @ x + g @ x  # noqa: E731

    def factor(free):
        both = free[:, None] & free[None, :]
        return jnp.linalg.cholesky(jnp.where(both, H, eye))

    def step(x, _):
        grad = g + H @ x
        free = ~(((x <= lower) & (grad > 0)) | ((x >= upper) & (grad < 0)))
        direction = jnp.where(free, -jax.scipy.linalg.cho_solve((factor(free), True), jnp.where(free, grad, 0.0)), 0.0)
        trials = jnp.clip(x + jnp.asarray(_ALPHAS, H.dtype)[:, None] * direction, lower, upper)
        values = jax.vmap(q)(trials)
        good = values <= q(x) + 1e-8 * (jnp.asarray(_ALPHAS, H.dtype) * (grad @ direction))
        return jnp.where(jnp.any(good), trials[jnp.argmax(good)], x), None

    x = jax.lax.scan(step, jnp.clip(x0, lower, upper), None, length=min(_BOX_QP_ITERATIONS, m + 1))[0]
    grad = g + H @ x
    free = ~(((x <= lower) & (grad > 0)) | ((x >= upper) & (grad < 0)))
    return x, free, factor(free)


class ILQRResult(eqx.Module):
    """The knot states (N+1, n) and inputs (N, m) of the solution, the cost J (without the
    constraint terms), the largest constraint violation, the number of inner (iLQR) iterations,
    and the `status` (an `ILQRStatus` code; an array for a batch): `success` (cost change below
    `tol`, constraints below `constraint_tol`, within the budget) and `message` from it."""

    knot_states: jax.Array
    knot_inputs: jax.Array
    time_step: jax.Array
    cost: jax.Array
    constraint_violation: jax.Array
    iterations: jax.Array
    status: jax.Array

    @property
    def success(self):
        """True where the solve converged; works on traced and batched results."""
        return self.status == ILQRStatus.SUCCESS

    @property
    def message(self):
        """What `status` means (an array of messages for a batch)."""
        return messages(ILQRStatus, self.status)

    @property
    def times(self):
        return jnp.arange(self.knot_states.shape[-2]) * self.time_step[..., None]

    @property
    def states(self) -> Trajectory:
        """The states as a first-order-hold `Trajectory` (one problem, not a batch)."""
        return Trajectory.from_samples(self.times, self.knot_states, "linear")

    @property
    def inputs(self) -> Trajectory:
        """The inputs as the zero-order-hold tape the optimizer assumed (one problem)."""
        return Trajectory.from_samples(self.times, jnp.concatenate([self.knot_inputs, self.knot_inputs[-1:]]), "zoh")


def _check(system, x0, inputs):
    require_plain_system(system, "ilqr", "optimize a deterministic system (one mode of a hybrid one)")
    if x0.shape != (system.num_states,):
        raise ValueError(f"ilqr: x0 must have shape ({system.num_states},), got {x0.shape}")
    if inputs.ndim != 2 or inputs.shape[1] != system.num_inputs:
        raise ValueError(f"ilqr: the input guess must have shape (N, {system.num_inputs}), got {inputs.shape}")


def ilqr(system: System, x0, inputs, time_step, running_cost, final_cost=None, *, final_state=None,
         input_bounds=None, max_iterations: int = 500, max_outer: int = 30, tol: float = 1e-8,
         constraint_tol: float = 1e-6, penalty: float = 1.0, penalty_growth: float = 10.0) -> ILQRResult:
    r"""Minimize $\sum_k h\,\ell(t_k, x_k, u_k) + \ell_f(x_N)$ from `x0` over N = len(inputs)
    steps of `time_step` h (ignored for a discrete system: its period), starting from the
    input guess `inputs` (N, m).

    - `running_cost(t, x, u)`, `final_cost(x)`: scalars (the final cost defaults to zero).
    - `final_state`: x_N = final_state, enforced by the augmented Lagrangian (NaN entries free).
    - `input_bounds`: (u_min, u_max); the system's input limits by default.
    - `max_iterations`: the total budget of iLQR iterations, shared by `max_outer`
      multiplier updates; `penalty` (the first) grows by `penalty_growth` per update, to 1e8; `tol`: relative cost change that ends an inner solve
      (at least 100 eps of the float width: 1.2e-5 in float32);
      `constraint_tol`: the violation accepted at the end.

    Returns an `ILQRResult` (pure arrays: `jax.vmap` gives batches). Compiled once per system
    structure, cost functions (by identity) and option values: a second call costs its run time."""
    x0 = jnp.asarray(x0)
    inputs = jnp.asarray(inputs, x0.dtype if jnp.issubdtype(x0.dtype, jnp.floating) else float)
    x0 = x0.astype(inputs.dtype)
    _check(system, x0, inputs)
    return _ilqr(system, x0, inputs, time_step, running_cost, final_cost, final_state, input_bounds,
                 max_iterations, max_outer, tol, constraint_tol, penalty, penalty_growth)


@eqx.filter_jit
def _ilqr(system, x0, inputs, time_step, running_cost, final_cost, final_state, input_bounds,
          max_iterations, max_outer, tol, constraint_tol, penalty, penalty_growth):
    """`ilqr`'s program, for checked arrays (see `ilqr`)."""
    m, n, dtype = inputs.shape[1], system.num_states, inputs.dtype
    h = jnp.asarray(system.sample_time if system.has_discrete_state else time_step, dtype)
    if input_bounds is None:
        input_bounds = system.input_limits if system.input_limits is not None else (-jnp.inf, jnp.inf)
    goal = goal_mask = None
    if final_state is not None:
        goal = jnp.broadcast_to(jnp.asarray(final_state, dtype), (n,))
        goal_mask = ~jnp.isnan(goal)
        goal = jnp.where(goal_mask, goal, 0.0)
    problem = ILQRProblem(
        system=system, running_cost=running_cost,
        final_cost=(lambda x: jnp.zeros((), dtype)) if final_cost is None else final_cost,
        x0=x0, times=jnp.arange(inputs.shape[0], dtype=dtype) * h, h=h,
        u_lo=jnp.broadcast_to(jnp.asarray(input_bounds[0], dtype), (m,)),
        u_hi=jnp.broadcast_to(jnp.asarray(input_bounds[1], dtype), (m,)), goal=goal, goal_mask=goal_mask,
        max_iterations=max_iterations, max_outer=max_outer,
        final_tol=max(tol, 100 * float(jnp.finfo(dtype).eps)),  # never below what the float width resolves
        constraint_tol=constraint_tol, penalty_growth=penalty_growth)
    U = jnp.clip(inputs, problem.u_lo, problem.u_hi)
    start = start_subproblem(problem, ILQRState(
        knot_states=problem.rollout(U), knot_inputs=U, multiplier=jnp.zeros(n, dtype),
        penalty=jnp.asarray(penalty, dtype), cost=jnp.zeros((), dtype), regularization=jnp.zeros((), dtype),
        iterations=jnp.asarray(0), updates=jnp.asarray(0), running=jnp.asarray(True)))
    s = jax.lax.while_loop(lambda s: s.running, functools.partial(iteration, problem), start)
    cost = problem.objective(s.knot_states, s.knot_inputs)
    violation = problem.violation(s.knot_states)
    finite = jnp.isfinite(cost) & jnp.all(jnp.isfinite(s.knot_states))
    status = jnp.select([~finite, s.iterations >= max_iterations,
                         ~(violation <= constraint_tol)],
                        [ILQRStatus.NONFINITE, ILQRStatus.MAXIMUM_ITERATIONS, ILQRStatus.GOAL_NOT_REACHED],
                        ILQRStatus.SUCCESS)
    return ILQRResult(knot_states=s.knot_states, knot_inputs=s.knot_inputs, time_step=h, cost=cost,
                      constraint_violation=violation, iterations=s.iterations, status=status)


class ILQRProblem(eqx.Module):
    r"""What every stage reads, fixed for one solve: the discretized dynamics
    $x_{k+1} = \Phi(t_k, x_k, u_k)$ from `x0` at the knot times $t_k = k h$, the costs, the input
    box $[u_{lo}, u_{hi}]$, the goal $c(x) = x - x_{goal}$ on the entries of `goal_mask` (`goal`
    None: no goal), and the loops' budget and tolerances. Closed over by the loops, never passed
    through a transformation."""

    system: System
    running_cost: Callable
    final_cost: Callable
    x0: jax.Array
    times: jax.Array  # (N,)
    h: jax.Array
    u_lo: jax.Array  # (m,)
    u_hi: jax.Array
    goal: jax.Array | None  # (n,), zero where free
    goal_mask: jax.Array | None  # (n,) bool: the constrained entries
    max_iterations: int  # iLQR iterations, shared by all subproblems
    max_outer: int  # subproblems (multiplier updates)
    final_tol: float  # the relative cost change that ends the last subproblems
    constraint_tol: float
    penalty_growth: float

    @property
    def dtype(self):
        return self.x0.dtype

    def step(self, t, x, u):
        r"""$\Phi(t, x, u)$: an RK4 step with u held (a discrete system's update)."""
        return discrete_step(self.system, t, x, u, self.h, "rk4")

    def step_derivatives(self, t, x, u):
        """((Phi_xx, Phi_xu, Phi_uu), (Phi_x, Phi_u)): the step's second-derivative tensors
        (output index first) with its Jacobians."""
        def jacobians(x, u):
            A, B = jax.jacfwd(self.step, (1, 2))(t, x, u)
            return (A, B), (A, B)
        ((fxx, fxu), (_, fuu)), first = jax.jacfwd(jacobians, (0, 1), has_aux=True)(x, u)
        return (fxx, fxu, fuu), first

    def goal_constraint(self, x):
        """c(x) = x - x_goal on the constrained entries, zero elsewhere (zero without a goal)."""
        if self.goal is None:
            return jnp.zeros(self.system.num_states, self.dtype)
        return jnp.where(self.goal_mask, x - self.goal, 0.0)

    def stage_cost(self, t, x, u):
        r"""$h\,\ell(t, x, u)$."""
        return self.h * self.running_cost(t, x, u)

    def terminal_cost(self, x, multiplier, penalty):
        r"""The augmented Lagrangian's final cost, $\ell_f(x) + \lambda^T c(x) + \tfrac{\mu}{2} |c(x)|^2$."""
        c = self.goal_constraint(x)
        return self.final_cost(x) + multiplier @ c + penalty / 2 * c @ c

    def rollout(self, U):
        """The knot states (N+1, n) from x0 under the inputs U."""
        def body(x, tu):
            t, u = tu
            return self.step(t, x, u), x
        xN, X = jax.lax.scan(body, self.x0, (self.times, U))
        return jnp.concatenate([X, xN[None]])

    def running_total(self, X, U):
        r"""$\sum_k h\,\ell(t_k, x_k, u_k)$."""
        return jnp.sum(jax.vmap(self.stage_cost)(self.times, X[:-1], U))

    def augmented_cost(self, X, U, multiplier, penalty):
        r"""The augmented Lagrangian, $\sum_k h\,\ell(t_k, x_k, u_k) + \ell_f(x_N) + \lambda^T c(x_N) +
        \tfrac{\mu}{2} |c(x_N)|^2$."""
        return self.running_total(X, U) + self.terminal_cost(X[-1], multiplier, penalty)

    def objective(self, X, U):
        r"""$J = \sum_k h\,\ell(t_k, x_k, u_k) + \ell_f(x_N)$, without the constraint terms."""
        return self.running_total(X, U) + self.final_cost(X[-1])

    def violation(self, X):
        """max |c(x_N)| (the inputs are clamped into their bounds, never outside)."""
        return jnp.max(jnp.abs(self.goal_constraint(X[-1])), initial=0.0)

    def inner_tolerance(self, updates):
        """The relative cost change that ends subproblem `updates`: loose first (1e-3), ten
        times tighter after each multiplier update, down to `final_tol` (as ALTRO)."""
        return jnp.maximum(self.final_tol, 1e-3 * 0.1 ** updates.astype(self.dtype))


class ILQRState(eqx.Module):
    """The solver's state: one iLQR iteration per step of the one loop, the augmented-Lagrangian
    updates folded in between (a batch then waits for its slowest member's total, not for the
    sum over subproblems of each one's slowest)."""

    knot_states: jax.Array  # X (N+1, n)
    knot_inputs: jax.Array  # U (N, m)
    multiplier: jax.Array  # lambda (n,), of the goal constraint
    penalty: jax.Array  # mu
    cost: jax.Array  # the augmented cost of the knots for lambda, mu
    regularization: jax.Array  # rho, added to the value Hessian for the gains
    iterations: jax.Array  # iLQR iterations so far, all subproblems together
    updates: jax.Array  # multiplier updates so far (subproblems solved)
    running: jax.Array  # False once the solve has ended: the state no longer changes


class StepModel(eqx.Module):
    """The second-order model of each step about the nominal knots (leading axis N): the
    dynamics' Jacobians and second-derivative tensors (output index first), the stage cost's
    gradient and Hessian blocks, and the nominal input."""

    A: jax.Array  # Phi_x (n, n)
    B: jax.Array  # Phi_u (n, m)
    fxx: jax.Array  # Phi_xx (n, n, n)
    fxu: jax.Array  # Phi_xu (n, n, m)
    fuu: jax.Array  # Phi_uu (n, m, m)
    lx: jax.Array
    lu: jax.Array
    lxx: jax.Array
    lux: jax.Array  # (m, n)
    luu: jax.Array
    u: jax.Array


class Gains(eqx.Module):
    r"""The backward pass's policy $u_k = \bar u_k + \alpha k_k + K_k (x_k - \bar x_k)$ (clamped),
    whether every step's factorization stayed finite, and the model's predicted decrease
    $\Delta V(\alpha) = -(\alpha d_1 + \alpha^2 d_2)$, $d = (\sum_k k_k^T Q_u, \sum_k \tfrac12 k_k^T Q_{uu} k_k)$."""

    feedforward: jax.Array  # k (N, m)
    feedback: jax.Array  # K (N, m, n)
    ok: jax.Array
    decrease: jax.Array  # d (2,)


def expand_steps(problem: ILQRProblem, X, U) -> StepModel:
    """Every step's `StepModel` at once (vmapped), off the backward pass's sequential path,
    which then only contracts the tensors with V_x."""
    (fxx, fxu, fuu), (A, B) = jax.vmap(problem.step_derivatives)(problem.times, X[:-1], U)
    lx, lu = jax.vmap(jax.grad(problem.stage_cost, (1, 2)))(problem.times, X[:-1], U)
    (lxx, _), (lux, luu) = jax.vmap(jax.hessian(problem.stage_cost, (1, 2)))(problem.times, X[:-1], U)
    return StepModel(A=A, B=B, fxx=fxx, fxu=fxu, fuu=fuu, lx=lx, lu=lu, lxx=lxx, lux=lux, luu=luu, u=U)


def convexified(H):
    r"""H where it is positive definite; else $H + sI$ with the Gershgorin shift
    $s = \max_i (\sum_{j \ne i} |H_{ij}| - H_{ii}) + \max_i |H_{ii}|$, which makes it
    diagonally dominant (for one input, $|H|$: the curvature's sign flipped, as saddle-free
    Newton does). The DDP curvature $V_x' \cdot \Phi_{uu}$ can make $Q_{uu}$ indefinite after a
    penalty increase; a step then costs one knot's shift instead of an iteration spent raising
    the regularization (the batch's stragglers waited for those: 106 iterations against a
    median of 26 among 8192 pendulum swing-ups, float32 on a GPU)."""
    definite = jnp.all(jnp.isfinite(jnp.linalg.cholesky(H)))
    diagonal = jnp.diagonal(H)
    shift = jnp.max(jnp.sum(jnp.abs(H), 1) - jnp.abs(diagonal) - diagonal) + jnp.max(jnp.abs(diagonal))
    return jnp.where(definite, H, H + shift * jnp.eye(H.shape[0], dtype=H.dtype))


def backward_step(problem: ILQRProblem, regularization, carry, k: StepModel):
    r"""One step of the backward pass, from $(V_x', V_{xx}')$ at step k+1 (DDP, with the
    dynamics' curvature):

    $$Q_x = \ell_x + A^T V_x', \quad Q_u = \ell_u + B^T V_x', \quad
      Q_{xx} = \ell_{xx} + A^T V_{xx}' A + V_x' \cdot \Phi_{xx},$$
    $$Q_{ux} = \ell_{ux} + B^T V_{xx}' A + V_x' \cdot \Phi_{ux}, \quad
      Q_{uu} = \ell_{uu} + B^T V_{xx}' B + V_x' \cdot \Phi_{uu};$$

    the gains from the regularized $\tilde Q = Q$ with $V_{xx}' + \rho I$ for $V_{xx}'$ (Tassa
    et al. 2012, eq. 10-11), made positive definite where it is not (`convexified`): $k$ solves
    the box QP $\min \tfrac12 k^T \tilde Q_{uu} k + Q_u^T k$,
    $u_{lo} - \bar u \le k \le u_{hi} - \bar u$ (warm-started at the next step's k), and
    $K = -\tilde Q_{uu}^{-1} \tilde Q_{ux}$ on the free inputs, zero on the clamped ones; then

    $$V_x = Q_x + K^T Q_{uu} k + K^T Q_u + Q_{ux}^T k, \quad
      V_{xx} = Q_{xx} + K^T Q_{uu} K + K^T Q_{ux} + Q_{ux}^T K.$$

    carry: (V_x, V_xx, ok, d, the next step's k); returns it for step k with (k, K)."""
    Vx, Vxx, ok, decrease, warm = carry
    n = Vx.shape[0]
    curvature = lambda T: jnp.tensordot(Vx, T, axes=1)  # noqa: E731  (V_x' . d^2 Phi)
    lxx, lux, luu = k.lxx + curvature(k.fxx), k.lux + curvature(k.fxu).T, k.luu + curvature(k.fuu)  # DDP
    A, B = k.A, k.B
    Vreg = Vxx + regularization * jnp.eye(n, dtype=Vxx.dtype)
    Qx, Qu = k.lx + A.T @ Vx, k.lu + B.T @ Vx
    Qxx = lxx + A.T @ Vxx @ A
    Quu, Qux = luu + B.T @ Vxx @ B, lux + B.T @ Vxx @ A
    Quu_reg = luu + B.T @ Vreg @ B
    kff, free, chol = box_qp(convexified((Quu_reg + Quu_reg.T) / 2), Qu, problem.u_lo - k.u, problem.u_hi - k.u, warm)
    ok = ok & jnp.all(jnp.isfinite(chol))
    K = jnp.where(free[:, None], -jax.scipy.linalg.cho_solve((chol, True), lux + B.T @ Vreg @ A), 0.0)
    Vx = Qx + K.T @ Quu @ kff + K.T @ Qu + Qux.T @ kff
    Vxx = Qxx + K.T @ Quu @ K + K.T @ Qux + Qux.T @ K
    decrease = decrease + jnp.stack([kff @ Qu, kff @ Quu @ kff / 2])
    return (Vx, (Vxx + Vxx.T) / 2, ok, decrease, kff), (kff, K)


def backward_pass(problem: ILQRProblem, X, U, multiplier, penalty, regularization) -> Gains:
    r"""The gains about the knots (X, U): `backward_step` from the final step to the first,
    starting from the augmented final cost's $V_x = \nabla L_f(x_N)$, $V_{xx} = \nabla^2 L_f(x_N)$."""
    model = expand_steps(problem, X, U)
    Vx = jax.grad(problem.terminal_cost)(X[-1], multiplier, penalty)
    Vxx = jax.hessian(problem.terminal_cost)(X[-1], multiplier, penalty)
    m, dtype = U.shape[1], U.dtype
    start = (Vx, Vxx, jnp.asarray(True), jnp.zeros(2, dtype), jnp.zeros(m, dtype))
    (_, _, ok, decrease, _), (kff, K) = jax.lax.scan(functools.partial(backward_step, problem, regularization),
                                                     start, model, reverse=True)
    return Gains(feedforward=kff, feedback=K, ok=ok, decrease=decrease)


def forward_pass(problem: ILQRProblem, X, U, gains: Gains, alpha):
    r"""The knots under the policy: $x_0$ given, $u_k = \mathrm{clip}(\bar u_k + \alpha k_k +
    K_k (x_k - \bar x_k), u_{lo}, u_{hi})$, $x_{k+1} = \Phi(t_k, x_k, u_k)$. Returns (X, U)."""
    def body(x, per_step):
        t, xb, ub, k, K = per_step
        u = jnp.clip(ub + alpha * k + K @ (x - xb), problem.u_lo, problem.u_hi)
        return problem.step(t, x, u), (x, u)
    xN, (X_new, U_new) = jax.lax.scan(body, problem.x0, (problem.times, X[:-1], U, gains.feedforward, gains.feedback))
    return jnp.concatenate([X_new, xN[None]]), U_new


def line_search(problem: ILQRProblem, X, U, cost, gains: Gains, multiplier, penalty):
    r"""Backtracking over $\alpha \in \{1, \tfrac12, \dots, 2^{-9}\}$, all forward passes at once:
    the largest $\alpha$ whose cost $J(\alpha)$ is finite, below J, and decreases by at least
    $10^{-4}$ of the predicted $\Delta V(\alpha)$ (Armijo). Returns (X, U, cost, improved): the
    knots unchanged when no step is accepted (or the gains are not `ok`)."""
    alphas = jnp.asarray(_ALPHAS, cost.dtype)
    trials = jax.vmap(lambda a: forward_pass(problem, X, U, gains, a))(alphas)
    costs = jax.vmap(lambda Xa, Ua: problem.augmented_cost(Xa, Ua, multiplier, penalty))(*trials)
    expected = -(alphas * gains.decrease[0] + alphas ** 2 * gains.decrease[1])
    accept = gains.ok & jnp.isfinite(costs) & ((cost - costs) > 1e-4 * jnp.maximum(expected, 0.0)) & (costs < cost)
    best = jnp.argmax(accept)  # the largest accepted step
    improved = jnp.any(accept)
    return (jnp.where(improved, trials[0][best], X), jnp.where(improved, trials[1][best], U),
            jnp.where(improved, costs[best], cost), improved)


def update_regularization(regularization, improved):
    r"""Levenberg-Marquardt: $\rho \leftarrow \max(\rho / 10, 10^{-9})$ after a step,
    $\min(10 \rho, 10^{10})$ after none."""
    return jnp.where(improved, jnp.maximum(regularization / 10, 1e-9), jnp.minimum(regularization * 10, 1e10))


def subproblem_converged(cost, new_cost, improved, gains: Gains, regularization, tolerance):
    r"""Done when a step changed the cost by at most `tolerance` $(1 + |J|)$; or the model's
    own predicted decrease for a full step, $\Delta V(1) = -(d_1 + d_2)$, is at rounding
    ($10\,\epsilon\,(1 + |J|)$: nothing left to gain at this float width); or no step helps
    even at the largest regularization."""
    small = improved & (cost - new_cost <= tolerance * (1 + jnp.abs(new_cost)))
    flat = -(gains.decrease[0] + gains.decrease[1]) <= 10 * jnp.finfo(cost.dtype).eps * (1 + jnp.abs(cost))
    return small | (gains.ok & flat) | (~improved & (regularization >= 1e10))


def ddp_iteration(problem: ILQRProblem, s: ILQRState):
    """One iteration of the current subproblem: `backward_pass`, `line_search`,
    `update_regularization`; returns the new state and whether the subproblem is over
    (`subproblem_converged` at `inner_tolerance`, or the budget spent)."""
    gains = backward_pass(problem, s.knot_states, s.knot_inputs, s.multiplier, s.penalty, s.regularization)
    X, U, cost, improved = line_search(problem, s.knot_states, s.knot_inputs, s.cost, gains, s.multiplier, s.penalty)
    regularization = update_regularization(s.regularization, improved)
    converged = subproblem_converged(s.cost, cost, improved, gains, regularization, problem.inner_tolerance(s.updates))
    s = dataclasses.replace(s, knot_states=X, knot_inputs=U, cost=cost, regularization=regularization,
                            iterations=s.iterations + 1)
    return s, converged | (s.iterations >= problem.max_iterations)


def update_multiplier(problem: ILQRProblem, s: ILQRState) -> ILQRState:
    r"""The method of multipliers: $\lambda \leftarrow \lambda + \mu\, c(x_N)$, then
    $\mu \leftarrow \min(\text{penalty\_growth}\,\mu, 10^8)$, and `start_subproblem`."""
    multiplier = s.multiplier + s.penalty * problem.goal_constraint(s.knot_states[-1])
    penalty = jnp.minimum(s.penalty * problem.penalty_growth, 1e8)
    return start_subproblem(problem, dataclasses.replace(s, multiplier=multiplier, penalty=penalty,
                                                         updates=s.updates + 1))


def start_subproblem(problem: ILQRProblem, s: ILQRState) -> ILQRState:
    r"""The subproblem of the current $\lambda$, $\mu$ from the current knots: their augmented
    cost, fresh regularization ($\rho = 10^{-6}$), and whether to run it at all (`keep_going`)."""
    s = dataclasses.replace(s, cost=problem.augmented_cost(s.knot_states, s.knot_inputs, s.multiplier, s.penalty),
                            regularization=jnp.full_like(s.regularization, _FRESH_REGULARIZATION))
    return dataclasses.replace(s, running=keep_going(problem, s))


def iteration(problem: ILQRProblem, s: ILQRState) -> ILQRState:
    """One step of the loop: a `ddp_iteration`, then `update_multiplier` if it ended the
    subproblem (selected per member, so `jax.vmap` keeps one loop)."""
    s, over = ddp_iteration(problem, s)
    return jax.tree.map(functools.partial(jnp.where, over), update_multiplier(problem, s), s)


def keep_going(problem: ILQRProblem, s: ILQRState):
    """Another subproblem while the budget lasts (`max_outer`, `max_iterations`) and: none has
    run yet, the goal is violated by more than `constraint_tol`, or the last one was solved
    only to a loose tolerance."""
    last_was_loose = problem.inner_tolerance(s.updates - 1) > problem.final_tol
    unfinished = (s.updates == 0) | (problem.violation(s.knot_states) > problem.constraint_tol) | last_was_loose
    return (s.updates < problem.max_outer) & (s.iterations < problem.max_iterations) & unfinished
