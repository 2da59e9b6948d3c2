"""One-step ODE methods, each with a dense-output polynomial.

Every method returns, besides the new state, the coefficients $c_0..c_4$ of its continuous
extension in monomial form, $y(t_0 + \\theta h) = \\sum_j c_j \\theta^j$ for $\\theta \\in [0, 1]$.
The monomial form makes the simulation loop solver-agnostic: a step cut short at an event
at $\\theta^*$ is the polynomial with coefficients $c_j \\theta^{*j}$.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..trajectories._trajectory import NUM_COEFFICIENTS


def _pad(coefficients):
    """Stack dense-output coefficients, padding with zero rows to NUM_COEFFICIENTS."""
    rows = list(coefficients)
    rows += [jnp.zeros_like(rows[0])] * (NUM_COEFFICIENTS - len(rows))
    return jnp.stack(rows)


class AbstractSolver(eqx.Module):
    """A one-step method for $\\dot y = f(t, y)$.

    `step(f, t0, h, y0, f0=None)` returns `(y1, error_estimate, coefficients, f1)`;
    `error_estimate` is None for fixed-step methods. `error_order` q means the estimate is
    $O(h^{q+1})$, which sets the exponent of the step-size controller. A method with `fsal`
    ("first same as last") evaluates $f_1 = f(t_0 + h, y_1)$ anyway and returns it, and takes
    it back as `f0` of the next step, saving one evaluation; others return None.
    """

    adaptive: ClassVar[bool]
    order: ClassVar[int]
    error_order: ClassVar[int]
    fsal: ClassVar[bool] = False

    @abc.abstractmethod
    def step(self, f, t0, h, y0, f0=None):
        ...


class Euler(AbstractSolver):
    """Forward Euler, $y_1 = y_0 + h f(t_0, y_0)$; fixed step, linear dense output."""

    adaptive: ClassVar[bool] = False
    order: ClassVar[int] = 1
    error_order: ClassVar[int] = 1

    def step(self, f, t0, h, y0, f0=None):
        dy = h * f(t0, y0)
        return y0 + dy, None, _pad([y0, dy]), None


class Midpoint(AbstractSolver):
    """The explicit midpoint rule, $y_1 = y_0 + h f(t_0 + h/2,\ y_0 + \tfrac h2 f(t_0, y_0))$; fixed
    step. Dense output: the quadratic through $y_0$ with slope $f_0$ reaching $y_1$."""

    adaptive: ClassVar[bool] = False
    order: ClassVar[int] = 2
    error_order: ClassVar[int] = 2

    def step(self, f, t0, h, y0, f0=None):
        k1 = f(t0, y0)
        k2 = f(t0 + h / 2, y0 + h / 2 * k1)
        return y0 + h * k2, None, _pad([y0, h * k1, h * (k2 - k1)]), None


class RK4(AbstractSolver):
    """The classical fourth-order Runge-Kutta method; fixed step.

    Dense output: its third-order continuous extension (Hairer, Norsett & Wanner, *Solving
    ODEs I*, II.6), $b_1(\\theta) = \\theta - \\tfrac32\\theta^2 + \\tfrac23\\theta^3$,
    $b_2 = b_3 = \\theta^2 - \\tfrac23\\theta^3$, $b_4 = -\\tfrac12\\theta^2 + \\tfrac23\\theta^3$.
    """

    adaptive: ClassVar[bool] = False
    order: ClassVar[int] = 4
    error_order: ClassVar[int] = 4

    def step(self, f, t0, h, y0, f0=None):
        k1 = f(t0, y0)
        k2 = f(t0 + h / 2, y0 + h / 2 * k1)
        k3 = f(t0 + h / 2, y0 + h / 2 * k2)
        k4 = f(t0 + h, y0 + h * k3)
        y1 = y0 + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        c2 = h * (-1.5 * k1 + k2 + k3 - 0.5 * k4)
        c3 = h * (2.0 / 3.0) * (k1 - k2 - k3 + k4)
        return y1, None, _pad([y0, h * k1, c2, c3]), None


# Dormand & Prince (1980) tableau, and Shampine's dense-output weights as given by Hairer,
# Norsett & Wanner, *Solving ODEs I* (the `contd5` continuous extension of DOPRI5).
_DP_C = (0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0)
_DP_A = (
    (),
    (1 / 5,),
    (3 / 40, 9 / 40),
    (44 / 45, -56 / 15, 32 / 9),
    (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
    (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
    (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
)
_DP_E = (71 / 57600, 0.0, -71 / 16695, 71 / 1920, -17253 / 339200, 22 / 525, -1 / 40)
_DP_D = (-12715105075 / 11282082432, 0.0, 87487479700 / 32700410799,
         -10690763975 / 1880347072, 701980252875 / 199316789632,
         -1453857185 / 822651844, 69997945 / 29380423)


class Dopri5(AbstractSolver):
    """Dormand-Prince 5(4): adaptive, fifth order with a fourth-order error estimate, and
    a fourth-order dense output. The default solver (MATLAB's ode45, SciPy's RK45)."""

    adaptive: ClassVar[bool] = True
    order: ClassVar[int] = 5
    error_order: ClassVar[int] = 4
    fsal: ClassVar[bool] = True

    def step(self, f, t0, h, y0, f0=None):
        ks = [] if f0 is None else [f0]
        for c, a in zip(_DP_C[len(ks):], _DP_A[len(ks):]):
            yi = y0
            for aij, kj in zip(a, ks):
                if aij != 0.0:
                    yi = yi + (h * aij) * kj
            if len(ks) == 6:
                y1 = yi  # the seventh stage is evaluated at the new point (FSAL)
            ks.append(f(t0 + c * h, yi))
        err = h * sum(e * k for e, k in zip(_DP_E, ks) if e != 0.0)
        r2 = y1 - y0
        r3 = h * ks[0] - r2
        r4 = r2 - h * ks[6] - r3
        r5 = h * sum(d * k for d, k in zip(_DP_D, ks) if d != 0.0)
        # y0 + th(r2 + (1-th)(r3 + th(r4 + (1-th) r5))) expanded in powers of th
        return y1, err, _pad([y0, r2 + r3, r4 + r5 - r3, -(r4 + 2 * r5), r5]), ks[6]


_ROS_D = 1.0 / (2.0 + np.sqrt(2.0))
_ROS_E32 = 6.0 + np.sqrt(2.0)


class Rosenbrock23(AbstractSolver):
    """The L-stable linearly implicit Rosenbrock method of MATLAB's ode23s (Shampine &
    Reichelt, "The MATLAB ODE Suite", 1997), for stiff systems.

    With $W = I - h d J$, $J = \\partial f/\\partial y$, $T = \\partial f / \\partial t$,
    $d = 1/(2+\\sqrt 2)$: $k_1 = W^{-1}(f_0 + h d T)$,
    $k_2 = W^{-1}(f(t_0 + h/2, y_0 + h k_1/2) - k_1) + k_1$, $y_1 = y_0 + h k_2$ (second
    order), and a third-order error estimate. No Newton iterations: one Jacobian (by
    forward-mode autodiff) and one LU factorization per step.
    """

    adaptive: ClassVar[bool] = True
    order: ClassVar[int] = 2
    error_order: ClassVar[int] = 2

    def step(self, f, t0, h, y0, f0=None):
        d = _ROS_D
        f0, dfdt = jax.jvp(lambda t: f(t, y0), (t0,), (jnp.ones_like(t0),))
        J = jax.jacfwd(lambda y: f(t0, y))(y0)
        W = jnp.eye(y0.shape[0], dtype=y0.dtype) - (h * d) * J
        lu = jax.scipy.linalg.lu_factor(W)
        solve = lambda b: jax.scipy.linalg.lu_solve(lu, b)
        k1 = solve(f0 + (h * d) * dfdt)
        f1 = f(t0 + h / 2, y0 + (h / 2) * k1)
        k2 = solve(f1 - k1) + k1
        y1 = y0 + h * k2
        f2 = f(t0 + h, y1)
        k3 = solve(f2 - _ROS_E32 * (k2 - f1) - 2.0 * (k1 - f0) + (h * d) * dfdt)
        err = (h / 6.0) * (k1 - 2.0 * k2 + k3)
        scale = h / (1.0 - 2.0 * d)
        return y1, err, _pad([y0, scale * (k1 - 2.0 * d * k2), scale * (k2 - k1)]), None


SOLVERS = {"dopri5": Dopri5, "rk4": RK4, "midpoint": Midpoint, "euler": Euler, "rosenbrock23": Rosenbrock23}


def make_solver(solver) -> AbstractSolver:
    """Accept a solver instance or one of the names in `SOLVERS`."""
    if isinstance(solver, AbstractSolver):
        return solver
    if isinstance(solver, str) and solver.lower() in SOLVERS:
        return SOLVERS[solver.lower()]()
    raise ValueError(f"unknown solver {solver!r}; use one of {sorted(SOLVERS)} or a solver instance")
