"""`jd.run_batch` on four CPU devices (a fresh process: the device count is fixed when JAX
starts): chunked and sharded results equal one unsharded vmap, outputs left on the devices
are sharded across all four, and a batch of eleven gathered chunks keeps none on the devices;
value iteration with its mesh split across the four devices equals one device's, bit for bit (slow)."""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import jaxdrake as jd

SCRIPT = textwrap.dedent("""
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    import jaxdrake as jd

    assert len(jax.devices()) == 4, jax.devices()
    pendulum = jd.models.Pendulum()

    def final_state(x0):
        return jd.simulate(pendulum, (0.0, 2.0), x0, dense=False, throw=False).final_state

    x0 = jax.random.uniform(jax.random.key(0), (1000, 2), minval=-3.0, maxval=3.0)
    reference = np.asarray(jax.jit(jax.vmap(final_state))(x0))
    chunked = jd.run_batch(final_state, x0, chunk_size=96)           # 11 chunks, the last padded
    ulp = np.spacing(np.abs(reference))
    assert chunked.shape == (1000, 2) and np.all(np.abs(chunked - reference) <= ulp), np.max(np.abs(chunked - reference) / ulp)
    on_devices = jd.run_batch(final_state, x0, chunk_size=200, gather=False)
    assert len(on_devices.sharding.device_set) == 4 and on_devices.shape == (1000, 2)
    assert np.all(np.abs(np.asarray(on_devices) - reference) <= ulp)
    # eleven chunks of 96 again (the same programs), gathered: the results live on the host,
    # nothing accumulates on the devices
    def live_bytes():
        return sum(a.nbytes for a in jax.live_arrays())
    before = live_bytes()
    result = jd.run_batch(final_state, x0, chunk_size=96, progress=True)
    assert isinstance(result, np.ndarray) and live_bytes() - before <= 96 * 2 * 8, live_bytes() - before
    print("OK", np.max(np.abs(chunked - reference)))
""")
VALUE_ITERATION_SCRIPT = textwrap.dedent("""
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    import jaxdrake as jd
    from jaxdrake.planning import fitted_value_iteration

    assert len(jax.devices()) == 4, jax.devices()
    pendulum = jd.models.Pendulum()
    # value iteration with its 2601 mesh points split across the four devices: equal to one device
    grids = [np.linspace(0, 2 * np.pi, 51), np.linspace(-8, 8, 51)]
    problem = (pendulum, lambda x, u: (x[0] - np.pi) ** 2 + x[1] ** 2 + u[0] ** 2, grids, [np.linspace(-3, 3, 9)], 0.05)
    one = fitted_value_iteration(*problem, periodic=[(0, 0.0, 2 * np.pi)], tol=1e-6, devices=jax.devices()[:1])
    four = fitted_value_iteration(*problem, periodic=[(0, 0.0, 2 * np.pi)], tol=1e-6)
    assert int(one.iterations) == int(four.iterations) > 100
    assert np.array_equal(one.J, four.J) and np.array_equal(one.policy_table, four.policy_table)
    print("OK")
""")


def _on_four_cpu_devices(script):
    """The script's process on four CPU devices: (exit status, stdout, the end of stderr)."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600)
    return done.returncode, done.stdout, done.stderr[-3000:]


def test_run_batch_on_four_cpu_devices_equals_one_vmap():
    status, out, err = _on_four_cpu_devices(SCRIPT)
    assert status == 0 and "OK" in out, err   # the script's own asserts passed


@pytest.mark.slow  # ~10 s alone; value iteration on one device runs by default (tests/test_planning.py)
def test_value_iteration_on_four_cpu_devices_equals_one_device():
    status, out, err = _on_four_cpu_devices(VALUE_ITERATION_SCRIPT)
    assert status == 0 and "OK" in out, err


def test_run_batch_errors_name_the_problem():
    with pytest.raises(ValueError, match="same leading batch axis"):
        jd.run_batch(lambda a, b: a, (np.zeros(3), np.zeros(4)))
    with pytest.raises(ValueError, match="chunk_size must be a positive int"):
        jd.run_batch(lambda a: a, np.zeros(3), chunk_size=0)
    np.testing.assert_array_equal(jd.run_batch(lambda a: 2 * a, np.arange(5.0), chunk_size=2), 2 * np.arange(5.0))


def test_run_batch_traces_under_the_callers_x64_context():
    # the devices' queues run in threads of their own; JAX's contexts are thread-local
    import jax

    assert jd.run_batch(lambda a: 2 * a, np.arange(5.0)).dtype == np.float64   # the suite enables x64
    with jax.enable_x64(False):
        assert jd.run_batch(lambda a: 2 * a, np.arange(5.0)).dtype == np.float32
