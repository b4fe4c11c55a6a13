"""Commands to a running twin: the one validation and the one dispatch of every op.

A :class:`~.state.Command` (from the live link or a script) changes how the twin
runs, not the room: ``run`` / ``pause`` / ``step`` set the twin's run state (which a
driver such as the live server reads), ``reset`` restarts it, and ``set_path`` /
``set_goal`` / ``teleop`` drive a robot. :func:`validate_command` checks a command
completely against the twin as it is now; :func:`apply_command` validates and
applies it. ``Twin.validate_command`` and ``Twin.command`` call them.
"""

from __future__ import annotations

import numpy as np

from ..bus.msgs import Twist
from ..contract import schema, wire
from .state import Command

__all__ = ["MAX_STEP_COUNT", "apply_command", "validate_command"]

#: Most single steps one ``step`` command may request.
MAX_STEP_COUNT = 100_000


def validate_command(twin, cmd: Command) -> None:
    """Check a command completely (op, every argument) against ``twin`` as it is now.

    Raises:
        ValueError: naming the command and the argument at fault.
    """
    what = f"command {cmd.op}"
    if cmd.op not in wire.COMMAND_OPS:
        raise ValueError(f"{what}: unknown op {cmd.op!r} (expected one of "
                         f"{', '.join(wire.COMMAND_OPS)})")
    a = cmd.args if isinstance(cmd.args, dict) else None
    if a is None:
        raise ValueError(f"{what}: args: expected an object")

    def robot():
        name = a.get("robot")
        if name not in twin.agents:
            raise ValueError(f"{what}: robot: expected one of {', '.join(twin.agents)}, "
                             f"got {name!r}")

    def number(key, lo, hi, default=None):
        v = a.get(key, default)
        if type(v) not in (int, float) or not (np.isfinite(v) and lo <= v <= hi):
            raise ValueError(f"{what}: {key}: expected a number in {lo:g}..{hi:g}, "
                             f"got {v!r}")

    if cmd.op in ("run", "pause", "reset"):
        return
    if cmd.op == "step":
        n = a.get("count", 1)
        if type(n) is not int or not 1 <= n <= MAX_STEP_COUNT:
            raise ValueError(f"{what}: count: expected an integer in 1..{MAX_STEP_COUNT}, "
                             f"got {n!r}")
    elif cmd.op == "set_path":
        robot()
        if not isinstance(a.get("path"), dict):
            raise ValueError(f"{what}: path: expected an object such as "
                             '{"kind": "circle", "centre": [x, y], "radius": r}')
        wps = a["path"].get("waypoints")
        if isinstance(wps, list) and len(wps) > schema.MAX_WAYPOINTS:
            # refused here, before the path is built and checked against the room
            raise ValueError(f"{what}: path: {len(wps)} waypoints, beyond the limit of "
                             f"{schema.MAX_WAYPOINTS}")
    elif cmd.op == "set_goal":
        robot()
        g = a.get("goal")
        lo, hi = twin.scene.bounds_min, twin.scene.bounds_max
        if not (isinstance(g, list) and len(g) == 2
                and all(type(x) in (int, float) and np.isfinite(x) for x in g)
                and lo[0] <= g[0] <= hi[0] and lo[1] <= g[1] <= hi[1]):
            raise ValueError(f"{what}: goal: expected [x, y] inside the room, got {g!r}")
    elif cmd.op == "teleop":
        robot()
        number("linear", -10.0, 10.0)
        number("angular", -20.0, 20.0)
    else:  # an op wire.COMMAND_OPS offers must be checked above
        raise AssertionError(f"{what}: wire.COMMAND_OPS has an op Twin does not handle")


def apply_command(twin, cmd: Command) -> None:
    """Validate (:func:`validate_command`) and apply a command to ``twin``.

    * ``run`` / ``pause``: set ``twin.running`` (``pause`` also drops
      ``twin.pending_steps``);
    * ``step`` (``count``, default 1): pause and request ``count`` single steps
      (``twin.pending_steps``; each ``twin.step()`` takes one);
    * ``reset``: ``twin.reset()``;
    * ``set_path`` (``robot``, ``path``), ``set_goal`` (``robot``, ``goal [x, y]``),
      ``teleop`` (``robot``, ``linear`` m/s, ``angular`` rad/s).

    Raises:
        ValueError: a bad command; nothing was changed.
    """
    validate_command(twin, cmd)
    a = cmd.args
    if cmd.op == "run":
        twin.running = True
    elif cmd.op == "pause":
        twin.running = False
        twin.pending_steps = 0
    elif cmd.op == "step":
        twin.running = False
        twin.pending_steps += int(a.get("count", 1))
    elif cmd.op == "reset":
        twin.reset()
    elif cmd.op == "set_path":
        twin.set_path(a["robot"], a["path"])
    elif cmd.op == "set_goal":
        twin.set_path(a["robot"], {"kind": "goal", "goal": a["goal"]})
    elif cmd.op == "teleop":
        tw = Twist(linear=np.array([float(a["linear"]), 0, 0]),
                   angular=np.array([0, 0, float(a["angular"])]))
        twin.set_controller(a["robot"], lambda _state, tw=tw: tw)
