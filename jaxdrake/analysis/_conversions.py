r"""Conversions of systems into (rational) polynomial systems (notes, D.3.1), for SOS analysis.

- `taylor_polynomial_system`: the Taylor polynomial of the dynamics (and output) in (x, u)
  about a point, by autodiff.
- `trig_polynomial_system`: the change of coordinates $q \mapsto (s, c) = (\sin q, \cos q)$ for
  chosen angles, with the algebraic constraint $s^2 + c^2 = 1$ carried as a state constraint.
  A `RigidBodySystem` becomes the rational polynomial system
  $\mathrm{blockdiag}(I, H(s, c))\,\dot x = [\,\dots;\ B u - C\dot q - G - D\dot q\,]$.
  The polynomials are found by least squares on the reduced monomial basis (at most degree 1
  in each c, which is unique modulo $s^2 + c^2 = 1$) and verified at fresh random points: a
  dynamics that is not a trigonometric polynomial of the given degree is an error, never a
  silent approximation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..multibody import RigidBodySystem
from ..polynomials import Polynomial, monomial_basis, taylor_polynomial
from ..systems import Frame, PolynomialSystem, System


def taylor_polynomial_system(system: System, x0, u0=None, degree: int = 3) -> PolynomialSystem:
    r"""The polynomial system whose f and g are the degree-`degree` Taylor polynomials of the
    system's dynamics (or discrete update) and output in $(x, u)$ about $(x_0, u_0)$."""
    if system.is_hybrid or system.is_stochastic or (system.num_discrete_states and system.num_continuous_states):
        raise ValueError(f"taylor_polynomial_system: {system.name} must be purely continuous or "
                         "purely discrete, and neither hybrid nor stochastic")
    n, m = system.num_states, system.num_inputs
    x0 = jnp.asarray(x0, float).reshape(-1)
    u0 = jnp.zeros(m) if u0 is None else jnp.asarray(u0, float).reshape(-1)
    if x0.shape != (n,) or u0.shape != (m,):
        raise ValueError(f"x0 must have shape ({n},) and u0 ({m},); got {x0.shape} and {u0.shape}")
    names = _names(system, n, m)
    point = jnp.concatenate([x0, u0])
    with jax.enable_x64(True):  # coefficients in float64 whatever the user's default
        f = taylor_polynomial(_step_at, point.astype(jnp.float64), degree, names, args=(system,))
        g = taylor_polynomial(_output_at, point.astype(jnp.float64), degree, names, args=(system,))
    return PolynomialSystem(f, g, sample_time=system.sample_time, input_frame=system.input_frame,
                            state_frame=system.state_frame, output_frame=system.output_frame)


def _step_at(z, system):
    n = system.num_states
    step = system.update if system.num_discrete_states else system.dynamics
    return step(0.0, z[:n], z[n:])


def _output_at(z, system):
    n = system.num_states
    return system.output(0.0, z[:n], z[n:])


def _names(system, n, m):
    state = system.state_frame.coordinates if system.state_frame else [f"x{i}" for i in range(n)]
    inputs = system.input_frame.coordinates if system.input_frame else [f"u{i}" for i in range(m)]
    return tuple(state) + tuple(inputs)


def to_trig_coordinates(x, angles) -> jnp.ndarray:
    """The state with each angle $q_i$ (indices `angles`) replaced by $(\\sin q_i, \\cos q_i)$."""
    x = jnp.asarray(x, float)
    parts = []
    for i in range(x.shape[-1]):
        parts += [jnp.sin(x[..., i]), jnp.cos(x[..., i])] if i in set(angles) else [x[..., i]]
    return jnp.stack(parts, -1)


def _fit(fn, angles, n, m, degree, rng, what):
    """The polynomial in the trig coordinates (and u) equal to fn(x, u) -> array."""
    k = len(angles)
    num_new = n + k + m
    new_angle_pos = _trig_positions(n, angles)
    basis = monomial_basis(num_new, degree)
    cos_columns = [c for _, c in new_angle_pos]
    basis = basis[np.all(basis[:, cos_columns] <= 1, axis=1)]  # reduced modulo s^2 + c^2 = 1

    def sample(count):
        x = rng.normal(size=(count, n)) * 1.5
        x[:, list(angles)] = rng.uniform(-np.pi, np.pi, size=(count, k))
        return x, rng.normal(size=(count, m))

    # in float64 even when the user runs float32: this is host-side analysis
    def features(x, u):
        with jax.enable_x64(True):
            z = np.asarray(to_trig_coordinates(x, angles))
        return Polynomial(basis, np.zeros(len(basis))).monomials(np.concatenate([z, u], axis=1))

    def values(x, u):
        with jax.enable_x64(True):
            return np.asarray(jax.jit(jax.vmap(fn))(jnp.asarray(x), jnp.asarray(u)))

    x, u = sample(4 * len(basis) + 20)
    target = values(x, u)
    shape = target.shape[1:]
    coefficients, *_ = np.linalg.lstsq(features(x, u), target.reshape(len(x), -1), rcond=None)
    x, u = sample(200)
    check = values(x, u).reshape(len(x), -1)
    error = np.abs(features(x, u) @ coefficients - check).max() / max(1.0, np.abs(check).max())
    if error > 1e-8:
        raise ValueError(f"trig_polynomial_system: {what} is not a polynomial of degree <= {degree} in "
                         f"sin/cos of the angles {list(angles)} and the other states and inputs "
                         f"(relative fit error {error:.1e}); raise `degree` or check `angles`")
    coefficients[np.abs(coefficients) < 1e-10 * max(1.0, np.abs(coefficients).max())] = 0.0
    return Polynomial(basis, coefficients.reshape((len(basis),) + shape)).pruned()


