"""The live link: a TCP server streaming a stepping twin to Blender viewers.

``protocol`` loads the shared wire format (``addon/wire.py``) and turns
:class:`~engine.state.StepResult` records into messages; ``server`` runs the
twin loop and the viewers' sockets; ``line_twin`` is a minimal real twin
(straight-line robots, Sionna paths) used when ``engine.twin`` is absent.
See ``docs/wire.md``.

``radiomap_feed`` streams floor radio maps (``engine.radiomap``) as the
server's ``on_step`` hook (``isac-twin serve --radiomap CELL``).
"""
