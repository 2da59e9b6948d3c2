r"""`cascade`, `feedback` and `parallel` (notes, D.3.4), preserving structure where the math
allows: two LTI systems (both continuous, or discrete with one sample time) combine into a
`LinearSystem` with the block formulas below; polynomial (or LTI) with polynomial into a
`PolynomialSystem`; anything else becomes a `Diagram`, which is
hybrid if a part is hybrid, stochastic if a part is stochastic, and keeps every sample time.
(`docs/architecture.md` has the table.)
"""

from __future__ import annotations

import jax.numpy as jnp

from ..trajectories import Trajectory
from ._diagram import DiagramBuilder
from ._frame import Frame, frame_conversion
from ._linear import LinearSystem
from ._polynomial_system import PolynomialSystem, combine_polynomial_systems
from ._source import TrajectorySource
from ._system import System, check_initialised


def _check_systems(*systems):
    for s in systems:
        if not isinstance(s, System):
            hint = (" (a Trajectory can only come first, as cascade(trajectory, system)'s input tape)"
                    if isinstance(s, Trajectory) else "")
            raise TypeError(f"combinators take jaxdrake.Systems, got {type(s).__name__}{hint}")
        check_initialised(s)


def _both_linear(a, b):
    return (isinstance(a, LinearSystem) and isinstance(b, LinearSystem)
            and a.sample_time == b.sample_time)


def _both_polynomial(a, b):
    """Polynomial (or LTI) with polynomial, at least one polynomial, one sample time: returns
    both as `PolynomialSystem`s, else None."""
    kinds = (PolynomialSystem, LinearSystem)
    if not (isinstance(a, kinds) and isinstance(b, kinds) and a.sample_time == b.sample_time
            and PolynomialSystem in (type(a), type(b))):
        return None
    as_poly = lambda s: s if isinstance(s, PolynomialSystem) else PolynomialSystem.from_linear(s)
    return as_poly(a), as_poly(b)


def _stacked_frame(name, a, b, role):
    """`role` frames of a and b side by side, coordinates prefixed with the systems' names
    (as a diagram names its subsystems)."""
    names = (a.name, b.name if b.name != a.name else f"{b.name}2")
    return Frame(name, tuple(f"{n}.{c}" for n, s in zip(names, (a, b))
                             for c in getattr(s, f"{role}_frame").coordinates), generic=True)


def _block(rows):
    return jnp.block([[jnp.asarray(m) for m in row] for row in rows])


def cascade(a: System | Trajectory, b: System) -> System:
    r"""a's output into b's input (the notes' figure D.2): u -> a -> b -> y. A `Trajectory`
    as `a` is an input tape: a `TrajectorySource` whose output u(t) drives b (its coordinates
    take b's input names).

    Polynomial (or LTI) with polynomial: a `PolynomialSystem` (b's inputs replaced by a's
    output polynomial). LTI with LTI: $A = \begin{bmatrix} A_a & 0 \\ B_b C_a & A_b \end{bmatrix}$,
    $B = \begin{bmatrix} B_a \\ B_b D_a \end{bmatrix}$, $C = [D_b C_a \;\; C_b]$,
    $D = D_b D_a$, state $[x_a; x_b]$.
    """
    if isinstance(a, Trajectory):
        _check_systems(b)
        if a.num_states != b.num_inputs:
            raise ValueError(f"cascade: the input tape has {a.num_states} coordinates, {b.name} has "
                             f"{b.num_inputs} inputs")
        a = TrajectorySource(a, output_frame=b.input_frame)
    _check_systems(a, b)
    conversion = frame_conversion(a.output_frame, b.input_frame)
    if _both_linear(a, b) and conversion is None and b.input_limits is None:
        na, nb = a.num_states, b.num_states
        return LinearSystem(
            _block([[a.A, jnp.zeros((na, nb))], [b.B @ a.C, b.A]]),
            _block([[a.B], [b.B @ a.D]]), _block([[b.D @ a.C, b.C]]), b.D @ a.D,
            sample_time=a.sample_time, input_limits=a.input_limits, input_frame=a.input_frame,
            state_frame=_stacked_frame("CascadeState", a, b, "state"), output_frame=b.output_frame)
    polynomial = _both_polynomial(a, b)
    if polynomial and conversion is None and b.input_limits is None:
        return combine_polynomial_systems(
            "cascade", *polynomial, input_limits=a.input_limits, input_frame=a.input_frame,
            state_frame=_stacked_frame("CascadeState", a, b, "state"), output_frame=b.output_frame)
    builder = DiagramBuilder()
    na, nb = builder.add(a), builder.add(b)
    builder.connect(na, nb)
    builder.export_input(na)
    builder.export_output(nb)
    return builder.build("Cascade")


