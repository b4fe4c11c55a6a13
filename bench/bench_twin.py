"""Twin step rate of the bundled lab with full PHY (issue #4: >= 20 steps/s).

The bundled lab (``blend_scenes/aces_lab/scene``): AP1 (4 x 8 = 32 antennas) and
AP2 (1 x 1) to robot1 (1 x 2) driving the circle centre (4, 3) m, radius 1.5 m;
lidar, IMU and odometry on, camera off; N = 1024 subcarriers, K = 14 symbols.
Two allocations: ``bundled`` (the resource sets of twin.toml, e.g. AP1 on
symbols 0-6 and AP2 on 7-13) and ``overlap`` (both APs on all REs, so each
interferes with the other: the heaviest PHY case). For each PHY variant, a
fresh twin (same seed) runs ``--steps`` steps after ``--warmup`` steps; printed: the per-stage split
(``twin.stats.table()``), steps/s, PHY ms/step, and ratios against the
``reference`` variant (``NetworkPHY(method="reference")``: np.linalg SVD /
slogdet / solve on every RE) measured in the same run.

Variants: ``batched`` (default NetworkPHY: every link of a step in one stacked
pass), ``fast`` (the same closed-form 2 x 2 paths + time-invariant shortcut at
1e-3 rad, one link at a time), ``fast-exact`` (per link, shortcut off),
``reference``. With ``--grid FILE`` (or a ``tracer.grid_file`` in the
scene's config) the ``fast`` variant is repeated with the grid tracer; skipped
otherwise. Rates of the variants are compared on the last step. No assertions
on time.

    .venv/bin/python bench/bench_twin.py [--quick] [--steps 40] [--grid FILE]
    .venv/bin/python bench/bench_twin.py --robots 1,2,4,8,16   # batched vs per-link PHY
    .venv/bin/python bench/bench_twin.py --robots 1,4,16 --split  # + the parts of a step
    .venv/bin/python bench/bench_twin.py --polarization VH    # VH access points vs V
    .venv/bin/python bench/bench_twin.py --sensing --robots 4 [--rate 20]  # radar: off / sync / worker

``--polarization P``: the lab with both access points' arrays set to ``P``
(``VH`` / ``cross``: two ports per element, so AP1 has 64 ports) against the
same lab with ``V``, same seed, default PHY; its ``[[sensing]]`` table is
dropped in both (sensing links model V elements only).

On a shared 2-core machine, ``OPENBLAS_NUM_THREADS=1`` makes every variant
faster and steadier (OpenBLAS threads otherwise wait on descheduled peers).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import isac_twin  # noqa: E402  - configures Dr.Jit's LLVM before mitsuba
from isac_twin import (
    NetworkPHY,  # noqa: E402
    Twin,  # noqa: E402
    load_config,  # noqa: E402
)
from isac_twin.robots import SensorOptions  # noqa: E402
from isac_twin.twin.pacing import STAGES

PATH = {"kind": "circle", "centre": [4.0, 3.0], "radius": 1.5}
VARIANTS = {
    "batched": dict(),
    "fast": dict(method="fast"),
    "fast-exact": dict(method="fast", time_invariant_tol=0.0),
    "reference": dict(method="reference"),
}


def overlap_config(cfg):
    """Every transmitter on all REs of the grid."""
    o = cfg.ofdm
    devs = tuple(dataclasses.replace(d, subcarriers=(0, o.num_subcarriers),
                                     symbols=(0, o.num_symbols)) if d.is_tx else d
                 for d in cfg.devices)
    return dataclasses.replace(cfg, devices=devs)


def run_variant(name: str, steps: int, warmup: int, tracer=None, seed: int = 0,
                overlap: bool = False, sensing: bool = False, folder: Path | None = None,
                sync_sensing: bool = False, rate_hz: float | None = None,
                sensing_process: bool = False) -> dict:
    kw = {"sync_sensing": True} if sync_sensing else {}  # (an older engine lacks the option)
    if sensing_process:
        kw["sensing_process"] = True
    tw = Twin.from_scene(folder or isac_twin.bundled_scene_dir(), seed=seed, tracer=tracer,
                         sensors=SensorOptions(lidar=True, imu=True, odometry=True,
                                               camera=False), sensing=sensing, **kw)
    cfg = overlap_config(tw.config) if overlap else tw.config
    tw.phy = NetworkPHY(cfg, **VARIANTS[name])
    tw.set_path("robot1", PATH)
    for _ in tw.run(warmup):
        pass
    tw.stats = type(tw.stats)()  # measure after the warm-up only
    phy_ms = []
    t0 = time.perf_counter()
    last = None
    for res in tw.run(steps, rate_hz=rate_hz):
        phy_ms.append(1e3 * res.timings_s["phy"])
        last = res
    wall = time.perf_counter() - t0
    return dict(name=name, table=tw.stats.table(), steps_s=steps / wall,
                phy_ms=float(np.mean(phy_ms)), phy_min=float(np.min(phy_ms)),
                stage_ms={s: 1e3 * tw.stats.stage_s[s] / steps for s in STAGES},
                rates={lk: ls.rate_bps for lk, ls in last.links.items()},
                paths={lk: ls.paths for lk, ls in last.links.items()}, config=cfg,
                overruns=tw.stats.overrun_summary(),
                doppler_phase=tw.phy.max_doppler_phase({lk: ls.paths
                                                        for lk, ls in last.links.items()}))


#: Extra robots of the ``--robots`` variant: start pose and circle, in free space
#: (the scene load refuses a pose or path point inside furniture) and clear of
#: robot1's circle (centre (4, 3) m, radius 1.5 m) and of each other; the last 11
#: were found with ``isac_twin.scene.room.path_obstruction`` on a 0.25 m grid of centres.
EXTRA_ROBOTS = [((2.0, 2.5, 0.0), {"kind": "circle", "centre": [1.5, 2.5], "radius": 0.5}),
                ((2.5, 5.0, 0.0), {"kind": "circle", "centre": [2.0, 5.0], "radius": 0.5}),
                ((6.5, 1.0, 0.0), {"kind": "circle", "centre": [6.0, 1.0], "radius": 0.5}),
                ((7.5, 4.0, 0.0), {"kind": "circle", "centre": [7.0, 4.0], "radius": 0.5})] + [
    ((cx + 0.35, cy, 0.0), {"kind": "circle", "centre": [cx, cy], "radius": 0.35})
    for cx, cy in ((4.75, 0.5), (0.5, 1.5), (7.0, 1.75), (6.0, 2.25), (7.0, 2.75),
                   (0.5, 3.0), (2.0, 3.75), (5.75, 4.25), (3.25, 5.0), (4.75, 5.0),
                   (6.5, 5.0))]


def lab_with_robots(n: int, folder: Path) -> Path:
    """A copy of the bundled lab with ``n`` robots (robot1 and n - 1 of
    :data:`EXTRA_ROBOTS`), each the rx of a downlink from both APs."""
    import shutil

    src = isac_twin.bundled_scene_dir()
    shutil.copytree(src, folder, dirs_exist_ok=True)
    text = (folder / "twin.toml").read_text()
    blocks = []
    for k, ((x, y, _), path) in enumerate(EXTRA_ROBOTS[:n - 1], start=2):
        blocks.append(f"""
