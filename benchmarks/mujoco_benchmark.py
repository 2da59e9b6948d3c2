"""MuJoCo models through jaxdrake against MJX's own loop: steps per second of `simulate` on a
`MujocoSystem` (vmapped over initial states) against a `lax.scan` over `mjx.step` (vmapped
over the same states), same model, batch and number of steps, in one process.

Models: the cart-pole of tests/data (no contact) and MJX's test humanoid (contacts, one solver
iteration: MuJoCo Playground's setting). Zero controls; initial states perturbed per member.
Where MuJoCo Warp is installed (`pip install 'jaxdrake[mujoco-warp]'`), a third row steps the
same system with `impl="warp"`.

    python benchmarks/mujoco_benchmark.py [--batch 1024] [--steps 200] [--models cartpole humanoid]
"""

from __future__ import annotations

import importlib.util
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxdrake as jd
from _common import argument_parser, failures, final_state_or_nan, machine_line  # benchmarks/_common.py

ROOT = pathlib.Path(__file__).resolve().parents[1]


def model_path(name):
    if name == "cartpole":
        return ROOT / "tests/data/mj_cartpole.xml"
    mjx_dir = pathlib.Path(importlib.util.find_spec("mujoco.mjx").submodule_search_locations[0])
    return mjx_dir / "test_data/humanoid/humanoid.xml"


def timed(fn, *args):
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return first, time.perf_counter() - start


def main():
    parser = argument_parser(__doc__, repeats=1, gpu_help="unused: JAX's default device is used", batch=1024)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--models", nargs="*", default=["cartpole", "humanoid"])
    args = parser.parse_args()
    from mujoco import mjx

    print(machine_line())
    print(f"{'model':10s} {'contender':28s} {'first call':>11s} {'second':>9s} {'steps/s':>12s} {'vs MJX':>8s}")
    for name in args.models:
        system = jd.MujocoSystem.from_xml(model_path(name), warm_start=True)  # MJX's own loop warm-starts
        dt = system.sample_time
        x0 = jnp.asarray(system.initial_state())
        noise = 0.01 * jax.random.normal(jax.random.key(0), (args.batch, system.num_states), x0.dtype)
        noise = noise.at[:, system.sizes[0] + system.sizes[1]:].set(0.0)  # no initial warm start
        starts = x0 + noise.at[:, :7].set(0.0) if name == "humanoid" else x0 + noise  # keep the root pose valid
        model, nq, nv = system.model, *system.sizes[:2]

        def mjx_rollout(x):
            data = mjx.make_data(model).replace(qpos=x[:nq], qvel=x[nq: nq + nv], qacc_warmstart=x[nq + nv:])
            data = jax.lax.scan(lambda d, _: (mjx.step(model, d), None), data, None, length=args.steps)[0]
            return jnp.concatenate([data.qpos, data.qvel, data.qacc_warmstart])

        def ours(x):
            return final_state_or_nan(jd.simulate(system, (0.0, args.steps * dt), x, dense=False, throw=False))

        rows = {"MJX lax.scan(mjx.step)": jax.jit(jax.vmap(mjx_rollout)),
                "jaxdrake simulate": jax.jit(jax.vmap(ours))}
        if importlib.util.find_spec("mujoco_warp") is not None:   # MuJoCo Warp installed: its row too
            sizes = {"naconmax": 64 * args.batch, "njmax": 256} if name == "humanoid" else None
            on_warp = jd.MujocoSystem.from_xml(model_path(name), warm_start=True, impl="warp", warp_sizes=sizes)

            def ours_on_warp(x):
                return final_state_or_nan(jd.simulate(on_warp, (0.0, args.steps * dt), x, dense=False, throw=False))
            rows["jaxdrake simulate, impl=warp"] = jax.jit(jax.vmap(ours_on_warp))
        reference = None
        for label, fn in rows.items():
            first, second = timed(fn, starts)
            failed = failures(fn(starts))
            if failed:
                print(f"{name:10s} {label:28s} {failed} of {args.batch} runs failed (non-finite): not timed")
                continue
            rate = args.batch * args.steps / second
            reference = reference or rate
            print(f"{name:10s} {label:28s} {first:10.2f}s {second:8.3f}s {rate:12.0f} {rate / reference:7.2f}x",
                  flush=True)
        a, *others = (np.asarray(fn(starts)) for fn in rows.values())
        print(f"{'':10s} max |difference| from MJX's loop: " + ", ".join(f"{np.max(np.abs(a - b)):.1e}" for b in others))


if __name__ == "__main__":
    main()
