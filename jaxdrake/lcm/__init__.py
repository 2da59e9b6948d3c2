"""LCM: coders between message types and vectors (`jaxdrake.lcmtypes` holds the `lcm-gen`
bindings of the definitions in the top-level `lcmtypes/`), attached to frames with
`Frame.with_coder`; nodes (`LcmNode`, `LcmViewer`) that run systems on an LCM network; and
`LoopbackRelay`, a tcpq hub on 127.0.0.1 that answers the requests it refuses on
`RELAY_ERROR_CHANNEL`."""

from ._bridge import HOST_ONLY_URL, LcmNode, NodeStatistics, load_system, open_lcm, restore_signals, stop_on_signals
from ._viewer import LcmViewer, ViewerStatistics
from ._relay import RELAY_ERROR_CHANNEL, LoopbackRelay
from ._coders import (LcmCoder, MessageError, RobotCommandCoder, RobotStateCoder, SignalCoder,
                      TypeCoder)

__all__ = ["HOST_ONLY_URL", "load_system", "open_lcm", "restore_signals", "stop_on_signals", "LcmCoder", "LcmNode", "LcmViewer", "LoopbackRelay", "NodeStatistics", "MessageError", "RELAY_ERROR_CHANNEL",
           "RobotCommandCoder", "RobotStateCoder", "SignalCoder", "TypeCoder", "ViewerStatistics"]
