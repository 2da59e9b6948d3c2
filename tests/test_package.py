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
