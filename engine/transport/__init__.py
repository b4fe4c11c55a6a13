"""Network transport, CDR codec and the twin/robot bridge.

* :mod:`isac_twin.transport.cdr` -- isac_twin.bus.msgs dataclasses <-> ROS 2 CDR (rosbags);
* :mod:`isac_twin.transport.record` -- MCAP recording and replay;
* :mod:`isac_twin.transport.keyexpr` -- rmw_zenoh key expressions and attachments;
* :mod:`isac_twin.transport.zenoh_transport` -- :class:`ZenohTransport` (a bus transport);
* :mod:`isac_twin.transport.clock` -- clock offsets between peers;
* :mod:`isac_twin.transport.bridge` -- :class:`TwinBridge`, real robots mirrored into a twin.

The ``isac_twin_msgs`` types themselves are bus messages
(:mod:`isac_twin.bus.twin_msgs`). Zenoh is imported lazily (only by
``zenoh_transport``/``bridge``), so the codec works without it.
"""

__all__: list[str] = []  # import the modules by name (zenoh loads lazily)
