"""One-step ODE methods, each with a dense-output polynomial, each tracing the vector field once.

Every method returns, besides the new state, the coefficients $c_0..c_4$ of its continuous
extension in monomial form, $y(t_0 + \\theta h) = \\sum_j c_j \\theta^j$ for $\\theta \\in [0, 1]$.
The monomial form makes the simulation loop solver-agnostic: a step cut short at an event
at $\\theta^*$ is the polynomial with coefficients $c_j \\theta^{*j}$.

The stages of an explicit Runge-Kutta method run in a `lax.scan` over the rows of its Butcher
tableau (as Diffrax does), so the vector field appears once in the compiled program whatever
the number of stages; its dense output is a fixed linear combination of the stages. The
step size is chosen *inside* the step, from the first stage $k_0 = f(t_0, y_0)$ (through the
caller's `step_size(k0)`), so that an adaptive method's initial-step heuristic needs no
evaluation of its own.
"""

from __future__ import annotations

import abc
import dataclasses
import functools
from typing import ClassVar

import equinox as eqx
import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from ..trajectories import NUM_COEFFICIENTS


class StepResult(eqx.Module):
    """What one attempted step produced.

    - `h`: the step size taken (from the caller's `step_size`).
    - `k_first`: $f(t_0, y_0)$, the first stage (from which `step_size` chose h).
    - `y1`: the state at $t_0 + h$.
    - `error`: the local error estimate (None for fixed-step methods).
    - `coefficients`: (NUM_COEFFICIENTS, n), the dense output in the normalized time.
    - `k_last`: $f(t_0 + h, y_1)$ for a first-same-as-last method (the next step's first
      stage), else None.
    - `linearization`: the matrix the step used, for a method that may reuse it (else None).
    """

    h: jax.Array
    k_first: jax.Array
    y1: jax.Array
    error: jax.Array | None
    coefficients: jax.Array
    k_last: jax.Array | None
    linearization: Linearization | None = None


class Linearization(eqx.Module):
    """$J = \\partial f/\\partial y$ and $T = \\partial f/\\partial t$ as a linearly implicit
    method formed them at the start of an attempt, kept by the simulation loop: a rejected
    attempt leaves the state where it was, so the next attempt reuses them (`current`)."""

    jacobian: jax.Array
    time_derivative: jax.Array
    current: jax.Array  # formed at the point the next attempt starts from

    @classmethod
    def none(cls, n, dtype):
        return cls(jnp.zeros((n, n), dtype), jnp.zeros(n, dtype), jnp.asarray(False))

    def after(self, accepted):
        """After an attempt: an accepted step moves the state away from it."""
        return dataclasses.replace(self, current=self.current & ~accepted)


class AbstractSolver(eqx.Module):
    """A one-step method for $\\dot y = f(t, y)$.

    `step(f, t0, y0, step_size, k0=None, f_stiff=None, linearization=None)` takes the step
    of size `h = step_size(k0)`, where $k_0 = f(t_0, y_0)$ is the method's first evaluation
    (given as `k0` to a first-same-as-last method, which then skips it) and returns a
    `StepResult`. `f_stiff`: the same vector field with a cheaper derivative that keeps its
    stiff terms (the systems' `stiff_linearization`), for a method that forms a Jacobian and
    is asked to use it. `linearization`: for a method with `reuses_linearization`, the
    `Linearization` of an earlier attempt, which it may use instead of forming one (the
    caller passes it only where the vector field changes through accepted steps alone).
    `error_order` q means the error estimate is $O(h^{q+1})$, which sets the exponent of the
    step-size controller. `fsal` ("first same as last"): the last stage is
    $f(t_0 + h, y_1)$, the next step's first.
    """

    adaptive: ClassVar[bool]
    order: ClassVar[int]
    error_order: ClassVar[int]
    fsal: ClassVar[bool] = False
    reuses_linearization: ClassVar[bool] = False

    @abc.abstractmethod
    def step(self, f, t0, y0, step_size, k0=None, f_stiff=None, linearization=None) -> StepResult:
        ...


