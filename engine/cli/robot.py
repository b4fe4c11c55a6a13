"""``robot``, ``topics``: the robot runtime on zenoh, and the topic registry of a twin's
robots."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path

from ..bus.bus import Bus
from ..bus.sensing_msgs import advertise
from ..errors import ConfigError, IsacTwinError
from ..robots import build_robots
from ..scene.twin_scene import load_scene
from .lifecycle import StopSignals, bounded_stop, exit_now
from .main import error_line
from .options import scene_arg, scene_path

__all__ = ["COMMANDS", "cmd_robot", "cmd_topics", "ROBOT_STOP_TIMEOUT_S"]

#: Longest the robot runtime's shutdown may take after a stop request, s.
ROBOT_STOP_TIMEOUT_S = 10.0

log = logging.getLogger(__name__)


def _robot_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=Path,
                   help="robot.toml (see engine/devices/runtime.py, docs/network.md)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")


def _open_runtime(cfg, path: Path):
    """The robot runtime of ``cfg`` (its zenoh session open).

    Raises:
        ConfigError: zenoh refuses the [network] endpoints (e.g. an address in use).
    """
    from ..devices.runtime import RobotRuntime  # imports zenoh

    try:
        return RobotRuntime(cfg)
    except Exception as exc:  # noqa: BLE001 - zenoh's errors have no narrower type
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        first = first.split(" at /")[0]  # zenoh appends its Rust source locations
        raise ConfigError(f"{path}: [network] listen = {cfg.network.listen}, connect = "
                          f"{cfg.network.connect}: zenoh could not open a session: "
                          f"{first}") from None


def cmd_robot(args) -> int:
    """Run the robot runtime (drivers, estimation, control, topics on zenoh) until
    SIGINT/SIGTERM or ``--duration``; print a summary per device."""
    from ..devices.runtime import load_robot_config  # the runtime imports zenoh

    cfg = load_robot_config(args.config)
    code = 0
    error: IsacTwinError | None = None
    with StopSignals(dump_stacks_on=signal.SIGUSR1) as life:
        life.starting = True  # a second signal while starting ends the process at once
        rt = _open_runtime(cfg, args.config)
        try:
            rt.start()
            life.starting = False
            if life.stop.is_set():
                print("isac-twin robot: signal during start-up; stopping", file=sys.stderr,
                      flush=True)
            else:
                print(f"isac-twin robot: {cfg.name} ({cfg.model}"
                      f"{', emulated' if cfg.emulated else ''}) up, zenoh "
                      f"{rt.transport.zid()} listen {cfg.network.listen} connect "
                      f"{cfg.network.connect}", flush=True)
                rt.run(args.duration, life.stop)  # wakes for signals whichever thread got them
        except IsacTwinError as exc:  # main prints it, once the runtime has stopped
            error = exc
        except Exception as exc:  # noqa: BLE001 - end cleanly, say what happened
            log.exception("robot runtime failed")
            print(error_line(f"robot runtime failed: {exc}"), file=sys.stderr)
            code = 1
        finally:
            life.starting = False
            stalled = not bounded_stop(rt.stop, ROBOT_STOP_TIMEOUT_S, "isac-twin robot",
                                       stage=lambda: getattr(rt, "stop_stage", "?"))
    print(f"isac-twin robot: stopped ({rt.stats})", flush=True)
    for line in rt.device_summaries():
        print(f"isac-twin robot:   {line}", flush=True)
    if stalled and error is not None:  # main would not get to print it
        print(error_line(str(error)), file=sys.stderr)
        code = 2
    if stalled:  # a stuck driver or transport thread must not keep the process alive
        exit_now(code)
    if error is not None:
        raise error
    return code


def _topics_args(p: argparse.ArgumentParser) -> None:
    scene_arg(p)
    p.add_argument("--steps", type=int, default=0,
                   help="run the robots this many 50 ms steps first (fills MSGS; the LiDAR "
                        "then loads the scene into Mitsuba)")
    p.add_argument("--seed", type=int, default=0, help="seed of the robots' noise")


def cmd_topics(args) -> int:
    """List the topic bus registry of a twin's robots (nodes, topics, types)."""
    scene = load_scene(scene_path(args), load_sionna=False)
    bus = Bus()
    agents = build_robots(scene.config, bus, scene, seed=args.seed)
    if scene.config.sensing:  # the twin's [[sensing]] radar publishes detections + tracks
        advertise(bus)
    dt = 0.05
    for k in range(max(args.steps, 0)):
        for a in agents.values():
            a.step((k + 1) * dt, dt)
    print(f"scene {scene.config.scene.name}: {len(agents)} robots "
          f"({', '.join(agents) or 'none'}), {max(args.steps, 0)} steps")
    print(bus.registry().table())
    return 0


#: command -> (adds its options to a sub-parser, runs it: args -> exit status)
COMMANDS = {
    "robot": (_robot_args, cmd_robot),
    "topics": (_topics_args, cmd_topics),
}
