"""Export and load time of the bundled lab, each against a baseline of the same run.

* export: ``addon.exporter.export_scene`` (validation + PLY/XML/TOML, without and
  with the DAE/STL/USD interchange files) vs. Blender's own PLY exporter writing
  the same objects into one file (``bpy.ops.wm.ply_export``);
* load: ``isac_twin.scene.twin_scene.load_scene`` (validation of every file, then Sionna) vs.
  plain ``sionna.rt.load_scene(scene.xml, merge_shapes=False)``.

Export runs in a subprocess with ``bpy`` (Blender and Mitsuba are kept in
separate processes, as a user's workflow has them).

    .venv/bin/python bench/bench_export.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

EXPORT_SCRIPT = r"""
import json, statistics, sys, tempfile, time
from pathlib import Path
sys.path.insert(0, {root!r})
import bpy
import addon
from addon.exporter import export_scene
bpy.ops.wm.open_mainfile(filepath={blend!r})
addon.register()
out = {{"ours": [], "ours_interchange": [], "blender_ply": []}}
with tempfile.TemporaryDirectory() as tmp:
    for i in range({repeat}):
        t = time.perf_counter(); export_scene(bpy.context.scene, Path(tmp) / f"a{{i}}", interchange=False)
        out["ours"].append(time.perf_counter() - t)
        t = time.perf_counter(); export_scene(bpy.context.scene, Path(tmp) / f"b{{i}}", interchange=True)
        out["ours_interchange"].append(time.perf_counter() - t)
        bpy.ops.object.select_all(action="SELECT")
        t = time.perf_counter()
        bpy.ops.wm.ply_export(filepath=str(Path(tmp) / f"c{{i}}.ply"), export_selected_objects=True,
                              apply_modifiers=True, export_triangulated_mesh=True)
        out["blender_ply"].append(time.perf_counter() - t)
print("RESULT " + json.dumps(out))
"""


def _median_ms(xs):
    return 1e3 * statistics.median(xs)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    blend = ROOT / "blend_scenes/aces_lab/aces_lab.blend"

    code = EXPORT_SCRIPT.format(root=str(ROOT), blend=str(blend), repeat=args.repeat)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")), None)
    if proc.returncode or line is None:
        print(proc.stdout[-2000:], proc.stderr[-2000:], file=sys.stderr)
        return 1
    ex = json.loads(line[len("RESULT "):])
    ours, inter, base = (_median_ms(ex[k]) for k in ("ours", "ours_interchange", "blender_ply"))
    print(f"export bundled lab (median of {args.repeat}):")
    print(f"  export_scene (PLY+XML+TOML)        {ours:8.1f} ms")
    print(f"  export_scene + DAE/STL/USD         {inter:8.1f} ms")
    print(f"  baseline: Blender's PLY exporter   {base:8.1f} ms")
    print(f"  ratio ours / baseline              {ours / base:8.2f}x")

    sys.path.insert(0, str(ROOT))
    import sionna.rt as rt

    import isac_twin  # noqa: F401  (LLVM for Dr.Jit)
    from isac_twin import load_scene

    folder = isac_twin.bundled_scene_dir()
    load_scene(folder)  # warm-up: first Mitsuba/Dr.Jit use
    ours_l, plain_l = [], []
    for _ in range(args.repeat):
        t = time.perf_counter()
        load_scene(folder)
        ours_l.append(time.perf_counter() - t)
        t = time.perf_counter()
        rt.load_scene(str(folder / "scene.xml"), merge_shapes=False)
        plain_l.append(time.perf_counter() - t)
    a, b = _median_ms(ours_l), _median_ms(plain_l)
    print(f"load bundled lab (median of {args.repeat}, after warm-up):")
    print(f"  isac_twin.scene.twin_scene.load_scene            {a:8.1f} ms")
    print(f"  baseline: sionna.rt.load_scene     {b:8.1f} ms")
    print(f"  ratio ours / baseline              {a / b:8.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
