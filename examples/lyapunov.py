"""Lyapunov analysis with sums of squares (Underactuated Robotics, ch. "Lyapunov analysis").

The chapter's examples, each certified by an SDP and then checked by simulation:
(a) a common Lyapunov function for a family of linear systems, decreasing along a randomly
switched trajectory; (b) global stability of the damped pendulum via SOS in (sin, cos, thetadot)
coordinates, V against the mechanical energy; (c) the one-dimensional cubic system, whose
certified region is exactly |x| < 1; (d) the time-reversed Van der Pol oscillator: the region
certified for the quadratic V from the linearization, the larger one found by searching over
quartic V, and simulated trajectories (converging inside, diverging outside the limit cycle).

Run:  python examples/lyapunov.py [--out DIR]     (saves lyapunov.png)
"""

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
import scipy.linalg

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jaxdrake as jd  # noqa: E402
from _cli import run, save  # noqa: E402  (examples/_cli.py)

jax.config.update("jax_enable_x64", True)
analysis = jd.analysis


def common_lyapunov(ax):
    """A family sharing x'P0x by construction; V = x'Px from the LMI along a switched run."""
    rng = np.random.default_rng(0)
    M = rng.normal(size=(3, 3))
    P0 = M @ M.T + np.eye(3)
    family = []
    for _ in range(3):
        N, W = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
        family.append(np.linalg.solve(P0, -(N @ N.T + 0.2 * np.eye(3)) + 2 * (W - W.T)))
    P = analysis.common_lyapunov_function(family)
    x, ts, Vs, modes = rng.normal(size=3), [0.0], [], []
    Vs.append(x @ P @ x)
    for k in range(40):  # switch to a random member every 0.25 s
        i = rng.integers(len(family))
        for _ in range(10):
            x = scipy.linalg.expm(family[i] * 0.025) @ x
            ts.append(ts[-1] + 0.025)
            Vs.append(x @ P @ x)
            modes.append(i)
    ax.semilogy(ts, Vs, color="k")
    for k, i in enumerate(modes[::10]):
        ax.axvspan(k * 0.25, (k + 1) * 0.25, color=f"C{i}", alpha=0.15, lw=0)
    ax.set(xlabel="t (s)", ylabel="V = x' P x",
           title="(a) common Lyapunov function under random switching (shade: active system)")


def global_pendulum(ax):
    pendulum = jd.models.Pendulum()
    mgl = pendulum.m * pendulum.g * pendulum.l
    s, c, w = jd.Polynomial.variables_of(3)
    V = analysis.global_lyapunov_function(
        analysis.trig_polynomial_system(pendulum, [0]), [0.0, 1.0, 0.0], 2,
        dissipation=(s**2 + (c - 1) ** 2 + w**2) * s**2, normalization=([1.0, 0.0, 0.0], mgl))
    print("pendulum: V =", V)
    q, qd = np.meshgrid(np.linspace(-2 * np.pi, 2 * np.pi, 201), np.linspace(-8, 8, 161))
    Vq = np.asarray(V(np.stack([np.sin(q), np.cos(q), qd], -1)))
    energy = 0.5 * pendulum.m * pendulum.l**2 * qd**2 + mgl * (1 - np.cos(q))
    levels = np.linspace(1, 20, 8)
    ax.contour(q, qd, Vq, levels=levels, cmap="viridis")
    ax.contour(q, qd, energy, levels=levels, colors="gray", linestyles="dashed", linewidths=0.8)
    traj = jd.simulate(pendulum, (0.0, 12.0), jnp.array([-2 * np.pi + 0.3, 7.0]))
    xs = np.asarray(traj.state(jnp.linspace(0.0, 12.0, 1500)))
    ax.plot(xs[:, 0], xs[:, 1], color="C3", lw=1.2, label="a damped trajectory")
    ax.set(xlabel="theta", ylabel="thetadot",
           title="(b) pendulum: SOS Lyapunov function V (solid) vs energy (dashed)")
    ax.legend(loc="upper right")


