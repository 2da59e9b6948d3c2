r"""The extended and unscented Kalman filters, as discrete systems at a period $h$.

They filter the plant's discrete-time model with additive noise,

$$x_{k+1} = \Phi_h(t_k, x_k, u_k) + w_k, \qquad y_k = g(t_k, x_k, u_k) + v_k, \qquad
  w_k \sim N(0, W),\ v_k \sim N(0, V),$$

where $\Phi_h$ is the plant's update (a discrete plant, $h$ its period) or `discrete_step`'s
integration of its dynamics over $h$ with $u$ held (a continuous plant; white noise of
spectral density $W_c$ gives $W \approx W_c h$). `W` and `V` are covariances per sample, as
a discrete `StochasticSystem` draws $w[n] \sim N(0, I)$ per sample.

The filter's state is the prior $[\hat x_{k|k-1};\ \mathrm{vec}\,P_{k|k-1}]$ (row-major $P$);
its input $[u; y]$, its output $\hat x_{k|k-1}$ (no direct feedthrough, so it closes a loop
with a static controller). At each sample it *corrects* with $y_k$, then *predicts* with
$u_k$ -- the order of the steady-state discrete filter, to which both tend on a linear plant.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..simulation import FIXED_STEP_RULES, discrete_step
from ..systems import Frame, System
from ._checks import as_matrix, check_covariance, check_plant
from ._linalg import cholesky, solve_positive_definite
from ._observer import estimate_frame, observer_input_frame


class _DiscreteGaussianFilter(System):
    """What the EKF and the UKF share: the model, the noise, the state layout and the step
    `update` = `correct` then `predict` (each filter defines those two)."""

    plant: System
    W: jax.Array
    V: jax.Array
    x0: jax.Array
    P0: jax.Array
    rule: str = eqx.field(static=True)
    substeps: int = eqx.field(static=True)

    def __init__(self, plant, W, V, *, period, x0, P0, rule, substeps):
        caller = type(self).__name__
        check_plant(plant, caller, stochastic=False)
        n, p = plant.num_states, plant.num_outputs
        if plant.has_discrete_state:
            if period is not None and float(period) != plant.sample_time:
                raise ValueError(f"{caller}: {plant.name} is discrete with period {plant.sample_time}; "
                                 f"its filter runs at that period (leave period out), not {period}")
            period = plant.sample_time
        elif period is None:
            raise ValueError(f"{caller}: {plant.name} is continuous: give the filter's sample period "
                             "(period=...), over which its model is integrated")
        if rule not in FIXED_STEP_RULES or not (isinstance(substeps, (int, np.integer)) and substeps >= 1):
            raise ValueError(f"{caller}: rule must be one of {FIXED_STEP_RULES} and substeps a positive "
                             f"int, got {rule!r} and {substeps!r}")
        W = as_matrix(W, caller, "W", (n, n), "the process noise covariance per sample")
        V = as_matrix(V, caller, "V", (p, p), "the measurement noise covariance")
        P0 = np.eye(n) if P0 is None else as_matrix(P0, caller, "P0", (n, n), "the initial covariance")
        check_covariance(caller, "W", W, definite=False, meaning="the process noise covariance per sample")
        check_covariance(caller, "V", V, definite=True, meaning="the measurement noise covariance")
        check_covariance(caller, "P0", P0, definite=False, meaning="the initial covariance")
        x0 = plant.initial_state() if x0 is None else x0
        self.plant, self.rule, self.substeps = plant, rule, int(substeps)
        self.W, self.V, self.P0 = (jnp.asarray(M, float) for M in (W, V, P0))
        self.x0 = jnp.asarray(x0, float).reshape(n)
        covariance = tuple(f"P.{a}.{b}" for a in plant.state_frame.coordinates for b in plant.state_frame.coordinates)
        state = estimate_frame(plant)
        super().__init__(num_discrete_states=n + n * n, num_inputs=plant.num_inputs + p, num_outputs=n,
                         sample_time=period, direct_feedthrough=False, time_invariant=plant.time_invariant,
                         input_frame=observer_input_frame(plant),
                         state_frame=Frame(f"{caller}State", state.coordinates + covariance, generic=True),
                         output_frame=plant.state_frame)

    # ----- the model ---------------------------------------------------------------------

    def transition(self, t, x, u):
        r"""$\Phi_h(t, x, u)$: the plant's state one period later, u held."""
        return discrete_step(self.plant, t, x, u, self.sample_time, self.rule, self.substeps)

    def measurement(self, t, x, u):
        """$g(t, x, u)$: the plant's output."""
        return self.plant.output(t, x, u)

    # ----- the state ---------------------------------------------------------------------

    def estimate(self, z):
        r"""$\hat x$ from the filter's state (or a batch of them)."""
        return z[..., : self.plant.num_states]

    def covariance(self, z):
        """P from the filter's state (or a batch of them)."""
        n = self.plant.num_states
        return z[..., n:].reshape(z.shape[:-1] + (n, n))

    def initial_state(self):
        return jnp.concatenate([self.x0, self.P0.reshape(-1)])

    def update(self, t, z, input_output):
        u, y = jnp.split(input_output, [self.plant.num_inputs])
        x, P = self.correct(t, self.estimate(z), self.covariance(z), u, y)
        x, P = self.predict(t, x, P, u)
        return jnp.concatenate([x, ((P + P.T) / 2).reshape(-1)])

    def output(self, t, z, input_output):
        return self.estimate(z)


