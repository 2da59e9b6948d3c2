"""The same contact scene in pydrake's continuous MultibodyPlant (time_step 0, point contact), and
conversions between its state and ours (the test oracle for `test_contact.py`)."""

from __future__ import annotations

import numpy as np

from jaxdrake.geometry import Box, HalfSpace, Sphere


def drake_scene(urdf, world_geometries, stiction_tolerance):
    """(plant, diagram, context) of the URDF plus shapes on the world: (name, shape, R, p, material)."""
    from pydrake.all import (AddContactMaterial, AddMultibodyPlantSceneGraph, ContactModel, CoulombFriction,
                             DiagramBuilder, Parser, ProximityProperties, RigidTransform, RotationMatrix)
    from pydrake.geometry import Box as DBox, HalfSpace as DHalfSpace, Sphere as DSphere

    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlantSceneGraph(builder, 0.0)
    Parser(plant).AddModels(str(urdf))
    for name, shape, R, p, material in world_geometries:
        drake_shape = {Box: lambda s: DBox(s.x, s.y, s.z), Sphere: lambda s: DSphere(s.radius),
                       HalfSpace: lambda s: DHalfSpace()}[type(shape)](shape)
        props = ProximityProperties()
        mu_s, mu_d = material.friction()
        AddContactMaterial(material.hunt_crossley_dissipation, material.point_contact_stiffness,
                           CoulombFriction(mu_s, mu_d), props)
        plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform(RotationMatrix(np.asarray(R)), np.asarray(p)),
                                        drake_shape, name, props)
    plant.set_contact_model(ContactModel.kPoint)
    plant.set_stiction_tolerance(stiction_tolerance)
    plant.Finalize()
    diagram = builder.Build()
    return plant, diagram


class StateMap:
    """Our x = [q; v] <-> Drake's (a free body: quaternion w, x, y, z then position, velocities
    angular then linear in the world; ours: position then quaternion x, y, z, w, velocities
    linear then angular in the body frame), for any number of free bodies."""

    def __init__(self, plant, ours):
        tree = ours.tree
        self.nq = tree.nq
        self.joints, self.free = [], []
        for body, name, kind, qs, vs in zip(tree.body_names, tree.joint_names, tree.joint_types, tree.q_starts,
                                            tree.v_starts):
            if kind != "floating":
                joint = plant.GetJointByName(name)
                self.joints.append((qs, vs, joint.position_start(), joint.velocity_start()))
            else:
                drake_body = plant.GetBodyByName(body)
                self.free.append((qs, vs, drake_body.floating_positions_start(),
                                  drake_body.floating_velocities_start_in_v()))
        self.plant_nq, self.plant_nv = plant.num_positions(), plant.num_velocities()

    @staticmethod
    def _rotation(quat_xyzw):
        from pydrake.all import Quaternion
        x, y, z, w = quat_xyzw / np.linalg.norm(quat_xyzw)
        return Quaternion(w, x, y, z).rotation()

    def to_drake(self, x):
        x = np.asarray(x, float)
        q, v = x[: self.nq], x[self.nq:]
        qd, vd = np.zeros(self.plant_nq), np.zeros(self.plant_nv)
        for qs, vs, dq, dv in self.joints:
            qd[dq], vd[dv] = q[qs], v[vs]
        for qs, vs, fq, fv in self.free:
            R = self._rotation(q[qs + 3: qs + 7])
            qd[fq: fq + 7] = np.concatenate([[q[qs + 6]], q[qs + 3: qs + 6], q[qs: qs + 3]])
            vd[fv: fv + 6] = np.concatenate([R @ v[vs + 3: vs + 6], R @ v[vs: vs + 3]])
        return qd, vd

    def from_drake(self, qd, vd):
        q, v = np.zeros(self.nq), np.zeros(len(vd))
        for qs, vs, dq, dv in self.joints:
            q[qs], v[vs] = qd[dq], vd[dv]
        for qs, vs, fq, fv in self.free:
            quat = qd[fq: fq + 4]
            q[qs: qs + 7] = np.concatenate([qd[fq + 4: fq + 7], quat[1:], quat[:1]])
            R = self._rotation(q[qs + 3: qs + 7])
            w, lin = vd[fv: fv + 3], vd[fv + 3: fv + 6]
            v[vs: vs + 6] = np.concatenate([R.T @ lin, R.T @ w])
        return np.concatenate([q, v])

    def velocity_derivative_from_drake(self, x, vdot_drake):
        """Our v-dot from Drake's: for a free body, d/dt (R^T v_W) = R^T a_W - w_B x v_B."""
        x = np.asarray(x, float)
        v = x[self.nq:]
        out = np.zeros(len(v))
        for qs, vs, dq, dv in self.joints:
            out[vs] = vdot_drake[dv]
        for qs, vs, fq, fv in self.free:
            R = self._rotation(x[qs + 3: qs + 7])
            alpha, a = vdot_drake[fv: fv + 3], vdot_drake[fv + 3: fv + 6]
            out[vs: vs + 6] = np.concatenate([R.T @ a - np.cross(v[vs + 3: vs + 6], v[vs: vs + 3]), R.T @ alpha])
        return out


def drake_velocity_derivative(plant, diagram, state_map, x):
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyContextFromRoot(context)
    qd, vd = state_map.to_drake(x)
    plant.SetPositions(plant_context, qd)
    plant.SetVelocities(plant_context, vd)
    xdot = plant.EvalTimeDerivatives(plant_context).CopyToVector()
    return state_map.velocity_derivative_from_drake(x, xdot[plant.num_positions():])


def drake_simulate(plant, diagram, state_map, x0, times, accuracy=1e-11):
    """Our states at `times`, from Drake's simulation (error-controlled RK5 at `accuracy`)."""
    from pydrake.systems.analysis import ResetIntegratorFromFlags, Simulator

    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    plant_context = plant.GetMyContextFromRoot(context)
    qd, vd = state_map.to_drake(x0)
    plant.SetPositions(plant_context, qd)
    plant.SetVelocities(plant_context, vd)
    ResetIntegratorFromFlags(simulator, "runge_kutta5", 1e-4)
    simulator.get_mutable_integrator().set_target_accuracy(accuracy)
    simulator.Initialize()
    states = []
    for t in times:
        simulator.AdvanceTo(t)
        states.append(state_map.from_drake(plant.GetPositions(plant_context), plant.GetVelocities(plant_context)))
    return np.array(states)
