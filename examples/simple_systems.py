"""The notes' first examples (Underactuated, appendix D.3.1 and D.3.6).

    sys = SimpleCTExample; traj = simulate(sys, [0 10], .99); fnplt(traj);
    sys = SimpleDTExample; traj = simulate(sys, [0 10], .99); fnplt(traj);

plus the mixed continuous / discrete example, whose discrete state is updated at
t in {0, 1, 2, ...} and held in between. Saves `simple_systems.png`.

Run:  python examples/simple_systems.py [--out DIR]
"""

import pathlib

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jaxdrake as jd  # noqa: E402
from _cli import run, save  # noqa: E402  (examples/_cli.py)
from jaxdrake.models import SimpleCTExample, SimpleDTExample, SimpleMixedCTDTExample  # noqa: E402

jax.config.update("jax_enable_x64", True)


def main(out: pathlib.Path) -> pathlib.Path:
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6), layout="constrained")

    ct = jd.simulate(SimpleCTExample(), (0.0, 10.0), 0.99)
    ct.plot(ax=axes[0])
    axes[0].set_title("SimpleCTExample:\n" r"$\dot x = -x + x^3$, $x_0 = 0.99$")

    dt = jd.simulate(SimpleDTExample(), (0.0, 10.0), 0.99)
    dt.plot(ax=axes[1])
    axes[1].set_title("SimpleDTExample:\n" r"$x[n+1] = x[n]^3$, $x_0 = 0.99$")

    # the state is laid out [x_d; x_c] = [x1; x2], as in the notes
    mixed = jd.simulate(SimpleMixedCTDTExample(), (0.0, 10.0), [0.99, 0.99])
    mixed.plot(ax=axes[2])
    axes[2].set_title("SimpleMixedCTDTExample:\n$x_1$ discrete (dt = 1), $x_2$ continuous")
    for ax in axes:
        ax.set_ylabel("y")

    print(f"SimpleCT: x(10) = {float(ct.eval(10.0)[0]):.3e} after {ct.num_steps} steps")
    print(f"SimpleDT: x at t = 0..5 = {[round(float(dt.eval(float(n))[0]), 4) for n in range(6)]}")
    return save(fig, out, "simple_systems.png", dpi=110)


if __name__ == "__main__":
    run(main, __doc__)
