"""Rigid bodies from URDF: Featherstone's algorithms against Pinocchio and closed forms,
energy conservation, loop closures, gradients, and malformed URDFs."""

import importlib.metadata
import pathlib
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake import multibody as mb
from jaxdrake.models._rigid import URDF_DIR

pin = pytest.importorskip("pinocchio")
DATA = pathlib.Path(__file__).parent / "data"


def example_robot(relative):
    """A URDF from the installed example-robot-data package (no download)."""
    root = importlib.metadata.distribution("example-robot-data").locate_file(
        "cmeel.prefix/share/example-robot-data/robots")
    path = pathlib.Path(root) / relative
    if not path.exists():
        pytest.skip(f"example-robot-data has no {relative}")
    return path


ROBOTS = {  # name: (path, floating base)
    "double_pendulum": (lambda: URDF_DIR / "double_pendulum.urdf", False),
    "acrobot": (lambda: URDF_DIR / "acrobot.urdf", False),
    "cartpole": (lambda: URDF_DIR / "cartpole.urdf", False),
    "panda (7-dof arm + gripper)": (lambda: example_robot("panda_description/urdf/panda.urdf"), False),
    "ur5": (lambda: example_robot("ur_description/urdf/ur5_robot.urdf"), False),
    "solo12 (floating quadruped)": (lambda: example_robot("solo_description/robots/solo12.urdf"), True),
}


class PinocchioTwin:
    """The same URDF in Pinocchio, with maps between our coordinates and Pinocchio's
    (Pinocchio gives a continuous joint two coordinates, cos and sin)."""

    def __init__(self, path, tree):
        self.model = (pin.buildModelFromUrdf(str(path), pin.JointModelFreeFlyer()) if tree.has_floating_base
                      else pin.buildModelFromUrdf(str(path)))
        self.data = self.model.createData()
        self.tree = tree
        self.v_perm = []
        for name, kind in zip(tree.joint_names, tree.joint_types):
            joint = self.model.joints[1 if kind == "floating" else self.model.getJointId(name)]
            self.v_perm += list(range(joint.idx_v, joint.idx_v + joint.nv))
        self.v_perm = np.array(self.v_perm)

    def q(self, q):
        out = np.zeros(self.model.nq)
        for name, kind, s in zip(self.tree.joint_names, self.tree.joint_types, self.tree.q_starts):
            joint = self.model.joints[1 if kind == "floating" else self.model.getJointId(name)]
            i = joint.idx_q
            if kind == "floating":
                out[i: i + 7] = q[s: s + 7]
            elif joint.nq == 2:
                out[i: i + 2] = np.cos(q[s]), np.sin(q[s])
            else:
                out[i] = q[s]
        return out

    def v(self, v):
        out = np.zeros(self.model.nv)
        out[self.v_perm] = v
        return out

    def ours(self, vec):
        return np.asarray(vec)[self.v_perm]


