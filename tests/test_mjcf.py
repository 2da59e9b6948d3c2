"""`RigidBodySystem.from_mjcf`: MuJoCo's compiler as the parser. Contact-free, the plant's
accelerations equal `mj_forward`'s on the same model at random states (a cart-pole, the
hopper with its leg spring, a floating quadruped, a chain of offset slide and hinge joints in
rotated bodies, MJX's humanoid with armature and springs, position servos on Barkour and the
Shadow hand); body frames and collision shapes sit where MuJoCo puts them, explicit contact
pairs touch; MuJoCo's renderer draws the plant's states; named errors for what the plant
cannot represent."""

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake.geometry import Box, Capsule, Convex, Cylinder, HalfSpace, Sphere
from jaxdrake.multibody import MJCFError, RigidBodySystem, body_poses, frame_pose

mujoco = pytest.importorskip("mujoco")
DATA = pathlib.Path(__file__).parent / "data"

QUADRUPED = """
<mujoco model="quadruped">
  <option gravity="0 0 -9.81"/>
  <default><geom contype="1" conaffinity="1"/></default>
  <asset><mesh name="wedge" vertex="0 0 0  0.1 0 0  0 0.08 0  0 0 0.06  0.1 0.08 0.06"/></asset>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1" friction="0.8 0.005 0.0001"/>
    <body name="torso" pos="0 0 0.5" euler="0 0 20">
      <freejoint name="root"/>
      <geom name="torso" type="box" size="0.3 0.15 0.05" mass="5"/>
      <geom name="lidar" type="cylinder" size="0.04 0.03" pos="0.1 0 0.08" mass="0.2"/>
      <geom name="hull" type="mesh" mesh="wedge" pos="-0.2 0 0.05" euler="0 0 30" mass="0.1"/>
      <geom name="antenna" type="ellipsoid" size="0.01 0.01 0.1" pos="0 0 0.2" contype="0" conaffinity="0"/>
      {legs}
    </body>
  </worldbody>
  <actuator>{motors}</actuator>
  <contact>{excludes}</contact>
</mujoco>
"""

LEG = """
      <body name="{n}_hip" pos="{x} {y} 0">
        <joint name="{n}_abduct" axis="1 0 0" damping="0.2" range="-0.6 0.6"/>
        <geom type="capsule" fromto="0 0 0 0 {s}0.06 0" size="0.03" mass="0.3"/>
        <body name="{n}_thigh" pos="0 {s}0.06 0" euler="0 15 0">
          <joint name="{n}_hip" axis="0 1 0" pos="0 0 0.02" damping="0.1"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.2" size="0.025" mass="0.4"/>
          <body name="{n}_shin" pos="0 0 -0.2">
            <joint name="{n}_knee" axis="0 1 0" damping="0.1" range="-2.5 -0.2"/>
            <geom type="capsule" fromto="0 0 0 0 0 -0.2" size="0.02" mass="0.2"/>
            <geom name="{n}_foot" type="sphere" pos="0 0 -0.2" size="0.03" mass="0.05" friction="1.2"/>
          </body>
        </body>
      </body>"""


def quadruped_xml(exclude=True):
    """A floating quadruped; `exclude`: its thighs and shins do not touch its torso."""
    corners = {"fl": (0.3, 0.15, ""), "fr": (0.3, -0.15, "-"), "hl": (-0.3, 0.15, ""), "hr": (-0.3, -0.15, "-")}
    legs = "".join(LEG.format(n=n, x=x, y=y, s=s) for n, (x, y, s) in corners.items())
    motors = "".join(f'<motor name="{n}_{j}" joint="{n}_{j}" gear="{20 + 5 * k}" ctrlrange="-1 1"/>'
                     for n in corners for k, j in enumerate(("abduct", "hip", "knee")))
    excludes = "".join(f'<exclude body1="torso" body2="{n}_{b}"/>' for n in corners for b in ("thigh", "shin"))
    return (QUADRUPED.replace("{legs}", legs).replace("{motors}", motors)
            .replace("{excludes}", excludes if exclude else ""))


# slide and hinge joints whose anchors (pos) are off the body origins, with references (ref),
# non-unit axes, rotated bodies, a body with two joints, a welded body, a static body
CHAIN = """
<mujoco model="chain">
  <compiler angle="radian"/>
  <option gravity="0.5 -1 -9"/>
  <worldbody>
    <body name="base" pos="0.1 0.2 0.3" quat="0.9 0.1 0.3 -0.2">
      <geom name="base" type="box" size="0.1 0.1 0.1"/>
      <body name="carriage" pos="0.2 0 0.1" euler="0.3 -0.2 0.5">
        <joint name="rail" type="slide" axis="1 1 0" pos="0.05 0.02 -0.03" ref="0.1" damping="0.3" range="-1 1"/>
        <geom type="box" size="0.1 0.05 0.05" mass="2" pos="0.01 0.02 0"/>
        <body name="arm" pos="0 0.1 0" quat="0.7 -0.3 0.2 0.6">
          <joint name="shoulder" type="hinge" axis="0 0.6 0.8" pos="0.1 -0.05 0.02" ref="0.4" damping="0.05"/>
          <joint name="extend" type="slide" axis="0 0 2" pos="0.03 0.1 0" ref="-0.05"/>
          <geom name="arm" type="capsule" fromto="0 0 0 0.3 0.1 0" size="0.03" mass="0.5"/>
          <body name="tool" pos="0.3 0.1 0" euler="0.1 0.2 0.3">
            <geom name="tool" type="sphere" size="0.05" mass="0.4" pos="0.02 0 0.01"/>
          </body>
          <body name="forearm" pos="0.3 0.1 0" euler="-0.4 0.1 0.9">
            <joint name="elbow" type="hinge" axis="1 0 0.2" pos="0 0 0.05" damping="0.02"/>
            <inertial pos="0.1 0.01 0.02" quat="0.8 0.2 -0.1 0.3" mass="0.7" diaginertia="0.01 0.02 0.015"/>
            <geom name="forearm" type="capsule" fromto="0 0 0 0.25 0 0" size="0.02"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="push" joint="rail" gear="5" ctrlrange="-2 1"/>
    <motor name="twist" joint="elbow" gear="2" forcerange="-3 3"/>
  </actuator>
</mujoco>
"""


