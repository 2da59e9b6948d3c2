"""The README's code and commands stay true."""

import pathlib
import re

import numpy as np

README = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()


def test_readme_example_runs():
    namespace = {}
    exec(re.findall(r"```python\n(.*?)```", README, re.S)[0], namespace)
    assert namespace["finals"].shape == (1000, 2)
    # d theta(5) / d b by finite differences
    jd, jnp = namespace["jd"], namespace["jnp"]
    f = lambda b: float(jd.simulate(jd.models.Pendulum(b=b), (0, 5), jnp.array([1.0, 0.0]),
                                    rtol=1e-10, atol=1e-12).final_state[0])
    np.testing.assert_allclose(namespace["dloss_db"], (f(0.1 + 1e-5) - f(0.1 - 1e-5)) / 2e-5, rtol=1e-3)


def test_readme_opens_with_the_two_commands_ci_runs():
    commands = re.findall(r"```bash\n(.*?)```", README, re.S)[0].splitlines()
    assert commands[0].startswith("# 1.") and "examples/demo.py" in commands[1]
    assert commands[2].startswith("# 2.") and "pytest" in commands[3]
    ci = (pathlib.Path(__file__).resolve().parents[1] / ".ci" / "run").read_text()
    assert "grep -A1 '^# 2\\. ' README.md" in ci
