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
