"""``info``, ``trace``, ``grid``, ``radiomap``: a scene folder checked, traced once, traced
on a floor grid, mapped."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ..errors import ConfigError, UsageError
from ..radiomap.figure import cut_footprints, save_radio_map_png
from ..radiomap.radio_map import DEFAULT_SAMPLES, compute_radio_map, save_radio_map
from ..raytrace import device_poses, make_tracer
from ..raytrace.grid import grid_summary, save_grid, trace_grid
from ..robots.control import controller_from_spec
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

__all__ = ["COMMANDS", "cmd_info", "cmd_trace", "cmd_grid", "cmd_radiomap"]


def cmd_info(args) -> int:
    """Load a scene folder, validate it (robot paths too) and print a summary."""
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
    scene_arg(p)
    p.add_argument("--out", type=Path, default=None,
                   help="write the paths: .json (per-link summary) or .npz (full arrays)")


#: The arrays of a link that ``trace --out X.npz`` stores, as ``TX->RX/<name>``.
_NPZ_FIELDS = ("a", "tau", "doppler", "theta_t", "phi_t", "theta_r", "phi_r", "vertices",
               "interactions", "tx_position", "rx_position", "tx_orientation",
               "rx_orientation")


def cmd_trace(args) -> int:
    """Trace every link of a scene once; print a per-link table; write .json/.npz."""
    scene = load_scene(scene_path(args))
    cfg = scene.config
    if args.out is not None and args.out.suffix not in (".json", ".npz"):
        raise UsageError(f"--out {args.out}: expected a .json or .npz file")
    with input_errors():
        res = make_tracer(cfg)(scene, device_poses(cfg))
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
        print(f"  {lp.tx + ' -> ' + lp.rx:<24} {s['num_paths']:>5} "
              f"{'yes' if s['los'] else 'no':>4} {los} {s['distance_m']:7.3f} "
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
            arrays = {f"{tx}->{rx}/{k}": getattr(lp, k)
                      for (tx, rx), lp in res.items() for k in _NPZ_FIELDS}
            np.savez(args.out, links=np.array(json.dumps(rows)), **arrays)
        print(f"wrote {args.out}")
    return 0


def _grid_args(p: argparse.ArgumentParser) -> None:
    scene_arg(p)
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
    cluster_args(p)


def cmd_grid(args) -> int:
    """Trace a floor grid of receiver positions (locally or on a Dask cluster); store it."""
    check_cluster_options(args)
    scene = load_scene(scene_path(args))
    t0 = time.perf_counter()
    distributed = uses_cluster(args)
    method = args.method or scene.config.tracer.method
    uses_chains = scene.config.tracer.uses_chains if method == "auto" else method == "chains"
    if distributed and not uses_chains:  # before a cluster starts
        raise UsageError("--workers/--scheduler trace grids with chain reuse only "
                         f"(method {method!r}); trace 'sbr' grids without them")
    tracer = tiled_tracer(args, args.out) if distributed else trace_grid
    with input_errors():
        g = tracer(scene, args.tx, spacing=args.spacing, height=args.height,
                   margin=args.margin, chunk_size=args.chunk_size,
                   method=args.method,
                   deterministic=True if args.deterministic else None,
                   verify=args.verify)
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
    scene_arg(p)
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


def cmd_radiomap(args) -> int:
    """A floor radio map per access point (Sionna's RadioMapSolver): NPZ and PNG."""
    scene = load_scene(scene_path(args))
    t0 = time.perf_counter()
    with input_errors():
        rm = compute_radio_map(scene, args.tx, cell_size=args.cell, height=args.height,
                               samples_per_tx=DEFAULT_SAMPLES if args.samples is None
                               else args.samples)
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


#: command -> (adds its options to a sub-parser, runs it: args -> exit status)
COMMANDS = {
    "info": (scene_arg, cmd_info),
    "trace": (_trace_args, cmd_trace),
    "grid": (_grid_args, cmd_grid),
    "radiomap": (_radiomap_args, cmd_radiomap),
}