def compiled(text):
    return mujoco.MjModel.from_xml_string(text)


def mujoco_acceleration(model, qpos, qvel, ctrl):
    """MuJoCo's qacc without constraints (contacts, limits) and without clamping ctrl."""
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT) | int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL)
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:], data.ctrl[:] = qpos, qvel, ctrl
    mujoco.mj_forward(model, data)
    return data


def quaternion_matrix(wxyz):
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, np.asarray(wxyz, float))
    return R.reshape(3, 3)


def free_joints(model):
    """(qpos address, dof address) of every free joint."""
    return [(model.jnt_qposadr[j], model.jnt_dofadr[j]) for j in range(model.njnt)
            if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]


def to_plant(model, qpos, qvel):
    """MuJoCo's (qpos, qvel) as the plant's x: a free body's quaternion reordered to (x, y, z, w),
    its linear velocity turned into the body frame."""
    q, v = np.array(qpos, float), np.array(qvel, float)
    for a, d in free_joints(model):
        R = quaternion_matrix(qpos[a + 3: a + 7])
        q[a + 3: a + 7] = np.roll(qpos[a + 3: a + 7], -1)
        v[d: d + 3] = R.T @ qvel[d: d + 3]
    return np.concatenate([q, v])


def plant_acceleration_from(model, qpos, qvel, qacc):
    """MuJoCo's qacc as the time derivative of the plant's v: for a free body,
    d/dt (R^T v_world) = R^T a_world - omega x v_body."""
    a = np.array(qacc, float)
    for p, d in free_joints(model):
        R = quaternion_matrix(qpos[p + 3: p + 7])
        a[d: d + 3] = R.T @ qacc[d: d + 3] - np.cross(qvel[d + 3: d + 6], R.T @ qvel[d: d + 3])
    return a


def random_state(model, rng):
    """qpos within the joint ranges (where the plant's compliant limits are silent), qvel."""
    qpos = np.array(model.qpos0, float)
    for j in range(model.njnt):
        a = model.jnt_qposadr[j]
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            qpos[a: a + 3] = rng.normal(size=3)
            quat = rng.normal(size=4)
            qpos[a + 3: a + 7] = quat / np.linalg.norm(quat)
        elif model.jnt_limited[j]:
            lo, hi = model.jnt_range[j]
            qpos[a] = rng.uniform(lo + 0.05 * (hi - lo), hi - 0.05 * (hi - lo))
        else:
            qpos[a] = rng.uniform(-2, 2)
    return qpos, rng.normal(size=model.nv)


def compare_accelerations(plant, model, seeds=range(5)):
    """The largest |qdd_plant - qdd_MuJoCo| / (1 + |qdd_MuJoCo|) over random states and inputs
    (the input u is the joint force: MuJoCo's ctrl = u / (gear gain))."""
    dynamics = jax.jit(plant.dynamics)
    worst = 0.0
    for seed in seeds:
        rng = np.random.default_rng(seed)
        qpos, qvel = random_state(model, rng)
        effort = np.asarray(plant.tree.effort_limit)[np.argmax(np.asarray(plant.B), 0)]  # MuJoCo clamps forcerange
        u = np.clip(rng.normal(size=plant.num_inputs) * 3, -0.9 * effort, 0.9 * effort)
        scale = model.actuator_gear[:, 0] * model.actuator_gainprm[:, 0]
        data = mujoco_acceleration(model, qpos, qvel, u / scale)
        x = to_plant(model, qpos, qvel)
        ours = np.asarray(dynamics(0.0, x, u))[model.nq:]
        theirs = plant_acceleration_from(model, qpos, qvel, data.qacc)
        assert np.all(np.isfinite(theirs)) and np.all(np.isfinite(ours))
        worst = max(worst, np.max(np.abs(ours - theirs) / (1 + np.abs(theirs))))
        check_frames(plant, model, data, x[: model.nq])
    return worst


def compare_servo_accelerations(plant, model, seeds=range(4)):
    """`compare_accelerations` for a plant whose inputs are MuJoCo's ctrl (servos), with
    targets that saturate the force-limited actuators (odd seeds) and ones that do not."""
    dynamics = jax.jit(plant.dynamics)
    worst, saturated = 0.0, 0
    for seed in seeds:
        rng = np.random.default_rng(seed)
        qpos, qvel = random_state(model, rng)
        lower, upper = np.where(model.actuator_ctrllimited[:, None], model.actuator_ctrlrange, [-2.0, 2.0]).T
        middle, half = (lower + upper) / 2, (upper - lower) / 2   # within ctrlrange (the plant's input limits)
        ctrl = middle + half * rng.uniform(-1, 1, model.nu) * (1.0 if seed % 2 else 0.05)
        data = mujoco_acceleration(model, qpos, qvel, ctrl)
        ours = np.asarray(dynamics(0.0, to_plant(model, qpos, qvel), ctrl))[model.nq:]
        theirs = plant_acceleration_from(model, qpos, qvel, data.qacc)
        worst = max(worst, np.max(np.abs(ours - theirs) / (1 + np.abs(theirs))))
        limited = model.actuator_forcelimited.astype(bool)
        saturated += int(np.sum(np.abs(data.actuator_force[limited]) >= np.abs(model.actuator_forcerange[limited]).max(1) - 1e-12))
    return worst, saturated


def poses_in_world(tree, q, bodies, rotations, translations):
    """World poses of things fixed at (rotations, translations) in `bodies` (-1: the world)."""
    Rs, ps = (np.asarray(x) for x in _body_poses(tree, q))
    Rs, ps = np.concatenate([Rs, np.eye(3)[None]]), np.concatenate([ps, np.zeros((1, 3))])
    bodies = np.asarray(bodies)
    return Rs[bodies] @ np.asarray(rotations), np.einsum("gij,gj->gi", Rs[bodies], np.asarray(translations)) + ps[bodies]


