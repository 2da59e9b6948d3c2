"""MuJoCo through jaxdrake leaves the user's working folder and terminal alone (a fresh process,
so that nothing imported mujoco.mjx before): MJX's import prints "Failed to import warp" lines
when the optional Warp backend is missing, and MuJoCo's own warning handler appends to
MUJOCO_LOG.TXT in the working folder; through jaxdrake the first are dropped and the second
become Python RuntimeWarnings."""

import os
import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("mujoco")

SCRIPT = textwrap.dedent("""
    import jaxdrake as jd, mujoco
    system = jd.MujocoSystem.from_xml('<mujoco><worldbody><body><joint type="hinge"/>'
                                      '<geom type="sphere" size="0.1"/></body></worldbody></mujoco>')
    print("built")
    data = mujoco.MjData(system.mj_model)
    data.qvel[:] = 1e30  # MuJoCo warns of a huge velocity and resets the state
    mujoco.mj_step(system.mj_model, data)
    print("stepped", data.qvel[0])
""")


# the same through the native plant's MJCF reader (the first MuJoCo use of the process)
SCRIPT_FROM_MJCF = SCRIPT.replace(
    "system = jd.MujocoSystem.from_xml(", "model = mujoco.MjModel.from_xml_string(").replace(
    "print(\"built\")", "jd.RigidBodySystem.from_mjcf(model); print(\"built\")").replace("system.mj_model", "model")


@pytest.mark.parametrize("script", [SCRIPT, SCRIPT_FROM_MJCF], ids=["MujocoSystem", "from_mjcf"])
def test_no_warp_lines_and_no_mujoco_log_file_in_the_working_folder(tmp_path, script):
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=os.pathsep.join(sys.path))
    done = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.split() == ["built", "stepped", "0.0"]  # nothing else printed; the state was reset
    assert "RuntimeWarning: MuJoCo: Nan, Inf or huge value in QVEL" in done.stderr
    assert "warp" not in done.stdout + done.stderr
    assert list(tmp_path.iterdir()) == []
