"""Whether Debian's ROS 1 tools are here, for the tests that need a real roscore: without them
those tests skip, and under CI (`.ci/run` installs them) they fail instead."""

from __future__ import annotations

import os
import shutil

import pytest

DEBIAN_PYTHON = "/usr/bin/python3"
HAVE_ROS1 = all(shutil.which(tool) for tool in ("roscore", "rostopic", "rosbag")) and os.path.exists(DEBIAN_PYTHON)


def require_ros1(tools_present=HAVE_ROS1, what="Debian's ROS 1 is"):
    if tools_present:
        return
    reason = (f"{what} not installed (apt-get install ros-core python3-rospy python3-rostopic python3-std-msgs "
              "python3-sensor-msgs python3-geometry-msgs python3-rosbag strace; .ci/run does)")
    if os.environ.get("CI"):
        pytest.fail(reason)
    pytest.skip(reason)
