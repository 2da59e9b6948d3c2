"""Contact in the rigid-body plant: Drake's compliant point contact, error-controlled and
differentiable.

- Solo-12 (example-robot-data) standing on the floor: contact spheres at its feet, knees and
  base corners (as in benchmarks/contact_benchmark.py), a joint PD about a crouched stance plus
  the feed-forward torque that holds it with vertical ground forces (inverse dynamics at rest),
  pushed sideways (a lateral base velocity of 0.8 m/s in the initial state), simulated for 1 s.
  Plots the base's height and sideways travel and the normal forces on the left and right feet
  (`contact_results`); writes a 3-D MeshCat scene with the contact forces drawn as arrows (one
  offline .html file).
- Closed forms: a box sliding on the floor stops after v0^2 / (2 mu g), and that distance's
  derivative in mu (forward mode through the simulation) is -v0^2 / (2 mu^2 g); a ball thrown
  sliding ends rolling at 5/7 of its speed (up to the compliant correction: it rolls about a
  point x/2 below its undeformed surface, x = m g / k its static penetration).
- A gradient-based identification through contact: the friction coefficient of a sliding box
  from 12 noisy positions of its slide and stop, by Gauss-Newton steps on the positions'
  derivative (forward mode, jax.jvp: one parameter).

About 40 s on a 2-core CPU, mostly compiling (Solo-12's simulation 4-10 s, its MeshCat scene
5 s, the box's value-and-derivative program 10 s, the ball 4-5 s). Solo-12 keeps Drake's
stiction tolerance (1e-4 m/s), with which the light lower legs make friction stiff
(eigenvalues -4e4 to -1e6 /s; dopri5 crawls: 10^5 steps reach t = 0.2 s), and rubber-like
feet (Hunt-Crossley dissipation 2 s/m). It runs the linearly implicit
`Rosenbrock23(jacobian="stiff")`, whose matrix comes from the contact's springs, dampers,
friction slopes and the contact points' motion alone (`RigidBodySystem.stiff_linearization`):
459 accepted and 69 rejected steps, about 0.07 s once compiled. With a stiction tolerance of
3 cm/s it would take 425 + 20 steps (0.06 s), dopri5 3779 + 355 (0.5 s).

Needs the example-robot-data package (installed with the test extras) and the viz extra.

Run:  python examples/contact.py [--out DIR]      (saves contact.png and contact_solo.html)
"""

import importlib.metadata
import pathlib
import tempfile
import time

import equinox as eqx
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
G = 9.81
LEGS = ("FL", "FR", "HL", "HR")
# Solo-12's contact spheres: (link, centre in the link's frame, radius)
SPHERES = ([(f"{leg}_FOOT", (0.0, 0.0, 0.0), 0.02) for leg in LEGS]
           + [(f"{leg}_LOWER_LEG", (0.0, 0.0, 0.0), 0.02) for leg in LEGS]
           + [("base_link", (x, y, 0.0), 0.03) for x in (-0.19, 0.19) for y in (-0.1, 0.1)])
RUBBER = jd.multibody.ContactMaterial(point_contact_stiffness=2e5, hunt_crossley_dissipation=2.0,
                                      mu_static=0.8, mu_dynamic=0.6)
KP, KD = 6.0, 0.3  # N m / rad, N m s / rad
BOX_URDF = """<?xml version="1.0"?>
<robot name="box" xmlns:drake="http://drake.mit.edu">
  <link name="box">
    <inertial><mass value="2.0"/><inertia ixx="0.0133" iyy="0.0133" izz="0.0133" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision name="box">
      <geometry><box size="0.2 0.2 0.2"/></geometry>
      <drake:proximity_properties>
        <drake:point_contact_stiffness value="1e6"/>
        <drake:hunt_crossley_dissipation value="50"/>
        <drake:mu_static value="0.4"/>
        <drake:mu_dynamic value="0.4"/>
      </drake:proximity_properties>
    </collision>
  </link>
</robot>
"""


def material(k, d, mu_static, mu_dynamic):
    return jd.multibody.ContactMaterial(point_contact_stiffness=k, hunt_crossley_dissipation=d,
                                        mu_static=mu_static, mu_dynamic=mu_dynamic)


# ----- Solo-12 standing, pushed ---------------------------------------------------------------