class AbstractExplicitRungeKutta(AbstractSolver):
    r"""An explicit Runge-Kutta method given by its tableau: nodes `c`, the strictly lower
    triangular `a`, weights `b`, error weights `e` (None: fixed step) and `dense`, the rows
    $w_j$ with $c_j = h\,w_j \cdot k$ for $j = 1..4$ ($c_0 = y_0$).

    Stage $i$: $k_i = f(t_0 + c_i h,\ y_0 + h \sum_{j<i} a_{ij} k_j)$;
    $y_1 = y_0 + h \sum_i b_i k_i$; error $h \sum_i e_i k_i$.

    The vector field is traced once (`jax.make_jaxpr`) and evaluated from its jaxpr at every
    stage. A small one (equations x stages <= `UNROLL_BELOW`) runs its stages one after
    another, as straight-line code is faster than a loop whose per-iteration cost exceeds the
    evaluations; a larger one runs them in a `lax.scan` over the tableau, so it appears once in
    the compiled program. The weighted sums are elementwise products and sums in stage order
    (no matmul, no reduction), so a batched run agrees with single runs bit for bit.
    """

    c: ClassVar[np.ndarray]
    a: ClassVar[np.ndarray]
    b: ClassVar[np.ndarray]
    e: ClassVar[np.ndarray | None] = None
    dense: ClassVar[np.ndarray]

    def step(self, f, t0, y0, step_size, k0=None, f_stiff=None, linearization=None):
        # the vector field traced once, then evaluated from its jaxpr at every stage
        vector_field = jax.make_jaxpr(f)(t0, y0)
        evaluate = jax.extend.core.jaxpr_as_fun(vector_field)
        if _size(vector_field.jaxpr) * len(self.c) <= UNROLL_BELOW:
            return self._unrolled_step(lambda t, y: evaluate(t, y)[0], t0, y0, step_size, k0)
        return self._looped_step(lambda t, y: evaluate(t, y)[0], t0, y0, step_size, k0)

    def _unrolled_step(self, f, t0, y0, step_size, k0):
        """The stages one after another: for a small vector field, whose evaluations cost less
        than a loop iteration."""
        ks = [f(t0, y0) if k0 is None else k0]
        h = step_size(ks[0])
        for i in range(1, len(self.c)):
            ks.append(f(t0 + float(self.c[i]) * h, y0 + h * _combine(self.a[i, :i], ks)))
        y1 = y0 + h * _combine(self.b, ks)
        error = None if self.e is None else h * _combine(self.e, ks)
        coefficients = jnp.stack([y0] + [h * _combine(row, ks) for row in self.dense])
        return StepResult(h, ks[0], y1, error, coefficients, ks[-1] if self.fsal else None)

    def _looped_step(self, f, t0, y0, step_size, k0):
        """The stages in a loop over the tableau: the vector field once in the program. Stage i,
        once known, adds $w_{mi} k_i$ to the running sum of every row m of
        $[a; b; e; \\text{dense}]$."""
        dtype = y0.dtype
        num_stages = len(self.c)
        rows = [self.a, self.b[None]] + ([] if self.e is None else [self.e[None]]) + [self.dense]
        weights = jnp.asarray(np.concatenate(rows), dtype)  # (rows, stages)
        c = jnp.asarray(self.c, dtype)
        sums = jnp.zeros((weights.shape[0],) + y0.shape, dtype)

        def add(sums, i, k):
            return sums + weights[:, i, None] * k

        first, k_first = 0, jnp.zeros_like(y0)  # the first stage's value, needed for h
        if k0 is not None:
            first, k_first, sums = 1, k0, add(sums, 0, k0)

        def stage(carry, i):
            sums, k_first = carry
            h = step_size(k_first)  # stage 0 sits at (t0, y0) whatever h is
            k = f(t0 + c[i] * h, y0 + h * sums[i])
            return (add(sums, i, k), jnp.where(i == 0, k, k_first)), k

        (sums, k_first), ks = jax.lax.scan(stage, (sums, k_first), jnp.arange(first, num_stages))
        h = step_size(k_first)
        s = num_stages
        y1 = y0 + h * sums[s]
        error = None if self.e is None else h * sums[s + 1]
        coefficients = jnp.concatenate([y0[None], h * sums[-(NUM_COEFFICIENTS - 1):]])
        return StepResult(h, k_first, y1, error, coefficients, ks[-1] if self.fsal else None)