def _trig_positions(n, angles):
    """(s index, c index) in the new state of each angle, in the order of `angles`."""
    positions, offset = {}, 0
    for i in range(n):
        if i in set(angles):
            positions[i] = (i + offset, i + offset + 1)
            offset += 1
    return [positions[i] for i in angles]


def trig_polynomial_system(system: System, angles, degree: int = 3) -> PolynomialSystem:
    r"""The system in coordinates where each angle $q_i$ (state indices `angles`) is replaced by
    $(s_i, c_i) = (\sin q_i, \cos q_i)$, so $\dot s_i = c_i \dot q_i$, $\dot c_i = -s_i\dot q_i$,
    with the state constraints $s_i^2 + c_i^2 - 1 = 0$. The remaining dynamics must be
    trigonometric polynomials (degree <= `degree`) in the angles and polynomial in the other
    states and the inputs -- true of pendulums and, after multiplying by the mass matrix, of
    rigid-body systems with revolute joints, which come back rational: $e = \mathrm{blockdiag}(I, H)$.
    """
    if system.num_discrete_states or system.is_hybrid or system.is_stochastic:
        raise ValueError("trig_polynomial_system: needs a continuous-time, non-hybrid, deterministic system")
    n, m = system.num_states, system.num_inputs
    angles = [int(i) for i in angles]
    if len(set(angles)) != len(angles) or any(not 0 <= i < n for i in angles):
        raise ValueError(f"angles must be distinct state indices in [0, {n}), got {angles}")
    rng = np.random.default_rng(0)
    rigid = isinstance(system, RigidBodySystem)
    nq = system.num_positions if rigid else 0
    if rigid:
        def split(x):
            return x[:nq], x[nq:]

        rhs = _fit(lambda x, u: system.manipulator_dynamics(*split(x))[0]
                   @ system.forward_dynamics(*split(x), u), angles, n, m, degree, rng, "H(q) qdd")
        H = _fit(lambda x, u: system.manipulator_dynamics(*split(x))[0], angles, n, m, degree, rng, "H(q)")
        qdot = _fit(lambda x, u: system.dynamics(0.0, x, u)[:nq], angles, n, m, degree, rng, "qdot")
        f_rows = [qdot[i] for i in range(nq)] + [rhs[i] for i in range(n - nq)]
    else:
        f_all = _fit(lambda x, u: system.dynamics(0.0, x, u), angles, n, m, degree, rng, "the dynamics")
        f_rows = [f_all[i] for i in range(n)]
    k = len(angles)
    num_new = n + k + m
    z = Polynomial.variables_of(num_new)
    positions = dict(zip(angles, _trig_positions(n, angles)))
    rows = []
    for i in range(n):
        if i in positions:
            s, c = positions[i]
            rows += [z[c] * f_rows[i], -(z[s] * f_rows[i])]
        else:
            rows.append(f_rows[i])
    names = _trig_names(system, n, m, angles)
    f = _vector(rows, names)
    constraints = _vector([z[s] * z[s] + z[c] * z[c] - 1.0 for s, c in positions.values()], names)
    e = None
    if rigid:
        size = n + k
        eye = Polynomial(np.zeros((1, num_new), int), np.eye(size)[None], names)
        H_block = Polynomial(H.exponent_array, np.pad(np.asarray(H.coefficients), ((0, 0), (size - (n - nq), 0),
                                                                                    (size - (n - nq), 0))), names)
        corner = np.zeros((size, size))
        corner[size - (n - nq):, size - (n - nq):] = np.eye(n - nq)
        e = eye - Polynomial(np.zeros((1, num_new), int), corner[None], names) + H_block
    state = Frame(f"{system.name}TrigState", names[:n + k])
    return PolynomialSystem(f, None, e, constraints, input_frame=system.input_frame, state_frame=state,
                            output_frame=state)


def _trig_names(system, n, m, angles):
    base = _names(system, n, m)
    names = []
    for i in range(n):
        names += [f"s_{base[i]}", f"c_{base[i]}"] if i in set(angles) else [base[i]]
    return tuple(names) + base[n:]


def _vector(rows, names):
    """Scalar polynomials (same variables) as one vector polynomial with the given names."""
    total = None
    for i, row in enumerate(rows):
        unit = np.eye(len(rows))[i]
        term = Polynomial(row.exponent_array, np.asarray(row.coefficients)[:, None] * unit, names)
        total = term if total is None else total + term
    return total
