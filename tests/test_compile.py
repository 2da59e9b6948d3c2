"""The compiled program grows with structure, not repetition: every solver traces a user's
vector field no more often than Euler does (its stages run in a loop), in forward and reverse
mode, with events, input limits and discrete updates; and the shared one-step rule."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd


class Counter:
    def __init__(self):
        self.traces = 0


def counted_oscillator(counter, **kwargs):
    """x'' = -x + u, counting the traces of its vector field."""
    def dynamics(t, x, u):
        counter.traces += 1  # runs at trace time only
        return jnp.stack([x[1], -x[0] + u[0]])

    return jd.System.from_functions(dynamics=dynamics, num_states=2, num_inputs=1, direct_feedthrough=False,
                                    **kwargs)


def counted_ball(counter):
    """A bouncing ball whose flight dynamics count their traces."""
    def flight(t, x, u):
        counter.traces += 1
        return jnp.stack([x[1], -9.81 * jnp.ones_like(x[1])])

    plant = jd.System.from_functions(dynamics=flight, num_states=2)
    bounce = jd.Transition(0, lambda s, t, x, u: jnp.where(x[1] < 0, x[0], 1.0),
                           lambda s, t, x, u: jnp.stack([x[0], -0.8 * x[1]]), 0)
    return jd.HybridSystem([plant], [bounce])


def counted_mixed(counter):
    """A continuous oscillator plus a discrete sampler of its position (period 0.1)."""
    def dynamics(t, x, u):
        counter.traces += 1
        return jnp.stack([x[2], -x[1]])

    return jd.System.from_functions(dynamics=dynamics, update=lambda t, x, u: x[1:2], num_states=3,
                                    num_discrete_states=1, sample_time=0.1)


def traces(make, solver, mode, **simulate_kwargs):
    counter = Counter()
    system = make(counter)
    x0 = jnp.asarray(np.asarray(system.initial_state()) + 1.0)
    dt = None if solver == "dopri5" else 1e-2

    def final(x0):
        return jd.simulate(system, (0.0, 1.0), x0, solver=solver, dt=dt, autodiff=mode,
                           **simulate_kwargs).final_state

    if mode == "reverse":
        jax.jit(jax.grad(lambda x0: jnp.sum(final(x0))))(x0)
    else:
        jax.jit(jax.jacfwd(final))(x0)
    return counter.traces


SYSTEMS = {
    "plain": lambda c: counted_oscillator(c),
    "input limits": lambda c: counted_oscillator(c, input_limits=(-0.5, 0.5)),
    "hybrid events": counted_ball,
    "discrete updates": counted_mixed,
}


@pytest.mark.parametrize("mode", ["reverse", "forward"])
@pytest.mark.parametrize("kind", [pytest.param(k, marks=pytest.mark.slow) if k in ("hybrid events", "input limits") else k
                                  for k in SYSTEMS])  # those two: 30-40 s each; "plain" and "discrete" run by default
def test_dopri5_traces_the_vector_field_no_more_than_euler(kind, mode):
    inputs = (lambda t: jnp.sin(3 * t)[None]) if kind == "input limits" else None
    kwargs = {"inputs": inputs} if inputs is not None else {}
    euler = traces(SYSTEMS[kind], "euler", mode, **kwargs)
    dopri5 = traces(SYSTEMS[kind], "dopri5", mode, **kwargs)
    rk4 = traces(SYSTEMS[kind], "rk4", mode, **kwargs)
    assert 0 < dopri5 <= euler and rk4 <= euler, (euler, rk4, dopri5)


def test_a_new_parameter_value_retraces_nothing():
    counter = Counter()
    system = counted_oscillator(counter)
    jd.simulate(system, (0.0, 1.0), jnp.array([1.0, 0.0]))
    first = counter.traces
    jd.simulate(system, (0.0, 2.0), jnp.array([0.5, 0.1]))
    assert counter.traces == first


def test_a_constant_input_is_an_argument_a_new_value_retraces_nothing():
    """`inputs=u` (an array, as Drake's FixValue): the forced oscillator x'' = -x + u from
    rest ends at u (1 - cos t), equal to the same input given as a function, and its
    derivative in u is 1 - cos t; a new u (a list, a NumPy or a JAX array, a number) reuses
    the program, where a new function would not."""
    counter = Counter()
    system = counted_oscillator(counter)
    final = lambda u: jd.simulate(system, (0.0, 2.0), jnp.zeros(2), inputs=u, rtol=1e-10, atol=1e-12).final_state  # noqa: E731
    np.testing.assert_allclose(final(jnp.array([0.7]))[0], 0.7 * (1 - np.cos(2.0)), rtol=1e-8)
    first = counter.traces
    for u in ([0.3], np.array([-1.2]), 2.5):
        np.testing.assert_allclose(final(u)[0], float(np.ravel(u)[0]) * (1 - np.cos(2.0)), rtol=1e-8)
    assert counter.traces == first
    np.testing.assert_array_equal(final(np.array([0.4])), final(lambda t: jnp.array([0.4])))
    np.testing.assert_allclose(jax.grad(lambda u: final(u)[0])(jnp.array([0.7])), [1 - np.cos(2.0)], rtol=1e-7)
    with pytest.raises(ValueError, match=r"inputs has shape \(3,\), but .*needs shape \(1,\)"):
        final(np.zeros(3))


def test_discrete_step_is_the_rule_and_the_update():
    a, h = -0.7, 0.3
    linear = jd.LinearSystem([[a]], [[1.0]], [[1.0]], [[0.0]])
    x = jnp.array([2.0])
    z = a * h
    taylor4 = 1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24  # RK4 on x' = a x, exactly
    np.testing.assert_allclose(jd.simulation.discrete_step(linear, 0.0, x, jnp.zeros(1), h, "rk4"), 2 * taylor4,
                               rtol=1e-14)
    np.testing.assert_allclose(jd.simulation.discrete_step(linear, 0.0, x, jnp.zeros(1), h, "euler"), 2 * (1 + z),
                               rtol=1e-14)
    zh = z / 3
    np.testing.assert_allclose(jd.simulation.discrete_step(linear, 0.0, x, jnp.zeros(1), h, "midpoint", substeps=3),
                               2 * (1 + zh + zh ** 2 / 2) ** 3, rtol=1e-14)
    sampled = jd.LinearSystem([[0.5]], [[1.0]], [[1.0]], [[0.0]], sample_time=0.1)
    np.testing.assert_allclose(jd.simulation.discrete_step(sampled, 0.0, x, jnp.array([1.0]), 0.1), [2.0])
    with pytest.raises(ValueError, match="fixed-step rule"):
        jd.simulation.discrete_step(linear, 0.0, x, jnp.zeros(1), h, "dopri5")


def test_xla_cpu_setting_respects_the_users_choice(monkeypatch):
    """jaxdrake adds --xla_cpu_use_fusion_emitters=false on jaxlib 0.10 only, and never over a
    choice already in XLA_FLAGS or with JAXDRAKE_KEEP_XLA_FLAGS set."""
    import importlib.metadata

    from jaxdrake._xla import prefer_fast_cpu_compilation

    monkeypatch.delenv("JAXDRAKE_KEEP_XLA_FLAGS", raising=False)
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true")
    assert not prefer_fast_cpu_compilation()
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/x")
    added = prefer_fast_cpu_compilation()
    assert added == importlib.metadata.version("jaxlib").startswith("0.10.")
    import os
    assert os.environ["XLA_FLAGS"] == ("--xla_dump_to=/tmp/x --xla_cpu_use_fusion_emitters=false" if added
                                       else "--xla_dump_to=/tmp/x")
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setenv("JAXDRAKE_KEEP_XLA_FLAGS", "1")
    assert not prefer_fast_cpu_compilation() and os.environ["XLA_FLAGS"] == ""


def test_lqr_linearize_and_tvlqr_called_outside_jit_trace_the_plant_once():
    """Un-jitted design calls keep their compiled programs: a second call (new Q, R, new
    parameter values) traces the plant's dynamics no more."""
    counter = Counter()
    plant = counted_oscillator(counter)
    first = jd.control.lqr(plant, jnp.eye(2), jnp.eye(1))
    after_first = counter.traces
    second = jd.control.lqr(plant, 3 * jnp.eye(2), 2 * jnp.eye(1))
    jd.control.linearize(plant, jnp.array([0.0, 0.0]))
    assert counter.traces == after_first
    assert not np.allclose(first.K, second.K)
    jd.control.finite_horizon_lqr(plant, jnp.eye(2), jnp.eye(1), (0.0, 1.0))
    after_tvlqr = counter.traces
    jd.control.finite_horizon_lqr(plant, 2 * jnp.eye(2), jnp.eye(1), (0.0, 1.0), Qf=jnp.eye(2))
    assert counter.traces == after_tvlqr


def test_rigid_body_queries_outside_jit_run_one_kept_program(monkeypatch):
    """A plant's energy called outside jit, under an eager vmap and then in a Python loop,
    traces the tree algorithms once (the shape of one state): one kept program, not the
    algorithms' operations one by one."""
    from jaxdrake.multibody import _algorithms as alg

    counter = Counter()
    kinetic_energy = alg.kinetic_energy

    def counted(*args):
        counter.traces += 1
        return kinetic_energy(*args)

    monkeypatch.setattr(alg, "kinetic_energy", counted)
    plant = jd.models.Acrobot()
    xs = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (5, 4)))
    batched = jax.vmap(plant.energy)(xs)
    jax.vmap(plant.energy)(xs + 1.0)
    looped = [plant.energy(x) for x in xs] + [plant.energy(np.asarray(xs[0]).tolist())]
    assert counter.traces == 1
    np.testing.assert_allclose(batched, looped[:5], rtol=1e-14)
    assert float(looped[5]) == float(looped[0])