def _combine(weights, ks):
    """sum_i weights[i] * ks[i] for static weights, added in stage order and skipping zeros:
    elementwise only (no matmul, which on a GPU may run in reduced precision, and no reduction,
    whose order XLA may change under vmap), so a batched run agrees with single runs bit for
    bit."""
    total = None
    for w, k in zip(np.asarray(weights, float).tolist(), ks):  # Python floats: weakly typed
        if w != 0.0:
            total = w * k if total is None else total + w * k
    return jnp.zeros_like(ks[0]) if total is None else total


UNROLL_BELOW = 400  # equations of the vector field x stages (a pendulum: ~10 x 7; an acrobot: ~500 x 7)


def _size(jaxpr) -> int:
    """The number of equations of a jaxpr, those of its sub-jaxprs included."""
    return len(jaxpr.eqns) + sum(_size(sub) for sub in jax.extend.core.subjaxprs(jaxpr))


def _dense_rows(*rows, num_stages):
    """Dense-output weights padded with zero rows to NUM_COEFFICIENTS - 1."""
    rows = [np.asarray(r, float) for r in rows]
    rows += [np.zeros(num_stages)] * (NUM_COEFFICIENTS - 1 - len(rows))
    return np.stack(rows)


class Euler(AbstractExplicitRungeKutta):
    """Forward Euler, $y_1 = y_0 + h f(t_0, y_0)$; fixed step, linear dense output."""

    adaptive: ClassVar[bool] = False
    order: ClassVar[int] = 1
    error_order: ClassVar[int] = 1
    c = np.array([0.0])
    a = np.zeros((1, 1))
    b = np.array([1.0])
    dense = _dense_rows([1.0], num_stages=1)


class Midpoint(AbstractExplicitRungeKutta):
    """The explicit midpoint rule, $y_1 = y_0 + h f(t_0 + h/2,\\ y_0 + \\tfrac h2 f(t_0, y_0))$;
    fixed step. Dense output: the quadratic through $y_0$ with slope $f_0$ reaching $y_1$."""

    adaptive: ClassVar[bool] = False
    order: ClassVar[int] = 2
    error_order: ClassVar[int] = 2
    c = np.array([0.0, 0.5])
    a = np.array([[0.0, 0.0], [0.5, 0.0]])
    b = np.array([0.0, 1.0])
    dense = _dense_rows([1.0, 0.0], [-1.0, 1.0], num_stages=2)


class RK4(AbstractExplicitRungeKutta):
    """The classical fourth-order Runge-Kutta method; fixed step.

    Dense output: its third-order continuous extension (Hairer, Norsett & Wanner, *Solving
    ODEs I*, II.6), $b_1(\\theta) = \\theta - \\tfrac32\\theta^2 + \\tfrac23\\theta^3$,
    $b_2 = b_3 = \\theta^2 - \\tfrac23\\theta^3$, $b_4 = -\\tfrac12\\theta^2 + \\tfrac23\\theta^3$.
    """

    adaptive: ClassVar[bool] = False
    order: ClassVar[int] = 4
    error_order: ClassVar[int] = 4
    c = np.array([0.0, 0.5, 0.5, 1.0])
    a = np.array([[0, 0, 0, 0], [0.5, 0, 0, 0], [0, 0.5, 0, 0], [0, 0, 1.0, 0]])
    b = np.array([1.0, 2.0, 2.0, 1.0]) / 6.0
    dense = _dense_rows([1.0, 0.0, 0.0, 0.0], [-1.5, 1.0, 1.0, -0.5],
                        [2.0 / 3.0, -2.0 / 3.0, -2.0 / 3.0, 2.0 / 3.0], num_stages=4)


