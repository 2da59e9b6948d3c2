"""Quadrotors (Underactuated ch. 3): the planar one and Drake's 3-D `QuadrotorPlant`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..multibody import rpy
from ..systems import Frame, System


class PlanarQuadrotor(System):
    r"""The planar quadrotor: a rigid body of mass m and inertia I in the vertical x-y plane,
    two rotors at distance r from the centre pushing along the body's up axis:

    $$m\ddot x = -(u_1 + u_2)\sin\theta,\quad m\ddot y = (u_1 + u_2)\cos\theta - m g,\quad
      I\ddot\theta = r(u_1 - u_2).$$

    State $[x, y, \theta, \dot x, \dot y, \dot\theta]$; defaults are Drake's `Quadrotor2D`
    (m = 0.486 kg, r = 0.25 m, I = 0.00383 kg m^2)."""

    m: float
    r: float
    I: float
    g: float

    def __init__(self, m=0.486, r=0.25, I=0.00383, g=9.81, *, input_limits=None):
        self.m, self.r, self.I, self.g = m, r, I, g
        state = Frame("PlanarQuadrotorState", ("x", "y", "theta", "xdot", "ydot", "thetadot"))
        super().__init__(num_continuous_states=6, num_inputs=2, direct_feedthrough=False,
                         time_invariant=True, input_limits=input_limits, state_frame=state,
                         output_frame=state, input_frame=Frame("PlanarQuadrotorInput", ("u1", "u2")))

    def dynamics(self, t, x, u):
        theta, thrust = x[2], u[0] + u[1]
        return jnp.stack([x[3], x[4], x[5], -thrust * jnp.sin(theta) / self.m,
                          thrust * jnp.cos(theta) / self.m - self.g, self.r * (u[0] - u[1]) / self.I])


class Quadrotor(System):
    r"""Drake's `QuadrotorPlant`: a rigid body (mass m, inertia I) with four rotors at distance
    L on the body's +x, +y, -x, -y axes (rotors 0, 1, 2, 3), each giving thrust $k_F u_i$
    along the body z axis and a drag moment $\pm k_M u_i$ about it (rotors 0 and 2 one way,
    1 and 3 the other):

    $$m\ddot p = R\,[0, 0, k_F \textstyle\sum u_i]^T - m g e_z,\qquad
      I\dot\omega_B + \omega_B \times I\omega_B = \tau_B,\quad
      \tau_B = [L k_F(u_1 - u_3),\ L k_F(u_2 - u_0),\ k_M(u_0 - u_1 + u_2 - u_3)].$$

    State $[x, y, z, \phi, \theta, \psi, \dot x, \dot y, \dot z, \dot\phi, \dot\theta, \dot\psi]$
    (roll, pitch, yaw with R = Rz(psi) Ry(theta) Rx(phi), and their rates), Drake's order and
    defaults (m = 0.775 kg, L = 0.15 m, I = diag(0.0015, 0.0025, 0.0035) kg m^2, kF = 1,
    kM = 0.0245). The rpy accelerations come from the angular acceleration by differentiating
    $\omega = M(\text{rpy})\,\dot{\text{rpy}}$ (autodiff, no hand-written Jacobian).

    At gimbal lock ($|\cos\theta| < 0.008$, pitch within 0.458 degrees of $\pm 90$ degrees, Drake's
    tolerance) M is singular and the rpy accelerations are undefined: as Drake's
    `QuadrotorPlant`, `dynamics` raises there (a `ValueError`) when called with concrete values;
    inside `jit` / `vmap` it returns NaN, so that `simulate` ends with a failure status (and,
    outside `jit`, a `SimulationError` naming gimbal lock)."""

    GIMBAL_LOCK_COS_PITCH = 0.008  # Drake's RollPitchYaw kGimbalLockToleranceCosPitchAngle

    m: float
    L: float
    I: jax.Array
    kF: float
    kM: float
    g: float

    def __init__(self, m=0.775, L=0.15, I=None, kF=1.0, kM=0.0245, g=9.81, *, input_limits=None):
        self.m, self.L, self.kF, self.kM, self.g = m, L, kF, kM, g
        self.I = jnp.diag(jnp.array([0.0015, 0.0025, 0.0035])) if I is None else jnp.asarray(I)
        state = Frame("QuadrotorState", ("x", "y", "z", "roll", "pitch", "yaw", "xdot", "ydot", "zdot",
                                         "rolldot", "pitchdot", "yawdot"))
        super().__init__(num_continuous_states=12, num_inputs=4, direct_feedthrough=False,
                         time_invariant=True, input_limits=input_limits, state_frame=state,
                         output_frame=state, input_frame=Frame("QuadrotorInput", ("u0", "u1", "u2", "u3")))

    @staticmethod
    def _rates_to_world(angles, rates):
        """omega in world coordinates from the rpy rates: psi' z + theta' Rz y + phi' Rz Ry x."""
        roll, pitch, yaw = angles
        Rz = rpy(0.0 * yaw, 0.0 * yaw, yaw)
        Rzy = rpy(0.0 * yaw, pitch, yaw)
        M = jnp.stack([Rzy[:, 0], Rz[:, 1], jnp.array([0.0, 0.0, 1.0], dtype=angles.dtype)], axis=1)
        return M @ rates, M

    def dynamics(self, t, x, u):
        x = jnp.asarray(x)
        pitch = x[4]
        if not isinstance(pitch, jax.core.Tracer) and self._at_gimbal_lock(pitch):
            raise ValueError(f"{self.name}.dynamics: {self._gimbal_lock_message(pitch)}")
        locked = jnp.abs(jnp.cos(pitch)) < self.GIMBAL_LOCK_COS_PITCH
        x = x.at[4].set(jnp.where(locked, 0.0, pitch))  # finite derivatives where it is not locked
        return jnp.where(locked, jnp.nan, self._dynamics(x, u))

    def failure_hint(self, x):
        """Names gimbal lock when the last state before a failed step is within a degree of it."""
        pitch = np.asarray(x, float)[4]
        if np.isfinite(pitch) and abs(np.cos(pitch)) < np.sin(np.radians(1.0)):
            return self._gimbal_lock_message(pitch)
        return None

    def _at_gimbal_lock(self, pitch):
        return abs(np.cos(float(pitch))) < self.GIMBAL_LOCK_COS_PITCH

    def _gimbal_lock_message(self, pitch):
        tolerance = np.degrees(np.arcsin(self.GIMBAL_LOCK_COS_PITCH))
        return (f"pitch = {np.degrees(float(pitch)):.6g} degrees is {'within' if self._at_gimbal_lock(pitch) else 'near'} "
                f"{tolerance:.6g} degrees of gimbal lock (+-90 degrees), where the roll-pitch-yaw rates are "
                "singular (Drake's QuadrotorPlant raises there too); keep the pitch away from +-90 degrees, "
                "or model the body with a quaternion (a floating-base RigidBodySystem)")

    def _dynamics(self, x, u):
        angles, rates = x[3:6], x[9:12]
        R = rpy(*angles)
        thrust = self.kF * u
        force = R @ jnp.stack([0.0 * thrust[0], 0.0 * thrust[0], jnp.sum(thrust)])
        accel = force / self.m - jnp.array([0.0, 0.0, self.g], dtype=x.dtype)
        torque = jnp.stack([self.L * (thrust[1] - thrust[3]), self.L * (thrust[2] - thrust[0]),
                            self.kM * (u[0] - u[1] + u[2] - u[3])])
        omega_world, M = self._rates_to_world(angles, rates)
        omega_body = R.T @ omega_world
        alpha_body = jnp.linalg.solve(self.I, torque - jnp.cross(omega_body, self.I @ omega_body))
        # omega_world' = M rates' + (dM/dt) rates  =>  rates' = M^-1 (R alpha_body - (dM/dt) rates)
        M_dot_rates = jax.jvp(lambda a: self._rates_to_world(a, rates)[0], (angles,), (rates,))[1]
        rates_dot = jnp.linalg.solve(M, R @ alpha_body - M_dot_rates)
        return jnp.concatenate([x[6:9], rates, accel, rates_dot])