_body_poses = jax.jit(body_poses)


def check_frames(plant, model, data, q):
    """Every body's frame where MuJoCo puts it."""
    tree = plant.tree
    R, p = poses_in_world(tree, q, tree.frame_bodies, tree.frame_rotation, tree.frame_translation)
    for b in range(1, model.nbody):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b)
        k = tree.frame_names.index(name)
        np.testing.assert_allclose(p[k], data.xpos[b], atol=1e-12, err_msg=name)
        np.testing.assert_allclose(R[k], data.xmat[b].reshape(3, 3), atol=1e-12, err_msg=name)


def test_cartpole_accelerations_equal_mujoco():
    model = mujoco.MjModel.from_xml_path(str(DATA / "mj_cartpole.xml"))
    plant = RigidBodySystem.from_mjcf(DATA / "mj_cartpole.xml")
    assert plant.tree.joint_names == ("slider", "hinge") and plant.input_frame.coordinates == ("slider",)
    np.testing.assert_allclose(plant.tree.effort_limit[0], 10.0)  # gear 10, ctrlrange [-1, 1]
    np.testing.assert_allclose(plant.tree.damping, [0.05, 0.01])
    assert compare_accelerations(plant, model) < 1e-12


def test_hopper_with_its_leg_spring_accelerations_equal_mujoco():
    model = mujoco.MjModel.from_xml_path(str(DATA / "mj_hopper.xml"))
    plant = RigidBodySystem.from_mjcf(DATA / "mj_hopper.xml")
    np.testing.assert_allclose(plant.tree.spring_stiffness, [0.0, 2000.0])
    np.testing.assert_allclose(plant.tree.position_lower[1], -0.1)
    np.testing.assert_allclose(plant.tree.position_upper[1], 0.15)
    assert plant.input_frame.coordinates == ("leg",)
    assert compare_accelerations(plant, model) < 1e-12
    model.jnt_stiffness[:] = 0.0  # a compiled model is accepted too
    assert RigidBodySystem.from_mjcf(model).tree.spring_stiffness is None


SERVOS = """<mujoco><option gravity="0 0 -9.81"/><worldbody>
  <body name="cart"><joint name="slide" type="slide" axis="1 0 0" damping="0.3" actuatorfrclimited="true"
      actuatorfrcrange="-4 5"/>
    <geom type="box" size=".2 .1 .05" mass="2"/>
    <body name="arm" pos="0 0 0.05"><joint name="hinge" axis="0 1 0" range="-2 2"/>
      <geom type="capsule" fromto="0 0 0 0 0 .5" size=".03" mass="0.5"/>
      <body name="tip" pos="0 0 .5"><joint name="wrist" axis="1 0 0"/>
        <geom type="sphere" size=".05" mass="0.2"/></body></body></body></worldbody>
  <actuator><position name="push" joint="slide" kp="40" kv="6" gear="1.5" ctrlrange="-1 1" forcerange="-3 3"/>
    <velocity name="spin" joint="hinge" kv="2" gear="2"/>
    <motor name="twist" joint="wrist" gear="0.5" ctrlrange="-3 3"/></actuator></mujoco>"""


def test_position_and_velocity_servos_beside_a_motor_accelerations_equal_mujoco():
    """With a servo in the file, the inputs are MuJoCo's ctrl for every actuator (a motor's
    too), limited to ctrlrange: a position servo (kp, kv, gear 1.5, forcerange), a velocity servo
    and a motor, the slide's total clamped to its actuatorfrcrange; accelerations equal
    `mj_forward`'s, clamped or not."""
    model = compiled(SERVOS)
    plant = RigidBodySystem.from_mjcf(model)
    assert plant.input_frame.coordinates == ("push", "spin", "twist")
    np.testing.assert_allclose(np.asarray(plant.input_limits), [[-1, -np.inf, -3], [1, np.inf, 3]])
    np.testing.assert_allclose(plant.B, [[1.5 * 40, 0, 0], [0, 2 * 2, 0], [0, 0, 0.5]])   # gear x gain
    worst, saturated = compare_servo_accelerations(plant, model)
    assert worst < 1e-12 and saturated > 0
    # the slide's force, clamped by the servo and then the joint: kp (u - gear q) - kv gear v, times gear
    x = jnp.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    tau = plant.actuation(x[:3], x[3:], jnp.array([0.5, 0.0, 0.0]))
    np.testing.assert_allclose(tau[0], 1.5 * min(40 * 0.5, 3.0), rtol=1e-14)
    np.testing.assert_allclose(plant.actuation(x[:3], x[3:], jnp.array([-0.9, 0.0, 0.0]))[0], max(1.5 * -3.0, -4.0))
    # stiff linearization: the servo's stiffness and damping are in it
    u = jnp.array([0.01, 0.0, 0.0])   # unsaturated
    exact = jax.jacfwd(plant.dynamics, argnums=1)(0.0, x, u)
    stiff = jax.jacfwd(plant.stiff_linearization().dynamics, argnums=1)(0.0, x, u)
    np.testing.assert_allclose(stiff[3:, 3:], exact[3:, 3:], rtol=1e-12, atol=1e-12)   # at rest: d/dv exact
    np.testing.assert_allclose(stiff[3, 0], exact[3, 0], rtol=1e-12)   # the cart's own spring


TENDON = """<mujoco><worldbody><body><joint name="a" axis="0 1 0" damping="0.1"/>
    <geom type="capsule" fromto="0 0 0 .4 0 0" size=".03" mass="1"/>
  <body pos=".4 0 0"><joint name="b" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 .3 0 0" size=".03" mass=".5"/>
  <body pos=".3 0 0"><joint name="c" axis="0 1 0"/><geom type="sphere" size=".05" mass=".2"/></body></body></body>
  </worldbody><tendon><fixed name="curl"><joint joint="b" coef="1"/><joint joint="c" coef="0.5"/></fixed>
    <fixed name="idle"><joint joint="a" coef="0.1"/></fixed></tendon>
  <actuator><position name="curl_servo" tendon="curl" kp="3" kv="0.2" gear="2" ctrlrange="-1 1" forcerange="-0.8 0.8"/>
    <motor name="shoulder" joint="a" gear="3" ctrlrange="-1 1"/></actuator></mujoco>"""


