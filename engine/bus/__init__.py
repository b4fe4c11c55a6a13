"""The topic bus: the paper's master node, in process.

Modules: :mod:`.msgs` (ROS 2-shaped message types), :mod:`.twin_msgs` (the
``isac_twin_msgs`` types: paths, link metrics, fingerprints, CSI, path commands, clock
pings), :mod:`.sensing_msgs` (the radar's ``isac_twin_msgs/msg/Detections``),
:mod:`.frames` (REP-105 frames and transforms), :mod:`.bus` (:class:`Bus`,
nodes, subscriptions, the transport interface).
"""

from . import twin_msgs  # noqa: F401  (adds the isac_twin_msgs types to msgs.MESSAGE_TYPES)
from .bus import Bus, Node, Subscription, Transport

__all__ = ["Bus", "Node", "Subscription", "Transport"]
