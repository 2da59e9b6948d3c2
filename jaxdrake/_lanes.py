"""Straight-line programs on lanes: a jaxpr of one evaluation, evaluated element by element so
that each value is a vector of lanes, one batch member per position (a GPU thread each).

A value of the original program is either concrete (a NumPy array, known while tracing) or an
object array of its shape whose elements are lane vectors (or Python / NumPy scalars). Only
elementwise arithmetic on lane vectors is left for the kernel: data movement with indices
known while tracing (slices, gathers, reshapes, concatenations, `.at[].set`) is resolved while
tracing, static scans unroll, products and sums become sums of products. Loops, linear solves
and traced indices are refused with the caller's named error.

Users: `simulate_ensemble` (a Dormand-Prince loop per lane around a vector field) and the
rigid-body algorithms' fused batches (`lane_map`: one evaluation per lane, one Pallas kernel).
"""

from __future__ import annotations

import collections
import functools

import jax
import jax.numpy as jnp
import numpy as np

BLOCK = 128  # members per GPU program (lanes of one Pallas block); 64 / 256 measured no faster


_ELEMENTWISE = {
    "abs", "acos", "acosh", "add", "and", "asin", "asinh", "atan", "atan2", "atanh", "cbrt", "ceil", "clamp",
    "convert_element_type", "copy", "copy_p", "cos", "cosh", "div", "eq", "erf", "erf_inv", "erfc", "exp", "exp2",
    "expm1", "floor", "ge", "gt", "integer_pow", "is_finite", "le", "log", "log1p", "logistic", "lt", "max", "min",
    "mul", "ne", "neg", "nextafter", "not", "or", "pow", "rem", "round", "rsqrt", "select_n", "sign", "sin", "sinh",
    "sqrt", "square", "sub", "tan", "tanh", "xor"}
# single-operand data movement: where each output element comes from, found by running the
# primitive on the operand's flat positions
_MOVEMENT = {"slice", "reshape", "squeeze", "broadcast_in_dim", "transpose", "rev", "dynamic_slice", "gather",
             "expand_dims"}
# two-operand data movement of the same kind (the update's positions offset past the operand's)
_OVERWRITE = {"dynamic_update_slice", "scatter"}
_INDEXED = _MOVEMENT | _OVERWRITE | {"scatter-add"}  # their index operands must be known
_CALLS = {"pjit": "jaxpr", "closed_call": "call_jaxpr", "core_call": "call_jaxpr", "custom_jvp_call": "call_jaxpr",
          "custom_vjp_call": "call_jaxpr", "custom_vmap_call": "call", "remat": "jaxpr", "checkpoint": "jaxpr",
          "jit": "jaxpr"}


class Budget:
    """The terms of one evaluation: counts the lane vectors it makes and refuses more than
    `limit`; names the caller (`who`), what is evaluated (`subject`), and what to do instead
    (`remedy`) in its errors (straight-line code is slow to trace and compile past a few
    thousand operations). `fold`: drop products with a known 0 or 1 and sums with a known 0
    (`_folded`): exact for finite values to the sign of zero, but a known zero times an infinite
    or NaN lane gives 0, so only for code whose zeros are structural (a rigid-body tree's axes
    and offsets: the 7-dof arm's ABA, 7,000 -> 4,000 operations), not for `simulate_ensemble`,
    whose members must fail as `simulate` does."""

    def __init__(self, who, subject, limit, remedy, fold=False):
        self.who, self.subject, self.limit, self.remedy, self.fold = who, subject, limit, remedy, fold
        self.spent = 0

    def fresh(self):
        """The same terms with nothing spent (one per trace)."""
        return Budget(self.who, self.subject, self.limit, self.remedy, self.fold)

    def spend(self, outputs):
        self.spent += sum(np.size(v) for v in outputs if not concrete(v))
        if self.spent > self.limit:
            raise NotImplementedError(f"{self.who}: {self.subject} unrolls into more than {self.limit:,} per-lane "
                                      f"operations, whose kernel is slow to compile: {self.remedy}")

    def refuse(self, what):
        raise NotImplementedError(f"{self.who}: {self.subject} {what}; {self.remedy}")


