"""Rigid-body algorithms: jaxdrake (JAX, jit + vmap) against Pinocchio (C++ through Python) and
MuJoCo MJX, on the same URDFs from example-robot-data.

Robots: the Panda arm with its fingers welded (7 dof) and Solo-12 (floating base, 18 dof).
Quantities: the mass matrix H (CRBA), the bias C v + G (RNEA with zero acceleration) and
forward dynamics (ABA), at random states, float64. jaxdrake: one jitted call, and vmapped
batches; Pinocchio: one call, and a Python loop over the batch; MJX (the arm only: MuJoCo's
URDF import gives no floating base): `mjx.forward` vmapped (it computes qacc, i.e. forward
dynamics including the URDF's joint damping, plus the rest of the pipeline). Reported as
evaluations per second; JAX programs are compiled first and timed separately.

    python benchmarks/multibody_benchmark.py [--batches 1000 100000]
    EXAMPLE_ROBOT_DATA=<copy of robots/> PYTHONPATH=. python3 benchmarks/multibody_benchmark.py \
        --gpu --batches 100000 1000000
"""

from __future__ import annotations

import importlib.metadata
import os
import pathlib
import re
import tempfile
import time

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from _common import argument_parser, best_time, machine_line  # benchmarks/_common.py
from jaxdrake import multibody as mb



def robot_path(relative):
    """A URDF of example-robot-data; `$EXAMPLE_ROBOT_DATA` may point at a copy of its robots/."""
    root = os.environ.get("EXAMPLE_ROBOT_DATA") or importlib.metadata.distribution(
        "example-robot-data").locate_file("cmeel.prefix/share/example-robot-data/robots")
    return pathlib.Path(root) / relative


def panda7(tmp):
    """panda.urdf with the finger joints welded: the 7-dof arm."""
    text = robot_path("panda_description/urdf/panda.urdf").read_text()
    text = re.sub(r'(<joint name="panda_finger_joint\d" type=)"prismatic"', r'\1"fixed"', text)
    path = pathlib.Path(tmp) / "panda7.urdf"
    path.write_text(text)
    return path


