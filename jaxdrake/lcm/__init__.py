"""LCM: coders between message types and vectors (`jaxdrake.lcmtypes` holds the `lcm-gen`
bindings of the definitions in the top-level `lcmtypes/`), attached to frames with
`Frame.with_coder`."""

from ._bridge import LcmNode, NodeStatistics
from ._viewer import LcmViewer, ViewerStatistics
from ._relay import LoopbackRelay
from ._coders import (LcmCoder, MessageError, RobotCommandCoder, RobotStateCoder, SignalCoder,
                      TypeCoder)

__all__ = ["LcmCoder", "LcmNode", "LcmViewer", "LoopbackRelay", "NodeStatistics", "MessageError", "RobotCommandCoder", "RobotStateCoder", "SignalCoder", "TypeCoder", "ViewerStatistics"]
