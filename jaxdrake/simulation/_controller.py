"""Step-size controllers: the initial step and the adaptation after each attempt (the roles of
Diffrax's `PIDController` / `ConstantStepSize`)."""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp


def rms(v):
    """Root mean square of a vector (0 for an empty one)."""
    return jnp.sqrt(jnp.mean(v * v)) if v.shape[0] else jnp.zeros((), v.dtype)


def carries_low_part(dtype) -> bool:
    """Whether the loop carries time as a pair $t + t_{low}$ (`advance`): in float32, whose
    spacing of t (3e-8 s at t = 0.3 s) is coarser than the steps in which a contact goes
    from sliding to sticking (float64 takes ~2e-9 s there). Without it a 1-kg cube dropped
    flat while sliding stopped with STEP_SIZE_TOO_SMALL in float32; float64 needs no pair."""
    return jnp.finfo(dtype).bits < 64


def advance(t, t_low, h):
    r"""The time $(t + t_{low}) + h$ as a pair: t the largest float at or below the sum and
    $0 \le t_{low}$ < t's spacing the rest (Knuth's two-sum, exact in floating point; the
    rest's own rounding, ~eps^2 t, where t steps down), so that a step shorter than t's
    spacing still moves time, and t read alone (a breakpoint, a sample instant, tf) is never
    past it. `(t + h, 0)` where time is one number (`carries_low_part`). The rest is held
    under differentiation: t carries all of time's derivative."""
    if not carries_low_part(t.dtype):
        return t + h, jnp.zeros_like(t)
    b = t_low + h
    total = t + b
    b_part = total - t
    low = (t - (total - b_part)) + (b - b_part)
    held = jax.lax.stop_gradient(total)
    gap = held - jnp.nextafter(held, jnp.asarray(-jnp.inf, held.dtype))   # to the float below, exactly
    below = low < 0
    return jnp.where(below, total - gap, total), jax.lax.stop_gradient(jnp.where(below, low + gap, low))


def elapsed(t0, low0, t1, low1):
    """The exact time from the pair (t0, low0) to (t1, low1): a step's size."""
    return (t1 - t0) + (low1 - low0)


def time_resolution(t, low_part: bool = False):
    """The spacing of time: eps |t|, or eps^2 |t| where the loop carries it as a pair
    (`low_part` in float32, `carries_low_part`); at least the smallest normal number."""
    finfo = jnp.finfo(t.dtype)
    pair = low_part and carries_low_part(t.dtype)
    return jnp.maximum(finfo.eps * jnp.abs(t) * (finfo.eps if pair else 1.0), finfo.tiny)


def least_step(t, low_part: bool = False):
    """The smallest step an adaptive simulation attempts: one unit of the spacing of time
    (`time_resolution`; with `low_part`, `simulate`'s loop where steps may go below t's
    spacing, time's as the loop carries it). A smaller one would not move t: a zero step,
    accepted and grown from zero, on which the loop would spin until max_steps."""
    return time_resolution(t, low_part)


def smallest_step(t, finite, low_part: bool = False):
    """The step size at or below which a rejected step ends an adaptive simulation: for a
    finite attempt 16 units of the spacing of time (`time_resolution`; MATLAB's `16*eps(t)`;
    SciPy's `solve_ivp` likewise scales its floor with t), far below any physical step (in
    float64 a lower floor let a finite-time blow-up step on past its pole instead of
    stopping there). Where float32 time is one number (`simulate_ensemble`; a vector field
    that reads t) the floor is 2 units, since a touchdown needs steps of 3-5. For a
    non-finite attempt 16 eps max(|t|, 1), then NONFINITE_STATE: a NaN or overflow that
    persists down to such steps is the vector field's, and near t = 0 the relative floor
    would take hundreds of rejections to say so."""
    finfo = jnp.finfo(t.dtype)
    units = 16 if (finfo.bits >= 64 or (low_part and carries_low_part(t.dtype))) else 2
    return jnp.where(finite, units * time_resolution(t, low_part), 16 * finfo.eps * jnp.maximum(jnp.abs(t), 1.0))


class AbstractStepSizeController(eqx.Module):
    """Chooses step sizes: `initial_step(t0, y0, k0)` from the first stage $k_0 = f(t_0, y_0)$,
    and `adapt(h, y0, y1, error, finite)` -> `(accept, h_next, error_norm)` after an attempt."""

    @abc.abstractmethod
    def initial_step(self, t0, y0, k0):
        ...

    @abc.abstractmethod
    def adapt(self, h, y0, y1, error, finite):
        ...


class ConstantStepSize(AbstractStepSizeController):
    """A fixed step `dt`: every finite step is accepted."""

    dt: jax.Array

    def initial_step(self, t0, y0, k0):
        return self.dt

    def adapt(self, h, y0, y1, error, finite):
        return finite, self.dt, jnp.zeros((), y0.dtype)


class IController(AbstractStepSizeController):
    r"""The standard integral controller (Hairer, Norsett & Wanner, *Solving ODEs I*, II.4).

    Error norm $\|e\| = \mathrm{rms}(e_i / (atol + rtol \max(|y_{0,i}|, |y_{1,i}|)))$; a step
    is accepted when $\|e\| \le 1$ and the next is $h\,\mathrm{clip}(0.9\|e\|^{-1/q}, 0.2, 10)$
    with q = `error_order` + 1. The initial step is the first half of Hairer's heuristic,
    $h_0 = 0.01\, d_0 / d_1$ with $d_0 = \mathrm{rms}(y_0 / s)$, $d_1 = \mathrm{rms}(k_0 / s)$
    ($10^{-6}$ when either is below $10^{-5}$): it needs only $k_0$, the method's own first
    stage, so the vector field is not evaluated for it; the controller grows a small first
    step by up to 10x per step.
    """

    rtol: jax.Array
    atol: jax.Array
    error_order: int = eqx.field(static=True)

    def initial_step(self, t0, y0, k0):
        scale = self.atol + self.rtol * jnp.abs(y0)
        d0, d1 = rms(y0 / scale), rms(k0 / scale)
        small = (d0 < 1e-5) | (d1 < 1e-5)
        return jax.lax.stop_gradient(jnp.where(small, 1e-6, 0.01 * d0 / jnp.where(small, 1.0, d1)))

    def adapt(self, h, y0, y1, error, finite):
        scale = self.atol + self.rtol * jnp.maximum(jnp.abs(y0), jnp.abs(y1))
        error_norm = jax.lax.stop_gradient(rms(error / scale))
        q = self.error_order + 1
        factor = jnp.where(error_norm > 0, 0.9 * jnp.where(error_norm > 0, error_norm, 1) ** (-1.0 / q), 10.0)
        factor = jnp.where(finite, jnp.clip(factor, 0.2, 10.0), 0.2)
        return finite & (error_norm <= 1), h * factor, error_norm