def test_a_servo_on_a_fixed_tendon_accelerations_equal_mujoco():
    """A position servo pulling a fixed tendon that couples two hinges (length b + c/2, gear 2)
    beside a motor: the moment arms are gear x coefficients, accelerations equal `mj_forward`'s
    (the servo saturating or not); a fixed tendon without an actuator changes nothing; a spatial
    tendon, or a tendon with a spring, is refused by name."""
    model = compiled(TENDON)
    plant = RigidBodySystem.from_mjcf(model)
    assert plant.input_frame.coordinates == ("curl_servo", "shoulder")
    np.testing.assert_allclose(plant.B, [[0.0, 3.0], [2.0 * 3.0, 0.0], [2.0 * 0.5 * 3.0, 0.0]])
    worst, saturated = compare_servo_accelerations(plant, model)
    assert worst < 1e-12 and saturated > 0
    with pytest.raises(MJCFError, match=r"tendon 'curl' has limits.*remove it from the tendon"):
        RigidBodySystem.from_mjcf(compiled(TENDON.replace('<fixed name="curl">', '<fixed name="curl" range="-1 1">')))
    spatial = TENDON.replace('<fixed name="idle"><joint joint="a" coef="0.1"/></fixed>',
                             '<spatial name="rope"><site site="s1"/><site site="s2"/></spatial>').replace(
        '<geom type="sphere" size=".05" mass=".2"/>', '<geom type="sphere" size=".05" mass=".2"/><site name="s2"/>').replace(
        '<joint name="a" axis="0 1 0" damping="0.1"/>', '<joint name="a" axis="0 1 0" damping="0.1"/><site name="s1"/>')
    with pytest.raises(MJCFError, match=r"tendon 'rope' is a spatial tendon.*fixed tendons"):
        RigidBodySystem.from_mjcf(compiled(spatial))


COUPLED = """<mujoco><worldbody><body name="upper"><joint name="a" axis="0 1 0" ref="0.2"/>
    <geom type="capsule" fromto="0 0 0 .4 0 0" size=".03" mass="1"/>
  <body pos=".4 0 0"><joint name="b" axis="0 1 0" ref="-0.1"/><geom type="capsule" fromto="0 0 0 .3 0 0" size=".03" mass=".5"/>
  <body pos=".3 0 0"><joint name="c" axis="0 1 0"/><geom type="sphere" size=".05" mass=".2"/></body></body></body>
  </worldbody><equality><joint name="tie" joint1="c" joint2="b" polycoef="0.1 -0.5 0 0 0" solref="0.0002 1"
    solimp="0.9999 0.9999 0.001"/></equality><actuator><motor joint="a"/></actuator></mujoco>"""


def test_a_joint_equality_is_a_coupler_constraint_whose_accelerations_equal_mujocos_hard_equality():
    """MuJoCo's joint equality c - c0 = a0 + a1 (b - b0) (about qpos0; refs in degrees) is the
    coupler c = a1 b + (c0 + a0 - a1 b0); the initial state satisfies it; at a state that does,
    the accelerations equal `mj_forward`'s under a nearly hard equality (solref 2e-4, solimp
    0.9999) to its softness; other equalities are refused by name."""
    model = compiled(COUPLED)
    plant = RigidBodySystem.from_mjcf(model)
    b0, c0 = model.qpos0[1], model.qpos0[2]
    (coupler,) = plant.couplers
    assert (coupler.joint, coupler.leader, coupler.gear_ratio) == ("c", "b", -0.5)
    np.testing.assert_allclose(coupler.offset, c0 + 0.1 + 0.5 * b0, rtol=1e-15)
    np.testing.assert_allclose(plant.constraint_residual(plant.initial_state()[:3]), 0.0, atol=1e-15)
    data = mujoco.MjData(model)
    data.qpos[:2], data.qvel[:] = [0.7, 0.4], [0.3, -1.0, 0.5]
    data.qpos[2] = c0 + 0.1 - 0.5 * (0.4 - b0)
    data.ctrl[:] = 0.4
    mujoco.mj_forward(model, data)
    ours = np.asarray(plant.dynamics(0.0, jnp.asarray(np.concatenate([data.qpos, data.qvel])), jnp.array([0.4])))[3:]
    np.testing.assert_allclose(ours, data.qacc, rtol=1e-4)
    for equality, message in [('<connect body1="upper" anchor="0 0 0"/>', r"equality 'equality0' is a connect constraint"),
                              ('<joint joint1="c"/>', r"holds one joint alone"),
                              ('<joint joint1="c" joint2="b" polycoef="0 1 0.3 0 0"/>', r"polynomial of degree > 1")]:
        with pytest.raises(MJCFError, match=message):
            RigidBodySystem.from_mjcf(compiled(COUPLED.replace(COUPLED[COUPLED.index("<equality>") + 10:
                                                                       COUPLED.index("</equality>")], equality)))


