"""The notes' simple continuous-time stochastic system (appendix D.3.1): xdot = -x + w.

w(t) is band-limited Gaussian white noise with time constant tau = 0.01 (held for tau at
N(0, 1/tau)), drawn from an explicit JAX PRNG key: `jd.run_batch` over 10^4 keys runs the
Monte-Carlo batch in chunks on every local device (one compiled program). Plots sample paths with the +-2 sigma band, the
sample variance over time against the analytic variance V (1 - e^{-2t}), and the distribution
of x(5) against N(0, V), V = (1 - e^{-tau}) / (tau (1 + e^{-tau})) ~ 1/2.

Run:  python examples/linear_gaussian.py [--out DIR]      (saves linear_gaussian.png)
"""

import pathlib

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jaxdrake as jd  # noqa: E402
from _cli import run, save  # noqa: E402  (examples/_cli.py)

jax.config.update("jax_enable_x64", True)


def main(out: pathlib.Path) -> pathlib.Path:
    system = jd.models.LinearGaussianExample(noise_time_constant=0.01)
    V = system.stationary_variance()
    T, num_paths, num_dense = 5.0, 10_000, 1000
    keys = jax.random.split(jax.random.key(0), num_paths)

    # final states of 10^4 paths (dense=False keeps only the end: small memory)
    def final(key):
        return jd.simulate(system, (0.0, T), jnp.zeros(1), key=key, dense=False).final_state[0]

    x_T = jd.run_batch(final, keys, chunk_size=2500)  # 4 chunks, sharded over the local devices
    # 1000 dense paths sampled on a grid, for the variance over time
    ts = jnp.linspace(0.0, T, 201)
    paths = jax.jit(jax.vmap(lambda k: jd.simulate(system, (0.0, T), jnp.zeros(1), key=k).state(ts)[:, 0]))
    xs = np.asarray(paths(keys[:num_dense]))
    sem = V * np.sqrt(2 / (num_paths - 1))
    print(f"sample variance of x({T:g}) over {num_paths} paths: {np.var(x_T, ddof=1):.4f}; "
          f"analytic {V:.4f} (+- {sem:.4f} standard error)")

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.4), layout="constrained")
    ts = np.asarray(ts)
    band = 2 * np.sqrt(V * (1 - np.exp(-2 * ts)))
    axes[0].fill_between(ts, -band, band, color="C0", alpha=0.15, label=r"$\pm 2\sigma(t)$")
    for i in range(12):
        axes[0].plot(ts, xs[i], lw=0.8)
    axes[0].set(xlabel="t", ylabel="x", title=r"sample paths of $\dot x = -x + w$, $\tau$ = 0.01")
    axes[0].legend(loc="upper left")

    var_t = np.var(xs, axis=0, ddof=1)
    exact = V * (1 - np.exp(-2 * ts))
    axes[1].plot(ts, var_t, color="C0", label=f"sample variance ({num_dense} paths)")
    axes[1].plot(ts, exact, "k--", label=r"$V(1 - e^{-2t})$")
    axes[1].fill_between(ts, exact * (1 - 3 * np.sqrt(2 / num_dense)), exact * (1 + 3 * np.sqrt(2 / num_dense)),
                         color="0.5", alpha=0.2, label="3 standard errors")
    axes[1].set(xlabel="t", ylabel="variance", title="variance approaches the stationary value")
    axes[1].legend(loc="lower right")

    axes[2].hist(x_T, bins=60, density=True, color="C0", alpha=0.6, label=f"x({T:g}), {num_paths} paths")
    grid = np.linspace(-3, 3, 200)
    axes[2].plot(grid, np.exp(-grid ** 2 / (2 * V)) / np.sqrt(2 * np.pi * V), "k", label=f"N(0, {V:.4f})")
    axes[2].set(xlabel="x", title=f"sample variance {np.var(x_T, ddof=1):.4f} vs {V:.4f}")
    axes[2].legend(loc="upper right")
    return save(fig, out, "linear_gaussian.png")


if __name__ == "__main__":
    run(main, __doc__)