[[devices]]
name = "robot{k}"
kind = "robot"
role = "rx"
model = "burger"
antenna_offset = [0.0, 0.0, 0.25]
position = [{x}, {y}, 0.0]
orientation = [0.0, 0.0, 1.5707964]
power_dbm = 10.0

[devices.array]
rows = 1
cols = 2

[devices.path]
kind = "circle"
centre = {path["centre"]}
radius = {path["radius"]}
""")
    links = "".join(f'\n[[links]]\ntx = "{ap}"\nrx = "robot{k}"\n'
                    for k in range(2, n + 1) for ap in ("AP1", "AP2"))
    head, sep, tail = text.partition("\n[[links]]")
    (folder / "twin.toml").write_text(head + "".join(blocks) + sep + tail + links)
    return folder


#: ``--split``: the parts of a step timed by profiling (cumulative time of these
#: functions; parts nest: ``bus publish`` includes the ``/tf`` publication of
#: ``tf frames`` and any synchronous subscriber, e.g. a recorder).
def split_parts() -> dict:
    from isac_twin.bus.bus import Node
    from isac_twin.robots.agent import RobotAgent
    from isac_twin.robots.kinematics import DiffDriveRobot
    from isac_twin.robots.sensors import (
        DepthCamera,
        ImuSensor,
        Lidar2D,
        WheelEncoders,
        WheelOdometry,
    )

    return {"kinematics": [DiffDriveRobot.step],
            "controllers": [RobotAgent.control],
            "lidar": [Lidar2D.measure, Lidar2D.discard],
            "camera": [DepthCamera.measure, DepthCamera.discard],
            "imu": [ImuSensor.measure],
            "odometry": [WheelEncoders.measure, WheelOdometry.update],
            "bus publish": [Node.publish],
            "tf frames": [Twin._publish_frames],
            "device poses": [Twin.device_poses]}


def profile_split(tw: Twin, steps: int) -> dict:
    """Run ``steps`` more steps under cProfile -> ``{part: ms per step}`` for
    :func:`split_parts` plus the twin's stages (from its own clock, inflated by
    the profiler like the parts)."""
    import cProfile
    import pstats

    tw.stats = type(tw.stats)()
    prof = cProfile.Profile()
    prof.enable()
    for _ in tw.run(steps):
        pass
    prof.disable()
    table = pstats.Stats(prof).stats  # (file, line, name) -> (cc, nc, tt, ct, callers)
    out = {}
    for part, fns in split_parts().items():
        keys = [(f.__code__.co_filename, f.__code__.co_firstlineno, f.__code__.co_name)
                for f in fns]
        out[part] = 1e3 * sum(table[k][3] for k in keys if k in table) / steps
    out.update({f"stage {st}": 1e3 * tw.stats.stage_s[st] / steps for st in STAGES})
    return out


def run_robots_variant(counts, steps: int, warmup: int, split: bool = False) -> dict:
    """The lab with n robots (2n downlinks) for each n of ``counts``, sensing off.

    Per n, one twin runs ``steps`` steps with the default (batched) PHY, then the
    same twin ``steps`` more with the per-link PHY (``NetworkPHY(method="fast")``,
    the loop before issue #19): steps/s and per-stage ms of both, the PHY alone
    replayed on the last step's paths (batched vs per-link, min of 5) and the
    largest rate difference between them on those paths. Then the marginal cost
    per added link (least-squares slope of ms/step over the link count). With
    ``split``, ``steps`` more batched steps under cProfile give the parts of a
    step (:func:`profile_split`), printed as ms per step and per robot."""
    import tempfile

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in counts:
            folder = (isac_twin.bundled_scene_dir() if n == 1
                      else lab_with_robots(n, Path(tmp) / f"lab{n}"))
            tw = Twin.from_scene(folder, seed=0, sensing=False,
                                 sensors=SensorOptions(lidar=True, imu=True, odometry=True,
                                                       camera=False))
            links = len(tw.config.links)
            row = dict(n=n, links=links)
            for label, method in (("batched", "batched"), ("per-link", "fast")):
                tw.phy = NetworkPHY(tw.config, method=method)
                for _ in tw.run(warmup):
                    pass
                tw.stats = type(tw.stats)()
                t0, c0 = time.perf_counter(), time.process_time()
                for res in tw.run(steps):
                    pass
                wall = time.perf_counter() - t0
                # (getattr: the same bench also measures an older engine as baseline)
                cpu = getattr(tw.stats, "stage_cpu_s", {})
                row[label] = dict(steps_s=steps / wall, ms=1e3 * wall / steps,
                                  proc_cpu=1e3 * (time.process_time() - c0) / steps,
                                  stage={st: 1e3 * tw.stats.stage_s.get(st, 0.0) / steps
                                         for st in STAGES},
                                  cpu={st: 1e3 * cpu.get(st, float("nan")) / steps
                                       for st in STAGES})
                print(f"== {n} robots ({links} links), {label} PHY, {steps} steps\n"
                      f"{tw.stats.table()}", flush=True)
            paths = {lk: ls.paths for lk, ls in res.links.items()}
            sig, replay, replay_cpu = {}, {}, {}
            for method in ("batched", "fast"):
                phy = NetworkPHY(tw.config, method=method)
                sig[method] = phy(paths)
                ts, cs = [], []
                for _ in range(5):
                    t0, c0 = time.perf_counter(), time.process_time()
                    phy(paths)
                    ts.append(1e3 * (time.perf_counter() - t0))
                    cs.append(1e3 * (time.process_time() - c0))
                replay[method], replay_cpu[method] = min(ts), min(cs)
            row["replay"], row["replay_cpu"] = replay, replay_cpu
            if split:
                tw.phy = NetworkPHY(tw.config)
                row["split"] = profile_split(tw, steps)
            row["rate_diff"] = max((abs(sig["batched"][lk].rate_bps / s_.rate_bps - 1)
                                    for lk, s_ in sig["fast"].items() if s_.rate_bps > 0),
                                   default=0.0)
            rows.append(row)
    print(f"\n{'robots':>6} {'links':>5} {'steps/s':>8} {'ms/step':>8} {'agents':>7} "
          f"{'trace':>7} {'phy':>7} {'other':>6} | {'per-link':>8} {'phy':>7} {'x step':>7} | "
          f"{'replay b/p ms':>14} {'x phy':>6} {'rate diff':>9}")
    for r in rows:
        b, p = r["batched"], r["per-link"]
        st = b["stage"]
        other = sum(v for k, v in st.items() if k not in ("agents", "trace", "phy"))
        print(f"{r['n']:6d} {r['links']:5d} {b['steps_s']:8.1f} {b['ms']:8.1f} "
              f"{st['agents']:7.1f} {st['trace']:7.1f} {st['phy']:7.1f} {other:6.1f} | "
              f"{p['steps_s']:8.1f} {p['stage']['phy']:7.1f} "
              f"{b['steps_s'] / p['steps_s']:6.2f}x | "
              f"{r['replay']['batched']:6.1f}/{r['replay']['fast']:6.1f} "
              f"{r['replay']['fast'] / r['replay']['batched']:5.2f}x {r['rate_diff']:9.1e}")
    print("\nthe stepping thread's CPU ms/step (robust to a shared machine's load; "
          "the trace's Dr.Jit kernel threads not counted), batched PHY | PHY replay "
          "process CPU ms, batched / per-link:")
    print(f"{'robots':>6} " + " ".join(f"{st:>8}" for st in STAGES) + f" {'total':>8} | "
          f"{'replay':>14} | {'process CPU ms/step':>19}")
    for r in rows:
        c = r["batched"]["cpu"]
        print(f"{r['n']:6d} " + " ".join(f"{c[st]:8.2f}" for st in STAGES)
              + f" {sum(c.values()):8.2f} | {r['replay_cpu']['batched']:6.1f}/"
              f"{r['replay_cpu']['fast']:6.1f} | {r['batched']['proc_cpu']:19.1f}")
    if split:
        print(f"\nparts of a step under cProfile (batched PHY, {steps} steps; ms/step, "
              "per robot in brackets; parts nest, stages are the twin's own clock):")
        print(f"{'part':<16}" + "".join(f"{str(r['n']) + ' robots':>20}" for r in rows))
        for part in rows[0]["split"]:
            print(f"{part:<16}" + "".join(
                f"{r['split'][part]:11.2f} ({r['split'][part] / r['n']:5.2f})" for r in rows))
    if len(rows) > 1:
        x = np.array([r["links"] for r in rows], float)
        for label in ("batched", "per-link"):
            parts = {k: np.polyfit(x, [r[label]["stage"][k] for r in rows], 1)[0]
                     for k in ("trace", "phy")}
            total = np.polyfit(x, [r[label]["ms"] for r in rows], 1)[0]
            print(f"marginal cost per added link ({label} PHY): {total:.2f} ms/step "
                  f"(trace {parts['trace']:.2f}, PHY {parts['phy']:.2f})")
    return {r["n"]: r for r in rows}


def run_sensing_variant(steps: int, warmup: int, robots: int = 1,
                        rate_hz: float | None = None) -> dict:
    """The lab (with ``robots`` robots) and its ``[[sensing]]`` radar (AP2 -> AP1,
    every 10th step) four ways, same seed, default (batched) PHY: without sensing,
    the radar on the stepping thread (``sync_sensing=True``), on the twin's
    sensing worker thread (the default) and in its own process
    (``sensing_process=True``). Prints the stage tables (the sense stage's wall
    and stepping-thread CPU), steps/s, overruns when paced at ``rate_hz``, and
    each against the twin without sensing."""
    import gc
    import tempfile

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = (isac_twin.bundled_scene_dir() if robots == 1
                  else lab_with_robots(robots, Path(tmp) / f"lab{robots}"))
        for label, on, mode in (("without sensing", False, "thread"),
                                ("radar on the stepping thread", True, "sync"),
                                ("radar on the sensing worker", True, "thread"),
                                ("radar in its own process", True, "process")):
            gc.collect()  # a dead twin's sensing targets would keep this one's trace unfrozen
            r = run_variant("batched", steps, warmup, sensing=on, folder=folder,
                            sync_sensing=mode == "sync", rate_hz=rate_hz,
                            sensing_process=mode == "process")
            out[label] = r
            print(f"== {robots} robot(s), {label} ({steps} steps"
                  + (f", paced at {rate_hz:g} Hz" if rate_hz else "") + f")\n{r['table']}")
            print(f"  -> {r['steps_s']:.1f} steps/s\n", flush=True)
    every = load_config(isac_twin.bundled_scene_dir()).sensing[0].every
    base = out["without sensing"]
    for label in list(out)[1:]:
        r = out[label]
        print(f"{label}: sense stage {r['stage_ms']['sense']:.1f} ms/step wall "
              f"({r['stage_ms']['sense'] * every:.1f} ms per frame, every {every}), "
              f"step rate x{r['steps_s'] / base['steps_s']:.2f} of the twin without sensing; "
              f"{r['overruns']}")
    return out


def lab_with_polarization(pol: str, folder: Path) -> Path:
    """A copy of the bundled lab whose access points have polarization ``pol``
    (and no ``[[sensing]]`` table)."""
    import re
    import shutil

    shutil.copytree(isac_twin.bundled_scene_dir(), folder)
    p = folder / "twin.toml"
    text = re.sub(r"\[\[sensing\]\][^\[]*", "", p.read_text())
    blocks = text.split("[[devices]]")
    for i, b in enumerate(blocks):
        if 'kind = "access_point"' in b:
            blocks[i] = b.replace('polarization = "V"', f'polarization = "{pol}"')
    p.write_text("[[devices]]".join(blocks))
    cfg = load_config(p)
    assert [d.array.polarization for d in cfg.devices if d.kind == "access_point"] \
        == [pol] * 2 and not cfg.sensing
    return folder


def run_polarization_variant(pol: str, steps: int, warmup: int) -> dict:
    """The lab with ``pol`` access points against the same lab with V ones."""
    import tempfile

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for p in ("V", pol):
            r = run_variant("batched", steps, warmup,
                            folder=lab_with_polarization(p, Path(tmp) / p))
            out[p] = r
            print(f"== bundled/batched, access points {p} ({steps} steps)\n{r['table']}")
            print(f"  -> {r['steps_s']:.1f} steps/s, PHY {r['phy_ms']:.1f} ms/step, trace "
                  f"{r['stage_ms']['trace']:.1f} ms/step; rates "
                  + ", ".join(f"{tx}->{rx} {v / 1e6:.0f} Mbit/s"
                              for (tx, rx), v in r["rates"].items()) + "\n", flush=True)
    a, b = out["V"], out[pol]
    print(f"{pol} / V: step time x{a['steps_s'] / b['steps_s']:.2f}, PHY x"
          f"{b['phy_ms'] / a['phy_ms']:.2f}, trace x"
          f"{b['stage_ms']['trace'] / a['stage_ms']['trace']:.2f}")
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="10 steps (reference: 5)")
    ap.add_argument("--grid", type=Path, default=None, help="grid NPZ for the grid tracer")
    ap.add_argument("--variants", default="batched,fast,fast-exact,reference")
    ap.add_argument("--allocations", default="bundled,overlap")
    ap.add_argument("--sensing", action="store_true",
                    help="only the sensing variant (run_sensing_variant): without sensing, "
                         "radar on the stepping thread, on the sensing worker, in its own "
                         "process; with "
                         "--robots N (one count) the lab with N robots, with --rate HZ paced")
    ap.add_argument("--rate", type=float, default=None,
                    help="with --sensing: pace the steps at this rate and count overruns")
    ap.add_argument("--robots", default="",
                    help="only the many-robot variant: comma-separated robot counts, e.g. "
                         "1,2,4,8,16 (the lab with n robots, 2n downlinks; batched vs "
                         f"per-link PHY; at most {1 + len(EXTRA_ROBOTS)} robots)")
    ap.add_argument("--split", action="store_true",
                    help="with --robots: also the parts of a step (kinematics, sensors, "
                         "controllers, bus, ...) from a cProfile run")
    ap.add_argument("--polarization", default="",
                    help="only the polarization variant: the lab's access points with this "
                         "polarization (H, VH, cross) against V")
    args = ap.parse_args(argv)
    if args.polarization:
        if args.polarization not in ("H", "VH", "cross"):
            ap.error(f"--polarization {args.polarization!r}: expected H, VH or cross")
        run_polarization_variant(args.polarization, 10 if args.quick else args.steps,
                                 1 if args.quick else args.warmup)
        return
    if args.sensing:
        n = int(args.robots or 1)
        run_sensing_variant(10 if args.quick else args.steps, 1 if args.quick else args.warmup,
                            robots=n, rate_hz=args.rate)
        return
    if args.robots:
        try:
            counts = [int(c) for c in args.robots.split(",") if c.strip()]
        except ValueError:
            ap.error(f"--robots {args.robots!r}: expected comma-separated integers")
        bad = [c for c in counts if not 1 <= c <= 1 + len(EXTRA_ROBOTS)]
        if bad or not counts:
            ap.error(f"--robots {args.robots!r}: each count must be in "
                     f"1..{1 + len(EXTRA_ROBOTS)}")
        run_robots_variant(counts, 10 if args.quick else args.steps,
                           1 if args.quick else args.warmup, split=args.split)
        return
    steps = 10 if args.quick else args.steps
    names = [v for v in args.variants.split(",") if v]
    results = []
    for alloc in args.allocations.split(","):
        for name in names:
            n = max(4, steps // 2) if name == "reference" else steps
            r = run_variant(name, n, 1 if args.quick else args.warmup,
                            overlap=alloc == "overlap")
            r["name"] = f"{alloc}/{name}"
            results.append(r)
            print(f"== {r['name']} ({n} steps, Sionna tracer)\n{r['table']}")
            print(f"  -> {r['steps_s']:.1f} steps/s, PHY {r['phy_ms']:.1f} ms/step "
                  f"(min {r['phy_min']:.1f}); max Doppler phase drift "
                  f"{r['doppler_phase']:.2e} rad\n", flush=True)
    grid = args.grid
    if grid is None:
        from isac_twin import load_scene

        cfg = load_scene(isac_twin.bundled_scene_dir()).config
        if cfg.tracer.grid_file:
            grid = cfg.folder / cfg.tracer.grid_file
    if grid is not None and Path(grid).exists():
        from isac_twin.raytrace.grid_backend import GridTracer

        try:
            r = run_variant("batched", steps, 1 if args.quick else args.warmup,
                            tracer=GridTracer(grid))
        except Exception as exc:  # a stale / foreign grid file must not kill the bench
            print(f"(grid tracer variant skipped: {type(exc).__name__}: {exc})\n")
        else:
            r["name"] = "bundled/batched+grid"
            results.append(r)
            print(f"== fast, grid tracer {grid}\n{r['table']}")
            print(f"  -> {r['steps_s']:.1f} steps/s, PHY {r['phy_ms']:.1f} ms/step\n")
    else:
        print("(grid tracer variant skipped: no --grid file and no tracer.grid_file)\n")

    print(f"{'variant':<24} {'steps/s':>8} {'phy ms':>8} {'phy min':>8} {'trace ms':>9} "
          f"{'phy speed-up':>13} {'step speed-up':>14}")
    for r in results:
        alloc = r["name"].split("/")[0]
        ref = next((x for x in results if x["name"] == f"{alloc}/reference"), None)
        su = f"{ref['phy_ms'] / r['phy_ms']:12.1f}x" if ref else "-"
        st = f"{r['steps_s'] / ref['steps_s']:13.1f}x" if ref else "-"
        print(f"{r['name']:<24} {r['steps_s']:8.1f} {r['phy_ms']:8.1f} {r['phy_min']:8.1f} "
              f"{r['stage_ms']['trace']:9.1f} {su:>13} {st:>14}")
    # PHY alone, replayed on the last step's paths (no tracer in between): min / median.
    print("\nPHY replay on the last step's paths (ms, min / median):")
    for r in results:
        if not r["name"].endswith("/batched"):
            continue
        line = []
        for name in VARIANTS:
            phy = NetworkPHY(r["config"], **VARIANTS[name])
            reps = 3 if name == "reference" else 11
            phy(r["paths"])
            ts = []
            for _ in range(reps):
                t0 = time.perf_counter()
                phy(r["paths"])
                ts.append(1e3 * (time.perf_counter() - t0))
            line.append((name, min(ts), float(np.median(ts))))
        ref_min = next(m for n, m, _ in line if n == "reference")
        print(f"  {r['name'].split('/')[0]:<9} " + "   ".join(
            f"{n} {m:.1f} / {md:.1f} ({ref_min / m:.0f}x)" for n, m, md in line))
    # Accuracy: the reference PHY on each variant's last-step paths.
    for r in results:
        if r["name"].endswith("/reference"):
            continue
        ref_sig = NetworkPHY(r["config"], method="reference")(r["paths"])
        errs = [abs(r["rates"][lk] / ref_sig[lk].rate_bps - 1) for lk in ref_sig
                if ref_sig[lk].rate_bps > 0]
        print(f"  {r['name']}: last-step rate rel. diff vs reference PHY on the same paths "
              f"{max(errs) if errs else float('nan'):.1e}")


if __name__ == "__main__":
    main()
