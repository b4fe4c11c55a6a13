"""The live link: a TCP server streaming a stepping twin to Blender viewers.

``protocol`` loads the shared wire format (``addon/contract/wire.py``) and turns
:class:`~isac_twin.twin.state.StepResult` records into messages; ``server`` runs a
real :class:`~isac_twin.twin.twin.Twin` in a loop thread and the viewers' sockets in
an I/O thread. See ``docs/wire.md`` (and its security model).

``radiomap_feed`` streams floor radio maps (``isac_twin.radiomap.radio_map``) as the
server's ``on_step`` hook (``isac-twin serve --radiomap CELL``).
"""

from .server import LiveServer, LiveTwin, is_loopback

__all__ = ["LiveServer", "LiveTwin", "is_loopback"]