def cubic(ax):
    system = jd.models.SimpleCTExample()
    rho = analysis.region_of_attraction(system, [0.0], [[1.0]])
    print(f"cubic: certified rho = {rho:.6f} (exact: 1)")
    starts = jnp.linspace(-1.15, 1.15, 23)
    runs = jax.vmap(lambda x0: jd.simulate(system, (0.0, 4.0), x0[None], throw=False))(starts)
    ts = jnp.linspace(0.0, 4.0, 300)
    for k, x0 in enumerate(np.asarray(starts)):
        xs = np.clip(np.asarray(runs[k].state(ts))[:, 0], -3, 3)
        ax.plot(ts, xs, color="C2" if abs(x0) ** 2 < rho else "C3", lw=1)
    ax.axhspan(-np.sqrt(rho), np.sqrt(rho), color="C2", alpha=0.12, label=f"certified V = x^2 <= {rho:.4f}")
    ax.set(xlabel="t (s)", ylabel="x", ylim=(-3, 3), title="(c) xdot = -x + x^3: certified region vs simulation")
    ax.legend(loc="lower right")


def van_der_pol(ax):
    system = jd.System.from_functions(lambda t, x, u: jnp.stack([-x[1], x[0] + (x[0] ** 2 - 1) * x[1]]),
                                      num_states=2, time_invariant=True)
    quadratic = analysis.region_of_attraction(system, [0.0, 0.0], return_certificate=True)
    search = analysis.search_region_of_attraction(system, [0.0, 0.0], degree=4, iterations=8)
    print(f"Van der Pol: quadratic rho = {quadratic.rho:.4f}; quartic search beta history "
          f"{np.round(search.history, 3)}")
    grid = np.stack(np.meshgrid(np.linspace(-3, 3, 301), np.linspace(-3.5, 3.5, 351)), -1)
    ax.contourf(grid[..., 0], grid[..., 1], np.asarray(search.V(grid)), levels=[-1, 1], colors=["C0"], alpha=0.25)
    ax.contour(grid[..., 0], grid[..., 1], np.asarray(search.V(grid)), levels=[1], colors=["C0"])
    ax.contour(grid[..., 0], grid[..., 1], np.asarray(quadratic.V(grid)), levels=[quadratic.rho], colors=["C1"])
    # the limit cycle: the forward oscillator's attracting cycle, after transients
    forward = jd.models.VanDerPol()
    cycle = jd.simulate(forward, (0.0, 30.0), jnp.array([2.0, 0.0]))
    xs = np.asarray(cycle.state(jnp.linspace(20.0, 30.0, 800)))
    ax.plot(xs[:, 0], xs[:, 1], "k--", lw=1.5)
    starts = np.stack(np.meshgrid(np.linspace(-2.6, 2.6, 9), np.linspace(-3, 3, 9)), -1).reshape(-1, 2)
    runs = jax.vmap(lambda x0: jd.simulate(system, (0.0, 6.0), x0, throw=False))(jnp.asarray(starts))
    ts = jnp.linspace(0.0, 6.0, 300)
    for k in range(len(starts)):
        path = np.asarray(runs[k].state(ts))
        inside = np.abs(path[-1]).max() < 0.5
        ax.plot(path[:, 0], path[:, 1], color="C2" if inside else "C3", lw=0.7, alpha=0.8)
    ax.plot([], [], color="C1", label=f"quadratic V (linearization), rho = {quadratic.rho:.3f}")
    ax.plot([], [], color="C0", label="quartic V from the search")
    ax.plot([], [], "k--", label="limit cycle (true boundary)")
    ax.set(xlim=(-3, 3), ylim=(-3.5, 3.5), xlabel="x1", ylabel="x2",
           title="(d) time-reversed Van der Pol: certified regions")
    ax.legend(loc="upper left", fontsize=8)


def main(out):
    fig, axes = plt.subplots(2, 2, figsize=(14, 10), constrained_layout=True)
    common_lyapunov(axes[0, 0])
    global_pendulum(axes[0, 1])
    cubic(axes[1, 0])
    van_der_pol(axes[1, 1])
    return save(fig, out, "lyapunov.png")


if __name__ == "__main__":
    run(main, __doc__)
