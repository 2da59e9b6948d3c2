"""The package as a user meets it: what `import jaxdrake` gives, and what it does not load."""

import subprocess
import sys

import pytest


def test_trajopt_and_lcm_are_reachable_from_the_top_level_without_being_imported_eagerly():
    code = ("import sys, jaxdrake as jd; "
            "eager = [m for m in ('jaxdrake.trajopt', 'jaxdrake.lcm') if m in sys.modules]; "
            "print(eager, jd.trajopt.DirectCollocation.__name__, jd.lcm.LcmNode.__name__, "
            "'trajopt' in dir(jd) or 'trajopt' in jd.__all__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["[]", "DirectCollocation", "LcmNode", "True"]


def test_an_unknown_attribute_is_an_attribute_error():
    import jaxdrake as jd

    with pytest.raises(AttributeError, match="no attribute 'no_such_thing'"):
        jd.no_such_thing


def _private_imports_across_packages():
    """(file, imported module) for every import in jaxdrake/ of another subpackage's private
    module (`jaxdrake.Q._name` from outside Q; the root's own `jaxdrake._name` helpers are shared)."""
    import ast
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[1] / "jaxdrake"
    found = []
    for path in root.rglob("*.py"):
        package = path.relative_to(root.parent).with_suffix("").parts[:-1]  # e.g. ("jaxdrake", "viz")
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = package[:len(package) - node.level + 1] if node.level else ()
                names = [(*base, *(node.module or "").split("."))]
            elif isinstance(node, ast.Import):
                names = [tuple(alias.name.split(".")) for alias in node.names]
            else:
                continue
            for parts in names:
                parts = tuple(p for p in parts if p)
                if len(parts) >= 3 and parts[0] == "jaxdrake" and parts[2].startswith("_") \
                        and parts[:2] != package[:2]:
                    found.append((str(path.relative_to(root.parent)), ".".join(parts)))
    return found


def test_no_package_imports_another_packages_private_module():
    """Every shared concept has a public home: a subpackage reaches another only through its
    public names (issue 43's boundary rule)."""
    assert _private_imports_across_packages() == []


def test_no_test_is_defined_twice_in_a_file():
    """A second `def test_x` in a module silently hides the first (it never runs)."""
    import ast
    import collections
    import pathlib

    for path in pathlib.Path(__file__).resolve().parent.glob("test_*.py"):
        names = [n.name for n in ast.parse(path.read_text()).body if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)]
        twice = [name for name, count in collections.Counter(names).items() if count > 1]
        assert not twice, f"{path.name} defines {twice} twice"


