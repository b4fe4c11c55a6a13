"""``isac-twin``: the engine's command line. Thin: parse, call, print.

Subcommands register themselves in :data:`COMMANDS` via :func:`command`;
each gets an ``argparse`` sub-parser and returns an exit code.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Callable
from pathlib import Path

from ..errors import ConfigError
from ..scene.bundled import bundled_scene_dir
from ..scene.config import LOCALIZATION_METHODS

__all__ = ["COMMANDS", "build_parser", "command", "main"]

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
    from ..robots.control import controller_from_spec
    from ..scene.twin_scene import load_scene

    scene = load_scene(scene_path(args))
    cfg = scene.config
    bounds = (scene.bounds_min[:2], scene.bounds_max[:2])
    for i, d in enumerate(cfg.devices):  # the check Twin makes when it builds the robots
        if d.kind == "robot" and d.path is not None:
            try:
                controller_from_spec(d.path, d.model or "burger", bounds=bounds)
            except ValueError as exc:
                raise ConfigError(f"{cfg.path}: devices[{i}] ({d.name}).path: {exc}") from None
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
        if d.is_tx:
            print(f"    resources: subcarriers [{d.subcarriers[0]}, {d.subcarriers[1]}), "
                  f"symbols [{d.symbols[0]}, {d.symbols[1]})")
        if d.path is not None:
            print(f"    path: {d.path}")
    for lk in cfg.links:
        print(f"  link {lk.tx} -> {lk.rx}")
    return 0


def _trace_args(p: argparse.ArgumentParser) -> None:
    _scene_arg(p)
    p.add_argument("--out", type=Path, default=None,
                   help="write the paths: .json (per-link summary) or .npz (full arrays)")


@command("trace", "trace all links of a scene once and print a per-link table", _trace_args)
def cmd_trace(args) -> int:
    import json

    import numpy as np

    from ..raytrace import device_poses, make_tracer
    from ..scene.twin_scene import load_scene

    scene = load_scene(scene_path(args))
    cfg = scene.config
    if args.out is not None and args.out.suffix not in (".json", ".npz"):
        print(f"isac-twin: error: --out {args.out}: expected a .json or .npz file",
              file=sys.stderr)
        return 2
    try:
        res = make_tracer(cfg)(scene, device_poses(cfg))
    except ValueError as exc:
        print(f"isac-twin: error: {exc}", file=sys.stderr)
        return 2
    print(f"{cfg.scene.name}: {len(res)} links traced with backend {cfg.tracer.backend!r} "
          f"at {cfg.scene.frequency_hz / 1e9:g} GHz")
    print(f"  {'link':<24} {'paths':>5} {'LOS':>4} {'LOS delay ns':>13} {'dist m':>7} "
          f"{'strongest dB':>13} {'total dB':>9}")
    rows = []
    for lp in res.values():
        s = lp.summary()
        rows.append(s)
        los = f"{s['los_delay_s'] * 1e9:13.4f}" if s["los"] else f"{'-':>13}"
        strong = s["strongest_path_gain_db"]
        total = s["total_gain_db"]
        print(f"  {lp.tx + ' -> ' + lp.rx:<24} {s['num_paths']:>5} {'yes' if s['los'] else 'no':>4} "
              f"{los} {s['distance_m']:7.3f} "
              f"{strong if strong is None else round(strong, 2):>13} "
              f"{total if total is None else round(total, 2):>9}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        if args.out.suffix == ".json":
            doc = {"scene": cfg.scene.name, "scene_hash": scene.content_hash(),
                   "frequency_hz": cfg.scene.frequency_hz, "backend": cfg.tracer.backend,
                   "links": rows}
            args.out.write_text(json.dumps(doc, indent=2) + "\n")
        else:
            arrays = {}
            for (tx, rx), lp in res.items():
                for k in ("a", "tau", "doppler", "theta_t", "phi_t", "theta_r", "phi_r",
                          "vertices", "interactions", "tx_position", "rx_position",
                          "tx_orientation", "rx_orientation"):
                    arrays[f"{tx}->{rx}/{k}"] = getattr(lp, k)
            np.savez(args.out, links=np.array(json.dumps(rows)), **arrays)
        print(f"wrote {args.out}")
    return 0


def _grid_args(p: argparse.ArgumentParser) -> None:
    _scene_arg(p)
    p.add_argument("--spacing", type=float, default=0.05, help="grid spacing, m (default 0.05)")
    p.add_argument("--height", type=float, default=None,
                   help="receiver height z, m (default: the first robot's antenna height)")
    p.add_argument("--margin", type=float, default=0.0,
                   help="distance kept from the room's bounding box, m")
    p.add_argument("--tx", action="append", default=None,
                   help="transmitter to trace (repeatable; default: all link transmitters)")
    p.add_argument("--chunk-size", type=int, default=None,
                   help="receivers per solver call (method sbr)")
    p.add_argument("--method", choices=("auto", "chains", "sbr"), default=None,
                   help="chains: every chain of the transmitters enumerated once, the "
                        "image method for every point; sbr: shoot-and-bounce for every "
                        "point (default: tracer.method of twin.toml)")
    p.add_argument("--deterministic", action="store_true",
                   help="use Sionna's deterministic generator (needs much more memory)")
    p.add_argument("--verify", type=int, default=8,
                   help="re-trace this many points one per call and report missing paths")
    p.add_argument("--compress", action="store_true", help="write a compressed NPZ")
    p.add_argument("--out", type=Path, required=True, help="output grid file (.npz)")
    _cluster_args(p)


def _cluster_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="trace tiles on a local Dask cluster of N single-threaded worker "
                        "processes (see docs/scaleout.md)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="trace tiles on a running Dask cluster (e.g. tcp://host:8786); the "
                        "scene folder must be at the same path on every worker")
    p.add_argument("--tile-size", type=int, default=None,
                   help="free points per tile (--workers/--scheduler; a multiple of the "
                        "1024-point chunk, default one chunk)")


def cluster_options(args) -> str | None:
    """Why ``--workers``/``--scheduler``/``--tile-size`` are refused (None: fine)."""
    from ..scaleout.cluster import check_cluster_args

    try:
        check_cluster_args(args.workers, args.scheduler)
    except ValueError as exc:
        return str(exc)
    if args.tile_size is not None and args.tile_size < 1:
        return f"--tile-size {args.tile_size}: expected at least 1 point per tile"
    if args.tile_size is not None and args.workers is None and args.scheduler is None:
        return "--tile-size: only with --workers or --scheduler"
    return None


def tiled_tracer(args, checkpoints: Path):
    """``trace_grid``'s stand-in that traces on the cluster of ``--workers`` /
    ``--scheduler`` (started, or connected to, only when a grid is traced)."""
    from ..scaleout.cluster import cluster_client, trace_grid_tiled

    def trace(*a, **kw):
        with cluster_client(args.workers, args.scheduler) as client:
            return trace_grid_tiled(*a, client=client, checkpoints=checkpoints,
                                    tile_size=args.tile_size, **kw)

    return trace


@command("grid", "trace a floor grid of receiver positions and store it (NPZ)", _grid_args)
def cmd_grid(args) -> int:
    import time

    from ..errors import TruncationError
    from ..raytrace.grid import grid_summary, save_grid, trace_grid
    from ..scene.twin_scene import load_scene

    refused = cluster_options(args)
    if refused:
        print(f"isac-twin: error: {refused}", file=sys.stderr)
        return 2
    scene = load_scene(scene_path(args))
    t0 = time.perf_counter()
    distributed = args.workers is not None or args.scheduler is not None
    method = args.method or scene.config.tracer.method
    uses_chains = scene.config.tracer.uses_chains if method == "auto" else method == "chains"
    if distributed and not uses_chains:  # before a cluster starts
        print("isac-twin: error: --workers/--scheduler trace grids with chain reuse only "
              f"(method {method!r}); trace 'sbr' grids without them", file=sys.stderr)
        return 2
    tracer = trace_grid
    if distributed:
        from ..scaleout.checkpoint import checkpoint_dir

        tracer = tiled_tracer(args, checkpoint_dir(args.out))
    try:
        g = tracer(scene, args.tx, spacing=args.spacing, height=args.height,
                   margin=args.margin, chunk_size=args.chunk_size,
                   method=args.method,
                   deterministic=True if args.deterministic else None,
                   verify=args.verify)
    except (ValueError, TruncationError) as exc:
        print(f"isac-twin: error: {exc}", file=sys.stderr)
        return 2
    save_grid(g, args.out, compress=args.compress)
    s = grid_summary(g)
    print(f"grid {s['shape'][0]} x {s['shape'][1]} at {s['spacing']:g} m, z={s['height']:.3f} m: "
          f"{s['free']}/{s['points']} points in free space, {s['mean_paths_per_link']:.1f} "
          f"paths per link on average (max {s['max_paths_per_link']}), "
          f"{s['truncation_retries']} truncation retries, {time.perf_counter() - t0:.1f} s")
    v = s["verification"]
    if distributed:
        so = g.meta["scaleout"]
        print(f"traced on {so['workers']} workers: {so['tiles_traced']} tiles of "
              f"{so['tile_size']} points ({so['tiles_resumed']} resumed from checkpoints)")
    if v.get("points"):
        print(f"verification: {v['points']} points re-traced one per call: "
              f"{v['paths_missing']} of {v['paths_single_calls']} paths missing in the grid, "
              f"{v.get('paths_extra', 0)} extra ({v.get('paths_grazing', 0)} more on an "
              f"edge), {v.get('paths_repeated', 0)} repeated")
    print(f"wrote {args.out}")
    return 0


def _radiomap_args(p: argparse.ArgumentParser) -> None:
    _scene_arg(p)
    p.add_argument("--out", type=Path, required=True,
                   help="output folder: radiomap.npz and radiomap.png")
    p.add_argument("--cell", type=float, default=0.25, help="cell size, m (default 0.25)")
    p.add_argument("--height", type=float, default=None,
                   help="plane height z, m (default: the first robot's antenna height)")
    p.add_argument("--samples", type=int, default=None,
                   help="rays launched per access point (default: "
                        "isac_twin.radiomap.radio_map.DEFAULT_SAMPLES, 0.5 s for the lab at 5 cm)")
    p.add_argument("--tx", action="append", default=None,
                   help="access point to map (repeatable; default: every access point)")


@command("radiomap", "floor radio map per access point (Sionna RadioMapSolver): NPZ + PNG",
         _radiomap_args)
def cmd_radiomap(args) -> int:
    import time

    import numpy as np

    from ..radiomap.figure import cut_footprints, save_radio_map_png
    from ..radiomap.radio_map import DEFAULT_SAMPLES, compute_radio_map, save_radio_map
    from ..scene.twin_scene import load_scene

    scene = load_scene(scene_path(args))
    t0 = time.perf_counter()
    try:
        rm = compute_radio_map(scene, args.tx, cell_size=args.cell, height=args.height,
                               samples_per_tx=DEFAULT_SAMPLES if args.samples is None
                               else args.samples)
    except ValueError as exc:
        print(f"isac-twin: error: {exc}", file=sys.stderr)
        return 2
    dt = time.perf_counter() - t0
    npz = save_radio_map(rm, args.out / "radiomap.npz")
    png = save_radio_map_png(rm, args.out / "radiomap.png",
                             footprints=cut_footprints(scene, rm.height))
    ny, nx = rm.shape
    print(f"radio map {nx} x {ny} cells of {rm.cell_size:g} m at z={rm.height:.3f} m, "
          f"{len(rm.tx_names)} access points, {dt:.2f} s")
    for i, n in enumerate(rm.tx_names):
        r = rm.rss_dbm[i]
        ok = np.isfinite(r)
        print(f"  {n}: RSS {np.median(r[ok]):.1f} dBm median, {r[ok].max():.1f} max; "
              f"best server in {int((rm.best_server == i).sum())} cells; "
              f"{int(np.isneginf(r).sum())} free cells without a ray")
    print(f"  {int((~rm.free).sum())} of {nx * ny} cells inside walls or furniture (NaN)")
    print(f"wrote {npz} and {png}")
    return 0


def _run_args(p: argparse.ArgumentParser) -> None:
    _scene_arg(p)
    p.add_argument("--steps", type=int, default=100, help="steps to run (default 100)")
    p.add_argument("--rate", type=float, default=None,
                   help="pace the loop at this many steps per second in real time "
                        "(default: as fast as possible); prints the overruns and the "
                        "stage that caused each")
    p.add_argument("--dt", type=float, default=0.05, help="simulated time per step, s")
    p.add_argument("--seed", type=int, default=0, help="seed of every random stream")
    p.add_argument("--no-phy", action="store_true", help="skip channels and rates")
    p.add_argument("--timing", action="store_true", help="print the per-stage timing table")
    _radar_arg(p)


def _radar_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--radar", choices=("auto", "thread", "process", "sync"), default="auto",
                   help="where the [[sensing]] radar computes its frames: a worker thread, "
                        "a child process (the twin's steps do not wait behind a frame), "
                        "or the stepping thread (each frame on its own step); auto "
                        "(default): process with --rate, thread otherwise")


def _radar_kw(args) -> dict:
    """The Twin keywords of ``--radar`` (and ``--rate``)."""
    radar = args.radar if args.radar != "auto" else ("process" if args.rate else "thread")
    return {"sync_sensing": radar == "sync", "sensing_process": radar == "process"}


def _radar_refused(args) -> bool:
    """``--radar`` named for a scene without a radar: say so (exit 2), not ignore it;
    read from the config, before a twin is built."""
    if args.radar == "auto":
        return False
    from ..scene.config import load_config

    cfg = load_config(scene_path(args))
    if cfg.sensing:
        return False
    print(f"isac-twin: error: --radar {args.radar}: {cfg.path} has no [[sensing]] radar",
          file=sys.stderr)
    return True


def _radar_line(frame) -> str:
    """``radar (step k) N det M tracks`` of a delivered radar frame (a ``SensingStep``)."""
    n = sum(len(v) for v in frame.detections.values())
    return f"radar (step {frame.step}) {n} det {len(frame.tracks)} tracks"


@command("run", "run the twin (Algorithm 1) for N steps and print a per-step line", _run_args)
def cmd_run(args) -> int:
    from ..twin.twin import Twin

    if args.steps < 0:
        print(f"isac-twin: error: --steps {args.steps}: expected >= 0", file=sys.stderr)
        return 2
    if args.rate is not None and not args.rate > 0:
        print(f"isac-twin: error: --rate {args.rate}: expected a positive rate in Hz",
              file=sys.stderr)
        return 2
    if _radar_refused(args):
        return 2
    twin = Twin.from_scene(scene_path(args), seed=args.seed, dt=args.dt, phy=not args.no_phy,
                           **_radar_kw(args))
    for r in twin.run(args.steps, rate_hz=args.rate):
        parts = [f"step {r.step:4d} t={r.time_s:6.2f}s"]
        for name, rb in r.robots.items():
            parts.append(f"{name} ({rb.pose[0]:.2f}, {rb.pose[1]:.2f}) yaw {rb.pose[5]:+.2f}")
        for (tx, rx), ls in r.links.items():
            parts.append(f"{tx}->{rx} {ls.paths.num_paths if ls.paths else 0} paths"
                         + ("" if args.no_phy else f" {ls.rate_bps / 1e6:.0f} Mbit/s"
                            f" (MCS {ls.mcs_rate_bps / 1e6:.0f})"))
        if r.sensing is not None:  # a [[sensing]] radar frame was delivered this step
            parts.append(_radar_line(r.sensing))
        print("  ".join(parts), flush=True)
    last = twin.flush_sensing()  # a frame still computed off the stepping thread
    twin.close()
    if last is not None:
        print(_radar_line(last), flush=True)
    if args.rate is not None:
        st = twin.stats
        print(f"paced at {args.rate:g} Hz: {st.steps} steps in {st.wall_s:.2f} s, "
              f"{st.overrun_summary()}", flush=True)
    if args.timing:
        print(twin.stats.table())
    return 0


def _fingerprint_args(p: argparse.ArgumentParser) -> None:
    _scene_arg(p)
    p.add_argument("--spacing", type=float, default=0.05, help="grid spacing, m (default 0.05)")
    p.add_argument("--cache-dir", type=Path, default=Path("out/cache"),
                   help="where databases are cached (default out/cache)")
    p.add_argument("--rebuild", action="store_true", help="trace again even if cached")
    _cluster_args(p)


@command("fingerprints", "build (or find in the cache) the fingerprint database of a scene: "
         "the multipath delay profile of every AP on a floor grid", _fingerprint_args)
def cmd_fingerprints(args) -> int:
    from ..localization.fingerprints import cache_path, cached_database
    from ..scene.twin_scene import load_scene

    if not args.spacing > 0:
        print(f"isac-twin: error: --spacing {args.spacing}: expected a positive size in m",
              file=sys.stderr)
        return 2
    refused = cluster_options(args)
    if refused:
        print(f"isac-twin: error: {refused}", file=sys.stderr)
        return 2
    scene = load_scene(scene_path(args))
    kw = {}
    if args.workers is not None or args.scheduler is not None:
        from ..scaleout.checkpoint import checkpoint_dir

        kw = {"progress": True, "grid_tracer": tiled_tracer(
            args, checkpoint_dir(cache_path(scene, args.spacing, args.cache_dir)))}
    try:
        db = cached_database(scene, spacing=args.spacing, cache_dir=args.cache_dir,
                             rebuild=args.rebuild, **kw)
    except ValueError as exc:
        print(f"isac-twin: error: {exc}", file=sys.stderr)
        return 2
    free = int(db.arrays["free"].sum())
    print(f"{db.path}: {free} free points of a {args.spacing:g} m grid, APs "
          f"{', '.join(db.ap_names)}, scene hash {db.scene_hash[:16]}")
    return 0


def _localize_args(p: argparse.ArgumentParser) -> None:
    _scene_arg(p)
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


def parse_path_option(text: str):
    """``--path`` text (TOML inline table or JSON object) -> a dict, or ConfigError."""
    import json
    import tomllib

    try:
        return json.loads(text)
    except ValueError:
        pass
    try:
        return tomllib.loads(f"path = {text}")["path"]
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"--path: expected a TOML inline table or a JSON object, "
                          f"got {text!r} ({exc})") from None


@command("localize", "the paper's case study on a scene folder: fingerprint database, "
         "deployment loop (paper mode and closed loop), static localizer table, figures, "
         "metrics.json; the robot follows its [devices.path]", _localize_args)
def cmd_localize(args) -> int:
    from ..experiments.casestudy import run_case_study

    for key, v, ok in (("--spacing", args.spacing, args.spacing > 0),
                       ("--steps", args.steps, args.steps is None or args.steps > 0),
                       ("--table-points", args.table_points, args.table_points > 0)):
        if not ok:
            print(f"isac-twin: error: {key} {v}: expected a positive number", file=sys.stderr)
            return 2
    from ..errors import PathError

    path = parse_path_option(args.path) if args.path is not None else None
    try:
        run_case_study(scene_path(args), args.out, spacing=args.spacing, steps=args.steps,
                       seed=args.seed, cache_dir=args.cache_dir, table_points=args.table_points,
                       snrs=tuple(args.snr) if args.snr else (0.0, 10.0, 20.0, 30.0),
                       closed_loop=not args.no_closed_loop, path=path,
                       closed_loop_method=args.closed_loop_method,
                       closed_loop_fusion=args.closed_loop_fusion)
    except PathError as exc:  # a path the robot cannot follow (too tight, leaves the room)
        print(f"isac-twin: error: path: {exc}", file=sys.stderr)
        return 2
    print(f"outputs in {args.out}/")
    return 0


COMMANDS["casestudy"] = ("the same as 'localize'", _localize_args, cmd_localize)


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


def _topics_args(p: argparse.ArgumentParser) -> None:
    _scene_arg(p)
    p.add_argument("--steps", type=int, default=0,
                   help="run the robots this many 50 ms steps first (fills MSGS; the LiDAR "
                        "then loads the scene into Mitsuba)")
    p.add_argument("--seed", type=int, default=0, help="seed of the robots' noise")


@command("topics", "list the topic bus registry of a twin's robots (nodes, topics, types)",
         _topics_args)
def cmd_topics(args) -> int:
    from ..bus.bus import Bus
    from ..robots import build_robots
    from ..scene.twin_scene import load_scene

    scene = load_scene(scene_path(args), load_sionna=False)
    bus = Bus()
    agents = build_robots(scene.config, bus, scene, seed=args.seed)
    if scene.config.sensing:  # the twin's [[sensing]] radar publishes detections + tracks
        from ..sensing.msgs import advertise

        advertise(bus)
    dt = 0.05
    for k in range(max(args.steps, 0)):
        for a in agents.values():
            a.step((k + 1) * dt, dt)
    print(f"scene {scene.config.scene.name}: {len(agents)} robots "
          f"({', '.join(agents) or 'none'}), {max(args.steps, 0)} steps")
    print(bus.registry().table())
    return 0


def _serve_args(p: argparse.ArgumentParser) -> None:
    _scene_arg(p)
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


def _twin_factory(spec: str | None):
    import importlib

    if spec:
        mod, _, attr = spec.partition(":")
        return getattr(importlib.import_module(mod), attr or "Twin")
    from ..twin.twin import Twin

    return Twin


def serve_token(args) -> str | None:
    """The live link's token: ``--token``, else ``--token-file`` (its first line), else
    the ``ISAC_TWIN_TOKEN`` environment variable; None when none is given.

    Raises:
        ValueError: the token file cannot be read or is empty (naming it).
    """
    if args.token:
        return args.token
    if args.token_file is not None:
        try:
            lines = args.token_file.read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"{args.token_file}: cannot read the token file ({exc})") from None
        token = lines[0].strip() if lines else ""
        if not token:
            raise ValueError(f"{args.token_file}: the token file is empty")
        return token
    return os.environ.get("ISAC_TWIN_TOKEN") or None


@command("serve", "run the twin and stream it to Blender viewers over TCP", _serve_args)
def cmd_serve(args) -> int:
    import signal
    import threading

    from ..live.protocol import wire
    from ..live.server import LiveServer, is_loopback

    try:
        token = serve_token(args)
    except ValueError as exc:
        print(f"isac-twin: error: {exc}", file=sys.stderr)
        return 2
    if not is_loopback(args.host) and not token:  # before the slow twin load
        print(f"isac-twin: error: refusing to listen on non-loopback address {args.host!r} "
              "without an auth token (pass --token-file, set ISAC_TWIN_TOKEN or --token)",
              file=sys.stderr)
        return 2
    for d in args.asset_dir:
        if not d.is_dir():
            print(f"isac-twin: error: --asset-dir {d}: not a folder", file=sys.stderr)
            return 2
    factory = _twin_factory(args.twin)
    kw = {"asset_dirs": args.asset_dir} if args.asset_dir else {}
    seed = args.seed
    if args.replay is not None:
        from ..transport.record import read_metadata

        try:
            meta = read_metadata(args.replay)
            kw["dt"] = float(meta.get("dt", 0.05))
            seed = int(meta.get("seed", seed))
        except (OSError, ValueError) as exc:
            print(f"isac-twin: error: --replay {args.replay}: cannot read the recording "
                  f"({exc})", file=sys.stderr)
            return 2
    twin = factory.from_scene(scene_path(args), seed=seed, **kw)
    if args.replay is not None:
        from ..transport.record import TrajectoryReplay

        try:
            TrajectoryReplay(twin, args.replay)
        except ValueError as exc:
            print(f"isac-twin: error: --replay {exc}", file=sys.stderr)
            return 2
    feed = None
    try:
        if args.radiomap is not None:
            from ..live.radiomap_feed import RadioMapFeed

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
        if feed is not None:
            server.publish(feed.last_message)
    except (ValueError, OSError, wire.WireError) as exc:
        print(f"isac-twin: error: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    host, port = server.address
    if args.port_file is not None:
        tmp = args.port_file.with_suffix(".tmp")
        tmp.write_text(f"{port}\n")
        tmp.replace(args.port_file)
    print(f"isac-twin serve: listening on {host}:{port} ({type(twin).__name__}, "
          f"scene {twin.scene.config.scene.name}, protocol "
          f"{'.'.join(map(str, wire.PROTOCOL_VERSION))})", flush=True)
    try:
        while not stop.is_set():
            if args.linger is not None and server.done.is_set():
                stop.wait(args.linger)
                break
            stop.wait(0.2)
    finally:
        server.stop()
    print(f"isac-twin serve: stopped after {server.steps_done} steps", flush=True)
    return 0


# ---------------------------------------------------------------- network: robot, record, replay

def _robot_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=Path, help="robot.toml (see engine/devices/runtime.py, docs/network.md)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")


@command("robot", "run the robot runtime: drivers, estimation, control, topics on zenoh",
         _robot_args)
def cmd_robot(args) -> int:
    import signal
    import threading

    from ..devices.runtime import RobotRuntime, load_robot_config
    from ..errors import RobotConfigError

    try:
        cfg = load_robot_config(args.config)
    except RobotConfigError as exc:
        print(f"isac-twin: error: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    starting = [True]

    def on_signal(signum, frame):  # noqa: ARG001
        # Only flag the stop: an exception raised from here could land inside
        # zenoh or a lock and be lost or re-raised at exit. Start-up is short
        # and the runtime stops as soon as it is up; a second signal while it
        # is still starting ends the process at once.
        if stop.is_set() and starting[0]:
            os._exit(128 + signum)
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    # `kill -USR1 PID` prints every thread's stack to stderr (works even while a
    # native call holds the GIL): how a stuck robot process says where it is.
    import faulthandler
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    rt = None
    code = 0
    try:
        try:
            rt = RobotRuntime(cfg)
        except Exception as exc:  # noqa: BLE001 - zenoh refuses the endpoints (e.g. address in use)
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            first = first.split(" at /")[0]  # zenoh appends its Rust source locations
            print(f"isac-twin: error: {args.config}: [network] listen = {cfg.network.listen}, connect = "
                  f"{cfg.network.connect}: zenoh could not open a session: {first}", file=sys.stderr)
            return 2
        rt.start()
        starting[0] = False
        if stop.is_set():
            print("isac-twin robot: signal during start-up; stopping", file=sys.stderr, flush=True)
        else:
            print(f"isac-twin robot: {cfg.name} ({cfg.model}{', emulated' if cfg.emulated else ''}) up, "
                  f"zenoh {rt.transport.zid()} listen {cfg.network.listen} connect "
                  f"{cfg.network.connect}", flush=True)
            rt.run(args.duration, stop)  # wakes for signals whichever thread got them
    except Exception as exc:  # noqa: BLE001 - end cleanly, say what happened
        logging.getLogger("isac_twin.cli").exception("robot runtime failed")
        print(f"isac-twin: error: robot runtime failed: {exc}", file=sys.stderr)
        code = 1
    finally:
        starting[0] = False
        stalled = rt is not None and not _bounded_stop(rt, ROBOT_STOP_TIMEOUT_S)
    if rt is not None:
        print(f"isac-twin robot: stopped ({rt.stats})", flush=True)
        for line in rt.device_summaries():
            print(f"isac-twin robot:   {line}", flush=True)
    if stalled:  # a stuck driver or transport thread must not keep the process alive
        sys.stderr.flush()
        os._exit(code)
    return code


#: Longest the robot runtime's shutdown may take after a stop request, s.
ROBOT_STOP_TIMEOUT_S = 10.0


def _bounded_stop(rt, timeout_s: float) -> bool:
    """``rt.stop()`` in a helper thread; False (and one line on stderr naming the
    shutdown stage it is stuck in) when it does not finish within ``timeout_s``."""
    import threading

    t = threading.Thread(target=rt.stop, name="robot-stop", daemon=True)
    t.start()
    t.join(timeout_s)
    if not t.is_alive():
        return True
    print(f"isac-twin robot: warning: shutdown did not finish in {timeout_s:g} s (stuck in "
          f"{getattr(rt, 'stop_stage', '?')}); exiting anyway", file=sys.stderr, flush=True)
    return False


def _record_args(p: argparse.ArgumentParser) -> None:
    _scene_arg(p)
    p.add_argument("--steps", type=int, default=100, help="twin steps to run (default 100)")
    p.add_argument("--out", type=Path, required=True, help="output .mcap")
    p.add_argument("--rate", type=float, default=None, help="steps per second (default: max)")
    p.add_argument("--seed", type=int, default=0, help="seed of the twin's noise")
    p.add_argument("--compression", choices=("none", "zstd", "lz4"), default="zstd")
    p.add_argument("--stamps", choices=("sim", "wall"), default="sim",
                   help="header stamps and log times: simulated s from 0 (default) or "
                        "wall clock (Unix epoch of the start + simulated s)")
    p.add_argument("--csi", choices=("compact", "full"), default="compact",
                   help="CSI: 1 symbol in 14, 1 subcarrier in 16 (default) or everything")
    p.add_argument("--csi-snr", type=float, default=None, metavar="DB",
                   help="add white Gaussian noise to the recorded CSI at this SNR (dB; "
                        "seeded by --seed): a measured channel estimate")
    p.add_argument("--connect", action="append", default=None,
                   help="zenoh endpoint of real robots to mirror (repeatable), "
                        "e.g. tcp/127.0.0.1:7448")
    p.add_argument("--share", action="store_true",
                   help="also publish every twin topic on zenoh (rmw_zenoh format, "
                        "wall-clock stamps) for ROS 2 nodes; needs --connect")
    p.add_argument("--share-prefix", default="/twin",
                   help="prefix of shared topic names (default /twin; '' keeps the names)")
    _radar_arg(p)


@command("record", "run the twin and record all its topics, link metrics and paths to MCAP",
         _record_args)
def cmd_record(args) -> int:
    import time

    from ..transport.record import CsiRecording, record_twin
    from ..twin.twin import Twin

    if args.share and not args.connect:
        print("isac-twin: error: --share needs --connect (the zenoh router or peer to "
              "publish to)", file=sys.stderr)
        return 2
    try:
        noise = {"snr_db": args.csi_snr, "seed": args.seed}
        csi = CsiRecording(**noise) if args.csi == "compact" else CsiRecording.full(**noise)
    except ValueError as exc:
        print(f"isac-twin: error: --csi-snr: {exc}", file=sys.stderr)
        return 2
    if _radar_refused(args):
        return 2
    twin = Twin.from_scene(scene_path(args), seed=args.seed, **_radar_kw(args))
    bridge = None
    if args.connect:
        from ..transport.bridge import TwinBridge
        from ..transport.zenoh_transport import ZenohConfig, ZenohTransport

        transport = ZenohTransport(ZenohConfig(connect=args.connect))
        try:
            bridge = TwinBridge(twin, transport, share="all" if args.share else None,
                                share_prefix=args.share_prefix)
        except ValueError as exc:
            transport.close()
            print(f"isac-twin: error: {exc}", file=sys.stderr)
            return 2
    try:
        rec = record_twin(twin, args.steps, args.out, rate_hz=args.rate,
                          compression=args.compression, bridge=bridge,
                          stamp_epoch_s=time.time() if args.stamps == "wall" else 0.0,
                          csi=csi)
    finally:
        if bridge is not None:
            bridge.close()
        twin.close()  # (record_twin kept the last radar frame)
    print(f"recorded {rec.messages} messages of {args.steps} steps to {args.out}")
    return 0


def _recover_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", type=Path, help="an .mcap whose writer was killed")
    p.add_argument("--out", type=Path, default=None,
                   help="output (default <name>.recovered.mcap next to it)")


@command("recover", "rewrite a killed recording's complete chunks as a finished MCAP",
         _recover_args)
def cmd_recover(args) -> int:
    from ..transport.record import recover

    try:
        out, n = recover(args.recording, args.out)
    except (OSError, ValueError) as exc:
        print(f"isac-twin: error: {exc}", file=sys.stderr)
        return 2
    print(f"recovered {n} messages of {args.recording} to {out}")
    return 0


def _replay_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", type=Path, help="an .mcap written by `isac-twin record`")
    p.add_argument("--scene", type=Path, default=None,
                   help="scene folder (default: the one named in the recording)")
    p.add_argument("--speed", type=float, default=1.0,
                   help="pace relative to the recording (0 = as fast as possible)")
    p.add_argument("--steps", type=int, default=None, help="steps (default: the recording's)")
    p.add_argument("--bus-only", action="store_true",
                   help="only re-publish the messages on a bus and print the topic table")
    p.add_argument("--serve", type=int, default=None, metavar="PORT",
                   help="stream the replaying twin to Blender viewers on 127.0.0.1:PORT")


@command("replay", "replay an MCAP recording: drive a twin along the recorded trajectories",
         _replay_args)
def cmd_replay(args) -> int:
    from ..transport.record import TrajectoryReplay, read_metadata, replay_to_bus

    if args.bus_only:
        from ..bus.bus import Bus

        bus = Bus()
        n = replay_to_bus(args.recording, bus, speed=args.speed or None)
        print(f"replayed {n} messages")
        print(bus.registry().table())
        return 0
    from ..twin.twin import Twin

    meta = read_metadata(args.recording)
    scene = args.scene or (Path(meta["scene"]) if meta.get("scene") else None)
    if scene is None:
        print("isac-twin: error: the recording names no scene: pass --scene", file=sys.stderr)
        return 2
    dt = float(meta.get("dt", 0.05))
    twin = Twin.from_scene(scene, seed=int(meta.get("seed", 0)), dt=dt)
    try:
        rp = TrajectoryReplay(twin, args.recording)
    except ValueError as exc:
        print(f"isac-twin: error: {exc}", file=sys.stderr)
        return 2
    steps = args.steps if args.steps is not None else rp.steps
    rate = args.speed / dt if args.speed else None
    if args.serve is not None:
        from ..live.server import LiveServer

        server = LiveServer(twin, "127.0.0.1", args.serve, rate_hz=rate or 0.0, max_steps=steps)
        server.start()
        print(f"isac-twin replay: serving on 127.0.0.1:{server.address[1]}", flush=True)
        try:
            while not server.done.wait(0.2):  # short waits: Ctrl-C is handled at once
                pass
        finally:
            server.stop()
        return 0
    for res in twin.run(steps, rate_hz=rate):
        poses = "  ".join(f"{n} ({r.pose[0]:.2f}, {r.pose[1]:.2f})" for n, r in res.robots.items())
        snr = "  ".join(f"{tx}->{rx} {ls.snr_db:.1f} dB" for (tx, rx), ls in res.links.items())
        print(f"step {res.step:4d} t={res.time_s:7.2f} s  {poses}  {snr}")
    return 0


def _calibrate_args(p: argparse.ArgumentParser) -> None:
    _scene_arg(p)
    p.add_argument("--measurements", type=Path, required=True,
                   help="an .mcap written by `isac-twin record` (/<robot>/csi and "
                        "/<robot>/ground_truth)")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder: scene/ (calibrated) and calibration.json")
    p.add_argument("--params", default="materials",
                   help="comma-separated: materials, poses (default materials)")
    p.add_argument("--objects", default="", help="comma-separated objects whose x, y, yaw "
                                                 "offsets are fitted (with --params poses)")
    p.add_argument("--materials", default="",
                   help="comma-separated materials fitted with --params materials: ITU "
                        "type, custom name or TYPE-THICKNESS such as wood-0.03 (default: "
                        "every material but metal)")
    p.add_argument("--links", default=None, metavar="TX,RX[;TX,RX...]",
                   help="the recorded links to use (default: every recorded link)")
    p.add_argument("--snapshots", type=int, default=6,
                   help="CSI messages used per link (default 6)")
    p.add_argument("--subcarriers", type=int, default=16,
                   help="recorded subcarriers used (default 16)")
    p.add_argument("--max-steps", type=int, default=30, help="optimiser iterations per start")
    p.add_argument("--pose-scan", action="store_true",
                   help="scan each fitted x/y/yaw offset (lambda/8 steps within +-10 cm, "
                        "1 deg within +-5 deg) before fitting, against local minima")
    p.add_argument("--no-scan", action="store_true",
                   help="start at the scene's permittivities (no scan, single start)")
    p.add_argument("--no-hop", action="store_true",
                   help="with poses: after the pose polish, do not scan the x/y offsets of "
                        "the objects with a clear path across the next half-wavelength "
                        "basins (shifts of 0.3-0.6 wavelength in wavelength/12 steps)")
    p.add_argument("--no-noise", action="store_true",
                   help="compare the model's exact power (default: each snapshot's noise, "
                        "estimated from the delay-domain tail of all its recorded "
                        "subcarriers, is added to the model's power)")


@command("calibrate", "fit materials and object poses of a scene to recorded CSI "
                      "(Sionna gradients)", _calibrate_args)
def cmd_calibrate(args) -> int:
    from ..calibration.run import calibrate_recording
    from ..errors import CalibrationError

    links = None
    if args.links is not None:
        links = [tuple(p.strip() for p in lk.split(",")) for lk in args.links.split(";")]
        if not links or any(len(lk) != 2 or not all(lk) for lk in links):
            print(f"isac-twin: error: --links: expected TX,RX[;TX,RX...], got {args.links!r}",
                  file=sys.stderr)
            return 2
    what = tuple(w.strip() for w in args.params.split(",") if w.strip())
    objects = [o.strip() for o in args.objects.split(",") if o.strip()]
    if not args.measurements.is_file():
        print(f"isac-twin: error: --measurements {args.measurements}: no such file",
              file=sys.stderr)
        return 2
    try:
        run = calibrate_recording(scene_path(args), args.measurements, args.out, what=what,
                                  objects=objects, links=links, max_snapshots=args.snapshots,
                                  max_subcarriers=args.subcarriers, max_steps=args.max_steps,
                                  scan=not args.no_scan, pose_scan=args.pose_scan,
                                  hop=not args.no_hop, noise=not args.no_noise,
                                  materials=[m.strip() for m in args.materials.split(",")
                                             if m.strip()] or None)
    except CalibrationError as exc:
        print(f"isac-twin: error: {exc}", file=sys.stderr)
        return 2
    r = run.report
    for p in r["parameters"]:
        print(f"{p['name']:32s} {p['initial']:12.6g} -> {p['final']:12.6g}")
    m = r["mismatch_db2"]
    print(f"mismatch {m['initial']:.4g} -> {m['final']:.4g} dB^2, "
          f"{'converged' if r['converged'] else 'NOT converged'} ({r['message']}), "
          f"{r['evaluations']} evaluations at {r['seconds_per_step']:.2f} s")
    if r["unobserved"]:
        print(f"not seen by the measurements: {', '.join(r['unobserved'])}")
    for name, mat in r["materials_written"].items():
        print(f"material {name}: eps_r {mat['relative_permittivity']:.6g}, sigma "
              f"{mat['conductivity']:.6g} S/m, {mat['thickness']:g} m")
    print(f"wrote {run.scene_dir} and {run.report_path}")
    return 0