def test_tree_algorithms_outside_jit_run_one_kept_program(monkeypatch):
    """`jd.multibody.mass_matrix` called outside jit at new configurations (a numpy array, a
    list) traces CRBA once, and equals the closed-form H(q) of a double pendulum of uniform rods."""
    from jaxdrake.multibody import _algorithms as alg

    counter = Counter()
    crba = alg._mass_matrix

    def counted(*args, **kwargs):
        counter.traces += 1
        return crba(*args, **kwargs)

    monkeypatch.setattr(alg, "_mass_matrix", counted)
    plant = jd.models.DoublePendulum()  # two uniform rods: m = 1, l = 1, centre at l/2, I = m l^2 / 12
    m, l, lc, inertia = 1.0, 1.0, 0.5, 1.0 / 12
    for q in (np.array([0.3, -0.7]), [1.1, 0.4], np.array([-2.0, 2.5])):
        H = jd.multibody.mass_matrix(plant.tree, q)
        c2 = np.cos(q[1])
        h12 = inertia + m * (lc ** 2 + l * lc * c2)
        expected = [[2 * inertia + m * lc ** 2 + m * (l ** 2 + lc ** 2 + 2 * l * lc * c2), h12],
                    [h12, inertia + m * lc ** 2]]
        np.testing.assert_allclose(H, expected, rtol=1e-12)
    assert counter.traces == 1