def solo12():
    """Solo-12 from example-robot-data (its visuals for MeshCat; its mesh collisions not read:
    contact=False), with contact spheres and a floor."""
    robots = pathlib.Path(str(importlib.metadata.distribution("example-robot-data").locate_file(
        "cmeel.prefix/share/example-robot-data/robots")))
    plant = jd.RigidBodySystem.from_urdf(robots / "solo_description/robots/solo12.urdf", floating_base=True,
                                         joint_limits=False, effort_limits=False,
                                         package_map={"example-robot-data": robots.parent})  # its meshes
    for i, (link, centre, radius) in enumerate(SPHERES):
        plant = plant.with_collision_geometry(link, jd.geometry.Sphere(radius), translation=centre,
                                              name=f"sphere{i}", material=RUBBER)
    return plant.with_ground(material=RUBBER)   # Drake's stiction tolerance, 1e-4 m/s


def crouched_stance(plant):
    """The crouched configuration (hips 0.8 rad, knees -1.6 rad, mirrored for the hind legs),
    lowered onto the floor until each foot carries a quarter of the weight."""
    tree = plant.tree
    q = np.array(tree.neutral_configuration())
    for joint, angle in (("HFE", 0.8), ("KFE", -1.6)):
        for leg in LEGS:
            q[tree.q_starts[tree.joint_names.index(f"{leg}_{joint}")]] = angle if leg[0] == "F" else -angle
    # jitted: a plant method called eagerly compiles each of its operations on first use (seconds)
    foot = float(jax.jit(lambda q: plant.frame_pose(q, "FL_FOOT")[1][2])(jnp.asarray(q)))  # base at z = 0
    weight = float(jnp.sum(tree.mass)) * G
    k = RUBBER.point_contact_stiffness / 2  # two equal materials in series
    q[2] = -foot + 0.02 - weight / 4 / k
    return jnp.asarray(q)


def posture_controller(plant, q_stance):
    """u = u_ff + kp (q* - q) - kd v on the 12 joints; u_ff holds q* at rest: the inverse
    dynamics at zero velocity and acceleration, G(q*) minus the ground forces' generalized force
    there (vertical: no slip, no friction). Its base rows vanish: the stance is an equilibrium."""
    tree = plant.tree
    at_rest = jnp.zeros(tree.nv)
    holding = np.asarray(jax.jit(plant.inverse_dynamics)(q_stance, at_rest, at_rest))
    print(f"  holding torques {np.round(holding[6:9], 3)} N m (one leg); base rows {np.abs(holding[:6]).max():.1e}")
    params = {"q": q_stance[7:], "u": jnp.asarray(holding[6:])}

    def torque(t, x, y, p):
        return p["u"] + KP * (p["q"] - y[7:tree.nq]) - KD * y[tree.nq + 6:]

    return jd.System.from_functions(output=torque, num_states=0, num_inputs=plant.num_states,
                                    num_outputs=plant.num_inputs, params=params)


