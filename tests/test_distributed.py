"""`jd.run_batch` across two processes of one JAX distributed run, as docs/scaling.md tells users
to run it across hosts: two processes on this machine (a coordinator on 127.0.0.1, two CPU devices
each, Gloo's CPU collectives bound to 127.0.0.1), each calling run_batch with the same inputs and
all four devices. The global batch equals one process's own `vmap`; each process holds the shards
of its own devices; gathered, every process has the whole batch; a process killed while the other
waits for it in a gather makes that one raise ConnectionError, within seconds, not hang."""

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time

import pytest

WORKER = textwrap.dedent("""
    import os, sys, time, traceback
    process_id, port, killed = map(int, sys.argv[1:])
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_num_cpu_devices", 2)
    # Gloo listens on the address of this machine's host name unless given one: loopback only.
    from jax._src import distributed, xla_bridge
    from jax._src.lib import _jax
    xla_bridge.register_backend_factory("cpu", lambda: xla_bridge.make_cpu_client(
        _jax.make_gloo_tcp_collectives(distributed.global_state.client, hostname="127.0.0.1")),
        priority=0, fail_quietly=False)
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=2,
                               process_id=process_id, initialization_timeout=60)
    import jaxdrake as jd
    from jaxdrake import _batch


    def final_state(x0):
        return jd.simulate(jd.models.Pendulum(), (0.0, 2.0), x0, dense=False, throw=False).final_state


    def main():
        assert jax.process_count() == 2 and len(jax.devices()) == 4 and len(jax.local_devices()) == 2
        x0 = np.random.default_rng(0).uniform(-3.0, 3.0, (100, 2))  # the same global inputs in both
        reference = np.asarray(jax.jit(jax.vmap(final_state))(x0))  # this process alone, one device
        ulp = np.spacing(np.abs(reference))

        # 5 chunks of 24 over the 4 devices (the last padded), left on the devices
        out = jd.run_batch(final_state, x0, chunk_size=24, devices=jax.devices(), gather=False)
        assert out.shape == (100, 2) and not out.is_fully_addressable
        shards = out.addressable_shards
        assert {shard.device for shard in shards} == set(jax.local_devices())
        assert sorted(shard.index[0].start for shard in shards) == [50 * process_id, 50 * process_id + 25]
        for shard in shards:
            assert np.all(np.abs(np.asarray(shard.data) - reference[shard.index]) <= ulp[shard.index])

        # gathered: the whole batch in each process
        whole = jd.run_batch(final_state, x0, chunk_size=24, devices=jax.devices())
        assert isinstance(whole, np.ndarray) and np.all(np.abs(whole - reference) <= ulp)

        # the default chunk: each process measures its own free memory, both take the least
        member = jax.ShapeDtypeStruct((2,), x0.dtype)
        per_member = _batch.member_bytes(final_state, member)
        _batch.free_memory = lambda device: (40 + 40 * process_id) * per_member
        assert _batch.default_chunk_size(final_state, member, jax.devices()) == 10 * 4
        print("EQUAL", flush=True)

        if process_id == killed:
            sys.stdin.read()  # until the test kills this process
        try:
            jd.run_batch(final_state, x0, chunk_size=24, devices=jax.devices())  # waits for the other
        except ConnectionError as error:
            print("NAMED", time.monotonic(), error, flush=True)


    # Leave with os._exit: the distributed runtime's exit would wait for the other process, or
    # for a dead one's heartbeat timeout (100 s), then abort.
    try:
        main()
    except BaseException:
        traceback.print_exc()
        sys.stdout.flush()
        os._exit(1)
    os._exit(0)
""")


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def wait_for(worker, log, text, deadline):
    while text not in log.read_text():
        assert worker.poll() is None and time.monotonic() < deadline, f"no {text!r}:\n{log.read_text()[-3000:]}"
        time.sleep(0.05)


# process 0 also hosts the coordinator; its death is found by the same gather as process 1's
@pytest.mark.parametrize("killed", [1, pytest.param(0, marks=pytest.mark.slow)])
def test_run_batch_across_two_processes_equals_one_vmap_and_names_a_killed_peer(tmp_path, killed):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    port = str(free_port())
    logs = [tmp_path / f"process{i}.log" for i in (0, 1)]
    outputs = [log.open("w") for log in logs]
    workers = [subprocess.Popen([sys.executable, "-c", WORKER, str(i), port, str(killed)], stdin=subprocess.PIPE,
                                stdout=output, stderr=subprocess.STDOUT, env=env)
               for i, output in enumerate(outputs)]
    try:
        deadline = time.monotonic() + 120
        for worker, log in zip(workers, logs):
            wait_for(worker, log, "EQUAL", deadline)
        time.sleep(0.5)  # the survivor is waiting for the other in the next gather
        survivor = 1 - killed
        kill_time = time.monotonic()
        workers[killed].send_signal(signal.SIGKILL)
        assert workers[survivor].wait(timeout=30) == 0, logs[survivor].read_text()[-3000:]
        named = logs[survivor].read_text()
        assert "NAMED" in named and "died while results were exchanged" in named, named[-3000:]
        seconds = float(named.split("NAMED ")[1].split()[0]) - kill_time
        assert seconds < 10, seconds  # found by the collective itself, not the heartbeat timeout
    finally:
        for worker in workers:
            if worker.poll() is None:
                worker.kill()
                worker.wait()
        for output in outputs:
            output.close()
