"""MuJoCo models as systems (the notes' D.3.3: existing models as blocks), stepped by MJX.

- A cart-pole written in MJCF (tests/data/mj_cartpole.xml) balanced upright by
  `jd.control.lqr` of its linearized MuJoCo update (a discrete LQR), closed with `jd.feedback`,
  from several tilts at once (vmap).
- A ball dropped onto a plane with contacts, from 64 heights and spins in one vmapped call,
  against the same drops stepped by C MuJoCo's own mj_step.

Needs `pip install 'jaxdrake[mujoco]'` (mujoco and mujoco-mjx 3.17.0).

Run:  python examples/mujoco_models.py [--out DIR]
      (saves mujoco_models.png and mujoco_cartpole.gif, drawn by MuJoCo's own renderer)
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


def main(out: pathlib.Path) -> pathlib.Path:
    import mujoco

    fig, axes = plt.subplots(1, 3, figsize=(17, 4.6), layout="constrained")
    cartpole = jd.MujocoSystem.from_xml(DATA / "mj_cartpole.xml")
    print(f"cart-pole: state {cartpole.state_frame}, input {cartpole.input_frame}, period {cartpole.sample_time} s")
    start = time.perf_counter()
    lqr = jd.control.lqr(cartpole, jnp.diag(jnp.array([1.0, 10.0, 1.0, 1.0])), jnp.eye(1), x0=jnp.zeros(4), u0=jnp.zeros(1))
    closed = jd.feedback(cartpole, lqr.controller)
    tilts = jnp.linspace(-0.25, 0.25, 7)
    ts = jnp.linspace(0.0, 6.0, 601)
    runs = jax.jit(jax.vmap(lambda a: jd.simulate(closed, (0.0, 6.0), jnp.array([0.0, a, 0.0, 0.0])).state(ts)))(tilts)
    print(f"LQR of the MuJoCo update and 7 closed-loop runs: {time.perf_counter() - start:.1f} s with compilation; "
          f"K = {np.asarray(lqr.K).round(2)}")
    for x, a in zip(np.asarray(runs), np.asarray(tilts)):
        axes[0].plot(ts, x[:, 1], label=f"{a:+.2f} rad")
        axes[1].plot(ts, x[:, 0])
    movie = jd.viz.MujocoVisualizer(cartpole, camera="side", width=320, height=240).save(
        jd.simulate(closed, (0.0, 2.0), jnp.array([0.0, 0.25, 0.0, 0.0])), out / "mujoco_cartpole.gif", fps=12)
    print(f"saved {movie} (MuJoCo's renderer)")
    axes[0].set(xlabel="t (s)", ylabel="pole angle (rad)", title="MJCF cart-pole balanced by LQR of its MJX update")
    axes[0].legend(fontsize=7, ncol=2)
    axes[1].set(xlabel="t (s)", ylabel="cart position (m)", title="the cart returns to the origin")

    ball = jd.MujocoSystem.from_xml(DATA / "mj_ball.xml")
    start = time.perf_counter()
    heights = jnp.linspace(0.4, 1.5, 64)
    x0s = jnp.asarray(ball.initial_state())[None].repeat(64, 0).at[:, 2].set(heights).at[:, 11].set(
        jnp.linspace(-20.0, 20.0, 64))  # spin about y (wy): friction turns it into rolling along x
    T = 2.0
    t_drop = jnp.linspace(0.0, T, 401)
    drops = jax.jit(jax.vmap(lambda x: jd.simulate(ball, (0.0, T), x).state(t_drop)))(x0s)
    print(f"64 ball drops with contacts: {time.perf_counter() - start:.1f} s with compilation")
    model = ball.mj_model
    data = mujoco.MjData(model)
    k = 40
    data.qpos[:], data.qvel[:] = np.asarray(x0s[k, :7]), np.asarray(x0s[k, 7:])
    c_heights = []
    for _ in range(int(round(T / model.opt.timestep))):
        c_heights.append(data.qpos[2])
        mujoco.mj_step(model, data)
    t_drop = np.asarray(t_drop)
    for x in np.asarray(drops)[::8]:
        axes[2].plot(x[:, 0], x[:, 2], lw=0.8)
    axes[2].plot(np.asarray(drops)[k][:, 0], np.asarray(drops)[k][:, 2], "k", lw=2, label="drop 40 (MJX)")
    axes[2].plot(np.asarray(drops)[k][-1, 0], np.asarray(drops)[k][-1, 2], "ko")
    c_ts = model.opt.timestep * np.arange(len(c_heights))
    gap = np.max(np.abs(np.interp(t_drop, c_ts, c_heights) - np.asarray(drops)[k][:, 2]))
    print(f"drop 40: max |height(MJX) - height(C MuJoCo)| = {gap:.2e} m (one solver iteration: a different line search)")
    axes[2].set(xlabel="x (m)", ylabel="height (m)", title="64 spinning balls dropped on a plane: paths in x-z\n(vmap, contacts; the spin becomes rolling)")
    axes[2].legend(fontsize=8)
    return save(fig, out, "mujoco_models.png")


if __name__ == "__main__":
    run(main, __doc__)