# Dormand & Prince (1980) tableau, and Shampine's dense-output weights as given by Hairer,
# Norsett & Wanner, *Solving ODEs I* (the `contd5` continuous extension of DOPRI5).
_DP_C = np.array([0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0])
_DP_A = np.zeros((7, 7))
for _i, _row in enumerate([(), (1 / 5,), (3 / 40, 9 / 40), (44 / 45, -56 / 15, 32 / 9),
                           (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
                           (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
                           (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84)]):
    _DP_A[_i, :len(_row)] = _row
_DP_E = np.array([71 / 57600, 0.0, -71 / 16695, 71 / 1920, -17253 / 339200, 22 / 525, -1 / 40])
_DP_D = np.array([-12715105075 / 11282082432, 0.0, 87487479700 / 32700410799,
                  -10690763975 / 1880347072, 701980252875 / 199316789632,
                  -1453857185 / 822651844, 69997945 / 29380423])
_E0, _E6 = np.eye(7)[0], np.eye(7)[6]


class Dopri5(AbstractExplicitRungeKutta):
    """Dormand-Prince 5(4): adaptive, fifth order with a fourth-order error estimate, and
    a fourth-order dense output. The default solver (MATLAB's ode45, SciPy's RK45).

    Dense output: $y_0 + \\theta h(r_2 + (1-\\theta)(r_3 + \\theta(r_4 + (1-\\theta) r_5)))$
    with $r_2 = y_1 - y_0$, $r_3 = h k_0 - r_2$, $r_4 = r_2 - h k_6 - r_3$, $r_5 = h\\,d\\cdot k$,
    expanded in powers of $\\theta$ (each a fixed combination of the stages)."""

    adaptive: ClassVar[bool] = True
    order: ClassVar[int] = 5
    error_order: ClassVar[int] = 4
    fsal: ClassVar[bool] = True
    c = _DP_C
    a = _DP_A
    b = _DP_A[6]
    e = _DP_E
    dense = _dense_rows(_E0, 3 * _DP_A[6] - 2 * _E0 - _E6 + _DP_D,
                        -2 * _DP_A[6] + _E0 + _E6 - 2 * _DP_D, _DP_D, num_stages=7)


_ROS_D = float(1.0 / (2.0 + np.sqrt(2.0)))   # Python floats: weakly typed, so a float32 step stays float32
_ROS_E32 = float(6.0 + np.sqrt(2.0))


class _LinearlyImplicit(AbstractSolver):
    r"""A Rosenbrock (linearly implicit) method: $W = I - h\gamma J$ with J and
    $T = \partial f / \partial t$ formed once per step at its start and reused by the retry
    of a rejected step. `jacobian`: "exact" (of the vector field) or "stiff" (of the systems'
    `stiff_linearization`, for a W-method, which keeps its order with any matrix).

    J and T are held under differentiation, as step sizes are: a derivative through the step
    is that of the scheme with its matrix fixed, itself a W-method for the sensitivities, as
    accurate as the exact discrete derivative (a bouncing, spinning ball's gradient at rtol
    1e-8: 7e-6 from the exact ODE's, against 3.5e-6) without the second derivatives of the
    dynamics (its gradient ran 6x faster and compiled 2.4 s sooner)."""

    adaptive: ClassVar[bool] = True
    fsal: ClassVar[bool] = True   # f(t0 + h, y1) is evaluated: the next step's first stage
    reuses_linearization: ClassVar[bool] = True
    jacobian: str = eqx.field(static=True, default="exact")

    def __check_init__(self):
        if self.jacobian not in ("exact", "stiff"):
            raise ValueError(f"{type(self).__name__}(jacobian={self.jacobian!r}): use 'exact' (the vector field's "
                             "Jacobian) or 'stiff' (the systems' cheaper stiff_linearization)")

    def linearize(self, f, t0, y0, k0, f_stiff, linearization):
        """(f0, `Linearization`) at (t0, y0): formed, or an earlier attempt's where it is current."""
        linearized = f_stiff if (self.jacobian == "stiff" and f_stiff is not None) else f

        def form():
            f_linearized, tangent = jax.linearize(linearized, t0, y0)
            dfdt = tangent(jnp.ones_like(t0), jnp.zeros_like(y0))
            J = jax.vmap(lambda v: tangent(jnp.zeros_like(t0), v), out_axes=1)(
                jnp.eye(y0.shape[0], dtype=y0.dtype))
            # held, as step sizes are: derivatives are those of the scheme with its W fixed
            J, dfdt = jax.lax.stop_gradient((J, dfdt))
            return f_linearized, Linearization(J, dfdt, jnp.asarray(True))

        if linearization is None or k0 is None:
            f_linearized, linearization = form()
            if k0 is None and linearized is not f:   # f's own value, with f's derivative
                return f(t0, y0), linearization
            # given k0, the linearization's own value is dead code
            return (f_linearized if k0 is None else k0), linearization
        # after a rejected attempt, the same point's matrix again
        return k0, jax.lax.cond(linearization.current, lambda: linearization, lambda: form()[1])


class Rosenbrock23(_LinearlyImplicit):
    """The L-stable linearly implicit Rosenbrock method of MATLAB's ode23s (Shampine &
    Reichelt, "The MATLAB ODE Suite", 1997), for stiff systems; for tight tolerances
    `Ros34PW2` (third order) takes fewer steps.

    With $W = I - h d J$, $J = \\partial f/\\partial y$, $T = \\partial f / \\partial t$,
    $d = 1/(2+\\sqrt 2)$: $k_1 = W^{-1}(f_0 + h d T)$,
    $k_2 = W^{-1}(f(t_0 + h/2, y_0 + h k_1/2) - k_1) + k_1$, $y_1 = y_0 + h k_2$ (second
    order), and a third-order error estimate $\\tfrac h6(k_1 - 2k_2 + k_3)$,
    $k_3 = W^{-1}(f(t_0 + h, y_1) - e_{32}(k_2 - f_1) - 2(k_1 - f_0) + h d T)$. No Newton
    iterations: $f_0$, $T$ and $J$ from one linearization, one LU factorization per step, and
    the two further evaluations in a loop. In `simulate`, the retry of a rejected step reuses
    its J and T (the state has not moved), so they are formed once per accepted step.

    `jacobian="stiff"`: J from the systems' `stiff_linearization` (a `RigidBodySystem`:
    $\\partial \\dot v/\\partial(q, v) \\approx H^{-1}\\,\\partial\\tau/\\partial(q, v)$ of its
    contact, limit, damping and input forces, without the derivatives of H, Coriolis and
    gravity terms). The step stays second order with any matrix in place of J (a W-method:
    Shampine & Reichelt's formula; Hairer & Wanner, *Solving ODEs II*, IV.7); what the
    approximation leaves out must not be stiff. Solo-12 landing: a Jacobian ~10x cheaper to
    evaluate and much cheaper to compile, the simulation ~4x faster than with the exact one
    (benchmarks/RESULTS.md). Where it loses: on fast-swinging legs with rounded feet (a
    hopper: 1.5-3x the exact Jacobian's steps) what it leaves out (the derivatives of H and of
    the Coriolis terms) costs steps; `"rosenbrock23"` may be faster there.
    """

    order: ClassVar[int] = 2
    error_order: ClassVar[int] = 2

    def step(self, f, t0, y0, step_size, k0=None, f_stiff=None, linearization=None):
        d = _ROS_D
        f0, linearization = self.linearize(f, t0, y0, k0, f_stiff, linearization)
        J, dfdt = linearization.jacobian, linearization.time_derivative
        h = step_size(f0)
        W = jnp.eye(y0.shape[0], dtype=y0.dtype) - (h * d) * J
        lu = jax.scipy.linalg.lu_factor(W)
        solve = lambda b: jax.scipy.linalg.lu_solve(lu, b)  # noqa: E731
        k1 = solve(f0 + (h * d) * dfdt)

        def stage(carry, i):  # i = 0: f1 = f(t0 + h/2, y0 + h k1 / 2); i = 1: f2 = f(t0 + h, y1)
            k2, _ = carry
            fi = f(t0 + h * (0.5 + 0.5 * i), y0 + h * jnp.where(i == 0, 0.5 * k1, k2))
            return (jnp.where(i == 0, solve(fi - k1) + k1, k2), fi), fi

        (k2, f2), (f1, _) = jax.lax.scan(stage, (k1, f0), jnp.arange(2))
        y1 = y0 + h * k2
        k3 = solve(f2 - _ROS_E32 * (k2 - f1) - 2.0 * (k1 - f0) + (h * d) * dfdt)
        error = (h / 6.0) * (k1 - 2.0 * k2 + k3)
        scale = h / (1.0 - 2.0 * d)
        zeros = jnp.zeros((NUM_COEFFICIENTS - 3,) + y0.shape, y0.dtype)
        coefficients = jnp.concatenate([jnp.stack([y0, scale * (k1 - 2.0 * d * k2), scale * (k2 - k1)]), zeros])
        return StepResult(h, f0, y1, error, coefficients, f2, linearization)


# Rang & Angermann (2005), "New Rosenbrock W-methods of order 3 for partial differential
# algebraic equations of index 1", BIT 45: ROS34PW2, in Hairer & Wanner's form (IV.7)
_W34_GAMMA = 4.3586652150845900e-01
_W34_A = np.array([[0.0, 0.0, 0.0, 0.0],
                   [8.7173304301691801e-01, 0.0, 0.0, 0.0],
                   [8.4457060015369423e-01, -1.1299064236484185e-01, 0.0, 0.0],
                   [0.0, 0.0, 1.0, 0.0]])
_W34_G = np.array([[0.0, 0.0, 0.0, 0.0],   # the off-diagonal gamma_ij
                   [-8.7173304301691801e-01, 0.0, 0.0, 0.0],
                   [-9.0338057013044082e-01, 5.4180672388095326e-02, 0.0, 0.0],
                   [2.4212380706095346e-01, -1.2232505839045147e+00, 5.4526025533510214e-01, 0.0]])
_W34_B = np.array([2.4212380706095346e-01, -1.2232505839045147e+00, 1.5452602553351020e+00, 4.3586652150845900e-01])
_W34_B_EMBEDDED = np.array([3.7810903145819369e-01, -9.6042292212423178e-02, 0.5, 2.1793326075422950e-01])


class Ros34PW2(_LinearlyImplicit):
    r"""The L-stable Rosenbrock W-method ROS34PW2 of Rang & Angermann (2005): third order in
    four stages, with a second-order embedded error estimate, and third order with any matrix
    in place of J (a W-method), so `jacobian="stiff"` keeps its order. For stiff systems at
    tight tolerances, where `Rosenbrock23`'s second order takes many steps.

    With $W = I - h\gamma J$: $W k_i = h f(t_0 + \alpha_i h, y_0 + \sum_{j<i} a_{ij} k_j) +
    h J \sum_{j<i} \gamma_{ij} k_j + \gamma_i h^2 T$ ($\alpha_i = \sum_j a_{ij}$,
    $\gamma_i = \gamma + \sum_{j<i}\gamma_{ij}$), $y_1 = y_0 + \sum_i b_i k_i$, error
    $\sum_i (b_i - \hat b_i) k_i$; one LU factorization per step. $f(t_0 + h, y_1)$ is
    evaluated too: the next step's first stage, and with $f_0$ the cubic Hermite dense
    output (third order, as the step). The stages and that evaluation run in one loop, so
    the vector field is traced once."""

    order: ClassVar[int] = 3
    error_order: ClassVar[int] = 2

    def step(self, f, t0, y0, step_size, k0=None, f_stiff=None, linearization=None):
        f0, linearization = self.linearize(f, t0, y0, k0, f_stiff, linearization)
        J, dfdt = linearization.jacobian, linearization.time_derivative
        h = step_size(f0)
        lu = jax.scipy.linalg.lu_factor(jnp.eye(y0.shape[0], dtype=y0.dtype) - (h * _W34_GAMMA) * J)
        gammas = _W34_GAMMA + _W34_G.sum(1)
        # rows 0-3: the stages (stage 0's evaluation is f0); row 4: f(t0 + h, y1)
        a = np.vstack([_W34_A, _W34_B[None]])
        g = np.vstack([_W34_G, np.zeros((1, 4))])
        alpha = np.append(_W34_A.sum(1), 1.0)
        ks = jnp.zeros((4,) + y0.shape, y0.dtype)

        def stage(ks, row):
            i, a_i, g_i, alpha_i, gamma_i = row
            weighted = lambda w: jnp.tensordot(w, ks, 1)  # noqa: E731
            fi = jax.lax.cond(i == 0, lambda: f0, lambda: f(t0 + alpha_i * h, y0 + weighted(a_i)))
            k = jax.scipy.linalg.lu_solve(lu, h * fi + h * (J @ weighted(g_i)) + (gamma_i * h * h) * dfdt)
            return ks.at[jnp.minimum(i, 3)].set(jnp.where(i < 4, k, ks[3])), fi

        rows = (jnp.arange(5),) + tuple(jnp.asarray(x, y0.dtype) for x in (a, g, alpha, np.append(gammas, 0.0)))
        ks, evaluations = jax.lax.scan(stage, ks, rows)
        y1 = y0 + jnp.tensordot(jnp.asarray(_W34_B, y0.dtype), ks, 1)
        f1 = evaluations[4]
        error = jnp.tensordot(jnp.asarray(_W34_B - _W34_B_EMBEDDED, y0.dtype), ks, 1)
        dy = y1 - y0
        coefficients = jnp.stack([y0, h * f0, 3.0 * dy - h * (2.0 * f0 + f1), -2.0 * dy + h * (f0 + f1),
                                  jnp.zeros_like(y0)])
        return StepResult(h, f0, y1, error, coefficients, f1, linearization)


SOLVERS = {"dopri5": Dopri5, "rk4": RK4, "midpoint": Midpoint, "euler": Euler, "rosenbrock23": Rosenbrock23,
           "ros34pw2": Ros34PW2}


def make_solver(solver) -> AbstractSolver:
    """Accept a solver instance or one of the names in `SOLVERS`."""
    if isinstance(solver, AbstractSolver):
        return solver
    if isinstance(solver, str) and solver.lower() in SOLVERS:
        return _solver_named(solver.lower())
    if isinstance(solver, type) and issubclass(solver, AbstractSolver):
        raise TypeError(f"solver={solver.__name__} is a class: pass an instance, {solver.__name__}()")
    raise ValueError(f"unknown solver {solver!r}; use one of {sorted(SOLVERS)} or a solver instance")


@functools.cache
def _solver_named(name: str) -> AbstractSolver:
    """One instance per name (immutable; building an equinox module costs microseconds a call)."""
    return SOLVERS[name]()