CACHED_RUN = """
import sys, jax, jax.numpy as jnp
import jaxdrake as jd
hits = []
jax.monitoring.register_event_listener(lambda event, **kw: hits.append(event) if event.endswith("cache_hits") else None)
print(jd.use_compilation_cache(sys.argv[1]))
final = jd.simulate(jd.models.Pendulum(), (0.0, 1.0), jnp.array([1.0, 0.0]), dense=False).final_state
print(len(hits), float(final[0]))
"""


def test_a_new_process_loads_the_programs_of_the_last_one_from_the_compilation_cache(tmp_path):
    """`use_compilation_cache`: the first process compiles and stores its programs, a second one
    (same program) loads them (JAX's own cache-hit events), with the same result."""
    import subprocess
    import sys

    def run():
        done = subprocess.run([sys.executable, "-c", CACHED_RUN, str(tmp_path / "xla")], capture_output=True,
                              text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
        lines = done.stdout.split("\n")
        return lines[0], int(lines[1].split()[0]), float(lines[1].split()[1])

    directory, hits_first, x_first = run()
    assert directory == str(tmp_path / "xla") and any((tmp_path / "xla").iterdir())
    _, hits_second, x_second = run()
    assert hits_first == 0 and hits_second >= 1 and x_second == x_first


def test_compiled_keeps_one_program_per_call_signature():
    """`jaxdrake._compiled.compiled` (simulate's dispatch): arrays traced, other leaves static
    and returned as they were; new values of the same signature reuse the program."""
    from jaxdrake._compiled import compiled

    traces = []

    @compiled
    def f(x, scale, name):
        traces.append(name)
        return {"y": scale * x, "name": name}

    out = f(jnp.ones(3), 2.0, "a")
    assert out["name"] == "a" and np.allclose(out["y"], 2.0)
    out = f(np.full(3, 4.0), 2.0, "a")  # numpy arrays are arguments too
    assert np.allclose(out["y"], 8.0) and traces == ["a"]
    assert f(jnp.ones(3), 3.0, "a")["y"][0] == 3.0 and len(traces) == 2  # a new static value


def test_python_numbers_are_kept_as_device_arrays_never_as_tracers():
    """`simulate`'s tolerances, time span and a model's float parameters are kept as one device
    array per value from its second use (a repeated call from Python transfers nothing; a sweep
    of new values pays no `device_put`): also when that use is while tracing (a kept tracer
    would break every later call); -0.0, 0.0 and the two widths are kept apart."""
    from jaxdrake._numbers import _SCALARS, scalar_argument

    b = 0.0123456789   # a value no other test uses
    assert isinstance(scalar_argument(b), np.ndarray)   # first use: a numpy scalar
    jax.make_jaxpr(lambda x0: jd.simulate(jd.models.Pendulum(b=b), (0.0, 1.0), x0).final_state)(jnp.array([1.0, 0.0]))
    assert all(not isinstance(v, jax.core.Tracer) for v in _SCALARS.values())
    x = jd.simulate(jd.models.Pendulum(b=b), (0.0, 1.0), jnp.array([1.0, 0.0]), rtol=1e-10, atol=1e-12).final_state
    x_numpy = jd.simulate(jd.models.Pendulum(b=np.asarray(b)), (0.0, 1.0), jnp.array([1.0, 0.0]), rtol=1e-10,
                          atol=1e-12).final_state
    np.testing.assert_array_equal(x, x_numpy)
    assert isinstance(scalar_argument(b), jax.Array) and scalar_argument(b) is scalar_argument(b)
    assert np.signbit(scalar_argument(-0.0)) and not np.signbit(scalar_argument(0.0))
    assert np.signbit(scalar_argument(-0.0)) and not np.signbit(scalar_argument(0.0))   # kept ones too
    with jax.enable_x64(False):
        assert scalar_argument(b).dtype == np.float32
    assert scalar_argument(b).dtype == np.float64
