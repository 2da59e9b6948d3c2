"""Fused rigid-body batches (`mb.fused_kernels`): the algorithms as straight-line code with one
member per lane, against Pinocchio, their own derivatives, and the lanes program.

Off a GPU the same code runs as `lane_map`'s "xla" kernel (the Pallas kernel's arithmetic,
vmapped over blocks of lanes); the Pallas kernel itself is checked on the device (`gpu`)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdrake import _lanes
from jaxdrake import multibody as mb
from jaxdrake.models._rigid import URDF_DIR
from jaxdrake.multibody import _algorithms

try:
    import pinocchio as pin
except ImportError:  # the GPU machine has none; the GPU test needs none
    pin = None


@pytest.fixture
def fused_on_this_backend(monkeypatch):
    """Fused batches of at least 4 members, as the "xla" kernel; counts the kernels built."""
    built = []
    lane_map = _lanes.lane_map

    def counting(fn, examples, budget, kernel="pallas"):
        built.append(budget.subject)
        return lane_map(fn, examples, budget, kernel=kernel)

    monkeypatch.setattr(_algorithms, "_fused_kernel", lambda: "xla")
    monkeypatch.setattr(_lanes, "lane_map", counting)
    monkeypatch.setattr(_algorithms, "_FUSED_PROGRAMS", type(_algorithms._FUSED_PROGRAMS)())
    previous = mb.fused_kernels(4)
    yield built
    mb.fused_kernels(previous)


def _cartpole():
    """The cart-pole's tree, Pinocchio's model and data, and q in Pinocchio's coordinates
    (its continuous pole joint takes cos and sin)."""
    if pin is None:
        pytest.skip("needs pinocchio")
    path = URDF_DIR / "cartpole.urdf"
    tree, _ = mb.tree_from_urdf(path)
    model = pin.buildModelFromUrdf(str(path))
    return tree, model, model.createData(), lambda q: np.array([q[0], np.cos(q[1]), np.sin(q[1])])


def test_fused_batches_equal_pinocchio_and_small_or_traced_trees_keep_the_lanes(fused_on_this_backend):
    """A prismatic and a revolute joint: ABA, RNEA, C v + G, G and H of a fused batch equal
    Pinocchio member by member (an unbatched argument broadcast); a batch under the threshold,
    and a tree passed into `jit` (not a constant), are not fused and agree too."""
    tree, model, data, pin_q = _cartpole()
    rng = np.random.default_rng(3)
    qs, vs, taus = rng.uniform(-2, 2, (3, 9, tree.nv))
    qdd = jax.jit(jax.vmap(lambda q, v, t: mb.aba(tree, q, v, t)))(qs, vs, taus)
    tau = jax.jit(jax.vmap(lambda q, v, a: mb.rnea(tree, q, v, a)))(qs, vs, taus)
    bias = jax.jit(jax.vmap(lambda q: mb.bias_forces(tree, q, vs[0])))(qs)
    gravity = jax.jit(jax.vmap(lambda q: mb.gravity_forces(tree, q)))(qs)
    H = jax.jit(jax.vmap(lambda q: mb.mass_matrix(tree, q)))(qs)
    assert fused_on_this_backend == ["cartpole's aba", "cartpole's rnea", "cartpole's rnea", "cartpole's rnea",
                                     "cartpole's mass_matrix"]
    for k in range(9):
        np.testing.assert_allclose(qdd[k], pin.aba(model, data, pin_q(qs[k]), vs[k], taus[k]), rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(tau[k], pin.rnea(model, data, pin_q(qs[k]), vs[k], taus[k]), rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(bias[k], pin.nonLinearEffects(model, data, pin_q(qs[k]), vs[0]), rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(gravity[k], pin.computeGeneralizedGravity(model, data, pin_q(qs[k])), rtol=1e-10,
                                   atol=1e-10)
        crba = pin.crba(model, data, pin_q(qs[k]))
        np.testing.assert_allclose(H[k], np.triu(crba) + np.triu(crba, 1).T, rtol=1e-10, atol=1e-10)
    small = jax.vmap(lambda q, v, t: mb.aba(tree, q, v, t))(qs[:3], vs[:3], taus[:3])
    as_argument = jax.jit(jax.vmap(mb.aba, in_axes=(None, 0, 0, 0)))(tree, qs, vs, taus)
    assert len(fused_on_this_backend) == 5
    np.testing.assert_allclose(small, qdd[:3], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(as_argument, qdd, rtol=1e-12, atol=1e-12)


def test_derivatives_of_a_fused_batch_are_the_one_lane_programs(fused_on_this_backend):
    """Reverse and forward mode through a fused batch: d qdd / d tau = H^{-1} (Pinocchio's),
    and the gradient of a vmapped loss equals the member-by-member one."""
    tree, model, data, pin_q = _cartpole()
    rng = np.random.default_rng(4)
    qs, vs, taus = rng.uniform(-2, 2, (3, 6, tree.nv))
    jacobians = jax.jit(jax.vmap(jax.jacfwd(lambda q, t: mb.aba(tree, q, vs[0], t), argnums=1)))(qs, taus)
    pin.computeMinverse(model, data, pin_q(qs[4]))
    np.testing.assert_allclose(jacobians[4], np.triu(data.Minv) + np.triu(data.Minv, 1).T, rtol=1e-9, atol=1e-10)

    def loss(v):
        return jnp.sum(jnp.sin(jax.vmap(lambda q, v, t: mb.aba(tree, q, v, t))(qs, v, taus)))

    grad = jax.jit(jax.grad(loss))(vs)
    one = jax.grad(lambda v: jnp.sum(jnp.sin(mb.aba(tree, qs[2], v, taus[2]))))(vs[2])
    np.testing.assert_allclose(grad[2], one, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(jax.jit(loss)(vs), np.sum(np.sin(
        [pin.aba(model, data, pin_q(qs[k]), vs[k], taus[k]) for k in range(6)])), rtol=1e-10)


def test_a_tree_too_long_for_straight_line_code_keeps_the_lanes(fused_on_this_backend, monkeypatch):
    """Beyond the operation budget the batch is not fused, with the same values."""
    tree, model, data, pin_q = _cartpole()
    monkeypatch.setattr(_algorithms, "_FUSED_OPERATIONS", 10)
    qs = np.random.default_rng(5).uniform(-2, 2, (8, tree.nv))
    tau = jax.jit(jax.vmap(lambda q: mb.gravity_forces(tree, q)))(qs)
    assert fused_on_this_backend == ["cartpole's rnea"]  # tried, refused
    np.testing.assert_allclose(tau[7], pin.computeGeneralizedGravity(model, data, pin_q(qs[7])), rtol=1e-10, atol=1e-10)


def test_fused_kernels_refuses_a_bad_threshold():
    with pytest.raises(ValueError, match="min_batch must be a positive int or None"):
        mb.fused_kernels(0)


@pytest.mark.gpu
def test_the_pallas_kernel_equals_the_lanes_program_on_a_gpu():
    """The 7-dof arm with its fingers (a branch) at 2 * 10^4 members: float32 to float32's
    rounding of the float64 lanes program (no worse than the float32 lanes program), float64
    to 1e-12."""
    import importlib.metadata
    import os
    import pathlib
    root = os.environ.get("EXAMPLE_ROBOT_DATA") or importlib.metadata.distribution("example-robot-data").locate_file(
        "cmeel.prefix/share/example-robot-data/robots")   # $EXAMPLE_ROBOT_DATA: a copy of its robots/
    tree, _ = mb.tree_from_urdf(pathlib.Path(root) / "panda_description/urdf/panda.urdf")
    rng = np.random.default_rng(6)
    args = [jnp.asarray(a) for a in rng.uniform(-1, 1, (3, 20000, tree.nv))]
    lanes = jax.jit(jax.vmap(lambda q, v, t: mb.aba(tree, q, v, t)))
    truth = np.asarray(lanes(*args))
    previous = mb.fused_kernels(16384)
    try:
        fused = jax.jit(jax.vmap(lambda q, v, t: mb.aba(tree, q, v, t)))
        np.testing.assert_allclose(fused(*args), truth, rtol=1e-12, atol=1e-12 * np.abs(truth).max())
        scale = np.abs(truth).max(axis=1, keepdims=True) + 1
        f32 = [a.astype(jnp.float32) for a in args]
        error = np.max(np.abs(np.asarray(fused(*f32), np.float64) - truth) / scale)
        mb.fused_kernels(None)
        reference = np.max(np.abs(np.asarray(jax.jit(jax.vmap(lambda q, v, t: mb.aba(tree, q, v, t)))(*f32),
                                             np.float64) - truth) / scale)
    finally:
        mb.fused_kernels(previous)
    assert error <= 2 * reference


def test_lane_code_computes_known_values_as_xla_does_and_folds_only_when_asked():
    """Known values computed while tracing equal XLA's (a float to int conversion saturates and
    maps NaN to 0 there, where NumPy would wrap); without `fold`, a known zero times an infinite
    lane is NaN as in the vmapped function, with `fold` it is dropped (structural zeros only)."""
    def f(x):
        known = jnp.array([jnp.nan, 3e9, -1.5, 2.7], jnp.float32).astype(jnp.int32).astype(jnp.float32)
        return x * known + jnp.float32(0.0) * x

    x = jnp.asarray([[1.0, -2.0, jnp.inf, 0.5]], jnp.float32)
    examples = [jax.ShapeDtypeStruct((4,), jnp.float32)]
    exact = _lanes.lane_map(f, examples, _lanes.Budget("test", "f", 1000, "-"), kernel="xla")(x)
    np.testing.assert_array_equal(exact, jax.vmap(f)(x))   # NaN where inf * 0
    folded = _lanes.lane_map(f, examples, _lanes.Budget("test", "f", 1000, "-", fold=True), kernel="xla")(x)
    np.testing.assert_array_equal(folded, x * jnp.array([0.0, 2**31 - 1, -1.0, 2.0], jnp.float32))


def test_lane_code_unrolls_scans_with_constants_carries_and_scanned_operands():
    """Scans (a constant, a carry, scanned pairs; one reversed with no scanned operand) unroll
    into lane code equal to the vmapped function (their operand counts are read as each JAX
    version writes them: checked on 0.10 here and 0.11 on the GPU machine)."""
    def f(x, w):
        c, ys = jax.lax.scan(lambda c, xs: (c * xs[0] + jnp.sin(xs[1]) * w[0], c + xs[1]), x[0], (x, w))
        c2, _ = jax.lax.scan(lambda c, _: (c * 0.5 + w[1], None), c, None, length=3, reverse=True)
        return jnp.concatenate([ys, jnp.stack([c, c2])])

    examples = [jax.ShapeDtypeStruct((4,), jnp.float64)] * 2
    program = _lanes.lane_map(f, examples, _lanes.Budget("test", "f", 10**4, "-"), kernel="xla")
    x, w = np.random.default_rng(7).normal(size=(2, 300, 4))
    np.testing.assert_allclose(program(x, w), jax.vmap(f)(x, w), rtol=1e-14, atol=1e-14)