def test_fixed_tendons_springs_and_dampers_accelerations_and_energy_equal_mujoco():
    """Fixed tendons with springs and dampers: one with a rest length, one with a dead band
    (springlength="l- l+"), both with damping; accelerations equal `mj_forward`'s and the
    springs' energy is MuJoCo's potential energy without gravity."""
    xml = TENDON.replace('<fixed name="curl">', '<fixed name="curl" stiffness="5" damping="0.3" springlength="0.2">')
    xml = xml.replace('<fixed name="idle">', '<fixed name="idle" stiffness="40" damping="0.1" springlength="-0.02 0.01">')
    model = compiled(xml)
    plant = RigidBodySystem.from_mjcf(model)
    assert plant.tendons.names == ("curl", "idle")
    worst, _ = compare_servo_accelerations(plant, model)
    assert worst < 1e-12
    no_gravity = compiled(xml.replace("<mujoco>", '<mujoco><option gravity="0 0 0"><flag energy="enable"/></option>'))
    springs_only = mujoco.MjData(no_gravity)
    springs_only.qpos[:] = [0.3, -0.4, 0.8]
    mujoco.mj_forward(no_gravity, springs_only)
    q = jnp.asarray(springs_only.qpos)
    np.testing.assert_allclose(plant.tendons.energy(q), springs_only.energy[0], rtol=1e-12)
    assert float(plant.tendons.energy(q)) > 0.1   # both springs stretched past their rest


@pytest.mark.parametrize("relative, first_input", [("barkour_v0/assets/barkour_v0_mjx.xml", "abduction_front_left"),
                                                   ("shadow_hand/right_hand.xml", "rh_A_WRJ2")])
def test_mjx_robots_with_position_servos_accelerations_equal_mujoco(relative, first_input):
    """MJX's Barkour v0 quadruped (twelve position servos, kp 35, kv 0.65, forcerange +-18 N m)
    and Shadow hand (24 position servos with armature and damping on 24 hinges)."""
    path = pathlib.Path(mujoco.__file__).parent / "mjx/test_data" / relative
    if not path.exists():
        pytest.skip("this mujoco wheel has no MJX test models")
    model = mujoco.MjModel.from_xml_path(str(path))
    plant = RigidBodySystem.from_mjcf(path)
    assert plant.num_inputs == model.nu and plant.input_frame.coordinates[0] == first_input
    worst, saturated = compare_servo_accelerations(plant, model, seeds=range(2))
    assert worst < 1e-10 and saturated > 0


def test_the_stiff_linearization_holds_the_joint_springs():
    """The hopper's two slides leave H, Coriolis and gravity terms constant, so the stiff
    linearization (the applied forces' derivative alone) is the exact Jacobian, spring included."""
    plant = RigidBodySystem.from_mjcf(DATA / "mj_hopper.xml")
    x, u = jnp.array([0.1, 0.05, 0.3, -0.2]), jnp.array([5.0])
    exact = jax.jacfwd(plant.dynamics, argnums=1)(0.0, x, u)
    stiff = jax.jacfwd(plant.stiff_linearization().dynamics, argnums=1)(0.0, x, u)
    np.testing.assert_allclose(stiff, exact, rtol=1e-12, atol=1e-12)
    assert abs(float(exact[3, 1])) > 1000   # the leg's spring, 2000 N/m over its moving mass


def test_mujocos_humanoid_with_armature_and_springs_accelerations_equal_mujoco():
    """MuJoCo's own humanoid (MJX's test model): 21 hinges with armature 0.01 and springs of
    stiffness 1-20 about their references, on a free body; contact-free accelerations equal
    `mj_forward`'s."""
    path = pathlib.Path(mujoco.__file__).parent / "mjx/test_data/humanoid/humanoid.xml"
    if not path.exists():
        pytest.skip("this mujoco wheel has no MJX test models")
    model = mujoco.MjModel.from_xml_path(str(path))
    plant = RigidBodySystem.from_mjcf(path)
    np.testing.assert_allclose(plant.tree.armature, model.dof_armature)
    assert np.count_nonzero(plant.tree.spring_stiffness) == np.count_nonzero(model.jnt_stiffness) == 19
    assert compare_accelerations(plant, model, seeds=range(3)) < 1e-10
    # motors alone: the inputs are joint forces named by the joints, unless asked for MuJoCo's ctrl
    as_ctrl = RigidBodySystem.from_mjcf(path, ctrl_inputs=True)
    assert plant.input_frame.coordinates[0] == "abdomen_y" and as_ctrl.input_frame.coordinates[0] == "abdomen_y"
    assert as_ctrl.actuators is not None and as_ctrl.input_limits[1][0] == 1.0   # ctrlrange, not gear x ctrlrange
    assert compare_servo_accelerations(as_ctrl, model, seeds=range(1))[0] < 1e-10
    with pytest.raises(ValueError, match=r"u has shape \(3,\), but needs \(21,\) \(MuJoCo's ctrl, one per actuator"):
        as_ctrl.dynamics(0.0, as_ctrl.initial_state(), jnp.zeros(3))


def test_armature_and_springs_keep_the_energy_they_add():
    """The hopper without damping, with armature on both slides: kinetic (rotors included),
    gravity's and the leg spring's energy stay constant over a second of bouncing on the
    spring (no contact, no limits)."""
    model = mujoco.MjModel.from_xml_path(str(DATA / "mj_hopper.xml"))
    model.dof_damping[:] = 0.0
    model.dof_armature[:] = [0.3, 0.5]
    plant = RigidBodySystem.from_mjcf(model, joint_limits=False)
    x0 = jnp.array([0.0, 0.05, 0.4, -0.3])
    traj = jd.simulate(plant, (0.0, 1.0), x0, rtol=1e-11, atol=1e-12)
    states = traj.state(traj.breakpoints())   # the accepted steps' ends
    energy = jax.vmap(plant.energy)(states)
    kinetic = 0.5 * ((4.0 + 0.3 + 0.4) * x0[2] ** 2 + (0.4 + 0.5) * x0[3] ** 2
                     + 2 * 0.4 * x0[2] * -x0[3])   # both bodies move with the height; the leg slides down
    np.testing.assert_allclose(plant.energy(x0) - plant.energy(x0.at[2:].set(0.0)), kinetic, rtol=1e-12)
    assert float(jnp.ptp(energy)) < 1e-8 * float(jnp.max(jnp.abs(energy)))
    assert float(jnp.ptp(states[:, 1])) > 0.01   # the spring did work