class ExtendedKalmanFilter(_DiscreteGaussianFilter):
    r"""The extended Kalman filter at a period: the Kalman filter of the model linearized
    (by `jax.jacfwd`) at the current estimate. With $C = \partial g / \partial x$ at
    $\hat x_{k|k-1}$ and $F = \partial \Phi_h / \partial x$ at $\hat x_{k|k}$:

    $$K = P C^T (C P C^T + V)^{-1},\quad \hat x_{k|k} = \hat x + K (y_k - g(\hat x)),\quad
      P_{k|k} = (I - KC) P (I - KC)^T + K V K^T,$$

    $$\hat x_{k+1|k} = \Phi_h(\hat x_{k|k}, u_k),\qquad P_{k+1|k} = F P_{k|k} F^T + W$$

    (Joseph's form keeps $P$ symmetric positive semidefinite).

    **Arguments:**

    - `plant`: a deterministic, non-hybrid system (continuous or discrete).
    - `W`: the process noise covariance per sample (n, n); `V`: the measurement noise
      covariance (p, p), positive definite.
    - `period`: the sample period (a discrete plant's own by default; required for a
      continuous one); `rule`, `substeps`: how `discrete_step` integrates a continuous plant
      over it (`"rk4"`, one step, by default).
    - `x0`, `P0`: the initial estimate and covariance (default: the plant's initial state and
      the identity).

    `estimate(z)` and `covariance(z)` read $\hat x$ and P from the filter's state z (of a
    simulation: `traj.state(t)`); `correct` and `predict` are the two stages of `update`.
    """

    def __init__(self, plant: System, W, V, *, period=None, x0=None, P0=None, rule: str = "rk4",
                 substeps: int = 1):
        super().__init__(plant, W, V, period=period, x0=x0, P0=P0, rule=rule, substeps=substeps)

    def correct(self, t, x, P, u, y):
        y_hat, C = _value_and_jacobian(lambda x: self.measurement(t, x, u), x)
        S = C @ P @ C.T + self.V
        K = solve_positive_definite(S, C @ P).T  # P C^T S^-1, S and P symmetric
        I_KC = jnp.eye(x.shape[0], dtype=x.dtype) - K @ C
        return x + K @ (y - y_hat), I_KC @ P @ I_KC.T + K @ self.V @ K.T

    def predict(self, t, x, P, u):
        x_next, F = _value_and_jacobian(lambda x: self.transition(t, x, u), x)
        return x_next, F @ P @ F.T + self.W


def _value_and_jacobian(fn, x):
    """(fn(x), dfn/dx) in one forward-mode pass."""
    return jax.jacfwd(lambda x: (fn(x), fn(x)), has_aux=True)(x)[::-1]