def _pyproject() -> dict:
    import pathlib
    import tomllib

    return tomllib.loads((pathlib.Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())


def test_the_version_has_one_source():
    """pyproject.toml reads the version from jaxdrake/_version.py, the only file that writes one,
    and the installed metadata agrees with `jaxdrake.__version__`."""
    import importlib.metadata
    import pathlib

    import jaxdrake

    project = _pyproject()
    assert "version" not in project["project"] and "version" in project["project"]["dynamic"]
    assert project["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "jaxdrake._version.__version__"}
    root = pathlib.Path(jaxdrake.__file__).parent
    writers = [p.name for p in root.rglob("*.py") if "__version__ =" in p.read_text()]
    assert writers == ["_version.py"]
    assert importlib.metadata.version("jaxdrake") == jaxdrake.__version__
    assert (root / "py.typed").is_file() and "py.typed" in project["tool"]["setuptools"]["package-data"]["jaxdrake"]


def test_each_optional_dependency_is_named_by_the_extra_that_installs_it(monkeypatch):
    """The extras table of jaxdrake._extras agrees with pyproject.toml (the extra it names lists
    the distribution that provides the module; the core does not), and a missing one is a
    `MissingExtraError` naming that extra, also where jaxdrake reaches for it: IPOPT (refused
    before anything compiles; "auto" falls back to SciPy with a warning) and LCM."""
    import importlib.metadata
    import re

    import jaxdrake as jd
    from jaxdrake._extras import EXTRAS, MissingExtraError, require
    from jaxdrake.trajopt._nlp import resolve_solver

    project = _pyproject()["project"]
    names = lambda requirements: {re.match(r"[A-Za-z0-9_.-]+", r).group().lower() for r in requirements}
    core, extras = names(project["dependencies"]), project["optional-dependencies"]
    providers = importlib.metadata.packages_distributions()
    for module, (_, extra) in EXTRAS.items():
        distributions = {d.lower() for d in providers[module]}
        assert distributions & names(extras[extra]), (module, extra)
        assert not distributions & core, module
        assert distributions & names(extras["test"]), module

    monkeypatch.setitem(sys.modules, "cyipopt", None)  # as if not installed
    monkeypatch.setitem(sys.modules, "lcm", None)
    with pytest.raises(MissingExtraError, match=r"solver='ipopt' needs IPOPT: pip install 'jaxdrake\[solvers\]'") \
            as missing:
        jd.trajopt.DirectCollocation(jd.models.Pendulum(), 5, duration=1.0).solve(solver="ipopt")
    assert missing.value.extra == "solvers" and isinstance(missing.value, ImportError)
    with pytest.warns(UserWarning, match=r"jaxdrake\[solvers\].*falls back to SciPy"):
        assert resolve_solver("auto") == "scipy"
    with pytest.raises(MissingExtraError, match=r"LcmNode needs LCM: pip install 'jaxdrake\[lcm\]'"):
        jd.lcm.LcmNode(jd.models.Pendulum(), "memq://")
    with pytest.raises(MissingExtraError, match=r"pip install 'jaxdrake\[lcm\]'") as missing:
        require("lcm", "this")
    assert missing.value.extra == "lcm" and missing.value.name == "lcm"


def test_a_progress_bar_appears_only_for_long_work_and_ends_full_when_work_converges_early(capsys, monkeypatch):
    """Progress is on by default but drawn only after `DELAY` seconds; a search that converges
    at step 7 of a budget of 1000 closes its bar at 7/7 (100%), not at 1%."""
    import time

    from jaxdrake import _progress

    monkeypatch.setattr(_progress, "DELAY", 0.0)
    bar = _progress.progress_bar(True, 1000, "search", "step")
    for _ in range(7):
        bar.update(1)
    _progress.finish(bar, 7)
    assert "100%" in capsys.readouterr().err.splitlines()[-1].split("\r")[-1]
    monkeypatch.setattr(_progress, "DELAY", 60.0)
    quick = _progress.progress_bar(True, 10, "quick", "step")
    quick.update(10)
    time.sleep(0.01)
    _progress.finish(quick, 10)
    assert capsys.readouterr().err == ""
    assert _progress.progress_bar(False, 10, "off", "step") is None


def test_every_status_code_carries_a_message_and_its_successes():
    """The result convention's one owner (jaxdrake._status): every status enum of the library
    is a StatusCode whose codes all have a message, and is_success agrees with success on
    arrays of codes (as inside jit / vmap)."""
    import jax.numpy as jnp

    import jaxdrake.analysis  # noqa: F401  (the packages that define status enums, some lazily imported)
    import jaxdrake.control  # noqa: F401
    import jaxdrake.trajopt  # noqa: F401
    from jaxdrake._status import StatusCode

    def subclasses(cls):
        for sub in cls.__subclasses__():
            yield sub
            yield from subclasses(sub)

    kinds = {c.__name__ for c in subclasses(StatusCode)}
    assert {"SimulationStatus", "SolverStatus", "ILQRStatus", "ConicStatus", "LQRStatus", "QPStatus"} <= kinds
    for kind in subclasses(StatusCode):
        codes = list(kind)
        assert all(isinstance(code.message, str) and code.message for code in codes), kind
        successes = kind.is_success(jnp.asarray([int(code) for code in codes]))
        assert list(map(bool, successes)) == [code.success for code in codes], kind
        assert list(kind.message_of(jnp.asarray([int(c) for c in codes]))) == [c.message for c in codes]
