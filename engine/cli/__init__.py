"""``isac-twin``: the engine's command line. Thin: parse, call, print.

One module per command group -- :mod:`.scene` (info, trace, grid, radiomap), :mod:`.run`
(run, record, recover, replay), :mod:`.localize` (fingerprints, localize), :mod:`.serve`,
:mod:`.robot` (robot, topics), :mod:`.calibrate` -- with the options they share in
:mod:`.options` and the process lifecycle of the long-running ones in :mod:`.lifecycle`.
:mod:`.main` holds the parser, the registry of commands and the one place that turns
an error into a line on stderr and an exit status.
"""

from __future__ import annotations

from .main import COMMANDS, build_parser, main

__all__ = ["COMMANDS", "build_parser", "main"]
