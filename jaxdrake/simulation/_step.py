"""`discrete_step`: one step of a plain system with its input held, the rule shared by the
trajectory programs, iLQR and the LCM node."""

from __future__ import annotations

import jax

from ._solvers import AbstractSolver, make_solver

FIXED_STEP_RULES = ("euler", "midpoint", "rk4")


def discrete_step(system, t, x, u, h, rule: str = "rk4", substeps: int = 1):
    r"""$x_{k+1} = \Phi_h(t_k, x_k, u_k)$ with $u$ held over the step.

    A discrete system takes its update, $x_{k+1} = f_d(t_k, x_k, u_k)$ (h is its period); a
    continuous one takes `substeps` steps of size h / substeps of the fixed-step `rule`
    (`"euler"`, `"midpoint"` or `"rk4"`, the simulator's own solvers); a system without state
    keeps x. Plain systems only (not hybrid or mixed: `simulate` runs those).
    """
    if system.has_discrete_state:
        return system.update(t, x, u)
    if not system.num_states:
        return x
    solver = rule if isinstance(rule, AbstractSolver) else make_solver(rule)
    if solver.adaptive:
        raise ValueError(f"discrete_step needs a fixed-step rule, one of {FIXED_STEP_RULES}, got {rule!r}")
    dt = h / substeps

    def one(i, x):
        s = t + i * dt
        return solver.step(lambda tt, y: system.dynamics(tt, y, u), s, x, lambda k0: dt).y1

    return jax.lax.fori_loop(0, substeps, one, x) if substeps > 1 else one(0, x)
