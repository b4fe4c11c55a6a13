"""``fingerprints``, ``localize`` (alias ``casestudy``): the fingerprint database of a scene
and the paper's localization case study on it."""

from __future__ import annotations

import argparse
import json
import tomllib
from pathlib import Path

from ..errors import UsageError
from ..experiments.casestudy import run_case_study
from ..localization.fingerprints import cache_path, cached_database
from ..scene.config import LOCALIZATION_METHODS
from ..scene.twin_scene import load_scene
from .options import (
    check_cluster_options,
    cluster_args,
    input_errors,
    scene_arg,
    scene_path,
    tiled_tracer,
    uses_cluster,
)

__all__ = ["COMMANDS", "cmd_fingerprints", "cmd_localize", "parse_path_option"]


def _fingerprint_args(p: argparse.ArgumentParser) -> None:
    scene_arg(p)
    p.add_argument("--spacing", type=float, default=0.05, help="grid spacing, m (default 0.05)")
    p.add_argument("--cache-dir", type=Path, default=Path("out/cache"),
                   help="where databases are cached (default out/cache)")
    p.add_argument("--rebuild", action="store_true", help="trace again even if cached")
    cluster_args(p)


def cmd_fingerprints(args) -> int:
    """Build (or find in the cache) the fingerprint database of a scene."""
    if not args.spacing > 0:
        raise UsageError(f"--spacing {args.spacing}: expected a positive size in m")
    check_cluster_options(args)
    scene = load_scene(scene_path(args))
    kw = {}
    if uses_cluster(args):
        kw = {"progress": True, "grid_tracer": tiled_tracer(
            args, cache_path(scene, args.spacing, args.cache_dir))}
    with input_errors():
        db = cached_database(scene, spacing=args.spacing, cache_dir=args.cache_dir,
                             rebuild=args.rebuild, **kw)
    free = int(db.arrays["free"].sum())
    print(f"{db.path}: {free} free points of a {args.spacing:g} m grid, APs "
          f"{', '.join(db.ap_names)}, scene hash {db.scene_hash[:16]}")
    return 0


def _localize_args(p: argparse.ArgumentParser) -> None:
    scene_arg(p)
    p.add_argument("--path", default=None,
                   help="the robot's path instead of its [devices.path], as a TOML inline "
                        "table or JSON object, e.g. '{kind = \"circle\", centre = [4, 3], "
                        "radius = 1.5}' (kinds: circle, polyline, figure_eight, goal)")
    p.add_argument("--out", type=Path, default=Path("out/localize"),
                   help="output folder for figures, table.md, metrics.json "
                        "(default out/localize)")
    p.add_argument("--spacing", type=float, default=0.05,
                   help="fingerprint grid spacing, m (default 0.05, the paper's)")
    p.add_argument("--steps", type=int, default=None,
                   help="deployment steps (default: one lap of a closed path, or to its end)")
    p.add_argument("--table-points", type=int, default=12,
                   help="test points along the path for the static table (default 12)")
    p.add_argument("--snr", type=float, action="append", default=None,
                   help="pilot SNR of the static table, dB (repeat; default 0 10 20 30)")
    p.add_argument("--no-closed-loop", action="store_true",
                   help="skip the closed-loop realistic run")
    p.add_argument("--closed-loop-method", default="MCA-angles",
                   choices=LOCALIZATION_METHODS,
                   help="localizer of the closed-loop run (default MCA-angles)")
    p.add_argument("--closed-loop-fusion", default="ekf", choices=("ekf", "blend"),
                   help="closed loop: EKF over odometry with gated fixes (default) or the "
                        "complementary filter (blend; the earlier run: --closed-loop-method "
                        "PDP --closed-loop-fusion blend)")
    p.add_argument("--cache-dir", type=Path, default=Path("out/cache"),
                   help="where databases are cached (default out/cache)")
    p.add_argument("--seed", type=int, default=0)


def parse_path_option(text: str) -> dict:
    """``--path`` text (a TOML inline table or a JSON object) -> a dict.

    Raises:
        UsageError: neither parses.
    """
    try:
        return json.loads(text)
    except ValueError:
        pass
    try:
        return tomllib.loads(f"path = {text}")["path"]
    except tomllib.TOMLDecodeError as exc:
        raise UsageError(f"--path: expected a TOML inline table or a JSON object, "
                         f"got {text!r} ({exc})") from None


def cmd_localize(args) -> int:
    """The paper's case study on a scene folder: fingerprint database, deployment loop
    (paper mode and closed loop), static localizer table, figures, metrics.json."""
    for key, v, ok in (("--spacing", args.spacing, args.spacing > 0),
                       ("--steps", args.steps, args.steps is None or args.steps > 0),
                       ("--table-points", args.table_points, args.table_points > 0)):
        if not ok:
            raise UsageError(f"{key} {v}: expected a positive number")
    path = parse_path_option(args.path) if args.path is not None else None
    run_case_study(scene_path(args), args.out, spacing=args.spacing, steps=args.steps,
                   seed=args.seed, cache_dir=args.cache_dir, table_points=args.table_points,
                   snrs=tuple(args.snr) if args.snr else (0.0, 10.0, 20.0, 30.0),
                   closed_loop=not args.no_closed_loop, path=path,
                   closed_loop_method=args.closed_loop_method,
                   closed_loop_fusion=args.closed_loop_fusion)
    print(f"outputs in {args.out}/")
    return 0


#: command -> (adds its options to a sub-parser, runs it: args -> exit status)
COMMANDS = {
    "fingerprints": (_fingerprint_args, cmd_fingerprints),
    "localize": (_localize_args, cmd_localize),
    "casestudy": (_localize_args, cmd_localize),
}
