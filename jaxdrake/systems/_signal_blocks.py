r"""Drake's primitive blocks that are not linear systems: the sources `ConstantVectorSource`,
`Sine` and `RandomSource`, and `WrapToSystem` (the linear ones are in `_primitives.py`)."""

from __future__ import annotations

import enum

import jax
import jax.numpy as jnp
import jax.scipy.special as jss
import numpy as np

from .._numbers import array_module
from ._primitives import _period, _positive_int, _vector, port_coordinates, port_frame
from ._system import System, _static


class ConstantVectorSource(System):
    r"""Drake's `ConstantVectorSource`: no state, no input, $y = $ `source_value`.

    (An affine, not a linear, system: combined with others it makes a `Diagram`.)
    """

    source_value: jax.Array

    def __init__(self, source_value):
        self.source_value = value = _vector(source_value, "source_value", "ConstantVectorSource")
        super().__init__(num_outputs=value.shape[0], direct_feedthrough=False, time_invariant=True)

    def output(self, t, x, u):
        return self.source_value


class Sine(System):
    r"""Drake's `Sine`: $y = a \odot \sin(f \odot s + p)$ and its first two derivatives in s,

    $$[y_0; y_1; y_2] = [a \sin\phi;\ a f \cos\phi;\ -a f^2 \sin\phi], \qquad \phi = f \odot s + p,$$

    with s the time t (`is_time_based=True`, no input) or the input u. The three are Drake's
    output ports `y0`, `y1`, `y2`, stacked: `sine.output_port(k)` names one's coordinates
    for `DiagramBuilder.connect`.

    **Arguments:** `amplitude`, `frequency` (rad/s), `phase` (rad): scalars with `size`, or
    vectors; `is_time_based`.
    """

    amplitude: jax.Array
    frequency: jax.Array
    phase: jax.Array
    is_time_based: bool = _static()

    def __init__(self, amplitude, frequency, phase, size: int | None = None, is_time_based: bool = True):
        xp = array_module(amplitude, frequency, phase)
        values = [xp.atleast_1d(xp.asarray(v, dtype=float)) for v in (amplitude, frequency, phase)]
        sizes = {v.shape[0] for v in values if v.shape != (1,)} | (
            set() if size is None else {_positive_int(size, "size", "Sine")})
        if any(v.ndim != 1 for v in values) or len(sizes) > 1:
            raise ValueError("Sine: amplitude, frequency and phase must be scalars or vectors of one size "
                             f"(and agree with size={size}), got shapes {[v.shape for v in values]}")
        n = sizes.pop() if sizes else 1
        self.amplitude, self.frequency, self.phase = (xp.broadcast_to(v, (n,)) for v in values)
        self.is_time_based = bool(is_time_based)
        super().__init__(num_inputs=0 if self.is_time_based else n, num_outputs=3 * n,
                         direct_feedthrough=not self.is_time_based, time_invariant=not self.is_time_based,
                         output_frame=port_frame("SineOutput", [(f"y{k}", n) for k in range(3)]))

    def output(self, t, x, u):
        a, f = self.amplitude, self.frequency
        phi = f * (t if self.is_time_based else u) + self.phase
        return jnp.concatenate([a * jnp.sin(phi), a * f * jnp.cos(phi), -a * f**2 * jnp.sin(phi)])

    def output_port(self, port: int | str) -> tuple[str, ...]:
        """The coordinate names of output port `port` (`k` or `"y{k}"`), for `DiagramBuilder.connect`."""
        return port_coordinates(self.output_frame, port)


class RandomDistribution(enum.Enum):
    r"""Drake's `RandomDistribution`: what a `RandomSource` draws. Each member owns its map
    from a standard normal sample w (the inverse-CDF transform, exact in distribution):
    `uniform` on [0, 1), $\Phi(w)$; `gaussian` N(0, 1), w; `exponential` with rate 1,
    $-\log(1 - \Phi(w)) = -\log\Phi(-w)$."""

    uniform = "uniform"
    gaussian = "gaussian"
    exponential = "exponential"

    def from_standard_normal(self, w):
        if self is RandomDistribution.uniform:
            return jss.ndtr(w)
        if self is RandomDistribution.exponential:
            return -jss.log_ndtr(-w)
        return w