_VALUE_KEYS: collections.OrderedDict = collections.OrderedDict()


def value_key(tree):
    """A hashable key of a pytree's values, for programs that compile them in as constants: its
    structure, each array leaf's shape, dtype and bytes, the other leaves as they are. Found by
    the leaves' identities when all are JAX arrays (immutable; kept alive while keyed), so a
    tree on a GPU is read back to the host once, not at every call."""
    leaves, treedef = jax.tree.flatten(tree)
    ids = (treedef, tuple(id(v) for v in leaves))
    immutable = all(isinstance(v, jax.Array) for v in leaves)
    hit = _VALUE_KEYS.get(ids) if immutable else None
    if hit is None:
        arrays = [np.asarray(v) if isinstance(v, (jax.Array, np.ndarray, np.generic)) else None for v in leaves]
        hit = (leaves, (treedef, tuple((a.shape, str(a.dtype), a.tobytes()) if a is not None else v
                                       for a, v in zip(arrays, leaves))))
        if immutable:
            _VALUE_KEYS[ids] = hit
            if len(_VALUE_KEYS) > 64:
                _VALUE_KEYS.popitem(last=False)
    return hit[1]


def lane_map(fn, examples, budget, kernel="pallas"):
    """`fn` (one evaluation: arrays shaped like `examples` -> an array or a pytree of them) as
    a program over a batch, one lane per member: `program(*batched)` takes each argument with
    a leading batch axis (N, *example.shape) and returns the outputs likewise, in the examples'
    dtype. Values known while tracing (`fn`'s closed-over constants) are folded into the code,
    which is traced here, once (`budget` bounds its length: its error is raised here).
    `kernel`: "pallas" (one Pallas program per `BLOCK` members, every intermediate in
    registers; on a non-GPU backend Pallas's interpreter, slow, for checking) or "xla" (the
    same code vmapped over blocks of `BLOCK` lanes, one jitted program)."""
    closed, out_struct = jax.make_jaxpr(fn, return_shape=True)(*examples)
    shapes, dtype = [tuple(e.shape) for e in examples], examples[0].dtype
    starts = np.cumsum([0] + [int(np.prod(s, dtype=int)) for s in shapes])
    out_shapes = [tuple(a.shape) for a in closed.out_avals]
    out_starts = np.cumsum([0] + [int(np.prod(s, dtype=int)) for s in out_shapes])

    def on_rows(*rows):  # one lane vector (BLOCK,) per input element -> one per output element
        args = [elements(rows[a:b], shape) for a, b, shape in zip(starts[:-1], starts[1:], shapes)]
        outs = evaluate(closed.jaxpr, closed.consts, args, (BLOCK,), dtype, budget.fresh())
        return [materialize(x, (BLOCK,), dtype) for out in outs for x in objects(out).reshape(-1)]

    code = jax.make_jaxpr(on_rows)(*[jax.ShapeDtypeStruct((BLOCK,), dtype)] * int(starts[-1]))

    def block(rows):
        return jax.core.eval_jaxpr(code.jaxpr, code.consts, *rows)

    @jax.jit
    def program(*batched):
        count = batched[0].shape[0]
        rows = jnp.concatenate([jnp.reshape(a, (count, -1)).astype(dtype) for a in batched], 1).T
        if kernel == "pallas":
            out = pallas_over_lanes(lambda ins: [block(ins[0])], [rows], [(int(out_starts[-1]), dtype)])[0]
        else:
            blocks = jnp.pad(rows, ((0, 0), (0, -count % BLOCK)), mode="edge").reshape(rows.shape[0], -1, BLOCK)
            out = jax.vmap(lambda b: jnp.stack(block(list(b))), in_axes=1, out_axes=1)(blocks)
            out = out.reshape(out.shape[0], -1)[:, :count]
        outs = [out[a:b].T.reshape((count, *s)) for a, b, s in zip(out_starts[:-1], out_starts[1:], out_shapes)]
        return jax.tree.unflatten(jax.tree.structure(out_struct), outs)

    return program


