r"""Linearization and the linear-quadratic regulator (Underactuated ch. 8; Drake's
`Linearize`, `LinearQuadraticRegulator`).

`linearize(system, x0, u0)` differentiates the dynamics (or the discrete update) and the
output at an operating point with `jax.jacfwd`: $\dot{\tilde x} = A \tilde x + B \tilde u$,
$\tilde y = C \tilde x + D \tilde u$ in the deviations $\tilde x = x - x_0$,
$\tilde u = u - u_0$, $\tilde y = y - g(x_0, u_0)$. `lqr` solves the Riccati equation of the
linearization for $\int \tilde x^T Q \tilde x + \tilde u^T R \tilde u + 2 \tilde x^T N \tilde u\,dt$
(or the sum, for a discrete system) and returns $K$, $S$ and the controller
$u = u_0 - K (x - x_0)$ as a system ready for `feedback`.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._compiled import compiled
from .._numbers import array_module, call_argument
from .._status import Reported, StatusCode
from ..systems import LinearSystem, System
from ..systems import require_plain_system
from ._riccati import solve_continuous_are, solve_discrete_are


@compiled  # compiled once per system structure: a second call costs a dictionary look-up
def _linearization(system: System, t, x0, u0):
    """(f(x0, u0) - [x0 if discrete], A, B, C, D) at the operating point."""
    discrete = system.has_discrete_state
    f = system.update if discrete else system.dynamics
    residual = f(t, x0, u0) - (x0 if discrete else 0.0)
    A, B = jax.jacfwd(f, argnums=(1, 2))(t, x0, u0)
    C, D = jax.jacfwd(system.output, argnums=(1, 2))(t, x0, u0)
    return residual, A, B, C, D


def linearize(system: System, x0, u0=None, *, t=0.0, check_equilibrium: bool = True,
              tolerance: float | None = None) -> LinearSystem:
    """The `LinearSystem` (continuous, or discrete with the system's sample time) of the
    deviations from (x0, u0). With `check_equilibrium`, (x0, u0) must be a fixed point:
    $|f(x_0, u_0)| \\le$ tolerance (continuous) or $|f_d(x_0, u_0) - x_0| \\le$ tolerance
    (discrete); otherwise a ValueError gives the residual. Default tolerance: 1e-6, or 1000
    machine epsilons where that is more (1.2e-4 in float32, where the cart-pole's upright
    angle, pi rounded, leaves a derivative of 2e-6)."""
    require_plain_system(system, "linearize", "linearize a mode (or the nominal deterministic system) instead")
    # host numbers stay numpy arrays until the compiled call (no device transfer each)
    x0, u0 = operating_point("linearize", system, call_argument(x0, float),
                             call_argument(np.zeros(system.num_inputs) if u0 is None else u0, float))
    discrete = system.has_discrete_state
    residual, A, B, C, D = _linearization(system, call_argument(t, float), x0, u0)
    if check_equilibrium and not isinstance(residual, jax.core.Tracer):
        worst = float(np.max(np.abs(np.asarray(residual)))) if residual.size else 0.0
        if tolerance is None:
            tolerance = max(1e-6, 1000 * float(np.finfo(np.asarray(residual).dtype).eps))
        if worst > tolerance:
            raise ValueError(f"linearize: ({x0}, {u0}) is not an equilibrium of {system.name}: "
                             f"the {'update moves x by' if discrete else 'derivative is'} up to {worst:.3g} "
                             "(pass check_equilibrium=False to linearize anyway)")
    return LinearSystem(A, B.reshape(system.num_states, system.num_inputs), C,
                        D.reshape(system.num_outputs, system.num_inputs),
                        sample_time=system.sample_time if discrete else None,
                        input_frame=system.input_frame, state_frame=system.state_frame,
                        output_frame=system.output_frame)


class LQRStatus(StatusCode):
    """How an `lqr` solve ended (`LQRResult.status`). A call outside `jit` raises instead of
    returning a failure; inside `jit` (or `grad`, `vmap`) the status reports it."""

    SUCCESS = 0
    NO_STABILISING_SOLUTION = 1


LQRStatus.describe({
    LQRStatus.SUCCESS: "solved: S is the stabilising solution of the Riccati equation",
    LQRStatus.NO_STABILISING_SOLUTION: "the Riccati equation has no stabilising solution (S is not finite or not "
                                       "positive semidefinite): an unstable mode is not controllable through B, "
                                       "or Q does not see a mode on the stability boundary; check the operating "
                                       "point and the inputs, or penalise every state in Q (Q > 0)"})


class LQRResult(eqx.Module, Reported):
    r"""`K` (gain), `S` (cost-to-go $\tilde x^T S \tilde x$), the `linearization` about the
    operating point (`x0`, `u0`), the `controller` system $u = u_0 - K(x - x_0)$ (input: the
    plant's state; output: its input) and the `status` (an `LQRStatus` code; `success` and
    `message` from it). The controller is, for a `LinearSystem` about the origin, a
    `LinearSystem` $u = -Kx$ (Drake's rule), so that its closed loops stay linear; otherwise a
    static `System.from_functions` system keeping (K, x0, u0) as its `functions.params` (where
    Drake returns an `AffineSystem` with $D = -K$, $y_0 = u_0 + K x_0$)."""

    K: jax.Array
    S: jax.Array
    linearization: LinearSystem
    controller: System
    x0: jax.Array
    u0: jax.Array
    status: jax.Array
    status_type = LQRStatus


def _affine_gain(t, x, y, params):
    K, x0, u0 = params
    return u0 - K @ (y - x0)


@functools.partial(jax.jit, static_argnums=5)
def _lqr_gain(A, B, Q, R, N, discrete: bool):
    """(K, S, status) from the Riccati equation of (A, B, Q, R, N); the status says whether S
    is finite and positive semidefinite (the stabilising solution is the one that is, for Q >= 0
    with (A, Q) detectable)."""
    if discrete:
        S = solve_discrete_are(A, B, Q, R, N)
        cross = B.T @ S @ A + (0.0 if N is None else N.T)
        K = jnp.linalg.solve(R + B.T @ S @ B, cross)
    else:
        S = solve_continuous_are(A, B, Q, R, N)
        K = jnp.linalg.solve(R, B.T @ S + (0.0 if N is None else N.T))
    finite = jnp.all(jnp.isfinite(S)) & jnp.all(jnp.isfinite(K))
    scale = jnp.max(jnp.abs(jnp.where(finite, S, 0.0)), initial=1.0)
    semidefinite = jnp.linalg.eigvalsh(jnp.where(finite, (S + S.T) / 2, 0.0))[0] >= -1e-8 * scale
    return K, S, jnp.where(finite & semidefinite, LQRStatus.SUCCESS, LQRStatus.NO_STABILISING_SOLUTION)


def _require_stabilising(system, lin, K, status):
    """A ValueError unless the status is SUCCESS and A - B K is stable (the Riccati equation
    has a stabilising solution only for stabilisable (A, B) and (A, Q) without unobservable
    modes on the stability boundary)."""
    poles = np.linalg.eigvals(np.asarray(lin.A) - np.asarray(lin.B) @ np.asarray(K)) if np.all(np.isfinite(K)) else None
    if lin.is_discrete:
        boundary, stable = "unit circle", poles is not None and np.all(np.abs(poles) < 1)
    else:
        boundary, stable = "imaginary axis", poles is not None and np.all(poles.real < 0)
    if not (stable and int(status) == LQRStatus.SUCCESS):
        raise ValueError(
            f"lqr: the Riccati equation of {system.name} has no stabilising solution "
            f"(closed-loop poles {poles}): an unstable mode is not controllable through B, or Q "
            f"does not see a mode on the {boundary}. Check the operating point and the "
            "inputs, or penalise every state in Q (Q > 0).")


def operating_point(caller: str, system: System, x0, u0):
    """(x0, u0) as vectors of `system`'s n states and m inputs (any shape of n and m entries,
    e.g. a column); another size is a ValueError naming the argument and the sizes."""
    for label, value, size in (("x0", x0, system.num_states), ("u0", u0, system.num_inputs)):
        if np.size(value) != size:
            what = ("state" if label == "x0" else "input") + ("" if size == 1 else "s")
            raise ValueError(f"{caller}: {label} must hold {system.name}'s {size} {what}, got shape {np.shape(value)}"
                             + (" (the weights come first: lqr(system, Q, R, x0, u0))" if caller == "lqr" else ""))
    return x0.reshape(system.num_states), u0.reshape(system.num_inputs)


def check_weight_shapes(caller: str, system: System, Q, R):
    """Q must be (n, n) and R (m, m) for `system`'s n states and m inputs."""
    for label, M, size in (("Q", Q, system.num_states), ("R", R, system.num_inputs)):
        if M.shape != (size, size):
            raise ValueError(f"{caller}: {label} must be ({size}, {size}) for {system.name}, got {M.shape}")


def check_cost_weights(caller: str, Q, R, N=None, Qf=None):
    """Refuse weights that make the quadratic cost $x^T Q x + 2 x^T N u + u^T R u$ unbounded
    below or the gain undefined: R positive definite, [[Q, N], [N^T, R]] (and Qf) positive
    semidefinite, all symmetric (traced weights are not checked)."""
    if any(isinstance(M, jax.core.Tracer) for M in (Q, R, N, Qf)):
        return
    Q, R = np.asarray(Q, float), np.asarray(R, float)
    N = np.zeros((Q.shape[0], R.shape[0])) if N is None else np.asarray(N, float)
    for label, M in (("Q", Q), ("R", R)) + ((("Qf", np.asarray(Qf, float)),) if Qf is not None else ()):
        if not np.all(np.isfinite(M)):
            raise ValueError(f"{caller}: {label} has non-finite entries")
        if not np.allclose(M, M.T, rtol=1e-10, atol=1e-12 * max(1.0, np.abs(M).max())):
            raise ValueError(f"{caller}: {label} must be symmetric (use (M + M.T) / 2)")
    least_R = np.linalg.eigvalsh(R).min()
    if least_R <= 0:
        raise ValueError(f"{caller}: R must be positive definite (its least eigenvalue is {least_R:.3g})")
    semidefinite = [("[[Q, N], [N^T, R]]" if N.any() else "Q", np.block([[Q, N], [N.T, R]]))]
    if Qf is not None:
        semidefinite.append(("Qf", np.asarray(Qf, float)))
    for label, M in semidefinite:
        least = np.linalg.eigvalsh(M).min()
        if least < -1e-10 * max(1.0, np.abs(M).max()):
            raise ValueError(f"{caller}: {label} must be positive semidefinite (its least eigenvalue is "
                             f"{least:.3g}): the cost would be unbounded below")


def lqr(system: System, Q, R, x0=None, u0=None, *, N=None, check_equilibrium: bool = True) -> LQRResult:
    """The infinite-horizon LQR of `system` about (x0, u0) (default: the origin, u = 0):
    continuous or discrete to match the system; `N` the cross term. Differentiable with
    respect to Q, R and the plant's parameters. Outside `jit` a Riccati equation without a
    stabilising solution is a ValueError; inside, the result's `status` says so."""
    n, m = system.num_states, system.num_inputs
    about_origin = x0 is None and u0 is None
    x0, u0 = operating_point("lqr", system, jnp.zeros(n) if x0 is None else jnp.asarray(x0, float),
                             jnp.zeros(m) if u0 is None else jnp.asarray(u0, float))
    Q, R = (array_module(M).atleast_2d(M).astype(float) for M in (Q, R))  # numbers stay numpy: nothing compiled
    check_weight_shapes("lqr", system, Q, R)
    if N is not None:
        N = jnp.asarray(N, float).reshape(n, m)
    check_cost_weights("lqr", Q, R, N)
    lin = linearize(system, x0, u0, check_equilibrium=check_equilibrium)
    K, S, status = _lqr_gain(lin.A, lin.B, Q, R, N, lin.is_discrete)
    if not isinstance(K, jax.core.Tracer):
        _require_stabilising(system, lin, K, status)
    if isinstance(system, LinearSystem) and about_origin:  # Drake's rule: u = -K x, a LinearSystem
        controller = LinearSystem(jnp.zeros((0, 0)), jnp.zeros((0, n)), jnp.zeros((m, 0)), -K,
                                  input_frame=system.state_frame, output_frame=system.input_frame)
    else:
        controller = System.from_functions(
            output=_affine_gain, num_states=0, num_inputs=n, num_outputs=m, params=(K, x0, u0),
            input_frame=system.state_frame, output_frame=system.input_frame)
    return LQRResult(K=K, S=S, linearization=lin, controller=controller, x0=x0, u0=u0, status=status)

