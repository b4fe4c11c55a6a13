"""``isac-twin``: the engine's command line. Thin: parse, call, print.

Subcommands register themselves in :data:`COMMANDS` via :func:`command`;
each gets an ``argparse`` sub-parser and returns an exit code.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable
from pathlib import Path

from engine.config import ConfigError
from engine.paths import bundled_scene_dir

COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable]] = {}


def command(name: str, help_: str, configure: Callable[[argparse.ArgumentParser], None]):
    """Register ``fn(args) -> int`` as subcommand ``name``."""

    def wrap(fn):
        COMMANDS[name] = (help_, configure, fn)
        return fn

    return wrap


def _scene_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", type=Path, default=None,
                   help="scene folder or its twin.toml (default: the bundled aces_lab)")


def scene_path(args) -> Path:
    return args.scene if args.scene is not None else bundled_scene_dir()


@command("info", "load a scene folder, validate it and print a summary", _scene_arg)
def cmd_info(args) -> int:
    from engine.scene import load_scene

    scene = load_scene(scene_path(args))
    cfg = scene.config
    print(f"scene {cfg.scene.name}: {cfg.scene.file}")
    print(f"  frequency {cfg.scene.frequency_hz / 1e9:g} GHz, OFDM N={cfg.ofdm.num_subcarriers} "
          f"x {cfg.ofdm.subcarrier_spacing_hz / 1e3:g} kHz, K={cfg.ofdm.num_symbols}")
    lo, hi = scene.bounds_min, scene.bounds_max
    print(f"  extent x {lo[0]:.2f}..{hi[0]:.2f}  y {lo[1]:.2f}..{hi[1]:.2f}  "
          f"z {lo[2]:.2f}..{hi[2]:.2f} m; content hash {scene.content_hash()[:16]}")
    mats: dict[str, list[str]] = {}
    for o in scene.objects.values():
        mats.setdefault(f"{o.material} ({o.thickness:g} m)", []).append(o.name)
    print(f"  {len(scene.objects)} objects, {len(mats)} materials:")
    for m, names in sorted(mats.items()):
        print(f"    {m}: {len(names)} -- {', '.join(names)}")
    for d in cfg.devices:
        print(f"  device {d.name}: {d.kind} {d.role}, {d.array.rows}x{d.array.cols} "
              f"{d.array.polarization} ({d.array.num_ant} ports), {d.power_dbm:g} dBm at "
              f"{tuple(round(x, 3) for x in d.position)}")
    for lk in cfg.links:
        print(f"  link {lk.tx} -> {lk.rx}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="isac-twin", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="log more (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (help_, configure, fn) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        configure(p)
        p.set_defaults(func=fn)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except ConfigError as exc:
        print(f"isac-twin: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
