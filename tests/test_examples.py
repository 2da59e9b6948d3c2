"""Every example script and notebook runs end to end (they are products, not decoration)."""

import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
EXAMPLES = sorted(p for p in (ROOT / "examples").glob("*.py") if not p.name.startswith("_"))
# a notebook that repeats its example script at a much larger batch runs with `-m slow` only
SLOW = {"swing_up.ipynb"}
NOTEBOOKS = [pytest.param(p, marks=pytest.mark.slow) if p.name in SLOW else p
             for p in sorted((ROOT / "notebooks").glob("*.ipynb"))]


@pytest.fixture(scope="module", autouse=True)
def _shared_compilation_cache(tmp_path_factory):
    """Scripts and notebook kernels share JAX's persistent compilation cache (a fresh one per
    run): a notebook that repeats its script's computations loads those programs instead of
    compiling them again, as a user's second session would."""
    settings = {"JAX_COMPILATION_CACHE_DIR": str(tmp_path_factory.mktemp("jax-cache")),
                "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0"}
    saved = {k: os.environ.get(k) for k in settings}
    os.environ.update(settings)
    yield
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k)
        else:
            os.environ[k] = v


@pytest.mark.notebook
@pytest.mark.parametrize("script", EXAMPLES, ids=lambda p: p.name)
def test_example_script_runs_and_saves_its_figure(script, tmp_path):
    result = subprocess.run([sys.executable, str(script), "--out", str(tmp_path)], cwd=ROOT,
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    figures = list(tmp_path.glob("*.png"))
    assert figures and all(f.stat().st_size > 10_000 for f in figures)


@pytest.mark.notebook
@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=lambda p: getattr(p, "name", None))
def test_notebook_executes(notebook):
    import nbclient
    import nbformat

    nb = nbformat.read(notebook, as_version=4)
    nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(notebook.parent)}}).execute()
    images = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if "image/png" in o.get("data", {})]
    assert images, "a notebook should show at least one plot"