def test_floating_quadruped_accelerations_equal_mujoco():
    model = compiled(quadruped_xml())
    plant = RigidBodySystem.from_mjcf(model)
    assert plant.tree.joint_types[0] == "floating" and plant.tree.nq == 19 and plant.tree.nv == 18
    assert plant.state_frame.coordinates[:7] == ("root_x", "root_y", "root_z", "root_qx", "root_qy", "root_qz", "root_qw")
    assert plant.num_inputs == 12
    assert compare_accelerations(plant, model) < 1e-12


FREE_BODIES_BESIDE_AN_ARM = """
<mujoco>
  <option gravity="0.3 0 -9.81"/>
  <worldbody>
    <body name="box" pos="0.5 0 0.2"><freejoint name="box_free"/>
      <geom type="box" size=".1 .15 .05" mass="2"/>
      <body name="flap" pos="0.1 0 0"><joint name="hinge" axis="0 1 0" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.2 0 0" size=".02" mass="0.3"/></body>
    </body>
    <body name="upper" pos="0 0 1"><joint name="shoulder" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.4" size=".04" mass="1.5"/>
      <body name="fore" pos="0 0 -0.4"><joint name="elbow" axis="1 0 0"/>
        <geom type="capsule" fromto="0 0 0 0.05 0 -0.3" size=".03" mass="0.8"/></body>
    </body>
    <body name="ball" pos="-0.4 0.2 0.3"><freejoint name="ball_free"/><geom size=".08" mass="0.5"/></body>
  </worldbody>
  <actuator><motor joint="shoulder" gear="2"/><motor joint="elbow"/></actuator>
</mujoco>
"""


def test_free_bodies_beside_an_arm_accelerations_equal_mujoco():
    """Two free bodies (one carrying a hinged flap) and an arm hanging from the world."""
    model = compiled(FREE_BODIES_BESIDE_AN_ARM)
    plant = RigidBodySystem.from_mjcf(model)
    assert plant.tree.joint_types == ("floating", "revolute", "revolute", "revolute", "floating")
    assert plant.tree.joint_names == ("box_free", "hinge", "shoulder", "elbow", "ball_free")
    assert compare_accelerations(plant, model) < 1e-12


def test_offset_slide_and_hinge_chain_accelerations_equal_mujoco():
    model = compiled(CHAIN)
    plant = RigidBodySystem.from_mjcf(model)
    tree = plant.tree
    # the two-joint body is a massless body for its first joint; the welded tool merges into arm
    assert tree.body_names == ("carriage", "arm_shoulder", "arm", "forearm")
    assert tree.joint_types == ("prismatic", "revolute", "prismatic", "revolute")
    assert float(tree.mass[1]) == 0.0
    np.testing.assert_allclose(tree.mass[2], model.body_mass[3] + model.body_mass[4])
    np.testing.assert_allclose(tree.gravity, [0.5, -1.0, -9.0])
    # effort limits: |gear| max|ctrlrange| = 5 * 2; |gear| max|forcerange| = 2 * 3
    np.testing.assert_allclose(np.asarray(tree.effort_limit)[[0, 3]], [10.0, 6.0])
    assert plant.input_frame.coordinates == ("rail", "elbow")
    assert compare_accelerations(plant, model, seeds=range(8)) < 1e-12


def test_collision_geometry_sits_where_mujoco_puts_it():
    model = compiled(quadruped_xml())
    plant = RigidBodySystem.from_mjcf(model, contact=True)
    contact, collision = plant.contact, plant.collision
    names = contact.names
    assert "antenna" not in names  # visual only (contype = conaffinity = 0)
    shapes = {g.name: g.shape for g in collision.geometries}
    assert isinstance(shapes["floor"], HalfSpace) and isinstance(shapes["lidar"], Cylinder)
    assert shapes["torso"] == Box(0.6, 0.3, 0.1) and shapes["fl_foot"] == Sphere(0.03)
    capsule = next(g.shape for g in collision.geometries if g.link == "fl_shin" and isinstance(g.shape, Capsule))
    assert capsule == Capsule(0.02, 0.2)
    hull = shapes["hull"]
    assert isinstance(hull, Convex)
    mesh = model.geom_dataid[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "hull")]
    vertices = model.mesh_vert[model.mesh_vertadr[mesh]: model.mesh_vertadr[mesh] + model.mesh_vertnum[mesh]]
    np.testing.assert_allclose(np.sort(hull.vertices, 0), np.sort(vertices, 0))
    mu = dict(zip(names, np.asarray(contact.mu_static)))
    assert mu["floor"] == pytest.approx(0.8) and mu["fl_foot"] == pytest.approx(1.2)
    # MuJoCo's parent filter: a body and its parent never touch; the floor touches everything
    excluded = {frozenset(p) for p in collision.excluded_link_pairs}
    assert frozenset(("fl_thigh", "fl_shin")) in excluded and frozenset(("torso", "fl_hip")) in excluded
    assert not any("world" in p for p in excluded)
    for seed in range(3):
        qpos, qvel = random_state(model, np.random.default_rng(seed))
        data = mujoco_acceleration(model, qpos, qvel, np.zeros(model.nu))
        check_geometry_poses(plant, model, data, to_plant(model, qpos, qvel)[: model.nq])


def check_geometry_poses(plant, model, data, q):
    """Every collision shape where MuJoCo puts its geom (the contact model's pose in its body)."""
    contact = plant.contact
    R, p = poses_in_world(plant.tree, q, contact.bodies, contact.rotation, contact.translation)
    for k, geometry in enumerate(plant.collision.geometries):
        g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, geometry.name)
        if g < 0:  # an unnamed geom: '<body>_geom<id>'
            g = int(geometry.name.rsplit("_geom", 1)[1])
        np.testing.assert_allclose(p[k], data.geom_xpos[g], atol=1e-12, err_msg=geometry.name)
        np.testing.assert_allclose(R[k], data.geom_xmat[g].reshape(3, 3), atol=1e-12, err_msg=geometry.name)


