r"""Drake's linear primitive blocks (`drake/systems/primitives`, `PidController`) as
`LinearSystem`s: each is a final subclass whose constructor takes Drake's arguments and builds
$A, B, C, D$, so `cascade`, `feedback` and `parallel` of these blocks with other LTI systems
stay LTI.

Drake's blocks with several input (or output) ports have one input (output) vector here: the
ports stacked in Drake's order, each coordinate named `port[i]` (`u0[0], u0[1], u1[0], ...`).
`block.input_port(k)` (by index or name) gives one port's coordinate names, which is what
`DiagramBuilder.connect` takes to wire a port::

    builder.connect("sensor", ("adder", adder.input_port(1)))
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import numpy as np

from .._numbers import array_module
from ._frame import Frame
from ._linear import LinearSystem


def port_frame(name: str, ports: Sequence[tuple[str, int]]) -> Frame:
    """A generic frame of named ports stacked in order, coordinates `port[i]`."""
    return Frame(name, tuple(f"{port}[{i}]" for port, size in ports for i in range(size)), generic=True)


def port_coordinates(frame: Frame, port: int | str) -> tuple[str, ...]:
    """The coordinate names of one port (its index or name) of a `port_frame`."""
    names = list(dict.fromkeys(c.rpartition("[")[0] for c in frame.coordinates))
    if isinstance(port, (int, np.integer)):
        if not 0 <= port < len(names):
            raise IndexError(f"port {port} is out of range: frame {frame.name} has the ports {names}")
        port = names[port]
    if port not in names:
        raise KeyError(f"frame {frame.name} has no port {port!r}; its ports are {names}")
    return tuple(c for c in frame.coordinates if c.rpartition("[")[0] == port)


def _positive_int(value, label: str, block: str) -> int:
    if not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{block}: {label} must be a positive int, got {value!r}")
    return int(value)


def _period(value, label: str, block: str) -> float:
    if isinstance(value, jax.core.Tracer) or not (float(value) > 0 and np.isfinite(float(value))):
        raise ValueError(f"{block}: {label} must be a positive, finite number of seconds (a "
                         f"static value, not traced), got {value!r}")
    return float(value)


def _vector(value, label: str, block: str, size: int | None = None):
    """`value` as a float vector (a scalar broadcast to `size` when given): numpy for host
    numbers (building a block compiles nothing), JAX for JAX arrays and tracers (a gain
    differentiated through the constructor)."""
    xp = array_module(value)
    v = xp.atleast_1d(xp.asarray(value, dtype=float))
    if size is not None and v.shape == (1,):
        v = xp.broadcast_to(v, (size,))
    if v.ndim != 1 or (size is not None and v.shape != (size,)):
        expected = f"a scalar or shape ({size},)" if size is not None else "a vector"
        raise ValueError(f"{block}: {label} must be {expected}, got shape {v.shape}")
    return v


def _stateless(D, **kwargs) -> dict:
    """The matrices of a memoryless block y = D u (no state)."""
    p, m = D.shape
    return dict(A=np.zeros((0, 0)), B=np.zeros((0, m)), C=np.zeros((p, 0)), D=D, **kwargs)


class ZeroOrderHold(LinearSystem):
    r"""Drake's `ZeroOrderHold`: samples its input every `period_sec` seconds and holds it,

    $$x[n+1] = u[n], \qquad y[n] = x[n], \qquad x[0] = 0,$$

    with updates at $t = 0, h, 2h, \dots$; the output on $(kh, (k+1)h]$ is $u(kh)$.

    **Arguments:** `period_sec` (h), `vector_size`, `offset_sec` (Drake's first update time;
    only 0 here: jaxdrake's sample times start at t = 0).
    """

    def __init__(self, period_sec: float, vector_size: int, offset_sec: float = 0.0):
        period = _period(period_sec, "period_sec", "ZeroOrderHold")
        n = _positive_int(vector_size, "vector_size", "ZeroOrderHold")
        if float(offset_sec) != 0.0:
            raise ValueError(f"ZeroOrderHold: offset_sec={offset_sec} is not supported: jaxdrake's discrete "
                             "updates happen at k * period from t = 0. Shift the time instead (simulate from "
                             "t0 = -offset_sec), or use offset_sec=0")
        super().__init__(np.zeros((n, n)), np.eye(n), np.eye(n), sample_time=period)


class DiscreteTimeDelay(LinearSystem):
    r"""Drake's `DiscreteTimeDelay`: the input sampled every `update_sec` seconds and output
    `delay_time_steps` updates later. With $d$ = `delay_time_steps`, the state is $d + 1$
    blocks of the input's size,

    $$x[n+1] = (x_1[n], \dots, x_d[n], u[n]), \qquad y[n] = x_0[n], \qquad x[0] = 0,$$

    so $y = u(t_k)$ on $(t_{k+d}, t_{k+d+1}]$ (a `ZeroOrderHold` when $d = 0$).

    **Arguments:** `update_sec`, `delay_time_steps` (d >= 0), `vector_size`.
    """

    def __init__(self, update_sec: float, delay_time_steps: int, vector_size: int):
        period = _period(update_sec, "update_sec", "DiscreteTimeDelay")
        z = _positive_int(vector_size, "vector_size", "DiscreteTimeDelay")
        if not isinstance(delay_time_steps, (int, np.integer)) or delay_time_steps < 0:
            raise ValueError(f"DiscreteTimeDelay: delay_time_steps must be a non-negative int, got "
                             f"{delay_time_steps!r}")
        n = (int(delay_time_steps) + 1) * z
        super().__init__(np.eye(n, k=z), np.eye(n, z, k=z - n), np.eye(z, n), sample_time=period)


class Gain(LinearSystem):
    r"""Drake's `Gain`: the element-wise $y = k \odot u$ (no state).

    **Arguments:** `k`, a scalar with `size`, or a vector (one gain per element).
    """

    def __init__(self, k, size: int | None = None):
        if size is not None:
            _positive_int(size, "size", "Gain")
        k = _vector(k, "k", "Gain", size)
        super().__init__(**_stateless(array_module(k).diag(k)))


class Adder(LinearSystem):
    r"""Drake's `Adder`: $y = u_0 + u_1 + \dots + u_{N-1}$ for N inputs of one size (no state).

    Its input is $[u_0; \dots; u_{N-1}]$, ports `u0`, ..., `u{N-1}`: wire one with
    `builder.connect(source, (name, adder.input_port(k)))`.

    **Arguments:** `num_inputs` (N), `size`.
    """

    def __init__(self, num_inputs: int, size: int):
        count = _positive_int(num_inputs, "num_inputs", "Adder")
        n = _positive_int(size, "size", "Adder")
        super().__init__(**_stateless(np.tile(np.eye(n), (1, count)),
                                      input_frame=port_frame("AdderInput", [(f"u{k}", n) for k in range(count)])))

    def input_port(self, port: int | str) -> tuple[str, ...]:
        """The coordinate names of input port `port` (`k` or `"u{k}"`), for `DiagramBuilder.connect`."""
        return port_coordinates(self.input_frame, port)


class Multiplexer(LinearSystem):
    r"""Drake's `Multiplexer`: stacks its input ports into one output vector,
    $y = [u_0; \dots; u_{N-1}]$ (no state).

    **Arguments:** `input_sizes`: an int N (N scalar ports) or the size of each port.
    """

    def __init__(self, input_sizes: int | Sequence[int]):
        if isinstance(input_sizes, (int, np.integer)):
            input_sizes = [1] * _positive_int(input_sizes, "num_scalar_inputs", "Multiplexer")
        sizes = [_positive_int(n, "each input size", "Multiplexer") for n in input_sizes]
        if not sizes:
            raise ValueError("Multiplexer: needs at least one input port")
        super().__init__(**_stateless(np.eye(sum(sizes)), input_frame=port_frame(
            "MultiplexerInput", [(f"u{k}", n) for k, n in enumerate(sizes)])))

    def input_port(self, port: int | str) -> tuple[str, ...]:
        """The coordinate names of input port `port` (`k` or `"u{k}"`), for `DiagramBuilder.connect`."""
        return port_coordinates(self.input_frame, port)


class Demultiplexer(LinearSystem):
    r"""Drake's `Demultiplexer`: splits its input into output ports,
    $[y_0; \dots; y_{N-1}] = u$ (no state).

    **Arguments:** `size` with `output_ports_size` (N = size / output_ports_size ports of that
    size), or `size` a list of the output ports' sizes.
    """

    def __init__(self, size: int | Sequence[int], output_ports_size: int = 1):
        if isinstance(size, (int, np.integer)):
            n = _positive_int(size, "size", "Demultiplexer")
            step = _positive_int(output_ports_size, "output_ports_size", "Demultiplexer")
            if n % step:
                raise ValueError(f"Demultiplexer: size {n} is not a multiple of output_ports_size {step}")
            size = [step] * (n // step)
        sizes = [_positive_int(n, "each output port size", "Demultiplexer") for n in size]
        if not sizes:
            raise ValueError("Demultiplexer: needs at least one output port")
        super().__init__(**_stateless(np.eye(sum(sizes)), output_frame=port_frame(
            "DemultiplexerOutput", [(f"y{k}", n) for k, n in enumerate(sizes)])))

    def output_port(self, port: int | str) -> tuple[str, ...]:
        """The coordinate names of output port `port` (`k` or `"y{k}"`), for `DiagramBuilder.connect`."""
        return port_coordinates(self.output_frame, port)


class Saturation(LinearSystem):
    r"""Drake's `Saturation` (constant limits): $y = \min(\max(u, u_{min}), u_{max})$,
    element-wise (no state).

    It is the identity $y = u$ with input limits $u_{min} \le u \le u_{max}$, the contract's own
    saturation: a diagram clips the signal entering it, `simulate` holds an input at its limit
    between located switching instants (events, when the block's input is the simulated
    system's input), and `cascade(saturation, lti)` stays a `LinearSystem` with those limits.
    Like any system with input limits, `output(t, x, u)` takes the saturated input: evaluate
    by hand as `output(t, x, saturate(u))`.

    **Arguments:** `min_value`, `max_value`: vectors of one size (or scalars for size 1),
    `min_value <= max_value`. (Drake's variable form, `Saturation(input_size)` with limit
    ports, is not a linear system; write it as `jnp.clip` in `System.from_functions`.)
    """

    def __init__(self, min_value, max_value=None):
        if max_value is None:
            raise TypeError("Saturation needs min_value and max_value (Drake's constant limits); the variable "
                            "form Saturation(input_size), with limit input ports, is not provided")
        low = _vector(min_value, "min_value", "Saturation")
        high = _vector(max_value, "max_value", "Saturation", low.shape[0])
        super().__init__(**_stateless(np.eye(low.shape[0]), input_limits=(low, high)))


class FirstOrderLowPassFilter(LinearSystem):
    r"""Drake's `FirstOrderLowPassFilter`: element-wise $\dot z_i = (u_i - z_i) / \tau_i$,
    $y = z$, the transfer function $1 / (1 + \tau_i s)$ (start from a given output with
    `simulate(..., x0=z0)`, Drake's `set_initial_output_value`).

    **Arguments:** `time_constant` (τ > 0) with `size`, or a vector of time constants.
    """

    def __init__(self, time_constant, size: int = 1):
        size = _positive_int(size, "size", "FirstOrderLowPassFilter")
        tau = _vector(time_constant, "time_constant", "FirstOrderLowPassFilter",
                      None if np.ndim(time_constant) else size)
        if not isinstance(tau, jax.core.Tracer) and not np.all(np.asarray(tau) > 0):
            raise ValueError(f"FirstOrderLowPassFilter: time constants must be positive, got {tau}")
        rate = array_module(tau).diag(1.0 / tau)
        super().__init__(-rate, rate)


class PidController(LinearSystem):
    r"""Drake's `PidController`, and its discrete-time form with `sample_time`.

    Input $[x_{in}; x_d]$ (ports `estimated_state`, of P_x's width, and `desired_state`
    $= (q_d, v_d)$, of size 2 nq); with the controlled state $x_c = P_x x_{in}$ and the error
    $e = x_d - x_c = (e_q, e_v)$ the state z integrates $e_q$ and the output is

    $$y = P_y\,(k_p \odot e_q + k_d \odot e_v + k_i \odot z),$$

    $\dot z = e_q$ (Drake's) or, with `sample_time` h, $z[n+1] = z[n] + h\, e_q[n]$ (explicit
    Euler, Drake's `DiscreteTimeIntegrator`); the output reads the input directly in both.
    Start from a given integral with `simulate(..., x0=z0)` (Drake's `set_integral_value`).

    **Arguments:** `kp`, `ki`, `kd` (vectors of size nq, or scalars for nq = 1);
    `state_projection` $P_x$ (2 nq, n_in), identity by default; `output_projection` $P_y$
    (n_out, nq), identity by default; `sample_time`: None (continuous) or h.

    Its two input ports are wired one by one (`jd.feedback` feeds a single vector), e.g. a
    pendulum held at the set point the diagram's input gives::

        pid = jd.PidController(kp=20.0, ki=5.0, kd=4.0)
        builder = jd.DiagramBuilder()
        builder.add(jd.models.Pendulum(), "plant"); builder.add(pid, "pid")
        builder.connect("plant", ("pid", pid.input_port("estimated_state")))
        builder.connect("pid", "plant")
        builder.export_input(("pid", pid.input_port("desired_state")))   # x_d = (q_d, v_d)
        builder.export_output("plant")
        loop = builder.build("PendulumPid")
        jd.simulate(loop, (0.0, 10.0), inputs=lambda t: jnp.array([0.5, 0.0]))
    """

    def __init__(self, kp, ki, kd, *, state_projection=None, output_projection=None,
                 sample_time: float | None = None):
        kp = _vector(kp, "kp", "PidController")
        nq = kp.shape[0]
        ki, kd = (_vector(k, label, "PidController", nq) for k, label in ((ki, "ki"), (kd, "kd")))
        xp = array_module(kp, ki, kd, state_projection, output_projection)
        Px = xp.eye(2 * nq) if state_projection is None else xp.atleast_2d(xp.asarray(state_projection, float))
        Py = xp.eye(nq) if output_projection is None else xp.atleast_2d(xp.asarray(output_projection, float))
        if Px.ndim != 2 or Px.shape[0] != 2 * nq:
            raise ValueError(f"PidController: state_projection must have {2 * nq} rows (2 x the {nq} gains), "
                             f"got shape {Px.shape}")
        if Py.ndim != 2 or Py.shape[1] != nq:
            raise ValueError(f"PidController: output_projection must have {nq} columns (one per gain), "
                             f"got shape {Py.shape}")
        error = xp.concatenate([-Px, xp.eye(2 * nq)], axis=1)  # e = x_d - P_x x_in
        e_q, e_v = error[:nq], error[nq:]
        h = None if sample_time is None else _period(sample_time, "sample_time", "PidController")
        A, B = (np.zeros((nq, nq)), e_q) if h is None else (np.eye(nq), h * e_q)
        super().__init__(A, B, Py * ki, Py @ (kp[:, None] * e_q + kd[:, None] * e_v), sample_time=h,
                         input_frame=port_frame("PidControllerInput",
                                                [("estimated_state", Px.shape[1]), ("desired_state", 2 * nq)]))

    def input_port(self, port: int | str) -> tuple[str, ...]:
        """The coordinate names of `"estimated_state"` (0) or `"desired_state"` (1), for
        `DiagramBuilder.connect`."""
        return port_coordinates(self.input_frame, port)
