r"""Reverse mode of the simulation loop (`simulate(..., autodiff="reverse")`, the default).

`jax.grad` asks for $\bar p = J^T \bar y$, the cotangent $\bar y$ of the loop's result (the
final state and the trajectory buffers) pulled back to the differentiated inputs $p$ (the
perturbed leaves of the system, the input source, x0, t0, tf, and of values the loop closes
over: the loop is traced once into a jaxpr whose closed-over values become arguments). Two
ways, picked while tracing from the number $P$ of differentiated scalars:

- **Forward sensitivities** ($P \le$ `MAX_FORWARD_DIRECTIONS`): the forward pass runs the
  plain loop under `jax.jvp` along the $P$ unit directions $e_i$ at once (a `vmap`) and keeps
  the tangents; the backward pass contracts them with the cotangent,
  $\bar p_i = \langle \bar y, J e_i \rangle$ (where the tangents would not fit in
  `TANGENT_BYTES`, it re-runs them in chunks instead). The program holds the loop and its
  tangent: no transpose of the loop, no recomputation of checkpoints, so it compiles 2.3-3.3x
  faster than JAX's transpose of a checkpointed loop (`benchmarks/RESULTS.md`) and runs faster for the
  few-parameter gradients of system identification and design; it also differentiates
  inner `while_loop`s that JAX cannot transpose (MJX's solver).
- **The discrete adjoint** (larger $P$: a floating robot's x0, a neural controller's
  weights, a long input tape), whose cost does not grow with $P$ (`run_adjoint`: one
  iteration's VJP, looped backwards); when a closed-over value is among the differentiated
  ones, the traced loop's tangents in chunks instead.

Either way it is the same derivative, that of the computed solution (step sizes and a
Rosenbrock step's matrix held, event times by the implicit-function theorem).
`autodiff="adjoint"` always takes the discrete adjoint. JAX never transposes the loop.
"""
from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np

from ._result import trajectory_bytes

MAX_FORWARD_DIRECTIONS = 32  # Solo-12 from x0 (37): 7x the adjoint's warm time; the Panda (18): faster both ways
TANGENT_BYTES = 256 * 2**20
KEPT_BYTES = 1024 * 2**20   # the adjoint keeps every iteration's state up to this (else every stride-th)


def run_reverse(loop, t0, x0, h0, status):
    """`loop.run_loop` differentiable by `jax.grad` (see the module doc). The loop is traced
    once into a jaxpr whose closed-over values (a traced gain inside an input function or a
    controller) become arguments, so that they are differentiated too."""
    inputs = (loop, t0, x0, h0)
    run = eqx.filter_closure_convert(lambda i: i[0].run_loop(i[1], i[2], i[3], status), inputs)
    return _differentiable_run((run, inputs), status)


@eqx.filter_custom_vjp
def _differentiable_run(vjp_arg, status):
    run, inputs = vjp_arg
    return run(inputs)


@_differentiable_run.def_fwd
def _forward(perturbed, vjp_arg, status):
    """The forward pass: with few differentiated scalars whose tangents fit in memory, the
    loop under `jax.jvp` along every unit direction at once (its tangents are the residuals,
    so the backward pass only contracts); else the plain loop."""
    directions = _Directions(vjp_arg, perturbed)
    adjoint = directions.adjoint(status)
    if adjoint is not None:   # the adjoint's forward pass; its pullback is the residual
        out, pullback = eqx.filter_vjp(adjoint, directions.values)
        return out, (out, pullback)
    if not (directions.forward and directions.chunk() == directions.count):
        return _differentiable_run.fn(vjp_arg, status), None
    out, tangents = jax.vmap(lambda e: jax.jvp(directions.run, (directions.values,), (directions.split(e),)),
                             out_axes=(None, 0))(directions.basis())
    return out, tangents


@_differentiable_run.def_bwd
def _backward(residuals, cotangent, perturbed, vjp_arg, status):
    directions = _Directions(vjp_arg, perturbed)
    if not directions.count:
        return directions.gradient([])
    if directions.adjoint(status) is not None:   # the adjoint's pullback
        out, pullback = residuals
        return directions.gradient(pullback(_dense_cotangent(out, cotangent))[0])
    if residuals is not None:  # the tangents, stored by the forward pass
        flat = jax.vmap(lambda t: _contract(cotangent, t))(residuals)
    else:
        # tangents over the memory bound, or a closed-over value among many differentiated
        # ones (only the traced jaxpr may be re-run then): the tangents again, in chunks
        flat = jax.lax.map(lambda e: _contract(cotangent, jax.jvp(directions.run, (directions.values,),
                                                                   (directions.split(e),))[1]),
                           directions.basis(), batch_size=directions.chunk())
    return directions.gradient(directions.split(flat))