def test_chain_geometry_on_offset_and_welded_bodies():
    model = compiled(CHAIN)
    plant = RigidBodySystem.from_mjcf(model, contact=True)
    assert plant.collision.geometries[0].link == "base"  # a static body: fixed to the world
    for seed in range(3):
        qpos, qvel = random_state(model, np.random.default_rng(seed))
        data = mujoco_acceleration(model, qpos, qvel, np.zeros(model.nu))
        check_geometry_poses(plant, model, data, to_plant(model, qpos, qvel)[: model.nq])


def test_contype_conaffinity_filtering():
    xml = """<mujoco><worldbody>
      <geom name="floor" type="plane" size="1 1 .1" contype="1" conaffinity="2"/>
      <body name="a" pos="0 0 1"><joint type="slide" axis="0 0 1"/>
        <geom name="a" type="sphere" size=".1" contype="2" conaffinity="0"/></body>
      <body name="b" pos="1 0 1"><joint type="slide" axis="0 0 1"/>
        <geom name="b" type="sphere" size=".1" contype="4" conaffinity="4"/></body>
      <body name="c" pos="2 0 1"><joint type="slide" axis="0 0 1"/>
        <geom name="c" type="sphere" size=".1" contype="1" conaffinity="1"/></body>
    </worldbody><contact><exclude body1="a" body2="c"/></contact></mujoco>"""
    plant = RigidBodySystem.from_mjcf(compiled(xml), contact=True)
    excluded = {frozenset(p) for p in plant.collision.excluded_link_pairs}
    # floor-a: 1 & 0 = 0 but 2 & 2 != 0 -> touch; floor-b, a-b: no common bit; a-c: <exclude>;
    # floor-c: 1 & 1 -> touch; b-c: no common bit
    assert excluded == {frozenset(p) for p in [("world", "b"), ("a", "b"), ("a", "c"), ("b", "c")]}
    # all three spheres 5 cm into the floor: only a and c are pushed, by Drake's default
    # stiffness (1e6 N/m each side, 5e5 N/m combined) at rest
    results = jax.jit(plant.contact_results)(np.array([-0.95, -0.95, -0.95, 0.0, 0.0, 0.0]))
    names = plant.contact.names
    pushed = {names[b] for a, b, on in zip(results.geometry_a, results.geometry_b, results.active) if on}
    pushed |= {names[a] for a, b, on in zip(results.geometry_a, results.geometry_b, results.active) if on}
    assert pushed == {"floor", "a", "c"}
    np.testing.assert_allclose(np.abs(np.asarray(results.force)[np.asarray(results.active), 2]), 5e5 * 0.05, rtol=1e-9)


