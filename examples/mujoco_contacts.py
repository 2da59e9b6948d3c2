"""MuJoCo models with contacts under jaxdrake controllers, and batches of them.

- A one-legged vertical hopper (tests/data/mj_hopper.xml: a sprung telescopic leg, a foot in
  contact with the floor) regulated to a hop height by a jaxdrake controller: in stance, thrust
  k (M g h* - E) while the body rises, E the body's energy plus the leg spring's; in flight,
  the leg held at its rest length. Eight targets at once (vmap over the controller's
  parameter), one run checked against C MuJoCo's mj_step under the same controller.
- A batch of humanoid rollouts (MJX's test humanoid, every body geom given contact with the
  floor): 256 randomly pushed humanoids under a posture-holding PD controller of four gains,
  run by `jd.run_batch` in chunks. A joint-space PD cannot balance a floating humanoid; the
  study measures how long each gain keeps it up.

Needs `pip install 'jaxdrake[mujoco]'` (mujoco and mujoco-mjx 3.17.0).

Run:  python examples/mujoco_contacts.py [--out DIR]
      (saves mujoco_contacts.png, mujoco_hopper.gif and mujoco_humanoid.gif, drawn by MuJoCo)
"""

import pathlib
import time

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jaxdrake as jd  # noqa: E402
from _cli import run, save  # noqa: E402  (examples/_cli.py)

jax.config.update("jax_enable_x64", True)
DATA = pathlib.Path(__file__).resolve().parents[1] / "tests/data"
BODY_MASS, LEG_STIFFNESS, G = 4.0, 2000.0, 9.81  # as in mj_hopper.xml


def hop_thrust(t, x, target):
    """The hopper's leg force for state x = [height, leg, heightdot, legdot] (height: the body's
    rise above touch-down with the leg at rest; leg: extension, negative when compressed)."""
    height, leg, rise, legdot = x
    stance = height - leg < 1e-3  # the foot on the floor
    total_mass = BODY_MASS + 0.4  # the leg and foot fly with the body
    energy = BODY_MASS * G * height + 0.5 * BODY_MASS * rise**2 + 0.5 * LEG_STIFFNESS * leg**2
    push = jnp.where(rise > 0, jnp.clip(50.0 * (total_mass * G * target - energy), 0.0, 400.0), 0.0)
    return jnp.atleast_1d(jnp.where(stance, push, -300.0 * leg - 20.0 * legdot))


def hopper_controller(hopper, target):
    return jd.System.from_functions(output=lambda t, x, u, target: hop_thrust(t, u, target), num_states=0,
                                    num_inputs=hopper.num_states, params=target)


def hopper_study(ax, out):
    import mujoco

    hopper = jd.MujocoSystem.from_xml(DATA / "mj_hopper.xml")
    x0 = jnp.array([0.1, 0.0, 0.0, 0.0])
    T, dt = 5.0, hopper.sample_time
    ts = dt * jnp.arange(round(T / dt))  # the step instants (the state holds between them)

    def hop(target):
        return jd.simulate(jd.feedback(hopper, hopper_controller(hopper, target)), (0.0, T), x0).state(ts)

    start = time.perf_counter()
    targets = jnp.linspace(0.05, 0.3, 8)
    runs = np.asarray(jax.jit(jax.vmap(hop))(targets))
    print(f"hopper: 8 hop-height targets, {T:g} s each: {time.perf_counter() - start:.1f} s with compilation")
    clearance = runs[:, :, 0] - runs[:, :, 1]
    settled = clearance[:, ts > T - 1.0].max(axis=1)
    for target, apex in zip(np.asarray(targets), settled):
        print(f"  target {target:.3f} m: apex {apex:.3f} m in the last second")
    for x, target in zip(runs[::2], np.asarray(targets)[::2]):
        line, = ax.plot(ts, x[:, 0] - x[:, 1], lw=1, label=f"h* = {target:.2f} m")
        ax.axhline(target, color=line.get_color(), ls=":", lw=1)

    model, data = hopper.mj_model, mujoco.MjData(hopper.mj_model)  # C MuJoCo, the same controller
    data.qpos[:] = np.asarray(x0[:2])
    c_runs = []
    for _ in range(int(round(T / model.opt.timestep))):
        c_runs.append(np.r_[data.qpos, data.qvel])
        data.ctrl[:] = np.clip(np.asarray(hop_thrust(0.0, jnp.asarray(c_runs[-1]), targets[5])), -400, 400)
        mujoco.mj_step(model, data)
    gap = np.abs(np.asarray(c_runs) - runs[5]).max(axis=1)
    print(f"  target {float(targets[5]):.3f} m vs C MuJoCo, step by step: max |state gap| "
          f"{gap[np.asarray(ts) <= 1.0].max():.1e} in the first second, {gap.max():.1e} over {T:g} s")
    ax.set(xlabel="t (s)", ylabel="foot height above the floor (m)", title="MJCF hopper under a jaxdrake hop-height controller\n"
           "(dotted: the targets; contacts by MJX)")
    ax.legend(fontsize=7)
    movie = jd.viz.MujocoVisualizer(hopper, camera="side", width=320, height=240).save(
        jd.simulate(jd.feedback(hopper, hopper_controller(hopper, 0.25)), (0.0, 3.0), x0),
        out / "mujoco_hopper.gif", fps=20)
    print(f"saved {movie} (MuJoCo's renderer)")


