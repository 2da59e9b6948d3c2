"""The documentation site builds in strict mode (a broken link or reference fails it): the API
reference from the docstrings, the notebooks as tutorials, the Drake name map."""

import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_the_docs_build_in_strict_mode(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "WARNING" not in done.stderr, done.stderr[-3000:]
    reference = (tmp_path / "site/api/simulation/index.html").read_text()
    assert 'id="jaxdrake.simulation.simulate"' in reference  # rendered from the docstring
    assert (tmp_path / "site/tutorials/limit_cycles/index.html").exists()
    drake = (tmp_path / "site/from_drake/index.html").read_text()
    for name in ("DrakeSystem", "HybridDrakeSystem", "LinearQuadraticRegulator", "runLCM"):
        assert name in drake, name