def solo_study(axes, out):
    plant = solo12()
    q_stance = crouched_stance(plant)
    x0 = jnp.concatenate([q_stance, jnp.zeros(plant.tree.nv)]).at[plant.tree.nq + 1].set(0.8)  # pushed
    start = time.perf_counter()
    traj = jd.simulate(jd.feedback(plant, posture_controller(plant, q_stance)), (0.0, 1.0), x0,
                       solver=jd.simulation.Rosenbrock23(jacobian="stiff"), rtol=1e-3, atol=1e-5, max_steps=20000)
    traj.final_state.block_until_ready()
    print(f"Solo-12 pushed at 0.8 m/s, 1 s: {int(traj.num_steps)} steps, {time.perf_counter() - start:.1f} s "
          "with compilation (Rosenbrock23 on the stiff linearization, rtol 1e-3)")
    ts = jnp.linspace(0.0, 1.0, 201)

    @jax.jit  # one program: sampling the dense output, and the contact results at each sample
    def sampled(traj):
        xs = traj.state(ts)[:, : plant.num_states]
        return xs, jax.vmap(plant.contact_results)(xs)

    xs, results = sampled(traj)
    normal = -np.sum(np.asarray(results.force) * np.asarray(results.normal), axis=-1)  # >= 0
    links = plant.contact.links  # of each geometry ('world' for the floor)
    on_floor = [links[b] if links[a] == "world" else links[a] for a, b in zip(results.geometry_a, results.geometry_b)]
    ts, xs = np.asarray(ts), np.asarray(xs)
    ax = axes[0]
    ax.plot(ts, 100 * xs[:, 2], color="C0")
    ax.set(xlabel="t (s)", title="Solo-12 pushed sideways (0.8 m/s) under a posture PD")
    ax.set_ylabel("base height z (cm)", color="C0")
    side = ax.twinx()
    side.plot(ts, 100 * xs[:, 1], color="C1")
    side.set_ylabel("sideways travel y (cm)", color="C1")
    ax = axes[1]
    weight = float(jnp.sum(plant.tree.mass)) * G
    for side, legs in (("left", ("FL", "HL")), ("right", ("FR", "HR"))):  # front and hind alike
        feet = np.isin(on_floor, [f"{leg}_FOOT" for leg in legs])
        ax.plot(ts, normal[:, feet].sum(axis=1), lw=1.5, label=f"{side} feet ({' + '.join(legs)})")
    ax.plot(ts, normal.sum(axis=1), "k", lw=1.5, label="all contacts")
    ax.axhline(weight, color="0.5", ls=":", lw=1, label="weight m g")
    ax.set(xlabel="t (s)", ylabel="N", ylim=(0, 1.4 * weight),
           title="normal forces: the push loads the left feet, unloads the right")
    ax.legend(fontsize=8, ncol=2, loc="upper right")
    touching = sorted({link for link, on in zip(on_floor, np.asarray(results.active).any(axis=0)) if on})
    print(f"  touching at some time: {', '.join(touching)}; base height {100 * xs[0, 2]:.2f} -> "
          f"{100 * xs[-1, 2]:.2f} cm, sideways {100 * xs[-1, 1]:.1f} cm")
    start = time.perf_counter()
    vis = jd.viz.MeshcatVisualizer(plant, contact_forces=True, newtons_per_meter=100.0)
    path = vis.save(traj, out / "contact_solo.html", fps=30)
    print(f"saved {path}: the 3-D scene, contact forces as green arrows ({time.perf_counter() - start:.1f} s)")


# ----- closed forms and a gradient through contact --------------------------------------------

def sliding_box(folder):
    path = pathlib.Path(folder) / "box.urdf"
    path.write_text(BOX_URDF)
    box = jd.RigidBodySystem.from_urdf(path, floating_base=True, contact=True)  # reads <collision>
    return box.with_ground(material=material(1e6, 50.0, 0.4, 0.4))


def box_slide(box, v0, ts):
    """`slide(mu)`: the box's positions x(ts) sliding from v0 on the floor with friction
    coefficient mu (the box's and the floor's: combined, mu), and their derivative dx/dmu by
    forward mode (one program for both: jax.jvp)."""
    x0 = jnp.array([0.0, 0.0, 0.1 - 2.0 * G / (4 * 5e5), 0, 0, 0, 1, v0, 0, 0, 0, 0, 0])  # on its 4 corners

    def positions(mu):
        slippery = eqx.tree_at(lambda p: (p.contact.mu_static, p.contact.mu_dynamic), box,
                               (jnp.full(2, mu), jnp.full(2, mu)))
        traj = jd.simulate(slippery, (0.0, ts[-1]), x0, rtol=1e-6, atol=1e-8, max_steps=4000, autodiff="forward")
        return traj.state(ts)[:, 0]

    return jax.jit(lambda mu: jax.jvp(positions, (mu,), (jnp.ones_like(mu),)))


