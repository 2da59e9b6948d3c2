"""`compiled`: `equinox.filter_jit`'s contract (arrays traced, every other leaf static,
any pytree returned) at the cost of a dictionary look-up per call, for the entry points a
notebook calls in a loop (`simulate`: the filter's own bookkeeping cost ~0.8 ms a call, five
times the pendulum's program); `compiled_query` for a function or method of an object (a
plant, a kinematic tree) that users call outside `jit`."""

from __future__ import annotations

import functools
from collections import OrderedDict

import equinox as eqx
import jax

from ._numbers import call_argument

MAX_PROGRAMS = 256  # per function: the least recently used program is dropped beyond


def compiled(fn):
    """`fn(*args)` compiled once per call signature: the pytree structure of `args` and its
    non-array leaves (hashable: ints, strings, functions, ...), which are static; array leaves
    (JAX or numpy) are the compiled program's arguments (retraced by `jax.jit` for new
    shapes and dtypes only)."""
    programs: OrderedDict = OrderedDict()

    @functools.wraps(fn)
    def call(*args):
        leaves, treedef = jax.tree.flatten(args)
        dynamic = [leaf for leaf in leaves if eqx.is_array(leaf)]
        is_dynamic = tuple(eqx.is_array(leaf) for leaf in leaves)
        static = tuple(leaf for leaf in leaves if not eqx.is_array(leaf))
        key = (treedef, is_dynamic, static)
        try:
            entry = programs.pop(key)
        except KeyError:
            entry = _program(fn, treedef, is_dynamic, static)
        programs[key] = entry  # most recently used last
        if len(programs) > MAX_PROGRAMS:
            programs.popitem(last=False)
        program, output = entry
        arrays = iter(program(dynamic))
        out_treedef, out_is_array, out_static = output[0]
        return jax.tree.unflatten(out_treedef, [next(arrays) if a else v for a, v in zip(out_is_array, out_static)])

    return call


def _program(fn, treedef, is_dynamic, static):
    """The jitted program of one call signature, and (filled while it is traced) the output's
    structure: its treedef, which leaves are arrays, and the other leaves."""
    output = []

    def program(dynamic):
        dynamic, others = iter(dynamic), iter(static)
        leaves = [next(dynamic) if d else next(others) for d in is_dynamic]
        # traced with the abstract mesh set (as it is): JAX sets it while it linearizes a
        # program, and a nested program traced once without it would be traced again there
        # (Solo-12's stiff simulation traced its dynamics twice: +0.5 s of first call); and
        # with float32 products at full precision: a GPU's default (TF32, 10 bits) made
        # float32 contact dynamics wrong by 1e-3 to 1 in 3 of 4 states of a hopper (H200)
        with jax.sharding.use_abstract_mesh(jax.sharding.get_abstract_mesh()), \
                jax.default_matmul_precision("highest"):
            out_leaves, out_treedef = jax.tree.flatten(fn(*jax.tree.unflatten(treedef, leaves)))
        out_is_array = [eqx.is_array(leaf) for leaf in out_leaves]
        output[:] = [(out_treedef, out_is_array, [None if a else leaf for a, leaf in zip(out_is_array, out_leaves)])]
        return [leaf for a, leaf in zip(out_is_array, out_leaves) if a]

    program.__name__ = program.__qualname__ = getattr(fn, "__qualname__", "program")  # named in profiles and logs
    return jax.jit(program), output


def compiled_query(fn):
    """`fn(owner, *args, **named)` through `compiled`, its first argument (a plant, a kinematic
    tree, a trajectory) passed as it is: called outside `jit` (or under an eager `jax.vmap`)
    it runs one program kept per owner structure and argument shapes, not thousands of
    operations one by one; inside a trace it is inlined. Numbers and lists become arrays (a new
    value never recompiles); strings, None and keyword arguments stay static. For methods and
    functions alike."""
    def query(owner, named, *args):
        return fn(owner, *args, **dict(named))

    query.__name__ = query.__qualname__ = fn.__qualname__
    program = compiled(query)

    @functools.wraps(fn)
    def call(owner, *args, **named):
        return program(owner, tuple(sorted(named.items())),
                       *(a if a is None or isinstance(a, str) else call_argument(a) for a in args))

    return call