class UnscentedKalmanFilter(_DiscreteGaussianFilter):
    r"""The unscented Kalman filter at a period (Julier & Uhlmann 1997; the scaled sigma
    points of van der Merwe 2004, filterpy's `MerweScaledSigmaPoints`). With
    $\lambda = \alpha^2 (n + \kappa) - n$ and $S S^T = (n + \lambda) P$ (Cholesky), the
    $2n + 1$ sigma points are $\mathcal X_0 = \hat x$, $\mathcal X_{i} = \hat x + S_{:,i}$,
    $\mathcal X_{n+i} = \hat x - S_{:,i}$, with weights $w^m_0 = \lambda / (n + \lambda)$,
    $w^c_0 = w^m_0 + 1 - \alpha^2 + \beta$, $w^m_i = w^c_i = 1 / (2(n + \lambda))$.
    An unscented transform of a function through them gives a mean and a covariance:

    correct: $\mathcal Y_i = g(\mathcal X_i)$, $\hat y = \sum w^m_i \mathcal Y_i$,
    $S = \sum w^c_i (\mathcal Y_i - \hat y)(\cdot)^T + V$,
    $P_{xy} = \sum w^c_i (\mathcal X_i - \hat x)(\mathcal Y_i - \hat y)^T$,
    $K = P_{xy} S^{-1}$, $\hat x_{k|k} = \hat x + K (y_k - \hat y)$, $P_{k|k} = P - K S K^T$;

    predict: sigma points of $(\hat x_{k|k}, P_{k|k})$ through $\Phi_h$, then
    $\hat x_{k+1|k} = \sum w^m_i \Phi_h(\mathcal X_i)$,
    $P_{k+1|k} = \sum w^c_i (\Phi_h(\mathcal X_i) - \hat x_{k+1|k})(\cdot)^T + W$.

    **Arguments:** those of `ExtendedKalmanFilter`, and the sigma-point parameters `alpha`
    (spread, default 1), `beta` (prior knowledge of the distribution, 2 for a Gaussian) and
    `kappa` (default 0); $n + \lambda$ must be positive. (A small alpha, such as 1e-3,
    gives weights of order $1/\alpha^2$ whose cancellation costs precision, in float32
    above all.)
    """

    alpha: float = eqx.field(static=True)
    beta: float = eqx.field(static=True)
    kappa: float = eqx.field(static=True)

    def __init__(self, plant: System, W, V, *, period=None, x0=None, P0=None, alpha: float = 1.0,
                 beta: float = 2.0, kappa: float = 0.0, rule: str = "rk4", substeps: int = 1):
        super().__init__(plant, W, V, period=period, x0=x0, P0=P0, rule=rule, substeps=substeps)
        self.alpha, self.beta, self.kappa = float(alpha), float(beta), float(kappa)
        n = plant.num_states
        spread = self.alpha ** 2 * (n + self.kappa)
        if not (self.alpha > 0 and spread > 0 and np.isfinite(spread) and np.isfinite(self.beta)):
            raise ValueError(f"UnscentedKalmanFilter: the sigma points need alpha > 0 and "
                             f"n + lambda = alpha^2 (n + kappa) > 0, got alpha={alpha}, kappa={kappa} "
                             f"for n = {n}: raise kappa (kappa = 0 always works)")

    def weights(self, dtype=float):
        """(w^m, w^c), each of length 2n + 1."""
        n = self.plant.num_states
        spread = self.alpha ** 2 * (n + self.kappa)  # n + lambda
        first = (spread - n) / spread
        mean = jnp.full(2 * n + 1, 0.5 / spread, dtype).at[0].set(first)
        return mean, mean.at[0].set(first + 1 - self.alpha ** 2 + self.beta)

    def sigma_points(self, x, P):
        r"""(2n + 1, n): $\hat x$, then $\hat x \pm$ the columns of chol$((n + \lambda) P)$."""
        spread = self.alpha ** 2 * (self.plant.num_states + self.kappa)
        S = cholesky(spread * P)
        return jnp.concatenate([x[None], x + S.T, x - S.T])

    def correct(self, t, x, P, u, y):
        mean, cov = self.weights(x.dtype)
        points = self.sigma_points(x, P)
        Y = jax.vmap(lambda p: self.measurement(t, p, u))(points)
        y_hat = mean @ Y
        dX, dY = points - x, Y - y_hat
        S = (cov[:, None] * dY).T @ dY + self.V
        K = solve_positive_definite(S, (cov[:, None] * dY).T @ dX).T  # P_xy S^-1, S symmetric
        return x + K @ (y - y_hat), P - K @ S @ K.T

    def predict(self, t, x, P, u):
        mean, cov = self.weights(x.dtype)
        X = jax.vmap(lambda p: self.transition(t, p, u))(self.sigma_points(x, P))
        x_next = mean @ X
        dX = X - x_next
        return x_next, (cov[:, None] * dX).T @ dX + self.W
