"""Reverse mode of `simulate` (`autodiff="reverse"`, `_reverse.py`): forward sensitivities
contracted with the cotangent for few differentiated scalars, the discrete adjoint (or
chunked sensitivities) for many. Each feature's gradient is checked against central
differences, and the adjoint against the forward sensitivities (two independent derivations);
the loop's Python code is traced once for a gradient."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake.simulation import _reverse

TOL = dict(rtol=1e-10, atol=1e-12)


def central_difference(f, p, h=1e-6):
    p = np.asarray(p, float)
    out = []
    for i in range(p.size):
        e = np.zeros_like(p)
        e.flat[i] = h
        out.append((f(jnp.asarray(p + e)) - f(jnp.asarray(p - e))) / (2 * h))
    return np.array(out).reshape(p.shape)


def pendulum_dense(mode):
    """Dense output read by `eval` at fixed times, w.r.t. x0 and the damping."""
    def loss(p):
        traj = jd.simulate(jd.models.Pendulum(b=p[2]), (0.0, 1.5), p[:2], autodiff=mode, **TOL)
        return jnp.sum(traj.eval(jnp.linspace(0.1, 1.5, 9)) ** 2)
    return loss, np.array([1.0, 0.3, 0.2])


def bouncing_ball(mode):
    """Two impacts (located events, saltation), w.r.t. the initial height and speed and the
    coefficient of restitution."""
    def loss(p):
        traj = jd.simulate(jd.models.BouncingBall(cor=p[2]), (0.0, 2.0), p[:2], autodiff=mode, **TOL)
        return traj.final_state[0] + 0.3 * traj.final_state[1]
    return loss, np.array([1.0, 0.5, 0.8])


def saturated_tape(mode):
    """An input tape (its breakpoints stop steps) through input limits (located switches),
    w.r.t. the tape's values."""
    system = jd.System.from_functions(lambda t, x, u: -x + u, num_states=1, num_inputs=1, input_limits=(-1.0, 1.0))

    def loss(values):
        tape = jd.Trajectory.from_samples(jnp.array([0.0, 0.7, 1.4, 2.0]), values[:, None])
        return jd.simulate(system, (0.0, 2.0), jnp.zeros(1), inputs=tape, autodiff=mode, **TOL).final_state[0]
    return loss, np.array([0.5, 2.0, -0.4, 0.3])


def sampled_controller(mode):
    """Discrete updates: a sampled-data loop (period 0.1) around the double integrator,
    w.r.t. the controller's gains."""
    def loss(k):
        plant = jd.LinearSystem(jnp.array([[0.0, 1.0], [0.0, 0.0]]), jnp.array([[0.0], [1.0]]), jnp.eye(2))
        gain = jd.LinearSystem(jnp.zeros((0, 0)), jnp.zeros((0, 2)), jnp.zeros((1, 0)), -k[None, :])
        controller = jd.cascade(gain, jd.ZeroOrderHold(0.1, 1))
        loop = jd.feedback(plant, controller)
        return jnp.sum(jd.simulate(loop, (0.0, 1.0), jnp.array([0.0, 1.0, 0.0]), autodiff=mode,
                                   **TOL).final_state ** 2)
    return loss, np.array([2.0, 1.5])


CASES = [pendulum_dense, bouncing_ball, saturated_tape, sampled_controller]

KNOTS = 80
KNOT_TIMES = jnp.linspace(0.0, 1.0, KNOTS)
FIRST_ORDER = jd.System.from_functions(lambda t, x, u: -x + u, num_states=1, num_inputs=1)


def by_tape(w, mode="reverse"):
    """|x(1)|^2 of a first-order lag driven by an input tape whose knots have the values w."""
    tape = jd.Trajectory.from_samples(KNOT_TIMES, w[:, None])
    return jd.simulate(FIRST_ORDER, (0.0, 1.0), jnp.ones(1), inputs=tape, autodiff=mode, **TOL).final_state[0] ** 2


