"""Network transport, CDR codec and the twin/robot bridge.

* :mod:`engine.transport.cdr` -- engine.msgs dataclasses <-> ROS 2 CDR (rosbags);
* :mod:`engine.transport.twin_msgs` -- ``isac_twin_msgs`` custom types (paths, link
  metrics, fingerprints, CSI, path commands, clock pings);
* :mod:`engine.transport.keyexpr` -- rmw_zenoh key expressions and attachments;
* :mod:`engine.transport.zenoh_transport` -- :class:`ZenohTransport` (a bus transport);
* :mod:`engine.transport.clock` -- clock offsets between peers;
* :mod:`engine.transport.bridge` -- :class:`TwinBridge`, real robots mirrored into a twin.

Importing this package registers the ``isac_twin_msgs`` types on the bus
(:data:`engine.msgs.MESSAGE_TYPES`). Zenoh is imported lazily (only by
``zenoh_transport``/``bridge``), so the codec works without it.
"""

from engine.transport import twin_msgs  # noqa: F401  (registers isac_twin_msgs types)

#: import the modules above by name (``zenoh_transport`` and ``bridge`` need zenoh)
__all__ = ["twin_msgs"]