def random_states(tree, n, seed):
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, (n, tree.nq))
    for s, kind in zip(tree.q_starts, tree.joint_types):
        if kind == "floating":
            q[:, s: s + 3] = rng.uniform(-1, 1, (n, 3))
            quat = rng.normal(size=(n, 4))
            q[:, s + 3: s + 7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    return q, rng.uniform(-2, 2, (n, tree.nv)), rng.uniform(-2, 2, (n, tree.nv))


def robot_data_root():
    try:
        return pathlib.Path(importlib.metadata.distribution("example-robot-data").locate_file(
            "cmeel.prefix/share/example-robot-data/robots"))
    except importlib.metadata.PackageNotFoundError:
        return None


# Every URDF shipped by example-robot-data is compared with Pinocchio (fixed base; the legged
# robots and humanoids with a floating base as well), except these, which are not valid trees:
NOT_TREES = {
    "hector_description/robots/quadrotor_base.urdf": "no movable joint",
    "iris_description/robots/iris_simple.urdf": "no movable joint",
    "ur_description/urdf/ur3.urdf": "no <robot> content (Pinocchio refuses it too)",
    "romeo_description/urdf/romeo_laas_small.urdf": "link 'body' has an inertia with a negative principal moment",
    "romeo_description/urdf/romeo_small.urdf": "link 'RShoulderYawLink' breaks the triangle inequality by ~5x "
                                               "(Drake refuses such inertias too)",
    "tiago_description/robots/tiago.urdf": "link 'base_antenna_left_link' has a negative principal moment",
    "tiago_description/robots/tiago_dual.urdf": "same antenna link as tiago.urdf",
    "tiago_description/robots/tiago_no_hand.urdf": "same antenna link as tiago.urdf",
    "talos_data/robots/talos_left_arm.urdf": "a <transmission> names a joint the file does not define",
    "romeo_description/urdf/romeo.urdf": "massless finger links at the ends of moving joints (H singular)",
}
FLOATING = ("a1_", "anymal", "b1_", "bolt", "go1", "go2", "hyq", "laikago", "quadruped", "solo",
            "talos_reduced.urdf", "talos_full_v2.urdf", "g1_29dof_rev", "icub_reduced", "romeo_small",
            "simple_humanoid.urdf", "alexander", "human.urdf", "centauro")
DEFAULT_SWEEP = {"panda_description/urdf/panda.urdf": False, "ur_description/urdf/ur5_robot.urdf": False,
                 "solo_description/robots/solo12.urdf": True, "go1_description/urdf/go1.urdf": True,
                 "kinova_description/robots/kinova.urdf": False}


def sweep_cases():
    cases = [pytest.param(URDF_DIR / f"{name}.urdf", False, id=name)
             for name in ("double_pendulum", "acrobot", "cartpole")]
    root = robot_data_root()
    if root is None:
        return cases
    for path in sorted(root.rglob("*.urdf")):
        relative = str(path.relative_to(root))
        if relative in NOT_TREES:
            continue
        for floating in (False, True) if any(key in relative for key in FLOATING) else (False,):
            default = DEFAULT_SWEEP.get(relative) == floating
            cases.append(pytest.param(path, floating, id=f"{relative}{' (floating)' if floating else ''}",
                                      marks=() if default else pytest.mark.slow))
    return cases


@pytest.mark.parametrize("path, floating", sweep_cases())
def test_dynamics_agree_with_pinocchio(path, floating):
    """H, C v + G, RNEA and ABA against Pinocchio at 1e-9 (relative to the largest entry).
    Coordinates are matched by joint name: Pinocchio orders siblings by joint name, we (as
    Drake and the file) by declaration; where the two agree, the map is the identity."""
    tree, _ = mb.tree_from_urdf(path, floating_base=floating)
    twin = PinocchioTwin(path, tree)
    qs, vs, xs = random_states(tree, 5, seed=tree.nv)
    ours = jax.jit(jax.vmap(lambda q, v, x: (mb.mass_matrix(tree, q), mb.bias_forces(tree, q, v),
                                              mb.rnea(tree, q, v, x), mb.aba(tree, q, v, x))))
    H, bias, tau, qdd = map(np.asarray, ours(qs, vs, xs))
    for k in range(len(qs)):
        q, v, x = twin.q(qs[k]), twin.v(vs[k]), twin.v(xs[k])
        H_pin = pin.crba(twin.model, twin.data, q)
        H_pin = np.triu(H_pin) + np.triu(H_pin, 1).T
        scale = lambda a: 1e-9 * max(1.0, np.max(np.abs(a)))
        np.testing.assert_allclose(H[k], H_pin[np.ix_(twin.v_perm, twin.v_perm)], rtol=0, atol=scale(H_pin))
        nle = twin.ours(pin.nonLinearEffects(twin.model, twin.data, q, v))
        np.testing.assert_allclose(bias[k], nle, rtol=0, atol=scale(nle))
        rnea_pin = twin.ours(pin.rnea(twin.model, twin.data, q, v, x))
        np.testing.assert_allclose(tau[k], rnea_pin, rtol=0, atol=scale(rnea_pin))
        aba_pin = twin.ours(pin.aba(twin.model, twin.data, q, v, x))
        np.testing.assert_allclose(qdd[k], aba_pin, rtol=0, atol=scale(aba_pin) * max(1.0, np.linalg.cond(H_pin) * 1e-6))


def test_coordinates_are_depth_first_in_declaration_order(tmp_path):
    """Children in the order the file declares their joints, each subtree before the next
    sibling: Drake's MultibodyPlant order (Pinocchio would sort the siblings by name)."""
    inertial = '<inertial><mass value="1"/><inertia ixx="1" iyy="1" izz="1" ixy="0" ixz="0" iyz="0"/></inertial>'
    joint = lambda name, parent, child: (f'<joint name="{name}" type="revolute"><parent link="{parent}"/>'
                                         f'<child link="{child}"/><axis xyz="0 0 1"/></joint>')
    path = tmp_path / "order.urdf"
    path.write_text('<robot name="order"><link name="base"/>'
                    + "".join(f'<link name="{n}">{inertial}</link>' for n in ("a", "b", "a2", "b2"))
                    + joint("zeta", "base", "a") + joint("alpha", "base", "b") + joint("mid", "a", "a2")
                    + joint("beta", "b", "b2") + "</robot>")
    assert mb.tree_from_urdf(path)[0].joint_names == ("zeta", "mid", "alpha", "beta")
    panda = mb.tree_from_urdf(example_robot("panda_description/urdf/panda.urdf"))[0]
    assert panda.joint_names[-2:] == ("panda_finger_joint1", "panda_finger_joint2")
    go1 = mb.tree_from_urdf(example_robot("go1_description/urdf/go1.urdf"))[0]
    assert go1.joint_names[:3] == ("FR_hip_joint", "FR_thigh_joint", "FR_calf_joint")


def test_frame_poses_and_jacobians_agree_with_pinocchio():
    path = example_robot("panda_description/urdf/panda.urdf")
    tree, _ = mb.tree_from_urdf(path)
    twin = PinocchioTwin(path, tree)
    qs, vs, _ = random_states(tree, 5, seed=3)
    fid = twin.model.getFrameId("panda_hand")
    for q, v in zip(qs, vs):
        qp = twin.q(q)
        pin.forwardKinematics(twin.model, twin.data, qp)
        pin.updateFramePlacements(twin.model, twin.data)
        R, p = mb.frame_pose(tree, jnp.asarray(q), "panda_hand")
        np.testing.assert_allclose(R, twin.data.oMf[fid].rotation, atol=1e-12)
        np.testing.assert_allclose(p, twin.data.oMf[fid].translation, atol=1e-12)
        J_pin = pin.computeFrameJacobian(twin.model, twin.data, qp, fid, pin.LOCAL_WORLD_ALIGNED)
        J = np.asarray(mb.frame_jacobian(tree, jnp.asarray(q), "panda_hand"))
        np.testing.assert_allclose(J[:3], J_pin[3:][:, twin.v_perm], atol=1e-12)   # angular
        np.testing.assert_allclose(J[3:], J_pin[:3][:, twin.v_perm], atol=1e-12)   # linear


def acrobot_closed_form(q, v, m1=1.0, m2=1.0, l1=1.0, lc1=0.5, lc2=1.0, Ic1=0.083, Ic2=0.33, g=9.81):
    """Underactuated ch. 3: H, C, tau_g (tau_g on the right, so G = -tau_g)."""
    I1, I2 = Ic1 + m1 * lc1 ** 2, Ic2 + m2 * lc2 ** 2
    c2, s1, s2, s12 = np.cos(q[1]), np.sin(q[0]), np.sin(q[1]), np.sin(q[0] + q[1])
    H = np.array([[I1 + I2 + m2 * l1 ** 2 + 2 * m2 * l1 * lc2 * c2, I2 + m2 * l1 * lc2 * c2],
                  [I2 + m2 * l1 * lc2 * c2, I2]])
    C = np.array([[-2 * m2 * l1 * lc2 * s2 * v[1], -m2 * l1 * lc2 * s2 * v[1]], [m2 * l1 * lc2 * s2 * v[0], 0.0]])
    tau_g = np.array([-m1 * g * lc1 * s1 - m2 * g * (l1 * s1 + lc2 * s12), -m2 * g * lc2 * s12])
    return H, C, tau_g, np.array([[0.0], [1.0]])


def cartpole_closed_form(q, v, mc=10.0, mp=1.0, l=0.5, g=9.81):
    c, s = np.cos(q[1]), np.sin(q[1])
    H = np.array([[mc + mp, mp * l * c], [mp * l * c, mp * l ** 2]])
    C = np.array([[0.0, -mp * l * v[1] * s], [0.0, 0.0]])
    return H, C, np.array([0.0, -mp * g * l * s]), np.array([[1.0], [0.0]])


@pytest.mark.parametrize("model, closed_form, params", [
    (jd.models.Acrobot, acrobot_closed_form, {}),
    (jd.models.Acrobot, acrobot_closed_form, dict(m1=1.3, m2=0.7, l1=1.2, lc1=0.4, lc2=0.9, Ic1=0.1, Ic2=0.2, g=9.7)),
    (jd.models.CartPole, cartpole_closed_form, {}),
    (jd.models.CartPole, cartpole_closed_form, dict(mc=2.0, mp=0.3, l=0.8, g=9.7)),
])
def test_acrobot_and_cartpole_from_urdf_match_their_closed_forms(model, closed_form, params):
    plant = model(**params)
    rng = np.random.default_rng(1)
    for q, v in zip(rng.uniform(-np.pi, np.pi, (20, 2)), rng.uniform(-3, 3, (20, 2))):
        H, Cv, G, B = map(np.asarray, plant.manipulator_dynamics(jnp.asarray(q), jnp.asarray(v)))
        H_ref, C_ref, tau_g, B_ref = closed_form(q, v, **params)
        np.testing.assert_allclose(H, H_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(Cv, C_ref @ v, rtol=0, atol=1e-12)
        np.testing.assert_allclose(G, -tau_g, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(B, B_ref)


def test_the_rigid_body_models_are_classes_whose_copies_batches_and_programs_keep_them():
    r"""The notes' rigid-body models are final subclasses of `RigidBodySystem`; copies made by
    `with_ground` / `equinox.tree_at` keep the class; the file constructors build the base
    class; acrobots built under vmap are one batched `Acrobot`; a jitted function of a plant
    traces once for acrobots of different masses (leaves), and every energy, batched or not, is
    the closed form's $\tfrac12 v^T H v - g (m_1 l_{c1}\cos q_1 + m_2 (l_1\cos q_1 + l_{c2}\cos(q_1 + q_2)))$."""
    import equinox as eqx

    for model in (jd.models.Acrobot, jd.models.CartPole, jd.models.DoublePendulum, jd.models.Panda):
        plant = model()
        assert type(plant) is model and isinstance(plant, jd.RigidBodySystem)
    acrobot = jd.models.Acrobot()
    grounded = acrobot.with_collision_geometry("lower_link", jd.geometry.Sphere(0.1)).with_ground(-4.0)
    assert type(grounded) is jd.models.Acrobot and grounded.contact is not None
    heavier = eqx.tree_at(lambda plant: plant.tree.mass, acrobot, jnp.array([1.0, 2.5]))
    assert type(heavier) is jd.models.Acrobot
    assert type(jd.models.Acrobot.from_urdf(acrobot.source)) is jd.RigidBodySystem

    x = np.array([0.4, -0.3, 1.0, -2.0])

    def closed_form(m2):
        H = acrobot_closed_form(x[:2], x[2:], m2=m2)[0]
        q1, q12 = x[0], x[0] + x[1]
        return 0.5 * x[2:] @ H @ x[2:] - 9.81 * (0.5 * np.cos(q1) + m2 * (np.cos(q1) + np.cos(q12)))

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def energy(plant):
        return plant.energy(jnp.asarray(x))

    for plant, m2 in ((acrobot, 1.0), (heavier, 2.5), (jd.models.Acrobot(m2=0.5), 0.5)):
        np.testing.assert_allclose(energy(plant), closed_form(m2), rtol=1e-13)
    masses = jnp.array([0.5, 1.0, 2.0])
    batch = eqx.filter_jit(eqx.filter_vmap(lambda m2: jd.models.Acrobot(m2=m2)))(masses)
    assert type(batch) is jd.models.Acrobot and batch.tree.mass.shape == (3, 2)
    lanes = eqx.filter_jit(eqx.filter_vmap(lambda plant: plant.energy(jnp.asarray(x))))(batch)
    np.testing.assert_allclose(lanes, [closed_form(float(m2)) for m2 in masses], rtol=1e-13)


def test_joint_types_own_their_widths_as_the_urdf_spec_and_pinocchio_count_them(tmp_path):
    """Each `JointType`'s widths: its degrees of freedom (num_velocities) are the URDF spec's
    (revolute, continuous, prismatic 1; fixed 0; floating 6), and its (num_positions,
    num_velocities) Pinocchio's (nq, nv) of the same joint; a URDF with one joint of each kind
    has the summed widths; an unknown kind ('planar', 3 dof in the spec) is refused by name by
    the enum, the tree and the URDF reader."""
    J = mb.JointType
    assert {k: k.num_velocities for k in J} == {J.REVOLUTE: 1, J.PRISMATIC: 1, J.FLOATING: 6, J.FIXED: 0}
    for kind, joint in ((J.REVOLUTE, pin.JointModelRY()), (J.PRISMATIC, pin.JointModelPX()),
                        (J.FLOATING, pin.JointModelFreeFlyer())):
        assert (kind.num_positions, kind.num_velocities) == (joint.nq, joint.nv)
    link = '<link name="{}"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>'
    joint = '<joint name="{0}" type="{0}"><parent link="{1}"/><child link="{2}"/><axis xyz="0 1 0"/></joint>'
    kinds = ("floating", "revolute", "continuous", "prismatic", "fixed")
    links = ("world", "base", "a", "b", "c", "d")
    text = ('<robot name="all">' + "".join(link.format(n) for n in links[1:])
            + "".join(joint.format(k, p, c) for k, p, c in zip(kinds, links, links[1:])) + "</robot>")
    (tmp_path / "all.urdf").write_text(text)
    tree, _ = mb.tree_from_urdf(tmp_path / "all.urdf")
    assert tree.joint_types == (J.FLOATING, J.REVOLUTE, J.REVOLUTE, J.PRISMATIC)  # the fixed one merged
    assert (tree.nq, tree.nv) == (7 + 1 + 1 + 1, 6 + 1 + 1 + 1)
    np.testing.assert_array_equal(tree.neutral_configuration(), [0, 0, 0, 0, 0, 0, 1, 0, 0, 0])
    with pytest.raises(ValueError, match="unknown joint type 'planar'.*revolute, prismatic, floating, fixed"):
        J("planar")
    import dataclasses

    with pytest.raises(ValueError, match="unknown joint type 'planar'"):
        dataclasses.replace(tree, joint_types=("floating", "revolute", "planar", "prismatic"))
    with pytest.raises(ValueError, match="movable joints only"):
        dataclasses.replace(tree, joint_types=("floating", "revolute", "fixed", "prismatic"))
    (tmp_path / "planar.urdf").write_text(text.replace('type="prismatic"', 'type="planar"'))
    with pytest.raises(mb.URDFError, match="joint 'prismatic' has type 'planar'; supported: revolute, continuous"):
        mb.tree_from_urdf(tmp_path / "planar.urdf")


def test_forward_and_inverse_dynamics_include_urdf_damping():
    plant = jd.models.Acrobot(b1=0.3, b2=0.2)
    q, v, u = jnp.array([0.4, -0.3]), jnp.array([1.0, -2.0]), jnp.array([0.7])
    H, Cv, G, B = plant.manipulator_dynamics(q, v)
    expected = np.linalg.solve(H, B @ u - Cv - G - jnp.array([0.3, 0.2]) * v)
    np.testing.assert_allclose(plant.forward_dynamics(q, v, u), expected, atol=1e-12)
    np.testing.assert_allclose(plant.inverse_dynamics(q, v, expected), B @ u, atol=1e-12)


def test_double_pendulum_conserves_energy():
    plant = jd.models.DoublePendulum()
    traj = jd.simulate(plant, (0.0, 10.0), jnp.array([1.0, 0.5, 0.0, 0.0]), rtol=1e-12, atol=1e-12,
                       max_steps=20000)
    E = jax.vmap(plant.energy)(traj.state(jnp.linspace(0.0, 10.0, 201)))
    assert float(jnp.max(jnp.abs(E - E[0]))) < 1e-8


def test_floating_base_robot_in_zero_gravity_conserves_energy_and_momentum_direction():
    path = example_robot("solo_description/robots/solo12.urdf")
    # free motion: the joints would reach their limits, whose compliant stops dissipate
    plant = jd.RigidBodySystem.from_urdf(path, floating_base=True, gravity=False, joint_limits=False)
    assert plant.num_positions == 19 and plant.num_velocities == 18
    q0 = plant.tree.neutral_configuration()
    rng = np.random.default_rng(0)
    x0 = jnp.concatenate([q0, jnp.asarray(rng.uniform(-1, 1, 18))])
    traj = jd.simulate(plant, (0.0, 10.0), x0, rtol=1e-12, atol=1e-12, max_steps=30000)
    xs = traj.state(jnp.linspace(0.0, 10.0, 101))
    E = jax.vmap(plant.energy)(xs)
    assert float(jnp.max(jnp.abs(E - E[0]))) < 1e-8
    quat_norm = jnp.linalg.norm(xs[:, 3:7], axis=1)
    assert float(jnp.max(jnp.abs(quat_norm - 1))) < 1e-8


def test_four_bar_linkage_stays_closed():
    plant = jd.RigidBodySystem.from_urdf(DATA / "fourbar.urdf",
                                         loops=[jd.LoopConstraint("coupler_end", "rocker_end", ("x", "z"))])
    assert plant.num_state_constraints == 4
    # an open-ish initial guess: simulate projects it onto phi(q) = 0, J v = 0 first
    traj = jd.simulate(plant, (0.0, 10.0), jnp.array([-1.2, 1.4, -1.9, 0.0, 0.0, 0.0]),
                       rtol=1e-10, atol=1e-10, max_steps=20000)
    xs = traj.state(jnp.linspace(0.0, 10.0, 401))
    phi = jax.vmap(lambda x: plant.loop_residual(x[:3]))(xs)
    assert float(jnp.max(jnp.abs(phi))) < 1e-8
    E = jax.vmap(plant.energy)(xs)
    assert float(jnp.max(jnp.abs(E - E[0]))) < 1e-7  # constraint forces do no work
    assert float(jnp.ptp(xs[:, 0])) > 0.5            # and the linkage does move


def test_the_loop_jacobian_and_its_rate_are_the_residuals_derivatives():
    """The four-bar's J(q) (both loop frames' Jacobians from one kinematics pass) is d phi/dq
    (revolute joints: v = qdot), and the J'v of its constrained dynamics is d^2 phi/dt^2 at
    zero acceleration."""
    plant = jd.RigidBodySystem.from_urdf(DATA / "fourbar.urdf",
                                         loops=[jd.LoopConstraint("coupler_end", "rocker_end", ("x", "z"))])
    q, v = jnp.array([-1.2, 1.4, -1.9]), jnp.array([0.3, -0.7, 0.5])
    np.testing.assert_allclose(plant.loop_jacobian(q), jax.jacfwd(plant.loop_residual)(q), atol=1e-13)
    phi_ddot = jax.jvp(lambda q_: jax.jvp(plant.loop_residual, (q_,), (v,))[1], (q,), (v,))[1]
    Jdot_v = jax.jvp(plant.loop_jacobian, (q,), (v,))[1] @ v
    np.testing.assert_allclose(Jdot_v, phi_ddot, atol=1e-13)
    np.testing.assert_array_equal(jd.multibody.frame_jacobian(plant.tree, q, "rocker_end"),
                                  jd.multibody._algorithms._frame_jacobians(plant.tree, q, ["coupler_end", "rocker_end"])[1])


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_gradient_of_an_acrobot_simulation_wrt_a_link_mass():
    def loss(m2):
        traj = jd.simulate(jd.models.Acrobot(m2=m2), (0.0, 1.0), jnp.array([0.5, -0.3, 0.0, 0.0]),
                           inputs=lambda t: jnp.array([jnp.sin(3 * t)]), rtol=1e-11, atol=1e-12)
        return jnp.sum(traj.final_state ** 2)

    g = jax.grad(loss)(1.0)
    fd = (loss(1.0 + 1e-5) - loss(1.0 - 1e-5)) / 2e-5
    np.testing.assert_allclose(g, fd, rtol=1e-6)


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_vmap_over_states_and_parameters():
    plant = jd.models.CartPole()
    xs = jnp.asarray(np.random.default_rng(2).uniform(-1, 1, (10, 4)))
    batched = jax.vmap(lambda x: plant.dynamics(0.0, x, jnp.array([1.0])))(xs)
    looped = np.stack([plant.dynamics(0.0, x, jnp.array([1.0])) for x in xs])
    np.testing.assert_allclose(batched, looped, rtol=1e-13, atol=1e-14)
    masses = jnp.linspace(0.5, 2.0, 7)
    per_mass = jax.vmap(lambda mp: jd.models.CartPole(mp=mp).dynamics(0.0, xs[0], jnp.zeros(1)))(masses)
    np.testing.assert_allclose(per_mass[3], jd.models.CartPole(mp=float(masses[3])).dynamics(0.0, xs[0], jnp.zeros(1)),
                               rtol=1e-13)


@pytest.mark.parametrize("relative, floating", [("panda_description/urdf/panda.urdf", False),
                                                pytest.param("solo_description/robots/solo12.urdf", True,
                                                             marks=pytest.mark.slow)])  # 42 s: the Panda's run checks the same
def test_a_vmapped_batch_in_lanes_matches_pinocchio_and_differentiates(relative, floating):
    """vmap puts the batch into the algorithms' lanes (a custom batching rule): the branched
    Panda (fingers: empty slots) and the floating quadruped agree with Pinocchio member by
    member, with an unbatched argument broadcast, and gradients through the vmapped call equal
    the looped ones."""
    path = example_robot(relative)
    tree, _ = mb.tree_from_urdf(path, floating_base=floating)
    model = pin.buildModelFromUrdf(str(path), pin.JointModelFreeFlyer()) if floating else pin.buildModelFromUrdf(str(path))
    data = model.createData()
    rng = np.random.default_rng(5)
    qs = np.stack([pin.randomConfiguration(model, -np.ones(model.nq), np.ones(model.nq)) for _ in range(6)])
    vs, taus = rng.uniform(-1, 1, (2, 6, tree.nv))
    qdd = jax.jit(jax.vmap(lambda q, v, t: mb.aba(tree, q, v, t)))(qs, vs, taus)
    tau = jax.jit(jax.vmap(lambda q, v, a: mb.rnea(tree, q, v, a)))(qs, vs, taus)
    for k in range(6):
        np.testing.assert_allclose(qdd[k], pin.aba(model, data, qs[k], vs[k], taus[k]), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(tau[k], pin.rnea(model, data, qs[k], vs[k], taus[k]), rtol=1e-9, atol=1e-9)
    still = jax.jit(jax.vmap(lambda q: mb.aba(tree, q, jnp.zeros(tree.nv), taus[0])))(qs)   # v, tau unbatched
    np.testing.assert_allclose(still[2], pin.aba(model, data, qs[2], np.zeros(tree.nv), taus[0]), rtol=1e-9, atol=1e-9)

    def loss(v, t):
        return jnp.sum(jnp.sin(jax.vmap(lambda q, v, t: mb.aba(tree, q, v, t))(qs, v, t)))

    grads = jax.jit(jax.grad(loss, argnums=(0, 1)))(vs, taus)
    one = jax.jit(jax.grad(lambda v, t: jnp.sum(jnp.sin(mb.aba(tree, qs[0], v, t))), argnums=(0, 1)))(vs[0], taus[0])
    np.testing.assert_allclose(grads[0][0], one[0], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(grads[1][0], one[1], rtol=1e-10, atol=1e-12)
    for k in (0, 5):
        pin.computeMinverse(model, data, qs[k])
        minv = np.triu(data.Minv) + np.triu(data.Minv, 1).T        # d qdd / d tau = H^{-1}
        np.testing.assert_allclose(grads[1][k], minv @ np.cos(qdd[k]), rtol=1e-8, atol=1e-9)
    dqdd_dtau = jax.jit(jax.vmap(jax.jacfwd(lambda q, t: mb.aba(tree, q, vs[0], t), argnums=1)))(qs, taus)
    np.testing.assert_allclose(dqdd_dtau[5], minv, rtol=1e-8, atol=1e-9)


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_forward_dynamics_derivatives_agree_with_pinocchio_and_finite_differences():
    """ABA is differentiated through inverse dynamics and a Cholesky solve of H (its own rule):
    forward and reverse mode against Pinocchio's `computeABADerivatives`, the second derivative
    and a link mass's derivative against central differences."""
    import equinox as eqx

    path = example_robot("panda_description/urdf/panda.urdf")
    tree, _ = mb.tree_from_urdf(path)
    model = pin.buildModelFromUrdf(str(path))
    data = model.createData()
    rng = np.random.default_rng(11)
    q = pin.randomConfiguration(model, -np.ones(model.nq), np.ones(model.nq))
    v, tau = rng.uniform(-1, 1, (2, tree.nv))
    pin.computeABADerivatives(model, data, q, v, tau)
    minv = np.triu(data.Minv) + np.triu(data.Minv, 1).T
    for jacobian in (jax.jacfwd, jax.jacrev):
        dq, dv, dtau = jax.jit(jacobian(lambda q, v, t: mb.aba(tree, q, v, t), argnums=(0, 1, 2)))(q, v, tau)
        np.testing.assert_allclose(dq, data.ddq_dq, rtol=1e-8, atol=1e-8 * np.abs(data.ddq_dq).max())
        np.testing.assert_allclose(dv, data.ddq_dv, rtol=1e-8, atol=1e-8 * np.abs(data.ddq_dv).max())
        np.testing.assert_allclose(dtau, minv, rtol=1e-8, atol=1e-8 * np.abs(minv).max())

    def jacobian_in_q(q):
        return jax.jacfwd(lambda q: mb.aba(tree, q, v, tau))(q)

    second = jax.jit(jax.jacfwd(jacobian_in_q))(q)
    step, k = 1e-5, 3
    e = np.zeros(tree.nv)
    e[k] = step
    central = (jacobian_in_q(q + e) - jacobian_in_q(q - e)) / (2 * step)
    np.testing.assert_allclose(second[:, :, k], central, rtol=1e-5, atol=1e-6 * np.abs(central).max())

    def with_mass(m):
        return mb.aba(eqx.tree_at(lambda t: t.mass, tree, tree.mass.at[4].set(m)), q, v, tau)

    m4 = float(tree.mass[4])
    np.testing.assert_allclose(jax.jacfwd(with_mass)(m4), (with_mass(m4 + 1e-6) - with_mass(m4 - 1e-6)) / 2e-6,
                               rtol=1e-6, atol=1e-8)


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_a_floating_base_dynamics_jacobian_matches_central_differences_off_the_unit_quaternion():
    """The quaternion's rotation is that of q / |q|, so forward and inverse dynamics stay each
    other's inverse off the unit sphere (a drifted state, a finite-difference probe) and the
    Jacobian through inverse dynamics is the function's own, radial direction included."""
    path = example_robot("solo_description/robots/solo12.urdf")
    plant = jd.multibody.RigidBodySystem.from_urdf(path, floating_base=True)
    rng = np.random.default_rng(4)
    x = np.asarray(plant.initial_state()) + rng.uniform(-0.3, 0.3, plant.initial_state().shape)
    x[3:7] *= 1.05 / np.linalg.norm(x[3:7])
    u = rng.uniform(-1, 1, plant.B.shape[1])
    f = jax.jit(lambda x: plant.dynamics(0.0, x, jnp.asarray(u)))
    central = np.stack([(f(x + 1e-6 * e) - f(x - 1e-6 * e)) / 2e-6 for e in np.eye(x.size)], axis=1)
    scale = np.abs(central).max()
    for jacobian in (jax.jacfwd, jax.jacrev):
        np.testing.assert_allclose(jax.jit(jacobian(f))(x), central, atol=1e-6 * scale)
    radial = np.zeros(x.size)
    radial[3:7] = x[3:7]
    scaled, plain = f(x + 0.1 * radial), f(x)           # the quaternion's rate scales with it
    np.testing.assert_allclose(scaled[3:7], 1.1 * plain[3:7], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.delete(scaled, np.s_[3:7]), np.delete(plain, np.s_[3:7]), rtol=1e-12, atol=1e-12)


MALFORMED = {
    "missing parent": ('<robot name="r"><link name="a"/><joint name="j" type="revolute">'
                       '<parent link="nope"/><child link="a"/><axis xyz="0 0 1"/></joint></robot>',
                       "parent link 'nope'"),
    "cycle": ('<robot name="r"><link name="a"/><link name="b"/>'
              '<joint name="j1" type="revolute"><parent link="a"/><child link="b"/></joint>'
              '<joint name="j2" type="revolute"><parent link="b"/><child link="a"/></joint></robot>',
              "no root link"),
    "a massless free body": ('<robot name="r"><link name="a"/><link name="b"/></robot>', r"link 'b' floats .* no mass"),
    "unknown joint type": ('<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="spherical">'
                           '<parent link="a"/><child link="b"/></joint></robot>', "type 'spherical'"),
    "non-positive-definite inertia": (
        '<robot name="r"><link name="a"/><link name="b"><inertial><mass value="1"/>'
        '<inertia ixx="1" ixy="0" ixz="0" iyy="-1" iyz="0" izz="1"/></inertial></link>'
        '<joint name="j" type="revolute"><parent link="a"/><child link="b"/></joint></robot>',
        "not positive semi-definite"),
    "billion laughs": ('<?xml version="1.0"?><!DOCTYPE lolz [<!ENTITY lol "lol">'
                       + "".join(f'<!ENTITY lol{i} "{("&lol" + (str(i - 1) if i > 1 else "") + ";") * 10}">'
                                 for i in range(1, 10))
                       + ']><robot name="&lol9;"><link name="a"/></robot>', "DOCTYPE"),
    "external entity": ('<?xml version="1.0"?><!DOCTYPE r [<!ENTITY x SYSTEM "http://127.0.0.1:9/x">]>'
                        '<robot name="&x;"><link name="a"/></robot>', "DOCTYPE"),
    "not xml": ("<robot name='r'><link name='a'>", "not well-formed"),
    "a word for a mass": ('<robot name="r"><link name="a"/><link name="b"><inertial><mass value="heavy"/>'
                          '<inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>'
                          '<joint name="j" type="revolute"><parent link="a"/><child link="b"/></joint></robot>',
                          r"link 'b': <mass value='heavy'> is not 1 number"),
    "two numbers for an axis": ('<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="revolute">'
                                '<parent link="a"/><child link="b"/><axis xyz="0 1"/></joint></robot>',
                                r"joint 'j': <axis xyz='0 1'> is not 3 numbers"),
    "a massless moving link": ('<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="revolute">'
                               '<parent link="a"/><child link="b"/><axis xyz="0 0 1"/></joint></robot>',
                               "joint 'j' moves link 'b', which has no mass"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_urdfs_raise_a_clear_error_quickly(case, tmp_path):
    text, message = MALFORMED[case]
    path = tmp_path / "bad.urdf"
    path.write_text(text)
    start = time.perf_counter()
    with pytest.raises(jd.multibody.URDFError, match=message):
        jd.RigidBodySystem.from_urdf(path)
    assert time.perf_counter() - start < 1.0


def test_a_mass_matrix_singular_at_run_time_is_named_with_its_joint():
    """A link's mass and inertia set to zero after loading (the load check cannot see it): the
    simulation stops at once, and the error names the singular H(q) and the joint, also when
    the plant sits inside a diagram."""
    import equinox as eqx

    plant = jd.RigidBodySystem.from_urdf(URDF_DIR / "double_pendulum.urdf")
    tree = plant.tree
    hollow = eqx.tree_at(lambda s: (s.tree.mass, s.tree.inertia), plant,
                         (tree.mass.at[1].set(0.0), tree.inertia.at[1].set(0.0)))
    x0 = jnp.array([0.3, 0.2, 0.0, 0.0])
    damper = jd.System.from_functions(output=lambda t, x, u: -0.1 * u[2:], num_states=0, num_inputs=4, num_outputs=2)
    with pytest.raises(jd.SimulationError, match=r"mass matrix H\(q\) of double_pendulum is singular .* joint\(s\) joint2 move no mass"):
        jd.simulate(jd.feedback(hollow, damper), (0.0, 1.0), x0, max_steps=100)
    assert plant.failure_hint(x0) is None


def test_bad_actuator_and_loop_names_are_errors():
    with pytest.raises(ValueError, match="no joint 'wrist'"):
        jd.RigidBodySystem.from_urdf(URDF_DIR / "acrobot.urdf", actuated=["wrist"])
    with pytest.raises(ValueError, match="frame 'nowhere'"):
        jd.RigidBodySystem.from_urdf(DATA / "fourbar.urdf", loops=[jd.LoopConstraint("nowhere", "rocker_end")])


@pytest.mark.parametrize("robot", ["acrobot", pytest.param("solo12 (floating quadruped)", marks=pytest.mark.slow)])
def test_a_pinocchio_model_is_a_source_too(robot):
    path, floating = ROBOTS[robot][0](), ROBOTS[robot][1]
    from_urdf = jd.RigidBodySystem.from_urdf(path, floating_base=floating)
    model = (pin.buildModelFromUrdf(str(path), pin.JointModelFreeFlyer()) if floating
             else pin.buildModelFromUrdf(str(path)))
    from_pin = jd.RigidBodySystem.from_pinocchio(model)
    ours, theirs = from_urdf.tree, from_pin.tree
    assert sorted(theirs.joint_types) == sorted(ours.joint_types)

    def perm(tree, starts, sizes):  # coordinates in the URDF tree's joint order, by joint name
        names = ["floating" if k == "floating" else n for n, k in zip(tree.joint_names, tree.joint_types)]
        order = ["floating" if k == "floating" else n for n, k in zip(ours.joint_names, ours.joint_types)]
        idx = []
        for n in order:
            i = names.index(n)
            idx += list(range(starts(tree)[i], starts(tree)[i] + sizes[tree.joint_types[i]]))
        return np.array(idx)

    vp = perm(theirs, lambda t: t.v_starts, {"floating": 6, "revolute": 1, "prismatic": 1})
    qp = perm(theirs, lambda t: t.q_starts, {"floating": 7, "revolute": 1, "prismatic": 1})
    q, v, a = random_states(ours, 1, seed=5)
    q, v, a = jnp.asarray(q[0]), jnp.asarray(v[0]), jnp.asarray(a[0])
    q_theirs = jnp.zeros_like(q).at[qp].set(q)
    v_theirs, a_theirs = jnp.zeros_like(v).at[vp].set(v), jnp.zeros_like(a).at[vp].set(a)
    np.testing.assert_allclose(mb.mass_matrix(theirs, q_theirs)[np.ix_(vp, vp)], mb.mass_matrix(ours, q), atol=1e-12)
    np.testing.assert_allclose(mb.aba(theirs, q_theirs, v_theirs, a_theirs)[vp], mb.aba(ours, q, v, a),
                               rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(theirs.damping[vp], ours.damping)


def test_quadrotor_matches_drakes_quadrotor_plant():
    examples = pytest.importorskip("pydrake.examples")
    drake = examples.QuadrotorPlant()
    context = drake.CreateDefaultContext()
    ours = jd.models.Quadrotor()
    assert ours.state_frame.coordinates[3:6] == ("roll", "pitch", "yaw")
    rng = np.random.default_rng(0)
    for x, u in zip(rng.uniform(-1, 1, (20, 12)), rng.uniform(0, 3, (20, 4))):
        context.SetContinuousState(x)
        drake.get_input_port(0).FixValue(context, u)
        expected = drake.EvalTimeDerivatives(context).CopyToVector()
        np.testing.assert_allclose(ours.dynamics(0.0, jnp.asarray(x), jnp.asarray(u)), expected,
                                   rtol=0, atol=1e-12 * max(1.0, np.max(np.abs(expected))))


def test_quadrotors_hover_and_respond_as_their_equations_say():
    quad = jd.models.Quadrotor()
    hover = jnp.full(4, quad.m * quad.g / 4)
    np.testing.assert_allclose(quad.dynamics(0.0, jnp.zeros(12), hover), 0.0, atol=1e-15)
    # more thrust on rotor 1 (+y) than rotor 3 (-y): positive roll acceleration L kF du / Ixx
    xdot = quad.dynamics(0.0, jnp.zeros(12), hover + jnp.array([0.0, 0.1, 0.0, -0.1]))
    np.testing.assert_allclose(xdot[9], quad.L * 0.2 / 0.0015, rtol=1e-12)
    planar = jd.models.PlanarQuadrotor()
    u = jnp.full(2, planar.m * planar.g / 2)
    np.testing.assert_allclose(planar.dynamics(0.0, jnp.zeros(6), u), 0.0, atol=1e-15)
    x = jnp.array([0.0, 0.0, 0.3, 0.0, 0.0, 0.0])
    xdot = planar.dynamics(0.0, x, jnp.array([2.0, 1.0]))
    np.testing.assert_allclose(xdot[3:], [-3.0 * np.sin(0.3) / planar.m, 3.0 * np.cos(0.3) / planar.m - planar.g,
                                          planar.r / planar.I], rtol=1e-13)


def test_quadrotor_gimbal_lock_is_reported_as_drake_reports_it():
    """Within 0.458 degrees of pitch = +-90 degrees (|cos(pitch)| < 0.008, Drake's tolerance) the
    rpy rates are singular: a named error with concrete values (once 2.3e17), NaN inside jit,
    a failure status from simulate; just outside, Drake's numbers."""
    quad = jd.models.Quadrotor()
    x = jnp.zeros(12).at[9:12].set(jnp.array([0.1, 0.2, 0.3]))
    u = jnp.ones(4)
    for pitch in (np.pi / 2, -np.pi / 2, np.pi / 2 - 0.007):
        with pytest.raises(ValueError, match=r"Quadrotor.dynamics: pitch = .* degrees is within 0.458371 degrees "
                                             r"of gimbal lock.*quaternion"):
            quad.dynamics(0.0, x.at[4].set(pitch), u)
        assert np.all(np.isnan(jax.jit(quad.dynamics)(0.0, x.at[4].set(pitch), u)))
    with pytest.raises(jd.SimulationError, match="gimbal lock"):
        jd.simulate(quad, (0.0, 1.0), x.at[4].set(np.pi / 2), max_steps=64, dense=False)
    status = jax.jit(lambda x0: jd.simulate(quad, (0.0, 1.0), x0, max_steps=64, dense=False).status)(
        x.at[4].set(np.pi / 2))
    assert not jd.SimulationStatus.is_success(int(status))
    examples = pytest.importorskip("pydrake.examples")
    drake = examples.QuadrotorPlant()
    context = drake.CreateDefaultContext()
    drake.get_input_port(0).FixValue(context, np.asarray(u))
    for pitch in np.pi / 2 - np.array([0.0, 0.004, 0.0079, 0.0081, 0.01, 0.1]):
        context.SetContinuousState(np.asarray(x.at[4].set(pitch)))
        try:
            expected = drake.EvalTimeDerivatives(context).CopyToVector()
        except RuntimeError as error:
            assert "gimbal-lock" in str(error)
            with pytest.raises(ValueError, match="gimbal lock"):
                quad.dynamics(0.0, x.at[4].set(pitch), u)
        else:
            np.testing.assert_allclose(quad.dynamics(0.0, x.at[4].set(pitch), u), expected, rtol=1e-9, atol=1e-12)


def test_feedback_cancellation_makes_the_double_pendulum_a_simple_pendulum():
    """u = H qdd_d + C v + G with qdd_1 = -(g / l) sin q_1 (and the elbow held): the shoulder
    follows a simple pendulum of length l simulated on its own (examples/feedback_cancellation.py)."""
    plant = jd.models.DoublePendulum()

    def torque(t, x, y, plant):
        H, Cv, G, B = plant.manipulator_dynamics(y[:2], y[2:])
        qdd = jnp.stack([-9.81 / 0.7 * jnp.sin(y[0]), -100.0 * y[1] - 20.0 * y[3]])
        return jnp.linalg.solve(B, H @ qdd + Cv + G)

    controller = jd.System.from_functions(output=torque, num_states=0, num_inputs=4, num_outputs=2, params=plant)
    tight = dict(rtol=1e-11, atol=1e-12, max_steps=8192)
    arm = jd.simulate(jd.feedback(plant, controller), (0.0, 3.0), jnp.array([1.2, 0.0, 0.0, 0.0]), **tight)
    simple = jd.simulate(jd.models.Pendulum(l=0.7, b=0.0), (0.0, 3.0), jnp.array([1.2, 0.0]), **tight)
    ts = jnp.linspace(0.0, 3.0, 61)
    np.testing.assert_allclose(arm.state(ts)[:, 0], simple.state(ts)[:, 0], atol=1e-9)


def test_welded_joints_and_the_panda_model():
    arm = jd.models.Panda()
    assert arm.num_positions == 7 and arm.num_inputs == 7
    full = jd.models.Panda(fingers=True)
    assert full.num_positions == 9
    q = jnp.array([0.1, -0.3, 0.2, -2.0, 0.1, 1.8, 0.5])
    # welding the fingers at zero: the arm's H is the full model's arm block at fingers = 0
    np.testing.assert_allclose(mb.mass_matrix(arm.tree, q),
                               mb.mass_matrix(full.tree, jnp.concatenate([q, jnp.zeros(2)]))[:7, :7], atol=1e-12)
    # gravity compensation holds the arm: qdd = 0 under u = G(q)
    H, Cv, G, B = arm.manipulator_dynamics(q, jnp.zeros(7))
    np.testing.assert_allclose(arm.forward_dynamics(q, jnp.zeros(7), G), 0.0, atol=1e-10)
    with pytest.raises(jd.multibody.URDFError, match="cannot weld joint 'nope'"):
        jd.RigidBodySystem.from_urdf(URDF_DIR / "acrobot.urdf", welded=["nope"])


def test_mesh_paths_are_never_opened(tmp_path):
    """package:// and http:// mesh references are not resolved (no file or network access)."""
    path = tmp_path / "meshes.urdf"
    path.write_text(
        '<robot name="r"><link name="a"/><link name="b"><inertial><mass value="1"/>'
        '<inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial>'
        '<visual><geometry><mesh filename="package://nowhere/b.dae"/></geometry></visual>'
        '<collision><geometry><mesh filename="http://127.0.0.1:9/b.stl"/></geometry></collision></link>'
        '<joint name="j" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/></joint></robot>')
    start = time.perf_counter()
    plant = jd.RigidBodySystem.from_urdf(path)
    assert plant.num_positions == 1 and time.perf_counter() - start < 1.0


def drake_example_urdfs():
    try:
        import pydrake
    except ImportError:
        return []
    root = pathlib.Path(pydrake.__file__).parent / "share/drake/examples"
    return [root / "acrobot/Acrobot.urdf", root / "acrobot/Acrobot_no_collision.urdf",
            root / "pendulum/Pendulum.urdf"]


@pytest.mark.parametrize("path", drake_example_urdfs(), ids=lambda p: p.name)
def test_drakes_own_urdfs_load_as_shipped_and_agree_with_multibody_plant(path):
    """Drake's robot URDFs (a joint whose parent is the undeclared link 'world') load as
    shipped; H, C v, G, B and forward dynamics with URDF damping equal MultibodyPlant's."""
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    drake_plant = MultibodyPlant(0.0)
    Parser(drake_plant).AddModels(str(path))
    if 'link="world"' not in path.read_text():  # Drake would float the root; we fix it, so weld it
        drake_plant.WeldFrames(drake_plant.world_frame(), drake_plant.GetFrameByName("base_link"))
    drake_plant.Finalize()
    context = drake_plant.CreateDefaultContext()
    ours = jd.RigidBodySystem.from_urdf(path)
    names = [drake_plant.get_joint(i).name() for i in drake_plant.GetJointIndices()
             if drake_plant.get_joint(i).num_velocities() == 1]
    order = np.array([drake_plant.GetJointByName(n).velocity_start() for n in ours.tree.joint_names])
    assert sorted(names) == sorted(ours.tree.joint_names)
    assert ours.num_inputs == drake_plant.num_actuators()
    rng = np.random.default_rng(0)
    for _ in range(5):
        q, v = rng.uniform(-np.pi, np.pi, ours.tree.nq), rng.uniform(-3, 3, ours.tree.nv)
        u = rng.uniform(-2, 2, ours.num_inputs)
        q_d, v_d = np.zeros(drake_plant.num_positions()), np.zeros(drake_plant.num_velocities())
        q_d[order], v_d[order] = q, v
        drake_plant.SetPositions(context, q_d)
        drake_plant.SetVelocities(context, v_d)
        drake_plant.get_actuation_input_port().FixValue(context, u)
        H, Cv, G, B = map(np.asarray, ours.manipulator_dynamics(jnp.asarray(q), jnp.asarray(v)))
        ix = np.ix_(order, order)
        np.testing.assert_allclose(H, drake_plant.CalcMassMatrix(context)[ix], rtol=0, atol=1e-9)
        np.testing.assert_allclose(Cv, drake_plant.CalcBiasTerm(context)[order], rtol=0, atol=1e-9)
        np.testing.assert_allclose(G, -drake_plant.CalcGravityGeneralizedForces(context)[order], rtol=0, atol=1e-9)
        np.testing.assert_allclose(B, drake_plant.MakeActuationMatrix()[order], rtol=0, atol=0)
        xdot = drake_plant.EvalTimeDerivatives(context).CopyToVector()
        qdd = np.asarray(ours.forward_dynamics(jnp.asarray(q), jnp.asarray(v), jnp.asarray(u)))
        np.testing.assert_allclose(qdd, xdot[drake_plant.num_positions():][order], rtol=0, atol=1e-9)


def test_effort_limits_become_input_limits_that_saturate_the_inputs():
    """The Panda's <limit effort> (87 N m for joints 1-4, 12 N m for 5-7) saturates its inputs."""
    panda = jd.RigidBodySystem.from_urdf(example_robot("panda_description/urdf/panda.urdf"),
                                         welded=["panda_finger_joint1", "panda_finger_joint2"])
    np.testing.assert_array_equal(panda.input_limits[1], [87, 87, 87, 87, 12, 12, 12])
    np.testing.assert_array_equal(panda.input_limits[0], -panda.input_limits[1])
    assert jd.RigidBodySystem.from_urdf(example_robot("panda_description/urdf/panda.urdf"),
                                        effort_limits=False).input_limits is None
    x = panda.initial_state()
    u = jnp.full(7, 500.0)
    qdd_limited = panda.forward_dynamics(x[:7], x[7:], panda.saturate(u))
    np.testing.assert_allclose(qdd_limited, panda.forward_dynamics(x[:7], x[7:], panda.input_limits[1]))
    assert not np.allclose(qdd_limited, panda.forward_dynamics(x[:7], x[7:], u))


@pytest.mark.parametrize("relative", ["panda_description/urdf/panda.urdf",
                                      pytest.param("baxter_description/urdf/baxter.urdf", marks=pytest.mark.slow)])
def test_mimic_joints_as_coupler_constraints_agree_with_pinocchios_reduced_model(relative):
    """`from_urdf(..., mimic=True)` keeps each <mimic> joint as a coordinate coupled to its
    leader by a constraint; on a consistent state the accelerations equal those of Pinocchio's
    mimic model (which removes the followers): qdd = G H_r^{-1} (G^T tau - nle_r), G the
    coupling map from Pinocchio's coordinates to ours. Baxter: 2 gripper followers, ratio -1.
    (Pinocchio refuses Talos' grippers, whose followers come before their leader; we take them.)"""
    path = example_robot(relative)
    ours = jd.RigidBodySystem.from_urdf(path, mimic=True)
    model = pin.buildModelFromUrdf(str(path), mimic=True)
    data = model.createData()
    tree, leader = ours.tree, {c.joint: (c.leader, c.gear_ratio) for c in ours.couplers}
    assert len(ours.couplers) == tree.nv - model.nv > 0
    G = np.zeros((tree.nv, model.nv))
    for name, start in zip(tree.joint_names, tree.v_starts):
        source, ratio = leader.get(name, (name, 1.0))
        G[start, model.joints[model.getJointId(source)].idx_v] = ratio
    rng = np.random.default_rng(1)
    lower, upper = np.asarray(tree.position_lower), np.asarray(tree.position_upper)
    for _ in range(3):
        q_r = rng.uniform(np.maximum(lower, -1.0), np.minimum(upper, 1.0))[[  # a leader's own range
            tree.joint_names.index(model.names[j]) for j in range(1, model.njoints) if model.joints[j].nv]]
        q_r = np.array([q_r[k] for k in np.argsort([model.joints[j].idx_v for j in range(1, model.njoints)
                                                     if model.joints[j].nv])])
        q, v_r = G @ q_r, rng.uniform(-1, 1, model.nv)
        v, u = G @ v_r, rng.uniform(-1, 1, ours.num_inputs)
        qdd = np.asarray(ours.forward_dynamics(jnp.asarray(q), jnp.asarray(v), jnp.asarray(u)))
        tau = np.asarray(ours.B @ u - tree.damping * v + ours.joint_limit_torque(jnp.asarray(q), jnp.asarray(v)))
        H_r = pin.crba(model, data, q_r)
        H_r = np.triu(H_r) + np.triu(H_r, 1).T
        expected = G @ np.linalg.solve(H_r, G.T @ tau - pin.nonLinearEffects(model, data, q_r, v_r))
        np.testing.assert_allclose(qdd, expected, rtol=0, atol=1e-8 * max(1.0, np.max(np.abs(expected))))
        np.testing.assert_allclose(np.asarray(ours.state_constraints(jnp.concatenate([q, v]))), 0.0, atol=1e-12)


SLIDER = """<robot name="slider"><link name="rail"/>
<link name="carriage"><inertial><mass value="2"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
<joint name="x" type="prismatic"><parent link="rail"/><child link="carriage"/><axis xyz="1 0 0"/>
<limit lower="-1" upper="0.5" effort="10" velocity="10"/></joint></robot>"""


def test_a_joint_limit_stops_a_slider_as_the_capped_spring_damper_closed_form_says(tmp_path):
    """A free 2 kg carriage at v0 = 1 m/s hits its 0.5 m limit at t = 0.5 s; past it by p, the
    push is clip(k p + d pd, 0, 2 k p) with k = m w^2, d = 2 m w. Entering, d pd > k p: the
    capped push 2 k p gives p = v0 sin(sqrt2 w t) / (sqrt2 w) until pd = w p / 2, at
    tan(sqrt2 w t1) = 2 sqrt2, where p1 = 2 v0 / (3 w), pd1 = v0 / 3. Then the critically
    damped m pdd + 2 m w pd + m w^2 p = 0 gives p = (v0 / w) e^{-w s} (2/3 + w s), s = t - t1:
    deepest v0 e^{-1/3} / w at w s = 1/3; the push vanishes at w s = 4/3 (pd = -w p / 2), 2 v0
    e^{-4/3} / w past the limit, whence the carriage coasts out at v0 e^{-4/3}, not pulled back."""
    path = tmp_path / "slider.urdf"
    path.write_text(SLIDER)
    slider = jd.RigidBodySystem.from_urdf(path, gravity=False)
    w, v0, t_hit = 2 * np.pi / 0.02, 1.0, 0.5
    np.testing.assert_allclose(slider.limit_stiffness, [2 * w ** 2])
    np.testing.assert_allclose(slider.limit_damping, [2 * 2 * w])
    traj = jd.simulate(slider, (0.0, 0.6), jnp.array([0.0, v0]), rtol=1e-10, atol=1e-12)
    t1 = t_hit + np.arctan(2 * np.sqrt(2)) / (np.sqrt(2) * w)
    np.testing.assert_allclose(traj.state(t1), [0.5 + 2 * v0 / (3 * w), v0 / 3], atol=1e-7)
    np.testing.assert_allclose(traj.state(t1 + 1 / (3 * w)), [0.5 + v0 * np.exp(-1 / 3) / w, 0.0], atol=1e-7)
    t_free = t1 + 4 / (3 * w)
    v_out = -v0 * np.exp(-4 / 3)
    np.testing.assert_allclose(traj.state(t_free), [0.5 - 2 * v_out / w, v_out], atol=1e-7)
    np.testing.assert_allclose(traj.final_state, [0.5 - 2 * v_out / w + v_out * (0.6 - t_free), v_out],
                               rtol=1e-6)
    free = jd.simulate(jd.RigidBodySystem.from_urdf(path, gravity=False, joint_limits=False), (0.0, 0.6),
                       jnp.array([0.0, 1.0]))
    np.testing.assert_allclose(free.final_state, [0.6, 1.0], atol=1e-9)


@pytest.mark.slow  # long; the same property in a cheaper test runs by default
def test_the_passive_panda_stays_within_its_joint_limits():
    """examples/manipulator.py's passive arm: without limits it swings far past them; with
    them, no joint goes past a limit by more than 0.1 rad."""
    panda = jd.models.Panda()
    x0 = jnp.concatenate([jnp.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8]), jnp.zeros(7)])
    lower, upper = np.asarray(panda.tree.position_lower), np.asarray(panda.tree.position_upper)
    ts = jnp.linspace(0.0, 1.5, 301)

    def past(plant):
        qs = np.asarray(jd.simulate(plant, (0.0, 1.5), x0).state(ts))[:, :7]
        return np.max(np.maximum(qs - upper, lower - qs))

    assert past(panda) < 0.1
    assert past(jd.RigidBodySystem(panda.tree, joint_limits=False)) > 1.0


def test_the_panda_simulates_from_its_initial_state_pressed_onto_its_joint_4_limit():
    """initial_state() puts joint 4 on its upper limit (its zero lies past it) and gravity
    presses it there. With default options the simulation succeeds (the push is continuous at
    the limit), joint 4 never goes past by more than (1 + e^{-4/3}/3) lambda / k, the bound
    for a joint pressed from rest by lambda, and once the impacts have settled it rests
    lambda / k past, where lambda(t) is the torque a rigid stop would bear: from Pinocchio's
    H and nonlinear effects with joint 4 locked (qdd_4 = 0), the other limits' pushes applied."""
    ts = np.linspace(0.0, 0.25, 51)
    with jax.enable_x64(False):  # float32, where the uncapped damper's jump stopped it at t = 4e-5
        panda = jd.models.Panda()
        x0 = panda.initial_state()
        traj = jd.simulate(panda, (0.0, 0.25), x0)
        assert traj.final_state.dtype == jnp.float32 and traj.success
        xs = np.asarray(traj.state(jnp.asarray(ts, jnp.float32)), float)
    lower, upper = np.asarray(panda.tree.position_lower, float), np.asarray(panda.tree.position_upper, float)
    k, d = np.asarray(panda.limit_stiffness, float), np.asarray(panda.limit_damping, float)
    assert float(x0[3]) == upper[3]

    def push(p, p_dot):  # the documented law, clip(k p + d pd, 0, 2 k p) past a limit by p
        spring = k * np.maximum(p, 0.0)
        return np.clip(spring + d * p_dot, 0.0, 2 * spring)

    others = push(lower - xs[:, :7], -xs[:, 7:]) - push(xs[:, :7] - upper, xs[:, 7:])
    others[:, 3] = 0.0
    full = pin.buildModelFromUrdf(str(panda.source))
    model = pin.buildReducedModel(full, [full.getJointId(f"panda_finger_joint{i}") for i in (1, 2)],
                                  pin.neutral(full))
    data = model.createData()
    rigid_stop = []
    for x, tau in zip(xs, others):
        q, v = x[:7], x[7:]
        H = pin.crba(model, data, q)
        H_inv = np.linalg.inv(np.triu(H) + np.triu(H, 1).T)
        n = pin.nonLinearEffects(model, data, q, v) + np.asarray(panda.tree.damping) * v - tau
        rigid_stop.append(-(H_inv @ n)[3] / H_inv[3, 3])  # pushing joint 4 down: > 0
    past = xs[:, 3] - upper[3]
    load = np.array(rigid_stop) / k[3]
    assert np.all(load > 0)
    assert np.max(past) <= (1 + np.exp(-4 / 3) / 3) * np.max(load)
    settled = ts >= 0.1
    np.testing.assert_allclose(past[settled], load[settled], rtol=0.01)


def test_free_bodies_a_kilometre_apart_keep_float32s_digits(tmp_path):
    """Every free body's subtree is expressed about the body's own position. About one point
    for all, the far body's spatial inertia carried m |p|^2 ~ 1e6 next to its 5e-4 kg m^2, and
    float32 lost its accelerations: 2% wrong 100 m apart, NaN (a 'singular mass matrix') 1 km
    apart. Now float32 agrees with float64 to its rounding, as at the origin."""
    (tmp_path / "two.urdf").write_text("""<robot name="two">
      <link name="crate"><inertial><mass value="1.5"/><inertia ixx="0.01" iyy="0.0125" izz="0.0125" ixy="0" ixz="0" iyz="0"/></inertial></link>
      <link name="ball"><inertial><origin xyz="0.01 0 0"/><mass value="0.5"/><inertia ixx="5e-4" iyy="6e-4" izz="7e-4" ixy="0" ixz="0" iyz="0"/></inertial></link></robot>""")
    plant = jd.RigidBodySystem.from_urdf(tmp_path / "two.urdf", floating_base=True)
    single = jax.tree.map(lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, plant)
    rng = np.random.default_rng(3)
    for distance in (0.0, 1e2, 1e3):
        x = np.zeros(26)
        x[6] = x[13] = 1.0
        x[7] = distance
        x[14:] = rng.normal(size=12)
        exact = np.asarray(plant.dynamics(0.0, jnp.asarray(x), jnp.zeros(0)))[14:]
        rounded = np.asarray(single.dynamics(jnp.float32(0.0), jnp.asarray(x, jnp.float32), jnp.zeros(0, jnp.float32)))[14:]
        assert np.all(np.isfinite(rounded))
        np.testing.assert_allclose(rounded, exact, atol=3e-5 * np.max(np.abs(exact)))


def test_armature_enters_the_algorithms_as_pinocchios_and_is_read_from_a_pinocchio_model():
    """Rotor inertias (armature) on Solo-12's joints: H, RNEA and ABA, one at a time and in a
    vmapped batch (lanes), equal Pinocchio's with the same `model.armature`; a Pinocchio model
    brings its armature along; ABA's derivative in tau is H^-1."""
    path = example_robot("solo_description/robots/solo12.urdf")
    tree, _ = mb.tree_from_urdf(path, floating_base=True)
    twin = PinocchioTwin(path, tree)
    armature = np.where(np.arange(tree.nv) < 6, 0.0, np.linspace(0.01, 0.12, tree.nv))  # none on the base
    tree = eqx.tree_at(lambda t: t.armature, tree, jnp.asarray(armature), is_leaf=lambda x: x is None)
    twin.model.armature = twin.v(armature)
    qs, vs, xs = random_states(tree, 3, seed=11)
    batched = jax.jit(jax.vmap(lambda q, v, x: (mb.mass_matrix(tree, q), mb.rnea(tree, q, v, x), mb.aba(tree, q, v, x))))
    for k, (H, tau, qdd) in enumerate(zip(*map(np.asarray, batched(qs, vs, xs)))):
        q, v, x = twin.q(qs[k]), twin.v(vs[k]), twin.v(xs[k])
        H_pin = pin.crba(twin.model, twin.data, q)
        H_pin = np.triu(H_pin) + np.triu(H_pin, 1).T
        np.testing.assert_allclose(H, H_pin[np.ix_(twin.v_perm, twin.v_perm)], rtol=0, atol=1e-10)
        np.testing.assert_allclose(tau, twin.ours(pin.rnea(twin.model, twin.data, q, v, x)), rtol=0, atol=1e-9)
        np.testing.assert_allclose(qdd, twin.ours(pin.aba(twin.model, twin.data, q, v, x)), rtol=1e-9, atol=1e-9)
    # the same H without armature differs by diag(armature) exactly
    H0 = np.asarray(mb.mass_matrix(eqx.tree_at(lambda t: t.armature, tree, None), jnp.asarray(qs[0])))
    np.testing.assert_allclose(np.asarray(mb.mass_matrix(tree, jnp.asarray(qs[0]))) - H0, np.diag(armature), atol=1e-13)
    from_pin = mb.tree_from_pinocchio(twin.model)
    np.testing.assert_allclose(np.sort(np.asarray(from_pin.armature)), np.sort(armature))
    # one evaluation (one lane) equals the batch; d qdd / d tau = H^{-1} (armature included)
    q, v, x = (jnp.asarray(a[0]) for a in (qs, vs, xs))
    one, J = jax.jit(lambda q, v, x: (mb.aba(tree, q, v, x), jax.jacfwd(lambda t: mb.aba(tree, q, v, t))(x)))(q, v, x)
    np.testing.assert_allclose(one, batched(qs, vs, xs)[2][0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(J, np.linalg.inv(np.asarray(mb.mass_matrix(tree, q))), rtol=1e-9, atol=1e-9)


def test_a_rotor_inertia_through_a_gear_is_drakes_reflected_inertia(tmp_path):
    """Drake's URDF extension `<drake:rotor_inertia>` / `<drake:gear_ratio>` in a transmission's
    actuator: the joint's armature is I n^2, and H and the forward dynamics equal
    MultibodyPlant's on the same file."""
    pydrake = pytest.importorskip("pydrake")
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import MultibodyPlant

    text = (pathlib.Path(pydrake.__file__).parent / "share/drake/examples/acrobot/Acrobot.urdf").read_text()
    text = text.replace('<robot name="Acrobot">', '<robot name="Acrobot" xmlns:drake="http://drake.mit.edu">')
    text = text.replace('<actuator name="elbow"/>', '<actuator name="elbow"><drake:rotor_inertia value="0.02"/>'
                                                    '<drake:gear_ratio value="3"/></actuator>')
    path = tmp_path / "acrobot_geared.urdf"
    path.write_text(text)
    ours = jd.RigidBodySystem.from_urdf(path)
    np.testing.assert_allclose(ours.tree.armature, [0.0, 0.02 * 3 ** 2])
    drake_plant = MultibodyPlant(0.0)
    Parser(drake_plant).AddModels(str(path))
    drake_plant.Finalize()
    context = drake_plant.CreateDefaultContext()
    order = np.array([drake_plant.GetJointByName(n).velocity_start() for n in ours.tree.joint_names])
    rng = np.random.default_rng(3)
    for _ in range(3):
        q, v, u = rng.uniform(-np.pi, np.pi, 2), rng.uniform(-3, 3, 2), rng.uniform(-2, 2, 1)
        drake_plant.SetPositions(context, q[np.argsort(order)])
        drake_plant.SetVelocities(context, v[np.argsort(order)])
        drake_plant.get_actuation_input_port().FixValue(context, u)
        H = np.asarray(ours.manipulator_dynamics(jnp.asarray(q), jnp.asarray(v))[0])
        np.testing.assert_allclose(H, drake_plant.CalcMassMatrix(context)[np.ix_(order, order)], rtol=0, atol=1e-12)
        xdot = drake_plant.EvalTimeDerivatives(context).CopyToVector()
        qdd = np.asarray(ours.forward_dynamics(jnp.asarray(q), jnp.asarray(v), jnp.asarray(u)))
        np.testing.assert_allclose(qdd, xdot[2:][order], rtol=0, atol=1e-10)