def box_and_ball(ax, slide, ts, v0):
    mu = 0.4
    start = time.perf_counter()
    x, dx_dmu = (np.asarray(a) for a in slide(jnp.asarray(mu)))
    print(f"box sliding at {v0} m/s, mu = {mu}: stops after {x[-1]:.6f} m, v0^2/(2 mu g) = "
          f"{v0 ** 2 / (2 * mu * G):.6f} m; d/dmu {dx_dmu[-1]:.5f}, closed form -v0^2/(2 mu^2 g) = "
          f"{-v0 ** 2 / (2 * mu ** 2 * G):.5f} ({time.perf_counter() - start:.1f} s with compilation)")
    t_stop = v0 / (mu * G)
    ax.plot(ts, x, label="box: x(t) (m)")
    ts = np.asarray(ts)
    exact = np.where(ts < t_stop, v0 * ts - mu * G * ts ** 2 / 2, v0 ** 2 / (2 * mu * G))
    ax.plot(ts[::8], exact[::8], "k.", ms=4, label=r"$v_0 t - \mu g t^2/2$, then $v_0^2/(2\mu g)$")

    ball = jd.RigidBodySystem.from_urdf(DATA / "contact_ball.urdf", floating_base=True, contact=True).with_ground(
        material=material(1e6, 50.0, 0.8, 0.6))
    m, r, inertia = 2.0, 0.1, 0.008  # a solid ball: I = 2/5 m r^2
    start = time.perf_counter()

    @jax.jit
    def rolling(x0):
        """The ball's velocity and spin in the world frame at ts (the floating base's velocities
        are in the ball's frame: rotated into the world's)."""
        xs = jd.simulate(ball, (0.0, ts[-1]), x0, rtol=1e-8, atol=1e-10, max_steps=20000).state(ts)
        R = jax.vmap(lambda q: ball.frame_pose(q, "ball")[0])(xs[:, :7])
        return jnp.einsum("nij,nj->ni", R, xs[:, 7:10]), jnp.einsum("nij,nj->ni", R, xs[:, 10:13])

    v, w = (np.asarray(a) for a in rolling(jnp.array([0.0, 0.0, r, 0, 0, 0, 1, v0, 0, 0, 0, 0, 0])))
    k = 3e4 * 1e6 / (3e4 + 1e6)  # the ball's and the floor's stiffness in series
    lever = r - m * G / k / 2
    print(f"ball thrown sliding at {v0} m/s: ends at {v[-1, 0]:.6f} m/s, 5/7 v0 = {5 / 7 * v0:.6f}, with the "
          f"compliant lever r - x/2: {v0 / (1 + inertia / (m * lever ** 2)):.6f}; spin x lever "
          f"{w[-1, 1] * lever:.6f} m/s ({time.perf_counter() - start:.1f} s with compilation)")
    ax.plot(ts, v[:, 0], label="ball: speed v(t) (m/s)")
    ax.plot(ts, w[:, 1] * r, "--", label=r"ball: $\omega r$ (m/s)")
    ax.axhline(5 / 7 * v0, color="k", ls=":", lw=1, label=r"$5/7\, v_0$")
    ax.set(xlabel="t (s)", ylabel="m, m/s", title="closed forms: a box slides to a stop, a ball starts rolling")
    ax.legend(fontsize=7)


def identify_friction(ax, slide, ts):
    """mu from 12 noisy positions of a slide and stop: least squares by Gauss-Newton steps,
    the residuals' derivative by forward mode through the simulation (the stop included)."""
    mu_true, sample = 0.35, np.arange(10, len(ts), 14)[:12]
    measured = np.asarray(slide(jnp.asarray(mu_true))[0])[sample] + 0.002 * np.random.default_rng(0).normal(size=12)
    mu, history = 0.6, []
    start = time.perf_counter()
    for _ in range(5):
        x, dx_dmu = (np.asarray(a)[sample] for a in slide(jnp.asarray(mu)))
        r = x - measured
        history.append(mu)
        mu -= float(dx_dmu @ r / (dx_dmu @ dx_dmu))
    print(f"friction identified from 12 positions (2 mm noise): mu = {mu:.4f} (true {mu_true}); iterates "
          + ", ".join(f"{m:.4f}" for m in history) + f" ({time.perf_counter() - start:.1f} s)")
    for value, style, label in ((history[0], "--", f"first guess mu = {history[0]:.2f}"),
                                (mu, "-", f"identified mu = {mu:.3f}")):
        ax.plot(ts, slide(jnp.asarray(value))[0], style, label=label)
    ax.plot(np.asarray(ts)[sample], measured, "ko", ms=4, label=f"measured (mu = {mu_true}, 2 mm noise)")
    ax.set(xlabel="t (s)", ylabel="x (m)", title="friction identified through contact (forward mode)")
    ax.legend(fontsize=8)


def main(out: pathlib.Path) -> pathlib.Path:
    out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 4, figsize=(21, 4.4), layout="constrained")
    solo_study(axes[:2], out)
    with tempfile.TemporaryDirectory() as folder:
        box = sliding_box(folder)
    v0, ts = 2.0, jnp.linspace(0.0, 0.85, 171)
    slide = box_slide(box, v0, ts)
    box_and_ball(axes[2], slide, ts, v0)
    identify_friction(axes[3], slide, ts)
    return save(fig, out, "contact.png")


if __name__ == "__main__":
    run(main, __doc__)