def by_closure(w, mode="reverse"):
    """The same lag driven by an input function that closes over the weights w."""
    def u(t):
        return jnp.sum(w * jnp.sin(jnp.arange(1, KNOTS + 1) * t))
    return jd.simulate(FIRST_ORDER, (0.0, 1.0), jnp.ones(1), inputs=u, autodiff=mode, **TOL).final_state[0] ** 2


def tape_gradient_equal_to_central_differences(w, mode):
    g = jax.grad(by_tape)(w, mode)
    for i in (0, 17, 79):
        e = jnp.zeros(KNOTS).at[i].set(1e-6)
        np.testing.assert_allclose(g[i], (by_tape(w + e, mode) - by_tape(w - e, mode)) / 2e-6, rtol=1e-6)
    return g


# slow: by default the same features' gradients are checked against central differences in
# test_input_limits, test_hybrid, test_compose and test_transforms, and the two ways of this
# file's other tests against each other
@pytest.mark.slow
@pytest.mark.parametrize("case", CASES, ids=lambda c: c.__name__)
def test_reverse_equals_central_differences(case):
    loss_reverse, p = case("reverse")
    np.testing.assert_allclose(jax.grad(loss_reverse)(jnp.asarray(p)), central_difference(loss_reverse, p),
                               rtol=2e-5, atol=1e-7)


def test_many_differentiated_scalars_take_the_adjoint_or_chunked_tangents(monkeypatch):
    """80 differentiated scalars, over the forward-direction limit: as the knots of an input
    tape (the discrete adjoint, against central differences) and as weights closed over by an
    input function (chunked forward sensitivities through the traced loop, against the
    adjoint asked for by name)."""
    assert KNOTS > _reverse.MAX_FORWARD_DIRECTIONS
    w = jnp.sin(3.0 * KNOT_TIMES) / KNOTS
    np.testing.assert_allclose(jax.grad(lambda w: by_closure(w, "adjoint"))(w), jax.grad(by_closure)(w),
                               rtol=1e-9, atol=1e-14)
    adjoints, run_adjoint = [], _reverse.run_adjoint
    monkeypatch.setattr(_reverse, "run_adjoint", lambda *args: adjoints.append(1) or run_adjoint(*args))
    tape_gradient_equal_to_central_differences(w, "reverse")
    assert adjoints, "80 tape knots should take the discrete adjoint"


def test_the_adjoint_keeping_every_stride_th_state_equals_keeping_them_all(monkeypatch):
    """Where every iteration's state would not fit in `KEPT_BYTES`, the adjoint keeps every
    stride-th (stride ~ sqrt(max_steps)) and the backward pass re-runs each stretch from its
    first state: the same gradient, over two stretches, the last one partial."""
    w = jnp.sin(3.0 * KNOT_TIMES) / KNOTS
    g = jax.grad(by_tape)(w)
    strides = _record_strides(monkeypatch)
    np.testing.assert_allclose(jax.grad(by_tape)(w), g, rtol=1e-12, atol=1e-15)
    assert strides == [64] and int(jd.simulate(FIRST_ORDER, (0.0, 1.0), jnp.ones(1), inputs=jd.Trajectory.from_samples(
        KNOT_TIMES, w[:, None]), **TOL).num_steps) > 64


def _record_strides(monkeypatch):
    """Every iteration's state over `KEPT_BYTES`; the strides the adjoint takes, recorded."""
    strides, kept_stride = [], _reverse.kept_stride
    monkeypatch.setattr(_reverse, "KEPT_BYTES", 0)
    monkeypatch.setattr(_reverse, "kept_stride", lambda *args: strides.append(kept_stride(*args)) or strides[-1])
    jax.clear_caches()   # the programs compiled before are traced again
    return strides


@pytest.mark.slow  # two more adjoint programs
@pytest.mark.parametrize("case", ["bouncing_ball", "stiff_van_der_pol"])
def test_the_adjoint_over_stretches_holds_through_impacts_and_reused_matrices(case, monkeypatch):
    loss, p = globals()[case]("adjoint")
    g = jax.grad(loss)(jnp.asarray(p))
    strides = _record_strides(monkeypatch)
    np.testing.assert_allclose(jax.grad(loss)(jnp.asarray(p)), g, rtol=1e-12, atol=1e-15)
    assert strides == [64]