def pallas_over_lanes(body, inputs, outputs):
    """One Pallas (Triton) program per `BLOCK` members. `inputs`: arrays (rows, N);
    `body(input rows)` gets each input as a list of lane vectors (BLOCK,) and returns each
    output likewise; `outputs`: (rows, dtype) of each. Rows are padded to powers of two and
    members to a multiple of `BLOCK` (Triton's block shapes), the padding dropped again."""
    from jax.experimental import pallas as pl

    count = inputs[0].shape[1]
    padded = -(-count // BLOCK) * BLOCK
    rows_in = [a.shape[0] for a in inputs]
    blocks = [jnp.pad(a, ((0, pl.next_power_of_2(r) - r), (0, padded - count)), mode="edge") if r
              else jnp.zeros((1, padded), inputs[0].dtype) for a, r in zip(inputs, rows_in)]

    def kernel(*refs):
        ins, outs = refs[:len(inputs)], refs[len(inputs):]
        results = body([[ref[i, :] for i in range(r)] for ref, r in zip(ins, rows_in)])
        for ref, rows in zip(outs, results):
            for i, row in enumerate(rows):
                ref[i, :] = row

    spec = lambda rows: pl.BlockSpec((pl.next_power_of_2(max(rows, 1)), BLOCK), lambda i: (0, i))  # noqa: E731
    out = pl.pallas_call(
        kernel, grid=(padded // BLOCK,),
        in_specs=[spec(b.shape[0]) for b in blocks], out_specs=[spec(r) for r, _ in outputs],
        out_shape=[jax.ShapeDtypeStruct((pl.next_power_of_2(max(r, 1)), padded), d) for r, d in outputs],
        interpret=jax.default_backend() != "gpu",  # elsewhere Pallas's interpreter (slow: for checking)
    )(*blocks)
    return [o[:r, :count] for o, (r, _) in zip(out, outputs)]


def evaluate(jaxpr, consts, args, shape, dtype, budget):
    """Evaluate `jaxpr` with `args` (object arrays of lanes, or concrete arrays); returns its
    outputs in the same representation."""
    env = {}

    def read(v):
        return np.asarray(v.val) if isinstance(v, jax.extend.core.Literal) else env[v]

    for var, value in zip(jaxpr.constvars, consts):
        env[var] = np.asarray(value)
    for var, value in zip(jaxpr.invars, args):
        env[var] = value
    for eqn in jaxpr.eqns:
        inputs = [read(v) for v in eqn.invars]
        name = eqn.primitive.name
        if all(concrete(v) for v in inputs) and name not in _CALLS:
            outs = _known(eqn, [np.asarray(v) for v in inputs])
        elif name in _CALLS:
            outs = evaluate(*_open(eqn.params[_CALLS[name]]), inputs, shape, dtype, budget)
        elif name in _INDEXED and not all(concrete(v) for v in _indices(name, inputs)):
            budget.refuse(f"takes the indices of its `{name}` from the state or time (traced indices)")
        elif name == "scan":
            outs = _unrolled_scan(eqn, inputs, shape, dtype, budget)
        elif name in _ELEMENTWISE:
            outs = [_elementwise(eqn, inputs, shape, budget.fold)]
        elif name in _MOVEMENT:
            outs = [_moved(eqn, inputs[0], inputs[1:])]
        elif name in _OVERWRITE:
            outs = [_overwritten(eqn, inputs)]
        elif name == "scatter-add":
            outs = [_scatter_added(eqn, inputs)]
        elif name == "concatenate":
            outs = [np.concatenate([objects(v) for v in inputs], axis=eqn.params["dimension"])]
        elif name == "stack":
            outs = [np.stack([objects(v) for v in inputs], axis=eqn.params["axis"])]
        elif name == "unstack":
            outs = list(np.moveaxis(objects(inputs[0]), eqn.params.get("axis", 0), 0))
        elif name == "split":
            outs = np.split(objects(inputs[0]), np.cumsum(eqn.params["sizes"])[:-1], axis=eqn.params["axis"])
        elif name in ("reduce_sum", "reduce_max", "reduce_min"):
            outs = [_reduced(name, objects(inputs[0]), eqn.params["axes"], budget.fold)]
        elif name == "dot_general":
            outs = [_dot(eqn, inputs, budget.fold)]
        else:
            budget.refuse(f"uses `{name}`, which has no per-lane form here (loops, linear solves and traced "
                          "indices do not)")
        if name not in _CALLS and name != "scan":  # (counted inside)
            budget.spend(outs)
        for var, value in zip(eqn.outvars, outs):
            env[var] = _wrapped(value)
    return [read(v) for v in jaxpr.outvars]


def _indices(name, inputs):
    """The index operands of a data-movement primitive (they must be known while tracing)."""
    if name in ("scatter", "scatter-add"):
        return [inputs[1]]
    return inputs[2:] if name == "dynamic_update_slice" else inputs[1:]


_NUMPY = {"add": np.add, "sub": np.subtract, "mul": np.multiply, "neg": np.negative, "max": np.maximum,
          "min": np.minimum, "abs": np.abs, "sin": np.sin, "cos": np.cos, "sqrt": np.sqrt, "exp": np.exp,
          "square": np.square, "lt": np.less, "le": np.less_equal, "gt": np.greater, "ge": np.greater_equal,
          "eq": np.equal, "ne": np.not_equal, "and": np.bitwise_and, "or": np.bitwise_or, "not": np.invert,
          "floor": np.floor, "ceil": np.ceil}


@functools.lru_cache(maxsize=1)
def _host():
    """The CPU device where known values are computed (a GPU compiles each eager op slower),
    or the default device when JAX runs without its CPU backend."""
    try:
        return jax.devices("cpu")[0]
    except RuntimeError:
        return None


def _known(eqn, inputs):
    """The outputs of `eqn` on known (NumPy) inputs, computed now: NumPy for the common
    arithmetic and data movement (JAX's eager dispatch compiled a program for each new
    primitive and shape: 4 s of the 7-dof ABA's 8-s trace), JAX otherwise."""
    name, params, x = eqn.primitive.name, eqn.params, (inputs[0] if inputs else None)
    with np.errstate(all="ignore"):  # inf and NaN as XLA makes them, silently
        out = _numpy_value(name, params, x, inputs)
    if out is None:
        with jax.ensure_compile_time_eval(), jax.default_device(_host()):
            value = eqn.primitive.bind(*[jnp.asarray(v) for v in inputs], **params)
        return [np.asarray(o) for o in (value if eqn.primitive.multiple_results else [value])]
    return [np.asarray(out) if name in _MOVEMENT else np.asarray(out, eqn.outvars[0].aval.dtype)]


def _numpy_value(name, params, x, inputs):
    """A primitive's value by NumPy, or None where `_known` leaves it to JAX."""
    out = None
    if x is None:  # no operand (iota, ...)
        return None
    if name in _NUMPY and (name not in ("and", "or", "not") or x.dtype == bool):
        out = _NUMPY[name](*inputs)
    elif name == "div" and np.issubdtype(x.dtype, np.floating):
        out = x / inputs[1]
    elif name == "select_n" and inputs[0].dtype == bool and len(inputs) == 3:
        out = np.where(inputs[0], inputs[2], inputs[1])
    elif name == "convert_element_type" and (np.issubdtype(params["new_dtype"], np.floating)
                                             or not np.issubdtype(x.dtype, np.floating)):
        out = x.astype(params["new_dtype"])  # (float to int: XLA saturates, NumPy wraps; JAX's below)
    elif name == "integer_pow":
        out = x ** params["y"]
    elif name == "slice":
        strides = params["strides"] or (1,) * x.ndim
        out = x[tuple(slice(a, b, s) for a, b, s in zip(params["start_indices"], params["limit_indices"], strides))]
    elif name == "squeeze":
        out = np.squeeze(x, axis=tuple(params["dimensions"]))
    elif name == "broadcast_in_dim" and len(inputs) == 1:
        dims, shape = params["broadcast_dimensions"], params["shape"]
        out = np.broadcast_to(x.reshape([x.shape[dims.index(d)] if d in dims else 1 for d in range(len(shape))]),
                              shape)
    elif name == "reshape" and params.get("dimensions") is None and len(inputs) == 1:
        out = x.reshape(params["new_sizes"])
    elif name == "transpose":
        out = np.transpose(x, params["permutation"])
    elif name == "rev":
        out = np.flip(x, axis=tuple(params["dimensions"]))
    return out


def _open(closed):
    """(jaxpr, consts) of a closed or open jaxpr."""
    return (closed.jaxpr, closed.consts) if hasattr(closed, "consts") else (closed, ())


def _unrolled_scan(eqn, inputs, shape, dtype, budget):
    """A `lax.scan` (a static length) unrolled: its body evaluated once per iteration, so that
    indices computed from the iteration counter are known while tracing."""
    p = eqn.params
    num_consts, num_carry = _scan_counts(p, len(inputs), budget)
    consts, carry = inputs[:num_consts], inputs[num_consts:num_consts + num_carry]
    xs, ys = inputs[num_consts + num_carry:], []
    order = range(p["length"] - 1, -1, -1) if p["reverse"] else range(p["length"])
    for i in order:
        outs = evaluate(*_open(p["jaxpr"]), [*consts, *carry, *[_element(x, i) for x in xs]], shape, dtype, budget)
        carry, y = outs[:num_carry], outs[num_carry:]
        ys.append(y)
    if p["reverse"]:
        ys.reverse()
    stacked = [np.stack([y[k] for y in ys]) if all(concrete(y[k]) for y in ys)
               else np.stack([objects(y[k]) for y in ys]) for k in range(len(eqn.outvars) - len(carry))]
    return [*carry, *stacked]


def _scan_counts(params, num_inputs, budget):
    """(constants, carries) among a scan's operands: JAX 0.10 names the counts; later versions
    give the three groups (constants, carries, scanned) as the flat trees of `ft_in.elts`,
    each as long as its operands."""
    if "num_consts" in params:
        return params["num_consts"], params["num_carry"]
    groups = [len(group) for group in getattr(params.get("ft_in"), "elts", ())]
    if len(groups) != 3 or sum(groups) != num_inputs:
        budget.refuse("uses a `scan` whose operands this JAX version describes in a way not understood here")
    return groups[0], groups[1]


def _element(value, i):
    """value[i] along the first axis, in the same representation as value."""
    return np.asarray(value[i]) if concrete(value) else _wrapped(value[i])


def _wrapped(value):
    """An object array as it is; a lone element (a lane vector, from indexing or a product)
    as a 0-d object array."""
    return value if isinstance(value, np.ndarray) else elements([value], ())


def concrete(value) -> bool:
    return not (isinstance(value, np.ndarray) and value.dtype == object)


def elements(lanes, shape):
    """An object array of `shape` holding the lane vectors `lanes` (NumPy would otherwise read
    the vectors as one more axis)."""
    out = np.empty(len(lanes), dtype=object)
    for i, lane in enumerate(lanes):
        out[i] = lane
    return out.reshape(shape)


def objects(value):
    """An object array of the value's elements (concrete numbers stay NumPy scalars)."""
    return value if not concrete(value) else np.asarray(value).astype(object)


def materialize(element, shape, dtype):
    """A lane vector of `dtype` from an element (a lane vector or a number)."""
    if isinstance(element, (int, float, bool, np.generic, np.ndarray)) or np.ndim(element) == 0:
        return jnp.full(shape, element, dtype)
    return element.astype(dtype) if element.dtype != dtype else element


def _elementwise(eqn, inputs, shape, fold):
    """An elementwise primitive, element by element: all operands known, the result is computed
    now; with `fold`, products with a known 0 or 1 and sums with a known 0 are dropped."""
    out_aval, name = eqn.outvars[0].aval, eqn.primitive.name
    arrays = np.broadcast_arrays(*[objects(v) for v in inputs])
    result = np.empty(out_aval.shape, dtype=object)
    for index in np.ndindex(*out_aval.shape):
        operands = [array[index] for array in arrays]
        known = [not isinstance(e, jax.Array) for e in operands]
        if all(known):
            result[index] = _known(eqn, [np.asarray(e, v.aval.dtype) for e, v in zip(operands, eqn.invars)])[0][()]
            continue
        folded = _folded(name, operands, known, out_aval.dtype) if fold else None
        if folded is not None:
            result[index] = folded
            continue
        result[index] = eqn.primitive.bind(*[materialize(e, shape, v.aval.dtype) if k else e
                                             for e, k, v in zip(operands, known, eqn.invars)], **eqn.params)
    return result


def _folded(name, operands, known, dtype):
    """x * 0 = 0, x * 1 = x, x + 0 = x, x - 0 = x, 0 - x = -x (one operand a lane vector, the
    other known); None otherwise."""
    if name not in ("mul", "add", "sub"):
        return None
    (a, b), (a_known, b_known) = operands, known
    if name == "mul":
        for value, other, value_known in ((a, b, a_known), (b, a, b_known)):
            if value_known and value == 0:
                return np.zeros((), dtype)[()]
            if value_known and value == 1:
                return other
    elif b_known and b == 0:
        return a
    elif a_known and a == 0:
        return b if name == "add" else -b
    return None


def _moved(eqn, operand, others):
    """A data-movement primitive on an object array, from the positions it moves."""
    operand = objects(operand)
    positions = np.arange(operand.size, dtype=np.int32).reshape(operand.shape)
    moved = _known(eqn, [positions, *[np.asarray(v) for v in others]])[0]
    return operand.reshape(-1)[moved]


def _overwritten(eqn, inputs):
    """`dynamic_update_slice(operand, update, *indices)` or `scatter(operand, indices, updates)`
    (replacing): the operand's and the update's elements, placed by their positions."""
    if eqn.primitive.name == "scatter":
        operand, indices, update = inputs[0], inputs[1], inputs[2]
        others = [indices]
    else:
        operand, update, others = inputs[0], inputs[1], inputs[2:]
    operand, update = objects(operand), objects(update)
    offset = operand.size
    positions = np.arange(operand.size, dtype=np.int32).reshape(operand.shape)
    update_positions = offset + np.arange(update.size, dtype=np.int32).reshape(update.shape)
    with jax.ensure_compile_time_eval(), jax.default_device(_host()):
        if eqn.primitive.name == "scatter":
            placed = eqn.primitive.bind(jnp.asarray(positions), jnp.asarray(others[0]), jnp.asarray(update_positions),
                                        **eqn.params)
        else:
            placed = eqn.primitive.bind(jnp.asarray(positions), jnp.asarray(update_positions),
                                        *[jnp.asarray(v) for v in others], **eqn.params)
    return np.concatenate([operand.reshape(-1), update.reshape(-1)])[np.asarray(placed)]


def _scatter_added(eqn, inputs):
    """`scatter-add(operand, indices, updates)` with known indices: each update's target found
    by scattering a one-hot update onto zeros, then added there."""
    operand, indices, updates = inputs
    out, updates = objects(operand).reshape(-1).copy(), objects(updates)
    dtype = eqn.invars[0].aval.dtype  # the primitive's own (its adding region is typed)
    for j in range(updates.size):
        one_hot = np.zeros(updates.size, dtype)
        one_hot[j] = 1
        with jax.ensure_compile_time_eval(), jax.default_device(_host()):
            hit = np.asarray(eqn.primitive.bind(jnp.zeros(np.shape(operand), dtype), jnp.asarray(indices),
                                                jnp.asarray(one_hot.reshape(updates.shape)), **eqn.params))
        for target in np.flatnonzero(hit.reshape(-1)):
            out[target] = out[target] + updates.reshape(-1)[j]
    return out.reshape(np.shape(operand))


def _reduced(name, operand, axes, fold):
    combine = {"reduce_sum": functools.partial(_arithmetic, "add", fold=fold), "reduce_max": jnp.maximum,
               "reduce_min": jnp.minimum}[name]
    moved = np.moveaxis(operand, axes, tuple(range(-len(axes), 0)))
    flat = moved.reshape(moved.shape[:moved.ndim - len(axes)] + (-1,))
    out = np.empty(flat.shape[:-1], dtype=object)
    for index in np.ndindex(*out.shape):
        out[index] = functools.reduce(combine, list(flat[index]))
    return out


def _dot(eqn, inputs, fold):
    """`dot_general` as sums of products (`_arithmetic`): batch dimensions first,
    then the left operand's free dimensions and the right one's (XLA's order)."""
    (lhs_contract, rhs_contract), (lhs_batch, rhs_batch) = eqn.params["dimension_numbers"]
    lhs, rhs = objects(inputs[0]), objects(inputs[1])
    lhs_free = [d for d in range(lhs.ndim) if d not in (*lhs_batch, *lhs_contract)]
    rhs_free = [d for d in range(rhs.ndim) if d not in (*rhs_batch, *rhs_contract)]
    lhs = np.transpose(lhs, (*lhs_batch, *lhs_free, *lhs_contract))
    rhs = np.transpose(rhs, (*rhs_batch, *rhs_contract, *rhs_free))
    batch, left = lhs.shape[:len(lhs_batch)], lhs.shape[len(lhs_batch):len(lhs_batch) + len(lhs_free)]
    right = rhs.shape[len(rhs_batch) + len(rhs_contract):]
    size = int(np.prod(lhs.shape[len(lhs_batch) + len(lhs_free):], dtype=int))
    lhs = lhs.reshape(int(np.prod(batch, dtype=int)), int(np.prod(left, dtype=int)), size)
    rhs = rhs.reshape(lhs.shape[0], size, int(np.prod(right, dtype=int)))
    zero = np.zeros((), eqn.outvars[0].aval.dtype)[()]
    out = np.empty((lhs.shape[0], lhs.shape[1], rhs.shape[2]), dtype=object)
    for b, i, j in np.ndindex(*out.shape):
        products = [_arithmetic("mul", lhs[b, i, k], rhs[b, k, j], fold) for k in range(size)]
        out[b, i, j] = functools.reduce(functools.partial(_arithmetic, "add", fold=fold), products) if size else zero
    return out.reshape(batch + left + right)


def _python_number(value):
    """A known number as a Python scalar: weakly typed, so it takes the lane's dtype."""
    return value.item() if hasattr(value, "item") else value


def _arithmetic(name, a, b, fold):
    """a * b or a + b ("mul", "add") of elements: known numbers now, `_folded` with `fold`."""
    known = [not isinstance(e, jax.Array) for e in (a, b)]
    if all(known):
        return a * b if name == "mul" else a + b
    dtype = (b if known[0] else a).dtype
    folded = _folded(name, (a, b), known, dtype) if fold else None
    if folded is not None:
        return folded
    a, b = (_python_number(e) if k else e for e, k in zip((a, b), known))
    return a * b if name == "mul" else a + b