def humanoid_with_floor_contacts():
    """MJX's test humanoid, whose file gives only the feet contact with the floor: every body
    geom gets a contact pair with the floor, so a fall lands on the ground."""
    import mujoco
    from mujoco import mjx

    spec = mujoco.MjSpec.from_file(str(pathlib.Path(mjx.__file__).parent / "test_data/humanoid/humanoid.xml"))
    paired = {pair.geomname1 for pair in spec.pairs if pair.geomname2 == "floor"}
    for geom in spec.geoms:
        if geom.name not in paired | {"floor", ""}:
            spec.add_pair(geomname1=geom.name, geomname2="floor")
    return jd.MujocoSystem(spec.compile())


def humanoid_study(ax_height, ax_fall, out):
    humanoid = humanoid_with_floor_contacts()
    model = humanoid.mj_model
    joints = model.actuator_trnid[:, 0]
    q_index, v_index = model.jnt_qposadr[joints], model.nq + model.jnt_dofadr[joints]
    gear, standing = model.actuator_gear[:, 0], model.qpos0[model.jnt_qposadr[joints]]

    def posture_pd(t, x, u, kp):  # u is the humanoid's state; controls are torques / gear
        return (kp * (standing - u[q_index]) - 0.1 * kp * u[v_index]) / gear

    T, ts = 3.0, jnp.linspace(0.0, 3.0, 61)

    def rollout(member):
        key, kp = member
        pd = jd.System.from_functions(output=posture_pd, num_states=0, num_inputs=humanoid.num_states,
                                      params=kp)
        x0 = humanoid.initial_state().at[model.nq: model.nq + model.nv].set(0.3 * jax.random.normal(key, (model.nv,)))
        return jd.simulate(jd.feedback(humanoid, pd), (0.0, T), x0).state(ts)[:, 2]  # torso height

    gains = np.array([0.0, 100.0, 400.0, 1600.0])
    per_gain = 64
    members = (jax.random.split(jax.random.key(0), per_gain * len(gains)), np.repeat(gains, per_gain))
    start = time.perf_counter()
    heights = jd.run_batch(rollout, members, chunk_size=128)
    print(f"humanoid: {len(members[1])} pushed rollouts of {T:g} s ({model.nv} dof, contacts) by run_batch in chunks "
          f"of 128: {time.perf_counter() - start:.1f} s with compilation")
    fallen = heights < 0.8
    fall_time = np.where(fallen.any(axis=1), np.asarray(ts)[fallen.argmax(axis=1)], np.inf)
    for k, kp in enumerate(gains):
        group = slice(k * per_gain, (k + 1) * per_gain)
        ax_height.plot(ts, heights[group][:16].T, color=f"C{k}", lw=0.6, alpha=0.7)
        ax_height.plot([], [], color=f"C{k}", label=f"kp = {kp:g}")
        print(f"  kp = {kp:6g}: median time to fall {np.median(fall_time[group]):.2f} s, "
              f"{np.isinf(fall_time[group]).mean():.0%} still up at {T:g} s")
    ax_fall.boxplot([np.minimum(fall_time[k * per_gain:(k + 1) * per_gain], T) for k in range(len(gains))],
                    tick_labels=[f"{kp:g}" for kp in gains])
    ax_height.set(xlabel="t (s)", ylabel="torso height (m)", title="pushed humanoids under a posture PD\n(16 of 64 per gain)")
    ax_height.legend(fontsize=7)
    ax_fall.set(xlabel="PD gain kp (N m / rad before the gear)", ylabel="time until the torso is below 0.8 m (s)",
                title=f"{len(members[1])} humanoids: the PD delays the fall")
    pd = jd.System.from_functions(output=posture_pd, num_states=0, num_inputs=humanoid.num_states, params=100.0)
    x0 = humanoid.initial_state().at[model.nq: model.nq + model.nv].set(
        0.3 * jax.random.normal(members[0][per_gain], (model.nv,)))
    movie = jd.viz.MujocoVisualizer(humanoid, camera="side", width=320, height=240).save(
        jd.simulate(jd.feedback(humanoid, pd), (0.0, T), x0), out / "mujoco_humanoid.gif", fps=15)
    print(f"saved {movie} (MuJoCo's renderer)")


def main(out: pathlib.Path) -> pathlib.Path:
    out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.6), layout="constrained")
    hopper_study(axes[0], out)
    humanoid_study(axes[1], axes[2], out)
    return save(fig, out, "mujoco_contacts.png")


if __name__ == "__main__":
    run(main, __doc__)