def feedback(a: System, b: System, sign: float = 1.0) -> System:
    r"""b's output fed back into a's input (the notes' figure D.1), with an external input:
    $u_a = u + s\, y_b$, $u_b = y_a$, $y = y_a$. The default sign $s = +1$ is Drake's (a
    controller's output is the command itself, e.g. $-Kx$); `sign=-1` is the classical
    negative feedback of control toolboxes.

    Polynomial (or LTI) with polynomial: a `PolynomialSystem`. LTI with LTI (no algebraic loop, so $D_a D_b = 0$ and $D_b D_a = 0$):
    $A = \begin{bmatrix} A_a + s B_a D_b C_a & s B_a C_b \\ B_b C_a & A_b + s B_b D_a C_b \end{bmatrix}$,
    $B = \begin{bmatrix} B_a \\ B_b D_a \end{bmatrix}$, $C = [C_a \;\; s D_a C_b]$, $D = D_a$.
    Both direct feedthrough is an algebraic loop: an error.
    """
    _check_systems(a, b)
    if _reads_input_and_output(b, a):
        return _output_feedback_through_estimator(a, b, float(sign))
    if a.direct_feedthrough and b.direct_feedthrough:
        raise ValueError(f"algebraic loop: feedback of {a.name} and {b.name}, which are both direct "
                         "feedthrough (each output depends on its input at the same instant). Break it "
                         "with a system without direct feedthrough; if one of them does not read u in "
                         "its output, declare it with direct_feedthrough=False (to System.__init__ or "
                         "from_functions) or leave it undeclared to have it inferred from output().")
    try:
        forward = frame_conversion(a.output_frame, b.input_frame)
    except ValueError as error:
        if not hasattr(b, "input_port"):
            raise
        raise ValueError(f"{error}. {b.name}'s input has several ports; feedback feeds one vector into it: "
                         f"wire its ports one by one with a jd.DiagramBuilder ({b.name}.input_port(name) gives "
                         "a port's coordinates; see PidController's docstring)") from None
    back = frame_conversion(b.output_frame, a.input_frame)
    s = float(sign)
    if (_both_linear(a, b) and forward is None and back is None
            and a.input_limits is None and b.input_limits is None):
        return LinearSystem(
            _block([[a.A + s * a.B @ b.D @ a.C, s * a.B @ b.C], [b.B @ a.C, b.A + s * b.B @ a.D @ b.C]]),
            _block([[a.B], [b.B @ a.D]]), _block([[a.C, s * a.D @ b.C]]), a.D,
            sample_time=a.sample_time, input_frame=a.input_frame,
            state_frame=_stacked_frame("FeedbackState", a, b, "state"), output_frame=a.output_frame)
    polynomial = _both_polynomial(a, b)
    if polynomial and forward is None and back is None and a.input_limits is None and b.input_limits is None:
        return combine_polynomial_systems(
            "feedback", *polynomial, sign=s, input_frame=a.input_frame,
            state_frame=_stacked_frame("FeedbackState", a, b, "state"), output_frame=a.output_frame)
    builder = DiagramBuilder()
    na, nb = builder.add(a), builder.add(b)
    builder.connect(na, nb)
    builder.connect(nb, na, gain=s)
    builder.export_input(na)
    builder.export_output(na)
    return builder.build("Feedback")


def _reads_input_and_output(b: System, a: System) -> bool:
    """Whether b's input frame is $[u_a; y_a]$ (an estimator of a, or a controller through one):
    a's input coordinates prefixed `u.`, then its output coordinates prefixed `y.`."""
    expected = (tuple(f"u.{c}" for c in a.input_frame.coordinates)
                + tuple(f"y.{c}" for c in a.output_frame.coordinates))
    return b.input_frame.coordinates == expected


