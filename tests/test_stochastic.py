"""Stochastic systems (notes D.3.1): band-limited white noise from explicit PRNG keys."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake.models import LinearGaussianExample

N = 10_000
TAU = 0.01


def band_limited_stationary_variance(tau):
    """xdot = -x + w, w held for tau at N(0, 1/tau): x_{k+1} = a x_k + (1 - a) w_k, a = e^-tau,
    so V = (1 - a)^2 / tau / (1 - a^2) = (1 - a) / (tau (1 + a))."""
    a = np.exp(-tau)
    return (1 - a) / (tau * (1 + a))


@pytest.fixture(scope="module")
def final_states():
    """x(5) and x(5.5) of 10^4 paths from x(0) = 0 (the second leg with its own key)."""
    system = LinearGaussianExample(TAU)
    run = lambda key, x0, tspan: jd.simulate(system, tspan, x0, key=key, dense=False).final_state
    keys = jax.random.split(jax.random.key(2026), N)
    x5 = jax.jit(jax.vmap(lambda k: run(k, jnp.zeros(1), (0.0, 5.0))))(keys)
    x55 = jax.jit(jax.vmap(lambda k, x: run(jax.random.fold_in(k, 1), x, (5.0, 5.5))))(keys, x5)
    return np.asarray(x5[:, 0]), np.asarray(x55[:, 0])


def test_sample_variance_matches_the_band_limited_stationary_variance(final_states):
    x5, _ = final_states
    V = band_limited_stationary_variance(TAU) * (1 - np.exp(-2 * 5.0))  # transient: e^-10
    standard_error = V * np.sqrt(2 / (N - 1))
    assert abs(np.var(x5, ddof=1) - V) < 3 * standard_error
    assert abs(np.mean(x5)) < 3 * np.sqrt(V / N)
    # the band-limited variance differs from white noise's 1/2 by O(tau^2): well inside the error
    assert abs(V - 0.5) < 1e-4


def test_autocovariance_is_that_of_white_noise_through_a_first_order_lag(final_states):
    x5, x55 = final_states
    V = band_limited_stationary_variance(TAU)
    cov = np.mean(x5 * x55) - np.mean(x5) * np.mean(x55)
    rho = np.exp(-0.5)
    assert abs(cov - rho * V) < 4 * V * np.sqrt((1 + rho ** 2) / N)


def test_the_same_key_gives_the_same_path_and_different_keys_independent_ones(final_states):
    system = LinearGaussianExample(TAU)
    key = jax.random.key(7)
    a = jd.simulate(system, (0.0, 2.0), jnp.zeros(1), key=key)
    b = jd.simulate(system, (0.0, 2.0), jnp.zeros(1), key=key)
    ts = jnp.linspace(0, 2, 101)
    np.testing.assert_array_equal(a.eval(ts), b.eval(ts))
    c = jd.simulate(system, (0.0, 2.0), jnp.zeros(1), key=jax.random.key(8))
    assert np.max(np.abs(a.eval(ts) - c.eval(ts))) > 0.1
    x5, _ = final_states  # paths of different keys are uncorrelated
    r = np.corrcoef(x5[: N // 2], x5[N // 2:])[0, 1]
    assert abs(r) < 4 / np.sqrt(N / 2)


def test_noise_is_constant_between_its_breakpoints_and_steps_stop_there():
    """With x(0) = 0 and w constant on each piece, the path is exact piecewise exponentials;
    the loop stops at every multiple of tau."""
    system = LinearGaussianExample(0.1)
    traj = jd.simulate(system, (0.0, 1.0), jnp.zeros(1), key=jax.random.key(3), rtol=1e-12, atol=1e-12)
    breakpoints = traj.breakpoints()
    for k in range(1, 10):
        assert np.min(np.abs(breakpoints - 0.1 * k)) < 1e-15
    # within each piece x(t) = w + (x_k - w) e^{-(t - t_k)}: recover w on a piece, check inside it
    t0, t1 = 0.3, 0.4
    xk, xm = float(traj.state(t0)[0]), float(traj.state(0.35)[0])
    w = (xm - xk * np.exp(-0.05)) / (1 - np.exp(-0.05))
    np.testing.assert_allclose(traj.state(t1, side="left")[0], w + (xk - w) * np.exp(-0.1), rtol=1e-9)


def test_discrete_stochastic_system_draws_iid_standard_normal_samples():
    """x[n+1] = a x[n] + w[n], w[n] ~ N(0, 1) i.i.d.: var x[n] = (1 - a^(2n)) / (1 - a^2)."""
    a = 0.9
    ar1 = jd.StochasticSystem.from_functions(update=lambda t, x, u, w: a * x + w, num_states=1,
                                             num_noise_inputs=1, sample_time=0.5)
    assert ar1.is_stochastic and ar1.noise_time_constant == 0.5
    run = jax.jit(jax.vmap(lambda k: jd.simulate(ar1, (0.0, 10.0), jnp.zeros(1), key=k,
                                                 dense=False).final_state[0]))
    x = np.asarray(run(jax.random.split(jax.random.key(0), N)))
    n = 20  # updates at 0, 0.5, ..., 9.5
    V = (1 - a ** (2 * n)) / (1 - a ** 2)
    assert abs(np.var(x, ddof=1) - V) < 3 * V * np.sqrt(2 / (N - 1))


def test_combinations_with_a_stochastic_system_are_stochastic_and_keep_its_noise():
    noisy = LinearGaussianExample(TAU)
    sensor = jd.LinearSystem([[-5.0]], [[5.0]], [[1.0]])
    chain = jd.cascade(noisy, sensor)
    assert type(chain) is jd.Diagram and chain.is_stochastic and chain.noise_groups == noisy.noise_groups
    key = jax.random.key(11)
    got = jd.simulate(chain, (0.0, 1.0), jnp.zeros(2), key=key, rtol=1e-12, atol=1e-12)
    alone = jd.simulate(noisy, (0.0, 1.0), jnp.zeros(1), key=key, rtol=1e-12, atol=1e-12)
    ts = jnp.linspace(0, 1, 51)
    np.testing.assert_allclose(got.state(ts)[:, 0], alone.state(ts)[:, 0], atol=1e-10)
    # the sensor sees the noisy state: its own simulation driven by that path agrees
    filtered = jd.simulate(sensor, (0.0, 1.0), jnp.zeros(1), inputs=alone, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got.final_state[1], filtered.final_state[0], atol=1e-9)


def test_gradient_through_a_stochastic_simulation_with_a_fixed_key():
    def final(rate):
        system = jd.StochasticSystem.from_functions(lambda t, x, u, w, p: -p * x + w, num_states=1,
                                                    num_noise_inputs=1, noise_time_constant=0.05,
                                                    params=rate)
        traj = jd.simulate(system, (0.0, 1.0), jnp.ones(1), key=jax.random.key(5), rtol=1e-10, atol=1e-12)
        return traj.final_state[0]

    g = jax.grad(final)(1.5)
    fd = (final(1.5 + 1e-5) - final(1.5 - 1e-5)) / 2e-5
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_from_functions_infers_the_output_size_as_system_from_functions_does():
    """One rule for every from_functions: the number of outputs is the length of output()'s
    result (here 1 of 2 states), a given num_outputs or output_frame must agree with it. The
    stochastic one once kept 2, and a diagram then blamed the wiring."""
    deterministic = jd.System.from_functions(lambda t, x, u: -x, output=lambda t, x, u: x[1:2], num_states=2)
    noisy = jd.StochasticSystem.from_functions(lambda t, x, u, w: -x + w, output=lambda t, x, u, w: x[1:2] + w,
                                               num_states=2, num_noise_inputs=1, noise_time_constant=0.1)
    assert deterministic.num_outputs == noisy.num_outputs == 1
    assert deterministic.output_frame.dim == noisy.output_frame.dim == 1
    with_params = jd.StochasticSystem.from_functions(
        lambda t, x, u, w, p: -x, output=lambda t, x, u, w, p: p * jnp.concatenate([x, x, w]),
        num_states=2, num_noise_inputs=1, noise_time_constant=0.1, params=2.0)
    assert with_params.num_outputs == 5
    sink = jd.System.from_functions(lambda t, x, u: u - x, num_states=1, num_inputs=1)
    for system in (deterministic, noisy):
        assert jd.cascade(system, sink).num_states == 3
        for given in (dict(num_outputs=2), dict(output_frame=jd.Frame("Y", ("a", "b")))):
            with pytest.raises(ValueError, match="output returns 1 values but .* was given"):
                if system is deterministic:
                    jd.System.from_functions(lambda t, x, u: -x, output=lambda t, x, u: x[1:2], num_states=2, **given)
                else:
                    jd.StochasticSystem.from_functions(
                        lambda t, x, u, w: -x + w, output=lambda t, x, u, w: x[1:2] + w, num_states=2,
                        num_noise_inputs=1, noise_time_constant=0.1, **given)
    named = jd.StochasticSystem.from_functions(lambda t, x, u, w: -x + w, output=lambda t, x, u, w: x[1:2] + w,
                                               num_states=2, num_noise_inputs=1, noise_time_constant=0.1,
                                               output_frame=jd.Frame("Y", ("y",)))
    assert named.output_frame.coordinates == ("y",)


def test_stochastic_errors_are_named():
    system = LinearGaussianExample()
    with pytest.raises(ValueError, match="stochastic.*needs a PRNG key"):
        jd.simulate(system, (0.0, 1.0), jnp.zeros(1))
    with pytest.raises(ValueError, match="deterministic"):
        jd.simulate(jd.models.Pendulum(), (0.0, 1.0), jnp.zeros(2), key=jax.random.key(0))
    with pytest.raises(ValueError, match="noise_time_constant"):
        jd.StochasticSystem.from_functions(lambda t, x, u, w: w, num_states=1, num_noise_inputs=1)
    with pytest.raises(ValueError, match="num_noise_inputs"):
        jd.StochasticSystem.from_functions(lambda t, x, u, w: w, num_states=1, num_noise_inputs=0,
                                           noise_time_constant=0.1)


def test_float32_stochastic_simulation_runs():
    with jax.enable_x64(False):
        traj = jd.simulate(LinearGaussianExample(), (0.0, 1.0), jnp.zeros(1, jnp.float32),
                           key=jax.random.key(0), dense=False)
        assert traj.final_state.dtype == jnp.float32 and bool(traj.success)


class _KeyedOffset(jd.System):
    """x' = -x + c with the constant c = 0.1 n, n ~ N(0, 1) drawn from a typed PRNG key that
    the system holds as a parameter."""

    key: jax.Array

    def __init__(self, key):
        self.key = key
        super().__init__(num_continuous_states=1)

    def dynamics(self, t, x, u):
        return -x + 0.1 * jax.random.normal(self.key, (1,))


def test_a_typed_prng_key_may_be_a_system_parameter():
    """simulate, vmap over keys and grad run on a system holding a typed key (it was refused
    by the NaN-parameter check); x(1) = c + (x0 - c) e^-1 for each key's c."""
    keys = jax.random.split(jax.random.key(3), 4)
    offsets = np.array([0.1 * float(jax.random.normal(k, (1,))[0]) for k in keys])
    finals = jax.vmap(lambda k: jd.simulate(_KeyedOffset(k), (0.0, 1.0), jnp.ones(1), rtol=1e-10,
                                            atol=1e-12).final_state[0])(keys)
    np.testing.assert_allclose(finals, offsets + (1.0 - offsets) * np.exp(-1.0), rtol=1e-8)
    one = jd.simulate(_KeyedOffset(keys[0]), (0.0, 1.0), jnp.ones(1), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(one.final_state[0], finals[0], rtol=1e-12)
    slope = jax.grad(lambda a: jd.simulate(_KeyedOffset(keys[0]), (0.0, 1.0), a * jnp.ones(1), rtol=1e-10,
                                           atol=1e-12).final_state[0])(1.0)
    np.testing.assert_allclose(slope, np.exp(-1.0), rtol=1e-8)