@pytest.mark.parametrize("mode", ["reverse", "adjoint"])
def test_vmap_of_the_gradient_equals_a_loop_and_the_loop_is_traced_once(mode):
    """Forward sensitivities, and the adjoint (whose backward pass re-runs the traced loop's
    iteration)."""
    traces = []

    class Counted(jd.System):
        b: float

        def __init__(self, b):
            self.b = b
            super().__init__(num_continuous_states=2, time_invariant=True, direct_feedthrough=False)

        def dynamics(self, t, x, u):
            traces.append(1)
            return jnp.array([x[1], -jnp.sin(x[0]) - self.b * x[1]])

    def loss(x0, b):
        return jnp.sum(jd.simulate(Counted(b), (0.0, 1.0), x0, autodiff=mode, **TOL).final_state ** 2)

    gradient = jax.jit(jax.vmap(jax.grad(loss, argnums=(0, 1))))
    x0s, bs = jnp.array([[1.0, 0.0], [0.5, 0.2], [-0.3, 1.0]]), jnp.array([0.1, 0.2, 0.3])
    gx, gb = gradient(x0s, bs)
    # as for `simulate` alone: once for the shape check, once for the loop; the derivative
    # passes work on the traced loop and trace nothing again
    assert len(traces) == 2, f"the vector field was traced {len(traces)} times for one gradient program"
    for i in range(3):
        gxi, gbi = jax.grad(loss, argnums=(0, 1))(x0s[i], bs[i])
        np.testing.assert_allclose(gx[i], gxi, rtol=1e-12)
        np.testing.assert_allclose(gb[i], gbi, rtol=1e-12)


def test_a_traced_gain_inside_a_controller_is_differentiated():
    """A controller built inside the differentiated function closes over the traced gain."""
    plant = jd.models.Pendulum()

    def loss(k):
        controller = jd.System.from_functions(output=lambda t, x, u: -k * u[1:2], num_states=0, num_inputs=2)
        traj = jd.simulate(jd.feedback(plant, controller), (0.0, 1.0), jnp.array([1.0, 0.0]), **TOL)
        return jnp.sum(traj.final_state ** 2)

    g = jax.grad(loss)(0.7)
    np.testing.assert_allclose(g, central_difference(lambda k: loss(k[0]), [0.7])[0], rtol=1e-6)
    assert eqx.is_array(g)


# ----- the discrete adjoint (autodiff="adjoint") ---------------------------------------------


def stiff_van_der_pol(mode, solver="rosenbrock23"):
    """Rosenbrock23 on a stiff Van der Pol (rejected steps whose retries reuse the matrix),
    w.r.t. x0 and mu."""
    def loss(p):
        system = jd.models.VanDerPol(p[2])
        traj = jd.simulate(system, (0.0, 3.0), p[:2], solver=solver, rtol=1e-6, atol=1e-8, autodiff=mode)
        return jnp.sum(traj.final_state ** 2)
    return loss, np.array([2.0, 0.0, 30.0])


def stiff_van_der_pol_third_order(mode):
    """The same with ROS34PW2 (its stages and f(t0 + h, y1) in one loop)."""
    return stiff_van_der_pol(mode, solver="ros34pw2")


# by default the features that change the iteration most (an impact's saltation, a reused
# matrix); the others slow
@pytest.mark.parametrize("case", [pytest.param(c, marks=() if c in (bouncing_ball, stiff_van_der_pol) else pytest.mark.slow)
                                  for c in CASES + [stiff_van_der_pol, stiff_van_der_pol_third_order]],
                         ids=lambda c: c.__name__)
def test_the_adjoint_equals_forward_sensitivities(case):
    """Two independent derivations of the same derivative: the adjoint's backward loop over
    one iteration's VJP, and the loop's tangents (which the slow test above checks against
    central differences and JAX's transpose)."""
    loss_adjoint, p = case("adjoint")
    loss_reverse, _ = case("reverse")
    np.testing.assert_allclose(jax.grad(loss_adjoint)(jnp.asarray(p)), jax.grad(loss_reverse)(jnp.asarray(p)),
                               rtol=1e-9, atol=1e-12)
