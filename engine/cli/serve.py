"""``serve``: run the twin and stream it to Blender viewers over the live link."""

from __future__ import annotations

import argparse
import importlib
import os
from pathlib import Path

from ..errors import UsageError
from ..live.protocol import wire
from ..live.radiomap_feed import RadioMapFeed
from ..live.server import LiveServer, is_loopback
from ..transport.record import TrajectoryReplay, read_metadata
from ..twin import Twin
from .lifecycle import StopSignals, wait_for_stop
from .options import input_errors, scene_arg, scene_path

__all__ = ["COMMANDS", "cmd_serve", "serve_token", "twin_factory"]


def _serve_args(p: argparse.ArgumentParser) -> None:
    scene_arg(p)
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1; others need --token)")
    p.add_argument("--port", type=int, default=8765, help="TCP port (0 = any free port)")
    p.add_argument("--token", default=None,
                   help="shared secret viewers must send (visible in `ps`: prefer "
                        "--token-file or the ISAC_TWIN_TOKEN environment variable)")
    p.add_argument("--token-file", type=Path, default=None,
                   help="read the shared secret from this file (first line)")
    p.add_argument("--asset-dir", type=Path, action="append", default=[],
                   help="a folder `add` edits may name meshes in by absolute path "
                        "(repeatable; relative paths are always inside the scene folder)")
    p.add_argument("--rate", type=float, default=10.0,
                   help="at most this many steps per second (0 = as fast as possible)")
    p.add_argument("--steps", type=int, default=None, help="pause after this many steps")
    p.add_argument("--linger", type=float, default=None,
                   help="with --steps: exit this many seconds after the last step")
    p.add_argument("--paused", action="store_true", help="start paused (wait for run/step)")
    p.add_argument("--max-paths", type=int, default=None,
                   help="ray polylines per link sent to viewers (strongest first)")
    p.add_argument("--seed", type=int, default=0, help="seed of the twin's noise")
    p.add_argument("--twin", default=None,
                   help="twin factory MODULE:ATTR with .from_scene(path, seed=) "
                        "(default isac_twin.twin.twin:Twin)")
    p.add_argument("--port-file", type=Path, default=None,
                   help="write the port listened on to this file once listening")
    p.add_argument("--step-log", type=Path, default=None,
                   help="append a JSON line per step (poses, path counts, SNR)")
    p.add_argument("--radiomap", type=float, default=None, metavar="CELL",
                   help="stream a floor radio map with cells of CELL m (e.g. 0.25), "
                        "recomputed after edits")
    p.add_argument("--radiomap-samples", type=int, default=200_000,
                   help="rays per access point of the streamed radio map")
    p.add_argument("--replay", type=Path, default=None, metavar="RUN.mcap",
                   help="drive the robots along a recording of `isac-twin record` (its time "
                        "step and seed; the viewer sees the recorded run re-traced)")


def twin_factory(spec: str | None):
    """The class of ``--twin MODULE:ATTR`` (default :class:`~isac_twin.twin.Twin`)."""
    if spec:
        mod, _, attr = spec.partition(":")
        return getattr(importlib.import_module(mod), attr or "Twin")
    return Twin


def serve_token(args) -> str | None:
    """The live link's token: ``--token``, else ``--token-file`` (its first line), else
    the ``ISAC_TWIN_TOKEN`` environment variable; None when none is given.

    Raises:
        UsageError: the token file cannot be read or is empty (naming it).
    """
    if args.token:
        return args.token
    if args.token_file is not None:
        try:
            lines = args.token_file.read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            raise UsageError(f"{args.token_file}: cannot read the token file ({exc})") from None
        token = lines[0].strip() if lines else ""
        if not token:
            raise UsageError(f"{args.token_file}: the token file is empty")
        return token
    return os.environ.get("ISAC_TWIN_TOKEN") or None


def _check(args, token: str | None) -> None:
    """What can be refused before the slow twin load."""
    if not is_loopback(args.host) and not token:
        raise UsageError(f"refusing to listen on non-loopback address {args.host!r} without "
                         "an auth token (pass --token-file, set ISAC_TWIN_TOKEN or --token)")
    for d in args.asset_dir:
        if not d.is_dir():
            raise UsageError(f"--asset-dir {d}: not a folder")


def _replay_settings(path: Path, seed: int) -> tuple[float, int]:
    """``(dt, seed)`` of the recording ``--replay`` names."""
    try:
        meta = read_metadata(path)
        return float(meta.get("dt", 0.05)), int(meta.get("seed", seed))
    except (OSError, ValueError) as exc:
        raise UsageError(f"--replay {path}: cannot read the recording ({exc})") from None


def _start_server(twin, args, token: str | None) -> LiveServer:
    """The live server (and the radio-map feed of ``--radiomap``), listening."""
    feed = None
    with input_errors(types=(ValueError, OSError)):  # OSError: e.g. the port is taken
        if args.radiomap is not None:
            feed = RadioMapFeed(twin, cell_size=args.radiomap,
                                samples_per_tx=args.radiomap_samples)
            feed.prime()
        server = LiveServer(twin, args.host, args.port, token=token, rate_hz=args.rate,
                            max_steps=args.steps, running=not args.paused,
                            max_paths=args.max_paths or wire.DEFAULT_MAX_PATHS_PER_LINK,
                            step_log=args.step_log, on_step=feed)
        if feed is not None:
            feed.publish = server.publish
        server.start()
        try:
            if feed is not None:
                server.publish(feed.last_message)
        except BaseException:
            server.stop()
            raise
    return server


def cmd_serve(args) -> int:
    """Run the twin and stream it to viewers until SIGINT/SIGTERM (or ``--linger`` s
    after ``--steps``)."""
    token = serve_token(args)
    _check(args, token)
    kw = {"asset_dirs": args.asset_dir} if args.asset_dir else {}
    seed = args.seed
    if args.replay is not None:
        kw["dt"], seed = _replay_settings(args.replay, seed)
    twin = twin_factory(args.twin).from_scene(scene_path(args), seed=seed, **kw)
    if args.replay is not None:
        with input_errors("--replay "):
            TrajectoryReplay(twin, args.replay)
    server = _start_server(twin, args, token)
    with StopSignals() as life:
        host, port = server.address
        if args.port_file is not None:
            tmp = args.port_file.with_suffix(".tmp")
            tmp.write_text(f"{port}\n")
            tmp.replace(args.port_file)
        print(f"isac-twin serve: listening on {host}:{port} ({type(twin).__name__}, "
              f"scene {twin.scene.config.scene.name}, protocol "
              f"{'.'.join(map(str, wire.PROTOCOL_VERSION))})", flush=True)
        try:
            wait_for_stop(life.stop, done=server.done, linger_s=args.linger)
        finally:
            server.stop()
    print(f"isac-twin serve: stopped after {server.steps_done} steps", flush=True)
    return 0


#: command -> (adds its options to a sub-parser, runs it: args -> exit status)
COMMANDS = {"serve": (_serve_args, cmd_serve)}
