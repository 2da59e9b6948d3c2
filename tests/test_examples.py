"""Every example script and notebook runs end to end (they are products, not decoration).

Each runs in a process of its own, three at a time (compiling is mostly single-threaded, and a
2-core machine then does two compilations at once): the selected scripts and notebooks are
started when the first of these tests runs, and each test waits for its own."""

import os
import pathlib
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import pytest

from _ros1 import require_ros1  # tests/_ros1.py

ROOT = pathlib.Path(__file__).resolve().parents[1]
EXAMPLES = sorted(p for p in (ROOT / "examples").glob("*.py") if not p.name.startswith("_"))
# a notebook that repeats its example script at a much larger batch runs with `-m slow` only
# swing_up.py: 61 s of compiling four hybrid closed loops, whose swing-ups and switches
# tests/test_control.py checks by default; trajectory_optimization.py (54 s) and its notebook:
# the swing-ups, TVLQR and iLQR batches that tests/test_trajopt.py checks by default;
# mujoco_models.py (36 s of MJX compiles and EGL frames) and mujoco_contacts.py (55 s, the humanoid
# batch): what tests/test_mujoco.py checks (C MuJoCo agreement, the hopper under a controller)
SLOW = {"swing_up.ipynb", "lqr.ipynb", "swing_up.py",  # lqr.ipynb: 45 s, extends lqr.py (run with -m slow)
        "trajectory_optimization.py", "trajectory_optimization.ipynb", "mujoco_models.py", "mujoco_models.ipynb",
        "mujoco_contacts.py", "mujoco_contacts.ipynb",
        "contact.ipynb",  # ~40 s, the same computations as contact.py (which runs by default)
        # the limit cycles' script (~40 s alone, mostly compiling hybrid Newton solves and their jvp):
        # tests/test_limit_cycles.py checks its orbits and derivatives by default; and the notebooks
        # that repeat a script which runs by default (the same computations; executed with -m slow)
        "limit_cycles.py", "limit_cycles.ipynb", "rimless_wheel.ipynb", "feedback_cancellation.ipynb",
        "linear_gaussian.ipynb", "bouncing_ball.ipynb", "composition.ipynb", "dynamic_programming.ipynb",
        "lyapunov.ipynb", "rrt.ipynb", "lcm_pendulum.ipynb",
        # ~50 s of a roscore, the translator and two nodes in real time; tests/test_ros.py checks the
        # translator's paths (rostopic pub -> LCM, LCM -> rostopic echo) by default
        "ros_pendulum.py",
        # the heaviest scripts (CPU seconds on 2 cores, alone): bouncing_ball.py 50 (the impacts and
        # their gradients: tests/test_hybrid.py), contact.py 54 (tests/test_contact.py), composition.py
        # 44 (tests/test_compose.py), lqr.py 43 (tests/test_control.py), manipulator.py 43
        # (tests/test_multibody.py, test_viz.py), demo.py 37 (README command 1, run before each stop)
        "bouncing_ball.py", "contact.py", "composition.py", "lqr.py", "manipulator.py", "demo.py",
        # mpc_estimation.py 80 (compiling the UKF/MPC and LQG loops, two LCM node processes; its pieces:
        # tests/test_mpc.py, each QP against OSQP/Clarabel and the constraints along a closed loop, and
        # tests/test_estimation.py, the UKF against filterpy and LQG's poles); its notebook repeats it
        "mpc_estimation.py", "mpc_estimation.ipynb",
        # scripts of 13-21 CPU s each whose content a fast test checks (the suite's 10-minute budget):
        # dynamic_programming.py (tests/test_planning.py: the grid world, the double integrator against
        # Drake and the exact minimum time, the pendulum's swing-up under its policy), lyapunov.py
        # (tests/test_analysis.py: the common Lyapunov function, the damped pendulum's certificate, the
        # cubic system's region, the reversed Van der Pol), feedback_cancellation.py
        # (tests/test_multibody.py), lcm_pendulum.py (tests/test_lcm_bridge.py, the two processes'
        # loop), rimless_wheel.py (tests/test_hybrid.py, the rolling fixed point)
        "dynamic_programming.py", "lyapunov.py", "feedback_cancellation.py", "lcm_pendulum.py",
        "rimless_wheel.py",
        # linear_gaussian.py, 15 s of 10^4 paths: tests/test_stochastic.py checks the same variance
        # over 10^4 paths (and the autocovariance), tests/test_batch.py run_batch's chunks
        "linear_gaussian.py",
        # mjcf_plant.py, 35 s (the Shadow hand's contact simulation compiles for ~15 s): its pieces
        # are tests/test_mjcf.py's (the hand's servos against mj_forward, MuJoCo's renderer of a plant)
        "mjcf_plant.py"}
NOTEBOOKS = [pytest.param(p, marks=pytest.mark.slow) if p.name in SLOW else p
             for p in sorted((ROOT / "notebooks").glob("*.ipynb"))]
NEEDS_ROS1 = {"ros_pendulum.py"}   # a real roscore
WORKERS = 3

EXECUTE_NOTEBOOK = """
import sys, nbclient, nbformat
nb = nbformat.read(sys.argv[1], as_version=4)
nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                        resources={"metadata": {"path": sys.argv[2]}}).execute()
images = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
          if "image/png" in o.get("data", {})]
print("IMAGES", len(images))
"""


@pytest.fixture(scope="module")
def runs(request, tmp_path_factory):
    """Start every selected script and notebook (`WORKERS` at a time); {path: future of the
    finished process}. Scripts and notebook kernels share JAX's persistent compilation cache
    (a fresh one per run): a notebook that repeats its script's computations loads those
    programs instead of compiling them again, as a user's second session would."""
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=str(tmp_path_factory.mktemp("jax-cache")),
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    selected = [item.callspec.params for item in request.session.items
                if item.module is request.module and hasattr(item, "callspec")]
    pool = ThreadPoolExecutor(WORKERS)
    futures = {}
    for params in selected:  # the scripts first: the notebooks then find their programs cached
        if "script" in params:
            script, out = params["script"], tmp_path_factory.mktemp(params["script"].stem)
            futures[script] = pool.submit(_run, [sys.executable, str(script), "--out", str(out)], env, out)
    for params in selected:
        if "notebook" in params:
            notebook = params["notebook"]
            futures[notebook] = pool.submit(_run, [sys.executable, "-c", EXECUTE_NOTEBOOK, str(notebook),
                                                   str(notebook.parent)], env, None)
    yield futures
    pool.shutdown(wait=True, cancel_futures=True)


def _run(command, env, out):
    done = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    return done, out


@pytest.mark.notebook
@pytest.mark.parametrize("script", [pytest.param(p, marks=pytest.mark.slow) if p.name in SLOW else p
                                    for p in EXAMPLES], ids=lambda p: getattr(p, "name", None))
def test_example_script_runs_and_saves_its_figure(script, runs):
    if script.name in NEEDS_ROS1:
        require_ros1()
    done, out = runs[script].result()
    assert done.returncode == 0, done.stderr[-3000:]
    figures = list(out.glob("*.png"))
    assert figures and all(f.stat().st_size > 10_000 for f in figures)
    movies = list(out.glob("*.gif"))
    assert all(m.stat().st_size > 10_000 for m in movies)


@pytest.mark.notebook
@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=lambda p: getattr(p, "name", None))
def test_notebook_executes(notebook, runs):
    done, _ = runs[notebook].result()
    assert done.returncode == 0, done.stderr[-3000:]
    assert "IMAGES" in done.stdout and int(done.stdout.split("IMAGES")[1]) > 0, \
        "a notebook should show at least one plot"
