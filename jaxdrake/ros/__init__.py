"""ROS: the ROS–LCM translator (`Translator`, `python -m jaxdrake.ros`) that carries LCM
channels to ROS 1 topics (`Ros1Network`, rospy) or ROS 2 topics (`Ros2Network`, DDS through
Cyclone DDS) and back along `Route`s; the ROS message types it speaks (`Float64MultiArray`,
`JointState`, `Twist`, `WrenchStamped`); and ROS bags (`RosBag`, `lcm_log_to_bag`).
docs/ros.md says how to install ROS 1 and what was tested."""

from .._extras import require
from ._messages import Float64MultiArray, JointState, RosMessage, Twist, WrenchStamped
from ._routes import TO_LCM, TO_ROS, Route, read_mapping
from ._translator import RouteStatistics, Translator
from ._ros1 import MasterError, Ros1Network, RosUnavailableError
from ._bags import RosBag, lcm_log_to_bag


def __getattr__(name):  # ROS 2 needs the cyclonedds binding (the `ros` extra): imported on use
    if name in ("Ros2Network", "LOOPBACK"):
        require("cyclonedds", "Ros2Network")
        from . import _ros2

        return getattr(_ros2, name)
    raise AttributeError(f"module 'jaxdrake.ros' has no attribute {name!r}")


__all__ = ["Float64MultiArray", "JointState", "LOOPBACK", "MasterError", "Ros1Network", "Ros2Network", "RosBag",
           "RosMessage", "RosUnavailableError", "Route", "RouteStatistics", "TO_LCM", "TO_ROS", "Translator",
           "Twist", "WrenchStamped", "lcm_log_to_bag", "read_mapping"]
