"""The ``isac-twin`` parser, its registry of commands, dispatch and the error mapping.

A command lives in a module of this package by group (:data:`COMMANDS` says which);
the module holds ``COMMANDS = {name: (configure, run)}``: ``configure(parser)`` adds
the command's options, ``run(args)`` does the work and returns the exit status. Only
the module of the command being run is imported, so ``isac-twin --help`` and
``isac-twin <cmd> --help`` load no ray tracer, zenoh, Dask or matplotlib.

Errors: every :class:`~isac_twin.errors.IsacTwinError` a command raises is printed here
as one line ``isac-twin: error: <message>`` with exit status 2, and so is an
``OSError`` on a path the user named (a missing or unreadable file). Anything else is
a bug and keeps its traceback (exit status 1).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Collection
from pathlib import Path

from ..errors import IsacTwinError

__all__ = ["COMMANDS", "build_parser", "error_line", "main"]

#: command -> (module of ``isac_twin.cli`` that defines it, one-line help), in the
#: order ``isac-twin --help`` lists them.
COMMANDS: dict[str, tuple[str, str]] = {
    "info": ("scene", "load a scene folder, validate it and print a summary"),
    "trace": ("scene", "trace all links of a scene once and print a per-link table"),
    "grid": ("scene", "trace a floor grid of receiver positions and store it (NPZ)"),
    "radiomap": ("scene", "floor radio map per access point (Sionna RadioMapSolver): "
                          "NPZ + PNG"),
    "run": ("run", "run the twin (Algorithm 1) for N steps and print a per-step line"),
    "fingerprints": ("localize", "build (or find in the cache) the fingerprint database of "
                                 "a scene: the multipath delay profile of every AP on a "
                                 "floor grid"),
    "localize": ("localize", "the paper's case study on a scene folder: fingerprint "
                             "database, deployment loop (paper mode and closed loop), "
                             "static localizer table, figures, metrics.json; the robot "
                             "follows its [devices.path]"),
    "casestudy": ("localize", "the same as 'localize'"),
    "topics": ("robot", "list the topic bus registry of a twin's robots (nodes, topics, "
                        "types)"),
    "serve": ("serve", "run the twin and stream it to Blender viewers over TCP"),
    "robot": ("robot", "run the robot runtime: drivers, estimation, control, topics on "
                       "zenoh"),
    "record": ("run", "run the twin and record all its topics, link metrics and paths to "
                      "MCAP"),
    "recover": ("run", "rewrite a killed recording's complete chunks as a finished MCAP"),
    "replay": ("run", "replay an MCAP recording: drive a twin along the recorded "
                      "trajectories"),
    "calibrate": ("calibrate", "fit materials and object poses of a scene to recorded CSI "
                               "(Sionna gradients)"),
}

_DESCRIPTION = "``isac-twin``: the engine's command line. Thin: parse, call, print."


def _command(name: str):
    """``(configure, run)`` of a command, from its module (imported now)."""
    module = importlib.import_module(f".{COMMANDS[name][0]}", __package__)
    return module.COMMANDS[name]


def build_parser(commands: Collection[str] | None = None) -> argparse.ArgumentParser:
    """The ``isac-twin`` parser.

    Args:
        commands: give only these commands their options (importing only their
            modules); None: every command (importing every command module).
    """
    parser = argparse.ArgumentParser(prog="isac-twin", description=_DESCRIPTION)
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="log more (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (_, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        if commands is None or name in commands:
            configure, fn = _command(name)
            configure(p)
            p.set_defaults(func=fn)
    return parser


def _commands_in(argv: list[str]) -> list[str]:
    """The command named in ``argv`` (the first word that is not an option: the
    top-level parser has only flags) as a list; empty when none is named."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return [word] if word in COMMANDS else []


def _user_paths(args: argparse.Namespace) -> list[Path]:
    """The paths among the parsed arguments (files and folders the user named)."""
    paths = []
    for v in vars(args).values():
        for p in v if isinstance(v, list) else [v]:
            if isinstance(p, Path):
                paths.append(p)
    return paths


def _on_user_path(exc: OSError, args: argparse.Namespace) -> bool:
    """Whether ``exc`` concerns a path the user named, one inside it or one of its
    folders (a missing recording, an unwritable output folder)."""
    failed = [Path(f).absolute() for f in (exc.filename, exc.filename2)
              if isinstance(f, (str, os.PathLike))]  # not a file descriptor
    for user in (p.absolute() for p in _user_paths(args)):
        for f in failed:
            if f == user or user in f.parents or f in user.parents:
                return True
    return False


def error_line(message: str) -> str:
    """``isac-twin: error: <message>``, the message folded into one line."""
    text = " ".join(ln.strip() for ln in message.splitlines() if ln.strip())
    return f"isac-twin: error: {text}"


def _fail(message: str) -> int:
    print(error_line(message), file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    """Run ``isac-twin`` with ``argv`` (default: the process's arguments).

    Returns:
        The exit status: 0 on success, 2 for bad input (one line on stderr).
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(_commands_in(argv)).parse_args(argv)
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except IsacTwinError as exc:
        return _fail(str(exc) or type(exc).__name__)
    except OSError as exc:
        if not _on_user_path(exc, args):
            raise
        return _fail(f"{exc.filename}: {exc.strerror or exc}")