class _Directions:
    """The differentiated leaves of (the traced loop's closed-over values, (loop, t0, x0,
    h0)), flattened into `count` scalars."""

    def __init__(self, vjp_arg, perturbed):
        self.leaves, self.treedef = jax.tree.flatten(vjp_arg)
        flags = self.treedef.flatten_up_to(perturbed)
        self.chosen = [i for i, flag in enumerate(flags) if flag]
        self.values = [self.leaves[i] for i in self.chosen]
        self.sizes = [int(np.prod(v.shape)) for v in self.values]
        self.offsets = np.cumsum([0] + self.sizes)
        self.count = int(self.offsets[-1])
        self.dtype = jnp.result_type(*self.values) if self.values else jnp.float32
        self.forward = 0 < self.count <= MAX_FORWARD_DIRECTIONS
        num_closure_leaves = len(jax.tree.leaves(vjp_arg[0]))
        self.in_closure = any(i < num_closure_leaves for i in self.chosen)

    def _with(self, values):
        leaves = list(self.leaves)
        for i, value in zip(self.chosen, values):
            leaves[i] = value
        return jax.tree.unflatten(self.treedef, leaves)

    def run(self, values):
        """The traced loop as a function of the differentiated leaves."""
        run, inputs = self._with(values)
        return run(inputs)

    def adjoint(self, status):
        """For many differentiated scalars, none of them closed over: the loop run by
        `run_adjoint`, a function of the differentiated leaves (else None)."""
        if self.forward or self.in_closure or not self.count:
            return None

        def run(values):
            _, (loop, t0, x0, h0) = self._with(values)
            return run_adjoint(loop, t0, x0, h0, status)
        return run

    def basis(self):
        return jnp.eye(self.count, dtype=self.dtype)

    def split(self, flat):
        """A vector over the `count` scalars as one array per differentiated leaf."""
        return [flat[a:b].reshape(v.shape).astype(v.dtype)
                for a, b, v in zip(self.offsets[:-1], self.offsets[1:], self.values)]

    def chunk(self):
        """How many directions' tangents (chiefly the trajectory buffers) fit in
        `TANGENT_BYTES` at once."""
        _, (loop, _, x0, _) = jax.tree.unflatten(self.treedef, self.leaves)
        per_direction = trajectory_bytes(x0.shape[0], loop.max_steps, loop.max_events, loop.dense,
                                         jnp.dtype(x0.dtype).itemsize)
        return int(max(1, min(self.count, TANGENT_BYTES // per_direction)))

    def gradient(self, grads):
        """The cotangent of the custom VJP's argument: `grads` at the differentiated leaves."""
        out = [None] * len(self.leaves)
        for i, g in zip(self.chosen, grads):
            out[i] = g
        return jax.tree.unflatten(self.treedef, out)


def _contract(cotangent, tangent_out):
    """<ybar, ydot> over the outputs whose cotangent is not a symbolic zero."""
    pairs = zip(jax.tree.leaves(cotangent, is_leaf=lambda x: x is None),
                jax.tree.leaves(tangent_out, is_leaf=lambda x: x is None))
    products = [jnp.vdot(c, t.astype(c.dtype)) for c, t in pairs if c is not None]
    return sum(products[1:], products[0]) if products else jnp.zeros(())


def _dense_cotangent(primal, cotangent):
    """The cotangent with its symbolic zeros (None at an inexact output) made zero arrays."""
    return jax.tree.map(lambda c, p: (jnp.zeros_like(p) if c is None else c) if eqx.is_inexact_array(p) else None,
                        cotangent, primal, is_leaf=lambda x: x is None)


# ----- the discrete adjoint (autodiff="adjoint") ---------------------------------------------


def run_adjoint(loop, t0, x0, h0, status):
    r"""`loop.run_loop` differentiable by `jax.grad` through its discrete adjoint: the loop
    as a sequence of iterations $s_{i+1} = \Phi(s_i, p)$ (each one `Loop.iterate`: a step
    attempt, its event, its reset, its record), and the backward pass
    $\bar s_i = (\partial\Phi/\partial s_i)^T \bar s_{i+1}$,
    $\bar p \mathrel{+}= (\partial\Phi/\partial p)^T \bar s_{i+1}$ from the last iteration to
    the first, a `lax.while_loop` over `jax.vjp` of one iteration. The forward pass keeps
    each iteration's state without its trajectory buffers (`max_steps` small states; where
    they would pass `KEPT_BYTES`, every `kept_stride`-th, and the backward pass re-runs each
    stretch from its first); the backward pass re-runs one iteration from it. The iteration
    is traced once, with its buffers cut to the one row it writes (`Loop.windowed`); the loop
    places that row, and the backward pass reads the row's cotangent. A linearly implicit
    solver's kept matrix is formed again where it was reused (same values, held as always). The same derivative as the other modes: that of the computed solution."""
    s0 = loop.initial_state(t0, x0, h0, status)
    step = eqx.filter_closure_convert(dataclasses.replace(loop, windowed=True).iterate, _window(s0, s0.linearization))
    continues = eqx.filter_closure_convert(loop.continues, _without_buffers(s0))
    state_bytes = sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(_without_buffers(s0)))
    return _adjoint_run((step, continues, s0), loop.max_steps, kept_stride(loop.max_steps, state_bytes))


def _window(s, linearization, like=None):
    """The state `s` as the windowed iteration takes it: buffers of one row of zeros (shaped
    as those of `like`, by default `s`), and the kept matrix `linearization`."""
    rows = tuple(None if b is None else jnp.zeros((1,) + b.shape[1:], b.dtype)
                 for b in (s if like is None else like).buffers())
    return dataclasses.replace(eqx.tree_at(lambda s: s.buffers(), s, rows, is_leaf=lambda x: x is None),
                               linearization=linearization)


def _without_buffers(s):
    """What the forward pass keeps of an iteration's state: no buffers (their counts stay), no
    kept matrix."""
    return dataclasses.replace(eqx.tree_at(lambda s: s.buffers(), s, (None,) * len(s.buffers())), linearization=None)


def _placed(s, w):
    """The iteration's result `w` (one-row buffers) with its rows written into the buffers
    of `s`, the state it started from, where they belong."""
    full = tuple(b.at[n].set(row[0], pred=m > n)
                 for b, row, n, m in zip(s.buffers(), w.buffers(), s.buffer_counts(), w.buffer_counts()))
    return eqx.tree_at(lambda s: s.buffers(), w, full)


def _iterations(step, continues, s0, max_steps, stride=None):
    """The forward loop; with a `stride`, also the state (`_without_buffers`) of every
    `stride`-th iteration."""
    kept = () if stride is None else tuple(jnp.zeros((-(-max_steps // stride),) + x.shape, x.dtype)
                                           for x in jax.tree.leaves(_without_buffers(s0)))

    def body(carry):
        s, kept = carry
        if stride is not None:   # a flat tuple: its entries are the loop's in-place buffers
            kept = tuple(b.at[s.iterations // stride].set(x, pred=s.iterations % stride == 0)
                         for b, x in zip(kept, jax.tree.leaves(_without_buffers(s))))
        return _placed(s, step(_window(s, s.linearization))), kept

    return eqxi.while_loop(lambda carry: continues(_without_buffers(carry[0])), body, (s0, kept),
                           max_steps=max_steps, kind="lax",
                           buffers=lambda carry: carry[0].buffers() + (() if stride is None else tuple(carry[1])))


def kept_stride(max_steps, state_bytes):
    """Iterations per state the adjoint keeps: 1 where `max_steps` states fit in `KEPT_BYTES`;
    else about sqrt(max_steps), and the backward pass re-runs each stretch of `stride`
    iterations from its first state (one more forward iteration per iteration whatever the
    stride, and the fewest states kept: max_steps / stride + stride)."""
    if max_steps * state_bytes <= KEPT_BYTES:
        return 1
    return math.isqrt(max_steps - 1) + 1


@eqx.filter_custom_vjp
def _adjoint_run(vjp_arg, max_steps, stride):
    step, continues, s0 = vjp_arg
    return _iterations(step, continues, s0, max_steps)[0]


@_adjoint_run.def_fwd
def _adjoint_forward(perturbed, vjp_arg, max_steps, stride):
    step, continues, s0 = vjp_arg
    final, kept = _iterations(step, continues, s0, max_steps, stride)
    return final, (final, kept)


@_adjoint_run.def_bwd
def _adjoint_backward(residuals, cotangent, perturbed, vjp_arg, max_steps, stride):
    final, kept = residuals
    step, _, s0 = vjp_arg
    cotangent = _dense_cotangent(final, cotangent)
    # the step's perturbed leaves alone (its other floats, e.g. the event tolerance, feed
    # loops that JAX cannot differentiate)
    step_diff, step_static = eqx.partition(step, perturbed[0])
    kept_structure = jax.tree.structure(_without_buffers(s0))
    stale = None if s0.linearization is None else dataclasses.replace(   # a kept matrix not current: formed again
        jax.tree.map(jnp.zeros_like, s0.linearization), current=jnp.asarray(False))

    def state(rows, k):
        return jax.tree.unflatten(kept_structure, [b[k] for b in rows])

    def rerun(i):
        """The states of the stretch of `stride` iterations that holds iteration i, from its
        kept first state to i."""
        def body(k, carry):
            s, stretch = carry
            s = _without_buffers(step(_window(s, stale, like=s0)))
            return s, tuple(b.at[k + 1].set(x) for b, x in zip(stretch, jax.tree.leaves(s)))
        first = state(kept, i // stride)
        stretch = tuple(jnp.zeros((stride,) + b.shape[1:], b.dtype).at[0].set(x)
                        for b, x in zip(kept, jax.tree.leaves(first)))
        return jax.lax.fori_loop(0, i % stride, body, (first, stretch))[1]

    def backward(carry):
        i, s_bar, p_bar, stretch = carry
        i = i - 1
        if stride == 1:
            start = state(kept, i)
        else:   # entering a stretch (from its end): its states again
            stretch = jax.lax.cond((i % stride == stride - 1) | (i == final.iterations - 1),
                                   rerun, lambda i: stretch, i)
            start = state(stretch, i % stride)
        start = _window(start, stale, like=s0)
        start_diff, start_static = eqx.partition(start, eqx.is_inexact_array)

        def one_iteration(step_diff, start_diff):
            start = eqx.combine(start_diff, start_static)   # step sizes held, as `Loop.record` holds them
            start = dataclasses.replace(start, h=jax.lax.stop_gradient(start.h))
            out = eqx.combine(step_diff, step_static)(start)
            return eqx.filter(out, eqx.is_inexact_array)

        _, pullback = jax.vjp(one_iteration, step_diff, start_diff)
        rows = tuple(None if c is None else jax.lax.dynamic_index_in_dim(c, n, keepdims=True)
                     for c, n in zip(cotangent.buffers(), start.buffer_counts()))
        step_bar, start_bar = pullback(eqx.tree_at(lambda s: s.buffers(), s_bar, rows, is_leaf=lambda x: x is None))
        return i, start_bar, jax.tree.map(jnp.add, p_bar, step_bar), stretch

    s_bar = eqx.filter(_window(cotangent, cotangent.linearization), eqx.is_inexact_array)
    p_bar = jax.tree.map(jnp.zeros_like, step_diff)
    stretch = () if stride == 1 else tuple(jnp.zeros((stride,) + b.shape[1:], b.dtype) for b in kept)
    _, s_bar, p_bar, _ = jax.lax.while_loop(lambda carry: carry[0] > 0, backward,
                                            (final.iterations, s_bar, p_bar, stretch))
    # s0's buffers reach the end unchanged except in the rows the iterations wrote
    unwritten = tuple(None if c is None else c * _rows_outside(c, n0, n1)
                      for c, n0, n1 in zip(cotangent.buffers(), s0.buffer_counts(), final.buffer_counts()))
    s0_bar = eqx.tree_at(lambda s: s.buffers(), s_bar, unwritten, is_leaf=lambda x: x is None)
    zeros = lambda tree: jax.tree.map(jnp.zeros_like, eqx.filter(tree, eqx.is_inexact_array))  # noqa: E731
    return eqx.combine(p_bar, zeros(eqx.filter(step, perturbed[0], inverse=True))), zeros(vjp_arg[1]), s0_bar


def _rows_outside(c, first, end):
    """1 for the rows of buffer `c` outside [first, end), else 0 (shaped to broadcast)."""
    rows = jnp.arange(c.shape[0])
    return ((rows < first) | (rows >= end)).astype(c.dtype).reshape((-1,) + (1,) * (c.ndim - 1))