class RandomSource(System):
    r"""Drake's `RandomSource`: independent samples of `distribution`, drawn every
    `sampling_interval_sec` seconds and held in between (y is constant on $[kh, (k+1)h)$).

    A stochastic system without state: its output reads noise samples w held on the same
    intervals, drawn from the key given to `simulate(..., key=key)` as a function of (key, k)
    only (the conventions of `StochasticSystem`), so a key always gives the same path and
    `jax.vmap` over keys gives a Monte-Carlo batch. `output(t, x, u)` is the nominal signal,
    the distribution's median (w = 0).

    **Arguments:** `distribution` (a `RandomDistribution` or its name), `num_outputs`,
    `sampling_interval_sec` (h).
    """

    distribution: RandomDistribution = _static()

    def __init__(self, distribution: RandomDistribution | str, num_outputs: int, sampling_interval_sec: float):
        try:
            self.distribution = RandomDistribution(distribution)
        except ValueError:
            raise ValueError(f"RandomSource: unknown distribution {distribution!r}; use one of "
                             f"{[d.value for d in RandomDistribution]}") from None
        n = _positive_int(num_outputs, "num_outputs", "RandomSource")
        h = _period(sampling_interval_sec, "sampling_interval_sec", "RandomSource")
        super().__init__(num_outputs=n, direct_feedthrough=False, noise_groups=((n, h, 1.0),))

    @property
    def sampling_interval_sec(self) -> float:
        return self.noise_groups[0][1]

    def output(self, t, x, u):
        return self.distribution.from_standard_normal(jnp.zeros(self.num_outputs, jnp.asarray(x).dtype))

    def mode_output(self, mode, t, x, u):
        return self.distribution.from_standard_normal(u[self.num_inputs:])


class WrapToSystem(System):
    r"""Drake's `WrapToSystem`: y = u, except that each element i given an interval
    $[l_i, h_i)$ is wrapped into it, $y_i = u_i - (h_i - l_i)\lfloor (u_i - l_i) / (h_i - l_i) \rfloor$
    (an angle into $[-\pi, \pi)$, say). No state; $\partial y / \partial u = I$ between wraps.

    **Arguments:** `input_size`; `intervals`: `{index: (low, high)}`. Drake's
    `set_interval(index, low, high)` is `with_interval`, which returns a new system.
    """

    low: jax.Array
    high: jax.Array
    wrapped: tuple[int, ...] = _static()

    def __init__(self, input_size: int, intervals: dict | None = None):
        n = _positive_int(input_size, "input_size", "WrapToSystem")
        intervals = dict(intervals or {})
        for index, (low, high) in intervals.items():
            if not isinstance(index, (int, np.integer)) or not 0 <= index < n:
                raise IndexError(f"WrapToSystem: index {index!r} is out of range for input_size {n}")
            concrete = not any(isinstance(v, jax.core.Tracer) for v in (low, high))
            if concrete and not (np.isfinite(low) and np.isfinite(high) and low < high):
                raise ValueError(f"WrapToSystem: the interval of element {index} needs finite low < high, "
                                 f"got ({low}, {high})")
        self.wrapped = tuple(sorted(int(i) for i in intervals))
        xp = array_module(*[v for pair in intervals.values() for v in pair])
        self.low, self.high = (xp.asarray([intervals[i][k] for i in self.wrapped], dtype=float) for k in (0, 1))
        super().__init__(num_inputs=n, num_outputs=n, direct_feedthrough=True, time_invariant=True)

    @property
    def intervals(self) -> dict:
        """`{index: (low, high)}` of the wrapped elements."""
        return {i: (self.low[k], self.high[k]) for k, i in enumerate(self.wrapped)}

    def with_interval(self, index: int, low, high) -> "WrapToSystem":
        """A copy that also wraps element `index` into [low, high) (Drake's `set_interval`;
        a later interval for the same index replaces the earlier)."""
        return WrapToSystem(self.num_inputs, {**self.intervals, index: (low, high)})

    def output(self, t, x, u):
        if not self.wrapped:
            return u
        index = np.asarray(self.wrapped)
        v, width = u[index], self.high - self.low
        return u.at[index].set(v - width * jnp.floor((v - self.low) / width))
