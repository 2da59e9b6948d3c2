"""What a traced function reads: dependencies followed through its jaxpr."""

from __future__ import annotations

import jax
import jax.extend

# primitives that call one jaxpr with their own inputs and outputs (jit, custom derivatives,
# checkpointing): followed inside, as are the branches of a switch (a hybrid system's modes)
# whose index does not depend; any other sub-program (a loop) counts as one equation whose
# outputs all depend on any input that does
_CALLS = frozenset({"pjit", "jit", "closed_call", "core_call", "custom_jvp_call", "custom_vjp_call",
                    "custom_vjp_call_jaxpr", "checkpoint", "remat", "remat2"})


def outputs_depending_on(jaxpr, reads) -> list[bool]:
    """Which outputs of `jaxpr` (a `Jaxpr`) depend on the inputs flagged True in `reads`,
    followed equation by equation (conservative: an output may be reported as depending on
    an input it only passes through a loop with)."""
    literal = jax.extend.core.Literal
    depends = {v for v, read in zip(jaxpr.invars, reads) if read}
    for eqn in jaxpr.eqns:
        inputs = [not isinstance(v, literal) and v in depends for v in eqn.invars]
        if not any(inputs):
            continue
        called = _called_jaxpr(eqn)
        if called is not None:
            outputs = outputs_depending_on(called, inputs)
        elif eqn.primitive.name == "cond" and not inputs[0]:   # a switch whose index does not depend
            branches = [outputs_depending_on(b.jaxpr, inputs[1:]) for b in eqn.params["branches"]]
            outputs = [any(column) for column in zip(*branches)]
        else:
            outputs = [True] * len(eqn.outvars)
        depends.update(v for v, out in zip(eqn.outvars, outputs) if out)
    return [not isinstance(v, literal) and v in depends for v in jaxpr.outvars]


def _called_jaxpr(eqn):
    """The jaxpr a call-like equation runs on its own inputs (None for anything else)."""
    if eqn.primitive.name not in _CALLS:
        return None
    subs = list(jax.extend.core.jaxprs_in_params(eqn.params))
    if len(subs) != 1:
        return None
    sub = subs[0]
    sub = getattr(sub, "jaxpr", sub)   # a ClosedJaxpr's own
    return sub if (len(sub.invars), len(sub.outvars)) == (len(eqn.invars), len(eqn.outvars)) else None


def reads_argument(fn, args, index: int) -> bool:
    """Whether `fn(*args)`'s result depends on `args[index]` (traced once, abstractly)."""
    jaxpr = jax.make_jaxpr(fn)(*args).jaxpr
    flat = [jax.tree.leaves(a) for a in args]
    reads = [i == index for i, leaves in enumerate(flat) for _ in leaves]
    return any(outputs_depending_on(jaxpr, reads))
