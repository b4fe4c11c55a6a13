"""A bundled room end to end: ``python -m isac_twin.experiments.demo [--scene NAME|DIR] [--out DIR] [--quick]``.

1. Export the bundled room (default the lab) from
   ``blend_scenes/<name>/<name>.blend`` with the Blender add-on (``bpy`` in a
   subprocess) to ``<out>/scene``; ``--scene DIR`` (any exported scene
   folder) skips this step.
2. Load it in the engine, trace the AP -> robot links once and print a
   summary (objects, materials, paths per link).
3. The paper's section IV case study on it (:func:`isac_twin.experiments.casestudy.run_case_study`):
   fingerprint database (built once, cached in ``out/cache``), deployment loop
   in the paper's mode, a closed-loop run in the realistic mode, the
   comparison table, figures and ``metrics.json`` in ``<out>``.

Prints the wall time of every part and of the whole demo.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

from ..scene.bundled import bundled_scene_dir, bundled_scenes, scenes_root

#: the repository in a source checkout: ``addon/`` beside ``blend_scenes/``
ROOT = scenes_root().parent
BLEND = scenes_root() / "aces_lab" / "aces_lab.blend"

_EXPORT = r"""
import json, sys
sys.path.insert(0, {root!r})
import bpy
bpy.ops.wm.open_mainfile(filepath={blend!r})
import addon
from addon.exporter import export_scene
registered = hasattr(bpy.types.Scene, "isac")
if not registered:
    addon.register()
try:
    rep = export_scene(bpy.context, {folder!r})
    print("EXPORT " + json.dumps({{"objects": rep.objects, "materials": rep.materials,
                                   "devices": rep.devices, "links": [list(l) for l in rep.links],
                                   "warnings": list(rep.warnings)}}))
finally:
    if not registered:
        addon.unregister()
"""


def bundled_blend(name: str = "aces_lab") -> Path:
    """The .blend of bundled room ``name`` (``blend_scenes/<name>/<name>.blend``)."""
    return scenes_root() / name / f"{name}.blend"


def export_bundled(folder: Path, python: str | None = None, blend: Path = BLEND) -> dict:
    """Export a bundled .blend with the add-on in a ``bpy`` subprocess -> its report."""
    py = python or sys.executable
    code = _EXPORT.format(root=str(ROOT), blend=str(blend), folder=str(folder))
    r = subprocess.run([py, "-c", code], capture_output=True, text=True, cwd=ROOT)
    line = next((x for x in r.stdout.splitlines() if x.startswith("EXPORT ")), None)
    if r.returncode or line is None:
        raise RuntimeError(f"exporting {blend} with the add-on failed (exit {r.returncode}):\n"
                           f"{r.stdout[-2000:]}\n{r.stderr[-4000:]}")
    return json.loads(line[len("EXPORT "):])


def trace_summary(folder: Path) -> str:
    """Load the scene folder, trace every link once, describe it."""
    from ..raytrace import device_poses, make_tracer
    from ..raytrace.base import SPEED_OF_LIGHT
    from ..scene.twin_scene import load_scene

    scene = load_scene(folder)
    cfg = scene.config
    mats = Counter(o.material for o in scene.objects.values())
    t = time.perf_counter()
    links = make_tracer(cfg)(scene, device_poses(cfg))
    dt = time.perf_counter() - t
    lines = [f"scene {cfg.scene.name!r}: {len(scene.objects)} objects, materials "
             + ", ".join(f"{m} x{n}" for m, n in sorted(mats.items()))
             + f"; {len(cfg.devices)} devices; {cfg.scene.frequency_hz / 1e9:g} GHz, "
             f"{cfg.ofdm.num_subcarriers} x {cfg.ofdm.subcarrier_spacing_hz / 1e3:g} kHz",
             f"traced {len(links)} links in {dt:.2f} s:"]
    for (tx, rx), lp in links.items():
        los = lp.num_paths and (lp.interactions[0] == 0).all()
        p = abs(lp.a) ** 2
        lines.append(f"  {tx} -> {rx}: {lp.num_paths} paths, shortest "
                     f"{SPEED_OF_LIGHT * lp.tau.min():.2f} m ({'LOS' if los else 'NLOS'}), "
                     f"total gain {10 * math.log10(p.sum()):.1f} dB")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m isac_twin.experiments.demo", description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="aces_lab",
                    help="a bundled room's name (a folder of blend_scenes/, exported from its "
                         ".blend) or any scene folder (used as is); default aces_lab")
    ap.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    ap.add_argument("--steps", type=int, default=None,
                    help="deployment steps (default: one lap of the robot's path)")
    ap.add_argument("--quick", action="store_true",
                    help="20 cm database grid, 40 steps, 6 table points (a smoke run)")
    ap.add_argument("--spacing", type=float, default=None,
                    help="database grid spacing in m (default 0.05, the paper's)")
    ap.add_argument("--cache", default="out/cache", help="database cache folder")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-export", action="store_true",
                    help="use the bundled scene folder instead of exporting the .blend")
    ap.add_argument("-v", "--verbose", action="store_true")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if a.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    t0 = time.perf_counter()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    folder = out / "scene"
    blend = bundled_blend(a.scene)
    if a.scene not in bundled_scenes():  # not a bundled room's name: a scene folder
        folder = Path(a.scene)
        if not (folder / "twin.toml").is_file() and not folder.name.endswith(".toml"):
            print(f"demo: error: --scene {a.scene}: neither a bundled room "
                  f"({', '.join(bundled_scenes())}) nor a scene folder with a twin.toml",
                  file=sys.stderr)
            return 2
        print(f"[1/3] scene folder {folder} (no export)")
    elif a.skip_export or not blend.is_file() or not (ROOT / "addon").is_dir():
        folder = bundled_scene_dir(a.scene)
        why = "--skip-export" if a.skip_export else "no .blend and add-on in this install"
        print(f"[1/3] the bundled scene folder {folder} ({why}: no export)")
    else:
        t = time.perf_counter()
        rep = export_bundled(folder.resolve(), blend=blend)
        print(f"[1/3] exported {blend.name} with the add-on -> {folder} in "
              f"{time.perf_counter() - t:.1f} s: {len(rep['objects'])} objects, "
              f"materials {rep['materials']}, devices {rep['devices']}")
    t = time.perf_counter()
    from ..errors import ConfigError

    try:
        summary = trace_summary(folder)
    except ConfigError as exc:
        print(f"demo: error: {exc}", file=sys.stderr)
        return 2
    print("[2/3] " + summary + f"  ({time.perf_counter() - t:.1f} s with loading)")

    from .casestudy import run_case_study

    spacing = a.spacing or (0.2 if a.quick else 0.05)
    steps = a.steps if a.steps is not None else (40 if a.quick else None)
    print(f"[3/3] case study (section IV) on {folder}, database grid {spacing * 100:g} cm")
    try:
        run_case_study(folder, out, spacing=spacing, steps=steps, seed=a.seed, cache_dir=a.cache,
                       table_points=6 if a.quick else 12,
                       closed_loop_steps=steps if steps is not None else None,
                       snrs=(0.0, 10.0, 20.0, 30.0))
    except ConfigError as exc:
        print(f"demo: error: {exc}", file=sys.stderr)
        return 2
    wall = time.perf_counter() - t0
    print(f"demo wall time: {wall:.1f} s ({wall / 60:.1f} min); outputs in {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