def test_explicit_pairs_make_their_geoms_touch_whatever_the_filters_say():
    """Visual-only geoms (contype = conaffinity = 0) named by a <pair> collide with each other
    alone; a pair overrides an <exclude> too. MuJoCo's humanoid: its four foot capsules touch
    the floor, and nothing else touches."""
    xml = """<mujoco><worldbody>
      <geom name="floor" type="plane" size="1 1 .1" contype="0" conaffinity="0"/>
      <body name="a" pos="0 0 1"><joint type="slide" axis="0 0 1"/>
        <geom name="a" type="sphere" size=".1" contype="0" conaffinity="0"/></body>
      <body name="b" pos="1 0 1"><joint type="slide" axis="0 0 1"/>
        <geom name="b" type="sphere" size=".1" contype="0" conaffinity="0"/>
        <body name="c" pos="0 0 -0.15"><joint type="slide" axis="1 0 0"/>
          <geom name="c" type="sphere" size=".1" contype="0" conaffinity="0"/></body></body>
      <body name="d" pos="2 0 1"><joint type="slide" axis="0 0 1"/>
        <geom name="d" type="sphere" size=".1" contype="0" conaffinity="0"/></body>
    </worldbody><contact><exclude body1="b" body2="c"/><pair geom1="a" geom2="floor"/><pair geom1="b" geom2="c"/>
      <pair geom1="floor" geom2="b"/></contact></mujoco>"""
    plant = RigidBodySystem.from_mjcf(compiled(xml), contact=True)
    assert set(plant.contact.names) == {"floor", "a", "b", "c"}   # d is in no pair: visual only
    excluded = {frozenset(p) for p in plant.collision.excluded_link_pairs}
    assert excluded == {frozenset(p) for p in [("world", "c"), ("a", "b"), ("a", "c")]}
    # a and b 5 cm into the floor, c 5 cm into b (its parent, and excluded, yet paired): each pushed
    # by Drake's default stiffness at rest (5e5 N/m combined)
    results = jax.jit(plant.contact_results)(np.array([-0.95, -0.95, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
    active = np.asarray(results.active)
    names = plant.contact.names
    touching = {frozenset((names[a], names[b])) for a, b, on in zip(results.geometry_a, results.geometry_b, active) if on}
    assert touching == {frozenset(p) for p in [("floor", "a"), ("floor", "b"), ("b", "c")]}
    np.testing.assert_allclose(np.linalg.norm(np.asarray(results.force)[active], axis=1), 5e5 * 0.05, rtol=1e-9)
    path = pathlib.Path(mujoco.__file__).parent / "mjx/test_data/humanoid/humanoid.xml"
    if path.exists():
        humanoid = RigidBodySystem.from_mjcf(path, contact=True)
        assert set(humanoid.contact.names) == {"floor", "foot1_left", "foot2_left", "foot1_right", "foot2_right"}
        assert {frozenset(p) for p in humanoid.collision.excluded_link_pairs} == {frozenset(("foot_left", "foot_right"))}


@pytest.mark.parametrize("body, message", [
    ('<body><joint name="ball" type="ball"/><geom size=".1"/></body>', r"joint 'ball' .*ball joint.*three hinges"),
    ('<body><joint name="j" type="free" armature="0.1"/><geom size=".1"/></body>',
     r"joint 'j' .*free joint with armature 0.1.*hinges and slides.*ignore_armature=True"),
    ('<body><joint name="j" type="free" stiffness="2"/><geom size=".1"/></body>',
     r"joint 'j' .*free joint with a spring \(stiffness 2\).*remove it"),
])
def test_unsupported_models_are_named_errors(body, message):
    with pytest.raises(MJCFError, match=message):
        RigidBodySystem.from_mjcf(compiled(f"<mujoco><worldbody>{body}</worldbody></mujoco>"))


def test_armature_can_be_ignored_and_actuators_chosen():
    xml = """<mujoco><worldbody><body><joint name="j" armature="0.1"/><geom size=".1" mass="1"/></body></worldbody>
      <actuator><general name="filtered" joint="j" dyntype="filter" dynprm="0.1"/></actuator></mujoco>"""
    with pytest.raises(MJCFError, match=r"actuator 'filtered' has activation dynamics \(dyntype filter.*"
                                        r"actuated=\[joint names\]"):
        RigidBodySystem.from_mjcf(compiled(xml), ignore_armature=True)
    plant = RigidBodySystem.from_mjcf(compiled(xml), ignore_armature=True, actuated=["j"])
    assert plant.input_frame.coordinates == ("j",) and plant.tree.armature is None
    np.testing.assert_allclose(RigidBodySystem.from_mjcf(compiled(xml), actuated=["j"]).tree.armature, [0.1])


def test_shapes_the_plant_cannot_collide_are_named_errors():
    # without the excludes, the torso's cylinder and hull are paired with the legs' capsules
    plant = RigidBodySystem.from_mjcf(compiled(quadruped_xml(exclude=False)), contact=True)
    assert {(a, b) for a, b, *_ in plant.contact.groups} >= {("capsule", "cylinder"), ("capsule", "convex")}
    xml = """<mujoco><worldbody><body><joint/><geom name="egg" type="ellipsoid" size=".1 .2 .3"/></body>
      </worldbody></mujoco>"""
    with pytest.raises(MJCFError, match=r"geom 'egg' \(body 'body1'\) has type=.ellipsoid..*contype=\"0\""):
        RigidBodySystem.from_mjcf(compiled(xml), contact=True)
    RigidBodySystem.from_mjcf(compiled(xml))  # without contact, geoms are only inertia


def test_compiler_errors_are_named(tmp_path):
    with pytest.raises(MJCFError, match="MuJoCo's compiler refused"):
        RigidBodySystem.from_mjcf(tmp_path / "nothing.xml")
    path = tmp_path / "nested_free.xml"  # MuJoCo itself refuses a free joint below the worldbody
    path.write_text('<mujoco><worldbody><body><joint/><geom size=".1"/><body><freejoint name="loose"/>'
                    '<geom size=".1"/></body></body></worldbody></mujoco>')
    with pytest.raises(MJCFError, match=r"nested_free.xml: MuJoCo's compiler refused the model: .*free joint"):
        RigidBodySystem.from_mjcf(path)


def test_the_initial_state_is_the_files_configuration_as_mujocos_reset():
    """x0 = None starts where `mj_resetData` does (qpos0): free bodies where the file places
    them (they sat at the world origin, inside each other), hinges and slides at their `ref`;
    every body frame then sits where MuJoCo's kinematics puts it."""
    tilted = """<mujoco><worldbody>
      <body name="crate" pos="0.3 -0.2 0.1" euler="10 20 30"><freejoint/><geom type="box" size=".1 .1 .1"/></body>
      <body name="ball" pos="1 0 0.5"><freejoint name="ball_free"/><geom type="sphere" size=".05"/></body>
    </worldbody></mujoco>"""
    for text in (tilted, FREE_BODIES_BESIDE_AN_ARM, CHAIN):
        model = compiled(text)
        plant = RigidBodySystem.from_mjcf(model)
        x0 = np.asarray(plant.initial_state())
        np.testing.assert_allclose(x0, to_plant(model, model.qpos0, np.zeros(model.nv)), atol=1e-15)
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        for b in range(1, model.nbody):
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b)
            R, p = frame_pose(plant.tree, x0[: plant.tree.nq], name)
            np.testing.assert_allclose(p, data.xpos[b], atol=1e-12)
            np.testing.assert_allclose(R, data.xmat[b].reshape(3, 3), atol=1e-12)


def test_a_plant_from_mjcf_is_drawn_by_mujocos_renderer_at_its_states(tmp_path):
    """`visualizer_for` a plant loaded from an MJCF file is MuJoCo's renderer of that file; a
    frame at the plant's state equals the frame MuJoCo renders at the same qpos (the floating
    quadruped's quaternion reordered); MeshCat names the remedy instead of misreading MJCF as URDF."""
    path = tmp_path / "quadruped.xml"
    path.write_text(quadruped_xml())
    plant = RigidBodySystem.from_mjcf(path)
    vis = jd.viz.visualizer_for(plant)
    assert isinstance(vis, jd.viz.MujocoVisualizer)
    model = mujoco.MjModel.from_xml_path(str(path))
    rng = np.random.default_rng(4)
    qposes = [random_state(model, rng)[0] for _ in range(2)]
    for qpos in qposes:   # the base near the origin, where the free camera looks
        qpos[:3] = rng.uniform(-0.1, 0.1, 3)
    xs = np.stack([to_plant(model, qpos, np.zeros(model.nv)) for qpos in qposes])
    theirs = jd.viz.MujocoVisualizer(jd.MujocoSystem.from_xml(path)).images(
        np.stack([np.concatenate([qpos, np.zeros(model.nv)]) for qpos in qposes]))
    ours = vis.images(xs)
    np.testing.assert_array_equal(ours, theirs)
    assert np.mean(np.any(ours[0] != ours[1], axis=-1)) > 0.01   # two different poses
    with pytest.raises(ValueError, match=r"loaded from an MJCF file.*MujocoVisualizer\(plant\)"):
        jd.viz.MeshcatVisualizer(plant)
    assert jd.viz.visualizer_for(RigidBodySystem.from_mjcf(DATA / "mj_cartpole.xml"), camera="side").camera == "side"