def _output_feedback_through_estimator(a: System, b: System, s: float) -> System:
    r"""`feedback(plant, cascade(estimator, controller))`: b reads the input a receives and a's
    output, $u_b = [u + s\, y_b;\; y_a]$, $u_a = u + s\, y_b$, $y = y_a$ (LQG in one line).
    LTI with LTI and $D_b = 0$: with $B_b = [B_u \; B_y]$,
    $A = \begin{bmatrix} A_a & s B_a C_b \\ B_y C_a & A_b + s (B_u + B_y D_a) C_b \end{bmatrix}$,
    $B = \begin{bmatrix} B_a \\ B_u + B_y D_a \end{bmatrix}$, $C = [C_a \;\; s D_a C_b]$, $D = D_a$."""
    if b.direct_feedthrough:
        raise ValueError(f"algebraic loop: {b.name} reads the input of {a.name}, which its own output "
                         "sets, at the same instant; an estimator's output (its state) must not depend "
                         "on its input directly")
    nu = a.num_inputs
    if (_both_linear(a, b) and frame_conversion(b.output_frame, a.input_frame) is None
            and a.input_limits is None and b.input_limits is None):
        b_u, b_y = b.B[:, :nu], b.B[:, nu:]
        return LinearSystem(
            _block([[a.A, s * a.B @ b.C], [b_y @ a.C, b.A + s * (b_u + b_y @ a.D) @ b.C]]),
            _block([[a.B], [b_u + b_y @ a.D]]), _block([[a.C, s * a.D @ b.C]]), a.D,
            sample_time=a.sample_time, input_frame=a.input_frame,
            state_frame=_stacked_frame("FeedbackState", a, b, "state"), output_frame=a.output_frame)
    builder = DiagramBuilder()
    na, nb = builder.add(a), builder.add(b)
    u_part, y_part = (nb, tuple(range(nu))), (nb, tuple(range(nu, b.num_inputs)))
    builder.connect(na, y_part)
    builder.connect(nb, na, gain=s)
    builder.connect(nb, u_part, gain=s)
    builder.connect_input(builder.export_input(na), u_part)
    builder.export_output(na)
    return builder.build("Feedback")


def parallel(a: System, b: System) -> System:
    r"""a and b side by side: input $[u_a; u_b]$, state $[x_a; x_b]$, output $[y_a; y_b]$.

    LTI with LTI: block-diagonal A, B, C, D. Polynomial (or LTI) with polynomial: a
    `PolynomialSystem`.
    """
    _check_systems(a, b)
    if _both_linear(a, b):
        zeros = lambda m, n: jnp.zeros((m, n))
        limits = None
        if a.input_limits is not None or b.input_limits is not None:
            side = lambda s, k: (s.input_limits[k] if s.input_limits is not None
                                 else jnp.full(s.num_inputs, (-jnp.inf, jnp.inf)[k]))
            limits = tuple(jnp.concatenate([side(a, k), side(b, k)]) for k in (0, 1))
        return LinearSystem(
            _block([[a.A, zeros(a.num_states, b.num_states)], [zeros(b.num_states, a.num_states), b.A]]),
            _block([[a.B, zeros(a.num_states, b.num_inputs)], [zeros(b.num_states, a.num_inputs), b.B]]),
            _block([[a.C, zeros(a.num_outputs, b.num_states)], [zeros(b.num_outputs, a.num_states), b.C]]),
            _block([[a.D, zeros(a.num_outputs, b.num_inputs)], [zeros(b.num_outputs, a.num_inputs), b.D]]),
            sample_time=a.sample_time, input_limits=limits,
            input_frame=_stacked_frame("ParallelInput", a, b, "input"),
            state_frame=_stacked_frame("ParallelState", a, b, "state"),
            output_frame=_stacked_frame("ParallelOutput", a, b, "output"))
    polynomial = _both_polynomial(a, b)
    if polynomial and a.input_limits is None and b.input_limits is None:
        return combine_polynomial_systems(
            "parallel", *polynomial, input_frame=_stacked_frame("ParallelInput", a, b, "input"),
            state_frame=_stacked_frame("ParallelState", a, b, "state"),
            output_frame=_stacked_frame("ParallelOutput", a, b, "output"))
    builder = DiagramBuilder()
    na, nb = builder.add(a), builder.add(b)
    builder.export_input(na)
    builder.export_input(nb)
    builder.export_output(na)
    builder.export_output(nb)
    return builder.build("Parallel")