def random_inputs(tree, n, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.uniform(-1, 1, (n, tree.nq))
    for s, kind in zip(tree.q_starts, tree.joint_types):
        if kind == "floating":
            quat = rng.normal(size=(n, 4))
            q[:, s + 3: s + 7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    return q, rng.uniform(-1, 1, (n, tree.nv)), rng.uniform(-1, 1, (n, tree.nv))


def jax_rates(tree, batches, repeats):
    fns = {"H (CRBA)": lambda q, v, t: mb.mass_matrix(tree, q),
           "C v + G": lambda q, v, t: mb.bias_forces(tree, q, v),
           "ABA": lambda q, v, t: mb.aba(tree, q, v, t)}
    out = {}
    for name, fn in fns.items():
        q, v, t = map(jnp.asarray, random_inputs(tree, max(batches)))
        one = jax.jit(fn)
        start = time.perf_counter()
        jax.block_until_ready(one(q[0], v[0], t[0]))
        compile_s = time.perf_counter() - start
        single = best_time(lambda: jax.block_until_ready(one(q[0], v[0], t[0])), 50)
        rows = {"single": (single, 1 / single, compile_s)}
        for n in batches:
            many = jax.jit(jax.vmap(fn))
            args = (q[:n], v[:n], t[:n])
            start = time.perf_counter()
            jax.block_until_ready(many(*args))
            first = time.perf_counter() - start
            seconds = best_time(lambda: jax.block_until_ready(many(*args)), repeats)
            rows[f"vmap {n}"] = (seconds, n / seconds, first)
        out[name] = rows
    return out


ARITHMETIC = {"add", "sub", "mul", "div", "neg", "sin", "cos", "sqrt", "rsqrt", "max", "min", "abs", "exp", "log"}


def arithmetic_count(jaxpr) -> int:
    """Arithmetic equations in a jaxpr and the jaxprs inside it."""
    count = 0
    for eqn in jaxpr.eqns:
        count += eqn.primitive.name in ARITHMETIC
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            count += arithmetic_count(sub)
    return count


def fused_against_lanes(tree, batches, repeats, float32):
    """Vmapped CRBA, ABA and C v + G with `mb.fused_kernels` on (the default on a GPU) and off: rates,
    first calls, operations per evaluation of the fused kernel, achieved FLOP/s and bytes/s
    (inputs and outputs once each) against the peak given (H100/H200 SXM: ~67 TFLOP/s float32,
    ~34 float64 without tensor cores, ~3.35 / 4.8 TB/s)."""
    from jaxdrake import _lanes
    from jaxdrake.multibody import _algorithms
    width = 4 if float32 else 8
    fns = {"H (CRBA)": (lambda q, v, t: mb.mass_matrix(tree, q), _algorithms._mass_matrix, 1, {}),
           "ABA": (lambda q, v, t: mb.aba(tree, q, v, t), _algorithms._aba, 3, {"gravity": True}),
           "C v + G": (lambda q, v, t: mb.bias_forces(tree, q, v), _algorithms._rnea, 2, {"gravity": True})}
    for name, (fn, algorithm, arity, static) in fns.items():
        dtype = jnp.float32 if float32 else jnp.float64
        examples = [jax.ShapeDtypeStruct((n,), dtype) for n in (tree.nq, tree.nv, tree.nv)[:arity]]

        def evaluation(*xs, algorithm=algorithm, static=static):
            return algorithm(tree, *(x[..., None] for x in xs), unroll=float("inf"), **static)[..., 0]

        try:   # the library's budget: over it, the batches keep the lanes program
            xla = _lanes.lane_map(evaluation, examples, _lanes.Budget("bench", name, _algorithms._FUSED_OPERATIONS, "",
                                                                      fold=True), kernel="xla")
        except NotImplementedError:
            print(f"  {name:8s} not fused: over the kernel's budget of {_algorithms._FUSED_OPERATIONS:,} lane values")
            continue
        ops = arithmetic_count(jax.make_jaxpr(xla)(*[jnp.zeros((128, *e.shape), dtype) for e in examples]).jaxpr)
        out_size = np.prod(jax.eval_shape(evaluation, *examples).shape)
        bytes_per = width * (sum(e.shape[0] for e in examples) + out_size)
        for n in batches:
            q, v, t = (jnp.asarray(a, dtype) for a in random_inputs(tree, n))
            row = {}
            for label, setting in (("fused", n), ("lanes", None)):
                previous = mb.fused_kernels(setting)
                try:
                    program = jax.jit(jax.vmap(fn))
                    start = time.perf_counter()
                    jax.block_until_ready(program(q, v, t))
                    first = time.perf_counter() - start
                    seconds = best_time(lambda: jax.block_until_ready(program(q, v, t)), repeats)
                finally:
                    mb.fused_kernels(previous)
                row[label] = (seconds, first)
            (fs, ff), (ls, lf) = row["fused"], row["lanes"]
            print(f"  {name:8s} {n:>8d}  fused {n / fs / 1e6:8.1f}M/s ({fs * 1e3:7.3f} ms, first call {ff:5.1f} s)"
                  f"  lanes {n / ls / 1e6:7.1f}M/s ({ls * 1e3:7.3f} ms, first call {lf:4.1f} s)  {ls / fs:5.1f}x"
                  f"  | {ops} ops: {ops * n / fs / 1e12:5.2f} TFLOP/s, {bytes_per * n / fs / 1e9:6.1f} GB/s")


def pinocchio_rates(path, tree, n):
    import pinocchio as pin
    model = (pin.buildModelFromUrdf(str(path), pin.JointModelFreeFlyer()) if tree.has_floating_base
             else pin.buildModelFromUrdf(str(path)))
    data = model.createData()
    q, v, t = random_inputs(tree, n)  # the same numbers; only revolute joints here, nq matches
    assert model.nq == tree.nq, "benchmark robots have no continuous joints"
    fns = {"H (CRBA)": lambda k: pin.crba(model, data, q[k]),
           "C v + G": lambda k: pin.nonLinearEffects(model, data, q[k], v[k]),
           "ABA": lambda k: pin.aba(model, data, q[k], v[k], t[k])}
    out = {}
    for name, fn in fns.items():
        single = best_time(lambda: fn(0), 200)
        loop = best_time(lambda: [fn(k) for k in range(n)], 3)
        out[name] = {"single": (single, 1 / single), f"loop {n}": (loop, n / loop)}
    return out


def mjx_rates(path, batches, repeats):
    import mujoco
    from mujoco import mjx
    text = re.sub(r"<(visual|collision)>.*?</\1>", "", pathlib.Path(path).read_text(), flags=re.S)
    with tempfile.TemporaryDirectory() as tmp:
        bare = pathlib.Path(tmp) / "bare.urdf"
        bare.write_text(text)
        model = mujoco.MjModel.from_xml_path(str(bare))
    model.opt.timestep = 1e-3
    mx = mjx.put_model(model)
    rng = np.random.default_rng(0)
    out = {}
    for n in batches:
        qpos = jnp.asarray(rng.uniform(-1, 1, (n, model.nq)))
        qvel = jnp.asarray(rng.uniform(-1, 1, (n, model.nv)))
        ctrl_free = mjx.make_data(mx)
        step = jax.jit(jax.vmap(lambda qp, qv: mjx.forward(mx, ctrl_free.replace(qpos=qp, qvel=qv)).qacc))
        jax.block_until_ready(step(qpos, qvel))
        seconds = best_time(lambda: jax.block_until_ready(step(qpos, qvel)), repeats)
        out[f"vmap {n}"] = (seconds, n / seconds)
    return out


def main(batches, repeats, gpu, float32, robots=("panda", "solo12")):
    jax.config.update("jax_enable_x64", not float32)
    print(machine_line())
    with tempfile.TemporaryDirectory() as tmp:
        chosen = {"panda (7 dof)": panda7(tmp),
                  "solo12 (floating, 18 dof)": robot_path("solo_description/robots/solo12.urdf")}
        for label, path in {k: p for k, p in chosen.items() if k.split()[0] in robots}.items():
            tree, _ = mb.tree_from_urdf(path, floating_base="solo" in label)
            ours = jax_rates(tree, batches, repeats)
            theirs = None if gpu else pinocchio_rates(path, tree, 1000)
            print(f"\n{label}: evaluations per second (time)")
            for name, rows in ours.items():
                base = theirs[name]["loop 1000"][1] if theirs else None
                for kind, (seconds, rate, compile_s) in rows.items():
                    extra = f"   (first call {compile_s:.2f} s)" if compile_s else ""
                    ratio = f"{rate / base:8.1f}x vs pinocchio loop" if base else ""
                    print(f"  {name:9s} jaxdrake {kind:12s} {rate:14,.0f}/s ({seconds * 1e3:9.3f} ms) {ratio}{extra}")
                if theirs:
                    for kind, (seconds, rate) in theirs[name].items():
                        print(f"  {name:9s} pinocchio {kind:11s} {rate:14,.0f}/s ({seconds * 1e3:9.3f} ms)")
            if gpu:
                print(f"\n{label}: fused kernels (mb.fused_kernels) against the lanes program")
                fused_against_lanes(tree, batches, repeats, float32)
            if "panda" in label:
                try:
                    for kind, (seconds, rate) in mjx_rates(path, batches, repeats).items():
                        print(f"  {'qacc':9s} mjx.forward {kind:9s} {rate:14,.0f}/s ({seconds * 1e3:9.3f} ms)")
                except (ImportError, AttributeError) as error:  # no mujoco-mjx, or no EGL for its renderer
                    print(f"  (mjx.forward skipped: {type(error).__name__}: {error})")


if __name__ == "__main__":
    parser = argument_parser(__doc__, repeats=3, gpu_help="JAX rows only (no Pinocchio)")
    parser.add_argument("--batches", type=int, nargs="+", default=[1000, 100000])
    parser.add_argument("--float32", action="store_true", help="JAX in float32 (the GPU default)")
    parser.add_argument("--robots", nargs="+", default=["panda", "solo12"], choices=["panda", "solo12"])
    args = parser.parse_args()
    main(args.batches, args.repeats, args.gpu, args.float32, args.robots)
